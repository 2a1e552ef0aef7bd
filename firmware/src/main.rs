//! # deform-firmware
//!
//! The target side of deform on QEMU's riscv32 `virt` machine: it reads frames from the UART,
//! hands each request to [`deform_target_core::session::Session`] and writes back exactly one
//! framed response per frame (see [`deform_shared::protocol`]). The session and the CG solver
//! are hardware-free and tested on the host; this crate adds only the devices and the storage.
//!
//! - Hart 0 runs the protocol; every hart (up to 8, QEMU `-smp N`) is an MVU and runs its share
//!   of each CG phase ([`harts`]). `TargetInfo::harts` reports how many came up.
//! - Storage ([`store`]): a matrix store of 512 Ki words and 4096 tiles, vectors for n ≤ 65536
//!   in three directions, all static and zeroed at boot (`.bss`).
//! - Timing: the solver's phases are charged with `mcycle`/`minstret`, exact under `-icount`;
//!   per-hart counts come from one iteration whose phases run one hart at a time.
//! - UART ([`hw::Uart`]): while waiting for input the hart sleeps in `wfi` (woken through the
//!   PLIC; interrupts stay globally off). Its FIFOs go on only after the first request, so that
//!   a request sent while the firmware still boots is not lost.
//! - The byte stream can be anything: undecodable frames are answered with
//!   `Error(Frame(..))` and sequence number [`UNKNOWN_SEQ`], overlong ones with
//!   `Error(Frame(TooLong))`.
//!
//! ## Faults
//!
//! Nothing may write to the UART but framed responses, so a fault cannot print a message.
//! Instead it stops QEMU through the SiFive test device with a distinctive exit status:
//! [`EXIT_PANIC`] (101) for a Rust panic, [`EXIT_EXCEPTION`] (102) for a CPU exception and
//! [`EXIT_INTERRUPT`] (103) for an unexpected interrupt. Normal operation never exits.
#![no_std]
#![no_main]
#![deny(unsafe_op_in_unsafe_fn, clippy::undocumented_unsafe_blocks)]

mod harts;
mod hw;
mod store;

use deform_shared::frame::{self, Feed, FrameAccumulator, FrameError};
use deform_shared::protocol::{
    Envelope, ErrorCode, Request, Response, TargetInfo, MAX_FRAME_LEN, PROTOCOL_VERSION,
    UNKNOWN_SEQ,
};
use deform_target_core::session::Session;

use harts::Harts;
use hw::Uart;

/// QEMU exit status after a panic.
pub const EXIT_PANIC: u16 = 101;
/// QEMU exit status after a CPU exception (illegal instruction, access fault, ...).
pub const EXIT_EXCEPTION: u16 = 102;
/// QEMU exit status after an interrupt (none is ever enabled).
pub const EXIT_INTERRUPT: u16 = 103;
/// QEMU exit status if the storage could not be taken (cannot happen: `main` runs once).
pub const EXIT_NO_STORAGE: u16 = 104;

const FIRMWARE_VERSION: &str = env!("CARGO_PKG_VERSION");
const _: () = assert!(
    FIRMWARE_VERSION.len() <= 16,
    "TargetInfo holds 16 bytes of version"
);

fn target_info(harts: usize) -> TargetInfo {
    TargetInfo {
        protocol_version: PROTOCOL_VERSION,
        firmware_version: heapless::String::try_from(FIRMWARE_VERSION).unwrap_or_default(),
        harts: harts as u8,
        word_capacity: store::WORD_CAPACITY as u32,
        tile_capacity: store::TILE_CAPACITY as u32,
        max_n: store::MAX_N as u32,
    }
}

#[riscv_rt::entry]
fn main(hart: usize) -> ! {
    if hart != 0 {
        harts::worker(hart);
    }
    let mut uart = Uart::init();
    let Some(buffers) = store::BUFFERS.take() else {
        hw::exit(EXIT_NO_STORAGE)
    };
    let count = harts::start_workers();
    let mut session = Session::new(buffers.storage(), target_info(count), Harts { count });
    let mut frames = FrameAccumulator::<MAX_FRAME_LEN>::new();
    let mut out = [0u8; MAX_FRAME_LEN];
    loop {
        let byte = uart.read();
        let (seq, body) = match frames.feed(byte) {
            Feed::Pending => continue,
            Feed::Overflow => (
                UNKNOWN_SEQ,
                Response::Error(ErrorCode::Frame(FrameError::TooLong)),
            ),
            Feed::Frame(bytes) => match frame::decode::<Envelope<Request>>(bytes) {
                Ok(Envelope { seq, body }) => (seq, session.handle(body)),
                Err(e) => (UNKNOWN_SEQ, Response::Error(ErrorCode::Frame(e))),
            },
        };
        send(&mut uart, &mut out, seq, body);
    }
}

/// Writes one framed response. Every response fits a frame (a shared test checks the largest);
/// should one not, the peer gets `Error(Frame(BufferTooSmall))` with the same sequence number.
fn send(uart: &mut Uart, out: &mut [u8], seq: u16, body: Response) {
    // A request is complete and the host awaits its answer: the line is quiet.
    uart.enable_fifos();
    let len = frame::encode(&Envelope { seq, body }, out).or_else(|e| {
        let body = Response::Error(ErrorCode::Frame(e));
        frame::encode(&Envelope { seq, body }, out)
    });
    match len.ok().and_then(|len| out.get(..len)) {
        Some(bytes) => uart.write(bytes),
        // Unreachable; a lone delimiter at least keeps the peer's framing in step.
        None => uart.write(&[frame::DELIMITER]),
    }
}

#[panic_handler]
fn panic(_: &core::panic::PanicInfo) -> ! {
    hw::exit(EXIT_PANIC)
}

/// Every exception riscv-rt does not route elsewhere (which is all of them) lands here.
#[export_name = "ExceptionHandler"]
fn exception_handler(_: &riscv_rt::TrapFrame) -> ! {
    hw::exit(EXIT_EXCEPTION)
}

/// Interrupts are never enabled; should one arrive anyway, stop.
#[export_name = "DefaultHandler"]
fn default_handler() -> ! {
    hw::exit(EXIT_INTERRUPT)
}
