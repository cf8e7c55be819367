//! Step 3', the `blend_sums` kernel (`label_sums.wgsl`): per-(Gaussian, label) sums of the blend
//! weights, accumulated per tile in workgroup memory and written as compact records, one per
//! (tile intersection, tile label) with a non-zero sum, instead of per-pixel lists; the records
//! of a band are reduced by (Gaussian, label) on the device ([`super::reduce`]) and only the
//! reduced records are read back (a view of several bands leaves the merge of their keys to
//! [`LabelSums::reduced`], on the image stage's thread).
//!
//! Bounded by construction: a band of tile rows writes at most one record per labelled
//! contribution and per (intersection, label of its tile), and the kernel counts the records it
//! wanted past the buffer's capacity, so a band that did not fit is re-run once with room for
//! exactly its count, or, past one binding, split into smaller bands. No table can overflow, and
//! there is no fallback to the per-pixel lists at any scene size.

use slag_common::{Error, Resource, Result};

use super::super::{LabelSum, LabelSums};
use super::buffers::{extend_pod, storage, storage_init};
use super::{Binned, GpuRasterizer, SEED_SALT, View};

/// Record capacity of a new rasterizer's buffer (4 MiB); grown per view as needed and kept.
pub(super) const INITIAL_LABEL_RECORDS: u64 = 1 << 18;
/// Bytes of one record (Gaussian, label, low and high word of the fixed-point sum).
const RECORD_BYTES: u64 = 16;
/// Bytes of the records buffer's header (count, contributions low and high, unused).
const HEADER_BYTES: u64 = 16;

/// The record buffer of the label sums and its `MAP_READ` twin, kept across views.
pub(super) struct RecordBuffers {
    records: wgpu::Buffer,
    staging: wgpu::Buffer,
    /// Records each holds after the header.
    capacity: u64,
}

/// Appends the records in `bytes` (4 little-endian words each: Gaussian, label, low and high word
/// of the sum, [`LabelSum`]'s layout; a trailing partial record is ignored) to `out`: one copy
/// when `bytes` is aligned ([`extend_pod`]).
fn decode_records(bytes: &[u8], out: &mut Vec<LabelSum>) {
    let whole = bytes.len() / RECORD_BYTES as usize * RECORD_BYTES as usize;
    extend_pod(out, &bytes[..whole]);
}

impl GpuRasterizer {
    /// Most records one binding (or the testing cap [`GpuRasterizer::set_label_record_limit`])
    /// holds.
    fn max_label_records(&self) -> u64 {
        let bytes = self
            .label_record_limit
            .map_or(u64::MAX, |r| HEADER_BYTES + r * RECORD_BYTES)
            .min(self.max_binding());
        (bytes.saturating_sub(HEADER_BYTES) / RECORD_BYTES).max(1)
    }

    /// `kept` if it holds `capacity` records, else new buffers of that capacity.
    fn record_buffers(&self, kept: Option<RecordBuffers>, capacity: u64) -> RecordBuffers {
        if let Some(b) = kept
            && b.capacity >= capacity
        {
            return b;
        }
        let bytes = HEADER_BYTES + capacity * RECORD_BYTES;
        RecordBuffers {
            records: storage(&self.device, "label_records", bytes),
            staging: self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("readback_label_records"),
                size: bytes.next_multiple_of(4),
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            capacity,
        }
    }

    /// The label-sum pass over a binned view, in bands of tile rows: each band's records are
    /// counted by the kernel; a band that did not fit is re-run with room for its count, or split
    /// when its count exceeds one binding.
    ///
    /// Returns the sums (sorted and one per key when the view took one band and the device
    /// reduced it) and the host's milliseconds copying the records out of the readback buffer.
    ///
    /// Errors: `labels` not one per raster pixel ([`Error::Internal`]); one row of tiles whose
    /// records exceed one binding ([`Error::Limit`]); device failures.
    pub(super) fn label_sums_pass(
        &mut self,
        view: &mut View,
        b: &Binned,
        labels: &[u32],
    ) -> Result<(LabelSums, f64)> {
        check_labels(view, labels)?;
        let labels_buf = storage_init(&self.device, "labels", bytemuck::cast_slice(labels));
        let max_records = self.max_label_records();
        let mut kept = self.label_out.take();
        let mut tally = BandTally::default();
        // The radix passes of the device reduction cover the label bits up to the largest.
        let max_label = labels.iter().copied().max().unwrap_or(0);
        let mut rows = view.tiles_y;
        let mut r0 = 0u32;
        while r0 < view.tiles_y {
            let r1 = (r0 + rows).min(view.tiles_y);
            let capacity = self.label_records.clamp(1, max_records);
            let out = self.record_buffers(kept.take(), capacity);
            let header = self.dispatch_band(view, b, &labels_buf, &out, (r0, r1), capacity)?;
            let wanted = u64::from(header[0]);
            if wanted > capacity {
                // The band did not fit: re-run it with room for its records, or split it.
                tally.retries += 1;
                self.grow_or_split(view, wanted, max_records, r1 - r0, &mut rows)?;
                kept = Some(out);
                continue;
            }
            tally.contributions += (u64::from(header[2]) << 32) | u64::from(header[1]);
            tally.written += wanted;
            if wanted > 0 {
                tally.bands += 1;
                tally.host +=
                    self.band_records(view, &out, wanted, max_label, &mut tally.records)?;
            }
            kept = Some(out);
            r0 = r1;
        }
        self.label_out = kept;
        self.label_retries = tally.retries;
        self.label_record_count = tally.written;
        Ok((
            LabelSums {
                records: tally.records,
                contributions: tally.contributions,
                // Keys of several bands may repeat across them.
                sorted: self.reduce_on_device && tally.bands <= 1,
            },
            tally.host.as_secs_f64() * 1e3,
        ))
    }

    /// Dispatch step: runs `blend_sums` over the tile rows `[r0, r1)` into `out` (room for
    /// `capacity` records, header cleared first) and reads back the 4-word header: records
    /// wanted, contributions low and high word.
    fn dispatch_band(
        &self,
        view: &mut View,
        b: &Binned,
        labels_buf: &wgpu::Buffer,
        out: &RecordBuffers,
        (r0, r1): (u32, u32),
        capacity: u64,
    ) -> Result<[u32; 4]> {
        self.noise(&out.records, SEED_SALT + 6 + u64::from(r0));
        view.params.tile_y0 = r0;
        view.params.out_cap = capacity as u32;
        self.write_params(view);
        let mut enc = self.device.create_command_encoder(&Default::default());
        enc.clear_buffer(&out.records, 0, Some(HEADER_BYTES));
        {
            let bg = self.bind(
                &self.pipelines.blend_sums,
                &[
                    (0, &view.params_buf),
                    (4, &self.splats),
                    (6, &b.ranges),
                    (7, &b.sorted_ids),
                    (12, labels_buf),
                    (13, &out.records),
                ],
            );
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipelines.blend_sums);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(view.tiles_x, r1 - r0, 1);
        }
        enc.copy_buffer_to_buffer(&out.records, 0, &out.staging, 0, HEADER_BYTES);
        let mut header = [0u32; 4];
        self.submit_and_map(enc, &[(&out.staging, HEADER_BYTES)], |_, bytes| {
            header = bytemuck::pod_read_unaligned(bytes);
        })?;
        Ok(header)
    }

    /// Overflow step: a band of `band_rows` tile rows wanted `wanted` records past its buffer;
    /// the next run gets room for them (a quarter more), or, past one binding, half the rows.
    ///
    /// Errors: one row of tiles wants more than one binding holds ([`Error::Limit`]).
    fn grow_or_split(
        &mut self,
        view: &View,
        wanted: u64,
        max_records: u64,
        band_rows: u32,
        rows: &mut u32,
    ) -> Result<()> {
        if wanted <= max_records {
            self.label_records = (wanted + wanted / 4).min(max_records);
        } else if band_rows > 1 {
            self.label_records = max_records;
            *rows = band_rows / 2;
        } else {
            return Err(Error::limit(
                Resource::GpuBinding,
                format!(
                    "{} MiB of label-sum records for one row of tiles of the {}x{} \
                     weight raster",
                    (wanted * RECORD_BYTES) >> 20,
                    view.k.width,
                    view.k.height
                ),
                format!("{} MiB per binding", (max_records * RECORD_BYTES) >> 20),
            ));
        }
        Ok(())
    }
}

/// Input step: `labels` holds one label per raster pixel of `view`.
fn check_labels(view: &View, labels: &[u32]) -> Result<()> {
    if labels.len() != view.n_pix as usize {
        return Err(Error::internal(format!(
            "{} pixel labels for a {}x{} raster; pass one label per raster pixel",
            labels.len(),
            view.k.width,
            view.k.height
        )));
    }
    Ok(())
}

/// What the bands of one label-sum view add up to.
#[derive(Default)]
struct BandTally {
    /// Records read back (none while the view is kept on the device).
    records: Vec<LabelSum>,
    /// Labelled contributions the kernel counted.
    contributions: u64,
    /// Band re-runs (a band did not fit its buffer).
    retries: u32,
    /// Records the kernel wrote, all bands.
    written: u64,
    /// Bands that wrote records.
    bands: u32,
    /// Host time copying records out of the readback buffer.
    host: std::time::Duration,
}

impl GpuRasterizer {
    /// One band's `wanted` records (in `out.records`): reduced on the device and kept there for
    /// the device reduction while a view is kept, else read back into `records` (one per key
    /// when reduced on the device, or as written). Returns the host's time copying them out.
    ///
    /// Errors: device failures; the kept sums' budget ([`GpuRasterizer::keep_band`]).
    fn band_records(
        &mut self,
        view: &View,
        out: &RecordBuffers,
        wanted: u64,
        max_label: u32,
        records: &mut Vec<LabelSum>,
    ) -> Result<std::time::Duration> {
        let mut host = std::time::Duration::ZERO;
        if let Some(keeping) = self.keeping {
            let (reduced, keys) =
                self.reduce_records(view, &out.records, wanted as u32, max_label)?;
            let heads = self.keep_band(keeping, &reduced, keys)?;
            self.kept_heads.extend(heads);
            return Ok(host);
        }
        let mut enc = self.device.create_command_encoder(&Default::default());
        // One record per key (reduced on the device), or the records as written.
        let bytes = if self.reduce_on_device {
            let (reduced, keys) =
                self.reduce_records(view, &out.records, wanted as u32, max_label)?;
            let bytes = u64::from(keys) * RECORD_BYTES;
            enc.copy_buffer_to_buffer(&reduced, 0, &out.staging, 0, bytes);
            bytes
        } else {
            let bytes = wanted * RECORD_BYTES;
            enc.copy_buffer_to_buffer(&out.records, HEADER_BYTES, &out.staging, 0, bytes);
            bytes
        };
        self.submit_and_map(enc, &[(&out.staging, bytes)], |_, bytes| {
            let t = std::time::Instant::now();
            decode_records(bytes, records);
            host += t.elapsed();
        })?;
        Ok(host)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_of_one_key_are_added() {
        let words = [
            3,
            1,
            u32::MAX,
            0, // (3, 1): 2^32 - 1
            1,
            2,
            5,
            0, //
            3,
            1,
            1,
            1, // (3, 1) again: 2^32 + 1
        ];
        let mut out = Vec::new();
        let mut bytes: Vec<u8> = words.iter().flat_map(|w: &u32| w.to_le_bytes()).collect();
        bytes.push(7); // a trailing partial record is ignored
        decode_records(&bytes, &mut out);
        let sums = LabelSums {
            records: out,
            contributions: 0,
            sorted: false,
        }
        .reduced();
        assert_eq!(
            sums,
            vec![
                LabelSum {
                    gaussian: 1,
                    label: 2,
                    sum: 5
                },
                LabelSum {
                    gaussian: 3,
                    label: 1,
                    sum: (1 << 33)
                },
            ]
        );
    }
}
