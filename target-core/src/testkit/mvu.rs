//! Random tiled matrices for the MVU's tests — the hardware MVUs' program
//! ([`crate::mvu_program`]) here, the gateware's unit tests in hil-sim — and the MVU phase's
//! reference results, computed by the portable kernel ([`crate::kernel`]): the specification the
//! gateware must meet bit for bit.
#![allow(unsafe_code)]

extern crate std;

use std::vec;
use std::vec::Vec;

use deform_shared::matrix::{validate_tile, TileHeader};
use deform_shared::protocol::MAX_DIRECTIONS;
use deform_shared::word::{Word, COLUMN_WINDOW, EM_BIT, VALUE_MAX, VALUE_MIN};

use crate::cg::MAX_WORDS_PER_ROW;
use crate::kernel::{p_kp_and_max, run_tile_dyn, Lanes, Sums, TileRun};
use crate::mvu_program::{ProgramSink, TileEntry};

/// How the tiles are shared out between the MVUs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Split {
    /// Each MVU a block of whole rows (thesis 4.1.2): no row is written by two MVUs.
    Rows,
    /// Tiles cut inside rows and handed to different MVUs (4.1.1): rows shared at the cuts.
    Overlap,
}

/// Which tiles are mirrored (persymmetric half storage).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mirroring {
    None,
    /// The tiles store rows 0..⌈n/2⌉ and every one is mirrored onto the bottom half.
    All,
    /// Every row stored plainly, plus some mirrored tiles on top (mirror and own rows meet).
    Extra,
}

/// What [`random_matrix`] draws.
#[derive(Debug, Clone, Copy)]
pub struct Shape {
    pub n: usize,
    pub mvus: usize,
    pub split: Split,
    pub mirroring: Mirroring,
    /// Nonzeros per stored row, at most (drawn from 0 ..= this).
    pub row_words: usize,
    /// Rows per tile, at most.
    pub tile_rows: usize,
    /// Chance in percent that a value or p element is an extreme of its range.
    pub extremes: u32,
}

/// A validated tiled matrix and the search directions to multiply.
#[derive(Debug, Clone)]
pub struct RandomMatrix {
    pub n: usize,
    pub tiles: Vec<TileHeader>,
    /// The tiles' words back to back.
    pub words: Vec<u32>,
}

/// The MVU phase's results: Kp per row, pᵀKp and the OR of |Kp| per direction.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MvuPhase {
    pub kp: Vec<Sums>,
    pub p_kp: [i128; MAX_DIRECTIONS],
    pub kp_or: [u64; MAX_DIRECTIONS],
}

/// The largest p mantissa (|p| < 2^30, see `crate::cg`).
pub const P_LIMIT: i32 = (1 << 30) - 1;

fn value(rng: &mut fastrand::Rng, extremes: u32) -> i64 {
    if rng.u32(0..100) < extremes {
        if rng.bool() {
            i64::from(VALUE_MIN)
        } else {
            i64::from(VALUE_MAX)
        }
    } else {
        i64::from(rng.i32(VALUE_MIN..=VALUE_MAX))
    }
}

/// n search directions (all lanes, the padding lane random too), |p| < 2^30.
pub fn random_p(rng: &mut fastrand::Rng, n: usize, extremes: u32) -> Vec<Lanes> {
    (0..n)
        .map(|_| {
            core::array::from_fn(|_| {
                if rng.u32(0..100) < extremes {
                    if rng.bool() {
                        P_LIMIT
                    } else {
                        -P_LIMIT
                    }
                } else {
                    rng.i32(-P_LIMIT..=P_LIMIT)
                }
            })
        })
        .collect()
}

/// One tile in the making: its rows' (column, value) entries within one column window.
struct Draft {
    row_base: usize,
    col_base: usize,
    rows: Vec<Vec<(usize, i64)>>,
    mvu: usize,
    mirrored: bool,
}

impl Draft {
    fn push(self, n: usize, tiles: &mut Vec<TileHeader>, words: &mut Vec<u32>) {
        let start = words.len();
        for row in &self.rows {
            if row.is_empty() {
                words.push(Word::empty_row(false).bits());
            }
            for (k, &(c, v)) in row.iter().enumerate() {
                let w = Word::new((c - self.col_base) as u32, v, k + 1 == row.len(), false);
                words.push(w.expect("drawn words encode").bits());
            }
        }
        *words.last_mut().expect("a tile has rows") |= EM_BIT;
        let header = TileHeader {
            row_base: self.row_base as u32,
            col_base: self.col_base as u32,
            rows: self.rows.len() as u32,
            words: (words.len() - start) as u32,
            mvu: self.mvu as u8,
            mirrored: self.mirrored,
        };
        let tile = tiles.len() as u32;
        validate_tile(tile, &header, &words[start..], n as u32).expect("drawn tiles are valid");
        tiles.push(header);
    }
}

/// A random tiled matrix of `shape`: every row written by some tile, columns anywhere in
/// 0..n (so tiles beyond the first 512 columns where n > 512), empty rows, rows cut between
/// tiles, and no row longer than the MVU's exact 64-bit sums allow.
pub fn random_matrix(rng: &mut fastrand::Rng, shape: &Shape) -> RandomMatrix {
    let n = shape.n;
    let window = COLUMN_WINDOW as usize;
    let stored = if shape.mirroring == Mirroring::All {
        n.div_ceil(2)
    } else {
        n
    };
    let mvus = shape.mvus.max(1);
    // The tiles' row ranges, the same in every column window (so that a row split keeps the
    // rows of a tile on one MVU).
    let mut bounds = vec![0];
    while bounds[bounds.len() - 1] < stored {
        let r0 = bounds[bounds.len() - 1];
        bounds.push((r0 + rng.usize(1..=shape.tile_rows.max(1))).min(stored));
    }
    let mut drafts = Vec::new();
    for w in 0..n.div_ceil(window) {
        for range in bounds.windows(2) {
            let (r0, r1) = (range[0], range[1]);
            let rows: Vec<Vec<(usize, i64)>> = (r0..r1)
                .map(|_| {
                    let lo = w * window;
                    let hi = (lo + window).min(n);
                    let mut row: Vec<(usize, i64)> = (0..rng.usize(0..=shape.row_words))
                        .map(|_| (rng.usize(lo..hi), value(rng, shape.extremes)))
                        .collect();
                    row.sort_by_key(|e| e.0);
                    row
                })
                .collect();
            // Window 0 covers every row; the others only where they have entries.
            if w == 0 || rows.iter().any(|r| !r.is_empty()) {
                let mvu = r0 * mvus / stored;
                let mirrored = shape.mirroring == Mirroring::All;
                cut(rng, shape, r0, w * window, rows, mvu, mirrored, &mut drafts);
            }
        }
    }
    if shape.mirroring == Mirroring::Extra {
        for _ in 0..rng.usize(1..=4) {
            let r0 = rng.usize(0..n);
            let r1 = (r0 + rng.usize(1..=shape.tile_rows.max(1))).min(n);
            let rows = (r0..r1)
                .map(|_| {
                    (0..rng.usize(0..=shape.row_words.min(window)))
                        .map(|_| (rng.usize(0..window.min(n)), value(rng, shape.extremes)))
                        .collect::<Vec<_>>()
                })
                .map(|mut row| {
                    row.sort_by_key(|e| e.0);
                    row
                })
                .collect();
            let mvu = rng.usize(0..mvus);
            drafts.push(Draft {
                row_base: r0,
                col_base: 0,
                rows,
                mvu,
                mirrored: true,
            });
        }
    }
    let (mut tiles, mut words) = (Vec::new(), Vec::new());
    for d in drafts {
        d.push(n, &mut tiles, &mut words);
    }
    let m = RandomMatrix { n, tiles, words };
    assert!(rows_fit(&m), "a drawn row is too long for exact sums");
    m
}

/// Appends the tile of rows `r0..` (one window's entries `rows`), cut in two inside a row and
/// shared between MVU `mvu` and the next one when the split is [`Split::Overlap`].
#[allow(clippy::too_many_arguments)]
fn cut(
    rng: &mut fastrand::Rng,
    shape: &Shape,
    r0: usize,
    col_base: usize,
    mut rows: Vec<Vec<(usize, i64)>>,
    mvu: usize,
    mirrored: bool,
    drafts: &mut Vec<Draft>,
) {
    let draft = |row_base, rows, mvu| Draft {
        row_base,
        col_base,
        rows,
        mvu,
        mirrored,
    };
    if shape.split == Split::Overlap && shape.mvus > 1 && rng.u32(0..3) > 0 {
        let at = rng.usize(0..rows.len());
        let tail_rows = rows.split_off(at + 1);
        let row = rows.last_mut().expect("the cut row");
        let tail_of_row = row.split_off(rng.usize(0..=row.len()));
        let mut second = vec![tail_of_row];
        second.extend(tail_rows);
        drafts.push(draft(r0, rows, mvu));
        drafts.push(draft(r0 + at, second, (mvu + 1) % shape.mvus));
    } else {
        drafts.push(draft(r0, rows, mvu));
    }
}

/// A matrix at the edge of the MVU's exact arithmetic: row 0 sums [`MAX_WORDS_PER_ROW`] − 1
/// products of the most negative value and p[0] = ∓(2^30 − 1) (|Kp| just below 2^62 in each
/// lane, of either sign; pᵀKp near 2^92), its words shared out between the MVUs (each adds its
/// part into the row: the partial sums meet in the shared-row reduction); the other rows short.
/// p from [`saturating_p`].
pub fn saturating_matrix(n: usize, mvus: usize, mirrored: bool) -> RandomMatrix {
    let long = MAX_WORDS_PER_ROW as usize - 1;
    let mvus = mvus.max(1);
    let (mut tiles, mut words) = (Vec::new(), Vec::new());
    let mut tile = |row_base: usize, rows: Vec<Vec<(usize, i64)>>, mvu: usize| {
        let draft = Draft {
            row_base,
            col_base: 0,
            rows,
            mvu,
            mirrored,
        };
        draft.push(n, &mut tiles, &mut words);
    };
    for m in 0..mvus {
        let part = long * (m + 1) / mvus - long * m / mvus;
        tile(0, vec![vec![(0, i64::from(VALUE_MIN)); part]], m);
    }
    let stored = if mirrored { n.div_ceil(2) } else { n };
    let rows: Vec<Vec<(usize, i64)>> = (1..stored)
        .map(|i| vec![(0, 1), (i, i64::from(VALUE_MIN))])
        .collect();
    let per = rows.len().div_ceil(mvus).max(1);
    for (k, chunk) in rows.chunks(per).enumerate() {
        tile(1 + k * per, chunk.to_vec(), k);
    }
    RandomMatrix { n, tiles, words }
}

/// p for [`saturating_matrix`]: the extremes of its range.
pub fn saturating_p(n: usize) -> Vec<Lanes> {
    (0..n)
        .map(|i| {
            let s = if i % 3 == 1 { -P_LIMIT } else { P_LIMIT };
            [-P_LIMIT, s, -s, P_LIMIT]
        })
        .collect()
}

/// True if no row's words (own and mirrored, over all tiles) exceed [`MAX_WORDS_PER_ROW`].
fn rows_fit(m: &RandomMatrix) -> bool {
    let mut counts = vec![0u32; m.n];
    let mut words = m.words.iter();
    for t in &m.tiles {
        let mut row = t.row_base as usize;
        for &w in words.by_ref().take(t.words as usize) {
            counts[row] += 1;
            if t.mirrored {
                counts[m.n - 1 - row] += 1;
            }
            row += usize::from(Word(w).end_of_row());
        }
    }
    counts.iter().all(|&c| c <= MAX_WORDS_PER_ROW)
}

/// The MVU phase by the portable kernel: every tile added into Kp (mirror rows included), then
/// pᵀKp and the OR of |Kp| over the finished rows, for `directions` fused directions.
pub fn reference_mvu_phase(m: &RandomMatrix, p: &[Lanes], directions: usize) -> MvuPhase {
    mvu_phase_in::<4, 3>(m, &p[..m.n], directions)
}

/// [`reference_mvu_phase`] for one direction with p laid out 4 bytes a node and Kp 8 bytes a
/// row, as the solver lays them out for one direction without hardware MVUs
/// ([`crate::kernel::lane_words`], [`crate::kernel::sum_words`]): p's first lane only; Kp's
/// rows are returned as [`Sums`] with the other lanes zero.
pub fn compact_mvu_phase(m: &RandomMatrix, p: &[Lanes]) -> MvuPhase {
    let compact: Vec<[i32; 1]> = p[..m.n].iter().map(|l| [l[0]]).collect();
    mvu_phase_in::<1, 1>(m, &compact, 1)
}

/// The MVU phase by the portable kernel with p `S` i32 words a node and Kp `R` i64 words a row
/// (the kernel's layouts: `R` is [`crate::kernel::sum_words`]`(S)`).
fn mvu_phase_in<const S: usize, const R: usize>(
    m: &RandomMatrix,
    p: &[[i32; S]],
    directions: usize,
) -> MvuPhase {
    let n = m.n;
    assert!(p.len() >= n && (1..=MAX_DIRECTIONS.min(S)).contains(&directions));
    assert_eq!(R, crate::kernel::sum_words(S));
    let mut kp = vec![[0i64; R]; n];
    let mut start = 0usize;
    for (i, t) in m.tiles.iter().enumerate() {
        let tile_words = &m.words[start..start + t.words as usize];
        validate_tile(i as u32, t, tile_words, n as u32).expect("a valid tile");
        let (row_base, col_base) = (t.row_base as usize, t.col_base as usize);
        let run = TileRun {
            words: tile_words.as_ptr(),
            rows: t.rows,
            p_cols: p.as_ptr().wrapping_add(col_base).cast(),
            p_mirror_cols: p.as_ptr().wrapping_add(n - 1 - col_base).cast(),
            y: kp.as_mut_ptr().wrapping_add(row_base).cast(),
            y_mirror: kp.as_mut_ptr().wrapping_add(n - 1 - row_base).cast(),
        };
        // SAFETY: the tile was validated against n just above; p and kp hold n elements, so
        // every column, mirrored column, row and mirror row the tile reaches is in bounds, and
        // nothing else touches kp during the call.
        unsafe { run_tile_dyn::<S>(&run, directions, t.mirrored, false, false) };
        start += t.words as usize;
    }
    let (p_kp, kp_or) = p_kp_and_max(&p[..n], &kp, directions);
    let kp = kp
        .iter()
        .map(|row| core::array::from_fn(|d| row.get(d).copied().unwrap_or(0)))
        .collect();
    MvuPhase { kp, p_kp, kp_or }
}

/// A hardware MVU program kept in memory ([`crate::mvu_program::build`]'s output), as the
/// program's tests and the gateware's vectors use it.
#[derive(Debug, Clone, Default)]
pub struct Recorded {
    /// Per MVU: (word, flags) entries.
    pub words: Vec<Vec<(u32, u8)>>,
    /// Per MVU: (row_base, col_base, mirror_col_base, mirrored).
    pub tiles: Vec<Vec<(u32, u32, u32, bool)>>,
    /// Per MVU: words run per phase.
    pub lengths: Vec<usize>,
    /// Per row: the owner MVU.
    pub owner: Vec<u8>,
    /// (row, contributor mask, owner).
    pub shared: Vec<(usize, u8, u8)>,
}

fn put<T: Default + Clone>(v: &mut Vec<T>, i: usize, x: T) {
    if v.len() <= i {
        v.resize(i + 1, T::default());
    }
    v[i] = x;
}

impl ProgramSink for Recorded {
    fn word(&mut self, mvu: usize, index: usize, word: u32, flags: u8) {
        if self.words.len() <= mvu {
            self.words.resize(mvu + 1, Vec::new());
        }
        put(&mut self.words[mvu], index, (word, flags));
    }
    fn tile(&mut self, mvu: usize, index: usize, e: TileEntry) {
        if self.tiles.len() <= mvu {
            self.tiles.resize(mvu + 1, Vec::new());
        }
        let entry = (e.row_base, e.col_base, e.mirror_col_base, e.mirrored);
        put(&mut self.tiles[mvu], index, entry);
    }
    fn length(&mut self, mvu: usize, words: usize) {
        put(&mut self.lengths, mvu, words);
    }
    fn owner(&mut self, row: usize, owner: u8) {
        put(&mut self.owner, row, owner);
    }
    fn shared(&mut self, index: usize, row: usize, contributors: u8, owner: u8) {
        put(&mut self.shared, index, (row, contributors, owner));
    }
}
