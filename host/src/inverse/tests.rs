//! The estimators against data with a known answer: exact (noise-free) recovery, noisy bounds,
//! the singular cases, and the tumour map.

use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};

use super::synthetic::{forward, observe, Noise};
use super::tumour::{distance_to_truth, tumour_model, tumour_observations};
use super::*;
use crate::model::{Connection, ModelSpec};

type Host<'a> = SpdSolver<'a, Box<dyn serialport::SerialPort>>;

fn host() -> Host<'static> {
    SpdSolver::Host { tol: 1e-14 }
}

fn spec(dims: (usize, usize, usize), connection: Connection, k: f64) -> ModelSpec {
    let grid = Grid::new(dims.0, dims.1, dims.2).unwrap();
    ModelSpec {
        grid,
        connection,
        elasticity: crate::model::Elasticity::isotropic(k).unwrap(),
        loads: vec![ModelSpec::default_load(grid)],
        ..ModelSpec::thesis_example()
    }
}

fn noise(variance: f64, seed: u64) -> Noise {
    Noise {
        displacement_variance: variance,
        load_variance: 0.0,
        seed,
    }
}

/// Loads that balance displacements `u` exactly for spring stiffnesses `k` (0 at constrained
/// nodes): f_p = Σ_s k_s·(u_p − u_q).
fn balancing_loads(net: &Network, k: &[f64], u: &[Vec<f64>; 3]) -> [Vec<f64>; 3] {
    [0, 1, 2].map(|d| {
        (0..net.n())
            .map(|p| {
                if net.is_constrained(p) {
                    return 0.0;
                }
                net.incident(p)
                    .iter()
                    .map(|&s| k[s] * (u[d][p] - u[d][net.other_end(s, p)]))
                    .sum()
            })
            .collect()
    })
}

/// One set per displacement field, each with the loads that balance it for the spring
/// stiffnesses `k_of(u)` gives.
fn balanced_observations(
    grid: Grid,
    net: &Network,
    fields: Vec<[Vec<f64>; 3]>,
    k_of: impl Fn(&[Vec<f64>; 3]) -> Vec<f64>,
) -> Observations {
    let sets = fields
        .into_iter()
        .enumerate()
        .map(|(id, u)| {
            let f = balancing_loads(net, &k_of(&u), &u);
            ObservationSet {
                id: id as u64,
                u,
                f,
            }
        })
        .collect();
    Observations { grid, sets }
}

/// Random displacement fields (0 at constrained nodes), `sets` of them.
fn random_fields(net: &Network, sets: usize, seed: u64) -> Vec<[Vec<f64>; 3]> {
    let mut rng = StdRng::seed_from_u64(seed);
    (0..sets)
        .map(|_| {
            [0, 1, 2].map(|_| {
                (0..net.n())
                    .map(|p| {
                        if net.is_constrained(p) {
                            0.0
                        } else {
                            rng.random_range(-1.0..1.0)
                        }
                    })
                    .collect()
            })
        })
        .collect()
}

#[test]
fn homogeneous_estimators_recover_k_exactly_without_noise() {
    for connection in [Connection::Axial, Connection::AxialShear] {
        let model = Model::build(&spec((6, 5, 4), connection, 1.7)).unwrap();
        let net = Network::of(&model);
        let obs = observe(&model, &forward(&model).unwrap(), 3, 0, noise(0.0, 1)).unwrap();
        let ee = homogeneous::equation_error(&net, &obs).unwrap();
        assert!((ee.k - 1.7).abs() < 1e-9, "{connection}: {ee:?}");
        assert!(ee.relative_residual < 1e-9);
        let oe = homogeneous::output_error(&net, &model, &obs, &mut host()).unwrap();
        assert!((oe.k - 1.7).abs() < 1e-9, "{connection}: {oe:?}");
        assert!(oe.relative_residual < 1e-9 && oe.standard_error < 1e-9);
        // Three identical sets, one loaded direction: one forward solve.
        assert_eq!(oe.solves.unwrap().systems, 1);
        assert_eq!(oe.k_by_direction[1], None);
    }
}

#[test]
fn output_error_handles_prescribed_displacements() {
    let mut s = spec((5, 5, 5), Connection::Axial, 0.8);
    s.fixed_sets = vec!["z-".parse().unwrap()];
    s.prescribed = vec!["2,2,4:0,0,-0.5".parse().unwrap()];
    s.loads = vec!["0,2,2:1,0,0".parse().unwrap()];
    let model = Model::build(&s).unwrap();
    let net = Network::of(&model);
    let obs = observe(&model, &forward(&model).unwrap(), 2, 0, noise(0.0, 1)).unwrap();
    let oe = homogeneous::output_error(&net, &model, &obs, &mut host()).unwrap();
    assert!((oe.k - 0.8).abs() < 1e-9, "{oe:?}");
    let ee = homogeneous::equation_error(&net, &obs).unwrap();
    assert!((ee.k - 0.8).abs() < 1e-9, "{ee:?}");
}

/// Table 3-1 in small: the thesis cube, k̃ = 1, 200 sets at variance 1e-2.
#[test]
fn noisy_displacements_bias_equation_error_but_not_output_error() {
    let model = Model::build(&spec((10, 10, 10), Connection::Axial, 1.0)).unwrap();
    let net = Network::of(&model);
    let obs = observe(&model, &forward(&model).unwrap(), 200, 0, noise(1e-2, 7)).unwrap();
    let oe = homogeneous::output_error(&net, &model, &obs, &mut host()).unwrap();
    assert!((oe.k - 1.0).abs() < 0.01, "{oe:?}");
    assert!(oe.standard_error < 0.004, "{oe:?}");
    assert!((oe.k - 1.0).abs() < 3.0 * oe.standard_error, "{oe:?}");
    let ee = homogeneous::equation_error(&net, &obs).unwrap();
    assert!(ee.k < 0.1, "equation error is biased towards 0: {ee:?}");
}

#[test]
fn homogeneous_estimators_refuse_motionless_or_unloaded_data() {
    let model = Model::build(&spec((4, 4, 4), Connection::Axial, 1.0)).unwrap();
    let net = Network::of(&model);
    let zero = [(); 3].map(|_| vec![0.0; 64]);
    let mut obs = observe(&model, &zero, 1, 0, noise(0.0, 1)).unwrap();
    let e = homogeneous::equation_error(&net, &obs)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("singular") && e.contains("stretches a spring"),
        "{e}"
    );
    obs.sets[0].f = zero.clone();
    let e = homogeneous::output_error(&net, &model, &obs, &mut host())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("singular") && e.contains("load vector is zero"),
        "{e}"
    );
}

#[test]
fn parametric_recovers_alpha_exactly_and_refuses_motionless_data() {
    let alpha = [1.2, 0.3, 0.5];
    for connection in [Connection::Axial, Connection::AxialShear] {
        let model = Model::build(&spec((4, 4, 3), connection, 1.0)).unwrap();
        let net = Network::of(&model);
        let obs = balanced_observations(model.grid(), &net, random_fields(&net, 2, 3), |u| {
            net.springs()
                .iter()
                .map(|&(p, q)| {
                    let dl = [0, 1, 2].map(|d| u[d][q] - u[d][p]);
                    alpha[0]
                        + alpha[1] * dl.iter().sum::<f64>()
                        + alpha[2] * dl.iter().map(|x| x * x).sum::<f64>()
                })
                .collect()
        });
        let est = parametric::estimate(&net, &obs).unwrap();
        for (got, want) in est.alpha.iter().zip(alpha) {
            assert!((got - want).abs() < 1e-9, "{connection}: {est:?}");
        }
        assert!(est.relative_residual < 1e-9);
    }
    let model = Model::build(&spec((3, 3, 3), Connection::Axial, 1.0)).unwrap();
    let zero = [(); 3].map(|_| vec![0.0; 27]);
    let obs = observe(&model, &zero, 1, 0, noise(0.0, 1)).unwrap();
    let e = parametric::estimate(&Network::of(&model), &obs)
        .unwrap_err()
        .to_string();
    assert!(e.contains("parametric estimator is singular"), "{e}");
}

/// Random spring stiffnesses and random displacement fields with the loads that balance them.
fn random_spring_data(
    model: &Model,
    fields: usize,
    seed: u64,
) -> (Network, Vec<f64>, Observations) {
    let net = Network::of(model);
    let mut rng = StdRng::seed_from_u64(seed);
    let mut k: Vec<f64> = net
        .springs()
        .iter()
        .map(|_| rng.random_range(1.0..3.0))
        .collect();
    // The springs from a free node to its constrained neighbours share one value (they are one
    // unknown, see spring_field's doc).
    let mut anchor = std::collections::HashMap::new();
    for (s, &(p, q)) in net.springs().iter().enumerate() {
        if net.is_constrained(p) != net.is_constrained(q) {
            let free = if net.is_constrained(p) { q } else { p };
            k[s] = *anchor.entry(free).or_insert(k[s]);
        }
    }
    let obs = balanced_observations(
        model.grid(),
        &net,
        random_fields(&net, fields, seed + 1),
        |_| k.clone(),
    );
    (net, k, obs)
}

#[test]
fn spring_field_recovers_every_spring_exactly_without_noise() {
    for connection in [Connection::Axial, Connection::AxialShear] {
        let mut s = spec((4, 4, 4), connection, 1.0);
        s.fixed_sets = vec!["z-".parse().unwrap()];
        let model = Model::build(&s).unwrap();
        let fields = if connection == Connection::Axial {
            2
        } else {
            6
        };
        let (net, k, obs) = random_spring_data(&model, fields, 11);
        let est = spring_field::estimate(&net, &obs, &[], &mut host()).unwrap();
        let mut checked = 0;
        for (value, &(p, q)) in est.springs.iter().zip(
            net.springs()
                .iter()
                .filter(|&&(p, q)| !(net.is_constrained(p) && net.is_constrained(q))),
        ) {
            let s = net.springs().iter().position(|&x| x == (p, q)).unwrap();
            assert!(
                (value.k - k[s]).abs() < 1e-9,
                "{connection}: {value:?} vs {}",
                k[s]
            );
            checked += 1;
        }
        assert_eq!(checked, est.springs.len());
        assert!(est.relative_residual < 1e-9);
    }
}

#[test]
fn spring_field_refuses_undetermined_springs_unless_regularised() {
    let mut s = spec((4, 4, 4), Connection::Axial, 1.0);
    s.fixed_sets = vec!["z-".parse().unwrap()];
    let model = Model::build(&s).unwrap();
    // Only node (1,1,2) moves: springs elsewhere never stretch.
    let (net, _, mut obs) = random_spring_data(&model, 1, 5);
    let moving = model.grid().index(Node::new(1, 1, 2)).unwrap();
    for set in &mut obs.sets {
        for u in &mut set.u {
            for (p, v) in u.iter_mut().enumerate() {
                if p != moving {
                    *v = 0.0;
                }
            }
        }
        set.f = balancing_loads(&net, &vec![1.0; net.springs().len()], &set.u);
    }
    let e = spring_field::estimate(&net, &obs, &[], &mut host())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("never stretch") && e.contains("--regularise"),
        "{e}"
    );
    // Tikhonov pulls the undetermined springs to the prior (here exactly 1).
    let est = spring_field::estimate(
        &net,
        &obs,
        &[regularise::Regularisation::Tikhonov(1e-3)],
        &mut host(),
    )
    .unwrap();
    assert!((est.prior_k - 1.0).abs() < 1e-12);
    assert!(est.springs.iter().all(|s| (s.k - 1.0).abs() < 1e-9));
    // One moving field gives one equation per free node, for about 3 springs per node.
    let (net, _, mut obs) = random_spring_data(&model, 1, 9);
    for d in [1, 2] {
        obs.sets[0].u[d].fill(0.0);
        obs.sets[0].f[d].fill(0.0);
    }
    let e = spring_field::estimate(&net, &obs, &[], &mut host())
        .unwrap_err()
        .to_string();
    assert!(e.contains("spring-field estimator is singular"), "{e}");
}

#[test]
fn tumour_map_places_the_inclusion() {
    // 4 load cases × 20 sets, noise variance 1e-7 on every displacement, light smoothing.
    let obs = tumour_observations(20, 1e-7, 100);
    let model = tumour_model(Vec::new());
    let net = Network::of(&model);
    let est = spring_field::estimate(
        &net,
        &obs,
        &[regularise::Regularisation::Smooth(1e-4)],
        &mut host(),
    )
    .unwrap();
    let centre = est.stiff_region.centre;
    let distance = distance_to_truth(centre);
    eprintln!(
        "tumour: centre {centre:?} ({distance:.2} nodes off), {} nodes ≥ {:.2}, k in [{:.2}, {:.2}], residual {:.2e}, {} iterations",
        est.stiff_region.nodes, est.stiff_region.threshold, est.min_k, est.max_k, est.relative_residual, est.solves.iterations
    );
    assert!(distance <= 1.0, "{centre:?}");
    // The inclusion stands out: its nodes average well above the rest.
    let truth = model.node_stiffness();
    let mean = |inside: bool| {
        let v: Vec<f64> = (0..net.n())
            .filter(|&p| (truth[p] > 1.0) == inside)
            .map(|p| est.node_stiffness[p])
            .collect();
        v.iter().sum::<f64>() / v.len() as f64
    };
    assert!(
        mean(true) > 2.5 * mean(false),
        "{} vs {}",
        mean(true),
        mean(false)
    );
}

/// Thesis Table 3-1 at full size: the 10³ cube (model A, corners fixed, 1 N in +x at (0,5,5)),
/// k̃ = 1, 1000 sets per variance. The output-error estimate must be within 1% of the truth at
/// every variance. docs/RESULTS.md gives the CLI run of the same table:
/// `cargo test -p deform-host --release --lib table_3_1 -- --ignored --nocapture`.
#[test]
#[ignore = "full-size Table 3-1, ~20 s in release"]
fn table_3_1() {
    let model = Model::build(&spec((10, 10, 10), Connection::Axial, 1.0)).unwrap();
    let net = Network::of(&model);
    let truth = forward(&model).unwrap();
    for (seed, variance) in [(1, 1e-4), (2, 1e-3), (3, 1e-2), (4, 1e-1)] {
        let obs = observe(&model, &truth, 1000, 0, noise(variance, seed)).unwrap();
        let oe = homogeneous::output_error(&net, &model, &obs, &mut host()).unwrap();
        let ee = homogeneous::equation_error(&net, &obs).unwrap();
        eprintln!(
            "| {variance:e} | {:.4} ± {:.4} | {:.4} |",
            oe.k, oe.standard_error, ee.k
        );
        assert!((oe.k - 1.0).abs() < 0.01, "{variance}: {oe:?}");
    }
}
