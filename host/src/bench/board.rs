//! The benchmark's target: the firmware in QEMU (or a real board), reached through a port that
//! counts the bytes it moves, so that wire traffic is measured rather than estimated.
//!
//! [`crate::board::Board`] serves `solve`/`simulate`; the bench needs two things it does not
//! have: a chosen number of harts (`-smp`, one per MVU) and byte counters on the line. The
//! counters wrap the port ([`Port`] is generic precisely so that the link works over any byte
//! stream), which leaves the link and protocol code untouched.

use std::io::{self, Read, Write};
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use deform_hil_sim::litex::{litex_firmware_elf, LitexConfig, LitexSim};
use deform_hil_sim::{firmware_elf, Qemu, QemuConfig};
use serialport::SerialPort;

use crate::link::{open_serial, Link, Port, Target, Timeouts};

/// Bytes moved by a [`CountingPort`], readable while the port is owned by a [`Target`].
#[derive(Debug, Clone, Default)]
pub struct WireCounter {
    sent: Arc<AtomicU64>,
    received: Arc<AtomicU64>,
}

/// Bytes moved between two readings of a [`WireCounter`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct WireBytes {
    /// Host → target.
    pub sent: u64,
    /// Target → host.
    pub received: u64,
}

impl WireBytes {
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

impl WireCounter {
    pub fn read(&self) -> WireBytes {
        WireBytes {
            sent: self.sent.load(Ordering::Relaxed),
            received: self.received.load(Ordering::Relaxed),
        }
    }
}

/// A [`Port`] that counts every byte written and read.
pub struct CountingPort<P> {
    inner: P,
    counter: WireCounter,
}

impl<P: Port> CountingPort<P> {
    pub fn new(inner: P) -> (Self, WireCounter) {
        let counter = WireCounter::default();
        (
            CountingPort {
                inner,
                counter: counter.clone(),
            },
            counter,
        )
    }
}

impl<P: Port> Read for CountingPort<P> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.counter.received.fetch_add(n as u64, Ordering::Relaxed);
        Ok(n)
    }
}

impl<P: Port> Write for CountingPort<P> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.counter.sent.fetch_add(n as u64, Ordering::Relaxed);
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }
}

impl<P: Port> Port for CountingPort<P> {
    fn set_timeout(&mut self, timeout: Duration) -> io::Result<()> {
        self.inner.set_timeout(timeout)
    }
}

/// The bench's deadlines: `solve` per solve, and a handshake long enough for QEMU on a busy
/// machine (QEMU notices the pty only once a second, and CI shares its cores).
pub fn timeouts(solve: Duration) -> Timeouts {
    Timeouts {
        handshake: Duration::from_secs(30),
        solve,
        ..Timeouts::default()
    }
}

/// The bench's target type.
pub type BenchTarget = Target<CountingPort<Box<dyn SerialPort>>>;

/// Where the bench runs its target parts.
#[derive(Debug, Clone)]
pub enum BenchBoardChoice {
    /// Boot this firmware (`None`: the default build) in QEMU with as many harts as asked.
    Qemu { firmware: Option<PathBuf> },
    /// Load this firmware (`None`: the `litex-vexriscv` build) into the simulated LiteX SoC.
    Litex { firmware: Option<PathBuf> },
    /// A board already running the firmware; its hart count is what it reports.
    Port(String),
}

/// A connected bench target and, for QEMU, the process behind it.
pub struct BenchBoard {
    pub target: BenchTarget,
    pub wire: WireCounter,
    /// Declared after `target` so that the port closes before QEMU is killed.
    _qemu: Option<Qemu>,
    _litex: Option<LitexSim>,
}

impl BenchBoard {
    /// Connects to the board, booting QEMU with `harts` harts if that is the choice.
    pub fn open(
        choice: &BenchBoardChoice,
        harts: u8,
        timeouts: Timeouts,
    ) -> anyhow::Result<BenchBoard> {
        let (mut qemu, mut litex) = (None, None);
        let mut timeouts = timeouts;
        let path = match choice {
            BenchBoardChoice::Port(path) => path.clone(),
            BenchBoardChoice::Qemu { firmware } => {
                let elf = firmware.clone().unwrap_or_else(firmware_elf);
                let started = Qemu::start(&QemuConfig::new(&elf).harts(harts))
                    .with_context(|| format!("starting QEMU with {harts} hart(s)"))?;
                let pty = started.pty_path().to_string_lossy().into_owned();
                qemu = Some(started);
                pty
            }
            BenchBoardChoice::Litex { firmware } => {
                let elf = firmware.clone().unwrap_or_else(litex_firmware_elf);
                let started = LitexSim::start(&LitexConfig::new(&elf))
                    .context("starting the simulated LiteX SoC")?;
                let path = started.serial_path().to_string_lossy().into_owned();
                litex = Some(started);
                timeouts = crate::board::litex_timeouts(timeouts);
                path
            }
        };
        let (port, wire) = CountingPort::new(open_serial(&path)?);
        let target = Target::handshake(Link::new(port), timeouts)
            .with_context(|| format!("connecting to the firmware on {path}"))?;
        Ok(BenchBoard {
            target,
            wire,
            _qemu: qemu,
            _litex: litex,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::net::UnixStream;

    #[test]
    fn counts_both_directions() {
        let (a, mut b) = UnixStream::pair().unwrap();
        let (mut port, counter) = CountingPort::new(a);
        port.write_all(b"hello").unwrap();
        b.write_all(b"abc").unwrap();
        let mut buf = [0u8; 8];
        let mut got = 0;
        while got < 3 {
            got += port.read(&mut buf[got..]).unwrap();
        }
        let now = counter.read();
        assert_eq!(
            now,
            WireBytes {
                sent: 5,
                received: 3
            }
        );
        assert_eq!(now.total(), 8);
        assert_eq!(
            now.since(WireBytes {
                sent: 1,
                received: 1
            })
            .total(),
            6
        );
    }
}
