//! Adapter and device acquisition, with a report of what we got and clear errors when we get nothing.

use std::collections::HashMap;
use std::fmt;
use std::sync::{Arc, Mutex};

use serde::Serialize;

use super::profile::{ProfileMode, Profiler, ProfilerState, MAX_QUERIES};

/// The limits every SiLVR kernel is written against: WebGPU's defaults, which every browser grants.
/// Storage-buffer sizes are raised to what the adapter offers at device creation.
pub const BASELINE: Baseline = Baseline {
    max_compute_invocations_per_workgroup: 256,
    max_compute_workgroup_storage_size: 16 * 1024,
    max_storage_buffers_per_shader_stage: 8,
    max_bind_groups: 4,
    max_compute_workgroups_per_dimension: 65_535,
    max_storage_buffer_binding_size: 128 << 20,
};

/// The subset of [`wgpu::Limits`] SiLVR depends on (see [`BASELINE`]).
#[derive(Clone, Copy, Debug)]
pub struct Baseline {
    pub max_compute_invocations_per_workgroup: u32,
    pub max_compute_workgroup_storage_size: u32,
    pub max_storage_buffers_per_shader_stage: u32,
    pub max_bind_groups: u32,
    pub max_compute_workgroups_per_dimension: u32,
    pub max_storage_buffer_binding_size: u64,
}

/// Everything that can go wrong between asking for a GPU and reading a result back.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error("no GPU adapter found (backends tried: {backends}). {hint}")]
    NoAdapter { backends: String, hint: String },
    #[error(
        "GPU adapter '{adapter}' is too limited: {limit} is {have}, SiLVR needs at least {need}"
    )]
    LimitsTooSmall {
        adapter: String,
        limit: &'static str,
        have: u64,
        need: u64,
    },
    #[error("could not open a device on GPU adapter '{adapter}': {detail}")]
    RequestDevice { adapter: String, detail: String },
    #[error("kernel '{kernel}' failed on the GPU: {detail}")]
    Kernel { kernel: String, detail: String },
    #[error(
        "{what} needs a {bytes}-byte GPU buffer, but this device allows at most {max} bytes per binding \
         (its max_storage_buffer_binding_size)"
    )]
    BufferTooLarge { what: String, bytes: u64, max: u64 },
    #[error("reading a GPU buffer back failed: {0}")]
    Readback(String),
    #[error(
        "the GPU device on '{adapter}' was lost ({reason}); the work in flight is gone. Open a new device \
         and resume from the last checkpoint (`silvr train ... --resume CHECKPOINT`)"
    )]
    DeviceLost { adapter: String, reason: String },
    #[error(
        "the GPU on '{adapter}' ran out of memory allocating {what} ({bytes} bytes; the device allows \
         {max_buffer} bytes per buffer): use fewer rays per batch or a smaller model"
    )]
    OutOfMemory {
        adapter: String,
        what: String,
        bytes: u64,
        max_buffer: u64,
    },
    #[error("invalid input for a GPU kernel: {0}")]
    InvalidInput(String),
}

/// How to choose an adapter.
#[derive(Clone, Debug, Default)]
pub struct GpuOptions {
    /// Backends to try natively; `None` honours `WGPU_BACKEND` and otherwise tries Vulkan, Metal and DX12.
    pub backends: Option<wgpu::Backends>,
    /// Refuse software adapters (lavapipe, SwiftShader, WARP).
    pub require_hardware: bool,
    /// Fill every buffer a kernel writes with this 32-bit pattern before it runs. Tests set it so that a
    /// kernel which forgets to write an element is caught, instead of being hidden by zero-initialised memory.
    pub poison: Option<u32>,
    /// Time every compute pass (see [`super::profile`]): timestamp queries where the adapter has them,
    /// otherwise timed submits (native only). For benchmarks; it costs a query pair or a wait per pass.
    pub profile: bool,
    /// Run the loop form of kernels that lavapipe otherwise runs as straight-line code (see
    /// [`Gpu::straight_line_kernels`]): the tests check both forms on the one adapter CI has.
    pub loop_kernels: bool,
}

/// What adapter we run on, for logs, the CLI's `gpu-info`, the studio page and benchmark records.
#[derive(Clone, Debug, Serialize, serde::Deserialize)]
pub struct AdapterReport {
    pub name: String,
    pub backend: String,
    pub device_type: String,
    pub driver: String,
    pub driver_info: String,
    /// True for CPU rasterisers (lavapipe, SwiftShader, WARP): correct but about 10x slower than plain Rust.
    pub software: bool,
    pub max_storage_buffer_binding_size: u64,
    pub max_buffer_size: u64,
    pub max_compute_workgroup_storage_size: u32,
    pub max_compute_invocations_per_workgroup: u32,
}

impl fmt::Display for AdapterReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} ({} backend, {}{}, driver {} {})",
            self.name,
            self.backend,
            self.device_type,
            if self.software { ", software" } else { "" },
            self.driver,
            self.driver_info
        )
    }
}

/// A device, its queue, and the pipelines built on it so far.
#[derive(Clone)]
pub struct Gpu {
    /// The instance and adapter the device came from: a canvas surface must be made by the same ones.
    pub instance: wgpu::Instance,
    pub adapter: wgpu::Adapter,
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    report: Arc<AdapterReport>,
    pub(super) poison: Option<u32>,
    straight: bool,
    pub(super) pipelines: Arc<Mutex<HashMap<String, wgpu::ComputePipeline>>>,
    pub(super) profiler: Profiler,
    /// Set by the device-lost callback: why the device went away.
    pub(super) lost: Arc<Mutex<Option<String>>>,
}

impl fmt::Debug for Gpu {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Gpu")
            .field("adapter", &*self.report)
            .finish()
    }
}

impl Gpu {
    /// Finds an adapter and opens a device with the limits SiLVR's kernels need.
    pub async fn new(options: GpuOptions) -> Result<Self, GpuError> {
        let instance = make_instance(&options);
        let backends = describe_backends(&options);
        let adapter = instance
            .request_adapter(&wgpu::RequestAdapterOptions {
                power_preference: wgpu::PowerPreference::HighPerformance,
                ..Default::default()
            })
            .await
            .map_err(|e| GpuError::NoAdapter {
                backends: backends.clone(),
                hint: format!("{} ({e})", no_adapter_hint()),
            })?;
        let report = report_for(&adapter);
        if options.require_hardware && report.software {
            return Err(GpuError::NoAdapter {
                backends,
                hint: format!(
                    "only the software adapter '{}' is present and a hardware GPU was required",
                    report.name
                ),
            });
        }
        let have = adapter.limits();
        check_baseline(&report.name, &have)?;
        // Large scenes need big storage buffers: take what the adapter offers. Workgroup memory too: the
        // kernels fit the 16 KiB baseline, and only a native fast path (mlp::record_inference on lavapipe)
        // stages more where the device has it.
        let limits = wgpu::Limits {
            max_storage_buffer_binding_size: have.max_storage_buffer_binding_size,
            max_buffer_size: have.max_buffer_size,
            max_compute_workgroup_storage_size: have.max_compute_workgroup_storage_size,
            ..Default::default()
        };
        let timestamps =
            options.profile && adapter.features().contains(wgpu::Features::TIMESTAMP_QUERY);
        let required_features = if timestamps {
            wgpu::Features::TIMESTAMP_QUERY
        } else {
            wgpu::Features::empty()
        };
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("silvr"),
                required_features,
                required_limits: limits,
                ..Default::default()
            })
            .await
            .map_err(|e| GpuError::RequestDevice {
                adapter: report.name.clone(),
                detail: e.to_string(),
            })?;
        device.on_uncaptured_error(Arc::new(|e| {
            log::error!("uncaptured wgpu error: {e}");
        }));
        let lost = Arc::new(Mutex::new(None));
        let flag = lost.clone();
        device.set_device_lost_callback(move |reason, message| {
            if let Ok(mut l) = flag.lock() {
                *l = Some(format!("{reason:?}: {message}"));
            }
        });
        let profiler = match (options.profile, timestamps) {
            (false, _) => None,
            (true, true) => {
                let qs = device.create_query_set(&wgpu::QuerySetDescriptor {
                    label: Some("profile"),
                    ty: wgpu::QueryType::Timestamp,
                    count: MAX_QUERIES,
                });
                Some(ProfilerState::new(ProfileMode::Timestamps, Some(qs)))
            }
            (true, false) if cfg!(not(target_arch = "wasm32")) => {
                Some(ProfilerState::new(ProfileMode::TimedSubmits, None))
            }
            (true, false) => None,
        };
        Ok(Self {
            instance,
            adapter,
            device,
            queue,
            straight: !options.loop_kernels
                && report.software
                && (report.driver.contains("llvmpipe") || report.name.contains("llvmpipe")),
            report: Arc::new(report),
            poison: options.poison,
            pipelines: Arc::new(Mutex::new(HashMap::new())),
            profiler: Arc::new(Mutex::new(profiler)),
            lost,
        })
    }

    /// Whether kernels should run their inner products as straight-line code (the MLP's, generated per
    /// layer shape): on lavapipe, which broadcasts a lane-uniform workgroup load only outside control flow
    /// (measured 1.4-2x faster per MLP pass there). Elsewhere loops: hardware GPUs unroll them themselves,
    /// and the straight-line code is untested on them.
    pub fn straight_line_kernels(&self) -> bool {
        self.straight
    }

    /// The adapter this device was opened on.
    pub fn report(&self) -> &AdapterReport {
        &self.report
    }

    /// How passes are timed, when this device was opened with [`GpuOptions::profile`].
    pub fn profiling(&self) -> Option<ProfileMode> {
        self.profiler
            .lock()
            .expect("profiler poisoned")
            .as_ref()
            .map(|p| p.mode)
    }

    /// Names the part of the work the next passes belong to (a no-op unless profiling).
    pub fn profile_scope(&self, scope: &str) {
        if let Some(p) = self.profiler.lock().expect("profiler poisoned").as_mut() {
            if p.scope != scope {
                p.scope = scope.to_string();
            }
        }
    }

    /// The passes timed since the last call (timestamps are resolved at each readback), in first-seen
    /// order; the totals start again from zero.
    pub fn profile_take(&self) -> Vec<super::profile::PassRow> {
        match self.profiler.lock().expect("profiler poisoned").as_mut() {
            Some(p) => {
                let rows = p.rows();
                p.totals.clear();
                rows
            }
            None => Vec::new(),
        }
    }

    /// [`GpuError::DeviceLost`] once the device has been lost (driver reset, out of memory, destroyed).
    pub fn check_lost(&self) -> Result<(), GpuError> {
        // Natively the lost callback runs from device maintenance: let it.
        #[cfg(not(target_arch = "wasm32"))]
        let _ = self.device.poll(wgpu::PollType::Poll);
        match self.lost.lock().ok().and_then(|l| l.clone()) {
            Some(reason) => Err(GpuError::DeviceLost {
                adapter: self.report.name.clone(),
                reason,
            }),
            None => Ok(()),
        }
    }

    /// Largest storage binding this device accepts, in bytes.
    pub fn max_binding_bytes(&self) -> u64 {
        self.report.max_storage_buffer_binding_size
    }
}

#[cfg(not(target_arch = "wasm32"))]
fn make_instance(options: &GpuOptions) -> wgpu::Instance {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
    desc.backends = match options.backends {
        Some(b) => b,
        None => wgpu::Backends::from_env()
            .unwrap_or(wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12),
    };
    wgpu::Instance::new(desc)
}

#[cfg(target_arch = "wasm32")]
fn make_instance(_options: &GpuOptions) -> wgpu::Instance {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::BROWSER_WEBGPU;
    wgpu::Instance::new(desc)
}

fn describe_backends(options: &GpuOptions) -> String {
    if cfg!(target_arch = "wasm32") {
        return "WebGPU".into();
    }
    match options.backends {
        Some(b) => format!("{b:?}"),
        None => std::env::var("WGPU_BACKEND").unwrap_or_else(|_| "Vulkan, Metal, DX12".into()),
    }
}

fn no_adapter_hint() -> &'static str {
    if cfg!(target_arch = "wasm32") {
        "This browser exposes no WebGPU adapter: use a recent Chrome/Edge (or Chromium with \
         --enable-unsafe-webgpu), or Firefox/Safari with WebGPU enabled."
    } else {
        "Install a Vulkan driver; without a GPU, Mesa's lavapipe CPU driver works \
         (Debian/Ubuntu: `apt-get install mesa-vulkan-drivers`). Set WGPU_BACKEND to choose a backend."
    }
}

fn report_for(adapter: &wgpu::Adapter) -> AdapterReport {
    let info = adapter.get_info();
    let limits = adapter.limits();
    let name_lc = info.name.to_lowercase();
    let software = info.device_type == wgpu::DeviceType::Cpu
        || name_lc.contains("llvmpipe")
        || name_lc.contains("swiftshader")
        || name_lc.contains("lavapipe")
        || name_lc.contains("warp");
    AdapterReport {
        name: if info.name.is_empty() {
            "unnamed adapter".into()
        } else {
            info.name.clone()
        },
        backend: format!("{:?}", info.backend),
        device_type: format!("{:?}", info.device_type),
        driver: info.driver.clone(),
        driver_info: info.driver_info.clone(),
        software,
        max_storage_buffer_binding_size: limits.max_storage_buffer_binding_size,
        max_buffer_size: limits.max_buffer_size,
        max_compute_workgroup_storage_size: limits.max_compute_workgroup_storage_size,
        max_compute_invocations_per_workgroup: limits.max_compute_invocations_per_workgroup,
    }
}

/// Names the first limit below [`BASELINE`], so the user learns which one and by how much.
pub(crate) fn check_baseline(adapter: &str, have: &wgpu::Limits) -> Result<(), GpuError> {
    let checks: [(&'static str, u64, u64); 6] = [
        (
            "max_compute_invocations_per_workgroup",
            have.max_compute_invocations_per_workgroup.into(),
            BASELINE.max_compute_invocations_per_workgroup.into(),
        ),
        (
            "max_compute_workgroup_storage_size",
            have.max_compute_workgroup_storage_size.into(),
            BASELINE.max_compute_workgroup_storage_size.into(),
        ),
        (
            "max_storage_buffers_per_shader_stage",
            have.max_storage_buffers_per_shader_stage.into(),
            BASELINE.max_storage_buffers_per_shader_stage.into(),
        ),
        (
            "max_bind_groups",
            have.max_bind_groups.into(),
            BASELINE.max_bind_groups.into(),
        ),
        (
            "max_compute_workgroups_per_dimension",
            have.max_compute_workgroups_per_dimension.into(),
            BASELINE.max_compute_workgroups_per_dimension.into(),
        ),
        (
            "max_storage_buffer_binding_size",
            have.max_storage_buffer_binding_size,
            BASELINE.max_storage_buffer_binding_size,
        ),
    ];
    for (limit, have, need) in checks {
        if have < need {
            return Err(GpuError::LimitsTooSmall {
                adapter: adapter.to_string(),
                limit,
                have,
                need,
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn baseline_rejects_small_limits_by_name() {
        let mut limits = wgpu::Limits::default();
        assert!(check_baseline("x", &limits).is_ok());
        limits.max_compute_invocations_per_workgroup = 128;
        let err = check_baseline("tiny", &limits).unwrap_err().to_string();
        assert!(
            err.contains("max_compute_invocations_per_workgroup"),
            "{err}"
        );
        assert!(
            err.contains("128") && err.contains("256") && err.contains("tiny"),
            "{err}"
        );
    }
}
