//! `deform simulate`: a time series of the model on the target ([`crate::simulate`]:
//! quasi-static steps, or elastodynamic ones with `--dynamic`, [`crate::dynamics`]), with
//! per-step CSV, one VTK file per step plus a `.pvd` collection, and a progress bar on a
//! terminal. Like `deform solve`, it takes an optional scenario file with flags over it.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{anyhow, Context};
use clap::Args;
use deform_shared::qformat::FIXED_POINT_FLOOR;

use crate::board::{Board, BoardFlags};
use crate::dynamics::flags::DynamicFlags;
use crate::dynamics::target::{DynamicModel, DynamicParams};
use crate::encode::EncodeOptions;
use crate::link::{LinkFlags, Timeouts, DEFAULT_SOLVE_TIMEOUT};
use crate::model::flags::ModelFlags;
use crate::model::Model;
use crate::output::paths::Outputs;
use crate::refine::{default_max_iterations, parse_tolerance, DEFAULT_MAX_SOLVES};
use crate::simulate::plan::{parse_alpha, Overrides, SeriesPlan};
use crate::simulate::run::{self, Files};
use crate::simulate::sink::Totals;
use crate::simulate::StepParams;
use crate::solve::LayoutFlags;

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

    /// Target CG tolerance per solve (relative residual, in (0, 1); floored at 1e-7, and a
    /// step that ends above it is reported). With --dynamic: the true relative residual of
    /// each step's S·v₁ = b, reached by refinement on the host.
    #[arg(long, default_value_t = FIXED_POINT_FLOOR, value_parser = parse_tolerance)]
    pub tol: f64,

    /// CG iterations allowed per target solve. Default: 10·n.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..))]
    pub max_iter: Option<u32>,

    /// The board (`--target host` has none: a series runs on a target).
    #[command(flatten)]
    pub board: BoardFlags,

    /// Seconds one target solve may take.
    #[arg(long, default_value_t = DEFAULT_SOLVE_TIMEOUT.as_secs(), value_parser = clap::value_parser!(u64).range(1..))]
    pub timeout: u64,

    #[command(flatten)]
    pub link: LinkFlags,

    /// Write one row per step to this CSV file: `step,t,iterations,residual,max_u,cycles`; with
    /// --dynamic `step,t,iterations,solves,fused_iterations,cycles,residual,max_u,energy,
    /// bytes_sent,bytes_received` (iterations summed over x, y and z; fused iterations of the
    /// target's solves; cycles on their critical path; bytes each frame's first copy, so
    /// without the retransmissions of a loaded host or a noisy line).
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

impl SimulateArgs {
    /// Where the steps go.
    fn files(&self) -> Files<'_> {
        Files {
            steps_csv: self.steps_csv.as_deref(),
            out: self.out.as_deref(),
        }
    }

    /// CG iterations per target solve for an n-node model.
    fn max_iterations(&self, n: usize) -> u32 {
        self.max_iter.unwrap_or(default_max_iterations(n))
    }

    /// Reads the scenario file, if any (as `deform solve` does), and merges flags over it.
    pub fn resolve(&self) -> anyhow::Result<SeriesPlan> {
        let overrides = Overrides {
            model: self.model.clone(),
            steps: self.steps,
            dt: self.dt,
            alpha: self.alpha,
            dynamics: self.dynamics.clone(),
        };
        SeriesPlan::load(self.scenario.as_deref(), &overrides)
    }
}

pub fn run(args: &SimulateArgs) -> anyhow::Result<()> {
    crate::interrupt::install();
    let plan = args.resolve()?;
    let model = Model::build(&plan.spec).context("building the model")?;
    // Checked before any board is opened or file created.
    let built = match &plan.dynamics {
        Some(spec) => Some(DynamicModel::for_target(&model, spec, plan.schedule.dt)?),
        None => None,
    };
    Outputs::new()
        .input("scenario", args.scenario.as_deref())
        .file("--steps-csv", args.steps_csv.as_deref())
        .directory("--out", args.out.as_deref())
        .check()?;
    let choice = args.board.choice(None)?.ok_or_else(|| {
        anyhow!("--target host: a series runs on a target (qemu, litex or --port)")
    })?;
    let timeouts = args.link.apply(Timeouts {
        solve: Duration::from_secs(args.timeout),
        ..Timeouts::default()
    });
    let mut board = Board::open(&choice, timeouts, &args.board.target.logs.options())?;
    let layout = args
        .layout
        .encode_options(board.target.info().harts, args.board.mvus)?;
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
    let totals = match built {
        Some(built) => dynamic(args, &plan, built, &model, &mut board, layout)?,
        None => quasi_static(args, &plan, &model, &mut board, layout)?,
    };
    if crate::interrupt::requested() {
        anyhow::bail!(
            "interrupted after {} step(s); the files hold the steps so far",
            totals.steps
        );
    }
    Ok(())
}

/// The quasi-static steps; the closing lines.
fn quasi_static(
    args: &SimulateArgs,
    plan: &SeriesPlan,
    model: &Model,
    board: &mut Board,
    layout: EncodeOptions,
) -> anyhow::Result<Totals> {
    let params = StepParams {
        warm_start: !args.cold,
        predict: !args.no_predict,
        fuse: !args.no_fuse,
        tol: args.tol,
        max_iterations: args.max_iterations(model.n()),
        check_reference: args.check,
        layout,
    };
    let (totals, wrote) = run::quasi_static(board, plan, model, params, args.files())?;
    print!(
        "{}",
        totals.quasi_static_lines(&params, plan.nonlinear.is_some())
    );
    if let Some(line) = totals.missed_line(args.tol) {
        eprintln!("{line}");
    }
    for line in wrote {
        println!("wrote       {line}");
    }
    Ok(totals)
}

/// The dynamic steps; the closing lines.
fn dynamic(
    args: &SimulateArgs,
    plan: &SeriesPlan,
    built: DynamicModel,
    model: &Model,
    board: &mut Board,
    layout: EncodeOptions,
) -> anyhow::Result<Totals> {
    let spec = plan.dynamics.as_ref().expect("a dynamic plan");
    println!(
        "dynamics    {}, h = {} s",
        spec.describe(),
        plan.schedule.dt
    );
    let params = DynamicParams {
        tol: args.tol,
        max_solves: args.dynamics.max_solves.unwrap_or(DEFAULT_MAX_SOLVES),
        max_iterations: args.max_iterations(model.n()),
        check_reference: args.check,
        layout,
    };
    let (totals, wrote) = run::dynamic(board, plan, built, model, params, args.files())?;
    print!("{}", totals.dynamic_lines());
    for line in wrote {
        println!("wrote       {line}");
    }
    Ok(totals)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simulate::{Nonlinear, Schedule};
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(flatten)]
        args: SimulateArgs,
    }

    fn resolve(argv: &[&str]) -> SeriesPlan {
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
