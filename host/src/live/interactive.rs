//! The interactive session behind `deform live --serve`: the tool goes where the browser puts
//! it instead of along the keyframes. The solver loop owns the target; it takes the newest
//! position from the [`Mailbox`], solves one full frame for it over the same [`LiveLink`] the
//! headless session uses (`LiveFrame`, then the quantised field with `ReadField`) and
//! publishes the frame for the browsers.
//!
//! With a force tool the browser's position is the load instead (1 grid unit = 1 N, every tool
//! node loaded alike) and a frame's `force` is the answer, the tool's mean displacement; the
//! mesh message's `kind` tells the page.

use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;

use super::field::FieldChoice;
use super::headless::CLOCK_HZ;
use super::link::LiveLink;
use super::serve::Mailbox;
use super::LiveSetup;
use crate::link::Port;

/// One solved frame, as the page shows it.
pub struct ViewFrame {
    pub force: [f64; 3],
    /// Per node, in the model's node order.
    pub u: Vec<[f64; 3]>,
    pub iterations: u32,
    /// Target cycles of the frame's solve (none on the host).
    pub cycles: Option<u32>,
    pub residual: f64,
}

/// Where the frames are solved.
pub trait FrameSolver {
    fn solve(&mut self, tool: &[[f64; 3]]) -> anyhow::Result<ViewFrame>;
    fn name(&self) -> &'static str;
    /// Whether frames go on while the tool rests: a dynamic tissue keeps moving (it relaxes
    /// after the tool stops), a quasi-static one is solved only for a new tool position.
    fn keeps_moving(&self) -> bool {
        false
    }
}

/// The target: a full frame (`LiveFrame`), then its field frame (`ReadField`).
pub struct TargetSolver<'l, 'a, P: Port> {
    pub link: &'l mut LiveLink<'a, P>,
    /// The nodes the field frames carry; the others are drawn at rest.
    pub field: FieldChoice,
    pub n: usize,
}

impl<P: Port> FrameSolver for TargetSolver<'_, '_, P> {
    fn solve(&mut self, tool: &[[f64; 3]]) -> anyhow::Result<ViewFrame> {
        let answer = self.link.frame(tool)?;
        let mut u = vec![[0.0; 3]; self.n];
        for (node, q) in self.link.field(self.field)?.nodes {
            u[node] = q;
        }
        Ok(ViewFrame {
            force: answer.value.map(f64::from),
            u,
            iterations: u32::from(answer.iterations),
            cycles: Some(answer.cycles),
            residual: f64::from(answer.residual),
        })
    }
    fn name(&self) -> &'static str {
        "target"
    }
}

/// The f64 reference alone (`--target host`), warm-started from the previous frame.
pub struct HostSolver<'a> {
    pub setup: &'a LiveSetup,
    pub warm: Option<[Vec<f64>; 3]>,
}

impl FrameSolver for HostSolver<'_> {
    fn solve(&mut self, tool: &[[f64; 3]]) -> anyhow::Result<ViewFrame> {
        let (u, force) = self.setup.converged(tool, self.warm.as_ref())?;
        let nodes = (0..u[0].len())
            .map(|i| [u[0][i], u[1][i], u[2][i]])
            .collect();
        self.warm = Some(u);
        Ok(ViewFrame {
            force,
            u: nodes,
            iterations: 0,
            cycles: None,
            residual: 0.0,
        })
    }
    fn name(&self) -> &'static str {
        "host"
    }
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

/// Runs the loop until the solver fails (the server threads end with the process).
pub fn run(
    setup: &LiveSetup,
    solver: &mut dyn FrameSolver,
    mailbox: &Arc<Mailbox>,
) -> anyhow::Result<()> {
    let limit = reach(setup);
    let mut tool = [0.0; 3];
    let mut frame = 0u64;
    let mut recent: Vec<Instant> = Vec::new();
    let mut arrived = Instant::now();
    let mut paused = false;
    loop {
        let moving = solver.keeps_moving() && !paused;
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
        let tools = vec![tool; setup.tools.len()];
        let view = solver.solve(&tools)?;
        frame += 1;
        let now = Instant::now();
        recent.retain(|t| now.duration_since(*t) < Duration::from_secs(1));
        recent.push(now);
        let u_max = view
            .u
            .iter()
            .map(|v| v.iter().fold(0.0f64, |m, x| m.max(x.abs())))
            .fold(0.0, f64::max);
        let message = FrameMessage {
            kind: "frame",
            frame,
            solver: solver.name(),
            tool,
            force: view.force,
            force_norm: view.force.iter().map(|f| f * f).sum::<f64>().sqrt(),
            iterations: view.iterations,
            cycles: view.cycles,
            frames_per_s_at_100mhz: view.cycles.map(|c| CLOCK_HZ / f64::from(c.max(1))),
            residual: view.residual,
            fps: recent.len() as f64,
            dropped,
            lag_ms: now.duration_since(arrived).as_secs_f64() * 1e3,
            paused,
            u_max,
            u: view.u.iter().flatten().map(|&v| v as f32).collect(),
        };
        mailbox.publish(serde_json::to_string(&message)?);
    }
}
