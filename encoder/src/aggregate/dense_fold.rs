//! The dense reduction (`--dense`) folded on the host view by view ([`DenseFold`]): each view's
//! `a_kj` are added to per-Gaussian f64 accumulators (`Σ a_kj·E_j`, `D` values, and `Σ a_kj`)
//! as soon as every view before it is in, and then freed, so that the host never holds every
//! view's records. The accumulators are tiled by ranges of Gaussian ids; the tiles that do not
//! fit in `--accumulator-memory-mb` live in spill files, and the views then wait in a batch (up
//! to `--contribution-memory-mb`) that is added to every tile in one sweep.
//!
//! The sums are f64 and run, per Gaussian, in view order then entry order: the order the
//! all-kept reduction ([`super::reduce_to_writer`]) adds them in. A spilled tile is stored as
//! the f64 bits themselves. So the rows written are, bit for bit, those of keeping every view.

use std::collections::BTreeMap;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use slag_common::embeddings::EmbeddingsWriter;
use slag_common::mixture::SparseMixture;
use slag_common::{Error, Resource, Result};

use super::fold::check_view;
use super::reduce::{add_entries, first_entry_of, reduced_rows};
use super::{MixtureFold, Reduced, StoredImage};

/// Gaussians per parallel block of a tile (each block one rayon task, its sums in the core's
/// cache while the batch's views are added); a tile holds whole blocks.
const BLOCK: usize = 128;

/// Bytes of one spill file's read and write buffer.
const IO_CHUNK: usize = 1 << 20;

/// Knobs of a [`DenseFold`].
#[derive(Debug, Clone, PartialEq)]
pub struct DenseFoldParams {
    /// A Gaussian whose `Σ a_kj` is below this, or whose `‖Σ a_kj·E_j‖` is at most
    /// `1e-9·Σ a_kj`, is unobserved (the rule of [`super::reduce`]).
    pub min_total_weight: f64,
    /// Bytes of f64 accumulators held in memory (`--accumulator-memory-mb`): the tiles beyond
    /// it are spilled. At least two tiles of [`BLOCK`] Gaussians are held whatever it says.
    pub accumulator_budget_bytes: usize,
    /// Bytes of views that wait in a batch for a sweep over the spilled tiles
    /// (`--contribution-memory-mb`, counted as [`StoredImage::bytes`]); a batch holds at least
    /// one view. Unused when no tile is spilled (each view is then added as it comes).
    pub batch_budget_bytes: usize,
    /// Folder of the spill files, created at the first spill and removed with the fold.
    pub spill_dir: PathBuf,
    /// With the mixture: the pairs kept per Gaussian ([`MixtureFold`]).
    pub mixture_keep: Option<usize>,
}

/// What the fold did, for the report (`counts.dense_fold`).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct DenseFoldStats {
    /// Tiles of Gaussian ids.
    pub tiles: usize,
    /// Tiles that live in spill files.
    pub tiles_spilled: usize,
    /// Sweeps of a batch of views over the tiles.
    pub batches: usize,
    /// Bytes written to spill files.
    pub spill_bytes_written: u64,
    /// The most bytes the fold held at once: the accumulators in memory, the batch and the
    /// views waiting for an earlier one (the mixture's state is not in it: see
    /// [`DenseFolded::peak_bytes`]).
    pub peak_bytes: u64,
}

/// What [`DenseFold::finish`] leaves.
pub struct DenseFolded {
    /// The dense file's writer, every observed row pushed (call [`EmbeddingsWriter::finish`]).
    pub writer: EmbeddingsWriter,
    /// With the mixture: its sparse parts over exactly the Gaussians written.
    pub sparse: Option<SparseMixture>,
    /// Rows written.
    pub observed: usize,
    /// What the fold did.
    pub stats: DenseFoldStats,
    /// The fold's peak ([`DenseFoldStats::peak_bytes`]) plus the mixture's running state at the
    /// end (its pairs per Gaussian and the `M × D` f32 codebook).
    pub peak_bytes: u64,
}

/// The host's streamed dense reduction: views pushed in any order ([`DenseFold::push`]) are
/// folded in view order into f64 accumulators tiled by Gaussian ids, and, with the mixture, into
/// a [`MixtureFold`]. Memory: at most `accumulator_budget_bytes` of accumulators (two tiles of
/// 128 Gaussians at least), the batch (`batch_budget_bytes` plus one view, only while a tile is
/// spilled), the views that arrived before an earlier one, and the mixture's state; none of it
/// grows with the views but for the mixture's codebook. Disk: `N × (D + 1) × 8` bytes less the
/// tiles in memory, in [`DenseFoldParams::spill_dir`]; each spill file is written to a
/// `.partial` name and renamed, and every file and the folder are removed when the fold is
/// dropped (at the end, or on an error).
pub struct DenseFold {
    dim: usize,
    min_total_weight: f64,
    tiles: Tiles,
    batch: Vec<StoredImage>,
    batch_bytes: usize,
    batch_budget: usize,
    /// The next view to fold: every view below it is folded or never comes.
    next: usize,
    /// Views that arrived before `next` reached them, by view index.
    pending: BTreeMap<usize, StoredImage>,
    pending_bytes: usize,
    mixture: Option<MixtureFold>,
    stats: DenseFoldStats,
    pushed: usize,
}

impl DenseFold {
    /// An empty fold for `n_gaussians` Gaussians of `dim`-wide mask embeddings.
    ///
    /// Errors: [`Error::Param`] `dim` for a width of 0; the mixture's ([`MixtureFold::new`]).
    pub fn new(n_gaussians: usize, dim: usize, p: DenseFoldParams) -> Result<Self> {
        if dim == 0 {
            return Err(Error::param("dim", dim, "an embedding width of at least 1"));
        }
        let mixture = p
            .mixture_keep
            .map(|keep| MixtureFold::new(n_gaussians, dim, keep, p.min_total_weight))
            .transpose()?;
        let tiles = Tiles::new(n_gaussians, dim, p.accumulator_budget_bytes, p.spill_dir);
        let stats = DenseFoldStats {
            tiles: tiles.count(),
            tiles_spilled: tiles.count() - tiles.resident.len(),
            ..Default::default()
        };
        Ok(DenseFold {
            dim,
            min_total_weight: p.min_total_weight,
            batch_budget: if stats.tiles_spilled > 0 {
                p.batch_budget_bytes
            } else {
                0
            },
            tiles,
            batch: Vec::new(),
            batch_bytes: 0,
            next: 0,
            pending: BTreeMap::new(),
            pending_bytes: 0,
            mixture,
            stats,
            pushed: 0,
        })
    }

    /// Views pushed so far.
    pub fn len(&self) -> usize {
        self.pushed
    }

    /// True before the first view.
    pub fn is_empty(&self) -> bool {
        self.pushed == 0
    }

    /// What the fold did so far.
    pub fn stats(&self) -> DenseFoldStats {
        self.stats
    }

    /// Adds view `view`'s `a_kj` (its index in the encode's view list, each view once): taken
    /// in now when every view below it is in (with the views waiting behind it), else kept until
    /// they are. A view taken in is folded into the mixture at once and into the accumulators
    /// at once, or with its batch when a tile is spilled.
    ///
    /// Errors: a view pushed twice or one already passed ([`Error::Internal`]); mask embeddings
    /// of another width ([`Error::Mismatch`]); a Gaussian id past the scene or a mask past the
    /// view's embeddings ([`Error::Invalid`]); spill-file I/O ([`Error::Io`], a full disk as
    /// [`Error::Limit`] [`Resource::DiskSpace`]).
    pub fn push(&mut self, view: usize, c: StoredImage) -> Result<()> {
        if view < self.next || self.pending.contains_key(&view) {
            return Err(Error::internal(format!(
                "view {view} reached the host's dense reduction twice"
            )));
        }
        self.pushed += 1;
        self.pending_bytes += c.bytes();
        self.pending.insert(view, c);
        self.note_peak();
        while let Some(c) = self.pending.remove(&self.next) {
            self.pending_bytes -= c.bytes();
            self.take_in(self.next, c)?;
            self.next += 1;
        }
        Ok(())
    }

    /// View `view` (the next) into the mixture and the batch; the batch swept over the tiles
    /// once it holds its budget.
    fn take_in(&mut self, view: usize, c: StoredImage) -> Result<()> {
        let masks = c.mask_embeddings.len() / self.dim;
        check_view(&c, self.dim, masks, self.tiles.n_gaussians)?;
        if let Some(m) = self.mixture.as_mut() {
            m.fold_next(view, &c)?;
        }
        self.batch_bytes += c.bytes();
        self.batch.push(c);
        self.note_peak();
        if self.batch_bytes >= self.batch_budget {
            self.sweep()?;
        }
        Ok(())
    }

    /// Adds the batch's views, in view order, to every tile its entries reach, then frees them.
    fn sweep(&mut self) -> Result<()> {
        if self.batch.is_empty() {
            return Ok(());
        }
        self.stats.batches += 1;
        let batch = std::mem::take(&mut self.batch);
        self.batch_bytes = 0;
        for t in 0..self.tiles.count() {
            let ids = self.tiles.ids(t);
            let reached = batch.iter().any(|c| {
                let lo = first_entry_of(c, ids.start as u32);
                c.gaussians.get(lo).is_some_and(|&g| (g as usize) < ids.end)
            });
            if !reached {
                continue;
            }
            let written = self
                .tiles
                .with_tile(t, |sums| add_batch(sums, &batch, self.dim))?;
            self.stats.spill_bytes_written += written;
        }
        Ok(())
    }

    /// Records the bytes held now in the peak.
    fn note_peak(&mut self) {
        let held = self.tiles.bytes() + self.batch_bytes + self.pending_bytes;
        self.stats.peak_bytes = self.stats.peak_bytes.max(held as u64);
    }

    /// The outputs: every view still waiting taken in (in view order) and the last batch swept,
    /// then each tile's observed rows (the rule of [`super::reduce`]: unit `E_k` rounded to f32,
    /// `Σ a_kj` as f32) pushed to `writer` in id order with their centres `means` (`[N]`, world
    /// frame), and the mixture's sparse parts (with `model_id`) over exactly those Gaussians.
    ///
    /// Errors: as [`Self::push`]; the writer's (I/O, non-finite rows); [`Error::Internal`] when
    /// `means` is not `[N]`.
    pub fn finish(
        mut self,
        means: &[[f32; 3]],
        model_id: &str,
        mut writer: EmbeddingsWriter,
    ) -> Result<DenseFolded> {
        if means.len() != self.tiles.n_gaussians {
            return Err(Error::internal(format!(
                "the host's dense fold: {} means for {} Gaussians",
                means.len(),
                self.tiles.n_gaussians
            )));
        }
        for (view, c) in std::mem::take(&mut self.pending) {
            self.pending_bytes -= c.bytes();
            self.take_in(view, c)?;
        }
        self.sweep()?;
        let mut observed = Vec::new();
        for t in 0..self.tiles.count() {
            let (dim, min) = (self.dim, self.min_total_weight);
            let runs = self.tiles.read_tile(t, |sums| tile_rows(sums, dim, min))?;
            for run in runs {
                let run_means: Vec<[f32; 3]> = run.ids.iter().map(|&k| means[k as usize]).collect();
                writer.push(&run.ids, &run_means, &run.vectors, &run.total_weights)?;
                observed.extend_from_slice(&run.ids);
            }
        }
        let mixture_bytes = self.mixture.as_ref().map_or(0, MixtureFold::state_bytes) as u64;
        let sparse = match self.mixture.take() {
            Some(m) => Some(retain_gaussians(m.finish(means, model_id)?, &observed)),
            None => None,
        };
        Ok(DenseFolded {
            writer,
            sparse,
            observed: observed.len(),
            stats: self.stats,
            peak_bytes: self.stats.peak_bytes + mixture_bytes,
        })
    }
}

/// One tile's sums: Gaussians `start..start + den.len()`.
struct TileSums {
    start: usize,
    /// `[B * D]` `Σ a_kj·E_j`, f64.
    num: Vec<f64>,
    /// `[B]` `Σ a_kj`, f64.
    den: Vec<f64>,
}

impl TileSums {
    /// Zeroed sums for Gaussians `ids`, reusing the buffers.
    fn reset(&mut self, ids: std::ops::Range<usize>, dim: usize) {
        self.start = ids.start;
        self.num.clear();
        self.num.resize(ids.len() * dim, 0.0);
        self.den.clear();
        self.den.resize(ids.len(), 0.0);
    }

    /// Empty sums (sized by [`Self::reset`]).
    fn empty() -> Self {
        TileSums {
            start: 0,
            num: Vec::new(),
            den: Vec::new(),
        }
    }
}

/// Adds `batch`'s views, in order, to `sums`: rayon over blocks of [`BLOCK`] Gaussians, each
/// block adding every view's entries of its ids in entry order (one Gaussian's terms in view,
/// then entry order, as every reduction adds them). Writes nothing to disk: returns 0 (the
/// bytes a [`Tiles::with_tile`] closure reports written).
fn add_batch(sums: &mut TileSums, batch: &[StoredImage], dim: usize) -> u64 {
    let start = sums.start;
    sums.num
        .par_chunks_mut(BLOCK * dim)
        .zip(sums.den.par_chunks_mut(BLOCK))
        .enumerate()
        .for_each(|(b, (num, den))| {
            let g0 = (start + b * BLOCK) as u32;
            let mut extras = vec![(); den.len()];
            for c in batch {
                let lo = first_entry_of(c, g0);
                add_entries(c, lo, g0, dim, num, den, &mut extras, 0, &|_, _, _| {});
            }
        });
    0
}

/// A tile's observed rows, one [`Reduced`] run per block of [`BLOCK`] Gaussians (made in
/// parallel), ascending.
fn tile_rows(sums: &TileSums, dim: usize, min_total_weight: f64) -> Vec<Reduced> {
    sums.num
        .par_chunks(BLOCK * dim)
        .zip(sums.den.par_chunks(BLOCK))
        .enumerate()
        .map(|(b, (num, den))| {
            reduced_rows(sums.start + b * BLOCK, dim, num, den, min_total_weight)
        })
        .collect()
}

/// `sparse` with only the Gaussians of `ids` (ascending, each among `sparse`'s own): the
/// mixture's rows of exactly the Gaussians the dense file holds (its rule also leaves out
/// Gaussians whose mask embeddings cancel, which the mixture's fold cannot see).
fn retain_gaussians(sparse: SparseMixture, ids: &[u32]) -> SparseMixture {
    if sparse.gaussian_ids.len() == ids.len() {
        return sparse;
    }
    let mut out = SparseMixture {
        offsets: vec![0],
        gaussian_ids: Vec::with_capacity(ids.len()),
        means: Vec::with_capacity(ids.len()),
        atoms: Vec::new(),
        weights: Vec::new(),
        ..sparse
    };
    let mut wanted = ids.iter().peekable();
    for (i, &k) in sparse.gaussian_ids.iter().enumerate() {
        if wanted.next_if_eq(&&k).is_none() {
            continue;
        }
        let row = sparse.offsets[i]..sparse.offsets[i + 1];
        out.gaussian_ids.push(k);
        out.means.push(sparse.means[i]);
        out.atoms.extend_from_slice(&sparse.atoms[row.clone()]);
        out.weights.extend_from_slice(&sparse.weights[row]);
        out.offsets.push(out.atoms.len());
    }
    out
}

/// The accumulators of `n_gaussians` Gaussians tiled by ids: tiles `0..resident.len()` in
/// memory, the others in spill files (a tile never written is zero and has no file), read into
/// `work` one at a time.
struct Tiles {
    n_gaussians: usize,
    dim: usize,
    /// Gaussians per tile (the last may hold fewer).
    tile: usize,
    resident: Vec<TileSums>,
    work: TileSums,
    spill_dir: PathBuf,
    /// `[tiles]` whether a spilled tile has its file.
    on_disk: Vec<bool>,
    /// Whether the spill folder was made (at the first spill).
    dir_made: bool,
}

impl Tiles {
    /// The tiling within `budget` bytes of accumulators ((D + 1) × 8 bytes a Gaussian): one
    /// tile in memory when the whole scene fits; else tiles of a quarter of the budget (whole
    /// blocks, one block at least), all but one tile's room of the budget resident, that one
    /// the buffer the spilled tiles are read into.
    fn new(n_gaussians: usize, dim: usize, budget: usize, spill_dir: PathBuf) -> Self {
        let per_gaussian = (dim + 1) * 8;
        let (tile, resident) = if n_gaussians * per_gaussian <= budget {
            (n_gaussians.max(1), 1)
        } else {
            let tile = ((budget / per_gaussian / 4) / BLOCK).max(1) * BLOCK;
            (tile, (budget / (tile * per_gaussian)).saturating_sub(1))
        };
        let count = n_gaussians.div_ceil(tile).max(1);
        let mut tiles = Tiles {
            n_gaussians,
            dim,
            tile,
            resident: Vec::new(),
            work: TileSums::empty(),
            spill_dir,
            on_disk: vec![false; count],
            dir_made: false,
        };
        for t in 0..resident.min(count) {
            let mut sums = TileSums::empty();
            sums.reset(tiles.ids(t), dim);
            tiles.resident.push(sums);
        }
        tiles
    }

    /// Number of tiles.
    fn count(&self) -> usize {
        self.on_disk.len()
    }

    /// The Gaussian ids of tile `t`.
    fn ids(&self, t: usize) -> std::ops::Range<usize> {
        t * self.tile..((t + 1) * self.tile).min(self.n_gaussians)
    }

    /// Bytes of accumulators in memory (the resident tiles and the buffer).
    fn bytes(&self) -> usize {
        let values = |s: &TileSums| (s.num.capacity() + s.den.capacity()) * 8;
        self.resident.iter().map(values).sum::<usize>() + values(&self.work)
    }

    /// `f` on tile `t`'s sums, which are then kept: in memory, or written back to its spill
    /// file. Returns the bytes `f` reported plus the bytes written to disk.
    ///
    /// Errors: spill-file I/O ([`spill_error`]).
    fn with_tile(&mut self, t: usize, f: impl FnOnce(&mut TileSums) -> u64) -> Result<u64> {
        if let Some(sums) = self.resident.get_mut(t) {
            return Ok(f(sums));
        }
        self.load(t)?;
        let reported = f(&mut self.work);
        let path = self.tile_path(t);
        if !self.dir_made {
            create_spill_dir(&self.spill_dir)?;
            self.dir_made = true;
        }
        let written = write_tile(&path, &self.work)?;
        self.on_disk[t] = true;
        Ok(reported + written)
    }

    /// `f` on tile `t`'s final sums (read from its file when spilled).
    ///
    /// Errors: spill-file I/O.
    fn read_tile<R>(&mut self, t: usize, f: impl FnOnce(&TileSums) -> R) -> Result<R> {
        if let Some(sums) = self.resident.get(t) {
            return Ok(f(sums));
        }
        self.load(t)?;
        Ok(f(&self.work))
    }

    /// Tile `t`'s spilled sums into the buffer (zeros when it has no file yet).
    fn load(&mut self, t: usize) -> Result<()> {
        let ids = self.ids(t);
        self.work.reset(ids, self.dim);
        if self.on_disk[t] {
            read_tile(&self.tile_path(t), &mut self.work)?;
        }
        Ok(())
    }

    /// The spill file of tile `t`.
    fn tile_path(&self, t: usize) -> PathBuf {
        self.spill_dir.join(format!("tile-{t:06}.f64"))
    }
}

impl Drop for Tiles {
    fn drop(&mut self) {
        for t in 0..self.count() {
            if self.on_disk[t] {
                let _ = std::fs::remove_file(self.tile_path(t));
            }
        }
        if self.dir_made {
            let _ = std::fs::remove_dir(&self.spill_dir);
        }
    }
}

/// The spill folder, created empty: the tile files of an earlier run that stopped there are
/// removed first (they are this fold's scratch, never an output).
///
/// Errors: a folder that cannot be made or written ([`Error::Io`] naming it; a full disk as
/// [`Error::Limit`] [`Resource::DiskSpace`]).
fn create_spill_dir(dir: &Path) -> Result<()> {
    if let Ok(entries) = std::fs::read_dir(dir) {
        for e in entries.flatten() {
            let name = e.file_name();
            let name = name.to_string_lossy();
            if name.starts_with("tile-") {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
    std::fs::create_dir_all(dir).map_err(|e| spill_error(dir, e, 0))
}

/// A spill file's I/O error: a full disk (or quota) is [`Error::Limit`]
/// [`Resource::DiskSpace`] saying how much the tile needed and what to do; anything else
/// [`Error::Io`] naming `path`.
fn spill_error(path: &Path, e: std::io::Error, bytes: usize) -> Error {
    use std::io::ErrorKind;
    match e.kind() {
        ErrorKind::StorageFull | ErrorKind::QuotaExceeded => Error::limit(
            Resource::DiskSpace,
            format!(
                "{bytes} B for a tile of the dense accumulators at {}",
                path.display()
            ),
            format!(
                "the free space there: free some, or raise --accumulator-memory-mb so that \
                 fewer tiles spill ({e})"
            ),
        ),
        _ => Error::io(path, e),
    }
}

/// Writes `sums` (`num` then `den`, f64 little-endian) to `<path>.partial`, then renames it to
/// `path`: a file under `path` is always a whole tile. No fsync: the files are this run's
/// scratch, read back by this process only. Returns the bytes written.
///
/// Errors: I/O ([`spill_error`]); the partial file is removed.
fn write_tile(path: &Path, sums: &TileSums) -> Result<u64> {
    let bytes = (sums.num.len() + sums.den.len()) * 8;
    let partial = path.with_extension("f64.partial");
    let written = (|| -> std::io::Result<()> {
        let mut f = BufWriter::with_capacity(IO_CHUNK, std::fs::File::create(&partial)?);
        let mut buf = Vec::with_capacity(IO_CHUNK);
        for values in [&sums.num, &sums.den] {
            for chunk in values.chunks(IO_CHUNK / 8) {
                buf.clear();
                buf.extend(chunk.iter().flat_map(|v| v.to_le_bytes()));
                f.write_all(&buf)?;
            }
        }
        f.into_inner().map_err(|e| e.into_error())?;
        std::fs::rename(&partial, path)
    })();
    written.map_err(|e| {
        let _ = std::fs::remove_file(&partial);
        spill_error(path, e, bytes)
    })?;
    Ok(bytes as u64)
}

/// Reads a tile written by [`write_tile`] into `sums` (sized for its Gaussians already).
///
/// Errors: I/O, or a file shorter than the tile ([`Error::Io`] naming it).
fn read_tile(path: &Path, sums: &mut TileSums) -> Result<()> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut r = BufReader::with_capacity(IO_CHUNK, file);
    let mut buf = vec![0u8; IO_CHUNK];
    for values in [&mut sums.num, &mut sums.den] {
        for chunk in values.chunks_mut(IO_CHUNK / 8) {
            let bytes = &mut buf[..chunk.len() * 8];
            r.read_exact(bytes).map_err(|e| Error::io(path, e))?;
            for (v, b) in chunk.iter_mut().zip(bytes.chunks_exact(8)) {
                *v = f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]);
            }
        }
    }
    Ok(())
}

#[cfg(test)]
#[path = "dense_fold_tests.rs"]
mod tests;
