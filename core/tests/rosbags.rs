//! ROS 1 bags and rosbag2 `.db3` bags through `silvr ingest`'s reader, checked against the Python
//! `rosbags` package (the tool robotics people convert bags with; installed by `scripts/setup.sh` into the
//! test virtual environment, found through `SILVR_PYTHON`): the shared third-party bags list the same
//! topics, types and counts, and the synthetic world written by `rosbags` as a ROS 1 bag and as a `.db3`
//! ingests to the same dataset as its MCAP. Damaged ROS 1 bags (no index, cut short, corrupt chunk) are
//! read or refused as the reader promises.

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use silvr_core::ingest::bag::{summarize, BagError, BagFormat, BagReader, Skip};
use silvr_core::ingest::config::RigConfig;
use silvr_core::ingest::ros::RosMessage;
use silvr_core::ingest::rosbag::ingest_bag;
use silvr_core::synthetic::bag::{rig_config, BagRecorder};
use silvr_core::synthetic::{generate, Preset};

fn formats_dir(rel: &str) -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/formats")
        .join(rel);
    if p.exists() {
        return Some(p);
    }
    common::skip("SILVR_REQUIRE_DATA", &format!("{} is absent", p.display()));
    None
}

/// The Python with `rosbags` (scripts/setup.sh's virtual environment), or a skip.
fn rosbags_python() -> Option<PathBuf> {
    common::peer_python("rosbags, mcap")
}

fn peer(py: &Path, args: &[&str]) -> serde_json::Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/rosbags_peer.py");
    let mut all = vec![script.as_os_str()];
    all.extend(args.iter().map(std::ffi::OsStr::new));
    common::python_json(py, &all)
}

/// topic → (type, messages) as `silvr ingest --info` reports it.
fn ours(path: &Path) -> BTreeMap<String, (String, u64)> {
    let s = summarize(path).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(
        s.decode_errors,
        0,
        "{}: {:?}",
        path.display(),
        s.first_errors
    );
    s.topics
        .into_iter()
        .map(|(k, t)| (k, (t.schema_name, t.messages)))
        .collect()
}

#[test]
fn shared_ros1_and_db3_bags_list_what_rosbags_lists() {
    let (Some(r1), Some(r2)) = (formats_dir("rosbag1"), formats_dir("rosbag2_sqlite3")) else {
        return;
    };
    let Some(py) = rosbags_python() else { return };
    let mut bags: Vec<PathBuf> = std::fs::read_dir(&r1)
        .unwrap()
        .chain(std::fs::read_dir(&r2).unwrap())
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_dir() || p.extension().is_some_and(|e| e == "bag"))
        .collect();
    bags.sort();
    assert!(bags.len() >= 10, "{bags:?}");
    let mut compared = 0;
    for bag in &bags {
        let name = bag.file_name().unwrap().to_string_lossy().to_string();
        let mine = ours(bag);
        if name.contains("empty-message-definition") {
            // rosbags refuses it (its definition's hash does not match); we read it and say why its
            // messages are not decoded.
            assert_eq!(
                mine["/led_array_status"],
                ("led_array_msgs/msg/Status".into(), 14)
            );
            let s = summarize(bag).unwrap();
            assert_eq!(s.skipped[&Skip::NoSchema.to_string()], 14);
            continue;
        }
        let theirs = peer(&py, &["summary", bag.to_str().unwrap()]);
        let theirs: BTreeMap<String, (String, u64)> = theirs["topics"]
            .as_object()
            .unwrap()
            .iter()
            .map(|(k, v)| {
                (
                    k.clone(),
                    (
                        v["type"].as_str().unwrap().to_string(),
                        v["messages"].as_u64().unwrap(),
                    ),
                )
            })
            .collect();
        assert_eq!(mine, theirs, "{name}");
        compared += 1;
    }
    assert!(compared >= 9, "compared {compared}");
    // The known types decode in every container and compression.
    for (f, topic, n) in [
        ("rosbag1/embag_test.bag", "/luminar_pointcloud", 5),
        ("rosbag1/embag_test.bag", "/base_pose_ground_truth", 5),
        ("rosbag1/ros_numpy_test.bag", "/image", 1),
        ("rosbag1/ros_numpy_test.bag", "/pointcloud", 1),
        ("rosbag1/rosbagjs_example-bz2.bag", "/tf", 2688),
        (
            "rosbag2_sqlite3/rosbags-rs_test_bag_sqlite3",
            "/test/sensor_msgs/point_cloud2",
            2,
        ),
        (
            "rosbag2_sqlite3/rosbags-rs_test_bag_sqlite3",
            "/test/sensor_msgs/camera_info",
            2,
        ),
    ] {
        let s = summarize(&r1.join("..").join(f)).unwrap();
        assert_eq!(s.topics[topic].decoded, n, "{f} {topic}");
    }
}

/// (topic, log time, payload) of every message, in file order.
fn stream(path: &Path) -> Result<Vec<(String, u64, Vec<u8>)>, BagError> {
    BagReader::open(path)?
        .map(|m| m.map(|m| (m.topic().to_string(), m.log_time(), m.data().to_vec())))
        .collect()
}

#[test]
fn ros1_compressions_read_alike_and_real_clouds_decode() {
    let Some(r1) = formats_dir("rosbag1") else {
        return;
    };
    let plain = stream(&r1.join("rosbagjs_example.bag")).unwrap();
    assert_eq!(plain.len(), 8647);
    for v in ["rosbagjs_example-bz2.bag", "rosbagjs_example-lz4.bag"] {
        let mut other = stream(&r1.join(v)).unwrap();
        let mut a = plain.clone();
        // Chunking differs between the copies, so file order may too: compare as sorted multisets.
        a.sort();
        other.sort();
        assert!(a == other, "{v} differs from the uncompressed copy");
    }
    // A real lidar's clouds (lz4 chunks): every point of every sweep, with its per-point time.
    let mut sweeps = 0;
    for m in BagReader::open(&r1.join("embag_test.bag")).unwrap() {
        let m = m.unwrap();
        if let Ok(Ok(RosMessage::PointCloud2(pc))) = m.decode() {
            assert!(
                pc.width > 30_000 && pc.point_step == 32,
                "{} {}",
                pc.width,
                pc.point_step
            );
            assert_eq!(pc.header.frame_id, "luminar_lidar");
            assert_eq!(pc.data.len(), (pc.width * pc.height * 32) as usize);
            let scan = pc.to_scan().unwrap();
            assert_eq!(scan.positions.len(), pc.width as usize);
            sweeps += 1;
        }
    }
    assert_eq!(sweeps, 5);
    assert_eq!(
        summarize(&r1.join("rosbagjs_example-unsorted-chunks.bag"))
            .unwrap()
            .format,
        Some(BagFormat::Ros1)
    );
}

/// The error reading `path` gives (panics, without printing the messages, when it reads).
fn stream_err(path: &Path) -> String {
    match stream(path) {
        Ok(m) => panic!(
            "{} read ({} messages) where an error was expected",
            path.display(),
            m.len()
        ),
        Err(e) => e.to_string(),
    }
}

/// Offset of the 8-byte value of `name=` in the bag header (the first record after the magic).
fn header_field(bytes: &[u8], name: &str) -> usize {
    let key = format!("{name}=");
    let at = bytes[13..4096.min(bytes.len())]
        .windows(key.len())
        .position(|w| w == key.as_bytes())
        .unwrap();
    13 + at + key.len()
}

#[test]
fn unindexed_cut_short_and_corrupt_ros1_bags() {
    let Some(r1) = formats_dir("rosbag1") else {
        return;
    };
    let src = std::fs::read(r1.join("embag_test.bag")).unwrap();
    let full = stream(&r1.join("embag_test.bag")).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let write = |name: &str, b: &[u8]| {
        let p = tmp.path().join(name);
        std::fs::write(&p, b).unwrap();
        p
    };
    let ip = header_field(&src, "index_pos");
    let index_pos = u64::from_le_bytes(src[ip..ip + 8].try_into().unwrap()) as usize;

    // As a crashed recorder leaves it: index position 0 and no index. Every message, and a note.
    let mut unindexed = src[..index_pos].to_vec();
    unindexed[ip..ip + 8].copy_from_slice(&0u64.to_le_bytes());
    let p = write("unindexed.bag", &unindexed);
    assert_eq!(stream(&p).unwrap(), full);
    let s = summarize(&p).unwrap();
    assert!(
        s.notes.iter().any(|n| n.contains("no index")),
        "{:?}",
        s.notes
    );

    // Cut inside its last chunk: the messages of the complete chunks, and a note saying where it ends.
    let cut = write("cut.bag", &unindexed[..index_pos - 1000]);
    let got = stream(&cut).unwrap();
    assert!(
        !got.is_empty() && got.len() < full.len(),
        "{} of {}",
        got.len(),
        full.len()
    );
    assert_eq!(got[..], full[..got.len()]);
    let s = summarize(&cut).unwrap();
    assert!(
        s.notes.iter().any(|n| n.contains("cut short")),
        "{:?}",
        s.notes
    );

    // The same cut where the header still names an index (now beyond the end): read by scanning, with
    // both facts noted.
    let p = write("claims-index.bag", &src[..index_pos - 1000]);
    assert_eq!(stream(&p).unwrap(), got);
    let s = summarize(&p).unwrap();
    assert!(
        s.notes.iter().any(|n| n.contains("outside the file")),
        "{:?}",
        s.notes
    );
    assert!(
        s.notes.iter().any(|n| n.contains("cut short")),
        "{:?}",
        s.notes
    );

    // A corrupt lz4 chunk: an error naming the chunk's offset, never a panic or a wrong message.
    let mut corrupt = src.clone();
    let chunk = corrupt
        .windows(15)
        .position(|w| w == b"compression=lz4")
        .unwrap();
    for b in &mut corrupt[chunk + 200..chunk + 400] {
        *b ^= 0x5a;
    }
    let p = write("corrupt.bag", &corrupt);
    let e = stream_err(&p);
    assert!(e.contains("corrupt.bag") && e.contains("lz4"), "{e}");

    // An absurd record length is refused before allocating.
    let mut absurd = src.clone();
    let first_record = 13
        + 4
        + u32::from_le_bytes(src[13..17].try_into().unwrap()) as usize
        + 4
        + u32::from_le_bytes(
            src[17 + u32::from_le_bytes(src[13..17].try_into().unwrap()) as usize..][..4]
                .try_into()
                .unwrap(),
        ) as usize;
    absurd[first_record..first_record + 4].copy_from_slice(&u32::MAX.to_le_bytes());
    let p = write("absurd.bag", &absurd);
    let e = stream_err(&p);
    assert!(e.contains("absurd.bag") && e.contains("bytes"), "{e}");
    // Not a bag at all, and a ROS 1 bag of the old format.
    let e = summarize(&write("text.bag", b"hello"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("not a bag"), "{e}");
    let e = summarize(&write("old.bag", b"#ROSBAG V1.2\nxxxx"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("1.2") && e.contains("not supported"), "{e}");
}

/// Every file under `root` (relative path → bytes).
fn tree(root: &Path) -> BTreeMap<String, Vec<u8>> {
    fn walk(root: &Path, dir: &Path, out: &mut BTreeMap<String, Vec<u8>>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                let rel = p.strip_prefix(root).unwrap().to_string_lossy().to_string();
                out.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(root, root, &mut out);
    out
}

#[test]
fn synthetic_world_as_ros1_and_db3_ingests_like_its_mcap() {
    let Some(py) = rosbags_python() else { return };
    let Some(gpu) = common::gpu() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let mut preset = Preset::ci(5);
    preset.keyframes = 4;
    let mcap = dir.join("scene.mcap");
    let mut rec = BagRecorder::create(&mcap).unwrap();
    pollster::block_on(generate::generate_recording(
        &preset,
        &gpu,
        &dir.join("synth"),
        false,
        &mut |_| {},
        Some(&mut rec),
    ))
    .unwrap();
    let ros1 = dir.join("scene.bag");
    let db3 = dir.join("scene_db3");
    let convert = |ros1: &Path, db3: &Path, extra: &[&str]| {
        let mut args = vec![
            "convert",
            mcap.to_str().unwrap(),
            "--ros1",
            ros1.to_str().unwrap(),
            "--db3",
            db3.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        peer(&py, &args)
    };
    let conv = convert(&ros1, &db3, &[]);
    println!("rosbags wrote {conv}");
    // The .db3 compressed as rosbag2 does it: the whole file, or each message, with zstd.
    let (db3_file, db3_msg) = (dir.join("zstd_file"), dir.join("zstd_message"));
    convert(&dir.join("f.bag"), &db3_file, &["--zstd", "file"]);
    convert(&dir.join("m.bag"), &db3_msg, &["--zstd", "message"]);
    let cfg = RigConfig::parse(&rig_config(&preset).to_yaml(), "scene.rig.yaml").unwrap();
    let ingest = |bag: &Path, out: &str| {
        let s = pollster::block_on(ingest_bag(
            bag,
            &cfg,
            dir,
            &dir.join(out),
            false,
            &gpu,
            &mut |_| {},
        ))
        .unwrap_or_else(|e| panic!("{}: {e}", bag.display()));
        assert_eq!(s.keyframes, 4, "{}", bag.display());
        assert!(s.dropped.is_empty(), "{:?}", s.dropped);
        tree(&dir.join(out))
    };
    let reference = ingest(&mcap, "from_mcap");
    assert!(reference.len() > 20, "{:?}", reference.keys());
    for (bag, out) in [
        (&ros1, "from_ros1"),
        (&db3, "from_db3"),
        (&db3_file, "from_db3_zstd_file"),
        (&db3_msg, "from_db3_zstd_message"),
    ] {
        assert_eq!(
            summarize(bag).unwrap().messages,
            conv["messages"].as_u64().unwrap()
        );
        let got = ingest(bag, out);
        assert_eq!(
            got.keys().collect::<Vec<_>>(),
            reference.keys().collect::<Vec<_>>(),
            "{out}"
        );
        for (name, bytes) in &reference {
            // The manifest records where the data came from; every image, depth, normal, sky mask,
            // cloud and pose is bit-equal.
            if name.ends_with("manifest.json") {
                continue;
            }
            assert!(got[name] == *bytes, "{out}: {name} differs from the MCAP's");
        }
    }
}
