//! The SLAM-like prior of the synthetic world scored against its exact poses (`silvr eval-poses`), and a
//! dataset cut into submaps (`silvr submaps`) that train where they are written, images not copied.

use std::path::Path;
use std::process::Command;

use silvr_tests::build_silvr;

fn silvr(args: &[&str]) -> std::process::Output {
    Command::new(build_silvr()).args(args).output().unwrap()
}

fn ok(args: &[&str]) -> String {
    let out = silvr(args);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "silvr {args:?}: {err}");
    err
}

fn json(p: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
}

/// The micro world (seed 2), generated once per test process.
fn world() -> &'static Path {
    static DIR: std::sync::OnceLock<(tempfile::TempDir, std::path::PathBuf)> =
        std::sync::OnceLock::new();
    &DIR.get_or_init(|| {
        let tmp = tempfile::tempdir().unwrap();
        let data = tmp.path().join("micro");
        ok(&[
            "synth",
            "--preset",
            "micro",
            "--seed",
            "2",
            "--out",
            data.to_str().unwrap(),
        ]);
        (tmp, data)
    })
    .1
}

/// A copy of the micro world at `dest` (for tests that change its files).
fn copy_of_world(dest: &Path) -> std::path::PathBuf {
    let cp = Command::new("cp")
        .arg("-r")
        .arg(world())
        .arg(dest)
        .status()
        .unwrap();
    assert!(cp.success());
    dest.to_path_buf()
}

#[test]
fn the_prior_drifts_within_its_documented_size_and_submaps_train_in_place() {
    let tmp = tempfile::tempdir().unwrap();
    let data = world().to_path_buf();
    let d = data.to_str().unwrap();

    // The prior: present, and wrong by the documented amounts (12 keyframes over ~8 m: drift of a few
    // centimetres, 2 cm / 0.2° noise), while the exact poses score zero against themselves.
    assert!(data.join("transforms_prior.json").is_file());
    assert!(data.join("poses/prior_base_tum.txt").is_file());
    let prior = tmp.path().join("prior.json");
    let said = ok(&[
        "eval-poses",
        "--est",
        data.join("transforms_prior.json").to_str().unwrap(),
        "--gt",
        d,
        "--out",
        prior.to_str().unwrap(),
    ]);
    assert!(said.contains("ATE"), "{said}");
    let e = json(&prior);
    let ate = e["ate_rmse_m"].as_f64().unwrap();
    let rot = e["rot_rmse_deg"].as_f64().unwrap();
    assert!(ate > 0.005 && ate < 0.3, "prior ATE {ate} m");
    assert!(rot > 0.05 && rot < 3.0, "prior rotation error {rot}°");
    assert_eq!(e["frames"], 36);
    let same = tmp.path().join("same.json");
    ok(&[
        "eval-poses",
        "--est",
        d,
        "--gt",
        d,
        "--out",
        same.to_str().unwrap(),
    ]);
    assert!(json(&same)["ate_rmse_m"].as_f64().unwrap() < 1e-9);

    // Candidate pairs from the prior: every camera's consecutive frames, fewer than all pairs, and
    // never the left and right cameras of one instant (they look apart).
    let pairs = tmp.path().join("pairs.txt");
    let said = ok(&[
        "pairs",
        data.join("transforms_prior.json").to_str().unwrap(),
        "--out",
        pairs.to_str().unwrap(),
    ]);
    assert!(said.contains("candidate pairs of 630 possible"), "{said}");
    let text = std::fs::read_to_string(&pairs).unwrap();
    let lines: Vec<(&str, &str)> = text.lines().map(|l| l.split_once(' ').unwrap()).collect();
    assert!(
        lines.len() > 36 && lines.len() < 630,
        "{} pairs",
        lines.len()
    );
    for cam in ["cam_front", "cam_left", "cam_right"] {
        for k in 0..11 {
            let (a, b) = (
                format!("images/{cam}/{k:05}.png"),
                format!("images/{cam}/{:05}.png", k + 1),
            );
            assert!(lines.contains(&(a.as_str(), b.as_str())), "{a} {b} missing");
        }
    }
    for k in 0..12 {
        let (l, r) = (
            format!("images/cam_left/{k:05}.png"),
            format!("images/cam_right/{k:05}.png"),
        );
        assert!(
            !lines
                .iter()
                .any(|&(a, b)| (a == l && b == r) || (a == r && b == l)),
            "{l} with {r}"
        );
    }

    // Two submaps by distance with a metre of overlap.
    let subs = tmp.path().join("out").join("subs");
    let said = ok(&[
        "submaps",
        d,
        "--out",
        subs.to_str().unwrap(),
        "--count",
        "2",
        "--overlap",
        "1.0",
    ]);
    assert!(said.contains("2 submaps of 12 keyframes"), "{said}");
    let manifest = json(&subs.join("manifest.json"));
    let parts = manifest["submaps"].as_array().unwrap();
    assert_eq!(parts.len(), 2);
    let mut own: Vec<u64> = parts
        .iter()
        .flat_map(|p| {
            p["keyframes"]
                .as_array()
                .unwrap()
                .iter()
                .map(|k| k.as_u64().unwrap())
        })
        .collect();
    own.sort_unstable();
    assert_eq!(
        own,
        (0..12).collect::<Vec<_>>(),
        "each keyframe in exactly one submap"
    );
    for p in parts {
        // Contiguous stretches of the street, and some overlap across the cut.
        let k: Vec<u64> = p["keyframes"]
            .as_array()
            .unwrap()
            .iter()
            .map(|k| k.as_u64().unwrap())
            .collect();
        assert_eq!(k.last().unwrap() - k[0] + 1, k.len() as u64, "{k:?}");
        assert!(!p["overlap"].as_array().unwrap().is_empty(), "{p}");
    }
    assert!(subs.join("submaps.png").is_file());
    // Each submap's files resolve from its own folder (the images stay in the dataset).
    let dir = subs.join("submap_00");
    let tf = json(&dir.join("transforms.json"));
    for f in tf["frames"].as_array().unwrap() {
        for k in ["file_path", "depth_file_path"] {
            let p = f[k].as_str().unwrap();
            assert!(p.starts_with("../../"), "{p}");
            assert!(dir.join(p).is_file(), "{p}");
        }
    }
    assert!(!std::fs::read_dir(&dir).unwrap().any(|e| e
        .unwrap()
        .path()
        .extension()
        .is_some_and(|x| x == "png")));
    ok(&[
        "train",
        dir.to_str().unwrap(),
        "--backend",
        "cpu",
        "--steps",
        "2",
        "--rays",
        "32",
        "--model",
        "tiny",
        "--export-rays",
        "0",
        "--render-views",
        "0",
        "--out",
        tmp.path().join("trained").to_str().unwrap(),
        // The submap names the world's images from beside it (both in the temporary folder).
        "--data-root",
        std::env::temp_dir().to_str().unwrap(),
    ]);

    // Co-visibility (from the lidar depth): the same street cut where less structure is shared, and
    // both cuts scored by it.
    let by_covis = tmp.path().join("covis");
    ok(&[
        "submaps",
        d,
        "--out",
        by_covis.to_str().unwrap(),
        "--method",
        "covis",
        "--count",
        "2",
    ]);
    let mc = json(&by_covis.join("manifest.json"));
    assert_eq!(mc["method"], "covis");
    let frac = |m: &serde_json::Value| {
        let c = &m["covis_cut"];
        c["shared"].as_f64().unwrap() / c["total"].as_f64().unwrap()
    };
    let (fc, fd) = (frac(&mc), frac(&manifest));
    println!("co-visible structure across the cut: covis {fc:.3}, distance {fd:.3}");
    // Not below: on this short straight street both cut between the same keyframes (measured 0.485 and
    // 0.485); the strict claim is checked on SfM tracks, in
    // `poses_refines_the_prior_and_names_a_textureless_image`.
    assert!(fc > 0.0 && fc <= fd + 1e-9, "covis {fc} vs distance {fd}");

    // Refusals name the problem: an existing output, co-visibility without lidar depth.
    let again = silvr(&["submaps", d, "--out", subs.to_str().unwrap()]);
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("exists"));
    let mut tf = json(&data.join("transforms.json"));
    for f in tf["frames"].as_array_mut().unwrap() {
        f.as_object_mut().unwrap().remove("depth_file_path");
    }
    // Beside the dataset's own file, so its relative paths resolve.
    let camera_only = data.join("camera_only.json");
    std::fs::write(&camera_only, serde_json::to_vec(&tf).unwrap()).unwrap();
    let covis = silvr(&[
        "submaps",
        camera_only.to_str().unwrap(),
        "--out",
        tmp.path().join("c").to_str().unwrap(),
        "--method",
        "covis",
    ]);
    assert!(!covis.status.success());
    assert!(String::from_utf8_lossy(&covis.stderr).contains("lidar depth"));
}

/// `silvr reconstruct` on the local scheduler: two covis submaps trained on WGSL with their uncertainty,
/// merged with a submap id per point and scored against ground truth; a submap that fails (a corrupt
/// image only it sees) is reported and left out while the other finishes (and nothing is rendered); the
/// rerun after the fix keeps the finished submap and trains only the failed one, plus the `--single`
/// baseline, scores the boundary zone and renders boundary views blended from both submaps on WGSL; a
/// rerun after a killed task and a changed input redoes only what they touch; other settings redo all.
#[test]
fn reconstruct_trains_each_submap_merges_and_resumes() {
    let tmp = tempfile::tempdir().unwrap();
    // A copy of the world: one of its images gets broken and mended.
    let data = copy_of_world(&tmp.path().join("micro"));
    let d = data.to_str().unwrap();
    let image = data.join("images/cam_front/00011.png");
    let good = std::fs::read(&image).unwrap();
    std::fs::write(&image, b"not a PNG").unwrap();
    let out = tmp.path().join("rec");
    let o = out.to_str().unwrap();
    let args = [
        "reconstruct",
        d,
        "--out",
        o,
        "--poses",
        "skip",
        "--count",
        "2",
        "--model",
        "tiny",
        "--steps",
        "200",
        "--rays",
        "256",
        "--backend",
        "wgpu",
        "--export-rays",
        "8192",
        "--uncertainty-batches",
        "2",
        "--renders",
        "4",
    ];
    let broken = silvr(&args);
    let said = String::from_utf8_lossy(&broken.stderr).into_owned();
    assert!(!broken.status.success(), "{said}");
    assert!(
        said.contains("submap_01 failed") && said.contains("00011.png"),
        "{said}"
    );
    assert!(said.contains("1 of 2 submaps failed (submap_01)"), "{said}");
    let report = json(&out.join("report.json"));
    assert_eq!(report["failed"][0]["name"], "submap_01");
    assert!(out.join("train/submap_01.error.txt").is_file());
    let merged = silvr_core::pointcloud::read_ply(&out.join("merged.ply")).unwrap();
    assert!(merged.scalar("submap").unwrap().iter().all(|&s| s == 0.0));
    // No renders of an incomplete map.
    assert!(report["renders"].is_null() && !out.join("renders").exists());

    // Mended: the rerun keeps submap_00, trains submap_01, and (`--single`, a task of its own) one
    // field over all images as the merged map's baseline.
    std::fs::write(&image, good).unwrap();
    let mut args = args.to_vec();
    args.push("--single");
    let said = ok(&args);
    assert!(said.contains("submap_00 (1/3): done earlier"), "{said}");
    assert!(said.contains("submap_01 (2/3): training"), "{said}");
    assert!(said.contains("single (3/3): training"), "{said}");
    assert!(!out.join("train/submap_01.error.txt").exists());
    let report = json(&out.join("report.json"));
    assert!(report["failed"].as_array().unwrap().is_empty());
    assert_eq!(report["per_submap"].as_array().unwrap().len(), 2);
    assert_eq!(report["submaps"]["method"], "covis");
    let merged = silvr_core::pointcloud::read_ply(&out.join("merged.ply")).unwrap();
    let ids = merged.scalar("submap").unwrap();
    assert!(
        ids.contains(&0.0) && ids.contains(&1.0),
        "both submaps in the merge"
    );
    assert!(merged.scalar("log_std_combined").is_some());
    // The same map as LAZ 1.4 for survey tools (issue 33): every point, its fields as extra bytes.
    let laz = silvr_core::eval::scan::read_scan(&out.join("merged.laz"), None, None).unwrap();
    assert_eq!(laz.cloud.len(), merged.len());
    let laz_bytes = std::fs::read(out.join("merged.laz")).unwrap();
    assert!(
        laz_bytes.windows(16).any(|w| w == b"log_std_combined"),
        "merged.laz names log_std_combined in its extra bytes"
    );
    // Every merged point (unfiltered) as COPC for the studio (issue 36), with the summary of the default
    // filter over the whole map: the count the native filter keeps of the same points.
    let copc = out.join("merged_unfiltered.copc.laz");
    let all = silvr_core::pointcloud::read_ply(&out.join("merged_unfiltered.ply")).unwrap();
    let (points, summary) = silvr_core::copc::write::read_summary(&copc).unwrap();
    assert_eq!(points, all.len() as u64);
    let v = all.scalar("log_std_combined").unwrap();
    let t = silvr_core::uncertainty::filter::default_threshold(v);
    assert_eq!(
        summary.expect("the summary VLR").filter.unwrap().kept as usize,
        v.iter().filter(|&&x| x <= t).count()
    );
    let read = silvr_core::eval::scan::read_scan(&copc, None, None).unwrap();
    assert_eq!(read.cloud.len(), all.len());
    let kept: u64 = report["per_submap"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["kept"].as_u64().unwrap())
        .sum();
    assert!(
        merged.len() as u64 <= kept && merged.len() > 100,
        "{} of {kept}",
        merged.len()
    );
    let ev = &report["evaluation"];
    for key in [
        "filtered",
        "unfiltered",
        "single_unfiltered",
        "boundary_filtered",
    ] {
        let acc = ev[key]["accuracy_m"].as_f64().unwrap_or(f64::NAN);
        assert!(acc.is_finite() && acc > 0.0, "{key}: {acc}");
    }
    assert!(
        report["single"]["heldout_psnr_mean"].as_f64().unwrap() > 10.0,
        "{report}"
    );
    // The merged map's uncertainty filter, as the README claims it. The default rule (Tukey's fence on the
    // combined log-std: points_filtered.ply) never makes the map less accurate and costs at most the
    // paper's 10 % of completeness (GT within 10 cm); where it drops points, the filtered map is the more
    // accurate (gain > 0). In this run it drops none (measured 2026-12-04, also at 600 steps: each submap's
    // log-std is bounded above by the prior's, where no uncertainty ray reaches a cell, and bunched below
    // it, so Q3 + 1.5 IQR lies above the largest value), so its gain is asserted on the filter curve
    // below, which ranks the same log-std.
    let f = |c: &serde_json::Value, k: &str| c[k].as_f64().unwrap();
    let (acc_u, acc_f) = (
        f(&ev["unfiltered"], "accuracy_m"),
        f(&ev["filtered"], "accuracy_m"),
    );
    let claims = &ev["claims"];
    let (gain, loss) = (
        f(claims, "filter_accuracy_gain"),
        f(claims, "filter_completeness_loss_at_10cm"),
    );
    let points: u64 = report["per_submap"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["points"].as_u64().unwrap())
        .sum();
    println!(
        "default filter: kept {kept} of {points} submap points; merged accuracy {acc_u:.4} -> {acc_f:.4} m \
         (gain {gain:+.3}), completeness loss {loss:+.3}"
    );
    assert!((gain - (1.0 - acc_f / acc_u)).abs() < 1e-9, "{claims}");
    assert!(acc_f <= acc_u && gain >= 0.0 && loss <= 0.10, "{claims}");
    if kept < points {
        assert!(
            gain > 0.0,
            "the filter dropped points and gained nothing: {claims}"
        );
    }
    // Each submap scored on its own clouds against the part of the GT its cameras saw (exact depth).
    let per_submap = report["per_submap"].as_array().unwrap();
    let seen = ev["per_submap_seen"]["submaps"].as_array().unwrap();
    let gt_all = ev["filtered"]["counts"]["gt_input"].as_u64().unwrap();
    assert_eq!(seen.len(), per_submap.len(), "{}", ev["per_submap_seen"]);
    for (s, p) in seen.iter().zip(per_submap) {
        assert_eq!(s["name"], p["name"]);
        let n = s["gt_points_seen"].as_u64().unwrap();
        assert!(
            n > 0 && n < gt_all,
            "{}: {n} of {gt_all} GT points seen",
            s["name"]
        );
        assert_eq!(s["filtered"]["counts"]["gt_input"].as_u64(), Some(n));
        assert_eq!(s["filtered"]["counts"]["reconstruction_input"], p["kept"]);
        assert_eq!(
            s["unfiltered"]["counts"]["reconstruction_input"],
            p["points"]
        );
        let acc = s["filtered"]["accuracy_m"].as_f64().unwrap_or(f64::NAN);
        assert!(acc.is_finite() && acc > 0.0, "{s}");
    }
    assert!(ev["per_submap_seen"]["mean_accuracy_m"]["filtered"]
        .as_f64()
        .is_some_and(f64::is_finite));
    // The filter curve starts at the unfiltered merged map and keeps fewer points at each step; the
    // report's charts are written beside it.
    let curve = ev["filter_curve"].as_array().unwrap();
    assert_eq!(curve.len(), 6, "{curve:?}");
    assert!(
        (f(&curve[0], "accuracy_m") - f(&ev["unfiltered"], "accuracy_m")).abs() < 1e-6,
        "{curve:?}"
    );
    assert!(curve
        .windows(2)
        .all(|w| f(&w[1], "kept_fraction") < f(&w[0], "kept_fraction")));
    // The uncertainty ranks error: every step (the most uncertain 10 % … 50 % dropped) is more accurate
    // than the unfiltered map, and dropping 10 % gains accuracy at less than 10 % completeness loss
    // (measured in three runs of this test's settings, 2026-12-04: +1.4 % for 4.4 %, +1.4 % for 4.5 %; at
    // 600 steps +1.5 % for 3.6 %; with the metric, calibrated read-out: +1.4 % for 6.6 %: the bound is
    // the paper's). How much more the later steps gain is not asserted: this test's fields are 0.36 m
    // off (a few steps on tiny images), and on them the per-ray read-out gained 4.5-5.0 % at 30 %, the
    // metric one 0.6 % (its ranking differs where a cell's vertices mix the prior with data, and in
    // weighing depth by the lidar's 2 cm noise rather than the loss schedule's final 3 cm).
    let gain_at = |c: &serde_json::Value| 1.0 - f(c, "accuracy_m") / f(&curve[0], "accuracy_m");
    let loss_at = |c: &serde_json::Value| 1.0 - f(c, "recall_10cm") / f(&curve[0], "recall_10cm");
    println!(
        "filter curve (kept, gain, completeness loss): {:?}",
        curve
            .iter()
            .map(|c| (f(c, "kept_fraction"), gain_at(c), loss_at(c)))
            .collect::<Vec<_>>()
    );
    assert!(curve[1..].iter().all(|c| gain_at(c) > 0.0), "{curve:?}");
    assert!(loss_at(&curve[1]) < 0.10, "{curve:?}");
    // That co-visibility cuts fewer shared views than distance is asserted where the cut differs:
    // `poses_refines_the_prior_and_names_a_textureless_image` (SfM tracks, the paper's co-visibility; on
    // the lidar's voxels this short straight street is cut in the same place by both, see
    // `the_prior_drifts_within_its_documented_size_and_submaps_train_in_place`).
    for png in ev["plots"].as_array().unwrap() {
        let bytes = std::fs::read(out.join(png.as_str().unwrap())).unwrap();
        assert!(bytes.starts_with(b"\x89PNG"), "{png}");
    }
    assert_eq!(ev["plots"].as_array().unwrap().len(), 2);
    // The boundary zone is part of the merged map: no more points than it.
    assert!(
        ev["boundary_filtered"]["counts"]["reconstruction_input"]
            .as_u64()
            .unwrap()
            <= merged.len() as u64
    );
    // Blended renders at the boundary: the micro world is synthetic, so the path is its keyframe
    // midpoints, photographed by the generator; each view rendered by both submaps (WGSL) and blended.
    let r = &report["renders"];
    assert_eq!(r["path"], "synthetic keyframe midpoints", "{r}");
    assert!(r["backend"].as_str().unwrap() != "cpu (rayon)", "{r}");
    let views = r["views"].as_array().unwrap();
    assert_eq!(views.len(), 4, "{r}");
    for v in views {
        let a = v["alpha_silvr"].as_f64().unwrap();
        assert!(
            (0.5 - 1e-9..=1.0).contains(&a) && v["second_m"].as_f64().unwrap() < 2.0,
            "{v}"
        );
        for s in [
            "nearest_only",
            "second_only",
            "blended_silvr",
            "blended_idw",
        ] {
            let p = v[s]["psnr"].as_f64().unwrap();
            assert!(p > 10.0 && p < 60.0, "{s}: {v}");
        }
        assert_ne!(v["nearest"], v["second"]);
        assert!(Path::new(v["strip"].as_str().unwrap()).is_file(), "{v}");
    }
    for k in ["mean_psnr_nearest", "mean_psnr_blended_silvr"] {
        assert!(r[k].as_f64().unwrap() > 10.0, "{k}: {r}");
    }

    // A submap whose run did not finish (no train.json: killed) is trained again; the finished one is kept.
    // An input file changed since (rewritten: a new modification time) redoes the tasks that read it — the
    // single field, and submap_01, which holds it — and the cut before them, but not submap_00.
    // (No renders from here on: they were checked above.)
    let at = args.iter().position(|a| *a == "--renders").unwrap();
    args[at + 1] = "0";
    std::fs::remove_file(out.join("train/submap_01/train.json")).unwrap();
    std::thread::sleep(std::time::Duration::from_millis(20));
    std::fs::write(&image, std::fs::read(&image).unwrap()).unwrap();
    let said = ok(&args);
    assert!(said.contains("changed since the last run"), "{said}");
    assert!(said.contains("submap_00 (1/3): done earlier"), "{said}");
    assert!(said.contains("submap_01 (2/3): training"), "{said}");
    assert!(said.contains("single (3/3): training"), "{said}");
    assert!(
        json(&out.join("report.json"))["merged_points"]
            .as_u64()
            .unwrap()
            > 100
    );

    // The folder records how it was cut: another cut on it is refused, not mixed in.
    let other = silvr(&["reconstruct", d, "--out", o, "--count", "3"]);
    assert!(!other.status.success());
    assert!(String::from_utf8_lossy(&other.stderr).contains("other options"));
    // Other settings retrain every submap (each records what it was trained with).
    let mut more = args.to_vec();
    let at = more.iter().position(|a| *a == "200").unwrap();
    more[at] = "150";
    let said = ok(&more);
    assert!(
        said.contains("submap_00 (1/3): training")
            && said.contains("submap_01 (2/3): training")
            && said.contains("single (3/3): training"),
        "{said}"
    );
}

/// `silvr reconstruct` killed with SIGKILL in the middle of its second submap: every output already
/// there is whole (each JSON parses, each PLY reads: stages write under a temporary name, then rename),
/// and the rerun finishes with the same merged map as a run never interrupted (CPU reference: the same
/// bits on every run, which the equality needs).
#[test]
fn reconstruct_killed_at_any_moment_finishes_with_the_same_map() {
    let tmp = tempfile::tempdir().unwrap();
    // A copy without the generator's manifest: to the renders, a capture like any other.
    let data = copy_of_world(&tmp.path().join("capture"));
    std::fs::remove_file(data.join("manifest.json")).unwrap();
    let d = data.to_str().unwrap().to_string();
    let args = |out: &Path| -> Vec<String> {
        [
            "reconstruct",
            &d,
            "--out",
            out.to_str().unwrap(),
            "--poses",
            "skip",
            "--count",
            "2",
            "--model",
            "tiny",
            "--steps",
            "60",
            "--rays",
            "256",
            "--backend",
            "cpu",
            "--export-rays",
            "4096",
            "--uncertainty-batches",
            "1",
            "--renders",
            "0",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect()
    };
    let clean = tmp.path().join("clean");
    let a = args(&clean);
    ok(&a.iter().map(String::as_str).collect::<Vec<_>>());

    let out = tmp.path().join("killed");
    let b = args(&out);
    let mut child = Command::new(build_silvr())
        .args(&b)
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let t = std::time::Instant::now();
    while !out.join("train/submap_01").exists() {
        assert!(t.elapsed().as_secs() < 300, "submap_01 never started");
        assert!(
            child.try_wait().unwrap().is_none(),
            "finished before the kill"
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    std::thread::sleep(std::time::Duration::from_millis(300));
    child.kill().unwrap();
    child.wait().unwrap();
    // What is there under its final name is whole.
    let mut files = vec![out.clone()];
    let mut seen = 0;
    while let Some(p) = files.pop() {
        if p.is_dir() {
            for e in std::fs::read_dir(&p).unwrap() {
                files.push(e.unwrap().path());
            }
            continue;
        }
        let name = p.file_name().unwrap().to_string_lossy().into_owned();
        if name.starts_with('.')
            || p.components()
                .any(|c| c.as_os_str().to_string_lossy().ends_with(".partial"))
        {
            continue;
        }
        if name.ends_with(".json") {
            serde_json::from_slice::<serde_json::Value>(&std::fs::read(&p).unwrap())
                .unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            seen += 1;
        } else if name.ends_with(".ply") {
            silvr_core::pointcloud::read_ply(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            seen += 1;
        }
    }
    assert!(seen >= 3, "{seen} outputs checked");
    assert!(!out.join("merged.ply").exists(), "killed before the merge");
    // The rerun (with renders now: of a capture, along its held-out frames) finishes the same map.
    let mut b: Vec<&str> = b.iter().map(String::as_str).collect();
    *b.last_mut().unwrap() = "2";
    let said = ok(&b);
    assert!(said.contains("submap_00 (1/2): done earlier"), "{said}");
    assert!(
        std::fs::read(out.join("merged.ply")).unwrap()
            == std::fs::read(clean.join("merged.ply")).unwrap(),
        "the resumed run's merged map differs from the clean run's"
    );
    let r = json(&out.join("renders/report.json"));
    assert_eq!(r["path"], "held-out frames", "{r}");
    assert_eq!(r["path_views"], 3, "{r}");
    for v in r["views"].as_array().unwrap() {
        assert!(v["blended_silvr"]["psnr"].as_f64().unwrap() > 10.0, "{v}");
    }
}

/// `silvr poses` on the micro world's SLAM prior: every image registers, the refined poses beat the
/// prior against the exact ones (the ci world's ≥ 5x check runs in the demo test), and the output is a
/// dataset: its transforms.json reaches the dataset's images from where it is written, and the COLMAP
/// model reads back. A textureless image is named as not registered (with why), never a panic, while its
/// keyframe's other cameras still carry it; a folder that exists is refused before any work.
#[test]
fn poses_refines_the_prior_and_names_a_textureless_image() {
    let tmp = tempfile::tempdir().unwrap();
    let data = world();
    let out = tmp.path().join("poses");
    let said = ok(&[
        "poses",
        data.join("transforms_prior.json").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--gt",
        data.join("transforms.json").to_str().unwrap(),
    ]);
    assert!(said.contains("registered 36/36"), "{said}");
    let r = json(&out.join("report.json"));
    let (prior, refined) = (&r["errors"]["prior"], &r["errors"]["refined"]);
    let f = |v: &serde_json::Value, k: &str| v[k].as_f64().unwrap();
    assert!(
        f(refined, "ate_rmse_m") * 2.0 < f(prior, "ate_rmse_m")
            && f(refined, "rot_rmse_deg") * 2.0 < f(prior, "rot_rmse_deg"),
        "{r}"
    );
    assert!(f(&r["poses"], "rmse_px") < 1.0, "{r}");
    // The refined poses are put back in the prior's frame (the prior's vertical: their alignment's rotation
    // is the prior's within 0.2°, measured 0.03°; fitting centres alone once let a straight path roll 3°
    // about itself), then to the lidar's metric scale: within 1 % of the exact poses' (measured 0.5 %,
    // the prior's 0.7 %).
    let rot = |v: &serde_json::Value| {
        let q = &v["alignment"]["rot"];
        glam::DQuat::from_xyzw(
            q[0].as_f64().unwrap(),
            q[1].as_f64().unwrap(),
            q[2].as_f64().unwrap(),
            q[3].as_f64().unwrap(),
        )
    };
    let between = rot(prior).angle_between(rot(refined)).to_degrees();
    let scale = f(&refined["alignment"], "scale");
    assert!(
        between < 0.2 && (scale - 1.0).abs() < 1e-2,
        "{between}° {scale}: {r}"
    );
    assert_eq!(r["poses"]["lidar_scale"]["applied"], true, "{r}");
    assert!(!tmp.path().join(".poses.partial").exists());
    let t = json(&out.join("transforms.json"));
    let frames = t["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 36);
    for fr in frames {
        for k in ["file_path", "depth_file_path", "sky_mask_path"] {
            let p = out.join(fr[k].as_str().unwrap());
            assert!(p.is_file(), "{} does not resolve", p.display());
        }
    }
    let model = silvr_core::ingest::colmap::read_model(&out.join("colmap")).unwrap();
    assert_eq!(model.images.len(), 36);
    assert!(model.points.len() > 300, "{} points", model.points.len());

    // The poses output cut into submaps by co-visibility counts shared SfM tracks (the paper's), and
    // that cut splits fewer shared tracks than the distance baseline's on the same images (the README's
    // "co-visibility cut weight below distance's"; the reconstruct test points here).
    let mut track_cut = Vec::new();
    for method in ["covis", "distance"] {
        let dir = tmp.path().join(format!("sub-{method}"));
        ok(&[
            "submaps",
            out.to_str().unwrap(),
            "--out",
            dir.to_str().unwrap(),
            "--method",
            method,
            "--count",
            "2",
            // The poses output names the world's lidar images from beside it.
            "--data-root",
            std::env::temp_dir().to_str().unwrap(),
        ]);
        let m = json(&dir.join("manifest.json"));
        if method == "covis" {
            assert_eq!(m["covis_source"], "tracks", "{m}");
        }
        let c = &m["track_cut"];
        assert!(c["total"].as_f64().unwrap() > 0.0, "{m}");
        track_cut.push(c["shared"].as_f64().unwrap());
        // Every image in at least one submap.
        let mut seen = std::collections::BTreeSet::new();
        for s in m["submaps"].as_array().unwrap() {
            seen.extend(
                s["frames"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|v| v.as_u64().unwrap()),
            );
        }
        assert_eq!(seen.len(), 36, "{m}");
    }
    // Measured 3439 vs 3627 shared tracks (37.5 % vs 39.6 %); the poses stage is deterministic.
    assert!(
        track_cut[0] < track_cut[1],
        "covis {} vs distance {}",
        track_cut[0],
        track_cut[1]
    );

    // One image replaced by flat grey: named, with the reason; the rest still register. And all three
    // images of keyframe 6: nothing ties that keyframe to the others by features, so the match graph falls
    // apart into two parts, said and named (the run still refines what it can).
    let grey = tmp.path().join("grey.png");
    image::RgbImage::from_pixel(180, 135, image::Rgb([128, 128, 128]))
        .save(&grey)
        .unwrap();
    let mut prior = json(&data.join("transforms_prior.json"));
    let mut victim = String::new();
    for (i, fr) in prior["frames"]
        .as_array_mut()
        .unwrap()
        .iter_mut()
        .enumerate()
    {
        for k in [
            "file_path",
            "depth_file_path",
            "normal_file_path",
            "sky_mask_path",
        ] {
            if let Some(p) = fr[k].as_str() {
                fr[k] = data.join(p).to_str().unwrap().into();
            }
        }
        if i == 4 {
            victim = fr["file_path"].as_str().unwrap().to_string();
            fr["file_path"] = grey.to_str().unwrap().into();
        }
        if fr["keyframe"] == 6 {
            let alone = tmp.path().join(format!("alone-{i}.png"));
            std::fs::copy(&grey, &alone).unwrap();
            fr["file_path"] = alone.to_str().unwrap().into();
        }
    }
    let pj = tmp.path().join("prior.json");
    std::fs::write(&pj, serde_json::to_vec(&prior).unwrap()).unwrap();
    let out2 = tmp.path().join("poses2");
    let said = ok(&[
        "poses",
        pj.to_str().unwrap(),
        "--out",
        out2.to_str().unwrap(),
    ]);
    assert!(
        said.contains("not registered") && said.contains("grey.png") && said.contains("features"),
        "{said}"
    );
    assert!(said.contains("registered 32/36"), "{said}");
    assert!(said.contains("falls apart into 2 parts"), "{said}");
    let part2 = said
        .lines()
        .find(|l| l.contains("part 2:"))
        .unwrap_or_else(|| panic!("no part 2 named: {said}"));
    assert!(
        part2.contains("3 images")
            && part2.contains("alone-18.png")
            && part2.contains("alone-20.png"),
        "{part2}"
    );
    let r2 = json(&out2.join("report.json"));
    assert_eq!(r2["poses"]["components"], 2, "{r2}");
    for im in r2["poses"]["per_image"].as_array().unwrap() {
        let alone = im["name"].as_str().unwrap().contains("alone-");
        assert_eq!(im["part"], if alone { 1 } else { 0 }, "{im}");
    }
    assert!(!victim.is_empty());
    // Refused: the folder exists.
    let again = silvr(&[
        "poses",
        pj.to_str().unwrap(),
        "--out",
        out2.to_str().unwrap(),
    ]);
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("exists"));
}

/// A capture whose poses are good, perturbed (`silvr perturb-poses`: the rig moves as one, so the cameras
/// of a keyframe keep their distances), with one listed image missing: `silvr poses` leaves the missing
/// frame out and names it (as the training loader does), registers the rest and brings the poses back
/// towards the exact ones (measured 4.3x in ATE and 3x in rotation on this world). With `--downscale`
/// the features come from smaller images while the COLMAP model stays at full resolution; a downscale that
/// leaves nothing to find features in is refused.
#[test]
fn poses_undoes_a_perturbation_and_leaves_out_a_missing_image() {
    let tmp = tempfile::tempdir().unwrap();
    let data = world();
    let pert = tmp.path().join("pert");
    ok(&[
        "perturb-poses",
        data.to_str().unwrap(),
        "--out",
        pert.to_str().unwrap(),
        "--noise",
        "0.03",
        "--noise-deg",
        "0.3",
        "--seed",
        "3",
    ]);
    let centres = |t: &serde_json::Value| -> Vec<(u64, [f64; 3])> {
        t["frames"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| {
                let m = &f["transform_matrix"];
                let c = |r: usize| m[r][3].as_f64().unwrap();
                (f["keyframe"].as_u64().unwrap(), [c(0), c(1), c(2)])
            })
            .collect()
    };
    let exact = centres(&json(&data.join("transforms.json")));
    let mut moved_json = json(&pert.join("transforms.json"));
    let moved = centres(&moved_json);
    let dist = |a: [f64; 3], b: [f64; 3]| {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
    };
    let mut shift = 0.0;
    for i in 0..exact.len() {
        shift += dist(exact[i].1, moved[i].1) / exact.len() as f64;
        for j in 0..exact.len() {
            if exact[i].0 == exact[j].0 {
                let (d0, d1) = (dist(exact[i].1, exact[j].1), dist(moved[i].1, moved[j].1));
                assert!((d0 - d1).abs() < 1e-9, "rig {i}-{j}: {d0} vs {d1}");
            }
        }
    }
    assert!(shift > 0.01, "mean shift {shift}");
    // One more listed frame whose image is not there.
    let mut ghost = moved_json["frames"][0].clone();
    ghost["file_path"] = "nowhere/missing.png".into();
    moved_json["frames"].as_array_mut().unwrap().push(ghost);
    std::fs::write(
        pert.join("transforms.json"),
        serde_json::to_vec(&moved_json).unwrap(),
    )
    .unwrap();

    let out = tmp.path().join("refined");
    let said = ok(&[
        "poses",
        pert.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--gt",
        data.to_str().unwrap(),
    ]);
    assert!(
        said.contains("left out 1 of 37 frames") && said.contains("nowhere/missing.png"),
        "{said}"
    );
    assert!(said.contains("registered 36/36"), "{said}");
    let r = json(&out.join("report.json"));
    assert_eq!(
        r["skipped"][0], "nowhere/missing.png: image file missing",
        "{r}"
    );
    let (prior, refined) = (&r["errors"]["prior"], &r["errors"]["refined"]);
    let f = |v: &serde_json::Value, k: &str| v[k].as_f64().unwrap();
    assert!(
        f(refined, "ate_rmse_m") * 2.0 < f(prior, "ate_rmse_m")
            && f(refined, "rot_rmse_deg") * 1.5 < f(prior, "rot_rmse_deg"),
        "{r}"
    );
    // The missing frame keeps its place (and prior pose) in the output, for the loader to skip again.
    let t = json(&out.join("transforms.json"));
    assert_eq!(t["frames"].as_array().unwrap().len(), 37);

    // Features on half-size images; the model is written at full size.
    let half = tmp.path().join("half");
    ok(&[
        "poses",
        pert.to_str().unwrap(),
        "--out",
        half.to_str().unwrap(),
        "--downscale",
        "2",
        "--quiet",
    ]);
    assert_eq!(json(&half.join("report.json"))["downscale"], 2);
    let model = silvr_core::ingest::colmap::read_model(&half.join("colmap")).unwrap();
    assert!(model
        .cameras
        .values()
        .all(|c| (c.width, c.height) == (180, 135)));
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for im in &model.images {
        for p in &im.points2d {
            lo = lo.min(p.xy.x.min(p.xy.y));
            hi = hi.max(p.xy.x);
        }
    }
    assert!(
        lo > -0.5 && hi < 179.5 && hi > 90.0,
        "keypoints span {lo}..{hi}"
    );
    let tiny = silvr(&[
        "poses",
        pert.to_str().unwrap(),
        "--out",
        tmp.path().join("tiny").to_str().unwrap(),
        "--downscale",
        "20",
    ]);
    let err = String::from_utf8_lossy(&tiny.stderr);
    assert!(
        !tiny.status.success() && err.contains("--downscale 20") && err.contains("too small"),
        "{err}"
    );
    assert!(!tmp.path().join("tiny").exists());
}

/// Real captures (skip cleanly when `../shared/data/real` is absent): the fox at its own 1080×1920, its
/// poses given a drifting prior (1 % drift along the listed order, 0.02 units / 0.2° of noise per frame)
/// and refined with the default settings, comes back ≥ 5x closer to its own poses (centres, rotations
/// and consecutive relative rotations) with every present image registered and the 17 missing ones
/// named. The defaults work at about a megapixel (540×960 here; measured 10x / 6.9x / 17x); at full size
/// the rotations came back only 1.3x better. The DGP scene's own poses adjust with all 18 images
/// registered and the reprojection RMSE below a pixel.
#[test]
fn real_captures_register_every_image_when_present() {
    let tmp = tempfile::tempdir().unwrap();
    if let Some(fox) = silvr_tests::shared_data("real/fox/transforms.json") {
        let fox = fox.parent().unwrap();
        let pert = tmp.path().join("fox-pert");
        ok(&[
            "perturb-poses",
            fox.to_str().unwrap(),
            "--out",
            pert.to_str().unwrap(),
            "--noise",
            "0.02",
            "--noise-deg",
            "0.2",
            "--drift",
            "0.01",
        ]);
        let out = tmp.path().join("fox-ref");
        let said = ok(&[
            "poses",
            pert.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--gt",
            fox.to_str().unwrap(),
        ]);
        assert!(said.contains("left out 17 of 67 frames"), "{said}");
        assert!(said.contains("registered 50/50"), "{said}");
        assert!(
            said.contains("features on 540x960 images (downscale 2"),
            "{said}"
        );
        let r = json(&out.join("report.json"));
        let (p, q) = (&r["errors"]["prior"], &r["errors"]["refined"]);
        let f = |v: &serde_json::Value, k: &str| v[k].as_f64().unwrap();
        for k in ["ate_rmse_m", "rot_rmse_deg", "rpe_rot_rmse_deg"] {
            assert!(f(q, k) * 5.0 < f(p, k), "{k}: {r}");
        }
    }
    if let Some(dgp) = silvr_tests::shared_data("real/dgp_scene_02") {
        let ds = tmp.path().join("dgp");
        ok(&[
            "import",
            "dgp",
            dgp.to_str().unwrap(),
            "--out",
            ds.to_str().unwrap(),
        ]);
        let out = tmp.path().join("dgp-ref");
        let said = ok(&[
            "poses",
            ds.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--downscale",
            "2",
        ]);
        assert!(said.contains("registered 18/18"), "{said}");
        let r = json(&out.join("report.json"));
        assert!(r["poses"]["rmse_px"].as_f64().unwrap() < 1.0, "{r}");
    }
}
