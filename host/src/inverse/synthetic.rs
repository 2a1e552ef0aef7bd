//! Synthetic observations (`deform observe`): the forward solution of a model plus white noise.
//!
//! The truth is solved by the f64 reference CG to a relative residual of 1e-13, not on the
//! target: the synthetic data should carry only the noise asked for, not the target's
//! fixed-point rounding as well. The noise is Gaussian, independent per node, component and set,
//! from a seeded generator (ChaCha12 via `rand`'s `StdRng`), so a seed always gives the same
//! file with the same build.

use rand::rngs::StdRng;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

use super::{ObservationSet, Observations};
use crate::model::{Axis, Model};
use crate::reference::{self, max_abs, max_abs_diff};
use crate::simulate::{nonlinear_matrix, SimulateError};

/// White noise to add: variances (not standard deviations), as the thesis's Table 3-1 states.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Noise {
    /// Variance of the noise on every displacement component.
    pub displacement_variance: f64,
    /// Variance of the noise on every load component.
    pub load_variance: f64,
    pub seed: u64,
}

#[derive(Debug, thiserror::Error)]
pub enum SyntheticError {
    #[error("noise variance {0} must be finite and non-negative")]
    BadVariance(f64),
    #[error("solving the forward model ({axis} direction)")]
    Solve {
        axis: Axis,
        #[source]
        source: reference::SolveError,
    },
    #[error(
        "the forward model did not converge in the {axis} direction (residual {residual:.3e})"
    )]
    NotConverged { axis: Axis, residual: f64 },
    #[error("the displacement-dependent springs")]
    Nonlinear(#[from] SimulateError),
    #[error("the displacement-dependent model does not support prescribed displacements")]
    PrescribedNonlinear,
    #[error("the displacement-dependent forward model did not settle in {0} fixed-point steps (last change {1:.3e} of max |u|); use smaller loads or α1, α2")]
    NotSettled(usize, f64),
}

/// The model's displacements u_x, u_y, u_z, by the f64 reference CG.
pub fn forward(model: &Model) -> Result<[Vec<f64>; 3], SyntheticError> {
    solve_directions(model.unit_matrix(), |axis| model.scaled_rhs(axis), 1e-13)
}

/// K·u = f solved for the model's loads with every K assembled as the f64 reference solves.
fn solve_all(
    model: &Model,
    k: &crate::model::Csr,
    tol: f64,
) -> Result<[Vec<f64>; 3], SyntheticError> {
    solve_directions(k, |axis| model.load(axis).to_vec(), tol)
}

/// `k`·u_d = `rhs(d)` for the three directions by the f64 reference CG, to `tol`.
fn solve_directions(
    k: &crate::model::Csr,
    rhs: impl Fn(Axis) -> Vec<f64>,
    tol: f64,
) -> Result<[Vec<f64>; 3], SyntheticError> {
    let mut u: [Vec<f64>; 3] = Default::default();
    for axis in Axis::ALL {
        let sol = reference::solve(k, &rhs(axis), None, tol, 40 * k.n().max(100))
            .map_err(|source| SyntheticError::Solve { axis, source })?;
        if !sol.converged {
            return Err(SyntheticError::NotConverged {
                axis,
                residual: sol.relative_residual,
            });
        }
        u[axis.position()] = sol.x;
    }
    Ok(u)
}

/// The displacements of the displacement-dependent model of thesis 3.2.2 (springs
/// k̃ = α0 + α1·ΣΔl + α2·ΣΔl², as `deform simulate --alpha` assembles them) under the model's
/// full loads, by fixed-point iteration u ← K(u)⁻¹f until u changes by less than 1e-12 of
/// max |u|, so that the observations satisfy the parametric model to rounding.
pub fn forward_displacement_dependent(
    model: &Model,
    alpha: [f64; 3],
) -> Result<[Vec<f64>; 3], SyntheticError> {
    const MAX_STEPS: usize = 200;
    if model.prescribed_count() > 0 {
        return Err(SyntheticError::PrescribedNonlinear);
    }
    let mut u: [Vec<f64>; 3] = [(); 3].map(|_| vec![0.0; model.n()]);
    let mut change = f64::INFINITY;
    for _ in 0..MAX_STEPS {
        let k = nonlinear_matrix(model, alpha, &u)?;
        let next = solve_all(model, &k, 1e-14)?;
        let scale = next.iter().map(|v| max_abs(v)).fold(0.0, f64::max);
        change = (0..3)
            .map(|d| max_abs_diff(&next[d], &u[d]))
            .fold(0.0, f64::max)
            / scale.max(f64::MIN_POSITIVE);
        u = next;
        if change < 1e-12 {
            return Ok(u);
        }
    }
    Err(SyntheticError::NotSettled(MAX_STEPS, change))
}

/// `sets` observation sets numbered from `first_id`: the displacements `truth` and the model's
/// loads, each plus `noise`.
pub fn observe(
    model: &Model,
    truth: &[Vec<f64>; 3],
    sets: usize,
    first_id: u64,
    noise: Noise,
) -> Result<Observations, SyntheticError> {
    for v in [noise.displacement_variance, noise.load_variance] {
        if !(v.is_finite() && v >= 0.0) {
            return Err(SyntheticError::BadVariance(v));
        }
    }
    let mut rng = StdRng::seed_from_u64(noise.seed);
    let normal = |variance: f64| {
        Normal::new(0.0, variance.sqrt()).expect("a finite non-negative standard deviation")
    };
    let (nu, nf) = (
        normal(noise.displacement_variance),
        normal(noise.load_variance),
    );
    let mut out = Vec::with_capacity(sets);
    for s in 0..sets {
        let mut u = truth.clone();
        let mut f = Axis::ALL.map(|axis| model.load(axis).to_vec());
        for (values, dist, variance) in [
            (&mut u, &nu, noise.displacement_variance),
            (&mut f, &nf, noise.load_variance),
        ] {
            if variance > 0.0 {
                for v in values.iter_mut().flatten() {
                    *v += dist.sample(&mut rng);
                }
            }
        }
        out.push(ObservationSet {
            id: first_id + s as u64,
            u,
            f,
        });
    }
    Ok(Observations {
        grid: model.grid(),
        sets: out,
    })
}
