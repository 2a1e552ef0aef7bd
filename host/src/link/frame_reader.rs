//! Frames from a [`Port`] with a deadline: the read side that the application link
//! ([`super::Link`]) and the serial loader's client (`crate::flash`) share. Both read whatever the
//! port has, feed it byte by byte to a [`FrameAccumulator`] and stop at the first delimited frame
//! or when the deadline passes; what they make of a frame differs, so the caller decodes it.

use std::io;
use std::time::Instant;

use deform_shared::frame::{Feed, FrameAccumulator};

use super::Port;

/// Bytes asked of the port per read.
const READ_CHUNK: usize = 1024;

/// What the next read brought.
#[derive(Debug)]
pub enum FrameEvent<T> {
    /// A delimited frame, as the caller's `decode` made it.
    Frame(T),
    /// A frame longer than `N` bytes was dropped.
    Overflow,
    /// The port reported end of file: the other end went away.
    EndOfFile,
    /// The deadline passed without a frame.
    TimedOut,
}

/// Bytes read from a port and not yet framed, and the frame being assembled (at most `N` bytes).
pub struct FrameReader<const N: usize> {
    frames: FrameAccumulator<N>,
    inbox: Vec<u8>,
    inbox_read: usize,
}

impl<const N: usize> Default for FrameReader<N> {
    fn default() -> Self {
        FrameReader {
            frames: FrameAccumulator::new(),
            inbox: Vec::with_capacity(READ_CHUNK),
            inbox_read: 0,
        }
    }
}

impl<const N: usize> FrameReader<N> {
    /// The next frame from `port`, reading it as needed until `deadline`, passed through
    /// `decode` (which gets the still COBS-encoded bytes that [`deform_shared::frame::decode`]
    /// takes); `on_read` is told how many bytes each read brought. Read timeouts and
    /// interruptions only mean "try again until the deadline"; other I/O errors are returned.
    pub fn next<P: Port, T>(
        &mut self,
        port: &mut P,
        deadline: Instant,
        mut on_read: impl FnMut(usize),
        decode: impl FnOnce(&mut [u8]) -> T,
    ) -> io::Result<FrameEvent<T>> {
        loop {
            while let Some(&byte) = self.inbox.get(self.inbox_read) {
                self.inbox_read += 1;
                match self.frames.feed(byte) {
                    Feed::Pending => {}
                    Feed::Overflow => return Ok(FrameEvent::Overflow),
                    Feed::Frame(body) => return Ok(FrameEvent::Frame(decode(body))),
                }
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(FrameEvent::TimedOut);
            }
            port.set_timeout(left)?;
            let mut buf = [0u8; READ_CHUNK];
            match port.read(&mut buf) {
                Ok(0) => return Ok(FrameEvent::EndOfFile),
                Ok(n) => {
                    on_read(n);
                    self.inbox.clear();
                    self.inbox.extend_from_slice(&buf[..n]);
                    self.inbox_read = 0;
                }
                Err(e) if super::is_timeout(&e) => {}
                Err(e) => return Err(e),
            }
        }
    }
}
