//! The `qemu-virt` board: QEMU's riscv32 `virt` machine.
//!
//! RAM at 0x8000_0000 (`boards/qemu-virt/memory.x`; hil-sim boots QEMU with 64 MiB), the ns16550
//! UART woken through the PLIC, the CLINT (per-hart software interrupts, `mtime`, hart 0's
//! `mtimecmp`), up to [`MAX_HARTS`] harts, and the SiFive test device to exit QEMU with a
//! status. The multi-hart boot hook (`_mp_hook`) is here too: it waits on the CLINT.

use deform_shared::protocol::MAX_HARTS;

use super::{Bsp, Serial};

/// ns16550 UART0 of QEMU `virt`.
const UART0: usize = 0x1000_0000;
/// Receiver buffer (read) / transmitter holding register (write).
const RBR_THR: usize = 0;
/// Interrupt enable.
const IER: usize = 1;
/// FIFO control (write).
const FCR: usize = 2;
/// Line control.
const LCR: usize = 3;
const LCR_DLAB: u8 = 1 << 7;
/// Divisor latch, low and high byte (with `LCR_DLAB` set).
const DLL: usize = 0;
const DLM: usize = 1;
/// Line status.
const LSR: usize = 5;
const LSR_DATA_READY: u8 = 1 << 0;
const LSR_THR_EMPTY: u8 = 1 << 5;
/// Transmitter holding register and shift register both empty.
#[allow(dead_code)] // `Serial::flush`, which only the loader calls
const LSR_TRANSMITTER_EMPTY: u8 = 1 << 6;

/// Platform-level interrupt controller of QEMU `virt`, and UART0's source number on it.
const PLIC: usize = 0x0c00_0000;
const PLIC_UART0: usize = 10;
/// Per-source priority registers.
const PLIC_PRIORITY: usize = PLIC;
/// Enable bits of context 0 (hart 0, M-mode).
const PLIC_ENABLE_CTX0: usize = PLIC + 0x2000;
/// Priority threshold and claim/complete registers of context 0.
const PLIC_THRESHOLD_CTX0: usize = PLIC + 0x20_0000;
const PLIC_CLAIM_CTX0: usize = PLIC + 0x20_0004;
/// IER bit: interrupt when received data is available.
const IER_RX_AVAILABLE: u8 = 1 << 0;

/// Core-local interruptor of QEMU `virt`: one MSIP word per hart, and the machine timer.
const CLINT_MSIP: usize = 0x0200_0000;
const CLINT_MTIME: usize = 0x0200_BFF8;
/// Hart 0's timer compare register.
const CLINT_MTIMECMP0: usize = 0x0200_4000;

/// SiFive test device ("sifive,test0") of QEMU `virt`.
const TEST_DEVICE: usize = 0x10_0000;
const TEST_PASS: u32 = 0x5555;
const TEST_FAIL: u32 = 0x3333;

fn mmio_read32(addr: usize) -> u32 {
    // SAFETY: only called with the PLIC and CLINT register addresses above, always mapped on
    // QEMU virt; reading them has no effect on Rust-visible memory.
    unsafe { core::ptr::read_volatile(addr as *const u32) }
}

fn mmio_write32(addr: usize, value: u32) {
    // SAFETY: only called with the PLIC, CLINT and test device addresses above, always mapped
    // on QEMU virt; writing them has no effect on Rust-visible memory (the test device may stop
    // QEMU; a CLINT write only raises or clears an interrupt or moves the timer compare).
    unsafe { core::ptr::write_volatile(addr as *mut u32, value) }
}

fn uart_read(offset: usize) -> u8 {
    // SAFETY: UART0 + offset (offset ≤ 7) is a byte register of QEMU virt's ns16550, always
    // mapped, with no side effect on Rust-visible memory.
    unsafe { core::ptr::read_volatile((UART0 + offset) as *const u8) }
}

fn uart_write(offset: usize, value: u8) {
    // SAFETY: as in `uart_read`.
    unsafe { core::ptr::write_volatile((UART0 + offset) as *mut u8, value) }
}

/// How [`Uart::new`] sets the ns16550 up.
#[derive(Clone, Copy, Debug)]
pub struct UartConfig {
    /// Baud-rate divisor (QEMU's transmit timing follows it): 1, the fastest, by default.
    pub divisor: u16,
}

impl Default for UartConfig {
    fn default() -> Self {
        UartConfig { divisor: 1 }
    }
}

/// The ns16550 UART, polled, 8N1.
///
/// While it waits for input the hart sleeps in `wfi` rather than spinning on the line status:
/// the UART's receive interrupt is routed through the PLIC to `mie.MEIE`, which wakes `wfi`
/// even though interrupts stay globally disabled (`mstatus.MIE` = 0, so no trap is taken).
/// Under `-icount` this matters: a spinning hart holds QEMU's I/O back, and a 64-word `Words`
/// round trip took ~11 ms instead of ~4 ms.
///
/// The FIFOs start off and are switched on at the first quiet moment ([`Serial::line_quiet`]).
/// Switching them on clears them, and the 4 MiB of storage take 10–20 ms of real time to zero
/// at boot under QEMU, so enabling them during start-up regularly cut short a request the host
/// had sent as soon as QEMU was up. Without FIFOs QEMU holds bytes back until the single
/// receive register is read, so nothing is lost before then, only slower (one byte per wake-up).
pub struct Uart {
    fifos: bool,
}

impl Uart {
    /// Sets the UART and its wake-up path up. Call once.
    pub fn new(config: UartConfig) -> Self {
        let [low, high] = config.divisor.to_le_bytes();
        uart_write(LCR, LCR_DLAB);
        uart_write(DLL, low);
        uart_write(DLM, high);
        uart_write(LCR, 0x03); // 8 data bits, no parity, 1 stop bit, DLAB off
        uart_write(IER, IER_RX_AVAILABLE);
        mmio_write32(PLIC_PRIORITY + 4 * PLIC_UART0, 1);
        mmio_write32(PLIC_ENABLE_CTX0, 1 << PLIC_UART0);
        mmio_write32(PLIC_THRESHOLD_CTX0, 0);
        // SAFETY: enables only the wake-up of `wfi` by external interrupts; with
        // `mstatus.MIE` clear (riscv-rt leaves it clear and nothing sets it) no trap is taken.
        unsafe { riscv::register::mie::set_mext() };
        Uart { fifos: false }
    }
}

impl Serial for Uart {
    /// Waits for the next received byte, asleep in `wfi` until the PLIC signals one.
    fn read(&mut self) -> u8 {
        while uart_read(LSR) & LSR_DATA_READY == 0 {
            riscv::asm::wfi();
            // Claim and complete whatever woke us, so that the PLIC can signal the next one.
            let source = mmio_read32(PLIC_CLAIM_CTX0);
            if source != 0 {
                mmio_write32(PLIC_CLAIM_CTX0, source);
            }
        }
        uart_read(RBR_THR)
    }

    fn write(&mut self, bytes: &[u8]) {
        write_raw(bytes);
    }

    fn flush(&mut self) {
        while uart_read(LSR) & LSR_TRANSMITTER_EMPTY == 0 {}
    }

    /// Switches the FIFOs on, once; only when the peer is not sending, since it clears them.
    ///
    /// The receive trigger level is 1 byte: the interrupt is raised as soon as anything is in
    /// the FIFO, and [`read`](Self::read) drains all of it per wake-up (QEMU fills up to 16 bytes
    /// at a time). A higher level would leave a frame's tail to QEMU's FIFO-timeout timer, which
    /// runs on the virtual clock: with `-icount …,sleep=off` (several harts) that clock stands
    /// still while every hart sleeps, so the tail would never arrive.
    fn line_quiet(&mut self) {
        if !self.fifos {
            uart_write(FCR, 0x07);
            self.fifos = true;
        }
    }
}

/// Polls the transmitter and writes `bytes`.
fn write_raw(bytes: &[u8]) {
    for &b in bytes {
        while uart_read(LSR) & LSR_THR_EMPTY == 0 {}
        uart_write(RBR_THR, b);
    }
}

/// `mtime` ticks at 10 MHz on QEMU `virt`.
const MTIME_HZ: u64 = 10_000_000;

/// QEMU's riscv32 `virt` machine.
pub struct QemuVirt;

impl Bsp for QemuVirt {
    const NAME: &'static str = "qemu-virt";
    const RAM_START: u32 = 0x8000_0000;
    /// hil-sim boots QEMU with `-m 64M`.
    const RAM_END: u32 = 0x8400_0000;
    const HARTS: usize = MAX_HARTS;
    /// 2 MiB of words, 80 KiB of tiles, 9 MiB of vectors: within the 16 MiB of memory.x.
    const WORD_CAPACITY: usize = 512 * 1024;
    const TILE_CAPACITY: usize = 4096;
    const MAX_N: usize = 65536;
    const TICK_HZ: u64 = MTIME_HZ;

    type Uart = Uart;

    fn uart() -> Uart {
        Uart::new(UartConfig::default())
    }

    fn write_raw(bytes: &[u8]) {
        write_raw(bytes);
    }

    /// Ends the QEMU process: with status 0 for `code == 0`, else with status `code`.
    fn exit(code: u16) -> ! {
        let value = if code == 0 {
            TEST_PASS
        } else {
            (u32::from(code) << 16) | TEST_FAIL
        };
        mmio_write32(TEST_DEVICE, value);
        // Not on QEMU (or the write did not stop it): park the hart.
        loop {
            core::hint::spin_loop();
        }
    }

    /// The CLINT's `mtime`. Two 32-bit reads: the low word may wrap in between, which only
    /// shortens one wait.
    fn ticks() -> u64 {
        let lo = mmio_read32(CLINT_MTIME);
        let hi = mmio_read32(CLINT_MTIME + 4);
        (u64::from(hi) << 32) | u64::from(lo)
    }

    /// A write to the MSIP word of a hart QEMU lacks is ignored.
    fn wake(hart: usize) {
        mmio_write32(CLINT_MSIP + 4 * hart, 1);
    }

    fn clear_wake(hart: usize) {
        mmio_write32(CLINT_MSIP + 4 * hart, 0);
    }

    /// Sets hart 0's timer compare register (the low word last, with the high word parked at
    /// its maximum meanwhile, so no spurious match happens in between).
    fn wake_at(at: u64) {
        mmio_write32(CLINT_MTIMECMP0 + 4, u32::MAX);
        mmio_write32(CLINT_MTIMECMP0, at as u32);
        mmio_write32(CLINT_MTIMECMP0 + 4, (at >> 32) as u32);
    }
}

/// The CLINT's MSIP base: the boot hooks (`_mp_hook`) of the application (`harts`) and of the
/// loader wait for their hart's word, in assembly.
pub const MSIP_BASE: usize = CLINT_MSIP;
