//! What `deform estimate` reports: every estimate (the homogeneous one chosen as `k`), the
//! observations it came from and where the solves ran; the `--json` document and the summary
//! a person reads.

use std::fmt;

use serde::Serialize;

use super::homogeneous::HomogeneousEstimate;
use super::parametric::ParametricEstimate;
use super::spring_field::SpringFieldEstimate;

/// Everything `deform estimate` reports (the `--json` document).
#[derive(Debug, Serialize)]
pub struct EstimateReport {
    /// The chosen homogeneous estimate (N/m) and its standard error.
    pub k: f64,
    pub k_standard_error: f64,
    pub estimator: &'static str,
    pub observations: ObservationSummary,
    pub target: String,
    /// The model the observations were taken with (the summary's line; not in the JSON).
    #[serde(skip)]
    pub model: ModelSummary,
    pub homogeneous: Homogeneous,
    pub parametric: Option<ParametricEstimate>,
    pub spring_field: Option<SpringFieldEstimate>,
}

#[derive(Debug, Serialize)]
pub struct Homogeneous {
    pub output_error: HomogeneousEstimate,
    pub equation_error: HomogeneousEstimate,
}

#[derive(Debug, Serialize)]
pub struct ObservationSummary {
    pub file: String,
    pub sets: usize,
    pub nodes: usize,
    pub free_nodes: usize,
}

/// The model line of the summary.
#[derive(Debug, Default)]
pub struct ModelSummary {
    pub grid: String,
    pub connection: String,
    pub fixed: usize,
    pub prescribed: usize,
}

fn homogeneous_lines(
    f: &mut fmt::Formatter<'_>,
    e: &HomogeneousEstimate,
    chosen: bool,
) -> fmt::Result {
    let directions: Vec<String> = ["x", "y", "z"]
        .iter()
        .zip(e.k_by_direction)
        .filter_map(|(axis, k)| k.map(|k| format!("{axis} {k:.6}")))
        .collect();
    writeln!(
        f,
        "{:<15} k = {:.6} ± {:.2e} N/m{}, relative residual {:.3e} ({} equations; by direction: {})",
        e.method,
        e.k,
        e.standard_error,
        if chosen { " [k]" } else { "" },
        e.relative_residual,
        e.equations,
        directions.join(", ")
    )?;
    if let Some(s) = e.solves {
        writeln!(
            f,
            "                {} forward system(s), {} target solve(s), {} CG iterations",
            s.systems, s.target_solves, s.iterations
        )?;
    }
    Ok(())
}

impl fmt::Display for EstimateReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "target          {}", self.target)?;
        writeln!(
            f,
            "model           {} grid, {}, {} fixed and {} prescribed node(s)",
            self.model.grid, self.model.connection, self.model.fixed, self.model.prescribed
        )?;
        writeln!(
            f,
            "observations    {}: {} set(s) × {} nodes ({} free)",
            self.observations.file,
            self.observations.sets,
            self.observations.nodes,
            self.observations.free_nodes
        )?;
        homogeneous_lines(
            f,
            &self.homogeneous.output_error,
            self.estimator == self.homogeneous.output_error.method,
        )?;
        homogeneous_lines(
            f,
            &self.homogeneous.equation_error,
            self.estimator == self.homogeneous.equation_error.method,
        )?;
        if let Some(p) = &self.parametric {
            writeln!(
                f,
                "parametric      α0 = {:.6}, α1 = {:.6}, α2 = {:.6}, relative residual {:.3e}",
                p.alpha[0], p.alpha[1], p.alpha[2], p.relative_residual
            )?;
        }
        if let Some(sf) = &self.spring_field {
            writeln!(
        f,
            "springs         {} unknowns from {} equations ({} field(s)); H: {} nonzeros, half-band {}; {}",
            sf.unknowns,
            sf.equations,
            sf.fields,
            sf.normal_nnz,
            sf.normal_bandwidth,
            if sf.regularisation.is_empty() {
                "no regularisation".to_string()
            } else {
                format!("regularised {}", sf.regularisation.join(", "))
            }
        )?;
            writeln!(
        f,
            "                k̃ in [{:.4}, {:.4}], relative residual {:.3e}; {} target solve(s), {} CG iterations",
            sf.min_k, sf.max_k, sf.relative_residual, sf.solves.target_solves, sf.solves.iterations
        )?;
            let r = &sf.stiff_region;
            if r.max - r.median <= 0.01 * r.median.abs() {
                writeln!(
        f,
                "stiffest region none: the map is uniform (max {:.4} within 1% of the median {:.4})",
                r.max, r.median
            )?;
            } else {
                let c = r.centre;
                writeln!(
        f,
                "stiffest region {} node(s) with k ≥ {:.3} (median {:.3}, max {:.3}), centred at ({:.2}, {:.2}, {:.2})",
                r.nodes, r.threshold, r.median, r.max, c[0], c[1], c[2]
            )?;
            }
        }
        Ok(())
    }
}
