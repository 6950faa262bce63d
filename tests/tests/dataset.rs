//! The synthetic dataset on disk: lidar products against ground truth, determinism, and broken files.
//! Generation runs the projection kernel through wgpu (lavapipe without a GPU).

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use silvr_core::dataset::{read_gray8, read_png16, read_rgb};
use silvr_core::gpu::{Gpu, GpuOptions};
use silvr_core::lidar::images::{decode_normal, SKY_DEPTH};
use silvr_core::synthetic::generate::{generate, SynthError};
use silvr_core::synthetic::world::Label;
use silvr_core::synthetic::Preset;

fn gpu() -> Gpu {
    pollster::block_on(Gpu::new(GpuOptions::default())).expect("a GPU adapter (lavapipe is enough)")
}

/// A short `ci` world: 4 keyframes.
fn small(seed: u64) -> Preset {
    let mut p = Preset::ci(seed);
    p.keyframes = 4;
    p
}

fn make(preset: &Preset, out: &Path) -> Result<PathBuf, SynthError> {
    pollster::block_on(generate(preset, &gpu(), out, false, &mut |_| {})).map(|s| s.path)
}

/// One dataset shared by the read-only tests of this file.
fn shared() -> &'static Path {
    static DIR: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    &DIR.get_or_init(|| {
        let tmp = tempfile::tempdir().unwrap();
        let path = make(&small(1), &tmp.path().join("ds")).unwrap();
        (tmp, path)
    })
    .1
}

fn frames(ds: &Path) -> Vec<(String, String)> {
    let mut v = Vec::new();
    for cam in ["cam_front", "cam_left", "cam_right"] {
        for k in 0..4 {
            v.push((cam.to_string(), format!("{k:05}")));
        }
    }
    let _ = ds;
    v
}

#[test]
fn lidar_normals_on_the_road_match_ground_truth() {
    let ds = shared();
    let mut errs = Vec::new();
    for (cam, k) in frames(ds) {
        let (_, _, lidar) = read_rgb(&ds.join(format!("lidar_normals/{cam}/{k}.png"))).unwrap();
        let (_, _, gt) = read_rgb(&ds.join(format!("gt/normals/{cam}/{k}.png"))).unwrap();
        let (_, _, sem) = read_gray8(&ds.join(format!("gt/semantic/{cam}/{k}.png"))).unwrap();
        for i in 0..lidar.len() {
            if sem[i] != Label::Road as u8 {
                continue;
            }
            if let (Some(a), Some(b)) = (decode_normal(lidar[i]), decode_normal(gt[i])) {
                errs.push(a.angle_between(b).to_degrees());
            }
        }
    }
    errs.sort_by(f64::total_cmp);
    assert!(
        errs.len() > 1000,
        "{} road pixels with lidar normals",
        errs.len()
    );
    let median = errs[errs.len() / 2];
    assert!(
        median < 3.0,
        "median road normal error {median}° over {} pixels",
        errs.len()
    );
}

#[test]
fn sky_masks_match_ground_truth() {
    let ds = shared();
    let (mut inter, mut union) = (0usize, 0usize);
    for (cam, k) in frames(ds) {
        let (_, _, m) = read_gray8(&ds.join(format!("sky_mask/{cam}/{k}.png"))).unwrap();
        let (_, _, g) = read_gray8(&ds.join(format!("gt/sky/{cam}/{k}.png"))).unwrap();
        let (_, _, d) = read_png16(&ds.join(format!("lidar_depth/{cam}/{k}.png"))).unwrap();
        for i in 0..m.len() {
            inter += (m[i] > 0 && g[i] > 0) as usize;
            union += (m[i] > 0 || g[i] > 0) as usize;
            // Sky pixels are also marked in the depth image (SiLVR's >= 250 m convention).
            assert_eq!(m[i] > 0, d[i] == SKY_DEPTH, "{cam}/{k} pixel {i}");
        }
    }
    let iou = inter as f64 / union as f64;
    assert!(iou >= 0.9, "sky IoU {iou}");
}

#[test]
fn lidar_depth_agrees_with_ground_truth_depth() {
    let ds = shared();
    let mut errs = Vec::new();
    for (cam, k) in frames(ds) {
        let (_, _, lidar) = read_png16(&ds.join(format!("lidar_depth/{cam}/{k}.png"))).unwrap();
        let (_, _, gt) = read_png16(&ds.join(format!("gt/depth/{cam}/{k}.png"))).unwrap();
        for i in 0..lidar.len() {
            if lidar[i] != 0 && lidar[i] != SKY_DEPTH && gt[i] != 0 {
                errs.push((lidar[i] as f64 - gt[i] as f64).abs() / 256.0);
            }
        }
    }
    errs.sort_by(f64::total_cmp);
    assert!(errs.len() > 3000, "{} lidar depth pixels", errs.len());
    // Range noise is 2 cm; the lidar point sits up to half a pixel away from the pixel centre.
    let median = errs[errs.len() / 2];
    assert!(median < 0.03, "median |lidar - GT| depth {median} m");
}

/// The campus (`Preset::campus`) goes through the same generator: a 3-keyframe prefix of its walk is a
/// dataset whose lidar depth agrees with its exact depth as the town's does, whose grid has the
/// campus's 0.2 m voxels, and whose manifest records the prefix of the whole walk.
#[test]
fn a_campus_prefix_is_a_dataset_like_the_towns() {
    let tmp = tempfile::tempdir().unwrap();
    let preset = Preset::campus(1).prefix(3).unwrap();
    let ds = make(&preset, &tmp.path().join("campus")).unwrap();
    let mut errs = Vec::new();
    let mut labels = std::collections::BTreeSet::new();
    for cam in ["cam_front", "cam_left", "cam_right"] {
        for k in 0..3 {
            let k = format!("{k:05}");
            let (_, _, lidar) = read_png16(&ds.join(format!("lidar_depth/{cam}/{k}.png"))).unwrap();
            let (_, _, gt) = read_png16(&ds.join(format!("gt/depth/{cam}/{k}.png"))).unwrap();
            for i in 0..lidar.len() {
                if lidar[i] != 0 && lidar[i] != SKY_DEPTH && gt[i] != 0 {
                    errs.push((lidar[i] as f64 - gt[i] as f64).abs() / 256.0);
                }
            }
            let (_, _, sem) = read_gray8(&ds.join(format!("gt/semantic/{cam}/{k}.png"))).unwrap();
            labels.extend(sem);
        }
    }
    errs.sort_by(f64::total_cmp);
    assert!(errs.len() > 10_000, "{} lidar depth pixels", errs.len());
    let median = errs[errs.len() / 2];
    assert!(median < 0.03, "median |lidar - GT| depth {median} m");
    for l in [Label::Road, Label::Sidewalk, Label::Facade, Label::Sky] {
        assert!(labels.contains(&(l as u8)), "no {l:?} in view: {labels:?}");
    }
    let grid =
        silvr_core::eval::occupancy::OccupancyGrid::load(&ds.join("gt/observed.bin")).unwrap();
    assert_eq!(grid.voxel_size(), 0.2);
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(ds.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(manifest["preset"]["name"], "campus");
    assert_eq!(manifest["preset"]["keyframes"], 3);
    assert_eq!(manifest["preset"]["walk_keyframes"], 1027);
}

#[test]
fn same_seed_gives_identical_bytes_and_another_seed_does_not() {
    let tmp = tempfile::tempdir().unwrap();
    let a = make(&small(1), &tmp.path().join("a")).unwrap();
    let b = make(&small(2), &tmp.path().join("b")).unwrap();
    let shared = shared();
    let mut compared = 0;
    for entry in walk(shared) {
        let rel = entry.strip_prefix(shared).unwrap();
        let x = std::fs::read(&entry).unwrap();
        let y = std::fs::read(a.join(rel)).unwrap_or_else(|e| panic!("{}: {e}", rel.display()));
        assert!(
            x == y,
            "{} differs between two runs with the same seed",
            rel.display()
        );
        compared += 1;
    }
    assert!(compared > 50, "{compared} files");
    let mesh_a = std::fs::read(a.join("gt/mesh.ply")).unwrap();
    let mesh_b = std::fs::read(b.join("gt/mesh.ply")).unwrap();
    assert_ne!(mesh_a, mesh_b, "another seed must give another layout");
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out.sort();
    out
}

#[test]
fn an_existing_output_is_refused_and_nothing_partial_is_left() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("taken");
    std::fs::create_dir(&out).unwrap();
    let err = make(&small(3), &out).unwrap_err().to_string();
    assert!(
        err.contains("taken") && err.contains("already exists"),
        "{err}"
    );
    let left: Vec<_> = std::fs::read_dir(tmp.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(
        left.len(),
        1,
        "only the pre-existing folder remains: {left:?}"
    );
}

#[test]
fn corrupt_files_give_errors_that_name_them() {
    let tmp = tempfile::tempdir().unwrap();
    let ds = tmp.path().join("copy");
    copy_dir(shared(), &ds);
    // A truncated sweep.
    let sweep = ds.join("lidar/deskewed/00002.ply");
    let bytes = std::fs::read(&sweep).unwrap();
    std::fs::write(&sweep, &bytes[..bytes.len() / 2]).unwrap();
    let err = silvr_core::lidar::map::lidar_map(&ds)
        .unwrap_err()
        .to_string();
    assert!(err.contains("00002.ply"), "{err}");
    // A corrupt pose file.
    std::fs::write(ds.join("poses/lidar_tum.txt"), "0 1 2 3 x 0 0 1\n").unwrap();
    let err = silvr_core::lidar::map::lidar_map(&ds)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("lidar_tum.txt") && err.contains("line 1"),
        "{err}"
    );
    // A corrupt GT cloud for the evaluator.
    std::fs::write(
        ds.join("gt/cloud.ply"),
        b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n",
    )
    .unwrap();
    let rec = ds.join("lidar/raw/00000.ply");
    let err = silvr_core::eval::evaluate_files(&rec, &ds, &Default::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("cloud.ply"), "{err}");
    // A truncated image.
    let img = ds.join("images/cam_front/00000.png");
    let bytes = std::fs::read(&img).unwrap();
    std::fs::write(&img, &bytes[..100]).unwrap();
    let err = read_rgb(&img).unwrap_err().to_string();
    assert!(err.contains("00000.png"), "{err}");
}

fn copy_dir(from: &Path, to: &Path) {
    for f in walk(from) {
        let dst = to.join(f.strip_prefix(from).unwrap());
        std::fs::create_dir_all(dst.parent().unwrap()).unwrap();
        std::fs::copy(&f, &dst).unwrap();
    }
}

#[test]
fn ground_truth_scored_against_itself_is_perfect_and_noise_lowers_it() {
    use silvr_core::eval::{evaluate_geometry, GeometryOptions, ObservedSpace, OccupancyGrid};
    use silvr_core::pointcloud::read_ply;
    let ds = shared();
    let gt = read_ply(&ds.join("gt/cloud.ply")).unwrap();
    let grid = OccupancyGrid::load(&ds.join("gt/observed.bin")).unwrap();
    let opts = GeometryOptions::default();
    let score = |rec: &silvr_core::pointcloud::PointCloud| {
        let observed = ObservedSpace {
            gt: Some(&grid),
            sensor: None,
        };
        evaluate_geometry(rec, &gt, observed, &opts).unwrap().report
    };
    let perfect = score(&gt);
    for key in ["fscore_3cm", "fscore_5cm", "fscore_10cm", "fscore_20cm"] {
        assert_eq!(
            perfect.per_threshold[key],
            1.0,
            "{key}: {}",
            perfect.summary()
        );
    }
    assert!(perfect.accuracy_m < 1e-9);
    // Gaussian noise of growing σ: F@5cm falls strictly.
    let mut rng = 7u64;
    let mut gauss = move || {
        // xorshift + Box–Muller: deterministic and dependency-free.
        let mut u = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng >> 11) as f64 / (1u64 << 53) as f64
        };
        let (a, b) = (u().max(1e-300), u());
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    };
    let mut last = 1.0;
    for sigma in [0.01, 0.03, 0.06] {
        let mut noisy = gt.clone();
        for p in &mut noisy.positions {
            *p += glam::DVec3::new(gauss(), gauss(), gauss()) * sigma;
        }
        let f = score(&noisy).per_threshold["fscore_5cm"];
        assert!(f < last, "σ={sigma}: F@5cm {f} not below {last}");
        last = f;
    }
}

#[test]
fn a_killed_run_leaves_no_trace_for_the_next() {
    let tmp = tempfile::tempdir().unwrap();
    // What a killed generator leaves behind: a hidden staging folder.
    let stale = tmp.path().join(".ds.partial-999999");
    std::fs::create_dir_all(stale.join("images")).unwrap();
    let mut p = small(9);
    p.keyframes = 1;
    let out = make(&p, &tmp.path().join("ds")).unwrap();
    assert!(out.join("manifest.json").is_file());
    assert!(!stale.exists(), "stale staging folder removed");
}
