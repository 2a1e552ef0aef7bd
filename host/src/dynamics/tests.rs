//! The scheme against closed forms (a single spring–mass–damper), energy behaviour, long-time
//! limits and bad input. The target is checked against the same f64 stepper in
//! `hil-sim/tests/hil/dynamics.rs`.

use super::host::host_step;
use super::*;
use crate::model::{
    Axis, Connection, Elasticity, FixedNodeSet, Grid, Model, ModelSpec, Node, PointLoad,
};
use crate::reference;

/// Two nodes on x, node 0 fixed, one spring k, mass m, damper β, force f at node 1 in x.
fn oscillator(k: f64, f: f64) -> Model {
    let grid = Grid::new(2, 1, 1).unwrap();
    Model::build(&ModelSpec {
        grid,
        connection: Connection::Axial,
        elasticity: Elasticity::isotropic(k).unwrap(),
        field: None,
        fixed_sets: vec![FixedNodeSet::None],
        fixed_nodes: vec![Node::new(0, 0, 0)],
        prescribed: Vec::new(),
        loads: vec![PointLoad {
            node: Node::new(1, 0, 0),
            force: [f, 0.0, 0.0],
        }],
        pressures: Vec::new(),
    })
    .unwrap()
}

/// A 4×4×4 model B block fixed at z−, 1 N down at the top centre.
fn block() -> Model {
    let grid = Grid::new(4, 4, 4).unwrap();
    Model::build(&ModelSpec {
        grid,
        connection: Connection::AxialShear,
        fixed_sets: vec!["z-".parse().unwrap()],
        loads: vec![PointLoad {
            node: Node::new(2, 2, 3),
            force: [0.3, 0.0, -1.0],
        }],
        ..ModelSpec::thesis_example()
    })
    .unwrap()
}

/// `steps` host steps from `start` with loads `loads(t)`.
fn run(
    model: &Model,
    spec: &DynamicsSpec,
    h: f64,
    steps: usize,
    start: State,
    loads: impl Fn(f64) -> Loads,
) -> Vec<State> {
    let system = DynamicSystem::new(model, spec).unwrap();
    let m = StepMatrices::new(&system, h, spec.scheme).unwrap();
    let mut states = vec![start];
    for _ in 0..steps {
        let s = states.last().unwrap();
        let (l0, l1) = (loads(s.t), loads(s.t + h));
        states.push(host_step(&system, &m, s, &l0.to(&l1)).unwrap());
    }
    states
}

fn constant(model: &Model) -> impl Fn(f64) -> Loads + '_ {
    move |_| Loads::of(model)
}

fn unloaded(model: &Model) -> impl Fn(f64) -> Loads + '_ {
    move |_| {
        let mut l = Loads::of(model);
        l.f.iter_mut().for_each(|f| f.fill(0.0));
        l
    }
}

/// x(t) of m·x'' + β·x' + k·x = f from rest (underdamped).
fn analytic(m: f64, beta: f64, k: f64, f: f64, t: f64) -> f64 {
    let w0 = (k / m).sqrt();
    let zeta = beta / (2.0 * (k * m).sqrt());
    assert!(zeta < 1.0);
    let wd = w0 * (1.0 - zeta * zeta).sqrt();
    f / k * (1.0 - (-zeta * w0 * t).exp() * ((wd * t).cos() + zeta * w0 / wd * (wd * t).sin()))
}

#[test]
fn one_oscillator_is_the_exact_backward_euler_recurrence() {
    let (m, beta, k, f, h) = (2.0, 0.3, 5.0, 1.5, 0.05);
    let model = oscillator(k, f);
    let spec = DynamicsSpec::uniform(m, [beta; 3]);
    let states = run(&model, &spec, h, 200, State::rest(2), constant(&model));
    let (mut u, mut v) = (0.0f64, 0.0f64);
    for s in &states[1..] {
        v = (m * v + h * (f - k * u)) / (m + h * beta + h * h * k);
        u += h * v;
        assert!(
            (s.u[0][1] - u).abs() <= 1e-12 * u.abs().max(1e-3),
            "{} vs {u}",
            s.u[0][1]
        );
        assert!((s.v[0][1] - v).abs() <= 1e-12 * v.abs().max(1e-3));
        assert_eq!((s.u[0][0], s.v[0][0]), (0.0, 0.0), "the fixed node stays");
        assert!(s.u[1].iter().chain(&s.u[2]).all(|&x| x == 0.0));
    }
}

/// The energy `deform simulate --dynamic` writes in its `energy` column, against the hand
/// computation for one spring: ½·(m·v² summed over the moving directions + k·u²). Neither
/// max |u| nor max |v| (which it was once suspected to repeat).
#[test]
fn the_energy_is_kinetic_plus_elastic_by_hand() {
    let (m, k) = (2.0, 5.0);
    let model = oscillator(k, 0.0);
    let system = DynamicSystem::new(&model, &DynamicsSpec::uniform(m, [0.3; 3])).unwrap();
    let (a, b, c) = (0.4, -1.5, 0.25);
    let u = [vec![0.0, a], vec![0.0; 2], vec![0.0; 2]];
    let v = [vec![0.0, b], vec![0.0, c], vec![0.0; 2]];
    let want = 0.5 * (m * b * b + m * c * c + k * a * a);
    let got = system.energy(&u, &v);
    assert!((got - want).abs() <= 1e-12 * want, "{got} vs {want}");
    assert_ne!(got, a);
    // At rest and undeformed there is none; u alone is elastic, v alone kinetic.
    let zero = [vec![0.0; 2], vec![0.0; 2], vec![0.0; 2]];
    assert_eq!(system.energy(&zero, &zero), 0.0);
    assert!((system.energy(&u, &zero) - 0.5 * k * a * a).abs() <= 1e-12);
    assert!((system.energy(&zero, &v) - 0.5 * m * (b * b + c * c)).abs() <= 1e-12);
}

/// Error at T = 2 s against the closed form, halving h each time.
fn convergence(scheme: Scheme) -> Vec<f64> {
    let (m, beta, k, f, end) = (1.0, 0.4, 9.0, 1.0, 2.0f64);
    let model = oscillator(k, f);
    let spec = DynamicsSpec {
        scheme,
        ..DynamicsSpec::uniform(m, [beta; 3])
    };
    [0.01f64, 0.005, 0.0025, 0.00125]
        .iter()
        .map(|&h| {
            let steps = (end / h).round() as usize;
            let states = run(&model, &spec, h, steps, State::rest(2), constant(&model));
            (states[steps].u[0][1] - analytic(m, beta, k, f, end)).abs()
        })
        .collect()
}

#[test]
fn backward_euler_converges_at_first_order_to_the_ode() {
    let e = convergence(Scheme::BackwardEuler);
    for w in e.windows(2) {
        let order = (w[0] / w[1]).log2();
        assert!((0.85..1.15).contains(&order), "errors {e:?}: order {order}");
    }
}

#[test]
fn the_trapezoidal_rule_converges_at_second_order() {
    let e = convergence(Scheme::Trapezoidal);
    for w in e.windows(2) {
        let order = (w[0] / w[1]).log2();
        assert!((1.85..2.15).contains(&order), "errors {e:?}: order {order}");
    }
}

/// The block's static deformation under its load, at rest: the start of a release.
fn deformed(model: &Model) -> State {
    let mut s = State::rest(model.n());
    for d in Axis::ALL {
        let k = model.stiffness_matrix(d);
        s.u[d.position()] = reference::solve(&k, model.load(d), None, 1e-14, 10_000)
            .unwrap()
            .x;
    }
    s
}

fn energies(model: &Model, spec: &DynamicsSpec, h: f64, steps: usize) -> Vec<f64> {
    let system = DynamicSystem::new(model, spec).unwrap();
    run(model, spec, h, steps, deformed(model), unloaded(model))
        .iter()
        .map(|s| system.energy(&s.u, &s.v))
        .collect()
}

#[test]
fn with_damping_the_energy_falls_monotonically() {
    let model = block();
    for scheme in [Scheme::BackwardEuler, Scheme::Trapezoidal] {
        let spec = DynamicsSpec {
            scheme,
            rayleigh: Some([0.05, 0.01]),
            ..DynamicsSpec::uniform(0.5, [0.2, 0.1, 0.3])
        };
        let e = energies(&model, &spec, 0.05, 200);
        for (i, w) in e.windows(2).enumerate() {
            assert!(w[1] < w[0], "{scheme} step {i}: {} → {}", w[0], w[1]);
        }
        assert!(e[200] < 1e-3 * e[0], "{scheme}: {} of {}", e[200], e[0]);
    }
}

#[test]
fn without_damping_backward_euler_loses_energy_at_first_order_and_the_trapezoidal_rule_keeps_it() {
    let model = block();
    let spec = DynamicsSpec::uniform(1.0, [0.0; 3]);
    // Lost over T = 0.5 s at h and h/2: first order halves it.
    let lost = |h: f64| {
        let steps = (0.5 / h).round() as usize;
        let e = energies(&model, &spec, h, steps);
        (e[0] - e[steps]) / e[0]
    };
    let (a, b) = (lost(0.01), lost(0.005));
    assert!(a > 0.0 && b > 0.0);
    let ratio = a / b;
    assert!((1.8..2.2).contains(&ratio), "lost {a:e} then {b:e}");
    let spec = DynamicsSpec {
        scheme: Scheme::Trapezoidal,
        ..spec
    };
    let e = energies(&model, &spec, 0.05, 400);
    for x in &e {
        assert!((x - e[0]).abs() <= 1e-9 * e[0], "{x} vs {}", e[0]);
    }
}

#[test]
fn under_a_constant_load_the_answer_tends_to_the_quasi_static_one_and_a_release_returns_to_rest() {
    let model = block();
    let spec = DynamicsSpec::uniform(0.2, [0.5; 3]);
    let statics = deformed(&model);
    let states = run(
        &model,
        &spec,
        0.1,
        600,
        State::rest(model.n()),
        constant(&model),
    );
    let end = states.last().unwrap();
    let scale = reference::max_abs(&statics.u[2]);
    for d in 0..3 {
        let diff = reference::max_abs_diff(&end.u[d], &statics.u[d]);
        assert!(diff < 1e-8 * scale, "direction {d}: {diff:e} of {scale:e}");
    }
    let released = run(&model, &spec, 0.1, 600, end.clone(), unloaded(&model));
    let last = released.last().unwrap();
    let rest = last
        .u
        .iter()
        .chain(&last.v)
        .map(|x| reference::max_abs(x))
        .fold(0.0, f64::max);
    assert!(rest < 1e-8 * scale, "{rest:e}");
}

#[test]
fn a_prescribed_node_moves_on_its_keyframes_and_drags_its_neighbour() {
    // Node 0 moves from 0 to 1 over 1 s, then holds; node 1 follows with a lag.
    let grid = Grid::new(2, 1, 1).unwrap();
    let at = |u: f64| {
        Model::build(&ModelSpec {
            grid,
            connection: Connection::Axial,
            elasticity: Elasticity::isotropic(4.0).unwrap(),
            field: None,
            fixed_sets: vec![FixedNodeSet::None],
            fixed_nodes: Vec::new(),
            prescribed: vec![format!("0,0,0:{u},0,0").parse().unwrap()],
            loads: Vec::new(),
            pressures: Vec::new(),
        })
        .unwrap()
    };
    let model = at(0.0);
    for scheme in [Scheme::BackwardEuler, Scheme::Trapezoidal] {
        let spec = DynamicsSpec {
            scheme,
            ..DynamicsSpec::uniform(1.0, [1.0; 3])
        };
        let states = run(&model, &spec, 0.01, 3000, State::rest(2), |t| {
            Loads::of(&at(t.min(1.0)))
        });
        let half = &states[50];
        assert!((half.u[0][0] - 0.5).abs() < 1e-12);
        assert!(
            half.u[0][1] > 0.0 && half.u[0][1] < 0.5,
            "lags: {}",
            half.u[0][1]
        );
        let end = states.last().unwrap();
        assert!(
            (end.u[0][1] - 1.0).abs() < 1e-5,
            "{scheme}: {}",
            end.u[0][1]
        );
    }
}

#[test]
fn a_field_of_masses_and_dampers_is_assembled_like_the_stiffness_field() {
    let model = oscillator(1.0, 1.0);
    let mut mass = crate::model::NodeField::uniform(1.0);
    mass.nodes = vec![(Node::new(1, 0, 0), 3.0)];
    let mut beta = crate::model::NodeField::uniform(2.0);
    beta.nodes = vec![(Node::new(1, 0, 0), 4.0)];
    let spec = DynamicsSpec {
        mass,
        damping: Damping::Field(beta),
        rayleigh: Some([0.5, 0.25]),
        scheme: Scheme::BackwardEuler,
    };
    let system = DynamicSystem::new(&model, &spec).unwrap();
    assert_eq!(system.mass(), &[1.0, 3.0]);
    // β of the one damper (2 + 4)/2 = 3; C = B + 0.5·M + 0.25·K.
    let c = system.damping(Axis::Y);
    assert_eq!(c.get(1, 1), 3.0 + 0.5 * 3.0 + 0.25);
    assert_eq!(c.get(0, 1), -3.0 - 0.25);
    let s = system.step_matrix(Axis::X, 0.5, Scheme::BackwardEuler);
    assert_eq!(s.get(1, 1), 3.0 + 0.5 * c.get(1, 1) + 0.25);
    assert_eq!(s.get(0, 1), 0.0, "the fixed node is eliminated");
}

#[test]
fn bad_mass_damping_and_step_are_refused_with_what_is_wrong() {
    let model = oscillator(1.0, 1.0);
    for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        let e = DynamicSystem::new(&model, &DynamicsSpec::uniform(bad, [1.0; 3])).unwrap_err();
        assert!(matches!(e, DynamicsError::Mass(_)), "{e}");
        assert!(e.to_string().contains("mass"), "{e}");
        let e = DynamicSystem::new(&model, &DynamicsSpec::uniform(1.0, [1.0, bad, 1.0]));
        if bad != 0.0 {
            assert!(matches!(e, Err(DynamicsError::Damping(_))), "{bad}");
        }
        let system = DynamicSystem::new(&model, &DynamicsSpec::uniform(1.0, [1.0; 3])).unwrap();
        let e = StepMatrices::new(&system, bad, Scheme::BackwardEuler).unwrap_err();
        assert!(matches!(e, DynamicsError::TimeStep(_)), "{e}");
        assert!(e.to_string().contains("time step"), "{e}");
    }
    let spec = DynamicsSpec {
        damping: Damping::Field(crate::model::NodeField::uniform(0.0)),
        ..DynamicsSpec::uniform(1.0, [1.0; 3])
    };
    assert!(matches!(
        DynamicSystem::new(&model, &spec),
        Err(DynamicsError::Damping(_))
    ));
    let spec = DynamicsSpec {
        rayleigh: Some([-1.0, 0.0]),
        ..DynamicsSpec::uniform(1.0, [1.0; 3])
    };
    assert!(matches!(
        DynamicSystem::new(&model, &spec),
        Err(DynamicsError::Rayleigh(..))
    ));
}

#[test]
fn an_s_the_fixed_point_cannot_hold_is_refused() {
    let model = block();
    let ok = DynamicSystem::new(&model, &DynamicsSpec::uniform(1.0, [0.1; 3])).unwrap();
    let s = ok.step_matrix(Axis::Z, 0.01, Scheme::BackwardEuler);
    let rho = fixed_point::check_representable(&s, ok.mass(), 0.01).unwrap();
    assert!(rho < 1e-4, "{rho}");
    // A microgram per node under h² = 1: the entries span far more than 21 bits.
    let tiny = DynamicSystem::new(&model, &DynamicsSpec::uniform(1e-9, [0.1; 3])).unwrap();
    let s = tiny.step_matrix(Axis::Z, 1.0, Scheme::BackwardEuler);
    let e = fixed_point::check_representable(&s, tiny.mass(), 1.0).unwrap_err();
    assert!(matches!(e, DynamicsError::Unrepresentable { .. }));
    assert!(e.to_string().contains("h = 1"), "{e}");
    // Too large for the format at all.
    let s = ok.step_matrix(Axis::Z, 1e4, Scheme::BackwardEuler);
    assert!(fixed_point::check_representable(&s, ok.mass(), 1e4).is_err());
}

/// The shipped `examples/needle-dynamic.toml` does what its comment says: node (5, 5, 7), two
/// below the tip, lags the needle, overshoots its quasi-static value a little while the tip is
/// held, swings a little past rest after the withdrawal and relaxes.
#[test]
fn the_dynamic_needle_example_lags_overshoots_and_relaxes() {
    let path = std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../examples/needle-dynamic.toml"
    ));
    let scenario = crate::scenario::Scenario::load(path, None).unwrap();
    let sim = scenario.simulation.clone().unwrap();
    assert!(sim.dynamic);
    let cli = crate::dynamics::flags::DynamicFlags::default();
    let spec = cli
        .resolve(true, scenario.dynamics.as_ref())
        .unwrap()
        .unwrap();
    let at = |t: f64| Model::build(&sim.spec_at(&scenario.model, t)).unwrap();
    let model = at(0.0);
    let node = model.grid().index(Node::new(5, 5, 7)).unwrap();
    let states = run(
        &model,
        &spec,
        sim.dt,
        sim.steps as usize,
        State::rest(model.n()),
        |t| Loads::of(&at(t)),
    );
    let held = at(1.0);
    let statics = reference::solve(
        held.unit_matrix(),
        &held.scaled_rhs(Axis::Z),
        None,
        1e-12,
        10_000,
    )
    .unwrap()
    .x[node];
    let uz = |t: f64| states[(t / sim.dt).round() as usize].u[2][node];
    assert!(uz(0.5) > 0.7 * statics, "lags: {} vs {statics}", uz(0.5));
    let deepest = states[..=75]
        .iter()
        .map(|s| s.u[2][node])
        .fold(0.0, f64::min);
    let overshoot = deepest / statics - 1.0;
    assert!((0.02..0.25).contains(&overshoot), "overshoot {overshoot}");
    let rebound = states[80..]
        .iter()
        .map(|s| s.u[2][node])
        .fold(0.0, f64::max);
    assert!(
        rebound > 0.0 && rebound < 0.25 * statics.abs(),
        "rebound {rebound}"
    );
    let last = states.last().unwrap().u[2][node];
    assert!(
        last.abs() < 0.05 * statics.abs() && last.abs() < 0.5 * rebound,
        "relaxes: {last}"
    );
}
