//! Dynamic frames (issue 14 in the live loop): when the scenario is dynamic, each frame of
//! `deform live` advances the tissue by one time step h with the tool's displacement at that
//! frame, so the tissue lags the tool, overshoots and relaxes after the tool has left, which
//! quasi-static frames (a fresh equilibrium per frame) cannot show.
//!
//! The step itself is [`crate::dynamics`]'s, unchanged: the host holds u and v in f64 and forms
//! each step's right-hand side; the target keeps S = M + h·C + h²·K resident and solves
//! S·v₁ = b by mixed-precision refinement from the prediction v₁ ≈ v₀
//! ([`DynamicRunner::step`], as `deform simulate --dynamic` does). No frame message of the
//! sparse protocol is used, so every frame carries whole vectors (the residual up, the
//! correction down): its bytes are reported as they are, not as the tens of bytes of a
//! quasi-static frame. Without a target ([`DynamicLive::host`]) the f64 stepper
//! ([`host_step`]) is the answer itself. Where the target can form the steps itself (backward
//! Euler, isotropic tissue, a uniform mass, no external loads) a session runs
//! [`super::resident::ResidentEngine`] instead, whose frames are a few dozen bytes.

use super::engine::{max_u, Engine, Frame, Motion};
use crate::dynamics::host::host_step;
use crate::dynamics::target::{DynamicModel, DynamicParams, DynamicRunner};
use crate::dynamics::{DynamicSystem, Loads, State};
use crate::link::{Port, Target};
use crate::model::{Axis, Model};
use crate::reference::max_abs_diff;

/// Who steps the tissue. (Both variants boxed: each holds a whole model's matrices.)
enum Stepper<'t, P: Port> {
    /// The f64 stepper is the answer.
    Host {
        built: Box<DynamicModel>,
        state: State,
    },
    /// The target solves each step, the f64 stepper runs alongside in the runner.
    Target {
        runner: Box<DynamicRunner>,
        target: &'t mut Target<P>,
    },
}

/// A dynamic live session: the tissue at rest at t = 0, stepped one h per frame. The model is
/// built once ([`DynamicModel`], also what was checked before the board opened); a frame's
/// loads are the base loads with the tool nodes' displacements written in, into one of two
/// buffers that swap each frame. (`P`, the target's port, defaults to a serial port so that a
/// host-only session can be named `<DynamicLive>::host`.)
pub struct DynamicLive<'t, P: Port = Box<dyn serialport::SerialPort>> {
    stepper: Stepper<'t, P>,
    tools: Vec<usize>,
    /// The loads at the last frame's end (the next step's start), and the buffer the next
    /// frame's go into.
    loads0: Loads,
    loads1: Loads,
}

impl<'t, P: Port> DynamicLive<'t, P> {
    /// Steps `model` (its `tools` the prescribed nodes, at rest) on the host's f64 stepper.
    pub fn host(model: &Model, tools: &[usize], built: DynamicModel) -> Self {
        let state = State::rest(built.system.n());
        let built = Box::new(built);
        Self::with(model, tools, Stepper::Host { built, state })
    }

    /// Steps on `target`, which is sent S at the first frame and keeps it; the f64 stepper
    /// runs alongside.
    pub fn on_target(
        model: &Model,
        tools: &[usize],
        built: DynamicModel,
        params: DynamicParams,
        target: &'t mut Target<P>,
    ) -> anyhow::Result<Self> {
        let params = DynamicParams {
            check_reference: true,
            ..params
        };
        let runner = DynamicRunner::from_model(built, params)?;
        Ok(Self::with(
            model,
            tools,
            Stepper::Target {
                runner: Box::new(runner),
                target,
            },
        ))
    }

    fn with(model: &Model, tools: &[usize], stepper: Stepper<'t, P>) -> Self {
        let base = Loads::of(model);
        Self {
            stepper,
            tools: tools.to_vec(),
            loads1: base.clone(),
            loads0: base,
        }
    }

    pub fn h(&self) -> f64 {
        match &self.stepper {
            Stepper::Host { built, .. } => built.matrices.h,
            Stepper::Target { runner, .. } => runner.h(),
        }
    }

    fn system(&self) -> &DynamicSystem {
        match &self.stepper {
            Stepper::Host { built, .. } => &built.system,
            Stepper::Target { runner, .. } => runner.system(),
        }
    }

    /// The state after the last frame.
    pub fn state(&self) -> &State {
        match &self.stepper {
            Stepper::Host { state, .. } => state,
            Stepper::Target { runner, .. } => &runner.state,
        }
    }

    /// Advances the tissue one step h with the tool at `tool` at the step's end.
    pub fn advance(&mut self, frame: u32, tool: &[[f64; 3]]) -> anyhow::Result<Frame> {
        for (&node, u) in self.tools.iter().zip(tool) {
            self.loads1.prescribed[node] = Some(*u);
        }
        let h = self.h();
        let (loads0, loads1, tools) = (&self.loads0, &self.loads1, &self.tools);
        let mut out = match &mut self.stepper {
            Stepper::Host { built, state } => {
                let v0 = tool_velocities(tools, state);
                let forcing = loads0.to(loads1);
                *state = host_step(&built.system, &built.matrices, state, &forcing)?;
                let force = tool_force(&built.system, h, tools, &v0, state, loads1);
                Frame {
                    answer: force,
                    reference: force,
                    ..Frame::default()
                }
            }
            Stepper::Target { runner, target } => {
                let (v0, v0_ref) = (
                    tool_velocities(tools, &runner.state),
                    tool_velocities(tools, &runner.reference),
                );
                let step = runner.advance(target, frame, loads0, loads1, |_| {})?;
                let (s, r, system) = (&runner.state, &runner.reference, runner.system());
                let reports = &step.result.reports;
                Frame {
                    answer: tool_force(system, h, tools, &v0, s, loads1),
                    reference: tool_force(system, h, tools, &v0_ref, r, loads1),
                    iterations: reports.iter().map(|r| r.iterations).sum(),
                    solves: reports.len() as u32,
                    cycles: Some(step.result.cycles),
                    hart0_cycles: Some(reports.iter().map(|r| r.mvu.cycles + r.svu.cycles).sum()),
                    residual: step.result.residual,
                    error_vs_converged: step.result.deviation,
                    error_abs: Some(
                        (0..3)
                            .map(|d| max_abs_diff(&s.u[d], &r.u[d]))
                            .fold(0.0, f64::max),
                    ),
                    bytes: step.result.bytes,
                    ..Frame::default()
                }
            }
        };
        std::mem::swap(&mut self.loads0, &mut self.loads1);
        let s = self.state();
        out.frame = frame;
        out.t = s.t;
        out.tool = tool.to_vec();
        out.max_u = max_u(&s.u);
        out.motion = Some(Motion {
            max_v: max_u(&s.v),
            energy: self.system().energy(&s.u, &s.v),
        });
        Ok(out)
    }
}

impl<P: Port> Engine for DynamicLive<'_, P> {
    fn name(&self) -> &'static str {
        match self.stepper {
            Stepper::Target { .. } => "target (dynamic)",
            Stepper::Host { .. } => "host (dynamic)",
        }
    }

    fn step(&self) -> Option<f64> {
        Some(self.h())
    }

    /// The step's end time is frame·h, whatever `t` says.
    fn frame(&mut self, frame: u32, _t: f64, tool: &[[f64; 3]]) -> anyhow::Result<Frame> {
        self.advance(frame, tool)
    }

    fn solution(&self) -> Option<&[Vec<f64>; 3]> {
        Some(&self.state().u)
    }
}

/// The tool nodes' velocities in `state`: all of the start state a tool force needs.
pub(super) fn tool_velocities(tools: &[usize], state: &State) -> Vec<[f64; 3]> {
    tools
        .iter()
        .map(|&t| [0, 1, 2].map(|p| state.v[p][t]))
        .collect()
}

/// The force the tool exerts to keep its nodes on their path over a step that started with
/// the tool nodes' velocities `v0` and ended in `s1`: the equation of motion's imbalance at the
/// tool nodes, Σ_t (M·(v₁ − v₀)/h + C·v₁ + K·u₁ − f₁)_t per direction. Without masses and
/// dampers it is the quasi-static reaction Σ_t (K·u)_t.
pub fn tool_force(
    system: &DynamicSystem,
    h: f64,
    tools: &[usize],
    v0: &[[f64; 3]],
    s1: &State,
    loads1: &Loads,
) -> [f64; 3] {
    Axis::ALL.map(|d| {
        let p = d.position();
        let (k, c) = (system.stiffness(d), system.damping(d));
        tools
            .iter()
            .zip(v0)
            .map(|(&t, v0)| {
                let (kc, kv) = k.row(t);
                let ku: f64 = kc.iter().zip(kv).map(|(&j, &v)| v * s1.u[p][j]).sum();
                let (cc, cv) = c.row(t);
                let cv1: f64 = cc.iter().zip(cv).map(|(&j, &v)| v * s1.v[p][j]).sum();
                let inertia = system.mass()[t] * (s1.v[p][t] - v0[p]) / h;
                inertia + cv1 + ku - loads1.f[p][t]
            })
            .sum()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dynamics::DynamicsSpec;
    use crate::encode::EncodeOptions;
    use crate::live::LiveSetup;
    use crate::model::prescribed::PrescribedDisplacement;
    use crate::model::{Connection, Elasticity, Grid, ModelSpec, Node};
    use crate::reference::max_abs;

    /// A 5³ model-B block on a fixed base, the tip at the centre of the top face.
    fn needle() -> ModelSpec {
        ModelSpec {
            grid: Grid::new(5, 5, 5).unwrap(),
            connection: Connection::AxialShear,
            fixed_sets: vec!["z-".parse().unwrap()],
            elasticity: Elasticity::isotropic(2.0).unwrap(),
            prescribed: vec![PrescribedDisplacement {
                node: Node { i: 2, j: 2, k: 4 },
                u: [0.0; 3],
            }],
            loads: Vec::new(),
            ..ModelSpec::thesis_example()
        }
    }

    /// Held long enough, a damped dynamic frame comes to the quasi-static one: the same field
    /// and the same reaction force at the tool (inertia and damper forces gone with v).
    #[test]
    fn a_held_tool_settles_to_the_quasi_static_frame() {
        let setup = LiveSetup::new(&needle(), &EncodeOptions::default()).unwrap();
        let spec = DynamicsSpec {
            rayleigh: Some([20.0, 0.0]),
            ..DynamicsSpec::uniform(0.01, [0.5; 3])
        };
        let built = DynamicModel::new(&setup.model, &spec, 0.05).unwrap();
        let mut live = <DynamicLive>::host(&setup.model, &setup.tools, built);
        let tool = [[0.1, 0.0, -0.5]];
        let first = live.advance(1, &tool).unwrap();
        let first_u = live.state().u.clone();
        let (want, force) = setup.converged(&tool, None).unwrap();
        // The first step lags the tool: the tissue has not followed yet.
        assert!(first_u[2]
            .iter()
            .zip(&want[2])
            .any(|(a, b)| (a - b).abs() > 1e-2));
        let mut last = first;
        for i in 2..=401 {
            last = live.advance(i, &tool).unwrap();
        }
        let last_u = &live.state().u;
        let scale = want.iter().map(|u| max_abs(u)).fold(0.0, f64::max);
        for d in 0..3 {
            assert!(
                max_abs_diff(&last_u[d], &want[d]) <= 1e-6 * scale,
                "direction {d}"
            );
            assert!(
                (last.answer[d] - force[d]).abs() <= 1e-6 * force[2].abs(),
                "{d}"
            );
        }
        let max_v = last.motion.unwrap().max_v;
        assert!(max_v < 1e-6, "{max_v}");
        assert!((last.t - 401.0 * 0.05).abs() < 1e-9);
    }
}
