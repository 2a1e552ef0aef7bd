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

pub mod plan;
pub mod run;
pub mod sink;
mod superposed;

use deform_shared::protocol::{SolveParams, Start, VectorSlot};

pub use crate::series::{Schedule, StepModel, StepResult};

use crate::board::WireBytes;
use crate::encode::{encode_with, EncodeOptions};
use crate::link::{LinkError, Port, Target, UpdateReport, UploadProgress};
use crate::model::assembly::assemble_laplacian;
use crate::model::boundary::eliminate_fixed_nodes;
use crate::model::{Axis, Csr, Model};
use crate::reference::{self, max_abs, max_abs_diff};
use deform_shared::qformat::FIXED_POINT_FLOOR;

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
/// A SIGINT or SIGTERM ends the series after the step under way ([`crate::interrupt`]).
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
        step_model.filter(|f| superposed::superposable(model, schedule, *f, nonlinear, &params))
    {
        return superposed::simulate_superposed(
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
        if crate::interrupt::requested() {
            break;
        }
        let t = schedule.time(s);
        let before = WireBytes::of(&target.stats());
        let at_t = model_at(model, step_model, t)?;
        // The ramp, or the step's own model at full value.
        let (factor, step) = match &at_t {
            None => (schedule.load_factor(t), model),
            Some(m) => (1.0, m),
        };
        let system = match nonlinear {
            None => StepSystem::linear(model, step, factor),
            Some(Nonlinear { alpha }) => StepSystem::nonlinear(
                target,
                model,
                step,
                factor,
                alpha,
                &previous,
                &params,
                &mut on_upload,
            )?,
        };
        let mut result = StepResult {
            step: s,
            t,
            iterations: 0,
            reports: Vec::new(),
            cycles: 0,
            superposed: false,
            residual: 0.0,
            max_u: 0.0,
            deviation: None,
            update: system.update,
            bytes: WireBytes::default(),
            u: Default::default(),
        };
        let solutions = if params.fuse {
            solve_fused_step(target, &system.rhs, &previous, s, params, &mut result)?
        } else {
            solve_step_separately(target, &system.rhs, &previous, params, &mut result)?
        };
        system.check(solutions, params.check_reference, &mut result)?;
        result.cycles = crate::refine::critical_path_cycles(&result.reports);
        result.bytes = WireBytes::of(&target.stats()).since(before);
        previous.clone_from(&result.u);
        on_step(&result);
        results.push(result);
    }
    Ok(results)
}

/// The model at `t` from `step_model`, checked to keep `model`'s matrix (`None`: no
/// keyframes, the ramp applies).
fn model_at(
    model: &Model,
    step_model: Option<StepModel>,
    t: f64,
) -> Result<Option<Model>, SimulateError> {
    let Some(f) = step_model else {
        return Ok(None);
    };
    let m = f(t).map_err(|source| SimulateError::StepModel { t, source })?;
    if m.unit_matrix() != model.unit_matrix() {
        return Err(SimulateError::MatrixChanged(t));
    }
    Ok(Some(m))
}

/// One step's system: the matrix its residual is measured with, how it reached the target
/// and the right-hand sides.
struct StepSystem<'m> {
    k: std::borrow::Cow<'m, Csr>,
    update: Option<UpdateReport>,
    rhs: Vec<Vec<f64>>,
}

impl<'m> StepSystem<'m> {
    /// The resident K and `step`'s loads at `factor` (scaled by 1/k_d: the unit matrix).
    fn linear(model: &'m Model, step: &Model, factor: f64) -> Self {
        StepSystem {
            k: std::borrow::Cow::Borrowed(model.unit_matrix()),
            update: None,
            rhs: Axis::ALL
                .iter()
                .map(|&d| step.scaled_rhs(d).iter().map(|b| b * factor).collect())
                .collect(),
        }
    }

    /// K after the `previous` displacements, sent as values only where its pattern allows.
    #[allow(clippy::too_many_arguments)]
    fn nonlinear<P: Port>(
        target: &mut Target<P>,
        model: &Model,
        step: &Model,
        factor: f64,
        alpha: [f64; 3],
        previous: &[Vec<f64>; 3],
        params: &StepParams,
        on_upload: &mut impl FnMut(UploadProgress),
    ) -> Result<Self, SimulateError> {
        let k = nonlinear_matrix(model, alpha, previous)?;
        let layout = EncodeOptions {
            use_symmetry: false,
            ..params.layout
        };
        let encoded = encode_with(&k, &layout)?.matrix;
        let update = if target.pattern_matches(&encoded) {
            Some(target.update_values(&encoded)?)
        } else {
            target.upload_matrix_with_progress(&encoded, on_upload)?;
            None
        };
        let rhs = Axis::ALL
            .iter()
            .map(|&d| step.load(d).iter().map(|f| f * factor).collect())
            .collect();
        Ok(StepSystem {
            k: std::borrow::Cow::Owned(k),
            update,
            rhs,
        })
    }

    /// Puts the step's `solutions` into `result` with their true residual, its largest |u|
    /// and, if asked, the deviation from the f64 reference.
    fn check(
        &self,
        solutions: Vec<Vec<f64>>,
        check_reference: bool,
        result: &mut StepResult,
    ) -> Result<(), SimulateError> {
        let n = self.k.n();
        let mut deviation: Option<f64> = None;
        for ((d, b), x) in Axis::ALL.iter().zip(&self.rhs).zip(solutions) {
            if max_abs(b) > 0.0 {
                result.residual = result
                    .residual
                    .max(reference::relative_residual(&self.k, b, &x));
                if check_reference {
                    let want = reference::solve(&self.k, b, None, 1e-12, 10 * n.max(100))?;
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
