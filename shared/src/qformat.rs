//! Fixed-point formats on the wire.
//!
//! Two formats travel between host and target:
//!
//! - **Matrix values** are Q-format numbers in the 21-bit value field of a [`crate::word::Word`].
//!   The number of fractional bits `F` is chosen per matrix by the host ([`choose_frac_bits`]) so
//!   that the largest magnitude just fits: raw = round(value · 2^F). The conversions use the
//!   `fixed` crate's correctly rounded, range-checked `FixedI32<F>`.
//! - **Vectors** (loads, displacements) are block floating point: `i32` mantissas sharing one
//!   exponent, value = m · 2^e, with |m| < 2^[`MANTISSA_BITS`]. One shared exponent per vector keeps
//!   30 significant bits relative to the largest entry whatever the physical scale, which is what
//!   lets the target's fixed-point CG never overflow (see `deform_target_core::cg`).

use fixed::types::extra::*;
use fixed::FixedI32;

use crate::word::{VALUE_BITS, VALUE_MAX, VALUE_MIN};

/// Largest number of fractional bits a matrix value may use: all 21 bits but the sign.
pub const MAX_FRAC_BITS: u8 = (VALUE_BITS - 1) as u8;

/// Block-floating-point mantissas stay strictly below 2^30 in magnitude, one bit of headroom
/// below `i32`, so that the sum of two of them never overflows.
pub const MANTISSA_BITS: u32 = 30;
/// 2^[`MANTISSA_BITS`], the exclusive bound on a mantissa's magnitude.
pub const MANTISSA_LIMIT: i64 = 1 << MANTISSA_BITS;

/// The relative residual below which the fixed-point CG is not asked to go: its block floating
/// point levels off around 1e-8 (30-bit mantissas), so a tighter inner tolerance only burns
/// cycles. The host refines in f64 below it (`deform_host::refine`); the target's live model
/// solves its columns to it. The one home of the figure.
pub const FIXED_POINT_FLOOR: f64 = 1e-7;

#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum QFormatError {
    #[error("{0} fractional bits requested; the 21-bit value field allows 0..=20")]
    FracBitsOutOfRange(u8),
    #[error("value {value} does not fit a 21-bit Q-format with {frac_bits} fractional bits")]
    ValueOutOfRange { value: f64, frac_bits: u8 },
    #[error("value {0} is not finite")]
    NotFinite(f64),
}

/// Runs `$body` with `$T` bound to `FixedI32<U$f>` for a runtime `$f` in `0..=20`.
macro_rules! with_frac {
    ($f:expr, $T:ident => $body:expr) => {
        match $f {
            0 => {
                type $T = FixedI32<U0>;
                Ok($body)
            }
            1 => {
                type $T = FixedI32<U1>;
                Ok($body)
            }
            2 => {
                type $T = FixedI32<U2>;
                Ok($body)
            }
            3 => {
                type $T = FixedI32<U3>;
                Ok($body)
            }
            4 => {
                type $T = FixedI32<U4>;
                Ok($body)
            }
            5 => {
                type $T = FixedI32<U5>;
                Ok($body)
            }
            6 => {
                type $T = FixedI32<U6>;
                Ok($body)
            }
            7 => {
                type $T = FixedI32<U7>;
                Ok($body)
            }
            8 => {
                type $T = FixedI32<U8>;
                Ok($body)
            }
            9 => {
                type $T = FixedI32<U9>;
                Ok($body)
            }
            10 => {
                type $T = FixedI32<U10>;
                Ok($body)
            }
            11 => {
                type $T = FixedI32<U11>;
                Ok($body)
            }
            12 => {
                type $T = FixedI32<U12>;
                Ok($body)
            }
            13 => {
                type $T = FixedI32<U13>;
                Ok($body)
            }
            14 => {
                type $T = FixedI32<U14>;
                Ok($body)
            }
            15 => {
                type $T = FixedI32<U15>;
                Ok($body)
            }
            16 => {
                type $T = FixedI32<U16>;
                Ok($body)
            }
            17 => {
                type $T = FixedI32<U17>;
                Ok($body)
            }
            18 => {
                type $T = FixedI32<U18>;
                Ok($body)
            }
            19 => {
                type $T = FixedI32<U19>;
                Ok($body)
            }
            20 => {
                type $T = FixedI32<U20>;
                Ok($body)
            }
            other => Err(QFormatError::FracBitsOutOfRange(other)),
        }
    };
}

/// Quantizes `value` to a raw 21-bit field with `frac_bits` fractional bits, rounding to nearest.
pub fn quantize(value: f64, frac_bits: u8) -> Result<i32, QFormatError> {
    if !value.is_finite() {
        return Err(QFormatError::NotFinite(value));
    }
    let raw: Option<i32> = with_frac!(frac_bits, Q => Q::checked_from_num(value).map(Q::to_bits))?;
    match raw {
        Some(r) if (VALUE_MIN..=VALUE_MAX).contains(&r) => Ok(r),
        _ => Err(QFormatError::ValueOutOfRange { value, frac_bits }),
    }
}

/// The value a raw field stands for.
pub fn dequantize(raw: i32, frac_bits: u8) -> Result<f64, QFormatError> {
    with_frac!(frac_bits, Q => Q::from_bits(raw).to_num::<f64>())
}

/// The most fractional bits with which every value of magnitude up to `max_abs` still fits.
pub fn choose_frac_bits(max_abs: f64) -> Result<u8, QFormatError> {
    if !max_abs.is_finite() {
        return Err(QFormatError::NotFinite(max_abs));
    }
    let max_abs = max_abs.abs();
    (0..=MAX_FRAC_BITS)
        .rev()
        .find(|&f| quantize(max_abs, f).is_ok() && quantize(-max_abs, f).is_ok())
        .ok_or(QFormatError::ValueOutOfRange {
            value: max_abs,
            frac_bits: 0,
        })
}

/// 2^k as an `f64`, for any `k` (saturating to 0 or infinity outside the `f64` range).
pub fn pow2(k: i32) -> f64 {
    if (-1022..=1023).contains(&k) {
        f64::from_bits(((1023 + k) as u64) << 52)
    } else if k > 0 {
        f64::INFINITY
    } else if k >= -2044 {
        // Subnormal (or zero below 2^-1074): two factors, each a normal power of two.
        pow2(-1022) * pow2(k + 1022)
    } else {
        0.0
    }
}

/// x · 2^k, exact unless the result leaves the `f64` range (two steps, so that `k` may exceed
/// the exponent range of a single power of two).
///
/// Where x and the result are both normal the product only moves x's exponent field, so that
/// is all this does there, bit for bit the product's result: on a target without an FPU a
/// multiplication is a soft-float call of a hundred or more instructions, and the firmware's
/// serial planning scales by powers of two dozens of times a step.
pub fn ldexp(x: f64, k: i32) -> f64 {
    let bits = x.to_bits();
    let biased = ((bits >> 52) & 0x7FF) as i32;
    if biased != 0 && biased != 0x7FF && (-2046..=2046).contains(&k) {
        let scaled = biased + k;
        if (1..=2046).contains(&scaled) {
            return f64::from_bits((bits & !(0x7FF << 52)) | ((scaled as u64) << 52));
        }
    }
    ldexp_by_product(x, k)
}

/// [`ldexp`] by multiplication: zeros, subnormals, infinities and NaNs, and results that leave
/// the normal range.
fn ldexp_by_product(x: f64, k: i32) -> f64 {
    if k > 1023 {
        x * pow2(1023) * pow2(k - 1023)
    } else if k < -1022 {
        x * pow2(-1022) * pow2(k + 1022)
    } else {
        x * pow2(k)
    }
}

/// ⌊log2 |x|⌋ for finite nonzero `x`.
pub fn floor_log2(x: f64) -> i32 {
    let bits = x.abs().to_bits();
    let biased = ((bits >> 52) & 0x7FF) as i32;
    if biased == 0 {
        // Subnormal: normalise first.
        floor_log2(x * pow2(64)) - 64
    } else {
        biased - 1023
    }
}

/// The shared exponent for a vector whose largest magnitude is `max_abs`: the smallest `e` with
/// round(max_abs · 2^-e) < 2^[`MANTISSA_BITS`]. A zero vector gets exponent 0.
pub fn block_exponent(max_abs: f64) -> i32 {
    if max_abs == 0.0 || !max_abs.is_finite() {
        return 0;
    }
    let mut e = floor_log2(max_abs) + 1 - MANTISSA_BITS as i32;
    // Rounding can carry into bit 30 (e.g. max_abs just below a power of two).
    if (ldexp(max_abs.abs(), -e) + 0.5) as i64 >= MANTISSA_LIMIT {
        e += 1;
    }
    e
}

/// The mantissa of `value` at exponent `e`, rounded to nearest. `None` if it would not fit.
pub fn to_mantissa(value: f64, e: i32) -> Option<i32> {
    if !value.is_finite() {
        return None;
    }
    let scaled = ldexp(value, -e);
    let rounded = if scaled >= 0.0 {
        scaled + 0.5
    } else {
        scaled - 0.5
    };
    if rounded.abs() >= MANTISSA_LIMIT as f64 {
        return None;
    }
    Some(rounded as i64 as i32)
}

/// The value of mantissa `m` at exponent `e`.
pub fn from_mantissa(m: i32, e: i32) -> f64 {
    ldexp(m as f64, e)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn frac_bits_keep_the_most_precision() {
        assert_eq!(choose_frac_bits(1.0).unwrap(), 19);
        assert_eq!(choose_frac_bits(0.9).unwrap(), 20);
        assert_eq!(choose_frac_bits(6.0).unwrap(), 17);
        assert_eq!(choose_frac_bits(26.0).unwrap(), 15);
        assert_eq!(choose_frac_bits(0.0).unwrap(), 20);
        assert_eq!(choose_frac_bits(1_048_575.0).unwrap(), 0);
        assert!(choose_frac_bits(1_048_576.0).is_err());
        assert!(choose_frac_bits(f64::NAN).is_err());
    }

    #[test]
    fn quantize_checks_range() {
        assert_eq!(quantize(1.5, 1).unwrap(), 3);
        assert_eq!(quantize(-2.0, 19).unwrap(), VALUE_MIN);
        assert!(quantize(2.0, 19).is_err());
        assert!(quantize(1.0, 21).is_err());
        assert!(quantize(f64::INFINITY, 3).is_err());
        assert_eq!(dequantize(VALUE_MIN, 20).unwrap(), -1.0);
    }

    /// The exponent-field fast path is bit for bit the product by 2^k, wherever it applies
    /// and around its edges (subnormal and overflowing results, zeros, infinities, NaN).
    #[test]
    fn ldexp_equals_the_product_by_a_power_of_two() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let specials = [
            0.0,
            -0.0,
            f64::MIN_POSITIVE,
            -f64::MIN_POSITIVE,
            5e-324,
            f64::MAX,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            1.0,
            -3.5,
        ];
        let ks = [
            0, 1, -1, 52, -52, 1022, -1022, 1023, -1074, 1100, -1100, 2046, -2046, 3000,
        ];
        let check = |x: f64, k: i32| {
            let want = ldexp_by_product(x, k);
            let got = ldexp(x, k);
            assert!(
                got.to_bits() == want.to_bits() || (got.is_nan() && want.is_nan()),
                "{x:e} · 2^{k}: {got:e} vs {want:e}"
            );
        };
        for &x in &specials {
            for &k in &ks {
                check(x, k);
                check(x, -k);
            }
        }
        for _ in 0..200_000 {
            let x = f64::from_bits(next());
            let k = (next() % 4400) as i32 - 2200;
            check(x, k);
            check(x, k % 64);
        }
    }

    #[test]
    fn pow2_is_exact() {
        assert_eq!(pow2(0), 1.0);
        assert_eq!(pow2(-30), 1.0 / 1073741824.0);
        assert_eq!(pow2(1023), f64::MAX / (2.0 - f64::EPSILON));
        assert_eq!(pow2(-1074), f64::from_bits(1));
        assert_eq!(pow2(-2000), 0.0);
        assert_eq!(pow2(2000), f64::INFINITY);
    }

    proptest! {
        #[test]
        fn quantize_round_trips_within_half_an_lsb(v in -1.0e6f64..1.0e6) {
            let f = choose_frac_bits(v).unwrap();
            let raw = quantize(v, f).unwrap();
            let back = dequantize(raw, f).unwrap();
            prop_assert!((back - v).abs() <= pow2(-(f as i32)) / 2.0);
        }

        #[test]
        fn block_mantissas_fit_and_keep_30_bits(v in prop::num::f64::NORMAL) {
            let e = block_exponent(v);
            let m = to_mantissa(v, e).unwrap();
            prop_assert!((m as i64).abs() < MANTISSA_LIMIT);
            prop_assert!((m as i64).abs() >= MANTISSA_LIMIT / 2 - 1);
            let back = from_mantissa(m, e);
            prop_assert!((back - v).abs() <= v.abs() * 2.0f64.powi(-29));
        }
    }
}
