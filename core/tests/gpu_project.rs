//! The lidar projection kernel (WGSL, through wgpu — lavapipe where there is no GPU) against its CPU
//! reference, on random inputs, with poisoned output buffers.
#![cfg(not(target_arch = "wasm32"))]

use glam::{DQuat, DVec3};
use silvr_core::camera::{CameraModel, Distortion};
use silvr_core::geometry::Se3;
use silvr_core::gpu::{Gpu, GpuError, GpuOptions, Kernel};
use silvr_core::lidar::project::{self, ProjectionInput, NONE};

mod common;
use common::gpu;

fn cameras() -> Vec<(&'static str, CameraModel)> {
    vec![
        (
            "pinhole",
            CameraModel {
                width: 97,
                height: 61,
                fx: 80.0,
                fy: 82.0,
                cx: 48.3,
                cy: 30.1,
                distortion: Distortion::None,
            },
        ),
        (
            "radtan",
            CameraModel {
                width: 120,
                height: 90,
                fx: 100.0,
                fy: 99.0,
                cx: 61.2,
                cy: 44.7,
                distortion: Distortion::RadTan {
                    k1: -0.28,
                    k2: 0.07,
                    p1: 1e-3,
                    p2: -2e-3,
                    k3: 0.01,
                },
            },
        ),
        (
            "fisheye",
            CameraModel {
                width: 144,
                height: 108,
                fx: 69.8,
                fy: 69.9,
                cx: 71.3,
                cy: 56.1,
                distortion: Distortion::Fisheye {
                    k1: -0.041142,
                    k2: -0.002422,
                    k3: 0.003400,
                    k4: -0.001852,
                },
            },
        ),
    ]
}

#[test]
fn kernel_matches_cpu_reference_on_all_camera_models() {
    let Some(gpu) = gpu() else { return };
    for (name, cam) in cameras() {
        for seed in [1u64, 2, 3] {
            let check = pollster::block_on(project::self_check(&gpu, &cam, seed, 6000)).unwrap();
            assert!(
                check.filled_pixels > 500,
                "{name}: too few pixels filled: {check:?}"
            );
            assert_eq!(check.winner_mismatches, 0, "{name} seed {seed}: {check:?}");
            assert!(check.passed(), "{name} seed {seed}: {check:?}");
        }
    }
}

#[test]
fn nearest_point_wins_and_ties_go_to_the_lowest_index() {
    let Some(gpu) = gpu() else { return };
    let (_, cam) = cameras().remove(0);
    let ray = cam.unproject(glam::DVec2::new(10.0, 20.0)).unwrap();
    // Same pixel: far, near, an exact duplicate of near, and nearer than the near limit.
    let points = vec![ray * 9.0, ray * 4.0, ray * 4.0, ray * 0.05, ray * 6.0];
    let input = ProjectionInput {
        camera: &cam,
        t_cam_points: Se3::IDENTITY,
        points: &points,
        near: 0.1,
    };
    let g = pollster::block_on(project::project_gpu(&gpu, &input)).unwrap();
    let c = project::project_cpu(&input).unwrap();
    let pix = (20 * cam.width + 10) as usize;
    assert_eq!(c.winner[pix], 1);
    assert_eq!(g.winner[pix], 1);
    assert!((g.range[pix] - 4.0).abs() < 1e-5);
    assert_eq!(
        g.filled(),
        1,
        "every other pixel must be cleared, not left poisoned"
    );
    assert_eq!(
        g.point_pixel[3], NONE,
        "a point nearer than `near` is dropped"
    );
    assert!(g.winner.iter().all(|&w| w == NONE || w == 1));
}

#[test]
fn non_finite_points_are_counted_and_skipped() {
    let Some(gpu) = gpu() else { return };
    let (_, cam) = cameras().remove(2);
    let points = vec![
        DVec3::new(f64::NAN, 0.0, 1.0),
        DVec3::new(0.0, f64::INFINITY, 1.0),
        DVec3::new(1e30, 0.0, 1.0),
        DVec3::new(0.1, 0.1, 3.0),
    ];
    let input = ProjectionInput {
        camera: &cam,
        t_cam_points: Se3::IDENTITY,
        points: &points,
        near: 0.0,
    };
    let g = pollster::block_on(project::project_gpu(&gpu, &input)).unwrap();
    let c = project::project_cpu(&input).unwrap();
    assert_eq!(g.skipped_nonfinite, 3);
    assert_eq!(c.skipped_nonfinite, 3);
    assert_eq!(&g.point_pixel[..3], &[NONE; 3]);
    assert_ne!(g.point_pixel[3], NONE);
    assert_eq!(g.winner, c.winner);
}

#[test]
fn transform_is_applied_like_the_reference() {
    let Some(gpu) = gpu() else { return };
    let (_, cam) = cameras().remove(1);
    let t = Se3::new(
        DQuat::from_rotation_y(0.4) * DQuat::from_rotation_x(-0.3),
        DVec3::new(0.5, -0.2, 1.0),
    );
    let points: Vec<DVec3> = project::sample_points(&cam, 11, 4000)
        .into_iter()
        .map(|p| t.inverse().transform_point(p))
        .collect();
    let input = ProjectionInput {
        camera: &cam,
        t_cam_points: t,
        points: &points,
        near: 0.1,
    };
    let g = pollster::block_on(project::project_gpu(&gpu, &input)).unwrap();
    let c = project::project_cpu(&input).unwrap();
    let check = project::compare(&g, &c);
    assert!(check.passed(), "{check:?}");
}

/// More than 65 535 workgroups of 64 points: the dispatch is folded into 2-D and every point still lands.
#[test]
fn folded_dispatch_reaches_every_point() {
    let Some(gpu) = gpu() else { return };
    let cam = CameraModel {
        width: 8,
        height: 8,
        fx: 8.0,
        fy: 8.0,
        // Pixel centres are integers (OpenCV): the optical axis lands on the centre of pixel (3, 3).
        cx: 3.0,
        cy: 3.0,
        distortion: Distortion::None,
    };
    let n = 65_535 * 64 + 1000;
    // Every point in pixel (3, 3); the nearest is the very last one, in the second row of workgroups.
    let mut points = vec![DVec3::new(0.0, 0.0, 5.0); n];
    points[n - 1] = DVec3::new(0.0, 0.0, 2.0);
    let input = ProjectionInput {
        camera: &cam,
        t_cam_points: Se3::IDENTITY,
        points: &points,
        near: 0.0,
    };
    let g = pollster::block_on(project::project_gpu(&gpu, &input)).unwrap();
    let pix = 3 * 8 + 3;
    assert_eq!(g.winner[pix], (n - 1) as u32);
    assert!(g.point_pixel.iter().all(|&p| p == pix as u32));
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let Some(gpu) = gpu() else { return };
    let mut cam = cameras().remove(0).1;
    cam.width = 0;
    let input = ProjectionInput {
        camera: &cam,
        t_cam_points: Se3::IDENTITY,
        points: &[],
        near: 0.0,
    };
    let err = pollster::block_on(project::project_gpu(&gpu, &input)).unwrap_err();
    assert!(matches!(err, GpuError::InvalidInput(_)), "{err}");
    assert!(err.to_string().contains("0x61"), "{err}");

    let too_big = gpu.max_binding_bytes() as usize / 4 + 1;
    let err = gpu.output("huge buffer", too_big).unwrap_err();
    assert!(matches!(err, GpuError::BufferTooLarge { .. }), "{err}");
    assert!(err.to_string().contains("huge buffer"), "{err}");

    let broken = Kernel {
        name: "broken",
        source: "@compute @workgroup_size(64) fn main() { let x: f32 = 1u; }",
        workgroup_size: 64,
    };
    let err = pollster::block_on(gpu.pipeline(&broken, "main")).unwrap_err();
    assert!(matches!(err, GpuError::Kernel { .. }), "{err}");
    assert!(err.to_string().contains("broken"), "{err}");
}

#[test]
fn missing_backend_is_a_clear_error() {
    // Metal/DX12 never exist on Linux; elsewhere ask for no backend at all.
    let backends = if cfg!(target_os = "linux") {
        wgpu_backends_metal_dx12()
    } else {
        return;
    };
    let err = pollster::block_on(Gpu::new(GpuOptions {
        backends: Some(backends),
        ..Default::default()
    }))
    .unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, GpuError::NoAdapter { .. }), "{msg}");
    assert!(msg.contains("mesa-vulkan-drivers"), "{msg}");
}

fn wgpu_backends_metal_dx12() -> silvr_core::gpu::Backends {
    silvr_core::gpu::Backends::METAL | silvr_core::gpu::Backends::DX12
}
