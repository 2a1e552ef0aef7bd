//! Target-resident dynamic frames (protocol version 12) on a damped chain against a backward
//! Euler stepper in f64 run over the same quantised S and K: the displacements follow it, the
//! tool's force too, and every refusal is clear.

use deform_shared::dynamics::{DynamicError, DynamicParams, DynamicTool};
use deform_shared::field::FieldSelection;
use deform_shared::live::{Coupling, FrameReport, LiveError, ToolRow};
use deform_shared::matrix::words_crc;
use deform_shared::qformat::{ldexp, quantize};
use deform_shared::word::VALUE_MASK;

use super::*;

const N: usize = 21;
const TOOL: usize = 10;
/// Both ends are fixed.
const FIXED: [usize; 2] = [0, N - 1];
/// S is uploaded as S·2^7 (its entries near 0.005 would use 13 of the 21 bits at F = 20).
const F_S: u8 = 20;
const S_SCALE: i8 = -7;
const F_K: u8 = 18;
const MASS: f64 = 0.005;
const H: f64 = 1e-3;
const BETA: f64 = 0.05;

fn constrained(i: usize) -> bool {
    i == TOOL || FIXED.contains(&i)
}

/// Row i of the unconstrained K (tridiag(−1, 2, −1)) and S = m·I + (h·β + h²)·K.
fn k_row(i: usize) -> Vec<(usize, f64)> {
    super::laplacian_row(N)(i)
}

fn s_row(i: usize) -> Vec<(usize, f64)> {
    let c = H * BETA + H * H;
    let up = 2f64.powi(-i32::from(S_SCALE));
    k_row(i)
        .into_iter()
        .map(|(j, k)| (j, up * if j == i { MASS + c * k } else { c * k }))
        .collect()
}

/// Whether entry (i, c) survives the elimination of the constrained rows and columns (their
/// diagonals stay).
fn kept(i: usize, c: usize) -> bool {
    if constrained(i) {
        c == i
    } else {
        !constrained(c)
    }
}

/// A matrix with the constrained rows and columns eliminated (their diagonals kept).
fn eliminated(row: fn(usize) -> Vec<(usize, f64)>, frac_bits: u8) -> Encoded {
    encode(N, 8, frac_bits, move |i| {
        row(i).into_iter().filter(|&(c, _)| kept(i, c)).collect()
    })
}

fn tool_row(row: Vec<(usize, f64)>, frac_bits: u8) -> ToolRow {
    let raw = |v: f64| quantize(v, frac_bits).unwrap();
    ToolRow {
        node: TOOL as u32,
        diagonal: raw(row.iter().find(|e| e.0 == TOOL).unwrap().1),
        row: row
            .iter()
            .filter(|e| e.0 != TOOL && !FIXED.contains(&e.0))
            .map(|&(column, v)| Coupling {
                column: column as u32,
                value: raw(v),
            })
            .collect(),
    }
}

fn params() -> DynamicParams {
    DynamicParams {
        h: H as f32,
        mass: MASS as f32,
        s_scale: S_SCALE,
        k_scale: 0,
        tolerance: 1e-7,
        max_iterations: 500,
        cycle_budget: 0,
    }
}

/// S uploaded, K's values into the stiffness copy, the tool, started.
fn started(s: &mut Session<'_, Sequential>) {
    started_with(s, params());
}

/// [`started`] with `params`.
fn started_with(s: &mut Session<'_, Sequential>, params: DynamicParams) {
    load(s, &eliminated(s_row, F_S));
    let k = eliminated(k_row, F_K);
    assert_eq!(
        s.handle(Request::BeginStiffness { frac_bits: F_K }),
        Response::Ack
    );
    let values: Vec<i32> = k
        .words
        .iter()
        .map(|&w| (((w & VALUE_MASK) << 11) as i32) >> 11)
        .collect();
    for (i, chunk) in values.chunks(7).enumerate() {
        let req = Request::UpdateValues {
            offset: (i * 7) as u32,
            values: chunk.iter().copied().collect(),
        };
        assert_eq!(s.handle(req), Response::Ack);
    }
    let crc32 = words_crc(&k.words);
    assert_eq!(s.handle(Request::EndUpdate { crc32 }), Response::Ack);
    let tool = DynamicTool {
        s: tool_row(s_row(TOOL), F_S),
        k: tool_row(k_row(TOOL), F_K),
    };
    assert_eq!(s.handle(Request::DynamicTool(tool)), Response::Ack);
    assert_eq!(s.handle(Request::DynamicStart(params)), Response::Ack);
}

/// Backward Euler in f64 over the quantised S and K: the stepper the target must follow.
struct Reference {
    s: Vec<Vec<f64>>,
    k: Vec<Vec<f64>>,
    u: Vec<f64>,
    v: Vec<f64>,
}

impl Reference {
    fn new() -> Self {
        let full = |row: fn(usize) -> Vec<(usize, f64)>, f: u8, scale: i8| {
            let mut a = vec![vec![0.0; N]; N];
            for (i, r) in a.iter_mut().enumerate() {
                for (j, v) in row(i) {
                    let q = f64::from(quantize(v, f).unwrap()) / f64::from(1u32 << f);
                    r[j] = q * 2f64.powi(i32::from(scale));
                }
            }
            a
        };
        Reference {
            s: full(s_row, F_S, S_SCALE),
            k: full(k_row, F_K, 0),
            u: vec![0.0; N],
            v: vec![0.0; N],
        }
    }

    /// One step with the tool at `ut`; returns the tool's force.
    fn step(&mut self, ut: f64) -> f64 {
        let vt = (ut - self.u[TOOL]) / H;
        let free: Vec<usize> = (0..N).filter(|&i| !constrained(i)).collect();
        let ku: Vec<f64> = (0..N)
            .map(|i| (0..N).map(|j| self.k[i][j] * self.u[j]).sum())
            .collect();
        let b: Vec<f64> = free
            .iter()
            .map(|&i| MASS * self.v[i] - H * ku[i] - self.s[i][TOOL] * vt)
            .collect();
        let a: Vec<Vec<f64>> = free
            .iter()
            .map(|&i| free.iter().map(|&j| self.s[i][j]).collect())
            .collect();
        let x = super::direct_solve(a, b);
        let mut v1 = vec![0.0; N];
        for (&i, xi) in free.iter().zip(x) {
            v1[i] = xi;
        }
        v1[TOOL] = vt;
        let sv: f64 = (0..N).map(|j| self.s[TOOL][j] * v1[j]).sum();
        let force = (sv - MASS * self.v[TOOL]) / H + ku[TOOL];
        for (u, v) in self.u.iter_mut().zip(&v1) {
            *u += H * v;
        }
        self.u[TOOL] = ut;
        self.v = v1;
        force
    }
}

/// The tool's path: pushed 1 unit in 100 steps, held, then released over 20.
fn path(step: usize) -> f64 {
    match step {
        0..=100 => step as f64 / 100.0,
        101..=150 => 1.0,
        151..=170 => 1.0 - (step - 150) as f64 / 20.0,
        _ => 0.0,
    }
}

#[test]
fn dynamic_frames_follow_the_f64_stepper() {
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    let mut s = bufs.session(info(), HARTS.harts);
    started(&mut s);
    // One reference per direction, fed the tool's displacements as the frames carry them
    // (f32): the tool's velocity is a difference of positions, which f32 rounds at 1e-5.
    let mut references = [Reference::new(), Reference::new(), Reference::new()];
    let u0 = [0.3f32, -0.2, 0.05];
    let mut peak = [0f64; 3];
    let mut peak_force = [0f64; 3];
    let mut iterations = Vec::new();
    for step in 1..=220 {
        let tool: heapless::Vec<[f32; 3], 8> =
            [u0.map(|u| u * path(step) as f32)].into_iter().collect();
        let report: FrameReport = match s.handle(Request::DynamicFrame { tool: tool.clone() }) {
            Response::LiveFrame(r) => r,
            other => panic!("step {step}: {other:?}"),
        };
        for (d, reference) in references.iter_mut().enumerate() {
            let force = reference.step(f64::from(tool[0][d]));
            let u_max = reference.u.iter().fold(0f64, |m, v| m.max(v.abs()));
            peak[d] = peak[d].max(u_max);
            let got = read_direction(&mut s, d as u8, N);
            let err = got
                .iter()
                .zip(&reference.u)
                .map(|(g, r)| (g - r).abs())
                .fold(0.0, f64::max);
            assert!(err <= 1e-6 * peak[d], "step {step} d {d}: {err:e}");
            peak_force[d] = peak_force[d].max(force.abs());
            let f_err = (f64::from(report.force[d]) - force).abs();
            assert!(
                f_err <= 1e-5 * peak_force[d],
                "step {step} d {d}: {report:?} vs {force}"
            );
        }
        iterations.push(report.iterations);
        if step % 50 == 0 {
            field_matches_the_state(&mut s, &references, step);
        }
    }
    // After the release the tissue is still moving; the start v₁ ≈ v₀ leaves a few
    // iterations per step.
    assert!(references[0].v.iter().any(|v| v.abs() > 1e-6));
    assert!(iterations.iter().all(|&i| i <= 6), "{iterations:?}");
}

/// The step's field frames (`ReadField`, every node) carry u quantised: each component within
/// one quantum of the reference's u, with one exponent for every chunk of the step.
fn field_matches_the_state(
    s: &mut Session<'_, Sequential>,
    references: &[Reference; 3],
    step: usize,
) {
    let selection = FieldSelection::new(N as u32, 1, None).unwrap();
    let mut exponent = None;
    for offset in selection.chunk_offsets() {
        let request = Request::ReadField {
            offset,
            stride: 1,
            surface: None,
        };
        let chunk = match s.handle(request) {
            Response::Field(chunk) => chunk,
            other => panic!("step {step}: {other:?}"),
        };
        assert_eq!(*exponent.get_or_insert(chunk.exponent), chunk.exponent);
        let quantum = ldexp(1.0, i32::from(chunk.exponent));
        for (node, q) in selection.chunk(offset).zip(chunk.displacements()) {
            for (d, reference) in references.iter().enumerate() {
                let err = (q[d] - reference.u[node as usize]).abs();
                assert!(err <= quantum, "step {step} node {node} d {d}: {err:e}");
            }
        }
    }
}

#[test]
fn dynamic_requests_are_refused_clearly_out_of_order() {
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    let mut s = bufs.session(info(), HARTS.harts);
    let frame = Request::DynamicFrame {
        tool: [[0.0f32; 3]].into_iter().collect(),
    };
    assert_eq!(s.handle(frame.clone()), ooo(SessionStep::NoMatrix));
    load(&mut s, &eliminated(s_row, F_S));
    assert_eq!(
        s.handle(Request::DynamicStart(params())),
        err(ErrorCode::Dynamic(DynamicError::NoStiffness))
    );
    assert_eq!(
        s.handle(frame.clone()),
        err(ErrorCode::Dynamic(DynamicError::NotStarted))
    );
    // Rows of S and K that differ, a node outside, a bad h.
    let mut k = tool_row(k_row(TOOL), F_K);
    k.row.pop();
    let tool = DynamicTool {
        s: tool_row(s_row(TOOL), F_S),
        k,
    };
    assert_eq!(
        s.handle(Request::DynamicTool(tool)),
        err(ErrorCode::Dynamic(DynamicError::RowsDiffer))
    );
    let mut far = tool_row(s_row(TOOL), F_S);
    far.node = 99;
    let mut far_k = tool_row(k_row(TOOL), F_K);
    far_k.node = 99;
    assert_eq!(
        s.handle(Request::DynamicTool(DynamicTool { s: far, k: far_k })),
        err(ErrorCode::Live(LiveError::NodeOutOfRange { node: 99 }))
    );
    started(&mut s);
    let bad = DynamicParams {
        h: f32::NAN,
        ..params()
    };
    assert_eq!(
        s.handle(Request::DynamicStart(bad)),
        err(ErrorCode::Dynamic(DynamicError::BadParams))
    );
    let two = Request::DynamicFrame {
        tool: [[0.0f32; 3]; 2].into_iter().collect(),
    };
    assert_eq!(
        s.handle(two),
        err(ErrorCode::Live(LiveError::ToolCount {
            expected: 1,
            got: 2
        }))
    );
}

/// S's row i as the target holds it: the eliminated rows' raw values at F = F_S.
fn s_raw_row(i: usize) -> Vec<(usize, i128)> {
    s_row(i)
        .into_iter()
        .filter(|&(c, _)| kept(i, c))
        .map(|(c, v)| (c, i128::from(quantize(v, F_S).unwrap())))
        .collect()
}

/// v·2^(e − e0) exactly in an `i128` (asserted to fit).
fn at(v: i128, e: i32, e0: i32) -> i128 {
    let s = (e - e0) as u32;
    let out = v.checked_shl(s).unwrap();
    assert!(s < 127 && out >> s == v && out.unsigned_abs() < 1 << 120);
    out
}

fn norm(v: &[i128], e0: i32) -> f64 {
    ldexp(
        v.iter()
            .map(|&x| (x as f64) * (x as f64))
            .sum::<f64>()
            .sqrt(),
        e0,
    )
}

/// Direction d's state after a step, exactly: ‖b − S·v‖ of the session's own b, v and S, the
/// distance of its r from that, and ‖b‖ (real units).
fn exact_state(s: &Session<'_, Sequential>, d: usize) -> (f64, f64, f64) {
    let (truth, gap, b, _) = exact_gap(s, d);
    (truth, gap, b)
}

/// [`exact_state`] and the gap r − (b − S·v) itself, element by element (real units).
fn exact_gap(s: &Session<'_, Sequential>, d: usize) -> (f64, f64, f64, Vec<f64>) {
    let st = s.dynamic.state().unwrap();
    let VectorState::Complete { exponent: e_b } = s.rhs[d] else {
        panic!("b of direction {d} is not complete");
    };
    let dir = &s.store.directions[d];
    let (e_v, e_r) = (
        st.v[d].e - i32::from(F_S),
        st.residual[d].map_or(e_b, |r| r.e),
    );
    let e0 = e_b.min(e_v).min(e_r);
    let truth: Vec<i128> = (0..N)
        .map(|i| {
            let sv: i128 = s_raw_row(i)
                .iter()
                .map(|&(c, q)| q * i128::from(dir.x0[c]))
                .sum();
            at(i128::from(dir.b[i]), e_b, e0) - at(sv, e_v, e0)
        })
        .collect();
    let gap: Vec<i128> = truth
        .iter()
        .zip(&dir.r[..N])
        .map(|(&t, &r)| at(i128::from(r), e_r, e0) - t)
        .collect();
    let b: Vec<i128> = dir.b[..N].iter().map(|&v| i128::from(v)).collect();
    let real = gap.iter().map(|&g| ldexp(g as f64, e0)).collect();
    (norm(&truth, e0), norm(&gap, e0), norm(&b, e_b), real)
}

/// Steps that accept their solve's recursive residual without the exact pass (on the drift's
/// bound, `cg::Outcome::drift`) are truly within the tolerance: after every step the exact
/// b − S·v of the session's own b, v and S is computed here, r is within the carried drift of
/// it wherever the drift is finite, and every unchecked step's true residual is within tol.
/// The change of that gap from the last step's is within `Stepping::delta` (the extrapolated
/// start's bound relies on it). The skip must happen (else this proves nothing), runs of
/// more than two skips too (which the delta allows), and an exact check at least every
/// `MAX_UNCHECKED` steps.
#[test]
fn steps_accepted_on_the_drift_bound_are_truly_within_the_tolerance() {
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    let mut s = bufs.session(info(), HARTS.harts);
    let tol = 1e-5;
    started_with(
        &mut s,
        DynamicParams {
            tolerance: tol as f32,
            ..params()
        },
    );
    let u0 = [0.3f32, -0.2, 0.05];
    let (mut skipped, mut checked, mut long_runs) = (0, 0, 0);
    let mut last_gap: [Option<Vec<f64>>; 3] = Default::default();
    for step in 1..=220 {
        let tool: heapless::Vec<[f32; 3], 8> =
            [u0.map(|u| u * path(step) as f32)].into_iter().collect();
        match s.handle(Request::DynamicFrame { tool }) {
            Response::LiveFrame(_) => {}
            other => panic!("step {step}: {other:?}"),
        }
        for (d, last_gap) in last_gap.iter_mut().enumerate() {
            let (truth, gap, b, gaps) = exact_gap(&s, d);
            let st = s.dynamic.state().unwrap();
            let (drift, unchecked) = (st.drift[d].to_f64(), st.unchecked[d]);
            let delta = st.delta[d].to_f64();
            if let (Some(last), true) = (&*last_gap, delta.is_finite()) {
                let change = gaps
                    .iter()
                    .zip(last)
                    .map(|(a, b)| (a - b) * (a - b))
                    .sum::<f64>()
                    .sqrt();
                assert!(
                    change <= delta,
                    "step {step} d {d}: ‖ε − ε₋₁‖ {change:e} > {delta:e}"
                );
            }
            *last_gap = Some(gaps);
            long_runs += usize::from(unchecked > 2);
            assert!(
                unchecked <= crate::dynamics::MAX_UNCHECKED,
                "step {step} d {d}"
            );
            if drift.is_finite() {
                assert!(
                    gap <= drift,
                    "step {step} d {d}: ‖r − (b − S·v)‖ {gap:e} > {drift:e}"
                );
            }
            if unchecked > 0 {
                skipped += 1;
                let rel = f64::from(tol as f32) * b;
                assert!(
                    truth <= rel,
                    "step {step} d {d}: true {:e} of ‖b‖",
                    truth / b
                );
            } else {
                checked += 1;
            }
        }
    }
    assert!(
        skipped > 20 && checked > 20 && long_runs > 20,
        "{skipped} skipped, {checked} checked, {long_runs} beyond two in a row"
    );
}

/// `ReadVector` (protocol version 13) answers a step's b, v and r exactly as the session holds
/// them, with their exponents, so that a host sees the true residual the session's own
/// arithmetic gives; and refuses clearly where there is no such vector.
#[test]
fn read_vector_gives_the_steps_own_vectors() {
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    let mut s = bufs.session(info(), HARTS.harts);
    let read = |vector, direction, offset| Request::ReadVector {
        vector,
        direction,
        offset,
        len: CHUNK_LEN as u16,
    };
    assert_eq!(
        s.handle(read(StateVector::Rhs, 0, 0)),
        ooo(SessionStep::NoRhs)
    );
    load(&mut s, &eliminated(s_row, F_S));
    assert_eq!(
        s.handle(read(StateVector::Velocity, 0, 0)),
        err(ErrorCode::Dynamic(DynamicError::NotStarted))
    );
    started_with(
        &mut s,
        DynamicParams {
            tolerance: 1e-5,
            ..params()
        },
    );
    assert_eq!(
        s.handle(read(StateVector::Residual, 2, 0)),
        ooo(SessionStep::NoSolution)
    );
    for step in 1..=12 {
        let tool = [[0.3f32, -0.2, 0.05].map(|u| u * path(step) as f32)];
        let tool: heapless::Vec<[f32; 3], 8> = tool.into_iter().collect();
        assert!(matches!(
            s.handle(Request::DynamicFrame { tool }),
            Response::LiveFrame(_)
        ));
    }
    assert_eq!(
        s.handle(read(StateVector::Rhs, 3, 0)),
        err(ErrorCode::DirectionOutOfRange {
            direction: 3,
            max: MAX_DIRECTIONS as u8
        })
    );
    assert_eq!(
        s.handle(read(StateVector::Velocity, 1, N as u32)),
        err(ErrorCode::ChunkTooLong)
    );
    for d in 0..3u8 {
        let st = *s.dynamic.state().unwrap();
        let dir = &s.store.directions[usize::from(d)];
        let VectorState::Complete { exponent: e_b } = s.rhs[usize::from(d)] else {
            panic!("no b in direction {d}");
        };
        let r = st.residual[usize::from(d)].unwrap();
        let tail =
            |v: &[i32]| -> heapless::Vec<i32, CHUNK_LEN> { v[5..N].iter().copied().collect() };
        let want = [
            (StateVector::Rhs, e_b, tail(dir.b)),
            (StateVector::Velocity, st.v[usize::from(d)].e, tail(dir.x0)),
            (StateVector::Residual, r.e, tail(dir.r)),
        ];
        for (vector, exponent, values) in want {
            let answer = Response::Solution {
                direction: d,
                offset: 5,
                exponent,
                mantissas: values,
            };
            assert_eq!(s.handle(read(vector, d, 5)), answer, "{vector:?} {d}");
        }
    }
}

/// The start's own bound (`dynamics::start_drift`, pass D's residual formed in O(n) from the
/// carried quantities) holds: at a tolerance every start meets, no step iterates, so each
/// step's r is its start's r₀ and v its start x₀ (pass A's v₀ + Δv₀), the carried drift is the
/// start's bound alone (chained over up to `MAX_UNCHECKED` steps), and r₀ is checked against
/// the exact b − S·x₀ after every step.
#[test]
fn the_start_residuals_drift_bound_holds_on_its_own() {
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    let mut s = bufs.session(info(), HARTS.harts);
    started_with(
        &mut s,
        DynamicParams {
            tolerance: 1.0,
            ..params()
        },
    );
    let u0 = [0.3f32, -0.2, 0.05];
    let mut bounded = 0;
    for step in 1..=40 {
        let tool: heapless::Vec<[f32; 3], 8> =
            [u0.map(|u| u * path(step) as f32)].into_iter().collect();
        let iterations = match s.handle(Request::DynamicFrame { tool }) {
            Response::LiveFrame(r) => r.iterations,
            other => panic!("step {step}: {other:?}"),
        };
        for d in 0..3 {
            let (_, gap, _) = exact_state(&s, d);
            let st = s.dynamic.state().unwrap();
            let drift = st.drift[d].to_f64();
            if iterations == 0 && st.unchecked[d] > 0 && gap > 0.0 {
                bounded += 1;
                assert!(
                    gap <= drift,
                    "step {step} d {d}: ‖r₀ − (b − S·x₀)‖ {gap:e} > {drift:e}"
                );
            }
        }
    }
    assert!(bounded > 30, "{bounded} starts bounded");
}
