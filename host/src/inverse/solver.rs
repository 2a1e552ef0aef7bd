//! Where the estimators' SPD systems are solved: on the target (the matrix encoded as
//! instruction words, uploaded once, each right-hand side solved with mixed-precision
//! refinement, exactly as `deform solve` does) or by the host's f64 reference CG.

use deform_shared::protocol::MAX_DIRECTIONS;
use serde::Serialize;
use serialport::SerialPort;

use crate::encode::{encode_with, EncodeError, EncodeOptions, Partition};
use crate::link::{LinkError, Port, Target};
use crate::model::Csr;
use crate::precondition::Scaled;
use crate::reference;
use crate::refine::{solve_refined, RefineError, RefineParams};

/// The solver for every SPD system of an estimate.
pub enum SpdSolver<'a, P: Port = Box<dyn SerialPort>> {
    /// The f64 reference CG, to a true relative residual of `tol`.
    Host { tol: f64 },
    /// The target's fixed-point CG, refined on the host to a true relative residual of `tol`.
    Target {
        target: &'a mut Target<P>,
        tol: f64,
        max_solves: u32,
    },
}

/// How much solving an estimate took.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct SolveCount {
    /// Right-hand sides solved (systems with a zero right-hand side are not counted).
    pub systems: u32,
    /// Solves run on the target, refinement steps included (0 on the host).
    pub target_solves: u32,
    /// CG iterations, over all solves.
    pub iterations: u64,
}

#[derive(Debug, thiserror::Error)]
pub enum SpdSolveError {
    #[error("encoding the matrix as instruction words")]
    Encode(#[from] EncodeError),
    #[error("sending the matrix to the target")]
    Upload(#[source] LinkError),
    #[error("solving on the target")]
    Refine(#[from] RefineError),
    #[error("f64 reference CG")]
    Reference(#[from] reference::SolveError),
    #[error("CG did not converge (relative residual {residual:.3e} after {iterations} iterations): the system is singular or badly conditioned")]
    NotConverged { residual: f64, iterations: usize },
}

impl<P: Port> SpdSolver<'_, P> {
    pub fn is_target(&self) -> bool {
        matches!(self, SpdSolver::Target { .. })
    }

    /// Solves a·x = b for every b of `rhs`; a zero b gives x = 0 without a solve.
    pub fn solve_all(
        &mut self,
        a: &Csr,
        rhs: &[Vec<f64>],
        count: &mut SolveCount,
    ) -> Result<Vec<Vec<f64>>, SpdSolveError> {
        let n = a.n();
        let nonzero = |b: &Vec<f64>| b.iter().any(|&v| v != 0.0);
        match self {
            SpdSolver::Host { tol } => rhs
                .iter()
                .map(|b| {
                    if !nonzero(b) {
                        return Ok(vec![0.0; n]);
                    }
                    let sol = reference::solve(a, b, None, *tol, 20 * n.max(100))?;
                    count.systems += 1;
                    count.iterations += sol.iterations as u64;
                    if !sol.converged {
                        return Err(SpdSolveError::NotConverged {
                            residual: sol.relative_residual,
                            iterations: sol.iterations,
                        });
                    }
                    Ok(sol.x)
                })
                .collect(),
            SpdSolver::Target {
                target,
                tol,
                max_solves,
            } => {
                if !rhs.iter().any(nonzero) {
                    return Ok(vec![vec![0.0; n]; rhs.len()]);
                }
                // Every MVU the target has, half storage when the system is persymmetric.
                let options = EncodeOptions {
                    mvus: target.info().harts.max(1),
                    partition: Partition::Rows,
                    use_symmetry: true,
                };
                let encoded = encode_with(a, &options)?.matrix;
                target
                    .check_matrix_fits(&encoded)
                    .map_err(SpdSolveError::Upload)?;
                target
                    .upload_matrix(&encoded)
                    .map_err(SpdSolveError::Upload)?;
                let params = RefineParams {
                    tol: *tol,
                    max_solves: *max_solves,
                    max_iterations: crate::refine::default_max_iterations(n),
                    fuse: true,
                };
                let unscaled = Scaled {
                    matrix: a.clone(),
                    scale: None,
                };
                let mut solutions = Vec::with_capacity(rhs.len());
                // Up to three right-hand sides share each fused target solve.
                for group in rhs.chunks(MAX_DIRECTIONS) {
                    let group: Vec<&[f64]> = group.iter().map(Vec::as_slice).collect();
                    let got = solve_refined(target, a, &unscaled, &group, params)?;
                    count.target_solves += got.reports.len() as u32;
                    for direction in got.directions {
                        if direction.solves > 0 {
                            count.systems += 1;
                        }
                        count.iterations += direction.iterations as u64;
                        solutions.push(direction.x);
                    }
                }
                Ok(solutions)
            }
        }
    }
}
