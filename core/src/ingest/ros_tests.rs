//! Unit tests of the ROS message decoders: hand-built messages through the CDR writer, both byte orders,
//! every truncation, and the PointCloud2 driver layouts.

use super::*;
use crate::ingest::cdr::{CdrWriter, Endian};

fn header(sec: i32, nanosec: u32, frame: &str) -> Header {
    Header {
        stamp: Time { sec, nanosec },
        frame_id: frame.to_string(),
    }
}

/// Every strict prefix of `bytes` must be rejected (and not panic).
fn all_prefixes_fail(bytes: &[u8], decode: impl Fn(&[u8]) -> Result<(), DecodeError>) {
    for n in 0..bytes.len() {
        let r = decode(&bytes[..n]);
        assert!(
            r.is_err(),
            "prefix of {n}/{} bytes decoded: {r:?}",
            bytes.len()
        );
    }
    decode(bytes).unwrap();
}

fn pose(t: [f64; 3], q: [f64; 4]) -> Se3 {
    Se3 {
        trans: DVec3::from_array(t),
        rot: DQuat::from_xyzw(q[0], q[1], q[2], q[3]),
    }
}

#[test]
fn header_round_trip_and_layout() {
    let h = header(1_700_000_000, 123_456_789, "base_link");
    let b = h.encode();
    assert_eq!(Header::decode(&b).unwrap(), h);
    assert_eq!(Header::decode(&h.encode_with(Endian::Big)).unwrap(), h);
    // sec@0, nanosec@4, frame_id length@8 (10 incl. NUL), text@12.
    assert_eq!(&b[4..8], &1_700_000_000i32.to_le_bytes());
    assert_eq!(&b[8..12], &123_456_789u32.to_le_bytes());
    assert_eq!(&b[12..16], &10u32.to_le_bytes());
    assert_eq!(&b[16..26], b"base_link\0");
    all_prefixes_fail(&b, |b| Header::decode(b).map(drop));
    assert!((h.stamp.seconds() - 1_700_000_000.123_456_8).abs() < 1e-6);
    assert_eq!(h.stamp.nanos(), 1_700_000_000_123_456_789);
    let t = Time {
        sec: -1,
        nanosec: 5,
    };
    assert_eq!(Time::decode(&t.encode()).unwrap(), t);
}

#[test]
fn big_endian_header() {
    let mut w = CdrWriter::with_endian(Endian::Big);
    w.i32(42).u32(7).string("map");
    let h = Header::decode(&w.finish()).unwrap();
    assert_eq!(h, header(42, 7, "map"));
}

#[test]
fn decode_errors_name_the_type() {
    let e = Odometry::decode(&[0, 1, 0, 0, 1]).unwrap_err();
    assert!(
        e.to_string()
            .starts_with("nav_msgs/msg/Odometry: truncated"),
        "{e}"
    );
    let e = PointCloud2::decode(&[0, 3, 0, 0]).unwrap_err();
    assert!(
        e.to_string().contains("sensor_msgs/msg/PointCloud2") && e.to_string().contains("PL_CDR"),
        "{e}"
    );
}

#[test]
fn tf_odometry_path_pose_round_trips() {
    let tf = TfMessage {
        transforms: vec![
            TransformStamped {
                header: header(10, 1, "odom"),
                child_frame_id: "base_footprint".into(),
                transform: pose([1.0, -2.0, 0.5], [0.0, 0.0, 0.38268343236, 0.92387953251]),
            },
            TransformStamped {
                header: header(10, 2, "base_link"),
                child_frame_id: "lidar".into(),
                transform: pose([0.0, 0.0, 0.124], [0.0, 0.0, 1.0, 0.0]),
            },
        ],
    };
    for endian in [Endian::Little, Endian::Big] {
        let b = tf.encode_with(endian);
        assert_eq!(TfMessage::decode(&b).unwrap(), tf);
        all_prefixes_fail(&b, |b| TfMessage::decode(b).map(drop));
    }

    let mut cov = [0.0; 36];
    cov.iter_mut()
        .enumerate()
        .for_each(|(i, c)| *c = i as f64 * 0.5);
    let odom = Odometry {
        header: header(5, 6, "odom"),
        child_frame_id: "base_footprint".into(),
        pose: pose([3.0, 4.0, 0.0], [0.0, 0.0, 0.0, 1.0]),
        pose_covariance: cov,
        linear: DVec3::new(0.2, 0.0, 0.0),
        angular: DVec3::new(0.0, 0.0, -0.1),
        twist_covariance: [1.0; 36],
    };
    for endian in [Endian::Little, Endian::Big] {
        let b = odom.encode_with(endian);
        assert_eq!(Odometry::decode(&b).unwrap(), odom);
        all_prefixes_fail(&b, |b| Odometry::decode(b).map(drop));
    }

    let path = Path {
        header: header(1, 0, "map"),
        poses: (0..3)
            .map(|i| PoseStamped {
                header: header(1, i, "map"),
                pose: pose([i as f64, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]),
            })
            .collect(),
    };
    for endian in [Endian::Little, Endian::Big] {
        let b = path.encode_with(endian);
        assert_eq!(Path::decode(&b).unwrap(), path);
        all_prefixes_fail(&b, |b| Path::decode(b).map(drop));
    }

    let ps = path.poses[2].clone();
    for endian in [Endian::Little, Endian::Big] {
        let b = ps.encode_with(endian);
        assert_eq!(PoseStamped::decode(&b).unwrap(), ps);
        all_prefixes_fail(&b, |b| PoseStamped::decode(b).map(drop));
    }

    let pwc = PoseWithCovarianceStamped {
        header: header(9, 9, "map"),
        pose: pose([1.0, 2.0, 3.0], [0.5, 0.5, 0.5, 0.5]),
        covariance: cov,
    };
    for endian in [Endian::Little, Endian::Big] {
        let b = pwc.encode_with(endian);
        assert_eq!(PoseWithCovarianceStamped::decode(&b).unwrap(), pwc);
        all_prefixes_fail(&b, |b| PoseWithCovarianceStamped::decode(b).map(drop));
    }
}

#[test]
fn absurd_transform_count_is_an_error() {
    let mut w = CdrWriter::new();
    w.u32(1_000_000_000).raw(&[0; 64]);
    let e = TfMessage::decode(&w.finish()).unwrap_err();
    assert!(e.to_string().contains("transforms"), "{e}");
}

// --- PointCloud2 -------------------------------------------------------------------------------------

/// Writes `v` of `datatype` at `at` in the given byte order.
fn put(buf: &mut [u8], at: usize, datatype: u8, v: f64, big: bool) {
    macro_rules! w {
        ($t:ty) => {{
            let b = if big {
                (v as $t).to_be_bytes()
            } else {
                (v as $t).to_le_bytes()
            };
            buf[at..at + b.len()].copy_from_slice(&b);
        }};
    }
    match datatype {
        1 => w!(i8),
        2 => w!(u8),
        3 => w!(i16),
        4 => w!(u16),
        5 => w!(i32),
        6 => w!(u32),
        7 => w!(f32),
        _ => w!(f64),
    }
}

/// A cloud with the given fields; `values(k)` gives each field's value for point k.
fn cloud(
    fields: Vec<PointField>,
    point_step: u32,
    width: u32,
    height: u32,
    row_step: u32,
    big: bool,
    values: impl Fn(usize) -> Vec<f64>,
) -> (Vec<u8>, PointCloud2<'static>) {
    let mut data = vec![0u8; (row_step * height) as usize];
    for r in 0..height as usize {
        for c in 0..width as usize {
            let k = r * width as usize + c;
            let base = r * row_step as usize + c * point_step as usize;
            for (f, v) in fields.iter().zip(values(k)) {
                put(&mut data, base + f.offset as usize, f.datatype, v, big);
            }
        }
    }
    let msg = PointCloud2 {
        header: header(1_700_000_000, 500_000_000, "lidar"),
        height,
        width,
        fields,
        is_bigendian: big,
        point_step,
        row_step,
        data: &[],
        is_dense: false,
    };
    (data, msg)
}

#[test]
fn hesai_absolute_seconds_unaligned_f64() {
    let f = |n, o, t| PointField::new(n, o, t);
    let fields = vec![
        f("x", 0, 7),
        f("y", 4, 7),
        f("z", 8, 7),
        f("intensity", 12, 7),
        f("ring", 16, 4),
        f("timestamp", 18, 8),
    ];
    let stamp = 1_700_000_000.5;
    let (data, mut msg) = cloud(fields, 26, 4, 1, 104, false, |k| {
        vec![
            k as f64 + 1.0,
            -(k as f64),
            0.5,
            10.0 * k as f64,
            k as f64,
            stamp + 0.025 * k as f64,
        ]
    });
    msg.data = &data;
    let bytes = msg.encode();
    let back = PointCloud2::decode(&bytes).unwrap();
    assert_eq!(back, msg);
    all_prefixes_fail(&bytes, |b| PointCloud2::decode(b).map(drop));
    let scan = back.to_scan().unwrap();
    assert_eq!(scan.time_kind, Some(PointTimeKind::AbsoluteSeconds));
    assert_eq!(scan.positions.len(), 4);
    assert_eq!(scan.positions[2], DVec3::new(3.0, -2.0, 0.5));
    assert_eq!(
        scan.intensities.as_deref(),
        Some(&[0.0, 10.0, 20.0, 30.0][..])
    );
    let times = scan.times.unwrap();
    for (k, t) in times.iter().enumerate() {
        assert!((t - 0.025 * k as f64).abs() < 1e-6, "point {k}: {t}");
    }
}

#[test]
fn ouster_relative_nanoseconds_organised_with_zeros() {
    let f = |n, o, t| PointField::new(n, o, t);
    let fields = vec![
        f("x", 0, 7),
        f("y", 4, 7),
        f("z", 8, 7),
        f("intensity", 16, 7),
        f("t", 20, 6),
        f("reflectivity", 24, 4),
        f("ring", 26, 4),
        f("ambient", 28, 4),
        f("range", 32, 6),
    ];
    // 2 beams x 3 columns; column c fires at c * 1 ms; point 4 is "no return" (all zeros).
    let (data, mut msg) = cloud(fields, 48, 3, 2, 3 * 48 + 16, false, |k| {
        let c = (k % 3) as f64;
        if k == 4 {
            vec![0.0; 9]
        } else {
            vec![
                1.0 + k as f64,
                2.0,
                3.0,
                7.0,
                c * 1e6,
                1.0,
                (k / 3) as f64,
                0.0,
                1000.0,
            ]
        }
    });
    msg.data = &data;
    let scan = PointCloud2::decode(&msg.encode())
        .unwrap()
        .to_scan()
        .unwrap();
    assert_eq!(scan.time_kind, Some(PointTimeKind::RelativeNanos));
    assert_eq!(scan.skipped_zero, 1);
    assert_eq!(scan.positions.len(), 5);
    assert_eq!(
        scan.positions[4],
        DVec3::new(6.0, 2.0, 3.0),
        "row 1 read through row_step padding"
    );
    assert_eq!(scan.times.unwrap(), vec![0.0, 0.001, 0.002, 0.0, 0.002]);
}

#[test]
fn velodyne_relative_seconds_big_endian_and_nan() {
    let f = |n, o, t| PointField::new(n, o, t);
    let fields = vec![
        f("x", 0, 7),
        f("y", 4, 7),
        f("z", 8, 7),
        f("intensity", 12, 7),
        f("ring", 16, 4),
        f("time", 18, 7),
    ];
    for big in [false, true] {
        let (data, mut msg) = cloud(fields.clone(), 22, 5, 1, 110, big, |k| {
            let x = if k == 1 { f64::NAN } else { k as f64 + 0.5 };
            vec![x, 1.0, -1.0, 3.0, 2.0, -0.05 + 0.01 * k as f64]
        });
        msg.data = &data;
        for endian in [Endian::Little, Endian::Big] {
            let bytes = msg.encode_with(endian);
            let scan = PointCloud2::decode(&bytes).unwrap().to_scan().unwrap();
            assert_eq!(scan.time_kind, Some(PointTimeKind::RelativeSeconds));
            assert_eq!(scan.skipped_nonfinite, 1);
            assert_eq!(scan.positions.len(), 4);
            assert_eq!(scan.positions[1].x, 2.5);
            let t = scan.times.unwrap();
            assert!((t[1] - (-0.03)).abs() < 1e-7, "{t:?}");
        }
    }
}

#[test]
fn livox_absolute_nanoseconds_and_integer_xyz() {
    let f = |n, o, t| PointField::new(n, o, t);
    let fields = vec![
        f("x", 0, 3),
        f("y", 2, 5),
        f("z", 6, 1),
        f("timestamp", 8, 8),
    ];
    let stamp_ns = 1_700_000_000_500_000_000.0;
    let (data, mut msg) = cloud(fields, 16, 2, 1, 32, false, |k| {
        vec![-300.0, 70_000.0 * k as f64, -5.0, stamp_ns + 1e6 * k as f64]
    });
    msg.data = &data;
    let scan = msg.to_scan().unwrap();
    assert_eq!(scan.time_kind, Some(PointTimeKind::AbsoluteNanos));
    assert_eq!(scan.positions[1], DVec3::new(-300.0, 70_000.0, -5.0));
    let t = scan.times.unwrap();
    assert!(t[0].abs() < 1e-6 && (t[1] - 1e-3).abs() < 1e-6, "{t:?}");
    let pc = scan_to_cloud_has_scalars(&msg);
    assert!(pc.scalar("time").is_some() && pc.scalar("intensity").is_none());
}

fn scan_to_cloud_has_scalars(msg: &PointCloud2) -> PointCloud {
    msg.to_scan().unwrap().to_point_cloud()
}

#[test]
fn pointcloud_layout_errors() {
    let f = |n, o, t| PointField::new(n, o, t);
    let base = vec![f("x", 0, 7), f("y", 4, 7), f("z", 8, 7)];
    let (data, mut msg) = cloud(base.clone(), 12, 3, 1, 36, false, |_| vec![1.0, 2.0, 3.0]);
    msg.data = &data;
    assert_eq!(msg.to_scan().unwrap().positions.len(), 3);
    assert!(msg.to_scan().unwrap().times.is_none());

    let mut m = msg.clone();
    m.data = &data[..35];
    assert!(m
        .to_scan()
        .unwrap_err()
        .to_string()
        .contains("data has 35 bytes"));
    let mut m = msg.clone();
    m.fields.truncate(2);
    assert!(m
        .to_scan()
        .unwrap_err()
        .to_string()
        .contains("no x, y and z"));
    let mut m = msg.clone();
    m.fields[2].offset = 10;
    assert!(m
        .to_scan()
        .unwrap_err()
        .to_string()
        .contains("does not fit"));
    let mut m = msg.clone();
    m.fields[0].datatype = 9;
    assert!(m
        .to_scan()
        .unwrap_err()
        .to_string()
        .contains("unknown datatype 9"));
    let mut m = msg.clone();
    m.point_step = 0;
    assert!(m.to_scan().is_err());
    let mut m = msg.clone();
    m.height = 2;
    m.width = 2;
    m.row_step = 12;
    assert!(m.to_scan().unwrap_err().to_string().contains("row_step"));
    let mut m = msg.clone();
    m.width = u32::MAX;
    m.height = u32::MAX;
    m.row_step = u32::MAX;
    assert!(m.to_scan().is_err(), "huge claimed size must not allocate");
}

// --- Images -------------------------------------------------------------------------------------------

fn image<'a>(enc: &str, w: u32, h: u32, step: u32, data: &'a [u8]) -> Image<'a> {
    Image {
        header: header(3, 4, "cam0"),
        height: h,
        width: w,
        encoding: enc.into(),
        is_bigendian: 0,
        step,
        data,
    }
}

#[test]
fn image_encodings_to_rgb() {
    // 2x1 pixels: (10,20,30) and (40,50,60), with one padding byte per row.
    let cases: [(&str, Vec<u8>, u32); 4] = [
        ("rgb8", vec![10, 20, 30, 40, 50, 60, 0], 7),
        ("bgr8", vec![30, 20, 10, 60, 50, 40, 0], 7),
        ("rgba8", vec![10, 20, 30, 255, 40, 50, 60, 255, 0], 9),
        ("bgra8", vec![30, 20, 10, 255, 60, 50, 40, 255, 0], 9),
    ];
    for (enc, data, step) in cases {
        let img = image(enc, 2, 1, step, &data);
        for endian in [Endian::Little, Endian::Big] {
            let bytes = img.encode_with(endian);
            let back = Image::decode(&bytes).unwrap();
            assert_eq!(back, img);
            let rgb = back.to_rgb().unwrap();
            assert_eq!(rgb.pixels, vec![[10, 20, 30], [40, 50, 60]], "{enc}");
        }
        all_prefixes_fail(&img.encode(), |b| Image::decode(b).map(drop));
    }
    let mono = image("mono8", 3, 1, 3, &[0, 128, 255]);
    assert_eq!(
        mono.to_rgb().unwrap().pixels,
        vec![[0; 3], [128; 3], [255; 3]]
    );
    let d16 = [0x00, 0x12, 0xff, 0xff];
    let mut m16 = image("mono16", 2, 1, 4, &d16);
    assert_eq!(m16.to_rgb().unwrap().pixels, vec![[0x12; 3], [0xff; 3]]);
    m16.is_bigendian = 1;
    assert_eq!(m16.to_rgb().unwrap().pixels, vec![[0x00; 3], [0xff; 3]]);
}

#[test]
fn bayer_demosaic_recovers_flat_colour() {
    let colour = [200u8, 100, 50];
    for (enc, cfa) in [
        ("bayer_rggb8", [0, 1, 1, 2]),
        ("bayer_bggr8", [2, 1, 1, 0]),
        ("bayer_gbrg8", [1, 2, 0, 1]),
        ("bayer_grbg8", [1, 0, 2, 1]),
    ] {
        let (w, h, step) = (6usize, 4usize, 8usize);
        let mut data = vec![0u8; step * h];
        for y in 0..h {
            for x in 0..w {
                data[y * step + x] = colour[cfa[(y & 1) * 2 + (x & 1)]];
            }
        }
        let rgb = image(enc, w as u32, h as u32, step as u32, &data)
            .to_rgb()
            .unwrap();
        assert_eq!(rgb.pixels.len(), w * h);
        assert!(
            rgb.pixels.iter().all(|p| *p == colour),
            "{enc}: {:?}",
            rgb.pixels
        );
    }
    // The pattern matters: a red-only RGGB mosaic has red exactly at (0, 0).
    let data = [255u8, 0, 0, 0];
    let rgb = image("bayer_rggb8", 2, 2, 2, &data).to_rgb().unwrap();
    assert_eq!(rgb.pixels[0], [255, 0, 0]);
    let rgb = image("bayer_bggr8", 2, 2, 2, &data).to_rgb().unwrap();
    assert_eq!(rgb.pixels[0], [0, 0, 255]);
}

#[test]
fn image_errors() {
    let e = image("yuv422", 1, 1, 2, &[0, 0]).to_rgb().unwrap_err();
    assert!(
        e.to_string()
            .contains("unsupported image encoding 'yuv422'"),
        "{e}"
    );
    let e = image("rgb8", 2, 2, 5, &[0; 12]).to_rgb().unwrap_err();
    assert!(e.to_string().contains("step 5"), "{e}");
    let e = image("rgb8", 2, 2, 6, &[0; 11]).to_rgb().unwrap_err();
    assert!(e.to_string().contains("needs 12"), "{e}");
    let e = image("mono8", u32::MAX, u32::MAX, u32::MAX, &[0; 4])
        .to_rgb()
        .unwrap_err();
    assert!(e.to_string().contains("data has 4 bytes"), "{e}");
}

#[test]
fn compressed_png_and_jpeg() {
    let (w, h) = (16u32, 8u32);
    let px: Vec<[u8; 3]> = (0..w * h)
        .map(|i| [(i * 2) as u8, 100, (255 - i) as u8])
        .collect();
    let png = crate::dataset::png_rgb(w, h, &px);
    let msg = CompressedImage {
        header: header(1, 2, "cam"),
        format: "png".into(),
        data: &png,
    };
    let bytes = msg.encode();
    all_prefixes_fail(&bytes, |b| CompressedImage::decode(b).map(drop));
    assert_eq!(
        CompressedImage::decode(&msg.encode_with(Endian::Big)).unwrap(),
        msg
    );
    let back = CompressedImage::decode(&bytes).unwrap();
    assert_eq!(back, msg);
    let rgb = back.to_rgb().unwrap();
    assert_eq!((rgb.width, rgb.height), (w, h));
    assert_eq!(rgb.pixels, px);

    let flat = image::RgbImage::from_pixel(w, h, image::Rgb([180, 90, 30]));
    let mut jpg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpg, 95)
        .encode_image(&flat)
        .unwrap();
    let msg = CompressedImage {
        header: header(1, 2, "cam"),
        format: "bgr8; jpeg compressed bgr8".into(),
        data: &jpg,
    };
    let rgb = msg.to_rgb().unwrap();
    assert_eq!(rgb.pixels.len(), (w * h) as usize);
    for p in &rgb.pixels {
        for (a, b) in p.iter().zip([180u8, 90, 30]) {
            assert!((*a as i32 - b as i32).abs() <= 3, "{p:?}");
        }
    }

    let bad = CompressedImage {
        format: "jpeg".into(),
        data: &jpg[..jpg.len() / 2],
        ..msg.clone()
    };
    assert!(bad.to_rgb().is_err());
    let garbage = CompressedImage {
        data: b"not an image at all",
        ..msg.clone()
    };
    assert!(garbage
        .to_rgb()
        .unwrap_err()
        .to_string()
        .contains("cannot identify"));
    let depth = CompressedImage {
        format: "16UC1; compressedDepth png".into(),
        data: &png,
        ..msg
    };
    assert!(depth
        .to_rgb()
        .unwrap_err()
        .to_string()
        .contains("compressedDepth"));
}

// --- CameraInfo ---------------------------------------------------------------------------------------

fn camera_info(model: &str, d: Vec<f64>) -> CameraInfo {
    CameraInfo {
        header: header(0, 0, "CAMERA_01"),
        height: 1216,
        width: 1936,
        distortion_model: model.into(),
        d,
        k: [2181.0, 0.0, 968.0, 0.0, 2182.0, 608.0, 0.0, 0.0, 1.0],
        r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: [
            2181.0, 0.0, 968.0, 0.0, 0.0, 2182.0, 608.0, 0.0, 0.0, 0.0, 1.0, 0.0,
        ],
        binning_x: 1,
        binning_y: 2,
        roi: RegionOfInterest {
            x_offset: 3,
            y_offset: 4,
            height: 5,
            width: 6,
            do_rectify: true,
        },
    }
}

#[test]
fn camera_info_layout_matches_the_worked_example() {
    // Offsets of the DGP CameraInfo worked example (formats notes §2.2), body-relative.
    let ci = camera_info("plumb_bob", vec![0.1, 0.2, 0.3, 0.4, 0.5]);
    let b = ci.encode();
    let body = &b[4..];
    let f64_at = |o: usize| f64::from_le_bytes(body[o..o + 8].try_into().unwrap());
    let u32_at = |o: usize| u32::from_le_bytes(body[o..o + 4].try_into().unwrap());
    assert_eq!(&body[12..22], b"CAMERA_01\0");
    assert_eq!(u32_at(24), 1216);
    assert_eq!(u32_at(28), 1936);
    assert_eq!(&body[36..46], b"plumb_bob\0");
    assert_eq!(u32_at(48), 5);
    assert_eq!(f64_at(56), 0.1);
    assert_eq!(f64_at(88), 0.5);
    assert_eq!(f64_at(96), 2181.0);
    for endian in [Endian::Little, Endian::Big] {
        assert_eq!(CameraInfo::decode(&ci.encode_with(endian)).unwrap(), ci);
    }
    all_prefixes_fail(&b, |b| CameraInfo::decode(b).map(drop));
}

#[test]
fn camera_info_models() {
    let cam = camera_info("plumb_bob", vec![0.1, -0.2, 0.001, 0.002, 0.03])
        .camera_model()
        .unwrap();
    assert_eq!(
        (cam.fx, cam.fy, cam.cx, cam.cy),
        (2181.0, 2182.0, 968.0, 608.0)
    );
    assert_eq!((cam.width, cam.height), (1936, 1216));
    assert_eq!(
        cam.distortion,
        Distortion::RadTan {
            k1: 0.1,
            k2: -0.2,
            p1: 0.001,
            p2: 0.002,
            k3: 0.03
        }
    );
    let cam = camera_info("equidistant", vec![-0.041142, -0.002422, 0.0034, -0.001852])
        .camera_model()
        .unwrap();
    assert_eq!(
        cam.distortion,
        Distortion::Fisheye {
            k1: -0.041142,
            k2: -0.002422,
            k3: 0.0034,
            k4: -0.001852
        }
    );
    let rp = camera_info(
        "rational_polynomial",
        vec![0.1, 0.2, 0.0, 0.0, 0.3, 0.0, 0.0, 0.0],
    );
    assert!(
        matches!(rp.camera_model().unwrap().distortion, Distortion::RadTan { k3, .. } if k3 == 0.3)
    );
    let rp = camera_info(
        "rational_polynomial",
        vec![0.1, 0.2, 0.0, 0.0, 0.3, 0.4, 0.0, 0.0],
    );
    assert!(rp
        .camera_model()
        .unwrap_err()
        .to_string()
        .contains("k4..k6"));
    assert_eq!(
        camera_info("plumb_bob", vec![])
            .camera_model()
            .unwrap()
            .distortion,
        Distortion::None
    );
    assert!(camera_info("plumb_bob", vec![0.1, 0.2])
        .camera_model()
        .unwrap_err()
        .to_string()
        .contains("needs 5"));
    assert!(camera_info("kannala", vec![0.1])
        .camera_model()
        .unwrap_err()
        .to_string()
        .contains("unknown distortion model"));
    let mut bad = camera_info("plumb_bob", vec![]);
    bad.k[0] = 0.0;
    assert!(bad.camera_model().is_err());
}

#[test]
fn absurd_distortion_count_is_an_error() {
    let mut w = CdrWriter::new();
    header(0, 0, "c").write(&mut w);
    w.u32(1)
        .u32(1)
        .string("plumb_bob")
        .u32(0x4000_0000)
        .raw(&[0; 256]);
    let e = CameraInfo::decode(&w.finish()).unwrap_err();
    assert!(
        e.to_string().contains("'d'") || e.to_string().contains("d at byte"),
        "{e}"
    );
}

// --- Dispatch -----------------------------------------------------------------------------------------

#[test]
fn dispatch_by_schema_name() {
    let ps = PoseStamped {
        header: header(1, 2, "map"),
        pose: pose([1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0]),
    };
    let b = ps.encode();
    for name in ["geometry_msgs/msg/PoseStamped", "geometry_msgs/PoseStamped"] {
        assert!(is_known_type(name));
        assert_eq!(
            decode(name, &b).unwrap().unwrap(),
            RosMessage::PoseStamped(ps.clone())
        );
    }
    assert!(decode("test_msgs/msg/BasicTypes", &b).is_none());
    assert!(!is_known_type("sensor_msgs/msg/Imu"));
    assert!(decode("nav_msgs/msg/Odometry", &b).unwrap().is_err());
    assert_eq!(canonical_type("a/msg/B"), "a/msg/B");
    assert_eq!(canonical_type("a/B"), "a/msg/B");
}

/// Writes the CDR fuzz target's seed corpus (`fuzz/seeds/cdr/`: one file per known type, the first byte
/// selecting the type as the target reads it). Regenerate with
/// `cargo test -p silvr-core --lib write_cdr_fuzz_seeds -- --ignored`.
#[test]
#[ignore]
fn write_cdr_fuzz_seeds() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/seeds/cdr");
    std::fs::create_dir_all(&dir).unwrap();
    let fields = vec![
        PointField::new("x", 0, PointField::FLOAT32),
        PointField::new("y", 4, PointField::FLOAT32),
        PointField::new("z", 8, PointField::FLOAT32),
        PointField::new("intensity", 12, PointField::FLOAT32),
        PointField::new("ring", 16, PointField::UINT16),
        PointField::new("timestamp", 18, PointField::FLOAT64),
    ];
    let (data, mut pc) = cloud(fields, 26, 3, 1, 78, false, |k| {
        vec![
            1.0 + k as f64,
            2.0,
            0.5,
            10.0,
            k as f64,
            1.7e9 + 0.01 * k as f64,
        ]
    });
    pc.data = &data;
    let px = [10u8, 20, 30, 40, 50, 60, 70, 80, 90, 100, 110, 120];
    let png = crate::dataset::png_rgb(2, 2, &[[1, 2, 3], [4, 5, 6], [7, 8, 9], [10, 11, 12]]);
    let tf = TfMessage {
        transforms: vec![TransformStamped {
            header: header(1, 2, "base_link"),
            child_frame_id: "lidar".into(),
            transform: pose([0.0, 0.0, 0.124], [0.0, 0.0, 1.0, 0.0]),
        }],
    };
    let odo = Odometry {
        header: header(3, 4, "odom"),
        child_frame_id: "base_link".into(),
        pose: pose([1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0]),
        pose_covariance: [0.0; 36],
        linear: DVec3::X,
        angular: DVec3::Z,
        twist_covariance: [0.0; 36],
    };
    let ps = PoseStamped {
        header: header(5, 6, "map"),
        pose: pose([1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]),
    };
    let seeds: Vec<(&str, Vec<u8>)> = vec![
        (PointCloud2::MSG, pc.encode()),
        (Image::MSG, image("rgb8", 2, 2, 6, &px).encode()),
        (
            CompressedImage::MSG,
            CompressedImage {
                header: header(0, 0, "cam"),
                format: "png".into(),
                data: &png,
            }
            .encode(),
        ),
        (
            CameraInfo::MSG,
            camera_info("equidistant", vec![0.1, 0.01, 0.0, 0.0]).encode(),
        ),
        (TfMessage::MSG, tf.encode()),
        (Odometry::MSG, odo.encode()),
        (
            Path::MSG,
            Path {
                header: header(7, 8, "map"),
                poses: vec![ps.clone(), ps.clone()],
            }
            .encode(),
        ),
        (PoseStamped::MSG, ps.encode()),
    ];
    for (ty, payload) in seeds {
        let pick = KNOWN_TYPES.iter().position(|t| *t == ty).unwrap() as u8;
        decode(ty, &payload).unwrap().unwrap();
        let mut bytes = vec![pick];
        bytes.extend_from_slice(&payload);
        let name = ty.rsplit('/').next().unwrap();
        std::fs::write(dir.join(name), bytes).unwrap();
    }
}

#[test]
fn an_image_without_pixels_is_refused_at_once() {
    // Width 0 and height 2^32 − 1 passed the data-length check and ran the row loop 4 billion times
    // (found by the cdr fuzz target: 85 s in an unoptimised build).
    for (width, height, step) in [(0, u32::MAX, 0), (5, 0, 15), (0, 0, 0)] {
        let img = Image {
            header: Header::default(),
            height,
            width,
            encoding: "rgb8".into(),
            is_bigendian: 0,
            step,
            data: &[],
        };
        let t = std::time::Instant::now();
        let e = img.to_rgb().unwrap_err().to_string();
        assert!(e.contains("no pixels"), "{e}");
        assert!(t.elapsed().as_secs_f64() < 1.0);
    }
}

#[test]
fn a_cloud_without_columns_is_empty_at_once() {
    // Width 0 with height 2^32 − 1 passed the size check and walked 4 billion empty rows (found by the
    // cdr fuzz target's CI smoke).
    let f = |n, o, t| PointField::new(n, o, t);
    let (data, mut msg) = cloud(
        vec![f("x", 0, 7), f("y", 4, 7), f("z", 8, 7)],
        12,
        3,
        1,
        36,
        false,
        |_| vec![1.0, 2.0, 3.0],
    );
    msg.data = &data;
    msg.width = 0;
    msg.height = u32::MAX;
    let t = std::time::Instant::now();
    assert_eq!(msg.to_scan().unwrap().positions.len(), 0);
    assert!(t.elapsed().as_secs_f64() < 1.0, "{:?}", t.elapsed());
}
