//! The live engine: one trait for everything that solves frames, quasi-static or dynamic, on a
//! target or on the host. The headless session ([`super::session`]), `--serve`
//! ([`super::interactive`]) and the tests drive any of them the same way; what differs between
//! them (the live protocol or whole vectors on the line, the f64 reference alongside or as the
//! answer, a local model between frames or none) stays inside each engine:
//!
//! | engine | frames | check |
//! |---|---|---|
//! | [`super::quasi_static::TargetEngine`] | `LiveFrame`/`LiveLoad` on a target | a converged f64 solve per frame |
//! | [`super::quasi_static::HostEngine`] | the converged f64 solve itself | none (it is the reference) |
//! | [`super::dynamic::DynamicLive`] | one step h, on a target (whole vectors) or the host | the f64 stepper alongside |
//! | [`super::resident::ResidentEngine`] | one step h formed on the target (`DynamicFrame`: the tool's motion up, its force down) | the f64 stepper alongside |
//!
//! A new kind of frame is a new engine; the sessions, the sink and the reports do not change.

use super::field::FieldChoice;
use super::link::FieldFrame;
use crate::board::WireBytes;

/// One solved frame, as every engine reports it.
#[derive(Debug, Clone, Default)]
pub struct Frame {
    pub frame: u32,
    /// The frame's time (a dynamic frame: the step's end, frame·h).
    pub t: f64,
    /// The tool's input: displacements, or loads for a force tool.
    pub tool: Vec<[f64; 3]>,
    /// The answer: the reaction force, or a force tool's mean displacement (a dynamic frame:
    /// the force holding the tool on its path).
    pub answer: [f64; 3],
    /// The same from the f64 reference (on the host: the answer itself).
    pub reference: [f64; 3],
    /// The solve's relative residual (0 where the host's f64 solve is the answer).
    pub residual: f64,
    /// CG iterations (a fused solve over x, y, z counted once for a dynamic frame).
    pub iterations: u32,
    /// Target solves of the frame (dynamic frames refine; 0 on the host).
    pub solves: u32,
    /// The target's cycles for the frame (`None` on the host).
    pub cycles: Option<u64>,
    /// The retired instructions counted as `cycles` is (equal to it under QEMU `-icount`).
    pub instructions: Option<u64>,
    /// Hart 0's `mcycle` over a dynamic frame's solves (real cycles on the LiteX SoC).
    pub hart0_cycles: Option<u64>,
    /// max |u − u_ref| / max |u_ref| against the f64 reference (`None` where the frame is the
    /// reference, or nothing was checked).
    pub error_vs_converged: Option<f64>,
    /// max |u − u_ref| itself (dynamic frames: near rest the relative error is large).
    pub error_abs: Option<f64>,
    /// Bytes on the line for the frame (framing and retransmissions included).
    pub bytes: WireBytes,
    /// Largest |u| of the frame's solution.
    pub max_u: f64,
    /// What a dynamic tissue does besides its shape: `None` for a quasi-static frame.
    pub motion: Option<Motion>,
}

/// A dynamic frame's motion after its step.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Motion {
    /// Largest |v|: how far the tissue is from rest.
    pub max_v: f64,
    /// Kinetic + elastic energy.
    pub energy: f64,
}

/// A query of the local model between frames, and its check.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Query {
    /// The model's answer (force, or a force tool's motion).
    pub answer: [f64; 3],
    /// A converged f64 solve's at the same tool input.
    pub reference: [f64; 3],
    pub cycles: u32,
    /// The retired instructions counted as `cycles` is.
    pub instructions: u32,
    pub bytes: WireBytes,
}

/// What solves the frames of a live session.
pub trait Engine {
    /// Who solves, as the page and the reports name it.
    fn name(&self) -> &'static str;

    /// A dynamic engine's step h (each frame advances the tissue by h); `None`: quasi-static.
    fn step(&self) -> Option<f64> {
        None
    }

    /// Solves frame number `frame` at time `t` with the tool at `tool`.
    fn frame(&mut self, frame: u32, t: f64, tool: &[[f64; 3]]) -> anyhow::Result<Frame>;

    /// The last frame's full solution, per direction, where the engine holds it (a target
    /// engine serving a page does not read it back).
    fn solution(&self) -> Option<&[Vec<f64>; 3]>;

    /// A query of the local model with the tool at `tool`; `None`: the engine has none.
    fn query(&mut self, _tool: &[[f64; 3]]) -> anyhow::Result<Option<Query>> {
        Ok(None)
    }

    /// The last frame's field as the line carries it (quantised, at the nodes `choice`
    /// selects); `None` where the whole field is at hand (the host, dynamic frames).
    fn field(&mut self, _choice: FieldChoice) -> anyhow::Result<Option<FieldFrame>> {
        Ok(None)
    }

    /// What building a quasi-static target's local model cost (`None`: no such model).
    fn model_report(&self) -> Option<deform_shared::live::ModelReport> {
        None
    }

    /// Times the target reset and was set up again.
    fn resets(&self) -> u32 {
        0
    }

    /// Frames the host sent again so far (a loaded host or a noisy line): the byte counts
    /// leave them out, so the report says how many there were.
    fn retransmits(&self) -> u64 {
        0
    }
}

/// max over directions of max |a − b|, relative to `scale` (a tiny scale counts as 1e-308).
pub fn relative_error(a: &[Vec<f64>; 3], b: &[Vec<f64>; 3], scale: f64) -> f64 {
    use crate::reference::max_abs_diff;
    (0..3)
        .map(|d| max_abs_diff(&a[d], &b[d]))
        .fold(0.0, f64::max)
        / scale.max(f64::MIN_POSITIVE)
}

/// Largest |u| over the three directions.
pub fn max_u(u: &[Vec<f64>; 3]) -> f64 {
    u.iter()
        .map(|v| crate::reference::max_abs(v))
        .fold(0.0, f64::max)
}
