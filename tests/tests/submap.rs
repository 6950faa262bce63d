//! A submap as a user hands it over: `silvr pack` → one tar archive → `silvr train` from the archive on
//! the WGSL path, the same run as from the folder. The run's settings are the studio's browser test's
//! (tests/browser/train.mjs), so its `train.json` is the native reference the browser run is held to; the
//! archive and broken variants of it are left in `$SILVR_STUDIO_FIXTURES` for that test.

use std::path::Path;
use std::process::Command;

use silvr_core::source::{Files, Source};
use silvr_core::train::data::{LoadOptions, TrainData};
use silvr_tests::build_silvr;

/// The browser test's run (tests/browser/train.mjs: `BROWSER_RUN`). Keep the two in step.
const STEPS: &str = "150";
const RAYS: &str = "256";
const MODEL: &str = "tiny";
const DOWNSCALE: &str = "2";
const EXPORT_RAYS: &str = "4096";
const UNCERTAINTY_BATCHES: &str = "2";
const UNCERTAINTY_RAYS: &str = "1024";

fn run(args: &[&str]) -> String {
    let out = Command::new(build_silvr())
        .args(args)
        .env(
            "WGPU_BACKEND",
            std::env::var("WGPU_BACKEND").unwrap_or("vulkan".into()),
        )
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "silvr {args:?} failed:\n{err}");
    err
}

fn json(p: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
}

#[test]
fn packed_submap_trains_on_wgsl_like_its_folder_and_leaves_the_browser_fixtures() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("micro");
    run(&[
        "synth",
        "--preset",
        "micro",
        "--seed",
        "1",
        "--out",
        data.to_str().unwrap(),
    ]);
    let tar = tmp.path().join("micro.tar");
    let said = run(&[
        "pack",
        data.to_str().unwrap(),
        "--out",
        tar.to_str().unwrap(),
    ]);
    assert!(said.contains("packed"), "{said}");

    // The archive holds what training reads and nothing of the ground truth or raw sweeps.
    let files = Files::from_tar("micro.tar", std::fs::read(&tar).unwrap()).unwrap();
    let names: Vec<&str> = files.names().collect();
    assert!(names.contains(&"transforms.json") && names.contains(&"calib/rig.json"));
    assert_eq!(
        names.iter().filter(|n| n.starts_with("images/")).count(),
        36
    );
    assert_eq!(
        names
            .iter()
            .filter(|n| n.starts_with("lidar_depth/"))
            .count(),
        36
    );
    assert!(!names
        .iter()
        .any(|n| n.starts_with("gt/") || n.starts_with("lidar/")));
    assert!(std::fs::metadata(&tar).unwrap().len() < 8 << 20);

    // Same run from the folder and from the archive: identical training on the CPU referee (bit-exact
    // there), so the archive loads the same rays, targets and scene frame.
    let mut losses = Vec::new();
    for (src, out) in [(&data, "from_dir"), (&tar, "from_tar")] {
        let out = tmp.path().join(out);
        run(&[
            "train",
            src.to_str().unwrap(),
            "--backend",
            "cpu",
            "--steps",
            "5",
            "--rays",
            "64",
            "--model",
            "tiny",
            "--seed",
            "1",
            "--export-rays",
            "0",
            "--render-views",
            "0",
            "--out",
            out.to_str().unwrap(),
        ]);
        let ck =
            silvr_core::train::checkpoint::Checkpoint::load(&out.join("checkpoint.ckpt")).unwrap();
        losses.push(ck.header.history.iter().map(|s| s.loss).collect::<Vec<_>>());
    }
    assert_eq!(losses[0], losses[1]);

    // Packed downscaled: the archive as it is loads exactly what the folder loads at that downscale
    // (pixels, lidar, normals, sky, cameras; the micro world's 135-pixel height is odd, so the last row
    // is dropped), in a smaller file.
    let small = tmp.path().join("micro-2.tar");
    let said = run(&[
        "pack",
        data.to_str().unwrap(),
        "--out",
        small.to_str().unwrap(),
        "--downscale",
        "2",
    ]);
    assert!(said.contains("downscaled by 2"), "{said}");
    let a = TrainData::load(&small, &LoadOptions::default()).unwrap();
    let b = TrainData::load(
        &data,
        &LoadOptions {
            downscale: 2,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(a.cameras, b.cameras);
    assert_eq!((a.cameras[0].width, a.cameras[0].height), (90, 67));
    assert_eq!(a.images.len(), b.images.len());
    for (x, y) in a.images.iter().zip(&b.images) {
        assert_eq!((x.width, x.height, &x.name), (y.width, y.height, &y.name));
        assert!(x.rgb == y.rgb && x.depth == y.depth && x.normals == y.normals && x.sky == y.sky);
        assert!(!x.depth.is_empty());
    }
    assert_eq!((a.train.clone(), a.frame), (b.train.clone(), b.frame));
    let (full, half) = (
        std::fs::metadata(&tar).unwrap().len(),
        std::fs::metadata(&small).unwrap().len(),
    );
    assert!(half * 2 < full, "{half} bytes packed at 1/2 vs {full}");

    // The browser test's run, natively on the WGSL engine (both browsers are held to it).
    let fixtures = std::env::var_os("SILVR_STUDIO_FIXTURES").map(std::path::PathBuf::from);
    if let Some(dir) = &fixtures {
        std::fs::create_dir_all(dir).unwrap();
        std::fs::copy(&tar, dir.join("micro.tar")).unwrap();
    }
    let steps = STEPS;
    let native = tmp.path().join(format!("native-{steps}"));
    run(&[
        "train",
        tar.to_str().unwrap(),
        "--backend",
        "wgpu",
        "--steps",
        steps,
        "--rays",
        RAYS,
        "--model",
        MODEL,
        "--downscale",
        DOWNSCALE,
        "--seed",
        "1",
        "--export-rays",
        EXPORT_RAYS,
        "--render-views",
        "8",
        "--uncertainty-batches",
        UNCERTAINTY_BATCHES,
        "--uncertainty-rays",
        UNCERTAINTY_RAYS,
        "--out",
        native.to_str().unwrap(),
    ]);
    let report = json(&native.join("train.json"));
    assert_eq!(report["backend"], "wgpu");
    assert_eq!(report["backends"]["uncertainty"], "wgpu");
    let psnr = report["heldout_psnr_mean"].as_f64().unwrap();
    assert!(psnr > 18.0, "{steps} steps: held-out PSNR {psnr}");
    let cloud = silvr_core::pointcloud::read_ply(&native.join("points.ply")).unwrap();
    assert!(cloud.len() > 100, "{} points", cloud.len());
    let q = quantiles(cloud.scalar("log_std_combined").unwrap());
    println!(
        "native WGSL run of the browser test's submap, {steps} steps: held-out PSNR {psnr:.2} dB, {} points, log_std quantiles {q:?}, {:.0} rays/s",
        cloud.len(),
        report["train_rays_per_s"].as_f64().unwrap()
    );
    if let Some(dir) = &fixtures {
        // The native checkpoint the browser continues (a field trained natively goes on there).
        std::fs::copy(
            native.join("checkpoint.ckpt"),
            dir.join("micro-native.ckpt"),
        )
        .unwrap();
        let mut reference = report.clone();
        reference["points_count"] = cloud.len().into();
        reference["log_std_quantiles"] = q.into();
        std::fs::write(
            dir.join("micro-native.json"),
            serde_json::to_vec_pretty(&reference).unwrap(),
        )
        .unwrap();
    }
    let Some(dir) = fixtures else {
        return;
    };
    // Broken variants: a corrupt image, no transforms.json, a missing lidar depth image.
    let keep = |skip: &dyn Fn(&str) -> bool, corrupt: &dyn Fn(&str) -> bool| {
        let mut out = Files::new("micro");
        for n in files.names() {
            if skip(n) {
                continue;
            }
            let bytes = if corrupt(n) {
                b"this is not a PNG".to_vec()
            } else {
                files.read(n).unwrap().into_owned()
            };
            out.insert(n, bytes).unwrap();
        }
        out.to_tar()
    };
    let bad_image = "images/cam_left/00003.png";
    std::fs::write(
        dir.join("corrupt-image.tar"),
        keep(&|_| false, &|n| n == bad_image),
    )
    .unwrap();
    std::fs::write(
        dir.join("no-transforms.tar"),
        keep(&|n| n == "transforms.json", &|_| false),
    )
    .unwrap();
    std::fs::write(
        dir.join("missing-lidar.tar"),
        keep(&|n| n == "lidar_depth/cam_front/00002.png", &|_| false),
    )
    .unwrap();
}

/// 5, 25, 50, 75, 95 % nearest-rank quantiles of the finite values (the studio's rule).
fn quantiles(v: &[f32]) -> Vec<f32> {
    let mut v: Vec<f32> = v.iter().copied().filter(|x| x.is_finite()).collect();
    v.sort_by(f32::total_cmp);
    [0.05, 0.25, 0.5, 0.75, 0.95]
        .iter()
        .map(|q| v[((v.len() - 1) as f64 * q).round() as usize])
        .collect()
}

/// Broken archives are refused with the file named; a dataset with a missing lidar image names it.
#[test]
fn broken_archives_name_the_file_and_the_problem() {
    let tmp = tempfile::tempdir().unwrap();
    let bad = tmp.path().join("bad.tar");
    std::fs::write(&bad, vec![0x5a; 4096]).unwrap();
    let out = Command::new(build_silvr())
        .args([
            "train",
            bad.to_str().unwrap(),
            "--backend",
            "cpu",
            "--steps",
            "1",
        ])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("bad.tar") && !err.contains("panicked"),
        "{err}"
    );
    let missing = tmp.path().join("nothing");
    let out = Command::new(build_silvr())
        .args([
            "pack",
            missing.to_str().unwrap(),
            "--out",
            bad.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("nothing"), "{err}");
    // The failed pack left the earlier file as it was (written under a temporary name, then renamed).
    assert_eq!(std::fs::read(&bad).unwrap(), vec![0x5a; 4096]);
}

/// The real fox capture (`../shared/data/real/fox`: nerfstudio layout, camera only, 50 of its 67 listed
/// photos present) packs with the missing frames left out and named, and trains vision-only from the
/// archive; the archive is left for the studio's browser test. Skips cleanly when the data is absent.
#[test]
fn a_nerfstudio_capture_packs_and_trains_vision_only_when_present() {
    let Some(fox) = silvr_tests::shared_data("real/fox/transforms.json") else {
        return;
    };
    let fox = fox.parent().unwrap().to_path_buf();
    let tmp = tempfile::tempdir().unwrap();
    let tar = tmp.path().join("fox.tar");
    let said = run(&[
        "pack",
        fox.to_str().unwrap(),
        "--out",
        tar.to_str().unwrap(),
    ]);
    assert_eq!(said.matches("left out").count(), 17, "{said}");
    let out = tmp.path().join("fox-train");
    run(&[
        "train",
        tar.to_str().unwrap(),
        "--mode",
        "vision",
        "--backend",
        "wgpu",
        "--steps",
        "40",
        "--rays",
        "256",
        "--model",
        "tiny",
        "--downscale",
        "8",
        "--seed",
        "1",
        "--export-rays",
        "0",
        "--render-views",
        "1",
        "--out",
        out.to_str().unwrap(),
    ]);
    let report = json(&out.join("train.json"));
    assert_eq!(report["mode"], "vision");
    let psnr = report["heldout_psnr_mean"].as_f64().unwrap();
    assert!(psnr > 12.0, "fox held-out PSNR {psnr}");
    println!("fox (vision-only, tiny, 40 steps, downscale 8): held-out PSNR {psnr:.2} dB");
    if let Some(dir) = std::env::var_os("SILVR_STUDIO_FIXTURES") {
        let dir = std::path::PathBuf::from(dir);
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::copy(&tar, dir.join("fox.tar")).unwrap();
        let mut r = report.clone();
        r["heldout_psnr_mean"] = psnr.into();
        std::fs::write(
            dir.join("fox-native.json"),
            serde_json::to_vec_pretty(&r).unwrap(),
        )
        .unwrap();
    }
}
