//! The `silvr` binary end to end: help, GPU report, the demo's report, and its errors.

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

/// The ci demo on the WGSL engine (lavapipe in CI), fields trained on the exact poses after the poses
/// stage: every stage of both fields runs on `wgpu`, and the conclusions the CPU reference reached hold
/// there too.
#[test]
fn demo_ci_on_wgsl_reports_lidar_vision_and_silvr_with_silvr_beating_vision() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let run = Command::new(build_silvr())
        .args([
            "demo",
            "--preset",
            "ci",
            "--backend",
            "wgpu",
            "--poses",
            "exact",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    // The poses stage (issue 18's CI check): the SLAM-like prior is off by the documented amounts; the
    // refined poses are ≥ 5x better in camera centres and in rotation, every image registers, and the
    // reprojection RMSE is below a pixel.
    let poses = &report["poses"];
    let prior = &poses["prior"];
    let refined = &poses["refined"];
    let f = |v: &serde_json::Value, k: &str| v[k].as_f64().unwrap_or(f64::NAN);
    let ate = f(prior, "ate_rmse_m");
    assert!(ate > 0.005 && ate < 0.5, "prior ATE {ate} m: {prior}");
    assert!(
        f(refined, "ate_rmse_m") * 5.0 <= ate,
        "refined ATE not 5x below the prior's: {poses}"
    );
    assert!(
        f(refined, "rot_rmse_deg") * 5.0 <= f(prior, "rot_rmse_deg"),
        "refined rotation error not 5x below the prior's: {poses}"
    );
    assert_eq!(poses["registered"], poses["images"], "{poses}");
    assert!(f(poses, "rmse_px") < 1.0, "{poses}");
    // The fields train on the exact poses here (`--poses exact`): this test checks the engine's
    // conclusions, which the measured pose ablation (BENCHMARKS.md) shows the refined poses change (the
    // uncertainty filter's gain above all). The demo's default trains on the refined poses, which carry
    // the prior's frame: their Sim(3) to the exact ones has the prior's ~0.6 % scale drift.
    assert_eq!(poses["trained_on"], "exact", "{poses}");
    let scale = f(&refined["alignment"], "scale");
    assert!((scale - 1.0).abs() < 0.02 && scale != 1.0, "{poses}");
    assert!(
        out.join("poses/colmap/points3D.txt").is_file()
            && out.join("poses/transforms.json").is_file()
    );
    let lidar = &report["methods"]["lidar_only"];
    for key in [
        "accuracy_m",
        "completeness_m",
        "precision_5cm",
        "recall_5cm",
        "fscore_5cm",
        "precision_10cm",
        "recall_10cm",
        "fscore_10cm",
    ] {
        assert!(
            lidar[key].is_number(),
            "methods.lidar_only.{key} missing: {lidar}"
        );
    }
    let acc = lidar["accuracy_m"].as_f64().unwrap();
    assert!(acc < 0.05, "lidar-only accuracy {acc} m");
    assert!(lidar["precision_10cm"].as_f64().unwrap() > 0.95);
    assert!(out.join("lidar_only.ply").is_file() && out.join("dataset/transforms.json").is_file());
    // The studio's browser tests open this demo's reconstructions (scripts/test.sh sets the folder).
    if let Some(dir) = std::env::var_os("SILVR_STUDIO_FIXTURES") {
        let dir = std::path::PathBuf::from(dir);
        std::fs::create_dir_all(&dir).unwrap();
        for (from, to) in [
            ("silvr/points.ply", "points.ply"),
            ("silvr/points_filtered.ply", "points_filtered.ply"),
            ("lidar_only.ply", "lidar_only.ply"),
        ] {
            std::fs::copy(out.join(from), dir.join(to)).unwrap();
        }
    }

    // The trained fields: same geometry keys plus image quality, and SiLVR ahead of vision-only.
    let m = &report["methods"];
    for method in ["vision_only", "silvr"] {
        for key in [
            "accuracy_m",
            "completeness_m",
            "fscore_10cm",
            "psnr",
            "ssim",
        ] {
            assert!(
                m[method][key].is_number(),
                "methods.{method}.{key} missing: {}",
                m[method]
            );
        }
        let t = &report["timing"][method];
        assert!(t["train_s"].as_f64().unwrap() > 0.0, "{t}");
        assert!(t["adapter"].is_string(), "{t}");
        // The WGSL engine ran every stage (the CPU reference must not stand in for it).
        assert_eq!(t["backend"], "wgpu", "{method}: {t}");
        let mut stages = vec!["training", "renders", "export"];
        if method == "silvr" {
            stages.push("uncertainty");
        }
        for stage in stages {
            assert_eq!(t["backends"][stage], "wgpu", "{method} {stage}: {t}");
        }
        assert!(out.join(method).join("points.ply").is_file());
    }
    // The demo's own cross-check, from the trained SiLVR field: WGSL and CPU agree on one batch.
    let x = &report["timing"]["wgsl_crosscheck"];
    assert_eq!(x["step"], 300, "{x}");
    assert!(x["loss_rel_diff"].as_f64().unwrap() < 1e-3, "{x}");
    assert!(x["grad_rel_l2"].as_f64().unwrap() < 1e-2, "{x}");
    let f = |method: &str, key: &str| m[method][key].as_f64().unwrap();
    // Lidar makes the geometry at least 3x more accurate (measured 4.5x with the CPU reference, 4.9x on
    // WGSL / lavapipe).
    assert!(
        3.0 * f("silvr", "accuracy_m") <= f("vision_only", "accuracy_m"),
        "SiLVR accuracy {} m is not 3x better than vision-only {} m",
        f("silvr", "accuracy_m"),
        f("vision_only", "accuracy_m")
    );
    assert!(
        f("silvr", "fscore_10cm") > f("vision_only", "fscore_10cm"),
        "SiLVR F@10cm {} is not above vision-only {}",
        f("silvr", "fscore_10cm"),
        f("vision_only", "fscore_10cm")
    );
    assert!(
        f("silvr", "psnr") > 25.0,
        "SiLVR held-out PSNR {}",
        f("silvr", "psnr")
    );

    // Uncertainty of the SiLVR field: every AUSE well below a random ordering's, the JSON agreeing with
    // its curves, the plots written, the default filter dropping some points, and the read-out at the
    // prior where no ray reaches (under the road) and for depth on the tower beyond lidar range.
    let u = &report["uncertainty"];
    let random = u["ause_random"].as_f64().unwrap();
    assert!(random > 0.3, "random-order AUSE {random}: {u}");
    let dir = out.join("silvr");
    let sp: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("sparsification.json")).unwrap()).unwrap();
    for m in ["colour", "depth", "combined"] {
        let a = u[format!("ause_{m}")].as_f64().unwrap();
        assert!(
            a > 0.0 && a < 0.6 * random,
            "AUSE {m} {a} vs random {random}"
        );
        let c = &sp["curves"][m];
        let xs: Vec<f64> = serde_json::from_value(c["fractions"].clone()).unwrap();
        let un: Vec<f64> = serde_json::from_value(c["uncertainty"].clone()).unwrap();
        let or: Vec<f64> = serde_json::from_value(c["oracle"].clone()).unwrap();
        assert_eq!((xs.len(), un.len(), or.len()), (100, 100, 100));
        let area: f64 = (1..xs.len())
            .map(|i| (xs[i] - xs[i - 1]) * 0.5 * (un[i] - or[i] + un[i - 1] - or[i - 1]))
            .sum();
        assert!(
            (area - a).abs() < 1e-9,
            "{m}: curves give {area}, report {a}"
        );
        assert!(
            or.windows(2).all(|w| w[1] <= w[0] + 1e-12),
            "the oracle curve falls"
        );
        assert!(dir.join(format!("error_vs_{m}.png")).is_file());
    }
    assert!(dir.join("sparsification.png").is_file() && dir.join("uncertainty.bin").is_file());
    let kept = u["filtered"]["kept_points"].as_u64().unwrap();
    let total = u["filtered"]["total_points"].as_u64().unwrap();
    assert!(
        kept < total && kept > total / 2,
        "filter kept {kept} of {total}"
    );
    // The default rule (Tukey's fence on the combined log-std) removes error, not surface: measured on
    // this world, accuracy −32 % for −6 % of recall@10cm; asserted with margin.
    let filt = &u["filtered"];
    let (acc, acc_f) = (
        f("silvr", "accuracy_m"),
        filt["accuracy_m"].as_f64().unwrap(),
    );
    let (rec, rec_f) = (
        f("silvr", "recall_10cm"),
        filt["recall_10cm"].as_f64().unwrap(),
    );
    assert!(acc_f < 0.85 * acc, "filtered accuracy {acc_f} vs {acc}");
    assert!(rec_f > 0.9 * rec, "filtered recall@10cm {rec_f} vs {rec}");
    let lab = &u["by_label"];
    let prior = lab["prior"].as_f64().unwrap();
    let under = lab["under_road_5m"]["combined"].as_f64().unwrap();
    assert!(
        (under - prior).abs() < 0.1,
        "under the road {under} vs prior {prior}"
    );
    let tower = lab["tower"]["depth"].as_f64().unwrap();
    assert!(
        (tower - prior).abs() < 0.1,
        "tower depth {tower} vs prior {prior}"
    );
    for surface in ["road", "facade", "white_wall"] {
        let c = lab[surface]["combined"].as_f64().unwrap();
        assert!(c < prior - 1.5, "{surface}: {c} vs prior {prior}");
    }
    let points = silvr_core::pointcloud::read_ply(&dir.join("points.ply")).unwrap();
    for field in ["log_std_colour", "log_std_depth", "log_std_combined"] {
        let v = points
            .scalar(field)
            .unwrap_or_else(|| panic!("points.ply has no {field}"));
        assert!(v.iter().all(|x| x.is_finite()));
    }
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
