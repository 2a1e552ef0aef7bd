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

/// A QEMU build sent to the LiteX SoC is refused at once, before the SoC is started, naming the
/// board it was built for and how to build for LiteX (it failed after 19 s of CRC errors); the
/// QEMU board checks the same way.
#[test]
fn an_image_for_another_board_is_refused_before_anything_starts() {
    let elf = deform_hil_sim::firmware_elf();
    let elf = elf.to_str().unwrap();
    let started = std::time::Instant::now();
    let out = deform(&["flash", elf, "--target", "litex"]);
    let text = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{text}");
    for needle in [
        "outside the LiteX VexRiscv SoC's RAM (0x40000000..0x40200000)",
        "it was built for QEMU's riscv32 virt board",
        "cargo xtask firmware --board litex",
    ] {
        assert!(text.contains(needle), "'{needle}' not in {text}");
    }
    assert!(!text.contains("starting the simulated LiteX SoC"), "{text}");
    assert!(started.elapsed() < std::time::Duration::from_secs(5));
    // The same through a BIOS on a port: refused before the port is opened for SFL.
    let out = deform(&[
        "flash",
        elf,
        "--port",
        "/nonexistent/tty",
        "--protocol",
        "litex",
    ]);
    assert!(
        stderr(&out).contains("built for QEMU's riscv32 virt board"),
        "{}",
        stderr(&out)
    );
}
