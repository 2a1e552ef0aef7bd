//! Conjugate gradients on the target (thesis 2.3, 4.2), in block floating point, on several
//! MVUs at once and for up to three right-hand sides together.
//!
//! # Work split (thesis 4.1, 4.2)
//!
//! Every iteration has two parallel phases and a little serial work on hart 0:
//!
//! - **MVU**: hart h executes the tiles whose header names `mvu = h` ([`crate::kernel`]).
//!   [`plan`] decides at upload time whether the MVUs' row ranges (mirror rows of mirrored
//!   tiles included) overlap. If not (thesis 4.1.2) each MVU adds its rows straight into Kp;
//!   if they do (4.1.1) each MVU accumulates into its own slots of the partial-sum pool, and a
//!   second parallel step adds the partial rows up. The same step finds max |Kp|.
//! - **SVU** ([`crate::svu`]): hart 0 computes α for each direction; every hart updates r on its
//!   slice of the vectors (pass R, with Σr² and a bound on max |r|), adding them into shared
//!   totals (`totals`), and hart 0 computes β from those; every hart updates x and p on its
//!   slice (pass XP) and adds in the OR-ed maxima.
//!
//! Every number a hart contributes is an integer (exact products and sums, OR-ed maxima), so the
//! result does not depend on the number of MVUs or on the partition: 1, 2, 4 or 8 MVUs give
//! bit-identical solutions, and a fused solve equals the separate solves direction by direction.
//!
//! # Number formats
//!
//! - Matrix values are raw 21-bit integers q with value = q · 2^-F (`frac_bits` = F).
//! - Every vector is a block: `i32` mantissas with one shared exponent, below 2^30 in
//!   magnitude (uploaded vectors and SVU results alike), which keeps every MVU product below 2^50.
//! - Scalars (α, β, the exponents and multipliers) are integers on hart 0 ([`Scalar`]: a 32-bit
//!   mantissa and an exponent; a few per iteration and direction, nothing per element), and
//!   the convergence test is exact on Σr² ([`Threshold`]). `f64` is left for the report.
//!
//! The SVU's element operation and why it cannot overflow are in [`crate::svu`].
//!
//! # Phases of [`solve`]
//!
//! `Solver::start` (r₀ = b − A·x₀ where there is a guess, p₀ = r₀), then per iteration
//! `Solver::iterate` (MVU, α, pass R, β, pass XP) and `Solver::replace_residuals`
//! (r = b − A·x for directions that converged on the recursive residual), then `finish`.
//!
//! # Measured, not extrapolated
//!
//! Every parallel phase runs through [`Executor::run_measured`], so every hart's cycles and
//! instructions in every phase are known exactly; the report carries the first iteration's breakdown
//! (`per_iteration`) and the whole solve's critical path (`whole_solve`: per phase the slowest
//! hart, plus all of hart 0's serial work).

// Harts share the vectors through `SharedSlice`s and the MVU kernel walks raw pointers; every
// `unsafe` block below states which part of the work split makes it sound.
#![allow(unsafe_code)]

use deform_shared::matrix::{MatrixError, TileHeader};
use deform_shared::protocol::{
    DirectionReport, IterationCost, PhaseCounters, SolveFailure, SolveParams, SolveReport, Start,
    MAX_DIRECTIONS, MAX_HARTS,
};
use deform_shared::qformat::ldexp;
use deform_shared::word::ER_BIT;

use crate::exec::{share, SharedSlice};
pub use crate::exec::{Executor, NoClock, PhaseClock, Sequential};
use crate::kernel::{
    lane_words, p_kp_and_max, p_kp_bounded, run_tile_dyn, sum_words, Lanes, Sums, TileRun,
    P_KP_BOUNDED_ROWS, SPLIT_MAX_ROW_ABS, SPLIT_MAX_WORDS, VALUE_SIGN_SHIFT,
};
use crate::mvu_backend::MvuBackend;
use crate::svu::{
    self, bound_of, bound_of_squares, bound_of_u64, check_bound, magnitude_bits, sum_squares,
    Block, HartOut, Lin, Narrow, PassR, PassXP, Scalar, Threshold,
};
use crate::upper::{Lower, Upper};
use totals::{OrField, Sink, Totals};

/// How often a direction's residual is recomputed as b − A·x after it converged on the
/// recursive one. Fixed point cannot go below its own floor, so after this the recursive
/// residual is accepted (the host's refinement takes over from there).
const MAX_REPLACEMENTS: u32 = 2;

/// The largest left shift of b (|b| < 2^30) onto K·x's exponent for which K·x − b·2^s is
/// formed exactly in `i64` ([`Solver::residual_of`]): |b·2^31| < 2^61 and |K·x| < 2^62.
const MAX_B_SHIFT: u32 = 31;

/// A row's total word count (over all tiles and mirrors) above which its i64 sum could
/// overflow: 2^12 products below 2^50 stay below 2^62.
pub const MAX_WORDS_PER_ROW: u32 = 1 << 12;

/// A half-open range of rows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Rows {
    pub lo: usize,
    pub hi: usize,
}

impl Rows {
    fn is_empty(self) -> bool {
        self.hi <= self.lo
    }

    fn len(self) -> usize {
        self.hi.saturating_sub(self.lo)
    }

    fn cover(self, lo: usize, hi: usize) -> Rows {
        if self.is_empty() {
            Rows { lo, hi }
        } else {
            Rows {
                lo: self.lo.min(lo),
                hi: self.hi.max(hi),
            }
        }
    }

    fn overlaps(self, other: Rows) -> bool {
        !self.is_empty() && !other.is_empty() && self.lo < other.hi && other.lo < self.hi
    }

    fn intersect(self, other: Rows) -> Rows {
        Rows {
            lo: self.lo.max(other.lo),
            hi: self.hi.min(other.hi),
        }
    }
}

/// How the MVUs share the matrix, worked out once per upload.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Plan {
    /// MVUs in use: the largest tile `mvu` + 1.
    pub mvus: usize,
    /// True if two MVUs write some row (thesis 4.1.1): then each accumulates privately.
    pub overlapping: bool,
    /// Per MVU: the hull of its tiles' rows, and of their mirror rows.
    pub rows: [[Rows; 2]; MAX_HARTS],
    /// Per MVU and hull: the first slot of its private partial sums (overlapping only).
    pub offsets: [[usize; 2]; MAX_HARTS],
    /// Partial-sum slots used in all.
    pub partial_len: usize,
    /// Every row of K is exactly one row of one tile (its own row or a mirror row) and the
    /// MVUs do not overlap: then each row's sum is final at its tile row's end, where it is
    /// stored and finished (pᵀKp, max |Kp|) at once, with no zeroing pass and no second step
    /// ([`crate::kernel::run_tile`]). Otherwise rows are zeroed, added into and finished in
    /// the MVU phase's second step.
    pub fused: bool,
    /// Every row of K has at most [`SPLIT_MAX_WORDS`] words and Σ|q| at most
    /// [`SPLIT_MAX_ROW_ABS`]: then the MVU loops may sum its rows as split sums
    /// ([`crate::kernel::rebuild_split`]), two instructions fewer per product, the same bits.
    pub split: bool,
    /// ‖K‖∞ in raw value units: the largest Σ_j |q_ij| over the rows (mirrors included). It
    /// bounds ‖K·v‖₂ ≤ ‖K‖∞·‖v‖₂ (K is symmetric), which a live frame's residual estimate
    /// needs ([`crate::superpose`]).
    pub row_abs_max: u64,
    /// `row_abs_max` and ⌈√n⌉ as [`Upper`]s, formed once here rather than in every solve and
    /// dynamic step (each a leading-zero count or a Newton loop on hart 0's serial path): the
    /// drift bounds' ‖A‖∞ (before its 2^−F) and √n.
    pub row_abs: Upper,
    pub root_n: Upper,
    /// The n `root_n` is of: a solve of another n forms its own.
    pub n: usize,
}

impl Plan {
    /// ‖A‖∞ in real units for a matrix of `frac_bits` fraction bits, and ⌈√n⌉ for `n` rows:
    /// the drift bounds' two factors, kept since upload (another n forms its own).
    pub fn drift_norms(&self, n: usize, frac_bits: u8) -> (Upper, Upper) {
        let root = if self.n == n { self.root_n } else { root_n(n) };
        (self.row_abs.scale2(-i32::from(frac_bits)), root)
    }
}

/// ⌈√n⌉ as an [`Upper`], the drift bounds' factor from a per-element bound to a 2-norm.
pub fn root_n(n: usize) -> Upper {
    Upper::new(crate::superpose::ceil_sqrt_int(n) as u64, 0)
}

/// True if `t`'s first row is the last row of `previous`, the tile its MVU ran before it, and
/// both are whole or both mirrored (so its first mirror row is `previous`'s last mirror row):
/// the row is split between the two tiles at a column window's edge. A fused plan stores the
/// first part at `previous`'s row end and adds it back after `t` has stored the second.
fn continues(previous: Option<&TileHeader>, t: &TileHeader) -> bool {
    previous.is_some_and(|p| {
        p.mirrored == t.mirrored && p.rows > 0 && p.row_base + p.rows - 1 == t.row_base
    })
}

/// Why [`plan`] refuses a matrix.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlanError {
    /// The overlapping MVUs need more private partial-sum rows than the pool holds.
    Overlap { rows: u32, capacity: u32 },
    /// A structural fault the tile validation cannot see (a row with too many words).
    Matrix(MatrixError),
}

/// Works out the [`Plan`] for validated `tiles` of dimension `n`; `words` are the tiles' words
/// back to back. `scratch` (n slots or more) is used to count words per row; `partial_capacity`
/// is the size of the partial-sum pool.
pub fn plan(
    tiles: &[TileHeader],
    words: &[u32],
    n: usize,
    scratch: &mut [Sums],
    partial_capacity: usize,
) -> Result<Plan, PlanError> {
    let mut plan = Plan {
        mvus: 1,
        overlapping: false,
        rows: [[Rows::default(); 2]; MAX_HARTS],
        offsets: [[0; 2]; MAX_HARTS],
        partial_len: 0,
        fused: false,
        split: false,
        row_abs_max: 0,
        row_abs: Upper::ZERO,
        root_n: root_n(n),
        n,
    };
    // Words per row, mirrors included: every row sum must stay far from i64 overflow. And
    // tile rows per row (own and mirror), for `fused`, and Σ|q| per row, for `row_abs_max`.
    let counts = scratch.get_mut(..n).unwrap_or(&mut []);
    counts.iter_mut().for_each(|c| *c = [0; MAX_DIRECTIONS]);
    let mut start = 0usize;
    let mut last = [None; MAX_HARTS];
    for (i, t) in tiles.iter().enumerate() {
        let h = usize::from(t.mvu).min(MAX_HARTS - 1);
        plan.mvus = plan.mvus.max(h + 1);
        let (lo, hi) = (t.row_base as usize, (t.row_base + t.rows) as usize);
        plan.rows[h][0] = plan.rows[h][0].cover(lo, hi);
        if t.mirrored {
            plan.rows[h][1] = plan.rows[h][1].cover(n - hi, n - lo);
        }
        // A row split over two tiles of one MVU, one after the other, counts once: the MVU
        // phase carries its first part into the second (`continues`).
        let first = lo + usize::from(continues(last[h], t));
        last[h] = Some(t);
        for r in first..hi {
            let mirror = t.mirrored.then(|| n - 1 - r);
            for c in [Some(r), mirror].into_iter().flatten() {
                if let Some(c) = counts.get_mut(c) {
                    c[1] += 1;
                }
            }
        }
        let end = start + t.words as usize;
        let mut row = lo;
        for &w in words.get(start..end).unwrap_or(&[]) {
            for r in [Some(row), t.mirrored.then(|| n - 1 - row)]
                .into_iter()
                .flatten()
            {
                if let Some(c) = counts.get_mut(r) {
                    c[0] += 1;
                    c[2] += i64::from(
                        (((w << VALUE_SIGN_SHIFT) as i32) >> VALUE_SIGN_SHIFT).unsigned_abs(),
                    );
                    if c[0] > i64::from(MAX_WORDS_PER_ROW) {
                        return Err(PlanError::Matrix(MatrixError::RowTooLong {
                            tile: i as u32,
                            row: r as u32,
                        }));
                    }
                }
            }
            row += usize::from(w >= ER_BIT);
        }
        start = end;
    }
    let hulls = |h: usize| plan.rows[h];
    plan.overlapping = (0..plan.mvus).any(|h| {
        (h + 1..plan.mvus).any(|g| {
            hulls(h)
                .iter()
                .any(|a| hulls(g).iter().any(|b| a.overlaps(*b)))
        })
    });
    plan.fused = !plan.overlapping && counts.len() == n && counts.iter().all(|c| c[1] == 1);
    plan.row_abs_max = counts.iter().map(|c| c[2] as u64).max().unwrap_or(0);
    plan.row_abs = Upper::new(plan.row_abs_max, 0);
    let max_words = counts.iter().map(|c| c[0] as u64).max().unwrap_or(0);
    plan.split = max_words <= SPLIT_MAX_WORDS && plan.row_abs_max <= SPLIT_MAX_ROW_ABS;
    if plan.overlapping {
        let mut next = 0usize;
        for h in 0..plan.mvus {
            for k in 0..2 {
                plan.offsets[h][k] = next;
                next += plan.rows[h][k].len();
            }
        }
        if next > partial_capacity {
            return Err(PlanError::Overlap {
                rows: u32::try_from(next).unwrap_or(u32::MAX),
                capacity: u32::try_from(partial_capacity).unwrap_or(u32::MAX),
            });
        }
        plan.partial_len = next;
    }
    Ok(plan)
}

/// A validated matrix as the MVUs see it.
#[derive(Clone, Copy)]
pub struct Matrix<'a> {
    pub n: usize,
    pub frac_bits: u8,
    pub tiles: &'a [TileHeader],
    /// All tiles' words, back to back in tile order.
    pub words: &'a [u32],
    pub plan: &'a Plan,
}

/// One direction's system: b, x (x₀ on entry unless [`Start::Zero`], the solution on return)
/// and its residual vector. Each needs n elements.
pub struct System<'a> {
    pub b: &'a [i32],
    pub b_exponent: i32,
    pub x: &'a mut [i32],
    pub x_exponent: i32,
    pub r: &'a mut [i32],
    /// `Some`: r already holds a residual for x₀ (a live frame's estimate,
    /// [`crate::superpose`]), which the solve starts from instead of forming b − A·x₀ (the
    /// caller vouches for it; a converged direction is still verified against b − A·x at the
    /// end, as always). `None`: r is formed from b.
    pub r_start: Option<GivenResidual>,
    /// Set by the solve: the state of r on return.
    pub outcome: Outcome,
}

/// A residual the caller hands a solve with x₀ ([`System::r_start`]): r's exponent, Σr² of its
/// mantissas (exact) and a bound on their magnitudes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GivenResidual {
    pub exponent: i32,
    pub rr: u128,
    pub bound: u64,
    /// Where it is already within the tolerance, check it against b − A·x by an exact pass
    /// before accepting x₀ (an estimate the caller cannot bound); else accept it as it is.
    pub verify: bool,
    /// `Some(e)`: the caller proves ‖r − (b − A·x₀)‖₂ ≤ e (real units). The solve then carries
    /// that bound through its updates ([`Outcome::drift`]) and accepts a converged recursive
    /// residual without the exact pass wherever ‖r‖ + drift ≤ tol·‖b‖ is proven: the pass
    /// costs a whole MVU pass, and the bound makes it redundant. `None`: verified as `verify`
    /// says, as before.
    pub drift: Option<Upper>,
}

/// What a solve leaves in a system's r and x besides the mantissas.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Outcome {
    /// r's exponent, and a bound on max |r| (mantissa units).
    pub r_exponent: i32,
    pub r_bound: u64,
    /// r is b − A·x formed by an MVU pass at the end (a start or a residual replacement that
    /// the solve ended on), each element within [`EXACT_PASS_ERROR`] units of r's exponent of
    /// the exact residual of the mantissas; else the recursive residual, or the given one.
    pub r_exact: bool,
    /// A bound on max |x| (mantissa units).
    pub x_bound: u64,
    /// A rigorous bound on ‖r − (b − A·x)‖₂ in real units for the mantissas returned (A·x of
    /// the fixed-point matrix, exact): the start's error plus every update's rounding since
    /// ([`drift_of_update`]). Infinite where the solve does not bound it: a saturation, or a
    /// recursive r of a solve not given a bounded residual ([`GivenResidual::drift`]). A caller
    /// that carries r on to another solve needs it.
    pub drift: Upper,
    /// The solve accepted r without an exact pass because the drift proved it
    /// ([`GivenResidual::drift`]).
    pub check_skipped: bool,
    /// The part of `drift` the updates added to the given start's: the returned r is the given
    /// one plus the updates, whose rounding moved it by at most this much from b − A·x's
    /// change. Infinite where an exact pass replaced r (or nothing was given), so that a
    /// caller relating consecutive residuals ([`crate::dynamics::Stepping::delta`]) knows r
    /// is no longer the given one plus updates.
    pub updates: Upper,
}

impl Default for Outcome {
    /// Nothing known: an infinite drift.
    fn default() -> Outcome {
        Outcome {
            r_exponent: 0,
            r_bound: 0,
            r_exact: false,
            x_bound: 0,
            drift: Upper::INFINITE,
            check_skipped: false,
            updates: Upper::INFINITE,
        }
    }
}

/// The largest error, in units of the result's exponent, of an element of an SVU update
/// z ← c·u + y as `lin` plans it (pass R's r + c·K·p with `narrowed_right` where K·p is
/// narrowed by a right shift, pass XP's x + α·p, pass A's v₀ + Δv₀) against the exact sum for
/// the `Scalar` c planned: ½ from rounding the term; ½ from the multiplier's rounding (at most
/// 1 unit, clamped at 2^31 − 1, times |u| < 2^31 over 2^32); below 1 where y's own term is
/// floored by a right shift (none where it is shifted left or not at all); below ½ where K·p
/// is floored by its narrowing (below 1 narrowed unit times |mult| ≤ 2^31 over 2^32). The
/// terms that do not apply are left out: in a steady solve the exponents rarely move, and the
/// bound halves without the floor.
///
/// In halves of a unit (an integer: the bound is kept in integers, [`Upper`]).
pub fn update_error(lin: &Lin, narrowed_right: bool) -> u64 {
    let own = u64::from(lin.own.is_some_and(|s| s.right > 0));
    2 + 2 * own + u64::from(narrowed_right)
}

/// How much one iteration's updates move the recursive residual away from b − A·x, in real
/// units (2-norm): pass R's rounding, `r_halves` halves of 2^`e_r` per element, and A times
/// pass XP's rounding of x, `x_halves` halves of 2^`e_x` per element ([`update_error`]), each
/// row of A·δx at most ‖A‖∞ = `a_inf` times max |δx|; `root_n` ≥ √n for the 2-norm of n
/// elements. Both passes use the same α and the same p, so nothing else separates r from
/// b − A·x. Rounded up throughout ([`Upper`]).
pub fn drift_of_update(
    root_n: Upper,
    a_inf: Upper,
    (r_halves, e_r): (u64, i32),
    (x_halves, e_x): (u64, i32),
) -> Upper {
    let x = a_inf.times(Upper::small(x_halves, e_x - 1));
    root_n.times(Upper::small(r_halves, e_r - 1).plus(x))
}

/// One iteration's drift ([`drift_of_update`]) for pass R as `r_plan` and pass XP's x as `x`
/// plan them. Out of line, and cold: most solves carry no bound, and inlined, the `Upper`
/// arithmetic cost hart 0's serial path of every iteration about 24 instructions in register
/// spills even where it did not run (`engine_figures`, 8³ B: 1,184 → 1,208 alone).
#[cold]
#[inline(never)]
fn update_drift(r_plan: &PassR, x: &Lin, root_n: Upper, a_inf: Upper) -> Upper {
    let r_units = update_error(&r_plan.lin, matches!(r_plan.narrow, Narrow::Right(_)));
    let (r, x) = ((r_units, r_plan.lin.e), (update_error(x, false), x.e));
    #[cfg(feature = "testkit")]
    crate::trace::record(
        "update",
        &[
            root_n.times(Upper::small(r.0, r.1 - 1)).to_f64(),
            root_n
                .times(a_inf.times(Upper::small(x.0, x.1 - 1)))
                .to_f64(),
        ],
    );
    drift_of_update(root_n, a_inf, r, x)
}

/// The drift of a residual formed by an exact MVU pass at exponent `e_r` ([`EXACT_PASS_ERROR`]
/// units per element), `root_n` ≥ √n.
pub fn drift_of_exact_pass(root_n: Upper, e_r: i32) -> Upper {
    root_n.times(Upper::small(EXACT_PASS_UNITS, e_r))
}

/// Whether ‖r‖ + `drift` ≤ `tol`·‖b‖ is proven, hence ‖b − A·x‖ ≤ tol·‖b‖, from Σr² = `rr` at
/// exponent `e_r` and Σb² = `bb` at `e_b` (mantissas, exact). Without a square root, and
/// without giving any case up (until session 16 the test was 2‖r‖² + 2E² ≤ tol²‖b‖², which
/// refused every case with ‖r‖ above about 0.7·tol·‖b‖ and allowed a drift of only
/// √(T²/2 − ‖r‖²)): with T² = tol²‖b‖², ‖r‖ + E ≤ T holds exactly where E² ≤ T² and
/// ‖r‖² ≤ (T − E)² = T² − 2TE + E², that is where X = T² + E² − ‖r‖² ≥ 2TE, or where
/// X ≥ 0 and X² ≥ 4T²E². T² is taken rounded down (the condition only weakens as T falls),
/// then X is formed rounded down (E² in it too) and 4T²E² rounded up, in integers
/// ([`Upper`], [`Lower`]).
pub fn proves_tolerance(rr: u128, e_r: i32, bb: u128, e_b: i32, drift: Upper, tol: f64) -> bool {
    if !drift.is_finite() || bb == 0 {
        return false;
    }
    let tol = Lower::from_f64(tol);
    let t2 = tol.times(tol).times(Lower::wide(bb, 2 * e_b));
    let e2 = drift.times(drift);
    if !e2.at_most(t2) {
        return false;
    }
    let e2_exact = Lower::exact(drift).times(Lower::exact(drift));
    let Some(x) = t2.plus(e2_exact).minus(Upper::wide(rr, 2 * e_r)) else {
        return false;
    };
    Upper::exact(t2).times(e2).scale2(2).at_most(x.times(x))
}

/// The largest error, in units of r's exponent, of an element of b − A·x formed by an MVU pass
/// ([`Solver::residual_of`]): below 1 unit from narrowing K·x (or K·x − b), ½ from rounding
/// the term and ¼ from its multiplier, and on the inexact path below 1 from flooring b's shift.
pub const EXACT_PASS_ERROR: f64 = EXACT_PASS_UNITS as f64;

/// [`EXACT_PASS_ERROR`] as an integer, for the bounds kept in integers ([`Upper`]).
pub const EXACT_PASS_UNITS: u64 = 2;

/// The vectors all directions share: the interleaved search directions, K·p, and the pool of
/// private partial sums for overlapping MVUs.
pub struct Work<'a> {
    /// n elements.
    pub p: &'a mut [Lanes],
    /// n elements.
    pub kp: &'a mut [Sums],
    /// At least `plan.partial_len` elements.
    pub partial: &'a mut [Sums],
}

/// Per-direction state of the fused loop.
#[derive(Debug, Clone, Copy)]
struct Direction {
    active: bool,
    iterations: u32,
    /// Σb² (b's mantissa units), for the report's residual.
    bb: u128,
    x: Block,
    r: Block,
    p: Block,
    /// Σr² of the current residual's mantissas, exact, and as a [`Scalar`] (formed once).
    rr: u128,
    rr_scalar: Scalar,
    /// ‖r‖/‖b‖ ≤ tol, decided on `rr` by `threshold`.
    converged: bool,
    threshold: Threshold,
    /// b's block, to restart r from.
    b: Block,
    /// Residual replacements done so far.
    replacements: u32,
    /// r was last formed by an MVU pass ([`Outcome::r_exact`]).
    r_exact: bool,
    /// r was given ([`System::r_start`]): no b − A·x₀ at the start.
    given: bool,
    /// The bound on ‖r − (b − A·x)‖₂ ([`Outcome::drift`]).
    drift: Upper,
    /// The part of `drift` the updates added since the given start ([`Outcome::updates`]):
    /// infinite once an exact pass replaced r.
    updates: Upper,
    /// A converged r may be accepted on the drift's proof ([`GivenResidual::drift`]).
    skippable: bool,
    /// It was ([`Outcome::check_skipped`]).
    skipped: bool,
}

impl Direction {
    const IDLE: Direction = Direction {
        active: false,
        iterations: 0,
        bb: 0,
        x: Block::ZERO,
        r: Block::ZERO,
        p: Block::ZERO,
        rr: 0,
        rr_scalar: Scalar::ZERO,
        converged: false,
        threshold: Threshold { m: 0, e: 0 },
        b: Block::ZERO,
        replacements: 0,
        r_exact: false,
        given: false,
        drift: Upper::ZERO,
        updates: Upper::ZERO,
        skippable: false,
        skipped: false,
    };

    /// Takes Σr² = `rr` of the residual block `r` as the current one.
    #[inline(always)]
    fn set_residual(&mut self, rr: u128, r: Block) {
        self.rr = rr;
        self.rr_scalar = Scalar::of_u128(rr);
        self.r = r;
        self.converged = self.threshold.holds(self.rr_scalar, r.e);
    }

    /// ‖r‖/‖b‖ for the report (`f64`, once per solve).
    fn residual(&self) -> f64 {
        if self.bb == 0 {
            return 0.0;
        }
        let ratio = ldexp(self.rr as f64 / self.bb as f64, 2 * (self.r.e - self.b.e));
        sqrt(ratio)
    }
}

/// The measured counts (cycles and instructions) of a solve: the first iteration's breakdown
/// and the whole solve's critical path, phase by phase.
#[derive(Default)]
struct Costs {
    /// The first CG iteration is running: its counts also go to `first`.
    first_iteration: bool,
    first: IterationCost,
    /// Hart 0's serial (scalar) work of the first iteration, part of `first`.
    first_scalar: PhaseCounters,
    whole: IterationCost,
}

impl Costs {
    fn parallel(&mut self, counts: [PhaseCounters; MAX_HARTS], harts: usize, mvu: bool) {
        let counts = &counts[..harts.min(MAX_HARTS)];
        let max = crate::exec::slowest(counts);
        let sum = counts
            .iter()
            .fold(PhaseCounters::default(), |s, &c| s.saturating_add(c));
        self.charge(max, sum, mvu);
    }

    /// An MVU phase that hart 0 alone ran (on hardware MVUs): what [`parallel`](Self::parallel)
    /// charges for hart 0's counts beside idle harts' zeros, without the array of every hart's
    /// counts that it fills and folds (a `memset` and two loops on hart 0's serial path).
    fn hart_0_mvu(&mut self, counts: PhaseCounters) {
        self.charge(counts, counts, true);
    }

    fn charge(&mut self, max: PhaseCounters, sum: PhaseCounters, mvu: bool) {
        for (cost, on) in [
            (&mut self.whole, true),
            (&mut self.first, self.first_iteration),
        ] {
            if !on {
                continue;
            }
            if mvu {
                cost.mvu_critical += max;
                cost.mvu_total += sum;
            } else {
                cost.svu_critical += max;
                cost.svu_total += sum;
            }
        }
    }

    fn serial(&mut self, counts: PhaseCounters) {
        self.whole.svu_critical += counts;
        self.whole.svu_total += counts;
        if self.first_iteration {
            self.first.svu_critical += counts;
            self.first.svu_total += counts;
            self.first_scalar += counts;
        }
    }
}

/// The solver's context for one solve: the matrix, the shared vectors and the executor.
struct Engine<'e, 'a, E: Executor> {
    a: &'e Matrix<'a>,
    exec: &'e E,
    /// The executor's hardware MVUs if they take this solve's MVU phases ([`hardware`]).
    hardware: Option<&'e E::Mvus>,
    harts: usize,
    directions: usize,
    /// p's layout: i32 words a node (1 or 4; [`lane_words_for`]). Kp's and the partial pool's
    /// follow it: [`sum_words`] i64 words a row.
    lane_words: usize,
    p: SharedSlice<'e, Lanes>,
    kp: SharedSlice<'e, Sums>,
    partial: SharedSlice<'e, Sums>,
    /// The totals of the last phases' results, hart 0's (a single slot; see [`Engine::sink`]).
    out: SharedSlice<'e, HartOut>,
    /// The harts' shared accumulators ([`totals`]), all zero between phases.
    totals: &'e Totals,
    /// Per direction: x and r, shared by the SVU passes.
    xs: heapless::Vec<SharedSlice<'e, i32>, MAX_DIRECTIONS>,
    rs: heapless::Vec<SharedSlice<'e, i32>, MAX_DIRECTIONS>,
}

/// Runs `$body` with `$s` bound to the engine's p layout (i32 words a node, 1 or 4) as a
/// constant, and `$r` (where named) to Kp's (i64 words a row, [`sum_words`]: 1 or 3), so that
/// each layout's loops are compiled for their strides.
macro_rules! with_lanes {
    ($engine:expr, |$s:ident| $body:expr) => {
        if $engine.lane_words == 1 {
            const $s: usize = 1;
            $body
        } else {
            const $s: usize = 4;
            $body
        }
    };
    ($engine:expr, |$s:ident, $r:ident| $body:expr) => {
        if $engine.lane_words == 1 {
            const $s: usize = 1;
            const $r: usize = sum_words($s);
            $body
        } else {
            const $s: usize = 4;
            const $r: usize = sum_words($s);
            $body
        }
    };
}

/// p's layout for a solve of `directions` on `exec`: by the direction count
/// ([`lane_words`]), except where hardware MVUs may run the MVU phase: their p window is
/// 16 bytes a node (gateware), and it is the solver's p on such a board.
fn lane_words_for(exec: &impl Executor, directions: usize) -> usize {
    if exec.mvu_backend().is_some() {
        4
    } else {
        lane_words(directions)
    }
}

/// Kp's layout for a solve or [`product`] of `directions` on `exec`: i64 words a row, 1 or 3
/// ([`sum_words`] of p's layout, [`lane_words_for`]). Row i's sum of direction (or lane) d is
/// word `R·i + d` of `work.kp` seen as i64 words ([`crate::kernel::sum_rows`]).
pub fn sum_words_for(exec: &impl Executor, directions: usize) -> usize {
    sum_words(lane_words_for(exec, directions))
}

impl<E: Executor> Engine<'_, '_, E> {
    /// p's nodes `range`, `S` i32 words a node.
    ///
    /// # Safety
    ///
    /// `S` is [`Engine::lane_words`] and `range` lies in `0..n`; as
    /// [`SharedSlice::slice_mut`]: no one else accesses these nodes of p while the slice lives.
    #[allow(clippy::mut_from_ref)]
    #[inline(always)]
    unsafe fn p_lanes<const S: usize>(&self, range: core::ops::Range<usize>) -> &mut [[i32; S]] {
        debug_assert!(S == self.lane_words && range.start <= range.end && range.end <= self.a.n);
        let base = self.p.as_mut_ptr().cast::<[i32; S]>();
        // SAFETY: n nodes of S ≤ 4 words lie within p's n `Lanes`; the caller has these.
        unsafe { core::slice::from_raw_parts_mut(base.wrapping_add(range.start), range.len()) }
    }

    /// Kp's rows `range`, `R` i64 words a row.
    ///
    /// # Safety
    ///
    /// `R` is [`sum_words`] of [`Engine::lane_words`] and `range` lies in `0..n`; as
    /// [`SharedSlice::slice_mut`]: no one else accesses these rows of Kp while the slice lives.
    #[allow(clippy::mut_from_ref)]
    #[inline(always)]
    unsafe fn kp_rows<const R: usize>(&self, range: core::ops::Range<usize>) -> &mut [[i64; R]] {
        debug_assert!(R == sum_words(self.lane_words) && range.end <= self.a.n);
        // SAFETY: forwarded; n rows of R ≤ 3 words lie within Kp's n `Sums`.
        unsafe { rows_of(&self.kp, range) }
    }

    /// The partial pool's slots `range`, `R` i64 words a slot (Kp's layout).
    ///
    /// # Safety
    ///
    /// As [`Engine::kp_rows`], within the pool's `plan.partial_len` slots.
    #[allow(clippy::mut_from_ref)]
    #[inline(always)]
    unsafe fn partial_rows<const R: usize>(
        &self,
        range: core::ops::Range<usize>,
    ) -> &mut [[i64; R]] {
        debug_assert!(R == sum_words(self.lane_words) && range.end <= self.a.plan.partial_len);
        // SAFETY: forwarded; the slots lie within the pool's `Sums`.
        unsafe { rows_of(&self.partial, range) }
    }

    /// Runs one parallel phase, every hart's share measured (one hart at a time: see
    /// [`Executor::run_measured`]), and charges hart 0's serial work since the previous phase.
    /// Inlined: as a call of its own, its register saves and restores fell on hart 0's serial
    /// path at every phase.
    #[inline(always)]
    fn run(&self, task: &(dyn Fn(usize) + Sync), clock: &mut Clock, mvu: bool) {
        clock.flush_serial(self.exec);
        if self.harts == 1 {
            // What `parallel` charges for one hart's counts (its slowest and its sum), without
            // the array of every hart's: a `memset`, a `memcpy` and two loops on hart 0's
            // serial path at every phase.
            let counts = self.exec.run_one_measured(task);
            clock.costs.charge(counts, counts, mvu);
        } else {
            let counts = self.exec.run_measured(self.harts, task);
            clock.costs.parallel(counts, self.harts, mvu);
        }
        clock.last = self.exec.now();
    }

    /// The totals of the harts' results, read on hart 0 between phases.
    fn total(&self) -> &HartOut {
        // SAFETY: called only between phases, when no task runs; the slot exists (`solve`).
        unsafe { &self.out.as_slice()[0] }
    }

    /// Where hart h puts its results of a phase: a lone hart into the totals' slot, several
    /// into the shared totals, which hart 0 then [`collect`](Self::collect)s. Adding them up in
    /// the parallel phase keeps hart 0 from looping over every hart's 128-bit sums serially.
    ///
    /// # Safety
    ///
    /// Only in a task of a phase, and with one hart only from that hart's task.
    #[inline(always)]
    unsafe fn sink(&self) -> Sink<'_> {
        if self.harts == 1 {
            // SAFETY: the caller is the only hart, so it has the slot to itself.
            Sink::Slot(unsafe { &mut self.out.slice_mut(0..1)[0] })
        } else {
            Sink::Shared(self.totals)
        }
    }

    /// Hart 0, after a phase with several harts: moves the totals `take` reads into the slot
    /// (and clears them). A lone hart wrote the slot itself.
    #[inline(always)]
    fn collect(&self, take: impl Fn(&Totals, &mut HartOut)) {
        if self.harts > 1 {
            // SAFETY: no task runs; hart 0 has the slot to itself.
            take(self.totals, unsafe { &mut self.out.slice_mut(0..1)[0] });
        }
    }

    /// Kp = K·p for every direction, pᵀKp, and the OR of |Kp|: the MVU phase, on the hardware
    /// MVUs where the board has them and they hold the matrix, else in software. Where the plan
    /// fuses the row ends, the tiles' step finishes every row and there is no second step.
    ///
    /// Its span on hart 0 (`clock.mvu`) runs from its first step's start to its last step's
    /// end, counters that [`run`](Self::run) reads anyway: reading them again here cost hart
    /// 0's serial path two counter reads per iteration.
    /// Inlined (like `run`): hart 0 calls it between the phases of every iteration, where its
    /// register saves and restores fell on the serial path.
    #[inline(always)]
    fn mvu(&self, clock: &mut Clock) {
        let start = if self.mvu_on_hardware(clock) {
            clock.flushed
        } else {
            with_lanes!(self, |S, R| self.run(
                &|h| self.mvu_tiles::<S, R>(h),
                clock,
                true
            ));
            let start = clock.flushed;
            if !self.a.plan.fused {
                self.run(&|h| self.mvu_rows(h), clock, true);
            }
            self.collect(|t, out| (0..self.directions).for_each(|d| t.take_mvu(out, d)));
            start
        };
        clock.mvu += clock.last.since(start);
    }

    /// The MVU phase on the executor's hardware MVUs ([`crate::mvu_backend`]): their results
    /// go to hart 0's slot (the others' are zero), hart 0's instructions meanwhile to the MVU
    /// phase's counts. False if the solve's phases run in software.
    ///
    /// The counters are read twice, at the phase's start and end, and the bookkeeping of both
    /// readings follows the second: done between them, as [`run`](Self::run) does it, it fell
    /// inside the phase's span, and with the instruction cache cold after the SVU's passes it
    /// cost as many cycles as the array's own work on 4 MVUs (docs/PERFORMANCE.md, session 11).
    fn mvu_on_hardware(&self, clock: &mut Clock) -> bool {
        let Some(hardware) = self.hardware else {
            return false;
        };
        // SAFETY: no task runs; hart 0 has the totals' slot to itself (and the shared totals
        // stay zero).
        let out = unsafe { &mut self.out.slice_mut(0..1)[0] };
        self.exec.now_into(&mut clock.flushed);
        hardware.run(self.directions, (&mut out.p_kp, &mut out.kp_or));
        let end = self.exec.now();
        clock.costs.serial(clock.flushed.since(clock.last));
        clock.costs.hart_0_mvu(end.since(clock.flushed));
        clock.last = end;
        true
    }

    /// Hart h's tiles: every tile with `mvu = h`. Fused, each row end stores and finishes its
    /// row; otherwise hart h first zeroes its rows (or private slots) and each row end adds.
    /// p is `S` words a node ([`Engine::lane_words`]) and Kp `R` words a row, constants so
    /// that a tile's column and row addresses cost what they did with one layout.
    fn mvu_tiles<const S: usize, const R: usize>(&self, h: usize) {
        let (a, plan, n) = (self.a, self.a.plan, self.a.n);
        let p = self.p.as_mut_ptr() as *const i32;
        let zeroed = if plan.fused { 0 } else { 2 };
        for (k, rows) in plan.rows[h].iter().enumerate().take(zeroed) {
            // SAFETY: the plan gives every MVU rows (direct: non-overlapping hulls) or slots
            // (overlapping: its own offsets) that no other MVU touches.
            let target = unsafe {
                if plan.overlapping {
                    let lo = plan.offsets[h][k];
                    self.partial_rows::<R>(lo..lo + rows.len())
                } else {
                    self.kp_rows::<R>(rows.lo..rows.hi)
                }
            };
            target.fill([0; R]);
        }
        let mut start = 0usize;
        let mut previous = None;
        for t in a.tiles {
            let first = start;
            start += t.words as usize;
            if usize::from(t.mvu) != h {
                continue;
            }
            let carried = plan.fused && continues(previous, t);
            previous = Some(t);
            let (row_base, col_base) = (t.row_base as usize, t.col_base as usize);
            let mirror_row = n - 1 - row_base;
            let (y, y_mirror) = if plan.overlapping {
                let base = self.partial.as_mut_ptr() as *mut i64;
                let [own, mirror] = plan.rows[h];
                (
                    base.wrapping_add((plan.offsets[h][0] + row_base - own.lo) * R),
                    base.wrapping_add((plan.offsets[h][1] + mirror_row - mirror.lo) * R),
                )
            } else {
                let base = self.kp.as_mut_ptr() as *mut i64;
                (
                    base.wrapping_add(row_base * R),
                    base.wrapping_add(mirror_row * R),
                )
            };
            let run = TileRun {
                words: a.words.as_ptr().wrapping_add(first),
                rows: t.rows,
                p_cols: p.wrapping_add(col_base * S).cast(),
                p_mirror_cols: p.wrapping_add((n - 1 - col_base) * S).cast(),
                y,
                y_mirror,
            };
            // A split row's first part, stored at the previous tile's row end, is carried over
            // the store of its second part (an exact i64 sum, so the same bits as adding).
            // SAFETY: fused plans do not overlap: these rows are this MVU's alone.
            let saved = carried.then(|| unsafe {
                let (y, y_mirror) = (y.cast::<[i64; R]>(), y_mirror.cast::<[i64; R]>());
                (*y, if t.mirrored { *y_mirror } else { *y })
            });
            // SAFETY: the session validated every tile against n (rows, columns, ER/EM
            // structure) and sized p, kp and the pool for n and the plan; the tile's rows and
            // mirror rows lie in this MVU's hulls, which map to slots only it writes; p is only
            // read during this phase.
            unsafe { run_tile_dyn::<S>(&run, self.directions, t.mirrored, plan.fused, plan.split) };
            if let Some((own, mirror)) = saved {
                // SAFETY: as above.
                unsafe { carry(y.cast(), own, self.directions) };
                if t.mirrored {
                    // SAFETY: as above.
                    unsafe { carry(y_mirror.cast(), mirror, self.directions) };
                }
            }
        }
        if plan.fused {
            self.finish_rows::<S, R>(plan.rows[h]);
        }
    }

    /// pᵀKp and max |Kp| over the rows of `hulls` (hart h's own and mirror rows, fused plans:
    /// they are finished, and only hart h wrote them), put to the totals.
    fn finish_rows<const S: usize, const R: usize>(&self, hulls: [Rows; 2]) {
        let mut p_kp = [0i128; MAX_DIRECTIONS];
        let mut or = [0u64; MAX_DIRECTIONS];
        for rows in hulls {
            // SAFETY: p is only read during this phase; these rows of Kp are this hart's alone.
            let (p, kp) = unsafe {
                (
                    self.p_lanes::<S>(rows.lo..rows.hi),
                    self.kp_rows::<R>(rows.lo..rows.hi),
                )
            };
            let (s, o) = self.p_kp(p, kp);
            for d in 0..MAX_DIRECTIONS {
                p_kp[d] += s[d];
                or[d] |= o[d];
            }
        }
        self.put_mvu(p_kp, or);
    }

    /// A hart's pᵀKp and OR of |Kp| of every direction (the MVU phase's results).
    #[inline(always)]
    fn put_mvu(&self, p_kp: [i128; MAX_DIRECTIONS], or: [u64; MAX_DIRECTIONS]) {
        // SAFETY: called from a task of the MVU phase.
        let mut sink = unsafe { self.sink() };
        for d in 0..self.directions {
            sink.p_kp(d, p_kp[d]);
            sink.kp_or(d, or[d]);
        }
    }

    /// Hart h's share of the rows: add the partial rows up (overlapping MVUs), then pᵀKp and
    /// max |Kp| over the finished rows.
    /// The layouts' dispatch is here, on every hart, rather than around the phase on hart 0's
    /// serial path.
    fn mvu_rows(&self, h: usize) {
        with_lanes!(self, |S, R| self.mvu_rows_in::<S, R>(h));
    }

    /// [`Engine::mvu_rows`] with p `S` words a node and Kp `R` words a row.
    fn mvu_rows_in<const S: usize, const R: usize>(&self, h: usize) {
        let (plan, n) = (self.a.plan, self.a.n);
        let range = share(n, self.harts, h);
        // SAFETY: the shares of the rows are disjoint; the pool is only read.
        let kp = unsafe { self.kp_rows::<R>(range.clone()) };
        let dirs = self.directions;
        if plan.overlapping {
            kp.fill([0; R]);
            // SAFETY: nothing writes the pool during this phase.
            let pool = unsafe { &*self.partial_rows::<R>(0..plan.partial_len) };
            let mine = Rows {
                lo: range.start,
                hi: range.end,
            };
            for g in 0..plan.mvus {
                for k in 0..2 {
                    let hull = plan.rows[g][k];
                    let both = hull.intersect(mine);
                    if both.is_empty() {
                        continue;
                    }
                    let from = plan.offsets[g][k] + both.lo - hull.lo;
                    let src = pool.get(from..from + both.len()).unwrap_or(&[]);
                    let dst = &mut kp[both.lo - mine.lo..both.hi - mine.lo];
                    for (d, s) in dst.iter_mut().zip(src) {
                        for j in 0..dirs {
                            d[j] += s[j];
                        }
                    }
                }
            }
        }
        // SAFETY: p is only read during this phase.
        let (p_kp, or) = self.p_kp(unsafe { self.p_lanes::<S>(range) }, kp);
        self.put_mvu(p_kp, or);
    }

    /// pᵀKp and the OR of |Kp| over finished rows: [`p_kp_bounded`] where the plan bounds |Kp|
    /// below 2^52 (split sums allowed) and the rows are few enough, else [`p_kp_and_max`].
    #[inline(always)]
    fn p_kp<const S: usize, const R: usize>(
        &self,
        p: &[[i32; S]],
        kp: &[[i64; R]],
    ) -> ([i128; MAX_DIRECTIONS], [u64; MAX_DIRECTIONS]) {
        if self.a.plan.split && kp.len() <= P_KP_BOUNDED_ROWS {
            p_kp_bounded(p, kp, self.directions)
        } else {
            p_kp_and_max(p, kp, self.directions)
        }
    }

    /// SVU pass R on every hart: r ← r − α·Kp for each planned direction.
    /// Inlined: see [`mvu`](Self::mvu).
    #[inline(always)]
    fn pass_r(&self, plans: &[Option<PassR>; MAX_DIRECTIONS], clock: &mut Clock) {
        let n = self.a.n;
        let task = |h: usize| {
            let range = share(n, self.harts, h);
            // SAFETY: each hart writes only its own share of r; kp is only read during this
            // pass.
            unsafe {
                let mut sink = self.sink();
                with_lanes!(self, |S, R| {
                    let kp = &*self.kp_rows::<R>(range.clone());
                    for (d, plan) in plans.iter().enumerate().take(self.directions) {
                        if let Some(plan) = plan {
                            let r = self.rs[d].slice_mut(range.clone());
                            let (rr, or) = svu::pass_r(r, kp, d, *plan);
                            sink.rr(d, rr);
                            sink.or(OrField::R, d, or);
                        }
                    }
                });
            }
        };
        self.run(&task, clock, false);
        self.collect(|t, out| {
            for (d, plan) in plans.iter().enumerate().take(self.directions) {
                if plan.is_some() {
                    t.take_r(out, d);
                }
            }
        });
    }

    /// SVU pass XP on every hart: x ← x + α·p, p ← r + β·p for each planned direction.
    /// Inlined: see [`mvu`](Self::mvu).
    #[inline(always)]
    fn pass_xp(&self, plans: &[PassXP; MAX_DIRECTIONS], clock: &mut Clock) {
        let n = self.a.n;
        let task = |h: usize| {
            let range = share(n, self.harts, h);
            // SAFETY: each hart writes only its own share of x and p; r is only read during
            // this pass.
            unsafe {
                let mut sink = self.sink();
                with_lanes!(self, |S| {
                    let p = self.p_lanes::<S>(range.clone());
                    for (d, plan) in plans.iter().enumerate().take(self.directions) {
                        let x = self.xs[d].slice_mut(range.clone());
                        let r = &self.rs[d].as_slice()[range.clone()];
                        let (x_or, p_or) = svu::pass_xp(x, p, r, d, plan);
                        sink.or(OrField::X, d, x_or);
                        sink.or(OrField::P, d, p_or);
                    }
                });
            }
        };
        self.run(&task, clock, false);
        self.collect(|t, out| (0..self.directions).for_each(|d| t.take_xp(out, d)));
    }

    /// K·x − b·2^s, exact, in place of K·x for each direction with a shift `s`, with the OR of
    /// the differences' magnitudes in `kp_or`: b − A·x cancels to a few bits when x is a good
    /// guess, and only the exact `i64` difference keeps those bits (see
    /// [`Solver::residual_of`]). |b·2^s| < 2^61 for s ≤ [`MAX_B_SHIFT`] and |K·x| < 2^62, so the
    /// difference fits.
    fn subtract_b(
        &self,
        b: &[&[i32]; MAX_DIRECTIONS],
        shifts: [Option<u32>; MAX_DIRECTIONS],
        clock: &mut Clock,
    ) {
        let n = self.a.n;
        let task = |h: usize| {
            let range = share(n, self.harts, h);
            // SAFETY: each hart writes only its own share of Kp; b is only read.
            unsafe {
                let mut sink = self.sink();
                with_lanes!(self, |S, R| {
                    let kp = self.kp_rows::<R>(range.clone());
                    for (d, shift) in shifts.iter().enumerate().take(self.directions) {
                        let Some(s) = *shift else { continue };
                        let mut or = 0u64;
                        for (ki, &bi) in kp.iter_mut().zip(&b[d][range.clone()]) {
                            let v = ki[d].wrapping_sub(i64::from(bi) << s);
                            ki[d] = v;
                            or |= (v ^ (v >> 63)) as u64;
                        }
                        sink.kp_or(d, or);
                    }
                });
            }
        };
        self.run(&task, clock, false);
        self.collect(|t, out| {
            for (d, shift) in shifts.iter().enumerate().take(self.directions) {
                if shift.is_some() {
                    out.kp_or[d] = t.kp_or[d].take();
                }
            }
        });
    }

    /// What each direction's lane of p becomes, on every hart's share in parallel. A lane
    /// copied from r also gets the OR of its magnitudes (`p_or`), the tight bound
    /// [`Solver::tighten_r_bounds`] needs.
    fn set_lanes(&self, lanes: [Lane; MAX_DIRECTIONS], clock: &mut Clock) {
        let n = self.a.n;
        let task = |h: usize| {
            let range = share(n, self.harts, h);
            // SAFETY: each hart writes only its own share of p; x and r are only read.
            unsafe {
                let mut sink = self.sink();
                with_lanes!(self, |S| {
                    let p = self.p_lanes::<S>(range.clone());
                    for (d, lane) in lanes.iter().enumerate().take(self.directions) {
                        match lane {
                            Lane::Keep => {}
                            Lane::Zero => {
                                p.iter_mut().for_each(|pi| pi[d] = 0);
                                sink.or(OrField::P, d, 0);
                            }
                            // x's bound is known; only r's copy is measured.
                            Lane::X => {
                                let x = &self.xs[d].as_slice()[range.clone()];
                                p.iter_mut().zip(x).for_each(|(pi, &v)| pi[d] = v);
                            }
                            Lane::R => {
                                let mut or = 0u32;
                                for (pi, &v) in
                                    p.iter_mut().zip(&self.rs[d].as_slice()[range.clone()])
                                {
                                    pi[d] = v;
                                    or |= magnitude_bits(v);
                                }
                                sink.or(OrField::P, d, or);
                            }
                        }
                    }
                });
            }
        };
        self.run(&task, clock, false);
        self.collect(|t, out| {
            for (d, lane) in lanes.iter().enumerate().take(self.directions) {
                if matches!(lane, Lane::Zero | Lane::R) {
                    out.p_or[d] = t.p_or[d].take();
                }
            }
        });
    }

    /// The set-up on every hart's share: r = b (where r is not `given`), Σb², the ORs of b and
    /// x, p's lanes = x (or x and its lane cleared, `zero_x`), and Kp cleared where the MVUs
    /// add into it (a fused plan stores every row).
    fn setup(
        &self,
        b: &[&[i32]; MAX_DIRECTIONS],
        given: [bool; MAX_DIRECTIONS],
        zero_x: bool,
        clock: &mut Clock,
    ) {
        let n = self.a.n;
        let task = |h: usize| {
            let range = share(n, self.harts, h);
            // SAFETY: each hart writes only its own share of r, x, p and Kp; b is only read.
            unsafe {
                let mut sink = self.sink();
                if !self.a.plan.fused {
                    with_lanes!(self, |S, R| self.kp_rows::<R>(range.clone()).fill([0; R]));
                }
                for d in 0..self.directions {
                    let b = &b[d][range.clone()];
                    if !given[d] {
                        self.rs[d].slice_mut(range.clone()).copy_from_slice(b);
                    }
                    sink.rr(d, sum_squares(b));
                    sink.or(
                        OrField::B,
                        d,
                        b.iter().fold(0, |o, &m| o | magnitude_bits(m)),
                    );
                    let x = self.xs[d].slice_mut(range.clone());
                    if zero_x {
                        x.fill(0);
                    }
                    sink.or(
                        OrField::X,
                        d,
                        x.iter().fold(0, |o, &m| o | magnitude_bits(m)),
                    );
                    sink.or(OrField::XAny, d, x.iter().fold(0, |o, &m| o | m as u32));
                    with_lanes!(self, |S| self
                        .p_lanes::<S>(range.clone())
                        .iter_mut()
                        .zip(x.iter())
                        .for_each(|(pi, &v)| pi[d] = v));
                }
            }
        };
        self.run(&task, clock, false);
        self.collect(|t, out| (0..self.directions).for_each(|d| t.take_setup(out, d)));
    }
}

/// What a direction's lane of p becomes ([`Engine::set_lanes`]).
#[derive(Debug, Clone, Copy, PartialEq)]
enum Lane {
    Keep,
    Zero,
    X,
    R,
}

/// Hart 0's bookkeeping of where its time went.
#[derive(Default)]
struct Clock {
    costs: Costs,
    /// Hart 0's counters when the last parallel phase ended (or the solve began).
    last: PhaseCounters,
    /// Hart 0's counters at the last [`flush_serial`](Self::flush_serial): where a phase
    /// began.
    flushed: PhaseCounters,
    mvu: PhaseCounters,
    svu: PhaseCounters,
}

impl Clock {
    /// Charges hart 0's serial work since the last parallel phase (or flush) to the costs.
    /// Inlined: its call's register saves came before the counter read, on the serial path.
    #[inline(always)]
    fn flush_serial(&mut self, clock: &impl PhaseClock) {
        let now = clock.now();
        self.costs.serial(now.since(self.last));
        self.last = now;
        self.flushed = now;
    }
}

/// The executor's hardware MVUs if they take the MVU phases of a solve with these vectors
/// ([`MvuBackend::begin_solve`]), asked once for the solve. Their p window is `Lanes`, 16 bytes
/// a node: p laid out more compactly ([`lane_words_for`]) is never theirs.
fn hardware<'e, E: Executor>(
    exec: &'e E,
    n: usize,
    (p, kp, lane_words): (&SharedSlice<'_, Lanes>, &SharedSlice<'_, Sums>, usize),
    directions: usize,
) -> Option<&'e E::Mvus> {
    if lane_words != size_of::<Lanes>() / 4 {
        return None;
    }
    let p_ptr = p.as_mut_ptr() as *const Lanes;
    exec.mvu_backend()
        .filter(|h| h.begin_solve(n, p_ptr, kp.as_mut_ptr(), directions))
}

/// One solve in progress: its phases are the methods.
struct Solver<'s, 'e, 'a, E: Executor> {
    engine: &'s Engine<'e, 'a, E>,
    params: &'s SolveParams,
    systems_b: [&'s [i32]; MAX_DIRECTIONS],
    state: [Direction; MAX_DIRECTIONS],
    x_exponents: [i32; MAX_DIRECTIONS],
    /// Pass XP's plans and α of the iteration in progress, kept here rather than in fresh
    /// arrays: initialising those costs hart 0 a `memcpy` or `memset` every iteration.
    xp_plans: [PassXP; MAX_DIRECTIONS],
    alphas: [Scalar; MAX_DIRECTIONS],
    iterations: u32,
    sat: u32,
    clock: Clock,
    /// ‖A‖∞ in real units, for the drift of x's rounding ([`drift_of_update`]), and ⌈√n⌉.
    a_inf: Upper,
    root_n: Upper,
}

impl<E: Executor> Solver<'_, '_, '_, E> {
    /// The cycle budget (`SolveParams::cycle_budget`, 0 for none): no new iteration starts
    /// once the critical path's cycles measured since the solve began (every parallel phase's
    /// slowest hart plus hart 0's serial work, as in `SolveReport::whole_solve`) reach it, so a
    /// budgeted step ends within one iteration of its budget with the residual it reached.
    fn within_budget(&self) -> bool {
        self.params.cycle_budget == 0
            || self.clock.costs.whole.critical().cycles < self.params.cycle_budget
    }

    fn f(&self) -> i32 {
        self.engine.a.frac_bits as i32
    }

    fn directions(&self) -> usize {
        self.engine.directions
    }

    /// Pass R's plan for direction d: r ← c·K·v (+ r if `keep`), where K·v is in the MVU's
    /// results, `kp_max` the harts' OR of its magnitudes, and v's block is `v` (p, or x when
    /// computing b − A·x).
    /// Inlined: hart 0 plans on the serial path, where the call's argument traffic costs more
    /// than the body.
    #[inline(always)]
    fn r_plan(&mut self, d: usize, c: Scalar, v: Block, keep: bool, kp_max: u64) -> PassR {
        let (narrow, e_offset, bound) = Narrow::new(bound_of_u64(kp_max), &mut self.sat);
        let kp = Block {
            e: v.e - self.f() + e_offset,
            bound,
        };
        PassR {
            lin: Lin::new(c, kp, true, keep.then_some(self.state[d].r), &mut self.sat),
            narrow,
        }
    }

    /// Folds pass R's results for direction d into its state.
    /// Inlined: as a call, `plan` went through memory on hart 0's serial path.
    #[inline(always)]
    fn take_r(&mut self, d: usize, plan: PassR) {
        let total = self.engine.total();
        let (rr, or) = (total.rr[d], total.r_or[d]);
        let bound = bound_of_squares(or);
        check_bound(bound, &mut self.sat);
        let r = Block {
            e: plan.lin.e,
            bound,
        };
        self.state[d].set_residual(rr, r);
    }

    /// Whether direction d's converged r may be accepted without an exact pass: the caller
    /// asked for it, nothing saturated, and ‖r‖ + drift ≤ tol·‖b‖ is proven. Marks it
    /// skipped if so.
    fn proven(&mut self, d: usize) -> bool {
        let st = &mut self.state[d];
        let tol = self.params.tolerance;
        st.skipped = st.skippable
            && self.sat == 0
            && proves_tolerance(st.rr, st.r.e, st.bb, st.b.e, st.drift, tol);
        // "proven" = [‖r‖, drift, tol·‖b‖, skipped, iterations] (real units).
        #[cfg(feature = "testkit")]
        if st.skippable {
            let norm = |s: u128, e: i32| deform_shared::qformat::ldexp((s as f64).sqrt(), e);
            crate::trace::record(
                "proven",
                &[
                    norm(st.rr, st.r.e),
                    st.drift.to_f64(),
                    tol * norm(st.bb, st.b.e),
                    f64::from(u8::from(st.skipped)),
                    f64::from(st.iterations),
                ],
            );
        }
        st.skipped
    }

    /// The left shift of b onto K·x's exponent (direction d) for which K·x − b·2^s is formed
    /// exactly ([`Solver::residual_of`]), if there is one.
    fn b_shift(&self, d: usize) -> Option<u32> {
        let s = self.state[d].b.e - (self.state[d].x.e - self.f());
        u32::try_from(s).ok().filter(|&s| s <= MAX_B_SHIFT)
    }

    /// r = b − K·x for the directions in `which`, whose x is in their lane of p (and b in r):
    /// one MVU pass and pass R.
    ///
    /// With a good x (a predicted or warm start, a residual replacement) b and K·x agree to
    /// many bits. Pass R would round K·x to 31 bits and r to an exponent sized for |b| + |K·x|,
    /// leaving r a few bits, rounded at about 2^-29 of max |b|, which is near the tolerances
    /// asked for: CG then chases that rounding. So where b's exponent is at most
    /// [`MAX_B_SHIFT`] above K·x's, K·x − b is formed exactly in `i64` first and pass R only
    /// narrows and negates it, r at the exponent of the difference itself.
    fn residual_of(&mut self, which: [bool; MAX_DIRECTIONS]) {
        self.engine.mvu(&mut self.clock);
        let t = self.engine.exec.now();
        let mut shifts = [None; MAX_DIRECTIONS];
        for d in (0..self.directions()).filter(|&d| which[d]) {
            shifts[d] = self.b_shift(d);
        }
        if shifts.iter().any(Option::is_some) {
            self.engine
                .subtract_b(&self.systems_b, shifts, &mut self.clock);
        }
        let mut plans = [None; MAX_DIRECTIONS];
        for d in (0..self.directions()).filter(|&d| which[d]) {
            let keep = shifts[d].is_none();
            let kp_max = self.engine.total().kp_or[d];
            plans[d] = Some(self.r_plan(d, Scalar::ONE.negate(), self.state[d].x, keep, kp_max));
        }
        self.engine.pass_r(&plans, &mut self.clock);
        for (d, plan) in plans.iter().enumerate() {
            if let Some(plan) = plan {
                self.take_r(d, *plan);
                self.state[d].r_exact = true;
                self.state[d].drift = drift_of_exact_pass(self.root_n, plan.lin.e);
                self.state[d].updates = Upper::INFINITE;
            }
        }
        charge(&mut self.clock.svu, t, self.engine.exec);
    }

    /// r₀ = b − A·x₀ where x₀ ≠ 0, then p₀ = r₀ for every direction with work to do.
    fn start(&mut self) {
        let guessed: [bool; MAX_DIRECTIONS] = core::array::from_fn(|d| {
            let st = &self.state[d];
            st.active && st.x.bound != 0 && !st.given
        });
        if guessed.iter().any(|&g| g) {
            self.residual_of(guessed);
        }
        let t = self.engine.exec.now();
        let mut lanes = [Lane::Keep; MAX_DIRECTIONS];
        let directions = self.directions();
        for (st, lane) in self.state.iter_mut().zip(&mut lanes).take(directions) {
            if st.active {
                st.active = !st.converged;
            }
            st.p = st.r;
            *lane = if st.active { Lane::R } else { Lane::Zero };
        }
        self.engine.set_lanes(lanes, &mut self.clock);
        self.tighten_r_bounds(lanes);
        charge(&mut self.clock.svu, t, self.engine.exec);
    }

    /// After r was copied into p (`Lane::R`, a start or a restart): r's and p's bound from the
    /// OR of r's magnitudes that the copy measured. Pass R bounds r through the high words of
    /// r², which cannot see below 2^16: tight for a residual the SVU itself normalised, but an
    /// r that cancelled to a few bits (b − A·x₀ on pass R's path, see
    /// [`Solver::residual_of`]) would be believed 2^16 when it is 2^4, and the next updates
    /// of r and p would choose exponents 12 bits too coarse and lose those bits.
    fn tighten_r_bounds(&mut self, lanes: [Lane; MAX_DIRECTIONS]) {
        let total = self.engine.total();
        for (d, lane) in lanes.iter().enumerate().take(self.directions()) {
            if *lane == Lane::R {
                let or = total.p_or[d];
                let st = &mut self.state[d];
                st.r.bound = st.r.bound.min(bound_of(or));
                st.p = st.r;
            }
        }
    }

    /// One CG iteration of every active direction: MVU, α, pass R, β, pass XP. Returns the
    /// directions that converged on their recursive residual and are to be verified.
    fn iterate(&mut self) -> Result<[bool; MAX_DIRECTIONS], SolveFailure> {
        self.iterations += 1;
        self.engine.mvu(&mut self.clock);
        // The SVU's span on hart 0 runs from the MVU phase's end to the flush below: counters
        // already read, not read again on the serial path.
        let t = self.clock.last;
        let mut r_plans = [None; MAX_DIRECTIONS];
        // By index: `d` indexes the state, the harts' results and α as well, and the iterator
        // form compiles to 9 more instructions of hart 0's serial work per iteration.
        #[allow(clippy::needless_range_loop)]
        for d in 0..self.directions() {
            if !self.state[d].active {
                continue;
            }
            self.state[d].iterations += 1;
            let total = self.engine.total();
            let (p_kp, kp_max) = (total.p_kp[d], total.kp_or[d]);
            if p_kp <= 0 {
                return Err(SolveFailure::NotPositiveDefinite {
                    iteration: self.iterations,
                });
            }
            let st = &self.state[d];
            // α = rᵀr / pᵀKp; exponents: 2e_r and 2e_p − F.
            let alpha = Scalar::quotient(st.rr_scalar, Scalar::of_i128(p_kp))
                .scale2(2 * st.r.e - 2 * st.p.e + self.f());
            self.alphas[d] = alpha;
            r_plans[d] = Some(self.r_plan(d, alpha.negate(), st.p, true, kp_max));
        }
        self.engine.pass_r(&r_plans, &mut self.clock);
        // Reset field by field: a fresh `[PassXP::NONE; MAX_DIRECTIONS]` compiles to a 48-byte
        // `memcpy` of the constant per direction on hart 0's serial path; this stores only the
        // `None` tags.
        for plan in &mut self.xp_plans {
            (plan.x, plan.p) = (None, None);
        }
        let mut verify = [false; MAX_DIRECTIONS];
        for (d, plan) in r_plans.iter().enumerate() {
            let Some(plan) = plan else { continue };
            let (rr_old, e_old) = (self.state[d].rr_scalar, self.state[d].r.e);
            self.take_r(d, *plan);
            let st = &mut self.state[d];
            st.r_exact = false;
            let x = Lin::new(self.alphas[d], st.p, false, Some(st.x), &mut self.sat);
            self.xp_plans[d].x = Some(x);
            if st.skippable {
                let w = update_drift(plan, &x, self.root_n, self.a_inf);
                (st.drift, st.updates) = (st.drift.plus(w), st.updates.plus(w));
            }
            if st.converged || st.iterations >= self.params.max_iterations {
                st.active = false;
                // Converged on the recursive residual: check it against b − A·x, unless the
                // drift proves it.
                verify[d] = st.converged && st.replacements < MAX_REPLACEMENTS && !self.proven(d);
                continue;
            }
            // β = r_newᵀr_new / rᵀr
            let beta = Scalar::quotient(st.rr_scalar, rr_old).scale2(2 * (st.r.e - e_old));
            self.xp_plans[d].p = Some(Lin::new(beta, st.p, false, Some(st.r), &mut self.sat));
        }
        self.engine.pass_xp(&self.xp_plans, &mut self.clock);
        let total = self.engine.total();
        for (d, plan) in self.xp_plans.iter().enumerate() {
            if plan.x.is_none() && plan.p.is_none() {
                continue;
            }
            let st = &mut self.state[d];
            let (x_or, p_or) = (total.x_or[d], total.p_or[d]);
            if let Some(lin) = plan.x {
                st.x = Block {
                    e: lin.e,
                    bound: bound_of(x_or),
                };
                check_bound(st.x.bound, &mut self.sat);
                self.x_exponents[d] = lin.e;
            }
            if let Some(lin) = plan.p {
                st.p = Block {
                    e: lin.e,
                    bound: bound_of(p_or),
                };
                check_bound(st.p.bound, &mut self.sat);
            }
        }
        // The first iteration's serial tail is charged to it before its breakdown closes.
        self.clock.flush_serial(self.engine.exec);
        self.clock.costs.first_iteration = false;
        self.clock.svu += self.clock.flushed.since(t);
        Ok(verify)
    }

    /// Residual replacement: a direction that converged on its recursive residual gets
    /// r = b − A·x recomputed (one extra MVU pass); if that is still above the tolerance — the
    /// recursive residual drifts from the true one by the rounding of the updates — CG restarts
    /// from it with p = r.
    fn replace_residuals(&mut self, verify: [bool; MAX_DIRECTIONS]) {
        if !verify.iter().any(|&v| v) {
            return;
        }
        let t = self.engine.exec.now();
        let mut lanes = [Lane::Keep; MAX_DIRECTIONS];
        for d in (0..self.directions()).filter(|&d| verify[d]) {
            self.state[d].replacements += 1;
            lanes[d] = Lane::X;
            if self.b_shift(d).is_none() {
                // Only pass R's inexact path reads b from r; the exact one subtracts b itself.
                // SAFETY: no task runs; hart 0 has the vectors to itself.
                unsafe { self.engine.rs[d].slice_mut(0..self.engine.a.n) }
                    .copy_from_slice(&self.systems_b[d][..self.engine.a.n]);
            }
            self.state[d].r = self.state[d].b;
        }
        self.engine.set_lanes(lanes, &mut self.clock);
        charge(&mut self.clock.svu, t, self.engine.exec);
        self.residual_of(verify);
        let t = self.engine.exec.now();
        let mut lanes = [Lane::Keep; MAX_DIRECTIONS];
        for d in (0..self.directions()).filter(|&d| verify[d]) {
            let st = &mut self.state[d];
            if !st.converged && st.iterations < self.params.max_iterations {
                st.active = true;
                st.p = st.r;
                lanes[d] = Lane::R;
            }
        }
        if lanes.iter().any(|&l| l != Lane::Keep) {
            self.engine.set_lanes(lanes, &mut self.clock);
            self.tighten_r_bounds(lanes);
        }
        charge(&mut self.clock.svu, t, self.engine.exec);
    }
}

/// Solves A x = b for every system in `systems` (1..=3 of them, fused: each MVU pass serves all)
/// on `exec`'s harts as planned by `a.plan`. Each system's `x`/`x_exponent` hold x₀ on entry
/// when `params.start` is not [`Start::Zero`], and the solution on return. The report's
/// residuals are the recursive ‖r‖/‖b‖.
pub fn solve(
    a: &Matrix<'_>,
    systems: &mut [System<'_>],
    work: Work<'_>,
    params: &SolveParams,
    exec: &impl Executor,
) -> Result<SolveReport, SolveFailure> {
    let n = a.n;
    let directions = systems.len();
    if !(1..=MAX_DIRECTIONS).contains(&directions) {
        return Err(SolveFailure::BadDirections(directions as u8));
    }
    let plan = a.plan;
    let harts = plan.mvus.clamp(1, MAX_HARTS);
    let short = systems
        .iter()
        .any(|s| s.b.len() < n || s.x.len() < n || s.r.len() < n);
    if short
        || work.p.len() < n
        || work.kp.len() < n
        || work.partial.len() < plan.partial_len
        || plan.mvus > exec.harts()
    {
        return Err(SolveFailure::WorkspaceTooSmall);
    }
    let t0 = exec.now();
    let Work { p, kp, partial } = work;
    let (p, kp) = (&mut p[..n], &mut kp[..n]);
    let mut out = [HartOut::default()];
    let totals = Totals::default();
    let mut systems_b: [&[i32]; MAX_DIRECTIONS] = [&[]; MAX_DIRECTIONS];
    let mut b_exponents = [0i32; MAX_DIRECTIONS];
    let mut x_exponents = [0i32; MAX_DIRECTIONS];
    let mut given = [None; MAX_DIRECTIONS];
    let mut xs = heapless::Vec::new();
    let mut rs = heapless::Vec::new();
    for (d, s) in systems.iter_mut().enumerate() {
        systems_b[d] = s.b;
        b_exponents[d] = s.b_exponent;
        x_exponents[d] = s.x_exponent;
        // A given residual belongs to x₀: without one (a zero start) it is ignored.
        given[d] = s.r_start.filter(|_| params.start != Start::Zero);
        let _ = xs.push(SharedSlice::new(&mut s.x[..n]));
        let _ = rs.push(SharedSlice::new(&mut s.r[..n]));
    }
    let (p, kp) = (SharedSlice::new(p), SharedSlice::new(kp));
    let lane_words = lane_words_for(exec, directions);
    let engine = Engine {
        a,
        exec,
        hardware: hardware(exec, n, (&p, &kp, lane_words), directions),
        harts,
        directions,
        lane_words,
        p,
        kp,
        partial: SharedSlice::new(partial),
        out: SharedSlice::new(&mut out),
        totals: &totals,
        xs,
        rs,
    };
    // The solver first, its state filled in place: built apart and moved in, its 1 kB
    // (three directions' state, the clock's costs) were copied on hart 0's serial path.
    let (a_inf, root_n) = plan.drift_norms(n, a.frac_bits);
    let mut solver = Solver {
        engine: &engine,
        params,
        systems_b,
        state: [Direction::IDLE; MAX_DIRECTIONS],
        x_exponents,
        xp_plans: [PassXP::NONE; MAX_DIRECTIONS],
        alphas: [Scalar::ZERO; MAX_DIRECTIONS],
        iterations: 0,
        sat: 0,
        clock: Clock {
            last: t0,
            ..Clock::default()
        },
        a_inf,
        root_n,
    };
    let given_flags = given.map(|g| g.is_some());
    engine.setup(
        &systems_b,
        given_flags,
        params.start == Start::Zero,
        &mut solver.clock,
    );
    let tol_sq = params.tolerance * params.tolerance;
    for d in 0..directions {
        let st = &mut solver.state[d];
        *st = initial_state(
            &engine,
            d,
            b_exponents[d],
            &mut solver.x_exponents[d],
            tol_sq,
        );
        if let Some(g) = given[d].filter(|_| st.active) {
            let r = Block {
                e: g.exponent,
                bound: g.bound,
            };
            st.set_residual(g.rr, r);
            st.given = true;
            st.drift = g.drift.unwrap_or(Upper::INFINITE);
            st.skippable = g.drift.is_some();
        }
    }
    charge(&mut solver.clock.svu, t0, exec);
    solver.start();
    let mut unverified = [false; MAX_DIRECTIONS];
    for (d, g) in given.iter().enumerate().take(directions) {
        let st = &solver.state[d];
        unverified[d] =
            st.given && st.converged && g.is_some_and(|g| g.verify) && !solver.proven(d);
    }
    solver.replace_residuals(unverified);
    while solver.state.iter().any(|s| s.active)
        && solver.iterations < params.max_iterations
        && solver.within_budget()
    {
        if solver.iterations == 0 {
            // The set-up's serial work goes to the whole solve, not to the first iteration.
            solver.clock.flush_serial(exec);
            solver.clock.costs.first_iteration = true;
        }
        let verify = solver.iterate()?;
        solver.replace_residuals(verify);
    }
    solver.clock.flush_serial(exec);
    let outcomes: [Outcome; MAX_DIRECTIONS] = core::array::from_fn(|d| {
        let st = &solver.state[d];
        Outcome {
            r_exponent: st.r.e,
            r_bound: st.r.bound,
            r_exact: st.r_exact,
            x_bound: st.x.bound,
            // Tracked through the updates only where asked for (integer `Upper` arithmetic on
            // hart 0's serial path, out of line); an exact pass's is always known, and so is a
            // start no update touched (r = b copied for x₀ = 0: none; a given r: the caller's).
            drift: if solver.sat == 0 && (st.r_exact || st.skippable || st.iterations == 0) {
                st.drift
            } else {
                Upper::INFINITE
            },
            check_skipped: st.skipped,
            updates: if solver.sat == 0 && st.given && st.skippable {
                st.updates
            } else {
                Upper::INFINITE
            },
        }
    });
    let (report, x_exponents) = finish(&solver);
    drop(engine);
    for ((s, e), outcome) in systems.iter_mut().zip(x_exponents).zip(outcomes) {
        s.x_exponent = e;
        s.outcome = outcome;
    }
    Ok(report)
}

/// What [`product`] measured: per lane the OR of |K·v| (its highest bit is that of the largest
/// row sum), hart 0's counters over the phase and its critical path (every parallel step's
/// slowest hart plus hart 0's serial work).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Product {
    pub or: [u64; MAX_DIRECTIONS],
    pub on_hart0: PhaseCounters,
    pub critical: PhaseCounters,
}

/// K·v for up to three vectors at once, `vectors[k]` into lane k of `work.kp` as exact `i64` row
/// sums (value 2^(e_v − F) each): the MVU phase on its own, as a dynamic step needs it for
/// K·u₀ ([`crate::dynamics`]). The vectors are only read (p's lanes take a copy). Kp is laid
/// out [`sum_words_for`]`(exec, vectors.len())` words a row, as the solver lays it out.
pub fn product(
    a: &Matrix<'_>,
    vectors: &mut [&mut [i32]],
    work: Work<'_>,
    exec: &impl Executor,
) -> Result<Product, SolveFailure> {
    let n = a.n;
    let lanes = vectors.len();
    if !(1..=MAX_DIRECTIONS).contains(&lanes) {
        return Err(SolveFailure::BadDirections(lanes as u8));
    }
    let plan = a.plan;
    let harts = plan.mvus.clamp(1, MAX_HARTS);
    if vectors.iter().any(|v| v.len() < n)
        || work.p.len() < n
        || work.kp.len() < n
        || work.partial.len() < plan.partial_len
        || plan.mvus > exec.harts()
    {
        return Err(SolveFailure::WorkspaceTooSmall);
    }
    let t0 = exec.now();
    let Work { p, kp, partial } = work;
    let mut out = [HartOut::default()];
    let totals = Totals::default();
    let mut xs = heapless::Vec::new();
    for v in vectors.iter_mut() {
        let _ = xs.push(SharedSlice::new(&mut v[..n]));
    }
    let (p, kp) = (
        SharedSlice::new(&mut p[..n]),
        SharedSlice::new(&mut kp[..n]),
    );
    let lane_words = lane_words_for(exec, lanes);
    let engine = Engine {
        a,
        exec,
        hardware: hardware(exec, n, (&p, &kp, lane_words), lanes),
        harts,
        directions: lanes,
        lane_words,
        p,
        kp,
        partial: SharedSlice::new(partial),
        out: SharedSlice::new(&mut out),
        totals: &totals,
        xs,
        rs: heapless::Vec::new(),
    };
    let mut clock = Clock {
        last: t0,
        ..Clock::default()
    };
    if !plan.fused {
        // Rows the MVUs add into start from zero.
        engine.run(
            &|h| {
                let range = share(n, harts, h);
                // SAFETY: each hart clears only its own share of Kp.
                with_lanes!(engine, |S, R| unsafe { engine.kp_rows::<R>(range) }
                    .fill([0; R]));
            },
            &mut clock,
            true,
        );
    }
    engine.set_lanes([Lane::X; MAX_DIRECTIONS], &mut clock);
    engine.mvu(&mut clock);
    clock.flush_serial(exec);
    let or = engine.total().kp_or;
    let now = exec.now();
    Ok(Product {
        or,
        on_hart0: now.since(t0),
        critical: clock.costs.whole.critical(),
    })
}

/// Direction d's state before the first iteration, from the set-up's results. A direction
/// with b = 0 gets x = 0 (on hart 0: it does nothing else).
fn initial_state<E: Executor>(
    engine: &Engine<'_, '_, E>,
    d: usize,
    b_exponent: i32,
    x_exponent: &mut i32,
    tol_sq: f64,
) -> Direction {
    let total = engine.total();
    let (bb, b_or) = (total.rr[d], total.b_or[d]);
    let (mut x_or, mut x_any) = (total.x_or[d], total.x_any[d]);
    if bb == 0 && x_any != 0 {
        // SAFETY: no task runs; hart 0 has the vectors to itself.
        unsafe { engine.xs[d].slice_mut(0..engine.a.n) }.fill(0);
        // SAFETY: as above.
        with_lanes!(engine, |S| unsafe { engine.p_lanes::<S>(0..engine.a.n) }
            .iter_mut()
            .for_each(|pi| pi[d] = 0));
        (x_or, x_any) = (0, 0);
    }
    if x_any == 0 {
        *x_exponent = 0;
    }
    let r = Block {
        e: b_exponent,
        bound: bound_of(b_or),
    };
    let mut st = Direction {
        active: bb != 0,
        bb,
        x: Block {
            e: *x_exponent,
            bound: if x_any != 0 { bound_of(x_or) } else { 0 },
        },
        b: r,
        threshold: Threshold::new(tol_sq, bb, b_exponent),
        ..Direction::IDLE
    };
    st.set_residual(bb, r);
    st
}

/// The report, and each system's x exponent.
/// By reference: the solver is about 1 kB, which a move copied on hart 0's serial path.
fn finish<E: Executor>(solver: &Solver<'_, '_, '_, E>) -> (SolveReport, [i32; MAX_DIRECTIONS]) {
    let engine = solver.engine;
    let costs = &solver.clock.costs;
    let mut report = SolveReport {
        iterations: solver.iterations,
        converged: true,
        residual: 0.0,
        directions: heapless::Vec::new(),
        words_per_iteration: engine.a.words.len() as u32,
        mvus: engine.harts as u8,
        overlapping: engine.a.plan.overlapping,
        mvu: solver.clock.mvu,
        svu: solver.clock.svu,
        per_iteration: costs.first,
        saturations: solver.sat,
        whole_solve: costs.whole,
        first_iteration_scalar: costs.first_scalar,
    };
    for st in &solver.state[..engine.directions] {
        let converged = st.converged;
        let residual = st.residual();
        report.converged &= converged;
        report.residual = report.residual.max(residual);
        let _ = report.directions.push(DirectionReport {
            iterations: st.iterations,
            converged,
            residual,
        });
    }
    (report, solver.x_exponents)
}

/// √x for x ≥ 0 without std, correctly rounded (as IEEE 754's square root), in integers:
/// the root of x's 53-bit mantissa (its exponent made even) digit by digit in 32-bit words,
/// then its low 26 bits from one division and the exact remainder, rounded to nearest. It
/// replaced Newton's method in soft f64 (a division per step, five to seven steps) on hart 0's
/// serial path at the end of every solve (docs/PERFORMANCE.md, "The dynamic step's
/// bookkeeping, session 10").
pub(crate) fn sqrt(x: f64) -> f64 {
    if x <= 0.0 || !x.is_finite() {
        return if x == 0.0 { 0.0 } else { x.max(0.0) };
    }
    let bits = x.to_bits();
    let biased = ((bits >> 52) & 0x7ff) as i32;
    if biased == 0 {
        // Subnormal: scaled by 2^64 it is normal, and both scalings are exact.
        return sqrt(x * ldexp(1.0, 64)) * ldexp(1.0, -32);
    }
    // x = m·2^k, m ∈ [2^52, 2^54) with k even.
    let (mut m, mut k) = ((bits & ((1u64 << 52) - 1)) | (1u64 << 52), biased - 1075);
    if k & 1 != 0 {
        m <<= 1;
        k -= 1;
    }
    // √m ∈ [2^26, 2^27) first, two bits of the radicand at a time in 32-bit words (m's high
    // and low words in turn; the root stays below 2^27 and the remainder, at most 2·root,
    // below 2^28): r1 = ⌊√m⌋, rem1 = m − r1².
    let (mut r1, mut rem1) = (0u32, 0u32);
    let (high, low) = ((m >> 32) as u32, m as u32);
    for i in 0..27 {
        let shift = 52 - 2 * i;
        let pair = if shift >= 32 {
            (high >> (shift - 32)) & 3
        } else {
            (low >> shift) & 3
        };
        rem1 = (rem1 << 2) | pair;
        let trial = (r1 << 2) | 1;
        r1 <<= 1;
        if rem1 >= trial {
            rem1 -= trial;
            r1 |= 1;
        }
    }
    // Then ⌊√(m·2^52)⌋ = r1·2^26 + t for the largest t ≥ 0 with f(t) = rem1·2^52 − t·(a + t)
    // ≥ 0, a = r1·2^27 (f falls with t). With rem1·2^25 = q·r1 + s, f(q) = s·2^27 − q²
    // exactly, and q ≥ t (it leaves out t²): f(t − 1) = f(t) + a + 2t − 1 steps down, at
    // most once (f(q) ≥ −q² ≥ −2^52 while a ≥ 2^53). Every quantity fits an i64.
    let (r1, rem1) = (u64::from(r1), u64::from(rem1));
    let numerator = rem1 << 25;
    let (q, s) = (numerator / r1, numerator % r1);
    let a = (r1 << 27) as i64;
    let mut t = q as i64;
    let mut rem = ((s << 27) as i64) - t * t;
    while rem < 0 {
        rem += a + 2 * t - 1;
        t -= 1;
    }
    let mut root = (r1 << 26) + t as u64;
    let rem = rem as u64;
    // (root + ½)² = root² + root + ¼, so the root rounds up where the remainder (m·2^52 −
    // root², at most 2·root) exceeds it (never a tie: the radicand is an integer).
    let mut e = (k - 52) / 2;
    if rem > root {
        root += 1;
        if root == 1u64 << 53 {
            root >>= 1;
            e += 1;
        }
    }
    // root·2^e, root ∈ [2^52, 2^53): a normal f64 for any x > 0.
    f64::from_bits((((e + 1075) as u64) << 52) | (root & ((1u64 << 52) - 1)))
}

/// Adds hart 0's counters elapsed since `since` to `total`.
/// Adds a split row's first part `part` into its finished second part at `y` (see
/// [`continues`]).
///
/// # Safety
///
/// `y` is a row of Kp that no other hart accesses during the call.
unsafe fn carry<const R: usize>(y: *mut [i64; R], part: [i64; R], directions: usize) {
    // SAFETY: forwarded from the caller.
    let row = unsafe { &mut *y };
    for (sum, part) in row.iter_mut().zip(part).take(directions) {
        *sum += part;
    }
}

/// Rows `range` of a buffer of [`Sums`] (Kp or the partial pool) seen `R` i64 words a row.
///
/// # Safety
///
/// `R` ≤ [`MAX_DIRECTIONS`] and `range` lies within the buffer's rows; as
/// [`SharedSlice::slice_mut`]: no one else accesses these rows while the slice lives.
#[allow(clippy::mut_from_ref)]
#[inline(always)]
unsafe fn rows_of<'s, const R: usize>(
    buffer: &'s SharedSlice<'_, Sums>,
    range: core::ops::Range<usize>,
) -> &'s mut [[i64; R]] {
    debug_assert!(R <= MAX_DIRECTIONS && range.start <= range.end);
    let base = buffer.as_mut_ptr().cast::<[i64; R]>();
    // SAFETY: forwarded from the caller.
    unsafe { core::slice::from_raw_parts_mut(base.wrapping_add(range.start), range.len()) }
}

fn charge(total: &mut PhaseCounters, since: PhaseCounters, clock: &impl PhaseClock) {
    *total += clock.now().since(since);
}

#[cfg(test)]
mod tests;
mod totals;
