//! The program against a model of the MVU array that runs it exactly as the gateware does
//! (per MVU: words in order, write-backs stored or added by their flags, pᵀKp per write-back,
//! the OR at the last write-back; then the shared rows), checked against the portable kernel.

extern crate std;

use std::vec;
use std::vec::Vec;

use super::*;
use crate::kernel::Lanes;
use crate::testkit::mvu::{
    compact_mvu_phase, random_matrix, random_p, reference_mvu_phase, saturating_matrix,
    saturating_p, Mirroring, MvuPhase, RandomMatrix, Recorded, Shape, Split,
};
use deform_shared::protocol::MAX_DIRECTIONS;
use deform_shared::word::{Word, EM_BIT};

/// The one's-complement magnitude the kernel ORs (`v ^ (v >> 63)`).
fn magnitude(v: i64) -> u64 {
    (v ^ (v >> 63)) as u64
}

/// The MVU array's state that outlives a phase: each MVU's Kp memory.
struct Model {
    y: Vec<Vec<Sums>>,
}

impl Model {
    /// Kp memories full of garbage, as after an earlier matrix.
    fn new(mvus: usize, n: usize) -> Self {
        let mut rng = fastrand::Rng::with_seed(7);
        let y = (0..mvus)
            .map(|_| {
                (0..n)
                    .map(|_| [rng.i64(..), rng.i64(..), rng.i64(..)])
                    .collect()
            })
            .collect();
        Model { y }
    }

    fn phase(&mut self, prog: &Recorded, n: usize, p: &[Lanes], d: usize) -> MvuPhase {
        let mut p_kp = [0i128; MAX_DIRECTIONS];
        let mut or = [0u64; MAX_DIRECTIONS];
        for (m, y) in self.y.iter_mut().enumerate() {
            let length = prog.lengths.get(m).copied().unwrap_or(0);
            if length == 0 {
                continue;
            }
            let tiles = &prog.tiles[m];
            let (mut tile, mut row) = (0usize, tiles[0].0 as usize);
            let (mut own, mut mir) = ([0i64; 3], [0i64; 3]);
            let mut write_back = |row: usize, acc: &mut [i64; 3], first: bool, last: bool| {
                for lane in 0..3 {
                    let v = if first {
                        acc[lane]
                    } else {
                        y[row][lane].wrapping_add(acc[lane])
                    };
                    y[row][lane] = v;
                    if lane < d {
                        p_kp[lane] += i128::from(p[row][lane]) * i128::from(acc[lane]);
                        if last {
                            or[lane] |= magnitude(v);
                        }
                    }
                }
                *acc = [0; 3];
            };
            for &(bits, f) in &prog.words[m][..length] {
                let (col_base, mirror_base, mirrored) = (
                    tiles[tile].1 as usize,
                    tiles[tile].2 as usize,
                    tiles[tile].3,
                );
                let w = Word(bits);
                let (c, v) = (w.column() as usize, i64::from(w.raw_value()));
                for lane in 0..3 {
                    own[lane] = own[lane].wrapping_add(v * i64::from(p[col_base + c][lane]));
                    if mirrored {
                        let q = i64::from(p[mirror_base - c][lane]);
                        mir[lane] = mir[lane].wrapping_add(v * q);
                    }
                }
                if w.end_of_row() {
                    write_back(
                        row,
                        &mut own,
                        f & flags::FIRST_OWN != 0,
                        f & flags::LAST_OWN != 0,
                    );
                    if mirrored {
                        let first = f & flags::FIRST_MIRROR != 0;
                        let last = f & flags::LAST_MIRROR != 0;
                        write_back(n - 1 - row, &mut mir, first, last);
                    }
                    row += 1;
                }
                if w.end_of_matrix() && tile + 1 < tiles.len() {
                    tile += 1;
                    row = tiles[tile].0 as usize;
                }
            }
        }
        for &(row, mask, owner) in &prog.shared {
            let mut sum = [0i64; 3];
            for (m, y) in self.y.iter().enumerate() {
                if mask & (1 << m) != 0 {
                    for lane in 0..3 {
                        sum[lane] = sum[lane].wrapping_add(y[row][lane]);
                    }
                }
            }
            self.y[usize::from(owner)][row] = sum;
            for lane in 0..d {
                or[lane] |= magnitude(sum[lane]);
            }
        }
        let kp = (0..n)
            .map(|row| self.y[usize::from(prog.owner[row])][row])
            .collect();
        MvuPhase {
            kp,
            p_kp,
            kp_or: or,
        }
    }
}

fn capacity(mvus: usize) -> Capacity {
    Capacity {
        mvus,
        nodes: 4096,
        words: 1 << 16,
        tiles: 1024,
    }
}

fn program(m: &RandomMatrix, cap: &Capacity) -> Result<(Recorded, Program), ProgramError> {
    let mut rec = Recorded::default();
    let mut scratch = vec![[0i64; 3]; m.n];
    let prog = build(&m.tiles, &m.words, m.n, cap, &mut scratch, &mut rec)?;
    Ok((rec, prog))
}

/// Runs two phases (with stale Kp memories first) and compares each with the kernel.
fn check(m: &RandomMatrix, mvus: usize, rng: &mut fastrand::Rng, p: Option<Vec<Lanes>>) {
    let (rec, prog) = program(m, &capacity(mvus)).expect("the program fits");
    assert_eq!(prog.words.iter().sum::<usize>(), m.words.len());
    let mut model = Model::new(mvus, m.n);
    for (round, d) in [(0, 3), (1, 1), (2, 2)] {
        let p = match (&p, round) {
            (Some(p), 0) => p.clone(),
            _ => random_p(rng, m.n, 10),
        };
        let want = reference_mvu_phase(m, &p, d);
        let got = model.phase(&rec, m.n, &p, d);
        for (row, (g, w)) in got.kp.iter().zip(&want.kp).enumerate() {
            assert_eq!(g[..d], w[..d], "Kp row {row}, round {round}");
        }
        assert_eq!(got.p_kp[..d], want.p_kp[..d], "pᵀKp, round {round}");
        assert_eq!(got.kp_or[..d], want.kp_or[..d], "OR of |Kp|, round {round}");
    }
}

#[test]
fn every_split_and_mirroring_matches_the_kernel() {
    let mut rng = fastrand::Rng::with_seed(18);
    for split in [Split::Rows, Split::Overlap] {
        for mirroring in [Mirroring::None, Mirroring::All, Mirroring::Extra] {
            for (mvus, n) in [(1, 37), (2, 64), (3, 91), (4, 700), (8, 1100)] {
                let shape = Shape {
                    n,
                    mvus,
                    split,
                    mirroring,
                    row_words: 6,
                    tile_rows: 40,
                    extremes: 10,
                };
                let m = random_matrix(&mut rng, &shape);
                check(&m, mvus, &mut rng, None);
            }
        }
    }
}

/// One direction's p laid out 4 bytes a node (the solver's layout without hardware MVUs) gives
/// the 16-byte layout's Kp, pᵀKp and OR of |Kp| bit for bit, on every split and mirroring and
/// at the edge of exact sums.
#[test]
fn one_directions_compact_p_matches_the_lanes() {
    let mut rng = fastrand::Rng::with_seed(19);
    let mut cases = Vec::new();
    for split in [Split::Rows, Split::Overlap] {
        for mirroring in [Mirroring::None, Mirroring::All, Mirroring::Extra] {
            for (mvus, n) in [(1, 37), (3, 91), (8, 1100)] {
                let shape = Shape {
                    n,
                    mvus,
                    split,
                    mirroring,
                    row_words: 6,
                    tile_rows: 40,
                    extremes: 10,
                };
                let m = random_matrix(&mut rng, &shape);
                let p = random_p(&mut rng, n, 10);
                cases.push((m, p));
            }
        }
    }
    for (mirrored, mvus) in [(false, 1), (true, 2)] {
        cases.push((saturating_matrix(9, mvus, mirrored), saturating_p(9)));
    }
    for (m, p) in &cases {
        let (want, got) = (reference_mvu_phase(m, p, 1), compact_mvu_phase(m, p));
        let kp = |ph: &MvuPhase| ph.kp.iter().map(|k| k[0]).collect::<Vec<_>>();
        assert_eq!(kp(&got), kp(&want), "Kp, n {}", m.n);
        assert_eq!(got.p_kp[0], want.p_kp[0], "pᵀKp, n {}", m.n);
        assert_eq!(got.kp_or[0], want.kp_or[0], "OR of |Kp|, n {}", m.n);
    }
}

#[test]
fn rows_at_the_edge_of_exact_sums_match_the_kernel() {
    let mut rng = fastrand::Rng::with_seed(3);
    for (mirrored, mvus) in [(false, 1), (true, 2), (false, 3)] {
        let m = saturating_matrix(9, mvus, mirrored);
        check(&m, mvus, &mut rng, Some(saturating_p(9)));
    }
}

#[test]
fn a_row_split_between_mvus_is_shared_and_owned_once() {
    let mut rng = fastrand::Rng::with_seed(5);
    let shape = Shape {
        n: 50,
        mvus: 2,
        split: Split::Overlap,
        mirroring: Mirroring::None,
        row_words: 4,
        tile_rows: 10,
        extremes: 0,
    };
    let m = random_matrix(&mut rng, &shape);
    let (rec, prog) = program(&m, &capacity(2)).unwrap();
    assert!(prog.shared_rows > 0);
    for &(row, mask, owner) in &rec.shared {
        assert!(mask.count_ones() > 1 && mask & (1 << owner) != 0);
        assert_eq!(rec.owner[row], owner);
    }
    // A shared row's write-backs never carry a last flag.
    let shared: Vec<usize> = rec.shared.iter().map(|s| s.0).collect();
    for mvu in 0..2 {
        let (mut tile, tiles) = (0, &rec.tiles[mvu]);
        let mut row = tiles[0].0 as usize;
        for &(bits, f) in &rec.words[mvu] {
            let w = Word(bits);
            if w.end_of_row() {
                if shared.contains(&row) {
                    assert_eq!(f & flags::LAST_OWN, 0);
                }
                row += 1;
            }
            if w.end_of_matrix() && tile + 1 < tiles.len() {
                tile += 1;
                row = tiles[tile].0 as usize;
            }
        }
    }
}

#[test]
fn refuses_what_does_not_fit_and_writes_nothing() {
    let mut rng = fastrand::Rng::with_seed(9);
    let shape = Shape {
        n: 40,
        mvus: 2,
        split: Split::Rows,
        mirroring: Mirroring::None,
        row_words: 3,
        tile_rows: 8,
        extremes: 0,
    };
    let m = random_matrix(&mut rng, &shape);
    let small = |f: &dyn Fn(&mut Capacity)| {
        let mut cap = capacity(2);
        f(&mut cap);
        let mut rec = Recorded::default();
        let mut scratch = vec![[0i64; 3]; m.n];
        let err = build(&m.tiles, &m.words, m.n, &cap, &mut scratch, &mut rec).unwrap_err();
        assert!(
            rec.words.is_empty() && rec.owner.is_empty(),
            "{err:?} wrote"
        );
        err
    };
    assert!(matches!(
        small(&|c| c.mvus = 1),
        ProgramError::NoSuchMvu { mvu: 1, .. }
    ));
    assert!(matches!(
        small(&|c| c.nodes = 39),
        ProgramError::DimensionTooLarge { n: 40, .. }
    ));
    assert!(matches!(
        small(&|c| c.words = 10),
        ProgramError::TooManyWords { .. }
    ));
    assert!(matches!(
        small(&|c| c.tiles = 1),
        ProgramError::TooManyTiles { .. }
    ));
    // Row 3 written by no tile.
    let header = TileHeader {
        row_base: 0,
        col_base: 0,
        rows: 3,
        words: 3,
        mvu: 0,
        mirrored: false,
    };
    let words = [
        Word::empty_row(false).0,
        Word::empty_row(false).0,
        EM_BIT | Word::empty_row(false).0,
    ];
    let mut rec = Recorded::default();
    let mut scratch = vec![[0i64; 3]; 4];
    assert_eq!(
        build(&[header], &words, 4, &capacity(1), &mut scratch, &mut rec),
        Err(ProgramError::RowUncovered { row: 3 })
    );
}
