//! The serial client: how the host drives a target (a board, or QEMU through its pty).
//!
//! Two layers:
//!
//! - [`Link`] moves one request and its response: it frames an [`Envelope`] with a sequence
//!   number, then reads until the response with that number arrives, skipping line noise and
//!   stale answers, within a deadline. It knows nothing about the session order.
//! - [`Target`] is the session: the `Hello` handshake and version check, then matrix and vector
//!   uploads in chunks, `Solve` and `ReadSolution`, converting vectors to and from block floating
//!   point on the way.
//!
//! The link works over any [`Port`] (a `Read + Write` byte stream with a read timeout), so the
//! unit tests run it against an in-process target on a socket pair; the serial port and the
//! QEMU pty go through [`serialport`].
//!
//! [`Envelope`]: deform_shared::protocol::Envelope

mod error;
mod port;
mod target;
mod wire;

#[cfg(test)]
mod fake_target;
#[cfg(test)]
mod test_systems;

pub use error::{Capacity, LinkError};
pub use port::{open_serial, Port, BAUD_RATE};
pub use target::{
    full_upload_bytes, update_bytes, Target, Timeouts, UpdateError, UpdateReport, UploadProgress,
};
pub use wire::{request_name, Link, LinkStats, DEFAULT_REQUEST_TIMEOUT};
