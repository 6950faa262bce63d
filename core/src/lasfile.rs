//! Results out for survey and GIS tools: a point cloud as LAS 1.4 / LAZ (point format 7: position,
//! RGB), every per-point scalar of the cloud (`log_std_colour`, `log_std_depth`, `log_std_combined`,
//! `submap`, `error_m`, …) as an extra-bytes dimension of type float, described by name and meaning in the
//! Extra Bytes VLR — the form PDAL, laspy, QGIS and CloudCompare read. Written through the `las` crate
//! (LAZ by its `laz` feature) under a temporary name, then renamed.

use std::path::Path;

use crate::pointcloud::PointCloud;

/// Coordinates are stored as integers of this step (m) from the cloud's minimum corner.
pub const SCALE_M: f64 = 1e-4;

/// What a scalar means, for the extra-bytes description (32 bytes at most).
fn describe(name: &str) -> &'static str {
    match name {
        "log_std_colour" => "log10 posterior std, colour (m)",
        "log_std_depth" => "log10 posterior std, lidar (m)",
        "log_std_combined" => "log10 posterior std, both (m)",
        "submap" => "submap index",
        "error_m" => "distance to ground truth (m)",
        "intensity" => "lidar intensity",
        _ => "per-point scalar",
    }
}

/// Why a LAS/LAZ file could not be written: the file and the problem.
#[derive(Debug, thiserror::Error)]
#[error("{file}: {reason}")]
pub struct LasError {
    pub file: String,
    pub reason: String,
}

/// One 192-byte extra-bytes descriptor (LAS 1.4 R15 §2.6.3) for a float dimension.
fn descriptor(name: &str, description: &str) -> [u8; 192] {
    let mut d = [0u8; 192];
    d[2] = 9; // data_type: float
    let n = name.as_bytes();
    d[4..4 + n.len().min(32)].copy_from_slice(&n[..n.len().min(32)]);
    let t = description.as_bytes();
    d[160..160 + t.len().min(32)].copy_from_slice(&t[..t.len().min(32)]);
    d
}

/// Writes `cloud` to `path` (`.laz` compressed, `.las` not). Non-finite positions are left out.
pub fn write_las(path: &Path, cloud: &PointCloud) -> Result<usize, LasError> {
    let err = |reason: String| LasError {
        file: path.display().to_string(),
        reason,
    };
    let keep: Vec<usize> = (0..cloud.len())
        .filter(|&i| cloud.positions[i].is_finite())
        .collect();
    let (mut lo, mut hi) = (
        glam::DVec3::splat(f64::INFINITY),
        glam::DVec3::splat(f64::NEG_INFINITY),
    );
    for &i in &keep {
        lo = lo.min(cloud.positions[i]);
        hi = hi.max(cloud.positions[i]);
    }
    if keep.is_empty() {
        lo = glam::DVec3::ZERO;
        hi = glam::DVec3::ZERO;
    }
    // i32 steps of SCALE_M from the minimum corner must hold the cloud's extent.
    if ((hi - lo).max_element() / SCALE_M) >= i32::MAX as f64 {
        return Err(err(format!(
            "the cloud spans {:.0} m, beyond what LAS integers hold at {SCALE_M} m",
            (hi - lo).max_element()
        )));
    }
    let scalars: Vec<&(String, Vec<f32>)> = cloud
        .scalars
        .iter()
        .filter(|(_, v)| v.len() == cloud.len())
        .collect();
    let mut b = las::Builder::from((1, 4));
    b.point_format = las::point::Format::new(7).map_err(|e| err(e.to_string()))?;
    b.point_format.is_compressed = is_laz(path);
    b.point_format.extra_bytes = (4 * scalars.len()) as u16;
    let t = |offset: f64| las::Transform {
        scale: SCALE_M,
        offset: offset.floor(),
    };
    b.transforms = las::Vector {
        x: t(lo.x),
        y: t(lo.y),
        z: t(lo.z),
    };
    b.generating_software = "SiLVR Studio".into();
    if !scalars.is_empty() {
        let mut data = Vec::with_capacity(192 * scalars.len());
        for (name, _) in &scalars {
            data.extend_from_slice(&descriptor(name, describe(name)));
        }
        b.vlrs.push(las::Vlr {
            user_id: "LASF_Spec".into(),
            record_id: 4,
            description: "Extra Bytes".into(),
            data,
        });
    }
    let header = b.into_header().map_err(|e| err(e.to_string()))?;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_default();
    // The extension decides compression, so the temporary name keeps it.
    let partial = path.with_file_name(format!(
        ".{name}.partial.{}",
        if is_laz(path) { "laz" } else { "las" }
    ));
    let mut w = las::Writer::from_path(&partial, header).map_err(|e| err(e.to_string()))?;
    let colours = cloud.colors.as_ref().filter(|c| c.len() == cloud.len());
    for &i in &keep {
        let p = cloud.positions[i];
        let mut extra = Vec::with_capacity(4 * scalars.len());
        for (_, v) in &scalars {
            extra.extend_from_slice(&v[i].to_le_bytes());
        }
        let point = las::Point {
            x: p.x,
            y: p.y,
            z: p.z,
            color: Some(colours.map_or(las::Color::new(0, 0, 0), |c| {
                let [r, g, b] = c[i];
                las::Color::new(r as u16 * 257, g as u16 * 257, b as u16 * 257)
            })),
            extra_bytes: extra,
            // Format 7 carries a GPS time; a reconstruction has none to give.
            gps_time: Some(0.0),
            ..Default::default()
        };
        w.write_point(point).map_err(|e| err(e.to_string()))?;
    }
    w.close().map_err(|e| err(e.to_string()))?;
    drop(w);
    std::fs::rename(&partial, path).map_err(|e| err(e.to_string()))?;
    Ok(keep.len())
}

fn is_laz(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("laz"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    #[test]
    fn scalars_become_described_extra_bytes_and_points_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let mut c = PointCloud::from_positions(vec![
            DVec3::new(1.0, 2.0, 3.0),
            DVec3::new(-4.5, 0.25, 1e3),
            DVec3::NAN,
        ]);
        c.colors = Some(vec![[255, 0, 10], [1, 2, 3], [0, 0, 0]]);
        c.set_scalar("log_std_depth", vec![-1.5, -2.0, 0.0]);
        c.set_scalar("submap", vec![0.0, 3.0, 1.0]);
        for ext in ["las", "laz"] {
            let p = dir.path().join(format!("x.{ext}"));
            assert_eq!(write_las(&p, &c).unwrap(), 2);
            let mut r = las::Reader::from_path(&p).unwrap();
            assert_eq!(r.header().number_of_points(), 2);
            let vlr = r
                .header()
                .vlrs()
                .iter()
                .find(|v| v.record_id == 4)
                .unwrap()
                .clone();
            assert_eq!(vlr.data.len(), 2 * 192);
            assert!(vlr.data[4..].starts_with(b"log_std_depth"));
            let all = r.read_all().unwrap();
            let pts: Vec<las::Point> = all.points().map(|p| p.unwrap()).collect();
            assert!((pts[1].z - 1e3).abs() <= SCALE_M / 2.0);
            assert_eq!(pts[0].color.unwrap().red, 65535);
            assert_eq!(
                f32::from_le_bytes(pts[1].extra_bytes[4..8].try_into().unwrap()),
                3.0
            );
            // No temporary file left behind.
            assert_eq!(
                std::fs::read_dir(dir.path()).unwrap().count(),
                if ext == "las" { 1 } else { 2 }
            );
        }
    }
}
