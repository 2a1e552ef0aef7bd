//! The ∞-norm error against CG iterations on the thesis cube (thesis Fig. 2-9), for the
//! target's fixed point with its refinement steps and for the host's f64.
//!
//! # How the per-iteration errors are obtained
//!
//! Neither solver reports its iterates, and the target should not be slowed by doing so. But
//! CG from a zero start is deterministic: the x after k iterations is exactly what a solve
//! capped at k iterations returns. So the error after k iterations is measured by solving again
//! with `max_iterations = k`, for every k (or every `stride`-th k): quadratic in the iteration
//! count, which for the 10³ cube is a few seconds on QEMU and nothing on the host.
//!
//! The target's curve follows `deform solve`'s mixed-precision refinement
//! ([`crate::refine`]): each outer step solves A·d = r for the f64 residual r = b − A·x to the
//! target's own floor ([`FIXED_POINT_FLOOR`]), then x ← x + d. Within step s the points are
//! x_s + d_k, plotted at the cumulative iteration count; the counts where steps begin are kept
//! as `refinement_starts` and marked on the plot.
//!
//! The error is ‖x_k − x*‖∞ in the x direction (as in the thesis), with x* the f64 reference
//! solved to a relative residual of 1e-14.

use anyhow::{bail, Context};
use deform_shared::protocol::{SolveParams, Start};
use serde::{Deserialize, Serialize};

use super::BenchModel;
use crate::encode::encode;
use crate::link::Target;
use crate::model::{Axis, Csr, Model};
use crate::reference::{self, max_abs_diff, norm, residual};
use deform_shared::qformat::FIXED_POINT_FLOOR;

/// What to run.
#[derive(Debug, Clone)]
pub struct ConvergenceConfig {
    /// The cube's edge (10 for the thesis's example).
    pub edge: usize,
    pub models: Vec<BenchModel>,
    /// Measure every `stride`-th iteration (1: every one). The last of each step always is.
    pub stride: u32,
    /// Refine until the true relative residual is at most this.
    pub tol: f64,
    /// Outer (refinement) steps at most.
    pub max_steps: u32,
}

/// Which arithmetic a curve is for.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum Arithmetic {
    /// The target: block-floating-point CG, refined on the host.
    #[default]
    FixedPoint,
    /// The host's f64 reference CG.
    F64,
}

impl Arithmetic {
    pub fn label(self) -> &'static str {
        match self {
            Arithmetic::FixedPoint => "fixed point (target)",
            Arithmetic::F64 => "f64 (host)",
        }
    }
}

/// One curve of Fig. 2-9.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct ConvergenceSeries {
    pub model: BenchModel,
    pub arithmetic: Arithmetic,
    pub edge: usize,
    /// (cumulative CG iterations, ‖x − x*‖∞), starting at (0, ‖x*‖∞).
    pub points: Vec<(u32, f64)>,
    /// Cumulative iteration counts at which a refinement step (outer solve) begins; the first
    /// is 0.
    pub refinement_starts: Vec<u32>,
    /// True relative residual ‖b − A·x‖/‖b‖ at the end.
    pub final_relative_residual: f64,
}

impl ConvergenceSeries {
    pub fn final_error(&self) -> f64 {
        self.points.last().map_or(f64::NAN, |p| p.1)
    }

    pub fn total_iterations(&self) -> u32 {
        self.points.last().map_or(0, |p| p.0)
    }
}

/// The cube's A, right-hand side (x) and converged solution x*.
struct Problem {
    a: Csr,
    b: Vec<f64>,
    exact: Vec<f64>,
}

fn problem(model: BenchModel, edge: usize) -> anyhow::Result<Problem> {
    let built = Model::build(&model.cube(edge)?).context("building the cube")?;
    let a = built.unit_matrix().clone();
    let b = built.scaled_rhs(Axis::X);
    let exact = reference::solve(&a, &b, None, 1e-14, 100 * a.n())?;
    if !exact.converged {
        bail!("the f64 reference did not reach 1e-14 on the {edge}³ cube, {model}");
    }
    Ok(Problem {
        a,
        b,
        exact: exact.x,
    })
}

/// Iteration counts 1..=last, every `stride`-th, and `last` itself.
fn sample_points(last: u32, stride: u32) -> impl Iterator<Item = u32> {
    let stride = stride.max(1);
    (1..=last).filter(move |k| k % stride == 0 || *k == last)
}

/// The host f64 curve: plain CG from zero until its error stops falling (1e-14 residual).
pub fn f64_series(
    model: BenchModel,
    config: &ConvergenceConfig,
) -> anyhow::Result<ConvergenceSeries> {
    let p = problem(model, config.edge)?;
    let converged = reference::solve(&p.a, &p.b, None, 1e-14, 100 * p.a.n())?;
    let mut points = vec![(0, max_abs_diff(&vec![0.0; p.b.len()], &p.exact))];
    for k in sample_points(converged.iterations as u32, config.stride) {
        // Tolerance 0: exactly k iterations.
        let x = reference::solve(&p.a, &p.b, None, 0.0, k as usize)?.x;
        points.push((k, max_abs_diff(&x, &p.exact)));
    }
    Ok(ConvergenceSeries {
        model,
        arithmetic: Arithmetic::F64,
        edge: config.edge,
        points,
        refinement_starts: vec![0],
        final_relative_residual: converged.relative_residual,
    })
}

/// The target's curve, with refinement (see the module doc). `target` gets the cube's A.
pub fn target_series(
    target: &mut Target,
    model: BenchModel,
    config: &ConvergenceConfig,
) -> anyhow::Result<ConvergenceSeries> {
    let p = problem(model, config.edge)?;
    target.upload_matrix(&encode(&p.a)?)?;
    let n = p.b.len();
    let b_norm = norm(&p.b);
    let cap = crate::refine::default_max_iterations(n);
    let params = |max_iterations| SolveParams {
        max_iterations,
        tolerance: config.tol.max(FIXED_POINT_FLOOR),
        start: Start::Zero,
        directions: 1,
        cycle_budget: 0,
    };
    let mut x = vec![0.0; n];
    let mut points = vec![(0, max_abs_diff(&x, &p.exact))];
    let mut refinement_starts = Vec::new();
    let mut done = 0u32;
    let mut relative = 1.0;
    for _ in 0..config.max_steps {
        let r = residual(&p.a, &p.b, &x);
        relative = norm(&r) / b_norm;
        if relative <= config.tol {
            break;
        }
        let (full, d) = target.solve_for(&r, params(cap))?;
        refinement_starts.push(done);
        for k in sample_points(full.iterations, config.stride) {
            let d_k = if k == full.iterations {
                d.clone()
            } else {
                target.solve_for(&r, params(k))?.1
            };
            let x_k: Vec<f64> = x.iter().zip(&d_k).map(|(x, d)| x + d).collect();
            points.push((done + k, max_abs_diff(&x_k, &p.exact)));
        }
        for (x, d) in x.iter_mut().zip(&d) {
            *x += d;
        }
        done += full.iterations;
        if full.iterations == 0 {
            break;
        }
    }
    let final_relative = norm(&residual(&p.a, &p.b, &x)) / b_norm;
    relative = relative.min(final_relative);
    Ok(ConvergenceSeries {
        model,
        arithmetic: Arithmetic::FixedPoint,
        edge: config.edge,
        points,
        refinement_starts,
        final_relative_residual: relative,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_every_stride_and_the_last() {
        assert_eq!(sample_points(7, 3).collect::<Vec<_>>(), [3, 6, 7]);
        assert_eq!(sample_points(3, 1).collect::<Vec<_>>(), [1, 2, 3]);
        assert_eq!(sample_points(0, 1).count(), 0);
    }

    #[test]
    fn the_f64_error_falls_to_rounding_and_model_b_needs_fewer_iterations() {
        let config = ConvergenceConfig {
            edge: 6,
            models: BenchModel::BOTH.to_vec(),
            stride: 1,
            tol: 1e-10,
            max_steps: 4,
        };
        let a = f64_series(BenchModel::A, &config).unwrap();
        let b = f64_series(BenchModel::B, &config).unwrap();
        for s in [&a, &b] {
            assert!(s.points[0].1 > 0.0);
            assert!(s.final_error() < 1e-10 * s.points[0].1, "{s:?}");
            assert!(s.final_relative_residual <= 1e-14);
            // Consecutive iteration counts, from 0.
            assert!(s.points.iter().enumerate().all(|(i, p)| p.0 == i as u32));
        }
        // Thesis 2.6: model B converges faster than model A.
        assert!(
            b.total_iterations() < a.total_iterations(),
            "{} vs {}",
            b.total_iterations(),
            a.total_iterations()
        );
    }
}
