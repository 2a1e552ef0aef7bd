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

/// A column of G whose entries cancel to below this fraction of their terms' size is rounding,
/// not information: any value of its parameter fits the observations alike.
const CANCELLED: f64 = 1e-9;

/// The Jacobi-scaled normal matrix's condition number above which the estimate is refused:
/// rounding alone would move α by more than 1e-4 of itself (f64's ε ≈ 2.2e-16 times this).
const MAX_CONDITION: f64 = 1e12;

/// The parameters' names, for messages: which column of eq. 48 each multiplies.
const PARAMETERS: [&str; 3] = [
    "α0 (the constant term)",
    "α1 (the ΣΔl term)",
    "α2 (the ΣΔl² term)",
];

/// Refuses observations that do not determine α: a column of G that cancels to rounding (its
/// parameter multiplies nothing the data can see), or a normal matrix whose condition number,
/// after Jacobi scaling, exceeds [`MAX_CONDITION`] (two columns all but proportional). Neither
/// shows in the residual: an undetermined α fits the data as well as the truth (the README's
/// one-load-case example gave α1 = 78.2 for a truth of 0.5 at a residual of 3e-15).
fn check_determined(
    h: &[[f64; 3]; 3],
    magnitude: &[f64; 3],
    sets: usize,
) -> Result<(), EstimateError> {
    let more = if sets == 1 {
        "observe more than this one load case"
    } else {
        "observe more load cases"
    };
    let remedy = format!(
        "{more}, with loads at other nodes and in other directions (`deform observe --append \
         --load …`)"
    );
    for j in 0..3 {
        let ratio = (h[j][j] / magnitude[j]).sqrt();
        if magnitude[j] > 0.0 && ratio < CANCELLED {
            // ΣΔl cancels when every load's components sum to zero (see
            // `spring_feature_sizes`).
            let hint = if j == 1 {
                " (on a uniform model, loads whose x, y and z components sum to zero move every \
                 node with u_x + u_y + u_z = 0: give a load whose components do not)"
            } else {
                ""
            };
            return Err(EstimateError::Singular {
                estimator: "parametric",
                why: format!(
                    "{} is not determined by these observations: its column of eq. 48 cancels \
                     to rounding ({ratio:.1e} of its terms' size), so any value fits them \
                     alike{hint}; {remedy}",
                    PARAMETERS[j]
                ),
            });
        }
    }
    let scale = [0, 1, 2].map(|i| {
        if h[i][i] > 0.0 {
            1.0 / h[i][i].sqrt()
        } else {
            0.0
        }
    });
    let scaled = [0, 1, 2].map(|i| [0, 1, 2].map(|j| h[i][j] * scale[i] * scale[j]));
    let (values, vectors) = symmetric_eigen_3x3(scaled);
    let (low, high) = (0..3).fold((0, 0), |(lo, hi), i| {
        (
            if values[i] < values[lo] { i } else { lo },
            if values[i] > values[hi] { i } else { hi },
        )
    });
    let condition = values[high] / values[low].max(f64::MIN_POSITIVE);
    if condition > MAX_CONDITION {
        // The parameter the least determined combination leans on most.
        let worst = (0..3)
            .max_by(|&a, &b| vectors[a][low].abs().total_cmp(&vectors[b][low].abs()))
            .unwrap_or(0);
        return Err(EstimateError::Singular {
            estimator: "parametric",
            why: format!(
                "{} is not determined by these observations: the normal matrix's condition \
                 number is {condition:.1e} (above {MAX_CONDITION:.0e}), so its columns are all \
                 but dependent and rounding alone moves the estimate; {remedy}",
                PARAMETERS[worst]
            ),
        });
    }
    Ok(())
}

/// Eigenvalues and eigenvectors (columns) of a symmetric 3×3 matrix by cyclic Jacobi rotations.
/// Hand-written: three unknowns do not justify a linear-algebra crate in the host, and the
/// rotations converge to f64 precision in a few sweeps.
fn symmetric_eigen_3x3(mut a: [[f64; 3]; 3]) -> ([f64; 3], [[f64; 3]; 3]) {
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _ in 0..50 {
        let off = a[0][1].abs() + a[0][2].abs() + a[1][2].abs();
        if off <= f64::EPSILON * (a[0][0].abs() + a[1][1].abs() + a[2][2].abs()) {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let sign = if theta >= 0.0 { 1.0 } else { -1.0 };
            let t = sign / (theta.abs() + (theta * theta + 1.0).sqrt());
            let (c, s) = (1.0 / (t * t + 1.0).sqrt(), t / (t * t + 1.0).sqrt());
            for k in 0..3 {
                let (akp, akq) = (a[k][p], a[k][q]);
                a[k][p] = c * akp - s * akq;
                a[k][q] = s * akp + c * akq;
            }
            for k in 0..3 {
                let (apk, aqk) = (a[p][k], a[q][k]);
                a[p][k] = c * apk - s * aqk;
                a[q][k] = s * apk + c * aqk;
            }
            for row in &mut v {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    ([a[0][0], a[1][1], a[2][2]], v)
}

/// What each wₛ would be without cancellation: (1, Σ_d |Δl^d|, ΣΔl²). A load whose components
/// sum to zero on an isotropic model moves every node by u with Σ_d u^d = 0, so ΣΔl cancels in
/// every spring and α1 multiplies nothing (the README's old example).
fn spring_feature_sizes(net: &Network, u: &[Vec<f64>; 3]) -> Vec<[f64; 3]> {
    net.springs()
        .iter()
        .map(|&(p, q)| {
            let dl = [0, 1, 2].map(|d| u[d][q] - u[d][p]);
            [
                1.0,
                dl.iter().map(|x| x.abs()).sum(),
                dl.iter().map(|x| x * x).sum::<f64>(),
            ]
        })
        .collect()
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
    // Per column of G, Σ over the equations of (Σ_s |stretch|·|wₛ| term by term)²: what H's
    // diagonal would be without cancellation (see `check_determined`).
    let mut magnitude = [0.0; 3];
    let mut ff = 0.0;
    let mut equations = 0;
    for set in &obs.sets {
        let u = net.effective_displacements(set);
        let w = spring_features(net, &u);
        let w_size = spring_feature_sizes(net, &u);
        for d in 0..3 {
            for p in net.free_nodes() {
                let mut g = [0.0; 3];
                let mut size = [0.0; 3];
                for &s in net.incident(p) {
                    let stretch = u[d][p] - u[d][net.other_end(s, p)];
                    for i in 0..3 {
                        g[i] += stretch * w[s][i];
                        size[i] += stretch.abs() * w_size[s][i];
                    }
                }
                for i in 0..3 {
                    magnitude[i] += size[i] * size[i];
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
    check_determined(&h, &magnitude, obs.sets.len())?;
    let (alpha, iterations) = solve_normal_3x3(h, b).map_err(|j| EstimateError::Singular {
        estimator: "parametric",
        why: format!(
            "the column {} of eq. 48 depends on the others in these observations (e.g. all displacements zero, \
             or too few sets for three parameters); observe under larger or more varied loads",
            PARAMETERS[j]
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
    let relative_residual = if ff > 0.0 { (rss / ff).sqrt() } else { 0.0 };
    super::ensure_finite(
        "parametric",
        &[
            ("α0", alpha[0]),
            ("α1", alpha[1]),
            ("α2", alpha[2]),
            ("the relative residual", relative_residual),
        ],
    )?;
    Ok(ParametricEstimate {
        alpha,
        relative_residual,
        equations,
        iterations,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_eigen_decomposition_reconstructs_the_matrix() {
        let a = [[4.0, 1.0, -2.0], [1.0, 3.0, 0.5], [-2.0, 0.5, 5.0]];
        let (values, v) = symmetric_eigen_3x3(a);
        for k in 0..3 {
            for i in 0..3 {
                let av: f64 = (0..3).map(|j| a[i][j] * v[j][k]).sum();
                assert!((av - values[k] * v[i][k]).abs() < 1e-12, "{values:?} {v:?}");
            }
        }
        let trace: f64 = values.iter().sum();
        assert!((trace - 12.0).abs() < 1e-12);
    }

    #[test]
    fn cancelled_or_dependent_columns_are_refused_with_the_parameter_named() {
        // Column 1 cancels: its entries are 1e-12 of their terms' size.
        let h = [[1.0, 0.0, 0.2], [0.0, 1e-24, 0.0], [0.2, 0.0, 1.0]];
        let e = check_determined(&h, &[1.0, 1.0, 1.0], 1)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("α1") && e.contains("sum to zero") && e.contains("this one load case"),
            "{e}"
        );
        // Columns 0 and 2 all but proportional.
        let h = [
            [1.0, 0.0, 1.0 - 1e-14],
            [0.0, 1.0, 0.0],
            [1.0 - 1e-14, 0.0, 1.0],
        ];
        let e = check_determined(&h, &[1.0, 1.0, 1.0], 3)
            .unwrap_err()
            .to_string();
        assert!(e.contains("condition number") && !e.contains("α1"), "{e}");
        let h = [[1.0, 0.3, 0.1], [0.3, 1.0, 0.2], [0.1, 0.2, 1.0]];
        check_determined(&h, &[1.0, 1.0, 1.0], 3).unwrap();
    }
}
