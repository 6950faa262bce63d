//! The one way a test skips (core's tests through `mod common`, silvr-tests' through its library, which
//! includes this file): a line `SKIP: <test>: <why>` that `scripts/test.sh` collects into its summary, or a
//! failure when the run demands what is missing (`SILVR_REQUIRE_GPU=1`, `SILVR_REQUIRE_DATA=1`,
//! `SILVR_REQUIRE_SLURM=1`, `SILVR_REQUIRE_PEERS=1`: CI sets them, so a test cannot pass there by skipping).

use std::io::Write;

/// The line a skip prints: `SKIP: <test>: <why>`.
pub fn skip_line(test: &str, why: &str) -> String {
    format!("SKIP: {test}: {why}")
}

/// Whether `var` demands that the calling test runs (it is set to `1`).
pub fn required(var: &str) -> bool {
    std::env::var(var).as_deref() == Ok("1")
}

/// Skips the calling test: prints [`skip_line`] on the process's stderr (written to the stream itself, past
/// the test harness's capture, so it shows for passing tests too), or panics when `require` (an environment
/// variable) is `1`. The caller returns after it.
pub fn skip(require: &str, why: &str) {
    let thread = std::thread::current();
    // libtest runs each test on a thread named after it.
    let test = thread.name().unwrap_or("unnamed test");
    assert!(
        !required(require),
        "{test}: {why}, and {require}=1 demands that it runs"
    );
    let line = skip_line(test, &format!("{why} (set {require}=1 to fail instead)"));
    let _ = writeln!(std::io::stderr().lock(), "{line}");
}
