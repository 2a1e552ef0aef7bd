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
//! ([`host_step`]) is the answer itself.

use std::time::{Duration, Instant};

use super::interactive::{FrameSolver, ViewFrame};
use crate::dynamics::host::host_step;
use crate::dynamics::target::{DynamicParams, DynamicRunner};
use crate::dynamics::{DynamicSystem, DynamicsSpec, Loads, State, StepMatrices};
use crate::link::{Port, Target};
use crate::model::{Axis, Model};
use crate::reference::{max_abs, max_abs_diff};

/// One dynamic frame: the state after the step, its checks and what it cost.
#[derive(Debug, Clone)]
pub struct DynamicFrame {
    pub frame: u32,
    /// The step's end time, frame·h.
    pub t: f64,
    pub tool: Vec<[f64; 3]>,
    pub u: [Vec<f64>; 3],
    /// The force holding the tool on its path (see [`tool_force`]).
    pub force: [f64; 3],
    /// The same from the f64 stepper's state.
    pub force_reference: [f64; 3],
    pub max_u: f64,
    /// Kinetic + elastic energy after the step.
    pub energy: f64,
    /// Largest |v| after the step: how far the tissue is from rest.
    pub max_v: f64,
    /// Target CG iterations of the step, a fused solve over x, y, z counted once (0 on the
    /// host).
    pub iterations: u32,
    /// Target solves (mixed-precision refinement rounds) of the step (0 on the host).
    pub solves: u32,
    /// Critical-path cycles of the step's target solves (`None` on the host): the target's
    /// `whole_solve` counts, which are instructions retired (`minstret`) on every board, so
    /// cycles only at CPI 1 (QEMU `-icount`), not on the LiteX SoC.
    pub cycles: Option<u64>,
    /// Hart 0's `mcycle` over the solves' MVU and SVU phases: the RTL's cycles on the LiteX
    /// SoC (one hart); under QEMU with several harts the machine-wide count (their sum).
    pub hart0_cycles: Option<u64>,
    /// True relative residual ‖b − S·v₁‖/‖b‖ of the step's solve (0 on the host).
    pub residual: f64,
    /// max |u − u_ref| / max |u_ref| against the f64 stepper run alongside from rest with the
    /// same tool positions (`None` on the host, which *is* the f64 stepper).
    pub error_vs_reference: Option<f64>,
    /// max |u − u_ref| itself: near rest max |u_ref| is small and the relative error large.
    pub error_abs: Option<f64>,
    /// Bytes written to / read from the port for the step, framing and retransmissions
    /// included (the link's own count, as the quasi-static frames' wire counter; the first
    /// frame's include S).
    pub bytes_up: u64,
    pub bytes_down: u64,
}

/// The target half of a dynamic session.
struct OnTarget<'t, P: Port> {
    runner: DynamicRunner,
    target: &'t mut Target<P>,
}

/// A dynamic live session: the tissue at rest at t = 0, stepped one h per frame. (`P`, the
/// target's port, defaults to a serial port so that a host-only session can be named
/// `<DynamicLive>::host`.)
pub struct DynamicLive<'t, P: Port = Box<dyn serialport::SerialPort>> {
    system: DynamicSystem,
    matrices: StepMatrices,
    on_target: Option<OnTarget<'t, P>>,
    /// The f64 stepper's state: the reference with a target, the answer without.
    reference: State,
    tools: Vec<usize>,
    /// The loads with the tool at rest; frames replace the tool nodes' displacements.
    base: Loads,
    /// The loads of the last frame (the next step's start).
    loads: Loads,
    frame: u32,
}

impl<'t, P: Port> DynamicLive<'t, P> {
    /// Steps `model` (its `tools` the prescribed nodes, at rest) on the host's f64 stepper.
    pub fn host(
        model: &Model,
        tools: &[usize],
        spec: &DynamicsSpec,
        h: f64,
    ) -> anyhow::Result<Self> {
        let system = DynamicSystem::new(model, spec)?;
        let matrices = StepMatrices::new(&system, h, spec.scheme)?;
        let base = Loads::of(model);
        Ok(Self {
            reference: State::rest(system.n()),
            system,
            matrices,
            on_target: None,
            tools: tools.to_vec(),
            loads: base.clone(),
            base,
            frame: 0,
        })
    }

    /// Steps on `target`, which is sent S at the first frame and keeps it; the f64 stepper
    /// runs alongside.
    pub fn on_target(
        model: &Model,
        tools: &[usize],
        spec: &DynamicsSpec,
        h: f64,
        params: DynamicParams,
        target: &'t mut Target<P>,
    ) -> anyhow::Result<Self> {
        let mut live = Self::host(model, tools, spec, h)?;
        let params = DynamicParams {
            check_reference: true,
            ..params
        };
        live.on_target = Some(OnTarget {
            runner: DynamicRunner::new(model, spec, h, params)?,
            target,
        });
        Ok(live)
    }

    pub fn h(&self) -> f64 {
        self.matrices.h
    }

    /// The loads of a frame: the base loads with the tool nodes at `tool`.
    fn loads_with(&self, tool: &[[f64; 3]]) -> Loads {
        let mut loads = self.base.clone();
        for (&node, u) in self.tools.iter().zip(tool) {
            loads.prescribed[node] = Some(*u);
        }
        loads
    }

    /// Advances the tissue one step h with the tool at `tool` at the step's end.
    pub fn frame(&mut self, tool: &[[f64; 3]]) -> anyhow::Result<DynamicFrame> {
        self.frame += 1;
        let loads1 = self.loads_with(tool);
        let (h, frame) = (self.h(), self.frame);
        let forcing = self.loads.to(&loads1);
        let out = match self.on_target.as_mut() {
            None => {
                let next = host_step(&self.system, &self.matrices, &self.reference, &forcing)?;
                let force = tool_force(
                    &self.system,
                    h,
                    &self.tools,
                    &self.reference,
                    &next,
                    &loads1,
                );
                self.reference = next;
                let s = &self.reference;
                DynamicFrame {
                    force_reference: force,
                    ..describe(&self.system, frame, tool, s, force)
                }
            }
            Some(t) => {
                let (start, start_ref) = (t.runner.state.clone(), t.runner.reference.clone());
                let step = t
                    .runner
                    .step(t.target, frame, &self.loads, &loads1, |_| {})?;
                let (s, r) = (&t.runner.state, &t.runner.reference);
                let force = tool_force(&self.system, h, &self.tools, &start, s, &loads1);
                DynamicFrame {
                    force_reference: tool_force(
                        &self.system,
                        h,
                        &self.tools,
                        &start_ref,
                        r,
                        &loads1,
                    ),
                    iterations: step.result.reports.iter().map(|r| r.iterations).sum(),
                    solves: step.result.reports.len() as u32,
                    cycles: Some(step.cycles),
                    hart0_cycles: Some(
                        step.result
                            .reports
                            .iter()
                            .map(|r| r.mvu.cycles + r.svu.cycles)
                            .sum(),
                    ),
                    residual: step.result.residual,
                    error_vs_reference: step.result.deviation,
                    error_abs: Some(
                        (0..3)
                            .map(|d| max_abs_diff(&s.u[d], &r.u[d]))
                            .fold(0.0, f64::max),
                    ),
                    bytes_up: step.bytes_sent,
                    bytes_down: step.bytes_received,
                    ..describe(&self.system, frame, tool, s, force)
                }
            }
        };
        self.loads = loads1;
        Ok(out)
    }
}

/// The frame's state-derived fields; the solve's figures left empty.
fn describe(
    system: &DynamicSystem,
    frame: u32,
    tool: &[[f64; 3]],
    s: &State,
    force: [f64; 3],
) -> DynamicFrame {
    DynamicFrame {
        frame,
        t: s.t,
        tool: tool.to_vec(),
        u: s.u.clone(),
        force,
        force_reference: force,
        max_u: s.u.iter().map(|u| max_abs(u)).fold(0.0, f64::max),
        energy: system.energy(&s.u, &s.v),
        max_v: s.v.iter().map(|v| max_abs(v)).fold(0.0, f64::max),
        iterations: 0,
        solves: 0,
        cycles: None,
        hart0_cycles: None,
        residual: 0.0,
        error_vs_reference: None,
        error_abs: None,
        bytes_up: 0,
        bytes_down: 0,
    }
}

/// The force the tool exerts to keep its nodes on their path over the step from `s0` to `s1`:
/// the equation of motion's imbalance at the tool nodes, Σ_t (M·(v₁ − v₀)/h + C·v₁ + K·u₁ − f₁)_t
/// per direction. Without masses and dampers it is the quasi-static reaction Σ_t (K·u)_t.
pub fn tool_force(
    system: &DynamicSystem,
    h: f64,
    tools: &[usize],
    s0: &State,
    s1: &State,
    loads1: &Loads,
) -> [f64; 3] {
    Axis::ALL.map(|d| {
        let p = d.position();
        let (k, c) = (system.stiffness(d), system.damping(d));
        tools
            .iter()
            .map(|&t| {
                let (kc, kv) = k.row(t);
                let ku: f64 = kc.iter().zip(kv).map(|(&j, &v)| v * s1.u[p][j]).sum();
                let (cc, cv) = c.row(t);
                let cv1: f64 = cc.iter().zip(cv).map(|(&j, &v)| v * s1.v[p][j]).sum();
                let inertia = system.mass()[t] * (s1.v[p][t] - s0.v[p][t]) / h;
                inertia + cv1 + ku - loads1.f[p][t]
            })
            .sum()
    })
}

/// `--serve` on a dynamic scenario: each frame is one step h with the tool where the browser
/// has it. Frames are paced to the wall clock (one h of tissue time per h of wall time at
/// most), so the tissue moves at its own speed, and they go on while the tool rests, so the
/// user sees the tissue relax.
pub struct DynamicViewSolver<'t, P: Port> {
    pub live: DynamicLive<'t, P>,
    next_at: Option<Instant>,
}

impl<'t, P: Port> DynamicViewSolver<'t, P> {
    pub fn new(live: DynamicLive<'t, P>) -> Self {
        Self {
            live,
            next_at: None,
        }
    }
}

impl<P: Port> FrameSolver for DynamicViewSolver<'_, P> {
    fn solve(&mut self, tool: &[[f64; 3]]) -> anyhow::Result<ViewFrame> {
        if let Some(wait) = self
            .next_at
            .map(|at| at.saturating_duration_since(Instant::now()))
        {
            std::thread::sleep(wait);
        }
        let started = Instant::now();
        let f = self.live.frame(tool)?;
        self.next_at = Some(started + Duration::from_secs_f64(self.live.h()));
        Ok(ViewFrame {
            force: f.force,
            u: (0..f.u[0].len())
                .map(|i| [f.u[0][i], f.u[1][i], f.u[2][i]])
                .collect(),
            iterations: f.iterations,
            cycles: f.cycles.map(|c| c.min(u64::from(u32::MAX)) as u32),
            residual: f.residual,
        })
    }

    fn name(&self) -> &'static str {
        if self.live.on_target.is_some() {
            "target (dynamic)"
        } else {
            "host (dynamic)"
        }
    }

    fn keeps_moving(&self) -> bool {
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::encode::EncodeOptions;
    use crate::live::LiveSetup;
    use crate::model::prescribed::PrescribedDisplacement;
    use crate::model::{Connection, Elasticity, Grid, ModelSpec, Node};

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
        let mut live = <DynamicLive>::host(&setup.model, &setup.tools, &spec, 0.05).unwrap();
        let tool = [[0.1, 0.0, -0.5]];
        let first = live.frame(&tool).unwrap();
        let (want, force) = setup.converged(&tool, None).unwrap();
        // The first step lags the tool: the tissue has not followed yet.
        assert!(first.u[2]
            .iter()
            .zip(&want[2])
            .any(|(a, b)| (a - b).abs() > 1e-2));
        let mut last = first;
        for _ in 0..400 {
            last = live.frame(&tool).unwrap();
        }
        let scale = want.iter().map(|u| max_abs(u)).fold(0.0, f64::max);
        for d in 0..3 {
            assert!(
                max_abs_diff(&last.u[d], &want[d]) <= 1e-6 * scale,
                "direction {d}"
            );
            assert!(
                (last.force[d] - force[d]).abs() <= 1e-6 * force[2].abs(),
                "{d}"
            );
        }
        assert!(last.max_v < 1e-6, "{}", last.max_v);
        assert!((last.t - 401.0 * 0.05).abs() < 1e-9);
    }
}
