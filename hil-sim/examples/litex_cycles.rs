//! True cycles: the CG engine on a VexRiscv's RTL (LiteX SoC under Verilator), its `mcycle`
//! beside its `minstret`, and QEMU's exact instruction counts beside both.
//!
//! ```text
//! cargo xtask setup && cargo xtask firmware && cargo xtask firmware --board litex
//! cargo run --release -p deform-hil-sim --example litex_cycles [-- --edges 4,6,8 --model a]
//! cargo run --release -p deform-hil-sim --example litex_cycles -- --mvus 4 [--whole]
//! cargo run --release -p deform-hil-sim --example litex_cycles -- --edges 8 --trace t.vcd
//! cargo run --release -p deform-hil-sim --example litex_cycles -- --edges 8 --no-bus-bursting
//! ```
//!
//! For each cubic grid (the `deform solve` layout: row blocks over `--mvus` MVUs, one without
//! the flag; mirrored half when K is persymmetric) it solves one direction for a fixed number of
//! iterations on both targets and
//! prints, per CG iteration: the MVU phase's cycles and instructions (and so its CPI and its
//! cycles per instruction word), the SVU's, and the whole iteration's, the time at a 100 MHz
//! soft-core clock, and the thesis's hardware (one instruction word per clock: 3,320 cycles
//! for 500 nodes of model A, 11,220 for model B, sec. 5.2.1) beside them.
//!
//! The counts are the firmware's own: `mcycle` and `minstret` around each phase (on LiteX the
//! RTL's cycles; under QEMU `-icount` a cycle is an instruction). They cover the whole phase:
//! loop, row ends and the reductions, not only the inner loop. The first iteration runs with
//! cold caches; its cost is averaged in.
//!
//! With `--mvus N` the SoC has N hardware MVUs (gateware/) and the MVU phase runs on them: its
//! cycles are then the CPU's start, wait and read-out around the array's work, and the
//! firmware's log line "MVU array: … cycles in the MVUs" (printed when the next grid's matrix
//! replaces the last) gives the array's own clocks. QEMU runs the same layout on N harts.
//!
//! With `--trace FILE` the SoC is the traced one (`hil-sim/litex/deform_soc_trace.py`, its own
//! Verilator build): a probe copies the VexRiscv's pipeline signals, and the simulator dumps
//! them for `--trace-cycles` clocks from the (`--trace-skip` + 1)-th retirement of the
//! instruction at `--trace-pc` (by default the head of the one-direction mirrored split loop,
//! found in the firmware by `vex_stalls.py locate`, and skipping two MVU phases' words and 100
//! more, so the window falls in the third iteration's MVU phase with warm caches). The VCD goes
//! to FILE, and `hil-sim/litex/vex_stalls.py analyse` prints why each clock of the window did
//! or did not retire, per cause and per iteration of the hottest loops.
//!
//! The SoC's bus bursts by default (a cache line fills in one Wishbone burst; issue 19);
//! `--no-bus-bursting` measures the SoC without bursts, as every figure before session 11 was
//! unless it says "bursting".

use std::time::{Duration, Instant};

use clap::Parser;
use std::path::{Path, PathBuf};
use std::process::Command;

use deform_hil_sim::litex::{litex_dir, litex_firmware_elf, LitexConfig, LitexSim, TraceWindow};
use deform_hil_sim::{firmware_elf, Qemu, QemuConfig};
use deform_host::board::{Board, BoardChoice, LogOptions};
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
    /// Hardware MVUs in the SoC, and MVUs the layout uses (0: the MVU phase in software, one
    /// MVU's layout).
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u8).range(0..=8))]
    mvus: u8,
    /// An SoC whose bus does not burst (a cache line by one single access per word), as every
    /// SoC was before session 11 (its `--bus-bursting` is now the default): its own Verilator
    /// build.
    #[arg(long)]
    no_bus_bursting: bool,
    /// Trace the VexRiscv's pipeline into this VCD and attribute its stalls (one grid only).
    #[arg(long)]
    trace: Option<PathBuf>,
    /// The traced window's start: this instruction's retirement (hex; default: the head of the
    /// one-direction mirrored split loop in the firmware).
    #[arg(long, value_parser = parse_hex)]
    trace_pc: Option<u32>,
    /// Retirements of `--trace-pc` before the window (default: two MVU phases' words + 100).
    #[arg(long)]
    trace_skip: Option<u32>,
    /// Clocks in the traced window.
    #[arg(long, default_value_t = 20_000)]
    trace_cycles: u32,
}

fn parse_hex(text: &str) -> Result<u32, String> {
    u32::from_str_radix(text.trim_start_matches("0x"), 16).map_err(|e| format!("{text}: {e}"))
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
    let layout_mvus = args.mvus.max(1);
    if args.trace.is_some() && args.edges.len() != 1 {
        anyhow::bail!("--trace takes one grid (--edges N)");
    }
    let first = encode_grid(args.edges[0], connection, args.whole, layout_mvus)?;
    // The firmware's logs are printed (the MVU array's own cycle count among them), except on
    // the non-bursting and traced SoCs, which Board::open does not build.
    let (mut own, mut board);
    let litex: &mut Target = if args.no_bus_bursting || args.trace.is_some() {
        let mut config = LitexConfig::new(litex_firmware_elf()).with_mvus(args.mvus);
        config.soc.bus_bursting = !args.no_bus_bursting;
        if args.trace.is_some() {
            config.soc.trace = true;
            config.trace_window = Some(trace_window(&args, first.1.matrix.words.len())?);
            eprintln!("traced window: {:x?}", config.trace_window);
        }
        let sim = LitexSim::start(&config)?;
        let target = Target::connect(sim.serial_path().to_str().unwrap_or_default(), timeouts)?;
        own = Some((sim, target));
        &mut own.as_mut().expect("just set").1
    } else {
        own = None;
        let choice = BoardChoice::Litex {
            firmware: None,
            mvus: args.mvus,
        };
        board = Board::open(&choice, timeouts, &LogOptions::default())?;
        &mut board.target
    };
    let qemu = Qemu::start(&QemuConfig::new(firmware_elf()).harts(layout_mvus))?;
    let mut virt = Target::connect(qemu.pty_path().to_str().unwrap_or_default(), timeouts)?;
    println!(
        "deform on a LiteX VexRiscv (imac, Verilator{}) and QEMU virt, model {}, {} MVU(s), {}, \
         {} iterations per solve; per CG iteration:",
        if args.mvus > 0 { ", hardware MVUs" } else { "" },
        connection.letter(),
        layout_mvus,
        if args.whole {
            "whole K"
        } else {
            "mirrored half of K where persymmetric"
        },
        args.iterations
    );
    println!(
        "{:>5} {:>6} | {:>9} {:>9} {:>5} {:>6} {:>6} | {:>9} {:>9} {:>5} | {:>9} {:>9} {:>5} {:>8} | {:>9} | {:>7}",
        "n", "words", "MVU cyc", "MVU ins", "CPI", "cyc/wd", "/MVU", "SVU cyc", "SVU ins", "CPI",
        "cycles", "instr", "CPI", "µs", "QEMU ins", "/thesis"
    );
    let mut first = Some(first);
    for &edge in &args.edges {
        let (model, encoding) = match first.take() {
            Some(built) => built,
            None => encode_grid(edge, connection, args.whole, layout_mvus)?,
        };
        let a = model.unit_matrix();
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
        let on_litex = Figures::of(&run(litex)?);
        let on_qemu = Figures::of(&run(&mut virt)?);
        let words = encoding.matrix.words.len() as f64;
        let cycles = on_litex.cycles();
        println!(
            "{:>5} {:>6} | {:>9.0} {:>9.0} {:>5.2} {:>6.2} {:>6.2} | {:>9.0} {:>9.0} {:>5.2} | {:>9.0} {:>9.0} {:>5.2} {:>8.1} | {:>9.0} | {:>6.1}×",
            a.n(),
            words,
            on_litex.mvu.0,
            on_litex.mvu.1,
            on_litex.mvu.0 / on_litex.mvu.1,
            on_litex.mvu.0 / words,
            on_litex.mvu.0 * f64::from(layout_mvus) / words,
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
         instruction word, /MVU: the same per MVU (words / MVUs); µs at {} MHz; QEMU ins: \
         QEMU's exact instructions per iteration; /thesis: cycles over the thesis's {thesis} per \
         iteration at 500 nodes, one word per clock)",
        args.clock_mhz
    );
    // A Hello drops the last matrix: with hardware MVUs the firmware logs their cycles.
    litex.reset()?;
    std::thread::sleep(Duration::from_secs(2));
    if let (Some(path), Some((sim, target))) = (&args.trace, own) {
        drop(target);
        sim.keep_trace(path)?;
        analyse(path)?;
    }
    eprintln!("wall time {:.1} s", started.elapsed().as_secs_f64());
    Ok(())
}

/// The model and its encoding for the cubic grid of `edge` nodes a side.
fn encode_grid(
    edge: usize,
    connection: Connection,
    whole: bool,
    mvus: u8,
) -> anyhow::Result<(Model, deform_host::encode::Encoding)> {
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
    let encoding = encode_with(
        model.unit_matrix(),
        &EncodeOptions {
            mvus,
            partition: Partition::Rows,
            use_symmetry: !whole,
        },
    )?;
    Ok((model, encoding))
}

/// The analyser beside the SoC generator, run by the LiteX venv's Python.
fn vex_stalls() -> (PathBuf, PathBuf) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("litex/vex_stalls.py");
    (litex_dir().join("venv/bin/python"), script)
}

/// The traced window from the arguments, the loop head found in the firmware by default.
fn trace_window(args: &Args, words: usize) -> anyhow::Result<TraceWindow> {
    let start_pc = match args.trace_pc {
        Some(pc) => pc,
        None => {
            let (python, script) = vex_stalls();
            let out = Command::new(python)
                .arg(script)
                .args(["locate", "--elf"])
                .arg(litex_firmware_elf())
                .output()?;
            if !out.status.success() {
                anyhow::bail!(
                    "vex_stalls.py locate failed (give --trace-pc): {}",
                    String::from_utf8_lossy(&out.stderr)
                );
            }
            parse_hex(String::from_utf8_lossy(&out.stdout).trim()).map_err(anyhow::Error::msg)?
        }
    };
    let skip = match args.trace_skip {
        Some(skip) => skip,
        None => u32::try_from(2 * words + 100)?,
    };
    Ok(TraceWindow {
        start_pc,
        skip,
        cycles: args.trace_cycles,
    })
}

/// Prints vex_stalls.py's attribution of the trace at `vcd`.
fn analyse(vcd: &Path) -> anyhow::Result<()> {
    let (python, script) = vex_stalls();
    let status = Command::new(python)
        .arg(script)
        .args(["analyse", "--listing", "--elf"])
        .arg(litex_firmware_elf())
        .arg("--vcd")
        .arg(vcd)
        .status()?;
    anyhow::ensure!(status.success(), "vex_stalls.py analyse failed ({status})");
    Ok(())
}
