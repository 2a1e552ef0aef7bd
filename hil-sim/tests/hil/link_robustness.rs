//! The firmware answers every out-of-order or malformed request with a typed error, over the
//! real link, and neither panics nor loses the session: afterwards it solves as usual. Needs
//! the firmware ELF and QEMU, like `qemu_board.rs`.

use crate::support;

use deform_host::link::LinkError;
use deform_shared::matrix::{words_crc, TileHeader};
use deform_shared::protocol::{
    ErrorCode, Request, SessionStep, SolveParams, Start, VectorSlot, CHUNK_LEN,
};

use support::*;

fn refused(target: &mut deform_host::link::Target, request: Request) -> ErrorCode {
    match target.link_mut().request(&request) {
        Err(LinkError::Target { code, .. }) => code,
        other => panic!("{request:?} was not refused: {other:?}"),
    }
}

#[test]
fn out_of_order_and_malformed_requests_get_typed_errors_and_no_panic() {
    let mut qemu = boot();
    let mut target = connect(&qemu);
    let info = target.info().clone();
    let solve = Request::Solve(SolveParams {
        max_iterations: 10,
        tolerance: 1e-6,
        start: Start::Zero,
        directions: 1,
        cycle_budget: 0,
    });
    assert_eq!(
        refused(&mut target, solve.clone()),
        ErrorCode::OutOfOrder(SessionStep::NoMatrix)
    );
    assert_eq!(
        refused(
            &mut target,
            Request::ReadSolution {
                direction: 0,
                offset: 0,
                len: CHUNK_LEN as u16
            }
        ),
        ErrorCode::OutOfOrder(SessionStep::NoSolution)
    );
    assert_eq!(
        refused(
            &mut target,
            Request::Words {
                offset: 0,
                words: [1u32].into_iter().collect(),
            }
        ),
        ErrorCode::OutOfOrder(SessionStep::NoMatrixUpload)
    );
    assert_eq!(
        refused(
            &mut target,
            Request::BeginMatrix {
                n: 8,
                frac_bits: 18,
                tiles: 1,
                words: info.word_capacity + 1,
            }
        ),
        ErrorCode::TooManyWords {
            requested: info.word_capacity + 1,
            capacity: info.word_capacity
        }
    );

    // A real matrix, then a chunk beyond its announced size and a wrong total CRC.
    let matrix = banded_spd(8, 1);
    let link = target.link_mut();
    link.request(&Request::BeginMatrix {
        n: matrix.n,
        frac_bits: matrix.frac_bits,
        tiles: 1,
        words: matrix.words.len() as u32,
    })
    .unwrap();
    let header: TileHeader = matrix.tiles[0];
    link.request(&Request::Tile(header)).unwrap();
    assert!(matrix.words.len() <= CHUNK_LEN);
    let too_long = matrix.words.iter().copied().chain([0, 0]).collect();
    assert_eq!(
        refused(
            &mut target,
            Request::Words {
                offset: 0,
                words: too_long,
            }
        ),
        ErrorCode::ChunkTooLong
    );
    assert_eq!(
        refused(
            &mut target,
            Request::Words {
                offset: 3,
                words: matrix.words.iter().copied().collect(),
            }
        ),
        ErrorCode::UnexpectedOffset {
            expected: 0,
            got: 3
        }
    );
    target
        .link_mut()
        .request(&Request::Words {
            offset: 0,
            words: matrix.words.iter().copied().collect(),
        })
        .unwrap();
    let wrong = words_crc(&matrix.words) ^ 1;
    assert!(matches!(
        refused(&mut target, Request::EndMatrix { crc32: wrong }),
        ErrorCode::MatrixCrc { .. }
    ));
    // The bad CRC dropped the matrix: solving is out of order again, vectors too.
    assert_eq!(
        refused(&mut target, solve),
        ErrorCode::OutOfOrder(SessionStep::NoMatrix)
    );
    assert_eq!(
        refused(
            &mut target,
            Request::BeginVector {
                slot: VectorSlot::RHS,
                exponent: 0,
                len: 8,
            }
        ),
        ErrorCode::OutOfOrder(SessionStep::NoMatrix)
    );
    assert_alive(&mut qemu);

    // And the session still works.
    target.upload_matrix(&matrix).unwrap();
    let (report, _) = target
        .solve_for(
            &[1.0; 8],
            SolveParams {
                max_iterations: 100,
                tolerance: 1e-9,
                start: Start::Zero,
                directions: 1,
                cycle_budget: 0,
            },
        )
        .unwrap();
    assert!(report.converged, "{report:?}");
    assert_alive(&mut qemu);
}
