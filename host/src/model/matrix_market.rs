//! Matrix Market export, so that K can be checked in MATLAB/Octave (`mmread`) or SciPy
//! (`scipy.io.mmread`) against the thesis's figures.
//!
//! The `general` (not `symmetric`) form lists every stored entry, both triangles, so that the
//! file is exactly what the target multiplies with and asymmetry would be visible.

use std::io::{self, Write};

use super::sparse::Csr;

/// Writes `k` as a 1-based `%%MatrixMarket matrix coordinate real general` file. Values use
/// Rust's shortest round-trip notation, so reading the file back gives the same `f64`s.
pub fn write_matrix_market(k: &Csr, comment: &str, mut out: impl Write) -> io::Result<()> {
    writeln!(out, "%%MatrixMarket matrix coordinate real general")?;
    for line in comment.lines() {
        writeln!(out, "% {line}")?;
    }
    writeln!(out, "{} {} {}", k.n(), k.n(), k.nnz())?;
    for (r, c, v) in k.entries() {
        writeln!(out, "{} {} {v:e}", r + 1, c + 1)?;
    }
    out.flush()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::sparse::test_support::from_dense;

    #[test]
    fn writes_a_full_one_based_coordinate_file() {
        let k = from_dense(&[vec![2.0, -0.5], vec![-0.5, 1e-20]]);
        let mut out = Vec::new();
        write_matrix_market(&k, "K_x\nsecond line", &mut out).unwrap();
        let text = String::from_utf8(out).unwrap();
        assert_eq!(
            text,
            "%%MatrixMarket matrix coordinate real general\n% K_x\n% second line\n2 2 4\n\
             1 1 2e0\n1 2 -5e-1\n2 1 -5e-1\n2 2 1e-20\n"
        );
        for line in text.lines().skip(4) {
            let value: f64 = line.split(' ').nth(2).unwrap().parse().unwrap();
            assert!(value != 0.0);
        }
    }
}
