use super::*;
use crate::cg::{drift_of_exact_pass, drift_of_update, proves_tolerance};
use crate::dynamics::{start_drift, History};
use crate::svu::Block;
use deform_shared::qformat::ldexp;

use crate::test_rng::Rng;

/// The upper-bound tests' draws beyond [`Rng`]'s own.
trait Draws {
    fn mantissa(&mut self) -> u64;
    fn exponent(&mut self, span: i32) -> i32;
}

impl Draws for Rng {
    /// A mantissa: random widths, and the extremes (0, 1, powers of two and their
    /// neighbours, all ones).
    fn mantissa(&mut self) -> u64 {
        const EDGES: [u64; 9] = [
            0,
            1,
            2,
            (1 << 31) - 1,
            1 << 31,
            (1 << 32) - 1,
            1 << 32,
            (1 << 33) + 1,
            u64::MAX,
        ];
        if self.below(4) == 0 {
            EDGES[self.below(EDGES.len() as u64) as usize]
        } else {
            self.next() >> self.below(64)
        }
    }

    fn exponent(&mut self, span: i32) -> i32 {
        self.below(2 * span as u64 + 1) as i32 - span
    }
}

/// `u`'s value in units of 2^`base` (exact: u's exponent is at least `base` and within 90 of it).
fn units(u: Upper, base: i32) -> u128 {
    u128::from(u.m) << (u.e - base)
}

/// Every operation's result is at least the exact value and within 2^−30 of it (relatively),
/// over random and extreme mantissas and exponents.
#[test]
fn every_operation_rounds_up_and_stays_close() {
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    for case in 0..200_000 {
        let (ma, ea) = (rng.mantissa(), rng.exponent(40));
        let (mb, eb) = (rng.mantissa(), rng.exponent(40));
        let (a, b) = (Upper::new(ma, ea), Upper::new(mb, eb));
        // new: m·2^e ≤ a < m·2^e·(1 + 2^−30).
        if ma != 0 {
            let base = a.e.min(ea);
            let (got, exact) = (units(a, base), u128::from(ma) << (ea - base));
            assert!(got >= exact && got - exact <= got >> 30, "{case}");
        } else {
            assert_eq!(a, Upper::ZERO);
        }
        // add, where both fit 2^−(lowest exponent) in a u128.
        let s = a.plus(b);
        if a.m != 0 && b.m != 0 && (a.e - b.e).abs() <= 60 {
            let base = a.e.min(b.e);
            let exact = units(a, base) + units(b, base);
            let got = units(s, base);
            assert!(got >= exact && got - exact <= exact >> 30, "{case}: add");
        } else if a.m != 0 && b.m != 0 {
            let hi = if a.e > b.e { a } else { b };
            assert!(s.e >= hi.e, "{case}: add far");
            let got = units(s, hi.e);
            assert!(got > u128::from(hi.m) && got - u128::from(hi.m) <= got >> 30);
        } else {
            assert_eq!(s, if a.m == 0 { b } else { a });
        }
        // mul.
        let p = a.times(b);
        if a.m != 0 && b.m != 0 {
            let exact = u128::from(a.m) * u128::from(b.m);
            let got = units(p, a.e + b.e);
            assert!(got >= exact && got - exact <= exact >> 30, "{case}: mul");
        } else {
            assert_eq!(p, Upper::ZERO);
        }
        // wide (a sum of squares) and its lower twin.
        let w = (u128::from(rng.mantissa()) << rng.below(64)) | u128::from(rng.next() & 7);
        let (up, down) = (Upper::wide(w, ea), Lower::wide(w, ea));
        if w != 0 {
            let base = ea.min(up.e).min(down.e);
            let got_up = units(up, base);
            let got_down = u128::from(down.m) << (down.e - base);
            let w = w << (ea - base);
            assert!(got_down <= w && w <= got_up, "{case}: wide");
            assert!(got_up - got_down <= got_up >> 30, "{case}: wide, close");
            assert_eq!(up.at_most(down), got_up == w, "{case}: at_most");
        }
    }
}

/// `small` is `new` for the unit counts it takes, at any exponent.
#[test]
fn small_counts_are_exact() {
    for k in 0..20 {
        for e in [
            -LIMIT as i32 - 40,
            -2000,
            -64,
            -1,
            0,
            1,
            63,
            2000,
            LIMIT as i32 + 40,
        ] {
            assert_eq!(Upper::small(k, e), Upper::new(k, e), "{k} {e}");
        }
    }
}

/// f64 conversions bound from the right side, at the extremes of f64 as well.
#[test]
fn f64_conversions_bound_from_their_side() {
    let mut rng = Rng(12345);
    let mut values = vec![
        0.0,
        5e-324,
        1e-310,
        f64::MIN_POSITIVE,
        1e-5,
        1.0,
        3.0,
        1e300,
    ];
    values.extend((0..10_000).map(|_| f64::from_bits(rng.next() >> 2)));
    for x in values
        .into_iter()
        .filter(|x| x.is_finite() && x.abs() < 1e300)
    {
        let up = Upper::from_f64(x);
        let down = Lower::from_f64(x);
        let (m, e) = f64_parts(x);
        if m != 0 && e > -1000 {
            assert!(up.to_f64() >= x, "{x:e}");
            assert!(ldexp(down.m as f64, down.e) <= x, "{x:e}");
        }
    }
    assert!(!Upper::from_f64(f64::NAN).is_finite());
    assert!(!Upper::from_f64(-1.0).is_finite());
    assert_eq!(Lower::from_f64(f64::INFINITY).m, 0);
    assert!(
        !Upper::new(1, i32::MAX - 1).is_finite() && !Upper::INFINITE.plus(Upper::ZERO).is_finite()
    );
    assert!(Upper::new(1, -2_000_000).to_f64() >= 0.0 && Upper::new(1, -2_000_000).m > 0);
}

/// The old soft-f64 bounds (session 6), kept here as the reference the integer ones must not
/// fall below.
mod f64_reference {
    use deform_shared::qformat::ldexp;

    const UP: f64 = 1.0 + 1.0 / (1u64 << 40) as f64;

    pub fn drift_of_update(
        root_n: f64,
        a_inf: f64,
        (r_units, e_r): (f64, i32),
        (x_units, e_x): (f64, i32),
    ) -> f64 {
        root_n * (ldexp(r_units, e_r) + a_inf * ldexp(x_units, e_x)) * UP
    }

    /// `start_drift` with the history's d₀ error, r₋₁f's drift and Δv's exponent spelt out.
    #[allow(clippy::too_many_arguments)]
    pub fn start_drift(
        root_n: f64,
        s_inf: f64,
        (e_d, e): (i32, i32),
        e0: f64,
        extrapolated: Option<(f64, f64, i32, i32, f64)>,
    ) -> f64 {
        let d1 = ldexp(1.0, e_d);
        let bound = match extrapolated {
            None => e0 + root_n * (d1 + ldexp(1.0, e)),
            Some((d0_err, r1_drift, dv_e, e_x, a_units)) => {
                let x_err = ldexp(1.0, dv_e) + ldexp(a_units, e_x);
                2.0 * e0 + r1_drift + root_n * (d1 + d0_err + ldexp(2.0, e) + s_inf * x_err)
            }
        };
        bound * UP
    }
}

/// Random operands for the bounds: the exponents the solve sees (mantissa exponents of 2^±60
/// around a real scale) and ‖A‖∞, √n and carried drifts from tiny to huge.
fn operand(rng: &mut Rng) -> (Upper, f64) {
    let u = Upper::new(rng.mantissa() | 1, rng.exponent(80));
    (u, u.to_f64())
}

/// The integer bounds are never below the soft-f64 ones they replace (which exceed the exact
/// quantities by at most 2^−40 relatively, so 1 − 2^−39 of them is below the exact value): the
/// drift of an update, of an exact pass, the start's drift both ways, and the tolerance test
/// proves nothing the f64 one would not have.
#[test]
fn the_integer_bounds_are_at_least_the_f64_ones() {
    let mut rng = Rng(0xdead_beef_1234_5678);
    let slack = 1.0 - ldexp(1.0, -39);
    for case in 0..50_000 {
        let (root_n, root_f) = {
            let n = 1 + rng.below(1 << 20) as usize;
            let r = crate::superpose::ceil_sqrt_int(n) as u64;
            (Upper::new(r, 0), r as f64)
        };
        let (a_inf, a_f) = operand(&mut rng);
        let (r_h, x_h) = (2 + rng.below(4), 2 + rng.below(3));
        let (e_r, e_x) = (rng.exponent(60), rng.exponent(60));
        let new = drift_of_update(root_n, a_inf, (r_h, e_r), (x_h, e_x)).to_f64();
        let old = f64_reference::drift_of_update(
            root_f,
            a_f,
            (r_h as f64 / 2.0, e_r),
            (x_h as f64 / 2.0, e_x),
        );
        assert!(
            new >= old * slack && new <= old * (1.0 + 1e-8),
            "{case}: {new:e} {old:e}"
        );
        let exact_pass = drift_of_exact_pass(root_n, e_r).to_f64();
        assert!(exact_pass >= root_f * ldexp(2.0, e_r), "{case}");

        let (e0, e0_f) = operand(&mut rng);
        let (d0_err, d0_f) = operand(&mut rng);
        let (r1, r1_f) = operand(&mut rng);
        let (e_d, e) = (rng.exponent(60), rng.exponent(60));
        let dv = Block {
            e: rng.exponent(60),
            bound: 0,
        };
        let h = History {
            dv,
            d0: dv,
            r1: dv,
            d0_err,
            r1_drift: r1,
        };
        let a_h = 2 + 2 * rng.below(2);
        let plain = start_drift(root_n, a_inf, (e_d, e), e0, None).to_f64();
        let plain_f = f64_reference::start_drift(root_f, a_f, (e_d, e), e0_f, None);
        assert!(
            plain >= plain_f * slack && plain <= plain_f * (1.0 + 1e-8),
            "{case}"
        );
        let ext = start_drift(root_n, a_inf, (e_d, e), e0, Some((&h, e_x, a_h))).to_f64();
        let ext_f = f64_reference::start_drift(
            root_f,
            a_f,
            (e_d, e),
            e0_f,
            Some((d0_f, r1_f, dv.e, e_x, a_h as f64 / 2.0)),
        );
        assert!(
            ext >= ext_f * slack && ext <= ext_f * (1.0 + 1e-8),
            "{case}: {ext:e} {ext_f:e}"
        );

        // The tolerance: never proven where ‖r‖ + E > tol·‖b‖ (f64, within 1e-12; the exact
        // test is `the_tolerance_is_proven_exactly_where_it_holds`).
        let rr = u128::from(rng.mantissa()) << rng.below(40);
        let bb = u128::from(rng.mantissa()) << rng.below(40);
        let (e_r2, e_b) = (rng.exponent(20), rng.exponent(20));
        let tol = [1e-3, 1e-5, 1e-7, 0.3][rng.below(4) as usize];
        let drift = Upper::new(rng.mantissa(), rng.exponent(30));
        if proves_tolerance(rr, e_r2, bb, e_b, drift, tol) {
            let lhs = ldexp((rr as f64).sqrt(), e_r2) + drift.to_f64();
            let rhs = tol * ldexp((bb as f64).sqrt(), e_b);
            assert!(lhs <= rhs * (1.0 + 1e-12), "{case}: {lhs:e} > {rhs:e}");
        }
    }
}

/// The tolerance test proves what it should where the margin is plain (so the skip is not
/// lost) and refuses at the edge and without a bound.
#[test]
fn the_tolerance_is_proven_only_within_it() {
    // ‖b‖² = 2^40, tol² ≈ 1e-10: tol²‖b‖² ≈ 110.
    let bb = 1u128 << 40;
    assert!(proves_tolerance(25, 0, bb, 0, Upper::new(5, 0), 1e-5));
    assert!(!proves_tolerance(25, 0, bb, 0, Upper::new(6, 0), 1e-5));
    // ‖r‖ above 0.7·tol·‖b‖: proven since session 16 (the old 2‖r‖² + 2E² ≤ T² refused both).
    assert!(proves_tolerance(60, 0, bb, 0, Upper::ZERO, 1e-5));
    assert!(proves_tolerance(100, 0, bb, 0, Upper::from_f64(0.4), 1e-5));
    assert!(!proves_tolerance(100, 0, bb, 0, Upper::from_f64(0.5), 1e-5));
    assert!(!proves_tolerance(110, 0, bb, 0, Upper::ZERO, 1e-5));
    // A drift above T alone, with r = 0 (X ≥ 2TE would hold without E ≤ T).
    assert!(!proves_tolerance(0, 0, bb, 0, Upper::new(11, 0), 1e-5));
    assert!(!proves_tolerance(1, 0, bb, 0, Upper::INFINITE, 1e-5));
    assert!(!proves_tolerance(0, 0, 0, 0, Upper::ZERO, 1e-5));
}

/// The tolerance test decides ‖r‖ + E ≤ T exactly (session 16), where the old one decided
/// 2‖r‖² + 2E² ≤ T² (and refused about half of what holds): at tol = 1, e = 0 and E an integer
/// k, T² = Σb² exactly, and ‖r‖ + E ≤ T holds exactly where k² ≤ Σb² and X = Σb² + k² − Σr² ≥ 0
/// with X² ≥ 4·Σb²·k², checked here in integers. The test must never prove what does not hold;
/// and wherever (‖r‖ + E)·(1 + 1e-4) ≤ T it must prove it (X − 2TE = (T − E)² − ‖r‖² is of
/// the order of that gap squared where ‖r‖ is small, so 32-bit mantissas lose gaps below about
/// 2^−15 of T there: nothing beside the 0.3 of T the old test gave up). Near-edge cases (Σb² drawn around
/// (√Σr² + k)²) and the extremes (r = 0, E = 0, E above T) are drawn.
#[test]
fn the_tolerance_is_proven_exactly_where_it_holds() {
    let mut rng = Rng(0x2545_f491_4f6c_dd1d);
    let (mut proven, mut refused_edge, mut margin_cases) = (0, 0, 0);
    for case in 0..300_000 {
        let rr = match rng.below(8) {
            0 => 0,
            _ => rng.next() >> (2 + rng.below(60)),
        };
        let k = match rng.below(8) {
            0 => 0,
            _ => rng.next() >> (33 + rng.below(31)),
        };
        let root = (rr as f64).sqrt() + k as f64;
        let bb: u64 = match rng.below(4) {
            // Near the edge: (√Σr² + k)² moved by a few parts in 2^30 either way.
            0 | 1 => {
                let edge = root * root;
                let moved = edge * (1.0 + (rng.unit() - 0.5) * 2f64.powi(-28));
                if moved >= 2f64.powi(62) {
                    continue;
                }
                moved as u64 + rng.below(3)
            }
            // Well within or beyond.
            2 => ((root * (1.0 + rng.unit())).powi(2)).min(2f64.powi(62)) as u64,
            _ => rng.next() >> (2 + rng.below(60)),
        };
        if bb == 0 || rr >= 1 << 62 || bb >= 1 << 62 {
            continue;
        }
        let drift = Upper::new(k, 0);
        let got = proves_tolerance(u128::from(rr), 0, u128::from(bb), 0, drift, 1.0);
        let (rr_w, bb_w, k_w) = (i128::from(rr), i128::from(bb), i128::from(k));
        let x = bb_w + k_w * k_w - rr_w;
        let holds = k_w * k_w <= bb_w && x >= 0 && x * x >= 4 * bb_w * k_w * k_w;
        assert!(!got || holds, "{case}: proven, but √{rr} + {k} > √{bb}");
        if root * (1.0 + 1e-4) <= (bb as f64).sqrt() {
            margin_cases += 1;
            assert!(got, "{case}: √{rr} + {k} ≤ √{bb} with a margin, not proven");
        }
        proven += usize::from(got);
        refused_edge += usize::from(holds && !got);
    }
    // The draws reach both sides and the edge.
    assert!(
        proven > 50_000 && margin_cases > 50_000,
        "{proven} {margin_cases}"
    );
    assert!(refused_edge > 0, "{refused_edge}");
}

/// `Lower::plus` and `Lower::minus` round down and stay close; `minus` refuses only where the
/// difference may be negative.
#[test]
fn lower_sums_and_differences_round_down() {
    let mut rng = Rng(0x6a09_e667_f3bc_c908);
    for case in 0..200_000 {
        let (ma, ea) = (rng.mantissa(), rng.exponent(40));
        let (mb, eb) = (rng.mantissa(), rng.exponent(40));
        let a = Lower::exact(Upper::new(ma, ea));
        let b = Lower::exact(Upper::new(mb, eb));
        let u = Upper::new(mb, eb);
        let units_l = |l: Lower, base: i32| u128::from(l.m) << (l.e - base);
        if a.m == 0 || b.m == 0 || (a.e - b.e).abs() > 60 {
            continue;
        }
        let base = a.e.min(b.e) - 2;
        let s = a.plus(b);
        let exact = units_l(a, base) + units_l(b, base);
        let got = units_l(s, base);
        assert!(got <= exact && exact - got <= exact >> 30, "{case}: plus");
        match a.minus(u) {
            Some(d) => {
                let exact = units_l(a, base) as i128 - units(u, base) as i128;
                assert!(exact >= 0, "{case}: minus of a larger value");
                if d.m != 0 {
                    let got = units_l(d, base.min(d.e)) >> (base - base.min(d.e));
                    assert!(got as i128 <= exact, "{case}: minus rounds down");
                    // Within one unit of a's exponent (where u is far below) or 2^−30.
                    let slack = (exact as u128 >> 30).max(1u128 << (a.e - base));
                    assert!(exact as u128 - got <= slack, "{case}: minus close");
                }
            }
            None => assert!(
                units(u, base) > units_l(a, base),
                "{case}: minus refused a non-negative difference"
            ),
        }
    }
}
