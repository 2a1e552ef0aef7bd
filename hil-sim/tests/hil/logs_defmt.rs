//! The firmware's defmt logs through QEMU: shipped in `Log` notices, decoded on the host against
//! the firmware ELF with their level and source location; an ELF of another build is refused.
//! Needs the firmware (`cargo xtask firmware`) and QEMU.

use crate::support;

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use deform_hil_sim::firmware_elf;
use deform_host::board::LogOptions;
use deform_host::board::{Board, BoardChoice};
use deform_host::firmware_logs::{FirmwareElf, FirmwareLogs, LogError, LogLevel, LogLine};
use deform_host::link::{open_serial, Link, Target};
use deform_shared::protocol::{SolveParams, Start};

use support::*;

/// The line of the `defmt::<level>!(` call whose format string starts with `format_start`, in
/// `file` (relative to the firmware crate): where the decoder must say the line came from.
fn log_call_line(file: &str, format_start: &str) -> u64 {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../firmware")
        .join(file);
    let source = std::fs::read_to_string(&path).unwrap();
    let lines: Vec<&str> = source.lines().collect();
    let at = lines
        .iter()
        .position(|l| l.contains(&format!("\"{format_start}")))
        .unwrap_or_else(|| panic!("no log call {format_start:?} in {}", path.display()));
    let call = (0..=at)
        .rev()
        .find(|&i| lines[i].contains("defmt::"))
        .expect("the format string belongs to a defmt call");
    call as u64 + 1
}

fn collecting(level: LogLevel) -> (FirmwareLogs, Arc<Mutex<Vec<LogLine>>>) {
    let lines = Arc::new(Mutex::new(Vec::new()));
    let sink = Arc::clone(&lines);
    let elf = FirmwareElf::load(&firmware_elf()).expect("the firmware ELF has a defmt table");
    let logs = FirmwareLogs::new(
        Some(elf),
        level,
        Box::new(move |line| sink.lock().unwrap().push(line.clone())),
    );
    (logs, lines)
}

fn find<'a>(lines: &'a [LogLine], level: LogLevel, start: &str) -> &'a LogLine {
    lines
        .iter()
        .find(|l| l.level == level && l.message.starts_with(start))
        .unwrap_or_else(|| panic!("no {level} line starting {start:?} in {lines:#?}"))
}

#[test]
fn a_solve_logs_decoded_lines_with_level_and_location_and_info_hides_debug() {
    let mut qemu = boot();
    let (all, all_lines) = collecting(LogLevel::Trace);
    let (info, info_lines) = collecting(LogLevel::Info);
    let (all, info) = (all.shared(), info.shared());
    let mut link = Link::new(open_serial(qemu.pty_path().to_str().unwrap()).unwrap());
    {
        let (all, info) = (Arc::clone(&all), Arc::clone(&info));
        link.set_notice_handler(Box::new(move |seq, body| {
            all.lock().unwrap().notice(seq, &body);
            info.lock().unwrap().notice(seq, &body);
        }));
    }
    let mut target = Target::handshake(link, timeouts()).unwrap();
    let build_id = target.info().build_id.clone();
    all.lock().unwrap().accept(&build_id).unwrap();
    info.lock().unwrap().accept(&build_id).unwrap();

    let matrix = banded_spd(200, 1);
    target.upload_matrix(&matrix).unwrap();
    let bytes_before_solve = all.lock().unwrap().stats().bytes;
    let rhs = vec![1.0; 200];
    let params = SolveParams {
        max_iterations: 5000,
        tolerance: 1e-10,
        start: Start::Zero,
        directions: 1,
        cycle_budget: 0,
    };
    let (report, _x) = target.solve_for(&rhs, params).unwrap();
    let stats = all.lock().unwrap().stats();
    eprintln!(
        "log bytes: {} in all, {} for one vector upload + solve + read-back; {} frames",
        stats.bytes,
        stats.bytes - bytes_before_solve,
        stats.frames
    );
    assert_eq!(
        (stats.dropped_bytes, stats.malformed, stats.lost_notices),
        (0, 0, 0)
    );

    let lines = all_lines.lock().unwrap().clone();
    let boot = find(
        &lines,
        LogLevel::Info,
        "deform firmware 0.1.0 up: 524288 words",
    );
    assert!(
        boot.location
            .as_deref()
            .is_some_and(|l| l.ends_with(&format!(
                "src/main.rs:{}",
                log_call_line("src/main.rs", "deform firmware {=str} up")
            ))),
        "{boot:?}"
    );
    let upload = find(&lines, LogLevel::Debug, "matrix upload: n = 200, 1 tiles");
    assert!(upload
        .location
        .as_deref()
        .is_some_and(|l| l.ends_with(&format!(
            "src/activity.rs:{}",
            log_call_line("src/activity.rs", "matrix upload: n = ")
        ))));
    find(&lines, LogLevel::Info, "matrix accepted and resident");
    find(&lines, LogLevel::Trace, "EndMatrix, host CRC");
    let solved = find(
        &lines,
        LogLevel::Info,
        &format!(
            "solved in {} iterations (converged: true)",
            report.iterations
        ),
    );
    assert!(solved.message.contains(&format!(
        "MVU {} cycles / {} instructions",
        report.mvu.cycles, report.mvu.instructions
    )));
    assert!(solved
        .location
        .as_deref()
        .is_some_and(|l| l.ends_with(&format!(
            "src/activity.rs:{}",
            log_call_line("src/activity.rs", "solved in {=u32} iterations")
        ))));
    assert!(
        solved.to_string().starts_with("firmware INFO  solved in"),
        "{solved}"
    );

    // The default level shows exactly the info-and-up lines.
    let shown = info_lines.lock().unwrap().clone();
    let expected: Vec<LogLine> = lines
        .iter()
        .filter(|l| l.level >= LogLevel::Info)
        .cloned()
        .collect();
    assert_eq!(shown, expected);
    assert!(lines.iter().any(|l| l.level == LogLevel::Trace));
    assert_alive(&mut qemu);
}

/// A copy of the firmware ELF with one byte of its build id changed: the same defmt table, but
/// not provably the running build.
fn rebuilt_copy() -> PathBuf {
    let data = std::fs::read(firmware_elf()).unwrap();
    let elf = FirmwareElf::load(&firmware_elf()).unwrap();
    let id = elf.build_id().unwrap().to_vec();
    let at = data
        .windows(id.len())
        .position(|w| w == id.as_slice())
        .unwrap();
    let mut copy = data.clone();
    copy[at] ^= 0x5A;
    let path = std::env::temp_dir().join(format!("deform-rebuilt-{}.elf", std::process::id()));
    std::fs::write(&path, copy).unwrap();
    path
}

#[test]
fn an_elf_of_another_build_is_refused_with_both_build_ids() {
    let mut qemu = boot();
    let other = rebuilt_copy();
    let options = LogOptions {
        elf: Some(other.clone()),
        min_level: LogLevel::Info,
    };
    let pty = qemu.pty_path().to_string_lossy().into_owned();
    let err = Board::open(&BoardChoice::Port(pty), timeouts(), &options)
        .err()
        .expect("a mismatched ELF must be refused");
    let text = format!("{err:#}");
    assert!(
        text.contains("is not the firmware the target runs"),
        "{text}"
    );
    let running = FirmwareElf::load(&firmware_elf()).unwrap();
    let running_id: String = running
        .build_id()
        .unwrap()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    assert!(text.contains(&running_id), "{text}");
    match FirmwareElf::load(&other)
        .unwrap()
        .check_build_id(running.build_id().unwrap())
    {
        Err(LogError::BuildIdMismatch { .. }) => {}
        other => panic!("{other:?}"),
    }
    std::fs::remove_file(&other).ok();
    assert_alive(&mut qemu);
}
