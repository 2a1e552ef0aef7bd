//! Small SPD systems with exact reference solutions, for the link's end-to-end unit tests.

use deform_shared::qformat::choose_frac_bits;
use deform_target_core::testkit::{banded_row, encode_rows};

use crate::encode::EncodedMatrix;

/// Rows per tile: a tile's rows `r` touch columns `r-1 ..= r+1`, well inside one 512-column
/// window, and a small tile height makes even modest n span several tiles.
const TILE_ROWS: usize = 100;

/// The 1-D Laplacian tridiag(-1, 2, -1) of order `n` (Dirichlet ends, so SPD).
pub fn laplacian_1d(n: u32) -> EncodedMatrix {
    let frac_bits = choose_frac_bits(2.0).unwrap();
    let n = n as usize;
    let s = encode_rows(n, n, TILE_ROWS, frac_bits, banded_row(n, 1));
    EncodedMatrix {
        n: s.n,
        frac_bits,
        tiles: s.tiles,
        words: s.words,
    }
}

/// Solves tridiag(-1, 2, -1) x = b exactly in f64 (Thomas algorithm).
pub fn laplacian_1d_solve(b: &[f64]) -> Vec<f64> {
    let n = b.len();
    // Forward sweep with sub- and super-diagonal -1: c'ᵢ = -1 / (2 + c'ᵢ₋₁),
    // d'ᵢ = (bᵢ + d'ᵢ₋₁) / (2 + c'ᵢ₋₁).
    let mut c = vec![0.0; n];
    let mut d = vec![0.0; n];
    for i in 0..n {
        let (c_prev, d_prev) = if i > 0 {
            (c[i - 1], d[i - 1])
        } else {
            (0.0, 0.0)
        };
        let denom = 2.0 + c_prev;
        c[i] = -1.0 / denom;
        d[i] = (b[i] + d_prev) / denom;
    }
    let mut x = vec![0.0; n];
    for i in (0..n).rev() {
        x[i] = d[i] - if i + 1 < n { c[i] * x[i + 1] } else { 0.0 };
    }
    x
}

/// max |got - want| / max |want|.
pub fn max_relative_error(got: &[f64], want: &[f64]) -> f64 {
    assert_eq!(got.len(), want.len());
    crate::reference::max_abs_diff(got, want) / crate::reference::max_abs(want)
}
