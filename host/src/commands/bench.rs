//! `deform bench`: the thesis's performance figures (Fig. 5-2, 5-3, 2-9), a real-time budget
//! and the host baseline, measured and written as JSON, CSV, SVG and PNG (see
//! [`crate::bench`]).

use std::path::PathBuf;
use std::time::Duration;

use clap::Args;

use crate::bench::plan::{read_report, run as measure, write_all, Choices, Part};
use crate::bench::report::BenchReport;
use crate::bench::BenchModel;
use crate::board::TargetFlags;
use crate::encode::Partition;

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
    #[arg(long, default_value_t = deform_shared::qformat::FIXED_POINT_FLOOR, value_name = "TOL", value_parser = crate::refine::parse_tolerance)]
    pub realtime_tol: f64,

    /// Measure nothing: redraw the plots (and rewrite the CSV tables) from the bench.json
    /// already in --out.
    #[arg(long, conflicts_with_all = ["only", "host_baseline", "quick"])]
    pub replot: bool,

    /// How the sweep shares the rows out over the MVUs: `rows` (thesis 4.1.2) or `overlap`
    /// (4.1.1).
    #[arg(long, value_enum, default_value_t = Partition::Rows)]
    pub partition: Partition,

    /// The board the target parts run on (`litex`: real cycles of a VexRiscv under
    /// Verilator, one MVU; use small --edges and `--mvus 1`).
    #[command(flatten)]
    pub target: TargetFlags,

    /// Seconds one target solve may take.
    #[arg(long, default_value_t = 600, value_parser = clap::value_parser!(u64).range(1..))]
    pub timeout: u64,
}

impl BenchArgs {
    /// What the flags ask to measure.
    pub fn choices(&self) -> Choices {
        Choices {
            quick: self.quick,
            only: match self.host_baseline {
                true => vec![Part::Host],
                false => self.only.clone(),
            },
            models: self.models.clone(),
            edges: self.edges.clone(),
            mvus: self.mvus.clone(),
            host_edges: self.host_edges.clone(),
            partition: self.partition,
            realtime_tol: self.realtime_tol,
            solve_timeout: Duration::from_secs(self.timeout),
        }
    }
}

pub fn run(args: &BenchArgs) -> anyhow::Result<BenchReport> {
    let (report, written) = if args.replot {
        let report = read_report(&args.out)?;
        let written = write_all(&report, &args.out)?;
        (report, written)
    } else {
        measure(&args.choices(), &args.target, &args.out)?
    };
    for path in &written {
        println!("wrote  {}", path.display());
    }
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
    fn flags_pick_parts_models_and_sizes() {
        let args = parse(&["--host-baseline", "--models", "b", "--host-edges", "4,6"]).unwrap();
        assert_eq!(args.choices().parts(), [Part::Host]);
        assert_eq!(args.choices().host_config().models, [BenchModel::B]);
        assert_eq!(args.choices().host_config().edges, [4, 6]);
        let args = parse(&[
            "--only",
            "sweep,convergence",
            "--edges",
            "4,5",
            "--mvus",
            "1,2",
        ])
        .unwrap();
        assert_eq!(args.choices().parts(), [Part::Sweep, Part::Convergence]);
        assert_eq!(args.choices().sweep_config().edges, [4, 5]);
        assert_eq!(args.choices().sweep_config().mvus, [1, 2]);
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
