//! # deform-loader
//!
//! The serial loader: what a soft core on an FPGA boots from on-chip RAM to receive its
//! application over the UART. QEMU boots it (`-kernel deform-loader`); the host (`deform flash`)
//! sends an image header, the image in CRC-checked chunks, asks for a verification of the whole
//! image as it sits in RAM, and only then has it started. The protocol and its rules are
//! [`deform_shared::loader`] (unit-tested on the host); this file adds the UART, the memory
//! writes, the CRC over RAM and the jump.
//!
//! Memory (`loader-memory.x`): the loader runs 48 MiB into RAM, out of the application's way
//! (the application is linked at the start of RAM, where QEMU starts the harts, so it also boots
//! directly); a jump at 0x8000_0000 leads here at reset.
//!
//! The loader never panics on input: every frame is answered, a malformed one with
//! `Error(Frame(..))` and sequence number `UNKNOWN_SEQ`.
#![no_std]
#![no_main]
#![deny(unsafe_op_in_unsafe_fn, clippy::undocumented_unsafe_blocks)]

// The board layer is the application's (built with the `qemu-virt` board: on LiteX the stock
// BIOS is the loader); the loader uses its UART, RAM bounds, hart count and wake-ups.
#[allow(dead_code)]
#[path = "../board/mod.rs"]
mod board;

use core::sync::atomic::{AtomicU32, Ordering};

use deform_shared::frame::{self, Feed, FrameAccumulator, FrameError};
use deform_shared::loader::{
    decode_frame, LoaderAction, LoaderEnvelope, LoaderError, LoaderInfo, LoaderRequest,
    LoaderResponse, LoaderSession, CRC32, LOADER_FRAME_LEN, LOADER_PROTOCOL_VERSION, UNKNOWN_SEQ,
};

use board::{qemu_virt::MSIP_BASE, Board, Bsp, Serial};

/// QEMU exit status after a panic (as the application's).
const EXIT_PANIC: u16 = 101;
/// QEMU exit status after a CPU exception.
const EXIT_EXCEPTION: u16 = 102;
/// QEMU exit status after an interrupt (none is ever enabled).
const EXIT_INTERRUPT: u16 = 103;

/// The RAM an image may occupy: the board's (QEMU `virt` as hil-sim configures it, `-m 64M`).
const RAM_START: u32 = Board::RAM_START;
const RAM_END: u32 = Board::RAM_END;

// At reset QEMU jumps to the start of RAM: on to riscv-rt's `_start`, up where the loader lives.
core::arch::global_asm!(
    ".section .boot_stub, \"ax\"",
    ".global _boot_stub",
    "_boot_stub:",
    "lui t0, %hi(_start)",
    "addi t0, t0, %lo(_start)",
    "jr t0",
);

extern "C" {
    static _loader_start: u8;
    static _loader_end: u8;
}

/// Harts the loader hands over to the application (`_max_hart_id` + 1 in loader-memory.x).
const HARTS: usize = Board::HARTS;

/// Where the harts other than 0 go once the image is started; 0 until then.
static RELEASE_ENTRY: AtomicU32 = AtomicU32::new(0);

// Harts other than 0 wait in the loader (riscv-rt calls `_mp_hook` with the hart id in a0)
// until hart 0 starts the image: it stores the entry point in RELEASE_ENTRY and raises their
// software interrupt (MSIP), and they jump to the entry as if reset there, so that the
// application's own `_mp_hook` finds every hart just as at a direct boot. mip.MSIP is checked
// before each `wfi` (an interrupt raised just before the `wfi` would otherwise be slept
// through), and cleared before the jump so the application starts with none pending.
core::arch::global_asm!(
    ".section .text._mp_hook, \"ax\"",
    ".global _mp_hook",
    "_mp_hook:",
    "beqz a0, 3f",
    "li t0, 8", // mie.MSIE / mip.MSIP
    "csrs mie, t0",
    "1:",
    "csrr t1, mip",
    "and t1, t1, t0",
    "bnez t1, 2f",
    "wfi",
    "j 1b",
    "2:",
    "li t1, {clint}",
    "slli t2, a0, 2",
    "add t1, t1, t2",
    "sw zero, 0(t1)",
    "fence",
    "la t1, {release}",
    "lw t1, 0(t1)",
    "beqz t1, 1b",
    "csrc mie, t0",
    "fence.i",
    "jr t1",
    "3:",
    "li a0, 1",
    "ret",
    clint = const MSIP_BASE,
    release = sym RELEASE_ENTRY,
);

fn loader_info() -> LoaderInfo {
    LoaderInfo {
        version: LOADER_PROTOCOL_VERSION,
        ram_start: RAM_START,
        ram_end: RAM_END,
        loader_start: core::ptr::addr_of!(_loader_start) as u32,
        loader_end: core::ptr::addr_of!(_loader_end) as u32,
    }
}

#[riscv_rt::entry]
fn main() -> ! {
    let mut uart = Board::uart();
    let info = loader_info();
    let mut session = LoaderSession::new();
    let mut frames = FrameAccumulator::<LOADER_FRAME_LEN>::new();
    let mut out = [0u8; LOADER_FRAME_LEN];
    loop {
        let byte = uart.read();
        let (seq, request) = match frames.feed(byte) {
            Feed::Pending => continue,
            Feed::Overflow => (UNKNOWN_SEQ, Err(FrameError::TooLong)),
            Feed::Frame(bytes) => match decode_frame::<LoaderRequest>(bytes) {
                Ok(LoaderEnvelope { seq, body, .. }) => (seq, Ok(body)),
                Err(e) => (UNKNOWN_SEQ, Err(e)),
            },
        };
        let request = match request {
            Ok(request) => request,
            Err(e) => {
                let body = LoaderResponse::Error(LoaderError::Frame(e));
                send(&mut uart, &mut out, seq, body);
                continue;
            }
        };
        let response = match session.handle(&info, &request) {
            LoaderAction::Reply(response) => response,
            LoaderAction::Write { address, data } => {
                // SAFETY: `LoaderSession` accepted this chunk only inside the image, whose header
                // `ImageHeader::check` confined to RAM_START..RAM_END and away from
                // _loader_start.._loader_end (all the loader's code, data and stack): no Rust
                // object lives there, and `data` is in the loader's own frame buffer.
                unsafe {
                    core::ptr::copy_nonoverlapping(data.as_ptr(), address as *mut u8, data.len())
                };
                LoaderResponse::Ack
            }
            LoaderAction::Checksum { address, length } => {
                // SAFETY: the same checked image range as the writes, every byte of it written
                // (Verify needs every chunk); nothing else refers to it.
                let image =
                    unsafe { core::slice::from_raw_parts(address as *const u8, length as usize) };
                session.verified(CRC32.checksum(image))
            }
            LoaderAction::Start { entry } => {
                send(&mut uart, &mut out, seq, LoaderResponse::Starting { entry });
                uart.flush();
                start(entry)
            }
        };
        send(&mut uart, &mut out, seq, response);
    }
}

fn send(uart: &mut <Board as Bsp>::Uart, out: &mut [u8], seq: u16, body: LoaderResponse) {
    // A request is complete and the host awaits its answer: the line is quiet.
    uart.line_quiet();
    match frame::encode(&LoaderEnvelope::new(seq, body), out)
        .ok()
        .and_then(|len| out.get(..len))
    {
        Some(bytes) => uart.write(bytes),
        // Unreachable (a shared test checks the largest answer fits); keeps the framing in step.
        None => uart.write(&[frame::DELIMITER]),
    }
}

/// Jumps to a verified image's entry point as if the hart had just been reset there (riscv-rt's
/// `_start` clears `mie`/`mip`, reads the hart id and sets up its own stack), and sends the other
/// harts after it.
fn start(entry: u32) -> ! {
    RELEASE_ENTRY.store(entry, Ordering::Release);
    for hart in 1..HARTS {
        // Raising a hart's software interrupt only wakes it in `_mp_hook` (QEMU ignores harts
        // it lacks).
        Board::wake(hart);
    }
    // SAFETY: `entry` lies inside an image whose every byte arrived CRC-checked and whose whole
    // CRC was then verified in RAM; `fence.i` makes the freshly written code visible to
    // instruction fetch. Nothing of the loader is used after the jump.
    unsafe { core::arch::asm!("fence.i", "jr {entry}", entry = in(reg) entry, options(noreturn)) }
}

#[panic_handler]
fn panic(_: &core::panic::PanicInfo) -> ! {
    Board::exit(EXIT_PANIC)
}

#[export_name = "ExceptionHandler"]
fn exception_handler(_: &riscv_rt::TrapFrame) -> ! {
    Board::exit(EXIT_EXCEPTION)
}

#[export_name = "DefaultHandler"]
fn default_handler() -> ! {
    Board::exit(EXIT_INTERRUPT)
}
