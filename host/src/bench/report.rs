//! The bench's results as files: `bench.json` (everything) and CSV tables: `bench.csv` (the
//! sweep, one row per point), `convergence.csv`, `realtime.csv` and `host_baseline.csv`.
//!
//! The CSVs hold only numbers and fixed labels (no quoting needed), so they are written with
//! `format!` rather than through a CSV crate.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::{Deserialize, Serialize};

use super::convergence::ConvergenceSeries;
use super::host_baseline::HostPoint;
use super::realtime::RealtimeScenario;
use super::sweep::SweepResult;
use super::NOMINAL_CLOCK_HZ;

/// Everything one `deform bench` run measured; the parts not run are `None`.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct BenchReport {
    /// The clock the cycle counts are converted at (Hz), with one instruction per cycle.
    pub nominal_clock_hz: f64,
    /// The target as it introduced itself (firmware version, harts, capacities).
    pub target: Option<String>,
    pub quick: bool,
    pub sweep: Option<SweepResult>,
    pub convergence: Option<Vec<ConvergenceSeries>>,
    pub realtime: Option<Vec<RealtimeScenario>>,
    pub host_baseline: Option<Vec<HostPoint>>,
}

impl BenchReport {
    pub fn new(quick: bool) -> Self {
        BenchReport {
            nominal_clock_hz: NOMINAL_CLOCK_HZ,
            quick,
            ..Default::default()
        }
    }
}

fn write(path: &Path, text: &str) -> anyhow::Result<PathBuf> {
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?;
    Ok(path.to_path_buf())
}

/// Writes `bench.json` and the CSV tables of the parts that ran into `dir`; returns the paths.
pub fn write_files(report: &BenchReport, dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let mut written = Vec::new();
    let json = serde_json::to_string_pretty(report)?;
    written.push(write(&dir.join("bench.json"), &json)?);
    if let Some(sweep) = &report.sweep {
        let mut csv = String::from(
            "model,edge,n,nnz,words,tiles,mvus,mvus_used,partition,symmetry_used,\
             mvu_cycles_per_iteration,svu_cycles_per_iteration,cycles_per_iteration,\
             mvu_instructions_per_iteration,svu_instructions_per_iteration,\
             instructions_per_nonzero,instructions_per_product,microseconds_per_iteration,mflops,\
             saturations,wire_bytes_matrix_upload,wire_bytes_per_solve\n",
        );
        for p in &sweep.points {
            let _ = writeln!(
                csv,
                "{},{},{},{},{},{},{},{},{},{},{:.0},{:.0},{:.0},{:.0},{:.0},{:.3},{:.3},{:.3},{:.3},{},{},{}",
                p.model.label(),
                p.edge,
                p.n,
                p.nnz,
                p.words,
                p.tiles,
                p.mvus,
                p.mvus_used,
                p.partition,
                p.symmetry_used,
                p.mvu_cycles_per_iteration,
                p.svu_cycles_per_iteration,
                p.cycles_per_iteration,
                p.mvu_instructions_per_iteration,
                p.svu_instructions_per_iteration,
                p.instructions_per_nonzero,
                p.instructions_per_product,
                p.microseconds_per_iteration,
                p.mflops,
                p.saturations,
                p.wire_bytes_matrix_upload,
                p.wire_bytes_per_solve
            );
        }
        written.push(write(&dir.join("bench.csv"), &csv)?);
    }
    if let Some(series) = &report.convergence {
        let mut csv = String::from("model,arithmetic,edge,iteration,error_inf,refinement_step\n");
        for s in series {
            for &(k, e) in &s.points {
                let step = s
                    .refinement_starts
                    .iter()
                    .filter(|&&r| r < k)
                    .count()
                    .max(1);
                let _ = writeln!(
                    csv,
                    "{},{:?},{},{},{:e},{}",
                    s.model.label(),
                    s.arithmetic,
                    s.edge,
                    k,
                    e,
                    step
                );
            }
        }
        written.push(write(&dir.join("convergence.csv"), &csv)?);
    }
    if let Some(scenarios) = &report.realtime {
        let mut csv = String::from(
            "model,edge,n,step,iterations,mvu_cycles,svu_cycles,cycles,wire_bytes,steps_per_second_at_100mhz\n",
        );
        for s in scenarios {
            for st in &s.steps {
                let _ = writeln!(
                    csv,
                    "{},{},{},{},{},{},{},{},{},{:.1}",
                    s.model.label(),
                    s.edge,
                    s.n,
                    st.step,
                    st.iterations,
                    st.mvu_cycles,
                    st.svu_cycles,
                    st.cycles,
                    st.wire_bytes,
                    NOMINAL_CLOCK_HZ / st.cycles.max(1) as f64
                );
            }
        }
        written.push(write(&dir.join("realtime.csv"), &csv)?);
    }
    if let Some(points) = &report.host_baseline {
        let mut csv = String::from(
            "model,edge,n,nnz,matrix_bytes,build_seconds,iterations_timed,seconds_per_iteration,nanoseconds_per_nonzero\n",
        );
        for p in points {
            let _ = writeln!(
                csv,
                "{},{},{},{},{},{:e},{},{:e},{:.4}",
                p.model.label(),
                p.edge,
                p.n,
                p.nnz,
                p.matrix_bytes,
                p.build_seconds,
                p.iterations_timed,
                p.seconds_per_iteration,
                p.nanoseconds_per_nonzero
            );
        }
        written.push(write(&dir.join("host_baseline.csv"), &csv)?);
    }
    Ok(written)
}
