//! The board layer: everything that differs between the machines the firmware runs on.
//!
//! Modelled on Hubris's `Bsp` trait (one board-support type per board, selected at build time)
//! and embassy's per-chip split (one driver per peripheral, set up from a `Config`). Each board
//! is one module that owns every memory-mapped address, the RAM bounds, the hart count, the
//! timer and the UART driver; the rest of the firmware (the application, the serial loader and
//! the multi-hart executor in `harts`) reaches the hardware only through [`Bsp`] and
//! [`Serial`]. A cargo feature picks the board, and build.rs the board's `memory.x`:
//!
//! - `qemu-virt` (default): QEMU's riscv32 `virt` machine — ns16550 UART woken through the
//!   PLIC, CLINT for inter-hart interrupts and the timer, up to
//!   [`MAX_HARTS`](deform_shared::protocol::MAX_HARTS) harts, the SiFive
//!   test device to exit ([`qemu_virt`]).
//! - `litex-vexriscv`: a LiteX SoC with a VexRiscv CPU (`imac`) — the LiteX UART polled, timer0,
//!   one hart, no CLINT or PLIC; its addresses come from the SoC's `csr.json` at build time
//!   ([`litex_vexriscv`]).
//!
//! A LiteX SoC may also carry deform's hardware MVUs (`gateware/`): the board finds them from
//! its csr.json and hands them over through [`Bsp::mvus`] ([`litex_mvus`]).

#[cfg(all(feature = "qemu-virt", feature = "litex-vexriscv"))]
compile_error!("choose one board feature: `qemu-virt` or `litex-vexriscv`, not both");
#[cfg(not(any(feature = "qemu-virt", feature = "litex-vexriscv")))]
compile_error!("choose a board feature: `qemu-virt` (the default) or `litex-vexriscv`");

#[cfg(feature = "qemu-virt")]
pub mod qemu_virt;
#[cfg(feature = "qemu-virt")]
pub use qemu_virt::QemuVirt as Board;

#[cfg(all(feature = "litex-vexriscv", not(feature = "qemu-virt")))]
pub mod litex_mvus;
#[cfg(all(feature = "litex-vexriscv", not(feature = "qemu-virt")))]
pub mod litex_vexriscv;
#[cfg(all(feature = "litex-vexriscv", not(feature = "qemu-virt")))]
pub use litex_vexriscv::LitexVexriscv as Board;

/// The board's hardware MVUs' driver: a type, not a trait object, so that the solver calls it
/// directly (see `deform_target_core::mvu_backend::NoMvus`).
#[cfg(feature = "qemu-virt")]
pub type MvuDriver = deform_target_core::mvu_backend::NoMvus;
#[cfg(all(feature = "litex-vexriscv", not(feature = "qemu-virt")))]
pub type MvuDriver = litex_mvus::LitexMvus;

/// A board's support: its constants and the few board-wide operations. Drivers for the UART
/// are [`Bsp::Uart`]; the rest is associated functions, since each board exists once.
pub trait Bsp {
    /// A short name for logs ("qemu-virt", "litex-vexriscv").
    const NAME: &'static str;
    /// The RAM an image may occupy: `RAM_START..RAM_END` (what the serial loader accepts).
    #[allow(dead_code)] // the loader's
    const RAM_START: u32;
    #[allow(dead_code)] // the loader's
    const RAM_END: u32;
    /// Harts the firmware may put to work (1 ..= `deform_shared::protocol::MAX_HARTS`); the linker scripts'
    /// `_max_hart_id` is this minus one.
    const HARTS: usize;
    /// The matrix store and vectors that fit the board's RAM (src/store.rs): instruction
    /// words, tile headers, and the largest dimension n.
    const WORD_CAPACITY: usize;
    const TILE_CAPACITY: usize;
    const MAX_N: usize;
    /// Values of the live loop's response columns (one of n per tool node, see
    /// `deform_target_core::superpose`); a tool set whose columns do not fit falls back to
    /// extrapolated starts. By default every tool node's column at `MAX_N` (QEMU: 2 MiB, 13 MiB
    /// of its 16 MiB in all; LiteX: 256 KiB, leaving about 0.7 MiB of its 2 MiB for code and
    /// stack); a board short of RAM sets less.
    const RESPONSE_VALUES: usize = deform_shared::live::MAX_TOOL_NODES * Self::MAX_N;
    /// Words of a dynamic session's stiffness copy of the resident matrix (the words with K's
    /// values, `deform_target_core::dynamics`); a larger matrix runs dynamic frames formed on
    /// the host. By default as many as the matrix store holds.
    const STIFFNESS_WORDS: usize = Self::WORD_CAPACITY;
    /// Ticks per second of [`Bsp::ticks`].
    const TICK_HZ: u64;

    /// The board's UART driver.
    type Uart: Serial;

    /// Sets the UART up (call once, from hart 0).
    fn uart() -> Self::Uart;

    /// Writes bytes to the UART without a driver: for the panic handler, which cannot reach the
    /// one `main` owns.
    fn write_raw(bytes: &[u8]);

    /// Ends the run with status `code` (0: success) where the board can (QEMU exits), else parks
    /// the hart. Never returns.
    fn exit(code: u16) -> !;

    /// A free-running time base (`mtime` on QEMU, timer0 on LiteX).
    fn ticks() -> u64;

    /// Raises hart `hart`'s software interrupt (wakes it from `wfi`). A single-hart board has
    /// no other hart to wake, and this does nothing.
    fn wake(hart: usize);

    /// Clears hart `hart`'s software interrupt.
    fn clear_wake(hart: usize);

    /// Arms hart 0's timer wake-up at `ticks` (the boot probe's deadline).
    fn wake_at(ticks: u64);

    /// The board's hardware MVUs, if it has any (called once, by hart 0 at boot). Without them
    /// the harts run the MVU phase in software.
    fn mvus() -> Option<Mvus> {
        None
    }
}

/// Hardware MVUs beside the CPU, and the vectors they share with it.
pub struct Mvus {
    /// Runs the MVU phase (see `deform_target_core::mvu_backend`).
    pub backend: &'static MvuDriver,
    /// The search directions and Kp in the MVUs' own memories, lent to the solver as its
    /// vectors, so that no phase copies them.
    pub p: &'static mut [deform_target_core::kernel::Lanes],
    pub kp: &'static mut [deform_target_core::kernel::Sums],
}

/// A polled serial port, as the protocol loops use it.
pub trait Serial {
    /// Waits for the next received byte.
    fn read(&mut self) -> u8;
    /// Writes bytes, waiting for room in the transmitter.
    fn write(&mut self, bytes: &[u8]);
    /// Waits until every byte written has left the transmitter.
    #[allow(dead_code)] // the loader's, before it starts the application
    fn flush(&mut self);
    /// Called when the peer is known to be quiet (a request complete, its answer not yet sent):
    /// the moment for set-up that would lose bytes in flight (QEMU: switching the FIFOs on).
    fn line_quiet(&mut self) {}
}
