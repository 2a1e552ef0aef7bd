//! The guarded wire: one value of every variant of every message enum, encoded, against the
//! bytes committed in `tests/golden/wire.txt`.
//!
//! postcard writes an enum variant as its index, so reordering, inserting or removing a variant
//! silently changes what every later variant means on the wire; so does changing a field. This
//! test catches all of them:
//!
//! - every enum has a `Golden` impl whose `variant` is an exhaustive `match` (for `Request`, its
//!   own `Request::name`): a new variant does not compile until it is named;
//! - the samples must cover every variant serde's derive knows of (read from the derive itself,
//!   see [`serde_variants`]), so a named variant without a sample fails the test;
//! - the encoded bytes must equal the committed ones, and a missing or extra entry fails.
//!
//! When the change is intended: bump `PROTOCOL_VERSION` (shared/src/protocol.rs) — or
//! `LOADER_PROTOCOL_VERSION` (shared/src/loader.rs) for the loader's messages — describe the
//! change in docs/PROTOCOL.md (docs/LOADER.md), then re-bless with
//!
//! ```text
//! DEFORM_BLESS=1 cargo test -p deform-shared --test golden
//! ```
//!
//! Blessing refuses to rewrite a section whose bytes changed under the same version number.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::PathBuf;

use deform_shared::dynamics::{DynamicError, DynamicParams, DynamicTool};
use deform_shared::frame::{self, FrameError};
use deform_shared::live::{
    Coupling, FieldChunk, ForceReport, FrameReport, LiveError, LiveParams, ModelReport,
    MotionQuery, MotionReport, ToolRow,
};
use deform_shared::loader::{
    ImageHeader, LoaderEnvelope, LoaderError, LoaderInfo, LoaderRequest, LoaderResponse,
    LOADER_PROTOCOL_VERSION,
};
use deform_shared::matrix::{MatrixError, TileHeader};
use deform_shared::protocol::{
    DirectionReport, Envelope, ErrorCode, IterationCost, PhaseCounters, Request, Response,
    SessionStep, SolveFailure, SolveParams, SolveReport, Start, StateVector, TargetInfo,
    VectorSlot, PROTOCOL_VERSION,
};
use deform_shared::transport::Uplink;
use serde::de::{self, Deserialize, Deserializer, Visitor};
use serde::Serialize;

/// A message type whose every variant has a golden sample.
trait Golden: Serialize + Sized + for<'de> Deserialize<'de> {
    /// The type's name in the golden file.
    const NAME: &'static str;
    /// One value (at least) per variant.
    fn samples() -> Vec<Self>;
    /// The variant's name: an exhaustive `match`, so that a new variant fails to compile here.
    fn variant(&self) -> &'static str;
}

fn tile() -> TileHeader {
    TileHeader {
        row_base: 512,
        col_base: 1024,
        rows: 300,
        words: 70_000,
        mvu: 3,
        mirrored: true,
    }
}

fn params() -> SolveParams {
    SolveParams {
        max_iterations: 1000,
        tolerance: 1e-8,
        start: Start::Previous,
        directions: 3,
        cycle_budget: 300_000,
    }
}

fn report() -> SolveReport {
    let d = DirectionReport {
        iterations: 37,
        converged: true,
        residual: 3.5e-9,
    };
    SolveReport {
        iterations: 40,
        converged: false,
        residual: 1.25e-3,
        directions: [d, d].into_iter().collect(),
        words_per_iteration: 4242,
        mvus: 4,
        overlapping: true,
        mvu: PhaseCounters {
            cycles: 1 << 33,
            instructions: 123_456_789,
        },
        svu: PhaseCounters {
            cycles: 77,
            instructions: 66,
        },
        per_iteration: IterationCost {
            mvu_critical: counters(2_000, 1_000),
            svu_critical: counters(390, 200),
            mvu_total: counters(8_000, 4_000),
            svu_total: counters(1_500, 800),
        },
        saturations: 1,
        whole_solve: IterationCost {
            mvu_critical: counters(82_000, 41_000),
            svu_critical: counters(16_000, 8_100),
            mvu_total: counters(320_000, 160_000),
            svu_total: counters(64_000, 32_000),
        },
        first_iteration_scalar: counters(6_000, 3_012),
    }
}

fn counters(cycles: u64, instructions: u64) -> PhaseCounters {
    PhaseCounters {
        cycles,
        instructions,
    }
}

fn info() -> TargetInfo {
    TargetInfo {
        protocol_version: 5,
        firmware_version: heapless::String::try_from("0.1.0").unwrap(),
        harts: 4,
        word_capacity: 524_288,
        tile_capacity: 4096,
        max_n: 65_536,
        build_id: [0xDE, 0xAD, 0xBE, 0xEF].into_iter().collect(),
    }
}

impl Golden for Request {
    const NAME: &'static str = "Request";
    fn samples() -> Vec<Self> {
        vec![
            // A fixed number, not PROTOCOL_VERSION: a version bump alone changes no bytes.
            Request::Hello {
                protocol_version: 5,
            },
            Request::BeginMatrix {
                n: 1728,
                frac_bits: 12,
                tiles: 16,
                words: 27_093,
            },
            Request::Tile(tile()),
            Request::Words {
                offset: 256,
                words: [0xC000_0001, 0x0020_0FFF, 7].into_iter().collect(),
            },
            Request::EndMatrix { crc32: 0x1234_5678 },
            Request::BeginVector {
                slot: VectorSlot::InitialGuess { direction: 2 },
                exponent: -7,
                len: 1728,
            },
            Request::VectorData {
                slot: VectorSlot::RHS,
                offset: 128,
                mantissas: [-1, i32::MIN, 5].into_iter().collect(),
            },
            Request::Solve(params()),
            Request::ReadSolution {
                direction: 1,
                offset: 384,
                len: 96,
            },
            Request::BeginUpdate {
                words: 27_093,
                frac_bits: 9,
            },
            Request::UpdateValues {
                offset: 0,
                values: [-1_048_576, 1_048_575].into_iter().collect(),
            },
            Request::EndUpdate { crc32: 0xCAFE_F00D },
            Request::LiveTool(ToolRow {
                node: 292,
                diagonal: 26 << 9,
                row: [
                    Coupling {
                        column: 291,
                        value: -512,
                    },
                    Coupling {
                        column: 293,
                        value: -(1 << 20),
                    },
                ]
                .into_iter()
                .collect(),
            }),
            Request::LiveStart(LiveParams {
                tolerance: 1e-4,
                max_iterations: 60,
                cycle_budget: 300_000,
                scale: [1.0, 2.0, 0.5],
            }),
            Request::LiveFrame {
                tool: [[0.0, -0.25, 1.5e-3]].into_iter().collect(),
            },
            Request::LiveForce {
                tool: [[1.0, 0.0, -2.0], [0.5, 0.5, 0.5]].into_iter().collect(),
            },
            Request::ReadField {
                offset: 80,
                stride: 2,
                surface: None,
            },
            Request::ReadField {
                offset: 56,
                stride: 1,
                surface: Some([9, 9, 9]),
            },
            Request::LiveForceTool {
                nodes: [10, 300].into_iter().collect(),
            },
            Request::LiveLoad {
                load: [[0.0, -0.25, 1.5e-3]].into_iter().collect(),
            },
            Request::LiveLoadQuery {
                load: [[1.0, 0.0, -2.0], [0.5, 0.5, 0.5]].into_iter().collect(),
            },
            Request::BeginStiffness { frac_bits: 18 },
            Request::DynamicTool(DynamicTool {
                s: ToolRow {
                    node: 292,
                    diagonal: 700_000,
                    row: [Coupling {
                        column: 291,
                        value: -6_845,
                    }]
                    .into_iter()
                    .collect(),
                },
                k: ToolRow {
                    node: 292,
                    diagonal: 26 << 9,
                    row: [Coupling {
                        column: 291,
                        value: -512,
                    }]
                    .into_iter()
                    .collect(),
                },
            }),
            Request::DynamicStart(DynamicParams {
                h: 1e-3,
                mass: 5e-3,
                s_scale: -7,
                k_scale: 0,
                tolerance: 1e-4,
                max_iterations: 60,
                cycle_budget: 100_000,
            }),
            Request::DynamicFrame {
                tool: [[0.0, -0.25, 1.5e-3]].into_iter().collect(),
            },
            Request::ReadVector {
                vector: StateVector::Residual,
                direction: 2,
                offset: 384,
                len: 100,
            },
        ]
    }
    fn variant(&self) -> &'static str {
        // `Request::name` is the exhaustive match (shared/src/protocol.rs).
        self.name()
    }
}

impl Golden for Response {
    const NAME: &'static str = "Response";
    fn samples() -> Vec<Self> {
        vec![
            Response::Hello(info()),
            Response::Ack,
            Response::Error(ErrorCode::ChunkTooLong),
            Response::Solved(report()),
            Response::Solution {
                direction: 2,
                offset: 128,
                exponent: -20,
                mantissas: [3, -3, 0x3FFF_FFFF].into_iter().collect(),
            },
            Response::Log {
                dropped: 12,
                frames: [1, 2, 3, 0].into_iter().collect(),
            },
            Response::LiveReady(ModelReport {
                solves: 3,
                iterations: 412,
                cycles: 1 << 33,
                converged: true,
                stall_cycles: 1 << 32,
            }),
            Response::LiveFrame(FrameReport {
                force: [-0.5, 0.0, 3.25],
                residual: 1e-5,
                iterations: 23,
                cycles: 281_000,
                stall_cycles: 140_000,
            }),
            Response::LiveForce(ForceReport {
                force: [1.0, -1.0, 0.125],
                cycles: 900,
                stall_cycles: 0,
            }),
            Response::Field(FieldChunk {
                offset: 6,
                exponent: -12,
                cycles: 21_000,
                stall_cycles: 9_000,
                values: [1, 0, -255, 3, i16::MIN, i16::MAX].into_iter().collect(),
            }),
            Response::LiveMotion(MotionReport {
                displacement: [-0.5, 0.0, 3.25e-3],
                residual: 1e-5,
                iterations: 23,
                cycles: 281_000,
                stall_cycles: 140_000,
            }),
            Response::LiveMotionQuery(MotionQuery {
                displacement: [1.0, -1.0, 0.125],
                cycles: 900,
                stall_cycles: 450,
            }),
        ]
    }
    fn variant(&self) -> &'static str {
        match self {
            Response::Hello(_) => "Hello",
            Response::Ack => "Ack",
            Response::Error(_) => "Error",
            Response::Solved(_) => "Solved",
            Response::Solution { .. } => "Solution",
            Response::Log { .. } => "Log",
            Response::LiveReady(_) => "LiveReady",
            Response::LiveFrame(_) => "LiveFrame",
            Response::LiveForce(_) => "LiveForce",
            Response::Field(_) => "Field",
            Response::LiveMotion(_) => "LiveMotion",
            Response::LiveMotionQuery(_) => "LiveMotionQuery",
        }
    }
}

impl Golden for Uplink {
    const NAME: &'static str = "Uplink";
    fn samples() -> Vec<Self> {
        vec![
            Uplink::Reply {
                seq: 0xFFFF,
                body: Response::Ack,
            },
            Uplink::Ack { seq: 300 },
            Uplink::Nak { expected: 9 },
            Uplink::NotSynced { seq: 1 },
            Uplink::Notice {
                seq: 2,
                body: Response::Error(ErrorCode::MantissaOutOfRange),
            },
            Uplink::Panic {
                message: heapless::String::try_from("panicked at src/main.rs:1:1").unwrap(),
            },
        ]
    }
    fn variant(&self) -> &'static str {
        match self {
            Uplink::Reply { .. } => "Reply",
            Uplink::Ack { .. } => "Ack",
            Uplink::Nak { .. } => "Nak",
            Uplink::NotSynced { .. } => "NotSynced",
            Uplink::Notice { .. } => "Notice",
            Uplink::Panic { .. } => "Panic",
        }
    }
}

impl Golden for ErrorCode {
    const NAME: &'static str = "ErrorCode";
    fn samples() -> Vec<Self> {
        vec![
            ErrorCode::Frame(FrameError::Crc),
            ErrorCode::VersionMismatch { target: 5 },
            ErrorCode::OutOfOrder(SessionStep::NoRhs),
            ErrorCode::TooManyWords {
                requested: 600_000,
                capacity: 524_288,
            },
            ErrorCode::TooManyTiles {
                requested: 5000,
                capacity: 4096,
            },
            ErrorCode::DimensionTooLarge {
                requested: 70_000,
                capacity: 65_536,
            },
            ErrorCode::BadFracBits(21),
            ErrorCode::UnexpectedOffset {
                expected: 128,
                got: 256,
            },
            ErrorCode::ChunkTooLong,
            ErrorCode::Matrix(MatrixError::MissingEnd { tile: 3 }),
            ErrorCode::MatrixCrc {
                computed: 0xDEAD_BEEF,
            },
            ErrorCode::LengthMismatch {
                expected: 1728,
                got: 1727,
            },
            ErrorCode::MantissaOutOfRange,
            ErrorCode::Solve(SolveFailure::NotPositiveDefinite { iteration: 4 }),
            ErrorCode::ValueOutOfRange(-2_000_000),
            ErrorCode::DirectionOutOfRange {
                direction: 3,
                max: 3,
            },
            ErrorCode::OverlapTooLarge {
                rows: 9000,
                capacity: 8192,
            },
            ErrorCode::Live(LiveError::ToolCount {
                expected: 4,
                got: 3,
            }),
            ErrorCode::Dynamic(DynamicError::NoStiffness),
        ]
    }
    fn variant(&self) -> &'static str {
        match self {
            ErrorCode::Frame(_) => "Frame",
            ErrorCode::VersionMismatch { .. } => "VersionMismatch",
            ErrorCode::OutOfOrder(_) => "OutOfOrder",
            ErrorCode::TooManyWords { .. } => "TooManyWords",
            ErrorCode::TooManyTiles { .. } => "TooManyTiles",
            ErrorCode::DimensionTooLarge { .. } => "DimensionTooLarge",
            ErrorCode::BadFracBits(_) => "BadFracBits",
            ErrorCode::UnexpectedOffset { .. } => "UnexpectedOffset",
            ErrorCode::ChunkTooLong => "ChunkTooLong",
            ErrorCode::Matrix(_) => "Matrix",
            ErrorCode::MatrixCrc { .. } => "MatrixCrc",
            ErrorCode::LengthMismatch { .. } => "LengthMismatch",
            ErrorCode::MantissaOutOfRange => "MantissaOutOfRange",
            ErrorCode::Solve(_) => "Solve",
            ErrorCode::ValueOutOfRange(_) => "ValueOutOfRange",
            ErrorCode::DirectionOutOfRange { .. } => "DirectionOutOfRange",
            ErrorCode::OverlapTooLarge { .. } => "OverlapTooLarge",
            ErrorCode::Live(_) => "Live",
            ErrorCode::Dynamic(_) => "Dynamic",
        }
    }
}

impl Golden for SessionStep {
    const NAME: &'static str = "SessionStep";
    fn samples() -> Vec<Self> {
        use SessionStep::*;
        vec![
            NoMatrixUpload,
            TileIncomplete,
            TileExpected,
            TilesMissing,
            NoVectorUpload,
            VectorIncomplete,
            NoMatrix,
            NoRhs,
            NoInitialGuess,
            NoPreviousSolution,
            NoSolution,
            NoUpdate,
            UpdateIncomplete,
        ]
    }
    fn variant(&self) -> &'static str {
        use SessionStep::*;
        match self {
            NoMatrixUpload => "NoMatrixUpload",
            TileIncomplete => "TileIncomplete",
            TileExpected => "TileExpected",
            TilesMissing => "TilesMissing",
            NoVectorUpload => "NoVectorUpload",
            VectorIncomplete => "VectorIncomplete",
            NoMatrix => "NoMatrix",
            NoRhs => "NoRhs",
            NoInitialGuess => "NoInitialGuess",
            NoPreviousSolution => "NoPreviousSolution",
            NoSolution => "NoSolution",
            NoUpdate => "NoUpdate",
            UpdateIncomplete => "UpdateIncomplete",
        }
    }
}

impl Golden for SolveFailure {
    const NAME: &'static str = "SolveFailure";
    fn samples() -> Vec<Self> {
        vec![
            SolveFailure::NotPositiveDefinite { iteration: 9 },
            SolveFailure::WorkspaceTooSmall,
            SolveFailure::BadDirections(4),
        ]
    }
    fn variant(&self) -> &'static str {
        match self {
            SolveFailure::NotPositiveDefinite { .. } => "NotPositiveDefinite",
            SolveFailure::WorkspaceTooSmall => "WorkspaceTooSmall",
            SolveFailure::BadDirections(_) => "BadDirections",
        }
    }
}

impl Golden for FrameError {
    const NAME: &'static str = "FrameError";
    fn samples() -> Vec<Self> {
        use FrameError::*;
        vec![BufferTooSmall, TooLong, Cobs, TooShort, Crc, Message]
    }
    fn variant(&self) -> &'static str {
        use FrameError::*;
        match self {
            BufferTooSmall => "BufferTooSmall",
            TooLong => "TooLong",
            Cobs => "Cobs",
            TooShort => "TooShort",
            Crc => "Crc",
            Message => "Message",
        }
    }
}

impl Golden for MatrixError {
    const NAME: &'static str = "MatrixError";
    fn samples() -> Vec<Self> {
        vec![
            MatrixError::EmptyTile { tile: 1 },
            MatrixError::RowsOutOfRange { tile: 2 },
            MatrixError::WordCountMismatch {
                tile: 3,
                expected: 10,
                found: 11,
            },
            MatrixError::RowCountMismatch {
                tile: 4,
                expected: 5,
                found: 6,
            },
            MatrixError::MissingEnd { tile: 5 },
            MatrixError::EarlyEnd { tile: 6 },
            MatrixError::ColumnOutOfRange {
                tile: 7,
                column: 600,
            },
            MatrixError::TotalWordsMismatch {
                expected: 100,
                found: 99,
            },
            MatrixError::RowTooLong { tile: 8, row: 300 },
            MatrixError::MvuOutOfRange {
                tile: 9,
                mvu: 8,
                harts: 4,
            },
        ]
    }
    fn variant(&self) -> &'static str {
        match self {
            MatrixError::EmptyTile { .. } => "EmptyTile",
            MatrixError::RowsOutOfRange { .. } => "RowsOutOfRange",
            MatrixError::WordCountMismatch { .. } => "WordCountMismatch",
            MatrixError::RowCountMismatch { .. } => "RowCountMismatch",
            MatrixError::MissingEnd { .. } => "MissingEnd",
            MatrixError::EarlyEnd { .. } => "EarlyEnd",
            MatrixError::ColumnOutOfRange { .. } => "ColumnOutOfRange",
            MatrixError::TotalWordsMismatch { .. } => "TotalWordsMismatch",
            MatrixError::RowTooLong { .. } => "RowTooLong",
            MatrixError::MvuOutOfRange { .. } => "MvuOutOfRange",
        }
    }
}

impl Golden for VectorSlot {
    const NAME: &'static str = "VectorSlot";
    fn samples() -> Vec<Self> {
        vec![
            VectorSlot::Rhs { direction: 1 },
            VectorSlot::InitialGuess { direction: 2 },
        ]
    }
    fn variant(&self) -> &'static str {
        match self {
            VectorSlot::Rhs { .. } => "Rhs",
            VectorSlot::InitialGuess { .. } => "InitialGuess",
        }
    }
}

impl Golden for StateVector {
    const NAME: &'static str = "StateVector";
    fn samples() -> Vec<Self> {
        vec![
            StateVector::Rhs,
            StateVector::Velocity,
            StateVector::Residual,
        ]
    }
    fn variant(&self) -> &'static str {
        match self {
            StateVector::Rhs => "Rhs",
            StateVector::Velocity => "Velocity",
            StateVector::Residual => "Residual",
        }
    }
}

impl Golden for Start {
    const NAME: &'static str = "Start";
    fn samples() -> Vec<Self> {
        vec![
            Start::Zero,
            Start::Previous,
            Start::Uploaded,
            Start::Predicted,
        ]
    }
    fn variant(&self) -> &'static str {
        match self {
            Start::Zero => "Zero",
            Start::Previous => "Previous",
            Start::Uploaded => "Uploaded",
            Start::Predicted => "Predicted",
        }
    }
}

impl Golden for DynamicError {
    const NAME: &'static str = "DynamicError";
    fn samples() -> Vec<Self> {
        vec![
            DynamicError::NoStiffness,
            DynamicError::RowsDiffer,
            DynamicError::BadParams,
            DynamicError::NotStarted,
        ]
    }
    fn variant(&self) -> &'static str {
        match self {
            DynamicError::NoStiffness => "NoStiffness",
            DynamicError::RowsDiffer => "RowsDiffer",
            DynamicError::BadParams => "BadParams",
            DynamicError::NotStarted => "NotStarted",
        }
    }
}

impl Golden for LiveError {
    const NAME: &'static str = "LiveError";
    fn samples() -> Vec<Self> {
        vec![
            LiveError::NodeOutOfRange { node: 9999 },
            LiveError::ColumnOutOfRange { column: 70_000 },
            LiveError::DuplicateNode { node: 3 },
            LiveError::TooManyNodes { max: 8 },
            LiveError::ValueOutOfRange,
            LiveError::NoTool,
            LiveError::NotStarted,
            LiveError::ToolCount {
                expected: 2,
                got: 1,
            },
            LiveError::NotFinite,
            LiveError::NoFrame,
            LiveError::BadStride,
            LiveError::FixedToolNode { node: 7 },
            LiveError::MixedKinds,
            LiveError::WrongKind,
            LiveError::BadGrid {
                grid: [9, 9, 8],
                nodes: 729,
            },
            LiveError::FieldOffset {
                offset: 800,
                selected: 729,
            },
        ]
    }
    fn variant(&self) -> &'static str {
        match self {
            LiveError::NodeOutOfRange { .. } => "NodeOutOfRange",
            LiveError::ColumnOutOfRange { .. } => "ColumnOutOfRange",
            LiveError::DuplicateNode { .. } => "DuplicateNode",
            LiveError::TooManyNodes { .. } => "TooManyNodes",
            LiveError::ValueOutOfRange => "ValueOutOfRange",
            LiveError::NoTool => "NoTool",
            LiveError::NotStarted => "NotStarted",
            LiveError::ToolCount { .. } => "ToolCount",
            LiveError::NotFinite => "NotFinite",
            LiveError::NoFrame => "NoFrame",
            LiveError::BadStride => "BadStride",
            LiveError::FixedToolNode { .. } => "FixedToolNode",
            LiveError::MixedKinds => "MixedKinds",
            LiveError::WrongKind => "WrongKind",
            LiveError::BadGrid { .. } => "BadGrid",
            LiveError::FieldOffset { .. } => "FieldOffset",
        }
    }
}

impl Golden for LoaderRequest {
    const NAME: &'static str = "LoaderRequest";
    fn samples() -> Vec<Self> {
        vec![
            LoaderRequest::Hello { version: 1 },
            LoaderRequest::Begin(ImageHeader {
                load_address: 0x8010_0000,
                length: 70_000,
                entry: 0x8010_0000,
                crc32: 0x0BAD_CAFE,
            }),
            LoaderRequest::Chunk {
                index: 3,
                data: [0, 1, 0xFF].into_iter().collect(),
            },
            LoaderRequest::Verify,
            LoaderRequest::Start,
        ]
    }
    fn variant(&self) -> &'static str {
        match self {
            LoaderRequest::Hello { .. } => "Hello",
            LoaderRequest::Begin(_) => "Begin",
            LoaderRequest::Chunk { .. } => "Chunk",
            LoaderRequest::Verify => "Verify",
            LoaderRequest::Start => "Start",
        }
    }
}

impl Golden for LoaderResponse {
    const NAME: &'static str = "LoaderResponse";
    fn samples() -> Vec<Self> {
        vec![
            LoaderResponse::Hello(LoaderInfo {
                version: 1,
                ram_start: 0x8000_0000,
                ram_end: 0x8800_0000,
                loader_start: 0x8000_0000,
                loader_end: 0x8001_0000,
            }),
            LoaderResponse::Ack,
            LoaderResponse::Verified { crc32: 0x0BAD_CAFE },
            LoaderResponse::Starting { entry: 0x8010_0000 },
            LoaderResponse::Error(LoaderError::NoImage),
        ]
    }
    fn variant(&self) -> &'static str {
        match self {
            LoaderResponse::Hello(_) => "Hello",
            LoaderResponse::Ack => "Ack",
            LoaderResponse::Verified { .. } => "Verified",
            LoaderResponse::Starting { .. } => "Starting",
            LoaderResponse::Error(_) => "Error",
        }
    }
}

impl Golden for LoaderError {
    const NAME: &'static str = "LoaderError";
    fn samples() -> Vec<Self> {
        vec![
            LoaderError::Frame(FrameError::Cobs),
            LoaderError::VersionMismatch { loader: 1 },
            LoaderError::NoImage,
            LoaderError::EmptyImage,
            LoaderError::OutOfRange {
                start: 0x1000,
                end: 0x2000,
            },
            LoaderError::OverlapsLoader {
                start: 0x8000_0000,
                end: 0x8000_1000,
            },
            LoaderError::EntryOutsideImage { entry: 0x10 },
            LoaderError::ChunkOutOfOrder {
                expected: 2,
                got: 4,
            },
            LoaderError::ChunkLength {
                index: 1,
                expected: 256,
                got: 200,
            },
            LoaderError::ImageIncomplete {
                received: 3,
                chunks: 9,
            },
            LoaderError::ImageCrc {
                expected: 1,
                computed: 2,
            },
            LoaderError::NotVerified,
        ]
    }
    fn variant(&self) -> &'static str {
        match self {
            LoaderError::Frame(_) => "Frame",
            LoaderError::VersionMismatch { .. } => "VersionMismatch",
            LoaderError::NoImage => "NoImage",
            LoaderError::EmptyImage => "EmptyImage",
            LoaderError::OutOfRange { .. } => "OutOfRange",
            LoaderError::OverlapsLoader { .. } => "OverlapsLoader",
            LoaderError::EntryOutsideImage { .. } => "EntryOutsideImage",
            LoaderError::ChunkOutOfOrder { .. } => "ChunkOutOfOrder",
            LoaderError::ChunkLength { .. } => "ChunkLength",
            LoaderError::ImageIncomplete { .. } => "ImageIncomplete",
            LoaderError::ImageCrc { .. } => "ImageCrc",
            LoaderError::NotVerified => "NotVerified",
        }
    }
}

/// The variant names serde's derive gives `T`: its `Deserialize` hands them to
/// `deserialize_enum`, which this deserializer captures before refusing to go on. Independent
/// of [`Golden::variant`], so a variant named there but without a sample is still noticed.
fn serde_variants<T: for<'de> Deserialize<'de>>() -> Vec<&'static str> {
    struct Capture;
    #[derive(Debug)]
    struct Captured(Vec<&'static str>);
    impl std::fmt::Display for Captured {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            write!(f, "{:?}", self.0)
        }
    }
    impl std::error::Error for Captured {}
    impl de::Error for Captured {
        fn custom<M: std::fmt::Display>(_: M) -> Self {
            Captured(Vec::new())
        }
    }
    impl<'de> Deserializer<'de> for Capture {
        type Error = Captured;
        fn deserialize_any<V: Visitor<'de>>(self, _: V) -> Result<V::Value, Captured> {
            Err(Captured(Vec::new()))
        }
        fn deserialize_enum<V: Visitor<'de>>(
            self,
            _name: &'static str,
            variants: &'static [&'static str],
            _: V,
        ) -> Result<V::Value, Captured> {
            Err(Captured(variants.to_vec()))
        }
        serde::forward_to_deserialize_any! {
            bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string bytes byte_buf
            option unit unit_struct newtype_struct seq tuple tuple_struct map struct identifier
            ignored_any
        }
    }
    match T::deserialize(Capture) {
        Err(Captured(variants)) => variants,
        Ok(_) => unreachable!("Capture never produces a value"),
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().fold(String::new(), |mut s, b| {
        let _ = write!(s, "{b:02x}");
        s
    })
}

/// The golden entries of `T` under `section`: `Name::Variant[#i] → hex(postcard(value))`, after
/// checking that every variant has a sample and that each sample decodes back to itself.
fn entries<T: Golden + PartialEq + std::fmt::Debug>(
    section: &str,
    out: &mut BTreeMap<String, BTreeMap<String, String>>,
) {
    let samples = T::samples();
    let covered: BTreeSet<&str> = samples.iter().map(T::variant).collect();
    let declared: BTreeSet<&str> = serde_variants::<T>().into_iter().collect();
    assert_eq!(
        covered,
        declared,
        "{}: every variant needs a golden sample in shared/tests/golden.rs",
        T::NAME
    );
    let mut seen = BTreeMap::<&str, usize>::new();
    for sample in &samples {
        let bytes = postcard::to_allocvec(sample).expect("samples encode");
        let back: T = postcard::from_bytes(&bytes).expect("samples decode");
        assert_eq!(&back, sample, "{} does not round-trip", T::NAME);
        let variant = sample.variant();
        let n = seen.entry(variant).or_default();
        let key = match *n {
            0 => format!("{}::{variant}", T::NAME),
            i => format!("{}::{variant}#{i}", T::NAME),
        };
        *n += 1;
        out.entry(section.to_string())
            .or_default()
            .insert(key, hex(&bytes));
    }
}

/// Whole frames (COBS, CRC, delimiter) of an envelope each way: the framing is wire too.
fn frames(out: &mut BTreeMap<String, BTreeMap<String, String>>) {
    let mut buf = [0u8; 600];
    let request = Envelope {
        seq: 0x1234,
        body: Request::ReadSolution {
            direction: 0,
            offset: 128,
            len: 128,
        },
    };
    let n = frame::encode(&request, &mut buf).unwrap();
    let protocol = out.entry("protocol".to_string()).or_default();
    protocol.insert("Frame::Envelope<Request>".into(), hex(&buf[..n]));
    let uplink = Uplink::Reply {
        seq: 0x1234,
        body: Response::Ack,
    };
    let n = frame::encode(&uplink, &mut buf).unwrap();
    protocol.insert("Frame::Uplink".into(), hex(&buf[..n]));
    let loader = LoaderEnvelope::new(7, LoaderRequest::Verify);
    let n = frame::encode(&loader, &mut buf).unwrap();
    out.entry("loader".to_string()).or_default().insert(
        "Frame::LoaderEnvelope<LoaderRequest>".into(),
        hex(&buf[..n]),
    );
}

fn current() -> BTreeMap<String, BTreeMap<String, String>> {
    let mut out = BTreeMap::new();
    entries::<Request>("protocol", &mut out);
    entries::<Response>("protocol", &mut out);
    entries::<Uplink>("protocol", &mut out);
    entries::<ErrorCode>("protocol", &mut out);
    entries::<SessionStep>("protocol", &mut out);
    entries::<SolveFailure>("protocol", &mut out);
    entries::<FrameError>("protocol", &mut out);
    entries::<MatrixError>("protocol", &mut out);
    entries::<VectorSlot>("protocol", &mut out);
    entries::<Start>("protocol", &mut out);
    entries::<StateVector>("protocol", &mut out);
    entries::<LiveError>("protocol", &mut out);
    entries::<DynamicError>("protocol", &mut out);
    entries::<LoaderRequest>("loader", &mut out);
    entries::<LoaderResponse>("loader", &mut out);
    entries::<LoaderError>("loader", &mut out);
    frames(&mut out);
    out
}

fn versions() -> BTreeMap<String, u16> {
    BTreeMap::from([
        ("protocol".to_string(), PROTOCOL_VERSION),
        ("loader".to_string(), LOADER_PROTOCOL_VERSION),
    ])
}

fn golden_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/golden/wire.txt")
}

/// The file: `[section version]` headers, then `key hex` lines.
type Parsed = (
    BTreeMap<String, u16>,
    BTreeMap<String, BTreeMap<String, String>>,
);

fn parse(text: &str) -> Parsed {
    let mut versions = BTreeMap::new();
    let mut sections: BTreeMap<String, BTreeMap<String, String>> = BTreeMap::new();
    let mut section = String::new();
    for line in text
        .lines()
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
    {
        if let Some(header) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
            let (name, version) = header.split_once(' ').expect("[section version]");
            section = name.to_string();
            versions.insert(section.clone(), version.parse().expect("a version number"));
        } else {
            let (key, hex) = line.split_once(' ').expect("key hex");
            sections
                .entry(section.clone())
                .or_default()
                .insert(key.to_string(), hex.to_string());
        }
    }
    (versions, sections)
}

fn render(
    versions: &BTreeMap<String, u16>,
    sections: &BTreeMap<String, BTreeMap<String, String>>,
) -> String {
    let mut s = String::from(
        "# The wire's golden bytes (postcard encoding of one value per variant; whole frames).\n\
         # Written by `DEFORM_BLESS=1 cargo test -p deform-shared --test golden`; see that test.\n",
    );
    for (name, entries) in sections {
        let _ = writeln!(s, "\n[{name} {}]", versions[name]);
        for (key, hex) in entries {
            let _ = writeln!(s, "{key} {hex}");
        }
    }
    s
}

/// What differs between the committed and the current entries of each section.
fn differences(
    old: &BTreeMap<String, BTreeMap<String, String>>,
    new: &BTreeMap<String, BTreeMap<String, String>>,
) -> BTreeMap<String, Vec<String>> {
    let mut out: BTreeMap<String, Vec<String>> = BTreeMap::new();
    let empty = BTreeMap::new();
    for section in old.keys().chain(new.keys()).collect::<BTreeSet<_>>() {
        let (o, n) = (
            old.get(section).unwrap_or(&empty),
            new.get(section).unwrap_or(&empty),
        );
        for key in o.keys().chain(n.keys()).collect::<BTreeSet<_>>() {
            let line = match (o.get(key), n.get(key)) {
                (Some(a), Some(b)) if a == b => continue,
                (Some(a), Some(b)) => format!("  {key}: committed {a}, now {b}"),
                (Some(_), None) => format!("  {key}: committed, no longer produced"),
                (None, Some(b)) => format!("  {key}: new, {b}"),
                (None, None) => unreachable!(),
            };
            out.entry(section.clone()).or_default().push(line);
        }
    }
    out
}

#[test]
fn the_wire_encoding_matches_the_committed_golden_bytes() {
    let path = golden_path();
    let now = current();
    let versions = versions();
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    let (old_versions, old) = parse(&committed);
    let diff = differences(&old, &now);
    if std::env::var_os("DEFORM_BLESS").is_some_and(|v| v == "1") {
        let unbumped: Vec<&String> = diff
            .keys()
            .filter(|s| old_versions.get(*s) == versions.get(*s) && old.contains_key(*s))
            .collect();
        assert!(
            unbumped.is_empty(),
            "refusing to bless: the wire of {unbumped:?} changed but its version did not; bump \
             PROTOCOL_VERSION (shared/src/protocol.rs) or LOADER_PROTOCOL_VERSION \
             (shared/src/loader.rs) and document the change in docs/PROTOCOL.md (docs/LOADER.md)"
        );
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, render(&versions, &now)).unwrap();
        return;
    }
    let mut report = String::new();
    for (section, lines) in &diff {
        let _ = writeln!(report, "[{section}]\n{}", lines.join("\n"));
    }
    assert!(
        diff.is_empty() && old_versions == versions,
        "the wire encoding differs from {} (versions committed {old_versions:?}, now {versions:?}):\n{report}\n\
         If this change is intended: bump PROTOCOL_VERSION in shared/src/protocol.rs (or \
         LOADER_PROTOCOL_VERSION in shared/src/loader.rs for the loader), document the change in \
         docs/PROTOCOL.md (docs/LOADER.md), then re-bless with\n    \
         DEFORM_BLESS=1 cargo test -p deform-shared --test golden\n\
         If it is not: restore the variant order and fields (new variants and fields go at the END).",
        path.display()
    );
}
