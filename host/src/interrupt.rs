//! Ctrl-C and `kill` end a run cleanly instead of mid-write: the first SIGINT or SIGTERM only
//! raises a flag, which the frame and step loops read between frames ([`requested`]); they
//! stop there, and the command finishes as at the end of its run (the series' `.pvd`, the CSV
//! renamed to its real name, the report, the board and its QEMU closed). A second signal ends
//! the process at once (the handler is reset when it runs).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Once;

static REQUESTED: AtomicBool = AtomicBool::new(false);
static INSTALL: Once = Once::new();

extern "C" fn on_signal(_signal: libc::c_int) {
    // Only an atomic store: what a signal handler may do.
    REQUESTED.store(true, Ordering::SeqCst);
}

/// Installs the handler for SIGINT and SIGTERM (once per process).
pub fn install() {
    INSTALL.call_once(|| {
        for signal in [libc::SIGINT, libc::SIGTERM] {
            // SAFETY: a zeroed sigaction is valid; the handler only stores to an atomic, and
            // SA_RESETHAND makes the next signal take its default action (end the process).
            unsafe {
                let mut action: libc::sigaction = std::mem::zeroed();
                action.sa_sigaction = on_signal as extern "C" fn(libc::c_int) as usize;
                action.sa_flags = libc::SA_RESETHAND | libc::SA_RESTART;
                libc::sigemptyset(&mut action.sa_mask);
                libc::sigaction(signal, &action, std::ptr::null_mut());
            }
        }
    });
}

/// Whether a SIGINT or SIGTERM asked the run to stop. (Tested end to end by the CLI tests,
/// which stop a live session with SIGTERM: a flag raised inside the unit tests' process would
/// stop every other test's loop.)
pub fn requested() -> bool {
    REQUESTED.load(Ordering::SeqCst)
}
