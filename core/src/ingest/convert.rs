//! Dataset-level conversions between our layout and the folder formats users have:
//! - [`import_nerfstudio`]: a nerfstudio / instant-ngp / SiLVR `transforms.json` (global or per-frame
//!   intrinsics, `depth_file_path` in any unit and as z-depth or range, `normal_file_path`,
//!   `sky_mask_path`) → our dataset, with depth converted to our range × 256 encoding;
//! - [`export_colmap`]: our dataset → a COLMAP text model (cameras, posed images; no 3-D points), so COLMAP,
//!   nerfstudio's `colmap` parser or evo can read the poses; [`import_colmap`] the other way (camera-only).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::DVec2;
use serde::Serialize;

use super::colmap::{self, ColmapImage, ColmapModel};
use crate::camera::CameraModel;
use crate::dataset::{
    self, png_gray16, png_gray8, png_rgb, DatasetError, DatasetWriter, NsFrame, Transforms,
};
use crate::lidar::images;

/// Why a conversion failed; every message names the file.
#[derive(Debug, thiserror::Error)]
pub enum ConvertError {
    #[error("{file}: {reason}")]
    Invalid { file: String, reason: String },
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error(transparent)]
    Colmap(#[from] colmap::ColmapError),
}

fn invalid(file: &Path, reason: impl Into<String>) -> ConvertError {
    ConvertError::Invalid {
        file: file.display().to_string(),
        reason: reason.into(),
    }
}

/// What a depth PNG's values mean in a foreign `transforms.json`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct DepthEncoding {
    /// Metres per PNG unit (nerfstudio's default 1e-3; SiLVR / Spires 1/256).
    pub scale: f64,
    /// Distance along the optical axis (nerfstudio, Spires) rather than along the ray.
    pub z_depth: bool,
}

/// What an import wrote.
#[derive(Clone, Debug, Serialize)]
pub struct ImportSummary {
    pub path: PathBuf,
    pub images: usize,
    pub with_depth: usize,
    pub with_normals: usize,
    pub with_sky: usize,
    pub depth: DepthEncoding,
    /// Frames left out, with why.
    pub skipped: Vec<String>,
}

/// Imports `transforms` (a `transforms.json`; paths inside are relative to its folder) into `out`. The depth
/// encoding defaults to the file's `depth_unit_scale_factor` (else nerfstudio's 1e-3) and z-depth.
pub fn import_nerfstudio(
    transforms: &Path,
    out: &Path,
    overwrite: bool,
    depth: Option<DepthEncoding>,
) -> Result<ImportSummary, ConvertError> {
    let root = transforms.parent().unwrap_or(Path::new("."));
    let (frames, train, val) = dataset::read_frames(transforms)?;
    if frames.is_empty() {
        return Err(invalid(transforms, "no frames"));
    }
    let text =
        std::fs::read_to_string(transforms).map_err(|e| invalid(transforms, e.to_string()))?;
    let top: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| invalid(transforms, e.to_string()))?;
    let depth = depth.unwrap_or(DepthEncoding {
        scale: top
            .get("depth_unit_scale_factor")
            .and_then(serde_json::Value::as_f64)
            .unwrap_or(1e-3),
        z_depth: true,
    });
    if !(depth.scale.is_finite() && depth.scale > 0.0) {
        return Err(invalid(
            transforms,
            format!("depth scale {} must be positive", depth.scale),
        ));
    }
    let w = DatasetWriter::create(out, overwrite)?;
    let mut out_frames = Vec::with_capacity(frames.len());
    let (mut n_depth, mut n_normals, mut n_sky) = (0, 0, 0);
    let mut skipped = Vec::new();
    // Ray directions per distinct camera model, for z-depth → range.
    let mut dirs: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    let (mut new_train, mut new_val) = (Vec::new(), Vec::new());
    for (i, f) in frames.iter().enumerate() {
        let (model, t_world_cam) = f.camera(transforms)?;
        let cam = f.camera.clone().unwrap_or_else(|| "cam0".into());
        if cam.is_empty() || cam.contains(['/', '\\']) || cam.starts_with('.') {
            return Err(invalid(
                transforms,
                format!("frame {i}: camera name {cam:?} is not a folder name"),
            ));
        }
        let name = format!("{i:05}");
        let src = root.join(&f.file_path);
        if !src.exists() {
            // instant-ngp captures often list frames whose photos were culled: skip them, as training does.
            skipped.push(format!("{}: image file missing", f.file_path));
            continue;
        }
        let img = image::open(&src)
            .map_err(|e| invalid(&src, e.to_string()))?
            .to_rgb8();
        if (img.width(), img.height()) != (model.width, model.height) {
            return Err(invalid(
                &src,
                format!(
                    "image is {}x{}, the frame says {}x{}",
                    img.width(),
                    img.height(),
                    model.width,
                    model.height
                ),
            ));
        }
        let px: Vec<[u8; 3]> = img.pixels().map(|p| p.0).collect();
        let image_rel = format!("images/{cam}/{name}.png");
        w.write(&image_rel, &png_rgb(model.width, model.height, &px))?;
        let mut nf = NsFrame::new(image_rel.clone(), &model, &t_world_cam);
        nf.camera = Some(cam.clone());
        nf.keyframe = Some(i);
        nf.time = f.time;
        if let Some(d) = &f.depth_file_path {
            let p = root.join(d);
            let (dw, dh, values) = read_depth(&p)?;
            if (dw, dh) != (model.width, model.height) {
                return Err(invalid(
                    &p,
                    format!(
                        "depth is {dw}x{dh}, the image {}x{}",
                        model.width, model.height
                    ),
                ));
            }
            let key = format!("{model:?}");
            let cos = dirs.entry(key).or_insert_with(|| axis_cosines(&model));
            let ours: Vec<u16> = values
                .iter()
                .zip(cos.iter())
                .map(|(&v, &c)| {
                    if v <= 0.0 || !v.is_finite() || c.is_nan() {
                        return 0;
                    }
                    let metres = v * depth.scale;
                    let range = if depth.z_depth { metres / c } else { metres };
                    images::encode_depth(range as f32)
                })
                .collect();
            let rel = format!("lidar_depth/{cam}/{name}.png");
            w.write(&rel, &png_gray16(model.width, model.height, &ours))?;
            nf.depth_file_path = Some(rel);
            n_depth += 1;
        }
        if let Some(n) = &f.normal_file_path {
            let p = root.join(n);
            let (nw, nh, px) = dataset::read_rgb(&p)?;
            let rel = format!("lidar_normals/{cam}/{name}.png");
            w.write(&rel, &png_rgb(nw, nh, &px))?;
            nf.normal_file_path = Some(rel);
            n_normals += 1;
        }
        if let Some(s) = &f.sky_mask_path {
            let p = root.join(s);
            let (sw, sh, px) = dataset::read_gray8(&p)?;
            let rel = format!("sky_mask/{cam}/{name}.png");
            let mask: Vec<u8> = px.iter().map(|&v| if v > 127 { 255 } else { 0 }).collect();
            w.write(&rel, &png_gray8(sw, sh, &mask))?;
            nf.sky_mask_path = Some(rel);
            n_sky += 1;
        }
        // Keep the source's split; without one, hold out every tenth image like our own datasets.
        let held_out = if train.is_empty() && val.is_empty() {
            i % 10 == 5
        } else {
            val.iter().any(|v| v == &f.file_path)
        };
        if held_out {
            new_val.push(image_rel);
        } else {
            new_train.push(image_rel);
        }
        out_frames.push(nf);
    }
    let summary = ImportSummary {
        path: out.to_path_buf(),
        images: out_frames.len(),
        with_depth: n_depth,
        with_normals: n_normals,
        with_sky: n_sky,
        depth,
        skipped,
    };
    if summary.images == 0 {
        return Err(invalid(
            transforms,
            format!("no frame has its image: {:?}", summary.skipped),
        ));
    }
    let t = Transforms {
        frames: out_frames,
        depth_unit_scale_factor: Some(1.0 / images::DEPTH_SCALE as f64),
        train_filenames: new_train,
        val_filenames: new_val,
    };
    w.write_json("transforms.json", &t)?;
    let manifest = serde_json::json!({
        "layout_version": dataset::LAYOUT_VERSION,
        "generator": "silvr-import-nerfstudio 1",
        "source": transforms.display().to_string(),
        "summary": &summary,
    });
    w.write_json("manifest.json", &manifest)?;
    let path = w.commit()?;
    Ok(ImportSummary { path, ..summary })
}

/// A depth PNG (8- or 16-bit grey) as numbers.
fn read_depth(p: &Path) -> Result<(u32, u32, Vec<f64>), ConvertError> {
    let img = image::open(p).map_err(|e| invalid(p, format!("not a readable depth image: {e}")))?;
    let (w, h) = (img.width(), img.height());
    let v = match img {
        image::DynamicImage::ImageLuma16(b) => b.into_raw().into_iter().map(f64::from).collect(),
        image::DynamicImage::ImageLuma8(b) => b.into_raw().into_iter().map(f64::from).collect(),
        other => {
            return Err(invalid(
                p,
                format!(
                    "depth must be a single-channel image, found {:?}",
                    other.color()
                ),
            ))
        }
    };
    Ok((w, h, v))
}

/// Per pixel, the cosine between its ray and the optical axis (NaN where the pixel has no ray).
fn axis_cosines(m: &CameraModel) -> Vec<f64> {
    let mut v = Vec::with_capacity((m.width * m.height) as usize);
    for y in 0..m.height {
        for x in 0..m.width {
            v.push(
                m.unproject(DVec2::new(x as f64, y as f64))
                    .map_or(f64::NAN, |d| d.normalize().z),
            );
        }
    }
    v
}

/// Imports a COLMAP text model (`model` holding cameras.txt, images.txt[, points3D.txt]) with its photos
/// (`images`, the folder COLMAP's image names are relative to) as a camera-only dataset: the poses in
/// COLMAP's frame and scale, every tenth image held out. With `points3D.txt`, its points are written to
/// `colmap_points.ply` (colour and reprojection error). Images missing on disk are skipped and listed.
pub fn import_colmap(
    model: &Path,
    images: &Path,
    out: &Path,
    overwrite: bool,
) -> Result<ImportSummary, ConvertError> {
    let m = colmap::read_model(model)?;
    if m.images.is_empty() {
        return Err(invalid(&model.join("images.txt"), "no images"));
    }
    let w = DatasetWriter::create(out, overwrite)?;
    let mut frames = Vec::new();
    let (mut train, mut val, mut skipped) = (Vec::new(), Vec::new(), Vec::new());
    let mut sorted: Vec<&ColmapImage> = m.images.iter().collect();
    sorted.sort_by(|a, b| a.name.cmp(&b.name));
    for (i, img) in sorted.into_iter().enumerate() {
        let cam = m
            .cameras
            .get(&img.camera_id)
            .expect("read_model checks camera ids");
        let src = images.join(&img.name);
        if !src.exists() {
            skipped.push(format!("{}: image file missing", img.name));
            continue;
        }
        let rgb = image::open(&src)
            .map_err(|e| invalid(&src, e.to_string()))?
            .to_rgb8();
        if (rgb.width(), rgb.height()) != (cam.width, cam.height) {
            return Err(invalid(
                &src,
                format!(
                    "image is {}x{}, camera {} says {}x{}",
                    rgb.width(),
                    rgb.height(),
                    img.camera_id,
                    cam.width,
                    cam.height
                ),
            ));
        }
        let px: Vec<[u8; 3]> = rgb.pixels().map(|p| p.0).collect();
        let cam_name = format!("camera{}", img.camera_id);
        let rel = format!("images/{cam_name}/{i:05}.png");
        w.write(&rel, &png_rgb(cam.width, cam.height, &px))?;
        let mut f = NsFrame::new(rel.clone(), cam, &img.t_world_cam());
        f.camera = Some(cam_name);
        f.keyframe = Some(i);
        if i % 10 == 5 {
            val.push(rel);
        } else {
            train.push(rel);
        }
        frames.push(f);
    }
    if frames.is_empty() {
        return Err(invalid(
            images,
            format!("none of the model's images is here: {skipped:?}"),
        ));
    }
    if !m.points.is_empty() {
        let ply = crate::pointcloud::write_ply_bytes(&m.point_cloud())
            .map_err(|e| invalid(&model.join("points3D.txt"), e.to_string()))?;
        w.write("colmap_points.ply", &ply)?;
    }
    let summary = ImportSummary {
        path: out.to_path_buf(),
        images: frames.len(),
        with_depth: 0,
        with_normals: 0,
        with_sky: 0,
        depth: DepthEncoding {
            scale: 1.0 / images::DEPTH_SCALE as f64,
            z_depth: false,
        },
        skipped,
    };
    let t = Transforms {
        frames,
        depth_unit_scale_factor: Some(1.0 / images::DEPTH_SCALE as f64),
        train_filenames: train,
        val_filenames: val,
    };
    w.write_json("transforms.json", &t)?;
    let manifest = serde_json::json!({
        "layout_version": dataset::LAYOUT_VERSION,
        "generator": "silvr-import-colmap 1",
        "source": model.display().to_string(),
        "images": images.display().to_string(),
        "summary": &summary,
    });
    w.write_json("manifest.json", &manifest)?;
    let path = w.commit()?;
    Ok(ImportSummary { path, ..summary })
}

/// Writes a COLMAP text model of `dataset` (its `transforms.json`) into `out`: one camera per distinct
/// intrinsics, one image per frame named by its path in the dataset, no 3-D points.
pub fn export_colmap(dataset: &Path, out: &Path) -> Result<usize, ConvertError> {
    let tpath = if dataset.is_dir() {
        dataset.join("transforms.json")
    } else {
        dataset.to_path_buf()
    };
    let t = Transforms::read(&tpath)?;
    let mut cameras: BTreeMap<u32, CameraModel> = BTreeMap::new();
    let mut images = Vec::with_capacity(t.frames.len());
    for (i, f) in t.frames.iter().enumerate() {
        let (model, t_world_cam) = f.camera(&tpath)?;
        let camera_id = match cameras.iter().find(|(_, m)| **m == model) {
            Some((id, _)) => *id,
            None => {
                let id = cameras.len() as u32 + 1;
                cameras.insert(id, model);
                id
            }
        };
        if f.file_path.chars().any(char::is_whitespace) {
            return Err(invalid(
                &tpath,
                format!(
                    "frame {i}: COLMAP names cannot hold spaces: {:?}",
                    f.file_path
                ),
            ));
        }
        images.push(ColmapImage {
            id: i as u32 + 1,
            camera_id,
            name: f.file_path.clone(),
            t_cam_world: t_world_cam.inverse(),
            points2d: Vec::new(),
        });
    }
    let n = images.len();
    colmap::write_model(
        out,
        &ColmapModel {
            cameras,
            images,
            points: Vec::new(),
        },
    )?;
    Ok(n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Distortion;
    use crate::geometry::Se3;
    use glam::{DQuat, DVec3};

    /// A foreign single-camera transforms.json with mm z-depth, imported: our range depth must match the
    /// geometry (a plane at z = 4 m), the poses must survive, and COLMAP export must read back.
    #[test]
    fn nerfstudio_import_converts_depth_and_colmap_export_reads_back() {
        let tmp = tempfile::tempdir().unwrap();
        let src = tmp.path().join("src");
        std::fs::create_dir_all(src.join("images")).unwrap();
        std::fs::create_dir_all(src.join("depth")).unwrap();
        let model = CameraModel {
            width: 40,
            height: 30,
            fx: 30.0,
            fy: 31.0,
            cx: 19.5,
            cy: 14.5,
            distortion: Distortion::RadTan {
                k1: -0.05,
                k2: 0.01,
                p1: 0.001,
                p2: 0.0,
                k3: 0.0,
            },
        };
        let mut frames = Vec::new();
        for i in 0..3 {
            let px: Vec<[u8; 3]> = (0..40 * 30)
                .map(|k| [(k % 251) as u8, i as u8 * 40, 7])
                .collect();
            std::fs::write(src.join(format!("images/{i}.png")), png_rgb(40, 30, &px)).unwrap();
            // 4 m along the optical axis everywhere, in millimetres.
            std::fs::write(
                src.join(format!("depth/{i}.png")),
                png_gray16(40, 30, &vec![4000u16; 1200]),
            )
            .unwrap();
            let pose = Se3::new(
                DQuat::from_rotation_y(0.2 * i as f64),
                DVec3::new(i as f64, 0.5, -1.0),
            );
            let f = NsFrame::new(format!("images/{i}.png"), &model, &pose);
            let mut v = serde_json::to_value(&f).unwrap();
            let o = v.as_object_mut().unwrap();
            // Intrinsics at the top level, as nerfstudio writes single-camera files.
            for k in dataset::SHARED_INTRINSICS {
                o.remove(k);
            }
            o.insert("depth_file_path".into(), format!("depth/{i}.png").into());
            frames.push(v);
        }
        let top = NsFrame::new(String::new(), &model, &Se3::IDENTITY);
        let mut t = serde_json::to_value(&top).unwrap();
        t.as_object_mut()
            .unwrap()
            .insert("frames".into(), frames.into());
        t.as_object_mut()
            .unwrap()
            .insert("depth_unit_scale_factor".into(), 0.001.into());
        std::fs::write(
            src.join("transforms.json"),
            serde_json::to_string(&t).unwrap(),
        )
        .unwrap();

        let out = tmp.path().join("ours");
        let s = import_nerfstudio(&src.join("transforms.json"), &out, false, None).unwrap();
        assert_eq!((s.images, s.with_depth), (3, 3));
        let ours = Transforms::read(&out.join("transforms.json")).unwrap();
        let (m, pose) = ours.frames[2].camera(&out.join("transforms.json")).unwrap();
        assert_eq!(m, model);
        let want = Se3::new(DQuat::from_rotation_y(0.4), DVec3::new(2.0, 0.5, -1.0));
        assert!(pose.distance_to(&want) < 1e-9 && pose.angle_to(&want) < 1e-9);
        let (_, _, d) =
            dataset::read_png16(&out.join(ours.frames[0].depth_file_path.as_ref().unwrap()))
                .unwrap();
        let cos = axis_cosines(&model);
        for (pix, (&v, &c)) in d.iter().zip(&cos).enumerate() {
            let want = images::encode_depth((4.0 / c) as f32);
            assert!(
                (v as i32 - want as i32).abs() <= 1,
                "pixel {pix}: {v} vs {want}"
            );
        }
        // The corner ray is longer than the axis one.
        assert!(
            d[0] > d[15 * 40 + 20] + 10,
            "{} vs {}",
            d[0],
            d[15 * 40 + 20]
        );

        let n = export_colmap(&out, &tmp.path().join("colmap")).unwrap();
        assert_eq!(n, 3);
        let back = colmap::read_model(&tmp.path().join("colmap")).unwrap();
        assert_eq!(back.cameras.len(), 1);
        assert_eq!(back.cameras[&1], model);
        let p = back.images[2].t_world_cam();
        assert!(p.distance_to(&want) < 1e-9 && p.angle_to(&want) < 1e-9);
        // ... and that model with the dataset's images is a dataset again.
        let again = import_colmap(
            &tmp.path().join("colmap"),
            &out,
            &tmp.path().join("again"),
            false,
        )
        .unwrap();
        assert_eq!(again.images, 3);
        let t2 = Transforms::read(&tmp.path().join("again/transforms.json")).unwrap();
        let (m2, p2) = t2.frames[2]
            .camera(&tmp.path().join("again/transforms.json"))
            .unwrap();
        assert_eq!(m2, model);
        assert!(p2.distance_to(&want) < 1e-9 && p2.angle_to(&want) < 1e-9);

        // Errors name the file; nothing is left behind.
        std::fs::write(
            src.join("depth/1.png"),
            png_gray16(20, 30, &vec![1u16; 600]),
        )
        .unwrap();
        let e = import_nerfstudio(
            &src.join("transforms.json"),
            &tmp.path().join("bad"),
            false,
            None,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("depth/1.png") && e.contains("20x30"), "{e}");
        assert!(!tmp.path().join("bad").exists());
    }
}
