//! Step 3b: the write mode of the `blend` kernel (`blend.wgsl`), in bands of whole tile rows
//! (each a contiguous range of CSR entries) so that no output binding exceeds the device limit;
//! each band's ids and weights are read back through the reused staging buffers.

use slag_common::{Error, Resource, Result};

use super::super::project::TILE_SIZE;
use super::buffers::OutBuffers;
use super::{Binned, GpuRasterizer, SEED_SALT, View};

impl GpuRasterizer {
    /// Writes and reads back every pixel's (Gaussian id, weight) entries, band by band, reusing
    /// `kept`'s buffers when they are large enough (the buffers used are left in `kept`).
    ///
    /// Errors: one row of tiles over the binding limit ([`Error::Limit`]); device failures.
    pub(super) fn write_banded(
        &self,
        view: &mut View,
        b: &Binned,
        offsets: &[u32],
        kept: &mut Option<OutBuffers>,
    ) -> Result<(Vec<u32>, Vec<f32>)> {
        let k = view.k;
        let band_bytes = self
            .band_limit
            .unwrap_or(u64::MAX)
            .min(self.max_binding())
            .max(4);
        let row_start = |tile_row: u32| {
            let py = (tile_row * TILE_SIZE).min(k.height);
            offsets[(py * k.width) as usize] as u64
        };
        let total = offsets[view.n_pix as usize] as usize;
        let mut ids = Vec::with_capacity(total);
        let mut weights = Vec::with_capacity(total);
        let mut r0 = 0u32;
        while r0 < view.tiles_y {
            let base = row_start(r0);
            let mut r1 = r0 + 1;
            if (row_start(r1) - base) * 4 > band_bytes {
                return Err(Error::limit(
                    Resource::GpuBinding,
                    format!(
                        "{:.2} MiB of output for one row of tiles of the {}x{} weight raster",
                        ((row_start(r1) - base) * 4) as f64 / 1048576.0,
                        k.width,
                        k.height
                    ),
                    format!("{:.2} MiB per binding", band_bytes as f64 / 1048576.0),
                ));
            }
            while r1 < view.tiles_y && (row_start(r1 + 1) - base) * 4 <= band_bytes {
                r1 += 1;
            }
            let entries = row_start(r1) - base;
            let bytes = entries * 4;
            if bytes == 0 {
                r0 = r1; // no pixel of these tile rows has a contributor: nothing to write
                continue;
            }
            let out = self.out_buffers(kept.take(), bytes, band_bytes);
            self.noise(&out.ids, SEED_SALT + 4 + r0 as u64);
            self.noise(&out.weights, SEED_SALT + 5 + r0 as u64);
            view.params.mode = 1;
            view.params.tile_y0 = r0;
            view.params.out_base = base as u32;
            self.write_params(view);
            let mut enc = self.device.create_command_encoder(&Default::default());
            {
                let bg = self.blend_group(view, b, &out.ids, &out.weights);
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&self.pipelines.blend);
                pass.set_bind_group(0, &bg, &[]);
                pass.dispatch_workgroups(view.tiles_x, r1 - r0, 1);
            }
            enc.copy_buffer_to_buffer(&out.ids, 0, &out.stage_ids, 0, bytes);
            enc.copy_buffer_to_buffer(&out.weights, 0, &out.stage_weights, 0, bytes);
            self.read_entries(enc, &out, bytes, &mut ids, &mut weights)?;
            *kept = Some(out);
            r0 = r1;
        }
        Ok((ids, weights))
    }
}
