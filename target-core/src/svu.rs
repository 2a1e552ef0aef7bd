//! The scalar–vector unit (SVU, thesis 4.2.2): the vector updates of a CG iteration in block
//! floating point, and the scalars hart 0 plans them with. This module is the specification:
//! the firmware's assembly passes (module `riscv`) equal it bit for bit, and a gateware SVU is
//! to be built bit-exact to it, so every step below is integer arithmetic a circuit does
//! directly (adds, shifts, 32-bit multiplies, one 64-by-32-bit division per scalar quotient).
//!
//! # Two passes per iteration
//!
//! - **Pass R** (after the MVU phase): r ← r − α·Kp, with Σr² and a bound on max |r|.
//! - **Pass XP** (after β is known): x ← x + α·p and p ← r + β·p in one sweep. The x-update
//!   needs the *old* p, which this pass reads anyway, so x costs no load of p of its own.
//!
//! Each pass runs on every hart, each on its own slice of the vectors ([`crate::exec::share`]);
//! hart 0 combines the harts' integer partial results (Σ, OR) between the passes. Integers add
//! up the same in any order, so the result does not depend on the number of MVUs or on the
//! partition.
//!
//! # The element operation, and why it cannot overflow
//!
//! Every update is z = c·u + y (or z = c·u): a scaled term and a term of coefficient one, the
//! vector's own (r in pass R, x in x's update) or r in p's update. Per element:
//!
//! - the scaled term ([`Term`]): `mulh(A, u_i << k)`, the high word of a 32-bit product, i.e.
//!   ⌊A·(u << k)/2^32⌋, or rounded to nearest, ⌊(A·(u << k) + 2^31)/2^32⌋ (`mul`, `mulh`, the
//!   low word's bit 31 added). Hart 0 folds c and the exponents into the 32-bit multiplier A;
//!   the shift k normalises u so that its bound lies in [2^30, 2^31).
//! - the term of coefficient one ([`Shift`]): y·2^(e_y − e_z), floored: `y << s` (exact) or
//!   `y >> s` (arithmetic). It needs no multiply.
//!
//! Bounds:
//!
//! - The output exponent e_z is chosen so that the bound |c|·‖u‖ + ‖y‖ (from the tracked
//!   maxima, formed in integers from c's mantissa rounded up) is below 2^29 output units
//!   ([`BOUND_BITS`]).
//! - Then |A| = |c|·2^(e_u − k − e_z + 32) < 2^29 · 2^32 / 2^30 = 2^31: A fits `i32` (rounding
//!   it to an integer can reach 2^31 only by half a unit, which is clamped to `i32::MAX`), and
//!   |y·2^(e_y − e_z)| < 2^29, so a left shift is exact.
//! - The scaled term is off by less than 1 unit (the floor of `mulh`, or half a unit where it
//!   is rounded) plus |u << k|·½/2^32 < ¼ unit (A's rounding), the shifted term by less than
//!   one unit, so |z| < 2^29 + 2.5 < 2^30 ([`OUTPUT_BITS`]): the MVU's products stay exact and
//!   nothing can saturate. A term too small to matter simply gets a small A: its absolute
//!   error is what counts, and that is bounded as above.
//!
//! Which terms are rounded: the α terms, α·p into x and α·Kp into r, are rounded to nearest,
//! because x and r accumulate them over all iterations and a floor's −½-unit bias would add up
//! (on the unit tests it cost the 1e-7 accuracy). The terms of coefficient one are exact
//! whenever the exponent does not grow, and β·p is rebuilt every iteration, so these are
//! floored.
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
//! # Scalars, in integers
//!
//! Hart 0 has no FPU, and a soft-float operation costs 30–250 instructions on rv32, so the
//! planning is integer too ([`Scalar`]): a scalar is ±m·2^e with a 32-bit mantissa
//! m ∈ [2^31, 2^32).
//!
//! - Σr² (`u128`) and pᵀKp (`i128`) enter truncated to their top 32 bits
//!   ([`Scalar::of_u128`]).
//! - α = Σr²/pᵀKp and β = Σr²_new/Σr²_old are quotients of such scalars,
//!   q = ⌊m_a·2^k/m_b⌋ with k = 32 or 31 so that q ∈ [2^31, 2^32) ([`Scalar::quotient`]): one
//!   64-by-32-bit unsigned division ([`div_64_32`]), two 32-bit hardware divisions on rv32, a
//!   32-step restoring divider in gateware.
//! - A multiplier A rounds c's mantissa to nearest at the term's scale ([`Lin::new`]).
//! - Convergence, ‖r‖²/‖b‖² ≤ tol², is decided on the exact Σr² against a threshold formed
//!   once per solve ([`Threshold`]).
//!
//! Saturation is nonetheless detected: a multiplier that would not fit `i32`, a vector whose
//! maximum breaks its bound, or a K·p beyond 2^62 is clamped and counted, and the host reports
//! any count as an error.

use deform_shared::protocol::MAX_DIRECTIONS;
use deform_shared::qformat::ldexp;

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
    let bits = bit_length(or) as u32;
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

/// The scaled term of an SVU update: ⌊mult·(u << shift)/2^32⌋, the high word of one `mul`
/// (or rounded to nearest, see [`Term::apply_rounded`]).
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

/// The term of coefficient one: y·2^s floored, as `(y << left) >> right` (arithmetic) with one
/// of the two shifts zero. Both are at most 31: a left shift beyond the bound's 29 bits only
/// meets y = 0, and an arithmetic right shift by 31 floors every `i32` to 0 or −1 as any larger
/// one would.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Shift {
    pub left: u32,
    pub right: u32,
}

impl Shift {
    /// The shift for s = e_y − e_z.
    pub fn by(s: i32) -> Shift {
        Shift {
            left: s.clamp(0, 31) as u32,
            right: (-s).clamp(0, 31) as u32,
        }
    }

    #[inline(always)]
    pub fn apply(self, y: i32) -> i32 {
        y.wrapping_shl(self.left) >> self.right
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

/// z = c·u + y (`own`: y's [`Shift`], or `None` for z = c·u), with z's exponent.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Lin {
    pub term: Term,
    pub own: Option<Shift>,
    pub e: i32,
}

/// The left shift that brings a vector with max |m| ≤ `bound` into [2^30, 2^31).
pub fn normalising_shift(bound: u64) -> u32 {
    match u32::try_from(bound) {
        Ok(0) => 0,
        // 30 − ⌊log2 bound⌋ = 31 − bits.
        Ok(b) => 31u32.saturating_sub(bit_length(b) as u32),
        Err(_) => 0,
    }
}

/// Number of bits of v (0 for 0): at most two comparisons pick v's highest nonzero byte, and a
/// 256-entry table ([`BYTE_BITS`]) gives that byte's bit count. rv32imac has no
/// count-leading-zeros instruction; the compiler's generic sequence (a population count of the
/// smeared bits) takes about 35 instructions, a binary search over the five halvings 15–20, and
/// this about 8. Hart 0's planning needs it a dozen times per iteration and direction.
pub fn bit_length(v: u32) -> i32 {
    let shift = if v >> 16 != 0 {
        if v >> 24 != 0 {
            24
        } else {
            16
        }
    } else if v >> 8 != 0 {
        8
    } else {
        0
    };
    // v >> shift < 256 for the shift chosen: the cast drops nothing, and there is no bounds check.
    shift + i32::from(BYTE_BITS[usize::from((v >> shift) as u8)])
}

/// The number of bits of every byte value, for [`bit_length`].
const BYTE_BITS: [u8; 256] = {
    let mut table = [0u8; 256];
    let mut i = 1;
    while i < 256 {
        table[i] = table[i / 2] + 1;
        i += 1;
    }
    table
};

/// ⌊(hi·2^32 + lo)/v⌋ for hi < v and v ≥ 2^31 (a normalised divisor), which fits `u32`: long
/// division in two 16-bit digits, each a 32-by-16-bit hardware division corrected at most
/// twice (Knuth's algorithm D; H. S. Warren, *Hacker's Delight*, `divlu`). Written out because
/// rv32 has only 32-bit divisions and compiler-rt's 64-bit one costs several times more; a
/// circuit computes the same quotient with a restoring divider.
pub fn div_64_32(hi: u32, lo: u32, v: u32) -> u32 {
    debug_assert!(hi < v && v >= 1 << 31);
    const B: u32 = 1 << 16;
    let (vn1, vn0) = (v >> 16, v & 0xFFFF);
    let (un1, un0) = (lo >> 16, lo & 0xFFFF);
    // First digit: q1 = ⌊(hi·2^16 + un1)/v⌋, estimated from hi/vn1 (at most 2 too large).
    let mut q1 = hi / vn1;
    let mut rhat = hi - q1 * vn1;
    while q1 >= B || q1 * vn0 > (rhat << 16) + un1 {
        q1 -= 1;
        rhat += vn1;
        if rhat >= B {
            break;
        }
    }
    let un21 = (hi << 16)
        .wrapping_add(un1)
        .wrapping_sub(q1.wrapping_mul(v));
    let mut q0 = un21 / vn1;
    rhat = un21 - q0 * vn1;
    while q0 >= B || q0 * vn0 > (rhat << 16) + un0 {
        q0 -= 1;
        rhat += vn1;
        if rhat >= B {
            break;
        }
    }
    (q1 << 16) | q0
}

/// A scalar of hart 0's planning: ±m·2^e with m = 0 (the scalar 0) or 2^31 ≤ m < 2^32.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Scalar {
    pub neg: bool,
    pub m: u32,
    pub e: i32,
}

impl Scalar {
    pub const ZERO: Scalar = Scalar {
        neg: false,
        m: 0,
        e: 0,
    };
    pub const ONE: Scalar = Scalar {
        neg: false,
        m: 1 << 31,
        e: -31,
    };

    /// v's top 32 bits (truncated) and their exponent.
    pub fn of_u128(v: u128) -> Scalar {
        // Word by word: rv32 has no 128-bit shifts, and one 32-bit shift pair suffices.
        let words = [
            v as u32,
            (v >> 32) as u32,
            (v >> 64) as u32,
            (v >> 96) as u32,
        ];
        let Some(top) = (0..4).rev().find(|&i| words[i] != 0) else {
            return Scalar::ZERO;
        };
        let lz = (32 - bit_length(words[top])) as u32;
        let below = if top == 0 { 0 } else { words[top - 1] };
        let m = if lz == 0 {
            words[top]
        } else {
            (words[top] << lz) | (below >> (32 - lz))
        };
        Scalar {
            neg: false,
            m,
            e: 32 * top as i32 - lz as i32,
        }
    }

    /// |v|'s top 32 bits and v's sign.
    pub fn of_i128(v: i128) -> Scalar {
        Scalar {
            neg: v < 0,
            ..Scalar::of_u128(v.unsigned_abs())
        }
    }

    /// a/b: the mantissas' quotient floored to 32 bits, ⌊m_a·2^k/m_b⌋ with k = 32 if m_a < m_b
    /// and 31 otherwise, so that it lies in [2^31, 2^32). A zero `b` gives zero (callers
    /// refuse it first).
    #[inline(always)]
    pub fn quotient(a: Scalar, b: Scalar) -> Scalar {
        if a.m == 0 || b.m == 0 {
            return Scalar::ZERO;
        }
        let (m, k) = if a.m < b.m {
            (div_64_32(a.m, 0, b.m), 32)
        } else {
            (div_64_32(a.m >> 1, a.m << 31, b.m), 31)
        };
        Scalar {
            neg: a.neg != b.neg,
            m,
            e: a.e - b.e - k,
        }
    }

    /// The scalar times 2^k.
    pub fn scale2(self, k: i32) -> Scalar {
        Scalar {
            e: self.e + k,
            ..self
        }
    }

    pub fn negate(self) -> Scalar {
        Scalar {
            neg: !self.neg && self.m != 0,
            ..self
        }
    }

    /// The value, for reports and tests.
    pub fn to_f64(self) -> f64 {
        let v = ldexp(f64::from(self.m), self.e);
        if self.neg {
            -v
        } else {
            v
        }
    }
}

/// An upper bound on |c|·bound·2^e as (mantissa, exponent): the high word of c's mantissa
/// times the bound (clamped to 32 bits), plus one. One `mulhu`; below 2^32.
pub fn magnitude_bound(c: Scalar, block: Block) -> (u32, i32) {
    if c.m == 0 || block.bound == 0 {
        return (0, 0);
    }
    let bound = block.bound.min(u64::from(u32::MAX)) as u32;
    let high = ((u64::from(c.m) * u64::from(bound)) >> 32) as u32;
    (high + 1, c.e + block.e + 32)
}

impl Lin {
    /// Plans z = c·u + y for blocks u and y (`own`: y's block, or `None` for z = c·u).
    /// `u_normalised`: u's elements are already shifted into range (the narrowed K·p) and get
    /// no shift of their own. Counts a multiplier that does not fit in `saturations`.
    ///
    /// The bound |c|·‖u‖ + ‖y‖ is formed from 32-bit parts rounded up, so it is an upper
    /// bound, and z's exponent is the smallest that keeps it below 2^[`BOUND_BITS`] units.
    #[inline(always)]
    pub fn new(c: Scalar, u: Block, u_normalised: bool, own: Option<Block>, sat: &mut u32) -> Lin {
        let ku = if u_normalised {
            0
        } else {
            normalising_shift(u.bound)
        };
        let (mu, eu) = magnitude_bound(c, u);
        let (my, ey) = match own {
            Some(y) if y.bound != 0 => (y.bound.min(u64::from(u32::MAX)) as u32, y.e),
            _ => (0, 0),
        };
        // Align the two terms to the larger exponent, rounding the smaller one up.
        let (hi, e_hi, lo, e_lo) = if (my == 0) || (mu != 0 && eu >= ey) {
            (mu, eu, my, ey)
        } else {
            (my, ey, mu, eu)
        };
        if hi == 0 {
            return Lin {
                term: Term { mult: 0, shift: ku },
                own: own.map(|_| Shift::default()),
                e: 0,
            };
        }
        let gap = (e_hi - e_lo) as u32;
        let lo = match (lo, gap) {
            (0, _) => 0,
            (_, 32..) => 1,
            _ => (lo >> gap) + 1,
        };
        let (sum, carry) = hi.overflowing_add(lo);
        let bits = if carry { 33 } else { bit_length(sum) };
        // floor(log2(bound)) = bits − 1 + e_hi; e = that + 1 − BOUND_BITS.
        let e = bits + e_hi - BOUND_BITS;
        Lin {
            term: term(c, u, ku, e, sat),
            own: own.map(|y| Shift::by(y.e - e)),
            e,
        }
    }
}

/// The [`Term`] for c·block into output exponent `e`, the block's elements shifted left by
/// `shift`: mult = c·2^(e_block − shift − e + 32), rounded to nearest (ties away from 0).
pub fn term(c: Scalar, block: Block, shift: u32, e: i32, sat: &mut u32) -> Term {
    if block.bound == 0 || c.m == 0 {
        return Term { mult: 0, shift };
    }
    let sh = c.e + block.e - shift as i32 - e + 32;
    let magnitude = match sh {
        0 => u64::from(c.m),
        1.. => u64::MAX,
        -32 => 1,
        ..=-33 => 0,
        _ => {
            let down = (-sh) as u32;
            u64::from((c.m >> down) + ((c.m >> (down - 1)) & 1))
        }
    };
    // Up to half a unit over 2^31 − 1 is the rounding of a multiplier just below 2^31;
    // anything more breaks the bound.
    if magnitude > 1 << 31 {
        *sat += 1;
    }
    let magnitude = magnitude.min(i32::MAX as u64) as i32;
    Term {
        mult: if c.neg { -magnitude } else { magnitude },
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
    #[inline(always)]
    pub fn new(max: u64, sat: &mut u32) -> (Narrow, i32, u64) {
        if max >= 1 << 62 {
            *sat += 1;
        }
        let bits = match (max >> 32) as u32 {
            0 => bit_length(max as u32),
            top => 32 + bit_length(top),
        } as u32;
        if bits <= 31 {
            let k = normalising_shift(max);
            (Narrow::Left(k), -(k as i32), max << k)
        } else {
            let s = (bits - 31).min(31);
            (Narrow::Right(s), s as i32, (max >> s) + 1)
        }
    }

    /// `v` narrowed.
    #[inline(always)]
    pub fn apply(self, v: i64) -> i32 {
        match self {
            Narrow::Left(k) => (v as i32).wrapping_shl(k),
            Narrow::Right(s) => {
                ((v as u32).wrapping_shr(s) | ((v >> 32) as u32).wrapping_shl(32 - s)) as i32
            }
        }
    }
}

/// Pass R's plan for one direction: r ← lin.term(narrow(Kp)) + lin.own(r).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PassR {
    pub lin: Lin,
    pub narrow: Narrow,
}

/// Pass XP's plan for one direction: x ← α·p + x (if `x`), p ← β·p + r (if `p`). Both scaled
/// terms are on the old p with the same shift (the normalising shift of p's bound, which both
/// plans derive from p's block), so the shifted p is shared.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PassXP {
    /// term on p, own x.
    pub x: Option<Lin>,
    /// term on p, own r.
    pub p: Option<Lin>,
}

impl PassXP {
    pub const NONE: PassXP = PassXP { x: None, p: None };
}

/// Threshold of the convergence test ‖r‖²/‖b‖² ≤ tol², formed once per solve from tol² and
/// Σb²: t = m·2^e ≤ tol²·Σb²·2^(2·e_b), both factors' mantissas and their product truncated
/// (rounded down). The test compares Σr² rounded *up* ([`Threshold::holds`]), so it never
/// accepts a residual above the tolerance, and costs a few integer instructions per
/// iteration.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Threshold {
    /// m = 0 (nothing but a zero residual passes) or 2^31 ≤ m < 2^32.
    pub m: u32,
    pub e: i32,
}

impl Threshold {
    /// The threshold for tolerance² `tol_sq` of a right-hand side with Σb² = `bb` (mantissa
    /// units) and exponent `e_b`.
    pub fn new(tol_sq: f64, bb: u128, e_b: i32) -> Threshold {
        let tol = tol_sq_scalar(tol_sq);
        let b = Scalar::of_u128(bb);
        if tol.m == 0 || b.m == 0 {
            return Threshold::default();
        }
        // Both mantissas have their top bit set, so the product has bit 62 or 63 set.
        let product = u64::from(tol.m) * u64::from(b.m);
        let top = (product >> 63) as u32;
        Threshold {
            m: (product >> (31 + top)) as u32,
            e: tol.e + b.e + 2 * e_b + 31 + top as i32,
        }
    }

    /// Σr² (as its truncated [`Scalar`] `rr`, of a residual with exponent `e_r`) rounded up is
    /// within the threshold.
    pub fn holds(self, rr: Scalar, e_r: i32) -> bool {
        if rr.m == 0 {
            return true;
        }
        if self.m == 0 {
            return false;
        }
        // (m + 1)·2^e bounds Σr² from above; keep it normalised.
        let (m, e) = match rr.m.checked_add(1) {
            Some(m) => (m, rr.e + 2 * e_r),
            None => (1 << 31, rr.e + 2 * e_r + 1),
        };
        e < self.e || (e == self.e && m <= self.m)
    }
}

/// tol² (non-negative, finite) as a [`Scalar`], its mantissa cut to 32 bits (rounded down).
fn tol_sq_scalar(tol_sq: f64) -> Scalar {
    if tol_sq.is_nan() || tol_sq <= 0.0 {
        return Scalar::ZERO;
    }
    Scalar::of_f64(tol_sq)
}

impl Scalar {
    /// v's sign and the top 32 bits of its magnitude (truncated); 0 and subnormals give zero,
    /// infinities the largest scalar. Bit operations only (no soft-float call).
    pub fn of_f64(v: f64) -> Scalar {
        let bits = v.to_bits();
        let biased = ((bits >> 52) & 0x7FF) as i32;
        let neg = bits >> 63 == 1;
        match biased {
            0 => Scalar::ZERO,
            0x7FF => Scalar {
                neg,
                m: u32::MAX,
                e: 1024,
            },
            _ => {
                let m53 = (bits & ((1 << 52) - 1)) | (1 << 52);
                Scalar {
                    neg,
                    m: (m53 >> 21) as u32,
                    e: biased - 1075 + 21,
                }
            }
        }
    }
}

/// The results of a phase: one hart's, or their totals, which the harts add up in the phase
/// (`cg::totals`) and hart 0 reads between phases.
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

/// Pass R on one slice of direction `d`: r ← lin.term(narrow(Kp)) + lin.own(r); returns
/// (Σr², exact, and the OR of the squares' high words). Kp is `R` sums a row
/// ([`crate::kernel::sum_words`]: 1 or 3).
pub fn pass_r<const R: usize>(
    r: &mut [i32],
    kp: &[[i64; R]],
    d: usize,
    plan: PassR,
) -> (u128, u32) {
    #[cfg(target_arch = "riscv32")]
    if let Some(out) = riscv::pass_r(r, kp, d, plan) {
        return out;
    }
    portable_pass_r(r, kp, d, plan)
}

/// The specification of pass R (the assembly in `riscv` must equal it bit for bit). The K·p
/// term is rounded to nearest, r's own term (coefficient one) is a floored shift.
pub fn portable_pass_r<const R: usize>(
    r: &mut [i32],
    kp: &[[i64; R]],
    d: usize,
    plan: PassR,
) -> (u128, u32) {
    let (mult, narrow) = (plan.lin.term.mult, plan.narrow);
    // One loop per case, so that neither choice is made per element.
    match (narrow, plan.lin.own) {
        (Narrow::Left(_), Some(own)) => r_loop(r, kp, d, mult, narrow, |y| own.apply(y)),
        (Narrow::Right(_), Some(own)) => r_loop(r, kp, d, mult, narrow, |y| own.apply(y)),
        (Narrow::Left(_), None) => r_loop(r, kp, d, mult, narrow, |_| 0),
        (Narrow::Right(_), None) => r_loop(r, kp, d, mult, narrow, |_| 0),
    }
}

/// Pass R's loop for one narrowing of K·p and one own term. The K·p term has no shift of its
/// own: the narrowing normalises it (`Lin::new` with `u_normalised`).
#[inline(always)]
fn r_loop<const R: usize>(
    r: &mut [i32],
    kp: &[[i64; R]],
    d: usize,
    mult: i32,
    narrow: Narrow,
    own: impl Fn(i32) -> i32,
) -> (u128, u32) {
    let mut sum = 0u128;
    let mut or = 0u32;
    for (rc, kc) in r.chunks_mut(SQUARE_BLOCK).zip(kp.chunks(SQUARE_BLOCK)) {
        let mut block = 0u64;
        for (ri, ki) in rc.iter_mut().zip(kc) {
            let z = mulh_rounded(mult, narrow.apply(ki[d])).wrapping_add(own(*ri));
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

/// Pass XP on one slice of direction `d`, p `S` lanes a node ([`crate::kernel::lane_words`]);
/// returns the ORs of |x| and |p| (0 where not updated). The plan by reference: by value, its
/// 48 bytes went through a `memcpy` on every hart at every pass.
pub fn pass_xp<const S: usize>(
    x: &mut [i32],
    p: &mut [[i32; S]],
    r: &[i32],
    d: usize,
    plan: &PassXP,
) -> (u32, u32) {
    #[cfg(target_arch = "riscv32")]
    if let Some(out) = riscv::pass_xp(x, p, r, d, plan) {
        return out;
    }
    portable_pass_xp(x, p, r, d, *plan)
}

/// The specification of pass XP. Every own term is present (x's own x, p's own r).
pub fn portable_pass_xp<const S: usize>(
    x: &mut [i32],
    p: &mut [[i32; S]],
    r: &[i32],
    d: usize,
    plan: PassXP,
) -> (u32, u32) {
    let (mut x_or, mut p_or) = (0u32, 0u32);
    let own = |lin: Lin| lin.own.unwrap_or_default();
    match plan {
        PassXP {
            x: Some(xl),
            p: Some(pl),
        } => {
            // p shifted once for both its terms.
            debug_assert!(xl.term.shift == pl.term.shift);
            let (shift, x_own, r_own) = (xl.term.shift, own(xl), own(pl));
            for ((xi, pi), &ri) in x.iter_mut().zip(p.iter_mut()).zip(r) {
                let old = pi[d].wrapping_shl(shift);
                let zx = mulh_rounded(xl.term.mult, old).wrapping_add(x_own.apply(*xi));
                *xi = zx;
                x_or |= magnitude_bits(zx);
                let zp = r_own.apply(ri).wrapping_add(mulh(pl.term.mult, old));
                pi[d] = zp;
                p_or |= magnitude_bits(zp);
            }
        }
        PassXP {
            x: Some(xl),
            p: None,
        } => {
            let x_own = own(xl);
            for (xi, pi) in x.iter_mut().zip(p.iter()) {
                let zx = xl.term.apply_rounded(pi[d]).wrapping_add(x_own.apply(*xi));
                *xi = zx;
                x_or |= magnitude_bits(zx);
            }
        }
        PassXP {
            x: None,
            p: Some(pl),
        } => {
            let r_own = own(pl);
            for (pi, &ri) in p.iter_mut().zip(r) {
                let zp = r_own.apply(ri).wrapping_add(pl.term.apply(pi[d]));
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

/// The passes in RV32IM assembly for their common cases; the rest goes to the portable loops,
/// which are the specification these equal bit for bit (the HIL tests check the firmware's
/// solves against the host's, which runs the portable loops).
///
/// - Pass R for a right-narrowed K·p (K·p beyond 2^31, the usual case) with r's own term, the
///   own shift left or right: 40 instructions per pair of elements (36 for a block's first,
///   whose squares start the block's sum), and 11 per block of 16 for the pointers, the fold
///   of its squares into the 96-bit total and the branch: 20.4 per element.
/// - Pass XP updating both x and p (x's coefficient α ≥ 0), each own shift left or right: 40
///   per pair, and 4 per block of 16 for the pointers and the branch: 20.25 per element.
///
/// Each loop body handles a block of 16 elements (eight pairs), so the pointers' increments,
/// the branch and pass R's fold are paid once per 16; the whole quads after the last block go
/// to a loop of four per iteration, and a slice's last `len % 4` elements to the portable
/// loop (with [`crate::exec::share`]'s shares of four only the last hart has any).
///
/// # Scheduling
///
/// For an in-order five-stage core such as VexRiscv (`/work/shared/notes/litex-vexriscv.md`):
/// every loaded value is used at least three instructions after its load, every product three
/// after its `mul`/`mulh`, every shifted value two after its shift; the two elements of a pair
/// are interleaved to make that so. Pass XP's four stores a pair are two slots apart: the
/// write-through data cache passes a store to the bus every other clock at best, so a run of
/// four back to back held the third and fourth a clock each. The counts are the same as
/// unscheduled, so QEMU's instruction counts do not show it; the VexRiscv's cycles do.
///
/// The own terms' shift direction is loop-invariant, so each loop comes in a left and a right
/// variant (one instruction instead of a shift pair), generated from one template per pass.
// The loops walk the slices by raw pointers inside `asm!`; each block states its bounds.
#[allow(unsafe_code)]
#[cfg(target_arch = "riscv32")]
mod riscv {
    use super::*;
    use core::arch::asm;

    /// One pair of pass R's elements: Kp words at byte offsets $ka/$kah and $kb/$kbh of `kp`,
    /// r at $ra and $rb of `r`; the own shift is the instruction $own.
    macro_rules! r_pair {
        ($own:literal, $ka:literal, $kah:literal, $kb:literal, $kbh:literal, $ra:literal, $rb:literal) => {
            r_pair!($own, $ka, $kah, $kb, $kbh, $ra, $rb, r_squares_added)
        };
        ($own:literal, $ka:literal, $kah:literal, $kb:literal, $kbh:literal, $ra:literal, $rb:literal,
         $sum:ident) => {
            concat!(
                "lw {a0}, ",
                $ka,
                "({kp})\n",
                "lw {a1}, ",
                $kah,
                "({kp})\n",
                "lw {b0}, ",
                $kb,
                "({kp})\n",
                "lw {b1}, ",
                $kbh,
                "({kp})\n",
                "lw {ya}, ",
                $ra,
                "({r})\n",
                "lw {yb}, ",
                $rb,
                "({r})\n",
                "srl {a0}, {a0}, {s}\n",
                "sll {a1}, {a1}, {t}\n",
                "srl {b0}, {b0}, {s}\n",
                "sll {b1}, {b1}, {t}\n",
                $own,
                " {ya}, {ya}, {k}\n",
                $own,
                " {yb}, {yb}, {k}\n",
                "or {a0}, {a0}, {a1}\n",
                "or {b0}, {b0}, {b1}\n",
                "mul {ma}, {m}, {a0}\n",
                "mulh {a0}, {m}, {a0}\n",
                "mul {mb}, {m}, {b0}\n",
                "mulh {b0}, {m}, {b0}\n",
                "srli {ma}, {ma}, 31\n",
                "srli {mb}, {mb}, 31\n",
                "add {ya}, {ya}, {a0}\n",
                "add {yb}, {yb}, {b0}\n",
                "add {ya}, {ya}, {ma}\n",
                "add {yb}, {yb}, {mb}\n",
                "sw {ya}, ",
                $ra,
                "({r})\n",
                "sw {yb}, ",
                $rb,
                "({r})\n",
                "mul {ma}, {ya}, {ya}\n",
                "mulh {ya}, {ya}, {ya}\n",
                "mul {mb}, {yb}, {yb}\n",
                "mulh {yb}, {yb}, {yb}\n",
                $sum!(),
            )
        };
    }

    /// The pair's squares (ma, ya) and (mb, yb) added into the block's (lo, hi), with their
    /// high words ORed into `or`.
    macro_rules! r_squares_added {
        () => {
            concat!(
                "add {lo}, {lo}, {ma}\n",
                "sltu {ma}, {lo}, {ma}\n",
                "add {hi}, {hi}, {ya}\n",
                "or {or}, {or}, {ya}\n",
                "add {lo}, {lo}, {mb}\n",
                "sltu {mb}, {lo}, {mb}\n",
                "add {hi}, {hi}, {yb}\n",
                "or {or}, {or}, {yb}\n",
                "add {hi}, {hi}, {ma}\n",
                "add {hi}, {hi}, {mb}\n",
            )
        };
    }

    /// A block's first pair: its two squares start (lo, hi) rather than add to them, so the
    /// block needs no zeroing and the pair one carry instead of two.
    macro_rules! r_squares_first {
        () => {
            concat!(
                "or {or}, {or}, {ya}\n",
                "add {lo}, {ma}, {mb}\n",
                "or {or}, {or}, {yb}\n",
                "add {hi}, {ya}, {yb}\n",
                "sltu {mb}, {lo}, {mb}\n",
                "add {hi}, {hi}, {mb}\n",
            )
        };
    }

    /// Folds a block's (lo, hi) into the 96-bit (w0, w1, w2).
    macro_rules! r_fold {
        () => {
            concat!(
                "add {w0}, {w0}, {lo}\n",
                "sltu {lo}, {w0}, {lo}\n",
                "add {w1}, {w1}, {hi}\n",
                "sltu {hi}, {w1}, {hi}\n",
                "add {w1}, {w1}, {lo}\n",
                "sltu {lo}, {w1}, {lo}\n",
                "add {w2}, {w2}, {hi}\n",
                "add {w2}, {w2}, {lo}\n",
            )
        };
    }

    /// One of pass R's loops (`body`) with its operands; `extra` names the loop's own
    /// (lo and hi, and any other scratch register).
    macro_rules! pass_r_asm {
        ([$($body:tt)*], $kp:ident, $r:ident, $end:ident, $m:ident, $s:ident, $k:ident,
         $w0:ident, $w1:ident, $w2:ident, $or:ident, $($extra:tt)*) => {
            // SAFETY: reads Kp and reads/writes r within the elements the caller sized `end`
            // to.
            unsafe {
                asm!(
                    concat!($($body)*),
                    kp = inout(reg) $kp => _,
                    r = inout(reg) $r => _,
                    end = in(reg) $end,
                    m = in(reg) $m,
                    s = in(reg) $s,
                    t = in(reg) 32 - $s,
                    k = in(reg) $k,
                    w0 = inout(reg) $w0,
                    w1 = inout(reg) $w1,
                    w2 = inout(reg) $w2,
                    or = inout(reg) $or,
                    a0 = out(reg) _,
                    a1 = out(reg) _,
                    b0 = out(reg) _,
                    b1 = out(reg) _,
                    ya = out(reg) _,
                    yb = out(reg) _,
                    ma = out(reg) _,
                    mb = out(reg) _,
                    $($extra)*
                    options(nostack),
                );
            }
        };
    }

    /// Pass R over whole blocks of 16 elements, own shift $own, Kp `$row` bytes a row (24, or
    /// 8 for one direction, [`crate::kernel::sum_words`]: the same instructions, Kp's offsets
    /// the row's multiples, as `const` operands): the block's 16 squares summed in (lo, hi) and
    /// folded into the 96-bit (w0, w1, w2) at its end. The body is one block unrolled, so the
    /// pointers' increments, the branch and the block bookkeeping are paid once per 16
    /// elements (the quad loop below handles what is left).
    macro_rules! pass_r_blocks {
        ($own:literal, $row:expr, $($args:ident),*) => {
            pass_r_asm!(
                [
                    "5:\n",
                    r_pair!($own, "{k0}", "{k0h}", "{k1}", "{k1h}", "0", "4", r_squares_first),
                    r_pair!($own, "{k2}", "{k2h}", "{k3}", "{k3h}", "8", "12"),
                    r_pair!($own, "{k4}", "{k4h}", "{k5}", "{k5h}", "16", "20"),
                    r_pair!($own, "{k6}", "{k6h}", "{k7}", "{k7h}", "24", "28"),
                    r_pair!($own, "{k8}", "{k8h}", "{k9}", "{k9h}", "32", "36"),
                    r_pair!($own, "{k10}", "{k10h}", "{k11}", "{k11h}", "40", "44"),
                    r_pair!($own, "{k12}", "{k12h}", "{k13}", "{k13h}", "48", "52"),
                    r_pair!($own, "{k14}", "{k14h}", "{k15}", "{k15h}", "56", "60"),
                    "addi {kp}, {kp}, {step}\n",
                    "addi {r}, {r}, 64\n",
                    r_fold!(),
                    "bltu {r}, {end}, 5b\n",
                ],
                $($args),*,
                lo = out(reg) _,
                hi = out(reg) _,
                k0 = const 0 * $row,
                k0h = const 0 * $row + 4,
                k1 = const 1 * $row,
                k1h = const 1 * $row + 4,
                k2 = const 2 * $row,
                k2h = const 2 * $row + 4,
                k3 = const 3 * $row,
                k3h = const 3 * $row + 4,
                k4 = const 4 * $row,
                k4h = const 4 * $row + 4,
                k5 = const 5 * $row,
                k5h = const 5 * $row + 4,
                k6 = const 6 * $row,
                k6h = const 6 * $row + 4,
                k7 = const 7 * $row,
                k7h = const 7 * $row + 4,
                k8 = const 8 * $row,
                k8h = const 8 * $row + 4,
                k9 = const 9 * $row,
                k9h = const 9 * $row + 4,
                k10 = const 10 * $row,
                k10h = const 10 * $row + 4,
                k11 = const 11 * $row,
                k11h = const 11 * $row + 4,
                k12 = const 12 * $row,
                k12h = const 12 * $row + 4,
                k13 = const 13 * $row,
                k13h = const 13 * $row + 4,
                k14 = const 14 * $row,
                k14h = const 14 * $row + 4,
                k15 = const 15 * $row,
                k15h = const 15 * $row + 4,
                step = const 16 * $row,
            )
        };
    }

    /// Pass R over whole quads, own shift $own, Kp `$row` bytes a row: blocks of 16 squares in
    /// (lo, hi), folded into the 96-bit (w0, w1, w2) at each block's end.
    macro_rules! pass_r_quads {
        ($own:literal, $row:expr, $($args:ident),*) => {
            pass_r_asm!(
                [
                    "3:\n",
                    "addi {blk}, {r}, 64\n",
                    "bltu {blk}, {end}, 4f\n",
                    "mv {blk}, {end}\n",
                    "4:\n",
                    r_pair!($own, "{k0}", "{k0h}", "{k1}", "{k1h}", "0", "4"),
                    r_pair!($own, "{k2}", "{k2h}", "{k3}", "{k3h}", "8", "12"),
                    "addi {kp}, {kp}, {step}\n",
                    "addi {r}, {r}, 16\n",
                    "bltu {r}, {blk}, 4b\n",
                    r_fold!(),
                    "li {lo}, 0\n",
                    "li {hi}, 0\n",
                    "bltu {r}, {end}, 3b\n",
                ],
                $($args),*,
                lo = inout(reg) 0u32 => _,
                hi = inout(reg) 0u32 => _,
                blk = out(reg) _,
                k0 = const 0 * $row,
                k0h = const 0 * $row + 4,
                k1 = const 1 * $row,
                k1h = const 1 * $row + 4,
                k2 = const 2 * $row,
                k2h = const 2 * $row + 4,
                k3 = const 3 * $row,
                k3h = const 3 * $row + 4,
                step = const 4 * $row,
            )
        };
    }

    /// The assembly pass R for a right-narrowed K·p with r's own term; `None` leaves every
    /// other case to the portable loop.
    pub fn pass_r<const R: usize>(
        r: &mut [i32],
        kp: &[[i64; R]],
        d: usize,
        plan: PassR,
    ) -> Option<(u128, u32)> {
        let (Narrow::Right(s), Some(own)) = (plan.narrow, plan.lin.own) else {
            return None;
        };
        let n = r.len().min(kp.len());
        let quads = n & !3;
        if quads == 0 || d >= MAX_DIRECTIONS.min(R) || !(1..=31).contains(&s) {
            return None;
        }
        // The loops below are written for the two layouts the solver uses.
        if R != 1 && R != MAX_DIRECTIONS {
            return None;
        }
        let blocks = n & !(SQUARE_BLOCK - 1);
        let (mut w0, mut w1, mut w2, mut or) = (0u32, 0u32, 0u32, 0u32);
        let kp_ptr = kp.as_ptr().cast::<u8>().wrapping_add(8 * d);
        let r_ptr = r.as_mut_ptr();
        let m = plan.lin.term.mult;
        // Whole blocks first (the portable loop's chunks of 16), then the quads that are left
        // (the last chunk's whole quads; its last `len % 4` go to the portable loop).
        let (kp_rest, r_rest) = (
            kp_ptr.wrapping_add(blocks * size_of::<[i64; R]>()),
            r_ptr.wrapping_add(blocks),
        );
        let (block_end, end) = (r_rest, r_ptr.wrapping_add(quads));
        let (k, left) = amount(own);
        macro_rules! both {
            ($own:literal) => {{
                if blocks > 0 {
                    pass_r_blocks!(
                        $own,
                        size_of::<[i64; R]>(),
                        kp_ptr,
                        r_ptr,
                        block_end,
                        m,
                        s,
                        k,
                        w0,
                        w1,
                        w2,
                        or
                    );
                }
                if quads > blocks {
                    pass_r_quads!(
                        $own,
                        size_of::<[i64; R]>(),
                        kp_rest,
                        r_rest,
                        end,
                        m,
                        s,
                        k,
                        w0,
                        w1,
                        w2,
                        or
                    );
                }
            }};
        }
        if left {
            both!("sll");
        } else {
            both!("sra");
        }
        let (tail, tail_or) = if quads < n {
            portable_pass_r(&mut r[quads..n], &kp[quads..n], d, plan)
        } else {
            (0, 0)
        };
        let total = u128::from(w0) | (u128::from(w1) << 32) | (u128::from(w2) << 64);
        Some((total + tail, or | tail_or))
    }

    /// One pair of pass XP's elements: p at byte offsets $pa and $pb of `p`, x at $xa/$xb of
    /// `x`, r at $xa/$xb of `r`; the own shifts are $xown (x) and $rown (r into p).
    macro_rules! xp_pair {
        ($xown:literal, $rown:literal, $pa:literal, $pb:literal, $xa:literal, $xb:literal) => {
            concat!(
                "lw {pa}, ",
                $pa,
                "({p})\n",
                "lw {pb}, ",
                $pb,
                "({p})\n",
                "lw {xa}, ",
                $xa,
                "({x})\n",
                "lw {xb}, ",
                $xb,
                "({x})\n",
                "lw {ra}, ",
                $xa,
                "({r})\n",
                "lw {rb}, ",
                $xb,
                "({r})\n",
                "sll {pa}, {pa}, {k}\n",
                "sll {pb}, {pb}, {k}\n",
                $xown,
                " {xa}, {xa}, {sx}\n",
                $xown,
                " {xb}, {xb}, {sx}\n",
                $rown,
                " {ra}, {ra}, {sr}\n",
                $rown,
                " {rb}, {rb}, {sr}\n",
                "mulhsu {ta}, {pa}, {ax2}\n",
                "mulhsu {tb}, {pb}, {ax2}\n",
                "mulh {pa}, {bp}, {pa}\n",
                "mulh {pb}, {bp}, {pb}\n",
                "addi {ta}, {ta}, 1\n",
                "addi {tb}, {tb}, 1\n",
                "srai {ta}, {ta}, 1\n",
                "srai {tb}, {tb}, 1\n",
                "add {ra}, {ra}, {pa}\n",
                "add {rb}, {rb}, {pb}\n",
                "sw {ra}, ",
                $pa,
                "({p})\n",
                "add {xa}, {xa}, {ta}\n",
                "sw {rb}, ",
                $pb,
                "({p})\n",
                "add {xb}, {xb}, {tb}\n",
                "sw {xa}, ",
                $xa,
                "({x})\n",
                "srai {ta}, {ra}, 31\n",
                "sw {xb}, ",
                $xb,
                "({x})\n",
                "srai {tb}, {rb}, 31\n",
                "srai {ua}, {xa}, 31\n",
                "srai {ub}, {xb}, 31\n",
                "xor {ta}, {ra}, {ta}\n",
                "xor {tb}, {rb}, {tb}\n",
                "xor {ua}, {xa}, {ua}\n",
                "xor {ub}, {xb}, {ub}\n",
                "or {op}, {op}, {ta}\n",
                "or {op}, {op}, {tb}\n",
                "or {ox}, {ox}, {ua}\n",
                "or {ox}, {ox}, {ub}\n",
            )
        };
    }

    /// One of pass XP's loops (`body`) with its operands.
    macro_rules! pass_xp_asm {
        ([$($body:tt)*], $p:ident, $x:ident, $r:ident, $end:ident, $k:ident, $sx:ident,
         $sr:ident, $ax2:ident, $bp:ident, $ox:ident, $op:ident) => {
            // SAFETY: reads r and reads/writes x and p's lane within the elements the caller
            // sized `end` to.
            unsafe {
                asm!(
                    concat!($($body)*),
                    p = inout(reg) $p => _,
                    x = inout(reg) $x => _,
                    r = inout(reg) $r => _,
                    end = in(reg) $end,
                    k = in(reg) $k,
                    sx = in(reg) $sx,
                    sr = in(reg) $sr,
                    ax2 = in(reg) $ax2,
                    bp = in(reg) $bp,
                    ox = inout(reg) $ox,
                    op = inout(reg) $op,
                    pa = out(reg) _,
                    pb = out(reg) _,
                    xa = out(reg) _,
                    xb = out(reg) _,
                    ra = out(reg) _,
                    rb = out(reg) _,
                    ta = out(reg) _,
                    tb = out(reg) _,
                    ua = out(reg) _,
                    ub = out(reg) _,
                    options(nostack),
                );
            }
        };
    }

    /// Pass XP over whole blocks of 16 elements, own shifts $xown (x) and $rown (r): the
    /// body unrolled over the block, so the three pointers' increments and the branch are paid
    /// once per 16 elements (the quad loop below handles what is left).
    macro_rules! pass_xp_blocks {
        ($xown:literal, $rown:literal, $($args:ident),*) => {
            pass_xp_asm!(
                [
                    "6:\n",
                    xp_pair!($xown, $rown, "0", "16", "0", "4"),
                    xp_pair!($xown, $rown, "32", "48", "8", "12"),
                    xp_pair!($xown, $rown, "64", "80", "16", "20"),
                    xp_pair!($xown, $rown, "96", "112", "24", "28"),
                    xp_pair!($xown, $rown, "128", "144", "32", "36"),
                    xp_pair!($xown, $rown, "160", "176", "40", "44"),
                    xp_pair!($xown, $rown, "192", "208", "48", "52"),
                    xp_pair!($xown, $rown, "224", "240", "56", "60"),
                    "addi {p}, {p}, 256\n",
                    "addi {x}, {x}, 64\n",
                    "addi {r}, {r}, 64\n",
                    "bltu {x}, {end}, 6b\n",
                ],
                $($args),*
            )
        };
    }

    /// Pass XP over whole quads, own shifts $xown (x) and $rown (r).
    macro_rules! pass_xp_quads {
        ($xown:literal, $rown:literal, $($args:ident),*) => {
            pass_xp_asm!(
                [
                    "2:\n",
                    xp_pair!($xown, $rown, "0", "16", "0", "4"),
                    xp_pair!($xown, $rown, "32", "48", "8", "12"),
                    "addi {p}, {p}, 64\n",
                    "addi {x}, {x}, 16\n",
                    "addi {r}, {r}, 16\n",
                    "bltu {x}, {end}, 2b\n",
                ],
                $($args),*
            )
        };
    }

    /// [`pass_xp_blocks`] with p 4 bytes a node (one direction, [`crate::kernel::lane_words`]):
    /// the same instructions, p's offsets those of x.
    macro_rules! pass_xp_blocks_compact {
        ($xown:literal, $rown:literal, $($args:ident),*) => {
            pass_xp_asm!(
                [
                    "6:\n",
                    xp_pair!($xown, $rown, "0", "4", "0", "4"),
                    xp_pair!($xown, $rown, "8", "12", "8", "12"),
                    xp_pair!($xown, $rown, "16", "20", "16", "20"),
                    xp_pair!($xown, $rown, "24", "28", "24", "28"),
                    xp_pair!($xown, $rown, "32", "36", "32", "36"),
                    xp_pair!($xown, $rown, "40", "44", "40", "44"),
                    xp_pair!($xown, $rown, "48", "52", "48", "52"),
                    xp_pair!($xown, $rown, "56", "60", "56", "60"),
                    "addi {p}, {p}, 64\n",
                    "addi {x}, {x}, 64\n",
                    "addi {r}, {r}, 64\n",
                    "bltu {x}, {end}, 6b\n",
                ],
                $($args),*
            )
        };
    }

    /// [`pass_xp_quads`] with p 4 bytes a node.
    macro_rules! pass_xp_quads_compact {
        ($xown:literal, $rown:literal, $($args:ident),*) => {
            pass_xp_asm!(
                [
                    "2:\n",
                    xp_pair!($xown, $rown, "0", "4", "0", "4"),
                    xp_pair!($xown, $rown, "8", "12", "8", "12"),
                    "addi {p}, {p}, 16\n",
                    "addi {x}, {x}, 16\n",
                    "addi {r}, {r}, 16\n",
                    "bltu {x}, {end}, 2b\n",
                ],
                $($args),*
            )
        };
    }

    /// Elements per iteration of pass XP's unrolled loop.
    const XP_BLOCK: usize = 16;

    /// The shift instruction's amount and whether it is a left shift.
    fn amount(s: Shift) -> (u32, bool) {
        if s.right == 0 {
            (s.left, true)
        } else {
            (s.right, false)
        }
    }

    /// The assembly pass XP updating both x and p; `None` leaves every other case to the
    /// portable loop.
    pub fn pass_xp<const S: usize>(
        x: &mut [i32],
        p: &mut [[i32; S]],
        r: &[i32],
        d: usize,
        plan: &PassXP,
    ) -> Option<(u32, u32)> {
        let PassXP {
            x: Some(xl),
            p: Some(pl),
        } = *plan
        else {
            return None;
        };
        let (Some(x_own), Some(r_own)) = (xl.own, pl.own) else {
            return None;
        };
        let n = x.len().min(p.len()).min(r.len());
        let quads = n & !3;
        if quads == 0 || d >= MAX_DIRECTIONS.min(S) || xl.term.shift != pl.term.shift {
            return None;
        }
        // The loops below are written for the two layouts the solver uses.
        if S != 1 && S != 4 {
            return None;
        }
        let blocks = n & !(XP_BLOCK - 1);
        let (mut ox, mut op) = (0u32, 0u32);
        let p_ptr = p.as_mut_ptr().cast::<u8>().wrapping_add(4 * d);
        let x_ptr = x.as_mut_ptr();
        let r_ptr = r.as_ptr();
        // Whole blocks first, then the quads that are left.
        let (p_rest, x_rest, r_rest) = (
            p_ptr.wrapping_add(blocks * size_of::<[i32; S]>()),
            x_ptr.wrapping_add(blocks),
            r_ptr.wrapping_add(blocks),
        );
        let (block_end, end) = (x_rest, x_ptr.wrapping_add(quads));
        let (k, ax, bp) = (xl.term.shift, xl.term.mult, pl.term.mult);
        // 2·ax as an unsigned multiplier: x's rounded term in three instructions (`mulhsu`,
        // +1, halved) instead of four. α ≥ 0 (a quotient of two non-negative scalars) keeps
        // ax ≥ 0; any other sign goes to the portable loop.
        let Ok(ax2) = u32::try_from(ax).map(|a| a << 1) else {
            return None;
        };
        let ((sx, x_left), (sr, r_left)) = (amount(x_own), amount(r_own));
        macro_rules! both {
            ($xown:literal, $rown:literal) => {{
                if S == 1 {
                    if blocks > 0 {
                        pass_xp_blocks_compact!(
                            $xown, $rown, p_ptr, x_ptr, r_ptr, block_end, k, sx, sr, ax2, bp, ox,
                            op
                        );
                    }
                    if quads > blocks {
                        pass_xp_quads_compact!(
                            $xown, $rown, p_rest, x_rest, r_rest, end, k, sx, sr, ax2, bp, ox, op
                        );
                    }
                } else {
                    if blocks > 0 {
                        pass_xp_blocks!(
                            $xown, $rown, p_ptr, x_ptr, r_ptr, block_end, k, sx, sr, ax2, bp, ox,
                            op
                        );
                    }
                    if quads > blocks {
                        pass_xp_quads!(
                            $xown, $rown, p_rest, x_rest, r_rest, end, k, sx, sr, ax2, bp, ox, op
                        );
                    }
                }
            }};
        }
        match (x_left, r_left) {
            (true, true) => both!("sll", "sll"),
            (true, false) => both!("sll", "sra"),
            (false, true) => both!("sra", "sll"),
            (false, false) => both!("sra", "sra"),
        }
        let (tx, tp) = if quads < n {
            portable_pass_xp(&mut x[quads..n], &mut p[quads..n], &r[quads..n], d, *plan)
        } else {
            (0, 0)
        };
        Some((ox | tx, op | tp))
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

    /// A xorshift64 stream of test inputs from `seed`.
    fn xorshift(mut seed: u64) -> impl FnMut() -> u64 {
        move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        }
    }

    /// The assembly pass XP rounds x's term with `mulhsu` by 2·mult (mult ≥ 0), plus one,
    /// halved: the same as [`mulh_rounded`] for every input.
    #[test]
    fn the_halved_rounding_equals_the_rounded_high_word() {
        let via_mulhsu = |mult: i32, v: i32| {
            let m2 = u64::from(u32::try_from(mult).unwrap() << 1);
            let t = ((i64::from(v) as i128 * i128::from(m2)) >> 32) as i32;
            (t + 1) >> 1
        };
        let mut next = xorshift(0x9E37_79B9_7F4A_7C15u64);
        let edges = [
            0,
            1,
            2,
            3,
            (1 << 30) - 1,
            1 << 30,
            (1 << 30) + 1,
            i32::MAX - 1,
            i32::MAX,
        ];
        let values = [
            0,
            1,
            -1,
            2,
            -2,
            1 << 29,
            -(1 << 29),
            i32::MAX,
            i32::MIN,
            i32::MIN + 1,
        ];
        for &m in &edges {
            for &v in &values {
                assert_eq!(via_mulhsu(m, v), mulh_rounded(m, v), "{m} {v}");
            }
        }
        for _ in 0..200_000 {
            let w = next();
            let m = (w as u32 >> 1) as i32;
            let v = (w >> 32) as i32;
            assert_eq!(via_mulhsu(m, v), mulh_rounded(m, v), "{m} {v}");
            // Products whose low word sits at the rounding edge (±2^31 and one either side).
            let m = m | 1 << 30;
            assert_eq!(via_mulhsu(m, v >> 3), mulh_rounded(m, v >> 3), "{m} {v}");
        }
        for m in [1i32 << 30, 3 << 29, i32::MAX] {
            for v in [-(1 << 20), 1 << 20, 12345, -12345] {
                for dv in -2..=2 {
                    let v = v + dv;
                    assert_eq!(via_mulhsu(m, v), mulh_rounded(m, v), "{m} {v}");
                }
            }
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

    /// A scalar for an f64 (tests only): its top 32 bits.
    fn scalar(v: f64) -> Scalar {
        if v == 0.0 {
            return Scalar::ZERO;
        }
        let e = v.abs().log2().floor() as i32 - 31;
        let m = (v.abs() / 2f64.powi(e)) as u64;
        let (m, e) = if m >= 1 << 32 {
            (m >> 1, e + 1)
        } else {
            (m, e)
        };
        Scalar {
            neg: v < 0.0,
            m: m as u32,
            e,
        }
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
        for a in [1.0, -0.37, 1e-12, 7.5, 2.9e3] {
            let lin = Lin::new(scalar(a), u, false, Some(y), &mut sat);
            let own = lin.own.unwrap();
            for (ui, yi) in [(1 << 30) - 1, -(1 << 30) + 1]
                .into_iter()
                .flat_map(|ui| [((1 << 29) + 7, ui), (-(1 << 29) - 7, ui)])
                .map(|(yi, ui)| (ui, yi))
            {
                let z = lin.term.apply_rounded(ui) as i64 + own.apply(yi) as i64;
                assert!(z.abs() < 1 << OUTPUT_BITS, "{a}: {z}");
            }
        }
        assert_eq!(sat, 0);
    }

    #[test]
    fn the_long_division_is_exact() {
        let mut next = xorshift(0x2545_F491_4F6C_DD1Du64);
        let edges = [
            1u32 << 31,
            (1 << 31) + 1,
            u32::MAX,
            u32::MAX - 1,
            0xC000_0000,
        ];
        for _ in 0..200_000 {
            let v = (next() as u32) | (1 << 31);
            let hi = (next() as u32) % v;
            let lo = next() as u32;
            let want = ((u64::from(hi) << 32) | u64::from(lo)) / u64::from(v);
            assert_eq!(u64::from(div_64_32(hi, lo, v)), want, "{hi} {lo} {v}");
        }
        for &v in &edges {
            for hi in [0, 1, v - 1, v / 2] {
                for lo in [0, 1, u32::MAX, 1 << 31] {
                    let want = ((u64::from(hi) << 32) | u64::from(lo)) / u64::from(v);
                    assert_eq!(u64::from(div_64_32(hi, lo, v)), want);
                }
            }
        }
    }

    #[test]
    fn scalars_are_truncated_and_quotients_floored() {
        for v in [
            1u128,
            3,
            u128::from(u32::MAX),
            1 << 40,
            (1 << 100) + 12345,
            u128::MAX,
        ] {
            let s = Scalar::of_u128(v);
            assert!(s.m >= 1 << 31);
            // m·2^e ≤ v < (m + 1)·2^e
            let lo = s.to_f64();
            assert!(lo <= v as f64 && (v as f64) <= ldexp(f64::from(s.m) + 1.0, s.e));
        }
        assert_eq!(Scalar::of_i128(-5), Scalar::of_u128(5).negate());
        for (a, b) in [
            (1u128, 3u128),
            (7, 7),
            (1 << 90, 3),
            (12345, 1 << 70),
            (5, 4),
        ] {
            let q = Scalar::quotient(Scalar::of_u128(a), Scalar::of_u128(b));
            assert!(q.m >= 1 << 31);
            let want = a as f64 / b as f64;
            assert!(
                (q.to_f64() - want).abs() <= want * 2f64.powi(-30),
                "{a}/{b}"
            );
            assert!(q.to_f64() <= want * (1.0 + 1e-15));
        }
    }

    #[test]
    fn the_threshold_is_never_too_generous() {
        let holds = |t: Threshold, rr: u128, e_r: i32| t.holds(Scalar::of_u128(rr), e_r);
        // tol² = 2^−20, Σb² = 2^40 at e_b = 0: the threshold is 2^20 (Σr² at e_r = 0); Σr²
        // is rounded up by one unit of its 32-bit mantissa before the comparison.
        let t = Threshold::new(2f64.powi(-20), 1 << 40, 0);
        assert!(holds(t, (1 << 20) - 1, 0));
        assert!(!holds(t, 1 << 20, 0));
        assert!(holds(t, (1 << 18) - 1, 1));
        assert!(!holds(t, (1 << 18) + 1, 1));
        assert!(holds(t, (1 << 22) - 1, -1));
        assert!(!holds(t, 1 << 22, -1));
        assert!(holds(t, 0, 50));
        assert!(!holds(Threshold::default(), 1, -500));
        // A tolerance that is no power of two: accepted means within it, and refused means
        // above it or within 2^−30 of it.
        for (tol_sq, bb, e_b) in [(1e-6, 1000u128, -3), (1e-14, 1 << 70, 10), (0.3, 7, 0)] {
            let t = Threshold::new(tol_sq, bb, e_b);
            for rr in [0u128, 1, 7, 1000, 12345, 1 << 30, (1 << 90) + 3] {
                for e_r in [-80, -60, -20, -10, -3, 0, 5, 30] {
                    let ratio = rr as f64 * 2f64.powi(2 * e_r) / (bb as f64 * 2f64.powi(2 * e_b));
                    if holds(t, rr, e_r) {
                        assert!(ratio <= tol_sq, "{rr} {e_r}");
                    } else {
                        assert!(ratio > tol_sq * (1.0 - 2f64.powi(-29)), "{rr} {e_r}");
                    }
                }
            }
        }
    }

    #[test]
    fn bit_length_counts_bits() {
        let powers = (0..40).map(|k| 1u64 << k).flat_map(|p| [p - 1, p, p + 1]);
        let mut next = xorshift(7);
        let random = (0..100_000).map(|_| next() >> (next() % 64));
        for v in powers.chain(random).chain(0..70_000) {
            let v = v as u32;
            assert_eq!(bit_length(v), (32 - v.leading_zeros()) as i32, "{v}");
        }
    }

    #[test]
    fn a_shift_is_the_floor_of_y_times_a_power_of_two() {
        for y in [0, 1, -1, 5, -5, 1 << 28, -(1 << 28) - 3, i32::MAX, i32::MIN] {
            for s in -40..=2 {
                let want = (f64::from(y) * 2f64.powi(s)).floor();
                if want.abs() < 2f64.powi(31) {
                    assert_eq!(f64::from(Shift::by(s).apply(y)), want, "{y} {s}");
                }
            }
        }
    }
}
