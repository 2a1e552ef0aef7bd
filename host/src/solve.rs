//! A model solved for the displacements of its three directions, on a target or by the host's
//! f64 reference: `deform solve`'s work, and what the HIL tests drive.
//!
//! The target receives A once (thesis eq. 38: K_d = k_d·A) and solves A·u_d = f_d / k_d for the
//! three directions against the resident matrix, fused into one run by default (every matrix word
//! fetched serves all three). The host chooses the layout first: conjugate symmetry when A is
//! persymmetric, the partition over the target's MVUs, optional Jacobi scaling; and it refuses
//! a matrix the target cannot hold before anything is uploaded or solved.

use std::time::Duration;

use anyhow::{bail, Context};
use clap::Args;
use deform_shared::protocol::PhaseCounters;
use deform_shared::word::VALUE_BITS;
use serde::Serialize;

use crate::board::{Board, BoardChoice, LogOptions};
use crate::encode::{encode_with, EncodeOptions, Encoding, EncodingSummary, Partition};
use crate::link::{LinkFlags, Timeouts};
use crate::metrics::{performance, Counts, Performance};
use crate::model::{Axis, Csr, Model};
use crate::precondition::{self, Preconditioner, Scaled};
use crate::reference::{self, max_abs, max_abs_diff};
use crate::refine::{default_max_iterations, solve_refined, RefineParams};

/// How the matrix is laid out over the target's MVUs (how many: `--mvus`,
/// [`crate::board::BoardFlags`]): shared by `deform solve` and `deform simulate`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Args)]
pub struct LayoutFlags {
    /// How the matrix is split over the MVUs: `rows` gives each MVU a block of whole rows
    /// balanced by nonzero count and rows, which it writes directly (thesis 4.1.2); `overlap`
    /// cuts the nonzeros into exactly equal runs, whose boundary rows two MVUs share and add
    /// (4.1.1).
    #[arg(long, value_enum, default_value_t = Partition::Rows)]
    pub partition: Partition,

    /// Store the whole matrix even when it is persymmetric (K_ij = K_{n−1−i,n−1−j}, e.g. a
    /// uniform grid with a symmetric fixed set). By default only half is stored then
    /// (conjugate symmetry, thesis 2.5 vi), which halves matrix memory and upload.
    #[arg(long)]
    pub no_symmetry: bool,
}

impl LayoutFlags {
    /// The encoder options for `mvus` MVUs (`None`: all) of a target with `harts` harts, or
    /// why they do not fit it.
    pub fn encode_options(&self, harts: u8, mvus: Option<u8>) -> anyhow::Result<EncodeOptions> {
        let harts = harts.max(1);
        let mvus = mvus.unwrap_or(harts);
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

/// The tolerance `deform solve` reaches when no flag or scenario says.
pub const DEFAULT_TOL: f64 = 1e-8;

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
    /// Hart 0's cycles and instructions over the MVU phases, and over the SVU phases, of all
    /// solves (real cycles on the LiteX SoC, hardware MVU phases included).
    pub mvu_phases: PhaseCounters,
    pub svu_phases: PhaseCounters,
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
#[derive(Debug, Clone)]
pub struct SolvePlan {
    /// `None`: the host's f64 reference only.
    pub board: Option<BoardChoice>,
    /// MVUs to use (`None`: every hart the target reports).
    pub mvus: Option<u8>,
    pub tol: f64,
    /// CG iterations per solve: per target solve, or the host reference's cap.
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

fn axis_name(axis: Axis) -> &'static str {
    ["x", "y", "z"][axis.position()]
}

/// A board opened for a solve, with A scaled and encoded for it (checked to fit).
struct TargetRun {
    board: Board,
    scaled: Scaled,
    encoding: Encoding,
}

/// Opens the plan's board and lays A out for its harts; a matrix it cannot hold is refused
/// before any solving or uploading is done.
fn open_target(plan: &SolvePlan, choice: &BoardChoice, a: &Csr) -> anyhow::Result<TargetRun> {
    let scaled = precondition::scale(a, plan.precondition).context("preconditioning A")?;
    let timeouts = plan.link.apply(Timeouts {
        solve: plan.solve_timeout,
        ..Timeouts::default()
    });
    let board = Board::open(choice, timeouts, &plan.logs)?;
    let options = plan
        .layout
        .encode_options(board.target.info().harts, plan.mvus)?;
    let encoding =
        encode_with(&scaled.matrix, &options).context("encoding A as instruction words")?;
    board
        .target
        .check_matrix_fits(&encoding.matrix)
        .context("the encoded matrix does not fit the target; use a smaller grid")?;
    Ok(TargetRun {
        board,
        scaled,
        encoding,
    })
}

/// The f64 reference of every direction, to `tol`: the answer on the host, the yardstick on a
/// target (then to 1e-12).
fn reference_solutions(
    a: &Csr,
    rhs: &[Vec<f64>],
    tol: f64,
    max_iter: usize,
) -> anyhow::Result<Vec<reference::Solution>> {
    let mut out = Vec::new();
    for (d, b) in Axis::ALL.iter().zip(rhs) {
        let sol = reference::solve(a, b, None, tol, max_iter)
            .with_context(|| format!("f64 reference solve, {} direction", axis_name(*d)))?;
        if !sol.converged {
            bail!(
                "the f64 reference CG did not converge in the {} direction (residual {:.3e} \
                 after {} iterations)",
                axis_name(*d),
                sol.relative_residual,
                sol.iterations
            );
        }
        out.push(sol);
    }
    Ok(out)
}

/// Solves all three directions of `model` as `plan` says.
pub fn solve_model(model: &Model, plan: &SolvePlan) -> anyhow::Result<Solved> {
    let a = model.unit_matrix();
    let n = model.n();
    let rhs: Vec<Vec<f64>> = Axis::ALL.iter().map(|&d| model.scaled_rhs(d)).collect();
    let target_run = match &plan.board {
        None => None,
        Some(choice) => Some(open_target(plan, choice, a)?),
    };
    let reference = match &target_run {
        Some(_) => reference_solutions(a, &rhs, 1e-12, 10 * n.max(100))?,
        None => {
            let cap = plan.max_iter.map_or(10 * n.max(100), |m| m as usize);
            reference_solutions(a, &rhs, plan.tol, cap)?
        }
    };
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
    let u = match target_run {
        None => host_directions(model, &reference, &mut stats),
        Some(run) => target_directions(model, plan, run, &rhs, &reference, &mut stats)?,
    };
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

/// The host's answer: the reference itself.
fn host_directions(
    model: &Model,
    reference: &[reference::Solution],
    stats: &mut SolveStats,
) -> [Vec<f64>; 3] {
    let mut u: [Vec<f64>; 3] = Default::default();
    for (d, sol) in Axis::ALL.iter().zip(reference) {
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
    u
}

/// The target's answer, refined to the plan's tolerance, against the reference.
fn target_directions(
    model: &Model,
    plan: &SolvePlan,
    run: TargetRun,
    rhs: &[Vec<f64>],
    reference: &[reference::Solution],
    stats: &mut SolveStats,
) -> anyhow::Result<[Vec<f64>; 3]> {
    let TargetRun {
        mut board,
        scaled,
        encoding: Encoding { matrix, summary },
    } = run;
    let (a, n) = (model.unit_matrix(), model.n());
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
        max_iterations: plan.max_iter.unwrap_or(default_max_iterations(n)),
        fuse: plan.fuse,
    };
    let refs: Vec<&[f64]> = rhs.iter().map(Vec::as_slice).collect();
    let refined = solve_refined(&mut board.target, a, &scaled, &refs, params)
        .context("solving on the target")?;
    let scale = reference.iter().map(|s| max_abs(&s.x)).fold(0.0, f64::max);
    let mut u: [Vec<f64>; 3] = Default::default();
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
        mvu_phases: refined.phases().0,
        svu_phases: refined.phases().1,
    });
    Ok(u)
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

/// The summary a person reads after a solve.
impl std::fmt::Display for SolveStats {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(f, "target      {}", self.target)?;
        writeln!(f, "model       {}", self.model)?;
        writeln!(
            f,
            "size        n = {}, nnz = {}, fixed nodes = {}",
            self.n, self.nnz, self.fixed_nodes
        )?;
        if let (Some(w), Some(t), Some(fb)) = (self.words, self.tiles, self.frac_bits) {
            // A value field of VALUE_BITS two's-complement bits with fb fractional bits is
            // Q(VALUE_BITS − 1 − fb).fb: one bit is the sign.
            writeln!(
                f,
                "encoding    {w} words in {t} tiles, Q{}.{fb} values",
                VALUE_BITS as i32 - 1 - fb as i32
            )?;
        }
        if let Some(e) = &self.engine {
            e.fmt_layout(f)?;
        }
        for d in &self.directions {
            self.fmt_direction(f, d)?;
        }
        if let Some(e) = &self.engine {
            e.fmt_runs(f)?;
        }
        writeln!(f, "max |u|     {:.6e}", self.max_displacement)?;
        if let Some(dev) = self.max_deviation_from_reference {
            writeln!(
                f,
                "max deviation from the f64 reference: {dev:.3e} of max |u|"
            )?;
        }
        Ok(())
    }
}

impl SolveStats {
    /// One direction's line: its iterations, target solves, residual and deviation.
    fn fmt_direction(
        &self,
        f: &mut std::fmt::Formatter<'_>,
        d: &DirectionStats,
    ) -> std::fmt::Result {
        write!(
            f,
            "u{}  (k = {}) iterations {:>5}, ",
            d.axis, d.k, d.iterations
        )?;
        // The host's f64 solve makes no target solves: its count says nothing.
        if self.engine.is_some() {
            write!(f, "solves {}, ", d.solves)?;
        }
        write!(f, "residual {:.2e}", d.relative_residual)?;
        if let Some(dev) = d.deviation_from_reference {
            write!(f, ", deviation from f64 {dev:.2e}")?;
        }
        writeln!(f,)
    }
}

impl EngineStats {
    /// The layout line: MVUs, partition, conjugate symmetry, padding, preconditioner.
    fn fmt_layout(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let l = &self.layout;
        writeln!(
            f,
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
            self.precondition
        )
    }

    /// The target's runs, its phases' counters and the first iteration's figures.
    fn fmt_runs(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "runs        {} target solve(s), {}; {} matrix words fetched ({} if solved one direction at a time); critical path in all {} (measured)",
            self.target_solves,
            if self.fused { "directions fused" } else { "one direction at a time" },
            self.words_fetched,
            self.words_fetched_unfused,
            self.critical_path
        )?;
        writeln!(
            f,
            "phases      MVU {} cycles / {} instructions retired, SVU {} cycles / {} instructions (hart 0's counters, all solves)",
            self.mvu_phases.cycles,
            self.mvu_phases.instructions,
            self.svu_phases.cycles,
            self.svu_phases.instructions
        )?;
        let Some(p) = &self.performance else {
            return Ok(());
        };
        writeln!(
            f,
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
        )
    }
}
