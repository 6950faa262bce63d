//! Helpers shared by the end-to-end tests in `tests/tests/`.

use std::path::PathBuf;
use std::process::Command;

// The one way a test skips, shared with core's tests (one file, so one format for scripts/test.sh).
#[path = "../../core/tests/common/skip.rs"]
mod skip;
pub use skip::{required, skip, skip_line};

/// The `silvr` binary built by cargo for this test run.
pub fn silvr_bin() -> PathBuf {
    let mut p = workspace_root().join("target");
    if let Ok(dir) = std::env::var("CARGO_TARGET_DIR") {
        p = PathBuf::from(dir);
    }
    let profile = if cfg!(debug_assertions) {
        "debug"
    } else {
        "release"
    };
    p.join(profile).join("silvr")
}

/// Builds the `silvr` binary (once per test process is enough; cargo makes repeats cheap), or, where
/// `SILVR_TESTS_PREBUILT` is set (scripts/test.sh, after `cargo build --workspace --all-targets`), uses the
/// one already built: `cargo build -p silvr` resolves dependency features for that one package, unlike
/// the workspace build, and so compiled image, wgpu, silvr-core and silvr again (~125 s in CI).
pub fn build_silvr() -> PathBuf {
    if std::env::var_os("SILVR_TESTS_PREBUILT").is_some() {
        let bin = silvr_bin();
        assert!(
            bin.is_file(),
            "SILVR_TESTS_PREBUILT is set but {} is missing",
            bin.display()
        );
        return bin;
    }
    let mut cmd = Command::new(env!("CARGO"));
    cmd.current_dir(workspace_root())
        .args(["build", "-q", "-p", "silvr"]);
    if !cfg!(debug_assertions) {
        cmd.arg("--release");
    }
    let status = cmd.status().expect("running cargo build");
    assert!(status.success(), "cargo build -p silvr failed");
    silvr_bin()
}

/// The repository root.
pub fn workspace_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ has a parent")
        .to_path_buf()
}

/// `../shared/data/<rel>` beside the repository, where third-party test data lives, or `None` with a line
/// saying the test skips ([`skip`]). With `SILVR_REQUIRE_DATA=1` (CI sets it when `../shared/data` is
/// there) an absent file is a failure instead, so a test cannot pass by skipping silently.
pub fn shared_data(rel: &str) -> Option<PathBuf> {
    let p = workspace_root().join("../shared/data").join(rel);
    if p.exists() {
        return Some(p);
    }
    skip("SILVR_REQUIRE_DATA", &format!("{} is absent", p.display()));
    None
}

#[cfg(test)]
mod tests {
    /// A skip's line reaches the test binary's stderr although the harness captures a passing test's
    /// output (scripts/test.sh finds it there): run in a child process of this test binary, which skips.
    #[test]
    fn a_skip_prints_its_line_past_the_capture() {
        const NAME: &str = "tests::a_skip_prints_its_line_past_the_capture";
        if std::env::var_os("SILVR_SKIP_CHILD").is_some() {
            super::skip("SILVR_REQUIRE_NOTHING", "the child skips");
            return;
        }
        let out = std::process::Command::new(std::env::current_exe().unwrap())
            .args(["--exact", NAME])
            .env("SILVR_SKIP_CHILD", "1")
            .env_remove("SILVR_REQUIRE_NOTHING")
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{stdout}{err}");
        assert!(stdout.contains("1 passed"), "{stdout}");
        let line = super::skip_line(NAME, "the child skips");
        assert!(err.contains(&line), "no '{line}' in: {err}");
    }

    /// Absent data skips, unless SILVR_REQUIRE_DATA=1 asks for it (then the panic names the path; the
    /// default panic hook prints it to the log). The only test in this crate's unit tests that sets a
    /// variable (the other passes its own to a child), so setting it races with nothing.
    #[test]
    fn shared_data_skips_or_fails_when_absent() {
        std::env::remove_var("SILVR_REQUIRE_DATA");
        assert_eq!(super::shared_data("no/such/capture"), None);
        std::env::set_var("SILVR_REQUIRE_DATA", "1");
        let required = std::panic::catch_unwind(|| super::shared_data("no/such/capture"));
        std::env::remove_var("SILVR_REQUIRE_DATA");
        let msg = required.unwrap_err();
        let msg = msg.downcast_ref::<String>().unwrap();
        assert!(
            msg.contains("no/such/capture") && msg.contains("SILVR_REQUIRE_DATA"),
            "{msg}"
        );
    }
}
