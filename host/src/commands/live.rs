//! `deform live SCENARIO.toml`: the real-time loop ([`crate::live`]). With `--headless` the
//! tool follows the scenario's keyframes for `--frames` frames and a JSON report says what the
//! target achieved, every frame checked against the f64 reference; with `--serve` a person
//! moves the tool in a browser and sees the tissue respond. The scenario picks the tool's kind
//! and whether frames are quasi-static or dynamic ([`crate::live::start`]).

use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::bail;
use clap::Args;

use crate::board::{session_timeouts, Board, BoardFlags, TargetKind, DEFAULT_QEMU_HARTS};
use crate::dynamics::flags::DynamicFlags;
use crate::live::engine::{Engine, Frame};
use crate::live::field::FieldChoice;
use crate::live::interactive;
use crate::live::report::{model_label, Place, SessionReport};
use crate::live::serve::Mailbox;
use crate::live::session::{self, Summary};
use crate::live::sink::FrameSink;
use crate::live::start::{Live, Mode, Options};
use crate::model::flags::ConnectionArg;
use crate::model::Connection;
use crate::output::paths::Outputs;
use crate::output::write_json;
use crate::refine::parse_tolerance;

/// The real-time loop over a scenario's tool.
#[derive(Debug, Args)]
pub struct LiveArgs {
    /// Scenario file: the tissue, its fixed set and static loads, and the tool — its
    /// `[[simulation.displace]]` nodes, moved along their keyframes over steps·dt (a
    /// displacement tool: the force comes back), or its `[[simulation.load]]` nodes, loaded
    /// along their keyframes (a force tool: the tool's mean displacement comes back; with
    /// --serve the browser sets the load, 1 grid unit = 1 N).
    pub scenario: PathBuf,

    /// Run the scripted session without a browser (the tool follows the keyframes).
    #[arg(long)]
    pub headless: bool,

    /// Serve the live view at --addr: the tissue in 3-D, the tool moved with the mouse or
    /// keys, the force and the target's cycles per frame, updated over a WebSocket. For a
    /// force tool the mouse or keys set the load and the page shows the tool's motion.
    #[arg(long, conflicts_with_all = ["headless", "frames", "report", "frames_csv", "out", "pace"])]
    pub serve: bool,

    /// Where --serve listens for the page (the WebSocket gets a port of its own, printed too).
    /// Port 0: any free port.
    #[arg(long, value_name = "IP:PORT", default_value = "127.0.0.1:8080")]
    pub addr: std::net::SocketAddr,

    /// Full frames to run, spread evenly over the scenario's time span (dynamic frames: one
    /// step of dt each, N·dt seconds, the keyframes holding their last value after their end).
    /// Default: its steps.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..))]
    pub frames: Option<u32>,

    /// Write the session's figures as JSON (frame cycles, rates at 100 MHz, iterations,
    /// residuals, error against a converged solve, bytes per frame on the line).
    #[arg(long, value_name = "FILE")]
    pub report: Option<PathBuf>,

    /// Write one CSV row per frame (t, tool, force and its reference — for a force tool the
    /// mean tool displacement —, residual, iterations, cycles, error against a converged solve,
    /// bytes up and down).
    #[arg(long, value_name = "FILE")]
    pub frames_csv: Option<PathBuf>,

    /// Record the session for ParaView, every frame's solution: a directory (one
    /// frame_NNNNN.vtu per frame and series.pvd), FILE.pvd (the .vtu files beside it) or
    /// FILE.csv (`frame,t,i,j,k,ux,uy,uz`).
    #[arg(long, value_name = "DIR|FILE.pvd|FILE.csv")]
    pub out: Option<PathBuf>,

    /// Relative residual at which a frame's solve stops, in (0, 1). [default: 1e-4]
    #[arg(long, value_parser = parse_tolerance, allow_hyphen_values = true)]
    pub tol: Option<f64>,

    /// Cycle budget per frame's solve, in hart 0's cycles (0: none). 333 333 is 300 frames/s
    /// at 100 MHz. Under QEMU with several harts hart 0 reads the machine-wide instruction
    /// count, the sum over all harts, so there a budget limits the work of all MVUs together.
    /// Frames over it are counted and reported. [default: 0]
    #[arg(long, value_name = "CYCLES")]
    pub cycle_budget: Option<u64>,

    /// Iteration budget per frame (per target solve of a dynamic frame). [default: 500]
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..))]
    pub max_iter: Option<u32>,

    /// Read the quantised field every this many frames (the field rate; 0: never).
    /// [default: 10]
    #[arg(long, value_name = "N")]
    pub field_every: Option<u32>,

    /// Which nodes a field frame carries: `all`, `surface` (the nodes on the outside of the
    /// box grid: 296 of 512 on an 8³ grid) or `stride:K` (every K-th node in node order).
    /// Fewer nodes, fewer bytes: the frame's components travel as differences from the
    /// previous node's, 1–2 bytes each for a smooth field. The browser view draws only the
    /// nodes sent. [default: all]
    #[arg(long, value_name = "all|surface|stride:K")]
    pub field: Option<FieldChoice>,

    /// Force queries from the local model between two full frames (the haptic rate); for a
    /// force tool, displacement queries from the compliance model. [default: 3]
    #[arg(long, value_name = "N")]
    pub forces_per_frame: Option<u32>,

    /// Run the tool in real time at this many frames per second of wall clock over the
    /// scenario's time span: a frame waits for its slot, slots the target cannot keep up with
    /// are dropped (not queued) and the lag is reported; only solved frames are counted.
    /// Default: every scripted frame, however long it takes.
    #[arg(long, value_name = "HZ", conflicts_with = "frames")]
    pub pace: Option<f64>,

    #[command(flatten)]
    pub board: BoardFlags,

    /// Spring model, overriding the scenario's: a (6 axial neighbours) or b (all 26).
    #[arg(long, value_name = "a|b", value_enum)]
    pub model: Option<ConnectionArg>,

    /// Seconds to wait for one frame's answer. [default: 60]
    #[arg(long, value_name = "SECS", value_parser = clap::value_parser!(u64).range(1..))]
    pub timeout: Option<u64>,

    /// A dynamic scenario (or `--dynamic`) runs dynamic frames: each frame is one time step
    /// h = the scenario's dt, the tissue has inertia and damping and keeps moving after the
    /// tool stops. --cycle-budget and --pace are refused then; --field-every, --field and
    /// --forces-per-frame do not apply (the whole field comes back every frame).
    #[command(flatten)]
    pub dynamics: DynamicFlags,
}

impl LiveArgs {
    fn options(&self) -> Options {
        Options {
            tol: self.tol,
            max_iter: self.max_iter,
            cycle_budget: self.cycle_budget,
            max_solves: self.dynamics.max_solves,
            field_every: self.field_every,
            field: self.field,
            forces_per_frame: self.forces_per_frame,
            frames: self.frames,
            pace: self.pace,
            timeout: self.timeout,
        }
    }

    /// The MVUs K is split over: `--mvus`, else all of QEMU's 8 harts or LiteX's one.
    fn mvus(&self) -> u8 {
        let litex = self.board.kind(None) == TargetKind::Litex && self.board.target.port.is_none();
        self.board
            .mvus
            .unwrap_or(if litex { 1 } else { DEFAULT_QEMU_HARTS })
    }
}

pub fn run(args: &LiveArgs) -> anyhow::Result<()> {
    if !args.headless && !args.serve {
        bail!("give --headless (the scripted session) or --serve (the browser view)");
    }
    crate::interrupt::install();
    let options = args.options();
    let choice = args.board.choice(None)?;
    let live = Live::load(
        &args.scenario,
        args.model.map(Connection::from),
        &args.dynamics,
        args.mvus(),
    )?;
    let mode = Mode {
        dynamic: live.dynamics.is_some(),
        on_host: choice.is_none(),
        serve: args.serve,
    };
    options.check(mode)?;
    Outputs::new()
        .input("scenario", Some(&args.scenario))
        .file("--report", args.report.as_deref())
        .file("--frames-csv", args.frames_csv.as_deref())
        .directory("--out", args.out.as_deref())
        .check()?;
    let built = live.dynamic_model(choice.is_some())?;
    let mut board = match &choice {
        Some(choice) => Some(Board::open(
            choice,
            session_timeouts(options.timeout()),
            &args.board.target.logs.options(),
        )?),
        None => None,
    };
    println!("model       {}", live.setup.model.spec().describe());
    if let Some(spec) = &live.dynamics {
        println!(
            "dynamics    {}; h = {} s, one step per frame",
            spec.describe(),
            live.simulation.dt
        );
    }
    let checked = args.headless;
    let mut engine = live.engine(board.as_mut(), built, &options, checked)?;
    if let Some(model) = engine.model_report() {
        println!(
            "{} {} CG solve(s), {} iterations, {} cycles",
            model_label(live.setup.kind),
            model.solves,
            model.iterations,
            model.cycles
        );
    }
    match args.serve {
        true => serve(args, &live, &mut *engine, mode),
        false => headless(args, &live, &mut *engine, &options, mode),
    }
}

/// `--serve`: the page, its WebSocket and frames for the browser's tool until stopped.
fn serve(args: &LiveArgs, live: &Live, engine: &mut dyn Engine, mode: Mode) -> anyhow::Result<()> {
    let setup = &live.setup;
    let field = args.field.unwrap_or_default();
    // The host and dynamic frames have every node's displacement.
    let shown = match mode.on_host || mode.dynamic {
        true => vec![true; setup.model.n()],
        false => field.carried(&setup.model.grid(), setup.model.n()),
    };
    let mailbox = Arc::new(Mailbox::new(interactive::mesh_json(setup, &shown)));
    let bound = crate::live::serve::start(args.addr, mailbox.clone())?;
    println!(
        "serving     http://{}/ (WebSocket on port {}); Ctrl-C to stop",
        bound.http,
        bound.websocket.port()
    );
    std::io::stdout().flush()?;
    interactive::run(setup, engine, field, &mailbox)
}

/// `--headless`: the scripted frames through the sink, then the report.
fn headless(
    args: &LiveArgs,
    live: &Live,
    engine: &mut dyn Engine,
    options: &Options,
    mode: Mode,
) -> anyhow::Result<()> {
    let setup = &live.setup;
    let script = live.script(options);
    let on = args.board.target.report_name(None);
    println!(
        "{}",
        live.tool_line(options, &script, mode, on, args.mvus())
    );
    let mut sink = FrameSink::create(
        &setup.model,
        setup.kind,
        mode.dynamic,
        args.frames_csv.as_deref(),
        args.out.as_deref(),
    )?;
    let progress = crate::progress::bar(script.timing.frames(), "frames");
    let tool_at = |t: f64| live.tool_at(t);
    let ran = session::run(engine, &script, &tool_at, |frame, u| {
        progress.inc(1);
        sink.write(frame, u)
    });
    progress.finish_and_clear();
    // The files are finished whether the session ran to its end or not.
    let wrote = sink.finish();
    let (frames, summary) = ran?;
    for line in wrote? {
        println!("wrote       {line}");
    }
    report(args, live, engine, &frames, &summary, mode)?;
    if summary.interrupted {
        bail!(
            "interrupted after {} frame(s); the files hold the frames so far",
            frames.len()
        );
    }
    Ok(())
}

/// The report of the frames: printed, and written with --report.
fn report(
    args: &LiveArgs,
    live: &Live,
    engine: &dyn Engine,
    frames: &[Frame],
    summary: &Summary,
    mode: Mode,
) -> anyhow::Result<()> {
    let on = Place {
        target: args.board.target.report_name(None).to_string(),
        mvus: if mode.on_host { 0 } else { args.mvus() },
    };
    let report = SessionReport::of(live, engine, &args.options(), on, frames, summary);
    print!("{}", report.summary(live.setup.kind));
    if let Some(path) = &args.report {
        write_json(path, &report)?;
        println!("wrote       {}", path.display());
    }
    Ok(())
}
