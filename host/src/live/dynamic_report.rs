//! The JSON report of a dynamic headless session (`deform live --headless --report` on a
//! dynamic scenario): the quasi-static report's keys where they mean the same, `null` with a
//! reason where they do not, and `dynamic` (h, scheme, mass, damping).

use serde::Serialize;

use super::engine::Frame;
use super::session::force_error_max;
use super::stats::{per_second, percentile, sorted, IterationSpread, Rate, Spread, BAUDS};
use crate::dynamics::{Damping, DynamicsSpec};

/// Why `force_updates_per_s` is null for dynamic frames.
pub const NO_FORCE_MODEL: &str = "dynamic frames have no local force model: the tool force \
    (M·(v1-v0)/h + C·v1 + K·u1 - f1 at the tool nodes) is updated once per frame, so the force \
    rate is the frame rate";

/// The dynamic model and step, as the report states them.
#[derive(Debug, Clone, Serialize)]
pub struct DynamicInfo {
    /// Seconds per frame: each frame is one step.
    pub h: f64,
    pub scheme: String,
    /// Lumped mass per node, kg (the background value of a mass field).
    pub mass: f64,
    /// β per direction, N·s/m (`null` for a per-node β field: see `describe`).
    pub damping: Option<[f64; 3]>,
    pub rayleigh: Option<[f64; 2]>,
    pub describe: String,
}

impl DynamicInfo {
    pub fn new(spec: &DynamicsSpec, h: f64) -> Self {
        Self {
            h,
            scheme: spec.scheme.to_string(),
            mass: spec.mass.background,
            damping: match &spec.damping {
                Damping::PerDirection(b) => Some(*b),
                Damping::Field(_) => None,
            },
            rayleigh: spec.rayleigh,
            describe: spec.describe(),
        }
    }
}

/// The first frame's bytes: S's upload is in them.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct FirstFrame {
    pub bytes_up: u64,
    pub bytes_down: u64,
}

/// Whole frames per second the serial line allows (8N1: 10 bits per byte).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct LineRate {
    pub baud: u32,
    pub frames_per_s: f64,
}

/// What the tissue did: the dynamics the quasi-static loop cannot show.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Motion {
    pub max_u: f64,
    /// max |u| and max |v| at the last frame.
    pub last_max_u: f64,
    pub last_max_v: f64,
    pub last_energy: f64,
}

/// `--report FILE.json` for a dynamic session.
#[derive(Debug, Clone, Serialize)]
pub struct DynamicReport {
    pub frames: u32,
    pub grid: [usize; 3],
    pub model: String,
    pub mvus: u8,
    /// `qemu`, `litex`, `port` or `host` (the f64 stepper alone: no target figures).
    pub target: String,
    pub tolerance: f64,
    /// Cycles of each frame's target solves. Under QEMU (or a board): the critical path
    /// (every phase's slowest hart plus hart 0's serial work), which the target counts in
    /// instructions retired, exact cycles under `-icount` (CPI 1). On the LiteX SoC (one
    /// hart): hart 0's `mcycle` over the MVU and SVU phases, the RTL's real cycles.
    pub frame_cycles: Option<Spread>,
    /// Hart 0's `mcycle` over the solves' MVU and SVU phases: the RTL's real cycles on the
    /// LiteX SoC (one hart); under QEMU with several harts the harts' summed work.
    pub frame_hart0_cycles: Option<Spread>,
    pub frames_per_s_at_100mhz: Option<Rate>,
    pub force_updates_per_s: Option<f64>,
    pub force_updates_note: &'static str,
    /// Target CG iterations per frame, a fused solve over x, y, z counted once.
    pub iterations: IterationSpread,
    /// Target solves (refinement rounds) per frame, at most.
    pub solves_max: u32,
    pub residual_max: f64,
    /// max |u − u_ref| / max |u_ref| against the f64 stepper run alongside (same tool path).
    pub error_vs_converged_max: Option<f64>,
    /// max |u − u_ref| over the session / the session's largest max |u_ref|: the same error
    /// on one scale (the per-frame figure above grows as the tissue passes through rest).
    pub error_vs_converged_of_peak_max: Option<f64>,
    /// max |F − F_ref| / max |F_ref| over the frames.
    pub force_error_max: Option<f64>,
    /// Median over the frames after the first: whole vectors where the host forms the steps (a
    /// residual up, a correction down), the tool's motion up and its force down where the
    /// target does ([`super::resident`]).
    pub bytes_up_per_frame: f64,
    pub bytes_down_per_frame: f64,
    pub bytes_up_per_frame_max: u64,
    pub bytes_down_per_frame_max: u64,
    pub first_frame: FirstFrame,
    pub link_rates: Vec<LineRate>,
    pub motion: Motion,
    pub dynamic: DynamicInfo,
}

/// The session's header fields.
pub struct Header {
    pub grid: [usize; 3],
    pub model: String,
    pub mvus: u8,
    pub target: String,
    pub tolerance: f64,
    pub dynamic: DynamicInfo,
    /// Frame cycles from hart 0's `mcycle` (the LiteX SoC, where instructions are not cycles).
    pub cycles_from_mcycle: bool,
}

/// The report over `records` (every frame of the session, in order).
pub fn report(header: Header, records: &[Frame]) -> DynamicReport {
    let on_target = records.iter().any(|r| r.cycles.is_some());
    let hart0 = sorted(
        records
            .iter()
            .filter_map(|r| r.hart0_cycles.map(|c| c as f64)),
    );
    let cycles = match header.cycles_from_mcycle {
        true => hart0.clone(),
        false => sorted(records.iter().filter_map(|r| r.cycles.map(|c| c as f64))),
    };
    let iterations = sorted(records.iter().map(|r| f64::from(r.iterations)));
    let later = records.get(1..).unwrap_or_default();
    let up = percentile(&sorted(later.iter().map(|r| r.bytes.sent as f64)), 0.5);
    let down = percentile(&sorted(later.iter().map(|r| r.bytes.received as f64)), 0.5);
    let last = records.last();
    let last_motion = last.and_then(|r| r.motion).unwrap_or_default();
    DynamicReport {
        frames: records.len() as u32,
        grid: header.grid,
        model: header.model,
        mvus: header.mvus,
        target: header.target,
        tolerance: header.tolerance,
        frame_cycles: on_target.then(|| Spread::of(&cycles)),
        frame_hart0_cycles: on_target.then(|| Spread::of(&hart0)),
        frames_per_s_at_100mhz: on_target.then(|| Rate::of(&cycles)),
        force_updates_per_s: None,
        force_updates_note: NO_FORCE_MODEL,
        iterations: IterationSpread::of(&iterations),
        solves_max: records.iter().map(|r| r.solves).max().unwrap_or(0),
        residual_max: records.iter().map(|r| r.residual).fold(0.0, f64::max),
        error_vs_converged_max: on_target.then(|| {
            records
                .iter()
                .filter_map(|r| r.error_vs_converged)
                .fold(0.0, f64::max)
        }),
        error_vs_converged_of_peak_max: on_target.then(|| {
            let peak = records.iter().map(|r| r.max_u).fold(0.0, f64::max);
            records
                .iter()
                .filter_map(|r| r.error_abs)
                .fold(0.0, f64::max)
                / peak.max(f64::MIN_POSITIVE)
        }),
        force_error_max: on_target.then(|| force_error_max(records)),
        bytes_up_per_frame: up,
        bytes_down_per_frame: down,
        bytes_up_per_frame_max: later.iter().map(|r| r.bytes.sent).max().unwrap_or(0),
        bytes_down_per_frame_max: later.iter().map(|r| r.bytes.received).max().unwrap_or(0),
        first_frame: FirstFrame {
            bytes_up: records.first().map_or(0, |r| r.bytes.sent),
            bytes_down: records.first().map_or(0, |r| r.bytes.received),
        },
        link_rates: BAUDS
            .into_iter()
            .map(|baud| LineRate {
                baud,
                frames_per_s: per_second(baud, up + down),
            })
            .collect(),
        motion: Motion {
            max_u: records.iter().map(|r| r.max_u).fold(0.0, f64::max),
            last_max_u: last.map_or(0.0, |r| r.max_u),
            last_max_v: last_motion.max_v,
            last_energy: last_motion.energy,
        },
        dynamic: header.dynamic,
    }
}

impl DynamicReport {
    /// The lines a person reads after the session.
    pub fn summary(&self) -> String {
        use std::fmt::Write;
        let mut out = String::new();

        if let (Some(c), Some(r)) = (self.frame_cycles, self.frames_per_s_at_100mhz) {
            writeln!(
                out,
            "frames      {}: cycles p50 {:.0}, p99 {:.0}, max {:.0} → {:.0} frames/s at 100 MHz (worst {:.0})",
            self.frames, c.p50, c.p99, c.max, r.p50, r.worst
        ).unwrap();
            if let Some(h) = self.frame_hart0_cycles {
                writeln!(
                out,
                "hart 0      mcycle over the MVU and SVU phases p50 {:.0}, p99 {:.0}, max {:.0} (real cycles on LiteX; the harts' sum under QEMU)",
                h.p50, h.p99, h.max
            ).unwrap();
            }
            writeln!(
                out,
            "accuracy    error vs the f64 stepper ≤ {:.2e} of the frame's max |u| ({:.2e} of the session's), force ≤ {:.2e}, residual ≤ {:.2e}, iterations p50 {} max {}, ≤ {} solve(s) per frame",
            self.error_vs_converged_max.unwrap_or(0.0),
            self.error_vs_converged_of_peak_max.unwrap_or(0.0),
            self.force_error_max.unwrap_or(0.0),
            self.residual_max,
            self.iterations.p50,
            self.iterations.max,
            self.solves_max
        ).unwrap();
            writeln!(
                out,
            "line        {} B up / {} B down per frame (median; max {} / {}; the first {} / {} with S)",
            self.bytes_up_per_frame,
            self.bytes_down_per_frame,
            self.bytes_up_per_frame_max,
            self.bytes_down_per_frame_max,
            self.first_frame.bytes_up,
            self.first_frame.bytes_down
        ).unwrap();
            for r in &self.link_rates {
                writeln!(out, "  {:>9} baud: {:.1} frames/s", r.baud, r.frames_per_s).unwrap();
            }
        } else {
            writeln!(
                out,
                "frames      {} steps by the host's f64 stepper",
                self.frames
            )
            .unwrap();
        }
        let m = self.motion;
        writeln!(
                out,
        "motion      max |u| {:.4e}; at the last frame max |u| {:.4e}, max |v| {:.4e}, energy {:.4e}",
        m.max_u, m.last_max_u, m.last_max_v, m.last_energy
    ).unwrap();
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dynamics::DynamicsSpec;
    use crate::live::engine::Motion as FrameMotion;

    fn frame(i: u32, cycles: Option<u64>, hart0: Option<u64>, bytes: u64) -> Frame {
        Frame {
            frame: i,
            t: f64::from(i) * 0.01,
            tool: vec![[0.0; 3]],
            answer: [0.0, 0.0, 2.0],
            reference: [0.0, 0.0, 2.0],
            max_u: 1.0,
            motion: Some(FrameMotion {
                energy: 1.0,
                max_v: 0.5,
            }),
            iterations: i,
            solves: 1,
            cycles,
            instructions: None,
            hart0_cycles: hart0,
            residual: 1e-5,
            error_vs_converged: cycles.map(|_| 1e-6),
            error_abs: cycles.map(|_| 1e-6),
            bytes: crate::board::WireBytes {
                sent: bytes,
                received: bytes,
            },
        }
    }

    fn header(cycles_from_mcycle: bool) -> Header {
        Header {
            grid: [8, 8, 8],
            model: "b".into(),
            mvus: 1,
            target: "litex".into(),
            tolerance: 1e-4,
            dynamic: DynamicInfo::new(&DynamicsSpec::uniform(0.005, [0.05; 3]), 0.01),
            cycles_from_mcycle,
        }
    }

    /// Frame rates come from the critical path, or from hart 0's mcycle on the LiteX SoC; the
    /// first frame (S's upload) stays out of the bytes per frame.
    #[test]
    fn cycles_and_bytes_are_taken_from_the_right_counts() {
        let frames: Vec<_> = (1..=3)
            .map(|i| {
                frame(
                    i,
                    Some(1_000_000),
                    Some(2_000_000),
                    [40_000, 2_000, 2_000][i as usize - 1],
                )
            })
            .collect();
        let r = report(header(false), &frames);
        assert_eq!(r.frame_cycles.unwrap().p50, 1e6);
        assert_eq!(r.frames_per_s_at_100mhz.unwrap().p50, 100.0);
        assert_eq!(
            (r.bytes_up_per_frame, r.first_frame.bytes_up),
            (2_000.0, 40_000)
        );
        assert_eq!(r.link_rates[0].frames_per_s, 11_520.0 / 4_000.0);
        let r = report(header(true), &frames);
        assert_eq!(r.frame_cycles.unwrap().p50, 2e6);
        assert_eq!(r.frames_per_s_at_100mhz.unwrap().p50, 50.0);
        assert!(r.force_updates_per_s.is_none());
    }

    /// On the host (no target) the target's figures are null, not zero.
    #[test]
    fn a_host_session_has_no_target_figures() {
        let frames: Vec<_> = (1..=3).map(|i| frame(i, None, None, 0)).collect();
        let r = report(header(false), &frames);
        assert!(r.frame_cycles.is_none() && r.frames_per_s_at_100mhz.is_none());
        assert!(r.error_vs_converged_max.is_none() && r.force_error_max.is_none());
        assert_eq!(r.motion.last_max_v, 0.5);
    }
}
