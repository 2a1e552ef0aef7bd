//! The live loop on a 1-D chain against a direct f64 solve: frames, the local force model, the
//! quantised field, and every refusal.

use deform_shared::live::{Coupling, FrameReport, LiveError, LiveParams, ToolRow};
use deform_shared::qformat::quantize;

use super::*;

pub(super) const N: usize = 21;
pub(super) const TOOL: usize = 10;
const F: u8 = 18;
pub(super) const SCALE: [f32; 3] = [1.0, 2.0, 0.5];
const U0: [f32; 3] = [0.3, -0.2, 0.05];

/// tridiag(−1, 2, −1) with the tool node's row and column eliminated (its row keeps 2).
pub(super) fn chain() -> Encoded {
    encode(N, 8, F, |i| {
        laplacian_row(N)(i)
            .into_iter()
            .filter(|&(c, _)| (i == TOOL) == (c == TOOL))
            .collect()
    })
}

fn raw(v: f64) -> i32 {
    quantize(v, F).unwrap()
}

pub(super) fn tool_row(node: u32) -> ToolRow {
    ToolRow {
        node,
        diagonal: raw(2.0),
        row: [node - 1, node + 1]
            .map(|column| Coupling {
                column,
                value: raw(-1.0),
            })
            .into_iter()
            .collect(),
    }
}

pub(super) fn static_load() -> Vec<f64> {
    sine_load(TOOL)
}

/// 0.1·sin(i) on the chain's nodes, 0 at `held` (the tool, or a fixed node).
pub(super) fn sine_load(held: usize) -> Vec<f64> {
    (0..N)
        .map(|i| {
            if i == held {
                0.0
            } else {
                0.1 * (i as f64).sin()
            }
        })
        .collect()
}

pub(super) fn params() -> LiveParams {
    LiveParams {
        tolerance: 1e-7,
        max_iterations: 500,
        cycle_budget: 0,
        scale: SCALE,
    }
}

/// The converged displacements and reaction force of direction d at tool displacement `u`.
fn reference(d: usize, u: f64) -> (Vec<f64>, f64) {
    let mut b = static_load();
    b[TOOL - 1] += u;
    b[TOOL + 1] += u;
    b[TOOL] = 2.0 * u;
    let x = direct_solve(dense(&chain()), b);
    let force = f64::from(SCALE[d]) * (2.0 * u - x[TOOL - 1] - x[TOOL + 1]);
    (x, force)
}

fn started(s: &mut Session<'_, Sequential>) {
    load(s, &chain());
    assert_eq!(
        s.handle(Request::LiveTool(tool_row(TOOL as u32))),
        Response::Ack
    );
    match s.handle(Request::LiveStart(params())) {
        Response::LiveReady(r) => assert!(r.converged && r.solves == 1, "{r:?}"),
        other => panic!("{other:?}"),
    }
    let (e, m) = to_block(&static_load());
    for d in 0..3 {
        all_ack(
            s,
            vector_requests(VectorSlot::Rhs { direction: d }, e, &m, CHUNK_LEN),
        );
    }
}

fn tool_at(t: f32) -> heapless::Vec<[f32; 3], 8> {
    [U0.map(|u| u * t)].into_iter().collect()
}

#[test]
fn frames_match_a_direct_solve_and_the_local_model_predicts_the_next_force() {
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    let mut s = bufs.session(info(), HARTS.harts);
    started(&mut s);
    let mut predicted: Option<[f32; 3]> = None;
    let mut iterations = Vec::new();
    for step in 1..=5 {
        let t = step as f32 * 0.7;
        let report = frame_at(&mut s, t);
        iterations.push(report.iterations);
        assert!(report.residual <= 1e-7, "{report:?}");
        for d in 0..3 {
            let (x, force) = reference(d, f64::from(U0[d] * t));
            let got = read_direction(&mut s, d as u8, N);
            assert!(max_rel_err(&got, &x) < 1e-5, "step {step} d {d}");
            let err = (f64::from(report.force[d]) - force).abs();
            assert!(err <= 1e-5 * force.abs().max(1e-3), "{report:?} vs {force}");
            if let Some(p) = predicted {
                // The chain is linear: the model is exact up to the solves' tolerance.
                let err = (f64::from(p[d]) - force).abs();
                assert!(err <= 1e-4 * force.abs().max(1e-3), "{p:?} vs {force}");
            }
        }
        let next = tool_at((step + 1) as f32 * 0.7);
        predicted = match s.handle(Request::LiveForce { tool: next }) {
            Response::LiveForce(r) => Some(r.force),
            other => panic!("{other:?}"),
        };
    }
    // The first frame starts from the tool's response alone (the static part is unknown);
    // every later one from the superposition, exact for the linear chain.
    assert!(iterations[0] > 2, "{iterations:?}");
    assert!(iterations[1..].iter().all(|&i| i <= 1), "{iterations:?}");
}

/// The full frame at tool position `t`.
fn frame_at(s: &mut Session<'_, Sequential>, t: f32) -> FrameReport {
    match s.handle(Request::LiveFrame { tool: tool_at(t) }) {
        Response::LiveFrame(r) => r,
        other => panic!("{other:?}"),
    }
}

/// The frames' iterations at tool positions 0.7, 1.4, … with `bufs`'s response storage, the
/// static load `load`, and each frame's solution checked against the direct solve.
fn frame_iterations(bufs: &mut OwnedStorage, load: &[f64]) -> Vec<u32> {
    let mut s = bufs.session(info(), HARTS.harts);
    load_matrix_and_tool(&mut s);
    let (e, m) = to_block(load);
    for d in 0..3 {
        all_ack(
            &mut s,
            vector_requests(VectorSlot::Rhs { direction: d }, e, &m, CHUNK_LEN),
        );
    }
    let mut iterations = Vec::new();
    for step in 1..=5 {
        let t = step as f32 * 0.7;
        let report = frame_at(&mut s, t);
        assert!(report.residual <= 1e-7, "{report:?}");
        for (d, u0) in U0.iter().enumerate() {
            let mut b = load.to_vec();
            let u = f64::from(u0 * t);
            b[TOOL - 1] += u;
            b[TOOL + 1] += u;
            b[TOOL] = 2.0 * u;
            let x = direct_solve(dense(&chain()), b);
            let got = read_direction(&mut s, d as u8, N);
            assert!(max_rel_err(&got, &x) < 1e-5, "step {step} d {d}");
        }
        iterations.push(u32::from(report.iterations));
    }
    iterations
}

fn load_matrix_and_tool(s: &mut Session<'_, Sequential>) {
    load(s, &chain());
    assert_eq!(
        s.handle(Request::LiveTool(tool_row(TOOL as u32))),
        Response::Ack
    );
    assert!(matches!(
        s.handle(Request::LiveStart(params())),
        Response::LiveReady(_)
    ));
}

#[test]
fn without_a_static_load_even_the_first_frame_is_superposed() {
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    let iterations = frame_iterations(&mut bufs, &[0.0; N]);
    assert!(iterations.iter().all(|&i| i <= 1), "{iterations:?}");
}

#[test]
fn without_room_for_the_columns_frames_fall_back_to_extrapolation() {
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    bufs.responses.truncate(N - 1);
    let iterations = frame_iterations(&mut bufs, &static_load());
    // From the third frame on the start is extrapolated: a straight push costs little, but
    // more than the superposition's nothing.
    assert!(iterations[3] * 2 < iterations[0], "{iterations:?}");
    assert!(iterations[1] > 1, "{iterations:?}");
}

/// A started session after one frame at tool position 1.
fn framed(s: &mut Session<'_, Sequential>) {
    started(s);
    assert!(matches!(
        s.handle(Request::LiveFrame { tool: tool_at(1.0) }),
        Response::LiveFrame(_)
    ));
}

fn field_chunk(
    s: &mut Session<'_, Sequential>,
    offset: u32,
    stride: u16,
    surface: Option<[u16; 3]>,
) -> deform_shared::live::FieldChunk {
    match s.handle(Request::ReadField {
        offset,
        stride,
        surface,
    }) {
        Response::Field(c) => c,
        other => panic!("{other:?}"),
    }
}

#[test]
fn the_field_arrives_quantised_to_its_scale() {
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    let mut s = bufs.session(info(), HARTS.harts);
    framed(&mut s);
    let want: Vec<Vec<f64>> = (0..3).map(|d| reference(d, f64::from(U0[d])).0).collect();
    let own: Vec<Vec<f64>> = (0..3).map(|d| read_direction(&mut s, d, N)).collect();
    let max = want.iter().flatten().fold(0f64, |m, v| m.max(v.abs()));
    for stride in [1u16, 3] {
        let chunk = field_chunk(&mut s, 1, stride, None);
        assert_eq!(chunk.offset, 1);
        // Rounded to the step 2^e, the largest component being at least 2^(e+14).
        let step = 2f64.powi(i32::from(chunk.exponent));
        assert!(step <= max * 2f64.powi(-14), "{step:e} for max {max:e}");
        let nodes: Vec<usize> = (1..N).step_by(usize::from(stride)).collect();
        let got: Vec<[f64; 3]> = chunk.displacements().collect();
        assert_eq!(got.len(), nodes.len());
        for (g, &node) in got.iter().zip(&nodes) {
            for d in 0..3 {
                assert!((g[d] - own[d][node]).abs() <= step / 2.0, "{node} {d}");
                assert!((g[d] - want[d][node]).abs() <= max * 1e-4, "{node} {d}");
            }
        }
    }
    // A 1 × 3 × 7 grid is all surface: the same chunk as every node.
    let all = field_chunk(&mut s, 2, 2, None);
    let surface = field_chunk(&mut s, 2, 2, Some([1, 3, 7]));
    assert_eq!(surface.values, all.values);
    assert_eq!(surface.exponent, all.exponent);
}

#[test]
fn bad_field_requests_are_refused_clearly() {
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    let mut s = bufs.session(info(), HARTS.harts);
    started(&mut s);
    let read = |s: &mut Session<'_, Sequential>, offset, stride, surface| {
        s.handle(Request::ReadField {
            offset,
            stride,
            surface,
        })
    };
    let live = |e| err(ErrorCode::Live(e));
    // Before any frame there is no field.
    assert_eq!(read(&mut s, 0, 1, None), ooo(SessionStep::NoSolution));
    assert!(matches!(
        s.handle(Request::LiveFrame { tool: tool_at(1.0) }),
        Response::LiveFrame(_)
    ));
    assert_eq!(read(&mut s, 0, 0, None), live(LiveError::BadStride));
    for grid in [[3, 3, 3], [0, 3, 7], [u16::MAX, u16::MAX, u16::MAX]] {
        assert_eq!(
            read(&mut s, 0, 1, Some(grid)),
            live(LiveError::BadGrid {
                grid,
                nodes: N as u32
            })
        );
    }
    for (offset, stride) in [(N as u32, 1), (u32::MAX, u16::MAX)] {
        assert_eq!(
            read(&mut s, offset, stride, None),
            live(LiveError::FieldOffset {
                offset,
                selected: N as u32
            })
        );
    }
    // The last node alone, with the largest stride.
    let last = field_chunk(&mut s, N as u32 - 1, u16::MAX, Some([7, 3, 1]));
    assert_eq!(last.values.len(), 3);
}

#[test]
fn bad_live_requests_are_refused_clearly() {
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    let mut s = bufs.session(info(), HARTS.harts);
    let live = |e| err(ErrorCode::Live(e));
    assert_eq!(
        s.handle(Request::LiveTool(tool_row(TOOL as u32))),
        ooo(SessionStep::NoMatrix)
    );
    load(&mut s, &chain());
    assert_eq!(
        s.handle(Request::LiveFrame { tool: tool_at(1.0) }),
        live(LiveError::NotStarted)
    );
    assert_eq!(
        s.handle(Request::LiveStart(params())),
        live(LiveError::NoTool)
    );
    let mut outside = tool_row(TOOL as u32);
    outside.node = N as u32;
    assert_eq!(
        s.handle(Request::LiveTool(outside)),
        live(LiveError::NodeOutOfRange { node: N as u32 })
    );
    let mut bad_column = tool_row(TOOL as u32);
    bad_column.row[0].column = 99;
    assert_eq!(
        s.handle(Request::LiveTool(bad_column)),
        live(LiveError::ColumnOutOfRange { column: 99 })
    );
    assert_eq!(
        s.handle(Request::LiveTool(tool_row(TOOL as u32))),
        Response::Ack
    );
    assert_eq!(
        s.handle(Request::LiveTool(tool_row(TOOL as u32))),
        live(LiveError::DuplicateNode { node: TOOL as u32 })
    );
    let mut nan = params();
    nan.scale[1] = f32::NAN;
    assert_eq!(
        s.handle(Request::LiveStart(nan)),
        live(LiveError::NotFinite)
    );
    assert!(matches!(
        s.handle(Request::LiveStart(params())),
        Response::LiveReady(_)
    ));
    // The static loads are not there yet.
    assert_eq!(
        s.handle(Request::LiveFrame { tool: tool_at(1.0) }),
        ooo(SessionStep::NoRhs)
    );
    let (e, m) = to_block(&static_load());
    for d in 0..3 {
        all_ack(
            &mut s,
            vector_requests(VectorSlot::Rhs { direction: d }, e, &m, CHUNK_LEN),
        );
    }
    assert_eq!(
        s.handle(Request::LiveForce { tool: tool_at(1.0) }),
        live(LiveError::NoFrame)
    );
    let two: heapless::Vec<[f32; 3], 8> = [[0.0; 3], [0.0; 3]].into_iter().collect();
    assert_eq!(
        s.handle(Request::LiveFrame { tool: two }),
        live(LiveError::ToolCount {
            expected: 1,
            got: 2
        })
    );
    let inf: heapless::Vec<[f32; 3], 8> = [[0.0, f32::INFINITY, 0.0]].into_iter().collect();
    assert_eq!(
        s.handle(Request::LiveFrame { tool: inf }),
        live(LiveError::NotFinite)
    );
    assert!(matches!(
        s.handle(Request::LiveFrame { tool: tool_at(1.0) }),
        Response::LiveFrame(_)
    ));
    // A new matrix forgets the tool set.
    load(&mut s, &chain());
    assert_eq!(
        s.handle(Request::LiveForce { tool: tool_at(1.0) }),
        live(LiveError::NotStarted)
    );
}

/// Random field requests after a frame: each is a chunk of exactly the nodes its selection
/// names, or a clear refusal; none panics.
#[test]
fn any_field_request_is_answered_or_refused() {
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    let mut s = bufs.session(info(), HARTS.harts);
    framed(&mut s);
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = |bound: u64| {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1);
        (state >> 33) % bound
    };
    let grids = [
        [1, 3, 7],
        [7, 3, 1],
        [21, 1, 1],
        [3, 3, 3],
        [0, 0, 0],
        [u16::MAX, 2, 1],
    ];
    for _ in 0..2000 {
        let offset = [next(25), u64::from(u32::MAX)][usize::from(next(8) == 0)] as u32;
        let stride = [next(25), u64::from(u16::MAX)][usize::from(next(8) == 0)] as u16;
        let surface = (next(2) == 0).then(|| grids[next(grids.len() as u64) as usize]);
        let answer = s.handle(Request::ReadField {
            offset,
            stride,
            surface,
        });
        let fits =
            surface.is_none_or(|g| g.iter().map(|&d| u64::from(d)).product::<u64>() == N as u64);
        if stride == 0 || !fits || offset >= N as u32 {
            assert!(
                matches!(answer, Response::Error(ErrorCode::Live(_))),
                "{answer:?}"
            );
            continue;
        }
        // Every grid of 21 nodes has a side below 3: its surface is every node.
        let nodes = (offset as usize..N)
            .step_by(usize::from(stride))
            .count()
            .min(56);
        match answer {
            Response::Field(c) => assert_eq!(c.values.len(), 3 * nodes, "{offset} {stride}"),
            other => panic!("{other:?}"),
        }
    }
}
