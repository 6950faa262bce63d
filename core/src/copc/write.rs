//! Writing COPC in bounded memory. Two passes over the map (a PLY on disk read in chunks, or a cloud already
//! in memory): the first sums up the [`CopcSummary`]; the second streams the points into a temporary
//! LAS 1.4 that carries our extra-bytes and summary VLRs, which `copc-writer` orders into the octree
//! through spill files on disk, keeping our VLRs. Memory: one chunk of points, the filter field's column
//! (4 bytes a point) and what `copc-writer` holds per octree level; disk: the temporary LAS and the spill
//! files beside the output, both removed at the end. The output appears under its name only when whole.

use std::path::{Path, PathBuf};

use glam::DVec3;

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

/// The cloud's points bucketed on disk by the leading bits of their Morton code (the octree's cube at
/// 2^21 cells an axis), then each bucket sorted in memory: an external sort by Morton code with one pass
/// over the points on each side. A bucket larger than [`MORTON_BUCKET_POINTS`] (a cloud crowded into one
/// corner) is split again on its next bits, so memory stays bounded whatever the distribution.
struct MortonBuckets {
    dir: PathBuf,
    lo: DVec3,
    cells_per_metre: f64,
    fields: usize,
    writers: Vec<Option<std::io::BufWriter<std::fs::File>>>,
    counts: Vec<u64>,
    /// Splits so far (their files' names' prefix).
    depth: u32,
    /// The most points sorted in memory at once ([`MORTON_BUCKET_POINTS`]; less in tests).
    max_in_memory: u64,
}

/// Bits of the Morton code the first split uses (256 bucket files open at once).
const MORTON_BUCKET_BITS: u32 = 8;
/// The most points sorted in memory at once (about 60 bytes each with a few fields).
const MORTON_BUCKET_POINTS: u64 = 4 << 20;
const MORTON_AXIS_BITS: u32 = 21;

/// Spreads the low 21 bits of `v` to every third bit.
fn spread3(v: u64) -> u64 {
    let mut x = v & 0x1f_ffff;
    x = (x | x << 32) & 0x1f00000000ffff;
    x = (x | x << 16) & 0x1f0000ff0000ff;
    x = (x | x << 8) & 0x100f00f00f00f00f;
    x = (x | x << 4) & 0x10c30c30c30c30c3;
    (x | x << 2) & 0x1249249249249249
}

impl MortonBuckets {
    fn new(dir: &Path, lo: DVec3, hi: DVec3, fields: usize) -> std::io::Result<Self> {
        let edge = (hi - lo).max_element().max(1e-9);
        Ok(Self {
            dir: dir.join("morton"),
            lo,
            cells_per_metre: ((1u64 << MORTON_AXIS_BITS) - 1) as f64 / edge,
            fields,
            writers: (0..1usize << MORTON_BUCKET_BITS).map(|_| None).collect(),
            counts: vec![0; 1 << MORTON_BUCKET_BITS],
            depth: 0,
            max_in_memory: MORTON_BUCKET_POINTS,
        })
        .and_then(|b| std::fs::create_dir_all(&b.dir).map(|_| b))
    }

    fn record_len(&self) -> usize {
        8 + 24 + 3 + 4 * self.fields
    }

    fn code(&self, p: DVec3) -> u64 {
        let q = ((p - self.lo) * self.cells_per_metre).round();
        let axis = |v: f64| (v.max(0.0) as u64).min((1 << MORTON_AXIS_BITS) - 1);
        spread3(axis(q.x)) | spread3(axis(q.y)) << 1 | spread3(axis(q.z)) << 2
    }

    fn bucket_path(&self, prefix: &str, b: usize) -> PathBuf {
        self.dir.join(format!("{prefix}{b:03}"))
    }

    /// Appends `c`'s finite points (its scalars in `names`' order, NaN where it lacks one).
    fn push(&mut self, c: &PointCloud, names: &[String]) -> std::io::Result<()> {
        use std::io::Write;
        let columns: Vec<Option<&[f32]>> = names
            .iter()
            .map(|n| c.scalar(n).filter(|v| v.len() == c.len()))
            .collect();
        let colours = c.colors.as_ref().filter(|v| v.len() == c.len());
        let mut rec = Vec::with_capacity(self.record_len());
        for (i, p) in c.positions.iter().enumerate() {
            if !p.is_finite() {
                continue;
            }
            let code = self.code(*p);
            let b = (code >> (3 * MORTON_AXIS_BITS - MORTON_BUCKET_BITS)) as usize;
            rec.clear();
            rec.extend_from_slice(&code.to_le_bytes());
            for v in [p.x, p.y, p.z] {
                rec.extend_from_slice(&v.to_le_bytes());
            }
            rec.extend_from_slice(&colours.map_or([0; 3], |c| c[i]));
            for col in &columns {
                rec.extend_from_slice(&col.map_or(f32::NAN, |v| v[i]).to_le_bytes());
            }
            if self.writers[b].is_none() {
                let f = std::fs::File::create(self.bucket_path("b", b))?;
                self.writers[b] = Some(std::io::BufWriter::with_capacity(1 << 16, f));
            }
            if let Some(w) = &mut self.writers[b] {
                w.write_all(&rec)?;
            }
            self.counts[b] += 1;
        }
        Ok(())
    }

    /// Hands every point to `f` in Morton order, in chunks, removing the bucket files as it goes.
    fn drain(
        mut self,
        names: &[String],
        f: &mut dyn FnMut(&PointCloud) -> Result<(), String>,
    ) -> Result<(), String> {
        use std::io::Write;
        for w in self.writers.iter_mut().flatten() {
            w.flush().map_err(|e| e.to_string())?;
        }
        self.writers.clear();
        let files: Vec<(PathBuf, u64)> = (0..self.counts.len())
            .filter(|&b| self.counts[b] > 0)
            .map(|b| (self.bucket_path("b", b), self.counts[b]))
            .collect();
        for (path, count) in files {
            self.drain_file(&path, count, MORTON_BUCKET_BITS, names, f)?;
        }
        let _ = std::fs::remove_dir(&self.dir);
        Ok(())
    }

    /// One bucket file whose codes share their first `used` bits: sorted in memory when small enough,
    /// else split on its next bits.
    fn drain_file(
        &mut self,
        path: &Path,
        count: u64,
        used: u32,
        names: &[String],
        f: &mut dyn FnMut(&PointCloud) -> Result<(), String>,
    ) -> Result<(), String> {
        use std::io::{Read, Write};
        let n = self.record_len();
        let io = |e: std::io::Error| format!("{}: {e}", path.display());
        if count > self.max_in_memory && used < 3 * MORTON_AXIS_BITS {
            let bits = MORTON_BUCKET_BITS.min(3 * MORTON_AXIS_BITS - used);
            self.depth += 1;
            let prefix = format!("d{}-", self.depth);
            let mut writers: Vec<Option<std::io::BufWriter<std::fs::File>>> =
                (0..1usize << bits).map(|_| None).collect();
            let mut counts = vec![0u64; 1 << bits];
            let mut r =
                std::io::BufReader::with_capacity(1 << 16, std::fs::File::open(path).map_err(io)?);
            let mut rec = vec![0u8; n];
            for _ in 0..count {
                r.read_exact(&mut rec).map_err(io)?;
                let code = u64::from_le_bytes(rec[..8].try_into().unwrap_or([0; 8]));
                let b = ((code << (used + 1)) >> (64 - bits)) as usize;
                if writers[b].is_none() {
                    let f = std::fs::File::create(self.bucket_path(&prefix, b)).map_err(io)?;
                    writers[b] = Some(std::io::BufWriter::with_capacity(1 << 16, f));
                }
                if let Some(w) = &mut writers[b] {
                    w.write_all(&rec).map_err(io)?;
                }
                counts[b] += 1;
            }
            drop(r);
            let _ = std::fs::remove_file(path);
            for w in writers.iter_mut().flatten() {
                w.flush().map_err(io)?;
            }
            drop(writers);
            for (b, &c) in counts.iter().enumerate() {
                if c > 0 {
                    let sub = self.bucket_path(&prefix, b);
                    self.drain_file(&sub, c, used + bits, names, f)?;
                }
            }
            return Ok(());
        }
        // Small enough (or every code equal): sort here.
        let mut bytes = Vec::new();
        std::fs::File::open(path)
            .and_then(|mut file| file.read_to_end(&mut bytes))
            .map_err(io)?;
        let _ = std::fs::remove_file(path);
        let mut order: Vec<(u64, u32)> = bytes
            .chunks_exact(n)
            .enumerate()
            .map(|(i, r)| {
                (
                    u64::from_le_bytes(r[..8].try_into().unwrap_or([0; 8])),
                    i as u32,
                )
            })
            .collect();
        order.sort_unstable();
        for part in order.chunks(CHUNK_POINTS) {
            let mut c = PointCloud::new();
            c.colors = Some(Vec::with_capacity(part.len()));
            let mut cols: Vec<Vec<f32>> = vec![Vec::with_capacity(part.len()); self.fields];
            for &(_, i) in part {
                let r = &bytes[i as usize * n..(i as usize + 1) * n];
                let f64_at =
                    |k: usize| f64::from_le_bytes(r[k..k + 8].try_into().unwrap_or([0; 8]));
                c.positions
                    .push(DVec3::new(f64_at(8), f64_at(16), f64_at(24)));
                if let Some(cs) = &mut c.colors {
                    cs.push([r[32], r[33], r[34]]);
                }
                for (k, col) in cols.iter_mut().enumerate() {
                    let at = 35 + 4 * k;
                    col.push(f32::from_le_bytes(
                        r[at..at + 4].try_into().unwrap_or([0; 4]),
                    ));
                }
            }
            for (name, col) in names.iter().zip(cols) {
                c.set_scalar(name, col);
            }
            f(&c)?;
        }
        Ok(())
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
    // The points go to the LAS in Morton order of the octree's cube: copc-writer's build reads its spill
    // file by point index node after node, which on a cloud in arbitrary order is a random read of the
    // whole file at every level (a 100 M-point cloud capped at 4 GB thrashed: 1.6 TB read in 15 minutes).
    // In Morton order each node's points lie together.
    let mut order =
        MortonBuckets::new(work.path(), lo, hi, names.len()).map_err(|e| error(out, e))?;
    chunks(&input, &mut |c| {
        order.push(c, &names).map_err(|e| error(out, e))
    })?;
    order
        .drain(&names, &mut |c| sink.push(c).map_err(|e| e.to_string()))
        .map_err(|e| error(out, e))?;
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
    // copc-writer creates its output private (0600); a map is meant to be served and shared.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&partial, std::fs::Permissions::from_mode(0o644))
            .map_err(|e| error(out, e))?;
    }
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
            #[cfg(unix)]
            {
                use std::os::unix::fs::PermissionsExt;
                let mode = std::fs::metadata(&out).unwrap().permissions().mode();
                assert_eq!(
                    mode & 0o044,
                    0o044,
                    "readable by others, as any export: {mode:o}"
                );
            }
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
            // Our own range reader (the studio's) decodes the same points, colours and fields.
            let (head, nodes) = super::super::read::read_file(&out).unwrap();
            assert_eq!(head.points, n as u64);
            assert_eq!(head.field_names(), ["log_std_combined", "submap"]);
            assert_eq!(head.summary.as_ref(), Some(&w.summary));
            assert!(nodes.len() > 1, "{} nodes", nodes.len());
            let mut seen = vec![false; n];
            for (_, pts) in &nodes {
                for (k, q) in pts.positions.iter().enumerate() {
                    let p = head.center() + DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64);
                    let key = (
                        (p.x * 1e4).round() as i64,
                        (p.y * 1e4).round() as i64,
                        (p.z * 1e4).round() as i64,
                    );
                    let i = index[&key];
                    assert!(!seen[i]);
                    seen[i] = true;
                    assert_eq!(pts.scalars[0][k], c.scalar("log_std_combined").unwrap()[i]);
                    assert_eq!(pts.scalars[1][k], c.scalar("submap").unwrap()[i]);
                    assert_eq!(pts.colors.as_ref().unwrap()[k], [(i % 256) as u8, 7, 200]);
                }
            }
            assert!(seen.iter().all(|&s| s));
            // Nothing left beside the output.
            let left: Vec<_> = std::fs::read_dir(dir.path())
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
                .filter(|n| n.starts_with('.'))
                .collect();
            assert!(left.is_empty(), "{left:?}");
        }
    }

    /// The Morton stage hands back every point once, with its colour and fields, in non-decreasing Morton
    /// order, also when buckets are split again (a bound of 100 points in memory; 200 of the 5,000 points
    /// crowded into one corner cell, so splits go several levels deep); and leaves no file behind.
    #[test]
    fn morton_buckets_sort_every_point_in_bounded_memory() {
        assert_eq!(spread3(0b101), 0b1_000_001);
        assert_eq!(spread3(0x1f_ffff).count_ones(), 21);
        let dir = tempfile::tempdir().unwrap();
        let mut c = PointCloud::new();
        for i in 0..5000u32 {
            let t = i as f64;
            let p = if i < 200 {
                DVec3::new(1e-7 * t, 0.0, 0.0)
            } else {
                DVec3::new(
                    (t * 0.618_033_988_7).fract() * 50.0,
                    (t * std::f64::consts::SQRT_2).fract() * 30.0,
                    (t * std::f64::consts::E).fract() * 8.0,
                )
            };
            c.push_colored(p, [(i % 256) as u8, (i / 256) as u8, 1]);
        }
        c.set_scalar("id", (0..5000).map(|i| i as f32).collect());
        let names = vec!["id".to_string()];
        let (lo, hi) = finite_bounds(&c).unwrap();
        let mut m = MortonBuckets::new(dir.path(), lo, hi, 1).unwrap();
        m.max_in_memory = 100;
        for part in [0..2500, 2500..5000] {
            let mut chunk = PointCloud::new();
            for i in part.clone() {
                chunk.push_colored(c.positions[i], c.colors.as_ref().unwrap()[i]);
            }
            chunk.set_scalar("id", part.map(|i| i as f32).collect());
            m.push(&chunk, &names).unwrap();
        }
        let probe = MortonBuckets::new(dir.path(), lo, hi, 1).unwrap();
        let mut seen = vec![false; 5000];
        let mut last = 0u64;
        let mut chunks = 0;
        m.drain(&names, &mut |ch| {
            chunks += 1;
            for (k, p) in ch.positions.iter().enumerate() {
                let id = ch.scalar("id").unwrap()[k] as usize;
                assert!(
                    !seen[id],
                    "point {id} twice (chunk {chunks}, {} points)",
                    ch.len()
                );
                seen[id] = true;
                assert_eq!(*p, c.positions[id]);
                assert_eq!(
                    ch.colors.as_ref().unwrap()[k],
                    c.colors.as_ref().unwrap()[id]
                );
                let code = probe.code(*p);
                assert!(code >= last, "out of Morton order at point {id}");
                last = code;
            }
            Ok(())
        })
        .unwrap();
        assert!(seen.iter().all(|&s| s));
        assert!(chunks > 1);
        let left: Vec<_> = std::fs::read_dir(dir.path().join("morton"))
            .map(|d| d.map(|e| e.unwrap().file_name()).collect())
            .unwrap_or_default();
        assert!(left.is_empty(), "{left:?}");
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
