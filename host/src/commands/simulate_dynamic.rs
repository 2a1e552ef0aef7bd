//! `deform simulate --dynamic`: the elastodynamic series ([`crate::dynamics`]) on the target,
//! printed step by step (iterations, cycles, bytes, energy) and written like the quasi-static
//! one. `deform simulate` dispatches here once the board is open.

use std::fs::File;
use std::io::{BufWriter, Write};

use anyhow::Context;

use super::simulate::{bar, upload_progress, ResolvedSimulation, SimulateArgs};
use crate::board::{self, Board};
use crate::dynamics::target::{simulate_dynamic, DynamicParams, DynamicStep};
use crate::dynamics::DynamicsSpec;
use crate::encode::EncodeOptions;
use crate::model::Model;
use crate::output::node_rows;
use crate::output::series::SeriesWriter;
use crate::simulate::StepModel;

/// Sums over the run, for the closing lines.
#[derive(Debug, Default)]
struct Totals {
    steps: u64,
    iterations: u64,
    cycles: u64,
    max_cycles: u64,
    bytes: u64,
    /// Bytes of every step after the first (whose include the matrix upload).
    bytes_after_first: u64,
}

/// CG iterations the target ran, a fused solve counted once (what the cycles follow).
fn fused_iterations(s: &DynamicStep) -> u32 {
    s.result.reports.iter().map(|r| r.iterations).sum()
}

/// The columns of `--steps-csv` for a dynamic series, one row per step ([`csv_row`]).
const STEPS_CSV_HEADER: &str =
    "step,t,iterations,solves,fused_iterations,cycles,residual,max_u,energy,bytes_sent,bytes_received";

fn csv_row(s: &DynamicStep) -> String {
    let r = &s.result;
    format!(
        "{},{},{},{},{},{},{:e},{:e},{:e},{},{}",
        r.step,
        r.t,
        r.iterations,
        r.reports.len(),
        fused_iterations(s),
        s.cycles,
        r.residual,
        r.max_u,
        s.energy,
        s.bytes_sent,
        s.bytes_received
    )
}

fn line(s: &DynamicStep) -> String {
    let r = &s.result;
    let mut line = format!(
        "step {:>4}  t = {:<8.4} iterations {:>4} ({} solve(s), {} fused)  cycles {:>9}  residual {:.1e}  max |u| {:.4e}  energy {:.4e}  {} B",
        r.step,
        r.t,
        r.iterations,
        r.reports.len(),
        fused_iterations(s),
        s.cycles,
        r.residual,
        r.max_u,
        s.energy,
        s.bytes_sent + s.bytes_received
    );
    if let Some(dev) = r.deviation {
        line += &format!("  deviation {dev:.1e}");
    }
    line
}

pub fn run(
    args: &SimulateArgs,
    resolved: &ResolvedSimulation,
    spec: &DynamicsSpec,
    model: &Model,
    board: &mut Board,
    layout: EncodeOptions,
    mut series: Option<SeriesWriter>,
) -> anyhow::Result<()> {
    let schedule = resolved.schedule;
    println!("dynamics    {}, h = {} s", spec.describe(), schedule.dt);
    let mut csv = match &args.steps_csv {
        Some(path) => {
            let mut f = BufWriter::new(
                File::create(path).with_context(|| format!("creating {}", path.display()))?,
            );
            writeln!(f, "{STEPS_CSV_HEADER}")?;
            Some(f)
        }
        None => None,
    };
    let n = model.n();
    let params = DynamicParams {
        tol: args.tol,
        max_solves: args.dynamics.max_solves,
        max_iterations: args
            .max_iter
            .unwrap_or((10 * n).min(u32::MAX as usize) as u32),
        check_reference: args.check,
        layout,
    };
    let steps_bar = bar(schedule.steps as u64, "steps");
    board::lock(board.logs()).set_progress(Some(steps_bar.clone()));
    let upload_bar = bar(0, "upload");
    let mut totals = Totals::default();
    let mut written: anyhow::Result<()> = Ok(());
    let mut on_step = |s: &DynamicStep| {
        let r = &s.result;
        totals.steps += 1;
        totals.iterations += r.iterations as u64;
        totals.cycles += s.cycles;
        totals.max_cycles = totals.max_cycles.max(s.cycles);
        let bytes = s.bytes_sent + s.bytes_received;
        totals.bytes += bytes;
        if r.step > 1 {
            totals.bytes_after_first += bytes;
        }
        steps_bar.suspend(|| println!("{}", line(s)));
        steps_bar.inc(1);
        let mut write = || -> anyhow::Result<()> {
            if let Some(f) = csv.as_mut() {
                writeln!(f, "{}", csv_row(s))?;
            }
            if let Some(series) = series.as_mut() {
                series.write_step(r.step, r.t, &node_rows(model, &r.u))?;
            }
            Ok(())
        };
        if written.is_ok() {
            written = write();
        }
    };
    let step_model = |t: f64| resolved.model_at(t);
    simulate_dynamic(
        &mut board.target,
        model,
        resolved
            .simulation
            .is_some()
            .then_some(&step_model as StepModel),
        schedule,
        spec,
        params,
        upload_progress(&upload_bar),
        &mut on_step,
    )
    .context("simulating the dynamics on the target")?;
    steps_bar.finish_and_clear();
    written?;
    if let Some(mut f) = csv {
        f.flush()?;
    }
    let steps = totals.steps.max(1);
    println!(
        "{} steps, {} CG iterations ({:.1} per step), {} critical-path cycles ({} per step, worst {})",
        totals.steps,
        totals.iterations,
        totals.iterations as f64 / steps as f64,
        totals.cycles,
        totals.cycles / steps,
        totals.max_cycles
    );
    println!(
        "link        {} bytes in all; {} per step after the first (right-hand sides, solves, solutions)",
        totals.bytes,
        totals.bytes_after_first / (steps - 1).max(1)
    );
    if let Some(series) = series {
        println!("wrote       {}", series.finish()?);
    }
    if let Some(path) = &args.steps_csv {
        println!("wrote       {}", path.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simulate::StepResult;

    /// The header names every column a row has (it once lacked `solves` and
    /// `fused_iterations`, shifting every later column's name).
    #[test]
    fn the_steps_csv_header_names_every_column() {
        let step = DynamicStep {
            result: StepResult {
                step: 3,
                t: 0.25,
                iterations: 12,
                reports: Vec::new(),
                cycles: 0,
                residual: 1e-5,
                max_u: 2.5e-3,
                deviation: None,
                update: None,
                u: [Vec::new(), Vec::new(), Vec::new()],
            },
            energy: 0.5,
            bytes_sent: 700,
            bytes_received: 800,
            cycles: 99_000,
        };
        let header: Vec<&str> = STEPS_CSV_HEADER.split(',').collect();
        let row = csv_row(&step);
        let fields: Vec<&str> = row.split(',').collect();
        assert_eq!(header.len(), fields.len(), "{row}");
        let column = |name: &str| fields[header.iter().position(|h| *h == name).unwrap()];
        assert_eq!(column("step"), "3");
        assert_eq!(column("solves"), "0");
        assert_eq!(column("cycles"), "99000");
        assert_eq!(column("bytes_received"), "800");
    }
}
