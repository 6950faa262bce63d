//! Simulated sensors over the analytic world: global-shutter cameras (with exact depth, normals, sky and
//! semantics at every pixel centre) and a spinning multi-beam lidar whose every column is fired from the
//! pose at its own instant, so raw sweeps carry real motion distortion.

use glam::{DVec2, DVec3, Vec3};
use rand::{Rng, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::world::{sky, Label, World};
use crate::camera::CameraModel;
use crate::geometry::Se3;

/// A spinning lidar. Beams are evenly spaced in elevation; column k of a sweep fires at
/// `t0 + k / columns / rate_hz` at azimuth `2π k / columns` (counter-clockwise from the sensor's +x).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LidarSpec {
    pub name: String,
    pub beams: u32,
    pub elevation_min_deg: f64,
    pub elevation_max_deg: f64,
    pub columns: u32,
    pub rate_hz: f64,
    pub min_range: f64,
    pub max_range: f64,
    /// Standard deviation of the range noise (m).
    pub range_noise: f64,
    /// Fraction of returns dropped at random.
    pub dropout: f64,
    /// Returns at grazing incidence beyond this angle are dropped.
    pub max_incidence_deg: f64,
}

impl LidarSpec {
    /// Hesai QT64-like (the Frontier rig's lidar): 64 beams over ±52.1°, 0.6° azimuth steps, 60 m.
    pub fn qt64() -> Self {
        Self {
            name: "qt64".into(),
            beams: 64,
            elevation_min_deg: -52.1,
            elevation_max_deg: 52.1,
            columns: 600,
            rate_hz: 10.0,
            min_range: 0.1,
            max_range: 60.0,
            range_noise: 0.02,
            dropout: 0.02,
            max_incidence_deg: 85.0,
        }
    }

    /// The ci world's lidar: every second ring of the QT64 (32 beams over ±52.1°) at 1° azimuth steps.
    /// The field of view is the Spires rig's, so, as in the paper's data, the lidar sees the whole height of
    /// the street the cameras see; only what is beyond its 60 m range (the far tower) is camera-only. (A
    /// ±15° VLP-16 left the upper third of every side image camera-only, which is not the rig SiLVR
    /// targets.)
    pub fn qt64_half() -> Self {
        Self {
            name: "qt64-half".into(),
            beams: 32,
            columns: 360,
            ..Self::qt64()
        }
    }

    pub fn elevation(&self, ring: u32) -> f64 {
        let f = if self.beams > 1 {
            ring as f64 / (self.beams - 1) as f64
        } else {
            0.5
        };
        (self.elevation_min_deg + f * (self.elevation_max_deg - self.elevation_min_deg))
            .to_radians()
    }

    pub fn azimuth(&self, column: u32) -> f64 {
        std::f64::consts::TAU * column as f64 / self.columns as f64
    }

    /// Unit beam direction in the sensor frame.
    pub fn direction(&self, ring: u32, column: u32) -> DVec3 {
        let (el, az) = (self.elevation(ring), self.azimuth(column));
        DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin())
    }

    /// Firing time offset of a column from the sweep start.
    pub fn column_time(&self, column: u32) -> f64 {
        column as f64 / self.columns as f64 / self.rate_hz
    }

    pub fn sweep_duration(&self) -> f64 {
        1.0 / self.rate_hz
    }
}

/// One lidar return as a driver reports it: in the sensor frame at its own firing time.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LidarPoint {
    pub position: DVec3,
    pub intensity: f32,
    pub ring: u16,
    pub column: u16,
    /// Absolute time (s).
    pub time: f64,
}

/// One revolution.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Sweep {
    pub t0: f64,
    pub points: Vec<LidarPoint>,
}

/// Lidar simulation switches; tests turn the noise off to check geometry exactly.
#[derive(Clone, Copy, Debug)]
pub struct LidarNoise {
    pub range: bool,
    pub dropout: bool,
}

/// Fires one sweep starting at `t0`. `pose_at(t)` gives `T_world_lidar` at any instant; with
/// `frozen = Some(t)` every column fires from the pose at `t` instead (the ideal, undistorted sweep).
pub fn simulate_sweep(
    world: &World,
    spec: &LidarSpec,
    pose_at: &(dyn Fn(f64) -> Se3 + Sync),
    t0: f64,
    frozen: Option<f64>,
    noise: LidarNoise,
    seed: u64,
) -> Sweep {
    let columns: Vec<Vec<LidarPoint>> = (0..spec.columns)
        .into_par_iter()
        .map(|col| {
            let mut rng = Xoshiro256PlusPlus::seed_from_u64(
                seed ^ (col as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15),
            );
            let time = t0 + spec.column_time(col);
            let pose = pose_at(frozen.unwrap_or(time));
            let mut out = Vec::with_capacity(spec.beams as usize);
            for ring in 0..spec.beams {
                let d_local = spec.direction(ring, col);
                let d = pose.transform_vector(d_local);
                // Draw every random number regardless of the outcome, so noise on one ray never shifts another's.
                let drop_roll: f64 = rng.random();
                let gauss = gaussian(&mut rng);
                let Some(hit) = world.scene.cast(pose.trans, d, spec.max_range) else {
                    continue;
                };
                if hit.t < spec.min_range {
                    continue;
                }
                let cos_inc = (-d).dot(hit.normal).clamp(0.0, 1.0);
                if noise.dropout
                    && (drop_roll < spec.dropout
                        || cos_inc < spec.max_incidence_deg.to_radians().cos())
                {
                    continue;
                }
                let range = if noise.range {
                    hit.t + spec.range_noise * gauss
                } else {
                    hit.t
                };
                let a = world.albedo(&hit);
                let lum = 0.2126 * a.x + 0.7152 * a.y + 0.0722 * a.z;
                out.push(LidarPoint {
                    position: d_local * range,
                    intensity: (255.0 * lum * cos_inc as f32).clamp(0.0, 255.0),
                    ring: ring as u16,
                    column: col as u16,
                    time,
                });
            }
            out
        })
        .collect();
    Sweep {
        t0,
        points: columns.into_iter().flatten().collect(),
    }
}

/// Standard normal sample (Box–Muller).
pub fn gaussian(rng: &mut Xoshiro256PlusPlus) -> f64 {
    let u1: f64 = rng.random::<f64>().max(1e-300);
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// A rendered camera image and its exact per-pixel ground truth (at pixel centres).
#[derive(Clone, Debug)]
pub struct CameraFrame {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<[u8; 3]>,
    /// Euclidean range from the camera centre (m); 0 for sky or pixels outside the lens model.
    pub range: Vec<f32>,
    /// Unit normal in the camera frame (OpenCV axes), facing the camera; zero where there is no surface.
    pub normal: Vec<[f32; 3]>,
    pub label: Vec<u8>,
}

/// Rendering options.
#[derive(Clone, Copy, Debug)]
pub struct RenderOptions {
    /// Sub-samples per axis (2 → 2x2 supersampling).
    pub supersample: u32,
    /// Standard deviation of per-pixel noise in 8-bit units (0 disables).
    pub noise_std: f32,
    pub seed: u64,
}

/// A camera's rays in its own frame, for every pixel centre and every colour sub-sample: the lens
/// model's inverse is iterative (fisheye), and the same for every frame, so a generator unprojects once.
#[derive(Clone, Debug)]
pub struct CameraRays {
    width: u32,
    height: u32,
    supersample: u32,
    /// Per pixel (row-major): the centre's ray, `None` outside the lens's valid angle.
    centre: Vec<Option<DVec3>>,
    /// Per pixel, `supersample²` sub-sample rays in row-major stratum order.
    sub: Vec<Option<DVec3>>,
}

impl CameraRays {
    pub fn new(camera: &CameraModel, supersample: u32) -> Self {
        let (w, h) = (camera.width, camera.height);
        let ss = supersample.max(1);
        let max_angle = camera.valid_angle();
        let rows: Vec<_> = (0..h)
            .into_par_iter()
            .map(|y| {
                let mut centre = Vec::with_capacity(w as usize);
                let mut sub = Vec::with_capacity((w * ss * ss) as usize);
                for x in 0..w {
                    let c = DVec2::new(x as f64, y as f64);
                    centre.push(camera.unproject_within(c, max_angle));
                    for sy in 0..ss {
                        for sx in 0..ss {
                            let off = DVec2::new(
                                (sx as f64 + 0.5) / ss as f64 - 0.5,
                                (sy as f64 + 0.5) / ss as f64 - 0.5,
                            );
                            sub.push(camera.unproject_within(c + off, max_angle));
                        }
                    }
                }
                (centre, sub)
            })
            .collect();
        let (mut centre, mut sub) = (Vec::new(), Vec::new());
        for (c, s) in rows {
            centre.extend(c);
            sub.extend(s);
        }
        CameraRays {
            width: w,
            height: h,
            supersample: ss,
            centre,
            sub,
        }
    }

    /// The ray through pixel (x, y)'s centre, in the camera frame.
    pub fn centre(&self, x: u32, y: u32) -> Option<DVec3> {
        self.centre[(y * self.width + x) as usize]
    }

    fn sub(&self, x: u32, y: u32) -> &[Option<DVec3>] {
        let n = (self.supersample * self.supersample) as usize;
        let i = (y * self.width + x) as usize * n;
        &self.sub[i..i + n]
    }
}

/// Renders one camera at pose `t_world_cam` (OpenCV camera axes).
pub fn render_camera(
    world: &World,
    camera: &CameraModel,
    t_world_cam: &Se3,
    opts: RenderOptions,
) -> CameraFrame {
    render_rays(
        world,
        &CameraRays::new(camera, opts.supersample),
        t_world_cam,
        opts,
    )
}

/// [`render_camera`] with the camera's rays unprojected beforehand ([`CameraRays`]); `opts.supersample`
/// is the rays'.
pub fn render_rays(
    world: &World,
    rays: &CameraRays,
    t_world_cam: &Se3,
    opts: RenderOptions,
) -> CameraFrame {
    let (w, h) = (rays.width, rays.height);
    let rows: Vec<_> = (0..h)
        .into_par_iter()
        .map(|y| {
            let mut rng = Xoshiro256PlusPlus::seed_from_u64(
                opts.seed ^ (y as u64 + 1).wrapping_mul(0xD1B5_4A32_D192_ED03),
            );
            let mut rgb = Vec::with_capacity(w as usize);
            let mut range = Vec::with_capacity(w as usize);
            let mut normal = Vec::with_capacity(w as usize);
            let mut label = Vec::with_capacity(w as usize);
            for x in 0..w {
                // Ground truth along the pixel-centre ray.
                match rays.centre(x, y) {
                    Some(dir_cam) => {
                        let d = t_world_cam.transform_vector(dir_cam);
                        match world.scene.cast(t_world_cam.trans, d, 1.0e4) {
                            Some(hit) => {
                                range.push(hit.t as f32);
                                let n = t_world_cam.rot.inverse() * hit.normal;
                                normal.push(n.as_vec3().to_array());
                                label.push(world.label(&hit) as u8);
                            }
                            None => {
                                range.push(0.0);
                                normal.push([0.0; 3]);
                                label.push(Label::Sky as u8);
                            }
                        }
                    }
                    None => {
                        range.push(0.0);
                        normal.push([0.0; 3]);
                        label.push(Label::Sky as u8);
                    }
                }
                // Colour: box-filtered over ss x ss stratified sub-samples.
                let mut acc = Vec3::ZERO;
                let mut n = 0.0f32;
                for dir_cam in rays.sub(x, y).iter().flatten() {
                    let d = t_world_cam.transform_vector(*dir_cam);
                    acc += match world.scene.cast(t_world_cam.trans, d, 1.0e4) {
                        Some(hit) => world.shade(&hit),
                        None => sky(d),
                    };
                    n += 1.0;
                }
                let c = if n > 0.0 { acc / n } else { Vec3::ZERO };
                let mut px = [0u8; 3];
                for (k, v) in px.iter_mut().enumerate() {
                    let noise = if opts.noise_std > 0.0 {
                        opts.noise_std * gaussian(&mut rng) as f32
                    } else {
                        0.0
                    };
                    *v = (c[k] * 255.0 + noise).round().clamp(0.0, 255.0) as u8;
                }
                rgb.push(px);
            }
            (rgb, range, normal, label)
        })
        .collect();
    let mut f = CameraFrame {
        width: w,
        height: h,
        rgb: Vec::with_capacity((w * h) as usize),
        range: Vec::with_capacity((w * h) as usize),
        normal: Vec::with_capacity((w * h) as usize),
        label: Vec::with_capacity((w * h) as usize),
    };
    for (rgb, range, normal, label) in rows {
        f.rgb.extend(rgb);
        f.range.extend(range);
        f.normal.extend(normal);
        f.label.extend(label);
    }
    f
}
