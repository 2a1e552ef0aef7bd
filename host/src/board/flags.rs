//! The board vocabulary of the command line: every command that talks to a target flattens
//! [`BoardFlags`] (`deform bench`, which sweeps over MVU counts, flattens [`TargetFlags`] and
//! its own list of counts) and gets its board from one method, [`TargetFlags::choice`]. A
//! scenario's `[solver] target` names a [`TargetKind`] too.

use std::path::PathBuf;

use anyhow::bail;
use clap::{ArgAction, Args, ValueEnum};
use serde::Deserialize;

use super::{BoardChoice, DEFAULT_QEMU_HARTS};
use crate::firmware_logs::LogLevel;

/// Where CG runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TargetKind {
    /// Boot the firmware in QEMU (riscv32 `virt`, exact instruction counts, up to 8 harts)
    /// and drive it over its serial pty.
    Qemu,
    /// Load the `litex-vexriscv` firmware into a LiteX SoC with a VexRiscv CPU, simulated cycle
    /// for cycle by Verilator (`cargo xtask setup` and `cargo xtask firmware --board litex`
    /// first; the SoC is built once, ~2 min). One MVU; about 0.8 M cycles per second: keep the
    /// grid small.
    Litex,
    /// The f64 reference on this computer (the thesis's "general purpose computer"): no board.
    Host,
}

impl TargetKind {
    /// The name flags and reports use.
    pub fn name(self) -> &'static str {
        match self {
            TargetKind::Qemu => "qemu",
            TargetKind::Litex => "litex",
            TargetKind::Host => "host",
        }
    }
}

/// Which target: its kind, a real board's port, the firmware to boot and how its logs show.
#[derive(Debug, Clone, Default, PartialEq, Eq, Args)]
pub struct TargetFlags {
    /// Where CG runs: `qemu` boots the firmware under QEMU, `litex` on a simulated LiteX
    /// VexRiscv SoC, `host` uses the f64 reference (no board). With --port: the board on the
    /// port. [default: the scenario's `[solver] target`, else qemu]
    #[arg(long = "target", value_enum, value_name = "qemu|litex|host")]
    pub kind: Option<TargetKind>,

    /// Serial device of a real board running the deform firmware (e.g. /dev/ttyUSB0).
    /// Default: none, boot the --target.
    #[arg(long, value_name = "PATH")]
    pub port: Option<String>,

    /// Firmware ELF for --target qemu or litex. Default: $DEFORM_FIRMWARE, else the release
    /// build in firmware/target (`cargo xtask firmware` builds it); for litex
    /// $DEFORM_LITEX_FIRMWARE, else the `--board litex` build.
    #[arg(long, value_name = "ELF")]
    pub firmware: Option<PathBuf>,

    #[command(flatten)]
    pub logs: LogFlags,
}

/// [`TargetFlags`] and the MVUs the board runs with: what every command but `deform bench`
/// flattens.
#[derive(Debug, Clone, Default, PartialEq, Eq, Args)]
pub struct BoardFlags {
    #[command(flatten)]
    pub target: TargetFlags,

    /// MVUs (harts) to share the matrix–vector product between: QEMU boots this many harts;
    /// a board on --port uses this many of the harts it reports. The simulated LiteX SoC has
    /// one. Default: every hart the target has (QEMU: 8).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u8).range(1..))]
    pub mvus: Option<u8>,
}

impl BoardFlags {
    /// The board these flags name (`None`: the host), `scenario` the kind a scenario file
    /// names; see [`TargetFlags::choice`].
    pub fn choice(&self, scenario: Option<TargetKind>) -> anyhow::Result<Option<BoardChoice>> {
        self.target.choice(self.mvus, scenario)
    }

    /// The kind of target these flags (over `scenario`, over the default qemu) name; a port is
    /// the kind it is given as.
    pub fn kind(&self, scenario: Option<TargetKind>) -> TargetKind {
        self.target.kind(scenario)
    }
}

impl TargetFlags {
    /// `--target` over the scenario's over qemu.
    pub fn kind(&self, scenario: Option<TargetKind>) -> TargetKind {
        self.kind.or(scenario).unwrap_or(TargetKind::Qemu)
    }

    /// The board to open with `mvus` MVUs (`None`: every hart it has), or `None` for the host.
    /// A flag the chosen target cannot honour is refused here, before anything starts.
    pub fn choice(
        &self,
        mvus: Option<u8>,
        scenario: Option<TargetKind>,
    ) -> anyhow::Result<Option<BoardChoice>> {
        let kind = self.kind(scenario);
        if let Some(port) = &self.port {
            if self.kind == Some(TargetKind::Host) {
                bail!("--port names a board, --target host runs on this computer: give one");
            }
            if self.firmware.is_some() {
                bail!(
                    "--firmware boots a simulated board; the board on --port {port} runs its own"
                );
            }
            return Ok(Some(BoardChoice::Port(port.clone())));
        }
        match kind {
            TargetKind::Host => {
                let given: Vec<&str> = [
                    ("--firmware", self.firmware.is_some()),
                    ("--mvus", mvus.is_some()),
                    ("--elf", self.logs.elf.is_some()),
                    ("--verbose", self.logs.verbose > 0),
                ]
                .into_iter()
                .filter_map(|(flag, given)| given.then_some(flag))
                .collect();
                if !given.is_empty() {
                    let verb = if given.len() == 1 {
                        "describes"
                    } else {
                        "describe"
                    };
                    bail!(
                        "{} {verb} a board; --target host runs the f64 reference on this \
                         computer",
                        given.join(", ")
                    );
                }
                Ok(None)
            }
            TargetKind::Qemu => Ok(Some(BoardChoice::Qemu {
                firmware: self.firmware.clone(),
                harts: mvus.unwrap_or(DEFAULT_QEMU_HARTS),
            })),
            TargetKind::Litex => match mvus {
                Some(m) if m > 1 => {
                    bail!("--mvus {m}: the simulated LiteX SoC has one MVU (its one VexRiscv hart)")
                }
                _ => Ok(Some(BoardChoice::Litex {
                    firmware: self.firmware.clone(),
                })),
            },
        }
    }

    /// The report's name for where the frames ran: `qemu`, `litex`, `host`, or `port`.
    pub fn report_name(&self, scenario: Option<TargetKind>) -> &'static str {
        match (&self.port, self.kind(scenario)) {
            (Some(_), _) => "port",
            (None, kind) => kind.name(),
        }
    }
}

/// How the target's defmt logs are decoded and which are shown.
#[derive(Debug, Clone, Default, PartialEq, Eq, Args)]
pub struct LogFlags {
    /// The firmware ELF whose defmt table decodes the target's logs. It must be the very build
    /// the target runs (the build ids are compared; another is refused). Default: the ELF that
    /// QEMU or the LiteX SoC booted; with --port, logs are not decoded unless this is given.
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

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(flatten)]
        board: BoardFlags,
    }

    fn choice(argv: &[&str]) -> anyhow::Result<Option<BoardChoice>> {
        let argv = std::iter::once("deform").chain(argv.iter().copied());
        Cli::try_parse_from(argv).unwrap().board.choice(None)
    }

    #[test]
    fn one_method_yields_every_board_and_refuses_what_a_target_cannot_honour() {
        assert!(matches!(
            choice(&[]).unwrap(),
            Some(BoardChoice::Qemu {
                harts: 8,
                firmware: None
            })
        ));
        assert!(matches!(
            choice(&["--mvus", "2"]).unwrap(),
            Some(BoardChoice::Qemu { harts: 2, .. })
        ));
        assert!(matches!(
            choice(&["--target", "litex"]).unwrap(),
            Some(BoardChoice::Litex { .. })
        ));
        assert!(matches!(
            choice(&["--port", "/dev/ttyUSB0"]).unwrap(),
            Some(BoardChoice::Port(p)) if p == "/dev/ttyUSB0"
        ));
        assert!(choice(&["--target", "host"]).unwrap().is_none());
        for (argv, needle) in [
            (&["--target", "host", "--mvus", "2"][..], "--mvus"),
            (&["--target", "host", "--firmware", "f.elf"], "--firmware"),
            (&["--target", "host", "-v"], "--verbose"),
            (&["--target", "host", "--port", "/dev/x"], "--port"),
            (&["--target", "litex", "--mvus", "4"], "one MVU"),
        ] {
            let e = choice(argv).unwrap_err().to_string();
            assert!(e.contains(needle), "{argv:?}: {e}");
        }
    }

    #[test]
    fn a_scenario_names_any_target_and_the_flag_wins() {
        let kind: TargetKind =
            toml::from_str::<std::collections::HashMap<String, TargetKind>>("t = \"litex\"")
                .unwrap()["t"];
        assert_eq!(kind, TargetKind::Litex);
        let cli = Cli::try_parse_from(["deform"]).unwrap();
        assert_eq!(cli.board.kind(Some(kind)), TargetKind::Litex);
        let cli = Cli::try_parse_from(["deform", "--target", "host"]).unwrap();
        assert_eq!(cli.board.kind(Some(kind)), TargetKind::Host);
    }
}
