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

#[test]
fn demo_ci_reports_lidar_vision_and_silvr_with_silvr_beating_vision() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let run = Command::new(build_silvr())
        .args(["demo", "--preset", "ci", "--out"])
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
        assert!(t["backend"].is_string() && t["adapter"].is_string(), "{t}");
        assert!(out.join(method).join("points.ply").is_file());
    }
    let f = |method: &str, key: &str| m[method][key].as_f64().unwrap();
    assert!(
        f("silvr", "accuracy_m") < f("vision_only", "accuracy_m"),
        "SiLVR accuracy {} m is not better than vision-only {} m",
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
        f("silvr", "psnr") > 23.0,
        "SiLVR held-out PSNR {}",
        f("silvr", "psnr")
    );
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
