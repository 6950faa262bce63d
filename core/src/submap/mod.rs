//! Submaps: the trajectory split into parts that are trained separately (the paper's large-scale
//! section), by recursive normalised cuts (Shi & Malik) of a graph over the keyframes.
//!
//! A node is a keyframe (every camera of the rig at one instant, which see the same place from one
//! spot), or a single image where a dataset has no keyframes. Edges come from one of two affinities:
//! - **distance** (what SiLVR's public code does: scikit-learn's `SpectralClustering` with
//!   `affinity="nearest_neighbors"` on camera positions, i.e. the symmetrised 10-nearest-neighbour graph);
//! - **co-visibility** (the paper: edge weight = tracks two keyframes share), once `silvr poses` writes
//!   tracks.
//!
//! Each cut takes the Fiedler vector of the normalised Laplacian of the part's graph and the threshold
//! along it with the smallest normalised cut (Shi–Malik's sweep); disconnected parts are split into
//! their components first. Parts are cut until every one holds at most `max_images` images, or until
//! there are `count` parts (the largest cut first). Then each part grows by the keyframes of its
//! neighbours within `overlap_m` of one of its own, so the fields overlap at the boundaries.
//!
//! Eigenvectors: nalgebra's dense symmetric solver for parts up to 400 keyframes, faer's restarted
//! Lanczos on the sparse graph above (a dense solve is cubic: 8 s at 2,000 keyframes).

use glam::DVec3;
use nalgebra::{DMatrix, SymmetricEigen};
use serde::Serialize;

pub mod blend;

/// A weighted undirected graph over nodes `0..n` (adjacency lists, both directions stored).
#[derive(Clone, Debug, Default)]
pub struct Graph {
    pub adj: Vec<Vec<(usize, f64)>>,
}

impl Graph {
    pub fn new(n: usize) -> Self {
        Graph {
            adj: vec![Vec::new(); n],
        }
    }

    pub fn len(&self) -> usize {
        self.adj.len()
    }

    pub fn is_empty(&self) -> bool {
        self.adj.is_empty()
    }

    /// Adds `w` to the edge i–j (both directions).
    pub fn add(&mut self, i: usize, j: usize, w: f64) {
        if i == j || w <= 0.0 {
            return;
        }
        for (a, b) in [(i, j), (j, i)] {
            match self.adj[a].iter_mut().find(|e| e.0 == b) {
                Some(e) => e.1 += w,
                None => self.adj[a].push((b, w)),
            }
        }
    }

    /// Total weight of all edges (each once).
    pub fn total_weight(&self) -> f64 {
        self.adj
            .iter()
            .enumerate()
            .flat_map(|(i, e)| e.iter().filter(move |x| x.0 > i).map(|x| x.1))
            .sum()
    }

    /// Total weight of the edges between different parts (each edge once).
    pub fn cut_weight(&self, parts: &[Vec<usize>]) -> f64 {
        let mut label = vec![usize::MAX; self.len()];
        for (p, nodes) in parts.iter().enumerate() {
            for &n in nodes {
                label[n] = p;
            }
        }
        let mut w = 0.0;
        for (i, edges) in self.adj.iter().enumerate() {
            for &(j, x) in edges {
                if i < j && label[i] != label[j] {
                    w += x;
                }
            }
        }
        w
    }
}

/// The distance affinity of SiLVR's public code: each node joined to its `k` nearest neighbours by
/// position (weight 1; an edge both ways counts once), symmetrised.
pub fn distance_graph(positions: &[DVec3], k: usize) -> Graph {
    let n = positions.len();
    let mut g = Graph::new(n);
    for i in 0..n {
        let mut d: Vec<(f64, usize)> = (0..n)
            .filter(|&j| j != i)
            .map(|j| (positions[i].distance_squared(positions[j]), j))
            .collect();
        d.sort_by(|a, b| a.0.total_cmp(&b.0));
        for &(_, j) in d.iter().take(k) {
            // Connectivity, not a sum: the symmetrised kNN graph has weight 1 on each edge.
            if !g.adj[i].iter().any(|e| e.0 == j) {
                g.add(i, j, 1.0);
            }
        }
    }
    g
}

/// When to stop cutting.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Limit {
    /// Cut until every part holds at most this many images.
    MaxImages(usize),
    /// Cut (largest part first) until there are this many parts.
    Count(usize),
}

/// Splits the nodes of `g` (node i holding `images[i]` images) into parts, each sorted.
pub fn partition(g: &Graph, images: &[usize], limit: Limit) -> Vec<Vec<usize>> {
    let size = |p: &[usize]| p.iter().map(|&i| images[i]).sum::<usize>();
    let mut parts: Vec<Vec<usize>> = vec![(0..g.len()).collect()];
    // The part to cut next: the largest with more than one keyframe.
    while let Some(k) = (0..parts.len())
        .filter(|&k| parts[k].len() > 1)
        .max_by_key(|&k| size(&parts[k]))
    {
        let go = match limit {
            Limit::MaxImages(m) => size(&parts[k]) > m.max(1),
            Limit::Count(c) => parts.len() < c,
        };
        if !go {
            break;
        }
        let (a, b) = bisect(g, &parts[k]);
        parts[k] = a;
        parts.push(b);
    }
    for p in &mut parts {
        p.sort_unstable();
    }
    // In path order (by first node), so submap 0 is where the trajectory starts.
    parts.sort_by_key(|p| p[0]);
    parts
}

/// Parts up to this many keyframes take the dense symmetric eigensolver (exact, and fast at this size);
/// larger ones faer's restarted Lanczos on the sparse graph.
const DENSE_MAX: usize = 400;

/// One normalised cut of the subgraph on `nodes` (at least 2): its components when it is disconnected
/// (the largest against the rest), else Shi–Malik's sweep along the Fiedler vector.
fn bisect(g: &Graph, nodes: &[usize]) -> (Vec<usize>, Vec<usize>) {
    let m = nodes.len();
    let mut local = vec![usize::MAX; g.len()];
    for (k, &n) in nodes.iter().enumerate() {
        local[n] = k;
    }
    // The part's graph as adjacency lists in local indices (the graphs built here have no parallel
    // edges).
    let adj: Vec<Vec<(usize, f64)>> = nodes
        .iter()
        .map(|&n| {
            g.adj[n]
                .iter()
                .filter(|&&(j, _)| local[j] != usize::MAX)
                .map(|&(j, x)| (local[j], x))
                .collect()
        })
        .collect();
    let deg: Vec<f64> = adj.iter().map(|r| r.iter().map(|e| e.1).sum()).collect();
    // Components (isolated nodes included).
    let comp = components(&adj);
    let count = comp.iter().copied().max().map_or(0, |c| c + 1);
    if count > 1 {
        let mut sizes = vec![0usize; count];
        for &c in &comp {
            sizes[c] += 1;
        }
        let big = (0..count).max_by_key(|&c| sizes[c]).unwrap_or(0);
        let (a, b): (Vec<usize>, Vec<usize>) = (0..m).partition(|&i| comp[i] == big);
        let take = |v: Vec<usize>| v.into_iter().map(|i| nodes[i]).collect();
        return (take(a), take(b));
    }
    // L_sym = I − D^-½ W D^-½; its second-smallest eigenvector z, and y = D^-½ z.
    let inv_sqrt: Vec<f64> = deg.iter().map(|&d| 1.0 / d.max(1e-300).sqrt()).collect();
    let z = if m <= DENSE_MAX {
        fiedler_dense(&adj, &inv_sqrt)
    } else {
        fiedler_lanczos(&adj, &deg, &inv_sqrt)
    };
    let y: Vec<f64> = (0..m).map(|i| z[i] * inv_sqrt[i]).collect();
    // Sweep: nodes sorted by y; each prefix a candidate side, Ncut = cut/assoc(A) + cut/assoc(B).
    let mut by_y: Vec<usize> = (0..m).collect();
    by_y.sort_by(|&a, &b| y[a].total_cmp(&y[b]).then(a.cmp(&b)));
    let total: f64 = deg.iter().sum();
    let mut in_a = vec![false; m];
    let (mut cut, mut assoc_a) = (0.0, 0.0);
    let mut best = (f64::INFINITY, 1);
    for (k, &i) in by_y.iter().enumerate().take(m - 1) {
        // Moving i into A: its edges to A leave the cut, its edges to B join it.
        for &(j, x) in &adj[i] {
            if x != 0.0 {
                if in_a[j] {
                    cut -= x;
                } else if j != i {
                    cut += x;
                }
            }
        }
        in_a[i] = true;
        assoc_a += deg[i];
        let assoc_b = total - assoc_a;
        let ncut = cut / assoc_a.max(1e-300) + cut / assoc_b.max(1e-300);
        if ncut < best.0 {
            best = (ncut, k + 1);
        }
    }
    let mut a: Vec<usize> = by_y[..best.1].iter().map(|&i| nodes[i]).collect();
    let mut b: Vec<usize> = by_y[best.1..].iter().map(|&i| nodes[i]).collect();
    a.sort_unstable();
    b.sort_unstable();
    (a, b)
}

/// The eigenvector of the second-smallest eigenvalue of L_sym, by nalgebra's dense solver.
fn fiedler_dense(adj: &[Vec<(usize, f64)>], inv_sqrt: &[f64]) -> Vec<f64> {
    let m = adj.len();
    let mut l = DMatrix::<f64>::identity(m, m);
    for (i, row) in adj.iter().enumerate() {
        for &(j, x) in row {
            l[(i, j)] -= inv_sqrt[i] * x * inv_sqrt[j];
        }
    }
    let eig = SymmetricEigen::new(l);
    let mut order: Vec<usize> = (0..m).collect();
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    eig.eigenvectors.column(order[1]).iter().copied().collect()
}

/// `P (I + D^-½ W D^-½) P` with `P` the projection off `u0 = D^½ 1 / |D^½ 1|`: L_sym's spectrum turned
/// around (eigenvalue 2 − λ) with its known lowest vector removed, so the largest-magnitude eigenvector
/// that Lanczos finds first is the Fiedler vector.
#[derive(Debug)]
struct ShiftedAdjacency<'a> {
    adj: &'a [Vec<(usize, f64)>],
    inv_sqrt: &'a [f64],
    u0: Vec<f64>,
}

impl ShiftedAdjacency<'_> {
    fn project(&self, v: &mut [f64]) {
        let d: f64 = v.iter().zip(&self.u0).map(|(a, b)| a * b).sum();
        v.iter_mut().zip(&self.u0).for_each(|(a, b)| *a -= d * b);
    }

    fn apply_vec(&self, x: &[f64]) -> Vec<f64> {
        let mut px = x.to_vec();
        self.project(&mut px);
        let mut y: Vec<f64> = self
            .adj
            .iter()
            .enumerate()
            .map(|(i, row)| {
                let s: f64 = row.iter().map(|&(j, w)| w * self.inv_sqrt[j] * px[j]).sum();
                px[i] + self.inv_sqrt[i] * s
            })
            .collect();
        self.project(&mut y);
        y
    }
}

impl faer::matrix_free::LinOp<f64> for ShiftedAdjacency<'_> {
    fn apply_scratch(&self, _rhs_ncols: usize, _par: faer::Par) -> faer::dyn_stack::StackReq {
        faer::dyn_stack::StackReq::EMPTY
    }
    fn nrows(&self) -> usize {
        self.adj.len()
    }
    fn ncols(&self) -> usize {
        self.adj.len()
    }
    fn apply(
        &self,
        mut out: faer::MatMut<'_, f64>,
        rhs: faer::MatRef<'_, f64>,
        _par: faer::Par,
        _stack: &mut faer::dyn_stack::MemStack,
    ) {
        for c in 0..rhs.ncols() {
            let x: Vec<f64> = (0..rhs.nrows()).map(|i| rhs[(i, c)]).collect();
            for (i, v) in self.apply_vec(&x).into_iter().enumerate() {
                out[(i, c)] = v;
            }
        }
    }
    fn conj_apply(
        &self,
        out: faer::MatMut<'_, f64>,
        rhs: faer::MatRef<'_, f64>,
        par: faer::Par,
        stack: &mut faer::dyn_stack::MemStack,
    ) {
        // Real and symmetric: its conjugate is itself.
        self.apply(out, rhs, par, stack)
    }
}

/// The Fiedler vector by faer's restarted Lanczos on [`ShiftedAdjacency`] (O(edges) per iteration,
/// no m × m matrix); falls back to the dense solver if it does not converge.
fn fiedler_lanczos(adj: &[Vec<(usize, f64)>], deg: &[f64], inv_sqrt: &[f64]) -> Vec<f64> {
    use faer::matrix_free::eigen::{
        partial_self_adjoint_eigen, partial_self_adjoint_eigen_scratch, PartialEigenParams,
    };
    let m = adj.len();
    let norm = deg.iter().sum::<f64>().sqrt().max(1e-300);
    let op = ShiftedAdjacency {
        adj,
        inv_sqrt,
        u0: deg.iter().map(|d| d.sqrt() / norm).collect(),
    };
    // A deterministic start with no special structure, off u0.
    let mut v0: Vec<f64> = (0..m)
        .map(|i| ((i as f64 + 1.0) * 0.618_034).fract() - 0.5)
        .collect();
    op.project(&mut v0);
    let v0 = faer::Col::<f64>::from_fn(m, |i| v0[i]);
    let params = PartialEigenParams {
        min_dim: 20.min(m),
        max_dim: 60.min(m),
        max_restarts: 2000,
        ..Default::default()
    };
    let mut vecs = faer::Mat::<f64>::zeros(m, 1);
    let mut vals = [0.0f64; 1];
    let mut mem = faer::dyn_stack::MemBuffer::new(partial_self_adjoint_eigen_scratch(
        &op,
        1,
        faer::Par::Seq,
        params,
    ));
    let info = partial_self_adjoint_eigen(
        vecs.as_mut(),
        &mut vals,
        &op,
        v0.as_ref(),
        1e-10,
        faer::Par::Seq,
        faer::dyn_stack::MemStack::new(&mut mem),
        params,
    );
    let z: Vec<f64> = (0..m).map(|i| vecs[(i, 0)]).collect();
    if info.n_converged_eigen < 1 || !z.iter().all(|v| v.is_finite()) {
        return fiedler_dense(adj, inv_sqrt);
    }
    z
}

/// Connected component of each node of the graph `adj`.
fn components(adj: &[Vec<(usize, f64)>]) -> Vec<usize> {
    let m = adj.len();
    let mut comp = vec![usize::MAX; m];
    let mut next = 0;
    for s in 0..m {
        if comp[s] != usize::MAX {
            continue;
        }
        let mut stack = vec![s];
        comp[s] = next;
        while let Some(i) = stack.pop() {
            for &(j, x) in &adj[i] {
                if x != 0.0 && comp[j] == usize::MAX {
                    comp[j] = next;
                    stack.push(j);
                }
            }
        }
        next += 1;
    }
    comp
}

/// Each part grown by the nodes of other parts within `margin` (m) of one of its own: the overlap at
/// the boundaries (shared nodes are trained by both submaps). Returns the extra nodes per part.
pub fn overlap(parts: &[Vec<usize>], positions: &[DVec3], margin: f64) -> Vec<Vec<usize>> {
    parts
        .iter()
        .map(|p| {
            let mut extra: Vec<usize> = (0..positions.len())
                .filter(|i| !p.contains(i))
                .filter(|&i| {
                    p.iter()
                        .any(|&j| positions[i].distance(positions[j]) <= margin)
                })
                .collect();
            extra.sort_unstable();
            extra
        })
        .collect()
}

/// How to cut.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// Nearest neighbours by camera position (SiLVR's public code).
    Distance,
    /// Co-visibility: the structure two keyframes both see. The paper's: SfM tracks both observe (a
    /// `silvr poses` output's COLMAP model); without tracks, the lidar's: voxels (`COVIS_VOXEL_M`) hit by
    /// the lidar depth of both keyframes' images.
    Covis,
}

/// Voxel size of the lidar co-visibility (m): coarse enough that two views of one wall share voxels
/// despite lidar sampling, fine enough that the two sides of a street do not.
pub const COVIS_VOXEL_M: f64 = 0.5;

/// Every `COVIS_STRIDE`-th lidar pixel in each direction is enough to know which voxels an image sees.
const COVIS_STRIDE: u32 = 2;

/// What one image sees, as a set of ids: lidar voxels ([`voxel_key`]) or SfM track (3-D point) ids.
pub type Seen = std::collections::HashSet<u64>;

/// A voxel's id in a [`Seen`] set: 21 bits per axis (±2^20 voxels, ±524 km at 0.5 m).
pub fn voxel_key(v: [i32; 3]) -> u64 {
    let b = |x: i32| ((x as i64 + (1 << 20)).clamp(0, (1 << 21) - 1)) as u64;
    (b(v[0]) << 42) | (b(v[1]) << 21) | b(v[2])
}

/// Each frame's SfM track ids from a COLMAP model whose images are the frames in order (image id
/// i + 1 is frame i, as `silvr poses` writes them); `None` when the model does not cover the frames.
pub fn track_sets(model: &crate::ingest::colmap::ColmapModel, frames: usize) -> Option<Vec<Seen>> {
    let mut sets = vec![Seen::new(); frames];
    if model.images.len() != frames {
        return None;
    }
    for img in &model.images {
        let i = (img.id as usize).checked_sub(1).filter(|&i| i < frames)?;
        sets[i].extend(img.points2d.iter().filter_map(|p| p.point3d_id));
    }
    Some(sets)
}

/// The co-visibility graph: weight = ids both nodes' sets hold.
pub fn covis_graph(voxels: &[Seen]) -> Graph {
    let mut g = Graph::new(voxels.len());
    for i in 0..voxels.len() {
        for j in i + 1..voxels.len() {
            let (a, b) = if voxels[i].len() <= voxels[j].len() {
                (&voxels[i], &voxels[j])
            } else {
                (&voxels[j], &voxels[i])
            };
            let shared = a.iter().filter(|v| b.contains(*v)).count();
            g.add(i, j, shared as f64);
        }
    }
    g
}

/// The voxels (world frame, `COVIS_VOXEL_M`) each frame's lidar depth image hits; empty for a frame
/// without one. Depth is our encoding (Euclidean range × 256, DATASET.md).
pub fn lidar_voxels(
    src: &dyn crate::source::Source,
    frames: &[crate::dataset::NsFrame],
    path: &std::path::Path,
) -> Result<Vec<Seen>, crate::dataset::DatasetError> {
    use rayon::prelude::*;
    frames
        .par_iter()
        .map(|f| {
            let mut set = Seen::new();
            let Some(rel) = &f.depth_file_path else {
                return Ok(set);
            };
            let (model, pose) = f.camera(path)?;
            let p = src.path(rel);
            let (w, h, depth) = crate::dataset::decode_png16(&src.read(rel)?, &p)?;
            if (w, h) != (model.width, model.height) {
                return Err(crate::dataset::DatasetError::Format {
                    path: p,
                    detail: format!("is {w}x{h}, its camera is {}x{}", model.width, model.height),
                });
            }
            for y in (0..h).step_by(COVIS_STRIDE as usize) {
                for x in (0..w).step_by(COVIS_STRIDE as usize) {
                    let Some(r) = crate::lidar::images::decode_depth(depth[(y * w + x) as usize])
                    else {
                        continue;
                    };
                    let Some(d) = model.unproject(glam::DVec2::new(x as f64, y as f64)) else {
                        continue;
                    };
                    let world = pose.transform_point(d.normalize() * r as f64);
                    let v = (world / COVIS_VOXEL_M).floor();
                    set.insert(voxel_key([v.x as i32, v.y as i32, v.z as i32]));
                }
            }
            Ok(set)
        })
        .collect()
}

/// What `silvr submaps` is asked for.
#[derive(Clone, Debug)]
pub struct SubmapOptions {
    pub method: Method,
    pub limit: Limit,
    /// Keyframes of neighbouring submaps within this distance (m) of one's own are trained by both.
    pub overlap_m: f64,
    /// Neighbours per keyframe in the distance graph (scikit-learn's default, 10; at most a sixth of
    /// the keyframes, at least 2).
    pub neighbours: usize,
}

/// A keyframe: the frames (indices into the file's list) taken at one instant, and where.
#[derive(Clone, Debug, Serialize)]
pub struct Node {
    pub key: String,
    pub frames: Vec<usize>,
    /// Mean camera centre (the file's world frame).
    pub position: [f64; 3],
}

/// One submap: its own keyframes and those it shares with neighbours.
#[derive(Clone, Debug, Serialize)]
pub struct Submap {
    pub name: String,
    pub keyframes: Vec<usize>,
    pub overlap: Vec<usize>,
    /// Frame indices (own and shared), in the file's order.
    pub frames: Vec<usize>,
}

/// The cut of one dataset.
#[derive(Clone, Debug, Serialize)]
pub struct Plan {
    pub method: Method,
    pub limit: Limit,
    pub overlap_m: f64,
    pub nodes: Vec<Node>,
    pub submaps: Vec<Submap>,
    /// Weight of the graph's edges between submaps (before overlap): lower is a cleaner cut.
    pub cut_weight: f64,
    /// The cut scored by lidar co-visibility whatever the method (when the dataset has lidar depth):
    /// the structure seen from both sides of a boundary, which is what a boundary costs the fields.
    pub covis_cut: Option<CovisCut>,
    /// The cut scored by SfM tracks whatever the method (when tracks were given): shared tracks
    /// (keyframe pair × track) split between submaps, and over all keyframe pairs.
    pub track_cut: Option<CovisCut>,
    /// What co-visibility meant for `method: covis`: `tracks` or `lidar`.
    pub covis_source: Option<&'static str>,
}

/// Co-visibility across the cut: shared ids (keyframe pair × shared voxel or track) split between
/// submaps, and over all keyframe pairs.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct CovisCut {
    pub shared: f64,
    pub total: f64,
}

/// Cuts the frames of a `transforms.json` (`frames` as [`crate::dataset::parse_frames`] reads them;
/// `path` names the file in errors). `voxels`: each frame's lidar voxels ([`lidar_voxels`]);
/// `tracks`: each frame's SfM tracks ([`track_sets`]). [`Method::Covis`] cuts by the tracks when given,
/// else by the voxels; either, when given, also scores the cut.
pub fn plan(
    frames: &[crate::dataset::NsFrame],
    path: &std::path::Path,
    voxels: Option<&[Seen]>,
    tracks: Option<&[Seen]>,
    opts: &SubmapOptions,
) -> Result<Plan, crate::dataset::DatasetError> {
    let fail = |detail: String| crate::dataset::DatasetError::Format {
        path: path.to_path_buf(),
        detail,
    };
    // Keyframes: frames sharing a keyframe index (our datasets), else each frame on its own.
    let mut index: std::collections::BTreeMap<String, usize> = Default::default();
    let mut nodes: Vec<Node> = Vec::new();
    let mut sums: Vec<DVec3> = Vec::new();
    for (i, f) in frames.iter().enumerate() {
        let (_, pose) = f.camera(path)?;
        let key = match f.keyframe {
            Some(k) => format!("keyframe {k}"),
            None => f.file_path.clone(),
        };
        let n = *index.entry(key.clone()).or_insert_with(|| {
            nodes.push(Node {
                key,
                frames: Vec::new(),
                position: [0.0; 3],
            });
            sums.push(DVec3::ZERO);
            nodes.len() - 1
        });
        nodes[n].frames.push(i);
        sums[n] += pose.trans;
    }
    if nodes.len() < 2 {
        return Err(fail(format!("{} keyframe(s): nothing to cut", nodes.len())));
    }
    let positions: Vec<DVec3> = nodes
        .iter()
        .zip(&sums)
        .map(|(n, s)| *s / n.frames.len() as f64)
        .collect();
    for (n, p) in nodes.iter_mut().zip(&positions) {
        n.position = p.to_array();
    }
    // scikit-learn's 10 neighbours join nearly every pair of a short path's keyframes (a cut of such a
    // graph is arbitrary): at most a sixth of the keyframes, at least 2.
    let k = opts.neighbours.min(nodes.len() / 6).max(2);
    let distance = distance_graph(&positions, k);
    // Co-visibility per keyframe: the union of its images' sets.
    let per_node = |v: &[Seen]| -> Option<Graph> {
        if !v.iter().any(|s| !s.is_empty()) {
            return None;
        }
        let sets: Vec<Seen> = nodes
            .iter()
            .map(|n| {
                n.frames
                    .iter()
                    .flat_map(|&i| v[i].iter().copied())
                    .collect()
            })
            .collect();
        Some(covis_graph(&sets))
    };
    let covis = voxels.and_then(per_node);
    let track_graph = tracks.and_then(per_node);
    let (graph, covis_source) = match opts.method {
        Method::Distance => (&distance, None),
        Method::Covis => match (&track_graph, &covis) {
            (Some(g), _) => (g, Some("tracks")),
            (None, Some(g)) => (g, Some("lidar")),
            (None, None) => return Err(fail("co-visibility needs SfM tracks (run `silvr poses` and cut its output folder) or lidar depth images (depth_file_path), and this dataset has neither; use --method distance".into())),
        },
    };
    let images: Vec<usize> = nodes.iter().map(|n| n.frames.len()).collect();
    let parts = partition(graph, &images, opts.limit);
    let cut_weight = graph.cut_weight(&parts);
    let track_cut = track_graph.as_ref().map(|g| CovisCut {
        shared: g.cut_weight(&parts),
        total: g.total_weight(),
    });
    let covis_cut = covis.as_ref().map(|g| CovisCut {
        shared: g.cut_weight(&parts),
        total: g.total_weight(),
    });
    let extra = overlap(&parts, &positions, opts.overlap_m);
    let submaps = parts
        .iter()
        .zip(extra)
        .enumerate()
        .map(|(k, (own, shared))| {
            let mut fr: Vec<usize> = own
                .iter()
                .chain(&shared)
                .flat_map(|&n| nodes[n].frames.iter().copied())
                .collect();
            fr.sort_unstable();
            Submap {
                name: format!("submap_{k:02}"),
                keyframes: own.clone(),
                overlap: shared,
                frames: fr,
            }
        })
        .collect();
    Ok(Plan {
        method: opts.method,
        limit: opts.limit,
        overlap_m: opts.overlap_m,
        nodes,
        submaps,
        cut_weight,
        covis_cut,
        track_cut,
        covis_source,
    })
}

/// The `transforms.json` of one submap: the dataset's file (`root`, parsed) with only the submap's
/// frames, every file path prefixed with `prefix` (the way from the submap's folder back to the
/// dataset, so no image is copied), and the train/held-out lists cut to match.
pub fn submap_transforms(
    root: &serde_json::Value,
    sub: &Submap,
    prefix: &str,
) -> serde_json::Value {
    use serde_json::Value;
    let mut out = root.clone();
    let all = root["frames"].as_array().cloned().unwrap_or_default();
    let mut names = std::collections::HashSet::new();
    let frames: Vec<Value> = sub
        .frames
        .iter()
        .filter_map(|&i| all.get(i).cloned())
        .map(|mut f| {
            if let Some(o) = f.as_object_mut() {
                if let Some(p) = o.get("file_path").and_then(Value::as_str) {
                    names.insert(p.to_string());
                }
                crate::dataset::prefix_frame_paths(o, prefix);
            }
            f
        })
        .collect();
    if let Some(o) = out.as_object_mut() {
        o.insert("frames".into(), Value::from(frames));
        for list in ["train_filenames", "val_filenames"] {
            if let Some(a) = root.get(list).and_then(Value::as_array) {
                let kept: Vec<Value> = a
                    .iter()
                    .filter_map(Value::as_str)
                    .filter(|n| names.contains(*n))
                    .map(|n| Value::from(crate::dataset::prefixed(prefix, n)))
                    .collect();
                o.insert(list.into(), Value::from(kept));
            }
        }
    }
    out
}

/// A top-down picture of the keyframes coloured by submap (shared ones ringed in their second colour).
pub fn plot(plan: &Plan) -> image::RgbImage {
    use crate::eval::plot::{text, PALETTE};
    let (w, h, pad) = (720u32, 720u32, 40.0);
    let mut img = image::RgbImage::from_pixel(w, h, image::Rgb([255, 255, 255]));
    let xy: Vec<(f64, f64)> = plan
        .nodes
        .iter()
        .map(|n| (n.position[0], n.position[1]))
        .collect();
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in &xy {
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    let span = (x1 - x0).max(y1 - y0).max(1e-6);
    // Centred: the shorter side's slack split evenly.
    let (ox, oy) = ((span - (x1 - x0)) / 2.0, (span - (y1 - y0)) / 2.0);
    let to_px = |(x, y): (f64, f64)| {
        (
            (pad + (x - x0 + ox) / span * (w as f64 - 2.0 * pad)) as i32,
            (h as f64 - pad - (y - y0 + oy) / span * (h as f64 - 2.0 * pad)) as i32,
        )
    };
    let dot = |img: &mut image::RgbImage, (cx, cy): (i32, i32), r: i32, c: [u8; 3]| {
        for dy in -r..=r {
            for dx in -r..=r {
                let (x, y) = (cx + dx, cy + dy);
                if dx * dx + dy * dy <= r * r
                    && x >= 0
                    && y >= 0
                    && (x as u32) < w
                    && (y as u32) < h
                {
                    img.put_pixel(x as u32, y as u32, image::Rgb(c));
                }
            }
        }
    };
    for (k, s) in plan.submaps.iter().enumerate() {
        let c = PALETTE[k % PALETTE.len()];
        for &n in &s.overlap {
            dot(&mut img, to_px(xy[n]), 9, c);
        }
    }
    for (k, s) in plan.submaps.iter().enumerate() {
        let c = PALETTE[k % PALETTE.len()];
        for &n in &s.keyframes {
            dot(&mut img, to_px(xy[n]), 5, c);
        }
        if let Some(&n) = s.keyframes.first() {
            let (x, y) = to_px(xy[n]);
            text(&mut img, x + 8, y - 18, &k.to_string(), 2, c);
        }
    }
    text(
        &mut img,
        10,
        10,
        &format!(
            "{} submaps by {:?}, top view, {:.0} m across",
            plan.submaps.len(),
            plan.method,
            span
        ),
        2,
        [0, 0, 0],
    );
    img
}

/// Voxel of the merge rule (m): where two submaps' points share one, only one submap keeps its points there.
pub const MERGE_VOXEL_M: f64 = 0.2;

/// Merges submaps' point clouds (each already filtered by its own uncertainty): within every
/// `voxel`-sized cell that more than one submap put points in, only the points of the submap whose
/// training cameras are nearest are kept (the median, over its points in the cell, of the distance to its
/// nearest camera in `cameras[c]`; then the lower median `log_std_combined`, then the lower id, break ties);
/// cells of one submap keep all of theirs. Why cameras and not log-std: measured on two ci worlds
/// (BENCHMARKS.md, issue 19), the submap with the lower log-std in a shared cell was no more accurate there
/// than keeping both, while the nearer one's points were ~5 % closer to the ground truth. A submap without
/// cameras counts as farthest, one without the log-std field as least certain. The result carries a
/// `submap` scalar (the id given with each cloud) and the scalars and colours every input has.
pub fn merge(
    clouds: &[(u32, crate::pointcloud::PointCloud)],
    cameras: &[Vec<DVec3>],
    voxel: f64,
) -> crate::pointcloud::PointCloud {
    use std::collections::HashMap;
    let key = |p: DVec3| {
        let v = (p / voxel).floor();
        [v.x as i64, v.y as i64, v.z as i64]
    };
    let nearest_camera = |c: usize, p: DVec3| {
        cameras
            .get(c)
            .into_iter()
            .flatten()
            .map(|q| q.distance(p))
            .fold(f64::INFINITY, f64::min)
    };
    // Per cell and submap: its points' camera distances and log-stds there.
    type Scores = (Vec<f64>, Vec<f32>);
    let mut cells: HashMap<[i64; 3], Vec<(usize, Scores)>> = HashMap::new();
    for (c, (_, cloud)) in clouds.iter().enumerate() {
        let ls = cloud.scalar("log_std_combined");
        for (i, &p) in cloud.positions.iter().enumerate() {
            let v = ls.map_or(f32::INFINITY, |s| s[i]);
            let v = if v.is_nan() { f32::INFINITY } else { v };
            let d = nearest_camera(c, p);
            let e = cells.entry(key(p)).or_default();
            match e.iter_mut().find(|x| x.0 == c) {
                Some(x) => {
                    x.1 .0.push(d);
                    x.1 .1.push(v);
                }
                None => e.push((c, (vec![d], vec![v]))),
            }
        }
    }
    let winner: HashMap<[i64; 3], usize> = cells
        .into_iter()
        .map(|(k, mut by)| {
            let best = by
                .iter_mut()
                .map(|(c, (d, v))| {
                    d.sort_by(f64::total_cmp);
                    v.sort_by(f32::total_cmp);
                    (d[d.len() / 2], v[v.len() / 2], *c)
                })
                .min_by(|a, b| {
                    a.0.total_cmp(&b.0)
                        .then(a.1.total_cmp(&b.1))
                        .then(a.2.cmp(&b.2))
                })
                .map_or(0, |x| x.2);
            (k, best)
        })
        .collect();
    // Scalars and colours every cloud has.
    let names: Vec<String> = clouds
        .first()
        .map(|(_, c)| {
            c.scalars
                .iter()
                .map(|(n, _)| n.clone())
                .collect::<Vec<String>>()
        })
        .unwrap_or_default()
        .into_iter()
        .filter(|n| n != "submap" && clouds.iter().all(|(_, c)| c.scalar(n).is_some()))
        .collect();
    let colours = clouds.iter().all(|(_, c)| c.colors.is_some());
    let mut out = crate::pointcloud::PointCloud::new();
    let mut scalars: Vec<Vec<f32>> = vec![Vec::new(); names.len()];
    let mut ids = Vec::new();
    let mut rgb = Vec::new();
    for (c, (id, cloud)) in clouds.iter().enumerate() {
        for (i, &p) in cloud.positions.iter().enumerate() {
            if winner.get(&key(p)) != Some(&c) {
                continue;
            }
            out.positions.push(p);
            ids.push(*id as f32);
            for (k, n) in names.iter().enumerate() {
                scalars[k].push(cloud.scalar(n).map_or(f32::NAN, |s| s[i]));
            }
            if colours {
                rgb.push(cloud.colors.as_ref().map_or([0; 3], |x| x[i]));
            }
        }
    }
    if colours {
        out.colors = Some(rgb);
    }
    for (n, v) in names.into_iter().zip(scalars) {
        out.set_scalar(&n, v);
    }
    out.set_scalar("submap", ids);
    out
}

/// Which points lie in the boundary zone between submaps: where the nearest training cameras of the
/// two nearest submaps are within `width` metres of the same distance (near the bisector of their camera
/// sets, where view selection switches from one submap to the other and a cut shows as a seam).
/// `cameras[k]`: submap k's training camera centres, in the points' frame.
pub fn near_boundary(positions: &[DVec3], cameras: &[Vec<DVec3>], width: f64) -> Vec<bool> {
    use crate::eval::metrics::NearestNeighbours;
    let trees: Vec<NearestNeighbours> = cameras
        .iter()
        .filter(|c| !c.is_empty())
        .map(|c| NearestNeighbours::new(c))
        .collect();
    if trees.len() < 2 {
        return vec![false; positions.len()];
    }
    let per: Vec<Vec<f64>> = trees.iter().map(|t| t.distances(positions)).collect();
    (0..positions.len())
        .map(|i| {
            let (mut d1, mut d2) = (f64::INFINITY, f64::INFINITY);
            for d in per.iter().map(|p| p[i]) {
                if d < d1 {
                    (d1, d2) = (d, d1);
                } else if d < d2 {
                    d2 = d;
                }
            }
            d2 - d1 < width
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The boundary zone is the band around the bisector of two submaps' cameras; one submap has none.
    #[test]
    fn near_boundary_is_the_band_between_two_submaps_cameras() {
        let cams = vec![
            vec![DVec3::new(0.0, 0.0, 0.0), DVec3::new(2.0, 0.0, 0.0)],
            vec![DVec3::new(10.0, 0.0, 0.0)],
            vec![],
        ];
        let pts: Vec<DVec3> = [1.0, 5.5, 6.0, 6.9, 8.5]
            .iter()
            .map(|&x| DVec3::new(x, 5.0, 0.0))
            .collect();
        // Bisector of 2 and 10 at x = 6: |d1 − d2| < 2 m from x ≈ 4.6 to 7.7 (at y = 5).
        assert_eq!(
            near_boundary(&pts, &cams, 2.0),
            vec![false, true, true, true, false]
        );
        assert!(near_boundary(&pts, &cams[..1], 2.0).iter().all(|b| !b));
    }

    /// The sparse Lanczos path finds the dense solver's Fiedler vector (up to sign) on a 600-keyframe
    /// path graph, so large parts are cut as small ones are.
    #[test]
    fn lanczos_fiedler_matches_the_dense_one() {
        let n = 600;
        let positions: Vec<DVec3> = (0..n)
            .map(|i| {
                let t = i as f64 * 0.5;
                DVec3::new(t, (t * 0.37).sin() * 3.0, (i % 7) as f64 * 0.01)
            })
            .collect();
        let g = distance_graph(&positions, 10);
        let adj: Vec<Vec<(usize, f64)>> = g.adj.clone();
        let deg: Vec<f64> = adj.iter().map(|r| r.iter().map(|e| e.1).sum()).collect();
        let inv_sqrt: Vec<f64> = deg.iter().map(|d| 1.0 / d.sqrt()).collect();
        let dense = fiedler_dense(&adj, &inv_sqrt);
        let t = std::time::Instant::now();
        let sparse = fiedler_lanczos(&adj, &deg, &inv_sqrt);
        let secs = t.elapsed().as_secs_f64();
        let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
        let dot: f64 = dense.iter().zip(&sparse).map(|(a, b)| a * b).sum::<f64>()
            / (norm(&dense) * norm(&sparse));
        assert!(dot.abs() > 0.999, "cosine {dot} ({secs:.3} s)");
        // The cut through the sparse path is the dense one's: the path's middle.
        let (a, b) = bisect(&g, &(0..n).collect::<Vec<_>>());
        assert!(
            a.len().abs_diff(b.len()) < n / 5,
            "{} / {}",
            a.len(),
            b.len()
        );
        assert!(a.contains(&0) != a.contains(&(n - 1)));
    }

    /// A path along x with `n` keyframes `step` apart.
    fn line(n: usize, step: f64) -> Vec<DVec3> {
        (0..n)
            .map(|i| DVec3::new(i as f64 * step, 0.0, 0.0))
            .collect()
    }

    #[test]
    fn a_path_is_cut_into_contiguous_pieces_of_the_asked_size() {
        let pos = line(40, 1.0);
        let g = distance_graph(&pos, 4);
        let images = vec![3; 40];
        let parts = partition(&g, &images, Limit::MaxImages(30));
        assert!(parts.iter().all(|p| p.len() * 3 <= 30), "{parts:?}");
        assert!(parts.len() >= 4 && parts.len() <= 8, "{parts:?}");
        for p in &parts {
            // Contiguous along the path.
            assert_eq!(p.last().unwrap() - p[0] + 1, p.len(), "{p:?}");
        }
        let all: usize = parts.iter().map(Vec::len).sum();
        assert_eq!(all, 40);
        let by_count = partition(&g, &images, Limit::Count(3));
        assert_eq!(by_count.len(), 3);
        assert!(by_count.iter().all(|p| p.len() >= 8), "{by_count:?}");
    }

    #[test]
    fn covisibility_counts_shared_and_cuts_where_little_is_shared() {
        use std::collections::HashSet;
        // Six keyframes: 0-2 see voxels 0..10, 3-5 see 8..20 (two shared), one voxel per keyframe of its own.
        let sets: Vec<Seen> = (0..6)
            .map(|k| {
                let range = if k < 3 { 0..10 } else { 8..20 };
                range
                    .map(|x| voxel_key([x, 0, -x]))
                    .chain([voxel_key([100 + k, 0, 0])])
                    .collect::<HashSet<u64>>()
            })
            .collect();
        // Distinct voxels, distinct keys (also negative coordinates).
        assert_ne!(voxel_key([0, 0, -1]), voxel_key([0, 0, 1]));
        assert_ne!(voxel_key([1, 0, 0]), voxel_key([0, 1, 0]));
        let g = covis_graph(&sets);
        assert_eq!(g.adj[0].iter().find(|e| e.0 == 1).unwrap().1, 10.0);
        assert_eq!(g.adj[0].iter().find(|e| e.0 == 3).unwrap().1, 2.0);
        let parts = partition(&g, &[1; 6], Limit::Count(2));
        assert_eq!(parts, vec![vec![0, 1, 2], vec![3, 4, 5]]);
        assert_eq!(g.cut_weight(&parts), 18.0);
        assert_eq!(g.total_weight(), 3.0 * 10.0 + 3.0 * 12.0 + 18.0);
    }

    #[test]
    fn merge_keeps_the_submap_with_the_nearer_cameras_where_both_have_points() {
        use crate::pointcloud::PointCloud;
        let cloud = |xs: &[f64], log_std: f32| {
            let mut c =
                PointCloud::from_positions(xs.iter().map(|&x| DVec3::new(x, 0.05, 0.05)).collect());
            c.set_scalar("log_std_combined", vec![log_std; xs.len()]);
            c
        };
        // Submap 3 alone at x < 1; both at 1.0–1.2; submap 7 alone beyond. Submap 3's camera is at x = 0,
        // submap 7's at x = 2: the shared cell (x 1.0–1.2) is nearer submap 7's, which keeps it although
        // submap 3 is the more certain there.
        let a = cloud(&[0.05, 0.5, 1.05, 1.15], 1.0);
        let b = cloud(&[1.1, 1.12, 1.5], 2.0);
        let cams = vec![vec![DVec3::ZERO], vec![DVec3::new(2.0, 0.0, 0.0)]];
        let m = merge(&[(3, a.clone()), (7, b.clone())], &cams, 0.2);
        let xs: Vec<f64> = m.positions.iter().map(|p| p.x).collect();
        assert_eq!(xs, vec![0.05, 0.5, 1.1, 1.12, 1.5]);
        assert_eq!(m.scalar("submap").unwrap(), &[3.0, 3.0, 7.0, 7.0, 7.0]);
        assert_eq!(m.scalar("log_std_combined").unwrap()[0], 1.0);
        // No cameras given (a tie in distance): the more certain submap (3) keeps the shared cell.
        let m = merge(&[(3, a), (7, b)], &[], 0.2);
        assert_eq!(m.scalar("submap").unwrap(), &[3.0, 3.0, 3.0, 3.0, 7.0]);
    }

    #[test]
    fn two_clusters_split_where_the_gap_is_and_overlap_crosses_it() {
        // Two streets 20 m apart, joined by one pair of neighbours 3 m apart.
        let mut pos = line(15, 1.0);
        pos.extend((0..15).map(|i| DVec3::new(17.0 + i as f64, 0.0, 0.0)));
        let mut g = distance_graph(&pos, 3);
        let weak = g.cut_weight(&[(0..15).collect(), (15..30).collect()]);
        assert!(weak <= 4.0, "{weak}");
        let parts = partition(&g, &[1; 30], Limit::Count(2));
        assert_eq!(parts, vec![(0..15).collect::<Vec<_>>(), (15..30).collect()]);
        let extra = overlap(&parts, &pos, 3.5);
        assert_eq!(extra, vec![vec![15], vec![14]]);
        // A disconnected graph splits along its components.
        g = Graph::new(4);
        g.add(0, 1, 1.0);
        g.add(2, 3, 1.0);
        assert_eq!(
            partition(&g, &[1; 4], Limit::Count(2)),
            vec![vec![0, 1], vec![2, 3]]
        );
    }
}
