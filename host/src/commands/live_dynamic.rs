//! `deform live` on a dynamic scenario (`[simulation] dynamic = true`, or `--dynamic`): every
//! frame is one time step h = the scenario's dt ([`crate::live::dynamic`]). `--headless` runs
//! `--frames` steps with the tool on its keyframes at t = frame·h and reports them
//! ([`crate::live::dynamic_report`]); `--serve` steps with the tool where the browser has it.
//! `deform live` dispatches here once the scenario and the tool are known.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::PathBuf;

use anyhow::{bail, Context};

use super::live::{open_board, open_outputs, serve_page, LiveArgs};
use super::simulate::bar;
use crate::dynamics::target::{preflight, DynamicParams};
use crate::dynamics::DynamicsSpec;
use crate::encode::{EncodeOptions, Partition};
use crate::link::Port;
use crate::live::dynamic::{DynamicFrame, DynamicLive, DynamicViewSolver};
use crate::live::dynamic_report::{report, DynamicInfo, DynamicReport, Header};
use crate::live::{interactive, LiveSetup};
use crate::model::Connection;
use crate::output::node_rows;
use crate::output::vtk::{write_pvd, write_vtk, VtkKind};

/// Runs the dynamic session `args` asks for: h = `dt`, `steps` frames by default.
pub fn run(
    args: &LiveArgs,
    setup: &LiveSetup,
    spec: &DynamicsSpec,
    (dt, steps): (f64, u32),
    tool_at: &dyn Fn(f64) -> Vec<[f64; 3]>,
) -> anyhow::Result<()> {
    check_flags(args)?;
    if args.target != "host" {
        // Before a board is opened: can the target's fixed point hold S?
        preflight(&setup.model, spec, dt).context("the dynamic model")?;
    }
    println!("model       {}", setup.model.spec().describe());
    println!(
        "dynamics    {}; h = {dt} s, one step per frame",
        spec.describe()
    );
    let frames = args.frames.unwrap_or(steps);
    let header = header(args, setup, spec, dt);
    if args.target == "host" {
        let live = <DynamicLive>::host(&setup.model, &setup.tools, spec, dt)?;
        return match args.serve {
            true => serve(setup, DynamicViewSolver::new(live), args),
            false => headless(args, setup, live, frames, tool_at, header),
        };
    }
    let mut board = open_board(args)?;
    let live = DynamicLive::on_target(
        &setup.model,
        &setup.tools,
        spec,
        dt,
        params(args),
        &mut board.target,
    )?;
    match args.serve {
        true => serve(setup, DynamicViewSolver::new(live), args),
        false => headless(args, setup, live, frames, tool_at, header),
    }
}

/// What the report says about the session before any frame.
fn header(args: &LiveArgs, setup: &LiveSetup, spec: &DynamicsSpec, dt: f64) -> Header {
    let g = setup.model.grid();
    Header {
        grid: [g.nx(), g.ny(), g.nz()],
        model: match setup.model.spec().connection {
            Connection::Axial => "a".into(),
            Connection::AxialShear => "b".into(),
        },
        mvus: args.mvu_count(),
        target: match (&args.port, args.target.as_str()) {
            (Some(_), t) if t != "host" => "port".into(),
            (_, t) => t.into(),
        },
        tolerance: args.tol,
        dynamic: DynamicInfo::new(spec, dt),
        cycles_from_mcycle: args.target == "litex" && args.port.is_none(),
    }
}

/// A tolerance refinement can reach, and no flag whose machinery dynamic frames do not use
/// (refused rather than ignored).
fn check_flags(args: &LiveArgs) -> anyhow::Result<()> {
    if !(args.tol.is_finite() && args.tol > 0.0) {
        bail!(
            "--tol {}: a dynamic frame is refined to this true relative residual; give one              greater than 0 (e.g. 1e-4)",
            args.tol
        );
    }
    if args.cycle_budget != 0 {
        bail!(
            "--cycle-budget applies to quasi-static frames; a dynamic frame is refined to --tol \
             (at most --max-solves target solves of --max-iter iterations)"
        );
    }
    if args.pace.is_some() {
        bail!("--pace applies to quasi-static frames; a dynamic session runs every step");
    }
    Ok(())
}

/// Each frame refined to `--tol`, with `--max-iter` iterations per target solve.
fn params(args: &LiveArgs) -> DynamicParams {
    DynamicParams {
        tol: args.tol,
        max_solves: args.dynamics.max_solves,
        max_iterations: args.max_iter,
        check_reference: true,
        layout: EncodeOptions {
            mvus: args.mvu_count(),
            partition: Partition::Rows,
            use_symmetry: true,
        },
    }
}

/// `--serve`: the page, its WebSocket and the dynamic frames until the process is stopped.
fn serve<P: Port>(
    setup: &LiveSetup,
    mut solver: DynamicViewSolver<'_, P>,
    args: &LiveArgs,
) -> anyhow::Result<()> {
    let mailbox = serve_page(args, setup, &vec![true; setup.model.n()])?;
    interactive::run(setup, &mut solver, &mailbox)
}

/// `--frames-csv` and `--out`, written frame by frame.
struct FrameSink {
    csv: Option<BufWriter<File>>,
    out: Option<PathBuf>,
    pvd: Vec<(f64, String)>,
}

impl FrameSink {
    fn new(args: &LiveArgs) -> anyhow::Result<Self> {
        let csv = open_outputs(args, "frame,t,tool_x,tool_y,tool_z,fx,fy,fz,fx_ref,fy_ref,fz_ref,residual,iterations,cycles,error_vs_converged,bytes_up,bytes_down,max_u,max_v,energy")?;
        Ok(Self {
            csv,
            out: args.out.clone(),
            pvd: Vec::new(),
        })
    }

    fn write(&mut self, setup: &LiveSetup, r: &DynamicFrame) -> anyhow::Result<()> {
        if let Some(dir) = &self.out {
            let name = format!("frame_{:05}.vtu", r.frame);
            let path = dir.join(&name);
            write_vtk(&path, &node_rows(&setup.model, &r.u), VtkKind::Unstructured)
                .with_context(|| path.display().to_string())?;
            self.pvd.push((r.t, name));
        }
        if let Some(f) = self.csv.as_mut() {
            let u = r.tool.first().copied().unwrap_or([0.0; 3]);
            let (fo, fr) = (r.force, r.force_reference);
            writeln!(
                f,
                "{},{},{},{},{},{},{},{},{},{},{},{:e},{},{},{},{},{},{:e},{:e},{:e}",
                r.frame,
                r.t,
                u[0],
                u[1],
                u[2],
                fo[0],
                fo[1],
                fo[2],
                fr[0],
                fr[1],
                fr[2],
                r.residual,
                r.iterations,
                r.cycles.map_or(String::new(), |c| c.to_string()),
                r.error_vs_reference
                    .map_or(String::new(), |e| format!("{e:e}")),
                r.bytes_up,
                r.bytes_down,
                r.max_u,
                r.max_v,
                r.energy
            )?;
        }
        Ok(())
    }

    fn finish(self) -> anyhow::Result<()> {
        if let Some(mut f) = self.csv {
            f.flush()?;
        }
        if let Some(dir) = &self.out {
            let path = dir.join("series.pvd");
            write_pvd(&path, &self.pvd)?;
            println!(
                "wrote       {} (+{} .vtu files)",
                path.display(),
                self.pvd.len()
            );
        }
        Ok(())
    }
}

/// `--headless`: `frames` steps with the tool on its keyframes, then the report.
fn headless<P: Port>(
    args: &LiveArgs,
    setup: &LiveSetup,
    mut live: DynamicLive<'_, P>,
    frames: u32,
    tool_at: &dyn Fn(f64) -> Vec<[f64; 3]>,
    header: Header,
) -> anyhow::Result<()> {
    println!(
        "tool        {} node(s), {frames} frames of {} s; tolerance {:e}, {} MVU(s), on {}",
        setup.tools.len(),
        live.h(),
        args.tol,
        header.mvus,
        header.target
    );
    let mut sink = FrameSink::new(args)?;
    let progress = bar(u64::from(frames), "frames");
    let mut records = Vec::with_capacity(frames as usize);
    for i in 1..=frames {
        let tool = tool_at(f64::from(i) * live.h());
        let mut f = live
            .frame(&tool)
            .with_context(|| format!("dynamic frame {i}"))?;
        sink.write(setup, &f)?;
        f.u = Default::default();
        records.push(f);
        progress.inc(1);
    }
    progress.finish_and_clear();
    sink.finish()?;
    let report = report(header, &records);
    print(&report);
    if let Some(path) = &args.report {
        let f = File::create(path).with_context(|| format!("creating {}", path.display()))?;
        serde_json::to_writer_pretty(BufWriter::new(f), &report)?;
        println!("wrote       {}", path.display());
    }
    Ok(())
}

fn print(report: &DynamicReport) {
    if let (Some(c), Some(r)) = (report.frame_cycles, report.frames_per_s_at_100mhz) {
        println!(
            "frames      {}: cycles p50 {:.0}, p99 {:.0}, max {:.0} → {:.0} frames/s at 100 MHz (worst {:.0})",
            report.frames, c.p50, c.p99, c.max, r.p50, r.worst
        );
        if let Some(h) = report.frame_hart0_cycles {
            println!(
                "hart 0      mcycle over the MVU and SVU phases p50 {:.0}, p99 {:.0}, max {:.0} (real cycles on LiteX; the harts' sum under QEMU)",
                h.p50, h.p99, h.max
            );
        }
        println!(
            "accuracy    error vs the f64 stepper ≤ {:.2e} of the frame's max |u| ({:.2e} of the session's), force ≤ {:.2e}, residual ≤ {:.2e}, iterations p50 {} max {}, ≤ {} solve(s) per frame",
            report.error_vs_converged_max.unwrap_or(0.0),
            report.error_vs_converged_of_peak_max.unwrap_or(0.0),
            report.force_error_max.unwrap_or(0.0),
            report.residual_max,
            report.iterations.p50,
            report.iterations.max,
            report.solves_max
        );
        println!(
            "line        {} B up / {} B down per frame (median; max {} / {}; the first {} / {} with S)",
            report.bytes_up_per_frame,
            report.bytes_down_per_frame,
            report.bytes_up_per_frame_max,
            report.bytes_down_per_frame_max,
            report.first_frame.bytes_up,
            report.first_frame.bytes_down
        );
        for r in &report.link_rates {
            println!("  {:>9} baud: {:.1} frames/s", r.baud, r.frames_per_s);
        }
    } else {
        println!(
            "frames      {} steps by the host's f64 stepper",
            report.frames
        );
    }
    let m = report.motion;
    println!(
        "motion      max |u| {:.4e}; at the last frame max |u| {:.4e}, max |v| {:.4e}, energy {:.4e}",
        m.max_u, m.last_max_u, m.last_max_v, m.last_energy
    );
}
