//! The reliable transport under the request/response messages: sequence numbers, a sliding
//! window, acknowledgements, retransmission and duplicate suppression. `docs/PROTOCOL.md` is the
//! full specification; this module holds the types and rules both ends share.
//!
//! # Downlink (host → target)
//!
//! Every frame is an [`Envelope<Request>`](crate::protocol::Envelope): a 16-bit sequence number
//! and one request. The host numbers requests consecutively (mod 2¹⁶) and may have up to
//! [`WINDOW`] requests without a reply outstanding.
//!
//! # Uplink (target → host)
//!
//! Every frame is an [`Uplink`]. The target handles requests strictly in sequence order, each
//! exactly once, and answers each with one [`Uplink::Reply`] carrying the request's number; a
//! reply to `s` therefore also acknowledges every request before `s` (cumulative ACK).
//!
//! - A frame that arrives ahead of its turn (a gap: the expected one was lost) is kept if it is
//!   within the window, and the target sends [`Uplink::Nak`] naming the number it expects; a
//!   frame that fails its CRC (or COBS, or is overlong) is answered the same way. The host
//!   resends just that frame (selective repeat).
//! - A frame the target has already handled (a retransmission whose reply was lost) is not
//!   handled again: the target resends the reply it keeps for each of the last [`WINDOW`]
//!   requests (duplicate suppression).
//! - Before work that takes long ([`long_running`]: `Solve`) the target sends
//!   [`Uplink::Ack`], so that the host stops retransmitting and waits for the reply as long as
//!   the solve may take.
//! - `Hello` (re)synchronises: it is accepted at any sequence number and sets the next expected
//!   number to its own + 1. Until the first `Hello` after boot the target answers every other
//!   request with [`Uplink::NotSynced`]: that is how a host notices that the target reset.
//! - [`Uplink::Notice`] carries unsolicited messages (firmware logs) outside the request
//!   sequence space, numbered in their own space so that the host can tell how many it missed;
//!   they are never retransmitted. [`Uplink::Panic`] is the last frame of a target that panicked.

use serde::{Deserialize, Serialize};

use crate::protocol::{Request, Response};

/// Requests the host may have outstanding (sent, no reply yet), and replies the target keeps
/// for duplicates. Eight frames of at most [`MAX_FRAME_LEN`](crate::protocol::MAX_FRAME_LEN)
/// bytes keep about 4 KiB in flight: enough to keep a pty or a USB-serial line busy while the
/// target handles the frame before, and within a Linux pty's 4 KiB buffer.
pub const WINDOW: u16 = 8;

/// Bytes of panic message the target reports.
pub const PANIC_MESSAGE_LEN: usize = 96;

/// Every frame from the target to the host.
// Reply/Notice carry a whole response (a solution chunk); no_std has no Box to shrink them.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Uplink {
    /// The answer to request `seq`. Acknowledges every request up to `seq`.
    Reply { seq: u16, body: Response },
    /// Request `seq` (and every one before it) arrived and is being handled; its `Reply` follows
    /// when the work is done. Sent before long-running work only.
    Ack { seq: u16 },
    /// The target is waiting for request `expected`: a corrupt frame arrived, or a frame from
    /// beyond a gap. Resend `expected`.
    Nak { expected: u16 },
    /// Request `seq` was refused because the target has not shaken hands since it booted (it
    /// reset, or a new host must start with `Hello`).
    NotSynced { seq: u16 },
    /// An unsolicited message (a firmware log), numbered in its own sequence space.
    Notice { seq: u16, body: Response },
    /// The target panicked and stops; this is its last frame.
    Panic {
        message: heapless::String<PANIC_MESSAGE_LEN>,
    },
}

/// Requests whose handling may take far longer than a round trip: the target sends
/// [`Uplink::Ack`] before it starts on them. A live frame is not one: it is budgeted to a few
/// milliseconds, and an `Ack` would add its bytes to every frame.
pub fn long_running(request: &Request) -> bool {
    matches!(request, Request::Solve(_) | Request::LiveStart(_))
}

/// How far `seq` is ahead of `base` in the 16-bit sequence space (`0` = it is `base`); numbers
/// more than half the space ahead count as behind (see [`behind`]).
pub const fn ahead(base: u16, seq: u16) -> u16 {
    seq.wrapping_sub(base)
}

/// How far `seq` lies behind `base` (1 = the number just before), if it lies behind at all.
pub const fn behind(base: u16, seq: u16) -> Option<u16> {
    let back = base.wrapping_sub(seq);
    if back != 0 && back <= u16::MAX / 2 {
        Some(back)
    } else {
        None
    }
}

/// True if `seq` is within the receive window that starts at `base`.
pub const fn in_window(base: u16, seq: u16) -> bool {
    ahead(base, seq) < WINDOW
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame;
    use crate::protocol::{ErrorCode, SessionStep, MAX_FRAME_LEN};

    #[test]
    fn sequence_arithmetic_wraps() {
        assert_eq!(ahead(0xFFFE, 1), 3);
        assert!(in_window(0xFFFE, 5));
        assert!(!in_window(0xFFFE, 6));
        assert_eq!(behind(1, 0xFFFF), Some(2));
        assert_eq!(behind(1, 1), None);
        assert_eq!(behind(1, 2), None);
    }

    #[test]
    fn uplink_frames_round_trip() {
        let mut message = heapless::String::new();
        message.push_str("panicked at src/main.rs:1:1").unwrap();
        for up in [
            Uplink::Reply {
                seq: 0xFFFF,
                body: Response::Error(ErrorCode::OutOfOrder(SessionStep::NoMatrix)),
            },
            Uplink::Ack { seq: 3 },
            Uplink::Nak { expected: 9 },
            Uplink::NotSynced { seq: 1 },
            Uplink::Notice {
                seq: 2,
                body: Response::Ack,
            },
            Uplink::Panic { message },
        ] {
            let mut buf = [0u8; MAX_FRAME_LEN];
            let n = frame::encode(&up, &mut buf).unwrap();
            assert_eq!(frame::decode::<Uplink>(&mut buf[..n - 1]).unwrap(), up);
        }
    }
}
