//! `deform simulate --dynamic` refuses bad input with a clear message and a non-zero exit,
//! before any board is opened; `[dynamics]` errors name file, line and key.

use std::path::Path;
use std::process::Command;

use deform_host::dynamics::{Damping, Scheme};
use deform_host::scenario::Scenario;

fn refused(args: &[&str], needle: &str) {
    let out = Command::new(env!("CARGO_BIN_EXE_deform"))
        .arg("simulate")
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
        refused(&["--dynamic", &format!("--damping={bad}")], "--damping");
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

/// `deform live` does not step dynamics: a dynamic scenario is refused by name, before any
/// board is opened, instead of being run as quasi-static frames.
#[test]
fn deform_live_refuses_a_dynamic_scenario_clearly() {
    let example = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/needle-dynamic.toml");
    let out = Command::new(env!("CARGO_BIN_EXE_deform"))
        .args([
            "live",
            example.to_str().unwrap(),
            "--headless",
            "--frames",
            "2",
        ])
        .env("DEFORM_FIRMWARE", "/nonexistent/firmware.elf")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("dynamic = true") && stderr.contains("deform simulate"),
        "{stderr}"
    );
}
