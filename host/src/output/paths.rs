//! Every output path a command will write, checked before any work is done: none is one of the
//! command's inputs or another of its outputs (`observe s.toml --out s.toml` once overwrote the
//! scenario), and each one's directory exists and takes a new file (`--report
//! /no/such/dir/r.json` once failed only after the whole session).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};

/// The files a command reads and the ones it will write, each with the flag that names it.
#[derive(Debug, Default)]
pub struct Outputs {
    inputs: Vec<(String, PathBuf)>,
    outputs: Vec<(String, PathBuf, Kind)>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    File,
    /// A directory the command creates if missing.
    Directory,
}

/// `path` made absolute and, as far as it exists, free of links and `..`, so that two names of
/// one file compare equal.
fn resolved(path: &Path) -> PathBuf {
    if let Ok(p) = path.canonicalize() {
        return p;
    }
    let absolute = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    match (absolute.parent(), absolute.file_name()) {
        (Some(dir), Some(name)) => dir
            .canonicalize()
            .map_or_else(|_| absolute.clone(), |d| d.join(name)),
        _ => absolute,
    }
}

impl Outputs {
    pub fn new() -> Self {
        Self::default()
    }

    /// A file the command reads (a scenario, an observation file…).
    pub fn input(mut self, flag: &str, path: Option<&Path>) -> Self {
        if let Some(p) = path {
            self.inputs.push((flag.to_string(), p.to_path_buf()));
        }
        self
    }

    /// A file the command writes.
    pub fn file(mut self, flag: &str, path: Option<&Path>) -> Self {
        if let Some(p) = path {
            self.outputs
                .push((flag.to_string(), p.to_path_buf(), Kind::File));
        }
        self
    }

    /// A directory the command writes into (created if missing).
    pub fn directory(mut self, flag: &str, path: Option<&Path>) -> Self {
        if let Some(p) = path {
            self.outputs
                .push((flag.to_string(), p.to_path_buf(), Kind::Directory));
        }
        self
    }

    /// Refuses a clash or an unwritable place, naming the flags.
    pub fn check(&self) -> anyhow::Result<()> {
        for (i, (flag, path, _)) in self.outputs.iter().enumerate() {
            let at = resolved(path);
            if let Some((input, _)) = self.inputs.iter().find(|(_, p)| resolved(p) == at) {
                bail!(
                    "{flag} {}: that is the {input} this command reads; write elsewhere",
                    path.display()
                );
            }
            if let Some((other, _, _)) =
                self.outputs[..i].iter().find(|(_, p, _)| resolved(p) == at)
            {
                bail!(
                    "{flag} {}: {other} writes there too; give each output its own path",
                    path.display()
                );
            }
            self.writable(flag, path, self.outputs[i].2)?;
        }
        Ok(())
    }

    /// The directory `path` goes into exists and takes a new file.
    fn writable(&self, flag: &str, path: &Path, kind: Kind) -> anyhow::Result<()> {
        if path.is_dir() && kind == Kind::File {
            bail!(
                "writing {} ({flag}): it is a directory, not a file",
                path.display()
            );
        }
        let dir = match kind {
            Kind::Directory if path.is_dir() => path.to_path_buf(),
            _ => match path.parent() {
                Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
                _ => PathBuf::from("."),
            },
        };
        if !dir.is_dir() {
            bail!(
                "writing {} ({flag}): the directory {} does not exist",
                path.display(),
                dir.display()
            );
        }
        let probe = dir.join(format!(".deform-probe-{}", std::process::id()));
        std::fs::File::create(&probe)
            .and_then(|_| std::fs::remove_file(&probe))
            .with_context(|| {
                format!(
                    "writing {} ({flag}): cannot create a file in {}",
                    path.display(),
                    dir.display()
                )
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_output_may_be_neither_an_input_nor_another_output_nor_nowhere() {
        let dir = std::env::temp_dir().join(format!("deform-paths-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let scenario = dir.join("s.toml");
        std::fs::write(&scenario, "").unwrap();
        let same = dir.join(".").join("s.toml");
        let e = Outputs::new()
            .input("scenario", Some(&scenario))
            .file("--out", Some(&same))
            .check()
            .unwrap_err();
        assert!(
            e.to_string().contains("the scenario this command reads"),
            "{e}"
        );
        let csv = dir.join("f.csv");
        let e = Outputs::new()
            .file("--frames-csv", Some(&csv))
            .file("--report", Some(&csv))
            .check()
            .unwrap_err();
        assert!(
            e.to_string().contains("--frames-csv writes there too"),
            "{e}"
        );
        let e = Outputs::new()
            .file("--report", Some(&dir.join("no/such/dir/r.json")))
            .check()
            .unwrap_err();
        assert!(e.to_string().contains("does not exist"), "{e}");
        Outputs::new()
            .input("scenario", Some(&scenario))
            .file("--report", Some(&dir.join("r.json")))
            .directory("--out", Some(&dir.join("series")))
            .check()
            .unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
