//! The matrices of the dynamic model: lumped masses M (diagonal), the damper Laplacian B built
//! by the same assembly as K ([`assemble_laplacian`], a damper beside every spring), Rayleigh
//! C = B + a·M + b·K, and the step matrix S = M + c_B·C + c_K·K of a scheme and h.

use super::params::{DynamicsError, DynamicsSpec, Scheme};
use crate::model::assembly::assemble_laplacian;
use crate::model::boundary::eliminate_fixed_nodes;
use crate::model::springs::{MeanOfEndNodes, Uniform};
use crate::model::{Axis, Csr, Model};

/// M, C_d and K_d of a model, before any node is eliminated (prescribed nodes move, so their
/// columns matter on the right-hand side).
#[derive(Debug, Clone)]
pub struct DynamicSystem {
    mass: Vec<f64>,
    stiffness: [Csr; 3],
    damping: [Csr; 3],
    constrained: Vec<bool>,
}

impl DynamicSystem {
    /// Assembles M, B (+ Rayleigh) and K for `model`'s network.
    pub fn new(model: &Model, spec: &DynamicsSpec) -> Result<Self, DynamicsError> {
        let grid = model.grid();
        let mass = spec.node_masses(grid)?;
        let node_damping = spec.node_damping(grid)?;
        let rayleigh = spec.rayleigh()?;
        let connection = model.spec().connection;
        let stiffness = Axis::ALL.map(|d| model.free_stiffness_matrix(d));
        let assemble = |d: Axis| {
            let dampers = match (&node_damping, &spec.damping) {
                (Some(values), _) => {
                    assemble_laplacian(grid, connection, &MeanOfEndNodes(values.clone()))
                }
                (None, super::params::Damping::PerDirection(b)) => {
                    assemble_laplacian(grid, connection, &Uniform(b[d.position()]))
                }
                (None, super::params::Damping::Field(_)) => unreachable!("checked above"),
            }
            .map_err(|e| DynamicsError::Damping(e.to_string()))?;
            Ok(match rayleigh {
                None => dampers,
                Some([a, b]) => Csr::combine(
                    &mass.iter().map(|m| a * m).collect::<Vec<_>>(),
                    &[(1.0, &dampers), (b, &stiffness[d.position()])],
                ),
            })
        };
        let [x, y, z] = Axis::ALL.map(assemble);
        Ok(Self {
            mass,
            damping: [x?, y?, z?],
            stiffness,
            constrained: model.constrained_mask(),
        })
    }

    pub fn n(&self) -> usize {
        self.mass.len()
    }

    pub fn mass(&self) -> &[f64] {
        &self.mass
    }

    /// K_d of the whole network (no node eliminated).
    pub fn stiffness(&self, axis: Axis) -> &Csr {
        &self.stiffness[axis.position()]
    }

    /// C_d = B_d (+ a·M + b·K_d) of the whole network.
    pub fn damping(&self, axis: Axis) -> &Csr {
        &self.damping[axis.position()]
    }

    /// Fixed or prescribed nodes, whose velocity is known.
    pub fn constrained(&self) -> &[bool] {
        &self.constrained
    }

    /// S_d = M + c_B·C_d + c_K·K_d with the constrained rows and columns eliminated (their
    /// diagonals kept), as the target holds it. SPD: M is positive, C and K semidefinite.
    pub fn step_matrix(&self, axis: Axis, h: f64, scheme: Scheme) -> Csr {
        eliminate_fixed_nodes(&self.free_step_matrix(axis, h, scheme), &self.constrained)
    }

    /// S_d before elimination: its columns at constrained nodes move their known velocities
    /// to the right-hand side.
    pub fn free_step_matrix(&self, axis: Axis, h: f64, scheme: Scheme) -> Csr {
        let (cb, ck) = scheme.coefficients(h);
        Csr::combine(
            &self.mass,
            &[(cb, self.damping(axis)), (ck, self.stiffness(axis))],
        )
    }

    /// Kinetic plus elastic energy ½·Σ_d (v_dᵀ·M·v_d + u_dᵀ·K_d·u_d).
    pub fn energy(&self, u: &[Vec<f64>; 3], v: &[Vec<f64>; 3]) -> f64 {
        Axis::ALL
            .iter()
            .map(|&d| {
                let p = d.position();
                let kinetic: f64 = v[p].iter().zip(&self.mass).map(|(v, m)| m * v * v).sum();
                let ku = self.stiffness(d).mul_vec(&u[p]);
                let elastic: f64 = ku.iter().zip(&u[p]).map(|(a, b)| a * b).sum();
                0.5 * (kinetic + elastic)
            })
            .sum()
    }
}
