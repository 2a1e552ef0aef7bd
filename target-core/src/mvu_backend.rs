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
//! returns pᵀKp and the OR of |Kp|, Kp being where the solver reads it.

use deform_shared::protocol::MAX_DIRECTIONS;

use crate::cg::Matrix;
use crate::kernel::{Lanes, Sums};

/// What an MVU phase yields besides Kp, summed over the MVUs (pᵀKp is exact, the ORs are of the
/// finished rows' magnitudes, as [`crate::kernel::p_kp_and_max`] computes them).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct MvuResults {
    pub p_kp: [i128; MAX_DIRECTIONS],
    pub kp_or: [u64; MAX_DIRECTIONS],
}

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

    /// One MVU phase for `directions` fused directions on the loaded matrix of dimension `n`:
    /// K·p into `kp`, p and kp being the solver's vectors. `None` if the hardware cannot run it
    /// (no matrix loaded, another n, or p and kp not in its memories): the software kernel
    /// then runs the phase.
    fn run(
        &self,
        n: usize,
        p: *const Lanes,
        kp: *mut Sums,
        directions: usize,
    ) -> Option<MvuResults>;
}
