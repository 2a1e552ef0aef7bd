//! Every command that talks to a target shows the firmware's logs (decoded against its ELF,
//! whose build id is checked): `deform live` and `deform bench` once dropped them. On the
//! firmware in QEMU, with the same runs checking what live and simulate report: a quasi-static
//! report names its target, frames over `--cycle-budget` are counted, and `simulate --alpha`
//! says when its steps end far above `--tol`.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn deform(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_deform"))
        .args(args)
        .output()
        .unwrap()
}

fn scratch(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("target-logs-{name}"));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn ok(out: &Output) -> (String, String) {
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    );
    assert!(out.status.success(), "{stdout}{stderr}");
    (stdout, stderr)
}

#[test]
fn live_shows_the_firmware_logs_names_its_target_and_counts_frames_over_budget() {
    let dir = scratch("live");
    let report = dir.join("r.json");
    let scenario = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/needle-push-8b.toml");
    let (stdout, stderr) = ok(&deform(&[
        "live",
        scenario.to_str().unwrap(),
        "--headless",
        "--frames",
        "3",
        "--mvus",
        "1",
        "--cycle-budget",
        "1",
        "--report",
        report.to_str().unwrap(),
    ]));
    assert!(
        stderr.contains("firmware INFO") && stderr.contains("live session ready"),
        "{stderr}"
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    assert_eq!(json["target"], "qemu", "{json}");
    // A budget of one cycle: every frame is over it, and says so.
    assert_eq!(json["over_budget"]["frames"], 3, "{json}");
    let worst = json["over_budget"]["worst_cycles"].as_u64().unwrap();
    assert_eq!(worst as f64, json["frame_cycles"]["max"].as_f64().unwrap());
    assert!(
        stdout.contains("3 of 3 frame(s) over the 1 cycles"),
        "{stdout}"
    );
}

#[test]
fn bench_shows_the_firmware_logs() {
    let dir = scratch("bench");
    let (_, stderr) = ok(&deform(&[
        "bench",
        "--quick",
        "--only",
        "sweep",
        "--edges",
        "4",
        "--mvus",
        "1",
        "--models",
        "a",
        "--out",
        dir.to_str().unwrap(),
    ]));
    assert!(
        stderr.contains("firmware INFO") && stderr.contains("host connected"),
        "{stderr}"
    );
}

#[test]
fn simulate_says_when_displacement_dependent_steps_miss_the_tolerance() {
    let (_, stderr) = ok(&deform(&[
        "simulate", "--steps", "2", "--mvus", "1", "--alpha", "1,0.5,2",
    ]));
    assert!(
        stderr.contains("of 2 step(s) ended far above --tol 1e-7"),
        "{stderr}"
    );
    let (_, stderr) = ok(&deform(&["simulate", "--steps", "2", "--mvus", "1"]));
    assert!(!stderr.contains("far above --tol"), "{stderr}");
}
