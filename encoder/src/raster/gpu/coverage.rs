//! The coverage pass on the device (`coverage.wgsl`): which Gaussians a view sees, without
//! reading back any weight.
//!
//! The label-sum path would make one record per tile intersection, radix-sort the records by
//! Gaussian on the device and read back 16 bytes per Gaussian the view shows (hundreds of MB a
//! view at 30M Gaussians), for the host to keep only those at the floor. Here the tile sums go
//! straight into a per-Gaussian 64-bit total (`blend_totals`), the floor is applied on the device
//! (`coverage_seen`), and a view reads back one bit per Gaussian. The largest total of a view that
//! saw each Gaussian stays on the device across views and is read once, at the end of the pass
//! ([`GpuRasterizer::read_coverage_maxima`]).
//!
//! The totals are the same integers as the view's label sums with every pixel in one label: the
//! same fixed point (`w·2^32` truncated per pixel, summed per tile with carry), and integer sums
//! do not depend on the order the tiles add them in.

use slag_common::camera::{Intrinsics, WorldToCamera};
use slag_common::{Error, Result};

use super::buffers::storage;
use super::sort::groups_2d;
use super::{Binned, GpuRasterizer, View, lap};

/// The pass's buffers, kept across its views: per Gaussian the current view's total and the
/// running maximum (two u32 words each), the seen bitset and its `MAP_READ` twin.
pub(super) struct CoverageBuffers {
    totals: wgpu::Buffer,
    maxima: wgpu::Buffer,
    bits: wgpu::Buffer,
    staging: wgpu::Buffer,
    /// Bytes of the bitset: 4 per 32 Gaussians, rounded up to whole u64 words.
    bits_bytes: u64,
}

impl CoverageBuffers {
    /// Zeroed buffers for `n` Gaussians (wgpu zero-fills new buffers).
    fn new(device: &wgpu::Device, n: u32) -> Self {
        let n = u64::from(n);
        let bits_bytes = n.div_ceil(64).max(1) * 8;
        CoverageBuffers {
            totals: storage(device, "coverage_totals", n.max(1) * 8),
            maxima: storage(device, "coverage_maxima", n.max(1) * 8),
            bits: storage(device, "coverage_bits", bits_bytes),
            staging: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("readback_coverage_bits"),
                size: bits_bytes,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            bits_bytes,
        }
    }
}

impl GpuRasterizer {
    /// One view of the coverage pass: steps 1–2 as any view, then the totals and the floor on the
    /// device. Returns the Gaussians whose total blend weight reaches `floor` (64-bit fixed point,
    /// `2^32` = one raster pixel; 0 counts as 1: a Gaussian must contribute), as a bitset over the
    /// scene: bit `k % 64` of word `k / 64`.
    ///
    /// Errors: as [`Self::project_and_bin`]; device failures.
    pub(super) fn run_coverage(
        &mut self,
        k: &Intrinsics,
        w2c: &WorldToCamera,
        floor: u64,
    ) -> Result<Vec<u64>> {
        let (mut view, binned, mut timings, mut clock) = self.project_and_bin(k, w2c)?;
        let floor = floor.max(1);
        view.params.floor_lo = floor as u32;
        view.params.floor_hi = (floor >> 32) as u32;
        self.write_params(&view);
        let seen = self.coverage_pass(&view, &binned)?;
        timings.write_ms = lap(&mut clock);
        timings.host_ms = timings.bin_sort_ms;
        self.timings = timings;
        Ok(seen)
    }

    /// Dispatch step: clears the totals and the bitset, runs `blend_totals` over every tile and
    /// `coverage_seen` over every Gaussian, and reads back the bitset.
    fn coverage_pass(&mut self, view: &View, b: &Binned) -> Result<Vec<u64>> {
        let cov = match self.coverage.take() {
            Some(c) => c,
            None => CoverageBuffers::new(&self.device, self.n),
        };
        let mut enc = self.device.create_command_encoder(&Default::default());
        enc.clear_buffer(&cov.totals, 0, None);
        enc.clear_buffer(&cov.bits, 0, None);
        {
            let totals = self.bind(
                &self.pipelines.blend_totals,
                &[
                    (0, &view.params_buf),
                    (4, &self.splats),
                    (6, &b.ranges),
                    (7, &b.sorted_ids),
                    (21, &cov.totals),
                ],
            );
            let seen = self.bind(
                &self.pipelines.coverage_seen,
                &[
                    (0, &view.params_buf),
                    (21, &cov.totals),
                    (22, &cov.maxima),
                    (23, &cov.bits),
                ],
            );
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipelines.blend_totals);
            pass.set_bind_group(0, &totals, &[]);
            pass.dispatch_workgroups(view.tiles_x, view.tiles_y, 1);
            let groups = self.n.div_ceil(256);
            if groups > 0 {
                let (x, y) = groups_2d(groups);
                pass.set_pipeline(&self.pipelines.coverage_seen);
                pass.set_bind_group(0, &seen, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        enc.copy_buffer_to_buffer(&cov.bits, 0, &cov.staging, 0, cov.bits_bytes);
        let mut words = Vec::new();
        self.submit_and_map(enc, &[(&cov.staging, cov.bits_bytes)], |_, bytes| {
            words = bytemuck::pod_collect_to_vec(bytes);
        })?;
        self.coverage = Some(cov);
        Ok(words)
    }

    /// The running maxima of the coverage pass's views since the last call: per Gaussian the
    /// largest total (fixed point, as [`Self::run_coverage`]) of a view that saw it, 0 when none
    /// did. The pass's buffers are freed (`16 B` per Gaussian), so the next view starts from 0.
    ///
    /// Errors: device failures.
    pub(super) fn read_coverage_maxima(&mut self) -> Result<Vec<u64>> {
        let Some(cov) = self.coverage.take() else {
            return Ok(vec![0; self.n as usize]);
        };
        let bytes = u64::from(self.n) * 8;
        if bytes == 0 {
            return Ok(Vec::new());
        }
        let enc = self.device.create_command_encoder(&Default::default());
        let read = self.submit_and_read(enc, &[(&cov.maxima, 0, bytes)])?;
        let words: &[u8] = read
            .first()
            .ok_or_else(|| Error::internal("coverage maxima: no readback"))?;
        Ok(bytemuck::pod_collect_to_vec(&words[..bytes as usize]))
    }
}
