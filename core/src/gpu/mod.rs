//! The GPU context and the small kernel-launch layer every WGSL kernel goes through.
//!
//! One async API serves the native binary (Vulkan/Metal/DX12, Mesa's lavapipe when there is no GPU) and the
//! browser worker (WebGPU). Nothing here blocks on the web: readbacks await a `map_async` callback; natively
//! the same future drives the device with `poll`, which is the only way wgpu makes progress there.
//!
//! Kernels are written for the browser's baseline (see [`BASELINE`]): ≤256 invocations per workgroup,
//! 16 KiB workgroup memory, ≤8 storage buffers per stage, ≤4 bind groups, no f16, no subgroups, float atomics
//! as compare-exchange loops, and dispatches folded into 2-D above 65 535 workgroups.

mod context;
mod kernel;
pub mod profile;

pub use context::{AdapterReport, Gpu, GpuError, GpuOptions, BASELINE};
pub use kernel::{folded_workgroups, Kernel, MAX_WORKGROUPS_PER_DIM};
pub use profile::{PassRow, ProfileMode};
/// Re-exported so callers name backends and buffers without depending on wgpu themselves.
pub use wgpu::{self, Backends};
