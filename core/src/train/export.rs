//! What a trained field gives back: renders of whole views (RGB, expected depth, normals) with PSNR / SSIM
//! on held-out views, and the point cloud of SiLVR's exporter (expected depth along training rays,
//! accumulation ≥ 0.98, rendered colour and normal) in the dataset's metric frame.

use glam::{DVec3, Vec3};
use rand::{Rng, SeedableRng};

use super::cpu::{RenderedRay, TrainRay};
use super::Trainer;
use crate::eval::image::{psnr_rgb8, ssim_rgb8};
use crate::gpu::GpuError;
use crate::lidar::images::{encode_depth, encode_normal};
use crate::pointcloud::PointCloud;

/// A rendered view.
pub struct ViewRender {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<[u8; 3]>,
    /// Expected depth in metres (range along the ray); 0 where the camera has no ray.
    pub depth_m: Vec<f32>,
    pub accumulation: Vec<f32>,
    /// Each ray's termination spread in metres ([`depth_spread`](super::cpu::depth_spread)).
    pub spread_m: Vec<f32>,
    /// World-frame unit normals (zero where none).
    pub normals: Vec<[f32; 3]>,
    /// Pixels the camera has a ray for.
    pub valid: Vec<bool>,
}

/// Image quality of one held-out view.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ViewScore {
    pub name: String,
    pub psnr: f64,
    pub ssim: f64,
}

/// Which rendered depth places an exported point on its ray.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ExportDepth {
    /// Σwt / Σw: SiLVR's exporter (its renderer replaces nerfacto's depth with the expected depth).
    #[default]
    Expected,
    /// Where the cumulative weight reaches ½: nerfacto's own depth, and so `ns-export pointcloud`'s.
    Median,
}

impl std::str::FromStr for ExportDepth {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "expected" => Ok(Self::Expected),
            "median" => Ok(Self::Median),
            _ => Err(format!("{s:?}: expected `expected` or `median`")),
        }
    }
}

impl ExportDepth {
    fn of(self, r: &RenderedRay) -> f32 {
        match self {
            Self::Expected => r.expected_depth,
            Self::Median => r.median_depth,
        }
    }
}

/// The exported point's field holding its ray's [`depth_spread`](super::cpu::depth_spread) in metres,
/// which the uncertainty read-out folds into each σ.
pub const DEPTH_SPREAD_FIELD: &str = "depth_spread_m";

/// Minimum accumulation of an exported point (SiLVR / nerfstudio).
pub const EXPORT_MIN_ACCUMULATION: f32 = 0.98;

fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

/// PSNR and SSIM of a `w`×`h` render against its photo (row-major RGB), over the `valid` pixels.
pub fn score_pixels(
    w: u32,
    h: u32,
    render: &[[u8; 3]],
    photo: &[[u8; 3]],
    valid: &[bool],
) -> Result<(f64, f64), crate::eval::image::ImageMetricError> {
    let mk = |px: &[[u8; 3]]| {
        image::RgbImage::from_fn(w, h, |x, y| image::Rgb(px[(y * w + x) as usize]))
    };
    let (a, b) = (mk(render), mk(photo));
    Ok((
        psnr_rgb8(&a, &b, Some(valid))?,
        ssim_rgb8(&a, &b, Some(valid))?,
    ))
}

impl Trainer {
    /// Rays of every pixel of image `i` (held-out images use the mean appearance).
    pub fn view_rays(&self, i: usize) -> (Vec<TrainRay>, Vec<bool>) {
        let im = &self.data.images[i];
        let mut rays = Vec::with_capacity((im.width * im.height) as usize);
        let mut valid = Vec::with_capacity(rays.capacity());
        for y in 0..im.height {
            for x in 0..im.width {
                match self.data.ray(i, x, y) {
                    Some((o, d)) => {
                        rays.push(TrainRay {
                            origin: o,
                            dir: d,
                            appearance: im.appearance.unwrap_or(u32::MAX),
                        });
                        valid.push(true);
                    }
                    None => {
                        rays.push(TrainRay {
                            origin: o_or_zero(&self.data.images[i].origin),
                            dir: [0.0, 0.0, 1.0],
                            appearance: u32::MAX,
                        });
                        valid.push(false);
                    }
                }
            }
        }
        (rays, valid)
    }

    /// Renders image `i`'s view (with density-gradient normals on request: they cost six more density
    /// evaluations per sample).
    pub async fn render_view(&mut self, i: usize, normals: bool) -> Result<ViewRender, GpuError> {
        let (rays, valid) = self.view_rays(i);
        let out = self.render(&rays, normals).await?;
        Ok(self.view_from(i, valid, &out))
    }

    /// Image `i`'s view from its rendered rays (in [`Trainer::view_rays`] order).
    pub fn view_from(&self, i: usize, valid: Vec<bool>, out: &[RenderedRay]) -> ViewRender {
        let scale = self.data.frame.scale as f32;
        let im = &self.data.images[i];
        let mut v = ViewRender {
            width: im.width,
            height: im.height,
            rgb: Vec::with_capacity(out.len()),
            depth_m: Vec::with_capacity(out.len()),
            accumulation: Vec::with_capacity(out.len()),
            spread_m: Vec::with_capacity(out.len()),
            normals: Vec::with_capacity(out.len()),
            valid,
        };
        for (o, &ok) in out.iter().zip(&v.valid) {
            if ok {
                v.rgb.push(o.out.rgb.map(to_u8));
                v.depth_m.push(o.expected_depth / scale);
                v.accumulation.push(o.out.accumulation);
                v.spread_m.push(o.depth_spread / scale);
                v.normals.push(o.out.normal);
            } else {
                v.rgb.push([0; 3]);
                v.depth_m.push(0.0);
                v.accumulation.push(0.0);
                v.spread_m.push(0.0);
                v.normals.push([0.0; 3]);
            }
        }
        v
    }

    /// PSNR and SSIM of image `i`'s render against its photo, over the pixels the camera has rays for.
    pub fn score_view(&self, i: usize, v: &ViewRender) -> Result<ViewScore, GpuError> {
        let im = &self.data.images[i];
        let (psnr, ssim) = score_pixels(im.width, im.height, &v.rgb, &im.rgb, &v.valid)
            .map_err(|e| GpuError::InvalidInput(format!("scoring {}: {e}", im.name)))?;
        Ok(ViewScore {
            name: im.name.clone(),
            psnr,
            ssim,
        })
    }

    /// PNG renders of a view: RGB, depth (lidar encoding, metres × 256) and normals (lidar encoding, in
    /// the camera frame).
    pub fn view_pngs(&self, i: usize, v: &ViewRender) -> (Vec<u8>, Vec<u8>, Vec<u8>) {
        let im = &self.data.images[i];
        let rgb = crate::dataset::png_rgb(v.width, v.height, &v.rgb);
        let depth: Vec<u16> = v.depth_m.iter().map(|&d| encode_depth(d)).collect();
        let r_t = im.rotation.transpose();
        let normals: Vec<[u8; 3]> = v
            .normals
            .iter()
            .map(|n| encode_normal(r_t * DVec3::new(n[0] as f64, n[1] as f64, n[2] as f64)))
            .collect();
        (
            rgb,
            crate::dataset::png_gray16(v.width, v.height, &depth),
            crate::dataset::png_rgb(v.width, v.height, &normals),
        )
    }

    /// SiLVR's point export: `rays` random training pixels (seeded), kept where the accumulation is at least
    /// [`EXPORT_MIN_ACCUMULATION`], placed at the `depth` along the ray; positions in metres in the dataset
    /// frame, rendered colour and normal, and the accumulation as a scalar field.
    /// Without `normals` the cloud has none (they cost six more density evaluations per sample).
    /// nerfstudio also crops to the [−1, 1]³ cube of its pose normalisation; we do not: on a walked
    /// trajectory that cube holds little of the street (measured on the ci world: completeness 4.5 m →
    /// 23 m for both fields).
    pub async fn export_points(
        &mut self,
        rays: usize,
        seed: u64,
        normals: bool,
        depth: ExportDepth,
    ) -> Result<PointCloud, GpuError> {
        let batch = self.export_rays(rays, seed);
        let out = self.render(&batch, normals).await?;
        let mut cloud = points_from(&self.data.frame, &batch, &out, depth);
        if !normals {
            cloud.normals = None;
        }
        Ok(cloud)
    }

    /// The export's rays: `rays` random training pixels drawn from `seed`.
    pub fn export_rays(&self, rays: usize, seed: u64) -> Vec<TrainRay> {
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed);
        let mut batch = Vec::with_capacity(rays);
        let mut tries = 0;
        while batch.len() < rays && tries < rays * 20 {
            tries += 1;
            let i = self.data.train[rng.random_range(0..self.data.train.len())];
            let im = &self.data.images[i];
            let (x, y) = (
                rng.random_range(0..im.width),
                rng.random_range(0..im.height),
            );
            if let Some((o, d)) = self.data.ray(i, x, y) {
                batch.push(TrainRay {
                    origin: o,
                    dir: d,
                    appearance: im.appearance.unwrap_or(u32::MAX),
                });
            }
        }
        batch
    }
}

fn o_or_zero(o: &DVec3) -> [f32; 3] {
    o.as_vec3().to_array()
}

/// Points of rendered rays with enough accumulation, at `depth` along the ray, in metres.
pub fn points_from(
    frame: &super::data::SceneFrame,
    rays: &[TrainRay],
    out: &[RenderedRay],
    depth: ExportDepth,
) -> PointCloud {
    let mut cloud = PointCloud::new();
    let mut colors = Vec::new();
    let mut normals = Vec::new();
    let mut acc = Vec::new();
    let mut spread = Vec::new();
    for (ray, o) in rays.iter().zip(out) {
        let t = depth.of(o);
        if o.out.accumulation < EXPORT_MIN_ACCUMULATION || !t.is_finite() {
            continue;
        }
        let p = Vec3::from(ray.origin) + Vec3::from(ray.dir) * t;
        cloud.positions.push(frame.to_metric(p.as_dvec3()));
        colors.push(o.out.rgb.map(to_u8));
        normals.push(Vec3::from(o.out.normal));
        acc.push(o.out.accumulation);
        spread.push((o.depth_spread as f64 / frame.scale) as f32);
    }
    cloud.colors = Some(colors);
    cloud.normals = Some(normals);
    cloud.set_scalar("accumulation", acc);
    cloud.set_scalar(DEPTH_SPREAD_FIELD, spread);
    cloud
}
