//! Shared by the QEMU tests: booting, connecting, and small SPD systems with f64 references.
// Each test binary that includes this module uses a different subset of it.
#![allow(dead_code)]

use std::time::Duration;

use deform_hil_sim::{firmware_elf, Qemu, QemuConfig};
use deform_host::encode::EncodedMatrix;
use deform_host::link::{Port, Target, Timeouts};
use deform_shared::protocol::{SolveParams, SolveReport, Start};
use deform_shared::qformat::choose_frac_bits;
use deform_shared::word::COLUMN_WINDOW;
use deform_target_core::testkit::{banded_row, dense, encode_rows, TestSystem};

/// Boots the firmware; a missing ELF or QEMU fails the test with the fix in the message.
pub fn boot() -> Qemu {
    let config = QemuConfig::new(firmware_elf());
    Qemu::start(&config).unwrap_or_else(|e| panic!("cannot boot the firmware: {e}"))
}

/// Boots the firmware with `harts` harts (one MVU each).
pub fn boot_harts(harts: u8) -> Qemu {
    Qemu::start(&QemuConfig::new(firmware_elf()).harts(harts))
        .unwrap_or_else(|e| panic!("cannot boot the firmware: {e}"))
}

/// `deform solve`'s plan for `board`: refined to `tol` with at most `max_solves` target solves
/// per direction, fused, default layout (every MVU), `timeout` per solve.
pub fn plan(
    board: deform_host::board::BoardChoice,
    tol: f64,
    max_solves: u32,
    timeout: Duration,
) -> deform_host::solve::SolvePlan {
    deform_host::solve::SolvePlan {
        board: Some(board),
        mvus: None,
        tol,
        max_iter: None,
        max_solves,
        solve_timeout: timeout,
        layout: Default::default(),
        precondition: Default::default(),
        fuse: true,
        link: Default::default(),
        logs: Default::default(),
    }
}

/// The board on QEMU's pty, as a real board on a port is reached.
pub fn port_of(qemu: &Qemu) -> deform_host::board::BoardChoice {
    deform_host::board::BoardChoice::Port(qemu.pty_path().to_string_lossy().into_owned())
}

/// The model the model flags give (over the thesis example).
pub fn build(flags: &deform_host::model::flags::ModelFlags) -> deform_host::model::Model {
    deform_host::model::Model::build(&flags.spec_over(None)).expect("model builds")
}

/// Generous deadlines: CI machines are slow and QEMU notices the pty only once a second.
pub fn timeouts() -> Timeouts {
    Timeouts {
        handshake: Duration::from_secs(20),
        request: Duration::from_secs(20),
        solve: Duration::from_secs(120),
        ..Timeouts::default()
    }
}

/// Connects through the very code path a real board uses.
pub fn connect(qemu: &Qemu) -> Target {
    let pty = qemu.pty_path().to_str().expect("pty paths are ASCII");
    Target::connect(pty, timeouts())
        .unwrap_or_else(|e| panic!("no handshake: {e}\nQEMU stderr:\n{}", qemu.stderr()))
}

/// Asserts that QEMU is still running (the firmware did not panic or fault).
pub fn assert_alive(qemu: &mut Qemu) {
    let exit = qemu.try_exit_code().expect("QEMU's status");
    assert_eq!(
        exit,
        None,
        "QEMU exited (101 = firmware panic, 102 = CPU exception); stderr:\n{}",
        qemu.stderr()
    );
}

/// A symmetric banded matrix of order `n`: 2 on the diagonal and -1/h on the `h` nearest
/// off-diagonals on either side. Every row sums to at most 0 but the first and last are strictly
/// dominant, so it is SPD; `h = 1` is the 1-D Laplacian.
pub fn banded_spd(n: u32, half_bandwidth: u32) -> EncodedMatrix {
    let h = half_bandwidth;
    assert!(h >= 1 && 2 * h < COLUMN_WINDOW);
    // A tile's rows touch `h` columns on either side; they must stay in its 512-column window.
    let tile_rows = (COLUMN_WINDOW - 2 * h) as usize;
    let frac_bits = choose_frac_bits(2.0).unwrap();
    let n = n as usize;
    encoded(encode_rows(
        n,
        n,
        tile_rows,
        frac_bits,
        banded_row(n, h as usize),
    ))
}

/// A test system as the host's encoded matrix.
pub fn encoded(s: TestSystem) -> EncodedMatrix {
    EncodedMatrix {
        n: s.n,
        frac_bits: s.frac_bits,
        tiles: s.tiles,
        words: s.words,
    }
}

/// The encoded matrix as the target sees it, dense, in f64.
pub fn decode_dense(matrix: &EncodedMatrix) -> Vec<Vec<f64>> {
    dense(&TestSystem {
        n: matrix.n,
        frac_bits: matrix.frac_bits,
        tiles: matrix.tiles.clone(),
        words: matrix.words.clone(),
    })
}

/// Solves the SPD system `a x = b` in f64 by Cholesky factorisation.
pub fn cholesky_solve(a: &[Vec<f64>], b: &[f64]) -> Vec<f64> {
    let n = b.len();
    let mut l = vec![vec![0.0; n]; n];
    for i in 0..n {
        for j in 0..=i {
            let dot: f64 = (0..j).map(|k| l[i][k] * l[j][k]).sum();
            if i == j {
                let pivot = a[i][i] - dot;
                assert!(pivot > 0.0, "the reference matrix is not positive definite");
                l[i][i] = pivot.sqrt();
            } else {
                l[i][j] = (a[i][j] - dot) / l[j][j];
            }
        }
    }
    let mut y = vec![0.0; n];
    for i in 0..n {
        y[i] = (b[i] - (0..i).map(|k| l[i][k] * y[k]).sum::<f64>()) / l[i][i];
    }
    let mut x = vec![0.0; n];
    for i in (0..n).rev() {
        x[i] = (y[i] - (i + 1..n).map(|k| l[k][i] * x[k]).sum::<f64>()) / l[i][i];
    }
    x
}

/// max |got - want| / max |want|.
pub fn max_relative_error(got: &[f64], want: &[f64]) -> f64 {
    assert_eq!(got.len(), want.len());
    deform_host::reference::max_abs_diff(got, want) / deform_host::reference::max_abs(want)
}

/// A fixed-seed xorshift generator: the noise is the same in every run.
pub struct Noise(u64);

impl Noise {
    pub fn new(seed: u64) -> Self {
        Noise(seed.max(1))
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }

    pub fn bytes(&mut self, len: usize) -> Vec<u8> {
        (0..len).map(|_| self.next_u64() as u8).collect()
    }

    pub fn below(&mut self, bound: usize) -> usize {
        (self.next_u64() % bound as u64) as usize
    }
}

/// (max |u − u_ref| / max |u_ref|, max |u_ref|) over every node and direction of a solve.
pub fn deviation_from_reference(solved: &deform_host::solve::Solved) -> (f64, f64) {
    use deform_host::reference::{max_abs, max_abs_diff};
    let scale = solved
        .reference
        .iter()
        .map(|r| max_abs(r))
        .fold(0.0, f64::max);
    let worst = solved
        .u
        .iter()
        .zip(&solved.reference)
        .map(|(u, r)| max_abs_diff(u, r))
        .fold(0.0, f64::max);
    (worst / scale, scale)
}

pub use crate::needle::DynamicNeedle;

/// A link's patience with the simulated LiteX SoC: it boots in about a second of wall time,
/// more on a busy machine, and runs about 0.8 M cycles a second.
pub fn litex_timeouts() -> Timeouts {
    Timeouts {
        handshake: Duration::from_secs(120),
        request: Duration::from_secs(60),
        solve: Duration::from_secs(600),
        ..Timeouts::default()
    }
}

/// Solves K·x = `b` on the resident `matrix` (one direction, from zero, to 1e-9 in at most
/// `max_iterations`) and checks that it converged to within 1e-6 of the f64 solution of the
/// same (quantised) system. Returns the target's report, for its cycle counts.
pub fn solve_matches_f64(
    target: &mut Target<impl Port>,
    matrix: &EncodedMatrix,
    b: &[f64],
    max_iterations: u32,
) -> SolveReport {
    let params = SolveParams {
        max_iterations,
        tolerance: 1e-9,
        start: Start::Zero,
        directions: 1,
        cycle_budget: 0,
    };
    let (report, x) = target.solve_for(b, params).unwrap();
    assert!(report.converged, "{report:?}");
    let reference = cholesky_solve(&decode_dense(matrix), b);
    let error = max_relative_error(&x, &reference);
    assert!(error <= 1e-6, "deviation {error:e} from the f64 solution");
    report
}
