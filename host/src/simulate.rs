//! Quasi-static time series (thesis 2.4.2): the model solved at a sequence of time steps, each
//! step's loads a function of time, with the target's matrix kept resident between steps.
//!
//! # Schedule
//!
//! A [`Schedule`] is `steps` steps of `dt`; step s (1-based) solves at t = s·dt. With
//! [`simulate`] every load (and prescribed displacement) is ramped linearly from 0 at t = 0 to
//! the model's full value at t = steps·dt (the factor t / (steps·dt)). With [`simulate_with`]
//! a caller gives the model at each t instead (a scenario's `[simulation]` keyframes, see
//! [`crate::scenario::Simulation::spec_at`]): its loads and its prescribed displacements, moved
//! into the right-hand side by [`Model::build`] as for `--displace`. The prescribed nodes must
//! be the same at every step, so the matrix is.
//!
//! # Displacement-independent model (the default)
//!
//! K (A, thesis eq. 38) is constant: it is uploaded once, and each step solves A·u_d = b_d(t)
//! for d = x, y, z. No refinement: the target's solution is the step's, to the target tolerance
//! `max(tol, 1e-7)`; the reported residual is the true f64 residual.
//!
//! - **Fused and predicted** (the default, [`StepParams::fuse`] and [`StepParams::predict`]):
//!   one target solve per step runs x, y and z together (direction d is axis d), and with
//!   [`Start::Predicted`] the target starts each direction from 2u(t−1) − u(t−2) of the
//!   solutions it keeps, so only the right-hand sides go down and the solutions up.
//! - **Plain warm start** (`predict = false`, or unfused): each solve starts from the previous
//!   step's solution of the same direction, uploaded as the `InitialGuess` (unfused, the
//!   target's own previous solution is the previous *direction's*).
//!
//! # Displacement-dependent model ([`Nonlinear`], thesis 3.2.2)
//!
//! Each spring p–q gets k̃ = α0 + α1·Σ_d Δl^d + α2·Σ_d (Δl^d)², with Δl^d = u_d[q] − u_d[p] the
//! spring's length change along d at the previous step (0 before the first), one K for all
//! three directions, K·u_d = f_d(t). K's pattern does not change, so from the second step on
//! only the new values go to the target ([`Target::update_values`]); the bytes saved against a
//! full upload are reported per step.

use deform_shared::live::{LiveParams, MAX_TOOL_NODES};
use deform_shared::protocol::{SolveParams, SolveReport, Start, VectorSlot};

use crate::encode::{encode_with, EncodeOptions};
use crate::link::{LinkError, Port, Target, UpdateReport, UploadProgress};
use crate::live::link::LiveLink;
use crate::live::LiveSetup;
use crate::model::assembly::assemble_laplacian;
use crate::model::boundary::eliminate_fixed_nodes;
use crate::model::{Axis, Csr, Model};
use crate::reference::{self, max_abs, max_abs_diff};
use crate::refine::FIXED_POINT_FLOOR;

/// The time steps and how the loads follow them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Schedule {
    pub steps: u32,
    pub dt: f64,
}

impl Schedule {
    /// t of step `s` (1-based).
    pub fn time(&self, s: u32) -> f64 {
        s as f64 * self.dt
    }

    /// The fraction of the model's loads applied at time `t`: a linear ramp to 1 at the end.
    pub fn load_factor(&self, t: f64) -> f64 {
        let end = self.steps as f64 * self.dt;
        if end > 0.0 {
            (t / end).clamp(0.0, 1.0)
        } else {
            1.0
        }
    }
}

/// Displacement-dependent spring stiffness k̃ = α0 + α1·Σ_d Δl^d + α2·Σ_d (Δl^d)².
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Nonlinear {
    pub alpha: [f64; 3],
}

/// How to solve each step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepParams {
    pub warm_start: bool,
    /// Start from the target's prediction 2u(t−1) − u(t−2) ([`Start::Predicted`]) instead of
    /// the uploaded previous solution. Only with `fuse` and `warm_start`.
    pub predict: bool,
    /// Solve the three directions in one fused target run per step.
    pub fuse: bool,
    /// Target CG tolerance (relative recursive residual), floored at 1e-7.
    pub tol: f64,
    pub max_iterations: u32,
    /// Also solve each step with the f64 reference CG and report the deviation.
    pub check_reference: bool,
    /// How K is laid out over the MVUs. The displacement-dependent model never uses conjugate
    /// symmetry: its K is persymmetric only by accident, and a layout that switched between
    /// half and whole from step to step would defeat the values-only updates.
    pub layout: EncodeOptions,
}

impl StepParams {
    /// The target solve of a step: to the tolerance (floored at the fixed-point floor), no
    /// cycle budget.
    fn solve(&self, start: Start, directions: u8) -> SolveParams {
        SolveParams {
            max_iterations: self.max_iterations,
            tolerance: self.tol.max(FIXED_POINT_FLOOR),
            start,
            directions,
            cycle_budget: 0,
        }
    }
}

/// What one step produced.
#[derive(Debug, Clone)]
pub struct StepResult {
    pub step: u32,
    pub t: f64,
    /// Target CG iterations, summed over the three directions (fused too: the fused loop's own
    /// count is each report's `iterations`).
    pub iterations: u32,
    /// The target's report of each solve this step made (one per direction with a load), with
    /// its cycle and instruction counters; none for a superposed step (see [`simulate_with`]).
    pub reports: Vec<SolveReport>,
    /// The step's cycles on the target's critical path: its solves' (`whole_solve`), or a
    /// superposed step's frame cycles (the first also carrying the response columns' solve).
    pub cycles: u64,
    /// Largest true relative residual ‖b − K·u‖/‖b‖ over the directions.
    pub residual: f64,
    pub max_u: f64,
    /// max |u − u_ref| / max |u_ref| against the f64 reference, if asked.
    pub deviation: Option<f64>,
    /// Nonlinear model: how K reached the target this step (`None`: full upload).
    pub update: Option<UpdateReport>,
    pub u: [Vec<f64>; 3],
}

#[derive(Debug, thiserror::Error)]
pub enum SimulateError {
    #[error(transparent)]
    Link(#[from] LinkError),
    #[error(transparent)]
    Update(#[from] crate::link::UpdateError),
    #[error("encoding K: {0}")]
    Encode(#[from] crate::encode::EncodeError),
    #[error("assembling K: {0}")]
    Assembly(#[from] crate::model::assembly::AssemblyError),
    #[error("f64 reference: {0}")]
    Reference(#[from] reference::SolveError),
    #[error("the displacement-dependent model does not support prescribed displacements yet")]
    PrescribedNonlinear,
    #[error("the model at t = {t}: {source}")]
    StepModel {
        t: f64,
        source: crate::model::ModelError,
    },
    #[error(
        "the model at t = {0} has another matrix (other fixed or prescribed nodes) than the first"
    )]
    MatrixChanged(f64),
    #[error("setting up the superposed steps: {0}")]
    Setup(#[from] crate::live::SetupError),
}

/// The model at time t, for [`simulate_with`].
pub type StepModel<'a> = &'a dyn Fn(f64) -> Result<Model, crate::model::ModelError>;

/// K for the nonlinear model after displacements `u` (fixed nodes eliminated).
pub fn nonlinear_matrix(
    model: &Model,
    alpha: [f64; 3],
    u: &[Vec<f64>; 3],
) -> Result<Csr, SimulateError> {
    let stiffness = |a: usize, b: usize| {
        let dl = [u[0][b] - u[0][a], u[1][b] - u[1][a], u[2][b] - u[2][a]];
        alpha[0]
            + alpha[1] * dl.iter().sum::<f64>()
            + alpha[2] * dl.iter().map(|d| d * d).sum::<f64>()
    };
    let free = assemble_laplacian(model.grid(), model.spec().connection, &stiffness)?;
    Ok(eliminate_fixed_nodes(&free, model.fixed_mask()))
}

/// Runs the series on `target` with `model`'s loads ramped linearly, calling `on_upload` while
/// a whole matrix streams and `on_step` after every step (for progress bars and output).
pub fn simulate<P: Port>(
    target: &mut Target<P>,
    model: &Model,
    schedule: Schedule,
    nonlinear: Option<Nonlinear>,
    params: StepParams,
    on_upload: impl FnMut(UploadProgress),
    on_step: impl FnMut(&StepResult),
) -> Result<Vec<StepResult>, SimulateError> {
    simulate_with(
        target, model, schedule, None, nonlinear, params, on_upload, on_step,
    )
}

/// Like [`simulate`], but with `step_model` given the loads and prescribed displacements of
/// each step come from `step_model(t)` (whose matrix must equal `model`'s) instead of a ramp.
#[allow(clippy::too_many_arguments)]
pub fn simulate_with<P: Port>(
    target: &mut Target<P>,
    model: &Model,
    schedule: Schedule,
    step_model: Option<StepModel>,
    nonlinear: Option<Nonlinear>,
    params: StepParams,
    mut on_upload: impl FnMut(UploadProgress),
    mut on_step: impl FnMut(&StepResult),
) -> Result<Vec<StepResult>, SimulateError> {
    if nonlinear.is_some() && model.prescribed_count() > 0 {
        return Err(SimulateError::PrescribedNonlinear);
    }
    if let Some(step_model) =
        step_model.filter(|f| superposable(model, schedule, *f, nonlinear, &params))
    {
        return simulate_superposed(
            target, model, schedule, step_model, params, on_upload, on_step,
        );
    }
    let n = model.n();
    let mut previous: [Vec<f64>; 3] = [vec![0.0; n], vec![0.0; n], vec![0.0; n]];
    let mut results = Vec::new();
    if nonlinear.is_none() {
        let encoding = encode_with(model.unit_matrix(), &params.layout)?;
        target.upload_matrix_with_progress(&encoding.matrix, &mut on_upload)?;
    }
    for s in 1..=schedule.steps {
        let t = schedule.time(s);
        let at_t = match step_model {
            None => None,
            Some(f) => {
                let m = f(t).map_err(|source| SimulateError::StepModel { t, source })?;
                if m.unit_matrix() != model.unit_matrix() {
                    return Err(SimulateError::MatrixChanged(t));
                }
                Some(m)
            }
        };
        // The ramp, or the step's own model at full value.
        let (factor, step) = match &at_t {
            None => (schedule.load_factor(t), model),
            Some(m) => (1.0, m),
        };
        let (k, update, rhs): (Csr, Option<UpdateReport>, Vec<Vec<f64>>) = match nonlinear {
            None => (
                model.unit_matrix().clone(),
                None,
                Axis::ALL
                    .iter()
                    .map(|&d| step.scaled_rhs(d).iter().map(|b| b * factor).collect())
                    .collect(),
            ),
            Some(Nonlinear { alpha }) => {
                let k = nonlinear_matrix(model, alpha, &previous)?;
                let layout = EncodeOptions {
                    use_symmetry: false,
                    ..params.layout
                };
                let encoded = encode_with(&k, &layout)?.matrix;
                let update = if target.pattern_matches(&encoded) {
                    Some(target.update_values(&encoded)?)
                } else {
                    target.upload_matrix_with_progress(&encoded, &mut on_upload)?;
                    None
                };
                let rhs = Axis::ALL
                    .iter()
                    .map(|&d| step.load(d).iter().map(|f| f * factor).collect())
                    .collect();
                (k, update, rhs)
            }
        };
        let mut result = StepResult {
            step: s,
            t,
            iterations: 0,
            reports: Vec::new(),
            cycles: 0,
            residual: 0.0,
            max_u: 0.0,
            deviation: None,
            update,
            u: Default::default(),
        };
        let solutions = if params.fuse {
            solve_fused_step(target, &rhs, &previous, s, params, &mut result)?
        } else {
            solve_step_separately(target, &rhs, &previous, params, &mut result)?
        };
        result.cycles = crate::refine::critical_path_cycles(&result.reports);
        check_step(&mut result, &k, &rhs, solutions, params.check_reference)?;
        previous = result.u.clone();
        on_step(&result);
        results.push(result);
    }
    Ok(results)
}

/// Takes a step's solutions into `result` with their true relative residual against K (`k`)
/// and the right-hand sides, and, if asked, their deviation from the f64 reference.
fn check_step(
    result: &mut StepResult,
    k: &Csr,
    rhs: &[Vec<f64>],
    solutions: Vec<Vec<f64>>,
    check_reference: bool,
) -> Result<(), SimulateError> {
    let n = k.n();
    let mut deviation: Option<f64> = None;
    for ((d, b), x) in Axis::ALL.iter().zip(rhs).zip(solutions) {
        if max_abs(b) > 0.0 {
            result.residual = result.residual.max(reference::relative_residual(k, b, &x));
            if check_reference {
                let want = reference::solve(k, b, None, 1e-12, 10 * n.max(100))?;
                let scale = max_abs(&want.x);
                let dev = max_abs_diff(&x, &want.x) / if scale > 0.0 { scale } else { 1.0 };
                deviation = Some(deviation.map_or(dev, |m| m.max(dev)));
            }
        }
        result.u[d.position()] = x;
    }
    result.deviation = deviation;
    result.max_u = result.u.iter().map(|v| max_abs(v)).fold(0.0, f64::max);
    Ok(())
}

/// Whether the series can run as superposed live frames ([`simulate_superposed`]): linear
/// springs, fused predicted warm steps, at most [`MAX_TOOL_NODES`] prescribed nodes, and every
/// step's loads the first model's (only the prescribed displacements move).
fn superposable(
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

/// The series as the live loop's frames ([`crate::live`]): the target solves one response
/// column per prescribed node once (`LiveStart`), then every step starts from the
/// superposition of those columns (exact for linear springs) and skips even the exact r₀
/// pass where its residual estimate allows; only the prescribed displacements go down per
/// step, and the solutions come up for the output. The extrapolation of [`Start::Predicted`]
/// stays the fallback where this does not apply ([`superposable`]).
fn simulate_superposed<P: Port>(
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
    let mut link = LiveLink::start(target, &setup, live_params)?;
    let mut start_cycles = link.model.cycles;
    let mut results = Vec::new();
    for s in 1..=schedule.steps {
        let t = schedule.time(s);
        let at_t = step_model(t).map_err(|source| SimulateError::StepModel { t, source })?;
        let tool: Vec<[f64; 3]> = setup
            .tools
            .iter()
            .map(|&p| at_t.prescribed()[p].unwrap_or([0.0; 3]))
            .collect();
        let frame = link.frame(&tool)?;
        let solutions = link.solution()?.to_vec();
        let rhs: Vec<Vec<f64>> = Axis::ALL.iter().map(|&d| at_t.scaled_rhs(d)).collect();
        let mut result = StepResult {
            step: s,
            t,
            iterations: u32::from(frame.iterations),
            reports: Vec::new(),
            cycles: u64::from(frame.cycles) + std::mem::take(&mut start_cycles),
            residual: 0.0,
            max_u: 0.0,
            deviation: None,
            update: None,
            u: Default::default(),
        };
        check_step(
            &mut result,
            at_t.unit_matrix(),
            &rhs,
            solutions,
            params.check_reference,
        )?;
        on_step(&result);
        results.push(result);
    }
    Ok(results)
}

/// One target run for all three directions of a step (a zero right-hand side gives 0 on the
/// target too), warm-started as `params` says: predicted on the target, or from `previous`.
fn solve_fused_step<P: Port>(
    target: &mut Target<P>,
    rhs: &[Vec<f64>],
    previous: &[Vec<f64>; 3],
    step: u32,
    params: StepParams,
    result: &mut StepResult,
) -> Result<Vec<Vec<f64>>, SimulateError> {
    let warm = params.warm_start && step > 1;
    let start = if !warm {
        Start::Zero
    } else if params.predict {
        Start::Predicted
    } else {
        for (d, u) in previous.iter().enumerate() {
            let slot = VectorSlot::InitialGuess { direction: d as u8 };
            target.upload_vector(slot, u)?;
        }
        Start::Uploaded
    };
    let solve = params.solve(start, rhs.len() as u8);
    let rhs: Vec<&[f64]> = rhs.iter().map(Vec::as_slice).collect();
    let (report, x) = target.solve_fused(&rhs, solve)?;
    result.iterations += report.directions.iter().map(|d| d.iterations).sum::<u32>();
    result.reports.push(report);
    Ok(x)
}

/// One target solve per loaded direction (direction 0 each), warm-started from the previous
/// step's uploaded solution.
fn solve_step_separately<P: Port>(
    target: &mut Target<P>,
    rhs: &[Vec<f64>],
    previous: &[Vec<f64>; 3],
    params: StepParams,
    result: &mut StepResult,
) -> Result<Vec<Vec<f64>>, SimulateError> {
    let mut out = Vec::new();
    for (b, prev) in rhs.iter().zip(previous) {
        if max_abs(b) == 0.0 {
            out.push(vec![0.0; b.len()]);
            continue;
        }
        let start = if params.warm_start && max_abs(prev) > 0.0 {
            target.upload_vector(VectorSlot::INITIAL_GUESS, prev)?;
            Start::Uploaded
        } else {
            Start::Zero
        };
        let (report, x) = target.solve_for(b, params.solve(start, 1))?;
        result.iterations += report.iterations;
        result.reports.push(report);
        out.push(x);
    }
    Ok(out)
}
