//! # deform-firmware
//!
//! The target side of deform on a RISC-V board — QEMU's riscv32 `virt` machine or a LiteX SoC
//! with a VexRiscv CPU, chosen by a cargo feature ([`board`]): it feeds the UART's bytes to the
//! transport ([`deform_target_core::transport::TargetLink`]), which hands each request, in
//! sequence order and exactly once, to [`deform_target_core::session::Session`] and writes back
//! its reply (see [`deform_shared::transport`] and [`deform_shared::protocol`]). The session and the CG solver
//! are hardware-free and tested on the host; this crate adds only the devices and the storage.
//!
//! - Hart 0 runs the protocol; every hart (up to 8 on QEMU `-smp N`, one on LiteX) is an MVU and runs its share
//!   of each CG phase ([`harts`]). `TargetInfo::harts` reports how many came up.
//! - Storage ([`store`]): a matrix store and vectors sized by the board (QEMU: 512 Ki words,
//!   4096 tiles, n ≤ 65536; LiteX: 64 Ki words, 1024 tiles, n ≤ 8192) in three directions, all
//!   static and zeroed at boot (`.bss`).
//! - Timing: the solver's phases are charged with `mcycle`/`minstret`: exact instruction counts
//!   under QEMU `-icount` (where a cycle is an instruction), the RTL's real cycles beside the
//!   instructions retired on LiteX; per-hart counts come from one iteration whose phases run one
//!   hart at a time.
//! - UART (the board's [`Bsp::Uart`](board::Bsp::Uart)): on QEMU the hart sleeps in `wfi` while
//!   it waits (woken through the PLIC; interrupts stay globally off), and the FIFOs go on only
//!   after the first request, so that a request sent while the firmware still boots is not lost;
//!   on LiteX the UART is polled.
//! - The byte stream can be anything: undecodable or overlong frames are NAKed, duplicates get
//!   their cached reply, frames from beyond a gap are held (see the transport).
//!
//! ## Faults
//!
//! Nothing may write to the UART but frames, so a fault cannot print a message. A panic sends
//! one last [`Uplink::Panic`](deform_shared::transport::Uplink::Panic) frame with its message;
//! then every fault stops QEMU through the SiFive test device (on LiteX the hart parks) with a distinctive exit status:
//! [`EXIT_PANIC`] (101) for a Rust panic, [`EXIT_EXCEPTION`] (102) for a CPU exception and
//! [`EXIT_INTERRUPT`] (103) for an unexpected interrupt. Normal operation never exits.
#![no_std]
#![no_main]
#![deny(unsafe_op_in_unsafe_fn, clippy::undocumented_unsafe_blocks)]

mod activity;
mod atomic;
mod board;
mod build_id;
mod harts;
mod logger;
mod store;

use deform_shared::protocol::{ErrorCode, Response, TargetInfo, PROTOCOL_VERSION};
use deform_target_core::session::Session;
use deform_target_core::transport::{self, LinkEvent, TargetLink, Tx};

use board::{Board, Bsp, Serial};
use deform_target_core::exec::Executor;
use harts::Harts;
use store::TakeOnce;

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
        build_id: build_id::build_id(),
    }
}

#[riscv_rt::entry]
fn main(hart: usize) -> ! {
    if hart != 0 {
        harts::worker(hart);
    }
    let mut uart = Board::uart();
    let Some(buffers) = store::BUFFERS.take() else {
        Board::exit(EXIT_NO_STORAGE)
    };
    let (mvus, vectors) = match Board::mvus() {
        Some(m) => (Some(m.backend), Some((m.p, m.kp))),
        None => (None, None),
    };
    let harts = Harts {
        count: harts::start_workers(),
        mvus,
    };
    let count = harts.harts();
    let mut session = Session::new(buffers.storage(vectors), target_info(count), harts);
    let Some(link) = LINK.take() else {
        Board::exit(EXIT_NO_STORAGE)
    };
    defmt::info!(
        "deform firmware {=str} up: {=usize} words, {=usize} tiles, n <= {=usize}, {=usize} MVUs ({=str}), board {=str}",
        FIRMWARE_VERSION,
        store::WORD_CAPACITY,
        store::TILE_CAPACITY,
        session.info().max_n as usize,
        count,
        if session.executor().mvu_backend().is_some() { "hardware" } else { "harts" },
        Board::NAME
    );
    let mut handle = |body| activity::logged(body, |body| session.handle(body));
    loop {
        let byte = uart.read();
        let event = link.feed(byte, &mut handle, &mut UartTx(&mut uart));
        if let Some(LinkEvent::Corrupt(e)) = event {
            activity::unreadable(&ErrorCode::Frame(e));
        }
    }
}

/// The transport's state (sequence numbers, held requests, cached replies: ~10 KiB), static
/// rather than on the stack.
static LINK: TakeOnce<TargetLink> = TakeOnce::new(TargetLink::new());

/// The UART as the transport's output.
struct UartTx<'a>(&'a mut <Board as Bsp>::Uart);

impl Tx for UartTx<'_> {
    fn write(&mut self, frame: &[u8]) {
        // The target writes only after a complete frame arrived, and the host waits for the
        // answer to its first frame (`Hello`) before it sends more: the line is quiet then.
        self.0.line_quiet();
        self.0.write(frame);
    }

    /// The buffered log frames go out before each reply, when the host is reading (see
    /// `logger`).
    fn pending_notice(&mut self) -> Option<Response> {
        logger::take_chunk().map(|(dropped, frames)| Response::Log { dropped, frames })
    }
}

/// Reports the panic over the link in a final [`Uplink::Panic`] frame (message and location,
/// truncated), then stops QEMU with [`EXIT_PANIC`].
///
/// [`Uplink::Panic`]: deform_shared::transport::Uplink::Panic
#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    report_fault(format_args!("{info}"));
    Board::exit(EXIT_PANIC)
}

/// Sends `message` (truncated) in a final [`Uplink::Panic`] frame.
///
/// [`Uplink::Panic`]: deform_shared::transport::Uplink::Panic
fn report_fault(message: core::fmt::Arguments<'_>) {
    use core::fmt::Write;
    let mut text = heapless::String::<{ deform_shared::transport::PANIC_MESSAGE_LEN }>::new();
    // A message longer than the buffer is cut off: `write!` stops at the first failed push.
    let _ = text.write_fmt(message);
    let mut frame = [0u8; 2 * deform_shared::transport::PANIC_MESSAGE_LEN];
    let len = transport::panic_frame(&text, &mut frame);
    // A delimiter first ends whatever frame was being written when the fault struck.
    Board::write_raw(&[deform_shared::frame::DELIMITER]);
    Board::write_raw(frame.get(..len).unwrap_or(&[]));
}

/// Every exception riscv-rt does not route elsewhere (which is all of them) lands here: it is
/// reported like a panic (cause and address, for a board with no other way out, such as
/// LiteX's), then QEMU stops with [`EXIT_EXCEPTION`].
#[export_name = "ExceptionHandler"]
fn exception_handler(_: &riscv_rt::TrapFrame) -> ! {
    report_fault(format_args!(
        "CPU exception: mcause {:#x}, mepc {:#010x}, mtval {:#010x}",
        riscv::register::mcause::read().bits(),
        riscv::register::mepc::read(),
        riscv::register::mtval::read()
    ));
    Board::exit(EXIT_EXCEPTION)
}

/// Interrupts are never enabled; should one arrive anyway, stop.
#[export_name = "DefaultHandler"]
fn default_handler() -> ! {
    Board::exit(EXIT_INTERRUPT)
}
