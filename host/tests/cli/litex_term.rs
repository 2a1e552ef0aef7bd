//! LiteX's own client on the simulated SoC with the stock BIOS: `litex_term --kernel fw.bin
//! --kernel-adr 0x40000000` in its default mode (calibrated inter-frame delay, 128 frames in
//! flight; no `--safe`) boots the firmware over the BIOS's serial boot, then `deform solve
//! --port` runs on the same line. Before the simulated UART was paced at a baud rate
//! (hil-sim/litex/deform_soc.py), it handed the SoC a byte per clock, the BIOS's 128-byte
//! receive ring overflowed and the upload failed at 0–5 % with `Got unexpected response from
//! device 'E'`.
//!
//! Needs the LiteX set-up (`cargo xtask setup`: the venv holds litex_term) and the LiteX firmware
//! (`cargo xtask firmware --board litex`); the BIOS SoC is built once (a few minutes, cached).

use std::io::Read;
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use deform_hil_sim::child;
use deform_hil_sim::litex::{litex_dir, litex_firmware_elf, LitexConfig, LitexSim};
use deform_host::flash::FlashImage;

/// What litex_term prints once the BIOS has acknowledged the jump to the image. Its
/// "Booting the device." comes *before* it sends that jump: ending litex_term on it raced the
/// jump frame, and the BIOS then never left its serial boot (CI: no answer to Hello).
const BOOTED: &str = "[LITEX-TERM] Done.";

/// What litex_term prints when the BIOS answers a frame with neither `K` nor `C`.
const UNKNOWN_REPLY: &str = "[LITEX-TERM] Got unknown reply";

/// SoC clocks per received byte on the BIOS line for this run: 19,200 baud at the nominal
/// 1 MHz. litex_term keeps up to 128 frames in flight, so the line must be no faster than the
/// BIOS empties its receive ring. The simulated line hands the SoC bytes at exactly this pace
/// while litex_term has them queued, so the outcome is the SoC's, not the host's: 260 and 390
/// clocks overflowed the ring at once (CRC error within the first frames), 455 passed, and
/// this run keeps 14 % above that. 9,600 baud (1,042), the build's default, took twice as long.
const LITEX_TERM_UART_PACE: u32 = 520;

/// litex_term's own lines (`[LITEX-TERM] …`), sent on as they end. Its upload loop redraws a
/// progress bar with `\r` on every turn (hundreds of MB over an upload), which is dropped here:
/// kept, it filled memory, and reading it slowly held litex_term up through the pty.
fn term_lines(mut out: impl Read, lines: mpsc::Sender<String>) {
    let mut buf = [0u8; 4096];
    let mut line = Vec::new();
    while let Ok(n) = out.read(&mut buf) {
        if n == 0 {
            break;
        }
        for &b in &buf[..n] {
            if b == b'\r' || b == b'\n' {
                let text = String::from_utf8_lossy(&line);
                if text.contains("[LITEX-TERM]") && lines.send(text.into_owned()).is_err() {
                    return;
                }
                line.clear();
            } else if line.len() < 512 {
                line.push(b);
            }
        }
    }
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
    // litex_term is an interactive terminal: it wants a tty on stdin, which Python's pty module
    // gives it (the test's own stdin is not one).
    let python = litex_dir().join("venv/bin/python");
    let mut term = Command::new(&python);
    term.args([
        "-c",
        "import pty, sys; sys.exit(pty.spawn(sys.argv[1:]) >> 8)",
    ])
    .arg(&python)
    .args(["-m", "litex.tools.litex_term", "--kernel"])
    .arg(&bin)
    .args(["--kernel-adr", &format!("{:#x}", image.load_address)])
    .arg(&serial)
    .stdin(Stdio::null())
    .stdout(Stdio::piped())
    .stderr(Stdio::piped());
    let mut term = child::spawn(term).expect("python runs litex_term");
    let (tx, rx) = mpsc::channel();
    let out = term.stdout.take().unwrap();
    std::thread::spawn(move || term_lines(out, tx));
    let started = Instant::now();
    // The BIOS's boot and the ~315 KB upload at 0.3–0.8 KB/s under a loaded gate: 900 s,
    // set when the image was 229 KB, ran out twice in session 13's fresh-clone gates.
    let deadline = started + Duration::from_secs(1800);
    let mut seen: Vec<String> = Vec::new();
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
        if let Ok(line) = rx.recv_timeout(Duration::from_millis(200)) {
            seen.push(line);
        }
    }
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

    let out = Command::new(env!("CARGO_BIN_EXE_deform"))
        .args([
            "solve", "--port", &serial, "--grid", "4,4,4", "--model", "b",
        ])
        .arg("--elf")
        .arg(&elf)
        .args(["--link-timeout", "60", "--timeout", "600"])
        .output()
        .expect("the deform binary runs");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "deform solve on the line litex_term booted: {}\n{stdout}",
        String::from_utf8_lossy(&out.stderr)
    );
    let deviation = stdout
        .lines()
        .find_map(|l| l.strip_prefix("max deviation from the f64 reference: "))
        .and_then(|l| l.split_whitespace().next())
        .and_then(|v| v.parse::<f64>().ok())
        .unwrap_or_else(|| panic!("no deviation in:\n{stdout}"));
    assert!(deviation <= 1e-6, "deviation {deviation:e}:\n{stdout}");
    drop(sim);
    std::fs::remove_dir_all(&scratch).unwrap();
}
