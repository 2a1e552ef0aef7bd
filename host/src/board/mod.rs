//! Which target the host talks to: a QEMU soft core it boots itself, a LiteX VexRiscv SoC
//! simulated by Verilator (cycle-accurate RTL, [`deform_hil_sim::litex`]), or a real board on a
//! serial port. All end in the same [`Target`] over the same serial code path; QEMU or the
//! simulator only add processes that live as long as the session (killed when the [`Board`] is
//! dropped).
//!
//! Every board's firmware logs ([`crate::firmware_logs`]) are decoded and printed as they arrive:
//! the link hands each `Log` notice to the board's [`FirmwareLogs`], and the firmware's build id
//! is checked against the ELF that decodes them. Every command that talks to a target opens
//! its board here, so none drops the logs. The bytes a board moved are the link's own count
//! ([`Board::wire`]): what the benchmark and the live reports quote.
//!
//! [`flags`] is the command line's side: `--target`, `--port`, `--firmware`, `--mvus` and the
//! log flags, and the one method that turns them into a [`BoardChoice`].

pub mod flags;

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use anyhow::Context;
use deform_hil_sim::litex::{litex_firmware_elf, LitexConfig, LitexSim, MAX_MVUS};
use deform_hil_sim::{firmware_elf, loader_elf, Qemu, QemuConfig};

use crate::firmware_logs::{FirmwareElf, FirmwareLogs};
use crate::flash::sfl::{SflClient, SflReport, SflTimeouts};
use crate::flash::{
    check_build_id, flash, FlashError, FlashImage, FlashProgress, FlashReport, LoaderLink,
    LoaderTimeouts,
};
use crate::link::{open_serial, Link, LinkStats, Target, Timeouts};
pub use flags::{BoardFlags, LogFlags, LogOptions, TargetFlags, TargetKind};

/// SoC clocks per received byte when deform's own SFL client flashes the simulated BIOS SoC
/// (see [`Board::flash_litex_bios`]): 115,200 baud at the SoC's nominal 1 MHz.
const SIMULATED_BIOS_UART_PACE: u32 = 87;

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
    /// Load this firmware ELF (`None`: the `litex-vexriscv` build) into the main RAM of the
    /// simulated LiteX VexRiscv SoC and run it there (one hart; real cycles), on the SoC with
    /// `mvus` hardware MVUs (0: none, the MVU phase in software).
    Litex { firmware: Option<PathBuf>, mvus: u8 },
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

/// Where a stock LiteX BIOS waits for a serial boot, for [`Board::flash_litex_bios`].
#[derive(Debug, Clone)]
pub enum BiosChoice {
    /// The simulated LiteX SoC with its ROM and BIOS, started here.
    Simulated,
    /// A LiteX board on this serial device.
    Port(String),
}

/// A connected target, with the QEMU process behind it when there is one.
pub struct Board {
    pub target: Target,
    logs: Arc<Mutex<FirmwareLogs>>,
    /// Declared after `target` so that the port closes before QEMU is killed.
    qemu: Option<Qemu>,
    /// The simulated LiteX SoC, when that is the board (also after `target`).
    litex: Option<LitexSim>,
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
            BoardChoice::Litex { firmware, mvus } => {
                if *mvus > MAX_MVUS {
                    anyhow::bail!(
                        "--mvus {mvus}: the simulated LiteX SoC has at most {MAX_MVUS} hardware MVUs"
                    );
                }
                let elf = firmware.clone().unwrap_or_else(litex_firmware_elf);
                let firmware_logs = firmware_logs(Some(logs.elf.as_deref().unwrap_or(&elf)), logs)?;
                let sim = LitexSim::start(&LitexConfig::new(&elf).with_mvus(*mvus))
                    .context("starting the simulated LiteX SoC")?;
                let path = sim.serial_path().to_string_lossy().into_owned();
                let link = Link::new(open_serial(&path)?);
                let target =
                    connect(link, litex_timeouts(timeouts), &firmware_logs).with_context(|| {
                        format!(
                            "connecting to the firmware {} on the LiteX SoC on {path}",
                            elf.display()
                        )
                    })?;
                let mut board = Board::new(target, firmware_logs, None, false)?;
                board.litex = Some(sim);
                Ok(board)
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

    /// Boots the firmware `elf` through a stock LiteX BIOS's serial boot (SFL, see
    /// [`crate::flash::sfl`]), then shakes hands with the started firmware and checks it is the
    /// image sent.
    pub fn flash_litex_bios(
        choice: &BiosChoice,
        elf: &Path,
        timeouts: Timeouts,
        sfl_timeouts: SflTimeouts,
        logs: &LogOptions,
        progress: impl FnMut(usize),
    ) -> anyhow::Result<(Board, SflReport)> {
        let image = FlashImage::from_file(elf)?;
        let firmware_logs = firmware_logs(Some(logs.elf.as_deref().unwrap_or(elf)), logs)?;
        let (sim, path) = match choice {
            BiosChoice::Simulated => {
                // deform's own SFL client keeps one 68-byte frame in flight, so the BIOS's
                // 128-byte receive ring cannot overflow: the SoC may hand it bytes faster than
                // the BIOS shape's default pace, which is set for stock litex_term's 128 frames
                // in flight (hil-sim/litex/deform_soc.py). Measured at 87 clocks a byte
                // (115,200 baud at the nominal 1 MHz): 3,819 frames, none resent.
                let config = LitexConfig::bios().with_uart_pace(SIMULATED_BIOS_UART_PACE);
                let sim = LitexSim::start(&config)
                    .context("starting the simulated LiteX SoC with its BIOS")?;
                let path = sim.serial_path().to_string_lossy().into_owned();
                (Some(sim), path)
            }
            BiosChoice::Port(path) => (None, path.clone()),
        };
        let flashed = || -> anyhow::Result<(Target, SflReport)> {
            let mut port = open_serial(&path)?;
            let mut client = SflClient::new(&mut port, sfl_timeouts);
            client.handshake()?;
            let report = client.boot(&image, progress)?;
            let target = connect(Link::new(port), litex_timeouts(timeouts), &firmware_logs)
                .map_err(FlashError::Application)?;
            check_build_id(&image, &target.info().build_id)?;
            Ok((target, report))
        };
        let (target, report) = flashed().with_context(|| {
            format!("booting {} through the LiteX BIOS on {path}", elf.display())
        })?;
        let mut board = Board::new(target, firmware_logs, None, true)?;
        board.litex = sim;
        Ok((board, report))
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
            litex: None,
            via_loader,
        })
    }

    /// Bytes this board's link has moved so far for its messages, both ways (see
    /// [`WireBytes`]): readings apart give a message's or a step's cost on the line.
    pub fn wire(&self) -> WireBytes {
        WireBytes::of(&self.target.stats())
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
            None => match &self.litex {
                Some(sim) if self.via_loader => format!(
                    "LiteX VexRiscv SoC under Verilator, booted by its BIOS (SFL), serial {}",
                    sim.serial_path().display()
                ),
                Some(sim) => format!(
                    "LiteX VexRiscv SoC under Verilator, serial {}",
                    sim.serial_path().display()
                ),
                None => "serial board".to_string(),
            },
        }
    }
}

/// Bytes a board's line carried for the messages, framing included: every frame's first copy
/// each way. Retransmissions, the repeats they draw (duplicate replies and acknowledgements),
/// NAKs, noise and corrupt frames are left out, so that a message's or a frame's cost is a
/// property of the protocol and not of how loaded the host was or how noisy the line;
/// [`LinkStats`] counts them.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct WireBytes {
    /// Host → target.
    pub sent: u64,
    /// Target → host.
    pub received: u64,
}

impl WireBytes {
    /// The byte counts in a link's statistics.
    pub fn of(stats: &LinkStats) -> WireBytes {
        WireBytes {
            sent: stats.bytes_sent - stats.bytes_resent,
            received: stats.bytes_received_clean,
        }
    }

    pub fn total(&self) -> u64 {
        self.sent + self.received
    }

    /// `self − earlier`.
    pub fn since(&self, earlier: WireBytes) -> WireBytes {
        WireBytes {
            sent: self.sent - earlier.sent,
            received: self.received - earlier.received,
        }
    }
}

/// Deadlines for long sessions (`deform bench`, `deform live`): `solve` per solve, and a
/// handshake long enough for QEMU on a busy machine (QEMU notices the pty only once a second,
/// and CI shares its cores).
pub fn session_timeouts(solve: std::time::Duration) -> Timeouts {
    Timeouts {
        handshake: std::time::Duration::from_secs(30),
        solve,
        ..Timeouts::default()
    }
}

/// The simulated SoC runs about 0.8 M cycles per second and boots in about one: the handshake
/// gets at least a minute.
pub fn litex_timeouts(timeouts: Timeouts) -> Timeouts {
    Timeouts {
        handshake: timeouts.handshake.max(std::time::Duration::from_secs(60)),
        ..timeouts
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
