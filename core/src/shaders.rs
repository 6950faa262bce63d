//! The hand-written WGSL, embedded at compile time from the workspace's `shaders/` folder so the native
//! binary and the wasm worker carry byte-identical kernels.

/// Lidar point → camera pixel projection with a nearest-range z-buffer (`lidar::project`).
pub const PROJECT_ZBUFFER: &str = include_str!("../../shaders/project_zbuffer.wgsl");

/// Multi-resolution hash-grid encoding, forward and backward (`field::hashgrid`).
pub const HASHGRID: &str = include_str!("../../shaders/hashgrid.wgsl");
