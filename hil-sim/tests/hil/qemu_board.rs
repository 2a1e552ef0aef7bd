//! The firmware on QEMU, driven through its pty by the host's own serial client: the same code
//! path as a real board. These tests need the firmware ELF (`cargo xtask firmware`, or
//! `$DEFORM_FIRMWARE`) and `qemu-system-riscv32` (`cargo xtask setup`); without them they fail
//! with a message saying so.

use crate::support;

use deform_host::link::{Capacity, Link, LinkError, Target};
use deform_shared::frame;
use deform_shared::protocol::{
    Envelope, Request, SolveParams, Start, VectorSlot, CHUNK_LEN, MAX_FRAME_LEN, PROTOCOL_VERSION,
};

use support::*;

#[test]
fn boots_and_shakes_hands() {
    let mut qemu = boot();
    let target = connect(&qemu);
    let info = target.info();
    assert_eq!(info.protocol_version, PROTOCOL_VERSION);
    assert!(info.harts >= 1, "{info:?}");
    assert!(
        info.word_capacity > 0 && info.tile_capacity > 0 && info.max_n > 0,
        "{info:?}"
    );
    assert!(!info.firmware_version.is_empty(), "{info:?}");
    assert_alive(&mut qemu);
}

#[test]
fn a_second_host_session_can_follow_the_first() {
    let mut qemu = boot();
    let mut first = connect(&qemu);
    first.upload_matrix(&banded_spd(32, 1)).unwrap();
    // Leave mid-session with an upload half done, as a crashed host would.
    first
        .link_mut()
        .request(&Request::BeginMatrix {
            n: 32,
            frac_bits: 18,
            tiles: 1,
            words: 94,
        })
        .unwrap();
    drop(first);
    // Long enough for QEMU to see the pty closed: it then drops the firmware's output and polls
    // for a new reader only once a second, the state a board is in between two CLI runs.
    std::thread::sleep(std::time::Duration::from_millis(1500));

    let mut second = connect(&qemu);
    let matrix = banded_spd(32, 1);
    second.upload_matrix(&matrix).unwrap();
    let (report, x) = second.solve_for(&[1.0; 32], solve_params()).unwrap();
    assert!(report.converged, "{report:?}");
    let err = max_relative_error(&x, &cholesky_solve(&decode_dense(&matrix), &[1.0; 32]));
    assert!(err < 1e-5, "max relative error {err:e}");
    assert_alive(&mut qemu);
}

#[test]
fn line_noise_neither_crashes_nor_confuses_the_firmware() {
    let mut qemu = boot();
    let pty = qemu.pty_path().to_str().unwrap().to_owned();
    let mut link = Link::open(&pty)
        .expect("open the pty")
        .with_timeout(timeouts().request);
    let mut noise = Noise::new(0x5EED_DEF0);

    // Random bytes: about one delimiter in 256, so many short and some long bogus frames.
    link.send_raw(&noise.bytes(4096)).unwrap();
    // A run longer than any frame, then its delimiter.
    link.send_raw(&vec![0x7E; 3 * MAX_FRAME_LEN]).unwrap();
    link.send_raw(&[0]).unwrap();
    // Valid frames, corrupted: a flipped byte, a truncation, and one with its delimiter lost.
    let words = (0..CHUNK_LEN as u32)
        .map(|i| i.wrapping_mul(0x9E37_79B9))
        .collect();
    let big = encoded(Request::Words { offset: 0, words }, 7);
    for _ in 0..32 {
        let mut corrupt = big.clone();
        let at = noise.below(corrupt.len() - 1);
        corrupt[at] = corrupt[at].wrapping_add(1 + noise.below(254) as u8).max(1);
        link.send_raw(&corrupt).unwrap();
    }
    link.send_raw(&big[..big.len() / 2]).unwrap();
    link.send_raw(&[0]).unwrap();
    link.send_raw(&big[..big.len() - 1]).unwrap(); // runs into the next frame
                                                   // Well-formed requests out of session order, and a response where a request belongs.
    link.send_raw(&encoded(Request::EndMatrix { crc32: 0 }, 8))
        .unwrap();
    link.send_raw(&encoded(
        Request::ReadSolution {
            direction: 0,
            offset: 0,
            len: CHUNK_LEN as u16,
        },
        9,
    ))
    .unwrap();
    let params = SolveParams {
        max_iterations: 10,
        tolerance: 0.5,
        start: Start::Previous,
        directions: 1,
        cycle_budget: 0,
    };
    link.send_raw(&encoded(Request::Solve(params), 10)).unwrap();
    link.send_raw(&encoded(deform_shared::protocol::Response::Ack, 11))
        .unwrap();

    // The handshake must still succeed, skipping every complaint about the noise.
    let mut target = Target::handshake(link, timeouts()).unwrap_or_else(|e| {
        panic!(
            "no handshake after noise: {e}\nQEMU stderr:\n{}",
            qemu.stderr()
        )
    });
    assert_eq!(target.info().protocol_version, PROTOCOL_VERSION);
    assert!(
        target.stats().stale_answers > 0,
        "the firmware answered none of the noise: {:?}",
        target.stats()
    );
    assert_alive(&mut qemu);

    // And the session works normally afterwards.
    let matrix = banded_spd(8, 1);
    target.upload_matrix(&matrix).unwrap();
    let (report, _) = target.solve_for(&[1.0; 8], solve_params()).unwrap();
    assert!(report.converged, "{report:?}");
    assert_alive(&mut qemu);
}

#[test]
fn solves_a_laplacian_like_the_f64_reference() {
    let mut qemu = boot();
    let mut target = connect(&qemu);
    let n = 300; // with a 1-wide band, tiles hold 510 rows: one tile; see the banded test for more
    let matrix = banded_spd(n, 1);
    let reference = decode_dense(&matrix);
    target.upload_matrix(&matrix).unwrap();
    for scale in [1.0, 2.5e-4, 4.0e3] {
        let rhs: Vec<f64> = (0..n)
            .map(|i| scale * (1.0 + (i as f64 * 0.05).sin()))
            .collect();
        let (report, x) = target.solve_for(&rhs, solve_params()).unwrap();
        assert!(report.converged, "{report:?}");
        assert!(
            report.iterations > 0 && report.words_per_iteration as usize == matrix.words.len(),
            "{report:?}"
        );
        let err = max_relative_error(&x, &cholesky_solve(&reference, &rhs));
        assert!(err < 1e-5, "max relative error {err:e} at scale {scale}");
    }
    assert_alive(&mut qemu);
}

#[test]
fn solves_a_multi_tile_banded_system_with_a_warm_start() {
    let mut qemu = boot();
    let mut target = connect(&qemu);
    let n = 700;
    let matrix = banded_spd(n, 5); // tiles of 502 rows: two tiles
    assert_eq!(matrix.tiles.len(), 2);
    let reference = decode_dense(&matrix);
    target.upload_matrix(&matrix).unwrap();
    let rhs: Vec<f64> = (0..n).map(|i| ((i * 7919) % 101) as f64 - 50.0).collect();
    let (cold, x) = target.solve_for(&rhs, solve_params()).unwrap();
    assert!(cold.converged, "{cold:?}");
    let want = cholesky_solve(&reference, &rhs);
    let err = max_relative_error(&x, &want);
    assert!(err < 1e-5, "max relative error {err:e}");

    // The same right-hand side again from the previous solution: already converged.
    target.upload_vector(VectorSlot::RHS, &rhs).unwrap();
    let warm = target
        .solve(SolveParams {
            start: Start::Previous,
            ..solve_params()
        })
        .unwrap();
    assert!(
        warm.converged && warm.iterations < cold.iterations,
        "cold {cold:?}, warm {warm:?}"
    );
    assert_alive(&mut qemu);
}

#[test]
fn a_matrix_beyond_the_targets_capacity_is_refused_before_upload() {
    let mut qemu = boot();
    let mut target = connect(&qemu);
    let info = target.info().clone();

    // More words than the store holds, at a dimension the target does hold.
    let n = info.max_n;
    let half_bandwidth = info.word_capacity / n / 2 + 1;
    let too_many_words = banded_spd(n, half_bandwidth);
    assert!(too_many_words.words.len() > info.word_capacity as usize);
    let sent_before = target.stats().requests;
    let err = target.upload_matrix(&too_many_words).unwrap_err();
    match err {
        LinkError::TooLarge {
            what: Capacity::MatrixWords,
            capacity,
            ..
        } => assert_eq!(capacity, info.word_capacity),
        other => panic!("expected TooLarge(MatrixWords), got {other:?}"),
    }
    assert!(err_text(&target, &too_many_words).contains(&format!("at most {}", info.word_capacity)));
    assert_eq!(
        target.stats().requests,
        sent_before,
        "nothing may be sent for a refused matrix"
    );

    // A dimension beyond max_n.
    let err = target
        .upload_matrix(&banded_spd(info.max_n + 1, 1))
        .unwrap_err();
    assert!(
        matches!(
            err,
            LinkError::TooLarge {
                what: Capacity::Dimension,
                ..
            }
        ),
        "{err:?}"
    );
    assert_eq!(target.stats().requests, sent_before);

    // The target is untouched and still serves a matrix that fits.
    target.upload_matrix(&banded_spd(16, 1)).unwrap();
    let (report, _) = target.solve_for(&[1.0; 16], solve_params()).unwrap();
    assert!(report.converged);
    assert_alive(&mut qemu);
}

fn err_text(target: &Target, matrix: &deform_host::encode::EncodedMatrix) -> String {
    target.check_matrix_fits(matrix).unwrap_err().to_string()
}

fn solve_params() -> SolveParams {
    SolveParams {
        max_iterations: 5000,
        tolerance: 1e-10,
        start: Start::Zero,
        directions: 1,
        cycle_budget: 0,
    }
}

/// One frame, delimiter included, as the host would send it.
fn encoded<T: serde::Serialize>(body: T, seq: u16) -> Vec<u8> {
    let mut buf = [0u8; MAX_FRAME_LEN];
    let len = frame::encode(&Envelope { seq, body }, &mut buf).unwrap();
    buf[..len].to_vec()
}
