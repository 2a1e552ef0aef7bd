//! Dynamic steps (issue 14) on the firmware in QEMU: S resident, right-hand sides from the
//! host, refinement; every step's displacements equal the host's f64 dynamic stepper to 1e-8
//! of max |u|, for both schemes, anisotropic tissue (one S per direction, swapped by
//! values-only updates) and a keyframed prescribed displacement.

use crate::support;

use deform_host::dynamics::host::host_step;
use deform_host::dynamics::target::{
    simulate_dynamic, DynamicModel, DynamicParams, DynamicRunner, DynamicStep,
};
use deform_host::dynamics::{DynamicsSpec, Loads, Scheme, StepMatrices};
use deform_host::model::{Connection, Elasticity, Grid, Model, ModelError, ModelSpec};
use deform_host::simulate::{Schedule, StepModel};

use support::*;

fn params() -> DynamicParams {
    DynamicParams {
        tol: 1e-11,
        max_solves: 12,
        max_iterations: 2000,
        check_reference: true,
        layout: Default::default(),
    }
}

fn check(steps: &[DynamicStep], what: &str) {
    for s in steps {
        let r = &s.result;
        let dev = r.deviation.expect("checked against the f64 stepper");
        println!(
            "{what} step {}: {} iterations, {} cycles, {} B sent, deviation {dev:.2e}, energy {:.4e}",
            r.step, r.iterations, r.cycles, r.bytes.sent, s.energy
        );
        assert!(dev <= 1e-8, "{what} step {}: deviation {dev:e}", r.step);
        assert!(r.max_u > 0.0);
    }
}

#[test]
fn dynamic_steps_on_the_target_equal_the_f64_stepper() {
    let mut qemu = boot();
    let mut target = connect(&qemu);
    let mut spec = ModelSpec::thesis_example();
    spec.grid = Grid::new(5, 5, 5).unwrap();
    spec.connection = Connection::AxialShear;
    spec.loads = vec![ModelSpec::default_load(spec.grid)];
    let schedule = Schedule { steps: 6, dt: 0.05 };
    // Anisotropic k (the thesis's 1, 2, 0.5): three S, swapped in by values-only updates.
    let model = Model::build(&spec).unwrap();
    for scheme in [Scheme::BackwardEuler, Scheme::Trapezoidal] {
        let dynamics = DynamicsSpec {
            scheme,
            rayleigh: Some([0.1, 0.01]),
            ..DynamicsSpec::uniform(0.5, [0.2, 0.4, 0.1])
        };
        let steps = simulate_dynamic(
            &mut target,
            &model,
            None,
            schedule,
            DynamicModel::new(&model, &dynamics, schedule.dt).unwrap(),
            params(),
            |_| {},
            |_| {},
        )
        .expect("dynamic series on QEMU");
        check(&steps, &format!("anisotropic {scheme}"));
        assert!(steps.iter().skip(1).all(|s| s.result.update.is_some()));
    }
    // Isotropic: one S, the three directions fused, no update after the upload.
    spec.elasticity = Elasticity::isotropic(1.0).unwrap();
    spec.loads[0].force = [1.0, -0.5, 0.25];
    let model = Model::build(&spec).unwrap();
    let steps = simulate_dynamic(
        &mut target,
        &model,
        None,
        schedule,
        DynamicModel::new(&model, &DynamicsSpec::uniform(1.0, [0.3; 3]), schedule.dt).unwrap(),
        params(),
        |_| {},
        |_| {},
    )
    .expect("dynamic series on QEMU");
    check(&steps, "isotropic");
    assert!(steps.iter().all(|s| s.result.update.is_none()));
    assert!(steps
        .iter()
        .all(|s| s.result.reports.iter().all(|r| r.directions.len() == 3)));
    assert_alive(&mut qemu);
}

#[test]
fn a_keyframed_needle_moves_the_tissue_on_the_target_as_in_f64() {
    let mut qemu = boot();
    let mut target = connect(&qemu);
    let grid = Grid::new(5, 5, 5).unwrap();
    let at = |t: f64| -> Result<Model, ModelError> {
        let depth = -(t / 0.2).min(1.0);
        Model::build(&ModelSpec {
            grid,
            fixed_sets: vec!["z-".parse().unwrap()],
            elasticity: Elasticity::isotropic(1.0).unwrap(),
            prescribed: vec![format!("2,2,4:0,0,{depth}").parse().unwrap()],
            loads: Vec::new(),
            ..ModelSpec::thesis_example()
        })
    };
    let model = at(0.0).unwrap();
    let step_model: StepModel = &at;
    let steps = simulate_dynamic(
        &mut target,
        &model,
        Some(step_model),
        Schedule { steps: 8, dt: 0.05 },
        DynamicModel::new(&model, &DynamicsSpec::uniform(0.2, [0.5; 3]), 0.05).unwrap(),
        params(),
        |_| {},
        |_| {},
    )
    .expect("dynamic series on QEMU");
    check(&steps, "needle");
    let tip = grid.index("2,2,4".parse().unwrap()).unwrap();
    assert_eq!(steps[1].result.u[2][tip], -0.5);
    assert_alive(&mut qemu);
}

/// A new h (or new masses and dampers) changes S's values only: the next step sends them as a
/// values-only update, and every step still equals the f64 stepper.
#[test]
fn a_new_time_step_is_a_values_only_update() {
    let mut qemu = boot();
    let mut target = connect(&qemu);
    let mut spec = ModelSpec::thesis_example();
    spec.grid = Grid::new(5, 5, 5).unwrap();
    spec.elasticity = Elasticity::isotropic(1.0).unwrap();
    spec.loads = vec![ModelSpec::default_load(spec.grid)];
    let model = Model::build(&spec).unwrap();
    let dynamics = DynamicsSpec::uniform(0.5, [0.2; 3]);
    let mut runner = DynamicRunner::new(&model, &dynamics, 0.05, params()).unwrap();
    let loads = Loads::of(&model);
    let first = runner.step(&mut target, 1, &loads, &loads, |_| {}).unwrap();
    assert!(first.result.update.is_none());
    runner.set_time_step(0.02).unwrap();
    let second = runner.step(&mut target, 2, &loads, &loads, |_| {}).unwrap();
    let update = second.result.update.expect("a values-only update");
    assert!(update.bytes_sent < update.full_upload_bytes);
    println!(
        "new h: values-only update {} B against a full upload of {} B; step bytes {} then {}",
        update.bytes_sent,
        update.full_upload_bytes,
        first.result.bytes.sent,
        second.result.bytes.sent
    );
    // The same two steps in f64 from scratch (the runner's own reference runs alongside too).
    let system = runner.system().clone();
    let mut state = deform_host::dynamics::State::rest(model.n());
    for h in [0.05, 0.02] {
        let m = StepMatrices::new(&system, h, Scheme::BackwardEuler).unwrap();
        state = host_step(&system, &m, &state, &loads.to(&loads)).unwrap();
    }
    let scale = state
        .u
        .iter()
        .map(|u| u.iter().fold(0.0f64, |a, b| a.max(b.abs())))
        .fold(0.0, f64::max);
    for d in 0..3 {
        for (a, b) in runner.state.u[d].iter().zip(&state.u[d]) {
            assert!((a - b).abs() <= 1e-8 * scale, "{a} vs {b}");
        }
    }
    // Heavier nodes and stiffer dampers: again values only, and still the f64 stepper's answer.
    runner
        .set_model(&model, &DynamicsSpec::uniform(2.0, [0.6; 3]))
        .unwrap();
    let third = runner.step(&mut target, 3, &loads, &loads, |_| {}).unwrap();
    assert!(third.result.update.is_some(), "a values-only update");
    for s in [&first, &second, &third] {
        let dev = s.result.deviation.unwrap();
        assert!(dev <= 1e-8, "step {}: {dev:e}", s.result.step);
    }
    assert_alive(&mut qemu);
}

/// The first 10 steps of `examples/needle-dynamic.toml` (the needle going in) on the target,
/// through the scenario and flag code `deform simulate` uses, equal the f64 stepper.
#[test]
fn the_dynamic_needle_example_on_the_target() {
    use deform_host::simulate::plan::{Overrides, SeriesPlan};
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../examples/needle-dynamic.toml"
    );
    let overrides = Overrides {
        steps: Some(10),
        ..Overrides::default()
    };
    let resolved = SeriesPlan::load(Some(std::path::Path::new(path)), &overrides).unwrap();
    let dynamics = resolved.dynamics.clone().expect("the example is dynamic");
    let model = Model::build(&resolved.spec).unwrap();
    let mut qemu = boot();
    let mut target = connect(&qemu);
    let step_model = |t: f64| resolved.model_at(t);
    let steps = simulate_dynamic(
        &mut target,
        &model,
        Some(&step_model as StepModel),
        resolved.schedule,
        DynamicModel::new(&model, &dynamics, resolved.schedule.dt).unwrap(),
        params(),
        |_| {},
        |_| {},
    )
    .expect("dynamic series on QEMU");
    check(&steps, "needle-dynamic");
    assert_alive(&mut qemu);
}

/// `deform live` on a dynamic scenario (examples/needle-dynamic-8b.toml: 8³ model B, 4 MVUs):
/// every frame one step of h on the target, equal to the host's f64 stepper run separately
/// over the same tool path; and after the needle is withdrawn (frame 55) the tissue is still
/// displaced and moving, losing energy every frame, where a quasi-static frame for the tool at
/// rest would be the undeformed tissue at once.
#[test]
fn a_dynamic_live_session_follows_the_f64_stepper_and_relaxes_after_the_tool_leaves() {
    use deform_hil_sim::{firmware_elf, Qemu, QemuConfig};
    use deform_host::encode::{EncodeOptions, Partition};
    use deform_host::live::dynamic::DynamicLive;
    use deform_host::reference::{max_abs, max_abs_diff};

    let layout = EncodeOptions {
        mvus: 4,
        partition: Partition::Rows,
        use_symmetry: true,
    };
    let needle = DynamicNeedle::load(&layout);
    let tol = 1e-7;
    let (h, spec, setup) = (needle.h, &needle.spec, &needle.setup);
    let mut qemu = Qemu::start(&QemuConfig::new(firmware_elf()).harts(4)).unwrap();
    let mut target = connect(&qemu);
    let (model, tools) = (&setup.model, &setup.tools);
    let params = needle.params(tol, layout);
    let built = DynamicModel::for_target(model, spec, h).unwrap();
    let mut live = DynamicLive::on_target(model, tools, built, params, &mut target).unwrap();
    let mut host = <DynamicLive>::host(model, tools, DynamicModel::new(model, spec, h).unwrap());
    let mut frames = Vec::new();
    for i in 1..=70 {
        let tool = needle.tool(i);
        let got = live.advance(i, &tool).unwrap();
        let want = host.advance(i, &tool).unwrap();
        let (got_u, want_u) = (&live.state().u, &host.state().u);
        let scale = want_u.iter().map(|u| max_abs(u)).fold(0.0, f64::max);
        let err = (0..3)
            .map(|d| max_abs_diff(&got_u[d], &want_u[d]))
            .fold(0.0, f64::max)
            / scale;
        let motion = want.motion.unwrap();
        println!(
            "frame {i}: tool z {:+.3}, {} iterations, {:?} cycles, {} B up / {} B down, error {err:.2e}, max |v| {:.3e}, energy {:.4e}",
            tool[0][2], got.iterations, got.cycles, got.bytes.sent, got.bytes.received, motion.max_v, motion.energy
        );
        // Refined to 1e-7 a step; 70 steps of accumulated rounding stay far below 1e-5.
        assert!(err <= 1e-5, "frame {i}: {err:e} of max |u|");
        assert!(got.error_vs_converged.unwrap() <= 1e-5);
        assert!(got.residual <= tol, "frame {i}: residual {}", got.residual);
        frames.push((want, want_u.clone()));
    }
    let peak = frames.iter().map(|(f, _)| f.max_u).fold(0.0, f64::max);
    let ((withdrawn, _), (last, last_u)) = (&frames[55], &frames[69]);
    assert_eq!(last.tool[0], [0.0; 3], "the needle is out");
    // The quasi-static frame for the tool at rest (no loads) is the undeformed tissue.
    let (rest, _) = setup.converged(&last.tool, None).unwrap();
    assert!(rest.iter().all(|u| max_abs(u) == 0.0));
    // The dynamic tissue is still displaced and moving 15 frames after the withdrawal.
    assert!(last.max_u > 1e-2 * peak, "max |u| {} of {peak}", last.max_u);
    let last_v = last.motion.unwrap().max_v;
    assert!(last_v > 1e-2, "max |v| {last_v}");
    let moved = (0..3)
        .map(|d| max_abs_diff(&frames[68].1[d], &last_u[d]))
        .fold(0.0, f64::max);
    assert!(moved > 1e-4, "the tissue stopped: {moved:e}");
    // With dampers and the tool at rest nothing feeds the motion: the energy only falls.
    let energy = |f: &deform_host::live::engine::Frame| f.motion.unwrap().energy;
    for w in frames[56..].windows(2) {
        let (e0, e1) = (energy(&w[0].0), energy(&w[1].0));
        assert!(e1 <= e0, "{e0} then {e1}");
    }
    assert!(energy(last) < energy(withdrawn));
    assert_alive(&mut qemu);
}

/// `deform live --port` on a dynamic scenario: the session's own path (scenario, options,
/// board over a serial device, engine, headless session, report) against the firmware in QEMU
/// as if it were a board; the report's keys and figures are those of a target session.
#[test]
fn deform_live_runs_dynamic_frames_over_a_port() {
    use deform_host::board::{session_timeouts, Board, BoardChoice};
    use deform_host::dynamics::flags::DynamicFlags;
    use deform_host::live::report::{Place, SessionReport};
    use deform_host::live::session;
    use deform_host::live::start::{Live, Mode, Options};
    let mut qemu = boot();
    let pty = qemu.pty_path().to_str().unwrap().to_string();
    let example = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../examples/needle-dynamic-8b.toml"
    );
    let options = Options {
        frames: Some(12),
        ..Options::default()
    };
    let live = Live::load(
        std::path::Path::new(example),
        None,
        &DynamicFlags::default(),
        1,
    )
    .expect("the example loads");
    let mode = Mode {
        dynamic: true,
        on_host: false,
        serve: false,
    };
    options.check(mode).unwrap();
    let built = live.dynamic_model(true).unwrap();
    let mut board = Board::open(
        &BoardChoice::Port(pty),
        session_timeouts(options.timeout()),
        &Default::default(),
    )
    .expect("the board on the port");
    let mut engine = live
        .engine(Some(&mut board), built, &options, true)
        .unwrap();
    let script = live.script(&options);
    let tool_at = |t: f64| live.tool_at(t);
    let (frames, summary) =
        session::run(&mut *engine, &script, &tool_at, |_, _| Ok(())).expect("the session");
    let place = Place {
        target: "port".into(),
        mvus: 1,
    };
    // The needle is a tool-driven, backward-Euler, isotropic tissue of one mass: the target
    // forms its steps (protocol 12), so a frame is the tool's motion up and its force down.
    assert_eq!(engine.name(), "target (dynamic, resident)");
    let report = SessionReport::of(&live, &*engine, &options, place, &frames, &summary);
    let r = serde_json::to_value(&report).unwrap();
    assert_eq!(r["frames"], 12);
    assert_eq!(r["target"], "port");
    assert!(r["frame_cycles"]["p50"].as_f64().unwrap() > 0.0, "{r}");
    let (up, down) = (
        r["bytes_up_per_frame"].as_f64().unwrap(),
        r["bytes_down_per_frame"].as_f64().unwrap(),
    );
    assert!(up > 0.0 && up <= 64.0 && down > 0.0 && down <= 64.0, "{r}");
    assert!(
        r["residual_max"].as_f64().unwrap() <= options.tol(),
        "every step within the tolerance: {r}"
    );
    assert!(r["error_vs_converged_max"].as_f64().unwrap() <= 1e-3, "{r}");
    assert!(r["force_updates_per_s"].is_null());
    assert_eq!(r["dynamic"]["h"], 0.01);
    drop(engine);
    drop(board);
    assert_alive(&mut qemu);
}

/// Target-resident dynamic frames (protocol version 12, issue 19 item 3) on 8 MVUs: the needle
/// of examples/needle-dynamic-8b.toml at h = 1 ms, the target forming every step's right-hand
/// side itself. The displacements stay
/// within 1e-4 of the session's peak |u| of the host's f64 stepper (fed the tool's positions
/// as the frames carry them, f32), and the figures print. The median frame is at most 64 bytes
/// each way on the line (the messages themselves always are: `shared`'s dynamics tests). Every
/// step's true residual b − S·v₁, from the target's own b and v₁ (protocol version 13's
/// `ReadVector`) and the resident S, is within the tolerance: also where the target accepted the
/// step on its carried residual and drift bound without the closing MVU pass.
/// A dynamic step's residuals, read back from the target (protocol version 13), relative to
/// ‖b‖: the true ‖b − S·v₁‖ of its own b and v₁, and how far the r it carries lies from it.
#[derive(Debug)]
struct StepResidual {
    true_relative: f64,
    drift_relative: f64,
}

fn true_residual(
    target: &mut deform_host::link::Target,
    s: &deform_host::model::Csr,
    d: u8,
) -> StepResidual {
    use deform_shared::protocol::StateVector;
    let n = s.n();
    let b = target.read_vector(StateVector::Rhs, d, n).unwrap();
    let v = target.read_vector(StateVector::Velocity, d, n).unwrap();
    let r = target.read_vector(StateVector::Residual, d, n).unwrap();
    let sv = s.mul_vec(&v);
    let norm = |x: &mut dyn Iterator<Item = f64>| x.map(|e| e * e).sum::<f64>().sqrt();
    let b_norm = norm(&mut b.iter().copied());
    let truth: Vec<f64> = b.iter().zip(&sv).map(|(b, sv)| b - sv).collect();
    StepResidual {
        true_relative: norm(&mut truth.iter().copied()) / b_norm,
        drift_relative: norm(&mut r.iter().zip(&truth).map(|(r, t)| r - t)) / b_norm,
    }
}

#[test]
fn target_resident_dynamic_frames_follow_the_f64_stepper() {
    use deform_hil_sim::{firmware_elf, Qemu, QemuConfig};
    use deform_host::dynamics::resident::ResidentSetup;
    use deform_host::dynamics::DynamicSystem;
    use deform_host::encode::{EncodeOptions, Partition};
    use deform_host::live::dynamic::DynamicLive;
    use deform_host::reference::{max_abs, max_abs_diff};

    let layout = EncodeOptions {
        mvus: 8,
        partition: Partition::Rows,
        use_symmetry: true,
    };
    let needle = DynamicNeedle::load(&layout);
    let h = 1e-3;
    let (spec, model, tools) = (&needle.spec, &needle.setup.model, &needle.setup.tools);
    let system = DynamicSystem::new(model, spec).unwrap();
    let matrices = StepMatrices::new(&system, h, spec.scheme).unwrap();
    let tol = 1e-5;
    let setup = ResidentSetup::new(&system, &matrices, tools, &layout, tol, 500, 0).unwrap();
    let mut qemu = Qemu::start(&QemuConfig::new(firmware_elf()).harts(8)).unwrap();
    let mut target = connect(&qemu);
    setup.start(&mut target).unwrap();
    let mut host = <DynamicLive>::host(model, tools, DynamicModel::new(model, spec, h).unwrap());
    let n = model.n();
    let (mut peak, mut worst, mut cycles) = (0f64, 0f64, Vec::new());
    let mut bytes = Vec::new();
    // The resident S as the target's MVUs see it (its words' values, the target's scaling).
    let resident_s = deform_host::encode::decode(&setup.matrix).unwrap();
    let (mut true_worst, mut drift_worst) = (0f64, 0f64);
    for i in 1..=300u32 {
        // The tool's position as the frame carries it.
        let t = f64::from(i) * h;
        let spec_t = needle.simulation.spec_at(&needle.model, t);
        let tool = vec![spec_t.prescribed[0].u.map(|v| f64::from(v as f32))];
        let before = target.stats();
        let report = ResidentSetup::frame(&mut target, &tool).unwrap();
        let after = target.stats();
        let (up, down) = (
            after.bytes_sent - before.bytes_sent,
            after.bytes_received - before.bytes_received,
        );
        let want = host.advance(i, &tool).unwrap();
        let want_u = &host.state().u;
        let got: Vec<Vec<f64>> = (0..3)
            .map(|d| target.read_direction_solution(d as u8, n).unwrap())
            .collect();
        peak = peak.max(want.max_u);
        let err = (0..3)
            .map(|d| max_abs_diff(&got[d], &want_u[d]))
            .fold(0.0, f64::max)
            / peak.max(f64::MIN_POSITIVE);
        worst = worst.max(err);
        if i % 25 == 0 || i <= 3 {
            println!(
                "frame {i}: tool z {:+.4}, {} iterations, {} cycles, {up} B up / {down} B down, error {err:.2e} of peak, force z {:+.4} (f64 {:+.4}), residual {:.1e}",
                tool[0][2], report.iterations, report.cycles, report.force[2], want.answer[2], report.residual
            );
        }
        bytes.push((up, down));
        assert!(err <= 1e-4, "frame {i}: {err:e} of the peak |u|");
        assert!(report.residual <= tol as f32, "frame {i}: {report:?}");
        assert!(max_abs(&got[2]) > 0.0);
        for d in (0..3).filter(|&d| max_abs(&got[d]) > 0.0) {
            let check = true_residual(&mut target, &resident_s, d as u8);
            assert!(
                check.true_relative <= f64::from(setup.params.tolerance) * (1.0 + 1e-9),
                "frame {i}, direction {d}: accepted with b - S·v at {check:?}"
            );
            (true_worst, drift_worst) = (
                true_worst.max(check.true_relative),
                drift_worst.max(check.drift_relative),
            );
        }
        cycles.push(u64::from(report.cycles));
    }
    // The target accepts a step where its residual, exact or recursive within a rigorous drift
    // bound, is within the tolerance: the true one, from the target's own b and v, shows it.
    println!(
        "true residual ‖b − S·v₁‖/‖b‖ at most {true_worst:.3e} (tolerance {tol:e}); the carried r within {drift_worst:.3e}·‖b‖ of it"
    );
    // On the line a frame is its request and its answer, resends included (a loaded machine
    // makes QEMU answer late now and then); the median frame is the frame.
    let median = |mut v: Vec<u64>| {
        v.sort_unstable();
        v[v.len() / 2]
    };
    let (up, down) = (
        median(bytes.iter().map(|b| b.0).collect()),
        median(bytes.iter().map(|b| b.1).collect()),
    );
    println!("bytes per frame (median): {up} up, {down} down");
    assert!(up <= 64 && down <= 64, "{up} B up, {down} B down");
    // Every frame's count: a measuring firmware (`DEFORM_STEP_PHASE=rotate`) reports one
    // phase of the step in each frame's (target-core's dynamic_glue.rs), which this line
    // carries out for the breakdown.
    println!("cycles per frame: {cycles:?}");
    let later = &cycles[1..];
    println!(
        "target-resident dynamic frames, 8³ B, h = 1 ms, 8 MVUs: first {} cycles, then mean {:.0}, max {}; worst error {worst:.2e} of the peak |u|",
        cycles[0],
        later.iter().sum::<u64>() as f64 / later.len() as f64,
        later.iter().max().unwrap()
    );
    assert_alive(&mut qemu);
}
