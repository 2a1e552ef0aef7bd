//! `deform solve`: build the model, solve K_d·u_d = f_d for the three directions on the chosen
//! target, compare with the f64 reference, print a summary and write the displacements.
//!
//! The target receives A once (thesis eq. 38: K_d = k_d·A) and solves A·u_d = f_d / k_d for the
//! three directions against the resident matrix, fused into one run by default (every matrix word
//! fetched serves all three). The host chooses the layout first: conjugate symmetry when A is
//! persymmetric, the partition over the target's MVUs, optional Jacobi scaling; and it refuses
//! a matrix the target cannot hold before anything is uploaded or solved.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context};
use clap::{Args, ValueEnum};
use deform_shared::word::VALUE_BITS;
use serde::Serialize;

use crate::board::{Board, BoardChoice, DEFAULT_QEMU_HARTS};
use crate::cli_logs::{LogFlags, LogOptions};
use crate::cli_model::ModelFlags;
use crate::encode::{encode_with, EncodeOptions, Encoding, EncodingSummary, Partition};
use crate::link::{LinkFlags, Timeouts, DEFAULT_SOLVE_TIMEOUT};
use crate::metrics::{performance, Counts, Performance};
use crate::model::{Axis, Model, ModelSpec};
use crate::output::{node_rows, write_displacements, OutputFormat};
use crate::precondition::{self, Preconditioner};
use crate::reference::{self, max_abs, max_abs_diff};
use crate::refine::{solve_refined, RefineParams};
use crate::scenario::{Scenario, TargetName};

/// Where CG runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum TargetKind {
    /// Boot the firmware in QEMU (riscv32 `virt`) and drive it over its serial pty.
    Qemu,
    /// The f64 reference CG on this computer (the thesis's "general purpose computer").
    Host,
    /// Load the `litex-vexriscv` firmware into a LiteX SoC with a VexRiscv CPU, simulated cycle
    /// for cycle by Verilator (`cargo xtask setup` and `cargo xtask firmware --board litex`
    /// first; the SoC is built once, ~2 min). One MVU; about 0.8 M cycles per second: keep the
    /// grid small.
    Litex,
}

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

    /// Where CG runs: `qemu` boots the firmware under QEMU, `litex` on a simulated LiteX
    /// VexRiscv SoC, `host` uses the f64 reference solver.
    /// Ignored when --port names a real board. [default: qemu]
    #[arg(long, value_enum)]
    pub target: Option<TargetKind>,

    /// Serial device of a real board running the deform firmware (e.g. /dev/ttyUSB0).
    /// Default: none, use --target.
    #[arg(long, value_name = "PATH")]
    pub port: Option<String>,

    /// Firmware ELF for --target qemu or litex. Default: $DEFORM_FIRMWARE, else the release
    /// build in firmware/target (`cargo xtask firmware` builds it); for litex
    /// $DEFORM_LITEX_FIRMWARE, else the `--board litex` build.
    #[arg(long, value_name = "ELF")]
    pub firmware: Option<PathBuf>,

    /// Stop when the true relative residual ‖f − K·u‖₂/‖f‖₂ of each direction, measured in f64
    /// on the host, is at most this. Below ~1e-7 the host refines the target's fixed-point
    /// answer (see --max-solves). [default: 1e-8]
    #[arg(long, value_parser = parse_tolerance)]
    pub tol: Option<f64>,

    /// CG iterations allowed per target solve. Default: 10·n.
    #[arg(long, value_name = "N")]
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

    #[command(flatten)]
    pub logs: LogFlags,

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

/// How the matrix is laid out over the target's MVUs: shared by `deform solve` and
/// `deform simulate`.
#[derive(Debug, Clone, Default, Args)]
pub struct LayoutFlags {
    /// MVUs (harts) to share the matrix–vector product between, 1 to the number of harts the
    /// target reports. Default: every hart the target reports.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u8).range(1..))]
    pub mvus: Option<u8>,

    /// How the matrix is split over the MVUs: `rows` gives each MVU a block of whole rows
    /// balanced by nonzero count, which it writes directly (thesis 4.1.2); `overlap` cuts the
    /// nonzeros into exactly equal runs, whose boundary rows two MVUs share and add (4.1.1).
    #[arg(long, value_enum, default_value_t = Partition::Rows)]
    pub partition: Partition,

    /// Store the whole matrix even when it is persymmetric (K_ij = K_{n−1−i,n−1−j}, e.g. a
    /// uniform grid with a symmetric fixed set). By default only half is stored then
    /// (conjugate symmetry, thesis 2.5 vi), which halves matrix memory and upload.
    #[arg(long)]
    pub no_symmetry: bool,
}

impl LayoutFlags {
    /// Harts to boot QEMU with: as many as --mvus asks for, else the most a target may have.
    pub fn qemu_harts(&self) -> u8 {
        self.mvus.unwrap_or(DEFAULT_QEMU_HARTS)
    }

    /// The encoder options for a target with `harts` harts, or why the flags do not fit it.
    pub fn encode_options(&self, harts: u8) -> anyhow::Result<EncodeOptions> {
        let harts = harts.max(1);
        let mvus = self.mvus.unwrap_or(harts);
        if mvus > harts {
            bail!(
                "--mvus {mvus} asks for more MVUs than the target has: it reports {harts} hart(s)"
            );
        }
        Ok(EncodeOptions {
            mvus,
            partition: self.partition,
            use_symmetry: !self.no_symmetry,
        })
    }
}

/// The built-in solver defaults (what `--help` states).
pub const DEFAULT_TOL: f64 = 1e-8;
pub const DEFAULT_MAX_SOLVES: u32 = 8;
pub const DEFAULT_TIMEOUT_SECONDS: u64 = DEFAULT_SOLVE_TIMEOUT.as_secs();

/// A solve's inputs once flags, scenario file and defaults are merged.
pub struct ResolvedSolve {
    pub spec: ModelSpec,
    pub plan: SolvePlan,
    pub out: Option<PathBuf>,
    pub scenario: Option<Scenario>,
}

pub fn parse_tolerance(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(t) if t.is_finite() && t > 0.0 && t < 1.0 => Ok(t),
        Ok(_) => Err("the tolerance must be a number in (0, 1)".into()),
        Err(e) => Err(format!("not a number: {e}")),
    }
}

/// Statistics of one direction's solve.
#[derive(Debug, Clone, Serialize)]
pub struct DirectionStats {
    pub axis: &'static str,
    /// The direction's spring elasticity k_d (K_d = k_d·A).
    pub k: f64,
    pub iterations: u32,
    /// Target solves (1 + refinement steps); 0 for the host target or a zero load.
    pub solves: u32,
    /// True ‖f − K·u‖₂/‖f‖₂.
    pub relative_residual: f64,
    /// max |u − u_ref| / max |u_ref| against the f64 reference (target runs only).
    pub deviation_from_reference: Option<f64>,
}

/// How the target ran: layout, features and the measured cost (target runs only).
#[derive(Debug, Clone, Serialize)]
pub struct EngineStats {
    /// The matrix layout: words, tiles, overhead, symmetry, partition, MVUs.
    pub layout: EncodingSummary,
    pub precondition: Preconditioner,
    /// The directions were solved together in fused target runs.
    pub fused: bool,
    /// Target solves in all (a fused solve counts once).
    pub target_solves: usize,
    /// The first target solve's first iteration (all loaded directions): the MVU/SVU
    /// breakdown of one iteration.
    pub performance: Option<Performance>,
    /// Matrix words the MVUs fetched over all solves.
    pub words_fetched: u64,
    /// What the same iterations fetch with every direction solved on its own.
    pub words_fetched_unfused: u64,
    /// The critical path over all solves, measured on the target phase by phase (slowest hart
    /// per parallel phase + hart 0's serial work), not extrapolated from one iteration: cycles
    /// and instructions.
    pub critical_path: Counts,
    /// Hart 0's MVU + SVU `mcycle` and `minstret` over all solves (under QEMU -icount: all
    /// harts' sum).
    pub hart0: Counts,
}

/// Everything a solve reports (the JSON `stats` object).
#[derive(Debug, Clone, Serialize)]
pub struct SolveStats {
    pub target: String,
    pub model: String,
    pub n: usize,
    pub nnz: usize,
    pub fixed_nodes: usize,
    /// Instruction words and tiles of A as sent, and its value format.
    pub words: Option<usize>,
    pub tiles: Option<usize>,
    pub frac_bits: Option<u8>,
    pub tolerance: f64,
    pub directions: Vec<DirectionStats>,
    pub engine: Option<EngineStats>,
    pub max_displacement: f64,
    /// Largest deviation over all directions, relative to the largest reference |u|.
    pub max_deviation_from_reference: Option<f64>,
}

/// A solved model: the displacements and how they were obtained.
pub struct Solved {
    pub u: [Vec<f64>; 3],
    pub reference: [Vec<f64>; 3],
    pub stats: SolveStats,
}

/// Where and how to solve, once the flags are parsed.
pub struct SolvePlan {
    /// `None`: the host's f64 reference only.
    pub board: Option<BoardChoice>,
    pub tol: f64,
    pub max_iter: Option<u32>,
    pub max_solves: u32,
    pub solve_timeout: Duration,
    /// How the target's logs are decoded and shown.
    pub logs: LogOptions,
    /// Link timeouts and retries (`--link-timeout`, `--retransmit-ms`, `--retries`).
    pub link: LinkFlags,
    pub layout: LayoutFlags,
    pub precondition: Preconditioner,
    pub fuse: bool,
}

/// Reads the scenario file at `path`, if any, and merges the model `flags` over it over the
/// defaults: the model half of [`SolveArgs::resolve`], shared with `deform simulate`.
pub fn resolve_model(
    path: Option<&Path>,
    flags: &ModelFlags,
) -> anyhow::Result<(Option<Scenario>, ModelSpec)> {
    let scenario = match path {
        Some(path) => Some(Scenario::load(path, flags.grid)?),
        None => None,
    };
    let spec = flags.spec_over(scenario.as_ref().map(|s| &s.model));
    Ok((scenario, spec))
}

impl SolveArgs {
    /// Reads the scenario file, if any, and merges flags over it over the defaults.
    pub fn resolve(&self) -> anyhow::Result<ResolvedSolve> {
        let (scenario, spec) = resolve_model(self.scenario.as_deref(), &self.model)?;
        let file_solver = scenario
            .as_ref()
            .map(|s| s.solver.clone())
            .unwrap_or_default();
        let target = self
            .target
            .or(file_solver.target.map(|t| match t {
                TargetName::Qemu => TargetKind::Qemu,
                TargetName::Host => TargetKind::Host,
            }))
            .unwrap_or(TargetKind::Qemu);
        let board = match (&self.port, target) {
            (Some(port), _) => Some(BoardChoice::Port(port.clone())),
            (None, TargetKind::Qemu) if self.via_loader => Some(BoardChoice::QemuViaLoader {
                firmware: self.firmware.clone(),
                harts: self.layout.qemu_harts(),
            }),
            (None, TargetKind::Qemu) => Some(BoardChoice::Qemu {
                firmware: self.firmware.clone(),
                harts: self.layout.qemu_harts(),
            }),
            (None, TargetKind::Litex) => Some(BoardChoice::Litex {
                firmware: self.firmware.clone(),
            }),
            (None, TargetKind::Host) => None,
        };
        let plan = SolvePlan {
            board,
            tol: self.tol.or(file_solver.tol).unwrap_or(DEFAULT_TOL),
            max_iter: self.max_iter.or(file_solver.max_iter),
            max_solves: self
                .max_solves
                .or(file_solver.max_solves)
                .unwrap_or(DEFAULT_MAX_SOLVES),
            solve_timeout: Duration::from_secs(
                self.timeout
                    .or(file_solver.timeout)
                    .unwrap_or(DEFAULT_TIMEOUT_SECONDS),
            ),
            layout: self.layout.clone(),
            precondition: self.precondition,
            fuse: !self.no_fuse,
            logs: self.logs.options(),
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
}

fn axis_name(axis: Axis) -> &'static str {
    ["x", "y", "z"][axis.position()]
}

/// Solves all three directions of `model` as `plan` says.
pub fn solve_model(model: &Model, plan: &SolvePlan) -> anyhow::Result<Solved> {
    let a = model.unit_matrix();
    let n = model.n();
    let max_iter = plan
        .max_iter
        .unwrap_or((10 * n).min(u32::MAX as usize) as u32);
    let rhs: Vec<Vec<f64>> = Axis::ALL.iter().map(|&d| model.scaled_rhs(d)).collect();

    // The target first: its harts decide the layout, and a matrix it cannot hold is refused
    // before any solving or uploading is done.
    let mut target_run = match &plan.board {
        None => None,
        Some(choice) => {
            let scaled = precondition::scale(a, plan.precondition).context("preconditioning A")?;
            let timeouts = plan.link.apply(Timeouts {
                solve: plan.solve_timeout,
                ..Timeouts::default()
            });
            let board = Board::open(choice, timeouts, &plan.logs)?;
            let options = plan.layout.encode_options(board.target.info().harts)?;
            let encoding =
                encode_with(&scaled.matrix, &options).context("encoding A as instruction words")?;
            board
                .target
                .check_matrix_fits(&encoding.matrix)
                .context("the encoded matrix does not fit the target; use a smaller grid")?;
            Some((board, scaled, encoding))
        }
    };

    // The f64 reference, always: it is the answer for --target host and the yardstick otherwise.
    let reference_tol = if target_run.is_some() {
        1e-12
    } else {
        plan.tol
    };
    let mut reference: Vec<reference::Solution> = Vec::new();
    for (d, b) in Axis::ALL.iter().zip(&rhs) {
        let sol = reference::solve(a, b, None, reference_tol, 10 * n.max(100))
            .with_context(|| format!("f64 reference solve, {} direction", axis_name(*d)))?;
        if !sol.converged {
            bail!(
                "the f64 reference CG did not converge in the {} direction (residual {:.3e})",
                axis_name(*d),
                sol.relative_residual
            );
        }
        reference.push(sol);
    }

    let mut stats = SolveStats {
        target: "host (f64 reference CG)".into(),
        model: model.spec().describe(),
        n,
        nnz: a.nnz(),
        fixed_nodes: model.fixed_count(),
        words: None,
        tiles: None,
        frac_bits: None,
        tolerance: plan.tol,
        directions: Vec::new(),
        engine: None,
        max_displacement: 0.0,
        max_deviation_from_reference: None,
    };
    let mut u: [Vec<f64>; 3] = Default::default();

    match target_run.take() {
        None => {
            for (d, sol) in Axis::ALL.iter().zip(&reference) {
                u[d.position()] = sol.x.clone();
                stats.directions.push(DirectionStats {
                    axis: axis_name(*d),
                    k: model.direction_scale(*d),
                    iterations: sol.iterations as u32,
                    solves: 0,
                    relative_residual: sol.relative_residual,
                    deviation_from_reference: None,
                });
            }
        }
        Some((mut board, scaled, Encoding { matrix, summary })) => {
            stats.words = Some(matrix.words.len());
            stats.tiles = Some(matrix.tiles.len());
            stats.frac_bits = Some(matrix.frac_bits);
            stats.target = board.describe();
            board
                .target
                .upload_matrix(&matrix)
                .context("uploading A to the target")?;
            let params = RefineParams {
                tol: plan.tol,
                max_solves: plan.max_solves,
                max_iterations: max_iter,
                fuse: plan.fuse,
            };
            let refs: Vec<&[f64]> = rhs.iter().map(Vec::as_slice).collect();
            let refined = solve_refined(&mut board.target, a, &scaled, &refs, params)
                .context("solving on the target")?;
            let scale = reference.iter().map(|s| max_abs(&s.x)).fold(0.0, f64::max);
            for (d, got) in Axis::ALL.iter().zip(&refined.directions) {
                let deviation = max_abs_diff(&got.x, &reference[d.position()].x);
                stats.directions.push(DirectionStats {
                    axis: axis_name(*d),
                    k: model.direction_scale(*d),
                    iterations: got.iterations,
                    solves: got.solves,
                    relative_residual: got.relative_residual,
                    deviation_from_reference: Some(if scale > 0.0 {
                        deviation / scale
                    } else {
                        deviation
                    }),
                });
                u[d.position()] = got.x.clone();
            }
            stats.max_deviation_from_reference = stats
                .directions
                .iter()
                .filter_map(|d| d.deviation_from_reference)
                .reduce(f64::max);
            stats.engine = Some(EngineStats {
                performance: refined
                    .reports
                    .first()
                    .and_then(|r| performance(r, &summary, n, a.nnz())),
                layout: summary,
                precondition: plan.precondition,
                fused: plan.fuse,
                target_solves: refined.reports.len(),
                words_fetched: refined.words_fetched(),
                words_fetched_unfused: refined.words_fetched_unfused(),
                critical_path: refined.critical_path().into(),
                hart0: refined.hart0().into(),
            });
        }
    }
    stats.max_displacement = u.iter().map(|v| max_abs(v)).fold(0.0, f64::max);
    let reference = reference
        .into_iter()
        .map(|s| s.x)
        .collect::<Vec<_>>()
        .try_into()
        .unwrap_or_default();
    Ok(Solved {
        u,
        reference,
        stats,
    })
}

/// max over prescribed nodes and directions of |u − u_prescribed|.
pub fn prescribed_error(model: &Model, u: &[Vec<f64>; 3]) -> f64 {
    model
        .prescribed()
        .iter()
        .enumerate()
        .filter_map(|(p, v)| v.map(|v| (p, v)))
        .flat_map(|(p, v)| (0..3).map(move |d| (u[d][p] - v[d]).abs()))
        .fold(0.0, f64::max)
}

/// Prints the summary a person reads after a solve.
fn print_summary(stats: &SolveStats) {
    println!("target      {}", stats.target);
    println!("model       {}", stats.model);
    println!(
        "size        n = {}, nnz = {}, fixed nodes = {}",
        stats.n, stats.nnz, stats.fixed_nodes
    );
    if let (Some(w), Some(t), Some(f)) = (stats.words, stats.tiles, stats.frac_bits) {
        // A value field of VALUE_BITS two's-complement bits with f fractional bits is
        // Q(VALUE_BITS − 1 − f).f: one bit is the sign.
        println!(
            "encoding    {w} words in {t} tiles, Q{}.{f} values",
            VALUE_BITS as i32 - 1 - f as i32
        );
    }
    if let Some(e) = &stats.engine {
        let l = &e.layout;
        println!(
            "layout      {} MVU(s), partition {}, conjugate symmetry {}, {} empty-row words ({:.3} %), precondition {}",
            l.mvus,
            l.partition,
            match (l.symmetry_used, l.persymmetric) {
                (true, _) => "used (half stored)",
                (false, true) => "available, not used",
                (false, false) => "no (not persymmetric)",
            },
            l.empty_row_words,
            100.0 * l.overhead(),
            e.precondition
        );
    }
    for d in &stats.directions {
        print!(
            "u{}  (k = {}) iterations {:>5}, solves {}, residual {:.2e}",
            d.axis, d.k, d.iterations, d.solves, d.relative_residual
        );
        if let Some(dev) = d.deviation_from_reference {
            print!(", deviation from f64 {dev:.2e}");
        }
        println!();
    }
    if let Some(e) = &stats.engine {
        println!(
            "runs        {} target solve(s), {}; {} matrix words fetched ({} if solved one direction at a time); critical path in all {} (measured)",
            e.target_solves,
            if e.fused { "directions fused" } else { "one direction at a time" },
            e.words_fetched,
            e.words_fetched_unfused,
            e.critical_path
        );
        if let Some(p) = &e.performance {
            println!(
                "1st iter.   {} MVU(s) × {} direction(s): {:.2} MVU instructions per word, {:.2} per multiply-accumulate; \
                 {}; {:.1} MFLOPS at 100 MHz by eq. 56 (m = {:.2}, n = {})",
                p.mvus,
                p.directions,
                p.mvu_instructions_per_word,
                p.mvu_instructions_per_product,
                p.critical_path_text(),
                p.mflops,
                p.m,
                p.n
            );
        }
    }
    println!("max |u|     {:.6e}", stats.max_displacement);
    if let Some(dev) = stats.max_deviation_from_reference {
        println!("max deviation from the f64 reference: {dev:.3e} of max |u|");
    }
}

pub fn run(args: &SolveArgs) -> anyhow::Result<()> {
    let resolved = args.resolve()?;
    if let Some(out) = &resolved.out {
        OutputFormat::of(out)?;
    }
    let model = Model::build(&resolved.spec).context("building the model")?;
    let solved = solve_model(&model, &resolved.plan)?;
    print_summary(&solved.stats);
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
