//! Force tools (version 9) on a 1-D chain against a direct f64 solve: frames, the compliance
//! model's prediction, and every refusal.

use deform_shared::live::{Coupling, LiveError, ToolRow};
use deform_shared::qformat::quantize;

use super::live::{params, sine_load, N, SCALE};
use super::*;

/// Node 0 is fixed: its row keeps only its diagonal and no other row couples to it.
const FIXED: usize = 0;
const F: u8 = 18;
const F0: [f32; 3] = [0.3, -0.2, 0.05];

type Tool = heapless::Vec<[f32; 3], 8>;

fn chain() -> Encoded {
    encode(N, 8, F, |i| {
        laplacian_row(N)(i)
            .into_iter()
            .filter(|&(c, _)| (i == FIXED) == (c == FIXED))
            .collect()
    })
}

fn static_load() -> Vec<f64> {
    sine_load(FIXED)
}

fn nodes(list: &[u32]) -> heapless::Vec<u32, 8> {
    list.iter().copied().collect()
}

/// The converged displacements of direction d with `load[t]` at `tools[t]`.
fn reference(d: usize, tools: &[u32], load: &[[f32; 3]]) -> Vec<f64> {
    let mut b = static_load();
    for (&t, l) in tools.iter().zip(load) {
        b[t as usize] += f64::from(l[d]) / f64::from(SCALE[d]);
    }
    direct_solve(dense(&chain()), b)
}

fn mean_at(x: &[f64], tools: &[u32]) -> f64 {
    tools.iter().map(|&t| x[t as usize]).sum::<f64>() / tools.len() as f64
}

fn upload_static(s: &mut Session<'_, Sequential>) {
    let (e, m) = to_block(&static_load());
    for d in 0..3 {
        all_ack(
            s,
            vector_requests(VectorSlot::Rhs { direction: d }, e, &m, CHUNK_LEN),
        );
    }
}

fn started(s: &mut Session<'_, Sequential>, tools: &[u32]) {
    load(s, &chain());
    let req = Request::LiveForceTool {
        nodes: nodes(tools),
    };
    assert_eq!(s.handle(req), Response::Ack);
    match s.handle(Request::LiveStart(params())) {
        Response::LiveReady(r) => {
            let solves = tools.len().div_ceil(3) as u8;
            assert!(r.converged && r.solves == solves, "{r:?}");
        }
        other => panic!("{other:?}"),
    }
    upload_static(s);
}

fn load_at(t: f32, nodes: usize) -> Tool {
    (0..nodes)
        .map(|j| F0.map(|f| f * t * (1.0 + j as f32)))
        .collect()
}

/// Full frames answer the tools' mean displacement of a direct solve, the field is that
/// solve's, and the compliance model predicts the next frame (the chain is linear, so up to
/// the solves' tolerance).
fn frames_and_model_match(tools: &[u32]) {
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    let mut s = bufs.session(info(), HARTS.harts);
    started(&mut s, tools);
    let mut predicted: Option<[f32; 3]> = None;
    let mut iterations = Vec::new();
    for step in 1..=4 {
        let load = load_at(step as f32 * 0.7, tools.len());
        let report = match s.handle(Request::LiveLoad { load: load.clone() }) {
            Response::LiveMotion(r) => r,
            other => panic!("{other:?}"),
        };
        assert!(report.residual <= 1e-7, "{report:?}");
        iterations.push(report.iterations);
        for d in 0..3 {
            let x = reference(d, tools, &load);
            let got = read_direction(&mut s, d as u8, N);
            assert!(max_rel_err(&got, &x) < 1e-5, "step {step} d {d}");
            let want = mean_at(&x, tools);
            let scale = x.iter().fold(0f64, |m, v| m.max(v.abs()));
            let err = (f64::from(report.displacement[d]) - want).abs();
            assert!(err <= 1e-5 * scale, "{report:?} vs {want}");
            if let Some(p) = predicted {
                let err = (f64::from(p[d]) - want).abs();
                assert!(err <= 1e-4 * scale, "{p:?} vs {want}");
            }
        }
        let next = load_at((step + 1) as f32 * 0.7, tools.len());
        predicted = match s.handle(Request::LiveLoadQuery { load: next }) {
            Response::LiveMotionQuery(r) => Some(r.displacement),
            other => panic!("{other:?}"),
        };
    }
    // After the first frame (whose static part is unknown) the compliance columns'
    // superposition, scaled by 1/k_d per direction, leaves (almost) nothing to iterate: the
    // columns are solved to 1e-7, this test's frame tolerance too, so with four of them
    // adding their errors a few iterations remain.
    assert!(iterations[0] > 10, "{iterations:?}");
    assert!(iterations[1..].iter().all(|&i| i <= 3), "{iterations:?}");
}

#[test]
fn a_one_node_force_tool_matches_a_direct_solve() {
    frames_and_model_match(&[10]);
}

#[test]
fn a_four_node_force_tool_answers_the_mean_displacement() {
    frames_and_model_match(&[3, 10, 11, 20]);
}

fn displacement_row() -> ToolRow {
    let raw = |v: f64| quantize(v, F).unwrap();
    ToolRow {
        node: 10,
        diagonal: raw(2.0),
        row: [9, 11]
            .map(|column| Coupling {
                column,
                value: raw(-1.0),
            })
            .into_iter()
            .collect(),
    }
}

#[test]
fn bad_force_tool_requests_are_refused_clearly() {
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    let mut s = bufs.session(info(), HARTS.harts);
    let live = |e| err(ErrorCode::Live(e));
    let tool = |list: &[u32]| Request::LiveForceTool { nodes: nodes(list) };
    assert_eq!(s.handle(tool(&[10])), ooo(SessionStep::NoMatrix));
    load(&mut s, &chain());
    let out = N as u32;
    assert_eq!(
        s.handle(tool(&[3, out])),
        live(LiveError::NodeOutOfRange { node: out })
    );
    assert_eq!(
        s.handle(tool(&[4, 4])),
        live(LiveError::DuplicateNode { node: 4 })
    );
    // A refused set leaves no tool behind.
    assert_eq!(
        s.handle(Request::LiveStart(params())),
        live(LiveError::NoTool)
    );
    // A load on the fixed node moves nothing: refused when the model is built.
    assert_eq!(s.handle(tool(&[5, FIXED as u32])), Response::Ack);
    assert_eq!(
        s.handle(Request::LiveStart(params())),
        live(LiveError::FixedToolNode { node: FIXED as u32 })
    );
    assert_eq!(
        s.handle(Request::LiveLoad {
            load: load_at(1.0, 2)
        }),
        live(LiveError::NotStarted)
    );
    // The kinds do not mix within one set.
    assert_eq!(s.handle(tool(&[10])), Response::Ack);
    assert_eq!(
        s.handle(Request::LiveTool(displacement_row())),
        live(LiveError::MixedKinds)
    );
    load(&mut s, &chain());
    assert_eq!(
        s.handle(Request::LiveTool(displacement_row())),
        Response::Ack
    );
    assert_eq!(s.handle(tool(&[10])), live(LiveError::MixedKinds));
    // A displacement session refuses force frames, and the other way round.
    assert!(matches!(
        s.handle(Request::LiveStart(params())),
        Response::LiveReady(_)
    ));
    upload_static(&mut s);
    assert_eq!(
        s.handle(Request::LiveLoad {
            load: load_at(1.0, 1)
        }),
        live(LiveError::WrongKind)
    );
    started(&mut s, &[10]);
    assert_eq!(
        s.handle(Request::LiveFrame {
            tool: load_at(1.0, 1)
        }),
        live(LiveError::WrongKind)
    );
    assert_eq!(
        s.handle(Request::LiveLoadQuery {
            load: load_at(1.0, 1)
        }),
        live(LiveError::NoFrame)
    );
    assert_eq!(
        s.handle(Request::LiveLoad {
            load: load_at(1.0, 2)
        }),
        live(LiveError::ToolCount {
            expected: 1,
            got: 2
        })
    );
    let nan: Tool = [[0.0, f32::NAN, 0.0]].into_iter().collect();
    assert_eq!(
        s.handle(Request::LiveLoad { load: nan }),
        live(LiveError::NotFinite)
    );
    // A load whose displacement no f32 holds: the answer is refused, not sent as inf.
    let huge: Tool = [[f32::MAX, 0.0, f32::MAX]].into_iter().collect();
    assert_eq!(
        s.handle(Request::LiveLoad { load: huge }),
        live(LiveError::NotFinite)
    );
    assert!(matches!(
        s.handle(Request::LiveLoad {
            load: load_at(1.0, 1)
        }),
        Response::LiveMotion(_)
    ));
}
