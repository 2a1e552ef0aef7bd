//! The host baseline: the f64 reference CG ([`crate::reference`]) on this computer, the
//! thesis's "general purpose computer", timed per iteration up to 64³ nodes.
//!
//! Wall time is what a host has, so these are seconds, not counts: each figure is the best of
//! three runs, and the per-iteration time is the difference between a run of `k` iterations and
//! one of a single iteration, divided by k − 1 (which removes the set-up and the final residual
//! check). The model build is timed too, and the matrix's bytes counted, to show that memory
//! and time grow with nnz (no dense step: the CSR holds (n + 1) row offsets, nnz column indices
//! and nnz values).

use std::time::{Duration, Instant};

use anyhow::Context;
use serde::{Deserialize, Serialize};

use super::BenchModel;
use crate::model::{Axis, Csr, Model};
use crate::reference;

/// What to run.
#[derive(Debug, Clone)]
pub struct HostBaselineConfig {
    pub edges: Vec<usize>,
    pub models: Vec<BenchModel>,
    /// Aim for about this much timed CG per run (the iteration count adapts).
    pub target_time: Duration,
}

/// One size.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct HostPoint {
    pub model: BenchModel,
    pub edge: usize,
    pub n: usize,
    pub nnz: usize,
    /// Bytes of A in CSR form.
    pub matrix_bytes: usize,
    /// Building the model (assembly, boundary conditions, checks), seconds.
    pub build_seconds: f64,
    pub iterations_timed: usize,
    pub seconds_per_iteration: f64,
    /// `seconds_per_iteration` / nnz: flat if time grows linearly with nnz.
    pub nanoseconds_per_nonzero: f64,
    /// `build_seconds` / nnz.
    pub build_nanoseconds_per_nonzero: f64,
}

/// Bytes of a CSR matrix's arrays.
pub fn csr_bytes(k: &Csr) -> usize {
    std::mem::size_of_val(k.row_ptr())
        + std::mem::size_of_val(k.col_indices())
        + std::mem::size_of_val(k.values())
}

fn best_of_three(mut run: impl FnMut() -> anyhow::Result<()>) -> anyhow::Result<Duration> {
    let mut best = Duration::MAX;
    for _ in 0..3 {
        let started = Instant::now();
        run()?;
        best = best.min(started.elapsed());
    }
    Ok(best)
}

/// Times every (model, edge), printing one line per point.
pub fn run(config: &HostBaselineConfig) -> anyhow::Result<Vec<HostPoint>> {
    let mut out = Vec::new();
    for &model in &config.models {
        for &edge in &config.edges {
            let point = measure(model, edge, config.target_time)?;
            println!(
                "host   {} n = {:>7} nnz = {:>8}: {:>9.3} ms/iter ({:.2} ns per nonzero), build {:.3} s, A {:.1} MB",
                model,
                point.n,
                point.nnz,
                point.seconds_per_iteration * 1e3,
                point.nanoseconds_per_nonzero,
                point.build_seconds,
                point.matrix_bytes as f64 / 1e6
            );
            out.push(point);
        }
    }
    Ok(out)
}

fn measure(model: BenchModel, edge: usize, target_time: Duration) -> anyhow::Result<HostPoint> {
    let spec = model.cube(edge)?;
    let mut built = None;
    let build_seconds = best_of_three(|| {
        built = Some(Model::build(&spec).context("building the model")?);
        Ok(())
    })?
    .as_secs_f64();
    let built = built.expect("built three times");
    let a = built.unit_matrix();
    let b = built.scaled_rhs(Axis::X);
    // Tolerance 0: exactly `k` iterations.
    let cg = |k: usize| -> anyhow::Result<()> {
        std::hint::black_box(reference::solve(a, &b, None, 0.0, k)?);
        Ok(())
    };
    let one = best_of_three(|| cg(1))?;
    let probe = best_of_three(|| cg(6))?;
    let per_probe = probe.saturating_sub(one).as_secs_f64() / 5.0;
    let k = if per_probe > 0.0 {
        (target_time.as_secs_f64() / per_probe).clamp(6.0, 500.0) as usize
    } else {
        500
    };
    let many = best_of_three(|| cg(k))?;
    let seconds_per_iteration = many.saturating_sub(one).as_secs_f64() / (k - 1) as f64;
    let nnz = a.nnz();
    Ok(HostPoint {
        model,
        edge,
        n: built.n(),
        nnz,
        matrix_bytes: csr_bytes(a),
        build_seconds,
        iterations_timed: k,
        seconds_per_iteration,
        nanoseconds_per_nonzero: seconds_per_iteration * 1e9 / nnz as f64,
        build_nanoseconds_per_nonzero: build_seconds * 1e9 / nnz as f64,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matrix_memory_is_linear_in_nnz() {
        // Bytes per nonzero stay the same from 4³ to 16³ (64× the nodes): no n² array.
        let per_nnz = |edge| {
            let m = Model::build(&BenchModel::B.cube(edge).unwrap()).unwrap();
            csr_bytes(m.unit_matrix()) as f64 / m.unit_matrix().nnz() as f64
        };
        let (small, large) = (per_nnz(4), per_nnz(16));
        assert!(large <= small && large > 16.0, "{small} {large}");
    }
}
