//! Cutting one MVU's rows into tiles whose column window is at most 512 wide.
//!
//! A word's 9-bit column addresses 512 columns, relative to its tile's `col_base`. A row whose
//! columns span more than that (model B on 16³ spans 547, model A on 32³ spans 2049) is split
//! over several tiles; the MVU adds every tile row into `y[row]`, so the partial sums add up.
//!
//! The tiler sweeps the rows in order and keeps a few tiles *open*, each with a fixed window
//! `col_base .. col_base + 512`. Each nonzero of the current row goes to the open tile with the
//! lowest window that contains it; the nonzeros no open window takes start new tiles, each at
//! the first such column (so that a band drifting right keeps fitting for as long as possible).
//! For a band matrix this settles into a few staggered tiles per row block, every row feeding
//! every open tile, and the only overhead is:
//!
//! - one tile header per tile (the target's tile store and one `Tile` message), and
//! - an empty-row word (zero value, ER) wherever an open tile gets nothing from a row between
//!   two rows it does get something from. A tile left without nonzeros for more than
//!   [`MAX_EMPTY_RUN`] rows is closed instead, which trades those words for a header.
//!
//! A tile is also closed at [`MAX_TILE_ROWS`] rows, so its row bookkeeping stays small.

use deform_shared::matrix::{TileHeader, TILE_COLUMNS};
use deform_shared::word::Word;

use super::partition::Piece;
use super::{EncodeError, QuantizedMatrix};

/// The most rows one tile takes.
pub const MAX_TILE_ROWS: u32 = 512;

/// The longest run of empty rows an open tile bridges with empty-row words before it is closed:
/// about what a tile header costs in words.
pub const MAX_EMPTY_RUN: u32 = 8;

/// Where finished tiles go, in stream order.
#[derive(Debug)]
pub struct TileSink {
    pub n: u32,
    pub tiles: Vec<TileHeader>,
    pub words: Vec<u32>,
    /// Zero words that only end an empty row.
    pub empty_row_words: usize,
}

impl TileSink {
    pub fn new(n: u32) -> Self {
        TileSink {
            n,
            tiles: Vec::new(),
            words: Vec::new(),
            empty_row_words: 0,
        }
    }
}

struct OpenTile {
    /// Creation order, which is the order tiles are emitted in.
    seq: usize,
    col_base: u32,
    row_base: u32,
    /// The row after the last one written.
    next_row: u32,
    words: Vec<u32>,
    empty_row_words: usize,
}

impl OpenTile {
    fn new(seq: usize, col_base: u32, row: u32) -> Self {
        OpenTile {
            seq,
            col_base,
            row_base: row,
            next_row: row,
            words: Vec::new(),
            empty_row_words: 0,
        }
    }

    fn contains(&self, column: u32) -> bool {
        column >= self.col_base && column - self.col_base < TILE_COLUMNS
    }

    /// Writes row `row` (after empty-row words for any rows skipped since the last one).
    fn push_row(&mut self, row: u32, entries: &[(u32, i32)]) -> Result<(), EncodeError> {
        for _ in self.next_row..row {
            self.words.push(Word::empty_row(false).bits());
            self.empty_row_words += 1;
        }
        if entries.is_empty() {
            self.words.push(Word::empty_row(false).bits());
            self.empty_row_words += 1;
        }
        for (k, &(column, raw)) in entries.iter().enumerate() {
            let end_of_row = k + 1 == entries.len();
            self.words
                .push(Word::new(column - self.col_base, raw as i64, end_of_row, false)?.bits());
        }
        self.next_row = row + 1;
        Ok(())
    }

    fn finish(mut self, mvu: u8, mirrored: bool) -> (usize, TileHeader, Vec<u32>, usize) {
        if let Some(last) = self.words.last_mut() {
            *last |= Word::empty_row(true).bits();
        }
        let header = TileHeader {
            row_base: self.row_base,
            col_base: self.col_base,
            rows: self.next_row - self.row_base,
            words: self.words.len() as u32,
            mvu,
            mirrored,
        };
        (self.seq, header, self.words, self.empty_row_words)
    }
}

/// Tiles `pieces` (rows ascending) for MVU `mvu`, mirrored or plain, into `sink`.
pub fn tile(
    q: &QuantizedMatrix,
    pieces: &[Piece],
    mvu: u8,
    mirrored: bool,
    sink: &mut TileSink,
) -> Result<(), EncodeError> {
    let mut open: Vec<OpenTile> = Vec::new();
    let mut done = Vec::new();
    let mut seq = 0;
    let mut per_tile: Vec<Vec<(u32, i32)>> = Vec::new();
    let mut leftover: Vec<(u32, i32)> = Vec::new();
    for piece in pieces {
        let row = piece.row;
        // Close the tiles this row cannot join: full, or idle for too long.
        let (keep, close): (Vec<_>, Vec<_>) = open
            .into_iter()
            .partition(|t| row - t.row_base < MAX_TILE_ROWS && row - t.next_row <= MAX_EMPTY_RUN);
        open = keep;
        done.extend(close.into_iter().map(|t| t.finish(mvu, mirrored)));
        // Open tiles are kept ordered by window, lowest first.
        open.sort_by_key(|t| t.col_base);
        per_tile.iter_mut().for_each(Vec::clear);
        per_tile.resize(open.len(), Vec::new());
        leftover.clear();
        for index in piece.entries.clone() {
            let (column, raw) = q.entry(index);
            match open.iter().position(|t| t.contains(column)) {
                Some(t) => per_tile[t].push((column, raw)),
                None => leftover.push((column, raw)),
            }
        }
        if piece.entries.is_empty() {
            // A row without nonzeros still needs its ER word somewhere, so its Kp entry is set.
            if let Some(t) = open.first_mut() {
                t.push_row(row, &[])?;
            } else {
                let mut t = OpenTile::new(seq, 0, row);
                seq += 1;
                t.push_row(row, &[])?;
                open.push(t);
            }
            continue;
        }
        for (t, entries) in open.iter_mut().zip(&per_tile) {
            if !entries.is_empty() {
                t.push_row(row, entries)?;
            }
        }
        // What no open window takes starts new tiles, each at its first column.
        let mut rest = leftover.as_slice();
        while let Some(&(col_base, _)) = rest.first() {
            let take = rest
                .iter()
                .position(|&(c, _)| c - col_base >= TILE_COLUMNS)
                .unwrap_or(rest.len());
            let mut t = OpenTile::new(seq, col_base, row);
            seq += 1;
            t.push_row(row, &rest[..take])?;
            open.push(t);
            rest = &rest[take..];
        }
    }
    done.extend(open.into_iter().map(|t| t.finish(mvu, mirrored)));
    done.sort_by_key(|(seq, ..)| *seq);
    for (_, header, words, empty) in done {
        sink.tiles.push(header);
        sink.words.extend(words);
        sink.empty_row_words += empty;
    }
    Ok(())
}
