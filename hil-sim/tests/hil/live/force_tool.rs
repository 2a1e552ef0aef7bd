//! Force tools (protocol version 9) on the firmware in QEMU: examples/probe-force-8b.toml's
//! loaded probe, every frame's tool displacement and field against a converged f64 solve of
//! the same load (to 1e-3 of max |u| at tolerance 1e-4), the compliance model's prediction
//! against a full solve, bad force tools refused with a clear error, and a target reset
//! mid-session answered by setting the force tool up again.

use std::path::Path;

use deform_host::encode::EncodeOptions;
use deform_host::link::LinkError;
use deform_host::live::link::LiveLink;
use deform_host::live::LiveSetup;
use deform_host::reference::{max_abs, max_abs_diff};
use deform_host::scenario::Scenario;
use deform_shared::live::{LiveError, LiveParams};
use deform_shared::protocol::{ErrorCode, Request, Response};

use crate::support::*;

fn scenario() -> Scenario {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/probe-force-8b.toml");
    Scenario::load(&path, None).expect("the example loads")
}

fn setup(s: &Scenario) -> LiveSetup {
    let sim = s.simulation.as_ref().unwrap();
    LiveSetup::for_simulation(&s.model, sim, &EncodeOptions::default()).unwrap()
}

fn params(setup: &LiveSetup) -> LiveParams {
    LiveParams {
        tolerance: 1e-4,
        max_iterations: 500,
        cycle_budget: 0,
        scale: setup.scale.map(|s| s as f32),
    }
}

/// max_d |got_d − want_d| / `scale`.
fn err(got: [f32; 3], want: [f64; 3], scale: f64) -> f64 {
    (0..3)
        .map(|d| (f64::from(got[d]) - want[d]).abs())
        .fold(0.0, f64::max)
        / scale
}

#[test]
fn force_frames_match_converged_solves_and_the_compliance_predicts_the_next() {
    let mut qemu = boot();
    let mut target = connect(&qemu);
    let s = scenario();
    let sim = s.simulation.as_ref().unwrap();
    let setup = setup(&s);
    assert_eq!(setup.kind.name(), "force");
    let mut link = LiveLink::start(&mut target, &setup, params(&setup)).unwrap();
    assert!(link.model.converged, "{:?}", link.model);
    for frame in 1..=6 {
        let t = frame as f64 * 0.1;
        let load = setup.tool_at(&s.model, sim, t);
        let next = setup.tool_at(&s.model, sim, t + 0.05);
        check_frame(&mut link, &setup, &load, &next);
    }
    assert_alive(&mut qemu);
}

/// A full frame at `load` against a converged f64 solve (the motion and the whole field, to
/// 1e-3 of max |u|), then the compliance model's answer at `next` against a full solve there.
fn check_frame(
    link: &mut LiveLink<'_, Box<dyn serialport::SerialPort>>,
    setup: &LiveSetup,
    load: &[[f64; 3]],
    next: &[[f64; 3]],
) {
    let answer = link.frame(load).unwrap();
    let (want, motion) = setup.converged(load, None).unwrap();
    let scale = want.iter().map(|v| max_abs(v)).fold(0.0, f64::max);
    assert!(
        err(answer.value, motion, scale) <= 1e-3,
        "{load:?}: {answer:?} vs {motion:?}"
    );
    let u = link.solution().unwrap();
    for d in 0..3 {
        assert!(max_abs_diff(&u[d], &want[d]) <= 1e-3 * scale, "{load:?}");
    }
    let model = link.force(next).unwrap();
    let (want_next, motion_next) = setup.converged(next, None).unwrap();
    let scale = want_next.iter().map(|v| max_abs(v)).fold(0.0, f64::max);
    assert!(
        err(model.value, motion_next, scale) <= 1e-3,
        "{next:?}: {model:?} vs {motion_next:?}"
    );
}

#[test]
fn bad_force_tools_are_refused_with_a_clear_error() {
    let s = scenario();
    let setup = setup(&s);
    let grid = setup.model.grid();
    // On the fixed base: refused by the host before anything is sent.
    let mut on_base = s.clone();
    let sim = on_base.simulation.as_mut().unwrap();
    sim.load[0].node.k = 0;
    let text = LiveSetup::for_simulation(&on_base.model, sim, &EncodeOptions::default())
        .err()
        .expect("refused")
        .to_string();
    assert!(text.contains("fixed"), "{text}");
    // The target checks what it is sent, too: a fixed node shows when the model is built.
    let mut qemu = boot();
    let mut target = connect(&qemu);
    target.upload_matrix(&setup.matrix).unwrap();
    let base = grid
        .index(deform_host::model::Node { i: 4, j: 4, k: 0 })
        .unwrap() as u32;
    let ack = target
        .link_mut()
        .request(&Request::LiveForceTool {
            nodes: [base].into_iter().collect(),
        })
        .unwrap();
    assert_eq!(ack, Response::Ack);
    let refused = |r: Result<Response, LinkError>, want: LiveError| match r {
        Err(LinkError::Target {
            code: ErrorCode::Live(e),
            ..
        }) => assert_eq!(e, want),
        other => panic!("{other:?}"),
    };
    refused(
        target
            .link_mut()
            .request(&Request::LiveStart(params(&setup))),
        LiveError::FixedToolNode { node: base },
    );
    let n = setup.matrix.n;
    refused(
        target.link_mut().request(&Request::LiveForceTool {
            nodes: [3, n].into_iter().collect(),
        }),
        LiveError::NodeOutOfRange { node: n },
    );
    refused(
        target.link_mut().request(&Request::LiveLoad {
            load: [[0.0f32, 0.0, -1.0]].into_iter().collect(),
        }),
        LiveError::NotStarted,
    );
    assert_alive(&mut qemu);
}

/// Four tool nodes (two fused model solves of three and one unit load), each loaded
/// differently: the mean displacement and the field against the f64 reference, and the
/// compliance model's prediction against a full solve.
#[test]
fn a_four_node_force_tool_matches_the_reference() {
    use deform_host::model::Node;
    let s = scenario();
    let mut rest = s.model.clone();
    rest.loads.clear();
    let nodes = [(3, 4), (4, 4), (5, 4), (4, 3)].map(|(i, j)| Node { i, j, k: 7 });
    let setup = LiveSetup::force(&rest, &nodes, &EncodeOptions::default()).unwrap();
    let mut qemu = boot();
    let mut target = connect(&qemu);
    let mut link = LiveLink::start(&mut target, &setup, params(&setup)).unwrap();
    assert_eq!(link.model.solves, 2, "{:?}", link.model);
    assert!(link.model.converged, "{:?}", link.model);
    let load_at = |t: f64| -> Vec<[f64; 3]> {
        (0..4)
            .map(|j| [0.1 * j as f64 * t, -0.2 * t, -(1.0 + j as f64) * t])
            .collect()
    };
    for frame in 1..=4 {
        let t = frame as f64 * 0.25;
        check_frame(&mut link, &setup, &load_at(t), &load_at(t + 0.1));
    }
    assert_alive(&mut qemu);
}

/// A target reset mid-session: the link sends the force tool again (not tool rows), rebuilds
/// the compliance model and repeats the frame.
#[test]
fn a_force_tool_survives_a_target_reset() {
    use deform_hil_sim::{firmware_elf, Qemu, QemuConfig};
    let monitor =
        std::env::temp_dir().join(format!("deform-force-monitor-{}.sock", std::process::id()));
    let _ = std::fs::remove_file(&monitor);
    let mut qemu = Qemu::start(&QemuConfig::new(firmware_elf()).monitor(&monitor))
        .unwrap_or_else(|e| panic!("cannot boot the firmware: {e}"));
    let mut target = connect(&qemu);
    let s = scenario();
    let sim = s.simulation.as_ref().unwrap();
    let setup = setup(&s);
    let mut link = LiveLink::start(&mut target, &setup, params(&setup)).unwrap();
    link.frame(&setup.tool_at(&s.model, sim, 0.1)).unwrap();
    qemu.system_reset(&monitor).unwrap();
    std::thread::sleep(std::time::Duration::from_millis(500));
    let load = setup.tool_at(&s.model, sim, 0.2);
    let answer = link
        .frame(&load)
        .unwrap_or_else(|e| panic!("no recovery from the reset: {e}"));
    assert_eq!(link.resets, 1);
    let (want, motion) = setup.converged(&load, None).unwrap();
    let scale = want.iter().map(|v| max_abs(v)).fold(0.0, f64::max);
    assert!(err(answer.value, motion, scale) <= 1e-3, "{answer:?}");
    assert_alive(&mut qemu);
    let _ = std::fs::remove_file(&monitor);
}
