//! Moving kept views off a device: to the host (all at once, in batches or by range of
//! Gaussians) and onto another device, whose reduction then takes them in as its own.

use slag_common::{Error, Result};

use super::tables::table_masks;
use super::{BLOCK_GAUSSIANS, Kept, KeptPart, OwnKept, READBACK_BYTES};
use crate::raster::gpu::GpuRasterizer;
use crate::raster::gpu::buffers::storage_init;
use crate::raster::{KeptExport, KeptHostView, KeptRangeCursor, LabelSum};

/// Records `[first, first + n)` of one band's buffer, to be read back
/// ([`GpuRasterizer::read_parts`]).
pub(super) struct RecordSlice<'a> {
    pub(super) records: &'a wgpu::Buffer,
    pub(super) first: u32,
    pub(super) n: u32,
}

impl RecordSlice<'_> {
    fn bytes(&self) -> u64 {
        u64::from(self.n) * 16
    }
}

/// Uploads the kept records of batches from other devices to one device without holding its
/// rasterizer ([`crate::raster::WeightRasterizer::kept_uploader`]): an exchange between devices
/// uploads one batch while the device reads its own next batch back.
#[derive(Debug, Clone)]
pub struct KeptUploader {
    pub(super) device: wgpu::Device,
}

impl KeptUploader {
    /// `batch` with each band's records in a buffer on this uploader's device, their host bytes
    /// let go, for [`crate::raster::WeightRasterizer::import_uploaded`].
    pub fn upload(&self, mut batch: KeptExport) -> UploadedKept {
        let records = batch
            .parts
            .iter_mut()
            .map(|(_, bytes, _)| {
                let bytes = std::mem::take(bytes);
                UploadedRecords {
                    buffer: storage_init(&self.device, "kept_records", &bytes),
                    n: (bytes.len() / 16) as u32,
                    device: self.device.clone(),
                }
            })
            .collect();
        UploadedKept { batch, records }
    }
}

/// A batch of kept views whose records are on the device that takes it in
/// ([`KeptUploader::upload`]).
#[derive(Debug)]
pub struct UploadedKept {
    /// The batch, its bands' bytes let go.
    batch: KeptExport,
    /// Per band of `batch`, its records.
    records: Vec<UploadedRecords>,
}

/// One band's records uploaded ([`UploadedKept`]).
#[derive(Debug)]
struct UploadedRecords {
    buffer: wgpu::Buffer,
    /// Records held.
    n: u32,
    /// The device it is on.
    device: wgpu::Device,
}

impl GpuRasterizer {
    /// Every kept view as host data ([`KeptExport`]), for another device's reduction; keeping
    /// stops here. `None` when nothing was kept.
    ///
    /// Errors: device failures reading the records back.
    pub(in crate::raster::gpu) fn export_kept_views(&mut self) -> Result<Option<KeptExport>> {
        let all = self.export_kept_views_batch(u64::MAX);
        self.kept = None;
        all
    }

    /// The next batch of the kept views as host data, for another device's reduction
    /// ([`Self::import_kept_views`]): the first batch has every view's label table and codebook
    /// rows, and each batch the next bands, as many as fit `max_bytes` of records (at least
    /// one), each freed here once read. Keeping stops at the first batch; `None` once every
    /// band went (or nothing was kept). So a hand-over need not hold every record on the host.
    ///
    /// Errors: device failures reading the records back.
    pub(in crate::raster::gpu) fn export_kept_views_batch(
        &mut self,
        max_bytes: u64,
    ) -> Result<Option<KeptExport>> {
        let Some(kept) = self.kept.as_mut() else {
            return Ok(None);
        };
        let first = !kept.exporting;
        if !first && kept.parts.is_empty() {
            self.kept = None;
            return Ok(None);
        }
        kept.exporting = true;
        let views = if first {
            host_views(kept, kept.views.len())
        } else {
            Vec::new()
        };
        let (mut take, mut bytes) = (0, 0u64);
        for p in &kept.parts {
            let b = u64::from(p.n) * 16;
            if take > 0 && bytes + b > max_bytes {
                break;
            }
            (take, bytes) = (take + 1, bytes + b);
        }
        let batch: Vec<KeptPart> = kept.parts.drain(..take).collect();
        kept.bytes -= bytes;
        let dim = kept.dim;
        let staging = kept.staging.take();
        let slices: Vec<RecordSlice<'_>> = batch
            .iter()
            .map(|p| RecordSlice {
                records: &p.records,
                first: 0,
                n: p.n,
            })
            .collect();
        let (read, staging) = self.read_parts(&slices, staging)?;
        if let Some(kept) = self.kept.as_mut() {
            kept.staging = staging;
        }
        let parts = batch
            .into_iter()
            .zip(read)
            .map(|(p, bytes)| (p.view, bytes, p.starts))
            .collect();
        Ok(Some(KeptExport {
            dim,
            views,
            parts,
            continues: !first,
            source: 0,
        }))
    }

    /// Per block of [`BLOCK_GAUSSIANS`] Gaussians, the records of this device's own kept views
    /// (`[blocks]`); `None` when it keeps nothing.
    pub(in crate::raster::gpu) fn kept_block_records(&self) -> Option<Vec<u64>> {
        let kept = self.kept.as_ref()?;
        let own = kept.own.map_or(kept.parts.len(), |o| o.parts);
        let blocks = self.n.div_ceil(BLOCK_GAUSSIANS) as usize;
        let mut out = vec![0u64; blocks];
        for p in &kept.parts[..own] {
            for (b, n) in out.iter_mut().enumerate() {
                *n += u64::from(p.starts[b + 1] - p.starts[b]);
            }
        }
        Some(out)
    }

    /// The next batch of this device's own kept records of the Gaussians in `cursor`'s range,
    /// for another device's reduction of that range ([`Self::import_kept_views`]): the first
    /// batch has every own view's label table and codebook rows, each batch the next bands'
    /// records in the range (as many as fit `max_bytes`, at least one band), each band's block
    /// index moved to the range (no records before it or after it). Keeping stops at the first
    /// batch; the records stay here for this device's own range. `None` once every band went
    /// (or nothing was kept).
    ///
    /// Errors: a range not on block bounds ([`Error::Internal`]); device failures reading the
    /// records back.
    pub(in crate::raster::gpu) fn export_kept_range(
        &mut self,
        cursor: &mut KeptRangeCursor,
        max_bytes: u64,
    ) -> Result<Option<KeptExport>> {
        let blocks = self.blocks_of(cursor.gaussians.clone())?;
        let Some(kept) = self.kept.as_mut() else {
            return Ok(None);
        };
        let own = kept.stop();
        if cursor.started && cursor.next_part >= own.parts {
            return Ok(None);
        }
        let views = if cursor.started {
            Vec::new()
        } else {
            host_views(kept, own.views)
        };
        let staging = kept.staging.take();
        let kept = self
            .kept
            .as_ref()
            .ok_or_else(|| Error::internal("keeping stopped"))?;
        let (mut slices, mut picked, mut bytes) = (Vec::new(), Vec::new(), 0u64);
        while cursor.next_part < own.parts {
            let p = &kept.parts[cursor.next_part];
            let (lo, hi) = (p.starts[blocks.start], p.starts[blocks.end]);
            let slice = RecordSlice {
                records: &p.records,
                first: lo,
                n: hi - lo,
            };
            if !slices.is_empty() && bytes + slice.bytes() > max_bytes {
                break;
            }
            cursor.next_part += 1;
            if slice.n == 0 {
                continue;
            }
            bytes += slice.bytes();
            let starts = p.starts.iter().map(|&s| s.clamp(lo, hi) - lo).collect();
            picked.push((p.view, starts));
            slices.push(slice);
        }
        let (read, staging) = self.read_parts(&slices, staging)?;
        let dim = kept.dim;
        if let Some(kept) = self.kept.as_mut() {
            kept.staging = staging;
        }
        let parts = picked
            .into_iter()
            .zip(read)
            .map(|((view, starts), bytes)| (view, bytes, starts))
            .collect();
        let continues = cursor.started;
        cursor.started = true;
        Ok(Some(KeptExport {
            dim,
            views,
            parts,
            continues,
            source: 0,
        }))
    }

    /// The blocks `[b0, b1)` of [`BLOCK_GAUSSIANS`] that hold the Gaussians `gaussians`.
    ///
    /// Errors: a range that does not start on a block or end on one (or at the last
    /// Gaussian), or past the scene ([`Error::Internal`]).
    pub(in crate::raster::gpu) fn blocks_of(
        &self,
        gaussians: std::ops::Range<u32>,
    ) -> Result<std::ops::Range<usize>> {
        let on_bound = |g: u32| g.is_multiple_of(BLOCK_GAUSSIANS) || g == self.n;
        if gaussians.start > gaussians.end
            || gaussians.end > self.n
            || !on_bound(gaussians.start)
            || !on_bound(gaussians.end)
        {
            return Err(Error::internal(format!(
                "Gaussians {gaussians:?} of {} are not whole blocks of {BLOCK_GAUSSIANS}",
                self.n
            )));
        }
        let b = |g: u32| g.div_ceil(BLOCK_GAUSSIANS) as usize;
        Ok(b(gaussians.start)..b(gaussians.end))
    }

    /// The records of `parts` read back, one `Vec` per slice, through one staging buffer reused
    /// group after group of slices (at most [`READBACK_BYTES`] a group, or one slice; see
    /// [`Self::set_readback_bytes`]): `staging`
    /// when it is large enough, else a new one, returned for the next call (a hand-over reads
    /// batch after batch, and mapping fresh host memory each time costs more than the copy).
    ///
    /// Errors: device failures.
    pub(super) fn read_parts(
        &self,
        parts: &[RecordSlice<'_>],
        mut staging: Option<wgpu::Buffer>,
    ) -> Result<(Vec<Vec<u8>>, Option<wgpu::Buffer>)> {
        let bytes_of = RecordSlice::bytes;
        let most = self.readback_bytes.unwrap_or(READBACK_BYTES);
        let mut out = Vec::with_capacity(parts.len());
        let mut rest = parts;
        while !rest.is_empty() {
            let (mut take, mut group) = (0, 0u64);
            for p in rest {
                if take > 0 && group + bytes_of(p) > most {
                    break;
                }
                (take, group) = (take + 1, group + bytes_of(p));
            }
            let (now, later) = rest.split_at(take);
            rest = later;
            if group == 0 {
                out.extend(now.iter().map(|_| Vec::new()));
                continue;
            }
            let size = group.next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT);
            let buffer = match staging.take() {
                Some(b) if b.size() >= size => b,
                _ => self.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("kept_readback"),
                    size,
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                }),
            };
            let mut enc = self.device.create_command_encoder(&Default::default());
            let mut at = 0;
            for p in now.iter().filter(|p| p.n > 0) {
                let from = u64::from(p.first) * 16;
                enc.copy_buffer_to_buffer(p.records, from, &buffer, at, bytes_of(p));
                at += bytes_of(p);
            }
            self.submit_and_map_all(enc, &[(&buffer, group)], |views| {
                let mut left: &[u8] = views.first().copied().unwrap_or_default();
                for p in now {
                    let (part, after) = left.split_at((bytes_of(p) as usize).min(left.len()));
                    left = after;
                    out.push(part.to_vec());
                }
            })?;
            staging = Some(buffer);
        }
        Ok((out, staging))
    }

    /// Adds another device's kept views ([`Self::export_kept_views`]) to this one's, after its
    /// own: their records uploaded, their tables and codebook rows appended.
    ///
    /// Errors: keeping not started here, or another width ([`Error::Internal`]); tables or
    /// codebook past 2^32.
    pub(in crate::raster::gpu) fn import_kept_views(&mut self, e: KeptExport) -> Result<()> {
        let uploaded = self.kept_uploader().upload(e);
        self.import_uploaded(uploaded)
    }

    /// The uploader of kept records to this device ([`KeptUploader`]).
    pub(in crate::raster::gpu) fn kept_uploader(&self) -> KeptUploader {
        KeptUploader {
            device: self.device.clone(),
        }
    }

    /// [`Self::import_kept_views`] of a batch whose records are on this device already
    /// ([`KeptUploader::upload`]).
    ///
    /// Errors: as [`Self::import_kept_views`]; a batch uploaded to another device.
    pub(in crate::raster::gpu) fn import_uploaded(&mut self, u: UploadedKept) -> Result<()> {
        self.check_uploaded(&u)?;
        let Some(kept) = self.kept.as_mut() else {
            return Err(Error::internal(
                "importing kept views without keeping started",
            ));
        };
        let first_view = kept.import_base(u.batch.source, u.batch.continues)?;
        kept.append_uploaded(u, first_view)
    }

    /// Takes in a batch of another device's views that a streamed reduction shared between
    /// devices sent ([`super::share`]): its views after every view kept so far, whatever batch
    /// came before; keeping goes on (this device's own views and the imported ones interleave).
    ///
    /// Errors: as [`Self::import_uploaded`].
    pub(in crate::raster::gpu) fn import_streamed(&mut self, u: UploadedKept) -> Result<()> {
        self.check_uploaded(&u)?;
        let Some(kept) = self.kept.as_mut() else {
            return Err(Error::internal(
                "importing kept views without keeping started",
            ));
        };
        let first_view = kept.views.len() as u32;
        kept.append_uploaded(u, first_view)
    }

    /// Check step of the imports: `u`'s records are all on this device, of this keeping's
    /// width.
    ///
    /// Errors: [`Error::Internal`] otherwise, or without keeping started.
    fn check_uploaded(&self, u: &UploadedKept) -> Result<()> {
        if u.records.len() != u.batch.parts.len()
            || u.records.iter().any(|r| r.device != self.device)
        {
            return Err(Error::internal(
                "kept records uploaded for another device, or not all of them",
            ));
        }
        let Some(kept) = self.kept.as_ref() else {
            return Err(Error::internal(
                "importing kept views without keeping started",
            ));
        };
        if kept.dim != u.batch.dim {
            return Err(Error::internal(format!(
                "kept views of width {} imported into a reduction of width {}",
                u.batch.dim, kept.dim
            )));
        }
        Ok(())
    }
}

impl Kept {
    /// Appends an uploaded batch's views (their tables and codebook rows, as views
    /// `first_view` on) and its bands (their records on the device already).
    ///
    /// Errors: tables or codebook past 2^32; a band of a view the batch does not have
    /// ([`Error::Internal`]).
    fn append_uploaded(&mut self, u: UploadedKept, first_view: u32) -> Result<()> {
        let UploadedKept { batch: e, records } = u;
        let too_big = || Error::Invalid("the kept label tables exceed 2^32 words".into());
        for (table, rows, index) in e.views {
            let base = u32::try_from(self.tables.len()).map_err(|_| too_big())?;
            let row = u32::try_from(self.codebook.len() / self.dim).map_err(|_| too_big())?;
            self.tables.extend_from_slice(&table);
            self.codebook.extend_from_slice(&rows);
            self.views.push([base, row, index]);
        }
        for ((view, _, starts), r) in e.parts.into_iter().zip(records) {
            let view = first_view + view;
            if view as usize >= self.views.len() {
                return Err(Error::internal(format!(
                    "an imported band of view {view} of {} kept views",
                    self.views.len()
                )));
            }
            self.bytes += u64::from(r.n) * 16;
            self.peak_bytes = self.peak_bytes.max(self.bytes);
            self.parts.push(KeptPart {
                records: r.buffer,
                n: r.n,
                view,
                starts,
            });
        }
        Ok(())
    }
}

/// Per kept view of the first `n`, its label table, its codebook rows and its index in the
/// encode's view list, copied out of `kept` (in keeping order, before [`Kept::sort_by_view`]).
fn host_views(kept: &Kept, n: usize) -> Vec<(Vec<u32>, Vec<f32>, u32)> {
    (0..n.min(kept.views.len()))
        .map(|v| host_view(kept, v))
        .collect()
}

/// Kept view `v`'s label table, codebook rows and index in the encode's view list, copied out
/// of `kept` (in keeping order, before [`Kept::sort_by_view`]).
pub(super) fn host_view(kept: &Kept, v: usize) -> (Vec<u32>, Vec<f32>, u32) {
    let dim = kept.dim;
    let (table, rows) = kept.extent(v);
    (
        kept.tables[table].to_vec(),
        kept.codebook[rows.start * dim..rows.end * dim].to_vec(),
        kept.views[v][2],
    )
}

impl Kept {
    /// Where the views of an imported batch from `source` start among the kept views: a first
    /// batch (`continues` false) starts them after every view kept so far; a later one points
    /// where that source's first batch did. Keeping stops ([`Kept::stop`]).
    ///
    /// Errors: a batch that continues an export never begun ([`Error::Internal`]).
    fn import_base(&mut self, source: u32, continues: bool) -> Result<u32> {
        self.stop();
        let next = self.views.len() as u32;
        let base_of = self.import_bases.iter_mut().find(|(s, _)| *s == source);
        match (continues, base_of) {
            (true, Some((_, base))) => Ok(*base),
            (true, None) => Err(Error::internal(format!(
                "a batch of kept views continues an export of source {source} never begun"
            ))),
            (false, Some((_, base))) => {
                *base = next;
                Ok(next)
            }
            (false, None) => {
                self.import_bases.push((source, next));
                Ok(next)
            }
        }
    }

    /// Stops keeping for an exchange between devices: from here on no view is kept, and the
    /// views and bands so far are this device's own ([`Kept::own`]). Returns them.
    fn stop(&mut self) -> OwnKept {
        *self.own.get_or_insert(OwnKept {
            views: self.views.len(),
            parts: self.parts.len(),
        })
    }
}

impl KeptExport {
    /// Every kept view as the host's image stage has it after the label sums
    /// ([`KeptHostView`]), in keeping order; the records' bytes are let go part by part.
    ///
    /// Errors: a label table, codebook rows or records not of the export's layout
    /// ([`Error::Internal`]).
    pub(crate) fn into_host_views(self) -> Result<Vec<KeptHostView>> {
        let KeptExport {
            dim, views, parts, ..
        } = self;
        let mut out = views
            .into_iter()
            .map(|(table, embeddings, view)| {
                if dim == 0 || !embeddings.len().is_multiple_of(dim) {
                    return Err(Error::internal(format!(
                        "{} kept mask embedding values are not rows of {dim}",
                        embeddings.len()
                    )));
                }
                let (masks_of, factors) = table_masks(&table)?;
                Ok(KeptHostView {
                    sums: Default::default(),
                    masks_of,
                    factors,
                    embeddings,
                    view: view as usize,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let n_views = out.len();
        for (view, bytes, _) in parts {
            let v = out.get_mut(view as usize).filter(|_| bytes.len() % 16 == 0);
            let v = v.ok_or_else(|| {
                Error::internal(format!(
                    "a kept band of {} bytes of view {view} ({n_views} views)",
                    bytes.len()
                ))
            })?;
            let records: Vec<LabelSum> = bytemuck::pod_collect_to_vec(&bytes);
            v.sums.records.extend_from_slice(&records);
        }
        Ok(out)
    }
}
