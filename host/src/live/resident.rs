//! Target-resident dynamic frames (issue 19 item 3, protocol version 12): the target keeps u
//! and v and forms each step's right-hand side b = M·v₀ − h·K·u₀ (with the tool's rows) itself,
//! so a frame carries only the tool's displacements up and the force holding the tool on its
//! path down, a few dozen bytes each way ([`crate::dynamics::resident`]). The host's f64
//! stepper runs alongside as the check and gives each frame's reference force; a checked frame
//! (the headless session) also reads u back, outside the frame's bytes, and reports its error.
//! The page's field (`--serve`) is the step's u as the target's compact field frames carry it,
//! as for quasi-static frames ([`read_field`]).
//!
//! It applies where the target's step is the host's ([`ResidentSetup::new`]: backward Euler,
//! isotropic tissue, a uniform nodal mass) and no external load acts (the tool drives the
//! tissue); elsewhere the session runs [`super::dynamic::DynamicLive`] on the target, whose
//! frames carry whole vectors.

use super::dynamic::{tool_force, tool_velocities};
use super::engine::{max_u, relative_error, Engine, Frame, Motion};
use super::field::FieldChoice;
use super::link::{read_field, FieldFrame};
use crate::dynamics::host::host_step;
use crate::dynamics::resident::{ResidentError, ResidentSetup};
use crate::dynamics::target::DynamicModel;
use crate::dynamics::{Loads, State};
use crate::encode::EncodeOptions;
use crate::link::{LinkError, Port, Target};
use crate::model::{Axis, Grid, Model};
use crate::reference::max_abs_diff;

/// Why a dynamic session's frames are not formed on the target.
#[derive(Debug, thiserror::Error)]
pub enum ResidentRefusal {
    #[error("external loads act on the tissue: the target's step has the tool alone")]
    Loads,
    #[error(transparent)]
    Setup(#[from] ResidentError),
}

/// How a resident session solves its steps.
#[derive(Debug, Clone, Copy)]
pub struct ResidentParams {
    /// Relative residual every step's solve reaches on the target (verified there).
    pub tol: f64,
    pub max_iterations: u32,
    /// Cycles a step's solve may take, 0 for none.
    pub cycle_budget: u64,
    pub layout: EncodeOptions,
}

/// A dynamic live session whose steps the target forms and solves.
pub struct ResidentEngine<'t, P: Port> {
    target: &'t mut Target<P>,
    built: DynamicModel,
    tools: Vec<usize>,
    grid: Grid,
    /// Read each frame's u back and hold it against the f64 stepper.
    checked: bool,
    /// The f64 stepper's state (the check) and its loads at the last frame's end, with the
    /// buffer the next frame's go into.
    reference: State,
    loads0: Loads,
    loads1: Loads,
    /// The last frame's u as read back (checked frames only).
    solution: Option<[Vec<f64>; 3]>,
}

/// The set-up for `model` (its `tools` the prescribed nodes, at rest) stepped by `built`,
/// or why the target cannot form its frames.
pub fn resident_setup(
    model: &Model,
    tools: &[usize],
    built: &DynamicModel,
    params: &ResidentParams,
) -> Result<ResidentSetup, ResidentRefusal> {
    if Axis::ALL
        .iter()
        .any(|&d| model.load(d).iter().any(|&f| f != 0.0))
    {
        return Err(ResidentRefusal::Loads);
    }
    Ok(ResidentSetup::new(
        &built.system,
        &built.matrices,
        tools,
        &params.layout,
        params.tol,
        params.max_iterations,
        params.cycle_budget,
    )?)
}

impl<'t, P: Port> ResidentEngine<'t, P> {
    /// Uploads `setup` to `target` and starts the session at rest.
    pub fn start(
        model: &Model,
        tools: &[usize],
        built: DynamicModel,
        setup: &ResidentSetup,
        target: &'t mut Target<P>,
        checked: bool,
    ) -> Result<Self, LinkError> {
        setup.start(target)?;
        let base = Loads::of(model);
        Ok(Self {
            target,
            reference: State::rest(built.system.n()),
            built,
            tools: tools.to_vec(),
            grid: model.grid(),
            checked,
            loads1: base.clone(),
            loads0: base,
            solution: None,
        })
    }

    fn h(&self) -> f64 {
        self.built.matrices.h
    }

    /// The f64 stepper's step to `loads1` and the force it needs at the tool.
    fn reference_step(&mut self) -> anyhow::Result<[f64; 3]> {
        let (system, matrices) = (&self.built.system, &self.built.matrices);
        let v0 = tool_velocities(&self.tools, &self.reference);
        let forcing = self.loads0.to(&self.loads1);
        self.reference = host_step(system, matrices, &self.reference, &forcing)?;
        Ok(tool_force(
            system,
            matrices.h,
            &self.tools,
            &v0,
            &self.reference,
            &self.loads1,
        ))
    }
}

impl<P: Port> Engine for ResidentEngine<'_, P> {
    fn name(&self) -> &'static str {
        "target (dynamic, resident)"
    }

    fn step(&self) -> Option<f64> {
        Some(self.h())
    }

    /// One step h with the tool at `tool` at its end; the step's end time is frame·h.
    fn frame(&mut self, frame: u32, _t: f64, tool: &[[f64; 3]]) -> anyhow::Result<Frame> {
        for (&node, u) in self.tools.iter().zip(tool) {
            self.loads1.prescribed[node] = Some(*u);
        }
        let start = crate::board::WireBytes::of(&self.target.stats());
        let report = ResidentSetup::frame(self.target, tool)?;
        let bytes = crate::board::WireBytes::of(&self.target.stats()).since(start);
        let reference = self.reference_step()?;
        std::mem::swap(&mut self.loads0, &mut self.loads1);
        let r = &self.reference;
        let mut out = Frame {
            frame,
            t: r.t,
            tool: tool.to_vec(),
            answer: report.force.map(f64::from),
            reference,
            residual: f64::from(report.residual),
            iterations: u32::from(report.iterations),
            solves: 1,
            cycles: Some(u64::from(report.cycles)),
            // The target's own count of the whole frame: on a one-hart board (the LiteX SoC)
            // hart 0's `mcycle`; with several MVUs the solve at its critical path.
            hart0_cycles: Some(u64::from(report.cycles)),
            bytes,
            max_u: max_u(&r.u),
            // The target keeps v; the stepper it is checked against gives the motion.
            motion: Some(Motion {
                max_v: max_u(&r.v),
                energy: self.built.system.energy(&r.u, &r.v),
            }),
            ..Frame::default()
        };
        if self.checked {
            let n = self.built.system.n();
            let mut u: [Vec<f64>; 3] = Default::default();
            for (d, ud) in u.iter_mut().enumerate() {
                *ud = self.target.read_direction_solution(d as u8, n)?;
            }
            out.error_vs_converged = Some(relative_error(&u, &r.u, max_u(&r.u)));
            out.error_abs = Some(
                (0..3)
                    .map(|d| max_abs_diff(&u[d], &r.u[d]))
                    .fold(0.0, f64::max),
            );
            out.max_u = max_u(&u);
            self.solution = Some(u);
        }
        Ok(out)
    }

    fn solution(&self) -> Option<&[Vec<f64>; 3]> {
        self.solution.as_ref()
    }

    fn field(&mut self, choice: FieldChoice) -> anyhow::Result<Option<FieldFrame>> {
        let n = self.built.system.n() as u32;
        Ok(Some(read_field(self.target, &self.grid, n, choice)?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dynamics::{DynamicsSpec, Scheme};
    use crate::live::LiveSetup;
    use crate::model::loads::PointLoad;
    use crate::model::prescribed::PrescribedDisplacement;
    use crate::model::{Connection, Elasticity, Grid, ModelSpec, Node};

    /// A 4³ model-B block on a fixed base, the tool at the centre of the top face.
    fn needle(loads: Vec<PointLoad>) -> ModelSpec {
        ModelSpec {
            grid: Grid::new(4, 4, 4).unwrap(),
            connection: Connection::AxialShear,
            fixed_sets: vec!["z-".parse().unwrap()],
            elasticity: Elasticity::isotropic(2.0).unwrap(),
            prescribed: vec![PrescribedDisplacement {
                node: Node { i: 2, j: 2, k: 3 },
                u: [0.0; 3],
            }],
            loads,
            ..ModelSpec::thesis_example()
        }
    }

    fn params() -> ResidentParams {
        ResidentParams {
            tol: 1e-4,
            max_iterations: 100,
            cycle_budget: 0,
            layout: EncodeOptions::default(),
        }
    }

    /// The target forms backward-Euler steps of a tool-driven tissue; loads or another scheme
    /// send the session to host-formed frames.
    #[test]
    fn the_target_forms_the_steps_only_where_its_step_is_the_hosts() {
        let spec = DynamicsSpec::uniform(0.01, [0.5; 3]);
        let formed = |spec: &DynamicsSpec, loads: Vec<PointLoad>| {
            let setup = LiveSetup::new(&needle(loads), &EncodeOptions::default()).unwrap();
            let built = DynamicModel::new(&setup.model, spec, 1e-3).unwrap();
            resident_setup(&setup.model, &setup.tools, &built, &params())
        };
        let ok = formed(&spec, Vec::new()).unwrap();
        assert_eq!(ok.tools.len(), 1);
        assert!(ok.params.s_scale < 0, "S is scaled up into the value field");
        let load = PointLoad {
            node: Node { i: 1, j: 1, k: 3 },
            force: [0.0, 0.0, -1.0],
        };
        assert!(matches!(
            formed(&spec, vec![load]),
            Err(ResidentRefusal::Loads)
        ));
        let trapezoidal = DynamicsSpec {
            scheme: Scheme::Trapezoidal,
            ..spec.clone()
        };
        assert!(matches!(
            formed(&trapezoidal, Vec::new()),
            Err(ResidentRefusal::Setup(ResidentError::Scheme(_)))
        ));
    }
}
