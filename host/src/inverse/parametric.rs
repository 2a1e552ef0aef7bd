//! The parametric model of thesis 3.2.2: every spring s has k̃_s = wₛᵀa with
//! wₛ = (1, Σ_d Δl_s^d, Σ_d (Δl_s^d)²) and a = (α0, α1, α2), Δl_s^d = l̃_q^d − l̃_p^d for the
//! spring p–q (p < q) in the observed set (the convention of `deform simulate --alpha`).
//!
//! The load at a free node p is f_p^d = Σ_s k̃_s·(l̃_p^d − l̃_q^d) = aᵀg_p^d with
//! g_p^d = Σ_s (l̃_p^d − l̃_q^d)·wₛ (eq. 48), so least squares over nodes, directions and sets is
//! the 3×3 normal system H·a = Σ g·f with H = Σ g·gᵀ (eq. 50). It is solved by CG (the f64
//! reference; three unknowns are not worth a round trip to the target) after symmetric
//! diagonal scaling, since the three columns differ in scale by the size of Δl.

use serde::Serialize;

use super::{EstimateError, Network, Observations};
use crate::model::sparse::CsrBuilder;
use crate::reference;

/// The estimated α0, α1, α2.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ParametricEstimate {
    pub alpha: [f64; 3],
    /// ‖f − G·a‖₂ / ‖f‖₂ over free nodes, directions and sets.
    pub relative_residual: f64,
    pub equations: usize,
    /// CG iterations on the 3×3 system.
    pub iterations: usize,
}

/// A pivot of the scaled normal matrix below this means its columns are dependent.
const SINGULAR_PIVOT: f64 = 1e-12;

/// Solves the 3×3 SPD system `h·x = b` by CG after Jacobi scaling; a (numerically) singular
/// `h` is refused with the index of the dependent column.
pub fn solve_normal_3x3(h: [[f64; 3]; 3], b: [f64; 3]) -> Result<([f64; 3], usize), usize> {
    let scale: Vec<f64> = (0..3)
        .map(|i| {
            if h[i][i] > 0.0 {
                1.0 / h[i][i].sqrt()
            } else {
                0.0
            }
        })
        .collect();
    let hs: Vec<Vec<f64>> = (0..3)
        .map(|i| (0..3).map(|j| h[i][j] * scale[i] * scale[j]).collect())
        .collect();
    // Cholesky pivots tell singular from merely badly scaled.
    let mut l = [[0.0f64; 3]; 3];
    for j in 0..3 {
        let pivot = hs[j][j] - (0..j).map(|k| l[j][k] * l[j][k]).sum::<f64>();
        if pivot.is_nan() || pivot <= SINGULAR_PIVOT {
            return Err(j);
        }
        l[j][j] = pivot.sqrt();
        for i in j + 1..3 {
            l[i][j] = (hs[i][j] - (0..j).map(|k| l[i][k] * l[j][k]).sum::<f64>()) / l[j][j];
        }
    }
    let mut builder = CsrBuilder::new(3, 9);
    for row in &hs {
        builder
            .push_row(row.iter().copied().enumerate())
            .expect("3 columns");
    }
    let hs = builder.finish().expect("3 rows");
    let bs: Vec<f64> = (0..3).map(|i| b[i] * scale[i]).collect();
    let sol = reference::solve(&hs, &bs, None, 1e-15, 100).map_err(|_| 0usize)?;
    Ok(([0, 1, 2].map(|i| sol.x[i] * scale[i]), sol.iterations))
}

/// wₛ of every spring for displacements `u`.
fn spring_features(net: &Network, u: &[Vec<f64>; 3]) -> Vec<[f64; 3]> {
    net.springs()
        .iter()
        .map(|&(p, q)| {
            let dl = [0, 1, 2].map(|d| u[d][q] - u[d][p]);
            [1.0, dl.iter().sum(), dl.iter().map(|x| x * x).sum::<f64>()]
        })
        .collect()
}

/// α0, α1, α2 by least squares over every set (eq. 50).
pub fn estimate(net: &Network, obs: &Observations) -> Result<ParametricEstimate, EstimateError> {
    if obs.sets.is_empty() {
        return Err(EstimateError::NoSets);
    }
    let mut h = [[0.0; 3]; 3];
    let mut b = [0.0; 3];
    let mut ff = 0.0;
    let mut equations = 0;
    for set in &obs.sets {
        let u = net.effective_displacements(set);
        let w = spring_features(net, &u);
        for d in 0..3 {
            for p in net.free_nodes() {
                let mut g = [0.0; 3];
                for &s in net.incident(p) {
                    let stretch = u[d][p] - u[d][net.other_end(s, p)];
                    for (g, w) in g.iter_mut().zip(w[s]) {
                        *g += stretch * w;
                    }
                }
                let f = set.f[d][p];
                for i in 0..3 {
                    b[i] += g[i] * f;
                    for j in 0..3 {
                        h[i][j] += g[i] * g[j];
                    }
                }
                ff += f * f;
                equations += 1;
            }
        }
    }
    const NAMES: [&str; 3] = ["1 (α0)", "ΣΔl (α1)", "ΣΔl² (α2)"];
    let (alpha, iterations) = solve_normal_3x3(h, b).map_err(|j| EstimateError::Singular {
        estimator: "parametric",
        why: format!(
            "the column {} of eq. 48 depends on the others in these observations (e.g. all displacements zero, \
             or too few sets for three parameters); observe under larger or more varied loads",
            NAMES[j]
        ),
    })?;
    let mut rss = 0.0;
    for set in &obs.sets {
        let u = net.effective_displacements(set);
        let w = spring_features(net, &u);
        for d in 0..3 {
            for p in net.free_nodes() {
                let predicted: f64 = net
                    .incident(p)
                    .iter()
                    .map(|&s| {
                        let k: f64 = (0..3).map(|i| w[s][i] * alpha[i]).sum();
                        k * (u[d][p] - u[d][net.other_end(s, p)])
                    })
                    .sum();
                rss += (set.f[d][p] - predicted).powi(2);
            }
        }
    }
    Ok(ParametricEstimate {
        alpha,
        relative_residual: if ff > 0.0 { (rss / ff).sqrt() } else { 0.0 },
        equations,
        iterations,
    })
}
