//! `deform live`: the interactive real-time loop (issue 12). A tool — the scenario's prescribed
//! nodes, moved along their keyframes — pushes the tissue frame by frame; the target answers
//! each frame with the reaction force, answers force queries between frames from a local
//! linear model, and sends the field quantised at a lower rate. The messages are in
//! [`deform_shared::live`]; the target's half is `target-core/src/live.rs`.
//!
//! - [`setup`]: what the target needs once: the matrix, each tool node's row of the
//!   unconstrained K, the static loads, and the f64 pieces the host checks against.
//! - [`link`]: the live requests over a [`Target`](crate::link::Target), with bytes counted on
//!   the line and a target reset answered by uploading everything again.
//! - [`field`]: which nodes a field frame carries (`--field all|surface|stride:K`).
//! - [`headless`]: the scripted session behind `--headless` and its JSON report.
//! - [`interactive`]: the session behind `--serve`, the tool where the browser puts it;
//!   [`serve`] carries the page and the frames to the browsers.

pub mod field;
pub mod headless;
pub mod interactive;
pub mod link;
pub mod serve;
pub mod setup;

pub use setup::{LiveSetup, SetupError};
