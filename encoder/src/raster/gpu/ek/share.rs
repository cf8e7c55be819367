//! The streamed reduction shared between devices (a run on several GPUs): each device folds
//! one range of Gaussians ([`crate::raster::gpu::fold`]), and as each of its own views is
//! kept, the records that view holds of the other devices' ranges go to those devices
//! ([`GpuRasterizer::share_kept_view`]): read back, uploaded to each device and left in its
//! [`KeptInbox`], which that device takes in before it folds ([`GpuRasterizer::take_inbox`]).
//! Every device so holds every view's label table and codebook rows, and of every view the
//! records of its own range; its own views' records of the other ranges are let go once sent.

use std::ops::Range;
use std::sync::{Arc, Mutex};

use slag_common::{Error, Result};

use super::exchange::{RecordSlice, host_view};
use super::{BLOCK_GAUSSIANS, KeptUploader, UploadedKept};
use crate::raster::KeptExport;
use crate::raster::gpu::GpuRasterizer;
use crate::raster::gpu::buffers::storage;

/// Where the views of a device's range come in ([`GpuRasterizer::share_kept_view`]): the
/// Gaussian ids the device folds, the uploader of records to its device, and the batches
/// uploaded there that it has not taken in yet. Cloned, it is the same inbox.
#[derive(Debug, Clone)]
pub struct KeptInbox {
    /// The Gaussian ids `[first, end)` the device folds (whole blocks of [`BLOCK_GAUSSIANS`]).
    pub(crate) gaussians: Range<u32>,
    uploader: KeptUploader,
    batches: Arc<Mutex<Vec<UploadedKept>>>,
}

impl KeptInbox {
    /// An empty inbox on `device` for the Gaussians `gaussians`.
    pub(in crate::raster::gpu) fn new(device: &wgpu::Device, gaussians: Range<u32>) -> Self {
        KeptInbox {
            gaussians,
            uploader: KeptUploader {
                device: device.clone(),
            },
            batches: Arc::new(Mutex::new(Vec::new())),
        }
    }

    /// `batch` uploaded to this inbox's device and left there.
    ///
    /// Errors: a lock poisoned by a panicked thread ([`Error::Internal`]).
    fn deliver(&self, batch: KeptExport) -> Result<()> {
        let uploaded = self.uploader.upload(batch);
        self.batches.lock().map_err(|_| poisoned())?.push(uploaded);
        Ok(())
    }

    /// The batches left here so far, in the order they came.
    ///
    /// Errors: a lock poisoned by a panicked thread ([`Error::Internal`]).
    fn take(&self) -> Result<Vec<UploadedKept>> {
        Ok(std::mem::take(
            &mut *self.batches.lock().map_err(|_| poisoned())?,
        ))
    }
}

fn poisoned() -> Error {
    Error::internal("a device's inbox of kept views poisoned by a panicked thread")
}

/// The Gaussian ids of share `share` of `shares` (from 0) of `n` Gaussians: consecutive runs
/// of whole blocks of [`BLOCK_GAUSSIANS`], about the same number of blocks each (a share may
/// be empty when there are fewer blocks than shares).
pub(in crate::raster::gpu) fn share_gaussians(n: u32, share: usize, shares: usize) -> Range<u32> {
    let blocks = u64::from(n.div_ceil(BLOCK_GAUSSIANS));
    let shares = shares.max(1) as u64;
    let at = |s: u64| {
        let b = blocks * s.min(shares) / shares;
        (b * u64::from(BLOCK_GAUSSIANS)).min(u64::from(n)) as u32
    };
    at(share as u64)..at(share as u64 + 1)
}

impl GpuRasterizer {
    /// Sends kept view `id` (this device's own, just kept) to every device in `peers`: its
    /// label table and codebook rows, and its bands' records of that device's range, read back
    /// in one go and uploaded there ([`KeptInbox`]). Then its bands keep only the records of
    /// `own` (this device's range), so that the device holds no more of its own views than
    /// the others send it.
    ///
    /// Errors: ranges not on block bounds ([`Error::Internal`]); device failures.
    pub(in crate::raster::gpu) fn share_kept_view(
        &mut self,
        id: u32,
        own: &Range<u32>,
        peers: &[KeptInbox],
    ) -> Result<()> {
        let peer_blocks = peers
            .iter()
            .map(|p| self.blocks_of(p.gaussians.clone()))
            .collect::<Result<Vec<_>>>()?;
        let own_blocks = self.blocks_of(own.clone())?;
        let Some(kept) = self.kept.as_mut() else {
            return Err(Error::internal(
                "a kept view shared without keeping started",
            ));
        };
        let staging = kept.staging.take();
        let kept = self
            .kept
            .as_ref()
            .ok_or_else(|| Error::internal("keeping stopped"))?;
        let view = host_view(kept, id as usize);
        let parts: Vec<usize> = (0..kept.parts.len())
            .filter(|&i| kept.parts[i].view == id)
            .collect();
        // Per peer, per band of the view: its slice of records and its block index there.
        let (mut slices, mut starts) = (Vec::new(), Vec::new());
        for blocks in &peer_blocks {
            for &i in &parts {
                let p = &kept.parts[i];
                let (lo, hi) = (p.starts[blocks.start], p.starts[blocks.end]);
                slices.push(RecordSlice {
                    records: &p.records,
                    first: lo,
                    n: hi - lo,
                });
                starts.push(p.starts.iter().map(|&s| s.clamp(lo, hi) - lo).collect());
            }
        }
        let (read, staging) = self.read_parts(&slices, staging)?;
        drop(slices);
        let dim = kept.dim;
        let mut read = read.into_iter().zip(starts);
        for peer in peers {
            let bands: Vec<(u32, Vec<u8>, Vec<u32>)> = read
                .by_ref()
                .take(parts.len())
                .filter(|(bytes, _)| !bytes.is_empty())
                .map(|(bytes, starts)| (0, bytes, starts))
                .collect();
            peer.deliver(KeptExport {
                dim,
                views: vec![view.clone()],
                parts: bands,
                continues: false,
                source: 0,
            })?;
        }
        self.keep_own_range(id, own_blocks);
        if let Some(kept) = self.kept.as_mut() {
            kept.staging = staging;
        }
        Ok(())
    }

    /// Trim step of [`Self::share_kept_view`]: each band of kept view `id` keeps only its
    /// records of the blocks `blocks` (copied to a buffer of their own; a band without any
    /// goes), its block index moved to them.
    fn keep_own_range(&mut self, id: u32, blocks: Range<usize>) {
        let Some(kept) = self.kept.as_mut() else {
            return;
        };
        let mut enc = self.device.create_command_encoder(&Default::default());
        let mut freed = 0u64;
        kept.parts.retain_mut(|p| {
            if p.view != id {
                return true;
            }
            let (lo, hi) = (p.starts[blocks.start], p.starts[blocks.end]);
            freed += u64::from(p.n - (hi - lo)) * 16;
            if hi == lo {
                return false;
            }
            if hi - lo < p.n {
                let records = storage(&self.device, "kept_records", u64::from(hi - lo) * 16);
                let bytes = u64::from(hi - lo) * 16;
                enc.copy_buffer_to_buffer(&p.records, u64::from(lo) * 16, &records, 0, bytes);
                p.records = records;
                p.n = hi - lo;
                p.starts
                    .iter_mut()
                    .for_each(|s| *s = (*s).clamp(lo, hi) - lo);
            }
            true
        });
        kept.bytes -= freed;
        // wgpu keeps the old buffers until the copies ran.
        self.queue.submit([enc.finish()]);
    }

    /// Takes in the batches other devices left in `inbox` ([`Self::share_kept_view`]), in
    /// the order they came, after every view kept so far.
    ///
    /// Errors: as [`Self::import_streamed`].
    pub(in crate::raster::gpu) fn take_inbox(&mut self, inbox: &KeptInbox) -> Result<()> {
        for batch in inbox.take()? {
            self.import_streamed(batch)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shares cover every Gaussian once, in order, on block bounds, with about the same
    /// blocks each; more shares than blocks leave some empty.
    #[test]
    fn the_shares_cover_the_gaussians_in_whole_blocks() {
        let b = BLOCK_GAUSSIANS;
        let n = 10 * b + 7;
        let shares: Vec<Range<u32>> = (0..3).map(|s| share_gaussians(n, s, 3)).collect();
        assert_eq!(shares, vec![0..3 * b, 3 * b..7 * b, 7 * b..n]);
        assert_eq!(share_gaussians(n, 0, 1), 0..n);
        let many: Vec<Range<u32>> = (0..4).map(|s| share_gaussians(b + 1, s, 4)).collect();
        assert_eq!(many, vec![0..0, 0..b, b..b, b..b + 1]);
    }
}
