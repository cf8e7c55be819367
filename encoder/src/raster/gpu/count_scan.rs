//! Step 3a: the count mode of the `blend` kernel (`blend.wgsl`, contributors per pixel) and the
//! exclusive prefix sum over pixels (`scan.wgsl`), giving the CSR offsets of the view.

use slag_common::Result;

use super::buffers::scan_overflow;
use super::{Binned, GROUPS_X, GpuRasterizer, View};

impl GpuRasterizer {
    /// Counts contributors per pixel, scans them in place and reads back the `n_pix + 1` CSR
    /// offsets (the last one the total).
    ///
    /// Errors: more than 2^32 entries ([`Error::Limit`]); device failures.
    pub(super) fn count_scan(&self, view: &View, b: &Binned) -> Result<Vec<u32>> {
        let scan_entries = [(0, &view.params_buf), (8, &b.offsets), (11, &b.block_sums)];
        let mut enc = self.device.create_command_encoder(&Default::default());
        {
            let bg = self.blend_group(view, b, &b.dummy, &b.dummy);
            let bg_l = self.bind(&self.pipelines.scan_local, &scan_entries);
            let bg_b = self.bind(&self.pipelines.scan_blocks, &scan_entries);
            let bg_a = self.bind(&self.pipelines.scan_add, &scan_entries);
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipelines.blend);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(view.tiles_x, view.tiles_y, 1);
            let (gx, gy) = (
                view.n_blocks.min(GROUPS_X),
                view.n_blocks.div_ceil(GROUPS_X),
            );
            pass.set_pipeline(&self.pipelines.scan_local);
            pass.set_bind_group(0, &bg_l, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
            pass.set_pipeline(&self.pipelines.scan_blocks);
            pass.set_bind_group(0, &bg_b, &[]);
            pass.dispatch_workgroups(1, 1, 1);
            pass.set_pipeline(&self.pipelines.scan_add);
            pass.set_bind_group(0, &bg_a, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        let read = self.submit_and_read(
            enc,
            &[
                (&b.offsets, 0, (view.n_pix as u64 + 1) * 4),
                (&b.block_sums, view.n_blocks as u64 * 4, 4),
            ],
        )?;
        let offsets: Vec<u32> = bytemuck::pod_collect_to_vec(&read[0]);
        scan_overflow(
            &read[1],
            format!(
                "more than 2^32 for the {}x{} weight raster",
                view.k.width, view.k.height
            ),
            "2^32",
        )?;
        Ok(offsets)
    }
}
