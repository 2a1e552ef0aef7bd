//! Inverse models (thesis ch. 3): the elasticity of a tissue from observed displacements and
//! loads.
//!
//! The forward model says, for every direction d and every node p that is neither fixed nor
//! prescribed, f_p^d = Σ over p's springs s = (p, q) of k̃_s·(l̃_p^d − l̃_q^d) (thesis eq. 24,
//! with K's sign convention). Observations ([`observations`]) give l̃ and f per node, in
//! repeated sets; the estimators fit k̃:
//!
//! - [`homogeneous`]: one k̃ for every spring (3.2.1). The thesis's equation-error estimator
//!   (eq. 44) and an output-error estimator that fits the model's *predicted* displacements to
//!   the observed ones, with the forward solves run on the target. Noise on the displacements
//!   biases the first strongly towards 0 and leaves the second unbiased (see docs/RESULTS.md).
//! - [`parametric`]: k̃_s = α0 + α1·Σ_d Δl_s^d + α2·Σ_d (Δl_s^d)² (3.2.2), a 3×3 normal system
//!   (eq. 50) solved by CG.
//! - [`spring_field`]: one k̃ per spring (3.3, eq. 54), a large sparse SPD normal system built
//!   as instruction words and solved on the target like any other, optionally regularised
//!   ([`regularise`]), and turned into a per-node stiffness map.
//!
//! Only the grid, the spring network and the fixed and prescribed nodes of the model matter
//! here: loads come from the observations and the elasticity is what is estimated. The
//! displacement of a fixed or prescribed node is known, so the model's value replaces whatever
//! the file says there, and the equation at such a node is not used (its load is an unknown
//! reaction).

// Directions d = 0, 1, 2 index several parallel arrays at once (displacements, loads,
// per-direction sums); `for d in 0..3` says that more plainly than zipped iterators.
#![allow(clippy::needless_range_loop)]

pub mod homogeneous;
pub mod observations;
pub mod parametric;
pub mod regularise;
pub mod report;
pub mod solver;
pub mod spring_field;
pub mod synthetic;
pub mod tumour;

use crate::model::{Grid, Model, Node};

pub use observations::{ObservationSet, Observations, ObservationsError};

/// Refuses an estimate any of whose `values` (name, value) is NaN or infinite: a silent
/// `k = 0.000000 ± NaN` is a wrong result, not a result.
pub(crate) fn ensure_finite(
    estimator: &'static str,
    values: &[(&str, f64)],
) -> Result<(), EstimateError> {
    match values.iter().find(|(_, v)| !v.is_finite()) {
        Some((name, value)) => Err(EstimateError::NotFinite {
            estimator,
            what: format!("{name} = {value}"),
        }),
        None => Ok(()),
    }
}
pub use solver::{SolveCount, SpdSolver};

/// Why an estimate could not be made.
#[derive(Debug, thiserror::Error)]
pub enum EstimateError {
    #[error("the normal matrix of the {estimator} estimator is singular: {why}")]
    Singular {
        estimator: &'static str,
        why: String,
    },
    #[error("the observations hold no set")]
    NoSets,
    #[error(
        "the {estimator} estimate is not a finite number ({what}): the observations' values \
         overflow or cancel in f64 arithmetic; check the file's displacements and loads"
    )]
    NotFinite {
        estimator: &'static str,
        what: String,
    },
    #[error(transparent)]
    Solve(#[from] solver::SpdSolveError),
}

/// The spring network of a model as the estimators see it: which nodes carry an equation,
/// which displacements are known, and the springs in a fixed order.
#[derive(Debug, Clone)]
pub struct Network {
    grid: Grid,
    /// Fixed or prescribed.
    constrained: Vec<bool>,
    /// The known displacement of each constrained node (0 for fixed nodes).
    known: Vec<[f64; 3]>,
    /// Springs (p, q) with p < q, sorted by p then q: node-major order, which keeps the springs
    /// meeting at one node close together (a narrow band for the spring-field system).
    springs: Vec<(usize, usize)>,
    /// For each node, the springs that end there (CSR-like: `incident[start[p]..start[p+1]]`).
    incident_start: Vec<usize>,
    incident: Vec<usize>,
}

impl Network {
    pub fn of(model: &Model) -> Self {
        let grid = model.grid();
        let connection = model.spec().connection;
        let n = grid.node_count();
        let prescribed = model.prescribed();
        let constrained: Vec<bool> = model
            .fixed_mask()
            .iter()
            .zip(prescribed)
            .map(|(&f, p)| f || p.is_some())
            .collect();
        let known: Vec<[f64; 3]> = prescribed.iter().map(|p| p.unwrap_or([0.0; 3])).collect();
        let mut springs = Vec::new();
        for (p, node) in grid.nodes().enumerate() {
            let mut partners: Vec<usize> = connection
                .neighbours(grid, node)
                .filter(|&q| q > p)
                .collect();
            partners.sort_unstable();
            springs.extend(partners.into_iter().map(|q| (p, q)));
        }
        let mut counts = vec![0usize; n + 1];
        for &(p, q) in &springs {
            counts[p + 1] += 1;
            counts[q + 1] += 1;
        }
        for p in 0..n {
            counts[p + 1] += counts[p];
        }
        let mut fill = counts.clone();
        let mut incident = vec![0; counts[n]];
        for (s, &(p, q)) in springs.iter().enumerate() {
            for end in [p, q] {
                incident[fill[end]] = s;
                fill[end] += 1;
            }
        }
        Self {
            grid,
            constrained,
            known,
            springs,
            incident_start: counts,
            incident,
        }
    }

    pub fn grid(&self) -> Grid {
        self.grid
    }

    pub fn n(&self) -> usize {
        self.grid.node_count()
    }

    pub fn springs(&self) -> &[(usize, usize)] {
        &self.springs
    }

    pub fn is_constrained(&self, p: usize) -> bool {
        self.constrained[p]
    }

    /// The springs ending at node `p`.
    pub fn incident(&self, p: usize) -> &[usize] {
        &self.incident[self.incident_start[p]..self.incident_start[p + 1]]
    }

    /// The nodes that carry an equation (neither fixed nor prescribed).
    pub fn free_nodes(&self) -> impl Iterator<Item = usize> + '_ {
        (0..self.n()).filter(|&p| !self.constrained[p])
    }

    /// The other end of spring `s` seen from node `p`.
    pub fn other_end(&self, s: usize, p: usize) -> usize {
        let (a, b) = self.springs[s];
        if a == p {
            b
        } else {
            a
        }
    }

    /// `set`'s displacements with the known values at constrained nodes.
    pub fn effective_displacements(&self, set: &ObservationSet) -> [Vec<f64>; 3] {
        let mut u = set.u.clone();
        for (p, known) in self.known.iter().enumerate() {
            if self.constrained[p] {
                for d in 0..3 {
                    u[d][p] = known[d];
                }
            }
        }
        u
    }

    pub fn node(&self, p: usize) -> Node {
        self.grid.node(p)
    }
}

/// Σ aᵢ·bᵢ.
pub(crate) fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

#[cfg(test)]
mod tests;
