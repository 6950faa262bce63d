//! Shared by the GPU kernel tests: a poisoned device; and by every test of core: the one way to skip.
#![allow(dead_code)]

mod skip;
pub use skip::skip;

use rand::{Rng, SeedableRng};
use silvr_core::field::model::{ModelConfig, Params};
use silvr_core::gpu::{Gpu, GpuOptions};
use silvr_core::render::RayTarget;
use silvr_core::train::cpu::{Batch, TrainRay};

/// Written into every buffer a kernel writes before it runs; an element left untouched reads back as this.
pub const POISON: u32 = 0xDEAD_BEEF;

/// A poisoned device, or `None` (the test skips, see [`skip`]) when there is no adapter and the run does
/// not demand one. The test scripts set `SILVR_REQUIRE_GPU=1`, so CI fails instead of skipping.
pub fn gpu() -> Option<Gpu> {
    gpu_with(GpuOptions {
        poison: Some(POISON),
        ..Default::default()
    })
}

/// [`gpu`] with other options (e.g. the loop form of the kernels, or profiling).
pub fn gpu_with(options: GpuOptions) -> Option<Gpu> {
    match pollster::block_on(Gpu::new(options)) {
        Ok(g) => Some(g),
        Err(e) => {
            skip("SILVR_REQUIRE_GPU", &format!("no usable GPU: {e}"));
            None
        }
    }
}

/// The tiny model with parameters randomised well past their init (so densities and colours vary along
/// rays), and a batch of `r` random rays with every kind of target (lidar, normals, sky, held-out).
pub fn setup(seed: u64, r: usize) -> (ModelConfig, Params, Batch) {
    let cfg = ModelConfig::tiny();
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed);
    let mut params = Params::init(&cfg, seed).unwrap();
    for t in &mut params.tensors {
        for v in t.iter_mut() {
            *v += rng.random_range(-0.3..0.3f32);
        }
    }
    let rays: Vec<TrainRay> = (0..r)
        .map(|i| {
            let d = [
                rng.random_range(-1.0..1.0f32),
                rng.random_range(-1.0..1.0),
                1.0,
            ];
            let l = (d[0] * d[0] + d[1] * d[1] + 1.0).sqrt();
            TrainRay {
                origin: [
                    rng.random_range(-0.3..0.3),
                    rng.random_range(-0.3..0.3),
                    -0.5,
                ],
                dir: d.map(|v| v / l),
                // Every fourth ray is a held-out view's (the mean embedding).
                appearance: if i % 4 == 3 { u32::MAX } else { (i % 3) as u32 },
            }
        })
        .collect();
    let targets: Vec<RayTarget> = (0..r)
        .map(|i| RayTarget {
            rgb: [rng.random(), rng.random(), rng.random()],
            depth: if i % 5 < 3 {
                rng.random_range(0.5..1.5)
            } else {
                0.0
            },
            normal: if i < r / 3 {
                [rng.random_range(-1.0..1.0), 0.3, -1.0]
            } else {
                [0.0; 3]
            },
            sky: (i % 5 == 4) as u32,
        })
        .collect();
    let batch = Batch {
        rays,
        targets,
        jitter: (0..r * 3).map(|_| rng.random()).collect(),
        normal_rays: r / 3,
    };
    (cfg, params, batch)
}

/// The Python of scripts/setup.sh's virtual environment (`SILVR_PYTHON`, else ~/.cache/silvr-venv) when it
/// can import `modules` (comma-separated, as in a Python `import`), or a skip that fails under
/// `SILVR_REQUIRE_PEERS=1` (scripts/test.sh).
pub fn peer_python(modules: &str) -> Option<std::path::PathBuf> {
    let py = std::env::var_os("SILVR_PYTHON")
        .map(std::path::PathBuf::from)
        .or_else(|| {
            let home = std::env::var_os("HOME")?;
            Some(std::path::PathBuf::from(home).join(".cache/silvr-venv/bin/python"))
        })?;
    let ok = std::process::Command::new(&py)
        .args(["-c", &format!("import {modules}")])
        .status()
        .is_ok_and(|s| s.success());
    if ok {
        return Some(py);
    }
    skip(
        "SILVR_REQUIRE_PEERS",
        &format!(
            "{} cannot import {modules} (scripts/setup.sh installs them)",
            py.display()
        ),
    );
    None
}

/// Runs `python args...` and parses its stdout as JSON, failing with its stderr.
pub fn python_json(py: &std::path::Path, args: &[&std::ffi::OsStr]) -> serde_json::Value {
    let out = std::process::Command::new(py).args(args).output().unwrap();
    assert!(
        out.status.success(),
        "python {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}
