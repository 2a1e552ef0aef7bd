//! Grids beyond the 512-column window on the firmware in QEMU, through `deform solve`'s own code
//! path: 16×16×16 in model A on one MVU and in model B on eight (refined to 1e-10), and a grid
//! too large for the target refused before anything is uploaded.

use crate::support;

use std::time::Duration;

use deform_hil_sim::Qemu;
use deform_host::model::{Connection, Grid, Model, ModelSpec};
use deform_host::solve::{solve_model, SolvePlan, Solved};

use support::*;

fn model(n: usize, connection: Connection) -> Model {
    let grid = Grid::new(n, n, n).unwrap();
    Model::build(&ModelSpec {
        grid,
        connection,
        loads: vec![ModelSpec::default_load(grid)],
        ..ModelSpec::thesis_example()
    })
    .expect("model builds")
}

fn plan_16(qemu: &Qemu, tol: f64) -> SolvePlan {
    plan(port_of(qemu), tol, 8, Duration::from_secs(300))
}

fn check(label: &str, solved: &Solved, tol: f64) {
    let (rel, scale) = deviation_from_reference(solved);
    let engine = solved.stats.engine.as_ref().expect("a target run");
    let perf = engine.performance.as_ref().expect("measured");
    println!(
        "{label}: {} words in {} tiles ({} empty-row), symmetry {}, {} MVU(s); iterations {:?}, \
         solves {:?}; max |u| {scale:.4e}, deviation {rel:.2e}; per iteration {:.2} MVU instr/word, \
         critical path {}, {:.1} MFLOPS",
        engine.layout.words,
        engine.layout.tiles,
        engine.layout.empty_row_words,
        engine.layout.symmetry_used,
        engine.layout.mvus,
        solved.stats.directions.iter().map(|d| d.iterations).collect::<Vec<_>>(),
        solved.stats.directions.iter().map(|d| d.solves).collect::<Vec<_>>(),
        perf.mvu_instructions_per_word,
        perf.critical_path,
        perf.mflops
    );
    assert!(rel <= 1e-6, "{label}: deviation {rel:e}");
    for d in &solved.stats.directions {
        assert!(d.relative_residual <= tol, "{label}: {d:?}");
    }
}

#[test]
fn sixteen_cubed_model_a_on_one_mvu() {
    let mut qemu = boot_harts(1);
    let model = model(16, Connection::Axial);
    let solved = solve_model(&model, &plan_16(&qemu, 1e-8)).expect("solve on QEMU");
    check("16³ model A, 1 MVU", &solved, 1e-8);
    let engine = solved.stats.engine.as_ref().unwrap();
    assert_eq!(engine.layout.mvus, 1);
    assert!(engine.layout.symmetry_used, "corners fixed: persymmetric");
    assert_alive(&mut qemu);
}

#[test]
fn sixteen_cubed_model_b_on_eight_mvus_refines_to_1e_10() {
    let mut qemu = boot_harts(8);
    let model = model(16, Connection::AxialShear);
    let solved = solve_model(&model, &plan_16(&qemu, 1e-10)).expect("solve on QEMU");
    check("16³ model B, 8 MVUs, tol 1e-10", &solved, 1e-10);
    let engine = solved.stats.engine.as_ref().unwrap();
    assert_eq!(engine.layout.mvus, 8, "the default is every hart");
    assert!(solved.stats.directions.iter().all(|d| d.solves <= 5));
    assert_alive(&mut qemu);
}

#[test]
fn a_grid_too_large_for_the_target_is_refused_with_its_capacity() {
    let mut qemu = boot_harts(1);
    // 48³ = 110 592 nodes: more rows than the target's vectors hold.
    let model = model(48, Connection::Axial);
    let err = solve_model(&model, &plan_16(&qemu, 1e-8))
        .err()
        .expect("refused");
    let text = format!("{err:#}");
    println!("48³ model A: {text}");
    assert!(
        text.contains("does not fit the target")
            && text.contains("dimension n")
            && text.contains("65536"),
        "{text}"
    );
    // --mvus beyond the harts the target has is refused the same way.
    let two = SolvePlan {
        mvus: Some(2),
        ..plan_16(&qemu, 1e-8)
    };
    let err = solve_model(&model, &two).err().expect("refused");
    let text = format!("{err:#}");
    assert!(
        text.contains("--mvus 2") && text.contains("1 hart"),
        "{text}"
    );
    assert_alive(&mut qemu);
}
