//! Upper bounds kept in integers, every operation rounding up.
//!
//! The dynamic step carries a bound on its residual's drift ([`crate::cg::Outcome::drift`])
//! from step to step. On the target every soft-f64 add or multiply costs hart 0 a few hundred
//! cycles of serial work, and the bound took about 6,000 a step (session 6, issue 19). A
//! mantissa and an exponent in integers cost tens, and rounding each result up keeps the bound
//! rigorous: each operation's result is at least the exact one, and at most 2^−31 above it
//! (relatively).

/// Mantissa bits of a nonzero finite [`Upper`]: m ∈ [2^31, 2^32), so that a product of two
/// fits a u64 exactly.
const BITS: u32 = 32;

/// Exponents are kept within ±`LIMIT`: above it the bound is infinite; below it a value is
/// rounded up to 2^31·2^−`LIMIT` (far below any bound the solve forms), so exponent arithmetic
/// never overflows an i32.
const LIMIT: i64 = 1 << 20;

/// A non-negative real upper bound m·2^e (m ∈ [2^31, 2^32) or 0), or infinite.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Upper {
    m: u64,
    e: i32,
}

impl Default for Upper {
    /// Nothing known: infinite.
    fn default() -> Upper {
        Upper::INFINITE
    }
}

impl Upper {
    pub const ZERO: Upper = Upper { m: 0, e: 0 };
    pub const INFINITE: Upper = Upper { m: 0, e: i32::MAX };

    /// m·2^e for any m, rounded up.
    pub fn new(m: u64, e: i32) -> Upper {
        normalize(m, i64::from(e))
    }

    /// k·2^e for a small k (the bounds' unit counts, 1 to 7), exact, without
    /// [`Upper::new`]'s leading-zero count (a loop on the RV32 target); larger k go there.
    pub fn small(k: u64, e: i32) -> Upper {
        let (m, shift) = match k {
            0 => return Upper::ZERO,
            1 => (1, 31),
            2..=3 => (k, 30),
            4..=7 => (k, 29),
            _ => return Upper::new(k, e),
        };
        clamp(m << shift, i64::from(e) - shift)
    }

    /// m·2^e for a 128-bit m (a sum of squares), rounded up.
    pub fn wide(m: u128, e: i32) -> Upper {
        let width = 128 - m.leading_zeros();
        if width <= 64 {
            return Upper::new(m as u64, e);
        }
        // Keep 63 bits, so that rounding the cut bits up cannot wrap the u64.
        let shift = width - 63;
        let inexact = m & ((1u128 << shift) - 1) != 0;
        let top = (m >> shift) as u64 + u64::from(inexact);
        normalize(top, i64::from(e) + i64::from(shift))
    }

    pub fn is_finite(self) -> bool {
        self.e != i32::MAX
    }

    /// The smaller of two bounds (each is one, so the smaller is): mantissas are normalized
    /// (m ∈ [2^31, 2^32) or 0), so a larger exponent is a larger value.
    pub fn min(self, other: Upper) -> Upper {
        let key = |u: Upper| (u.m != 0, u.e, u.m);
        if !other.is_finite() || (self.is_finite() && key(self) <= key(other)) {
            self
        } else {
            other
        }
    }

    /// self + other, rounded up.
    pub fn plus(self, other: Upper) -> Upper {
        if !self.is_finite() || !other.is_finite() {
            return Upper::INFINITE;
        }
        if other.m == 0 {
            return self;
        }
        if self.m == 0 {
            return other;
        }
        let (hi, lo) = if self.e >= other.e {
            (self, other)
        } else {
            (other, self)
        };
        let d = (i64::from(hi.e) - i64::from(lo.e)) as u64;
        // lo at hi's exponent, rounded up: lo.m < 2^32, so past 32 places it is below 1 unit.
        let aligned = if d >= u64::from(BITS) {
            1
        } else {
            (lo.m + (1u64 << d) - 1) >> d
        };
        // Both mantissas below 2^32: the sum is below 2^33, so at most one place to cut
        // (no general normalization: a leading-zero count is a loop on the RV32 target).
        let sum = hi.m + aligned;
        if sum >> BITS == 0 {
            return Upper { m: sum, e: hi.e };
        }
        up_one(sum.div_ceil(2), i64::from(hi.e) + 1)
    }

    /// self · other, rounded up.
    pub fn times(self, other: Upper) -> Upper {
        if !self.is_finite() || !other.is_finite() {
            return Upper::INFINITE;
        }
        if self.m == 0 || other.m == 0 {
            return Upper::ZERO;
        }
        // Both mantissas in [2^31, 2^32): the product lies in [2^62, 2^64), so it is cut by 31
        // or 32 places (no general normalization, as in `plus`).
        let p = self.m * other.m;
        let e = i64::from(self.e) + i64::from(other.e);
        let cut = if p >> 63 != 0 { BITS } else { BITS - 1 };
        up_one(p.div_ceil(1u64 << cut), e + i64::from(cut))
    }

    /// self · 2^k, exact (or infinite).
    pub fn scale2(self, k: i32) -> Upper {
        if !self.is_finite() || self.m == 0 {
            return self;
        }
        clamp(self.m, i64::from(self.e) + i64::from(k))
    }

    /// The smallest `Upper` at least `x` (x ≥ 0; NaN or negative gives infinite: nothing
    /// known), from f64's bits: for a caller's bound given in f64 and for the tests.
    pub fn from_f64(x: f64) -> Upper {
        if x.is_nan() || x < 0.0 || x.is_infinite() {
            return Upper::INFINITE;
        }
        let (m, e) = f64_parts(x);
        Upper::new(m, e)
    }

    /// The value as f64 (for reports and tests): exact wherever 2^e is within f64's normal
    /// range, as it is for every bound the solve forms.
    pub fn to_f64(self) -> f64 {
        if !self.is_finite() {
            return f64::INFINITY;
        }
        deform_shared::qformat::ldexp(self.m as f64, self.e)
    }

    /// A [`Lower`]'s value, exactly (the two share their form).
    pub fn exact(l: Lower) -> Upper {
        Upper { m: l.m, e: l.e }
    }

    /// Whether self ≤ `m`·2^`e`, exactly (for a lower bound of the right-hand side formed by
    /// [`Lower`]).
    pub fn at_most(self, rhs: Lower) -> bool {
        if !self.is_finite() {
            return false;
        }
        if self.m == 0 {
            return true;
        }
        if rhs.m == 0 {
            return false;
        }
        // Both mantissas lie in [2^31, 2^32): the exponent orders them first.
        (self.e, self.m) <= (rhs.e, rhs.m)
    }
}

/// A non-negative real lower bound m·2^e (m ∈ [2^31, 2^32) or 0), every operation rounding
/// down: the right-hand side of [`Upper::at_most`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Lower {
    m: u64,
    e: i32,
}

impl Lower {
    /// m·2^e for a 128-bit m, rounded down.
    pub fn wide(m: u128, e: i32) -> Lower {
        let width = 128 - m.leading_zeros();
        let shift = width.saturating_sub(BITS);
        floor_normalize((m >> shift) as u64, i64::from(e) + i64::from(shift))
    }

    /// The largest `Lower` at most `x` (0 for NaN, negative or infinite x: nothing proven).
    pub fn from_f64(x: f64) -> Lower {
        if x.is_nan() || x <= 0.0 || x.is_infinite() {
            return Lower { m: 0, e: 0 };
        }
        let (m, e) = f64_parts(x);
        floor_normalize(m, i64::from(e))
    }

    /// self · other, rounded down.
    pub fn times(self, other: Lower) -> Lower {
        floor_normalize(self.m * other.m, i64::from(self.e) + i64::from(other.e))
    }

    /// A finite [`Upper`]'s value, exactly (the two share their form); 0 for an infinite one
    /// (nothing proven).
    pub fn exact(u: Upper) -> Lower {
        if !u.is_finite() {
            return Lower { m: 0, e: 0 };
        }
        Lower { m: u.m, e: u.e }
    }

    /// self + other, rounded down.
    pub fn plus(self, other: Lower) -> Lower {
        if other.m == 0 {
            return self;
        }
        if self.m == 0 {
            return other;
        }
        let (hi, lo) = if self.e >= other.e {
            (self, other)
        } else {
            (other, self)
        };
        let d = (i64::from(hi.e) - i64::from(lo.e)) as u64;
        let aligned = if d >= u64::from(BITS) { 0 } else { lo.m >> d };
        // Both below 2^32: the sum is below 2^33 (at most one place to cut, rounding down).
        let sum = hi.m + aligned;
        if sum >> BITS == 0 {
            return Lower { m: sum, e: hi.e };
        }
        floor_normalize(sum >> 1, i64::from(hi.e) + 1)
    }

    /// self − `other`, rounded down, where it is proven non-negative (`other` ≤ self); `None`
    /// where it is not.
    pub fn minus(self, other: Upper) -> Option<Lower> {
        if !other.is_finite() {
            return None;
        }
        if other.m == 0 {
            return Some(self);
        }
        // Both mantissas lie in [2^31, 2^32): a smaller exponent is a smaller value.
        if self.m == 0 || self.e < other.e {
            return None;
        }
        let d = (i64::from(self.e) - i64::from(other.e)) as u64;
        if d <= u64::from(BITS) {
            // Exact at other's exponent: self.m < 2^32 shifted by at most 32 places.
            let hi = self.m << d;
            let diff = hi.checked_sub(other.m)?;
            return Some(floor_normalize(diff, i64::from(other.e)));
        }
        // other below one unit of self's exponent, counted as one (rounded up).
        Some(floor_normalize(self.m - 1, i64::from(self.e)))
    }
}

/// x = m·2^e exactly for a finite x ≥ 0.
fn f64_parts(x: f64) -> (u64, i32) {
    let bits = x.to_bits();
    let biased = ((bits >> 52) & 0x7ff) as i32;
    let frac = bits & ((1u64 << 52) - 1);
    if biased == 0 {
        (frac, -1074)
    } else {
        (frac | 1u64 << 52, biased - 1075)
    }
}

/// A mantissa q ∈ [2^31, 2^32] already rounded up, at exponent e: 2^32 carried into the
/// exponent, which is kept within ±[`LIMIT`].
fn up_one(q: u64, e: i64) -> Upper {
    if q >> BITS != 0 {
        return clamp(1u64 << (BITS - 1), e + 1);
    }
    clamp(q, e)
}

/// A normalized mantissa at exponent e: infinite above [`LIMIT`], rounded up to
/// 2^31·2^−`LIMIT` below −`LIMIT`.
fn clamp(q: u64, e: i64) -> Upper {
    if e > LIMIT {
        return Upper::INFINITE;
    }
    if e < -LIMIT {
        return Upper {
            m: 1u64 << (BITS - 1),
            e: -LIMIT as i32,
        };
    }
    Upper { m: q, e: e as i32 }
}

/// m·2^e rounded up to a mantissa in [2^31, 2^32), the exponent kept within ±[`LIMIT`].
fn normalize(m: u64, e: i64) -> Upper {
    if m == 0 {
        return Upper::ZERO;
    }
    let width = 64 - m.leading_zeros();
    let (q, e) = if width > BITS {
        let shift = width - BITS;
        let inexact = m & ((1u64 << shift) - 1) != 0;
        ((m >> shift) + u64::from(inexact), e + i64::from(shift))
    } else {
        (m << (BITS - width), e - i64::from(BITS - width))
    };
    up_one(q, e)
}

/// m·2^e rounded down to a mantissa in [2^31, 2^32); 0 below 2^−[`LIMIT`], and above
/// 2^[`LIMIT`] clamped there (still a lower bound).
fn floor_normalize(m: u64, e: i64) -> Lower {
    if m == 0 {
        return Lower { m: 0, e: 0 };
    }
    let width = 64 - m.leading_zeros();
    let (q, e) = if width > BITS {
        let shift = width - BITS;
        (m >> shift, e + i64::from(shift))
    } else {
        (m << (BITS - width), e - i64::from(BITS - width))
    };
    if e < -LIMIT {
        return Lower { m: 0, e: 0 };
    }
    Lower {
        m: q,
        e: e.min(LIMIT) as i32,
    }
}

#[cfg(test)]
mod tests;
