//! The superposition predictor of live frames, and the residual estimate that lets a frame skip
//! the exact r₀ = b − K·x₀ pass.
//!
//! # The prediction
//!
//! A frame's CG starts from the previous frame's solution plus the response of the linear model
//! to the tool's change, x₀ = x_prev + Σ_j a_j·G_j (+ the tool nodes' own displacements for a
//! displacement tool), where G_j is the response column `LiveStart` solved for tool node j and
//! a_j the change of node j's input scaled to that column (see `live_glue.rs`). The springs are
//! linear, so for an exact x_prev the prediction is exact up to rounding and CG has (almost)
//! nothing left to do, from the first, cold frame on; where the columns are not held the frame
//! falls back to [`crate::predict`]'s extrapolation.
//!
//! # The residual estimate (issue 19)
//!
//! `LiveStart` also keeps each column's own residual ρ_j = c_j − K·G_j (c_j the column's
//! right-hand side: K_f,t_j for a displacement tool, the unit load e_j for a force tool),
//! formed by an exact MVU pass. The frame's right-hand side changes by Σ_j a_j·c_j (up to
//! rounding) and K·x₀ by Σ_j a_j·(c_j − ρ_j), so
//!
//! r₀ = b − K·x₀ = r_prev + Σ_j a_j·ρ_j + (rounding),
//!
//! an O(n·columns) pass instead of an MVU pass. The rounding (of x₀, of b, of the tool inputs,
//! of the stored ρ_j and of r₀ itself) is bounded rigorously ([`ErrorBound`]) and carried from
//! frame to frame; the frame is accepted without any MVU pass only where the estimate *plus*
//! that bound is within the tolerance ([`verdict`]), so no frame is accepted above it. An exact
//! pass (every [`EXACT_EVERY`] frames, or when the estimate is near the tolerance) resets the
//! bound.
//!
//! # The integer pass
//!
//! Everything per node is integer and shaped like the SVU's updates ([`crate::svu`]): each
//! column's term is a 32-bit multiplier times the column's mantissas normalised into
//! [2^30, 2^31), the product's high word rounded to nearest, and the old vector's term a
//! floored shift. The new exponent keeps the bound |v| + Σ_j |a_j|·max|col_j| + max|own| below
//! 2^29 units, so every mantissa written stays below 2^30, as the MVU needs. Hart 0 plans each
//! direction once per frame ([`Terms::plan`], O(columns)); the pass over n is split over the
//! harts ([`apply_share`]), and hart 0 adds the own values at the tool nodes.

use deform_shared::live::MAX_TOOL_NODES;
use deform_shared::qformat::ldexp;

use crate::svu::{
    bound_of, magnitude_bits, magnitude_bound, normalising_shift, sum_squares, term, Block, Scalar,
    Shift, Term, BOUND_BITS,
};

/// Frames a residual estimate may be carried over before an exact pass renews it.
pub const EXACT_EVERY: u32 = 16;

/// One held column (a response G_j, or a residual ρ_j): its exponent and largest |mantissa|.
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

/// The planned update of one vector of one direction, v ← v·2^(e_v − e) + Σ_j a_j·col_j
/// (+ own values at single nodes) at the new exponent e, each column's term an SVU [`Term`]
/// rounded to nearest (`mulh` of a 32-bit multiplier and the column's normalised mantissas)
/// and the old vector's a floored [`Shift`], as in [`crate::svu`]; the exponent is chosen, as
/// there, so that the bound |v| + Σ_j |a_j|·max|col_j| + max|own| stays below 2^29 units.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Terms {
    /// The vector's new exponent.
    pub e: i32,
    /// The old vector's shift, or `None` where it is taken as zero (and overwritten).
    keep: Option<Shift>,
    /// The columns that move: (index, term), `count` of them.
    live: [(usize, Term); MAX_TOOL_NODES],
    count: usize,
}

impl Terms {
    /// Plans the update of a vector with exponent and bound `prev` (`None`: taken as zero) by
    /// Σ_j coeffs_j·(column j) and the `own` values (node, value). Returns `None` if a
    /// coefficient is not finite, and `Some((terms, own))` otherwise, the own values as
    /// (node, mantissa at the new exponent); nothing changes where `!terms.moves()` and no
    /// own value is left.
    pub fn plan(
        prev: Option<(i32, u64)>,
        columns: &[Column],
        coeffs: &[f64],
        own: &[(u32, f64)],
    ) -> Option<(Terms, heapless::Vec<(u32, i64), MAX_TOOL_NODES>)> {
        let finite = coeffs.iter().chain(own.iter().map(|(_, v)| v));
        if !finite.clone().all(|v| v.is_finite()) {
            return None;
        }
        let mut plan = Terms {
            e: prev.map_or(0, |(e, _)| e),
            keep: prev.map(|_| Shift::default()),
            ..Terms::default()
        };
        let still = |v: &f64| *v == 0.0;
        if coeffs.iter().all(still) && own.iter().all(|(_, v)| still(v)) && prev.is_some() {
            // Nothing moves (a direction the tool does not act in): the vector stays.
            return Some((plan, heapless::Vec::new()));
        }
        // Upper bounds of every part, as (mantissa, exponent): the old vector, the columns'
        // terms and the largest own value.
        let mut parts: heapless::Vec<(u32, i32), { MAX_TOOL_NODES + 2 }> = heapless::Vec::new();
        if let Some((e_v, bound)) = prev.filter(|&(_, b)| b != 0) {
            let _ = parts.push((bound.min(u64::from(u32::MAX)) as u32, e_v));
        }
        let blocks = columns.iter().map(|c| Block {
            e: c.exponent,
            bound: u64::from(c.max),
        });
        for (c, block) in coeffs.iter().zip(blocks.clone()) {
            let _ = parts.push(magnitude_bound(Scalar::of_f64(*c), block));
        }
        let own_max = own.iter().map(|(_, v)| v.abs()).fold(0f64, f64::max);
        let unit = Block { e: 0, bound: 1 };
        let _ = parts.push(magnitude_bound(Scalar::of_f64(own_max), unit));
        let Some(e) = exponent_for(&parts) else {
            // Everything is zero: so is the vector.
            plan.keep = None;
            return Some((plan, heapless::Vec::new()));
        };
        plan.e = e;
        plan.keep = prev.map(|(e_v, _)| Shift::by(e_v - e));
        let mut sat = 0;
        for (j, (c, block)) in coeffs.iter().zip(blocks).enumerate() {
            let c = Scalar::of_f64(*c);
            if c.m == 0 || block.bound == 0 {
                continue;
            }
            let t = term(c, block, normalising_shift(block.bound), e, &mut sat);
            if t.mult != 0 {
                plan.live[plan.count] = (j, t);
                plan.count += 1;
            }
        }
        if sat != 0 {
            return None;
        }
        let own_at_e = own
            .iter()
            .filter(|(_, v)| *v != 0.0)
            .map(|&(node, v)| {
                let r = ldexp(v, -e);
                (node, (if r >= 0.0 { r + 0.5 } else { r - 0.5 }) as i64)
            })
            .collect();
        Some((plan, own_at_e))
    }

    /// The update that sets a vector to zero.
    pub fn zero() -> Terms {
        Terms::default()
    }

    /// Whether the update changes anything besides the own values.
    pub fn moves(&self) -> bool {
        self.count != 0 || self.keep != Some(Shift::default())
    }

    /// A bound, in units of 2^e, on the rounding of one element: below 1 for the old value's
    /// floored shift where it shifts right, ¾ per column term (½ for its rounding, ¼ for its
    /// multiplier's) and ½ for an own value.
    pub fn rounding_units(&self) -> f64 {
        let keep = match self.keep {
            Some(s) if s.right > 0 => 1.0,
            _ => 0.0,
        };
        keep + 0.75 * self.count as f64 + 0.5
    }

    /// Applies the update to `v`, whose column values are `col(j)` (the slices of the same
    /// elements); returns the OR of the new magnitudes. One loop per column count, the usual
    /// one column without an inner loop.
    fn apply<'c, T: Copy + 'c>(&self, v: &mut [i32], col: impl Fn(usize) -> &'c [T]) -> u32
    where
        i32: From<T>,
    {
        let keep = |x: i32| self.keep.map_or(0, |s| s.apply(x));
        let mut or = 0u32;
        match self.count {
            0 => {
                for vi in v.iter_mut() {
                    *vi = keep(*vi);
                    or |= magnitude_bits(*vi);
                }
            }
            1 => {
                let (j, t) = self.live[0];
                for (vi, &g) in v.iter_mut().zip(col(j)) {
                    *vi = keep(*vi).wrapping_add(t.apply_rounded(i32::from(g)));
                    or |= magnitude_bits(*vi);
                }
            }
            _ => {
                for (i, vi) in v.iter_mut().enumerate() {
                    let mut z = keep(*vi);
                    for &(j, t) in &self.live[..self.count] {
                        let g = col(j).get(i).copied().map_or(0, i32::from);
                        z = z.wrapping_add(t.apply_rounded(g));
                    }
                    *vi = z;
                    or |= magnitude_bits(z);
                }
            }
        }
        or
    }
}

/// The smallest exponent that keeps the sum of the upper bounds `parts` (mantissa, exponent)
/// below 2^29 units, or `None` if they are all zero: as [`crate::svu::Lin::new`] for any number
/// of parts, each aligned to the largest exponent and rounded up.
pub(crate) fn exponent_for(parts: &[(u32, i32)]) -> Option<i32> {
    let e_hi = parts.iter().filter(|p| p.0 != 0).map(|p| p.1).max()?;
    let sum: u64 = parts
        .iter()
        .filter(|p| p.0 != 0)
        .map(|&(m, e)| match (e_hi - e) as u32 {
            0 => u64::from(m),
            gap @ 1..=31 => u64::from(m >> gap) + 1,
            _ => 1,
        })
        .sum();
    let bits = (u64::BITS - sum.leading_zeros()) as i32;
    Some(bits + e_hi - BOUND_BITS)
}

/// What one hart's share of a frame's pass measured.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ShareSums {
    /// OR of |x| over the share (the new x).
    pub x_or: u32,
    /// Σr² (exact) and the OR of |r| over the share (the estimate).
    pub rr: u128,
    pub r_or: u32,
    /// Σb² over the share (exact).
    pub bb: u128,
}

/// One hart's share `lo..lo + x.len()` of one direction's frame: x by `xt` from the response
/// columns `g`, r by `rt` from the residual columns `rho` (if given), each n long and back to
/// back, and the sums the verdict needs. The own terms are not applied here.
#[allow(clippy::too_many_arguments)]
pub fn apply_share(
    x: &mut [i32],
    r: &mut [i32],
    b: &[i32],
    lo: usize,
    n: usize,
    g: &[i32],
    rho: &[i16],
    xt: &Terms,
    rt: Option<&Terms>,
) -> ShareSums {
    let hi = lo + x.len();
    let mut out = ShareSums {
        x_or: xt.apply(x, |j| g.get(j * n + lo..j * n + hi).unwrap_or(&[])),
        ..ShareSums::default()
    };
    if let Some(rt) = rt {
        out.r_or = rt.apply(r, |j| rho.get(j * n + lo..j * n + hi).unwrap_or(&[]));
        out.rr = sum_squares(r);
    }
    out.bb = sum_squares(b);
    out
}

/// What a frame may do with its residual estimate ([`verdict`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Verdict {
    /// The estimate plus its error bound is within the tolerance: x₀ is the frame's solution.
    Accept,
    /// The estimate is at least twice the tolerance: CG starts from it (and verifies its end
    /// against b − K·x, as every solve does), whatever its error bound.
    Iterate,
    /// Near the tolerance, or the bound is unknown or old: form r₀ by an exact MVU pass.
    #[default]
    Exact,
}

/// The verdict for an estimate with Σr² = `rr` (exponent `e_r`) and error bound `error` (real
/// units) against the tolerance `tol` of a right-hand side with Σb² = `bb` (exponent `e_b`).
/// Accepting needs ‖r̃‖ ≤ ¾·tol·‖b‖ and error ≤ ¼·tol·‖b‖, so ‖r₀‖ ≤ ‖r̃‖ + error ≤ tol·‖b‖
/// (a margin of 2^−40 absorbs the rounding of the `f64` comparisons).
pub fn verdict(rr: u128, e_r: i32, bb: u128, e_b: i32, tol: f64, error: f64) -> Verdict {
    let r2 = ldexp(rr as f64, 2 * e_r);
    let b2 = ldexp(bb as f64, 2 * e_b) * tol * tol;
    let margin = 1.0 - ldexp(1.0, -40);
    if bb == 0 {
        return Verdict::Exact;
    }
    if r2 >= 4.0 * b2 {
        // Far from converged whatever the bound: CG's own end check makes it safe.
        Verdict::Iterate
    } else if error.is_finite()
        && r2 * 16.0 <= 9.0 * b2 * margin
        && error * error * 16.0 <= b2 * margin
    {
        Verdict::Accept
    } else {
        Verdict::Exact
    }
}

/// The error bound of a residual estimate, in real units (an upper bound on ‖r₀ − r̃‖₂ where r₀
/// is the exact residual of the mantissas the target holds), built term by term.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ErrorBound {
    pub total: f64,
}

impl ErrorBound {
    /// The bound of a residual formed by an exact MVU pass at exponent `e_r` over n elements.
    pub fn exact(n: usize, e_r: i32) -> ErrorBound {
        ErrorBound {
            total: ldexp(crate::cg::EXACT_PASS_ERROR * ceil_sqrt(n), e_r),
        }
    }

    /// `self` carried over one frame, which adds: ‖K·δ‖ for x's rounding (`x_units` of 2^e_x
    /// per element, ‖K‖∞ = `k_inf` in real units), the estimate's own rounding (`r_units` of
    /// 2^e_r per element), the right-hand side's (`b_units` of 2^e_b on `b_rows` rows), the tool
    /// inputs' (`input` real units times `input_weight`), and the residual columns' (Σ_j
    /// |a_j|·their stored error).
    #[allow(clippy::too_many_arguments)]
    pub fn carried(
        self,
        n: usize,
        k_inf: f64,
        (x_units, e_x): (f64, i32),
        (r_units, e_r): (f64, i32),
        (b_units, e_b, b_rows): (f64, i32, usize),
        (input, input_weight): (f64, f64),
        columns: f64,
    ) -> ErrorBound {
        let root_n = ceil_sqrt(n);
        let terms = [
            k_inf * root_n * ldexp(x_units, e_x),
            root_n * ldexp(r_units, e_r),
            ceil_sqrt(b_rows) * ldexp(b_units, e_b),
            input * input_weight,
            columns,
        ];
        let added: f64 = terms.iter().sum();
        // Each f64 operation above rounds by at most 2^−53 relatively: 2^−40 covers them.
        ErrorBound {
            total: (self.total + added) * (1.0 + ldexp(1.0, -40)),
        }
    }
}

/// An upper bound on √v for v ≥ 0: the correctly rounded root ([`crate::cg::sqrt`], in
/// integers) is within half an ulp of √v, so the next float up is at or above it. It replaced
/// four Newton steps in soft f64 (four divisions, twice a frame).
pub fn sqrt_up(v: f64) -> f64 {
    if v <= 0.0 || !v.is_finite() {
        return v.max(0.0);
    }
    crate::cg::sqrt(v).next_up()
}

/// ⌈√k⌉ for an integer k, by integer Newton steps (the √n of the error bounds, once per frame).
pub fn ceil_sqrt(k: usize) -> f64 {
    ceil_sqrt_int(k) as f64
}

/// ⌈√k⌉ in integers ([`ceil_sqrt`]), for the bounds kept in integers ([`crate::upper`]).
pub fn ceil_sqrt_int(k: usize) -> usize {
    if k < 2 {
        return k;
    }
    // Newton from above on integers converges to ⌊√k⌋.
    let mut g = k;
    loop {
        let next = (g + k / g) / 2;
        if next >= g {
            break;
        }
        g = next;
    }
    if g * g < k {
        g + 1
    } else {
        g
    }
}

/// The bound of a vector's maximum from the OR of its magnitudes (0 for a zero vector).
pub fn bound_from_or(or: u32) -> u64 {
    if or == 0 {
        0
    } else {
        bound_of(or)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn value(m: &[i32], e: i32) -> Vec<f64> {
        m.iter().map(|&v| ldexp(f64::from(v), e)).collect()
    }

    /// The whole pass on one share, own values applied after, as the session does.
    fn superpose(
        x: &mut [i32],
        prev: Option<(i32, u64)>,
        g: &[i32],
        columns: &[Column],
        coeffs: &[f64],
        own: &[(u32, f64)],
    ) -> Option<i32> {
        let (terms, own) = Terms::plan(prev, columns, coeffs, own)?;
        if !terms.moves() && own.is_empty() {
            return Some(terms.e);
        }
        assert!(own.iter().all(|(_, v)| v.unsigned_abs() < 1 << 30));
        let n = x.len();
        let mut r = vec![0; n];
        let b = vec![0; n];
        apply_share(x, &mut r, &b, 0, n, g, &[], &terms, None);
        for (node, v) in own {
            let xi = &mut x[node as usize];
            *xi = (i64::from(*xi) + v) as i32;
        }
        Some(terms.e)
    }

    fn bound(x: &[i32]) -> u64 {
        bound_from_or(x.iter().fold(0, |o, &v| o | magnitude_bits(v)))
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
        let prev = Some((-20, bound(&x_prev)));
        let e = superpose(&mut x, prev, &g, &columns, &coeffs, &own).unwrap();
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
        assert!(x.iter().all(|v| v.unsigned_abs() < 1 << 30));
    }

    #[test]
    fn a_zero_start_and_extreme_inputs_stay_in_range() {
        let g = [i32::MAX, i32::MIN + 1, i32::MAX, i32::MIN + 1];
        let columns = [Column::of(&g[..2], 0), Column::of(&g[2..], 0)];
        let mut x = [5, 5];
        let e = superpose(&mut x, None, &g, &columns, &[1e30, 1e30], &[]).unwrap();
        assert!(x.iter().all(|v| v.unsigned_abs() < 1 << 30));
        let want = 2e30 * f64::from(i32::MAX);
        assert!((value(&x, e)[0] - want).abs() <= want * 1e-6);
        assert!(Terms::plan(Some((3, 5)), &columns, &[0.0, f64::NAN], &[]).is_none());
        // No change: nothing to do, the exponent stays.
        let (t, own) = Terms::plan(Some((-9, 8)), &columns, &[0.0, 0.0], &[]).unwrap();
        assert!(!t.moves() && own.is_empty());
        assert_eq!(t.e, -9);
    }

    #[test]
    fn the_estimate_adds_the_residual_columns() {
        // r̃ = r_prev + Σ a_j·ρ_j on i16 residual columns, every share the same as one pass.
        let n = 9;
        let rho: Vec<i16> = (0..2 * n)
            .map(|i| (i as i16 * 1237) % 3001 - 1500)
            .collect();
        let res = [
            Column {
                exponent: -40,
                max: 1500,
            },
            Column {
                exponent: -38,
                max: 1500,
            },
        ];
        let coeffs = [0.5, -2.0];
        let r_prev: Vec<i32> = (0..n).map(|i| (i as i32 - 4) * 100_000).collect();
        let (rt, _) = Terms::plan(Some((-45, bound(&r_prev))), &res, &coeffs, &[]).unwrap();
        let mut whole = r_prev.clone();
        let mut x = vec![0; n];
        let b = vec![3; n];
        let xt = Terms::plan(Some((0, 0)), &[], &[], &[]).unwrap().0;
        let one = apply_share(&mut x, &mut whole, &b, 0, n, &[], &rho, &xt, Some(&rt));
        let mut split = r_prev.clone();
        let (lo, hi) = split.split_at_mut(4);
        let a = apply_share(&mut x[..4], lo, &b[..4], 0, n, &[], &rho, &xt, Some(&rt));
        let c = apply_share(&mut x[4..], hi, &b[4..], 4, n, &[], &rho, &xt, Some(&rt));
        assert_eq!(whole, split);
        assert_eq!(one.rr, a.rr + c.rr);
        assert_eq!(one.bb, 9 * 9);
        for i in 0..n {
            let want = ldexp(f64::from(r_prev[i]), -45) + 0.5 * ldexp(f64::from(rho[i]), -40)
                - 2.0 * ldexp(f64::from(rho[n + i]), -38);
            let got = ldexp(f64::from(whole[i]), rt.e);
            assert!(
                (got - want).abs() <= ldexp(rt.rounding_units(), rt.e),
                "{i}"
            );
        }
    }

    #[test]
    fn the_verdict_never_accepts_above_the_tolerance() {
        // ‖b‖ = 1 (Σb² = 2^40 at 2^−20), tol 1e-3.
        let (bb, e_b, tol) = (1u128 << 40, -20, 1e-3);
        for rr_scale in [0.1f64, 0.5, 0.7, 0.74, 0.76, 0.9, 1.0, 1.5, 1.9, 2.1, 10.0] {
            for error in [0.0, 1e-5, 2.4e-4, 2.6e-4, 1e-3, f64::INFINITY] {
                // ‖r̃‖ = rr_scale·tol
                let r = rr_scale * tol;
                let rr = (r * r * ldexp(1.0, 80)) as u128;
                let v = verdict(rr, -40, bb, e_b, tol, error);
                if v == Verdict::Accept {
                    assert!(r + error <= tol, "{rr_scale} {error}");
                }
                if v == Verdict::Iterate {
                    assert!(r >= 2.0 * tol * (1.0 - 1e-9));
                }
            }
        }
        assert_eq!(verdict(0, 0, 0, 0, 1e-3, 0.0), Verdict::Exact);
    }

    #[test]
    fn ceil_sqrt_rounds_up() {
        for k in 0..3000usize {
            let s = ceil_sqrt(k) as usize;
            assert!(s * s >= k && (s == 0 || (s - 1) * (s - 1) < k), "{k}");
        }
    }

    #[test]
    fn sqrt_up_is_an_upper_bound() {
        let mut v = 1e-310_f64;
        let mut values = vec![0.0, 1e-300, 0.25, 2.0, 3.0, 512.0, 65536.0, 1e300, f64::MAX];
        while v < 1e300 {
            values.push(v);
            v *= 1.618_033_988_7;
        }
        for v in values {
            let s = sqrt_up(v);
            // Above √v (checked exactly: s² rounded to nearest may fall below v when s is
            // at most √v, so s's predecessor must be below √v), and within two ulps of it.
            assert!(s >= v.sqrt(), "{v}");
            assert!(s.next_down() <= v.sqrt() || v == 0.0, "{v}");
            assert!(s <= v.sqrt().next_up().next_up() || v == 0.0, "{v}");
        }
        assert_eq!(sqrt_up(-1.0), 0.0);
    }
}
