//! The masks' record ([`slag_common::mask_record`]) kept on the device while the device reduction
//! keeps the views' label sums ([`super::ek`]): each kept band's Gaussians enter their dominant
//! mask of the view straight into a per-Gaussian slot table on the device (`ek.wgsl`
//! `record_dominant`), so nothing per Gaussian crosses to the host per view; the table is read
//! back once, after the last view ([`GpuRasterizer::take_device_mask_record`]).
//!
//! Layout on the device: per Gaussian `S` slots of two words, `((view + 1) << 16 | mask, a_kj
//! bits)`, 0 when unused, so a zeroed buffer is an empty record: 8 bytes a slot, as on the host
//! (64 bytes per Gaussian with the default 8 slots: 1.9 GB at 30M Gaussians). A scene whose table
//! does not fit one binding keeps the record on the host (the per-view dominant masks are read
//! back, as without the device reduction).
//!
//! The result equals the host's [`MaskRecord::add_view`] fed with the same per-band dominant
//! masks ([`super::ek`]'s `dominant` kernel): the same slots in the same order, whatever the
//! order of the views.

use slag_common::mask_record::MaskRecord;
use slag_common::{Error, Result};

use super::GpuRasterizer;
use super::buffers::{storage, uniform_init};
use super::ek::Kept;

/// The uniform of `record_dominant` (`ek.wgsl` `RecordParams`), 16 bytes.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct RecordParams {
    view: u32,
    slots: u32,
    n_gaussians: u32,
    pad0: u32,
}

/// Most bytes of the slot table read back at once (the staging buffer's size).
const READ_CHUNK_BYTES: u64 = 256 << 20;

/// The masks' record on the device: the slot table and its shape.
pub(super) struct DeviceRecord {
    table: wgpu::Buffer,
    slots: u32,
    view_count: usize,
}

impl GpuRasterizer {
    /// Starts the masks' record of `slots` slots per Gaussian on the device, for an encode of
    /// `view_count` views, once the device keeps the views' label sums
    /// ([`Self::start_keeping`]). Returns whether it does: not without keeping, nor when the
    /// slot table (8 bytes a slot) does not fit one binding.
    pub(super) fn start_device_mask_record(&mut self, slots: usize, view_count: usize) -> bool {
        if self.mask_record.is_some() {
            return true;
        }
        let bytes = u64::from(self.n) * slots as u64 * 8;
        if self.kept.is_none() || !(1..=64).contains(&slots) || bytes > self.max_binding() {
            return false;
        }
        // Buffers are zeroed at creation: an empty record.
        let table = storage(&self.device, "mask_record", bytes);
        self.mask_record = Some(DeviceRecord {
            table,
            slots: slots as u32,
            view_count,
        });
        true
    }

    /// Dispatch step of [`Self::keep_band`] with the record on the device: `record_dominant`
    /// over one band of view `view`. `band` holds the band's `ek.wgsl` uniform, its records,
    /// its block starts (bound for the shared record reader) and its view's label table;
    /// `groups` the dispatch of one thread per record.
    pub(super) fn record_band(
        &self,
        pass: &mut wgpu::ComputePass<'_>,
        kept: &Kept,
        view: u32,
        [params, records, starts, tables]: [&wgpu::Buffer; 4],
        (x, y): (u32, u32),
    ) {
        let Some(record) = &self.mask_record else {
            return;
        };
        let record_params = RecordParams {
            view,
            slots: record.slots,
            n_gaussians: self.n,
            pad0: 0,
        };
        let uniform = uniform_init(&self.device, "record_params", &record_params);
        let bg = self.bind(
            &kept.record_dominant,
            &[
                (0, params),
                (1, records),
                (2, starts),
                (4, tables),
                (9, &uniform),
                (10, &record.table),
            ],
        );
        pass.set_pipeline(&kept.record_dominant);
        pass.set_bind_group(0, &bg, &[]);
        pass.dispatch_workgroups(x, y, 1);
    }

    /// The masks' record kept on the device, read back (in chunks of at most
    /// [`READ_CHUNK_BYTES`]) and freed there; `None` when none was kept.
    ///
    /// Errors: device failures; [`Error::Internal`] for a table of another size than its shape.
    pub(super) fn take_device_mask_record(&mut self) -> Result<Option<MaskRecord>> {
        let Some(record) = self.mask_record.take() else {
            return Ok(None);
        };
        let slots = record.slots as usize;
        let mut out = MaskRecord::new(self.n as usize, slots, record.view_count)?;
        let slot_bytes = 8u64;
        let total = out.views.len() as u64 * slot_bytes;
        let chunk = (READ_CHUNK_BYTES / slot_bytes) * slot_bytes;
        let mut at = 0u64;
        while at < total {
            let len = chunk.min(total - at);
            let enc = self.device.create_command_encoder(&Default::default());
            let read = self.submit_and_read(enc, &[(&record.table, at, len)])?;
            let bytes = read
                .first()
                .and_then(|b| b.get(..len as usize))
                .ok_or_else(|| Error::internal("the masks' record read back short"))?;
            let first = (at / slot_bytes) as usize;
            unpack_slots(&mut out, first, bytes);
            at += len;
        }
        Ok(Some(out))
    }
}

/// Unpacks device slots (`bytes`, 8 a slot, module doc's layout) into `record`'s slots from
/// slot index `first` on.
fn unpack_slots(record: &mut MaskRecord, first: usize, bytes: &[u8]) {
    use rayon::prelude::*;
    let n = bytes.len() / 8;
    let end = (first + n).min(record.views.len());
    let views = &mut record.views[first..end];
    let masks = &mut record.masks[first..end];
    let weights = &mut record.weights[first..end];
    const PER_TASK: usize = 1 << 16;
    views
        .par_chunks_mut(PER_TASK)
        .zip(masks.par_chunks_mut(PER_TASK))
        .zip(weights.par_chunks_mut(PER_TASK))
        .zip(bytes.par_chunks(PER_TASK * 8))
        .for_each(|(((v, m), w), b)| {
            for (i, word) in b.chunks_exact(8).enumerate() {
                let tag = u32::from_le_bytes([word[0], word[1], word[2], word[3]]);
                let a = f32::from_le_bytes([word[4], word[5], word[6], word[7]]);
                if tag != 0 {
                    v[i] = ((tag >> 16) - 1) as u16;
                    m[i] = (tag & 0xffff) as u16;
                    w[i] = a;
                }
            }
        });
}
