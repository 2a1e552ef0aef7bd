//! Where a time series goes as it runs: `--steps-csv` (one typed row per step: [`StepRow`],
//! or [`DynamicStepRow`] for a dynamic series) and `--out` (every step's displacements), through
//! [`RunFiles`]; and the lines a person reads per step and at the end.

use std::fmt::Display;
use std::path::Path;

use super::StepResult;
use crate::dynamics::target::DynamicStep;
use crate::model::Model;
use crate::output::csv::{CsvRow, Sci};
use crate::output::node_rows;
use crate::output::series::{Numbering, RunFiles};

/// One quasi-static step of `--steps-csv`.
pub struct StepRow<'a>(pub &'a StepResult);

impl CsvRow for StepRow<'_> {
    fn columns(&self, column: &mut dyn FnMut(&'static str, &dyn Display)) {
        let r = self.0;
        column("step", &r.step);
        column("t", &r.t);
        column("iterations", &r.iterations);
        column("residual", &Sci(r.residual));
        column("max_u", &Sci(r.max_u));
        column("cycles", &r.cycles);
    }
}

/// One dynamic step of `--steps-csv`: iterations summed over x, y and z, the fused iterations
/// of the target's solves, the cycles on their critical path, the energy and the bytes.
pub struct DynamicStepRow<'a>(pub &'a DynamicStep);

/// CG iterations the target ran, a fused solve counted once (what the cycles follow).
pub fn fused_iterations(s: &DynamicStep) -> u32 {
    s.result.reports.iter().map(|r| r.iterations).sum()
}

impl CsvRow for DynamicStepRow<'_> {
    fn columns(&self, column: &mut dyn FnMut(&'static str, &dyn Display)) {
        let r = &self.0.result;
        column("step", &r.step);
        column("t", &r.t);
        column("iterations", &r.iterations);
        column("solves", &r.reports.len());
        column("fused_iterations", &fused_iterations(self.0));
        column("cycles", &r.cycles);
        column("residual", &Sci(r.residual));
        column("max_u", &Sci(r.max_u));
        column("energy", &Sci(self.0.energy));
        column("bytes_sent", &r.bytes.sent);
        column("bytes_received", &r.bytes.received);
    }
}

/// `--steps-csv` and `--out` of a series.
pub struct StepSink {
    files: RunFiles,
}

impl StepSink {
    /// Creates the files (their paths checked beforehand); `template` gives the CSV header.
    pub fn create(
        csv: Option<&Path>,
        out: Option<&Path>,
        template: &dyn CsvRow,
    ) -> anyhow::Result<Self> {
        Ok(Self {
            files: RunFiles::create(csv, template, out, Numbering::STEPS)?,
        })
    }

    /// One step: its row, and its displacements (the model's node stiffness alongside: a
    /// displacement-dependent model's per-spring field is not written).
    pub fn write(&mut self, row: &dyn CsvRow, model: &Model, r: &StepResult) -> anyhow::Result<()> {
        self.files
            .write(row, r.step, r.t, || Some(node_rows(model, &r.u)))
    }

    /// Gives the files their real names; the lines to print.
    pub fn finish(self) -> anyhow::Result<Vec<String>> {
        self.files.finish()
    }
}

/// A quasi-static step as the run prints it.
pub fn step_line(r: &StepResult) -> String {
    let mut line = format!(
        "step {:>4}  t = {:<8.4} iterations {:>5}  residual {:.2e}  max |u| {:.4e}",
        r.step, r.t, r.iterations, r.residual, r.max_u
    );
    if let Some(dev) = r.deviation {
        line += &format!("  deviation {dev:.1e}");
    }
    if let Some(u) = &r.update {
        line += &format!(
            "  values-only update {} B (full upload {} B, saved {} B)",
            u.bytes_sent,
            u.full_upload_bytes,
            u.bytes_saved()
        );
    }
    line
}

/// A dynamic step as the run prints it.
pub fn dynamic_step_line(s: &DynamicStep) -> String {
    let r = &s.result;
    let mut line = format!(
        "step {:>4}  t = {:<8.4} iterations {:>4} ({} solve(s), {} fused)  cycles {:>9}  residual {:.1e}  max |u| {:.4e}  energy {:.4e}  {} B",
        r.step,
        r.t,
        r.iterations,
        r.reports.len(),
        fused_iterations(s),
        r.cycles,
        r.residual,
        r.max_u,
        s.energy,
        r.bytes.total()
    );
    if let Some(dev) = r.deviation {
        line += &format!("  deviation {dev:.1e}");
    }
    line
}

/// How far above `--tol` a quasi-static step's true residual may end before the run says so:
/// the target stops on its recursive fixed-point residual, which the true f64 one exceeds by a
/// small factor (1e-7 asked, up to 1.8e-7 measured on the thesis cube), while a
/// displacement-dependent K costs the fixed point far more (1.4e-5).
pub const MISS_FACTOR: f64 = 10.0;

/// Sums over a run, for its closing lines.
#[derive(Debug, Default)]
pub struct Totals {
    pub steps: u64,
    pub iterations: u64,
    pub cycles: u64,
    pub max_cycles: u64,
    pub bytes: u64,
    /// Bytes of every step after the first (whose include the matrix upload).
    pub bytes_after_first: u64,
    /// Bytes a values-only update saved against full uploads.
    pub saved: u64,
    /// Steps whose true residual ended above [`MISS_FACTOR`] × the tolerance, and the worst
    /// residual of all.
    pub missed: u64,
    pub worst_residual: f64,
    /// Steps run as superposed live frames.
    pub superposed: u64,
}

impl Totals {
    /// Adds step `r`, solved to `tol`.
    pub fn add(&mut self, r: &StepResult, tol: f64) {
        self.steps += 1;
        self.iterations += u64::from(r.iterations);
        self.cycles += r.cycles;
        self.max_cycles = self.max_cycles.max(r.cycles);
        self.bytes += r.bytes.total();
        if r.step > 1 {
            self.bytes_after_first += r.bytes.total();
        }
        self.saved += r.update.map_or(0, |u| u.bytes_saved());
        if r.residual > MISS_FACTOR * tol {
            self.missed += 1;
        }
        self.worst_residual = self.worst_residual.max(r.residual);
        self.superposed += u64::from(r.superposed);
    }

    /// The closing lines of a quasi-static run solved with `params`.
    pub fn quasi_static_lines(&self, params: &super::StepParams, nonlinear: bool) -> String {
        let start = match (params.warm_start, params.fuse && params.predict) {
            _ if self.superposed > 0 && self.superposed == self.steps => {
                "superposed live frames: the prescribed nodes' response columns"
            }
            (false, _) => "cold starts",
            (true, false) => "warm starts from the previous step",
            (true, true) => "fused, started from the target's prediction 2u(t−1) − u(t−2)",
        };
        let mut out = format!(
            "{} steps, {} CG iterations in all, {} critical-path cycles (worst step {}) ({start})\n",
            self.steps, self.iterations, self.cycles, self.max_cycles
        );
        if nonlinear {
            out += &format!(
                "values-only updates saved {} bytes on the wire against full uploads\n",
                self.saved
            );
        }
        out
    }

    /// The closing lines of a dynamic run.
    pub fn dynamic_lines(&self) -> String {
        let steps = self.steps.max(1);
        format!(
            "{} steps, {} CG iterations ({:.1} per step), {} critical-path cycles ({} per step, worst {})\n\
             link        {} bytes in all; {} per step after the first (right-hand sides, solves, solutions)\n",
            self.steps,
            self.iterations,
            self.iterations as f64 / steps as f64,
            self.cycles,
            self.cycles / steps,
            self.max_cycles,
            self.bytes,
            self.bytes_after_first / (steps - 1).max(1)
        )
    }

    /// Says so when steps ended above the tolerance (the target's fixed point stops at its own
    /// recursive residual; a displacement-dependent K costs it precision).
    pub fn missed_line(&self, tol: f64) -> Option<String> {
        (self.missed > 0).then(|| {
            format!(
                "warning: {} of {} step(s) ended far above --tol {tol:e}: true residual up to \
                 {:.2e} (the target's fixed point stops at its own recursive residual, which a \
                 displacement-dependent K leaves far from the true one; quasi-static steps are not \
                 refined)",
                self.missed, self.steps, self.worst_residual
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::board::WireBytes;

    fn result() -> StepResult {
        StepResult {
            step: 3,
            t: 0.25,
            iterations: 12,
            reports: Vec::new(),
            cycles: 99_000,
            superposed: false,
            residual: 1e-5,
            max_u: 2.5e-3,
            deviation: None,
            update: None,
            bytes: WireBytes {
                sent: 700,
                received: 800,
            },
            u: [Vec::new(), Vec::new(), Vec::new()],
        }
    }

    /// The header names every column a row has (the dynamic one once lacked `solves` and
    /// `fused_iterations`, shifting every later column's name).
    #[test]
    fn the_steps_csv_header_names_every_column() {
        let step = DynamicStep {
            result: result(),
            energy: 0.5,
        };
        let row = DynamicStepRow(&step);
        let header: Vec<String> = row.header().split(',').map(String::from).collect();
        let line = row.line();
        let fields: Vec<&str> = line.split(',').collect();
        assert_eq!(header.len(), fields.len(), "{line}");
        let column = |name: &str| fields[header.iter().position(|h| h == name).unwrap()];
        assert_eq!(column("step"), "3");
        assert_eq!(column("solves"), "0");
        assert_eq!(column("cycles"), "99000");
        assert_eq!(column("bytes_received"), "800");
        // The energy is the step's own, not max |u| repeated.
        assert_eq!(column("max_u"), "2.5e-3");
        assert_eq!(column("energy"), "5e-1");
        let r = result();
        let row = StepRow(&r);
        assert_eq!(row.header(), "step,t,iterations,residual,max_u,cycles");
        assert_eq!(row.line(), "3,0.25,12,1e-5,2.5e-3,99000");
    }
}
