//! The live loop's messages (protocol version 8; force tools version 9, compact fields version 10): a tool pushes the tissue frame by frame, the
//! reaction force comes back at haptic rate and the field at a lower rate (`deform live`).
//!
//! K, the fixed set and the static loads stay resident on the target. The host sends once per
//! tool node its row of the unconstrained K ([`ToolRow`]: the couplings K_tf to the free
//! nodes, K_tt among the tool nodes), then [`LiveParams`]. Each frame then carries only the
//! tool nodes' prescribed displacements, a dozen bytes per node: the target moves them into
//! the right-hand side itself (b_i = b_static,i − Σ_t K_it·u_t for the free neighbours, b_t =
//! K_tt·u_t on the tool's own eliminated row, exactly as the host's model does), solves the
//! three directions fused from its prediction within the budget and answers the reaction force
//! Σ_t (K·u)_t, the residual reached, the iterations and the cycles ([`FrameReport`]).
//!
//! Between full frames a force query ([`ForceReport`]) is answered from a local linear model:
//! for displacement tools the effective stiffness at the tool nodes, the Schur complement
//! S = K_tt − K_tf·K_ff⁻¹·K_ft, of which the force summed over the tool nodes needs only the
//! column sums s_j. The target computes them with CG solves when the tool set is given
//! ([`ModelReport`]), and each full frame re-anchors the model: F(u) = F_frame + k_d·Σ_j s_j·
//! (u_j − u_j,frame).
//!
//! A force tool (protocol version 9) is the other kind: its nodes stay free in the resident K
//! and [`Request::LiveForceTool`](crate::protocol::Request) names them. A frame
//! ([`Request::LiveLoad`](crate::protocol::Request)) carries the point loads at the tool nodes,
//! which the target adds to its static loads (b_t = b_static,t + f_t/k_d); it answers the tool
//! nodes' mean displacement ([`MotionReport`]). The local model is then the compliance, the
//! block C = (K⁻¹)_tt of the resident matrix, one unit-load CG column per tool node; the mean
//! displacement needs only C's column means c̄_j, and each full frame re-anchors it:
//! ū = ū_frame + Σ_j c̄_j·(f_j − f_j,frame)/k_d ([`MotionQuery`]).
//!
//! The displacement field travels in its own [`FieldChunk`]s, quantised to `i16` per component
//! with one power-of-two scale per frame, every k-th node or only the surface nodes, and
//! difference-coded on the wire ([`crate::field`], protocol version 10).

use heapless::Vec;
use serde::{Deserialize, Serialize};

/// Most tool nodes a live session drives.
pub const MAX_TOOL_NODES: usize = 8;

/// Most off-diagonal entries of a tool node's row (model B has 26 neighbours).
pub const MAX_TOOL_ROW: usize = 32;

pub use crate::field::{FieldChunk, FieldSelection, FIELD_COMPONENTS, FIELD_NODES};

/// One entry of a tool node's row of K: the column (a node index) and its raw value in the
/// resident matrix's Q-format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Coupling {
    pub column: u32,
    pub value: i32,
}

/// A tool node and its row of the unconstrained K (fixed neighbours left out: they do not
/// move). The node's own row in the resident matrix is its eliminated row K_tt alone.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ToolRow {
    pub node: u32,
    /// K_tt, raw.
    pub diagonal: i32,
    /// The off-diagonal entries, to free and to other tool nodes.
    pub row: Vec<Coupling, MAX_TOOL_ROW>,
}

/// How every frame is solved, kept by the target from [`LiveStart`](crate::protocol::Request).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LiveParams {
    /// Relative residual at which a frame's solve stops.
    pub tolerance: f32,
    /// Iteration budget of a frame.
    pub max_iterations: u32,
    /// Cycle budget of a frame's solve, 0 for none (`SolveParams::cycle_budget`).
    pub cycle_budget: u64,
    /// k_d per direction: the resident matrix times k_d is K_d (1 for heterogeneous tissue),
    /// so forces come back in newtons.
    pub scale: [f32; 3],
}

/// What building the local force model cost.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ModelReport {
    /// Fused CG solves run (one per three tool nodes).
    pub solves: u8,
    /// CG iterations over those solves.
    pub iterations: u32,
    /// Hart 0's cycles for the whole model, each solve counted at its critical path (with
    /// one MVU simply hart 0's count; see [`FrameReport::cycles`]).
    pub cycles: u64,
    /// Every column converged.
    pub converged: bool,
    /// (Version 11.) `cycles` minus the retired instructions counted the same way (see
    /// [`FrameReport::stall_cycles`]).
    pub stall_cycles: u64,
}

/// The answer to a full frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FrameReport {
    /// Reaction force summed over the tool nodes, K·u, per direction (N).
    pub force: [f32; 3],
    /// The largest relative residual the three directions reached.
    pub residual: f32,
    /// Iterations of the fused loop.
    pub iterations: u16,
    /// Hart 0's cycles for the whole frame: right-hand side, prediction, solve, force; with
    /// several MVUs the solve counted at its measured critical path.
    pub cycles: u32,
    /// (Version 11.) `cycles` minus the retired instructions counted the same way: the cycles
    /// in which no instruction retired (instructions = `cycles − stall_cycles`). Sent as the
    /// difference, not the count, because it is 0 under QEMU `-icount` (CPI 1) and so costs one
    /// byte of the 32-byte frame budget; on the LiteX VexRiscv it is the RTL's stalls.
    pub stall_cycles: u32,
}

/// The answer to a force query from the local model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ForceReport {
    pub force: [f32; 3],
    /// Hart 0's cycles for the query.
    pub cycles: u32,
    /// (Version 11.) `cycles` minus hart 0's retired instructions (see
    /// [`FrameReport::stall_cycles`]).
    pub stall_cycles: u32,
}

/// The answer to a full frame of a force tool (version 9): the mean displacement of the tool
/// nodes. A haptic device driven by force (admittance) displays one position, the tool's; a
/// probe spreading its load over several nodes sits at their mean displacement.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MotionReport {
    /// Mean displacement of the tool nodes, per direction (m).
    pub displacement: [f32; 3],
    /// The largest relative residual the three directions reached.
    pub residual: f32,
    /// Iterations of the fused loop.
    pub iterations: u16,
    /// Hart 0's cycles for the whole frame (on the critical path with several MVUs).
    pub cycles: u32,
    /// (Version 11.) `cycles` minus the retired instructions (see
    /// [`FrameReport::stall_cycles`]).
    pub stall_cycles: u32,
}

/// The answer to a displacement query of a force tool from the compliance model (version 9).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MotionQuery {
    /// Mean displacement of the tool nodes, per direction (m).
    pub displacement: [f32; 3],
    /// Hart 0's cycles for the query.
    pub cycles: u32,
    /// (Version 11.) `cycles` minus hart 0's retired instructions (see
    /// [`FrameReport::stall_cycles`]).
    pub stall_cycles: u32,
}

/// Why the target refused a live request.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, thiserror::Error)]
pub enum LiveError {
    #[error("tool node {node} is outside the matrix")]
    NodeOutOfRange { node: u32 },
    #[error("column {column} of a tool row is outside the matrix")]
    ColumnOutOfRange { column: u32 },
    #[error("tool node {node} was given twice")]
    DuplicateNode { node: u32 },
    #[error("more than {max} tool nodes")]
    TooManyNodes { max: u8 },
    #[error("a raw value of a tool row does not fit the 21-bit value field")]
    ValueOutOfRange,
    #[error("no tool node was given before LiveStart")]
    NoTool,
    #[error("no live session: send the tool rows and LiveStart first")]
    NotStarted,
    #[error("{got} tool displacements for {expected} tool nodes")]
    ToolCount { expected: u8, got: u8 },
    #[error("a tool displacement or parameter is not finite")]
    NotFinite,
    #[error("no full frame yet: the local force model has no anchor")]
    NoFrame,
    #[error("the field stride must be at least 1")]
    BadStride,
    /// Version 9 (force tools): the unit load at a force tool node moved no other node, so
    /// its row couples to no free node: it is fixed (or prescribed).
    #[error("force tool node {node} is fixed: a load there moves nothing")]
    FixedToolNode { node: u32 },
    #[error("a tool set mixes displacement rows (LiveTool) and force nodes (LiveForceTool)")]
    MixedKinds,
    #[error("the request is for the other kind of tool than the session's")]
    WrongKind,
    /// Protocol version 10: a surface field's grid is not the resident matrix's.
    #[error("a {}×{}×{} grid does not have the resident matrix's {nodes} nodes", grid[0], grid[1], grid[2])]
    BadGrid { grid: [u16; 3], nodes: u32 },
    /// Protocol version 10: a field chunk's offset is past its selection.
    #[error("field offset {offset} is past the {selected} nodes selected")]
    FieldOffset { offset: u32, selected: u32 },
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame;
    use crate::protocol::{Envelope, Request, Response, MAX_FRAME_LEN};
    use crate::transport::Uplink;

    fn encoded_len<T: Serialize>(msg: &T) -> usize {
        let mut buf = [0u8; MAX_FRAME_LEN];
        frame::encode(msg, &mut buf).unwrap()
    }

    /// The budget: at most 32 bytes on the line up and 32 down per force frame, even
    /// with the largest sequence number and a one-node tool.
    #[test]
    fn a_frame_fits_32_bytes_each_way() {
        let tool = [[-1.25e-3f32, 7.5, f32::MAX]].into_iter().collect();
        let up = Envelope {
            seq: u16::MAX,
            body: Request::LiveFrame { tool },
        };
        assert!(encoded_len(&up) <= 32, "{}", encoded_len(&up));
        let report = FrameReport {
            force: [f32::MIN, -0.5, 3.25],
            residual: 1e-5,
            iterations: 120,
            cycles: 2_000_000,
            stall_cycles: 0,
        };
        let down = Uplink::Reply {
            seq: u16::MAX,
            body: Response::LiveFrame(report),
        };
        assert!(encoded_len(&down) <= 32, "{}", encoded_len(&down));
        // A force tool's frame and its answer (version 9), and the query's.
        let load: Vec<[f32; 3], MAX_TOOL_NODES> = [[f32::MIN, 7.5, -1e-30]].into_iter().collect();
        for body in [
            Request::LiveLoad { load: load.clone() },
            Request::LiveLoadQuery { load },
        ] {
            let up = Envelope {
                seq: u16::MAX,
                body,
            };
            assert!(encoded_len(&up) <= 32, "{}", encoded_len(&up));
        }
        let motion = MotionReport {
            displacement: [f32::MIN, -0.5, 3.25e-3],
            residual: 1e-5,
            iterations: 120,
            cycles: 2_000_000,
            stall_cycles: 0,
        };
        let query = MotionQuery {
            displacement: [f32::MIN, -0.5, 3.25e-3],
            cycles: u32::MAX,
            stall_cycles: 0,
        };
        for body in [
            Response::LiveMotion(motion),
            Response::LiveMotionQuery(query),
        ] {
            let down = Uplink::Reply {
                seq: u16::MAX,
                body,
            };
            assert!(encoded_len(&down) <= 32, "{}", encoded_len(&down));
        }
    }

    #[test]
    fn the_largest_live_messages_fit_a_frame() {
        let row = ToolRow {
            node: u32::MAX,
            diagonal: i32::MIN,
            row: (0..MAX_TOOL_ROW as u32)
                .map(|c| Coupling {
                    column: u32::MAX - c,
                    value: i32::MIN,
                })
                .collect(),
        };
        let up = Envelope {
            seq: u16::MAX,
            body: Request::LiveTool(row),
        };
        assert!(encoded_len(&up) + 16 <= MAX_FRAME_LEN);
    }
}
