//! The hand-written WGSL, embedded at compile time from the workspace's `shaders/` folder so the native
//! binary and the wasm worker carry byte-identical kernels.

/// Lidar point → camera pixel projection with a nearest-range z-buffer (`lidar::project`).
pub const PROJECT_ZBUFFER: &str = include_str!("../../shaders/project_zbuffer.wgsl");

/// Multi-resolution hash-grid encoding, forward and backward (`field::hashgrid`).
pub const HASHGRID: &str = include_str!("../../shaders/hashgrid.wgsl");

/// Per-ray volume rendering and the SiLVR ray losses, forward and backward (`render`).
pub const RENDER: &str = include_str!("../../shaders/render.wgsl");

/// Small fully-connected MLP (nerfacto's density and colour heads), forward and backward (`field::mlp`).
pub const MLP: &str = include_str!("../../shaders/mlp.wgsl");

/// nerfacto's proposal sampling, field glue, sampler losses, gradient plumbing and Adam (`train::gpu`).
pub const TRAIN: &str = include_str!("../../shaders/train.wgsl");

/// The uncertainty pass: render Jacobians, position gradients to world space, Fisher accumulation
/// (`uncertainty::gpu`).
pub const UNCERTAINTY: &str = include_str!("../../shaders/uncertainty.wgsl");

/// The studio's point-cloud view, drawn as instanced screen-space quads (`viewer`, the reference draw):
/// the view block, colour maps and uncertainty threshold it shares with the compute rasteriser, then its
/// vertex and fragment shaders.
pub const POINTS: &str = concat!(
    include_str!("../../shaders/points_common.wgsl"),
    include_str!("../../shaders/points.wgsl")
);

/// The studio's compute rasteriser (`viewer::compute`): the same shared block, then the depth, colour and
/// resolve passes.
pub const POINTS_COMPUTE: &str = concat!(
    include_str!("../../shaders/points_common.wgsl"),
    include_str!("../../shaders/points_compute.wgsl")
);
