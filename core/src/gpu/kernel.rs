//! Launching WGSL kernels: cached pipelines, bind groups from buffer lists, folded dispatches and async
//! readback. Each kernel module describes its WGSL with a [`Kernel`] and calls these helpers; none of them
//! blocks in the browser.

use bytemuck::Pod;

use super::context::{Gpu, GpuError};
use super::profile::{ProfileMode, MAX_QUERIES};

/// WebGPU's `maxComputeWorkgroupsPerDimension` default; larger dispatches are folded into 2-D.
pub const MAX_WORKGROUPS_PER_DIM: u32 = 65_535;

/// A WGSL module and the workgroup size its entry points were written for.
///
/// Every entry point recovers its linear invocation index from a possibly folded dispatch as
/// `(wg.y * nwg.x + wg.x) * WORKGROUP + local_index` and bounds-checks it against its element count.
#[derive(Clone, Copy, Debug)]
pub struct Kernel {
    pub name: &'static str,
    pub source: &'static str,
    pub workgroup_size: u32,
}

/// The kernel's WGSL. Debug builds read `$SILVR_SHADER_DIR/<name>.wgsl` instead when that variable is set,
/// so kernel work can iterate on a shader without rebuilding the engine; release builds always run the
/// embedded copy.
fn kernel_source(kernel: &Kernel) -> std::borrow::Cow<'static, str> {
    #[cfg(all(debug_assertions, not(target_arch = "wasm32")))]
    if let Some(dir) = std::env::var_os("SILVR_SHADER_DIR") {
        let path = std::path::Path::new(&dir).join(format!("{}.wgsl", kernel.name));
        if let Ok(s) = std::fs::read_to_string(&path) {
            return s.into();
        }
    }
    kernel.source.into()
}

/// Workgroup counts for `invocations` threads, folded into (x, y) when x would exceed the per-dimension limit.
pub fn folded_workgroups(invocations: u32, workgroup_size: u32) -> (u32, u32) {
    let groups = invocations.div_ceil(workgroup_size).max(1);
    if groups <= MAX_WORKGROUPS_PER_DIM {
        (groups, 1)
    } else {
        (
            MAX_WORKGROUPS_PER_DIM,
            groups.div_ceil(MAX_WORKGROUPS_PER_DIM),
        )
    }
}

impl Gpu {
    /// The compute pipeline for `kernel`'s `entry`, compiled once per device. WGSL errors come back as
    /// [`GpuError::Kernel`] (not a panic) thanks to an error scope around the compile.
    pub async fn pipeline(
        &self,
        kernel: &Kernel,
        entry: &str,
    ) -> Result<wgpu::ComputePipeline, GpuError> {
        self.pipeline_variant(kernel, "", entry).await
    }

    /// [`Self::pipeline`] for the module compiled with `prelude` (WGSL `const` declarations, see
    /// [`Kernel`]) in front of its source: one pipeline per distinct prelude, so kernels specialised to
    /// a layer's shape get constant loop bounds (unrolled, private arrays in registers).
    pub async fn pipeline_variant(
        &self,
        kernel: &Kernel,
        prelude: &str,
        entry: &str,
    ) -> Result<wgpu::ComputePipeline, GpuError> {
        let key = format!("{}::{entry}{prelude}", kernel.name);
        if let Some(p) = self
            .pipelines
            .lock()
            .expect("pipeline cache poisoned")
            .get(&key)
        {
            return Ok(p.clone());
        }
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let source = format!("{prelude}{}", kernel_source(kernel));
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(kernel.name),
                source: wgpu::ShaderSource::Wgsl(source.into()),
            });
        let pipeline = self
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(&key),
                layout: None,
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            });
        if let Some(err) = scope.pop().await {
            return Err(GpuError::Kernel {
                kernel: key,
                detail: err.to_string(),
            });
        }
        self.pipelines
            .lock()
            .expect("pipeline cache poisoned")
            .insert(key, pipeline.clone());
        Ok(pipeline)
    }

    /// A read-only storage buffer holding `data` (at least 4 bytes, as WebGPU forbids empty bindings).
    pub fn upload<T: Pod>(&self, label: &str, data: &[T]) -> Result<wgpu::Buffer, GpuError> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        self.check_size(label, bytes.len() as u64)?;
        let contents: Vec<u8> = if bytes.is_empty() {
            vec![0; 4]
        } else {
            bytes.to_vec()
        };
        Ok(self.buffer_with(
            label,
            &contents,
            wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
        ))
    }

    /// A buffer holding `contents` (a multiple of 4 bytes), written through the queue rather than mapped
    /// at creation: on a lost device wgpu's mapped-at-creation path panics, this one lets the next
    /// submit or readback report the loss.
    pub(crate) fn buffer_with(
        &self,
        label: &str,
        contents: &[u8],
        usage: wgpu::BufferUsages,
    ) -> wgpu::Buffer {
        let size = (contents.len() as u64).next_multiple_of(4).max(4);
        let b = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage: usage | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        if !contents.is_empty() {
            self.queue.write_buffer(&b, 0, contents);
        }
        b
    }

    /// A uniform buffer holding one `T`.
    pub fn uniform<T: Pod>(&self, label: &str, value: &T) -> wgpu::Buffer {
        self.buffer_with(
            label,
            bytemuck::bytes_of(value),
            wgpu::BufferUsages::UNIFORM,
        )
    }

    /// A storage buffer a kernel writes, `words` 32-bit words long. Its contents are undefined to the
    /// kernel: with [`GpuOptions::poison`](super::GpuOptions::poison) set they are that pattern, so a
    /// kernel must write (or clear) every element it later reads or returns.
    pub fn output(&self, label: &str, words: usize) -> Result<wgpu::Buffer, GpuError> {
        let bytes = (words.max(1) * 4) as u64;
        self.check_size(label, bytes)?;
        match self.poison {
            Some(pattern) => Ok(self.buffer_with(
                label,
                bytemuck::cast_slice(&vec![pattern; words.max(1)]),
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            )),
            None => Ok(self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes,
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })),
        }
    }

    fn check_size(&self, what: &str, bytes: u64) -> Result<(), GpuError> {
        let max = self.max_binding_bytes();
        if bytes > max {
            return Err(GpuError::BufferTooLarge {
                what: what.to_string(),
                bytes,
                max,
            });
        }
        Ok(())
    }

    /// Records one dispatch of `entry` over `invocations` threads. `bindings` pairs group-0 binding numbers
    /// with buffers; list exactly the bindings this entry point uses (pipeline layouts are derived from
    /// the WGSL, so unused bindings are not part of them).
    pub async fn dispatch(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        kernel: &Kernel,
        entry: &str,
        bindings: &[(u32, &wgpu::Buffer)],
        invocations: u32,
    ) -> Result<(), GpuError> {
        self.dispatch_variant(encoder, kernel, "", entry, bindings, invocations)
            .await
    }

    /// [`Self::dispatch`] of the module specialised by `prelude` (see [`Self::pipeline_variant`]).
    pub async fn dispatch_variant(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        kernel: &Kernel,
        prelude: &str,
        entry: &str,
        bindings: &[(u32, &wgpu::Buffer)],
        invocations: u32,
    ) -> Result<(), GpuError> {
        let pipeline = self.pipeline_variant(kernel, prelude, entry).await?;
        let layout = pipeline.get_bind_group_layout(0);
        let entries: Vec<wgpu::BindGroupEntry> = bindings
            .iter()
            .map(|(i, b)| wgpu::BindGroupEntry {
                binding: *i,
                resource: b.as_entire_binding(),
            })
            .collect();
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let bind_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(entry),
            layout: &layout,
            entries: &entries,
        });
        if let Some(err) = scope.pop().await {
            self.check_lost()?;
            return Err(GpuError::Kernel {
                kernel: format!("{}::{entry}", kernel.name),
                detail: err.to_string(),
            });
        }
        let (x, y) = folded_workgroups(invocations, kernel.workgroup_size);
        let record =
            |encoder: &mut wgpu::CommandEncoder,
             timestamps: Option<wgpu::ComputePassTimestampWrites<'_>>| {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some(entry),
                    timestamp_writes: timestamps,
                });
                pass.set_pipeline(&pipeline);
                pass.set_bind_group(0, &bind_group, &[]);
                pass.dispatch_workgroups(x, y, 1);
            };
        let mut guard = self.profiler.lock().expect("profiler poisoned");
        let Some(prof) = guard.as_mut() else {
            drop(guard);
            record(encoder, None);
            return Ok(());
        };
        let key = (prof.scope.clone(), format!("{}::{entry}", kernel.name));
        let bytes: u64 = bindings.iter().map(|(_, b)| b.size()).sum();
        match prof.mode {
            ProfileMode::Timestamps => {
                let i = 2 * prof.pending.len() as u32;
                match prof.query_set.clone() {
                    Some(qs) if i + 2 <= MAX_QUERIES => {
                        prof.pending.push((key, bytes));
                        drop(guard);
                        record(
                            encoder,
                            Some(wgpu::ComputePassTimestampWrites {
                                query_set: &qs,
                                beginning_of_pass_write_index: Some(i),
                                end_of_pass_write_index: Some(i + 1),
                            }),
                        );
                    }
                    // More passes than queries before a readback: this one goes untimed.
                    _ => {
                        drop(guard);
                        record(encoder, None);
                    }
                }
            }
            ProfileMode::TimedSubmits => {
                drop(guard);
                #[cfg(not(target_arch = "wasm32"))]
                {
                    // Finish what came before, then time this pass alone.
                    let before = std::mem::replace(encoder, self.encoder("profiled"));
                    self.queue.submit([before.finish()]);
                    self.device
                        .poll(wgpu::PollType::wait_indefinitely())
                        .map_err(|e| GpuError::Readback(e.to_string()))?;
                    let t = std::time::Instant::now();
                    record(encoder, None);
                    let this = std::mem::replace(encoder, self.encoder("profiled"));
                    self.queue.submit([this.finish()]);
                    self.device
                        .poll(wgpu::PollType::wait_indefinitely())
                        .map_err(|e| GpuError::Readback(e.to_string()))?;
                    let s = t.elapsed().as_secs_f64();
                    if let Some(p) = self.profiler.lock().expect("profiler poisoned").as_mut() {
                        p.add(key, s, bytes);
                    }
                }
                #[cfg(target_arch = "wasm32")]
                {
                    let _ = key;
                    record(encoder, None);
                }
            }
        }
        Ok(())
    }

    /// A fresh command encoder.
    pub fn encoder(&self, label: &str) -> wgpu::CommandEncoder {
        self.device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) })
    }

    /// Copies `buffers` to the host after the work in `encoder` and returns them as `T`s, in order.
    /// One submit, one map per buffer, awaited without blocking the browser.
    pub async fn finish_and_read<T: Pod>(
        &self,
        mut encoder: wgpu::CommandEncoder,
        buffers: &[(&wgpu::Buffer, usize)],
    ) -> Result<Vec<Vec<T>>, GpuError> {
        self.check_lost()?;
        let elem = std::mem::size_of::<T>() as u64;
        let mut staging = Vec::with_capacity(buffers.len());
        for (buffer, count) in buffers {
            let bytes = (*count as u64 * elem).max(4).next_multiple_of(4);
            let s = self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("readback"),
                size: bytes,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            encoder.copy_buffer_to_buffer(buffer, 0, &s, 0, bytes.min(buffer.size()));
            staging.push((s, *count));
        }
        // Profiling: resolve the timestamps of the passes recorded since the last readback.
        let timed = {
            let mut guard = self.profiler.lock().expect("profiler poisoned");
            match guard.as_mut() {
                Some(p) if !p.pending.is_empty() => {
                    let qs = p.query_set.clone().expect("timestamp mode has a query set");
                    let n = 2 * p.pending.len() as u32;
                    let bytes = n as u64 * 8;
                    let resolve = self.device.create_buffer(&wgpu::BufferDescriptor {
                        label: Some("profile resolve"),
                        size: bytes,
                        usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                        mapped_at_creation: false,
                    });
                    let read = self.device.create_buffer(&wgpu::BufferDescriptor {
                        label: Some("profile readback"),
                        size: bytes,
                        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                        mapped_at_creation: false,
                    });
                    encoder.resolve_query_set(&qs, 0..n, &resolve, 0);
                    encoder.copy_buffer_to_buffer(&resolve, 0, &read, 0, bytes);
                    Some((read, std::mem::take(&mut p.pending)))
                }
                _ => None,
            }
        };
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        self.queue.submit([encoder.finish()]);
        let timed_rx = timed.map(|(read, passes)| {
            let (tx, rx) = futures_channel::oneshot::channel();
            read.map_async(wgpu::MapMode::Read, .., move |r| {
                let _ = tx.send(r);
            });
            (read, passes, rx)
        });
        let mut receivers = Vec::with_capacity(staging.len());
        for (s, _) in &staging {
            let (tx, rx) = futures_channel::oneshot::channel();
            s.map_async(wgpu::MapMode::Read, .., move |r| {
                let _ = tx.send(r);
            });
            receivers.push(rx);
        }
        if let Some(err) = scope.pop().await {
            self.check_lost()?;
            return Err(GpuError::Kernel {
                kernel: "submit".into(),
                detail: err.to_string(),
            });
        }
        #[cfg(not(target_arch = "wasm32"))]
        if let Err(e) = self.device.poll(wgpu::PollType::wait_indefinitely()) {
            self.check_lost()?;
            return Err(GpuError::Readback(e.to_string()));
        }
        let mut out = Vec::with_capacity(staging.len());
        for ((s, count), rx) in staging.iter().zip(receivers) {
            let mapped = rx
                .await
                .map_err(|_| GpuError::Readback("the device dropped the map request".into()))
                .and_then(|r| r.map_err(|e| GpuError::Readback(e.to_string())));
            if mapped.is_err() {
                self.check_lost()?;
            }
            mapped?;
            let view = s
                .get_mapped_range(..)
                .map_err(|e| GpuError::Readback(e.to_string()))?;
            let mut v: Vec<T> = bytemuck::pod_collect_to_vec(&view[..(*count * elem as usize)]);
            v.truncate(*count);
            drop(view);
            s.unmap();
            out.push(v);
        }
        if let Some((read, passes, rx)) = timed_rx {
            rx.await
                .map_err(|_| GpuError::Readback("the device dropped the map request".into()))?
                .map_err(|e| GpuError::Readback(e.to_string()))?;
            let ticks: Vec<u64> = {
                let view = read
                    .get_mapped_range(..)
                    .map_err(|e| GpuError::Readback(e.to_string()))?;
                bytemuck::pod_collect_to_vec(&view[..])
            };
            read.unmap();
            let period = self.queue.get_timestamp_period() as f64 * 1e-9;
            if let Some(p) = self.profiler.lock().expect("profiler poisoned").as_mut() {
                for (k, (key, bytes)) in passes.into_iter().enumerate() {
                    let dt = ticks[2 * k + 1].saturating_sub(ticks[2 * k]) as f64 * period;
                    p.add(key, dt, bytes);
                }
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn folding_covers_every_invocation() {
        assert_eq!(folded_workgroups(0, 64), (1, 1));
        assert_eq!(folded_workgroups(64, 64), (1, 1));
        assert_eq!(folded_workgroups(65, 64), (2, 1));
        let n = 65_535 * 64 + 1;
        let (x, y) = folded_workgroups(n, 64);
        assert_eq!((x, y), (65_535, 2));
        assert!(x as u64 * y as u64 * 64 >= n as u64);
        let (x, y) = folded_workgroups(u32::MAX, 256);
        assert!(x <= MAX_WORKGROUPS_PER_DIM && y <= MAX_WORKGROUPS_PER_DIM);
        assert!(x as u64 * y as u64 * 256 >= u32::MAX as u64);
    }
}
