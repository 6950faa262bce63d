//! The compute rasteriser (`shaders/points_compute.wgsl`): points drawn without triangles. A software
//! adapter (SwiftShader, lavapipe) spends ~10 µs setting up a point's two triangles; projecting a point and
//! one atomic per covered pixel costs a small fraction of that, and on hardware GPUs the same approach
//! (Schütz et al. 2021/2022) outruns point primitives by an order of magnitude.
//!
//! A frame is: clear the two per-pixel word buffers, a depth pass and a colour pass over every chunk of
//! every layer (the `View` block of each layer at its dynamic offset, as the quad draw), then a resolve
//! pass that copies the words to the colour target. WebGPU has no 64-bit atomics, hence two passes: depth
//! keeps full f32 precision, and equal depths resolve to the larger colour, so a picture never depends on
//! thread order. [`super::reference::rasterise`] is its CPU reference.

use super::{
    clear_to_background, view_binding, view_entry, Frame, LayerDraw, LayerParams, UNIFORM_STRIDE,
};
use crate::gpu::{folded_workgroups, Gpu};
use crate::shaders;

/// Invocations per workgroup (`GROUP` in the shader).
const GROUP: u32 = 256;
/// Points one chunk may hold: a dispatch of one workgroup row (2-D beyond it, see
/// [`folded_workgroups`]) stays well inside the per-dimension limit.
pub const MAX_DISPATCH_POINTS: usize = 1 << 24;

/// The compute rasteriser's pipelines for one target format.
pub struct ComputeRaster {
    depth: wgpu::ComputePipeline,
    colour: wgpu::ComputePipeline,
    resolve: wgpu::RenderPipeline,
    points_layout: wgpu::BindGroupLayout,
    resolve_layout: wgpu::BindGroupLayout,
}

/// The per-pixel words of one target size, and the resolve pass's bindings of them.
pub struct Words {
    width: u32,
    height: u32,
    depth: wgpu::Buffer,
    colour: wgpu::Buffer,
    resolve_uniform: wgpu::Buffer,
    resolve_bind: wgpu::BindGroup,
}

fn storage(
    binding: u32,
    read_only: bool,
    visibility: wgpu::ShaderStages,
) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

fn whole(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buffer.as_entire_binding(),
    }
}

impl ComputeRaster {
    /// Builds the pipelines (errors surface through the caller's validation scope).
    pub(super) fn new(gpu: &Gpu, format: wgpu::TextureFormat) -> Self {
        let device = &gpu.device;
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("points compute"),
            source: wgpu::ShaderSource::Wgsl(shaders::POINTS_COMPUTE.into()),
        });
        let cs = wgpu::ShaderStages::COMPUTE;
        let points_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("points compute"),
            entries: &[
                view_entry(cs),
                storage(1, true, cs),
                storage(2, true, cs),
                storage(3, true, cs),
                storage(4, true, cs),
                storage(5, false, cs),
                storage(6, false, cs),
            ],
        });
        let fs = wgpu::ShaderStages::FRAGMENT;
        let resolve_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("points resolve"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 7,
                    visibility: fs,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                },
                storage(8, true, fs),
                storage(9, true, fs),
            ],
        });
        let layout_of = |label, bind: &wgpu::BindGroupLayout| {
            device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some(label),
                bind_group_layouts: &[Some(bind)],
                immediate_size: 0,
            })
        };
        let points = layout_of("points compute", &points_layout);
        let pass = |entry: &str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: Some(&points),
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let (depth, colour) = (pass("depth_pass"), pass("colour_pass"));
        let resolve = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("points resolve"),
            layout: Some(&layout_of("points resolve", &resolve_layout)),
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some("resolve_vs"),
                compilation_options: Default::default(),
                buffers: &[],
            },
            primitive: Default::default(),
            depth_stencil: None,
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &module,
                entry_point: Some("resolve_fs"),
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
        Self {
            depth,
            colour,
            resolve,
            points_layout,
            resolve_layout,
        }
    }

    /// The words for a `width` × `height` target, or `None` where one word per pixel exceeds the
    /// adapter's storage-binding limit (the caller then draws quads). Their contents are undefined
    /// (poisoned in tests): every frame clears them.
    pub(super) fn words(&self, gpu: &Gpu, width: u32, height: u32) -> Option<Words> {
        let pixels = width as usize * height as usize;
        let depth = gpu.output("view depth words", pixels).ok()?;
        let colour = gpu.output("view colour words", pixels).ok()?;
        let resolve_uniform = gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("points resolve"),
            size: 32,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let resolve_bind = gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("points resolve"),
            layout: &self.resolve_layout,
            entries: &[
                whole(7, &resolve_uniform),
                whole(8, &depth),
                whole(9, &colour),
            ],
        });
        Some(Words {
            width,
            height,
            depth,
            colour,
            resolve_uniform,
            resolve_bind,
        })
    }

    /// Records one frame of `layers` into `encoder`: clear, depth pass, colour pass, resolve to `target`.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn encode(
        &self,
        gpu: &Gpu,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        words: &Words,
        uniforms: &wgpu::Buffer,
        frame: &Frame,
        layers: &[LayerDraw<'_>],
    ) {
        debug_assert_eq!((frame.width, frame.height), (words.width, words.height));
        encoder.clear_buffer(&words.depth, 0, None);
        encoder.clear_buffer(&words.colour, 0, None);
        // One bind group per chunk, used by both passes.
        let mut work = Vec::new();
        for (k, d) in layers.iter().enumerate() {
            let p = LayerParams::of(d.colouring, d.filter, |i| d.layer.has_scalar(i));
            for c in &d.layer.chunks {
                let bind = gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("points compute"),
                    layout: &self.points_layout,
                    entries: &[
                        view_binding(uniforms),
                        whole(1, &c.positions),
                        whole(2, &c.colours),
                        whole(3, c.scalar(p.colour_scalar)),
                        whole(4, c.scalar(p.filter_scalar)),
                        whole(5, &words.depth),
                        whole(6, &words.colour),
                    ],
                });
                work.push(((k as u64 * UNIFORM_STRIDE) as u32, bind, c.points));
            }
        }
        for pipeline in [&self.depth, &self.colour] {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("points compute"),
                timestamp_writes: None,
            });
            pass.set_pipeline(pipeline);
            for (offset, bind, points) in &work {
                pass.set_bind_group(0, bind, &[*offset]);
                let (x, y) = folded_workgroups(*points, GROUP);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        let [r, g, b] = frame.background;
        let mut block = [0u8; 32];
        block[..16].copy_from_slice(bytemuck::cast_slice(&[r as f32, g as f32, b as f32, 1.0]));
        block[16..20].copy_from_slice(&words.width.to_le_bytes());
        gpu.queue.write_buffer(&words.resolve_uniform, 0, &block);
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("points resolve"),
            color_attachments: &[Some(clear_to_background(target, frame))],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&self.resolve);
        pass.set_bind_group(0, &words.resolve_bind, &[]);
        pass.draw(0..3, 0..1);
    }
}
