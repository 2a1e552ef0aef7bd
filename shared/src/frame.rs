//! Framing: how one message travels on a byte stream.
//!
//! ```text
//! COBS( postcard(message) ++ crc32_le(postcard(message)) ) ++ 0x00
//! ```
//!
//! COBS removes every `0x00` from the body, so `0x00` is an unambiguous delimiter: after line
//! noise a receiver resynchronises at the next delimiter. The CRC-32 (ISO-HDLC, the Ethernet/zip
//! polynomial, from the `crc` crate) covers the postcard bytes. A decoder reports separately
//! whether COBS, the CRC or the message itself was bad, so that the peer can say which.

use serde::{Deserialize, Serialize};

/// CRC-32/ISO-HDLC, used for frames and for whole-matrix checksums.
pub const CRC32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// Ends every frame; never occurs inside one.
pub const DELIMITER: u8 = 0x00;

/// Bytes of CRC appended to the payload.
pub const CRC_LEN: usize = 4;

/// Why a frame could not be encoded or decoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, thiserror::Error)]
pub enum FrameError {
    #[error("the output buffer is too small for the frame")]
    BufferTooSmall,
    #[error("the frame is longer than the receive buffer")]
    TooLong,
    #[error("the frame's COBS encoding is invalid")]
    Cobs,
    #[error("the frame is too short to hold a CRC")]
    TooShort,
    #[error("the frame's CRC does not match its contents")]
    Crc,
    #[error("the frame's CRC is right but its message does not decode")]
    Message,
}

/// Encodes `msg` as one complete frame, delimiter included, into `out`. Returns its length.
pub fn encode<T: Serialize>(msg: &T, out: &mut [u8]) -> Result<usize, FrameError> {
    use postcard::ser_flavors::{crc::CrcModifier, Cobs, Slice};
    let cobs = Cobs::try_new(Slice::new(out)).map_err(|_| FrameError::BufferTooSmall)?;
    let flavor = CrcModifier::new(cobs, CRC32.digest());
    postcard::serialize_with_flavor(msg, flavor)
        .map(|frame: &mut [u8]| frame.len())
        .map_err(|_| FrameError::BufferTooSmall)
}

/// Decodes one frame in place. `frame` holds the bytes between two delimiters (without them).
pub fn decode<'a, T: Deserialize<'a>>(frame: &'a mut [u8]) -> Result<T, FrameError> {
    let len = cobs::decode_in_place(frame).map_err(|_| FrameError::Cobs)?;
    let decoded = &frame[..len];
    if len < CRC_LEN {
        return Err(FrameError::TooShort);
    }
    let (payload, crc) = decoded.split_at(len - CRC_LEN);
    let expected = u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]);
    if CRC32.checksum(payload) != expected {
        return Err(FrameError::Crc);
    }
    match postcard::take_from_bytes(payload) {
        Ok((msg, [])) => Ok(msg),
        _ => Err(FrameError::Message),
    }
}

/// The largest frame, delimiter included, that a `payload_len`-byte message can become.
pub const fn max_frame_len(payload_len: usize) -> usize {
    cobs::max_encoding_length(payload_len + CRC_LEN) + 1
}

/// What feeding one byte to a [`FrameAccumulator`] produced.
#[derive(Debug, PartialEq, Eq)]
pub enum Feed<'a> {
    /// No complete frame yet.
    Pending,
    /// A complete frame (without delimiter), ready for [`decode`].
    Frame(&'a mut [u8]),
    /// A frame longer than the buffer ended here; its bytes were discarded.
    Overflow,
}

/// Collects bytes up to each delimiter into a fixed buffer, never allocating and never
/// panicking: an overlong frame is dropped and reported once, at its delimiter, and empty frames
/// (two delimiters in a row, which a sender may use to flush a peer's partial frame) are skipped.
pub struct FrameAccumulator<const N: usize> {
    buf: [u8; N],
    len: usize,
    overflowed: bool,
}

impl<const N: usize> Default for FrameAccumulator<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> FrameAccumulator<N> {
    pub const fn new() -> Self {
        Self {
            buf: [0; N],
            len: 0,
            overflowed: false,
        }
    }

    /// Forgets any partial frame.
    pub fn reset(&mut self) {
        self.len = 0;
        self.overflowed = false;
    }

    pub fn feed(&mut self, byte: u8) -> Feed<'_> {
        if byte == DELIMITER {
            let len = core::mem::take(&mut self.len);
            if core::mem::take(&mut self.overflowed) {
                return Feed::Overflow;
            }
            if len == 0 {
                return Feed::Pending;
            }
            return Feed::Frame(&mut self.buf[..len]);
        }
        if self.overflowed {
            return Feed::Pending;
        }
        match self.buf.get_mut(self.len) {
            Some(slot) => {
                *slot = byte;
                self.len += 1;
            }
            None => {
                self.overflowed = true;
                self.len = 0;
            }
        }
        Feed::Pending
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use serde::Deserialize;

    #[derive(Debug, PartialEq, Serialize, Deserialize)]
    struct Msg {
        a: u32,
        b: [u8; 8],
        c: i64,
    }

    fn sample() -> Msg {
        Msg {
            a: 0,
            b: [0, 1, 2, 0, 0, 255, 0, 7],
            c: -5,
        }
    }

    fn frame_of(msg: &Msg) -> Vec<u8> {
        let mut buf = [0u8; 64];
        let n = encode(msg, &mut buf).unwrap();
        buf[..n].to_vec()
    }

    #[test]
    fn round_trip_has_one_delimiter_at_the_end() {
        let f = frame_of(&sample());
        assert_eq!(f.iter().filter(|&&b| b == 0).count(), 1);
        assert_eq!(*f.last().unwrap(), 0);
        let mut body = f[..f.len() - 1].to_vec();
        assert_eq!(decode::<Msg>(&mut body).unwrap(), sample());
    }

    #[test]
    fn every_single_bit_flip_is_detected() {
        let f = frame_of(&sample());
        for i in 0..f.len() - 1 {
            for bit in 0..8 {
                let mut body = f[..f.len() - 1].to_vec();
                body[i] ^= 1 << bit;
                if body[i] == 0 {
                    continue; // would split the frame at the receiver instead
                }
                assert!(
                    decode::<Msg>(&mut body).is_err(),
                    "flip {i}:{bit} went unnoticed"
                );
            }
        }
    }

    #[test]
    fn errors_are_told_apart() {
        let f = frame_of(&sample());
        let mut truncated = f[..3].to_vec();
        assert!(matches!(
            decode::<Msg>(&mut truncated),
            Err(FrameError::Cobs | FrameError::TooShort)
        ));
        let mut bad_crc = f[..f.len() - 1].to_vec();
        let k = bad_crc.len() - 1;
        bad_crc[k] ^= 0x40;
        assert!(matches!(
            decode::<Msg>(&mut bad_crc),
            Err(FrameError::Crc | FrameError::Cobs)
        ));
        // A valid frame of another message type: CRC fine, message wrong.
        let mut buf = [0u8; 16];
        let n = encode(&7u8, &mut buf).unwrap();
        assert_eq!(decode::<Msg>(&mut buf[..n - 1]), Err(FrameError::Message));
        // Trailing bytes inside a valid CRC are refused too.
        let n = encode(&(sample(), 1u8), &mut [0u8; 64]).unwrap();
        let mut buf = [0u8; 64];
        encode(&(sample(), 1u8), &mut buf).unwrap();
        assert_eq!(decode::<Msg>(&mut buf[..n - 1]), Err(FrameError::Message));
        assert_eq!(
            encode(&sample(), &mut [0u8; 4]),
            Err(FrameError::BufferTooSmall)
        );
    }

    #[test]
    fn accumulator_resyncs_after_garbage_and_overflow() {
        let mut acc = FrameAccumulator::<32>::new();
        let mut got = Vec::new();
        let mut stream: Vec<u8> = vec![0xAA; 100]; // overlong garbage
        stream.push(0);
        stream.extend_from_slice(&[1, 2, 3, 0, 0]); // short garbage, an empty frame
        stream.extend(frame_of(&sample()));
        let mut overflows = 0;
        for b in stream {
            match acc.feed(b) {
                Feed::Frame(f) => got.push(decode::<Msg>(f)),
                Feed::Overflow => overflows += 1,
                Feed::Pending => {}
            }
        }
        assert_eq!(overflows, 1);
        assert_eq!(got.len(), 2);
        assert!(got[0].is_err());
        assert_eq!(got[1].as_ref().unwrap(), &sample());
    }

    proptest! {
        #[test]
        fn arbitrary_bytes_never_panic(mut bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
            let _ = decode::<Msg>(&mut bytes);
            let _ = decode::<crate::protocol::Request>(&mut bytes.clone());
            let _ = decode::<crate::protocol::Response>(&mut bytes.clone());
        }

        #[test]
        fn round_trips(a: u32, b: [u8; 8], c: i64) {
            let m = Msg { a, b, c };
            let f = frame_of(&m);
            let mut body = f[..f.len() - 1].to_vec();
            prop_assert_eq!(decode::<Msg>(&mut body).unwrap(), m);
        }
    }
}
