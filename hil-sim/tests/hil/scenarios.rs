//! Whole scenarios solved on the firmware in QEMU through `deform solve`'s own code path
//! (`solve_model` over the pty with `serialport`), each displacement checked against the host's
//! f64 reference solver.

use crate::support;

use std::time::Duration;

use deform_host::model::flags::{ConnectionArg, ModelFlags};
use deform_host::model::{Node, PointLoad};
use deform_host::solve::{solve_model, Solved};

use support::*;

/// Fails above this deviation from the f64 reference, relative to max |u|.
const MAX_DEVIATION: f64 = 1e-3;

fn solve_on_qemu(args: &ModelFlags, tol: f64, max_solves: u32) -> Solved {
    let mut qemu = boot();
    let model = build(args);
    let plan = plan(port_of(&qemu), tol, max_solves, Duration::from_secs(120));
    let solved = solve_model(&model, &plan).expect("solve on QEMU");
    assert_alive(&mut qemu);
    solved
}

/// max over nodes and directions of |u − u_ref|, relative to max |u_ref|; printed and returned.
fn deviation(label: &str, solved: &Solved) -> f64 {
    let (rel, scale) = deviation_from_reference(solved);
    assert!(scale > 0.0, "{label}: the reference displacement is zero");
    println!("{label}: max |u| = {scale:.6e}, max relative error against f64 = {rel:.3e}");
    rel
}

#[test]
fn default_scenario_matches_f64_from_fixed_point_alone() {
    // One target solve per direction, no refinement: the fixed-point CG's own accuracy.
    let solved = solve_on_qemu(&ModelFlags::default(), 1e-6, 1);
    let rel = deviation("thesis cube, model A", &solved);
    assert!(rel < MAX_DEVIATION, "deviation {rel:e}");
    let x = &solved.stats.directions[0];
    assert_eq!(x.solves, 1);
    let engine = solved.stats.engine.as_ref().expect("a target run");
    assert!(x.iterations > 0 && engine.hart0.cycles > 0, "{x:?}");
    // The load pushes the loaded node in +x.
    let loaded = 5 * 10 + 5 * 100;
    assert!(solved.u[0][loaded] > 0.0);
}

#[test]
fn model_b_with_loads_in_every_direction_matches_f64() {
    let args = ModelFlags {
        connection: Some(ConnectionArg::B),
        load: vec![
            PointLoad {
                node: Node { i: 5, j: 5, k: 9 },
                force: [0.3, -1.0, 0.5],
            },
            PointLoad {
                node: Node { i: 2, j: 7, k: 3 },
                force: [0.0, 0.25, -2.0],
            },
        ],
        ..ModelFlags::default()
    };
    let solved = solve_on_qemu(&args, 1e-10, 8);
    let rel = deviation("10³ model B, three directions", &solved);
    assert!(rel < MAX_DEVIATION, "deviation {rel:e}");
    for d in &solved.stats.directions {
        assert!(d.relative_residual <= 1e-10, "{d:?}");
        assert!(d.iterations > 0, "{d:?}");
    }
}
