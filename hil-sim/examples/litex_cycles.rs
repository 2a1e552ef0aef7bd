//! True cycles: the CG engine on a VexRiscv's RTL (LiteX SoC under Verilator), its `mcycle`
//! beside its `minstret`, and QEMU's exact instruction counts beside both.
//!
//! ```text
//! cargo xtask setup && cargo xtask firmware && cargo xtask firmware --board litex
//! cargo run --release -p deform-hil-sim --example litex_cycles [-- --edges 4,6,8 --model a]
//! ```
//!
//! For each cubic grid (one MVU, the `deform solve` layout: row blocks, mirrored half when K is
//! persymmetric) it solves one direction for a fixed number of iterations on both targets and
//! prints, per CG iteration: the MVU phase's cycles and instructions (and so its CPI and its
//! cycles per instruction word), the SVU's, and the whole iteration's, the time at a 100 MHz
//! soft-core clock, and the thesis's hardware (one instruction word per clock: 3,320 cycles
//! for 500 nodes of model A, 11,220 for model B, sec. 5.2.1) beside them.
//!
//! The counts are the firmware's own: `mcycle` and `minstret` around each phase (on LiteX the
//! RTL's cycles; under QEMU `-icount` a cycle is an instruction). They cover the whole phase:
//! loop, row ends and the reductions, not only the inner loop. The first iteration runs with
//! cold caches; its cost is averaged in.

use std::time::{Duration, Instant};

use clap::Parser;
use deform_hil_sim::litex::{litex_firmware_elf, LitexConfig, LitexSim};
use deform_hil_sim::{firmware_elf, Qemu, QemuConfig};
use deform_host::encode::{encode_with, EncodeOptions, Partition};
use deform_host::link::{Target, Timeouts};
use deform_host::model::{Axis, Connection, Elasticity, FixedNodeSet, Grid, Model, ModelSpec};
use deform_shared::protocol::{SolveParams, SolveReport, Start};

#[derive(Parser)]
#[command(about = "Cycles and instructions per CG iteration on the LiteX VexRiscv and QEMU")]
struct Args {
    /// Nodes per side of the cubic grids.
    #[arg(long, value_delimiter = ',', default_values_t = [4usize, 6, 8])]
    edges: Vec<usize>,
    /// Spring model: a (6 neighbours) or b (26 neighbours).
    #[arg(long, default_value = "a")]
    model: char,
    /// CG iterations per measured solve (the tolerance is unreachable, so each runs them all).
    #[arg(long, default_value_t = 8)]
    iterations: u32,
    /// Store the whole K (one multiply-accumulate per word) instead of the mirrored half.
    #[arg(long)]
    whole: bool,
    /// The soft core's clock for the time column, MHz.
    #[arg(long, default_value_t = 100.0)]
    clock_mhz: f64,
    /// An SoC whose bus bursts (a cache line in one Wishbone burst): its own Verilator build.
    #[arg(long)]
    bus_bursting: bool,
}

/// The thesis's hardware, 500 nodes, one MVU: cycles per CG iteration (model A, model B).
const THESIS_CYCLES: (u64, u64) = (3_320, 11_220);

/// Per-iteration figures of one solve.
struct Figures {
    mvu: (f64, f64),
    svu: (f64, f64),
}

impl Figures {
    fn of(report: &SolveReport) -> Figures {
        let per = |x: u64| x as f64 / f64::from(report.iterations.max(1));
        Figures {
            mvu: (per(report.mvu.cycles), per(report.mvu.instructions)),
            svu: (per(report.svu.cycles), per(report.svu.instructions)),
        }
    }

    fn cycles(&self) -> f64 {
        self.mvu.0 + self.svu.0
    }

    fn instructions(&self) -> f64 {
        self.mvu.1 + self.svu.1
    }
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let (connection, thesis) = match args.model.to_ascii_lowercase() {
        'a' => (Connection::Axial, THESIS_CYCLES.0),
        'b' => (Connection::AxialShear, THESIS_CYCLES.1),
        other => anyhow::bail!("--model must be a or b, not {other}"),
    };
    let timeouts = Timeouts {
        handshake: Duration::from_secs(120),
        request: Duration::from_secs(120),
        solve: Duration::from_secs(1800),
        ..Timeouts::default()
    };
    let started = Instant::now();
    let mut config = LitexConfig::new(litex_firmware_elf());
    config.soc.bus_bursting = args.bus_bursting;
    let sim = LitexSim::start(&config)?;
    let mut litex = Target::connect(sim.serial_path().to_str().unwrap_or_default(), timeouts)?;
    let qemu = Qemu::start(&QemuConfig::new(firmware_elf()))?;
    let mut virt = Target::connect(qemu.pty_path().to_str().unwrap_or_default(), timeouts)?;
    println!(
        "deform on a LiteX VexRiscv (imac, Verilator) and QEMU virt, model {}, 1 MVU, {}, {} \
         iterations per solve; per CG iteration:",
        connection.letter(),
        if args.whole {
            "whole K"
        } else {
            "mirrored half of K where persymmetric"
        },
        args.iterations
    );
    println!(
        "{:>5} {:>6} | {:>9} {:>9} {:>5} {:>6} | {:>9} {:>9} {:>5} | {:>9} {:>9} {:>5} {:>8} | {:>9} | {:>7}",
        "n", "words", "MVU cyc", "MVU ins", "CPI", "cyc/wd", "SVU cyc", "SVU ins", "CPI",
        "cycles", "instr", "CPI", "µs", "QEMU ins", "/thesis"
    );
    for &edge in &args.edges {
        let grid = Grid::new(edge, edge, edge)?;
        let spec = ModelSpec {
            grid,
            connection,
            elasticity: Elasticity::new(1.0, 2.0, 0.5)?,
            field: None,
            fixed_sets: vec![FixedNodeSet::Corners],
            fixed_nodes: Vec::new(),
            prescribed: Vec::new(),
            loads: vec![ModelSpec::default_load(grid)],
            pressures: Vec::new(),
        };
        let model = Model::build(&spec)?;
        let a = model.unit_matrix();
        let encoding = encode_with(
            a,
            &EncodeOptions {
                mvus: 1,
                partition: Partition::Rows,
                use_symmetry: !args.whole,
            },
        )?;
        let rhs = model.scaled_rhs(Axis::X);
        let params = SolveParams {
            max_iterations: args.iterations,
            tolerance: 1e-300,
            start: Start::Zero,
            directions: 1,
            cycle_budget: 0,
        };
        let run = |target: &mut Target| -> anyhow::Result<SolveReport> {
            target.upload_matrix(&encoding.matrix)?;
            Ok(target.solve_for(&rhs, params)?.0)
        };
        let on_litex = Figures::of(&run(&mut litex)?);
        let on_qemu = Figures::of(&run(&mut virt)?);
        let words = encoding.matrix.words.len() as f64;
        let cycles = on_litex.cycles();
        println!(
            "{:>5} {:>6} | {:>9.0} {:>9.0} {:>5.2} {:>6.2} | {:>9.0} {:>9.0} {:>5.2} | {:>9.0} {:>9.0} {:>5.2} {:>8.1} | {:>9.0} | {:>6.1}×",
            a.n(),
            words,
            on_litex.mvu.0,
            on_litex.mvu.1,
            on_litex.mvu.0 / on_litex.mvu.1,
            on_litex.mvu.0 / words,
            on_litex.svu.0,
            on_litex.svu.1,
            on_litex.svu.0 / on_litex.svu.1,
            cycles,
            on_litex.instructions(),
            cycles / on_litex.instructions(),
            cycles / args.clock_mhz,
            on_qemu.instructions(),
            cycles / thesis as f64,
        );
    }
    println!(
        "(cycles: VexRiscv mcycle; instr: its minstret; cyc/wd: MVU-phase cycles per stored \
         instruction word; µs at {} MHz; QEMU ins: QEMU's exact instructions per iteration; \
         /thesis: cycles over the thesis's {thesis} per iteration at 500 nodes, one word per clock)",
        args.clock_mhz
    );
    eprintln!("wall time {:.1} s", started.elapsed().as_secs_f64());
    drop(sim);
    Ok(())
}
