//! Cycles per CG iteration against grid size, model and MVU count (thesis Fig. 5-2), and what
//! follows from them: MFLOPS by eq. 56 (Fig. 5-3), instructions per nonzero, wire bytes.
//!
//! # How a point is measured
//!
//! Each point is an `edge`³ cube of the thesis 2.6 example in model A or B. Its A is uploaded
//! once; then the x right-hand side is solved twice from zero, with the tolerance at 0 so that
//! exactly `k1` and then `k2` iterations run. CG from zero is deterministic, so the two solves
//! share their set-up (r₀ = b, p₀ = r₀, ‖b‖) and the difference of their counters divided by
//! k2 − k1 is the exact cost of one iteration, set-up excluded. The MVU and SVU counters are the
//! firmware's `mcycle`/`minstret` deltas around each phase, exact under `-icount shift=0`.
//!
//! The second solve's traffic (right-hand side up, `Solve`/`Solved`, solution down) is the
//! wire cost of one solve; CG's iterations themselves move no byte.

use std::time::Duration;

use anyhow::Context;
use deform_shared::protocol::{SolveParams, SolveReport, Start};
use serde::{Deserialize, Serialize};

use super::board::{BenchBoard, BenchBoardChoice, BenchTarget, WireBytes, WireCounter};
use super::{mflops, micros, BenchModel};
use crate::encode::encode;
use crate::model::{Axis, Model};

/// What to sweep.
#[derive(Debug, Clone)]
pub struct SweepConfig {
    /// Cube edges: n = edge³ nodes.
    pub edges: Vec<usize>,
    pub models: Vec<BenchModel>,
    /// MVU counts; QEMU is booted with one hart per MVU.
    pub mvus: Vec<u8>,
    /// Iterations of the shorter and the longer solve (see the module doc).
    pub short_iterations: u32,
    pub long_iterations: u32,
    pub solve_timeout: Duration,
}

/// One measured point.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct SweepPoint {
    pub model: BenchModel,
    pub edge: usize,
    /// Unknowns (nodes; fixed nodes keep a diagonal row).
    pub n: usize,
    /// Nonzeros of A.
    pub nnz: usize,
    /// Instruction words the MVUs execute per iteration (nonzeros plus empty-row words).
    pub words: u32,
    pub tiles: usize,
    pub mvus: u8,
    /// Iterations the per-iteration figures are averaged over (k2 − k1).
    pub iterations_measured: u32,
    /// Critical-path cycles of one iteration: MVU phase, SVU phase and their sum.
    pub mvu_cycles_per_iteration: f64,
    pub svu_cycles_per_iteration: f64,
    pub cycles_per_iteration: f64,
    pub mvu_instructions_per_iteration: f64,
    pub svu_instructions_per_iteration: f64,
    /// MVU instructions per instruction word executed.
    pub instructions_per_nonzero: f64,
    /// Time of one iteration at 100 MHz, CPI 1.
    pub microseconds_per_iteration: f64,
    /// Thesis eq. 56 at 100 MHz.
    pub mflops: f64,
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
pub fn run(config: &SweepConfig, choice: &BenchBoardChoice) -> anyhow::Result<SweepResult> {
    anyhow::ensure!(
        config.long_iterations > config.short_iterations,
        "the long solve must run more iterations than the short one"
    );
    let mut result = SweepResult::default();
    let timeouts = super::board::timeouts(config.solve_timeout);
    for &mvus in &config.mvus {
        let mut board = match BenchBoard::open(choice, mvus, timeouts) {
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
                match measure(&mut board, model, edge, mvus, config) {
                    Ok(Measured::Point(point)) => {
                        println!(
                            "sweep  {} n = {:>6} MVUs {}: {:>10.0} cycles/iter (MVU {:.0} + SVU {:.0}), {:.2} instr/nonzero, {:>6.1} MFLOPS",
                            model,
                            point.n,
                            mvus,
                            point.cycles_per_iteration,
                            point.mvu_cycles_per_iteration,
                            point.svu_cycles_per_iteration,
                            point.instructions_per_nonzero,
                            point.mflops
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

fn fixed_iterations(iterations: u32) -> SolveParams {
    SolveParams {
        max_iterations: iterations,
        tolerance: 0.0,
        start: Start::Zero,
    }
}

/// One solve of exactly `iterations` iterations, with its wire traffic.
fn timed_solve(
    target: &mut BenchTarget,
    wire: &WireCounter,
    rhs: &[f64],
    iterations: u32,
) -> anyhow::Result<(SolveReport, WireBytes)> {
    let before = wire.read();
    let (report, _) = target.solve_for(rhs, fixed_iterations(iterations))?;
    Ok((report, wire.read().since(before)))
}

fn measure(
    board: &mut BenchBoard,
    model: BenchModel,
    edge: usize,
    mvus: u8,
    config: &SweepConfig,
) -> anyhow::Result<Measured> {
    let spec = model.cube(edge)?;
    let built = Model::build(&spec).context("building the model")?;
    let a = built.unit_matrix();
    let encoded = match encode(a) {
        Ok(e) => e,
        Err(e) => return Ok(Measured::Skipped(format!("cannot encode A: {e}"))),
    };
    if let Err(e) = board.target.check_matrix_fits(&encoded) {
        return Ok(Measured::Skipped(e.to_string()));
    }
    let before = board.wire.read();
    board.target.upload_matrix(&encoded)?;
    let upload = board.wire.read().since(before);
    let rhs = built.scaled_rhs(Axis::X);
    let (short, _) = timed_solve(
        &mut board.target,
        &board.wire,
        &rhs,
        config.short_iterations,
    )?;
    let (long, wire) = timed_solve(&mut board.target, &board.wire, &rhs, config.long_iterations)?;
    let iterations = long.iterations.saturating_sub(short.iterations);
    if iterations == 0 {
        return Ok(Measured::Skipped(format!(
            "CG converged within {} iterations, nothing left to measure",
            short.iterations
        )));
    }
    let per = |long: u64, short: u64| (long - short) as f64 / iterations as f64;
    let mvu_cycles = per(long.mvu.cycles, short.mvu.cycles);
    let svu_cycles = per(long.svu.cycles, short.svu.cycles);
    let mvu_instructions = per(long.mvu.instructions, short.mvu.instructions);
    let svu_instructions = per(long.svu.instructions, short.svu.instructions);
    let cycles = mvu_cycles + svu_cycles;
    let (n, nnz) = (built.n(), a.nnz());
    Ok(Measured::Point(SweepPoint {
        model,
        edge,
        n,
        nnz,
        words: long.words_per_iteration,
        tiles: encoded.tiles.len(),
        mvus,
        iterations_measured: iterations,
        mvu_cycles_per_iteration: mvu_cycles,
        svu_cycles_per_iteration: svu_cycles,
        cycles_per_iteration: cycles,
        mvu_instructions_per_iteration: mvu_instructions,
        svu_instructions_per_iteration: svu_instructions,
        instructions_per_nonzero: mvu_instructions / long.words_per_iteration.max(1) as f64,
        microseconds_per_iteration: micros(cycles),
        mflops: mflops(n, nnz, cycles),
        wire_bytes_matrix_upload: upload.total(),
        wire_bytes_per_solve: wire.total(),
    }))
}
