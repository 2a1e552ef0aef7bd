//! The hardware-in-the-loop tests, one module per area, in one test binary: one link of
//! deform-host and its dependencies instead of eighteen (each ~25 MB; a fresh clone's build had
//! outgrown a CI machine's disk). Run one area with `cargo test -p deform-hil-sim --test hil --
//! live::`.

mod needle;
mod support;

mod bench_quick;
mod big_grid_16;
mod bios_boot;
mod dynamics;
mod engine_harts;
mod examples;
mod flash_loader;
mod gateware;
mod inverse_target;
mod link_adaptive;
mod link_faults;
mod link_reset;
mod link_robustness;
mod litex_mvus;
mod litex_target;
mod live;
mod logs_defmt;
mod partition_equivalence;
mod qemu_board;
mod scenarios;
mod simulate;
