//! K as MVU instruction words: Q-format selection and tiling (thesis 4.1.2).
//! (Owned by the model work; the type below is the contract the link code relies on.)
//!
//! # Q-format
//!
//! One fractional-bit count F serves the whole matrix, the largest with which the largest
//! |value| still fits the 21-bit field ([`deform_shared::qformat::choose_frac_bits`]); every
//! value is rounded to the nearest multiple of 2^-F. An integer matrix such as A is therefore
//! exact, and any other value is off by at most half an LSB. A value that rounds to 0 is not
//! stored at all: it would cost a word and add nothing.
//!
//! # Tiles
//!
//! A word's 9-bit column addresses 512 columns, so the matrix is cut into tiles
//! ([`deform_shared::matrix`]). This encoder uses the simplest tiling that suits K's band
//! structure: contiguous blocks of whole rows, each block as long as the union of its rows'
//! columns fits one 512-column window starting at the block's smallest column (and at most
//! [`MAX_TILE_ROWS`] rows). K of a 10×10×10 grid has a half-band of 100 (model A) or 111
//! (model B), so every row fits with room to share a window with its neighbours. A row that
//! alone spans 512 columns or more (a 16×16×16 grid in model B has a half-band of 273) would
//! need a row split across tiles, which the layout allows but this encoder does not do yet.

use deform_shared::matrix::{validate_tile, MatrixError, TileHeader, TILE_COLUMNS};
use deform_shared::qformat::{choose_frac_bits, dequantize, pow2, quantize, QFormatError};
use deform_shared::word::{Word, WordError};

use crate::model::sparse::{Csr, CsrBuilder};

/// A matrix ready to stream to the target: tiles in order and their words back to back.
#[derive(Debug, Clone, PartialEq)]
pub struct EncodedMatrix {
    pub n: u32,
    /// Fractional bits of every word's value field: value = raw · 2^-frac_bits.
    pub frac_bits: u8,
    pub tiles: Vec<TileHeader>,
    pub words: Vec<u32>,
}

impl EncodedMatrix {
    /// The value of one LSB of the value field, 2^-frac_bits.
    pub fn lsb(&self) -> f64 {
        pow2(-(self.frac_bits as i32))
    }

    /// Each tile's header with its slice of `words`, in order.
    pub fn tile_words(&self) -> impl Iterator<Item = (&TileHeader, &[u32])> {
        self.tiles.iter().scan(0usize, move |start, header| {
            let range = *start..*start + header.words as usize;
            *start = range.end;
            Some((header, self.words.get(range).unwrap_or(&[])))
        })
    }
}

/// The most rows one tile takes, so that a tile's row count stays small for the target's
/// row bookkeeping even for a narrow band (a diagonal matrix would otherwise be one tile).
pub const MAX_TILE_ROWS: usize = 512;

/// Why a matrix cannot be encoded.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EncodeError {
    #[error("the matrix has {0} rows, more than a u32 can count")]
    TooLarge(usize),
    #[error("row {row} spans columns {first}..={last} ({} columns), wider than the {TILE_COLUMNS}-column window of one tile; \
             the band is too wide for this encoder (general tiling that splits rows is not supported yet), use a smaller grid",
            last - first + 1)]
    BandTooWide {
        row: usize,
        first: usize,
        last: usize,
    },
    #[error("the matrix values cannot be put in Q-format: {0}")]
    QFormat(#[from] QFormatError),
    #[error("internal encoder error: {0}")]
    Word(#[from] WordError),
    #[error("internal encoder error, a produced tile is invalid: {0}")]
    InvalidTile(#[from] MatrixError),
}

/// Why words do not decode to a matrix.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DecodeError {
    #[error("the tile headers cover {headers} words but there are {words}")]
    WordCount { headers: u64, words: usize },
    #[error(transparent)]
    Tile(#[from] MatrixError),
    #[error(transparent)]
    QFormat(#[from] QFormatError),
}

/// The row block of one tile: rows `start..end`, columns `first..=last` (if any nonzero).
struct RowBlock {
    start: usize,
    end: usize,
    columns: Option<(usize, usize)>,
}

/// Rows of `k` grouped greedily into blocks whose columns fit one window.
fn row_blocks(k: &Csr) -> Result<Vec<RowBlock>, EncodeError> {
    let window = TILE_COLUMNS as usize;
    let mut blocks = Vec::new();
    let mut current: Option<RowBlock> = None;
    for row in 0..k.n() {
        let cols = k.row(row).0;
        let span = cols.first().zip(cols.last()).map(|(&a, &b)| (a, b));
        if let Some((first, last)) = span {
            if last - first >= window {
                return Err(EncodeError::BandTooWide { row, first, last });
            }
        }
        let merged = |block: &RowBlock| match (block.columns, span) {
            (Some((a, b)), Some((c, d))) => Some((a.min(c), b.max(d))),
            (columns, None) | (None, columns) => columns,
        };
        match current.as_mut() {
            Some(block)
                if block.end - block.start < MAX_TILE_ROWS
                    && merged(block).is_none_or(|(a, b)| b - a < window) =>
            {
                block.columns = merged(block);
                block.end = row + 1;
            }
            _ => {
                blocks.extend(current.take());
                current = Some(RowBlock {
                    start: row,
                    end: row + 1,
                    columns: span,
                });
            }
        }
    }
    blocks.extend(current);
    Ok(blocks)
}

/// Encodes `k` as tiles of instruction words; every tile is checked with
/// [`deform_shared::matrix::validate_tile`] before it is returned.
pub fn encode(k: &Csr) -> Result<EncodedMatrix, EncodeError> {
    let n = u32::try_from(k.n()).map_err(|_| EncodeError::TooLarge(k.n()))?;
    let frac_bits = choose_frac_bits(k.max_abs())?;
    let blocks = row_blocks(k)?;
    let mut tiles = Vec::with_capacity(blocks.len());
    let mut words = Vec::with_capacity(k.nnz() + blocks.len());
    let mut row_words = Vec::new();
    for block in &blocks {
        let tile_start = words.len();
        let col_base = block.columns.map_or(0, |(first, _)| first);
        for row in block.start..block.end {
            row_words.clear();
            let (cols, vals) = k.row(row);
            for (&c, &v) in cols.iter().zip(vals) {
                let raw = quantize(v, frac_bits)?;
                if raw != 0 {
                    row_words.push(Word::new((c - col_base) as u32, raw as i64, false, false)?);
                }
            }
            match row_words.last_mut() {
                Some(last) => *last = Word(last.bits() | Word::empty_row(false).bits()),
                None => row_words.push(Word::empty_row(false)),
            }
            words.extend(row_words.iter().map(|w| w.bits()));
        }
        let last = words.last_mut().expect("every row adds a word");
        *last |= Word::empty_row(true).bits();
        let header = TileHeader {
            row_base: block.start as u32,
            col_base: col_base as u32,
            rows: (block.end - block.start) as u32,
            words: (words.len() - tile_start) as u32,
            mvu: 0,
            mirrored: false,
        };
        validate_tile(tiles.len() as u32, &header, &words[tile_start..], n)?;
        tiles.push(header);
    }
    Ok(EncodedMatrix {
        n,
        frac_bits,
        tiles,
        words,
    })
}

/// The largest |v − quantized v| over `k`'s values at `frac_bits`: what encoding loses.
pub fn max_quantization_error(k: &Csr, frac_bits: u8) -> Result<f64, QFormatError> {
    k.values().iter().try_fold(0.0f64, |worst, &v| {
        let back = dequantize(quantize(v, frac_bits)?, frac_bits)?;
        Ok(worst.max((back - v).abs()))
    })
}

/// The matrix the words stand for, as the MVU would see it: tiles are validated, each word
/// adds raw·2^-F at (row_base + row, col_base + column), and zero words (empty rows) add
/// nothing. For tests and diagnostics.
pub fn decode(encoded: &EncodedMatrix) -> Result<Csr, DecodeError> {
    let covered: u64 = encoded.tiles.iter().map(|t| t.words as u64).sum();
    if covered != encoded.words.len() as u64 {
        return Err(DecodeError::WordCount {
            headers: covered,
            words: encoded.words.len(),
        });
    }
    let n = encoded.n as usize;
    let mut rows: Vec<Vec<(usize, f64)>> = vec![Vec::new(); n];
    for (index, (header, words)) in encoded.tile_words().enumerate() {
        validate_tile(index as u32, header, words, encoded.n)?;
        let mut row = header.row_base as usize;
        for &bits in words {
            let word = Word(bits);
            if word.raw_value() != 0 {
                let value = dequantize(word.raw_value(), encoded.frac_bits)?;
                rows[row].push((header.col_base as usize + word.column() as usize, value));
            }
            row += word.end_of_row() as usize;
        }
    }
    let mut builder = CsrBuilder::new(n, encoded.words.len());
    for entries in rows {
        builder
            .push_row(entries)
            .expect("validated columns are inside the matrix");
    }
    Ok(builder.finish().expect("one row per matrix row"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::sparse::test_support::from_dense;
    use crate::model::{Axis, Connection, Grid, Model, ModelSpec};

    fn model(dims: (usize, usize, usize), connection: Connection) -> Model {
        let grid = Grid::new(dims.0, dims.1, dims.2).unwrap();
        Model::build(&ModelSpec {
            grid,
            connection,
            loads: vec![ModelSpec::default_load(grid)],
            ..ModelSpec::thesis_example()
        })
        .unwrap()
    }

    fn check_tiles(encoded: &EncodedMatrix) {
        let mut next_row = 0;
        for (index, (header, words)) in encoded.tile_words().enumerate() {
            assert_eq!(
                validate_tile(index as u32, header, words, encoded.n),
                Ok(())
            );
            assert_eq!(header.row_base, next_row, "tiles are contiguous row blocks");
            next_row += header.rows;
        }
        assert_eq!(next_row, encoded.n);
        assert_eq!(
            encoded
                .tiles
                .iter()
                .map(|t| t.words as usize)
                .sum::<usize>(),
            encoded.words.len()
        );
    }

    #[test]
    fn unit_matrices_round_trip_exactly() {
        for connection in [Connection::Axial, Connection::AxialShear] {
            for dims in [(2, 2, 2), (3, 4, 5), (10, 10, 10)] {
                let a = model(dims, connection).unit_matrix().clone();
                let encoded = encode(&a).unwrap();
                check_tiles(&encoded);
                assert_eq!(decode(&encoded).unwrap(), a, "{dims:?} {connection}");
                assert_eq!(max_quantization_error(&a, encoded.frac_bits), Ok(0.0));
                assert_eq!(encoded.words.len(), a.nnz(), "no row of A is empty");
            }
        }
    }

    #[test]
    fn thesis_example_tiles() {
        let a = model((10, 10, 10), Connection::Axial).unit_matrix().clone();
        let encoded = encode(&a).unwrap();
        assert_eq!(encoded.frac_bits, 17, "max |A| = 6");
        // Rows span ±100 columns, so a 512-column window holds about 300 rows: n = 1000 needs 3.
        assert_eq!(encoded.tiles.len(), 3);
        let b = model((10, 10, 10), Connection::AxialShear)
            .unit_matrix()
            .clone();
        assert_eq!(encode(&b).unwrap().frac_bits, 15, "max |A| = 26");
    }

    #[test]
    fn non_integer_values_round_within_half_an_lsb() {
        let model = model((5, 4, 3), Connection::AxialShear);
        let k = model.stiffness_matrix(Axis::X).scaled(0.1234567);
        let encoded = encode(&k).unwrap();
        check_tiles(&encoded);
        let decoded = decode(&encoded).unwrap();
        let half_lsb = encoded.lsb() / 2.0;
        let error = max_quantization_error(&k, encoded.frac_bits).unwrap();
        assert!(error > 0.0 && error <= half_lsb);
        for (r, c, v) in k.entries() {
            assert!((decoded.get(r, c) - v).abs() <= half_lsb, "({r},{c})");
        }
        for (r, c, v) in decoded.entries() {
            assert!((k.get(r, c) - v).abs() <= half_lsb, "({r},{c})");
        }
    }

    #[test]
    fn empty_rows_and_tiny_values_become_empty_row_words() {
        let k = from_dense(&[
            vec![2.0, 0.0, 0.0],
            vec![0.0, 0.0, 0.0],
            vec![1e-9, 0.0, 1.0],
        ]);
        let encoded = encode(&k).unwrap();
        check_tiles(&encoded);
        assert_eq!(encoded.tiles.len(), 1);
        assert_eq!(
            encoded.words.len(),
            3,
            "one word per stored row, one for the empty row"
        );
        assert_eq!(encoded.words[1], Word::empty_row(false).bits());
        let last = Word(*encoded.words.last().unwrap());
        assert!(last.end_of_matrix() && last.end_of_row());
        let decoded = decode(&encoded).unwrap();
        assert_eq!(decoded.get(2, 0), 0.0, "1e-9 is below half an LSB");
        assert_eq!(decoded.get(0, 0), 2.0);
        assert_eq!(decoded.nnz(), 2);
    }

    #[test]
    fn word_fields_are_row_major_with_relative_columns() {
        // A 600-row tridiagonal matrix: row 511 reaches column 512, one past the first window.
        let n = 600;
        let mut builder = CsrBuilder::new(n, 3 * n);
        for r in 0..n {
            let entries = [(r.wrapping_sub(1), -1.0), (r, 2.0), (r + 1, -1.0)];
            builder
                .push_row(entries.into_iter().filter(|&(c, _)| c < n))
                .unwrap();
        }
        let k = builder.finish().unwrap();
        let encoded = encode(&k).unwrap();
        check_tiles(&encoded);
        assert_eq!(encoded.frac_bits, 18);
        assert_eq!(
            encoded.tiles,
            vec![
                TileHeader {
                    row_base: 0,
                    col_base: 0,
                    rows: 511,
                    words: 3 * 511 - 1,
                    mvu: 0,
                    mirrored: false,
                },
                TileHeader {
                    row_base: 511,
                    col_base: 510,
                    rows: 89,
                    words: 3 * 89 - 1,
                    mvu: 0,
                    mirrored: false,
                },
            ]
        );
        let (_, words) = encoded.tile_words().nth(1).unwrap();
        let fields = |bits: u32| {
            let w = Word(bits);
            (w.column(), w.raw_value(), w.end_of_row(), w.end_of_matrix())
        };
        let one = 1 << 18;
        assert_eq!(fields(words[0]), (0, -one, false, false));
        assert_eq!(fields(words[1]), (1, 2 * one, false, false));
        assert_eq!(fields(words[2]), (2, -one, true, false));
        assert_eq!(fields(words[3]), (1, -one, false, false));
        assert_eq!(fields(*words.last().unwrap()), (89, 2 * one, true, true));
        assert_eq!(decode(&encoded).unwrap(), k);
    }

    #[test]
    fn tiles_have_at_most_512_rows() {
        let n = 600;
        let mut builder = CsrBuilder::new(n, n);
        for r in 0..n {
            builder.push_row([(r, 1.0)]).unwrap();
        }
        let k = builder.finish().unwrap();
        let encoded = encode(&k).unwrap();
        check_tiles(&encoded);
        let rows: Vec<u32> = encoded.tiles.iter().map(|t| t.rows).collect();
        assert_eq!(rows, vec![512, 88]);
        assert_eq!(decode(&encoded).unwrap(), k);
    }

    #[test]
    fn wide_band_is_refused() {
        let wide = model((16, 16, 16), Connection::AxialShear)
            .unit_matrix()
            .clone();
        assert_eq!(wide.bandwidth(), 273);
        let err = encode(&wide).unwrap_err();
        assert!(matches!(err, EncodeError::BandTooWide { .. }));
        let message = err.to_string();
        assert!(
            message.contains("512") && message.contains("not supported yet"),
            "{message}"
        );
    }

    #[test]
    fn values_too_large_for_the_field_are_refused() {
        let k = from_dense(&[vec![2e6]]);
        assert!(matches!(encode(&k), Err(EncodeError::QFormat(_))));
    }

    #[test]
    fn decode_refuses_broken_streams() {
        let a = model((3, 3, 3), Connection::Axial).unit_matrix().clone();
        let mut encoded = encode(&a).unwrap();
        encoded.words.pop();
        assert!(matches!(
            decode(&encoded),
            Err(DecodeError::WordCount { .. })
        ));
        let mut encoded = encode(&a).unwrap();
        encoded.tiles[0].rows += 1;
        assert!(matches!(decode(&encoded), Err(DecodeError::Tile(_))));
    }
}
