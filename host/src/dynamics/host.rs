//! The f64 reference dynamic stepper: every step's S_d·v₁ = b solved by the host's CG to
//! 1e-14, warm-started from v₀. The target's results are checked against it.

use super::step::{advance, rhs, Forcing, State, StepMatrices};
use super::system::DynamicSystem;
use crate::model::Axis;
use crate::reference::{self, SolveError};

/// Relative residual the reference solves to: far below anything the target is asked for.
pub const REFERENCE_TOL: f64 = 1e-14;

/// One step of the scheme in `m` in f64.
pub fn host_step(
    system: &DynamicSystem,
    m: &StepMatrices,
    state: &State,
    forcing: &Forcing,
) -> Result<State, SolveError> {
    let n = system.n();
    let mut v1: [Vec<f64>; 3] = Default::default();
    for d in Axis::ALL {
        let p = d.position();
        let b = rhs(system, m, state, forcing, d);
        let x = reference::solve(
            m.matrix(d),
            &b,
            Some(&state.v[p]),
            REFERENCE_TOL,
            20 * n.max(100),
        )?;
        v1[p] = x.x;
    }
    Ok(advance(system, m, state, v1, forcing))
}
