//! The ci demo end to end on the WGSL engine: the one test of this binary, so that it runs alone.
//!
//! Its own test binary because `cargo test` runs binaries one after another but the tests of one binary
//! side by side: next to other GPU tests, lavapipe's threads and the CPU reference's rayon pool
//! oversubscribe the two cores of a CI machine, and the demo took 617 s instead of 407 s alone.

use std::process::Command;

use silvr_tests::build_silvr;

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
        // The same cloud as COPC, by the CLI (`silvr export copc`): the studio opens it by byte ranges.
        let copc = dir.join("points.copc.laz");
        let run = Command::new(build_silvr())
            .args(["export", "copc"])
            .arg(out.join("silvr/points.ply"))
            .arg("--out")
            .arg(&copc)
            .output()
            .unwrap();
        let said = String::from_utf8_lossy(&run.stdout);
        assert!(
            run.status.success() && said.contains("summary: the default filter"),
            "silvr export copc: {said}{}",
            String::from_utf8_lossy(&run.stderr)
        );
        let (points, summary) = silvr_core::copc::write::read_summary(&copc).unwrap();
        let filtered = silvr_core::pointcloud::read_ply(&out.join("silvr/points_filtered.ply"))
            .unwrap()
            .len();
        let kept = summary.unwrap().filter.unwrap().kept;
        assert_eq!(kept as usize, filtered, "{points} points");
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
    // AUSE / random measured on refined poses: colour 0.51, depth 0.56, combined 0.51 (CPU reference,
    // here, 2026-12-04); depth 0.603 on CI's machine (WGSL on its lavapipe, the same day). A random
    // ordering scores ~1 and an inverted one above 1; 0.7 leaves lavapipe's run-to-run spread room.
    let u = &report["uncertainty"];
    let random = u["ause_random"].as_f64().unwrap();
    assert!(random > 0.3, "random-order AUSE {random}: {u}");
    let dir = out.join("silvr");
    let sp: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("sparsification.json")).unwrap()).unwrap();
    for m in ["colour", "depth", "combined"] {
        let a = u[format!("ause_{m}")].as_f64().unwrap();
        assert!(
            a > 0.0 && a < 0.7 * random,
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
    // this world, accuracy −20.5 % (here) and −12.9 % (CI's machine, 2026-12-04: lavapipe's results differ
    // between machines) for ≤ 6 % of recall@10cm; asserted with margin: a filter that kept points at
    // random would leave accuracy where it was.
    let filt = &u["filtered"];
    let (acc, acc_f) = (
        f("silvr", "accuracy_m"),
        filt["accuracy_m"].as_f64().unwrap(),
    );
    let (rec, rec_f) = (
        f("silvr", "recall_10cm"),
        filt["recall_10cm"].as_f64().unwrap(),
    );
    assert!(acc_f < 0.95 * acc, "filtered accuracy {acc_f} vs {acc}");
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
    // Seen surfaces are constrained: σ in metres (log10), measured here road −1.6 near the car, facade
    // −1.04 (9 cm), against the 1 m prior (0); asserted as ≥ 6× tighter than the prior.
    for surface in ["road", "facade", "white_wall"] {
        let c = lab[surface]["combined"].as_f64().unwrap();
        assert!(c < prior - 0.8, "{surface}: {c} vs prior {prior}");
    }
    let points = silvr_core::pointcloud::read_ply(&dir.join("points.ply")).unwrap();
    for field in ["log_std_colour", "log_std_depth", "log_std_combined"] {
        let v = points
            .scalar(field)
            .unwrap_or_else(|| panic!("points.ply has no {field}"));
        assert!(v.iter().all(|x| x.is_finite()));
    }
}
