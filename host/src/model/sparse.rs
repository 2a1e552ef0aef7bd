//! Compressed sparse row storage for K.
//!
//! K has at most 7 (model A) or 27 (model B) nonzeros per row whatever n is (thesis 2.5), so
//! everything here is linear in the number of nonzeros; nothing ever forms the dense n×n
//! matrix. Columns within a row are kept sorted and unique, which is what lets the encoder
//! stream a row's words in column order and lets [`Csr::get`] binary-search.

/// Why CSR parts are inconsistent.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CsrError {
    #[error("row_ptr has {found} entries, a {n}-row matrix needs {}", n + 1)]
    RowPtrLength { n: usize, found: usize },
    #[error("row_ptr must start at 0, end at nnz = {nnz} and never decrease")]
    RowPtrNotMonotone { nnz: usize },
    #[error("col has {col} entries but val has {val}")]
    LengthMismatch { col: usize, val: usize },
    #[error("row {row} has column {column}, beyond the dimension {n}")]
    ColumnOutOfRange { row: usize, column: usize, n: usize },
    #[error("row {row}'s columns are not strictly increasing")]
    ColumnsNotSorted { row: usize },
    #[error("the builder got {rows} rows for a {n}-row matrix")]
    RowCount { n: usize, rows: usize },
}

/// A square sparse matrix in CSR form: row `r`'s nonzeros are `col[row_ptr[r]..row_ptr[r+1]]`
/// with values `val[..]` at the same positions, columns strictly increasing.
#[derive(Debug, Clone, PartialEq)]
pub struct Csr {
    n: usize,
    row_ptr: Vec<usize>,
    col: Vec<usize>,
    val: Vec<f64>,
}

impl Csr {
    /// Checks and wraps raw CSR arrays.
    pub fn from_parts(
        n: usize,
        row_ptr: Vec<usize>,
        col: Vec<usize>,
        val: Vec<f64>,
    ) -> Result<Self, CsrError> {
        if row_ptr.len() != n + 1 {
            return Err(CsrError::RowPtrLength {
                n,
                found: row_ptr.len(),
            });
        }
        if col.len() != val.len() {
            return Err(CsrError::LengthMismatch {
                col: col.len(),
                val: val.len(),
            });
        }
        let nnz = col.len();
        if row_ptr[0] != 0 || row_ptr[n] != nnz || row_ptr.windows(2).any(|w| w[0] > w[1]) {
            return Err(CsrError::RowPtrNotMonotone { nnz });
        }
        for row in 0..n {
            let cols = &col[row_ptr[row]..row_ptr[row + 1]];
            if let Some(&column) = cols.iter().find(|&&c| c >= n) {
                return Err(CsrError::ColumnOutOfRange { row, column, n });
            }
            if cols.windows(2).any(|w| w[0] >= w[1]) {
                return Err(CsrError::ColumnsNotSorted { row });
            }
        }
        Ok(Self {
            n,
            row_ptr,
            col,
            val,
        })
    }

    /// diag(d) + Σ c·A over `terms`, all of order d.len(): the union of the patterns, entries
    /// at equal positions summed (the dynamic system S = M + c₁·B + c₂·K of [`crate::dynamics`]).
    pub fn combine(diagonal: &[f64], terms: &[(f64, &Csr)]) -> Csr {
        let n = diagonal.len();
        assert!(terms.iter().all(|(_, a)| a.n == n), "terms of order {n}");
        let nnz = terms.iter().map(|(_, a)| a.nnz()).max().unwrap_or(0) + n;
        let mut builder = CsrBuilder::new(n, nnz);
        for (r, &d) in diagonal.iter().enumerate() {
            let off = terms.iter().flat_map(|&(c, a)| {
                let (cols, vals) = a.row(r);
                cols.iter().zip(vals).map(move |(&j, &v)| (j, c * v))
            });
            builder
                .push_row(std::iter::once((r, d)).chain(off))
                .expect("columns come from matrices of order n");
        }
        builder.finish().expect("one row per diagonal entry")
    }

    /// The order n (rows = columns).
    pub fn n(&self) -> usize {
        self.n
    }

    /// Stored nonzeros.
    pub fn nnz(&self) -> usize {
        self.col.len()
    }

    pub fn row_ptr(&self) -> &[usize] {
        &self.row_ptr
    }

    pub fn col_indices(&self) -> &[usize] {
        &self.col
    }

    pub fn values(&self) -> &[f64] {
        &self.val
    }

    /// Row `row`'s columns and values.
    pub fn row(&self, row: usize) -> (&[usize], &[f64]) {
        let range = self.row_ptr[row]..self.row_ptr[row + 1];
        (&self.col[range.clone()], &self.val[range])
    }

    /// Every stored entry as `(row, column, value)`, row by row.
    pub fn entries(&self) -> impl Iterator<Item = (usize, usize, f64)> + '_ {
        (0..self.n).flat_map(move |r| {
            let (cols, vals) = self.row(r);
            cols.iter().zip(vals).map(move |(&c, &v)| (r, c, v))
        })
    }

    /// The value at `(row, column)`, 0 where nothing is stored.
    pub fn get(&self, row: usize, column: usize) -> f64 {
        let (cols, vals) = self.row(row);
        cols.binary_search(&column).map_or(0.0, |p| vals[p])
    }

    /// y = K·x. Panics if the lengths are not n: a caller bug, not a data error.
    pub fn mul_vec_into(&self, x: &[f64], y: &mut [f64]) {
        assert_eq!(x.len(), self.n, "x has the wrong length");
        assert_eq!(y.len(), self.n, "y has the wrong length");
        for (r, y_r) in y.iter_mut().enumerate() {
            let (cols, vals) = self.row(r);
            *y_r = cols.iter().zip(vals).map(|(&c, &v)| v * x[c]).sum();
        }
    }

    /// K·x as a new vector.
    pub fn mul_vec(&self, x: &[f64]) -> Vec<f64> {
        let mut y = vec![0.0; self.n];
        self.mul_vec_into(x, &mut y);
        y
    }

    /// The diagonal (0 where nothing is stored).
    pub fn diagonal(&self) -> Vec<f64> {
        (0..self.n).map(|r| self.get(r, r)).collect()
    }

    /// s·K, same sparsity.
    pub fn scaled(&self, s: f64) -> Csr {
        Csr {
            val: self.val.iter().map(|v| v * s).collect(),
            ..self.clone()
        }
    }

    /// Whether K equals its transpose exactly, value for value (an entry stored on one side
    /// only counts as asymmetric unless it is 0).
    pub fn is_symmetric(&self) -> bool {
        self.entries().all(|(r, c, v)| self.get(c, r) == v)
    }

    /// Half-bandwidth: the largest |i − j| over stored entries (0 for a diagonal matrix).
    pub fn bandwidth(&self) -> usize {
        self.entries()
            .map(|(r, c, _)| r.abs_diff(c))
            .max()
            .unwrap_or(0)
    }

    /// The most nonzeros in any row.
    pub fn max_row_nnz(&self) -> usize {
        self.row_ptr
            .windows(2)
            .map(|w| w[1] - w[0])
            .max()
            .unwrap_or(0)
    }

    /// The largest |value| (0 for an empty matrix).
    pub fn max_abs(&self) -> f64 {
        self.val.iter().fold(0.0, |m, v| m.max(v.abs()))
    }

    /// The fraction of zero entries, 1 − nnz/n² (thesis eq. 37, first line).
    pub fn sparsity(&self) -> f64 {
        if self.n == 0 {
            return 1.0;
        }
        1.0 - self.nnz() as f64 / (self.n as f64 * self.n as f64)
    }

    /// The thesis's estimate of sparsity, 1 − (max nonzeros per row)/n (eq. 37, last line). It
    /// slightly underestimates, because boundary rows have fewer neighbours.
    pub fn sparsity_estimate(&self) -> f64 {
        if self.n == 0 {
            return 1.0;
        }
        1.0 - self.max_row_nnz() as f64 / self.n as f64
    }
}

/// Builds a [`Csr`] row by row from unsorted entries; duplicate columns in a row add up.
#[derive(Debug, Clone)]
pub struct CsrBuilder {
    n: usize,
    row_ptr: Vec<usize>,
    col: Vec<usize>,
    val: Vec<f64>,
    scratch: Vec<(usize, f64)>,
}

impl CsrBuilder {
    /// A builder for an n×n matrix expecting about `nnz_hint` nonzeros.
    pub fn new(n: usize, nnz_hint: usize) -> Self {
        let mut row_ptr = Vec::with_capacity(n + 1);
        row_ptr.push(0);
        Self {
            n,
            row_ptr,
            col: Vec::with_capacity(nnz_hint),
            val: Vec::with_capacity(nnz_hint),
            scratch: Vec::new(),
        }
    }

    /// Appends the next row. Entries may come in any order; equal columns are summed.
    pub fn push_row(
        &mut self,
        entries: impl IntoIterator<Item = (usize, f64)>,
    ) -> Result<(), CsrError> {
        let row = self.row_ptr.len() - 1;
        if row >= self.n {
            return Err(CsrError::RowCount {
                n: self.n,
                rows: row + 1,
            });
        }
        self.scratch.clear();
        self.scratch.extend(entries);
        if let Some(&(column, _)) = self.scratch.iter().find(|(c, _)| *c >= self.n) {
            return Err(CsrError::ColumnOutOfRange {
                row,
                column,
                n: self.n,
            });
        }
        self.scratch.sort_unstable_by_key(|&(c, _)| c);
        for &(c, v) in &self.scratch {
            match self.col.last() {
                Some(&last) if last == c && self.col.len() > self.row_ptr[row] => {
                    *self.val.last_mut().expect("val grows with col") += v;
                }
                _ => {
                    self.col.push(c);
                    self.val.push(v);
                }
            }
        }
        self.row_ptr.push(self.col.len());
        Ok(())
    }

    /// The finished matrix; every one of the n rows must have been pushed.
    pub fn finish(self) -> Result<Csr, CsrError> {
        let rows = self.row_ptr.len() - 1;
        if rows != self.n {
            return Err(CsrError::RowCount { n: self.n, rows });
        }
        Ok(Csr {
            n: self.n,
            row_ptr: self.row_ptr,
            col: self.col,
            val: self.val,
        })
    }
}

#[cfg(test)]
pub(crate) mod test_support {
    use super::Csr;

    /// The dense form, for comparing small matrices in tests only.
    pub fn to_dense(k: &Csr) -> Vec<Vec<f64>> {
        let mut dense = vec![vec![0.0; k.n()]; k.n()];
        for (r, c, v) in k.entries() {
            dense[r][c] = v;
        }
        dense
    }

    /// A CSR matrix from a dense one, dropping zeros.
    pub fn from_dense(dense: &[Vec<f64>]) -> Csr {
        let n = dense.len();
        let mut builder = super::CsrBuilder::new(n, 0);
        for row in dense {
            builder
                .push_row(row.iter().copied().enumerate().filter(|&(_, v)| v != 0.0))
                .unwrap();
        }
        builder.finish().unwrap()
    }

    /// Solves the dense system by Gaussian elimination with partial pivoting.
    pub fn dense_solve(k: &Csr, b: &[f64]) -> Vec<f64> {
        let n = k.n();
        let mut a = to_dense(k);
        let mut x = b.to_vec();
        for col in 0..n {
            let pivot = (col..n)
                .max_by(|&p, &q| a[p][col].abs().total_cmp(&a[q][col].abs()))
                .unwrap();
            a.swap(col, pivot);
            x.swap(col, pivot);
            let (upper, lower) = a.split_at_mut(col + 1);
            let pivot_row = &upper[col];
            for (offset, row) in lower.iter_mut().enumerate() {
                let factor = row[col] / pivot_row[col];
                if factor != 0.0 {
                    for (entry, &p) in row[col..].iter_mut().zip(&pivot_row[col..]) {
                        *entry -= factor * p;
                    }
                    x[col + 1 + offset] -= factor * x[col];
                }
            }
        }
        for r in (0..n).rev() {
            let tail: f64 = (r + 1..n).map(|c| a[r][c] * x[c]).sum();
            x[r] = (x[r] - tail) / a[r][r];
        }
        x
    }
}

#[cfg(test)]
mod tests {
    use super::test_support::*;
    use super::*;

    fn sample() -> Csr {
        from_dense(&[
            vec![4.0, -1.0, 0.0],
            vec![-1.0, 4.0, -2.0],
            vec![0.0, -2.0, 4.0],
        ])
    }

    #[test]
    fn builder_sorts_and_merges() {
        let mut b = CsrBuilder::new(2, 4);
        b.push_row([(1, 2.0), (0, 1.0), (1, 3.0)]).unwrap();
        b.push_row([]).unwrap();
        let k = b.finish().unwrap();
        assert_eq!(k.row_ptr(), &[0, 2, 2]);
        assert_eq!(k.col_indices(), &[0, 1]);
        assert_eq!(k.values(), &[1.0, 5.0]);
    }

    #[test]
    fn builder_merges_only_within_a_row() {
        let mut b = CsrBuilder::new(2, 4);
        b.push_row([(1, 1.0)]).unwrap();
        b.push_row([(1, 1.0)]).unwrap();
        let k = b.finish().unwrap();
        assert_eq!(k.nnz(), 2);
    }

    #[test]
    fn builder_checks_rows_and_columns() {
        let mut b = CsrBuilder::new(1, 1);
        assert!(matches!(
            b.push_row([(1, 1.0)]),
            Err(CsrError::ColumnOutOfRange { .. })
        ));
        assert!(matches!(
            CsrBuilder::new(2, 0).finish(),
            Err(CsrError::RowCount { n: 2, rows: 0 })
        ));
        let mut b = CsrBuilder::new(1, 1);
        b.push_row([]).unwrap();
        assert!(b.push_row([]).is_err());
    }

    #[test]
    fn from_parts_checks_invariants() {
        assert!(Csr::from_parts(2, vec![0, 1, 2], vec![0, 1], vec![1.0, 1.0]).is_ok());
        assert!(matches!(
            Csr::from_parts(2, vec![0, 2], vec![0, 1], vec![1.0, 1.0]),
            Err(CsrError::RowPtrLength { .. })
        ));
        assert!(matches!(
            Csr::from_parts(2, vec![0, 2, 1], vec![0, 1], vec![1.0, 1.0]),
            Err(CsrError::RowPtrNotMonotone { .. })
        ));
        assert!(matches!(
            Csr::from_parts(2, vec![0, 2, 2], vec![1, 0], vec![1.0, 1.0]),
            Err(CsrError::ColumnsNotSorted { row: 0 })
        ));
        assert!(matches!(
            Csr::from_parts(2, vec![0, 1, 2], vec![0, 2], vec![1.0, 1.0]),
            Err(CsrError::ColumnOutOfRange { .. })
        ));
        assert!(matches!(
            Csr::from_parts(2, vec![0, 1, 2], vec![0, 1], vec![1.0]),
            Err(CsrError::LengthMismatch { .. })
        ));
    }

    #[test]
    fn properties() {
        let k = sample();
        assert_eq!(k.nnz(), 7);
        assert_eq!(k.get(1, 2), -2.0);
        assert_eq!(k.get(0, 2), 0.0);
        assert!(k.is_symmetric());
        assert_eq!(k.bandwidth(), 1);
        assert_eq!(k.max_row_nnz(), 3);
        assert_eq!(k.max_abs(), 4.0);
        assert_eq!(k.diagonal(), vec![4.0, 4.0, 4.0]);
        assert!((k.sparsity() - 2.0 / 9.0).abs() < 1e-15);
        assert_eq!(k.sparsity_estimate(), 0.0);
        assert_eq!(k.mul_vec(&[1.0, 1.0, 1.0]), vec![3.0, 1.0, 2.0]);
        assert_eq!(k.scaled(0.5).get(2, 2), 2.0);
        assert_eq!(to_dense(&from_dense(&to_dense(&k))), to_dense(&k));
    }

    #[test]
    fn asymmetry_is_detected() {
        let k = from_dense(&[vec![1.0, 2.0], vec![2.5, 1.0]]);
        assert!(!k.is_symmetric());
        let k = from_dense(&[vec![1.0, 2.0], vec![0.0, 1.0]]);
        assert!(!k.is_symmetric());
    }

    #[test]
    fn dense_solver_solves() {
        let k = sample();
        let x = dense_solve(&k, &[1.0, 2.0, 3.0]);
        let back = k.mul_vec(&x);
        for (a, b) in back.iter().zip([1.0, 2.0, 3.0]) {
            assert!((a - b).abs() < 1e-14);
        }
    }
}
