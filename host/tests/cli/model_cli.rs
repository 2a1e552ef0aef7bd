//! `deform model` end to end: exit codes, output and the exported Matrix Market file.

use std::path::PathBuf;
use std::process::{Command, Output};

fn deform(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_deform"))
        .args(args)
        .output()
        .expect("the deform binary runs")
}

fn stdout(output: &Output) -> String {
    String::from_utf8_lossy(&output.stdout).into_owned()
}

fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

#[test]
fn default_scenario_reports_the_thesis_example() {
    let out = deform(&["model"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    for needle in [
        "10×10×10 grid, model A",
        "k_x = 1, k_y = 2, k_z = 0.5",
        "fixed nodes    8",
        "n              1000",
        "nnz            6352",
        "99.3000 % by thesis eq. 37",
        "bandwidth      100",
        "symmetric      yes",
        "17 fractional bits",
        "0 (exact)",
    ] {
        assert!(text.contains(needle), "'{needle}' missing from:\n{text}");
    }
}

#[test]
fn model_b_has_27_nonzeros_per_row_and_band_111() {
    let out = deform(&["model", "--model", "b"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    assert!(
        text.contains("1 − 27/n") && text.contains("bandwidth      111"),
        "{text}"
    );
}

#[test]
fn exports_k_x_in_matrix_market_format() {
    let dir = std::env::temp_dir().join(format!("deform-cli-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path: PathBuf = dir.join("k.mtx");
    let out = deform(&[
        "model",
        "--grid",
        "2,2,2",
        "--k",
        "2,1,1",
        "--export-mtx",
        path.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&path).unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
    let mut lines = text.lines();
    assert_eq!(
        lines.next(),
        Some("%%MatrixMarket matrix coordinate real general")
    );
    let body: Vec<&str> = lines.filter(|l| !l.starts_with('%')).collect();
    // 2×2×2 with all 8 corners fixed: K_x = 2·3·I, only the diagonal is left.
    assert_eq!(body[0], "8 8 8");
    let expected: Vec<String> = (1..=8).map(|p| format!("{p} {p} 6e0")).collect();
    assert_eq!(
        body[1..],
        expected.iter().map(String::as_str).collect::<Vec<_>>()[..]
    );
}

#[test]
fn bad_flags_fail_with_a_clear_message() {
    let cases: &[(&[&str], &str)] = &[
        (&["model", "--grid", "10,10"], "--grid"),
        (&["model", "--k", "0"], "greater than 0"),
        (&["model", "--fix", "edges"], "'edges'"),
        (&["model", "--load", "1,2,3"], "I,J,K:FX,FY,FZ"),
        (
            &["model", "--load", "10,0,0:1,0,0"],
            "outside the 10×10×10 grid",
        ),
        (&["model", "--fix", "none"], "no node is fixed"),
        (
            &["model", "--export-mtx", "/nonexistent-dir/k.mtx"],
            "writing /nonexistent-dir/k.mtx",
        ),
    ];
    for (args, needle) in cases {
        let out = deform(args);
        assert!(!out.status.success(), "{args:?} succeeded");
        let message = stderr(&out);
        assert!(
            message.contains(needle),
            "{args:?}: '{needle}' not in {message}"
        );
        assert!(!message.contains("panicked"), "{args:?}: {message}");
    }
}

#[test]
fn loads_only_on_fixed_nodes_warn_but_succeed() {
    let out = deform(&["model", "--load", "0,0,0:1,0,0"]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(stderr(&out).contains("fixed node and is ignored"));
}

#[test]
fn a_band_wider_than_one_window_encodes_in_halves() {
    // Model B on 16³: rows span 547 columns, more than a tile's 512.
    let out = deform(&["model", "--grid", "16,16,16", "--model", "b"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    assert!(text.contains("bandwidth      273"), "{text}");
    assert!(
        text.contains("16 tile(s), 97227 words (3 empty-row)"),
        "{text}"
    );
    assert!(
        text.contains(
            "persymmetric   yes: conjugate symmetry stores half, 48612 words in 8 tile(s)"
        ),
        "{text}"
    );
}

/// The advertised limit of 2²⁴ nodes (a 256³ grid) is refused before anything is allocated, with
/// what it would need and what the machine has: `model` and `solve` both allocated past 5 GB
/// and died in the allocator (exit 134). Model B needs ~29 GB, more than this machine has; model
/// A (~10 GB) is run under an address-space limit of 2 GB (`ulimit -v`), which counts as what the
/// process may take.
#[test]
fn the_largest_grid_is_refused_before_allocating_with_what_it_needs() {
    let refused = |out: &Output, what: &str| {
        let message = stderr(out);
        assert_eq!(out.status.code(), Some(1), "{what}: {message}");
        for needle in [
            "256×256×256",
            "needs about",
            "GB",
            "available",
            "smaller --grid",
        ] {
            assert!(
                message.contains(needle),
                "{what}: '{needle}' not in {message}"
            );
        }
        assert!(!message.contains("panicked"), "{what}: {message}");
    };
    for command in ["model", "solve"] {
        let started = std::time::Instant::now();
        let out = deform(&[command, "--grid", "256,256,256", "--model", "b"]);
        refused(&out, command);
        assert!(
            stderr(&out).contains("16777216 nodes and 449455096 nonzeros"),
            "{}",
            stderr(&out)
        );
        assert!(started.elapsed() < std::time::Duration::from_secs(20));
        let limited = Command::new("sh")
            .arg("-c")
            .arg(r#"ulimit -v 2000000 && exec "$0" "$@""#)
            .arg(env!("CARGO_BIN_EXE_deform"))
            .args([command, "--grid", "256,256,256", "--model", "a"])
            .output()
            .expect("sh runs");
        refused(&limited, &format!("{command} (model A, ulimit -v)"));
    }
}
