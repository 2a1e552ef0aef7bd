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
use super::step::{advance, rhs, Forcing, Loads, State, StepMatrices};
use super::system::DynamicSystem;
use crate::board::WireBytes;
use crate::encode::{encode_with, EncodeError, EncodeOptions, EncodedMatrix};
use crate::link::{LinkError, Port, Target, UpdateError, UpdateReport, UploadProgress};
use crate::model::{Axis, Model, ModelError};
use crate::precondition::Scaled;
use crate::reference::{self, max_abs, max_abs_diff, norm};
use crate::refine::{critical_path_cycles, solve_refined, RefineError, RefineParams};
use crate::series::{Schedule, StepModel, StepResult};

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
    /// What every time series reports (u per direction, iterations, the target's reports,
    /// cycles, bytes: vectors, solves, solutions, acknowledgements and any matrix update).
    pub result: StepResult,
    /// Kinetic + elastic energy after the step.
    pub energy: f64,
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

/// A dynamic model for one step h: M, C and K, and the step matrices S. Built once: the
/// checks before a board opens, the target's runner and the f64 stepper all take this one.
#[derive(Debug, Clone)]
pub struct DynamicModel {
    pub system: DynamicSystem,
    pub matrices: StepMatrices,
}

impl DynamicModel {
    /// Assembles the model; checks the masses, dampers and h.
    pub fn new(model: &Model, spec: &DynamicsSpec, h: f64) -> Result<Self, DynamicsError> {
        let system = DynamicSystem::new(model, spec)?;
        let matrices = StepMatrices::new(&system, h, spec.scheme)?;
        Ok(Self { system, matrices })
    }

    /// Like [`DynamicModel::new`], and checks that the target's fixed point can hold every
    /// S: run before a board is opened.
    pub fn for_target(model: &Model, spec: &DynamicsSpec, h: f64) -> Result<Self, DynamicsError> {
        let built = Self::new(model, spec, h)?;
        for g in &built.matrices.groups {
            check_representable(built.matrices.matrix(g[0]), built.system.mass(), h)?;
        }
        Ok(built)
    }
}

/// A dynamic model on a target: the step matrices of the current h, which of them the target
/// holds, and the state (plus the f64 reference's, if checked). `deform simulate --dynamic`
/// drives it over a schedule; an interactive loop can call [`DynamicRunner::step`] with the
/// loads it has and change h with [`DynamicRunner::set_time_step`] (a values-only update).
pub struct DynamicRunner {
    system: DynamicSystem,
    matrices: StepMatrices,
    encoded: Vec<(EncodedMatrix, Scaled)>,
    /// The group of `encoded` the target holds (`None`: nothing uploaded yet).
    resident: Option<usize>,
    params: DynamicParams,
    pub state: State,
    /// The f64 stepper's state, run alongside when `params.check_reference`.
    pub reference: State,
}

impl DynamicRunner {
    /// Assembles M, C, K and S for step `h`, checks S against the fixed point and encodes it.
    /// Nothing is sent until the first step.
    pub fn new(
        model: &Model,
        spec: &DynamicsSpec,
        h: f64,
        params: DynamicParams,
    ) -> Result<Self, DynamicRunError> {
        Self::from_model(DynamicModel::new(model, spec, h)?, params)
    }

    /// The runner of a model already built (see [`DynamicModel`]).
    pub fn from_model(built: DynamicModel, params: DynamicParams) -> Result<Self, DynamicRunError> {
        let DynamicModel { system, matrices } = built;
        let encoded = encode_groups(&system, &matrices, &params.layout)?;
        let state = State::rest(system.n());
        Ok(Self {
            reference: state.clone(),
            state,
            system,
            matrices,
            encoded,
            resident: None,
            params,
        })
    }

    pub fn system(&self) -> &DynamicSystem {
        &self.system
    }

    /// The step h.
    pub fn h(&self) -> f64 {
        self.matrices.h
    }

    /// A new step length: S's values change, its pattern does not, so the next step sends
    /// the values only (`BeginUpdate`/`UpdateValues`/`EndUpdate`).
    pub fn set_time_step(&mut self, h: f64) -> Result<(), DynamicRunError> {
        let matrices = StepMatrices::new(&self.system, h, self.matrices.scheme)?;
        self.encoded = encode_groups(&self.system, &matrices, &self.params.layout)?;
        self.matrices = matrices;
        if self.resident.is_some() {
            // Whatever the target holds is stale; any group's pattern is the same.
            self.resident = Some(usize::MAX);
        }
        Ok(())
    }

    /// New masses, dampers or springs (the same grid, network and constrained nodes), keeping
    /// the state: S's pattern is K's, so the next step sends S's values only.
    pub fn set_model(&mut self, model: &Model, spec: &DynamicsSpec) -> Result<(), DynamicRunError> {
        let system = DynamicSystem::new(model, spec)?;
        if system.n() != self.system.n() || system.constrained() != self.system.constrained() {
            return Err(DynamicRunError::MatrixChanged(self.state.t));
        }
        let matrices = StepMatrices::new(&system, self.matrices.h, spec.scheme)?;
        self.encoded = encode_groups(&system, &matrices, &self.params.layout)?;
        self.system = system;
        self.matrices = matrices;
        if self.resident.is_some() {
            self.resident = Some(usize::MAX);
        }
        Ok(())
    }

    /// Makes the target hold group `gi`'s S: a full upload the first time, values after.
    fn make_resident<P: Port>(
        &mut self,
        target: &mut Target<P>,
        gi: usize,
        on_upload: &mut impl FnMut(UploadProgress),
    ) -> Result<Option<UpdateReport>, DynamicRunError> {
        let update = match self.resident {
            Some(r) if r == gi => None,
            Some(_) => Some(target.update_values(&self.encoded[gi].0)?),
            None => {
                target.upload_matrix_with_progress(&self.encoded[gi].0, on_upload)?;
                None
            }
        };
        self.resident = Some(gi);
        Ok(update)
    }

    /// One step from the loads `loads0` at t to `loads1` at t + h; the result carries the new
    /// displacements (a copy of [`DynamicRunner::state`]'s).
    pub fn step<P: Port>(
        &mut self,
        target: &mut Target<P>,
        step: u32,
        loads0: &Loads,
        loads1: &Loads,
        on_upload: impl FnMut(UploadProgress),
    ) -> Result<DynamicStep, DynamicRunError> {
        let mut out = self.advance(target, step, loads0, loads1, on_upload)?;
        out.result.u = self.state.u.clone();
        Ok(out)
    }

    /// [`DynamicRunner::step`] without the copy of u: read it from [`DynamicRunner::state`].
    pub fn advance<P: Port>(
        &mut self,
        target: &mut Target<P>,
        step: u32,
        loads0: &Loads,
        loads1: &Loads,
        mut on_upload: impl FnMut(UploadProgress),
    ) -> Result<DynamicStep, DynamicRunError> {
        let forcing = loads0.to(loads1);
        let before = WireBytes::of(&target.stats());
        let mut v1: [Vec<f64>; 3] = Default::default();
        let mut reports: Vec<SolveReport> = Vec::new();
        let (mut iterations, mut residual) = (0u32, 0.0f64);
        let mut update: Option<UpdateReport> = None;
        for gi in 0..self.matrices.groups.len() {
            update = self.make_resident(target, gi, &mut on_upload)?.or(update);
            let (m, system, state) = (&self.matrices, &self.system, &self.state);
            let group = &m.groups[gi];
            let scaled = &self.encoded[gi].1;
            let s_matrix = &scaled.matrix;
            let b: Vec<Vec<f64>> = group
                .iter()
                .map(|&d| rhs(system, m, state, &forcing, d))
                .collect();
            // The prediction v₁ ≈ v₀: solve for the correction from the residual.
            let r: Vec<Vec<f64>> = group
                .iter()
                .zip(&b)
                .map(|(&d, b)| reference::residual(s_matrix, b, &state.v[d.position()]))
                .collect();
            let tol = correction_tolerance(self.params.tol, &b, &r);
            let refs: Vec<&[f64]> = r.iter().map(Vec::as_slice).collect();
            let refined = solve_refined(
                target,
                s_matrix,
                scaled,
                &refs,
                RefineParams {
                    tol: tol.min(0.5),
                    max_solves: self.params.max_solves,
                    max_iterations: self.params.max_iterations,
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
        self.state = advance(&self.system, &self.matrices, &self.state, v1, &forcing);
        let deviation = self.check_reference(&forcing)?;
        Ok(DynamicStep {
            energy: self.system.energy(&self.state.u, &self.state.v),
            result: StepResult {
                step,
                t: self.state.t,
                iterations,
                cycles: critical_path_cycles(&reports),
                superposed: false,
                reports,
                residual,
                max_u: self.state.u.iter().map(|u| max_abs(u)).fold(0.0, f64::max),
                deviation,
                update,
                bytes: WireBytes::of(&target.stats()).since(before),
                u: Default::default(),
            },
        })
    }

    /// With the check on, the host's f64 stepper's same step, and how far the target's u is
    /// from its u, relative to its max |u|.
    fn check_reference(&mut self, forcing: &Forcing<'_>) -> Result<Option<f64>, DynamicRunError> {
        if !self.params.check_reference {
            return Ok(None);
        }
        self.reference = host_step(&self.system, &self.matrices, &self.reference, forcing)?;
        let scale = self
            .reference
            .u
            .iter()
            .map(|u| max_abs(u))
            .fold(0.0, f64::max);
        let diff = Axis::ALL
            .iter()
            .map(|d| max_abs_diff(&self.state.u[d.position()], &self.reference.u[d.position()]))
            .fold(0.0, f64::max);
        Ok(Some(if scale > 0.0 { diff / scale } else { diff }))
    }
}

/// Runs `schedule.steps` steps of `schedule.dt` (the step `built` was made for) from rest on
/// `target`.
#[allow(clippy::too_many_arguments)]
pub fn simulate_dynamic<P: Port>(
    target: &mut Target<P>,
    model: &Model,
    step_model: Option<StepModel>,
    schedule: Schedule,
    built: DynamicModel,
    params: DynamicParams,
    mut on_upload: impl FnMut(UploadProgress),
    mut on_step: impl FnMut(&DynamicStep),
) -> Result<Vec<DynamicStep>, DynamicRunError> {
    let mut runner = DynamicRunner::from_model(built, params)?;
    let mut loads0 = model_at(model, step_model, 0.0)?;
    let mut out = Vec::new();
    for s in 1..=schedule.steps {
        if crate::interrupt::requested() {
            break;
        }
        let loads1 = model_at(model, step_model, schedule.time(s))?;
        let step = runner.step(target, s, &loads0, &loads1, &mut on_upload)?;
        on_step(&step);
        out.push(step);
        loads0 = loads1;
    }
    Ok(out)
}

/// The tolerance of the correction's solve that gives each direction's v₁ its step tolerance
/// `tol`·‖b‖: the tightest over the directions, relative to the start's residual r.
fn correction_tolerance(tol: f64, b: &[Vec<f64>], r: &[Vec<f64>]) -> f64 {
    b.iter()
        .zip(r)
        .filter(|(_, r)| norm(r) > 0.0)
        .map(|(b, r)| tol * norm(b) / norm(r))
        .fold(f64::INFINITY, f64::min)
}
