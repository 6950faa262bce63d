//! Which octree nodes to show: the level-of-detail choice of a streaming viewer (Potree's, Schütz 2016
//! §4.2), within a point budget. A node is worth loading by its projected size — its cube's edge over its
//! distance from the eye, in pixels — and a child only with its parent (a parent holds a subsample of the
//! children's region, so the nodes shown are always a connected top of the tree). Nodes are taken largest
//! projected size first while their points fit the budget; nodes outside the view frustum, or smaller on
//! screen than a minimum, are skipped with their subtrees. Pure: the worker runs it on each camera change
//! and the tests here fix its behaviour.

use std::cmp::Ordering;
use std::collections::{BinaryHeap, HashMap};

use copc_core::{Entry, VoxelKey};
use glam::DVec3;

use super::read::CopcHead;

/// What the camera sees.
#[derive(Clone, Copy, Debug)]
pub struct LodView {
    pub eye: DVec3,
    /// Pixels a unit length subtends at unit distance: the viewport's height over 2·tan(fov_y / 2).
    pub pixels_per_radian: f64,
    /// The view frustum's planes as (normal, d) with normal·p + d ≥ 0 inside; empty: no culling.
    pub planes: [Option<(DVec3, f64)>; 6],
    /// Nodes smaller on screen than this (pixels) are not loaded.
    pub min_pixels: f64,
}

/// The chosen nodes, largest on screen first, and their points.
#[derive(Clone, Debug, PartialEq)]
pub struct LodChoice {
    pub nodes: Vec<VoxelKey>,
    pub points: u64,
}

struct Candidate {
    priority: f64,
    key: VoxelKey,
}
impl PartialEq for Candidate {
    fn eq(&self, o: &Self) -> bool {
        self.cmp(o) == Ordering::Equal
    }
}
impl Eq for Candidate {}
impl PartialOrd for Candidate {
    fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Candidate {
    fn cmp(&self, o: &Self) -> Ordering {
        // Largest priority first; ties by key, so the choice is deterministic.
        self.priority
            .total_cmp(&o.priority)
            .then_with(|| o.key.cmp(&self.key))
    }
}

/// A node's projected size in pixels (`f64::INFINITY` with the eye inside its bounding sphere), or `None`
/// when its cube lies wholly outside a frustum plane.
fn projected(head: &CopcHead, key: VoxelKey, view: &LodView) -> Option<f64> {
    let (min, edge) = head.node_cube(key);
    let centre = min + DVec3::splat(edge / 2.0);
    let radius = edge * 3f64.sqrt() / 2.0;
    for (n, d) in view.planes.iter().flatten() {
        if n.dot(centre) + d < -radius * n.length() {
            return None;
        }
    }
    let dist = (centre - view.eye).length();
    if dist <= radius {
        return Some(f64::INFINITY);
    }
    Some(view.pixels_per_radian * radius / (dist - radius))
}

/// The nodes to show for `view` within `budget` points, from the hierarchy's `nodes` (those with points,
/// as [`super::read::walk_hierarchy`] or the pages read so far give them). The root is taken whatever its
/// size, so something is always shown.
pub fn select(head: &CopcHead, nodes: &[Entry], view: &LodView, budget: u64) -> LodChoice {
    let by_key: HashMap<VoxelKey, &Entry> = nodes.iter().map(|e| (e.key, e)).collect();
    let mut heap = BinaryHeap::new();
    let root = VoxelKey::root();
    if by_key.contains_key(&root) {
        heap.push(Candidate {
            priority: f64::INFINITY,
            key: root,
        });
    }
    let mut out = LodChoice {
        nodes: Vec::new(),
        points: 0,
    };
    while let Some(Candidate { key, .. }) = heap.pop() {
        let Some(e) = by_key.get(&key) else { continue };
        let n = e.point_count.max(0) as u64;
        if out.points + n > budget && !out.nodes.is_empty() {
            // Smaller nodes later in the queue might fit, but a viewer refines the biggest first: stop.
            break;
        }
        out.points += n;
        out.nodes.push(key);
        for octant in 0..8u8 {
            let Ok(child) = key.child(octant) else {
                continue;
            };
            if !by_key.contains_key(&child) {
                continue;
            }
            if let Some(px) = projected(head, child, view) {
                if px >= view.min_pixels {
                    heap.push(Candidate {
                        priority: px,
                        key: child,
                    });
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use copc_core::CopcInfo;

    /// A head for a 100 m cube at the origin (only the fields the choice reads matter).
    fn head() -> CopcHead {
        CopcHead {
            points: 0,
            point_format: 7,
            record_length: 36,
            extra_at: 36,
            scale: DVec3::splat(1e-4),
            offset: DVec3::ZERO,
            min: DVec3::splat(-50.0),
            max: DVec3::splat(50.0),
            info: CopcInfo {
                center: (0.0, 0.0, 0.0),
                halfsize: 50.0,
                spacing: 1.0,
                root_hier_offset: 0,
                root_hier_size: 0,
                gpstime_min: 0.0,
                gpstime_max: 0.0,
            },
            laz: laz::LazVlrBuilder::default()
                .with_point_format(7, 0)
                .unwrap()
                .build(),
            layers: 9,
            extra: Vec::new(),
            summary: None,
        }
    }

    /// A full octree to `depth`, 1000 points a node.
    fn tree(depth: i32) -> Vec<Entry> {
        let mut out = Vec::new();
        for level in 0..=depth {
            let n = 1 << level;
            for x in 0..n {
                for y in 0..n {
                    for z in 0..n {
                        out.push(Entry {
                            key: VoxelKey { level, x, y, z },
                            offset: 1,
                            byte_size: 1,
                            point_count: 1000,
                        });
                    }
                }
            }
        }
        out
    }

    fn view(eye: DVec3) -> LodView {
        LodView {
            eye,
            pixels_per_radian: 1000.0,
            planes: [None; 6],
            min_pixels: 0.0,
        }
    }

    /// The budget is never exceeded (past the root), every chosen node's parent is chosen, and nodes near
    /// the eye are refined deeper than far ones.
    #[test]
    fn the_choice_fits_the_budget_and_refines_near_the_eye() {
        let (h, nodes) = (head(), tree(4));
        let eye = DVec3::new(-45.0, -45.0, -45.0);
        for budget in [0, 1000, 5000, 37_000, 200_000] {
            let c = select(&h, &nodes, &view(eye), budget);
            assert!(c.points <= budget.max(1000), "{budget}: {}", c.points);
            assert_eq!(c.points, 1000 * c.nodes.len() as u64);
            for k in &c.nodes {
                if k.level > 0 {
                    let parent = VoxelKey {
                        level: k.level - 1,
                        x: k.x / 2,
                        y: k.y / 2,
                        z: k.z / 2,
                    };
                    assert!(c.nodes.contains(&parent), "{k:?} without its parent");
                }
            }
        }
        let c = select(&h, &nodes, &view(eye), 60_000);
        // The eye's corner (keys 0, 0, 0) against the opposite one.
        let deepest = |corner: fn(&VoxelKey) -> bool| {
            c.nodes.iter().filter(|k| corner(k)).map(|k| k.level).max()
        };
        let near = deepest(|k| k.x == 0 && k.y == 0 && k.z == 0);
        let far = deepest(|k| {
            let last = (1 << k.level) - 1;
            k.x == last && k.y == last && k.z == last
        });
        assert_eq!(near, Some(4));
        assert!(
            far.unwrap_or(0) < 4,
            "the far corner refined to level {far:?}"
        );
        // A bigger budget never shows less.
        let more = select(&h, &nodes, &view(eye), 120_000);
        assert!(c.nodes.iter().all(|k| more.nodes.contains(k)));
    }

    /// Nodes behind a frustum plane are culled with their subtrees; nodes below the minimum size are not
    /// loaded.
    #[test]
    fn culled_and_tiny_nodes_are_skipped() {
        let (h, nodes) = (head(), tree(3));
        let mut v = view(DVec3::new(0.0, 0.0, 500.0));
        // Keep x ≥ 0 only.
        v.planes[0] = Some((DVec3::X, 0.0));
        let c = select(&h, &nodes, &v, u64::MAX);
        // Culled by bounding sphere: a chosen node's sphere reaches x ≥ 0; the far side's nodes are gone.
        for k in &c.nodes {
            let (min, edge) = h.node_cube(*k);
            assert!(
                min.x + edge / 2.0 + edge * 3f64.sqrt() / 2.0 >= 0.0,
                "{k:?}"
            );
        }
        assert!(c.nodes.len() > 1 && c.nodes.len() < nodes.len());
        let far_side = VoxelKey {
            level: 3,
            x: 0,
            y: 4,
            z: 4,
        };
        assert!(!c.nodes.contains(&far_side));
        v.planes[0] = None;
        v.min_pixels = 1e9;
        assert_eq!(
            select(&h, &nodes, &v, u64::MAX).nodes,
            vec![VoxelKey::root()]
        );
    }
}
