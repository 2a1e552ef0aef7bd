//! Which target the host talks to: a QEMU soft core it boots itself, or a real board on a serial
//! port. Both end in the same [`Target`] over the same serial code path; QEMU only adds a process
//! that lives as long as the session (and is killed when the [`Board`] is dropped).

use std::path::PathBuf;

use anyhow::Context;
use deform_hil_sim::{firmware_elf, Qemu, QemuConfig};

use crate::link::{Target, Timeouts};

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
    /// A board already running the firmware, on this serial device.
    Port(String),
}

/// A connected target, with the QEMU process behind it when there is one.
pub struct Board {
    pub target: Target,
    /// Declared after `target` so that the port closes before QEMU is killed.
    qemu: Option<Qemu>,
}

impl Board {
    pub fn open(choice: &BoardChoice, timeouts: Timeouts) -> anyhow::Result<Board> {
        match choice {
            BoardChoice::Port(path) => {
                let target = Target::connect(path, timeouts)
                    .with_context(|| format!("connecting to the board on {path}"))?;
                Ok(Board { target, qemu: None })
            }
            BoardChoice::Qemu { firmware, harts } => {
                let elf = firmware.clone().unwrap_or_else(firmware_elf);
                let qemu =
                    Qemu::start(&QemuConfig::new(&elf).harts(*harts)).context("starting QEMU")?;
                let pty = qemu.pty_path().to_string_lossy().into_owned();
                let target = Target::connect(&pty, timeouts).with_context(|| {
                    format!(
                        "connecting to the firmware {} in QEMU on {pty}",
                        elf.display()
                    )
                })?;
                Ok(Board {
                    target,
                    qemu: Some(qemu),
                })
            }
        }
    }

    /// A short description for summaries: "QEMU (pty /dev/pts/3)" or the port.
    pub fn describe(&self) -> String {
        match &self.qemu {
            Some(q) => format!("QEMU riscv32 virt, pty {}", q.pty_path().display()),
            None => "serial board".to_string(),
        }
    }
}
