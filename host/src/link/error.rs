use std::fmt;
use std::time::Duration;

use deform_shared::frame::FrameError;
use deform_shared::matrix::MatrixError;
use deform_shared::protocol::{ErrorCode, VectorSlot};

/// Everything that can go wrong between the host and a target.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    #[error("cannot open serial port {path}: {source}")]
    Open {
        path: String,
        #[source]
        source: serialport::Error,
    },
    #[error("serial I/O with the target failed: {0}")]
    Io(#[from] std::io::Error),
    #[error(
        "no answer to {request}: nothing acknowledged for {after:.1?} ({retries} \
         retransmissions; is the target running, on this port, and the line not too noisy? see \
         --link-timeout and --retries)"
    )]
    Timeout {
        request: &'static str,
        after: Duration,
        retries: u32,
    },
    #[error(
        "the target reset mid-session (it answered as a freshly booted target that has not \
         shaken hands): its matrix and vectors are gone"
    )]
    TargetReset,
    #[error("the target firmware panicked: {message}")]
    TargetPanicked { message: String },
    #[error("the connection to the target is gone: {0} (QEMU exited, or the board was unplugged)")]
    Disconnected(&'static str),
    #[error(
        "the target stopped reading: a write to it made no progress within the link's timeout"
    )]
    WriteStalled,
    #[error(
        "the target answers in a format this host does not understand ({frames} well-formed \
         frames that do not decode): is it running firmware for another protocol version than \
         {host}? Rebuild and flash it from this checkout (`cargo xtask firmware`)"
    )]
    Incompatible { frames: u64, host: u16 },
    #[error("the target refused {request}: {code}")]
    Target {
        request: &'static str,
        code: ErrorCode,
    },
    #[error("unexpected answer to {request}: expected {expected}, got {got}")]
    Protocol {
        request: &'static str,
        expected: &'static str,
        got: String,
    },
    #[error(
        "protocol version mismatch: the host speaks version {host}, the target version {target}; \
         rebuild and flash the firmware from this checkout (`cargo xtask firmware`)"
    )]
    VersionMismatch { host: u16, target: u16 },
    #[error("too large for the target: {requested} {what} requested, the target holds at most {capacity}")]
    TooLarge {
        what: Capacity,
        requested: u64,
        capacity: u32,
    },
    #[error("the encoded matrix is malformed: {0}")]
    MalformedMatrix(MatrixError),
    #[error("{slot:?} entry {index} is {value}, which has no block-floating-point mantissa")]
    NotFinite {
        slot: VectorSlot,
        index: usize,
        value: f64,
    },
    #[error("{0} right-hand sides given; a fused solve takes 1 to {max}", max = deform_shared::protocol::MAX_DIRECTIONS)]
    Directions(usize),
    #[error("cannot frame {request}: {source}")]
    Encode {
        request: &'static str,
        #[source]
        source: FrameError,
    },
}

impl LinkError {
    /// The target's own error code, if it refused a request.
    pub fn target_code(&self) -> Option<ErrorCode> {
        match self {
            LinkError::Target { code, .. } => Some(*code),
            _ => None,
        }
    }
}

/// Which of the target's capacities ([`TargetInfo`](deform_shared::protocol::TargetInfo)) a
/// matrix or vector exceeds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Capacity {
    /// `word_capacity`: instruction words in the matrix store.
    MatrixWords,
    /// `tile_capacity`: tile headers in the matrix store.
    MatrixTiles,
    /// `max_n`: the length of the target's vectors.
    Dimension,
}

impl fmt::Display for Capacity {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Capacity::MatrixWords => "matrix words",
            Capacity::MatrixTiles => "matrix tiles",
            Capacity::Dimension => "rows (dimension n)",
        })
    }
}
