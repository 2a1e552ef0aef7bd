//! Performance figures of a target solve, from its counters (thesis 5.2).
//!
//! The target measures one CG iteration hart by hart
//! ([`deform_shared::protocol::IterationCost`]): the slowest MVU's instructions summed over the
//! MVU steps (T_MVU) and the SVU's (T_SVU). Under QEMU `-icount shift=0` a hart retires one
//! instruction per cycle, so these counts are the critical-path cycles of thesis eq. 55,
//! T = T_MVU + T_SVU, exactly. From them:
//!
//! - **instructions per nonzero**: all harts' MVU instructions over the words they executed (an
//!   empty-row word counts, it costs a loop turn), and over the multiply–accumulates those words
//!   stand for (a mirrored word serves two, a fused solve one per direction);
//! - **MFLOPS** at a nominal 100 MHz by thesis eq. 56, (2mn + 6n + 2)/T per direction, where n
//!   is the dimension of K and m its average nonzeros per row (of the whole K, however much of
//!   it is stored): 2mn for Kp and pᵀKp, 6n for the three vector updates and rᵀr.

use deform_shared::protocol::SolveReport;
use serde::Serialize;

use crate::encode::EncodingSummary;

/// The clock eq. 56 is evaluated at, as in thesis 5.2.
pub const NOMINAL_CLOCK_HZ: f64 = 100e6;

/// Per-iteration figures of one target solve.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Performance {
    /// MVUs (harts) the solve ran on.
    pub mvus: u8,
    /// Systems solved together (fused directions).
    pub directions: u8,
    /// Instruction words executed per iteration, all MVUs together.
    pub words_per_iteration: u32,
    /// Multiply–accumulates per iteration: nonzero words × (2 if mirrored) × directions.
    pub products_per_iteration: u64,
    /// MVU inner loop: instructions per word executed.
    pub mvu_instructions_per_word: f64,
    /// MVU inner loop: instructions per multiply–accumulate.
    pub mvu_instructions_per_product: f64,
    /// T_MVU: the slowest MVU's instructions per iteration.
    pub mvu_critical_cycles: u64,
    /// T_SVU: the SVU's critical-path instructions per iteration.
    pub svu_critical_cycles: u64,
    /// T = T_MVU + T_SVU (thesis eq. 55).
    pub critical_path_cycles: u64,
    /// m of eq. 56: average nonzeros per row of K.
    pub m: f64,
    /// n of eq. 56: the dimension of K.
    pub n: usize,
    /// directions · (2mn + 6n + 2) / T at [`NOMINAL_CLOCK_HZ`].
    pub mflops: f64,
    /// Values clamped to their fixed-point range during the solve (must be 0).
    pub saturations: u32,
}

/// The figures of `report` for a matrix laid out as `layout`, K being n×n with `nnz` nonzeros.
/// `None` when the solve did no iteration (nothing was measured).
pub fn performance(
    report: &SolveReport,
    layout: &EncodingSummary,
    n: usize,
    nnz: usize,
) -> Option<Performance> {
    let cost = report.per_iteration;
    let critical = cost.mvu_critical + cost.svu_critical;
    if report.iterations == 0 || critical == 0 || report.words_per_iteration == 0 {
        return None;
    }
    let directions = report.directions.len().max(1) as u8;
    let products = layout.products_per_mvu.iter().sum::<usize>() as u64 * directions as u64;
    let m = nnz as f64 / n.max(1) as f64;
    let flops = directions as f64 * (2.0 * m * n as f64 + 6.0 * n as f64 + 2.0);
    let seconds = critical as f64 / NOMINAL_CLOCK_HZ;
    Some(Performance {
        mvus: report.mvus,
        directions,
        words_per_iteration: report.words_per_iteration,
        products_per_iteration: products,
        mvu_instructions_per_word: cost.mvu_total as f64 / report.words_per_iteration as f64,
        mvu_instructions_per_product: cost.mvu_total as f64 / products.max(1) as f64,
        mvu_critical_cycles: cost.mvu_critical,
        svu_critical_cycles: cost.svu_critical,
        critical_path_cycles: critical,
        m,
        n,
        mflops: flops / seconds / 1e6,
        saturations: report.saturations,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use deform_shared::protocol::{DirectionReport, IterationCost, PhaseCounters};

    #[test]
    fn eq_56_at_100_mhz() {
        let direction = DirectionReport {
            iterations: 10,
            converged: true,
            residual: 1e-8,
        };
        let report = SolveReport {
            iterations: 10,
            converged: true,
            residual: 1e-8,
            directions: [direction; 3].into_iter().collect(),
            words_per_iteration: 500,
            mvus: 2,
            overlapping: false,
            mvu: PhaseCounters::default(),
            svu: PhaseCounters::default(),
            per_iteration: IterationCost {
                mvu_critical: 4_000,
                svu_critical: 6_000,
                mvu_total: 7_500,
                svu_total: 9_000,
            },
            saturations: 0,
            whole_solve: IterationCost::default(),
            first_iteration_scalar: 0,
        };
        let layout = EncodingSummary {
            nonzeros: 700,
            stored_nonzeros: 400,
            empty_row_words: 100,
            words: 500,
            tiles: 4,
            persymmetric: true,
            symmetry_used: true,
            partition: crate::encode::Partition::Rows,
            mvus: 2,
            words_per_mvu: vec![250, 250],
            products_per_mvu: vec![400, 400],
        };
        let p = performance(&report, &layout, 100, 700).unwrap();
        assert_eq!(p.critical_path_cycles, 10_000);
        assert_eq!(p.products_per_iteration, 2_400);
        assert_eq!(p.mvu_instructions_per_word, 15.0);
        assert!((p.mvu_instructions_per_product - 7_500.0 / 2_400.0).abs() < 1e-12);
        // 3 · (2·7·100 + 600 + 2) flops in 10 000 cycles = 100 µs.
        assert!((p.mflops - 3.0 * 2002.0 / 100e-6 / 1e6).abs() < 1e-9);
        let idle = SolveReport {
            iterations: 0,
            ..report
        };
        assert_eq!(performance(&idle, &layout, 100, 700), None);
    }
}
