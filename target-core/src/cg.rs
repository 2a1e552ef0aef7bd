//! Conjugate gradients on the target, in block floating point.
//!
//! (Implementation in progress: API fixed, body pending.)

use deform_shared::matrix::TileHeader;
use deform_shared::protocol::{PhaseCounters, SolveFailure, SolveParams, SolveReport};

/// A validated matrix as the MVUs see it.
#[derive(Clone, Copy)]
pub struct Matrix<'a> {
    pub n: usize,
    pub frac_bits: u8,
    pub tiles: &'a [TileHeader],
    /// All tiles' words, back to back in tile order.
    pub words: &'a [u32],
}

/// The working vectors CG needs besides b and x, each of length n.
pub struct Scratch<'a> {
    pub r: &'a mut [i32],
    pub p: &'a mut [i32],
    pub kp: &'a mut [i64],
}

/// Reads the cycle and retired-instruction counters, so that the solver can charge each phase.
pub trait PhaseClock {
    fn now(&self) -> PhaseCounters;
}

/// A clock that always reads zero, for hosts and tests.
pub struct NoClock;
impl PhaseClock for NoClock {
    fn now(&self) -> PhaseCounters {
        PhaseCounters::default()
    }
}

/// Solves A x = b. `b` and `x` are block-floating-point vectors (value = m · 2^exponent);
/// `x`/`x_exponent` hold x₀ on entry and the solution on return.
#[allow(clippy::too_many_arguments)]
pub fn solve(
    a: &Matrix<'_>,
    b: &[i32],
    b_exponent: i32,
    x: &mut [i32],
    x_exponent: &mut i32,
    scratch: Scratch<'_>,
    params: &SolveParams,
    clock: &impl PhaseClock,
) -> Result<SolveReport, SolveFailure> {
    let _ = (a, b, b_exponent, x, x_exponent, scratch, params, clock);
    todo!("cg::solve")
}
