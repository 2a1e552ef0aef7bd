//! What the machine has, and what a command will take of it: a model's and a long run's memory
//! are checked against it before they are allocated, so that too much is refused with both
//! figures instead of ending in an allocation abort (exit 134, any QEMU it had started left
//! behind).
//!
//! A model's figure ([`model_estimate`]) is the measured peak of `deform model` (the largest of
//! the commands: it also encodes K and analyses it) as bytes per node plus bytes per nonzero,
//! fitted on 64³ models A and B (130 MB and 366 MB peak resident), with a margin: the grid may
//! have up to 2²⁴ nodes, but a 256³ model B needs about 24 GB.

use crate::model::{Connection, Grid};

/// Bytes per node of the measured peak (the vectors, per-node tables, the tool-free analysis).
const BYTES_PER_NODE: f64 = 182.0;
/// Bytes per nonzero of K (triplets while assembling, CSR, the encoded words and their copies).
const BYTES_PER_NONZERO: f64 = 45.0;
/// The process itself (binary, allocator, the firmware ELF's tables).
const BASE_BYTES: f64 = 8e6;
/// Head-room over the fitted peak.
const MARGIN: f64 = 1.25;

/// What building a model would take.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MemoryEstimate {
    pub nodes: u64,
    /// Nonzeros of K: one per node and two per spring.
    pub nonzeros: u64,
    pub bytes: u64,
}

/// The estimate for a `grid` with `connection` springs (exact counts, no allocation).
pub fn model_estimate(grid: Grid, connection: Connection) -> MemoryEstimate {
    let dims = [grid.nx(), grid.ny(), grid.nz()].map(|d| d as u64);
    let nodes = dims.iter().product::<u64>();
    // Each spring joins a node to the one at +offset; half the offsets cover every spring once.
    let springs: u64 = connection
        .offsets()
        .filter(|&o| o > (0, 0, 0))
        .map(|(di, dj, dk)| {
            [di, dj, dk]
                .iter()
                .zip(dims)
                .map(|(&d, n)| n.saturating_sub(d.unsigned_abs() as u64))
                .product::<u64>()
        })
        .sum();
    let nonzeros = nodes + 2 * springs;
    let bytes =
        MARGIN * (BASE_BYTES + BYTES_PER_NODE * nodes as f64 + BYTES_PER_NONZERO * nonzeros as f64);
    MemoryEstimate {
        nodes,
        nonzeros,
        bytes: bytes as u64,
    }
}

/// The memory this process may still take, in bytes: the kernel's `MemAvailable`, or less where
/// a cgroup (a container's limit) or the process's address-space limit (`ulimit -v`) allows
/// less. `None` where none can be read (not Linux): then nothing is refused.
///
/// Read from `/proc` and `/sys` by hand: three numbers in three text files do not justify a
/// system-information crate.
pub fn available() -> Option<u64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok();
    let available = meminfo.as_deref().and_then(|text| {
        text.lines()
            .find_map(|l| l.strip_prefix("MemAvailable:"))
            .and_then(|v| v.trim().strip_suffix("kB"))
            .and_then(|v| v.trim().parse::<u64>().ok())
            .map(|kb| kb * 1024)
    });
    let read =
        |path: &str| -> Option<u64> { std::fs::read_to_string(path).ok()?.trim().parse().ok() };
    let cgroup = read("/sys/fs/cgroup/memory.max")
        .map(|max| max.saturating_sub(read("/sys/fs/cgroup/memory.current").unwrap_or(0)));
    [available, cgroup, address_space_limit()]
        .into_iter()
        .flatten()
        .min()
}

/// The soft `RLIMIT_AS` from `/proc/self/limits` (`Max address space  SOFT  HARD  bytes`), if
/// it is not `unlimited`.
fn address_space_limit() -> Option<u64> {
    let limits = std::fs::read_to_string("/proc/self/limits").ok()?;
    let line = limits
        .lines()
        .find(|l| l.starts_with("Max address space"))?;
    line["Max address space".len()..]
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

/// `bytes` for people: "34.4 GB".
pub fn human(bytes: u64) -> String {
    let units = ["B", "kB", "MB", "GB", "TB", "PB", "EB"];
    let mut value = bytes as f64;
    let mut unit = 0;
    while value >= 1000.0 && unit + 1 < units.len() {
        value /= 1000.0;
        unit += 1;
    }
    if unit == 0 {
        format!("{bytes} B")
    } else {
        format!("{value:.1} {}", units[unit])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn figures_read_as_people_write_them() {
        assert_eq!(human(512), "512 B");
        assert_eq!(human(34_359_738_368), "34.4 GB");
        assert!(available().is_some_and(|b| b > 0));
    }

    #[test]
    fn nonzeros_are_counted_exactly() {
        // 3×3×3 model A: 27 nodes, 54 springs (3 directions × 2 × 3 × 3).
        let a = model_estimate(Grid::new(3, 3, 3).unwrap(), Connection::Axial);
        assert_eq!((a.nodes, a.nonzeros), (27, 27 + 2 * 54));
        // 2×2×2 model B: every pair of the 8 corners is a spring (28).
        let b = model_estimate(Grid::new(2, 2, 2).unwrap(), Connection::AxialShear);
        assert_eq!(b.nonzeros, 8 + 2 * 28);
        // The advertised limit, 2²⁴ nodes of model B: ~453 M nonzeros, tens of GB.
        let big = model_estimate(Grid::new(256, 256, 256).unwrap(), Connection::AxialShear);
        assert_eq!(big.nodes, 1 << 24);
        assert!(
            big.nonzeros > 440_000_000 && big.bytes > 20_000_000_000,
            "{big:?}"
        );
    }
}
