//! The dynamic series on the target: S uploaded once and kept resident, each step's
//! right-hand side formed on the host, S·v₁ = b solved by the target's CG with mixed-precision
//! refinement, every step optionally checked against the f64 stepper ([`super::host`]) run
//! alongside from the same start.
//!
//! Each solve starts from the prediction v₁ ≈ v₀: the target gets the residual b − S·v₀ and
//! returns the correction, which is what makes small steps cheap (v changes little per step).
//! Directions with equal S (isotropic tissue) share one fused target solve; anisotropic
//! tissue has one S per direction, swapped in by values-only updates, and its bytes show it.

use deform_shared::protocol::SolveReport;

use super::fixed_point::check_representable;
use super::host::host_step;
use super::params::{DynamicsError, DynamicsSpec};
use super::step::{advance, rhs, Loads, State, StepMatrices};
use super::system::DynamicSystem;
use crate::encode::{encode_with, EncodeError, EncodeOptions, EncodedMatrix};
use crate::link::{LinkError, Port, Target, UpdateError, UpdateReport, UploadProgress};
use crate::model::{Axis, Model, ModelError};
use crate::precondition::Scaled;
use crate::reference::{self, max_abs, max_abs_diff, norm};
use crate::refine::{critical_path_cycles, solve_refined, RefineError, RefineParams};
use crate::simulate::{Schedule, StepModel, StepResult};

/// How to solve each step.
#[derive(Debug, Clone, Copy)]
pub struct DynamicParams {
    /// True relative residual ‖b − S·v₁‖/‖b‖ every step's solve reaches (refined on the host).
    pub tol: f64,
    pub max_solves: u32,
    /// CG iterations allowed per target solve.
    pub max_iterations: u32,
    /// Run the f64 stepper alongside and report max |u − u_ref| / max |u_ref|.
    pub check_reference: bool,
    pub layout: EncodeOptions,
}

/// One step on the target.
#[derive(Debug, Clone)]
pub struct DynamicStep {
    /// What every time series reports (u per direction, iterations, the target's reports…).
    pub result: StepResult,
    /// Kinetic + elastic energy after the step.
    pub energy: f64,
    /// Bytes written to / read from the port during the step (vectors, solves, solutions,
    /// acknowledgements; any matrix update included).
    pub bytes_sent: u64,
    pub bytes_received: u64,
    /// Measured critical-path cycles of the step's solves (slowest MVU + SVU per iteration).
    pub cycles: u64,
}

#[derive(Debug, thiserror::Error)]
pub enum DynamicRunError {
    #[error(transparent)]
    Dynamics(#[from] DynamicsError),
    #[error(transparent)]
    Link(#[from] LinkError),
    #[error(transparent)]
    Update(#[from] UpdateError),
    #[error(transparent)]
    Refine(#[from] RefineError),
    #[error("encoding S: {0}")]
    Encode(#[from] EncodeError),
    #[error("f64 reference stepper: {0}")]
    Reference(#[from] reference::SolveError),
    #[error("the model at t = {t}: {source}")]
    StepModel { t: f64, source: ModelError },
    #[error(
        "the model at t = {0} has another matrix (other fixed or prescribed nodes) than the first"
    )]
    MatrixChanged(f64),
}

/// The model at `t`: the keyframed one, or `model` (whose loads then act from t = 0).
fn model_at(
    model: &Model,
    step_model: Option<StepModel>,
    t: f64,
) -> Result<Loads, DynamicRunError> {
    match step_model {
        None => Ok(Loads::of(model)),
        Some(f) => {
            let m = f(t).map_err(|source| DynamicRunError::StepModel { t, source })?;
            if m.unit_matrix() != model.unit_matrix() {
                return Err(DynamicRunError::MatrixChanged(t));
            }
            Ok(Loads::of(&m))
        }
    }
}

/// S of each direction group, checked against the fixed point and encoded.
fn encode_groups(
    system: &DynamicSystem,
    m: &StepMatrices,
    layout: &EncodeOptions,
) -> Result<Vec<(EncodedMatrix, Scaled)>, DynamicRunError> {
    m.groups
        .iter()
        .map(|g| {
            let s = m.matrix(g[0]);
            check_representable(s, system.mass(), m.h)?;
            Ok((
                encode_with(s, layout)?.matrix,
                Scaled {
                    matrix: s.clone(),
                    scale: None,
                },
            ))
        })
        .collect()
}

/// Runs `schedule.steps` steps of `schedule.dt` from rest on `target`.
#[allow(clippy::too_many_arguments)]
pub fn simulate_dynamic<P: Port>(
    target: &mut Target<P>,
    model: &Model,
    step_model: Option<StepModel>,
    schedule: Schedule,
    spec: &DynamicsSpec,
    params: DynamicParams,
    mut on_upload: impl FnMut(UploadProgress),
    mut on_step: impl FnMut(&DynamicStep),
) -> Result<Vec<DynamicStep>, DynamicRunError> {
    let system = DynamicSystem::new(model, spec)?;
    let m = StepMatrices::new(&system, schedule.dt, spec.scheme)?;
    let encoded = encode_groups(&system, &m, &params.layout)?;
    let mut resident: Option<usize> = None;
    let mut state = State::rest(system.n());
    let mut reference = state.clone();
    let mut loads0 = model_at(model, step_model, 0.0)?;
    let mut out = Vec::new();
    for s in 1..=schedule.steps {
        let t = schedule.time(s);
        let loads1 = model_at(model, step_model, t)?;
        let forcing = loads0.to(&loads1);
        let before = target.stats();
        let mut v1: [Vec<f64>; 3] = Default::default();
        let mut reports: Vec<SolveReport> = Vec::new();
        let (mut iterations, mut residual) = (0u32, 0.0f64);
        let mut update: Option<UpdateReport> = None;
        for (gi, group) in m.groups.iter().enumerate() {
            match resident {
                Some(r) if r == gi => {}
                Some(_) => update = Some(target.update_values(&encoded[gi].0)?),
                None => target.upload_matrix_with_progress(&encoded[gi].0, &mut on_upload)?,
            }
            resident = Some(gi);
            let scaled = &encoded[gi].1;
            let s_matrix = &scaled.matrix;
            let b: Vec<Vec<f64>> = group
                .iter()
                .map(|&d| rhs(&system, &m, &state, &forcing, d))
                .collect();
            // The prediction v₁ ≈ v₀: solve for the correction from the residual.
            let r: Vec<Vec<f64>> = group
                .iter()
                .zip(&b)
                .map(|(&d, b)| reference::residual(s_matrix, b, &state.v[d.position()]))
                .collect();
            let tol = b
                .iter()
                .zip(&r)
                .filter(|(_, r)| norm(r) > 0.0)
                .map(|(b, r)| params.tol * norm(b) / norm(r))
                .fold(f64::INFINITY, f64::min);
            let refs: Vec<&[f64]> = r.iter().map(Vec::as_slice).collect();
            let refined = solve_refined(
                target,
                s_matrix,
                scaled,
                &refs,
                RefineParams {
                    tol: tol.min(0.5),
                    max_solves: params.max_solves,
                    max_iterations: params.max_iterations,
                    fuse: true,
                },
            )?;
            for ((&d, b), dir) in group.iter().zip(&b).zip(&refined.directions) {
                let p = d.position();
                let v: Vec<f64> = state.v[p].iter().zip(&dir.x).map(|(a, c)| a + c).collect();
                if norm(b) > 0.0 {
                    residual = residual.max(reference::relative_residual(s_matrix, b, &v));
                }
                iterations += dir.iterations;
                v1[p] = v;
            }
            reports.extend(refined.reports);
        }
        state = advance(&system, &m, &state, v1, &forcing);
        let deviation = if params.check_reference {
            reference = host_step(&system, &m, &reference, &forcing)?;
            let scale = reference.u.iter().map(|u| max_abs(u)).fold(0.0, f64::max);
            let diff = Axis::ALL
                .iter()
                .map(|d| max_abs_diff(&state.u[d.position()], &reference.u[d.position()]))
                .fold(0.0, f64::max);
            Some(if scale > 0.0 { diff / scale } else { diff })
        } else {
            None
        };
        let after = target.stats();
        let step = DynamicStep {
            energy: system.energy(&state.u, &state.v),
            bytes_sent: after.bytes_sent - before.bytes_sent,
            bytes_received: after.bytes_received - before.bytes_received,
            cycles: critical_path_cycles(&reports),
            result: StepResult {
                step: s,
                t,
                iterations,
                reports,
                residual,
                max_u: state.u.iter().map(|u| max_abs(u)).fold(0.0, f64::max),
                deviation,
                update,
                u: state.u.clone(),
            },
        };
        on_step(&step);
        out.push(step);
        loads0 = loads1;
    }
    Ok(out)
}
