//! The firmware's defmt logs on the host: decoded against the firmware ELF and printed with their
//! level and source location.
//!
//! The target encodes each log call as a defmt frame (an index into the string table that only
//! the ELF holds, then the arguments; rzcobs-framed) and ships the frames in `Response::Log`
//! notices (see `firmware/src/logger.rs`). [`FirmwareElf`] reads the ELF's defmt table, the
//! DWARF locations of the log calls and its GNU build id; [`FirmwareLogs`] feeds the received
//! bytes to defmt-decoder's stream decoder and prints what is at or above the chosen level.
//!
//! A table from another build would print wrong messages without any error, so the ELF is used
//! only once its build id equals the one the firmware reported in `Hello`
//! ([`FirmwareElf::check_build_id`]). Until then the bytes wait.

use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use defmt_decoder::{DecodeError, Locations, StreamDecoder, Table};
use deform_shared::protocol::Response;
use indicatif::ProgressBar;
use object::Object;

/// A log frame's level, in increasing severity.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum LogLevel {
    Trace,
    Debug,
    Info,
    Warn,
    Error,
}

impl LogLevel {
    /// What `-v` given `count` times shows: info and up by default, debug and trace with `-v`
    /// (`-vv` changes nothing more: trace is the floor).
    pub fn from_verbosity(count: u8) -> LogLevel {
        match count {
            0 => LogLevel::Info,
            _ => LogLevel::Trace,
        }
    }

    fn from_defmt(name: &str) -> LogLevel {
        match name {
            "trace" => LogLevel::Trace,
            "debug" => LogLevel::Debug,
            "warn" => LogLevel::Warn,
            "error" => LogLevel::Error,
            _ => LogLevel::Info,
        }
    }
}

impl fmt::Display for LogLevel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.pad(match self {
            LogLevel::Trace => "TRACE",
            LogLevel::Debug => "DEBUG",
            LogLevel::Info => "INFO",
            LogLevel::Warn => "WARN",
            LogLevel::Error => "ERROR",
        })
    }
}

/// One decoded log line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LogLine {
    pub level: LogLevel,
    pub message: String,
    /// `file:line` of the log call, when the ELF's debug info has it.
    pub location: Option<String>,
}

impl fmt::Display for LogLine {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "firmware {:<5} {}", self.level, self.message)?;
        if let Some(location) = &self.location {
            write!(f, "  ({location})")?;
        }
        Ok(())
    }
}

#[derive(Debug, thiserror::Error)]
pub enum LogError {
    #[error("cannot read the firmware ELF {}: {source}", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{} is not a firmware ELF with a defmt table: {reason}", path.display())]
    NoTable { path: PathBuf, reason: String },
    #[error(
        "{} is not the firmware the target runs: its build id is {elf}, the target reports \
         {target}. Its log table would decode the target's logs into wrong messages. Pass the \
         ELF that was flashed (--elf), or flash this one (`deform flash`)",
        path.display()
    )]
    BuildIdMismatch {
        path: PathBuf,
        elf: String,
        target: String,
    },
}

/// A firmware ELF's defmt table, log locations and build id.
pub struct FirmwareElf {
    path: PathBuf,
    /// Leaked once per process: the stream decoder borrows the table for as long as logs arrive.
    table: &'static Table,
    locations: Locations,
    build_id: Option<Vec<u8>>,
}

impl FirmwareElf {
    pub fn load(path: &Path) -> Result<FirmwareElf, LogError> {
        let data = std::fs::read(path).map_err(|source| LogError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let no_table = |reason: String| LogError::NoTable {
            path: path.to_path_buf(),
            reason,
        };
        let table = Table::parse(&data)
            .map_err(|e| no_table(format!("{e:#}")))?
            .ok_or_else(|| no_table("it has no .defmt section".into()))?;
        // Without debug info the lines still decode, only without file:line.
        let locations = table.get_locations(&data).unwrap_or_default();
        let build_id = object::File::parse(&*data)
            .ok()
            .and_then(|elf| elf.build_id().ok().flatten().map(<[u8]>::to_vec));
        Ok(FirmwareElf {
            path: path.to_path_buf(),
            table: Box::leak(Box::new(table)),
            locations,
            build_id,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn build_id(&self) -> Option<&[u8]> {
        self.build_id.as_deref()
    }

    /// Accepts the ELF only if its build id is the running firmware's.
    pub fn check_build_id(&self, target: &[u8]) -> Result<(), LogError> {
        if self.build_id.as_deref() == Some(target) {
            return Ok(());
        }
        Err(LogError::BuildIdMismatch {
            path: self.path.clone(),
            elf: self
                .build_id
                .as_deref()
                .map_or_else(|| "missing".to_string(), crate::flash::hex),
            target: if target.is_empty() {
                "none".to_string()
            } else {
                crate::flash::hex(target)
            },
        })
    }
}

/// Counts of what arrived, for summaries and tests.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LogStats {
    /// Log bytes received (inside `Log` notices).
    pub bytes: u64,
    /// Frames decoded (all levels, printed or not).
    pub frames: u64,
    /// Bytes the target dropped because its log buffer was full.
    pub dropped_bytes: u64,
    /// `Log` notices that never arrived (gaps in the notice numbers).
    pub lost_notices: u64,
    /// Stretches of bytes that did not decode.
    pub malformed: u64,
}

/// Where decoded lines go.
pub type LineSink = Box<dyn FnMut(&LogLine) + Send>;

/// Decodes the `Log` notices of one target and prints (or collects) the lines.
pub struct FirmwareLogs {
    elf: Option<FirmwareElf>,
    decoder: Option<Box<dyn StreamDecoder + Send + Sync>>,
    /// Bytes received before the ELF was accepted.
    waiting: Vec<u8>,
    min_level: LogLevel,
    sink: LineSink,
    progress: Option<ProgressBar>,
    stats: LogStats,
    last_notice: Option<u16>,
    /// Told once that logs arrive but no ELF decodes them.
    told_no_elf: bool,
}

impl FirmwareLogs {
    /// Logs decoded with `elf` (once [`accept`](Self::accept)ed), lines at or above `min_level`
    /// given to `sink`.
    pub fn new(elf: Option<FirmwareElf>, min_level: LogLevel, sink: LineSink) -> Self {
        FirmwareLogs {
            elf,
            decoder: None,
            waiting: Vec::new(),
            min_level,
            sink,
            progress: None,
            stats: LogStats::default(),
            last_notice: None,
            told_no_elf: false,
        }
    }

    /// Lines printed on stderr, the progress bar (if any) suspended meanwhile.
    pub fn printing(elf: Option<FirmwareElf>, min_level: LogLevel) -> Self {
        FirmwareLogs::new(elf, min_level, Box::new(|line| eprintln!("{line}")))
    }

    /// Shares `self` for a link's notice handler and the command that prints around it.
    pub fn shared(self) -> Arc<Mutex<FirmwareLogs>> {
        Arc::new(Mutex::new(self))
    }

    /// While set, lines are printed with this bar suspended, so they do not tear it.
    pub fn set_progress(&mut self, bar: Option<ProgressBar>) {
        self.progress = bar;
    }

    pub fn stats(&self) -> LogStats {
        self.stats
    }

    /// Checks the ELF against the build id the firmware reported and, if it matches, decodes
    /// whatever arrived so far. Without an ELF there is nothing to check.
    pub fn accept(&mut self, target_build_id: &[u8]) -> Result<(), LogError> {
        let Some(elf) = &self.elf else {
            return Ok(());
        };
        elf.check_build_id(target_build_id)?;
        self.decoder = Some(elf.table.new_stream_decoder());
        let waiting = std::mem::take(&mut self.waiting);
        self.decode(&waiting);
        Ok(())
    }

    /// A notice from the link: `Log` bytes are decoded, anything else ignored.
    pub fn notice(&mut self, seq: u16, body: &Response) {
        let Response::Log { dropped, frames } = body else {
            return;
        };
        if let Some(last) = self.last_notice {
            self.stats.lost_notices += u64::from(seq.wrapping_sub(last).saturating_sub(1));
        }
        self.last_notice = Some(seq);
        self.receive(*dropped, frames);
    }

    /// Log bytes as they came from the target, and how many it dropped before them.
    pub fn receive(&mut self, dropped: u32, bytes: &[u8]) {
        self.stats.bytes += bytes.len() as u64;
        if dropped > 0 {
            self.stats.dropped_bytes += u64::from(dropped);
            self.emit(LogLine {
                level: LogLevel::Warn,
                message: format!(
                    "{dropped} bytes of log were dropped: the target's log buffer was full"
                ),
                location: None,
            });
        }
        if self.decoder.is_some() {
            self.decode(bytes);
        } else if self.elf.is_some() {
            self.waiting.extend_from_slice(bytes);
        } else if !self.told_no_elf && !bytes.is_empty() {
            self.told_no_elf = true;
            self.emit(LogLine {
                level: LogLevel::Info,
                message: "the firmware logs, but without its ELF (--elf) they cannot be decoded"
                    .into(),
                location: None,
            });
        }
    }

    fn decode(&mut self, bytes: &[u8]) {
        let Some(decoder) = self.decoder.as_mut() else {
            return;
        };
        decoder.received(bytes);
        let Some(elf) = &self.elf else { return };
        let mut lines = Vec::new();
        loop {
            match decoder.decode() {
                Ok(frame) => {
                    self.stats.frames += 1;
                    let level = frame
                        .level()
                        .map_or(LogLevel::Info, |l| LogLevel::from_defmt(l.as_str()));
                    let location = elf
                        .locations
                        .get(&frame.index())
                        .map(|l| format!("{}:{}", shorten(&l.file).display(), l.line));
                    lines.push(LogLine {
                        level,
                        message: frame.display_message().to_string(),
                        location,
                    });
                }
                Err(DecodeError::UnexpectedEof) => break,
                // The rzcobs decoder has skipped the bad frame; go on with the next.
                Err(DecodeError::Malformed) => self.stats.malformed += 1,
            }
        }
        for line in lines {
            self.emit(line);
        }
    }

    fn emit(&mut self, line: LogLine) {
        if line.level < self.min_level {
            return;
        }
        let sink = &mut self.sink;
        match &self.progress {
            Some(bar) => bar.suspend(|| sink(&line)),
            None => sink(&line),
        }
    }
}

/// A source path relative to the current directory when it lies below it (the DWARF paths are
/// absolute), so that lines read `firmware/src/main.rs:42`.
fn shorten(path: &Path) -> &Path {
    std::env::current_dir()
        .ok()
        .and_then(|cwd| path.strip_prefix(cwd).ok())
        .unwrap_or(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn collecting(min_level: LogLevel) -> (FirmwareLogs, Arc<Mutex<Vec<LogLine>>>) {
        let lines = Arc::new(Mutex::new(Vec::new()));
        let sink = Arc::clone(&lines);
        let logs = FirmwareLogs::new(
            None,
            min_level,
            Box::new(move |line| sink.lock().unwrap().push(line.clone())),
        );
        (logs, lines)
    }

    #[test]
    fn verbosity_picks_the_floor() {
        assert_eq!(LogLevel::from_verbosity(0), LogLevel::Info);
        assert_eq!(LogLevel::from_verbosity(1), LogLevel::Trace);
        assert!(LogLevel::Trace < LogLevel::Debug && LogLevel::Warn < LogLevel::Error);
        assert_eq!(format!("{:<5}|", LogLevel::Warn), "WARN |");
    }

    #[test]
    fn dropped_bytes_and_lost_notices_are_reported_and_undecodable_logs_said_once() {
        let (mut logs, lines) = collecting(LogLevel::Info);
        let log = |dropped, frames: &[u8]| Response::Log {
            dropped,
            frames: frames.try_into().unwrap(),
        };
        logs.notice(7, &log(0, &[1, 2, 0]));
        logs.notice(8, &log(120, &[3, 0]));
        logs.notice(11, &log(0, &[4, 0]));
        logs.notice(12, &Response::Ack); // not a log: ignored
        let stats = logs.stats();
        assert_eq!(stats.bytes, 7);
        assert_eq!(stats.dropped_bytes, 120);
        assert_eq!(stats.lost_notices, 2);
        let lines = lines.lock().unwrap();
        assert_eq!(lines.len(), 2, "{lines:#?}");
        assert!(lines[0].message.contains("--elf"), "{}", lines[0]);
        assert_eq!(lines[1].level, LogLevel::Warn);
        assert!(lines[1]
            .message
            .starts_with("120 bytes of log were dropped"));
    }

    #[test]
    fn an_elf_without_a_defmt_table_is_refused_by_name() {
        let path = std::env::temp_dir().join(format!("deform-no-table-{}", std::process::id()));
        std::fs::write(&path, b"\x7fELF but not really").unwrap();
        let err = FirmwareElf::load(&path).err().unwrap();
        std::fs::remove_file(&path).ok();
        assert!(matches!(err, LogError::NoTable { .. }), "{err}");
        assert!(err.to_string().contains("deform-no-table"), "{err}");
        let missing = FirmwareElf::load(Path::new("/nonexistent/fw.elf"))
            .err()
            .unwrap();
        assert!(matches!(missing, LogError::Read { .. }), "{missing}");
    }
}
