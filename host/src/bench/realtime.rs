//! The real-time budget: a `deform simulate` scenario run on the target, each time step's
//! cycles, and the step rate they allow at 100 MHz against haptic (1 kHz) and visual (60 Hz)
//! rates.
//!
//! The scenario is the thesis cube's load ramped over `steps` steps (the `simulate` default:
//! K resident, each direction warm-started from the previous step), for the grids the thesis
//! quotes (about 500 nodes: 8³ = 512) and for 1000 nodes (10³), on 1 and on several MVUs. A
//! step's cycles are those of its three solves (one per direction), run one after the other:
//! the critical path each solve measured over its whole run (`SolveReport::whole_solve`: every
//! parallel phase's slowest hart plus hart 0's serial work, the warm start's initial residual
//! b − A·x₀ and any residual replacement included).
//!
//! Two budgets are kept apart, because they have different cures:
//! - **compute**: the CG cycles at 100 MHz, CPI 1;
//! - **wire**: the bytes the step moves (right-hand sides and initial guesses up, solutions
//!   down), as measured on the line, and their time at the serial line's 115200 baud (10 bits a
//!   byte). Protocol handling on the target (framing, block-floating-point conversion) is in
//!   neither: the firmware does not count it.

use std::time::Duration;

use anyhow::Context;
use serde::{Deserialize, Serialize};

use super::{open_board, BenchModel, NOMINAL_CLOCK_HZ};
use crate::board::{Board, TargetFlags};
use crate::encode::{EncodeOptions, Partition};
use crate::link::BAUD_RATE;
use crate::model::Model;
use crate::simulate::{simulate, Schedule, StepParams};
use deform_shared::protocol::SolveReport;

/// Haptic feedback needs about 1 kHz, a visual display about 60 Hz.
pub const HAPTIC_HZ: f64 = 1000.0;
pub const VISUAL_HZ: f64 = 60.0;

/// What to run.
#[derive(Debug, Clone)]
pub struct RealtimeConfig {
    pub edges: Vec<usize>,
    pub models: Vec<BenchModel>,
    /// MVU counts; each scenario runs on a QEMU with that many harts.
    pub mvus: Vec<u8>,
    pub steps: u32,
    /// Target CG tolerance per solve (as `deform simulate --tol`).
    pub tol: f64,
    pub solve_timeout: Duration,
}

/// One time step's cost.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct StepBudget {
    pub step: u32,
    /// CG iterations, summed over x, y and z.
    pub iterations: u32,
    pub mvu_cycles: u64,
    pub svu_cycles: u64,
    pub cycles: u64,
    pub wire_bytes: u64,
}

/// One scenario's steps and verdicts.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct RealtimeScenario {
    pub model: BenchModel,
    pub edge: usize,
    pub mvus: u8,
    pub n: usize,
    pub nnz: usize,
    pub tol: f64,
    pub steps: Vec<StepBudget>,
    /// The slowest step's cycles, and the step rate it allows at 100 MHz.
    pub worst_step_cycles: u64,
    pub compute_rate_hz: f64,
    pub meets_haptic: bool,
    pub meets_visual: bool,
    /// The largest step's bytes, and the step rate the serial line allows for them.
    pub worst_step_wire_bytes: u64,
    pub wire_rate_hz_at_baud: f64,
    pub baud: u32,
    /// Wire bytes per CG iteration over the whole run (steps' bytes / steps' iterations).
    pub wire_bytes_per_iteration: f64,
    /// Bytes of the one-off upload of A.
    pub wire_bytes_matrix_upload: u64,
}

/// Runs every (model, edge) scenario on its own fresh one-hart board.
pub fn run(config: &RealtimeConfig, target: &TargetFlags) -> anyhow::Result<Vec<RealtimeScenario>> {
    let mut out = Vec::new();
    for &mvus in &config.mvus {
        for &model in &config.models {
            for &edge in &config.edges {
                let mut board = match open_board(target, mvus, config.solve_timeout) {
                    Ok(board) => board,
                    // As in the sweep: one MVU must work, more depend on the board.
                    Err(e) if mvus > 1 => {
                        println!("budget {model} {edge}³ {mvus} MVUs: skipped, {e:#}");
                        continue;
                    }
                    Err(e) => return Err(e),
                };
                let scenario = run_one(&mut board, model, edge, mvus, config)?;
                println!(
                "budget {} {}³ (n = {}), {} MVU(s): worst step {} cycles → {:.0} steps/s at 100 MHz (1 kHz: {}, 60 Hz: {}); {} B on the wire per step → {:.1} steps/s at {} baud",
                model,
                edge,
                scenario.n,
                mvus,
                scenario.worst_step_cycles,
                scenario.compute_rate_hz,
                yes_no(scenario.meets_haptic),
                yes_no(scenario.meets_visual),
                scenario.worst_step_wire_bytes,
                scenario.wire_rate_hz_at_baud,
                scenario.baud
            );
                out.push(scenario);
            }
        }
    }
    Ok(out)
}

fn yes_no(b: bool) -> &'static str {
    if b {
        "yes"
    } else {
        "no"
    }
}

/// (MVU, SVU) critical-path cycles of a step's solves, as the target measured them over each
/// whole solve (`SolveReport::whole_solve`: the initial residual of a warm start included).
fn step_cycles(reports: &[SolveReport]) -> (u64, u64) {
    reports.iter().fold((0, 0), |(mvu, svu), r| {
        (
            mvu + r.whole_solve.mvu_critical.cycles,
            svu + r.whole_solve.svu_critical.cycles,
        )
    })
}

/// Steps per second that `per_step` units allow at `rate` units per second.
fn rate(per_step: f64, units_per_second: f64) -> f64 {
    if per_step > 0.0 {
        units_per_second / per_step
    } else {
        f64::INFINITY
    }
}

fn run_one(
    board: &mut Board,
    model: BenchModel,
    edge: usize,
    mvus: u8,
    config: &RealtimeConfig,
) -> anyhow::Result<RealtimeScenario> {
    let built = Model::build(&model.cube(edge)?).context("building the model")?;
    let n = built.n();
    let schedule = Schedule {
        steps: config.steps,
        dt: 1.0 / HAPTIC_HZ,
    };
    let params = StepParams {
        warm_start: true,
        predict: false,
        fuse: false,
        tol: config.tol,
        max_iterations: crate::refine::default_max_iterations(n),
        check_reference: false,
        layout: EncodeOptions {
            mvus,
            partition: Partition::Rows,
            use_symmetry: true,
        },
    };
    let start = board.wire();
    let mut steps = Vec::new();
    simulate(
        &mut board.target,
        &built,
        schedule,
        None,
        params,
        |_| {},
        |r| {
            let (mvu_cycles, svu_cycles) = step_cycles(&r.reports);
            steps.push(StepBudget {
                step: r.step,
                iterations: r.iterations,
                mvu_cycles,
                svu_cycles,
                cycles: mvu_cycles + svu_cycles,
                wire_bytes: r.bytes.total(),
            });
        },
    )
    .with_context(|| format!("simulating {model} on a {edge}³ grid"))?;
    let worst_step_cycles = steps.iter().map(|s| s.cycles).max().unwrap_or(0);
    let worst_step_wire_bytes = steps.iter().map(|s| s.wire_bytes).max().unwrap_or(0);
    let compute_rate_hz = rate(worst_step_cycles as f64, NOMINAL_CLOCK_HZ);
    let iterations: u64 = steps.iter().map(|s| s.iterations as u64).sum();
    let bytes: u64 = steps.iter().map(|s| s.wire_bytes).sum();
    // Every byte before the first step is the upload of A.
    let upload = board.wire().since(start).total() - bytes;
    Ok(RealtimeScenario {
        model,
        edge,
        mvus,
        n,
        nnz: built.unit_matrix().nnz(),
        tol: config.tol,
        worst_step_cycles,
        compute_rate_hz,
        meets_haptic: compute_rate_hz >= HAPTIC_HZ,
        meets_visual: compute_rate_hz >= VISUAL_HZ,
        worst_step_wire_bytes,
        // 8N1: ten bits on the line per byte.
        wire_rate_hz_at_baud: rate(worst_step_wire_bytes as f64 * 10.0, BAUD_RATE as f64),
        baud: BAUD_RATE,
        wire_bytes_per_iteration: if iterations > 0 {
            bytes as f64 / iterations as f64
        } else {
            0.0
        },
        wire_bytes_matrix_upload: upload,
        steps,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rates_follow_the_budget() {
        assert_eq!(rate(100_000.0, NOMINAL_CLOCK_HZ), 1000.0);
        assert!(rate(0.0, 1.0).is_infinite());
    }
}
