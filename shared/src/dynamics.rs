//! Target-resident dynamic frames (protocol version 12): the target keeps the displacements u
//! and velocities v of a backward-Euler elastodynamic model and forms each step's right-hand
//! side itself, so a frame carries only the tool's prescribed displacements up and its force
//! down, as a quasi-static frame does ([`crate::live`]).
//!
//! Each step solves S·v₁ = b with S = M + h·C + h²·K, the resident matrix, and
//! b = M·v₀ − h·K·u₀ (no external loads), the tool nodes' known velocities
//! v₁ = (u₁ − u₀)/h moved over with their rows of S; then u₁ = u₀ + h·v₁. K·u₀ is one MVU pass
//! over a resident copy of K ([`crate::protocol::Request::BeginStiffness`]: S's words with K's
//! values, the same tiles and pattern).
//!
//! # Session order
//!
//! 1. The matrix S as usual (`BeginMatrix` … `EndMatrix`), then K's values into its copy
//!    (`BeginStiffness`, `UpdateValues`…, `EndUpdate` with the CRC of K's words).
//! 2. One [`DynamicTool`] per tool node: its rows of the unconstrained S and K.
//! 3. `DynamicStart(`[`DynamicParams`]`)`: the tissue at rest, u = v = 0, the tool at 0.
//! 4. `DynamicFrame { tool }` per step: the tool's displacements at the step's end; answered
//!    by `LiveFrame(`[`crate::live::FrameReport`]`)`, the force the tool exerts.
//!    `ReadSolution` and `ReadField` read u.
//!
//! Directions the tool does not move and whose state is at rest stay at rest without a solve.

use serde::{Deserialize, Serialize};

use crate::live::ToolRow;

/// One tool node of a dynamic session: its rows of the unconstrained S and K (the node and its
/// couplings the same in both; raw values in each matrix's own Q-format).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DynamicTool {
    pub s: ToolRow,
    pub k: ToolRow,
}

/// The model and how every step is solved.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DynamicParams {
    /// The time step h (s).
    pub h: f32,
    /// The lumped mass of every node (kg): M = m·I.
    pub mass: f32,
    /// The resident matrix is S·2^−`s_scale` and the stiffness copy K·2^−`k_scale` (their
    /// tool rows likewise): a small mass puts S's entries far below the 21-bit value field's
    /// range at its most fractional bits (20), so the host scales S up by a power of two to use
    /// all of them.
    pub s_scale: i8,
    pub k_scale: i8,
    /// Relative residual at which a step's solve stops.
    pub tolerance: f32,
    /// Iteration budget of a step.
    pub max_iterations: u32,
    /// Cycle budget of a step's solve, 0 for none (`SolveParams::cycle_budget`).
    pub cycle_budget: u64,
}

/// Why the target refused a dynamic request.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, thiserror::Error)]
pub enum DynamicError {
    #[error("no stiffness copy: upload K's values (BeginStiffness) after the matrix")]
    NoStiffness,
    #[error("a tool node's rows of S and K name different nodes or columns")]
    RowsDiffer,
    #[error("h, the mass or the tolerance is not a positive finite number")]
    BadParams,
    #[error("no dynamic session: send the tools and DynamicStart first")]
    NotStarted,
}

#[cfg(test)]
mod tests {
    use heapless::Vec;

    use crate::frame;
    use crate::live::{FrameReport, MAX_TOOL_NODES};
    use crate::protocol::{Envelope, Request, Response, MAX_FRAME_LEN};
    use crate::transport::Uplink;

    fn encoded_len<T: serde::Serialize>(msg: &T) -> usize {
        let mut buf = [0u8; MAX_FRAME_LEN];
        frame::encode(msg, &mut buf).unwrap()
    }

    /// Issue 19's budget: at most 64 bytes on the line each way per dynamic frame, with the
    /// largest sequence number; a one-node tool takes as much as a quasi-static frame (32).
    #[test]
    fn a_dynamic_frame_fits_64_bytes_each_way() {
        for nodes in [1, 3] {
            let tool: Vec<[f32; 3], MAX_TOOL_NODES> =
                (0..nodes).map(|_| [f32::MIN, -0.25, 1.5e-3]).collect();
            let up = Envelope {
                seq: u16::MAX,
                body: Request::DynamicFrame { tool },
            };
            assert!(
                encoded_len(&up) <= 64,
                "{nodes} nodes: {}",
                encoded_len(&up)
            );
        }
        let down = Uplink::Reply {
            seq: u16::MAX,
            body: Response::LiveFrame(FrameReport {
                force: [f32::MIN, -0.5, 3.25],
                residual: 1e-5,
                iterations: u16::MAX,
                cycles: u32::MAX,
                stall_cycles: u32::MAX,
            }),
        };
        assert!(encoded_len(&down) <= 64, "{}", encoded_len(&down));
    }
}
