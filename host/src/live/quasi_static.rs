//! Quasi-static frames: each frame a fresh equilibrium for the tool's input, on a target over
//! the live protocol ([`TargetEngine`], K resident, a few dozen bytes a frame) or on the host
//! by the f64 reference CG ([`HostEngine`]).

use super::engine::{max_u, relative_error, Engine, Frame, Query};
use super::field::FieldChoice;
use super::link::{FieldFrame, LiveLink};
use super::LiveSetup;
use crate::link::Port;

/// Frames on a target. `checked`: read each frame's full solution back and compare it (and
/// each query) with a converged f64 solve of the same tool input, as the headless session
/// reports; unchecked (`--serve`) a frame moves only the frame and the field the page shows.
pub struct TargetEngine<'a, P: Port> {
    link: LiveLink<'a, P>,
    setup: &'a LiveSetup,
    checked: bool,
    /// The last frame's converged f64 solution: the next solves' warm start.
    warm: Option<[Vec<f64>; 3]>,
    /// The last frame's solution as read back (checked frames only).
    solution: Option<[Vec<f64>; 3]>,
}

impl<'a, P: Port> TargetEngine<'a, P> {
    pub fn new(link: LiveLink<'a, P>, setup: &'a LiveSetup, checked: bool) -> Self {
        Self {
            link,
            setup,
            checked,
            warm: None,
            solution: None,
        }
    }

    pub fn link(&self) -> &LiveLink<'a, P> {
        &self.link
    }
}

impl<P: Port> Engine for TargetEngine<'_, P> {
    fn name(&self) -> &'static str {
        "target"
    }

    fn frame(&mut self, frame: u32, t: f64, tool: &[[f64; 3]]) -> anyhow::Result<Frame> {
        let start = self.link.wire();
        let answer = self.link.frame(tool)?;
        let bytes = self.link.wire().since(start);
        let mut out = Frame {
            frame,
            t,
            tool: tool.to_vec(),
            answer: answer.value.map(f64::from),
            residual: f64::from(answer.residual),
            iterations: u32::from(answer.iterations),
            cycles: Some(u64::from(answer.cycles)),
            instructions: Some(u64::from(answer.instructions)),
            bytes,
            ..Frame::default()
        };
        if self.checked {
            let u = self.link.solution()?;
            let (want, reference) = self.setup.converged(tool, self.warm.as_ref())?;
            out.reference = reference;
            out.error_vs_converged = Some(relative_error(&u, &want, max_u(&want)));
            out.max_u = max_u(&u);
            self.solution = Some(u);
            self.warm = Some(want);
        }
        Ok(out)
    }

    fn solution(&self) -> Option<&[Vec<f64>; 3]> {
        self.solution.as_ref()
    }

    fn query(&mut self, tool: &[[f64; 3]]) -> anyhow::Result<Option<Query>> {
        let start = self.link.wire();
        let answer = self.link.force(tool)?;
        let bytes = self.link.wire().since(start);
        let (_, reference) = self.setup.converged(tool, self.warm.as_ref())?;
        Ok(Some(Query {
            answer: answer.value.map(f64::from),
            reference,
            cycles: answer.cycles,
            instructions: answer.instructions,
            bytes,
        }))
    }

    fn field(&mut self, choice: FieldChoice) -> anyhow::Result<Option<FieldFrame>> {
        Ok(Some(self.link.field(choice)?))
    }

    fn resets(&self) -> u32 {
        self.link.resets
    }

    fn retransmits(&self) -> u64 {
        self.link.retransmits()
    }

    fn model_report(&self) -> Option<deform_shared::live::ModelReport> {
        Some(self.link.model)
    }
}

/// Frames by the f64 reference alone (`--target host`): each the converged solve of its tool
/// input, warm-started from the previous frame's. No target figures.
pub struct HostEngine<'a> {
    setup: &'a LiveSetup,
    solution: Option<[Vec<f64>; 3]>,
}

impl<'a> HostEngine<'a> {
    pub fn new(setup: &'a LiveSetup) -> Self {
        Self {
            setup,
            solution: None,
        }
    }
}

impl Engine for HostEngine<'_> {
    fn name(&self) -> &'static str {
        "host"
    }

    fn frame(&mut self, frame: u32, t: f64, tool: &[[f64; 3]]) -> anyhow::Result<Frame> {
        let (u, answer) = self.setup.converged(tool, self.solution.as_ref())?;
        let max_u = max_u(&u);
        self.solution = Some(u);
        Ok(Frame {
            frame,
            t,
            tool: tool.to_vec(),
            answer,
            reference: answer,
            max_u,
            ..Frame::default()
        })
    }

    fn solution(&self) -> Option<&[Vec<f64>; 3]> {
        self.solution.as_ref()
    }
}
