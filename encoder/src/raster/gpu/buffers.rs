//! Device buffers of the weight rasterizer: storage allocation, the reused write-pass outputs
//! with their staging twins, readback (submit, map, copy out) and the noise fill of tests.

use std::sync::mpsc;

use slag_common::rng::SplitMix64;
use slag_common::{Error, Resource, Result};
use wgpu::util::DeviceExt;

use super::{GpuRasterizer, gpu_err};

/// A uniform buffer holding `params` (a kernel's parameter block).
pub(super) fn uniform_init<T: bytemuck::Pod>(
    device: &wgpu::Device,
    label: &str,
    params: &T,
) -> wgpu::Buffer {
    device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(label),
        contents: bytemuck::bytes_of(params),
        usage: wgpu::BufferUsages::UNIFORM,
    })
}

pub(super) fn storage_init(device: &wgpu::Device, label: &str, data: &[u8]) -> wgpu::Buffer {
    // Bindings must be non-empty and hold one array element: pad empty data to 64 bytes.
    let pad = [0u8; 64];
    let contents = if data.is_empty() { &pad[..] } else { data };
    device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(label),
        contents,
        usage: wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_SRC
            | wgpu::BufferUsages::COPY_DST,
    })
}

/// The overflow flag of a scan (`scan.wgsl`: the word after the block sums, read back as
/// `flag`): non-zero is [`Error::Limit`] `RasterEntries` for `what`, past `limit`.
pub(super) fn scan_overflow(flag: &[u8], what: String, limit: &str) -> Result<()> {
    if flag.iter().take(4).any(|&b| b != 0) {
        return Err(Error::limit(Resource::RasterEntries, what, limit));
    }
    Ok(())
}

pub(super) fn storage(device: &wgpu::Device, label: &str, size: u64) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: size.max(64).next_multiple_of(4),
        usage: wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_SRC
            | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

/// Deterministic pseudo-random bytes (splitmix64), for the noise fill.
fn noise_bytes(seed: u64, len: usize) -> Vec<u8> {
    let mut rng = SplitMix64::new(seed);
    let mut out = Vec::with_capacity(len + 8);
    while out.len() < len {
        out.extend_from_slice(&rng.next_u64().to_le_bytes());
    }
    out.truncate(len);
    out
}

/// The write pass's output buffers (ids, weights) and their `MAP_READ` staging twins, reused
/// across views so that a view neither allocates (and zero-fills) ~8 bytes per entry on the
/// device nor maps fresh host memory: each view's weights are copied once, from the mapped
/// staging range straight into the returned [`PixelWeights`].
pub(super) struct OutBuffers {
    pub(super) ids: wgpu::Buffer,
    pub(super) weights: wgpu::Buffer,
    pub(super) stage_ids: wgpu::Buffer,
    pub(super) stage_weights: wgpu::Buffer,
    /// Bytes each of the four holds.
    pub(super) capacity: u64,
}

/// Appends the little-endian `T`s in `bytes` to `dst` (one copy when `bytes` is aligned for `T`,
/// as mapped ranges are; element by element otherwise).
pub(super) fn extend_pod<T: bytemuck::Pod>(dst: &mut Vec<T>, bytes: &[u8]) {
    match bytemuck::try_cast_slice::<u8, T>(bytes) {
        Ok(s) => dst.extend_from_slice(s),
        Err(_) => dst.extend(
            bytes
                .chunks_exact(std::mem::size_of::<T>())
                .map(bytemuck::pod_read_unaligned::<T>),
        ),
    }
}

impl GpuRasterizer {
    pub(super) fn noise(&self, buf: &wgpu::Buffer, salt: u64) {
        if let Some(seed) = self.noise_seed {
            let bytes = noise_bytes(
                seed ^ salt.wrapping_mul(0x2545_F491_4F6C_DD1D),
                buf.size() as usize,
            );
            self.queue.write_buffer(buf, 0, &bytes);
        }
    }

    pub(super) fn bind(
        &self,
        pipeline: &wgpu::ComputePipeline,
        entries: &[(u32, &wgpu::Buffer)],
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry<'_>> = entries
            .iter()
            .map(|(b, buf)| wgpu::BindGroupEntry {
                binding: *b,
                resource: buf.as_entire_binding(),
            })
            .collect();
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        })
    }

    /// Submits `encoder` after adding copies of `(buffer, byte offset, byte size)` into staging
    /// buffers, waits, and returns the bytes of each.
    pub(super) fn submit_and_read(
        &self,
        mut encoder: wgpu::CommandEncoder,
        reads: &[(&wgpu::Buffer, u64, u64)],
    ) -> Result<Vec<Vec<u8>>> {
        let staging: Vec<wgpu::Buffer> = reads
            .iter()
            .map(|&(src, off, size)| {
                let size = size.max(4).next_multiple_of(4);
                let dst = self.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("readback"),
                    size,
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                });
                let copy = size.min(src.size() - off);
                encoder.copy_buffer_to_buffer(src, off, &dst, 0, copy);
                dst
            })
            .collect();
        let mut out = Vec::with_capacity(reads.len());
        let mapped: Vec<(&wgpu::Buffer, u64)> = staging
            .iter()
            .zip(reads)
            .map(|(buf, &(_, _, size))| (buf, size))
            .collect();
        self.submit_and_map(encoder, &mapped, |_, bytes| out.push(bytes.to_vec()))?;
        Ok(out)
    }

    /// `kept` if it holds `bytes`, else new write-pass buffers of `bytes` plus a quarter (at
    /// most `limit`), so views of similar size reuse them.
    pub(super) fn out_buffers(
        &self,
        kept: Option<OutBuffers>,
        bytes: u64,
        limit: u64,
    ) -> OutBuffers {
        if let Some(o) = kept
            && o.capacity >= bytes
            && o.capacity <= limit.max(bytes)
        {
            return o;
        }
        let capacity = (bytes + bytes / 4)
            .min(limit.max(bytes))
            .next_multiple_of(4);
        let staging = |label| {
            self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: capacity,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        OutBuffers {
            ids: storage(&self.device, "out_ids", capacity),
            weights: storage(&self.device, "out_weights", capacity),
            stage_ids: staging("readback_ids"),
            stage_weights: staging("readback_weights"),
            capacity,
        }
    }

    /// Submits `enc` (which ends with the copies into `out`'s staging buffers), waits, and
    /// appends the first `bytes` of each staging buffer to `ids` / `weights`.
    pub(super) fn read_entries(
        &self,
        enc: wgpu::CommandEncoder,
        out: &OutBuffers,
        bytes: u64,
        ids: &mut Vec<u32>,
        weights: &mut Vec<f32>,
    ) -> Result<()> {
        let staged = [(&out.stage_ids, bytes), (&out.stage_weights, bytes)];
        self.submit_and_map(enc, &staged, |i, view| {
            if i == 0 {
                extend_pod(ids, view);
            } else {
                extend_pod(weights, view);
            }
        })
    }

    /// Submits `enc` (which ends with copies into the `MAP_READ` buffers of `staged`), waits, and
    /// hands the first `bytes` of each staged buffer to `visit(index, bytes)`, then unmaps them.
    pub(super) fn submit_and_map(
        &self,
        enc: wgpu::CommandEncoder,
        staged: &[(&wgpu::Buffer, u64)],
        mut visit: impl FnMut(usize, &[u8]),
    ) -> Result<()> {
        self.submit_and_map_all(enc, staged, |views| {
            for (i, view) in views.iter().enumerate() {
                visit(i, view);
            }
        })
    }

    /// As [`Self::submit_and_map`], but hands the first `bytes` of every staged buffer to
    /// `visit` at once (outputs read together), returning what it returns.
    pub(super) fn submit_and_map_all<R>(
        &self,
        enc: wgpu::CommandEncoder,
        staged: &[(&wgpu::Buffer, u64)],
        visit: impl FnOnce(&[&[u8]]) -> R,
    ) -> Result<R> {
        self.queue.submit([enc.finish()]);
        let range = |bytes: u64| ..bytes.max(4).next_multiple_of(4);
        let (tx, rx) = mpsc::channel();
        for &(buf, bytes) in staged {
            let tx = tx.clone();
            buf.slice(range(bytes))
                .map_async(wgpu::MapMode::Read, move |r| {
                    let _ = tx.send(r);
                });
        }
        drop(tx);
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| gpu_err("waiting for the rasterizer kernels failed", e))?;
        for r in rx.iter() {
            r.map_err(|e| gpu_err("reading back rasterizer output failed", e))?;
        }
        let out = {
            let views = staged
                .iter()
                .map(|&(buf, bytes)| buf.slice(range(bytes)).get_mapped_range())
                .collect::<std::result::Result<Vec<_>, _>>()
                .map_err(|e| gpu_err("mapping rasterizer output failed", e))?;
            let slices: Vec<&[u8]> = views
                .iter()
                .zip(staged)
                .map(|(view, &(_, bytes))| &view[..bytes as usize])
                .collect();
            visit(&slices)
        };
        for &(buf, _) in staged {
            buf.unmap();
        }
        Ok(out)
    }
}
