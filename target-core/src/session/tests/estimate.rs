//! The residual estimate of superposed live frames (issue 19, [`crate::superpose`]): frames
//! skip the exact r₀ pass, and none is accepted above its tolerance. Every frame's solution is
//! checked against the *true* residual ‖b − K·x‖/‖b‖, formed in `f64` from the solution read
//! back, the tool's input and the matrix's quantised values.

use deform_shared::live::{FrameReport, LiveParams, MotionReport};

use super::live::{chain, static_load, tool_row, N, SCALE, TOOL};
use super::*;
use crate::superpose::EXACT_EVERY;

fn params(tolerance: f32) -> LiveParams {
    LiveParams {
        tolerance,
        max_iterations: 500,
        cycle_budget: 0,
        scale: SCALE,
    }
}

/// ‖b − K·x‖/‖b‖ of direction d's solution in `s` for the chain's static load plus
/// `extra` (the tool's part of b, by node).
fn true_residual(s: &mut Session<'_, Sequential>, d: u8, k: &[Vec<f64>], b: &[f64]) -> f64 {
    let x = read_direction(s, d, N);
    let rr: f64 = (0..N)
        .map(|i| {
            let kx: f64 = (0..N).map(|j| k[i][j] * x[j]).sum();
            (b[i] - kx).powi(2)
        })
        .sum();
    (rr / b.iter().map(|v| v * v).sum::<f64>()).sqrt()
}

/// A tool path with smooth stretches, a reversal and a jump: frame k's displacement.
fn path(k: usize) -> f32 {
    let t = k as f32;
    let jump = if k >= 40 { 3.0 } else { 0.0 };
    0.05 * t + 0.4 * (t / 7.0).sin() + jump
}

struct Run {
    /// Per frame, the largest true residual over the directions.
    residuals: Vec<f64>,
    /// Per frame and direction, the frames since the last exact pass (0: this frame's r came
    /// from an exact pass or a solve; `None`: no estimate).
    estimated: Vec<[Option<u32>; 3]>,
    iterations: Vec<u16>,
}

/// A displacement tool on the chain with the static sine load, `frames` frames along
/// [`path`] at tolerance `tol`.
fn displacement_run(tol: f32, frames: usize) -> Run {
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    let mut s = bufs.session(info(), HARTS.harts);
    load(&mut s, &chain());
    assert_eq!(
        s.handle(Request::LiveTool(tool_row(TOOL as u32))),
        Response::Ack
    );
    assert!(matches!(
        s.handle(Request::LiveStart(params(tol))),
        Response::LiveReady(_)
    ));
    let (e, m) = to_block(&static_load());
    for d in 0..3 {
        all_ack(
            &mut s,
            vector_requests(VectorSlot::Rhs { direction: d }, e, &m, CHUNK_LEN),
        );
    }
    let k = dense(&chain());
    let u0 = [0.3f32, -0.2, 0.05];
    let mut run = Run {
        residuals: Vec::new(),
        estimated: Vec::new(),
        iterations: Vec::new(),
    };
    for frame in 1..=frames {
        let tool: heapless::Vec<[f32; 3], 8> = [u0.map(|u| u * path(frame))].into_iter().collect();
        let report: FrameReport = match s.handle(Request::LiveFrame { tool: tool.clone() }) {
            Response::LiveFrame(r) => r,
            other => panic!("{other:?}"),
        };
        assert!(report.residual <= tol, "frame {frame}: {report:?}");
        let mut worst = 0f64;
        for d in 0..3 {
            let u = f64::from(tool[0][d]);
            let mut b = static_load();
            b[TOOL - 1] += u;
            b[TOOL + 1] += u;
            b[TOOL] = 2.0 * u;
            worst = worst.max(true_residual(&mut s, d as u8, &k, &b));
        }
        run.residuals.push(worst);
        run.estimated
            .push(s.live_estimates().map(|e| e.map(|e| e.frames)));
        run.iterations.push(report.iterations);
    }
    run
}

#[test]
fn no_frame_is_accepted_above_its_tolerance() {
    for tol in [1e-3f32, 1e-5] {
        let run = displacement_run(tol, 70);
        // The true residual of the target's numbers: its b differs from the f64 one by
        // rounding at 2^−29 of max |b|, far below these tolerances.
        for (frame, r) in run.residuals.iter().enumerate() {
            assert!(
                *r <= f64::from(tol) * (1.0 + 1e-3),
                "tol {tol} frame {}: {r:e}",
                frame + 1
            );
        }
        // Most frames skip the exact pass: their r is carried over (frames > 0), and an exact
        // pass renews it at least every EXACT_EVERY frames.
        let carried = run
            .estimated
            .iter()
            .filter(|e| e.iter().flatten().all(|&f| f > 0))
            .count();
        assert!(
            carried * 2 > run.estimated.len(),
            "tol {tol}: {:?}",
            run.estimated
        );
        assert!(run
            .estimated
            .iter()
            .flatten()
            .flatten()
            .all(|&f| f < EXACT_EVERY));
    }
}

#[test]
fn after_the_first_frame_the_superposition_leaves_nothing_to_iterate() {
    // The chain is linear: every superposed frame is exact up to rounding, a 3-unit jump of
    // the tool at frame 40 included; only the first, which does not know the static load's
    // part of the solution, iterates.
    let run = displacement_run(1e-5, 45);
    assert!(run.iterations[0] > 2, "{:?}", run.iterations);
    assert!(
        run.iterations[1..].iter().all(|&i| i == 0),
        "{:?}",
        run.iterations
    );
    assert!(run.residuals.iter().all(|&r| r <= 1e-5 * (1.0 + 1e-3)));
}

#[test]
fn force_tool_frames_skip_the_exact_pass_too() {
    // A force tool at two nodes of a chain whose node 0 is fixed (its row and column
    // eliminated): b's tool rows take the loads.
    let fixed_chain = encode(N, 8, 18, |i| {
        laplacian_row(N)(i)
            .into_iter()
            .filter(|&(c, _)| (i == 0) == (c == 0))
            .collect()
    });
    let nodes = [7u32, 15];
    let mut bufs = OwnedStorage::new(4 * N, 8, N);
    let mut s = bufs.session(info(), HARTS.harts);
    load(&mut s, &fixed_chain);
    let req = Request::LiveForceTool {
        nodes: nodes.iter().copied().collect(),
    };
    assert_eq!(s.handle(req), Response::Ack);
    assert!(matches!(
        s.handle(Request::LiveStart(params(1e-5))),
        Response::LiveReady(_)
    ));
    let load0: Vec<f64> = (0..N)
        .map(|i| if i == 0 { 0.0 } else { 0.1 * (i as f64).sin() })
        .collect();
    let (e, m) = to_block(&load0);
    for d in 0..3 {
        all_ack(
            &mut s,
            vector_requests(VectorSlot::Rhs { direction: d }, e, &m, CHUNK_LEN),
        );
    }
    let k = dense(&fixed_chain);
    let f0 = [0.3f32, -0.2, 0.05];
    let mut carried = 0;
    for frame in 1..=40 {
        let load: heapless::Vec<[f32; 3], 8> = (0..nodes.len())
            .map(|j| f0.map(|f| f * path(frame) * (1.0 + j as f32)))
            .collect();
        let report: MotionReport = match s.handle(Request::LiveLoad { load: load.clone() }) {
            Response::LiveMotion(r) => r,
            other => panic!("{other:?}"),
        };
        assert!(report.residual <= 1e-5, "frame {frame}: {report:?}");
        for d in 0..3 {
            let mut b = load0.clone();
            for (&t, l) in nodes.iter().zip(&load) {
                b[t as usize] += f64::from(l[d]) / f64::from(SCALE[d]);
            }
            let r = true_residual(&mut s, d as u8, &k, &b);
            assert!(r <= 1e-5 * (1.0 + 1e-3), "frame {frame} d {d}: {r:e}");
        }
        let estimates = s.live_estimates();
        carried += estimates.iter().flatten().filter(|e| e.frames > 0).count();
    }
    assert!(
        carried > 20,
        "{carried} of 40 frames skipped the exact pass"
    );
}
