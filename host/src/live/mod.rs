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
//! - [`engine`]: the one trait every kind of frame is solved through, quasi-static
//!   ([`quasi_static`]: on a target over [`link`], or on the host) or dynamic ([`dynamic`]:
//!   one time step h of [`crate::dynamics`] per frame, S resident on the target).
//! - [`session`]: the scripted session behind `--headless`, over any engine; [`sink`] writes
//!   its frames (`--frames-csv`, `--out`); [`report`] and [`dynamic_report`] are its JSON, over
//!   the figures of [`stats`].
//! - [`interactive`]: the session behind `--serve`, the tool where the browser puts it, over
//!   any engine; [`serve`] carries the page and the frames to the browsers.
//! - [`field`]: which nodes a field frame carries (`--field all|surface|stride:K`).
//! - [`start`]: a session from a scenario and its options: the set-up, the engine on a board or
//!   the host, the checks that come before anything starts.

pub mod dynamic;
pub mod dynamic_report;
pub mod engine;
pub mod field;
pub mod interactive;
pub mod link;
pub mod quasi_static;
pub mod report;
pub mod resident;
pub mod serve;
pub mod session;
pub mod setup;
pub mod sink;
pub mod start;
pub mod stats;

pub use setup::{LiveSetup, SetupError};
