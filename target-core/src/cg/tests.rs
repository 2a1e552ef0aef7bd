//! The CG engine against f64 references: single and fused directions, 1 to 8 MVUs in both
//! partition schemes, mirrored tiles, and the error paths.

use super::*;
use deform_shared::matrix::validate_tile;
use deform_shared::qformat::{block_exponent, from_mantissa, quantize, to_mantissa};
use deform_shared::word::Word;
use proptest::prelude::*;

/// A sparse matrix as rows of (column, value) in f64, with the tiles and words encoding it.
struct Encoded {
    n: usize,
    frac_bits: u8,
    tiles: Vec<TileHeader>,
    words: Vec<u32>,
    rows: Vec<Vec<(usize, f64)>>,
}

/// Row blocks of `block` rows, each with the window starting at its smallest column.
fn encode(rows: Vec<Vec<(usize, f64)>>, frac_bits: u8, block: usize) -> Encoded {
    let n = rows.len();
    encode_rows(rows, n, frac_bits, block)
}

/// Like [`encode`] for the first `rows.len()` rows of an n×n matrix.
fn encode_rows(rows: Vec<Vec<(usize, f64)>>, n: usize, frac_bits: u8, block: usize) -> Encoded {
    let pieces = (0..rows.len())
        .step_by(block)
        .map(|start| (start, rows[start..(start + block).min(rows.len())].to_vec()))
        .collect();
    encode_pieces(pieces, rows, n, frac_bits)
}

/// Like [`encode`], but each block's last row is split with the next block: its entries left of
/// the diagonal end this block's tile and the rest begin the next tile (a row split at a
/// column window's edge, as the host's encoder makes them).
fn encode_split(rows: Vec<Vec<(usize, f64)>>, frac_bits: u8, block: usize) -> Encoded {
    let n = rows.len();
    let mut pieces: Vec<Piece> = Vec::new();
    let mut carried: Option<Vec<(usize, f64)>> = None;
    for start in (0..n).step_by(block) {
        let end = (start + block).min(n);
        let mut piece: Vec<_> = carried.take().into_iter().collect();
        let first = start + usize::from(!piece.is_empty());
        piece.extend(rows[first..end].iter().cloned());
        if end < n {
            let shared = &rows[end];
            let (left, right) = shared.iter().partition(|&&(c, _)| c < end);
            piece.push(left);
            carried = Some(right);
        }
        pieces.push((start, piece));
    }
    encode_pieces(pieces, rows, n, frac_bits)
}

/// A tile to encode: its first row and its rows' entries.
type Piece = (usize, Vec<Vec<(usize, f64)>>);

/// Tiles of `pieces`, in order.
fn encode_pieces(
    pieces: Vec<Piece>,
    rows: Vec<Vec<(usize, f64)>>,
    n: usize,
    frac_bits: u8,
) -> Encoded {
    let mut tiles = Vec::new();
    let mut words = Vec::new();
    for (row_base, piece) in pieces {
        let col_base = piece.iter().flatten().map(|&(c, _)| c).min().unwrap_or(0);
        let first = words.len();
        for row in &piece {
            if row.is_empty() {
                words.push(Word::empty_row(false).bits());
            }
            for (k, &(c, v)) in row.iter().enumerate() {
                let raw = quantize(v, frac_bits).unwrap() as i64;
                words.push(
                    Word::new((c - col_base) as u32, raw, k + 1 == row.len(), false)
                        .unwrap()
                        .bits(),
                );
            }
        }
        *words.last_mut().unwrap() |= deform_shared::word::EM_BIT;
        let header = TileHeader {
            row_base: row_base as u32,
            col_base: col_base as u32,
            rows: piece.len() as u32,
            words: (words.len() - first) as u32,
            mvu: 0,
            mirrored: false,
        };
        validate_tile(tiles.len() as u32, &header, &words[first..], n as u32).unwrap();
        tiles.push(header);
    }
    Encoded {
        n,
        frac_bits,
        tiles,
        words,
        rows,
    }
}

fn laplacian_1d(n: usize) -> Vec<Vec<(usize, f64)>> {
    (0..n)
        .map(|i| {
            let mut row = Vec::new();
            if i > 0 {
                row.push((i - 1, -1.0));
            }
            row.push((i, 2.0));
            if i + 1 < n {
                row.push((i + 1, -1.0));
            }
            row
        })
        .collect()
}

/// Model-A Laplacian of an m³ grid with the 8 corners eliminated symmetrically.
fn laplacian_3d(m: usize, k: f64) -> Vec<Vec<(usize, f64)>> {
    let idx = |i: usize, j: usize, l: usize| i + m * (j + m * l);
    let corner = |i: usize| i == 0 || i == m - 1;
    let fixed = |v: usize| corner(v % m) && corner((v / m) % m) && corner(v / (m * m));
    let mut rows = vec![Vec::new(); m * m * m];
    for l in 0..m {
        for j in 0..m {
            for i in 0..m {
                let v = idx(i, j, l);
                let mut diag = 0.0;
                let mut row = Vec::new();
                let mut nb = |c: usize| {
                    diag += k;
                    if !fixed(v) && !fixed(c) {
                        row.push((c, -k));
                    }
                };
                if i > 0 {
                    nb(idx(i - 1, j, l))
                }
                if i + 1 < m {
                    nb(idx(i + 1, j, l))
                }
                if j > 0 {
                    nb(idx(i, j - 1, l))
                }
                if j + 1 < m {
                    nb(idx(i, j + 1, l))
                }
                if l > 0 {
                    nb(idx(i, j, l - 1))
                }
                if l + 1 < m {
                    nb(idx(i, j, l + 1))
                }
                row.push((v, diag));
                row.sort_by_key(|&(c, _)| c);
                rows[v] = row;
            }
        }
    }
    rows
}

fn matvec(rows: &[Vec<(usize, f64)>], x: &[f64]) -> Vec<f64> {
    rows.iter()
        .map(|row| row.iter().map(|&(c, v)| v * x[c]).sum())
        .collect()
}

/// Plain f64 CG to a tight tolerance: the yardstick.
fn reference(rows: &[Vec<(usize, f64)>], b: &[f64]) -> Vec<f64> {
    let n = b.len();
    let mut x = vec![0.0; n];
    let mut r = b.to_vec();
    let mut p = r.clone();
    let mut rr: f64 = r.iter().map(|v| v * v).sum();
    let bb = rr;
    for _ in 0..10 * n {
        if rr <= 1e-28 * bb {
            break;
        }
        let kp = matvec(rows, &p);
        let alpha = rr / p.iter().zip(&kp).map(|(a, b)| a * b).sum::<f64>();
        for i in 0..n {
            x[i] += alpha * p[i];
            r[i] -= alpha * kp[i];
        }
        let rr_new: f64 = r.iter().map(|v| v * v).sum();
        for i in 0..n {
            p[i] = r[i] + rr_new / rr * p[i];
        }
        rr = rr_new;
    }
    x
}

/// One solve's outcome: per direction the solution in f64, and the report.
struct Run {
    x: Vec<Vec<f64>>,
    report: SolveReport,
}

fn to_block(v: &[f64]) -> (Vec<i32>, i32) {
    let e = block_exponent(v.iter().fold(0.0f64, |a, b| a.max(b.abs())));
    (v.iter().map(|&x| to_mantissa(x, e).unwrap()).collect(), e)
}

/// Solves `m` for every right-hand side in `bs` at once (fused), starting from `x0` if given,
/// with the tiles' MVU assignment as encoded, on a sequential executor of `harts` harts.
fn run_fused(
    m: &Encoded,
    bs: &[&[f64]],
    x0: Option<&[&[f64]]>,
    tol: f64,
    harts: usize,
) -> Result<Run, SolveFailure> {
    run_fused_on(m, bs, x0, tol, &Sequential { harts }, 0)
}

/// [`run_fused`] on `exec`, with a cycle budget.
fn run_fused_on(
    m: &Encoded,
    bs: &[&[f64]],
    x0: Option<&[&[f64]]>,
    tol: f64,
    exec: &impl Executor,
    cycle_budget: u64,
) -> Result<Run, SolveFailure> {
    let n = m.n;
    let mut kp = vec![[0i64; MAX_DIRECTIONS]; n];
    let mut partial = vec![[0i64; MAX_DIRECTIONS]; 4 * n];
    let plan = plan(&m.tiles, &m.words, n, &mut kp, partial.len()).unwrap();
    // Per direction: b's mantissas and exponent, x's, and r.
    type Vectors = (Vec<i32>, i32, Vec<i32>, i32, Vec<i32>);
    let mut vectors: Vec<Vectors> = bs
        .iter()
        .enumerate()
        .map(|(d, b)| {
            let (bm, be) = to_block(b);
            let (xm, xe) = x0.map(|x| to_block(x[d])).unwrap_or((vec![0; n], 0));
            (bm, be, xm, xe, vec![0; n])
        })
        .collect();
    let mut systems: Vec<System<'_>> = vectors
        .iter_mut()
        .map(|(b, be, x, xe, r)| System {
            b,
            b_exponent: *be,
            x,
            x_exponent: *xe,
            r,
            r_start: None,
            outcome: Default::default(),
        })
        .collect();
    let mut p = vec![[0i32; 4]; n];
    let matrix = Matrix {
        n,
        frac_bits: m.frac_bits,
        tiles: &m.tiles,
        words: &m.words,
        plan: &plan,
    };
    let params = SolveParams {
        max_iterations: 10 * n as u32,
        tolerance: tol,
        start: if x0.is_some() {
            Start::Uploaded
        } else {
            Start::Zero
        },
        directions: bs.len() as u8,
        cycle_budget,
    };
    let work = Work {
        p: &mut p,
        kp: &mut kp,
        partial: &mut partial,
    };
    let report = solve(&matrix, &mut systems, work, &params, exec)?;
    Ok(Run {
        x: systems
            .iter()
            .map(|s| {
                s.x.iter()
                    .map(|&v| from_mantissa(v, s.x_exponent))
                    .collect()
            })
            .collect(),
        report,
    })
}

/// One right-hand side on one MVU.
fn run(m: &Encoded, b: &[f64], x0: Option<&[f64]>, tol: f64) -> Result<Run1, SolveFailure> {
    let x0 = x0.map(|x| [x]);
    let out = run_fused(m, &[b], x0.as_ref().map(|x| &x[..]), tol, 1)?;
    Ok(Run1 {
        x: out.x.into_iter().next().unwrap(),
        report: out.report,
    })
}

struct Run1 {
    x: Vec<f64>,
    report: SolveReport,
}

fn max_rel_err(x: &[f64], reference: &[f64]) -> f64 {
    let scale = reference.iter().fold(0.0f64, |a, b| a.max(b.abs()));
    x.iter()
        .zip(reference)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max)
        / scale
}

fn true_residual(rows: &[Vec<(usize, f64)>], x: &[f64], b: &[f64]) -> f64 {
    let kx = matvec(rows, x);
    let rr: f64 = kx.iter().zip(b).map(|(a, b)| (a - b) * (a - b)).sum();
    (rr / b.iter().map(|v| v * v).sum::<f64>()).sqrt()
}

#[test]
fn solves_a_1d_laplacian_like_f64() {
    let m = encode(laplacian_1d(60), 18, 64);
    let b: Vec<f64> = (0..60).map(|i| ((i * 7919) % 13) as f64 - 6.0).collect();
    let run = run(&m, &b, None, 1e-9).unwrap();
    assert!(run.report.converged, "{:?}", run.report);
    let err = max_rel_err(&run.x, &reference(&m.rows, &b));
    assert!(err < 1e-7, "max relative error {err:e}");
    assert!(true_residual(&m.rows, &run.x, &b) < 1e-7);
}

#[test]
fn solves_the_thesis_cube_across_tiles() {
    // 10³ model A, k = 1, corner nodes fixed, 1 N at (0, 5, 5): thesis 2.6, x direction.
    let rows = laplacian_3d(10, 1.0);
    let m = encode(rows, 17, 250);
    assert_eq!(m.tiles.len(), 4);
    let mut b = vec![0.0; 1000];
    b[5 * 10 + 5 * 100] = 1.0; // node (0, 5, 5)
    let run = run(&m, &b, None, 1e-9).unwrap();
    assert!(run.report.converged, "{:?}", run.report);
    let reference = reference(&m.rows, &b);
    let err = max_rel_err(&run.x, &reference);
    assert!(
        err < 1e-6,
        "max relative error {err:e} after {} iterations",
        run.report.iterations
    );
    assert_eq!(run.report.words_per_iteration as usize, m.words.len());
}

#[test]
fn warm_start_from_the_answer_needs_fewer_iterations() {
    let m = encode(laplacian_3d(6, 1.0), 17, 216);
    let mut b = vec![0.0; 216];
    b[100] = 1.0;
    b[7] = -0.5;
    let cold = run(&m, &b, None, 1e-8).unwrap();
    let warm = run(&m, &b, Some(&cold.x), 1e-8).unwrap();
    assert!(
        warm.report.iterations * 2 < cold.report.iterations,
        "{} vs {}",
        warm.report.iterations,
        cold.report.iterations
    );
    assert!(max_rel_err(&warm.x, &reference(&m.rows, &b)) < 1e-6);
}

#[test]
fn scale_of_the_load_does_not_matter() {
    let m = encode(laplacian_1d(30), 18, 30);
    for scale in [1e-30, 1e-6, 1.0, 1e9, 1e30] {
        let b: Vec<f64> = (0..30).map(|i| scale * (1.0 + (i % 5) as f64)).collect();
        let run = run(&m, &b, None, 1e-9).unwrap();
        let err = max_rel_err(&run.x, &reference(&m.rows, &b));
        assert!(err < 1e-7, "scale {scale:e}: error {err:e}");
    }
}

#[test]
fn fractional_values_use_their_q_format() {
    // tridiag(-0.3, 0.75, -0.3): SPD with non-integer entries.
    let rows: Vec<Vec<(usize, f64)>> = laplacian_1d(40)
        .into_iter()
        .map(|r| {
            r.into_iter()
                .map(|(c, v)| (c, if v > 0.0 { 0.75 } else { -0.3 }))
                .collect()
        })
        .collect();
    let m = encode(rows, 20, 40);
    let b: Vec<f64> = (0..40).map(|i| (i as f64).sin()).collect();
    let run = run(&m, &b, None, 1e-10).unwrap();
    // The quantized matrix is what the target solves; compare against it.
    let q = m
        .rows
        .iter()
        .map(|r| {
            r.iter()
                .map(|&(c, v)| (c, (v * 1048576.0f64).round() / 1048576.0))
                .collect()
        })
        .collect::<Vec<Vec<_>>>();
    assert!(max_rel_err(&run.x, &reference(&q, &b)) < 1e-7);
}

#[test]
fn zero_load_gives_zero_displacement() {
    let m = encode(laplacian_1d(10), 18, 10);
    let run = run(&m, &[0.0; 10], Some(&[1.0; 10]), 1e-9).unwrap();
    assert!(run.report.converged);
    assert!(run.x.iter().all(|&v| v == 0.0));
}

#[test]
fn indefinite_matrix_is_reported() {
    let rows: Vec<Vec<(usize, f64)>> = (0..8)
        .map(|i| vec![(i, if i == 3 { -1.0 } else { 1.0 })])
        .collect();
    let m = encode(rows, 18, 8);
    let mut b = vec![0.0; 8];
    b[3] = 1.0;
    assert!(matches!(
        run(&m, &b, None, 1e-9),
        Err(SolveFailure::NotPositiveDefinite { iteration: 1 })
    ));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    #[test]
    fn random_spd_systems_match_f64(
        n in 2usize..40,
        diag in proptest::collection::vec(2.5f64..6.0, 40),
        off in proptest::collection::vec(-1.0f64..1.0, 40),
        b in proptest::collection::vec(-1.0e3f64..1.0e3, 40),
    ) {
        // Diagonally dominant symmetric tridiagonal: SPD.
        let rows: Vec<Vec<(usize, f64)>> = (0..n).map(|i| {
            let mut row = Vec::new();
            if i > 0 { row.push((i - 1, off[i - 1])); }
            row.push((i, diag[i]));
            if i + 1 < n { row.push((i + 1, off[i])); }
            row
        }).collect();
        let m = encode(rows, 17, 7);
        let q: Vec<Vec<(usize, f64)>> = m.rows.iter().map(|r| r.iter().map(|&(c, v)| (c, quantize(v, 17).unwrap() as f64 / 131072.0)).collect()).collect();
        let b = &b[..n];
        prop_assume!(b.iter().any(|&v| v != 0.0));
        let run = run(&m, b, None, 1e-10).unwrap();
        prop_assert!(run.report.converged);
        let tr = true_residual(&q, &run.x, b);
        prop_assert!(tr < 1e-7, "true residual {tr:e}, report {:?}", run.report);
    }
}

#[test]
fn short_workspace_is_an_error_not_a_panic() {
    let m = encode(laplacian_1d(10), 18, 10);
    let mut kp = vec![[0i64; MAX_DIRECTIONS]; 10];
    let plan = plan(&m.tiles, &m.words, 10, &mut kp, 0).unwrap();
    let matrix = Matrix {
        n: 10,
        frac_bits: 18,
        tiles: &m.tiles,
        words: &m.words,
        plan: &plan,
    };
    let (b, mut x, mut r) = (vec![1; 10], vec![0; 10], vec![0; 5]);
    let mut systems = [System {
        b: &b,
        b_exponent: 0,
        x: &mut x,
        x_exponent: 0,
        r: &mut r,
        r_start: None,
        outcome: Default::default(),
    }];
    let params = SolveParams {
        max_iterations: 5,
        tolerance: 1e-6,
        start: Start::Zero,
        directions: 1,
        cycle_budget: 0,
    };
    let work = Work {
        p: &mut [[0; 4]; 10],
        kp: &mut kp,
        partial: &mut [],
    };
    let out = solve(
        &matrix,
        &mut systems,
        work,
        &params,
        &Sequential { harts: 1 },
    );
    assert_eq!(out, Err(SolveFailure::WorkspaceTooSmall));
}

#[test]
fn iteration_cap_is_honoured() {
    let m = encode(laplacian_1d(100), 18, 100);
    let b = vec![1.0; 100];
    let mut kp = vec![[0i64; MAX_DIRECTIONS]; 100];
    let plan = plan(&m.tiles, &m.words, 100, &mut kp, 0).unwrap();
    let matrix = Matrix {
        n: 100,
        frac_bits: 18,
        tiles: &m.tiles,
        words: &m.words,
        plan: &plan,
    };
    let (bm, be) = to_block(&b);
    let (mut x, mut r) = (vec![0; 100], vec![0; 100]);
    let mut systems = [System {
        b: &bm,
        b_exponent: be,
        x: &mut x,
        x_exponent: 0,
        r: &mut r,
        r_start: None,
        outcome: Default::default(),
    }];
    let params = SolveParams {
        max_iterations: 3,
        tolerance: 1e-12,
        start: Start::Zero,
        directions: 1,
        cycle_budget: 0,
    };
    let work = Work {
        p: &mut vec![[0; 4]; 100],
        kp: &mut kp,
        partial: &mut [],
    };
    let report = solve(
        &matrix,
        &mut systems,
        work,
        &params,
        &Sequential { harts: 1 },
    )
    .unwrap();
    assert_eq!(report.iterations, 3);
    assert_eq!(report.directions[0].iterations, 3);
    assert!(!report.converged && report.residual > 1e-12);
}

/// Assigns the tiles to `mvus` MVUs: in contiguous runs (rows do not overlap, thesis 4.1.2) or
/// round robin (they do, 4.1.1).
fn assign(m: &Encoded, mvus: usize, round_robin: bool) -> Encoded {
    let count = m.tiles.len();
    let mut out = Encoded {
        n: m.n,
        frac_bits: m.frac_bits,
        tiles: m.tiles.clone(),
        words: m.words.clone(),
        rows: m.rows.clone(),
    };
    for (i, t) in out.tiles.iter_mut().enumerate() {
        t.mvu = if round_robin {
            i % mvus
        } else {
            i * mvus / count
        } as u8;
    }
    out
}

fn cube_rhs(n: usize, d: usize) -> Vec<f64> {
    (0..n)
        .map(|i| (((i * (7 + 3 * d)) % 11) as f64 - 5.0) * 0.25)
        .collect()
}

#[test]
fn any_number_of_mvus_and_either_partition_give_the_same_bits() {
    let rows = laplacian_3d(8, 1.0);
    let m = encode(rows, 17, 40);
    assert!(m.tiles.len() >= 8);
    let b = cube_rhs(m.n, 0);
    let one = run_fused(&m, &[&b], None, 1e-9, 1).unwrap();
    assert!(one.report.converged);
    assert!(!one.report.overlapping);
    assert!(max_rel_err(&one.x[0], &reference(&m.rows, &b)) < 1e-6);
    for mvus in [2, 4, 8] {
        for round_robin in [false, true] {
            let split = assign(&m, mvus, round_robin);
            let out = run_fused(&split, &[&b], None, 1e-9, mvus).unwrap();
            assert_eq!(out.report.mvus as usize, mvus);
            assert_eq!(out.report.overlapping, round_robin, "{mvus} MVUs");
            assert_eq!(out.x, one.x, "{mvus} MVUs, round robin {round_robin}");
            assert_eq!(out.report.directions, one.report.directions);
        }
    }
}

/// Rows split between two tiles of one MVU, one after the other, keep the plan fused (the first
/// part is carried over the second's store); split between two MVUs, the MVUs overlap. Either
/// way the bits are those of the unsplit matrix.
#[test]
fn rows_split_between_consecutive_tiles_stay_fused_and_exact() {
    let rows = laplacian_3d(6, 1.0);
    let whole = encode(rows.clone(), 17, 24);
    let split = encode_split(rows, 17, 24);
    assert!(split
        .tiles
        .windows(2)
        .all(|t| t[0].row_base + t[0].rows - 1 == t[1].row_base));
    let n = whole.n;
    let b = cube_rhs(n, 1);
    let want = run_fused(&whole, &[&b], None, 1e-9, 1).unwrap();
    for mvus in [1, 2, 3, 8] {
        let m = assign(&split, mvus, false);
        let mut kp = vec![[0i64; MAX_DIRECTIONS]; n];
        let p = plan(&m.tiles, &m.words, n, &mut kp, 4 * n).unwrap();
        assert_eq!(p.fused, mvus == 1, "{mvus} MVUs");
        assert_eq!(p.overlapping, mvus > 1, "{mvus} MVUs");
        let got = run_fused(&m, &[&b], None, 1e-9, mvus).unwrap();
        assert_eq!(got.x, want.x, "{mvus} MVUs");
        assert_eq!(got.report.directions, want.report.directions);
    }
}

#[test]
fn a_plan_needs_room_for_overlapping_partial_sums() {
    let m = assign(&encode(laplacian_1d(100), 18, 10), 2, true);
    let mut kp = vec![[0i64; MAX_DIRECTIONS]; 100];
    let err = plan(&m.tiles, &m.words, 100, &mut kp, 50).unwrap_err();
    assert_eq!(
        err,
        PlanError::Overlap {
            rows: 180,
            capacity: 50
        }
    );
    let ok = plan(&m.tiles, &m.words, 100, &mut kp, 180).unwrap();
    assert!(ok.overlapping && ok.partial_len == 180 && ok.mvus == 2);
}

#[test]
fn a_row_with_too_many_words_is_refused() {
    // One row of 4097 words (column 0 repeated): its exact i64 sum could overflow.
    let mut words = vec![Word::new(0, 1, false, false).unwrap().bits(); 4096];
    words.push(Word::new(0, 1, true, true).unwrap().bits());
    let tiles = [TileHeader {
        row_base: 0,
        col_base: 0,
        rows: 1,
        words: words.len() as u32,
        mvu: 0,
        mirrored: false,
    }];
    let mut kp = vec![[0i64; MAX_DIRECTIONS]; 1];
    assert_eq!(
        plan(&tiles, &words, 1, &mut kp, 0),
        Err(PlanError::Matrix(MatrixError::RowTooLong {
            tile: 0,
            row: 0
        }))
    );
}

/// The plan allows split sums exactly within the kernel's limits: words per row and Σ|q| per
/// row (a row of `len` words of value `v` at column 0, mirrored rows counting too).
#[test]
fn split_sums_only_within_their_limits() {
    let split = |len: usize, v: i64| {
        let mut words = vec![Word::new(0, v, false, false).unwrap().bits(); len - 1];
        words.push(Word::new(0, v, true, true).unwrap().bits());
        let tiles = [TileHeader {
            row_base: 0,
            col_base: 0,
            rows: 1,
            words: len as u32,
            mvu: 0,
            mirrored: false,
        }];
        let mut kp = vec![[0i64; MAX_DIRECTIONS]; 1];
        plan(&tiles, &words, 1, &mut kp, 0).unwrap().split
    };
    let words = SPLIT_MAX_WORDS as usize;
    assert!(split(words, 1));
    assert!(!split(words + 1, 1));
    // Σ|q| = 4·v: at the limit and one unit over (the limit is a multiple of 4).
    let v = (SPLIT_MAX_ROW_ABS / 4) as i64;
    assert_eq!(SPLIT_MAX_ROW_ABS % 4, 0);
    assert!(split(4, v));
    assert!(!split(4, -v - 1));
}

#[test]
fn fused_directions_equal_separate_solves() {
    let m = assign(&encode(laplacian_3d(6, 1.0), 17, 50), 3, false);
    let bs: Vec<Vec<f64>> = (0..3).map(|d| cube_rhs(m.n, d)).collect();
    for count in [2, 3] {
        let refs: Vec<&[f64]> = bs.iter().take(count).map(Vec::as_slice).collect();
        let fused = run_fused(&m, &refs, None, 1e-9, 3).unwrap();
        assert_eq!(fused.report.directions.len(), count);
        for (d, b) in refs.iter().enumerate() {
            let single = run_fused(&m, &[b], None, 1e-9, 3).unwrap();
            assert_eq!(fused.x[d], single.x[0], "direction {d} of {count}");
            assert_eq!(fused.report.directions[d], single.report.directions[0]);
        }
        let most = fused.report.directions.iter().map(|d| d.iterations).max();
        assert_eq!(Some(fused.report.iterations), most);
    }
}

#[test]
fn fused_warm_starts_and_zero_loads_mix() {
    let m = encode(laplacian_3d(5, 1.0), 17, 60);
    let b0 = cube_rhs(m.n, 0);
    let zero = vec![0.0; m.n];
    let cold = run_fused(&m, &[&b0, &zero], None, 1e-9, 1).unwrap();
    assert!(cold.x[1].iter().all(|&v| v == 0.0));
    assert_eq!(cold.report.directions[1].iterations, 0);
    let guess = [cold.x[0].as_slice(), zero.as_slice()];
    // From the answer, a looser tolerance is met at once.
    let warm = run_fused(&m, &[&b0, &zero], Some(&guess), 1e-7, 1).unwrap();
    let (w, c) = (
        warm.report.directions[0].iterations,
        cold.report.directions[0].iterations,
    );
    assert!(w * 2 < c, "warm {w}, cold {c}");
    assert!(max_rel_err(&warm.x[0], &reference(&m.rows, &b0)) < 1e-6);
}

/// The rows `0..n/2` of a persymmetric matrix as mirrored tiles: they stand for all n rows.
fn mirrored_half(m: &Encoded, block: usize) -> Encoded {
    let half: Vec<Vec<(usize, f64)>> = m.rows[..m.n / 2].to_vec();
    let mut e = encode_rows(half, m.n, m.frac_bits, block);
    for t in &mut e.tiles {
        t.mirrored = true;
    }
    e.rows = m.rows.clone();
    e
}

#[test]
fn mirrored_tiles_solve_like_the_whole_persymmetric_matrix() {
    // The 6³ cube with its corners fixed is persymmetric: node i ↔ n − 1 − i.
    let whole = encode(laplacian_3d(6, 1.0), 17, 40);
    let half = mirrored_half(&whole, 40);
    assert!(half.words.len() * 2 < whole.words.len() + 2 * half.tiles.len());
    let b = cube_rhs(whole.n, 1);
    let full = run_fused(&whole, &[&b], None, 1e-9, 1).unwrap();
    let mirrored = run_fused(&half, &[&b], None, 1e-9, 1).unwrap();
    assert_eq!(mirrored.x, full.x);
    assert!(max_rel_err(&mirrored.x[0], &reference(&whole.rows, &b)) < 1e-6);
    for mvus in [2, 4] {
        for round_robin in [false, true] {
            let split = assign(&half, mvus, round_robin);
            let bs = [b.as_slice(), b.as_slice(), b.as_slice()];
            let out = run_fused(&split, &bs, None, 1e-9, mvus).unwrap();
            for x in &out.x {
                assert_eq!(x, &full.x[0], "{mvus} MVUs, round robin {round_robin}");
            }
        }
    }
}

/// A given residual ([`System::r_start`]) is started from without an exact pass; even a wrong
/// one ends verified against b − A·x, so the solution meets the tolerance.
#[test]
fn a_given_residual_is_started_from_and_the_end_verified() {
    let m = encode(laplacian_3d(5, 1.0), 17, 125);
    let n = m.n;
    let b: Vec<f64> = (0..n).map(|i| ((i * 37) % 11) as f64 - 5.0).collect();
    let x_near: Vec<f64> = reference(&m.rows, &b).iter().map(|v| v * 0.9).collect();
    let kx = matvec(&m.rows, &x_near);
    for factor in [1.0, 2.0] {
        // The residual of x_near, or twice it (a wrong estimate).
        let r: Vec<f64> = b.iter().zip(&kx).map(|(b, k)| factor * (b - k)).collect();
        let (rm, re) = to_block(&r);
        let rr: u128 = rm
            .iter()
            .map(|&v| (i64::from(v) * i64::from(v)) as u128)
            .sum();
        let or = rm.iter().fold(0, |o, &v| o | crate::svu::magnitude_bits(v));
        let (bm, be) = to_block(&b);
        let (mut xm, xe) = to_block(&x_near);
        let mut r_vec = rm.clone();
        let mut kp = vec![[0i64; MAX_DIRECTIONS]; n];
        let mut partial = vec![[0i64; MAX_DIRECTIONS]; 4 * n];
        let plan = plan(&m.tiles, &m.words, n, &mut kp, partial.len()).unwrap();
        let mut systems = [System {
            b: &bm,
            b_exponent: be,
            x: &mut xm,
            x_exponent: xe,
            r: &mut r_vec,
            r_start: Some(GivenResidual {
                exponent: re,
                rr,
                bound: crate::svu::bound_of(or),
                verify: true,
                drift: None,
            }),
            outcome: Default::default(),
        }];
        let matrix = Matrix {
            n,
            frac_bits: m.frac_bits,
            tiles: &m.tiles,
            words: &m.words,
            plan: &plan,
        };
        let params = SolveParams {
            max_iterations: 500,
            tolerance: 1e-7,
            start: Start::Previous,
            directions: 1,
            cycle_budget: 0,
        };
        let work = Work {
            p: &mut vec![[0; 4]; n],
            kp: &mut kp,
            partial: &mut partial,
        };
        let report = solve(
            &matrix,
            &mut systems,
            work,
            &params,
            &Sequential { harts: 3 },
        )
        .unwrap();
        let s = &systems[0];
        let x: Vec<f64> =
            s.x.iter()
                .map(|&v| from_mantissa(v, s.x_exponent))
                .collect();
        assert!(
            report.converged && s.outcome.r_exact,
            "{factor}: {report:?}"
        );
        assert!(true_residual(&m.rows, &x, &b) < 2e-7, "{factor}");
    }
}

/// A sequential executor on a core with a CPI of 3: its clock gains 3 cycles per instruction,
/// one instruction per read, and each hart's measured task costs 30 cycles, 10 instructions.
struct CpiThree {
    instructions: std::sync::atomic::AtomicU64,
    harts: usize,
}

impl PhaseClock for CpiThree {
    fn now(&self) -> PhaseCounters {
        let i = self
            .instructions
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        PhaseCounters {
            cycles: 3 * i,
            instructions: i,
        }
    }
}

impl Executor for CpiThree {
    type Mvus = crate::mvu_backend::NoMvus;

    fn harts(&self) -> usize {
        self.harts
    }
    fn run(&self, harts: usize, task: crate::exec::Task<'_>) {
        Sequential { harts: self.harts }.run(harts, task)
    }
    fn run_measured(
        &self,
        harts: usize,
        task: crate::exec::Task<'_>,
    ) -> [PhaseCounters; MAX_HARTS] {
        self.run(harts, task);
        let mut counts = [PhaseCounters::default(); MAX_HARTS];
        for c in counts.iter_mut().take(harts) {
            *c = PhaseCounters {
                cycles: 30,
                instructions: 10,
            };
        }
        counts
    }
}

/// Cycles are reported beside instructions, each as measured (protocol 11: the first iteration
/// and the whole solve carried instructions only, and the summary called them cycles), and the
/// cycle budget counts cycles.
#[test]
fn the_report_carries_cycles_beside_instructions_and_the_budget_counts_cycles() {
    let m = encode(laplacian_1d(40), 18, 64);
    let b: Vec<f64> = (0..40).map(|i| ((i * 7919) % 13) as f64 - 6.0).collect();
    let exec = CpiThree {
        instructions: Default::default(),
        harts: 1,
    };
    let run = run_fused_on(&m, &[&b], None, 1e-9, &exec, 0).unwrap();
    let report = run.report;
    for cost in [report.per_iteration, report.whole_solve] {
        for phase in [
            cost.mvu_critical,
            cost.svu_critical,
            cost.mvu_total,
            cost.svu_total,
        ] {
            assert!(phase.instructions > 0, "{cost:?}");
            assert_eq!(phase.cycles, 3 * phase.instructions, "{cost:?}");
        }
    }
    assert_eq!(report.per_iteration.critical().cpi(), Some(3.0));
    let scalar = report.first_iteration_scalar;
    assert!(scalar.instructions > 0 && scalar.cycles == 3 * scalar.instructions);
    // A budget of the whole solve's instructions stops it a third of the way in cycles.
    let all = report.whole_solve.critical();
    let budgeted = run_fused_on(&m, &[&b], None, 1e-9, &exec, all.instructions).unwrap();
    assert!(
        budgeted.report.iterations < report.iterations / 2,
        "{} of {} iterations within {} cycles",
        budgeted.report.iterations,
        report.iterations,
        all.instructions
    );
}

/// The report's ‖r‖/‖b‖ comes from `sqrt`: correctly rounded, bit for bit std's (IEEE 754's
/// square root), over values spread across the exponent range, subnormals, the largest
/// finite and random bit patterns.
#[test]
fn sqrt_is_correctly_rounded() {
    let mut x = 1.0e-30f64;
    let mut checked = 0;
    while x < 1.0e30 {
        for v in [x, x * 1.000_000_1, x * 2.999_999, x * 0.613] {
            assert_eq!(super::sqrt(v).to_bits(), v.sqrt().to_bits(), "{v:e}");
            checked += 1;
        }
        x *= 1.37;
    }
    assert!(checked > 400);
    let mut rng = Rng(0x5eed_5a7e);
    for _ in 0..1_000_000 {
        let v = f64::from_bits(rng.next() >> 1);
        if v.is_finite() {
            assert_eq!(super::sqrt(v).to_bits(), v.sqrt().to_bits(), "{v:e}");
        }
    }
    // Around exact squares, where the remainder is zero or tiny.
    for _ in 0..100_000 {
        let j = (rng.next() >> 38) | 1 << 25;
        let square = (j * j) as f64;
        let scale = ldexp(1.0, (rng.next() % 400) as i32 - 200);
        for v in [
            square,
            f64::from_bits(square.to_bits() + 1),
            f64::from_bits(square.to_bits() - 1),
        ] {
            let v = v * scale;
            assert_eq!(super::sqrt(v).to_bits(), v.sqrt().to_bits(), "{v:e}");
        }
    }
    for v in [
        f64::MIN_POSITIVE,
        f64::MIN_POSITIVE / 3.0,
        5e-324,
        f64::MAX,
        1.0,
        2.0,
        4.0,
        (1u64 << 53) as f64 - 1.0,
    ] {
        assert_eq!(super::sqrt(v).to_bits(), v.sqrt().to_bits(), "{v:e}");
    }
    assert_eq!(super::sqrt(0.0), 0.0);
    assert_eq!(super::sqrt(-1.0), 0.0);
}

use crate::test_rng::Rng;

/// A random symmetric, diagonally dominant (hence positive definite) sparse matrix of n rows:
/// a few random couplings per row of random sign and size, the diagonal their magnitudes'
/// sum times 1–2 plus a random mass (a dynamic step's S is of this kind).
fn random_spd(n: usize, rng: &mut Rng) -> Vec<Vec<(usize, f64)>> {
    let mut off = vec![Vec::new(); n];
    for i in 0..n {
        for _ in 0..3 {
            let j = rng.below(n as u64) as usize;
            if j != i && !off[i].iter().any(|&(c, _)| c == j) {
                let v = (rng.unit() - 0.5) * 4.0;
                off[i].push((j, v));
                off[j].push((i, v));
            }
        }
    }
    let mass = 0.01 + rng.unit();
    off.into_iter()
        .enumerate()
        .map(|(i, mut row)| {
            let sum: f64 = row.iter().map(|&(_, v)| f64::abs(v)).sum();
            row.push((i, sum * (1.0 + rng.unit()) + mass));
            row.sort_by_key(|&(c, _)| c);
            row
        })
        .collect()
}

/// v·2^(e − e0) exactly, asserting it fits an `i128` (the tests keep their exponents close).
fn aligned(v: i128, e: i32, e0: i32) -> i128 {
    let s = (e - e0) as u32;
    let out = v.checked_shl(s).unwrap();
    assert!(s < 127 && out >> s == v && out.unsigned_abs() < 1 << 120);
    out
}

/// The exact b − A·x of the mantissas (A of `m`'s raw integers), each element at exponent
/// `e0` as an `i128`.
fn exact_residual(m: &Encoded, b: (&[i32], i32), x: (&[i32], i32), e0: i32) -> Vec<i128> {
    let f = i32::from(m.frac_bits);
    m.rows
        .iter()
        .zip(b.0)
        .map(|(row, &bi)| {
            let ax: i128 = row
                .iter()
                .map(|&(c, v)| {
                    let raw = i128::from(quantize(v, m.frac_bits).unwrap());
                    raw * i128::from(x.0[c])
                })
                .sum();
            aligned(i128::from(bi), b.1, e0) - aligned(ax, x.1 - f, e0)
        })
        .collect()
}

/// ‖v‖₂ of elements at exponent e0.
fn norm_at(v: &[i128], e0: i32) -> f64 {
    let ss: f64 = v.iter().map(|&d| (d as f64) * (d as f64)).sum();
    ldexp(ss.sqrt(), e0)
}

/// One bounded solve of `rows` (quantised with F = `frac_bits`) from x₀ (`None`: zero) with
/// its exact residual rounded to a block and that rounding as the given drift. Returns the
/// outcome, the recursive ‖r‖ − exact, the exact ‖b − A·x‖ and ‖b‖, all in real units.
struct Bounded {
    outcome: Outcome,
    drift_seen: f64,
    true_residual: f64,
    b_norm: f64,
    iterations: u32,
}

fn bounded_solve(m: &Encoded, b: &[f64], x0: &[f64], tol: f64, max_iterations: u32) -> Bounded {
    let n = m.n;
    let (bm, be) = to_block(b);
    let (mut xm, xe) = to_block(x0);
    let f = i32::from(m.frac_bits);
    // The start's residual, exact at a fine exponent, then rounded to 30 bits.
    let e_fine = be.min(xe - f) - 40;
    let exact = exact_residual(m, (&bm, be), (&xm, xe), e_fine);
    let max = exact.iter().map(|v| v.unsigned_abs()).max().unwrap_or(0);
    let bits = 128 - max.leading_zeros() as i32;
    let e_g = e_fine + (bits - 29).max(0);
    let shift = (e_g - e_fine) as u32;
    let round = |v: i128| ((v + if shift > 0 { 1 << (shift - 1) } else { 0 }) >> shift) as i32;
    let mut rm: Vec<i32> = exact.iter().map(|&v| round(v)).collect();
    let rr: u128 = rm
        .iter()
        .map(|&v| (i64::from(v) * i64::from(v)) as u128)
        .sum();
    let or = rm.iter().fold(0, |o, &v| o | crate::svu::magnitude_bits(v));
    // ½ unit per element of rounding (0 where nothing was cut).
    let drift0 = if shift > 0 {
        let root_n = crate::superpose::ceil_sqrt_int(n) as u64;
        crate::upper::Upper::new(root_n, e_g - 1)
    } else {
        crate::upper::Upper::ZERO
    };
    let mut kp = vec![[0i64; MAX_DIRECTIONS]; n];
    let mut partial = vec![[0i64; MAX_DIRECTIONS]; 4 * n];
    let plan = plan(&m.tiles, &m.words, n, &mut kp, partial.len()).unwrap();
    let mut systems = [System {
        b: &bm,
        b_exponent: be,
        x: &mut xm,
        x_exponent: xe,
        r: &mut rm,
        r_start: Some(GivenResidual {
            exponent: e_g,
            rr,
            bound: crate::svu::bound_of(or),
            verify: true,
            drift: Some(drift0),
        }),
        outcome: Default::default(),
    }];
    let matrix = Matrix {
        n,
        frac_bits: m.frac_bits,
        tiles: &m.tiles,
        words: &m.words,
        plan: &plan,
    };
    let params = SolveParams {
        max_iterations,
        tolerance: tol,
        start: Start::Previous,
        directions: 1,
        cycle_budget: 0,
    };
    let work = Work {
        p: &mut vec![[0; 4]; n],
        kp: &mut kp,
        partial: &mut partial,
    };
    let report = solve(
        &matrix,
        &mut systems,
        work,
        &params,
        &Sequential { harts: 2 },
    )
    .unwrap();
    let s = &systems[0];
    let (o, xe) = (s.outcome, s.x_exponent);
    let e0 = o.r_exponent.min(be).min(xe - f);
    let truth = exact_residual(m, (&bm, be), (s.x, xe), e0);
    let gap: Vec<i128> = truth
        .iter()
        .zip(s.r.iter())
        .map(|(&t, &r)| aligned(i128::from(r), o.r_exponent, e0) - t)
        .collect();
    Bounded {
        outcome: o,
        drift_seen: norm_at(&gap, e0),
        true_residual: norm_at(&truth, e0),
        b_norm: norm_at(&bm.iter().map(|&v| i128::from(v)).collect::<Vec<_>>(), be),
        iterations: report.iterations,
    }
}

/// The drift a bounded solve reports holds: over random SPD systems, starts, tolerances and
/// iteration caps, the recursive r returned is within `Outcome::drift` of the exact b − A·x
/// of the returned mantissas, and every step accepted without the exact pass is truly within
/// the tolerance. The skip must fire in some cases and not in others (else the test proves
/// nothing).
#[test]
fn the_reported_drift_bounds_the_true_residual_and_skips_only_within_tolerance() {
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    let (mut skipped, mut checked) = (0, 0);
    for case in 0..160 {
        let n = 20 + rng.below(120) as usize;
        let m = encode(random_spd(n, &mut rng), 10 + rng.below(6) as u8, 64);
        let b: Vec<f64> = (0..n).map(|_| rng.unit() - 0.5).collect();
        let x_ref = reference(&m.rows, &b);
        // A start near the answer (a predicted step) or far from it.
        let noise = [1e-2, 1e-4, 1e-6, 1.0][case % 4];
        let x0: Vec<f64> = x_ref
            .iter()
            .map(|v| v + noise * (rng.unit() - 0.5))
            .collect();
        let tol = [1e-3, 1e-5, 1e-7][rng.below(3) as usize];
        let cap = 1 + rng.below(30) as u32;
        let out = bounded_solve(&m, &b, &x0, tol, cap);
        let o = out.outcome;
        assert!(
            out.drift_seen <= o.drift.to_f64(),
            "case {case}: ‖r − (b − A·x)‖ = {:e} above the bound {:e} ({} iterations)",
            out.drift_seen,
            o.drift.to_f64(),
            out.iterations
        );
        if o.check_skipped {
            skipped += 1;
            assert!(!o.r_exact);
            assert!(
                out.true_residual <= tol * out.b_norm,
                "case {case}: skipped at a true ‖b − A·x‖/‖b‖ of {:e} > {tol:e}",
                out.true_residual / out.b_norm
            );
        } else if o.r_exact {
            checked += 1;
        }
    }
    assert!(
        skipped > 10 && checked > 10,
        "{skipped} skipped, {checked} checked"
    );
}

/// A random value below 2^`bits` in magnitude, of random sign, whose low bits (a random
/// number of them) are all ones or all zeros: the floors' and roundings' extremes.
fn extreme(rng: &mut Rng, bits: u32) -> i64 {
    let v = (rng.next() >> (64 - bits)) as i64;
    let k = rng.below(u64::from(bits)) as u32;
    let low = (1i64 << k) - 1;
    let v = if rng.below(2) == 0 { v | low } else { v & !low };
    if rng.below(2) == 0 {
        v
    } else {
        -v
    }
}

/// The largest error, in units of 2^`e`, of `got` (mantissas at `e`) against `exact` (at
/// `e0`).
fn worst_units(got: &[i32], e: i32, exact: &[i128], e0: i32) -> f64 {
    got.iter()
        .zip(exact)
        .map(|(&g, &x)| ldexp((aligned(i128::from(g), e, e0) - x).abs() as f64, e0 - e))
        .fold(0.0, f64::max)
}

/// The per-element bounds behind the drift ([`update_error`]) hold at their worst: pass R's r + c·K·p and pass XP's x + α·p against the exact sums, over random
/// plans (coefficients of every size and sign, own terms above and below the result's
/// exponent, K·p narrowed left and right) and values whose cut bits are all ones or all zeros.
#[test]
fn pass_r_and_x_updates_stay_within_their_error_constants() {
    let mut rng = Rng(0x2545_f491_4f6c_dd1d);
    // The worst error as a share of its plan's bound, and the worst error in units.
    let (mut worst_r, mut worst_x) = (0f64, 0f64);
    let mut worst_units_seen = 0f64;
    for _ in 0..3000 {
        let n = 32;
        let c = Scalar {
            neg: rng.below(2) == 1,
            m: (rng.next() as u32) | (1 << 31),
            e: -(rng.below(40) as i32) - 31,
        };
        // Pass R: K·p (i64 row sums) at a raw exponent, r's own term near the product's size.
        let bits = 20 + rng.below(42) as u32;
        let kp: Vec<i64> = (0..n).map(|_| extreme(&mut rng, bits)).collect();
        let e_kp = rng.below(40) as i32 - 20;
        let e_own = c.e + 32 + bits as i32 + e_kp - 29 + rng.below(41) as i32 - 20;
        let r0: Vec<i32> = (0..n).map(|_| extreme(&mut rng, 29) as i32).collect();
        let mut sat = 0;
        let or = kp.iter().fold(0u64, |o, &v| o | (v ^ (v >> 63)) as u64);
        let (narrow, off, bound) = Narrow::new(bound_of_u64(or), &mut sat);
        let r_or = r0.iter().fold(0, |o, &v| o | magnitude_bits(v));
        let own = Block {
            e: e_own,
            bound: bound_of(r_or),
        };
        let lin = Lin::new(
            c,
            Block {
                e: e_kp + off,
                bound,
            },
            true,
            Some(own),
            &mut sat,
        );
        let sums: Vec<Sums> = kp.iter().map(|&k| [k, 0, 0]).collect();
        let mut r = r0.clone();
        svu::portable_pass_r(&mut r, &sums, 0, PassR { lin, narrow });
        let sign = if c.neg { -1 } else { 1 };
        let e0 = lin.e.min(e_own).min(c.e + e_kp);
        let exact: Vec<i128> = (0..n)
            .map(|i| {
                aligned(i128::from(r0[i]), e_own, e0)
                    + sign * aligned(i128::from(c.m) * i128::from(kp[i]), c.e + e_kp, e0)
            })
            .collect();
        if sat == 0 {
            let units = worst_units(&r, lin.e, &exact, e0);
            let bound = update_error(&lin, matches!(narrow, Narrow::Right(_))) as f64 / 2.0;
            worst_r = worst_r.max(units / bound);
            worst_units_seen = worst_units_seen.max(units);
        }
        // Pass XP's x ← x + α·p: p a block below 2^30, x's own term near the product's size.
        let p: Vec<i32> = (0..n).map(|_| extreme(&mut rng, 30) as i32).collect();
        let e_p = rng.below(40) as i32 - 20;
        let e_x = c.e + 32 + 30 + e_p - 29 + rng.below(41) as i32 - 20;
        let x0: Vec<i32> = (0..n).map(|_| extreme(&mut rng, 29) as i32).collect();
        let mut sat = 0;
        let p_or = p.iter().fold(0, |o, &v| o | magnitude_bits(v));
        let x_or = x0.iter().fold(0, |o, &v| o | magnitude_bits(v));
        let p_block = Block {
            e: e_p,
            bound: bound_of(p_or),
        };
        let x_block = Block {
            e: e_x,
            bound: bound_of(x_or),
        };
        let xl = Lin::new(c, p_block, false, Some(x_block), &mut sat);
        let mut lanes: Vec<Lanes> = p.iter().map(|&v| [v, 0, 0, 0]).collect();
        let mut x = x0.clone();
        let plan = PassXP {
            x: Some(xl),
            p: None,
        };
        svu::portable_pass_xp(&mut x, &mut lanes, &vec![0; n], 0, plan);
        let e0 = xl.e.min(e_x).min(c.e + e_p);
        let exact: Vec<i128> = (0..n)
            .map(|i| {
                aligned(i128::from(x0[i]), e_x, e0)
                    + sign * aligned(i128::from(c.m) * i128::from(p[i]), c.e + e_p, e0)
            })
            .collect();
        if sat == 0 {
            let units = worst_units(&x, xl.e, &exact, e0);
            worst_x = worst_x.max(units / (update_error(&xl, false) as f64 / 2.0));
            worst_units_seen = worst_units_seen.max(units);
        }
    }
    assert!(worst_r <= 1.0, "pass R: {worst_r} of its bound");
    assert!(worst_x <= 1.0, "pass XP: {worst_x} of its bound");
    // The extremes were reached: close to the bounds, beyond a single rounding.
    assert!(worst_r > 0.7 && worst_x > 0.7 && worst_units_seen > 1.5);
}
