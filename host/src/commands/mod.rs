//! One module per `deform` subcommand: each has a clap `Args` struct and a `run` that returns
//! `anyhow::Result`, so that `main.rs` only parses and dispatches. This is the one layer that
//! uses anyhow: the library modules return typed errors and the commands add context.

pub mod bench;
pub mod estimate;
pub mod flash;
pub mod live;
pub mod live_dynamic;
pub mod model;
pub mod observe;
pub mod simulate;
pub mod simulate_dynamic;
pub mod solve;
