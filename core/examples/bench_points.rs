//! Frame time of the studio's two point draws side by side, natively (lavapipe where there is no GPU):
//! the compute rasteriser and the instanced quads, on the same cloud, camera and target, for BENCHMARKS.md.
//!
//! ```text
//! cargo run --release -p silvr-core --example bench_points -- [POINTS ...] [--frames N] [--size PX]
//! ```
//! Defaults: 1000000 10000000 points, 5 frames, 2-px squares, 1100 × 900 px. The cloud is
//! `scripts/bench-studio.mjs`'s street (200 m of ground and two facades, RGB and `log_std_combined`, the
//! same generator), seen whole by the studio's fitted camera; each frame is drawn and waited for on the
//! device before the next (one warm-up frame first). Prints one JSON line per cloud and draw.

use std::time::Instant;

use glam::DVec3;
use silvr_core::gpu::{wgpu, Gpu, GpuOptions};
use silvr_core::pointcloud::PointCloud;
use silvr_core::viewer::{Colouring, Frame, LayerDraw, PointRenderer, Raster, ViewCloud};

const W: u32 = 1100;
const H: u32 = 900;

/// `bench-studio.mjs`'s street: the same linear congruential generator and layout.
fn street(n: usize) -> PointCloud {
    let mut seed: u32 = 12345;
    let mut rnd = || {
        seed = seed.wrapping_mul(1_103_515_245).wrapping_add(12345);
        seed as f64 / 4_294_967_296.0
    };
    let mut c = PointCloud::new();
    let mut values = Vec::with_capacity(n);
    for _ in 0..n {
        let kind = rnd();
        let x = rnd() * 200.0 - 100.0;
        let (y, z) = if kind < 0.5 {
            (rnd() * 16.0 - 8.0, 0.0)
        } else {
            (if rnd() < 0.5 { -8.0 } else { 8.0 }, rnd() * 12.0)
        };
        let r = (80.0 + 120.0 * rnd()) as u8;
        c.push_colored(
            DVec3::new(x as f32 as f64, y as f32 as f64, z as f32 as f64),
            [r, (90.0 + 100.0 * (z / 12.0)) as u8, 100],
        );
        values.push((-2.5 + 0.02 * x.abs() + 0.3 * rnd()) as f32);
    }
    c.set_scalar("log_std_combined", values);
    c
}

fn main() {
    let mut counts = Vec::new();
    let (mut frames, mut size) = (5usize, 2.0f32);
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--frames" => {
                frames = args
                    .next()
                    .and_then(|v| v.parse().ok())
                    .expect("--frames N")
            }
            "--size" => size = args.next().and_then(|v| v.parse().ok()).expect("--size PX"),
            n => counts.push(n.parse::<usize>().expect("a point count")),
        }
    }
    if counts.is_empty() {
        counts = vec![1_000_000, 10_000_000];
    }
    let gpu = pollster::block_on(Gpu::new(GpuOptions::default())).expect("a WebGPU adapter");
    let adapter = gpu.report().name.clone();
    let format = wgpu::TextureFormat::Rgba8Unorm;
    let r = pollster::block_on(PointRenderer::new(&gpu, format)).expect("the point view");
    let target = gpu.device.create_texture(&wgpu::TextureDescriptor {
        label: Some("bench target"),
        size: wgpu::Extent3d {
            width: W,
            height: H,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
        view_formats: &[],
    });
    let view = target.create_view(&Default::default());
    let targets = r.targets(&gpu, W, H);
    for n in counts {
        let cloud = ViewCloud::from_cloud(&street(n), ViewCloud::MAX_POINTS);
        let layer = r.upload(&gpu, &cloud).expect("upload");
        // The studio's fitted camera: looking at the centre from the south-west, above.
        let centre = (cloud.fit_min + cloud.fit_max) * 0.5;
        let radius = 0.5 * (cloud.fit_max - cloud.fit_min).length();
        let eye = centre + DVec3::new(-0.6, -0.8, 0.5).normalize() * radius * 1.6;
        let frame = Frame {
            reference: centre,
            view_proj: Frame::look_at(
                eye,
                centre,
                50f64.to_radians(),
                (radius * 0.01, radius * 10.0),
                (W, H),
                centre,
            ),
            width: W,
            height: H,
            point_size: size,
            round: false,
            background: [0.0; 3],
        };
        let draws = [LayerDraw {
            layer: &layer,
            colouring: Colouring::Rgb,
            filter: None,
        }];
        for raster in [Raster::Compute, Raster::Quads] {
            let mut times = Vec::new();
            for k in 0..=frames {
                let start = Instant::now();
                let used = r.render(&gpu, &view, &targets, &frame, &draws, raster);
                assert_eq!(used, raster);
                gpu.device
                    .poll(wgpu::PollType::wait_indefinitely())
                    .expect("the frame finishes");
                if k > 0 {
                    times.push(start.elapsed().as_secs_f64() * 1e3);
                }
            }
            times.sort_by(f64::total_cmp);
            println!(
                "{{\"adapter\":{adapter:?},\"points\":{},\"draw\":\"{}\",\"frames\":{},\"median_ms\":{:.1},\"min_ms\":{:.1}}}",
                cloud.len(),
                raster.name(),
                times.len(),
                times[times.len() / 2],
                times[0]
            );
        }
    }
}
