//! The studio's point view through wgpu (lavapipe where there is no GPU), both draws — the compute
//! rasteriser (`shaders/points_compute.wgsl`) and the instanced quads (`shaders/points.wgsl`) — against the
//! CPU reference and each other, on poisoned buffers: random points rendered into a texture land on the
//! pixel `viewer::project` predicts, with the colour of their mode (RGB, Turbo of a scalar, solid), the
//! nearest point wins, the uncertainty threshold hides exactly the points the native filter drops (NaN
//! included), the compute picture is the CPU reference's and the quads' up to edge snapping.
#![cfg(not(target_arch = "wasm32"))]

use glam::DVec3;
use rand::{Rng, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;
use silvr_core::gpu::{wgpu, Gpu};
use silvr_core::pointcloud::PointCloud;
use silvr_core::uncertainty::filter::{default_threshold, keeps};
use silvr_core::viewer::reference::{rasterise, ReferenceLayer};
use silvr_core::viewer::{
    map_colour, project, Colouring, Frame, LayerDraw, PointRenderer, Raster, ViewCloud, ViewTargets,
};

mod common;

const W: u32 = 160;
const H: u32 = 120;
const FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
const BACKGROUND: [f64; 3] = [0.0, 0.0, 0.0];

/// Renders `draws` with `raster` into fresh targets and reads the picture back as RGBA8 rows.
fn render(
    gpu: &Gpu,
    r: &PointRenderer,
    frame: &Frame,
    draws: &[LayerDraw<'_>],
    raster: Raster,
) -> Vec<[u8; 4]> {
    let targets = r.targets(gpu, W, H);
    render_into(gpu, r, &targets, frame, draws, raster)
}

/// Renders `draws` with `raster` using `targets` (kept between frames, as the studio keeps them).
fn render_into(
    gpu: &Gpu,
    r: &PointRenderer,
    targets: &ViewTargets,
    frame: &Frame,
    draws: &[LayerDraw<'_>],
    raster: Raster,
) -> Vec<[u8; 4]> {
    let target = gpu.device.create_texture(&wgpu::TextureDescriptor {
        label: Some("test target"),
        size: wgpu::Extent3d {
            width: W,
            height: H,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: FORMAT,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    });
    assert!(targets.computes(), "a {W}×{H} target fits the compute path");
    let used = r.render(
        gpu,
        &target.create_view(&Default::default()),
        targets,
        frame,
        draws,
        raster,
    );
    assert_eq!(used, raster, "the draw asked for is the draw made");
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
    for (colouring, raster) in [
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
    ]
    .into_iter()
    .flat_map(|c| [Raster::Compute, Raster::Quads].map(|r| (c, r)))
    {
        let px = render(
            &gpu,
            &r,
            &f,
            &[LayerDraw {
                layer: &layer,
                colouring,
                filter: None,
            }],
            raster,
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
                "{raster:?} {colouring:?}: point {i} at pixel {at}: {:?} vs {want:?}",
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
    for (threshold, raster) in [t, s.quantile(0.5).unwrap()]
        .into_iter()
        .flat_map(|t| [Raster::Compute, Raster::Quads].map(|r| (t, r)))
    {
        let px = render(
            &gpu,
            &r,
            &f,
            &[LayerDraw {
                layer: &layer,
                colouring: Colouring::Solid([1.0, 1.0, 1.0]),
                filter: Some((0, threshold)),
            }],
            raster,
        );
        let (mut shown, mut hidden) = (0, 0);
        for &(i, at) in &pts {
            let lit = px[at][..3] != [0, 0, 0];
            assert_eq!(
                lit,
                keeps(s.values[i], threshold),
                "{raster:?}: point {i} value {} threshold {threshold}",
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
    for raster in [Raster::Compute, Raster::Quads] {
        let px = render(
            &gpu,
            &r,
            &f,
            &[LayerDraw {
                layer: &layer,
                colouring: Colouring::Rgb,
                filter: None,
            }],
            raster,
        );
        let ([x, y], _) = project(&f, vc.origin, vc.positions[0]).unwrap();
        let at =
            |dx: i32, dy: i32| px[((y as i32 + dy) as u32 * W + (x as i32 + dx) as u32) as usize];
        assert_eq!(
            &at(0, 0)[..3],
            &[255, 0, 0],
            "{raster:?}: the near point must hide the far one"
        );
        // 5 px squares: ±1 px around the centre are covered whichever way the centre rounds, ±4 px are
        // not.
        assert_eq!(&at(1, -1)[..3], &[255, 0, 0], "{raster:?}");
        assert_eq!(&at(-1, 1)[..3], &[255, 0, 0], "{raster:?}");
        assert_eq!(&at(0, 4)[..3], &[0, 0, 0], "{raster:?}");
        assert_eq!(&at(-4, 0)[..3], &[0, 0, 0], "{raster:?}");
        let ([bx, by], _) = project(&f, vc.origin, vc.positions[2]).unwrap();
        assert_eq!(
            &px[(by as u32 * W + bx as u32) as usize][..3],
            &[0, 0, 255],
            "{raster:?}"
        );
    }
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

/// A dense scene on the device: two layers (a far-from-origin cloud coloured by a filtered scalar, and a
/// second cloud in RGB overlapping it), so footprints overlap and the depth test decides most pixels.
struct Scene {
    clouds: [ViewCloud; 2],
    layers: [silvr_core::viewer::GpuLayer; 2],
    threshold: f32,
}

/// Point sizes and round/square footprints both draws are compared at.
const FOOTPRINTS: [(f32, bool); 4] = [(1.0, false), (3.0, false), (4.0, true), (7.5, true)];

fn dense_scene(gpu: &Gpu, r: &PointRenderer) -> Scene {
    let a = ViewCloud::from_cloud(&cloud(7, 3000), ViewCloud::MAX_POINTS);
    let mut b = cloud(8, 1500);
    for p in &mut b.positions {
        p.z += 0.3;
    }
    let b = ViewCloud::from_cloud(&b, ViewCloud::MAX_POINTS);
    let threshold = a.scalar("log_std_combined").unwrap().quantile(0.6).unwrap();
    Scene {
        layers: [r.upload(gpu, &a).unwrap(), r.upload(gpu, &b).unwrap()],
        clouds: [a, b],
        threshold,
    }
}

/// Pixels of `a` and `b` that differ by more than `tol` (0-255) in a channel.
fn differing(a: &[[u8; 4]], b: &[[u8; 4]], tol: u8) -> usize {
    a.iter()
        .zip(b)
        .filter(|(p, q)| (0..3).any(|k| p[k].abs_diff(q[k]) > tol))
        .count()
}

impl Scene {
    /// The scene's draws and their reference layers.
    fn draws(&self) -> (Vec<LayerDraw<'_>>, Vec<ReferenceLayer<'_>>) {
        let s = self.clouds[0].scalar("log_std_combined").unwrap();
        let (lo, hi) = s.range().unwrap();
        let styles = [
            (
                Colouring::Map {
                    index: 0,
                    lo,
                    hi,
                    above: s.quantile(0.8).unwrap(),
                },
                Some((0, self.threshold)),
            ),
            (Colouring::Rgb, None),
        ];
        let draws = self
            .layers
            .iter()
            .zip(styles)
            .map(|(layer, (colouring, filter))| LayerDraw {
                layer,
                colouring,
                filter,
            })
            .collect();
        let refs = self
            .clouds
            .iter()
            .zip(styles)
            .map(|(cloud, (colouring, filter))| ReferenceLayer {
                cloud,
                colouring,
                filter,
            })
            .collect();
        (draws, refs)
    }
}

#[test]
fn the_compute_rasteriser_draws_its_cpu_reference_picture() {
    let Some(gpu) = common::gpu() else { return };
    let r = pollster::block_on(PointRenderer::new(&gpu, FORMAT)).unwrap();
    let scene = dense_scene(&gpu, &r);
    let (draws, refs) = scene.draws();
    // One set of targets for every frame, as the studio keeps them: each frame must clear them (they
    // start poisoned).
    let targets = r.targets(&gpu, W, H);
    for (size, round) in FOOTPRINTS {
        let mut f = frame(size);
        f.round = round;
        f.background = [0.1, 0.2, 0.3];
        let gpu_px = render_into(&gpu, &r, &targets, &f, &draws, Raster::Compute);
        let cpu_px = rasterise(&f, &refs);
        let lit = cpu_px.iter().filter(|p| p[..3] != [26, 51, 77]).count();
        assert!(
            lit > (W * H / 20) as usize,
            "size {size}: only {lit} lit pixels"
        );
        // Turbo and projection in f32 on both sides: a channel may round the other way, and a point
        // within an ulp of a footprint edge or of another's depth may land differently.
        let off = differing(&gpu_px, &cpu_px, 1);
        assert!(
            off * 1000 <= lit,
            "size {size} round {round}: {off} of {lit} lit pixels differ from the CPU reference"
        );
    }
    // Nothing left over from the last frame.
    let f = frame(1.0);
    let empty = render_into(&gpu, &r, &targets, &f, &[], Raster::Compute);
    assert!(empty.iter().all(|p| p[..3] == [0, 0, 0]));
}

#[test]
fn compute_and_quads_make_the_same_picture() {
    let Some(gpu) = common::gpu() else { return };
    let r = pollster::block_on(PointRenderer::new(&gpu, FORMAT)).unwrap();
    let scene = dense_scene(&gpu, &r);
    let (draws, _) = scene.draws();
    for (size, round) in FOOTPRINTS {
        let mut f = frame(size);
        f.round = round;
        let compute = render(&gpu, &r, &f, &draws, Raster::Compute);
        let quads = render(&gpu, &r, &f, &draws, Raster::Quads);
        let lit = quads.iter().filter(|p| p[..3] != [0, 0, 0]).count();
        let off = differing(&compute, &quads, 1);
        eprintln!("size {size} round {round}: {off} of {lit} lit pixels differ");
        // The hardware rasteriser snaps footprint corners to 1/256 px (8 sub-pixel bits on lavapipe) and
        // breaks depth ties by draw order: pixels whose centre is that close to an edge may differ.
        assert!(
            off * 100 <= lit,
            "size {size} round {round}: {off} of {lit} lit pixels differ between the draws"
        );
    }
}
