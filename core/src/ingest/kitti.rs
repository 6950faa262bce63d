//! KITTI velodyne scans (`velodyne/NNNNNN.bin`) and nuScenes lidar sweeps (`*.pcd.bin`): headerless
//! little-endian `f32` records, one per point.
//!
//! KITTI (<https://www.cvlibs.net/datasets/kitti/eval_odometry.php>) writes 4 floats per point, `x y z
//! reflectance` in the sensor frame; nuScenes writes 5, `x y z intensity ring`. Both are selected with a
//! `stride` ([`KITTI_STRIDE`], [`NUSCENES_STRIDE`]). With no header, the length is the only check the file
//! allows, so a length that is not a whole number of records is refused rather than truncated: it means the
//! wrong stride or a cut-off download. Points with a non-finite coordinate carry no geometry and are
//! skipped (and counted), unlike organised PCD/PLY clouds where a NaN holds a pixel's place.

use std::path::Path;

use glam::DVec3;
use thiserror::Error;

use crate::dataset::{write_atomic, DatasetError};
use crate::pointcloud::PointCloud;

/// Floats per point of a KITTI `.bin`: x, y, z, reflectance.
pub const KITTI_STRIDE: usize = 4;
/// Floats per point of a nuScenes `.pcd.bin`: x, y, z, intensity, ring.
pub const NUSCENES_STRIDE: usize = 5;

/// `.bin` cloud errors; every variant names the file.
#[derive(Debug, Error)]
pub enum BinCloudError {
    #[error("{file}: {source}")]
    Io {
        file: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{file}: stride {stride} is not 4 (KITTI x y z reflectance) or 5 (nuScenes x y z intensity ring)")]
    BadStride { file: String, stride: usize },
    #[error("{file}: {bytes} bytes is not a whole number of {record}-byte points ({stride} little-endian f32 each); wrong stride or a truncated file")]
    BadLength {
        file: String,
        bytes: usize,
        record: usize,
        stride: usize,
    },
    #[error(transparent)]
    Write(#[from] DatasetError),
}

/// A decoded scan: positions, an `intensity` scalar (KITTI reflectance or nuScenes intensity) and, for
/// nuScenes, a `ring` scalar.
#[derive(Clone, Debug, PartialEq)]
pub struct BinScan {
    pub cloud: PointCloud,
    /// Records dropped for a NaN or infinite x, y or z.
    pub skipped: usize,
}

fn check_stride(file: &str, stride: usize) -> Result<(), BinCloudError> {
    if stride == KITTI_STRIDE || stride == NUSCENES_STRIDE {
        Ok(())
    } else {
        Err(BinCloudError::BadStride {
            file: file.to_string(),
            stride,
        })
    }
}

/// Decodes `.bin` bytes with `stride` floats per point; `name` is used in errors.
pub fn read_bin_bytes(bytes: &[u8], name: &str, stride: usize) -> Result<BinScan, BinCloudError> {
    check_stride(name, stride)?;
    let record = 4 * stride;
    if !bytes.len().is_multiple_of(record) {
        return Err(BinCloudError::BadLength {
            file: name.to_string(),
            bytes: bytes.len(),
            record,
            stride,
        });
    }
    let n = bytes.len() / record;
    let mut positions = Vec::with_capacity(n);
    let mut intensity = Vec::with_capacity(n);
    let mut ring = Vec::with_capacity(if stride == NUSCENES_STRIDE { n } else { 0 });
    let mut skipped = 0;
    let mut values = [0f32; NUSCENES_STRIDE];
    for rec in bytes.chunks_exact(record) {
        for (v, b) in values.iter_mut().zip(rec.chunks_exact(4)) {
            *v = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        }
        let [x, y, z, i, r] = values;
        let p = DVec3::new(x as f64, y as f64, z as f64);
        if !p.is_finite() {
            skipped += 1;
            continue;
        }
        positions.push(p);
        intensity.push(i);
        if stride == NUSCENES_STRIDE {
            ring.push(r);
        }
    }
    let mut cloud = PointCloud::from_positions(positions);
    cloud.set_scalar("intensity", intensity);
    if stride == NUSCENES_STRIDE {
        cloud.set_scalar("ring", ring);
    }
    Ok(BinScan { cloud, skipped })
}

/// Reads a KITTI (`stride` 4) or nuScenes (`stride` 5) `.bin` scan.
pub fn read_bin(path: &Path, stride: usize) -> Result<BinScan, BinCloudError> {
    let file = path.display().to_string();
    check_stride(&file, stride)?;
    let bytes = std::fs::read(path).map_err(|source| BinCloudError::Io {
        file: file.clone(),
        source,
    })?;
    read_bin_bytes(&bytes, &file, stride)
}

/// Encodes a cloud as `.bin` records: positions narrowed to `f32` (values beyond its range become
/// infinite), `intensity` and (stride 5) `ring` from the cloud's scalars, 0 where absent.
pub fn write_bin_bytes(cloud: &PointCloud, stride: usize) -> Result<Vec<u8>, BinCloudError> {
    check_stride("(bin writer)", stride)?;
    let intensity = cloud.scalar("intensity").unwrap_or(&[]);
    let ring = cloud.scalar("ring").unwrap_or(&[]);
    let mut out = Vec::with_capacity(cloud.len() * 4 * stride);
    for (k, p) in cloud.positions.iter().enumerate() {
        let i = intensity.get(k).copied().unwrap_or(0.0);
        let r = ring.get(k).copied().unwrap_or(0.0);
        let record = [p.x as f32, p.y as f32, p.z as f32, i, r];
        for v in record.iter().take(stride) {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    Ok(out)
}

/// Writes a `.bin` scan through a temporary file and a rename.
pub fn write_bin(path: &Path, cloud: &PointCloud, stride: usize) -> Result<(), BinCloudError> {
    check_stride(&path.display().to_string(), stride)?;
    write_atomic(path, &write_bin_bytes(cloud, stride)?)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn floats(v: &[f32]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_le_bytes()).collect()
    }

    #[test]
    fn reads_kitti_records() {
        let bytes = floats(&[1.0, 2.0, 3.0, 0.25, -4.5, 0.0, 1e-3, 1.0]);
        let scan = read_bin_bytes(&bytes, "000000.bin", KITTI_STRIDE).unwrap();
        assert_eq!(scan.skipped, 0);
        assert_eq!(
            scan.cloud.positions,
            vec![
                DVec3::new(1.0, 2.0, 3.0),
                DVec3::new(-4.5, 0.0, 1e-3f32 as f64)
            ]
        );
        assert_eq!(scan.cloud.scalar("intensity").unwrap(), &[0.25, 1.0]);
        assert!(scan.cloud.scalar("ring").is_none());
        assert!(scan.cloud.validate().is_ok());
    }

    #[test]
    fn round_trips_both_strides() {
        let mut cloud = PointCloud::from_positions(vec![
            DVec3::new(0.1, -2.5, 30.0),
            DVec3::new(-80.123456, 0.0, -1.75),
            DVec3::ZERO,
        ]);
        cloud.set_scalar("intensity", vec![0.5, 255.0, 0.0]);
        cloud.set_scalar("ring", vec![0.0, 31.0, 7.0]);
        for stride in [KITTI_STRIDE, NUSCENES_STRIDE] {
            let bytes = write_bin_bytes(&cloud, stride).unwrap();
            assert_eq!(bytes.len(), 3 * 4 * stride);
            let back = read_bin_bytes(&bytes, "x.bin", stride).unwrap();
            assert_eq!(back.skipped, 0);
            for (a, b) in back.cloud.positions.iter().zip(&cloud.positions) {
                // f64 → f32: relative error below 2^-24.
                assert!((*a - *b).abs().max_element() <= 6e-8 * b.abs().max_element().max(1.0));
            }
            assert_eq!(back.cloud.scalar("intensity"), cloud.scalar("intensity"));
            let ring = back.cloud.scalar("ring");
            if stride == NUSCENES_STRIDE {
                assert_eq!(ring, cloud.scalar("ring"));
            } else {
                assert!(ring.is_none());
            }
            // Writing what was read reproduces the bytes.
            assert_eq!(write_bin_bytes(&back.cloud, stride).unwrap(), bytes);
        }
        // Without scalars the extra columns are zero.
        let bare = PointCloud::from_positions(vec![DVec3::new(1.0, 2.0, 3.0)]);
        assert_eq!(
            write_bin_bytes(&bare, NUSCENES_STRIDE).unwrap(),
            floats(&[1.0, 2.0, 3.0, 0.0, 0.0])
        );
    }

    #[test]
    fn odd_lengths_and_strides_are_named_errors() {
        let bytes = floats(&[1.0, 2.0, 3.0, 0.5, 9.0]);
        let e = read_bin_bytes(&bytes, "seq/000042.bin", KITTI_STRIDE)
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("seq/000042.bin: 20 bytes") && e.contains("16-byte"),
            "{e}"
        );
        // The same 20 bytes are one nuScenes point.
        assert_eq!(
            read_bin_bytes(&bytes, "n.pcd.bin", NUSCENES_STRIDE)
                .unwrap()
                .cloud
                .len(),
            1
        );
        for len in [1, 3, 15, 17, 33] {
            assert!(read_bin_bytes(&vec![0u8; len], "a.bin", KITTI_STRIDE).is_err());
        }
        let e = read_bin_bytes(&bytes, "a.bin", 3).unwrap_err().to_string();
        assert!(e.starts_with("a.bin: stride 3"), "{e}");
        assert!(write_bin_bytes(&PointCloud::new(), 6).is_err());
    }

    #[test]
    fn non_finite_points_are_skipped_and_counted() {
        let bytes = floats(&[
            f32::NAN,
            0.0,
            0.0,
            1.0,
            1.0,
            2.0,
            3.0,
            0.5,
            0.0,
            f32::INFINITY,
            0.0,
            1.0,
            4.0,
            5.0,
            6.0,
            f32::NAN, // a NaN intensity keeps the point
        ]);
        let scan = read_bin_bytes(&bytes, "a.bin", KITTI_STRIDE).unwrap();
        assert_eq!(scan.skipped, 2);
        assert_eq!(
            scan.cloud.positions,
            vec![DVec3::new(1.0, 2.0, 3.0), DVec3::new(4.0, 5.0, 6.0)]
        );
        let i = scan.cloud.scalar("intensity").unwrap();
        assert_eq!(i[0], 0.5);
        assert!(i[1].is_nan());
    }

    #[test]
    fn empty_file_is_an_empty_scan() {
        for stride in [KITTI_STRIDE, NUSCENES_STRIDE] {
            let scan = read_bin_bytes(&[], "empty.bin", stride).unwrap();
            assert!(scan.cloud.is_empty());
            assert_eq!(scan.skipped, 0);
            assert_eq!(scan.cloud.scalar("intensity").unwrap().len(), 0);
        }
    }

    #[test]
    fn native_files() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("velodyne/000000.bin");
        let mut cloud = PointCloud::from_positions(vec![DVec3::new(1.0, 2.0, 3.0)]);
        cloud.set_scalar("intensity", vec![0.75]);
        write_bin(&path, &cloud, KITTI_STRIDE).unwrap();
        assert_eq!(std::fs::metadata(&path).unwrap().len(), 16);
        assert_eq!(read_bin(&path, KITTI_STRIDE).unwrap().cloud, cloud);
        let e = read_bin(&dir.path().join("nope.bin"), KITTI_STRIDE)
            .unwrap_err()
            .to_string();
        assert!(e.contains("nope.bin"), "{e}");
    }
}
