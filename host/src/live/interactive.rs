//! The interactive session behind `deform live --serve`: the tool goes where the browser puts
//! it instead of along the keyframes. The loop owns the [`Engine`] (the same the headless
//! session drives); it takes the newest position from the [`Mailbox`], solves one full frame
//! for it (on a target: `LiveFrame`, then the quantised field with `ReadField`) and publishes
//! the frame for the browsers.
//!
//! With a force tool the browser's position is the load instead (1 grid unit = 1 N, every tool
//! node loaded alike) and a frame's `force` is the answer, the tool's mean displacement; the
//! mesh message's `kind` tells the page.

use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;

use super::engine::Engine;
use super::field::FieldChoice;
use super::serve::Mailbox;
use super::LiveSetup;
use crate::metrics::NOMINAL_CLOCK_HZ as CLOCK_HZ;

/// The displacement field the page draws after a frame: the line's quantised field at the
/// nodes `field` selects where the engine reads one (a target; the other nodes are drawn at
/// rest), else the engine's own solution.
fn view(engine: &mut dyn Engine, field: FieldChoice, n: usize) -> anyhow::Result<Vec<[f64; 3]>> {
    let mut u = vec![[0.0; 3]; n];
    match engine.field(field)? {
        Some(frame) => {
            for (node, q) in frame.nodes {
                u[node] = q;
            }
        }
        None => {
            if let Some(x) = engine.solution() {
                for (i, ui) in u.iter_mut().enumerate() {
                    *ui = [x[0][i], x[1][i], x[2][i]];
                }
            }
        }
    }
    Ok(u)
}

/// Sent once on every connection: what the page draws the frames on. `shown`: per node,
/// whether its displacement arrives (`--field`); the page draws only those nodes and the
/// springs between them, so a surface field shows the box's outside, not an inside at rest.
pub fn mesh_json(setup: &LiveSetup, shown: &[bool]) -> String {
    let grid = setup.model.grid();
    let nodes: Vec<[usize; 3]> = (0..setup.model.n())
        .map(|p| {
            let n = setup.model.node(p);
            [n.i, n.j, n.k]
        })
        .collect();
    serde_json::json!({
        "type": "mesh",
        "grid": [grid.nx(), grid.ny(), grid.nz()],
        "nodes": nodes,
        "fixed": setup.model.fixed_mask(),
        "tools": setup.tools,
        "kind": setup.kind.name(),
        "shown": shown,
    })
    .to_string()
}

/// One frame as the browsers get it.
#[derive(Serialize)]
struct FrameMessage {
    #[serde(rename = "type")]
    kind: &'static str,
    frame: u64,
    solver: &'static str,
    /// The tool displacement this frame was solved for.
    tool: [f64; 3],
    force: [f64; 3],
    force_norm: f64,
    iterations: u32,
    cycles: Option<u32>,
    frames_per_s_at_100mhz: Option<f64>,
    residual: f64,
    /// Frames solved per second of wall clock, over the last second.
    fps: f64,
    /// Tool positions replaced before they were solved.
    dropped: u64,
    /// From the browser's position arriving to its frame being published.
    lag_ms: f64,
    paused: bool,
    u_max: f64,
    /// x, y, z per node, f32 precision.
    u: Vec<f32>,
}

/// How far from rest the browser may take the tool, in grid units (the grid's half size).
fn reach(setup: &LiveSetup) -> f64 {
    let g = setup.model.grid();
    g.nx().max(g.ny()).max(g.nz()) as f64 / 2.0
}

/// Runs the loop until the engine fails or a SIGINT or SIGTERM comes (the server threads end
/// with the process). A dynamic engine's frames go on while the tool rests (the tissue keeps
/// moving) at one h of tissue time per h of wall clock at most, so it moves at its own speed;
/// a quasi-static one solves a frame for each new tool position.
pub fn run(
    setup: &LiveSetup,
    engine: &mut dyn Engine,
    field: FieldChoice,
    mailbox: &Arc<Mailbox>,
) -> anyhow::Result<()> {
    let limit = reach(setup);
    let mut tool = [0.0; 3];
    let mut frame = 0u32;
    let mut recent: Vec<Instant> = Vec::new();
    let mut arrived = Instant::now();
    let mut paused = false;
    let mut next_at: Option<Instant> = None;
    let started = Instant::now();
    while !crate::interrupt::requested() {
        let moving = engine.step().is_some() && !paused;
        let (dropped, solve) = {
            let idle = if moving { 0 } else { 250 };
            let mut inbox = mailbox.wait(Duration::from_millis(idle));
            let was_paused = paused;
            paused = inbox.paused;
            let mut solve = frame == 0 || was_paused != paused || (moving && !paused);
            if solve {
                arrived = Instant::now();
            }
            if inbox.reset {
                inbox.reset = false;
                tool = [0.0; 3];
                arrived = Instant::now();
                solve = true;
            } else if !inbox.paused {
                if let Some((u, at)) = inbox.tool.take() {
                    tool = u.map(|v| {
                        if v.is_finite() {
                            v.clamp(-limit, limit)
                        } else {
                            0.0
                        }
                    });
                    arrived = at;
                    solve = true;
                }
            }
            (inbox.dropped, solve)
        };
        if !solve {
            continue;
        }
        if let (Some(h), Some(at)) = (engine.step(), next_at) {
            std::thread::sleep(at.saturating_duration_since(Instant::now()));
            next_at = Some(Instant::now() + Duration::from_secs_f64(h));
        } else if let Some(h) = engine.step() {
            next_at = Some(Instant::now() + Duration::from_secs_f64(h));
        }
        let tools = vec![tool; setup.tools.len()];
        frame += 1;
        let solved = engine.frame(frame, started.elapsed().as_secs_f64(), &tools)?;
        let u = view(engine, field, setup.model.n())?;
        let now = Instant::now();
        recent.retain(|t| now.duration_since(*t) < Duration::from_secs(1));
        recent.push(now);
        let u_max = u
            .iter()
            .map(|v| v.iter().fold(0.0f64, |m, x| m.max(x.abs())))
            .fold(0.0, f64::max);
        let cycles = solved.cycles.map(|c| c.min(u64::from(u32::MAX)) as u32);
        let message = FrameMessage {
            kind: "frame",
            frame: u64::from(frame),
            solver: engine.name(),
            tool,
            force: solved.answer,
            force_norm: solved.answer.iter().map(|f| f * f).sum::<f64>().sqrt(),
            iterations: solved.iterations,
            cycles,
            frames_per_s_at_100mhz: cycles.map(|c| CLOCK_HZ / f64::from(c.max(1))),
            residual: solved.residual,
            fps: recent.len() as f64,
            dropped,
            lag_ms: now.duration_since(arrived).as_secs_f64() * 1e3,
            paused,
            u_max,
            u: u.iter().flatten().map(|&v| v as f32).collect(),
        };
        mailbox.publish(serde_json::to_string(&message)?);
    }
    Ok(())
}
