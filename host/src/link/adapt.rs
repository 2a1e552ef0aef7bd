//! How big the link's frames are and how many fly at once, adapted to the line. A frame of L
//! bytes arrives intact with probability (1 − e)^L at byte-error rate e: at e = 1e-2 a full
//! 540-byte chunk frame almost never does (0.4 %), while on a clean line small frames only add
//! header bytes. Like TCP and LiteX's serial boot (which falls back from 8 frames in flight to
//! 4 to 1), the link shrinks when frames keep failing and grows back when the line is clean —
//! but instead of halving and creeping back blindly it *estimates* e and picks the size that
//! costs the fewest bytes at that rate:
//!
//! - **Estimate**: ê = damaged frames / bytes on the line (both ways), each count decaying by
//!   half every [`HALF_LIFE`] bytes, so that ê follows a line that changes. A damaged frame is
//!   a NAK for a request (counted once per send of it) or a frame from the target that did not
//!   decode. A timeout alone is no evidence: on a loaded machine a slow target is not a noisy
//!   line. The estimate starts pessimistic ([`PRIOR_RATE`] over [`PRIOR_BYTES`]), so the first
//!   frames of a link are small, and a clean line washes the prior out within a few KB.
//! - **Chunk** (elements per `Words`, `VectorData`, `UpdateValues`, and per `ReadSolution`
//!   answer): a chunk of c elements costs (4c + h)·(1 − e)^−(4c + h) bytes for its 4c data
//!   bytes, h ≈ [`FRAME_OVERHEAD`] bytes being the frame's header and its reply. That cost per
//!   element is least at c = (√(h² + 4h/λ) − h) / 8 with λ = −ln(1 − e): 10 at e = 1e-2, 38 at
//!   1e-3, 128 ([`CHUNK_LEN`]) below about 1e-4. Clamped to [`MIN_CHUNK`]..=[`CHUNK_LEN`].
//! - **Window** (requests in flight): the configured window times the chance that a frame of
//!   the chosen size arrives intact, at least 1.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use deform_shared::protocol::CHUNK_LEN;

/// The smallest chunk: 4 elements (16 bytes of data and about 17 of frame).
pub const MIN_CHUNK: usize = 4;

/// Bytes after which the estimate's counts have decayed to half.
pub const HALF_LIFE: f64 = 4096.0;

/// The estimate before the line has said anything: one damaged frame per 100 bytes, worth
/// 100 bytes of evidence (so that 2 KB of clean traffic already halves it).
pub const PRIOR_RATE: f64 = 1e-2;
pub const PRIOR_BYTES: f64 = 100.0;

/// A chunk frame's fixed bytes (sequence number, tag, offset, count, CRC, COBS, delimiter:
/// about 17) plus its reply's (an `Ack` frame: about 11).
pub const FRAME_OVERHEAD: f64 = 28.0;

/// The chunk size that costs the fewest bytes per element at byte-error rate `e` (see the
/// module doc), clamped to [`MIN_CHUNK`]..=[`CHUNK_LEN`].
pub fn best_chunk(e: f64) -> usize {
    let lambda = -(1.0 - e.clamp(1e-12, 0.5)).ln();
    let h = FRAME_OVERHEAD;
    let c = ((h * h + 4.0 * h / lambda).sqrt() - h) / 8.0;
    (c.floor() as usize).clamp(MIN_CHUNK, CHUNK_LEN)
}

/// The adaptive sizes; see the module doc.
#[derive(Debug)]
pub struct Adaptive {
    /// Shared with the request generators, which read it as they make each chunk.
    chunk: Arc<AtomicUsize>,
    window: u16,
    max_window: u16,
    /// Decaying counts of damaged frames and of bytes on the line.
    damaged: f64,
    bytes: f64,
    /// Damaged frames seen and the smallest chunk chosen, for reports.
    damage_seen: u64,
    smallest: usize,
    /// Adaptation off: the chunk and window stay as set (tests that count requests).
    frozen: bool,
}

impl Adaptive {
    pub fn new(max_window: u16) -> Self {
        let mut adaptive = Adaptive {
            chunk: Arc::new(AtomicUsize::new(CHUNK_LEN)),
            window: max_window,
            max_window,
            damaged: PRIOR_RATE * PRIOR_BYTES,
            bytes: PRIOR_BYTES,
            damage_seen: 0,
            smallest: CHUNK_LEN,
            frozen: false,
        };
        adaptive.choose();
        adaptive
    }

    /// Fixed sizes: `chunk` elements and the whole configured window, whatever the line does.
    pub fn fixed(chunk: usize, max_window: u16) -> Self {
        Adaptive {
            chunk: Arc::new(AtomicUsize::new(chunk)),
            smallest: chunk,
            window: max_window,
            frozen: true,
            ..Adaptive::new(max_window)
        }
    }

    /// The chunk size now, as a handle the request generators read lazily.
    pub fn chunk_handle(&self) -> ChunkSize {
        ChunkSize(Arc::clone(&self.chunk))
    }

    pub fn chunk(&self) -> usize {
        self.chunk.load(Ordering::Relaxed)
    }

    pub fn window(&self) -> u16 {
        self.window
    }

    /// The estimated byte-error rate ê.
    pub fn error_rate(&self) -> f64 {
        self.damaged / self.bytes
    }

    pub fn damage_seen(&self) -> u64 {
        self.damage_seen
    }

    pub fn smallest_chunk(&self) -> usize {
        self.smallest
    }

    /// A new configured window (the window adapts within it).
    pub fn set_max_window(&mut self, max_window: u16) {
        self.max_window = max_window.max(1);
        if self.frozen {
            self.window = self.max_window;
        } else {
            self.choose();
        }
    }

    /// `bytes` went over the line, either way.
    pub fn traffic(&mut self, bytes: usize) {
        let decay = 0.5f64.powf(bytes as f64 / HALF_LIFE);
        self.damaged *= decay;
        self.bytes = self.bytes * decay + bytes as f64;
        self.choose();
    }

    /// A damaged frame: a NAK, or a frame from the target that did not decode.
    pub fn damage(&mut self) {
        self.damaged += 1.0;
        self.damage_seen += 1;
        self.choose();
    }

    fn choose(&mut self) {
        if self.frozen {
            return;
        }
        let e = self.error_rate();
        let chunk = best_chunk(e);
        let intact = (1.0 - e).powf(4.0 * chunk as f64 + FRAME_OVERHEAD);
        self.window =
            ((f64::from(self.max_window) * intact).round() as u16).clamp(1, self.max_window);
        self.smallest = self.smallest.min(chunk);
        self.chunk.store(chunk, Ordering::Relaxed);
    }
}

/// The link's current chunk size, read by the request generators as they make each chunk.
#[derive(Debug, Clone)]
pub struct ChunkSize(Arc<AtomicUsize>);

impl ChunkSize {
    /// A fixed size, for code that does not adapt (byte counts, tests).
    pub fn fixed(len: usize) -> Self {
        ChunkSize(Arc::new(AtomicUsize::new(len)))
    }

    pub fn get(&self) -> usize {
        self.0.load(Ordering::Relaxed).clamp(1, CHUNK_LEN)
    }

    /// `0..total` cut into consecutive ranges, each as long as the chunk size is when the range
    /// is taken (so a generator that the link pulls lazily follows the adaptation).
    pub fn ranges(&self, total: usize) -> impl Iterator<Item = std::ops::Range<usize>> {
        let size = self.clone();
        let mut start = 0;
        std::iter::from_fn(move || {
            (start < total).then(|| {
                let end = (start + size.get()).min(total);
                let range = start..end;
                start = end;
                range
            })
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_best_chunk_shrinks_with_the_error_rate() {
        assert_eq!(best_chunk(0.0), CHUNK_LEN);
        assert_eq!(best_chunk(1e-5), CHUNK_LEN);
        assert_eq!(best_chunk(1e-3), 38);
        assert_eq!(best_chunk(1e-2), 10);
        assert_eq!(best_chunk(0.2), MIN_CHUNK);
    }

    #[test]
    fn a_link_starts_small_grows_on_a_clean_line_and_shrinks_on_damage() {
        let mut a = Adaptive::new(8);
        assert!(a.chunk() <= 16 && a.window() < 8, "{a:?}");
        for _ in 0..40 {
            a.traffic(500);
        }
        assert_eq!((a.chunk(), a.window()), (CHUNK_LEN, 8), "{a:?}");
        // One damaged frame per ~100 bytes, as at a byte-error rate of 1e-2.
        for _ in 0..200 {
            a.traffic(100);
            a.damage();
        }
        assert!((4..=12).contains(&a.chunk()) && a.window() < 8, "{a:?}");
        assert_eq!(a.damage_seen(), 200);
        let mut fixed = Adaptive::fixed(CHUNK_LEN, 8);
        fixed.damage();
        assert_eq!((fixed.chunk(), fixed.window()), (CHUNK_LEN, 8));
    }

    #[test]
    fn ranges_follow_the_size_as_it_changes() {
        let size = ChunkSize::fixed(4);
        let mut ranges = size.ranges(10);
        assert_eq!(ranges.next(), Some(0..4));
        size.0.store(2, Ordering::Relaxed);
        assert_eq!(ranges.next(), Some(4..6));
        size.0.store(100, Ordering::Relaxed);
        assert_eq!(ranges.next(), Some(6..10));
        assert_eq!(ranges.next(), None);
    }
}
