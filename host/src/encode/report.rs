//! What `deform model` reports about a model: the properties of its stiffness matrix K
//! (thesis 2.5: size, sparsity, bandwidth, symmetry) and of A's encoding as instruction words.

use std::fmt;

use super::{encode_with, max_quantization_error, EncodeOptions, Encoding};
use crate::model::{Axis, Csr, Model};

/// Everything `deform model` prints, computed once so that it can be tested without stdout.
#[derive(Debug, Clone)]
pub struct ModelReport {
    pub model_line: String,
    pub n: usize,
    pub nnz: usize,
    pub max_row_nnz: usize,
    pub sparsity: f64,
    pub sparsity_estimate: f64,
    pub bandwidth: usize,
    pub symmetric: bool,
    pub fixed_nodes: usize,
    pub loads: String,
    /// The encoding of A (what `deform solve` sends), or why it cannot be encoded.
    pub encoding: Result<EncodingSummary, String>,
}

/// The size and precision of an encoded matrix.
#[derive(Debug, Clone, PartialEq)]
pub struct EncodingSummary {
    pub tiles: usize,
    pub words: usize,
    /// Zero words that only end an empty tile row (the tiling's overhead).
    pub empty_row_words: usize,
    pub frac_bits: u8,
    pub max_quantization_error: f64,
    /// A is persymmetric (conjugate symmetry, thesis 2.5 vi).
    pub persymmetric: bool,
    /// Words and tiles when only the half is stored (if persymmetric).
    pub half: Option<(usize, usize)>,
}

impl EncodingSummary {
    fn of(matrix: &Csr, full: &Encoding, half: Option<&Encoding>) -> Self {
        let encoded = &full.matrix;
        Self {
            tiles: encoded.tiles.len(),
            words: encoded.words.len(),
            empty_row_words: full.summary.empty_row_words,
            frac_bits: encoded.frac_bits,
            max_quantization_error: max_quantization_error(matrix, encoded.frac_bits)
                .expect("the encoder already quantized these values"),
            persymmetric: full.summary.persymmetric,
            half: half.map(|h| (h.summary.words, h.summary.tiles)),
        }
    }
}

impl ModelReport {
    /// Describes K_x (the other directions differ only by the factor k_d/k_x) and the
    /// encoding of A.
    pub fn of(model: &Model) -> Self {
        let k = model.stiffness_matrix(Axis::X);
        let spec = model.spec();
        let a = model.unit_matrix();
        let full = encode_with(a, &EncodeOptions::default());
        let half = full
            .as_ref()
            .ok()
            .filter(|f| f.summary.persymmetric)
            .map(|_| {
                encode_with(
                    a,
                    &EncodeOptions {
                        use_symmetry: true,
                        ..EncodeOptions::default()
                    },
                )
            });
        let encoding = match (full, half) {
            (Ok(full), None) => Ok(EncodingSummary::of(a, &full, None)),
            (Ok(full), Some(Ok(half))) => Ok(EncodingSummary::of(a, &full, Some(&half))),
            (Err(e), _) | (_, Some(Err(e))) => Err(e.to_string()),
        };
        let force: Vec<f64> = Axis::ALL
            .iter()
            .map(|&axis| model.load(axis).iter().sum())
            .collect();
        let loads = format!(
            "{} point load(s), {} face pressure(s), {} prescribed displacement(s); total force on free nodes ({}, {}, {}) N",
            spec.loads.len(),
            spec.pressures.len(),
            model.prescribed_count(),
            force[0],
            force[1],
            force[2]
        );
        Self {
            model_line: spec.describe(),
            n: k.n(),
            nnz: k.nnz(),
            max_row_nnz: k.max_row_nnz(),
            sparsity: k.sparsity(),
            sparsity_estimate: k.sparsity_estimate(),
            bandwidth: k.bandwidth(),
            symmetric: k.is_symmetric(),
            fixed_nodes: model.fixed_count(),
            loads,
            encoding,
        }
    }
}

impl fmt::Display for ModelReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "model          {}", self.model_line)?;
        writeln!(f, "fixed nodes    {}", self.fixed_nodes)?;
        writeln!(f, "loads          {}", self.loads)?;
        writeln!(f, "n              {}", self.n)?;
        writeln!(
            f,
            "nnz            {} (K_x; every direction has the same pattern)",
            self.nnz
        )?;
        writeln!(
            f,
            "sparsity       {:.4} % exact (1 − nnz/n²), {:.4} % by thesis eq. 37 (1 − {}/n)",
            100.0 * self.sparsity,
            100.0 * self.sparsity_estimate,
            self.max_row_nnz
        )?;
        writeln!(
            f,
            "bandwidth      {} (max |i − j| over nonzeros)",
            self.bandwidth
        )?;
        writeln!(
            f,
            "symmetric      {}",
            if self.symmetric {
                "yes (checked)"
            } else {
                "NO"
            }
        )?;
        match &self.encoding {
            Ok(e) => {
                let error = match e.max_quantization_error {
                    0.0 => "0 (exact)".to_string(),
                    error => format!("{error:.3e}"),
                };
                writeln!(
                    f,
                    "encoding of A  {} tile(s), {} words ({} empty-row), {} fractional bits, max quantization error {error}",
                    e.tiles, e.words, e.empty_row_words, e.frac_bits
                )?;
                match e.half {
                    Some((words, tiles)) => writeln!(
                        f,
                        "persymmetric   yes: conjugate symmetry stores half, {words} words in {tiles} tile(s)"
                    ),
                    None => writeln!(f, "persymmetric   no (the whole matrix is stored)"),
                }
            }
            Err(reason) => writeln!(f, "encoding of A  not possible: {reason}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{Connection, ModelSpec};

    #[test]
    fn report_of_the_thesis_example() {
        let model = Model::build(&ModelSpec::thesis_example()).unwrap();
        let report = ModelReport::of(&model);
        assert_eq!(report.n, 1000);
        assert_eq!(report.max_row_nnz, 7);
        assert_eq!(report.bandwidth, 100);
        assert!(report.symmetric);
        assert_eq!(report.fixed_nodes, 8);
        // 1000 diagonals + 2·2700 springs, minus the 2·3 spring entries at each corner.
        assert_eq!(report.nnz, 1000 + 2 * 2700 - 8 * 6);
        assert!((report.sparsity_estimate - 0.993).abs() < 1e-12);
        let encoding = report.encoding.clone().unwrap();
        assert_eq!(encoding.words, report.nnz + encoding.empty_row_words);
        assert!(encoding.empty_row_words <= 2);
        assert_eq!(encoding.max_quantization_error, 0.0);
        let text = report.to_string();
        assert!(text.contains("symmetric      yes"), "{text}");
        assert!(text.contains("bandwidth      100"), "{text}");
    }

    #[test]
    fn a_band_wider_than_a_window_encodes_and_halves() {
        let grid = crate::model::Grid::new(16, 16, 16).unwrap();
        let spec = ModelSpec {
            grid,
            connection: Connection::AxialShear,
            loads: vec![ModelSpec::default_load(grid)],
            ..ModelSpec::thesis_example()
        };
        let report = ModelReport::of(&Model::build(&spec).unwrap());
        let encoding = report.encoding.clone().unwrap();
        assert_eq!(report.bandwidth, 273);
        assert!(encoding.words < report.nnz + report.n / 100);
        let (half_words, _) = encoding.half.unwrap();
        assert!(half_words * 2 <= report.nnz + report.n);
        assert!(report.to_string().contains("persymmetric   yes"));
    }
}
