//! One k̃ for every spring (thesis 3.2.1), two ways.
//!
//! # Equation error (the thesis's eq. 44)
//!
//! With g = A·l̃ (A the unit-spring Laplacian, rows of free nodes only), the model says f = k̃·g,
//! and k̂ = Σ fᵀg / Σ gᵀg over directions and sets. The observed l̃ enters *both* sums: noise of
//! variance σ² on every displacement adds about σ²·‖A‖_F² to the denominator and nothing to
//! the numerator, so k̂ shrinks towards 0 by the factor 1 / (1 + σ²·‖A‖_F²/‖A·l̃‖²). For the
//! thesis cube (1 N on one node, ‖A·l̃‖ = 1/k̃) that is a factor of ~14 already at σ² = 1e-4.
//!
//! # Output error
//!
//! The model *predicts* the displacements: l̃(k̃) = A⁻¹f / k̃ + v (v: what prescribed
//! displacements alone cause). Fitting them to the observed ones in least squares,
//! min Σ ‖l̃_obs − v − c·w‖² with w = A⁻¹f and c = 1/k̃, is linear in c, so
//! ĉ = Σ wᵀ(l̃_obs − v) / Σ wᵀw and k̂ = 1/ĉ. The noise now enters only the numerator,
//! linearly: ĉ is unbiased and k̂ is off by a second-order term only. The price is the forward
//! solves w = A⁻¹f, one per *distinct* load vector and direction (repeated sets under the same
//! loads share them), run on the target.

use std::collections::HashMap;

use serde::Serialize;

use super::solver::{SolveCount, SpdSolver};
use super::{dot, EstimateError, Network, Observations};
use crate::link::Port;
use crate::model::Model;

/// One homogeneous estimate.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HomogeneousEstimate {
    /// `output-error` or `equation-error`.
    pub method: &'static str,
    /// k̂ in N/m.
    pub k: f64,
    /// Standard error of k̂ (from the residual variance; for the equation-error estimator it
    /// ignores the noise in the regressor, so it does not show the bias).
    pub standard_error: f64,
    /// ‖residual‖₂ / ‖fitted data‖₂: loads for equation error, displacements for output error.
    pub relative_residual: f64,
    /// The same fit per direction, where that direction carries information.
    pub k_by_direction: [Option<f64>; 3],
    /// Scalar equations used (free nodes × 3 × sets).
    pub equations: usize,
    /// Forward solves (output error only).
    pub solves: Option<SolveCount>,
}

fn free_count(net: &Network) -> usize {
    net.free_nodes().count()
}

/// g = A·l̃ at node p (unit springs): Σ over p's springs of (l̃_p − l̃_q).
fn unit_force(net: &Network, u: &[f64], p: usize) -> f64 {
    net.incident(p)
        .iter()
        .map(|&s| u[p] - u[net.other_end(s, p)])
        .sum()
}

/// The thesis's estimator, eq. 44, summed over directions and sets.
pub fn equation_error(
    net: &Network,
    obs: &Observations,
) -> Result<HomogeneousEstimate, EstimateError> {
    if obs.sets.is_empty() {
        return Err(EstimateError::NoSets);
    }
    let (mut fg, mut gg, mut ff) = ([0.0; 3], [0.0; 3], [0.0; 3]);
    for set in &obs.sets {
        let u = net.effective_displacements(set);
        for d in 0..3 {
            for p in net.free_nodes() {
                let g = unit_force(net, &u[d], p);
                let f = set.f[d][p];
                fg[d] += f * g;
                gg[d] += g * g;
                ff[d] += f * f;
            }
        }
    }
    let ff_all: f64 = ff.iter().sum();
    let (fg_all, gg_all): (f64, f64) = (fg.iter().sum(), gg.iter().sum());
    if gg_all == 0.0 {
        return Err(EstimateError::Singular {
            estimator: "homogeneous equation-error",
            why: "A·l̃ is zero in every set and direction: no observed displacement stretches a spring".into(),
        });
    }
    let k = fg_all / gg_all;
    // A second pass rather than fᵀf − 2k·fᵀg + k²·gᵀg, which cancels to noise near a perfect fit.
    let mut rss = 0.0;
    for set in &obs.sets {
        let u = net.effective_displacements(set);
        for d in 0..3 {
            for p in net.free_nodes() {
                rss += (set.f[d][p] - k * unit_force(net, &u[d], p)).powi(2);
            }
        }
    }
    let equations = obs.sets.len() * 3 * free_count(net);
    let variance = rss / (equations.saturating_sub(1).max(1)) as f64;
    let standard_error = (variance / gg_all).sqrt();
    let relative_residual = if ff_all > 0.0 {
        (rss / ff_all).sqrt()
    } else {
        0.0
    };
    super::ensure_finite(
        "equation-error",
        &[
            ("k", k),
            ("its standard error", standard_error),
            ("the relative residual", relative_residual),
        ],
    )?;
    Ok(HomogeneousEstimate {
        method: "equation-error",
        k,
        standard_error,
        relative_residual,
        // A direction without loads says nothing about k̃ by itself.
        k_by_direction: [0, 1, 2].map(|d| (gg[d] > 0.0 && ff[d] > 0.0).then(|| fg[d] / gg[d])),
        equations,
        solves: None,
    })
}

/// The right-hand side of A·v = b that moves the prescribed displacements of direction `d`
/// over (b_i = Σ u_j over springs i–j to prescribed j for free i, b_j = A_jj·u_j), or `None`
/// when nothing is prescribed in that direction.
fn prescribed_rhs(net: &Network, model: &Model, d: usize) -> Option<Vec<f64>> {
    let prescribed = model.prescribed();
    if !prescribed.iter().flatten().any(|u| u[d] != 0.0) {
        return None;
    }
    let a = model.unit_matrix();
    let mut b = vec![0.0; net.n()];
    for (j, u) in prescribed.iter().enumerate() {
        let Some(u) = u else { continue };
        b[j] = a.get(j, j) * u[d];
        for &s in net.incident(j) {
            let i = net.other_end(s, j);
            if !net.is_constrained(i) {
                b[i] += u[d];
            }
        }
    }
    Some(b)
}

/// Fits the model's predicted displacements to the observed ones; the forward solves run on
/// `solver` (see the module doc).
pub fn output_error<P: Port>(
    net: &Network,
    model: &Model,
    obs: &Observations,
    solver: &mut SpdSolver<'_, P>,
) -> Result<HomogeneousEstimate, EstimateError> {
    if obs.sets.is_empty() {
        return Err(EstimateError::NoSets);
    }
    let n = net.n();
    let free: Vec<bool> = (0..n).map(|p| !net.is_constrained(p)).collect();
    let (mut rhs, key_of) = distinct_loads(obs, &free);
    let distinct = rhs.len();
    for d in 0..3 {
        rhs.push(prescribed_rhs(net, model, d).unwrap_or_else(|| vec![0.0; n]));
    }
    let mut count = SolveCount::default();
    let solved = solver.solve_all(model.unit_matrix(), &rhs, &mut count)?;
    let (w, v) = solved.split_at(distinct);

    // Observed minus the prescribed part, at free nodes.
    let target = |set: &super::ObservationSet, d: usize| -> Vec<f64> {
        (0..n)
            .map(|p| if free[p] { set.u[d][p] - v[d][p] } else { 0.0 })
            .collect()
    };
    let (mut wy, mut ww, mut yy) = ([0.0; 3], [0.0; 3], 0.0);
    for (s, set) in obs.sets.iter().enumerate() {
        for d in 0..3 {
            let y = target(set, d);
            let w = &w[key_of[s][d]];
            wy[d] += dot(w, &y);
            ww[d] += dot(w, w);
            yy += dot(&y, &y);
        }
    }
    let ww_all: f64 = ww.iter().sum();
    let c = fitted_compliance(wy.iter().sum(), ww_all)?;
    let mut rss = 0.0;
    for (s, set) in obs.sets.iter().enumerate() {
        for d in 0..3 {
            let w = &w[key_of[s][d]];
            rss += target(set, d)
                .iter()
                .zip(w)
                .map(|(y, w)| (y - c * w).powi(2))
                .sum::<f64>();
        }
    }
    let equations = obs.sets.len() * 3 * free.iter().filter(|&&f| f).count();
    let variance = rss / (equations.saturating_sub(1).max(1)) as f64;
    let se_c = (variance / ww_all).sqrt();
    let relative_residual = if yy > 0.0 { (rss / yy).sqrt() } else { 0.0 };
    super::ensure_finite(
        "output-error",
        &[
            ("k", 1.0 / c),
            ("its standard error", se_c / (c * c)),
            ("the relative residual", relative_residual),
        ],
    )?;
    Ok(HomogeneousEstimate {
        method: "output-error",
        k: 1.0 / c,
        standard_error: se_c / (c * c),
        relative_residual,
        k_by_direction: [0, 1, 2].map(|d| (ww[d] > 0.0 && wy[d] > 0.0).then(|| ww[d] / wy[d])),
        equations,
        solves: Some(count),
    })
}

/// The distinct load vectors of `obs` (free nodes only, each to be solved once) and, for each
/// set and direction, the index of its own.
fn distinct_loads(obs: &Observations, free: &[bool]) -> (Vec<Vec<f64>>, Vec<[usize; 3]>) {
    let mut keys: HashMap<Vec<u64>, usize> = HashMap::new();
    let mut rhs: Vec<Vec<f64>> = Vec::new();
    let mut key_of = vec![[0usize; 3]; obs.sets.len()];
    for (s, set) in obs.sets.iter().enumerate() {
        for d in 0..3 {
            let b: Vec<f64> = free
                .iter()
                .zip(&set.f[d])
                .map(|(&free, &f)| if free { f } else { 0.0 })
                .collect();
            let key: Vec<u64> = b.iter().map(|v| v.to_bits()).collect();
            key_of[s][d] = *keys.entry(key).or_insert_with(|| {
                rhs.push(b);
                rhs.len() - 1
            });
        }
    }
    (rhs, key_of)
}

/// The least-squares c = 1/k̃ of y ≈ c·w from its sums Σw·y and Σw·w, which must be positive.
fn fitted_compliance(wy_all: f64, ww_all: f64) -> Result<f64, EstimateError> {
    if ww_all == 0.0 {
        return Err(EstimateError::Singular {
            estimator: "homogeneous output-error",
            why: "every load vector is zero at the free nodes, so the predicted displacements do not depend on k̃".into(),
        });
    }
    let c = wy_all / ww_all;
    if c <= 0.0 {
        return Err(EstimateError::Singular {
            estimator: "homogeneous output-error",
            why: format!(
                "the observed displacements point against the loads (fitted 1/k̃ = {c:.3e} ≤ 0); check the signs of the loads and displacements"
            ),
        });
    }
    Ok(c)
}
