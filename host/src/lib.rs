//! The deform host library; `main.rs` is a thin CLI over it.
pub mod encode;
pub mod link;
pub mod model;
pub mod reference;
