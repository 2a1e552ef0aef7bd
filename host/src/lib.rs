//! The deform host library; `main.rs` is a thin CLI over it ([`commands`]: one file per
//! subcommand, which parses its flags, calls the library and prints). The layers, top down:
//!
//! - [`commands`]: the CLI (the only layer that uses anyhow's context for people);
//! - the library: [`solve`] (a model solved on a target or the host), [`simulate`] and
//!   [`dynamics`] (time series), [`live`] (the live engine and its sessions), [`inverse`]
//!   (estimates from observations), [`bench`] (the thesis's performance analysis);
//! - [`series`]: a time series' schedule and steps, under both kinds of series;
//! - [`board`] (which target, its logs and its bytes) over [`link`] (the serial protocol)
//!   and [`flash`] (loaders);
//! - what they all share: [`model`] (the spring network of thesis ch. 2 and its flags),
//!   [`scenario`] (files), [`encode`] (K as MVU instruction words), [`refine`] (mixed
//!   precision), [`reference`] (the f64 CG), [`precondition`], [`metrics`], [`output`] (files
//!   written whole, series, CSV rows, output paths checked), [`progress`], [`interrupt`],
//!   [`memory`], [`firmware_logs`].
pub mod bench;
pub mod board;
pub mod commands;
pub mod dynamics;
pub mod encode;
pub mod firmware_logs;
pub mod flash;
pub mod interrupt;
pub mod inverse;
pub mod link;
pub mod live;
pub mod memory;
pub mod metrics;
pub mod model;
pub mod output;
pub mod precondition;
pub mod progress;
pub mod reference;
pub mod refine;
pub mod scenario;
pub mod series;
pub mod simulate;
pub mod solve;
