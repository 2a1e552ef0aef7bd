//! The bench's results as files: `bench.json` (everything) and CSV tables: `bench.csv` (the
//! sweep, one row per point), `convergence.csv`, `realtime.csv` and `host_baseline.csv`.
//!
//! The CSVs hold only numbers and fixed labels (no quoting needed), so they are written with
//! `format!` rather than through a CSV crate.

use std::fmt::Display;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::convergence::ConvergenceSeries;
use super::host_baseline::HostPoint;
use super::realtime::{RealtimeScenario, StepBudget};
use super::sweep::{SweepPoint, SweepResult};
use super::NOMINAL_CLOCK_HZ;
use crate::output::csv::{CsvRow, Fixed, Sci};
use crate::output::file::write_atomic;

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
    write_atomic(path, |out| Ok(out.write_all(text.as_bytes())?))?;
    Ok(path.to_path_buf())
}

/// A table as text: `template`'s header, then `rows`.
fn table<R: CsvRow>(template: R, rows: impl IntoIterator<Item = R>) -> String {
    let mut text = template.header() + "\n";
    for row in rows {
        text += &row.line();
        text.push('\n');
    }
    text
}

/// The columns every bench table starts with: which cube.
fn cube_columns(
    column: &mut dyn FnMut(&'static str, &dyn Display),
    model: super::BenchModel,
    edge: usize,
    n: usize,
) {
    column("model", &model.label());
    column("edge", &edge);
    column("n", &n);
}

/// One sweep point of `bench.csv`.
struct SweepRow<'a>(&'a super::sweep::SweepPoint);

impl CsvRow for SweepRow<'_> {
    fn columns(&self, column: &mut dyn FnMut(&'static str, &dyn Display)) {
        let p = self.0;
        cube_columns(column, p.model, p.edge, p.n);
        column("nnz", &p.nnz);
        column("words", &p.words);
        column("tiles", &p.tiles);
        column("mvus", &p.mvus);
        column("mvus_used", &p.mvus_used);
        column("partition", &p.partition);
        column("symmetry_used", &p.symmetry_used);
        // (name, value, decimals): cycles and instructions whole, ratios to three places.
        let figures = [
            ("mvu_cycles_per_iteration", p.mvu_cycles_per_iteration, 0),
            ("svu_cycles_per_iteration", p.svu_cycles_per_iteration, 0),
            ("cycles_per_iteration", p.cycles_per_iteration, 0),
            (
                "mvu_instructions_per_iteration",
                p.mvu_instructions_per_iteration,
                0,
            ),
            (
                "svu_instructions_per_iteration",
                p.svu_instructions_per_iteration,
                0,
            ),
            ("instructions_per_nonzero", p.instructions_per_nonzero, 3),
            ("instructions_per_product", p.instructions_per_product, 3),
            (
                "microseconds_per_iteration",
                p.microseconds_per_iteration,
                3,
            ),
            ("mflops", p.mflops, 3),
        ];
        for (name, value, decimals) in figures {
            column(name, &Fixed(value, decimals));
        }
        column("saturations", &p.saturations);
        column("wire_bytes_matrix_upload", &p.wire_bytes_matrix_upload);
        column("wire_bytes_per_solve", &p.wire_bytes_per_solve);
    }
}

/// One point of a convergence curve in `convergence.csv`.
struct ConvergenceRow<'a> {
    series: &'a ConvergenceSeries,
    iteration: u32,
    error: f64,
}

impl CsvRow for ConvergenceRow<'_> {
    fn columns(&self, column: &mut dyn FnMut(&'static str, &dyn Display)) {
        let s = self.series;
        let step = s
            .refinement_starts
            .iter()
            .filter(|&&r| r < self.iteration)
            .count()
            .max(1);
        column("model", &s.model.label());
        column("arithmetic", &format!("{:?}", s.arithmetic));
        column("edge", &s.edge);
        column("iteration", &self.iteration);
        column("error_inf", &Sci(self.error));
        column("refinement_step", &step);
    }
}

/// One time step of `realtime.csv`.
struct RealtimeRow<'a>(&'a RealtimeScenario, &'a StepBudget);

impl CsvRow for RealtimeRow<'_> {
    fn columns(&self, column: &mut dyn FnMut(&'static str, &dyn Display)) {
        let (s, st) = (self.0, self.1);
        cube_columns(column, s.model, s.edge, s.n);
        column("step", &st.step);
        column("iterations", &st.iterations);
        column("mvu_cycles", &st.mvu_cycles);
        column("svu_cycles", &st.svu_cycles);
        column("cycles", &st.cycles);
        column("wire_bytes", &st.wire_bytes);
        let rate = NOMINAL_CLOCK_HZ / st.cycles.max(1) as f64;
        column("steps_per_second_at_100mhz", &Fixed(rate, 1));
    }
}

/// One grid of `host_baseline.csv`.
struct HostRow<'a>(&'a HostPoint);

impl CsvRow for HostRow<'_> {
    fn columns(&self, column: &mut dyn FnMut(&'static str, &dyn Display)) {
        let p = self.0;
        cube_columns(column, p.model, p.edge, p.n);
        column("nnz", &p.nnz);
        column("matrix_bytes", &p.matrix_bytes);
        column("build_seconds", &Sci(p.build_seconds));
        column("iterations_timed", &p.iterations_timed);
        column("seconds_per_iteration", &Sci(p.seconds_per_iteration));
        column(
            "nanoseconds_per_nonzero",
            &Fixed(p.nanoseconds_per_nonzero, 4),
        );
    }
}

/// Writes `bench.json` and the CSV tables of the parts that ran into `dir`; returns the paths.
pub fn write_files(report: &BenchReport, dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let mut written = vec![write(
        &dir.join("bench.json"),
        &serde_json::to_string_pretty(report)?,
    )?];
    if let Some(sweep) = &report.sweep {
        let text = table(
            SweepRow(&SweepPoint::default()),
            sweep.points.iter().map(SweepRow),
        );
        written.push(write(&dir.join("bench.csv"), &text)?);
    }
    if let Some(series) = &report.convergence {
        let blank = ConvergenceSeries::default();
        let template = ConvergenceRow {
            series: &blank,
            iteration: 0,
            error: 0.0,
        };
        let text = table(
            template,
            series.iter().flat_map(|s| {
                s.points
                    .iter()
                    .map(move |&(iteration, error)| ConvergenceRow {
                        series: s,
                        iteration,
                        error,
                    })
            }),
        );
        written.push(write(&dir.join("convergence.csv"), &text)?);
    }
    if let Some(scenarios) = &report.realtime {
        let (s0, st0) = (RealtimeScenario::default(), StepBudget::default());
        let text = table(
            RealtimeRow(&s0, &st0),
            scenarios
                .iter()
                .flat_map(|s| s.steps.iter().map(move |st| RealtimeRow(s, st))),
        );
        written.push(write(&dir.join("realtime.csv"), &text)?);
    }
    if let Some(points) = &report.host_baseline {
        let text = table(HostRow(&HostPoint::default()), points.iter().map(HostRow));
        written.push(write(&dir.join("host_baseline.csv"), &text)?);
    }
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The tables keep the columns and the number formats they had when each was written out
    /// by hand.
    #[test]
    fn the_tables_keep_their_columns_and_formats() {
        let p = SweepPoint {
            mvu_cycles_per_iteration: 1234.4,
            instructions_per_nonzero: 15.0,
            mflops: 2.5,
            ..SweepPoint::default()
        };
        let row = SweepRow(&p);
        assert_eq!(
            row.header(),
            "model,edge,n,nnz,words,tiles,mvus,mvus_used,partition,symmetry_used,\
             mvu_cycles_per_iteration,svu_cycles_per_iteration,cycles_per_iteration,\
             mvu_instructions_per_iteration,svu_instructions_per_iteration,\
             instructions_per_nonzero,instructions_per_product,microseconds_per_iteration,mflops,\
             saturations,wire_bytes_matrix_upload,wire_bytes_per_solve"
        );
        assert_eq!(
            row.line(),
            "A,0,0,0,0,0,0,0,,false,1234,0,0,0,0,15.000,0.000,0.000,2.500,0,0,0"
        );
        let (s, st) = (
            RealtimeScenario::default(),
            StepBudget {
                cycles: 100_000,
                ..StepBudget::default()
            },
        );
        assert!(RealtimeRow(&s, &st).line().ends_with(",100000,0,1000.0"));
        let h = HostPoint {
            seconds_per_iteration: 2.5e-6,
            ..HostPoint::default()
        };
        assert_eq!(HostRow(&h).line(), "A,0,0,0,0,0e0,0,2.5e-6,0.0000");
    }
}
