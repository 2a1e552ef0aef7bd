//! Mixed-precision iterative refinement around the target's fixed-point CG.
//!
//! The target solves A·d = r in block floating point, which by itself levels off at a relative
//! residual of about 1e-8 (the mantissas keep 29 bits). The host then measures the *true* residual
//! r = b − A·x in f64, and while it is above the requested tolerance sends r as a new right-hand
//! side and adds the correction d to x. Each round gains the target's precision again, so a
//! tolerance far below what fixed point reaches on its own takes only a few rounds; the matrix
//! stays resident on the target throughout. `--tol` therefore always means the true residual.

use deform_shared::protocol::{PhaseCounters, SolveParams, Start};

use crate::link::{LinkError, Port, Target};
use crate::model::Csr;
use crate::reference::{norm, residual};

/// The target never gets an inner tolerance tighter than this: below it the fixed-point
/// iteration only burns cycles, and refinement does better.
pub const FIXED_POINT_FLOOR: f64 = 1e-7;

/// How hard to try.
#[derive(Debug, Clone, Copy)]
pub struct RefineParams {
    /// Stop once ‖b − A·x‖₂ / ‖b‖₂ ≤ `tol` (f64, measured on the host).
    pub tol: f64,
    /// At most this many target solves (the first one included).
    pub max_solves: u32,
    /// CG iteration cap for each target solve.
    pub max_iterations: u32,
}

/// What the refinement produced, with the target's work summed over every solve.
#[derive(Debug, Clone)]
pub struct Refined {
    pub x: Vec<f64>,
    /// True relative residual of `x`.
    pub relative_residual: f64,
    /// Target solves (1 + refinement steps).
    pub solves: u32,
    /// CG iterations over all solves.
    pub iterations: u32,
    pub words_per_iteration: u32,
    pub mvu: PhaseCounters,
    pub svu: PhaseCounters,
}

#[derive(Debug, thiserror::Error)]
pub enum RefineError {
    #[error(transparent)]
    Link(#[from] LinkError),
    #[error(
        "the true relative residual is still {residual:.3e} after {solves} target solves \
         (tolerance {tol:.1e}); raise --max-solves or --max-iter, or loosen --tol"
    )]
    NotConverged {
        residual: f64,
        solves: u32,
        tol: f64,
    },
}

fn add(total: &mut PhaseCounters, more: PhaseCounters) {
    total.cycles += more.cycles;
    total.instructions += more.instructions;
}

/// Solves A·x = b on `target` (which must hold A already) to a true relative residual of
/// `params.tol`. A zero `b` gives x = 0 without a target solve.
pub fn solve_refined<P: Port>(
    target: &mut Target<P>,
    a: &Csr,
    b: &[f64],
    params: RefineParams,
) -> Result<Refined, RefineError> {
    let n = b.len();
    let b_norm = norm(b);
    let mut out = Refined {
        x: vec![0.0; n],
        relative_residual: 0.0,
        solves: 0,
        iterations: 0,
        words_per_iteration: 0,
        mvu: PhaseCounters::default(),
        svu: PhaseCounters::default(),
    };
    if b_norm == 0.0 {
        return Ok(out);
    }
    let solve = SolveParams {
        max_iterations: params.max_iterations,
        tolerance: params.tol.max(FIXED_POINT_FLOOR),
        start: Start::Zero,
        directions: 1,
    };
    let mut r = b.to_vec();
    out.relative_residual = 1.0;
    while out.relative_residual > params.tol {
        if out.solves >= params.max_solves {
            return Err(RefineError::NotConverged {
                residual: out.relative_residual,
                solves: out.solves,
                tol: params.tol,
            });
        }
        let (report, d) = target.solve_for(&r, solve)?;
        out.solves += 1;
        out.iterations += report.iterations;
        out.words_per_iteration = report.words_per_iteration;
        add(&mut out.mvu, report.mvu);
        add(&mut out.svu, report.svu);
        for (x, d) in out.x.iter_mut().zip(&d) {
            *x += d;
        }
        r = residual(a, b, &out.x);
        out.relative_residual = norm(&r) / b_norm;
    }
    Ok(out)
}
