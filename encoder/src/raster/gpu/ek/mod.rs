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
//!
//! The files: [`tables`] lays out each view's label table; [`keep`] keeps a view's bands on the
//! device within the budget; [`exchange`] moves kept views between devices and to the host;
//! [`share`] sends each view to the other devices of a streamed reduction shared between them;
//! [`tiles`] reduces the kept records tile by tile. This file holds the state they share.

mod exchange;
mod keep;
mod share;
mod tables;
mod tiles;

pub use exchange::{KeptUploader, UploadedKept};
pub use share::KeptInbox;
pub(super) use share::share_gaussians;
pub(super) use tiles::{Tile, TileStaging, gather_tile_records, output_bytes, tile_output};

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

impl Kept {
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
