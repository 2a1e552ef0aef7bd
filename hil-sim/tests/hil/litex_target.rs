//! The firmware on a real soft core's RTL: a LiteX SoC with a VexRiscv CPU simulated cycle for
//! cycle by Verilator (hil-sim's `litex` module), driven through `deform solve`'s own code path.
//!
//! Needs `cargo xtask setup` (Verilator, socat, the LiteX venv) and the LiteX firmware
//! (`cargo xtask firmware --board litex`, or `$DEFORM_LITEX_FIRMWARE`); set-up builds the SoC
//! (about 3 minutes, cached in target/litex; a run without it builds it first). The simulator runs about 0.8 M cycles per
//! second, so the systems here are small.

use crate::support;

use std::time::{Duration, Instant};

use deform_hil_sim::litex::{litex_firmware_elf, LitexConfig, LitexSim};
use deform_host::board::BoardChoice;
use deform_host::link::{open_serial, Link, Target, Timeouts};
use deform_host::model::flags::{ConnectionArg, ModelFlags};
use deform_host::model::{Grid, Node, PointLoad};
use deform_host::solve::solve_model;

use support::{build, deviation_from_reference, plan};

fn start() -> LitexSim {
    LitexSim::start(&LitexConfig::new(litex_firmware_elf()))
        .unwrap_or_else(|e| panic!("cannot start the LiteX SoC: {e}"))
}

#[test]
fn model_b_on_6_cubed_matches_f64_to_1e_8_with_refinement() {
    let args = ModelFlags {
        grid: Some(Grid::new(6, 6, 6).unwrap()),
        connection: Some(ConnectionArg::B),
        load: vec![
            PointLoad {
                node: Node { i: 3, j: 3, k: 5 },
                force: [0.3, -1.0, 0.5],
            },
            PointLoad {
                node: Node { i: 1, j: 4, k: 2 },
                force: [0.0, 0.25, -2.0],
            },
        ],
        ..ModelFlags::default()
    };
    let model = build(&args);
    let plan = plan(
        BoardChoice::Litex {
            firmware: None,
            mvus: 0,
        },
        1e-10,
        8,
        Duration::from_secs(600),
    );
    let started = Instant::now();
    let solved = solve_model(&model, &plan).expect("solve on the LiteX SoC");
    let (rel, scale) = deviation_from_reference(&solved);
    println!(
        "6³ model B on LiteX VexRiscv: max |u| = {scale:.6e}, deviation from f64 {rel:.3e}, \
         {:.1} s wall",
        started.elapsed().as_secs_f64()
    );
    assert!(scale > 0.0);
    assert!(rel <= 1e-8, "deviation {rel:e} of max |u|");
    let engine = solved.stats.engine.as_ref().expect("a target run");
    assert!(engine.target_solves >= 2, "refinement ran: {engine:?}");
    // Real cycles beside instructions: the VexRiscv's CPI is above 1 (cache misses, the
    // multiplier, branches), so a report giving one for the other would be wrong.
    assert!(
        engine.hart0.cycles > engine.hart0.instructions && engine.hart0.instructions > 0,
        "{:?}",
        engine.hart0
    );
    let perf = engine
        .performance
        .as_ref()
        .expect("an iteration was measured");
    for phase in [perf.mvu_critical, perf.svu_critical, perf.critical_path] {
        assert!(phase.cycles > phase.instructions, "{perf:?}");
    }
    assert!(engine.critical_path.cycles > engine.critical_path.instructions);
    println!(
        "first iteration: critical path {} (MVU {} + SVU {})",
        perf.critical_path, perf.mvu_critical, perf.svu_critical
    );
    for d in &solved.stats.directions {
        assert!(d.relative_residual <= 1e-10, "{d:?}");
    }
}

/// Garbage on the line gets an error frame (a NAK naming the request the target waits for),
/// a frame with a wrong CRC too; the firmware keeps serving the session afterwards.
#[test]
fn bad_bytes_are_answered_with_an_error_frame() {
    let sim = start();
    let path = sim.serial_path().to_string_lossy().into_owned();
    let port = open_serial(&path).expect("open the bridge's pty");
    let mut target = Target::handshake(Link::new(port), support::litex_timeouts())
        .unwrap_or_else(|e| panic!("handshake: {e}; simulator:\n{}", sim.output()));
    assert_eq!(target.info().harts, 1, "{:?}", target.info());
    let before = target.stats().naks;
    // Not COBS of any frame: a short frame of junk, and a frame whose CRC is wrong.
    for junk in [
        &[0x05u8, 0x01, 0x02, 0x03, 0x04, 0x00][..],
        &[0x03, 0xFF, 0xEE, 0x00],
    ] {
        target.link_mut().send_raw(junk).unwrap();
    }
    // The next exchange reads the NAKs that arrived meanwhile.
    let matrix = support::banded_spd(16, 1);
    target.upload_matrix(&matrix).unwrap();
    let naks = target.stats().naks - before;
    assert!(
        naks >= 2,
        "{naks} NAK(s) for two bad frames: {:?}",
        target.stats()
    );
    let report = support::solve_matches_f64(&mut target, &matrix, &[1.0; 16], 200);
    // Real cycles: the RTL takes more cycles than it retires instructions.
    assert!(
        report.mvu.cycles > report.mvu.instructions && report.mvu.instructions > 0,
        "{report:?}"
    );
}

/// `deform live` on the soft core: the needle-push example's first frames (8³ model B, one
/// MVU) against converged f64 solves of the same tool position, with real cycles per frame.
#[test]
fn live_frames_on_the_soft_core_match_converged_solves() {
    use deform_host::encode::EncodeOptions;
    use deform_host::live::link::LiveLink;
    use deform_host::live::LiveSetup;
    use deform_host::scenario::Scenario;
    use deform_shared::live::LiveParams;

    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/needle-push-8b.toml");
    let scenario = Scenario::load(&path, None).expect("the example loads");
    let simulation = scenario.simulation.as_ref().expect("a keyframed tool");
    let spec_at = |t: f64| simulation.spec_at(&scenario.model, t);
    let setup = LiveSetup::new(&spec_at(0.0), &EncodeOptions::default()).unwrap();
    let sim = start();
    let path = sim.serial_path().to_string_lossy().into_owned();
    let port = open_serial(&path).expect("open the bridge's pty");
    // A cold first frame is ~11 M cycles: tens of seconds of simulation while the other tests'
    // SoCs share the two cores. LiveFrame is not acknowledged before it is solved, so the host
    // keeps resending it (answered from the reply cache afterwards): allow it many retries.
    let patient = Timeouts {
        retransmit: Duration::from_secs(2),
        retries: 200,
        ..support::litex_timeouts()
    };
    let mut target = Target::handshake(Link::new(port), patient)
        .unwrap_or_else(|e| panic!("handshake: {e}; simulator:\n{}", sim.output()));
    let params = LiveParams {
        tolerance: 1e-3,
        max_iterations: 500,
        cycle_budget: 0,
        scale: setup.scale.map(|s| s as f32),
    };
    let mut link = LiveLink::start(&mut target, &setup, params).unwrap();
    for frame in 1..=2 {
        let tool = vec![spec_at(frame as f64 * 0.05).prescribed[0].u];
        let answer = link.frame(&tool).unwrap();
        let (_, want) = setup.converged(&tool, None).unwrap();
        let scale = want.iter().fold(0f64, |m, v| m.max(v.abs()));
        let err = (0..3)
            .map(|d| (f64::from(answer.value[d]) - want[d]).abs())
            .fold(0.0, f64::max)
            / scale;
        assert!(err <= 1e-3, "frame {frame}: {answer:?} vs {want:?}");
        assert!(answer.cycles > 0, "{answer:?}");
    }
}

/// Dynamic frames (`deform live` on a dynamic scenario) on the soft core: S resident on the
/// one hart, two steps of examples/needle-dynamic-8b.toml equal the host's f64 stepper to the
/// tolerance's order, with real cycles.
#[test]
fn dynamic_live_frames_on_the_soft_core_follow_the_f64_stepper() {
    use deform_host::encode::EncodeOptions;
    use deform_host::live::dynamic::DynamicLive;

    let needle = support::DynamicNeedle::load(&EncodeOptions::default());
    let sim = start();
    let port = open_serial(&sim.serial_path().to_string_lossy()).expect("open the bridge's pty");
    let mut target = Target::handshake(Link::new(port), support::litex_timeouts())
        .unwrap_or_else(|e| panic!("handshake: {e}; simulator:\n{}", sim.output()));
    let params = needle.params(1e-4, EncodeOptions::default());
    let (model, tools) = (&needle.setup.model, &needle.setup.tools);
    let (h, spec) = (needle.h, &needle.spec);
    let built = deform_host::dynamics::target::DynamicModel::for_target(model, spec, h).unwrap();
    let mut live = DynamicLive::on_target(model, tools, built, params, &mut target).unwrap();
    for frame in 1..=2 {
        let tool = needle.tool(frame);
        let f = live.advance(frame, &tool).unwrap();
        let err = f
            .error_vs_converged
            .expect("checked against the f64 stepper");
        println!(
            "LiteX dynamic frame {frame}: {} iterations, {:?} cycles, error {err:.2e}",
            f.iterations, f.cycles
        );
        assert!(err <= 1e-3, "frame {frame}: {err:e}");
        assert!(f.cycles.unwrap() > 0);
    }
}
