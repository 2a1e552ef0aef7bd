//! The fuzz targets' committed inputs as plain tests: the seed corpus (`fuzz/corpus/<target>/`)
//! and every input a fuzzer ever crashed on (`fuzz/regressions/<target>/`), through the same
//! harnesses cargo-fuzz runs (`deform_target_core::testkit::fuzz`). CI runs these without
//! libFuzzer; the coverage-guided runs themselves are documented in docs/PROTOCOL.md.

use std::path::{Path, PathBuf};

use deform_target_core::testkit::fuzz;

fn inputs(kind: &str, target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../fuzz")
        .join(kind)
        .join(target);
    let Ok(entries) = std::fs::read_dir(&dir) else {
        return Vec::new();
    };
    let mut out: Vec<_> = entries
        .map(|e| e.expect("a readable corpus directory").path())
        .filter(|p| p.is_file())
        .map(|p| {
            let bytes = std::fs::read(&p).expect("a readable corpus file");
            (p, bytes)
        })
        .collect();
    out.sort();
    out
}

fn run(target: &str, harness: fn(&[u8])) {
    let seeds = inputs("corpus", target);
    assert!(
        !seeds.is_empty(),
        "no seed corpus for {target}: run `cargo run -p deform-target-core --features testkit \
         --example fuzz_seeds`"
    );
    for (path, bytes) in seeds.iter().chain(&inputs("regressions", target)) {
        eprintln!("{}", path.display());
        harness(bytes);
    }
}

#[test]
fn frame_decoder_corpus() {
    run("frame_decoder", fuzz::frame_decoder);
}

#[test]
fn message_decoder_corpus() {
    run("message_decoder", fuzz::message_decoder);
}

#[test]
fn target_session_corpus() {
    run("target_session", fuzz::target_session);
}

#[test]
fn loader_corpus() {
    run("loader", fuzz::loader);
}

/// The committed seeds are what `fuzz::seeds` makes now (the messages have not moved on).
#[test]
fn the_seeds_are_the_committed_corpus() {
    for (target, name, input) in fuzz::seeds() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../fuzz/corpus")
            .join(target)
            .join(format!("seed-{name}"));
        let committed = std::fs::read(&path).unwrap_or_default();
        assert_eq!(
            committed,
            input,
            "{} is stale: rerun the fuzz_seeds example",
            path.display()
        );
    }
}
