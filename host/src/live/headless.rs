//! The scripted live session (`deform live --headless`): the tool follows the scenario's
//! keyframes, one full frame per time step with force queries between frames and the field
//! every few frames, every frame checked against a converged f64 solve of the same tool
//! position. [`Report`] is the JSON the issue asks for.
//!
//! Both kinds of tool run the same script: for a force tool the "force" keys hold its answer,
//! the tool nodes' mean displacement, and the queries are displacement queries from the
//! compliance model (`tool` and `answer` in the report say which).

use deform_shared::protocol::PhaseCounters;
use serde::Serialize;

use super::field::FieldChoice;
use super::link::{FrameAnswer, LiveLink};
use super::LiveSetup;
use crate::bench::board::{WireBytes, WireCounter};
use crate::link::Port;
use crate::reference::{max_abs, max_abs_diff};

/// The target clock the per-second figures are quoted at (the thesis's 100 MHz).
pub const CLOCK_HZ: f64 = 100e6;

/// How the scripted session runs.
#[derive(Debug, Clone, Copy)]
pub struct Script {
    /// Read the quantised field every this many frames (0: never).
    pub field_every: u32,
    /// Which nodes a field frame carries.
    pub field: FieldChoice,
    /// Force queries from the local model between two frames.
    pub forces_per_frame: u32,
    /// Run the tool in real time at this frame rate (Hz): each frame takes the tool where the
    /// wall clock has it now, the frame slots it fell behind are dropped (never queued) and the
    /// lag is reported. `None`: every frame at its scripted time.
    pub pace: Option<f64>,
}

/// How far a paced session fell behind the tool.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct Lag {
    /// Frame slots skipped because the previous frame was still on its way.
    pub frames_dropped: u64,
    /// Largest wall time from a tool position to the answer for it, seconds.
    pub lag_max_s: f64,
}

/// One frame as the target answered it, and its check.
#[derive(Debug, Clone, Serialize)]
pub struct FrameRecord {
    pub frame: u32,
    pub t: f64,
    /// The tool's input: displacements, or loads for a force tool.
    pub tool: Vec<[f64; 3]>,
    /// The target's answer: the reaction force, or the mean tool displacement.
    pub force: [f64; 3],
    /// The same from the converged f64 solve.
    pub force_reference: [f64; 3],
    pub residual: f64,
    pub iterations: u32,
    pub cycles: u32,
    /// The retired instructions counted as `cycles` is (equal to it under QEMU `-icount`).
    pub instructions: u32,
    /// max |u − u_converged| / max |u_converged|.
    pub error_vs_converged: f64,
    pub bytes_up: u64,
    pub bytes_down: u64,
    pub u: [Vec<f64>; 3],
}

#[derive(Debug, Clone, Copy, Serialize)]
pub struct Spread {
    pub p50: f64,
    pub p99: f64,
    pub max: f64,
}

#[derive(Debug, Clone, Copy, Serialize)]
pub struct Rate {
    pub p50: f64,
    pub worst: f64,
}

#[derive(Debug, Clone, Copy, Serialize)]
pub struct IterationSpread {
    pub p50: f64,
    pub max: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct DownBytes {
    /// One full frame's answer, on the line.
    pub force: f64,
    /// One whole field frame (all its chunks), on the line.
    pub field: f64,
    /// The field frame per transmitted component.
    pub field_per_component: f64,
    /// Which nodes the field frames carried (`all`, `surface` or `stride:K`).
    pub field_selection: String,
    /// Nodes one field frame carried.
    pub field_nodes: usize,
    /// The target's cycles for building one field frame (all its chunks; the largest over
    /// the session), and its retired instructions.
    pub field_build_cycles: u64,
    pub field_build_instructions: u64,
}

/// Frames per second the serial line itself allows at a baud rate (8N1: 10 bits per byte).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct LinkRate {
    pub baud: u32,
    /// Full frames (request + answer) per second.
    pub frames_per_s: f64,
    /// Force queries per second.
    pub force_queries_per_s: f64,
    /// Field frames per second.
    pub field_frames_per_s: f64,
}

/// The report `--report FILE.json` writes.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub frames: u32,
    pub grid: [usize; 3],
    pub model: String,
    pub mvus: u8,
    pub tolerance: f64,
    pub cycle_budget: u64,
    /// The frames' cycles (the target's `mcycle`) and their retired instructions, and the
    /// cycles per instruction over all frames: equal under QEMU `-icount` (CPI 1), the RTL's on
    /// the LiteX SoC.
    pub frame_cycles: Spread,
    pub frame_instructions: Spread,
    pub frame_cpi: Option<f64>,
    pub frames_per_s_at_100mhz: Rate,
    /// Force updates per second at 100 MHz from the local model's measured cycles (worst).
    pub force_updates_per_s: f64,
    pub force_query_cycles_max: u64,
    pub force_query_instructions_max: u64,
    pub iterations: IterationSpread,
    pub residual_max: f64,
    pub error_vs_converged_max: f64,
    /// max |F − F_converged| / max |F_converged| over the frames.
    pub force_error_max: f64,
    /// The local model's force against a converged solve at the queried position, relative
    /// to max |F_converged|.
    pub model_force_error_max: f64,
    /// The quantised field against the frame's own solution, relative to max |u|.
    pub field_quantisation_error_max: f64,
    pub model_cycles: u64,
    pub model_instructions: u64,
    pub model_iterations: u32,
    /// Median over the frames, on the line (a frame's request).
    pub bytes_up_per_frame: f64,
    /// Median over the frames for `force` (a frame's answer); one field frame for `field`.
    pub bytes_down_per_frame: DownBytes,
    /// The largest frame up and down: retransmissions included (a slow first frame outlasts
    /// the host's retransmit timer).
    pub bytes_up_per_frame_max: u64,
    pub bytes_down_per_frame_max: u64,
    pub bytes_up_per_force_query: f64,
    pub bytes_down_per_force_query: f64,
    pub link_rates: Vec<LinkRate>,
    pub target_resets: u32,
    /// Paced sessions only.
    pub lag: Option<Lag>,
    /// The tool's kind: "displacement" or "force".
    pub tool: &'static str,
    /// What the "force" keys measure for this kind of tool.
    pub answer: &'static str,
}

/// The frames' retired instructions beside their cycles: the CPI, or that the two are equal
/// (QEMU `-icount`: one instruction per cycle by construction).
pub fn instructions_line(report: &Report) -> String {
    let i = &report.frame_instructions;
    match report.frame_cpi {
        Some(cpi) if report.frame_cycles.max != i.max || report.frame_cycles.p50 != i.p50 => {
            format!(
                "instructions p50 {:.0}, p99 {:.0}, max {:.0}: CPI {cpi:.2} over the frames",
                i.p50, i.p99, i.max
            )
        }
        _ => "(cycles = instructions retired: one per cycle under QEMU -icount)".to_string(),
    }
}

pub(crate) fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[i]
}

pub(crate) fn sorted(v: impl Iterator<Item = f64>) -> Vec<f64> {
    let mut v: Vec<f64> = v.collect();
    v.sort_by(f64::total_cmp);
    v
}

impl Spread {
    /// p50, p99 and max of `sorted`.
    pub(crate) fn of(sorted: &[f64]) -> Spread {
        Spread {
            p50: percentile(sorted, 0.5),
            p99: percentile(sorted, 0.99),
            max: sorted.last().copied().unwrap_or(0.0),
        }
    }
}

impl Rate {
    /// Frames per second at [`CLOCK_HZ`] for the median and the largest of `sorted` cycles.
    pub(crate) fn of(sorted: &[f64]) -> Rate {
        Rate {
            p50: CLOCK_HZ / percentile(sorted, 0.5).max(1.0),
            worst: CLOCK_HZ / sorted.last().copied().unwrap_or(0.0).max(1.0),
        }
    }
}

impl IterationSpread {
    pub(crate) fn of(sorted: &[f64]) -> IterationSpread {
        IterationSpread {
            p50: percentile(sorted, 0.5),
            max: sorted.last().copied().unwrap_or(0.0),
        }
    }
}

/// The baud rates the reports state the line's own frame rate for.
pub(crate) const BAUDS: [u32; 3] = [115_200, 921_600, 3_000_000];

/// How many messages of `bytes` the line carries per second at `baud` (8N1: 10 bits per
/// byte), 0 for none.
pub(crate) fn per_second(baud: u32, bytes: f64) -> f64 {
    if bytes > 0.0 {
        f64::from(baud) / 10.0 / bytes
    } else {
        0.0
    }
}

/// Relative error of a force against its reference, on the scale of the largest reference.
pub(crate) fn force_error(got: &[f64; 3], want: &[f64; 3], scale: f64) -> f64 {
    let diff = (0..3).map(|d| (got[d] - want[d]).abs()).fold(0.0, f64::max);
    diff / scale.max(f64::MIN_POSITIVE)
}

/// Measures what the session's messages cost on the line.
struct Meter<'a> {
    wire: &'a WireCounter,
    mark: WireBytes,
}

impl Meter<'_> {
    fn lap(&mut self) -> WireBytes {
        let now = self.wire.read();
        let d = now.since(self.mark);
        self.mark = now;
        d
    }
}

/// Runs the script: `tool_at(t)` gives the tool displacements at time t, frames are taken at
/// `times`. `on_frame` sees every frame (progress bars, CSV).
pub fn run<P: Port>(
    link: &mut LiveLink<'_, P>,
    setup: &LiveSetup,
    wire: &WireCounter,
    times: &[f64],
    tool_at: &dyn Fn(f64) -> Vec<[f64; 3]>,
    script: Script,
    mut on_frame: impl FnMut(&FrameRecord),
) -> anyhow::Result<(Vec<FrameRecord>, Summary)> {
    let mut meter = Meter {
        wire,
        mark: wire.read(),
    };
    let mut records = Vec::new();
    let mut summary = Summary::default();
    let mut warm: Option<[Vec<f64>; 3]> = None;
    let mut previous_t = 0.0;
    let clock = std::time::Instant::now();
    let end = times.last().copied().unwrap_or(0.0);
    let mut last_slot = 0u64;
    for (i, &scripted) in times.iter().enumerate() {
        let frame = i as u32 + 1;
        // Paced: the tool is where the wall clock has it; the slots missed are dropped.
        let t = match script.pace {
            None => scripted,
            Some(hz) => {
                let now = clock.elapsed().as_secs_f64().min(end);
                let slot = (now * hz) as u64;
                summary.lag.frames_dropped += slot.saturating_sub(last_slot + 1);
                last_slot = slot.max(last_slot + 1);
                now.max(previous_t)
            }
        };
        let sent_at = clock.elapsed().as_secs_f64();
        // Force queries on the way from the previous frame's position to this one.
        if i > 0 {
            for q in 1..=script.forces_per_frame {
                let s =
                    previous_t + (t - previous_t) * q as f64 / (script.forces_per_frame + 1) as f64;
                let tool = tool_at(s);
                meter.lap();
                let answer = link.force(&tool)?;
                let bytes = meter.lap();
                let (_, want) = setup.converged(&tool, warm.as_ref())?;
                let got = answer.value.map(f64::from);
                let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                summary.model_force_error =
                    summary
                        .model_force_error
                        .max(force_error(&got, &want, scale.max(1e-12)));
                summary.force_cycles = summary.force_cycles.max(u64::from(answer.cycles));
                summary.force_instructions = summary
                    .force_instructions
                    .max(u64::from(answer.instructions));
                summary.force_bytes = Some(bytes);
            }
        }
        let tool = tool_at(t);
        meter.lap();
        let answer: FrameAnswer = link.frame(&tool)?;
        let bytes = meter.lap();
        if script.pace.is_some() {
            // From the moment the tool was sampled at its position to the answer for it.
            let lag = clock.elapsed().as_secs_f64() - sent_at;
            summary.lag.lag_max_s = summary.lag.lag_max_s.max(lag);
        }
        let u = link.solution()?;
        meter.lap();
        let (want, force_ref) = setup.converged(&tool, warm.as_ref())?;
        let scale = want.iter().map(|v| max_abs(v)).fold(0.0, f64::max);
        let err = (0..3)
            .map(|d| max_abs_diff(&u[d], &want[d]))
            .fold(0.0, f64::max)
            / scale.max(f64::MIN_POSITIVE);
        if script.field_every > 0 && frame.is_multiple_of(script.field_every) {
            let field = link.field(script.field)?;
            let field_bytes = meter.lap();
            let umax = u.iter().map(|v| max_abs(v)).fold(0.0, f64::max);
            for (node, q) in &field.nodes {
                for d in 0..3 {
                    let e = (q[d] - u[d][*node]).abs() / umax.max(f64::MIN_POSITIVE);
                    summary.field_error = summary.field_error.max(e);
                }
            }
            summary.field = Some((field_bytes, 3 * field.nodes.len()));
            summary.field_cycles = summary.field_cycles.max(field.cycles);
            summary.field_instructions = summary.field_instructions.max(field.instructions);
        }
        let record = FrameRecord {
            frame,
            t,
            tool,
            force: answer.value.map(f64::from),
            force_reference: force_ref,
            residual: f64::from(answer.residual),
            iterations: u32::from(answer.iterations),
            cycles: answer.cycles,
            instructions: answer.instructions,
            error_vs_converged: err,
            bytes_up: bytes.sent,
            bytes_down: bytes.received,
            u,
        };
        on_frame(&record);
        records.push(record);
        warm = Some(want);
        previous_t = t;
    }
    Ok((records, summary))
}

/// What the script measured besides the frames.
#[derive(Debug, Clone, Copy, Default)]
pub struct Summary {
    pub model_force_error: f64,
    pub force_cycles: u64,
    pub force_instructions: u64,
    pub force_bytes: Option<WireBytes>,
    pub field: Option<(WireBytes, usize)>,
    pub field_error: f64,
    pub field_cycles: u64,
    pub field_instructions: u64,
    pub lag: Lag,
}

/// The session as the target ran it, for the report's header.
pub struct Session {
    pub grid: [usize; 3],
    pub model: String,
    pub mvus: u8,
    pub tolerance: f64,
    pub cycle_budget: u64,
    pub model_cycles: u64,
    pub model_instructions: u64,
    pub model_iterations: u32,
    pub resets: u32,
    pub paced: bool,
    pub kind: super::setup::ToolKind,
    /// The field frames' node selection.
    pub field: FieldChoice,
}

/// The report over `records`.
pub fn report(session: Session, records: &[FrameRecord], summary: &Summary) -> Report {
    let cycles = sorted(records.iter().map(|r| f64::from(r.cycles)));
    let instructions = sorted(records.iter().map(|r| f64::from(r.instructions)));
    let iterations = sorted(records.iter().map(|r| f64::from(r.iterations)));
    let force_scale = records
        .iter()
        .flat_map(|r| r.force_reference)
        .fold(0.0f64, |m, v| m.max(v.abs()));
    let force_error = records
        .iter()
        .map(|r| force_error(&r.force, &r.force_reference, force_scale))
        .fold(0.0, f64::max);
    let up = percentile(&sorted(records.iter().map(|r| r.bytes_up as f64)), 0.5);
    let down = percentile(&sorted(records.iter().map(|r| r.bytes_down as f64)), 0.5);
    let (field_bytes, field_components) = summary
        .field
        .map_or((0.0, 0), |(b, c)| (b.received as f64, c));
    let field_up = summary.field.map_or(0.0, |(b, _)| b.sent as f64);
    let force_bytes = summary.force_bytes.unwrap_or_default();
    let link_rates = BAUDS
        .into_iter()
        .map(|baud| LinkRate {
            baud,
            frames_per_s: per_second(baud, up + down),
            force_queries_per_s: per_second(baud, force_bytes.total() as f64),
            field_frames_per_s: per_second(baud, field_bytes + field_up),
        })
        .collect();
    Report {
        frames: records.len() as u32,
        grid: session.grid,
        model: session.model,
        mvus: session.mvus,
        tolerance: session.tolerance,
        cycle_budget: session.cycle_budget,
        frame_cycles: Spread::of(&cycles),
        frame_instructions: Spread::of(&instructions),
        frame_cpi: PhaseCounters {
            cycles: records.iter().map(|r| u64::from(r.cycles)).sum(),
            instructions: records.iter().map(|r| u64::from(r.instructions)).sum(),
        }
        .cpi(),
        frames_per_s_at_100mhz: Rate::of(&cycles),
        force_updates_per_s: if summary.force_cycles > 0 {
            CLOCK_HZ / summary.force_cycles as f64
        } else {
            0.0
        },
        force_query_cycles_max: summary.force_cycles,
        force_query_instructions_max: summary.force_instructions,
        iterations: IterationSpread::of(&iterations),
        residual_max: records.iter().map(|r| r.residual).fold(0.0, f64::max),
        error_vs_converged_max: records
            .iter()
            .map(|r| r.error_vs_converged)
            .fold(0.0, f64::max),
        force_error_max: force_error,
        model_force_error_max: summary.model_force_error,
        field_quantisation_error_max: summary.field_error,
        model_cycles: session.model_cycles,
        model_instructions: session.model_instructions,
        model_iterations: session.model_iterations,
        bytes_up_per_frame: up,
        bytes_up_per_frame_max: records.iter().map(|r| r.bytes_up).max().unwrap_or(0),
        bytes_down_per_frame_max: records.iter().map(|r| r.bytes_down).max().unwrap_or(0),
        bytes_down_per_frame: DownBytes {
            force: down,
            field: field_bytes,
            field_per_component: if field_components > 0 {
                field_bytes / field_components as f64
            } else {
                0.0
            },
            field_selection: session.field.to_string(),
            field_nodes: field_components / 3,
            field_build_cycles: summary.field_cycles,
            field_build_instructions: summary.field_instructions,
        },
        bytes_up_per_force_query: force_bytes.sent as f64,
        bytes_down_per_force_query: force_bytes.received as f64,
        link_rates,
        target_resets: session.resets,
        lag: session.paced.then_some(summary.lag),
        tool: session.kind.name(),
        answer: match session.kind {
            super::setup::ToolKind::Displacement => "reaction force summed over the tool nodes (N)",
            super::setup::ToolKind::Force => "mean displacement of the tool nodes (m)",
        },
    }
}
