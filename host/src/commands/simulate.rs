//! `deform simulate`: quasi-static time steps of the model on the target (see
//! [`crate::simulate`]), with per-step CSV, one VTK file per step plus a `.pvd` collection, and
//! a progress bar on a terminal.
//!
//! Like `deform solve`, it takes an optional scenario file with flags overriding it. With a
//! `[simulation]` table the steps, dt, keyframed loads and prescribed displacements and the
//! displacement-dependent model come from the file (--steps, --dt, --alpha override them);
//! without one, the model's loads are ramped linearly.
//!
//! With `--dynamic` (or `[simulation] dynamic = true`) the steps are elastodynamic instead:
//! [`super::simulate_dynamic`] runs them (masses and dampers, [`crate::dynamics`]).

use std::fs::File;
use std::io::{BufWriter, IsTerminal, Write};
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use crate::board::{self, Board, BoardChoice};
use crate::cli_dynamics::DynamicFlags;
use crate::cli_logs::LogFlags;
use crate::cli_model::ModelFlags;
use crate::commands::solve::{resolve_model, LayoutFlags};
use crate::dynamics::DynamicsSpec;
use crate::link::{LinkFlags, Timeouts};
use crate::model::{Model, ModelError, ModelSpec};
use crate::output::node_rows;
use crate::output::series::{SeriesTarget, SeriesWriter};
use crate::scenario::Simulation;
use crate::simulate::{simulate_with, Nonlinear, Schedule, StepParams, StepResult};

/// Quasi-static time series solved step by step on the target with K resident: a scenario's
/// `[simulation]` keyframes, or else the model's loads ramped linearly from 0 to full.
#[derive(Debug, Clone, Args)]
pub struct SimulateArgs {
    /// A scenario file (TOML, see examples/); its `[simulation]` table gives the time steps,
    /// keyframed loads and displacements. Flags given on the command line override it.
    #[arg(value_name = "SCENARIO.toml")]
    pub scenario: Option<PathBuf>,

    #[command(flatten)]
    pub model: ModelFlags,

    /// Time steps. [default: the scenario's, else 10]
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub steps: Option<u32>,

    /// Step length in seconds. [default: the scenario's, else 0.1]
    #[arg(long)]
    pub dt: Option<f64>,

    /// Displacement-dependent springs k̃ = a0 + a1·ΣΔl + a2·ΣΔl² (thesis 3.2.2), as
    /// `a0,a1,a2`. Default: the scenario's `[simulation.nonlinear]`, else the
    /// displacement-independent model.
    #[arg(long, value_name = "A0,A1,A2", value_parser = parse_alpha)]
    pub alpha: Option<[f64; 3]>,

    /// Start every solve from zero instead of the previous step's solution.
    #[arg(long)]
    pub cold: bool,

    /// Warm-start from the previous step's solution uploaded by the host, instead of the
    /// target's own prediction 2u(t−1) − u(t−2) (the default: no vector goes down for it).
    #[arg(long, conflicts_with = "cold")]
    pub no_predict: bool,

    /// Solve x, y and z one after the other instead of fused in one target run per step
    /// (unfused steps warm-start from the uploaded previous solution, never predicted).
    #[arg(long)]
    pub no_fuse: bool,

    /// Target CG tolerance per solve (relative residual; floored at 1e-7). With --dynamic: the
    /// true relative residual of each step's S·v₁ = b, reached by refinement on the host.
    #[arg(long, default_value_t = 1e-7)]
    pub tol: f64,

    /// CG iterations allowed per target solve. Default: 10·n.
    #[arg(long, value_name = "N")]
    pub max_iter: Option<u32>,

    /// Serial device of a real board. Default: boot the firmware in QEMU.
    #[arg(long, value_name = "PATH")]
    pub port: Option<String>,

    /// The simulated board when no --port is given: `qemu`, or `litex` (the `--board litex`
    /// firmware on a LiteX VexRiscv SoC under Verilator; slow, keep it small).
    #[arg(long, value_enum, default_value_t = board::SimulatedBoard::Qemu)]
    pub target: board::SimulatedBoard,

    /// Firmware ELF for QEMU. Default: $DEFORM_FIRMWARE, else the release build.
    #[arg(long, value_name = "ELF")]
    pub firmware: Option<PathBuf>,

    #[command(flatten)]
    pub logs: LogFlags,

    /// Seconds one target solve may take.
    #[arg(long, default_value_t = super::solve::DEFAULT_TIMEOUT_SECONDS, value_parser = clap::value_parser!(u64).range(1..))]
    pub timeout: u64,

    #[command(flatten)]
    pub link: LinkFlags,

    /// Write one row per step to this CSV file: `step,t,iterations,residual,max_u`; with
    /// --dynamic `step,t,iterations,solves,fused_iterations,cycles,residual,max_u,energy,
    /// bytes_sent,bytes_received` (iterations summed over x, y and z; fused iterations of the
    /// target's solves; cycles on their critical path).
    #[arg(long, value_name = "FILE")]
    pub steps_csv: Option<PathBuf>,

    /// Every step's displacements: `FILE.csv` (rows `step,t,i,j,k,ux,uy,uz`), `FILE.pvd`
    /// (a ParaView collection with `FILE_NNNN.vtu` beside it), or a directory (one
    /// `step_NNNN.vtu` per step and `series.pvd`).
    #[arg(long, value_name = "FILE.csv|FILE.pvd|DIR")]
    pub out: Option<PathBuf>,

    /// Also solve every step with the f64 reference and print the deviation.
    #[arg(long)]
    pub check: bool,

    #[command(flatten)]
    pub layout: LayoutFlags,

    #[command(flatten)]
    pub dynamics: DynamicFlags,
}

/// `A0,A1,A2` for `--alpha` (also `deform observe`'s).
pub(crate) fn parse_alpha(s: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>().map_err(|e| format!("{p:?}: {e}")))
        .collect::<Result<_, _>>()?;
    let a: [f64; 3] = v
        .try_into()
        .map_err(|_| "expected three numbers a0,a1,a2".to_string())?;
    if a.iter().all(|x| x.is_finite()) && a[0] > 0.0 {
        Ok(a)
    } else {
        Err("a0 must be positive and all three finite".into())
    }
}

/// A progress bar on stderr (hidden unless it is a terminal); `deform live` uses it too.
pub(crate) fn bar(len: u64, what: &str) -> ProgressBar {
    if !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(len);
    bar.set_style(
        ProgressStyle::with_template("{msg:>10} [{bar:40}] {pos}/{len} {elapsed}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    bar.set_message(what.to_string());
    bar
}

/// Moves `bar` with a matrix upload and clears it when the upload is done.
pub(crate) fn upload_progress(bar: &ProgressBar) -> impl FnMut(crate::link::UploadProgress) + '_ {
    |p| {
        bar.set_length(p.words_total as u64);
        bar.set_position(p.words_sent as u64);
        if p.words_sent == p.words_total {
            bar.finish_and_clear();
        }
    }
}

/// A simulation's inputs once flags, scenario file and defaults are merged.
pub struct ResolvedSimulation {
    /// The static model (a scenario's schedules at their final time).
    pub spec: ModelSpec,
    pub schedule: Schedule,
    pub nonlinear: Option<Nonlinear>,
    /// The scenario's `[simulation]`, whose keyframes drive the steps.
    pub simulation: Option<Simulation>,
    /// Masses and dampers, if the run is dynamic.
    pub dynamics: Option<DynamicsSpec>,
}

impl ResolvedSimulation {
    /// The model at time `t`: the keyframes evaluated at t, or the static model.
    pub fn model_at(&self, t: f64) -> Result<Model, ModelError> {
        match &self.simulation {
            Some(sim) => Model::build(&sim.spec_at(&self.spec, t)),
            None => Model::build(&self.spec),
        }
    }
}

impl SimulateArgs {
    /// Reads the scenario file, if any (as `deform solve` does), and merges flags over it.
    pub fn resolve(&self) -> anyhow::Result<ResolvedSimulation> {
        let (scenario, spec) = resolve_model(self.scenario.as_deref(), &self.model)?;
        let dynamics = self.dynamics.resolve(
            scenario
                .as_ref()
                .and_then(|s| s.simulation.as_ref())
                .is_some_and(|s| s.dynamic),
            scenario.as_ref().and_then(|s| s.dynamics.as_ref()),
        )?;
        let simulation = scenario.and_then(|s| s.simulation);
        let schedule = Schedule {
            steps: self
                .steps
                .or(simulation.as_ref().map(|s| s.steps))
                .unwrap_or(10),
            dt: self.dt.or(simulation.as_ref().map(|s| s.dt)).unwrap_or(0.1),
        };
        if !(schedule.dt.is_finite() && schedule.dt > 0.0) {
            anyhow::bail!(
                "--dt {}: the time step must be finite and greater than 0",
                schedule.dt
            );
        }
        let nonlinear = self
            .alpha
            .or(simulation
                .as_ref()
                .and_then(|s| s.nonlinear.as_ref().map(|n| n.alpha)))
            .map(|alpha| Nonlinear { alpha });
        Ok(ResolvedSimulation {
            spec,
            schedule,
            nonlinear,
            simulation,
            dynamics,
        })
    }
}

pub fn run(args: &SimulateArgs) -> anyhow::Result<()> {
    let resolved = args.resolve()?;
    let model = Model::build(&resolved.spec).context("building the model")?;
    if let Some(dynamics) = &resolved.dynamics {
        // Refused before any board is opened or file created.
        if resolved.nonlinear.is_some() {
            anyhow::bail!(
                "the displacement-dependent springs (--alpha) are not supported with --dynamic yet"
            );
        }
        crate::dynamics::target::preflight(&model, dynamics, resolved.schedule.dt)?;
    }
    let n = model.n();
    let mut series = match &args.out {
        Some(path) => Some(SeriesWriter::create(SeriesTarget::of(path))?),
        None => None,
    };
    // The dynamic branch writes its own per-step CSV, with more columns.
    let mut csv = match args
        .steps_csv
        .as_ref()
        .filter(|_| resolved.dynamics.is_none())
    {
        Some(path) => {
            let mut f = BufWriter::new(
                File::create(path).with_context(|| format!("creating {}", path.display()))?,
            );
            writeln!(f, "step,t,iterations,residual,max_u")?;
            Some(f)
        }
        None => None,
    };
    let choice = match (&args.port, args.target) {
        (Some(port), _) => BoardChoice::Port(port.clone()),
        (None, board::SimulatedBoard::Qemu) => BoardChoice::Qemu {
            firmware: args.firmware.clone(),
            harts: args.layout.qemu_harts(),
        },
        (None, board::SimulatedBoard::Litex) => BoardChoice::Litex {
            firmware: args.firmware.clone(),
        },
    };
    let timeouts = args.link.apply(Timeouts {
        solve: Duration::from_secs(args.timeout),
        ..Timeouts::default()
    });
    let mut board = Board::open(&choice, timeouts, &args.logs.options())?;
    let layout = args.layout.encode_options(board.target.info().harts)?;
    println!("target      {}", board.describe());
    println!("model       {}", model.spec().describe());
    println!(
        "layout      {} MVU(s), partition {}, conjugate symmetry {}",
        layout.mvus,
        layout.partition,
        if layout.use_symmetry {
            "when K is persymmetric"
        } else {
            "off"
        }
    );
    let schedule = resolved.schedule;
    if let Some(dynamics) = &resolved.dynamics {
        return super::simulate_dynamic::run(
            args, &resolved, dynamics, &model, &mut board, layout, series,
        );
    }
    let params = StepParams {
        warm_start: !args.cold,
        predict: !args.no_predict,
        fuse: !args.no_fuse,
        tol: args.tol,
        max_iterations: args
            .max_iter
            .unwrap_or((10 * n).min(u32::MAX as usize) as u32),
        check_reference: args.check,
        layout,
    };
    let nonlinear = resolved.nonlinear;
    let steps_bar = bar(schedule.steps as u64, "steps");
    // Firmware log lines print above the bar, not through it.
    board::lock(board.logs()).set_progress(Some(steps_bar.clone()));
    let upload_bar = bar(0, "upload");
    let mut total_iterations = 0u64;
    let mut saved = 0u64;
    let mut written: anyhow::Result<()> = Ok(());
    let mut on_step = |r: &StepResult| {
        total_iterations += r.iterations as u64;
        let mut line = format!(
            "step {:>4}  t = {:<8.4} iterations {:>5}  residual {:.2e}  max |u| {:.4e}",
            r.step, r.t, r.iterations, r.residual, r.max_u
        );
        if let Some(dev) = r.deviation {
            line += &format!("  deviation {dev:.1e}");
        }
        if let Some(u) = &r.update {
            saved += u.bytes_saved();
            line += &format!(
                "  values-only update {} B (full upload {} B, saved {} B)",
                u.bytes_sent,
                u.full_upload_bytes,
                u.bytes_saved()
            );
        }
        steps_bar.suspend(|| println!("{line}"));
        steps_bar.inc(1);
        let mut write = || -> anyhow::Result<()> {
            if let Some(f) = csv.as_mut() {
                writeln!(
                    f,
                    "{},{},{},{:e},{:e}",
                    r.step, r.t, r.iterations, r.residual, r.max_u
                )?;
            }
            if let Some(series) = series.as_mut() {
                // The node stiffness shown is the model's (a displacement-dependent model's
                // springs change per step; that per-spring field is not written).
                series.write_step(r.step, r.t, &node_rows(&model, &r.u))?;
            }
            Ok(())
        };
        if written.is_ok() {
            written = write();
        }
    };
    let step_model = |t: f64| resolved.model_at(t);
    let results = simulate_with(
        &mut board.target,
        &model,
        schedule,
        resolved
            .simulation
            .is_some()
            .then_some(&step_model as crate::simulate::StepModel),
        nonlinear,
        params,
        upload_progress(&upload_bar),
        &mut on_step,
    )
    .context("simulating on the target")?;
    steps_bar.finish_and_clear();
    written?;
    if let Some(mut f) = csv {
        f.flush()?;
    }
    let cycles: Vec<u64> = results.iter().map(|r| r.cycles).collect();
    println!(
        "{} steps, {} CG iterations in all, {} critical-path cycles (worst step {}) ({})",
        results.len(),
        total_iterations,
        cycles.iter().sum::<u64>(),
        cycles.iter().max().unwrap_or(&0),
        match (args.cold, args.no_fuse || args.no_predict) {
            _ if results.iter().all(|r| r.reports.is_empty()) => {
                "superposed live frames: the prescribed nodes' response columns"
            }
            (true, _) => "cold starts",
            (false, true) => "warm starts from the previous step",
            (false, false) => "fused, started from the target's prediction 2u(t−1) − u(t−2)",
        }
    );
    if nonlinear.is_some() {
        println!("values-only updates saved {saved} bytes on the wire against full uploads");
    }
    if let Some(series) = series {
        println!("wrote       {}", series.finish()?);
    }
    if let Some(path) = &args.steps_csv {
        println!("wrote       {}", path.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(flatten)]
        args: SimulateArgs,
    }

    fn resolve(argv: &[&str]) -> ResolvedSimulation {
        let argv = std::iter::once("deform").chain(argv.iter().copied());
        Cli::try_parse_from(argv).unwrap().args.resolve().unwrap()
    }

    const NEEDLE: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../examples/needle-insertion.toml"
    );

    #[test]
    fn the_scenario_gives_the_schedule_and_flags_override_it() {
        let r = resolve(&[NEEDLE]);
        assert_eq!(
            r.schedule,
            Schedule {
                steps: 75,
                dt: 0.02
            }
        );
        assert!(r.nonlinear.is_none());
        let r = resolve(&[NEEDLE, "--steps", "5", "--dt", "0.1", "--alpha", "1,0,0.5"]);
        assert_eq!(r.schedule, Schedule { steps: 5, dt: 0.1 });
        assert_eq!(
            r.nonlinear,
            Some(Nonlinear {
                alpha: [1.0, 0.0, 0.5]
            })
        );
        let r = resolve(&[]);
        assert_eq!(r.schedule, Schedule { steps: 10, dt: 0.1 });
        assert!(r.simulation.is_none());
    }

    #[test]
    fn each_step_prescribes_the_keyframed_displacement() {
        let r = resolve(&[NEEDLE]);
        let tip = r.spec.grid.index(crate::model::Node::new(5, 5, 9)).unwrap();
        // The ramp 0 → −2 over t = 0 … 1, then held.
        for (t, want) in [
            (0.0, 0.0),
            (0.25, -0.5),
            (0.5, -1.0),
            (1.0, -2.0),
            (1.5, -2.0),
        ] {
            let m = r.model_at(t).unwrap();
            assert_eq!(m.prescribed()[tip], Some([0.0, 0.0, want]), "t = {t}");
            let u = crate::reference::solve(
                m.unit_matrix(),
                &m.scaled_rhs(crate::model::Axis::Z),
                None,
                1e-12,
                10_000,
            )
            .unwrap();
            assert!((u.x[tip] - want).abs() < 1e-9, "t = {t}: {}", u.x[tip]);
            assert_eq!(m.unit_matrix(), r.model_at(0.0).unwrap().unit_matrix());
        }
        // A --displace flag replaces the file's schedule: the tip stays where the flag says.
        let r = resolve(&[NEEDLE, "--displace", "5,5,9:0,0,-1"]);
        let m = r.model_at(0.5).unwrap();
        assert_eq!(m.prescribed()[tip], Some([0.0, 0.0, -1.0]));
    }
}
