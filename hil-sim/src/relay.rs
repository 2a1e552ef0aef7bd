//! A fault-injecting relay between the host and QEMU's serial pty: a bad cable on demand.
//!
//! [`FaultRelay::start`] opens QEMU's pty and a second pseudo-terminal pair of its own; the host
//! opens the new pair's slave ([`FaultRelay::pty_path`]) exactly as it would a board's serial
//! port, and the relay copies bytes between the two, damaging them on the way as its
//! [`FaultConfig`] says: bit flips, dropped, duplicated and inserted bytes at set rates, stalls,
//! and a cut (the line goes dead) after a set number of bytes or whenever the test says. All
//! randomness comes from the config's seed, so a run's faults depend only on the bytes that
//! pass (the timing of the two directions may still interleave differently).
//!
//! Written here rather than taken from a crate because nothing on crates.io injects faults into
//! a pty stream; the pty and termios calls come from `nix`.

use std::fs::{File, OpenOptions};
use std::io::{Read, Write};
use std::os::fd::{AsRawFd, FromRawFd, RawFd};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread;
use std::time::Duration;

use nix::poll::{poll, PollFd, PollFlags};
use nix::sys::termios::{cfmakeraw, tcgetattr, tcsetattr, SetArg};

/// What the relay does to the bytes. Rates are probabilities per byte, in each direction.
#[derive(Debug, Clone, PartialEq)]
pub struct FaultConfig {
    pub seed: u64,
    /// Flip one random bit of the byte.
    pub flip: f64,
    /// Lose the byte.
    pub drop: f64,
    /// Send the byte twice.
    pub duplicate: f64,
    /// Insert a random byte before it (which may be a frame delimiter).
    pub garbage: f64,
    /// Start a stall of [`stall_for`](Self::stall_for) before the byte.
    pub stall: f64,
    pub stall_for: Duration,
    /// Go dead (forward nothing more, either way) once this many bytes went to the target.
    pub cut_after: Option<u64>,
}

impl FaultConfig {
    /// A relay that passes every byte unharmed.
    pub fn clean() -> Self {
        FaultConfig {
            seed: 1,
            flip: 0.0,
            drop: 0.0,
            duplicate: 0.0,
            garbage: 0.0,
            stall: 0.0,
            stall_for: Duration::ZERO,
            cut_after: None,
        }
    }

    /// Byte errors at `rate` per byte in each direction, split evenly over flips, drops,
    /// duplicates and inserted garbage, plus a 20 ms stall every ~20 000 bytes.
    pub fn byte_error_rate(rate: f64, seed: u64) -> Self {
        FaultConfig {
            seed,
            flip: rate / 4.0,
            drop: rate / 4.0,
            duplicate: rate / 4.0,
            garbage: rate / 4.0,
            stall: 5e-5,
            stall_for: Duration::from_millis(20),
            cut_after: None,
        }
    }

    /// The total per-byte probability that a byte is damaged (flipped, dropped, duplicated or
    /// preceded by garbage).
    pub fn total_error_rate(&self) -> f64 {
        self.flip + self.drop + self.duplicate + self.garbage
    }
}

/// What the relay did so far.
#[derive(Debug, Default)]
pub struct RelayCounters {
    pub to_target: AtomicU64,
    pub to_host: AtomicU64,
    pub flipped: AtomicU64,
    pub dropped: AtomicU64,
    pub duplicated: AtomicU64,
    pub inserted: AtomicU64,
    pub stalls: AtomicU64,
}

impl RelayCounters {
    /// Bytes damaged in either direction.
    pub fn faults(&self) -> u64 {
        [
            &self.flipped,
            &self.dropped,
            &self.duplicated,
            &self.inserted,
        ]
        .iter()
        .map(|c| c.load(Ordering::Relaxed))
        .sum()
    }
}

/// Why the relay could not start.
#[derive(Debug, thiserror::Error)]
pub enum RelayError {
    #[error("cannot open the target's pty {}: {source}", path.display())]
    OpenTarget {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot create the relay's pty pair: {0}")]
    Pty(#[source] nix::Error),
}

/// A running relay. Dropping it stops the copying threads and closes both ptys.
pub struct FaultRelay {
    pty: PathBuf,
    counters: Arc<RelayCounters>,
    cut: Arc<AtomicBool>,
    stop: Arc<AtomicBool>,
    threads: Vec<thread::JoinHandle<()>>,
    /// Our own handle on the slave side: while it is open the master never reads EIO, whether
    /// or not the host has the slave open.
    _slave: File,
}

impl FaultRelay {
    /// Starts relaying between the host-side pty it creates and `target_pty` (QEMU's).
    pub fn start(target_pty: &Path, config: FaultConfig) -> Result<FaultRelay, RelayError> {
        let target = OpenOptions::new()
            .read(true)
            .write(true)
            .open(target_pty)
            .map_err(|source| RelayError::OpenTarget {
                path: target_pty.to_path_buf(),
                source,
            })?;
        make_raw(target.as_raw_fd()).map_err(RelayError::Pty)?;
        let pair = nix::pty::openpty(None, None).map_err(RelayError::Pty)?;
        // SAFETY: openpty just returned these descriptors; each is owned by exactly one File.
        let (master, slave) = unsafe {
            (
                File::from_raw_fd(pair.master),
                File::from_raw_fd(pair.slave),
            )
        };
        // Raw at once: a cooked slave would echo the target's bytes back into the relay.
        make_raw(slave.as_raw_fd()).map_err(RelayError::Pty)?;
        let pty = nix::unistd::ttyname(slave.as_raw_fd()).map_err(RelayError::Pty)?;

        let counters = Arc::new(RelayCounters::default());
        let cut = Arc::new(AtomicBool::new(false));
        let stop = Arc::new(AtomicBool::new(false));
        let clone = |f: &File| f.try_clone().map_err(|e| RelayError::Pty(errno_of(&e)));
        let directions = [
            (clone(&master)?, clone(&target)?, Direction::ToTarget, 1),
            (target, master, Direction::ToHost, 2),
        ];
        let threads = directions
            .into_iter()
            .map(|(from, to, direction, stream)| {
                let pump = Pump {
                    from,
                    to,
                    direction,
                    faults: Faults::new(&config, stream),
                    cut_after: config.cut_after,
                    counters: Arc::clone(&counters),
                    cut: Arc::clone(&cut),
                    stop: Arc::clone(&stop),
                };
                thread::spawn(move || pump.run())
            })
            .collect();
        Ok(FaultRelay {
            pty,
            counters,
            cut,
            stop,
            threads,
            _slave: slave,
        })
    }

    /// The pty the host opens instead of QEMU's.
    pub fn pty_path(&self) -> &Path {
        &self.pty
    }

    pub fn counters(&self) -> &RelayCounters {
        &self.counters
    }

    /// Cuts the line now: nothing more passes in either direction.
    pub fn cut(&self) {
        self.cut.store(true, Ordering::SeqCst);
    }
}

impl Drop for FaultRelay {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        for thread in self.threads.drain(..) {
            let _ = thread.join();
        }
    }
}

fn errno_of(e: &std::io::Error) -> nix::Error {
    nix::Error::from_i32(e.raw_os_error().unwrap_or(libc_eio()))
}

const fn libc_eio() -> i32 {
    5
}

fn make_raw(fd: RawFd) -> Result<(), nix::Error> {
    let mut termios = tcgetattr(fd)?;
    cfmakeraw(&mut termios);
    tcsetattr(fd, SetArg::TCSANOW, &termios)
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Direction {
    ToTarget,
    ToHost,
}

/// One direction's fault generator: xorshift64* from the seed, a stream of its own per
/// direction.
struct Faults {
    state: u64,
    config: FaultConfig,
}

impl Faults {
    fn new(config: &FaultConfig, stream: u64) -> Self {
        Faults {
            state: (config.seed ^ stream.wrapping_mul(0x9E37_79B9_7F4A_7C15)).max(1),
            config: config.clone(),
        }
    }

    fn next(&mut self) -> u64 {
        self.state ^= self.state >> 12;
        self.state ^= self.state << 25;
        self.state ^= self.state >> 27;
        self.state.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    /// A uniform number in [0, 1).
    fn uniform(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Copies one direction.
struct Pump {
    from: File,
    to: File,
    direction: Direction,
    faults: Faults,
    cut_after: Option<u64>,
    counters: Arc<RelayCounters>,
    cut: Arc<AtomicBool>,
    stop: Arc<AtomicBool>,
}

impl Pump {
    fn run(mut self) {
        let mut buf = [0u8; 4096];
        let mut out = Vec::with_capacity(2 * buf.len());
        while !self.stop.load(Ordering::SeqCst) {
            let mut fds = [PollFd::new(self.from.as_raw_fd(), PollFlags::POLLIN)];
            match poll(&mut fds, 20) {
                Ok(0) | Err(nix::Error::EINTR) => continue,
                Ok(_) => {}
                Err(_) => return,
            }
            let n = match self.from.read(&mut buf) {
                Ok(0) => return,
                Ok(n) => n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                // EIO: the other end (QEMU) is gone; keep the host's side open but silent.
                Err(_) => {
                    thread::sleep(Duration::from_millis(20));
                    continue;
                }
            };
            out.clear();
            for &byte in &buf[..n] {
                if self.cut.load(Ordering::SeqCst) {
                    break;
                }
                self.damage(byte, &mut out);
                if self.direction == Direction::ToTarget {
                    let sent = self.counters.to_target.fetch_add(1, Ordering::SeqCst) + 1;
                    if self.cut_after.is_some_and(|limit| sent >= limit) {
                        self.cut.store(true, Ordering::SeqCst);
                    }
                } else {
                    self.counters.to_host.fetch_add(1, Ordering::SeqCst);
                }
            }
            if !out.is_empty() && self.to.write_all(&out).is_err() {
                thread::sleep(Duration::from_millis(20));
            }
        }
    }

    fn damage(&mut self, byte: u8, out: &mut Vec<u8>) {
        let c = &self.counters;
        let config = &self.faults.config;
        let (stall, stall_for) = (config.stall, config.stall_for);
        if stall > 0.0 && self.faults.uniform() < stall {
            c.stalls.fetch_add(1, Ordering::Relaxed);
            // Deliver what came before, then hold the line.
            let _ = self.to.write_all(out);
            out.clear();
            thread::sleep(stall_for);
        }
        let config = &self.faults.config;
        let thresholds = [
            config.flip,
            config.flip + config.drop,
            config.flip + config.drop + config.duplicate,
            config.total_error_rate(),
        ];
        let roll = self.faults.uniform();
        if roll < thresholds[0] {
            c.flipped.fetch_add(1, Ordering::Relaxed);
            let bit = self.faults.next() % 8;
            out.push(byte ^ (1 << bit));
        } else if roll < thresholds[1] {
            c.dropped.fetch_add(1, Ordering::Relaxed);
        } else if roll < thresholds[2] {
            c.duplicated.fetch_add(1, Ordering::Relaxed);
            out.extend([byte, byte]);
        } else if roll < thresholds[3] {
            c.inserted.fetch_add(1, Ordering::Relaxed);
            out.extend([self.faults.next() as u8, byte]);
        } else {
            out.push(byte);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fault_mix_matches_the_configured_rates() {
        let config = FaultConfig::byte_error_rate(0.01, 7);
        let mut faults = Faults::new(&config, 1);
        let n = 200_000;
        let hits = (0..n)
            .filter(|_| faults.uniform() < config.total_error_rate())
            .count();
        let rate = hits as f64 / n as f64;
        assert!((0.008..0.012).contains(&rate), "{rate}");
        // The same seed gives the same faults.
        let mut a = Faults::new(&config, 1);
        let mut b = Faults::new(&config, 1);
        assert!((0..100).all(|_| a.next() == b.next()));
        let mut other = Faults::new(&config, 2);
        assert_ne!(Faults::new(&config, 1).next(), other.next());
    }

    /// A relay between two ptys of our own: what goes in comes out, damaged as configured.
    #[test]
    fn relays_bytes_between_ptys_and_damages_them_as_told() {
        let far = nix::pty::openpty(None, None).unwrap();
        // SAFETY: fresh descriptors from openpty, each owned by one File.
        let (mut far_master, far_slave) =
            unsafe { (File::from_raw_fd(far.master), File::from_raw_fd(far.slave)) };
        make_raw(far_slave.as_raw_fd()).unwrap();
        let far_path = nix::unistd::ttyname(far_slave.as_raw_fd()).unwrap();
        let relay = FaultRelay::start(&far_path, FaultConfig::clean()).unwrap();
        let mut host = OpenOptions::new()
            .read(true)
            .write(true)
            .open(relay.pty_path())
            .unwrap();
        make_raw(host.as_raw_fd()).unwrap();
        let message: Vec<u8> = (0..=255u8).cycle().take(3000).collect();
        host.write_all(&message).unwrap();
        let mut got = vec![0u8; message.len()];
        far_master.read_exact(&mut got).unwrap();
        assert_eq!(got, message);
        far_master.write_all(b"back\0").unwrap();
        let mut back = [0u8; 5];
        host.read_exact(&mut back).unwrap();
        assert_eq!(&back, b"back\0");
        assert_eq!(relay.counters().faults(), 0);
        relay.cut();
        host.write_all(b"lost").unwrap();
        thread::sleep(Duration::from_millis(100));
        let mut fds = [PollFd::new(far_master.as_raw_fd(), PollFlags::POLLIN)];
        assert_eq!(poll(&mut fds, 50).unwrap(), 0, "nothing passes a cut line");
    }
}
