//! Loop closure in `silvr poses` at CI size (issue 35): the `campus-loop` world (one campus block walked
//! round and on along its first street, 282 images at 360x270) with a prior whose yaw drift leaves the
//! second pass along the south street ~2 m off the first. Without loop closure the refinement cannot undo
//! that (the prior's epipolar gate pairs the passes with wrong matches); with it the walk comes back onto
//! itself.

use std::path::Path;
use std::process::Command;

use silvr_tests::build_silvr;

fn ok(args: &[&str]) -> String {
    let out = Command::new(build_silvr()).args(args).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "silvr {args:?}: {err}");
    err
}

fn json(p: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
}

#[test]
fn poses_closes_the_campus_loop_the_prior_leaves_metres_open() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("campus-loop");
    let d = data.to_str().unwrap();
    ok(&["synth", "--preset", "campus-loop", "--out", d]);
    let prior = format!("{d}/transforms_prior.json");
    let exact = format!("{d}/transforms.json");
    let run = |name: &str, extra: &[&str]| {
        let out = tmp.path().join(name);
        let mut args = vec![
            "poses",
            &prior,
            "--gt",
            &exact,
            "--out",
            out.to_str().unwrap(),
            "--quiet",
        ];
        args.extend_from_slice(extra);
        ok(&args);
        json(&out.join("report.json"))
    };
    let ate = |r: &serde_json::Value, which: &str| {
        r["errors"][which]["ate_rmse_m"]
            .as_f64()
            .unwrap_or(f64::NAN)
    };

    let without = run("no-loops", &["--no-loops"]);
    let with = run("loops", &[]);
    let prior_ate = ate(&with, "prior");
    eprintln!(
        "campus-loop ATE: prior {prior_ate:.3} m, refined without loop closure {:.3} m, with {:.3} m",
        ate(&without, "refined"),
        ate(&with, "refined")
    );
    assert!(prior_ate > 1.0, "the prior must be metres off: {prior_ate}");
    // The baseline: the adjustment along the walk alone leaves the loop open.
    assert!(
        ate(&without, "refined") > 0.3,
        "without loop closure: {}",
        ate(&without, "refined")
    );
    assert_eq!(without["poses"]["loops"]["skipped"], "loop closure off");
    // Loop closure: the walk comes back onto itself, centimetres from the truth.
    assert!(
        ate(&with, "refined") < 0.05 && ate(&with, "refined") * 20.0 < prior_ate,
        "with loop closure: {} (prior {prior_ate})",
        ate(&with, "refined")
    );
    let loops = &with["poses"]["loops"];
    let edges = loops["edges"].as_array().unwrap();
    assert!(edges.len() >= 10, "{loops}");
    // Every loop joins the two passes: images at least 30 m apart along the walk.
    for e in edges {
        assert!(e["path_m"].as_f64().unwrap() >= 30.0, "{e}");
    }
    let p = &with["poses"];
    assert_eq!(p["registered"], p["images"], "every image registered");
}
