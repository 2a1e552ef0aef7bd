//! Time series on the firmware in QEMU through `deform simulate`'s library code: every step
//! checked against the f64 reference, warm starts against cold starts, and the values-only
//! update of the displacement-dependent model against a fresh upload of the same matrix.

use crate::support;

use deform_host::encode::encode;
use deform_host::model::{Grid, Model, ModelSpec};
use deform_host::simulate::{
    nonlinear_matrix, simulate, simulate_with, Nonlinear, Schedule, StepModel, StepParams,
};
use deform_shared::protocol::{SolveParams, Start};

use support::*;

fn model() -> Model {
    let mut spec = ModelSpec::thesis_example();
    spec.grid = Grid::new(6, 6, 6).unwrap();
    spec.loads = vec![ModelSpec::default_load(spec.grid)];
    Model::build(&spec).expect("model builds")
}

fn params(warm_start: bool) -> StepParams {
    StepParams {
        warm_start,
        predict: false,
        fuse: false,
        tol: 1e-7,
        max_iterations: 2000,
        check_reference: true,
        layout: Default::default(),
    }
}

const SCHEDULE: Schedule = Schedule { steps: 4, dt: 0.25 };

#[test]
fn warm_starts_need_fewer_iterations_and_every_step_matches_f64() {
    let mut qemu = boot();
    let model = model();
    let mut target = connect(&qemu);
    let mut total = [0u32; 2];
    for (i, warm) in [false, true].into_iter().enumerate() {
        let steps = simulate(
            &mut target,
            &model,
            SCHEDULE,
            None,
            params(warm),
            |_| {},
            |_| {},
        )
        .expect("simulate on QEMU");
        assert_eq!(steps.len(), 4);
        for s in &steps {
            let dev = s.deviation.expect("checked against f64");
            println!(
                "{} step {}: {} iterations, residual {:.2e}, deviation {dev:.2e}",
                if warm { "warm" } else { "cold" },
                s.step,
                s.iterations,
                s.residual
            );
            assert!(dev < 1e-5, "step {}: deviation {dev:e}", s.step);
            assert!(
                s.residual < 1e-5,
                "step {}: residual {:e}",
                s.step,
                s.residual
            );
        }
        total[i] = steps.iter().map(|s| s.iterations).sum();
    }
    println!("iterations: cold {}, warm {}", total[0], total[1]);
    assert!(
        total[1] < total[0],
        "warm {} vs cold {}",
        total[1],
        total[0]
    );
    assert_alive(&mut qemu);
}

#[test]
fn the_nonlinear_model_updates_values_only_and_matches_a_fresh_upload() {
    let mut qemu = boot();
    let model = model();
    let mut target = connect(&qemu);
    let alpha = [1.0, 0.5, 0.2];
    let steps = simulate(
        &mut target,
        &model,
        SCHEDULE,
        Some(Nonlinear { alpha }),
        params(true),
        |_| {},
        |_| {},
    )
    .expect("simulate on QEMU");
    assert!(steps[0].update.is_none(), "the first K is uploaded in full");
    for s in &steps[1..] {
        let u = s.update.expect("values-only update");
        println!("step {}: {u:?}, saved {} B", s.step, u.bytes_saved());
        assert!(u.bytes_sent < u.full_upload_bytes);
        assert!(s.deviation.unwrap() < 1e-4, "{:?}", s.deviation);
    }

    // The resident K after the last update solves like a fresh upload of the same matrix.
    let k = nonlinear_matrix(&model, alpha, &steps[2].u).unwrap();
    let b: Vec<f64> = (0..model.n())
        .map(|i| ((i % 7) as f64 - 3.0) * 0.1)
        .collect();
    let solve = SolveParams {
        max_iterations: 2000,
        tolerance: 1e-7,
        start: Start::Zero,
        directions: 1,
        cycle_budget: 0,
    };
    let (updated_report, updated_x) = target.solve_for(&b, solve).unwrap();
    target.upload_matrix(&encode(&k).unwrap()).unwrap();
    let (fresh_report, fresh_x) = target.solve_for(&b, solve).unwrap();
    assert_eq!(updated_report.iterations, fresh_report.iterations);
    assert_eq!(updated_report.residual, fresh_report.residual);
    assert_eq!(updated_x, fresh_x);
    assert_alive(&mut qemu);
}

/// `deform simulate examples/needle-insertion.toml --steps 6 --dt 0.25`'s series and model.
fn needle_insertion() -> (deform_host::simulate::plan::SeriesPlan, Model) {
    use deform_host::simulate::plan::{Overrides, SeriesPlan};
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../examples/needle-insertion.toml"
    );
    let overrides = Overrides {
        steps: Some(6),
        dt: Some(0.25),
        ..Overrides::default()
    };
    let resolved =
        SeriesPlan::load(Some(std::path::Path::new(path)), &overrides).expect("resolves");
    assert_eq!(resolved.schedule, Schedule { steps: 6, dt: 0.25 });
    let model = Model::build(&resolved.spec).expect("model builds");
    (resolved, model)
}

/// The series `resolved` of `model` on the target of `qemu`, solved with `params`.
fn simulate_series(
    qemu: &deform_hil_sim::Qemu,
    resolved: &deform_host::simulate::plan::SeriesPlan,
    model: &Model,
    params: StepParams,
    on_step: impl FnMut(&deform_host::simulate::StepResult),
) -> Vec<deform_host::simulate::StepResult> {
    let mut target = connect(qemu);
    let step_model = |t: f64| resolved.model_at(t);
    simulate_with(
        &mut target,
        model,
        resolved.schedule,
        Some(&step_model as StepModel),
        None,
        params,
        |_| {},
        on_step,
    )
    .expect("simulate on QEMU")
}

/// `deform simulate examples/needle-insertion.toml --steps 6 --dt 0.25`: the keyframed tip
/// displacement (0 → −2 over t = 0 … 1, then held) is met at every step, and every step
/// matches the f64 reference.
#[test]
fn the_needle_insertion_example_follows_its_keyframes() {
    use deform_host::model::Node;
    use deform_host::scenario::value_at;

    let (resolved, model) = needle_insertion();
    let sim = resolved.simulation.clone().expect("[simulation]");
    let tip = model.grid().index(Node::new(5, 5, 9)).unwrap();

    let mut qemu = boot();
    let steps = simulate_series(&qemu, &resolved, &model, params(true), |_| {});
    assert_eq!(steps.len(), 6);
    for s in &steps {
        let want = value_at(&sim.displace[0].keyframes, s.t);
        let got = [0, 1, 2].map(|d| s.u[d][tip]);
        let dev = s.deviation.expect("checked against f64");
        println!(
            "step {} t = {}: tip {got:?} (want {want:?}), {} iterations, deviation {dev:.2e}",
            s.step, s.t, s.iterations
        );
        for d in 0..3 {
            assert!(
                (got[d] - want[d]).abs() < 1e-4,
                "step {}: tip {got:?}, want {want:?}",
                s.step
            );
        }
        assert!(dev < 1e-5, "step {}: deviation {dev:e}", s.step);
        assert!(
            s.residual < 1e-5,
            "step {}: residual {:e}",
            s.step,
            s.residual
        );
    }
    assert_eq!(
        steps[1].u[2][tip].round(),
        -1.0,
        "t = 0.5 is half of the 0 → −2 ramp"
    );
    assert_alive(&mut qemu);
}

/// `deform simulate examples/needle-insertion.toml --steps 6 --dt 0.25` with simulate's own
/// defaults (fused, predicted, warm): the series runs as superposed live frames (issue 19 item
/// 2), not on the extrapolation 2u(t−1) − u(t−2). Every step says so, the closing line names
/// the predictor, and every step after the first (where the extrapolation has one solution at
/// most to start from, and needs iterations) takes 0 CG iterations; each still matches f64.
#[test]
fn simulate_takes_the_superposed_path_for_a_prescribed_tool() {
    use deform_host::simulate::sink::Totals;

    let (resolved, model) = needle_insertion();
    let params = StepParams {
        predict: true,
        fuse: true,
        tol: 1e-5,
        ..params(true)
    };
    let mut qemu = boot();
    let mut totals = Totals::default();
    let steps = simulate_series(&qemu, &resolved, &model, params, |s| {
        totals.add(s, params.tol)
    });
    assert_eq!(steps.len(), 6);
    for s in &steps {
        let dev = s.deviation.expect("checked against f64");
        println!(
            "step {} t = {}: superposed {}, {} iterations, {} cycles, deviation {dev:.2e}",
            s.step, s.t, s.superposed, s.iterations, s.cycles
        );
        assert!(s.superposed, "step {}: not a superposed frame", s.step);
        assert!(dev < 1e-4, "step {}: deviation {dev:e}", s.step);
        if s.step > 1 {
            assert_eq!(s.iterations, 0, "step {}", s.step);
        }
    }
    let closing = totals.quasi_static_lines(&params, false);
    assert!(
        closing.contains("superposed live frames"),
        "the closing line names the predictor: {closing}"
    );
    assert_alive(&mut qemu);
}
