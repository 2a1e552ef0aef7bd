//! `deform live` picks the tool's kind from the scenario: `[[simulation.displace]]` keyframes
//! make a displacement tool, `[[simulation.load]]` keyframes a force tool; both at once, and
//! neither, are refused clearly before any board is opened.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn deform_live(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_deform"))
        .arg("live")
        .args(args)
        // No QEMU may be needed: these run on the host or are refused before a board opens.
        .env("DEFORM_FIRMWARE", "/nonexistent/firmware.elf")
        .output()
        .unwrap()
}

fn example(name: &str) -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../examples")
        .join(name);
    path.to_str().unwrap().to_string()
}

fn scratch(name: &str) -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join(name)
}

fn refused(out: &Output, needles: &[&str]) {
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    for n in needles {
        assert!(stderr.contains(n), "'{n}' not in {stderr}");
    }
    assert!(!stderr.contains("panicked"), "{stderr}");
}

/// The f64 reference's report of a short session: its tool kind and the last frame.
fn host_report(scenario: &str, name: &str) -> serde_json::Value {
    let report = scratch(name);
    let out = deform_live(&[
        scenario,
        "--headless",
        "--target",
        "host",
        "--frames",
        "3",
        "--report",
        report.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    let _ = std::fs::remove_file(&report);
    json
}

#[test]
fn load_keyframes_make_a_force_tool_and_displace_keyframes_a_displacement_tool() {
    let force = host_report(&example("probe-force-8b.toml"), "force-host.json");
    assert_eq!(force["tool"], "force");
    let last = &force["per_frame"][2];
    assert!(last.get("force").is_none(), "{last}");
    // The probe is pressed down (−z) and drifts in +x: it moves that way.
    let u = &last["displacement"];
    assert!(
        u[2].as_f64().unwrap() < 0.0 && u[0].as_f64().unwrap() > 0.0,
        "{u}"
    );
    let push = host_report(&example("needle-push-8b.toml"), "push-host.json");
    assert_eq!(push["tool"], "displacement");
    assert!(push["per_frame"][2]["force"].is_array());
}

#[test]
fn mixed_kinds_and_no_tool_are_refused() {
    let both = scratch("both-kinds.toml");
    std::fs::write(
        &both,
        "grid = [4, 4, 4]\n[boundary]\nfix = [\"z-\"]\n[simulation]\nsteps = 2\ndt = 0.5\n\
         [[simulation.displace]]\nnode = [2, 2, 3]\nkeyframes = [[0.0, 0, 0, 0], [1.0, 0, 0, -1]]\n\
         [[simulation.load]]\nnode = [1, 1, 3]\nkeyframes = [[0.0, 0, 0, 0], [1.0, 0, 0, -1]]\n",
    )
    .unwrap();
    let out = deform_live(&[both.to_str().unwrap(), "--headless", "--target", "host"]);
    refused(&out, &["both-kinds.toml", "not both"]);
    let _ = std::fs::remove_file(&both);
    let none = scratch("no-tool.toml");
    std::fs::write(
        &none,
        "grid = [4, 4, 4]\n[simulation]\nsteps = 2\ndt = 0.5\n",
    )
    .unwrap();
    let out = deform_live(&[none.to_str().unwrap(), "--headless", "--target", "host"]);
    refused(&out, &["no-tool.toml", "[[simulation.load]]"]);
    let _ = std::fs::remove_file(&none);
}
