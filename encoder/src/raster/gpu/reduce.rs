//! The label-sum records of a band reduced by (Gaussian, label) on the device (`reduce.wgsl`),
//! so that one record per key is read back instead of one per tile: the keys `(label, Gaussian)`
//! of the records sorted by the stable LSD radix sort of [`super::sort`] (4 bits a pass, only
//! the label and Gaussian-id bits the view needs), the first record of each run of equal keys
//! marked and their marks scanned into output slots, and each run's 64-bit fixed-point sums
//! added in integers. The result equals [`crate::raster::LabelSums::reduced`] of the records,
//! bit for bit, in the same (Gaussian, label) order.
//!
//! Buffers, kept across views and grown with the records of a band: the sort's keys (8 B) and
//! values (4 B) twice, its histogram, the run marks (4 B), and the reduced records (16 B): about
//! 44 bytes per record of the band on the device, beside the records' own 16.

use slag_common::Result;

use super::buffers::storage;
use super::sort::{SortBuffers, groups_2d};
use super::{GpuRasterizer, Params, SCAN_BLOCK, SEED_SALT, View};

/// The device buffers of the reduction, kept across views.
pub(super) struct ReduceBuffers {
    sort: SortBuffers,
    /// Run marks, scanned in place into output slots (`n + 1` words, the count of keys last).
    heads: wgpu::Buffer,
    /// The scan's block sums (and overflow flag).
    head_sums: wgpu::Buffer,
    /// One record per distinct key (16 B each).
    reduced: wgpu::Buffer,
    /// Records each buffer holds.
    capacity: u64,
}

/// The bit offsets of the radix passes that order `(label, Gaussian)` keys by (Gaussian, label),
/// least significant first: the bits of labels up to `max_label` (low word), then those of
/// Gaussian ids below `n_gaussians` (high word), 4 a pass.
pub(super) fn record_radix_shifts(max_label: u32, n_gaussians: u32) -> Vec<u32> {
    let bits = |v: u32| 32 - v.leading_zeros();
    let label_bits = bits(max_label);
    let gaussian_bits = bits(n_gaussians.saturating_sub(1));
    (0..label_bits)
        .step_by(4)
        .chain((32..32 + gaussian_bits).step_by(4))
        .collect()
}

impl GpuRasterizer {
    /// `kept` if it holds `n` records, else new buffers for them (plus a quarter).
    fn reduce_buffers(&self, kept: Option<ReduceBuffers>, n: u64) -> ReduceBuffers {
        if let Some(b) = kept
            && b.capacity >= n
        {
            return b;
        }
        let sort = self.sort_buffers(None, n);
        // A band holds at most one binding of records, so this is at least n.
        let capacity = sort.capacity().min(self.max_binding() / 16).max(n);
        let blocks = capacity.div_ceil(u64::from(SCAN_BLOCK));
        ReduceBuffers {
            sort,
            heads: storage(&self.device, "record_heads", (capacity + 1) * 4),
            head_sums: storage(&self.device, "record_head_sums", (blocks + 1) * 4),
            reduced: storage(&self.device, "reduced_records", capacity * 16),
            capacity,
        }
    }

    /// Reduces the `n` label-sum records in `records` (a band's, after the `blend_sums` header)
    /// on the device; returns the buffer holding one record per distinct (Gaussian, label),
    /// sorted (kept for the next band), and their count. `max_label`: the largest pixel label of
    /// the view.
    ///
    /// Errors: device failures.
    pub(super) fn reduce_records(
        &mut self,
        view: &View,
        records: &wgpu::Buffer,
        n: u32,
        max_label: u32,
    ) -> Result<(wgpu::Buffer, u32)> {
        let kept = self.reduce.take();
        let rb = self.reduce_buffers(kept, u64::from(n));
        for (i, b) in rb.sort.keys.iter().chain(&rb.sort.vals).enumerate() {
            self.noise(b, SEED_SALT + 20 + i as u64);
        }
        self.noise(&rb.heads, SEED_SALT + 24);
        self.noise(&rb.reduced, SEED_SALT + 25);
        let shifts = record_radix_shifts(max_label, self.n);
        let radix = self.radix_params(n, &shifts, &view.params);
        let blocks = n.div_ceil(SCAN_BLOCK);
        let params = self.uniform(&Params {
            n_keys: n,
            n_pixels: n,
            n_blocks: blocks,
            ..view.params
        });
        // The sorted keys and record indices end in the buffer the last pass wrote.
        let last = shifts.len() % 2;
        let (keys, vals) = (&rb.sort.keys[last], &rb.sort.vals[last]);
        let p = &self.pipelines;
        let (x, y) = groups_2d(n.div_ceil(256));
        let mut enc = self.device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            let bg = self.bind(
                &p.record_keys,
                &[
                    (0, &params),
                    (13, records),
                    (16, &rb.sort.keys[0]),
                    (17, &rb.sort.vals[0]),
                ],
            );
            pass.set_pipeline(&p.record_keys);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(x, y, 1);
            self.encode_radix_passes(&mut pass, &rb.sort, n, &radix);
            let bg = self.bind(&p.record_heads, &[(0, &params), (8, &rb.heads), (14, keys)]);
            pass.set_pipeline(&p.record_heads);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(x, y, 1);
            self.encode_scan(&mut pass, &params, &rb.heads, &rb.head_sums, blocks);
            let bg = self.bind(
                &p.record_sums,
                &[
                    (0, &params),
                    (8, &rb.heads),
                    (13, records),
                    (14, keys),
                    (15, vals),
                    (20, &rb.reduced),
                ],
            );
            pass.set_pipeline(&p.record_sums);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(x, y, 1);
        }
        let read = self.submit_and_read(enc, &[(&rb.heads, u64::from(n) * 4, 4)])?;
        let reduced = rb.reduced.clone();
        self.reduce = Some(rb);
        // At most n: the scan of n marks of 0 or 1 cannot overflow.
        Ok((reduced, bytemuck::pod_read_unaligned(&read[0][..4])))
    }
}

#[cfg(test)]
mod tests {
    use super::record_radix_shifts;

    #[test]
    fn record_passes_cover_only_the_label_and_gaussian_bits_needed() {
        // Labels up to 3 (2 bits: one pass), Gaussians 0..1000 (10 bits: three passes).
        assert_eq!(record_radix_shifts(3, 1000), vec![0, 32, 36, 40]);
        // Labels up to 16 need a 5th bit; a single Gaussian needs no pass of its own.
        assert_eq!(record_radix_shifts(16, 1), vec![0, 4]);
        // 2M Gaussians (21 bits), 255 labels (8 bits): 2 + 6 passes.
        assert_eq!(record_radix_shifts(255, 2_000_000).len(), 8);
        assert_eq!(record_radix_shifts(u32::MAX, u32::MAX).len(), 16);
    }
}
