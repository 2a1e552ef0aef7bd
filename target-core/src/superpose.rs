//! The superposition predictor of live frames: a frame's CG starts from the previous frame's
//! solution plus the response of the linear model to the tool's change,
//! x_pred = x_prev + Σ_j a_j·G_j (+ the tool nodes' own displacements for a displacement
//! tool), where G_j is the response column `LiveStart` solved for tool node j and a_j the
//! change of node j's input scaled to that column (see `live_glue.rs`). The springs are
//! linear, so for an exact x_prev the prediction is exact up to rounding and CG has (almost)
//! nothing left to do, from the first, cold frame on; where the columns are not held the
//! frame falls back to [`crate::predict`]'s extrapolation.
//!
//! # Bounds
//!
//! Everything per node is integer. The coefficients a_j·2^e_j (e_j the column's exponent)
//! and the own terms share one exponent e_c, chosen so that the largest term |a_j|·max|g_j|
//! (g_j column j's mantissas) or own value is below 2^[`TERM_BITS`] = 2^55 at e_c: every
//! product m_j·g_i, |g_i| ≤ max|g_j|, is then below 2^55 (each term keeps 55 bits relative
//! to the largest, far more than the 29 written), and the at most [`MAX_TOOL_NODES`] = 8
//! products plus the own term of a node stay below 9·2^55 < 2^59: an `i64` holds the sum. The
//! bound B = Σ_j |m_j|·max|g_j| + max|own| (also < 2^59) sets the output exponent before the
//! pass, so the pass is a single one over n.

use deform_shared::live::MAX_TOOL_NODES;
use deform_shared::qformat::{block_exponent, ldexp};

use crate::predict::{bits, scale, TOP_BITS};

/// Bits of the largest term m_j·g (see the bounds in the module doc).
const TERM_BITS: i32 = 55;

/// One held response column: its exponent and its largest |mantissa|.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Column {
    pub exponent: i32,
    pub max: u32,
}

impl Column {
    /// Describes the column `g` (exponent `exponent`).
    pub fn of(g: &[i32], exponent: i32) -> Self {
        Column {
            exponent,
            max: g.iter().map(|v| v.unsigned_abs()).max().unwrap_or(0),
        }
    }
}

/// Adds Σ_j coeffs_j·G_j and the `own` terms (node, value) to `x`, whose exponent is `e_x`
/// (`None`: x is taken as zero and overwritten). `g` holds the columns back to back, n = x's
/// length each, described by `columns`. Returns x's new exponent, or `None` (x untouched) if
/// a coefficient is not finite.
pub fn superpose(
    x: &mut [i32],
    e_x: Option<i32>,
    g: &[i32],
    columns: &[Column],
    coeffs: &[f64],
    own: &[(u32, f64)],
) -> Option<i32> {
    let n = x.len();
    // The terms' real sizes, then one exponent that puts them all within TERM_BITS.
    let mut scaled = [0f64; MAX_TOOL_NODES];
    for ((s, c), col) in scaled.iter_mut().zip(coeffs).zip(columns) {
        *s = ldexp(*c, col.exponent);
    }
    let terms = || scaled.iter().chain(own.iter().map(|(_, v)| v));
    if !terms().all(|v| v.is_finite()) {
        return None;
    }
    // The largest term a_j·G_j (or own value), in real size.
    let sizes = scaled
        .iter()
        .zip(columns)
        .map(|(s, col)| s.abs() * f64::from(col.max));
    let tmax = sizes
        .chain(own.iter().map(|(_, v)| v.abs()))
        .fold(0f64, f64::max);
    if !tmax.is_finite() {
        return None;
    }
    let e_c = block_exponent(tmax) - (TERM_BITS - 30);
    let mant = |v: f64| {
        let r = ldexp(v, -e_c);
        (if r >= 0.0 { r + 0.5 } else { r - 0.5 }) as i64
    };
    let mut m = [0i64; MAX_TOOL_NODES];
    let mut bound = 0u64;
    for ((mj, s), col) in m.iter_mut().zip(&scaled).zip(columns) {
        if col.max != 0 {
            *mj = mant(*s);
            bound += mj.unsigned_abs() * u64::from(col.max);
        }
    }
    let own_max = own.iter().map(|(_, v)| mant(*v).unsigned_abs()).max();
    bound += own_max.unwrap_or(0);
    if bound == 0 {
        // Nothing moved (a direction the tool does not act in): x stays as it is.
        if e_x.is_none() {
            x.fill(0);
        }
        return Some(e_x.unwrap_or(0));
    }
    let x_top = match e_x {
        Some(e) => {
            let max = x.iter().map(|v| v.unsigned_abs()).max().unwrap_or(0);
            (max != 0).then(|| bits(u64::from(max)) + e)
        }
        None => None,
    };
    let acc_top = bits(bound) + e_c;
    let top = x_top.map_or(acc_top, |t| t.max(acc_top));
    // Two terms below 2^top each: the sum stays below 2^(top + 1) = 2^(e + 29).
    let e = top + 1 - TOP_BITS;
    let (sx, sa) = (e - e_x.unwrap_or(e), e - e_c);
    // Only the columns that move contribute.
    let mut live = [(0usize, 0i64); MAX_TOOL_NODES];
    let mut k = 0;
    for (j, &mj) in m.iter().enumerate().take(columns.len()) {
        if mj != 0 {
            live[k] = (j, mj);
            k += 1;
        }
    }
    let live = &live[..k];
    for (i, xi) in x.iter_mut().enumerate() {
        let mut acc = 0i64;
        for &(j, mj) in live {
            let gi = g.get(j * n + i).copied().unwrap_or(0);
            acc += mj * i64::from(gi);
        }
        let base = if e_x.is_some() {
            scale(i64::from(*xi), sx)
        } else {
            0
        };
        *xi = (base + scale(acc, sa)).clamp(-(1 << TOP_BITS), 1 << TOP_BITS) as i32;
    }
    for &(node, v) in own {
        if let Some(xi) = x.get_mut(node as usize) {
            let add = scale(mant(v), sa);
            *xi = (i64::from(*xi) + add).clamp(-(1 << TOP_BITS), 1 << TOP_BITS) as i32;
        }
    }
    Some(e)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn value(m: &[i32], e: i32) -> Vec<f64> {
        m.iter().map(|&v| ldexp(f64::from(v), e)).collect()
    }

    #[test]
    fn the_prediction_is_the_superposed_sum() {
        let n = 5;
        let g0 = [1 << 28, -(1 << 27), 3, 0, 12345];
        let g1 = [-7, 1 << 29, 0, -(1 << 20), 99];
        let g: Vec<i32> = g0.iter().chain(&g1).copied().collect();
        let columns = [Column::of(&g0, -30), Column::of(&g1, -45)];
        let coeffs = [0.75, -3e4];
        let own = [(3u32, 0.125)];
        let x_prev = [100, -(1 << 29), 7, 0, 1];
        let mut x = x_prev;
        let e = superpose(&mut x, Some(-20), &g, &columns, &coeffs, &own).unwrap();
        let got = value(&x, e);
        let mut want = value(&x_prev, -20);
        for i in 0..n {
            want[i] +=
                coeffs[0] * ldexp(f64::from(g0[i]), -30) + coeffs[1] * ldexp(f64::from(g1[i]), -45);
        }
        want[3] += 0.125;
        let top = want.iter().fold(0f64, |m, v| m.max(v.abs()));
        for (a, b) in got.iter().zip(&want) {
            assert!((a - b).abs() <= top * 1e-6, "{got:?} vs {want:?}");
        }
        assert!(x.iter().all(|v| v.unsigned_abs() <= 1 << 29));
    }

    #[test]
    fn a_zero_start_and_extreme_inputs_stay_in_range() {
        let g = [i32::MAX, i32::MIN + 1, i32::MAX, i32::MIN + 1];
        let columns = [Column::of(&g[..2], 0), Column::of(&g[2..], 0)];
        let mut x = [5, 5];
        let e = superpose(&mut x, None, &g, &columns, &[1e30, 1e30], &[]).unwrap();
        assert!(x.iter().all(|v| v.unsigned_abs() <= 1 << 29));
        let want = 2e30 * f64::from(i32::MAX);
        assert!((value(&x, e)[0] - want).abs() <= want * 1e-6);
        let mut x = [5, 5];
        assert_eq!(
            superpose(&mut x, Some(3), &g, &columns, &[0.0, f64::NAN], &[]),
            None
        );
        assert_eq!(
            superpose(&mut x, None, &g, &columns, &[0.0, 0.0], &[]),
            Some(0)
        );
        assert_eq!(x, [0, 0]);
        // No change: x and its exponent stay.
        let mut x = [5, -7];
        assert_eq!(
            superpose(&mut x, Some(-9), &g, &columns, &[0.0, 0.0], &[]),
            Some(-9)
        );
        assert_eq!(x, [5, -7]);
    }
}
