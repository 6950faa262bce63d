//! Reading COPC by byte ranges: the head (LAS header and VLRs), the hierarchy pages, and one octree node's
//! points. Bytes in, structures out, no I/O: the studio's worker fetches ranges over HTTP (asynchronously)
//! and the CLI reads a file, and both hand the bytes here. Everything read from the file is bounded before
//! it sizes an allocation (the file is untrusted: a dropped file or a shared link).
//!
//! The order a reader follows: [`head_len`] on the file's first [`LAS_HEADER_BYTES`] bytes, [`parse_head`]
//! on that many, [`parse_page`] on the root hierarchy page ([`CopcHead::root_page`]) and on the child pages
//! it names, then [`decode_node`] on the bytes of each node it wants.

use std::io::Cursor;

/// The hierarchy's types (copc-core's), for the readers above this module.
pub use copc_core::{CopcInfo, Entry, VoxelKey};
use copc_core::{EntryAvailability, HierarchyPage};
use glam::DVec3;
use laz::record::{LayeredPointRecordDecompressor, RecordDecompressor};

use super::extra_bytes::{self, ExtraDim};
use super::{CopcSummary, SUMMARY_RECORD_ID, SUMMARY_USER_ID};

/// The LAS 1.4 header's size: what a reader fetches first.
pub const LAS_HEADER_BYTES: usize = 375;
/// The header and VLRs we accept before the point data (ours take a few KB; a CRS as WKT a few more).
pub const MAX_HEAD_BYTES: u64 = 4 << 20;
/// One hierarchy page: 32 bytes an entry, so a million entries.
pub const MAX_PAGE_BYTES: u64 = 32 << 20;
/// A whole hierarchy: pages and entries (a 100 M-point map at 100 k points a node has ~2,000 nodes).
pub const MAX_PAGES: usize = 1 << 16;
pub const MAX_ENTRIES: usize = 4 << 20;
/// One node: points and compressed bytes (copc-writer puts 100 k points in a node, PDAL about as many).
pub const MAX_NODE_POINTS: u32 = 4 << 20;
pub const MAX_NODE_BYTES: u64 = 256 << 20;
/// What one decoded node may take in memory (positions, colours and every field's values).
pub const MAX_NODE_DECODED_BYTES: u64 = 512 << 20;

/// What went wrong, and in which file or link.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{source_name}: {message}")]
pub struct CopcReadError {
    pub source_name: String,
    pub message: String,
}

fn fail(source: &str, message: impl std::fmt::Display) -> CopcReadError {
    CopcReadError {
        source_name: source.to_string(),
        message: message.to_string(),
    }
}

/// A byte range of the file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Range {
    pub offset: u64,
    pub size: u64,
}

/// What the head of a COPC file says: enough to read its hierarchy and decode its nodes.
#[derive(Clone, Debug)]
pub struct CopcHead {
    /// Points in the file (the header's 64-bit count).
    pub points: u64,
    /// 6, 7 or 8 (COPC's formats); 7 and 8 carry RGB.
    pub point_format: u8,
    /// Bytes a point record takes, the extra bytes included.
    pub record_length: usize,
    /// Where the extra bytes start in a record.
    pub extra_at: usize,
    pub scale: DVec3,
    pub offset: DVec3,
    /// The header's bounds of the points.
    pub min: DVec3,
    pub max: DVec3,
    /// The octree's root cube and the root hierarchy page.
    pub info: CopcInfo,
    /// How the points are compressed, and the number of layers a chunk's header sizes.
    pub laz: laz::LazVlr,
    pub layers: u64,
    /// The numeric extra dimensions (our `log_std_*`, `submap`, …), in the file's order.
    pub extra: Vec<ExtraDim>,
    /// Our whole-cloud summary, when the file has one (a file another tool wrote does not).
    pub summary: Option<CopcSummary>,
}

/// How many bytes from the file's start [`parse_head`] needs (the header and every VLR), from the first
/// [`LAS_HEADER_BYTES`] (or more) of them.
pub fn head_len(first: &[u8], source: &str) -> Result<u64, CopcReadError> {
    let h = las::raw::Header::read_from(Cursor::new(first))
        .map_err(|e| fail(source, format!("not a LAS file: {e}")))?;
    let end = h.offset_to_point_data as u64;
    if end < LAS_HEADER_BYTES as u64 || end > MAX_HEAD_BYTES {
        return Err(fail(
            source,
            format!(
                "the point data starts at byte {end}: a COPC file's header and VLRs take {LAS_HEADER_BYTES} \
                 to {MAX_HEAD_BYTES} bytes"
            ),
        ));
    }
    Ok(end)
}

/// Parses the head: `bytes` from the file's start, at least [`head_len`] of them.
pub fn parse_head(bytes: &[u8], source: &str) -> Result<CopcHead, CopcReadError> {
    let end = head_len(bytes, source)?;
    if (bytes.len() as u64) < end {
        return Err(fail(
            source,
            format!("the head takes {end} bytes, {} were read", bytes.len()),
        ));
    }
    let mut cur = Cursor::new(&bytes[..end as usize]);
    let h = las::raw::Header::read_from(&mut cur)
        .map_err(|e| fail(source, format!("not a LAS file: {e}")))?;
    if (h.version.major, h.version.minor) != (1, 4) {
        return Err(fail(
            source,
            format!(
                "LAS {}.{}: COPC is LAS 1.4",
                h.version.major, h.version.minor
            ),
        ));
    }
    let compressed = h.point_data_record_format & 0x80 != 0;
    let point_format = h.point_data_record_format & 0x3f;
    let base = match point_format {
        6 => 30,
        7 => 36,
        8 => 38,
        f => {
            return Err(fail(
                source,
                format!("point format {f}: COPC uses formats 6, 7 and 8"),
            ))
        }
    };
    if !compressed {
        return Err(fail(source, "the points are not compressed (not LAZ)"));
    }
    let record_length = h.point_data_record_length as usize;
    if record_length < base {
        return Err(fail(
            source,
            format!("a point record of {record_length} bytes is shorter than format {point_format}'s {base}"),
        ));
    }
    let points = h
        .large_file
        .map(|l| l.number_of_point_records)
        .unwrap_or(h.number_of_point_records as u64);
    let scale = DVec3::new(h.x_scale_factor, h.y_scale_factor, h.z_scale_factor);
    let offset = DVec3::new(h.x_offset, h.y_offset, h.z_offset);
    if !(scale.is_finite() && offset.is_finite() && scale.min_element() > 0.0) {
        return Err(fail(
            source,
            format!("scale {scale} and offset {offset} must be finite, the scale positive"),
        ));
    }
    // The VLRs follow the header; each one's size is in its own 54-byte header (≤ 64 KiB), within `bytes`.
    cur.set_position(h.header_size as u64);
    if h.number_of_variable_length_records > 4096 {
        return Err(fail(
            source,
            format!(
                "{} VLRs (at most 4096)",
                h.number_of_variable_length_records
            ),
        ));
    }
    let (mut info, mut lazvlr, mut extra, mut summary) = (None, None, Vec::new(), None);
    for i in 0..h.number_of_variable_length_records {
        let v = las::raw::Vlr::read_from(&mut cur, false).map_err(|e| {
            fail(
                source,
                format!("VLR {i} runs past the point data's start (byte {end}): {e}"),
            )
        })?;
        let user = {
            let n = v.user_id.iter().position(|&b| b == 0).unwrap_or(16);
            String::from_utf8_lossy(&v.user_id[..n]).into_owned()
        };
        match (user.as_str(), v.record_id) {
            ("copc", 1) => {
                if i != 0 {
                    return Err(fail(source, "the COPC info VLR is not the first VLR"));
                }
                info = Some(
                    CopcInfo::from_le_bytes(&v.data)
                        .map_err(|e| fail(source, format!("COPC info VLR: {e}")))?,
                );
            }
            ("laszip encoded", 22204) => {
                lazvlr = Some(
                    laz::LazVlr::from_buffer(&v.data)
                        .map_err(|e| fail(source, format!("LASzip VLR: {e}")))?,
                );
            }
            ("LASF_Spec", 4) => {
                extra = extra_bytes::descriptors(&v.data, record_length - base);
            }
            (SUMMARY_USER_ID, SUMMARY_RECORD_ID) => {
                summary = Some(
                    CopcSummary::from_bytes(&v.data, source)
                        .map_err(|e| fail(source, e.to_string()))?,
                );
            }
            _ => {}
        }
    }
    let info = info.ok_or_else(|| fail(source, "no COPC info VLR: a LAZ file, but not COPC"))?;
    let laz = lazvlr.ok_or_else(|| fail(source, "no LASzip VLR"))?;
    let (item_bytes, layers) = laz_item_layout(laz.items()).map_err(|e| fail(source, e))?;
    if item_bytes != record_length as u64 {
        return Err(fail(
            source,
            format!(
                "the LASzip items take {item_bytes} bytes a point, the header says {record_length}"
            ),
        ));
    }
    let layers = layers.ok_or_else(|| {
        fail(
            source,
            "the LASzip items are not layered (LAS 1.4 formats 6-8, as COPC requires)",
        )
    })?;
    if let Some(s) = &summary {
        if s.points != points {
            return Err(fail(
                source,
                format!(
                    "the summary counts {} points, the header {points}",
                    s.points
                ),
            ));
        }
    }
    Ok(CopcHead {
        points,
        point_format,
        record_length,
        extra_at: base,
        scale,
        offset,
        min: DVec3::new(h.min_x, h.min_y, h.min_z),
        max: DVec3::new(h.max_x, h.max_y, h.max_z),
        info,
        laz,
        layers,
        extra,
        summary,
    })
}

/// The LASzip items' point record size and, when every item is layered (LAS 1.4's formats 6–10, which COPC
/// uses), their number of layers. Each item must have its type's size: laz 0.13 trusts the VLR and reads
/// past a wrong one (a find of the `scan_file` fuzz target), and panics on a VLR of no items.
pub(crate) fn laz_item_layout(items: &[laz::LazItem]) -> Result<(u64, Option<u64>), String> {
    use laz::LazItemType as T;
    if items.is_empty() {
        return Err("the LASzip VLR lists no point items (corrupt file)".into());
    }
    let (mut record, mut layers, mut layered) = (0u64, 0u64, true);
    for item in items {
        let (size, item_layers) = match item.item_type() {
            T::Point10 => (20, None),
            T::GpsTime => (8, None),
            T::RGB12 => (6, None),
            T::WavePacket13 => (29, None),
            T::Byte(n) => (n, None),
            T::Point14 => (30, Some(9)),
            T::RGB14 => (6, Some(1)),
            T::RGBNIR14 => (8, Some(2)),
            T::WavePacket14 => (29, Some(1)),
            T::Byte14(n) => (n, Some(n as u64)),
        };
        if item.size() != size {
            return Err(format!(
                "the LASzip VLR's {:?} item is {} bytes; that item is {size} (corrupt file)",
                item.item_type(),
                item.size()
            ));
        }
        record += size as u64;
        match item_layers {
            Some(n) => layers += n,
            None => layered = false,
        }
    }
    Ok((record, layered.then_some(layers)))
}

impl CopcHead {
    /// The root hierarchy page's byte range.
    pub fn root_page(&self) -> Range {
        Range {
            offset: self.info.root_hier_offset,
            size: self.info.root_hier_size,
        }
    }

    /// The octree root cube's centre: a good origin for positions in f32 (what [`decode_node`] returns).
    pub fn center(&self) -> DVec3 {
        let (x, y, z) = self.info.center;
        DVec3::new(x, y, z)
    }

    /// A node's cube: its minimum corner and edge length.
    pub fn node_cube(&self, key: VoxelKey) -> (DVec3, f64) {
        let edge = 2.0 * self.info.halfsize / 2f64.powi(key.level.clamp(0, 1000));
        let min = self.center() - DVec3::splat(self.info.halfsize)
            + DVec3::new(key.x as f64, key.y as f64, key.z as f64) * edge;
        (min, edge)
    }

    /// The extra dimensions' names, in the order [`decode_node`] returns their values.
    pub fn field_names(&self) -> Vec<String> {
        self.extra.iter().map(|d| d.name.clone()).collect()
    }

    pub fn has_rgb(&self) -> bool {
        self.point_format >= 7
    }
}

/// The entries of one hierarchy page, each checked: its key valid, a node's point count and byte size
/// within [`MAX_NODE_POINTS`] and [`MAX_NODE_BYTES`], a child page within [`MAX_PAGE_BYTES`], and each
/// byte range inside the file when its length is known.
pub fn parse_page(
    bytes: &[u8],
    file_len: Option<u64>,
    source: &str,
) -> Result<Vec<Entry>, CopcReadError> {
    if bytes.len() as u64 > MAX_PAGE_BYTES {
        return Err(fail(
            source,
            format!(
                "a hierarchy page of {} bytes (at most {MAX_PAGE_BYTES})",
                bytes.len()
            ),
        ));
    }
    let page = HierarchyPage::from_le_bytes(bytes)
        .map_err(|e| fail(source, format!("hierarchy page: {e}")))?;
    let entries = page.into_entries();
    for e in &entries {
        e.validate()
            .map_err(|err| fail(source, format!("hierarchy entry {:?}: {err}", e.key)))?;
        let (size, limit, what) = match e.availability() {
            Ok(EntryAvailability::Empty) => continue,
            Ok(EntryAvailability::PointData { point_count }) => {
                if point_count > MAX_NODE_POINTS {
                    return Err(fail(
                        source,
                        format!(
                            "node {:?} holds {point_count} points (at most {MAX_NODE_POINTS})",
                            e.key
                        ),
                    ));
                }
                (e.byte_size as u64, MAX_NODE_BYTES, "node")
            }
            Ok(EntryAvailability::ChildPage) => (e.byte_size as u64, MAX_PAGE_BYTES, "page"),
            Err(err) => return Err(fail(source, format!("hierarchy entry {:?}: {err}", e.key))),
        };
        if size > limit {
            return Err(fail(
                source,
                format!("{what} {:?} takes {size} bytes (at most {limit})", e.key),
            ));
        }
        if let Some(len) = file_len {
            if e.offset.checked_add(size).is_none_or(|end| end > len) {
                return Err(fail(
                    source,
                    format!(
                        "{what} {:?} at bytes {}..+{size} lies past the file's end ({len} bytes)",
                        e.key, e.offset
                    ),
                ));
            }
        }
    }
    Ok(entries)
}

/// A walk of the hierarchy's pages, the root first, for a reader that fetches as it likes (the worker,
/// asynchronously): take [`HierarchyWalk::next_page`], fetch it, hand it to [`HierarchyWalk::add_page`],
/// until there is none; then [`HierarchyWalk::finish`]. Pages are visited once each (a page that names
/// itself or an earlier one is refused), within [`MAX_PAGES`] and [`MAX_ENTRIES`].
pub struct HierarchyWalk {
    pending: Vec<Range>,
    seen: std::collections::HashSet<u64>,
    nodes: Vec<Entry>,
    entries: usize,
    file_len: Option<u64>,
    source: String,
}

impl HierarchyWalk {
    pub fn new(head: &CopcHead, file_len: Option<u64>, source: &str) -> Self {
        Self {
            pending: vec![head.root_page()],
            seen: Default::default(),
            nodes: Vec::new(),
            entries: 0,
            file_len,
            source: source.to_string(),
        }
    }

    /// The next page to read, checked first.
    pub fn next_page(&mut self) -> Result<Option<Range>, CopcReadError> {
        let Some(r) = self.pending.pop() else {
            return Ok(None);
        };
        let source = &self.source;
        if r.size > MAX_PAGE_BYTES {
            return Err(fail(
                source,
                format!(
                    "a hierarchy page of {} bytes (at most {MAX_PAGE_BYTES})",
                    r.size
                ),
            ));
        }
        if !self.seen.insert(r.offset) {
            return Err(fail(
                source,
                format!("the hierarchy page at byte {} is named twice", r.offset),
            ));
        }
        if self.seen.len() > MAX_PAGES {
            return Err(fail(
                source,
                format!("more than {MAX_PAGES} hierarchy pages"),
            ));
        }
        Ok(Some(r))
    }

    /// The bytes of page `r` (as [`HierarchyWalk::next_page`] gave it).
    pub fn add_page(&mut self, r: Range, bytes: &[u8]) -> Result<(), CopcReadError> {
        let source = &self.source;
        if bytes.len() as u64 != r.size {
            return Err(fail(
                source,
                format!(
                    "the hierarchy page at byte {} should take {} bytes, {} were read",
                    r.offset,
                    r.size,
                    bytes.len()
                ),
            ));
        }
        for e in parse_page(bytes, self.file_len, source)? {
            self.entries += 1;
            if self.entries > MAX_ENTRIES {
                return Err(fail(
                    source,
                    format!("more than {MAX_ENTRIES} hierarchy entries"),
                ));
            }
            if e.is_child_page() {
                self.pending.push(Range {
                    offset: e.offset,
                    size: e.byte_size as u64,
                });
            } else if e.has_point_data() {
                self.nodes.push(e);
            }
        }
        Ok(())
    }

    /// Every node with points, by key.
    pub fn finish(mut self) -> Vec<Entry> {
        self.nodes.sort_by_key(|e| e.key);
        self.nodes
    }
}

/// The whole hierarchy through `read` (offset, size → bytes), blocking: for the CLI and the tests.
pub fn walk_hierarchy(
    head: &CopcHead,
    file_len: Option<u64>,
    source: &str,
    read: &mut dyn FnMut(Range) -> Result<Vec<u8>, String>,
) -> Result<Vec<Entry>, CopcReadError> {
    let mut walk = HierarchyWalk::new(head, file_len, source);
    while let Some(r) = walk.next_page()? {
        let bytes = read(r).map_err(|e| fail(source, e))?;
        walk.add_page(r, &bytes)?;
    }
    Ok(walk.finish())
}

/// One node's points: positions relative to an origin (in f32: a map's extent in metres keeps them to
/// well under a millimetre), 8-bit colours when the file has them, and each extra dimension's values.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NodePoints {
    pub positions: Vec<[f32; 3]>,
    pub colors: Option<Vec<[u8; 3]>>,
    /// In [`CopcHead::field_names`]'s order.
    pub scalars: Vec<Vec<f32>>,
}

/// Decodes a node (`entry`, one with points) from its `bytes` (the file's range `entry.offset`,
/// `entry.byte_size`), with positions relative to `origin`.
pub fn decode_node(
    head: &CopcHead,
    entry: &Entry,
    bytes: &[u8],
    origin: DVec3,
    source: &str,
) -> Result<NodePoints, CopcReadError> {
    let n = match entry.availability() {
        Ok(EntryAvailability::PointData { point_count }) if point_count <= MAX_NODE_POINTS => {
            point_count as usize
        }
        _ => {
            return Err(fail(
                source,
                format!(
                    "node {:?}: {} points is not a node to decode",
                    entry.key, entry.point_count
                ),
            ))
        }
    };
    if bytes.len() as u64 != entry.byte_size as u64 {
        return Err(fail(
            source,
            format!(
                "node {:?} should take {} bytes, {} were read",
                entry.key,
                entry.byte_size,
                bytes.len()
            ),
        ));
    }
    let decoded = n as u64 * (12 + 3 + 4 * head.extra.len() as u64);
    if decoded > MAX_NODE_DECODED_BYTES {
        return Err(fail(
            source,
            format!(
                "node {:?}: {n} points of {} fields would take {decoded} bytes decoded (at most {MAX_NODE_DECODED_BYTES})",
                entry.key,
                head.extra.len()
            ),
        ));
    }
    // The laz decoder panics on some corrupt chunks (laz-rs issue #43; `fuzz/seeds/scan_file`): natively
    // that is caught here and reported; in the browser a panic traps, so the studio decodes nodes in a
    // worker it can replace.
    #[cfg(not(target_arch = "wasm32"))]
    {
        let run =
            std::panic::AssertUnwindSafe(|| decode_chunk(head, entry, bytes, n, origin, source));
        std::panic::catch_unwind(run).unwrap_or_else(|_| {
            Err(fail(
                source,
                format!(
                    "node {:?}: the LAZ decoder failed on its chunk (corrupt data)",
                    entry.key
                ),
            ))
        })
    }
    #[cfg(target_arch = "wasm32")]
    decode_chunk(head, entry, bytes, n, origin, source)
}

fn decode_chunk(
    head: &CopcHead,
    entry: &Entry,
    bytes: &[u8],
    n: usize,
    origin: DVec3,
    source: &str,
) -> Result<NodePoints, CopcReadError> {
    let at = |m: &str| fail(source, format!("node {:?}: {m}", entry.key));
    // A layered chunk: the first point raw, its point count, each layer's byte size, the layers. laz 0.13
    // sizes its buffers from those sizes before reading (a 1 KB file reserved 4 GB: the `scan_file` fuzz
    // target's find), so they must fit in the chunk, and the count must be the hierarchy's.
    let head_bytes = head.record_length + 4 + 4 * head.layers as usize;
    if bytes.len() < head_bytes {
        return Err(at(&format!(
            "a chunk of {} bytes, shorter than its {head_bytes}-byte start",
            bytes.len()
        )));
    }
    let u32_at =
        |k: usize| u32::from_le_bytes([bytes[k], bytes[k + 1], bytes[k + 2], bytes[k + 3]]);
    let in_chunk = u32_at(head.record_length) as usize;
    if in_chunk != n {
        return Err(at(&format!(
            "its chunk holds {in_chunk} points, the hierarchy says {n}"
        )));
    }
    let layer_bytes: u64 = (0..head.layers as usize)
        .map(|l| u32_at(head.record_length + 4 + 4 * l) as u64)
        .sum();
    if layer_bytes > (bytes.len() - head_bytes) as u64 {
        return Err(at(&format!(
            "its layers state {layer_bytes} bytes, {} follow",
            bytes.len() - head_bytes
        )));
    }
    let mut dec = LayeredPointRecordDecompressor::new(Cursor::new(bytes));
    dec.set_fields_from(head.laz.items())
        .map_err(|e| at(&format!("its LASzip items: {e}")))?;
    if dec.record_size() != head.record_length {
        return Err(at(&format!(
            "LASzip records of {} bytes, the header says {}",
            dec.record_size(),
            head.record_length
        )));
    }
    let mut out = NodePoints {
        positions: Vec::with_capacity(n),
        colors: head.has_rgb().then(|| Vec::with_capacity(n)),
        scalars: head.extra.iter().map(|_| Vec::with_capacity(n)).collect(),
    };
    // Integer coordinates to metres, then to the origin, in f64 before the f32 they are kept in.
    let base = head.offset - origin;
    let mut rec = vec![0u8; head.record_length];
    let i32_at = |r: &[u8], k: usize| i32::from_le_bytes([r[k], r[k + 1], r[k + 2], r[k + 3]]);
    for i in 0..n {
        dec.decompress_next(&mut rec)
            .map_err(|e| at(&format!("point {i} of {n}: {e}")))?;
        let q = DVec3::new(
            i32_at(&rec, 0) as f64,
            i32_at(&rec, 4) as f64,
            i32_at(&rec, 8) as f64,
        );
        let p = q * head.scale + base;
        out.positions.push([p.x as f32, p.y as f32, p.z as f32]);
        if let Some(c) = &mut out.colors {
            c.push([rec[31], rec[33], rec[35]]);
        }
        let extra = &rec[head.extra_at..];
        for (d, v) in head.extra.iter().zip(&mut out.scalars) {
            v.push(d.value(extra));
        }
    }
    Ok(out)
}

/// Every node of a COPC file of `len` bytes, read through the functions above by byte ranges (`range`),
/// as the worker reads a link. Blocking: for the CLI, the tests and the fuzzer.
pub fn read_ranges(
    len: u64,
    source: &str,
    range: &mut dyn FnMut(Range) -> Result<Vec<u8>, String>,
) -> Result<(CopcHead, Vec<(Entry, NodePoints)>), CopcReadError> {
    let mut checked = |r: Range| -> Result<Vec<u8>, String> {
        if r.offset.checked_add(r.size).is_none_or(|end| end > len) {
            return Err(format!(
                "bytes {}..+{} lie past the file's end ({len} bytes)",
                r.offset, r.size
            ));
        }
        range(r)
    };
    let first = checked(Range {
        offset: 0,
        size: (LAS_HEADER_BYTES as u64).min(len),
    })
    .map_err(|e| fail(source, e))?;
    let head_bytes = checked(Range {
        offset: 0,
        size: head_len(&first, source)?,
    })
    .map_err(|e| fail(source, e))?;
    let head = parse_head(&head_bytes, source)?;
    let entries = walk_hierarchy(&head, Some(len), source, &mut checked)?;
    let mut out = Vec::with_capacity(entries.len());
    for e in entries {
        let bytes = checked(Range {
            offset: e.offset,
            size: e.byte_size as u64,
        })
        .map_err(|m| fail(source, m))?;
        let pts = decode_node(&head, &e, &bytes, head.center(), source)?;
        out.push((e, pts));
    }
    Ok((head, out))
}

/// [`read_ranges`] over a file on disk.
#[cfg(not(target_arch = "wasm32"))]
pub fn read_file(
    path: &std::path::Path,
) -> Result<(CopcHead, Vec<(Entry, NodePoints)>), CopcReadError> {
    use std::io::{Read, Seek, SeekFrom};
    let source = path.display().to_string();
    let mut f = std::fs::File::open(path).map_err(|e| fail(&source, e))?;
    let len = f.metadata().map_err(|e| fail(&source, e))?.len();
    read_ranges(len, &source, &mut |r| {
        let mut b = vec![0u8; r.size as usize];
        f.seek(SeekFrom::Start(r.offset))
            .and_then(|_| f.read_exact(&mut b))
            .map_err(|e| e.to_string())?;
        Ok(b)
    })
}

/// [`read_ranges`] over bytes in memory (a dropped file; the fuzzer).
pub fn read_bytes(
    data: &[u8],
    source: &str,
) -> Result<(CopcHead, Vec<(Entry, NodePoints)>), CopcReadError> {
    read_ranges(data.len() as u64, source, &mut |r| {
        Ok(data[r.offset as usize..(r.offset + r.size) as usize].to_vec())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A head too short, not LAS, or with a point-data offset past the bound is refused by name.
    #[test]
    fn a_bad_head_names_the_source_and_the_problem() {
        let e = head_len(b"not a las file", "x.copc.laz").unwrap_err();
        assert_eq!(e.source_name, "x.copc.laz");
        let mut h = vec![0u8; LAS_HEADER_BYTES];
        h[..4].copy_from_slice(b"LASF");
        h[24] = 1;
        h[25] = 4;
        h[94..96].copy_from_slice(&(LAS_HEADER_BYTES as u16).to_le_bytes());
        h[96..100].copy_from_slice(&u32::MAX.to_le_bytes());
        let e = head_len(&h, "m").unwrap_err();
        assert!(e.message.contains("point data starts"), "{e}");
        h[96..100].copy_from_slice(&(LAS_HEADER_BYTES as u32).to_le_bytes());
        assert_eq!(head_len(&h, "m").unwrap(), LAS_HEADER_BYTES as u64);
        let e = parse_head(&h, "m").unwrap_err();
        assert!(e.message.contains("point format 0"), "{e}");
    }

    /// A page whose node claims more points than the bound, or bytes past the file's end, is refused.
    #[test]
    fn hierarchy_entries_are_bounded() {
        let entry = |count: i32, offset: u64, size: i32| {
            let mut b = vec![0u8; 32];
            b[16..24].copy_from_slice(&offset.to_le_bytes());
            b[24..28].copy_from_slice(&size.to_le_bytes());
            b[28..32].copy_from_slice(&count.to_le_bytes());
            b
        };
        assert_eq!(
            parse_page(&entry(10, 1000, 50), Some(2000), "p")
                .unwrap()
                .len(),
            1
        );
        let e = parse_page(&entry(10, 1000, 50), Some(1020), "p").unwrap_err();
        assert!(e.message.contains("past the file's end"), "{e}");
        let e = parse_page(&entry(i32::MAX, 1000, 50), None, "p").unwrap_err();
        assert!(e.message.contains("points (at most"), "{e}");
        let e = parse_page(&[0u8; 33], None, "p").unwrap_err();
        assert!(e.message.contains("multiple of 32"), "{e}");
    }
}
