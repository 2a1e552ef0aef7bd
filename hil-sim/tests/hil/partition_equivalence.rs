//! The CG engine's layouts on the firmware in QEMU: 1, 2, 4 and 8 MVUs, both partition schemes,
//! with and without conjugate symmetry, all equal to each other and to the f64 reference; the
//! three directions fused against one at a time; Jacobi scaling on a stiff inclusion.

use crate::support;

use deform_host::encode::{encode_with, EncodeOptions, EncodedMatrix, Partition};
use deform_host::link::Target;
use deform_host::model::{
    Axis, Connection, Grid, Inclusion, Model, ModelSpec, Node, NodeField, PointLoad,
};
use deform_host::precondition::{self, Preconditioner};
use deform_host::reference::{self, max_abs, max_abs_diff};
use deform_host::refine::{solve_refined, RefineParams, Refined};

use support::*;

/// The harts QEMU boots: the most MVUs a tile may name.
const HARTS: u8 = 8;

/// A 6×6×6 model-B cube, corners fixed (so A is persymmetric), loads in all three directions.
fn cube() -> Model {
    let grid = Grid::new(6, 6, 6).unwrap();
    Model::build(&ModelSpec {
        grid,
        connection: Connection::AxialShear,
        loads: vec![
            PointLoad {
                node: Node::new(0, 3, 3),
                force: [1.0, 0.5, 0.0],
            },
            PointLoad {
                node: Node::new(4, 1, 2),
                force: [0.0, -0.7, 2.0],
            },
        ],
        ..ModelSpec::thesis_example()
    })
    .expect("model builds")
}

fn params(tol: f64, fuse: bool) -> RefineParams {
    RefineParams {
        tol,
        max_solves: 8,
        max_iterations: 4000,
        fuse,
    }
}

fn rhs(model: &Model) -> Vec<Vec<f64>> {
    Axis::ALL.iter().map(|&d| model.scaled_rhs(d)).collect()
}

fn solve(
    target: &mut Target,
    model: &Model,
    options: EncodeOptions,
    preconditioner: Preconditioner,
    params: RefineParams,
) -> (EncodedMatrix, Refined) {
    let a = model.unit_matrix();
    let scaled = precondition::scale(a, preconditioner).unwrap();
    let encoding = encode_with(&scaled.matrix, &options).unwrap();
    assert_eq!(encoding.summary.mvus, options.mvus, "{options:?}");
    target.upload_matrix(&encoding.matrix).expect("upload");
    let rhs = rhs(model);
    let refs: Vec<&[f64]> = rhs.iter().map(Vec::as_slice).collect();
    let refined = solve_refined(target, a, &scaled, &refs, params).expect("solve on QEMU");
    (encoding.matrix, refined)
}

/// Whether two MVUs write the same row of Kp (a mirrored tile writes its rows and their mirrors).
fn shares_rows(matrix: &EncodedMatrix) -> bool {
    let n = matrix.n;
    let mut writer: Vec<Option<u8>> = vec![None; n as usize];
    let mut shared = false;
    for t in &matrix.tiles {
        let rows = t.row_base..t.row_base + t.rows;
        let mirrors = rows.clone().filter(|_| t.mirrored).map(|r| n - 1 - r);
        for r in rows.chain(mirrors) {
            let w = writer[r as usize].get_or_insert(t.mvu);
            shared |= *w != t.mvu;
        }
    }
    shared
}

#[test]
fn every_layout_matches_f64_and_each_other() {
    let mut qemu = boot_harts(HARTS);
    let mut target = connect(&qemu);
    let harts = target.info().harts;
    assert_eq!(harts, HARTS, "the firmware puts every hart to work");
    let model = cube();
    let a = model.unit_matrix();
    let reference: Vec<Vec<f64>> = rhs(&model)
        .iter()
        .map(|b| reference::solve(a, b, None, 1e-12, 10_000).unwrap().x)
        .collect();
    let scale = reference.iter().map(|x| max_abs(x)).fold(0.0, f64::max);
    let mut first: Option<Vec<Vec<f64>>> = None;
    for mvus in [1u8, 2, 4, 8] {
        for partition in [Partition::Rows, Partition::Overlap] {
            for use_symmetry in [false, true] {
                let options = EncodeOptions {
                    mvus,
                    partition,
                    use_symmetry,
                };
                let (layout, got) = solve(
                    &mut target,
                    &model,
                    options,
                    Preconditioner::None,
                    params(1e-10, true),
                );
                let report = &got.reports[0];
                assert_eq!(report.mvus, mvus);
                assert_eq!(report.saturations, 0);
                // Row blocks never share a row; equal nonzero runs do unless a cut falls on a row end.
                assert_eq!(report.overlapping, shares_rows(&layout), "{options:?}");
                if partition == Partition::Rows {
                    assert!(!report.overlapping, "{options:?}");
                }
                let cost = report.per_iteration;
                println!(
                    "{mvus} MVU(s), {partition}, symmetry {use_symmetry}: iterations {:?}, solves {}, \
                     per iteration MVU critical {} / total {}, SVU critical {}",
                    got.directions.iter().map(|d| d.iterations).collect::<Vec<_>>(),
                    got.reports.len(),
                    cost.mvu_critical.instructions,
                    cost.mvu_total.instructions,
                    cost.svu_critical.instructions
                );
                let xs: Vec<Vec<f64>> = got.directions.iter().map(|d| d.x.clone()).collect();
                for (d, (x, want)) in xs.iter().zip(&reference).enumerate() {
                    assert!(got.directions[d].relative_residual <= 1e-10);
                    let dev = max_abs_diff(x, want) / scale;
                    assert!(dev <= 1e-8, "{options:?} direction {d}: deviation {dev:e}");
                }
                match &first {
                    None => first = Some(xs),
                    Some(first) => {
                        for (x, y) in xs.iter().zip(first) {
                            assert!(max_abs_diff(x, y) / scale <= 1e-8, "{options:?}");
                        }
                    }
                }
            }
        }
    }
    assert_alive(&mut qemu);
}

#[test]
fn fused_directions_fetch_each_word_once_for_all_three() {
    let mut qemu = boot_harts(1);
    let mut target = connect(&qemu);
    let model = cube();
    let options = EncodeOptions::default();
    let (_, fused) = solve(
        &mut target,
        &model,
        options,
        Preconditioner::None,
        params(1e-9, true),
    );
    let (_, single) = solve(
        &mut target,
        &model,
        options,
        Preconditioner::None,
        params(1e-9, false),
    );
    println!(
        "6³ model B, 3 directions to 1e-9: fused {} words fetched, {} critical-path cycles; \
         one at a time {} words, {} cycles",
        fused.words_fetched(),
        fused.critical_path_cycles(),
        single.words_fetched(),
        single.critical_path_cycles()
    );
    for (f, s) in fused.directions.iter().zip(&single.directions) {
        assert!(max_abs_diff(&f.x, &s.x) <= 1e-7 * max_abs(&s.x));
    }
    assert!(fused.words_fetched() * 2 < single.words_fetched());
    assert!(fused.critical_path_cycles() < single.critical_path_cycles());
    assert_alive(&mut qemu);
}

#[test]
fn jacobi_cuts_iterations_on_a_stiff_inclusion() {
    let mut qemu = boot_harts(1);
    let mut target = connect(&qemu);
    let grid = Grid::new(8, 8, 8).unwrap();
    let model = Model::build(&ModelSpec {
        grid,
        connection: Connection::Axial,
        field: Some(NodeField {
            background: 1.0,
            inclusions: vec![Inclusion {
                center: [4.0, 4.0, 4.0],
                radius: 2.0,
                k: 1000.0,
            }],
            nodes: Vec::new(),
        }),
        loads: vec![ModelSpec::default_load(grid)],
        ..ModelSpec::thesis_example()
    })
    .unwrap();
    let options = EncodeOptions::default();
    let want = reference::solve(
        model.unit_matrix(),
        &model.scaled_rhs(Axis::X),
        None,
        1e-11,
        20_000,
    )
    .unwrap()
    .x;
    let mut iterations = Vec::new();
    for preconditioner in [Preconditioner::None, Preconditioner::Jacobi] {
        let (_, got) = solve(
            &mut target,
            &model,
            options,
            preconditioner,
            params(1e-10, true),
        );
        let x = &got.directions[0];
        assert!(x.relative_residual <= 1e-10, "{preconditioner}: {x:?}");
        assert!(max_abs_diff(&x.x, &want) <= 1e-7 * max_abs(&want));
        println!(
            "8³ stiff inclusion (1000×), precondition {preconditioner}: {} iterations in {} solves",
            x.iterations, x.solves
        );
        iterations.push(x.iterations);
    }
    assert!(iterations[1] * 3 < iterations[0] * 2, "{iterations:?}");
    assert_alive(&mut qemu);
}
