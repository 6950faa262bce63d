//! Lidar points → one camera's pixels with a z-buffer (nearest range wins), on the GPU
//! (`shaders/project_zbuffer.wgsl`) and on the CPU (the reference, in f64 through [`CameraModel`]).
//!
//! Ties are broken by the lower point index on both sides, so the two agree exactly on which point owns a
//! pixel whenever the f32 arithmetic of the GPU cannot flip a decision (a point within ~1e-4 px of a pixel
//! boundary, or two ranges within a few ulps). The later depth and normal images read the winners.

use bytemuck::{Pod, Zeroable};
use glam::{DVec3, Vec4};

use crate::camera::{CameraModel, Distortion};
use crate::geometry::Se3;
use crate::gpu::{Gpu, GpuError, Kernel};
use crate::shaders;

/// Marks "no point" in [`Projection::winner`] and "not in the image" in [`Projection::point_pixel`].
pub const NONE: u32 = u32::MAX;

/// Coordinates whose magnitude exceeds this are treated like NaN: f32 range computations would overflow.
const MAX_COORD: f32 = 1.0e18;

const KERNEL: Kernel = Kernel {
    name: "project_zbuffer",
    source: shaders::PROJECT_ZBUFFER,
    workgroup_size: 64,
};

/// What to project and where.
#[derive(Clone, Copy, Debug)]
pub struct ProjectionInput<'a> {
    pub camera: &'a CameraModel,
    /// Maps the points' frame into the camera's (OpenCV axes).
    pub t_cam_points: Se3,
    /// Point positions in their own frame.
    pub points: &'a [DVec3],
    /// Points nearer than this (m) are ignored, like a lidar's minimum range.
    pub near: f32,
}

/// Per-pixel winners and per-point pixels.
#[derive(Clone, Debug, PartialEq)]
pub struct Projection {
    pub width: u32,
    pub height: u32,
    /// Per pixel (row-major), the index of the nearest point, or [`NONE`].
    pub winner: Vec<u32>,
    /// Per pixel, the Euclidean range (m) of the winner, or 0.
    pub range: Vec<f32>,
    /// Per point, its pixel index, or [`NONE`] when it is outside the image, behind, too near or invalid.
    pub point_pixel: Vec<u32>,
    /// Per point, the projected (u, v) in pixels (meaningful only where `point_pixel` is not [`NONE`]).
    pub point_uv: Vec<[f32; 2]>,
    /// Points skipped because a coordinate was NaN, infinite or absurdly large.
    pub skipped_nonfinite: usize,
}

impl Projection {
    /// Pixels that received a point.
    pub fn filled(&self) -> usize {
        self.winner.iter().filter(|&&w| w != NONE).count()
    }

    /// Pixels whose winner differs between `self` and `other`.
    pub fn winner_mismatches(&self, other: &Projection) -> usize {
        self.winner
            .iter()
            .zip(&other.winner)
            .filter(|(a, b)| a != b)
            .count()
    }
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct Params {
    intrinsics: [f32; 4],
    dist: [f32; 4],
    extra: [f32; 4],
    r0: [f32; 4],
    r1: [f32; 4],
    r2: [f32; 4],
    dims: [u32; 4],
}

fn check(input: &ProjectionInput) -> Result<(), GpuError> {
    let c = input.camera;
    if c.width == 0 || c.height == 0 {
        return Err(GpuError::InvalidInput(format!(
            "camera image size is {}x{}",
            c.width, c.height
        )));
    }
    let pixels = c.width as u64 * c.height as u64;
    if pixels >= NONE as u64 {
        return Err(GpuError::InvalidInput(format!(
            "camera image {}x{} has too many pixels",
            c.width, c.height
        )));
    }
    if input.points.len() as u64 >= NONE as u64 {
        return Err(GpuError::InvalidInput(format!(
            "{} points is more than one projection call takes",
            input.points.len()
        )));
    }
    let params = [c.fx, c.fy, c.cx, c.cy];
    if params.iter().any(|v| !v.is_finite()) || c.fx <= 0.0 || c.fy <= 0.0 {
        return Err(GpuError::InvalidInput(format!(
            "camera intrinsics must be finite with positive focal lengths, got fx={} fy={} cx={} cy={}",
            c.fx, c.fy, c.cx, c.cy
        )));
    }
    if !input.near.is_finite() || input.near < 0.0 {
        return Err(GpuError::InvalidInput(format!(
            "near range must be a finite non-negative number, got {}",
            input.near
        )));
    }
    Ok(())
}

fn usable(p: &DVec3) -> bool {
    p.is_finite() && p.abs().max_element() <= MAX_COORD as f64
}

/// The CPU reference: f64 geometry through [`CameraModel::project`].
pub fn project_cpu(input: &ProjectionInput) -> Result<Projection, GpuError> {
    check(input)?;
    let c = input.camera;
    let (w, h) = (c.width, c.height);
    let n_pix = (w * h) as usize;
    let mut winner = vec![NONE; n_pix];
    let mut best = vec![f64::INFINITY; n_pix];
    let mut point_pixel = vec![NONE; input.points.len()];
    let mut point_uv = vec![[0.0f32; 2]; input.points.len()];
    let mut skipped = 0;
    let max_angle = c.valid_angle();
    for (i, p) in input.points.iter().enumerate() {
        if !usable(p) {
            skipped += 1;
            continue;
        }
        // Same rounding point as the kernel: positions are f32 on the GPU.
        let q = p.as_vec3().as_dvec3();
        let pc = input.t_cam_points.transform_point(q);
        let range = pc.length();
        if !(range > 0.0 && range >= input.near as f64) {
            continue;
        }
        let Some(uv) = c.project_within(pc, max_angle) else {
            continue;
        };
        let Some((px, py)) = c.pixel_of(uv) else {
            continue;
        };
        point_uv[i] = [uv.x as f32, uv.y as f32];
        let pix = (py * w + px) as usize;
        point_pixel[i] = pix as u32;
        // Lower range wins; on an exact tie the lower index (visited first) keeps the pixel.
        if range < best[pix] {
            best[pix] = range;
            winner[pix] = i as u32;
        }
    }
    let range = winner
        .iter()
        .zip(&best)
        .map(|(&wi, &r)| if wi == NONE { 0.0 } else { r as f32 })
        .collect();
    Ok(Projection {
        width: w,
        height: h,
        winner,
        range,
        point_pixel,
        point_uv,
        skipped_nonfinite: skipped,
    })
}

/// The WGSL path: three dispatches (clear, project, resolve) and one async readback.
pub async fn project_gpu(gpu: &Gpu, input: &ProjectionInput<'_>) -> Result<Projection, GpuError> {
    check(input)?;
    let c = input.camera;
    let (w, h) = (c.width, c.height);
    let n_pix = (w * h) as usize;
    let n = input.points.len();
    let mut skipped = 0;
    let packed: Vec<Vec4> = input
        .points
        .iter()
        .map(|p| {
            if usable(p) {
                p.as_vec3().extend(1.0)
            } else {
                skipped += 1;
                Vec4::ZERO
            }
        })
        .collect();
    let m = input.t_cam_points.to_mat4();
    let row = |r: usize| -> [f32; 4] {
        let v = m.row(r);
        [v.x as f32, v.y as f32, v.z as f32, v.w as f32]
    };
    let (model, dist, k3) = match c.distortion {
        Distortion::None => (0u32, [0.0; 4], 0.0),
        Distortion::RadTan { k1, k2, p1, p2, k3 } => (1, [k1, k2, p1, p2], k3),
        Distortion::Fisheye { k1, k2, k3, k4 } => (2, [k1, k2, k3, k4], 0.0),
    };
    let params = Params {
        intrinsics: [c.fx as f32, c.fy as f32, c.cx as f32, c.cy as f32],
        dist: dist.map(|d| d as f32),
        extra: [k3 as f32, c.valid_angle() as f32, input.near, 0.0],
        r0: row(0),
        r1: row(1),
        r2: row(2),
        dims: [w, h, model, n as u32],
    };
    let u_params = gpu.uniform("project.params", &params);
    let b_points = gpu.upload("lidar points", &packed)?;
    let b_key = gpu.output("pixel range keys", n_pix)?;
    let b_winner = gpu.output("pixel winners", n_pix)?;
    let b_pixel = gpu.output("point pixels", n)?;
    let b_proj = gpu.output("point projections", n * 4)?;

    let mut enc = gpu.encoder("project_zbuffer");
    gpu.dispatch(
        &mut enc,
        &KERNEL,
        "clear",
        &[(0, &u_params), (2, &b_key), (3, &b_winner)],
        n_pix as u32,
    )
    .await?;
    if n > 0 {
        gpu.dispatch(
            &mut enc,
            &KERNEL,
            "project",
            &[
                (0, &u_params),
                (1, &b_points),
                (2, &b_key),
                (4, &b_pixel),
                (5, &b_proj),
            ],
            n as u32,
        )
        .await?;
        gpu.dispatch(
            &mut enc,
            &KERNEL,
            "resolve",
            &[
                (0, &u_params),
                (2, &b_key),
                (3, &b_winner),
                (4, &b_pixel),
                (5, &b_proj),
            ],
            n as u32,
        )
        .await?;
    }
    let mut out = gpu
        .finish_and_read::<u32>(
            enc,
            &[
                (&b_key, n_pix),
                (&b_winner, n_pix),
                (&b_pixel, n),
                (&b_proj, n * 4),
            ],
        )
        .await?
        .into_iter();
    let (keys, winner, point_pixel, proj) = (
        out.next().unwrap_or_default(),
        out.next().unwrap_or_default(),
        out.next().unwrap_or_default(),
        out.next().unwrap_or_default(),
    );
    let range = keys
        .iter()
        .zip(&winner)
        .map(|(&k, &wi)| if wi == NONE { 0.0 } else { f32::from_bits(k) })
        .collect();
    let point_uv = proj
        .chunks_exact(4)
        .zip(&point_pixel)
        .map(|(q, &pix)| {
            if pix == NONE {
                [0.0, 0.0]
            } else {
                [f32::from_bits(q[0]), f32::from_bits(q[1])]
            }
        })
        .collect();
    Ok(Projection {
        width: w,
        height: h,
        winner,
        range,
        point_pixel,
        point_uv,
        skipped_nonfinite: skipped,
    })
}

/// A reproducible projection problem for self-checks (CLI `gpu-info`, the studio worker, tests): points
/// unprojected from random sub-pixel positions (kept ≥ 0.1 px from pixel boundaries, so f32 and f64 agree
/// on the pixel), some exact duplicates (tie-break by index), and points behind the camera, outside the
/// image, too near, and NaN.
pub fn sample_points(camera: &CameraModel, seed: u64, n: usize) -> Vec<DVec3> {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed);
    let mut pts = Vec::with_capacity(n);
    let max_angle = camera.valid_angle();
    while pts.len() < n {
        let kind: f64 = rng.random();
        let p = if kind < 0.05 && !pts.is_empty() {
            // An exact duplicate of an earlier point.
            pts[rng.random_range(0..pts.len())]
        } else if kind < 0.10 {
            // Anywhere around the camera, often behind it or off-image.
            DVec3::new(
                rng.random_range(-20.0..20.0),
                rng.random_range(-20.0..20.0),
                rng.random_range(-20.0..20.0),
            )
        } else if kind < 0.11 {
            DVec3::new(f64::NAN, 1.0, 2.0)
        } else if kind < 0.12 {
            DVec3::new(0.0, 0.0, 0.01)
        } else {
            let px = rng.random_range(0..camera.width) as f64 + rng.random_range(-0.4..0.4);
            let py = rng.random_range(0..camera.height) as f64 + rng.random_range(-0.4..0.4);
            let Some(ray) = camera.unproject_within(glam::DVec2::new(px, py), max_angle) else {
                continue;
            };
            ray * rng.random_range(0.5..40.0)
        };
        pts.push(p);
    }
    pts
}

/// The outcome of running the kernel and its reference on [`sample_points`].
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct SelfCheck {
    pub points: usize,
    pub pixels: usize,
    pub filled_pixels: usize,
    pub winner_mismatches: usize,
    pub max_uv_error_px: f32,
    pub max_range_rel_error: f32,
}

impl SelfCheck {
    /// Exact winners, sub-millipixel positions and f32-rounding-level ranges.
    pub fn passed(&self) -> bool {
        self.winner_mismatches == 0
            && self.filled_pixels > 0
            && self.max_uv_error_px < 1e-2
            && self.max_range_rel_error < 1e-5
    }
}

/// Compares two projections of the same input.
pub fn compare(gpu: &Projection, cpu: &Projection) -> SelfCheck {
    let mut max_uv = 0.0f32;
    for ((g, c), (&pg, &pc)) in gpu
        .point_uv
        .iter()
        .zip(&cpu.point_uv)
        .zip(gpu.point_pixel.iter().zip(&cpu.point_pixel))
    {
        if pg != NONE && pc != NONE {
            max_uv = max_uv.max((g[0] - c[0]).abs()).max((g[1] - c[1]).abs());
        }
    }
    let mut max_rel = 0.0f32;
    for (&g, &c) in gpu.range.iter().zip(&cpu.range) {
        if c > 0.0 {
            max_rel = max_rel.max((g - c).abs() / c);
        }
    }
    let pixel_mismatch = gpu
        .point_pixel
        .iter()
        .zip(&cpu.point_pixel)
        .filter(|(a, b)| a != b)
        .count();
    SelfCheck {
        points: gpu.point_pixel.len(),
        pixels: gpu.winner.len(),
        filled_pixels: cpu.filled(),
        winner_mismatches: gpu.winner_mismatches(cpu) + pixel_mismatch,
        max_uv_error_px: max_uv,
        max_range_rel_error: max_rel,
    }
}

/// Runs the projection kernel against its CPU reference on a generated problem.
pub async fn self_check(
    gpu: &Gpu,
    camera: &CameraModel,
    seed: u64,
    n: usize,
) -> Result<SelfCheck, GpuError> {
    // Express the points in a rotated, offset "lidar" frame so the kernel's transform is exercised too.
    let t_lidar_cam = Se3::new(
        glam::DQuat::from_euler(glam::EulerRot::ZYX, 0.7, -0.2, 1.9),
        DVec3::new(0.3, -1.2, 0.5),
    );
    let points: Vec<DVec3> = sample_points(camera, seed, n)
        .into_iter()
        .map(|p| t_lidar_cam.transform_point(p))
        .collect();
    let input = ProjectionInput {
        camera,
        t_cam_points: t_lidar_cam.inverse(),
        points: &points,
        near: 0.1,
    };
    let g = project_gpu(gpu, &input).await?;
    let c = project_cpu(&input)?;
    Ok(compare(&g, &c))
}
