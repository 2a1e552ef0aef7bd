//! Scenario files: the shipped examples load, errors name file, key and line, flags override.

use std::path::{Path, PathBuf};
use std::process::Command;

use deform_host::model::{Model, Node};
use deform_host::scenario::{Scenario, ScenarioError};

fn examples() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples")
}

fn error(src: &str) -> ScenarioError {
    Scenario::parse(Path::new("bad.toml"), src, None).unwrap_err()
}

#[test]
fn shipped_examples_load_and_build() {
    for name in [
        "thesis-cube",
        "tumour-palpation",
        "needle-insertion",
        "needle-dynamic",
        "needle-dynamic-8b",
        "needle-push-8b",
    ] {
        let s = Scenario::load(&examples().join(format!("{name}.toml")), None).unwrap();
        Model::build(&s.model).unwrap();
    }
    let cube = Scenario::load(&examples().join("thesis-cube.toml"), None).unwrap();
    assert_eq!(cube.model, deform_host::model::ModelSpec::thesis_example());
    let needle = Scenario::load(&examples().join("needle-insertion.toml"), None).unwrap();
    assert_eq!(needle.model.prescribed.len(), 1);
    assert_eq!(needle.model.prescribed[0].node, Node::new(5, 5, 9));
    assert_eq!(needle.model.prescribed[0].u, [0.0, 0.0, -2.0]);
    let sim = needle.simulation.unwrap();
    assert_eq!((sim.steps, sim.dt), (75, 0.02));
    assert_eq!(sim.displace[0].value_at(0.5), [0.0, 0.0, -1.0]);
}

#[test]
fn errors_name_file_key_and_line() {
    let cases: &[(&str, usize, &str, &str)] = &[
        ("grid = [4, 4, 4]\ncolour = 3\n", 2, "colour", "unknown field"),
        ("[boundary]\nfix = [\"corners\"]\nfix_node = [[0,0,0]]\n", 3, "boundary.fix_node", "unknown field"),
        ("[solver]\ntol = \"small\"\n", 2, "solver.tol", "invalid type"),
        ("grid = [4, 4, 4]\n\n[loads]\npoint = [{ node = [4, 0, 0], force = [1, 0, 0] }]\n", 4, "loads.point", "outside the 4×4×4 grid"),
        ("[boundary]\nfix = [\"corners\", \"edges\"]\n", 2, "boundary.fix", "'edges'"),
        ("[elasticity]\nk = [1, -2, 3]\n", 2, "elasticity.k", "k_y"),
        ("[loads]\npressure = [{ face = \"top\", force = [0, 0, 1] }]\n", 2, "loads.pressure", "'top'"),
        ("[simulation]\nsteps = 5\ndt = 0.1\n[[simulation.displace]]\nnode = [0, 0, 0]\nkeyframes = [[1, 0, 0, 0], [0, 1, 1, 1]]\n", 6, "simulation.displace", "sorted"),
        ("[simulation]\nsteps = 5\ndt = 0.1\n[[simulation.load]]\nnode = [0, 0, 10]\nkeyframes = [[0, 0, 0, 0]]\n", 5, "simulation.load", "outside"),
        ("[elasticity]\ninclusion = [{ center = [1, 1, 1], radius = 1, k = 5 }]\n", 2, "elasticity.background", "background"),
    ];
    for (src, line, key, needle) in cases {
        let e = error(src);
        let text = e.to_string();
        assert_eq!(e.line, *line, "{text}");
        assert_eq!(e.key, *key, "{text}");
        assert!(text.starts_with("bad.toml:"), "{text}");
        assert!(text.contains(needle), "'{needle}' not in {text}");
    }
}

#[test]
fn field_csv_is_read_relative_to_the_file() {
    let dir = std::env::temp_dir().join(format!("deform-scenario-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(
        dir.join("k.csv"),
        "i,j,k,k\n1,1,1,4\n# comment\n0,0,0,2.5\n",
    )
    .unwrap();
    let toml = "grid = [3, 3, 3]\n[elasticity]\nk = 1\nfield = \"k.csv\"\n";
    std::fs::write(dir.join("s.toml"), toml).unwrap();
    let s = Scenario::load(&dir.join("s.toml"), None).unwrap();
    let model = Model::build(&s.model).unwrap();
    let k = model.node_stiffness();
    assert_eq!((k[13], k[0], k[1]), (4.0, 2.5, 1.0));

    std::fs::write(dir.join("k.csv"), "1,1,1,4\n1,1,5,4\n").unwrap();
    let e = Scenario::load(&dir.join("s.toml"), None).unwrap_err();
    std::fs::remove_dir_all(&dir).unwrap();
    assert_eq!((e.line, e.key.as_str()), (4, "elasticity.field"));
    assert!(
        e.message.contains("k.csv:2") && e.message.contains("outside"),
        "{e}"
    );
}

#[test]
fn flags_override_the_file_on_the_command_line() {
    let run = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_deform"))
            .args(args)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    let cube = examples().join("thesis-cube.toml");
    let cube = cube.to_str().unwrap();
    let text = run(&["model", cube]);
    assert!(
        text.contains("10×10×10 grid, model A") && text.contains("bandwidth      100"),
        "{text}"
    );
    let text = run(&["model", cube, "--model", "b", "--grid", "6,6,6"]);
    assert!(text.contains("6×6×6 grid, model B"), "{text}");
    let text = run(&["solve", cube, "--target", "host", "--k", "2"]);
    assert!(text.contains("k_x = 2, k_y = 2, k_z = 2"), "{text}");
    let needle = examples().join("needle-insertion.toml");
    let text = run(&[
        "solve",
        needle.to_str().unwrap(),
        "--target",
        "host",
        "--displace",
        "5,5,9:0,0,-1",
    ]);
    assert!(text.contains("max |u|     1.0"), "{text}");

    let bad = Command::new(env!("CARGO_BIN_EXE_deform"))
        .args(["solve", "no-such-file.toml", "--target", "host"])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("no-such-file.toml"));
}
