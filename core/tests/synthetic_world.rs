//! The synthetic world's sensors against its exact geometry (no GPU needed).

use glam::{DVec2, DVec3};
use silvr_core::lidar::{deskew, normals};
use silvr_core::synthetic::generate::odometry;
use silvr_core::synthetic::sensors::{simulate_sweep, LidarNoise};
use silvr_core::synthetic::world::{Label, World};
use silvr_core::synthetic::Preset;

const EXACT: LidarNoise = LidarNoise {
    range: false,
    dropout: false,
};
const NOISY: LidarNoise = LidarNoise {
    range: true,
    dropout: true,
};

/// With noise off, every lidar return lies on the surface the camera sees through the same direction:
/// the range along the camera ray through the point's projection equals the point's distance (< 1 mm).
#[test]
fn noise_free_lidar_agrees_with_camera_ground_truth() {
    let preset = Preset::ci(4);
    let world = World::generate(preset.world.clone(), preset.seed);
    let k = 7;
    let t = preset.image_time(k);
    let pose_at = |t: f64| preset.t_world_lidar(t);
    // Frozen at the image time: the sweep the cameras saw.
    let sweep = simulate_sweep(
        &world,
        &preset.lidar,
        &pose_at,
        preset.sweep_start(k),
        Some(t),
        EXACT,
        1,
    );
    let t_world_lidar = preset.t_world_lidar(t);
    let mut checked = 0;
    let mut worst: f64 = 0.0;
    for (ci, cam) in preset.rig.cameras.iter().enumerate() {
        let t_world_cam = preset.t_world_cam(ci, t);
        let t_cam_lidar = cam.t_lidar_cam.inverse();
        let max_angle = cam.model.valid_angle();
        for p in &sweep.points {
            let pc = t_cam_lidar.transform_point(p.position);
            let Some(uv) = cam.model.project_within(pc, max_angle) else {
                continue;
            };
            if !cam.model.in_image(uv) {
                continue;
            }
            let ray = cam.model.unproject_within(uv, max_angle).unwrap();
            let d = t_world_cam.transform_vector(ray);
            let Some(hit) = world.scene.cast(t_world_cam.trans, d, 1e4) else {
                panic!("camera ray through a lidar return hit nothing");
            };
            // Occlusion between the camera and the point is legitimate (parallax): skip those.
            if hit.t < pc.length() - 0.01 {
                continue;
            }
            let err = (hit.t - pc.length()).abs();
            worst = worst.max(err);
            checked += 1;
            let _ = t_world_lidar;
        }
    }
    assert!(checked > 1000, "only {checked} points checked");
    assert!(
        worst < 1e-3,
        "worst disagreement {worst} m over {checked} points"
    );
}

/// The raw sweep is motion-distorted; deskewing it with the sampled odometry recovers the ideal sweep
/// (every return expressed in the lidar frame at the image time) to < 1 mm.
#[test]
fn deskewing_reproduces_the_ideal_sweep() {
    let preset = Preset::ci(5);
    let world = World::generate(preset.world.clone(), preset.seed);
    let k = 4;
    let (t0, t_ref) = (preset.sweep_start(k), preset.image_time(k));
    let pose_at = |t: f64| preset.t_world_lidar(t);
    let sweep = simulate_sweep(&world, &preset.lidar, &pose_at, t0, None, EXACT, 2);
    let raw: Vec<DVec3> = sweep.points.iter().map(|p| p.position).collect();
    let times: Vec<f64> = sweep.points.iter().map(|p| p.time).collect();
    let inv_ref = preset.t_world_lidar(t_ref).inverse();
    let ideal: Vec<DVec3> = sweep
        .points
        .iter()
        .map(|p| inv_ref.transform_point(preset.t_world_lidar(p.time).transform_point(p.position)))
        .collect();
    let desk = deskew::deskew(&raw, &times, &odometry(&preset), t_ref).unwrap();
    assert_eq!(desk.dropped, 0);
    let max_err = desk
        .positions
        .iter()
        .zip(&ideal)
        .map(|(a, b)| (*a - *b).length())
        .fold(0.0, f64::max);
    let max_distortion = raw
        .iter()
        .zip(&ideal)
        .map(|(a, b)| (*a - *b).length())
        .fold(0.0, f64::max);
    assert!(
        max_distortion > 0.05,
        "the raw sweep should be visibly distorted, max {max_distortion} m"
    );
    assert!(max_err < 1e-3, "deskew error {max_err} m");
    // A reference time outside the odometry is an error, not a guess.
    assert!(deskew::deskew(&raw, &times, &odometry(&preset), 1e6).is_err());
}

/// Newell normals of a noisy sweep on the road point straight up (median < 3°).
#[test]
fn lidar_normals_on_the_road_are_vertical() {
    let preset = Preset::ci(6);
    let world = World::generate(preset.world.clone(), preset.seed);
    let k = 2;
    let (t0, t_ref) = (preset.sweep_start(k), preset.image_time(k));
    let pose_at = |t: f64| preset.t_world_lidar(t);
    let sweep = simulate_sweep(&world, &preset.lidar, &pose_at, t0, None, NOISY, 3);
    let raw: Vec<DVec3> = sweep.points.iter().map(|p| p.position).collect();
    let times: Vec<f64> = sweep.points.iter().map(|p| p.time).collect();
    let desk = deskew::deskew(&raw, &times, &odometry(&preset), t_ref).unwrap();
    let ring: Vec<u16> = sweep.points.iter().map(|p| p.ring).collect();
    let col: Vec<u16> = sweep.points.iter().map(|p| p.column).collect();
    let (_, n) = normals::sweep_normals(
        &desk.positions,
        preset.lidar.beams as usize,
        preset.lidar.columns as usize,
        &ring,
        &col,
    );
    let rot = preset.t_world_lidar(t_ref).rot;
    let mut errs = Vec::new();
    for (i, p) in sweep.points.iter().enumerate() {
        // Which surface this return came from: re-cast its beam without noise.
        let pose = preset.t_world_lidar(p.time);
        let d = pose.transform_vector(p.position.normalize());
        let hit = world.scene.cast(pose.trans, d, 100.0).unwrap();
        if world.label(&hit) != Label::Road || !n[i].is_finite() {
            continue;
        }
        errs.push((rot * n[i]).angle_between(DVec3::Z).to_degrees());
    }
    errs.sort_by(f64::total_cmp);
    assert!(errs.len() > 300, "{} road normals", errs.len());
    let median = errs[errs.len() / 2];
    assert!(median < 3.0, "median road normal error {median}°");
}

/// Cameras see the sky above the street, and the world's textureless road really is textureless in the
/// rendered image (the failure mode SiLVR targets), while facades are not.
#[test]
fn rendered_images_have_the_intended_texture_contrast() {
    use silvr_core::synthetic::sensors::{render_camera, RenderOptions};
    let preset = Preset::ci(7);
    let world = World::generate(preset.world.clone(), preset.seed);
    let t = preset.image_time(0);
    let f = render_camera(
        &world,
        &preset.rig.cameras[0].model,
        &preset.t_world_cam(0, t),
        RenderOptions {
            supersample: 2,
            noise_std: 0.0,
            seed: 0,
        },
    );
    let (w, h) = (f.width as usize, f.height as usize);
    // Interior pixels of a class (all 8 neighbours share it), so edges blended by anti-aliasing don't count.
    let interior = |i: usize, label: Label| {
        let (x, y) = (i % w, i / w);
        x > 0
            && y > 0
            && x + 1 < w
            && y + 1 < h
            && (-1i64..=1).all(|dy| {
                (-1i64..=1).all(|dx| {
                    f.label[((y as i64 + dy) as usize) * w + (x as i64 + dx) as usize]
                        == label as u8
                })
            })
    };
    // Texture = mean absolute difference between horizontally adjacent interior pixels of a class.
    let spread = |label: Label| {
        let v: Vec<f32> = (0..w * h - 1)
            .filter(|&i| interior(i, label) && interior(i + 1, label))
            .map(|i| (f.rgb[i][1] as f32 - f.rgb[i + 1][1] as f32).abs())
            .collect();
        (v.len(), v.iter().sum::<f32>() / v.len().max(1) as f32)
    };
    let (n_sky, _) = spread(Label::Sky);
    let (n_facade, facade_std) = spread(Label::Facade);
    assert!(
        n_sky > 1000 && n_facade > 1000,
        "sky {n_sky}, facade {n_facade} px"
    );
    // Road pixels away from lane markings: compare a road patch's local contrast with a facade's.
    let (n_white, white_std) = spread(Label::WhiteWall);
    assert!(
        n_white > 500,
        "the white wall should be in view of cam_front at the start ({n_white} px)"
    );
    assert!(white_std < 1.5, "white wall gradient {white_std}");
    assert!(
        facade_std > 5.0 * white_std.max(1.0),
        "facade gradient {facade_std} vs white wall {white_std}"
    );
    // The image is bright where the sky is and the ray points up.
    let max_angle = preset.rig.cameras[0].model.valid_angle();
    let up = preset.rig.cameras[0]
        .model
        .unproject_within(DVec2::new(180.0, 5.0), max_angle)
        .unwrap();
    assert!(preset.t_world_cam(0, t).transform_vector(up).z > 0.3);
}
