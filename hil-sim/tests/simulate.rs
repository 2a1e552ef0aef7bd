//! Time series on the firmware in QEMU through `deform simulate`'s library code: every step
//! checked against the f64 reference, warm starts against cold starts, and the values-only
//! update of the displacement-dependent model against a fresh upload of the same matrix.

mod support;

use deform_host::encode::encode;
use deform_host::model::{Grid, Model, ModelSpec};
use deform_host::simulate::{nonlinear_matrix, simulate, Nonlinear, Schedule, StepParams};
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
        tol: 1e-7,
        max_iterations: 2000,
        check_reference: true,
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
    };
    let (updated_report, updated_x) = target.solve_for(&b, solve).unwrap();
    target.upload_matrix(&encode(&k).unwrap()).unwrap();
    let (fresh_report, fresh_x) = target.solve_for(&b, solve).unwrap();
    assert_eq!(updated_report.iterations, fresh_report.iterations);
    assert_eq!(updated_report.residual, fresh_report.residual);
    assert_eq!(updated_x, fresh_x);
    assert_alive(&mut qemu);
}
