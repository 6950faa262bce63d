//! The studio's point view (`shaders/points.wgsl`, through wgpu — lavapipe where there is no GPU) against
//! its CPU reference: random points rendered into a texture land on the pixel `viewer::project` predicts,
//! with the colour of their mode (RGB, Turbo of a scalar, solid), the nearest point wins, and the
//! uncertainty threshold hides exactly the points the native filter drops (NaN included).
#![cfg(not(target_arch = "wasm32"))]

use glam::DVec3;
use rand::{Rng, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;
use silvr_core::gpu::{wgpu, Gpu};
use silvr_core::pointcloud::PointCloud;
use silvr_core::uncertainty::filter::{default_threshold, keeps};
use silvr_core::viewer::{
    map_colour, project, Colouring, Frame, LayerDraw, PointRenderer, ViewCloud, DEPTH_FORMAT,
};

mod common;

const W: u32 = 160;
const H: u32 = 120;
const FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
const BACKGROUND: [f64; 3] = [0.0, 0.0, 0.0];

/// Renders `draws` and reads the target back as RGBA8 rows.
fn render(gpu: &Gpu, r: &PointRenderer, frame: &Frame, draws: &[LayerDraw<'_>]) -> Vec<[u8; 4]> {
    let tex = |format, usage| {
        gpu.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("test target"),
            size: wgpu::Extent3d {
                width: W,
                height: H,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage,
            view_formats: &[],
        })
    };
    let target = tex(
        FORMAT,
        wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
    );
    let depth = tex(DEPTH_FORMAT, wgpu::TextureUsages::RENDER_ATTACHMENT);
    r.render(
        gpu,
        &target.create_view(&Default::default()),
        &depth.create_view(&Default::default()),
        frame,
        draws,
    );
    // Rows of a texture copy are padded to 256 bytes.
    let row = (W * 4).next_multiple_of(256);
    let out = gpu.output("test readback", (row * H / 4) as usize).unwrap();
    let mut enc = gpu.encoder("test copy");
    enc.copy_texture_to_buffer(
        target.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &out,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(row),
                rows_per_image: Some(H),
            },
        },
        wgpu::Extent3d {
            width: W,
            height: H,
            depth_or_array_layers: 1,
        },
    );
    let words =
        pollster::block_on(gpu.finish_and_read::<u32>(enc, &[(&out, (row * H / 4) as usize)]))
            .unwrap()
            .remove(0);
    let mut px = Vec::with_capacity((W * H) as usize);
    for y in 0..H {
        for x in 0..W {
            px.push(words[(y * row / 4 + x) as usize].to_le_bytes());
        }
    }
    px
}

fn frame(point_size: f32) -> Frame {
    let reference = DVec3::new(1000.0, -2000.0, 30.0);
    Frame {
        reference,
        view_proj: Frame::look_at(
            reference + DVec3::new(-6.0, -5.0, 3.0),
            reference,
            0.9,
            (0.1, 100.0),
            (W, H),
            reference,
        ),
        width: W,
        height: H,
        point_size,
        round: false,
        background: BACKGROUND,
    }
}

/// Points spread so that no two share a pixel neighbourhood, in a cloud far from the origin (metric map
/// coordinates), with RGB and an uncertainty scalar (a few NaN).
fn cloud(seed: u64, n: usize) -> PointCloud {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    let mut c = PointCloud::new();
    let base = DVec3::new(1000.0, -2000.0, 30.0);
    let mut values = Vec::new();
    while c.len() < n {
        let p = base
            + DVec3::new(
                rng.random_range(-2.0..2.0),
                rng.random_range(-2.0..2.0),
                rng.random_range(-1.0..1.0),
            );
        c.push_colored(p, [rng.random(), rng.random(), rng.random()]);
        values.push(if rng.random_range(0..10) == 0 {
            f32::NAN
        } else {
            rng.random_range(-3.0..1.0)
        });
    }
    c.set_scalar("log_std_combined", values);
    c
}

fn close(a: [u8; 4], b: [f32; 3], tol: f32) -> bool {
    (0..3).all(|k| (a[k] as f32 / 255.0 - b[k]).abs() <= tol)
}

/// Pixels the CPU reference assigns to one point (size 1: the pixel containing it), keeping only those
/// far enough from every other point's pixel that rasterisation ties cannot decide them.
fn isolated(frame: &Frame, vc: &ViewCloud) -> Vec<(usize, usize)> {
    let proj: Vec<Option<[f32; 2]>> = vc
        .positions
        .iter()
        .map(|&p| project(frame, vc.origin, p).map(|(xy, _)| xy))
        .collect();
    let mut out = Vec::new();
    for (i, a) in proj.iter().enumerate() {
        let Some(a) = a else { continue };
        let (x, y) = (a[0], a[1]);
        // Away from pixel edges and the border, and 3 px from every other point.
        let fx = x - x.floor();
        let fy = y - y.floor();
        if !(0.2..0.8).contains(&fx) || !(0.2..0.8).contains(&fy) {
            continue;
        }
        if x < 2.0 || y < 2.0 || x > W as f32 - 2.0 || y > H as f32 - 2.0 {
            continue;
        }
        let alone = proj.iter().enumerate().all(|(j, b)| {
            j == i || b.is_none_or(|b| (b[0] - x).abs() > 3.0 || (b[1] - y).abs() > 3.0)
        });
        if alone {
            out.push((i, (y as usize) * W as usize + x as usize));
        }
    }
    out
}

#[test]
fn points_land_where_the_cpu_reference_puts_them_in_every_colour_mode() {
    let Some(gpu) = common::gpu() else { return };
    let r = pollster::block_on(PointRenderer::new(&gpu, FORMAT)).unwrap();
    let c = cloud(1, 60);
    let vc = ViewCloud::from_cloud(&c, ViewCloud::MAX_POINTS);
    assert_eq!(vc.len(), 60);
    let layer = r.upload(&gpu, &vc).unwrap();
    let f = frame(1.0);
    let pts = isolated(&f, &vc);
    assert!(pts.len() >= 8, "only {} isolated points", pts.len());
    let s = vc.scalar("log_std_combined").unwrap();
    let (lo, hi) = s.range().unwrap();
    // The upper third of the values as "unconstrained".
    let above = s.quantile(0.67).unwrap();
    for colouring in [
        Colouring::Rgb,
        Colouring::Map {
            index: 0,
            lo,
            hi,
            above: f32::INFINITY,
        },
        Colouring::Map {
            index: 0,
            lo,
            hi,
            above,
        },
        Colouring::Solid([0.2, 0.9, 0.4]),
    ] {
        let px = render(
            &gpu,
            &r,
            &f,
            &[LayerDraw {
                layer: &layer,
                colouring,
                filter: None,
            }],
        );
        for &(i, at) in &pts {
            let want = match colouring {
                Colouring::Rgb => {
                    let b = vc.colours[i].to_le_bytes();
                    [
                        b[0] as f32 / 255.0,
                        b[1] as f32 / 255.0,
                        b[2] as f32 / 255.0,
                    ]
                }
                Colouring::Map { lo, hi, above, .. } => map_colour(s.values[i], lo, hi, above),
                Colouring::Solid(c) => c,
            };
            assert!(
                close(px[at], want, 2.5 / 255.0),
                "{colouring:?}: point {i} at pixel {at}: {:?} vs {want:?}",
                px[at]
            );
        }
        // Nothing is drawn where no point projects (1-px points, so most of the image is background).
        let lit = px.iter().filter(|p| p[..3] != [0, 0, 0]).count();
        assert!(lit <= vc.len(), "{lit} lit pixels for {} points", vc.len());
    }
}

#[test]
fn the_threshold_hides_exactly_the_points_the_native_filter_drops() {
    let Some(gpu) = common::gpu() else { return };
    let r = pollster::block_on(PointRenderer::new(&gpu, FORMAT)).unwrap();
    let c = cloud(2, 60);
    let vc = ViewCloud::from_cloud(&c, ViewCloud::MAX_POINTS);
    let layer = r.upload(&gpu, &vc).unwrap();
    let f = frame(1.0);
    let pts = isolated(&f, &vc);
    let s = vc.scalar("log_std_combined").unwrap();
    let t = default_threshold(&s.values);
    // Lower than the fence too, so some finite values are cut.
    for threshold in [t, s.quantile(0.5).unwrap()] {
        let px = render(
            &gpu,
            &r,
            &f,
            &[LayerDraw {
                layer: &layer,
                colouring: Colouring::Solid([1.0, 1.0, 1.0]),
                filter: Some((0, threshold)),
            }],
        );
        let (mut shown, mut hidden) = (0, 0);
        for &(i, at) in &pts {
            let lit = px[at][..3] != [0, 0, 0];
            assert_eq!(
                lit,
                keeps(s.values[i], threshold),
                "point {i} value {} threshold {threshold}",
                s.values[i]
            );
            if lit {
                shown += 1
            } else {
                hidden += 1
            }
        }
        assert!(shown > 0 && hidden > 0, "{shown} shown, {hidden} hidden");
        // The count the studio shows is the native filter's count.
        let native = s.values.iter().filter(|&&v| keeps(v, threshold)).count();
        assert_eq!(s.kept(threshold), native);
        assert_eq!(
            vc.filtered("log_std_combined", threshold).unwrap().len(),
            native
        );
    }
}

#[test]
fn the_nearest_point_wins_and_size_grows_the_footprint() {
    let Some(gpu) = common::gpu() else { return };
    let r = pollster::block_on(PointRenderer::new(&gpu, FORMAT)).unwrap();
    let f = frame(5.0);
    let eye = DVec3::new(-6.0, -5.0, 3.0);
    // Two points on one line of sight: red near, green far, and a lone blue one.
    let mut c = PointCloud::new();
    let base = f.reference;
    let dir = (-eye).normalize();
    c.push_colored(base + eye + dir * 4.0, [255, 0, 0]);
    c.push_colored(base + eye + dir * 8.0, [0, 255, 0]);
    c.push_colored(base + DVec3::new(0.0, 0.0, 1.0), [0, 0, 255]);
    let vc = ViewCloud::from_cloud(&c, ViewCloud::MAX_POINTS);
    let layer = r.upload(&gpu, &vc).unwrap();
    let px = render(
        &gpu,
        &r,
        &f,
        &[LayerDraw {
            layer: &layer,
            colouring: Colouring::Rgb,
            filter: None,
        }],
    );
    let ([x, y], _) = project(&f, vc.origin, vc.positions[0]).unwrap();
    let at = |dx: i32, dy: i32| px[((y as i32 + dy) as u32 * W + (x as i32 + dx) as u32) as usize];
    assert_eq!(
        &at(0, 0)[..3],
        &[255, 0, 0],
        "the near point must hide the far one"
    );
    // 5 px squares: ±1 px around the centre are covered whichever way the centre rounds, ±4 px are not.
    assert_eq!(&at(1, -1)[..3], &[255, 0, 0]);
    assert_eq!(&at(-1, 1)[..3], &[255, 0, 0]);
    assert_eq!(&at(0, 4)[..3], &[0, 0, 0]);
    assert_eq!(&at(-4, 0)[..3], &[0, 0, 0]);
    let ([bx, by], _) = project(&f, vc.origin, vc.positions[2]).unwrap();
    assert_eq!(&px[(by as u32 * W + bx as u32) as usize][..3], &[0, 0, 255]);
}

#[test]
fn large_clouds_are_decimated_with_a_stated_stride() {
    let c = cloud(3, 1000);
    let vc = ViewCloud::from_cloud(&c, 300);
    assert_eq!(vc.stride, 4);
    assert_eq!(vc.len(), 250);
    assert_eq!(vc.total, 1000);
    // Positions keep sub-millimetre precision far from the origin.
    let back = vc.origin + glam::Vec3::from_array(vc.positions[1]).as_dvec3();
    assert!((back - c.positions[4]).length() < 1e-4);
}
