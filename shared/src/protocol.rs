//! The request/response messages between the host and the target.
//!
//! The host always speaks first and the target answers every request with exactly one
//! response, which travels in an [`Uplink::Reply`](crate::transport::Uplink) carrying the
//! request's sequence number. Sequencing, the window, acknowledgements and retransmission are the
//! transport's business ([`crate::transport`], `docs/PROTOCOL.md`): by the time a request reaches
//! the session it arrived intact, in order and exactly once.
//!
//! Session order (the firmware enforces it and says which step is out of order):
//!
//! 1. `Hello` → `Hello(TargetInfo)`: versions and capacities; it also resets the session.
//! 2. `BeginMatrix`, then for each tile a `Tile` followed by its `Words` chunks, then `EndMatrix`
//!    with the CRC of all words → `Ack` once the whole matrix is validated.
//! 3. `BeginVector(Rhs { direction })` and its `VectorData` chunks for each direction to solve
//!    (likewise an initial guess, if wanted).
//! 4. `Solve` → `Solved(SolveReport)`, then `ReadSolution { direction, offset, len }` chunk by
//!    chunk, each answer at most `len` elements long.
//!
//! Steps 3–4 repeat for as many right-hand sides as wanted; the matrix stays resident.
//!
//! # Parallel MVUs, mirrored tiles, fused directions (protocol version 5)
//!
//! - Each tile names the MVU (hart) that runs it (`TileHeader::mvu`, below `TargetInfo::harts`);
//!   the solve uses `max(mvu) + 1` MVUs. y = Σ over all tiles whatever the assignment: when the
//!   MVUs' row ranges overlap (thesis 4.1.1) each accumulates into private partial sums that are
//!   added afterwards, otherwise (4.1.2) each writes its rows of y directly.
//! - A `mirrored` tile stores half of a persymmetric K (K_ij = K_{n−1−i, n−1−j}, thesis 2.5 vi):
//!   each of its words (row i, column j, value v) also adds v·p[n−1−j] to y[n−1−i].
//! - `SolveParams::directions` runs up to three CGs on the same K together (x, y, z).
//!
//! # Values-only update (protocol version 2)
//!
//! A displacement-dependent model (thesis 2.4.2, 3.2.2) changes K's values every time step but
//! not its sparsity pattern. Instead of the whole word stream the host may then send only the
//! new 21-bit value fields of the resident words:
//!
//! 5. `BeginUpdate { words, frac_bits }` (`words` must equal the resident matrix's word count;
//!    `frac_bits` is the new Q-format of the values, it may differ from the upload's), then
//!    `UpdateValues { offset, values }` chunks in order (raw two's complement values in
//!    `VALUE_MIN..=VALUE_MAX`; offsets count words from the start of the stream, as for
//!    `Words`), then `EndUpdate { crc32 }` with the CRC of the *resulting* words
//!    ([`crate::matrix::words_crc`]) → `Ack`.
//!
//! Each value replaces bits 20..0 of the word at its position; the EM/ER bits and the column
//! stay, so the tile structure validated at upload time still holds. While an update is in
//! progress the matrix cannot be solved with (`OutOfOrder(UpdateIncomplete)`); vectors and the
//! previous solution survive an update, so `Start::Previous` warm-starts after it. A CRC
//! mismatch at `EndUpdate` drops the matrix (it is a mix of old and new values): upload it
//! again.

use heapless::Vec;
use serde::{Deserialize, Serialize};

use crate::frame::FrameError;
use crate::matrix::{MatrixError, TileHeader};

/// Bumped on any change to these types or to the framing.
///
/// Version 4 (link): the reliable transport ([`crate::transport`]: window, ACK/NAK, `Uplink` frames),
/// fixed-width chunk payloads ([`crate::chunk`]) and 128-element chunks.
/// Version 5 (engine): tiles carry their MVU and a mirrored flag, fused directions, per-hart costs.
/// Version 6 (engine): the whole solve's measured critical path (`SolveReport::whole_solve`).
/// Version 7 (craft): `ReadSolution` carries the most elements its answer may hold (`len`).
/// Version 8 (live): predicted warm starts, cycle budgets, the sparse frame messages.
/// Version 9 (forcetool): force tools in the live loop (`LiveForceTool`, `LiveLoad`,
/// `LiveLoadQuery`; `LiveMotion`, `LiveMotionQuery`; three more `LiveError`s).
/// Version 10 (field): compact field frames: `ReadField::surface`, difference-coded
/// `FieldChunk` values and their build cycles ([`crate::field`]).
/// Version 11 (hardening): cycles beside instructions wherever the target reads `mcycle`:
/// `IterationCost`'s four counts and `first_iteration_scalar` become [`PhaseCounters`], and the
/// live reports (`ModelReport`, `FrameReport`, `ForceReport`, `MotionReport`, `MotionQuery`,
/// `FieldChunk`) gain `stall_cycles` (cycles minus instructions) beside `cycles`.
/// Version 12 (engine): target-resident dynamic frames (`BeginStiffness`, `DynamicTool`,
/// `DynamicStart`, `DynamicFrame`, `ErrorCode::Dynamic`; [`crate::dynamics`]).
/// Version 13 (check): `ReadVector` reads a session vector other than the solution (a dynamic
/// step's right-hand side, velocity and residual), so that the host can check a step's true
/// residual b − S·v₁ against what the target accepted.
pub const PROTOCOL_VERSION: u16 = 13;

/// Most CG systems one `Solve` runs together on the same K (x, y and z: thesis eq. 38).
pub const MAX_DIRECTIONS: usize = 3;

/// Most harts (MVUs) a target may report; `TileHeader::mvu` must be below the reported count.
pub const MAX_HARTS: usize = 8;

/// Words or mantissas per chunk message. Each element takes 4 bytes on the wire and a chunk
/// frame adds about 17 bytes (sequence number, tag, offset, count, CRC, COBS, delimiter), so 128
/// elements cost ≈ 4.13 bytes per element; 64 would cost ≈ 4.27. Larger chunks would save
/// little more and lose more data to each corrupted frame on a noisy line.
pub const CHUNK_LEN: usize = 128;

/// Largest encoded frame, delimiter included, that either side must accept: the largest chunk
/// message (≈ 540 bytes) with room for a few more header fields.
pub const MAX_FRAME_LEN: usize = 576;

/// Most log bytes one [`Response::Log`] carries: with its envelope it stays well inside
/// [`MAX_FRAME_LEN`] even after the transport's own header.
pub const LOG_CHUNK: usize = 256;

/// Most bytes of build id [`TargetInfo::build_id`] holds: 20 for a SHA-1 GNU build id, 16 for
/// md5/uuid, 8 for lld's default "fast" hash.
pub const BUILD_ID_MAX: usize = 32;

/// Every request travels in one envelope: its sequence number and the request (see
/// [`crate::transport`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Envelope<T> {
    pub seq: u16,
    pub body: T,
}

/// Which vector a `BeginVector`/`VectorData` fills. `direction` (0..[`MAX_DIRECTIONS`]) picks
/// which of the fused systems it belongs to; a single-direction solve uses direction 0.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum VectorSlot {
    /// The right-hand side b of one direction.
    Rhs { direction: u8 },
    /// A starting point x₀ for one direction's CG.
    InitialGuess { direction: u8 },
}

impl VectorSlot {
    /// The right-hand side of direction 0, what a single-direction solve uses.
    pub const RHS: VectorSlot = VectorSlot::Rhs { direction: 0 };
    /// The initial guess of direction 0.
    pub const INITIAL_GUESS: VectorSlot = VectorSlot::InitialGuess { direction: 0 };

    /// The direction this slot belongs to.
    pub fn direction(self) -> u8 {
        match self {
            VectorSlot::Rhs { direction } | VectorSlot::InitialGuess { direction } => direction,
        }
    }
}

/// A session vector that [`Request::ReadVector`] reads (protocol version 13), besides the
/// solution that `ReadSolution` reads. Its answer is a [`Response::Solution`] chunk with the
/// vector's own exponent.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum StateVector {
    /// The right-hand side b of the last solve or dynamic step (an uploaded one, or the one a
    /// dynamic step formed on the target).
    Rhs,
    /// A dynamic session's velocities v after its last step.
    Velocity,
    /// A dynamic session's residual r of its last step, as the target carries it (the
    /// recursive one where the step accepted its solve without the closing MVU pass).
    Residual,
}

/// Where CG starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Start {
    /// x₀ = 0.
    Zero,
    /// x₀ = the previous solve's result (warm start for time series).
    Previous,
    /// x₀ = the uploaded `InitialGuess` vector.
    Uploaded,
    /// x₀ predicted on the target from the solutions it keeps (protocol version 8): the linear
    /// extrapolation 2u(t−1) − u(t−2) once two consecutive solves of the direction are known
    /// (the previous one `Predicted`), u(t−1) after one solve, 0 before any. No vector crosses
    /// the link. The target keeps u(t−1) in the `InitialGuess` slot, so a `Predicted` solve
    /// consumes an uploaded guess, and uploading a guess restarts the prediction.
    Predicted,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SolveParams {
    /// Upper bound on CG iterations.
    pub max_iterations: u32,
    /// Stop once ‖r‖₂ / ‖b‖₂ falls to this (the target's recursive residual).
    pub tolerance: f64,
    pub start: Start,
    /// How many systems (1..=[`MAX_DIRECTIONS`]) run fused on the resident K: directions
    /// `0..directions`, each with its own `Rhs` (and `InitialGuess` for [`Start::Uploaded`]).
    /// Every matrix word fetched serves one multiply-accumulate per direction. Each direction
    /// stops on its own tolerance; the loop runs until all have stopped.
    pub directions: u8,
    /// Cycle budget of the step (protocol version 8), 0 for none: the loop starts no new CG
    /// iteration once the solve's measured critical path (as in `SolveReport::whole_solve`)
    /// reaches it. A step thus stops at the
    /// tolerance, at `max_iterations` (the iteration budget) or at this budget, whichever comes
    /// first; the report's residuals say how far it got.
    pub cycle_budget: u64,
}

// Chunk variants are large by design (one frame's worth of data); no_std has no Box to shrink them.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Request {
    Hello {
        protocol_version: u16,
    },
    BeginMatrix {
        n: u32,
        frac_bits: u8,
        tiles: u32,
        words: u32,
    },
    Tile(TileHeader),
    Words {
        offset: u32,
        #[serde(with = "crate::chunk")]
        words: Vec<u32, CHUNK_LEN>,
    },
    EndMatrix {
        crc32: u32,
    },
    BeginVector {
        slot: VectorSlot,
        exponent: i32,
        len: u32,
    },
    VectorData {
        slot: VectorSlot,
        offset: u32,
        #[serde(with = "crate::chunk")]
        mantissas: Vec<i32, CHUNK_LEN>,
    },
    Solve(SolveParams),
    ReadSolution {
        direction: u8,
        offset: u32,
        /// Most elements the answer may carry (it carries `min(len, CHUNK_LEN, n − offset)`):
        /// the host shrinks replies on a noisy line as it shrinks its own chunks (protocol
        /// version 7).
        len: u16,
    },
    /// Starts a values-only update of the resident matrix (see the module doc).
    BeginUpdate {
        words: u32,
        frac_bits: u8,
    },
    /// New raw values for the resident words `offset..offset + values.len()`.
    UpdateValues {
        offset: u32,
        #[serde(with = "crate::chunk")]
        values: Vec<i32, CHUNK_LEN>,
    },
    /// Ends a values-only update: the CRC of all words as they now are.
    EndUpdate {
        crc32: u32,
    },
    /// Live loop (protocol version 8, see [`crate::live`]): one tool node's row of the
    /// unconstrained K, sent once per tool node before [`Request::LiveStart`].
    LiveTool(crate::live::ToolRow),
    /// Live loop: the tool set is complete; the target computes the local force model (the
    /// Schur complement's column sums, one CG solve per three tool nodes), keeps `params` for
    /// every frame and forgets its right-hand sides (upload the static loads next).
    LiveStart(crate::live::LiveParams),
    /// Live loop: a full frame. The tool nodes' prescribed displacements, in the order of their
    /// `LiveTool`s; the target builds the right-hand sides, solves fused, predicted and within
    /// the budget, and answers [`Response::LiveFrame`].
    LiveFrame {
        tool: Vec<[f32; 3], { crate::live::MAX_TOOL_NODES }>,
    },
    /// Live loop: a force query between full frames, answered from the local linear model.
    LiveForce {
        tool: Vec<[f32; 3], { crate::live::MAX_TOOL_NODES }>,
    },
    /// Live loop: a chunk of the quantised displacement field of the last frame: every
    /// `stride`-th node of the selection from its `offset`-th on ([`crate::field`]).
    ReadField {
        offset: u32,
        stride: u16,
        /// Protocol version 10: `Some([nx, ny, nz])` selects only the nodes on the surface of
        /// that box grid (its node count must be the resident matrix's n); `None` all nodes.
        surface: Option<[u16; 3]>,
    },
    /// Live loop, version 9: a force tool, its nodes free in the resident K; replaces the tool
    /// set. Then [`Request::LiveStart`] computes the compliance model.
    LiveForceTool {
        nodes: Vec<u32, { crate::live::MAX_TOOL_NODES }>,
    },
    /// Live loop, version 9: a full frame of a force tool. The point loads (N) at the tool
    /// nodes, in the order of `LiveForceTool`; answered by [`Response::LiveMotion`].
    LiveLoad {
        load: Vec<[f32; 3], { crate::live::MAX_TOOL_NODES }>,
    },
    /// Live loop, version 9: a displacement query of a force tool between full frames,
    /// answered from the compliance model by [`Response::LiveMotionQuery`].
    LiveLoadQuery {
        load: Vec<[f32; 3], { crate::live::MAX_TOOL_NODES }>,
    },
    /// Version 12 ([`crate::dynamics`]): starts a values-only upload of K into the resident
    /// matrix's stiffness copy (its words, K's values in Q-format `frac_bits`); `UpdateValues`
    /// and `EndUpdate` continue it as for `BeginUpdate`.
    BeginStiffness {
        frac_bits: u8,
    },
    /// Version 12: a dynamic session's tool node, its rows of S and K.
    DynamicTool(crate::dynamics::DynamicTool),
    /// Version 12: starts the dynamic session at rest; answered `Ack`.
    DynamicStart(crate::dynamics::DynamicParams),
    /// Version 12: one time step with the tool nodes at `tool` at its end (in the order of the
    /// `DynamicTool`s); answered by [`Response::LiveFrame`].
    DynamicFrame {
        tool: Vec<[f32; 3], { crate::live::MAX_TOOL_NODES }>,
    },
    /// Version 13: a chunk of a session vector other than the solution, answered as
    /// `ReadSolution` is (a [`Response::Solution`] of at most `len` elements from `offset`),
    /// with the vector's exponent.
    ReadVector {
        vector: StateVector,
        direction: u8,
        offset: u32,
        len: u16,
    },
}

impl Request {
    /// The variant's name, for messages and logs. An exhaustive `match`: a new variant does
    /// not compile until it is named here (the golden test uses it too).
    pub fn name(&self) -> &'static str {
        match self {
            Request::Hello { .. } => "Hello",
            Request::BeginMatrix { .. } => "BeginMatrix",
            Request::Tile(_) => "Tile",
            Request::Words { .. } => "Words",
            Request::EndMatrix { .. } => "EndMatrix",
            Request::BeginVector { .. } => "BeginVector",
            Request::VectorData { .. } => "VectorData",
            Request::Solve(_) => "Solve",
            Request::ReadSolution { .. } => "ReadSolution",
            Request::BeginUpdate { .. } => "BeginUpdate",
            Request::UpdateValues { .. } => "UpdateValues",
            Request::EndUpdate { .. } => "EndUpdate",
            Request::LiveTool(_) => "LiveTool",
            Request::LiveStart(_) => "LiveStart",
            Request::LiveFrame { .. } => "LiveFrame",
            Request::LiveForce { .. } => "LiveForce",
            Request::ReadField { .. } => "ReadField",
            Request::LiveForceTool { .. } => "LiveForceTool",
            Request::LiveLoad { .. } => "LiveLoad",
            Request::LiveLoadQuery { .. } => "LiveLoadQuery",
            Request::BeginStiffness { .. } => "BeginStiffness",
            Request::DynamicTool(_) => "DynamicTool",
            Request::DynamicStart(_) => "DynamicStart",
            Request::DynamicFrame { .. } => "DynamicFrame",
            Request::ReadVector { .. } => "ReadVector",
        }
    }
}

/// What the target is and what it can hold.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct TargetInfo {
    pub protocol_version: u16,
    pub firmware_version: heapless::String<16>,
    /// Harts available as MVUs.
    pub harts: u8,
    /// Instruction words the matrix store holds.
    pub word_capacity: u32,
    /// Tiles the matrix store holds.
    pub tile_capacity: u32,
    /// Largest dimension n the vectors hold.
    pub max_n: u32,
    /// The firmware ELF's GNU build id (`.note.gnu.build-id`, a hash of the whole linked ELF,
    /// defmt's string table included): the host decodes the firmware's logs only with an ELF
    /// whose build id is the same. Empty if the firmware has none.
    pub build_id: Vec<u8, BUILD_ID_MAX>,
}

/// Cycle and retired-instruction counts of one phase (`mcycle`/`minstret` deltas).
///
/// Both, always: on a real core (the LiteX VexRiscv, a hardware MVU) they differ, and a report
/// that gave one for the other would be wrong by the CPI; under QEMU `-icount shift=0` they are
/// equal by construction.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct PhaseCounters {
    pub cycles: u64,
    pub instructions: u64,
}

impl PhaseCounters {
    /// The counts from `earlier` to `self`, two readings of free-running counters.
    pub fn since(self, earlier: PhaseCounters) -> PhaseCounters {
        PhaseCounters {
            cycles: self.cycles.wrapping_sub(earlier.cycles),
            instructions: self.instructions.wrapping_sub(earlier.instructions),
        }
    }

    pub fn saturating_add(self, other: PhaseCounters) -> PhaseCounters {
        PhaseCounters {
            cycles: self.cycles.saturating_add(other.cycles),
            instructions: self.instructions.saturating_add(other.instructions),
        }
    }

    pub fn saturating_sub(self, other: PhaseCounters) -> PhaseCounters {
        PhaseCounters {
            cycles: self.cycles.saturating_sub(other.cycles),
            instructions: self.instructions.saturating_sub(other.instructions),
        }
    }

    /// Each count's own maximum (the slowest hart by cycles need not retire the most
    /// instructions).
    pub fn max_each(self, other: PhaseCounters) -> PhaseCounters {
        PhaseCounters {
            cycles: self.cycles.max(other.cycles),
            instructions: self.instructions.max(other.instructions),
        }
    }

    /// Cycles per instruction; `None` with no instruction counted.
    pub fn cpi(self) -> Option<f64> {
        (self.instructions > 0).then(|| self.cycles as f64 / self.instructions as f64)
    }

    /// Cycles in which no instruction retired: `cycles − instructions` (0 if fewer), what the
    /// live reports send beside `cycles`.
    pub fn stall_cycles(self) -> u64 {
        self.cycles.saturating_sub(self.instructions)
    }

    /// The counts a live report's `cycles` and `stall_cycles` give.
    pub fn from_stalls(cycles: u64, stall_cycles: u64) -> PhaseCounters {
        PhaseCounters {
            cycles,
            instructions: cycles.saturating_sub(stall_cycles),
        }
    }
}

impl core::ops::AddAssign for PhaseCounters {
    /// Saturating: a count never wraps into a small one.
    fn add_assign(&mut self, other: PhaseCounters) {
        *self = self.saturating_add(other);
    }
}

/// How one direction of a (possibly fused) solve ended.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DirectionReport {
    /// CG iterations this direction took (it stops updating once converged).
    pub iterations: u32,
    pub converged: bool,
    /// Final ‖r‖₂ / ‖b‖₂ of this direction's recursive residual.
    pub residual: f64,
}

/// Cycles and retired instructions of one CG iteration (or, in `SolveReport::whole_solve`, of a
/// whole solve), measured hart by hart (protocol version 11: cycles beside instructions; before,
/// instructions only).
///
/// Under QEMU `-icount` every hart's `minstret` and `mcycle` read one machine-wide count, so the
/// target runs every parallel phase one hart at a time (the others asleep in `wfi`): each
/// hart's delta is then exactly its own work, barrier waits excluded. There cycles equal
/// instructions; on the LiteX VexRiscv (one hart) the cycles are the RTL's.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct IterationCost {
    /// Σ over the MVU phase's steps of the slowest hart's counts (thesis T_MVU), each count's
    /// own slowest hart.
    pub mvu_critical: PhaseCounters,
    /// Σ over the SVU's steps of the slowest hart's counts, plus hart 0's scalar work
    /// (thesis T_SVU).
    pub svu_critical: PhaseCounters,
    /// All harts' MVU-phase counts together.
    pub mvu_total: PhaseCounters,
    /// All harts' SVU-phase counts together.
    pub svu_total: PhaseCounters,
}

impl IterationCost {
    /// T = T_MVU + T_SVU (thesis eq. 55): the critical path, in cycles and in instructions.
    pub fn critical(&self) -> PhaseCounters {
        self.mvu_critical.saturating_add(self.svu_critical)
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SolveReport {
    /// Iterations of the fused loop: the most any direction took.
    pub iterations: u32,
    /// Every direction converged.
    pub converged: bool,
    /// The largest final ‖r‖₂ / ‖b‖₂ over the directions.
    pub residual: f64,
    /// One entry per direction, in order.
    pub directions: Vec<DirectionReport, MAX_DIRECTIONS>,
    /// Nonzeros the MVUs executed per iteration (instruction words, empty-row words included);
    /// each serves one multiply-accumulate per direction (two for a mirrored tile).
    pub words_per_iteration: u32,
    /// MVUs (harts) the solve ran on: the largest tile `mvu` + 1.
    pub mvus: u8,
    /// Whether the MVUs' row ranges overlap (thesis 4.1.1: private partial sums, added
    /// afterwards) or not (4.1.2: each MVU writes its rows of Kp directly).
    pub overlapping: bool,
    /// Hart 0's counters over the MVU phases of the whole solve (wall clock of the phase).
    pub mvu: PhaseCounters,
    /// Hart 0's counters over the SVU phases of the whole solve.
    pub svu: PhaseCounters,
    /// Per-hart instruction counts of the first iteration (zero if the solve needed no
    /// iteration): the MVU/SVU breakdown. The solve's total is `whole_solve`.
    pub per_iteration: IterationCost,
    /// Values that had to be clamped to fit their fixed-point format. The block-floating-point
    /// bounds make this impossible; anything but 0 means the result cannot be trusted.
    pub saturations: u32,
    /// (Protocol version 6.) The whole solve's measured instruction counts: every parallel
    /// phase of every iteration (residual replacements and the initial residual included) run
    /// one hart at a time and its slowest hart's count summed, plus all of hart 0's serial work
    /// from the start of the solve to its end. `mvu_critical + svu_critical` is the solve's
    /// critical path, measured, not extrapolated from `per_iteration`.
    pub whole_solve: IterationCost,
    /// (Protocol version 6; cycles since 11.) Hart 0's serial (scalar) work in the first
    /// iteration: α, β, block exponents and combining the harts' partial results. Part of
    /// `per_iteration.svu_critical`.
    pub first_iteration_scalar: PhaseCounters,
}

/// Why CG stopped without an answer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, thiserror::Error)]
pub enum SolveFailure {
    #[error("pᵀKp ≤ 0 at iteration {iteration}: the matrix is not positive definite (unconstrained or singular system)")]
    NotPositiveDefinite { iteration: u32 },
    #[error("the solver's work vectors are shorter than the matrix needs (a firmware fault)")]
    WorkspaceTooSmall,
    #[error("{0} directions requested; a solve runs 1 to 3")]
    BadDirections(u8),
}

/// Every error the target can answer with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, thiserror::Error)]
pub enum ErrorCode {
    #[error("bad frame: {0}")]
    Frame(FrameError),
    #[error("protocol version mismatch: target speaks {target}")]
    VersionMismatch { target: u16 },
    #[error("request out of order: {0}")]
    OutOfOrder(SessionStep),
    #[error("matrix of {requested} words exceeds the target's capacity of {capacity} words")]
    TooManyWords { requested: u32, capacity: u32 },
    #[error("matrix of {requested} tiles exceeds the target's capacity of {capacity} tiles")]
    TooManyTiles { requested: u32, capacity: u32 },
    #[error("dimension {requested} exceeds the target's maximum n of {capacity}")]
    DimensionTooLarge { requested: u32, capacity: u32 },
    #[error("{0} fractional bits requested; the value field allows 0..=20")]
    BadFracBits(u8),
    #[error("chunk at offset {got}, expected offset {expected}")]
    UnexpectedOffset { expected: u32, got: u32 },
    #[error("chunk runs past the announced length")]
    ChunkTooLong,
    #[error("malformed matrix: {0}")]
    Matrix(MatrixError),
    #[error("matrix CRC mismatch: computed {computed:#010x}")]
    MatrixCrc { computed: u32 },
    #[error("vector length {got} differs from the matrix dimension {expected}")]
    LengthMismatch { expected: u32, got: u32 },
    #[error("vector mantissa out of range (|m| must be < 2^30)")]
    MantissaOutOfRange,
    #[error("solve failed: {0}")]
    Solve(SolveFailure),
    #[error("matrix value {0} does not fit the 21-bit value field")]
    ValueOutOfRange(i32),
    #[error("direction {direction} does not exist; the target runs directions 0..{max}")]
    DirectionOutOfRange { direction: u8, max: u8 },
    #[error("the MVUs' overlapping row ranges need {rows} rows of private partial sums, the target holds {capacity}")]
    OverlapTooLarge { rows: u32, capacity: u32 },
    #[error("live loop: {0}")]
    Live(crate::live::LiveError),
    /// Version 12.
    #[error("dynamic frames: {0}")]
    Dynamic(crate::dynamics::DynamicError),
}

/// The step a request arrived out of, for [`ErrorCode::OutOfOrder`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, thiserror::Error)]
pub enum SessionStep {
    #[error("no matrix upload is in progress")]
    NoMatrixUpload,
    #[error("a tile's words are still expected")]
    TileIncomplete,
    #[error("a tile header was expected")]
    TileExpected,
    #[error("not all tiles were sent")]
    TilesMissing,
    #[error("no vector upload is in progress for that slot")]
    NoVectorUpload,
    #[error("the vector upload is incomplete")]
    VectorIncomplete,
    #[error("no matrix is loaded")]
    NoMatrix,
    #[error("no right-hand side is loaded")]
    NoRhs,
    #[error("no initial guess is loaded")]
    NoInitialGuess,
    #[error("there is no previous solution")]
    NoPreviousSolution,
    #[error("no solution is available")]
    NoSolution,
    #[error("no values-only update is in progress")]
    NoUpdate,
    #[error("the values-only update is incomplete")]
    UpdateIncomplete,
}

// Chunk variants are large by design (one frame's worth of data); no_std has no Box to shrink them.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Response {
    Hello(TargetInfo),
    Ack,
    Error(ErrorCode),
    Solved(SolveReport),
    Solution {
        direction: u8,
        offset: u32,
        exponent: i32,
        #[serde(with = "crate::chunk")]
        mantissas: Vec<i32, CHUNK_LEN>,
    },
    /// Unsolicited: defmt log frames (rzcobs-encoded, each ending in `0x00`), sent by the target
    /// just before an answer; the host decodes them against the firmware ELF. A chunk may end
    /// inside a frame, the next `Log` continues it. `dropped` counts the log bytes the target
    /// discarded since the previous `Log` because its log buffer was full (whole frames are
    /// discarded, so what does arrive still decodes).
    Log {
        dropped: u32,
        frames: Vec<u8, LOG_CHUNK>,
    },
    /// Live loop: the tool set is ready; what building the local force model cost.
    LiveReady(crate::live::ModelReport),
    /// Live loop: the answer to a full frame.
    LiveFrame(crate::live::FrameReport),
    /// Live loop: the answer to a force query.
    LiveForce(crate::live::ForceReport),
    /// Live loop: a chunk of the quantised field (see [`crate::live::FieldChunk`]).
    Field(crate::live::FieldChunk),
    /// Live loop, version 9: the answer to a force tool's full frame.
    LiveMotion(crate::live::MotionReport),
    /// Live loop, version 9: the answer to a force tool's query.
    LiveMotionQuery(crate::live::MotionQuery),
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame;

    #[test]
    fn the_largest_messages_fit_a_frame() {
        let words: Vec<u32, CHUNK_LEN> = (0..CHUNK_LEN as u32).map(|i| u32::MAX - i).collect();
        let req = Envelope {
            seq: u16::MAX,
            body: Request::Words {
                offset: u32::MAX,
                words,
            },
        };
        let mut buf = [0u8; MAX_FRAME_LEN];
        let n = frame::encode(&req, &mut buf).unwrap();
        assert!(n + 16 <= MAX_FRAME_LEN, "{n}: leave room for new fields");
        let back: Envelope<Request> = frame::decode(&mut buf[..n - 1]).unwrap();
        assert_eq!(back, req);

        let values: Vec<i32, CHUNK_LEN> = (0..CHUNK_LEN as i32).map(|i| i32::MIN + i).collect();
        let req = Envelope {
            seq: u16::MAX,
            body: Request::UpdateValues {
                offset: u32::MAX,
                values,
            },
        };
        let n = frame::encode(&req, &mut buf).unwrap();
        let back: Envelope<Request> = frame::decode(&mut buf[..n - 1]).unwrap();
        assert_eq!(back, req);

        let mantissas: Vec<i32, CHUNK_LEN> = (0..CHUNK_LEN as i32).map(|i| i32::MIN + i).collect();
        let resp = crate::transport::Uplink::Reply {
            seq: u16::MAX,
            body: Response::Solution {
                direction: 2,
                offset: u32::MAX,
                exponent: i32::MIN,
                mantissas,
            },
        };
        let n = frame::encode(&resp, &mut buf).unwrap();
        assert!(n + 16 <= MAX_FRAME_LEN, "{n}: leave room for new fields");
        let direction = DirectionReport {
            iterations: u32::MAX,
            converged: false,
            residual: f64::MAX,
        };
        let max = PhaseCounters {
            cycles: u64::MAX,
            instructions: u64::MAX,
        };
        let report = SolveReport {
            iterations: u32::MAX,
            converged: false,
            residual: f64::MAX,
            directions: [direction; MAX_DIRECTIONS].into_iter().collect(),
            words_per_iteration: u32::MAX,
            mvus: u8::MAX,
            overlapping: true,
            mvu: PhaseCounters {
                cycles: u64::MAX,
                instructions: u64::MAX,
            },
            svu: PhaseCounters {
                cycles: u64::MAX,
                instructions: u64::MAX,
            },
            per_iteration: IterationCost {
                mvu_critical: max,
                svu_critical: max,
                mvu_total: max,
                svu_total: max,
            },
            saturations: u32::MAX,
            whole_solve: IterationCost {
                mvu_critical: max,
                svu_critical: max,
                mvu_total: max,
                svu_total: max,
            },
            first_iteration_scalar: max,
        };
        let resp = crate::transport::Uplink::Reply {
            seq: u16::MAX,
            body: Response::Solved(report),
        };
        let n = frame::encode(&resp, &mut buf).unwrap();
        assert!(n + 16 <= MAX_FRAME_LEN, "{n}: leave room for new fields");
        let back: crate::transport::Uplink = frame::decode(&mut buf[..n - 1]).unwrap();
        assert_eq!(back, resp);
        let info = TargetInfo {
            protocol_version: 1,
            firmware_version: heapless::String::try_from("0.1.0-abcdefghij").unwrap(),
            harts: 8,
            word_capacity: u32::MAX,
            tile_capacity: u32::MAX,
            max_n: u32::MAX,
            build_id: (0..BUILD_ID_MAX as u8).map(|b| 0xF0 | b).collect(),
        };
        assert!(frame::encode(
            &crate::transport::Uplink::Reply {
                seq: 1,
                body: Response::Hello(info)
            },
            &mut buf
        )
        .is_ok());
        let log = Envelope {
            seq: u16::MAX,
            body: Response::Log {
                dropped: u32::MAX,
                frames: (0..LOG_CHUNK).map(|_| 0xFF).collect(),
            },
        };
        let n = frame::encode(&log, &mut buf).unwrap();
        assert!(
            n <= MAX_FRAME_LEN - 64,
            "{n}: leave room for a transport header"
        );
    }

    /// The goal: at most 4.2 bytes on the wire per matrix nonzero (4 is the floor).
    #[test]
    fn a_full_words_chunk_costs_under_4_2_bytes_per_word() {
        let words: Vec<u32, CHUNK_LEN> = (0..CHUNK_LEN as u32).map(|i| 0xC000_0000 | i).collect();
        let req = Envelope {
            seq: 0xFFFF,
            body: Request::Words {
                offset: 0x0010_0000,
                words,
            },
        };
        let mut buf = [0u8; MAX_FRAME_LEN];
        let n = frame::encode(&req, &mut buf).unwrap();
        let per_word = n as f64 / CHUNK_LEN as f64;
        assert!(per_word <= 4.15, "{n} bytes: {per_word} per word");
    }
}
