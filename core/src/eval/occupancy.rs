//! Occupancy grid for the Spires "remove unknown space" step.
//!
//! Spires builds an OctoMap (0.1 m) by ray casting every GT scan from its scanner position and drops
//! reconstruction points whose location has no octree node ("unknown"). This grid stores the same thing
//! sparsely: a hash map from integer voxel coordinates to log-odds, i.e. the leaf level of that octree
//! (OctoMap's `search` only finds a node where a leaf was updated or where pruning merged eight updated
//! leaves, so "has a node" ≡ "the leaf was updated"). Cells are `[k·res, (k+1)·res)` like OctoMap keys.
//!
//! Updates use OctoMap's default sensor model (log-odds, p_hit 0.7, p_miss 0.4, clamping 0.1192/0.971,
//! occupied when p ≥ 0.5). [`OccupancyGrid::insert_ray`] updates immediately (OctoMap `insertRay`);
//! [`OccupancyGrid::insert_scan`] does OctoMap's discretised point-cloud insertion: endpoints are
//! snapped to voxel centres and deduplicated, every voxel is updated at most once per scan, and a voxel
//! that is both traversed and hit in the same scan counts as occupied.

use crate::pointcloud::{voxel_key, write_atomic, PointCloud, VoxelHasher, VoxelMap};
use glam::DVec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::hash::{BuildHasher, BuildHasherDefault};
use std::io::Write;
use std::path::Path;
use thiserror::Error;

/// What is known about a voxel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum VoxelState {
    /// Never traversed nor hit by a ray.
    Unknown,
    Free,
    Occupied,
}

/// Probabilistic sensor model (OctoMap defaults).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct OccupancyParams {
    pub prob_hit: f64,
    pub prob_miss: f64,
    pub clamp_min: f64,
    pub clamp_max: f64,
    pub occupancy_threshold: f64,
}

impl Default for OccupancyParams {
    fn default() -> Self {
        Self {
            prob_hit: 0.7,
            prob_miss: 0.4,
            clamp_min: 0.1192,
            clamp_max: 0.971,
            occupancy_threshold: 0.5,
        }
    }
}

impl OccupancyParams {
    fn validate(&self) -> Result<(), String> {
        let p = [
            self.prob_hit,
            self.prob_miss,
            self.clamp_min,
            self.clamp_max,
            self.occupancy_threshold,
        ];
        if p.iter().any(|v| !(v.is_finite() && *v > 0.0 && *v < 1.0)) {
            return Err(format!("probabilities must lie in (0, 1): {self:?}"));
        }
        if !(self.prob_hit > 0.5 && self.prob_miss < 0.5 && self.clamp_min < self.clamp_max) {
            return Err(format!(
                "need prob_hit > 0.5 > prob_miss and clamp_min < clamp_max: {self:?}"
            ));
        }
        Ok(())
    }
}

fn logit(p: f64) -> f32 {
    (p / (1.0 - p)).ln() as f32
}

/// Errors from building, saving and loading grids; file errors name the file.
#[derive(Debug, Error)]
pub enum OccupancyError {
    #[error("voxel size must be finite and positive, got {0}")]
    BadVoxelSize(f64),
    #[error("bad occupancy parameters: {0}")]
    BadParams(String),
    #[error("{file}: {source}")]
    Io {
        file: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{file}: not an occupancy grid file (bad magic bytes)")]
    BadMagic { file: String },
    #[error(
        "{file}: unsupported occupancy grid version {version} (this build reads {FORMAT_VERSION})"
    )]
    UnsupportedVersion { file: String, version: u32 },
    #[error("{file}: truncated occupancy grid: {reason}")]
    Truncated { file: String, reason: String },
    #[error("{file}: corrupt occupancy grid: {reason}")]
    Corrupt { file: String, reason: String },
    #[error("{file}: voxel key {key:?} does not fit the file's 32-bit coordinates")]
    KeyOutOfRange { file: String, key: [i64; 3] },
}

/// Sparse voxel occupancy (see the module docs).
#[derive(Clone, Debug)]
pub struct OccupancyGrid {
    voxel_size: f64,
    inv_voxel: f64,
    params: OccupancyParams,
    hit: f32,
    miss: f32,
    min: f32,
    max: f32,
    threshold: f32,
    cells: Cells,
}

/// The known voxels' log-odds, split by key hash into shards, so that a scan's millions of updates run
/// on every core (each shard is one thread's) and the tables grow a 64th at a time: one table of the
/// default world's 76 M cells doubled in one step, holding both copies at once. Keys are packed into 64
/// bits ([`pack`]: ±2^21 voxels across, ±2^19 up, ±210 km and ±52 km at 0.1 m), 16 B an entry instead
/// of 32; a key beyond that range (garbage coordinates) lives in `spill`, so every finite point still
/// has its voxel.
#[derive(Clone, Debug)]
struct Cells {
    shards: Vec<PackedMap>,
    spill: VoxelMap<f32>,
}

type PackedMap = HashMap<u64, f32, BuildHasherDefault<VoxelHasher>>;

const SHARDS: usize = 64;
const XY_BITS: u32 = 22;
const Z_BITS: u32 = 20;

/// A voxel key as 64 bits (x and y biased into 22 bits each, z into 20; x highest, so packed keys sort
/// as the keys do), or `None` beyond that range.
fn pack(k: &[i64; 3]) -> Option<u64> {
    let field = |v: i64, bits: u32| {
        let b = v.checked_add(1 << (bits - 1))?;
        (0..1i64 << bits).contains(&b).then_some(b as u64)
    };
    Some(
        field(k[0], XY_BITS)? << (XY_BITS + Z_BITS)
            | field(k[1], XY_BITS)? << Z_BITS
            | field(k[2], Z_BITS)?,
    )
}

fn unpack(p: u64) -> [i64; 3] {
    let field = |v: u64, bits: u32| (v & ((1 << bits) - 1)) as i64 - (1 << (bits - 1));
    [
        field(p >> (XY_BITS + Z_BITS), XY_BITS),
        field(p >> Z_BITS, XY_BITS),
        field(p, Z_BITS),
    ]
}

impl Cells {
    fn new() -> Self {
        Self {
            shards: (0..SHARDS).map(|_| PackedMap::default()).collect(),
            spill: VoxelMap::default(),
        }
    }

    /// The shard of a packed key: bits 40..46 of its hash, which neither a table's bucket index (the low
    /// bits) nor its control tag (the top 7) uses, so each shard's table still sees well-spread hashes.
    fn shard(p: u64) -> usize {
        let h = BuildHasherDefault::<VoxelHasher>::default().hash_one(p);
        ((h >> 40) as usize) % SHARDS
    }

    fn len(&self) -> usize {
        self.shards.iter().map(|m| m.len()).sum::<usize>() + self.spill.len()
    }

    fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn get(&self, k: &[i64; 3]) -> Option<&f32> {
        match pack(k) {
            Some(p) => self.shards[Self::shard(p)].get(&p),
            None => self.spill.get(k),
        }
    }

    fn contains_key(&self, k: &[i64; 3]) -> bool {
        self.get(k).is_some()
    }

    fn insert(&mut self, k: [i64; 3], v: f32) -> Option<f32> {
        match pack(&k) {
            Some(p) => self.shards[Self::shard(p)].insert(p, v),
            None => self.spill.insert(k, v),
        }
    }

    /// A key's log-odds, inserted at 0 when new.
    fn entry(&mut self, k: [i64; 3]) -> &mut f32 {
        match pack(&k) {
            Some(p) => self.shards[Self::shard(p)].entry(p).or_insert(0.0),
            None => self.spill.entry(k).or_insert(0.0),
        }
    }

    #[cfg(test)]
    fn iter(&self) -> impl Iterator<Item = ([i64; 3], f32)> + '_ {
        self.shards
            .iter()
            .flat_map(|m| m.iter().map(|(p, l)| (unpack(*p), *l)))
            .chain(self.spill.iter().map(|(k, l)| (*k, *l)))
    }

    fn values(&self) -> impl Iterator<Item = &f32> {
        self.shards
            .iter()
            .flat_map(|m| m.values())
            .chain(self.spill.values())
    }

    /// Applies `f` to the log-odds of every key in `keys` (a new voxel starts at 0), in parallel by
    /// shard. Each key's result is independent of the others', so the order does not matter.
    fn apply(&mut self, keys: &[[i64; 3]], f: impl Fn(&[i64; 3], &mut f32) + Sync) {
        let chunk = keys
            .len()
            .div_ceil(rayon::current_num_threads().max(1))
            .max(4096);
        // Per chunk of keys: (packed key, index in `keys`) by shard, and the spilled keys' indices.
        type Part = (Vec<Vec<(u64, usize)>>, Vec<usize>);
        let parts: Vec<Part> = keys
            .par_chunks(chunk)
            .enumerate()
            .map(|(c, part)| {
                let (mut by_shard, mut spilled) = (vec![Vec::new(); SHARDS], Vec::new());
                for (i, k) in part.iter().enumerate() {
                    let at = c * chunk + i;
                    match pack(k) {
                        Some(p) => by_shard[Self::shard(p)].push((p, at)),
                        None => spilled.push(at),
                    }
                }
                (by_shard, spilled)
            })
            .collect();
        self.shards.par_iter_mut().enumerate().for_each(|(s, map)| {
            for (by_shard, _) in &parts {
                for &(p, at) in &by_shard[s] {
                    f(&keys[at], map.entry(p).or_insert(0.0));
                }
            }
        });
        for (_, spilled) in &parts {
            for &at in spilled {
                f(&keys[at], self.spill.entry(keys[at]).or_insert(0.0));
            }
        }
    }
}

/// Rays longer than this many voxel steps are ignored (a 0.1 m grid allows 1000 km), so garbage
/// coordinates cannot stall the traversal.
pub const MAX_RAY_STEPS: u64 = 10_000_000;

impl OccupancyGrid {
    /// Empty grid with the OctoMap sensor model; Spires uses `voxel_size` 0.1 m.
    pub fn new(voxel_size: f64) -> Result<Self, OccupancyError> {
        Self::with_params(voxel_size, OccupancyParams::default())
    }

    pub fn with_params(voxel_size: f64, params: OccupancyParams) -> Result<Self, OccupancyError> {
        if !(voxel_size.is_finite() && voxel_size > 0.0) {
            return Err(OccupancyError::BadVoxelSize(voxel_size));
        }
        params.validate().map_err(OccupancyError::BadParams)?;
        Ok(Self {
            voxel_size,
            inv_voxel: 1.0 / voxel_size,
            params,
            hit: logit(params.prob_hit),
            miss: logit(params.prob_miss),
            min: logit(params.clamp_min),
            max: logit(params.clamp_max),
            threshold: logit(params.occupancy_threshold),
            cells: Cells::new(),
        })
    }

    pub fn voxel_size(&self) -> f64 {
        self.voxel_size
    }

    pub fn params(&self) -> OccupancyParams {
        self.params
    }

    /// Number of known (free or occupied) voxels.
    pub fn len(&self) -> usize {
        self.cells.len()
    }

    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }

    /// Integer voxel coordinates of a finite point.
    pub fn key(&self, p: DVec3) -> Option<[i64; 3]> {
        p.is_finite().then(|| voxel_key(p, self.inv_voxel))
    }

    /// Centre of a voxel.
    pub fn key_center(&self, k: [i64; 3]) -> DVec3 {
        (DVec3::new(k[0] as f64, k[1] as f64, k[2] as f64) + 0.5) * self.voxel_size
    }

    fn update(&mut self, k: [i64; 3], delta: f32) {
        let l = self.cells.entry(k);
        *l = (*l + delta).clamp(self.min, self.max);
    }

    /// Marks the voxel holding each point as surely occupied (log-odds at the upper clamp). A ground-truth
    /// grid does this for every GT point, so the GT never lies in space the grid calls unknown or free —
    /// as in Spires, where the grid is built from the very scans that make the GT cloud.
    pub fn mark_occupied(&mut self, points: &[DVec3]) {
        let max = self.max;
        let keys: Vec<[i64; 3]> = points
            .par_iter()
            .filter(|p| p.is_finite())
            .map(|p| voxel_key(*p, self.inv_voxel))
            .collect();
        self.cells.apply(&keys, |_, l| *l = max);
    }

    /// Casts one ray: voxels from the origin's up to (not including) the endpoint's are updated as free,
    /// the endpoint voxel as occupied when `hit` (a return), left alone otherwise (a max-range ray, as in
    /// OctoMap). Returns false, changing nothing, for non-finite input or rays over [`MAX_RAY_STEPS`].
    pub fn insert_ray(&mut self, origin: DVec3, endpoint: DVec3, hit: bool) -> bool {
        let mut keys = Vec::new();
        if !ray_keys(origin, endpoint, self.inv_voxel, &mut keys) {
            return false;
        }
        for k in keys {
            self.update(k, self.miss);
        }
        if hit {
            self.update(voxel_key(endpoint, self.inv_voxel), self.hit);
        }
        true
    }

    /// Inserts one scan taken from `origin` (OctoMap discretised insertion, see the module docs).
    /// Non-finite endpoints are skipped. Ray traversal runs in parallel (on the calling thread on wasm).
    /// Returns the number of rays cast (unique endpoint voxels).
    pub fn insert_scan(&mut self, origin: DVec3, endpoints: &[DVec3]) -> usize {
        if !origin.is_finite() {
            return 0;
        }
        let inv = self.inv_voxel;
        // Sorted, deduplicated key lists rather than hash sets: a scan's rays visit millions of voxel
        // keys, and sorting them (in parallel) costs a fraction of growing and merging hash tables.
        let mut ends: Vec<[i64; 3]> = endpoints
            .iter()
            .filter(|p| p.is_finite())
            .map(|p| voxel_key(*p, inv))
            .collect();
        ends.par_sort_unstable();
        ends.dedup();
        let free: Vec<[i64; 3]> = ends
            .par_chunks(1024)
            .map(|chunk| {
                let (mut all, mut keys) = (Vec::new(), Vec::new());
                for &k in chunk {
                    keys.clear();
                    if ray_keys(origin, self.key_center(k), inv, &mut keys) {
                        all.extend_from_slice(&keys);
                    }
                }
                all.sort_unstable();
                all.dedup();
                all
            })
            .reduce(Vec::new, merge_sorted);
        let (lo, hi) = (self.min, self.max);
        let (hit, miss) = (self.hit, self.miss);
        self.cells.apply(&free, |k, l| {
            if ends.binary_search(k).is_err() {
                *l = (*l + miss).clamp(lo, hi);
            }
        });
        self.cells
            .apply(&ends, |_, l| *l = (*l + hit).clamp(lo, hi));
        ends.len()
    }

    /// State of the voxel holding `p` (non-finite points are Unknown).
    pub fn state_at(&self, p: DVec3) -> VoxelState {
        self.key(p)
            .map_or(VoxelState::Unknown, |k| self.state_of_key(k))
    }

    pub fn state_of_key(&self, k: [i64; 3]) -> VoxelState {
        match self.cells.get(&k) {
            None => VoxelState::Unknown,
            Some(&l) if l >= self.threshold => VoxelState::Occupied,
            Some(_) => VoxelState::Free,
        }
    }

    /// Log-odds of a known voxel.
    pub fn log_odds(&self, k: [i64; 3]) -> Option<f32> {
        self.cells.get(&k).copied()
    }

    /// Whether the voxel holding `p` has been observed (free or occupied).
    pub fn is_known(&self, p: DVec3) -> bool {
        self.key(p).is_some_and(|k| self.cells.contains_key(&k))
    }

    /// Counts of (free, occupied) voxels.
    pub fn counts(&self) -> (usize, usize) {
        let occ = self
            .cells
            .values()
            .filter(|&&l| l >= self.threshold)
            .count();
        (self.cells.len() - occ, occ)
    }

    /// Keeps the points whose own voxel is known (free or occupied), exactly Spires'
    /// `removeUnknownPoints` (`tree.search(p) != NULL`): no neighbourhood dilation, so a surface point
    /// just outside the observed shell is dropped, as in the benchmark.
    pub fn filter_unknown(&self, cloud: &PointCloud) -> PointCloud {
        let idx = cloud.indices_where(|_, p| self.is_known(p));
        cloud.select(&idx)
    }

    /// Serialises the grid (format in [`OccupancyGrid::save`]).
    pub fn to_bytes(&self) -> Result<Vec<u8>, OccupancyError> {
        let mut out = Vec::with_capacity(HEADER_BYTES + ENTRY_BYTES * self.cells.len());
        self.write_to(&mut out, "(memory)").map_err(|e| match e {
            WriteErr::Io(source) => OccupancyError::Io {
                file: "(memory)".into(),
                source,
            },
            WriteErr::Grid(e) => e,
        })?;
        Ok(out)
    }

    fn write_to(&self, w: &mut impl Write, file: &str) -> Result<(), WriteErr> {
        // The entries in key order. The packed keys sort as the keys do, so the order is the packed
        // keys' alone (8 B an entry; the default world's 76 M cells made a sorted copy of whole entries the
        // generator's peak), each log-odds looked up as it is written. Spilled keys (beyond the packed
        // range) are merged in; every key must fit the file's i32.
        let mut packed: Vec<u64> = self
            .cells
            .shards
            .iter()
            .flat_map(|m| m.keys().copied())
            .collect();
        packed.par_sort_unstable();
        let mut spilled: Vec<([i64; 3], f32)> =
            self.cells.spill.iter().map(|(k, l)| (*k, *l)).collect();
        spilled.sort_unstable_by_key(|e| e.0);
        let small = |k: [i64; 3]| {
            let [Some(x), Some(y), Some(z)] = k.map(|c| i32::try_from(c).ok()) else {
                return Err(WriteErr::Grid(OccupancyError::KeyOutOfRange {
                    file: file.to_string(),
                    key: k,
                }));
            };
            Ok([x, y, z])
        };
        for (k, _) in &spilled {
            small(*k)?;
        }
        let count = self.cells.len();
        // Log-odds looked up a million keys at a time, in parallel, and merged with the spilled keys.
        let mut spilled = spilled.into_iter().peekable();
        let entries = packed.chunks(1 << 20).flat_map(move |chunk| {
            let looked: Vec<([i64; 3], f32)> = chunk
                .par_iter()
                .map(|&p| (unpack(p), self.cells.shards[Cells::shard(p)][&p]))
                .collect();
            looked
        });
        let mut entries = entries.peekable();
        let entries = std::iter::from_fn(move || match (entries.peek(), spilled.peek()) {
            (Some(a), Some(b)) if b.0 < a.0 => spilled.next(),
            (Some(_), _) => entries.next(),
            (None, _) => spilled.next(),
        });
        let p = self.params;
        let mut h = Vec::with_capacity(HEADER_BYTES);
        h.extend_from_slice(MAGIC);
        h.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        h.extend_from_slice(&(ENTRY_BYTES as u32).to_le_bytes());
        for v in [
            self.voxel_size,
            p.prob_hit,
            p.prob_miss,
            p.clamp_min,
            p.clamp_max,
            p.occupancy_threshold,
        ] {
            h.extend_from_slice(&v.to_le_bytes());
        }
        h.extend_from_slice(&(count as u64).to_le_bytes());
        debug_assert_eq!(h.len(), HEADER_BYTES);
        w.write_all(&h).map_err(WriteErr::Io)?;
        let mut buf = Vec::with_capacity(ENTRY_BYTES * 4096);
        for (k, l) in entries {
            for c in small(k)? {
                buf.extend_from_slice(&c.to_le_bytes());
            }
            buf.extend_from_slice(&l.to_le_bytes());
            if buf.len() >= ENTRY_BYTES * 4096 {
                w.write_all(&buf).map_err(WriteErr::Io)?;
                buf.clear();
            }
        }
        w.write_all(&buf).map_err(WriteErr::Io)
    }

    /// Saves atomically (`<path>.tmp-<pid>`, then rename). Format, little endian: magic `SILVROCC`,
    /// u32 version (1), u32 entry size (16), f64 voxel size, f64 × 5 sensor model (p_hit, p_miss,
    /// clamp_min, clamp_max, threshold), u64 entry count, then entries sorted by key: i32 × 3 voxel
    /// coordinates and f32 log-odds. 16 bytes per observed voxel.
    pub fn save(&self, path: &Path) -> Result<(), OccupancyError> {
        let file = path.display().to_string();
        let mut grid_err = None;
        let res = write_atomic(path, |w| match self.write_to(w, &file) {
            Ok(()) => Ok(()),
            Err(WriteErr::Io(e)) => Err(e),
            Err(WriteErr::Grid(e)) => {
                grid_err = Some(e);
                Err(std::io::Error::other("grid cannot be written"))
            }
        });
        match (res, grid_err) {
            (_, Some(e)) => Err(e),
            (Err(source), None) => Err(OccupancyError::Io { file, source }),
            (Ok(()), None) => Ok(()),
        }
    }

    /// Loads a grid written by [`OccupancyGrid::save`].
    pub fn load(path: &Path) -> Result<Self, OccupancyError> {
        let file = path.display().to_string();
        let bytes = std::fs::read(path).map_err(|source| OccupancyError::Io {
            file: file.clone(),
            source,
        })?;
        Self::from_bytes(&bytes, &file)
    }

    /// Parses grid bytes; `name` appears in errors. Never panics on malformed input.
    pub fn from_bytes(bytes: &[u8], name: &str) -> Result<Self, OccupancyError> {
        let file = || name.to_string();
        if bytes.len() < MAGIC.len() || &bytes[..MAGIC.len()] != MAGIC {
            return Err(OccupancyError::BadMagic { file: file() });
        }
        if bytes.len() < HEADER_BYTES {
            return Err(OccupancyError::Truncated {
                file: file(),
                reason: format!(
                    "{} bytes, the header alone needs {HEADER_BYTES}",
                    bytes.len()
                ),
            });
        }
        let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().unwrap_or([0; 4]));
        let f64_at = |o: usize| f64::from_le_bytes(bytes[o..o + 8].try_into().unwrap_or([0; 8]));
        let version = u32_at(8);
        if version != FORMAT_VERSION {
            return Err(OccupancyError::UnsupportedVersion {
                file: file(),
                version,
            });
        }
        let entry = u32_at(12);
        if entry as usize != ENTRY_BYTES {
            return Err(OccupancyError::Corrupt {
                file: file(),
                reason: format!("entry size {entry}, expected 16"),
            });
        }
        let voxel = f64_at(16);
        let params = OccupancyParams {
            prob_hit: f64_at(24),
            prob_miss: f64_at(32),
            clamp_min: f64_at(40),
            clamp_max: f64_at(48),
            occupancy_threshold: f64_at(56),
        };
        let count = u64::from_le_bytes(bytes[64..72].try_into().unwrap_or([0; 8]));
        let mut grid = Self::with_params(voxel, params).map_err(|e| OccupancyError::Corrupt {
            file: file(),
            reason: e.to_string(),
        })?;
        let body = (bytes.len() - HEADER_BYTES) as u64;
        let expected = count.checked_mul(ENTRY_BYTES as u64);
        if expected != Some(body) {
            let reason = format!(
                "header says {count} entries ({ENTRY_BYTES} bytes each) but {body} bytes follow"
            );
            return Err(if expected.is_none_or(|e| e > body) {
                OccupancyError::Truncated {
                    file: file(),
                    reason,
                }
            } else {
                OccupancyError::Corrupt {
                    file: file(),
                    reason,
                }
            });
        }
        for (i, e) in bytes[HEADER_BYTES..].chunks_exact(ENTRY_BYTES).enumerate() {
            let c = |o: usize| i32::from_le_bytes(e[o..o + 4].try_into().unwrap_or([0; 4])) as i64;
            let l = f32::from_le_bytes(e[12..16].try_into().unwrap_or([0; 4]));
            if !l.is_finite() {
                return Err(OccupancyError::Corrupt {
                    file: file(),
                    reason: format!("entry {i} has log-odds {l}"),
                });
            }
            if grid.cells.insert([c(0), c(4), c(8)], l).is_some() {
                return Err(OccupancyError::Corrupt {
                    file: file(),
                    reason: format!("entry {i} repeats a voxel"),
                });
            }
        }
        Ok(grid)
    }
}

enum WriteErr {
    Io(std::io::Error),
    Grid(OccupancyError),
}

const MAGIC: &[u8; 8] = b"SILVROCC";
const FORMAT_VERSION: u32 = 1;
const HEADER_BYTES: usize = 72;
const ENTRY_BYTES: usize = 16;

/// The union of two sorted, deduplicated key lists, sorted and deduplicated.
fn merge_sorted(a: Vec<[i64; 3]>, b: Vec<[i64; 3]>) -> Vec<[i64; 3]> {
    if a.is_empty() {
        return b;
    }
    if b.is_empty() {
        return a;
    }
    let mut out = Vec::with_capacity(a.len().max(b.len()));
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        match a[i].cmp(&b[j]) {
            std::cmp::Ordering::Less => {
                out.push(a[i]);
                i += 1;
            }
            std::cmp::Ordering::Greater => {
                out.push(b[j]);
                j += 1;
            }
            std::cmp::Ordering::Equal => {
                out.push(a[i]);
                i += 1;
                j += 1;
            }
        }
    }
    out.extend_from_slice(&a[i..]);
    out.extend_from_slice(&b[j..]);
    out
}

/// The voxels a ray from `origin` to `endpoint` traverses, in order, starting with the origin's voxel
/// and stopping before the endpoint's (OctoMap `computeRayKeys`): 3-D DDA (Amanatides & Woo 1987).
/// Empty when both lie in one voxel or the input is non-finite or over [`MAX_RAY_STEPS`].
pub fn ray_voxels(origin: DVec3, endpoint: DVec3, voxel_size: f64) -> Vec<[i64; 3]> {
    let mut out = Vec::new();
    if voxel_size.is_finite() && voxel_size > 0.0 {
        ray_keys(origin, endpoint, 1.0 / voxel_size, &mut out);
    }
    out
}

/// Appends the traversed keys to `out`; false if the ray is rejected (non-finite or too long).
fn ray_keys(origin: DVec3, endpoint: DVec3, inv: f64, out: &mut Vec<[i64; 3]>) -> bool {
    if !(origin.is_finite() && endpoint.is_finite()) {
        return false;
    }
    let start = voxel_key(origin, inv);
    let stop = voxel_key(endpoint, inv);
    if start == stop {
        return true;
    }
    let steps = (0..3).fold(0u64, |acc, i| {
        acc.saturating_add(start[i].abs_diff(stop[i]))
    });
    if steps > MAX_RAY_STEPS {
        return false;
    }
    let res = 1.0 / inv;
    let o = origin.to_array();
    let d = endpoint - origin;
    let dir = (d / d.length()).to_array();
    let mut step = [0i64; 3];
    let mut t_max = [f64::INFINITY; 3];
    let mut t_delta = [f64::INFINITY; 3];
    for i in 0..3 {
        if dir[i] != 0.0 {
            step[i] = if dir[i] > 0.0 { 1 } else { -1 };
            // Distance along the ray to the first voxel border on this axis (OctoMap's formulation).
            let border = (start[i] as f64 + 0.5) * res + step[i] as f64 * 0.5 * res;
            t_max[i] = (border - o[i]) / dir[i];
            t_delta[i] = res / dir[i].abs();
        }
    }
    let mut cur = start;
    out.push(cur);
    // Exactly `steps` unit moves lead from start to stop, one axis at a time; axes already at the stop
    // coordinate are never stepped, which keeps rounding from overshooting and bounds the loop.
    for s in 0..steps {
        let mut dim = usize::MAX;
        for i in 0..3 {
            // Ties go to the later axis, as in OctoMap.
            if cur[i] != stop[i] && (dim == usize::MAX || t_max[i] <= t_max[dim]) {
                dim = i;
            }
        }
        cur[dim] += step[dim];
        t_max[dim] += t_delta[dim];
        if s + 1 < steps {
            out.push(cur);
        }
    }
    debug_assert_eq!(cur, stop);
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The temporary path an atomic save goes through (must be gone afterwards).
    fn tmp_of(path: &Path) -> std::path::PathBuf {
        crate::pointcloud::temp_sibling(path).unwrap()
    }

    fn keys(v: &[[i64; 3]]) -> Vec<[i64; 3]> {
        v.to_vec()
    }

    /// The scan insertion (sorted key lists merged in parallel) marks exactly the voxels of the plain
    /// definition: every unique endpoint voxel hit once, every voxel a ray crosses on the way and that
    /// no endpoint occupies missed once.
    #[test]
    fn scan_insertion_matches_the_plain_definition() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(5);
        let origin = DVec3::new(0.31, -0.12, 1.7);
        let ends: Vec<DVec3> = (0..5000)
            .map(|_| {
                origin
                    + DVec3::new(
                        rng.random_range(-30.0..30.0),
                        rng.random_range(-30.0..30.0),
                        rng.random_range(-3.0..3.0),
                    )
            })
            .collect();
        let mut grid = OccupancyGrid::new(0.1).unwrap();
        grid.insert_scan(origin, &ends);
        let inv = 1.0 / grid.voxel_size;
        let occupied: std::collections::HashSet<[i64; 3]> =
            ends.iter().map(|p| voxel_key(*p, inv)).collect();
        let mut free = std::collections::HashSet::new();
        for &k in &occupied {
            let mut keys = Vec::new();
            if ray_keys(origin, grid.key_center(k), inv, &mut keys) {
                free.extend(keys);
            }
        }
        free.retain(|k| !occupied.contains(k));
        assert_eq!(grid.cells.len(), occupied.len() + free.len());
        for k in &occupied {
            assert_eq!(grid.log_odds(*k), Some(grid.hit.clamp(grid.min, grid.max)));
        }
        for k in &free {
            assert_eq!(grid.log_odds(*k), Some(grid.miss.clamp(grid.min, grid.max)));
        }
    }

    #[test]
    fn dda_axis_aligned_ray() {
        let v = ray_voxels(
            DVec3::new(0.05, 0.05, 0.05),
            DVec3::new(0.45, 0.05, 0.05),
            0.1,
        );
        assert_eq!(v, keys(&[[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]]));
        let v = ray_voxels(
            DVec3::new(0.05, 0.05, 0.05),
            DVec3::new(0.05, 0.05, -0.25),
            0.1,
        );
        assert_eq!(v, keys(&[[0, 0, 0], [0, 0, -1], [0, 0, -2]]));
        assert!(ray_voxels(DVec3::splat(0.01), DVec3::splat(0.09), 0.1).is_empty());
    }

    #[test]
    fn dda_diagonal_ray() {
        // From (0.05, 0.05) to (0.35, 0.25) in z = 0.05: slope 2/3. The ray crosses x = 0.1 at y ≈ 0.083,
        // y = 0.1 at x = 0.125, x = 0.2 at y = 0.15, y = 0.2 at x = 0.275, x = 0.3 at y ≈ 0.217.
        let v = ray_voxels(
            DVec3::new(0.05, 0.05, 0.05),
            DVec3::new(0.35, 0.25, 0.05),
            0.1,
        );
        assert_eq!(
            v,
            keys(&[[0, 0, 0], [1, 0, 0], [1, 1, 0], [2, 1, 0], [2, 2, 0]])
        );
        // A 3-D diagonal in the negative direction visits a 6-connected path of Manhattan length.
        let (a, b) = (
            DVec3::new(0.51, 0.32, 0.13),
            DVec3::new(-0.37, -0.41, -0.29),
        );
        let v = ray_voxels(a, b, 0.1);
        assert_eq!(v.len(), 9 + 8 + 4);
        assert_eq!(v[0], [5, 3, 1]);
        for w in v.windows(2) {
            let d: i64 = (0..3).map(|i| (w[1][i] - w[0][i]).abs()).sum();
            assert_eq!(d, 1, "{w:?}");
        }
        // Every listed voxel is really crossed by the segment (sampled densely).
        for k in &v {
            let lo = DVec3::new(k[0] as f64, k[1] as f64, k[2] as f64) * 0.1;
            let hit = (0..=100_000).any(|i| {
                let p = a.lerp(b, i as f64 / 100_000.0);
                p.cmpge(lo).all() && p.cmplt(lo + 0.1).all()
            });
            assert!(hit, "voxel {k:?} not on the segment");
        }
    }

    #[test]
    fn rays_mark_free_and_occupied() {
        let mut g = OccupancyGrid::new(0.1).unwrap();
        assert!(g.insert_ray(
            DVec3::new(0.05, 0.05, 0.05),
            DVec3::new(0.55, 0.05, 0.05),
            true
        ));
        assert_eq!(g.state_at(DVec3::new(0.02, 0.0, 0.0)), VoxelState::Free);
        assert_eq!(g.state_at(DVec3::new(0.45, 0.05, 0.05)), VoxelState::Free);
        assert_eq!(
            g.state_at(DVec3::new(0.52, 0.08, 0.01)),
            VoxelState::Occupied
        );
        assert_eq!(
            g.state_at(DVec3::new(0.65, 0.05, 0.05)),
            VoxelState::Unknown
        );
        assert_eq!(
            g.state_at(DVec3::new(0.25, 0.15, 0.05)),
            VoxelState::Unknown
        );
        assert_eq!(g.counts(), (5, 1));
        // A max-range ray leaves its end voxel alone.
        g.insert_ray(
            DVec3::new(0.05, 0.05, 0.05),
            DVec3::new(0.05, 0.35, 0.05),
            false,
        );
        assert_eq!(g.state_at(DVec3::new(0.05, 0.25, 0.05)), VoxelState::Free);
        assert_eq!(
            g.state_at(DVec3::new(0.05, 0.35, 0.05)),
            VoxelState::Unknown
        );
        assert!(!g.insert_ray(DVec3::NAN, DVec3::ONE, true));
        assert!(!g.insert_ray(DVec3::ZERO, DVec3::splat(1e300), true));
    }

    #[test]
    fn scan_insertion_prefers_occupied_and_filters_unknown() {
        let mut g = OccupancyGrid::new(0.1).unwrap();
        // A wall at x = 1.0 seen from the origin, plus a point behind it on the same ray as another.
        let mut ends = Vec::new();
        for iy in -5..=5 {
            for iz in -5..=5 {
                ends.push(DVec3::new(
                    1.05,
                    iy as f64 * 0.1 + 0.05,
                    iz as f64 * 0.1 + 0.05,
                ));
            }
        }
        ends.push(DVec3::new(0.55, 0.05, 0.05)); // occupied even though wall rays pass through it
        let rays = g.insert_scan(DVec3::new(0.05, 0.05, 0.05), &ends);
        assert_eq!(rays, ends.len());
        assert_eq!(
            g.state_at(DVec3::new(0.55, 0.05, 0.05)),
            VoxelState::Occupied
        );
        assert_eq!(
            g.state_at(DVec3::new(1.05, 0.35, 0.05)),
            VoxelState::Occupied
        );
        assert_eq!(g.state_at(DVec3::new(0.75, 0.05, 0.05)), VoxelState::Free);
        let cloud = PointCloud::from_positions(vec![
            DVec3::new(0.75, 0.05, 0.05), // free
            DVec3::new(1.05, 0.05, 0.05), // occupied
            DVec3::new(1.55, 0.05, 0.05), // behind the wall: never traversed
            DVec3::new(-0.55, 2.0, 0.05), // elsewhere
            DVec3::new(f64::NAN, 0.0, 0.0),
        ]);
        let kept = g.filter_unknown(&cloud);
        assert_eq!(kept.positions, cloud.positions[..2].to_vec());
    }

    #[test]
    fn log_odds_follow_octomap_defaults() {
        let mut g = OccupancyGrid::new(0.1).unwrap();
        let (o, e) = (DVec3::splat(0.05), DVec3::new(0.35, 0.05, 0.05));
        g.insert_ray(o, e, true);
        let k = g.key(e).unwrap();
        assert!((g.log_odds(k).unwrap() - 0.847_298).abs() < 1e-5);
        for _ in 0..20 {
            g.insert_ray(o, e, true);
        }
        assert!(
            (g.log_odds(k).unwrap() - logit(0.971)).abs() < 1e-6,
            "clamped at the top"
        );
        // Misses through an occupied voxel eventually free it.
        let far = DVec3::new(0.95, 0.05, 0.05);
        for _ in 0..30 {
            g.insert_ray(o, far, true);
        }
        assert_eq!(g.state_at(e), VoxelState::Free);
        assert!(
            (g.log_odds(k).unwrap() - logit(0.1192)).abs() < 1e-6,
            "clamped at the bottom"
        );
    }

    /// Keys inside the packed range and beyond it (the spill map) are all kept, and the file lists them
    /// in key order whichever map holds them.
    #[test]
    fn keys_beyond_the_packed_range_are_kept_and_written_in_order() {
        let edge = (1i64 << 21) - 1;
        let keys = [
            [0, 0, 0],
            [-1, -1, -1],
            [edge, -edge - 1, (1 << 19) - 1],
            [edge + 1, 0, 0],
            [-edge - 2, 5, 5],
            [3, 4, 1 << 19],
            [3, 4, -(1 << 19) - 1],
            [1 << 30, -(1 << 30), 7],
        ];
        for k in &keys[..3] {
            assert_eq!(pack(k).map(unpack), Some(*k), "{k:?} packs");
        }
        for k in &keys[3..] {
            assert_eq!(pack(k), None, "{k:?} is beyond the packed range");
        }
        let mut g = OccupancyGrid::new(0.1).unwrap();
        for (i, k) in keys.iter().enumerate() {
            g.cells.insert(*k, i as f32);
        }
        assert_eq!(g.len(), keys.len());
        assert!(!g.cells.spill.is_empty());
        for (i, k) in keys.iter().enumerate() {
            assert_eq!(g.log_odds(*k), Some(i as f32));
        }
        let bytes = g.to_bytes().unwrap();
        let read: Vec<[i32; 3]> = bytes[HEADER_BYTES..]
            .chunks_exact(ENTRY_BYTES)
            .map(|e| {
                std::array::from_fn(|c| i32::from_le_bytes(e[4 * c..4 * c + 4].try_into().unwrap()))
            })
            .collect();
        let mut want: Vec<[i32; 3]> = keys.iter().map(|k| k.map(|c| c as i32)).collect();
        want.sort_unstable();
        assert_eq!(read, want);
        let h = OccupancyGrid::from_bytes(&bytes, "mem").unwrap();
        for (i, k) in keys.iter().enumerate() {
            assert_eq!(h.log_odds(*k), Some(i as f32));
        }
        // A key beyond the file's i32 is an error naming it, not a wrapped coordinate.
        g.cells.insert([1 << 40, 0, 0], 1.0);
        assert!(matches!(
            g.to_bytes(),
            Err(OccupancyError::KeyOutOfRange { key, .. }) if key == [1 << 40, 0, 0]
        ));
    }

    #[test]
    fn save_load_round_trip_and_corruption() {
        let dir = std::env::temp_dir().join(format!("silvr-occ-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("observed.bin");
        let mut g = OccupancyGrid::new(0.1).unwrap();
        g.insert_scan(
            DVec3::ZERO,
            &[DVec3::new(3.0, 1.0, -2.0), DVec3::new(-1.0, 4.0, 0.5)],
        );
        g.save(&path).unwrap();
        assert!(!tmp_of(&path).exists());
        let h = OccupancyGrid::load(&path).unwrap();
        assert_eq!(h.len(), g.len());
        assert_eq!(h.voxel_size(), 0.1);
        for (k, l) in g.cells.iter() {
            assert_eq!(h.log_odds(k), Some(l));
        }
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(bytes, g.to_bytes().unwrap());
        let name = "obs.bin";
        let err = |b: &[u8]| OccupancyGrid::from_bytes(b, name).unwrap_err();
        assert!(matches!(err(&bytes[..5]), OccupancyError::BadMagic { .. }));
        assert!(matches!(
            err(&bytes[..40]),
            OccupancyError::Truncated { .. }
        ));
        assert!(matches!(
            err(&bytes[..bytes.len() - 1]),
            OccupancyError::Truncated { .. }
        ));
        let mut extra = bytes.clone();
        extra.extend_from_slice(&[0; 16 * 3]);
        assert!(matches!(err(&extra), OccupancyError::Corrupt { .. }));
        let mut v = bytes.clone();
        v[8] = 9;
        assert!(matches!(
            err(&v),
            OccupancyError::UnsupportedVersion { version: 9, .. }
        ));
        let mut v = bytes.clone();
        v[16..24].copy_from_slice(&(-1.0f64).to_le_bytes());
        assert!(matches!(err(&v), OccupancyError::Corrupt { .. }));
        let mut v = bytes.clone();
        v[64..72].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(matches!(err(&v), OccupancyError::Truncated { .. }));
        let mut v = bytes.clone();
        let n = v.len();
        v[n - 4..].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(matches!(err(&v), OccupancyError::Corrupt { .. }));
        // Duplicate keys are corruption too.
        let mut v = bytes[..HEADER_BYTES + 32].to_vec();
        v[64..72].copy_from_slice(&2u64.to_le_bytes());
        let first: Vec<u8> = v[HEADER_BYTES..HEADER_BYTES + 16].to_vec();
        v[HEADER_BYTES + 16..].copy_from_slice(&first);
        assert!(matches!(err(&v), OccupancyError::Corrupt { .. }));
        for e in [err(&bytes[..5]), err(&extra)] {
            assert!(e.to_string().starts_with("obs.bin: "), "{e}");
        }
        let missing = OccupancyGrid::load(&dir.join("nope.bin")).unwrap_err();
        assert!(missing.to_string().contains("nope.bin"), "{missing}");
        std::fs::remove_dir_all(dir).ok();
    }
}
