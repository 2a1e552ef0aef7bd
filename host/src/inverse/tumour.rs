//! The tumour case of issue 6 (docs/RESULTS.md): a stiff inclusion in a 12³ block, observed
//! under a few load cases. The unit tests and the `tumour_study` example (which prints
//! docs/RESULTS.md's table) share it.

use super::synthetic::{forward, observe, Noise};
use super::Observations;
use crate::model::{
    Axis, Connection, Elasticity, FixedNodeSet, Grid, Inclusion, Model, ModelSpec, NodeField,
    PointLoad, Side,
};

/// Where the inclusion really is.
pub const TRUE_CENTRE: [f64; 3] = [7.0, 5.0, 6.0];

/// The tumour case of issue 6 (see docs/RESULTS.md): a 12³ grid, model A, resting on its
/// bottom face, an inclusion 5× stiffer centred at (7, 5, 6) with radius 2.
pub fn tumour_model(loads: Vec<PointLoad>) -> Model {
    let grid = Grid::new(12, 12, 12).expect("a 12³ grid is valid");
    Model::build(&ModelSpec {
        grid,
        connection: Connection::Axial,
        field: Some(NodeField {
            background: 1.0,
            inclusions: vec![Inclusion {
                center: TRUE_CENTRE,
                radius: 2.0,
                k: 5.0,
            }],
            nodes: Vec::new(),
        }),
        fixed_sets: vec![FixedNodeSet::Face {
            axis: Axis::Z,
            side: Side::Low,
        }],
        fixed_nodes: Vec::new(),
        prescribed: Vec::new(),
        loads,
        pressures: Vec::new(),
        elasticity: Elasticity::isotropic(1.0).expect("k = 1 is a valid elasticity"),
    })
    .expect("the tumour model is valid")
}

/// The load cases of the tumour case: in each, x, y and z get point loads at different
/// surface nodes, so one case gives three independent displacement fields.
pub fn tumour_load_cases() -> Vec<Vec<PointLoad>> {
    [
        ["0,6,6:1,0,0", "6,0,6:0,1,0", "6,6,11:0,0,-1"],
        ["11,6,6:-1,0,0", "6,11,6:0,-1,0", "3,3,11:0,0,-1"],
        ["6,6,11:1,0,0", "6,6,11:0,1,0", "9,9,11:0,0,-1"],
        ["0,3,9:1,0,0", "9,0,3:0,1,0", "3,9,11:0,0,-1"],
    ]
    .iter()
    .map(|case| {
        case.iter()
            .map(|l| l.parse().expect("the load cases parse"))
            .collect()
    })
    .collect()
}

pub fn tumour_observations(sets_per_case: usize, variance: f64, seed: u64) -> Observations {
    let mut all = Vec::new();
    for (c, loads) in tumour_load_cases().into_iter().enumerate() {
        let model = tumour_model(loads);
        let truth = forward(&model).expect("the tumour case is well-posed");
        let obs = observe(
            &model,
            &truth,
            sets_per_case,
            (c * sets_per_case) as u64,
            Noise {
                displacement_variance: variance,
                load_variance: 0.0,
                seed: seed + c as u64,
            },
        )
        .expect("the tumour case's observations are well-formed");
        all.extend(obs.sets);
    }
    Observations {
        grid: Grid::new(12, 12, 12).expect("a 12³ grid is valid"),
        sets: all,
    }
}

/// How far `centre` lies from the inclusion's true centre, in node spacings.
pub fn distance_to_truth(centre: [f64; 3]) -> f64 {
    centre
        .iter()
        .zip(TRUE_CENTRE)
        .map(|(a, b)| (a - b) * (a - b))
        .sum::<f64>()
        .sqrt()
}
