//! How every output file is written so that no reader, and no interrupted run, finds half a
//! file: a whole file goes to a temporary name beside it and is renamed over the real name
//! once complete ([`write_atomic`]); a file written row by row as a run goes
//! ([`StreamedFile`]) grows under its temporary name, every row flushed, and takes its real
//! name when the run finishes (also when it is interrupted, see [`crate::interrupt`]).

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::Context;

/// The temporary name `path` is written under: `.NAME.part` in the same directory, so that the
/// rename cannot cross a file system.
pub fn part_path(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map_or_else(|| "output".into(), |n| n.to_string_lossy().into_owned());
    path.with_file_name(format!(".{name}.part"))
}

/// Writes `path` whole or not at all (see the module doc).
pub fn write_atomic(
    path: &Path,
    write: impl FnOnce(&mut BufWriter<File>) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    let part = part_path(path);
    let written = (|| {
        let file = File::create(&part).with_context(|| format!("creating {}", path.display()))?;
        let mut out = BufWriter::new(file);
        write(&mut out)?;
        out.flush()?;
        std::fs::rename(&part, path).with_context(|| format!("renaming {}", part.display()))
    })();
    if written.is_err() {
        let _ = std::fs::remove_file(&part);
    }
    written.with_context(|| format!("writing {}", path.display()))
}

/// A file written as a run goes: under its temporary name, each [`StreamedFile::flush`]ed
/// piece readable at once, renamed to its real name by [`StreamedFile::finish`].
#[derive(Debug)]
pub struct StreamedFile {
    path: PathBuf,
    part: PathBuf,
    out: BufWriter<File>,
}

impl StreamedFile {
    pub fn create(path: &Path) -> anyhow::Result<Self> {
        let part = part_path(path);
        let file = File::create(&part).with_context(|| format!("creating {}", path.display()))?;
        Ok(Self {
            path: path.to_path_buf(),
            part,
            out: BufWriter::new(file),
        })
    }

    pub fn writer(&mut self) -> &mut BufWriter<File> {
        &mut self.out
    }

    /// Makes what was written so far readable in the temporary file.
    pub fn flush(&mut self) -> anyhow::Result<()> {
        self.out
            .flush()
            .with_context(|| format!("writing {}", self.part.display()))
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Flushes and gives the file its real name; returns it.
    pub fn finish(mut self) -> anyhow::Result<PathBuf> {
        self.flush()?;
        std::fs::rename(&self.part, &self.path).with_context(|| {
            format!(
                "renaming {} to {}",
                self.part.display(),
                self.path.display()
            )
        })?;
        Ok(self.path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_appears_whole_or_not_at_all() {
        let dir = std::env::temp_dir().join(format!("deform-file-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("r.json");
        let failed = write_atomic(&path, |out| {
            writeln!(out, "{{")?;
            anyhow::bail!("the work failed half-way")
        });
        assert!(failed.is_err());
        assert!(!path.exists() && !part_path(&path).exists());
        write_atomic(&path, |out| Ok(writeln!(out, "{{}}")?)).unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "{}\n");

        let csv = dir.join("f.csv");
        let mut streamed = StreamedFile::create(&csv).unwrap();
        writeln!(streamed.writer(), "a,b").unwrap();
        streamed.flush().unwrap();
        assert!(!csv.exists());
        assert_eq!(std::fs::read_to_string(part_path(&csv)).unwrap(), "a,b\n");
        assert_eq!(streamed.finish().unwrap(), csv);
        assert_eq!(std::fs::read_to_string(&csv).unwrap(), "a,b\n");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
