//! The firmware-log flags, shared by every subcommand that talks to a target (`deform solve`,
//! `deform simulate`, `deform flash`): flatten [`LogFlags`] into a subcommand's clap `Args`.

use std::path::PathBuf;

use clap::{ArgAction, Args};

use crate::firmware_logs::LogLevel;

/// How the target's defmt logs are decoded and which are shown.
#[derive(Debug, Clone, Default, PartialEq, Eq, Args)]
pub struct LogFlags {
    /// The firmware ELF whose defmt table decodes the target's logs. It must be the very build
    /// the target runs (the build ids are compared; another is refused). Default: the ELF that
    /// QEMU booted; with --port, logs are not decoded unless this is given.
    #[arg(help_heading = "Firmware logs", long, value_name = "ELF")]
    pub elf: Option<PathBuf>,

    /// Show the firmware's debug and trace logs too (default: info, warnings and errors).
    #[arg(help_heading = "Firmware logs", short, long, action = ArgAction::Count)]
    pub verbose: u8,
}

impl LogFlags {
    pub fn options(&self) -> LogOptions {
        LogOptions {
            elf: self.elf.clone(),
            min_level: LogLevel::from_verbosity(self.verbose),
        }
    }
}

/// The log flags once parsed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LogOptions {
    /// `None`: the ELF QEMU booted, or no decoding for a port.
    pub elf: Option<PathBuf>,
    pub min_level: LogLevel,
}

impl Default for LogOptions {
    fn default() -> Self {
        LogOptions {
            elf: None,
            min_level: LogLevel::Info,
        }
    }
}
