//! The shipped scenario files (`examples/*.toml`), each one's static solve run on the firmware
//! in QEMU through `deform solve`'s own code path and checked against the host's f64 reference;
//! prescribed displacements must be met.

use crate::support;

use std::path::Path;
use std::time::Duration;

use deform_host::model::Model;
use deform_host::scenario::Scenario;
use deform_host::solve::{prescribed_error, solve_model, SolvePlan};

use support::*;

/// Fails above this deviation from the f64 reference, relative to max |u|.
const MAX_DEVIATION: f64 = 1e-3;

fn run_example(name: &str) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../examples")
        .join(format!("{name}.toml"));
    let scenario = Scenario::load(&path, None).expect("the example loads");
    let model = Model::build(&scenario.model).expect("the example builds");
    let mut qemu = boot();
    let plan = SolvePlan {
        max_iter: scenario.solver.max_iter,
        ..plan(
            port_of(&qemu),
            scenario.solver.tol.unwrap_or(1e-8),
            scenario.solver.max_solves.unwrap_or(8),
            Duration::from_secs(120),
        )
    };
    let solved = solve_model(&model, &plan).expect("solve on QEMU");
    assert_alive(&mut qemu);

    let (rel, scale) = deviation_from_reference(&solved);
    assert!(scale > 0.0, "{name}: the reference displacement is zero");
    let prescribed = prescribed_error(&model, &solved.u);
    println!(
        "{name}: max |u| = {scale:.6e}, max relative error against f64 = {rel:.3e}, \
         prescribed error {prescribed:.3e}, iterations {:?}",
        solved
            .stats
            .directions
            .iter()
            .map(|d| d.iterations)
            .collect::<Vec<_>>()
    );
    assert!(rel < MAX_DEVIATION, "{name}: deviation {rel:e}");
    assert!(
        prescribed <= 1e-6 * scale,
        "{name}: prescribed displacement missed by {prescribed:e}"
    );
}

#[test]
fn thesis_cube_example() {
    run_example("thesis-cube");
}

#[test]
fn tumour_palpation_example() {
    run_example("tumour-palpation");
}

#[test]
fn needle_insertion_example() {
    run_example("needle-insertion");
}
