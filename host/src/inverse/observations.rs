//! Observation sets: displacements and loads per node, repeated measurements of one tissue.
//!
//! # File format (CSV)
//!
//! ```text
//! set,i,j,k,ux,uy,uz,fx,fy,fz
//! 0,0,0,0,1.2e-3,0,-4e-4,0,0,0
//! ...
//! ```
//!
//! One row per node per set. `set` is a non-negative integer naming the set (the numbers need
//! not be contiguous, and rows of different sets may interleave); `i,j,k` the 0-based grid
//! indices of the node (x fastest numbering is not required: rows may come in any order); `ux,
//! uy, uz` its observed displacement (grid units, like `deform solve`'s output) and `fx, fy, fz`
//! the load applied there (N; 0 where nothing pushes). Every set must give every node of the
//! grid exactly once; the grid is the one the model flags name (`--grid`). Spaces around
//! fields are allowed. Real measurements come in the same way: interpolate them onto the grid
//! nodes and give each repeated measurement its own set number.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{self, BufReader, BufWriter, Read, Write};
use std::path::Path;

use crate::model::{Grid, Node};

/// The largest magnitude a displacement or load may have: the estimators sum squares of products
/// of them over up to 2²⁴ nodes, which overflows f64 (into ∞ and then NaN) beyond about 1e150.
pub const MAX_MAGNITUDE: f64 = 1e100;

/// The columns of an observation file, in order.
pub const HEADER: [&str; 10] = ["set", "i", "j", "k", "ux", "uy", "uz", "fx", "fy", "fz"];

/// One set: the displacement and load of every node (by global index) in x, y and z.
#[derive(Debug, Clone, PartialEq)]
pub struct ObservationSet {
    pub id: u64,
    pub u: [Vec<f64>; 3],
    pub f: [Vec<f64>; 3],
}

/// Every set of an observation file, ordered by set number.
#[derive(Debug, Clone, PartialEq)]
pub struct Observations {
    pub grid: Grid,
    pub sets: Vec<ObservationSet>,
}

/// Why an observation file is unusable. Every message names the file, and the line where one
/// line is at fault.
#[derive(Debug, thiserror::Error)]
pub enum ObservationsError {
    #[error("{path}: {error}")]
    Io { path: String, error: io::Error },
    #[error("{path}:{line}: {what}")]
    Malformed {
        path: String,
        line: u64,
        what: String,
    },
    #[error("{path}: the file has a header but no observation rows")]
    Empty { path: String },
    #[error("{path}:{line}: node {node} appears twice in set {set} (first at line {first})")]
    Duplicate {
        path: String,
        line: u64,
        first: u64,
        set: u64,
        node: Node,
    },
    #[error(
        "{path}:{line}: node {node} is outside the {grid} grid the model flags give; fix the \
         row, or pass the grid the observations were taken on (--grid)"
    )]
    OutsideGrid {
        path: String,
        line: u64,
        node: Node,
        grid: Grid,
    },
    #[error(
        "{path}: the observations cover a {}×{}×{} grid but the model flags give {grid}; \
         pass the grid the observations were taken on (--grid {},{},{})",
        found[0], found[1], found[2], found[0], found[1], found[2]
    )]
    GridMismatch {
        path: String,
        /// Nodes along x, y and z that the rows span (largest index + 1).
        found: [usize; 3],
        grid: Grid,
    },
    #[error("{path}: set {set} has no row for node {node} ({missing} node(s) of the {grid} grid missing in that set); every set must give every node")]
    MissingNode {
        path: String,
        set: u64,
        node: Node,
        missing: usize,
        grid: Grid,
    },
}

impl Observations {
    /// Reads and checks the observation file at `path` against `grid`.
    pub fn read(path: &Path, grid: Grid) -> Result<Self, ObservationsError> {
        let name = path.display().to_string();
        let file = File::open(path).map_err(|error| ObservationsError::Io {
            path: name.clone(),
            error,
        })?;
        Self::parse(BufReader::new(file), &name, grid)
    }

    /// Parses observation CSV from `reader`; `name` is used in messages.
    pub fn parse(reader: impl Read, name: &str, grid: Grid) -> Result<Self, ObservationsError> {
        let mut csv = csv::ReaderBuilder::new()
            .has_headers(true)
            .trim(csv::Trim::All)
            .from_reader(reader);
        let header = csv.headers().map_err(|e| csv_error(name, e))?.clone();
        if header.iter().ne(HEADER.iter().copied()) {
            return Err(malformed(
                name,
                1,
                format!(
                    "the header must be `{}`, found `{}`",
                    HEADER.join(","),
                    header.iter().collect::<Vec<_>>().join(",")
                ),
            ));
        }
        let n = grid.node_count();
        // Per set: the line of each node's row (0 = none yet) and the values.
        let mut sets: BTreeMap<u64, (Vec<u64>, ObservationSet)> = BTreeMap::new();
        let mut found = [0usize; 3];
        let mut record = csv::StringRecord::new();
        while csv
            .read_record(&mut record)
            .map_err(|e| csv_error(name, e))?
        {
            let row = Row::parse(&record, name)?;
            for (extent, index) in found.iter_mut().zip([row.node.i, row.node.j, row.node.k]) {
                *extent = (*extent).max(index.saturating_add(1));
            }
            let Some(p) = grid.index(row.node) else {
                return Err(ObservationsError::OutsideGrid {
                    path: name.to_string(),
                    line: row.line,
                    node: row.node,
                    grid,
                });
            };
            let (lines, values) = sets.entry(row.set).or_insert_with(|| {
                (
                    vec![0; n],
                    ObservationSet {
                        id: row.set,
                        u: [(); 3].map(|_| vec![0.0; n]),
                        f: [(); 3].map(|_| vec![0.0; n]),
                    },
                )
            });
            if lines[p] != 0 {
                return Err(ObservationsError::Duplicate {
                    path: name.to_string(),
                    line: row.line,
                    first: lines[p],
                    set: row.set,
                    node: row.node,
                });
            }
            lines[p] = row.line;
            for d in 0..3 {
                values.u[d][p] = row.u[d];
                values.f[d][p] = row.f[d];
            }
        }
        if !sets.is_empty() && found != [grid.nx(), grid.ny(), grid.nz()] {
            return Err(ObservationsError::GridMismatch {
                path: name.to_string(),
                found,
                grid,
            });
        }
        complete(name, grid, sets).map(|sets| Self { grid, sets })
    }

    /// Writes the observations as CSV (see the module doc), nodes in index order.
    pub fn write(&self, out: impl Write) -> io::Result<()> {
        let mut out = BufWriter::new(out);
        writeln!(out, "{}", HEADER.join(","))?;
        for set in &self.sets {
            for (p, node) in self.grid.nodes().enumerate() {
                writeln!(
                    out,
                    "{},{},{},{},{:e},{:e},{:e},{:e},{:e},{:e}",
                    set.id,
                    node.i,
                    node.j,
                    node.k,
                    set.u[0][p],
                    set.u[1][p],
                    set.u[2][p],
                    set.f[0][p],
                    set.f[1][p],
                    set.f[2][p]
                )?;
            }
        }
        out.flush()
    }
}

/// A malformed-row error of file `name` at `line`.
fn malformed(name: &str, line: u64, what: String) -> ObservationsError {
    ObservationsError::Malformed {
        path: name.to_string(),
        line,
        what,
    }
}

/// The CSV reader's error, said for people.
fn csv_error(name: &str, e: csv::Error) -> ObservationsError {
    let line = e.position().map_or(0, |p| p.line());
    match e.into_kind() {
        csv::ErrorKind::Io(error) => ObservationsError::Io {
            path: name.to_string(),
            error,
        },
        csv::ErrorKind::UnequalLengths {
            expected_len, len, ..
        } => malformed(
            name,
            line,
            format!(
                "{len} fields, expected {expected_len} ({})",
                HEADER.join(",")
            ),
        ),
        csv::ErrorKind::Utf8 { .. } => malformed(name, line, "not valid UTF-8".into()),
        other => malformed(name, line, format!("{other:?}")),
    }
}

/// One row of the file, its fields checked.
struct Row {
    line: u64,
    set: u64,
    node: Node,
    u: [f64; 3],
    f: [f64; 3],
}

impl Row {
    fn parse(record: &csv::StringRecord, name: &str) -> Result<Self, ObservationsError> {
        let line = record.position().map_or(0, |p| p.line());
        let field = |index: usize| record.get(index).unwrap_or("");
        let integer = |index: usize| {
            field(index).parse::<u64>().map_err(|_| {
                malformed(
                    name,
                    line,
                    format!(
                        "column `{}`: '{}' is not a non-negative integer",
                        HEADER[index],
                        field(index)
                    ),
                )
            })
        };
        let number = |index: usize| match field(index).parse::<f64>() {
            Ok(v) if v.abs() <= MAX_MAGNITUDE => Ok(v),
            Ok(v) if v.is_finite() => Err(malformed(
                name,
                line,
                format!(
                    "column `{}`: {v:e} is beyond ±{MAX_MAGNITUDE:e}, where the estimators' \
                     sums of squares would overflow",
                    HEADER[index]
                ),
            )),
            _ => Err(malformed(
                name,
                line,
                format!(
                    "column `{}`: '{}' is not a finite number",
                    HEADER[index],
                    field(index)
                ),
            )),
        };
        let set = integer(0)?;
        let [i, j, k] = [integer(1)?, integer(2)?, integer(3)?]
            .map(|v| usize::try_from(v).unwrap_or(usize::MAX));
        Ok(Row {
            line,
            set,
            node: Node::new(i, j, k),
            u: [number(4)?, number(5)?, number(6)?],
            f: [number(7)?, number(8)?, number(9)?],
        })
    }
}

/// The sets, each checked to have every node of `grid`.
fn complete(
    name: &str,
    grid: Grid,
    sets: BTreeMap<u64, (Vec<u64>, ObservationSet)>,
) -> Result<Vec<ObservationSet>, ObservationsError> {
    if sets.is_empty() {
        return Err(ObservationsError::Empty {
            path: name.to_string(),
        });
    }
    let mut out = Vec::with_capacity(sets.len());
    for (set, (lines, values)) in sets {
        let missing = lines.iter().filter(|&&l| l == 0).count();
        if let Some(p) = lines.iter().position(|&l| l == 0) {
            return Err(ObservationsError::MissingNode {
                path: name.to_string(),
                set,
                node: grid.node(p),
                missing,
                grid,
            });
        }
        out.push(values);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid() -> Grid {
        Grid::new(2, 1, 1).unwrap()
    }

    const GOOD: &str = "set,i,j,k,ux,uy,uz,fx,fy,fz\n\
                        3, 1,0,0, 0.5,0,0, 1,0,0\n\
                        3,0,0,0,0,0,0,0,0,0\n\
                        1,0,0,0,0,0,0,0,0,0\n\
                        1,1,0,0,0.25,-1,2e-3,1,0,0\n";

    fn parse(text: &str) -> Result<Observations, ObservationsError> {
        Observations::parse(text.as_bytes(), "obs.csv", grid())
    }

    #[test]
    fn parses_sets_in_any_row_order_and_round_trips() {
        let obs = parse(GOOD).unwrap();
        assert_eq!(obs.sets.len(), 2);
        assert_eq!(obs.sets[0].id, 1);
        assert_eq!(obs.sets[0].u[1], vec![0.0, -1.0]);
        assert_eq!(obs.sets[1].u[0], vec![0.0, 0.5]);
        assert_eq!(obs.sets[1].f[0], vec![0.0, 1.0]);
        let mut text = Vec::new();
        obs.write(&mut text).unwrap();
        assert_eq!(parse(std::str::from_utf8(&text).unwrap()).unwrap(), obs);
    }

    fn error(text: &str) -> String {
        parse(text).unwrap_err().to_string()
    }

    #[test]
    fn malformed_files_name_the_line() {
        let e = error("set,i,j,k,ux,uy,uz\n");
        assert!(e.starts_with("obs.csv:1: the header must be"), "{e}");
        let e = error(&GOOD.replace("0.25", "abc"));
        assert!(
            e.contains("obs.csv:5:") && e.contains("`ux`") && e.contains("'abc'"),
            "{e}"
        );
        let e = error(&GOOD.replace("3,0,0,0,0,0,0,0,0,0", "3,0,0,0,0,0,0,0,0"));
        assert!(e.contains("obs.csv:3:") && e.contains("9 fields"), "{e}");
        let e = error(&GOOD.replace("1,0,0,0,0,0", "-1,0,0,0,0,0"));
        assert!(e.contains("obs.csv:4:") && e.contains("`set`"), "{e}");
        let e = error(&GOOD.replace("2e-3", "inf"));
        assert!(e.contains("obs.csv:5:") && e.contains("finite"), "{e}");
        // Finite, but its square overflows the estimators' sums.
        let e = error(&GOOD.replace("2e-3", "1e308"));
        assert!(
            e.contains("obs.csv:5:") && e.contains("`uz`: 1e308 is beyond"),
            "{e}"
        );
        let e = error("set,i,j,k,ux,uy,uz,fx,fy,fz\n");
        assert!(e.contains("no observation rows"), "{e}");
    }

    #[test]
    fn missing_and_duplicate_nodes_and_grid_mismatch() {
        let e = error(&GOOD.replace("1,0,0,0,0,0,0,0,0,0\n", ""));
        assert!(e.contains("set 1 has no row for node (0,0,0)"), "{e}");
        let e = error(&GOOD.replace("3,0,0,0,", "3,1,0,0,"));
        assert!(
            e.contains("obs.csv:3: node (1,0,0) appears twice in set 3 (first at line 2)"),
            "{e}"
        );
        // A row outside the grid is named by its line: a typo, not a larger grid.
        let e = error(&format!("{GOOD}1,30,0,0,0,0,0,0,0,0\n"));
        assert!(
            e.contains("obs.csv:6: node (30,0,0) is outside the 2×1×1 grid")
                && !e.contains("--grid 31"),
            "{e}"
        );
        let small = "set,i,j,k,ux,uy,uz,fx,fy,fz\n0,0,0,0,0,0,0,0,0,0\n";
        assert!(error(small).contains("cover a 1×1×1 grid"));
    }
}
