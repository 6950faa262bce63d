//! `silvr odometry` (issue 34): a trajectory from the lidar alone, scored against exact ground truth on a
//! synthetic bag (per-point times, deskewed) and on the real KITTI snippets in
//! `../shared/data/real/kitti_odometry` (skipped where absent, required under SILVR_REQUIRE_DATA=1).

use std::path::Path;
use std::process::Command;

use silvr_core::dataset::read_tum;
use silvr_core::synthetic::bag::EPOCH;
use silvr_tests::build_silvr;

/// `silvr eval-poses --est EST --gt GT`, which must succeed: its JSON.
fn eval_poses(est: &Path, gt: &Path) -> serde_json::Value {
    let o = Command::new(build_silvr())
        .args(["eval-poses", "--est"])
        .arg(est)
        .arg("--gt")
        .arg(gt)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap()
}

fn odometry(input: &Path, out: &Path, extra: &[&str]) -> serde_json::Value {
    let o = Command::new(build_silvr())
        .arg("odometry")
        .arg(input)
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{}: {err}", input.display());
    serde_json::from_slice(&o.stdout).unwrap_or_else(|e| panic!("{e}: {err}"))
}

#[test]
fn a_bag_without_a_trajectory_gets_one_from_its_lidar() {
    let tmp = tempfile::tempdir().unwrap();
    let (ds, bag) = (tmp.path().join("micro"), tmp.path().join("micro.mcap"));
    let o = Command::new(build_silvr())
        .args(["synth", "--preset", "micro", "--out"])
        .arg(&ds)
        .arg("--mcap")
        .arg(&bag)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // The exact lidar trajectory, on the bag's clock.
    let exact = read_tum(&ds.join("poses/odometry_lidar_tum.txt")).unwrap();
    let stamps: Vec<f64> = exact.stamps().iter().map(|t| t + EPOCH).collect();
    let shifted = silvr_core::geometry::Trajectory::new(stamps, exact.poses().to_vec()).unwrap();
    let gt = tmp.path().join("gt.tum");
    std::fs::write(&gt, silvr_core::ingest::poses::tum_string(&shifted)).unwrap();

    let out = tmp.path().join("lidar.tum");
    let r = odometry(&bag, &out, &["--gt", gt.to_str().unwrap()]);
    assert_eq!(r["kind"], "bag", "{r}");
    assert_eq!(r["topic"], "/hesai/pandar", "{r}");
    assert_eq!(r["sweeps"], 12, "{r}");
    assert_eq!(r["config"]["deskew"], "auto", "{r}");
    let e = &r["pose_errors"]["errors"];
    assert_eq!(r["pose_errors"]["matched"], 12, "{r}");
    // Measured 8 cm over the 7.7 m walk (sweeps 0.5 s apart, ~10 k points each, turning 4-6° between
    // them; KISS-ICP 1.3.0 on the same points: 28 cm). Standing still would be metres off.
    assert!(e["ate_rmse_m"].as_f64().unwrap() < 0.2, "{e}");
    assert_eq!(e["scale"].as_f64().unwrap(), 1.0, "SE(3), not Sim(3): {e}");
    let traj = read_tum(&out).unwrap();
    assert_eq!(traj.len(), 12);
    // Same input, same bytes (deterministic whatever the thread count).
    let again = tmp.path().join("again.tum");
    odometry(&bag, &again, &[]);
    assert_eq!(std::fs::read(&out).unwrap(), std::fs::read(&again).unwrap());

    // Ingest on it: asked for (--trajectory lidar), and on its own when the bag has no trajectory (here
    // the rig file names a topic the bag lacks), saying so.
    let rig = tmp.path().join("micro.rig.yaml");
    let ingest = |out: &Path, rig: &Path, extra: &[&str]| {
        let o = Command::new(build_silvr())
            .arg("ingest")
            .arg(&bag)
            .arg("--config")
            .arg(rig)
            .arg("--out")
            .arg(out)
            .arg("--json")
            .args(extra)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr).to_string();
        assert!(o.status.success(), "{err}");
        let s: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        (s, err)
    };
    let lidar_ds = tmp.path().join("lidar_ds");
    let (s, _) = ingest(&lidar_ds, &rig, &["--trajectory", "lidar"]);
    assert_eq!(s["trajectory"], "lidar odometry (/hesai/pandar)", "{s}");
    // Asked for, the odometry is no notice (the first sweep's points before its first pose are one).
    assert!(
        !s["notices"]
            .as_array()
            .unwrap()
            .iter()
            .any(|n| n.as_str().unwrap().contains("no trajectory")),
        "{s}"
    );
    assert!(s["keyframes"].as_u64().unwrap() >= 10, "{s}");
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(lidar_ds.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(manifest["source"]["trajectory"], s["trajectory"]);
    let no_traj = tmp.path().join("no_traj.rig.yaml");
    let text = std::fs::read_to_string(&rig).unwrap();
    assert!(text.contains("trajectory_topic: /odometry"));
    std::fs::write(
        &no_traj,
        text.replace(
            "trajectory_topic: /odometry",
            "trajectory_topic: /not_recorded",
        ),
    )
    .unwrap();
    let (s2, err) = ingest(&tmp.path().join("auto_ds"), &no_traj, &[]);
    assert_eq!(s2["trajectory"], s["trajectory"], "{s2}");
    assert!(
        err.contains("notice: no trajectory in the bag (0 pose(s) on '/not_recorded')"),
        "{err}"
    );
    // The camera poses it gives, against the exact ones (Sim(3)): measured 7 cm (ci world: 9 cm).
    let e = eval_poses(&lidar_ds, &ds);
    assert!(e["ate_rmse_m"].as_f64().unwrap() < 0.2, "{e}");

    // The lidar trajectory as the SLAM prior of `silvr poses`, as any other: refined to millimetres
    // (measured 10.1 cm / 1.24° → 4.9 mm / 0.11°; the ci world 10.4 cm / 1.05° → 2.8 mm / 0.05°, on which
    // SiLVR trained to 0.064 m accuracy against vision-only's 0.288 m, 26.3 dB held out: BENCHMARKS.md).
    let refined = tmp.path().join("refined");
    let o = Command::new(build_silvr())
        .arg("poses")
        .arg(&lidar_ds)
        .arg("--out")
        .arg(&refined)
        .arg("--gt")
        .arg(ds.join("transforms.json"))
        .arg("--quiet")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value =
        serde_json::from_slice(&std::fs::read(refined.join("report.json")).unwrap()).unwrap();
    let (prior, fine) = (&r["errors"]["prior"], &r["errors"]["refined"]);
    let ate = |v: &serde_json::Value| v["ate_rmse_m"].as_f64().unwrap();
    assert!(
        ate(fine) < 0.02 && ate(fine) < ate(prior) / 5.0,
        "refined {fine} vs lidar prior {prior}"
    );
    assert!(fine["rot_rmse_deg"].as_f64().unwrap() < 0.5, "{fine}");
}

#[test]
fn kitti_sequences_are_tracked_within_centimetres_and_scored_alike_by_eval_poses() {
    let Some(root) = silvr_tests::shared_data("real/kitti_odometry/sequences") else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    for seq in ["00", "03"] {
        let out = tmp.path().join(format!("{seq}.tum"));
        let gt = tmp.path().join(format!("{seq}_gt.tum"));
        let r = odometry(&root.join(seq), &out, &["--gt-out", gt.to_str().unwrap()]);
        assert_eq!(r["kind"], "kitti", "{r}");
        // KITTI's sweeps are motion-compensated: not deskewed again unless asked.
        assert_eq!(r["config"]["deskew"], "off", "{r}");
        assert_eq!(r["sweeps"], 10, "{r}");
        let e = &r["pose_errors"]["errors"];
        // Measured 2.1 cm (00) and 2.7 cm (03) over 6.7 and 8.5 m; KISS-ICP 1.3.0 on the same points
        // 2.5 and 3.0 cm (BENCHMARKS.md, "Lidar odometry").
        let ate = e["ate_rmse_m"].as_f64().unwrap();
        assert!(ate < 0.04, "{seq}: {e}");
        assert!(e["rpe_trans_rmse_m"].as_f64().unwrap() < 0.04, "{seq}: {e}");
        assert!(e["rpe_rot_rmse_deg"].as_f64().unwrap() < 0.3, "{seq}: {e}");
        // The exported ground truth scores the same trajectory to the same numbers.
        let e2 = eval_poses(&out, &gt);
        assert!(
            (e2["ate_rmse_m"].as_f64().unwrap() - ate).abs() < 1e-6,
            "{e2} vs {e}"
        );
    }
}
