//! The harts as MVUs (on a board with several, see [`Bsp::HARTS`]): boot, the worker loop, and the executor that runs the solver's phases on
//! all of them (see `deform_target_core::exec`).
//!
//! - Boot: riscv-rt calls `_mp_hook` on every hart. Hart 0 returns 1 and initialises RAM; the
//!   others sleep in `wfi` until hart 0 sends them a software interrupt (CLINT MSIP) once RAM
//!   is ready, then enter `main` with their hart id, which sends them to [`worker`].
//! - Probe: each worker counts itself in [`HARTS_UP`]; hart 0 waits for them a bounded time, so
//!   `TargetInfo::harts` is the number that really came up, whatever `-smp` says.
//! - A phase: hart 0 publishes the task and a new generation number, wakes the harts it needs
//!   by IPI, runs its own share, and waits until the `done` counter says every worker finished
//!   (the last one wakes hart 0 by IPI). Every sleeper checks `mip.MSIP` before `wfi`, so an IPI
//!   that arrives just before it sleeps is not lost (under `-icount` such a hart would never
//!   wake again).
//! - Measured phases run the shares one hart at a time while all others sleep in `wfi`. Under
//!   QEMU `-icount` every hart's `minstret` reads one machine-wide count, so only then is each
//!   hart's delta its own work.

use core::cell::UnsafeCell;
use core::sync::atomic::{fence, AtomicU32, AtomicUsize, Ordering};

use deform_shared::protocol::{PhaseCounters, MAX_HARTS};
use deform_target_core::exec::{Executor, PhaseClock, Task};
use deform_target_core::mvu_backend::MvuBackend;

use crate::board::{Board, Bsp, MvuDriver};

/// How long hart 0 waits at boot for the other harts to report (virtual time).
const PROBE_TICKS: u64 = Board::TICK_HZ / 200;

// The boot hook of a multi-hart board (riscv-rt: assembly, hart id in a0, must not touch
// s0–s2). Harts other than 0 enable only the software-interrupt wake-up (interrupts stay
// globally off, no trap is taken), sleep until their CLINT MSIP word is set, clear it and
// return 0: riscv-rt then skips RAM initialisation for them and enters `main(hartid)`.
// A single-hart board keeps riscv-rt's default hook.
#[cfg(feature = "qemu-virt")]
core::arch::global_asm!(
    r#"
    .section .init.mp_hook, "ax"
    .global _mp_hook
_mp_hook:
    beqz a0, 2f
    li t0, 8
    csrs mie, t0
1:  csrr t1, mip
    andi t1, t1, 8
    bnez t1, 3f
    wfi
    j 1b
3:  li t1, {msip}
    slli t2, a0, 2
    add t1, t1, t2
    sw zero, 0(t1)
    li a0, 0
    ret
2:  li a0, 1
    ret
"#,
    msip = const crate::board::qemu_virt::MSIP_BASE,
);

/// Workers that have reached their loop.
pub static HARTS_UP: AtomicUsize = AtomicUsize::new(0);

/// `ONLY` value meaning "every hart below `harts`".
const ALL: usize = usize::MAX;

/// What hart 0 publishes for a phase.
struct Dispatch {
    /// Bumped (Release) after the fields below are set; workers read them after seeing it.
    generation: AtomicUsize,
    harts: AtomicUsize,
    only: AtomicUsize,
    done: AtomicUsize,
    task: UnsafeCell<Option<Task<'static>>>,
    /// Each hart's retired instructions and cycles over its last measured task.
    counts: [AtomicU32; MAX_HARTS],
    cycles: [AtomicU32; MAX_HARTS],
}

// SAFETY: `task` is written only by hart 0 while no worker runs a phase (before the generation
// is bumped, after `done` says all have finished) and read by workers only in between.
unsafe impl Sync for Dispatch {}

static DISPATCH: Dispatch = Dispatch {
    generation: AtomicUsize::new(0),
    harts: AtomicUsize::new(0),
    only: AtomicUsize::new(ALL),
    done: AtomicUsize::new(0),
    task: UnsafeCell::new(None),
    counts: [const { AtomicU32::new(0) }; MAX_HARTS],
    cycles: [const { AtomicU32::new(0) }; MAX_HARTS],
};

/// Sends hart `hart` a software interrupt.
fn ipi(hart: usize) {
    Board::wake(hart);
}

/// Clears this hart's software interrupt.
fn clear_ipi(hart: usize) {
    Board::clear_wake(hart);
}

/// Sleeps until `ready()` holds; each wake-up clears this hart's IPI.
fn sleep_until(hart: usize, ready: impl Fn() -> bool) {
    while !ready() {
        if !riscv::register::mip::read().msoft() {
            riscv::asm::wfi();
        }
        clear_ipi(hart);
    }
}

/// Wakes the other harts once RAM is initialised and counts those that report within
/// [`PROBE_TICKS`]. Call once, from hart 0. Returns the number of harts, hart 0 included.
///
/// Hart 0 sleeps while it waits (woken by each reporting worker's IPI, or by its timer at the
/// deadline): under `-icount` a spinning hart is not preempted until its budget runs out, so
/// the workers would never get to run.
// On a one-hart board (LiteX) this returns at once, and clippy sees the rest's ranges and
// comparisons on `Board::HARTS - 1 == 0` as empty or constant.
#[allow(
    clippy::reversed_empty_ranges,
    clippy::absurd_extreme_comparisons,
    clippy::unnecessary_min_or_max
)]
pub fn start_workers() -> usize {
    if Board::HARTS == 1 {
        return 1;
    }
    // SAFETY: enables only the wake-up of `wfi` by this hart's software and timer interrupts;
    // with `mstatus.MIE` clear no trap is taken.
    unsafe {
        riscv::register::mie::set_msoft();
        riscv::register::mie::set_mtimer();
    }
    let deadline = Board::ticks() + PROBE_TICKS;
    Board::wake_at(deadline);
    fence(Ordering::SeqCst);
    for hart in 1..Board::HARTS {
        ipi(hart);
    }
    loop {
        let up = HARTS_UP.load(Ordering::Acquire);
        if up >= Board::HARTS - 1 || Board::ticks() >= deadline {
            break;
        }
        let pending = riscv::register::mip::read();
        if !pending.msoft() && !pending.mtimer() {
            riscv::asm::wfi();
        }
        clear_ipi(0);
    }
    // The timer has fired or will fire once and then stay quiet; its wake-up is masked again.
    // (Re-arming it far in the future instead would, under `-icount …,sleep=off`, make QEMU
    // warp the virtual clock to that deadline as soon as every hart sleeps.)
    // SAFETY: as above.
    unsafe { riscv::register::mie::clear_mtimer() };
    clear_ipi(0);
    1 + HARTS_UP.load(Ordering::Acquire).min(Board::HARTS - 1)
}

/// The loop of every hart but 0: run the phases it is woken for, forever.
pub fn worker(hart: usize) -> ! {
    let mut seen = DISPATCH.generation.load(Ordering::Acquire);
    crate::atomic::fetch_add(&HARTS_UP, 1);
    ipi(0);
    loop {
        sleep_until(hart, || DISPATCH.generation.load(Ordering::Acquire) != seen);
        seen = DISPATCH.generation.load(Ordering::Acquire);
        let harts = DISPATCH.harts.load(Ordering::Acquire);
        let only = DISPATCH.only.load(Ordering::Acquire);
        if hart >= harts || (only != ALL && only != hart) {
            continue;
        }
        // SAFETY: hart 0 set `task` before bumping the generation we just saw, and leaves it
        // alone until this hart has counted itself done.
        let task = unsafe { *DISPATCH.task.get() };
        if let Some(task) = task {
            if only == hart {
                let start = counters();
                task(hart);
                let spent = counters().since(start);
                DISPATCH.counts[hart].store(spent.instructions as u32, Ordering::Relaxed);
                DISPATCH.cycles[hart].store(spent.cycles as u32, Ordering::Relaxed);
            } else {
                task(hart);
            }
        }
        let expected = if only == ALL { harts - 1 } else { 1 };
        if crate::atomic::fetch_add(&DISPATCH.done, 1) + 1 == expected {
            ipi(0);
        }
    }
}

/// The firmware's executor: hart 0 plus the workers that came up, and the board's hardware
/// MVUs if it has them. There may be more MVUs than harts (a LiteX SoC has one hart): a phase's
/// tasks for MVUs beyond the harts then run on hart 0, after its own.
pub struct Harts {
    pub count: usize,
    pub mvus: Option<&'static MvuDriver>,
}

impl Harts {
    /// Publishes `task` for `harts` harts (`only`: one of them) and wakes them.
    fn publish(&self, task: Task<'_>, harts: usize, only: usize) {
        // SAFETY: the lifetime is erased only for the duration of the phase: `run` and
        // `run_measured` wait for every worker to finish before returning, and clear it.
        let task: Task<'static> = unsafe { core::mem::transmute(task) };
        // SAFETY: no worker runs a phase now (the previous one is complete).
        unsafe { *DISPATCH.task.get() = Some(task) };
        DISPATCH.harts.store(harts, Ordering::Relaxed);
        DISPATCH.only.store(only, Ordering::Relaxed);
        DISPATCH.done.store(0, Ordering::Relaxed);
        clear_ipi(0);
        crate::atomic::fetch_add(&DISPATCH.generation, 1);
        if only == ALL {
            for hart in 1..harts {
                ipi(hart);
            }
        } else {
            ipi(only);
        }
    }

    fn finish(&self, expected: usize) {
        sleep_until(0, || DISPATCH.done.load(Ordering::Acquire) >= expected);
        // SAFETY: every worker of the phase has finished with the task.
        unsafe { *DISPATCH.task.get() = None };
    }
}

/// This hart's `mcycle` and `minstret`, read back to back: the one body of [`counters`] and
/// [`counters_into`].
#[inline(always)]
fn read_counters() -> PhaseCounters {
    PhaseCounters {
        cycles: riscv::register::mcycle::read64(),
        instructions: riscv::register::minstret::read64(),
    }
}

/// This hart's `mcycle` and `minstret`. Never inlined: every reading then runs the same
/// instructions between the two counters, so a delta of `mcycle` and one of `minstret` cover the
/// same stretch of work (under QEMU `-icount`, where both count instructions, they are equal).
#[inline(never)]
fn counters() -> PhaseCounters {
    read_counters()
}

/// [`counters`] into `out`, for [`PhaseClock::now_into`]: the same instructions between the
/// two counters.
#[inline(never)]
fn counters_into(out: &mut PhaseCounters) {
    *out = read_counters();
}

impl PhaseClock for Harts {
    fn now(&self) -> PhaseCounters {
        counters()
    }

    fn now_into(&self, out: &mut PhaseCounters) {
        counters_into(out);
    }
}

impl Executor for Harts {
    /// The harts, or the hardware MVUs where there are more of those.
    fn harts(&self) -> usize {
        let mvus = self.mvus.map_or(0, |m| m.mvus());
        self.count.max(mvus).clamp(1, MAX_HARTS)
    }

    fn run(&self, harts: usize, task: Task<'_>) {
        let harts = harts.clamp(1, self.harts());
        let real = harts.min(self.count);
        if real > 1 {
            self.publish(task, real, ALL);
        }
        task(0);
        for h in real..harts {
            task(h);
        }
        if real > 1 {
            self.finish(real - 1);
        }
    }

    fn run_measured(&self, harts: usize, task: Task<'_>) -> [PhaseCounters; MAX_HARTS] {
        // Beyond the harts (hardware MVUs, `self.harts()`), hart 0 runs the shares in turn.
        let harts = harts.clamp(1, self.harts());
        let mut counts = [PhaseCounters::default(); MAX_HARTS];
        for (hart, count) in counts.iter_mut().enumerate().take(harts) {
            if hart == 0 || hart >= self.count {
                let start = counters();
                task(hart);
                *count = counters().since(start);
            } else {
                self.publish(task, self.count.min(harts), hart);
                self.finish(1);
                *count = PhaseCounters {
                    cycles: u64::from(DISPATCH.cycles[hart].load(Ordering::Relaxed)),
                    instructions: u64::from(DISPATCH.counts[hart].load(Ordering::Relaxed)),
                };
            }
        }
        counts
    }

    /// Hart 0's task alone, measured as [`run_measured`](Executor::run_measured) measures it.
    fn run_one_measured(&self, task: Task<'_>) -> PhaseCounters {
        let start = counters();
        task(0);
        counters().since(start)
    }

    type Mvus = MvuDriver;

    fn mvu_backend(&self) -> Option<&MvuDriver> {
        self.mvus
    }
}
