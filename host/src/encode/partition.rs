//! Sharing the stored rows out over the MVUs (thesis 4.1.1, 4.1.2).
//!
//! The time of one matrix–vector product is the time of the slowest MVU: the words it executes,
//! plus, on the harts' software kernel, a fixed cost per row of Kp it finishes (the row's store,
//! its pᵀKp and max |Kp| terms), so both schemes balance that work:
//!
//! - [`Partition::Rows`] (4.1.2, "non-overlapping sub-matrices"): contiguous blocks of whole
//!   rows, the cut between MVU m and m+1 placed at the row end nearest to (m+1)/M of the
//!   weight, a row weighing its nonzeros plus [`ROW_WEIGHT`] per row of Kp it yields (two for a
//!   mirrored row). No two MVUs write the same row, so each writes its block of Kp directly.
//!   The imbalance is at most about one row's weight (≤ 33 for model B) per MVU.
//! - [`Partition::Overlap`] (4.1.1, "overlapping sub-matrices"): the row-major stream of
//!   nonzeros is cut into M runs of exactly equal length (±1), so a row at a cut is split
//!   between two MVUs. Their sub-matrices then overlap in that row and the partial row sums
//!   are added. The thesis draws square diagonal blocks with wider overlaps, each shared nonzero
//!   given to exactly one block; cutting the stream at equal counts is that scheme with the
//!   smallest overlap that still balances perfectly. It buys the last word of balance at the
//!   price of the additions.
//!
//! With conjugate symmetry the rows partitioned are those of the stored half B (thesis 4.1:
//! "further dividing matrix B"); each MVU then also produces the mirror of its rows.

use std::ops::Range;

use serde::Serialize;

use super::QuantizedMatrix;

/// What finishing one row of Kp costs an MVU on the software kernel, in words of its inner
/// loop. A tile row's end and its rows' pᵀKp and max |Kp| cost 2.4 words of the fused
/// three-direction mirrored loop per row of Kp (242 instructions a tile row against 51 a word,
/// counted in the firmware's disassembly), more of the shorter one-direction loops. Measured
/// on QEMU (issue 19, 8 MVUs): by words alone the MVU with the most (shortest) rows was the
/// slowest; weights 2, 3 and 4 gave the fused 8³ model B phase 43,840, 43,404 and 43,768
/// instructions (45,714 by words alone).
pub const ROW_WEIGHT: u64 = 3;

/// How the rows are shared out over the MVUs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Partition {
    /// Disjoint row blocks balanced by nonzero count and rows (thesis 4.1.2, each row of Kp
    /// weighing [`ROW_WEIGHT`] words): each MVU writes its rows of Kp directly.
    #[default]
    Rows,
    /// Equal runs of the nonzero stream whose boundary rows are shared (thesis 4.1.1): exact
    /// balance, partial row sums added.
    Overlap,
}

impl std::fmt::Display for Partition {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Partition::Rows => "rows",
            Partition::Overlap => "overlap",
        })
    }
}

/// A row, or the part of it an MVU gets: `entries` indexes [`QuantizedMatrix::entry`]. An empty
/// range stands for a row without nonzeros (it still gets an ER word, so its Kp entry is set).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Piece {
    pub row: u32,
    pub entries: Range<usize>,
}

/// The pieces of `rows` each MVU executes, in row order, one list per MVU actually used (at
/// most `mvus`, fewer when there are fewer rows or nonzeros than MVUs). The rows in `mirrored`
/// are stored for their mirror rows too (persymmetric half storage).
pub fn partition(
    q: &QuantizedMatrix,
    rows: Range<usize>,
    mirrored: Range<usize>,
    scheme: Partition,
    mvus: u8,
) -> Vec<Vec<Piece>> {
    if rows.is_empty() {
        return Vec::new();
    }
    match scheme {
        Partition::Rows => by_rows(q, rows, mirrored, mvus.max(1) as usize),
        Partition::Overlap => by_stream(q, rows, mvus.max(1) as usize),
    }
}

fn whole(q: &QuantizedMatrix, row: usize) -> Piece {
    Piece {
        row: row as u32,
        entries: q.row_range(row),
    }
}

/// Disjoint row blocks: cut m is at the row end whose prefix weight is nearest to m/M of the
/// total, each block keeping at least one row. A row weighs its nonzeros (an empty row 1, its
/// ER word) plus [`ROW_WEIGHT`] per row of Kp: two if it is in `mirrored`, else one.
fn by_rows(
    q: &QuantizedMatrix,
    rows: Range<usize>,
    mirrored: Range<usize>,
    mvus: usize,
) -> Vec<Vec<Piece>> {
    let mvus = mvus.min(rows.len());
    let weight = |r: usize| {
        let kp_rows = if mirrored.contains(&r) { 2 } else { 1 };
        q.row_range(r).len().max(1) as u64 + ROW_WEIGHT * kp_rows
    };
    // prefix[i] = weight of rows.start .. rows.start + i.
    let mut prefix = Vec::with_capacity(rows.len() + 1);
    prefix.push(0u64);
    for r in rows.clone() {
        prefix.push(prefix.last().copied().unwrap_or(0) + weight(r));
    }
    let total = *prefix.last().unwrap_or(&0);
    let mut cuts = vec![0usize];
    for m in 1..mvus {
        let goal = total as f64 * m as f64 / mvus as f64;
        let at = prefix.partition_point(|&w| (w as f64) < goal);
        // `at` is the first cut with weight ≥ goal; the one before may be nearer.
        let nearer = if at > 0 && goal - prefix[at - 1] as f64 <= prefix[at] as f64 - goal {
            at - 1
        } else {
            at
        };
        let lowest = cuts.last().copied().unwrap_or(0) + 1;
        let highest = rows.len() - (mvus - m);
        cuts.push(nearer.clamp(lowest, highest));
    }
    cuts.push(rows.len());
    cuts.windows(2)
        .map(|w| (w[0]..w[1]).map(|i| whole(q, rows.start + i)).collect())
        .collect()
}

/// Equal runs of the nonzero stream: MVU m gets stream positions ⌊m·T/M⌋ .. ⌊(m+1)·T/M⌋, a row
/// crossing a cut becoming one piece on either side. Empty rows go with the run their position
/// falls in.
fn by_stream(q: &QuantizedMatrix, rows: Range<usize>, mvus: usize) -> Vec<Vec<Piece>> {
    let first = q.row_range(rows.start).start;
    let end = q.row_range(rows.end - 1).end;
    let total = end - first;
    let mvus = mvus.min(total.max(1));
    let cut = |m: usize| first + m * total / mvus;
    let mut shares: Vec<Vec<Piece>> = vec![Vec::new(); mvus];
    for row in rows {
        let range = q.row_range(row);
        if range.is_empty() {
            let m = (0..mvus)
                .rev()
                .find(|&m| cut(m) <= range.start)
                .unwrap_or(0);
            shares[m].push(whole(q, row));
            continue;
        }
        for (m, share) in shares.iter_mut().enumerate() {
            let lo = range.start.max(cut(m));
            let hi = range.end.min(cut(m + 1));
            if lo < hi {
                share.push(Piece {
                    row: row as u32,
                    entries: lo..hi,
                });
            }
        }
    }
    shares.retain(|s| !s.is_empty());
    shares
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::sparse::test_support::from_dense;

    fn q(dense: &[Vec<f64>]) -> QuantizedMatrix {
        QuantizedMatrix::from_csr(&from_dense(dense)).unwrap()
    }

    fn tridiagonal(n: usize) -> QuantizedMatrix {
        let dense: Vec<Vec<f64>> = (0..n)
            .map(|r| {
                (0..n)
                    .map(|c| match r.abs_diff(c) {
                        0 => 2.0,
                        1 => -1.0,
                        _ => 0.0,
                    })
                    .collect()
            })
            .collect();
        q(&dense)
    }

    fn entries(share: &[Piece]) -> usize {
        share.iter().map(|p| p.entries.len()).sum()
    }

    #[test]
    fn rows_are_disjoint_blocks_balanced_by_weight() {
        let m = tridiagonal(100); // 298 nonzeros
        let total = 298 + ROW_WEIGHT as usize * 100;
        for mvus in 1..=8u8 {
            let shares = partition(&m, 0..100, 0..0, Partition::Rows, mvus);
            assert_eq!(shares.len(), mvus as usize);
            let mut next = 0;
            for share in &shares {
                for piece in share {
                    assert_eq!(piece.row, next, "contiguous, disjoint, complete");
                    assert_eq!(piece.entries, m.row_range(next as usize));
                    next += 1;
                }
            }
            assert_eq!(next, 100);
            let ideal = total as f64 / mvus as f64;
            for share in &shares {
                let weight = entries(share) + ROW_WEIGHT as usize * share.len();
                // At most one row's weight (3 + ROW_WEIGHT) from the ideal.
                assert!(
                    (weight as f64 - ideal).abs() <= (3 + ROW_WEIGHT) as f64,
                    "{mvus}"
                );
            }
        }
    }

    /// A row's cost beyond its words counts: a block of short rows gets fewer nonzeros than a
    /// block of long ones, and a mirrored row (two rows of Kp) weighs its row cost twice.
    #[test]
    fn rows_weigh_their_row_cost() {
        // Rows 0..6 have one nonzero each, rows 6..9 four each (columns 5..9): 18 nonzeros.
        let dense: Vec<Vec<f64>> = (0..9)
            .map(|r| {
                (0..9)
                    .map(|c| {
                        if c == r || (r >= 6 && c >= 5) {
                            1.0
                        } else {
                            0.0
                        }
                    })
                    .collect()
            })
            .collect();
        let m = q(&dense);
        let rows_of = |mirrored| -> Vec<usize> {
            partition(&m, 0..9, mirrored, Partition::Rows, 2)
                .iter()
                .map(Vec::len)
                .collect()
        };
        assert_eq!(ROW_WEIGHT, 3, "the cuts below are worked out for 3");
        // By nonzeros alone the cut would fall at 9 of 18, after row 6 (10). Weighed 4 per
        // short row and 7 per long one (45), it falls at 22.5, after row 5 (24; 20 after row 4).
        assert_eq!(rows_of(0..0), vec![6, 3]);
        // Mirrored, 7 and 10 (72): at 36, after row 4 (35; 42 after row 5).
        assert_eq!(rows_of(0..9), vec![5, 4]);
    }

    #[test]
    fn overlap_splits_the_stream_exactly() {
        let m = tridiagonal(100);
        for mvus in 1..=8u8 {
            let shares = partition(&m, 0..100, 0..0, Partition::Overlap, mvus);
            assert_eq!(shares.len(), mvus as usize);
            let sizes: Vec<usize> = shares.iter().map(|s| entries(s)).collect();
            assert!(sizes.iter().max().unwrap() - sizes.iter().min().unwrap() <= 1);
            // Every entry exactly once, in order.
            let all: Vec<usize> = shares
                .iter()
                .flatten()
                .flat_map(|p| p.entries.clone())
                .collect();
            assert_eq!(all, (0..298).collect::<Vec<_>>());
            // Neighbouring MVUs share at most their boundary row.
            for w in shares.windows(2) {
                let last = w[0].last().unwrap().row;
                let first = w[1].first().unwrap().row;
                assert!(first == last || first == last + 1);
            }
        }
    }

    #[test]
    fn more_mvus_than_rows_uses_fewer() {
        let m = tridiagonal(3);
        assert_eq!(partition(&m, 0..3, 0..0, Partition::Rows, 8).len(), 3);
        assert_eq!(partition(&m, 0..3, 0..0, Partition::Overlap, 8).len(), 7);
        assert_eq!(partition(&m, 1..2, 0..0, Partition::Rows, 8).len(), 1);
        assert!(partition(&m, 0..0, 0..0, Partition::Rows, 8).is_empty());
    }

    #[test]
    fn empty_rows_are_kept() {
        let m = q(&[
            vec![1.0, 0.0, 0.0],
            vec![0.0, 0.0, 0.0],
            vec![0.0, 0.0, 1.0],
        ]);
        for scheme in [Partition::Rows, Partition::Overlap] {
            let rows: Vec<u32> = partition(&m, 0..3, 0..0, scheme, 2)
                .iter()
                .flatten()
                .map(|p| p.row)
                .collect();
            assert_eq!(rows, vec![0, 1, 2], "{scheme}");
        }
    }
}
