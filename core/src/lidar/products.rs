//! The lidar supervision of one keyframe, shared by the synthetic generator and the ingest of real bags so
//! that both turn the same inputs into the same dataset bytes: a deskewed sweep (lidar frame at the image
//! time) with each point's ring and column, and the cameras' images → per camera the lidar depth image
//! (range × 256, sky = 65535), the lidar normal image (Newell's method on the range image) and the sky mask.

use glam::DVec3;

use super::{images, normals, project, sky};
use crate::dataset::{
    png_gray16, png_gray8, png_rgb, DatasetError, DatasetWriter, NsFrame, Transforms,
};
use crate::geometry::Se3;
use crate::gpu::{Gpu, GpuError};
use crate::rig::RigCamera;

/// One deskewed sweep organised as a spinning lidar's range image.
#[derive(Clone, Copy, Debug)]
pub struct SweepInput<'a> {
    /// Points in the lidar frame at the image time; NaN entries (dropped by deskewing) are ignored.
    pub positions: &'a [DVec3],
    pub ring: &'a [u16],
    pub column: &'a [u16],
    /// Range-image size: beams × columns per revolution.
    pub beams: usize,
    pub columns: usize,
    /// Returns nearer than this (m) are ignored when projecting.
    pub min_range: f64,
    /// The lidar's pose at the image time (only its rotation is used: world "up" for the sky mask).
    pub t_world_lidar: Se3,
}

/// What one camera gets from the sweep.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraProducts {
    /// 16-bit depth image ([`images::encode_depth`]; [`images::SKY_DEPTH`] where the mask says sky).
    pub depth: Vec<u16>,
    /// 8-bit normal image ([`images::encode_normal`]).
    pub normals: Vec<[u8; 3]>,
    /// 255 = sky.
    pub sky: Vec<u8>,
}

/// Depth, normal and sky images of every camera in `cameras` (with its RGB image, row-major) for one sweep.
/// The projection runs on the GPU; the rest on the CPU.
pub async fn keyframe_products(
    gpu: &Gpu,
    sweep: &SweepInput<'_>,
    cameras: &[(&RigCamera, &[[u8; 3]])],
) -> Result<Vec<CameraProducts>, GpuError> {
    let (rimg, nrm) = normals::sweep_normals(
        sweep.positions,
        sweep.beams,
        sweep.columns,
        sweep.ring,
        sweep.column,
    );
    let up_lidar = sweep.t_world_lidar.rot.inverse() * DVec3::Z;
    let mut out = Vec::with_capacity(cameras.len());
    for &(cam, rgb) in cameras {
        let model = &cam.model;
        let t_cam_lidar = cam.t_lidar_cam.inverse();
        let input = project::ProjectionInput {
            camera: model,
            t_cam_points: t_cam_lidar,
            points: sweep.positions,
            near: sweep.min_range as f32,
        };
        let proj = project::project_gpu(gpu, &input).await?;
        let (mut depth, normal_img) =
            images::lidar_images(&proj, sweep.positions, &nrm, &t_cam_lidar);
        let mask = sky::sky_mask(
            &sky::SkyInput {
                camera: model,
                rgb,
                t_cam_lidar,
                points: sweep.positions,
                image: &rimg,
                depth: &depth,
                up_lidar,
            },
            sky::SkyParams::default(),
        );
        for (d, &m) in depth.iter_mut().zip(&mask) {
            if m && *d == 0 {
                *d = images::SKY_DEPTH;
            }
        }
        out.push(CameraProducts {
            depth,
            normals: normal_img,
            sky: mask.iter().map(|&m| if m { 255 } else { 0 }).collect(),
        });
    }
    Ok(out)
}

/// Writes one camera's image of keyframe `k` and its lidar products in the dataset layout
/// (`images/`, `lidar_depth/`, `lidar_normals/`, `sky_mask/` `{camera}/{k:05}.png`) and returns its
/// `transforms.json` frame. Every writer of datasets (generator, bag ingest, importers) goes through here.
pub fn write_camera(
    w: &DatasetWriter,
    cam: &RigCamera,
    k: usize,
    time: f64,
    t_world_cam: &Se3,
    rgb: &[[u8; 3]],
    p: &CameraProducts,
) -> Result<NsFrame, DatasetError> {
    let (cn, m) = (cam.name.as_str(), &cam.model);
    let (wd, ht) = (m.width, m.height);
    let name = format!("{k:05}");
    let image = format!("images/{cn}/{name}.png");
    let depth = format!("lidar_depth/{cn}/{name}.png");
    let normal = format!("lidar_normals/{cn}/{name}.png");
    let sky = format!("sky_mask/{cn}/{name}.png");
    w.write(&image, &png_rgb(wd, ht, rgb))?;
    w.write(&depth, &png_gray16(wd, ht, &p.depth))?;
    w.write(&normal, &png_rgb(wd, ht, &p.normals))?;
    w.write(&sky, &png_gray8(wd, ht, &p.sky))?;
    let mut f = NsFrame::new(image, m, t_world_cam);
    f.depth_file_path = Some(depth);
    f.normal_file_path = Some(normal);
    f.sky_mask_path = Some(sky);
    f.camera = Some(cn.to_string());
    f.keyframe = Some(k);
    f.time = Some(time);
    Ok(f)
}

/// The hold-out rule of our datasets: every keyframe k with k mod 10 = 5 (all its cameras) is a novel view.
pub fn every_tenth_keyframe(f: &NsFrame) -> bool {
    f.keyframe.unwrap_or(0) % 10 == 5
}

/// `transforms.json` of `frames` (as [`write_camera`] made them) with the train/val split `held_out`.
pub fn transforms(frames: Vec<NsFrame>, held_out: impl Fn(&NsFrame) -> bool) -> Transforms {
    let (mut train, mut val) = (Vec::new(), Vec::new());
    for f in &frames {
        if held_out(f) {
            val.push(f.file_path.clone());
        } else {
            train.push(f.file_path.clone());
        }
    }
    Transforms {
        frames,
        depth_unit_scale_factor: Some(1.0 / images::DEPTH_SCALE as f64),
        train_filenames: train,
        val_filenames: val,
    }
}
