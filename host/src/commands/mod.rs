//! One module per `deform` subcommand: each has a clap `Args` struct and a `run` that returns
//! `anyhow::Result`, so that `main.rs` only parses and dispatches. A command parses its flags,
//! calls the library and prints; it imports no other command (shared flags live beside what
//! they configure: [`crate::board::BoardFlags`], [`crate::model::flags::ModelFlags`],
//! [`crate::solve::LayoutFlags`], [`crate::dynamics::flags::DynamicFlags`],
//! [`crate::link::LinkFlags`]).

pub mod bench;
pub mod estimate;
pub mod flash;
pub mod live;
pub mod model;
pub mod observe;
pub mod simulate;
pub mod solve;
