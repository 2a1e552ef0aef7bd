//! # deform-target-core
//!
//! The target's logic, free of hardware so that it runs in host tests too:
//!
//! - [`cg`]: conjugate gradients in block floating point, phase by phase. The MVU
//!   ([`kernel`]) executes the instruction words (thesis 4.2.1) and yields Kp and pᵀKp; the SVU
//!   ([`svu`]) does α, r, β, x and p (4.2.2).
//! - [`mvu_backend`], [`mvu_program`]: hardware MVUs beside the CPU (the gateware's MVU array)
//!   take over the MVU phase where the board has them; the program is how a matrix is laid
//!   out in their memories.
//! - [`session`]: the protocol state machine. It owns no memory: the firmware lends it the
//!   matrix store and the vectors, and it turns each request into exactly one response.
//! - [`log_buffer`]: where the firmware's encoded defmt frames wait to be shipped; it never
//!   blocks and drops whole frames, counted, when full.
//! - [`transport`]: the target end of the reliable link: sequencing, selective repeat, NAKs,
//!   duplicate suppression with cached replies, notices and the panic frame.
//! - `testkit` (tests only, feature `testkit`): owned session storage and tiled test systems.
#![cfg_attr(not(test), no_std)]
// `unsafe` is denied crate-wide and allowed (`#![allow(unsafe_code)]`) only in the modules
// where harts share vectors or walk raw pointers: `exec` (the shared slices), `cg` (the phases
// that hand the harts their slices), `kernel` (the MVU loop) and `svu` (the SVU's assembly
// loops), each `unsafe` block with its invariants written down.
#![deny(unsafe_code)]
#![deny(clippy::undocumented_unsafe_blocks)]

pub mod cg;
pub mod dynamics;
pub mod exec;
pub mod kernel;
pub mod live;
pub mod log_buffer;
pub mod mvu_backend;
pub mod mvu_program;
pub mod predict;
pub mod session;
pub mod superpose;
pub mod svu;
#[cfg(test)]
mod test_rng;
#[cfg(any(test, feature = "testkit"))]
pub mod testkit;
#[cfg(feature = "testkit")]
pub mod trace;
pub mod transport;
pub mod upper;
