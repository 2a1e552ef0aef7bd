//! The link at a byte-error rate of 1e-2 each way, end to end: the `deform solve` binary with
//! its default link flags, through the fault relay in front of QEMU with 8 harts, once clean and
//! then once per seed. Every noisy run's displacements must equal the clean run's bit for bit
//! (the `--out` CSV holds them in round-trip precision, so the files must be equal).
//!
//! ```text
//! cargo xtask firmware && cargo build --release -p deform-host
//! cargo run --release -p deform-hil-sim --example noisy_link [-- --seeds 8 --rate 1e-2]
//! ```
//!
//! Prints per seed the wall time, the bytes the relay passed each way, the faults it injected
//! and whether the run completed bit-identical; then how many did. The default solve is the one
//! the issue reported half its seeds failing on (`--model b --grid 8,8,8 --k 1 --load
//! 0,4,4:1,0.5,-0.25 --tol 1e-10`); `-- ARGS…` replaces it.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use clap::Parser;
use deform_hil_sim::relay::{FaultConfig, FaultRelay};
use deform_hil_sim::{firmware_elf, Qemu, QemuConfig, MAX_HARTS};

#[derive(Parser)]
#[command(about = "deform solve through the fault relay, one run per seed, against a clean run")]
struct Args {
    /// Seeds of the relay's faults (0x5EED0000 + 0, 1, …).
    #[arg(long, default_value_t = 8)]
    seeds: u64,
    /// Byte-error rate each way (flips, drops, duplicates and inserted bytes in equal parts).
    #[arg(long, default_value_t = 1e-2)]
    rate: f64,
    /// The `deform solve` arguments (the port and --out are added).
    #[arg(last = true)]
    solve: Vec<String>,
}

const DEFAULT_SOLVE: &[&str] = &[
    "--model",
    "b",
    "--grid",
    "8,8,8",
    "--k",
    "1",
    "--load",
    "0,4,4:1,0.5,-0.25",
    "--tol",
    "1e-10",
];

/// One run's outcome.
struct Run {
    csv: Result<String, String>,
    wall: Duration,
    to_target: u64,
    to_host: u64,
    faults: u64,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let deform = deform_binary()?;
    let solve: Vec<String> = if args.solve.is_empty() {
        DEFAULT_SOLVE.iter().map(|s| s.to_string()).collect()
    } else {
        args.solve.clone()
    };
    let scratch = std::env::temp_dir().join(format!("deform-noisy-link-{}", std::process::id()));
    std::fs::create_dir_all(&scratch)?;
    println!(
        "deform solve {} (default link flags), QEMU with {MAX_HARTS} harts",
        solve.join(" ")
    );
    let clean = run(
        &deform,
        &solve,
        FaultConfig::clean(),
        &scratch.join("clean.csv"),
    )?;
    let want = clean
        .csv
        .clone()
        .map_err(anyhow::Error::msg)
        .context("the clean run")?;
    report("clean", &clean, true);
    let mut identical = 0;
    for seed in 0..args.seeds {
        let config = FaultConfig::byte_error_rate(args.rate, 0x5EED_0000 + seed);
        let noisy = run(
            &deform,
            &solve,
            config,
            &scratch.join(format!("{seed}.csv")),
        )?;
        let same = noisy.csv.as_ref().is_ok_and(|csv| *csv == want);
        identical += u64::from(same);
        report(&format!("seed {seed}"), &noisy, same);
    }
    println!(
        "{identical} of {} seeds at a byte-error rate of {:e} each way completed bit-identical",
        args.seeds, args.rate
    );
    std::fs::remove_dir_all(&scratch)?;
    Ok(())
}

/// `target/release/deform`, beside this example's own directory.
fn deform_binary() -> anyhow::Result<PathBuf> {
    let exe = std::env::current_exe()?;
    let release = exe
        .parent()
        .and_then(Path::parent)
        .context("the example's directory")?;
    let deform = release.join("deform");
    if !deform.is_file() {
        bail!(
            "{} is missing: run `cargo build --release -p deform-host` first",
            deform.display()
        );
    }
    Ok(deform)
}

/// Boots QEMU, puts a relay with `config` in front of it and runs `deform solve` through it.
fn run(deform: &Path, solve: &[String], config: FaultConfig, out: &Path) -> anyhow::Result<Run> {
    let qemu = Qemu::start(&QemuConfig::new(firmware_elf()).harts(MAX_HARTS))?;
    let relay = FaultRelay::start(qemu.pty_path(), config)?;
    let started = Instant::now();
    let output = Command::new(deform)
        .arg("solve")
        .args(solve)
        .arg("--port")
        .arg(relay.pty_path())
        .arg("--out")
        .arg(out)
        .stdin(Stdio::null())
        .output()
        .context("running deform")?;
    let wall = started.elapsed();
    let csv = if output.status.success() {
        std::fs::read_to_string(out).map_err(|e| e.to_string())
    } else {
        Err(String::from_utf8_lossy(&output.stderr).trim().to_string())
    };
    let counters = relay.counters();
    Ok(Run {
        csv,
        wall,
        to_target: counters.to_target.load(Relaxed),
        to_host: counters.to_host.load(Relaxed),
        faults: counters.faults(),
    })
}

fn report(label: &str, run: &Run, same: bool) {
    let outcome = match (&run.csv, same) {
        (Ok(_), true) => "bit-identical".to_string(),
        (Ok(_), false) => "DIFFERS from the clean run".to_string(),
        (Err(e), _) => format!("FAILED: {}", e.lines().last().unwrap_or("")),
    };
    println!(
        "{label:>8}: {:6.1} s, {:7} bytes to the target, {:7} to the host, {:5} faults: {outcome}",
        run.wall.as_secs_f64(),
        run.to_target,
        run.to_host,
        run.faults
    );
}
