//! What `deform bench` measures: the parts, their sizes (a quick CI run or the full range) and
//! the run over them, its files written into one directory.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context;
use clap::ValueEnum;
use deform_shared::qformat::FIXED_POINT_FLOOR;

use super::convergence::{self, ConvergenceConfig};
use super::host_baseline::{self, HostBaselineConfig};
use super::realtime::{self, RealtimeConfig};
use super::report::{write_files, BenchReport};
use super::sweep::{self, SweepConfig};
use super::{open_board, plots, BenchModel};
use crate::board::TargetFlags;
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

/// What to measure: every list empty takes its default, the full range or (`quick`) a small
/// one that checks everything works in about a minute.
#[derive(Debug, Clone)]
pub struct Choices {
    pub quick: bool,
    /// Empty: every part.
    pub only: Vec<Part>,
    pub models: Vec<BenchModel>,
    pub edges: Vec<u16>,
    pub mvus: Vec<u8>,
    pub host_edges: Vec<u16>,
    pub partition: Partition,
    pub realtime_tol: f64,
    pub solve_timeout: Duration,
}

impl Default for Choices {
    fn default() -> Self {
        Self {
            quick: false,
            only: Vec::new(),
            models: Vec::new(),
            edges: Vec::new(),
            mvus: Vec::new(),
            host_edges: Vec::new(),
            partition: Partition::Rows,
            realtime_tol: FIXED_POINT_FLOOR,
            solve_timeout: Duration::from_secs(600),
        }
    }
}

impl Choices {
    pub fn parts(&self) -> Vec<Part> {
        if self.only.is_empty() {
            vec![Part::Sweep, Part::Convergence, Part::Realtime, Part::Host]
        } else {
            self.only.clone()
        }
    }

    pub fn models(&self) -> Vec<BenchModel> {
        if self.models.is_empty() {
            BenchModel::BOTH.to_vec()
        } else {
            self.models.clone()
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
            solve_timeout: self.solve_timeout,
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
            solve_timeout: self.solve_timeout,
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
pub fn write_all(report: &BenchReport, dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let mut written = write_files(report, dir)?;
    written.extend(plots::draw_all(report, dir)?);
    Ok(written)
}

/// Reads `dir/bench.json` back: to redraw its plots without measuring.
pub fn read_report(dir: &Path) -> anyhow::Result<BenchReport> {
    let path = dir.join("bench.json");
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("reading {} (run `deform bench` first)", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{} is not a bench report", path.display()))
}

/// Measures the parts `choices` asks for on `target` (and the host), printing a line per
/// point as it goes; the files go into `out` (created if missing), listed in the report's
/// `written`.
pub fn run(
    choices: &Choices,
    target: &TargetFlags,
    out: &Path,
) -> anyhow::Result<(BenchReport, Vec<PathBuf>)> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let parts = choices.parts();
    let mut report = BenchReport::new(choices.quick);

    if parts.contains(&Part::Sweep) {
        let result = sweep::run(&choices.sweep_config(), target).context("the sweep")?;
        report.sweep = Some(result);
    }
    if parts.contains(&Part::Convergence) {
        let config = choices.convergence_config();
        let mut board = open_board(target, 1, choices.solve_timeout)?;
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
        report.realtime = Some(
            realtime::run(&choices.realtime_config(), target).context("the real-time budget")?,
        );
    }
    if parts.contains(&Part::Host) {
        report.host_baseline = Some(host_baseline::run(&choices.host_config())?);
    }

    let written = write_all(&report, out)?;
    Ok((report, written))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_cover_the_thesis_range_and_quick_shrinks_it() {
        let full = Choices::default();
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

        let quick = Choices {
            quick: true,
            ..Choices::default()
        };
        assert!(quick.sweep_config().edges.iter().all(|&e| e <= 8));
        assert!(quick.host_config().edges.iter().all(|&e| e <= 8));
        assert!(quick.convergence_config().edge < 10);
    }
}
