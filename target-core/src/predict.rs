//! The predictor of [`Start::Predicted`](deform_shared::protocol::Start::Predicted): each time
//! step's CG starts from the linear extrapolation 2u(t−1) − u(t−2) of the two solutions before
//! it, computed on the target so that no vector crosses the link (issue 11, item 4).
//!
//! A tool that moves smoothly moves the solution smoothly: along a straight push the
//! extrapolation is exact up to the solver's tolerance, and along a curve its error is second
//! order in the step, against first order for a plain warm start from u(t−1). CG's iterations
//! grow with the logarithm of the starting error, so the prediction saves iterations every step.
//!
//! Both solutions are block floating point (`i32` mantissas, one exponent each), usually with
//! different exponents. The prediction gets an exponent chosen from their actual magnitudes, not
//! from their exponents alone: a zero solution has exponent 0 whatever the scale of the others.

/// Largest |mantissa| the prediction produces: 2^29, the bound the SVU's vectors keep (the
/// wire allows 2^30; staying a factor two below it costs one bit of 30). The superposition
/// predictor and the live right-hand sides keep the same bound: this is its one home.
pub(crate) const TOP_BITS: i32 = 29;

/// Number of bits of |v| (0 for 0).
pub(crate) fn bits(v: u64) -> i32 {
    (u64::BITS - v.leading_zeros()) as i32
}

/// Number of bits of the largest magnitude in `v` (0 for a zero vector).
fn magnitude_bits(v: &[i32]) -> i32 {
    let max = v.iter().map(|&m| m.unsigned_abs()).max().unwrap_or(0);
    (u32::BITS - max.leading_zeros()) as i32
}

/// v·2^−s rounded to nearest, for any shift (a shift ≥ 63 leaves 0; negative shifts multiply,
/// and the callers keep those below the headroom they checked).
pub(crate) fn scale(v: i64, s: i32) -> i64 {
    match s {
        ..=-1 => v << (-s).min(62),
        0 => v,
        1..=62 => (v + (1 << (s - 1))) >> s,
        _ => 0,
    }
}

/// `scale(i64::from(v), s) as i32`, the low 32 bits of the rounded shift, in `i32` alone: a
/// pass that keeps only those bits of a sum of such terms (an `i32` result) need not form them
/// in `i64`, whose variable shifts take several instructions each on RV32. Rounding to nearest
/// is the floor plus the bit below the cut; left shifts of 32 or more, and right shifts of 32
/// or more of an `i32`, leave no low bits.
#[inline(always)]
pub(crate) fn scale_low(v: i32, s: i32) -> i32 {
    match s {
        -31..=-1 => v.wrapping_shl((-s) as u32),
        0 => v,
        1..=31 => (v >> s) + ((v >> (s - 1)) & 1),
        _ => 0,
    }
}

/// `scale(v, s) as i32` for an `i64` v below 2^62 in magnitude, from its two words: the same
/// low word without a 64-bit shift (see [`scale_low`]).
#[inline(always)]
pub(crate) fn scale_low_wide(v: i64, s: i32) -> i32 {
    let (lo, hi) = (v as u32, (v >> 32) as i32);
    match s {
        -31..=-1 => (lo as i32).wrapping_shl((-s) as u32),
        0 => lo as i32,
        1..=31 => {
            let low = (lo >> s) | ((hi as u32) << (32 - s));
            low.wrapping_add((lo >> (s - 1)) & 1) as i32
        }
        32 => hi.wrapping_add((lo >> 31) as i32),
        33..=62 => (hi >> (s - 32)).wrapping_add((hi >> (s - 33)) & 1),
        _ => 0,
    }
}

/// Overwrites `x` (u(t−1), exponent `e1`) with 2u(t−1) − u(t−2) (u(t−2) in `kept`, exponent
/// `e2`) and `kept` with u(t−1): afterwards `kept` holds what the next prediction needs. Returns
/// the exponents of the prediction now in `x`. Every mantissa written stays below 2^29.
pub fn extrapolate(x: &mut [i32], e1: i32, kept: &mut [i32], e2: i32) -> i32 {
    let (b1, b2) = (magnitude_bits(x), magnitude_bits(kept));
    // |2u(t−1)| < 2^(e1+b1+1) and |u(t−2)| < 2^(e2+b2), so the prediction stays below 2^(top+1).
    let top = match (b1, b2) {
        (0, 0) => {
            kept.fill(0);
            return 0;
        }
        (0, _) => e2 + b2,
        (_, 0) => e1 + b1 + 1,
        _ => (e1 + b1 + 1).max(e2 + b2),
    };
    let e = top + 1 - TOP_BITS;
    let (s1, s2) = (e - e1 - 1, e - e2);
    for (xi, ki) in x.iter_mut().zip(kept.iter_mut()) {
        let (a, c) = (*xi, *ki);
        let value = scale(i64::from(a), s1) - scale(i64::from(c), s2);
        // |value| ≤ 2^28 + 2^28 + 1 by the choice of e: it fits.
        *xi = value.clamp(-(1 << TOP_BITS), 1 << TOP_BITS) as i32;
        *ki = a;
    }
    e
}

#[cfg(test)]
mod tests {
    /// [`scale_low_wide`] is [`scale`]'s low 32 bits for every shift and `i64` values up to
    /// 2^62 in magnitude.
    #[test]
    fn scale_low_wide_is_the_low_word_of_scale() {
        let big = (1i64 << 62) - 1;
        let values = [
            0,
            1,
            -1,
            3,
            -3,
            big,
            -big,
            1 << 40,
            -(1 << 40) + 7,
            0x0123_4567_89ab_cdef,
        ];
        let spread = (0..3000i64).map(|k| (k - 1500) * 3_074_457_345_618_258 + k * 977);
        for v in values.into_iter().chain(spread) {
            for s in -80..80 {
                assert_eq!(
                    super::scale_low_wide(v, s),
                    super::scale(v, s) as i32,
                    "{v} {s}"
                );
            }
        }
    }

    /// [`scale_low`] is [`scale`]'s low 32 bits for every shift and the `i32` extremes.
    #[test]
    fn scale_low_is_the_low_word_of_scale() {
        let values = [
            0,
            1,
            -1,
            2,
            -2,
            3,
            -3,
            0x1234_5678,
            -0x1234_5679,
            (1 << 29) + 1,
            -(1 << 30) + 3,
            i32::MAX,
            i32::MIN,
            i32::MAX - 1,
            i32::MIN + 1,
        ];
        for v in values
            .into_iter()
            .chain((0..2000).map(|k| k * 1_073_741 - 1_073_741_000))
        {
            for s in -80..80 {
                assert_eq!(
                    super::scale_low(v, s),
                    super::scale(i64::from(v), s) as i32,
                    "{v} {s}"
                );
            }
        }
    }

    use super::*;

    fn value(m: &[i32], e: i32) -> Vec<f64> {
        m.iter().map(|&v| f64::from(v) * 2f64.powi(e)).collect()
    }

    #[test]
    fn a_straight_path_is_extrapolated_to_its_next_point() {
        // u(t) = t·w: u(2) from u(1) and u(0) with different exponents.
        let w = [3.0, -7.5, 0.25, 1e-3];
        let u1: Vec<i32> = w.iter().map(|v| (v * 2f64.powi(26)) as i32).collect();
        let u0: Vec<i32> = w.iter().map(|v| (0.5 * v * 2f64.powi(27)) as i32).collect();
        let (mut x, mut kept) = (u1.clone(), u0);
        let e = extrapolate(&mut x, -26, &mut kept, -27);
        for (got, want) in value(&x, e).iter().zip(w) {
            assert!((got - 1.5 * want).abs() < 1e-6, "{got} vs {}", 1.5 * want);
        }
        assert_eq!(kept, u1, "u(t−1) is kept for the next step");
        assert!(x.iter().all(|m| m.unsigned_abs() <= 1 << 29));
    }

    /// Asserts `got` equals `want` to 2^−27 of max |want| (the prediction keeps 29 bits).
    fn assert_close(got: &[f64], want: &[f64]) {
        let scale = want.iter().fold(0f64, |m, v| m.max(v.abs()));
        for (g, w) in got.iter().zip(want) {
            assert!(
                (g - w).abs() <= scale * 2f64.powi(-27),
                "{got:?} vs {want:?}"
            );
        }
    }

    #[test]
    fn zero_solutions_do_not_set_the_scale() {
        // u(t−2) = 0 with exponent 0 (what a zero right-hand side leaves): 2u(t−1).
        let (mut x, mut kept) = (vec![1 << 29, -(1 << 29), 5], vec![0; 3]);
        let e = extrapolate(&mut x, -60, &mut kept, 0);
        assert_close(&value(&x, e), &value(&[1 << 29, -(1 << 29), 5], -59));
        assert!(
            e < -50,
            "the exponent follows u(t−1), not the zero vector's 0"
        );
        // u(t−1) = 0: −u(t−2).
        let (mut x, mut kept) = (vec![0; 2], vec![-(1 << 29) + 1, 12]);
        let e = extrapolate(&mut x, 3, &mut kept, -40);
        assert_close(&value(&x, e), &value(&[(1 << 29) - 1, -12], -40));
        let (mut x, mut kept) = (vec![0; 2], vec![0; 2]);
        assert_eq!(extrapolate(&mut x, 9, &mut kept, -9), 0);
        assert_eq!(x, [0, 0]);
    }

    #[test]
    fn extreme_mantissas_stay_in_range() {
        let big = (1 << 30) - 1;
        for (e1, e2) in [(0, 0), (-30, 10), (10, -30), (-100, -100)] {
            let (mut x, mut kept) = (vec![big, -big, big], vec![-big, big, 1]);
            let e = extrapolate(&mut x, e1, &mut kept, e2);
            assert!(x.iter().all(|m| m.unsigned_abs() <= 1 << 29), "{x:?} e {e}");
            let want: Vec<f64> = value(&[big, -big, big], e1)
                .iter()
                .zip(value(&[-big, big, 1], e2))
                .map(|(a, c)| 2.0 * a - c)
                .collect();
            let scale = want.iter().fold(0f64, |m, v| m.max(v.abs()));
            for (got, want) in value(&x, e).iter().zip(&want) {
                assert!((got - want).abs() <= scale * 1e-8, "{got} vs {want}");
            }
        }
    }
}
