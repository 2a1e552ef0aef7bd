//! The serial client: how the host drives a target (a board, or QEMU through its pty).
//!
//! Two layers:
//!
//! - [`Link`] is the reliable transport (`transport.rs`, `docs/PROTOCOL.md`): numbered request
//!   frames with up to a window of them in flight, replies matched by number and delivered in
//!   order, retransmission on NAK or timeout, a bounded wait for everything. It knows nothing
//!   about the session order.
//! - [`Target`] is the session: the `Hello` handshake and version check, then matrix and vector
//!   uploads in chunks, `Solve` and `ReadSolution`, converting vectors to and from block floating
//!   point on the way.
//!
//! The link works over any [`Port`] (a `Read + Write` byte stream with a read timeout), so the
//! unit tests run it against an in-process target on a socket pair; the serial port and the
//! QEMU pty go through [`serialport`].
//!
//! [`Envelope`]: deform_shared::protocol::Envelope

mod adapt;
mod error;
mod flags;
mod frame_reader;
mod port;
mod target;
mod transport;

#[cfg(test)]
mod fake_target;
#[cfg(test)]
mod test_systems;

pub use adapt::{best_chunk, Adaptive, ChunkSize, MIN_CHUNK};
pub use error::{Capacity, LinkError};
pub use flags::LinkFlags;
pub use frame_reader::{FrameEvent, FrameReader};
pub use port::{is_timeout, open_serial, Port, BAUD_RATE};
pub use target::{
    full_upload_bytes, update_bytes, Target, Timeouts, UpdateError, UpdateReport, UploadProgress,
    DEFAULT_SOLVE_TIMEOUT,
};
pub use transport::{Link, LinkConfig, LinkStats, NoticeHandler, DEFAULT_REQUEST_TIMEOUT};
