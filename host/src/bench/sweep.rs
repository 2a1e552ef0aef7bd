//! Cycles per CG iteration against grid size, model and MVU count (thesis Fig. 5-2), and what
//! follows from them: MFLOPS by eq. 56 (Fig. 5-3), instructions per nonzero, wire bytes.
//!
//! # How a point is measured
//!
//! Each point is an `edge`³ cube of the thesis 2.6 example in model A or B, laid out as
//! `deform solve` lays it out by default (row blocks balanced over the MVUs, only half of K
//! stored when it is persymmetric), uploaded once to a QEMU booted with one hart per MVU. The x
//! right-hand side is then solved from zero with the tolerance at 0, so that exactly
//! `iterations` iterations run. The target measures one iteration hart by hart (its parallel
//! phases run one hart at a time, so that under `-icount` each hart's `minstret` delta is its
//! own work): the slowest MVU's instructions are T_MVU, the SVU's critical path T_SVU, and
//! T = T_MVU + T_SVU (thesis eq. 55) is the critical path at one instruction per cycle.
//! [`crate::metrics::performance`] turns them into instructions per nonzero and eq. 56 MFLOPS.
//!
//! The solve's traffic (right-hand side up, `Solve`/`Solved`, solution down) is the wire cost
//! of one solve; CG's iterations themselves move no byte.

use std::time::Duration;

use anyhow::Context;
use deform_shared::protocol::{SolveParams, Start};
use serde::{Deserialize, Serialize};

use super::{micros, open_board, BenchModel};
use crate::board::{Board, TargetFlags};
use crate::encode::{encode_with, EncodeOptions, Partition};
use crate::metrics::performance;
use crate::model::{Axis, Model};

/// What to sweep.
#[derive(Debug, Clone)]
pub struct SweepConfig {
    /// Cube edges: n = edge³ nodes.
    pub edges: Vec<usize>,
    pub models: Vec<BenchModel>,
    /// MVU counts; QEMU is booted with one hart per MVU.
    pub mvus: Vec<u8>,
    /// How the rows are shared out over the MVUs.
    pub partition: Partition,
    /// CG iterations of the measured solve (see the module doc).
    pub iterations: u32,
    pub solve_timeout: Duration,
}

/// One measured point.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct SweepPoint {
    pub model: BenchModel,
    pub edge: usize,
    /// Unknowns (nodes; fixed nodes keep a diagonal row).
    pub n: usize,
    /// Nonzeros of A.
    pub nnz: usize,
    /// Instruction words the MVUs execute per iteration, all together (half of A's nonzeros
    /// with conjugate symmetry, plus empty-row words of the tiling).
    pub words: u32,
    pub tiles: usize,
    /// MVUs asked for, and MVUs the layout used.
    pub mvus: u8,
    pub mvus_used: u8,
    /// `rows` (thesis 4.1.2) or `overlap` (4.1.1).
    pub partition: String,
    /// Only half of A was stored (conjugate symmetry).
    pub symmetry_used: bool,
    /// Critical-path cycles of one iteration: T_MVU (slowest MVU), T_SVU and T = their sum
    /// (the target's `mcycle`: equal to the instructions under QEMU `-icount`, the RTL's
    /// cycles on the LiteX SoC).
    pub mvu_cycles_per_iteration: f64,
    pub svu_cycles_per_iteration: f64,
    pub cycles_per_iteration: f64,
    /// T in retired instructions, and cycles per instruction.
    pub critical_instructions_per_iteration: f64,
    pub cpi: Option<f64>,
    /// All harts' instructions of one iteration, by phase.
    pub mvu_instructions_per_iteration: f64,
    pub svu_instructions_per_iteration: f64,
    /// MVU instructions per instruction word executed.
    pub instructions_per_nonzero: f64,
    /// MVU instructions per multiply–accumulate (a mirrored word serves two).
    pub instructions_per_product: f64,
    /// Time of one iteration at 100 MHz, CPI 1.
    pub microseconds_per_iteration: f64,
    /// Thesis eq. 56 at 100 MHz.
    pub mflops: f64,
    /// Values clamped to their fixed-point range (must be 0).
    pub saturations: u32,
    /// Uploading A, both directions (once per matrix, not per solve).
    pub wire_bytes_matrix_upload: u64,
    /// One solve: right-hand side up, Solve/Solved, solution down, both directions.
    pub wire_bytes_per_solve: u64,
}

/// A point that could not be measured, and why (e.g. A does not fit the target).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct SkippedPoint {
    pub model: BenchModel,
    pub edge: usize,
    pub mvus: u8,
    pub reason: String,
}

#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct SweepResult {
    pub points: Vec<SweepPoint>,
    pub skipped: Vec<SkippedPoint>,
}

/// Runs the sweep, printing one line per point as it goes.
pub fn run(config: &SweepConfig, target: &TargetFlags) -> anyhow::Result<SweepResult> {
    anyhow::ensure!(
        config.iterations > 0,
        "the sweep needs at least one iteration"
    );
    let mut result = SweepResult::default();
    for &mvus in &config.mvus {
        let mut board = match open_board(target, mvus, config.solve_timeout) {
            Ok(board) => board,
            // One hart must work; more depend on the firmware, so they are reported, not fatal.
            Err(e) if mvus > 1 => {
                println!("sweep  {mvus} MVUs: skipped, the target did not come up: {e:#}");
                for &model in &config.models {
                    for &edge in &config.edges {
                        result.skipped.push(SkippedPoint {
                            model,
                            edge,
                            mvus,
                            reason: format!("the target did not come up with {mvus} harts: {e:#}"),
                        });
                    }
                }
                continue;
            }
            Err(e) => return Err(e),
        };
        let harts = board.target.info().harts;
        if harts < mvus {
            println!("sweep  {mvus} MVUs: skipped, the target puts only {harts} hart(s) to work");
        }
        for &model in &config.models {
            for &edge in &config.edges {
                let skip = |reason: String| SkippedPoint {
                    model,
                    edge,
                    mvus,
                    reason,
                };
                if harts < mvus {
                    result.skipped.push(skip(format!(
                        "the target puts {harts} hart(s) to work, {mvus} MVUs asked"
                    )));
                    continue;
                }
                let started = std::time::Instant::now();
                match measure(&mut board, model, edge, mvus, config) {
                    Ok(Measured::Point(point)) => {
                        println!(
                            "sweep  {} n = {:>6} MVUs {}: {:>10.0} cycles/iter (MVU {:.0} + SVU {:.0}), {:.2} instr/nonzero, {:>6.1} MFLOPS ({:.1?})",
                            model,
                            point.n,
                            mvus,
                            point.cycles_per_iteration,
                            point.mvu_cycles_per_iteration,
                            point.svu_cycles_per_iteration,
                            point.instructions_per_nonzero,
                            point.mflops,
                            started.elapsed()
                        );
                        result.points.push(point);
                    }
                    Ok(Measured::Skipped(reason)) => {
                        println!("sweep  {model} {edge}³ MVUs {mvus}: skipped, {reason}");
                        result.skipped.push(skip(reason));
                    }
                    Err(e) => return Err(e),
                }
            }
        }
    }
    Ok(result)
}

enum Measured {
    Point(SweepPoint),
    Skipped(String),
}

fn measure(
    board: &mut Board,
    model: BenchModel,
    edge: usize,
    mvus: u8,
    config: &SweepConfig,
) -> anyhow::Result<Measured> {
    let spec = model.cube(edge)?;
    let built = Model::build(&spec).context("building the model")?;
    let a = built.unit_matrix();
    let options = EncodeOptions {
        mvus,
        partition: config.partition,
        use_symmetry: true,
    };
    let encoding = match encode_with(a, &options) {
        Ok(e) => e,
        Err(e) => return Ok(Measured::Skipped(format!("cannot encode A: {e}"))),
    };
    if let Err(e) = board.target.check_matrix_fits(&encoding.matrix) {
        return Ok(Measured::Skipped(e.to_string()));
    }
    let before = board.wire();
    board.target.upload_matrix(&encoding.matrix)?;
    let upload = board.wire().since(before);
    let rhs = built.scaled_rhs(Axis::X);
    let before = board.wire();
    let (report, _) = board.target.solve_for(
        &rhs,
        SolveParams {
            max_iterations: config.iterations,
            // Tolerance 0: exactly `iterations` iterations.
            tolerance: 0.0,
            start: Start::Zero,
            directions: 1,
            cycle_budget: 0,
        },
    )?;
    let wire = board.wire().since(before);
    let (n, nnz) = (built.n(), a.nnz());
    let Some(perf) = performance(&report, &encoding.summary, n, nnz) else {
        return Ok(Measured::Skipped(format!(
            "the solve ran {} iterations, nothing was measured",
            report.iterations
        )));
    };
    let cost = report.per_iteration;
    let cycles = perf.critical_path.cycles as f64;
    Ok(Measured::Point(SweepPoint {
        model,
        edge,
        n,
        nnz,
        words: report.words_per_iteration,
        tiles: encoding.summary.tiles,
        mvus,
        mvus_used: report.mvus,
        partition: encoding.summary.partition.to_string(),
        symmetry_used: encoding.summary.symmetry_used,
        mvu_cycles_per_iteration: perf.mvu_critical.cycles as f64,
        svu_cycles_per_iteration: perf.svu_critical.cycles as f64,
        cycles_per_iteration: cycles,
        critical_instructions_per_iteration: perf.critical_path.instructions as f64,
        cpi: perf.critical_path.cpi,
        mvu_instructions_per_iteration: cost.mvu_total.instructions as f64,
        svu_instructions_per_iteration: cost.svu_total.instructions as f64,
        instructions_per_nonzero: perf.mvu_instructions_per_word,
        instructions_per_product: perf.mvu_instructions_per_product,
        microseconds_per_iteration: micros(cycles),
        mflops: perf.mflops,
        saturations: perf.saturations,
        wire_bytes_matrix_upload: upload.total(),
        wire_bytes_per_solve: wire.total(),
    }))
}
