//! `deform simulate --dynamic` and `deform live` on a dynamic scenario refuse bad input with a
//! clear message and a non-zero exit, before any board is opened; `[dynamics]` errors name
//! file, line and key. `deform live` runs the dynamic needle example on the host.

use std::path::Path;
use std::process::Command;

use deform_host::dynamics::{Damping, Scheme};
use deform_host::scenario::Scenario;

fn refused(args: &[&str], needle: &str) {
    refused_by("simulate", args, needle);
}

/// `deform COMMAND ARGS` fails with `needle` in its message, without a panic.
fn refused_by(command: &str, args: &[&str], needle: &str) {
    let out = Command::new(env!("CARGO_BIN_EXE_deform"))
        .arg(command)
        .args(args)
        // No QEMU may be needed: a board would only be opened after these checks.
        .env("DEFORM_FIRMWARE", "/nonexistent/firmware.elf")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{args:?} succeeded");
    assert!(
        stderr.contains(needle),
        "{args:?}: '{needle}' not in {stderr}"
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
}

#[test]
fn bad_mass_damping_and_step_are_refused() {
    for bad in ["0", "-1", "nan", "inf"] {
        // `--flag=value`: clap takes "-1" after a space for a flag of its own.
        refused(&["--dynamic", &format!("--mass={bad}")], "--mass");
        if bad != "0" {
            // β = 0 is an undamped model (below).
            refused(&["--dynamic", &format!("--damping={bad}")], "--damping");
        }
        refused(&["--dynamic", &format!("--dt={bad}")], "time step");
    }
    refused(&["--dynamic", "--damping", "1,2"], "--damping");
    refused(&["--dynamic", "--rayleigh=-1,0"], "--rayleigh");
    refused(&["--dynamic", "--scheme", "leapfrog"], "unknown scheme");
    refused(&["--mass", "1"], "add --dynamic");
    refused(
        &[
            "--dynamic",
            "--mass",
            "1e-9",
            "--dt",
            "1",
            "--grid",
            "4,4,4",
        ],
        "cannot be represented in the target's 21-bit fixed point",
    );
}

/// The max |u| column of a `--steps-csv` file.
fn max_u_column(path: &Path) -> Vec<f64> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let column = header.iter().position(|&h| h == "max_u").unwrap();
    lines
        .map(|l| l.split(',').nth(column).unwrap().parse().unwrap())
        .collect()
}

/// The trapezoidal scheme keeps an undamped model's energy, so `--damping 0` is allowed (it was
/// refused as "must be greater than 0"): on QEMU the undamped cube keeps oscillating about its
/// static shape through 40 steps, where the default β = 0.05 settles to it.
#[test]
fn an_undamped_model_keeps_oscillating_under_the_trapezoidal_scheme() {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("undamped");
    std::fs::create_dir_all(&dir).unwrap();
    let run = |damping: &str| {
        let csv = dir.join(format!("steps-{damping}.csv"));
        let out = Command::new(env!("CARGO_BIN_EXE_deform"))
            .args(["simulate", "--dynamic", "--scheme", "trapezoidal"])
            .args(["--damping", damping, "--grid", "3,3,3", "--steps", "40"])
            .arg("--steps-csv")
            .arg(&csv)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "--damping {damping}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        max_u_column(&csv)
    };
    let spread = |u: &[f64]| {
        let last = &u[u.len() - 20..];
        last.iter().copied().fold(f64::MIN, f64::max)
            - last.iter().copied().fold(f64::MAX, f64::min)
    };
    let undamped = run("0");
    let damped = run("0.05");
    assert_eq!((undamped.len(), damped.len()), (40, 40));
    let static_u = damped[damped.len() - 1];
    // Undamped: still swinging by more than half the static displacement; damped: at rest.
    assert!(spread(&undamped) > 0.5 * static_u, "{undamped:?}");
    assert!(spread(&damped) < 0.05 * static_u, "{damped:?}");
    std::fs::remove_dir_all(&dir).unwrap();
}

fn parse(src: &str) -> Result<Scenario, deform_host::scenario::ScenarioError> {
    Scenario::parse(Path::new("bad.toml"), src, None)
}

#[test]
fn the_dynamics_table_is_read_and_its_errors_name_file_line_and_key() {
    let s = parse(
        "grid = [4, 4, 4]\n[simulation]\nsteps = 3\ndt = 0.1\ndynamic = true\n\
         [dynamics]\nmass = { background = 0.5, inclusion = [{ center = [1, 1, 1], radius = 1, value = 2 }] }\n\
         damping = [0.1, 0.2, 0.3]\nrayleigh = [0.5, 0.01]\nscheme = \"trapezoidal\"\n",
    )
    .unwrap();
    assert!(s.simulation.unwrap().dynamic);
    let d = s.dynamics.unwrap();
    let mass = d.mass.unwrap();
    assert_eq!((mass.background, mass.inclusions[0].k), (0.5, 2.0));
    assert_eq!(d.damping, Some(Damping::PerDirection([0.1, 0.2, 0.3])));
    assert_eq!(d.rayleigh, Some([0.5, 0.01]));
    assert_eq!(d.scheme, Some(Scheme::Trapezoidal));

    let cases: &[(&str, usize, &str, &str)] = &[
        (
            "[dynamics]\nmass = 0\n",
            2,
            "dynamics.mass",
            "greater than 0",
        ),
        (
            "[dynamics]\nmass = [1, 2, 3]\n",
            2,
            "dynamics.mass",
            "one number per node",
        ),
        (
            "\n[dynamics]\ndamping = -0.5\n",
            3,
            "dynamics.damping",
            "greater than 0",
        ),
        (
            "[dynamics]\ndamping = { background = nan }\n",
            2,
            "dynamics.damping",
            "background",
        ),
        (
            "[dynamics]\nrayleigh = [1, -1]\n",
            2,
            "dynamics.rayleigh",
            "not negative",
        ),
        (
            "[dynamics]\nscheme = \"rk4\"\n",
            2,
            "dynamics.scheme",
            "unknown scheme",
        ),
        ("[dynamics]\nmas = 1\n", 2, "dynamics.mas", "unknown field"),
    ];
    for (src, line, key, needle) in cases {
        let e = parse(src).unwrap_err();
        let text = e.to_string();
        assert_eq!((e.line, e.key.as_str()), (*line, *key), "{text}");
        assert!(
            text.starts_with("bad.toml:") && text.contains(needle),
            "{text}"
        );
    }
}

fn deform_live(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_deform"))
        .arg("live")
        .args(args)
        // No QEMU may be needed: `--target host`, or a refusal before any board is opened.
        .env("DEFORM_FIRMWARE", "/nonexistent/firmware.elf")
        .output()
        .unwrap()
}

/// `deform live` on the dynamic needle example steps the dynamics frame by frame on the host's
/// f64 stepper: the report has the quasi-static report's keys plus `dynamic`, and the tissue
/// is still moving and displaced after the needle has been withdrawn (t = 1.6 s, frame 80).
#[test]
fn deform_live_runs_a_dynamic_scenario_on_the_host() {
    let example = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/needle-dynamic.toml");
    let dir = std::env::temp_dir().join(format!("deform-live-dynamic-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (report, csv) = (dir.join("r.json"), dir.join("f.csv"));
    let out = deform_live(&[
        example.to_str().unwrap(),
        "--target",
        "host",
        "--headless",
        "--frames",
        "100",
        "--report",
        report.to_str().unwrap(),
        "--frames-csv",
        csv.to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    for key in [
        "frames",
        "grid",
        "model",
        "mvus",
        "frame_cycles",
        "frames_per_s_at_100mhz",
        "force_updates_per_s",
        "iterations",
        "residual_max",
        "error_vs_converged_max",
        "bytes_up_per_frame",
        "bytes_down_per_frame",
        "dynamic",
    ] {
        assert!(r.get(key).is_some(), "no '{key}' in {r}");
    }
    assert_eq!(r["frames"], 100);
    assert_eq!(r["grid"], serde_json::json!([10, 10, 10]));
    assert_eq!(r["target"], "host");
    assert_eq!(r["dynamic"]["h"], 0.02);
    assert_eq!(r["dynamic"]["scheme"], "backward-euler");
    assert_eq!(r["dynamic"]["mass"], 0.005);
    // No local force model for dynamic frames: null, with the reason beside it.
    assert!(r["force_updates_per_s"].is_null());
    assert!(r["force_updates_note"]
        .as_str()
        .unwrap()
        .contains("frame rate"));
    // Frame 100 is 0.4 s after the withdrawal: the tool is at rest, the tissue is not.
    let rows: Vec<Vec<f64>> = std::fs::read_to_string(&csv)
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| {
            l.split(',')
                .map(|v| v.parse().unwrap_or(f64::NAN))
                .collect()
        })
        .collect();
    assert_eq!(rows.len(), 100);
    let last = &rows[99];
    assert_eq!(&last[2..5], &[0.0, 0.0, 0.0], "the tool is withdrawn");
    let (max_u, max_v) = (last[17], last[18]);
    assert!(
        max_u > 1e-2 && max_v > 1e-2,
        "max |u| {max_u}, max |v| {max_v}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Bad dynamic input to `deform live` gets a clear message and a non-zero exit, no panic.
#[test]
fn deform_live_refuses_bad_dynamic_input_clearly() {
    let example = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/needle-dynamic.toml");
    let example = example.to_str().unwrap();
    let dir = std::env::temp_dir().join(format!("deform-live-dyn-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let text = std::fs::read_to_string(example).unwrap();
    let zero_dt = dir.join("zero-dt.toml");
    std::fs::write(&zero_dt, text.replace("dt = 0.02", "dt = 0.0")).unwrap();
    let zero_dt = zero_dt.to_str().unwrap();
    let cases: &[(&[&str], &str)] = &[
        (
            &[zero_dt, "--headless", "--target", "host"],
            "simulation.dt",
        ),
        (&[example, "--headless", "--mass=0"], "greater than 0"),
        (&[example, "--headless", "--mass=-1"], "greater than 0"),
        (&[example, "--headless", "--damping=nan"], "finite"),
        (
            &[example, "--headless", "--cycle-budget", "1000"],
            "--cycle-budget",
        ),
        (&[example, "--headless", "--tol", "0"], "greater than 0"),
        (&[example, "--headless", "--tol", "nan"], "greater than 0"),
        // S with 1 µg nodes at h = 0.01 s: beyond the target's 21-bit values.
        (&[example, "--headless", "--mass=1e-9"], "fixed point"),
    ];
    for (args, needle) in cases {
        refused_by("live", args, needle);
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The next frame message on the live view's WebSocket.
fn next_frame<S: std::io::Read + std::io::Write>(
    ws: &mut tungstenite::WebSocket<S>,
) -> serde_json::Value {
    loop {
        let m = ws.read().unwrap();
        let v: serde_json::Value = serde_json::from_str(m.to_text().unwrap()).unwrap();
        if v["type"] == "frame" {
            return v;
        }
    }
}

/// `deform live --serve` on a dynamic scenario, on the host's f64 stepper and on the firmware
/// in QEMU: frames come one time step apart for a tool position the page sent, and go on after
/// it, the tissue still moving with the tool at rest, where the quasi-static view waits for
/// the next position.
#[test]
fn deform_live_serve_keeps_stepping_a_dynamic_scenario_while_the_tool_rests() {
    for (target, solver) in [
        ("host", "host (dynamic)"),
        ("qemu", "target (dynamic, resident)"),
    ] {
        serve_dynamic(target, solver);
    }
}

fn serve_dynamic(target: &str, solver: &str) {
    use std::io::{BufRead, BufReader};
    use std::process::Stdio;
    use tungstenite::Message;

    let example = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/needle-dynamic-8b.toml");
    /// Stops the server however the test ends: SIGTERM, which it answers by closing its board
    /// (QEMU with it), then SIGKILL if it has not ended within 10 s.
    struct Server(std::process::Child);
    impl Drop for Server {
        fn drop(&mut self) {
            // SAFETY: a signal to our own child.
            unsafe { libc::kill(self.0.id() as i32, libc::SIGTERM) };
            let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
            while std::time::Instant::now() < deadline {
                if let Ok(Some(_)) = self.0.try_wait() {
                    return;
                }
                std::thread::sleep(std::time::Duration::from_millis(50));
            }
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
    let mut command = Command::new(env!("CARGO_BIN_EXE_deform"));
    command
        .arg("live")
        .arg(&example)
        .args(["--serve", "--target", target, "--addr", "127.0.0.1:0"])
        .stdout(Stdio::piped());
    let mut server = Server(deform_hil_sim::child::spawn(command).unwrap());
    let mut out = BufReader::new(server.0.stdout.take().unwrap());
    let mut serving = String::new();
    while !serving.contains("WebSocket on port ") {
        serving.clear();
        assert!(
            out.read_line(&mut serving).unwrap() > 0,
            "no 'serving' line"
        );
    }
    let port: u16 = serving
        .split("WebSocket on port ")
        .nth(1)
        .and_then(|s| s.split(')').next())
        .and_then(|p| p.parse().ok())
        .unwrap();
    let (mut ws, _) = tungstenite::connect(format!("ws://127.0.0.1:{port}/")).unwrap();
    let first = next_frame(&mut ws);
    assert_eq!(first["solver"], solver, "{first}");
    ws.send(Message::text(r#"{"type":"tool","u":[0,0,-1]}"#))
        .unwrap();
    let mut frames = Vec::new();
    while frames.len() < 40 {
        let v = next_frame(&mut ws);
        if v["tool"] == serde_json::json!([0.0, 0.0, -1.0]) {
            frames.push(v);
        }
    }
    drop(server);
    // 40 frames for one position: the tissue moved between them (inertia, then relaxation).
    let u = |v: &serde_json::Value| -> Vec<f64> {
        v["u"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    let (a, b) = (u(&frames[0]), u(&frames[39]));
    let moved = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max);
    assert!(
        moved > 1e-3,
        "the tissue did not move between the frames: {moved:e}"
    );
    let numbers: Vec<u64> = frames
        .iter()
        .map(|v| v["frame"].as_u64().unwrap())
        .collect();
    assert!(numbers.windows(2).all(|w| w[1] > w[0]), "{numbers:?}");
}
