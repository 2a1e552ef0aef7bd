//! Performance figures of a target solve, from its counters (thesis 5.2).
//!
//! The target measures one CG iteration hart by hart
//! ([`deform_shared::protocol::IterationCost`]): the slowest MVU's cycles and instructions
//! summed over the MVU steps (T_MVU) and the SVU's (T_SVU), so T = T_MVU + T_SVU of thesis
//! eq. 55 in both. Under QEMU `-icount shift=0` a hart retires one instruction per cycle, so the
//! two are equal by construction; on the LiteX VexRiscv the cycles are the RTL's, and the CPI is
//! their ratio. "Cycles" means cycles here, never instructions. From them:
//!
//! - **instructions per nonzero**: all harts' MVU instructions over the words they executed (an
//!   empty-row word counts, it costs a loop turn), and over the multiply–accumulates those words
//!   stand for (a mirrored word serves two, a fused solve one per direction);
//! - **MFLOPS** at a nominal 100 MHz by thesis eq. 56, (2mn + 6n + 2)/T per direction, T in
//!   cycles, where n is the dimension of K and m its average nonzeros per row (of the whole K,
//!   however much of it is stored): 2mn for Kp and pᵀKp, 6n for the three vector updates and rᵀr.

use deform_shared::protocol::{PhaseCounters, SolveReport};
use serde::Serialize;

use crate::encode::EncodingSummary;

/// The clock eq. 56 is evaluated at, as in thesis 5.2.
pub const NOMINAL_CLOCK_HZ: f64 = 100e6;

/// Cycles and instructions of one phase side by side, with their ratio (the JSON form of
/// [`PhaseCounters`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Counts {
    pub cycles: u64,
    pub instructions: u64,
    /// Cycles per instruction (`null` with no instruction counted).
    pub cpi: Option<f64>,
}

impl From<PhaseCounters> for Counts {
    fn from(c: PhaseCounters) -> Self {
        Counts {
            cycles: c.cycles,
            instructions: c.instructions,
            cpi: c.cpi(),
        }
    }
}

impl std::fmt::Display for Counts {
    /// `N cycles / M instructions (CPI x.xx)`; `N cycles = instructions` where they are equal
    /// (QEMU `-icount`: one instruction per cycle by construction).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.cycles == self.instructions {
            return write!(f, "{} cycles = instructions", self.cycles);
        }
        write!(
            f,
            "{} cycles / {} instructions",
            self.cycles, self.instructions
        )?;
        match self.cpi {
            Some(cpi) => write!(f, " (CPI {cpi:.2})"),
            None => Ok(()),
        }
    }
}

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
    /// T_MVU: the slowest MVU's cycles and instructions per iteration.
    pub mvu_critical: Counts,
    /// T_SVU: the SVU's critical-path cycles and instructions per iteration.
    pub svu_critical: Counts,
    /// T = T_MVU + T_SVU (thesis eq. 55).
    pub critical_path: Counts,
    /// m of eq. 56: average nonzeros per row of K.
    pub m: f64,
    /// n of eq. 56: the dimension of K.
    pub n: usize,
    /// directions · (2mn + 6n + 2) / T at [`NOMINAL_CLOCK_HZ`], T in cycles.
    pub mflops: f64,
    /// Values clamped to their fixed-point range during the solve (must be 0).
    pub saturations: u32,
}

impl Performance {
    /// `critical path T (MVU T_MVU + SVU T_SVU)` in cycles and instructions: one number each
    /// where cycles equal instructions (QEMU `-icount`), else both with the CPI.
    pub fn critical_path_text(&self) -> String {
        let (t, mvu, svu) = (self.critical_path, self.mvu_critical, self.svu_critical);
        if [t, mvu, svu].iter().all(|c| c.cycles == c.instructions) {
            return format!(
                "critical path {} cycles (MVU {} + SVU {}; cycles = instructions, as under QEMU \
                 -icount)",
                t.cycles, mvu.cycles, svu.cycles
            );
        }
        format!("critical path {t} (MVU {mvu} + SVU {svu})")
    }
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
    let critical = cost.critical();
    if report.iterations == 0 || critical.cycles == 0 || report.words_per_iteration == 0 {
        return None;
    }
    let directions = report.directions.len().max(1) as u8;
    let products = layout.products_per_mvu.iter().sum::<usize>() as u64 * directions as u64;
    let m = nnz as f64 / n.max(1) as f64;
    let flops = directions as f64 * (2.0 * m * n as f64 + 6.0 * n as f64 + 2.0);
    let seconds = critical.cycles as f64 / NOMINAL_CLOCK_HZ;
    Some(Performance {
        mvus: report.mvus,
        directions,
        words_per_iteration: report.words_per_iteration,
        products_per_iteration: products,
        mvu_instructions_per_word: cost.mvu_total.instructions as f64
            / report.words_per_iteration as f64,
        mvu_instructions_per_product: cost.mvu_total.instructions as f64 / products.max(1) as f64,
        mvu_critical: cost.mvu_critical.into(),
        svu_critical: cost.svu_critical.into(),
        critical_path: critical.into(),
        m,
        n,
        mflops: flops / seconds / 1e6,
        saturations: report.saturations,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use deform_shared::protocol::{DirectionReport, IterationCost};

    fn at_cpi_2(instructions: u64) -> PhaseCounters {
        PhaseCounters {
            cycles: 2 * instructions,
            instructions,
        }
    }

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
                mvu_critical: at_cpi_2(2_000),
                svu_critical: at_cpi_2(3_000),
                mvu_total: at_cpi_2(7_500),
                svu_total: at_cpi_2(9_000),
            },
            saturations: 0,
            whole_solve: IterationCost::default(),
            first_iteration_scalar: PhaseCounters::default(),
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
        // Cycles are cycles: 10 000 of them, for 5 000 instructions.
        assert_eq!(p.critical_path.cycles, 10_000);
        assert_eq!(p.critical_path.instructions, 5_000);
        assert_eq!(p.critical_path.cpi, Some(2.0));
        assert_eq!(
            p.critical_path.to_string(),
            "10000 cycles / 5000 instructions (CPI 2.00)"
        );
        assert_eq!(
            p.critical_path_text(),
            "critical path 10000 cycles / 5000 instructions (CPI 2.00) (MVU 4000 cycles / 2000 \
             instructions (CPI 2.00) + SVU 6000 cycles / 3000 instructions (CPI 2.00))"
        );
        assert_eq!(
            Counts::from(PhaseCounters {
                cycles: 7,
                instructions: 7
            })
            .to_string(),
            "7 cycles = instructions"
        );
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
