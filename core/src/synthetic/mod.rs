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

    /// A preset by name (`ci`, `default`, or `micro` for the parity tests).
    pub fn by_name(name: &str, seed: u64) -> Option<Self> {
        match name {
            "ci" => Some(Self::ci(seed)),
            "micro" => Some(Self::micro(seed)),
            "default" => Some(Self::default_preset(seed)),
            _ => None,
        }
    }

    /// Sweep start time of keyframe `k`.
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
