//! Helpers shared by the end-to-end tests in `tests/tests/`.

use std::path::PathBuf;
use std::process::Command;

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
/// saying the test skips. With `SILVR_REQUIRE_DATA=1` (CI sets it when `../shared/data` is there) an
/// absent file is a failure instead, so a test cannot pass by skipping silently.
pub fn shared_data(rel: &str) -> Option<PathBuf> {
    let p = workspace_root().join("../shared/data").join(rel);
    if p.exists() {
        return Some(p);
    }
    assert!(
        std::env::var("SILVR_REQUIRE_DATA").as_deref() != Ok("1"),
        "{} is absent and SILVR_REQUIRE_DATA=1",
        p.display()
    );
    eprintln!("skipping: {} absent", p.display());
    None
}

#[cfg(test)]
mod tests {
    /// Absent data skips, unless SILVR_REQUIRE_DATA=1 asks for it (then the panic names the path; the
    /// default panic hook prints it to the log). The only test in this crate's unit tests, so setting the
    /// variable races with nothing.
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
