//! Writing displacement fields: CSV (`i,j,k,ux,uy,uz`) or JSON (the same rows plus statistics).
//! The format follows the file extension, checked before any work is done.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use serde::Serialize;

use crate::model::Model;

/// The output formats `--out` understands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OutputFormat {
    Csv,
    Json,
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
            _ => bail!(
                "--out {}: unknown format; use a .csv or .json file name",
                path.display()
            ),
        }
    }
}

/// One node's displacement, as written to CSV and JSON.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct NodeDisplacement {
    pub i: usize,
    pub j: usize,
    pub k: usize,
    pub ux: f64,
    pub uy: f64,
    pub uz: f64,
}

/// The rows of a displacement field `u = [ux, uy, uz]`, in node order.
pub fn node_rows(model: &Model, u: &[Vec<f64>; 3]) -> Vec<NodeDisplacement> {
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
            }
        })
        .collect()
}

/// Writes `rows` to `path` in the format its extension names; `stats` goes into JSON only.
pub fn write_displacements(
    path: &PathBuf,
    rows: &[NodeDisplacement],
    stats: &impl Serialize,
) -> anyhow::Result<()> {
    let format = OutputFormat::of(path)?;
    let file = File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut out = BufWriter::new(file);
    match format {
        OutputFormat::Csv => {
            writeln!(out, "i,j,k,ux,uy,uz")?;
            for r in rows {
                writeln!(
                    out,
                    "{},{},{},{:e},{:e},{:e}",
                    r.i, r.j, r.k, r.ux, r.uy, r.uz
                )?;
            }
        }
        OutputFormat::Json => {
            #[derive(Serialize)]
            struct Document<'a, S: Serialize> {
                stats: &'a S,
                nodes: &'a [NodeDisplacement],
            }
            serde_json::to_writer_pretty(&mut out, &Document { stats, nodes: rows })?;
            writeln!(out)?;
        }
    }
    out.flush()
        .with_context(|| format!("writing {}", path.display()))
}
