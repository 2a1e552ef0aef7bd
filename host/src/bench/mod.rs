//! `deform bench`: the thesis's performance analysis (ch. 5 and 2.6) reproduced on our target.
//!
//! Four parts, each its own module, each producing plain data that [`report`] writes as
//! `bench.json`/`bench.csv` and [`plots`] draws:
//!
//! - [`sweep`]: cycles per CG iteration, split into MVU and SVU, against grid size, model and
//!   MVU count (thesis Fig. 5-2), the MFLOPS of eq. 56 (Fig. 5-3), instructions per nonzero and
//!   the bytes a solve puts on the wire;
//! - [`convergence`]: the ∞-norm error against CG iterations on the thesis cube (Fig. 2-9), for
//!   the target's fixed point with its refinement steps and for the host's f64;
//! - [`realtime`]: a `simulate` scenario's cycles per time step, and whether the step rate
//!   meets haptic (1 kHz) and visual (60 Hz) rates;
//! - [`host_baseline`]: the f64 reference CG's wall time per iteration up to 64³ nodes, the
//!   thesis's "general purpose computer".
//!
//! # Method
//!
//! The target's figures are counts, not times: QEMU runs with `-icount shift=0`, so `minstret`
//! and `mcycle` are exact and repeatable. Times and MFLOPS convert them at the thesis's nominal
//! 100 MHz ([`NOMINAL_CLOCK_HZ`]) with one instruction per cycle, the rate of a simple in-order
//! soft core; the instruction counts stay the primary figure.

pub mod convergence;
pub mod host_baseline;
pub mod plan;
pub mod plots;
pub mod realtime;
pub mod report;
pub mod sweep;

use std::time::Duration;

use anyhow::bail;
use serde::{Deserialize, Serialize};

use crate::board::{session_timeouts, Board, TargetFlags};
use crate::model::{Connection, Grid, ModelSpec};

/// The bench's board with `mvus` MVUs (QEMU: as many harts), its logs decoded: what every
/// target part opens.
pub fn open_board(
    target: &TargetFlags,
    mvus: u8,
    solve_timeout: Duration,
) -> anyhow::Result<Board> {
    if target.kind(None) == crate::board::TargetKind::Host && target.port.is_none() {
        bail!("--target host: the bench measures a target; the host baseline alone is --only host");
    }
    let choice = target
        .choice(Some(mvus), None)?
        .expect("a board: the host was refused above");
    Board::open(
        &choice,
        session_timeouts(solve_timeout),
        &target.logs.options(),
    )
}

/// The clock at which the thesis measured its accelerator (sec. 5.2), at which our cycle counts
/// become times and MFLOPS (eq. 56 itself is [`crate::metrics::performance`]).
pub use crate::metrics::NOMINAL_CLOCK_HZ;

/// Cycles at [`NOMINAL_CLOCK_HZ`] as microseconds.
pub fn micros(cycles: f64) -> f64 {
    cycles / NOMINAL_CLOCK_HZ * 1e6
}

/// The two spring networks of thesis Fig. 2-5, as the benchmark names them.
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum,
)]
pub enum BenchModel {
    /// Model A: 6 axial neighbours.
    #[default]
    A,
    /// Model B: all 26 neighbours.
    B,
}

impl BenchModel {
    pub const BOTH: [BenchModel; 2] = [BenchModel::A, BenchModel::B];

    pub fn connection(self) -> Connection {
        match self {
            BenchModel::A => Connection::Axial,
            BenchModel::B => Connection::AxialShear,
        }
    }

    pub fn label(self) -> &'static str {
        match self {
            BenchModel::A => "A",
            BenchModel::B => "B",
        }
    }

    /// The thesis 2.6 cube's settings (k = 1, 2, 0.5 N/m, corners fixed, 1 N in +x at the
    /// centre of the x = 0 face) on an `edge`³ grid of this model.
    pub fn cube(self, edge: usize) -> Result<ModelSpec, crate::model::grid::GridError> {
        let grid = Grid::new(edge, edge, edge)?;
        Ok(ModelSpec {
            grid,
            connection: self.connection(),
            loads: vec![ModelSpec::default_load(grid)],
            ..ModelSpec::thesis_example()
        })
    }
}

impl std::fmt::Display for BenchModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "model {}", self.label())
    }
}

/// The thesis's own figures, quoted beside ours.
pub mod thesis {
    /// Sec. 5.2.1: "a solution to a system with a grid of 500 nodes can be arrived at in 16.6 ms
    /// and 56.1 ms for connection models A and B respectively when one MVU is used", in the
    /// worst case, i.e. n = 500 iterations.
    pub const SOLVE_500_MS_A: f64 = 16.6;
    pub const SOLVE_500_MS_B: f64 = 56.1;
    /// The nodes of those figures, which are also the worst-case iteration count.
    pub const NODES: usize = 500;
    /// Sec. 5.2.2: "more than 1400 MFLOPS and 1100 MFLOPS" with 5 MVUs.
    pub const MFLOPS_5_MVUS_A: f64 = 1400.0;
    pub const MFLOPS_5_MVUS_B: f64 = 1100.0;

    /// Cycles per iteration at 100 MHz implied by the 500-node worst-case times.
    pub fn cycles_per_iteration_500(model: super::BenchModel) -> f64 {
        let ms = match model {
            super::BenchModel::A => SOLVE_500_MS_A,
            super::BenchModel::B => SOLVE_500_MS_B,
        };
        ms * 1e-3 * super::NOMINAL_CLOCK_HZ / NODES as f64
    }

    pub fn mflops_5_mvus(model: super::BenchModel) -> f64 {
        match model {
            super::BenchModel::A => MFLOPS_5_MVUS_A,
            super::BenchModel::B => MFLOPS_5_MVUS_B,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_host_is_no_board_to_measure() {
        let host = TargetFlags {
            kind: Some(crate::board::TargetKind::Host),
            ..TargetFlags::default()
        };
        let e = open_board(&host, 1, Duration::from_secs(1))
            .err()
            .expect("refused");
        assert!(e.to_string().contains("--only host"), "{e}");
    }

    #[test]
    fn micros_at_the_nominal_clock() {
        assert!((micros(100.0) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn the_thesis_figures_imply_about_one_nonzero_per_cycle() {
        // 16.6 ms / 500 iterations = 33.2 µs = 3320 cycles for a 500-node model-A system
        // (~7 nonzeros per row, ~3500 nonzeros): the hardware MVU takes one word per clock.
        assert!((thesis::cycles_per_iteration_500(BenchModel::A) - 3320.0).abs() < 1e-6);
        assert!((thesis::cycles_per_iteration_500(BenchModel::B) - 11220.0).abs() < 1e-6);
    }

    #[test]
    fn cubes_follow_the_thesis_example() {
        let spec = BenchModel::B.cube(6).unwrap();
        assert_eq!(spec.grid.node_count(), 216);
        assert_eq!(spec.connection, Connection::AxialShear);
        assert!(BenchModel::A.cube(0).is_err());
    }
}
