//! A time series' displacements, as `deform simulate --out` and `deform live --out` write
//! them:
//!
//! - `FILE.csv`: every step's every node, `step,t,i,j,k,ux,uy,uz`;
//! - `FILE.pvd`: that ParaView collection, with one `FILE_NNNN.vtu` per step beside it;
//! - any other path: a directory with `step_NNNN.vtu` (live: `frame_NNNNN.vtu`) per step and
//!   `series.pvd`.
//!
//! An interrupted run leaves a readable series: every `.vtu` appears whole, the `.pvd` is
//! rewritten as the steps come (at most once a second, and at the end), and the CSV grows under
//! its temporary name (see [`super::file`]).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::Context;

use super::csv::{CsvRow, CsvTable};
use super::file::StreamedFile;
use super::vtk::{write_pvd, write_vtk, VtkKind};
use super::{write_csv_row, NodeDisplacement};

/// Where and how the series goes, from the path's extension.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SeriesTarget {
    Csv(PathBuf),
    Pvd(PathBuf),
    Directory(PathBuf),
}

impl SeriesTarget {
    pub fn of(path: &Path) -> Self {
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .as_deref()
        {
            Some("csv") => SeriesTarget::Csv(path.to_path_buf()),
            Some("pvd") => SeriesTarget::Pvd(path.to_path_buf()),
            _ => SeriesTarget::Directory(path.to_path_buf()),
        }
    }
}

/// How a directory series names its files: `step_0001.vtu` or `frame_00001.vtu`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Numbering {
    pub word: &'static str,
    pub digits: usize,
}

impl Numbering {
    /// `deform simulate`'s steps.
    pub const STEPS: Numbering = Numbering {
        word: "step",
        digits: 4,
    };
    /// `deform live`'s frames.
    pub const FRAMES: Numbering = Numbering {
        word: "frame",
        digits: 5,
    };
}

/// How often a growing series' `.pvd` is rewritten at most.
const PVD_EVERY: Duration = Duration::from_secs(1);

/// Writes the steps as they come.
#[derive(Debug)]
pub struct SeriesWriter {
    target: SeriesTarget,
    numbering: Numbering,
    csv: Option<StreamedFile>,
    /// (t, .vtu name relative to the .pvd; empty for CSV) so far.
    steps: Vec<(f64, String)>,
    pvd_written: Option<Instant>,
}

impl SeriesWriter {
    /// Creates the CSV file (with its header) or the directory, before any step is solved.
    pub fn create(target: SeriesTarget, numbering: Numbering) -> anyhow::Result<Self> {
        let csv = match &target {
            SeriesTarget::Csv(path) => {
                let mut file = StreamedFile::create(path)?;
                writeln!(file.writer(), "{},t,i,j,k,ux,uy,uz", numbering.word)?;
                file.flush()?;
                Some(file)
            }
            SeriesTarget::Pvd(path) => {
                if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
                    std::fs::create_dir_all(dir)
                        .with_context(|| format!("creating {}", dir.display()))?;
                }
                None
            }
            SeriesTarget::Directory(dir) => {
                std::fs::create_dir_all(dir)
                    .with_context(|| format!("creating {}", dir.display()))?;
                None
            }
        };
        Ok(Self {
            target,
            numbering,
            csv,
            steps: Vec::new(),
            pvd_written: None,
        })
    }

    /// The collection file of a `.pvd` or directory series.
    fn pvd(&self) -> Option<PathBuf> {
        match &self.target {
            SeriesTarget::Csv(_) => None,
            SeriesTarget::Pvd(path) => Some(path.clone()),
            SeriesTarget::Directory(dir) => Some(dir.join("series.pvd")),
        }
    }

    /// Step `step` at time `t`.
    pub fn write_step(
        &mut self,
        step: u32,
        t: f64,
        rows: &[NodeDisplacement],
    ) -> anyhow::Result<()> {
        let Numbering { word, digits } = self.numbering;
        let (dir, name) = match &self.target {
            SeriesTarget::Csv(_) => {
                let out = self.csv.as_mut().expect("created with the file");
                let prefix = format!("{step},{t},");
                for r in rows {
                    write_csv_row(out.writer(), &prefix, r)?;
                }
                out.flush()?;
                self.steps.push((t, String::new()));
                return Ok(());
            }
            SeriesTarget::Pvd(path) => {
                let stem = path
                    .file_stem()
                    .and_then(|s| s.to_str())
                    .unwrap_or("series");
                (
                    path.parent().map(Path::to_path_buf).unwrap_or_default(),
                    format!("{stem}_{step:0digits$}.vtu"),
                )
            }
            SeriesTarget::Directory(dir) => (dir.clone(), format!("{word}_{step:0digits$}.vtu")),
        };
        write_vtk(&dir.join(&name), rows, VtkKind::Unstructured)?;
        self.steps.push((t, name));
        if self.pvd_written.is_none_or(|at| at.elapsed() >= PVD_EVERY) {
            if let Some(pvd) = self.pvd() {
                write_pvd(&pvd, &self.steps)?;
                self.pvd_written = Some(Instant::now());
            }
        }
        Ok(())
    }

    /// Flushes the CSV or writes the .pvd; returns a line saying what was written.
    pub fn finish(self) -> anyhow::Result<String> {
        let count = self.steps.len();
        let what = if self.numbering == Numbering::STEPS {
            "steps"
        } else {
            "frames"
        };
        let pvd = self.pvd();
        match (self.csv, pvd) {
            (Some(csv), _) => Ok(format!("{} ({count} {what})", csv.finish()?.display())),
            (None, Some(pvd)) => {
                write_pvd(&pvd, &self.steps)?;
                let beside = match self.target {
                    SeriesTarget::Pvd(_) => " beside it",
                    _ => "",
                };
                Ok(format!("{} (+{count} .vtu files{beside})", pvd.display()))
            }
            (None, None) => unreachable!("a CSV series has its file"),
        }
    }
}

/// What a run writes as it goes: its per-step (or per-frame) CSV table and its series of
/// displacement fields, either or both. `deform simulate` and `deform live` each write
/// through one.
pub struct RunFiles {
    csv: Option<CsvTable>,
    series: Option<SeriesWriter>,
}

impl RunFiles {
    /// Creates the table (`template`'s header) and the series, before the run starts.
    pub fn create(
        csv: Option<&Path>,
        template: &dyn CsvRow,
        series: Option<&Path>,
        numbering: Numbering,
    ) -> anyhow::Result<Self> {
        Ok(Self {
            csv: csv.map(|p| CsvTable::create(p, template)).transpose()?,
            series: series
                .map(|p| SeriesWriter::create(SeriesTarget::of(p), numbering))
                .transpose()?,
        })
    }

    /// Step `step` at `t`: its row, and its field if the series wants one (`rows` is called
    /// only then).
    pub fn write(
        &mut self,
        row: &dyn CsvRow,
        step: u32,
        t: f64,
        rows: impl FnOnce() -> Option<Vec<NodeDisplacement>>,
    ) -> anyhow::Result<()> {
        if let Some(csv) = self.csv.as_mut() {
            csv.write(row)?;
        }
        if let Some(series) = self.series.as_mut() {
            if let Some(rows) = rows() {
                series.write_step(step, t, &rows)?;
            }
        }
        Ok(())
    }

    /// Gives the files their real names and writes the series' collection; the lines to print.
    pub fn finish(self) -> anyhow::Result<Vec<String>> {
        let mut wrote = Vec::new();
        if let Some(series) = self.series {
            wrote.push(series.finish()?);
        }
        if let Some(csv) = self.csv {
            wrote.push(csv.finish()?.display().to_string());
        }
        Ok(wrote)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rows() -> Vec<NodeDisplacement> {
        (0..2)
            .map(|i| NodeDisplacement {
                i,
                j: 0,
                k: 0,
                ux: i as f64 * 0.5,
                uy: 0.0,
                uz: -1.0,
                stiffness: 1.0,
            })
            .collect()
    }

    fn temp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("deform-series-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn a_pvd_path_is_a_file_with_its_vtu_files_beside_it() {
        let dir = temp("pvd");
        let path = dir.join("needle.pvd");
        let mut w = SeriesWriter::create(SeriesTarget::of(&path), Numbering::STEPS).unwrap();
        w.write_step(1, 0.5, &rows()).unwrap();
        w.write_step(2, 1.0, &rows()).unwrap();
        w.finish().unwrap();
        assert!(path.is_file(), "needle.pvd must be a file");
        assert!(dir.join("needle_0001.vtu").is_file());
        let pvd = std::fs::read_to_string(&path).unwrap();
        assert!(pvd.contains(r#"file="needle_0002.vtu""#), "{pvd}");
        let dir_out = dir.join("series");
        let mut w = SeriesWriter::create(SeriesTarget::of(&dir_out), Numbering::STEPS).unwrap();
        w.write_step(1, 0.5, &rows()).unwrap();
        w.finish().unwrap();
        assert!(dir_out.join("series.pvd").is_file() && dir_out.join("step_0001.vtu").is_file());
    }

    #[test]
    fn a_csv_path_gets_every_step_and_node() {
        let dir = temp("csv");
        let path = dir.join("u.csv");
        let mut w = SeriesWriter::create(SeriesTarget::of(&path), Numbering::STEPS).unwrap();
        w.write_step(1, 0.5, &rows()).unwrap();
        w.write_step(2, 1.0, &rows()).unwrap();
        w.finish().unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "step,t,i,j,k,ux,uy,uz");
        assert_eq!(lines.len(), 5);
        assert_eq!(lines[4], "2,1,1,0,0,5e-1,0e0,-1e0");
    }
}
