//! Scanner ground truth: a point-cloud file as the reference of `silvr eval --gt` — E57 (every scan of the
//! file, each placed by its own pose, as survey scanners deliver them; the Oxford Spires ground truth is
//! E57), LAS/LAZ, PLY or PCD, recognised from the content — optionally moved into the map's frame by a
//! rigid transform (`--gt-transform`).
//!
//! Memory stays bounded for a 100 M-point scan: a file whose header counts more than
//! [`MAX_EXACT_POINTS`] is voxelised on the way in (per-voxel centroids accumulated in first-seen order,
//! exactly what [`PointCloud::voxel_downsample`] computes, at the evaluation's voxel size), so only one
//! point per voxel is ever held. Smaller files are read whole, so the protocol sees the very points a PLY
//! of the same scan would give (a test checks the numbers agree to 1e-6 m). E57 and LAS/LAZ go through
//! the well-kept `e57` and `las` (+ `laz`) crates; both are pure Rust.

use std::io::Read;
use std::path::Path;

use glam::{DMat4, DVec3};

use std::io::Seek;

use crate::ingest::pcd::{read_pcd, read_pcd_bytes};
use crate::pointcloud::{read_ply, read_ply_bytes, PointCloud, VoxelMap};

/// A seekable byte source (a file or bytes in memory) for the E57 reader.
trait ReadSeek: Read + Seek {}
impl<T: Read + Seek> ReadSeek for T {}

/// Above this many points (from the file's header) the scan is voxelised while it is read.
pub const MAX_EXACT_POINTS: u64 = 20_000_000;

/// The point-cloud formats a scan may come in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ScanFormat {
    E57,
    Las,
    Ply,
    Pcd,
}

/// Why a scan could not be read: the file and the problem.
#[derive(Debug, thiserror::Error)]
#[error("{file}: {reason}")]
pub struct ScanError {
    pub file: String,
    pub reason: String,
}

fn err(path: &Path, reason: impl Into<String>) -> ScanError {
    ScanError {
        file: path.display().to_string(),
        reason: reason.into(),
    }
}

fn detect_head(head: &[u8]) -> Option<ScanFormat> {
    if head.starts_with(b"ASTM-E57") {
        Some(ScanFormat::E57)
    } else if head.starts_with(b"LASF") {
        Some(ScanFormat::Las)
    } else if head.starts_with(b"ply") {
        Some(ScanFormat::Ply)
    } else if head.starts_with(b"#") || head.starts_with(b"VERSION") || head.starts_with(b"FIELDS")
    {
        Some(ScanFormat::Pcd)
    } else {
        None
    }
}

const NOT_A_CLOUD: &str =
    "not a point cloud this reads (E57, LAS/LAZ, PLY or PCD, recognised from the first bytes)";

/// Recognises a point-cloud file from its first bytes.
pub fn detect(path: &Path) -> Result<ScanFormat, ScanError> {
    let mut head = [0u8; 16];
    let mut f = std::fs::File::open(path).map_err(|e| err(path, e.to_string()))?;
    let mut n = 0;
    while n < head.len() {
        match f
            .read(&mut head[n..])
            .map_err(|e| err(path, e.to_string()))?
        {
            0 => break,
            k => n += k,
        }
    }
    detect_head(&head[..n]).ok_or_else(|| err(path, NOT_A_CLOUD))
}

/// Where a scan is read from.
#[derive(Clone, Copy)]
enum Input<'a> {
    File(&'a Path),
    /// Bytes in memory (the fuzz target), named for errors.
    Bytes(&'a [u8], &'a Path),
}

impl Input<'_> {
    fn name(&self) -> &Path {
        match self {
            Input::File(p) | Input::Bytes(_, p) => p,
        }
    }
}

/// [`read_scan`] over bytes in memory; `name` names them in errors. The fuzz target reads this way.
pub fn read_scan_bytes(
    bytes: &[u8],
    name: &Path,
    transform: Option<DMat4>,
    voxel: Option<f64>,
) -> Result<Scan, ScanError> {
    on_reader_stack(name, || {
        read_with(
            Input::Bytes(bytes, name),
            transform,
            voxel,
            MAX_EXACT_POINTS,
        )
    })
}

/// Stack of the thread a scan is read on: laz 0.13 decodes a point format 6+ GPS time by recursion
/// (`read_gps_time`), which corrupt data drives deep enough to overflow an 8 MiB main-thread stack (the
/// `scan_file` fuzz target's thirteenth find, a SIGSEGV). Reserved, not committed: pages are used only as
/// deep as the recursion goes.
const READER_STACK_BYTES: usize = 1 << 30;

/// Runs `f` on a thread with [`READER_STACK_BYTES`] of stack.
fn on_reader_stack<T: Send>(
    path: &Path,
    f: impl FnOnce() -> Result<T, ScanError> + Send,
) -> Result<T, ScanError> {
    std::thread::scope(|s| {
        let thread = std::thread::Builder::new()
            .name("scan-reader".into())
            .stack_size(READER_STACK_BYTES)
            .spawn_scoped(s, f)
            .map_err(|e| err(path, format!("cannot start the reader's thread: {e}")))?;
        thread
            .join()
            .unwrap_or_else(|payload| std::panic::resume_unwind(payload))
    })
}

/// Where read points go: kept all, or accumulated per voxel.
enum Sink {
    All(PointCloud, Vec<[u8; 3]>, bool),
    Voxels {
        inv: f64,
        slots: VoxelMap<usize>,
        sum: Vec<DVec3>,
        colour: Vec<[u64; 3]>,
        count: Vec<u32>,
        coloured: bool,
    },
}

impl Sink {
    fn new(voxel: Option<f64>, expected: u64, threshold: u64) -> Self {
        match voxel {
            Some(v) if expected > threshold && v > 0.0 => Sink::Voxels {
                inv: 1.0 / v,
                slots: VoxelMap::default(),
                sum: Vec::new(),
                colour: Vec::new(),
                count: Vec::new(),
                coloured: true,
            },
            _ => Sink::All(PointCloud::new(), Vec::new(), true),
        }
    }

    fn push(&mut self, p: DVec3, c: Option<[u8; 3]>) {
        if !p.is_finite() {
            return;
        }
        match self {
            Sink::All(cloud, colours, coloured) => {
                cloud.positions.push(p);
                *coloured &= c.is_some();
                if *coloured {
                    colours.push(c.unwrap_or_default());
                }
            }
            Sink::Voxels {
                inv,
                slots,
                sum,
                colour,
                count,
                coloured,
            } => {
                let next = sum.len();
                let s = *slots
                    .entry(crate::pointcloud::voxel_key(p, *inv))
                    .or_insert(next);
                if s == next {
                    sum.push(DVec3::ZERO);
                    colour.push([0; 3]);
                    count.push(0);
                }
                sum[s] += p;
                count[s] += 1;
                *coloured &= c.is_some();
                if let Some(c) = c {
                    for k in 0..3 {
                        colour[s][k] += c[k] as u64;
                    }
                }
            }
        }
    }

    fn finish(self) -> PointCloud {
        match self {
            Sink::All(mut cloud, colours, coloured) => {
                if coloured && colours.len() == cloud.len() && !cloud.is_empty() {
                    cloud.colors = Some(colours);
                }
                cloud
            }
            Sink::Voxels {
                sum,
                colour,
                count,
                coloured,
                ..
            } => {
                let mut cloud = PointCloud::from_positions(
                    sum.iter()
                        .zip(&count)
                        .map(|(s, &n)| *s / n as f64)
                        .collect(),
                );
                if coloured && !cloud.is_empty() {
                    cloud.colors = Some(
                        colour
                            .iter()
                            .zip(&count)
                            .map(|(c, &n)| c.map(|v| (v as f64 / n as f64).round() as u8))
                            .collect(),
                    );
                }
                cloud
            }
        }
    }
}

/// Checks what the `las`/`laz` crates would trust in a LAS/LAZ header, before they read it (both found by
/// the `scan_file` fuzz target): the point-record count times the record length must not overflow (las
/// 0.11 multiplies unchecked), and a LAZ file's chunk count must fit its point data, one byte a chunk at
/// least (laz 0.13 reserves the stated count: 2^32 chunks is 64 GiB and an abort).
fn check_las_header(r: &mut (impl Read + Seek)) -> Result<(), String> {
    let len = r
        .seek(std::io::SeekFrom::End(0))
        .map_err(|e| e.to_string())?;
    let mut at = |pos: u64, n: usize| -> Result<Option<Vec<u8>>, String> {
        if pos.checked_add(n as u64).is_none_or(|end| end > len) {
            return Ok(None);
        }
        r.seek(std::io::SeekFrom::Start(pos))
            .map_err(|e| e.to_string())?;
        let mut b = vec![0u8; n];
        r.read_exact(&mut b).map_err(|e| e.to_string())?;
        Ok(Some(b))
    };
    let Some(h) = at(0, 111)? else {
        return Ok(());
    };
    // The las crate computes the end of the point records as offset + count × record length without
    // overflow checks (a panic in a build with them): refuse counts whose product overflows.
    let data_offset = u32::from_le_bytes([h[96], h[97], h[98], h[99]]) as u64;
    let record_len = u16::from_le_bytes([h[105], h[106]]) as u64;
    let mut count = u32::from_le_bytes([h[107], h[108], h[109], h[110]]) as u64;
    // LAS 1.4 headers (by version, whatever their stated size) carry a 64-bit count too.
    if h[24] > 1 || h[25] >= 4 {
        if let Some(b) = at(247, 8)? {
            count = count.max(u64::from_le_bytes(b.try_into().unwrap_or([0; 8])));
        }
    }
    if count
        .checked_mul(record_len)
        .and_then(|b| b.checked_add(data_offset))
        .is_none()
    {
        return Err(format!(
            "the header's {count} point records of {record_len} bytes overflow (corrupt file)"
        ));
    }
    // Extended VLRs (LAS 1.4) state 64-bit lengths that the las crate reserves before reading (an
    // abort on ~8 EB; the fuzz target's sixth find): each must fit in the file.
    if h[24] > 1 || h[25] >= 4 {
        if let (Some(start), Some(n)) = (at(235, 8)?, at(243, 4)?) {
            let mut pos = u64::from_le_bytes(start.try_into().unwrap_or([0; 8]));
            let n = u32::from_le_bytes(n.try_into().unwrap_or([0; 4]));
            for i in 0..n.min((len / 60 + 1) as u32) {
                let Some(e) = at(pos, 60)? else { break };
                let body = u64::from_le_bytes(e[20..28].try_into().unwrap_or([0; 8]));
                let left = len.saturating_sub(pos + 60);
                if body > left {
                    return Err(format!(
                        "extended VLR {i} at byte {pos} states {body} bytes, but only {left} follow \
                         (corrupt file)"
                    ));
                }
                pos += 60 + body;
            }
        }
    }
    // Point data format byte: LASzip sets bit 7 (or 6) on compressed files.
    if h[104] & 0xc0 == 0 {
        return Ok(());
    }
    let data = data_offset;
    let Some(b) = at(data, 8)? else {
        return Ok(());
    };
    // As laz reads it: an offset not past the point data's start (-1 from a streaming compressor) means
    // the offset is in the file's last 8 bytes; none there either means no table (chunks read in turn).
    let mut table = i64::from_le_bytes(b.try_into().unwrap_or([0; 8]));
    if table <= data as i64 {
        if let Some(b) = at(len.saturating_sub(8), 8)? {
            table = i64::from_le_bytes(b.try_into().unwrap_or([0; 8]));
        }
    }
    let table = u64::try_from(table).ok().filter(|&t| t > data);
    let mut table_chunks = None;
    if let Some(b) = match table {
        Some(t) => at(t, 8)?,
        None => None,
    } {
        let chunks = u32::from_le_bytes([b[4], b[5], b[6], b[7]]) as u64;
        table_chunks = Some(chunks);
        let room = table.unwrap_or(0).saturating_sub(data + 8);
        if chunks > room {
            return Err(format!(
                "the LAZ chunk table claims {chunks} chunks in {room} bytes of point data (corrupt file)"
            ));
        }
    }
    // The las crate reads its version's fixed header, then any padding up to the stated header size: the
    // VLRs start after whichever is longer (a 1.4 file stating 256 bytes still has its VLRs at 375; the
    // fuzz target's seventh find hid its LASzip VLR from this check that way).
    let version_size = match (h[24], h[25]) {
        (1, 0..=2) => 227,
        (1, 3) => 235,
        _ => 375,
    };
    let header_size = (u16::from_le_bytes([h[94], h[95]]) as u64).max(version_size);
    let n_vlrs = u32::from_le_bytes([h[100], h[101], h[102], h[103]]);
    check_laz_layers(
        &mut at,
        LazLayout {
            header_size,
            n_vlrs,
            record_len,
            count,
            data,
            table_chunks,
            len,
        },
    )
}

/// What [`check_laz_layers`] needs of the header: where the VLRs start and how many, the point record's
/// length and count, where the point data starts, the chunk table's count where there is one, the file's
/// length.
struct LazLayout {
    header_size: u64,
    n_vlrs: u32,
    record_len: u64,
    count: u64,
    data: u64,
    table_chunks: Option<u64>,
    len: u64,
}

/// Layered (LAS 1.4, point formats 6–10) LAZ chunks state each layer's byte count, and laz 0.13 sizes its
/// buffer from it before reading (a 1 KB file reserved 4 GB; found by the `scan_file` fuzz target). Checks
/// the LASzip items against the point record, then walks the chunks (each one: the first point raw, a point
/// count, the layer sizes, the layers) and refuses any whose layers would run past the file.
fn check_laz_layers(
    at: &mut impl FnMut(u64, usize) -> Result<Option<Vec<u8>>, String>,
    f: LazLayout,
) -> Result<(), String> {
    let LazLayout {
        header_size,
        n_vlrs,
        record_len,
        count,
        data,
        table_chunks,
        len,
    } = f;
    // Find the LASzip VLR (user "laszip encoded", record 22204) among the header's VLRs.
    let mut pos = header_size;
    let mut vlr = None;
    // LASzip's compressor: 1 point-wise (one chunk, no chunk-table offset), 2 and 3 chunked.
    let mut compressor = 0u16;
    for _ in 0..n_vlrs.min(1 << 16) {
        let Some(v) = at(pos, 54)? else { break };
        let body_len = u16::from_le_bytes([v[20], v[21]]) as usize;
        let record = u16::from_le_bytes([v[18], v[19]]);
        if v[2..16].starts_with(b"laszip encoded") && record == 22204 {
            if let Some(body) = at(pos + 54, body_len)? {
                vlr = laz::LazVlr::from_buffer(&body).ok();
                if let [a, b, ..] = body[..] {
                    compressor = u16::from_le_bytes([a, b]);
                }
            }
            break;
        }
        pos += 54 + body_len as u64;
    }
    let Some(vlr) = vlr else { return Ok(()) };
    let (first_point, layers) = crate::copc::read::laz_item_layout(vlr.items())?;
    if first_point != record_len {
        return Err(format!(
            "the LASzip items make {first_point}-byte points, but the header's records are {record_len} \
             bytes (corrupt file)"
        ));
    }
    // Point-wise (pre-1.4) items have no layers.
    let Some(layers) = layers else {
        return Ok(());
    };
    // Every chunk laz may read, each within the file. laz reads chunks one after another (each starts
    // where the previous one's layers end) while points remain, and it bounds a chunk by the chunk size,
    // by the table's point counts or by the count inside the chunk, depending on the file. So the walk
    // goes on while any of those says more chunks follow: the chunk size's or the table's number of
    // chunks (at least one), and until the chunks' own counts add up to the header's. A consistent file
    // agrees on all three; an inconsistent one may be refused where laz would have read it. Finds of the
    // fuzz target: one-point chunks read on past the chunk table (9th), a table of no chunks (10th), a
    // point-wise file, whose one chunk starts without the table's offset (11th).
    let point_wise = compressor == 1;
    let by_rule = if point_wise {
        1
    } else if vlr.uses_variable_size_chunks() {
        table_chunks.unwrap_or(0)
    } else {
        count.div_ceil(u64::from(vlr.chunk_size().max(1)))
    }
    .max(u64::from(count > 0));
    let head = first_point + 4 + 4 * layers;
    let mut chunk_at = if point_wise { data } else { data + 8 };
    let mut points = 0u64;
    let mut index = 0u64;
    while index < by_rule || points < count {
        let Some(b) = at(chunk_at + first_point, 4 + 4 * layers as usize)? else {
            break;
        };
        let in_chunk = u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as u64;
        let sizes: u64 = b[4..]
            .chunks_exact(4)
            .map(|s| u32::from_le_bytes([s[0], s[1], s[2], s[3]]) as u64)
            .sum();
        let left = len.saturating_sub(chunk_at + head);
        if sizes > left {
            return Err(format!(
                "LAZ chunk {index} at byte {chunk_at} states {sizes} bytes of layers, but only {left} \
                 bytes of the file follow (corrupt file)"
            ));
        }
        chunk_at += head + sizes;
        points = points.saturating_add(in_chunk.max(1));
        index += 1;
    }
    Ok(())
}

/// Runs a third-party reader's `f`, turning its panic (the las and laz crates panic on some corrupt files)
/// into an error naming the file and what was being done.
fn caught<T>(path: &Path, doing: &str, f: impl FnOnce() -> T) -> Result<T, ScanError> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).map_err(|payload| {
        let detail = crate::ingest::container::panic_message(payload.as_ref());
        err(
            path,
            format!("corrupt LAS/LAZ data: the reader failed {doing} ({detail})"),
        )
    })
}

/// What was read: the cloud (in the map's frame when a transform was given) and notes for the report.
pub struct Scan {
    pub cloud: PointCloud,
    pub format: ScanFormat,
    /// Points in the file (before voxelising).
    pub points_read: u64,
    pub notes: Vec<String>,
}

/// Reads a scan, applies `transform` (`T_map_scan`) to every point, and voxelises it on the way in at
/// `voxel` when the file holds more than [`MAX_EXACT_POINTS`].
pub fn read_scan(
    path: &Path,
    transform: Option<DMat4>,
    voxel: Option<f64>,
) -> Result<Scan, ScanError> {
    on_reader_stack(path, || {
        read_with(Input::File(path), transform, voxel, MAX_EXACT_POINTS)
    })
}

/// The streaming voxeliser [`read_scan`] uses beyond [`MAX_EXACT_POINTS`], whatever the file's size (for
/// tests and benchmarks: it equals reading everything and [`PointCloud::voxel_downsample`]).
pub fn voxelise_while_reading(
    path: &Path,
    transform: Option<DMat4>,
    voxel: f64,
) -> Result<PointCloud, ScanError> {
    let s = read_with(Input::File(path), transform, Some(voxel), 0)?;
    Ok(match s.format {
        ScanFormat::E57 | ScanFormat::Las => s.cloud,
        ScanFormat::Ply | ScanFormat::Pcd => s.cloud.voxel_downsample(voxel),
    })
}

fn read_with(
    input: Input,
    transform: Option<DMat4>,
    voxel: Option<f64>,
    threshold: u64,
) -> Result<Scan, ScanError> {
    let path = input.name();
    let format = match input {
        Input::File(p) => detect(p)?,
        Input::Bytes(b, p) => {
            detect_head(&b[..b.len().min(16)]).ok_or_else(|| err(p, NOT_A_CLOUD))?
        }
    };
    let t = transform.unwrap_or(DMat4::IDENTITY);
    let mut notes = Vec::new();
    let mut read = 0u64;
    let cloud = match format {
        ScanFormat::E57 => {
            let mut r: e57::E57Reader<Box<dyn ReadSeek>> = match input {
                Input::File(p) => {
                    let f = std::fs::File::open(p).map_err(|e| err(p, e.to_string()))?;
                    e57::E57Reader::new(Box::new(std::io::BufReader::new(f)) as Box<dyn ReadSeek>)
                }
                Input::Bytes(b, _) => e57::E57Reader::new(
                    Box::new(std::io::Cursor::new(b.to_vec())) as Box<dyn ReadSeek>,
                ),
            }
            .map_err(|e| err(path, e.to_string()))?;
            let clouds = r.pointclouds();
            let total: u64 = clouds.iter().map(|c| c.records).sum();
            let mut sink = Sink::new(voxel, total, threshold);
            for (i, pc) in clouds.iter().enumerate() {
                let mut it = r
                    .pointcloud_simple(pc)
                    .map_err(|e| err(path, format!("scan {i}: {e}")))?;
                // Every scan in the file's frame (its pose applied), spherical scans as Cartesian,
                // colours in 0..1.
                it.apply_pose(true);
                it.spherical_to_cartesian(true);
                it.normalize_color(true);
                for p in it {
                    let p = p.map_err(|e| err(path, format!("scan {i}: {e}")))?;
                    read += 1;
                    if let e57::CartesianCoordinate::Valid { x, y, z } = p.cartesian {
                        let c = p.color.map(|c| {
                            [c.red, c.green, c.blue]
                                .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
                        });
                        sink.push(t.transform_point3(DVec3::new(x, y, z)), c);
                    }
                }
            }
            notes.push(format!(
                "ground truth: {} scan(s) of an E57 file, each placed by its pose",
                clouds.len()
            ));
            sink.finish()
        }
        ScanFormat::Las => {
            match input {
                Input::File(p) => {
                    let mut f = std::fs::File::open(p).map_err(|e| err(p, e.to_string()))?;
                    check_las_header(&mut f)
                }
                Input::Bytes(b, _) => check_las_header(&mut std::io::Cursor::new(b)),
            }
            .map_err(|e| err(path, e))?;
            let mut r = caught(path, "reading the header", || match input {
                Input::File(p) => las::Reader::from_path(p),
                Input::Bytes(b, _) => las::Reader::new(std::io::Cursor::new(b.to_vec())),
            })?
            .map_err(|e| err(path, e.to_string()))?;
            let total = r.header().number_of_points();
            let mut sink = Sink::new(voxel, total, threshold);
            let mut batch = las::PointDataBuilder::new().for_header(r.header()).build();
            // Batches of at most 16 MiB: the record length comes from the file (up to 64 KiB a point).
            let per_batch = ((16u64 << 20) / batch.record_len().max(1) as u64).clamp(1, 1 << 16);
            loop {
                // The LAZ decoder panics on some corrupt arithmetic-coded data (an index out of bounds;
                // laz-rs issue #43, open): caught and reported like its errors.
                let n = caught(path, &format!("decoding after {read} points"), || {
                    r.fill_points(per_batch, &mut batch)
                })?
                .map_err(|e| err(path, e.to_string()))?;
                if n == 0 {
                    break;
                }
                for p in batch.points() {
                    let p = p.map_err(|e| err(path, e.to_string()))?;
                    read += 1;
                    let c = p
                        .color
                        .map(|c| [c.red, c.green, c.blue].map(|v| (v >> 8) as u8));
                    sink.push(t.transform_point3(DVec3::new(p.x, p.y, p.z)), c);
                }
            }
            sink.finish()
        }
        ScanFormat::Ply | ScanFormat::Pcd => {
            let name = path.display().to_string();
            let mut cloud = if format == ScanFormat::Ply {
                match input {
                    Input::File(p) => read_ply(p),
                    Input::Bytes(b, _) => read_ply_bytes(b, &name),
                }
                .map_err(|e| err(path, e.to_string()))?
            } else {
                let pcd = match input {
                    Input::File(p) => read_pcd(p),
                    Input::Bytes(b, _) => read_pcd_bytes(b, &name),
                }
                .map_err(|e| err(path, e.to_string()))?;
                // A PCD's VIEWPOINT places the scan (the Oxford Spires GT convention).
                let vp = pcd.viewpoint;
                let mut c = pcd.cloud;
                for p in &mut c.positions {
                    *p = vp.transform_point(*p);
                }
                c
            };
            read = cloud.len() as u64;
            for p in &mut cloud.positions {
                *p = t.transform_point3(*p);
            }
            let keep: Vec<usize> = (0..cloud.len())
                .filter(|&i| cloud.positions[i].is_finite())
                .collect();
            if keep.len() < cloud.len() {
                cloud = cloud.select(&keep);
            }
            cloud
        }
    };
    if let (Some(v), true) = (
        voxel,
        read > threshold && matches!(format, ScanFormat::E57 | ScanFormat::Las),
    ) {
        notes.push(format!(
            "ground truth voxelised to {v} m while read ({read} points in the file, {} kept)",
            cloud.len()
        ));
    }
    if transform.is_some() {
        notes.push("ground truth moved into the map's frame by --gt-transform".into());
    }
    Ok(Scan {
        cloud,
        format,
        points_read: read,
        notes,
    })
}

/// Reads a LAS/LAZ file (COPC included) in chunks of at most `per_chunk` points with positions, colours
/// (8-bit) and every numeric extra-bytes dimension as a scalar, and hands each chunk to `f` (on the
/// reader's thread). The file is checked as [`read_scan`] checks it, and a reader panic is an error.
/// Returns the scalars' names.
pub fn read_las_chunks(
    path: &Path,
    per_chunk: usize,
    f: &mut (dyn FnMut(&PointCloud) -> Result<(), String> + Send),
) -> Result<Vec<String>, ScanError> {
    on_reader_stack(path, || {
        let mut file = std::fs::File::open(path).map_err(|e| err(path, e.to_string()))?;
        check_las_header(&mut file).map_err(|e| err(path, e))?;
        let mut r = caught(path, "reading the header", || las::Reader::from_path(path))?
            .map_err(|e| err(path, e.to_string()))?;
        let extra_bytes = r.header().point_format().extra_bytes as usize;
        let dims = r
            .header()
            .all_vlrs()
            .find(|v| v.user_id == "LASF_Spec" && v.record_id == 4)
            .map_or_else(Vec::new, |v| {
                crate::copc::extra_bytes::descriptors(&v.data, extra_bytes)
            });
        let names: Vec<String> = dims.iter().map(|d| d.name.clone()).collect();
        let mut batch = las::PointDataBuilder::new().for_header(r.header()).build();
        let per_batch = ((16u64 << 20) / batch.record_len().max(1) as u64).clamp(1, 1 << 16);
        let mut chunk = PointCloud::new();
        let mut read = 0u64;
        let flush =
            |chunk: &mut PointCloud,
             f: &mut (dyn FnMut(&PointCloud) -> Result<(), String> + Send)| {
                let out = f(chunk).map_err(|e| err(path, e));
                *chunk = PointCloud::new();
                out
            };
        loop {
            let n = caught(path, &format!("decoding after {read} points"), || {
                r.fill_points(per_batch, &mut batch)
            })?
            .map_err(|e| err(path, e.to_string()))?;
            if n == 0 {
                break;
            }
            for p in batch.points() {
                let p = p.map_err(|e| err(path, e.to_string()))?;
                read += 1;
                if chunk.is_empty() {
                    chunk.colors = Some(Vec::new());
                    chunk.scalars = names.iter().map(|n| (n.clone(), Vec::new())).collect();
                }
                let c = p
                    .color
                    .map_or([0; 3], |c| [c.red, c.green, c.blue].map(|v| (v >> 8) as u8));
                // `push_colored` pads every scalar with NaN; the values then replace the padding.
                chunk.push_colored(DVec3::new(p.x, p.y, p.z), c);
                if p.extra_bytes.len() >= extra_bytes {
                    for (d, (_, v)) in dims.iter().zip(&mut chunk.scalars) {
                        if let Some(last) = v.last_mut() {
                            *last = d.value(&p.extra_bytes);
                        }
                    }
                }
                if chunk.len() >= per_chunk.max(1) {
                    flush(&mut chunk, f)?;
                }
            }
        }
        if !chunk.is_empty() {
            flush(&mut chunk, f)?;
        }
        Ok(names)
    })
}

/// Parses `--gt-transform`: 16 numbers (a row-major 4×4, `T_map_scan`) or a TUM line (`[t] x y z qx qy qz
/// qw`, 7 or 8 numbers).
pub fn parse_transform(text: &str) -> Result<DMat4, String> {
    let v: Vec<f64> = text
        .split(|c: char| c.is_whitespace() || c == ',')
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<f64>()
                .map_err(|_| format!("'{s}' is not a number"))
        })
        .collect::<Result<_, _>>()?;
    if v.iter().any(|x| !x.is_finite()) {
        return Err("the transform has a non-finite number".into());
    }
    let m = match v.len() {
        16 => {
            let m = DMat4::from_cols_array(&[
                v[0], v[4], v[8], v[12], v[1], v[5], v[9], v[13], v[2], v[6], v[10], v[14], v[3], v[7],
                v[11], v[15],
            ]);
            if (m.row(3) - glam::DVec4::new(0.0, 0.0, 0.0, 1.0)).length() > 1e-9 {
                return Err("the 4x4's last row must be 0 0 0 1".into());
            }
            m
        }
        7 | 8 => {
            let o = v.len() - 7;
            let q = glam::DQuat::from_xyzw(v[o + 3], v[o + 4], v[o + 5], v[o + 6]);
            if (q.length() - 1.0).abs() > 1e-3 {
                return Err(format!("the quaternion's norm is {}, not 1", q.length()));
            }
            DMat4::from_rotation_translation(q.normalize(), DVec3::new(v[o], v[o + 1], v[o + 2]))
        }
        n => {
            return Err(format!(
                "{n} numbers: a 4x4 matrix (16, row-major) or a TUM pose (x y z qx qy qz qw, optionally after a time) is expected"
            ))
        }
    };
    Ok(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transforms_parse_from_a_matrix_or_a_tum_line() {
        let m = parse_transform("1 0 0 2  0 1 0 3  0 0 1 4  0 0 0 1").unwrap();
        assert_eq!(m.transform_point3(DVec3::ZERO), DVec3::new(2.0, 3.0, 4.0));
        let t = parse_transform("0.5 1 2 3 0 0 0.7071067811865476 0.7071067811865476").unwrap();
        let p = t.transform_point3(DVec3::X);
        assert!((p - DVec3::new(1.0, 3.0, 3.0)).length() < 1e-12, "{p}");
        assert!(parse_transform("1 2 3").is_err());
        assert!(parse_transform("1 0 0 0 0 1 0 0 0 0 1 0 1 0 0 1").is_err());
        assert!(parse_transform("0 0 0 0 0 0 2").is_err());
        assert!(parse_transform("0 0 0 nan 0 0 1").is_err());
    }
}
