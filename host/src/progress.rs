//! Progress bars on stderr for long runs (steps, frames, uploads, flashing): shown on a
//! terminal, hidden otherwise (CI logs, pipes), and never in the way of the firmware's log
//! lines, which print above them ([`crate::firmware_logs::FirmwareLogs::set_progress`]).

use std::io::IsTerminal;

use indicatif::{ProgressBar, ProgressStyle};

/// A bar of `len` units labelled `what`.
pub fn bar(len: u64, what: &str) -> ProgressBar {
    styled(len, what, "{msg:>10} [{bar:40}] {pos}/{len} {elapsed}")
}

/// A bar of `len` bytes (flashing an image).
pub fn byte_bar(len: u64, what: &str) -> ProgressBar {
    styled(
        len,
        what,
        "{msg:>8} [{bar:40}] {bytes}/{total_bytes} {bytes_per_sec} {elapsed}",
    )
}

fn styled(len: u64, what: &str, template: &str) -> ProgressBar {
    if !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(len);
    bar.set_style(
        ProgressStyle::with_template(template)
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    bar.set_message(what.to_string());
    bar
}

/// Moves `bar` with a matrix upload and clears it when the upload is done.
pub fn upload_progress(bar: &ProgressBar) -> impl FnMut(crate::link::UploadProgress) + '_ {
    |p| {
        bar.set_length(p.words_total as u64);
        bar.set_position(p.words_sent as u64);
        if p.words_sent == p.words_total {
            bar.finish_and_clear();
        }
    }
}
