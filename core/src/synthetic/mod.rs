//! The built-in synthetic world: exact ground truth for every measurement the product makes.
//!
//! [`world`] builds the town, [`raycast`] intersects rays with it, [`trajectory`] walks the rig around it,
//! [`sensors`] renders the cameras and fires the lidar, and [`dataset`] writes it all in the project's
//! dataset layout (the same layout ingest writes for real data); [`bag`] (native) records it as a ROS 2 bag.

#[cfg(not(target_arch = "wasm32"))]
pub mod bag;
pub mod generate;
pub mod prior;
pub mod raycast;
pub mod sensors;
pub mod trajectory;
pub mod world;

use serde::{Deserialize, Serialize};

use crate::geometry::Se3;
use crate::rig::Rig;
use sensors::LidarSpec;
use trajectory::MotionParams;
use world::WorldParams;

/// Everything that defines a generated dataset, recorded in its manifest.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Preset {
    pub name: String,
    pub seed: u64,
    pub world: WorldParams,
    pub motion: MotionParams,
    pub rig: Rig,
    pub lidar: LidarSpec,
    /// Number of keyframes (each = one lidar sweep + one image per camera).
    pub keyframes: usize,
    /// Time between keyframes (s); keyframe k's sweep starts at k * interval.
    pub keyframe_interval: f64,
    /// Camera colour supersampling per axis.
    pub supersample: u32,
    /// Per-pixel noise, 8-bit units.
    pub pixel_noise: f32,
    /// Spacing of the ground-truth surface samples (m).
    pub gt_spacing: f64,
    /// Voxel size of the observed-space grid (m).
    pub observed_voxel: f64,
    /// How the SLAM-like prior trajectory (`transforms_prior.json`, `poses/prior_*`) errs.
    #[serde(default)]
    pub prior: prior::PriorParams,
    /// Keyframes of the whole walk when this preset is a prefix of it ([`Preset::prefix`]): the prior's
    /// drift and noise are drawn over the whole walk, so a prefix's prior is the walk's.
    #[serde(default)]
    pub walk_keyframes: Option<usize>,
}

impl Preset {
    /// Small and fast (seconds): 360x270 images, a 32-beam lidar with the QT64's field of view, 20 keyframes
    /// over ~13 m of the south street, which holds the white wall, the textureless road and the far tower in
    /// view.
    pub fn ci(seed: u64) -> Self {
        Self {
            name: "ci".into(),
            seed,
            world: WorldParams::default(),
            motion: MotionParams::default(),
            rig: Rig::oxford_spires_scaled(0.25),
            lidar: LidarSpec::qt64_half(),
            keyframes: 20,
            keyframe_interval: 0.5,
            supersample: 2,
            pixel_noise: 1.0,
            gt_spacing: 0.03,
            observed_voxel: 0.1,
            prior: prior::PriorParams::default(),
            walk_keyframes: None,
        }
    }

    /// The parity tests' world (seconds to generate and to train on a software adapter): the `ci` street
    /// at 180x135 pixels, 12 keyframes (two held out), ground truth at 5 cm spacing.
    pub fn micro(seed: u64) -> Self {
        Self {
            name: "micro".into(),
            rig: Rig::oxford_spires_scaled(0.125),
            keyframes: 12,
            gt_spacing: 0.05,
            ..Self::ci(seed)
        }
    }

    /// The full loop: 720x540 images, a 64-beam lidar, 120 keyframes around the block, closing on itself.
    pub fn default_preset(seed: u64) -> Self {
        let motion = MotionParams::default();
        // Walk the loop plus 8 m, so the end revisits the start.
        let duration = (motion.loop_length() + 8.0) / motion.speed;
        let keyframes = 120;
        Self {
            name: "default".into(),
            seed,
            world: WorldParams::default(),
            rig: Rig::oxford_spires_scaled(0.5),
            lidar: LidarSpec::qt64(),
            keyframes,
            keyframe_interval: duration / keyframes as f64,
            motion,
            supersample: 2,
            pixel_noise: 1.0,
            gt_spacing: 0.03,
            observed_voxel: 0.1,
            prior: prior::PriorParams::default(),
            walk_keyframes: None,
        }
    }

    /// The paper-scale mission: a 4 x 3-block campus (192 x 114 m between its perimeter streets'
    /// centre lines, 21,900 m²) walked along 1.28 km of its streets, a keyframe every 1.25 m (1,027
    /// keyframes, 3,081 images at 720x540). The walk closes loops: it comes back to streets it walked
    /// before across them, along them in the same direction and in the opposite one ([`campus_route`]).
    /// Its prior (0.005°/m of yaw drift, a tenth of the town's, whose loop is 160 m) is metres off at
    /// each revisit. Ground truth at 5 cm and the observed-space
    /// grid at 20 cm (the default world's 3 cm and 10 cm would hold ~8x the memory over this area).
    pub fn campus(seed: u64) -> Self {
        let campus = world::CampusParams::default();
        let world = WorldParams {
            road_width: 8.0,
            layout: world::Layout::Campus(campus.clone()),
            ..WorldParams::default()
        };
        let motion = MotionParams {
            route: campus_route(&campus, world.road_width),
            start_offset: 0.0,
            ..MotionParams::default()
        };
        let spacing = 1.25;
        let keyframes = ((motion.path_length() - 1.0) / spacing).floor() as usize;
        Self {
            name: "campus".into(),
            seed,
            rig: Rig::oxford_spires_scaled(0.5),
            lidar: LidarSpec::qt64(),
            keyframes,
            keyframe_interval: spacing / motion.speed,
            world,
            motion,
            supersample: 2,
            pixel_noise: 1.0,
            gt_spacing: 0.05,
            observed_voxel: 0.2,
            prior: prior::PriorParams {
                yaw_deg_per_m: 0.005,
                ..prior::PriorParams::default()
            },
            walk_keyframes: None,
        }
    }

    /// The campus's loop at CI size: one 40 x 30 m block of the campus world, walked once round its
    /// four streets and on along the first to its middle, a keyframe every 2 m (94 keyframes, 282 images
    /// at 360x270, the ci world's rig and lidar). Its prior drifts 0.08°/m in yaw, so that one short lap
    /// ends ~2 m off, as the campus's long ones do at 0.005°/m: at 0.03°/m (~1 m off) the prior's own
    /// gate still paired the two passes and the adjustment alone closed the loop, which a CI check of
    /// loop closure must not allow.
    pub fn campus_loop(seed: u64) -> Self {
        // The campus's world, ground truth and noise settings; its own block, walk, rig and prior.
        let base = Self::campus(seed);
        let campus = world::CampusParams {
            blocks: [1, 1],
            block_size: [40.0, 30.0],
        };
        let world = WorldParams {
            layout: world::Layout::Campus(campus.clone()),
            ..base.world.clone()
        };
        let c = |i, j| campus.crossing(world.road_width, i, j).to_array();
        let (a, b) = (c(0, 0), c(1, 0));
        let motion = MotionParams {
            route: vec![
                a,
                b,
                c(1, 1),
                c(0, 1),
                a,
                [(a[0] + b[0]) / 2.0, (a[1] + b[1]) / 2.0],
            ],
            ..base.motion.clone()
        };
        let spacing = 2.0;
        Self {
            name: "campus-loop".into(),
            rig: Rig::oxford_spires_scaled(0.25),
            lidar: LidarSpec::qt64_half(),
            keyframes: ((motion.path_length() - 1.0) / spacing).floor() as usize,
            keyframe_interval: spacing / motion.speed,
            world,
            motion,
            prior: prior::PriorParams {
                yaw_deg_per_m: 0.08,
                ..base.prior.clone()
            },
            ..base
        }
    }

    /// A preset by name (`ci`, `default`, `campus`, `campus-loop`, or `micro` for the parity tests).
    pub fn by_name(name: &str, seed: u64) -> Option<Self> {
        match name {
            "ci" => Some(Self::ci(seed)),
            "micro" => Some(Self::micro(seed)),
            "default" => Some(Self::default_preset(seed)),
            "campus" => Some(Self::campus(seed)),
            "campus-loop" => Some(Self::campus_loop(seed)),
            _ => None,
        }
    }

    /// The names [`Preset::by_name`] knows, for messages.
    pub const NAMES: &'static str = "ci, default, campus, campus-loop (or micro)";

    /// The first `n` keyframes of the same walk: the same world, poses and prior at every kept
    /// keyframe (the interval stays the full walk's), for growth curves. 3 keyframes at least (poses and
    /// evaluation need them), at most the preset's.
    pub fn prefix(mut self, n: usize) -> Result<Self, String> {
        if n < 3 || n > self.keyframes {
            return Err(format!(
                "the {} preset has {} keyframes; a prefix keeps 3 to {}",
                self.name, self.keyframes, self.keyframes
            ));
        }
        self.walk_keyframes = Some(self.walk_keyframes.unwrap_or(self.keyframes));
        self.keyframes = n;
        Ok(self)
    }

    /// Sweep start time of keyframe `k`.
    pub fn sweep_start(&self, k: usize) -> f64 {
        k as f64 * self.keyframe_interval
    }

    /// Image time of keyframe `k`: cameras are triggered at the sweep's mid-time.
    pub fn image_time(&self, k: usize) -> f64 {
        self.sweep_start(k) + 0.5 * self.lidar.sweep_duration()
    }

    /// `T_world_base` at time t.
    pub fn t_world_base(&self, t: f64) -> Se3 {
        self.motion.pose(t)
    }

    /// `T_world_lidar` at time t.
    pub fn t_world_lidar(&self, t: f64) -> Se3 {
        self.motion.pose(t) * self.rig.t_base_lidar
    }

    /// `T_world_cam` of camera `i` at time t.
    pub fn t_world_cam(&self, i: usize, t: f64) -> Se3 {
        self.t_world_lidar(t) * self.rig.cameras[i].t_lidar_cam
    }
}

/// The campus walk as crossings of its street grid (vertical street i, horizontal street j), from the
/// south-west corner east along the south street. It comes back to streets it walked at least 150 m
/// before seven times (seed 1: with 1.2 to 8.2 m of the prior's drift between the two passes): across
/// them, along them the same way, and twice against its first pass (the south street westwards after
/// the first 440 m loop, the street i = 3 northwards after the second).
pub fn campus_route(c: &world::CampusParams, road_width: f64) -> Vec<[f64; 2]> {
    const CROSSINGS: [(usize, usize); 16] = [
        (0, 0),
        (4, 0),
        (4, 2),
        (2, 2),
        (2, 0),
        (0, 0),
        (0, 3),
        (3, 3),
        (3, 1),
        (1, 1),
        (1, 0),
        (3, 0),
        (3, 1),
        (4, 1),
        (4, 3),
        (3, 3),
    ];
    CROSSINGS
        .iter()
        .map(|&(i, j)| c.crossing(road_width, i, j).to_array())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Where the campus walk comes back: keyframes within 4 m of one walked at least 150 m earlier (the
    /// nearest such), grouped into events: a new event when the walk leaves the old path for 40
    /// keyframes or meets another part of it. Per event its first pair and whether the two passes head
    /// the opposite way anywhere in it.
    fn revisits(p: &Preset) -> Vec<(usize, usize, bool)> {
        let poses: Vec<Se3> = (0..p.keyframes)
            .map(|k| p.t_world_base(p.image_time(k)))
            .collect();
        let heading = |k: usize| poses[k].rot * glam::DVec3::X;
        let gap = (150.0 / (p.motion.speed * p.keyframe_interval)) as usize;
        let mut events: Vec<(usize, usize, bool)> = Vec::new();
        let mut last: Option<(usize, usize)> = None;
        for k in 0..poses.len() {
            let near = (0..k.saturating_sub(gap))
                .map(|j| ((poses[k].trans - poses[j].trans).truncate().length(), j))
                .filter(|&(d, _)| d < 4.0)
                .min_by(|a, b| a.0.total_cmp(&b.0));
            let Some((_, j)) = near else { continue };
            let opposite = heading(k).dot(heading(j)) < -0.9;
            match last {
                Some((lk, lj)) if k <= lk + 40 && j.abs_diff(lj) <= 40 => {
                    events.last_mut().unwrap().2 |= opposite;
                }
                _ => events.push((j, k, opposite)),
            }
            last = Some((k, j));
        }
        events
    }

    #[test]
    fn the_campus_is_paper_scale_and_its_walk_closes_loops_the_prior_does_not() {
        let p = Preset::campus(1);
        let images = p.keyframes * p.rig.cameras.len();
        assert!(p.keyframes >= 1000 && images >= 3000, "{images} images");
        let (mut lo, mut hi) = (glam::DVec2::INFINITY, glam::DVec2::NEG_INFINITY);
        for k in 0..p.keyframes {
            let t = p.t_world_base(p.image_time(k)).trans.truncate();
            lo = lo.min(t);
            hi = hi.max(t);
        }
        let area = (hi - lo).x * (hi - lo).y;
        assert!(area >= 20_000.0, "walked over {area} m²");

        let events = revisits(&p);
        assert!(events.len() >= 3, "revisits {events:?}");
        assert!(
            events.iter().any(|e| e.2),
            "no opposite revisit: {events:?}"
        );
        // The prior's drift between the two passes of each revisit: metres, so loops do not close by
        // themselves.
        let exact: Vec<Se3> = (0..p.keyframes)
            .map(|k| p.t_world_base(p.image_time(k)))
            .collect();
        let (prior, _) = prior::prior_trajectory(&exact, &p.prior, p.seed);
        for &(j, k, _) in &events {
            let rel = |poses: &[Se3]| poses[k].trans - poses[j].trans;
            let drift = (rel(&prior) - rel(&exact)).length();
            assert!(
                drift > 1.0,
                "revisit {j}->{k}: the prior drifted only {drift:.2} m"
            );
        }
    }
}
