//! `deform solve`: build the model, solve it on the chosen target ([`crate::solve`]), compare
//! with the f64 reference, print a summary and write the displacements.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Context};
use clap::Args;

use crate::board::{BoardChoice, BoardFlags};
use crate::link::{LinkFlags, DEFAULT_SOLVE_TIMEOUT};
use crate::model::flags::ModelFlags;
use crate::model::{Model, ModelSpec};
use crate::output::paths::Outputs;
use crate::output::{node_rows, write_displacements, OutputFormat};
use crate::precondition::Preconditioner;
use crate::refine::{parse_tolerance, DEFAULT_MAX_SOLVES};
use crate::scenario::resolve_model;
use crate::scenario::Scenario;
use crate::solve::{prescribed_error, solve_model, LayoutFlags, SolvePlan, DEFAULT_TOL};

/// Solve the tissue model for the displacements u_x, u_y, u_z of every node.
#[derive(Debug, Clone, Args)]
pub struct SolveArgs {
    /// A scenario file (TOML: grid, model, elasticity, boundary conditions, loads, solver,
    /// output; see examples/). Flags given on the command line override it. Default: none, the
    /// flags and their defaults (the thesis 2.6 example).
    #[arg(value_name = "SCENARIO.toml")]
    pub scenario: Option<PathBuf>,

    #[command(flatten)]
    pub model: ModelFlags,

    #[command(flatten)]
    pub board: BoardFlags,

    /// Stop when the true relative residual ‖f − K·u‖₂/‖f‖₂ of each direction, measured in f64
    /// on the host, is at most this. Below ~1e-7 the host refines the target's fixed-point
    /// answer (see --max-solves). [default: 1e-8]
    #[arg(long, value_parser = parse_tolerance, allow_hyphen_values = true)]
    pub tol: Option<f64>,

    /// CG iterations allowed per target solve (on the host: the f64 CG's). Default: 10·n.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..))]
    pub max_iter: Option<u32>,

    /// Target solves allowed per direction: the first, plus refinement steps on the host's f64
    /// residual. [default: 8]
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub max_solves: Option<u32>,

    /// Solve the x, y and z directions one after the other instead of fused into one target
    /// run (for comparison: the fused run fetches each matrix word once for all three).
    #[arg(long)]
    pub no_fuse: bool,

    /// Seconds one target solve may take before the host gives up. [default: 300]
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub timeout: Option<u64>,

    #[command(flatten)]
    pub link: LinkFlags,

    /// Boot QEMU with the serial loader and flash the firmware through it (as `deform flash`
    /// does) instead of booting the firmware directly. Only with --target qemu.
    #[arg(long, conflicts_with = "port")]
    pub via_loader: bool,

    /// Write the displacements: FILE.csv gets `i,j,k,ux,uy,uz` per node, FILE.json the same
    /// plus the solver statistics. Default: no file, summary only.
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,

    /// Precondition CG: `jacobi` sends D^-1/2·K·D^-1/2 (D = diag K) and scales the vectors on
    /// the host, which cuts iterations for stiff inclusions in soft tissue; --tol still means
    /// the residual of the original system.
    #[arg(long, value_enum, default_value_t = Preconditioner::None)]
    pub precondition: Preconditioner,

    #[command(flatten)]
    pub layout: LayoutFlags,
}

/// Seconds one target solve may take when no flag or scenario says.
pub const DEFAULT_TIMEOUT_SECONDS: u64 = DEFAULT_SOLVE_TIMEOUT.as_secs();

/// A solve's inputs once flags, scenario file and defaults are merged.
pub struct ResolvedSolve {
    pub spec: ModelSpec,
    pub plan: SolvePlan,
    pub out: Option<PathBuf>,
    pub scenario: Option<Scenario>,
}

impl SolveArgs {
    /// Reads the scenario file, if any, and merges flags over it over the defaults.
    pub fn resolve(&self) -> anyhow::Result<ResolvedSolve> {
        let (scenario, spec) = resolve_model(self.scenario.as_deref(), &self.model)?;
        let file = scenario
            .as_ref()
            .map(|s| s.solver.clone())
            .unwrap_or_default();
        let mut board = self.board.choice(file.target)?;
        if self.via_loader {
            board = match board {
                Some(BoardChoice::Qemu { firmware, harts }) => {
                    Some(BoardChoice::QemuViaLoader { firmware, harts })
                }
                _ => bail!("--via-loader flashes QEMU through its loader: only with --target qemu"),
            };
        }
        if board.is_none() {
            self.refuse_target_flags_on_host()?;
        }
        let plan = SolvePlan {
            board,
            mvus: self.board.mvus,
            tol: self.tol.or(file.tol).unwrap_or(DEFAULT_TOL),
            max_iter: self.max_iter.or(file.max_iter),
            max_solves: self
                .max_solves
                .or(file.max_solves)
                .unwrap_or(DEFAULT_MAX_SOLVES),
            solve_timeout: Duration::from_secs(
                self.timeout
                    .or(file.timeout)
                    .unwrap_or(DEFAULT_TIMEOUT_SECONDS),
            ),
            layout: self.layout.clone(),
            precondition: self.precondition,
            fuse: !self.no_fuse,
            logs: self.board.target.logs.options(),
            link: self.link,
        };
        let out = self
            .out
            .clone()
            .or_else(|| scenario.as_ref().and_then(|s| s.out.clone()));
        Ok(ResolvedSolve {
            spec,
            plan,
            out,
            scenario,
        })
    }

    /// `--target host` solves by the f64 reference: a flag about target solves is refused
    /// rather than ignored.
    fn refuse_target_flags_on_host(&self) -> anyhow::Result<()> {
        let given = [
            ("--max-solves", self.max_solves.is_some()),
            ("--no-fuse", self.no_fuse),
            ("--timeout", self.timeout.is_some()),
            ("--precondition", self.precondition != Preconditioner::None),
            (
                "--partition/--no-symmetry",
                self.layout != LayoutFlags::default(),
            ),
            (
                "--link-timeout/--retransmit-ms/--retries",
                self.link != LinkFlags::default(),
            ),
        ];
        let given: Vec<&str> = given.iter().filter(|(_, g)| *g).map(|(f, _)| *f).collect();
        if !given.is_empty() {
            let verb = if given.len() == 1 { "applies" } else { "apply" };
            bail!(
                "{} {verb} to target solves; --target host solves by the f64 reference CG \
                 (--tol and --max-iter apply to it)",
                given.join(", ")
            );
        }
        Ok(())
    }
}

pub fn run(args: &SolveArgs) -> anyhow::Result<()> {
    let resolved = args.resolve()?;
    if let Some(out) = &resolved.out {
        OutputFormat::of(out)?;
    }
    Outputs::new()
        .input("scenario", args.scenario.as_deref())
        .file("--out", resolved.out.as_deref())
        .check()?;
    let model = Model::build(&resolved.spec).context("building the model")?;
    let solved = solve_model(&model, &resolved.plan)?;
    print!("{}", solved.stats);
    if model.prescribed_count() > 0 {
        let worst = prescribed_error(&model, &solved.u);
        println!(
            "prescribed  {} node(s), max |u − u_prescribed| = {worst:.3e}",
            model.prescribed_count()
        );
    }
    if let Some(out) = &resolved.out {
        write_displacements(out, &node_rows(&model, &solved.u), &solved.stats)?;
        println!("wrote       {}", out.display());
    }
    Ok(())
}
