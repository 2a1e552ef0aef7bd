//! The defmt global logger: log frames go into a RAM buffer, never straight onto the UART.
//!
//! The UART carries only protocol frames (COBS, `0x00`-delimited), so raw defmt bytes there would
//! corrupt the link. Instead every log call encodes its frame (rzcobs: self-delimited, ending in
//! `0x00`) into [`LOG_BUFFER_LEN`] bytes of RAM, and the main loop ships the buffer in
//! `Response::Log` messages just before it answers a request ([`take_chunk`]), when the host is
//! sure to be reading.
//!
//! A log call never blocks and never panics: when a frame does not fit, the whole frame is
//! discarded (so the buffer only ever holds complete frames, and what arrives still decodes) and
//! its bytes are counted; the next `Log` message reports the count.
//!
//! Several harts may log: a spin lock serialises them. No interrupt handler logs (interrupts are
//! never taken), so a hart never waits for itself.

use core::cell::UnsafeCell;
use core::sync::atomic::{AtomicUsize, Ordering};

use deform_shared::protocol::LOG_CHUNK;
use deform_target_core::log_buffer::LogBuffer as Frames;
use heapless::Vec;

/// Bytes of log the target holds between two answers. Today's milestone logging puts well under
/// a hundred bytes between two answers; the rest is room for chattier code (e.g. per-iteration
/// traces) before frames are dropped.
pub const LOG_BUFFER_LEN: usize = 4096;

struct LogBuffer {
    encoder: defmt::Encoder,
    /// The frames; its rules (whole frames dropped and counted) are unit-tested in target-core.
    store: Frames<LOG_BUFFER_LEN>,
}

impl LogBuffer {
    fn start_frame(&mut self) {
        let LogBuffer { encoder, store } = self;
        store.start_frame();
        encoder.start_frame(|b| store.push(b));
    }

    fn write(&mut self, bytes: &[u8]) {
        let LogBuffer { encoder, store } = self;
        encoder.write(bytes, |b| store.push(b));
    }

    fn end_frame(&mut self) {
        let LogBuffer { encoder, store } = self;
        encoder.end_frame(|b| store.push(b));
        store.end_frame();
    }
}

struct SharedLog {
    locked: AtomicUsize,
    buffer: UnsafeCell<LogBuffer>,
}

// SAFETY: `buffer` is only reached between a successful `lock` and the matching `unlock`, so one
// hart at a time.
unsafe impl Sync for SharedLog {}

static LOG: SharedLog = SharedLog {
    locked: AtomicUsize::new(0),
    buffer: UnsafeCell::new(LogBuffer {
        encoder: defmt::Encoder::new(),
        store: Frames::new(),
    }),
};

impl SharedLog {
    fn lock(&self) {
        while !crate::atomic::set_flag(&self.locked, Ordering::Acquire) {
            core::hint::spin_loop();
        }
    }

    fn unlock(&self) {
        self.locked.store(0, Ordering::Release);
    }

    /// The buffer; only between `lock` and `unlock`.
    ///
    /// # Safety
    /// The caller holds the lock and keeps no other reference to the buffer.
    #[allow(clippy::mut_from_ref)]
    unsafe fn buffer(&self) -> &mut LogBuffer {
        // SAFETY: the caller holds the lock, so this is the only reference.
        unsafe { &mut *self.buffer.get() }
    }
}

#[defmt::global_logger]
struct BufferLogger;

// SAFETY: `acquire` takes the lock that `release` gives back, so `write` and `release` run with
// exclusive access to the buffer, as defmt requires; defmt calls them in this order only.
unsafe impl defmt::Logger for BufferLogger {
    fn acquire() {
        LOG.lock();
        // SAFETY: locked just above.
        unsafe { LOG.buffer() }.start_frame();
    }

    unsafe fn flush() {}

    unsafe fn release() {
        // SAFETY: defmt calls `release` only after `acquire`, so we hold the lock.
        unsafe { LOG.buffer() }.end_frame();
        LOG.unlock();
    }

    unsafe fn write(bytes: &[u8]) {
        // SAFETY: defmt calls `write` only between `acquire` and `release`: we hold the lock.
        unsafe { LOG.buffer() }.write(bytes);
    }
}

/// One `Log` message's worth of the buffer: up to [`LOG_CHUNK`] bytes from its start, and the
/// bytes dropped since the previous call. `None` if there is nothing to report.
pub fn take_chunk() -> Option<(u32, Vec<u8, LOG_CHUNK>)> {
    LOG.lock();
    // SAFETY: locked just above; the reference is gone before the unlock.
    let chunk = unsafe { LOG.buffer() }.store.take_chunk();
    LOG.unlock();
    chunk
}
