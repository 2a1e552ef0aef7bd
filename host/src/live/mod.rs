//! `deform live`: the interactive real-time loop (issue 12). A tool — the scenario's prescribed
//! nodes, moved along their keyframes — pushes the tissue frame by frame; the target answers
//! each frame with the reaction force, answers force queries between frames from a local
//! linear model, and sends the field quantised at a lower rate. The messages are in
//! [`deform_shared::live`]; the target's half is `target-core/src/live.rs`. A scenario whose
//! tool is scheduled point loads instead drives a force tool (protocol 9): loads in, the tool
//! nodes' mean displacement out, the compliance as the local model ([`setup::ToolKind`]).
//!
//! - [`setup`]: what the target needs once: the matrix, each tool node's row of the
//!   unconstrained K, the static loads, and the f64 pieces the host checks against.
//! - [`link`]: the live requests over a [`Target`](crate::link::Target), with bytes counted on
//!   the line and a target reset answered by uploading everything again.
//! - [`field`]: which nodes a field frame carries (`--field all|surface|stride:K`).
//! - [`headless`]: the scripted session behind `--headless` and its JSON report.
//! - [`dynamic`]: dynamic frames (a dynamic scenario): one time step h of
//!   [`crate::dynamics`] per frame, S resident on the target, u and v held on the host;
//!   [`dynamic_report`] is their JSON report.
//! - [`interactive`]: the session behind `--serve`, the tool where the browser puts it;
//!   [`serve`] carries the page and the frames to the browsers.

pub mod dynamic;
pub mod dynamic_report;
pub mod field;
pub mod headless;
pub mod interactive;
pub mod link;
pub mod serve;
pub mod setup;

pub use setup::{LiveSetup, SetupError};
