//! The JSON report of a headless quasi-static session (`deform live --headless --report`):
//! the target's frame cycles and rates at 100 MHz, iterations, residuals, the error against a
//! converged solve, the local model, the field and the bytes on the line, over the kept
//! [`Frame`]s. Both kinds of tool share it: for a force tool the "force" keys hold its answer,
//! the tool nodes' mean displacement (`tool` and `answer` say which). A session on the host
//! gets [`HostReport`], a dynamic one [`super::dynamic_report`].

use deform_shared::protocol::PhaseCounters;
use serde::Serialize;

use super::engine::Frame;
use super::field::FieldChoice;
use super::session::{force_error_max, Lag, Summary};
use super::setup::ToolKind;
use super::stats::{per_second, percentile, sorted, BAUDS};
pub use super::stats::{IterationSpread, Rate, Spread};
// The target clock the per-second figures are quoted at (the thesis's 100 MHz).
use crate::metrics::NOMINAL_CLOCK_HZ as CLOCK_HZ;

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

/// Frames whose solve ran past `--cycle-budget`: the budget stops starting new iterations, so
/// the last one can overshoot it.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct OverBudget {
    pub frames: u32,
    pub worst_cycles: u64,
}

/// Where and how the session ran: the report's first keys.
#[derive(Debug, Clone, Serialize)]
pub struct Header {
    /// `qemu`, `litex` or `port`, as dynamic reports name it.
    pub target: String,
    pub grid: [usize; 3],
    pub model: String,
    pub mvus: u8,
    pub tolerance: f64,
    pub cycle_budget: u64,
}

/// The report `--report FILE.json` writes.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub frames: u32,
    #[serde(flatten)]
    pub header: Header,
    /// With a budget: the frames over it (none: 0 and 0).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub over_budget: Option<OverBudget>,
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
    /// The largest frame up and down, each frame's first copy (as all byte counts here).
    pub bytes_up_per_frame_max: u64,
    pub bytes_down_per_frame_max: u64,
    pub bytes_up_per_force_query: f64,
    pub bytes_down_per_force_query: f64,
    pub link_rates: Vec<LinkRate>,
    pub target_resets: u32,
    /// Frames the host sent again (a loaded host or a noisy line), left out of the bytes.
    pub link_retransmits: u64,
    /// Paced sessions only.
    pub lag: Option<Lag>,
    /// The tool's kind: "displacement" or "force".
    pub tool: &'static str,
    /// What the "force" keys measure for this kind of tool.
    pub answer: &'static str,
}

/// The session as the target ran it, for the report's header.
pub struct Session {
    pub header: Header,
    pub model_cycles: u64,
    pub model_instructions: u64,
    pub model_iterations: u32,
    pub resets: u32,
    pub retransmits: u64,
    pub paced: bool,
    pub kind: ToolKind,
    /// The field frames' node selection.
    pub field: FieldChoice,
}

/// The report over `records`.
pub fn report(session: Session, records: &[Frame], summary: &Summary) -> Report {
    let cycles = sorted(records.iter().map(|r| r.cycles.unwrap_or(0) as f64));
    let instructions = sorted(records.iter().map(|r| r.instructions.unwrap_or(0) as f64));
    let iterations = sorted(records.iter().map(|r| f64::from(r.iterations)));
    let up = percentile(&sorted(records.iter().map(|r| r.bytes.sent as f64)), 0.5);
    let down = percentile(
        &sorted(records.iter().map(|r| r.bytes.received as f64)),
        0.5,
    );
    let (field_bytes, field_components) = summary
        .field
        .map_or((0.0, 0), |(b, c)| (b.received as f64, c));
    let field_up = summary.field.map_or(0.0, |(b, _)| b.sent as f64);
    let force_bytes = summary.force_bytes.unwrap_or_default();
    let over_budget = over_budget(records, session.header.cycle_budget);
    let link_rates = link_rates(
        up + down,
        force_bytes.total() as f64,
        field_bytes + field_up,
    );
    Report {
        frames: records.len() as u32,
        header: session.header,
        over_budget,
        frame_cycles: Spread::of(&cycles),
        frame_instructions: Spread::of(&instructions),
        frame_cpi: PhaseCounters {
            cycles: records.iter().filter_map(|r| r.cycles).sum(),
            instructions: records.iter().filter_map(|r| r.instructions).sum(),
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
            .filter_map(|r| r.error_vs_converged)
            .fold(0.0, f64::max),
        force_error_max: force_error_max(records),
        model_force_error_max: summary.model_force_error,
        field_quantisation_error_max: summary.field_error,
        model_cycles: session.model_cycles,
        model_instructions: session.model_instructions,
        model_iterations: session.model_iterations,
        bytes_up_per_frame: up,
        bytes_up_per_frame_max: records.iter().map(|r| r.bytes.sent).max().unwrap_or(0),
        bytes_down_per_frame_max: records.iter().map(|r| r.bytes.received).max().unwrap_or(0),
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
        link_retransmits: session.retransmits,
        lag: session.paced.then_some(summary.lag),
        tool: session.kind.name(),
        answer: match session.kind {
            ToolKind::Displacement => "reaction force summed over the tool nodes (N)",
            ToolKind::Force => "mean displacement of the tool nodes (m)",
        },
    }
}

/// The frames, force queries and field frames per second that each line rate allows, from
/// their bytes each way.
fn link_rates(frame_bytes: f64, force_bytes: f64, field_bytes: f64) -> Vec<LinkRate> {
    BAUDS
        .into_iter()
        .map(|baud| LinkRate {
            baud,
            frames_per_s: per_second(baud, frame_bytes),
            force_queries_per_s: per_second(baud, force_bytes),
            field_frames_per_s: per_second(baud, field_bytes),
        })
        .collect()
}

/// With a cycle budget, how many frames went over it and the worst of them.
fn over_budget(records: &[Frame], budget: u64) -> Option<OverBudget> {
    let over = records
        .iter()
        .filter_map(|r| r.cycles)
        .filter(|&c| budget > 0 && c > budget);
    (budget > 0).then(|| OverBudget {
        frames: over.clone().count() as u32,
        worst_cycles: over.max().unwrap_or(0),
    })
}

/// The local model's name in the summary (ten columns, as the other labels).
pub fn model_label(kind: ToolKind) -> &'static str {
    match kind {
        ToolKind::Displacement => "force model",
        ToolKind::Force => "compliance",
    }
}

impl Report {
    /// The frames' retired instructions beside their cycles: the CPI, or that the two are equal
    /// (QEMU `-icount`: one instruction per cycle by construction).
    pub fn instructions_line(&self) -> String {
        let i = &self.frame_instructions;
        match self.frame_cpi {
            Some(cpi) if self.frame_cycles.max != i.max || self.frame_cycles.p50 != i.p50 => {
                format!(
                    "instructions p50 {:.0}, p99 {:.0}, max {:.0}: CPI {cpi:.2} over the frames",
                    i.p50, i.p99, i.max
                )
            }
            _ => "(cycles = instructions retired: one per cycle under QEMU -icount)".to_string(),
        }
    }

    /// The lines a person reads after the session.
    pub fn summary(&self, kind: ToolKind) -> String {
        use std::fmt::Write;
        let mut out = String::new();
        writeln!(
                out,
        "frames      {}: cycles p50 {:.0}, p99 {:.0}, max {:.0} → {:.0} frames/s at 100 MHz (worst {:.0})",
        self.frames,
        self.frame_cycles.p50,
        self.frame_cycles.p99,
        self.frame_cycles.max,
        self.frames_per_s_at_100mhz.p50,
        self.frames_per_s_at_100mhz.worst
    ).unwrap();
        writeln!(out, "            {}", self.instructions_line()).unwrap();
        let (answer, unit) = match kind {
            ToolKind::Displacement => ("force", "F"),
            ToolKind::Force => ("tool motion", "ū"),
        };
        writeln!(
                out,
        "accuracy    error vs converged ≤ {:.2e} of max |u|, {answer} ≤ {:.2e}, residual ≤ {:.2e}, iterations p50 {} max {}",
        self.error_vs_converged_max,
        self.force_error_max,
        self.residual_max,
        self.iterations.p50,
        self.iterations.max
    ).unwrap();
        writeln!(
            out,
            "{} {:.0} updates/s at 100 MHz ({} cycles per query), error ≤ {:.2e} of max |{unit}|",
            model_label(kind),
            self.force_updates_per_s,
            self.force_query_cycles_max,
            self.model_force_error_max
        )
        .unwrap();
        writeln!(
            out,
            "line        {} B up / {} B down per frame (median; max {} / {})",
            self.bytes_up_per_frame,
            self.bytes_down_per_frame.force,
            self.bytes_up_per_frame_max,
            self.bytes_down_per_frame_max,
        )
        .unwrap();
        let field = &self.bytes_down_per_frame;
        writeln!(
                out,
        "field       {} ({} nodes): {} B per frame, {:.3} B per component, quantisation ≤ {:.1e}, built in {} cycles",
        field.field_selection,
        field.field_nodes,
        field.field,
        field.field_per_component,
        self.field_quantisation_error_max,
        field.field_build_cycles
    ).unwrap();
        for r in &self.link_rates {
            writeln!(
                out,
                "  {:>9} baud: {:.0} frames/s, {:.0} force queries/s, {:.1} field frames/s",
                r.baud, r.frames_per_s, r.force_queries_per_s, r.field_frames_per_s
            )
            .unwrap();
        }
        if let Some(lag) = self.lag {
            writeln!(
                out,
                "pace        {} frame slot(s) dropped, lag up to {:.3} s",
                lag.frames_dropped, lag.lag_max_s
            )
            .unwrap();
        }
        if self.link_retransmits > 0 {
            writeln!(
                out,
                "resent      {} frame(s) sent again (a loaded host or a noisy line), not in the bytes above",
                self.link_retransmits
            )
            .unwrap();
        }
        if self.target_resets > 0 {
            writeln!(
                out,
                "target reset {} time(s); set up again each time",
                self.target_resets
            )
            .unwrap();
        }
        if let Some(over) = self.over_budget {
            writeln!(
                out,
                "budget      {} of {} frame(s) over the {} cycles, worst {} cycles",
                over.frames, self.frames, self.header.cycle_budget, over.worst_cycles
            )
            .unwrap();
        }
        out
    }
}

/// One frame of a session on the host, as its report lists it.
#[derive(Debug, Clone, Serialize)]
pub struct HostFrame {
    pub t: f64,
    pub tool: Vec<[f64; 3]>,
    /// Displacement tools: the reaction force.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub force: Option<[f64; 3]>,
    /// Force tools: the tool nodes' mean displacement.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub displacement: Option<[f64; 3]>,
    pub max_u: f64,
}

/// `--report` of a quasi-static session on the host: the tool path and the answers, no target
/// figures.
#[derive(Debug, Clone, Serialize)]
pub struct HostReport {
    pub frames: usize,
    pub target: &'static str,
    pub tool: &'static str,
    pub per_frame: Vec<HostFrame>,
}

/// The host report over `records`.
pub fn host_report(kind: ToolKind, records: &[Frame]) -> HostReport {
    let force_tool = kind == ToolKind::Force;
    HostReport {
        frames: records.len(),
        target: "host",
        tool: kind.name(),
        per_frame: records
            .iter()
            .map(|r| HostFrame {
                t: r.t,
                tool: r.tool.clone(),
                force: (!force_tool).then_some(r.answer),
                displacement: force_tool.then_some(r.answer),
                max_u: r.max_u,
            })
            .collect(),
    }
}

impl HostReport {
    /// The line a person reads after the session.
    pub fn summary(&self) -> String {
        let Some(last) = self.per_frame.last() else {
            return "host        no frame solved".into();
        };
        let (what, v, unit) = match (last.force, last.displacement) {
            (Some(f), _) => ("force", f, "N"),
            (None, Some(u)) => ("tool displacement", u, "m"),
            (None, None) => ("force", [0.0; 3], "N"),
        };
        format!(
            "host        {} frames solved by the f64 reference; last {what} ({:.6e}, {:.6e}, {:.6e}) {unit}, max |u| {:.4e}",
            self.frames, v[0], v[1], v[2], last.max_u
        )
    }
}

/// Where a session ran, for its report: `qemu`, `litex`, `port` or `host`, and its MVUs (0 on
/// the host).
pub struct Place {
    pub target: String,
    pub mvus: u8,
}

/// A session's report, of whichever kind the session was; serialised as that kind's JSON.
#[derive(Debug, Clone, Serialize)]
#[serde(untagged)]
pub enum SessionReport {
    QuasiStatic(Report),
    Host(HostReport),
    Dynamic(super::dynamic_report::DynamicReport),
}

impl SessionReport {
    /// The report of `frames`, solved by `engine` for `live` with `options` at `on`.
    pub fn of(
        live: &super::start::Live,
        engine: &dyn super::engine::Engine,
        options: &super::start::Options,
        on: Place,
        frames: &[Frame],
        summary: &Summary,
    ) -> Self {
        use super::dynamic_report::{report as dynamic, DynamicInfo, Header as DynamicHeader};
        let setup = &live.setup;
        let g = setup.model.grid();
        let grid = [g.nx(), g.ny(), g.nz()];
        let model = match setup.model.spec().connection {
            crate::model::Connection::Axial => "a",
            crate::model::Connection::AxialShear => "b",
        };
        if let Some(spec) = &live.dynamics {
            let header = DynamicHeader {
                grid,
                model: model.into(),
                mvus: on.mvus,
                cycles_from_mcycle: on.target == "litex",
                target: on.target,
                tolerance: options.tol(),
                dynamic: DynamicInfo::new(spec, live.simulation.dt),
            };
            return SessionReport::Dynamic(dynamic(header, frames));
        }
        if on.target == "host" {
            return SessionReport::Host(host_report(setup.kind, frames));
        }
        let built = engine.model_report();
        let session = Session {
            header: Header {
                target: on.target,
                grid,
                model: model.into(),
                mvus: on.mvus,
                tolerance: options.tol(),
                cycle_budget: options.cycle_budget(),
            },
            model_cycles: built.map_or(0, |m| m.cycles),
            model_instructions: built.map_or(0, |m| m.cycles.saturating_sub(m.stall_cycles)),
            model_iterations: built.map_or(0, |m| m.iterations),
            resets: engine.resets(),
            retransmits: engine.retransmits(),
            paced: options.pace.is_some(),
            kind: setup.kind,
            field: options.field(),
        };
        SessionReport::QuasiStatic(report(session, frames, summary))
    }

    /// The lines a person reads after the session.
    pub fn summary(&self, kind: ToolKind) -> String {
        match self {
            SessionReport::QuasiStatic(r) => r.summary(kind),
            SessionReport::Host(r) => r.summary() + "\n",
            SessionReport::Dynamic(r) => r.summary(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bytes leave retransmissions out, so the report says how many there were.
    #[test]
    fn frames_sent_again_are_reported_beside_the_bytes() {
        let session = |retransmits| Session {
            header: Header {
                target: "qemu".into(),
                grid: [8, 8, 8],
                model: "B".into(),
                mvus: 8,
                tolerance: 1e-3,
                cycle_budget: 0,
            },
            model_cycles: 0,
            model_instructions: 0,
            model_iterations: 0,
            resets: 0,
            retransmits,
            paced: false,
            kind: ToolKind::Displacement,
            field: FieldChoice::default(),
        };
        let quiet = report(session(0), &[], &Summary::default());
        assert_eq!(quiet.link_retransmits, 0);
        assert!(!quiet.summary(ToolKind::Displacement).contains("resent"));
        let loaded = report(session(3), &[], &Summary::default());
        assert_eq!(loaded.link_retransmits, 3);
        let text = loaded.summary(ToolKind::Displacement);
        assert!(text.contains("resent      3 frame(s) sent again"), "{text}");
    }
}
