//! Read-modify-write atomics from compare-and-swap alone.
//!
//! Why not `fetch_add`, `swap` or an `AtomicBool`: the LiteX VexRiscv `imac` CPU implements the
//! A extension's LR/SC but none of its AMO instructions (`amoadd.w`, `amoswap.w`, `amoor.w`, …
//! are illegal instructions there; tried one by one in hil-sim's SoC). LLVM lowers a 32-bit
//! `compare_exchange` to an LR/SC loop, but `fetch_add` and `swap` — and even a `bool`
//! compare-exchange, which it turns into `amoor` — to AMOs. So every read-modify-write in the
//! firmware goes through these, on every board (QEMU gets the same semantics, one LR/SC loop).
//! hil-sim refuses a LiteX firmware image that still holds an AMO instruction.

use core::sync::atomic::{AtomicUsize, Ordering};

/// `a += value`, returning the previous value (`AcqRel`, like the `fetch_add` it replaces).
pub fn fetch_add(a: &AtomicUsize, value: usize) -> usize {
    let mut current = a.load(Ordering::Relaxed);
    loop {
        match a.compare_exchange_weak(
            current,
            current.wrapping_add(value),
            Ordering::AcqRel,
            Ordering::Relaxed,
        ) {
            Ok(previous) => return previous,
            Err(now) => current = now,
        }
    }
}

/// Sets a 0/1 flag to 1; true if this call did (it was 0), false if it was already set.
pub fn set_flag(flag: &AtomicUsize, success: Ordering) -> bool {
    flag.compare_exchange(0, 1, success, Ordering::Relaxed)
        .is_ok()
}
