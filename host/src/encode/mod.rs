//! K as MVU instruction words: Q-format, conjugate symmetry, partitioning over the MVUs and
//! tiling into 512-column windows (thesis 4.1, 4.2.1).
//!
//! The pipeline, each step its own submodule:
//!
//! 1. **Q-format** ([`QuantizedMatrix`]): one fractional-bit count F serves the whole matrix, the
//!    largest with which the largest |value| still fits the 21-bit field
//!    ([`deform_shared::qformat::choose_frac_bits`]); every value is rounded to the nearest
//!    multiple of 2^-F. An integer matrix such as A is therefore exact, and any other value is
//!    off by at most half an LSB. A value that rounds to 0 is not stored at all.
//! 2. **Conjugate symmetry** ([`persymmetry`], thesis 2.5 vi): when the *quantised* matrix is
//!    persymmetric, K_ij = K_{n−1−i,n−1−j} exactly, only the rows i < n/2 are stored, as
//!    mirrored tiles (each word also serves row n−1−i against p[n−1−j]), and for odd n the middle
//!    row as a plain tile. That halves the matrix memory and the upload.
//! 3. **Partitioning** ([`partition`], thesis 4.1.1/4.1.2): the stored rows are shared out
//!    over the MVUs, either as disjoint row blocks balanced by nonzero count and rows or as an
//!    exact equal split of the nonzero stream whose boundary rows overlap (their partial sums
//!    add).
//! 4. **Tiling** ([`tiling`]): each MVU's rows are cut into tiles whose column window is at
//!    most 512 wide, splitting a row over several tiles where its columns span more than one
//!    window (tiles accumulate `y[row] +=`), so any bandwidth encodes.

pub mod partition;
pub mod persymmetry;
pub mod report;
pub mod tiling;

use deform_shared::matrix::{validate_tile, MatrixError, TileHeader};
use deform_shared::qformat::{choose_frac_bits, dequantize, pow2, quantize, QFormatError};
use deform_shared::word::{Word, WordError};
use serde::Serialize;

use crate::model::sparse::{Csr, CsrBuilder};
pub use partition::Partition;

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

/// How to lay the matrix out.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EncodeOptions {
    /// MVUs (harts) to share the matrix between, at least 1. Fewer are used when there are
    /// fewer stored rows (rows partition) or nonzeros (overlap partition) than MVUs.
    pub mvus: u8,
    pub partition: Partition,
    /// Store only half of a persymmetric matrix (when it is one).
    pub use_symmetry: bool,
}

impl Default for EncodeOptions {
    /// One MVU, disjoint row blocks, the whole matrix: the plainest layout.
    fn default() -> Self {
        EncodeOptions {
            mvus: 1,
            partition: Partition::Rows,
            use_symmetry: false,
        }
    }
}

/// What the layout cost and which features it used: the figures `deform solve` prints.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EncodingSummary {
    /// Nonzeros of the quantised matrix (what a plain CSR would hold).
    pub nonzeros: usize,
    /// Nonzero words stored (half of `nonzeros`, roughly, with conjugate symmetry).
    pub stored_nonzeros: usize,
    /// Zero words that only end an empty tile row (overhead of the tiling).
    pub empty_row_words: usize,
    pub words: usize,
    pub tiles: usize,
    /// The quantised matrix is persymmetric.
    pub persymmetric: bool,
    /// Only half of it is stored (mirrored tiles).
    pub symmetry_used: bool,
    pub partition: Partition,
    /// MVUs the tiles are assigned to (max `mvu` + 1).
    pub mvus: u8,
    /// Words each MVU executes per product, by MVU.
    pub words_per_mvu: Vec<usize>,
    /// Multiply–accumulates each MVU performs per product, by MVU (a mirrored word counts 2).
    pub products_per_mvu: Vec<usize>,
}

impl EncodingSummary {
    /// Tiling overhead: empty-row words as a fraction of the stored nonzeros.
    pub fn overhead(&self) -> f64 {
        self.empty_row_words as f64 / self.stored_nonzeros.max(1) as f64
    }
}

/// An encoded matrix with its summary.
#[derive(Debug, Clone, PartialEq)]
pub struct Encoding {
    pub matrix: EncodedMatrix,
    pub summary: EncodingSummary,
}

/// Why a matrix cannot be encoded.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EncodeError {
    #[error("the matrix has {0} rows, more than a u32 can count")]
    TooLarge(usize),
    #[error("--mvus must be at least 1")]
    NoMvus,
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
    #[error("mirrored tile {tile} reaches row {row}, whose mirror row {mirror} is not a different row of the lower half")]
    MirrorOverlap {
        tile: usize,
        row: usize,
        mirror: usize,
    },
}

/// A matrix in the target's number format: each row's nonzeros as (column, raw 21-bit value),
/// raw · 2^-frac_bits being the value. Values that round to 0 are dropped.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct QuantizedMatrix {
    pub n: usize,
    pub frac_bits: u8,
    row_ptr: Vec<usize>,
    cols: Vec<u32>,
    raws: Vec<i32>,
}

impl QuantizedMatrix {
    /// Quantises `k` at the largest F its largest |value| allows.
    pub fn from_csr(k: &Csr) -> Result<Self, EncodeError> {
        u32::try_from(k.n()).map_err(|_| EncodeError::TooLarge(k.n()))?;
        let frac_bits = choose_frac_bits(k.max_abs())?;
        let mut row_ptr = Vec::with_capacity(k.n() + 1);
        let mut cols = Vec::with_capacity(k.nnz());
        let mut raws = Vec::with_capacity(k.nnz());
        row_ptr.push(0);
        for row in 0..k.n() {
            let (c, v) = k.row(row);
            for (&c, &v) in c.iter().zip(v) {
                let raw = quantize(v, frac_bits)?;
                if raw != 0 {
                    cols.push(c as u32);
                    raws.push(raw);
                }
            }
            row_ptr.push(cols.len());
        }
        Ok(QuantizedMatrix {
            n: k.n(),
            frac_bits,
            row_ptr,
            cols,
            raws,
        })
    }

    pub fn nnz(&self) -> usize {
        self.cols.len()
    }

    /// Positions of row `row`'s entries in [`Self::entry`] numbering.
    pub fn row_range(&self, row: usize) -> std::ops::Range<usize> {
        self.row_ptr[row]..self.row_ptr[row + 1]
    }

    /// Entry `index`: (column, raw value).
    pub fn entry(&self, index: usize) -> (u32, i32) {
        (self.cols[index], self.raws[index])
    }

    /// Row `row` as (columns, raw values), columns ascending.
    pub fn row(&self, row: usize) -> (&[u32], &[i32]) {
        let range = self.row_range(row);
        (&self.cols[range.clone()], &self.raws[range])
    }

    /// y = Q·p in exact integer arithmetic (raw values times `p`), the yardstick for the
    /// tiles' product.
    pub fn mul_exact(&self, p: &[i64]) -> Vec<i128> {
        (0..self.n)
            .map(|row| {
                let (c, v) = self.row(row);
                c.iter()
                    .zip(v)
                    .map(|(&c, &v)| v as i128 * p[c as usize] as i128)
                    .sum()
            })
            .collect()
    }
}

/// Encodes `k` in the plainest layout ([`EncodeOptions::default`]): one MVU, the whole matrix.
pub fn encode(k: &Csr) -> Result<EncodedMatrix, EncodeError> {
    Ok(encode_with(k, &EncodeOptions::default())?.matrix)
}

/// Encodes `k` as `options` say; every tile is checked with
/// [`deform_shared::matrix::validate_tile`] before it is returned.
pub fn encode_with(k: &Csr, options: &EncodeOptions) -> Result<Encoding, EncodeError> {
    if options.mvus == 0 {
        return Err(EncodeError::NoMvus);
    }
    let q = QuantizedMatrix::from_csr(k)?;
    let n = q.n as u32;
    let persymmetric = persymmetry::is_persymmetric(&q);
    let symmetry_used = options.use_symmetry && persymmetric && q.n >= 2;
    // The rows stored: all, or the lower half mirrored plus (odd n) the middle row plain.
    let (mirrored_rows, plain_rows) = if symmetry_used {
        (0..q.n / 2, q.n / 2..q.n.div_ceil(2))
    } else {
        (0..0, 0..q.n)
    };
    let stored_rows = if symmetry_used {
        0..q.n.div_ceil(2)
    } else {
        0..q.n
    };
    let shares = partition::partition(
        &q,
        stored_rows,
        mirrored_rows.clone(),
        options.partition,
        options.mvus,
    );
    let mut sink = tiling::TileSink::new(n);
    for (mvu, pieces) in shares.iter().enumerate() {
        let mvu = mvu as u8;
        let (mirrored, plain): (Vec<_>, Vec<_>) = pieces
            .iter()
            .cloned()
            .partition(|piece| mirrored_rows.contains(&(piece.row as usize)));
        debug_assert!(plain.iter().all(|p| plain_rows.contains(&(p.row as usize))));
        tiling::tile(&q, &mirrored, mvu, true, &mut sink)?;
        tiling::tile(&q, &plain, mvu, false, &mut sink)?;
    }
    let tiling::TileSink {
        tiles,
        words,
        empty_row_words,
        ..
    } = sink;
    let matrix = EncodedMatrix {
        n,
        frac_bits: q.frac_bits,
        tiles,
        words,
    };
    for (index, (header, words)) in matrix.tile_words().enumerate() {
        validate_tile(index as u32, header, words, n)?;
    }
    let mvus = matrix
        .tiles
        .iter()
        .map(|t| t.mvu)
        .max()
        .map_or(0, |m| m + 1);
    let mut words_per_mvu = vec![0; mvus as usize];
    let mut products_per_mvu = vec![0; mvus as usize];
    for (header, tile_words) in matrix.tile_words() {
        let nonzero = tile_words
            .iter()
            .filter(|&&w| Word(w).raw_value() != 0)
            .count();
        words_per_mvu[header.mvu as usize] += header.words as usize;
        products_per_mvu[header.mvu as usize] += nonzero * if header.mirrored { 2 } else { 1 };
    }
    let summary = EncodingSummary {
        nonzeros: q.nnz(),
        stored_nonzeros: matrix.words.len() - empty_row_words,
        empty_row_words,
        words: matrix.words.len(),
        tiles: matrix.tiles.len(),
        persymmetric,
        symmetry_used,
        partition: options.partition,
        mvus,
        words_per_mvu,
        products_per_mvu,
    };
    Ok(Encoding { matrix, summary })
}

/// The largest |v − quantized v| over `k`'s values at `frac_bits`: what encoding loses.
pub fn max_quantization_error(k: &Csr, frac_bits: u8) -> Result<f64, QFormatError> {
    k.values().iter().try_fold(0.0f64, |worst, &v| {
        let back = dequantize(quantize(v, frac_bits)?, frac_bits)?;
        Ok(worst.max((back - v).abs()))
    })
}

/// Calls `visit(row, column, raw)` for every multiply–accumulate the MVUs perform, mirrored
/// words twice (as (i, j) and (n−1−i, n−1−j)), after validating every tile.
fn for_each_product(
    encoded: &EncodedMatrix,
    mut visit: impl FnMut(usize, usize, i32),
) -> Result<(), DecodeError> {
    let covered: u64 = encoded.tiles.iter().map(|t| t.words as u64).sum();
    if covered != encoded.words.len() as u64 {
        return Err(DecodeError::WordCount {
            headers: covered,
            words: encoded.words.len(),
        });
    }
    let n = encoded.n as usize;
    for (index, (header, words)) in encoded.tile_words().enumerate() {
        validate_tile(index as u32, header, words, encoded.n)?;
        if header.mirrored {
            let last = (header.row_base + header.rows - 1) as usize;
            if 2 * last + 1 >= n {
                return Err(DecodeError::MirrorOverlap {
                    tile: index,
                    row: last,
                    mirror: n - 1 - last,
                });
            }
        }
        let mut row = header.row_base as usize;
        for &bits in words {
            let word = Word(bits);
            let raw = word.raw_value();
            if raw != 0 {
                let column = header.col_base as usize + word.column() as usize;
                visit(row, column, raw);
                if header.mirrored {
                    visit(n - 1 - row, n - 1 - column, raw);
                }
            }
            row += word.end_of_row() as usize;
        }
    }
    Ok(())
}

/// The matrix the words stand for, as the MVUs would see it: every word adds raw·2^-F at
/// (row_base + row, col_base + column), a mirrored one also at the mirror position, partial
/// rows of several tiles add up, and zero words (empty rows) add nothing. For tests and
/// diagnostics.
pub fn decode(encoded: &EncodedMatrix) -> Result<Csr, DecodeError> {
    let n = encoded.n as usize;
    let mut rows: Vec<Vec<(usize, i64)>> = vec![Vec::new(); n];
    for_each_product(encoded, |row, column, raw| {
        rows[row].push((column, raw as i64))
    })?;
    let mut builder = CsrBuilder::new(n, encoded.words.len());
    for mut entries in rows {
        // Sum the partial entries exactly in integers before converting.
        entries.sort_unstable_by_key(|&(c, _)| c);
        let mut merged: Vec<(usize, i64)> = Vec::with_capacity(entries.len());
        for (c, v) in entries {
            match merged.last_mut() {
                Some((last, sum)) if *last == c => *sum += v,
                _ => merged.push((c, v)),
            }
        }
        let mut converted = Vec::with_capacity(merged.len());
        for (c, v) in merged.into_iter().filter(|&(_, v)| v != 0) {
            converted.push((c, v as f64 * encoded.lsb()));
        }
        builder
            .push_row(converted)
            .expect("validated columns are inside the matrix");
    }
    Ok(builder.finish().expect("one row per matrix row"))
}

/// y = K·p exactly as the MVUs compute it, over raw values and integer `p`: the tiles'
/// product, to compare with [`QuantizedMatrix::mul_exact`].
pub fn tiles_mul_exact(encoded: &EncodedMatrix, p: &[i64]) -> Result<Vec<i128>, DecodeError> {
    let mut y = vec![0i128; encoded.n as usize];
    for_each_product(encoded, |row, column, raw| {
        y[row] += raw as i128 * p[column] as i128
    })?;
    Ok(y)
}

#[cfg(test)]
mod tests;
