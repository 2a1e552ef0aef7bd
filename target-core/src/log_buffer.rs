//! The buffer behind the firmware's defmt logger (`firmware/src/logger.rs`): encoded log frames
//! wait here until the main loop ships them in `Response::Log` notices.
//!
//! It holds only complete frames: a frame that does not fit is discarded whole when it ends, and
//! its bytes are counted and reported with the next chunk taken, so a log call never blocks and
//! never fails, and whatever is shipped still decodes.

use heapless::Vec;

/// `N` bytes of log frames.
pub struct LogBuffer<const N: usize> {
    bytes: [u8; N],
    /// Bytes of complete frames, plus those of the frame being written.
    len: usize,
    /// Where the frame being written started.
    frame_start: usize,
    /// Bytes the frame being written has produced, including those that did not fit.
    frame_bytes: u32,
    /// The frame being written did not fit: it is discarded at its end.
    frame_overflowed: bool,
    /// Bytes discarded since the last [`take_chunk`](Self::take_chunk).
    dropped: u32,
}

impl<const N: usize> Default for LogBuffer<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> LogBuffer<N> {
    pub const fn new() -> Self {
        LogBuffer {
            bytes: [0; N],
            len: 0,
            frame_start: 0,
            frame_bytes: 0,
            frame_overflowed: false,
            dropped: 0,
        }
    }

    /// Begins a frame.
    pub fn start_frame(&mut self) {
        self.frame_start = self.len;
        self.frame_bytes = 0;
        self.frame_overflowed = false;
    }

    /// Appends bytes of the current frame, if they fit.
    pub fn push(&mut self, data: &[u8]) {
        self.frame_bytes = self.frame_bytes.saturating_add(data.len() as u32);
        if self.frame_overflowed {
            return;
        }
        match self.bytes.get_mut(self.len..self.len + data.len()) {
            Some(slot) => {
                slot.copy_from_slice(data);
                self.len += data.len();
            }
            None => self.frame_overflowed = true,
        }
    }

    /// Ends the frame: keeps it if it fit, else removes it whole and counts its bytes.
    pub fn end_frame(&mut self) {
        if self.frame_overflowed {
            self.len = self.frame_start;
            self.dropped = self.dropped.saturating_add(self.frame_bytes);
            self.frame_overflowed = false;
        }
    }

    /// Bytes of complete frames waiting.
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Up to `M` bytes from the start (a chunk may end inside a frame; the next continues it)
    /// and the bytes dropped since the last call, or `None` if there is nothing to report.
    /// Call it between frames only.
    pub fn take_chunk<const M: usize>(&mut self) -> Option<(u32, Vec<u8, M>)> {
        let taken = self.len.min(M);
        if taken == 0 && self.dropped == 0 {
            return None;
        }
        let chunk = Vec::from_slice(&self.bytes[..taken]).unwrap_or_default();
        self.bytes.copy_within(taken..self.len, 0);
        self.len -= taken;
        Some((core::mem::take(&mut self.dropped), chunk))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn frame<const N: usize>(buffer: &mut LogBuffer<N>, pieces: &[&[u8]]) {
        buffer.start_frame();
        for piece in pieces {
            buffer.push(piece);
        }
        buffer.end_frame();
    }

    #[test]
    fn frames_that_fit_come_out_in_order_in_chunks() {
        let mut buffer = LogBuffer::<16>::new();
        assert_eq!(buffer.take_chunk::<4>(), None);
        frame(&mut buffer, &[&[1, 2], &[3, 0]]);
        frame(&mut buffer, &[&[4, 5, 6, 0]]);
        assert_eq!(buffer.len(), 8);
        let (dropped, first) = buffer.take_chunk::<5>().unwrap();
        assert_eq!((dropped, first.as_slice()), (0, &[1, 2, 3, 0, 4][..]));
        let (_, rest) = buffer.take_chunk::<5>().unwrap();
        assert_eq!(rest.as_slice(), &[5, 6, 0]);
        assert!(buffer.is_empty() && buffer.take_chunk::<5>().is_none());
    }

    #[test]
    fn a_frame_that_does_not_fit_is_dropped_whole_and_counted_once() {
        let mut buffer = LogBuffer::<8>::new();
        frame(&mut buffer, &[&[1, 2, 0]]);
        // 3 + 2 fit, the next 4 do not: the whole 9-byte frame goes, the first one stays.
        frame(&mut buffer, &[&[7, 7, 7], &[7, 7], &[7, 7, 7, 0]]);
        assert_eq!(buffer.len(), 3);
        // Room is back for a small frame after the dropped one.
        frame(&mut buffer, &[&[9, 0]]);
        let (dropped, chunk) = buffer.take_chunk::<64>().unwrap();
        assert_eq!((dropped, chunk.as_slice()), (9, &[1, 2, 0, 9, 0][..]));
        frame(&mut buffer, &[&[0xEE; 20]]);
        let (dropped, chunk) = buffer.take_chunk::<64>().unwrap();
        assert_eq!((dropped, chunk.len()), (20, 0));
        assert_eq!(buffer.take_chunk::<64>(), None);
    }

    proptest! {
        /// Whatever the frames, what comes out is exactly the frames that were kept, in order,
        /// and kept + dropped accounts for every byte.
        #[test]
        fn every_byte_is_shipped_or_counted(
            frames in proptest::collection::vec(proptest::collection::vec(1u8..=255, 0..40), 0..30),
            drain_every in 1usize..6,
        ) {
            let mut buffer = LogBuffer::<64>::new();
            let (mut shipped, mut dropped, mut kept) = (std::vec::Vec::new(), 0u64, std::vec::Vec::new());
            for (i, f) in frames.iter().enumerate() {
                let before = buffer.len();
                frame(&mut buffer, &[f.as_slice()]);
                if buffer.len() > before || f.is_empty() {
                    kept.extend_from_slice(f);
                }
                if i % drain_every == 0 {
                    while let Some((d, chunk)) = buffer.take_chunk::<16>() {
                        dropped += u64::from(d);
                        shipped.extend_from_slice(&chunk);
                    }
                }
            }
            while let Some((d, chunk)) = buffer.take_chunk::<16>() {
                dropped += u64::from(d);
                shipped.extend_from_slice(&chunk);
            }
            let total: u64 = frames.iter().map(|f| f.len() as u64).sum();
            prop_assert_eq!(&shipped, &kept);
            prop_assert_eq!(shipped.len() as u64 + dropped, total);
        }
    }
}
