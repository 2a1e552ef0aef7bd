//! Writing displacement fields: CSV (`i,j,k,ux,uy,uz`), JSON (the same rows plus statistics),
//! or VTK XML for ParaView (`.vtu`/`.vts`, see [`vtk`]: the grid with the displacement vector,
//! |u| and the node stiffness as point data). The format follows the file extension, checked
//! before any work is done.

pub mod csv;
pub mod file;
pub mod paths;
pub mod series;
pub mod vtk;

use std::io::Write;
use std::path::Path;

use anyhow::bail;
use serde::Serialize;

use crate::model::Model;

/// The output formats `--out` understands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OutputFormat {
    Csv,
    Json,
    /// VTK XML unstructured grid (hexahedra).
    Vtu,
    /// VTK XML structured grid.
    Vts,
}

impl OutputFormat {
    /// The format a path asks for by its extension.
    pub fn of(path: &Path) -> anyhow::Result<OutputFormat> {
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .as_deref()
        {
            Some("csv") => Ok(OutputFormat::Csv),
            Some("json") => Ok(OutputFormat::Json),
            Some("vtu") => Ok(OutputFormat::Vtu),
            Some("vts") => Ok(OutputFormat::Vts),
            _ => bail!(
                "--out {}: unknown format; use a .csv, .json, .vtu or .vts file name",
                path.display()
            ),
        }
    }
}

/// One node's displacement, as written to CSV and JSON (and VTK, with the stiffness).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct NodeDisplacement {
    pub i: usize,
    pub j: usize,
    pub k: usize,
    pub ux: f64,
    pub uy: f64,
    pub uz: f64,
    /// The node's stiffness in N/m (VTK point data only; CSV and JSON leave it out).
    #[serde(skip)]
    pub stiffness: f64,
}

/// The rows of a displacement field `u = [ux, uy, uz]`, in node order, with the model's node
/// stiffness.
pub fn node_rows(model: &Model, u: &[Vec<f64>; 3]) -> Vec<NodeDisplacement> {
    node_rows_with_stiffness(model, u, &model.node_stiffness())
}

/// Like [`node_rows`], with the node stiffness given (e.g. a displacement-dependent one).
pub fn node_rows_with_stiffness(
    model: &Model,
    u: &[Vec<f64>; 3],
    stiffness: &[f64],
) -> Vec<NodeDisplacement> {
    (0..model.n())
        .map(|p| {
            let node = model.node(p);
            NodeDisplacement {
                i: node.i,
                j: node.j,
                k: node.k,
                ux: u[0][p],
                uy: u[1][p],
                uz: u[2][p],
                stiffness: stiffness.get(p).copied().unwrap_or(f64::NAN),
            }
        })
        .collect()
}

/// Writes `rows` to `path` in the format its extension names; `stats` goes into JSON only.
pub fn write_displacements(
    path: &Path,
    rows: &[NodeDisplacement],
    stats: &impl Serialize,
) -> anyhow::Result<()> {
    match OutputFormat::of(path)? {
        OutputFormat::Vtu => vtk::write_vtk(path, rows, vtk::VtkKind::Unstructured),
        OutputFormat::Vts => vtk::write_vtk(path, rows, vtk::VtkKind::Structured),
        OutputFormat::Csv => write_table(path, rows, None::<&()>),
        OutputFormat::Json => write_table(path, rows, Some(stats)),
    }
}

/// One CSV row `PREFIXi,j,k,ux,uy,uz` (the prefix carries a time series' `step,t,`).
pub(crate) fn write_csv_row(
    out: &mut impl Write,
    prefix: &str,
    r: &NodeDisplacement,
) -> std::io::Result<()> {
    writeln!(
        out,
        "{prefix}{},{},{},{:e},{:e},{:e}",
        r.i, r.j, r.k, r.ux, r.uy, r.uz
    )
}

/// CSV (`stats` = `None`) or JSON.
fn write_table(
    path: &Path,
    rows: &[NodeDisplacement],
    stats: Option<&impl Serialize>,
) -> anyhow::Result<()> {
    file::write_atomic(path, |out| write_table_to(out, rows, stats))
}

fn write_table_to(
    out: &mut impl Write,
    rows: &[NodeDisplacement],
    stats: Option<&impl Serialize>,
) -> anyhow::Result<()> {
    match stats {
        None => {
            writeln!(out, "i,j,k,ux,uy,uz")?;
            for r in rows {
                write_csv_row(out, "", r)?;
            }
        }
        Some(stats) => {
            #[derive(Serialize)]
            struct Document<'a, S: Serialize> {
                stats: &'a S,
                nodes: &'a [NodeDisplacement],
            }
            serde_json::to_writer_pretty(&mut *out, &Document { stats, nodes: rows })?;
            writeln!(out)?;
        }
    }
    Ok(())
}

/// Writes `value` as pretty JSON to `path`, whole or not at all (a report).
pub fn write_json(path: &Path, value: &impl Serialize) -> anyhow::Result<()> {
    file::write_atomic(path, |out| {
        Ok(serde_json::to_writer_pretty(&mut *out, value)?)
    })
}
