//! Prints the CG engine's figures, measured on QEMU with `-icount shift=0` (exact instruction
//! counts; `sleep=off` with several harts):
//!
//! - MVU instructions per nonzero, one direction and three fused directions (per
//!   multiply-accumulate), on one MVU;
//! - critical-path instructions per CG iteration (slowest MVU + SVU, thesis eq. 55) with 1, 2,
//!   4 and 8 MVUs, and the speed-up over one MVU;
//! - MFLOPS at a nominal 100 MHz by thesis eq. 56, (2mn + 6n + 2)/T.
//!
//! ```text
//! cargo xtask firmware
//! cargo run --release -p deform-hil-sim --example engine_figures [-- --grid 16 --model b]
//! ```
//!
//! Each figure comes from the target's own report: every solve measures one iteration with its
//! parallel phases run one hart at a time, so that each hart's `minstret` delta is its own work
//! (under `-icount` all harts read one machine-wide count). The solves are cut to a few
//! iterations: the per-iteration cost does not depend on how many follow.

use std::time::Duration;

use clap::Parser;
use deform_hil_sim::{firmware_elf, Qemu, QemuConfig};
use deform_host::encode::{encode_with, EncodeOptions, Partition};
use deform_host::link::{Target, Timeouts};
use deform_host::model::{
    Axis, Connection, Csr, Elasticity, FixedNodeSet, Grid, Model, ModelSpec, Node, PointLoad,
};
use deform_shared::protocol::{SolveParams, SolveReport, Start};

#[derive(Parser)]
#[command(about = "Print the engine's instruction counts and MVU speed-ups, measured on QEMU")]
struct Args {
    /// Nodes per side of the cubic grid.
    #[arg(long, default_value_t = 16)]
    grid: usize,
    /// Spring model: a (6 neighbours) or b (26 neighbours).
    #[arg(long, default_value = "b")]
    model: char,
    /// Store half of the persymmetric matrix (mirrored tiles).
    #[arg(long)]
    symmetry: bool,
    /// Share rows with overlapping partial sums (thesis 4.1.1) instead of disjoint row blocks.
    #[arg(long)]
    overlap: bool,
}

/// One MVU count's measurements.
struct Row {
    harts: u8,
    words: usize,
    /// One direction, then three fused.
    single: SolveReport,
    fused: SolveReport,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let spec = model_spec(&args)?;
    let model = Model::build(&spec)?;
    let a = model.unit_matrix();
    let rhs: Vec<Vec<f64>> = [Axis::X, Axis::Y, Axis::Z]
        .into_iter()
        .map(|axis| model.scaled_rhs(axis))
        .collect();
    let n = a.n();
    let m = a.nnz() as f64 / n as f64;
    println!(
        "deform engine figures: {}³ grid, model {}, n = {n}, {} nonzeros ({m:.1} per row){}{}",
        args.grid,
        spec.connection.letter(),
        a.nnz(),
        if args.symmetry { ", mirrored half" } else { "" },
        if args.overlap {
            ", overlapping partition"
        } else {
            ", row-block partition"
        },
    );
    println!(
        "(QEMU -icount shift=0: instruction counts are exact; T = critical path per iteration)\n"
    );
    let table = [1u8, 2, 4, 8]
        .into_iter()
        .map(|harts| measure(&args, harts, a, &rhs))
        .collect::<anyhow::Result<Vec<Row>>>()?;
    print_per_element(&table, n);
    print_whole_solves(&table);
    print_critical_paths(&table, n, m);
    Ok(())
}

/// The benchmark model: corners fixed, the default load and two point loads across it, so that
/// the three directions' right-hand sides differ.
fn model_spec(args: &Args) -> anyhow::Result<ModelSpec> {
    let connection = match args.model.to_ascii_lowercase() {
        'a' => Connection::Axial,
        'b' => Connection::AxialShear,
        other => anyhow::bail!("--model must be a or b, not {other}"),
    };
    let grid = Grid::new(args.grid, args.grid, args.grid)?;
    Ok(ModelSpec {
        grid,
        connection,
        elasticity: Elasticity::new(1.0, 2.0, 0.5)?,
        field: None,
        fixed_sets: vec![FixedNodeSet::Corners],
        fixed_nodes: Vec::new(),
        prescribed: Vec::new(),
        loads: vec![
            ModelSpec::default_load(grid),
            PointLoad {
                node: Node::new(grid.nx() / 2, 0, grid.nz() / 2),
                force: [0.0, 1.0, 0.0],
            },
            PointLoad {
                node: Node::new(grid.nx() / 2, grid.ny() / 2, 0),
                force: [0.0, 0.0, 1.0],
            },
        ],
        pressures: Vec::new(),
    })
}

/// One direction's and three fused directions' solves on QEMU with `harts` harts (MVUs), cut
/// to two iterations.
fn measure(args: &Args, harts: u8, a: &Csr, rhs: &[Vec<f64>]) -> anyhow::Result<Row> {
    let options = EncodeOptions {
        mvus: harts,
        partition: if args.overlap {
            Partition::Overlap
        } else {
            Partition::Rows
        },
        use_symmetry: args.symmetry,
    };
    let encoding = encode_with(a, &options)?;
    let qemu = Qemu::start(&QemuConfig::new(firmware_elf()).harts(harts))?;
    let mut target = Target::connect(
        qemu.pty_path().to_str().unwrap_or_default(),
        Timeouts {
            handshake: Duration::from_secs(30),
            request: Duration::from_secs(30),
            solve: Duration::from_secs(600),
            ..Timeouts::default()
        },
    )?;
    anyhow::ensure!(
        target.info().harts == harts,
        "{harts} harts requested, {} came up",
        target.info().harts
    );
    target.upload_matrix(&encoding.matrix)?;
    let params = |directions| SolveParams {
        max_iterations: 2,
        tolerance: 1e-12,
        start: Start::Zero,
        directions,
        cycle_budget: 0,
    };
    let (single, _) = target.solve_for(&rhs[0], params(1))?;
    let refs: Vec<&[f64]> = rhs.iter().map(Vec::as_slice).collect();
    let (fused, _) = target.solve_fused(&refs, params(3))?;
    Ok(Row {
        harts,
        words: encoding.matrix.words.len(),
        single,
        fused,
    })
}

/// Instructions per word (one MVU) and per element (one hart), and hart 0's scalar work.
fn print_per_element(table: &[Row], n: usize) {
    let Row {
        words,
        single: one,
        fused: one_fused,
        ..
    } = &table[0];
    let w = *words as f64;
    println!("MVU instructions per nonzero (1 MVU, whole MVU phase incl. row ends and Kp max):");
    println!(
        "  one direction      {:6.2} per word",
        one.per_iteration.mvu_critical.instructions as f64 / w
    );
    println!(
        "  three fused        {:6.2} per word, {:5.2} per multiply-accumulate",
        one_fused.per_iteration.mvu_critical.instructions as f64 / w,
        one_fused.per_iteration.mvu_critical.instructions as f64 / (3.0 * w)
    );
    println!(
        "SVU instructions per element and direction (1 hart): {:.1} (one direction), {:.1} (fused)\n",
        one.per_iteration.svu_critical.instructions as f64 / n as f64,
        one_fused.per_iteration.svu_critical.instructions as f64 / (3.0 * n as f64)
    );
    let Row {
        single: eight,
        fused: eight_fused,
        ..
    } = &table[table.len() - 1];
    println!(
        "SVU scalar work on hart 0 per iteration and direction (first iteration, {} MVUs): {} (one direction), {} (fused)\n",
        eight.mvus,
        eight.first_iteration_scalar.instructions,
        eight_fused.first_iteration_scalar.instructions / 3
    );
}

/// Every MVU count's whole solves, set-up included.
fn print_whole_solves(table: &[Row]) {
    println!(
        "whole solves as measured ({} iterations; every phase's slowest hart + hart 0's serial work, set-up included):",
        table[0].single.iterations
    );
    for Row {
        harts,
        single,
        fused,
        ..
    } in table
    {
        println!(
            "  {harts} MVUs: one direction {} (MVU {} + SVU {}), three fused {} (MVU {} + SVU {})",
            whole(single),
            single.whole_solve.mvu_critical.instructions,
            single.whole_solve.svu_critical.instructions,
            whole(fused),
            fused.whole_solve.mvu_critical.instructions,
            fused.whole_solve.svu_critical.instructions,
        );
    }
    println!();
}

/// The first iteration's critical path on each MVU count, its speed-up and MFLOPS (thesis
/// eq. 56), one direction and three fused.
fn print_critical_paths(table: &[Row], n: usize, m: f64) {
    println!("critical path of the first CG iteration (T = slowest MVU + SVU), one direction:");
    println!(
        "  MVUs   T_MVU      T_SVU      T          speed-up  MFLOPS@100MHz  overlap  saturations"
    );
    let t1 = total(&table[0].single);
    for Row { harts, single, .. } in table {
        let t = total(single);
        let mflops = (2.0 * m * n as f64 + 6.0 * n as f64 + 2.0) / (t as f64 / 100e6) / 1e6;
        println!(
            "  {harts:<5}  {:<9}  {:<9}  {t:<9}  {:>7.2}×  {mflops:>12.1}   {:<7}  {}",
            single.per_iteration.mvu_critical.instructions,
            single.per_iteration.svu_critical.instructions,
            t1 as f64 / t as f64,
            single.overlapping,
            single.saturations,
        );
    }
    println!("\nthree fused directions (first iteration of all three):");
    let f1 = total(&table[0].fused);
    for Row {
        harts,
        single,
        fused,
        ..
    } in table
    {
        let t = total(fused);
        println!(
            "  {harts:<5}  T_MVU {:<9} T_SVU {:<9} T {t:<9} speed-up {:>5.2}×, vs three separate solves {:.2}×",
            fused.per_iteration.mvu_critical.instructions,
            fused.per_iteration.svu_critical.instructions,
            f1 as f64 / t as f64,
            3.0 * total(single) as f64 / t as f64,
        );
    }
}

fn whole(report: &SolveReport) -> u64 {
    report.whole_solve.mvu_critical.instructions + report.whole_solve.svu_critical.instructions
}

fn total(report: &SolveReport) -> u64 {
    report.per_iteration.mvu_critical.instructions + report.per_iteration.svu_critical.instructions
}
