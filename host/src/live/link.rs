//! The live requests over a [`Target`]: set-up, frames, force queries and field chunks.
//!
//! A target that resets mid-session loses its matrix, tool set and static loads; the host
//! holds all of them ([`LiveSetup`]), so [`LiveLink`] shakes hands again, uploads them and
//! repeats the frame, counting the resets. Only the prediction's history is lost: the next two
//! frames start plainly.

use std::time::Duration;

use deform_shared::live::{FieldSelection, LiveParams, ModelReport, MAX_TOOL_NODES};
use deform_shared::protocol::{ErrorCode, Request, Response, VectorSlot};

use super::field::FieldChoice;
use super::setup::ToolKind;
use super::LiveSetup;
use crate::board::WireBytes;
use crate::link::{LinkError, Port, Target};
use crate::model::Grid;

/// A started live session on a target.
pub struct LiveLink<'a, P: Port> {
    target: &'a mut Target<P>,
    setup: &'a LiveSetup,
    params: LiveParams,
    /// Times the target reset and was set up again.
    pub resets: u32,
    /// What building the local force model cost, at the last set-up.
    pub model: ModelReport,
}

fn unexpected(request: &'static str, expected: &'static str, got: Response) -> LinkError {
    LinkError::Protocol {
        request,
        expected,
        got: format!("{got:?}"),
    }
}

/// A full frame's answer, of either kind of tool: the reaction force (N) of a displacement
/// tool (`LiveFrame`) or the mean tool displacement (m) of a force tool (`LiveMotion`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameAnswer {
    pub value: [f32; 3],
    pub residual: f32,
    pub iterations: u16,
    pub cycles: u32,
    /// The retired instructions counted as `cycles` is (`cycles − stall_cycles` on the wire).
    pub instructions: u32,
}

/// A query's answer from the local model (`LiveForce` or `LiveMotionQuery`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QueryAnswer {
    pub value: [f32; 3],
    pub cycles: u32,
    pub instructions: u32,
}

/// The tool displacements (or loads) as a frame carries them.
fn tool_vec(tool: &[[f64; 3]]) -> heapless::Vec<[f32; 3], MAX_TOOL_NODES> {
    tool.iter().map(|u| u.map(|v| v as f32)).collect()
}

impl<'a, P: Port> LiveLink<'a, P> {
    /// Uploads the matrix, the tool rows and the static loads and starts the session.
    pub fn start(
        target: &'a mut Target<P>,
        setup: &'a LiveSetup,
        params: LiveParams,
    ) -> Result<Self, LinkError> {
        let mut link = LiveLink {
            target,
            setup,
            params,
            resets: 0,
            model: ModelReport {
                solves: 0,
                iterations: 0,
                cycles: 0,
                converged: false,
                stall_cycles: 0,
            },
        };
        link.begin()?;
        Ok(link)
    }

    fn begin(&mut self) -> Result<(), LinkError> {
        self.target.upload_matrix(&self.setup.matrix)?;
        if self.setup.kind == ToolKind::Force {
            let nodes = self.setup.tools.iter().map(|&t| t as u32).collect();
            match self
                .target
                .link_mut()
                .request(&Request::LiveForceTool { nodes })?
            {
                Response::Ack => {}
                other => return Err(unexpected("LiveForceTool", "Ack", other)),
            }
        }
        for row in &self.setup.rows {
            match self
                .target
                .link_mut()
                .request(&Request::LiveTool(row.clone()))?
            {
                Response::Ack => {}
                other => return Err(unexpected("LiveTool", "Ack", other)),
            }
        }
        let timeout = self.solve_timeout();
        let request = Request::LiveStart(self.params);
        self.model = match self.target.link_mut().request_within(&request, timeout)? {
            Response::LiveReady(model) => model,
            other => return Err(unexpected("LiveStart", "LiveReady", other)),
        };
        for (d, b) in self.setup.static_rhs.iter().enumerate() {
            let slot = VectorSlot::Rhs { direction: d as u8 };
            self.target.upload_vector(slot, b)?;
        }
        Ok(())
    }

    /// Bytes the target's link has moved so far (see [`WireBytes`]).
    pub fn wire(&self) -> WireBytes {
        WireBytes::of(&self.target.stats())
    }

    /// Frames the link sent again so far.
    pub fn retransmits(&self) -> u64 {
        self.target.stats().retransmits
    }

    fn solve_timeout(&self) -> Duration {
        self.target.timeouts().solve
    }

    /// Sends `request`; if the target reset, sets the session up again and repeats it once.
    fn request(&mut self, request: &Request) -> Result<Response, LinkError> {
        let timeout = self.solve_timeout();
        match self.target.link_mut().request_within(request, timeout) {
            Err(LinkError::TargetReset) => {
                self.target.reset()?;
                self.begin()?;
                self.resets += 1;
                self.target.link_mut().request_within(request, timeout)
            }
            other => other,
        }
    }

    /// A full frame with the tool nodes at `tool` (displacements, or loads for a force tool).
    pub fn frame(&mut self, tool: &[[f64; 3]]) -> Result<FrameAnswer, LinkError> {
        let (request, name) = match self.setup.kind {
            ToolKind::Displacement => (
                Request::LiveFrame {
                    tool: tool_vec(tool),
                },
                "LiveFrame",
            ),
            ToolKind::Force => (
                Request::LiveLoad {
                    load: tool_vec(tool),
                },
                "LiveMotion",
            ),
        };
        match self.request(&request)? {
            Response::LiveFrame(r) => Ok(FrameAnswer {
                value: r.force,
                residual: r.residual,
                iterations: r.iterations,
                cycles: r.cycles,
                instructions: r.cycles.saturating_sub(r.stall_cycles),
            }),
            Response::LiveMotion(r) => Ok(FrameAnswer {
                value: r.displacement,
                residual: r.residual,
                iterations: r.iterations,
                cycles: r.cycles,
                instructions: r.cycles.saturating_sub(r.stall_cycles),
            }),
            other => Err(unexpected(name, name, other)),
        }
    }

    /// A query from the local model: the force at tool displacements, or the motion under
    /// loads for a force tool.
    pub fn force(&mut self, tool: &[[f64; 3]]) -> Result<QueryAnswer, LinkError> {
        let (request, name) = match self.setup.kind {
            ToolKind::Displacement => (
                Request::LiveForce {
                    tool: tool_vec(tool),
                },
                "LiveForce",
            ),
            ToolKind::Force => (
                Request::LiveLoadQuery {
                    load: tool_vec(tool),
                },
                "LiveMotionQuery",
            ),
        };
        match self.request(&request)? {
            Response::LiveForce(r) => Ok(QueryAnswer {
                value: r.force,
                cycles: r.cycles,
                instructions: r.cycles.saturating_sub(r.stall_cycles),
            }),
            Response::LiveMotionQuery(r) => Ok(QueryAnswer {
                value: r.displacement,
                cycles: r.cycles,
                instructions: r.cycles.saturating_sub(r.stall_cycles),
            }),
            other => Err(unexpected(name, name, other)),
        }
    }

    /// The last frame's quantised field at the nodes `choice` selects ([`read_field`]).
    pub fn field(&mut self, choice: FieldChoice) -> Result<FieldFrame, LinkError> {
        read_field(
            self.target,
            &self.setup.model.grid(),
            self.setup.matrix.n,
            choice,
        )
    }

    /// The last frame's full-precision solution (for checking, not the live path).
    pub fn solution(&mut self) -> Result<[Vec<f64>; 3], LinkError> {
        let n = self.setup.matrix.n as usize;
        let mut u: [Vec<f64>; 3] = Default::default();
        for (d, ud) in u.iter_mut().enumerate() {
            *ud = self.target.read_direction_solution(d as u8, n)?;
        }
        Ok(u)
    }
}

/// The last frame's quantised field at the nodes `choice` selects, as (node, u), and the
/// target's cycles for building it (all chunks together): a live frame's, or a target-resident
/// dynamic step's ([`super::resident`]), on the model's `grid` with the resident matrix of `n`
/// rows.
pub fn read_field<P: Port>(
    target: &mut Target<P>,
    grid: &Grid,
    n: u32,
    choice: FieldChoice,
) -> Result<FieldFrame, LinkError> {
    let (stride, surface) = choice.request(grid);
    // The target runs the same check on the same numbers and would refuse alike.
    let selection = FieldSelection::new(n, stride, surface).map_err(|e| LinkError::Target {
        request: "ReadField",
        code: ErrorCode::Live(e),
    })?;
    let start = WireBytes::of(&target.stats());
    let mut frame = FieldFrame::default();
    let mut exponent = None;
    let requests = selection.chunk_offsets().map(|offset| Request::ReadField {
        offset,
        stride,
        surface,
    });
    target.link_mut().run(requests, |request, reply| {
        let Request::ReadField { offset, .. } = *request else {
            return Err(unexpected("ReadField", "Field", reply));
        };
        match reply {
            Response::Field(chunk)
                if chunk.offset == offset
                    && *exponent.get_or_insert(chunk.exponent) == chunk.exponent
                    && chunk.values.len() == 3 * selection.chunk(offset).count() =>
            {
                let nodes = selection.chunk(offset).map(|p| p as usize);
                frame.nodes.extend(nodes.zip(chunk.displacements()));
                frame.cycles += u64::from(chunk.cycles);
                frame.instructions += u64::from(chunk.cycles.saturating_sub(chunk.stall_cycles));
                Ok(())
            }
            other => Err(unexpected(
                "ReadField",
                "a Field chunk at the offset asked, with the frame's exponent and every node asked",
                other,
            )),
        }
    })?;
    frame.bytes = WireBytes::of(&target.stats()).since(start);
    Ok(frame)
}

/// One field frame as the host received it.
#[derive(Debug, Clone, Default)]
pub struct FieldFrame {
    /// (node, u) for every node transmitted, in the order they travelled.
    pub nodes: Vec<(usize, [f64; 3])>,
    /// The target's cycles for building the frame: its chunks' together.
    pub cycles: u64,
    /// The retired instructions counted as `cycles` is.
    pub instructions: u64,
    /// Its bytes on the line, both ways.
    pub bytes: WireBytes,
}
