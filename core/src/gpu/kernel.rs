//! Launching WGSL kernels: cached pipelines, bind groups from buffer lists, folded dispatches and async
//! readback. Each kernel module describes its WGSL with a [`Kernel`] and calls these helpers; none of them
//! blocks in the browser.

use bytemuck::Pod;
use wgpu::util::DeviceExt;

use super::context::{Gpu, GpuError};

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
        let key = format!("{}::{entry}", kernel.name);
        if let Some(p) = self
            .pipelines
            .lock()
            .expect("pipeline cache poisoned")
            .get(&key)
        {
            return Ok(p.clone());
        }
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(kernel.name),
                source: wgpu::ShaderSource::Wgsl(kernel.source.into()),
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
        Ok(self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: &contents,
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
            }))
    }

    /// A uniform buffer holding one `T`.
    pub fn uniform<T: Pod>(&self, label: &str, value: &T) -> wgpu::Buffer {
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytemuck::bytes_of(value),
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            })
    }

    /// A storage buffer a kernel writes, `words` 32-bit words long. Its contents are undefined to the
    /// kernel: with [`GpuOptions::poison`](super::GpuOptions::poison) set they are that pattern, so a
    /// kernel must write (or clear) every element it later reads or returns.
    pub fn output(&self, label: &str, words: usize) -> Result<wgpu::Buffer, GpuError> {
        let bytes = (words.max(1) * 4) as u64;
        self.check_size(label, bytes)?;
        match self.poison {
            Some(pattern) => {
                Ok(self
                    .device
                    .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                        label: Some(label),
                        contents: bytemuck::cast_slice(&vec![pattern; words.max(1)]),
                        usage: wgpu::BufferUsages::STORAGE
                            | wgpu::BufferUsages::COPY_SRC
                            | wgpu::BufferUsages::COPY_DST,
                    }))
            }
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
        let pipeline = self.pipeline(kernel, entry).await?;
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
            return Err(GpuError::Kernel {
                kernel: format!("{}::{entry}", kernel.name),
                detail: err.to_string(),
            });
        }
        let (x, y) = folded_workgroups(invocations, kernel.workgroup_size);
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(entry),
            timestamp_writes: None,
        });
        pass.set_pipeline(&pipeline);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.dispatch_workgroups(x, y, 1);
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
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        self.queue.submit([encoder.finish()]);
        let mut receivers = Vec::with_capacity(staging.len());
        for (s, _) in &staging {
            let (tx, rx) = futures_channel::oneshot::channel();
            s.map_async(wgpu::MapMode::Read, .., move |r| {
                let _ = tx.send(r);
            });
            receivers.push(rx);
        }
        if let Some(err) = scope.pop().await {
            return Err(GpuError::Kernel {
                kernel: "submit".into(),
                detail: err.to_string(),
            });
        }
        #[cfg(not(target_arch = "wasm32"))]
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        let mut out = Vec::with_capacity(staging.len());
        for ((s, count), rx) in staging.iter().zip(receivers) {
            rx.await
                .map_err(|_| GpuError::Readback("the device dropped the map request".into()))?
                .map_err(|e| GpuError::Readback(e.to_string()))?;
            let view = s
                .get_mapped_range(..)
                .map_err(|e| GpuError::Readback(e.to_string()))?;
            let mut v: Vec<T> = bytemuck::pod_collect_to_vec(&view[..(*count * elem as usize)]);
            v.truncate(*count);
            drop(view);
            s.unmap();
            out.push(v);
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
