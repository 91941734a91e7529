//! Saying that a test skipped, where `cargo test` shows it.
//!
//! libtest captures what `print!`/`eprint!` write from a passing test; a write straight to
//! the process's stderr is not captured, so this line shows in every run (CI's included,
//! which also lists the SKIPPED lines at the end of its log). Used by tests that need
//! something this machine may lack (a V4L2 device, a private mount namespace).

use std::io::Write;

/// Print `SKIPPED: <test>: <reason>` on stderr, past the test harness's output capture.
pub fn skipped(test: &str, reason: &str) {
    let _ = writeln!(std::io::stderr().lock(), "SKIPPED: {test}: {reason}");
}
