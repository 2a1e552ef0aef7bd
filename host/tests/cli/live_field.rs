//! `deform live --field`: which nodes a field frame carries. Bad selections are refused by
//! the argument parser with the accepted forms named; a headless session on QEMU reports the
//! selection it used, its node count and its bytes per component on the line; `--serve` tells
//! the page which nodes arrive.

use std::path::Path;
use std::process::Command;

use super::live_browser::serve;

const SCENARIO: &str = "../examples/needle-push-8b.toml";

fn deform_live(args: &[&str]) -> std::process::Output {
    let scenario = Path::new(env!("CARGO_MANIFEST_DIR")).join(SCENARIO);
    Command::new(env!("CARGO_BIN_EXE_deform"))
        .arg("live")
        .arg(&scenario)
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn bad_field_selections_are_refused_with_the_forms_named() {
    for bad in ["stride:0", "stride:x", "stride:70000", "edges", ""] {
        let out = deform_live(&["--headless", "--frames", "1", "--field", bad]);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{bad}: {stderr}");
        assert!(
            stderr.contains("--field") && stderr.contains("stride"),
            "{bad}: {stderr}"
        );
    }
    let help = deform_live(&["--help"]);
    let text = String::from_utf8_lossy(&help.stdout);
    assert!(text.contains("all|surface|stride:K"), "{text}");
}

#[test]
fn a_surface_session_reports_its_selection_and_bytes() {
    let dir = std::env::temp_dir().join(format!("deform-live-field-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let report = dir.join("r.json");
    let out = deform_live(&[
        "--headless",
        "--frames",
        "2",
        "--field-every",
        "1",
        "--field",
        "surface",
        "--mvus",
        "2",
        "--report",
        report.to_str().unwrap(),
    ]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    let field = &json["bytes_down_per_frame"];
    assert_eq!(field["field_selection"], "surface", "{field}");
    // 8³ nodes, 6³ of them inside.
    assert_eq!(field["field_nodes"], 512 - 216, "{field}");
    let per = field["field_per_component"].as_f64().unwrap();
    assert!(per > 0.0 && per <= 2.0, "{field}");
    assert!(field["field_build_cycles"].as_u64().unwrap() > 0, "{field}");
    assert!(json["field_quantisation_error_max"].as_f64().unwrap() <= 1.0 / 32767.0);
    assert!(
        stdout.contains("field       surface (296 nodes)"),
        "{stdout}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_surface_view_tells_the_page_which_nodes_arrive() {
    let scenario = Path::new(env!("CARGO_MANIFEST_DIR")).join(SCENARIO);
    let (_server, _, port) = serve(&scenario, &["--field", "surface", "--mvus", "2"]);
    let (mut ws, _) = tungstenite::connect(format!("ws://127.0.0.1:{port}/")).unwrap();
    let text = |m: tungstenite::Message| -> serde_json::Value {
        serde_json::from_str(m.to_text().unwrap()).unwrap()
    };
    let mesh = text(ws.read().unwrap());
    let shown: Vec<bool> = serde_json::from_value(mesh["shown"].clone()).unwrap();
    let nodes = mesh["nodes"].as_array().unwrap();
    assert_eq!(shown.len(), 512);
    for (node, &on) in nodes.iter().zip(&shown) {
        let c: Vec<u64> = serde_json::from_value(node.clone()).unwrap();
        let inside = c.iter().all(|&c| (1..=6).contains(&c));
        assert_eq!(on, !inside, "{c:?}");
    }
    // The first frame: the inside, not sent, at rest.
    let frame = loop {
        let m = text(ws.read().unwrap());
        if m["type"] == "frame" {
            break m;
        }
    };
    let u: Vec<f64> = serde_json::from_value(frame["u"].clone()).unwrap();
    assert_eq!(u.len(), 3 * 512);
    for (p, &on) in shown.iter().enumerate() {
        if !on {
            assert_eq!(&u[3 * p..3 * p + 3], [0.0; 3], "node {p}");
        }
    }
}
