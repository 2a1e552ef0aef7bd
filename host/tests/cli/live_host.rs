//! `deform live` on the host and its flags, tried as a careless script would: every output flag
//! works with `--target host`, a flag that does not apply is refused before anything starts,
//! `--tol` and `--max-iter` are checked as `deform solve` checks them, outputs never clobber an
//! input or each other, an interrupted session leaves readable files, a huge `--frames` is
//! refused with what it would need, and a tool on a fixed node is named as a person writes it.
//! No QEMU is needed: everything here runs on the host or is refused first.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

fn deform(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_deform"))
        .args(args)
        // No QEMU may be needed: these run on the host or are refused before a board opens.
        .env("DEFORM_FIRMWARE", "/nonexistent/firmware.elf")
        .output()
        .unwrap()
}

fn scratch(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("live-host-{name}"));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A 4³ block on a fixed base, the tip pushed down over 0.4 s in 8 steps: quick on the host.
fn small_push(dir: &Path) -> String {
    let path = dir.join("push.toml");
    std::fs::write(
        &path,
        "grid = [4, 4, 4]\nmodel = \"b\"\n[boundary]\nfix = [\"z-\"]\n[simulation]\nsteps = 8\n\
         dt = 0.05\n[[simulation.displace]]\nnode = [2, 2, 3]\n\
         keyframes = [[0.0, 0, 0, 0], [0.4, 0, 0, -1]]\n",
    )
    .unwrap();
    path.to_str().unwrap().to_string()
}

fn refused(out: &Output, needles: &[&str]) {
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_ne!(out.status.code(), Some(0), "{stderr}");
    for n in needles {
        assert!(stderr.contains(n), "'{n}' not in {stderr}");
    }
    assert!(!stderr.contains("panicked"), "{stderr}");
}

fn ok(out: &Output) -> String {
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

#[test]
fn every_output_flag_works_on_the_host_and_target_flags_are_refused() {
    let dir = scratch("outputs");
    let scenario = small_push(&dir);
    let (csv, out, report) = (dir.join("f.csv"), dir.join("series"), dir.join("r.json"));
    let stdout = ok(&deform(&[
        "live",
        &scenario,
        "--headless",
        "--target",
        "host",
        "--frames-csv",
        csv.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--report",
        report.to_str().unwrap(),
    ]));
    assert!(!stdout.contains("MVU"), "{stdout}");
    let table = std::fs::read_to_string(&csv).unwrap();
    let lines: Vec<&str> = table.lines().collect();
    assert_eq!(lines.len(), 1 + 8, "{table}");
    assert!(lines[0].starts_with("frame,t,tool_x,tool_y,tool_z,fx,fy,fz"));
    let pvd = std::fs::read_to_string(out.join("series.pvd")).unwrap();
    assert_eq!(pvd.matches("<DataSet").count(), 8, "{pvd}");
    assert!(out.join("frame_00008.vtu").is_file());
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    assert_eq!(json["target"], "host");
    assert_eq!(json["frames"], 8);
    for flag in [
        &["--tol", "1e-3"][..],
        &["--max-iter", "50"],
        &["--cycle-budget", "1000"],
        &["--field", "surface"],
        &["--field-every", "2"],
        &["--forces-per-frame", "1"],
        &["--mvus", "2"],
        &["--timeout", "5"],
    ] {
        let mut argv = vec!["live", &scenario, "--headless", "--target", "host"];
        argv.extend_from_slice(flag);
        refused(&deform(&argv), &[flag[0]]);
    }
}

#[test]
fn tolerance_and_iterations_are_checked_as_solve_checks_them() {
    let dir = scratch("tol");
    let scenario = small_push(&dir);
    for tol in ["0", "-1", "10", "NaN", "inf"] {
        let out = deform(&["live", &scenario, "--headless", "--tol", tol]);
        refused(&out, &["--tol", "(0, 1)"]);
        assert!(
            !String::from_utf8_lossy(&out.stderr).contains("tool displacement"),
            "{tol}"
        );
    }
    refused(
        &deform(&["live", &scenario, "--headless", "--max-iter", "0"]),
        &["--max-iter"],
    );
    let help = String::from_utf8_lossy(&deform(&["live", "--help"]).stdout).into_owned();
    assert!(help.contains("296 of 512 on an 8³ grid"), "{help}");
    assert!(!help.contains("386 of 729"), "{help}");
}

#[test]
fn an_output_is_never_an_input_or_another_output_and_is_checked_first() {
    let dir = scratch("clobber");
    let scenario = small_push(&dir);
    let before = std::fs::read_to_string(&scenario).unwrap();
    let same = dir.join("x.csv");
    let same = same.to_str().unwrap();
    refused(
        &deform(&[
            "live",
            &scenario,
            "--headless",
            "--target",
            "host",
            "--report",
            same,
            "--frames-csv",
            same,
        ]),
        &["writes there too"],
    );
    refused(
        &deform(&["observe", &scenario, "--out", &scenario]),
        &["the scenario this command reads"],
    );
    assert_eq!(std::fs::read_to_string(&scenario).unwrap(), before);
    // Refused at once, not after the work.
    let started = Instant::now();
    refused(
        &deform(&[
            "live",
            &scenario,
            "--headless",
            "--target",
            "host",
            "--report",
            "/no/such/dir/r.json",
        ]),
        &["/no/such/dir", "does not exist"],
    );
    refused(
        &deform(&[
            "solve",
            "--target",
            "host",
            "--grid",
            "30,30,30",
            "--out",
            "/no/such/dir/u.csv",
        ]),
        &["/no/such/dir", "does not exist"],
    );
    assert!(started.elapsed() < Duration::from_secs(20));
    assert!(!dir.join("x.csv").exists());
}

#[test]
fn pace_counts_solved_frames_only() {
    let dir = scratch("pace");
    let scenario = small_push(&dir);
    let report = dir.join("r.json");
    ok(&deform(&[
        "live",
        &scenario,
        "--headless",
        "--target",
        "host",
        "--pace",
        "20",
        "--report",
        report.to_str().unwrap(),
    ]));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    let frames = json["per_frame"].as_array().unwrap();
    // 0.4 s at 20 frames/s: at most 8 slots, each solved once.
    assert!(!frames.is_empty() && frames.len() <= 8, "{json}");
    let times: Vec<f64> = frames.iter().map(|f| f["t"].as_f64().unwrap()).collect();
    assert!(times.windows(2).all(|w| w[1] > w[0]), "{times:?}");
    assert_eq!(json["frames"].as_u64().unwrap() as usize, frames.len());
}

#[test]
fn a_huge_frame_count_is_refused_with_what_it_would_need() {
    let dir = scratch("huge");
    let scenario = small_push(&dir);
    let started = Instant::now();
    refused(
        &deform(&[
            "live",
            &scenario,
            "--headless",
            "--target",
            "host",
            "--frames",
            "4294967295",
        ]),
        &["4294967295 frames", "available"],
    );
    assert!(started.elapsed() < Duration::from_secs(20));
}

#[test]
fn an_interrupted_session_leaves_readable_files() {
    let dir = scratch("interrupt");
    let scenario = small_push(&dir);
    let (csv, out, report) = (dir.join("f.csv"), dir.join("series"), dir.join("r.json"));
    let child = Command::new(env!("CARGO_BIN_EXE_deform"))
        .args([
            "live",
            &scenario,
            "--headless",
            "--target",
            "host",
            "--frames",
            "100000",
            "--frames-csv",
            csv.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--report",
            report.to_str().unwrap(),
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Let some frames through, then stop it as `kill` would.
    let deadline = Instant::now() + Duration::from_secs(60);
    while !out.join("frame_00020.vtu").exists() {
        assert!(Instant::now() < deadline, "no frames written");
        std::thread::sleep(Duration::from_millis(50));
    }
    // SAFETY: a signal to our own child.
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    let done = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&done.stderr);
    assert_eq!(done.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("interrupted after"), "{stderr}");
    let table = std::fs::read_to_string(&csv).unwrap();
    let rows = table.lines().count() - 1;
    assert!(rows >= 20, "{rows} rows");
    let pvd = std::fs::read_to_string(out.join("series.pvd")).unwrap();
    assert_eq!(pvd.matches("<DataSet").count(), rows, "{pvd}");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    assert_eq!(json["frames"].as_u64().unwrap() as usize, rows);
    let leftovers: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .chain(std::fs::read_dir(&out).unwrap())
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().ends_with(".part"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

#[test]
fn a_force_tool_on_a_fixed_node_is_named_with_its_file_and_line() {
    let dir = scratch("fixed-tool");
    let path = dir.join("probe.toml");
    std::fs::write(
        &path,
        "grid = [8, 8, 8]\n[boundary]\nfix = [\"z-\"]\n[simulation]\nsteps = 2\ndt = 0.5\n\n\
         [[simulation.load]]\nnode = [4, 4, 0]\nkeyframes = [[0.0, 0, 0, 0], [1.0, 0, 0, -1]]\n",
    )
    .unwrap();
    let out = deform(&[
        "live",
        path.to_str().unwrap(),
        "--headless",
        "--target",
        "host",
    ]);
    refused(&out, &["probe.toml:9:", "(4, 4, 0)", "fixed"]);
    assert!(!String::from_utf8_lossy(&out.stderr).contains("Node {"));
}

#[test]
fn a_node_field_names_its_quantity_and_refuses_a_node_given_twice() {
    let dir = scratch("fields");
    std::fs::write(dir.join("mass.csv"), "i,j,k,m\n0,0,0,0.1\n1,1,1,-2\n").unwrap();
    std::fs::write(dir.join("k.csv"), "0,0,0,1\n1,0,0,2\n0,0,0,3\n").unwrap();
    let mass = dir.join("mass.toml");
    std::fs::write(
        &mass,
        "grid = [4, 4, 4]\n[dynamics]\nmass = { background = 0.1, field = \"mass.csv\" }\n",
    )
    .unwrap();
    let out = deform(&["model", mass.to_str().unwrap()]);
    refused(&out, &["mass.csv:3", "mass -2", "kg"]);
    assert!(!String::from_utf8_lossy(&out.stderr).contains("stiffness"));
    let stiff = dir.join("k.toml");
    std::fs::write(
        &stiff,
        "grid = [4, 4, 4]\n[elasticity]\nbackground = 1.0\nfield = \"k.csv\"\n",
    )
    .unwrap();
    refused(
        &deform(&["model", stiff.to_str().unwrap()]),
        &["k.csv:3", "second time", "line 1"],
    );
}
