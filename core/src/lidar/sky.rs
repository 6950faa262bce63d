//! Sky masks without a learned network: the lidar says where the sky is (beams that return nothing, with
//! nothing above them either), the image says how far it extends (a smooth, blue-leaning region).
//!
//! 1. Ring elevations and column azimuths are estimated from the returns themselves (medians), so no
//!    sensor model is needed and real sweeps work the same way.
//! 2. A no-return cell is sky evidence when its beam points above the sensor's horizon and every higher
//!    ring in its column is empty too (a clear line to the sky, not a dropout or a dark surface).
//! 3. Evidence directions are projected into the camera as seeds; pixels whose ray rises above the lidar's
//!    top beam and look like sky seed too (the lidar knows nothing there).
//! 4. A 4-connected flood fill grows the seeds over sky-coloured pixels with small colour steps, and never
//!    crosses a pixel where a lidar return projects (dilated by one pixel).

use glam::{DVec2, DVec3};

use super::normals::RangeImage;
use crate::camera::CameraModel;
use crate::geometry::Se3;

/// Tunables of [`sky_mask`]; the defaults are used for every dataset (not tuned per scene).
#[derive(Clone, Copy, Debug)]
pub struct SkyParams {
    /// Minimum blue-minus-red (8-bit) of a sky-coloured pixel.
    pub min_blue_excess: i32,
    /// Minimum blue channel (8-bit).
    pub min_blue: u8,
    /// Largest per-channel step between neighbouring sky pixels (8-bit).
    pub max_step: i32,
    /// Extra elevation (rad) above the lidar's top beam for image-only seeds.
    pub prior_margin: f64,
}

impl Default for SkyParams {
    fn default() -> Self {
        Self {
            min_blue_excess: 12,
            min_blue: 110,
            max_step: 10,
            prior_margin: 2f64.to_radians(),
        }
    }
}

/// Inputs describing one camera image and the (deskewed) sweep taken with it.
pub struct SkyInput<'a> {
    pub camera: &'a CameraModel,
    pub rgb: &'a [[u8; 3]],
    /// Maps the sweep's frame (the lidar at image time) into the camera.
    pub t_cam_lidar: Se3,
    /// Sweep points in the lidar frame, their cells in `image`.
    pub points: &'a [DVec3],
    pub image: &'a RangeImage,
    /// Per-pixel depth of the projected returns (non-zero = a return lands there).
    pub depth: &'a [u16],
    /// World "up" expressed in the lidar frame.
    pub up_lidar: DVec3,
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let mid = v.len() / 2;
    v.select_nth_unstable_by(mid, f64::total_cmp);
    Some(v[mid])
}

/// The sky mask (true = sky), row-major like the image.
pub fn sky_mask(input: &SkyInput, params: SkyParams) -> Vec<bool> {
    let cam = input.camera;
    let (w, h) = (cam.width as usize, cam.height as usize);
    let img = input.image;
    let max_angle = cam.valid_angle();
    // 1. Beam geometry from the returns.
    let mut ring_el: Vec<Vec<f64>> = vec![Vec::new(); img.rings];
    let mut col_az: Vec<Vec<f64>> = vec![Vec::new(); img.columns];
    for (cell, i) in img.cells.iter().enumerate() {
        let Some(i) = i else { continue };
        let p = input.points[*i as usize];
        if p.is_finite() && p.length() > 0.0 {
            ring_el[cell / img.columns].push((p.z / p.length()).asin());
            col_az[cell % img.columns].push(p.y.atan2(p.x));
        }
    }
    let ring_el: Vec<Option<f64>> = ring_el.into_iter().map(median).collect();
    let mut col_az: Vec<Option<f64>> = col_az.into_iter().map(median).collect();
    // Columns with no return at all (open sky all round) take the azimuth their neighbours imply.
    let n_cols = img.columns;
    for (c, az) in col_az.iter_mut().enumerate() {
        if az.is_none() {
            *az = Some(std::f64::consts::TAU * c as f64 / n_cols as f64);
        }
    }
    let top_el = ring_el
        .iter()
        .flatten()
        .cloned()
        .fold(f64::NEG_INFINITY, f64::max);
    // 2. Evidence cells.
    let mut seeds: Vec<(usize, usize)> = Vec::new();
    let r_cam = input.t_cam_lidar;
    for (c, az) in col_az.iter().enumerate() {
        let mut clear_above = true;
        for r in (0..img.rings).rev() {
            if img.cells[r * n_cols + c].is_some() {
                clear_above = false;
            }
            let (Some(el), Some(az)) = (ring_el[r], *az) else {
                continue;
            };
            if !clear_above || el <= 0.0 {
                continue;
            }
            let d = DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
            let dc = r_cam.transform_vector(d);
            if let Some(uv) = cam.project_within(dc, max_angle) {
                if let Some((x, y)) = cam.pixel_of(uv) {
                    seeds.push((x as usize, y as usize));
                }
            }
        }
    }
    // Barrier: pixels where returns land, dilated by one.
    let mut barrier = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            if input.depth[y * w + x] != 0 {
                for (dx, dy) in [(0i64, 0i64), (1, 0), (-1, 0), (0, 1), (0, -1)] {
                    let (xx, yy) = (x as i64 + dx, y as i64 + dy);
                    if xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
                        barrier[yy as usize * w + xx as usize] = true;
                    }
                }
            }
        }
    }
    let sky_like = |px: [u8; 3]| {
        px[2] as i32 - px[0] as i32 >= params.min_blue_excess && px[2] >= params.min_blue
    };
    // 3. Image-only seeds above the lidar's field of view.
    let up_cam = r_cam.transform_vector(input.up_lidar).normalize();
    if top_el.is_finite() {
        let min_el = top_el + params.prior_margin;
        for y in 0..h {
            for x in 0..w {
                if let Some(ray) = cam.unproject_within(DVec2::new(x as f64, y as f64), max_angle) {
                    if ray.dot(up_cam).clamp(-1.0, 1.0).asin() > min_el {
                        seeds.push((x, y));
                    }
                }
            }
        }
    }
    // 4. Flood fill.
    let mut mask = vec![false; w * h];
    let mut stack: Vec<usize> = seeds
        .into_iter()
        .map(|(x, y)| y * w + x)
        .filter(|&i| !barrier[i] && sky_like(input.rgb[i]))
        .collect();
    for &i in &stack {
        mask[i] = true;
    }
    while let Some(i) = stack.pop() {
        let (x, y) = (i % w, i / w);
        let here = input.rgb[i];
        let mut visit = |j: usize| {
            if mask[j] || barrier[j] {
                return;
            }
            let px = input.rgb[j];
            let step = (0..3)
                .map(|k| (px[k] as i32 - here[k] as i32).abs())
                .max()
                .unwrap_or(0);
            if step <= params.max_step && sky_like(px) {
                mask[j] = true;
                stack.push(j);
            }
        };
        if x > 0 {
            visit(i - 1);
        }
        if x + 1 < w {
            visit(i + 1);
        }
        if y > 0 {
            visit(i - w);
        }
        if y + 1 < h {
            visit(i + w);
        }
    }
    mask
}

/// Intersection over union of two masks (1.0 when both are empty).
pub fn iou(a: &[bool], b: &[bool]) -> f64 {
    let inter = a.iter().zip(b).filter(|(x, y)| **x && **y).count();
    let union = a.iter().zip(b).filter(|(x, y)| **x || **y).count();
    if union == 0 {
        1.0
    } else {
        inter as f64 / union as f64
    }
}
