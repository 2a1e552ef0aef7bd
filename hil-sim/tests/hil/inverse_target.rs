//! The inverse models with their SPD solves on the firmware in QEMU: the output-error forward
//! solves of the homogeneous estimate, and the per-spring normal system (encoded as
//! instruction words like any K) of a tumour case. Each is compared with the same estimate
//! solved by the host's f64 reference.

use crate::support;

use deform_host::inverse::regularise::Regularisation;
use deform_host::inverse::synthetic::{forward, observe, Noise};
use deform_host::inverse::{homogeneous, spring_field, Network, Observations, SpdSolver};
use deform_host::model::{
    Connection, Elasticity, FixedNodeSet, Grid, Inclusion, Model, ModelSpec, NodeField, PointLoad,
};

use support::*;

fn noise(variance: f64, seed: u64) -> Noise {
    Noise {
        displacement_variance: variance,
        load_variance: 0.0,
        seed,
    }
}

fn host() -> SpdSolver<'static> {
    SpdSolver::Host { tol: 1e-12 }
}

#[test]
fn output_error_forward_solves_run_on_the_target() {
    let mut qemu = boot();
    let mut target = connect(&qemu);
    let spec = ModelSpec {
        elasticity: Elasticity::isotropic(1.0).unwrap(),
        ..ModelSpec::thesis_example()
    };
    let model = Model::build(&spec).unwrap();
    let obs = observe(&model, &forward(&model).unwrap(), 100, 0, noise(1e-2, 3)).unwrap();
    let net = Network::of(&model);
    let mut solver = SpdSolver::Target {
        target: &mut target,
        tol: 1e-10,
        max_solves: 8,
    };
    let on_target = homogeneous::output_error(&net, &model, &obs, &mut solver).unwrap();
    let on_host = homogeneous::output_error(&net, &model, &obs, &mut host()).unwrap();
    let solves = on_target.solves.unwrap();
    println!(
        "output error on QEMU: k = {:.6} ± {:.1e}; host {:.6}; {} system(s), {} target solve(s), {} iterations",
        on_target.k, on_target.standard_error, on_host.k, solves.systems, solves.target_solves, solves.iterations
    );
    // 100 sets under one load: one loaded direction, one forward system.
    assert_eq!(solves.systems, 1);
    assert!(solves.target_solves >= 1);
    assert!((on_target.k - on_host.k).abs() < 1e-8, "{on_target:?}");
    assert!((on_target.k - 1.0).abs() < 3.0 * on_target.standard_error);
    assert_alive(&mut qemu);
}

/// An 8³ tissue on its bottom face with an inclusion 5× stiffer at (5, 3, 4): the per-spring
/// normal system (its half-band fits the encoder's 512-column tiles at this size) solved on
/// the target places the inclusion like the host does.
#[test]
fn spring_field_normal_system_runs_on_the_target() {
    let grid = Grid::new(8, 8, 8).unwrap();
    let tissue = |loads: Vec<PointLoad>| {
        Model::build(&ModelSpec {
            grid,
            connection: Connection::Axial,
            elasticity: Elasticity::isotropic(1.0).unwrap(),
            field: Some(NodeField {
                background: 1.0,
                inclusions: vec![Inclusion {
                    center: [5.0, 3.0, 4.0],
                    radius: 1.5,
                    k: 5.0,
                }],
                nodes: Vec::new(),
            }),
            fixed_sets: vec!["z-".parse::<FixedNodeSet>().unwrap()],
            fixed_nodes: Vec::new(),
            prescribed: Vec::new(),
            loads,
            pressures: Vec::new(),
        })
        .unwrap()
    };
    let cases = [
        ["0,4,4:1,0,0", "4,0,4:0,1,0", "4,4,7:0,0,-1"],
        ["7,4,4:-1,0,0", "4,7,4:0,-1,0", "2,2,7:0,0,-1"],
        ["4,4,7:1,0,0", "4,4,7:0,1,0", "6,6,7:0,0,-1"],
    ];
    let mut sets = Vec::new();
    for (c, case) in cases.iter().enumerate() {
        let model = tissue(case.iter().map(|l| l.parse().unwrap()).collect());
        let obs = observe(
            &model,
            &forward(&model).unwrap(),
            10,
            10 * c as u64,
            noise(1e-8, 40 + c as u64),
        )
        .unwrap();
        sets.extend(obs.sets);
    }
    let obs = Observations { grid, sets };
    let model = tissue(Vec::new());
    let net = Network::of(&model);
    let regularise = [Regularisation::Smooth(1e-4)];

    let mut qemu = boot();
    let mut target = connect(&qemu);
    let mut solver = SpdSolver::Target {
        target: &mut target,
        tol: 1e-9,
        max_solves: 8,
    };
    let on_target = spring_field::estimate(&net, &obs, &regularise, &mut solver).unwrap();
    let on_host = spring_field::estimate(&net, &obs, &regularise, &mut host()).unwrap();
    let c = on_target.stiff_region.centre;
    let worst = on_target
        .springs
        .iter()
        .zip(&on_host.springs)
        .map(|(t, h)| (t.k - h.k).abs())
        .fold(0.0, f64::max);
    println!(
        "spring field on QEMU: {} unknowns, H {} nonzeros, half-band {}; {} target solve(s), {} iterations; \
         centre ({:.2}, {:.2}, {:.2}), k in [{:.2}, {:.2}]; max |k_target − k_host| = {worst:.2e}",
        on_target.unknowns,
        on_target.normal_nnz,
        on_target.normal_bandwidth,
        on_target.solves.target_solves,
        on_target.solves.iterations,
        c[0],
        c[1],
        c[2],
        on_target.min_k,
        on_target.max_k
    );
    let distance = c
        .iter()
        .zip([5.0, 3.0, 4.0])
        .map(|(a, b)| (a - b) * (a - b))
        .sum::<f64>()
        .sqrt();
    assert!(distance <= 1.0, "{c:?}");
    assert!(worst < 1e-6, "{worst}");
    assert!(on_target.solves.target_solves >= 1);
    assert_alive(&mut qemu);
}
