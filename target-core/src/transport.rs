//! The target's end of the reliable transport ([`deform_shared::transport`], `docs/PROTOCOL.md`):
//! it turns the raw UART byte stream into requests delivered to the session in sequence order,
//! each exactly once, and sends every reply, NAK, ACK and notice.
//!
//! The target never times anything: the host owns every timer and retransmits, and the target
//! only reacts to what arrives. That keeps the firmware's loop a plain "read a byte, feed it"
//! and makes this module deterministic, so that it is unit-tested and fuzzed on the host:
//!
//! - a request with the expected number is handled, then any requests held from beyond the gap
//!   it closed;
//! - one from within [`WINDOW`] ahead is held (selective repeat) and the missing number is
//!   NAKed, once per gap;
//! - one from up to [`WINDOW`] behind is a duplicate whose reply was lost: the cached reply is
//!   sent again and the request is *not* handled again;
//! - a frame that fails COBS, its CRC or decoding, or overruns the buffer, is NAKed;
//! - `Hello` resynchronises at any number; before the first `Hello` everything else is
//!   answered [`Uplink::NotSynced`].
//!
//! Like the session it never panics and never indexes out of bounds, whatever the bytes.

use deform_shared::frame::{self, Feed, FrameAccumulator, FrameError};
use deform_shared::protocol::{Envelope, ErrorCode, Request, Response, MAX_FRAME_LEN};
use deform_shared::transport::{ahead, behind, long_running, Uplink, PANIC_MESSAGE_LEN, WINDOW};

const SLOTS: usize = WINDOW as usize;

/// Where the link's frames go, and where unsolicited notices come from.
pub trait Tx {
    /// Writes one complete frame (delimiter included).
    fn write(&mut self, frame: &[u8]);

    /// The next unsolicited message to send (a firmware log chunk), if any. The link asks
    /// before every reply, when the host is known to be listening, and sends each as an
    /// [`Uplink::Notice`].
    fn pending_notice(&mut self) -> Option<Response> {
        None
    }
}

/// A reply kept for a duplicate of its request.
struct CachedReply {
    seq: u16,
    len: usize,
    bytes: [u8; MAX_FRAME_LEN],
}

/// The target's transport state. About 10 KiB: the firmware keeps it in static storage.
pub struct TargetLink {
    frames: FrameAccumulator<MAX_FRAME_LEN>,
    /// A `Hello` has been seen since boot.
    synced: bool,
    /// The number of the next request to handle.
    expected: u16,
    /// A NAK for `expected` was sent since it last changed: a frame from beyond a gap NAKs only
    /// if none was (corrupt frames are NAKed every time, since each may be the retransmission
    /// that was awaited).
    gap_naked: bool,
    /// Requests from beyond a gap, by `seq % WINDOW`.
    held: [Option<(u16, Request)>; SLOTS],
    /// The replies to the last [`WINDOW`] requests, by `seq % WINDOW`; `len == 0`: none.
    replies: [CachedReply; SLOTS],
    notice_seq: u16,
    /// Scratch for frames that are not cached.
    out: [u8; MAX_FRAME_LEN],
}

impl Default for TargetLink {
    fn default() -> Self {
        Self::new()
    }
}

impl TargetLink {
    pub const fn new() -> Self {
        const NO_REPLY: CachedReply = CachedReply {
            seq: 0,
            len: 0,
            bytes: [0; MAX_FRAME_LEN],
        };
        TargetLink {
            frames: FrameAccumulator::new(),
            synced: false,
            expected: 0,
            gap_naked: false,
            held: [const { None }; SLOTS],
            replies: [NO_REPLY; SLOTS],
            notice_seq: 0,
            out: [0; MAX_FRAME_LEN],
        }
    }

    /// True once a `Hello` has been handled.
    pub fn synced(&self) -> bool {
        self.synced
    }

    /// Feeds one received byte; `handle` turns each in-order request into its response.
    pub fn feed(
        &mut self,
        byte: u8,
        handle: &mut impl FnMut(Request) -> Response,
        tx: &mut impl Tx,
    ) -> Option<LinkEvent> {
        let decoded = match self.frames.feed(byte) {
            Feed::Pending => return None,
            Feed::Overflow => Err(FrameError::TooLong),
            Feed::Frame(bytes) => frame::decode::<Envelope<Request>>(bytes),
        };
        Some(match decoded {
            Ok(Envelope { seq, body }) => self.receive(seq, body, handle, tx),
            Err(error) => {
                if self.synced {
                    // It names the request we wait for, so a frame from beyond the gap that
                    // follows need not NAK it again.
                    self.send_nak(tx);
                    self.gap_naked = true;
                }
                LinkEvent::Corrupt(error)
            }
        })
    }

    /// One intact request.
    fn receive(
        &mut self,
        seq: u16,
        request: Request,
        handle: &mut impl FnMut(Request) -> Response,
        tx: &mut impl Tx,
    ) -> LinkEvent {
        if matches!(request, Request::Hello { .. }) {
            // A retransmitted Hello whose reply was lost must not reset the session twice.
            if self.synced && behind(self.expected, seq) == Some(1) && self.resend(seq, tx) {
                return LinkEvent::Duplicate;
            }
            self.synced = true;
            self.expected = seq;
            self.held = [const { None }; SLOTS];
            for reply in &mut self.replies {
                reply.len = 0;
            }
        }
        if !self.synced {
            self.send(&Uplink::NotSynced { seq }, tx);
            return LinkEvent::NotSynced;
        }
        let distance = ahead(self.expected, seq);
        if distance == 0 {
            self.handle(seq, request, handle, tx);
            self.drain(handle, tx);
            return LinkEvent::Handled;
        }
        if distance < WINDOW {
            if let Some(slot) = self.held.get_mut(usize::from(seq % WINDOW)) {
                *slot = Some((seq, request));
            }
            if !self.gap_naked {
                self.send_nak(tx);
                self.gap_naked = true;
            }
            return LinkEvent::Held;
        }
        match behind(self.expected, seq) {
            Some(back) if back <= WINDOW => {
                self.resend(seq, tx);
                LinkEvent::Duplicate
            }
            // Too far off to be anything of this session's: say where we are.
            _ => {
                self.send_nak(tx);
                LinkEvent::OutOfWindow
            }
        }
    }

    /// Handles the held requests that now follow in order; NAKs the next gap if one remains.
    fn drain(&mut self, handle: &mut impl FnMut(Request) -> Response, tx: &mut impl Tx) {
        loop {
            let slot = usize::from(self.expected % WINDOW);
            match self.held.get_mut(slot).map(Option::take) {
                Some(Some((seq, request))) if seq == self.expected => {
                    self.handle(seq, request, handle, tx)
                }
                // A stale entry from an earlier round of the window.
                Some(Some(_)) | Some(None) | None => break,
            }
        }
        let expected = self.expected;
        let beyond_gap = self
            .held
            .iter()
            .flatten()
            .any(|(seq, _)| ahead(expected, *seq) < WINDOW);
        if beyond_gap {
            self.send_nak(tx);
            self.gap_naked = true;
        }
    }

    fn handle(
        &mut self,
        seq: u16,
        request: Request,
        handle: &mut impl FnMut(Request) -> Response,
        tx: &mut impl Tx,
    ) {
        if long_running(&request) {
            self.send(&Uplink::Ack { seq }, tx);
        }
        let body = handle(request);
        self.expected = seq.wrapping_add(1);
        self.gap_naked = false;
        while let Some(notice) = tx.pending_notice() {
            self.notice(notice, tx);
        }
        let Some(cached) = self.replies.get_mut(usize::from(seq % WINDOW)) else {
            return;
        };
        cached.seq = seq;
        cached.len = encode_reply(seq, body, &mut cached.bytes);
        tx.write(
            cached
                .bytes
                .get(..cached.len)
                .unwrap_or(&[frame::DELIMITER]),
        );
    }

    /// Sends the cached reply to `seq` again, if there is one.
    fn resend(&mut self, seq: u16, tx: &mut impl Tx) -> bool {
        match self.replies.get(usize::from(seq % WINDOW)) {
            Some(cached) if cached.seq == seq && cached.len > 0 => {
                tx.write(cached.bytes.get(..cached.len).unwrap_or(&[]));
                true
            }
            _ => false,
        }
    }

    fn send_nak(&mut self, tx: &mut impl Tx) {
        self.send(
            &Uplink::Nak {
                expected: self.expected,
            },
            tx,
        );
    }

    /// Sends an unsolicited message (a log chunk) as a [`Uplink::Notice`].
    pub fn notice(&mut self, body: Response, tx: &mut impl Tx) {
        let seq = self.notice_seq;
        self.notice_seq = seq.wrapping_add(1);
        self.send(&Uplink::Notice { seq, body }, tx);
    }

    fn send(&mut self, up: &Uplink, tx: &mut impl Tx) {
        if let Ok(len) = frame::encode(up, &mut self.out) {
            tx.write(self.out.get(..len).unwrap_or(&[]));
        }
    }
}

/// What one complete frame turned out to be, for counters and logs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkEvent {
    /// Handled in order (with any held requests it released).
    Handled,
    /// From beyond a gap: held until the gap is filled.
    Held,
    /// Handled before; its cached reply was sent again.
    Duplicate,
    /// Refused: no `Hello` since boot.
    NotSynced,
    /// Too far from the expected number to belong to this session.
    OutOfWindow,
    /// Not a readable frame; NAKed.
    Corrupt(FrameError),
}

/// Encodes the reply frame; a response too large for a frame (never, a shared test checks the
/// largest) becomes `Error(Frame(BufferTooSmall))`.
fn encode_reply(seq: u16, body: Response, out: &mut [u8]) -> usize {
    frame::encode(&Uplink::Reply { seq, body }, out)
        .or_else(|e| {
            let body = Response::Error(ErrorCode::Frame(e));
            frame::encode(&Uplink::Reply { seq, body }, out)
        })
        .unwrap_or(0)
}

/// The frame a panicking target sends last: [`Uplink::Panic`] with `message` (truncated to
/// [`PANIC_MESSAGE_LEN`] bytes at a character boundary). Returns its length in `out`.
pub fn panic_frame(message: &str, out: &mut [u8]) -> usize {
    let mut text = heapless::String::<PANIC_MESSAGE_LEN>::new();
    for c in message.chars() {
        if text.push(c).is_err() {
            break;
        }
    }
    frame::encode(&Uplink::Panic { message: text }, out).unwrap_or(0)
}

#[cfg(test)]
mod tests;
