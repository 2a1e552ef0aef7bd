//! The f64 conjugate-gradient solver of thesis 2.3: the "general purpose computer" baseline
//! that the fixed-point firmware is measured against.
//!
//! Plain, unpreconditioned CG, exactly the thesis's iteration, so that iteration counts compare
//! like with like. The stopping test uses the cheap recursive residual, but a solve only counts
//! as converged once the *true* residual ‖b − Kx‖₂/‖b‖₂ meets the tolerance: if rounding has
//! let the two drift apart, CG restarts from the current x with the true residual.

use crate::model::Csr;

/// What a solve produced.
#[derive(Debug, Clone, PartialEq)]
pub struct Solution {
    pub x: Vec<f64>,
    /// CG iterations performed (matrix-vector products, not counting residual checks).
    pub iterations: usize,
    /// The true relative residual ‖b − Kx‖₂/‖b‖₂ of the returned x (0 for b = 0).
    pub relative_residual: f64,
    /// Whether `relative_residual <= tol`; false if `max_iter` ran out first.
    pub converged: bool,
}

/// Why a solve could not run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SolveError {
    #[error("{what} has length {found}, K is {n}×{n}")]
    DimensionMismatch {
        what: &'static str,
        found: usize,
        n: usize,
    },
    #[error("{what} has a non-finite entry")]
    NotFinite { what: &'static str },
    #[error("tolerance {0} must be finite and non-negative")]
    InvalidTolerance(f64),
    #[error("pᵀKp = {curvature} ≤ 0 at iteration {iteration}: K is not positive definite")]
    NotPositiveDefinite { iteration: usize, curvature: f64 },
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// ‖a‖₂.
pub fn norm(a: &[f64]) -> f64 {
    dot(a, a).sqrt()
}

/// max |aᵢ|: the scale against which deviations from the reference are quoted.
pub fn max_abs(a: &[f64]) -> f64 {
    a.iter().fold(0.0f64, |m, x| m.max(x.abs()))
}

/// max |aᵢ − bᵢ|: how far a solution lies from the reference, node by node.
pub fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

/// b − K·x.
pub fn residual(k: &Csr, b: &[f64], x: &[f64]) -> Vec<f64> {
    let mut r = k.mul_vec(x);
    for (r_i, b_i) in r.iter_mut().zip(b) {
        *r_i = b_i - *r_i;
    }
    r
}

/// ‖b − K·x‖₂ / ‖b‖₂, or ‖K·x‖₂ when b = 0 (so that x = 0 scores 0).
pub fn relative_residual(k: &Csr, b: &[f64], x: &[f64]) -> f64 {
    let r = norm(&residual(k, b, x));
    let b_norm = norm(b);
    if b_norm == 0.0 {
        r
    } else {
        r / b_norm
    }
}

/// Solves K·x = b for symmetric positive definite K by CG, starting from `x0` (zero if `None`),
/// until ‖b − Kx‖₂/‖b‖₂ ≤ `tol` or `max_iter` iterations. b = 0 gives x = 0 at once.
pub fn solve(
    k: &Csr,
    b: &[f64],
    x0: Option<&[f64]>,
    tol: f64,
    max_iter: usize,
) -> Result<Solution, SolveError> {
    let n = k.n();
    let check = |what, v: &[f64]| {
        if v.len() != n {
            Err(SolveError::DimensionMismatch {
                what,
                found: v.len(),
                n,
            })
        } else if v.iter().any(|e| !e.is_finite()) {
            Err(SolveError::NotFinite { what })
        } else {
            Ok(())
        }
    };
    check("b", b)?;
    if let Some(x0) = x0 {
        check("x0", x0)?;
    }
    if !(tol.is_finite() && tol >= 0.0) {
        return Err(SolveError::InvalidTolerance(tol));
    }

    let b_norm = norm(b);
    if b_norm == 0.0 {
        return Ok(Solution {
            x: vec![0.0; n],
            iterations: 0,
            relative_residual: 0.0,
            converged: true,
        });
    }
    let target = tol * b_norm;
    let mut x = x0.map_or_else(|| vec![0.0; n], <[f64]>::to_vec);
    let mut r = residual(k, b, &x);
    let mut rr = dot(&r, &r);
    let mut p = r.clone();
    let mut kp = vec![0.0; n];
    let mut iterations = 0;

    while rr.sqrt() > target && iterations < max_iter {
        k.mul_vec_into(&p, &mut kp);
        let curvature = dot(&p, &kp);
        if curvature.is_nan() || curvature <= 0.0 {
            return Err(SolveError::NotPositiveDefinite {
                iteration: iterations,
                curvature,
            });
        }
        let alpha = rr / curvature;
        for i in 0..n {
            x[i] += alpha * p[i];
            r[i] -= alpha * kp[i];
        }
        iterations += 1;
        let mut rr_next = dot(&r, &r);
        if rr_next.sqrt() <= target {
            // Confirm with the true residual; if it disagrees, restart from here.
            r = residual(k, b, &x);
            rr_next = dot(&r, &r);
            if rr_next.sqrt() > target {
                p.copy_from_slice(&r);
                rr = rr_next;
                continue;
            }
        }
        let beta = rr_next / rr;
        for i in 0..n {
            p[i] = r[i] + beta * p[i];
        }
        rr = rr_next;
    }

    let relative_residual = norm(&residual(k, b, &x)) / b_norm;
    Ok(Solution {
        x,
        iterations,
        relative_residual,
        converged: relative_residual <= tol,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::sparse::test_support::{dense_solve, from_dense};
    use crate::model::{Axis, Connection, Grid, Model, ModelSpec, Node};

    fn spec(grid: (usize, usize, usize), connection: Connection) -> ModelSpec {
        let grid = Grid::new(grid.0, grid.1, grid.2).unwrap();
        ModelSpec {
            grid,
            connection,
            loads: vec![
                ModelSpec::default_load(grid),
                crate::model::PointLoad {
                    node: Node::new(1, 1, 1),
                    force: [0.3, -2.0, 0.7],
                },
            ],
            ..ModelSpec::thesis_example()
        }
    }

    #[test]
    fn matches_gaussian_elimination_on_small_grids() {
        for connection in [Connection::Axial, Connection::AxialShear] {
            for dims in [(2, 2, 2), (3, 3, 3), (4, 3, 5)] {
                let model = Model::build(&spec(dims, connection)).unwrap();
                for axis in Axis::ALL {
                    let k = model.stiffness_matrix(axis);
                    let b = model.load(axis);
                    let exact = dense_solve(&k, b);
                    let sol = solve(&k, b, None, 1e-14, 10 * k.n()).unwrap();
                    assert!(sol.converged, "{dims:?} {axis}: {}", sol.relative_residual);
                    let scale = exact.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(1.0);
                    for (got, want) in sol.x.iter().zip(&exact) {
                        assert!(
                            (got - want).abs() <= 1e-10 * scale,
                            "{dims:?} {axis}: {got} vs {want}"
                        );
                    }
                    // The same solution through A and the scaled right-hand side.
                    let via_a = solve(
                        model.unit_matrix(),
                        &model.scaled_rhs(axis),
                        None,
                        1e-14,
                        10 * k.n(),
                    )
                    .unwrap();
                    for (got, want) in via_a.x.iter().zip(&exact) {
                        assert!((got - want).abs() <= 1e-10 * scale);
                    }
                }
            }
        }
    }

    #[test]
    fn reaches_tolerance_on_the_thesis_example_in_both_models() {
        for connection in [Connection::Axial, Connection::AxialShear] {
            let model = Model::build(&ModelSpec {
                connection,
                ..ModelSpec::thesis_example()
            })
            .unwrap();
            let k = model.stiffness_matrix(Axis::X);
            let b = model.load(Axis::X);
            let sol = solve(&k, b, None, 1e-10, 5000).unwrap();
            assert!(sol.converged, "{connection}: {sol:?}");
            assert!(sol.relative_residual <= 1e-10);
            assert!(relative_residual(&k, b, &sol.x) <= 1e-10);
            assert!(
                sol.iterations > 10 && sol.iterations < 1000,
                "{}",
                sol.iterations
            );
            // The pushed node moves in +x, fixed nodes do not move.
            let loaded = model.grid().index(Node::new(0, 5, 5)).unwrap();
            assert!(sol.x[loaded] > 0.0);
            for (p, &fixed) in model.fixed_mask().iter().enumerate() {
                if fixed {
                    assert_eq!(sol.x[p], 0.0);
                }
            }
        }
    }

    #[test]
    fn zero_right_hand_side_gives_zero() {
        let k = from_dense(&[vec![2.0, -1.0], vec![-1.0, 2.0]]);
        let sol = solve(&k, &[0.0, 0.0], Some(&[3.0, 4.0]), 1e-12, 10).unwrap();
        assert_eq!(
            sol,
            Solution {
                x: vec![0.0, 0.0],
                iterations: 0,
                relative_residual: 0.0,
                converged: true
            }
        );
    }

    #[test]
    fn warm_start_at_the_solution_takes_no_iterations() {
        let k = from_dense(&[vec![2.0, -1.0], vec![-1.0, 2.0]]);
        let sol = solve(&k, &[1.0, 1.0], Some(&[1.0, 1.0]), 1e-12, 10).unwrap();
        assert_eq!(sol.iterations, 0);
        assert!(sol.converged);
    }

    #[test]
    fn reports_running_out_of_iterations() {
        let model = Model::build(&ModelSpec::thesis_example()).unwrap();
        let sol = solve(
            model.unit_matrix(),
            &model.scaled_rhs(Axis::X),
            None,
            1e-12,
            3,
        )
        .unwrap();
        assert_eq!(sol.iterations, 3);
        assert!(!sol.converged);
        assert!(sol.relative_residual > 1e-12);
    }

    #[test]
    fn refuses_bad_input() {
        let k = from_dense(&[vec![2.0, -1.0], vec![-1.0, 2.0]]);
        assert!(matches!(
            solve(&k, &[1.0], None, 1e-9, 5),
            Err(SolveError::DimensionMismatch { what: "b", .. })
        ));
        assert!(matches!(
            solve(&k, &[1.0, 1.0], Some(&[0.0]), 1e-9, 5),
            Err(SolveError::DimensionMismatch { what: "x0", .. })
        ));
        assert!(matches!(
            solve(&k, &[1.0, f64::NAN], None, 1e-9, 5),
            Err(SolveError::NotFinite { .. })
        ));
        assert!(matches!(
            solve(&k, &[1.0, 1.0], None, -1.0, 5),
            Err(SolveError::InvalidTolerance(_))
        ));
        let indefinite = from_dense(&[vec![1.0, 0.0], vec![0.0, -1.0]]);
        assert!(matches!(
            solve(&indefinite, &[0.0, 1.0], None, 1e-9, 5),
            Err(SolveError::NotPositiveDefinite { .. })
        ));
    }

    #[test]
    fn residual_helpers() {
        let k = from_dense(&[vec![2.0, -1.0], vec![-1.0, 2.0]]);
        assert_eq!(residual(&k, &[1.0, 1.0], &[1.0, 0.0]), vec![-1.0, 2.0]);
        assert_eq!(relative_residual(&k, &[0.0, 0.0], &[0.0, 0.0]), 0.0);
        assert_eq!(relative_residual(&k, &[3.0, 4.0], &[0.0, 0.0]), 1.0);
    }
}
