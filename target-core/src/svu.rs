//! The scalar–vector unit (SVU, thesis 4.2.2): the vector updates of a CG iteration in block
//! floating point, and the scalars hart 0 plans them with.
//!
//! # Two passes per iteration
//!
//! - **Pass R** (after the MVU phase): r ← r − α·Kp, with Σr² and a bound on max |r|.
//! - **Pass XP** (after β is known): x ← x + α·p and p ← r + β·p in one sweep. The x-update
//!   needs the *old* p, which this pass reads anyway, so x costs no load of p of its own (the
//!   x-update used to run in pass R and read p there too).
//!
//! Each pass runs on every hart, each on its own equal slice of the vectors; hart 0 combines
//! the harts' integer partial results (Σ, OR) between the passes. Integers add up the same in
//! any order, so the result does not depend on the number of MVUs or on the partition.
//!
//! # The element operation, and why it cannot overflow
//!
//! Every update is z = a·u + b·y, done per element as two [`Term`]s,
//! `z_i = mulh(A, u_i << k_u) + mulh(B, y_i << k_y)` — `mulh` is the high word of the 64-bit
//! product, i.e. ⌊A·(u << k)/2^32⌋. Hart 0 folds the scalar and the exponents into the 32-bit
//! multipliers A, B; the shifts k normalise u and y so that their bound lies in [2^30, 2^31).
//! That is a shift and a `mulh` per term where the previous SVU (issue 4) also kept A in
//! [2^30, 2^31) by a variable right shift after the product; the bound below shows that this is
//! not needed:
//!
//! - The output exponent e_z is chosen so that the bound |a|·‖u‖ + |b|·‖y‖ (from the tracked
//!   maxima, formed in integers from the scalars' mantissas rounded up) is below 2^29 output
//!   units ([`BOUND_BITS`]).
//! - Then |A| = |a|·2^(e_u − k_u − e_z + 32) < 2^29 · 2^32 / 2^30 = 2^31: A fits `i32` (rounding
//!   it to an integer can reach 2^31 only by half a unit, which is clamped to `i32::MAX`).
//! - Each term is off by less than 1 unit (the floor of `mulh`, or half a unit where the term
//!   is rounded) plus |u << k|·½/2^32 < ¼ unit (A's rounding), so |z| < 2^29 + 2.5 < 2^30
//!   ([`OUTPUT_BITS`]): the MVU's products stay exact and nothing can saturate. A term too
//!   small to matter simply gets a small A: its absolute error is what counts, and that is
//!   bounded as above.
//!
//! Which terms are rounded: the α terms, α·p into x and α·Kp into r, are rounded to nearest
//! (`mul`, `mulh` and the low word's carry into the high one), because x and r accumulate them
//! over all iterations and a floor's −½-unit bias would add up (on the unit tests it cost the
//! 1e-7 accuracy). The power-of-two terms (x's and r's own, r's in p) are exact whenever the
//! exponent does not grow, and β·p is rebuilt every iteration, so these are floored.
//!
//! The maxima are measured in every pass, so the exponent follows each vector down as the
//! residual shrinks: x and p by an OR of their magnitudes (the same highest bit as the maximum),
//! r through its squares, which Σr² needs anyway (the OR of the squares' high words bounds
//! max r² within a factor 2^32, i.e. max |r| within 2^16 at worst and a factor of √2 once
//! |r| ≥ 2^16). Σr² is exact: squares below 2^60 summed in `u64` blocks of 16 into a `u128`.
//! A cheaper Σ⌊4r²/2^32⌋ was tried: it rounds a residual of many small elements to nothing near
//! the fixed-point floor, and the unit tests caught the lost accuracy.
//!
//! K·p comes from the MVU as exact `i64` row sums; pass R narrows each to 31 bits with a
//! loop-invariant funnel shift chosen from max |Kp| ([`Narrow`]).
//!
//! Saturation is nonetheless detected: a multiplier that would not fit `i32`, a vector whose
//! maximum breaks its bound, or a K·p beyond 2^62 is clamped and counted, and the host reports
//! any count as an error.

use deform_shared::protocol::MAX_DIRECTIONS;

use crate::kernel::{Lanes, Sums};

/// Mantissas produced by the SVU stay below 2^OUTPUT_BITS (the MVU's exactness needs < 2^30).
pub const OUTPUT_BITS: i32 = 30;
/// The output exponent keeps the bound on |a·u + b·y| below 2^BOUND_BITS units, leaving room
/// for the two terms' errors below 2^OUTPUT_BITS.
pub const BOUND_BITS: i32 = 29;

/// Block-floating-point vector state besides its mantissas: exponent and a bound on max |m|.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Block {
    pub e: i32,
    pub bound: u64,
}

impl Block {
    pub const ZERO: Block = Block { e: 0, bound: 0 };
}

/// A bound on max |z| from the OR of `magnitude_bits(z)` (= |z| − 1 for negative z): every
/// |z| ≤ or + 1.
pub fn bound_of(or: u32) -> u64 {
    u64::from(or) + 1
}

/// A bound on max |z| from the OR of the high words of z² over a vector: max z² < 2^(bits + 32),
/// so max |z| < 2^⌈(bits + 32)/2⌉ (2^16 if every high word was 0).
pub fn bound_of_squares(or: u32) -> u64 {
    let bits = 32 - or.leading_zeros();
    1u64 << (bits + 32).div_ceil(2)
}

/// The bound for a K·p maximum from the OR of its magnitudes.
pub fn bound_of_u64(or: u64) -> u64 {
    if or == 0 {
        0
    } else {
        or.saturating_add(1)
    }
}

#[inline(always)]
pub fn magnitude_bits(z: i32) -> u32 {
    (z ^ (z >> 31)) as u32
}

/// z², exact (below 2^60 for |z| < 2^30): a `mul` and a `mulh`.
#[inline(always)]
fn square(z: i32) -> u64 {
    (z as i64 * z as i64) as u64
}

/// One term of an SVU update: ⌊mult·(u << shift)/2^32⌋, the high word of one `mul`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Term {
    pub mult: i32,
    pub shift: u32,
}

impl Term {
    #[inline(always)]
    pub fn apply(self, u: i32) -> i32 {
        mulh(self.mult, u.wrapping_shl(self.shift))
    }
    /// Like [`Term::apply`], rounded to nearest: ⌊(mult·(u << shift) + 2^31)/2^32⌋.
    #[inline(always)]
    pub fn apply_rounded(self, u: i32) -> i32 {
        mulh_rounded(self.mult, u.wrapping_shl(self.shift))
    }
}

#[inline(always)]
fn mulh(a: i32, b: i32) -> i32 {
    ((a as i64 * b as i64) >> 32) as i32
}

/// The high word of a·b rounded to nearest (ties up): `mul`, `mulh`, and the low word's bit 31
/// added.
#[inline(always)]
fn mulh_rounded(a: i32, b: i32) -> i32 {
    ((a as i64 * b as i64 + (1 << 31)) >> 32) as i32
}

/// z = a·u + b·y as two [`Term`]s, with z's exponent.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Lin {
    pub u: Term,
    pub y: Term,
    pub e: i32,
}

/// The left shift that brings a vector with max |m| ≤ `bound` into [2^30, 2^31).
pub fn normalising_shift(bound: u64) -> u32 {
    match u32::try_from(bound) {
        Ok(0) => 0,
        // 30 − ⌊log2 bound⌋ = leading zeros − 1, with a 32-bit count (rv32 has no 64-bit one).
        Ok(b) => b.leading_zeros().saturating_sub(1),
        Err(_) => 0,
    }
}

/// A finite `f64` as sign, 53-bit mantissa and exponent (value = ±m·2^e); 0 and subnormals
/// (which no CG scalar comes near) give m = 0.
fn decompose(c: f64) -> (bool, u64, i32) {
    let bits = c.to_bits();
    let biased = ((bits >> 52) & 0x7FF) as i32;
    if biased == 0 || biased == 0x7FF {
        return (false, 0, 0);
    }
    // The sign from its bit: an f64 comparison is a soft-float call on rv32.
    (
        bits >> 63 == 1,
        (bits & ((1 << 52) - 1)) | (1 << 52),
        biased - 1075,
    )
}

/// An upper bound on |c|·bound·2^e as (mantissa, exponent): c's mantissa cut to 31 bits and
/// rounded up, times the bound (below 2^32), is exact in `u64` and below 2^63, so two such
/// terms add up in `u64` too.
fn magnitude_bound(c: (bool, u64, i32), block: Block) -> (u64, i32) {
    let (_, m, e) = c;
    if m == 0 || block.bound == 0 {
        return (0, 0);
    }
    let top = ((m >> 22) + 1) as u32;
    let bound = block.bound.min(u64::from(u32::MAX)) as u32;
    (u64::from(top) * u64::from(bound), e + 22 + block.e)
}

impl Lin {
    /// Plans z = a·u + b·y for blocks u and y. `u_normalised`: u's elements are already
    /// shifted into range (the narrowed K·p) and get no shift of their own. Counts a multiplier
    /// that does not fit in `saturations`.
    ///
    /// Integer arithmetic throughout (hart 0 has no FPU, and soft-float operations cost about
    /// a hundred instructions each): the bound |a|·‖u‖ + |b|·‖y‖ is formed from the scalars'
    /// mantissas rounded up, so it is an upper bound, and z's exponent is the smallest that
    /// keeps it below 2^[`BOUND_BITS`] units.
    pub fn new(a: f64, u: Block, u_normalised: bool, b: f64, y: Block, sat: &mut u32) -> Lin {
        let (a, b) = (decompose(a), decompose(b));
        let (mu, eu) = magnitude_bound(a, u);
        let (my, ey) = magnitude_bound(b, y);
        // Align the two terms to the larger exponent, rounding the smaller one up.
        let (hi, e_hi, lo, e_lo) = if (my == 0) || (mu != 0 && eu >= ey) {
            (mu, eu, my, ey)
        } else {
            (my, ey, mu, eu)
        };
        if hi == 0 {
            return Lin::default();
        }
        let gap = (e_hi - e_lo) as u32;
        let lo = if lo == 0 {
            0
        } else if gap >= 64 {
            1
        } else {
            (lo >> gap) + 1
        };
        let sum = hi + lo;
        let bits = match (sum >> 32) as u32 {
            0 => 32 - (sum as u32).leading_zeros() as i32,
            top => 64 - top.leading_zeros() as i32,
        };
        // floor(log2(bound)) = bits − 1 + e_hi; e = that + 1 − BOUND_BITS.
        let e = bits + e_hi - BOUND_BITS;
        let ku = if u_normalised {
            0
        } else {
            normalising_shift(u.bound)
        };
        Lin {
            u: term(a, u, ku, e, sat),
            y: term(b, y, normalising_shift(y.bound), e, sat),
            e,
        }
    }
}

/// The [`Term`] for c·block into output exponent `e`, the block's elements shifted left by
/// `shift`: mult = c·2^(e_block − shift − e + 32), rounded to nearest (ties away from 0).
fn term(c: (bool, u64, i32), block: Block, shift: u32, e: i32, sat: &mut u32) -> Term {
    let (neg, m, ec) = c;
    if block.bound == 0 || m == 0 {
        return Term::default();
    }
    let sh = ec + block.e - shift as i32 - e + 32;
    let magnitude = if sh >= 0 {
        if sh >= 11 {
            u64::MAX
        } else {
            m << sh
        }
    } else if sh <= -64 {
        0
    } else {
        let down = (-sh) as u32;
        (m >> down) + ((m >> (down - 1)) & 1)
    };
    // Up to half a unit over 2^31 − 1 is the rounding of a multiplier just below 2^31;
    // anything more breaks the bound.
    if magnitude > 1 << 31 {
        *sat += 1;
    }
    let magnitude = magnitude.min(i32::MAX as u64) as i32;
    Term {
        mult: if neg { -magnitude } else { magnitude },
        shift,
    }
}

/// How pass R reads K·p: narrowed from `i64` to 31 bits by a loop-invariant shift.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Narrow {
    /// max |Kp| < 2^31: `(kp as i32) << k`.
    Left(u32),
    /// `kp >> s` for s in 1..=31, as a funnel shift of the two halves.
    Right(u32),
}

impl Default for Narrow {
    fn default() -> Self {
        Narrow::Left(0)
    }
}

impl Narrow {
    /// The narrowing for max |Kp| ≤ `max`, and the narrowed block's exponent offset and bound.
    /// Counts max ≥ 2^62 (which the MVU's bounds rule out) as a saturation.
    pub fn new(max: u64, sat: &mut u32) -> (Narrow, i32, u64) {
        if max >= 1 << 62 {
            *sat += 1;
        }
        let bits = 64 - max.leading_zeros();
        if bits <= 31 {
            let k = normalising_shift(max);
            (Narrow::Left(k), -(k as i32), max << k)
        } else {
            let s = (bits - 31).min(31);
            (Narrow::Right(s), s as i32, (max >> s) + 1)
        }
    }
}

/// Pass R's plan for one direction: r ← kp_term(narrow(Kp)) + r_term(r).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PassR {
    pub lin: Lin,
    pub narrow: Narrow,
}

/// Pass XP's plan for one direction: x ← x + α·p (if `x`), p ← r + β·p (if `p`). Both terms
/// on p use the same shift (the normalising shift of p's bound), so the shifted p is shared;
/// [`PassXP::new`] makes that so.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PassXP {
    /// u = p, y = x.
    pub x: Option<Lin>,
    /// u = r, y = p.
    pub p: Option<Lin>,
}

impl PassXP {
    pub const NONE: PassXP = PassXP { x: None, p: None };

    /// The plan for an x-update and a p-update; where one of p's terms is zero (mult 0), its
    /// shift is set to the other's, which changes nothing but lets the loop shift p once.
    pub fn new(x: Option<Lin>, p: Option<Lin>) -> PassXP {
        let (mut x, mut p) = (x, p);
        if let (Some(xl), Some(pl)) = (x.as_mut(), p.as_mut()) {
            if xl.u.mult == 0 {
                xl.u.shift = pl.y.shift;
            } else if pl.y.mult == 0 {
                pl.y.shift = xl.u.shift;
            }
        }
        PassXP { x, p }
    }
}

/// What each hart reports from a phase; hart 0 combines them between phases.
#[derive(Debug, Clone, Copy, Default)]
pub struct HartOut {
    /// pᵀKp over this hart's share of the rows (MVU phase, second step), exact.
    pub p_kp: [i128; MAX_DIRECTIONS],
    /// OR of |Kp| over this hart's share of the rows (MVU phase, second step).
    pub kp_or: [u64; MAX_DIRECTIONS],
    /// Σr² over this hart's slice (pass R), exact.
    pub rr: [u128; MAX_DIRECTIONS],
    /// OR of the high words of r² over this hart's slice (pass R): bounds max |r|.
    pub r_or: [u32; MAX_DIRECTIONS],
    /// OR of the magnitudes of the new x (pass XP).
    pub x_or: [u32; MAX_DIRECTIONS],
    /// OR of the magnitudes of the new p (pass XP).
    pub p_or: [u32; MAX_DIRECTIONS],
    /// Set-up: Σb² (in `rr`), the OR of |b| and the OR of x's raw bits (nonzero if any x is).
    pub b_or: [u32; MAX_DIRECTIONS],
    pub x_any: [u32; MAX_DIRECTIONS],
}

/// Pass R on one slice of direction `d`: r ← lin.u(narrow(Kp)) + lin.y(r); returns
/// (Σr², exact, and the OR of the squares' high words).
pub fn pass_r(r: &mut [i32], kp: &[Sums], d: usize, plan: PassR) -> (u128, u32) {
    #[cfg(target_arch = "riscv32")]
    if let Some(out) = riscv::pass_r(r, kp, d, plan) {
        return out;
    }
    portable_pass_r(r, kp, d, plan)
}

/// The specification of pass R (the assembly in `riscv` must equal it bit for bit). The K·p
/// term is rounded to nearest, r's own term (a power of two) is exact or floored.
pub fn portable_pass_r(r: &mut [i32], kp: &[Sums], d: usize, plan: PassR) -> (u128, u32) {
    // One loop per narrowing, so that the choice is not made per element.
    match plan.narrow {
        Narrow::Left(k) => r_loop(r, kp, d, plan.lin, |v| (v as i32).wrapping_shl(k)),
        Narrow::Right(s) => r_loop(r, kp, d, plan.lin, |v| {
            ((v as u32).wrapping_shr(s) | ((v >> 32) as u32).wrapping_shl(32 - s)) as i32
        }),
    }
}

/// Pass R's loop for one narrowing of K·p. The K·p term has no shift of its own: the narrowing
/// normalises it (`Lin::new` with `u_normalised`).
#[inline(always)]
fn r_loop(
    r: &mut [i32],
    kp: &[Sums],
    d: usize,
    lin: Lin,
    narrow: impl Fn(i64) -> i32,
) -> (u128, u32) {
    let (mult, y) = (lin.u.mult, lin.y);
    let mut sum = 0u128;
    let mut or = 0u32;
    for (rc, kc) in r.chunks_mut(SQUARE_BLOCK).zip(kp.chunks(SQUARE_BLOCK)) {
        let mut block = 0u64;
        for (ri, ki) in rc.iter_mut().zip(kc) {
            let z = mulh_rounded(mult, narrow(ki[d])).wrapping_add(y.apply(*ri));
            *ri = z;
            let sq = square(z);
            block = block.wrapping_add(sq);
            or |= (sq >> 32) as u32;
        }
        sum += u128::from(block);
    }
    (sum, or)
}

/// Squares (each below 2^60) summed in a `u64` before they go into the `u128` total.
const SQUARE_BLOCK: usize = 16;

/// Pass XP on one slice of direction `d`; returns the ORs of |x| and |p| (0 where not updated).
pub fn pass_xp(x: &mut [i32], p: &mut [Lanes], r: &[i32], d: usize, plan: PassXP) -> (u32, u32) {
    #[cfg(target_arch = "riscv32")]
    if let Some(out) = riscv::pass_xp(x, p, r, d, plan) {
        return out;
    }
    portable_pass_xp(x, p, r, d, plan)
}

/// The specification of pass XP.
pub fn portable_pass_xp(
    x: &mut [i32],
    p: &mut [Lanes],
    r: &[i32],
    d: usize,
    plan: PassXP,
) -> (u32, u32) {
    let (mut x_or, mut p_or) = (0u32, 0u32);
    match plan {
        PassXP {
            x: Some(xl),
            p: Some(pl),
        } => {
            // p shifted once for both its terms (see `PassXP::new`).
            debug_assert!(xl.u.shift == pl.y.shift || xl.u.mult == 0 || pl.y.mult == 0);
            let shift = xl.u.shift;
            for ((xi, pi), &ri) in x.iter_mut().zip(p.iter_mut()).zip(r) {
                let old = pi[d].wrapping_shl(shift);
                let zx = mulh_rounded(xl.u.mult, old).wrapping_add(xl.y.apply(*xi));
                *xi = zx;
                x_or |= magnitude_bits(zx);
                let zp = pl.u.apply(ri).wrapping_add(mulh(pl.y.mult, old));
                pi[d] = zp;
                p_or |= magnitude_bits(zp);
            }
        }
        PassXP {
            x: Some(xl),
            p: None,
        } => {
            for (xi, pi) in x.iter_mut().zip(p.iter()) {
                let zx = xl.u.apply_rounded(pi[d]).wrapping_add(xl.y.apply(*xi));
                *xi = zx;
                x_or |= magnitude_bits(zx);
            }
        }
        PassXP {
            x: None,
            p: Some(pl),
        } => {
            for (pi, &ri) in p.iter_mut().zip(r) {
                let zp = pl.u.apply(ri).wrapping_add(pl.y.apply(pi[d]));
                pi[d] = zp;
                p_or |= magnitude_bits(zp);
            }
        }
        PassXP { x: None, p: None } => {}
    }
    (x_or, p_or)
}

/// Σ z² over a slice, exact, summed as pass R sums r² (for ‖b‖², once per solve).
pub fn sum_squares(v: &[i32]) -> u128 {
    v.chunks(SQUARE_BLOCK)
        .map(|c| u128::from(c.iter().map(|&z| square(z)).fold(0u64, u64::wrapping_add)))
        .sum()
}

/// Counts a vector whose maximum broke the 2^30 bound its exponent was chosen for.
pub fn check_bound(bound: u64, sat: &mut u32) {
    if bound > 1 << OUTPUT_BITS {
        *sat += 1;
    }
}

#[cfg(target_arch = "riscv32")]
mod riscv {
    use super::*;

    /// The assembly pass R, where there is one; `None` leaves it to the portable loop.
    pub fn pass_r(_r: &mut [i32], _kp: &[Sums], _d: usize, _plan: PassR) -> Option<(u128, u32)> {
        None
    }

    /// The assembly pass XP, where there is one; `None` leaves it to the portable loop.
    pub fn pass_xp(
        _x: &mut [i32],
        _p: &mut [Lanes],
        _r: &[i32],
        _d: usize,
        _plan: PassXP,
    ) -> Option<(u32, u32)> {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_square_bound_holds() {
        for z in [
            0i32,
            1,
            -1,
            1 << 15,
            40_000,
            -(1 << 20),
            (1 << 29) + 2,
            -(1 << 29) - 2,
        ] {
            let sq = square(z);
            assert_eq!(sq as i64, z as i64 * z as i64);
            assert!(
                u64::from(z.unsigned_abs()) < bound_of_squares((sq >> 32) as u32),
                "{z}"
            );
        }
    }

    #[test]
    fn a_term_equals_the_high_word_of_its_product() {
        let t = Term {
            mult: -(3 << 29),
            shift: 2,
        };
        let u = 123_456_789 >> 2;
        assert_eq!(
            t.apply(u),
            ((-(3i64 << 29) * ((u << 2) as i64)) >> 32) as i32
        );
    }

    #[test]
    fn no_update_can_leave_its_bound() {
        // The largest inputs the bounds allow, with coefficients that put the sum right at
        // the bound: |z| stays below 2^30.
        let u = Block {
            e: -3,
            bound: (1 << 30) - 1,
        };
        let y = Block {
            e: 5,
            bound: (1 << 29) + 7,
        };
        let mut sat = 0;
        for (a, b) in [(1.0, 1.0), (-0.37, 2.9e-3), (1e-12, 1.0), (7.5, -1e-9)] {
            let lin = Lin::new(a, u, false, b, y, &mut sat);
            for (ui, yi) in [(1 << 30) - 1, -(1 << 30) + 1]
                .into_iter()
                .flat_map(|ui| [((1 << 29) + 7, ui), (-(1 << 29) - 7, ui)])
                .map(|(yi, ui)| (ui, yi))
            {
                let z = lin.u.apply(ui) as i64 + lin.y.apply(yi) as i64;
                assert!(z.abs() < 1 << OUTPUT_BITS, "{a} {b}: {z}");
            }
        }
        assert_eq!(sat, 0);
    }
}
