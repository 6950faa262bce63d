//! Which engine a command runs on (`--backend auto|wgpu|cpu`), and the per-pass profile table: shared by
//! `silvr train`, `silvr bench-train` and `silvr uncertainty` (so those two modules need not import each
//! other).

use anyhow::{bail, Context, Result};
use silvr_core::gpu::{Gpu, GpuOptions};
use silvr_core::train::Backend;

/// `--backend`: `wgpu` forces the WGSL engine (on any adapter, lavapipe included), `cpu` the rayon
/// reference; `auto` takes the WGSL engine on a hardware GPU and the CPU reference where the only adapter
/// is a software one (on lavapipe a WGSL training step takes ~1.8x the CPU reference's, BENCHMARKS.md).
pub fn backend_for(backend: &str) -> Result<(Backend, String)> {
    backend_with(backend, GpuOptions::default())
}

/// [`backend_for`] with the device opened with `options` (e.g. profiling).
pub fn backend_with(backend: &str, options: GpuOptions) -> Result<(Backend, String)> {
    let open = || {
        pollster::block_on(Gpu::new(options.clone()))
            .context("--backend wgpu needs a WebGPU adapter")
    };
    match backend {
        "cpu" => Ok((Backend::Cpu, "cpu (rayon)".into())),
        "wgpu" => {
            let g = open()?;
            let name = g.report().to_string();
            Ok((Backend::Wgpu(g), name))
        }
        "auto" => match pollster::block_on(Gpu::new(options.clone())) {
            Ok(g) if !g.report().software => {
                let name = g.report().to_string();
                Ok((Backend::Wgpu(g), name))
            }
            Ok(g) => Ok((
                Backend::Cpu,
                format!(
                    "cpu (rayon; the only adapter, {}, is software)",
                    g.report().name
                ),
            )),
            Err(e) => Ok((Backend::Cpu, format!("cpu (rayon; no GPU adapter: {e})"))),
        },
        o => bail!("unknown backend {o:?} (auto, wgpu, cpu)"),
    }
}

/// Prints profiled passes per step (of `steps`) as a table on stderr, and returns them as JSON rows.
pub fn print_profile(
    rows: &[silvr_core::gpu::PassRow],
    steps: u32,
    wall_s: f64,
) -> Vec<serde_json::Value> {
    let steps = steps.max(1);
    let total: f64 = rows.iter().map(|r| r.seconds).sum::<f64>() / steps as f64;
    eprintln!(
        "{:.1} ms wall, {:.1} ms in passes, per step",
        wall_s / steps as f64 * 1e3,
        total * 1e3
    );
    eprintln!(
        "{:<22} {:<32} {:>6} {:>10} {:>6} {:>10}",
        "scope", "pass", "calls", "ms/step", "%", "MB bound"
    );
    let mut out = Vec::new();
    for r in rows {
        let ms = r.seconds / steps as f64 * 1e3;
        let mb = r.bytes_bound as f64 / steps as f64 / 1e6;
        eprintln!(
            "{:<22} {:<32} {:>6} {:>10.2} {:>6.1} {:>10.1}",
            r.scope,
            r.pass,
            r.calls / steps as u64,
            ms,
            100.0 * r.seconds / steps as f64 / total.max(1e-12),
            mb
        );
        out.push(serde_json::json!({
            "scope": r.scope, "pass": r.pass, "calls_per_step": r.calls as f64 / steps as f64,
            "ms_per_step": ms, "mb_bound_per_step": mb,
        }));
    }
    out
}
