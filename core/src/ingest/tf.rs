//! The static part of a bag's TF tree (`/tf_static`, or `/tf` edges that never move): frame-to-frame
//! lookups by walking the tree, so the ingest can find `T_base_lidar` and each `T_lidar_cam` when the
//! calibration file does not give them.

use std::collections::{BTreeMap, VecDeque};

use crate::geometry::Se3;

/// Transforms between named frames, stored as `T_parent_child` edges.
#[derive(Clone, Debug, Default)]
pub struct TfGraph {
    /// frame → [(neighbour, T_frame_neighbour)], both directions.
    edges: BTreeMap<String, Vec<(String, Se3)>>,
}

impl TfGraph {
    /// Adds (or replaces) the edge `parent` ← `child` with `t_parent_child` (maps child points into parent).
    pub fn insert(&mut self, parent: &str, child: &str, t_parent_child: Se3) {
        let t = Se3::new(t_parent_child.rot, t_parent_child.trans);
        self.remove(parent, child);
        self.edges
            .entry(parent.to_string())
            .or_default()
            .push((child.to_string(), t));
        self.edges
            .entry(child.to_string())
            .or_default()
            .push((parent.to_string(), t.inverse()));
    }

    fn remove(&mut self, a: &str, b: &str) {
        if let Some(v) = self.edges.get_mut(a) {
            v.retain(|(n, _)| n != b);
        }
        if let Some(v) = self.edges.get_mut(b) {
            v.retain(|(n, _)| n != a);
        }
    }

    /// Whether `frame` appears in any edge.
    pub fn has_frame(&self, frame: &str) -> bool {
        self.edges.get(frame).is_some_and(|v| !v.is_empty())
    }

    /// Every frame name.
    pub fn frames(&self) -> impl Iterator<Item = &str> {
        self.edges.keys().map(|s| s.as_str())
    }

    /// `T_target_source`: maps points of `source` into `target`, through any chain of edges. `None` when the
    /// frames are not connected.
    pub fn lookup(&self, target: &str, source: &str) -> Option<Se3> {
        if target == source {
            return Some(Se3::IDENTITY);
        }
        // Breadth-first from `target`, carrying T_target_frame.
        let mut seen: BTreeMap<&str, Se3> = BTreeMap::new();
        let mut queue = VecDeque::new();
        seen.insert(target, Se3::IDENTITY);
        queue.push_back(target);
        while let Some(frame) = queue.pop_front() {
            let t_target_frame = seen[frame];
            for (next, t_frame_next) in self.edges.get(frame).into_iter().flatten() {
                if seen.contains_key(next.as_str()) {
                    continue;
                }
                let t = t_target_frame * *t_frame_next;
                if next == source {
                    return Some(t);
                }
                seen.insert(next, t);
                queue.push_back(next);
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{DQuat, DVec3};

    #[test]
    fn lookup_chains_and_inverts() {
        let t_base_lidar = Se3::new(
            DQuat::from_rotation_z(std::f64::consts::PI),
            DVec3::new(0.0, 0.0, 0.124),
        );
        let t_lidar_cam = Se3::new(DQuat::from_rotation_x(-1.2), DVec3::new(0.01, -0.08, -0.05));
        let mut g = TfGraph::default();
        g.insert("base_link", "lidar", t_base_lidar);
        g.insert("lidar", "cam0", t_lidar_cam);
        g.insert("odom", "other", Se3::IDENTITY);
        let p = DVec3::new(1.0, 2.0, 3.0);
        let want = (t_base_lidar * t_lidar_cam).transform_point(p);
        let got = g.lookup("base_link", "cam0").unwrap().transform_point(p);
        assert!((want - got).length() < 1e-12, "{want} {got}");
        let back = g.lookup("cam0", "base_link").unwrap().transform_point(want);
        assert!((back - p).length() < 1e-12);
        assert!(g.lookup("base_link", "other").is_none());
        assert!(g.lookup("cam0", "cam0").is_some());
        // Replacing an edge (also given in the other direction) keeps one.
        g.insert("cam0", "lidar", t_lidar_cam.inverse());
        let got = g.lookup("base_link", "cam0").unwrap().transform_point(p);
        assert!((want - got).length() < 1e-12);
        assert!(g.has_frame("odom") && !g.has_frame("map"));
    }
}
