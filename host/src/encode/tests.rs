use super::*;
use crate::model::sparse::test_support::from_dense;
use crate::model::{Axis, Connection, FixedNodeSet, Grid, Model, ModelSpec};

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

/// Structural checks every encoding must pass, whatever the options.
fn check_tiles(encoded: &EncodedMatrix) {
    for (index, (header, words)) in encoded.tile_words().enumerate() {
        assert_eq!(
            validate_tile(index as u32, header, words, encoded.n),
            Ok(())
        );
        assert!(header.rows <= tiling::MAX_TILE_ROWS);
    }
    assert_eq!(
        encoded
            .tiles
            .iter()
            .map(|t| t.words as usize)
            .sum::<usize>(),
        encoded.words.len()
    );
}

/// A deterministic pseudo-random integer vector (a 64-bit LCG), values in ±2^29.
fn vector(n: usize, seed: u64) -> Vec<i64> {
    let mut state = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
    (0..n)
        .map(|_| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 34) as i64) - (1 << 29)
        })
        .collect()
}

/// The tiles' exact integer product equals the quantised CSR product for two vectors.
fn assert_exact_product(k: &Csr, encoded: &EncodedMatrix) {
    let q = QuantizedMatrix::from_csr(k).unwrap();
    assert_eq!(q.frac_bits, encoded.frac_bits);
    for seed in [1, 2] {
        let p = vector(k.n(), seed);
        assert_eq!(tiles_mul_exact(encoded, &p).unwrap(), q.mul_exact(&p));
    }
}

fn options(mvus: u8, partition: Partition, use_symmetry: bool) -> EncodeOptions {
    EncodeOptions {
        mvus,
        partition,
        use_symmetry,
    }
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
            assert!(
                encoded.words.len() <= a.nnz() + a.n() / 100,
                "little overhead"
            );
        }
    }
}

#[test]
fn every_layout_gives_the_same_product() {
    for connection in [Connection::Axial, Connection::AxialShear] {
        for dims in [(3, 4, 5), (6, 6, 6), (10, 10, 10)] {
            let a = model(dims, connection).unit_matrix().clone();
            for partition in [Partition::Rows, Partition::Overlap] {
                for mvus in [1, 2, 3, 4, 8] {
                    for use_symmetry in [false, true] {
                        let enc = encode_with(&a, &options(mvus, partition, use_symmetry)).unwrap();
                        check_tiles(&enc.matrix);
                        assert_eq!(enc.summary.mvus, mvus, "{dims:?}");
                        assert!(enc.summary.persymmetric, "corners fixed: symmetric");
                        assert_eq!(enc.summary.symmetry_used, use_symmetry);
                        assert_exact_product(&a, &enc.matrix);
                        assert_eq!(decode(&enc.matrix).unwrap(), a);
                    }
                }
            }
        }
    }
}

#[test]
fn the_rows_partition_gives_each_mvu_its_own_rows() {
    let a = model((10, 10, 10), Connection::AxialShear)
        .unit_matrix()
        .clone();
    for use_symmetry in [false, true] {
        let enc = encode_with(&a, &options(8, Partition::Rows, use_symmetry)).unwrap();
        let mut owner = vec![None; a.n()];
        for t in &enc.matrix.tiles {
            let rows = t.row_base..t.row_base + t.rows;
            let mirrors = rows.clone().map(|r| a.n() as u32 - 1 - r);
            let all: Vec<u32> = if t.mirrored {
                rows.chain(mirrors).collect()
            } else {
                rows.collect()
            };
            for r in all {
                let o = owner[r as usize].get_or_insert(t.mvu);
                assert_eq!(*o, t.mvu, "row {r} written by two MVUs");
            }
        }
        assert!(owner.iter().all(Option::is_some), "every row has an MVU");
        // Balanced by weight (words and rows of Kp): the busiest MVU has at most one model-B
        // row (27 words and two rows of Kp) over the ideal.
        let row_weight = crate::encode::partition::ROW_WEIGHT as usize;
        let weights: Vec<usize> = (0..8u8)
            .map(|m| {
                let rows = owner.iter().filter(|o| **o == Some(m)).count();
                enc.summary.words_per_mvu[m as usize] + row_weight * rows
            })
            .collect();
        let ideal = weights.iter().sum::<usize>() as f64 / 8.0;
        assert!(
            *weights.iter().max().unwrap() as f64 - ideal <= (27 + 2 * row_weight + 8) as f64,
            "{weights:?}"
        );
    }
}

#[test]
fn the_overlap_partition_balances_exactly() {
    let a = model((10, 10, 10), Connection::AxialShear)
        .unit_matrix()
        .clone();
    let enc = encode_with(&a, &options(8, Partition::Overlap, false)).unwrap();
    let products = &enc.summary.products_per_mvu;
    assert!(products.iter().max().unwrap() - products.iter().min().unwrap() <= 1);
    // Some rows are shared: that is what makes it the overlapping scheme.
    let mut writers = vec![std::collections::BTreeSet::new(); a.n()];
    for t in &enc.matrix.tiles {
        for r in t.row_base..t.row_base + t.rows {
            writers[r as usize].insert(t.mvu);
        }
    }
    assert!(writers.iter().any(|w| w.len() > 1));
}

/// 16³ model A and B and 32³ model A: the grids beyond 512 columns. Prints the layout figures.
#[test]
fn big_grids_tile_exactly_and_cheaply() {
    for (dims, connection, max_overhead) in [
        ((16, 16, 16), Connection::Axial, 0.01),
        ((16, 16, 16), Connection::AxialShear, 0.01),
        ((32, 32, 32), Connection::Axial, 0.01),
    ] {
        let a = model(dims, connection).unit_matrix().clone();
        for use_symmetry in [false, true] {
            let enc = encode_with(&a, &options(1, Partition::Rows, use_symmetry)).unwrap();
            check_tiles(&enc.matrix);
            assert_exact_product(&a, &enc.matrix);
            let s = &enc.summary;
            eprintln!(
                "{dims:?} {connection} symmetry {use_symmetry}: n {} nnz {} -> {} words \
                 ({} nonzero, {} empty-row, overhead {:.3}%), {} tiles",
                a.n(),
                a.nnz(),
                s.words,
                s.stored_nonzeros,
                s.empty_row_words,
                100.0 * s.overhead(),
                s.tiles
            );
            assert!(s.overhead() <= max_overhead, "{dims:?} {connection}");
            assert!(
                s.words <= 512 * 1024 && s.tiles <= 4096,
                "fits the firmware store"
            );
            if use_symmetry {
                assert!(
                    s.stored_nonzeros * 2 <= a.nnz() + a.n(),
                    "about half stored"
                );
            } else {
                assert_eq!(s.stored_nonzeros, a.nnz());
            }
        }
    }
}

#[test]
fn symmetry_is_only_used_when_the_matrix_is_persymmetric() {
    let grid = Grid::new(6, 6, 6).unwrap();
    let one_face = Model::build(&ModelSpec {
        grid,
        fixed_sets: vec!["z-".parse::<FixedNodeSet>().unwrap()],
        loads: vec![ModelSpec::default_load(grid)],
        ..ModelSpec::thesis_example()
    })
    .unwrap();
    let a = one_face.unit_matrix();
    let enc = encode_with(a, &options(2, Partition::Rows, true)).unwrap();
    assert!(!enc.summary.persymmetric && !enc.summary.symmetry_used);
    assert!(enc.matrix.tiles.iter().all(|t| !t.mirrored));
    assert_exact_product(a, &enc.matrix);
}

#[test]
fn odd_n_keeps_the_middle_row_plain() {
    let a = model((3, 3, 3), Connection::AxialShear)
        .unit_matrix()
        .clone();
    assert_eq!(a.n(), 27);
    let enc = encode_with(&a, &options(1, Partition::Rows, true)).unwrap();
    assert!(enc.summary.symmetry_used);
    let plain: Vec<_> = enc.matrix.tiles.iter().filter(|t| !t.mirrored).collect();
    assert_eq!(plain.len(), 1);
    assert_eq!((plain[0].row_base, plain[0].rows), (13, 1));
    assert!(enc
        .matrix
        .tiles
        .iter()
        .filter(|t| t.mirrored)
        .all(|t| t.row_base + t.rows <= 13));
    assert_exact_product(&a, &enc.matrix);
}

#[test]
fn thesis_example_tiles() {
    let a = model((10, 10, 10), Connection::Axial).unit_matrix().clone();
    let encoded = encode(&a).unwrap();
    assert_eq!(encoded.frac_bits, 17, "max |A| = 6");
    // Rows span ±100 columns: three staggered row blocks of about 300 rows, plus the windows
    // that take over each block's high columns.
    assert!(encoded.tiles.len() <= 6, "{}", encoded.tiles.len());
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

fn tridiagonal(n: usize) -> Csr {
    let mut builder = CsrBuilder::new(n, 3 * n);
    for r in 0..n {
        let entries = [(r.wrapping_sub(1), -1.0), (r, 2.0), (r + 1, -1.0)];
        builder
            .push_row(entries.into_iter().filter(|&(c, _)| c < n))
            .unwrap();
    }
    builder.finish().unwrap()
}

#[test]
fn word_fields_are_row_major_with_relative_columns() {
    // A 600-row tridiagonal matrix: row 511 reaches column 512, one past the first window,
    // which a second window starting there takes.
    let k = tridiagonal(600);
    let encoded = encode(&k).unwrap();
    check_tiles(&encoded);
    assert_eq!(encoded.frac_bits, 18);
    let t = encoded.tiles[0];
    assert_eq!(
        (t.row_base, t.col_base, t.rows, t.words),
        (0, 0, 512, 3 * 512 - 2)
    );
    let t = encoded.tiles[1];
    assert_eq!((t.row_base, t.col_base), (511, 512));
    assert!(encoded.tiles.len() <= 3, "{:?}", encoded.tiles);
    let (_, words) = encoded.tile_words().nth(1).unwrap();
    let fields = |bits: u32| {
        let w = Word(bits);
        (w.column(), w.raw_value(), w.end_of_row(), w.end_of_matrix())
    };
    let one = 1 << 18;
    // Row 511's column 512 is the second tile's first word, relative column 0.
    assert_eq!(fields(words[0]), (0, -one, true, false));
    assert!(fields(*words.last().unwrap()).3, "EM on the last word");
    let (_, words) = encoded.tile_words().next().unwrap();
    assert_eq!(fields(words[0]), (0, 2 * one, false, false));
    assert_eq!(fields(words[1]), (1, -one, true, false));
    assert_eq!(decode(&encoded).unwrap(), k);
    assert_exact_product(&k, &encoded);
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
fn rows_wider_than_a_window_are_split() {
    // Arrow matrix: row 0 and column 0 are full, so row 0 spans all 1500 columns.
    let n = 1500;
    let mut builder = CsrBuilder::new(n, 3 * n);
    builder
        .push_row((0..n).map(|c| (c, if c == 0 { n as f64 } else { -1.0 })))
        .unwrap();
    for r in 1..n {
        builder.push_row([(0, -1.0), (r, 2.0)]).unwrap();
    }
    let k = builder.finish().unwrap();
    for mvus in [1, 3] {
        for partition in [Partition::Rows, Partition::Overlap] {
            let enc = encode_with(&k, &options(mvus, partition, true)).unwrap();
            check_tiles(&enc.matrix);
            assert!(!enc.summary.persymmetric);
            assert_exact_product(&k, &enc.matrix);
            assert_eq!(decode(&enc.matrix).unwrap(), k);
        }
    }
}

#[test]
fn values_too_large_for_the_field_are_refused() {
    let k = from_dense(&[vec![2e6]]);
    assert!(matches!(encode(&k), Err(EncodeError::QFormat(_))));
    let k = from_dense(&[vec![2.0]]);
    assert_eq!(
        encode_with(&k, &options(0, Partition::Rows, false)),
        Err(EncodeError::NoMvus)
    );
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
    let mut encoded = encode(&a).unwrap();
    encoded.tiles[0].mirrored = true;
    assert!(matches!(
        decode(&encoded),
        Err(DecodeError::MirrorOverlap { .. })
    ));
}
