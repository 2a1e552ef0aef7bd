//! `Start::Predicted` (the target extrapolates the previous solutions) and the cycle budget.

use core::sync::atomic::{AtomicU64, Ordering};

use super::*;
use crate::exec::{PhaseClock, Task};
use deform_shared::protocol::PhaseCounters;

fn params(start: Start, tolerance: f64, cycle_budget: u64) -> Request {
    Request::Solve(SolveParams {
        max_iterations: 1000,
        tolerance,
        start,
        directions: 1,
        cycle_budget,
    })
}

/// Solves A·u = t·b for t = 1..=4 with `start`, returning each step's iterations.
fn straight_path(start: Start) -> (Vec<u32>, Vec<Vec<f64>>) {
    let n = 40;
    let mut bufs = OwnedStorage::new(4 * n, 4, n);
    let mut s = bufs.session(info(), HARTS.harts);
    let e = laplacian(n, n);
    load(&mut s, &e);
    let b: Vec<f64> = (0..n).map(|i| (i as f64 * 0.37).sin()).collect();
    let (mut iterations, mut solutions) = (Vec::new(), Vec::new());
    for t in 1..=4 {
        let bt: Vec<f64> = b.iter().map(|v| v * t as f64).collect();
        load_rhs(&mut s, &bt);
        let first = if t == 1 { Start::Zero } else { start };
        let report = solved(s.handle(params(first, 1e-8, 0)));
        assert!(report.converged, "{report:?}");
        iterations.push(report.iterations);
        let want = direct_solve(dense(&e), bt);
        let got = read_all(&mut s, n);
        assert!(max_rel_err(&got, &want) < 1e-6, "step {t}");
        solutions.push(got);
    }
    (iterations, solutions)
}

#[test]
fn a_predicted_start_extrapolates_a_straight_path() {
    let (plain, _) = straight_path(Start::Previous);
    let (predicted, _) = straight_path(Start::Predicted);
    // Step 2 has only u(1): a plain warm start either way. From step 3 on 2u(t−1) − u(t−2) is
    // the solution up to the previous steps' errors, so far fewer iterations are left (measured:
    // 10 and 9 against 65 and 51). This needs r₀ = b − A·x₀ formed exactly (cg::residual_of):
    // rounded at b's scale it took 31 and 17.
    assert_eq!(plain[1], predicted[1], "{plain:?} {predicted:?}");
    for t in 2..4 {
        assert!(predicted[t] * 3 < plain[t], "{predicted:?} vs {plain:?}");
    }
}

#[test]
fn prediction_uses_the_guess_slot_and_a_new_guess_restarts_it() {
    let n = 16;
    let mut bufs = OwnedStorage::new(4 * n, 4, n);
    let mut s = bufs.session(info(), HARTS.harts);
    load(&mut s, &laplacian(n, n));
    let b: Vec<f64> = (0..n).map(|i| i as f64 - 7.0).collect();
    load_rhs(&mut s, &b);
    // No solution yet: a predicted start is a cold one, never refused.
    assert!(solved(s.handle(params(Start::Predicted, 1e-9, 0))).converged);
    let (e, m) = to_block(&b);
    all_ack(
        &mut s,
        vector_requests(VectorSlot::INITIAL_GUESS, e, &m, CHUNK_LEN),
    );
    assert!(solved(s.handle(params(Start::Predicted, 1e-9, 0))).converged);
    // The guess slot now holds the kept solution, not the upload.
    assert_eq!(
        s.handle(params(Start::Uploaded, 1e-9, 0)),
        ooo(SessionStep::NoInitialGuess)
    );
    all_ack(
        &mut s,
        vector_requests(VectorSlot::INITIAL_GUESS, e, &m, CHUNK_LEN),
    );
    assert!(solved(s.handle(params(Start::Uploaded, 1e-9, 0))).converged);
    // A new matrix forgets everything: predicted = cold, and still right.
    load(&mut s, &laplacian(n, 4));
    load_rhs(&mut s, &b);
    let report = solved(s.handle(params(Start::Predicted, 1e-9, 0)));
    assert!(report.converged && report.iterations > 2, "{report:?}");
}

/// Sequential harts with a clock that advances 1000 cycles every time it is read.
struct Ticking(AtomicU64);

impl PhaseClock for Ticking {
    fn now(&self) -> PhaseCounters {
        let cycles = self.0.fetch_add(1000, Ordering::Relaxed);
        PhaseCounters {
            cycles,
            instructions: cycles,
        }
    }
}

impl Executor for Ticking {
    type Mvus = crate::mvu_backend::NoMvus;

    fn harts(&self) -> usize {
        HARTS.harts()
    }
    fn run(&self, harts: usize, task: Task<'_>) {
        HARTS.run(harts, task)
    }
    fn run_measured(&self, harts: usize, task: Task<'_>) -> [PhaseCounters; MAX_HARTS] {
        HARTS.run_measured(harts, task)
    }
}

#[test]
fn a_cycle_budget_stops_the_step_with_the_residual_it_reached() {
    let n = 64;
    let mut bufs = OwnedStorage::new(4 * n, 4, n);
    let mut s = Session::new(bufs.storage(), info(), Ticking(AtomicU64::new(0)));
    for req in matrix_requests(&laplacian(n, n), CHUNK_LEN) {
        assert_eq!(s.handle(req), Response::Ack);
    }
    let b: Vec<f64> = (0..n).map(|i| ((i * 31) % 7) as f64 - 3.0).collect();
    let (e, m) = to_block(&b);
    for req in vector_requests(VectorSlot::RHS, e, &m, CHUNK_LEN) {
        assert_eq!(s.handle(req), Response::Ack);
    }
    let free = solved(s.handle(params(Start::Zero, 1e-10, 0)));
    assert!(free.converged && free.iterations > 20, "{free:?}");
    let budget = (free.mvu.cycles + free.svu.cycles) / 4;
    let budgeted = solved(s.handle(params(Start::Zero, 1e-10, budget)));
    assert!(!budgeted.converged, "{budgeted:?}");
    assert!(budgeted.iterations < free.iterations / 2, "{budgeted:?}");
    // It stopped at the first iteration boundary past the budget, and says how far it got.
    assert!(budgeted.mvu.cycles + budgeted.svu.cycles >= budget);
    assert!(
        budgeted.residual > 1e-10 && budgeted.residual < 1.0,
        "{budgeted:?}"
    );
    assert_eq!(budgeted.directions[0].residual, budgeted.residual);
}
