//! The figures every live report computes the same way: percentiles over the frames, frame
//! rates at the thesis's 100 MHz, and what the serial line allows at the usual baud rates.

use serde::Serialize;

// The target clock the per-second figures are quoted at (the thesis's 100 MHz).
use crate::metrics::NOMINAL_CLOCK_HZ as CLOCK_HZ;

#[derive(Debug, Clone, Copy, Serialize)]
pub struct Spread {
    pub p50: f64,
    pub p99: f64,
    pub max: f64,
}

#[derive(Debug, Clone, Copy, Serialize)]
pub struct Rate {
    pub p50: f64,
    pub worst: f64,
}

#[derive(Debug, Clone, Copy, Serialize)]
pub struct IterationSpread {
    pub p50: f64,
    pub max: f64,
}

pub(crate) fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[i]
}

pub(crate) fn sorted(v: impl Iterator<Item = f64>) -> Vec<f64> {
    let mut v: Vec<f64> = v.collect();
    v.sort_by(f64::total_cmp);
    v
}

impl Spread {
    /// p50, p99 and max of `sorted`.
    pub(crate) fn of(sorted: &[f64]) -> Spread {
        Spread {
            p50: percentile(sorted, 0.5),
            p99: percentile(sorted, 0.99),
            max: sorted.last().copied().unwrap_or(0.0),
        }
    }
}

impl Rate {
    /// Frames per second at [`CLOCK_HZ`] for the median and the largest of `sorted` cycles.
    pub(crate) fn of(sorted: &[f64]) -> Rate {
        Rate {
            p50: CLOCK_HZ / percentile(sorted, 0.5).max(1.0),
            worst: CLOCK_HZ / sorted.last().copied().unwrap_or(0.0).max(1.0),
        }
    }
}

impl IterationSpread {
    pub(crate) fn of(sorted: &[f64]) -> IterationSpread {
        IterationSpread {
            p50: percentile(sorted, 0.5),
            max: sorted.last().copied().unwrap_or(0.0),
        }
    }
}

/// The baud rates the reports state the line's own frame rate for.
pub(crate) const BAUDS: [u32; 3] = [115_200, 921_600, 3_000_000];

/// How many messages of `bytes` the line carries per second at `baud` (8N1: 10 bits per
/// byte), 0 for none.
pub(crate) fn per_second(baud: u32, bytes: f64) -> f64 {
    if bytes > 0.0 {
        f64::from(baud) / 10.0 / bytes
    } else {
        0.0
    }
}
