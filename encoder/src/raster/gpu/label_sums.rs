//! Step 3', mode 2 of the `blend` kernel (`label_sums.wgsl`): per-(Gaussian, label) sums of the
//! blend weights in an open-addressing table on the device, instead of per-pixel lists; only the
//! table is read back.

use rayon::prelude::*;
use slag_common::{Error, Result};

use super::super::{LabelSum, LabelSums};
use super::buffers::{storage, storage_init};
use super::{Binned, GpuRasterizer, RunOutput, View};

/// Label-sum table slots of a new rasterizer (4 MiB); grown per view as needed.
pub(super) const INITIAL_LABEL_SLOTS: u32 = 1 << 18;
/// Most label-sum table slots (4 GiB of table): beyond, the view is refused.
const MAX_LABEL_SLOTS: u32 = 1 << 28;

/// The non-empty slots of a mode-2 table (4 words each: Gaussian + 1, label, low, high), sorted by
/// (Gaussian, label), duplicates of one key (see `add_label_sum` in label_sums.wgsl) added.
fn decode_label_sums(slots: &[u32]) -> Vec<LabelSum> {
    let mut out: Vec<LabelSum> = slots
        .chunks_exact(4)
        .filter(|w| w[0] != 0)
        .map(|w| LabelSum {
            gaussian: w[0] - 1,
            label: w[1],
            sum: (u64::from(w[3]) << 32) | u64::from(w[2]),
        })
        .collect();
    out.par_sort_unstable_by_key(|e| (e.gaussian, e.label));
    out.dedup_by(|next, kept| {
        if (next.gaussian, next.label) == (kept.gaussian, kept.label) {
            kept.sum += next.sum;
            true
        } else {
            false
        }
    });
    out
}

impl GpuRasterizer {
    /// The label-sum pass over a binned view: a table at most half full for one label per
    /// visible Gaussian (at least the last view's size), retried with 4× the slots on overflow;
    /// [`RunOutput::UseLists`] past what one binding holds.
    ///
    /// Errors: `labels` not one per raster pixel ([`Error::Internal`]); a table over the binding
    /// limit; device failures.
    pub(super) fn label_sums_pass(
        &mut self,
        view: &mut View,
        b: &Binned,
        labels: &[u32],
        fixed_slots: bool,
        visible: u64,
    ) -> Result<RunOutput> {
        let k = view.k;
        if labels.len() != view.n_pix as usize {
            return Err(Error::internal(format!(
                "{} pixel labels for a {}x{} raster; pass one label per raster pixel",
                labels.len(),
                k.width,
                k.height
            )));
        }
        let labels_buf = storage_init(&self.device, "labels", bytemuck::cast_slice(labels));
        // A table at most half full for one label per visible Gaussian, at least the size
        // the last view needed: a first view of a large scene then rarely retries.
        // Most slots one binding holds (a power of two).
        let cap =
            ((self.max_binding().saturating_sub(16) / 16).min(u64::from(MAX_LABEL_SLOTS))).max(4);
        let cap = 1u64 << (63 - cap.leading_zeros());
        let mut slots = if fixed_slots {
            u64::from(self.label_slots.max(4)).min(cap)
        } else {
            (visible * 2)
                .next_power_of_two()
                .clamp(u64::from(self.label_slots.max(4)), cap)
        } as u32;
        let mut retries = 0;
        loop {
            let table_bytes = 16 + u64::from(slots) * 16;
            self.check_size("label-sum table", table_bytes, &k)?;
            let table = storage(&self.device, "label_sums", table_bytes);
            view.params.mode = 2;
            view.params.table_mask = slots - 1;
            self.write_params(view);
            let mut enc = self.device.create_command_encoder(&Default::default());
            enc.clear_buffer(&table, 0, None);
            {
                let bg = self.blend_group(view, b, &b.dummy, &b.dummy, &labels_buf, &table);
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&self.pipelines.blend);
                pass.set_bind_group(0, &bg, &[]);
                pass.dispatch_workgroups(view.tiles_x, view.tiles_y, 1);
            }
            let read = self.submit_and_read(enc, &[(&table, 0, table_bytes)])?;
            let words: Vec<u32> = bytemuck::pod_collect_to_vec(&read[0]);
            if words.first().copied().unwrap_or(1) != 0 {
                // Some contribution found no slot: retry the view with 4x the slots, or,
                // past what one binding holds, let the caller take the per-pixel lists.
                retries += 1;
                if u64::from(slots) >= cap {
                    self.label_retries = retries;
                    return Ok(RunOutput::UseLists);
                }
                slots = (u64::from(slots) * 4).min(cap) as u32;
                continue;
            }
            let sums = LabelSums {
                sums: decode_label_sums(&words[4..]),
                contributions: (u64::from(words[2]) << 32) | u64::from(words[1]),
            };
            // Next view: keep the table at most half full.
            let want = (sums.sums.len() as u64 * 2).next_power_of_two();
            let next = u64::from(slots).max(want).min(cap) as u32;
            self.label_slots = next;
            self.label_retries = retries;
            return Ok(RunOutput::Sums(sums));
        }
    }
}
