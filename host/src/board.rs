//! Which target the host talks to: a QEMU soft core it boots itself, or a real board on a serial
//! port. Both end in the same [`Target`] over the same serial code path; QEMU only adds a process
//! that lives as long as the session (and is killed when the [`Board`] is dropped).
//!
//! Every board's firmware logs ([`crate::firmware_logs`]) are decoded and printed as they arrive:
//! the link hands each `Log` notice to the board's [`FirmwareLogs`].

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use anyhow::Context;
use deform_hil_sim::{firmware_elf, loader_elf, Qemu, QemuConfig};

use crate::cli_logs::LogOptions;
use crate::firmware_logs::{FirmwareElf, FirmwareLogs};
use crate::flash::{
    check_build_id, flash, FlashError, FlashImage, FlashProgress, FlashReport, LoaderLink,
    LoaderTimeouts,
};
use crate::link::{open_serial, Link, Target, Timeouts};

/// Harts a QEMU board gets when `--mvus` does not say: the most a target may have
/// ([`deform_shared::protocol::MAX_HARTS`]), so that by default every MVU is used.
pub const DEFAULT_QEMU_HARTS: u8 = deform_shared::protocol::MAX_HARTS as u8;

/// Where to run.
#[derive(Debug, Clone)]
pub enum BoardChoice {
    /// Boot this firmware ELF in QEMU (`None`: the default build location) with `harts` harts
    /// (`-smp`), each of which the firmware can use as an MVU.
    Qemu {
        firmware: Option<PathBuf>,
        harts: u8,
    },
    /// Boot the serial loader in QEMU and flash this firmware ELF through it (`deform flash`'s
    /// path), then use the started firmware like a directly booted one.
    QemuViaLoader {
        firmware: Option<PathBuf>,
        harts: u8,
    },
    /// A board already running the firmware, on this serial device.
    Port(String),
}

/// Where the serial loader runs, for [`Board::flash`].
#[derive(Debug, Clone)]
pub enum LoaderChoice {
    /// Boot QEMU with the loader ([`loader_elf`]) and `harts` harts, which the loader hands to
    /// the application.
    Qemu { harts: u8 },
    /// A board whose loader waits on this serial device.
    Port(String),
}

/// A connected target, with the QEMU process behind it when there is one.
pub struct Board {
    pub target: Target,
    logs: Arc<Mutex<FirmwareLogs>>,
    /// Declared after `target` so that the port closes before QEMU is killed.
    qemu: Option<Qemu>,
    via_loader: bool,
}

impl Board {
    pub fn open(
        choice: &BoardChoice,
        timeouts: Timeouts,
        logs: &LogOptions,
    ) -> anyhow::Result<Board> {
        match choice {
            BoardChoice::Port(path) => {
                let elf = logs.elf.as_deref();
                let firmware_logs = firmware_logs(elf, logs)?;
                let link = Link::new(open_serial(path)?);
                let target = connect(link, timeouts, &firmware_logs)
                    .with_context(|| format!("connecting to the board on {path}"))?;
                Board::new(target, firmware_logs, None, false)
            }
            BoardChoice::Qemu { firmware, harts } => {
                let elf = firmware.clone().unwrap_or_else(firmware_elf);
                let firmware_logs = firmware_logs(Some(logs.elf.as_deref().unwrap_or(&elf)), logs)?;
                let qemu =
                    Qemu::start(&QemuConfig::new(&elf).harts(*harts)).context("starting QEMU")?;
                let pty = qemu.pty_path().to_string_lossy().into_owned();
                let link = Link::new(open_serial(&pty)?);
                let target = connect(link, timeouts, &firmware_logs).with_context(|| {
                    format!(
                        "connecting to the firmware {} in QEMU on {pty}",
                        elf.display()
                    )
                })?;
                Board::new(target, firmware_logs, Some(qemu), false)
            }
            BoardChoice::QemuViaLoader { firmware, harts } => {
                let elf = firmware.clone().unwrap_or_else(firmware_elf);
                let (board, _) = Board::flash(
                    &LoaderChoice::Qemu { harts: *harts },
                    &elf,
                    timeouts,
                    LoaderTimeouts::default(),
                    logs,
                    |_| {},
                )?;
                Ok(board)
            }
        }
    }

    /// Flashes the firmware `elf` through the serial loader (on a port, or in a QEMU booted
    /// here), then shakes hands with the started firmware and checks it is the image sent.
    pub fn flash(
        choice: &LoaderChoice,
        elf: &Path,
        timeouts: Timeouts,
        loader_timeouts: LoaderTimeouts,
        logs: &LogOptions,
        progress: impl FnMut(FlashProgress),
    ) -> anyhow::Result<(Board, FlashReport)> {
        let image = FlashImage::from_file(elf)?;
        let firmware_logs = firmware_logs(Some(logs.elf.as_deref().unwrap_or(elf)), logs)?;
        let (qemu, path) = match choice {
            LoaderChoice::Qemu { harts } => {
                let qemu = Qemu::start(&QemuConfig::new(loader_elf()).harts(*harts))
                    .context("starting QEMU with the serial loader")?;
                let pty = qemu.pty_path().to_string_lossy().into_owned();
                (Some(qemu), pty)
            }
            LoaderChoice::Port(path) => (None, path.clone()),
        };
        let flashed = || -> anyhow::Result<(Target, FlashReport)> {
            let mut loader = LoaderLink::new(open_serial(&path)?, loader_timeouts);
            let report = flash(&mut loader, &image, progress)?;
            let link = Link::new(loader.into_port());
            let target =
                connect(link, timeouts, &firmware_logs).map_err(FlashError::Application)?;
            check_build_id(&image, &target.info().build_id)?;
            Ok((target, report))
        };
        let (target, report) = flashed()
            .with_context(|| format!("flashing {} through the loader on {path}", elf.display()))?;
        let via_loader = qemu.is_some();
        Ok((Board::new(target, firmware_logs, qemu, via_loader)?, report))
    }

    fn new(
        target: Target,
        logs: Arc<Mutex<FirmwareLogs>>,
        qemu: Option<Qemu>,
        via_loader: bool,
    ) -> anyhow::Result<Board> {
        lock(&logs)
            .accept(&target.info().build_id)
            .context("checking the firmware ELF for the target's logs")?;
        Ok(Board {
            target,
            logs,
            qemu,
            via_loader,
        })
    }

    /// The decoder of this board's logs: to suspend a progress bar while they print, or for
    /// their counts.
    pub fn logs(&self) -> &Arc<Mutex<FirmwareLogs>> {
        &self.logs
    }

    /// A short description for summaries: "QEMU (pty /dev/pts/3)" or the port.
    pub fn describe(&self) -> String {
        match &self.qemu {
            Some(q) if self.via_loader => format!(
                "QEMU riscv32 virt, flashed through the serial loader, pty {}",
                q.pty_path().display()
            ),
            Some(q) => format!("QEMU riscv32 virt, pty {}", q.pty_path().display()),
            None => "serial board".to_string(),
        }
    }
}

fn firmware_logs(
    elf: Option<&Path>,
    options: &LogOptions,
) -> anyhow::Result<Arc<Mutex<FirmwareLogs>>> {
    let elf = elf
        .map(FirmwareElf::load)
        .transpose()
        .context("loading the firmware ELF for its logs")?;
    Ok(FirmwareLogs::printing(elf, options.min_level).shared())
}

/// Shakes hands with the firmware's logs already going to `logs` (its boot log arrives just
/// before the `Hello` answer).
fn connect(
    mut link: Link,
    timeouts: Timeouts,
    logs: &Arc<Mutex<FirmwareLogs>>,
) -> Result<Target, crate::link::LinkError> {
    let logs = Arc::clone(logs);
    link.set_notice_handler(Box::new(move |seq, body| lock(&logs).notice(seq, &body)));
    Target::handshake(link, timeouts)
}

/// The logs, even if a printing thread panicked while holding them.
pub fn lock(logs: &Mutex<FirmwareLogs>) -> std::sync::MutexGuard<'_, FirmwareLogs> {
    logs.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}
