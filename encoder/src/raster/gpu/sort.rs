//! Step 2, tile binning and the depth sort on the device (`sort.wgsl`, with the scan kernels of
//! `scan.wgsl`): every (Gaussian, tile) intersection gets the 64-bit key `tile << 32 | f32 depth
//! bits` and its Gaussian id as value, emitted in id order after an exclusive prefix sum of the
//! Gaussians' tile counts; a stable LSD radix sort (4 bits a pass: the depth's 32 bits, then only
//! the tile-id bits the view's grid needs) orders them by (tile, depth), equal f32 depths by id;
//! the tile ranges are found on the device. Only the total number of intersections (one u32,
//! with an overflow flag) is read back, to size the sort buffers; the host's share is the f32
//! sort depths ([`sort_depths`], 4 bytes per Gaussian, made ahead on the encoder's prepare thread
//! through [`SortDepthsAhead`]) and recording the passes.
//!
//! The depth is the host's f64 camera-frame depth rounded to f32 (uploaded per view, 4 bytes a
//! Gaussian), so the order equals the host reference's ([`super::project::bin_and_sort`], the
//! same keys) exactly, and the CPU rasterizer's.
//!
//! Buffers, per view (grown when a view needs more, then kept): keys `8 B` and values `4 B` per
//! intersection, twice (ping-pong), each a single binding, so a view's intersections are at most
//! `max_storage_buffer_binding_size / 8` ([`Error::Limit`] `GpuBinding` beyond); the radix
//! histogram `64 B` per 1024 intersections; the tile ranges `8 B` per tile.

use std::sync::Arc;

use rayon::prelude::*;
use slag_common::Result;
use slag_common::camera::WorldToCamera;

use super::super::project::camera_point;
use super::super::{PrecomputedView, ViewPrecompute};
use super::buffers::{scan_overflow, storage};
use super::{Binned, GROUPS_X, GpuRasterizer, Params, SCAN_BLOCK, SEED_SALT, View};

/// `[N]` sort depths of `means` in the view `w2c`: [`camera_point`]'s f64 depth, clamped at 0,
/// rounded to f32 (one f64 multiply-add per Gaussian and axis, in parallel), the key of
/// [`super::project::bin_and_sort`] and of the CPU rasterizer. (The kernel's own f32 `t.z` can be
/// a few f32 steps off the f64 value, and a two-float evaluation in WGSL is not safe from the
/// drivers' algebraic rewriting.)
pub(super) fn sort_depths(means: &[[f32; 3]], w2c: &WorldToCamera) -> Vec<f32> {
    means
        .par_iter()
        .map(|m| camera_point(m.map(f64::from), w2c).z.max(0.0) as f32)
        .collect()
}

/// The GPU rasterizer's [`ViewPrecompute`]: a view's sort depths, made on the caller's thread.
pub(super) struct SortDepthsAhead {
    pub(super) means: Arc<Vec<[f32; 3]>>,
}

impl ViewPrecompute for SortDepthsAhead {
    fn precompute(&self, w2c: &WorldToCamera) -> PrecomputedView {
        PrecomputedView {
            world_to_camera: *w2c,
            sort_depths: sort_depths(&self.means, w2c),
        }
    }
}

/// Keys per workgroup of the radix passes (`RADIX_BLOCK` in sort.wgsl).
const RADIX_BLOCK: u32 = 1024;
/// Digits per radix pass (4 bits).
const RADIX_DIGITS: u32 = 16;
/// Bytes of one key (depth bits, tile id).
const KEY_BYTES: u64 = 8;

/// The sort's key and value buffers (ping-pong pairs) and the radix histogram with its scan's
/// block sums, kept across views.
pub(super) struct SortBuffers {
    pub(super) keys: [wgpu::Buffer; 2],
    pub(super) vals: [wgpu::Buffer; 2],
    hist: wgpu::Buffer,
    hist_sums: wgpu::Buffer,
    /// Intersections each key / value buffer holds.
    capacity: u64,
}

/// The bit offsets of the radix passes of a view with `n_tiles` tiles, least significant first:
/// 8 passes over the depth's 32 bits, then `⌈bits(n_tiles − 1) / 4⌉` over the tile id (none for
/// a single tile).
pub(super) fn radix_shifts(n_tiles: u32) -> Vec<u32> {
    let tile_bits = 32 - n_tiles.saturating_sub(1).leading_zeros();
    (0..32 + tile_bits).step_by(4).collect()
}

/// A 2D dispatch of `groups` workgroups (x at most [`GROUPS_X`]).
pub(super) fn groups_2d(groups: u32) -> (u32, u32) {
    (groups.min(GROUPS_X), groups.div_ceil(GROUPS_X))
}

impl SortBuffers {
    /// Keys (and values) each buffer holds.
    pub(super) fn capacity(&self) -> u64 {
        self.capacity
    }
}

impl GpuRasterizer {
    /// A uniform buffer holding `p`.
    pub(super) fn uniform(&self, p: &Params) -> wgpu::Buffer {
        super::buffers::uniform_init(&self.device, "params", p)
    }

    /// Records the exclusive scan (`scan.wgsl`) of `data[0..params.n_pixels]` in place, total to
    /// `data[n_pixels]`, overflow flag to `sums[params.n_blocks]`.
    pub(super) fn encode_scan(
        &self,
        pass: &mut wgpu::ComputePass<'_>,
        params: &wgpu::Buffer,
        data: &wgpu::Buffer,
        sums: &wgpu::Buffer,
        n_blocks: u32,
    ) {
        let entries = [(0, params), (8, data), (11, sums)];
        let (gx, gy) = groups_2d(n_blocks);
        let p = &self.pipelines;
        for (pipe, (x, y)) in [
            (&p.scan_local, (gx, gy)),
            (&p.scan_blocks, (1, 1)),
            (&p.scan_add, (gx, gy)),
        ] {
            if x > 0 {
                let bg = self.bind(pipe, &entries);
                pass.set_pipeline(pipe);
                pass.set_bind_group(0, &bg, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
    }

    /// The view's sort depths ([`sort_depths`]) queued for upload (4 bytes per Gaussian): those
    /// made ahead on another thread ([`WeightRasterizer::label_sums_precomputed`]) when they are
    /// this view's, else computed here.
    pub(super) fn upload_sort_depths(&mut self, w2c: &WorldToCamera) {
        let ahead = self.precomputed.take();
        if self.n > 0 {
            let depths = match ahead {
                Some(p) if p.world_to_camera == *w2c && p.sort_depths.len() == self.means.len() => {
                    p.sort_depths
                }
                _ => sort_depths(&self.means, w2c),
            };
            self.queue
                .write_buffer(&self.sort_depths, 0, bytemuck::cast_slice(&depths));
        }
    }

    /// Step 1 and the count of step 2: the projection kernel (splats, tile rects and every
    /// Gaussian's tile count), the exclusive scan of the counts, and the readback of their total
    /// (the view's intersections: 8 bytes with the overflow flag).
    ///
    /// Errors: 2^32 − 1 or more intersections ([`Error::Limit`] `RasterEntries`); device failures.
    pub(super) fn project_count(&self, view: &View) -> Result<u32> {
        let n_blocks = self.n.div_ceil(SCAN_BLOCK);
        let params = self.uniform(&Params {
            n_pixels: self.n,
            n_blocks,
            ..view.params
        });
        self.noise(&self.tile_counts, SEED_SALT + 16);
        let mut enc = self.device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            let groups = self.n.div_ceil(256);
            if groups > 0 {
                let bg = self.bind(
                    &self.pipelines.project,
                    &[
                        (0, &params),
                        (1, &self.means_opac),
                        (2, &self.scales),
                        (3, &self.quats),
                        (4, &self.splats),
                        (5, &self.isect),
                        (8, &self.tile_counts),
                        (19, &self.sort_depths),
                    ],
                );
                let (x, y) = groups_2d(groups);
                pass.set_pipeline(&self.pipelines.project);
                pass.set_bind_group(0, &bg, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
            self.encode_scan(
                &mut pass,
                &params,
                &self.tile_counts,
                &self.tile_count_sums,
                n_blocks,
            );
        }
        let read = self.submit_and_read(
            enc,
            &[
                (&self.tile_counts, u64::from(self.n) * 4, 4),
                (&self.tile_count_sums, u64::from(n_blocks) * 4, 4),
            ],
        )?;
        scan_overflow(
            &read[1],
            format!(
                "2^32 - 1 or more tile intersections in the {}x{} view",
                view.k.width, view.k.height
            ),
            "2^32 - 1",
        )?;
        Ok(bytemuck::pod_read_unaligned(&read[0][..4]))
    }

    /// `kept` if it holds `keys` intersections, else new sort buffers for them plus a quarter
    /// (at most one binding).
    pub(super) fn sort_buffers(&self, kept: Option<SortBuffers>, keys: u64) -> SortBuffers {
        if let Some(b) = kept
            && b.capacity >= keys
        {
            return b;
        }
        let capacity = (keys + keys / 4)
            .min(self.max_binding() / KEY_BYTES)
            .max(keys);
        let hist_words = u64::from(RADIX_DIGITS) * capacity.div_ceil(u64::from(RADIX_BLOCK));
        let hist_blocks = hist_words.div_ceil(u64::from(SCAN_BLOCK));
        let d = &self.device;
        SortBuffers {
            keys: [0, 1].map(|_| storage(d, "sort_keys", capacity * KEY_BYTES)),
            vals: [0, 1].map(|_| storage(d, "sort_ids", capacity * 4)),
            hist: storage(d, "radix_histogram", (hist_words + 1) * 4),
            hist_sums: storage(d, "radix_block_sums", (hist_blocks + 1) * 4),
            capacity,
        }
    }

    /// One uniform per radix pass over `n_keys` keys, at the bit offsets `shifts` (the rest of
    /// `base`: the view's fields).
    pub(super) fn radix_params(
        &self,
        n_keys: u32,
        shifts: &[u32],
        base: &Params,
    ) -> Vec<wgpu::Buffer> {
        let hist_len = RADIX_DIGITS * n_keys.div_ceil(RADIX_BLOCK);
        shifts
            .iter()
            .map(|&shift| {
                self.uniform(&Params {
                    n_keys,
                    shift,
                    n_pixels: hist_len,
                    n_blocks: hist_len.div_ceil(SCAN_BLOCK),
                    ..*base
                })
            })
            .collect()
    }

    /// Records the stable LSD radix sort of `sb.keys[0]` / `sb.vals[0]` (`n_keys` of them), one
    /// pass per uniform of [`Self::radix_params`] (count, scan of the histogram, scatter), ping-
    /// pong between the two buffers: the result is in buffer `params.len() % 2`.
    pub(super) fn encode_radix_passes(
        &self,
        pass: &mut wgpu::ComputePass<'_>,
        sb: &SortBuffers,
        n_keys: u32,
        params: &[wgpu::Buffer],
    ) {
        let hist_len = RADIX_DIGITS * n_keys.div_ceil(RADIX_BLOCK);
        let p = &self.pipelines;
        let (bx, by) = groups_2d(n_keys.div_ceil(RADIX_BLOCK));
        for (i, pbuf) in params.iter().enumerate() {
            let (src, dst) = (i % 2, 1 - i % 2);
            let bg = self.bind(
                &p.radix_count,
                &[(0, pbuf), (8, &sb.hist), (14, &sb.keys[src])],
            );
            pass.set_pipeline(&p.radix_count);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(bx, by, 1);
            self.encode_scan(
                pass,
                pbuf,
                &sb.hist,
                &sb.hist_sums,
                hist_len.div_ceil(SCAN_BLOCK),
            );
            let bg = self.bind(
                &p.radix_scatter,
                &[
                    (0, pbuf),
                    (8, &sb.hist),
                    (14, &sb.keys[src]),
                    (15, &sb.vals[src]),
                    (16, &sb.keys[dst]),
                    (17, &sb.vals[dst]),
                ],
            );
            pass.set_pipeline(&p.radix_scatter);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(bx, by, 1);
        }
    }

    /// Step 2 on the device for `total` intersections (from [`Self::project_count`]): emit,
    /// radix passes and tile ranges, submitted without waiting; returns the view's binned
    /// buffers (the sorted ids are one of the kept sort buffers) with the per-pixel scratch of
    /// the list path.
    ///
    /// Errors: more intersections than one binding holds ([`Error::Limit`] `GpuBinding`).
    pub(super) fn sort_tiles(&mut self, view: &View, total: u32) -> Result<Binned> {
        self.check_size(
            "tile intersections' sort keys",
            u64::from(total) * KEY_BYTES,
            &view.k,
        )?;
        let kept = self.sort.take();
        let sb = self.sort_buffers(kept, u64::from(total));
        for (i, b) in sb.keys.iter().chain(&sb.vals).enumerate() {
            self.noise(b, SEED_SALT + 10 + i as u64);
        }
        self.noise(&sb.hist, SEED_SALT + 14);
        let ranges = storage(&self.device, "tile_ranges", u64::from(view.n_tiles) * 8);
        self.noise(&ranges, SEED_SALT + 15);
        let shifts = radix_shifts(view.n_tiles);
        let params = self.radix_params(total, &shifts, &view.params);
        // The sorted keys and ids end in the buffer the last pass wrote.
        let last = shifts.len() % 2;
        let mut enc = self.device.create_command_encoder(&Default::default());
        enc.clear_buffer(&ranges, 0, None);
        if total > 0 {
            let mut pass = enc.begin_compute_pass(&Default::default());
            let p = &self.pipelines;
            let bg = self.bind(
                &p.emit,
                &[
                    (0, &params[0]),
                    (4, &self.splats),
                    (5, &self.isect),
                    (8, &self.tile_counts),
                    (16, &sb.keys[0]),
                    (17, &sb.vals[0]),
                ],
            );
            let (x, y) = groups_2d(self.n.div_ceil(256));
            pass.set_pipeline(&p.emit);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(x, y, 1);
            self.encode_radix_passes(&mut pass, &sb, total, &params);
            let bg = self.bind(
                &p.tile_bounds,
                &[(0, &params[0]), (14, &sb.keys[last]), (18, &ranges)],
            );
            let (x, y) = groups_2d(total.div_ceil(256));
            pass.set_pipeline(&p.tile_bounds);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(x, y, 1);
        }
        self.queue.submit([enc.finish()]);
        let binned = Binned {
            ranges,
            sorted_ids: sb.vals[last].clone(),
            sorted_keys: sb.keys[last].clone(),
            offsets: storage(&self.device, "offsets", (u64::from(view.n_pix) + 1) * 4),
            block_sums: storage(
                &self.device,
                "block_sums",
                (u64::from(view.n_blocks) + 1) * 4,
            ),
            dummy: storage(&self.device, "dummy", 16),
        };
        self.noise(&binned.offsets, SEED_SALT + 2);
        self.noise(&binned.block_sums, SEED_SALT + 3);
        self.sort = Some(sb);
        Ok(binned)
    }

    /// Testing aid: one view's binning and depth sort on the device, read back: the tile ranges
    /// (`[start, end)` per tile, `[0, 0)` when empty), the sorted keys `(f32 depth bits, tile)`
    /// and the sorted Gaussian ids, as [`super::project::bin_and_sort`] orders them on the host.
    ///
    /// Errors: as [`crate::raster::WeightRasterizer::rasterize`].
    #[cfg(test)]
    pub(crate) fn sorted_intersections(
        &mut self,
        k: &slag_common::camera::Intrinsics,
        w2c: &slag_common::camera::WorldToCamera,
    ) -> Result<SortedIntersections> {
        super::super::validate_raster(k)?;
        let view = self.begin_view(k, w2c)?;
        self.noise(&self.splats, SEED_SALT);
        self.noise(&self.isect, SEED_SALT + 1);
        self.upload_sort_depths(w2c);
        let total = self.project_count(&view)?;
        let b = self.sort_tiles(&view, total)?;
        let n = u64::from(total);
        let enc = self.device.create_command_encoder(&Default::default());
        let read = self.submit_and_read(
            enc,
            &[
                (&b.ranges, 0, u64::from(view.n_tiles) * 8),
                (&b.sorted_keys, 0, n * KEY_BYTES),
                (&b.sorted_ids, 0, n * 4),
                (&self.isect, 0, u64::from(self.n) * 8),
            ],
        )?;
        let mut ranges: Vec<[u32; 2]> = bytemuck::pod_collect_to_vec(&read[0]);
        let mut keys: Vec<[u32; 2]> = bytemuck::pod_collect_to_vec(&read[1]);
        let mut ids: Vec<u32> = bytemuck::pod_collect_to_vec(&read[2]);
        let mut rects: Vec<[u32; 2]> = bytemuck::pod_collect_to_vec(&read[3]);
        rects.truncate(self.n as usize);
        ranges.truncate(view.n_tiles as usize);
        keys.truncate(total as usize);
        ids.truncate(total as usize);
        Ok(SortedIntersections {
            ranges,
            keys,
            ids,
            rects,
        })
    }
}

/// The device's binned view, read back ([`GpuRasterizer::sorted_intersections`]).
#[cfg(test)]
#[derive(Debug)]
pub(crate) struct SortedIntersections {
    /// `[start, end)` per tile, row-major.
    pub ranges: Vec<[u32; 2]>,
    /// `(f32 depth bits, tile id)` per intersection, sorted.
    pub keys: Vec<[u32; 2]>,
    /// Gaussian ids, parallel to `keys`.
    pub ids: Vec<u32>,
    /// Every Gaussian's packed tile rect from the projection (`[x0 | y0 << 16, x1 | y1 << 16]`),
    /// the input of the host reference.
    pub rects: Vec<[u32; 2]>,
}

#[cfg(test)]
mod tests {
    use super::radix_shifts;

    #[test]
    fn radix_passes_cover_the_depth_and_only_the_tile_bits_needed() {
        assert_eq!(radix_shifts(1), (0..8).map(|p| p * 4).collect::<Vec<_>>());
        assert_eq!(radix_shifts(16).len(), 9); // tiles 0..15: 4 bits
        assert_eq!(radix_shifts(17).len(), 10); // tile 16 needs a 5th bit
        assert_eq!(radix_shifts(744).len(), 11); // 31x24 tiles: 10 bits
        assert_eq!(*radix_shifts(u32::MAX).last().unwrap_or(&0), 60);
    }
}
