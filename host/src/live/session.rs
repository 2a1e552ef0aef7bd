//! The scripted session behind `deform live --headless`, over any [`Engine`]: the tool follows
//! the scenario's keyframes, one full frame per time step, with queries of the local model
//! between frames and the field every few frames where the engine has them; every frame goes
//! to the caller as it comes (the sink: CSV, ParaView series) and is kept, without its field,
//! for the report.
//!
//! Paced (`--pace HZ`, quasi-static frames): frame slot k is due at k/HZ seconds of wall clock
//! with the tool where the keyframes have it then; a frame that comes early waits for its slot,
//! a late one takes the newest slot due and the slots it skipped are counted as dropped. Only
//! solved frames are counted and reported: the same tool position is never solved twice.
//!
//! A SIGINT or SIGTERM ends the session after the frame under way ([`crate::interrupt`]).

use std::time::{Duration, Instant};

use anyhow::bail;
use serde::Serialize;

use super::engine::{Engine, Frame};
use super::field::FieldChoice;
use crate::board::WireBytes;
use crate::reference::max_abs;

/// When the frames are taken.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Timing {
    /// `frames` frames spread evenly over (0, `end`].
    Spread { frames: u32, end: f64 },
    /// `frames` steps of `h` (dynamic frames: frame i at i·h).
    Steps { frames: u32, h: f64 },
    /// In real time at `hz` frames per second of wall clock over (0, `end`].
    Paced { hz: f64, end: f64 },
}

/// How the scripted session runs.
#[derive(Debug, Clone, Copy)]
pub struct Script {
    pub timing: Timing,
    /// Read the quantised field every this many frames (0: never).
    pub field_every: u32,
    /// Which nodes a field frame carries.
    pub field: FieldChoice,
    /// Queries of the local model between two frames.
    pub queries_per_frame: u32,
}

/// Bytes one kept frame costs, tool input not counted: what a long session is checked against
/// before it starts.
pub const FRAME_RECORD_BYTES: u64 = std::mem::size_of::<Frame>() as u64;

impl Timing {
    /// Frames the session solves at most.
    pub fn frames(&self) -> u64 {
        match *self {
            Timing::Spread { frames, .. } | Timing::Steps { frames, .. } => u64::from(frames),
            Timing::Paced { hz, end } => ((end * hz).floor() as u64).max(1),
        }
    }

    /// The memory the session keeps for its report (a frame record per frame, `tools` tool
    /// nodes each), refused up front if the machine has less available, saying both.
    pub fn check_memory(&self, tools: usize) -> anyhow::Result<()> {
        let per_frame = FRAME_RECORD_BYTES + 24 * tools as u64;
        let need = self.frames().saturating_mul(per_frame);
        if let Some(available) = crate::memory::available() {
            if need > available / 2 {
                bail!(
                    "{} frames keep {} bytes each for the report: {} in all, and this machine has \
                     {} available; run fewer frames (--frames)",
                    self.frames(),
                    per_frame,
                    crate::memory::human(need),
                    crate::memory::human(available)
                );
            }
        }
        Ok(())
    }
}

/// How far a paced session fell behind the tool.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct Lag {
    /// Frame slots skipped because the previous frame was still on its way.
    pub frames_dropped: u64,
    /// Largest wall time from a tool position to the answer for it, seconds.
    pub lag_max_s: f64,
}

/// What the session measured besides the frames.
#[derive(Debug, Clone, Copy, Default)]
pub struct Summary {
    /// The local model's answer against a converged solve at the queried input, relative to
    /// its largest |answer|.
    pub model_force_error: f64,
    pub force_cycles: u64,
    pub force_instructions: u64,
    pub force_bytes: Option<WireBytes>,
    /// The last field frame's bytes and components.
    pub field: Option<(WireBytes, usize)>,
    pub field_error: f64,
    pub field_cycles: u64,
    pub field_instructions: u64,
    pub lag: Lag,
    /// A signal stopped the session before its last frame.
    pub interrupted: bool,
}

/// Relative error of an answer against its reference, on the scale of the largest reference.
pub fn force_error(got: &[f64; 3], want: &[f64; 3], scale: f64) -> f64 {
    let diff = (0..3).map(|d| (got[d] - want[d]).abs()).fold(0.0, f64::max);
    diff / scale.max(f64::MIN_POSITIVE)
}

/// The worst frame's answer against its reference, relative to the largest reference value.
pub fn force_error_max(records: &[Frame]) -> f64 {
    let scale = records
        .iter()
        .flat_map(|r| r.reference)
        .fold(0.0f64, |m, v| m.max(v.abs()));
    records
        .iter()
        .map(|r| force_error(&r.answer, &r.reference, scale))
        .fold(0.0, f64::max)
}

/// Hands out the frame times, waiting for a paced slot where the wall clock has not come to it.
struct Clock {
    timing: Timing,
    started: Instant,
    slot: u64,
}

impl Clock {
    /// The next frame's number and time, or `None` at the end.
    fn next(&mut self, lag: &mut Lag) -> Option<f64> {
        let last = self.slot;
        let t = match self.timing {
            Timing::Spread { frames, end } => {
                (last < u64::from(frames)).then(|| end * (last + 1) as f64 / f64::from(frames))
            }
            Timing::Steps { frames, h } => {
                (last < u64::from(frames)).then(|| (last + 1) as f64 * h)
            }
            Timing::Paced { hz, end } => {
                let slots = self.timing.frames();
                if last >= slots {
                    return None;
                }
                let now = self.started.elapsed().as_secs_f64();
                let due = (now * hz) as u64;
                let slot = if due <= last {
                    // Early: wait for the next slot.
                    let at = (last + 1) as f64 / hz;
                    std::thread::sleep(Duration::from_secs_f64((at - now).max(0.0)));
                    last + 1
                } else {
                    due.min(slots)
                };
                lag.frames_dropped += slot - last - 1;
                self.slot = slot;
                return Some((slot as f64 / hz).min(end));
            }
        };
        self.slot += 1;
        t
    }
}

/// Runs the script on `engine`: `tool_at(t)` gives the tool's input at time t. `on_frame`
/// sees every frame with the engine's full solution, if it holds one (the sink).
pub fn run(
    engine: &mut dyn Engine,
    script: &Script,
    tool_at: &dyn Fn(f64) -> Vec<[f64; 3]>,
    mut on_frame: impl FnMut(&Frame, Option<&[Vec<f64>; 3]>) -> anyhow::Result<()>,
) -> anyhow::Result<(Vec<Frame>, Summary)> {
    script.timing.check_memory(tool_at(0.0).len())?;
    let mut frames = Vec::new();
    let mut summary = Summary::default();
    let mut clock = Clock {
        timing: script.timing,
        started: Instant::now(),
        slot: 0,
    };
    let paced = matches!(script.timing, Timing::Paced { .. });
    let mut previous_t = 0.0;
    loop {
        if crate::interrupt::requested() {
            summary.interrupted = true;
            break;
        }
        let Some(t) = clock.next(&mut summary.lag) else {
            break;
        };
        let number = frames.len() as u32 + 1;
        if number > 1 {
            queries(engine, script, tool_at, (previous_t, t), &mut summary)?;
        }
        let tool = tool_at(t);
        let frame = engine.frame(number, t, &tool)?;
        if paced {
            // From the moment the tool was at its position to the answer for it.
            let lag = clock.started.elapsed().as_secs_f64() - t;
            summary.lag.lag_max_s = summary.lag.lag_max_s.max(lag);
        }
        if script.field_every > 0 && number.is_multiple_of(script.field_every) {
            sample_field(engine, script.field, &mut summary)?;
        }
        on_frame(&frame, engine.solution())?;
        frames.push(frame);
        previous_t = t;
    }
    Ok((frames, summary))
}

/// The local model's queries on the way from the previous frame's time to this one's.
fn queries(
    engine: &mut dyn Engine,
    script: &Script,
    tool_at: &dyn Fn(f64) -> Vec<[f64; 3]>,
    (from, to): (f64, f64),
    summary: &mut Summary,
) -> anyhow::Result<()> {
    let between = script.queries_per_frame;
    for q in 1..=between {
        let s = from + (to - from) * f64::from(q) / f64::from(between + 1);
        let Some(query) = engine.query(&tool_at(s))? else {
            return Ok(());
        };
        let scale = query.reference.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let error = force_error(&query.answer, &query.reference, scale.max(1e-12));
        summary.model_force_error = summary.model_force_error.max(error);
        summary.force_cycles = summary.force_cycles.max(u64::from(query.cycles));
        summary.force_instructions = summary
            .force_instructions
            .max(u64::from(query.instructions));
        summary.force_bytes = Some(query.bytes);
    }
    Ok(())
}

/// A field frame after the frame just solved, held against that frame's own solution.
fn sample_field(
    engine: &mut dyn Engine,
    choice: FieldChoice,
    summary: &mut Summary,
) -> anyhow::Result<()> {
    let Some(field) = engine.field(choice)? else {
        return Ok(());
    };
    if let Some(u) = engine.solution() {
        let umax = u.iter().map(|v| max_abs(v)).fold(0.0, f64::max);
        for (node, q) in &field.nodes {
            for d in 0..3 {
                let e = (q[d] - u[d][*node]).abs() / umax.max(f64::MIN_POSITIVE);
                summary.field_error = summary.field_error.max(e);
            }
        }
    }
    summary.field = Some((field.bytes, 3 * field.nodes.len()));
    summary.field_cycles = summary.field_cycles.max(field.cycles);
    summary.field_instructions = summary.field_instructions.max(field.instructions);
    Ok(())
}
