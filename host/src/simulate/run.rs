//! A series run on a board as `deform simulate` runs it: a progress bar on a terminal with the
//! firmware's logs above it, each step's line printed, its row and displacements through the
//! sink, and the run's totals. A write error stops the run at that step in either mode.

use std::path::Path;

use anyhow::Context;

use super::plan::SeriesPlan;
use super::sink::{dynamic_step_line, step_line, DynamicStepRow, StepRow, StepSink, Totals};
use super::{simulate_with, StepModel, StepParams, StepResult};
use crate::board::{self, Board};
use crate::dynamics::target::{simulate_dynamic, DynamicModel, DynamicParams, DynamicStep};
use crate::model::Model;
use crate::progress::{bar, upload_progress};

/// Where the steps go: `--steps-csv` and `--out`.
#[derive(Debug, Clone, Copy)]
pub struct Files<'a> {
    pub steps_csv: Option<&'a Path>,
    pub out: Option<&'a Path>,
}

/// The bars of a run: the steps (the firmware's log lines print above it) and the upload.
fn bars(board: &Board, steps: u32) -> (indicatif::ProgressBar, indicatif::ProgressBar) {
    let steps_bar = bar(u64::from(steps), "steps");
    board::lock(board.logs()).set_progress(Some(steps_bar.clone()));
    (steps_bar, bar(0, "upload"))
}

/// The quasi-static steps of `plan`; the totals and the files written.
pub fn quasi_static(
    board: &mut Board,
    plan: &SeriesPlan,
    model: &Model,
    params: StepParams,
    files: Files,
) -> anyhow::Result<(Totals, Vec<String>)> {
    let template = StepResult::default();
    let mut sink = StepSink::create(files.steps_csv, files.out, &StepRow(&template))?;
    let (steps_bar, upload_bar) = bars(board, plan.schedule.steps);
    let mut totals = Totals::default();
    let mut written: anyhow::Result<()> = Ok(());
    let step_model = |t: f64| plan.model_at(t);
    let ran = simulate_with(
        &mut board.target,
        model,
        plan.schedule,
        plan.simulation
            .is_some()
            .then_some(&step_model as StepModel),
        plan.nonlinear,
        params,
        upload_progress(&upload_bar),
        |r: &StepResult| {
            totals.add(r, params.tol);
            steps_bar.suspend(|| println!("{}", step_line(r)));
            steps_bar.inc(1);
            if written.is_ok() {
                written = sink.write(&StepRow(r), model, r);
            }
        },
    );
    steps_bar.finish_and_clear();
    let wrote = sink.finish();
    ran.context("simulating on the target")?;
    written?;
    Ok((totals, wrote?))
}

/// The dynamic steps of `plan` (the model `built` for its step); the totals and the files.
pub fn dynamic(
    board: &mut Board,
    plan: &SeriesPlan,
    built: DynamicModel,
    model: &Model,
    params: DynamicParams,
    files: Files,
) -> anyhow::Result<(Totals, Vec<String>)> {
    let template = DynamicStep {
        result: StepResult::default(),
        energy: 0.0,
    };
    let mut sink = StepSink::create(files.steps_csv, files.out, &DynamicStepRow(&template))?;
    let (steps_bar, upload_bar) = bars(board, plan.schedule.steps);
    let mut totals = Totals::default();
    let mut written: anyhow::Result<()> = Ok(());
    let step_model = |t: f64| plan.model_at(t);
    let ran = simulate_dynamic(
        &mut board.target,
        model,
        plan.simulation
            .is_some()
            .then_some(&step_model as StepModel),
        plan.schedule,
        built,
        params,
        upload_progress(&upload_bar),
        |s| {
            totals.add(&s.result, params.tol);
            steps_bar.suspend(|| println!("{}", dynamic_step_line(s)));
            steps_bar.inc(1);
            if written.is_ok() {
                written = sink.write(&DynamicStepRow(s), model, &s.result);
            }
        },
    );
    steps_bar.finish_and_clear();
    let wrote = sink.finish();
    ran.context("simulating the dynamics on the target")?;
    written?;
    Ok((totals, wrote?))
}
