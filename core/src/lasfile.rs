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
    let names: Vec<String> = cloud
        .scalars
        .iter()
        .filter(|(_, v)| v.len() == cloud.len())
        .map(|(n, _)| n.clone())
        .collect();
    let (lo, hi) = finite_bounds(cloud).unwrap_or((glam::DVec3::ZERO, glam::DVec3::ZERO));
    let mut sink = LasSink::create(path, lo, hi, &names, Vec::new())?;
    sink.push(cloud)?;
    sink.finish()
}

/// The box of `cloud`'s finite positions, `None` when it has none.
pub fn finite_bounds(cloud: &PointCloud) -> Option<(glam::DVec3, glam::DVec3)> {
    let mut b: Option<(glam::DVec3, glam::DVec3)> = None;
    for p in cloud.positions.iter().filter(|p| p.is_finite()) {
        b = Some(b.map_or((*p, *p), |(lo, hi)| (lo.min(*p), hi.max(*p))));
    }
    b
}

/// A LAS/LAZ file written chunk by chunk (a map larger than the memory streams through it): the box and
/// the scalar names are fixed up front, points arrive in [`LasSink::push`]es, and [`LasSink::finish`]
/// renames the file into place (until then it lives under a temporary name).
pub struct LasSink {
    writer: las::Writer<std::io::BufWriter<std::fs::File>>,
    path: std::path::PathBuf,
    partial: std::path::PathBuf,
    names: Vec<String>,
    written: usize,
}

impl LasSink {
    /// A sink for points within `lo`..`hi` carrying `names` as float extra bytes, with `vlrs` added
    /// after the Extra Bytes VLR.
    pub fn create(
        path: &Path,
        lo: glam::DVec3,
        hi: glam::DVec3,
        names: &[String],
        vlrs: Vec<las::Vlr>,
    ) -> Result<Self, LasError> {
        let err = |reason: String| LasError {
            file: path.display().to_string(),
            reason,
        };
        // i32 steps of SCALE_M from the minimum corner must hold the cloud's extent.
        if ((hi - lo).max_element() / SCALE_M) >= i32::MAX as f64 {
            return Err(err(format!(
                "the cloud spans {:.0} m, beyond what LAS integers hold at {SCALE_M} m",
                (hi - lo).max_element()
            )));
        }
        let mut b = las::Builder::from((1, 4));
        b.point_format = las::point::Format::new(7).map_err(|e| err(e.to_string()))?;
        b.point_format.is_compressed = is_laz(path);
        b.point_format.extra_bytes = (4 * names.len()) as u16;
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
        if !names.is_empty() {
            let mut data = Vec::with_capacity(192 * names.len());
            for name in names {
                data.extend_from_slice(&descriptor(name, describe(name)));
            }
            b.vlrs.push(las::Vlr {
                user_id: "LASF_Spec".into(),
                record_id: 4,
                description: "Extra Bytes".into(),
                data,
            });
        }
        b.vlrs.extend(vlrs);
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
        let file = std::fs::File::create(&partial).map_err(|e| err(e.to_string()))?;
        let writer = las::Writer::new(std::io::BufWriter::with_capacity(1 << 20, file), header)
            .map_err(|e| {
                let _ = std::fs::remove_file(&partial);
                err(e.to_string())
            })?;
        Ok(Self {
            writer,
            path: path.to_path_buf(),
            partial,
            names: names.to_vec(),
            written: 0,
        })
    }

    fn err(&self, reason: String) -> LasError {
        LasError {
            file: self.path.display().to_string(),
            reason,
        }
    }

    /// Appends `chunk`'s finite points; a scalar the chunk lacks is written as NaN.
    pub fn push(&mut self, chunk: &PointCloud) -> Result<(), LasError> {
        let columns: Vec<Option<&[f32]>> = self
            .names
            .iter()
            .map(|n| chunk.scalar(n).filter(|v| v.len() == chunk.len()))
            .collect();
        let colours = chunk.colors.as_ref().filter(|c| c.len() == chunk.len());
        for (i, p) in chunk.positions.iter().enumerate() {
            if !p.is_finite() {
                continue;
            }
            let mut extra = Vec::with_capacity(4 * columns.len());
            for c in &columns {
                extra.extend_from_slice(&c.map_or(f32::NAN, |v| v[i]).to_le_bytes());
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
            self.writer
                .write_point(point)
                .map_err(|e| self.err(e.to_string()))?;
            self.written += 1;
        }
        Ok(())
    }

    /// Closes the file and renames it into place; returns how many points it holds.
    pub fn finish(mut self) -> Result<usize, LasError> {
        self.writer.close().map_err(|e| self.err(e.to_string()))?;
        std::fs::rename(&self.partial, &self.path).map_err(|e| self.err(e.to_string()))?;
        Ok(self.written)
    }
}

impl Drop for LasSink {
    /// A sink dropped before [`LasSink::finish`] (an error on the way) leaves no partial file behind.
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.partial);
    }
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
