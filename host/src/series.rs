//! A time series' vocabulary, shared by the quasi-static series ([`crate::simulate`]) and the
//! elastodynamic one ([`crate::dynamics`]): the schedule of steps, the model at a time, and
//! what a step produced.

use deform_shared::protocol::SolveReport;

use crate::board::WireBytes;
use crate::link::UpdateReport;
use crate::model::Model;

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

/// The model at time t: a scenario's keyframes evaluated at t (`simulate_with`,
/// `simulate_dynamic`).
pub type StepModel<'a> = &'a dyn Fn(f64) -> Result<Model, crate::model::ModelError>;

/// What one step produced.
#[derive(Debug, Clone, Default)]
pub struct StepResult {
    pub step: u32,
    pub t: f64,
    /// Target CG iterations, summed over the three directions (fused too: the fused loop's own
    /// count is each report's `iterations`).
    pub iterations: u32,
    /// The target's report of each solve this step made (one per direction with a load), with
    /// its cycle and instruction counters.
    pub reports: Vec<SolveReport>,
    /// Critical-path cycles of the step's solves, as the target measured them
    /// ([`crate::refine::critical_path_cycles`]), or a superposed step's frame cycles (the
    /// first step's also carrying the response columns' solve).
    pub cycles: u64,
    /// The step ran as a superposed live frame (`crate::simulate`'s prescribed-tool series:
    /// no solve reports, the frame's own cycles and iterations).
    pub superposed: bool,
    /// Bytes the step moved on the line, both ways (any matrix upload or update included).
    pub bytes: WireBytes,
    /// Largest true relative residual ‖b − K·u‖/‖b‖ over the directions.
    pub residual: f64,
    pub max_u: f64,
    /// max |u − u_ref| / max |u_ref| against the f64 reference, if asked.
    pub deviation: Option<f64>,
    /// Nonlinear model: how K reached the target this step (`None`: full upload).
    pub update: Option<UpdateReport>,
    pub u: [Vec<f64>; 3],
}
