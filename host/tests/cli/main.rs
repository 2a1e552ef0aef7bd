//! The `deform` command-line tests, one module per subcommand or area, in one test binary (one
//! link instead of seven). Run one area with `cargo test -p deform-host --test cli --
//! live_browser::`.

mod dynamics_cli;
mod flash_cli;
mod inverse_cli;
mod link_target_loss;
mod live_browser;
mod live_cli;
mod live_field;
mod live_host;
mod model_cli;
mod scenario_files;
mod signals;
mod target_logs;
