//! The device reduction `E_k = Σ_i Σ_j a_kj·E_j / Σ_i Σ_j a_kj` (`ek.wgsl`): every labelled view's
//! device-reduced label sums stay on the device ([`GpuRasterizer::keep_label_sums`]) with the
//! view's label table and its masks' codebook rows, and at the end the Gaussians are reduced in
//! tiles ([`GpuRasterizer::reduce_kept`]): the same terms as the host's image stage and f64
//! reduction (`aggregate::image::expand_labels`, `aggregate::reduce`), the same unobserved rule,
//! the same kept pairs as the mixture's, without any `a_kj` crossing to the host.
//!
//! Memory on the device: each view's reduced records (16 B per (Gaussian, label) key), kept until
//! the end, counted against a budget ([`DeviceReduce::budget_bytes`]); at the end, per tile, its
//! records again with the sort's buffers (about 40 B a record) and the tile's outputs. On the
//! host: 4 B per view and block of [`BLOCK_GAUSSIANS`] Gaussians, the label tables and the
//! codebook (`M × D` f32).
//!
//! The kernels need f64 (wgpu `SHADER_F64`): a device without it keeps no views, and the encoder
//! reduces on the host.

use slag_common::{Error, Resource, Result};

use super::buffers::{storage, storage_init};
use super::reduce::record_radix_shifts;
use super::sort::{SortBuffers, groups_2d};
use super::{GROUPS_X, GpuRasterizer, Params};
use crate::raster::{
    DeviceReduce, KeptExport, KeptHostView, KeptMasks, KeptRangeCursor, KeptReduced, KeptTile,
    LabelSum,
};

/// Gaussians per block of a view's record index (`ek.wgsl` `BLOCK_GAUSSIANS`): tiles of the
/// reduction are whole blocks.
pub(super) const BLOCK_GAUSSIANS: u32 = 4096;
/// Widest embedding the kernel holds in registers (`ek.wgsl`: 64 threads × 16).
pub const MAX_DIM: usize = 1024;
/// Most kept pairs per Gaussian (`ek.wgsl` `MAX_KEEP`).
pub const MAX_KEEP: usize = 32;
/// Most bytes of kept records read back through one staging buffer at a time
/// ([`GpuRasterizer::read_parts`]): a band larger than this is read alone.
const READBACK_BYTES: u64 = 256 << 20;
/// Most bytes of one tile's outputs (meta, kept pairs, rows) and of its records. The host
/// holds a tile's outputs while it takes them in, beside the segments that run on during the
/// reduction: at 30M Gaussians, 512 MiB tiles (8 of them, the host taking one at a time)
/// peaked 0.45–0.73 GiB lower than 1 GiB tiles, in the same reduction time
/// (docs/results/scaling.md).
pub(super) const TILE_BYTES: u64 = 512 << 20;

/// The uniform of `ek.wgsl` (`EkParams`): an f64 then 10 u32, 48 bytes.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct EkParams {
    pub(super) min_total_weight: f64,
    pub(super) n_records: u32,
    pub(super) g0: u32,
    pub(super) n_tile: u32,
    pub(super) dim: u32,
    pub(super) keep: u32,
    pub(super) n_segments: u32,
    pub(super) groups_x: u32,
    pub(super) dense: u32,
    pub(super) n_blocks: u32,
    /// `block_starts`, `dominant`: the view's label-table base; `ek_fold`, `ek_finish`: the
    /// first Gaussian of the state chunk bound.
    pub(super) pad0: u32,
}

const _: () = assert!(std::mem::size_of::<EkParams>() == 48);

/// One band of a kept view: its reduced records on the device and where each block of
/// Gaussians starts among them.
pub(super) struct KeptPart {
    pub(super) records: wgpu::Buffer,
    /// Records held.
    pub(super) n: u32,
    /// The view (an index into [`Kept::views`]).
    pub(super) view: u32,
    /// `[blocks + 1]`: index of the first record of each block of [`BLOCK_GAUSSIANS`], `n` last.
    pub(super) starts: Vec<u32>,
}

/// Every kept view, and the kernels that reduce them.
pub(super) struct Kept {
    block_starts: wgpu::ComputePipeline,
    run_starts: wgpu::ComputePipeline,
    ek_reduce: wgpu::ComputePipeline,
    dominant: wgpu::ComputePipeline,
    /// The masks' record's kernel ([`super::record`]).
    pub(super) record_dominant: wgpu::ComputePipeline,
    pub(super) dim: usize,
    pub(super) budget: u64,
    pub(super) bytes: u64,
    pub(super) parts: Vec<KeptPart>,
    /// The views' label tables, one after the other (layout: see [`push_table`]).
    pub(super) tables: Vec<u32>,
    /// Per kept view, in keeping order: the base of its table in `tables`, its first codebook
    /// row, and its index in the encode's view list ([`KeptMasks::view`]).
    pub(super) views: Vec<[u32; 3]>,
    /// `[M × D]` every kept view's mask embeddings, in keeping order (in the encode's view
    /// order once [`Kept::sort_by_view`] ran).
    pub(super) codebook: Vec<f32>,
    /// Whether an export batch took the views' tables and codebook already
    /// ([`GpuRasterizer::export_kept_views_batch`]); keeping has stopped then.
    exporting: bool,
    /// This device's own views and bands, counted when keeping stopped for an exchange
    /// between devices (the first [`GpuRasterizer::export_kept_range`] or
    /// [`GpuRasterizer::import_kept_views`]): what a range export sends; imports come after.
    own: Option<OwnKept>,
    /// Per source ([`KeptExport::source`]), the first of the views its first batch brought
    /// ([`GpuRasterizer::import_kept_views`]): where the bands of its later batches point.
    import_bases: Vec<(u32, u32)>,
    /// The staging buffer of the last export batch, for the next ([`GpuRasterizer::read_parts`]).
    staging: Option<wgpu::Buffer>,
    /// The most bytes of records kept at once.
    pub(super) peak_bytes: u64,
    /// Bytes of every record kept so far.
    pub(super) total_bytes: u64,
}

/// Appends one view's label table to `tables` and returns its base: `[n_labels, factors
/// offset, n_labels + 1 mask offsets, the masks of every label, one f32 factor (bits) per
/// mask]`, offsets relative to the base. Without factors every mask's is 1.
fn push_table(tables: &mut Vec<u32>, masks: &KeptMasks<'_>, n_masks: usize) -> Result<u32> {
    let too_big = || Error::Invalid("the kept label tables exceed 2^32 words".into());
    let base = u32::try_from(tables.len()).map_err(|_| too_big())?;
    let n_labels = masks.masks_of.len();
    let header = 2 + n_labels + 1;
    let n_entries: usize = masks.masks_of.iter().map(Vec::len).sum();
    let factors_at = header + n_entries;
    let mut table = Vec::with_capacity(factors_at + n_masks);
    table.extend([n_labels as u32, factors_at as u32]);
    let mut at = header;
    for set in masks.masks_of {
        table.push(at as u32);
        at += set.len();
    }
    table.push(at as u32);
    for set in masks.masks_of {
        table.extend_from_slice(set);
    }
    for j in 0..n_masks {
        let f = masks.factors.get(j).copied().unwrap_or(1.0);
        table.push(f.to_bits());
    }
    tables.extend_from_slice(&table);
    u32::try_from(tables.len()).map_err(|_| too_big())?;
    Ok(base)
}

/// The masks of each label and each mask's factor from a view's label table ([`push_table`]'s
/// layout, `table` starting at its base).
///
/// Errors: a table that is not of that layout ([`Error::Internal`]).
fn table_masks(table: &[u32]) -> Result<(Vec<Vec<u32>>, Vec<f32>)> {
    let bad = || Error::internal(format!("a kept label table of {} words", table.len()));
    let (&n_labels, &factors_at) = (
        table.first().ok_or_else(bad)?,
        table.get(1).ok_or_else(bad)?,
    );
    let offsets = table.get(2..3 + n_labels as usize).ok_or_else(bad)?;
    let masks_of = offsets
        .windows(2)
        .map(|w| table.get(w[0] as usize..w[1] as usize).map(<[u32]>::to_vec))
        .collect::<Option<Vec<_>>>()
        .ok_or_else(bad)?;
    let factors = table.get(factors_at as usize..).ok_or_else(bad)?;
    Ok((
        masks_of,
        factors.iter().map(|&b| f32::from_bits(b)).collect(),
    ))
}

/// The dominant masks the `dominant` kernel wrote (4 words per record: Gaussian, mask, a bits,
/// 0; Gaussian `u32::MAX` where no Gaussian starts), in record order: Gaussians ascending.
fn dominant_heads(bytes: &[u8]) -> Vec<(u32, u32, f32)> {
    let words: Vec<[u32; 4]> = bytemuck::pod_collect_to_vec(bytes);
    words
        .iter()
        .filter(|w| w[0] != u32::MAX)
        .map(|w| (w[0], w[1], f32::from_bits(w[2])))
        .collect()
}

/// The kept view a band belongs to, and what its dominant masks are for
/// ([`GpuRasterizer::keep_band`]).
#[derive(Debug, Clone, Copy)]
pub(super) struct Keeping {
    /// The kept view (an index into [`Kept::views`]).
    pub(super) id: u32,
    /// Return each Gaussian's dominant mask of the band to the host.
    pub(super) dominant: bool,
    /// Enter them into the masks' record on the device ([`super::record`]) as this view of the
    /// encode (below 65,535) instead.
    pub(super) record_view: Option<u32>,
}

/// How many of the kept views and bands are a device's own, counted when keeping stopped for
/// an exchange ([`Kept::own`]).
#[derive(Debug, Clone, Copy)]
struct OwnKept {
    views: usize,
    parts: usize,
}

/// Records `[first, first + n)` of one band's buffer, to be read back
/// ([`GpuRasterizer::read_parts`]).
struct RecordSlice<'a> {
    records: &'a wgpu::Buffer,
    first: u32,
    n: u32,
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
    device: wgpu::Device,
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

/// A tile of the reduction: blocks `[b0, b1)` and, per part, its records there.
pub(super) struct Tile {
    pub(super) g0: u32,
    pub(super) n_tile: u32,
    /// Per part with records: (part, first record, count).
    pub(super) ranges: Vec<(usize, u32, u32)>,
    pub(super) records: u64,
}

impl GpuRasterizer {
    /// Starts keeping every labelled view's sums on the device for [`Self::reduce_kept`]
    /// (`dim`: the embedding width, at most [`MAX_DIM`]; `budget_bytes`: the most device memory
    /// the kept records may take). Returns whether it does: the device needs f64 and the label
    /// sums reduced on the device.
    pub(super) fn start_keeping(&mut self, dim: usize, budget_bytes: u64) -> bool {
        if !self.device.features().contains(wgpu::Features::SHADER_F64)
            || !self.reduce_on_device
            || dim == 0
            || dim > MAX_DIM
        {
            return false;
        }
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("slag-ek kernels"),
                source: wgpu::ShaderSource::Wgsl(include_str!("ek.wgsl").into()),
            });
        let pipe = |entry: &str| super::compute_pipeline(&self.device, &module, entry);
        let (block_starts, run_starts, ek_reduce, dominant, record_dominant) = (
            pipe("block_starts"),
            pipe("run_starts"),
            pipe("ek_reduce"),
            pipe("dominant"),
            pipe("record_dominant"),
        );
        if let Some(e) = pollster::block_on(scope.pop()) {
            tracing::warn!(error = %e, "the device reduction's kernels do not build here; reducing on the host");
            return false;
        }
        self.spent_kept = None;
        self.stream = None;
        self.kept = Some(Kept {
            block_starts,
            run_starts,
            ek_reduce,
            dominant,
            record_dominant,
            dim,
            budget: budget_bytes,
            bytes: 0,
            parts: Vec::new(),
            tables: Vec::new(),
            views: Vec::new(),
            codebook: Vec::new(),
            exporting: false,
            own: None,
            import_bases: Vec::new(),
            staging: None,
            peak_bytes: 0,
            total_bytes: 0,
        });
        true
    }

    /// Registers the next kept view's masks (label table, factors, embeddings) and returns its
    /// id, which [`Self::keep_band`] tags its records with.
    ///
    /// Errors: embeddings not `M × D` ([`Error::Internal`]: the image stage checked them); tables or codebook past 2^32.
    pub(super) fn begin_kept_view(&mut self, masks: &KeptMasks<'_>) -> Result<u32> {
        let Some(kept) = self
            .kept
            .as_mut()
            .filter(|k| !k.exporting && k.own.is_none())
        else {
            return Err(Error::internal(
                "a kept view without keeping started, or after its export began",
            ));
        };
        let dim = kept.dim;
        if !masks.embeddings.len().is_multiple_of(dim) {
            return Err(Error::internal(format!(
                "{} mask embedding values are not rows of {dim}",
                masks.embeddings.len()
            )));
        }
        let n_masks = masks.embeddings.len() / dim;
        let index = u32::try_from(masks.view)
            .map_err(|_| Error::Invalid(format!("view index {} past 2^32", masks.view)))?;
        let base = push_table(&mut kept.tables, masks, n_masks)?;
        let row = u32::try_from(kept.codebook.len() / dim)
            .map_err(|_| Error::Invalid("more than 2^32 kept mask embeddings".into()))?;
        kept.codebook.extend_from_slice(masks.embeddings);
        let id = kept.views.len() as u32;
        kept.views.push([base, row, index]);
        Ok(id)
    }

    /// Keeps the `n` reduced records of one band of the kept view `keeping.id` (in `reduced`,
    /// sorted by (Gaussian, label)) on the device, with the index of where each block of
    /// Gaussians starts; with [`Keeping::dominant`], also returns each Gaussian's dominant mask
    /// of the band for the masks' record (`(Gaussian, mask, a_kj)`, Gaussians ascending;
    /// `aggregate`'s rule: the largest `a_kj`, ties to the smaller mask); with
    /// [`Keeping::record_view`], enters them into the masks' record on the device instead.
    ///
    /// Errors: the kept records would pass the budget ([`Error::Limit`] `GpuMemory`, naming the
    /// flag that raises it); device failures.
    pub(super) fn keep_band(
        &mut self,
        keeping: Keeping,
        reduced: &wgpu::Buffer,
        n: u32,
    ) -> Result<Vec<(u32, u32, f32)>> {
        let bytes = u64::from(n) * 16;
        let Some(kept) = self.kept.as_ref() else {
            return Err(Error::internal("a kept band without keeping started"));
        };
        check_kept_budget(kept, bytes)?;
        let blocks = self.n.div_ceil(BLOCK_GAUSSIANS);
        let band = self.band_buffers(n, blocks, keeping.dominant);
        let mut enc = self.device.create_command_encoder(&Default::default());
        if n > 0 {
            enc.copy_buffer_to_buffer(reduced, 0, &band.records, 0, bytes);
            self.encode_band_index(&mut enc, kept, keeping, &band, (n, blocks));
        }
        let (starts, heads) = self.read_band_index(enc, &band, (n, blocks), keeping.dominant)?;
        let kept = self
            .kept
            .as_mut()
            .ok_or_else(|| Error::internal("keeping stopped"))?;
        kept.bytes += bytes;
        kept.peak_bytes = kept.peak_bytes.max(kept.bytes);
        kept.total_bytes += bytes;
        kept.parts.push(KeptPart {
            records: band.records,
            n,
            view: keeping.id,
            starts,
        });
        Ok(heads)
    }

    /// Allocation step of [`Self::keep_band`]: the band's `n` records, its index of `blocks`
    /// block starts, and room for its dominant masks (a placeholder without `dominant`).
    fn band_buffers(&self, n: u32, blocks: u32, dominant: bool) -> BandBuffers {
        let records = storage(&self.device, "kept_records", u64::from(n) * 16);
        let starts_bytes = (u64::from(blocks) + 1) * 4;
        let starts = storage(&self.device, "kept_block_starts", starts_bytes);
        let dom_bytes = if dominant { u64::from(n) * 16 } else { 4 };
        let dom = storage(&self.device, "kept_dominant", dom_bytes);
        BandBuffers {
            records,
            starts,
            starts_bytes,
            dom,
            dom_bytes,
        }
    }

    /// Dispatch step of [`Self::keep_band`]: `block_starts` over the band's `n` records and,
    /// with [`Keeping::dominant`], the `dominant` kernel on the view's own label table, or with
    /// [`Keeping::record_view`], the masks' record's kernel ([`Self::record_band`]).
    fn encode_band_index(
        &self,
        enc: &mut wgpu::CommandEncoder,
        kept: &Kept,
        keeping: Keeping,
        band: &BandBuffers,
        (n, blocks): (u32, u32),
    ) {
        let params = self.ek_uniform(&EkParams {
            n_records: n,
            n_blocks: blocks,
            groups_x: GROUPS_X,
            // The view's own table alone is uploaded (at base 0), not every view's so far.
            pad0: 0,
            ..bytemuck::Zeroable::zeroed()
        });
        let base = kept
            .views
            .get(keeping.id as usize)
            .map_or(0, |v| v[0] as usize);
        let record_view = keeping.record_view.filter(|_| self.mask_record.is_some());
        let tables = (keeping.dominant || record_view.is_some()).then(|| {
            let table = kept.tables.get(base..).unwrap_or_default();
            storage_init(&self.device, "ek_view_table", bytemuck::cast_slice(table))
        });
        let (x, y) = groups_2d(n.div_ceil(256));
        let mut pass = enc.begin_compute_pass(&Default::default());
        let bg = self.bind(
            &kept.block_starts,
            &[(0, &params), (1, &band.records), (2, &band.starts)],
        );
        pass.set_pipeline(&kept.block_starts);
        pass.set_bind_group(0, &bg, &[]);
        pass.dispatch_workgroups(x, y, 1);
        let Some(tables) = &tables else {
            return;
        };
        if let Some(view) = record_view {
            let band_bufs = [&params, &band.records, &band.starts, tables];
            self.record_band(&mut pass, kept, view, band_bufs, (x, y));
        } else {
            // `order` (2) is bound for the record reader `dominant` shares with ek_reduce;
            // `dominant` reads the records unsorted, never `order`.
            let bg = self.bind(
                &kept.dominant,
                &[
                    (0, &params),
                    (1, &band.records),
                    (2, &band.starts),
                    (4, tables),
                    (7, &band.dom),
                ],
            );
            pass.set_pipeline(&kept.dominant);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(x, y, 1);
        }
    }

    /// Readback step of [`Self::keep_band`]: submits `enc` and returns the band's block starts
    /// (all 0 for an empty band) and, with `dominant`, its dominant masks.
    ///
    /// Errors: device failures.
    fn read_band_index(
        &self,
        enc: wgpu::CommandEncoder,
        band: &BandBuffers,
        (n, blocks): (u32, u32),
        dominant: bool,
    ) -> Result<(Vec<u32>, Vec<(u32, u32, f32)>)> {
        let mut reads = vec![(&band.starts, 0, band.starts_bytes)];
        if dominant && n > 0 {
            reads.push((&band.dom, 0, band.dom_bytes));
        }
        let read = self.submit_and_read(enc, &reads)?;
        let starts: Vec<u32> = if n > 0 {
            bytemuck::pod_collect_to_vec(&read[0][..band.starts_bytes as usize])
        } else {
            vec![0; blocks as usize + 1]
        };
        let heads = match read.get(1) {
            Some(bytes) => dominant_heads(&bytes[..band.dom_bytes as usize]),
            None => Vec::new(),
        };
        Ok((starts, heads))
    }

    /// Every kept view as host data ([`KeptExport`]), for another device's reduction; keeping
    /// stops here. `None` when nothing was kept.
    ///
    /// Errors: device failures reading the records back.
    pub(super) fn export_kept_views(&mut self) -> Result<Option<KeptExport>> {
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
    pub(super) fn export_kept_views_batch(&mut self, max_bytes: u64) -> Result<Option<KeptExport>> {
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
    pub(super) fn kept_block_records(&self) -> Option<Vec<u64>> {
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
    pub(super) fn export_kept_range(
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
    fn blocks_of(&self, gaussians: std::ops::Range<u32>) -> Result<std::ops::Range<usize>> {
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
    fn read_parts(
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
    pub(super) fn import_kept_views(&mut self, e: KeptExport) -> Result<()> {
        let uploaded = self.kept_uploader().upload(e);
        self.import_uploaded(uploaded)
    }

    /// The uploader of kept records to this device ([`KeptUploader`]).
    pub(super) fn kept_uploader(&self) -> KeptUploader {
        KeptUploader {
            device: self.device.clone(),
        }
    }

    /// [`Self::import_kept_views`] of a batch whose records are on this device already
    /// ([`KeptUploader::upload`]).
    ///
    /// Errors: as [`Self::import_kept_views`]; a batch uploaded to another device.
    pub(super) fn import_uploaded(&mut self, u: UploadedKept) -> Result<()> {
        let UploadedKept { batch: e, records } = u;
        if records.len() != e.parts.len() || records.iter().any(|r| r.device != self.device) {
            return Err(Error::internal(
                "kept records uploaded for another device, or not all of them",
            ));
        }
        let Some(kept) = self.kept.as_mut() else {
            return Err(Error::internal(
                "importing kept views without keeping started",
            ));
        };
        if kept.dim != e.dim {
            return Err(Error::internal(format!(
                "kept views of width {} imported into a reduction of width {}",
                e.dim, kept.dim
            )));
        }
        let too_big = || Error::Invalid("the kept label tables exceed 2^32 words".into());
        let first_view = kept.import_base(e.source, e.continues)?;
        for (table, rows, index) in e.views {
            let base = u32::try_from(kept.tables.len()).map_err(|_| too_big())?;
            let row = u32::try_from(kept.codebook.len() / kept.dim).map_err(|_| too_big())?;
            kept.tables.extend_from_slice(&table);
            kept.codebook.extend_from_slice(&rows);
            kept.views.push([base, row, index]);
        }
        for ((view, _, starts), r) in e.parts.into_iter().zip(records) {
            let view = first_view + view;
            if view as usize >= kept.views.len() {
                return Err(Error::internal(format!(
                    "an imported band of view {view} of {} kept views",
                    kept.views.len()
                )));
            }
            kept.bytes += u64::from(r.n) * 16;
            kept.peak_bytes = kept.peak_bytes.max(kept.bytes);
            kept.parts.push(KeptPart {
                records: r.buffer,
                n: r.n,
                view,
                starts,
            });
        }
        Ok(())
    }

    /// Testing aid: the most bytes of one tile's records and outputs (default 512 MiB, and at
    /// most one binding); a tile holds at least one block of Gaussians whatever it says.
    pub fn set_reduce_tile_bytes(&mut self, bytes: Option<u64>) {
        self.reduce_tile_bytes = bytes;
    }

    /// Testing aid: the most bytes of kept records read back through one staging buffer at a
    /// time (default [`READBACK_BYTES`]); a band larger than this is read alone.
    pub fn set_readback_bytes(&mut self, bytes: Option<u64>) {
        self.readback_bytes = bytes;
    }

    /// Testing aid: whether the device counts as a CPU one (lavapipe), where only a forced
    /// device reduction keeps views ([`crate::raster::WeightRasterizer::keep_on_device`]);
    /// `false` lets `--reduce auto` keep them there too.
    pub fn set_cpu_adapter(&mut self, cpu: bool) {
        self.cpu_adapter = cpu;
    }

    /// Drops what view `view` kept so far (its bands; its table and codebook rows when it is
    /// the last view): a view whose keeping failed is not kept at all, the views before it stay.
    pub(super) fn forget_kept_view(&mut self, view: u32) {
        let Some(kept) = self.kept.as_mut() else {
            return;
        };
        let Kept {
            parts, bytes, dim, ..
        } = kept;
        parts.retain(|p| {
            if p.view == view {
                *bytes -= u64::from(p.n) * 16;
            }
            p.view != view
        });
        if kept.views.len() == view as usize + 1
            && let Some([base, row, _]) = kept.views.pop()
        {
            kept.tables.truncate(base as usize);
            kept.codebook.truncate(row as usize * *dim);
        }
    }

    pub(super) fn ek_uniform(&self, p: &EkParams) -> wgpu::Buffer {
        super::buffers::uniform_init(&self.device, "ek_params", p)
    }

    /// The tiles of the reduction: runs of whole blocks whose records fit one tile buffer and
    /// whose outputs (`out_per_gaussian` bytes each) fit `tile_bytes` (at least one block).
    ///
    /// Errors: one block holds more records than a tile can ([`Error::Limit`] `GpuBinding`).
    pub(super) fn kept_tiles(
        &self,
        parts: &[KeptPart],
        blocks: std::ops::Range<usize>,
        out_per_gaussian: u64,
        tile_bytes: u64,
    ) -> Result<Vec<Tile>> {
        self.kept_tiles_within(parts, blocks, out_per_gaussian, tile_bytes, usize::MAX)
    }

    /// [`Self::kept_tiles`] with no tile across a multiple of `chunk_blocks` blocks (the chunks
    /// of the streamed reduction's state, [`super::fold`]).
    ///
    /// Errors: as [`Self::kept_tiles`].
    pub(super) fn kept_tiles_within(
        &self,
        parts: &[KeptPart],
        blocks: std::ops::Range<usize>,
        out_per_gaussian: u64,
        tile_bytes: u64,
        chunk_blocks: usize,
    ) -> Result<Vec<Tile>> {
        let record_cap = (self.max_binding().min(tile_bytes) / 16).saturating_sub(1);
        let gaussian_cap = (self.max_binding().min(tile_bytes) / out_per_gaussian.max(1))
            .max(u64::from(BLOCK_GAUSSIANS));
        let block_records = |b: usize| -> u64 {
            parts
                .iter()
                .map(|p| u64::from(p.starts[b + 1] - p.starts[b]))
                .sum()
        };
        let mut tiles = Vec::new();
        let mut b0 = blocks.start;
        while b0 < blocks.end {
            let mut b1 = b0;
            let mut records = 0u64;
            while b1 < blocks.end {
                let more = block_records(b1);
                let gaussians = (b1 + 1 - b0) as u64 * u64::from(BLOCK_GAUSSIANS);
                let chunk_end = b1 > b0 && b1.is_multiple_of(chunk_blocks.max(1));
                if b1 > b0 && (records + more > record_cap || gaussians > gaussian_cap || chunk_end)
                {
                    break;
                }
                if more > record_cap {
                    return Err(Error::limit(
                        Resource::GpuBinding,
                        format!("{more} kept label sums for {BLOCK_GAUSSIANS} Gaussians"),
                        format!("{record_cap} per tile of the device reduction"),
                    ));
                }
                records += more;
                b1 += 1;
            }
            let g0 = b0 as u32 * BLOCK_GAUSSIANS;
            let g1 = (b1 as u32 * BLOCK_GAUSSIANS).min(self.n);
            let ranges = parts
                .iter()
                .enumerate()
                .filter_map(|(i, p)| {
                    let (s, e) = (p.starts[b0], p.starts[b1]);
                    (e > s).then_some((i, s, e - s))
                })
                .collect();
            tiles.push(Tile {
                g0,
                n_tile: g1 - g0,
                ranges,
                records,
            });
            b0 = b1;
        }
        Ok(tiles)
    }

    /// Reduces every kept view (see the module docs), tile by tile of Gaussian ids ascending
    /// (those of [`DeviceReduce::gaussians`] only, when given), handing each tile's observed
    /// Gaussians to `sink`; keeping stops, and the kept records are freed with the rasterizer
    /// (or when keeping starts again). Returns the number of tiles and the codebook.
    ///
    /// Errors: nothing kept ([`Error::Internal`]); `p.keep` above [`MAX_KEEP`] ([`Error::Param`]);
    /// a range of Gaussians not on block bounds ([`Error::Internal`]); device failures; `sink`'s.
    pub(super) fn reduce_kept_tiles(
        &mut self,
        p: &DeviceReduce,
        sink: &mut dyn FnMut(KeptTile) -> Result<()>,
    ) -> Result<KeptReduced> {
        let Some(mut kept) = self.kept.take() else {
            return Err(Error::internal("the device reduction has no kept views"));
        };
        if p.keep == 0 || p.keep > MAX_KEEP {
            return Err(Error::param(
                "mixture_keep",
                p.keep,
                format!("1 to {MAX_KEEP} for the device reduction (or --reduce host)"),
            ));
        }
        let blocks = self.blocks_of(p.gaussians.map_or(0..self.n, |(a, b)| a..b))?;
        kept.sort_by_view();
        let dim = kept.dim;
        let tile_bytes = self.reduce_tile_bytes.unwrap_or(TILE_BYTES);
        let out_per_gaussian = 8 + p.keep as u64 * 8 + if p.dense { dim as u64 * 4 } else { 0 };
        let tiles = self.kept_tiles(&kept.parts, blocks, out_per_gaussian, tile_bytes)?;
        let tables = storage_init(
            &self.device,
            "ek_tables",
            bytemuck::cast_slice(&kept.tables),
        );
        let codebook = storage_init(
            &self.device,
            "ek_codebook",
            bytemuck::cast_slice(&kept.codebook),
        );
        let shared = TileShared {
            kept: &kept,
            tables: &tables,
            codebook: &codebook,
            p,
        };
        let mut sort: Option<SortBuffers> = None;
        let largest = tiles.iter().map(|t| u64::from(t.n_tile)).max().unwrap_or(0);
        let staging = TileStaging::new(&self.device, largest, p, dim);
        let (mut device_s, mut sink_s) = (0.0, 0.0);
        for tile in &tiles {
            let t0 = std::time::Instant::now();
            let out = self.reduce_tile(&shared, tile, &mut sort, &staging)?;
            let t1 = std::time::Instant::now();
            sink(out)?;
            device_s += (t1 - t0).as_secs_f64();
            sink_s += t1.elapsed().as_secs_f64();
        }
        // Where the reduction's time goes: the tiles on the device (with their readback), and
        // the host's sink (the mixture's rows, the dense rows) after each.
        tracing::info!(
            target: "slag_encoder::pipeline",
            tiles = tiles.len(),
            device_s = format!("{device_s:.2}"),
            sink_s = format!("{sink_s:.2}"),
            "device reduction"
        );
        let codebook = std::mem::take(&mut kept.codebook);
        let (peak_kept_bytes, records_bytes) = (kept.peak_bytes, kept.total_bytes);
        self.spent_kept = Some(kept);
        Ok(KeptReduced {
            tiles: tiles.len(),
            codebook,
            waves: 1,
            state_bytes: 0,
            peak_kept_bytes,
            records_bytes,
        })
    }

    /// One tile: its records gathered view by view, sorted by Gaussian, reduced, read back.
    fn reduce_tile(
        &self,
        s: &TileShared<'_>,
        tile: &Tile,
        sort: &mut Option<SortBuffers>,
        staging: &TileStaging,
    ) -> Result<KeptTile> {
        let (p, dim) = (s.p, s.kept.dim);
        let n = tile.records as u32;
        let mut phases = TilePhases::new();
        // The tile's records after a 4-word header (the layout record_keys reads).
        let recs = storage(&self.device, "ek_tile_records", 16 + tile.records * 16);
        let mut enc = self.device.create_command_encoder(&Default::default());
        let views = &s.kept.views;
        let segs = gather_tile_records(&mut enc, &s.kept.parts, tile, &recs, |part| {
            let [base, row, _] = views[part.view as usize];
            [base, row]
        });
        let segs_buf = storage_init(&self.device, "ek_segments", bytemuck::cast_slice(&segs));
        let out = TileOutputs::new(&self.device, tile, p, dim);
        for b in [&out.meta, &out.kept, &out.rows, &out.run_start] {
            enc.clear_buffer(b, 0, None);
        }
        enc = self.phase_end(enc, &mut phases)?;
        let order = if n > 0 {
            Some(self.sort_tile(&mut enc, &recs, n, sort)?)
        } else {
            None
        };
        enc = self.phase_end(enc, &mut phases)?;
        if let Some(order) = &order {
            let inputs = [&recs, order, &segs_buf];
            self.encode_ek_reduce(&mut enc, s, tile, segs.len() as u32, inputs, &out);
        }
        enc = self.phase_end(enc, &mut phases)?;
        let sizes = output_bytes(u64::from(tile.n_tile), p, dim);
        let staged: Vec<(&wgpu::Buffer, u64)> = staging.buffers.iter().zip(sizes).collect();
        for (src, &(dst, size)) in [&out.meta, &out.kept, &out.rows].into_iter().zip(&staged) {
            enc.copy_buffer_to_buffer(src, 0, dst, 0, size);
        }
        let output = self.submit_and_map_all(enc, &staged, |read| {
            phases.mark();
            tile_output(tile, p, dim, read)
        })?;
        phases.mark();
        phases.log(tile);
        Ok(output)
    }

    /// With the reduction's debug log on, ends a phase of [`Self::reduce_tile`]: submits `enc`,
    /// waits for the device and marks the time, returning a new encoder; otherwise returns `enc`
    /// as it is (one submission per tile).
    ///
    /// Errors: waiting for the device fails.
    fn phase_end(
        &self,
        enc: wgpu::CommandEncoder,
        phases: &mut TilePhases,
    ) -> Result<wgpu::CommandEncoder> {
        if phases.marks.is_none() {
            return Ok(enc);
        }
        self.queue.submit([enc.finish()]);
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| super::gpu_err("waiting for the device reduction failed", e))?;
        phases.mark();
        Ok(self.device.create_command_encoder(&Default::default()))
    }

    /// Dispatch step of [`Self::reduce_tile`]: `run_starts` over the tile's sorted records, then
    /// `ek_reduce` over the tile's Gaussians, reading `[records, sorted order, segments]` and
    /// writing its outputs.
    fn encode_ek_reduce(
        &self,
        enc: &mut wgpu::CommandEncoder,
        s: &TileShared<'_>,
        tile: &Tile,
        n_segments: u32,
        [recs, order, segs]: [&wgpu::Buffer; 3],
        out: &TileOutputs,
    ) {
        let (kept, p) = (s.kept, s.p);
        let n = tile.records as u32;
        let params = self.ek_uniform(&EkParams {
            min_total_weight: p.min_total_weight,
            n_records: n,
            g0: tile.g0,
            n_tile: tile.n_tile,
            dim: kept.dim as u32,
            keep: p.keep as u32,
            n_segments,
            groups_x: GROUPS_X,
            dense: u32::from(p.dense),
            n_blocks: 0,
            pad0: 0,
        });
        let starts = self.bind(
            &kept.run_starts,
            &[(0, &params), (1, recs), (2, order), (11, &out.run_start)],
        );
        let bg = self.bind(
            &kept.ek_reduce,
            &[
                (0, &params),
                (1, recs),
                (2, order),
                (3, segs),
                (4, s.tables),
                (5, s.codebook),
                (6, &out.meta),
                (7, &out.kept),
                (8, &out.rows),
                (11, &out.run_start),
            ],
        );
        let mut pass = enc.begin_compute_pass(&Default::default());
        pass.set_pipeline(&kept.run_starts);
        pass.set_bind_group(0, &starts, &[]);
        let (x, y) = groups_2d(n.div_ceil(256));
        pass.dispatch_workgroups(x, y, 1);
        pass.set_pipeline(&kept.ek_reduce);
        pass.set_bind_group(0, &bg, &[]);
        let (x, y) = groups_2d(tile.n_tile);
        pass.dispatch_workgroups(x, y, 1);
    }

    /// Records the stable sort of the tile's `n` records by Gaussian (the raster module's
    /// `record_keys` and radix passes over the Gaussian-id bits only) and returns the buffer of
    /// sorted record indices.
    pub(super) fn sort_tile(
        &self,
        enc: &mut wgpu::CommandEncoder,
        recs: &wgpu::Buffer,
        n: u32,
        kept: &mut Option<SortBuffers>,
    ) -> Result<wgpu::Buffer> {
        let sb = self.sort_buffers(kept.take(), u64::from(n));
        let shifts = record_radix_shifts(0, self.n);
        let base = Params {
            n_keys: n,
            n_pixels: n,
            groups_x: GROUPS_X,
            ..bytemuck::Zeroable::zeroed()
        };
        let radix = self.radix_params(n, &shifts, &base);
        let params = self.uniform(&base);
        let (x, y) = groups_2d(n.div_ceil(256));
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            let p = &self.pipelines;
            let bg = self.bind(
                &p.record_keys,
                &[
                    (0, &params),
                    (13, recs),
                    (16, &sb.keys[0]),
                    (17, &sb.vals[0]),
                ],
            );
            pass.set_pipeline(&p.record_keys);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(x, y, 1);
            self.encode_radix_passes(&mut pass, &sb, n, &radix);
        }
        let order = sb.vals[shifts.len() % 2].clone();
        *kept = Some(sb);
        Ok(order)
    }
}

/// The device buffers of one kept band ([`GpuRasterizer::keep_band`]): its records, the index
/// of where each block of Gaussians starts, and its dominant masks, with their sizes in bytes.
struct BandBuffers {
    records: wgpu::Buffer,
    starts: wgpu::Buffer,
    starts_bytes: u64,
    dom: wgpu::Buffer,
    dom_bytes: u64,
}

/// Budget step of [`GpuRasterizer::keep_band`]: `bytes` more kept records stay within the
/// budget.
///
/// Errors: past it ([`Error::Limit`] `GpuMemory`, naming the flag that raises it).
fn check_kept_budget(kept: &Kept, bytes: u64) -> Result<()> {
    if kept.bytes + bytes > kept.budget {
        return Err(Error::limit(
            Resource::GpuMemory,
            format!(
                "{} MiB of label sums kept on the device for the reduction",
                (kept.bytes + bytes) >> 20
            ),
            format!(
                "{} MiB (--device-reduce-memory-mb; or --reduce host)",
                kept.budget >> 20
            ),
        ));
    }
    Ok(())
}

/// Gather step of [`GpuRasterizer::reduce_tile`]: records the copies of every part's records
/// in the tile into `recs` (after its 4-word header) and returns per part its segment: first
/// record, view, table base, codebook row (one zero segment when the tile has none).
pub(super) fn gather_tile_records(
    enc: &mut wgpu::CommandEncoder,
    parts: &[KeptPart],
    tile: &Tile,
    recs: &wgpu::Buffer,
    table_and_row: impl Fn(&KeptPart) -> [u32; 2],
) -> Vec<[u32; 4]> {
    let mut segs: Vec<[u32; 4]> = Vec::with_capacity(tile.ranges.len().max(1));
    let mut at = 0u32;
    for &(i, first, count) in &tile.ranges {
        let part = &parts[i];
        let [base, row] = table_and_row(part);
        segs.push([at, part.view, base, row]);
        enc.copy_buffer_to_buffer(
            &part.records,
            u64::from(first) * 16,
            recs,
            16 + u64::from(at) * 16,
            u64::from(count) * 16,
        );
        at += count;
    }
    if segs.is_empty() {
        segs.push([0; 4]);
    }
    segs
}

/// The outputs of one tile of the reduction: per Gaussian its meta (observed, total weight)
/// and kept pairs, and with `p.dense` its row (a placeholder without); and per Gaussian where
/// its sorted records start (`run_starts`, read by `ek_reduce`).
struct TileOutputs {
    meta: wgpu::Buffer,
    kept: wgpu::Buffer,
    rows: wgpu::Buffer,
    run_start: wgpu::Buffer,
}

impl TileOutputs {
    /// Allocation step of [`GpuRasterizer::reduce_tile`]: the tile's output buffers.
    fn new(device: &wgpu::Device, tile: &Tile, p: &DeviceReduce, dim: usize) -> Self {
        let n_tile = u64::from(tile.n_tile);
        let bytes = output_bytes(n_tile, p, dim);
        TileOutputs {
            meta: storage(device, "ek_meta", bytes[0]),
            kept: storage(device, "ek_kept", bytes[1]),
            // A placeholder without the dense rows.
            rows: storage(device, "ek_rows", bytes.get(2).copied().unwrap_or(4)),
            run_start: storage(device, "ek_run_start", n_tile * 4),
        }
    }
}

/// Where one tile's time goes, kept only while the reduction's debug log is on (target
/// `slag_encoder::pipeline`): the device is then waited for after each phase (gather and
/// clear, sort, reduce, readback), and the host's conversion of the outputs is timed.
struct TilePhases {
    /// The start, then one instant per phase end.
    marks: Option<Vec<std::time::Instant>>,
}

impl TilePhases {
    const NAMES: [&str; 5] = ["gather_s", "sort_s", "reduce_s", "read_s", "output_s"];

    fn new() -> Self {
        let on = tracing::enabled!(target: "slag_encoder::pipeline", tracing::Level::DEBUG);
        TilePhases {
            marks: on.then(|| vec![std::time::Instant::now()]),
        }
    }

    fn mark(&mut self) {
        if let Some(m) = &mut self.marks {
            m.push(std::time::Instant::now());
        }
    }

    /// The debug line of one tile: its Gaussians, records and seconds per phase.
    fn log(&self, tile: &Tile) {
        let Some(m) = &self.marks else { return };
        let phases: Vec<String> = Self::NAMES
            .iter()
            .zip(m.windows(2))
            .map(|(name, w)| format!("{name}={:.3}", (w[1] - w[0]).as_secs_f64()))
            .collect();
        tracing::debug!(
            target: "slag_encoder::pipeline",
            g0 = tile.g0,
            gaussians = tile.n_tile,
            records = tile.records,
            phases = phases.join(" "),
            "device reduction tile"
        );
    }
}

/// The host-visible buffers each tile's outputs are copied to and read from (meta, kept pairs,
/// and with `p.dense` the rows), made once for the largest tile: a new mapping per tile of
/// hundreds of MB costs more than the copy.
pub(super) struct TileStaging {
    pub(super) buffers: Vec<wgpu::Buffer>,
}

impl TileStaging {
    pub(super) fn new(device: &wgpu::Device, largest: u64, p: &DeviceReduce, dim: usize) -> Self {
        let buffers = output_bytes(largest, p, dim)
            .into_iter()
            .map(|size| {
                device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("ek_staging"),
                    size: size.max(4).next_multiple_of(4),
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                })
            })
            .collect();
        TileStaging { buffers }
    }
}

/// Bytes of the outputs read back for `n` Gaussians: meta, kept pairs, and with `p.dense`
/// the rows.
pub(super) fn output_bytes(n: u64, p: &DeviceReduce, dim: usize) -> Vec<u64> {
    let mut sizes = vec![n * 8, n * p.keep as u64 * 8];
    if p.dense {
        sizes.push(n * dim as u64 * 4);
    }
    sizes
}

/// What every tile of one reduction shares.
struct TileShared<'a> {
    kept: &'a Kept,
    tables: &'a wgpu::Buffer,
    codebook: &'a wgpu::Buffer,
    p: &'a DeviceReduce,
}

/// The observed Gaussians of a tile from its read-back outputs (`read`: meta, kept pairs, and
/// with `p.dense` the rows), converted on every thread in chunks of Gaussians, then joined in
/// order (millions of Gaussians per tile).
pub(super) fn tile_output(tile: &Tile, p: &DeviceReduce, dim: usize, read: &[&[u8]]) -> KeptTile {
    use rayon::prelude::*;
    const CHUNK: usize = 1 << 16;
    let n_tile = tile.n_tile as usize;
    let parts: Vec<KeptTile> = (0..n_tile.div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| tile_output_range(tile, p, dim, read, c * CHUNK..((c + 1) * CHUNK).min(n_tile)))
        .collect();
    let mut out = KeptTile {
        kept_starts: vec![0],
        ..KeptTile::default()
    };
    for part in parts {
        let base = out.kept.len() as u32;
        out.ids.extend_from_slice(&part.ids);
        out.total_weights.extend_from_slice(&part.total_weights);
        out.kept_starts
            .extend(part.kept_starts[1..].iter().map(|&e| base + e));
        out.kept.extend_from_slice(&part.kept);
        out.rows.extend_from_slice(&part.rows);
    }
    out
}

/// [`tile_output`] of the tile's Gaussians `range` (tile indices). Read-back bytes carry no
/// alignment: each value is read, not cast in place.
fn tile_output_range(
    tile: &Tile,
    p: &DeviceReduce,
    dim: usize,
    read: &[&[u8]],
    range: std::ops::Range<usize>,
) -> KeptTile {
    let pair = |bytes: &[u8], i: usize| -> [u32; 2] {
        bytemuck::pod_read_unaligned(&bytes[i * 8..i * 8 + 8])
    };
    let mut out = KeptTile {
        kept_starts: vec![0],
        ..KeptTile::default()
    };
    // One flat list of pairs, not a list per Gaussian: tens of millions of Gaussians per
    // reduction.
    for i in range {
        let m = pair(read[0], i);
        if m[0] != 1 {
            continue;
        }
        out.ids.push(tile.g0 + i as u32);
        out.total_weights.push(f32::from_bits(m[1]));
        let used = (i * p.keep..(i + 1) * p.keep)
            .map(|s| pair(read[1], s))
            .filter(|s| s[0] != u32::MAX);
        out.kept.extend(used.map(|s| (f32::from_bits(s[1]), s[0])));
        out.kept_starts.push(out.kept.len() as u32);
        if p.dense {
            let row = &read[2][i * dim * 4..(i + 1) * dim * 4];
            out.rows.extend(
                row.chunks_exact(4)
                    .map(|b| f32::from_ne_bytes([b[0], b[1], b[2], b[3]])),
            );
        }
    }
    out
}

/// Per kept view of the first `n`, its label table, its codebook rows and its index in the
/// encode's view list, copied out of `kept` (in keeping order, before [`Kept::sort_by_view`]).
fn host_views(kept: &Kept, n: usize) -> Vec<(Vec<u32>, Vec<f32>, u32)> {
    let dim = kept.dim;
    (0..n.min(kept.views.len()))
        .map(|v| {
            let (table, rows) = kept.extent(v);
            (
                kept.tables[table].to_vec(),
                kept.codebook[rows.start * dim..rows.end * dim].to_vec(),
                kept.views[v][2],
            )
        })
        .collect()
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

    /// View `v`'s words of `tables` and rows of the codebook: from its own starts to the next
    /// view's (or the ends). Holds while both follow keeping order, before
    /// [`Kept::sort_by_view`] moves the rows.
    fn extent(&self, v: usize) -> (std::ops::Range<usize>, std::ops::Range<usize>) {
        let [base, row, _] = self.views[v];
        let (table_end, row_end) = match self.views.get(v + 1) {
            Some(&[b, r, _]) => (b as usize, r as usize),
            None => (self.tables.len(), self.codebook.len() / self.dim),
        };
        (base as usize..table_end, row as usize..row_end)
    }

    /// Puts the kept views in the encode's view order, whatever order they were kept in (the
    /// fronts finish views in no fixed order, and a second device's views come after the
    /// first's): the codebook's rows by view index and then mask, each view's first row moved
    /// with them, and the bands by view index (a view's bands in keeping order). The reduction
    /// then numbers its atoms, breaks ties between equal `a_kj` (the smaller row) and adds the
    /// views' terms in one order for every run, so that the same encode writes the same bytes.
    pub(super) fn sort_by_view(&mut self) {
        let dim = self.dim;
        let mut order: Vec<usize> = (0..self.views.len()).collect();
        order.sort_by_key(|&v| (self.views[v][2], v));
        // Each view's rows in keeping order, before any first row moves.
        let rows: Vec<std::ops::Range<usize>> =
            (0..self.views.len()).map(|v| self.extent(v).1).collect();
        let mut rank = vec![0u32; self.views.len()];
        let mut codebook = Vec::with_capacity(self.codebook.len());
        for (r, &v) in order.iter().enumerate() {
            rank[v] = r as u32;
            self.views[v][1] = (codebook.len() / dim) as u32;
            codebook.extend_from_slice(&self.codebook[rows[v].start * dim..rows[v].end * dim]);
        }
        self.codebook = codebook;
        self.parts.sort_by_key(|p| rank[p.view as usize]);
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

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn a_label_table_reads_back_as_written() {
        let masks_of = vec![vec![], vec![0, 2], vec![1]];
        let factors = [0.5f32, 2.0, 1.25];
        let embeddings = [0.0f32; 6];
        let mut tables = vec![7, 7, 7];
        for (f, n) in [(&factors[..], 3), (&[][..], 3)] {
            let masks = KeptMasks {
                masks_of: &masks_of,
                factors: f,
                embeddings: &embeddings,
                dominant: false,
                view: 0,
            };
            let base = push_table(&mut tables, &masks, n).unwrap() as usize;
            let (m, got) = table_masks(&tables[base..]).unwrap();
            assert_eq!(m, masks_of);
            // Without factors every mask's is 1.
            let want = if f.is_empty() {
                vec![1.0; 3]
            } else {
                f.to_vec()
            };
            assert_eq!(got, want);
            tables.truncate(base + 2);
            assert!(table_masks(&tables[base..]).is_err(), "a cut table");
        }
    }
}
