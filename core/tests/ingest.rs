//! Ingest end to end: MCAP bags (the shared conformance files, third-party-encoded fixtures in
//! `tests/data/ingest/`, bags we write with the `mcap` crate in every chunk/index/compression variant,
//! and damaged ones) and PCD files (the shared real scan, a pypcd4 file, and our own in every DATA kind).
//! Tests that need `../shared/data` print a line and pass when it is absent.

use std::collections::BTreeMap;
use std::io::Cursor;
use std::path::{Path, PathBuf};

use glam::{DQuat, DVec3};
use silvr_core::camera::Distortion;
use silvr_core::geometry::Se3;
use silvr_core::ingest::bag::{summarize, BagError, BagReader, Skip};
use silvr_core::ingest::pcd::{lzf_compress, read_pcd, read_pcd_bytes, PcdError};
use silvr_core::ingest::ros::{
    CameraInfo, CompressedImage, Header, Image, Odometry, Path as RosPath, PointCloud2, PointField,
    PointTimeKind, PoseStamped, RegionOfInterest, RosMessage, TfMessage, Time, TransformStamped,
};

/// `../shared/data` beside the workspace root when `rel` is inside it, or `None` (the test skips, with a
/// line saying so). With `SILVR_REQUIRE_DATA=1` (CI, where `../shared/data` is mounted) an absent `rel`
/// fails instead.
fn shared_data(what: &str, rel: &str) -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    if p.join(rel).exists() {
        return Some(p);
    }
    common::skip(
        "SILVR_REQUIRE_DATA",
        &format!("{what}: {} is absent", p.join(rel).display()),
    );
    None
}

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/ingest")
        .join(name)
}

fn header(sec: i32, nanosec: u32, frame: &str) -> Header {
    Header {
        stamp: Time { sec, nanosec },
        frame_id: frame.into(),
    }
}

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol
}

// ---------------------------------------------------------------------------------------------------
// Shared MCAP conformance files
// ---------------------------------------------------------------------------------------------------

#[test]
fn shared_mcaps_read_and_known_types_decode() {
    let Some(data) = shared_data("shared MCAP fixtures", "formats/mcap") else {
        return;
    };
    let dir = data.join("formats/mcap");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .collect();
    files.sort();
    assert!(files.len() >= 4, "{files:?}");
    let mut summaries = BTreeMap::new();
    for f in &files {
        let s = summarize(f).unwrap_or_else(|e| panic!("{e}"));
        assert!(s.messages > 0, "{}", f.display());
        assert_eq!(s.decode_errors, 0, "{}: {:?}", f.display(), s.first_errors);
        let per_topic: u64 = s.topics.values().map(|t| t.messages).sum();
        assert_eq!(per_topic, s.messages);
        let decoded: u64 = s.topics.values().map(|t| t.decoded).sum();
        let skipped: u64 = s.skipped.values().sum();
        assert_eq!(decoded + skipped, s.messages, "{}", f.display());
        summaries.insert(f.file_name().unwrap().to_string_lossy().to_string(), s);
    }

    let nav = &summaries["nav2_turtlebot.mcap"];
    let counts: Vec<(&str, u64, u64)> = nav
        .topics
        .iter()
        .map(|(k, t)| (k.as_str(), t.messages, t.decoded))
        .collect();
    assert_eq!(
        counts,
        vec![
            ("/amcl_pose", 135, 135),
            ("/odom", 2639, 2639),
            ("/tf", 5422, 5422),
            ("/tf_static", 1, 1)
        ]
    );
    assert!(nav.skipped.is_empty());
    assert_eq!(nav.topics["/odom"].schema_name, "nav_msgs/msg/Odometry");
    let (t0, t1) = nav.span.unwrap();
    assert!(t0 <= 1_778_234_353_382_747_000 && t1 > t0);

    let cdr = &summaries["cdr_test_0.mcap"];
    assert_eq!(
        cdr.skipped.get("no decoder for test_msgs/msg/BasicTypes"),
        Some(&3)
    );
    assert_eq!(
        cdr.skipped.get("no decoder for test_msgs/msg/Arrays"),
        Some(&4)
    );
    let wrong = &summaries["wrong_rmw_test_0.mcap"];
    assert_eq!(
        wrong
            .skipped
            .get("message encoding 'wrong_format' is not cdr"),
        Some(&7)
    );
    let rewriter = &summaries["rewriter_a_0.mcap"];
    assert_eq!(rewriter.topics["a_empty"].messages, 100);
    assert_eq!(rewriter.topics["b_basictypes"].messages, 50);
}

/// Expected values from the reference Python decoder (mcap 1.x + mcap-ros2-support, which decodes from
/// the schema text in the file), printed by `scripts/crosscheck_mcap.py` on
/// `../shared/data/formats/mcap/nav2_turtlebot.mcap`.
#[test]
fn nav2_turtlebot_matches_python_decoder() {
    let Some(data) = shared_data(
        "nav2_turtlebot cross-check",
        "formats/mcap/nav2_turtlebot.mcap",
    ) else {
        return;
    };
    let path = data.join("formats/mcap/nav2_turtlebot.mcap");
    let mut odom = Vec::new();
    let mut tf = None;
    let mut tf_static = None;
    let mut amcl = None;
    for msg in BagReader::open(&path).unwrap() {
        let msg = msg.unwrap();
        let index = msg.index;
        let log_time = msg.log_time();
        match msg.decode().unwrap() {
            Ok(RosMessage::Odometry(o)) if odom.len() <= 100 => odom.push((index, log_time, o)),
            Ok(RosMessage::Tf(t)) if msg.topic() == "/tf" && tf.is_none() => {
                tf = Some((index, log_time, t))
            }
            Ok(RosMessage::Tf(t)) if msg.topic() == "/tf_static" => tf_static = Some((index, t)),
            Ok(RosMessage::PoseWithCovarianceStamped(p)) if amcl.is_none() => {
                amcl = Some((index, p))
            }
            _ => {}
        }
    }

    // odom_0
    let (index, log_time, o) = &odom[0];
    assert_eq!((*index, *log_time), (0, 1_778_234_353_382_747_000));
    assert_eq!(o.header, header(928, 800_000_000, "odom"));
    assert_eq!(o.child_frame_id, "base_link");
    assert_eq!(
        o.pose.trans,
        DVec3::new(-2.8019166340612314, 1.0977901491292252, 0.0)
    );
    assert_eq!(
        o.pose.rot,
        DQuat::from_xyzw(-0.0, 0.0, 0.08457359616958599, -0.9964172353140746)
    );
    assert_eq!(o.pose_covariance[0], 0.0);
    assert_eq!(o.linear, DVec3::ZERO);

    // odom_100: moving, so the twist is non-zero.
    let (index, log_time, o) = &odom[100];
    assert_eq!((*index, *log_time), (309, 1_778_234_357_009_234_000));
    assert_eq!(o.header, header(932, 400_000_000, "odom"));
    assert_eq!(
        o.pose.trans,
        DVec3::new(-2.7975350686182927, 1.0970384416669292, 0.0)
    );
    assert_eq!(
        o.pose.rot,
        DQuat::from_xyzw(-0.0, 0.0, 0.08509008134296159, -0.9963732624157717)
    );
    assert_eq!(o.linear, DVec3::new(0.05810752467626894, 0.0, 0.0));
    assert_eq!(o.angular.z, -0.012776057890344712);

    // First /tf message: one odom -> base_link transform.
    let (index, log_time, t) = tf.unwrap();
    assert_eq!((index, log_time), (1, 1_778_234_353_382_761_000));
    assert_eq!(t.transforms.len(), 1);
    let t0 = &t.transforms[0];
    assert_eq!(t0.header, header(928, 800_000_000, "odom"));
    assert_eq!(t0.child_frame_id, "base_link");
    assert_eq!(
        t0.transform.trans,
        DVec3::new(-2.8019166340612314, 1.0977901491292252, 0.0)
    );
    assert_eq!(
        t0.transform.rot,
        DQuat::from_xyzw(-0.0, 0.0, 0.08457359616958599, -0.9964172353140746)
    );

    // /tf_static: 29 transforms; spot-check a rotated one and the last.
    let (index, ts) = tf_static.unwrap();
    assert_eq!(index, 4);
    assert_eq!(ts.transforms.len(), 29);
    let bump = &ts.transforms[2];
    assert_eq!(
        (bump.header.frame_id.as_str(), bump.child_frame_id.as_str()),
        ("base_link", "bump_front_left")
    );
    assert_eq!(bump.transform.trans, DVec3::new(0.02345, -0.0875, 0.025));
    assert_eq!(
        bump.transform.rot,
        DQuat::from_xyzw(0.0, 0.0, 0.25881891199876106, 0.9659258619541035)
    );
    let last = &ts.transforms[28];
    assert_eq!(
        (last.header.frame_id.as_str(), last.child_frame_id.as_str()),
        ("shell_link", "tower_sensor_plate")
    );
    assert_eq!(last.transform.trans, DVec3::new(0.0, 0.0, 0.25257));

    // First /amcl_pose.
    let (index, p) = amcl.unwrap();
    assert_eq!(index, 22);
    assert_eq!(p.header.frame_id, "map");
    assert_eq!(
        p.pose.trans,
        DVec3::new(4.36519665396771, 7.579351695734543, 0.0)
    );
    assert_eq!(
        p.pose.rot,
        DQuat::from_xyzw(0.0, 0.0, 0.08968222067714808, 0.9959704309337779)
    );
    assert_eq!(
        [p.covariance[0], p.covariance[7], p.covariance[35]],
        [
            0.028234069455002037,
            0.022814564407611353,
            0.01388336421478153
        ]
    );
}

// ---------------------------------------------------------------------------------------------------
// Third-party-encoded fixture: lz4 chunks, messages serialised by mcap-ros2-support
// ---------------------------------------------------------------------------------------------------

/// `tests/data/ingest/py_ros2_lz4.mcap`, written by `scripts/make_ingest_fixtures.py`.
#[test]
fn python_encoded_lz4_bag_decodes() {
    let path = fixture("py_ros2_lz4.mcap");
    let s = summarize(&path).unwrap();
    assert_eq!(s.messages, 6);
    assert_eq!(s.decode_errors, 0, "{:?}", s.first_errors);
    assert!(s.skipped.is_empty());
    let mut seen = 0;
    for msg in BagReader::open(&path).unwrap() {
        let msg = msg.unwrap();
        assert_eq!(msg.message_encoding(), "cdr");
        assert_eq!(msg.schema_encoding(), "ros2msg");
        match msg.decode().unwrap().unwrap() {
            RosMessage::PointCloud2(pc) => {
                assert_eq!(msg.topic(), "/hesai/pandar");
                assert_eq!((pc.point_step, pc.width, pc.fields.len()), (26, 6, 6));
                let scan = pc.to_scan().unwrap();
                assert_eq!(scan.frame_id, "hesai_lidar");
                assert_eq!(scan.time_kind, Some(PointTimeKind::AbsoluteSeconds));
                assert_eq!(scan.skipped_nonfinite, 1);
                assert_eq!(scan.positions.len(), 5);
                // Point 4 (the 4th kept): x = 5, y = -2, z = 0.25, intensity 40, time 0.04 s.
                assert_eq!(scan.positions[3], DVec3::new(5.0, -2.0, 0.25));
                assert_eq!(scan.intensities.as_ref().unwrap()[3], 40.0);
                let t = scan.times.as_ref().unwrap();
                for (got, k) in t.iter().zip([0, 1, 2, 4, 5]) {
                    assert!(close(*got, 0.01 * k as f64, 1e-6), "{t:?}");
                }
                seen |= 1;
            }
            RosMessage::Image(img) => {
                let rgb = img.to_rgb().unwrap();
                assert_eq!(
                    rgb.pixels,
                    vec![[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255]]
                );
                seen |= 2;
            }
            RosMessage::CompressedImage(ci) => {
                let rgb = ci.to_rgb().unwrap();
                assert_eq!((rgb.width, rgb.height), (2, 2));
                assert_eq!(
                    rgb.pixels,
                    vec![[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255]]
                );
                seen |= 4;
            }
            RosMessage::CameraInfo(ci) => {
                let cam = ci.camera_model().unwrap();
                assert_eq!((cam.width, cam.height), (720, 540));
                assert_eq!(
                    (cam.fx, cam.fy, cam.cx, cam.cy),
                    (349.1, 349.2, 356.4, 280.3)
                );
                assert_eq!(
                    cam.distortion,
                    Distortion::Fisheye {
                        k1: -0.041142,
                        k2: -0.002422,
                        k3: 0.0034,
                        k4: -0.001852
                    }
                );
                seen |= 8;
            }
            RosMessage::Tf(tf) => {
                assert_eq!(tf.transforms.len(), 2);
                assert_eq!(tf.transforms[1].child_frame_id, "cam0");
                assert_eq!(
                    tf.transforms[1].transform.rot,
                    DQuat::from_xyzw(0.50347, 0.50033, -0.49475, 0.50140)
                );
                assert_eq!(
                    tf.transforms[0].transform.trans,
                    DVec3::new(0.0, 0.0, 0.124)
                );
                seen |= 16;
            }
            RosMessage::Path(p) => {
                assert_eq!(p.poses.len(), 3);
                assert_eq!(p.poses[2].pose.trans, DVec3::new(2.0, 4.0, 0.0));
                assert_eq!(p.poses[2].header.stamp.nanosec, 2);
                seen |= 32;
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    assert_eq!(seen, 63);
}

// ---------------------------------------------------------------------------------------------------
// Bags we write with the mcap crate: every container variant, then damage them
// ---------------------------------------------------------------------------------------------------

/// The messages of a small bag: (topic, schema name, payload).
fn sample_messages() -> Vec<(&'static str, &'static str, Vec<u8>)> {
    let f = |n, o, t| PointField::new(n, o, t);
    let mut data = Vec::new();
    for k in 0..50u32 {
        for v in [k as f32, 1.0, -2.0, 5.0] {
            data.extend_from_slice(&v.to_le_bytes());
        }
        data.extend_from_slice(&(k * 1000).to_le_bytes());
    }
    let pc = PointCloud2 {
        header: header(100, 0, "os_lidar"),
        height: 1,
        width: 50,
        fields: vec![
            f("x", 0, 7),
            f("y", 4, 7),
            f("z", 8, 7),
            f("intensity", 12, 7),
            f("t", 16, 6),
        ],
        is_bigendian: false,
        point_step: 20,
        row_step: 1000,
        data: &data,
        is_dense: true,
    };
    let pixels = [9u8; 4 * 3 * 3];
    let img = Image {
        header: header(100, 1, "cam"),
        height: 3,
        width: 4,
        encoding: "rgb8".into(),
        is_bigendian: 0,
        step: 12,
        data: &pixels,
    };
    let png = silvr_core::dataset::png_rgb(2, 1, &[[1, 2, 3], [4, 5, 6]]);
    let ci = CompressedImage {
        header: header(100, 2, "cam"),
        format: "png".into(),
        data: &png,
    };
    let info = CameraInfo {
        header: header(100, 3, "cam"),
        height: 3,
        width: 4,
        distortion_model: "plumb_bob".into(),
        d: vec![0.1, 0.0, 0.0, 0.0, 0.0],
        k: [2.0, 0.0, 1.5, 0.0, 2.0, 1.0, 0.0, 0.0, 1.0],
        r: [0.0; 9],
        p: [0.0; 12],
        binning_x: 0,
        binning_y: 0,
        roi: RegionOfInterest::default(),
    };
    let pose = |x: f64| Se3 {
        rot: DQuat::IDENTITY,
        trans: DVec3::new(x, 0.0, 0.0),
    };
    let tf = TfMessage {
        transforms: vec![TransformStamped {
            header: header(100, 4, "odom"),
            child_frame_id: "base_link".into(),
            transform: pose(1.0),
        }],
    };
    let odom = Odometry {
        header: header(100, 5, "odom"),
        child_frame_id: "base_link".into(),
        pose: pose(2.0),
        pose_covariance: [0.0; 36],
        linear: DVec3::X,
        angular: DVec3::Z,
        twist_covariance: [0.0; 36],
    };
    let ps = PoseStamped {
        header: header(100, 6, "map"),
        pose: pose(3.0),
    };
    let path = RosPath {
        header: header(100, 7, "map"),
        poses: vec![ps.clone(), ps.clone()],
    };
    vec![
        ("/points", PointCloud2::MSG, pc.encode()),
        ("/image", Image::MSG, img.encode()),
        ("/image/compressed", CompressedImage::MSG, ci.encode()),
        ("/camera_info", CameraInfo::MSG, info.encode()),
        ("/tf", TfMessage::MSG, tf.encode()),
        ("/odom", Odometry::MSG, odom.encode()),
        ("/pose", PoseStamped::MSG, ps.encode()),
        ("/path", RosPath::MSG, path.encode()),
        ("/imu", "sensor_msgs/msg/Imu", vec![0, 1, 0, 0, 1, 2, 3, 4]),
    ]
}

#[derive(Clone, Copy, Debug)]
enum Variant {
    Plain,
    Zstd,
    Lz4,
    Unchunked,
    Unindexed,
}

/// Writes the sample messages (each `repeat` times) as an MCAP with the ROS 2 profile.
fn write_bag(variant: Variant, repeat: usize) -> Vec<u8> {
    let mut opts = mcap::WriteOptions::new()
        .profile("ros2")
        .chunk_size(Some(4096))
        .compression(match variant {
            Variant::Zstd => Some(mcap::Compression::Zstd),
            Variant::Lz4 => Some(mcap::Compression::Lz4),
            _ => None,
        });
    match variant {
        Variant::Unchunked => opts = opts.use_chunks(false),
        Variant::Unindexed => {
            opts = opts
                .emit_summary_records(false)
                .emit_summary_offsets(false)
                .emit_statistics(false)
                .emit_message_indexes(false)
                .emit_chunk_indexes(false)
        }
        _ => {}
    }
    let mut out = Cursor::new(Vec::new());
    {
        let mut w = opts.create(&mut out).unwrap();
        let msgs = sample_messages();
        let mut channels = Vec::new();
        for (topic, schema, _) in &msgs {
            let sid = w.add_schema(schema, "ros2msg", b"# schema text").unwrap();
            channels.push(w.add_channel(sid, topic, "cdr", &BTreeMap::new()).unwrap());
        }
        let json = w
            .add_channel(0, "/diagnostics_json", "json", &BTreeMap::new())
            .unwrap();
        let mut seq = 0;
        for r in 0..repeat {
            for ((_, _, payload), &channel_id) in msgs.iter().zip(&channels) {
                seq += 1;
                let header = mcap::records::MessageHeader {
                    channel_id,
                    sequence: seq,
                    log_time: 1_000_000_000 * (r as u64 + 1) + seq as u64,
                    publish_time: 0,
                };
                w.write_to_known_channel(&header, payload).unwrap();
            }
            let header = mcap::records::MessageHeader {
                channel_id: json,
                sequence: 0,
                log_time: 1_000_000_000 * (r as u64 + 1),
                publish_time: 0,
            };
            w.write_to_known_channel(&header, b"{}").unwrap();
        }
        w.finish().unwrap();
    }
    out.into_inner()
}

fn temp_file(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

#[test]
fn every_container_variant_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let expected = sample_messages();
    for variant in [
        Variant::Plain,
        Variant::Zstd,
        Variant::Lz4,
        Variant::Unchunked,
        Variant::Unindexed,
    ] {
        let bytes = write_bag(variant, 3);
        let path = temp_file(dir.path(), &format!("{variant:?}.mcap"), &bytes);
        let mut n = 0;
        for msg in BagReader::open(&path).unwrap() {
            let msg = msg.unwrap();
            n += 1;
            if msg.topic() == "/diagnostics_json" {
                assert_eq!(msg.decode().unwrap(), Err(Skip::NotCdr("json".into())));
                continue;
            }
            let (_, schema, payload) = expected.iter().find(|(t, _, _)| *t == msg.topic()).unwrap();
            assert_eq!(msg.schema_name(), *schema);
            assert_eq!(msg.data(), &payload[..], "{variant:?} {}", msg.topic());
            match msg.decode().unwrap() {
                Ok(RosMessage::PointCloud2(pc)) => {
                    let scan = pc.to_scan().unwrap();
                    assert_eq!(scan.positions.len(), 50);
                    assert_eq!(scan.time_kind, Some(PointTimeKind::RelativeNanos));
                    assert!(close(scan.times.unwrap()[49], 49e-6, 1e-12));
                }
                Ok(RosMessage::Image(img)) => {
                    assert_eq!(img.to_rgb().unwrap().pixels, vec![[9; 3]; 12])
                }
                Ok(RosMessage::CompressedImage(c)) => {
                    assert_eq!(c.to_rgb().unwrap().pixels, vec![[1, 2, 3], [4, 5, 6]])
                }
                Ok(RosMessage::CameraInfo(c)) => assert_eq!(c.camera_model().unwrap().fx, 2.0),
                Ok(RosMessage::Odometry(o)) => assert_eq!(o.linear, DVec3::X),
                Ok(RosMessage::Path(p)) => assert_eq!(p.poses.len(), 2),
                Ok(RosMessage::Tf(t)) => assert_eq!(t.transforms[0].child_frame_id, "base_link"),
                Ok(RosMessage::PoseStamped(p)) => assert_eq!(p.pose.trans.x, 3.0),
                Ok(other) => panic!("unexpected {other:?}"),
                Err(skip) => assert_eq!(skip, Skip::UnknownType("sensor_msgs/msg/Imu".into())),
            }
        }
        assert_eq!(n, 3 * 10, "{variant:?}");
        let s = summarize(&path).unwrap();
        assert_eq!(s.messages, 30);
        assert_eq!(s.decode_errors, 0);
        assert_eq!(s.topics["/points"].decoded, 3);
        assert_eq!(s.skipped["no decoder for sensor_msgs/msg/Imu"], 3);
        assert_eq!(s.skipped["message encoding 'json' is not cdr"], 3);
        // The 9 CDR messages of each round carry sequence numbers 1..=27 in their log times.
        assert_eq!(s.span, Some((1_000_000_000, 3_000_000_027)));
        assert!(close(s.duration(), 2.000000027, 1e-12));
    }
}

/// Reads the whole bag; `Err` as soon as the container reports a problem.
fn read_all(path: &Path) -> Result<usize, BagError> {
    let mut n = 0;
    for m in BagReader::open(path)? {
        m?;
        n += 1;
    }
    Ok(n)
}

/// (topic, payload) of every message; `Err` as soon as the container reports a problem.
fn read_payloads(path: &Path) -> Result<Vec<(String, Vec<u8>)>, BagError> {
    BagReader::open(path)?
        .map(|m| m.map(|m| (m.topic().to_string(), m.data().to_vec())))
        .collect()
}

#[test]
fn truncated_bags_are_errors_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    for variant in [
        Variant::Zstd,
        Variant::Lz4,
        Variant::Unchunked,
        Variant::Unindexed,
    ] {
        let bytes = write_bag(variant, 1);
        assert_eq!(
            read_all(&temp_file(dir.path(), "full.mcap", &bytes)).unwrap(),
            10
        );
        // Every cut must fail; step through the file (all offsets near the ends, every 7th elsewhere).
        let cuts = (0..bytes.len()).filter(|&n| n < 64 || n + 64 > bytes.len() || n % 7 == 0);
        for n in cuts {
            let path = temp_file(dir.path(), "cut.mcap", &bytes[..n]);
            let e =
                read_all(&path).expect_err(&format!("{variant:?} cut at {n} of {}", bytes.len()));
            assert!(e.to_string().contains("cut.mcap"), "{e}");
        }
    }
    let path = temp_file(dir.path(), "cut.mcap", &write_bag(Variant::Zstd, 1)[..300]);
    let e = summarize(&path).unwrap_err();
    assert!(e.to_string().contains("truncated"), "{e}");
}

#[test]
fn corrupt_chunks_and_non_mcap_are_errors() {
    let dir = tempfile::tempdir().unwrap();
    let path = temp_file(
        dir.path(),
        "text.mcap",
        b"this is not an mcap file at all, sorry",
    );
    let e = read_all(&path).unwrap_err();
    assert!(
        e.to_string().contains("text.mcap") && e.to_string().contains("not a bag"),
        "{e}"
    );
    let e = read_all(&dir.path().join("missing.mcap")).unwrap_err();
    assert!(
        matches!(e, BagError::Io { .. }) && e.to_string().contains("missing.mcap"),
        "{e}"
    );

    // Flip each byte of the compressed records of every chunk: the chunk CRC (over the uncompressed
    // records) or the decompressor must catch it.
    for variant in [Variant::Plain, Variant::Zstd, Variant::Lz4] {
        let bytes = write_bag(variant, 2);
        let ranges = chunk_record_ranges(&bytes);
        assert!(!ranges.is_empty(), "{variant:?} has chunks");
        let original = read_payloads(&temp_file(dir.path(), "orig.mcap", &bytes)).unwrap();
        let (mut tries, mut detected) = (0, 0);
        for at in ranges.into_iter().flatten() {
            let mut b = bytes.clone();
            b[at] ^= 0x5a;
            tries += 1;
            let path = temp_file(dir.path(), "flip.mcap", &b);
            match read_payloads(&path) {
                Err(e) => {
                    assert!(e.to_string().contains("flip.mcap"), "{e}");
                    detected += 1;
                }
                // A few zstd bits do not change the output (the CRC then matches): the data must be intact.
                Ok(msgs) => assert_eq!(
                    msgs, original,
                    "{variant:?}: flip at {at} changed data silently"
                ),
            }
        }
        assert!(
            detected * 100 >= tries * 95,
            "{variant:?}: {detected}/{tries} flips detected"
        );
    }
}

#[test]
fn inconsistent_record_in_crc_less_chunk_is_an_error() {
    // Without a chunk CRC nothing catches a record that claims more bytes than its chunk holds; the
    // mcap crate then overflows (a panic in debug builds), which the reader must turn into an error.
    let dir = tempfile::tempdir().unwrap();
    let mut out = Cursor::new(Vec::new());
    {
        let mut w = mcap::WriteOptions::new()
            .compression(None)
            .calculate_chunk_crcs(false)
            .create(&mut out)
            .unwrap();
        let ch = w.add_channel(0, "/x", "cdr", &BTreeMap::new()).unwrap();
        for seq in 0..3 {
            let hdr = mcap::records::MessageHeader {
                channel_id: ch,
                sequence: seq,
                log_time: seq as u64,
                publish_time: 0,
            };
            w.write_to_known_channel(&hdr, &[0, 1, 0, 0, 7, 7, 7, 7])
                .unwrap();
        }
        w.finish().unwrap();
    }
    let bytes = out.into_inner();
    let ranges = chunk_record_ranges(&bytes);
    let records = ranges[0].clone();
    // Records inside the chunk: opcode u8 + length u64. Enlarge the last one's length.
    let mut pos = records.start;
    let mut last = pos;
    while pos < records.end {
        last = pos;
        pos += 9 + u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().unwrap()) as usize;
    }
    let mut b = bytes.clone();
    b[last + 1] = b[last + 1].wrapping_add(100);
    let path = temp_file(dir.path(), "nocrc.mcap", &b);
    let e = read_all(&path).unwrap_err();
    println!("{e}");
    assert!(e.to_string().contains("nocrc.mcap"), "{e}");
    assert_eq!(
        read_all(&temp_file(dir.path(), "ok.mcap", &bytes)).unwrap(),
        3
    );
}

/// Byte ranges of the (compressed) records inside each Chunk record of an MCAP file, from its layout:
/// magic (8), then records of opcode u8, length u64, content; a Chunk (opcode 6) holds start/end time,
/// uncompressed size (u64 each), uncompressed CRC (u32), compression (u32-length string), records
/// length (u64), records.
fn chunk_record_ranges(bytes: &[u8]) -> Vec<std::ops::Range<usize>> {
    let u64_at = |o: usize| u64::from_le_bytes(bytes[o..o + 8].try_into().unwrap()) as usize;
    let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().unwrap()) as usize;
    let mut out = Vec::new();
    let mut pos = 8;
    while pos + 9 <= bytes.len() - 8 {
        let (op, len) = (bytes[pos], u64_at(pos + 1));
        let content = pos + 9;
        if op == 0x06 {
            let comp_len = u32_at(content + 28);
            let rec_len_at = content + 32 + comp_len;
            let start = rec_len_at + 8;
            out.push(start..start + u64_at(rec_len_at));
        }
        pos = content + len;
    }
    out
}

#[test]
fn a_bad_payload_in_a_good_bag_is_counted_with_context() {
    let dir = tempfile::tempdir().unwrap();
    let mut out = Cursor::new(Vec::new());
    {
        let mut w = mcap::WriteOptions::new()
            .profile("ros2")
            .create(&mut out)
            .unwrap();
        let sid = w.add_schema(Odometry::MSG, "ros2msg", b"").unwrap();
        let ch = w
            .add_channel(sid, "/odom", "cdr", &BTreeMap::new())
            .unwrap();
        let hdr = mcap::records::MessageHeader {
            channel_id: ch,
            sequence: 1,
            log_time: 42,
            publish_time: 42,
        };
        w.write_to_known_channel(&hdr, &[0, 1, 0, 0, 1, 2]).unwrap();
        w.finish().unwrap();
    }
    let path = temp_file(dir.path(), "bad_payload.mcap", out.get_ref());
    let s = summarize(&path).unwrap();
    assert_eq!((s.messages, s.decode_errors), (1, 1));
    let e = &s.first_errors[0];
    assert!(
        e.contains("bad_payload.mcap")
            && e.contains("/odom")
            && e.contains("nav_msgs/msg/Odometry: truncated"),
        "{e}"
    );
}

// ---------------------------------------------------------------------------------------------------
// PCD
// ---------------------------------------------------------------------------------------------------

#[test]
fn shared_pcd_scan_reads() {
    let Some(data) = shared_data("shared PCD scan", "formats/pcd_camera_pair/0.pcd") else {
        return;
    };
    let pcd = read_pcd(&data.join("formats/pcd_camera_pair/0.pcd")).unwrap();
    assert_eq!(pcd.fields, ["x", "y", "z", "intensity"]);
    assert_eq!((pcd.width, pcd.height), (78238, 1));
    assert_eq!(pcd.viewpoint, Se3::IDENTITY);
    let cloud = &pcd.cloud;
    assert_eq!(cloud.len(), 78238);
    let finite = cloud.len() - cloud.count_nonfinite();
    assert!(finite > 70_000, "{finite} finite points");
    assert_eq!(
        cloud.positions[0],
        DVec3::new(21.647913, 0.19822195, -1.8524752)
    );
    assert_eq!(cloud.scalar("intensity").unwrap()[0], 11.0);
    // A car-mounted scan: ranges of a few to ~200 m, most points within 100 m.
    let (lo, hi) = cloud.bounds().unwrap();
    assert!(hi.x - lo.x > 20.0 && hi.x - lo.x < 500.0, "{lo} {hi}");
}

/// `tests/data/ingest/pypcd4_binary_compressed.pcd` from `scripts/make_ingest_fixtures.py`.
#[test]
fn pypcd4_compressed_pcd_reads() {
    let pcd = read_pcd(&fixture("pypcd4_binary_compressed.pcd")).unwrap();
    assert_eq!(pcd.fields, ["x", "y", "z", "intensity", "ring"]);
    let c = &pcd.cloud;
    assert_eq!(c.len(), 40);
    assert_eq!(c.count_nonfinite(), 1);
    assert!(c.positions[5].x.is_nan());
    for k in (0..40).filter(|&k| k != 5) {
        let kf = k as f64;
        assert_eq!(
            c.positions[k],
            DVec3::new(kf * 0.5, -kf * 0.25, (k % 7) as f64),
            "point {k}"
        );
        assert_eq!(c.scalar("intensity").unwrap()[k], 3.0 * kf as f32);
    }
}

/// A cloud written by this test in each DATA kind, with mixed field types and a count > 1 field.
fn pcd_bytes(kind: &str, n: usize, viewpoint: &str) -> Vec<u8> {
    let header = format!(
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x normal y z intensity rgb\n\
         SIZE 4 4 8 2 1 4\nTYPE F F F I U U\nCOUNT 1 3 1 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT {viewpoint}\n\
         POINTS {n}\nDATA {kind}\n"
    );
    let value = |k: usize| {
        (
            k as f32 * 0.5,
            [1.0f32, 2.0, 3.0],
            -(k as f64) * 1.25,
            k as i16 - 3,
            (k * 2) as u8,
            0x00102030u32 + k as u32,
        )
    };
    let mut out = header.into_bytes();
    match kind {
        "ascii" => {
            for k in 0..n {
                let (x, nn, y, z, i, rgb) = value(k);
                out.extend_from_slice(
                    format!("{x} {} {} {} {y} {z} {i} {rgb}\n", nn[0], nn[1], nn[2]).as_bytes(),
                );
            }
        }
        "binary" => {
            for k in 0..n {
                let (x, nn, y, z, i, rgb) = value(k);
                out.extend_from_slice(&x.to_le_bytes());
                nn.iter()
                    .for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
                out.extend_from_slice(&y.to_le_bytes());
                out.extend_from_slice(&z.to_le_bytes());
                out.push(i);
                out.extend_from_slice(&rgb.to_le_bytes());
            }
        }
        _ => {
            // Field-major: all x, all normals, all y, ...
            let mut raw = Vec::new();
            (0..n).for_each(|k| raw.extend_from_slice(&value(k).0.to_le_bytes()));
            (0..n).for_each(|k| {
                value(k)
                    .1
                    .iter()
                    .for_each(|v| raw.extend_from_slice(&v.to_le_bytes()))
            });
            (0..n).for_each(|k| raw.extend_from_slice(&value(k).2.to_le_bytes()));
            (0..n).for_each(|k| raw.extend_from_slice(&value(k).3.to_le_bytes()));
            (0..n).for_each(|k| raw.push(value(k).4));
            (0..n).for_each(|k| raw.extend_from_slice(&value(k).5.to_le_bytes()));
            let c = lzf_compress(&raw);
            out.extend_from_slice(&(c.len() as u32).to_le_bytes());
            out.extend_from_slice(&(raw.len() as u32).to_le_bytes());
            out.extend_from_slice(&c);
        }
    }
    out
}

#[test]
fn pcd_data_kinds_agree() {
    let vp = "1 2 3 0.70710678 0 0 0.70710678";
    for kind in ["ascii", "binary", "binary_compressed"] {
        let bytes = pcd_bytes(kind, 300, vp);
        let pcd = read_pcd_bytes(&bytes, kind).unwrap_or_else(|e| panic!("{e}"));
        let c = &pcd.cloud;
        assert_eq!(c.len(), 300, "{kind}");
        for k in [0usize, 7, 299] {
            assert_eq!(
                c.positions[k],
                DVec3::new(k as f64 * 0.5, -(k as f64) * 1.25, k as f64 - 3.0),
                "{kind} point {k}"
            );
            assert_eq!(c.scalar("intensity").unwrap()[k], (k * 2) as u8 as f32);
            let rgb = 0x00102030u32 + k as u32;
            assert_eq!(
                c.colors.as_ref().unwrap()[k],
                [(rgb >> 16) as u8, (rgb >> 8) as u8, rgb as u8]
            );
        }
        assert_eq!(pcd.viewpoint.trans, DVec3::new(1.0, 2.0, 3.0));
        let z90 = DQuat::from_rotation_z(std::f64::consts::FRAC_PI_2);
        assert!(pcd.viewpoint.rot.angle_between(z90) < 1e-6, "{kind}");
    }
}

#[test]
fn pcd_errors_name_the_file_and_never_over_allocate() {
    let dir = tempfile::tempdir().unwrap();
    // Billions of points claimed by a tiny file, in every DATA kind.
    for kind in ["ascii", "binary", "binary_compressed"] {
        let mut bytes = pcd_bytes(kind, 3, "0 0 0 1 0 0 0");
        let text = String::from_utf8_lossy(&bytes).to_string();
        let header_end = text.find(&format!("DATA {kind}\n")).unwrap() + kind.len() + 6;
        let body = bytes.split_off(header_end);
        let header = String::from_utf8(bytes)
            .unwrap()
            .replace("WIDTH 3", "WIDTH 4000000000")
            .replace("POINTS 3", "POINTS 4000000000");
        let mut huge = header.into_bytes();
        huge.extend_from_slice(&body);
        let path = temp_file(dir.path(), &format!("huge_{kind}.pcd"), &huge);
        let e = read_pcd(&path).unwrap_err();
        assert!(e.to_string().contains(&format!("huge_{kind}.pcd")), "{e}");
        assert!(
            matches!(e, PcdError::CountTooLarge { .. } | PcdError::Lzf { .. }),
            "{kind}: {e}"
        );
    }
    // Every truncation of each kind is an error, not a panic.
    for kind in ["ascii", "binary", "binary_compressed"] {
        let bytes = pcd_bytes(kind, 5, "0 0 0 1 0 0 0");
        // ASCII cannot tell a cut inside the last value from a shorter number, so it only has to fail
        // (and never panic) while the last line is incomplete up to its final value.
        let must_fail = if kind == "ascii" {
            let body = &bytes[..bytes.len() - 1];
            body.iter().rposition(|&b| b == b' ').unwrap()
        } else {
            bytes.len()
        };
        for n in 0..bytes.len() {
            let r = read_pcd_bytes(&bytes[..n], "cut.pcd");
            assert!(
                n >= must_fail || r.is_err(),
                "{kind} cut at {n} of {} read",
                bytes.len()
            );
        }
    }
    let cases: [(&str, &str); 6] = [
        (
            "VERSION 0.7\nFIELDS a b c\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nDATA ascii\n1 2 3\n",
            "no x, y and z",
        ),
        (
            "VERSION 0.7\nFIELDS x y z\nSIZE 4 4\nTYPE F F F\nWIDTH 1\nDATA ascii\n1 2 3\n",
            "differ in length",
        ),
        (
            "FIELDS x y z\nSIZE 4 4 3\nTYPE F F F\nWIDTH 1\nDATA ascii\n1 2 3\n",
            "SIZE '3'",
        ),
        (
            "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nPOINTS 2\nDATA ascii\n1 2 3\n",
            "POINTS 2 differs",
        ),
        (
            "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nDATA ascii\n1 oops 3\n",
            "'oops' is not a number",
        ),
        (
            "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nDATA binary_packed\n",
            "DATA binary_packed",
        ),
    ];
    for (text, want) in cases {
        let e = read_pcd_bytes(text.as_bytes(), "case.pcd")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(want) && e.starts_with("case.pcd: "),
            "{e} (wanted {want})"
        );
    }
    // A corrupt LZF stream.
    let mut bytes = pcd_bytes("binary_compressed", 50, "0 0 0 1 0 0 0");
    let n = bytes.len();
    bytes[n - 10] ^= 0xff;
    bytes[n - 20] = 0xff;
    assert!(read_pcd_bytes(&bytes, "lzf.pcd").is_err());
}

// ---------------------------------------------------------------------------------------------------
// The synthetic world as a bag → `silvr ingest` → the same dataset
// ---------------------------------------------------------------------------------------------------

mod common;

use silvr_core::dataset::{read_gray8, read_png16, read_rgb, Transforms};
use silvr_core::ingest::config::RigConfig;
use silvr_core::ingest::rosbag::{ingest_bag, IngestError};
use silvr_core::synthetic::bag::{rig_config, BagRecorder, EPOCH};
use silvr_core::synthetic::{generate, Preset};

/// The ci world cut to a few keyframes, generated as a dataset and recorded as a bag at the same time.
fn synth_with_bag(dir: &Path, gpu: &silvr_core::gpu::Gpu) -> Preset {
    let mut preset = Preset::ci(5);
    preset.keyframes = 4;
    let mut rec = BagRecorder::create(&dir.join("scene.mcap")).unwrap();
    pollster::block_on(generate::generate_recording(
        &preset,
        gpu,
        &dir.join("synth"),
        false,
        &mut |_| {},
        Some(&mut rec),
    ))
    .unwrap();
    preset
}

/// Fraction of entries where `a` and `b` differ by more than `tol`.
fn frac_differing<T: Copy + Into<f64>>(a: &[T], b: &[T], tol: f64) -> f64 {
    assert_eq!(a.len(), b.len());
    let n = a
        .iter()
        .zip(b)
        .filter(|(x, y)| ((**x).into() - (**y).into()).abs() > tol)
        .count();
    n as f64 / a.len() as f64
}

#[test]
fn synthetic_bag_ingests_to_the_generated_dataset() {
    let Some(gpu) = common::gpu() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let preset = synth_with_bag(dir, &gpu);
    // The rig file goes through its YAML form, as `silvr synth --mcap` writes it.
    let cfg = RigConfig::parse(&rig_config(&preset).to_yaml(), "scene.rig.yaml").unwrap();
    assert_eq!(cfg.ingest.lidar_topic, "/hesai/pandar");
    let summary = pollster::block_on(ingest_bag(
        &dir.join("scene.mcap"),
        &cfg,
        dir,
        &dir.join("ingested"),
        false,
        &gpu,
        &mut |_| {},
    ))
    .unwrap();
    println!("{}", serde_json::to_string_pretty(&summary).unwrap());
    assert_eq!(summary.keyframes, 4);
    assert_eq!(summary.images, 12);
    assert!(summary.dropped.is_empty(), "{:?}", summary.dropped);
    // Estimated from the clouds, not given: the ci lidar is 32 beams × 360 columns.
    assert_eq!((summary.lidar_beams, summary.lidar_columns), (32, 360));
    assert_eq!(
        summary.topics["/odometry"].used,
        summary.topics["/odometry"].messages
    );

    let (a, b) = (dir.join("synth"), dir.join("ingested"));
    let ta = Transforms::read(&a.join("transforms.json")).unwrap();
    let tb = Transforms::read(&b.join("transforms.json")).unwrap();
    assert_eq!(ta.frames.len(), tb.frames.len());
    assert_eq!(ta.train_filenames, tb.train_filenames);
    assert_eq!(ta.val_filenames, tb.val_filenames);
    let (mut worst_depth, mut worst_normal, mut worst_sky) = (0.0f64, 0.0f64, 0.0f64);
    for (fa, fb) in ta.frames.iter().zip(&tb.frames) {
        assert_eq!(fa.file_path, fb.file_path);
        assert_eq!(
            (fa.fl_x, fa.fl_y, fa.cx, fa.cy, fa.k1, fa.k4),
            (fb.fl_x, fb.fl_y, fb.cx, fb.cy, fb.k1, fb.k4)
        );
        for (ra, rb) in fa.transform_matrix.iter().zip(&fb.transform_matrix) {
            for (x, y) in ra.iter().zip(rb) {
                assert!(
                    (x - y).abs() < 1e-6,
                    "{} pose {ra:?} vs {rb:?}",
                    fa.file_path
                );
            }
        }
        assert!((fa.time.unwrap() + EPOCH - fb.time.unwrap()).abs() < 1e-6);
        // Images: lossless through the bag.
        assert_eq!(
            read_rgb(&a.join(&fa.file_path)).unwrap(),
            read_rgb(&b.join(&fb.file_path)).unwrap()
        );
        // Depth within the PNG quantisation (1/256 m); the bag's f32 coordinates may move a return across
        // a pixel border or flip which of two nearly equal returns wins, rarely.
        let da = read_png16(&a.join(fa.depth_file_path.as_ref().unwrap()))
            .unwrap()
            .2;
        let db = read_png16(&b.join(fb.depth_file_path.as_ref().unwrap()))
            .unwrap()
            .2;
        let filled = da.iter().filter(|&&d| d > 0 && d < u16::MAX).count();
        assert!(filled > 300, "{}: only {filled} lidar pixels", fa.file_path);
        worst_depth =
            worst_depth.max(frac_differing(&da, &db, 1.0) * da.len() as f64 / filled as f64);
        let na: Vec<u8> = read_rgb(&a.join(fa.normal_file_path.as_ref().unwrap()))
            .unwrap()
            .2
            .concat();
        let nb: Vec<u8> = read_rgb(&b.join(fb.normal_file_path.as_ref().unwrap()))
            .unwrap()
            .2
            .concat();
        worst_normal =
            worst_normal.max(frac_differing(&na, &nb, 2.0) * da.len() as f64 / filled as f64);
        let sa = read_gray8(&a.join(fa.sky_mask_path.as_ref().unwrap()))
            .unwrap()
            .2;
        let sb = read_gray8(&b.join(fb.sky_mask_path.as_ref().unwrap()))
            .unwrap()
            .2;
        worst_sky = worst_sky.max(frac_differing(&sa, &sb, 0.0));
    }
    println!("differing: depth {worst_depth:.2e} of lidar pixels, normals {worst_normal:.2e}, sky {worst_sky:.2e} of all");
    assert!(
        worst_depth <= 2e-3,
        "depth differs on {worst_depth:.2e} of lidar pixels"
    );
    assert!(worst_normal <= 5e-3, "normals differ on {worst_normal:.2e}");
    assert!(
        worst_sky <= 1e-3,
        "sky masks differ on {worst_sky:.2e} of pixels"
    );
    // Deskewed sweeps agree to the f32 precision of PointCloud2 coordinates.
    for k in 0..4 {
        let rel = format!("lidar/deskewed/{k:05}.ply");
        let pa = silvr_core::pointcloud::read_ply(&a.join(&rel)).unwrap();
        let pb = silvr_core::pointcloud::read_ply(&b.join(&rel)).unwrap();
        assert_eq!(pa.len(), pb.len(), "{rel}");
        let worst = pa
            .positions
            .iter()
            .zip(&pb.positions)
            .filter(|(p, _)| p.is_finite())
            .map(|(p, q)| (*p - *q).length())
            .fold(0.0, f64::max);
        assert!(worst < 1e-4, "{rel}: {worst} m");
        assert_eq!(pa.scalar("ring"), pb.scalar("ring"), "{rel}");
        assert_eq!(
            pa.scalar("column"),
            pb.scalar("column"),
            "{rel}: columns recovered from azimuths"
        );
    }
    // Poses: lidar trajectory at the keyframes.
    let pa = silvr_core::dataset::read_tum(&a.join("poses/lidar_tum.txt")).unwrap();
    let pb = silvr_core::dataset::read_tum(&b.join("poses/lidar_tum.txt")).unwrap();
    for ((sa, qa), (sb, qb)) in pa
        .stamps()
        .iter()
        .zip(pa.poses())
        .zip(pb.stamps().iter().zip(pb.poses()))
    {
        assert!((sa + EPOCH - sb).abs() < 1e-6);
        assert!(qa.distance_to(qb) < 1e-6 && qa.angle_to(qb) < 1e-6);
    }
}

#[test]
fn broken_bags_and_rig_files_fail_cleanly_without_a_dataset() {
    let Some(gpu) = common::gpu() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let preset = synth_with_bag(dir, &gpu);
    let bag = dir.join("scene.mcap");
    let ingest = |bag: &Path, cfg: &RigConfig, out: &str| {
        pollster::block_on(ingest_bag(
            bag,
            cfg,
            dir,
            &dir.join(out),
            false,
            &gpu,
            &mut |_| {},
        ))
    };
    let no_partial = |name: &str| {
        let left: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.contains(name))
            .collect();
        assert!(left.is_empty(), "left behind: {left:?}");
    };
    // A wrong lidar topic: named, with the topics the bag has.
    let mut cfg = rig_config(&preset);
    cfg.ingest.lidar_topic = "/velodyne_points".into();
    let e = ingest(&bag, &cfg, "o1").unwrap_err().to_string();
    assert!(
        e.contains("scene.mcap") && e.contains("/velodyne_points") && e.contains("/hesai/pandar"),
        "{e}"
    );
    no_partial("o1");
    // No extrinsics in the rig file: taken from /tf_static, same result as with them.
    let mut cfg = rig_config(&preset);
    cfg.sensor.t_base_lidar = None;
    for c in &mut cfg.sensor.cameras {
        c.t_cam_lidar = None;
        c.intrinsics = None; // and intrinsics from CameraInfo
    }
    let s = ingest(&bag, &cfg, "o2").unwrap();
    assert_eq!(s.keyframes, 4);
    let rig_tf: silvr_core::rig::Rig =
        serde_json::from_str(&std::fs::read_to_string(dir.join("o2/calib/rig.json")).unwrap())
            .unwrap();
    for (c, want) in rig_tf.cameras.iter().zip(&preset.rig.cameras) {
        assert!(c.t_lidar_cam.distance_to(&want.t_lidar_cam) < 1e-9);
        assert!(
            (c.model.fx - want.model.fx).abs() < 1e-9
                && c.model.distortion == want.model.distortion
        );
    }
    // ... but without either, a clear error.
    let mut cfg2 = cfg.clone();
    cfg2.ingest.base_frame = "body".into();
    let e = ingest(&bag, &cfg2, "o3").unwrap_err().to_string();
    assert!(e.contains("T_base_lidar") && e.contains("body"), "{e}");
    no_partial("o3");
    // A truncated bag: a container error naming the file, and no dataset.
    let bytes = std::fs::read(&bag).unwrap();
    let cut = dir.join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let e = ingest(&cut, &rig_config(&preset), "o4").unwrap_err();
    assert!(matches!(e, IngestError::Bag(_)), "{e}");
    assert!(e.to_string().contains("cut.mcap"), "{e}");
    assert!(!dir.join("o4").exists());
    no_partial("o4");
    // Keyframe thinning: 4 keyframes 0.7 m apart, a 1.2 m rule keeps every second.
    let mut cfg = rig_config(&preset);
    cfg.ingest.keyframe_distance = 1.2;
    cfg.ingest.keyframe_angle_deg = 90.0;
    let s = ingest(&bag, &cfg, "o5").unwrap();
    assert_eq!(s.keyframes, 2, "{:?}", s.dropped);
    assert_eq!(s.dropped.values().sum::<u64>(), 2);
}

#[test]
fn dgp_scene_becomes_a_dataset_whose_depth_agrees_with_an_independent_projection() {
    let Some(data) = shared_data("the DGP scene import", "real/dgp_scene_02") else {
        return;
    };
    let Some(gpu) = common::gpu() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("dgp");
    let s = pollster::block_on(silvr_core::ingest::dgp::import_dgp(
        &data.join("real/dgp_scene_02"),
        &out,
        false,
        silvr_core::ingest::dgp::DgpOptions {
            downscale: 4,
            ..Default::default()
        },
        &gpu,
        &mut |_, _| {},
    ))
    .unwrap();
    println!("{}", serde_json::to_string_pretty(&s).unwrap());
    assert_eq!((s.keyframes, s.images), (3, 18));
    // Thousands of lidar pixels in every camera (5k-12k points fall in each at full resolution).
    for (cam, n) in &s.depth_pixels {
        assert!(*n >= 3000, "{cam}: {n} lidar pixels over 3 keyframes");
    }
    // The written depth (GPU z-buffer) against the CPU reference projection of the written sweep with the
    // written poses.
    let t = Transforms::read(&out.join("transforms.json")).unwrap();
    assert_eq!(
        (t.train_filenames.len(), t.val_filenames.len()),
        (12, 6),
        "the middle sample is held out"
    );
    let lidar = silvr_core::dataset::read_tum(&out.join("poses/lidar_tum.txt")).unwrap();
    let pts = silvr_core::pointcloud::read_ply(&out.join("lidar/deskewed/00000.ply")).unwrap();
    let f = t
        .frames
        .iter()
        .find(|f| f.keyframe == Some(0) && f.camera.as_deref() == Some("CAMERA_05"))
        .unwrap();
    let (model, t_world_cam) = f.camera(&out.join("transforms.json")).unwrap();
    let t_cam_lidar = t_world_cam.inverse() * lidar.poses()[0];
    let proj =
        silvr_core::lidar::project::project_cpu(&silvr_core::lidar::project::ProjectionInput {
            camera: &model,
            t_cam_points: t_cam_lidar,
            points: &pts.positions,
            near: 0.5,
        })
        .unwrap();
    let written = read_png16(&out.join(f.depth_file_path.as_ref().unwrap()))
        .unwrap()
        .2;
    let (mut agree, mut total) = (0, 0);
    for (pix, &r) in proj.range.iter().enumerate() {
        if r > 0.0 {
            total += 1;
            let want = silvr_core::lidar::images::encode_depth(r) as i32;
            if (written[pix] as i32 - want).abs() <= 1 {
                agree += 1;
            }
        }
    }
    println!("CAMERA_05 keyframe 0: {agree} of {total} lidar pixels agree");
    assert!(
        total > 1000 && agree as f64 >= 0.99 * total as f64,
        "{agree} of {total}"
    );
}

#[test]
fn synthetic_dataset_round_trips_through_the_spires_layout() {
    let Some(gpu) = common::gpu() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    synth_with_bag(dir, &gpu);
    let (a, sp, b) = (dir.join("synth"), dir.join("spires"), dir.join("back"));
    let n = silvr_core::ingest::spires::export_spires(&a, &sp).unwrap();
    assert_eq!(n, 12);
    assert!(
        sp.join("sensor.yaml").exists() && sp.join("processed/vilens-slam/slam-poses.csv").exists()
    );
    // The Spires rig file holds no ingest block: every image set is 0.7 m from the last, so the default
    // 0.5 m rule keeps all four.
    let s = pollster::block_on(silvr_core::ingest::spires::import_spires(
        &sp,
        None,
        &b,
        false,
        &gpu,
        &mut |_, _| {},
    ))
    .unwrap();
    println!("{}", serde_json::to_string_pretty(&s).unwrap());
    assert_eq!((s.keyframes, s.images), (4, 12));
    let ta = Transforms::read(&a.join("transforms.json")).unwrap();
    let tb = Transforms::read(&b.join("transforms.json")).unwrap();
    let (mut worst_depth, mut worst_normal, mut worst_sky) = (0.0f64, 0.0f64, 0.0f64);
    for (fa, fb) in ta.frames.iter().zip(&tb.frames) {
        assert_eq!(fa.file_path, fb.file_path);
        for (ra, rb) in fa.transform_matrix.iter().zip(&fb.transform_matrix) {
            for (x, y) in ra.iter().zip(rb) {
                assert!((x - y).abs() < 1e-6, "{}: {ra:?} vs {rb:?}", fa.file_path);
            }
        }
        assert_eq!(
            read_rgb(&a.join(&fa.file_path)).unwrap(),
            read_rgb(&b.join(&fb.file_path)).unwrap()
        );
        let da = read_png16(&a.join(fa.depth_file_path.as_ref().unwrap()))
            .unwrap()
            .2;
        let db = read_png16(&b.join(fb.depth_file_path.as_ref().unwrap()))
            .unwrap()
            .2;
        let filled = da.iter().filter(|&&d| d > 0 && d < u16::MAX).count() as f64;
        let lidar_only = |d: &[u16]| {
            d.iter()
                .map(|&v| if v == u16::MAX { 0 } else { v })
                .collect::<Vec<u16>>()
        };
        worst_depth = worst_depth.max(
            frac_differing(&lidar_only(&da), &lidar_only(&db), 1.0) * da.len() as f64 / filled,
        );
        let na: Vec<u8> = read_rgb(&a.join(fa.normal_file_path.as_ref().unwrap()))
            .unwrap()
            .2
            .concat();
        let nb: Vec<u8> = read_rgb(&b.join(fb.normal_file_path.as_ref().unwrap()))
            .unwrap()
            .2
            .concat();
        worst_normal = worst_normal.max(frac_differing(&na, &nb, 8.0) * da.len() as f64 / filled);
        let sa = read_gray8(&a.join(fa.sky_mask_path.as_ref().unwrap()))
            .unwrap()
            .2;
        let sb = read_gray8(&b.join(fb.sky_mask_path.as_ref().unwrap()))
            .unwrap()
            .2;
        worst_sky = worst_sky.max(frac_differing(&sa, &sb, 0.0));
    }
    println!("differing: depth {worst_depth:.2e} of lidar pixels, normals {worst_normal:.2e}, sky {worst_sky:.2e}");
    // Depth is the same sweep projected the same way (f32 PCD coordinates); normals and sky masks may move
    // where a deskewed point's azimuth rounds to the neighbouring column of the range image.
    assert!(worst_depth <= 2e-3, "depth differs on {worst_depth:.2e}");
    assert!(worst_normal <= 0.05, "normals differ on {worst_normal:.2e}");
    assert!(worst_sky <= 0.01, "sky differs on {worst_sky:.2e}");
}

/// Copies a bag message by message through `edit` (topic, type, payload) → `None` drops the message,
/// `Some(bytes)` writes those bytes; used to break one thing at a time.
fn edit_bag(src: &Path, dst: &Path, edit: impl Fn(&str, &str, &[u8]) -> Option<Vec<u8>>) {
    edit_bag_typed(src, dst, |t, ty, d| {
        edit(t, ty, d).map(|b| (ty.to_string(), b))
    });
}

/// [`edit_bag`] that may also change a message's type (the channel takes the first type written).
fn edit_bag_typed(
    src: &Path,
    dst: &Path,
    edit: impl Fn(&str, &str, &[u8]) -> Option<(String, Vec<u8>)>,
) {
    let mut w = silvr_core::ingest::writer::BagWriter::create(dst).unwrap();
    for m in BagReader::open(src).unwrap() {
        let m = m.unwrap();
        if let Some((ty, bytes)) = edit(m.topic(), m.schema_name(), m.data()) {
            let t = silvr_core::ingest::writer::ros_time(m.log_time() as f64 * 1e-9);
            w.write(m.topic(), &ty, t, &bytes).unwrap();
        }
    }
    w.finish().unwrap();
}

#[test]
fn ingest_error_paths_name_the_problem() {
    let Some(gpu) = common::gpu() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let preset = synth_with_bag(dir, &gpu);
    let bag = dir.join("scene.mcap");
    let cfg = rig_config(&preset);
    let run = |bag: &Path, cfg: &RigConfig, out: &str| {
        let r = pollster::block_on(ingest_bag(
            bag,
            cfg,
            dir,
            &dir.join(out),
            false,
            &gpu,
            &mut |_| {},
        ));
        assert!(
            r.is_ok() || !dir.join(out).exists(),
            "{out}: a failed ingest left a dataset"
        );
        r
    };
    // No trajectory at all: lidar odometry stands in, and the summary says so (issue 34).
    let b = dir.join("no_odom.mcap");
    edit_bag(&bag, &b, |t, _, d| (t != "/odometry").then(|| d.to_vec()));
    let s = run(&b, &cfg, "e1").unwrap();
    assert_eq!(s.trajectory, "lidar odometry (/hesai/pandar)");
    assert!(
        s.notices[0].contains("no trajectory in the bag (0 pose(s) on '/odometry')"),
        "{:?}",
        s.notices
    );
    assert!(s.keyframes > 0);
    // Clouds as many drivers and converters publish them (issue 33): without a ring field, without
    // per-point time, or neither. Each ingests, says what it assumed, and drops nothing silently.
    let strip = |d: &[u8], drop_ring: bool, drop_time: bool| {
        let pc = PointCloud2::decode(d).unwrap();
        let fields = pc
            .fields
            .iter()
            .filter(|f| !((drop_ring && f.name == "ring") || (drop_time && f.name == "timestamp")))
            .cloned()
            .collect();
        PointCloud2 {
            fields,
            ..pc.clone()
        }
        .encode()
    };
    let reference = run(&bag, &cfg, "e0").unwrap();
    let depth_of = |out: &str| -> Vec<Vec<u16>> {
        let t = Transforms::read(&dir.join(out).join("transforms.json")).unwrap();
        t.frames
            .iter()
            .map(|f| {
                read_png16(&dir.join(out).join(f.depth_file_path.as_ref().unwrap()))
                    .unwrap()
                    .2
            })
            .collect()
    };
    let ref_depth = depth_of("e0");
    // The rig file's azimuth timing: the synthetic lidar turns counter-clockwise from +x at its stamp,
    // once per sweep duration (its bag keeps one sweep in five, so the interval between stamps is not it).
    let mut by_azimuth = cfg.clone();
    by_azimuth.ingest.azimuth_timing = Some(silvr_core::ingest::config::AzimuthTiming {
        spin: silvr_core::ingest::config::Spin::Ccw,
        start_azimuth_deg: 0.0,
        period: Some(preset.lidar.sweep_duration()),
    });
    let mut differing = std::collections::BTreeMap::new();
    for (name, drop_ring, drop_time, cfg) in [
        ("no_ring", true, false, &cfg),
        ("no_time", false, true, &cfg),
        ("neither", true, true, &cfg),
        ("azimuth", false, true, &by_azimuth),
    ] {
        let b = dir.join(format!("{name}.mcap"));
        edit_bag(&bag, &b, |t, _, d| {
            Some(if t == "/hesai/pandar" {
                strip(d, drop_ring, drop_time)
            } else {
                d.to_vec()
            })
        });
        let s = run(&b, cfg, name).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(s.keyframes, reference.keyframes, "{name}");
        assert!(s.dropped.is_empty(), "{name}: {:?}", s.dropped);
        let said = |what: &str| s.notices.iter().any(|n| n.contains(what));
        assert_eq!(
            said("no 'ring' field"),
            drop_ring,
            "{name}: {:?}",
            s.notices
        );
        assert_eq!(
            said("no per-point time"),
            drop_time,
            "{name}: {:?}",
            s.notices
        );
        let manifest = std::fs::read_to_string(dir.join(name).join("manifest.json")).unwrap();
        assert_eq!(
            manifest.contains("no per-point time"),
            drop_time,
            "{name}: the manifest records it"
        );
        assert_eq!(
            said("timed from its azimuth"),
            name == "azimuth",
            "{name}: {:?}",
            s.notices
        );
        let depth = depth_of(name);
        let worst = ref_depth
            .iter()
            .zip(&depth)
            .map(|(a, b)| frac_differing(a, b, 1.0))
            .fold(0.0, f64::max);
        differing.insert(name, worst);
        for (k, (a, b)) in ref_depth.iter().zip(&depth).enumerate() {
            let filled = |d: &[u16]| d.iter().filter(|&&v| v > 0 && v < u16::MAX).count();
            assert!(
                filled(b) > 300,
                "{name} frame {k}: {} lidar pixels",
                filled(b)
            );
            if !drop_time || name == "azimuth" {
                // The ring only shapes normals and sky: the depth is the same projection. Timed from
                // the azimuth, each point gets its own firing time back (to within a column's).
                assert!(frac_differing(a, b, 1.0) < 1e-3, "{name} frame {k}");
            }
        }
    }
    eprintln!("depth pixels differing from the timed clouds' (worst frame): {differing:?}");
    // Untimed and taken as compensated, the sweep's motion stays in the points: the depth moves.
    assert!(
        differing["no_time"] > 10.0 * differing["azimuth"].max(1e-4),
        "{differing:?}"
    );
    // A corrupt message on a topic we need is dropped and counted; the rest still ingests.
    let b = dir.join("one_bad.mcap");
    let first = std::sync::atomic::AtomicBool::new(true);
    edit_bag(&bag, &b, |t, _, d| {
        Some(
            if t == "/hesai/pandar" && first.swap(false, std::sync::atomic::Ordering::SeqCst) {
                d[..d.len() / 2].to_vec()
            } else {
                d.to_vec()
            },
        )
    });
    let s = run(&b, &cfg, "e4").unwrap();
    assert_eq!(s.keyframes, 3, "{:?}", s.dropped);
    assert!(
        s.dropped.keys().any(|k| k.contains("undecodable")),
        "{:?}",
        s.dropped
    );
    assert!(
        s.dropped.keys().any(|k| k.contains("no sweep covers")),
        "{:?}",
        s.dropped
    );
    // Images whose size disagrees with the calibration.
    let mut small = cfg.clone();
    small.sensor.cameras[1].image_width = Some(300);
    small.sensor.cameras[1].intrinsics = Some(vec![150.0, 150.0, 150.0, 135.0]);
    let e = run(&bag, &small, "e5").unwrap_err().to_string();
    assert!(
        e.contains("cam_left") && e.contains("360x270") && e.contains("300x270"),
        "{e}"
    );
    // The trajectory from /tf (odom → base_link) instead of /odometry gives the same dataset poses.
    let b = dir.join("tf_traj.mcap");
    edit_bag_typed(&bag, &b, |t, ty, d| {
        if t != "/odometry" {
            return Some((ty.to_string(), d.to_vec()));
        }
        let o = Odometry::decode(d).unwrap();
        let tf = TfMessage {
            transforms: vec![TransformStamped {
                header: o.header.clone(),
                child_frame_id: o.child_frame_id.clone(),
                transform: o.pose,
            }],
        };
        Some((TfMessage::MSG.to_string(), tf.encode()))
    });
    // The TF messages keep the topic name "/odometry", now typed TFMessage.
    let mut via_tf = cfg.clone();
    via_tf.ingest.trajectory_topic = Some("/odometry".into());
    let s = run(&b, &via_tf, "e7").unwrap();
    assert_eq!(s.keyframes, 4);
    let pa = silvr_core::dataset::read_tum(&dir.join("synth/poses/lidar_tum.txt")).unwrap();
    let pb = silvr_core::dataset::read_tum(&dir.join("e7/poses/lidar_tum.txt")).unwrap();
    for (qa, qb) in pa.poses().iter().zip(pb.poses()) {
        assert!(qa.distance_to(qb) < 1e-6, "{qa:?} vs {qb:?}");
    }
    // Only one camera's images in the window: nothing synchronised.
    let b = dir.join("one_cam.mcap");
    edit_bag(&bag, &b, |t, _, d| {
        (!t.contains("cam1/debayered/image")).then(|| d.to_vec())
    });
    let e = run(&b, &cfg, "e6").unwrap_err().to_string();
    assert!(e.contains("cam_left") && e.contains("no images"), "{e}");
}
