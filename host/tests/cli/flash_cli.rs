//! `deform flash` and the log flags on bad input: a clear message and exit status 1, before
//! anything is booted or sent.

use std::process::{Command, Output};

fn deform(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_deform"))
        .args(args)
        .output()
        .expect("the deform binary runs")
}

fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

#[test]
fn a_missing_file_is_named() {
    let out = deform(&["flash", "/nonexistent/firmware.elf", "--target", "qemu"]);
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    let text = stderr(&out);
    assert!(text.contains("/nonexistent/firmware.elf"), "{text}");
    assert!(!text.contains("panicked"), "{text}");
}

#[test]
fn a_file_that_is_not_an_elf_is_refused() {
    let manifest = concat!(env!("CARGO_MANIFEST_DIR"), "/Cargo.toml");
    let out = deform(&["flash", manifest]);
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("not a 32-bit ELF"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn port_and_target_exclude_each_other_and_bad_timeouts_are_refused() {
    let out = deform(&["flash", "fw.elf", "--port", "/dev/null", "--target", "qemu"]);
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    let out = deform(&["flash", "fw.elf", "--request-timeout", "0"]);
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("seconds"), "{}", stderr(&out));
}

#[test]
fn an_elf_without_a_log_table_is_refused_for_logs() {
    // Cargo.toml is no ELF: `--elf` must name a firmware with a defmt table.
    let manifest = concat!(env!("CARGO_MANIFEST_DIR"), "/Cargo.toml");
    let out = deform(&[
        "solve",
        "--grid",
        "3,3,3",
        "--port",
        "/dev/null",
        "--elf",
        manifest,
    ]);
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("not a firmware ELF with a defmt table"),
        "{}",
        stderr(&out)
    );
}
