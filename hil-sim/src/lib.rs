//! # deform-hil-sim
//!
//! QEMU as a board. [`Qemu::start`] boots the firmware ELF on QEMU's `virt` machine with its
//! first UART on a pseudo-terminal, and [`Qemu::pty_path`] names that pty: to the host it is a
//! serial port like a real board's, so the host's ordinary serial client (`deform-host`'s `link`)
//! is tested on exactly the code path it uses with hardware.
//!
//! Two properties of QEMU's pty backend shape how the host talks to it:
//!
//! - bytes the firmware sends while no one has the pty open are dropped, so the host must speak
//!   first (every session starts with a handshake);
//! - QEMU notices that the pty was opened only on its next poll, up to a second later; until then
//!   the host's bytes wait in the pty, so the first answer may take that long.
//!
//! [`relay::FaultRelay`] puts a bad cable between the host and that pty: bit flips, lost,
//! duplicated and inserted bytes, stalls and cuts, from a fixed seed.
//!
//! `-icount shift=0` makes the guest's cycle counters deterministic (one instruction per
//! virtual nanosecond), which is what lets the firmware's `mcycle`/`minstret` reports be compared
//! between runs.

pub mod child;
pub mod litex;
pub mod relay;

use std::ffi::OsString;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

/// The most harts the firmware uses (its `_max_hart_id` is 7): the protocol's, in `shared`.
pub const MAX_HARTS: u8 = deform_shared::protocol::MAX_HARTS as u8;

/// The QEMU binary that emulates the 32-bit RISC-V `virt` machine.
pub const QEMU_BINARY: &str = "qemu-system-riscv32";

/// Where `cargo xtask setup` unpacks Debian's QEMU packages, relative to the workspace root, on a
/// machine where installing them through apt would remove another package (Debian's
/// `qemu-system-misc` 7.2 conflicts with a backported `qemu-utils` 10).
pub const QEMU_UNPACK_DIR: &str = "target/tools/qemu";

/// The binary inside [`QEMU_UNPACK_DIR`] (`-bios none` needs none of the package's firmware files).
pub const QEMU_UNPACKED_BINARY: &str = "usr/bin/qemu-system-riscv32";

/// Where `cargo build --release` in the firmware's workspace puts the ELF, relative to the
/// workspace root (`cargo xtask firmware` builds it there).
pub const FIRMWARE_BUILD_PATH: &str =
    "firmware/target/riscv32imac-unknown-none-elf/release/deform-firmware";

/// Overrides [`firmware_elf`]'s default path when set.
pub const FIRMWARE_ENV: &str = "DEFORM_FIRMWARE";

/// Where the serial loader lands (the firmware package's second binary, built with it).
pub const LOADER_BUILD_PATH: &str =
    "firmware/target/riscv32imac-unknown-none-elf/release/deform-loader";

/// Overrides [`loader_elf`]'s default path when set.
pub const LOADER_ENV: &str = "DEFORM_LOADER";

/// The exit code with which the firmware's panic handler stops QEMU (via the SiFive test device).
pub const PANIC_EXIT_CODE: i32 = 101;

/// The line prefix with which QEMU announces the pty of a `-serial pty` device.
const PTY_ANNOUNCEMENT: &str = "char device redirected to ";

/// Where the firmware ELF is: `$DEFORM_FIRMWARE` if set, else the release build inside the
/// firmware's own workspace (`cargo xtask firmware` puts it there).
pub fn firmware_elf() -> PathBuf {
    match std::env::var_os(FIRMWARE_ENV) {
        Some(path) if !path.is_empty() => PathBuf::from(path),
        _ => default_firmware_elf(),
    }
}

/// The release build inside the firmware's workspace, which sits beside this crate.
fn default_firmware_elf() -> PathBuf {
    workspace_root().join(FIRMWARE_BUILD_PATH)
}

/// Where the serial loader ELF is: `$DEFORM_LOADER` if set, else its release build beside the
/// firmware's (`cargo xtask firmware` builds both). Boot it like the firmware
/// (`QemuConfig::new(loader_elf())`) and flash an application through its UART.
pub fn loader_elf() -> PathBuf {
    match std::env::var_os(LOADER_ENV) {
        Some(path) if !path.is_empty() => PathBuf::from(path),
        _ => workspace_root().join(LOADER_BUILD_PATH),
    }
}

/// The QEMU to run: [`QEMU_BINARY`] on `PATH`, else the copy `cargo xtask setup` unpacked into
/// the workspace ([`QEMU_UNPACK_DIR`]), else the bare name (whose start then fails with
/// [`HilError::QemuMissing`]).
pub fn qemu_binary() -> PathBuf {
    find_qemu(std::env::var_os("PATH").as_deref(), &workspace_root())
}

/// [`qemu_binary`] for a given `PATH` and workspace root.
pub fn find_qemu(path: Option<&std::ffi::OsStr>, root: &Path) -> PathBuf {
    let on_path = path
        .into_iter()
        .flat_map(std::env::split_paths)
        .find_map(|dir| {
            let candidate = dir.join(QEMU_BINARY);
            is_executable(&candidate).then_some(candidate)
        });
    let unpacked = root.join(QEMU_UNPACK_DIR).join(QEMU_UNPACKED_BINARY);
    on_path
        .or_else(|| is_executable(&unpacked).then_some(unpacked))
        .unwrap_or_else(|| PathBuf::from(QEMU_BINARY))
}

/// A file with an execute bit (what a shell's `PATH` search takes).
pub fn is_executable(path: &Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    path.metadata()
        .is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
}

pub(crate) fn workspace_root() -> PathBuf {
    let manifest_dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    manifest_dir.parent().unwrap_or(manifest_dir).to_path_buf()
}

/// Why QEMU could not be started or did not behave.
#[derive(Debug, thiserror::Error)]
pub enum HilError {
    #[error(
        "the firmware ELF {} does not exist: run `cargo xtask firmware` \
         (or point ${FIRMWARE_ENV} at a built firmware)",
        path.display()
    )]
    FirmwareMissing { path: PathBuf },
    #[error(
        "`{binary}` was not found on PATH nor in the workspace's {QEMU_UNPACK_DIR}: run \
         `cargo xtask setup` (it installs Debian's qemu-system-misc, or unpacks it there where \
         installing it would remove another package)"
    )]
    QemuMissing { binary: String },
    #[error("could not start `{binary}`: {source}")]
    Spawn {
        binary: String,
        #[source]
        source: std::io::Error,
    },
    #[error("QEMU exited ({status}) before announcing its serial pty; its stderr:\n{stderr}")]
    ExitedEarly { status: ExitStatus, stderr: String },
    #[error(
        "QEMU did not announce its serial pty within {after:?}; \
         its output so far:\n{stdout}\nstderr:\n{stderr}"
    )]
    NoPty {
        after: Duration,
        stdout: String,
        stderr: String,
    },
    #[error("waiting for QEMU failed: {0}")]
    Wait(#[source] std::io::Error),
    #[error("talking to QEMU's monitor failed: {0}")]
    Monitor(#[source] std::io::Error),
}

/// How to boot the firmware.
#[derive(Debug, Clone)]
pub struct QemuConfig {
    /// The firmware ELF, loaded with `-kernel`.
    pub elf: PathBuf,
    /// Harts (`-smp`); the firmware tells in its `TargetInfo` how many it puts to work.
    pub harts: u8,
    /// The QEMU executable; [`qemu_binary`] by default.
    pub qemu: OsString,
    /// How long QEMU may take to announce its pty.
    pub start_timeout: Duration,
    /// A Unix socket for QEMU's monitor, so that a test can reset the board
    /// ([`Qemu::system_reset`]); `None`: no monitor.
    pub monitor: Option<PathBuf>,
}

impl QemuConfig {
    /// A single-hart board running `elf`.
    pub fn new(elf: impl Into<PathBuf>) -> Self {
        Self {
            elf: elf.into(),
            harts: 1,
            qemu: qemu_binary().into_os_string(),
            start_timeout: Duration::from_secs(10),
            monitor: None,
        }
    }

    /// Puts QEMU's monitor on a Unix socket at `path` (see [`Qemu::system_reset`]).
    pub fn monitor(mut self, path: impl Into<PathBuf>) -> Self {
        self.monitor = Some(path.into());
        self
    }

    /// Harts (`-smp`), clamped to 1..=[`MAX_HARTS`]: the firmware puts up to 8 to work as MVUs,
    /// and a hart beyond them would spin in riscv-rt's `abort`, stealing QEMU's time.
    pub fn harts(mut self, harts: u8) -> Self {
        self.harts = harts.clamp(1, MAX_HARTS);
        self
    }

    /// The arguments QEMU is started with (without the binary).
    pub fn args(&self) -> Vec<OsString> {
        // icount ties virtual time to retired instructions; with several harts QEMU runs them
        // round-robin on one thread, and `sleep=off` keeps idle harts from stalling the clock.
        let icount = if self.harts > 1 {
            "shift=0,sleep=off"
        } else {
            "shift=0"
        };
        let mut args: Vec<OsString> = [
            "-machine", "virt", "-bios", "none", "-display", "none", "-serial", "pty", "-m", "64M",
        ]
        .iter()
        .map(OsString::from)
        .collect();
        args.push("-monitor".into());
        args.push(match &self.monitor {
            Some(path) => {
                let mut spec = OsString::from("unix:");
                spec.push(path);
                spec.push(",server=on,wait=off");
                spec
            }
            None => "none".into(),
        });
        args.push("-smp".into());
        args.push(self.harts.to_string().into());
        args.push("-icount".into());
        args.push(icount.into());
        args.push("-kernel".into());
        args.push(self.elf.clone().into_os_string());
        args
    }
}

impl Default for QemuConfig {
    /// A single-hart board running [`firmware_elf`].
    fn default() -> Self {
        Self::new(firmware_elf())
    }
}

/// A running QEMU board. Dropping it kills and reaps QEMU.
pub struct Qemu {
    child: Child,
    pty: PathBuf,
    /// Everything QEMU printed on stdout and stderr, collected by two reader threads so that QEMU
    /// never blocks on a full pipe.
    stdout: Arc<Mutex<String>>,
    stderr: Arc<Mutex<String>>,
    /// The collector threads, joined once QEMU has exited so that its last words are in.
    collectors: Vec<thread::JoinHandle<()>>,
    exit: Option<ExitStatus>,
}

impl Qemu {
    /// Boots the firmware and waits until QEMU names the pty of the board's UART.
    pub fn start(config: &QemuConfig) -> Result<Qemu, HilError> {
        if !config.elf.is_file() {
            return Err(HilError::FirmwareMissing {
                path: config.elf.clone(),
            });
        }
        let binary = config.qemu.to_string_lossy().into_owned();
        let mut command = Command::new(&config.qemu);
        command
            .args(config.args())
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        let mut child = child::spawn(command).map_err(|source| match source.kind() {
            std::io::ErrorKind::NotFound => HilError::QemuMissing {
                binary: binary.clone(),
            },
            _ => HilError::Spawn {
                binary: binary.clone(),
                source,
            },
        })?;

        let stdout = Arc::new(Mutex::new(String::new()));
        let stderr = Arc::new(Mutex::new(String::new()));
        let (pty_tx, pty_rx) = mpsc::channel();
        let out_pipe = child.stdout.take().expect("stdout is piped");
        let err_pipe = child.stderr.take().expect("stderr is piped");
        let collectors = vec![
            spawn_line_collector(out_pipe, Arc::clone(&stdout), pty_tx.clone()),
            // QEMU versions differ on which stream the announcement goes to.
            spawn_line_collector(err_pipe, Arc::clone(&stderr), pty_tx),
        ];

        let mut qemu = Qemu {
            child,
            pty: PathBuf::new(),
            stdout,
            stderr,
            collectors,
            exit: None,
        };
        let deadline = Instant::now() + config.start_timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match pty_rx.recv_timeout(left.min(Duration::from_millis(50))) {
                Ok(pty) => {
                    qemu.pty = pty;
                    return Ok(qemu);
                }
                Err(mpsc::RecvTimeoutError::Timeout)
                | Err(mpsc::RecvTimeoutError::Disconnected) => {
                    if qemu.try_exit_code()?.is_some() {
                        let status = qemu.exit.expect("try_exit_code saw the exit");
                        return Err(HilError::ExitedEarly {
                            status,
                            stderr: qemu.stderr(),
                        });
                    }
                    if left.is_zero() {
                        return Err(HilError::NoPty {
                            after: config.start_timeout,
                            stdout: qemu.stdout(),
                            stderr: qemu.stderr(),
                        });
                    }
                }
            }
        }
    }

    /// The pseudo-terminal connected to the board's UART, e.g. `/dev/pts/3`.
    pub fn pty_path(&self) -> &Path {
        &self.pty
    }

    /// QEMU's process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Resets the board through QEMU's monitor (which [`QemuConfig::monitor`] must have put on
    /// a socket): the firmware reboots, losing everything it held, while its UART stays on the
    /// same pty, as a board whose reset button was pressed.
    pub fn system_reset(&self, monitor: &Path) -> Result<(), HilError> {
        use std::io::Write;
        let mut socket =
            std::os::unix::net::UnixStream::connect(monitor).map_err(HilError::Monitor)?;
        socket
            .set_read_timeout(Some(Duration::from_secs(5)))
            .map_err(HilError::Monitor)?;
        socket
            .write_all(b"system_reset\n")
            .map_err(HilError::Monitor)?;
        // Wait for the monitor to echo the command back, i.e. to have executed it.
        let mut seen = Vec::new();
        let mut buf = [0u8; 256];
        while !String::from_utf8_lossy(&seen).contains("system_reset") {
            let n = socket.read(&mut buf).map_err(HilError::Monitor)?;
            if n == 0 {
                break;
            }
            seen.extend_from_slice(&buf[..n]);
        }
        Ok(())
    }

    /// Kills QEMU now (a board losing power) and reaps it.
    pub fn kill(&mut self) -> Result<(), HilError> {
        if self.exit.is_none() {
            let _ = self.child.kill();
            self.exit = Some(self.child.wait().map_err(HilError::Wait)?);
            for collector in self.collectors.drain(..) {
                let _ = collector.join();
            }
        }
        Ok(())
    }

    /// QEMU's exit code if it has exited ([`PANIC_EXIT_CODE`] after a firmware panic), `None`
    /// while it runs. A QEMU killed by a signal reports -1.
    pub fn try_exit_code(&mut self) -> Result<Option<i32>, HilError> {
        if self.exit.is_none() {
            self.exit = self.child.try_wait().map_err(HilError::Wait)?;
            if self.exit.is_some() {
                // The pipes are closed now, so the collectors finish promptly.
                for collector in self.collectors.drain(..) {
                    let _ = collector.join();
                }
            }
        }
        Ok(self.exit.map(exit_code))
    }

    /// Waits up to `timeout` for QEMU to exit; its exit code, or `None` if it still runs.
    pub fn wait_exit(&mut self, timeout: Duration) -> Result<Option<i32>, HilError> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(code) = self.try_exit_code()? {
                return Ok(Some(code));
            }
            if Instant::now() >= deadline {
                return Ok(None);
            }
            thread::sleep(Duration::from_millis(10));
        }
    }

    /// What QEMU printed on stderr so far (its error messages); all of it once
    /// [`try_exit_code`](Self::try_exit_code) or [`wait_exit`](Self::wait_exit) saw it exit.
    pub fn stderr(&self) -> String {
        self.stderr.lock().map(|s| s.clone()).unwrap_or_default()
    }

    /// What QEMU printed on stdout so far.
    pub fn stdout(&self) -> String {
        self.stdout.lock().map(|s| s.clone()).unwrap_or_default()
    }
}

impl Drop for Qemu {
    fn drop(&mut self) {
        if self.exit.is_none() {
            // Killing an exited-but-unreaped child is harmless; the wait reaps it either way.
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

fn exit_code(status: ExitStatus) -> i32 {
    status.code().unwrap_or(-1)
}

/// Copies `pipe` line by line into `log`, and sends the path of a pty announcement to `pty_tx`.
fn spawn_line_collector(
    pipe: impl Read + Send + 'static,
    log: Arc<Mutex<String>>,
    pty_tx: mpsc::Sender<PathBuf>,
) -> thread::JoinHandle<()> {
    thread::spawn(move || {
        let mut reader = BufReader::new(pipe);
        let mut line = Vec::new();
        loop {
            line.clear();
            match reader.read_until(b'\n', &mut line) {
                Ok(0) | Err(_) => break,
                Ok(_) => {}
            }
            let text = String::from_utf8_lossy(&line);
            if let Some(pty) = parse_pty_announcement(&text) {
                let _ = pty_tx.send(pty);
            }
            if let Ok(mut log) = log.lock() {
                log.push_str(&text);
            }
        }
    })
}

/// `char device redirected to /dev/pts/3 (label serial0)` → `/dev/pts/3`.
fn parse_pty_announcement(line: &str) -> Option<PathBuf> {
    let rest = &line[line.find(PTY_ANNOUNCEMENT)? + PTY_ANNOUNCEMENT.len()..];
    let path = rest.split_whitespace().next()?;
    path.starts_with('/').then(|| PathBuf::from(path))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_the_pty_announcement() {
        assert_eq!(
            parse_pty_announcement("char device redirected to /dev/pts/7 (label serial0)\n"),
            Some(PathBuf::from("/dev/pts/7"))
        );
        assert_eq!(
            parse_pty_announcement("qemu: char device redirected to /dev/pts/12 (label s)"),
            Some(PathBuf::from("/dev/pts/12"))
        );
        assert_eq!(
            parse_pty_announcement("VNC server running on ::1:5900"),
            None
        );
    }

    #[test]
    fn several_harts_turn_off_icount_sleep() {
        let one = QemuConfig::new("fw.elf").args();
        let four = QemuConfig::new("fw.elf").harts(4).args();
        let text = |a: &[OsString]| {
            a.iter()
                .map(|s| s.to_string_lossy())
                .collect::<Vec<_>>()
                .join(" ")
        };
        assert!(text(&one).contains("-smp 1 -icount shift=0 -kernel fw.elf"));
        assert!(text(&four).contains("-smp 4 -icount shift=0,sleep=off"));
        assert!(text(&one).contains("-bios none") && text(&one).contains("-serial pty"));
        let many = QemuConfig::new("fw.elf").harts(200).args();
        assert!(text(&many).contains("-smp 8 "));
        assert!(text(&QemuConfig::new("fw.elf").harts(0).args()).contains("-smp 1 "));
    }

    #[test]
    fn a_missing_elf_says_how_to_build_it() {
        let config = QemuConfig::new("/nonexistent/deform-firmware");
        let err = Qemu::start(&config).err().expect("must fail");
        assert!(err.to_string().contains("cargo xtask firmware"), "{err}");
    }

    #[test]
    fn a_missing_qemu_says_how_to_install_it() {
        let mut config = QemuConfig::new(env!("CARGO_MANIFEST_DIR").to_string() + "/Cargo.toml");
        config.qemu = "qemu-system-riscv32-that-does-not-exist".into();
        let err = Qemu::start(&config).err().expect("must fail");
        let text = err.to_string();
        assert!(
            text.contains("cargo xtask setup") && text.contains("qemu-system-misc"),
            "{text}"
        );
        // Never advise `apt-get install qemu-system-misc`: it may remove a newer qemu-utils.
        assert!(!text.contains("apt-get install"), "{text}");
    }

    /// A PATH without QEMU falls back to the copy `cargo xtask setup` unpacked in the workspace;
    /// one on PATH wins; with neither, the bare name (so that starting it says it is missing).
    #[test]
    fn qemu_is_found_on_path_else_unpacked_in_the_workspace() {
        use std::os::unix::fs::PermissionsExt;
        let dir = std::env::temp_dir().join(format!("deform-find-qemu-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let root = dir.join("workspace");
        let bin = dir.join("bin");
        let executable = |path: &Path| {
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            std::fs::write(path, "#!/bin/sh\n").unwrap();
            std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o755)).unwrap();
        };
        std::fs::create_dir_all(&bin).unwrap();
        let path = std::env::join_paths([&bin]).unwrap();
        assert_eq!(
            find_qemu(Some(&path), &root),
            PathBuf::from(QEMU_BINARY),
            "nothing anywhere"
        );
        let unpacked = root.join(QEMU_UNPACK_DIR).join(QEMU_UNPACKED_BINARY);
        executable(&unpacked);
        assert_eq!(find_qemu(Some(&path), &root), unpacked);
        assert_eq!(find_qemu(None, &root), unpacked);
        executable(&bin.join(QEMU_BINARY));
        assert_eq!(find_qemu(Some(&path), &root), bin.join(QEMU_BINARY));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Needs QEMU (`cargo xtask setup`): an empty kernel image makes it exit at once.
    #[test]
    fn a_qemu_exit_is_seen_with_its_stderr() {
        let empty =
            std::env::temp_dir().join(format!("deform-empty-kernel-{}", std::process::id()));
        std::fs::write(&empty, b"").unwrap();
        let started = Qemu::start(&QemuConfig::new(&empty));
        let stderr = match started {
            // QEMU may announce the pty before it tries the kernel.
            Ok(mut qemu) => {
                assert_eq!(qemu.wait_exit(Duration::from_secs(10)).unwrap(), Some(1));
                assert_eq!(qemu.try_exit_code().unwrap(), Some(1));
                qemu.stderr()
            }
            Err(HilError::ExitedEarly { stderr, .. }) => stderr,
            Err(other) => panic!("unexpected error: {other}"),
        };
        std::fs::remove_file(&empty).unwrap();
        assert!(stderr.contains("could not load kernel"), "{stderr:?}");
    }

    #[test]
    fn the_default_firmware_path_is_inside_the_firmware_workspace() {
        let elf = default_firmware_elf();
        assert!(
            elf.ends_with("firmware/target/riscv32imac-unknown-none-elf/release/deform-firmware")
        );
        assert!(elf.is_absolute());
        assert!(elf
            .parent()
            .unwrap()
            .ancestors()
            .any(|dir| dir.join("Cargo.lock").is_file()));
    }
}
