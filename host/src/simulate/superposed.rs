//! A prescribed-tool series as the live loop's frames ([`crate::live`], issue 19 item 2): the
//! target solves one response column per prescribed node once (`LiveStart`), then every step
//! starts from the superposition of those columns (exact for linear springs) and skips even the
//! exact r₀ pass where its residual estimate allows; only the prescribed displacements go down
//! per step, and the solutions come up for the output and the true residual. The extrapolation
//! of [`Start::Predicted`](deform_shared::protocol::Start::Predicted) stays the fallback where
//! this does not apply ([`superposable`]).

use deform_shared::live::{LiveParams, MAX_TOOL_NODES};
use deform_shared::qformat::FIXED_POINT_FLOOR;

use super::{Nonlinear, Schedule, SimulateError, StepModel, StepParams, StepResult, StepSystem};
use crate::board::WireBytes;
use crate::link::{Port, Target, UploadProgress};
use crate::live::link::LiveLink;
use crate::live::LiveSetup;
use crate::model::{Axis, Model};

/// Whether the series can run as superposed live frames ([`simulate_superposed`]): linear
/// springs, fused predicted warm steps, 1 to [`MAX_TOOL_NODES`] prescribed nodes, and every
/// step's loads the first model's (only the prescribed displacements move).
pub(super) fn superposable(
    model: &Model,
    schedule: Schedule,
    step_model: StepModel,
    nonlinear: Option<Nonlinear>,
    params: &StepParams,
) -> bool {
    let eligible = nonlinear.is_none()
        && params.fuse
        && params.predict
        && params.warm_start
        && (1..=MAX_TOOL_NODES).contains(&model.prescribed_count());
    eligible
        && (1..=schedule.steps).all(|s| {
            step_model(schedule.time(s)).is_ok_and(|m| {
                m.unit_matrix() == model.unit_matrix()
                    && Axis::ALL.iter().all(|&d| m.load(d) == model.load(d))
            })
        })
}

/// Runs the series as superposed live frames; a step's cycles are its frame's, the first
/// step's also the response columns' solve. A SIGINT or SIGTERM ends the series after the
/// step under way ([`crate::interrupt`]).
pub(super) fn simulate_superposed<P: Port>(
    target: &mut Target<P>,
    model: &Model,
    schedule: Schedule,
    step_model: StepModel,
    params: StepParams,
    mut on_upload: impl FnMut(UploadProgress),
    mut on_step: impl FnMut(&StepResult),
) -> Result<Vec<StepResult>, SimulateError> {
    let setup = LiveSetup::new(model.spec(), &params.layout)?;
    // The live set-up streams the matrix itself: the whole of it, then the tool rows.
    on_upload(UploadProgress {
        words_sent: 0,
        words_total: setup.matrix.words.len(),
    });
    let live_params = LiveParams {
        tolerance: params.tol.max(FIXED_POINT_FLOOR) as f32,
        max_iterations: params.max_iterations,
        cycle_budget: 0,
        scale: setup.scale.map(|k| k as f32),
    };
    let mut before = WireBytes::of(&target.stats());
    let mut link = LiveLink::start(target, &setup, live_params)?;
    let mut start_cycles = link.model.cycles;
    let mut results = Vec::new();
    for s in 1..=schedule.steps {
        if crate::interrupt::requested() {
            break;
        }
        let t = schedule.time(s);
        let at_t = step_model(t).map_err(|source| SimulateError::StepModel { t, source })?;
        let tool: Vec<[f64; 3]> = setup
            .tools
            .iter()
            .map(|&p| at_t.prescribed()[p].unwrap_or([0.0; 3]))
            .collect();
        let frame = link.frame(&tool)?;
        let solutions = link.solution()?.to_vec();
        let mut result = StepResult {
            step: s,
            t,
            iterations: u32::from(frame.iterations),
            cycles: u64::from(frame.cycles) + std::mem::take(&mut start_cycles),
            superposed: true,
            ..StepResult::default()
        };
        StepSystem::linear(model, &at_t, 1.0).check(
            solutions,
            params.check_reference,
            &mut result,
        )?;
        let now = link.wire();
        result.bytes = now.since(before);
        before = now;
        on_step(&result);
        results.push(result);
    }
    Ok(results)
}
