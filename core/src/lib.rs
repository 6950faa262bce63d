//! SiLVR Studio engine.
//!
//! One crate that builds natively and for `wasm32-unknown-unknown`, so the browser worker and the native
//! `silvr` binary run the same code and the same WGSL. Modules are named after the parts of the method;
//! dependencies point one way: `geometry` ← `camera` ← `rig` ← `lidar` ← (later) `field`, `render`, …,
//! with `gpu` as the launch layer every kernel module uses.
//!
//! Conventions (stated once, used everywhere):
//! - **Camera frame**: OpenCV — x right, y down, z forward. nerfstudio's OpenGL camera axes (x right, y up,
//!   z back) appear only at the file boundary ([`camera::opencv_to_opengl_c2w`]).
//! - **Pixel centres**: OpenCV/ROS — the centre of the top-left pixel is (0, 0), so the pixel that holds a
//!   projected point (u, v) is `(floor(u + 0.5), floor(v + 0.5))`. COLMAP and nerfstudio place that centre at
//!   (0.5, 0.5); converters add 0.5 to cx, cy when writing those formats.
//! - **Transforms**: `T_a_b` maps points from frame b into frame a (`p_a = T_a_b * p_b`).
//! - **Units**: metres, seconds, radians.

pub mod camera;
pub mod copc;
pub mod dataset;
pub mod eval;
pub mod field;
pub mod geometry;
pub mod gpu;
pub mod ingest;
pub mod job;
#[cfg(not(target_arch = "wasm32"))]
pub mod lasfile;
pub mod lidar;
pub mod odometry;
pub mod pointcloud;
pub mod render;
pub mod rig;
pub mod sampler;
pub mod sfm;
pub mod shaders;
pub mod source;
pub mod submap;
pub mod synthetic;
pub mod train;
pub mod uncertainty;
pub mod viewer;
