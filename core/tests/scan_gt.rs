//! Scanner ground truth (`silvr eval --gt scan.e57|.laz|.las|.ply`): the same points as a dataset's
//! `gt/cloud.ply` give the same scores to 1e-6 m in every format — E57 with two scans each placed by its
//! own pose, LAS and LAZ (quantised at 1e-7 m) — and through `--gt-transform`; the shared third-party E57
//! and LAS/LAZ files read.

mod common;

use std::path::{Path, PathBuf};

use glam::{DMat4, DQuat, DVec3};
use silvr_core::eval::options::GeometryOptions;
use silvr_core::eval::scan::{read_scan, ScanFormat};
use silvr_core::eval::GroundTruth;
use silvr_core::pointcloud::{write_ply, PointCloud};

/// A floor and a wall, 5 cm apart, coloured by position; off the 1 cm voxel grid's planes (a point on a
/// voxel border may land in either voxel once a format quantises it, as a real scan's never sit there).
fn scene() -> PointCloud {
    let mut pos = Vec::new();
    let o = DVec3::new(0.003_137, 0.002_718, 0.001_414);
    for i in 0..160 {
        for j in 0..160 {
            pos.push(o + DVec3::new(i as f64 * 0.05, j as f64 * 0.05, 0.0));
        }
        for k in 0..50 {
            pos.push(o + DVec3::new(8.0, i as f64 * 0.05, k as f64 * 0.05));
        }
    }
    let mut c = PointCloud::from_positions(pos.clone());
    c.colors = Some(
        pos.iter()
            .map(|p| [(p.x * 30.0) as u8, (p.y * 30.0) as u8, (p.z * 80.0) as u8])
            .collect(),
    );
    c
}

/// Every third GT point moved by a deterministic few centimetres, and some floating outliers.
fn reconstruction(gt: &PointCloud) -> PointCloud {
    let mut pos: Vec<DVec3> = gt
        .positions
        .iter()
        .enumerate()
        .filter(|(i, _)| i % 3 == 0)
        // Never on a face of the GT's box, where the crop would hinge on the 1e-7 m of a format's
        // quantisation.
        .map(|(i, p)| *p + DVec3::new(-7e-4, -7e-4, ((i * 7919) % 41) as f64 * 0.001 - 0.0205))
        .collect();
    pos.extend((0..200).map(|i| DVec3::new(i as f64 * 0.04, 3.0, 1.0 + (i % 7) as f64 * 0.1)));
    PointCloud::from_positions(pos)
}

fn write_las(path: &Path, cloud: &PointCloud, to_file: DMat4) {
    let mut b = las::Builder::from((1, 4));
    b.point_format = las::point::Format::new(2).unwrap();
    b.point_format.is_compressed = path.extension().is_some_and(|e| e == "laz");
    b.transforms = las::Vector {
        x: las::Transform {
            scale: 1e-7,
            offset: 0.0,
        },
        y: las::Transform {
            scale: 1e-7,
            offset: 0.0,
        },
        z: las::Transform {
            scale: 1e-7,
            offset: 0.0,
        },
    };
    let mut w = las::Writer::from_path(path, b.into_header().unwrap()).unwrap();
    for (p, c) in cloud.positions.iter().zip(cloud.colors.as_ref().unwrap()) {
        let q = to_file.transform_point3(*p);
        w.write_point(las::Point {
            x: q.x,
            y: q.y,
            z: q.z,
            color: Some(las::Color::new(
                c[0] as u16 * 257,
                c[1] as u16 * 257,
                c[2] as u16 * 257,
            )),
            ..Default::default()
        })
        .unwrap();
    }
    w.close().unwrap();
}

/// Two scans, each stored in its own frame with its pose in the file, as a tripod scanner writes them.
fn write_e57(path: &Path, cloud: &PointCloud) {
    use e57::{Quaternion, Record, RecordValue, Transform, Translation};
    let mut w = e57::E57Writer::from_file(path, "silvr-test-file").unwrap();
    let n = cloud.len();
    let poses = [
        (DQuat::from_rotation_z(0.3), DVec3::new(1.0, -2.0, 0.5)),
        (
            DQuat::from_rotation_x(-0.2) * DQuat::from_rotation_z(2.0),
            DVec3::new(5.0, 4.0, 1.5),
        ),
    ];
    for (s, (q, t)) in poses.iter().enumerate() {
        let prototype = vec![
            Record::CARTESIAN_X_F64,
            Record::CARTESIAN_Y_F64,
            Record::CARTESIAN_Z_F64,
            Record::COLOR_RED_U8,
            Record::COLOR_GREEN_U8,
            Record::COLOR_BLUE_U8,
        ];
        let mut pc = w.add_pointcloud(&format!("scan-{s}"), prototype).unwrap();
        pc.set_transform(Some(Transform {
            rotation: Quaternion {
                w: q.w,
                x: q.x,
                y: q.y,
                z: q.z,
            },
            translation: Translation {
                x: t.x,
                y: t.y,
                z: t.z,
            },
        }));
        let to_local = DMat4::from_rotation_translation(*q, *t).inverse();
        let range = if s == 0 { 0..n / 2 } else { n / 2..n };
        for i in range {
            let p = to_local.transform_point3(cloud.positions[i]);
            let c = cloud.colors.as_ref().unwrap()[i];
            pc.add_point(vec![
                RecordValue::Double(p.x),
                RecordValue::Double(p.y),
                RecordValue::Double(p.z),
                RecordValue::Integer(c[0] as i64),
                RecordValue::Integer(c[1] as i64),
                RecordValue::Integer(c[2] as i64),
            ])
            .unwrap();
        }
        pc.finalize().unwrap();
    }
    w.finalize().unwrap();
}

/// The numbers of two reports agree to `tol` (paths and notes aside).
fn assert_same_scores(a: &serde_json::Value, b: &serde_json::Value, tol: f64, at: &str) {
    use serde_json::Value::*;
    match (a, b) {
        (Object(x), Object(y)) => {
            for (k, v) in x {
                if k == "notes" {
                    continue;
                }
                assert_same_scores(v, &y[k], tol, &format!("{at}.{k}"));
            }
        }
        (Array(x), Array(y)) => {
            assert_eq!(x.len(), y.len(), "{at}");
            for (i, (v, w)) in x.iter().zip(y).enumerate() {
                assert_same_scores(v, w, tol, &format!("{at}[{i}]"));
            }
        }
        (Number(x), Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            assert!((x - y).abs() <= tol, "{at}: {x} vs {y}");
        }
        _ => assert_eq!(a, b, "{at}"),
    }
}

#[test]
fn a_scan_in_any_format_scores_like_the_same_points_as_ply() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let gt = scene();
    let rec = reconstruction(&gt);
    std::fs::create_dir_all(dir.join("ds/gt")).unwrap();
    write_ply(&dir.join("ds/gt/cloud.ply"), &gt).unwrap();
    let options = GeometryOptions::default();
    let reference = GroundTruth::load(&dir.join("ds"))
        .unwrap()
        .evaluate(&rec, &options)
        .unwrap();
    let reference = serde_json::to_value(&reference.report).unwrap();
    assert!(
        reference["accuracy_m"].as_f64().unwrap() > 0.005,
        "{reference}"
    );

    // The scan somewhere else: 30° about z and 100 m away, brought back by --gt-transform.
    let t_map_scan = DMat4::from_rotation_translation(
        DQuat::from_rotation_z(0.5),
        DVec3::new(100.0, -50.0, 2.0),
    );
    let files: Vec<(PathBuf, ScanFormat, Option<DMat4>)> = vec![
        (dir.join("scan.ply"), ScanFormat::Ply, None),
        (dir.join("scan.las"), ScanFormat::Las, None),
        (dir.join("scan.laz"), ScanFormat::Las, None),
        (dir.join("moved.laz"), ScanFormat::Las, Some(t_map_scan)),
        (dir.join("scan.e57"), ScanFormat::E57, None),
    ];
    write_ply(&files[0].0, &gt).unwrap();
    write_las(&files[1].0, &gt, DMat4::IDENTITY);
    write_las(&files[2].0, &gt, DMat4::IDENTITY);
    write_las(&files[3].0, &gt, t_map_scan.inverse());
    write_e57(&files[4].0, &gt);
    for (path, format, transform) in &files {
        let scan = read_scan(path, *transform, None).unwrap();
        assert_eq!(scan.format, *format);
        assert_eq!(scan.cloud.len(), gt.len(), "{}", path.display());
        assert_eq!(scan.cloud.colors, gt.colors, "{}: colours", path.display());
        let worst = scan
            .cloud
            .positions
            .iter()
            .zip(&gt.positions)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max);
        assert!(
            worst < 1e-6,
            "{}: points moved by {worst} m",
            path.display()
        );
        // Read from memory (the fuzz target's way) it is the same scan.
        let bytes = std::fs::read(path).unwrap();
        let mem = silvr_core::eval::scan::read_scan_bytes(&bytes, path, *transform, None).unwrap();
        assert_eq!(
            mem.cloud.positions,
            scan.cloud.positions,
            "{}",
            path.display()
        );
        let (truth, notes) = GroundTruth::from_scan(path, *transform, &options).unwrap();
        let got = serde_json::to_value(&truth.evaluate(&rec, &options).unwrap().report).unwrap();
        assert_same_scores(&reference, &got, 1e-6, &path.display().to_string());
        if *format == ScanFormat::E57 {
            assert!(notes.iter().any(|n| n.contains("2 scan(s)")), "{notes:?}");
        }
    }
    // Without the transform, the moved scan scores as far away as it is.
    let (truth, _) = GroundTruth::from_scan(&files[3].0, None, &options).unwrap();
    if let Ok(off) = truth.evaluate(&rec, &options) {
        let r = off.report;
        assert!(
            r.counts.reconstruction_evaluated == 0 || r.accuracy_m > 1.0,
            "an unplaced scan must not score like the placed one: {}",
            r.summary()
        );
    }
    // Not a point cloud.
    std::fs::write(dir.join("x.e57"), b"hello").unwrap();
    let e = read_scan(&dir.join("x.e57"), None, None)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("x.e57") && e.contains("not a point cloud"),
        "{e}"
    );
}

#[test]
fn large_scans_are_voxelised_while_read_like_the_protocol_does() {
    // The streaming voxeliser gives the protocol's own down-sampling (centroids in first-seen order).
    let gt = scene();
    let tmp = tempfile::tempdir().unwrap();
    let p = tmp.path().join("scan.las");
    write_las(&p, &gt, DMat4::IDENTITY);
    let all = read_scan(&p, None, None)
        .unwrap()
        .cloud
        .voxel_downsample(0.1);
    // Force the streaming path by asking for it through the threshold's public knob: a voxel and a file
    // counted above MAX_EXACT_POINTS cannot be made small, so compare the two down-samplings directly.
    let streamed = silvr_core::eval::scan::voxelise_while_reading(&p, None, 0.1).unwrap();
    assert_eq!(all.len(), streamed.len());
    let worst = all
        .positions
        .iter()
        .zip(&streamed.positions)
        .map(|(a, b)| (*a - *b).length())
        .fold(0.0, f64::max);
    assert!(worst < 1e-9, "{worst}");
}

fn shared(rel: &str) -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/formats")
        .join(rel);
    if p.exists() {
        return Some(p);
    }
    common::skip("SILVR_REQUIRE_DATA", &format!("{} is absent", p.display()));
    None
}

#[test]
fn shared_e57_and_las_files_read() {
    let (Some(e57), Some(las)) = (shared("e57"), shared("las_copc")) else {
        return;
    };
    for dir in [e57, las] {
        for f in std::fs::read_dir(&dir).unwrap() {
            let p = f.unwrap().path();
            let name = p.file_name().unwrap().to_string_lossy().to_string();
            if !(name.ends_with(".e57") || name.ends_with(".las") || name.ends_with(".laz")) {
                continue;
            }
            let s = read_scan(&p, None, None).unwrap_or_else(|e| panic!("{e}"));
            println!(
                "{name}: {} points read, {} kept",
                s.points_read,
                s.cloud.len()
            );
            assert!(!s.cloud.is_empty(), "{name}");
        }
    }
}

/// The Python with pye57 and laspy (scripts/setup.sh's virtual environment), or a skip.
fn scan_python() -> Option<PathBuf> {
    common::peer_python("pye57, laspy, lazrs")
}

#[test]
fn shared_e57_and_las_files_read_as_pye57_and_laspy_read_them() {
    let (Some(e57), Some(las)) = (shared("e57"), shared("las_copc")) else {
        return;
    };
    let Some(py) = scan_python() else { return };
    let mut files: Vec<PathBuf> = std::fs::read_dir(&e57)
        .unwrap()
        .chain(std::fs::read_dir(&las).unwrap())
        .map(|f| f.unwrap().path())
        .filter(|p| {
            p.extension()
                .is_some_and(|e| e == "e57" || e == "las" || e == "laz")
        })
        .collect();
    files.sort();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/scan_peer.py");
    let mut args = vec![script.as_os_str()];
    args.extend(files.iter().map(|f| f.as_os_str()));
    let peer = common::python_json(&py, &args);
    for f in &files {
        let theirs = &peer[f.to_str().unwrap()];
        let ours = read_scan(f, None, None).unwrap_or_else(|e| panic!("{e}"));
        let name = f.file_name().unwrap().to_string_lossy();
        assert_eq!(
            ours.cloud.len() as u64,
            theirs["points"].as_u64().unwrap(),
            "{name}"
        );
        for (k, xyz) in theirs["xyz"].as_array().unwrap().iter().enumerate() {
            let p = ours.cloud.positions[k * 97];
            let q = DVec3::new(
                xyz[0].as_f64().unwrap(),
                xyz[1].as_f64().unwrap(),
                xyz[2].as_f64().unwrap(),
            );
            assert!(
                (p - q).length() <= 1e-6 * q.length().max(1.0),
                "{name} point {}: {p} vs {q}",
                k * 97
            );
        }
        if let Some(rgb) = theirs["rgb"].as_array() {
            let colours = ours
                .cloud
                .colors
                .as_ref()
                .unwrap_or_else(|| panic!("{name}: no colours"));
            for (k, c) in rgb.iter().enumerate() {
                let c: Vec<u8> = c
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|v| v.as_u64().unwrap() as u8)
                    .collect();
                assert_eq!(colours[k * 97].to_vec(), c, "{name} colour {}", k * 97);
            }
        }
    }
}

/// Our LAZ as laspy reads it: every scalar of the cloud is an extra dimension with its name, values equal
/// to the PLY's (float32), positions within half the 0.1 mm step, colours 8-bit × 257.
#[test]
fn laspy_reads_our_laz_with_every_extra_dimension() {
    let Some(py) = scan_python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let mut cloud = scene();
    let n = cloud.len();
    for (k, name) in [
        "log_std_colour",
        "log_std_depth",
        "log_std_combined",
        "submap",
        "error_m",
    ]
    .iter()
    .enumerate()
    {
        cloud.set_scalar(
            name,
            (0..n)
                .map(|i| ((i * (k + 3)) % 101) as f32 * 0.013 - 0.4)
                .collect(),
        );
    }
    let laz = tmp.path().join("map.laz");
    assert_eq!(silvr_core::lasfile::write_las(&laz, &cloud).unwrap(), n);
    let code = "import json, sys, laspy\n\
                f = laspy.read(sys.argv[1])\n\
                d = {n: [float(v) for v in f[n]] for n in f.point_format.extra_dimension_names}\n\
                d['xyz'] = [[float(a), float(b), float(c)] for a, b, c in zip(f.x, f.y, f.z)]\n\
                d['red'] = [int(v) for v in f.red]\n\
                d['version'] = str(f.header.version)\n\
                print(json.dumps(d))";
    let d = common::python_json(&py, &["-c".as_ref(), code.as_ref(), laz.as_os_str()]);
    assert_eq!(d["version"], "1.4");
    for (name, values) in &cloud.scalars {
        let got = d[name]
            .as_array()
            .unwrap_or_else(|| panic!("laspy has no dimension {name}"));
        assert_eq!(got.len(), n);
        for (a, b) in values.iter().zip(got) {
            assert_eq!(*a, b.as_f64().unwrap() as f32, "{name}");
        }
    }
    for (i, xyz) in d["xyz"].as_array().unwrap().iter().enumerate() {
        let q = DVec3::new(
            xyz[0].as_f64().unwrap(),
            xyz[1].as_f64().unwrap(),
            xyz[2].as_f64().unwrap(),
        );
        assert!(
            (q - cloud.positions[i]).abs().max_element() <= 0.5e-4 + 1e-9,
            "point {i}"
        );
    }
    let reds: Vec<u64> = d["red"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap())
        .collect();
    assert!(reds
        .iter()
        .zip(cloud.colors.as_ref().unwrap())
        .all(|(r, c)| *r == c[0] as u64 * 257));
}

/// A peer's LAS/LAZ with extra bytes of every layout (arrays, an undefined block, then scalars): the chunked
/// reader behind `silvr export copc X.laz` locates each scalar past the others and reads the values laspy
/// reads; a peer's COPC reads whole.
#[test]
fn shared_extra_bytes_read_as_laspy_reads_them() {
    let Some(dir) = shared("las_copc") else {
        return;
    };
    let Some(py) = scan_python() else { return };
    for name in ["extrabytes.las", "extra.laz", "simple.copc.laz"] {
        let path = dir.join(name);
        let mut all = PointCloud::new();
        let mut chunks = 0;
        let names = silvr_core::eval::scan::read_las_chunks(&path, 400, &mut |c| {
            chunks += 1;
            all.positions.extend(&c.positions);
            for (n, v) in &c.scalars {
                match all.scalars.iter_mut().find(|(m, _)| m == n) {
                    Some((_, w)) => w.extend(v),
                    None => all.scalars.push((n.clone(), v.clone())),
                }
            }
            Ok(())
        })
        .unwrap();
        assert_eq!(chunks, all.len().div_ceil(400), "{name}");
        let code = "import json, sys, laspy\n\
                    f = laspy.read(sys.argv[1])\n\
                    d = {e.name: [float(v) for v in f[e.name]] for e in f.point_format.extra_dimensions \
                         if e.num_elements == 1}\n\
                    d['n'] = len(f.points)\n\
                    print(json.dumps(d))";
        let d = common::python_json(&py, &["-c".as_ref(), code.as_ref(), path.as_os_str()]);
        assert_eq!(all.len() as u64, d["n"].as_u64().unwrap(), "{name}");
        let theirs: Vec<&String> = d
            .as_object()
            .unwrap()
            .keys()
            .filter(|k| *k != "n")
            .collect();
        assert_eq!(names.len(), theirs.len(), "{name}: {names:?} vs {theirs:?}");
        for n in &names {
            let want = d[n.as_str()].as_array().unwrap();
            let got = all.scalar(n).unwrap();
            for (a, b) in got.iter().zip(want) {
                assert_eq!(*a, b.as_f64().unwrap() as f32, "{name} {n}");
            }
        }
    }
}

/// Our COPC as laspy's COPC reader reads it (by its octree, as a streaming viewer does): every point, every
/// scalar an extra dimension equal to ours (float32), positions within half the 0.1 mm step, colours
/// 8-bit × 257; the octree has levels below the root holding points, and our summary VLR is there for
/// others to read, its kept count equal to the native filter's.
#[test]
fn laspy_reads_our_copc_with_every_extra_dimension() {
    use silvr_core::copc::write::{write_copc, CopcInput, CopcOptions};
    let Some(py) = scan_python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let mut cloud = scene();
    let n = cloud.len();
    let names = [
        "log_std_colour",
        "log_std_depth",
        "log_std_combined",
        "submap",
        "error_m",
    ];
    for (k, name) in names.iter().enumerate() {
        cloud.set_scalar(
            name,
            (0..n)
                .map(|i| ((i * (k + 3)) % 101) as f32 * 0.013 - 0.4 + (i % 7919) as f32 * 1e-4)
                .collect(),
        );
    }
    let path = tmp.path().join("map.copc.laz");
    let w = write_copc(
        CopcInput::Cloud(&cloud),
        &path,
        &CopcOptions {
            points_per_node: 4000,
        },
    )
    .unwrap();
    assert_eq!(w.points as usize, n);
    let code = "import json, sys, laspy\n\
                r = laspy.CopcReader.open(sys.argv[1])\n\
                f = r.query()\n\
                d = {n: [float(v) for v in f[n]] for n in f.point_format.extra_dimension_names}\n\
                d['xyz'] = [[float(a), float(b), float(c)] for a, b, c in zip(f.x, f.y, f.z)]\n\
                d['red'] = [int(v) for v in f.red]\n\
                d['root'] = len(r.level_query(0))\n\
                d['level1'] = len(r.level_query(1))\n\
                s = [v for v in r.header.vlrs if v.user_id == 'SiLVR' and v.record_id == 1]\n\
                d['summary'] = json.loads(bytes(s[0].record_data)) if s else None\n\
                print(json.dumps(d))";
    let d = common::python_json(&py, &["-c".as_ref(), code.as_ref(), path.as_os_str()]);
    // The octree's order is not ours: match laspy's points to ours by position.
    let key = |p: DVec3| {
        (
            (p.x * 1e4).round() as i64,
            (p.y * 1e4).round() as i64,
            (p.z * 1e4).round() as i64,
        )
    };
    let index: std::collections::HashMap<_, usize> = cloud
        .positions
        .iter()
        .enumerate()
        .map(|(i, p)| (key(*p), i))
        .collect();
    let xyz = d["xyz"].as_array().unwrap();
    assert_eq!(xyz.len(), n, "laspy reads every point");
    let mut seen = vec![false; n];
    for (j, q) in xyz.iter().enumerate() {
        let q = DVec3::new(
            q[0].as_f64().unwrap(),
            q[1].as_f64().unwrap(),
            q[2].as_f64().unwrap(),
        );
        let i = *index
            .get(&key(q))
            .unwrap_or_else(|| panic!("laspy point {j} is not ours: {q}"));
        assert!(!seen[i]);
        seen[i] = true;
        assert!((q - cloud.positions[i]).abs().max_element() <= 0.5e-4 + 1e-9);
        for name in names {
            let got = d[name][j]
                .as_f64()
                .unwrap_or_else(|| panic!("laspy has no {name}"));
            assert_eq!(
                got as f32,
                cloud.scalar(name).unwrap()[i],
                "{name} of point {i}"
            );
        }
        assert_eq!(
            d["red"][j].as_u64().unwrap(),
            cloud.colors.as_ref().unwrap()[i][0] as u64 * 257
        );
    }
    let (root, level1) = (d["root"].as_u64().unwrap(), d["level1"].as_u64().unwrap());
    assert!(
        root > 0 && level1 > 0 && (root as usize) < n,
        "an octree: root {root}, level 1 {level1}"
    );
    let s = &d["summary"];
    let v = cloud.scalar("log_std_combined").unwrap();
    let t = silvr_core::uncertainty::filter::default_threshold(v);
    assert_eq!(s["points"].as_u64().unwrap() as usize, n);
    assert_eq!(
        s["filter"]["kept"].as_u64().unwrap() as usize,
        v.iter().filter(|&&x| x <= t).count()
    );
}

/// A LAZ whose chunk table claims more chunks than its bytes can hold is refused before the `laz` crate
/// reserves the table (laz 0.13 reserved the stated count: an abort on 2^32, found by the fuzz target).
#[test]
fn a_laz_with_an_absurd_chunk_count_is_an_error_not_an_abort() {
    let tmp = tempfile::tempdir().unwrap();
    let p = tmp.path().join("x.laz");
    write_las(&p, &scene(), DMat4::IDENTITY);
    let mut b = std::fs::read(&p).unwrap();
    assert!(read_scan(&p, None, None).is_ok());
    let data = u32::from_le_bytes(b[96..100].try_into().unwrap()) as usize;
    let table = i64::from_le_bytes(b[data..data + 8].try_into().unwrap()) as usize;
    b[table + 4..table + 8].copy_from_slice(&u32::MAX.to_le_bytes());
    std::fs::write(&p, &b).unwrap();
    let e = read_scan(&p, None, None).err().unwrap().to_string();
    assert!(e.contains("x.laz") && e.contains("chunk table"), "{e}");
    let e = silvr_core::eval::scan::read_scan_bytes(&b, &p, None, None)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("chunk table"), "{e}");
}

/// A layered LAZ chunk (point formats 6+) whose layer sizes run past the file is refused before the `laz`
/// crate sizes its buffers from them (laz 0.13 resized to the stated size: a 1 KB file reserved 4 GB).
#[test]
fn a_laz_layer_larger_than_the_file_is_an_error_not_a_4gb_allocation() {
    let tmp = tempfile::tempdir().unwrap();
    let p = tmp.path().join("x.laz");
    // The product's own writer: LAS 1.4 point format 7, layered chunks.
    silvr_core::lasfile::write_las(&p, &scene()).unwrap();
    let mut b = std::fs::read(&p).unwrap();
    assert!(read_scan(&p, None, None).is_ok());
    // Our LAZ is point format 7: the first chunk holds the first point raw (one record), a point count,
    // then one u32 size per layer; the first is the x/y layer's.
    let data = u32::from_le_bytes(b[96..100].try_into().unwrap()) as usize;
    let record = u16::from_le_bytes(b[105..107].try_into().unwrap()) as usize;
    let xy = data + 8 + record + 4;
    b[xy..xy + 4].copy_from_slice(&0xFFFF_FF00u32.to_le_bytes());
    std::fs::write(&p, &b).unwrap();
    let e = read_scan(&p, None, None).err().unwrap().to_string();
    assert!(e.contains("x.laz") && e.contains("bytes of layers"), "{e}");
    // The fuzz target's find, a 1,108-byte file.
    let known = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../fuzz/seeds/scan_file/laz14-layer-size-4gb.laz"
    );
    let kb = std::fs::read(known).unwrap();
    let e = silvr_core::eval::scan::read_scan_bytes(&kb, Path::new(known), None, None)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("bytes of layers"), "{e}");
}

/// Corrupt LAZ files on which the las/laz readers themselves panic are errors naming the file, not crashes:
/// corrupt arithmetic-coded data (an index out of bounds in the decoder, laz-rs issue #43; the fuzz
/// target's fourth find) and a LASzip VLR listing no items (a panic while the reader is made; the fifth);
/// and an extended VLR stating ~8 EB, which the las crate reserved (an abort; the sixth). Three more whose
/// layer sizes laz 0.13 reserved (GBs): a 1.4 header stating 256 bytes, which hid its LASzip VLR from the
/// layer check; an item of the wrong size; one-point chunks read on past the chunk table; variable-size
/// chunks with a table of none (the first chunk is read all the same); a point-wise file, whose one chunk
/// starts without the table's offset.
#[test]
fn lazs_whose_readers_panic_are_errors_naming_the_file() {
    for (name, says) in [
        (
            "laz-decoder-panic",
            "corrupt LAS/LAZ data: the reader failed decoding after 0 points",
        ),
        ("laz-no-items", "lists no point items"),
        ("las-evlr-length-oom", "extended VLR 0"),
        ("laz-short-header-layer-oom", "bytes of layers"),
        ("laz-item-size-oom", "RGB14 item is 518 bytes"),
        ("laz-one-point-chunks-oom", "LAZ chunk 1 at byte"),
        ("laz-variable-chunks-empty-table-oom", "LAZ chunk 0 at byte"),
        ("laz-point-wise-layered-oom", "LAZ chunk 0 at byte 727"),
        // Our own check's find: an empty LASzip VLR indexed out of bounds.
        ("laz-empty-laszip-vlr", "failed to fill whole buffer"),
    ] {
        let known = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../fuzz/seeds/scan_file")
            .join(name);
        let e = read_scan(&known, None, None).err().unwrap().to_string();
        assert!(e.contains(name) && e.contains(says), "{e}");
    }
}

/// The studio's COPC range reader (head, hierarchy pages — two of them in `simple_with_page` — and each
/// node's LAZ chunk) decodes every point of the peers' COPC files that the `las` crate reads from the whole
/// file: the same positions (to the files' scale) and colours, node by node adding up to the header's count.
#[test]
fn peer_copc_files_read_by_range_as_whole() {
    let Some(dir) = shared("las_copc") else {
        return;
    };
    for name in [
        "simple.copc.laz",
        "simple_with_page.copc.laz",
        "lasrs_autzen.copc.laz",
    ] {
        let path = dir.join(name);
        let (head, nodes) = silvr_core::copc::read::read_file(&path).unwrap();
        let key = |p: DVec3, c: [u8; 3]| {
            let q = ((p - head.offset) / head.scale).round();
            (q.x as i64, q.y as i64, q.z as i64, c)
        };
        let mut ours = Vec::new();
        for (e, pts) in &nodes {
            assert_eq!(pts.positions.len(), e.point_count as usize, "{name}");
            for (k, q) in pts.positions.iter().enumerate() {
                let p = head.center() + DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64);
                let c = pts.colors.as_ref().map_or([0; 3], |c| c[k]);
                ours.push(key(p, c));
            }
        }
        let mut r = las::Reader::from_path(&path).unwrap();
        let all = r.read_all().unwrap();
        let mut theirs: Vec<_> = all
            .points()
            .map(|p| {
                let p = p.unwrap();
                let c = p
                    .color
                    .map_or([0; 3], |c| [c.red, c.green, c.blue].map(|v| (v >> 8) as u8));
                key(DVec3::new(p.x, p.y, p.z), c)
            })
            .collect();
        assert_eq!(ours.len() as u64, head.points, "{name}");
        assert_eq!(ours.len(), theirs.len(), "{name}");
        ours.sort();
        theirs.sort();
        assert!(ours == theirs, "{name}: the decoded points differ");
        assert!(
            head.summary.is_none(),
            "{name}: a peer's file has no summary"
        );
        if name == "simple_with_page.copc.laz" {
            assert!(nodes.len() > 1);
        }
    }
}
