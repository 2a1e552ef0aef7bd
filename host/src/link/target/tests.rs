//! The host's session against a fake target: uploads, solves, updates, resets and noise.

use std::os::unix::net::UnixStream;
use std::sync::atomic::Ordering;
use std::time::Instant;

use deform_shared::protocol::SessionStep;
use deform_shared::transport::Uplink;

use super::*;
use crate::link::fake_target::{
    answer_frame, info, serve, serve_resetting, serve_session, serve_session_through, uplink_frame,
    Received,
};
use crate::link::test_systems::{laplacian_1d, laplacian_1d_solve, max_relative_error};

fn quick() -> Timeouts {
    Timeouts {
        handshake: Duration::from_secs(5),
        request: Duration::from_secs(5),
        solve: Duration::from_secs(30),
        retransmit: Duration::from_millis(50),
        retries: 16,
    }
}

fn session_target(
    info: TargetInfo,
) -> (
    Target<UnixStream>,
    std::sync::Arc<std::sync::atomic::AtomicUsize>,
) {
    let (host, target) = UnixStream::pair().unwrap();
    let requests = serve_session(target, info);
    (
        Target::handshake(Link::new(host), quick()).unwrap(),
        requests,
    )
}

fn params() -> SolveParams {
    SolveParams {
        max_iterations: 2000,
        tolerance: 1e-9,
        start: Start::Zero,
        directions: 1,
        cycle_budget: 0,
    }
}

#[test]
fn a_fused_solve_returns_every_direction() {
    let (mut target, _) = session_target(info());
    let n = 150;
    target.upload_matrix(&laplacian_1d(n)).unwrap();
    let rhs: Vec<Vec<f64>> = (1..=3)
        .map(|d| (0..n).map(|i| (i as f64 * 0.05 * d as f64).cos()).collect())
        .collect();
    let slices: Vec<&[f64]> = rhs.iter().map(Vec::as_slice).collect();
    let (report, x) = target.solve_fused(&slices, params()).unwrap();
    assert_eq!(report.directions.len(), 3);
    assert!(report.converged, "{report:?}");
    for (b, x) in rhs.iter().zip(&x) {
        assert!(max_relative_error(x, &laplacian_1d_solve(b)) < 1e-5);
    }
    let (single, x1) = target.solve_for(&rhs[1], params()).unwrap();
    assert_eq!(single.directions[0], report.directions[1]);
    assert_eq!(x1, x[1]);
    let err = target.solve_fused(&[], params()).unwrap_err();
    assert!(matches!(err, LinkError::Directions(0)), "{err:?}");
    let four = [slices[0]; 4];
    assert!(matches!(
        target.solve_fused(&four, params()),
        Err(LinkError::Directions(4))
    ));
}

#[test]
fn solves_a_laplacian_against_the_firmware_session_logic() {
    let (mut target, _) = session_target(info());
    assert_eq!(target.info().firmware_version.as_str(), "fake");
    let n = 250; // three tiles
    let matrix = laplacian_1d(n);
    assert_eq!(matrix.tiles.len(), 3);
    let mut reports = Vec::new();
    target
        .upload_matrix_with_progress(&matrix, |p| reports.push(p))
        .unwrap();
    assert_eq!(reports.last().unwrap().words_sent, matrix.words.len());
    assert!(reports
        .windows(2)
        .all(|w| w[0].words_sent < w[1].words_sent));
    assert!(reports.iter().all(|p| p.words_total == matrix.words.len()));

    // Two right-hand sides against the resident matrix, of very different scales.
    for scale in [1.0, 3.0e-7] {
        let rhs: Vec<f64> = (0..n)
            .map(|i| scale * (1.0 + (i as f64 * 0.1).sin()))
            .collect();
        let (report, x) = target.solve_for(&rhs, params()).unwrap();
        assert!(report.converged, "{report:?}");
        let err = max_relative_error(&x, &laplacian_1d_solve(&rhs));
        assert!(err < 1e-5, "max relative error {err:e} at scale {scale}");
    }
}

/// `factor` times `matrix`, in a Q-format with two fractional bits fewer (its raw values
/// must be multiples of 4).
fn scaled(matrix: &EncodedMatrix, factor: i64) -> EncodedMatrix {
    let words = matrix
        .words
        .iter()
        .map(|&w| {
            let w = Word(w);
            Word::new(
                w.column(),
                w.raw_value() as i64 * factor / 4,
                w.end_of_row(),
                w.end_of_matrix(),
            )
            .unwrap()
            .bits()
        })
        .collect();
    EncodedMatrix {
        words,
        frac_bits: matrix.frac_bits - 2,
        ..matrix.clone()
    }
}

#[test]
fn a_values_only_update_solves_like_a_fresh_upload_and_sends_less() {
    let n = 250;
    let a = laplacian_1d(n);
    let a3 = scaled(&a, 3);
    let rhs: Vec<f64> = (0..n).map(|i| 1.0 + (i as f64 * 0.1).sin()).collect();

    let (mut fresh, _) = session_target(info());
    fresh.upload_matrix(&a3).unwrap();
    let (fresh_report, fresh_x) = fresh.solve_for(&rhs, params()).unwrap();

    let (mut target, _) = session_target(info());
    let err = target.update_values(&a3).unwrap_err();
    assert!(matches!(err, UpdateError::NoResidentMatrix), "{err:?}");
    target.upload_matrix(&a).unwrap();
    target.solve_for(&rhs, params()).unwrap();
    assert!(target.pattern_matches(&a3));
    let report = target.update_values(&a3).unwrap();
    let (got_report, x) = target.solve_for(&rhs, params()).unwrap();
    assert_eq!(got_report, fresh_report);
    assert_eq!(x, fresh_x);
    assert_eq!(report.full_upload_bytes, full_upload_bytes(&a3).unwrap());
    assert_eq!(report.bytes_sent, update_bytes(&a3).unwrap());
    assert!(
        report.bytes_saved() > 0 && report.bytes_sent < report.full_upload_bytes,
        "{report:?}"
    );
    // The solution is x(A)/3.
    let want: Vec<f64> = laplacian_1d_solve(&rhs).iter().map(|v| v / 3.0).collect();
    assert!(max_relative_error(&x, &want) < 1e-5);
}

#[test]
fn an_update_with_another_pattern_is_refused_before_anything_is_sent() {
    let (mut target, requests) = session_target(info());
    target.upload_matrix(&laplacian_1d(20)).unwrap();
    let sent = requests.load(Ordering::SeqCst);
    let mut other = laplacian_1d(20);
    other.words[3] ^= deform_shared::word::ER_BIT;
    assert!(!target.pattern_matches(&other));
    let err = target.update_values(&other).unwrap_err();
    assert!(matches!(err, UpdateError::PatternChanged), "{err:?}");
    let err = target.update_values(&laplacian_1d(21)).unwrap_err();
    assert!(matches!(err, UpdateError::PatternChanged), "{err:?}");
    assert_eq!(requests.load(Ordering::SeqCst), sent);
    // upload_or_update falls back to a full upload, then updates.
    assert_eq!(target.upload_or_update(&laplacian_1d(21)).unwrap(), None);
    let report = target.upload_or_update(&scaled(&laplacian_1d(21), 2));
    assert!(report.unwrap().is_some());
    target.reset().unwrap();
    assert!(!target.pattern_matches(&laplacian_1d(21)));
}

#[test]
fn a_matrix_too_large_is_refused_before_anything_is_sent() {
    let small = TargetInfo {
        word_capacity: 100,
        ..info()
    };
    let (mut target, requests) = session_target(small);
    let sent_before = requests.load(Ordering::SeqCst);
    let matrix = laplacian_1d(50); // 148 words
    let err = target.upload_matrix(&matrix).unwrap_err();
    assert!(
        matches!(
            err,
            LinkError::TooLarge {
                what: Capacity::MatrixWords,
                requested: 148,
                capacity: 100
            }
        ),
        "{err:?}"
    );
    let text = err.to_string();
    assert!(
        text.contains("148 matrix words") && text.contains("at most 100"),
        "{text}"
    );
    assert_eq!(
        requests.load(Ordering::SeqCst),
        sent_before,
        "nothing may be sent"
    );
    assert_eq!(target.stats().requests, 1, "only the handshake");

    let err = target.upload_matrix(&laplacian_1d(2000)).unwrap_err();
    assert!(
        matches!(
            err,
            LinkError::TooLarge {
                what: Capacity::Dimension,
                capacity: 1024,
                ..
            }
        ),
        "{err:?}"
    );
}

#[test]
fn a_malformed_matrix_is_refused_before_anything_is_sent() {
    let (mut target, requests) = session_target(info());
    let mut matrix = laplacian_1d(10);
    matrix.tiles[0].rows += 1;
    let err = target.upload_matrix(&matrix).unwrap_err();
    assert!(matches!(err, LinkError::MalformedMatrix(_)), "{err:?}");
    matrix = laplacian_1d(10);
    matrix.words.pop();
    let err = target.upload_matrix(&matrix).unwrap_err();
    assert!(
        matches!(
            err,
            LinkError::MalformedMatrix(MatrixError::TotalWordsMismatch { .. })
        ),
        "{err:?}"
    );
    assert_eq!(requests.load(Ordering::SeqCst), 1);
}

#[test]
fn the_targets_refusals_come_back_with_its_reason() {
    let (mut target, _) = session_target(info());
    let err = target
        .upload_vector(VectorSlot::RHS, &[1.0, 2.0])
        .unwrap_err();
    assert_eq!(
        err.target_code(),
        Some(ErrorCode::OutOfOrder(SessionStep::NoMatrix))
    );
    target.upload_matrix(&laplacian_1d(4)).unwrap();
    let warm = SolveParams {
        start: Start::Previous,
        ..params()
    };
    let err = target.solve_for(&[1.0; 4], warm).unwrap_err();
    assert_eq!(
        err.target_code(),
        Some(ErrorCode::OutOfOrder(SessionStep::NoPreviousSolution)),
        "{err:?}"
    );
    assert!(err.to_string().contains("refused Solve"), "{err}");
    let err = target
        .upload_vector(VectorSlot::RHS, &[1.0, f64::NAN, 0.0, 0.0])
        .unwrap_err();
    assert!(
        matches!(err, LinkError::NotFinite { index: 1, .. }),
        "{err:?}"
    );
}

#[test]
fn a_reset_drops_the_matrix() {
    let (mut target, _) = session_target(info());
    target.upload_matrix(&laplacian_1d(4)).unwrap();
    target.reset().unwrap();
    let err = target
        .upload_vector(VectorSlot::RHS, &[1.0; 4])
        .unwrap_err();
    assert_eq!(
        err.target_code(),
        Some(ErrorCode::OutOfOrder(SessionStep::NoMatrix))
    );
}

#[test]
fn another_protocol_version_is_named_with_ours() {
    let (host, target) = UnixStream::pair().unwrap();
    serve(target, |received| match received {
        Received::Request(req) => answer_frame(
            req.seq,
            Response::Hello(TargetInfo {
                protocol_version: PROTOCOL_VERSION + 1,
                ..info()
            }),
        ),
        Received::Unreadable(_) => Vec::new(),
    });
    let err = Target::handshake(Link::new(host), quick()).err().unwrap();
    assert!(
        matches!(err, LinkError::VersionMismatch { host, target } if host == PROTOCOL_VERSION && target == PROTOCOL_VERSION + 1),
        "{err:?}"
    );
    let text = err.to_string();
    assert!(
        text.contains(&format!("version {PROTOCOL_VERSION}")),
        "{text}"
    );
    assert!(
        text.contains(&format!("version {}", PROTOCOL_VERSION + 1)),
        "{text}"
    );
}

#[test]
fn the_handshake_outlasts_complaints_about_noise_and_a_lost_hello() {
    let (host, target) = UnixStream::pair().unwrap();
    let mut hellos = 0;
    serve(target, move |received| match received {
        Received::Request(req) => {
            hellos += 1;
            // The first Hello is lost behind NAKs, a stale reply and a stale NotSynced.
            let mut out = Vec::new();
            for _ in 0..3 {
                out.extend(uplink_frame(&Uplink::Nak { expected: 1 }));
            }
            out.extend(answer_frame(req.seq.wrapping_sub(9), Response::Ack));
            out.extend(uplink_frame(&Uplink::NotSynced { seq: 3 }));
            if hellos > 1 {
                out.extend(answer_frame(req.seq, Response::Hello(info())));
            }
            out
        }
        Received::Unreadable(_) => Vec::new(),
    });
    let target = Target::handshake(Link::new(host), quick()).unwrap();
    // One Hello, sent twice (with the same number).
    assert_eq!(target.stats().requests, 1);
    assert_eq!(target.stats().retransmits, 1);
    assert_eq!(target.stats().naks, 6);
    assert_eq!(target.stats().stale_answers, 4);
}

#[test]
fn the_handshake_skips_a_stale_answer_that_happens_to_carry_its_number() {
    let (host, target) = UnixStream::pair().unwrap();
    serve(target, |received| match received {
        Received::Request(req) => {
            let code = ErrorCode::OutOfOrder(SessionStep::NoMatrixUpload);
            let mut out = answer_frame(req.seq, Response::Error(code));
            out.extend(answer_frame(req.seq, Response::Ack));
            out.extend(answer_frame(req.seq, Response::Hello(info())));
            out
        }
        Received::Unreadable(_) => Vec::new(),
    });
    let target = Target::handshake(Link::new(host), quick()).unwrap();
    assert_eq!(target.stats().stale_answers, 2);
}

#[test]
fn a_silent_target_fails_the_handshake_in_time() {
    let (host, target) = UnixStream::pair().unwrap();
    serve(target, |_| Vec::new());
    let timeouts = Timeouts {
        handshake: Duration::from_millis(500),
        ..quick()
    };
    let started = Instant::now();
    let err = Target::handshake(Link::new(host), timeouts).err().unwrap();
    assert!(
        matches!(
            err,
            LinkError::Timeout {
                request: "Hello",
                ..
            }
        ),
        "{err:?}"
    );
    assert!(started.elapsed() < Duration::from_secs(2));
}

#[test]
fn a_target_silent_past_the_retries_still_answers_within_the_handshake_time() {
    let (host, target) = UnixStream::pair().unwrap();
    let mut hellos = 0;
    // Silent for the first six copies of the Hello (a board still booting), then answers.
    serve(target, move |received| match received {
        Received::Request(req) => {
            hellos += 1;
            if hellos > 6 {
                answer_frame(req.seq, Response::Hello(info()))
            } else {
                Vec::new()
            }
        }
        Received::Unreadable(_) => Vec::new(),
    });
    let timeouts = Timeouts {
        retransmit: Duration::from_millis(10),
        retries: 2,
        ..quick()
    };
    let target = Target::handshake(Link::new(host), timeouts).unwrap();
    assert_eq!(target.stats().retransmits, 6);
    // The cap applies again to the requests after the handshake.
    assert_eq!(target.link.config().retries, 2);
}

#[test]
fn a_solution_chunk_at_the_wrong_offset_is_a_protocol_error() {
    let (host, target) = UnixStream::pair().unwrap();
    serve(target, |received| match received {
        Received::Request(req) => match req.body {
            Request::Hello { .. } => answer_frame(req.seq, Response::Hello(info())),
            _ => answer_frame(
                req.seq,
                Response::Solution {
                    direction: 0,
                    offset: 5,
                    exponent: 0,
                    mantissas: [1, 2].into_iter().collect(),
                },
            ),
        },
        Received::Unreadable(_) => Vec::new(),
    });
    let mut target = Target::handshake(Link::new(host), quick()).unwrap();
    let err = target.read_solution(3).unwrap_err();
    assert!(
        matches!(
            err,
            LinkError::Protocol {
                request: "ReadSolution",
                ..
            }
        ),
        "{err:?}"
    );
}

/// A line that flips bits, drops, duplicates and inserts bytes, each at `rate / 4` per
/// byte, from a fixed seed.
fn noisy_line(seed: u64, rate: f64) -> impl FnMut(&[u8]) -> Vec<u8> + Send + 'static {
    let mut state = seed;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    move |bytes| {
        let mut out = Vec::with_capacity(bytes.len() + 8);
        for &b in bytes {
            let roll = (next() % 1_000_000) as f64 / 1e6;
            let fault = (roll / (rate / 4.0)) as u32;
            match fault {
                0 => out.push(b ^ (1 << (next() % 8))),
                1 => {}
                2 => out.extend([b, b]),
                3 => out.extend([next() as u8, b]),
                _ => out.push(b),
            }
        }
        out
    }
}

#[test]
fn a_noisy_line_gives_bit_identical_results_to_a_clean_one() {
    let n = 600;
    let matrix = laplacian_1d(n);
    let rhs: Vec<f64> = (0..n).map(|i| 1.0 + (i as f64 * 0.1).sin()).collect();
    let (mut clean, _) = session_target(info());
    clean.upload_matrix(&matrix).unwrap();
    let (clean_report, clean_x) = clean.solve_for(&rhs, params()).unwrap();

    let (host, target) = UnixStream::pair().unwrap();
    serve_session_through(target, info(), noisy_line(0xDEF0_2026, 1e-3));
    let mut noisy = Target::handshake(Link::new(host), quick()).unwrap();
    noisy.upload_matrix(&matrix).unwrap();
    let (report, x) = noisy.solve_for(&rhs, params()).unwrap();
    assert_eq!(report, clean_report);
    assert_eq!(x, clean_x, "bit for bit");
    let stats = noisy.stats();
    assert!(
        stats.retransmits > 0 && stats.corrupt_frames > 0,
        "{stats:?}"
    );
}

#[test]
fn a_target_that_resets_mid_session_is_given_its_matrix_again() {
    let n = 300;
    let matrix = laplacian_1d(n);
    let rhs: Vec<f64> = (0..n).map(|i| (i % 7) as f64 - 3.0).collect();
    let (mut clean, _) = session_target(info());
    clean.upload_matrix(&matrix).unwrap();
    let want = clean.solve_for(&rhs, params()).unwrap();

    let (host, target) = UnixStream::pair().unwrap();
    // Hello + BeginMatrix + 3 tiles + 9 word chunks + EndMatrix = 15 requests, then the
    // target reboots as the right-hand side arrives.
    serve_resetting(target, info(), |b| b.to_vec(), Some(16));
    let link = Link::new(host).with_fixed_chunk(CHUNK_LEN);
    let mut target = Target::handshake(link, quick()).unwrap();
    target.upload_matrix(&matrix).unwrap();
    let got = target.solve_for(&rhs, params()).unwrap();
    assert_eq!(target.resumes(), 1);
    assert_eq!(got, want);

    // A warm start cannot resume: the state it starts from is gone.
    let (host, target) = UnixStream::pair().unwrap();
    serve_resetting(target, info(), |b| b.to_vec(), Some(16));
    let link = Link::new(host).with_fixed_chunk(CHUNK_LEN);
    let mut target = Target::handshake(link, quick()).unwrap();
    target.upload_matrix(&matrix).unwrap();
    let warm = SolveParams {
        start: Start::Previous,
        ..params()
    };
    let err = target.solve_for(&rhs, warm).unwrap_err();
    assert!(matches!(err, LinkError::TargetReset), "{err:?}");
    assert!(err.to_string().contains("reset mid-session"), "{err}");
}

/// At a byte-error rate of 1e-2 each way a full 540-byte chunk frame arrives intact 0.4 % of
/// the time: only a link that shrinks its chunks and replies gets through, and it must give
/// the clean run's bits.
#[test]
fn at_a_byte_error_rate_of_1e_2_the_link_shrinks_its_chunks_and_still_matches_bit_for_bit() {
    let n = 600;
    let matrix = laplacian_1d(n);
    let rhs: Vec<f64> = (0..n).map(|i| 1.0 + (i as f64 * 0.1).sin()).collect();
    let (mut clean, _) = session_target(info());
    clean.upload_matrix(&matrix).unwrap();
    let (clean_report, clean_x) = clean.solve_for(&rhs, params()).unwrap();
    assert_eq!(clean.link_mut().adaptive().damage_seen(), 0);
    assert_eq!(
        clean.link_mut().adaptive().chunk(),
        CHUNK_LEN,
        "a clean line grows to full chunks"
    );

    let (host, target) = UnixStream::pair().unwrap();
    serve_session_through(target, info(), noisy_line(0x1E2_2026, 1e-2));
    let patient = Timeouts {
        retries: 60,
        request: Duration::from_secs(30),
        ..quick()
    };
    let mut noisy = Target::handshake(Link::new(host), patient).unwrap();
    noisy.upload_matrix(&matrix).unwrap();
    let (report, x) = noisy.solve_for(&rhs, params()).unwrap();
    assert_eq!(report, clean_report);
    assert_eq!(x, clean_x, "bit for bit");
    let adaptive = noisy.link_mut().adaptive();
    assert!(
        adaptive.damage_seen() > 0 && adaptive.smallest_chunk() <= 16,
        "the chunk adapted: {adaptive:?}"
    );
}
