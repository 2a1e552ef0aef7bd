//! Test support shared by every test that runs a session or builds a test matrix: the session's
//! storage as owned buffers, and tiled test systems built row by row. Compiled for this crate's
//! own tests and, with the `testkit` feature, for the host's, hil-sim's and the fuzz targets'
//! (one copy instead of four; never in the firmware).

extern crate std;

use std::vec;
use std::vec::Vec;

use deform_shared::live::MAX_TOOL_NODES;
use deform_shared::matrix::TileHeader;
use deform_shared::protocol::{TargetInfo, MAX_DIRECTIONS};
use deform_shared::qformat::quantize;
use deform_shared::word::{Word, EM_BIT};

use crate::exec::Sequential;
use crate::kernel::{Lanes, Sums};
use crate::session::{DirectionStorage, Session, Storage};

/// The buffers a [`Session`] borrows, owned: the matrix store, each direction's vectors and
/// the solver's work vectors, sized for `words`, `tiles` and `max_n`.
/// The fields are public so that a test can shorten one or inspect what a session wrote.
pub struct OwnedStorage {
    pub words: Vec<u32>,
    pub tiles: Vec<TileHeader>,
    /// Each direction's `[b, x, x0, r]`.
    pub directions: [[Vec<i32>; 4]; MAX_DIRECTIONS],
    pub p: Vec<Lanes>,
    pub kp: Vec<Sums>,
    pub partial: Vec<Sums>,
    /// The live loop's response columns: room for every tool node's at `max_n`, and their
    /// residuals.
    pub responses: Vec<i32>,
    pub residuals: Vec<i16>,
    /// A dynamic session's stiffness copy, as long as `words`.
    pub stiffness: Vec<u32>,
}

impl OwnedStorage {
    /// Zeroed buffers; `partial` holds twice `max_n` rows of private partial sums.
    pub fn new(words: usize, tiles: usize, max_n: usize) -> Self {
        OwnedStorage {
            words: vec![0; words],
            tiles: vec![TileHeader::default(); tiles],
            directions: core::array::from_fn(|_| core::array::from_fn(|_| vec![0; max_n])),
            p: vec![[0; 4]; max_n],
            kp: vec![[0; MAX_DIRECTIONS]; max_n],
            partial: vec![[0; MAX_DIRECTIONS]; 2 * max_n],
            responses: vec![0; MAX_TOOL_NODES * max_n],
            residuals: vec![0; MAX_TOOL_NODES * max_n],
            stiffness: vec![0; words],
        }
    }

    /// Buffers for the capacities `info` reports.
    pub fn for_info(info: &TargetInfo) -> Self {
        Self::new(
            info.word_capacity as usize,
            info.tile_capacity as usize,
            info.max_n as usize,
        )
    }

    /// The buffers, lent as a session's [`Storage`].
    pub fn storage(&mut self) -> Storage<'_> {
        let [d0, d1, d2] = &mut self.directions;
        Storage {
            words: &mut self.words,
            tiles: &mut self.tiles,
            directions: [direction(d0), direction(d1), direction(d2)],
            p: &mut self.p,
            kp: &mut self.kp,
            partial: &mut self.partial,
            responses: &mut self.responses,
            residuals: &mut self.residuals,
            stiffness: &mut self.stiffness,
        }
    }

    /// A session over these buffers, its MVUs run one after another on this thread.
    pub fn session(&mut self, info: TargetInfo, harts: usize) -> Session<'_, Sequential> {
        Session::new(self.storage(), info, Sequential { harts })
    }

    /// A session over freshly leaked buffers sized by `info` (for a fake target that lives as
    /// long as its test), with as many MVUs as `info` reports.
    pub fn leaked_session(info: TargetInfo) -> Session<'static, Sequential> {
        let harts = usize::from(info.harts);
        let storage = std::boxed::Box::leak(std::boxed::Box::new(Self::for_info(&info)));
        Session::new(storage.storage(), info, Sequential { harts })
    }
}

/// One direction's vectors (b, x, x0, r), lent.
fn direction(vectors: &mut [Vec<i32>; 4]) -> DirectionStorage<'_> {
    let [b, x, x0, r] = vectors;
    DirectionStorage { b, x, x0, r }
}

/// A matrix encoded as tiles of instruction words, ready to upload (the host's
/// `EncodedMatrix` has the same fields).
#[derive(Debug, Clone, PartialEq)]
pub struct TestSystem {
    pub n: u32,
    pub frac_bits: u8,
    pub tiles: Vec<TileHeader>,
    pub words: Vec<u32>,
}

/// Encodes rows `0..rows` of an n×n matrix, `row(i)` giving row i's `(column, value)` entries
/// in column order, `rows_per_tile` rows per tile, each tile's column window starting at its
/// smallest column (the caller keeps a tile's columns within 512 of it). A row without entries
/// becomes an empty-row word. Values are quantised with `frac_bits` fractional bits.
pub fn encode_rows(
    n: usize,
    rows: usize,
    rows_per_tile: usize,
    frac_bits: u8,
    row: impl Fn(usize) -> Vec<(usize, f64)>,
) -> TestSystem {
    let mut tiles = Vec::new();
    let mut words = Vec::new();
    for base in (0..rows).step_by(rows_per_tile) {
        let entries: Vec<_> = (base..rows.min(base + rows_per_tile)).map(&row).collect();
        let col_base = entries.iter().flatten().map(|&(c, _)| c).min().unwrap_or(0);
        let start = words.len();
        for entries in &entries {
            if entries.is_empty() {
                words.push(Word::empty_row(false).bits());
            }
            for (k, &(c, v)) in entries.iter().enumerate() {
                let raw = quantize(v, frac_bits).expect("test values fit the Q-format") as i64;
                let er = k + 1 == entries.len();
                let word = Word::new((c - col_base) as u32, raw, er, false);
                words.push(word.expect("test words encode").bits());
            }
        }
        *words.last_mut().expect("a tile has words") |= EM_BIT;
        tiles.push(TileHeader {
            row_base: base as u32,
            col_base: col_base as u32,
            rows: entries.len() as u32,
            words: (words.len() - start) as u32,
            mvu: 0,
            mirrored: false,
        });
    }
    TestSystem {
        n: n as u32,
        frac_bits,
        tiles,
        words,
    }
}

/// Row i of the symmetric banded matrix of order `n` with 2 on the diagonal and −1/h on the
/// `h` nearest off-diagonals either side: SPD (the first and last rows are strictly dominant);
/// `h = 1` is the 1-D Laplacian tridiag(−1, 2, −1).
pub fn banded_row(n: usize, h: usize) -> impl Fn(usize) -> Vec<(usize, f64)> {
    move |i| {
        (i.saturating_sub(h)..=(i + h).min(n - 1))
            .map(|c| (c, if c == i { 2.0 } else { -1.0 / h as f64 }))
            .collect()
    }
}

/// The encoded matrix as the target sees it, dense, in f64.
pub fn dense(system: &TestSystem) -> Vec<Vec<f64>> {
    let n = system.n as usize;
    let mut a = vec![vec![0.0; n]; n];
    let mut words = system.words.iter();
    let lsb = 1.0 / (1u64 << system.frac_bits) as f64;
    for t in &system.tiles {
        let mut row = t.row_base as usize;
        for &bits in words.by_ref().take(t.words as usize) {
            let w = Word(bits);
            a[row][t.col_base as usize + w.column() as usize] += f64::from(w.raw_value()) * lsb;
            row += usize::from(w.end_of_row());
        }
    }
    a
}

pub mod fuzz;
