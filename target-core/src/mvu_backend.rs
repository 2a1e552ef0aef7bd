//! Hardware MVUs beside the CPU (the gateware's MVU array, thesis 4.2.1 and Fig. 4-8): the hook
//! through which the solver hands them its MVU phase. Without them — and whenever they cannot
//! run a phase — the harts run the software kernel ([`crate::kernel`]), which stays the
//! specification: the hardware computes the same Kp, pᵀKp and max |Kp| bit for bit.
//!
//! The session tells the backend when a matrix becomes resident ([`MvuBackend::load`], after an
//! upload or a values-only update) and when it stops being so ([`MvuBackend::unload`]); the
//! backend lays it out in its MVUs' memories ([`crate::mvu_program`]) if it fits. The solver's
//! p and Kp are the MVU array's own memories on such a board (the firmware lends those windows
//! as its vectors), so a phase copies no vector: [`MvuBackend::run`] starts the MVUs, waits, and
//! writes pᵀKp and the OR of |Kp| into hart 0's slot, Kp being where the solver reads it.

use deform_shared::protocol::MAX_DIRECTIONS;

use crate::cg::Matrix;
use crate::kernel::{Lanes, Sums};

/// Where an MVU phase puts what it yields besides Kp, summed over the MVUs, for directions
/// `0..directions` (pᵀKp is exact, the ORs are of the finished rows' magnitudes, as
/// [`crate::kernel::p_kp_and_max`] computes them): hart 0's slot of the phase's results. The
/// backend writes them there itself: a struct of them returned by value cost a `memset` and two
/// `memcpy`s of 72 bytes per phase on the CPU's path.
pub type MvuOut<'o> = (
    &'o mut [i128; MAX_DIRECTIONS],
    &'o mut [u64; MAX_DIRECTIONS],
);

/// Hardware that runs the MVU phase.
pub trait MvuBackend: Sync {
    /// MVUs the hardware has: tiles may name MVUs `0..mvus()` (the target reports them as its
    /// harts).
    fn mvus(&self) -> usize;

    /// The resident matrix is about to change (an upload or a values-only update begins, or the
    /// session resets): forget it, so that the memories behave as plain vectors again.
    fn unload(&self);

    /// `a` is now resident and validated: take it into the MVUs' memories if it fits; `scratch`
    /// has n rows to lay it out with. Returns whether the hardware will run its phases.
    fn load(&self, a: &Matrix<'_>, scratch: &mut [Sums]) -> bool;

    /// Whether the hardware takes the MVU phases of a solve of `directions` fused directions on
    /// the loaded matrix of dimension `n`, with the solver's vectors `p` and `kp` (they must be
    /// its memories). Asked once per solve, whose matrix and vectors stay the same throughout:
    /// asked every phase, it cost the phase data-cache misses on the backend's state. Where it
    /// answers yes, the backend may set the hardware up for the solve's phases (the direction
    /// count): the solver asks at the start of each solve (and of each [`crate::cg::product`]),
    /// and runs no other solve's phase before this one's last.
    fn begin_solve(&self, n: usize, p: *const Lanes, kp: *mut Sums, directions: usize) -> bool;

    /// One MVU phase of a solve that [`begin_solve`](Self::begin_solve) accepted: K·p into the
    /// solver's Kp, pᵀKp and the OR of |Kp| into `out`.
    fn run(&self, directions: usize, out: MvuOut<'_>);
}

/// The backend of an executor without hardware MVUs: a type with no values, so that
/// [`Executor::mvu_backend`](crate::exec::Executor::mvu_backend) of such an executor can only
/// be `None`. The backend is a type of the executor, not a trait object, so that the solver's
/// call of [`MvuBackend::run`] is a direct one that the board may inline: on the LiteX SoC, a
/// call through the vtable cost the phase a cold instruction-cache line and a data load before
/// `start` (docs/PERFORMANCE.md, "The hardware phase's start inlined, session 12").
pub enum NoMvus {}

impl MvuBackend for NoMvus {
    fn mvus(&self) -> usize {
        match *self {}
    }

    fn unload(&self) {
        match *self {}
    }

    fn load(&self, _: &Matrix<'_>, _: &mut [Sums]) -> bool {
        match *self {}
    }

    fn begin_solve(&self, _: usize, _: *const Lanes, _: *mut Sums, _: usize) -> bool {
        match *self {}
    }

    fn run(&self, _: usize, _: MvuOut<'_>) {
        match *self {}
    }
}
