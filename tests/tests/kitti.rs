//! `silvr import kitti` on real KITTI odometry snippets (`../shared/data/real/kitti_odometry`, 10 frames each
//! of sequences 00 and 03): the rig from calib.txt, the ground-truth trajectory turned z-up, lidar depth in both
//! colour cameras, and the refusal to invent a trajectory. Skips where the data is absent (required under
//! SILVR_REQUIRE_DATA=1).

use std::path::Path;
use std::process::Command;

use silvr_core::dataset::read_tum;
use silvr_core::pointcloud::read_ply;
use silvr_tests::build_silvr;

fn import(seq: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    Command::new(build_silvr())
        .args(["import", "kitti"])
        .arg(seq)
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .unwrap()
}

/// Distance from `p` to the nearest of `cloud`, capped at `cap` (a brute-force scan: 10 sweeps' worth is
/// quick enough, and the test needs no index of its own).
fn nearest_within(cloud: &[glam::DVec3], p: glam::DVec3, cap: f64) -> f64 {
    cloud
        .iter()
        .map(|q| (*q - p).length_squared())
        .fold(cap * cap, f64::min)
        .sqrt()
}

#[test]
fn a_kitti_sequence_imports_with_its_rig_ground_truth_and_lidar_depth() {
    let Some(root) = silvr_tests::shared_data("real/kitti_odometry/sequences") else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    for (seq, travelled) in [("00", 6.7), ("03", 8.5)] {
        let ds = tmp.path().join(seq);
        let out = import(&root.join(seq), &ds, &["--downscale", "2"]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{seq}: {err}");
        let s: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(
            (s["keyframes"].as_u64(), s["images"].as_u64()),
            (Some(10), Some(20)),
            "{s}"
        );

        // The trajectory, z-up: the car drives along the ground plane and its camera stays at its height.
        let base = read_tum(&ds.join("poses/base_tum.txt")).unwrap();
        let first = base.poses()[0].trans;
        let last = base.poses()[9].trans;
        let d = last - first;
        assert!(
            (d.length() - travelled).abs() < 0.3 && d.z.abs() < 0.2,
            "{seq}: cam0 moved {d:?}, KITTI's ground truth says {travelled} m along the road"
        );

        // Lidar depth reaches both colour cameras (a wrong Tr or P would put the returns beside the image).
        for cam in ["image_2", "image_3"] {
            let px = s["depth_pixels"][cam].as_f64().unwrap();
            // 10 keyframes of 620 × 188: the HDL-64E covers the lower ~half of the frame, sparsely.
            assert!(
                px > 0.03 * 10.0 * 620.0 * 188.0,
                "{seq} {cam}: {px} depth pixels"
            );
        }

        // The sweeps, placed by the lidar poses, agree with each other: the road and walls of frame 0 are
        // where frame 9 sees them (the README's ICP check says a few centimetres). A rig or axis error of
        // the conversion moves them apart by metres.
        let lidar = read_tum(&ds.join("poses/lidar_tum.txt")).unwrap();
        let world = |k: usize| -> Vec<glam::DVec3> {
            let c = read_ply(&ds.join(format!("lidar/deskewed/{k:05}.ply"))).unwrap();
            c.positions
                .iter()
                .map(|p| lidar.poses()[k].transform_point(*p))
                .filter(|p| (*p - lidar.poses()[k].trans).length() < 20.0)
                .collect()
        };
        let (a, b) = (world(0), world(9));
        let mut d: Vec<f64> = b
            .iter()
            .step_by(97)
            .map(|p| nearest_within(&a, *p, 0.5))
            .collect();
        d.sort_by(f64::total_cmp);
        let median = d[d.len() / 2];
        assert!(
            median < 0.1,
            "{seq}: frame 9's returns lie {median} m (median) from frame 0's"
        );
    }
}

/// One sequence imported and trained briefly on WGSL: the real images and lidar are a dataset training reads
/// like any other (the held-out frame's colour and depth improve on an untrained field's).
#[test]
fn an_imported_kitti_sequence_trains() {
    let Some(seq) = silvr_tests::shared_data("real/kitti_odometry/sequences/00") else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let ds = tmp.path().join("00");
    let out = import(&seq, &ds, &["--downscale", "2"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let model = tmp.path().join("model");
    let out = Command::new(build_silvr())
        .arg("train")
        .arg(&ds)
        .args([
            "--model",
            "tiny",
            "--steps",
            "300",
            "--rays",
            "1024",
            "--downscale",
            "2",
        ])
        .args([
            "--backend",
            "wgpu",
            "--render-views",
            "1",
            "--export-rays",
            "20000",
            "--out",
        ])
        .arg(&model)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    let t: serde_json::Value =
        serde_json::from_slice(&std::fs::read(model.join("train.json")).unwrap()).unwrap();
    assert_eq!(t["backend"], "wgpu", "{t}");
    // Measured 15.6 dB after 300 steps, 9.8 dB after one (2026-12-04, lavapipe).
    let psnr = t["heldout_psnr_mean"].as_f64().unwrap();
    assert!(psnr > 13.0, "held-out PSNR {psnr} dB: {t}");
    let points = read_ply(&model.join("points.ply")).unwrap();
    assert!(points.len() > 1000, "{} points", points.len());
}

#[test]
fn a_kitti_sequence_without_a_trajectory_gets_lidar_odometry_and_says_so() {
    let Some(seq) = silvr_tests::shared_data("real/kitti_odometry/sequences/00") else {
        return;
    };
    // The sequence without its poses.txt: the other files linked.
    let tmp = tempfile::tempdir().unwrap();
    let copy = tmp.path().join("sequences/00");
    std::fs::create_dir_all(&copy).unwrap();
    for f in ["calib.txt", "times.txt", "image_2", "image_3", "velodyne"] {
        std::os::unix::fs::symlink(seq.join(f), copy.join(f)).unwrap();
    }
    let out = import(&copy, &tmp.path().join("ds"), &["--downscale", "4"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("notice: no trajectory") && err.contains("--poses"),
        "{err}"
    );
    let s: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(s["poses"], "lidar odometry (velodyne/)", "{s}");
    assert_eq!(s["keyframes"], 10, "{s}");
    // The odometry's camera path against KITTI's own ground truth (imported beside it): both start at
    // cam0 of frame 0 and are metric, so they are compared without any alignment (measured 8.6 cm at worst
    // over the 6.7 m: a few tenths of a degree of heading; 2.1 cm after an SE(3) alignment).
    let gt_ds = tmp.path().join("gt_ds");
    let out = import(&seq, &gt_ds, &["--downscale", "4"]);
    assert!(out.status.success());
    let (a, b) = (
        read_tum(&tmp.path().join("ds/poses/base_tum.txt")).unwrap(),
        read_tum(&gt_ds.join("poses/base_tum.txt")).unwrap(),
    );
    let worst = a
        .poses()
        .iter()
        .zip(b.poses())
        .map(|(p, q)| p.distance_to(q))
        .fold(0.0, f64::max);
    assert!(
        worst < 0.15,
        "lidar odometry's cam0 path is {worst} m off KITTI's"
    );

    // A trajectory too short for the frames names the file and the line it lacks; nothing is written.
    let short = tmp.path().join("short.txt");
    let gt = std::fs::read_to_string(seq.join("poses.txt")).unwrap();
    std::fs::write(&short, gt.lines().take(4).collect::<Vec<_>>().join("\n")).unwrap();
    let out = import(
        &copy,
        &tmp.path().join("ds_short"),
        &["--poses", short.to_str().unwrap()],
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("short.txt") && err.contains("4 poses"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    assert!(!tmp.path().join("ds_short").exists(), "nothing is written");
}

/// A KITTI sequence as many converters write it to a ROS 2 bag — PointCloud2 with x, y, z, intensity only
/// (no per-point time, no ring), the colour images, the ground-truth trajectory as nav_msgs/Odometry — goes
/// through `silvr ingest` to the dataset `silvr import kitti` makes of the same sequence: same keyframes,
/// images bit-equal, camera poses to 1e-6, lidar depth on the same pixels; nothing dropped silently, and
/// both assumptions printed (issue 33). Training reads the two datasets alike because they are alike.
#[test]
fn a_kitti_sequence_as_a_bag_of_bare_clouds_ingests_like_the_import() {
    use silvr_core::dataset::{read_png16, Transforms};
    use silvr_core::ingest::config::{IngestSection, RigConfig};
    use silvr_core::ingest::kitti::{read_bin_bytes, KITTI_STRIDE};
    use silvr_core::ingest::ros::{CompressedImage, Header, Odometry, PointCloud2, PointField};
    use silvr_core::ingest::writer::{ros_time, BagWriter};
    use silvr_core::rig::Rig;

    let Some(root) = silvr_tests::shared_data("real/kitti_odometry/sequences") else {
        return;
    };
    let seq = root.join("00");
    let tmp = tempfile::tempdir().unwrap();
    let imported = tmp.path().join("imported");
    let out = import(&seq, &imported, &[]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let rig: Rig =
        serde_json::from_slice(&std::fs::read(imported.join("calib/rig.json")).unwrap()).unwrap();
    let traj = read_tum(&imported.join("poses/lidar_tum.txt")).unwrap();

    // The bag: one message of each kind per frame, stamped with the frame's time.
    let bag = tmp.path().join("kitti.mcap");
    let mut w = BagWriter::create(&bag).unwrap();
    let cam_topic = |i: usize| {
        format!(
            "/kitti/camera_color_{}/image_raw/compressed",
            ["left", "right"][i]
        )
    };
    for (f, (&t, pose)) in traj.stamps().iter().zip(traj.poses()).enumerate() {
        let header = |frame: &str| Header {
            stamp: ros_time(t),
            frame_id: frame.to_string(),
        };
        let odo = Odometry {
            header: header("world"),
            child_frame_id: rig.lidar_frame.clone(),
            pose: *pose,
            pose_covariance: [0.0; 36],
            linear: glam::DVec3::ZERO,
            angular: glam::DVec3::ZERO,
            twist_covariance: [0.0; 36],
        };
        w.write(
            "/odometry",
            "nav_msgs/msg/Odometry",
            ros_time(t),
            &odo.encode(),
        )
        .unwrap();
        let bin = seq.join(format!("velodyne/{f:06}.bin"));
        let scan = read_bin_bytes(&std::fs::read(&bin).unwrap(), "bin", KITTI_STRIDE).unwrap();
        let intensity = scan.cloud.scalar("intensity").unwrap();
        let mut data = Vec::new();
        for (p, i) in scan.cloud.positions.iter().zip(intensity) {
            for v in [p.x as f32, p.y as f32, p.z as f32, *i] {
                data.extend_from_slice(&v.to_le_bytes());
            }
        }
        let n = scan.cloud.positions.len() as u32;
        let pc = PointCloud2 {
            header: header(&rig.lidar_frame),
            height: 1,
            width: n,
            fields: ["x", "y", "z", "intensity"]
                .iter()
                .enumerate()
                .map(|(k, name)| PointField::new(name, 4 * k as u32, PointField::FLOAT32))
                .collect(),
            is_bigendian: false,
            point_step: 16,
            row_step: 16 * n,
            data: &data,
            is_dense: true,
        };
        w.write(
            "/kitti/velo/pointcloud",
            "sensor_msgs/msg/PointCloud2",
            ros_time(t),
            &pc.encode(),
        )
        .unwrap();
        for (i, dir) in ["image_2", "image_3"].iter().enumerate() {
            let png = std::fs::read(seq.join(format!("{dir}/{f:06}.png"))).unwrap();
            let img = CompressedImage {
                header: header(&rig.cameras[i].name),
                format: "png".into(),
                data: &png,
            };
            w.write(
                &cam_topic(i),
                "sensor_msgs/msg/CompressedImage",
                ros_time(t),
                &img.encode(),
            )
            .unwrap();
        }
    }
    w.finish().unwrap();
    let mut cfg = RigConfig::from_rig(&rig, cam_topic);
    cfg.ingest = IngestSection {
        lidar_topic: "/kitti/velo/pointcloud".into(),
        trajectory_topic: Some("/odometry".into()),
        base_frame: rig.base_frame.clone(),
        keyframe_distance: 0.0,
        keyframe_angle_deg: 0.0,
        ..IngestSection::default()
    };
    let rig_file = tmp.path().join("kitti.rig.yaml");
    std::fs::write(&rig_file, cfg.to_yaml()).unwrap();

    let ingested = tmp.path().join("ingested");
    let out = Command::new(build_silvr())
        .arg("ingest")
        .arg(&bag)
        .arg("--config")
        .arg(&rig_file)
        .arg("--out")
        .arg(&ingested)
        .arg("--json")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("no per-point time") && err.contains("no 'ring' field"),
        "{err}"
    );
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(summary["dropped"], serde_json::json!({}), "{summary}");
    assert_eq!(summary["keyframes"], 10);

    let ta = Transforms::read(&imported.join("transforms.json")).unwrap();
    let tb = Transforms::read(&ingested.join("transforms.json")).unwrap();
    assert_eq!(ta.frames.len(), tb.frames.len());
    let (mut pixels, mut differing) = (0usize, 0usize);
    for (fa, fb) in ta.frames.iter().zip(&tb.frames) {
        assert_eq!(
            silvr_core::dataset::read_rgb(&imported.join(&fa.file_path)).unwrap(),
            silvr_core::dataset::read_rgb(&ingested.join(&fb.file_path)).unwrap(),
            "{}",
            fa.file_path
        );
        for (ra, rb) in fa.transform_matrix.iter().zip(&fb.transform_matrix) {
            for (x, y) in ra.iter().zip(rb) {
                assert!((x - y).abs() < 1e-6, "{}: {ra:?} vs {rb:?}", fa.file_path);
            }
        }
        let da = read_png16(&imported.join(fa.depth_file_path.as_ref().unwrap()))
            .unwrap()
            .2;
        let db = read_png16(&ingested.join(fb.depth_file_path.as_ref().unwrap()))
            .unwrap()
            .2;
        for (a, b) in da.iter().zip(&db) {
            if *a > 0 && *a < u16::MAX {
                pixels += 1;
                differing += usize::from(a.abs_diff(*b) > 1);
            }
        }
    }
    println!("lidar pixels {pixels}, differing {differing}");
    assert!(pixels > 10_000, "{pixels}");
    assert!(
        differing * 1000 <= pixels,
        "{differing} of {pixels} lidar pixels differ"
    );
}

/// Writes sequence `seq` (odometry layout) as a KITTI raw drive, `DATE/DATE_drive_0067_sync` (sequence 03
/// comes from drive 0067 of 2011-09-26): the images and sweeps under 10-digit names, `calib_cam_to_cam.txt`
/// with P_rect_02/03 = P2/P3 and R_rect_00 = I, `calib_velo_to_cam.txt` = Tr, the released drives'
/// `calib_imu_to_velo.txt`, `image_02/timestamps.txt` from times.txt, and one OXTS record per frame made from
/// the ground truth by the inverse of the devkit's projection, placed near Karlsruhe with the IMU level at
/// frame 0. Returns the drive folder.
fn write_raw_drive(seq: &Path, date_dir: &Path) -> std::path::PathBuf {
    use glam::{DQuat, DVec3};
    use silvr_core::geometry::Se3;
    use silvr_core::ingest::kitti::{oxts_from_pose, parse_calib};
    use silvr_core::ingest::poses::{parse_kitti, KittiTimes};

    let drive = date_dir.join("2011_09_26_drive_0067_sync");
    let calib = parse_calib(
        &std::fs::read_to_string(seq.join("calib.txt")).unwrap(),
        "calib.txt",
    )
    .unwrap();
    let nums = |k: &str| {
        calib
            .numbers(k)
            .unwrap()
            .iter()
            .map(|v| format!("{v:e}"))
            .collect::<Vec<_>>()
            .join(" ")
    };
    std::fs::create_dir_all(&drive).unwrap();
    std::fs::write(
        date_dir.join("calib_cam_to_cam.txt"),
        format!(
            "calib_time: 09-Jan-2012 13:57:47\ncorner_dist: 9.950000e-02\nR_rect_00: 1 0 0 0 1 0 0 0 1\n\
             P_rect_02: {}\nP_rect_03: {}\n",
            nums("P2"),
            nums("P3")
        ),
    )
    .unwrap();
    let tr = calib.rigid("Tr").unwrap();
    let m = glam::DMat3::from_quat(tr.rot);
    let row = |m: glam::DMat3| {
        (0..3)
            .flat_map(|r| (0..3).map(move |c| m.col(c)[r]))
            .map(|v| format!("{v:e}"))
            .collect::<Vec<_>>()
            .join(" ")
    };
    std::fs::write(
        date_dir.join("calib_velo_to_cam.txt"),
        format!(
            "calib_time: 15-Mar-2012 11:37:16\nR: {}\nT: {:e} {:e} {:e}\ndelta_f: 0 0\ndelta_c: 0 0\n",
            row(m),
            tr.trans.x,
            tr.trans.y,
            tr.trans.z
        ),
    )
    .unwrap();
    // The released drives' IMU → velodyne (2011_09_26), as a unit quaternion's exact rotation.
    let t_velo_imu = Se3::new(
        DQuat::from_xyzw(0.0035, -0.0030, 0.0006, 1.0).normalize(),
        DVec3::new(-0.8086759, 0.3195559, -0.7997231),
    );
    std::fs::write(
        date_dir.join("calib_imu_to_velo.txt"),
        format!(
            "calib_time: 25-May-2012 16:47:16\nR: {}\nT: {:e} {:e} {:e}\n",
            row(glam::DMat3::from_quat(t_velo_imu.rot)),
            t_velo_imu.trans.x,
            t_velo_imu.trans.y,
            t_velo_imu.trans.z
        ),
    )
    .unwrap();
    let times: Vec<f64> = std::fs::read_to_string(seq.join("times.txt"))
        .unwrap()
        .lines()
        .map(|l| l.trim().parse().unwrap())
        .collect();
    let gt = parse_kitti(
        &std::fs::read_to_string(seq.join("poses.txt")).unwrap(),
        "poses.txt",
        KittiTimes::Period(1.0),
    )
    .unwrap();
    let t_cam0_imu = tr * t_velo_imu;
    // Level IMU at frame 0, heading 30° north of east, at 49° N 8.4° E, 115 m.
    let (lat0, lon0) = (49.0_f64, 8.4_f64);
    let (er, scale) = (6_378_137.0, lat0.to_radians().cos());
    let origin = DVec3::new(
        scale * er * lon0.to_radians(),
        scale * er * ((90.0 + lat0) * std::f64::consts::PI / 360.0).tan().ln(),
        115.0,
    );
    let g = Se3::new(DQuat::from_rotation_z(30f64.to_radians()), origin)
        * (gt.poses()[0] * t_cam0_imu).inverse();
    let mut stamps = String::new();
    for sub in [
        "image_02/data",
        "image_03/data",
        "velodyne_points/data",
        "oxts/data",
    ] {
        std::fs::create_dir_all(drive.join(sub)).unwrap();
    }
    // The snippet keeps the sequence's times.txt whole; its first frames are the ones with images.
    let frames = std::fs::read_dir(seq.join("image_2")).unwrap().count();
    for (f, t) in times.iter().enumerate().take(frames) {
        let name = format!("{f:010}");
        for (from, to) in [("image_2", "image_02"), ("image_3", "image_03")] {
            std::fs::copy(
                seq.join(format!("{from}/{f:06}.png")),
                drive.join(format!("{to}/data/{name}.png")),
            )
            .unwrap();
        }
        std::fs::copy(
            seq.join(format!("velodyne/{f:06}.bin")),
            drive.join(format!("velodyne_points/data/{name}.bin")),
        )
        .unwrap();
        let o = oxts_from_pose(&(g * gt.poses()[f] * t_cam0_imu), lat0);
        // The 30 numbers of a record: position and attitude, then velocities etc. (unused) as zeros.
        let mut rec = format!(
            "{} {} {} {} {} {}",
            o.lat, o.lon, o.alt, o.roll, o.pitch, o.yaw
        );
        rec.push_str(&" 0".repeat(19));
        rec.push_str(" 4 10 4 4 0\n");
        std::fs::write(drive.join(format!("oxts/data/{name}.txt")), rec).unwrap();
        stamps.push_str(&format!("2011-09-26 13:02:{:012.9}\n", 20.0 + t));
    }
    std::fs::write(drive.join("image_02/timestamps.txt"), stamps).unwrap();
    drive
}

/// The raw release's layout (a drive folder, its OXTS for poses) imports to the same dataset as the
/// odometry layout of the same frames: images, lidar and depth bit-equal, poses equal to a micrometre.
#[test]
fn a_kitti_raw_drive_imports_like_the_odometry_sequence_made_from_it() {
    let Some(seq) = silvr_tests::shared_data("real/kitti_odometry/sequences/03") else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let date_dir = tmp.path().join("2011_09_26");
    let drive = write_raw_drive(&seq, &date_dir);
    let (raw, odo) = (tmp.path().join("raw"), tmp.path().join("odo"));
    let out = import(&drive, &raw, &["--downscale", "4"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    let s: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(
        (&s["layout"], &s["keyframes"], &s["images"]),
        (&"raw".into(), &10.into(), &20.into()),
        "{s}"
    );
    assert!(s["poses"].as_str().unwrap().contains("OXTS"), "{s}");
    assert!(import(&seq, &odo, &["--downscale", "4"]).status.success());
    for k in 0..10 {
        for (a, b) in [("image_02", "image_2"), ("image_03", "image_3")] {
            for kind in ["images", "lidar_depth", "lidar_normals", "sky_mask"] {
                let f = |root: &Path, cam: &str| {
                    std::fs::read(root.join(format!("{kind}/{cam}/{k:05}.png"))).unwrap()
                };
                assert!(f(&raw, a) == f(&odo, b), "{kind}/{a}/{k:05}.png differs");
            }
        }
        let ply = |root: &Path| std::fs::read(root.join(format!("lidar/raw/{k:05}.ply"))).unwrap();
        assert!(ply(&raw) == ply(&odo), "sweep {k} differs");
    }
    for file in ["base_tum.txt", "lidar_tum.txt"] {
        let (a, b) = (
            read_tum(&raw.join("poses").join(file)).unwrap(),
            read_tum(&odo.join("poses").join(file)).unwrap(),
        );
        for (k, (p, q)) in a.poses().iter().zip(b.poses()).enumerate() {
            let (dt, dr) = (p.distance_to(q), p.rot.angle_between(q.rot));
            assert!(dt < 1e-6 && dr < 1e-8, "{file} {k}: {dt} m, {dr} rad");
        }
        for (t, u) in a.stamps().iter().zip(b.stamps()) {
            assert!((t - u).abs() < 1e-6, "{file}: stamps {t} vs {u}");
        }
    }

    // `silvr odometry` reads the drive too, scored against its OXTS (in the lidar frame): the same
    // sweeps and the same trajectory as the sequence gives (measured 2.7 cm ATE on 03, tests/odometry.rs).
    let odo_out = Command::new(build_silvr())
        .arg("odometry")
        .arg(&drive)
        .arg("--out")
        .arg(tmp.path().join("drive.tum"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&odo_out.stderr);
    assert!(odo_out.status.success(), "{err}");
    let r: serde_json::Value = serde_json::from_slice(&odo_out.stdout).unwrap();
    assert_eq!(
        (&r["kind"], &r["sweeps"]),
        (&"kitti".into(), &10.into()),
        "{r}"
    );
    let ate = r["pose_errors"]["errors"]["ate_rmse_m"].as_f64().unwrap();
    assert!(ate < 0.04, "{r}");

    // The date folder is not a drive: the error names the drives inside it.
    let out = import(&date_dir, &tmp.path().join("x"), &[]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success()
            && err.contains("2011_09_26_drive_0067_sync")
            && !err.contains("panicked"),
        "{err}"
    );
    // A corrupt OXTS record is named, with its line; nothing is written.
    std::fs::write(drive.join("oxts/data/0000000003.txt"), "49.0 8.4 nan\n").unwrap();
    let out = import(&drive, &tmp.path().join("y"), &[]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("0000000003.txt") && !err.contains("panicked"),
        "{err}"
    );
    assert!(!tmp.path().join("y").exists());
}
