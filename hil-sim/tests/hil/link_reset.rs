//! A board that resets mid-session (QEMU's `system_reset`: the firmware reboots and forgets its
//! matrix, the UART stays on the same pty). The host notices through the transport's
//! handshake state (`NotSynced`), shakes hands again, re-uploads the matrix and gives the same
//! answer as before, bit for bit. Needs the firmware ELF and QEMU, like `qemu_board.rs`.

use crate::support;

use deform_hil_sim::{firmware_elf, Qemu, QemuConfig};
use deform_shared::protocol::{SolveParams, Start};

use support::*;

#[test]
fn a_board_reset_mid_session_is_noticed_and_the_matrix_sent_again() {
    let monitor = std::env::temp_dir().join(format!("deform-monitor-{}.sock", std::process::id()));
    let _ = std::fs::remove_file(&monitor);
    let mut qemu = Qemu::start(&QemuConfig::new(firmware_elf()).monitor(&monitor))
        .unwrap_or_else(|e| panic!("cannot boot the firmware: {e}"));
    let mut target = connect(&qemu);
    let n = 700;
    let matrix = banded_spd(n, 5);
    target.upload_matrix(&matrix).unwrap();
    let rhs: Vec<f64> = (0..n).map(|i| ((i * 37) % 23) as f64 - 11.0).collect();
    let params = SolveParams {
        max_iterations: 5000,
        tolerance: 1e-10,
        start: Start::Zero,
        directions: 1,
        cycle_budget: 0,
    };
    let before = target.solve_for(&rhs, params).unwrap();

    qemu.system_reset(&monitor).unwrap();
    // Let the firmware boot again (zeroing its storage takes a few milliseconds).
    std::thread::sleep(std::time::Duration::from_millis(500));
    let after = target
        .solve_for(&rhs, params)
        .unwrap_or_else(|e| panic!("no recovery from the reset: {e}"));
    assert_eq!(target.resumes(), 1, "{:?}", target.stats());
    assert_eq!(after.0, before.0);
    assert_eq!(
        after.1.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
        before.1.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
    );

    // A warm start after another reset cannot resume: it fails clearly.
    qemu.system_reset(&monitor).unwrap();
    std::thread::sleep(std::time::Duration::from_millis(500));
    let warm = SolveParams {
        start: Start::Previous,
        ..params
    };
    let err = target.solve_for(&rhs, warm).unwrap_err();
    assert!(err.to_string().contains("reset mid-session"), "{err}");
    assert_alive(&mut qemu);
    let _ = std::fs::remove_file(&monitor);
}
