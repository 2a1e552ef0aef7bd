//! `deform model`: build the model from the flags and describe its stiffness matrix K (the
//! properties of thesis 2.5) and its encoding as instruction words, optionally exporting K.

use std::fmt;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;

use crate::encode::{encode_with, max_quantization_error, EncodeOptions, Encoding};
use crate::model::flags::ModelFlags;
use crate::model::matrix_market::write_matrix_market;
use crate::model::{Axis, Csr, Model};
use crate::output::file::write_atomic;
use crate::output::paths::Outputs;

/// Build the tissue model and print the properties of its stiffness matrix K and its encoding.
#[derive(Debug, Clone, Args)]
pub struct ModelCommandArgs {
    /// A scenario file (TOML; see examples/). Flags given on the command line override it.
    /// Default: none, the flags and their defaults (the thesis 2.6 example).
    #[arg(value_name = "SCENARIO.toml")]
    pub scenario: Option<PathBuf>,

    #[command(flatten)]
    pub model: ModelFlags,

    /// Also write K for the x direction (k_x·A, fixed nodes applied) to FILE.mtx in Matrix
    /// Market coordinate format (1-based, every nonzero of both triangles). Default: no export.
    #[arg(long, value_name = "FILE.mtx")]
    pub export_mtx: Option<PathBuf>,
}

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

/// Runs `deform model`.
pub fn run(args: &ModelCommandArgs) -> anyhow::Result<()> {
    Outputs::new()
        .input("scenario", args.scenario.as_deref())
        .file("--export-mtx", args.export_mtx.as_deref())
        .check()?;
    let (_, spec) = args.model.resolve(args.scenario.as_deref())?;
    let model = Model::build(&spec).context("the model does not describe a solvable system")?;
    let report = ModelReport::of(&model);
    let mut stdout = io::stdout().lock();
    write!(stdout, "{report}").context("writing the report to stdout")?;
    for node in model.loads_on_fixed_nodes() {
        eprintln!("warning: the load at node {node} acts on a fixed node and is ignored");
    }
    if Axis::ALL
        .iter()
        .all(|&axis| model.scaled_rhs(axis).iter().all(|&f| f == 0.0))
    {
        eprintln!(
            "warning: every load and prescribed displacement is zero (or on fixed nodes), so the displacements are all zero"
        );
    }
    if let Some(path) = &args.export_mtx {
        export_stiffness(&model, path)?;
        writeln!(stdout, "exported K_x  {}", path.display()).context("writing to stdout")?;
    }
    Ok(())
}

/// Writes K_x to `path` in Matrix Market format.
fn export_stiffness(model: &Model, path: &Path) -> anyhow::Result<()> {
    let k = model.stiffness_matrix(Axis::X);
    let spec = model.spec();
    let comment = format!(
        "deform: K_x = k_x·A, {} grid, {}, {}, {} fixed node(s)\nnode index = i + nx·(j + ny·k), 1-based here",
        spec.grid,
        spec.connection,
        spec.elasticity,
        model.fixed_count()
    );
    write_atomic(path, |out| Ok(write_matrix_market(&k, &comment, out)?))
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

    #[test]
    fn export_writes_a_readable_file_and_reports_bad_paths() {
        let model = Model::build(&ModelSpec::thesis_example()).unwrap();
        let dir = std::env::temp_dir().join(format!("deform-model-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("k.mtx");
        export_stiffness(&model, &path).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let mut lines = text.lines().filter(|l| !l.starts_with('%'));
        assert_eq!(lines.next(), Some("1000 1000 6352"));
        assert_eq!(lines.count(), 6352);
        std::fs::remove_dir_all(&dir).unwrap();

        let missing = dir.join("no-such-dir").join("k.mtx");
        let message = format!("{:#}", export_stiffness(&model, &missing).unwrap_err());
        assert!(
            message.starts_with("writing ") && message.contains("k.mtx"),
            "{message}"
        );
    }
}
