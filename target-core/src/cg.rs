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
//! - **SVU**: hart 0 computes α for each direction; every hart updates x and r on its slice of
//!   the vectors (with Σr² and the maxima for the block exponents), hart 0 combines them and
//!   computes β; every hart updates p on its slice; hart 0 combines the maxima.
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
//! - Scalars (α, β, norms) are `f64` on hart 0 (soft float, a few hundred instructions per
//!   iteration, nothing per element).
//!
//! # The SVU's element operation, and why it cannot overflow
//!
//! Every vector update is z = a·u + b·y, done per element as
//! `z_i = round(A·(u_i << k_u) / 2^(32 + o_u)) + round(B·(y_i << k_y) / 2^(32 + o_y))`
//! (`Term`): hart 0 folds the scalars and the exponents into two 32-bit multipliers A, B and
//! loop-invariant shifts. That costs a `sll`, `mul`, `mulh`, a rounding carry and a `sra` per
//! term instead of a 64-bit variable shift. The shifts k normalise u and y so that their largest
//! element lies in [2^30, 2^31), and the shifts o keep |A|, |B| in [2^30, 2^31): the scalars
//! keep 30 significant bits however small their term is next to the other. The output exponent
//! is chosen from the tracked maxima so that |a·u + b·y| < 2^29 in output units; the two
//! roundings add at most one unit, so |z| < 2^30: nothing can saturate. Because the maxima are
//! measured in every pass (an OR of the magnitudes, which has the same highest bit as the
//! maximum), the exponent follows the vector down as the residual shrinks, and each vector keeps
//! ~28–29 significant bits relative to its largest element.
//!
//! K·p comes from the MVU as exact `i64` row sums; the r-update narrows each to 31 bits with a
//! loop-invariant funnel shift chosen from max |Kp|. pᵀKp (exact `i128`) and Σr² (exact `u128`,
//! summed in `u64` blocks of 8) are integers.
//!
//! Saturation is nonetheless detected: a multiplier that would not fit `i32`, a vector whose
//! maximum breaks its bound, or a K·p beyond 2^62 is clamped and counted in
//! [`SolveReport::saturations`], which the host reports as an error.

// Harts share the vectors through `SharedSlice`s and the MVU kernel walks raw pointers; every
// `unsafe` block below states which part of the work split makes it sound.
#![allow(unsafe_code)]

use deform_shared::matrix::{MatrixError, TileHeader};
use deform_shared::protocol::{
    DirectionReport, IterationCost, PhaseCounters, SolveFailure, SolveParams, SolveReport, Start,
    MAX_DIRECTIONS, MAX_HARTS,
};
use deform_shared::qformat::{floor_log2, ldexp};
use deform_shared::word::ER_BIT;

use crate::exec::{share, SharedSlice};
pub use crate::exec::{Executor, NoClock, PhaseClock, Sequential};
use crate::kernel::{run_tile_dyn, Lanes, Sums, TileRun};

/// How often a direction's residual is recomputed as b − A·x after it converged on the
/// recursive one. Fixed point cannot go below its own floor, so after this the recursive
/// residual is accepted (the host's refinement takes over from there).
const MAX_REPLACEMENTS: u32 = 2;

/// Mantissas produced by the SVU stay below 2^OUTPUT_BITS (the MVU's exactness needs < 2^30).
const OUTPUT_BITS: i32 = 30;
/// The output exponent keeps the bound on |a·u + b·y| below 2^BOUND_BITS units, leaving room
/// for the two rounding errors below 2^OUTPUT_BITS.
const BOUND_BITS: i32 = 29;
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
    };
    // Words per row, mirrors included: every row sum must stay far from i64 overflow.
    let counts = scratch.get_mut(..n).unwrap_or(&mut []);
    counts.iter_mut().for_each(|c| c[0] = 0);
    let mut start = 0usize;
    for (i, t) in tiles.iter().enumerate() {
        let h = usize::from(t.mvu).min(MAX_HARTS - 1);
        plan.mvus = plan.mvus.max(h + 1);
        let (lo, hi) = (t.row_base as usize, (t.row_base + t.rows) as usize);
        plan.rows[h][0] = plan.rows[h][0].cover(lo, hi);
        if t.mirrored {
            plan.rows[h][1] = plan.rows[h][1].cover(n - hi, n - lo);
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
}

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

/// Block-floating-point vector state besides its mantissas: exponent and a bound on max |m|.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Block {
    e: i32,
    bound: u64,
}

/// A bound on max |z| from the OR of `magnitude_bits(z)` (= |z| − 1 for negative z): every
/// |z| ≤ or + 1.
fn bound_of(or: u32) -> u64 {
    u64::from(or) + 1
}

#[inline(always)]
fn magnitude_bits(z: i32) -> u32 {
    (z ^ (z >> 31)) as u32
}

/// One term of an SVU update: mult·(u << shift) / 2^(32 + out), rounded to nearest.
///
/// `mult` is kept in [2^30, 2^31) in magnitude whenever the term matters, so the scalar it
/// carries (α, β, or a power of two) keeps 30 significant bits however small the term is next
/// to the other one; `out` shifts the product's high word down instead.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Term {
    mult: i32,
    shift: u32,
    out: u32,
    /// 2^(31 + out): rounds the final shift to nearest.
    round: i64,
}

impl Term {
    #[inline(always)]
    fn apply(self, u: i32) -> i32 {
        let product = self.mult as i64 * (u << self.shift) as i64 + self.round;
        ((product >> 32) as i32) >> self.out
    }
}

/// z = a·u + b·y as two [`Term`]s, with z's exponent.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Lin {
    u: Term,
    y: Term,
    e: i32,
}

/// The left shift that brings a vector with max |m| ≤ `bound` into [2^30, 2^31).
fn normalising_shift(bound: u64) -> u32 {
    if bound == 0 {
        0
    } else {
        (30 - floor_log2(bound as f64)).clamp(0, 31) as u32
    }
}

impl Lin {
    /// Plans z = a·u + b·y for blocks u and y (`u_shift`: u's elements are already normalised,
    /// e.g. narrowed K·p, and must not be shifted again). Counts a multiplier that does not fit
    /// in `saturations`.
    fn new(a: f64, u: Block, u_normalised: bool, b: f64, y: Block, saturations: &mut u32) -> Lin {
        let bound = a.abs() * ldexp(u.bound as f64, u.e) + b.abs() * ldexp(y.bound as f64, y.e);
        if bound == 0.0 || !bound.is_finite() {
            if !bound.is_finite() {
                *saturations += 1;
            }
            return Lin::default();
        }
        let e = floor_log2(bound) + 1 - BOUND_BITS;
        let ku = if u_normalised {
            0
        } else {
            normalising_shift(u.bound)
        };
        let ky = normalising_shift(y.bound);
        let term = |c: f64, block: Block, shift: u32, saturations: &mut u32| -> Term {
            if block.bound == 0 || c == 0.0 {
                return Term::default();
            }
            let m = ldexp(c, block.e - shift as i32 - e + 32);
            let out = (30 - floor_log2(m)).clamp(0, 31) as u32;
            let m = ldexp(m, out as i32);
            let m = if m >= 0.0 { m + 0.5 } else { m - 0.5 };
            let mult = if m.abs() >= 2147483648.0 {
                // Up to half a unit over is the rounding of a multiplier just below 2^31;
                // anything more breaks the bound.
                if m.abs() >= 2147483649.0 {
                    *saturations += 1;
                }
                if m > 0.0 {
                    i32::MAX
                } else {
                    i32::MIN + 1
                }
            } else {
                m as i64 as i32
            };
            Term {
                mult,
                shift,
                out,
                round: 1i64 << (31 + out),
            }
        };
        Lin {
            u: term(a, u, ku, saturations),
            y: term(b, y, ky, saturations),
            e,
        }
    }
}

/// How the r-update reads K·p: narrowed from `i64` to 31 bits by a loop-invariant shift.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
enum Narrow {
    /// max |Kp| < 2^31: `(kp as i32) << k`.
    #[default]
    Left,
    /// `kp >> s` for s in 1..=31, as a funnel shift of the two halves.
    Right(u32),
}

impl Narrow {
    /// The narrowing for max |Kp| ≤ `max`, its left shift (for `Left`), and the resulting
    /// block's exponent offset and bound. Counts max ≥ 2^62 (cannot happen) as a saturation.
    fn new(max: u64, saturations: &mut u32) -> (Narrow, u32, i32, u64) {
        if max >= 1 << 62 {
            *saturations += 1;
        }
        let bits = 64 - max.leading_zeros();
        if bits <= 31 {
            let k = normalising_shift(max);
            (Narrow::Left, k, -(k as i32), max << k)
        } else {
            let s = (bits - 31).min(31);
            (Narrow::Right(s), 0, s as i32, (max >> s) + 1)
        }
    }
}

/// What each hart reports from a phase.
#[derive(Debug, Clone, Copy, Default)]
struct HartOut {
    p_kp: [i128; MAX_DIRECTIONS],
    /// Σ r² of the new residual.
    sum_sq: [u128; MAX_DIRECTIONS],
    /// OR of magnitudes: [0] of Kp's (as u64), [1] of x, [2] of r or p.
    kp_or: [u64; MAX_DIRECTIONS],
    x_or: [u32; MAX_DIRECTIONS],
    v_or: [u32; MAX_DIRECTIONS],
}

/// Per-direction state of the fused loop.
#[derive(Debug, Clone, Copy)]
struct Direction {
    active: bool,
    iterations: u32,
    bb: f64,
    b_e: i32,
    x: Block,
    r: Block,
    p: Block,
    rr: u128,
    residual_sq: f64,
    /// b's block, to restart r from.
    b: Block,
    /// Residual replacements done so far.
    replacements: u32,
}

impl Direction {
    /// ‖r‖²/‖b‖² for a residual block with exponent e_r and Σm² = rr.
    fn ratio(&self, rr: u128, e_r: i32) -> f64 {
        ldexp(rr as f64 / self.bb, 2 * (e_r - self.b_e))
    }
}

/// Σ z² over a slice, exact: squares below 2^60 summed in u64 blocks of 8.
fn sum_squares(v: &[i32]) -> u128 {
    v.chunks(8)
        .map(|c| {
            c.iter()
                .map(|&z| (z as i64 * z as i64) as u64)
                .fold(0u64, u64::wrapping_add) as u128
        })
        .sum()
}

/// The per-phase instruction counts of the measured iteration.
#[derive(Default)]
struct Costs {
    measuring: bool,
    cost: IterationCost,
}

impl Costs {
    fn parallel(&mut self, counts: [u64; MAX_HARTS], harts: usize, mvu: bool) {
        let counts = &counts[..harts.min(MAX_HARTS)];
        let max = counts.iter().copied().max().unwrap_or(0);
        let sum: u64 = counts.iter().sum();
        if mvu {
            self.cost.mvu_critical += max;
            self.cost.mvu_total += sum;
        } else {
            self.cost.svu_critical += max;
            self.cost.svu_total += sum;
        }
    }

    fn serial(&mut self, instructions: u64) {
        self.cost.svu_critical += instructions;
        self.cost.svu_total += instructions;
    }
}

/// The solver's context for one solve: the matrix, the shared vectors and the executor.
struct Engine<'e, 'a, E: Executor> {
    a: &'e Matrix<'a>,
    exec: &'e E,
    harts: usize,
    directions: usize,
    p: SharedSlice<'e, Lanes>,
    kp: SharedSlice<'e, Sums>,
    partial: SharedSlice<'e, Sums>,
    out: SharedSlice<'e, HartOut>,
}

impl<E: Executor> Engine<'_, '_, E> {
    fn run(&self, task: &(dyn Fn(usize) + Sync), costs: &mut Costs, mvu: bool) {
        if costs.measuring {
            let counts = self.exec.run_measured(self.harts, task);
            costs.parallel(counts, self.harts, mvu);
        } else {
            self.exec.run(self.harts, task);
        }
    }

    /// The results of every hart in use, read on hart 0 between phases.
    fn outs(&self) -> &[HartOut] {
        // SAFETY: called only between phases, when no task runs.
        let all = unsafe { self.out.as_slice() };
        &all[..self.harts.min(all.len())]
    }

    /// Kp = K·p for every direction, pᵀKp, and the OR of |Kp|.
    fn mvu(&self, costs: &mut Costs) {
        let a = self.a;
        let plan = a.plan;
        let n = a.n;
        let directions = self.directions;
        let task = |h: usize| {
            let p = self.p.as_mut_ptr() as *const Lanes;
            let mut p_kp = [0i128; MAX_DIRECTIONS];
            // Zero this MVU's rows (direct) or private slots (overlapping).
            for (k, rows) in plan.rows[h].iter().enumerate() {
                let range = if plan.overlapping {
                    plan.offsets[h][k]..plan.offsets[h][k] + rows.len()
                } else {
                    rows.lo..rows.hi
                };
                let target = if plan.overlapping {
                    &self.partial
                } else {
                    &self.kp
                };
                // SAFETY: the plan gives every MVU rows (direct: non-overlapping hulls) or
                // slots (overlapping: its own offsets) that no other MVU touches.
                unsafe { target.slice_mut(range) }.fill([0; MAX_DIRECTIONS]);
            }
            let mut start = 0usize;
            for t in a.tiles {
                let first = start;
                start += t.words as usize;
                if usize::from(t.mvu) != h {
                    continue;
                }
                let (row_base, col_base) = (t.row_base as usize, t.col_base as usize);
                let mirror_row = n - 1 - row_base;
                let (y, y_mirror) = if plan.overlapping {
                    let base = self.partial.as_mut_ptr();
                    let [own, mirror] = plan.rows[h];
                    (
                        base.wrapping_add(plan.offsets[h][0] + row_base - own.lo),
                        base.wrapping_add(plan.offsets[h][1])
                            .wrapping_add(mirror_row)
                            .wrapping_sub(mirror.lo),
                    )
                } else {
                    let base = self.kp.as_mut_ptr();
                    (base.wrapping_add(row_base), base.wrapping_add(mirror_row))
                };
                let run = TileRun {
                    words: a.words.as_ptr().wrapping_add(first),
                    rows: t.rows,
                    p_cols: p.wrapping_add(col_base),
                    p_mirror_cols: p.wrapping_add(n - 1 - col_base),
                    y,
                    y_mirror,
                    p_row: p.wrapping_add(row_base),
                    p_mirror_row: p.wrapping_add(mirror_row),
                };
                // SAFETY: the session validated every tile against n (rows, columns, ER/EM
                // structure) and sized p, kp and the pool for n and the plan; the tile's rows
                // and mirror rows lie in this MVU's hulls, which map to slots only it writes;
                // p is only read during this phase.
                unsafe { run_tile_dyn(&run, directions, t.mirrored, &mut p_kp) };
            }
            // SAFETY: each hart writes only its own result slot.
            if let Some(out) = unsafe { self.out.slice_mut(h..h + 1) }.first_mut() {
                out.p_kp = p_kp;
            }
        };
        self.run(&task, costs, true);

        // Add the partial rows (overlapping) and find max |Kp|, each hart on its share of rows.
        let task = |h: usize| {
            let range = share(n, self.harts, h);
            // SAFETY: the shares of the rows are disjoint; the pool is only read.
            let kp = unsafe { self.kp.slice_mut(range.clone()) };
            if plan.overlapping {
                kp.fill([0; MAX_DIRECTIONS]);
                // SAFETY: nothing writes the pool during this phase.
                let pool = unsafe { self.partial.as_slice() };
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
                            for j in 0..MAX_DIRECTIONS {
                                d[j] += s[j];
                            }
                        }
                    }
                }
            }
            let mut or = [0u64; MAX_DIRECTIONS];
            for row in kp.iter() {
                for d in 0..directions {
                    let v = row[d];
                    or[d] |= (v ^ (v >> 63)) as u64;
                }
            }
            // SAFETY: each hart writes only its own result slot.
            if let Some(out) = unsafe { self.out.slice_mut(h..h + 1) }.first_mut() {
                out.kp_or = or;
            }
        };
        self.run(&task, costs, true);
    }
}

/// The x- and r-updates of one direction on one slice: x ← x + α p, r ← r − α Kp.
#[allow(clippy::too_many_arguments)]
fn update_x_r(
    x: &mut [i32],
    r: &mut [i32],
    p: &[Lanes],
    kp: &[Sums],
    d: usize,
    x_lin: Option<Lin>,
    r_lin: Lin,
    narrow: (Narrow, u32),
    out: &mut HartOut,
) {
    if let Some(lin) = x_lin {
        let mut or = 0u32;
        for (xi, pi) in x.iter_mut().zip(p) {
            let z = lin.u.apply(pi[d]) + lin.y.apply(*xi);
            *xi = z;
            or |= magnitude_bits(z);
        }
        out.x_or[d] = or;
    }
    let mut or = 0u32;
    let mut sum_sq = 0u128;
    let (u, y) = (r_lin.u, r_lin.y);
    match narrow {
        (Narrow::Left, k) => {
            for (rc, kc) in r.chunks_mut(8).zip(kp.chunks(8)) {
                let mut block = 0u64;
                for (ri, ki) in rc.iter_mut().zip(kc) {
                    let z = u.apply((ki[d] as i32) << k) + y.apply(*ri);
                    *ri = z;
                    or |= magnitude_bits(z);
                    block = block.wrapping_add((z as i64 * z as i64) as u64);
                }
                sum_sq += block as u128;
            }
        }
        (Narrow::Right(s), _) => {
            let back = 32 - s;
            for (rc, kc) in r.chunks_mut(8).zip(kp.chunks(8)) {
                let mut block = 0u64;
                for (ri, ki) in rc.iter_mut().zip(kc) {
                    let v = ki[d];
                    let narrowed =
                        ((v as u32).wrapping_shr(s) | ((v >> 32) as u32).wrapping_shl(back)) as i32;
                    let z = u.apply(narrowed) + y.apply(*ri);
                    *ri = z;
                    or |= magnitude_bits(z);
                    block = block.wrapping_add((z as i64 * z as i64) as u64);
                }
                sum_sq += block as u128;
            }
        }
    }
    out.v_or[d] = or;
    out.sum_sq[d] = sum_sq;
}

/// p ← r + β p for one direction on one slice.
fn update_p(p: &mut [Lanes], r: &[i32], d: usize, lin: Lin, out: &mut HartOut) {
    let mut or = 0u32;
    for (pi, ri) in p.iter_mut().zip(r) {
        let z = lin.u.apply(*ri) + lin.y.apply(pi[d]);
        pi[d] = z;
        or |= magnitude_bits(z);
    }
    out.v_or[d] = or;
}

/// The scalars hart 0 hands to pass A for one direction.
#[derive(Debug, Clone, Copy)]
struct PassA {
    x: Option<Lin>,
    r: Lin,
    narrow: (Narrow, u32),
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
    let f = a.frac_bits as i32;
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
    let mut saturations = 0u32;
    let mut report = SolveReport {
        iterations: 0,
        converged: false,
        residual: 0.0,
        directions: heapless::Vec::new(),
        words_per_iteration: a.words.len() as u32,
        mvus: harts as u8,
        overlapping: plan.overlapping,
        mvu: PhaseCounters::default(),
        svu: PhaseCounters::default(),
        per_iteration: IterationCost::default(),
        saturations: 0,
    };
    let t = exec.now();
    let zero = Block { e: 0, bound: 0 };
    let mut state = [Direction {
        active: false,
        iterations: 0,
        bb: 0.0,
        b_e: 0,
        x: zero,
        r: zero,
        p: zero,
        rr: 0,
        residual_sq: 0.0,
        b: zero,
        replacements: 0,
    }; MAX_DIRECTIONS];
    let tol_sq = params.tolerance * params.tolerance;
    let Work { p, kp, partial } = work;
    let (p, kp) = (&mut p[..n], &mut kp[..n]);
    p.fill([0; 4]);
    kp.fill([0; MAX_DIRECTIONS]);
    let mut any_guess = false;
    for (d, s) in systems.iter_mut().enumerate() {
        let bb = sum_squares(&s.b[..n]);
        let st = &mut state[d];
        st.b_e = s.b_exponent;
        st.bb = bb as f64;
        if bb == 0 || params.start == Start::Zero {
            s.x[..n].fill(0);
            s.x_exponent = 0;
        }
        let or = |v: &[i32]| v.iter().fold(0, |o, &m| o | magnitude_bits(m));
        st.x = Block {
            e: s.x_exponent,
            bound: bound_of(or(&s.x[..n])),
        };
        st.active = bb != 0;
        s.r[..n].copy_from_slice(&s.b[..n]);
        st.rr = bb;
        st.r = Block {
            e: s.b_exponent,
            bound: bound_of(or(&s.b[..n])),
        };
        st.b = st.r;
        st.x.bound = if s.x[..n].iter().any(|&v| v != 0) {
            st.x.bound
        } else {
            0
        };
        if st.active && st.x.bound != 0 {
            any_guess = true;
            for (pi, &xi) in p.iter_mut().zip(s.x[..n].iter()) {
                pi[d] = xi;
            }
        }
    }
    let mut outs = [HartOut::default(); MAX_HARTS];
    let systems_b: heapless::Vec<&[i32], MAX_DIRECTIONS> = systems.iter().map(|s| s.b).collect();
    let mut xs: heapless::Vec<SharedSlice<'_, i32>, MAX_DIRECTIONS> = heapless::Vec::new();
    let mut rs: heapless::Vec<SharedSlice<'_, i32>, MAX_DIRECTIONS> = heapless::Vec::new();
    let mut x_exponents = [0i32; MAX_DIRECTIONS];
    for (d, s) in systems.iter_mut().enumerate() {
        x_exponents[d] = s.x_exponent;
        let _ = xs.push(SharedSlice::new(&mut s.x[..n]));
        let _ = rs.push(SharedSlice::new(&mut s.r[..n]));
    }
    let engine = Engine {
        a,
        exec,
        harts,
        directions,
        p: SharedSlice::new(p),
        kp: SharedSlice::new(kp),
        partial: SharedSlice::new(partial),
        out: SharedSlice::new(&mut outs),
    };
    let mut costs = Costs::default();
    charge(&mut report.svu, t, exec);

    // Pass A: x ← x + α p (if planned) and r ← r − α Kp, each hart on its share.
    let pass_a = |plans: &[Option<PassA>; MAX_DIRECTIONS], costs: &mut Costs| {
        let task = |h: usize| {
            let range = share(n, harts, h);
            // SAFETY: each hart writes only its own share of x and r and its own result slot;
            // p and kp are only read during this pass.
            unsafe {
                let out = &mut engine.out.slice_mut(h..h + 1)[0];
                let (p, kp) = (engine.p.as_slice(), engine.kp.as_slice());
                for (d, plan) in plans.iter().enumerate().take(directions) {
                    if let Some(plan) = plan {
                        let x = xs[d].slice_mut(range.clone());
                        let r = rs[d].slice_mut(range.clone());
                        let (p, kp) = (&p[range.clone()], &kp[range.clone()]);
                        update_x_r(x, r, p, kp, d, plan.x, plan.r, plan.narrow, out);
                    }
                }
            }
        };
        engine.run(&task, costs, false);
    };
    // Pass B: p ← r + β p, each hart on its share.
    let pass_b = |plans: &[Option<Lin>; MAX_DIRECTIONS], costs: &mut Costs| {
        let task = |h: usize| {
            let range = share(n, harts, h);
            // SAFETY: each hart writes only its own share of p and its own result slot; r is
            // only read during this pass.
            unsafe {
                let out = &mut engine.out.slice_mut(h..h + 1)[0];
                let p = engine.p.slice_mut(range.clone());
                for (d, plan) in plans.iter().enumerate().take(directions) {
                    if let Some(lin) = plan {
                        let r = &rs[d].as_slice()[range.clone()];
                        update_p(p, r, d, *lin, out);
                    }
                }
            }
        };
        engine.run(&task, costs, false);
    };
    // The r-update's scalars for direction d: r ← r + c·Kp with Kp narrowed from its maxima.
    let r_plan =
        |d: usize, c: f64, st: &Direction, saturations: &mut u32| -> (Lin, (Narrow, u32)) {
            let kp_max = engine.outs().iter().fold(0u64, |o, out| o | out.kp_or[d]);
            let (narrow, k, e_offset, bound) = Narrow::new(bound_of_u64(kp_max), saturations);
            let kp_block = Block {
                e: st.p.e - f + e_offset,
                bound,
            };
            let lin = Lin::new(c, kp_block, true, 1.0, st.r, saturations);
            (lin, (narrow, k))
        };
    // Folds pass A's results of direction d into its state.
    let take_r = |d: usize, lin: Lin, st: &mut Direction, saturations: &mut u32| {
        let outs = engine.outs();
        let rr: u128 = outs.iter().map(|o| o.sum_sq[d]).sum();
        let or = outs.iter().fold(0u32, |o, out| o | out.v_or[d]);
        check_bound(or, saturations);
        st.rr = rr;
        st.r = Block {
            e: lin.e,
            bound: bound_of(or),
        };
        st.residual_sq = st.ratio(rr, lin.e);
    };

    // r₀ = b − A x₀ where x₀ ≠ 0.
    if any_guess {
        let t = exec.now();
        engine.mvu(&mut costs);
        charge(&mut report.mvu, t, exec);
        let t = exec.now();
        let mut plans = [None; MAX_DIRECTIONS];
        for d in 0..directions {
            let st = &state[d];
            if st.active && st.x.bound != 0 {
                // K·x₀ was computed with x₀'s exponent in place of p's.
                let st = Direction { p: st.x, ..*st };
                let (r, narrow) = r_plan(d, -1.0, &st, &mut saturations);
                plans[d] = Some(PassA { x: None, r, narrow });
            }
        }
        pass_a(&plans, &mut costs);
        for (d, plan) in plans.iter().enumerate() {
            if let Some(plan) = plan {
                take_r(d, plan.r, &mut state[d], &mut saturations);
            }
        }
        charge(&mut report.svu, t, exec);
    }
    let t = exec.now();
    // p₀ = r₀ for every direction that still has work.
    for (d, st) in state.iter_mut().enumerate().take(directions) {
        if st.active {
            st.residual_sq = st.ratio(st.rr, st.r.e);
            st.active = st.residual_sq > tol_sq;
        }
        // SAFETY: no task runs; hart 0 has the vectors to itself.
        let (p, r) = unsafe { (engine.p.slice_mut(0..n), rs[d].as_slice()) };
        for (pi, &ri) in p.iter_mut().zip(r) {
            pi[d] = if st.active { ri } else { 0 };
        }
        st.p = st.r;
    }
    charge(&mut report.svu, t, exec);

    // The cycle budget (`SolveParams::cycle_budget`, 0 for none): no new iteration starts once
    // hart 0's cycles since the solve began reach it, so a budgeted step ends within one
    // iteration of its budget with the residual it reached.
    let within_budget = |report: &SolveReport| {
        params.cycle_budget == 0
            || report.mvu.cycles.saturating_add(report.svu.cycles) < params.cycle_budget
    };
    while state.iter().any(|s| s.active)
        && report.iterations < params.max_iterations
        && within_budget(&report)
    {
        costs.measuring = report.iterations == 0;
        report.iterations += 1;
        let t = exec.now();
        engine.mvu(&mut costs);
        charge(&mut report.mvu, t, exec);

        let t = exec.now();
        let mut plans = [None; MAX_DIRECTIONS];
        for d in 0..directions {
            let st = &mut state[d];
            if !st.active {
                continue;
            }
            st.iterations += 1;
            let p_kp: i128 = engine.outs().iter().map(|o| o.p_kp[d]).sum();
            if p_kp <= 0 {
                return Err(SolveFailure::NotPositiveDefinite {
                    iteration: report.iterations,
                });
            }
            // α = rᵀr / pᵀKp; exponents: 2e_r and 2e_p − F.
            let alpha = ldexp(st.rr as f64 / p_kp as f64, 2 * st.r.e - 2 * st.p.e + f);
            let x = Lin::new(alpha, st.p, false, 1.0, st.x, &mut saturations);
            let (r, narrow) = r_plan(d, -alpha, st, &mut saturations);
            plans[d] = Some(PassA {
                x: Some(x),
                r,
                narrow,
            });
        }
        let serial = exec.now();
        if costs.measuring {
            costs.serial(serial.instructions.wrapping_sub(t.instructions));
        }
        pass_a(&plans, &mut costs);
        let serial = exec.now();
        let mut p_plans = [None; MAX_DIRECTIONS];
        let mut verify = [false; MAX_DIRECTIONS];
        for (d, plan) in plans.iter().enumerate() {
            let Some(plan) = plan else { continue };
            let st = &mut state[d];
            let x_or = engine.outs().iter().fold(0u32, |o, out| o | out.x_or[d]);
            check_bound(x_or, &mut saturations);
            st.x = Block {
                e: plan.x.map_or(st.x.e, |l| l.e),
                bound: bound_of(x_or),
            };
            x_exponents[d] = st.x.e;
            let (rr_old, e_old) = (st.rr, st.r.e);
            take_r(d, plan.r, st, &mut saturations);
            if st.residual_sq <= tol_sq || st.iterations >= params.max_iterations {
                st.active = false;
                // Converged on the recursive residual: check it against b − A·x below.
                verify[d] = st.residual_sq <= tol_sq && st.replacements < MAX_REPLACEMENTS;
                continue;
            }
            // β = r_newᵀr_new / rᵀr
            let beta = ldexp(st.rr as f64 / rr_old as f64, 2 * (st.r.e - e_old));
            p_plans[d] = Some(Lin::new(1.0, st.r, false, beta, st.p, &mut saturations));
        }
        if costs.measuring {
            costs.serial(exec.now().instructions.wrapping_sub(serial.instructions));
        }
        let mut verify_any = false;
        pass_b(&p_plans, &mut costs);
        let serial = exec.now();
        for (d, lin) in p_plans.iter().enumerate() {
            if let Some(lin) = lin {
                let or = engine.outs().iter().fold(0u32, |o, out| o | out.v_or[d]);
                check_bound(or, &mut saturations);
                state[d].p = Block {
                    e: lin.e,
                    bound: bound_of(or),
                };
            }
        }
        if costs.measuring {
            costs.serial(exec.now().instructions.wrapping_sub(serial.instructions));
            report.per_iteration = costs.cost;
            costs.measuring = false;
        }
        charge(&mut report.svu, t, exec);

        // Residual replacement: a direction that converged on its recursive residual gets
        // r = b − A·x recomputed (one extra MVU pass); if that is still above the tolerance —
        // the recursive residual drifts from the true one by the rounding of the updates —
        // CG restarts from it with p = r.
        for (d, v) in verify.iter().enumerate() {
            if !v {
                continue;
            }
            verify_any = true;
            state[d].replacements += 1;
            // SAFETY: no task runs; hart 0 has the vectors to itself.
            let (p, x, r) = unsafe {
                (
                    engine.p.slice_mut(0..n),
                    xs[d].as_slice(),
                    rs[d].slice_mut(0..n),
                )
            };
            for (pi, &xi) in p.iter_mut().zip(x) {
                pi[d] = xi;
            }
            r.copy_from_slice(&systems_b[d][..n]);
            state[d].r = state[d].b;
        }
        if verify_any {
            let t = exec.now();
            engine.mvu(&mut costs);
            charge(&mut report.mvu, t, exec);
            let t = exec.now();
            let mut plans = [None; MAX_DIRECTIONS];
            for (d, v) in verify.iter().enumerate() {
                if *v {
                    let st = Direction {
                        p: state[d].x,
                        ..state[d]
                    };
                    let (r, narrow) = r_plan(d, -1.0, &st, &mut saturations);
                    plans[d] = Some(PassA { x: None, r, narrow });
                }
            }
            pass_a(&plans, &mut costs);
            for (d, plan) in plans.iter().enumerate() {
                let Some(plan) = plan else { continue };
                let st = &mut state[d];
                take_r(d, plan.r, st, &mut saturations);
                if st.residual_sq > tol_sq && st.iterations < params.max_iterations {
                    st.active = true;
                    // SAFETY: no task runs; hart 0 has the vectors to itself.
                    let (p, r) = unsafe { (engine.p.slice_mut(0..n), rs[d].as_slice()) };
                    for (pi, &ri) in p.iter_mut().zip(r) {
                        pi[d] = ri;
                    }
                    st.p = st.r;
                }
            }
            charge(&mut report.svu, t, exec);
        }
    }

    drop(xs);
    drop(rs);
    report.converged = true;
    for (d, s) in systems.iter_mut().enumerate() {
        let st = &state[d];
        s.x_exponent = x_exponents[d];
        let converged = st.residual_sq <= tol_sq;
        let residual = sqrt(st.residual_sq);
        report.converged &= converged;
        report.residual = report.residual.max(residual);
        let _ = report.directions.push(DirectionReport {
            iterations: st.iterations,
            converged,
            residual,
        });
    }
    report.saturations = saturations;
    Ok(report)
}

/// Counts a vector whose maximum broke the 2^29 bound its exponent was chosen for.
fn check_bound(or: u32, saturations: &mut u32) {
    if or >= 1 << OUTPUT_BITS {
        *saturations += 1;
    }
}

fn bound_of_u64(or: u64) -> u64 {
    if or == 0 {
        0
    } else {
        or.saturating_add(1)
    }
}

/// √x for x ≥ 0 without std: Newton's method from a power-of-two first guess.
fn sqrt(x: f64) -> f64 {
    if x <= 0.0 || !x.is_finite() {
        return if x == 0.0 { 0.0 } else { x.max(0.0) };
    }
    let mut g = ldexp(1.0, floor_log2(x) / 2);
    for _ in 0..8 {
        g = 0.5 * (g + x / g);
    }
    g
}

/// Adds the counters elapsed since `since` to `total`.
fn charge(total: &mut PhaseCounters, since: PhaseCounters, clock: &impl PhaseClock) {
    let now = clock.now();
    total.cycles += now.cycles.wrapping_sub(since.cycles);
    total.instructions += now.instructions.wrapping_sub(since.instructions);
}

#[cfg(test)]
mod tests;
