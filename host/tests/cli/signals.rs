//! Stopping `deform` with SIGTERM (a service manager, `kill`) or SIGINT (Ctrl-C, `kill -INT`)
//! leaves no board process behind: its QEMU, or the LiteX SoC's Verilator simulator and socat
//! bridge, die with it (hil-sim's `child::spawn`, `PR_SET_PDEATHSIG`), though no destructor runs.
//! Needs QEMU and the firmware, and for the LiteX case the LiteX set-up and its firmware, like the
//! other hardware-in-the-loop tests.

use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::thread;
use std::time::{Duration, Instant};

use deform_hil_sim::child::{children_of, is_running, ProcessInfo};

/// Starts `deform ARGS` and waits until it has a child process whose name starts with each of
/// `wanted` (the kernel keeps 15 bytes of a name: `qemu-system-ris`).
fn start_with_children(
    args: &[&str],
    wanted: &[&str],
    within: Duration,
) -> (Child, Vec<ProcessInfo>) {
    let log = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("signals-{}.log", args[0]));
    let mut deform = Command::new(env!("CARGO_BIN_EXE_deform"));
    deform
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap());
    // An ignored signal stays ignored across exec: a test run started in the background of a
    // non-interactive shell (`cargo xtask test &`, nohup) hands SIGINT to deform as ignored, and
    // a command without its own handler (`deform solve`) would then never see Ctrl-C. The test
    // is about deform, not about how its runner was started, so deform starts with both
    // signals at their default action, as from a terminal.
    // SAFETY: only async-signal-safe calls (signal) between fork and exec.
    unsafe {
        deform.pre_exec(|| {
            libc::signal(libc::SIGINT, libc::SIG_DFL);
            libc::signal(libc::SIGTERM, libc::SIG_DFL);
            Ok(())
        });
    }
    let mut deform = deform.spawn().expect("the deform binary runs");
    let deadline = Instant::now() + within;
    loop {
        let children = children_of(deform.id());
        if wanted
            .iter()
            .all(|w| children.iter().any(|c| c.name.starts_with(w)))
        {
            return (deform, children);
        }
        if let Some(status) = deform.try_wait().unwrap() {
            let stderr = std::fs::read_to_string(&log).unwrap_or_default();
            panic!("deform {args:?} exited ({status}) before starting {wanted:?}: {stderr}");
        }
        if Instant::now() >= deadline {
            let _ = deform.kill();
            let _ = deform.wait();
            panic!("deform {args:?} did not start {wanted:?} within {within:?}: {children:?}");
        }
        thread::sleep(Duration::from_millis(50));
    }
}

/// Sends `signal` (`TERM`, `INT`) to `deform`, waits for it to end, then for every one of
/// `children` to be gone.
fn stop_and_check(mut deform: Child, children: &[ProcessInfo], signal: &str) {
    let pid = deform.id().to_string();
    let sent = Command::new("kill")
        .args([&format!("-{signal}"), &pid])
        .status()
        .unwrap();
    assert!(sent.success(), "kill -{signal} {pid} failed");
    let deadline = Instant::now() + Duration::from_secs(30);
    while deform.try_wait().unwrap().is_none() {
        if Instant::now() >= deadline {
            let _ = deform.kill();
            let _ = deform.wait();
            panic!("deform did not end within 30 s of SIG{signal}");
        }
        thread::sleep(Duration::from_millis(20));
    }
    let deadline = Instant::now() + Duration::from_secs(10);
    for child in children {
        while is_running(child.pid) {
            assert!(
                Instant::now() < deadline,
                "after SIG{signal} to deform, its child {} ({}) still runs",
                child.name,
                child.pid
            );
            thread::sleep(Duration::from_millis(20));
        }
    }
}

#[test]
fn sigterm_and_sigint_to_deform_live_serve_leave_no_qemu() {
    let scenario = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/needle-insertion.toml");
    let scenario = scenario.to_str().unwrap();
    for signal in ["TERM", "INT"] {
        let (deform, children) = start_with_children(
            &["live", scenario, "--serve", "--addr", "127.0.0.1:0"],
            &["qemu-system"],
            Duration::from_secs(60),
        );
        stop_and_check(deform, &children, signal);
    }
}

#[test]
fn sigterm_and_sigint_to_deform_solve_on_litex_leave_no_verilator_or_socat() {
    for signal in ["TERM", "INT"] {
        let (deform, children) = start_with_children(
            &["solve", "--target", "litex", "--grid", "8,8,8"],
            &["Vsim", "socat"],
            Duration::from_secs(600),
        );
        // Let the solve get under way (the serial line up, the upload started).
        thread::sleep(Duration::from_secs(2));
        stop_and_check(deform, &children, signal);
    }
}
