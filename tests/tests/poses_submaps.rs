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

#[test]
fn the_prior_drifts_within_its_documented_size_and_submaps_train_in_place() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("micro");
    let d = data.to_str().unwrap();
    ok(&["synth", "--preset", "micro", "--seed", "2", "--out", d]);

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
    ]);

    // Refusals name the problem: an existing output, co-visibility before `silvr poses` exists.
    let again = silvr(&["submaps", d, "--out", subs.to_str().unwrap()]);
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("exists"));
    let covis = silvr(&[
        "submaps",
        d,
        "--out",
        tmp.path().join("c").to_str().unwrap(),
        "--method",
        "covis",
    ]);
    assert!(!covis.status.success());
    assert!(String::from_utf8_lossy(&covis.stderr).contains("silvr poses"));
}
