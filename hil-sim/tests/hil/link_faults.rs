//! The link under a bad cable: whole solves through the fault-injecting relay
//! ([`deform_hil_sim::relay`]) at a byte-error rate of 1e-3 in each direction, compared bit for
//! bit with the clean run; and the throughput of a large matrix upload through the QEMU pty.
//! Needs the firmware ELF and QEMU, like `qemu_board.rs`.

use crate::support;

use std::time::{Duration, Instant};

use deform_hil_sim::relay::{FaultConfig, FaultRelay};
use deform_host::link::{full_upload_bytes, LinkStats, Target, Timeouts};
use deform_shared::protocol::{SolveParams, SolveReport, Start};

use support::*;

/// Patient settings for a line that loses ~40 % of its full frames: more retries than the
/// default, the same deadlines.
fn noisy_timeouts() -> Timeouts {
    Timeouts {
        retries: 40,
        ..timeouts()
    }
}

fn connect_via(relay: &FaultRelay, timeouts: Timeouts) -> Target {
    let pty = relay.pty_path().to_str().expect("pty paths are ASCII");
    Target::connect(pty, timeouts).unwrap_or_else(|e| panic!("no handshake through the relay: {e}"))
}

fn params(start: Start) -> SolveParams {
    SolveParams {
        max_iterations: 5000,
        tolerance: 1e-9,
        start,
        directions: 1,
        cycle_budget: 0,
    }
}

/// Uploads the matrix once and solves three right-hand sides, the last one warm-started.
fn solve_three(target: &mut Target, n: u32) -> Vec<(SolveReport, Vec<f64>)> {
    let matrix = banded_spd(n, 4);
    target.upload_matrix(&matrix).unwrap();
    let mut results = Vec::new();
    for k in 0..3u32 {
        let rhs: Vec<f64> = (0..n)
            .map(|i| ((i * 7919 + k * 31) % 101) as f64 - 50.0 + k as f64 * 0.25)
            .collect();
        let start = if k == 2 { Start::Previous } else { Start::Zero };
        results.push(target.solve_for(&rhs, params(start)).unwrap());
    }
    results
}

fn print_stats(label: &str, stats: &LinkStats, relay: &FaultRelay) {
    let c = relay.counters();
    use std::sync::atomic::Ordering::Relaxed;
    println!(
        "{label}: {stats:?}\n  relay: {} bytes to target, {} to host; flipped {}, dropped {}, \
         duplicated {}, inserted {}, stalls {}",
        c.to_target.load(Relaxed),
        c.to_host.load(Relaxed),
        c.flipped.load(Relaxed),
        c.dropped.load(Relaxed),
        c.duplicated.load(Relaxed),
        c.inserted.load(Relaxed),
        c.stalls.load(Relaxed),
    );
}

#[test]
fn whole_solves_through_a_noisy_line_match_the_clean_run_bit_for_bit() {
    let mut qemu = boot();
    let n = 1200; // three tiles
    let clean_relay = FaultRelay::start(qemu.pty_path(), FaultConfig::clean()).unwrap();
    let mut clean = connect_via(&clean_relay, timeouts());
    let started = Instant::now();
    let want = solve_three(&mut clean, n);
    println!(
        "clean run took {:.1?}: {:?}",
        started.elapsed(),
        clean.stats()
    );
    // A clean line corrupts nothing. A loaded machine may still cause spurious resends, and a
    // resend the target has already answered and forgotten (beyond its reply cache) is NAKed,
    // so NAKs are not counted here.
    let stats = clean.stats();
    assert_eq!(stats.corrupt_frames, 0, "{stats:?}");
    drop(clean);
    drop(clean_relay);
    // Long enough for QEMU to notice the pty was closed and poll for the next reader.
    std::thread::sleep(Duration::from_millis(1500));

    let config = FaultConfig::byte_error_rate(1e-3, 0x0BAD_CAB1E);
    assert!(config.total_error_rate() >= 1e-3);
    let relay = FaultRelay::start(qemu.pty_path(), config).unwrap();
    let mut noisy = connect_via(&relay, noisy_timeouts());
    let started = Instant::now();
    let got = solve_three(&mut noisy, n);
    let stats = noisy.stats();
    print_stats("noisy run", &stats, &relay);
    println!("noisy run took {:.1?}", started.elapsed());
    for (k, ((got_report, got_x), (want_report, want_x))) in got.iter().zip(&want).enumerate() {
        assert_eq!(got_report, want_report, "right-hand side {k}");
        assert_eq!(
            got_x.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            want_x.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            "right-hand side {k}: the solution differs from the clean run"
        );
    }
    assert!(relay.counters().faults() > 0, "the relay injected nothing");
    assert!(stats.retransmits > 0, "{stats:?}");
    assert_alive(&mut qemu);
}

/// Straight through QEMU's pty, no relay: the throughput a host sees from a QEMU board.
#[test]
fn a_large_matrix_upload_reports_bytes_per_nonzero_and_throughput() {
    let mut qemu = boot();
    let mut target = connect(&qemu);
    let matrix = banded_spd(16_000, 4); // 9 nonzeros a row
    let words = matrix.words.len();
    let before = target.stats();
    let started = Instant::now();
    target.upload_matrix(&matrix).unwrap();
    let elapsed = started.elapsed();
    // First transmissions only: on a loaded machine a frame may be resent spuriously.
    let resent = target.stats().bytes_resent - before.bytes_resent;
    let sent = target.stats().bytes_sent - before.bytes_sent - resent;
    let received = target.stats().bytes_received - before.bytes_received;
    let per_nonzero = sent as f64 / words as f64;
    println!(
        "upload of {words} words ({} tiles): {sent} bytes to the target ({per_nonzero:.3} per \
         nonzero) and {resent} resent, {received} bytes of replies, {:.2?}: {:.0} KB/s, \
         {:.0} nonzeros/s",
        matrix.tiles.len(),
        elapsed,
        (sent + resent) as f64 / elapsed.as_secs_f64() / 1e3,
        words as f64 / elapsed.as_secs_f64(),
    );
    // full_upload_bytes counts two-byte sequence numbers (real ones take up to three) and
    // full-size chunks; the adaptive link starts with smaller ones until the line has shown
    // itself clean (host/src/link/adapt.rs: about the first 2 KB, ≲ 30 frames of ≤ 17 header
    // bytes each, so at most 512 bytes more).
    let estimate = full_upload_bytes(&matrix).unwrap();
    let requests = target.stats().requests - before.requests;
    assert!(
        sent >= estimate && sent - estimate <= requests + 512,
        "sent {sent}, estimated {estimate}"
    );
    assert!(per_nonzero <= 4.2, "{per_nonzero} bytes per nonzero");
    // A clean line corrupts nothing. On a loaded machine a spurious timeout resend may reach
    // the target after it answered and forgot the frame, which it NAKs: so a NAK is allowed
    // only in the wake of a resend.
    let stats = target.stats();
    assert_eq!(stats.corrupt_frames, 0, "{stats:?}");
    assert!(stats.naks <= stats.retransmits, "{stats:?}");
    assert_alive(&mut qemu);
}
