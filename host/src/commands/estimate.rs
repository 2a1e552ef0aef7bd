//! `deform estimate`: the inverse models of thesis ch. 3 on an observation file (see
//! [`crate::inverse`]). Homogeneous k̃ always (both estimators), the parametric α's with
//! `--parametric`, one k̃ per spring with `--springs` (and its per-node map with `--map`).

use std::io::Write;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Context};
use clap::{Args, ValueEnum};

use crate::board::{Board, BoardFlags};
use crate::inverse::homogeneous;
use crate::inverse::parametric::{self, ParametricEstimate};
use crate::inverse::regularise::Regularisation;
use crate::inverse::report::{EstimateReport, Homogeneous, ModelSummary, ObservationSummary};
use crate::inverse::spring_field::{self, SpringFieldEstimate};
use crate::inverse::{Network, Observations, SpdSolver};
use crate::link::DEFAULT_SOLVE_TIMEOUT;
use crate::link::{LinkFlags, Timeouts};
use crate::model::flags::ModelFlags;
use crate::model::Model;
use crate::output::paths::Outputs;
use crate::output::vtk::{write_vtk, VtkKind};
use crate::output::{node_rows_with_stiffness, OutputFormat};
use crate::refine::DEFAULT_MAX_SOLVES;
use crate::scenario::resolve_model;

/// The homogeneous estimator reported as `k`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Estimator {
    /// Fit the predicted displacements A⁻¹f/k̃ to the observed ones (forward solves on the
    /// target); unbiased with noisy displacements.
    OutputError,
    /// The thesis's eq. 44, Σ fᵀA·l̃ / Σ ‖A·l̃‖²; biased towards 0 by noise on displacements.
    EquationError,
}

/// Estimate the tissue's elasticity from observed displacements and loads (thesis ch. 3).
///
/// OBSERVATIONS.csv has the header `set,i,j,k,ux,uy,uz,fx,fy,fz`, one row per node per set
/// (what `deform observe` writes; see README). The model flags give the grid, the spring
/// network and the fixed and prescribed nodes the observations were taken with; loads come from
/// the file and the elasticity is what is estimated, so --k, --load and --pressure are not used.
#[derive(Debug, Clone, Args)]
pub struct EstimateArgs {
    /// The observation file.
    #[arg(value_name = "OBSERVATIONS.csv")]
    pub observations: PathBuf,

    /// A scenario file whose grid, model and boundary conditions to use (flags override it).
    #[arg(long, value_name = "SCENARIO.toml")]
    pub scenario: Option<PathBuf>,

    #[command(flatten)]
    pub model: ModelFlags,

    /// The homogeneous estimate reported as `k`. Both are always computed and printed.
    #[arg(long, value_enum, default_value_t = Estimator::OutputError)]
    pub estimator: Estimator,

    /// Also estimate α0, α1, α2 of k̃ = α0 + α1·ΣΔl + α2·ΣΔl² (thesis 3.2.2).
    #[arg(long)]
    pub parametric: bool,

    /// Also estimate one k̃ per spring (thesis 3.3): a sparse SPD normal system solved on the
    /// target. Needs several load cases (sets with different loads); see README.
    #[arg(long)]
    pub springs: bool,

    /// Regularise the per-spring estimate: `tikhonov:W` (towards the homogeneous value) or
    /// `smooth:W` (neighbouring springs alike), W relative to the data's weight, e.g.
    /// smooth:1e-4. Repeatable. Needed when the estimate is refused as singular (too few load
    /// cases) and with noisy displacements. Default: none.
    #[arg(long, value_name = "KIND:W")]
    pub regularise: Vec<Regularisation>,

    /// Write the per-node stiffness map (mean of each node's spring estimates, point data
    /// `stiffness`; `displacement` is the first set's) as VTK for ParaView. Implies --springs.
    #[arg(long, value_name = "FILE.vtu|FILE.vts")]
    pub map: Option<PathBuf>,

    /// Where the SPD solves run (`host`: the f64 reference CG).
    #[command(flatten)]
    pub board: BoardFlags,

    /// True relative residual each SPD solve must reach (target solves are refined on the host).
    #[arg(long, default_value_t = 1e-10)]
    pub tol: f64,

    /// Target solves allowed per right-hand side (the first plus refinement steps).
    #[arg(long, default_value_t = DEFAULT_MAX_SOLVES, value_parser = clap::value_parser!(u32).range(1..))]
    pub max_solves: u32,

    /// Seconds one target solve may take.
    #[arg(long, default_value_t = DEFAULT_SOLVE_TIMEOUT.as_secs(), value_parser = clap::value_parser!(u64).range(1..))]
    pub timeout: u64,

    #[command(flatten)]
    pub link: LinkFlags,

    /// Print every estimate as one JSON document (the homogeneous one under `k`) instead of
    /// the summary.
    #[arg(long)]
    pub json: bool,
}

/// The homogeneous estimates, and the parametric and spring-field ones where asked for.
pub type Estimates = (
    Homogeneous,
    Option<ParametricEstimate>,
    Option<SpringFieldEstimate>,
);

/// Runs the estimators on `obs` as `args` ask, solving on `solver`.
pub fn estimate_all<P: crate::link::Port>(
    args: &EstimateArgs,
    model: &Model,
    obs: &Observations,
    solver: &mut SpdSolver<'_, P>,
) -> anyhow::Result<Estimates> {
    let net = Network::of(model);
    let equation_error = homogeneous::equation_error(&net, obs)?;
    let output_error = homogeneous::output_error(&net, model, obs, solver)
        .context("output-error estimate (forward solves)")?;
    let parametric = args
        .parametric
        .then(|| parametric::estimate(&net, obs))
        .transpose()?;
    let springs = (args.springs || args.map.is_some())
        .then(|| {
            spring_field::estimate(&net, obs, &args.regularise, solver).with_context(|| {
                format!(
                    "per-spring estimate{}",
                    if solver.is_target() {
                        " on the target (if the normal matrix's band is too wide for the tiler, use --target host or a smaller grid)"
                    } else {
                        ""
                    }
                )
            })
        })
        .transpose()?;
    Ok((
        Homogeneous {
            output_error,
            equation_error,
        },
        parametric,
        springs,
    ))
}

pub fn run(args: &EstimateArgs) -> anyhow::Result<()> {
    check_args(args)?;
    let (_, spec) = resolve_model(args.scenario.as_deref(), &args.model)?;
    let model = Model::build(&spec).context("building the model")?;
    let obs = Observations::read(&args.observations, model.grid())?;
    let (target_name, (homogeneous, parametric, spring_field)) =
        estimate_on_target(args, &model, &obs)?;
    let chosen = match args.estimator {
        Estimator::OutputError => &homogeneous.output_error,
        Estimator::EquationError => &homogeneous.equation_error,
    };
    let report = EstimateReport {
        k: chosen.k,
        k_standard_error: chosen.standard_error,
        estimator: chosen.method,
        observations: ObservationSummary {
            file: args.observations.display().to_string(),
            sets: obs.sets.len(),
            nodes: model.n(),
            free_nodes: Network::of(&model).free_nodes().count(),
        },
        target: target_name,
        model: ModelSummary {
            grid: spec.grid.to_string(),
            connection: spec.connection.to_string(),
            fixed: model.fixed_count(),
            prescribed: model.prescribed_count(),
        },
        parametric,
        spring_field,
        homogeneous,
    };
    if let (Some(map), Some(field)) = (&args.map, &report.spring_field) {
        write_map(map, &model, &obs, &field.node_stiffness)?;
    }
    if args.json {
        // Written rather than println!'d: a closed pipe is an error, not a panic.
        let mut out = std::io::stdout().lock();
        serde_json::to_writer_pretty(&mut out, &report)?;
        writeln!(out)?;
        return Ok(());
    }
    print!("{report}");
    if let Some(map) = &args.map {
        println!("wrote           {}", map.display());
    }
    Ok(())
}

/// The flags checked before anything is read or solved: the map's format, the tolerance, and
/// that no output would overwrite an input.
fn check_args(args: &EstimateArgs) -> anyhow::Result<()> {
    if let Some(map) = &args.map {
        if !matches!(
            OutputFormat::of(map)?,
            OutputFormat::Vtu | OutputFormat::Vts
        ) {
            bail!(
                "--map {}: the map is written as VTK, use a .vtu or .vts file name",
                map.display()
            );
        }
    }
    if !(args.tol.is_finite() && args.tol > 0.0 && args.tol < 1.0) {
        bail!("--tol {} must be a number in (0, 1)", args.tol);
    }
    Outputs::new()
        .input("scenario", args.scenario.as_deref())
        .input("observations", Some(&args.observations))
        .file("--map", args.map.as_deref())
        .check()
}

/// Every estimate, its solves on the board the flags choose (the host's f64 CG without one),
/// and that target's name.
fn estimate_on_target(
    args: &EstimateArgs,
    model: &Model,
    obs: &Observations,
) -> anyhow::Result<(String, Estimates)> {
    let Some(choice) = args.board.choice(None)? else {
        let mut host: SpdSolver<'_, Box<dyn serialport::SerialPort>> =
            SpdSolver::Host { tol: args.tol };
        let estimates = estimate_all(args, model, obs, &mut host)?;
        return Ok(("host (f64 reference CG)".to_string(), estimates));
    };
    let timeouts = args.link.apply(Timeouts {
        solve: Duration::from_secs(args.timeout),
        ..Timeouts::default()
    });
    let mut board = Board::open(&choice, timeouts, &args.board.target.logs.options())?;
    let name = board.describe();
    let mut solver = SpdSolver::Target {
        target: &mut board.target,
        tol: args.tol,
        max_solves: args.max_solves,
    };
    Ok((name, estimate_all(args, model, obs, &mut solver)?))
}

/// The spring-field map: the first observation set's displacements with each node's
/// estimated stiffness, as VTK.
fn write_map(
    map: &std::path::Path,
    model: &Model,
    obs: &Observations,
    node_stiffness: &[f64],
) -> anyhow::Result<()> {
    let kind = match OutputFormat::of(map)? {
        OutputFormat::Vts => VtkKind::Structured,
        _ => VtkKind::Unstructured,
    };
    let rows = node_rows_with_stiffness(model, &obs.sets[0].u, node_stiffness);
    write_vtk(map, &rows, kind)?;
    Ok(())
}
