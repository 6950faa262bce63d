//! A COPC map in the studio: which octree nodes to load (the level of detail the fitted camera sees, within
//! a point budget) and the layer's cloud made of them. The reading itself is the core's
//! (`silvr_core::copc::read`, by byte ranges); the fetching is the worker's (`web.rs`). Plain Rust, so the
//! tests run natively.

use glam::DVec3;
use serde::{Deserialize, Serialize};
use silvr_core::copc::lod::{self, LodView};
use silvr_core::copc::read::{CopcHead, Entry, NodePoints};
use silvr_core::pointcloud::PointCloud;

use crate::studio::SHOWN_FIELDS;
use crate::view::Camera;

/// Points loaded by default: Potree's default budget, which a software adapter still draws.
pub const DEFAULT_BUDGET: u64 = 1_000_000;

/// What the page is told of a COPC layer's level of detail.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LodInfo {
    /// Octree nodes loaded, of those with points.
    pub nodes: u32,
    pub nodes_total: u32,
    /// The point budget they were chosen within.
    pub budget: u64,
    /// The file's whole-cloud summary of the default filter (`None` for a file without our summary VLR):
    /// the points it keeps of the whole map, and its threshold (log10 σ, metres).
    pub summary_kept: Option<u64>,
    pub summary_threshold: Option<f32>,
}

/// The nodes the camera that frames the map sees, largest on screen first, within `budget` points.
pub fn choose(head: &CopcHead, nodes: &[Entry], budget: u64) -> Vec<Entry> {
    let cam = Camera::fit(head.min.to_array(), head.max.to_array());
    let view = LodView {
        eye: cam.eye(),
        // A nominal 1000-pixel-high view: the choice does not wait for the canvas.
        pixels_per_radian: 1000.0 / (2.0 * (cam.fov.to_radians() / 2.0).tan()),
        planes: [None; 6],
        min_pixels: 0.0,
    };
    let chosen = lod::select(head, nodes, &view, budget);
    chosen
        .nodes
        .iter()
        .filter_map(|k| nodes.iter().find(|e| e.key == *k).copied())
        .collect()
}

/// The layer's cloud: the loaded nodes' points (positions back in the file's frame), colours when the file
/// has them, and the fields the studio shows.
pub fn cloud_of(head: &CopcHead, origin: DVec3, nodes: &[NodePoints]) -> PointCloud {
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
    #[test]
    fn a_budget_loads_the_top_of_the_octree() {
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
        let (head, all) = silvr_core::copc::read::read_file(&out).unwrap();
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
            let nodes: Vec<NodePoints> = chosen
                .iter()
                .map(|e| all.iter().find(|(f, _)| f.key == e.key).unwrap().1.clone())
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
}
