//! `deform bench`: the thesis's performance figures (Fig. 5-2, 5-3, 2-9), a real-time budget
//! and the host baseline, measured and written as JSON, CSV, SVG and PNG (see
//! [`crate::bench`]).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::{Args, ValueEnum};

use crate::bench::board::{BenchBoard, BenchBoardChoice};
use crate::bench::convergence::{self, ConvergenceConfig};
use crate::bench::host_baseline::{self, HostBaselineConfig};
use crate::bench::realtime::{self, RealtimeConfig};
use crate::bench::report::{write_files, BenchReport};
use crate::bench::sweep::{self, SweepConfig};
use crate::bench::{plots, BenchModel};
use crate::board::SimulatedBoard;
use crate::encode::Partition;

/// The parts of the bench.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Part {
    /// Cycles per iteration, MFLOPS, instructions per nonzero, wire bytes against n and MVUs
    /// (thesis Fig. 5-2, 5-3). Target.
    Sweep,
    /// ∞-norm error against iterations on the thesis cube, fixed point and f64 (Fig. 2-9).
    /// Target and host.
    Convergence,
    /// Cycles per time step of a simulate scenario against 1 kHz and 60 Hz. Target.
    Realtime,
    /// The f64 reference CG's wall time per iteration up to 64³ nodes. Host only.
    Host,
}

/// Measure the target (QEMU with exact instruction counts, or a board) and the host against the
/// thesis's figures; write bench.json, CSV tables and SVG/PNG plots to --out.
#[derive(Debug, Clone, Args)]
pub struct BenchArgs {
    /// A small run for CI (about a minute): few sizes, short solves. Checks that everything
    /// works, not the figures to quote.
    #[arg(long)]
    pub quick: bool,

    /// Directory for bench.json, the CSV tables and the plots (created if missing).
    #[arg(long, value_name = "DIR", default_value = "bench-out")]
    pub out: PathBuf,

    /// Run only these parts (comma-separated). [default: all]
    #[arg(long, value_enum, value_delimiter = ',', value_name = "PART")]
    pub only: Vec<Part>,

    /// Shorthand for `--only host`: the host baseline alone, no target needed.
    #[arg(long, conflicts_with = "only")]
    pub host_baseline: bool,

    /// Models to measure (comma-separated). [default: a,b]
    #[arg(long, value_enum, value_delimiter = ',', value_name = "MODEL")]
    pub models: Vec<BenchModel>,

    /// Cube edges of the sweep, n = edge³ (comma-separated).
    /// [default: 5,6,8,10,12,14,16,20,24; --quick: 4,6,8]
    #[arg(long, value_delimiter = ',', value_name = "EDGE", value_parser = clap::value_parser!(u16).range(2..=64))]
    pub edges: Vec<u16>,

    /// MVU counts of the sweep (comma-separated); QEMU gets one hart per MVU. Counts above what
    /// the firmware puts to work are listed as skipped. [default: 1,2,4,8]
    #[arg(long, value_delimiter = ',', value_name = "N", value_parser = clap::value_parser!(u8).range(1..=8))]
    pub mvus: Vec<u8>,

    /// Cube edges of the host baseline (comma-separated).
    /// [default: 8,12,16,24,32,48,64; --quick: 4,6,8]
    #[arg(long, value_delimiter = ',', value_name = "EDGE", value_parser = clap::value_parser!(u16).range(2..=128))]
    pub host_edges: Vec<u16>,

    /// Target CG tolerance of each solve in the real-time scenario (relative residual, floored
    /// at 1e-7 as in `deform simulate`); a looser one trades accuracy for step rate.
    #[arg(long, default_value_t = 1e-7, value_name = "TOL", value_parser = crate::commands::solve::parse_tolerance)]
    pub realtime_tol: f64,

    /// Measure nothing: redraw the plots (and rewrite the CSV tables) from the bench.json
    /// already in --out.
    #[arg(long, conflicts_with_all = ["only", "host_baseline", "quick"])]
    pub replot: bool,

    /// How the sweep shares the rows out over the MVUs: `rows` (thesis 4.1.2) or `overlap`
    /// (4.1.1).
    #[arg(long, value_enum, default_value_t = Partition::Rows)]
    pub partition: Partition,

    /// Serial device of a real board running the firmware. Default: QEMU.
    #[arg(long, value_name = "PATH")]
    pub port: Option<String>,

    /// The simulated board when no --port is given: `qemu` (exact instruction counts), or
    /// `litex` (real cycles of a VexRiscv under Verilator, one MVU; use small --edges and
    /// `--mvus 1`).
    #[arg(long, value_enum, default_value_t = SimulatedBoard::Qemu)]
    pub target: SimulatedBoard,

    /// Firmware ELF for QEMU. Default: $DEFORM_FIRMWARE, else the release build.
    #[arg(long, value_name = "ELF")]
    pub firmware: Option<PathBuf>,

    /// Seconds one target solve may take.
    #[arg(long, default_value_t = 600, value_parser = clap::value_parser!(u64).range(1..))]
    pub timeout: u64,
}

impl BenchArgs {
    fn parts(&self) -> Vec<Part> {
        if self.host_baseline {
            vec![Part::Host]
        } else if self.only.is_empty() {
            vec![Part::Sweep, Part::Convergence, Part::Realtime, Part::Host]
        } else {
            self.only.clone()
        }
    }

    fn models(&self) -> Vec<BenchModel> {
        if self.models.is_empty() {
            BenchModel::BOTH.to_vec()
        } else {
            self.models.clone()
        }
    }

    fn choice(&self) -> BenchBoardChoice {
        match (&self.port, self.target) {
            (Some(port), _) => BenchBoardChoice::Port(port.clone()),
            (None, SimulatedBoard::Qemu) => BenchBoardChoice::Qemu {
                firmware: self.firmware.clone(),
            },
            (None, SimulatedBoard::Litex) => BenchBoardChoice::Litex {
                firmware: self.firmware.clone(),
            },
        }
    }

    pub fn sweep_config(&self) -> SweepConfig {
        let default_edges: &[u16] = if self.quick {
            &[4, 6, 8]
        } else {
            &[5, 6, 8, 10, 12, 14, 16, 20, 24]
        };
        let edges = if self.edges.is_empty() {
            default_edges
        } else {
            &self.edges
        };
        SweepConfig {
            edges: edges.iter().map(|&e| e as usize).collect(),
            models: self.models(),
            mvus: if self.mvus.is_empty() {
                if self.quick {
                    vec![1, 2]
                } else {
                    vec![1, 2, 4, 8]
                }
            } else {
                self.mvus.clone()
            },
            partition: self.partition,
            iterations: 3,
            solve_timeout: Duration::from_secs(self.timeout),
        }
    }

    pub fn convergence_config(&self) -> ConvergenceConfig {
        ConvergenceConfig {
            edge: if self.quick { 5 } else { 10 },
            models: self.models(),
            stride: if self.quick { 3 } else { 1 },
            tol: 1e-12,
            max_steps: 6,
        }
    }

    pub fn realtime_config(&self) -> RealtimeConfig {
        RealtimeConfig {
            edges: if self.quick { vec![5] } else { vec![8, 10] },
            models: self.models(),
            mvus: if self.quick { vec![1] } else { vec![1, 8] },
            steps: if self.quick { 3 } else { 10 },
            tol: self.realtime_tol,
            solve_timeout: Duration::from_secs(self.timeout),
        }
    }

    pub fn host_config(&self) -> HostBaselineConfig {
        let default_edges: &[u16] = if self.quick {
            &[4, 6, 8]
        } else {
            &[8, 12, 16, 24, 32, 48, 64]
        };
        let edges = if self.host_edges.is_empty() {
            default_edges
        } else {
            &self.host_edges
        };
        HostBaselineConfig {
            edges: edges.iter().map(|&e| e as usize).collect(),
            models: self.models(),
            target_time: Duration::from_millis(if self.quick { 20 } else { 300 }),
        }
    }
}

/// Writes the files and plots of `report` into `dir` and lists them.
fn write_all(report: &BenchReport, dir: &std::path::Path) -> anyhow::Result<()> {
    let mut written = write_files(report, dir)?;
    written.extend(plots::draw_all(report, dir)?);
    for path in &written {
        println!("wrote  {}", path.display());
    }
    Ok(())
}

pub fn run(args: &BenchArgs) -> anyhow::Result<BenchReport> {
    if args.replot {
        let path = args.out.join("bench.json");
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("reading {} (run `deform bench` first)", path.display()))?;
        let report: BenchReport = serde_json::from_str(&text)
            .with_context(|| format!("{} is not a bench report", path.display()))?;
        write_all(&report, &args.out)?;
        return Ok(report);
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let parts = args.parts();
    let choice = args.choice();
    let mut report = BenchReport::new(args.quick);
    let timeouts = crate::bench::board::timeouts(Duration::from_secs(args.timeout));

    if parts.contains(&Part::Sweep) {
        let result = sweep::run(&args.sweep_config(), &choice).context("the sweep")?;
        report.sweep = Some(result);
    }
    if parts.contains(&Part::Convergence) {
        let config = args.convergence_config();
        let mut board = BenchBoard::open(&choice, 1, timeouts)?;
        report.target = Some(format!("{:?}", board.target.info()));
        let mut series = Vec::new();
        for &model in &config.models {
            for s in [
                convergence::f64_series(model, &config)?,
                convergence::target_series(&mut board.target, model, &config)
                    .with_context(|| format!("convergence of {model} on the target"))?,
            ] {
                println!(
                    "error  {} {}³ {}: {:.3e} → {:.3e} in {} iterations, {} solve(s), residual {:.1e}",
                    model,
                    s.edge,
                    s.arithmetic.label(),
                    s.points.first().map_or(f64::NAN, |p| p.1),
                    s.final_error(),
                    s.total_iterations(),
                    s.refinement_starts.len(),
                    s.final_relative_residual
                );
                series.push(s);
            }
        }
        report.convergence = Some(series);
    }
    if parts.contains(&Part::Realtime) {
        report.realtime =
            Some(realtime::run(&args.realtime_config(), &choice).context("the real-time budget")?);
    }
    if parts.contains(&Part::Host) {
        report.host_baseline = Some(host_baseline::run(&args.host_config())?);
    }

    write_all(&report, &args.out)?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(flatten)]
        args: BenchArgs,
    }

    fn parse(argv: &[&str]) -> Result<BenchArgs, clap::Error> {
        Cli::try_parse_from(std::iter::once("deform").chain(argv.iter().copied())).map(|c| c.args)
    }

    #[test]
    fn defaults_cover_the_thesis_range_and_quick_shrinks_it() {
        let full = parse(&[]).unwrap();
        assert_eq!(
            full.parts(),
            [Part::Sweep, Part::Convergence, Part::Realtime, Part::Host]
        );
        let sweep = full.sweep_config();
        assert_eq!(sweep.mvus, [1, 2, 4, 8]);
        assert_eq!(sweep.models, BenchModel::BOTH);
        // n from 125 to beyond 4096.
        assert_eq!(sweep.edges.first(), Some(&5));
        assert!(sweep.edges.iter().any(|e| e.pow(3) > 4096));
        assert_eq!(full.convergence_config().edge, 10);
        assert_eq!(full.realtime_config().edges, [8, 10]);
        assert_eq!(full.host_config().edges.last(), Some(&64));

        let quick = parse(&["--quick"]).unwrap();
        assert!(quick.sweep_config().edges.iter().all(|&e| e <= 8));
        assert!(quick.host_config().edges.iter().all(|&e| e <= 8));
        assert!(quick.convergence_config().edge < 10);
    }

    #[test]
    fn flags_pick_parts_models_and_sizes() {
        let args = parse(&["--host-baseline", "--models", "b", "--host-edges", "4,6"]).unwrap();
        assert_eq!(args.parts(), [Part::Host]);
        assert_eq!(args.host_config().models, [BenchModel::B]);
        assert_eq!(args.host_config().edges, [4, 6]);
        let args = parse(&[
            "--only",
            "sweep,convergence",
            "--edges",
            "4,5",
            "--mvus",
            "1,2",
        ])
        .unwrap();
        assert_eq!(args.parts(), [Part::Sweep, Part::Convergence]);
        assert_eq!(args.sweep_config().edges, [4, 5]);
        assert_eq!(args.sweep_config().mvus, [1, 2]);
        for bad in [
            &["--mvus", "0"][..],
            &["--mvus", "9"],
            &["--edges", "1"],
            &["--only", "nothing"],
            &["--models", "c"],
            &["--host-baseline", "--only", "sweep"],
            &["--timeout", "0"],
            &["--realtime-tol", "0"],
        ] {
            assert!(parse(bad).is_err(), "{bad:?}");
        }
    }
}
