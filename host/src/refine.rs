//! Mixed-precision iterative refinement around the target's fixed-point CG.
//!
//! The target solves A·d = r in block floating point, which by itself levels off at a relative
//! residual of about 1e-8 (the mantissas keep 29 bits). The host then measures the *true* residual
//! r = b − A·x in f64, and while it is above the requested tolerance sends r as a new right-hand
//! side and adds the correction d to x. Each round gains the target's precision again, so a
//! tolerance far below what fixed point reaches on its own takes only a few rounds; the matrix
//! stays resident on the target throughout. `--tol` therefore always means the true residual.
//!
//! Up to three right-hand sides with the same matrix (the x, y and z directions, thesis eq. 38)
//! are refined together: every round sends the residuals of the directions not yet converged
//! and solves them in one fused target run, so each matrix word fetched serves all of them.
//!
//! With Jacobi preconditioning ([`crate::precondition`]) the target holds S = D^-1/2·A·D^-1/2:
//! the residual goes in as s⊙r and the correction comes back as s⊙d, while the residual is
//! still measured against A itself.

use deform_shared::protocol::{PhaseCounters, SolveParams, SolveReport, Start, MAX_DIRECTIONS};
// The target never gets an inner tolerance tighter than this: below it refinement does better.
use deform_shared::qformat::FIXED_POINT_FLOOR;

use crate::link::{LinkError, Port, Target};
use crate::model::Csr;
use crate::precondition::Scaled;
use crate::reference::{norm, residual};

/// Target solves per right-hand side (the first plus refinement steps) when no flag or
/// scenario says: `solve --max-solves`, `simulate --dynamic --max-solves`, `estimate`.
pub const DEFAULT_MAX_SOLVES: u32 = 8;

/// `--tol` as every command takes it: a relative residual in (0, 1).
pub fn parse_tolerance(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(t) if t.is_finite() && t > 0.0 && t < 1.0 => Ok(t),
        Ok(_) => {
            Err("the tolerance must be a number in (0, 1): greater than 0 and less than 1".into())
        }
        Err(e) => Err(format!("not a number: {e}")),
    }
}

/// CG iterations allowed per target solve when no flag says: 10·n (CG converges in at most n
/// steps in exact arithmetic; fixed point needs some more), capped at what the wire carries.
pub fn default_max_iterations(n: usize) -> u32 {
    (10 * n).min(u32::MAX as usize) as u32
}

/// The target's inner tolerance is this fraction of `--tol`: its recursive fixed-point residual
/// can sit a little below the true f64 one, and a solve that stops right at `--tol` would then
/// miss it by a hair and cost a whole refinement step.
pub const INNER_MARGIN: f64 = 0.5;

/// How hard to try.
#[derive(Debug, Clone, Copy)]
pub struct RefineParams {
    /// Stop once ‖b − A·x‖₂ / ‖b‖₂ ≤ `tol` (f64, measured on the host).
    pub tol: f64,
    /// At most this many target solves per direction (the first one included).
    pub max_solves: u32,
    /// CG iteration cap for each target solve.
    pub max_iterations: u32,
    /// Solve the directions together in one fused target run (else one after the other).
    pub fuse: bool,
}

/// What the refinement produced for one right-hand side.
#[derive(Debug, Clone)]
pub struct DirectionResult {
    pub x: Vec<f64>,
    /// True relative residual of `x`.
    pub relative_residual: f64,
    /// Target solves this direction took part in (1 + refinement steps; 0 for b = 0).
    pub solves: u32,
    /// CG iterations of this direction over all its solves.
    pub iterations: u32,
}

/// Every direction's result and every target solve's report.
#[derive(Debug, Clone)]
pub struct Refined {
    pub directions: Vec<DirectionResult>,
    /// The target's report of each solve, in order (a fused solve is one report).
    pub reports: Vec<SolveReport>,
}

impl Refined {
    /// Matrix words the MVUs fetched over all solves.
    pub fn words_fetched(&self) -> u64 {
        self.reports
            .iter()
            .map(|r| r.words_per_iteration as u64 * r.iterations as u64)
            .sum()
    }

    /// Words the same iterations would have fetched with every direction solved on its own.
    pub fn words_fetched_unfused(&self) -> u64 {
        self.reports
            .iter()
            .map(|r| {
                r.words_per_iteration as u64
                    * r.directions
                        .iter()
                        .map(|d| d.iterations as u64)
                        .sum::<u64>()
            })
            .sum()
    }

    /// Critical-path cycles over all solves, as the target measured them: per solve, every
    /// parallel phase's slowest hart plus hart 0's serial work, over the whole solve
    /// (`SolveReport::whole_solve`; fused solves that drop converged directions and residual
    /// replacements' extra MVU passes included). Nothing is extrapolated from one iteration.
    pub fn critical_path_cycles(&self) -> u64 {
        critical_path_cycles(&self.reports)
    }

    /// The same critical path in cycles and in retired instructions.
    pub fn critical_path(&self) -> PhaseCounters {
        critical_path(&self.reports)
    }

    /// Hart 0's `mcycle` and `minstret` over the MVU and SVU phases of all solves. Under QEMU
    /// `-icount` every hart's counters follow one machine-wide instruction count, so with several
    /// harts this is their sum, not the parallel time: see [`Refined::critical_path`] for that.
    pub fn hart0(&self) -> PhaseCounters {
        self.reports
            .iter()
            .fold(PhaseCounters::default(), |sum, r| {
                sum.saturating_add(r.mvu).saturating_add(r.svu)
            })
    }
}

/// Critical-path cycles of `reports`, as the target measured them over each whole solve
/// (`SolveReport::whole_solve`: every phase's slowest hart plus hart 0's serial work), summed.
pub fn critical_path_cycles(reports: &[SolveReport]) -> u64 {
    critical_path(reports).cycles
}

/// [`critical_path_cycles`] with the retired instructions beside the cycles.
pub fn critical_path(reports: &[SolveReport]) -> PhaseCounters {
    reports.iter().fold(PhaseCounters::default(), |sum, r| {
        sum.saturating_add(r.whole_solve.critical())
    })
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
    #[error(
        "the target clamped {0} value(s) to their fixed-point range: its result cannot be \
         trusted (a firmware fault, since the block-floating-point scaling should prevent it)"
    )]
    Saturated(u32),
    #[error("{0} right-hand sides given; a target solve takes 1 to {MAX_DIRECTIONS}")]
    Directions(usize),
}

/// Solves A·x_d = b_d for every `rhs` on `target` (which must hold `scaled.matrix`, A or its
/// Jacobi scaling, already) to a true relative residual of `params.tol` each. A zero b_d gives
/// x_d = 0 without a target solve.
pub fn solve_refined<P: Port>(
    target: &mut Target<P>,
    a: &Csr,
    scaled: &Scaled,
    rhs: &[&[f64]],
    params: RefineParams,
) -> Result<Refined, RefineError> {
    if rhs.is_empty() || rhs.len() > MAX_DIRECTIONS {
        return Err(RefineError::Directions(rhs.len()));
    }
    let mut out = Refined {
        directions: Vec::with_capacity(rhs.len()),
        reports: Vec::new(),
    };
    let mut residuals: Vec<Vec<f64>> = rhs.iter().map(|b| b.to_vec()).collect();
    let norms: Vec<f64> = rhs.iter().map(|b| norm(b)).collect();
    for (b, &b_norm) in rhs.iter().zip(&norms) {
        out.directions.push(DirectionResult {
            x: vec![0.0; b.len()],
            relative_residual: if b_norm == 0.0 { 0.0 } else { 1.0 },
            solves: 0,
            iterations: 0,
        });
    }
    let groups: Vec<Vec<usize>> = if params.fuse {
        vec![(0..rhs.len()).collect()]
    } else {
        (0..rhs.len()).map(|d| vec![d]).collect()
    };
    let solve = SolveParams {
        max_iterations: params.max_iterations,
        tolerance: (params.tol * INNER_MARGIN).max(FIXED_POINT_FLOOR),
        start: Start::Zero,
        directions: 1,
        cycle_budget: 0,
    };
    for group in groups {
        loop {
            let active: Vec<usize> = group
                .iter()
                .copied()
                .filter(|&d| out.directions[d].relative_residual > params.tol)
                .collect();
            let Some(&first) = active.first() else { break };
            if out.directions[first].solves >= params.max_solves {
                let worst = active
                    .iter()
                    .map(|&d| out.directions[d].relative_residual)
                    .fold(0.0, f64::max);
                return Err(RefineError::NotConverged {
                    residual: worst,
                    solves: out.directions[first].solves,
                    tol: params.tol,
                });
            }
            let sent: Vec<Vec<f64>> = active
                .iter()
                .map(|&d| scaled.apply(&residuals[d]))
                .collect();
            let sent: Vec<&[f64]> = sent.iter().map(Vec::as_slice).collect();
            let (report, corrections) = target.solve_fused(&sent, solve)?;
            if report.saturations > 0 {
                return Err(RefineError::Saturated(report.saturations));
            }
            for (i, &d) in active.iter().enumerate() {
                let result = &mut out.directions[d];
                result.solves += 1;
                result.iterations += report.directions.get(i).map_or(0, |r| r.iterations);
                for (x, c) in result.x.iter_mut().zip(scaled.apply(&corrections[i])) {
                    *x += c;
                }
                residuals[d] = residual(a, rhs[d], &result.x);
                result.relative_residual = norm(&residuals[d]) / norms[d];
            }
            out.reports.push(report);
        }
    }
    Ok(out)
}
