//! `deform live SCENARIO.toml`: the interactive real-time loop (see [`crate::live`]). With
//! `--headless` the tool follows the scenario's keyframes for `--frames` frames and a JSON
//! report says what the target achieved, every frame checked against a converged f64 solve.
//! With `--serve` a person moves the tool in a browser and sees the tissue respond.
//!
//! The scenario picks the tool's kind: `[[simulation.displace]]` keyframes make a displacement
//! tool (the force comes back), `[[simulation.load]]` keyframes a force tool (protocol 9: the
//! tool's motion comes back, its local model the compliance). A scenario with both is refused.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context};
use clap::Args;
use deform_shared::live::LiveParams;

use crate::bench::board::{timeouts, BenchBoard, BenchBoardChoice};
use crate::cli_dynamics::DynamicFlags;
use crate::commands::simulate::bar;
use crate::encode::{EncodeOptions, Partition};
use crate::live::field::FieldChoice;
use crate::live::headless::{self, FrameRecord, Script, Session};
use crate::live::interactive;
use crate::live::link::LiveLink;
use crate::live::serve::Mailbox;
use crate::live::setup::ToolKind;
use crate::live::LiveSetup;
use crate::model::Connection;
use crate::output::node_rows;
use crate::output::vtk::{write_pvd, write_vtk, VtkKind};
use crate::scenario::Scenario;

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

    /// Record the session for ParaView: one .vtu per frame (the frame's solution) and
    /// series.pvd in this directory.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,

    /// Relative residual at which a frame's solve stops.
    #[arg(long, default_value_t = 1e-4)]
    pub tol: f64,

    /// Cycle budget per frame's solve, in hart 0's cycles (0: none). 333 333 is 300 frames/s
    /// at 100 MHz. Under QEMU with several harts hart 0 reads the machine-wide instruction
    /// count, the sum over all harts, so there a budget limits the work of all MVUs together.
    #[arg(long, default_value_t = 0)]
    pub cycle_budget: u64,

    /// Iteration budget per frame.
    #[arg(long, default_value_t = 500)]
    pub max_iter: u32,

    /// Read the quantised field every this many frames (the field rate; 0: never).
    #[arg(long, default_value_t = 10)]
    pub field_every: u32,

    /// Which nodes a field frame carries: `all`, `surface` (the nodes on the outside of the
    /// box grid: 386 of 729 on an 8³ grid) or `stride:K` (every K-th node in node order).
    /// Fewer nodes, fewer bytes: the frame's components travel as differences from the
    /// previous node's, 1–2 bytes each for a smooth field. The browser view draws only the
    /// nodes sent.
    #[arg(long, value_name = "all|surface|stride:K", default_value = "all")]
    pub field: FieldChoice,

    /// Force queries from the local model between two full frames (the haptic rate); for a
    /// force tool, displacement queries from the compliance model.
    #[arg(long, default_value_t = 3)]
    pub forces_per_frame: u32,

    /// Run the tool in real time at this many frames per second of wall clock: a frame takes
    /// the tool where it is now, frames the target cannot keep up with are dropped (not queued)
    /// and the lag is reported. Default: every scripted frame, however long it takes.
    #[arg(long, value_name = "HZ")]
    pub pace: Option<f64>,

    /// MVUs (harts) to boot QEMU with and split K over (`--target litex`: its one hart).
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u8).range(1..=8))]
    pub mvus: u8,

    /// Where frames are solved: `qemu` (the firmware in QEMU, default), `litex` (the
    /// `--board litex` firmware on the simulated LiteX VexRiscv SoC: real cycles, one MVU) or
    /// `host` (the f64 reference alone: forces and fields, no target figures).
    #[arg(long, value_name = "qemu|litex|host", default_value = "qemu", value_parser = ["qemu", "litex", "host"])]
    pub target: String,

    /// Serial device of a real board running the firmware. Default: boot it in QEMU.
    #[arg(long, value_name = "PATH")]
    pub port: Option<String>,

    /// Firmware ELF for QEMU or LiteX. Default: $DEFORM_FIRMWARE, else the release build (for
    /// `--target litex`, the `--board litex` build).
    #[arg(long, value_name = "ELF")]
    pub firmware: Option<PathBuf>,

    /// Spring model, overriding the scenario's: a (6 axial neighbours) or b (all 26).
    #[arg(long, value_name = "a|b", value_parser = ["a", "b"])]
    pub model: Option<String>,

    /// Seconds to wait for one frame's answer.
    #[arg(long, default_value_t = 60)]
    pub timeout: u64,

    /// A dynamic scenario (or `--dynamic`) runs dynamic frames: each frame is one time step
    /// h = the scenario's dt, the tissue has inertia and damping and keeps moving after the
    /// tool stops. --cycle-budget and --pace are refused then; --field-every, --field and
    /// --forces-per-frame do not apply (the whole field comes back every frame).
    #[command(flatten)]
    pub dynamics: DynamicFlags,
}

pub fn run(args: &LiveArgs) -> anyhow::Result<()> {
    if !args.headless && !args.serve {
        bail!("give --headless (the scripted session) or --serve (the browser view)");
    }
    if args.pace.is_some_and(|hz| !(hz.is_finite() && hz > 0.0)) {
        bail!("--pace must be a positive frame rate");
    }
    let mut scenario = Scenario::load(&args.scenario, None)?;
    match args.model.as_deref() {
        Some("a") => scenario.model.connection = Connection::Axial,
        Some("b") => scenario.model.connection = Connection::AxialShear,
        _ => {}
    }
    let Some(simulation) = scenario.simulation.clone() else {
        bail!(
            "{}: no [simulation] table, so no tool path: give [[simulation.displace]] or \
             [[simulation.load]] keyframes",
            args.scenario.display()
        );
    };
    let frames = args.frames.unwrap_or(simulation.steps);
    let end = simulation.end_time();
    let times: Vec<f64> = (1..=frames)
        .map(|i| end * f64::from(i) / f64::from(frames))
        .collect();
    let layout = EncodeOptions {
        mvus: args.mvu_count(),
        partition: Partition::Rows,
        use_symmetry: true,
    };
    let setup = LiveSetup::for_simulation(&scenario.model, &simulation, &layout)
        .with_context(|| format!("{}", args.scenario.display()))?;
    let grid = setup.model.grid();
    let tool_at = |t: f64| setup.tool_at(&scenario.model, &simulation, t);
    let dynamics = args
        .dynamics
        .resolve(simulation.dynamic, scenario.dynamics.as_ref())?;
    if let Some(spec) = dynamics {
        if setup.kind == ToolKind::Force {
            bail!(
                "{}: dynamic frames drive a displacement tool ([[simulation.displace]] \
                 keyframes); a force tool runs quasi-static frames only",
                args.scenario.display()
            );
        }
        let steps = (simulation.dt, simulation.steps);
        return super::live_dynamic::run(args, &setup, &spec, steps, &tool_at);
    }
    if args.serve {
        return serve(args, &setup);
    }
    if args.target == "host" {
        return run_on_host(args, &setup, &times, &tool_at);
    }
    let mut board = open_board(args)?;
    let params = live_params(args, &setup);
    println!("model       {}", setup.model.spec().describe());
    println!(
        "tool        {} {} node(s), {frames} frames over {end} s; tolerance {:e}, budget {} cycles, {} MVU(s)",
        setup.tools.len(),
        setup.kind.name(),
        args.tol,
        args.cycle_budget,
        args.mvu_count()
    );
    let mut link = LiveLink::start(&mut board.target, &setup, params)
        .context("setting the live session up on the target")?;
    println!(
        "{} {} CG solve(s), {} iterations, {} cycles",
        model_label(setup.kind),
        link.model.solves,
        link.model.iterations,
        link.model.cycles
    );
    let script = Script {
        field_every: args.field_every,
        field: args.field,
        forces_per_frame: args.forces_per_frame,
        pace: args.pace,
    };
    // A force tool's input is a load and its answer the mean tool displacement.
    let answer = match setup.kind {
        ToolKind::Displacement => "fx,fy,fz,fx_ref,fy_ref,fz_ref",
        ToolKind::Force => "ux,uy,uz,ux_ref,uy_ref,uz_ref",
    };
    let mut csv = open_outputs(
        args,
        &format!("frame,t,tool_x,tool_y,tool_z,{answer},residual,iterations,cycles,error_vs_converged,bytes_up,bytes_down"),
    )?;
    let mut pvd = Vec::new();
    let progress = bar(u64::from(frames), "frames");
    let mut written: std::io::Result<()> = Ok(());
    let on_frame = |r: &FrameRecord| {
        progress.inc(1);
        if let Some(dir) = &args.out {
            let name = format!("frame_{:05}.vtu", r.frame);
            let path = dir.join(&name);
            if let Err(e) = write_vtk(&path, &node_rows(&setup.model, &r.u), VtkKind::Unstructured)
            {
                if written.is_ok() {
                    written = Err(std::io::Error::other(format!("{}: {e:#}", path.display())));
                }
            }
            pvd.push((r.t, name));
        }
        if let Some(f) = csv.as_mut() {
            let u = r.tool.first().copied().unwrap_or([0.0; 3]);
            let line = writeln!(
                f,
                "{},{},{},{},{},{},{},{},{},{},{},{:e},{},{},{:e},{},{}",
                r.frame,
                r.t,
                u[0],
                u[1],
                u[2],
                r.force[0],
                r.force[1],
                r.force[2],
                r.force_reference[0],
                r.force_reference[1],
                r.force_reference[2],
                r.residual,
                r.iterations,
                r.cycles,
                r.error_vs_converged,
                r.bytes_up,
                r.bytes_down
            );
            if written.is_ok() {
                written = line;
            }
        }
    };
    let (records, summary) = headless::run(
        &mut link,
        &setup,
        &board.wire,
        &times,
        &tool_at,
        script,
        on_frame,
    )?;
    progress.finish_and_clear();
    written?;
    if let Some(mut f) = csv {
        f.flush()?;
    }
    if let Some(dir) = &args.out {
        let path = dir.join("series.pvd");
        write_pvd(&path, &pvd)?;
        println!("wrote       {} (+{} .vtu files)", path.display(), pvd.len());
    }
    let session = Session {
        grid: [grid.nx(), grid.ny(), grid.nz()],
        model: match setup.model.spec().connection {
            Connection::Axial => "a".into(),
            Connection::AxialShear => "b".into(),
        },
        mvus: args.mvu_count(),
        tolerance: args.tol,
        cycle_budget: args.cycle_budget,
        model_cycles: link.model.cycles,
        model_instructions: link.model.cycles.saturating_sub(link.model.stall_cycles),
        model_iterations: link.model.iterations,
        resets: link.resets,
        paced: args.pace.is_some(),
        kind: setup.kind,
        field: args.field,
    };
    let report = headless::report(session, &records, &summary);
    println!(
        "frames      {}: cycles p50 {:.0}, p99 {:.0}, max {:.0} → {:.0} frames/s at 100 MHz (worst {:.0})",
        report.frames,
        report.frame_cycles.p50,
        report.frame_cycles.p99,
        report.frame_cycles.max,
        report.frames_per_s_at_100mhz.p50,
        report.frames_per_s_at_100mhz.worst
    );
    println!("            {}", headless::instructions_line(&report));
    let (answer, unit) = match setup.kind {
        ToolKind::Displacement => ("force", "F"),
        ToolKind::Force => ("tool motion", "ū"),
    };
    println!(
        "accuracy    error vs converged ≤ {:.2e} of max |u|, {answer} ≤ {:.2e}, residual ≤ {:.2e}, iterations p50 {} max {}",
        report.error_vs_converged_max,
        report.force_error_max,
        report.residual_max,
        report.iterations.p50,
        report.iterations.max
    );
    println!(
        "{} {:.0} updates/s at 100 MHz ({} cycles per query), error ≤ {:.2e} of max |{unit}|",
        model_label(setup.kind),
        report.force_updates_per_s,
        report.force_query_cycles_max,
        report.model_force_error_max
    );
    println!(
        "line        {} B up / {} B down per frame (median; max {} / {})",
        report.bytes_up_per_frame,
        report.bytes_down_per_frame.force,
        report.bytes_up_per_frame_max,
        report.bytes_down_per_frame_max,
    );
    let field = &report.bytes_down_per_frame;
    println!(
        "field       {} ({} nodes): {} B per frame, {:.3} B per component, quantisation ≤ {:.1e}, built in {} cycles",
        field.field_selection,
        field.field_nodes,
        field.field,
        field.field_per_component,
        report.field_quantisation_error_max,
        field.field_build_cycles
    );
    for r in &report.link_rates {
        println!(
            "  {:>9} baud: {:.0} frames/s, {:.0} force queries/s, {:.1} field frames/s",
            r.baud, r.frames_per_s, r.force_queries_per_s, r.field_frames_per_s
        );
    }
    if let Some(lag) = report.lag {
        println!(
            "pace        {} frame slot(s) dropped, lag up to {:.3} s",
            lag.frames_dropped, lag.lag_max_s
        );
    }
    if report.target_resets > 0 {
        println!(
            "target reset {} time(s); set up again each time",
            report.target_resets
        );
    }
    if let Some(path) = &args.report {
        let f = File::create(path).with_context(|| format!("creating {}", path.display()))?;
        serde_json::to_writer_pretty(BufWriter::new(f), &report)?;
        println!("wrote       {}", path.display());
    }
    Ok(())
}

/// The local model's name in the summary (ten columns, as the other labels).
fn model_label(kind: ToolKind) -> &'static str {
    match kind {
        ToolKind::Displacement => "force model",
        ToolKind::Force => "compliance",
    }
}

impl LiveArgs {
    /// The MVUs K is split over: `--mvus`, except on the LiteX SoC, which has one hart.
    pub(crate) fn mvu_count(&self) -> u8 {
        if self.target == "litex" {
            1
        } else {
            self.mvus
        }
    }
}

/// Creates `--out`'s directory and opens `--frames-csv` with its `header` line: what the
/// quasi-static and the dynamic sessions both write.
pub(crate) fn open_outputs(
    args: &LiveArgs,
    header: &str,
) -> anyhow::Result<Option<BufWriter<File>>> {
    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let Some(path) = &args.frames_csv else {
        return Ok(None);
    };
    let mut f =
        BufWriter::new(File::create(path).with_context(|| format!("creating {}", path.display()))?);
    writeln!(f, "{header}")?;
    Ok(Some(f))
}

/// The board (or QEMU) the session runs on.
pub(crate) fn open_board(args: &LiveArgs) -> anyhow::Result<BenchBoard> {
    let choice = match &args.port {
        Some(port) => BenchBoardChoice::Port(port.clone()),
        None if args.target == "litex" => BenchBoardChoice::Litex {
            firmware: args.firmware.clone(),
        },
        None => BenchBoardChoice::Qemu {
            firmware: args.firmware.clone(),
        },
    };
    BenchBoard::open(
        &choice,
        args.mvu_count(),
        timeouts(Duration::from_secs(args.timeout)),
    )
}

fn live_params(args: &LiveArgs, setup: &LiveSetup) -> LiveParams {
    LiveParams {
        tolerance: args.tol as f32,
        max_iterations: args.max_iter,
        cycle_budget: args.cycle_budget,
        scale: setup.scale.map(|s| s as f32),
    }
}

/// Starts the page's server at `--addr` and says where: the mailbox the frames go through.
/// `shown`: the nodes whose displacement the page gets (the field selection's).
pub(crate) fn serve_page(
    args: &LiveArgs,
    setup: &LiveSetup,
    shown: &[bool],
) -> anyhow::Result<Arc<Mailbox>> {
    let mailbox = Arc::new(Mailbox::new(interactive::mesh_json(setup, shown)));
    let bound = crate::live::serve::start(args.addr, mailbox.clone())?;
    println!(
        "serving     http://{}/ (WebSocket on port {}); Ctrl-C to stop",
        bound.http,
        bound.websocket.port()
    );
    std::io::stdout().flush()?;
    Ok(mailbox)
}

/// `--serve`: the page and its WebSocket, the browser's tool positions solved frame by frame
/// on the target (or the host reference) until the process is stopped.
fn serve(args: &LiveArgs, setup: &LiveSetup) -> anyhow::Result<()> {
    let shown = match args.target.as_str() {
        // The host reference has every node's displacement.
        "host" => vec![true; setup.model.n()],
        _ => args.field.carried(&setup.model.grid(), setup.model.n()),
    };
    println!("model       {}", setup.model.spec().describe());
    let mut board = None;
    let mut link = None;
    if args.target != "host" {
        let b = board.insert(open_board(args)?);
        let l = LiveLink::start(&mut b.target, setup, live_params(args, setup))
            .context("setting the live session up on the target")?;
        println!(
            "{} {} CG solve(s), {} iterations, {} cycles",
            model_label(setup.kind),
            l.model.solves,
            l.model.iterations,
            l.model.cycles
        );
        link = Some(l);
    }
    let mailbox = serve_page(args, setup, &shown)?;
    match link.as_mut() {
        Some(link) => {
            let mut solver = interactive::TargetSolver {
                link,
                field: args.field,
                n: setup.model.n(),
            };
            interactive::run(setup, &mut solver, &mailbox)
        }
        None => {
            let mut solver = interactive::HostSolver { setup, warm: None };
            interactive::run(setup, &mut solver, &mailbox)
        }
    }
}

/// `--target host`: every frame solved by the f64 reference (converged), its force printed and,
/// with `--report`, written as JSON: the tool path and forces without any target figures.
fn run_on_host(
    args: &LiveArgs,
    setup: &LiveSetup,
    times: &[f64],
    tool_at: &dyn Fn(f64) -> Vec<[f64; 3]>,
) -> anyhow::Result<()> {
    #[derive(serde::Serialize)]
    struct HostFrame {
        t: f64,
        tool: Vec<[f64; 3]>,
        /// Displacement tools: the reaction force.
        #[serde(skip_serializing_if = "Option::is_none")]
        force: Option<[f64; 3]>,
        /// Force tools: the tool nodes' mean displacement.
        #[serde(skip_serializing_if = "Option::is_none")]
        displacement: Option<[f64; 3]>,
        max_u: f64,
    }
    let progress = bar(times.len() as u64, "frames");
    let mut warm: Option<[Vec<f64>; 3]> = None;
    let mut frames = Vec::new();
    for &t in times {
        let tool = tool_at(t);
        let (u, answer) = setup.converged(&tool, warm.as_ref())?;
        let force_tool = setup.kind == ToolKind::Force;
        let max_u = u
            .iter()
            .map(|v| crate::reference::max_abs(v))
            .fold(0.0, f64::max);
        frames.push(HostFrame {
            t,
            tool,
            force: (!force_tool).then_some(answer),
            displacement: force_tool.then_some(answer),
            max_u,
        });
        warm = Some(u);
        progress.inc(1);
    }
    progress.finish_and_clear();
    if let Some(last) = frames.last() {
        let (what, v, unit) = match (last.force, last.displacement) {
            (Some(f), _) => ("force", f, "N"),
            (None, Some(u)) => ("tool displacement", u, "m"),
            (None, None) => ("force", [0.0; 3], "N"),
        };
        println!(
            "host        {} frames solved by the f64 reference; last {what} ({:.6e}, {:.6e}, {:.6e}) {unit}, max |u| {:.4e}",
            frames.len(),
            v[0],
            v[1],
            v[2],
            last.max_u
        );
    }
    if let Some(path) = &args.report {
        let f = File::create(path).with_context(|| format!("creating {}", path.display()))?;
        serde_json::to_writer_pretty(
            BufWriter::new(f),
            &serde_json::json!({
                "frames": frames.len(),
                "target": "host",
                "tool": setup.kind.name(),
                "per_frame": frames,
            }),
        )?;
        println!("wrote       {}", path.display());
    }
    Ok(())
}
