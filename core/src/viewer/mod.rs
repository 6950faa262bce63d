//! The studio's point-cloud view: reconstructions (one layer per file or submap) in GPU buffers, drawn as
//! screen-space squares or discs coloured by RGB, by a colour-mapped scalar (each `log_std_*`, `error_m`)
//! or by a solid layer colour, with the uncertainty threshold applied on the GPU. Two draws, one picture:
//! - [`compute`] (the default, [`Raster::Compute`]): a compute rasteriser, one invocation per point and an
//!   atomic depth test in storage buffers (`shaders/points_compute.wgsl`);
//! - instanced quads through the hardware rasteriser ([`Raster::Quads`], `shaders/points.wgsl`): the
//!   reference draw, and the fallback where a target is too large for the compute path's buffers.
//!
//! Why here and not in the worker: the same device as the engine draws the view, and native tests render
//! through lavapipe and compare pixels with the CPU reference ([`reference::rasterise`], [`project`],
//! [`turbo`]) and the two draws with each other.
//!
//! Buffers are split into chunks that fit the adapter's `max_buffer_size`, never one giant buffer; clouds
//! above [`ViewCloud::MAX_POINTS`] are decimated with a stated stride. Positions are stored relative to
//! each layer's centre in f32 and the camera works relative to a reference point, so a city-sized map in
//! metric UTM-like coordinates keeps millimetre precision near the camera.

use glam::{DMat4, DVec3, DVec4, Mat4, Vec3};

use crate::gpu::{Gpu, GpuError};
use crate::pointcloud::PointCloud;
use crate::shaders;

pub mod compute;
pub mod reference;

/// The scalar properties the studio colours and filters by, in the order it offers them.
pub const UNCERTAINTY_FIELDS: [&str; 3] = ["log_std_combined", "log_std_colour", "log_std_depth"];
/// The evaluator's per-point distance to ground truth (`silvr eval --error-ply`), metres.
pub const ERROR_FIELD: &str = "error_m";
/// The scalar properties the studio colours and filters by; a reader for the view decodes no others.
pub const SHOWN_FIELDS: [&str; 4] = [
    UNCERTAINTY_FIELDS[0],
    UNCERTAINTY_FIELDS[1],
    UNCERTAINTY_FIELDS[2],
    ERROR_FIELD,
];

/// Colour of a value the map marks as beyond meaning (an uncertainty that reads its prior:
/// "unconstrained"), apart from Turbo's range and from the grey of a missing value.
pub const UNCONSTRAINED_COLOUR: [f32; 3] = [0.85, 0.78, 0.95];
/// Colour of a missing or non-finite value.
pub const NO_VALUE_COLOUR: [f32; 3] = [0.45, 0.45, 0.45];

/// CPU reference of the shader's colour map: NaN grey, `value ≥ above` [`UNCONSTRAINED_COLOUR`], else
/// Turbo over `lo..hi`.
pub fn map_colour(value: f32, lo: f32, hi: f32, above: f32) -> [f32; 3] {
    if !value.is_finite() {
        NO_VALUE_COLOUR
    } else if value >= above {
        UNCONSTRAINED_COLOUR
    } else if hi != lo {
        turbo((value - lo) / (hi - lo))
    } else {
        turbo(0.5)
    }
}

/// Google's Turbo colour map (polynomial approximation; the WGSL uses the same coefficients): `t` in
/// [0, 1] (clamped) → RGB, clamped to [0, 1] (the polynomial dips just below 0 at the red end).
pub fn turbo(t: f32) -> [f32; 3] {
    let t = t.clamp(0.0, 1.0);
    let v4 = [1.0, t, t * t, t * t * t];
    let v2 = [v4[2] * v4[2], v4[3] * v4[2]];
    let dot4 = |c: [f32; 4]| v4[0] * c[0] + v4[1] * c[1] + v4[2] * c[2] + v4[3] * c[3];
    let dot2 = |c: [f32; 2]| v2[0] * c[0] + v2[1] * c[1];
    [
        dot4([0.135_721_38, 4.615_392_6, -42.660_324, 132.131_08]) + dot2([-152.942_4, 59.286_38]),
        dot4([0.091_402_61, 2.194_188_4, 4.842_966_6, -14.185_033])
            + dot2([4.277_298_6, 2.829_566]),
        dot4([0.106_673_3, 12.641_946, -60.582_05, 110.362_77]) + dot2([-89.903_11, 27.348_25]),
    ]
    .map(|c| c.clamp(0.0, 1.0))
}

/// One named scalar of a cloud with what the studio needs to colour and filter by it.
#[derive(Clone, Debug)]
pub struct Scalar {
    pub name: String,
    pub values: Vec<f32>,
    /// Every non-NaN value, ascending (`total_cmp`): the kept count of any threshold is one binary search.
    sorted: Vec<f32>,
}

impl Scalar {
    pub fn new(name: &str, values: Vec<f32>) -> Self {
        let mut sorted: Vec<f32> = values.iter().copied().filter(|v| !v.is_nan()).collect();
        sorted.sort_by(f32::total_cmp);
        Self {
            name: name.to_string(),
            values,
            sorted,
        }
    }

    /// Points kept by `value <= threshold`, the native filter's rule (NaN is never kept).
    pub fn kept(&self, threshold: f32) -> usize {
        if threshold.is_nan() {
            return 0;
        }
        self.sorted.partition_point(|&v| v <= threshold)
    }

    /// The value at quantile `q` of the finite values (nearest rank), if any.
    pub fn quantile(&self, q: f64) -> Option<f32> {
        let finite: &[f32] = {
            let lo = self.sorted.partition_point(|v| *v == f32::NEG_INFINITY);
            let hi = self.sorted.partition_point(|v| *v < f32::INFINITY);
            &self.sorted[lo..hi]
        };
        (!finite.is_empty())
            .then(|| finite[((finite.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize])
    }

    /// The value at quantile `q` of the finite values below `limit` (nearest rank), if any: the colour
    /// map's range without the values it marks apart (`map_colour`'s `above`).
    pub fn quantile_below(&self, q: f64, limit: f32) -> Option<f32> {
        let lo = self.sorted.partition_point(|v| *v == f32::NEG_INFINITY);
        let hi = self
            .sorted
            .partition_point(|v| *v < f32::INFINITY && *v < limit);
        let finite = &self.sorted[lo..hi.max(lo)];
        (!finite.is_empty())
            .then(|| finite[((finite.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize])
    }

    /// How many values are at or above `limit` (NaN never is).
    pub fn at_least(&self, limit: f32) -> usize {
        self.sorted.len() - self.sorted.partition_point(|v| *v < limit)
    }

    /// Smallest and largest finite value.
    pub fn range(&self) -> Option<(f32, f32)> {
        Some((self.quantile(0.0)?, self.quantile(1.0)?))
    }
}

/// A cloud as the view holds it: f32 positions relative to `origin`, RGBA8 colours, the scalars.
#[derive(Clone, Debug)]
pub struct ViewCloud {
    /// Centre of the cloud's bounds (metres, the file's frame).
    pub origin: DVec3,
    pub positions: Vec<[f32; 3]>,
    /// RGBA8 packed little-endian (R in the low byte); grey where the file has no colour.
    pub colours: Vec<u32>,
    pub has_rgb: bool,
    pub scalars: Vec<Scalar>,
    /// Points in the file.
    pub total: usize,
    /// Every `stride`-th point is kept (1: all of them).
    pub stride: usize,
    /// Bounds of the kept points (metres, the file's frame).
    pub min: DVec3,
    pub max: DVec3,
    /// The 1st-99th percentile box per axis: what "fit to view" frames, so a few far points (a
    /// radiance field's floaters, a lidar return off a distant tower) do not shrink the scene to a dot.
    pub fit_min: DVec3,
    pub fit_max: DVec3,
}

impl ViewCloud {
    /// Largest number of points the studio keeps of one cloud (more are decimated, and it says so).
    pub const MAX_POINTS: usize = 20_000_000;

    /// The view of `cloud`, keeping at most `max_points` (every k-th point beyond that). Points with a
    /// non-finite coordinate are dropped (they cannot be drawn); their count is `total - positions.len()`
    /// when `stride` is 1.
    pub fn from_cloud(cloud: &PointCloud, max_points: usize) -> Self {
        let total = cloud.len();
        let stride = total.div_ceil(max_points.max(1)).max(1);
        let keep: Vec<usize> = (0..total)
            .step_by(stride)
            .filter(|&i| cloud.positions[i].is_finite())
            .collect();
        let (mut min, mut max) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for &i in &keep {
            min = min.min(cloud.positions[i]);
            max = max.max(cloud.positions[i]);
        }
        if keep.is_empty() {
            (min, max) = (DVec3::ZERO, DVec3::ZERO);
        }
        let origin = (min + max) * 0.5;
        let (fit_min, fit_max) = robust_box(&keep, &cloud.positions).unwrap_or((min, max));
        let positions = keep
            .iter()
            .map(|&i| (cloud.positions[i] - origin).as_vec3().to_array())
            .collect();
        let colours = match &cloud.colors {
            Some(c) => keep
                .iter()
                .map(|&i| u32::from_le_bytes([c[i][0], c[i][1], c[i][2], 255]))
                .collect(),
            None => vec![u32::from_le_bytes([170, 170, 170, 255]); keep.len()],
        };
        let scalars = cloud
            .scalars
            .iter()
            .map(|(name, v)| Scalar::new(name, keep.iter().map(|&i| v[i]).collect()))
            .collect();
        Self {
            origin,
            positions,
            colours,
            has_rgb: cloud.colors.is_some(),
            scalars,
            total,
            stride,
            min,
            max,
            fit_min,
            fit_max,
        }
    }

    pub fn len(&self) -> usize {
        self.positions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    pub fn scalar(&self, name: &str) -> Option<&Scalar> {
        self.scalars.iter().find(|s| s.name == name)
    }

    /// The points kept by `field <= threshold`, as a cloud in the file's frame (what the studio
    /// downloads; the same rule and the same PLY writer as the native `points_filtered.ply`).
    pub fn filtered(&self, field: &str, threshold: f32) -> Option<PointCloud> {
        let s = self.scalar(field)?;
        let keep: Vec<usize> = (0..self.len())
            .filter(|&i| s.values[i] <= threshold)
            .collect();
        let mut out = PointCloud::new();
        out.positions = keep
            .iter()
            .map(|&i| self.origin + Vec3::from_array(self.positions[i]).as_dvec3())
            .collect();
        if self.has_rgb {
            out.colors = Some(
                keep.iter()
                    .map(|&i| {
                        let b = self.colours[i].to_le_bytes();
                        [b[0], b[1], b[2]]
                    })
                    .collect(),
            );
        }
        for sc in &self.scalars {
            out.set_scalar(&sc.name, keep.iter().map(|&i| sc.values[i]).collect());
        }
        Some(out)
    }
}

/// The 1st and 99th percentile of each axis over (at most 100 k of) the points `keep` selects.
fn robust_box(keep: &[usize], positions: &[DVec3]) -> Option<(DVec3, DVec3)> {
    if keep.is_empty() {
        return None;
    }
    let step = keep.len().div_ceil(100_000).max(1);
    let sample: Vec<DVec3> = keep.iter().step_by(step).map(|&i| positions[i]).collect();
    let mut lo = [0.0; 3];
    let mut hi = [0.0; 3];
    for axis in 0..3 {
        let mut v: Vec<f64> = sample.iter().map(|p| p[axis]).collect();
        v.sort_by(f64::total_cmp);
        let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
        lo[axis] = at(0.01);
        hi[axis] = at(0.99);
    }
    Some((DVec3::from_array(lo), DVec3::from_array(hi)))
}

/// How a layer is coloured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Colouring {
    /// The file's RGB (grey where it has none).
    Rgb,
    /// Scalar `index` of the layer through [`turbo`], `lo` at blue and `hi` at red; values at or above
    /// `above` in [`UNCONSTRAINED_COLOUR`] (`f32::INFINITY`: none) — see [`map_colour`].
    Map {
        index: usize,
        lo: f32,
        hi: f32,
        above: f32,
    },
    /// One colour for the whole layer (RGB in [0, 1]).
    Solid([f32; 3]),
}

/// The camera of one frame: `view_proj` maps points relative to `reference` to clip space.
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    pub reference: DVec3,
    pub view_proj: Mat4,
    pub width: u32,
    pub height: u32,
    pub point_size: f32,
    pub round: bool,
    pub background: [f64; 3],
}

impl Frame {
    /// A perspective camera at `eye` looking at `target` (z up), vertical field of view `fov_y` (rad),
    /// with `reference` as the origin of the f32 maths.
    pub fn look_at(
        eye: DVec3,
        target: DVec3,
        fov_y: f64,
        (near, far): (f64, f64),
        (width, height): (u32, u32),
        reference: DVec3,
    ) -> Mat4 {
        let up = if (target - eye).normalize_or_zero().cross(DVec3::Z).length() < 1e-6 {
            DVec3::Y
        } else {
            DVec3::Z
        };
        let (e, t) = (eye - reference, target - reference);
        // Right-handed view (camera looks down -z), WebGPU clip depth in [0, 1].
        let f = (t - e).normalize();
        let s = f.cross(up).normalize();
        let u = s.cross(f);
        let view = DMat4::from_cols(
            DVec4::new(s.x, u.x, -f.x, 0.0),
            DVec4::new(s.y, u.y, -f.y, 0.0),
            DVec4::new(s.z, u.z, -f.z, 0.0),
            DVec4::new(-s.dot(e), -u.dot(e), f.dot(e), 1.0),
        );
        let aspect = width.max(1) as f64 / height.max(1) as f64;
        let h = 1.0 / (0.5 * fov_y).tan();
        let r = far / (near - far);
        let proj = DMat4::from_cols(
            DVec4::new(h / aspect, 0.0, 0.0, 0.0),
            DVec4::new(0.0, h, 0.0, 0.0),
            DVec4::new(0.0, 0.0, r, -1.0),
            DVec4::new(0.0, 0.0, r * near, 0.0),
        );
        (proj * view).as_mat4()
    }
}

/// One layer to draw this frame.
pub struct LayerDraw<'a> {
    pub layer: &'a GpuLayer,
    pub colouring: Colouring,
    /// Scalar index and threshold: points whose value is not `<= threshold` are hidden.
    pub filter: Option<(usize, f32)>,
}

/// Which draw puts the points on screen.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Raster {
    /// The compute rasteriser ([`compute`]): one invocation per point, an atomic depth test in storage
    /// buffers. The studio's default: on SwiftShader and lavapipe it is many times faster than triangles.
    #[default]
    Compute,
    /// Instanced screen-space quads through the hardware rasteriser (`points.wgsl`): the reference draw.
    Quads,
}

impl Raster {
    pub fn name(self) -> &'static str {
        match self {
            Raster::Compute => "compute",
            Raster::Quads => "quads",
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "compute" => Some(Raster::Compute),
            "quads" => Some(Raster::Quads),
            _ => None,
        }
    }
}

struct Chunk {
    points: u32,
    positions: wgpu::Buffer,
    colours: wgpu::Buffer,
    scalars: Vec<wgpu::Buffer>,
}

impl Chunk {
    /// The buffer of scalar `i`, or (when the layer lacks it, and mode and filter are then off so it is
    /// never read) any buffer of 4 bytes per point.
    fn scalar(&self, i: Option<usize>) -> &wgpu::Buffer {
        i.and_then(|i| self.scalars.get(i)).unwrap_or(&self.colours)
    }
}

/// A cloud on the device, in chunks that fit the adapter's buffer and storage-binding limits.
pub struct GpuLayer {
    chunks: Vec<Chunk>,
    origin: DVec3,
    points: usize,
}

impl GpuLayer {
    pub fn points(&self) -> usize {
        self.points
    }

    pub fn origin(&self) -> DVec3 {
        self.origin
    }

    /// GPU bytes held by the layer.
    pub fn bytes(&self) -> u64 {
        self.chunks
            .iter()
            .map(|c| {
                c.positions.size()
                    + c.colours.size()
                    + c.scalars.iter().map(|s| s.size()).sum::<u64>()
            })
            .sum()
    }

    fn has_scalar(&self, i: usize) -> bool {
        self.chunks.first().is_none_or(|c| i < c.scalars.len())
    }
}

/// Size of the per-draw uniform block (`View` in `points_common.wgsl`), padded to WebGPU's 256-byte
/// `minUniformBufferOffsetAlignment`.
const UNIFORM_STRIDE: u64 = 256;

/// The point view's pipelines for one target format: the instanced-quad draw and the compute rasteriser.
pub struct PointRenderer {
    pipeline: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    /// `None` where the adapter cannot build the compute draw.
    compute: Option<compute::ComputeRaster>,
    pub format: wgpu::TextureFormat,
}

/// Depth format of the quad draw.
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

/// What a frame is drawn with besides the colour target, sized to it: the quad draw's depth texture and
/// the compute rasteriser's per-pixel words (absent where a target of this size exceeds the adapter's
/// storage-binding limit, or the adapter cannot build the compute draw: then the quads draw).
pub struct ViewTargets {
    pub width: u32,
    pub height: u32,
    depth: wgpu::TextureView,
    words: Option<compute::Words>,
}

impl ViewTargets {
    /// Whether the compute rasteriser can draw into targets of this size.
    pub fn computes(&self) -> bool {
        self.words.is_some()
    }

    /// The draw a frame asking for `wanted` gets: quads where these targets cannot take the compute one.
    pub fn draw_for(&self, wanted: Raster) -> Raster {
        if self.computes() {
            wanted
        } else {
            Raster::Quads
        }
    }
}

impl PointRenderer {
    /// Compiles `points.wgsl` and `points_compute.wgsl` for `format` (a non-sRGB format: colours are
    /// written as they are encoded, the way a browser canvas shows them). A WGSL or pipeline error comes
    /// back as [`GpuError::Kernel`].
    pub async fn new(gpu: &Gpu, format: wgpu::TextureFormat) -> Result<Self, GpuError> {
        let device = &gpu.device;
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("points"),
            source: wgpu::ShaderSource::Wgsl(shaders::POINTS.into()),
        });
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("points view"),
            entries: &[view_entry(wgpu::ShaderStages::VERTEX_FRAGMENT)],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("points"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let attr = |location, format| wgpu::VertexAttribute {
            format,
            offset: 0,
            shader_location: location,
        };
        let a_pos = [attr(0, wgpu::VertexFormat::Float32x3)];
        let a_rgb = [attr(1, wgpu::VertexFormat::Unorm8x4)];
        let a_val = [attr(2, wgpu::VertexFormat::Float32)];
        let a_flt = [attr(3, wgpu::VertexFormat::Float32)];
        let per_point = |stride, attributes| {
            Some(wgpu::VertexBufferLayout {
                array_stride: stride,
                step_mode: wgpu::VertexStepMode::Instance,
                attributes,
            })
        };
        let buffers = [
            per_point(12, &a_pos[..]),
            per_point(4, &a_rgb[..]),
            per_point(4, &a_val[..]),
            per_point(4, &a_flt[..]),
        ];
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("points"),
            layout: Some(&pipeline_layout),
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some("vs"),
                compilation_options: Default::default(),
                buffers: &buffers,
            },
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::TriangleStrip,
                ..Default::default()
            },
            depth_stencil: Some(wgpu::DepthStencilState {
                format: DEPTH_FORMAT,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Less),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &module,
                entry_point: Some("fs"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        if let Some(err) = scope.pop().await {
            return Err(GpuError::Kernel {
                kernel: "points".into(),
                detail: err.to_string(),
            });
        }
        // The compute draw is a speed-up, not a requirement: an adapter that cannot build it (storage
        // buffers in fragment shaders, atomics) still gets the view, drawn with quads.
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let compute = compute::ComputeRaster::new(gpu, format);
        let compute = match scope.pop().await {
            None => Some(compute),
            Some(err) => {
                log::warn!(
                    "the compute point draw cannot be built here, quads draw instead: {err}"
                );
                None
            }
        };
        Ok(Self {
            pipeline,
            layout,
            compute,
            format,
        })
    }

    /// Uploads `cloud` in chunks that each fit `max_buffer_size`, the storage-binding limit (the compute
    /// rasteriser reads them as storage) and one dispatch.
    pub fn upload(&self, gpu: &Gpu, cloud: &ViewCloud) -> Result<GpuLayer, GpuError> {
        let limits = gpu.device.limits();
        let bytes = limits
            .max_buffer_size
            .min(limits.max_storage_buffer_binding_size);
        let per_chunk = ((bytes / 12) as usize).clamp(1, compute::MAX_DISPATCH_POINTS);
        let mut chunks = Vec::new();
        let mut start = 0;
        while start < cloud.len() {
            let end = (start + per_chunk).min(cloud.len());
            // Each buffer holds at most 12 bytes per point of the chunk: within both limits.
            let vertex = |label: &str, bytes: &[u8]| -> Result<wgpu::Buffer, GpuError> {
                gpu.check_lost()?;
                Ok(gpu.buffer_with(
                    label,
                    bytes,
                    wgpu::BufferUsages::VERTEX
                        | wgpu::BufferUsages::STORAGE
                        | wgpu::BufferUsages::COPY_DST,
                ))
            };
            chunks.push(Chunk {
                points: (end - start) as u32,
                positions: vertex(
                    "view positions",
                    bytemuck::cast_slice(&cloud.positions[start..end]),
                )?,
                colours: vertex(
                    "view colours",
                    bytemuck::cast_slice(&cloud.colours[start..end]),
                )?,
                scalars: cloud
                    .scalars
                    .iter()
                    .map(|s| vertex("view scalar", bytemuck::cast_slice(&s.values[start..end])))
                    .collect::<Result<_, _>>()?,
            });
            start = end;
        }
        Ok(GpuLayer {
            chunks,
            origin: cloud.origin,
            points: cloud.len(),
        })
    }

    /// The depth texture and per-pixel words for targets of `width` × `height`.
    pub fn targets(&self, gpu: &Gpu, width: u32, height: u32) -> ViewTargets {
        let (width, height) = (width.max(1), height.max(1));
        let depth = gpu
            .device
            .create_texture(&wgpu::TextureDescriptor {
                label: Some("view depth"),
                size: wgpu::Extent3d {
                    width,
                    height,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: DEPTH_FORMAT,
                usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
                view_formats: &[],
            })
            .create_view(&Default::default());
        let words = self
            .compute
            .as_ref()
            .and_then(|c| c.words(gpu, width, height));
        ViewTargets {
            width,
            height,
            depth,
            words,
        }
    }

    /// Draws `layers` into `target` (format [`Self::format`], the size of `targets`), clearing it to the
    /// frame's background first, with `raster` where it can (the compute rasteriser needs `targets`'
    /// words). Returns the draw it used.
    pub fn render(
        &self,
        gpu: &Gpu,
        target: &wgpu::TextureView,
        targets: &ViewTargets,
        frame: &Frame,
        layers: &[LayerDraw<'_>],
        raster: Raster,
    ) -> Raster {
        let uniforms = layer_uniforms(gpu, frame, layers);
        let mut encoder = gpu.encoder("points view");
        let used = match (&self.compute, &targets.words, targets.draw_for(raster)) {
            (Some(compute), Some(words), Raster::Compute) => {
                compute.encode(gpu, &mut encoder, target, words, &uniforms, frame, layers);
                Raster::Compute
            }
            _ => {
                self.encode_quads(
                    gpu,
                    &mut encoder,
                    target,
                    &targets.depth,
                    &uniforms,
                    frame,
                    layers,
                );
                Raster::Quads
            }
        };
        gpu.queue.submit([encoder.finish()]);
        used
    }

    #[allow(clippy::too_many_arguments)]
    fn encode_quads(
        &self,
        gpu: &Gpu,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        depth: &wgpu::TextureView,
        uniforms: &wgpu::Buffer,
        frame: &Frame,
        layers: &[LayerDraw<'_>],
    ) {
        let bind = gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("points view"),
            layout: &self.layout,
            entries: &[view_binding(uniforms)],
        });
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("points view"),
            color_attachments: &[Some(clear_to_background(target, frame))],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: depth,
                depth_ops: Some(wgpu::Operations {
                    load: wgpu::LoadOp::Clear(1.0),
                    store: wgpu::StoreOp::Discard,
                }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&self.pipeline);
        for (k, d) in layers.iter().enumerate() {
            pass.set_bind_group(0, &bind, &[(k as u64 * UNIFORM_STRIDE) as u32]);
            let p = LayerParams::of(d.colouring, d.filter, |i| d.layer.has_scalar(i));
            for c in &d.layer.chunks {
                pass.set_vertex_buffer(0, c.positions.slice(..));
                pass.set_vertex_buffer(1, c.colours.slice(..));
                pass.set_vertex_buffer(2, c.scalar(p.colour_scalar).slice(..));
                pass.set_vertex_buffer(3, c.scalar(p.filter_scalar).slice(..));
                pass.draw(0..4, 0..c.points);
            }
        }
    }
}

/// A colour attachment cleared to the frame's background.
fn clear_to_background<'a>(
    target: &'a wgpu::TextureView,
    frame: &Frame,
) -> wgpu::RenderPassColorAttachment<'a> {
    let [r, g, b] = frame.background;
    wgpu::RenderPassColorAttachment {
        view: target,
        depth_slice: None,
        resolve_target: None,
        ops: wgpu::Operations {
            load: wgpu::LoadOp::Clear(wgpu::Color { r, g, b, a: 1.0 }),
            store: wgpu::StoreOp::Store,
        },
    }
}

/// Binding 0 of both draws: one layer's `View` block at a dynamic offset.
fn view_entry(visibility: wgpu::ShaderStages) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding: 0,
        visibility,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: true,
            min_binding_size: None,
        },
        count: None,
    }
}

fn view_binding(uniforms: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding: 0,
        resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: uniforms,
            offset: 0,
            size: wgpu::BufferSize::new(UNIFORM_BYTES as u64),
        }),
    }
}

/// The `View` blocks of `layers`, one per [`UNIFORM_STRIDE`].
fn layer_uniforms(gpu: &Gpu, frame: &Frame, layers: &[LayerDraw<'_>]) -> wgpu::Buffer {
    let draws = layers.len().max(1) as u64;
    let mut block = vec![0u8; (draws * UNIFORM_STRIDE) as usize];
    for (k, d) in layers.iter().enumerate() {
        let p = LayerParams::of(d.colouring, d.filter, |i| d.layer.has_scalar(i));
        let u = view_uniform(frame, d.layer.origin, &p);
        let at = k * UNIFORM_STRIDE as usize;
        block[at..at + u.len()].copy_from_slice(&u);
    }
    gpu.buffer_with("points view", &block, wgpu::BufferUsages::UNIFORM)
}

/// Bytes of `View` in `points_common.wgsl`: mat4 + 5 vec4.
const UNIFORM_BYTES: usize = 64 + 5 * 16;

/// How one layer is coloured and filtered once its scalars are known: a colour map of a scalar the layer
/// lacks falls back to solid black, a filter by one is off. Shared by both draws and the CPU reference.
#[derive(Clone, Copy, Debug)]
pub(crate) struct LayerParams {
    /// 0 RGB, 1 colour map, 2 solid (as `View.mode.x`).
    mode: u32,
    solid: [f32; 3],
    lo: f32,
    hi: f32,
    above: f32,
    colour_scalar: Option<usize>,
    filter_scalar: Option<usize>,
    threshold: f32,
}

impl LayerParams {
    pub(crate) fn of(
        colouring: Colouring,
        filter: Option<(usize, f32)>,
        has: impl Fn(usize) -> bool,
    ) -> Self {
        let (mode, solid, lo, hi, above, colour_scalar) = match colouring {
            Colouring::Rgb => (0u32, [0.0; 3], 0.0, 1.0, f32::INFINITY, None),
            Colouring::Map {
                index,
                lo,
                hi,
                above,
            } if has(index) => (1, [0.0; 3], lo, hi, above, Some(index)),
            Colouring::Map { .. } => (2, [0.0; 3], 0.0, 1.0, f32::INFINITY, None),
            Colouring::Solid(c) => (2, c, 0.0, 1.0, f32::INFINITY, None),
        };
        let (filter_scalar, threshold) = match filter {
            Some((i, t)) if has(i) => (Some(i), t),
            _ => (None, 0.0),
        };
        // NaN would compare false everywhere: "no such value" is +∞.
        let above = if above.is_nan() { f32::INFINITY } else { above };
        Self {
            mode,
            solid,
            lo,
            hi,
            above,
            colour_scalar,
            filter_scalar,
            threshold,
        }
    }
}

fn view_uniform(frame: &Frame, origin: DVec3, p: &LayerParams) -> [u8; UNIFORM_BYTES] {
    let offset = (origin - frame.reference).as_vec3();
    let (w, h) = (frame.width.max(1) as f32, frame.height.max(1) as f32);
    let mut f = [0f32; 16 + 16];
    f[..16].copy_from_slice(&frame.view_proj.to_cols_array());
    f[16..20].copy_from_slice(&[offset.x, offset.y, offset.z, frame.point_size.max(0.5)]);
    f[20..24].copy_from_slice(&[w, h, 1.0 / w, 1.0 / h]);
    f[24..28].copy_from_slice(&[p.solid[0], p.solid[1], p.solid[2], 1.0]);
    f[28..32].copy_from_slice(&[p.lo, p.hi, p.threshold, p.above]);
    let mut out = [0u8; UNIFORM_BYTES];
    out[..128].copy_from_slice(bytemuck::cast_slice(&f));
    let m = [
        p.mode,
        p.filter_scalar.is_some() as u32,
        frame.round as u32,
        0,
    ];
    out[128..].copy_from_slice(bytemuck::cast_slice(&m));
    out
}

/// CPU reference of the vertex shader's placement: the pixel (x right, y down, centres at +0.5) where
/// the point `p` (the layer's frame, relative to its origin `origin`) lands, and its depth, or `None`
/// behind the camera.
pub fn project(frame: &Frame, origin: DVec3, p: [f32; 3]) -> Option<([f32; 2], f32)> {
    let rel = Vec3::from_array(p) + (origin - frame.reference).as_vec3();
    let c = frame.view_proj * rel.extend(1.0);
    if c.w <= 0.0 {
        return None;
    }
    let ndc = c.truncate() / c.w;
    let x = (ndc.x * 0.5 + 0.5) * frame.width as f32;
    let y = (0.5 - ndc.y * 0.5) * frame.height as f32;
    Some(([x, y], ndc.z))
}
