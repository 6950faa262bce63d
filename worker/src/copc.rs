//! A COPC map in the studio: which octree nodes to load (the level of detail the camera sees, within a
//! point budget), the decoded nodes kept, and the layer's cloud made of them. The reading itself is the
//! core's (`silvr_core::copc::read`, by byte ranges); the fetching and the timing (refine when the camera
//! rests) are the worker's (`web.rs`). Plain Rust, so the tests run natively.

use std::collections::{HashMap, HashSet};

use glam::DVec3;
use serde::{Deserialize, Serialize};
use silvr_core::copc::lod::{self, LodView};
use silvr_core::copc::read::{CopcHead, Entry, NodePoints, VoxelKey};
use silvr_core::pointcloud::PointCloud;
use silvr_core::viewer::SHOWN_FIELDS;

use crate::view::{Camera, BUDGET_RANGE};

/// Points loaded by default on a software adapter: with the compute rasteriser SwiftShader draws 250 k
/// points in ~80 ms and an orbit step follows a drag in ~0.2 s; at 1 M (Potree's default budget) a frame
/// takes ~0.35 s and an orbit step ~0.9 s (BENCHMARKS.md, "Streaming a COPC map"), too slow to steer.
pub const SOFTWARE_BUDGET: u64 = 250_000;
/// The default on a hardware GPU, which draws millions of points a frame (4x Potree's default).
pub const HARDWARE_BUDGET: u64 = 4_000_000;
/// The first frame's points: a coarse top of the octree, shown quickly, then refined to the budget.
pub const FIRST_FRAME_POINTS: u64 = 200_000;
/// Nodes smaller on screen than this (pixels) are not worth loading (Potree's minimum node size).
pub const MIN_NODE_PIXELS: f64 = 30.0;
/// Decoded nodes kept beyond those shown, for a camera that comes back, in points per point of budget.
pub const CACHE_PER_BUDGET: u64 = 2;

/// The budget in force: the view's (a link's or the page's), else the adapter's default.
pub fn budget(view: Option<u64>, software: bool) -> u64 {
    match view {
        Some(b) => b.clamp(BUDGET_RANGE.0, BUDGET_RANGE.1),
        None if software => SOFTWARE_BUDGET,
        None => HARDWARE_BUDGET,
    }
}

/// What the page is told of a COPC layer's level of detail.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LodInfo {
    /// Octree nodes loaded, of those with points.
    pub nodes: u32,
    pub nodes_total: u32,
    /// The point budget they were chosen within.
    pub budget: u64,
    /// Nodes the current view still waits for (0: refined for this view).
    #[serde(default)]
    pub pending: u32,
    /// Nodes that could not be read (a failed request, a corrupt chunk): left out, the rest is shown.
    #[serde(default)]
    pub failed: u32,
    /// The file's whole-cloud summary of the default filter (`None` for a file without our summary VLR):
    /// the points it keeps of the whole map, and its threshold (log10 σ, metres).
    pub summary_kept: Option<u64>,
    pub summary_threshold: Option<f32>,
}

/// What the camera sees, for the level-of-detail choice: the eye, the pixels a radian spans on a canvas of
/// `size`, and the view frustum (its four sides and the plane through the eye; no far plane, the view's
/// far clip lies beyond the map).
pub fn lod_view(camera: &Camera, (width, height): (u32, u32)) -> LodView {
    let eye = camera.eye();
    let f = -camera.back();
    // As the view matrix (`Frame::look_at`) chooses its up.
    let up = if f.cross(DVec3::Z).length() < 1e-6 {
        DVec3::Y
    } else {
        DVec3::Z
    };
    let s = f.cross(up).normalize();
    let u = s.cross(f);
    let tan_v = (camera.fov.to_radians() / 2.0).tan();
    let tan_h = tan_v * width.max(1) as f64 / height.max(1) as f64;
    // Inside: |d·s| ≤ (d·f)·tan_h and |d·u| ≤ (d·f)·tan_v, d = p − eye.
    let plane = |n: DVec3| Some((n, -n.dot(eye)));
    LodView {
        eye,
        pixels_per_radian: height.max(1) as f64 / (2.0 * tan_v),
        planes: [
            plane(f * tan_h - s),
            plane(f * tan_h + s),
            plane(f * tan_v - u),
            plane(f * tan_v + u),
            plane(f),
            None,
        ],
        min_pixels: MIN_NODE_PIXELS,
    }
}

/// A decoded node and when it was last shown.
struct Cached {
    points: NodePoints,
    used: u64,
}

/// A COPC layer's state in the worker: the file's head and hierarchy, the nodes decoded so far (those shown
/// and, within a bound, those shown recently), and the nodes that could not be read.
pub struct CopcStream {
    pub head: CopcHead,
    pub entries: Vec<Entry>,
    /// Decoded positions are relative to this (the octree's centre), as the view's are.
    pub origin: DVec3,
    cache: HashMap<VoxelKey, Cached>,
    failed: HashSet<VoxelKey>,
    tick: u64,
}

/// What a view wants: the nodes to show (largest on screen first) and those of them not decoded yet.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    pub chosen: Vec<Entry>,
    pub missing: Vec<Entry>,
}

impl CopcStream {
    pub fn new(head: CopcHead, entries: Vec<Entry>) -> Self {
        let origin = head.center();
        Self {
            head,
            entries,
            origin,
            cache: HashMap::new(),
            failed: HashSet::new(),
            tick: 0,
        }
    }

    /// The nodes `view` wants within `budget` points; a map that fits the budget whole is loaded whole
    /// (like a PLY: a small map is not thinned by the view). A node that failed is left out of the choice
    /// but not its subtree (COPC stores each point in one node, so its children show their own points).
    pub fn plan(&self, view: &LodView, budget: u64) -> Plan {
        let whole: u64 = self
            .entries
            .iter()
            .map(|e| e.point_count.max(0) as u64)
            .sum();
        let all = LodView {
            planes: [None; 6],
            min_pixels: 0.0,
            ..*view
        };
        let view = if whole <= budget { &all } else { view };
        let chosen = select_entries(&self.head, &self.entries, view, budget, &self.failed);
        let missing = chosen
            .iter()
            .filter(|e| !self.cache.contains_key(&e.key))
            .copied()
            .collect();
        Plan { chosen, missing }
    }

    pub fn insert(&mut self, key: VoxelKey, points: NodePoints) {
        self.tick += 1;
        self.cache.insert(
            key,
            Cached {
                points,
                used: self.tick,
            },
        );
    }

    /// Marks a node that could not be read: it is not asked for again.
    pub fn fail(&mut self, key: VoxelKey) {
        self.failed.insert(key);
    }

    pub fn failed(&self) -> usize {
        self.failed.len()
    }

    pub fn is_cached(&self, key: &VoxelKey) -> bool {
        self.cache.contains_key(key)
    }

    /// Points decoded and kept.
    pub fn cached_points(&self) -> u64 {
        self.cache
            .values()
            .map(|c| c.points.positions.len() as u64)
            .sum()
    }

    /// The cloud of the `chosen` nodes that are decoded (marking them used), and their keys.
    pub fn show(&mut self, chosen: &[Entry]) -> (PointCloud, Vec<VoxelKey>) {
        self.tick += 1;
        let mut keys = Vec::new();
        for e in chosen {
            if let Some(c) = self.cache.get_mut(&e.key) {
                c.used = self.tick;
                keys.push(e.key);
            }
        }
        let nodes: Vec<&NodePoints> = keys.iter().map(|k| &self.cache[k].points).collect();
        (cloud_of(&self.head, self.origin, &nodes), keys)
    }

    /// Drops the least recently shown nodes until at most `keep` points stay decoded (nodes shown last are
    /// never dropped).
    pub fn evict(&mut self, keep: u64) {
        let mut total = self.cached_points();
        if total <= keep {
            return;
        }
        let mut old: Vec<(u64, VoxelKey, u64)> = self
            .cache
            .iter()
            .filter(|(_, c)| c.used < self.tick)
            .map(|(k, c)| (c.used, *k, c.points.positions.len() as u64))
            .collect();
        old.sort_unstable();
        for (_, k, n) in old {
            if total <= keep {
                break;
            }
            self.cache.remove(&k);
            total -= n;
        }
    }
}

/// The nodes the camera that frames the map sees, largest on screen first, within `budget` points: the
/// first frame's, before the page has a camera (a nominal 1000-pixel-high view, no culling).
pub fn choose(head: &CopcHead, nodes: &[Entry], budget: u64) -> Vec<Entry> {
    let cam = Camera::fit(head.min.to_array(), head.max.to_array());
    let view = LodView {
        planes: [None; 6],
        min_pixels: 0.0,
        ..lod_view(&cam, (1000, 1000))
    };
    select_entries(head, nodes, &view, budget, &HashSet::new())
}

/// [`lod::select`]'s choice as the hierarchy's entries, leaving out the `failed` ones (their subtrees are
/// still chosen).
fn select_entries(
    head: &CopcHead,
    nodes: &[Entry],
    view: &LodView,
    budget: u64,
    failed: &HashSet<VoxelKey>,
) -> Vec<Entry> {
    let by_key: HashMap<VoxelKey, &Entry> = nodes.iter().map(|e| (e.key, e)).collect();
    lod::select(head, nodes, view, budget)
        .nodes
        .iter()
        .filter(|k| !failed.contains(k))
        .filter_map(|k| by_key.get(k).map(|e| **e))
        .collect()
}

/// The layer's cloud: the loaded nodes' points (positions back in the file's frame), colours when the file
/// has them, and the fields the studio shows.
pub fn cloud_of(head: &CopcHead, origin: DVec3, nodes: &[&NodePoints]) -> PointCloud {
    let n: usize = nodes.iter().map(|p| p.positions.len()).sum();
    let mut c = PointCloud::new();
    c.positions.reserve(n);
    if head.has_rgb() {
        c.colors = Some(Vec::with_capacity(n));
    }
    let names = head.field_names();
    let shown: Vec<usize> = (0..names.len())
        .filter(|&k| SHOWN_FIELDS.contains(&names[k].as_str()))
        .collect();
    let mut cols: Vec<Vec<f32>> = shown.iter().map(|_| Vec::with_capacity(n)).collect();
    for p in nodes {
        c.positions.extend(
            p.positions
                .iter()
                .map(|q| origin + DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64)),
        );
        if let (Some(all), Some(these)) = (&mut c.colors, &p.colors) {
            all.extend_from_slice(these);
        }
        for (col, &k) in cols.iter_mut().zip(&shown) {
            col.extend_from_slice(&p.scalars[k]);
        }
    }
    for (col, &k) in cols.into_iter().zip(&shown) {
        c.set_scalar(&names[k], col);
    }
    c
}

#[cfg(all(test, not(target_arch = "wasm32")))]
mod tests {
    use super::*;
    use silvr_core::copc::write::{write_copc, CopcInput, CopcOptions};

    /// A 40,000-point map in nodes of 2,000: within a budget the choice loads at most the budget (past the
    /// root), a connected top of the tree; the cloud made of it has the chosen points, in the map's frame,
    /// with their colours and the shown fields only; a budget above the map loads all of it.
    /// A 40,000-point map over 60 × 40 × 10 m at (1000, 2000, 0), in nodes of 2,000 points, read whole.
    fn map() -> (CopcHead, Vec<(Entry, NodePoints)>) {
        let dir = tempfile::tempdir().unwrap();
        let mut c = PointCloud::new();
        for i in 0..40_000u32 {
            let t = i as f64;
            c.push_colored(
                DVec3::new(
                    1000.0 + (t * 0.618_033_988_7).fract() * 60.0,
                    2000.0 + (t * std::f64::consts::SQRT_2).fract() * 40.0,
                    (t * std::f64::consts::E).fract() * 10.0,
                ),
                [(i % 251) as u8, 3, 4],
            );
        }
        c.set_scalar(
            "log_std_combined",
            (0..40_000).map(|i| -2.0 + (i % 7) as f32 * 0.1).collect(),
        );
        c.set_scalar("not_shown", vec![1.0; 40_000]);
        let out = dir.path().join("m.copc.laz");
        write_copc(
            CopcInput::Cloud(&c),
            &out,
            &CopcOptions {
                points_per_node: 2000,
            },
        )
        .unwrap();
        silvr_core::copc::read::read_file(&out).unwrap()
    }

    #[test]
    fn a_budget_loads_the_top_of_the_octree() {
        let (head, all) = map();
        let entries: Vec<Entry> = all.iter().map(|(e, _)| *e).collect();
        for budget in [5000, 15_000] {
            let chosen = choose(&head, &entries, budget);
            let points: u64 = chosen.iter().map(|e| e.point_count as u64).sum();
            assert!(
                points <= budget && !chosen.is_empty(),
                "{points} of {budget}"
            );
            assert!(chosen.len() < entries.len());
            assert_eq!(
                chosen[0].key,
                silvr_core::copc::read::VoxelKey {
                    level: 0,
                    x: 0,
                    y: 0,
                    z: 0
                }
            );
            let nodes: Vec<&NodePoints> = chosen
                .iter()
                .map(|e| &all.iter().find(|(f, _)| f.key == e.key).unwrap().1)
                .collect();
            let cloud = cloud_of(&head, head.center(), &nodes);
            assert_eq!(cloud.len() as u64, points);
            assert_eq!(cloud.scalars.len(), 1);
            assert!(cloud.scalar("log_std_combined").is_some());
            assert!(cloud
                .positions
                .iter()
                .all(|p| p.x >= 999.99 && p.x <= 1060.01 && p.y >= 1999.99));
            assert_eq!(cloud.colors.as_ref().unwrap().len(), cloud.len());
        }
        assert_eq!(choose(&head, &entries, u64::MAX).len(), entries.len());
    }

    /// The camera's view drives the choice: a camera close to one end of the map refines that end and
    /// culls what is behind it; nodes decoded for one view are kept for the next within the cache bound,
    /// least recently shown dropped first, and a failed node is left out of later plans.
    #[test]
    fn the_camera_refines_what_it_sees_and_the_cache_keeps_the_recent() {
        let (head, all) = map();
        let entries: Vec<Entry> = all.iter().map(|(e, _)| *e).collect();
        let mut s = CopcStream::new(head.clone(), entries.clone());
        let decode = |s: &mut CopcStream, plan: &Plan| {
            for e in &plan.missing {
                let p = &all.iter().find(|(f, _)| f.key == e.key).unwrap().1;
                s.insert(e.key, p.clone());
            }
        };
        let fitted = Camera::fit(head.min.to_array(), head.max.to_array());
        let wide = s.plan(&lod_view(&fitted, (800, 600)), 12_000);
        assert_eq!(wide.chosen, wide.missing, "nothing decoded yet");
        let wide_points: u64 = wide.chosen.iter().map(|e| e.point_count as u64).sum();
        assert!(wide_points <= 12_000 && wide.chosen.len() > 1);
        decode(&mut s, &wide);
        let (cloud, keys) = s.show(&wide.chosen);
        assert_eq!(
            (cloud.len() as u64, keys.len()),
            (wide_points, wide.chosen.len())
        );
        assert!(s
            .plan(&lod_view(&fitted, (800, 600)), 12_000)
            .missing
            .is_empty());
        // Close to the west end, looking east along the map: the far (east) half is culled or coarse.
        let close = Camera {
            target: [1005.0, 2020.0, 5.0],
            yaw: 180.0,
            pitch: 10.0,
            distance: 8.0,
            fov: 60.0,
        };
        let v = lod_view(&close, (800, 600));
        // The eye is west of the target and looks east: a point east of the target is inside, one behind
        // the eye is not.
        let inside = |p: DVec3| v.planes.iter().flatten().all(|(n, d)| n.dot(p) + d >= 0.0);
        assert!(inside(DVec3::new(1010.0, 2020.0, 5.0)));
        assert!(!inside(DVec3::new(990.0, 2020.0, 5.0)));
        let near = s.plan(&v, 12_000);
        let deepest = |p: &Plan, west: bool| {
            p.chosen
                .iter()
                .filter(|e| {
                    let (min, edge) = head.node_cube(e.key);
                    (min.x + edge / 2.0 < 1030.0) == west
                })
                .map(|e| e.key.level)
                .max()
                .unwrap_or(0)
        };
        assert!(
            deepest(&near, true) > deepest(&wide, true),
            "the near end refines"
        );
        assert!(deepest(&near, true) > deepest(&near, false));
        assert!(!near.missing.is_empty());
        decode(&mut s, &near);
        s.show(&near.chosen);
        // Both views' nodes fit a large cache; a small one drops the wide view's nodes not shown now.
        let both = s.cached_points();
        s.evict(u64::MAX);
        assert_eq!(s.cached_points(), both);
        s.evict(0);
        let shown: u64 = near.chosen.iter().map(|e| e.point_count as u64).sum();
        assert_eq!(s.cached_points(), shown, "only the shown nodes stay");
        assert!(near.chosen.iter().all(|e| s.is_cached(&e.key)));
        // A node that failed is not chosen again; the rest of the plan stands, its subtree included.
        let bad = near.chosen[1].key;
        s.fail(bad);
        let again = s.plan(&v, 12_000);
        assert!(again.chosen.iter().all(|e| e.key != bad));
        assert_eq!(again.chosen.len(), near.chosen.len() - 1);
        assert_eq!(s.failed(), 1);
        // A budget the whole map fits loads it whole, whatever the camera sees: even looking away from it
        // (where a smaller budget gets the root alone).
        let away = Camera {
            target: [900.0, 2020.0, 5.0],
            yaw: 0.0,
            pitch: 0.0,
            distance: 10.0,
            fov: 60.0,
        };
        let v = lod_view(&away, (800, 600));
        assert_eq!(s.plan(&v, 39_999).chosen.len(), 1);
        let whole = s.plan(&v, 1_000_000);
        assert_eq!(whole.chosen.len(), entries.len() - 1);
    }

    #[test]
    fn the_budget_is_the_views_else_the_adapters() {
        assert_eq!(budget(None, true), SOFTWARE_BUDGET);
        assert_eq!(budget(None, false), HARDWARE_BUDGET);
        assert_eq!(budget(Some(5), false), BUDGET_RANGE.0);
        assert_eq!(budget(Some(300_000), true), 300_000);
    }
}
