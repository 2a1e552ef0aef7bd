//! The `deform` binary when the target dies mid-transfer: QEMU is killed (or the line cut)
//! while the matrix is uploading, and `deform solve` must exit non-zero with a clear message
//! within its link timeout, never hang. Needs the firmware ELF and QEMU (`cargo xtask setup`,
//! `cargo xtask firmware`), like the hil-sim tests.

use std::io::Read;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::Ordering;
use std::thread;
use std::time::{Duration, Instant};

use deform_hil_sim::relay::{FaultConfig, FaultRelay};
use deform_hil_sim::{Qemu, QemuConfig};

/// Seconds the binary may wait for any one reply.
const LINK_TIMEOUT: u64 = 4;

/// Starts `deform solve` on a model large enough that its upload takes seconds, through `relay`.
fn solve_through(relay: &FaultRelay) -> Child {
    Command::new(env!("CARGO_BIN_EXE_deform"))
        .args(["solve", "--grid", "12,12,60", "--model", "b", "--port"])
        .arg(relay.pty_path())
        .args([
            "--link-timeout",
            &LINK_TIMEOUT.to_string(),
            "--retries",
            "6",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the deform binary runs")
}

/// Waits until `bytes` went to the target (the upload is under way).
fn wait_for_upload(relay: &FaultRelay, bytes: u64, child: &mut Child) {
    let deadline = Instant::now() + Duration::from_secs(60);
    while relay.counters().to_target.load(Ordering::SeqCst) < bytes {
        assert!(Instant::now() < deadline, "the upload never got going");
        if let Some(status) = child.try_wait().unwrap() {
            let mut err = String::new();
            child
                .stderr
                .take()
                .unwrap()
                .read_to_string(&mut err)
                .unwrap();
            panic!("deform exited early ({status}): {err}");
        }
        thread::sleep(Duration::from_millis(20));
    }
}

/// Waits for `child` to exit; its status, stderr and how long it took after the fault.
fn wait_exit(mut child: Child, fault_at: Instant) -> (std::process::ExitStatus, String, Duration) {
    let limit = Duration::from_secs(LINK_TIMEOUT + 10);
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            let mut err = String::new();
            child
                .stderr
                .take()
                .unwrap()
                .read_to_string(&mut err)
                .unwrap();
            return (status, err, fault_at.elapsed());
        }
        if fault_at.elapsed() > limit {
            let _ = child.kill();
            panic!("deform still runs {limit:?} after the fault: it hangs");
        }
        thread::sleep(Duration::from_millis(20));
    }
}

fn boot() -> Qemu {
    Qemu::start(&QemuConfig::default()).unwrap_or_else(|e| panic!("cannot boot the firmware: {e}"))
}

#[test]
fn killing_qemu_mid_upload_ends_deform_with_a_clear_error_in_time() {
    let mut qemu = boot();
    let relay = FaultRelay::start(qemu.pty_path(), FaultConfig::clean()).unwrap();
    let mut child = solve_through(&relay);
    wait_for_upload(&relay, 40_000, &mut child);
    qemu.kill().unwrap();
    let (status, stderr, took) = wait_exit(child, Instant::now());
    assert!(
        !status.success(),
        "deform succeeded without a target: {stderr}"
    );
    assert_eq!(status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("uploading A to the target")
            && (stderr.contains("no answer to") || stderr.contains("connection to the target")),
        "unclear message: {stderr}"
    );
    assert!(
        took <= Duration::from_secs(LINK_TIMEOUT + 3),
        "took {took:?} for a {LINK_TIMEOUT} s link timeout"
    );
    println!("deform exited after {took:.1?}: {}", stderr.trim());
}

#[test]
fn a_line_cut_mid_upload_ends_deform_with_a_clear_error_in_time() {
    let mut qemu = boot();
    let relay = FaultRelay::start(qemu.pty_path(), FaultConfig::clean()).unwrap();
    let mut child = solve_through(&relay);
    wait_for_upload(&relay, 40_000, &mut child);
    relay.cut();
    let (status, stderr, took) = wait_exit(child, Instant::now());
    assert_eq!(status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("no answer to"), "unclear message: {stderr}");
    assert!(stderr.contains("retransmissions"), "{stderr}");
    assert!(
        took <= Duration::from_secs(LINK_TIMEOUT + 3),
        "took {took:?}"
    );
    // The target itself is fine: it just lost its host.
    assert_eq!(qemu.try_exit_code().unwrap(), None);
    println!("deform exited after {took:.1?}: {}", stderr.trim());
}
