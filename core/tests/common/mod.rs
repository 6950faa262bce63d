//! Shared by the GPU kernel tests: a poisoned device.
#![allow(dead_code)]

use silvr_core::gpu::{Gpu, GpuOptions};

/// Written into every buffer a kernel writes before it runs; an element left untouched reads back as this.
pub const POISON: u32 = 0xDEAD_BEEF;

/// A poisoned device, or `None` (test skipped with a message) when there is no adapter and the run does
/// not demand one. The test scripts set `SILVR_REQUIRE_GPU=1`, so CI fails instead of skipping.
pub fn gpu() -> Option<Gpu> {
    match pollster::block_on(Gpu::new(GpuOptions {
        poison: Some(POISON),
        ..Default::default()
    })) {
        Ok(g) => Some(g),
        Err(e) if std::env::var_os("SILVR_REQUIRE_GPU").is_none() => {
            eprintln!("skipping GPU test: {e}");
            None
        }
        Err(e) => panic!("SILVR_REQUIRE_GPU is set but no GPU is usable: {e}"),
    }
}
