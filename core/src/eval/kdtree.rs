//! A static 3-D KD-tree for nearest-neighbour distances (and the k nearest points, for a local plane).
//!
//! Why not kiddo: its mutable tree panics once more than a bucket's worth of points share a coordinate
//! (raw reconstructions have exact duplicates), and its immutable tree slows down ~10× on clouds with many
//! equal coordinates on one axis (planar GT, quantised exports). Here a node splits at the median of
//! its widest axis, which always halves the range whatever the ties, and a range whose points are all
//! identical collapses into one representative. Only distances are needed, so the tree keeps no
//! indices. The layout is implicit (node k has children 2k+1 and 2k+2; a node over `[lo, hi)` splits at
//! `lo + (hi − lo)/2`), so only one split value and one axis byte are stored per node.

/// Points per leaf.
const LEAF: usize = 12;
/// Node kinds beyond the split axes 0..=2.
const KIND_LEAF: u8 = 3;
const KIND_SAME: u8 = 4;

pub(crate) struct KdTree {
    pts: Vec<[f64; 3]>,
    split: Vec<f64>,
    kind: Vec<u8>,
}

impl KdTree {
    /// Builds over `points`, which must be finite (callers filter).
    pub(crate) fn new(mut points: Vec<[f64; 3]>) -> Self {
        let (mut depth, mut m) = (0u32, points.len());
        while m > LEAF {
            m = m.div_ceil(2);
            depth += 1;
        }
        let nodes = (1usize << (depth + 1)) - 1;
        let mut tree = Self {
            pts: Vec::new(),
            split: vec![0.0; nodes],
            kind: vec![KIND_LEAF; nodes],
        };
        build(&mut points, 0, &mut tree.split, &mut tree.kind);
        tree.pts = points;
        tree
    }

    pub(crate) fn is_empty(&self) -> bool {
        self.pts.is_empty()
    }

    /// Squared distance from `q` to the nearest point (+∞ for an empty tree).
    pub(crate) fn nearest_sq(&self, q: [f64; 3]) -> f64 {
        let mut best = f64::INFINITY;
        if self.pts.is_empty() {
            return best;
        }
        // Per node: its range and the query's per-axis offsets to the node's cell (SciPy cKDTree's
        // incremental bound: the squared distance to anything below the node is at least |off|²).
        struct Item {
            k: usize,
            lo: usize,
            hi: usize,
            off: [f64; 3],
            bound: f64,
        }
        let mut stack: Vec<Item> = Vec::with_capacity(64);
        stack.push(Item {
            k: 0,
            lo: 0,
            hi: self.pts.len(),
            off: [0.0; 3],
            bound: 0.0,
        });
        while let Some(Item {
            k,
            lo,
            hi,
            off,
            bound,
        }) = stack.pop()
        {
            if bound >= best {
                continue;
            }
            match self.kind[k] {
                KIND_LEAF => {
                    for p in &self.pts[lo..hi] {
                        best = best.min(dist_sq(p, &q));
                    }
                }
                KIND_SAME => best = best.min(dist_sq(&self.pts[lo], &q)),
                axis => {
                    let a = axis as usize;
                    let mid = lo + (hi - lo) / 2;
                    let diff = q[a] - self.split[k];
                    // Left holds values ≤ split, right values ≥ split, so |diff| separates the query from
                    // the far side along this axis.
                    let (near, far) = if diff < 0.0 {
                        ((2 * k + 1, lo, mid), (2 * k + 2, mid, hi))
                    } else {
                        ((2 * k + 2, mid, hi), (2 * k + 1, lo, mid))
                    };
                    let mut far_off = off;
                    far_off[a] = diff;
                    let far_bound = bound - off[a] * off[a] + diff * diff;
                    if far_bound < best {
                        stack.push(Item {
                            k: far.0,
                            lo: far.1,
                            hi: far.2,
                            off: far_off,
                            bound: far_bound,
                        });
                    }
                    stack.push(Item {
                        k: near.0,
                        lo: near.1,
                        hi: near.2,
                        off,
                        bound,
                    });
                }
            }
        }
        best
    }
}

impl KdTree {
    /// The `k` nearest points to `q` with their squared distances, nearest first (fewer when the tree
    /// holds fewer). The same traversal as [`Self::nearest_sq`], pruned by the k-th best so far.
    pub(crate) fn k_nearest(&self, q: [f64; 3], k: usize) -> Vec<(f64, [f64; 3])> {
        let mut best: Vec<(f64, [f64; 3])> = Vec::with_capacity(k + 1);
        if self.pts.is_empty() || k == 0 {
            return best;
        }
        let worst = |b: &Vec<(f64, [f64; 3])>| {
            if b.len() < k {
                f64::INFINITY
            } else {
                b[b.len() - 1].0
            }
        };
        let offer = |b: &mut Vec<(f64, [f64; 3])>, p: &[f64; 3]| {
            let d = dist_sq(p, &q);
            if d < worst(b) {
                let at = b.partition_point(|e| e.0 <= d);
                b.insert(at, (d, *p));
                b.truncate(k);
            }
        };
        let mut stack: Vec<(usize, usize, usize, [f64; 3], f64)> = Vec::with_capacity(64);
        stack.push((0, 0, self.pts.len(), [0.0; 3], 0.0));
        while let Some((node, lo, hi, off, bound)) = stack.pop() {
            if bound >= worst(&best) {
                continue;
            }
            match self.kind[node] {
                KIND_LEAF => {
                    for p in &self.pts[lo..hi] {
                        offer(&mut best, p);
                    }
                }
                KIND_SAME => {
                    for p in &self.pts[lo..hi] {
                        offer(&mut best, p);
                        if best.len() >= k {
                            break;
                        }
                    }
                }
                axis => {
                    let a = axis as usize;
                    let mid = lo + (hi - lo) / 2;
                    let diff = q[a] - self.split[node];
                    let (near, far) = if diff < 0.0 {
                        ((2 * node + 1, lo, mid), (2 * node + 2, mid, hi))
                    } else {
                        ((2 * node + 2, mid, hi), (2 * node + 1, lo, mid))
                    };
                    let mut far_off = off;
                    far_off[a] = diff;
                    let far_bound = bound - off[a] * off[a] + diff * diff;
                    if far_bound < worst(&best) {
                        stack.push((far.0, far.1, far.2, far_off, far_bound));
                    }
                    stack.push((near.0, near.1, near.2, off, bound));
                }
            }
        }
        best
    }
}

#[inline]
fn dist_sq(p: &[f64; 3], q: &[f64; 3]) -> f64 {
    let (dx, dy, dz) = (p[0] - q[0], p[1] - q[1], p[2] - q[2]);
    dx * dx + dy * dy + dz * dz
}

fn build(pts: &mut [[f64; 3]], k: usize, split: &mut [f64], kind: &mut [u8]) {
    if pts.len() <= LEAF {
        kind[k] = KIND_LEAF;
        return;
    }
    let mut lo = pts[0];
    let mut hi = pts[0];
    for p in pts.iter() {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let ext = [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]];
    let axis = if ext[0] >= ext[1] && ext[0] >= ext[2] {
        0
    } else if ext[1] >= ext[2] {
        1
    } else {
        2
    };
    if ext[axis] == 0.0 {
        kind[k] = KIND_SAME;
        return;
    }
    let mid = pts.len() / 2;
    pts.select_nth_unstable_by(mid, |a, b| a[axis].total_cmp(&b[axis]));
    split[k] = pts[mid][axis];
    kind[k] = axis as u8;
    let (l, r) = pts.split_at_mut(mid);
    build(l, 2 * k + 1, split, kind);
    build(r, 2 * k + 2, split, kind);
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_xoshiro::Xoshiro256PlusPlus;

    fn brute(q: [f64; 3], pts: &[[f64; 3]]) -> f64 {
        pts.iter()
            .map(|p| dist_sq(p, &q))
            .fold(f64::INFINITY, f64::min)
    }

    #[test]
    fn matches_brute_force_on_hard_inputs() {
        let mut r = Xoshiro256PlusPlus::seed_from_u64(11);
        let mut sets: Vec<Vec<[f64; 3]>> = vec![
            vec![[1.0, 2.0, 3.0]],
            vec![[0.5; 3]; 1000], // all identical
        ];
        for n in [2usize, 12, 13, 25, 100, 1000, 5000] {
            // Uniform, planar (many equal coordinates), and coarse-quantised point sets.
            sets.push(
                (0..n)
                    .map(|_| [r.random(), r.random(), r.random()])
                    .collect(),
            );
            sets.push(
                (0..n)
                    .map(|i| {
                        let mut p: [f64; 3] = [r.random(), r.random(), r.random()];
                        p[i % 3] = (i / 3 % 3) as f64 * 0.5;
                        p
                    })
                    .collect(),
            );
            sets.push(
                (0..n)
                    .map(|_| {
                        [
                            r.random_range(0..3) as f64,
                            r.random_range(0..2) as f64,
                            0.0,
                        ]
                    })
                    .collect(),
            );
        }
        for pts in sets {
            let tree = KdTree::new(pts.clone());
            for _ in 0..200 {
                let q = [
                    r.random_range(-0.5..3.5),
                    r.random_range(-0.5..2.5),
                    r.random_range(-0.5..1.5),
                ];
                assert_eq!(tree.nearest_sq(q), brute(q, &pts), "n = {}", pts.len());
            }
            // Every indexed point is at distance 0 from itself.
            for p in pts.iter().step_by(7) {
                assert_eq!(tree.nearest_sq(*p), 0.0);
            }
        }
        assert_eq!(KdTree::new(Vec::new()).nearest_sq([0.0; 3]), f64::INFINITY);
    }

    #[test]
    fn k_nearest_matches_brute_force() {
        let mut r = Xoshiro256PlusPlus::seed_from_u64(12);
        for n in [1usize, 5, 13, 200, 3000] {
            let mut pts: Vec<[f64; 3]> = (0..n)
                .map(|_| [r.random(), r.random(), (r.random_range(0..4) as f64) * 0.25])
                .collect();
            pts.extend(vec![[0.5, 0.5, 0.5]; 20]);
            let tree = KdTree::new(pts.clone());
            for _ in 0..100 {
                let q = [r.random(), r.random(), r.random()];
                let k = 8;
                let got: Vec<f64> = tree.k_nearest(q, k).iter().map(|e| e.0).collect();
                let mut all: Vec<f64> = pts.iter().map(|p| dist_sq(p, &q)).collect();
                all.sort_by(f64::total_cmp);
                all.truncate(k);
                assert_eq!(got, all, "n = {n}");
            }
        }
        assert!(KdTree::new(Vec::new()).k_nearest([0.0; 3], 4).is_empty());
    }
}
