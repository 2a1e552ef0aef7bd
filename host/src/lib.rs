//! The deform host library; `main.rs` is a thin CLI over it.
//!
//! - [`model`]: the spring-network tissue model of thesis ch. 2 and its stiffness matrix (CSR);
//! - [`reference`]: the f64 conjugate-gradient baseline;
//! - [`encode`]: K as tiles of MVU instruction words (symmetry, partitioning, tiling);
//! - [`precondition`]: Jacobi as diagonal scaling; [`metrics`]: per-iteration figures;
//! - [`cli_model`]: the model flags shared by subcommands; [`commands`]: the subcommands;
//! - [`bench`]: the performance analysis behind `deform bench`.
pub mod bench;
pub mod board;
pub mod cli_dynamics;
pub mod cli_logs;
pub mod cli_model;
pub mod commands;
pub mod dynamics;
pub mod encode;
pub mod firmware_logs;
pub mod flash;
pub mod inverse;
pub mod link;
pub mod live;
pub mod metrics;
pub mod model;
pub mod output;
pub mod precondition;
pub mod reference;
pub mod refine;
pub mod scenario;
pub mod simulate;
