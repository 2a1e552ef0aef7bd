//! The gateware's unit tests (gateware/, Migen's own simulator) against vectors that
//! target-core's portable kernel computes here: random tiled matrices in every combination of
//! split (rows, overlap), mirroring (none, all, extra mirrored tiles) and fused directions
//! (1..3), matrices wider than one 512-column window, and rows at the edge of exact sums. Each
//! case runs two phases on the same program (the second on Kp memories the first left behind).
//!
//! Then the synthesis check: one MVU, alone, for the ECP5 the boards carry, must fit and close
//! timing at the thesis's 133 MHz.
//!
//! Needs the LiteX venv (`cargo xtask setup`), which has Migen and the YoWASP tools. Set
//! `DEFORM_MVU_VECTORS_KEEP` to a folder to keep the vectors there (then `python -m unittest` in
//! gateware/ with `DEFORM_MVU_VECTORS` naming the file reruns the Python side alone).

use std::path::PathBuf;

use deform_hil_sim::gateware::{run_unit_tests, synthesize_mvu, MvuSize, VECTORS_ENV};
use deform_shared::word::{Word, VALUE_MAX, VALUE_MIN};
use deform_target_core::kernel::Lanes;
use deform_target_core::mvu_program::{build, Capacity};
use deform_target_core::testkit::mvu::{
    random_matrix, random_p, reference_mvu_phase, saturating_matrix, saturating_p, Mirroring,
    RandomMatrix, Recorded, Shape, Split,
};
use serde_json::{json, Value};

mod svu_vectors;

/// The simulated array's capacity (the gateware tests build it with these): that of the ECP5
/// builds, and small memories keep Migen's simulator quick to set up.
const CAPACITY: Capacity = Capacity {
    mvus: 3,
    nodes: 1024,
    words: 4096,
    tiles: 256,
};

fn case(name: &str, m: &RandomMatrix, mvus: usize, phases: &[(Vec<Lanes>, usize)]) -> Value {
    let mut rec = Recorded::default();
    let mut scratch = vec![[0i64; 3]; m.n];
    let cap = Capacity { mvus, ..CAPACITY };
    build(&m.tiles, &m.words, m.n, &cap, &mut scratch, &mut rec).expect("the program fits");
    let phases: Vec<Value> = phases
        .iter()
        .map(|(p, d)| {
            let want = reference_mvu_phase(m, p, *d);
            json!({
                "directions": d,
                "p": p,
                "kp": want.kp,
                "p_kp": want.p_kp[..*d].iter().map(|v| v.to_string()).collect::<Vec<_>>(),
                "kp_or": want.kp_or[..*d],
            })
        })
        .collect();
    json!({
        "name": name,
        "n": m.n,
        "mvus": mvus,
        "words": rec.words,
        "tiles": rec.tiles,
        "lengths": rec.lengths,
        "owner": rec.owner,
        "shared": rec.shared,
        "phases": phases,
    })
}

/// Words with every field at its edges, decoded by `shared::word`.
fn decoded_words() -> Value {
    let mut rng = fastrand::Rng::with_seed(21);
    let mut words: Vec<u32> = vec![0, u32::MAX, 1 << 20, (1 << 20) - 1, 0x3FE0_0000];
    for col in [0u32, 1, 255, 511] {
        for v in [VALUE_MIN, -1, 0, 1, VALUE_MAX] {
            for (er, em) in [(false, false), (true, false), (true, true)] {
                words.push(Word::new(col, i64::from(v), er, em).unwrap().bits());
            }
        }
    }
    words.extend((0..200).map(|_| rng.u32(..)));
    let rows: Vec<Value> = words
        .iter()
        .map(|&bits| {
            let w = Word(bits);
            json!([
                bits,
                w.column(),
                w.raw_value(),
                w.end_of_row(),
                w.end_of_matrix()
            ])
        })
        .collect();
    Value::Array(rows)
}

fn vectors() -> Value {
    let mut rng = fastrand::Rng::with_seed(18);
    let mut cases = Vec::new();
    let mut k = 0usize;
    for split in [Split::Rows, Split::Overlap] {
        for mirroring in [Mirroring::None, Mirroring::All, Mirroring::Extra] {
            for d in 1..=3 {
                let mvus = 1 + (k % 3).max(usize::from(split == Split::Overlap));
                k += 1;
                let shape = Shape {
                    n: rng.usize(16..40),
                    mvus,
                    split,
                    mirroring,
                    row_words: 4,
                    tile_rows: 6,
                    extremes: 10,
                };
                let m = random_matrix(&mut rng, &shape);
                let phases = [
                    (random_p(&mut rng, m.n, 10), d),
                    (random_p(&mut rng, m.n, 10), 4 - d),
                ];
                let name = format!("{split:?} {mirroring:?} {d} direction(s), {mvus} MVU(s)");
                cases.push(case(&name, &m, mvus, &phases));
            }
        }
    }
    for (split, mirroring, d) in [
        (Split::Rows, Mirroring::All, 3),
        (Split::Overlap, Mirroring::None, 2),
    ] {
        let shape = Shape {
            n: 520,
            mvus: 2,
            split,
            mirroring,
            row_words: 1,
            tile_rows: 260,
            extremes: 10,
        };
        let m = random_matrix(&mut rng, &shape);
        let phases = [(random_p(&mut rng, m.n, 10), d)];
        let name = format!("wide (n = 520, two column windows) {split:?} {mirroring:?}");
        cases.push(case(&name, &m, 2, &phases));
    }
    // The long row's words on two MVUs side by side, its own and its mirror row's sums at the
    // edge of exact arithmetic.
    let m = saturating_matrix(9, 2, true);
    let phases = [(saturating_p(9), 3)];
    cases.push(case("saturating rows, mirrored, 2 MVUs", &m, 2, &phases));
    json!({
        "capacity": {"nodes": CAPACITY.nodes, "words": CAPACITY.words, "tiles": CAPACITY.tiles},
        "decoded_words": decoded_words(),
        "cases": cases,
        "svu": svu_vectors::vectors(),
    })
}

#[test]
fn the_gateware_matches_the_portable_kernel_bit_for_bit() {
    let keep = std::env::var_os("DEFORM_MVU_VECTORS_KEEP").map(PathBuf::from);
    let dir = keep.clone().unwrap_or_else(|| {
        std::env::temp_dir().join(format!("deform-mvu-vectors-{}", std::process::id()))
    });
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("mvu_vectors.json");
    std::fs::write(&path, serde_json::to_vec(&vectors()).unwrap()).unwrap();
    let result = run_unit_tests(&path);
    if keep.is_none() {
        let _ = std::fs::remove_dir_all(&dir);
    }
    let report = result.unwrap_or_else(|e| panic!("{e}"));
    println!("{report}");
    assert!(
        report.contains("OK"),
        "the gateware's tests ({VECTORS_ENV}) did not pass:\n{report}"
    );
}

/// One MVU synthesised alone (out of context) for the LFE5U-85F at speed grade 6 with YoWASP's
/// Yosys and nextpnr-ecp5: it fits, and nextpnr's Fmax is at least the thesis's 133 MHz.
///
/// The gate's MVU is the CI size (`MvuSize::Ci`): the unit and pipeline of the ECP5 builds, with
/// every block RAM, multiplier and row compare of theirs, but a 1,024-word memory and a 16-entry
/// tile table, to shorten synthesis, placement and routing (4-6 minutes on 2 shared cores; the
/// full size took 4-23 minutes, depending on the load). The full-size unit's figures are a
/// benchmark in docs/PERFORMANCE.md (`python -m deform_gateware.synth --out DIR`).
///
/// Part of the gate since the CI size reached 141.4 MHz at seed 1 in 207 s (fmax2 branch; 146.7
/// MHz in 199 s after fmax3) and `cargo xtask setup` took the SoCs' Verilation out of the test
/// run, which made room for it.
#[test]
fn one_mvu_fits_the_ecp5_and_meets_133_mhz() {
    // In the workspace, wherever it is (a clone under /tmp too: synth.py hands the tools only
    // paths relative to this folder, which YoWASP's sandbox maps as it is).
    let out = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/gateware/synth-mvu");
    let report = synthesize_mvu(&out, MvuSize::Ci, 133.0, 6, 1).unwrap_or_else(|e| panic!("{e}"));
    println!(
        "one MVU ({} words, {} tiles, {} rows) on the LFE5U-85F: {} LUT4, {} FF, {} MULT18X18D, \
         {} DP16KD, Fmax {:.1} MHz",
        report.words,
        report.tiles,
        report.nodes,
        report.placed.lut4.used,
        report.placed.ff.used,
        report.placed.mult18x18d.used,
        report.placed.dp16kd.used,
        report.placed.fmax_mhz
    );
    assert!(report.placed.fits, "{report:?}");
    assert!(
        report.placed.meets_timing && report.placed.fmax_mhz >= 133.0,
        "Fmax {:.1} MHz, below 133: {report:?}",
        report.placed.fmax_mhz
    );
}
