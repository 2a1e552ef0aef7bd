//! Elastodynamics (thesis eq. 4–7): the tissue as nodal masses joined by springs *and*
//! dampers, f = m·a + Σ(β·du/dt + k̃·u), stepped in time implicitly with the step matrix
//! resident on the target.
//!
//! # Model
//!
//! Per direction d: M·a + C_d·v + K_d·u = f_d, with M the lumped nodal masses (diagonal; a
//! uniform mass or a per-node field given like the stiffness field), K_d the spring Laplacian
//! of the static model, and C_d = B_d (+ a·M + b·K_d with Rayleigh damping). B_d is the damper
//! Laplacian: a damper beside each spring, assembled by the same code as K
//! ([`crate::model::assembly::assemble_laplacian`]) with β per direction, or from a per-node β
//! field whose dampers take the mean of their end nodes' values, like k̃.
//!
//! # Scheme
//!
//! Backward Euler (the default), exactly as issue 14 gives it:
//!
//! ```text
//!     (M + h·C + h²·K)·v₁ = M·v₀ + h·(f₁ − K·u₀),     u₁ = u₀ + h·v₁
//! ```
//!
//! and, as an option, the trapezoidal rule (Newmark average acceleration, second order,
//! energy-conserving without damping), on the same matrix pattern:
//!
//! ```text
//!     (M + h/2·C + h²/4·K)·v₁ = (M − h/2·C − h²/4·K)·v₀ + h·((f₀ + f₁)/2 − K·u₀),
//!     u₁ = u₀ + h·(v₀ + v₁)/2
//! ```
//!
//! Backward Euler is the default because it is L-stable: the spring grid's highest modes,
//! which no practical h resolves, are damped out instead of ringing on (the trapezoidal rule
//! keeps them at full amplitude for ever), and it is what SOFA users compare against.
//!
//! S = M + c_B·C + c_K·K has K's pattern and is SPD. Fixed nodes are eliminated as in the
//! static model (v = 0 there); a prescribed node's velocity is the one that lands on its
//! keyframed displacement at t₁, moved to the right-hand side like a prescribed displacement.
//! f₁ is the load at t₁; a load without keyframes is a step load from t = 0 (no ramp).
//!
//! # Where what runs
//!
//! The host forms each step's right-hand side in f64 (it holds u, v, M, C and K; this keeps
//! the protocol unchanged) and the target solves S·v₁ = b with its resident S, refined in
//! mixed precision ([`crate::refine`]) from the prediction v₁ ≈ v₀. S is uploaded once; a
//! new h or model replaces its values only (`BeginUpdate`/`UpdateValues`/`EndUpdate`).
//!
//! Submodules: [`params`] (what the user gives, checked), [`flags`] (the command line's), [`system`] (M, C, K and S),
//! [`step`] (right-hand side and update, shared by both solvers), [`host`] (the f64
//! reference stepper), [`target`] (the series on the target), [`fixed_point`] (whether the
//! target can hold S), [`resident`] (frames whose right-hand side the target forms itself,
//! protocol version 12).

pub mod fixed_point;
pub mod flags;
pub mod host;
pub mod params;
pub mod resident;
pub mod step;
pub mod system;
pub mod target;

#[cfg(test)]
mod tests;

pub use params::{Damping, DynamicsError, DynamicsSettings, DynamicsSpec, Scheme};
pub use step::{Forcing, Loads, State, StepMatrices};
pub use system::DynamicSystem;
