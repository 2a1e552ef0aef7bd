//! Jacobi preconditioning as symmetric diagonal scaling, done on the host.
//!
//! CG on K·x = b preconditioned with M = diag(K) is, in exact arithmetic, the same iteration as
//! plain CG on the scaled system S·y = s⊙b with S = D^-1/2·K·D^-1/2, s = diag(D^-1/2) and
//! x = s⊙y. So the host sends S instead of K and scales the vectors on the way in and out: the
//! target's CG is unchanged, and refinement still measures the true residual b − K·x of the
//! *original* system, so `--tol` keeps its meaning.
//!
//! Why bother: CG's iteration count grows with √κ. A stiff inclusion in soft tissue puts rows
//! whose diagonal is orders of magnitude larger than their neighbours' into K, and κ(K) with
//! them; scaling every diagonal to 1 removes that part of κ (for homogeneous tissue the diagonal
//! is nearly constant and it changes little). S has a unit diagonal and off-diagonals in
//! (−1, 1), so its Q-format keeps 19 fractional bits whatever the stiffness range.

use serde::Serialize;

use crate::model::sparse::{Csr, CsrBuilder};

/// How the host preconditions the system it sends.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Preconditioner {
    /// Plain CG on K.
    #[default]
    None,
    /// Jacobi: CG on D^-1/2·K·D^-1/2 (symmetric diagonal scaling).
    Jacobi,
}

impl std::fmt::Display for Preconditioner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Preconditioner::None => "none",
            Preconditioner::Jacobi => "jacobi",
        })
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PreconditionError {
    #[error("K[{row},{row}] = {value}: Jacobi scaling needs a positive diagonal")]
    NonPositiveDiagonal { row: usize, value: f64 },
}

/// The matrix to send and the scaling that maps its solution back: x = `scale` ⊙ y, and the
/// right-hand side sent is `scale` ⊙ b.
#[derive(Debug, Clone, PartialEq)]
pub struct Scaled {
    pub matrix: Csr,
    /// s_i = 1/√K_ii, or all ones without preconditioning.
    pub scale: Option<Vec<f64>>,
}

impl Scaled {
    /// `v` ⊙ s: a right-hand side into the scaled system, or a solution out of it.
    pub fn apply(&self, v: &[f64]) -> Vec<f64> {
        match &self.scale {
            Some(s) => v.iter().zip(s).map(|(v, s)| v * s).collect(),
            None => v.to_vec(),
        }
    }
}

/// K scaled as `preconditioner` says.
pub fn scale(k: &Csr, preconditioner: Preconditioner) -> Result<Scaled, PreconditionError> {
    match preconditioner {
        Preconditioner::None => Ok(Scaled {
            matrix: k.clone(),
            scale: None,
        }),
        Preconditioner::Jacobi => jacobi(k),
    }
}

/// S = D^-1/2·K·D^-1/2 with D = diag(K).
pub fn jacobi(k: &Csr) -> Result<Scaled, PreconditionError> {
    let diagonal = k.diagonal();
    if let Some((row, &value)) = diagonal
        .iter()
        .enumerate()
        .find(|(_, &d)| !(d > 0.0 && d.is_finite()))
    {
        return Err(PreconditionError::NonPositiveDiagonal { row, value });
    }
    let s: Vec<f64> = diagonal.iter().map(|d| 1.0 / d.sqrt()).collect();
    let mut builder = CsrBuilder::new(k.n(), k.nnz());
    for (row, &s_row) in s.iter().enumerate() {
        let (cols, vals) = k.row(row);
        let entries = cols.iter().zip(vals).map(|(&c, &v)| {
            // The diagonal is exactly 1, not 1 ± rounding, so it quantises exactly; s_i·s_j is
            // formed first so that S_ij and S_ji (and mirrored entries) are bit-identical.
            (c, if c == row { 1.0 } else { v * (s_row * s[c]) })
        });
        builder
            .push_row(entries)
            .expect("the columns come from a valid matrix");
    }
    Ok(Scaled {
        matrix: builder.finish().expect("one row per matrix row"),
        scale: Some(s),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{Connection, Grid, Inclusion, Model, ModelSpec, NodeField};
    use crate::reference;

    /// A 12³ cube with a stiff inclusion (1000× the background) in its middle.
    fn stiff_inclusion() -> Model {
        let grid = Grid::new(12, 12, 12).unwrap();
        Model::build(&ModelSpec {
            grid,
            connection: Connection::Axial,
            field: Some(NodeField {
                background: 1.0,
                inclusions: vec![Inclusion {
                    center: [6.0, 6.0, 6.0],
                    radius: 3.0,
                    k: 1000.0,
                }],
                nodes: Vec::new(),
            }),
            loads: vec![ModelSpec::default_load(grid)],
            ..ModelSpec::thesis_example()
        })
        .unwrap()
    }

    #[test]
    fn the_scaled_matrix_has_a_unit_diagonal_and_the_same_solution() {
        let model = stiff_inclusion();
        let k = model.unit_matrix();
        let scaled = jacobi(k).unwrap();
        assert!(scaled.matrix.diagonal().iter().all(|&d| d == 1.0));
        assert!(scaled.matrix.is_symmetric());
        let b = model.scaled_rhs(crate::model::Axis::X);
        let plain = reference::solve(k, &b, None, 1e-12, 100_000).unwrap();
        let y = reference::solve(&scaled.matrix, &scaled.apply(&b), None, 1e-12, 100_000).unwrap();
        let x = scaled.apply(&y.x);
        let scale = reference::max_abs(&plain.x);
        assert!(reference::max_abs_diff(&x, &plain.x) <= 1e-9 * scale);
        assert!(reference::relative_residual(k, &b, &x) <= 1e-9);
        eprintln!(
            "stiff inclusion 12³: f64 CG iterations to 1e-12, plain {} vs Jacobi {}",
            plain.iterations, y.iterations
        );
        assert!(
            (y.iterations as f64) < 0.7 * plain.iterations as f64,
            "Jacobi must pay off on a stiff inclusion: {} vs {}",
            y.iterations,
            plain.iterations
        );
    }

    #[test]
    fn none_is_the_identity_and_bad_diagonals_are_refused() {
        let k = crate::model::sparse::test_support::from_dense(&[vec![4.0, -1.0], vec![-1.0, 0.0]]);
        let same = scale(&k, Preconditioner::None).unwrap();
        assert_eq!(same.matrix, k);
        assert_eq!(same.apply(&[1.0, 2.0]), vec![1.0, 2.0]);
        assert_eq!(
            jacobi(&k),
            Err(PreconditionError::NonPositiveDiagonal { row: 1, value: 0.0 })
        );
    }
}
