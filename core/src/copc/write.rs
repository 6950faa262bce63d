//! Writing COPC in bounded memory. Two passes over the map (a PLY on disk read in chunks, or a cloud already
//! in memory): the first sums up the [`CopcSummary`]; the second streams the points into a temporary
//! LAS 1.4 that carries our extra-bytes and summary VLRs, which `copc-writer` orders into the octree
//! through spill files on disk, keeping our VLRs. Memory: one chunk of points, the filter field's column
//! (4 bytes a point) and what `copc-writer` holds per octree level; disk: the temporary LAS and the spill
//! files beside the output, both removed at the end. The output appears under its name only when whole.

use std::path::{Path, PathBuf};

use super::{CopcSummary, SummaryBuilder, SUMMARY_RECORD_ID, SUMMARY_USER_ID};
use crate::lasfile::{finite_bounds, LasSink};
use crate::pointcloud::{PlyChunks, PointCloud};

/// Points read from a PLY at a time.
const CHUNK_POINTS: usize = 1 << 20;

/// What to write.
pub enum CopcInput<'a> {
    /// A cloud in memory (`reconstruct`'s merged map).
    Cloud(&'a PointCloud),
    /// A PLY on disk, streamed (`silvr export copc X.ply`).
    Ply(&'a Path),
    /// A LAS/LAZ (or COPC) on disk, streamed, its numeric extra dimensions kept (`silvr export copc X.laz`).
    Las(&'a Path),
}

/// How the octree is cut.
#[derive(Clone, Copy, Debug)]
pub struct CopcOptions {
    /// Most points in one octree node (one LAZ chunk, one range request of a viewer).
    pub points_per_node: u32,
}

impl Default for CopcOptions {
    /// 100,000 points a node: copc-writer's default, the order of PDAL's and Potree's nodes.
    fn default() -> Self {
        Self {
            points_per_node: 100_000,
        }
    }
}

/// What was written.
#[derive(Clone, Debug)]
pub struct CopcWritten {
    pub points: u64,
    pub fields: Vec<String>,
    pub summary: CopcSummary,
    pub bytes: u64,
}

/// Why a COPC file could not be written: the file and the problem.
#[derive(Debug, thiserror::Error)]
#[error("{file}: {reason}")]
pub struct CopcError {
    pub file: String,
    pub reason: String,
}

fn error(file: &Path, reason: impl std::fmt::Display) -> CopcError {
    CopcError {
        file: file.display().to_string(),
        reason: reason.to_string(),
    }
}

/// The scalars of `c` with a value for every point.
fn full_scalars(c: &PointCloud) -> Vec<String> {
    c.scalars
        .iter()
        .filter(|(_, v)| v.len() == c.len())
        .map(|(n, _)| n.clone())
        .collect()
}

/// Calls `f` with each chunk of the input; returns the extra dimensions' names.
fn chunks(
    input: &CopcInput,
    f: &mut (dyn FnMut(&PointCloud) -> Result<(), CopcError> + Send),
) -> Result<Vec<String>, CopcError> {
    match input {
        CopcInput::Cloud(c) => {
            f(c)?;
            Ok(full_scalars(c))
        }
        CopcInput::Las(path) => {
            // The reader hands its chunks over on its own thread; `f`'s error comes back as text.
            let mut failure = None;
            let names = crate::eval::scan::read_las_chunks(path, CHUNK_POINTS, &mut |c| {
                f(c).map_err(|e| {
                    let text = e.reason.clone();
                    failure = Some(e);
                    text
                })
            });
            match (names, failure) {
                (_, Some(e)) => Err(e),
                (Ok(n), None) => Ok(n),
                (Err(e), None) => Err(error(path, e.reason)),
            }
        }
        CopcInput::Ply(path) => {
            let mut r = PlyChunks::open(path).map_err(|e| error(path, e))?;
            while let Some(c) = r.next_chunk(CHUNK_POINTS).map_err(|e| error(path, e))? {
                f(&c)?;
            }
            Ok(r.scalar_names().to_vec())
        }
    }
}

/// Writes `input` to `out` as COPC with every scalar as a float extra dimension and the summary VLR.
pub fn write_copc(
    input: CopcInput,
    out: &Path,
    opts: &CopcOptions,
) -> Result<CopcWritten, CopcError> {
    if opts.points_per_node == 0 {
        return Err(error(out, "points per node must be at least 1"));
    }
    // Pass 1: the box and the summary.
    let mut builder: Option<SummaryBuilder> = None;
    let mut bounds: Option<(glam::DVec3, glam::DVec3)> = None;
    let names = chunks(&input, &mut |c| {
        if let Some((lo, hi)) = finite_bounds(c) {
            bounds = Some(bounds.map_or((lo, hi), |(a, b)| (a.min(lo), b.max(hi))));
        }
        builder
            .get_or_insert_with(|| SummaryBuilder::new(&full_scalars(c)))
            .add(c)
            .map_err(|e| error(out, e))
    })?;
    let summary = builder
        .unwrap_or_else(|| SummaryBuilder::new(&names))
        .finish();
    let Some((lo, hi)) = bounds else {
        return Err(error(out, "the cloud has no point with a finite position"));
    };
    let data = summary.to_bytes();
    if data.len() > u16::MAX as usize {
        return Err(error(
            out,
            format!(
                "the summary takes {} bytes, more than a VLR holds",
                data.len()
            ),
        ));
    }
    let vlr = las::Vlr {
        user_id: SUMMARY_USER_ID.into(),
        record_id: SUMMARY_RECORD_ID,
        description: "SiLVR whole-cloud summary".into(),
        data,
    };

    // Pass 2: a temporary LAS beside the output (same file system: the final rename is atomic).
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let work = tempfile::Builder::new()
        .prefix(".silvr-copc-")
        .tempdir_in(&parent)
        .map_err(|e| {
            error(
                out,
                format!("temporary folder in {}: {e}", parent.display()),
            )
        })?;
    let las_path = work.path().join("points.las");
    let mut sink =
        LasSink::create(&las_path, lo, hi, &names, vec![vlr]).map_err(|e| error(out, e))?;
    chunks(&input, &mut |c| sink.push(c).map_err(|e| error(out, e)))?;
    let written = sink.finish().map_err(|e| error(out, e))? as u64;
    if written != summary.points {
        return Err(error(
            out,
            format!(
                "the input changed between passes ({} then {written} points)",
                summary.points
            ),
        ));
    }

    // The octree, through copc-writer's spill files in the same folder.
    let partial = work.path().join("out.copc.laz");
    copc_writer::convert_las_to_copc_streaming(
        &las_path,
        &partial,
        &copc_writer::CopcWriterParams::new(opts.points_per_node),
        work.path(),
        &copc_core::NeverCancel,
    )
    .map_err(|e| error(out, e))?;
    let _ = std::fs::remove_file(&las_path);
    std::fs::rename(&partial, out).map_err(|e| error(out, e))?;
    let bytes = std::fs::metadata(out).map(|m| m.len()).unwrap_or(0);
    Ok(CopcWritten {
        points: written,
        fields: names,
        summary,
        bytes,
    })
}

/// The point count of a LAS/LAZ/COPC file's header and its summary VLR, if it has one (our COPC does).
pub fn read_summary(path: &Path) -> Result<(u64, Option<CopcSummary>), CopcError> {
    let r = las::Reader::from_path(path).map_err(|e| error(path, e))?;
    let h = r.header();
    let summary = h
        .vlrs()
        .iter()
        .find(|v| v.user_id == SUMMARY_USER_ID && v.record_id == SUMMARY_RECORD_ID)
        .map(|v| CopcSummary::from_bytes(&v.data, &path.display().to_string()))
        .transpose()
        .map_err(|e| error(path, e.reason))?;
    Ok((h.number_of_points(), summary))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    /// A cloud of a few octree nodes: every point comes back (to the 0.1 mm step) with its colour and
    /// every extra dimension, the file is COPC (its info VLR first, LAZ 1.4 format 7), and the summary
    /// VLR reads back equal to what was written. The PLY and LAZ paths stream to the same content.
    #[test]
    fn a_cloud_written_as_copc_reads_back_whole() {
        let dir = tempfile::tempdir().unwrap();
        let n = 5000;
        let mut c = PointCloud::new();
        for i in 0..n {
            let t = i as f64 * 0.37;
            c.push_colored(
                DVec3::new(t.sin() * 20.0, t.cos() * 20.0, (i % 97) as f64 * 0.05),
                [(i % 256) as u8, 7, 200],
            );
        }
        c.positions.push(DVec3::NAN);
        c.colors.as_mut().unwrap().push([0, 0, 0]);
        let m = n + 1;
        c.set_scalar(
            "log_std_combined",
            (0..m).map(|i| -2.0 + (i % 50) as f32 * 0.02).collect(),
        );
        c.set_scalar("submap", (0..m).map(|i| (i % 4) as f32).collect());
        let ply = dir.path().join("map.ply");
        crate::pointcloud::write_ply(&ply, &c).unwrap();
        let laz = dir.path().join("map.laz");
        crate::lasfile::write_las(&laz, &c).unwrap();
        for (k, input) in [
            CopcInput::Cloud(&c),
            CopcInput::Ply(&ply),
            CopcInput::Las(&laz),
        ]
        .into_iter()
        .enumerate()
        {
            let out = dir.path().join(format!("map{k}.copc.laz"));
            let w = write_copc(
                input,
                &out,
                &CopcOptions {
                    points_per_node: 1000,
                },
            )
            .unwrap();
            assert_eq!(w.points, n as u64);
            assert_eq!(w.fields, ["log_std_combined", "submap"]);
            let mut r = las::Reader::from_path(&out).unwrap();
            let h = r.header().clone();
            assert_eq!(h.number_of_points(), n as u64);
            assert_eq!(h.point_format().to_u8().unwrap(), 7);
            assert!(h.point_format().is_compressed);
            let first = &h.vlrs()[0];
            assert_eq!((first.user_id.as_str(), first.record_id), ("copc", 1));
            let ours = h
                .vlrs()
                .iter()
                .find(|v| v.user_id == SUMMARY_USER_ID && v.record_id == SUMMARY_RECORD_ID)
                .expect("the summary VLR");
            let back = CopcSummary::from_bytes(&ours.data, "x").unwrap();
            assert_eq!(back, w.summary);
            assert_eq!(back.points, n as u64);
            // The points, in the octree's order: match each to its original by its submap and position.
            let all = r.read_all().unwrap();
            let pts: Vec<las::Point> = all.points().map(|p| p.unwrap()).collect();
            assert_eq!(pts.len(), n);
            let mut seen = vec![false; n];
            let mut index = std::collections::HashMap::new();
            for i in 0..n {
                let p = c.positions[i];
                let key = (
                    (p.x * 1e4).round() as i64,
                    (p.y * 1e4).round() as i64,
                    (p.z * 1e4).round() as i64,
                );
                index.insert(key, i);
            }
            for p in &pts {
                let key = (
                    (p.x * 1e4).round() as i64,
                    (p.y * 1e4).round() as i64,
                    (p.z * 1e4).round() as i64,
                );
                let i = index[&key];
                assert!(!seen[i]);
                seen[i] = true;
                let f = |k: usize| {
                    f32::from_le_bytes(p.extra_bytes[4 * k..4 * k + 4].try_into().unwrap())
                };
                assert_eq!(f(0), c.scalar("log_std_combined").unwrap()[i]);
                assert_eq!(f(1), c.scalar("submap").unwrap()[i]);
                assert_eq!(p.color.unwrap().red, (i % 256) as u16 * 257);
            }
            // Nothing left beside the output.
            let left: Vec<_> = std::fs::read_dir(dir.path())
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
                .filter(|n| n.starts_with('.'))
                .collect();
            assert!(left.is_empty(), "{left:?}");
        }
    }

    /// Nothing to write is a clear error, and no file appears.
    #[test]
    fn an_empty_cloud_is_refused_without_a_file() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("e.copc.laz");
        let c = PointCloud::from_positions(vec![DVec3::NAN]);
        let e = write_copc(CopcInput::Cloud(&c), &out, &CopcOptions::default()).unwrap_err();
        assert!(
            e.to_string().contains("no point with a finite position"),
            "{e}"
        );
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }
}
