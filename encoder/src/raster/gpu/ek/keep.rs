//! Keeping views on the device: each labelled view's reduced label sums (its bands of
//! records, their block index and dominant masks) stay there until the reduction, counted
//! against the budget.

use slag_common::{Error, Resource, Result};

use super::tables::push_table;
use super::{BLOCK_GAUSSIANS, EkParams, Keeping, Kept, KeptPart, MAX_DIM};
use crate::raster::KeptMasks;
use crate::raster::gpu::buffers::{storage, storage_init};
use crate::raster::gpu::sort::groups_2d;
use crate::raster::gpu::{GROUPS_X, GpuRasterizer};

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

impl GpuRasterizer {
    /// Starts keeping every labelled view's sums on the device for [`Self::reduce_kept`]
    /// (`dim`: the embedding width, at most [`MAX_DIM`]; `budget_bytes`: the most device memory
    /// the kept records may take). Returns whether it does: the device needs f64 and the label
    /// sums reduced on the device.
    pub(in crate::raster::gpu) fn start_keeping(&mut self, dim: usize, budget_bytes: u64) -> bool {
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
                source: wgpu::ShaderSource::Wgsl(include_str!("../ek.wgsl").into()),
            });
        let pipe = |entry: &str| crate::raster::gpu::compute_pipeline(&self.device, &module, entry);
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
    pub(in crate::raster::gpu) fn begin_kept_view(&mut self, masks: &KeptMasks<'_>) -> Result<u32> {
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
    pub(in crate::raster::gpu) fn keep_band(
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
    pub(in crate::raster::gpu) fn forget_kept_view(&mut self, view: u32) {
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
