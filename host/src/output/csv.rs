//! Per-step and per-frame CSV tables: a row type names its columns and gives their values in
//! one place ([`CsvRow::columns`]), so the header and the rows cannot drift apart (the dynamic
//! steps table once had 9 names for 11 columns). [`CsvTable`] streams the rows as a run goes
//! (see [`super::file::StreamedFile`]).

use std::fmt::{self, Display};
use std::io::Write;
use std::path::{Path, PathBuf};

use super::file::StreamedFile;

/// One row of a CSV table.
pub trait CsvRow {
    /// Calls `column(name, value)` for every column, in order.
    fn columns(&self, column: &mut dyn FnMut(&'static str, &dyn Display));

    /// The header line's names, joined.
    fn header(&self) -> String {
        let mut names = Vec::new();
        self.columns(&mut |name, _| names.push(name));
        names.join(",")
    }

    /// The row's values, joined.
    fn line(&self) -> String {
        let mut values = Vec::new();
        self.columns(&mut |_, value| values.push(value.to_string()));
        values.join(",")
    }
}

/// A float in scientific notation (`1.5e-5`), as residuals and errors are written.
pub struct Sci(pub f64);

impl Display for Sci {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:e}", self.0)
    }
}

/// A float with a fixed number of decimals (`{:.N}`).
pub struct Fixed(pub f64, pub usize);

impl Display for Fixed {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:.*}", self.1, self.0)
    }
}

/// A value that may be missing: an empty field then.
pub struct Maybe<T>(pub Option<T>);

impl<T: Display> Display for Maybe<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.0 {
            Some(v) => v.fmt(f),
            None => Ok(()),
        }
    }
}

/// A CSV table written row by row.
#[derive(Debug)]
pub struct CsvTable {
    file: StreamedFile,
}

impl CsvTable {
    /// Creates the table with `template`'s header (the row's values are not written).
    pub fn create(path: &Path, template: &dyn CsvRow) -> anyhow::Result<Self> {
        let mut file = StreamedFile::create(path)?;
        writeln!(file.writer(), "{}", template.header())?;
        file.flush()?;
        Ok(Self { file })
    }

    /// Appends `row`, readable at once.
    pub fn write(&mut self, row: &dyn CsvRow) -> anyhow::Result<()> {
        writeln!(self.file.writer(), "{}", row.line())?;
        self.file.flush()
    }

    pub fn path(&self) -> &Path {
        self.file.path()
    }

    pub fn finish(self) -> anyhow::Result<PathBuf> {
        self.file.finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Row {
        step: u32,
        residual: f64,
        cycles: Option<u64>,
    }

    impl CsvRow for Row {
        fn columns(&self, column: &mut dyn FnMut(&'static str, &dyn Display)) {
            column("step", &self.step);
            column("residual", &Sci(self.residual));
            column("cycles", &Maybe(self.cycles));
        }
    }

    #[test]
    fn the_header_and_the_row_come_from_one_list() {
        let row = Row {
            step: 3,
            residual: 1.5e-5,
            cycles: None,
        };
        assert_eq!(row.header(), "step,residual,cycles");
        assert_eq!(row.line(), "3,1.5e-5,");
        let row = Row {
            cycles: Some(99),
            ..row
        };
        assert_eq!(row.line(), "3,1.5e-5,99");
    }
}
