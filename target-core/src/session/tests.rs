//! Session tests: every error path, the happy path against a direct f64 solve, and a proptest
//! that throws random request sequences at a session with small buffers.

use super::*;
use crate::exec::Sequential;
use crate::testkit::{banded_row, dense, encode_rows, OwnedStorage, TestSystem};

/// The host's stand-in for the firmware's harts.
const HARTS: Sequential = Sequential { harts: 4 };
use deform_shared::frame;
use deform_shared::protocol::{Envelope, SolveFailure, SolveReport, MAX_FRAME_LEN};
use deform_shared::qformat::{block_exponent, from_mantissa, to_mantissa};
use deform_shared::word::{Word, VALUE_MAX, VALUE_MIN};
use proptest::prelude::*;

// ---------------------------------------------------------------------------------------------
// Fixtures

fn info() -> TargetInfo {
    TargetInfo {
        protocol_version: 0,
        firmware_version: heapless::String::try_from("test").unwrap(),
        harts: 1,
        word_capacity: u32::MAX,
        tile_capacity: u32::MAX,
        max_n: u32::MAX,
        build_id: heapless::Vec::new(),
    }
}

/// A matrix encoded as tiles, ready to upload.
type Encoded = TestSystem;

/// Encodes the rows `row(i) = [(column, value)]` of an n×n matrix, `rows_per_tile` rows per
/// tile, each tile's column window starting at its smallest column.
fn encode(
    n: usize,
    rows_per_tile: usize,
    frac_bits: u8,
    row: impl Fn(usize) -> Vec<(usize, f64)>,
) -> Encoded {
    encode_rows(n, n, rows_per_tile, frac_bits, row)
}

/// tridiag(−1, 2, −1), the 1-D Laplacian.
fn laplacian_row(n: usize) -> impl Fn(usize) -> Vec<(usize, f64)> {
    banded_row(n, 1)
}

fn laplacian(n: usize, rows_per_tile: usize) -> Encoded {
    encode(n, rows_per_tile, 18, laplacian_row(n))
}

/// Gaussian elimination with partial pivoting.
fn direct_solve(mut a: Vec<Vec<f64>>, mut b: Vec<f64>) -> Vec<f64> {
    let n = b.len();
    for k in 0..n {
        let piv = (k..n)
            .max_by(|&i, &j| a[i][k].abs().total_cmp(&a[j][k].abs()))
            .unwrap();
        a.swap(k, piv);
        b.swap(k, piv);
        for i in k + 1..n {
            let f = a[i][k] / a[k][k];
            if f != 0.0 {
                let (top, bottom) = a.split_at_mut(i);
                for (aij, akj) in bottom[0][k..].iter_mut().zip(&top[k][k..]) {
                    *aij -= f * akj;
                }
                b[i] -= f * b[k];
            }
        }
    }
    let mut x = vec![0.0; n];
    for i in (0..n).rev() {
        let s: f64 = (i + 1..n).map(|j| a[i][j] * x[j]).sum();
        x[i] = (b[i] - s) / a[i][i];
    }
    x
}

fn chunk<T: Copy, const N: usize>(s: &[T]) -> heapless::Vec<T, N> {
    heapless::Vec::from_slice(s).unwrap()
}

fn begin(e: &Encoded) -> Request {
    Request::BeginMatrix {
        n: e.n,
        frac_bits: e.frac_bits,
        tiles: e.tiles.len() as u32,
        words: e.words.len() as u32,
    }
}

/// The requests that upload `e` in chunks of `chunk_len` words.
fn matrix_requests(e: &Encoded, chunk_len: usize) -> Vec<Request> {
    let mut reqs = vec![begin(e)];
    let mut offset = 0usize;
    for t in &e.tiles {
        reqs.push(Request::Tile(*t));
        let end = offset + t.words as usize;
        while offset < end {
            let stop = end.min(offset + chunk_len);
            reqs.push(Request::Words {
                offset: offset as u32,
                words: chunk(&e.words[offset..stop]),
            });
            offset = stop;
        }
    }
    reqs.push(Request::EndMatrix {
        crc32: words_crc(&e.words),
    });
    reqs
}

/// The requests that replace the resident matrix's values by `e`'s, `chunk_len` per chunk.
fn update_requests(e: &Encoded, chunk_len: usize) -> Vec<Request> {
    let mut reqs = vec![Request::BeginUpdate {
        words: e.words.len() as u32,
        frac_bits: e.frac_bits,
    }];
    let values: Vec<i32> = e.words.iter().map(|&w| Word(w).raw_value()).collect();
    for (k, c) in values.chunks(chunk_len).enumerate() {
        reqs.push(Request::UpdateValues {
            offset: (k * chunk_len) as u32,
            values: chunk(c),
        });
    }
    reqs.push(Request::EndUpdate {
        crc32: words_crc(&e.words),
    });
    reqs
}

fn vector_requests(slot: VectorSlot, exponent: i32, m: &[i32], chunk_len: usize) -> Vec<Request> {
    let mut reqs = vec![Request::BeginVector {
        slot,
        exponent,
        len: m.len() as u32,
    }];
    for (k, c) in m.chunks(chunk_len).enumerate() {
        reqs.push(Request::VectorData {
            slot,
            offset: (k * chunk_len) as u32,
            mantissas: chunk(c),
        });
    }
    reqs
}

/// Block-floating-point form of `v`.
fn to_block(v: &[f64]) -> (i32, Vec<i32>) {
    let e = block_exponent(v.iter().fold(0.0f64, |m, x| m.max(x.abs())));
    (e, v.iter().map(|&x| to_mantissa(x, e).unwrap()).collect())
}

fn all_ack(s: &mut Session<'_, Sequential>, reqs: Vec<Request>) {
    for req in reqs {
        let what = format!("{req:?}");
        assert_eq!(s.handle(req), Response::Ack, "{what}");
    }
}

fn load(s: &mut Session<'_, Sequential>, e: &Encoded) {
    all_ack(s, matrix_requests(e, CHUNK_LEN));
}

fn load_rhs(s: &mut Session<'_, Sequential>, b: &[f64]) {
    let (e, m) = to_block(b);
    all_ack(s, vector_requests(VectorSlot::RHS, e, &m, CHUNK_LEN));
}

fn err(code: ErrorCode) -> Response {
    Response::Error(code)
}

fn ooo(step: SessionStep) -> Response {
    Response::Error(ErrorCode::OutOfOrder(step))
}

fn solve_req(start: Start) -> Request {
    Request::Solve(SolveParams {
        max_iterations: 1000,
        tolerance: 1e-9,
        start,
        directions: 1,
        cycle_budget: 0,
    })
}

fn solved(r: Response) -> SolveReport {
    match r {
        Response::Solved(report) => report,
        other => panic!("expected Solved, got {other:?}"),
    }
}

/// Reads the whole solution back, chunk by chunk.
fn read_all(s: &mut Session<'_, Sequential>, n: usize) -> Vec<f64> {
    read_direction(s, 0, n)
}

/// Reads one direction's solution back, chunk by chunk.
fn read_direction(s: &mut Session<'_, Sequential>, direction: u8, n: usize) -> Vec<f64> {
    let mut out = Vec::new();
    while out.len() < n {
        match s.handle(Request::ReadSolution {
            direction,
            offset: out.len() as u32,
            len: CHUNK_LEN as u16,
        }) {
            Response::Solution {
                direction: got,
                offset,
                exponent,
                mantissas,
            } => {
                assert_eq!(got, direction);
                assert_eq!(offset as usize, out.len());
                assert!(!mantissas.is_empty() && mantissas.len() <= CHUNK_LEN);
                out.extend(mantissas.iter().map(|&m| from_mantissa(m, exponent)));
            }
            other => panic!("expected Solution, got {other:?}"),
        }
    }
    assert_eq!(out.len(), n);
    out
}

fn max_rel_err(got: &[f64], want: &[f64]) -> f64 {
    let scale = want.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    got.iter()
        .zip(want)
        .map(|(g, w)| (g - w).abs() / scale)
        .fold(0.0, f64::max)
}

// ---------------------------------------------------------------------------------------------
// Hello and capacities

#[test]
fn hello_reports_capacities_clamped_to_the_storage() {
    let mut bufs = OwnedStorage::new(100, 7, 20);
    let mut s = bufs.session(info(), HARTS.harts);
    let Response::Hello(info) = s.handle(Request::Hello {
        protocol_version: PROTOCOL_VERSION,
    }) else {
        panic!()
    };
    assert_eq!(info.protocol_version, PROTOCOL_VERSION);
    assert_eq!(
        (info.word_capacity, info.tile_capacity, info.max_n),
        (100, 7, 20)
    );
    assert_eq!(info.firmware_version.as_str(), "test");
    assert_eq!(&info, s.info());
}

#[test]
fn advertised_capacities_below_the_storage_are_kept_and_enforced() {
    let mut bufs = OwnedStorage::new(100, 7, 20);
    bufs.directions[1][3].truncate(15); // r of direction 1 limits max_n to 15
    let storage = bufs.storage();
    let mut s = Session::new(
        storage,
        TargetInfo {
            word_capacity: 50,
            ..info()
        },
        HARTS,
    );
    assert_eq!(
        (
            s.info().word_capacity,
            s.info().tile_capacity,
            s.info().max_n
        ),
        (50, 7, 15)
    );
    let r = s.handle(Request::BeginMatrix {
        n: 16,
        frac_bits: 0,
        tiles: 1,
        words: 1,
    });
    assert_eq!(
        r,
        err(ErrorCode::DimensionTooLarge {
            requested: 16,
            capacity: 15
        })
    );
    let r = s.handle(Request::BeginMatrix {
        n: 15,
        frac_bits: 0,
        tiles: 1,
        words: 51,
    });
    assert_eq!(
        r,
        err(ErrorCode::TooManyWords {
            requested: 51,
            capacity: 50
        })
    );
}

#[test]
fn a_fresh_session_needs_no_hello() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    load(&mut s, &laplacian(10, 10));
    assert!(s.matrix_loaded());
}

#[test]
fn a_version_mismatch_answers_hello_then_refuses_until_a_matching_hello() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    let e = laplacian(10, 10);
    load(&mut s, &e);
    let other = PROTOCOL_VERSION.wrapping_add(1);
    let Response::Hello(info) = s.handle(Request::Hello {
        protocol_version: other,
    }) else {
        panic!()
    };
    assert_eq!(info.protocol_version, PROTOCOL_VERSION);
    assert!(!s.matrix_loaded(), "Hello resets the session");
    let mismatch = err(ErrorCode::VersionMismatch {
        target: PROTOCOL_VERSION,
    });
    assert_eq!(s.handle(begin(&e)), mismatch);
    assert_eq!(
        s.handle(Request::ReadSolution {
            direction: 0,
            offset: 0,
            len: CHUNK_LEN as u16
        }),
        mismatch
    );
    assert!(matches!(
        s.handle(Request::Hello {
            protocol_version: PROTOCOL_VERSION
        }),
        Response::Hello(_)
    ));
    load(&mut s, &e);
}

#[test]
fn hello_resets_a_loaded_matrix_and_an_upload() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    let e = laplacian(10, 10);
    load(&mut s, &e);
    s.handle(Request::Hello {
        protocol_version: PROTOCOL_VERSION,
    });
    assert_eq!(
        s.handle(Request::BeginVector {
            slot: VectorSlot::RHS,
            exponent: 0,
            len: 10
        }),
        ooo(SessionStep::NoMatrix)
    );
    assert_eq!(s.handle(begin(&e)), Response::Ack);
    s.handle(Request::Hello {
        protocol_version: PROTOCOL_VERSION,
    });
    assert_eq!(
        s.handle(Request::Tile(e.tiles[0])),
        ooo(SessionStep::NoMatrixUpload)
    );
}

// ---------------------------------------------------------------------------------------------
// BeginMatrix

#[test]
fn begin_matrix_checks_the_announced_shape() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    let bm = |n, frac_bits, tiles, words| Request::BeginMatrix {
        n,
        frac_bits,
        tiles,
        words,
    };
    assert_eq!(
        s.handle(bm(17, 0, 1, 1)),
        err(ErrorCode::DimensionTooLarge {
            requested: 17,
            capacity: 16
        })
    );
    assert_eq!(
        s.handle(bm(u32::MAX, 0, 1, 1)),
        err(ErrorCode::DimensionTooLarge {
            requested: u32::MAX,
            capacity: 16
        })
    );
    assert_eq!(
        s.handle(bm(16, 0, 1, 101)),
        err(ErrorCode::TooManyWords {
            requested: 101,
            capacity: 100
        })
    );
    assert_eq!(
        s.handle(bm(16, 0, 5, 100)),
        err(ErrorCode::TooManyTiles {
            requested: 5,
            capacity: 4
        })
    );
    assert_eq!(
        s.handle(bm(16, 21, 4, 100)),
        err(ErrorCode::BadFracBits(21))
    );
    assert_eq!(
        s.handle(bm(16, 255, 4, 100)),
        err(ErrorCode::BadFracBits(255))
    );
    assert_eq!(
        s.handle(bm(0, 0, 1, 1)),
        err(ErrorCode::Matrix(MatrixError::EmptyTile { tile: 0 }))
    );
    assert_eq!(
        s.handle(bm(16, 0, 0, 0)),
        err(ErrorCode::Matrix(MatrixError::EmptyTile { tile: 0 }))
    );
    assert_eq!(s.handle(bm(16, 20, 4, 100)), Response::Ack);
    assert_eq!(s.handle(bm(1, 0, 1, 1)), Response::Ack);
}

#[test]
fn begin_matrix_drops_the_loaded_matrix_even_when_refused() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    let e = laplacian(10, 10);
    load(&mut s, &e);
    load_rhs(&mut s, &[1.0; 10]);
    let r = s.handle(Request::BeginMatrix {
        n: 99,
        frac_bits: 0,
        tiles: 1,
        words: 1,
    });
    assert!(matches!(
        r,
        Response::Error(ErrorCode::DimensionTooLarge { .. })
    ));
    assert!(!s.matrix_loaded());
    assert_eq!(s.handle(solve_req(Start::Zero)), ooo(SessionStep::NoMatrix));
    // The vectors went with the matrix.
    load(&mut s, &e);
    assert_eq!(s.handle(solve_req(Start::Zero)), ooo(SessionStep::NoRhs));
}

// ---------------------------------------------------------------------------------------------
// Tiles and words

#[test]
fn tiles_and_words_without_an_upload_are_out_of_order() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    let e = laplacian(10, 10);
    assert_eq!(
        s.handle(Request::Tile(e.tiles[0])),
        ooo(SessionStep::NoMatrixUpload)
    );
    assert_eq!(
        s.handle(Request::Words {
            offset: 0,
            words: chunk(&e.words[..4])
        }),
        ooo(SessionStep::NoMatrixUpload)
    );
    assert_eq!(
        s.handle(Request::EndMatrix { crc32: 0 }),
        ooo(SessionStep::NoMatrixUpload)
    );
    // Nor once the matrix is loaded.
    load(&mut s, &e);
    assert_eq!(
        s.handle(Request::Tile(e.tiles[0])),
        ooo(SessionStep::NoMatrixUpload)
    );
    assert_eq!(
        s.handle(Request::EndMatrix {
            crc32: words_crc(&e.words)
        }),
        ooo(SessionStep::NoMatrixUpload)
    );
}

#[test]
fn words_need_a_tile_and_a_tile_needs_its_words() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    let e = laplacian(10, 5);
    assert_eq!(s.handle(begin(&e)), Response::Ack);
    assert_eq!(
        s.handle(Request::Words {
            offset: 0,
            words: chunk(&e.words[..4])
        }),
        ooo(SessionStep::TileExpected)
    );
    assert_eq!(s.handle(Request::Tile(e.tiles[0])), Response::Ack);
    assert_eq!(
        s.handle(Request::Tile(e.tiles[1])),
        ooo(SessionStep::TileIncomplete)
    );
    assert_eq!(
        s.handle(Request::EndMatrix {
            crc32: words_crc(&e.words)
        }),
        ooo(SessionStep::TileIncomplete)
    );
    let first = e.tiles[0].words as usize;
    assert_eq!(
        s.handle(Request::Words {
            offset: 0,
            words: chunk(&e.words[..first])
        }),
        Response::Ack
    );
    assert_eq!(
        s.handle(Request::EndMatrix {
            crc32: words_crc(&e.words)
        }),
        ooo(SessionStep::TilesMissing)
    );
    assert_eq!(
        s.handle(Request::Words {
            offset: first as u32,
            words: chunk(&e.words[first..])
        }),
        ooo(SessionStep::TileExpected)
    );
    assert_eq!(s.handle(Request::Tile(e.tiles[1])), Response::Ack);
    assert_eq!(
        s.handle(Request::Words {
            offset: first as u32,
            words: chunk(&e.words[first..])
        }),
        Response::Ack
    );
    // All tiles are in: more tiles or words run past the announced size.
    assert_eq!(
        s.handle(Request::Tile(e.tiles[1])),
        err(ErrorCode::ChunkTooLong)
    );
    assert_eq!(
        s.handle(Request::Words {
            offset: e.words.len() as u32,
            words: chunk(&[1])
        }),
        err(ErrorCode::ChunkTooLong)
    );
    assert_eq!(
        s.handle(Request::EndMatrix {
            crc32: words_crc(&e.words)
        }),
        Response::Ack
    );
}

#[test]
fn word_chunks_must_be_in_order_and_within_the_tile() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    let e = laplacian(10, 5);
    let first = e.tiles[0].words as usize;
    s.handle(begin(&e));
    s.handle(Request::Tile(e.tiles[0]));
    let w = |offset: u32, range: core::ops::Range<usize>| Request::Words {
        offset,
        words: chunk(&e.words[range]),
    };
    assert_eq!(
        s.handle(w(1, 0..3)),
        err(ErrorCode::UnexpectedOffset {
            expected: 0,
            got: 1
        })
    );
    assert_eq!(
        s.handle(w(u32::MAX, 0..3)),
        err(ErrorCode::UnexpectedOffset {
            expected: 0,
            got: u32::MAX
        })
    );
    assert_eq!(s.handle(w(0, 0..first + 1)), err(ErrorCode::ChunkTooLong));
    assert_eq!(s.handle(w(0, 0..3)), Response::Ack);
    assert_eq!(
        s.handle(Request::Words {
            offset: 3,
            words: heapless::Vec::new()
        }),
        Response::Ack
    );
    // A resent chunk is refused with the offset the target expects, and changes nothing.
    assert_eq!(
        s.handle(w(0, 0..3)),
        err(ErrorCode::UnexpectedOffset {
            expected: 3,
            got: 0
        })
    );
    assert_eq!(s.handle(w(3, 3..first + 1)), err(ErrorCode::ChunkTooLong));
    assert_eq!(s.handle(w(3, 3..first)), Response::Ack);
    // The next tile's chunks count on from the start of the stream.
    s.handle(Request::Tile(e.tiles[1]));
    assert_eq!(
        s.handle(w(0, first..first + 2)),
        err(ErrorCode::UnexpectedOffset {
            expected: first as u32,
            got: 0
        })
    );
    assert_eq!(
        s.handle(w(first as u32, first..e.words.len())),
        Response::Ack
    );
    assert_eq!(
        s.handle(Request::EndMatrix {
            crc32: words_crc(&e.words)
        }),
        Response::Ack
    );
}

#[test]
fn tile_headers_are_checked_on_arrival_and_a_refused_header_changes_nothing() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    let e = laplacian(10, 5);
    s.handle(begin(&e));
    let t = e.tiles[0];
    let m = |e| err(ErrorCode::Matrix(e));
    assert_eq!(
        s.handle(Request::Tile(TileHeader { rows: 0, ..t })),
        m(MatrixError::EmptyTile { tile: 0 })
    );
    assert_eq!(
        s.handle(Request::Tile(TileHeader { words: 0, ..t })),
        m(MatrixError::EmptyTile { tile: 0 })
    );
    assert_eq!(
        s.handle(Request::Tile(TileHeader { row_base: 6, ..t })),
        m(MatrixError::RowsOutOfRange { tile: 0 })
    );
    assert_eq!(
        s.handle(Request::Tile(TileHeader {
            row_base: u32::MAX,
            ..t
        })),
        m(MatrixError::RowsOutOfRange { tile: 0 })
    );
    assert_eq!(
        s.handle(Request::Tile(TileHeader { words: 29, ..t })),
        m(MatrixError::TotalWordsMismatch {
            expected: 28,
            found: 29
        })
    );
    assert_eq!(
        s.handle(Request::Tile(TileHeader {
            words: u32::MAX,
            ..t
        })),
        m(MatrixError::TotalWordsMismatch {
            expected: 28,
            found: u32::MAX
        })
    );
    // The upload goes on.
    for req in matrix_requests(&e, 5).into_iter().skip(1) {
        assert_eq!(s.handle(req), Response::Ack);
    }
}

#[test]
fn a_malformed_tile_aborts_the_upload() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    let mut e = laplacian(10, 5);
    let last = e.tiles[0].words as usize - 1;
    e.words[last] &= !deform_shared::word::EM_BIT;
    let reqs = matrix_requests(&e, 4);
    let mut answers = reqs.into_iter().map(|r| s.handle(r));
    let first_error = answers.find(|a| *a != Response::Ack);
    assert_eq!(
        first_error,
        Some(err(ErrorCode::Matrix(MatrixError::MissingEnd { tile: 0 })))
    );
    // Everything after it finds no upload.
    assert!(answers.all(|a| a == ooo(SessionStep::NoMatrixUpload)));
}

#[test]
fn each_tile_is_validated_against_n_when_complete() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    // Column 10 in a 10×10 matrix.
    let e = encode(10, 5, 18, |i| {
        if i == 7 {
            vec![(10, 1.0)]
        } else {
            vec![(i, 2.0)]
        }
    });
    let answers: Vec<_> = matrix_requests(&e, 64)
        .into_iter()
        .map(|r| s.handle(r))
        .collect();
    assert!(
        answers.contains(&err(ErrorCode::Matrix(MatrixError::ColumnOutOfRange {
            tile: 1,
            column: 10
        })))
    );
    // A row count that does not match the header.
    let mut e = laplacian(10, 10);
    e.words[0] |= deform_shared::word::ER_BIT;
    let answers: Vec<_> = matrix_requests(&e, 64)
        .into_iter()
        .map(|r| s.handle(r))
        .collect();
    assert!(
        answers.contains(&err(ErrorCode::Matrix(MatrixError::RowCountMismatch {
            tile: 0,
            expected: 10,
            found: 11
        })))
    );
}

#[test]
fn end_matrix_checks_the_word_total_and_the_crc() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    let e = laplacian(10, 10);
    // Tiles that hold fewer words than announced.
    let mut reqs = matrix_requests(&e, 64);
    reqs[0] = Request::BeginMatrix {
        n: 10,
        frac_bits: 18,
        tiles: 1,
        words: 40,
    };
    let end = reqs.pop().unwrap();
    all_ack(&mut s, reqs);
    assert_eq!(
        s.handle(end),
        err(ErrorCode::Matrix(MatrixError::TotalWordsMismatch {
            expected: 40,
            found: 28
        }))
    );
    assert_eq!(
        s.handle(Request::EndMatrix {
            crc32: words_crc(&e.words)
        }),
        ooo(SessionStep::NoMatrixUpload)
    );
    // A wrong CRC reports the computed one and aborts.
    let mut reqs = matrix_requests(&e, 64);
    reqs.pop();
    all_ack(&mut s, reqs);
    let crc = words_crc(&e.words);
    assert_eq!(
        s.handle(Request::EndMatrix { crc32: !crc }),
        err(ErrorCode::MatrixCrc { computed: crc })
    );
    assert!(!s.matrix_loaded());
    assert_eq!(
        s.handle(Request::EndMatrix { crc32: crc }),
        ooo(SessionStep::NoMatrixUpload)
    );
}

// ---------------------------------------------------------------------------------------------
// Vectors

#[test]
fn vectors_need_a_matrix_of_their_length() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    let bv = |slot, len| Request::BeginVector {
        slot,
        exponent: 0,
        len,
    };
    assert_eq!(
        s.handle(bv(VectorSlot::RHS, 10)),
        ooo(SessionStep::NoMatrix)
    );
    assert_eq!(
        s.handle(Request::VectorData {
            slot: VectorSlot::RHS,
            offset: 0,
            mantissas: chunk(&[1])
        }),
        ooo(SessionStep::NoVectorUpload)
    );
    let e = laplacian(10, 10);
    s.handle(begin(&e));
    assert_eq!(
        s.handle(bv(VectorSlot::RHS, 10)),
        ooo(SessionStep::NoMatrix),
        "an upload is not a matrix"
    );
    load(&mut s, &e);
    assert_eq!(
        s.handle(bv(VectorSlot::RHS, 9)),
        err(ErrorCode::LengthMismatch {
            expected: 10,
            got: 9
        })
    );
    assert_eq!(
        s.handle(bv(VectorSlot::INITIAL_GUESS, u32::MAX)),
        err(ErrorCode::LengthMismatch {
            expected: 10,
            got: u32::MAX
        })
    );
    assert_eq!(s.handle(bv(VectorSlot::INITIAL_GUESS, 10)), Response::Ack);
}

#[test]
fn vector_chunks_are_checked() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    load(&mut s, &laplacian(10, 10));
    let slot = VectorSlot::INITIAL_GUESS;
    let vd = |offset, m: &[i32]| Request::VectorData {
        slot,
        offset,
        mantissas: chunk(m),
    };
    assert_eq!(s.handle(vd(0, &[1])), ooo(SessionStep::NoVectorUpload));
    s.handle(Request::BeginVector {
        slot,
        exponent: -3,
        len: 10,
    });
    // The other slot has no upload.
    assert_eq!(
        s.handle(Request::VectorData {
            slot: VectorSlot::RHS,
            offset: 0,
            mantissas: chunk(&[1])
        }),
        ooo(SessionStep::NoVectorUpload)
    );
    assert_eq!(
        s.handle(vd(2, &[1])),
        err(ErrorCode::UnexpectedOffset {
            expected: 0,
            got: 2
        })
    );
    assert_eq!(s.handle(vd(0, &[0; 11])), err(ErrorCode::ChunkTooLong));
    let limit = 1 << 30;
    assert_eq!(
        s.handle(vd(0, &[1, limit])),
        err(ErrorCode::MantissaOutOfRange)
    );
    assert_eq!(
        s.handle(vd(0, &[-limit])),
        err(ErrorCode::MantissaOutOfRange)
    );
    assert_eq!(
        s.handle(vd(0, &[i32::MIN])),
        err(ErrorCode::MantissaOutOfRange)
    );
    assert_eq!(
        s.handle(vd(0, &[i32::MAX])),
        err(ErrorCode::MantissaOutOfRange)
    );
    assert_eq!(s.handle(vd(0, &[limit - 1, 1 - limit])), Response::Ack);
    assert_eq!(s.handle(vd(2, &[])), Response::Ack);
    assert_eq!(
        s.handle(vd(0, &[1])),
        err(ErrorCode::UnexpectedOffset {
            expected: 2,
            got: 0
        })
    );
    assert_eq!(s.handle(vd(2, &[0; 9])), err(ErrorCode::ChunkTooLong));
    assert_eq!(
        s.handle(solve_req(Start::Uploaded)),
        ooo(SessionStep::NoRhs)
    );
    load_rhs(&mut s, &[1.0; 10]);
    assert_eq!(
        s.handle(solve_req(Start::Uploaded)),
        ooo(SessionStep::VectorIncomplete)
    );
    assert_eq!(s.handle(vd(2, &[0; 8])), Response::Ack);
    // Complete: no more data.
    assert_eq!(s.handle(vd(10, &[0])), ooo(SessionStep::NoVectorUpload));
    // A new BeginVector drops the old vector, even when refused.
    assert_eq!(
        s.handle(Request::BeginVector {
            slot,
            exponent: 0,
            len: 3
        }),
        err(ErrorCode::LengthMismatch {
            expected: 10,
            got: 3
        })
    );
    assert_eq!(
        s.handle(solve_req(Start::Uploaded)),
        ooo(SessionStep::NoInitialGuess)
    );
}

#[test]
fn a_new_matrix_invalidates_the_vectors() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    let e = laplacian(10, 10);
    load(&mut s, &e);
    let (exp, m) = to_block(&[1.0; 10]);
    let mut reqs = vector_requests(VectorSlot::RHS, exp, &m, 4);
    let last = reqs.pop().unwrap();
    all_ack(&mut s, reqs);
    load(&mut s, &e);
    assert_eq!(s.handle(last), ooo(SessionStep::NoVectorUpload));
    assert_eq!(s.handle(solve_req(Start::Zero)), ooo(SessionStep::NoRhs));
}

// ---------------------------------------------------------------------------------------------
// Solve preconditions (no solver call)

#[test]
fn solve_checks_its_inputs_before_touching_anything() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    assert_eq!(s.handle(solve_req(Start::Zero)), ooo(SessionStep::NoMatrix));
    assert_eq!(
        s.handle(Request::ReadSolution {
            direction: 0,
            offset: 0,
            len: CHUNK_LEN as u16
        }),
        ooo(SessionStep::NoSolution)
    );
    load(&mut s, &laplacian(10, 10));
    assert_eq!(s.handle(solve_req(Start::Zero)), ooo(SessionStep::NoRhs));
    let (exp, m) = to_block(&[1.0; 10]);
    let mut reqs = vector_requests(VectorSlot::RHS, exp, &m, 4);
    let last = reqs.pop().unwrap();
    all_ack(&mut s, reqs);
    assert_eq!(
        s.handle(solve_req(Start::Zero)),
        ooo(SessionStep::VectorIncomplete)
    );
    assert_eq!(s.handle(last), Response::Ack);
    assert_eq!(
        s.handle(solve_req(Start::Previous)),
        ooo(SessionStep::NoPreviousSolution)
    );
    assert_eq!(
        s.handle(solve_req(Start::Uploaded)),
        ooo(SessionStep::NoInitialGuess)
    );
    assert_eq!(
        s.handle(Request::ReadSolution {
            direction: 0,
            offset: 0,
            len: CHUNK_LEN as u16
        }),
        ooo(SessionStep::NoSolution)
    );
}

// ---------------------------------------------------------------------------------------------
// Happy paths (these call cg::solve)

#[test]
fn solves_the_1d_laplacian_like_a_direct_solver() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    let n = 10;
    let e = laplacian(n, n);
    assert_eq!(e.tiles.len(), 1);
    all_ack(&mut s, matrix_requests(&e, 8));
    let b: Vec<f64> = (0..n).map(|i| 1.0 + 0.25 * i as f64).collect();
    let (b_exp, b_m) = to_block(&b);
    all_ack(&mut s, vector_requests(VectorSlot::RHS, b_exp, &b_m, 3));
    let report = solved(s.handle(solve_req(Start::Zero)));
    assert!(report.converged, "{report:?}");
    // CG needs n iterations in exact arithmetic; at 1e-9, close to the fixed-point floor,
    // residual replacement may restart it once or twice.
    assert!(report.iterations <= 4 * n as u32, "{report:?}");
    assert_eq!(report.words_per_iteration, e.words.len() as u32);
    let want = direct_solve(
        dense(&e),
        b.iter()
            .enumerate()
            .map(|(i, _)| from_mantissa(b_m[i], b_exp))
            .collect(),
    );
    let got = read_all(&mut s, n);
    assert!(
        max_rel_err(&got, &want) < 1e-6,
        "got {got:?}\nwant {want:?}"
    );
    // Past the end.
    assert_eq!(
        s.handle(Request::ReadSolution {
            direction: 0,
            offset: n as u32,
            len: CHUNK_LEN as u16
        }),
        err(ErrorCode::ChunkTooLong)
    );
    assert_eq!(
        s.handle(Request::ReadSolution {
            direction: 0,
            offset: u32::MAX,
            len: CHUNK_LEN as u16
        }),
        err(ErrorCode::ChunkTooLong)
    );

    // A warm start from the previous solution needs (almost) no iterations to reach a looser
    // tolerance, where a cold start needs several.
    let loose = |start| {
        Request::Solve(SolveParams {
            max_iterations: 1000,
            tolerance: 1e-6,
            start,
            directions: 1,
            cycle_budget: 0,
        })
    };
    assert!(solved(s.handle(loose(Start::Zero))).iterations > 2);
    let warm = solved(s.handle(loose(Start::Previous)));
    assert!(warm.converged && warm.iterations <= 2, "{warm:?}");
    assert!(max_rel_err(&read_all(&mut s, n), &want) < 1e-6);

    // An uploaded initial guess (the exact solution) likewise.
    let (x_exp, x_m) = to_block(&want);
    all_ack(
        &mut s,
        vector_requests(VectorSlot::INITIAL_GUESS, x_exp, &x_m, 64),
    );
    let guessed = solved(s.handle(loose(Start::Uploaded)));
    assert!(guessed.converged && guessed.iterations <= 2, "{guessed:?}");
    assert!(max_rel_err(&read_all(&mut s, n), &want) < 1e-6);

    // A new right-hand side keeps the solution; the matrix stays resident.
    let b2: Vec<f64> = (0..n).map(|i| if i == 3 { -5.0 } else { 0.0 }).collect();
    load_rhs(&mut s, &b2);
    assert!(matches!(
        s.handle(Request::ReadSolution {
            direction: 0,
            offset: 0,
            len: CHUNK_LEN as u16
        }),
        Response::Solution { .. }
    ));
    assert!(solved(s.handle(solve_req(Start::Previous))).converged);
    let want2 = direct_solve(dense(&e), b2.clone());
    assert!(max_rel_err(&read_all(&mut s, n), &want2) < 1e-6);
}

#[test]
fn solves_a_matrix_of_several_tiles_sent_in_many_chunks() {
    let n = 600;
    let mut bufs = OwnedStorage::new(2000, 8, n);
    let mut s = bufs.session(info(), HARTS.harts);
    // Rows split 250/250/100, each tile's column window starting one column before its rows.
    let e = laplacian(n, 250);
    assert_eq!(e.tiles.len(), 3);
    assert_eq!(e.tiles[1].col_base, 249);
    all_ack(&mut s, matrix_requests(&e, 64));
    let b: Vec<f64> = (0..n).map(|i| ((i * 7919) % 13) as f64 - 6.0).collect();
    load_rhs(&mut s, &b);
    let r = s.handle(Request::Solve(SolveParams {
        max_iterations: 5000,
        tolerance: 1e-10,
        start: Start::Zero,
        directions: 1,
        cycle_budget: 0,
    }));
    let report = solved(r);
    assert!(report.converged, "{report:?}");
    let (b_exp, b_m) = to_block(&b);
    let bq: Vec<f64> = b_m.iter().map(|&m| from_mantissa(m, b_exp)).collect();
    let want = direct_solve(dense(&e), bq);
    let got = read_all(&mut s, n);
    assert!(
        max_rel_err(&got, &want) < 1e-5,
        "{}",
        max_rel_err(&got, &want)
    );
}

#[test]
fn rows_split_between_tiles_add_up() {
    // The Laplacian's lower part and diagonal in one tile, its upper part in another.
    let n = 10;
    let lower = encode(n, n, 18, |i| {
        laplacian_row(n)(i)
            .into_iter()
            .filter(|&(c, _)| c <= i)
            .collect()
    });
    let upper = encode(n, n, 18, |i| {
        laplacian_row(n)(i)
            .into_iter()
            .filter(|&(c, _)| c > i)
            .collect()
    });
    let mut e = lower.clone();
    e.tiles.extend(&upper.tiles);
    e.words.extend(&upper.words);
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    all_ack(&mut s, matrix_requests(&e, 5));
    load_rhs(&mut s, &[1.0; 10]);
    assert!(solved(s.handle(solve_req(Start::Zero))).converged);
    // x_i = (i+1)(n-i)/2 for b = 1.
    let want: Vec<f64> = (0..n).map(|i| ((i + 1) * (n - i)) as f64 / 2.0).collect();
    assert!(max_rel_err(&read_all(&mut s, n), &want) < 1e-6);
}

#[test]
fn a_failed_solve_leaves_no_solution() {
    let n = 10;
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    load(&mut s, &laplacian(n, n));
    load_rhs(&mut s, &[1.0; 10]);
    assert!(solved(s.handle(solve_req(Start::Zero))).converged);
    // −L is negative definite.
    let neg = encode(n, n, 18, |i| {
        laplacian_row(n)(i)
            .into_iter()
            .map(|(c, v)| (c, -v))
            .collect()
    });
    load(&mut s, &neg);
    load_rhs(&mut s, &[1.0; 10]);
    let r = s.handle(solve_req(Start::Zero));
    assert!(
        matches!(
            r,
            Response::Error(ErrorCode::Solve(SolveFailure::NotPositiveDefinite { .. }))
        ),
        "{r:?}"
    );
    assert_eq!(
        s.handle(Request::ReadSolution {
            direction: 0,
            offset: 0,
            len: CHUNK_LEN as u16
        }),
        ooo(SessionStep::NoSolution)
    );
    assert_eq!(
        s.handle(solve_req(Start::Previous)),
        ooo(SessionStep::NoPreviousSolution)
    );
}

// ---------------------------------------------------------------------------------------------
// Random request sequences

/// Numbers that are mostly small (so that requests often fit the state), sometimes huge.
fn num(small: u32) -> impl Strategy<Value = u32> {
    prop_oneof![6 => 0..=small, 1 => any::<u32>(), 1 => Just(u32::MAX)]
}

fn slot() -> impl Strategy<Value = VectorSlot> {
    prop_oneof![
        (0u8..4).prop_map(|direction| VectorSlot::Rhs { direction }),
        (0u8..4).prop_map(|direction| VectorSlot::InitialGuess { direction }),
    ]
}

fn start() -> impl Strategy<Value = Start> {
    prop_oneof![
        Just(Start::Zero),
        Just(Start::Previous),
        Just(Start::Uploaded),
        Just(Start::Predicted)
    ]
}

fn any_word() -> impl Strategy<Value = u32> {
    prop_oneof![
        any::<u32>(),
        // Small columns and values, sometimes ER/EM: words that may validate.
        (0u32..12, -8i64..8, any::<bool>(), prop::bool::weighted(0.2))
            .prop_map(|(c, v, er, em)| Word::new(c, v, er, em).unwrap().bits()),
    ]
}

fn mantissa() -> impl Strategy<Value = i32> {
    prop_oneof![100 => -1000i32..1000, 1 => any::<i32>(), 1 => Just((1 << 30) - 1)]
}

fn raw_request() -> impl Strategy<Value = Request> {
    prop_oneof![
        prop_oneof![3 => Just(PROTOCOL_VERSION), 1 => any::<u16>()]
            .prop_map(|protocol_version| Request::Hello { protocol_version }),
        (num(12), 0u8..24, num(4), num(40)).prop_map(|(n, frac_bits, tiles, words)| {
            Request::BeginMatrix {
                n,
                frac_bits,
                tiles,
                words,
            }
        }),
        (num(12), num(12), num(12), num(40)).prop_map(|(row_base, col_base, rows, words)| {
            Request::Tile(TileHeader {
                row_base,
                col_base,
                rows,
                words,
                mvu: (row_base % 3) as u8,
                mirrored: col_base % 2 == 1,
            })
        }),
        (num(40), prop::collection::vec(any_word(), 0..=CHUNK_LEN)).prop_map(|(offset, w)| {
            Request::Words {
                offset,
                words: chunk(&w),
            }
        }),
        any::<u32>().prop_map(|crc32| Request::EndMatrix { crc32 }),
        (slot(), any::<i32>(), num(12)).prop_map(|(slot, exponent, len)| Request::BeginVector {
            slot,
            exponent,
            len
        }),
        (
            slot(),
            num(12),
            prop::collection::vec(mantissa(), 0..=CHUNK_LEN)
        )
            .prop_map(|(slot, offset, m)| Request::VectorData {
                slot,
                offset,
                mantissas: chunk(&m)
            }),
        (0u32..40, prop_oneof![Just(1e-6), any::<f64>()], start()).prop_map(
            |(max_iterations, tolerance, start)| Request::Solve(SolveParams {
                max_iterations,
                tolerance,
                start,
                directions: 1,
                cycle_budget: 0,
            })
        ),
        (0u8..4, num(12)).prop_map(|(direction, offset)| Request::ReadSolution {
            direction,
            offset,
            len: CHUNK_LEN as u16
        }),
        (
            prop_oneof![
                Just(StateVector::Rhs),
                Just(StateVector::Velocity),
                Just(StateVector::Residual)
            ],
            0u8..4,
            num(12),
            1u16..
        )
            .prop_map(|(vector, direction, offset, len)| Request::ReadVector {
                vector,
                direction,
                offset,
                len
            }),
        (num(40), 0u8..24).prop_map(|(words, frac_bits)| Request::BeginUpdate { words, frac_bits }),
        (
            num(40),
            prop::collection::vec(prop_oneof![8 => -8i32..8, 1 => any::<i32>()], 0..=CHUNK_LEN)
        )
            .prop_map(|(offset, v)| Request::UpdateValues {
                offset,
                values: chunk(&v)
            }),
        any::<u32>().prop_map(|crc32| Request::EndUpdate { crc32 }),
        prop::collection::vec(num(12), 0..=3).prop_map(|n| Request::LiveForceTool {
            nodes: n.into_iter().collect()
        }),
        (prop_oneof![Just(1e-4f32), any::<f32>()], 0u32..40).prop_map(
            |(tolerance, max_iterations)| Request::LiveStart(deform_shared::live::LiveParams {
                tolerance,
                max_iterations,
                cycle_budget: 0,
                scale: [1.0, 2.0, 0.5],
            })
        ),
        prop::collection::vec(any::<[f32; 3]>(), 0..=3).prop_map(|l| Request::LiveLoad {
            load: l.into_iter().collect()
        }),
        prop::collection::vec(any::<[f32; 3]>(), 0..=3).prop_map(|l| Request::LiveLoadQuery {
            load: l.into_iter().collect()
        }),
    ]
}

/// A step of a random session: one raw request, or a well-formed upload that random requests
/// then interleave with and corrupt (it may stop early).
#[derive(Debug, Clone)]
// A step is short-lived test data; boxing the request would only obscure the strategies.
#[allow(clippy::large_enum_variant)]
enum Step {
    Raw(Request),
    Matrix {
        e: Encoded,
        chunk_len: usize,
        stop_after: usize,
    },
    /// A vector of the last uploaded matrix's length (`len: None`) or of the given length.
    Vector {
        slot: VectorSlot,
        exponent: i32,
        m: Vec<i32>,
        len: Option<usize>,
        chunk_len: usize,
        stop_after: usize,
    },
    /// A values-only update to `e`'s values (it fits the resident matrix only if that has
    /// `e`'s pattern).
    Update {
        e: Encoded,
        chunk_len: usize,
        stop_after: usize,
    },
}

/// A diagonally dominant (so SPD) symmetric band matrix, or its negation.
fn spd(n: usize, rows_per_tile: usize, off: f64, negate: bool) -> Encoded {
    let sign = if negate { -1.0 } else { 1.0 };
    encode(n, rows_per_tile, 16, move |i| {
        let mut r = Vec::new();
        if i > 0 {
            r.push((i - 1, sign * off));
        }
        r.push((i, sign * 3.0));
        if i + 1 < n {
            r.push((i + 1, sign * off));
        }
        r
    })
}

/// Stops an upload after `stop` requests now and then, else lets it finish.
fn stop_after(stop: usize) -> usize {
    if stop >= 6 {
        usize::MAX
    } else {
        stop * 3
    }
}

fn step() -> impl Strategy<Value = Step> {
    let matrix = (
        1usize..=12,
        3usize..=12,
        -1.0f64..1.0,
        prop::bool::weighted(0.1),
        1usize..=8,
        0usize..20,
    )
        .prop_map(|(n, rows, off, negate, chunk_len, stop)| Step::Matrix {
            e: spd(n, rows, off, negate),
            chunk_len,
            stop_after: stop_after(stop),
        });
    let vector = (
        slot(),
        -40i32..10,
        prop::collection::vec(mantissa(), 13),
        prop_oneof![8 => Just(None), 1 => (0usize..=13).prop_map(Some)],
        1usize..=8,
        0usize..20,
    )
        .prop_map(|(slot, exponent, m, len, chunk_len, stop)| Step::Vector {
            slot,
            exponent,
            m,
            len,
            chunk_len,
            stop_after: stop_after(stop),
        });
    let solve = (
        0u32..40,
        prop_oneof![4 => Just(1e-6), 1 => any::<f64>()],
        start(),
    )
        .prop_map(|(max_iterations, tolerance, start)| {
            Step::Raw(Request::Solve(SolveParams {
                max_iterations,
                tolerance,
                start,
                directions: 1,
                cycle_budget: 0,
            }))
        });
    let read = (0u8..4, 0u32..14).prop_map(|(direction, offset)| {
        Step::Raw(Request::ReadSolution {
            direction,
            offset,
            len: CHUNK_LEN as u16,
        })
    });
    let update = (
        1usize..=12,
        3usize..=12,
        -1.0f64..1.0,
        1usize..=8,
        0usize..20,
    )
        .prop_map(|(n, rows, off, chunk_len, stop)| Step::Update {
            e: spd(n, rows, off, false),
            chunk_len,
            stop_after: stop_after(stop),
        });
    prop_oneof![
        2 => update,
        6 => raw_request().prop_map(Step::Raw),
        1 => Just(Step::Raw(Request::Hello { protocol_version: PROTOCOL_VERSION })),
        3 => matrix,
        4 => vector,
        3 => solve,
        2 => read,
    ]
}

/// The requests of `step`; `n` tracks the dimension of the last matrix upload begun.
fn expand(step: Step, n: &mut usize) -> Vec<Request> {
    match step {
        Step::Raw(r) => vec![r],
        Step::Matrix {
            e,
            chunk_len,
            stop_after,
        } => {
            *n = e.n as usize;
            matrix_requests(&e, chunk_len)
                .into_iter()
                .take(stop_after)
                .collect()
        }
        Step::Vector {
            slot,
            exponent,
            m,
            len,
            chunk_len,
            stop_after,
        } => {
            let len = len.unwrap_or(*n).min(m.len());
            vector_requests(slot, exponent, &m[..len], chunk_len)
                .into_iter()
                .take(stop_after)
                .collect()
        }
        Step::Update {
            e,
            chunk_len,
            stop_after,
        } => update_requests(&e, chunk_len)
            .into_iter()
            .take(stop_after)
            .collect(),
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]

    #[test]
    fn random_request_sequences_never_panic(steps in prop::collection::vec(step(), 0..40)) {
        // Small buffers: capacities are hit often.
        let mut bufs = OwnedStorage::new(40, 4, 12);
        let mut s = bufs.session(info(), HARTS.harts);
        let mut frame = [0u8; MAX_FRAME_LEN];
        let mut n = 0;
        for req in steps.into_iter().flat_map(|step| expand(step, &mut n)) {
            let was_read = matches!(req, Request::ReadSolution { .. } | Request::ReadVector { .. });
            let response = s.handle(req);
            // Every answer fits a frame.
            let envelope = Envelope { seq: 0, body: response.clone() };
            prop_assert!(frame::encode(&envelope, &mut frame).is_ok(), "{:?}", response);
            if let Response::Solution { offset, mantissas, .. } = &response {
                prop_assert!(was_read);
                prop_assert!(!mantissas.is_empty() && (*offset as usize) < 12);
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Values-only update

/// The 1-D matrix tridiag(−off, d, −off) with the Laplacian's pattern, `frac_bits` fractional bits.
fn band(n: usize, rows_per_tile: usize, frac_bits: u8, d: f64, off: f64) -> Encoded {
    encode(n, rows_per_tile, frac_bits, move |i| {
        let mut r = Vec::new();
        if i > 0 {
            r.push((i - 1, -off));
        }
        r.push((i, d));
        if i + 1 < n {
            r.push((i + 1, -off));
        }
        r
    })
}

#[test]
fn a_solve_after_an_update_equals_one_after_a_fresh_upload() {
    let n = 100;
    let old = band(n, 30, 18, 2.0, 1.0);
    // Other values, another Q-format, the same pattern.
    let new = band(n, 30, 16, 5.5, 1.75);
    assert_eq!(old.tiles, new.tiles);
    let b: Vec<f64> = (0..n).map(|i| 1.0 + (i as f64 * 0.3).cos()).collect();

    let mut fresh_bufs = OwnedStorage::new(400, 8, n);
    let mut fresh = fresh_bufs.session(info(), HARTS.harts);
    load(&mut fresh, &new);
    load_rhs(&mut fresh, &b);
    let fresh_report = solved(fresh.handle(solve_req(Start::Zero)));
    let fresh_x = read_all(&mut fresh, n);

    let mut bufs = OwnedStorage::new(400, 8, n);
    let mut s = bufs.session(info(), HARTS.harts);
    load(&mut s, &old);
    load_rhs(&mut s, &b);
    solved(s.handle(solve_req(Start::Zero)));
    all_ack(&mut s, update_requests(&new, 7));
    // The rhs survived the update, and the stored words are now the fresh upload's.
    let report = solved(s.handle(solve_req(Start::Zero)));
    let x = read_all(&mut s, n);
    assert_eq!(report, fresh_report);
    assert_eq!(x, fresh_x);
    drop(s);
    assert_eq!(bufs.words[..new.words.len()], new.words[..]);
    assert!(max_rel_err(&x, &direct_solve(dense(&new), b.clone())) < 1e-6);
}

#[test]
fn the_previous_solution_survives_an_update_for_a_warm_start() {
    let n = 40;
    let old = band(n, 40, 18, 3.0, 1.0);
    let new = band(n, 40, 18, 3.03, 1.01);
    let b: Vec<f64> = (0..n).map(|i| (i as f64 * 0.2).sin() + 1.5).collect();
    let mut bufs = OwnedStorage::new(200, 4, n);
    let mut s = bufs.session(info(), HARTS.harts);
    load(&mut s, &old);
    load_rhs(&mut s, &b);
    solved(s.handle(solve_req(Start::Zero)));
    all_ack(&mut s, update_requests(&new, CHUNK_LEN));
    let cold = solved(s.handle(solve_req(Start::Zero)));
    let cold_x = read_all(&mut s, n);
    // Rewind to the old solution and warm-start from it after updating again.
    all_ack(&mut s, update_requests(&old, CHUNK_LEN));
    solved(s.handle(solve_req(Start::Zero)));
    all_ack(&mut s, update_requests(&new, CHUNK_LEN));
    let warm = solved(s.handle(solve_req(Start::Previous)));
    let warm_x = read_all(&mut s, n);
    assert!(warm.iterations < cold.iterations, "{warm:?} vs {cold:?}");
    assert!(max_rel_err(&warm_x, &cold_x) < 1e-6);
}

#[test]
fn an_update_needs_a_resident_matrix_of_its_word_count() {
    let e = band(10, 10, 18, 2.0, 1.0);
    let words = e.words.len() as u32;
    let mut bufs = OwnedStorage::new(100, 4, 10);
    let mut s = bufs.session(info(), HARTS.harts);
    let begin_update = |words, frac_bits| Request::BeginUpdate { words, frac_bits };
    assert_eq!(
        s.handle(begin_update(words, 18)),
        ooo(SessionStep::NoMatrix)
    );
    assert_eq!(
        s.handle(Request::UpdateValues {
            offset: 0,
            values: chunk(&[1])
        }),
        ooo(SessionStep::NoUpdate)
    );
    assert_eq!(
        s.handle(Request::EndUpdate { crc32: 0 }),
        ooo(SessionStep::NoUpdate)
    );
    // Mid-upload is not resident either.
    s.handle(begin(&e));
    assert_eq!(
        s.handle(begin_update(words, 18)),
        ooo(SessionStep::NoMatrix)
    );
    load(&mut s, &e);
    assert_eq!(
        s.handle(begin_update(words + 1, 18)),
        err(ErrorCode::Matrix(MatrixError::TotalWordsMismatch {
            expected: words,
            found: words + 1
        }))
    );
    assert_eq!(
        s.handle(begin_update(words, 21)),
        err(ErrorCode::BadFracBits(21))
    );
    // Refused: the matrix is still loaded and solvable.
    load_rhs(&mut s, &[1.0; 10]);
    solved(s.handle(solve_req(Start::Zero)));
}

#[test]
fn update_chunks_are_checked_and_a_refused_chunk_writes_nothing() {
    let e = band(10, 10, 18, 2.0, 1.0);
    let words = e.words.len();
    let mut bufs = OwnedStorage::new(100, 4, 10);
    let mut s = bufs.session(info(), HARTS.harts);
    load(&mut s, &e);
    load_rhs(&mut s, &[1.0; 10]);
    solved(s.handle(solve_req(Start::Zero)));
    assert_eq!(
        s.handle(Request::BeginUpdate {
            words: words as u32,
            frac_bits: 18
        }),
        Response::Ack
    );
    let values: Vec<i32> = e.words.iter().map(|&w| Word(w).raw_value()).collect();
    let values_at = |offset: usize, v: &[i32]| Request::UpdateValues {
        offset: offset as u32,
        values: chunk(v),
    };
    assert_eq!(
        s.handle(values_at(1, &values[1..3])),
        err(ErrorCode::UnexpectedOffset {
            expected: 0,
            got: 1
        })
    );
    let mut bad = values[..4].to_vec();
    bad[2] = VALUE_MAX + 1;
    assert_eq!(
        s.handle(values_at(0, &bad)),
        err(ErrorCode::ValueOutOfRange(VALUE_MAX + 1))
    );
    bad[2] = VALUE_MIN - 1;
    assert_eq!(
        s.handle(values_at(0, &bad)),
        err(ErrorCode::ValueOutOfRange(VALUE_MIN - 1))
    );
    assert_eq!(s.handle(values_at(0, &values[..4])), Response::Ack);
    assert_eq!(s.handle(values_at(4, &[])), Response::Ack);
    // During the update: no solve, no early end; vectors and the solution stay available.
    assert_eq!(
        s.handle(solve_req(Start::Zero)),
        ooo(SessionStep::UpdateIncomplete)
    );
    assert_eq!(
        s.handle(Request::EndUpdate {
            crc32: words_crc(&e.words)
        }),
        ooo(SessionStep::UpdateIncomplete)
    );
    assert_eq!(read_all(&mut s, 10).len(), 10);
    load_rhs(&mut s, &[2.0; 10]);
    let mut long = values[4..].to_vec();
    long.push(0);
    assert_eq!(s.handle(values_at(4, &long)), err(ErrorCode::ChunkTooLong));
    assert_eq!(s.handle(values_at(4, &values[4..])), Response::Ack);
    assert_eq!(
        s.handle(Request::EndUpdate {
            crc32: words_crc(&e.words)
        }),
        Response::Ack
    );
    drop(s);
    assert_eq!(
        bufs.words[..words],
        e.words[..],
        "nothing refused was written"
    );
}

#[test]
fn an_update_keeps_em_er_and_columns_and_a_crc_mismatch_drops_the_matrix() {
    let e = band(10, 4, 18, 2.0, 1.0);
    let words = e.words.len();
    let mut bufs = OwnedStorage::new(100, 4, 10);
    let mut s = bufs.session(info(), HARTS.harts);
    load(&mut s, &e);
    load_rhs(&mut s, &[1.0; 10]);
    // All-ones value fields (-1 raw): the flags and columns must survive.
    let mut reqs = update_requests(&e, 5);
    for r in &mut reqs {
        if let Request::UpdateValues { values, .. } = r {
            values.iter_mut().for_each(|v| *v = -1);
        }
    }
    let expected: Vec<u32> = e.words.iter().map(|&w| w | VALUE_MASK).collect();
    let last = reqs.len() - 1;
    reqs[last] = Request::EndUpdate {
        crc32: words_crc(&expected),
    };
    all_ack(&mut s, reqs);
    // A wrong CRC: the matrix and its vectors are gone.
    all_ack(&mut s, update_requests(&e, 5)[..last].to_vec());
    let computed = words_crc(&e.words);
    assert_eq!(
        s.handle(Request::EndUpdate { crc32: 0 }),
        err(ErrorCode::MatrixCrc { computed })
    );
    assert_eq!(s.handle(solve_req(Start::Zero)), ooo(SessionStep::NoMatrix));
    assert_eq!(
        s.handle(Request::BeginVector {
            slot: VectorSlot::RHS,
            exponent: 0,
            len: 10
        }),
        ooo(SessionStep::NoMatrix)
    );
    drop(s);
    assert_eq!(bufs.words[..words], e.words[..]);
}

// ---------------------------------------------------------------------------------------------
// Protocol version 4: directions, MVU assignment, mirrored tiles

fn load_direction(s: &mut Session<'_, Sequential>, direction: u8, b: &[f64]) {
    let (e, m) = to_block(b);
    all_ack(
        s,
        vector_requests(VectorSlot::Rhs { direction }, e, &m, CHUNK_LEN),
    );
}

fn fused_req(directions: u8) -> Request {
    Request::Solve(SolveParams {
        max_iterations: 1000,
        tolerance: 1e-9,
        start: Start::Zero,
        directions,
        cycle_budget: 0,
    })
}

#[test]
fn a_fused_solve_equals_separate_solves_per_direction() {
    let n = 40;
    let e = laplacian(n, 16);
    let rhs: Vec<Vec<f64>> = (0..3)
        .map(|d| (0..n).map(|i| ((i * (d + 3)) % 7) as f64 - 3.0).collect())
        .collect();
    let mut bufs = OwnedStorage::new(1000, 10, 64);
    let mut s = bufs.session(info(), HARTS.harts);
    load(&mut s, &e);
    let mut singles = Vec::new();
    for b in &rhs {
        load_rhs(&mut s, b);
        let report = solved(s.handle(solve_req(Start::Zero)));
        singles.push((report.directions[0], read_all(&mut s, n)));
    }
    for (d, b) in rhs.iter().enumerate() {
        load_direction(&mut s, d as u8, b);
    }
    let report = solved(s.handle(fused_req(3)));
    assert_eq!(report.directions.len(), 3);
    for (d, (single, x)) in singles.iter().enumerate() {
        assert_eq!(&report.directions[d], single);
        assert_eq!(&read_direction(&mut s, d as u8, n), x, "direction {d}");
    }
    assert_eq!(
        report.iterations,
        singles.iter().map(|s| s.0.iterations).max().unwrap()
    );
    assert!(report.converged);
    let want = direct_solve(dense(&e), rhs[2].clone());
    let got = read_direction(&mut s, 2, n);
    let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(got
        .iter()
        .zip(&want)
        .all(|(a, b)| (a - b).abs() < 1e-6 * scale));
}

#[test]
fn directions_beyond_the_fused_count_are_refused() {
    let e = laplacian(8, 8);
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    load(&mut s, &e);
    let out_of_range = err(ErrorCode::DirectionOutOfRange {
        direction: 3,
        max: 3,
    });
    let slot = VectorSlot::Rhs { direction: 3 };
    assert_eq!(
        s.handle(Request::BeginVector {
            slot,
            exponent: 0,
            len: 8
        }),
        out_of_range
    );
    assert_eq!(
        s.handle(Request::ReadSolution {
            direction: 3,
            offset: 0,
            len: CHUNK_LEN as u16
        }),
        out_of_range
    );
    load_direction(&mut s, 0, &[1.0; 8]);
    for bad in [0, 4, 255] {
        assert_eq!(
            s.handle(fused_req(bad)),
            err(ErrorCode::Solve(SolveFailure::BadDirections(bad)))
        );
    }
    // Direction 1 has no right-hand side yet.
    assert_eq!(s.handle(fused_req(2)), ooo(SessionStep::NoRhs));
    load_direction(&mut s, 1, &[2.0; 8]);
    let report = solved(s.handle(fused_req(2)));
    assert_eq!(report.directions.len(), 2);
    // Only solved directions have a solution.
    assert_eq!(
        s.handle(Request::ReadSolution {
            direction: 2,
            offset: 0,
            len: CHUNK_LEN as u16
        }),
        ooo(SessionStep::NoSolution)
    );
    let x0 = read_direction(&mut s, 0, 8);
    let x1 = read_direction(&mut s, 1, 8);
    for (a, b) in x0.iter().zip(&x1) {
        assert!((2.0 * a - b).abs() < 1e-6 * b.abs(), "{a} {b}");
    }
}

#[test]
fn a_tile_for_a_missing_hart_is_refused() {
    let mut e = laplacian(8, 4);
    e.tiles[1].mvu = 1;
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    let mut reqs = matrix_requests(&e, CHUNK_LEN).into_iter();
    for req in reqs.by_ref().take(3) {
        assert_eq!(s.handle(req), Response::Ack);
    }
    assert_eq!(
        s.handle(reqs.next().unwrap()),
        err(ErrorCode::Matrix(MatrixError::MvuOutOfRange {
            tile: 1,
            mvu: 1,
            harts: 1
        }))
    );
}

#[test]
fn a_mirrored_half_solves_like_the_whole_persymmetric_matrix() {
    // tridiag(-1, 2, -1) of order 10 is persymmetric: rows 0..5 with mirrored = true stand for
    // all ten rows.
    let n = 10;
    let whole = laplacian(n, 10);
    let mut half = encode(n, 5, 18, laplacian_row(n));
    half.tiles.truncate(1);
    half.tiles[0].mirrored = true;
    half.words.truncate(half.tiles[0].words as usize);
    let b: Vec<f64> = (0..n).map(|i| 1.0 + i as f64).collect();
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    load(&mut s, &whole);
    load_rhs(&mut s, &b);
    solved(s.handle(solve_req(Start::Zero)));
    let want = read_all(&mut s, n);
    load(&mut s, &half);
    load_rhs(&mut s, &b);
    let report = solved(s.handle(solve_req(Start::Zero)));
    assert_eq!(report.words_per_iteration, half.words.len() as u32);
    let got = read_all(&mut s, n);
    let exact = direct_solve(dense(&whole), b);
    for ((g, w), x) in got.iter().zip(&want).zip(&exact) {
        assert!((g - x).abs() < 1e-6 * x.abs(), "{g} vs exact {x}");
        assert!((w - x).abs() < 1e-6 * x.abs(), "{w} vs exact {x}");
    }
}

/// `ReadSolution.len` (protocol 6) bounds the answer: a noisy line asks for short ones.
#[test]
fn a_solution_answer_holds_at_most_len_elements() {
    let mut bufs = OwnedStorage::new(100, 4, 16);
    let mut s = bufs.session(info(), HARTS.harts);
    let n = 10;
    load(&mut s, &laplacian(n, 10));
    load_rhs(&mut s, &[1.0; 10]);
    assert!(matches!(
        s.handle(solve_req(Start::Zero)),
        Response::Solved(_)
    ));
    let whole = read_all(&mut s, n);
    for (offset, len, expect) in [(0, 3, 3), (8, 5, 2), (0, 0, 0), (4, u16::MAX, 6)] {
        let Response::Solution {
            mantissas,
            exponent,
            ..
        } = s.handle(Request::ReadSolution {
            direction: 0,
            offset,
            len,
        })
        else {
            panic!("no Solution for offset {offset}, len {len}")
        };
        assert_eq!(mantissas.len(), expect, "offset {offset}, len {len}");
        let got: Vec<f64> = mantissas
            .iter()
            .map(|&m| from_mantissa(m, exponent))
            .collect();
        assert_eq!(got[..], whole[offset as usize..][..expect]);
    }
}

mod dynamic;
mod estimate;
mod force_tool;
mod live;
mod predicted;
