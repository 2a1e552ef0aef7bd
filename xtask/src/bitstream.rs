//! `cargo xtask bitstream`: deform's SoC with 0 to 8 hardware MVUs built for an ECP5 board
//! (gateware/deform_gateware/bitstream.py through hil-sim's gateware module), and the report of
//! every build: resources, Fmax, the Fmax lost against the SoC without MVUs, Fig. 5-1.
//!
//! The report in `target/bitstream/BOARD/` gathers builds across runs, one row per MVU count,
//! seed and depth (Yosys only, placed only, or placed and routed), each with the gateware commit
//! it built:
//! the SoCs are built one at a time and a big one takes long, so a sweep is often several runs,
//! and a second seed is a row beside the first, not in its place. It is rewritten after each
//! build, whole or not at all, so an interrupted sweep keeps the builds it finished.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use deform_hil_sim::gateware::{
    build_bitstream, check_synthesis_venv, Router, SocBuild, SocReport,
};
use deform_hil_sim::litex::{litex_dir, MAX_MVUS};
use deform_host::output::file::write_atomic;

/// The boards `bitstream` builds for.
pub const BOARDS: &[&str] = &["ulx3s"];
/// The MVU counts a sweep builds by default: 0 is the Fmax comparison's baseline.
const DEFAULT_MVUS: &[u32] = &[0, 1, 2, 4, 8];
/// The rows of p and Kp per MVU a build may ask for: bitstream.py's `NODES`, which a test
/// holds this copy to.
const NODES: [u32; 2] = [512, 1024];
/// Every how many rows of logic tiles one is held free while placing, by default:
/// bitstream.py's `KEEP_OUT`, which a test holds this copy to.
const KEEP_OUT: u32 = 3;
/// An LFE5U-85F's MULT18X18D, for the plot when no build was placed.
const LFE5U_85F_MULTIPLIERS: u64 = 156;

pub const USAGE: &str = "\
  bitstream --board ulx3s [--mvus 0,1,2,4,8] [--seed N] [--router router1|router2]
            [--nodes 512|1024] [--keep-out N] [--global-reset] [--no-bus-bursting]
            [--no-pnr | --place-only | --report-only]
                     build deform's SoC with each number of hardware MVUs, one at a time,
                     into an ECP5 bitstream (YoWASP Yosys, nextpnr-ecp5, ecppack; each stage
                     printed with its time) in target/bitstream/BOARD-<N>mvu/, and gather the
                     resources, Fmax and Fig. 5-1 plot of every build so far in
                     target/bitstream/BOARD/ (report.md, report.json,
                     multipliers_per_mvu.svg). --seed: nextpnr's (default 1); --router:
                     nextpnr's (default router1, nextpnr's own; router2 is faster,
                     with a lower Fmax; each build is compared with the 0-MVU
                     baseline of the same router); --nodes: each MVU's rows of p
                     and Kp (default 1024 up to 4 MVUs, else 512; at 512 Kp and
                     p's row copy take the block RAM's 36-bit mode: 24 DP16KD per
                     MVU, not 32; the firmware runs a larger model's MVU phase in
                     software, as the SoC's rows say); --keep-out N: place
                     with every N-th row of logic tiles held free by locked
                     filler cells, deleted before routing, so that nextpnr
                     spreads the SoC over the device, and route with router2's
                     bounding box widened to 8 tiles (default 3; 0: nextpnr's
                     own flow in one run, which packs a 4-MVU SoC too densely
                     to route; such builds are marked and compared only with
                     their like); --global-reset: the
                     MVU array's reset through a DCCA onto a global network,
                     as the clocks go, not through the general routing (19,127
                     flip-flops at 4 MVUs; 12,609 fewer arcs to route, and
                     still not routed in session 12: docs/PERFORMANCE.md); the
                     report marks such builds and compares them only with
                     their like; --no-bus-bursting: the SoC without
                     Wishbone burst cycles (LiteX's bus_bursting off; the
                     simulated SoC and the default build have them), to
                     measure what they cost; marked and compared likewise;
                     --no-pnr:
                     stop after Yosys (cell counts only: no Fmax, no bitstream);
                     --place-only: pack and place, do not route (nextpnr's
                     --no-route): the placement settles whether the SoC fits
                     and gives nextpnr's Fmax estimate after placement, where
                     routing a 4-MVU SoC took over an hour here and did not
                     finish; the report labels that figure an estimate, not
                     a routed Fmax (no bitstream; --router does not apply);
                     --report-only: build nothing, rewrite report.md and the plot from
                     report.json";

/// What the command line asks for.
#[derive(Debug, PartialEq, Eq)]
pub enum Request {
    Help,
    Build(Sweep),
    /// Rewrite report.md and the plot from the gathered report.json.
    Report {
        board: String,
    },
}

/// One SoC build per MVU count, otherwise alike.
#[derive(Debug, PartialEq, Eq)]
pub struct Sweep {
    pub mvus: Vec<u32>,
    /// Each build as asked; its `mvus` is each count of the sweep in turn.
    pub soc: SocBuild,
}

impl Sweep {
    fn build(&self, mvus: u32) -> SocBuild {
        SocBuild {
            mvus,
            ..self.soc.clone()
        }
    }
}

/// Parses `bitstream`'s arguments (those after the command's name).
pub fn parse(args: &[String]) -> Result<Request> {
    let mut board = None;
    let mut mvus = DEFAULT_MVUS.to_vec();
    let mut seed = 1;
    let mut router = None;
    let mut no_pnr = false;
    let mut place_only = false;
    let mut nodes = None;
    let mut report_only = false;
    let mut global_reset = false;
    let mut bus_bursting = true;
    let mut keep_out = None;
    let mut it = args.iter();
    while let Some(flag) = it.next() {
        let mut value = || {
            it.next()
                .with_context(|| format!("bitstream: {flag} needs a value\n\n{USAGE}"))
        };
        match flag.as_str() {
            "-h" | "--help" => return Ok(Request::Help),
            "--no-pnr" => no_pnr = true,
            "--place-only" => place_only = true,
            "--report-only" => report_only = true,
            "--global-reset" => global_reset = true,
            "--no-bus-bursting" => bus_bursting = false,
            "--board" => board = Some(value()?.clone()),
            "--mvus" => mvus = parse_mvus(value()?)?,
            "--seed" => {
                let value = value()?;
                seed = value
                    .parse()
                    .with_context(|| format!("--seed takes a number, not `{value}`"))?;
            }
            "--router" => router = Some(value()?.parse().map_err(anyhow::Error::msg)?),
            "--keep-out" => {
                let value = value()?;
                match value.parse() {
                    Ok(n) if n != 1 => keep_out = Some(n),
                    _ => bail!(
                        "--keep-out {value}: 0 (no rows held) or every N-th row, N at least 2"
                    ),
                }
            }
            "--nodes" => {
                let value = value()?;
                match value.parse() {
                    Ok(n) if NODES.contains(&n) => nodes = Some(n),
                    _ => bail!(
                        "--nodes {value}: the MVUs are built with {} rows of p and Kp",
                        NODES.map(|n| n.to_string()).join(" or ")
                    ),
                }
            }
            other => bail!("bitstream does not take `{other}`\n\n{USAGE}"),
        }
    }
    let board = board.with_context(|| format!("bitstream needs --board\n\n{USAGE}"))?;
    if !BOARDS.contains(&board.as_str()) {
        bail!(
            "--board {board}: the bitstream builds for {} only",
            BOARDS.join(", ")
        );
    }
    if report_only {
        if no_pnr
            || place_only
            || nodes.is_some()
            || global_reset
            || !bus_bursting
            || keep_out.is_some()
        {
            bail!(
                "--report-only builds nothing: --no-pnr, --place-only, --nodes, --keep-out, \
                 --global-reset and --no-bus-bursting do not go with it"
            );
        }
        return Ok(Request::Report { board });
    }
    if place_only && no_pnr {
        bail!("--place-only places after Yosys; --no-pnr stops before: one or the other");
    }
    if place_only && router.is_some() {
        bail!("--place-only does not route: --router does not go with it");
    }
    Ok(Request::Build(Sweep {
        mvus,
        soc: SocBuild {
            board,
            mvus: 0,
            seed,
            router: router.unwrap_or_default(),
            nodes,
            no_pnr,
            place_only,
            global_reset,
            bus_bursting,
            keep_out: keep_out.unwrap_or(KEEP_OUT),
        },
    }))
}

/// `0,4,8`: MVU counts from 0 to [`MAX_MVUS`], each once.
fn parse_mvus(value: &str) -> Result<Vec<u32>> {
    let mut mvus = Vec::new();
    for item in value.split(',') {
        let n: u32 = item.trim().parse().with_context(|| {
            format!("--mvus takes MVU counts separated by commas (0,4), not `{value}`")
        })?;
        if n > u32::from(MAX_MVUS) {
            bail!("--mvus {n}: the MVU array has at most {MAX_MVUS} MVUs");
        }
        if mvus.contains(&n) {
            bail!("--mvus {value}: {n} is there twice");
        }
        mvus.push(n);
    }
    Ok(mvus)
}

/// Runs `cargo xtask bitstream ARGS`.
pub fn run(args: &[String], workspace: &Path) -> Result<()> {
    let sweep = match parse(args)? {
        Request::Help => {
            println!("usage: cargo xtask\n{USAGE}");
            return Ok(());
        }
        Request::Report { board } => {
            let dir = workspace.join("target/bitstream").join(&board);
            let builds = read_builds(&dir.join("report.json"))?;
            if builds.is_empty() {
                bail!("{} has no builds yet", dir.join("report.json").display());
            }
            write_reports(&dir, &board, &builds)?;
            print!("{}", markdown(&board, &builds));
            return Ok(());
        }
        Request::Build(sweep) => sweep,
    };
    check_synthesis_venv(&litex_dir())?;
    let board = &sweep.soc.board;
    let dir = workspace.join("target/bitstream").join(board);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    // Fail before the first build, not an hour in, if the gathered report cannot be read.
    let mut builds = read_builds(&dir.join("report.json"))?;
    for (i, &n) in sweep.mvus.iter().enumerate() {
        let build = sweep.build(n);
        let out = build_dir(workspace, &build);
        eprintln!(
            "\n==> [{}/{}] {board}: the SoC with {}, seed {}{} ({})",
            i + 1,
            sweep.mvus.len(),
            describe(&build),
            build.seed,
            if build.no_pnr {
                ", Yosys only".to_string()
            } else if build.place_only {
                ", placed only (not routed)".to_string()
            } else {
                format!(", {}", build.router)
            },
            out.display()
        );
        let started = Instant::now();
        let report =
            build_bitstream(&build, &out).with_context(|| format!("building the {n}-MVU SoC"))?;
        eprintln!("    built in {:.0?}", started.elapsed());
        // Read again: another run may have added builds meanwhile.
        builds = read_builds(&dir.join("report.json"))?;
        record(&mut builds, report);
        write_reports(&dir, board, &builds)?;
    }
    print!("\n{}", markdown(board, &builds));
    eprintln!("report: {}", dir.join("report.md").display());
    Ok(())
}

/// "4 MVU(s) of 512 rows, its reset on a global network, without bus bursting".
fn describe(build: &SocBuild) -> String {
    let mut text = format!("{} MVU(s)", build.mvus);
    if let Some(rows) = build.nodes {
        text += &format!(" of {rows} rows");
    }
    if build.global_reset {
        text += ", its reset on a global network";
    }
    if !build.bus_bursting {
        text += ", without bus bursting";
    }
    if build.keep_out != KEEP_OUT {
        text += &format!(", {}", keep_out_mark(build.keep_out));
    }
    text
}

/// The builds gathered so far (none if there is no report yet).
fn read_builds(path: &Path) -> Result<Vec<SocReport>> {
    match std::fs::read_to_string(path) {
        Ok(text) => serde_json::from_str(&text).with_context(|| {
            format!(
                "{} is not a report of this version: delete it to start a new one",
                path.display()
            )
        }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Vec::new()),
        Err(e) => Err(e).with_context(|| format!("reading {}", path.display())),
    }
}

/// How far a build went, in the report's order: Yosys only, placed only (`--place-only`), placed
/// and routed, the last by its router (a build that did not route has none).
fn depth(r: &SocReport) -> (u8, Option<Router>) {
    match &r.pnr {
        None => (0, None),
        Some(p) if !p.routed => (1, None),
        Some(_) => (2, Some(r.router)),
    }
}

/// What makes two SoCs of the same MVU count different designs, whose builds are kept and
/// compared apart: the MVU array's reset network, the bus (bursting or not) and the rows kept
/// out while placing.
fn kind(r: &SocReport) -> (bool, bool, u32) {
    (r.global_reset, r.bus_bursting, r.keep_out)
}

/// "every 4th row kept out while placing": what marks a build whose keep-out rows are not the
/// default.
fn keep_out_mark(keep_out: u32) -> String {
    match keep_out {
        0 => "no keep-out rows, nextpnr's own flow".into(),
        n => format!("every {n}th row kept out while placing"),
    }
}

/// Adds `report` to `builds`, in place of an earlier build of the same count, seed, rows per MVU,
/// reset network, bus and depth (and router, for a routed build).
fn record(builds: &mut Vec<SocReport>, report: SocReport) {
    let key = |r: &SocReport| (r.mvus, r.seed, r.nodes, kind(r), depth(r));
    builds.retain(|b| key(b) != key(&report));
    builds.push(report);
    builds.sort_by_key(key);
}

/// report.json, report.md and the Fig. 5-1 plot, each whole or not at all.
fn write_reports(dir: &Path, board: &str, builds: &[SocReport]) -> Result<()> {
    write_atomic(&dir.join("report.json"), |out| {
        Ok(serde_json::to_writer_pretty(out, builds)?)
    })?;
    write_atomic(&dir.join("report.md"), |out| {
        Ok(std::io::Write::write_all(
            out,
            markdown(board, builds).as_bytes(),
        )?)
    })?;
    plot(dir, builds)
}

/// Fig. 5-1: Yosys's MULT18X18D per MVU count (the same for every seed), drawn in a scratch
/// folder and renamed into `dir` once both files are whole (the plot code writes in place).
fn plot(dir: &Path, builds: &[SocReport]) -> Result<()> {
    let mut points: Vec<(f64, f64)> = Vec::new();
    for b in builds {
        let x = f64::from(b.mvus);
        if !points.iter().any(|&(m, _)| m == x) {
            points.push((x, b.yosys.mult18x18d as f64));
        }
    }
    let available = builds
        .iter()
        .find_map(|b| b.pnr.as_ref().map(|p| p.mult18x18d.available))
        .unwrap_or(LFE5U_85F_MULTIPLIERS);
    let scratch = dir.join(".plot.part");
    let _ = std::fs::remove_dir_all(&scratch);
    std::fs::create_dir_all(&scratch)?;
    let files = deform_host::bench::plots::multipliers_per_mvu(&points, available as f64, &scratch);
    let moved = files.and_then(|files| {
        files.iter().try_for_each(|f| {
            let name = f.file_name().context("a plot without a name")?;
            Ok(std::fs::rename(f, dir.join(name))?)
        })
    });
    let _ = std::fs::remove_dir_all(&scratch);
    moved.context("drawing multipliers_per_mvu")
}

/// The report's table: Yosys's cells, nextpnr's use and Fmax, the Fmax against the SoC without
/// MVUs placed with the same seed and routed by the same router, each stage's time, the
/// gateware built. A build placed and not routed shows nextpnr's estimate after placement,
/// labelled so, compared only with a 0-MVU build placed and not routed likewise.
pub fn markdown(board: &str, builds: &[SocReport]) -> String {
    let mut md = format!(
        "# deform's SoC on the {board} (LFE5U-85F, speed grade 6), synthesised\n\n\
         Yosys's cells (LUT4 and CCU2C apart; nextpnr counts both as TRELLIS_COMB), nextpnr's \
         use of the device and the system clock's Fmax (asked: 50 MHz). \"vs. 0 MVUs\": the \
         Fmax against the SoC without MVUs placed with the same seed and routed by the same \
         router, with the MVU array's reset on the same network (in the fabric, or on a \
         global one), the same bus (bursting, or not) and the same rows of logic tiles held \
         free while placing (every 3rd by default): the gateware column marks the \
         exceptions; for a build placed and not routed \
         (--place-only), nextpnr's estimate after \
         placement, against the SoC without MVUs placed likewise: an estimate, not a routed \
         Fmax.\n\n\
         | MVUs | seed | router | LUT4 | CCU2C | FF | MULT18X18D | DP16KD | placed: COMB / FF / DP16KD of the device | Fmax (MHz) | vs. 0 MVUs | words / tiles / rows per MVU | stages (s) | gateware |\n\
         |---:|---:|---|---:|---:|---:|---:|---:|---|---:|---:|---|---|---|\n"
    );
    for b in builds {
        let y = &b.yosys;
        let baseline = builds
            .iter()
            .find(|r| {
                r.mvus == 0
                    && r.seed == b.seed
                    && kind(r) == kind(b)
                    && r.pnr.is_some()
                    && depth(r) == depth(b)
            })
            .and_then(|r| r.pnr.as_ref());
        let (placed, fmax, versus) = match (&b.pnr, baseline) {
            (None, _) => ("—".into(), "not placed (Yosys only)".into(), "—".into()),
            (Some(p), base) => (
                format!(
                    "{} / {} / {} of {} / {} / {}{}",
                    p.lut4.used,
                    p.ff.used,
                    p.dp16kd.used,
                    p.lut4.available,
                    p.ff.available,
                    p.dp16kd.available,
                    if p.fits { "" } else { " (does not fit)" }
                ),
                if p.routed {
                    format!("{:.1}", p.fmax_mhz)
                } else {
                    format!("{:.1} (estimate after placement; not routed)", p.fmax_mhz)
                },
                match base {
                    Some(base) if b.mvus > 0 => format!(
                        "{:+.1} %{}",
                        100.0 * (p.fmax_mhz / base.fmax_mhz - 1.0),
                        if p.routed { "" } else { " (estimates)" }
                    ),
                    _ => "—".into(),
                },
            ),
        };
        let stages = [
            "litex",
            "yosys",
            "nextpnr",
            "nextpnr-place",
            "nextpnr-route",
            "ecppack",
        ]
        .iter()
        .filter_map(|s| b.stages.get(*s).map(|t| format!("{s} {t:.0}")))
        .collect::<Vec<_>>()
        .join(", ");
        md += &format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {placed} | {fmax} | {versus} | {} / {} / {} | {stages} | {}{}{}{} |\n",
            b.mvus,
            b.seed,
            match &b.pnr {
                Some(p) if p.routed => b.router.to_string(),
                Some(_) => "— (not routed)".into(),
                None => "—".into(),
            },
            y.lut4,
            y.ccu2c,
            y.trellis_ff,
            y.mult18x18d,
            y.dp16kd,
            b.words,
            b.tiles,
            b.nodes,
            b.commit.as_deref().unwrap_or("?"),
            if b.global_reset {
                " (reset on a global network)"
            } else {
                ""
            },
            if b.bus_bursting {
                ""
            } else {
                " (no bus bursting)"
            },
            if b.keep_out == KEEP_OUT {
                String::new()
            } else {
                format!(" ({})", keep_out_mark(b.keep_out))
            },
        );
    }
    md
}

/// Where a build lands: `target/bitstream/BOARD-<N>mvu`, `-<R>rows` after it when the rows per
/// MVU were asked for, `-global-reset` with the reset on a global network, `-no-bursting`
/// without bus bursting, `-keepout<N>` with other keep-out rows than the default's
/// (`-keepout0`: none).
pub fn build_dir(workspace: &Path, build: &SocBuild) -> PathBuf {
    let rows = build.nodes.map(|r| format!("-{r}rows")).unwrap_or_default();
    let reset = if build.global_reset {
        "-global-reset"
    } else {
        ""
    };
    let bus = if build.bus_bursting {
        ""
    } else {
        "-no-bursting"
    };
    let keep_out = if build.keep_out == KEEP_OUT {
        String::new()
    } else {
        format!("-keepout{}", build.keep_out)
    };
    workspace.join("target/bitstream").join(format!(
        "{}-{}mvu{rows}{reset}{bus}{keep_out}",
        build.board, build.mvus
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use deform_hil_sim::gateware::{Placed, Usage, YosysCells};

    fn args(line: &str) -> Vec<String> {
        line.split_whitespace().map(String::from).collect()
    }

    fn error(line: &str) -> String {
        format!("{:#}", parse(&args(line)).unwrap_err())
    }

    /// `NODES` is checked here so that a bad value fails before an hour-long build; it must be
    /// bitstream.py's own list, which sizes the memories.
    #[test]
    fn the_row_counts_are_bitstream_pys() {
        let script =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../gateware/deform_gateware/bitstream.py");
        let text = std::fs::read_to_string(&script).unwrap();
        let line = text
            .lines()
            .find(|l| l.starts_with("NODES = ("))
            .expect("bitstream.py defines NODES");
        let listed = NODES.map(|n| n.to_string()).join(", ");
        assert_eq!(line, format!("NODES = ({listed})"));
    }

    /// The sweep of the defaults, over `mvus`, changed by `change`.
    fn sweep(mvus: &[u32], change: impl FnOnce(&mut SocBuild)) -> Request {
        let mut soc = SocBuild {
            board: "ulx3s".into(),
            mvus: 0,
            seed: 1,
            router: Router::Router1,
            nodes: None,
            no_pnr: false,
            place_only: false,
            global_reset: false,
            bus_bursting: true,
            keep_out: 3,
        };
        change(&mut soc);
        Request::Build(Sweep {
            mvus: mvus.to_vec(),
            soc,
        })
    }

    #[test]
    fn arguments_parse_with_defaults() {
        assert_eq!(
            parse(&args("--board ulx3s")).unwrap(),
            sweep(&[0, 1, 2, 4, 8], |_| {})
        );
        assert_eq!(
            parse(&args(
                "--mvus 0,4 --no-pnr --board ulx3s --seed 2 --router router2 --nodes 512"
            ))
            .unwrap(),
            sweep(&[0, 4], |b| {
                b.seed = 2;
                b.router = Router::Router2;
                b.nodes = Some(512);
                b.no_pnr = true;
            })
        );
        assert_eq!(
            parse(&args("--board ulx3s --mvus 8 --nodes 512 --place-only")).unwrap(),
            sweep(&[8], |b| {
                b.nodes = Some(512);
                b.place_only = true;
            })
        );
        assert_eq!(
            parse(&args("--board ulx3s --mvus 0,4 --nodes 512 --global-reset")).unwrap(),
            sweep(&[0, 4], |b| {
                b.nodes = Some(512);
                b.global_reset = true;
            })
        );
        assert_eq!(
            parse(&args("--board ulx3s --mvus 4 --no-bus-bursting")).unwrap(),
            sweep(&[4], |b| b.bus_bursting = false)
        );
        assert_eq!(
            parse(&args("--board ulx3s --mvus 4 --keep-out 0")).unwrap(),
            sweep(&[4], |b| b.keep_out = 0)
        );
        assert_eq!(
            parse(&args("--board ulx3s --mvus 4 --keep-out 4")).unwrap(),
            sweep(&[4], |b| b.keep_out = 4)
        );
        let Request::Build(s) = sweep(&[0, 4], |b| b.seed = 3) else {
            unreachable!()
        };
        assert_eq!((s.build(4).mvus, s.build(4).seed), (4, 3));
        assert_eq!(parse(&args("--help")).unwrap(), Request::Help);
        assert_eq!(
            parse(&args("--report-only --board ulx3s")).unwrap(),
            Request::Report {
                board: "ulx3s".into()
            }
        );
        assert_eq!(parse(&args("--board nope -h")).unwrap(), Request::Help);
    }

    #[test]
    fn bad_arguments_say_what_is_wrong() {
        assert!(error("").contains("needs --board"));
        assert!(error("--board orangecrab").contains("builds for ulx3s only"));
        assert!(error("--board ulx3s --mvus").contains("--mvus needs a value"));
        assert!(error("--board ulx3s --mvus 0,x").contains("not `0,x`"));
        assert!(error("--board ulx3s --mvus 0,,4").contains("not `0,,4`"));
        assert!(error("--board ulx3s --mvus 9").contains("at most 8"));
        assert!(error("--board ulx3s --mvus 4,4").contains("4 is there twice"));
        assert!(error("--board ulx3s --mvus -1").contains("not `-1`"));
        assert!(error("--board ulx3s --seed x").contains("--seed takes a number"));
        assert!(error("--board ulx3s --router fast").contains("router1 and router2, not `fast`"));
        assert!(error("--board ulx3s --router").contains("--router needs a value"));
        assert!(error("--board ulx3s --fast").contains("does not take `--fast`"));
        assert!(error("--board ulx3s --report-only --no-pnr").contains("do not go with it"));
        assert!(error("--board ulx3s --report-only --nodes 512").contains("do not go with it"));
        assert!(error("--board ulx3s --report-only --place-only").contains("do not go with it"));
        assert!(error("--board ulx3s --report-only --global-reset").contains("do not go with it"));
        assert!(
            error("--board ulx3s --report-only --no-bus-bursting").contains("do not go with it")
        );
        assert!(error("--board ulx3s --place-only --no-pnr").contains("one or the other"));
        assert!(error("--board ulx3s --place-only --router router2")
            .contains("--place-only does not route: --router does not go with it"));
        assert!(error("--board ulx3s --router router1 --place-only").contains("does not route"));
        assert!(error("--board ulx3s --nodes 500").contains("built with 512 or 1024 rows"));
        assert!(error("--board ulx3s --nodes x").contains("--nodes x:"));
        assert!(error("--board ulx3s --nodes").contains("--nodes needs a value"));
        assert!(error("--board ulx3s --keep-out 1").contains("N at least 2"));
        assert!(error("--board ulx3s --keep-out x").contains("--keep-out x:"));
        assert!(error("--board ulx3s --keep-out").contains("--keep-out needs a value"));
        assert!(error("--board ulx3s --report-only --keep-out 0").contains("do not go with it"));
    }

    #[test]
    fn the_default_keep_out_is_bitstream_py_s() {
        let script =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../gateware/deform_gateware/bitstream.py");
        let text = std::fs::read_to_string(&script).unwrap();
        assert!(
            text.lines().any(|l| l == format!("KEEP_OUT = {KEEP_OUT}")),
            "bitstream.py's KEEP_OUT is not {KEEP_OUT}"
        );
    }

    fn usage(used: u64) -> Usage {
        Usage {
            used,
            available: 1000,
        }
    }

    fn build(mvus: u32, seed: u32, fmax: Option<f64>) -> SocReport {
        SocReport {
            board: "ulx3s".into(),
            mvus,
            seed,
            router: Router::Router2,
            commit: Some("abc".into()),
            yosys: YosysCells {
                lut4: 100,
                ccu2c: 10,
                trellis_ff: 50,
                mult18x18d: 4 + 4 * u64::from(mvus),
                dp16kd: 55,
            },
            pnr: fmax.map(|fmax_mhz| Placed {
                lut4: usage(120),
                ff: usage(50),
                mult18x18d: usage(8),
                dp16kd: usage(55),
                fmax_mhz,
                target_mhz: 50.0,
                fits: true,
                meets_timing: fmax_mhz >= 50.0,
                routed: true,
            }),
            bitstream: None,
            stages: [("yosys".to_string(), 12.0)].into_iter().collect(),
            global_reset: false,
            bus_bursting: true,
            keep_out: 3,
            words: 4096,
            tiles: 256,
            nodes: 1024,
        }
    }

    #[test]
    fn the_report_compares_each_fmax_with_the_same_seeds_baseline() {
        let mut builds = Vec::new();
        record(&mut builds, build(4, 1, Some(45.0)));
        record(&mut builds, build(0, 1, Some(50.0)));
        record(&mut builds, build(0, 2, Some(40.0)));
        record(&mut builds, build(4, 2, Some(44.0)));
        record(&mut builds, build(8, 1, None));
        // A router1 build of 4 MVUs with no router1 baseline: not compared with router2's.
        let mut other_router = build(4, 1, Some(30.0));
        other_router.router = Router::Router1;
        record(&mut builds, other_router);
        let md = markdown("ulx3s", &builds);
        let rows: Vec<&str> = md.lines().filter(|l| l.starts_with("| ")).skip(1).collect();
        assert_eq!(rows.len(), 6, "{md}");
        assert!(rows[0].starts_with("| 0 | 1 | router2 |") && rows[0].contains("| 50.0 | — |"));
        assert!(rows[2].starts_with("| 4 | 1 | router1 |") && rows[2].contains("| 30.0 | — |"));
        assert!(rows[3].starts_with("| 4 | 1 | router2 |") && rows[3].contains("| -10.0 % |"));
        assert!(rows[4].starts_with("| 4 | 2 |") && rows[4].contains("| +10.0 % |"));
        assert!(rows[5].starts_with("| 8 | 1 | — |"), "{}", rows[5]);
        assert!(rows[5].contains("not placed (Yosys only)"));
        assert!(rows[5].contains("yosys 12"), "{}", rows[5]);
    }

    /// `build` placed and not routed (`--place-only`): its Fmax is nextpnr's estimate.
    fn placed_only(mvus: u32, seed: u32, estimate: f64) -> SocReport {
        let mut b = build(mvus, seed, Some(estimate));
        b.pnr.as_mut().unwrap().routed = false;
        b
    }

    #[test]
    fn an_estimate_after_placement_is_labelled_and_compared_with_its_like_only() {
        let mut builds = Vec::new();
        record(&mut builds, build(0, 1, Some(46.7)));
        record(&mut builds, placed_only(8, 1, 30.0));
        let md = markdown("ulx3s", &builds);
        let rows: Vec<&str> = md.lines().filter(|l| l.starts_with("| ")).skip(1).collect();
        assert_eq!(rows.len(), 2, "{md}");
        // No placed-only 0-MVU build: the estimate is not set against a routed Fmax.
        assert!(
            rows[1].starts_with("| 8 | 1 | — (not routed) |")
                && rows[1].contains("| 30.0 (estimate after placement; not routed) | — |"),
            "{}",
            rows[1]
        );
        record(&mut builds, placed_only(0, 1, 37.5));
        let md = markdown("ulx3s", &builds);
        let rows: Vec<&str> = md.lines().filter(|l| l.starts_with("| ")).skip(1).collect();
        assert_eq!(rows.len(), 3, "{md}");
        assert!(
            rows[0].starts_with("| 0 | 1 | — (not routed) |"),
            "{}",
            rows[0]
        );
        assert!(rows[1].starts_with("| 0 | 1 | router2 |") && rows[1].contains("| 46.7 | — |"));
        assert!(rows[2].contains("| -20.0 % (estimates) |"), "{}", rows[2]);
        // A routed build of the same count and seed is a row of its own; placing again
        // replaces the placement only.
        record(&mut builds, build(8, 1, Some(35.0)));
        record(&mut builds, placed_only(8, 1, 31.0));
        assert_eq!(builds.len(), 4);
        let md = markdown("ulx3s", &builds);
        assert!(
            md.contains("| 31.0 (estimate after placement; not routed) | -17.3 % (estimates) |")
        );
        assert!(md.contains("| 35.0 | -25.1 % |"), "{md}");
        assert!(!md.contains("| 30.0 "), "{md}");
    }

    #[test]
    fn a_new_build_replaces_the_same_count_seed_and_depth_only() {
        let mut builds = Vec::new();
        record(&mut builds, build(4, 1, None));
        record(&mut builds, build(4, 1, Some(45.0)));
        record(&mut builds, build(4, 1, Some(47.0)));
        assert_eq!(builds.len(), 2);
        assert_eq!(builds[1].pnr.as_ref().unwrap().fmax_mhz, 47.0);
        // The same count and seed with fewer rows per MVU is a build of its own.
        let mut fewer_rows = build(4, 1, Some(46.0));
        fewer_rows.nodes = 512;
        record(&mut builds, fewer_rows);
        assert_eq!(builds.len(), 3);
        assert_eq!(builds[2].pnr.as_ref().unwrap().fmax_mhz, 47.0);
    }

    #[test]
    fn a_build_with_rows_asked_for_lands_beside_the_default() {
        let dir = |change: fn(&mut SocBuild)| {
            let Request::Build(s) = sweep(&[4], change) else {
                unreachable!()
            };
            build_dir(Path::new("/w"), &s.build(4))
        };
        assert_eq!(dir(|_| {}), Path::new("/w/target/bitstream/ulx3s-4mvu"));
        assert_eq!(
            dir(|b| b.nodes = Some(512)),
            Path::new("/w/target/bitstream/ulx3s-4mvu-512rows")
        );
        assert_eq!(
            dir(|b| {
                b.nodes = Some(512);
                b.global_reset = true;
            }),
            Path::new("/w/target/bitstream/ulx3s-4mvu-512rows-global-reset")
        );
        assert_eq!(
            dir(|b| b.bus_bursting = false),
            Path::new("/w/target/bitstream/ulx3s-4mvu-no-bursting")
        );
        assert_eq!(
            dir(|b| b.keep_out = 0),
            Path::new("/w/target/bitstream/ulx3s-4mvu-keepout0")
        );
    }

    /// A build with the array's reset on a global network is a row of its own, compared only
    /// with a 0-MVU build whose reset was on one too; reports from before it was recorded read
    /// as builds with the reset in the fabric.
    /// A build of another kind (`change`: the reset on a global network, or no bus bursting) is
    /// a row of its own, marked `mark` and compared only with a 0-MVU build of its kind;
    /// reports from before `field` was recorded read as builds without it.
    fn a_kind_keeps_builds_apart(
        change: fn(&mut SocReport),
        mark: &str,
        field: &str,
        absent: serde_json::Value,
    ) {
        let mut builds = Vec::new();
        record(&mut builds, build(0, 1, Some(50.0)));
        record(&mut builds, build(4, 1, Some(45.0)));
        let mut other = build(4, 1, Some(44.0));
        change(&mut other);
        record(&mut builds, other.clone());
        assert_eq!(builds.len(), 3);
        let md = markdown("ulx3s", &builds);
        assert!(md.contains("| 45.0 | -10.0 % |"), "{md}");
        assert!(
            md.contains("| 44.0 | — |") && md.contains(&format!("abc ({mark}) |")),
            "{md}"
        );
        let mut other_baseline = build(0, 1, Some(40.0));
        change(&mut other_baseline);
        record(&mut builds, other_baseline);
        let md = markdown("ulx3s", &builds);
        assert!(md.contains("| 44.0 | +10.0 % |"), "{md}");
        let mut before = serde_json::to_value(&other).unwrap();
        before.as_object_mut().unwrap().remove(field);
        let before: SocReport = serde_json::from_value(before).unwrap();
        assert_eq!(serde_json::to_value(&before).unwrap()[field], absent);
    }

    #[test]
    fn the_reset_network_keeps_builds_apart() {
        a_kind_keeps_builds_apart(
            |b| b.global_reset = true,
            "reset on a global network",
            "global_reset",
            false.into(),
        );
    }

    /// Reports from before bursting was recorded read as builds without it (as they were).
    #[test]
    fn the_bus_keeps_builds_apart() {
        a_kind_keeps_builds_apart(
            |b| b.bus_bursting = false,
            "no bus bursting",
            "bus_bursting",
            false.into(),
        );
    }

    /// Reports from before the keep-out rows were recorded read as builds placed without them
    /// (as they were).
    #[test]
    fn the_keep_out_rows_keep_builds_apart() {
        a_kind_keeps_builds_apart(
            |b| b.keep_out = 0,
            "no keep-out rows, nextpnr's own flow",
            "keep_out",
            0.into(),
        );
    }

    #[test]
    fn reports_are_written_whole_and_read_back() {
        let dir = std::env::temp_dir().join(format!("deform-bitstream-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let builds = vec![build(0, 1, Some(50.0)), build(2, 1, None)];
        write_reports(&dir, "ulx3s", &builds).unwrap();
        assert_eq!(read_builds(&dir.join("report.json")).unwrap(), builds);
        assert!(dir.join("multipliers_per_mvu.svg").is_file());
        assert!(!dir.join(".plot.part").exists());
        std::fs::write(dir.join("report.json"), "[{\"old\": 1}]").unwrap();
        let err = read_builds(&dir.join("report.json")).unwrap_err();
        assert!(format!("{err:#}").contains("delete it"), "{err:#}");
        assert!(read_builds(&dir.join("none.json")).unwrap().is_empty());
        // A report gathered before the router was recorded: its builds were router1's.
        let mut old: serde_json::Value = serde_json::to_value(&builds).unwrap();
        old[0].as_object_mut().unwrap().remove("router");
        std::fs::write(dir.join("report.json"), old.to_string()).unwrap();
        let read = read_builds(&dir.join("report.json")).unwrap();
        assert_eq!(
            (read[0].router, read[1].router),
            (Router::Router1, Router::Router2)
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
