//! The `litex-vexriscv` board: a LiteX SoC with a VexRiscv CPU (`imac` variant), one hart.
//!
//! Every address comes from the SoC's `csr.json` at build time (build.rs writes them to
//! `litex_csr.rs`; the committed `boards/litex-vexriscv/csr.json` describes the SoC that
//! hil-sim generates, `DEFORM_LITEX_CSR_JSON` names another SoC's). There is no CLINT and no
//! PLIC: the UART is polled, timer0 runs free as the time base, and `mcycle`/`minstret` (which
//! the `imac`, `full` and `secure` variants implement) count the solver's cycles and
//! instructions — on this board the cycles are the RTL's, not one per instruction.
//!
//! Main RAM is cached (reads and writes through the 4 KiB data cache); addresses with bit 31
//! set are uncached I/O on this VexRiscv, which is where LiteX puts the CSRs.

use super::{Bsp, Serial};

/// The CSR register addresses, main RAM and clock of the SoC (generated from csr.json).
mod csr {
    include!(concat!(env!("OUT_DIR"), "/litex_csr.rs"));
}

/// LiteX UART event bit of a received byte (`ev_pending`: write it to pop the byte).
const UART_EV_RX: u32 = 1 << 1;

fn read32(addr: usize) -> u32 {
    // SAFETY: only called with CSR addresses from the SoC's csr.json, always mapped (uncached
    // I/O); reading them has no effect on Rust-visible memory.
    unsafe { core::ptr::read_volatile(addr as *const u32) }
}

fn write32(addr: usize, value: u32) {
    // SAFETY: as in `read32`; writing a UART or timer register touches no Rust-visible memory.
    unsafe { core::ptr::write_volatile(addr as *mut u32, value) }
}

/// How [`Uart::new`] sets the LiteX UART up. Its baud rate is fixed in the gateware (and not
/// modelled by the simulator), so there is nothing to choose but whether to drain it.
#[derive(Clone, Copy, Debug, Default)]
pub struct UartConfig {
    /// Discard bytes already received (e.g. the tail of a BIOS session) at set-up.
    pub drain: bool,
}

/// The LiteX UART, polled (interrupts stay off; there is no PLIC to route them anyway).
pub struct Uart;

impl Uart {
    pub fn new(config: UartConfig) -> Self {
        // No UART interrupts: the CPU polls `rxempty`.
        write32(csr::UART_EV_ENABLE, 0);
        if config.drain {
            while read32(csr::UART_RXEMPTY) == 0 {
                write32(csr::UART_EV_PENDING, UART_EV_RX);
            }
        }
        Uart
    }
}

impl Serial for Uart {
    fn read(&mut self) -> u8 {
        while read32(csr::UART_RXEMPTY) != 0 {}
        let byte = read32(csr::UART_RXTX) as u8;
        write32(csr::UART_EV_PENDING, UART_EV_RX);
        byte
    }

    fn write(&mut self, bytes: &[u8]) {
        write_raw(bytes);
    }

    fn flush(&mut self) {
        while read32(csr::UART_TXEMPTY) == 0 {}
    }
}

fn write_raw(bytes: &[u8]) {
    for &b in bytes {
        while read32(csr::UART_TXFULL) != 0 {}
        write32(csr::UART_RXTX, u32::from(b));
    }
}

/// How [`Timer::start`] runs timer0.
#[derive(Clone, Copy, Debug)]
pub struct TimerConfig {
    /// The value it counts down from, and reloads at zero.
    pub reload: u32,
}

impl Default for TimerConfig {
    fn default() -> Self {
        TimerConfig { reload: u32::MAX }
    }
}

/// LiteX timer0 as a free-running down-counter at the system clock.
pub struct Timer;

impl Timer {
    pub fn start(config: TimerConfig) -> Timer {
        write32(csr::TIMER0_EN, 0);
        write32(csr::TIMER0_LOAD, config.reload);
        write32(csr::TIMER0_RELOAD, config.reload);
        write32(csr::TIMER0_EN, 1);
        Timer
    }

    /// Clock cycles since the last reload (the counter latched by `update_value`).
    pub fn elapsed(&self) -> u32 {
        write32(csr::TIMER0_UPDATE_VALUE, 1);
        u32::MAX - read32(csr::TIMER0_VALUE)
    }
}

/// A LiteX SoC with one VexRiscv hart.
pub struct LitexVexriscv;

impl Bsp for LitexVexriscv {
    const NAME: &'static str = "litex-vexriscv";
    const RAM_START: u32 = csr::MAIN_RAM_BASE;
    const RAM_END: u32 = csr::MAIN_RAM_BASE + csr::MAIN_RAM_SIZE;
    /// No SMP VexRiscv is packaged for LiteX: one hart, one MVU.
    const HARTS: usize = 1;
    /// 256 KiB of words, 20 KiB of tiles, 0.7 MiB of vectors: about 1 MiB, half of hil-sim's
    /// 2 MiB main RAM (zeroed at boot in about 0.3 M cycles), the rest for code and stack.
    const WORD_CAPACITY: usize = 64 * 1024;
    const TILE_CAPACITY: usize = 1024;
    const MAX_N: usize = 8192;
    /// 64 KiB: a dynamic session's stiffness copy for matrices up to 16 Ki words (8³ model B
    /// takes about 5.5 Ki mirrored); the 2 MiB main RAM has no room for a full-size one beside
    /// the response columns and their residuals.
    const STIFFNESS_WORDS: usize = 16 * 1024;
    const TICK_HZ: u64 = csr::CLOCK_FREQUENCY;

    type Uart = Uart;

    /// Also starts timer0, the board's time base.
    fn uart() -> Uart {
        Timer::start(TimerConfig::default());
        Uart::new(UartConfig::default())
    }

    fn write_raw(bytes: &[u8]) {
        write_raw(bytes);
    }

    /// A LiteX SoC has nothing to exit to (the simulator is stopped by its owner): wait for
    /// the last bytes to leave, then park the hart.
    fn exit(_code: u16) -> ! {
        while read32(csr::UART_TXEMPTY) == 0 {}
        loop {
            core::hint::spin_loop();
        }
    }

    fn ticks() -> u64 {
        u64::from(Timer.elapsed())
    }

    /// One hart: no other to wake.
    fn wake(_hart: usize) {}

    fn clear_wake(_hart: usize) {}

    /// One hart never waits for others at boot (`harts::start_workers` returns at once).
    fn wake_at(_ticks: u64) {}
}
