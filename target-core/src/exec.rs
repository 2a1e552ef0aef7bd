//! Running one CG phase on several harts: the [`Executor`] abstraction.
//!
//! The solver ([`crate::cg`]) splits every phase into per-hart tasks — hart h runs the tiles
//! assigned to MVU h, or the h-th slice of the vectors — and hands them to an executor. The
//! firmware's executor runs them truly in parallel on the harts of the chip (woken by IPI,
//! joined by an atomic barrier); [`Sequential`] runs them one after another on the calling
//! thread, which is what the host's unit tests use to simulate any number of MVUs with the very
//! same code.
//!
//! Tasks of one phase write disjoint parts of the shared vectors. Rust cannot see that through a
//! `Fn(usize) + Sync` closure, so the solver passes the vectors as [`SharedSlice`]s, whose
//! mutable accessors are `unsafe` with the disjointness as their contract.
#![allow(unsafe_code)]

use core::marker::PhantomData;
use core::ops::Range;

use deform_shared::protocol::{PhaseCounters, MAX_HARTS};

use crate::mvu_backend::{MvuBackend, NoMvus};

/// Reads the cycle and retired-instruction counters, so that the solver can charge each phase.
pub trait PhaseClock {
    fn now(&self) -> PhaseCounters;

    /// [`now`](Self::now), written into `out`. The hardware MVU phase keeps its first reading
    /// in place: read into a local, it was loaded back from the stack before `start`, each
    /// load behind one of the reading's stores to the write-through data cache.
    fn now_into(&self, out: &mut PhaseCounters) {
        *out = self.now();
    }
}

/// A clock that always reads zero, for hosts and tests.
pub struct NoClock;
impl PhaseClock for NoClock {
    fn now(&self) -> PhaseCounters {
        PhaseCounters::default()
    }
}

/// One phase's task: called once with each hart index `0..harts`.
pub type Task<'t> = &'t (dyn Fn(usize) + Sync);

/// Runs the per-hart tasks of one phase.
pub trait Executor: PhaseClock + Sync {
    /// How many harts can run tasks (≥ 1).
    fn harts(&self) -> usize;

    /// Runs `task(h)` for every `h < harts` (`harts ≤ self.harts()`), possibly in parallel,
    /// and returns once all have finished.
    fn run(&self, harts: usize, task: Task<'_>);

    /// Like [`run`](Self::run), but one hart at a time while the others sleep, so that each
    /// hart's cycle and retired-instruction counts over its own task are exact; returns those
    /// counts (zero where the executor cannot count).
    fn run_measured(&self, harts: usize, task: Task<'_>) -> [PhaseCounters; MAX_HARTS];

    /// [`run_measured`](Self::run_measured) for one hart: `task(0)` alone, and its counts
    /// alone. An executor that counts overrides it to skip the array of every hart's counts,
    /// which hart 0 would otherwise zero, return and fold on its serial path at every phase.
    fn run_one_measured(&self, task: Task<'_>) -> PhaseCounters {
        self.run_measured(1, task)[0]
    }

    /// The board's hardware MVUs ([`crate::mvu_backend`]); [`NoMvus`] where it has none.
    type Mvus: MvuBackend;

    /// The hardware MVUs beside the harts, if the board has them (see
    /// [`crate::mvu_backend`]); without them the harts run every MVU phase in software.
    fn mvu_backend(&self) -> Option<&Self::Mvus> {
        None
    }
}

/// The slowest of `harts`' counts from [`Executor::run_measured`], each count its own slowest
/// hart's (the hart with the most cycles need not retire the most instructions): a parallel
/// phase's critical path.
pub fn slowest(counts: &[PhaseCounters]) -> PhaseCounters {
    counts
        .iter()
        .fold(PhaseCounters::default(), |m, &c| m.max_each(c))
}

/// Runs every hart's task in turn on the calling thread: the host's stand-in for N MVUs.
pub struct Sequential {
    pub harts: usize,
}

impl PhaseClock for Sequential {
    fn now(&self) -> PhaseCounters {
        PhaseCounters::default()
    }
}

impl Executor for Sequential {
    type Mvus = NoMvus;

    fn harts(&self) -> usize {
        self.harts.clamp(1, MAX_HARTS)
    }

    fn run(&self, harts: usize, task: Task<'_>) {
        for h in 0..harts.min(self.harts()) {
            task(h);
        }
    }

    fn run_measured(&self, harts: usize, task: Task<'_>) -> [PhaseCounters; MAX_HARTS] {
        self.run(harts, task);
        [PhaseCounters::default(); MAX_HARTS]
    }
}

/// A mutable slice that the tasks of one phase share, each touching only its own elements.
///
/// Created from a `&mut [T]`, so for its lifetime nothing else can reach the elements.
pub struct SharedSlice<'a, T> {
    ptr: *mut T,
    len: usize,
    _borrow: PhantomData<&'a mut [T]>,
}

// SAFETY: a SharedSlice only hands out element access through `unsafe` methods whose callers
// guarantee that no two harts touch the same element at once; `T: Send` lets the elements be
// reached from another hart.
unsafe impl<T: Send> Sync for SharedSlice<'_, T> {}
// SAFETY: as above; moving the handle moves only the borrow.
unsafe impl<T: Send> Send for SharedSlice<'_, T> {}

impl<'a, T> SharedSlice<'a, T> {
    pub fn new(slice: &'a mut [T]) -> Self {
        SharedSlice {
            ptr: slice.as_mut_ptr(),
            len: slice.len(),
            _borrow: PhantomData,
        }
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Elements `range` (clamped to the slice), mutably.
    ///
    /// # Safety
    ///
    /// While the returned slice lives, no other task may access any element of `range`.
    #[allow(clippy::mut_from_ref)]
    pub unsafe fn slice_mut(&self, range: Range<usize>) -> &mut [T] {
        let end = range.end.min(self.len);
        let start = range.start.min(end);
        // SAFETY: start ≤ end ≤ len keeps the pointer inside the borrowed slice; exclusivity
        // is the caller's promise.
        unsafe { core::slice::from_raw_parts_mut(self.ptr.add(start), end - start) }
    }

    /// All elements, read-only.
    ///
    /// # Safety
    ///
    /// While the returned slice lives, no task may write any element.
    pub unsafe fn as_slice(&self) -> &[T] {
        // SAFETY: the whole borrowed slice; the absence of writers is the caller's promise.
        unsafe { core::slice::from_raw_parts(self.ptr, self.len) }
    }

    /// The raw base pointer, for the MVU kernels (see [`crate::kernel`]).
    pub fn as_mut_ptr(&self) -> *mut T {
        self.ptr
    }
}

/// Pieces of a [`share`] start at multiples of this: the SVU's assembly loops take four
/// elements per pass of their body, so only the last piece can leave a shorter tail.
pub const SHARE_ALIGN: usize = 4;

/// The `h`-th of `parts` near-equal contiguous pieces of `0..len`, each starting at a
/// multiple of [`SHARE_ALIGN`] (the last one takes what is left).
pub fn share(len: usize, parts: usize, h: usize) -> Range<usize> {
    let parts = parts.max(1);
    let blocks = len / SHARE_ALIGN;
    let edge = |k: usize| {
        if k >= parts {
            len
        } else {
            blocks * k / parts * SHARE_ALIGN
        }
    };
    edge(h)..edge(h + 1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shares_cover_the_range_once() {
        for len in [0, 1, 7, 13, 512, 1000, 4096] {
            for parts in 1..=8 {
                let mut next = 0;
                for h in 0..parts {
                    let r = share(len, parts, h);
                    assert_eq!(r.start, next);
                    assert_eq!(r.start % SHARE_ALIGN, 0);
                    assert!(r.len() <= len.div_ceil(parts) + 2 * SHARE_ALIGN);
                    next = r.end;
                }
                assert_eq!(next, len);
            }
        }
    }

    #[test]
    fn sequential_runs_every_hart_once() {
        let hits = core::sync::atomic::AtomicUsize::new(0);
        let exec = Sequential { harts: 4 };
        exec.run(3, &|h| {
            hits.fetch_add(1 << (8 * h), core::sync::atomic::Ordering::Relaxed);
        });
        assert_eq!(hits.into_inner(), 0x01_01_01);
    }
}
