//! The vectors of the gateware SVU's tests (gateware/deform_gateware/svu_test.py): every pass of
//! target-core's portable SVU (`svu::portable_pass_r`, `svu::portable_pass_xp`) on each of the
//! three directions, with plans as hart 0 makes them (`Lin::new`, `Narrow::new`, from random
//! blocks and scalars) and with any plan the passes accept (every shift amount, multipliers
//! over the whole `i32` range, full-range vectors that wrap), and the edges: zero vectors and
//! zero multipliers, `i32::MIN`/`MAX` and `i64::MIN`/`MAX` elements, sign boundaries, squares
//! whose block of 16 wraps its `u64`, and lengths around a block (0, 1, 15, 16, 17, 33).
//!
//! Each case carries its inputs (three lanes of r, x, p and Kp per element), the registers the
//! plan maps to (as the gateware names them) and the portable pass's outputs.

use deform_target_core::kernel::{Lanes, Sums};
use deform_target_core::svu::{
    bound_of, bound_of_u64, magnitude_bits, portable_pass_r, portable_pass_xp, Block, Lin, Narrow,
    PassR, PassXP, Scalar, Shift, Term,
};
use serde_json::{json, Value};

/// One case's vectors: three directions of r and x, p's lanes, Kp's sums.
#[derive(Clone)]
struct Vectors {
    r: Vec<[i32; 3]>,
    x: Vec<[i32; 3]>,
    p: Vec<Lanes>,
    kp: Vec<Sums>,
}

enum Plan {
    R(PassR),
    Xp(PassXP),
}

/// The gateware's registers for a plan (see the module doc of gateware/deform_gateware/svu.py).
fn registers(plan: &Plan) -> Value {
    let own = |s: Option<Shift>| s.unwrap_or_default();
    match plan {
        Plan::R(r) => {
            let (kp_right, kp_shift) = match r.narrow {
                Narrow::Left(k) => (0, k),
                Narrow::Right(s) => (1, s),
            };
            let o = own(r.lin.own);
            json!({
                "pass_xp": 0, "r_mult": r.lin.term.mult, "kp_right": kp_right,
                "kp_shift": kp_shift, "r_keep": u32::from(r.lin.own.is_some()),
                "r_left": o.left, "r_right": o.right,
            })
        }
        Plan::Xp(xp) => {
            // The portable pass shifts p once, by x's term's shift when x is updated.
            let shift = xp.x.or(xp.p).map_or(0, |l| l.term.shift);
            let (x, p) = (xp.x.unwrap_or_default(), xp.p.unwrap_or_default());
            let (xo, po) = (own(x.own), own(p.own));
            json!({
                "pass_xp": 1, "p_shift": shift,
                "x_update": u32::from(xp.x.is_some()), "x_mult": x.term.mult,
                "x_left": xo.left, "x_right": xo.right,
                "p_update": u32::from(xp.p.is_some()), "p_mult": p.term.mult,
                "r_into_p_left": po.left, "r_into_p_right": po.right,
            })
        }
    }
}

/// Runs the portable pass on direction `d` of `v`; returns the case as JSON.
fn case(name: &str, d: usize, plan: Plan, v: &Vectors) -> Value {
    let mut out = v.clone();
    let column = |m: &[[i32; 3]]| m.iter().map(|e| e[d]).collect::<Vec<i32>>();
    let put = |m: &mut [[i32; 3]], c: &[i32]| m.iter_mut().zip(c).for_each(|(e, &z)| e[d] = z);
    let (mut rr, mut r_or, mut x_or, mut p_or) = (0u128, 0, 0, 0);
    match &plan {
        Plan::R(pr) => {
            let mut r = column(&out.r);
            (rr, r_or) = portable_pass_r(&mut r, &v.kp, d, *pr);
            put(&mut out.r, &r);
        }
        Plan::Xp(pxp) => {
            let (mut x, r) = (column(&out.x), column(&out.r));
            (x_or, p_or) = portable_pass_xp(&mut x, &mut out.p, &r, d, *pxp);
            put(&mut out.x, &x);
        }
    }
    json!({
        "name": name,
        "direction": d,
        "n": v.r.len(),
        "registers": registers(&plan),
        "r": v.r, "x": v.x, "p": v.p, "kp": v.kp,
        "want": {
            "r": out.r, "x": out.x, "p": out.p,
            "rr": rr.to_string(), "r_or": r_or, "x_or": x_or, "p_or": p_or,
        },
    })
}

/// A random element of at most `bits` bits of magnitude (sign included in the range).
fn element(rng: &mut fastrand::Rng, bits: u32) -> i32 {
    let lim = 1i64 << bits.min(31);
    rng.i64(-lim..lim).clamp(i32::MIN.into(), i32::MAX.into()) as i32
}

fn lanes3(rng: &mut fastrand::Rng, bits: u32) -> [i32; 3] {
    [0; 3].map(|_| element(rng, bits))
}

/// Random vectors of n elements: r, x, p below 2^`bits`, Kp below 2^`kp_bits`.
fn random(rng: &mut fastrand::Rng, n: usize, bits: u32, kp_bits: u32) -> Vectors {
    let kp_lim = 1i128 << kp_bits.min(63);
    Vectors {
        r: (0..n).map(|_| lanes3(rng, bits)).collect(),
        x: (0..n).map(|_| lanes3(rng, bits)).collect(),
        p: (0..n)
            .map(|_| {
                let l = lanes3(rng, bits);
                [l[0], l[1], l[2], rng.i32(..)]
            })
            .collect(),
        kp: (0..n)
            .map(|_| {
                [0; 3].map(|_| {
                    rng.i128(-kp_lim..kp_lim)
                        .clamp(i64::MIN.into(), i64::MAX.into()) as i64
                })
            })
            .collect(),
    }
}

/// Every element of every vector `value` (Kp: `kp`).
fn filled(n: usize, value: i32, kp: i64) -> Vectors {
    Vectors {
        r: vec![[value; 3]; n],
        x: vec![[value; 3]; n],
        p: vec![[value; 4]; n],
        kp: vec![[kp; 3]; n],
    }
}

fn scalar(rng: &mut fastrand::Rng) -> Scalar {
    Scalar {
        neg: rng.bool(),
        m: rng.u32(1 << 31..),
        e: rng.i32(-80..10),
    }
}

/// Direction d's block of a vector of lanes: a random exponent, the bound from its OR.
fn block(rng: &mut fastrand::Rng, v: &[[i32; 3]], d: usize) -> Block {
    let or = v.iter().fold(0, |o, e| o | magnitude_bits(e[d]));
    Block {
        e: rng.i32(-60..0),
        bound: if or == 0 { 0 } else { bound_of(or) },
    }
}

/// Pass R as hart 0 plans it (`cg::r_plan`): Kp's narrowing from its OR, r kept or not.
fn planned_r(rng: &mut fastrand::Rng, v: &Vectors, d: usize, keep: bool) -> PassR {
    let mut sat = 0;
    let kp_or =
        v.kp.iter()
            .fold(0u64, |o, s| o | (s[d] ^ (s[d] >> 63)) as u64);
    let (narrow, e_offset, bound) = Narrow::new(bound_of_u64(kp_or), &mut sat);
    let kp = Block {
        e: rng.i32(-60..-20) + e_offset,
        bound,
    };
    let r = block(rng, &v.r, d);
    PassR {
        lin: Lin::new(scalar(rng), kp, true, keep.then_some(r), &mut sat),
        narrow,
    }
}

/// Pass XP as hart 0 plans it: α·p + x and β·p + r on p's block.
fn planned_xp(rng: &mut fastrand::Rng, v: &Vectors, d: usize, x: bool, p: bool) -> PassXP {
    let mut sat = 0;
    let p_lanes: Vec<[i32; 3]> = v.p.iter().map(|l| [l[0], l[1], l[2]]).collect();
    let pb = block(rng, &p_lanes, d);
    let (xb, rb) = (block(rng, &v.x, d), block(rng, &v.r, d));
    PassXP {
        x: x.then(|| Lin::new(scalar(rng), pb, false, Some(xb), &mut sat)),
        p: p.then(|| Lin::new(scalar(rng), pb, false, Some(rb), &mut sat)),
    }
}

/// A plan of any fields the passes accept: multipliers over all of `i32`, every shift amount.
fn any_lin(rng: &mut fastrand::Rng, shift: u32) -> Lin {
    Lin {
        term: Term {
            mult: rng.i32(..),
            shift,
        },
        own: Some(Shift {
            left: rng.u32(0..32),
            right: rng.u32(0..32),
        }),
        e: 0,
    }
}

fn any_r(rng: &mut fastrand::Rng) -> PassR {
    let s = rng.u32(0..32);
    PassR {
        lin: Lin {
            own: rng.bool().then_some(any_lin(rng, 0).own.unwrap()),
            ..any_lin(rng, 0)
        },
        narrow: if rng.bool() {
            Narrow::Left(s)
        } else {
            Narrow::Right(s)
        },
    }
}

fn any_xp(rng: &mut fastrand::Rng) -> PassXP {
    let shift = rng.u32(0..32);
    PassXP {
        x: Some(any_lin(rng, shift)),
        p: Some(any_lin(rng, shift)),
    }
}

fn planned_cases(rng: &mut fastrand::Rng, cases: &mut Vec<Value>) {
    for d in 0..3 {
        // K·p beyond 2^31 (narrowed right), and below it (narrowed left).
        for (kp_bits, keep) in [(50, true), (62, true), (20, true), (40, false)] {
            let n = rng.usize(20..40);
            let v = random(rng, n, 29, kp_bits);
            let plan = Plan::R(planned_r(rng, &v, d, keep));
            let name = format!("pass R, direction {d}, Kp < 2^{kp_bits}, r kept: {keep}");
            cases.push(case(&name, d, plan, &v));
        }
        for (x, p) in [(true, true), (true, false), (false, true)] {
            let (n, bits) = (rng.usize(20..40), rng.u32(8..30));
            let v = random(rng, n, bits, 40);
            let plan = Plan::Xp(planned_xp(rng, &v, d, x, p));
            let name = format!("pass XP, direction {d}, x: {x}, p: {p}");
            cases.push(case(&name, d, plan, &v));
        }
    }
}

fn any_plan_cases(rng: &mut fastrand::Rng, cases: &mut Vec<Value>) {
    for k in 0..6 {
        let d = k % 3;
        let v = random(rng, 24, 31, 63);
        cases.push(case(
            &format!("pass R, any plan, full-range vectors ({k})"),
            d,
            Plan::R(any_r(rng)),
            &v,
        ));
        cases.push(case(
            &format!("pass XP, any plan, full-range vectors ({k})"),
            d,
            Plan::Xp(any_xp(rng)),
            &v,
        ));
    }
}

/// The plan that keeps r (or x, p) as it is: multiplier `mult`, identity shifts.
fn plain_r(mult: i32, narrow: Narrow) -> Plan {
    Plan::R(PassR {
        lin: Lin {
            term: Term { mult, shift: 0 },
            own: Some(Shift::default()),
            e: 0,
        },
        narrow,
    })
}

fn plain_xp(mult: i32, shift: u32) -> Plan {
    let lin = Lin {
        term: Term { mult, shift },
        own: Some(Shift::default()),
        e: 0,
    };
    Plan::Xp(PassXP {
        x: Some(lin),
        p: Some(lin),
    })
}

fn edge_cases(rng: &mut fastrand::Rng, cases: &mut Vec<Value>) {
    let (max, min) = (i32::MAX, i32::MIN);
    // Squares of 2^62: blocks of 16 wrap their u64 to 0, the last (5 squares) to 2^62.
    let v = filled(37, min, 0);
    let name = "pass R, r = i32::MIN: blocks of squares wrap";
    cases.push(case(name, 1, plain_r(0, Narrow::Left(0)), &v));
    // Kp at its extremes through every kind of narrowing, multipliers at theirs.
    let kps = [
        i64::MIN,
        i64::MIN + 1,
        i64::MAX,
        -1,
        1 << 62,
        -(1 << 62) - 1,
    ];
    let narrowings = [0, 1, 31]
        .into_iter()
        .flat_map(|s| [Narrow::Left(s), Narrow::Right(s)]);
    let mults = [max, min, -max, 1, -1];
    for (k, (kp, narrow)) in kps
        .iter()
        .flat_map(|&kp| narrowings.clone().map(move |n| (kp, n)))
        .enumerate()
    {
        let mult = mults[k % mults.len()];
        let mut v = random(rng, 4, 31, 63);
        v.kp[..3].iter_mut().for_each(|s| *s = [kp; 3]);
        let name = format!("pass R, Kp = {kp}, {narrow:?}, mult {mult}");
        cases.push(case(&name, k % 3, plain_r(mult, narrow), &v));
    }
    for (value, mult, shift) in [
        (max, min, 0),
        (min, min, 0),
        (min, max, 31),
        (-1, -max, 31),
        (1, max, 30),
    ] {
        let v = filled(16, value, 0);
        let name = format!("pass XP, every element {value}, mult {mult}, p << {shift}");
        cases.push(case(&name, 0, plain_xp(mult, shift), &v));
    }
    // Zero vectors, and zero multipliers on random vectors.
    let zero = filled(33, 0, 0);
    cases.push(case(
        "pass R, zero vectors",
        0,
        Plan::R(planned_r(rng, &zero, 0, true)),
        &zero,
    ));
    cases.push(case(
        "pass XP, zero vectors",
        1,
        Plan::Xp(planned_xp(rng, &zero, 1, true, true)),
        &zero,
    ));
    let v = random(rng, 15, 30, 62);
    cases.push(case(
        "pass R, zero multiplier",
        2,
        plain_r(0, Narrow::Right(7)),
        &v,
    ));
    cases.push(case("pass XP, zero multipliers", 2, plain_xp(0, 3), &v));
    // Sign boundaries: small magnitudes around zero and around the 2^29/2^30 bounds.
    let edges = [
        0,
        1,
        -1,
        2,
        -2,
        1 << 29,
        -(1 << 29),
        (1 << 29) - 1,
        -(1 << 29) - 1,
        (1 << 30) - 1,
        -(1 << 30),
    ];
    let mut v = random(rng, edges.len(), 4, 4);
    for (k, &e) in edges.iter().enumerate() {
        v.r[k] = [e, -e, e];
        v.x[k] = [-e, e, e];
        v.p[k] = [e, e, -e, 0];
        v.kp[k] = [i64::from(e), -i64::from(e) << 20, i64::from(e) << 33];
    }
    for d in 0..3 {
        cases.push(case(
            &format!("pass R, sign boundaries, direction {d}"),
            d,
            Plan::R(planned_r(rng, &v, d, true)),
            &v,
        ));
        cases.push(case(
            &format!("pass XP, sign boundaries, direction {d}"),
            d,
            Plan::Xp(planned_xp(rng, &v, d, true, true)),
            &v,
        ));
    }
    // Lengths around a block of 16 squares.
    for n in [0, 1, 15, 16, 17, 33] {
        let v = random(rng, n, 29, 50);
        cases.push(case(
            &format!("pass R, n = {n}"),
            n % 3,
            Plan::R(planned_r(rng, &v, n % 3, true)),
            &v,
        ));
    }
}

/// The SVU's vectors: `{"nodes": …, "cases": […]}`.
pub fn vectors() -> Value {
    let mut rng = fastrand::Rng::with_seed(22);
    let mut cases = Vec::new();
    planned_cases(&mut rng, &mut cases);
    any_plan_cases(&mut rng, &mut cases);
    edge_cases(&mut rng, &mut cases);
    json!({ "nodes": 64, "cases": cases })
}
