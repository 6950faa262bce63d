//! The `silvr` binary end to end: help, GPU report, a micro demo on refined poses, a killed training run,
//! and their errors. The ci demo on WGSL has a binary of its own (`demo.rs`).

use std::process::Command;

use silvr_tests::build_silvr;

#[test]
fn help_lists_the_commands() {
    let out = Command::new(build_silvr()).arg("--help").output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    for cmd in ["gpu-info", "synth", "eval", "demo"] {
        assert!(text.contains(cmd), "--help lacks {cmd}:\n{text}");
    }
}

#[test]
fn gpu_info_reports_the_adapter_and_a_passing_kernel_check() {
    let out = Command::new(build_silvr())
        .args(["gpu-info", "--json"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(!v["adapter"]["name"].as_str().unwrap().is_empty());
    assert_eq!(v["projection_check"]["winner_mismatches"], 0);
}

#[test]
fn gpu_info_without_a_vulkan_driver_is_a_clear_error() {
    // Point the Vulkan loader at no driver at all.
    let out = Command::new(build_silvr())
        .arg("gpu-info")
        .env("VK_ICD_FILENAMES", "/nonexistent.json")
        .env("VK_DRIVER_FILES", "/nonexistent.json")
        .env("WGPU_BACKEND", "vulkan")
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1), "exit code");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("no GPU adapter found") && err.contains("mesa-vulkan-drivers"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn eval_of_a_missing_file_names_it() {
    let tmp = tempfile::tempdir().unwrap();
    let out = Command::new(build_silvr())
        .args(["eval", "--reconstruction"])
        .arg(tmp.path().join("nope.ply"))
        .arg("--gt")
        .arg(tmp.path())
        .arg("--out")
        .arg(tmp.path().join("r.json"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("cloud.ply") || err.contains("nope.ply"),
        "{err}"
    );
    assert!(!tmp.path().join("r.json").exists(), "no report on failure");
}

/// `silvr train` on the WGSL engine killed with SIGKILL between checkpoints, then `--resume`d: the
/// checkpoint on disk is whole (written to a temporary name and renamed), the run continues from its
/// step to the end, and the loss curve continues where it stopped instead of starting over.
#[cfg(unix)]
#[test]
fn wgsl_training_killed_mid_run_resumes_from_its_last_checkpoint() {
    use silvr_core::train::checkpoint::Checkpoint;
    let silvr = build_silvr();
    let tmp = tempfile::tempdir().unwrap();
    let ds = tmp.path().join("micro");
    let synth = Command::new(&silvr)
        .args(["synth", "--preset", "micro", "--seed", "2", "--out"])
        .arg(&ds)
        .output()
        .unwrap();
    assert!(
        synth.status.success(),
        "{}",
        String::from_utf8_lossy(&synth.stderr)
    );
    let out = tmp.path().join("run");
    let args = |steps: &str| {
        let mut c = Command::new(&silvr);
        c.arg("train")
            .arg(&ds)
            .args([
                "--backend",
                "wgpu",
                "--model",
                "small",
                "--rays",
                "256",
                "--steps",
                steps,
            ])
            .args([
                "--checkpoint-every",
                "10",
                "--export-rays",
                "0",
                "--render-views",
                "0",
            ])
            .arg("--out")
            .arg(&out);
        c
    };
    let ckpt = out.join("checkpoint.ckpt");
    let mut child = args("90")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let t0 = std::time::Instant::now();
    let killed_after = loop {
        if let Ok(ck) = Checkpoint::load(&ckpt) {
            if ck.header.step >= 30 {
                break ck.header.step;
            }
        }
        assert!(
            child.try_wait().unwrap().is_none(),
            "training ended before it could be killed"
        );
        assert!(t0.elapsed().as_secs() < 600, "no checkpoint at step 30");
        std::thread::sleep(std::time::Duration::from_millis(50));
    };
    child.kill().unwrap(); // SIGKILL
    let status = child.wait().unwrap();
    assert!(!status.success(), "the run was to be killed: {status:?}");
    let before = Checkpoint::load(&ckpt).expect("the checkpoint survives SIGKILL whole");
    let at = before.header.step;
    assert!(
        at >= killed_after && at.is_multiple_of(10) && at < 90,
        "checkpoint at step {at}"
    );
    let resumed = args("90").arg("--resume").arg(&ckpt).output().unwrap();
    let err = String::from_utf8_lossy(&resumed.stderr);
    assert!(resumed.status.success(), "{err}");
    assert!(err.contains(&format!("at step {at}")), "{err}");
    let after = Checkpoint::load(&ckpt).unwrap();
    assert_eq!(after.header.step, 90);
    let h = &after.header.history;
    assert_eq!(h.len(), 90);
    // The part before the kill is carried over exactly; the first resumed step continues the curve
    // (a fresh start would be back at the first step's loss, several times higher).
    for (a, b) in before.header.history.iter().zip(h) {
        assert_eq!(a.loss, b.loss);
    }
    let k = at as usize;
    let recent = h[k - 5..k].iter().map(|s| s.loss).sum::<f64>() / 5.0;
    assert!(
        h[k].loss < 1.5 * recent && h[k].loss < 0.5 * h[0].loss,
        "step {k}: loss {} after {recent} (first step {})",
        h[k].loss,
        h[0].loss
    );
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("train.json")).unwrap()).unwrap();
    assert_eq!(json["steps"], 90);
    assert_eq!(json["backend"], "wgpu");
}

/// The demo's default, as a user's data would be: the fields train on the poses stage's refined poses
/// (not the exact ones) and their clouds are scored after the Sim(3) from those poses to the exact ones.
/// The micro world on the CPU reference, labelled as such: this checks the plumbing, not the engine.
#[test]
fn demo_trains_on_the_refined_poses_by_default() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let run = Command::new(build_silvr())
        .args([
            "demo",
            "--preset",
            "micro",
            "--seed",
            "2",
            "--steps",
            "200",
            "--model",
            "tiny",
            "--rays",
            "512",
            "--uncertainty-batches",
            "1",
            "--backend",
            "cpu",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{err}");
    assert!(err.contains("training on the refined poses"), "{err}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let poses = &report["poses"];
    assert_eq!(poses["trained_on"], "refined", "{poses}");
    let scale = poses["alignment"]["scale"].as_f64().unwrap();
    assert!((scale - 1.0).abs() < 0.02 && scale != 1.0, "{poses}");
    assert_eq!(report["timing"]["silvr"]["backend"], "cpu");
    let acc = report["methods"]["silvr"]["accuracy_m"].as_f64().unwrap();
    assert!(acc.is_finite() && acc < 1.0, "{acc}");
    // The training dataset is the poses stage's output, which points back at the world's images.
    let t: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("poses/transforms.json")).unwrap()).unwrap();
    assert!(t["frames"][0]["file_path"]
        .as_str()
        .unwrap()
        .starts_with("../dataset/"));
}
