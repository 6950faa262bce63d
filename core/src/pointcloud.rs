//! Point clouds (positions in f64, optional colours, normals and named float properties) and PLY I/O.
//!
//! Positions are f64 because ground-truth TLS maps are kilometre-scale with millimetre detail; an f32
//! coordinate at 1 km is only good to ~0.06 mm, but the evaluator compares clouds that went through several
//! transforms, so we keep f64 end to end and write `double` x/y/z. Normals and extra properties are f32,
//! which is what every PLY producer we meet writes for them.
//!
//! The PLY reader never panics on malformed input: every problem becomes a [`PlyError`] that names the file.
//! It reads `ascii`, `binary_little_endian` and `binary_big_endian`, takes x/y/z (any numeric type),
//! red/green/blue and nx/ny/nz when all three of a group are present, keeps every other scalar vertex
//! property as a named f32 scalar, and skips other elements (faces, edges…), list properties included.
//! [`PlyReadOptions`] narrows what is kept (the studio's worker decodes only what it shows).
//!
//! Untrusted sizes: every element count is bounded by the bytes left in the file before anything is
//! reserved, and the vertex buffers are reserved fallibly (`try_reserve_exact`), so a count the memory
//! cannot hold (a 32-bit browser heap, for one) is a [`PlyError::TooLarge`], never an abort.

use glam::{DAffine3, DVec3, Vec3};
use std::collections::HashMap;
use std::fs::{self, File};
use std::hash::{BuildHasherDefault, Hasher};
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// A point cloud. Attribute vectors, when present, have one entry per position.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointCloud {
    pub positions: Vec<DVec3>,
    /// Per-point RGB.
    pub colors: Option<Vec<[u8; 3]>>,
    /// Per-point normals (not necessarily unit length when read from a file).
    pub normals: Option<Vec<Vec3>>,
    /// Extra per-point float properties (uncertainty, error, intensity…), kept in file order.
    pub scalars: Vec<(String, Vec<f32>)>,
}

impl PointCloud {
    pub fn new() -> Self {
        Self::default()
    }

    /// A cloud with positions only.
    pub fn from_positions(positions: Vec<DVec3>) -> Self {
        Self {
            positions,
            ..Self::default()
        }
    }

    pub fn len(&self) -> usize {
        self.positions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Appends a point. Attributes the cloud already carries are padded with neutral values (black, zero
    /// normal, NaN scalar) so the lengths stay consistent; use [`Self::push_colored`] to give a colour.
    pub fn push(&mut self, p: DVec3) {
        self.positions.push(p);
        if let Some(c) = &mut self.colors {
            c.push([0, 0, 0]);
        }
        if let Some(n) = &mut self.normals {
            n.push(Vec3::ZERO);
        }
        for (_, s) in &mut self.scalars {
            s.push(f32::NAN);
        }
    }

    /// Appends a coloured point; creates the colour channel (black for earlier points) if needed.
    pub fn push_colored(&mut self, p: DVec3, rgb: [u8; 3]) {
        let n = self.len();
        self.push(p);
        let colors = self.colors.get_or_insert_with(|| vec![[0, 0, 0]; n + 1]);
        colors[n] = rgb;
    }

    /// The named scalar property, if present.
    pub fn scalar(&self, name: &str) -> Option<&[f32]> {
        self.scalars
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_slice())
    }

    /// Adds or replaces a scalar property.
    ///
    /// # Panics
    /// If `values.len() != self.len()` (a programming error, not an input error).
    pub fn set_scalar(&mut self, name: &str, values: Vec<f32>) {
        assert_eq!(
            values.len(),
            self.len(),
            "scalar '{name}' length must match the point count"
        );
        match self.scalars.iter_mut().find(|(n, _)| n == name) {
            Some((_, v)) => *v = values,
            None => self.scalars.push((name.to_string(), values)),
        }
    }

    /// Number of points with a NaN or infinite coordinate. Such points are legal in files (PLY
    /// producers use NaN for "no return") and are kept by the reader; geometric operations skip them.
    pub fn count_nonfinite(&self) -> usize {
        self.positions.iter().filter(|p| !p.is_finite()).count()
    }

    /// Checks that every attribute has one entry per point and that scalar names are writable to PLY.
    pub fn validate(&self) -> Result<(), String> {
        let n = self.len();
        if let Some(c) = &self.colors {
            if c.len() != n {
                return Err(format!("{} colours for {n} points", c.len()));
            }
        }
        if let Some(v) = &self.normals {
            if v.len() != n {
                return Err(format!("{} normals for {n} points", v.len()));
            }
        }
        let mut seen: Vec<&str> = Vec::new();
        for (name, v) in &self.scalars {
            if v.len() != n {
                return Err(format!(
                    "scalar '{name}' has {} values for {n} points",
                    v.len()
                ));
            }
            if name.is_empty()
                || name
                    .chars()
                    .any(|c| c.is_whitespace() || !c.is_ascii_graphic())
            {
                return Err(format!(
                    "scalar name '{name}' is empty or not printable ASCII without spaces"
                ));
            }
            if RESERVED_NAMES.contains(&name.as_str()) || seen.contains(&name.as_str()) {
                return Err(format!("scalar name '{name}' is reserved or duplicated"));
            }
            seen.push(name);
        }
        Ok(())
    }

    /// Axis-aligned bounds `(min, max)` of the finite points; `None` when there are none.
    pub fn bounds(&self) -> Option<(DVec3, DVec3)> {
        let mut it = self.positions.iter().filter(|p| p.is_finite());
        let first = *it.next()?;
        Some(it.fold((first, first), |(lo, hi), p| (lo.min(*p), hi.max(*p))))
    }

    /// The points with the given indices, in that order, with all attributes.
    ///
    /// # Panics
    /// If an index is out of range.
    pub fn select(&self, indices: &[usize]) -> PointCloud {
        PointCloud {
            positions: indices.iter().map(|&i| self.positions[i]).collect(),
            colors: self
                .colors
                .as_ref()
                .map(|c| indices.iter().map(|&i| c[i]).collect()),
            normals: self
                .normals
                .as_ref()
                .map(|v| indices.iter().map(|&i| v[i]).collect()),
            scalars: self
                .scalars
                .iter()
                .map(|(name, v)| (name.clone(), indices.iter().map(|&i| v[i]).collect()))
                .collect(),
        }
    }

    /// Indices of the points for which `keep(index, position)` holds.
    pub fn indices_where(&self, mut keep: impl FnMut(usize, DVec3) -> bool) -> Vec<usize> {
        (0..self.len())
            .filter(|&i| keep(i, self.positions[i]))
            .collect()
    }

    /// The finite points inside the closed box `[min, max]`.
    pub fn crop_aabb(&self, min: DVec3, max: DVec3) -> PointCloud {
        let idx =
            self.indices_where(|_, p| p.is_finite() && p.cmpge(min).all() && p.cmple(max).all());
        self.select(&idx)
    }

    /// The finite points only.
    pub fn finite_only(&self) -> PointCloud {
        let idx = self.indices_where(|_, p| p.is_finite());
        self.select(&idx)
    }

    /// The cloud mapped by `t` (e.g. `T_gt_lidar`); normals are rotated by the linear part and renormalised.
    pub fn transformed(&self, t: &DAffine3) -> PointCloud {
        let mut out = self.clone();
        for p in &mut out.positions {
            *p = t.transform_point3(*p);
        }
        if let Some(normals) = &mut out.normals {
            let m = t.matrix3.inverse().transpose();
            for n in normals {
                let v = (m * n.as_dvec3()).normalize_or_zero();
                *n = v.as_vec3();
            }
        }
        out
    }

    /// One point per occupied voxel of a grid anchored at the origin (cells `[k·v, (k+1)·v)`), placed at
    /// the **centroid** of the voxel's points, like Open3D's `voxel_down_sample` that the Spires
    /// benchmark uses (Open3D anchors its grid at the cloud's minimum instead; an origin-anchored grid
    /// makes the reconstruction and the GT share cells). Colours, normals and scalars are averaged
    /// (normals renormalised). Output order is the order in which voxels are first met, so the result
    /// is deterministic. Non-finite points are dropped. A voxel size that is not finite and positive
    /// returns an unchanged copy.
    pub fn voxel_downsample(&self, voxel: f64) -> PointCloud {
        if !(voxel.is_finite() && voxel > 0.0) {
            return self.clone();
        }
        let inv = 1.0 / voxel;
        let mut slots: VoxelMap<usize> = VoxelMap::default();
        let mut slot_of: Vec<usize> = Vec::with_capacity(self.len());
        for p in &self.positions {
            if !p.is_finite() {
                slot_of.push(usize::MAX);
                continue;
            }
            let next = slots.len();
            slot_of.push(*slots.entry(voxel_key(*p, inv)).or_insert(next));
        }
        let m = slots.len();
        drop(slots);
        let mut count = vec![0u32; m];
        let mut sum = vec![DVec3::ZERO; m];
        for (i, &s) in slot_of.iter().enumerate() {
            if s != usize::MAX {
                count[s] += 1;
                sum[s] += self.positions[i];
            }
        }
        let positions = sum
            .iter()
            .zip(&count)
            .map(|(s, &c)| *s / c as f64)
            .collect();
        let colors = self.colors.as_ref().map(|colors| {
            let mut acc = vec![[0u64; 3]; m];
            for (i, &s) in slot_of.iter().enumerate() {
                if s != usize::MAX {
                    for k in 0..3 {
                        acc[s][k] += colors[i][k] as u64;
                    }
                }
            }
            acc.iter()
                .zip(&count)
                .map(|(a, &c)| a.map(|v| ((v as f64 / c as f64).round()).min(255.0) as u8))
                .collect()
        });
        let normals = self.normals.as_ref().map(|normals| {
            let mut acc = vec![DVec3::ZERO; m];
            for (i, &s) in slot_of.iter().enumerate() {
                if s != usize::MAX {
                    acc[s] += normals[i].as_dvec3();
                }
            }
            acc.iter()
                .map(|a| a.normalize_or_zero().as_vec3())
                .collect()
        });
        let scalars = self
            .scalars
            .iter()
            .map(|(name, values)| {
                let mut acc = vec![0f64; m];
                for (i, &s) in slot_of.iter().enumerate() {
                    if s != usize::MAX {
                        acc[s] += values[i] as f64;
                    }
                }
                let mean = acc
                    .iter()
                    .zip(&count)
                    .map(|(a, &c)| (a / c as f64) as f32)
                    .collect();
                (name.clone(), mean)
            })
            .collect();
        PointCloud {
            positions,
            colors,
            normals,
            scalars,
        }
    }
}

/// Property names the writer emits itself, so they cannot also be scalar names.
const RESERVED_NAMES: [&str; 9] = ["x", "y", "z", "red", "green", "blue", "nx", "ny", "nz"];

/// Integer voxel coordinates of `p` for a grid with cells `[k/inv, (k+1)/inv)` (OctoMap's key rule
/// `floor(p · (1/resolution))`). `p` must be finite; huge coordinates saturate.
#[inline]
pub(crate) fn voxel_key(p: DVec3, inv_voxel: f64) -> [i64; 3] {
    [
        (p.x * inv_voxel).floor() as i64,
        (p.y * inv_voxel).floor() as i64,
        (p.z * inv_voxel).floor() as i64,
    ]
}

/// A fixed (unseeded) hasher for integer voxel keys: fast, and deterministic across runs, unlike
/// `RandomState`, so iteration-order-dependent code stays reproducible.
#[derive(Clone, Copy, Default)]
pub(crate) struct VoxelHasher(u64);

impl Hasher for VoxelHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    /// Eight bytes a round: an `[i64; 3]` key arrives as one 24-byte write (integers hash their slices
    /// as bytes), which a round per byte made 24 rounds.
    fn write(&mut self, bytes: &[u8]) {
        let mut words = bytes.chunks_exact(8);
        for w in &mut words {
            let mut b = [0u8; 8];
            b.copy_from_slice(w);
            self.write_u64(u64::from_le_bytes(b));
        }
        let rest = words.remainder();
        if !rest.is_empty() {
            let mut b = [0u8; 8];
            b[..rest.len()].copy_from_slice(rest);
            self.write_u64(u64::from_le_bytes(b) ^ ((rest.len() as u64) << 59));
        }
    }
    fn write_u64(&mut self, v: u64) {
        // splitmix64 finaliser over the running state.
        let mut z = (self.0.rotate_left(23) ^ v).wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        self.0 = z ^ (z >> 31);
    }
    fn write_i64(&mut self, v: i64) {
        self.write_u64(v as u64);
    }
    fn write_usize(&mut self, v: usize) {
        self.write_u64(v as u64);
    }
}

/// Hash map keyed by integer voxel coordinates.
pub(crate) type VoxelMap<V> = HashMap<[i64; 3], V, BuildHasherDefault<VoxelHasher>>;

// ---------------------------------------------------------------------------------------------------
// Atomic file writes
// ---------------------------------------------------------------------------------------------------

/// The temporary sibling `<path>.tmp-<pid>` that atomic writes go through.
pub(crate) fn temp_sibling(path: &Path) -> io::Result<PathBuf> {
    let name = path.file_name().ok_or_else(|| {
        io::Error::new(io::ErrorKind::InvalidInput, "output path has no file name")
    })?;
    let mut tmp = name.to_os_string();
    tmp.push(format!(".tmp-{}", process_id()));
    Ok(path.with_file_name(tmp))
}

fn process_id() -> u32 {
    // std::process::id panics on wasm32-unknown-unknown; file writes fail there anyway.
    #[cfg(not(target_arch = "wasm32"))]
    {
        std::process::id()
    }
    #[cfg(target_arch = "wasm32")]
    {
        0
    }
}

/// Writes through `<path>.tmp-<pid>` in the same directory, syncs, then renames over `path`, so readers
/// never see a half-written file. The temporary file is removed on failure.
pub(crate) fn write_atomic(
    path: &Path,
    write: impl FnOnce(&mut BufWriter<File>) -> io::Result<()>,
) -> io::Result<()> {
    let tmp = temp_sibling(path)?;
    let result = (|| {
        let mut w = BufWriter::with_capacity(1 << 20, File::create(&tmp)?);
        write(&mut w)?;
        // Sync, and close the file before the rename (Windows cannot rename an open file).
        w.into_inner().map_err(|e| e.into_error())?.sync_all()?;
        fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

// ---------------------------------------------------------------------------------------------------
// PLY
// ---------------------------------------------------------------------------------------------------

/// PLY read/write errors. Every variant names the file (or the name given to [`read_ply_bytes`]).
#[derive(Debug, Error)]
pub enum PlyError {
    #[error("{file}: {source}")]
    Io {
        file: String,
        #[source]
        source: io::Error,
    },
    #[error("{file}: bad PLY header (line {line}): {reason}")]
    BadHeader {
        file: String,
        line: usize,
        reason: String,
    },
    #[error("{file}: unsupported PLY: {reason}")]
    Unsupported { file: String, reason: String },
    #[error("{file}: truncated PLY data: {reason}")]
    Truncated { file: String, reason: String },
    #[error(
        "{file}: element '{element}' claims {count} items, but only {available} bytes of data follow \
         (each item needs at least {min_item_bytes})"
    )]
    CountTooLarge {
        file: String,
        element: String,
        count: u64,
        available: u64,
        min_item_bytes: u64,
    },
    #[error(
        "{file}: bad value in element '{element}' item {index}, property '{property}': {reason}"
    )]
    BadValue {
        file: String,
        element: String,
        index: u64,
        property: String,
        reason: String,
    },
    /// A buffer a (plausible) size needs could not be reserved: the memory cannot hold the file.
    #[error("{file}: too large for this memory: {bytes} bytes for {what} could not be allocated")]
    TooLarge {
        file: String,
        /// What the buffer was for (`2147483647 positions`).
        what: String,
        bytes: u64,
    },
    #[error("{file}: no vertex element with x, y and z properties")]
    MissingXyz { file: String },
    #[error("{file}: cannot write point cloud: {reason}")]
    InvalidCloud { file: String, reason: String },
}

/// PLY scalar types.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum PlyType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl PlyType {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }

    fn is_float(self) -> bool {
        matches!(self, Self::F32 | Self::F64)
    }

    /// Decodes one value; `b` holds at least `self.size()` bytes.
    fn decode(self, b: &[u8], big_endian: bool) -> f64 {
        macro_rules! get {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                if big_endian {
                    <$t>::from_be_bytes(a) as f64
                } else {
                    <$t>::from_le_bytes(a) as f64
                }
            }};
        }
        match self {
            Self::I8 => b[0] as i8 as f64,
            Self::U8 => b[0] as f64,
            Self::I16 => get!(i16, 2),
            Self::U16 => get!(u16, 2),
            Self::I32 => get!(i32, 4),
            Self::U32 => get!(u32, 4),
            Self::F32 => get!(f32, 4),
            Self::F64 => get!(f64, 8),
        }
    }

    /// Rounds an ASCII value to what this type can hold (floats go through f32 for `float`).
    fn round_ascii(self, v: f64) -> f64 {
        match self {
            Self::F32 => v as f32 as f64,
            _ => v,
        }
    }
}

#[derive(Clone, Debug)]
enum PropKind {
    Scalar(PlyType),
    List { count: PlyType, item: PlyType },
}

#[derive(Clone, Debug)]
struct Property {
    name: String,
    kind: PropKind,
}

#[derive(Clone, Debug)]
struct Element {
    name: String,
    count: u64,
    props: Vec<Property>,
}

impl Element {
    /// Smallest number of bytes one item takes in a binary file.
    fn min_binary_item_bytes(&self) -> u64 {
        self.props
            .iter()
            .map(|p| match p.kind {
                PropKind::Scalar(t) => t.size() as u64,
                PropKind::List { count, .. } => count.size() as u64,
            })
            .sum()
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum PlyFormat {
    Ascii,
    BinaryLe,
    BinaryBe,
}

struct Header {
    format: PlyFormat,
    elements: Vec<Element>,
    /// Byte offset of the first data byte.
    data_start: usize,
}

/// Longest header we accept before giving up looking for `end_header` (binary junk has no newlines).
const MAX_HEADER_BYTES: usize = 1 << 20;

fn parse_header(bytes: &[u8], file: &str) -> Result<Header, PlyError> {
    let bad = |line: usize, reason: String| PlyError::BadHeader {
        file: file.to_string(),
        line,
        reason,
    };
    let mut pos = 0usize;
    let mut line_no = 0usize;
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        line_no += 1;
        if pos >= bytes.len() || pos > MAX_HEADER_BYTES {
            let reason = if pos > MAX_HEADER_BYTES {
                "no end_header in the first 1 MiB".to_string()
            } else {
                "file ends before end_header".to_string()
            };
            return Err(bad(line_no, reason));
        }
        let rest = &bytes[pos..];
        let end = rest.iter().position(|&b| b == b'\n').unwrap_or(rest.len());
        let raw = &rest[..end];
        pos += end + 1;
        let raw = raw.strip_suffix(b"\r").unwrap_or(raw);
        let line =
            std::str::from_utf8(raw).map_err(|_| bad(line_no, "header line is not text".into()))?;
        if line_no == 1 {
            if line.trim_end() != "ply" {
                return Err(bad(
                    1,
                    "file does not start with 'ply' (not a PLY file)".into(),
                ));
            }
            continue;
        }
        let mut words = line.split_whitespace();
        let Some(keyword) = words.next() else {
            continue;
        };
        match keyword {
            "comment" | "obj_info" => {}
            "format" => {
                let f = match words.next() {
                    Some("ascii") => PlyFormat::Ascii,
                    Some("binary_little_endian") => PlyFormat::BinaryLe,
                    Some("binary_big_endian") => PlyFormat::BinaryBe,
                    other => {
                        return Err(PlyError::Unsupported {
                            file: file.to_string(),
                            reason: format!("format '{}'", other.unwrap_or("")),
                        })
                    }
                };
                match words.next() {
                    Some("1.0") | Some("1") => {}
                    v => {
                        return Err(PlyError::Unsupported {
                            file: file.to_string(),
                            reason: format!("format version '{}'", v.unwrap_or("")),
                        })
                    }
                }
                format = Some(f);
            }
            "element" => {
                let (Some(name), Some(count), None) = (words.next(), words.next(), words.next())
                else {
                    return Err(bad(
                        line_no,
                        format!("expected 'element <name> <count>', got '{line}'"),
                    ));
                };
                let count: u64 = count
                    .parse()
                    .map_err(|_| bad(line_no, format!("element count '{count}' is not a count")))?;
                if elements.iter().any(|e| e.name == name) {
                    return Err(bad(line_no, format!("element '{name}' declared twice")));
                }
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    props: Vec::new(),
                });
            }
            "property" => {
                let Some(element) = elements.last_mut() else {
                    return Err(bad(line_no, "property before any element".into()));
                };
                let words: Vec<&str> = words.collect();
                let ty = |s: &str| {
                    PlyType::parse(s).ok_or_else(|| bad(line_no, format!("unknown type '{s}'")))
                };
                let prop = match words.as_slice() {
                    ["list", count, item, name] => {
                        let count = ty(count)?;
                        if count.is_float() {
                            return Err(bad(line_no, "list count type must be an integer".into()));
                        }
                        Property {
                            name: name.to_string(),
                            kind: PropKind::List {
                                count,
                                item: ty(item)?,
                            },
                        }
                    }
                    [t, name] => Property {
                        name: name.to_string(),
                        kind: PropKind::Scalar(ty(t)?),
                    },
                    _ => return Err(bad(line_no, format!("cannot parse property line '{line}'"))),
                };
                if element.props.iter().any(|p| p.name == prop.name) {
                    return Err(bad(
                        line_no,
                        format!("property '{}' declared twice", prop.name),
                    ));
                }
                element.props.push(prop);
            }
            "end_header" => break,
            other => return Err(bad(line_no, format!("unknown header keyword '{other}'"))),
        }
    }
    let format = format.ok_or_else(|| bad(2, "no 'format' line".into()))?;
    Ok(Header {
        format,
        elements,
        data_start: pos.min(bytes.len()),
    })
}

/// Where a vertex property goes.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Target {
    Pos(usize),
    Color(usize),
    Normal(usize),
    Scalar(usize),
    Skip,
}

/// Which vertex properties [`read_ply_bytes_with`] keeps. Positions are always read; what is not kept
/// is skipped in the data without being decoded or stored.
#[derive(Clone, Copy, Debug)]
pub struct PlyReadOptions<'a> {
    /// red/green/blue, when all three are present.
    pub colours: bool,
    /// nx/ny/nz, when all three are present. When `false` they are skipped (not kept as scalars).
    pub normals: bool,
    /// The other scalar properties to keep: `None` keeps every one, `Some(names)` only those named.
    pub scalars: Option<&'a [&'a str]>,
}

impl Default for PlyReadOptions<'_> {
    /// Everything (what [`read_ply`] and [`read_ply_bytes`] keep).
    fn default() -> Self {
        Self {
            colours: true,
            normals: true,
            scalars: None,
        }
    }
}

impl<'a> PlyReadOptions<'a> {
    /// Positions, colours and the named scalars only (no normals).
    pub fn only(scalars: &'a [&'a str]) -> Self {
        Self {
            colours: true,
            normals: false,
            scalars: Some(scalars),
        }
    }

    fn keeps_scalar(&self, name: &str) -> bool {
        self.scalars.is_none_or(|s| s.contains(&name))
    }
}

/// Maps the vertex element's properties to cloud fields. Returns targets, scalar names, and whether
/// colours / normals are complete and kept.
fn vertex_targets(el: &Element, opts: &PlyReadOptions) -> (Vec<Target>, Vec<String>, bool, bool) {
    let has = |n: &str| {
        el.props
            .iter()
            .any(|p| p.name == n && matches!(p.kind, PropKind::Scalar(_)))
    };
    let colors = opts.colours && has("red") && has("green") && has("blue");
    let normal_props = has("nx") && has("ny") && has("nz");
    let normals = opts.normals && normal_props;
    let mut names = Vec::new();
    let targets = el
        .props
        .iter()
        .map(|p| {
            if matches!(p.kind, PropKind::List { .. }) {
                return Target::Skip;
            }
            match p.name.as_str() {
                "x" => Target::Pos(0),
                "y" => Target::Pos(1),
                "z" => Target::Pos(2),
                "red" if colors => Target::Color(0),
                "green" if colors => Target::Color(1),
                "blue" if colors => Target::Color(2),
                "nx" if normals => Target::Normal(0),
                "ny" if normals => Target::Normal(1),
                "nz" if normals => Target::Normal(2),
                "nx" | "ny" | "nz" if normal_props && !opts.normals => Target::Skip,
                "red" | "green" | "blue" if !opts.colours => Target::Skip,
                name if !opts.keeps_scalar(name) => Target::Skip,
                name => {
                    names.push(name.to_string());
                    Target::Scalar(names.len() - 1)
                }
            }
        })
        .collect();
    (targets, names, colors, normals)
}

/// Colour channel value: integers are clamped to 0..=255, floats are taken as [0, 1] and scaled.
fn color_value(v: f64, ty: PlyType) -> u8 {
    let v = if ty.is_float() {
        (v * 255.0).round()
    } else {
        v
    };
    if v.is_nan() {
        0
    } else {
        v.clamp(0.0, 255.0) as u8
    }
}

/// Accumulates vertex data while an item is decoded.
struct VertexSink {
    cloud: PointCloud,
    targets: Vec<Target>,
    types: Vec<Option<PlyType>>,
    pos: [f64; 3],
    color: [u8; 3],
    normal: [f32; 3],
}

/// An empty vector with room for `count` items, or [`PlyError::TooLarge`] when the memory cannot hold it.
fn try_vec<T>(count: u64, what: &str, file: &str) -> Result<Vec<T>, PlyError> {
    let too_large = || PlyError::TooLarge {
        file: file.to_string(),
        what: format!("{count} {what}"),
        bytes: count.saturating_mul(std::mem::size_of::<T>() as u64),
    };
    let n = usize::try_from(count).map_err(|_| too_large())?;
    let mut v = Vec::new();
    v.try_reserve_exact(n).map_err(|_| too_large())?;
    Ok(v)
}

impl VertexSink {
    /// The sink of `el`'s `count` items; every buffer is reserved up front, fallibly.
    fn new(el: &Element, opts: &PlyReadOptions, file: &str) -> Result<Self, PlyError> {
        let (targets, names, colors, normals) = vertex_targets(el, opts);
        let n = el.count;
        let mut scalars = Vec::new();
        for name in names {
            let v = try_vec(n, &format!("values of '{name}'"), file)?;
            scalars.push((name, v));
        }
        let cloud = PointCloud {
            positions: try_vec(n, "positions", file)?,
            colors: colors.then(|| try_vec(n, "colours", file)).transpose()?,
            normals: normals.then(|| try_vec(n, "normals", file)).transpose()?,
            scalars,
        };
        let types = el
            .props
            .iter()
            .map(|p| match p.kind {
                PropKind::Scalar(t) => Some(t),
                PropKind::List { .. } => None,
            })
            .collect();
        Ok(Self {
            cloud,
            targets,
            types,
            pos: [0.0; 3],
            color: [0; 3],
            normal: [0.0; 3],
        })
    }

    #[inline]
    fn set(&mut self, prop: usize, v: f64) {
        match self.targets[prop] {
            Target::Pos(k) => self.pos[k] = v,
            Target::Color(k) => {
                self.color[k] = color_value(v, self.types[prop].unwrap_or(PlyType::U8))
            }
            Target::Normal(k) => self.normal[k] = v as f32,
            Target::Scalar(k) => self.cloud.scalars[k].1.push(v as f32),
            Target::Skip => {}
        }
    }

    #[inline]
    fn finish_item(&mut self) {
        self.cloud.positions.push(DVec3::from_array(self.pos));
        if let Some(c) = &mut self.cloud.colors {
            c.push(self.color);
        }
        if let Some(n) = &mut self.cloud.normals {
            n.push(Vec3::from_array(self.normal));
        }
    }
}

/// Reads a PLY file (see the module docs for what is kept). The whole file is read into memory
/// (fallibly: a file larger than the memory is a [`PlyError::TooLarge`]).
pub fn read_ply(path: &Path) -> Result<PointCloud, PlyError> {
    read_ply_with(path, &PlyReadOptions::default())
}

/// [`read_ply`] keeping only what `opts` asks for.
pub fn read_ply_with(path: &Path, opts: &PlyReadOptions) -> Result<PointCloud, PlyError> {
    let file = path.display().to_string();
    let io = |source| PlyError::Io {
        file: file.clone(),
        source,
    };
    let mut f = File::open(path).map_err(io)?;
    let len = f.metadata().map_err(io)?.len();
    let mut bytes: Vec<u8> = try_vec(len, "bytes of the file", &file)?;
    io::Read::read_to_end(&mut f, &mut bytes).map_err(io)?;
    read_ply_bytes_with(&bytes, &file, opts)
}

/// Parses PLY bytes (e.g. a file dropped into the browser); `name` is used in error messages.
pub fn read_ply_bytes(bytes: &[u8], name: &str) -> Result<PointCloud, PlyError> {
    read_ply_bytes_with(bytes, name, &PlyReadOptions::default())
}

/// [`read_ply_bytes`] keeping only what `opts` asks for: the rest is skipped, never decoded or stored.
pub fn read_ply_bytes_with(
    bytes: &[u8],
    name: &str,
    opts: &PlyReadOptions,
) -> Result<PointCloud, PlyError> {
    let header = parse_header(bytes, name)?;
    let vertex = header.elements.iter().position(|e| e.name == "vertex");
    let Some(vi) = vertex else {
        return Err(PlyError::MissingXyz {
            file: name.to_string(),
        });
    };
    let el = &header.elements[vi];
    let (targets, ..) = vertex_targets(el, opts);
    for k in 0..3 {
        if !targets.contains(&Target::Pos(k)) {
            return Err(PlyError::MissingXyz {
                file: name.to_string(),
            });
        }
    }
    let data = &bytes[header.data_start..];
    match header.format {
        PlyFormat::Ascii => read_ascii(data, &header.elements, vi, opts, name),
        PlyFormat::BinaryLe => read_binary(data, &header.elements, vi, opts, false, name),
        PlyFormat::BinaryBe => read_binary(data, &header.elements, vi, opts, true, name),
    }
}

fn read_binary(
    data: &[u8],
    elements: &[Element],
    vertex: usize,
    opts: &PlyReadOptions,
    big_endian: bool,
    file: &str,
) -> Result<PointCloud, PlyError> {
    let mut pos = 0usize;
    let mut out = None;
    let truncated = |el: &Element, i: u64| PlyError::Truncated {
        file: file.to_string(),
        reason: format!(
            "data ends inside element '{}' item {i} of {}",
            el.name, el.count
        ),
    };
    for (ei, el) in elements.iter().enumerate() {
        let available = (data.len() - pos) as u64;
        let min_item = el.min_binary_item_bytes();
        if el
            .count
            .checked_mul(min_item)
            .is_none_or(|need| need > available)
        {
            return Err(PlyError::CountTooLarge {
                file: file.to_string(),
                element: el.name.clone(),
                count: el.count,
                available,
                min_item_bytes: min_item,
            });
        }
        // The check above bounds count by the data size when items have bytes; itemless elements
        // (no properties) are legal but carry nothing, so there is nothing to loop over.
        if min_item == 0 {
            continue;
        }
        let fixed = el
            .props
            .iter()
            .all(|p| matches!(p.kind, PropKind::Scalar(_)));
        if ei != vertex {
            if fixed {
                pos += (el.count * min_item) as usize;
                continue;
            }
            for i in 0..el.count {
                for p in &el.props {
                    pos = skip_binary_prop(data, pos, &p.kind, big_endian)
                        .ok_or_else(|| truncated(el, i))?;
                }
            }
            continue;
        }
        let mut sink = VertexSink::new(el, opts, file)?;
        for i in 0..el.count {
            for (pi, p) in el.props.iter().enumerate() {
                match p.kind {
                    PropKind::Scalar(t) => {
                        if sink.targets[pi] != Target::Skip {
                            let b = data
                                .get(pos..pos + t.size())
                                .ok_or_else(|| truncated(el, i))?;
                            sink.set(pi, t.decode(b, big_endian));
                        } else if pos + t.size() > data.len() {
                            return Err(truncated(el, i));
                        }
                        pos += t.size();
                    }
                    PropKind::List { .. } => {
                        pos = skip_binary_prop(data, pos, &p.kind, big_endian)
                            .ok_or_else(|| truncated(el, i))?;
                    }
                }
            }
            sink.finish_item();
        }
        out = Some(sink.cloud);
    }
    // Trailing bytes after the last element are tolerated (some writers pad).
    out.ok_or_else(|| PlyError::MissingXyz {
        file: file.to_string(),
    })
}

/// A PLY's vertices handed out in chunks, without holding the whole file: what the COPC export streams
/// a map through (a 100 M-point map is ~6 GB of PLY). A binary PLY whose vertex items are all scalars, and
/// whose elements before the vertices are too, is read from disk chunk by chunk; any other PLY (ASCII,
/// lists among the vertex properties) is read whole as [`read_ply_with`] reads it and handed out from memory.
pub struct PlyChunks {
    file: String,
    total: u64,
    done: u64,
    opts_scalars: Vec<String>,
    colours: bool,
    source: ChunkSource,
}

enum ChunkSource {
    Disk {
        reader: io::BufReader<File>,
        vertex: Element,
        item_bytes: usize,
        big_endian: bool,
        buffer: Vec<u8>,
    },
    Memory(PointCloud),
}

impl PlyChunks {
    /// Opens `path` keeping positions, colours and every scalar property but normals.
    pub fn open(path: &Path) -> Result<Self, PlyError> {
        let file = path.display().to_string();
        let io_err = |source| PlyError::Io {
            file: file.clone(),
            source,
        };
        let mut f = File::open(path).map_err(io_err)?;
        let len = f.metadata().map_err(io_err)?.len();
        let mut head = Vec::new();
        io::Read::read_to_end(
            &mut io::Read::take(&mut f, MAX_HEADER_BYTES as u64 + 1),
            &mut head,
        )
        .map_err(io_err)?;
        let header = parse_header(&head, &file)?;
        let opts = PlyReadOptions {
            colours: true,
            normals: false,
            scalars: None,
        };
        let vi = header
            .elements
            .iter()
            .position(|e| e.name == "vertex")
            .ok_or_else(|| PlyError::MissingXyz { file: file.clone() })?;
        let vertex = header.elements[vi].clone();
        let (targets, names, colours, _) = vertex_targets(&vertex, &opts);
        if (0..3).any(|k| !targets.contains(&Target::Pos(k))) {
            return Err(PlyError::MissingXyz { file });
        }
        let scalar = |e: &Element| {
            e.props
                .iter()
                .all(|p| matches!(p.kind, PropKind::Scalar(_)))
        };
        let streams = header.format != PlyFormat::Ascii
            && header.elements[..=vi].iter().all(scalar)
            && vertex.min_binary_item_bytes() > 0;
        if !streams {
            let cloud = read_ply_with(path, &opts)?;
            return Ok(Self {
                file,
                total: cloud.len() as u64,
                done: 0,
                opts_scalars: names,
                colours: cloud.colors.is_some(),
                source: ChunkSource::Memory(cloud),
            });
        }
        // Every element before the vertices is skipped by its size; the vertices must fit the file.
        let mut skip = header.data_start as u64;
        for e in &header.elements[..vi] {
            skip = e
                .count
                .checked_mul(e.min_binary_item_bytes())
                .and_then(|b| b.checked_add(skip))
                .unwrap_or(u64::MAX);
        }
        let item = vertex.min_binary_item_bytes();
        let available = len.saturating_sub(skip);
        if vertex
            .count
            .checked_mul(item)
            .is_none_or(|need| need > available)
        {
            return Err(PlyError::CountTooLarge {
                file,
                element: vertex.name.clone(),
                count: vertex.count,
                available,
                min_item_bytes: item,
            });
        }
        io::Seek::seek(&mut f, io::SeekFrom::Start(skip)).map_err(io_err)?;
        Ok(Self {
            total: vertex.count,
            done: 0,
            opts_scalars: names,
            colours,
            source: ChunkSource::Disk {
                reader: io::BufReader::with_capacity(1 << 20, f),
                item_bytes: item as usize,
                big_endian: header.format == PlyFormat::BinaryBe,
                vertex,
                buffer: Vec::new(),
            },
            file,
        })
    }

    /// How many points the file holds.
    pub fn len(&self) -> u64 {
        self.total
    }

    /// Whether the file holds no point.
    pub fn is_empty(&self) -> bool {
        self.total == 0
    }

    /// The scalar properties each chunk carries, in file order.
    pub fn scalar_names(&self) -> &[String] {
        &self.opts_scalars
    }

    /// Whether the chunks carry colours.
    pub fn has_colours(&self) -> bool {
        self.colours
    }

    /// The next at most `max` points (at least one), or `None` after the last.
    pub fn next_chunk(&mut self, max: usize) -> Result<Option<PointCloud>, PlyError> {
        let n = (self.total - self.done).min(max.max(1) as u64);
        if n == 0 {
            return Ok(None);
        }
        let start = self.done as usize;
        self.done += n;
        match &mut self.source {
            ChunkSource::Memory(cloud) => {
                let idx: Vec<usize> = (start..start + n as usize).collect();
                let mut c = cloud.select(&idx);
                c.normals = None;
                Ok(Some(c))
            }
            ChunkSource::Disk {
                reader,
                vertex,
                item_bytes,
                big_endian,
                buffer,
            } => {
                let bytes = n as usize * *item_bytes;
                buffer.resize(bytes, 0);
                io::Read::read_exact(reader, buffer).map_err(|e| {
                    if e.kind() == io::ErrorKind::UnexpectedEof {
                        PlyError::Truncated {
                            file: self.file.clone(),
                            reason: format!(
                                "data ends inside the vertices after item {start} of {}",
                                self.total
                            ),
                        }
                    } else {
                        PlyError::Io {
                            file: self.file.clone(),
                            source: e,
                        }
                    }
                })?;
                let mut el = vertex.clone();
                el.count = n;
                let opts = PlyReadOptions {
                    colours: true,
                    normals: false,
                    scalars: None,
                };
                let mut sink = VertexSink::new(&el, &opts, &self.file)?;
                let mut pos = 0usize;
                for _ in 0..n {
                    for (pi, p) in el.props.iter().enumerate() {
                        if let PropKind::Scalar(t) = p.kind {
                            if sink.targets[pi] != Target::Skip {
                                sink.set(pi, t.decode(&buffer[pos..pos + t.size()], *big_endian));
                            }
                            pos += t.size();
                        }
                    }
                    sink.finish_item();
                }
                Ok(Some(sink.cloud))
            }
        }
    }
}

/// Skips one property in binary data; `None` when the data ends first.
fn skip_binary_prop(data: &[u8], pos: usize, kind: &PropKind, big_endian: bool) -> Option<usize> {
    match *kind {
        PropKind::Scalar(t) => {
            let end = pos.checked_add(t.size())?;
            (end <= data.len()).then_some(end)
        }
        PropKind::List { count, item } => {
            let n = count.decode(data.get(pos..pos + count.size())?, big_endian);
            if n.is_nan() || n < 0.0 {
                return None;
            }
            let len = (n as u64).checked_mul(item.size() as u64)?;
            let end = (pos as u64)
                .checked_add(count.size() as u64)?
                .checked_add(len)?;
            (end <= data.len() as u64).then_some(end as usize)
        }
    }
}

fn read_ascii(
    data: &[u8],
    elements: &[Element],
    vertex: usize,
    opts: &PlyReadOptions,
    file: &str,
) -> Result<PointCloud, PlyError> {
    let text = std::str::from_utf8(data).map_err(|e| PlyError::BadValue {
        file: file.to_string(),
        element: "(data)".into(),
        index: 0,
        property: "(any)".into(),
        reason: format!(
            "ASCII data is not text (invalid byte at offset {})",
            e.valid_up_to()
        ),
    })?;
    let mut tokens = text.split_ascii_whitespace();
    let mut out = None;
    let mut consumed = 0u64;
    for (ei, el) in elements.iter().enumerate() {
        // Each item needs at least one token per property and each token takes at least two bytes
        // (a character and a separator), so this bounds counts before anything is allocated.
        let available = (data.len() as u64).saturating_sub(consumed) + 1;
        let min_item = 2 * el.props.len() as u64;
        if el
            .count
            .checked_mul(min_item)
            .is_none_or(|need| need > available)
        {
            return Err(PlyError::CountTooLarge {
                file: file.to_string(),
                element: el.name.clone(),
                count: el.count,
                available,
                min_item_bytes: min_item,
            });
        }
        if el.props.is_empty() {
            continue;
        }
        let mut sink = (ei == vertex)
            .then(|| VertexSink::new(el, opts, file))
            .transpose()?;
        for i in 0..el.count {
            for (pi, p) in el.props.iter().enumerate() {
                let mut next = |what: &str| -> Result<f64, PlyError> {
                    let tok = tokens.next().ok_or_else(|| PlyError::Truncated {
                        file: file.to_string(),
                        reason: format!(
                            "data ends at element '{}' item {i} of {}, property '{}' ({what})",
                            el.name, el.count, p.name
                        ),
                    })?;
                    consumed += tok.len() as u64 + 1;
                    tok.parse::<f64>().map_err(|_| PlyError::BadValue {
                        file: file.to_string(),
                        element: el.name.clone(),
                        index: i,
                        property: p.name.clone(),
                        reason: format!("'{tok}' is not a number"),
                    })
                };
                match p.kind {
                    PropKind::Scalar(t) => {
                        let v = t.round_ascii(next("value")?);
                        if let Some(s) = &mut sink {
                            s.set(pi, v);
                        }
                    }
                    PropKind::List { .. } => {
                        let n = next("list length")?;
                        if !(n >= 0.0 && n.fract() == 0.0 && n <= data.len() as f64) {
                            return Err(PlyError::BadValue {
                                file: file.to_string(),
                                element: el.name.clone(),
                                index: i,
                                property: p.name.clone(),
                                reason: format!("list length {n} is not a plausible count"),
                            });
                        }
                        for _ in 0..n as u64 {
                            next("list item")?;
                        }
                    }
                }
            }
            if let Some(s) = &mut sink {
                s.finish_item();
            }
        }
        if let Some(s) = sink {
            out = Some(s.cloud);
        }
    }
    out.ok_or_else(|| PlyError::MissingXyz {
        file: file.to_string(),
    })
}

/// Writes `cloud` as `binary_little_endian` PLY, atomically (`<path>.tmp-<pid>` then rename). Positions
/// are written as `double` so GT evaluation loses nothing; colours as `uchar`; normals and scalars as
/// `float`.
pub fn write_ply(path: &Path, cloud: &PointCloud) -> Result<(), PlyError> {
    let file = path.display().to_string();
    cloud.validate().map_err(|reason| PlyError::InvalidCloud {
        file: file.clone(),
        reason,
    })?;
    write_atomic(path, |w| write_ply_to(w, cloud)).map_err(|source| PlyError::Io { file, source })
}

/// The bytes [`write_ply`] would write (for downloads from the browser).
pub fn write_ply_bytes(cloud: &PointCloud) -> Result<Vec<u8>, PlyError> {
    cloud.validate().map_err(|reason| PlyError::InvalidCloud {
        file: "(memory)".into(),
        reason,
    })?;
    let mut out = Vec::new();
    write_ply_to(&mut out, cloud).map_err(|source| PlyError::Io {
        file: "(memory)".into(),
        source,
    })?;
    Ok(out)
}

/// Writes a validated cloud.
fn write_ply_to(w: &mut impl Write, cloud: &PointCloud) -> io::Result<()> {
    let mut h = String::new();
    h.push_str("ply\nformat binary_little_endian 1.0\ncomment written by silvr-core\n");
    h.push_str(&format!("element vertex {}\n", cloud.len()));
    h.push_str("property double x\nproperty double y\nproperty double z\n");
    if cloud.colors.is_some() {
        h.push_str("property uchar red\nproperty uchar green\nproperty uchar blue\n");
    }
    if cloud.normals.is_some() {
        h.push_str("property float nx\nproperty float ny\nproperty float nz\n");
    }
    for (name, _) in &cloud.scalars {
        h.push_str(&format!("property float {name}\n"));
    }
    h.push_str("end_header\n");
    w.write_all(h.as_bytes())?;
    let mut rec = Vec::with_capacity(24 + 3 + 12 + 4 * cloud.scalars.len());
    for i in 0..cloud.len() {
        rec.clear();
        let p = cloud.positions[i];
        for v in [p.x, p.y, p.z] {
            rec.extend_from_slice(&v.to_le_bytes());
        }
        if let Some(c) = &cloud.colors {
            rec.extend_from_slice(&c[i]);
        }
        if let Some(n) = &cloud.normals {
            for v in n[i].to_array() {
                rec.extend_from_slice(&v.to_le_bytes());
            }
        }
        for (_, s) in &cloud.scalars {
            rec.extend_from_slice(&s[i].to_le_bytes());
        }
        w.write_all(&rec)?;
    }
    w.flush()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_xoshiro::Xoshiro256PlusPlus;

    fn tmp_dir(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("silvr-pc-{tag}-{}", std::process::id()));
        fs::create_dir_all(&d).unwrap();
        d
    }

    fn sample_cloud(n: usize, seed: u64) -> PointCloud {
        let mut r = Xoshiro256PlusPlus::seed_from_u64(seed);
        let mut c = PointCloud::new();
        for _ in 0..n {
            let p = DVec3::new(
                r.random_range(-1e3..1e3),
                r.random_range(-1e3..1e3),
                r.random::<f64>(),
            );
            c.push_colored(p, [r.random(), r.random(), r.random()]);
        }
        c.normals = Some(
            (0..n)
                .map(|i| Vec3::new(i as f32, 1.0, -0.5).normalize())
                .collect(),
        );
        c.set_scalar("uncertainty", (0..n).map(|i| i as f32 * 0.25).collect());
        c.set_scalar("error_m", (0..n).map(|i| -(i as f32)).collect());
        c
    }

    /// Chunks of a streamed binary PLY, and of an ASCII one read whole, join to what `read_ply` reads
    /// (normals left out); a file cut inside the vertices is refused up front, naming it.
    #[test]
    fn chunks_join_to_the_whole_cloud() {
        let dir = tmp_dir("chunks");
        let c = sample_cloud(103, 4);
        let bin = dir.join("c.ply");
        write_ply(&bin, &c).unwrap();
        let mut ascii = format!(
            "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\n\
             property float z\nproperty float error_m\nend_header\n",
            c.len()
        );
        for (i, p) in c.positions.iter().enumerate() {
            ascii += &format!(
                "{} {} {} {}\n",
                p.x as f32,
                p.y as f32,
                p.z as f32,
                -(i as f32)
            );
        }
        let asc = dir.join("a.ply");
        fs::write(&asc, ascii).unwrap();
        for path in [&bin, &asc] {
            let whole = read_ply(path).unwrap();
            let mut chunks = PlyChunks::open(path).unwrap();
            assert_eq!(chunks.len(), 103);
            let mut joined = PointCloud::new();
            let mut sizes = vec![];
            while let Some(k) = chunks.next_chunk(25).unwrap() {
                sizes.push(k.len());
                assert!(k.normals.is_none());
                joined.positions.extend(&k.positions);
                if let Some(col) = k.colors {
                    joined.colors.get_or_insert_with(Vec::new).extend(col);
                }
                for (name, v) in k.scalars {
                    match joined.scalars.iter_mut().find(|(n, _)| *n == name) {
                        Some((_, all)) => all.extend(v),
                        None => joined.scalars.push((name, v)),
                    }
                }
            }
            assert_eq!(sizes, [25, 25, 25, 25, 3]);
            assert_eq!(joined.positions, whole.positions);
            assert_eq!(joined.colors, whole.colors);
            assert_eq!(joined.scalars, whole.scalars);
            assert_eq!(chunks.scalar_names().len(), whole.scalars.len());
        }
        let bytes = fs::read(&bin).unwrap();
        let cut = dir.join("cut.ply");
        fs::write(&cut, &bytes[..bytes.len() - 10]).unwrap();
        let e = PlyChunks::open(&cut).err().unwrap().to_string();
        assert!(
            e.contains("cut.ply") && e.contains("claims 103 items"),
            "{e}"
        );
    }

    #[test]
    fn binary_round_trip_is_exact() {
        let dir = tmp_dir("rt");
        let path = dir.join("cloud.ply");
        let mut c = sample_cloud(257, 1);
        c.positions[3] = DVec3::new(f64::NAN, 0.0, 1.0);
        write_ply(&path, &c).unwrap();
        let back = read_ply(&path).unwrap();
        assert_eq!(back.len(), c.len());
        assert_eq!(back.colors, c.colors);
        assert_eq!(back.normals, c.normals);
        assert_eq!(back.scalars, c.scalars);
        assert_eq!(back.count_nonfinite(), 1);
        for (a, b) in back.positions.iter().zip(&c.positions) {
            assert!(a == b || (a.x.is_nan() && b.x.is_nan()), "{a} != {b}");
        }
        // No temporary file is left behind and the bytes API matches the file.
        assert_eq!(fs::read_dir(&dir).unwrap().count(), 1);
        assert_eq!(fs::read(&path).unwrap(), write_ply_bytes(&c).unwrap());
        fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn ascii_with_faces_and_extra_properties_parses() {
        let text = "ply\r\nformat ascii 1.0\r\ncomment hello\r\nelement vertex 3\r\n\
            property float x\nproperty float y\nproperty double z\nproperty uchar red\n\
            property uchar green\nproperty uchar blue\nproperty float intensity\n\
            property list uchar int vertex_indices\nproperty float nx\n\
            element face 2\nproperty list uchar int vertex_indices\nproperty uchar flag\nend_header\n\
            0.1 0.2 0.3 255 0 10 7.5 2 1 2 1\n\
            1 2 3 1 2 3 nan 0 0\n\
            -1e3 4 5.25 9 8 7 -1 3 0 0 0 2\n\
            3 0 1 2 5\n4 0 1 2 0 6\n";
        let c = read_ply_bytes(text.as_bytes(), "mem.ply").unwrap();
        assert_eq!(c.len(), 3);
        assert_eq!(
            c.positions[0],
            DVec3::new(0.1f32 as f64, 0.2f32 as f64, 0.3)
        );
        assert_eq!(c.positions[2], DVec3::new(-1000.0, 4.0, 5.25));
        assert_eq!(c.colors.as_ref().unwrap()[0], [255, 0, 10]);
        assert!(c.normals.is_none(), "only nx present: kept as a scalar");
        assert_eq!(c.scalars.len(), 2);
        assert_eq!(c.scalar("nx").unwrap(), &[1.0, 0.0, 2.0]);
        let i = c.scalar("intensity").unwrap();
        assert_eq!(i[0], 7.5);
        assert!(i[1].is_nan());
    }

    #[test]
    fn big_endian_binary_parses() {
        let mut b = b"ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty float x\n\
            property float y\nproperty float z\nproperty short s\nend_header\n"
            .to_vec();
        for (p, s) in [([1.5f32, -2.0, 3.25], -7i16), ([0.0, 1e-3, 42.0], 300)] {
            for v in p {
                b.extend_from_slice(&v.to_be_bytes());
            }
            b.extend_from_slice(&s.to_be_bytes());
        }
        let c = read_ply_bytes(&b, "be.ply").unwrap();
        assert_eq!(c.positions[0], DVec3::new(1.5, -2.0, 3.25));
        assert_eq!(c.positions[1].y, 1e-3f32 as f64);
        assert_eq!(c.scalar("s").unwrap(), &[-7.0, 300.0]);
    }

    #[test]
    fn binary_faces_before_vertices_are_skipped() {
        let mut b = b"ply\nformat binary_little_endian 1.0\nelement face 2\n\
            property list uchar uint vertex_indices\nelement vertex 1\nproperty double x\n\
            property double y\nproperty double z\nend_header\n"
            .to_vec();
        b.push(3);
        for i in [0u32, 1, 2] {
            b.extend_from_slice(&i.to_le_bytes());
        }
        b.push(0);
        for v in [1.0f64, 2.0, 3.0] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        let c = read_ply_bytes(&b, "faces.ply").unwrap();
        assert_eq!(c.positions, vec![DVec3::new(1.0, 2.0, 3.0)]);
    }

    #[test]
    fn malformed_files_are_errors_that_name_the_file() {
        let good = write_ply_bytes(&sample_cloud(10, 2)).unwrap();
        let header_len = good.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let mut cases: Vec<(&str, Vec<u8>)> = vec![
            ("empty", Vec::new()),
            ("not ply", b"PLY\nformat ascii 1.0\nend_header\n".to_vec()),
            ("no end_header", good[..header_len - 5].to_vec()),
            ("truncated data", good[..good.len() - 3].to_vec()),
            ("header only", good[..header_len].to_vec()),
            (
                "no xyz",
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n"
                    .to_vec(),
            ),
            (
                "no vertex",
                b"ply\nformat ascii 1.0\nelement face 0\nend_header\n".to_vec(),
            ),
            (
                "bad format",
                b"ply\nformat binary_middle_endian 1.0\nend_header\n".to_vec(),
            ),
            (
                "bad type",
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n".to_vec(),
            ),
            (
                "bad count",
                b"ply\nformat ascii 1.0\nelement vertex -3\nend_header\n".to_vec(),
            ),
            (
                "ascii junk",
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
                  property float z\nend_header\n1 2 abc\n"
                    .to_vec(),
            ),
            (
                "ascii short",
                b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n\
                  property float z\nend_header\n1 2 3\n4 5\n"
                    .to_vec(),
            ),
            ("garbage", vec![0xff; 4096]),
        ];
        // Absurd counts must be refused before allocating.
        let mut huge =
            b"ply\nformat binary_little_endian 1.0\nelement vertex 18446744073709551615\n\
            property double x\nproperty double y\nproperty double z\nend_header\n"
                .to_vec();
        huge.extend_from_slice(&[0u8; 48]);
        cases.push(("huge count", huge));
        let mut big = b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\n\
            property float x\nproperty float y\nproperty float z\nend_header\n"
            .to_vec();
        big.extend_from_slice(&[0u8; 24]);
        cases.push(("absurd count", big));
        // A face list whose length runs past the end of the data.
        let mut list = b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n\
            property float y\nproperty float z\nelement face 1\nproperty list uchar int idx\nend_header\n"
            .to_vec();
        list.extend_from_slice(&[0u8; 12]);
        list.push(200);
        list.extend_from_slice(&[0u8; 8]);
        cases.push(("truncated list", list));
        // Every prefix of a valid binary file is either an error or (only at full length) the cloud.
        for cut in (0..good.len()).step_by(7) {
            if let Ok(c) = read_ply_bytes(&good[..cut], "prefix.ply") {
                panic!(
                    "prefix {cut} of {} parsed to {} points",
                    good.len(),
                    c.len()
                );
            }
        }
        for (what, bytes) in cases {
            let err = read_ply_bytes(&bytes, "broken.ply").expect_err(what);
            assert!(err.to_string().starts_with("broken.ply: "), "{what}: {err}");
        }
        // Files that do not exist name themselves too.
        let err = read_ply(Path::new("/nonexistent/dir/x.ply")).unwrap_err();
        assert!(err.to_string().contains("/nonexistent/dir/x.ply"), "{err}");
    }

    #[test]
    fn random_corruption_never_panics() {
        let good = write_ply_bytes(&sample_cloud(20, 3)).unwrap();
        let mut r = Xoshiro256PlusPlus::seed_from_u64(9);
        for _ in 0..500 {
            let mut b = good.clone();
            for _ in 0..r.random_range(1..6) {
                let i = r.random_range(0..b.len());
                b[i] = r.random();
            }
            let _ = read_ply_bytes(&b, "fuzz.ply");
        }
    }

    #[test]
    fn options_keep_only_what_is_asked() {
        let c = sample_cloud(30, 5);
        let bin = write_ply_bytes(&c).unwrap();
        let mut ascii = String::from(
            "ply\nformat ascii 1.0\nelement vertex 30\nproperty double x\nproperty double y\n\
             property double z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n\
             property float nx\nproperty float ny\nproperty float nz\nproperty float uncertainty\n\
             property float error_m\nend_header\n",
        );
        for i in 0..30 {
            let (p, k, n) = (
                c.positions[i],
                c.colors.as_ref().unwrap()[i],
                c.normals.as_ref().unwrap()[i],
            );
            ascii.push_str(&format!(
                "{:?} {:?} {:?} {} {} {} {:?} {:?} {:?} {:?} {:?}\n",
                p.x,
                p.y,
                p.z,
                k[0],
                k[1],
                k[2],
                n.x,
                n.y,
                n.z,
                c.scalar("uncertainty").unwrap()[i],
                c.scalar("error_m").unwrap()[i]
            ));
        }
        for bytes in [&bin[..], ascii.as_bytes()] {
            let only =
                read_ply_bytes_with(bytes, "o.ply", &PlyReadOptions::only(&["error_m"])).unwrap();
            assert_eq!(only.positions, c.positions);
            assert_eq!(only.colors, c.colors);
            assert_eq!(only.normals, None, "normals are not asked for");
            assert_eq!(
                only.scalars.len(),
                1,
                "{:?}",
                only.scalars.iter().map(|s| &s.0).collect::<Vec<_>>()
            );
            assert_eq!(only.scalar("error_m"), c.scalar("error_m"));
            let none = PlyReadOptions {
                colours: false,
                scalars: Some(&[]),
                ..PlyReadOptions::default()
            };
            let bare = read_ply_bytes_with(bytes, "b.ply", &none).unwrap();
            assert_eq!(
                (bare.colors, bare.normals.is_some(), bare.scalars.len()),
                (None, true, 0)
            );
            // The default keeps everything.
            assert_eq!(
                read_ply_bytes_with(bytes, "a.ply", &PlyReadOptions::default()).unwrap(),
                read_ply_bytes(bytes, "a.ply").unwrap()
            );
        }
        // Skipped properties are still bounds-checked: a truncated file stays an error.
        for cut in [1, 2, 5] {
            let e = read_ply_bytes_with(
                &bin[..bin.len() - cut],
                "cut.ply",
                &PlyReadOptions::only(&[]),
            );
            assert!(e.is_err(), "{cut}");
        }
        let mut listed = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n\
            property float y\nproperty float z\nproperty list uchar int idx\nproperty float s\nend_header\n"
            .to_vec();
        listed.extend_from_slice(&[0; 12 + 1 + 4]); // xyz, an empty list, s
        listed.extend_from_slice(&[0; 12]);
        listed.push(3); // a list of three
        listed.extend_from_slice(&[0; 12 + 2]); // and `s` cut short
        let e = read_ply_bytes_with(&listed, "cut.ply", &PlyReadOptions::only(&[]));
        assert!(matches!(e, Err(PlyError::Truncated { .. })), "{e:?}");
    }

    /// A count the memory cannot hold is an error, not an abort (`Vec::with_capacity` would abort).
    #[test]
    fn buffers_too_large_for_memory_are_errors() {
        let e = try_vec::<DVec3>(u64::MAX / 4, "positions", "huge.ply").unwrap_err();
        assert!(matches!(e, PlyError::TooLarge { .. }), "{e:?}");
        let e = e.to_string();
        assert!(
            e.starts_with("huge.ply: too large") && e.contains("4611686018427387903 positions"),
            "{e}"
        );
        assert!(
            try_vec::<DVec3>(1000, "positions", "ok.ply")
                .unwrap()
                .capacity()
                >= 1000
        );
    }

    #[test]
    fn invalid_clouds_are_refused_on_write() {
        let mut c = sample_cloud(4, 4);
        c.scalars.push(("bad name".into(), vec![0.0; 4]));
        assert!(matches!(
            write_ply_bytes(&c),
            Err(PlyError::InvalidCloud { .. })
        ));
        let mut c = sample_cloud(4, 4);
        c.colors.as_mut().unwrap().pop();
        assert!(write_ply_bytes(&c).is_err());
        let mut c = sample_cloud(4, 4);
        c.scalars.push(("x".into(), vec![0.0; 4]));
        assert!(write_ply_bytes(&c).is_err());
    }

    #[test]
    fn voxel_downsample_takes_centroids_in_first_seen_order() {
        let mut c = PointCloud::new();
        c.push_colored(DVec3::new(0.01, 0.01, 0.01), [10, 0, 0]);
        c.push_colored(DVec3::new(0.55, 0.01, 0.01), [0, 0, 0]);
        c.push_colored(DVec3::new(0.03, 0.05, 0.07), [20, 0, 0]);
        c.push_colored(DVec3::new(f64::NAN, 0.0, 0.0), [0, 0, 0]);
        c.push_colored(DVec3::new(-0.01, 0.0, 0.0), [0, 0, 9]);
        c.set_scalar("s", vec![1.0, 5.0, 3.0, 0.0, 4.0]);
        let d = c.voxel_downsample(0.1);
        assert_eq!(d.len(), 3);
        assert!((d.positions[0] - DVec3::new(0.02, 0.03, 0.04)).length() < 1e-15);
        assert_eq!(d.positions[1], DVec3::new(0.55, 0.01, 0.01));
        assert_eq!(d.positions[2], DVec3::new(-0.01, 0.0, 0.0));
        assert_eq!(d.colors.as_ref().unwrap()[0], [15, 0, 0]);
        assert_eq!(d.scalar("s").unwrap(), &[2.0, 5.0, 4.0]);
        // Idempotent on its own output (centroids stay in their voxels).
        assert_eq!(d.voxel_downsample(0.1).len(), 3);
        assert_eq!(c.voxel_downsample(0.0).len(), c.len());
    }

    #[test]
    fn crop_and_bounds() {
        let mut c = PointCloud::from_positions(vec![
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(1.0, 2.0, 3.0),
            DVec3::new(-1.0, 5.0, 0.5),
            DVec3::new(f64::INFINITY, 0.0, 0.0),
        ]);
        c.set_scalar("i", vec![0.0, 1.0, 2.0, 3.0]);
        assert_eq!(
            c.bounds(),
            Some((DVec3::new(-1.0, 0.0, 0.0), DVec3::new(1.0, 5.0, 3.0)))
        );
        assert_eq!(c.count_nonfinite(), 1);
        let k = c.crop_aabb(DVec3::ZERO, DVec3::new(1.0, 2.0, 3.0));
        assert_eq!(k.scalar("i").unwrap(), &[0.0, 1.0]);
        assert_eq!(PointCloud::new().bounds(), None);
        let t = DAffine3::from_translation(DVec3::X);
        assert_eq!(c.transformed(&t).positions[1], DVec3::new(2.0, 2.0, 3.0));
    }
}
