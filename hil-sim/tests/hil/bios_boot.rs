//! The firmware booted through the stock LiteX BIOS on the simulated SoC with ROM (built once,
//! cached in target/litex): by deform's own SFL client (`deform flash --target litex`'s path),
//! and by LiteX's own `litex_term`, after which `deform solve --port`'s path runs on the same
//! line.
//!
//! Named to run first: libtest starts a binary's tests in the order of their names, and these
//! two are among the longest (the BIOS receives ~315 KB at a paced line rate). Started first,
//! they run beside the rest on the other core instead of alone at the end. (The litex_term test
//! was alone at the end of the CLI tests' binary before session 14: ten minutes with one core
//! idle.)
//!
//! `litex_term --kernel fw.bin --kernel-adr 0x40000000` runs in its default mode (calibrated
//! inter-frame delay, 128 frames in flight; no `--safe`). Before the simulated UART was paced at
//! a baud rate (hil-sim/litex/deform_soc.py), it handed the SoC a byte per clock, the BIOS's
//! 128-byte receive ring overflowed and the upload failed at 0–5 % with `Got unexpected response
//! from device 'E'`.
//!
//! Needs the LiteX set-up (`cargo xtask setup`: the venv holds litex_term) and the LiteX firmware
//! (`cargo xtask firmware --board litex`).

use crate::support;

use std::fs::File;
use std::io::{Read, Write};
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::path::Path;
use std::process::{ChildStdout, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use deform_hil_sim::child;
use deform_hil_sim::litex::{litex_dir, litex_firmware_elf, LitexConfig, LitexSim};
use deform_host::board::{BiosChoice, Board, BoardChoice};
use deform_host::flash::sfl::{self, SflTimeouts};
use deform_host::flash::FlashImage;
use deform_host::link::LinkFlags;
use deform_host::model::{Connection, Grid, Model, ModelSpec};
use deform_host::solve::solve_model;

/// What litex_term prints once the BIOS has acknowledged the jump to the image. Its
/// "Booting the device." comes *before* it sends that jump: ending litex_term on it raced the
/// jump frame, and the BIOS then never left its serial boot (CI: no answer to Hello).
const BOOTED: &str = "[LITEX-TERM] Done.";

/// What litex_term prints when the BIOS answers a frame with neither `K` nor `C`.
const UNKNOWN_REPLY: &str = "[LITEX-TERM] Got unknown reply";

/// What litex_term prints when it has seen the BIOS's magic request.
const DOWNLOAD_REQUEST: &str = "[LITEX-TERM] Received firmware download request";

/// SoC clocks per received byte on the BIOS line for this run: 19,200 baud at the nominal
/// 1 MHz. litex_term keeps up to 128 frames in flight, so the line must be no faster than the
/// BIOS empties its receive ring. The simulated line hands the SoC bytes at exactly this pace
/// while litex_term has them queued, so the outcome is the SoC's, not the host's: 260 and 390
/// clocks overflowed the ring at once (CRC error within the first frames), 455 passed, and
/// this run keeps 14 % above that. 9,600 baud (1,042), the build's default, took twice as long.
const LITEX_TERM_UART_PACE: u32 = 520;

/// What litex_term sends on: its own lines (`[LITEX-TERM] …`) and the BIOS's prompt.
enum Term {
    Line(String),
    /// The BIOS sits at `litex> `: its serial boot asked before anyone answered.
    Prompt,
}

/// How often the reader of litex_term's output drains it (see [`term_lines`]).
const DRAIN_EVERY: Duration = Duration::from_millis(20);

/// litex_term's own lines and the BIOS's prompts (found as deform's own client finds them,
/// `sfl::shows_prompt`), sent on as they come.
///
/// Its upload loop spins while 128 frames are in flight, redrawing a progress bar with `\r` on
/// every turn. Drained as fast as it came, through a pty, that bar was hundreds of MB, and
/// litex_term, the pty and this reader took about a core of the two that the simulated SoC
/// needed (session 14: the simulator at 65 % of a core; alone, as with deform's own client,
/// 94 %). So the reader reads its pipe, shrunk to a page, at most every [`DRAIN_EVERY`]: a
/// full pipe holds litex_term's loop still. The loop needs little time to keep the BIOS fed,
/// since 128 frames in flight last the BIOS seconds.
fn term_lines(mut out: ChildStdout, events: mpsc::Sender<Term>) {
    // SAFETY: F_SETPIPE_SZ on a pipe this function owns; a failure leaves the default size.
    unsafe { libc::fcntl(out.as_raw_fd(), libc::F_SETPIPE_SZ, 4096) };
    let mut buf = [0u8; 4096];
    let mut line = Vec::new();
    while let Ok(n) = out.read(&mut buf) {
        if n == 0 {
            break;
        }
        std::thread::sleep(DRAIN_EVERY);
        for &b in &buf[..n] {
            if b == b'\r' || b == b'\n' {
                let text = String::from_utf8_lossy(&line);
                if text.contains("[LITEX-TERM]")
                    && events.send(Term::Line(text.into_owned())).is_err()
                {
                    return;
                }
                line.clear();
            } else if line.len() < 512 {
                line.push(b);
                // The prompt ends in "> ": only then is the line worth a look.
                if line.ends_with(b"> ") && sfl::shows_prompt(&line) {
                    if events.send(Term::Prompt).is_err() {
                        return;
                    }
                    line.clear();
                }
            }
        }
    }
}

/// How long the test waits, with no download request, before it types `serialboot` again.
const RETYPE_AFTER: Duration = Duration::from_secs(20);

/// litex_term's keyboard: a pty whose slave is its stdin (it sets its terminal's modes, so it
/// wants a tty there) and whose master the test types into.
fn keyboard() -> (File, OwnedFd) {
    // nix's openpty, as hil-sim's relay opens its ptys.
    let pair = nix::pty::openpty(None, None).expect("openpty");
    // SAFETY: openpty just returned these descriptors; each is owned by exactly one value.
    unsafe {
        (
            File::from_raw_fd(pair.master),
            OwnedFd::from_raw_fd(pair.slave),
        )
    }
}

/// Waits until litex_term has booted the device, typing `serialboot` at the BIOS's prompt (as a
/// user does) until the BIOS asks for the download: the BIOS asks once at boot and waits a
/// quarter of a second of its clock, and under a loaded gate the simulated BIOS got there
/// before Python had litex_term reading the line (session 13: no line from litex_term in
/// 900 s). Returns litex_term's lines.
fn boot_through(
    term: &mut std::process::Child,
    mut keys: File,
    events: &mpsc::Receiver<Term>,
) -> Vec<String> {
    // The BIOS's boot and the ~315 KB upload: 0.6–0.9 KB/s here, slower under a loaded gate.
    let deadline = Instant::now() + Duration::from_secs(1800);
    let mut seen: Vec<String> = Vec::new();
    let mut typed = Instant::now();
    let mut prompted = false;
    while !seen.iter().any(|l| l.contains(BOOTED)) {
        let text = seen.join("\n");
        assert!(
            !text.contains("[LITEX-TERM] Got unexpected")
                && !text.contains(UNKNOWN_REPLY)
                && !text.contains("[LITEX-TERM] Upload to device failed"),
            "litex_term's upload failed:\n{text}"
        );
        if let Ok(Some(status)) = term.try_wait() {
            panic!("litex_term exited ({status}) before booting the device:\n{text}");
        }
        assert!(
            Instant::now() < deadline,
            "litex_term did not boot the device:\n{text}"
        );
        let asked = text.contains(DOWNLOAD_REQUEST);
        if !asked && (prompted || typed.elapsed() >= RETYPE_AFTER) {
            // Not sfl::SERIALBOOT_COMMAND: its leading newline makes the BIOS print a prompt
            // first, which would have this loop type again as the upload starts.
            keys.write_all(b"serialboot\n")
                .expect("typing into litex_term");
            seen.push("[test] typed serialboot".into());
            typed = Instant::now();
            prompted = false;
        }
        match events.recv_timeout(Duration::from_millis(200)) {
            Ok(Term::Line(line)) => seen.push(line),
            Ok(Term::Prompt) => prompted = true,
            Err(_) => {}
        }
    }
    seen
}

#[test]
fn stock_litex_term_boots_the_firmware_through_the_bios_and_deform_solves_on_that_line() {
    let elf = litex_firmware_elf();
    let image = FlashImage::from_file(&elf).unwrap_or_else(|e| panic!("{}: {e}", elf.display()));
    let scratch = Path::new(env!("CARGO_TARGET_TMPDIR")).join("litex-term");
    std::fs::create_dir_all(&scratch).unwrap();
    let bin = scratch.join("fw.bin");
    std::fs::write(&bin, &image.bytes).unwrap();

    let sim = LitexSim::start(&LitexConfig::bios().with_uart_pace(LITEX_TERM_UART_PACE))
        .unwrap_or_else(|e| panic!("cannot start the LiteX SoC with its BIOS: {e}"));
    let serial = sim.serial_path().to_str().unwrap().to_string();
    // litex_term is an interactive terminal: its stdin is a pty of the test's (`keyboard`).
    let python = litex_dir().join("venv/bin/python");
    // At the lowest priority, so that under a loaded gate it takes no time the simulated SoC,
    // which sets the pace, could use (see `term_lines`).
    let mut term = Command::new("nice");
    let (keys, tty) = keyboard();
    term.args(["-n", "19"])
        .arg(&python)
        .args(["-m", "litex.tools.litex_term", "--kernel"])
        .arg(&bin)
        .args(["--kernel-adr", &format!("{:#x}", image.load_address)])
        .arg(&serial)
        // Its lines at once through the pipe: Python buffers a pipe's output.
        .env("PYTHONUNBUFFERED", "1")
        .stdin(Stdio::from(tty))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let mut term = child::spawn(term).expect("python runs litex_term");
    let (tx, rx) = mpsc::channel();
    let out = term.stdout.take().unwrap();
    std::thread::spawn(move || term_lines(out, tx));
    let started = Instant::now();
    let seen = boot_through(&mut term, keys, &rx);
    let text = seen.join("\n");
    println!(
        "litex_term booted the firmware in {:.1} s:\n{text}",
        started.elapsed().as_secs_f64(),
    );
    assert!(
        !text.contains(UNKNOWN_REPLY),
        "the BIOS did not acknowledge the jump:\n{text}"
    );
    assert!(
        !text.contains("switching to --safe"),
        "the calibration fell back to --safe mode:\n{text}"
    );
    // litex_term holds the line: end it, and `deform solve` takes the line over.
    let _ = term.kill();
    let _ = term.wait();

    let grid = Grid::new(4, 4, 4).unwrap();
    let model = Model::build(&ModelSpec {
        grid,
        connection: Connection::AxialShear,
        loads: vec![ModelSpec::default_load(grid)],
        ..ModelSpec::thesis_example()
    })
    .expect("model builds");
    let mut plan = support::plan(BoardChoice::Port(serial), 1e-6, 8, Duration::from_secs(600));
    plan.link = LinkFlags {
        link_timeout: 60,
        ..LinkFlags::default()
    };
    let solved = solve_model(&model, &plan).expect("the solve on the line litex_term booted");
    let (deviation, _) = support::deviation_from_reference(&solved);
    println!("deform solve on that line: deviation {deviation:.2e} from the f64 reference");
    assert!(deviation <= 1e-6, "deviation {deviation:e}");
    drop(sim);
    std::fs::remove_dir_all(&scratch).unwrap();
}

/// The stock LiteX BIOS (the litex_sim SoC with ROM, built once) boots our firmware over its
/// serial line (SFL), as `litex_term --kernel` would; the firmware then solves.
#[test]
fn the_stock_litex_bios_boots_the_firmware_which_then_solves() {
    let elf = litex_firmware_elf();
    let started = Instant::now();
    let (mut board, report) = Board::flash_litex_bios(
        &BiosChoice::Simulated,
        &elf,
        support::litex_timeouts(),
        SflTimeouts::default(),
        &Default::default(),
        |_| {},
    )
    .unwrap_or_else(|e| panic!("boot through the BIOS: {e:#}"));
    println!(
        "booted through the LiteX BIOS: {} SFL frames, {} resent, {:.1} s",
        report.frames,
        report.resends,
        started.elapsed().as_secs_f64()
    );
    assert!(report.frames > 1);
    assert_eq!(board.target.info().harts, 1);
    let matrix = support::banded_spd(32, 2);
    board.target.upload_matrix(&matrix).unwrap();
    let b: Vec<f64> = (0..32).map(|i| 1.0 + f64::from(i % 5)).collect();
    support::solve_matches_f64(&mut board.target, &matrix, &b, 400);
}
