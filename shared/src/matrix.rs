//! How a sparse matrix is laid out as MVU instruction words.
//!
//! The 9-bit column field addresses only 512 columns, so a matrix travels as **tiles** (thesis
//! 4.1.2: sub-matrices, each with its own sub-vector). A tile covers the rows
//! `row_base .. row_base + rows` and the columns `col_base .. col_base + 512`; its words hold, row
//! after row, the nonzeros of that window with columns relative to `col_base`. Every row of the
//! tile ends with an ER word (an empty row is one zero word with ER), and the tile's last word
//! also has EM. The MVU adds each tile row's dot product into `y[row_base + r]`, so tiles may
//! split a row between them (their partial sums add up), which is what lets a later tiler handle
//! bands wider than 512.

use serde::{Deserialize, Serialize};

use crate::word::{Word, COLUMN_WINDOW};

/// Where one tile sits in the matrix, how many words it has, and who runs it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct TileHeader {
    pub row_base: u32,
    pub col_base: u32,
    pub rows: u32,
    pub words: u32,
    /// The MVU (hart) that executes this tile; must be below the target's `harts`.
    pub mvu: u8,
    /// Persymmetric half storage: every word (row i, column j, value v) also adds
    /// v·p[n−1−j] to y[n−1−i] (thesis 2.5 vi, 4.1). Mirrored rows and columns are in range
    /// whenever the tile's own are.
    pub mirrored: bool,
}

/// A structural fault in a tile: the firmware refuses such a matrix before any solve.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, thiserror::Error)]
pub enum MatrixError {
    #[error("tile {tile} has no rows or no words")]
    EmptyTile { tile: u32 },
    #[error("tile {tile} covers rows beyond the matrix dimension")]
    RowsOutOfRange { tile: u32 },
    #[error("tile {tile} has {found} words, its header says {expected}")]
    WordCountMismatch {
        tile: u32,
        expected: u32,
        found: u32,
    },
    #[error("tile {tile} ends {found} rows, its header says {expected}")]
    RowCountMismatch {
        tile: u32,
        expected: u32,
        found: u32,
    },
    #[error("tile {tile} does not end with an EM+ER word")]
    MissingEnd { tile: u32 },
    #[error("tile {tile} has an EM bit before its last word")]
    EarlyEnd { tile: u32 },
    #[error("tile {tile} addresses column {column}, beyond the matrix dimension")]
    ColumnOutOfRange { tile: u32, column: u32 },
    #[error("the tiles hold {found} words in all, the matrix header says {expected}")]
    TotalWordsMismatch { expected: u32, found: u32 },
    #[error("row {row} (reached by tile {tile}) has more words than the MVU's exact 64-bit row sum allows")]
    RowTooLong { tile: u32, row: u32 },
    #[error("tile {tile} is assigned to MVU {mvu}, but the target has {harts} harts")]
    MvuOutOfRange { tile: u32, mvu: u8, harts: u8 },
}

/// Checks a tile's MVU assignment against the harts the target has.
pub fn validate_mvu(tile: u32, header: &TileHeader, harts: u8) -> Result<(), MatrixError> {
    if header.mvu >= harts {
        return Err(MatrixError::MvuOutOfRange {
            tile,
            mvu: header.mvu,
            harts,
        });
    }
    Ok(())
}

/// Checks one tile's words against its header and the dimension `n`.
pub fn validate_tile(
    tile: u32,
    header: &TileHeader,
    words: &[u32],
    n: u32,
) -> Result<(), MatrixError> {
    if header.rows == 0 || header.words == 0 {
        return Err(MatrixError::EmptyTile { tile });
    }
    if header
        .row_base
        .checked_add(header.rows)
        .is_none_or(|end| end > n)
    {
        return Err(MatrixError::RowsOutOfRange { tile });
    }
    if words.len() as u64 != header.words as u64 {
        return Err(MatrixError::WordCountMismatch {
            tile,
            expected: header.words,
            found: words.len() as u32,
        });
    }
    let last = words.len() - 1;
    let mut rows = 0u32;
    for (i, &bits) in words.iter().enumerate() {
        let w = Word(bits);
        let column = header.col_base as u64 + w.column() as u64;
        if column >= n as u64 {
            return Err(MatrixError::ColumnOutOfRange {
                tile,
                column: column.min(u32::MAX as u64) as u32,
            });
        }
        rows += w.end_of_row() as u32;
        if w.end_of_matrix() && i != last {
            return Err(MatrixError::EarlyEnd { tile });
        }
    }
    let end = Word(words[last]);
    if !(end.end_of_matrix() && end.end_of_row()) {
        return Err(MatrixError::MissingEnd { tile });
    }
    if rows != header.rows {
        return Err(MatrixError::RowCountMismatch {
            tile,
            expected: header.rows,
            found: rows,
        });
    }
    Ok(())
}

/// CRC-32 of a word stream as it is stored (little-endian bytes), for the end-of-matrix check.
pub fn words_crc(words: &[u32]) -> u32 {
    let mut digest = crate::frame::CRC32.digest();
    for w in words {
        digest.update(&w.to_le_bytes());
    }
    digest.finalize()
}

/// The largest column window one tile may address.
pub const TILE_COLUMNS: u32 = COLUMN_WINDOW;

#[cfg(test)]
mod tests {
    use super::*;

    fn w(col: u32, v: i64, er: bool, em: bool) -> u32 {
        Word::new(col, v, er, em).unwrap().bits()
    }

    fn tile(rows: u32, words: &[u32]) -> TileHeader {
        TileHeader {
            row_base: 0,
            col_base: 0,
            rows,
            words: words.len() as u32,
            mvu: 0,
            mirrored: false,
        }
    }

    #[test]
    fn accepts_a_well_formed_tile_with_an_empty_row() {
        let words = [
            w(0, 2, false, false),
            w(1, -1, true, false),
            w(0, 0, true, false),
            w(1, 3, true, true),
        ];
        assert_eq!(validate_tile(0, &tile(3, &words), &words, 3), Ok(()));
    }

    #[test]
    fn refuses_each_structural_fault() {
        let good = [w(0, 2, true, false), w(1, 3, true, true)];
        assert_eq!(
            validate_tile(0, &tile(3, &good), &good, 2),
            Err(MatrixError::RowsOutOfRange { tile: 0 })
        );
        assert_eq!(
            validate_tile(0, &tile(3, &good), &good, 3),
            Err(MatrixError::RowCountMismatch {
                tile: 0,
                expected: 3,
                found: 2
            })
        );
        assert_eq!(
            validate_tile(0, &tile(2, &good), &good, 1),
            Err(MatrixError::RowsOutOfRange { tile: 0 })
        );
        let wide = [w(0, 2, true, false), w(5, 3, true, true)];
        assert_eq!(
            validate_tile(1, &tile(2, &wide), &wide, 4),
            Err(MatrixError::ColumnOutOfRange { tile: 1, column: 5 })
        );
        let early = [w(0, 2, true, true), w(1, 3, true, true)];
        assert_eq!(
            validate_tile(0, &tile(2, &early), &early, 2),
            Err(MatrixError::EarlyEnd { tile: 0 })
        );
        let open = [w(0, 2, true, false), w(1, 3, true, false)];
        assert_eq!(
            validate_tile(0, &tile(2, &open), &open, 2),
            Err(MatrixError::MissingEnd { tile: 0 })
        );
        assert_eq!(
            validate_tile(0, &tile(2, &[]), &[], 2),
            Err(MatrixError::EmptyTile { tile: 0 })
        );
        let h = TileHeader {
            words: 5,
            ..tile(2, &good)
        };
        assert_eq!(
            validate_tile(0, &h, &good, 2),
            Err(MatrixError::WordCountMismatch {
                tile: 0,
                expected: 5,
                found: 2
            })
        );
        let h = TileHeader {
            row_base: u32::MAX,
            ..tile(2, &good)
        };
        assert_eq!(
            validate_tile(0, &h, &good, 2),
            Err(MatrixError::RowsOutOfRange { tile: 0 })
        );
    }

    #[test]
    fn the_mvu_must_exist() {
        let h = TileHeader {
            mvu: 3,
            ..TileHeader::default()
        };
        assert_eq!(validate_mvu(0, &h, 4), Ok(()));
        assert_eq!(
            validate_mvu(5, &h, 3),
            Err(MatrixError::MvuOutOfRange {
                tile: 5,
                mvu: 3,
                harts: 3
            })
        );
    }

    #[test]
    fn crc_depends_on_every_word() {
        assert_ne!(words_crc(&[1, 2, 3]), words_crc(&[1, 2, 4]));
        assert_ne!(words_crc(&[1, 2, 3]), words_crc(&[2, 1, 3]));
    }
}
