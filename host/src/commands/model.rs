//! `deform model`: build the model from the flags and describe its stiffness matrix K (the
//! properties of thesis 2.5) and its encoding as instruction words, optionally exporting K.

use std::io::{self, Write};
use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;

use crate::encode::report::ModelReport;
use crate::model::flags::ModelFlags;
use crate::model::matrix_market::write_matrix_market;
use crate::model::{Axis, Model};
use crate::output::file::write_atomic;
use crate::output::paths::Outputs;
use crate::scenario::resolve_model;

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

/// Runs `deform model`.
pub fn run(args: &ModelCommandArgs) -> anyhow::Result<()> {
    Outputs::new()
        .input("scenario", args.scenario.as_deref())
        .file("--export-mtx", args.export_mtx.as_deref())
        .check()?;
    let (_, spec) = resolve_model(args.scenario.as_deref(), &args.model)?;
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
    use crate::model::ModelSpec;

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
