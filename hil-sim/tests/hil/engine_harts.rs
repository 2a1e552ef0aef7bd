//! The CG engine on QEMU with 1, 2, 4 and 8 harts as MVUs: every partition gives the same bits,
//! which match the f64 reference; fused directions (one, two and three, each with its own MVU
//! assembly loop) equal separate solves; mirrored (persymmetric) tiles equal the whole matrix;
//! the firmware's assembly MVU and SVU loops equal the host's portable specification bit for
//! bit; the per-hart costs shrink with more MVUs.

use crate::support;

use deform_host::encode::EncodedMatrix;
use deform_shared::protocol::MAX_DIRECTIONS;
use deform_shared::protocol::{SolveParams, SolveReport, Start};
use deform_shared::qformat::{block_exponent, choose_frac_bits, from_mantissa, to_mantissa};
use deform_target_core::cg::{self, Matrix, System, Work};
use deform_target_core::exec::Sequential;
use deform_target_core::testkit::encode_rows;
use support::{
    assert_alive, boot_harts as boot, cholesky_solve, connect, decode_dense, encoded,
    max_relative_error,
};

fn params(directions: u8) -> SolveParams {
    SolveParams {
        max_iterations: 2000,
        tolerance: 1e-9,
        start: Start::Zero,
        directions,
        cycle_budget: 0,
    }
}

/// The model-A Laplacian of an m×m×m grid with the 8 corners fixed (persymmetric), in tiles of
/// `rows_per_tile` rows; with `half`, only the first n/2 rows, as mirrored tiles.
fn cube(m: usize, rows_per_tile: usize, half: bool) -> EncodedMatrix {
    let n = m * m * m;
    let idx = |i: usize, j: usize, l: usize| i + m * (j + m * l);
    let corner = |i: usize| i == 0 || i == m - 1;
    let fixed = |v: usize| corner(v % m) && corner((v / m) % m) && corner(v / (m * m));
    let row = |v: usize| -> Vec<(usize, f64)> {
        let (i, j, l) = (v % m, (v / m) % m, v / (m * m));
        let mut out = Vec::new();
        let mut diag = 0.0;
        let mut near = Vec::new();
        if i > 0 {
            near.push(idx(i - 1, j, l));
        }
        if i + 1 < m {
            near.push(idx(i + 1, j, l));
        }
        if j > 0 {
            near.push(idx(i, j - 1, l));
        }
        if j + 1 < m {
            near.push(idx(i, j + 1, l));
        }
        if l > 0 {
            near.push(idx(i, j, l - 1));
        }
        if l + 1 < m {
            near.push(idx(i, j, l + 1));
        }
        for c in near {
            diag += 1.0;
            if !fixed(v) && !fixed(c) {
                out.push((c, -1.0));
            }
        }
        out.push((v, diag));
        out.sort_by_key(|&(c, _)| c);
        out
    };
    let frac_bits = choose_frac_bits(6.0).unwrap();
    let rows = if half { n / 2 } else { n };
    let mut system = encode_rows(n, rows, rows_per_tile, frac_bits, row);
    for tile in &mut system.tiles {
        tile.mirrored = half;
    }
    encoded(system)
}

/// `matrix` with its tiles spread over `mvus` MVUs: contiguous runs (thesis 4.1.2) or round
/// robin, so that the MVUs' row ranges overlap (4.1.1).
fn assign(matrix: &EncodedMatrix, mvus: usize, round_robin: bool) -> EncodedMatrix {
    let mut out = matrix.clone();
    let count = out.tiles.len();
    for (i, t) in out.tiles.iter_mut().enumerate() {
        t.mvu = if round_robin {
            i % mvus
        } else {
            i * mvus / count
        } as u8;
    }
    out
}

fn rhs(n: usize, d: usize) -> Vec<f64> {
    (0..n)
        .map(|i| ((i * (7 + 4 * d)) % 13) as f64 - 6.0)
        .collect()
}

/// The same solve on the host: the target's own CG code (its portable MVU loop) on a
/// sequential executor, from the vectors exactly as the link uploads them.
fn host_solve(matrix: &EncodedMatrix, b: &[&[f64]], mvus: usize) -> Vec<Vec<f64>> {
    let n = matrix.n as usize;
    let mut kp = vec![[0i64; MAX_DIRECTIONS]; n];
    let mut partial = vec![[0i64; MAX_DIRECTIONS]; 8 * n];
    let plan = cg::plan(&matrix.tiles, &matrix.words, n, &mut kp, partial.len()).unwrap();
    // Per direction: b's mantissas and exponent, x, r.
    type Vectors = (Vec<i32>, i32, Vec<i32>, Vec<i32>);
    let mut vectors: Vec<Vectors> = b
        .iter()
        .map(|b| {
            let e = block_exponent(b.iter().fold(0.0f64, |m, v| m.max(v.abs())));
            let m = b.iter().map(|&v| to_mantissa(v, e).unwrap()).collect();
            (m, e, vec![0; n], vec![0; n])
        })
        .collect();
    let mut systems: Vec<System<'_>> = vectors
        .iter_mut()
        .map(|(b, e, x, r)| System {
            b,
            b_exponent: *e,
            x,
            x_exponent: 0,
            r,
            r_start: None,
            outcome: Default::default(),
        })
        .collect();
    let a = Matrix {
        n,
        frac_bits: matrix.frac_bits,
        tiles: &matrix.tiles,
        words: &matrix.words,
        plan: &plan,
    };
    let work = Work {
        p: &mut vec![[0; 4]; n],
        kp: &mut kp,
        partial: &mut partial,
    };
    let params = params(b.len() as u8);
    cg::solve(&a, &mut systems, work, &params, &Sequential { harts: mvus }).unwrap();
    systems
        .iter()
        .map(|s| {
            s.x.iter()
                .map(|&m| from_mantissa(m, s.x_exponent))
                .collect()
        })
        .collect()
}

struct Outcome {
    report: SolveReport,
    x: Vec<Vec<f64>>,
}

#[test]
fn one_to_eight_mvus_agree_bit_for_bit_and_with_f64() {
    let whole = cube(6, 24, false);
    let half = cube(6, 12, true);
    let n = whole.n as usize;
    let dense = decode_dense(&whole);
    let b: Vec<Vec<f64>> = (0..3).map(|d| rhs(n, d)).collect();
    let want: Vec<Vec<f64>> = b.iter().map(|b| cholesky_solve(&dense, b)).collect();
    let refs: Vec<&[f64]> = b.iter().map(Vec::as_slice).collect();
    let mut baseline: Option<Outcome> = None;
    let mut costs = Vec::new();
    for harts in [1u8, 2, 4, 8] {
        let mut qemu = boot(harts);
        let mut target = connect(&qemu);
        assert_eq!(target.info().harts, harts, "harts that came up");
        let mvus = usize::from(harts);
        for (matrix, round_robin, counted) in [
            (&whole, false, true),
            (&whole, true, false),
            (&half, false, false),
        ] {
            let split = assign(matrix, mvus, round_robin);
            target.upload_matrix(&split).unwrap();
            let (report, x) = target.solve_fused(&refs, params(3)).unwrap();
            assert!(report.converged, "{harts} harts: {report:?}");
            assert_eq!(report.mvus, harts);
            assert_eq!(report.overlapping, round_robin && harts > 1);
            assert_eq!(report.saturations, 0);
            for (x, want) in x.iter().zip(&want) {
                let err = max_relative_error(x, want);
                assert!(err < 1e-6, "{harts} harts: error {err:e}");
            }
            let cost = report.per_iteration;
            // The firmware (assembly MVU loop, parallel harts) equals the host (portable loop,
            // one thread) bit for bit.
            assert_eq!(x, host_solve(&split, &refs, mvus), "{harts} harts vs host");
            // One direction alone: p 4 bytes a node (`kernel::lane_words`), the assembly
            // loops of that layout against the host's portable loop, bit for bit.
            let (one, x1) = target.solve_fused(&refs[..1], params(1)).unwrap();
            assert!(one.converged, "{harts} harts, one direction: {one:?}");
            let host1 = host_solve(&split, &refs[..1], mvus);
            assert_eq!(x1, host1, "{harts} harts, one direction vs host");
            assert_eq!(
                x1[0], x[0],
                "{harts} harts, one direction vs the fused first"
            );
            match &baseline {
                None => baseline = Some(Outcome { report, x }),
                Some(base) => {
                    assert_eq!(x, base.x, "{harts} harts, round robin {round_robin}");
                    assert_eq!(report.directions, base.report.directions);
                }
            }
            if counted {
                costs.push((harts, cost));
            }
        }
        // Fused equals separate solves, direction by direction.
        let base = baseline.as_ref().unwrap();
        target.upload_matrix(&assign(&whole, mvus, false)).unwrap();
        let (single, x1) = target.solve_for(&b[1], params(1)).unwrap();
        assert_eq!(x1, base.x[1]);
        assert_eq!(single.directions[0], base.report.directions[1]);
        // One direction on the mirrored half, its MVUs overlapping: the same bits again, and
        // the firmware's mirrored loop equals the host's.
        let mirrored = assign(&half, mvus, true);
        target.upload_matrix(&mirrored).unwrap();
        let (_, x0) = target.solve_for(&b[0], params(1)).unwrap();
        assert_eq!(x0, base.x[0], "{harts} harts, mirrored, one direction");
        assert_eq!(x0, host_solve(&mirrored, &[&b[0]], mvus)[0]);
        // Two fused directions (their own assembly loops, whole and mirrored; the new SVU
        // passes on every hart): the host's portable loops, and the three-direction solve, bit
        // for bit.
        for matrix in [assign(&whole, mvus, false), assign(&half, mvus, harts > 1)] {
            target.upload_matrix(&matrix).unwrap();
            let (two, x2) = target.solve_fused(&refs[1..], params(2)).unwrap();
            assert_eq!(two.saturations, 0);
            assert_eq!(
                x2,
                host_solve(&matrix, &refs[1..], mvus),
                "{harts} harts, two"
            );
            assert_eq!(
                x2[..],
                base.x[1..],
                "{harts} harts, two vs three directions"
            );
            assert_eq!(two.directions[..], base.report.directions[1..]);
        }
        assert_alive(&mut qemu);
    }
    for (harts, cost) in &costs {
        eprintln!("{harts} harts: {cost:?}");
    }
    let one = costs[0].1;
    let eight = costs[3].1;
    assert!(
        one.mvu_critical.instructions > 0 && one.svu_critical.instructions > 0,
        "{one:?}"
    );
    assert!(
        eight.mvu_critical.instructions * 4 < one.mvu_critical.instructions,
        "8 MVUs {} vs 1 MVU {} instructions",
        eight.mvu_critical.instructions,
        one.mvu_critical.instructions
    );
    // Under `-icount shift=0` every hart retires one instruction per cycle: the target's
    // `mcycle` and `minstret` agree phase by phase, on one hart and on eight.
    for (harts, cost) in &costs {
        for phase in [
            cost.mvu_critical,
            cost.svu_critical,
            cost.mvu_total,
            cost.svu_total,
        ] {
            assert_eq!(phase.cycles, phase.instructions, "{harts} harts: {cost:?}");
        }
    }
}
