//! The reduction `E_k = Σ_i Σ_j a_kj·E_j / Σ_i Σ_j a_kj` in f64, chunked over Gaussian ids within a
//! memory budget, into memory ([`reduce`]) or streamed to the embeddings file ([`reduce_to_writer`]).

use rayon::prelude::*;
use slag_common::embeddings::EmbeddingsWriter;
use slag_common::{Error, Result};

use super::*;

/// Knobs of the reduction.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ReduceParams {
    /// A Gaussian whose `Σ a_kj` is below this is *unobserved* and gets no embedding.
    pub min_total_weight: f64,
    /// Upper bound on the f64 accumulator, bytes; the Gaussians are processed in chunks that fit.
    pub accumulator_budget_bytes: usize,
    /// Use the image-major loop (the spilled path's) even when every contribution is in memory.
    /// Same values bit for bit, only slower; kept so that benchmarks can measure the two orders
    /// against each other in one run (`slag-bench reduce`).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub image_major: bool,
    /// The block-major loop's shape; changes no value, only the speed (`slag-bench reduce
    /// --shapes` measures shapes against each other in one run).
    #[serde(skip)]
    pub shape: BlockShape,
}

/// The shape of the Gaussian-block-major loop ([`accumulate`]): each task sums `gaussians`
/// Gaussians (ids `g0..g0 + gaussians`) over every image, `slice_dims` embedding dimensions at
/// a time. The accumulator is `gaussians × slice_dims` f64 per thread; every image's mask
/// embeddings `E_j` whose entries fall in the block are read once per block, so larger blocks
/// read fewer rows in all (at 2M Gaussians, 250 views and 83 masks per view, blocks of 128 read
/// about 560 GB of `E_j` over the reduction, blocks of 1024 about 80 GB), and the entries are
/// read once per slice. `by_gaussian`: the block's entries are visited Gaussian by Gaussian
/// (all images' entries of one Gaussian, in image then entry order, its row staying in the L1
/// cache) instead of image by image; `slice_dims` is then ignored (whole rows).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BlockShape {
    /// Gaussians per task (at least 1).
    pub gaussians: usize,
    /// Embedding dimensions per visit of the block's entries (at least 1; `D` or more: whole rows).
    pub slice_dims: usize,
    /// Visit the block's entries Gaussian by Gaussian.
    pub by_gaussian: bool,
}

impl Default for BlockShape {
    /// 1024 Gaussians by 64 dimensions: a 512 KiB accumulator, which stays in a core's L2 cache.
    fn default() -> Self {
        Self {
            gaussians: 1024,
            slice_dims: 64,
            by_gaussian: false,
        }
    }
}

impl Default for ReduceParams {
    fn default() -> Self {
        Self {
            min_total_weight: 1e-6,
            accumulator_budget_bytes: 2 << 30,
            image_major: false,
            shape: BlockShape::default(),
        }
    }
}

/// Result of the reduction: the observed Gaussians with their `E_k`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Reduced {
    /// Observed Gaussian indices, ascending.
    pub ids: Vec<u32>,
    /// `[ids.len() * dim]`, rows L2-normalised `E_k`.
    pub vectors: Vec<f32>,
    /// `Σ_i Σ_j a_kj` per observed Gaussian.
    pub total_weights: Vec<f32>,
    /// Number of chunks the reduction used.
    pub chunks: usize,
}

impl Reduced {
    /// Runs in ascending id order joined into one (`chunks` summed).
    pub fn concat(parts: Vec<Reduced>) -> Reduced {
        let rows: usize = parts.iter().map(|p| p.ids.len()).sum();
        let values: usize = parts.iter().map(|p| p.vectors.len()).sum();
        let mut out = Reduced {
            ids: Vec::with_capacity(rows),
            vectors: Vec::with_capacity(values),
            total_weights: Vec::with_capacity(rows),
            chunks: 0,
        };
        for p in parts {
            out.ids.extend_from_slice(&p.ids);
            out.vectors.extend_from_slice(&p.vectors);
            out.total_weights.extend_from_slice(&p.total_weights);
            out.chunks += p.chunks;
        }
        out
    }
}

/// `E_k = Σ a_kj E_j / Σ a_kj` over every stored contribution, for Gaussians `0..n_gaussians`,
/// normalised to unit length (cosine queries). f64 accumulation; chunked over Gaussian ids.
/// Unobserved: `Σ a < min_total_weight`, or the weighted mean's norm below 1e-9 of `Σ a`
/// (mask embeddings that cancel out carry no direction).
pub fn reduce(
    store: &ContributionStore,
    n_gaussians: usize,
    dim: usize,
    params: ReduceParams,
) -> Result<Reduced> {
    let mut out = Reduced::default();
    out.chunks = reduce_each(store, n_gaussians, dim, params, |parts| {
        let part = Reduced::concat(parts);
        out.ids.extend_from_slice(&part.ids);
        out.vectors.extend_from_slice(&part.vectors);
        out.total_weights.extend_from_slice(&part.total_weights);
        Ok(())
    })?;
    Ok(out)
}

/// [`reduce`] without collecting: for each chunk of Gaussian ids (ascending), hands `sink` the
/// chunk's observed rows as consecutive [`Reduced`] runs in ascending id order (observed ids
/// `[B]`, unit vectors `[B * dim]`, `Σ a_kj` `[B]`, `chunks` 0; one run per block of Gaussians), owned, so
/// that a sink may pass them to a writer thread and overlap the write with the next chunk's
/// accumulation. Memory: the f64 accumulators (one chunk's, ≤ `params.accumulator_budget_bytes`,
/// on the image-major path; one block's per thread otherwise) plus one chunk's output (at most
/// [`OUTPUT_CHUNK_BYTES`] on the block-major path, [`output_chunk_rows`] Gaussians; about half the
/// accumulator budget on the image-major path), whatever the scene size. Returns the number of
/// chunks.
///
/// Errors: a contribution of another width ([`Error::Mismatch`]); spill-file I/O; `sink`'s errors.
pub fn reduce_each(
    store: &ContributionStore,
    n_gaussians: usize,
    dim: usize,
    params: ReduceParams,
    mut sink: impl FnMut(Vec<Reduced>) -> Result<()>,
) -> Result<usize> {
    accumulate(
        Pass::streamed(store, n_gaussians, dim, params, (dim + 1) * 8),
        |_, _, _| Ok(0),
        |_: &mut (), _, _| {},
        |sums| sums.reduced(params.min_total_weight),
        &mut sink,
    )
}

/// Bytes of output rows (unit vectors in f32, ids, total weights) of one chunk of the
/// Gaussian-block-major reduction ([`reduce_each`]).
pub const OUTPUT_CHUNK_BYTES: usize = 64 << 20;

/// Gaussians per chunk of the Gaussian-block-major reduction at width `dim`: as many whole blocks
/// of 1024 Gaussians (the default [`BlockShape`]) as [`OUTPUT_CHUNK_BYTES`] holds rows of
/// `4 · dim + 8` bytes (31,744 at D = 512), at least one block. The chunk size changes no value: each Gaussian's sums run in the
/// same order whatever the chunking.
pub fn output_chunk_rows(dim: usize) -> usize {
    let rows = OUTPUT_CHUNK_BYTES / (4 * dim + 8);
    (rows / 1024).max(1) * 1024
}

/// What [`reduce_to_writer`] leaves: the writer with every observed row pushed (call
/// [`EmbeddingsWriter::finish`]), the number of chunks, and the reduction's wall time in seconds
/// until its last chunk was handed to the writer thread.
pub struct Streamed {
    /// The writer, all rows pushed, not yet finished.
    pub writer: EmbeddingsWriter,
    /// Chunks the reduction used.
    pub chunks: usize,
    /// Seconds from the start until the last chunk was handed on (the rest of the call's time
    /// is the writer finishing its last chunk).
    pub reduce_s: f64,
}

/// [`reduce_each`] streamed into `writer` (the encoder's tail): a writer thread converts and
/// writes the runs of chunk c while chunk c + 1 is accumulated; at most one chunk waits in
/// between, so memory stays at the accumulators plus three chunks' output (being written,
/// waiting, being accumulated: 3 × [`OUTPUT_CHUNK_BYTES`] on the block-major path). `means` are all
/// Gaussian centres (`[N]`, world frame, `.ply` order), written beside each row.
///
/// Errors: those of [`reduce_each`]; the writer's (I/O, non-finite rows), which take precedence
/// over the reduction's "writer stopped" error they cause.
pub fn reduce_to_writer(
    store: &ContributionStore,
    means: &[[f32; 3]],
    dim: usize,
    params: ReduceParams,
    writer: EmbeddingsWriter,
) -> Result<Streamed> {
    stream_to_writer(
        Pass::streamed(store, means.len(), dim, params, (dim + 1) * 8),
        params.min_total_weight,
        means,
        writer,
        |_, _, _| Ok(0),
        |_: &mut (), _, _| {},
        |_, _| (),
        |_| Ok(()),
    )
}

/// The body of [`reduce_to_writer`], with a side product: one [`accumulate`] pass whose every
/// run of final sums is turned into the observed rows ([`ChunkSums::reduced`], sent to the writer
/// thread) and into a side part by `side_part(sums, rows)` (in parallel, as `accumulate`'s
/// `finish`; `rows` are the run's observed rows, so the side sees exactly the Gaussians written);
/// `side(parts)` then receives the chunk's side parts in ascending id order on the calling thread,
/// after the chunk's rows were handed to the writer. `on_image` and `on_entry` are
/// [`accumulate`]'s hooks. The mixture rides on this ([`super::reduce_to_writer_with_mixture`]):
/// one f64 reduction feeds both outputs.
///
/// Errors: those of [`accumulate`], `side`'s, and the writer's (I/O, non-finite rows, means
/// missing), which take precedence over the reduction's "writer stopped" error they cause.
#[allow(clippy::too_many_arguments)]
pub(super) fn stream_to_writer<T: Clone + Default + Send, S: Send>(
    pass: Pass<'_>,
    min_total_weight: f64,
    means: &[[f32; 3]],
    writer: EmbeddingsWriter,
    on_image: impl FnMut(bool, usize, &StoredImage) -> Result<u32>,
    on_entry: impl Fn(&mut T, &Entry, u32) + Sync,
    side_part: impl Fn(&mut ChunkSums<T>, &Reduced) -> S + Sync,
    mut side: impl FnMut(Vec<S>) -> Result<()>,
) -> Result<Streamed> {
    let t0 = std::time::Instant::now();
    std::thread::scope(|s| {
        let (tx, rx) = std::sync::mpsc::sync_channel::<Vec<Reduced>>(1);
        let handle = s.spawn(move || -> Result<EmbeddingsWriter> {
            let mut writer = writer;
            let mut run_means: Vec<[f32; 3]> = Vec::new();
            for run in rx.into_iter().flatten() {
                run_means.clear();
                for &k in &run.ids {
                    run_means.push(*means.get(k as usize).ok_or_else(|| {
                        Error::internal(format!("Gaussian {k} has no mean ({} given)", means.len()))
                    })?);
                }
                writer.push(&run.ids, &run_means, &run.vectors, &run.total_weights)?;
            }
            Ok(writer)
        });
        let reduced = accumulate(
            pass,
            on_image,
            on_entry,
            |sums| {
                let rows = sums.reduced(min_total_weight);
                let part = side_part(sums, &rows);
                (rows, part)
            },
            |parts| {
                let (runs, sides): (Vec<Reduced>, Vec<S>) = parts.into_iter().unzip();
                tx.send(runs)
                    .map_err(|_| Error::internal("the embeddings writer stopped early"))?;
                side(sides)
            },
        );
        let reduce_s = t0.elapsed().as_secs_f64();
        drop(tx);
        let writer = handle
            .join()
            .map_err(|_| Error::internal("the embeddings writer thread panicked"))??;
        Ok(Streamed {
            writer,
            chunks: reduced?,
            reduce_s,
        })
    })
}

/// One run of Gaussian ids (a chunk, or a block of one) after every contribution was added:
/// `Σ_i Σ_j a_kj E_j` and `Σ_i Σ_j a_kj` in f64 for Gaussians `start..start + den.len()`, plus a
/// per-Gaussian extra (`T`) that the entry hook of [`accumulate`] filled.
pub(super) struct ChunkSums<T> {
    /// First Gaussian id of the chunk.
    pub(super) start: usize,
    /// Embedding width D.
    pub(super) dim: usize,
    /// `[B * D]` weighted sums `Σ a_kj E_j`.
    pub(super) num: Vec<f64>,
    /// `[B]` total weights `Σ a_kj`.
    pub(super) den: Vec<f64>,
    /// `[B]` per-Gaussian extras.
    pub(super) extra: Vec<T>,
}

impl<T: Clone + Default> ChunkSums<T> {
    /// Zeroed sums for Gaussians `start..start + len`, reusing the buffers.
    fn reset(&mut self, start: usize, len: usize) {
        self.start = start;
        self.num.clear();
        self.num.resize(len * self.dim, 0.0);
        self.den.clear();
        self.den.resize(len, 0.0);
        self.extra.clear();
        self.extra.resize(len, T::default());
    }

    /// The observed rows of the run ([`ChunkSums::observed`]) as a [`Reduced`]: ids `[B]`, the
    /// unit vectors `Σ a E / ‖Σ a E‖` rounded to f32 `[B * D]`, `Σ a` rounded to f32 `[B]`,
    /// `chunks` 0.
    pub(super) fn reduced(&self, min_total_weight: f64) -> Reduced {
        let mut out = Reduced::default();
        for (r, row, norm, d) in self.observed(min_total_weight) {
            out.ids.push((self.start + r) as u32);
            out.vectors.extend(row.iter().map(|v| (v / norm) as f32));
            out.total_weights.push(d as f32);
        }
        out
    }

    /// The observed Gaussians of the chunk, ascending: `(row r, Σ a E [D], its L2 norm, Σ a)`.
    /// Unobserved (skipped): `Σ a` NaN or below `min_total_weight`, or the norm not finite or
    /// at most `1e-9 · Σ a` (mask embeddings that cancel out carry no direction).
    pub(super) fn observed(
        &self,
        min_total_weight: f64,
    ) -> impl Iterator<Item = (usize, &[f64], f64, f64)> {
        self.den.iter().enumerate().filter_map(move |(r, &d)| {
            // NaN sums count as unobserved too.
            if d.is_nan() || d < min_total_weight {
                return None;
            }
            let row = &self.num[r * self.dim..(r + 1) * self.dim];
            let norm = row.iter().map(|v| v * v).sum::<f64>().sqrt();
            if !norm.is_finite() || norm <= 1e-9 * d {
                return None;
            }
            Some((r, row, norm, d))
        })
    }
}

/// What one [`accumulate`] pass reduces: every contribution of `store` over Gaussian ids
/// `0..n_gaussians` of width `dim`, `chunk` ids at a time, in the loop order `image_major`
/// ([`ReduceParams::image_major`]).
#[derive(Clone, Copy)]
pub(super) struct Pass<'a> {
    pub(super) store: &'a ContributionStore,
    pub(super) n_gaussians: usize,
    pub(super) dim: usize,
    pub(super) chunk: usize,
    pub(super) image_major: bool,
    pub(super) shape: BlockShape,
}

impl<'a> Pass<'a> {
    /// A pass whose chunk holds as many Gaussians as `params.accumulator_budget_bytes` allows at
    /// `per_gaussian` accumulator bytes each (at least 1024, at most the scene rounded up to
    /// 1024).
    pub(super) fn new(
        store: &'a ContributionStore,
        n_gaussians: usize,
        dim: usize,
        params: ReduceParams,
        per_gaussian: usize,
    ) -> Self {
        Pass {
            store,
            n_gaussians,
            dim,
            chunk: (params.accumulator_budget_bytes / per_gaussian)
                .clamp(1024, n_gaussians.max(1024)),
            image_major: params.image_major,
            shape: BlockShape {
                gaussians: params.shape.gaussians.max(1),
                slice_dims: params.shape.slice_dims.max(1),
                by_gaussian: params.shape.by_gaussian,
            },
        }
    }

    /// [`Pass::new`] for a pass whose output is streamed chunk by chunk ([`reduce_each`],
    /// [`reduce_to_writer`]): on the block-major path (no spilled contribution, not
    /// [`ReduceParams::image_major`]) there is no chunk-wide accumulator, so the chunk is sized by
    /// its output instead, at most [`output_chunk_rows`] Gaussians: a chunk's rows are what a
    /// sink holds while the next chunks are accumulated (the streamed tail holds up to three).
    pub(super) fn streamed(
        store: &'a ContributionStore,
        n_gaussians: usize,
        dim: usize,
        params: ReduceParams,
        per_gaussian: usize,
    ) -> Self {
        let mut pass = Self::new(store, n_gaussians, dim, params, per_gaussian);
        if store.spilled() == 0 && !params.image_major {
            pass.chunk = pass.chunk.min(output_chunk_rows(dim));
        }
        pass
    }
}

/// The f64 accumulation shared by [`reduce_each`], [`reduce_mixture`] and the fused tail
/// ([`super::reduce_to_writer_with_mixture`]): for each chunk of `chunk` Gaussian ids, visits every
/// contribution ([`ContributionStore::for_each`] order) and adds `a_kj` to `Σ a` and `a_kj · E_j`
/// to `Σ a E` of its Gaussian; `finish` turns each run of final sums into a part (in parallel; it
/// may take the extras out, the sums are reset before their next use), and `done` receives the
/// chunk's parts in ascending id order.
/// Within a Gaussian the sums always run in contribution, then entry order, so every caller and
/// both loop orders below get bit-identical f64 values.
///
/// Loop order ([`ReduceParams::image_major`]):
/// - *Gaussian-block-major* (default when no contribution is spilled): rayon over blocks of
///   [`BlockShape::gaussians`] Gaussians, each block visiting every image's entries of its id
///   range once for `Σ a` and once per slice of [`BlockShape::slice_dims`] dimensions for
///   `Σ a E`, into its thread's slice accumulator (512 KiB by default, reused), which stays in
///   the core's cache while all images are added ([`add_block`]); `finish` runs per block. The
///   memory traffic is a few reads of the entries and one read of each image's mask embeddings
///   per block.
/// - *Image-major* (spilled contributions, streamed from disk one at a time): a chunk-sized
///   accumulator; for each image, rayon over blocks of 1024 Gaussians; every entry reads and
///   writes its Gaussian's f64 row in memory; `finish` runs once on the whole chunk.
///
/// Hooks: `on_image(first_chunk, image, c)` runs once per contribution and chunk, in visit order,
/// before its entries are added (after the width check; `image` counts the contributions of this
/// chunk's visit from 0) and returns a tag passed to `on_entry` (the mixture's codebook offset);
/// `on_entry(extra, entry, tag)` sees every entry with its Gaussian's extra, in the per-Gaussian
/// order above. The first error of a width mismatch or `on_image` is returned and no part of
/// that chunk is handed on (spill-file I/O errors come first). Returns the number of chunks.
pub(super) fn accumulate<T: Clone + Default + Send, B: Send>(
    pass: Pass<'_>,
    mut on_image: impl FnMut(bool, usize, &StoredImage) -> Result<u32>,
    on_entry: impl Fn(&mut T, &Entry, u32) + Sync,
    finish: impl Fn(&mut ChunkSums<T>) -> B + Sync,
    mut done: impl FnMut(Vec<B>) -> Result<()>,
) -> Result<usize> {
    let Pass {
        store,
        n_gaussians,
        dim,
        chunk,
        image_major,
        shape,
    } = pass;
    let width_check = |c: &StoredImage| {
        if c.dim != dim {
            return Err(Error::mismatch(
                slag_common::Mismatched::EmbeddingWidth,
                format!(
                    "contribution of dim {}, expected {dim}: reduce contributions of one CLIP model",
                    c.dim
                ),
            ));
        }
        Ok(())
    };
    let empty = || ChunkSums {
        start: 0,
        dim,
        num: Vec::new(),
        den: Vec::new(),
        extra: Vec::new(),
    };
    let mut chunks = 0;
    for start in (0..n_gaussians).step_by(chunk) {
        chunks += 1;
        let end = (start + chunk).min(n_gaussians);
        if store.spilled() == 0 && !image_major {
            let images = &store.in_memory;
            let mut tags = Vec::with_capacity(images.len());
            for (image, c) in images.iter().enumerate() {
                width_check(c)?;
                tags.push(on_image(start == 0, image, c)?);
            }
            let parts: Vec<B> = (start..end)
                .step_by(shape.gaussians)
                .collect::<Vec<_>>()
                .into_par_iter()
                .map_init(
                    || (empty(), BlockScratch::default()),
                    |(sums, scratch), g0| {
                        sums.reset(g0, shape.gaussians.min(end - g0));
                        add_block(images, &tags, shape, sums, scratch, &on_entry);
                        finish(sums)
                    },
                )
                .collect();
            done(parts)?;
        } else {
            const BLOCK: usize = 1024;
            let mut sums = empty();
            sums.reset(start, end - start);
            let mut failure: Option<Error> = None;
            let mut image = 0usize;
            store.for_each(|c| {
                if failure.is_some() {
                    return;
                }
                let tag = match width_check(c).and_then(|()| on_image(start == 0, image, c)) {
                    Ok(tag) => tag,
                    Err(e) => {
                        failure = Some(e);
                        return;
                    }
                };
                image += 1;
                sums.num
                    .par_chunks_mut(BLOCK * dim)
                    .zip(sums.den.par_chunks_mut(BLOCK))
                    .zip(sums.extra.par_chunks_mut(BLOCK))
                    .enumerate()
                    .for_each(|(b, ((num, den), extra))| {
                        let run = Run::of(c, (start + b * BLOCK) as u32, den.len());
                        run.add_totals(den, extra, tag, &on_entry);
                        run.add_slice(0, dim, num);
                    });
            })?;
            if let Some(e) = failure {
                return Err(e);
            }
            done(vec![finish(&mut sums)])?;
        }
    }
    Ok(chunks)
}

/// Per-thread buffer of the block-major path, reused from block to block.
#[derive(Default)]
struct BlockScratch {
    /// `[B * w]` the current slice's sums `Σ a_kj E_j[s0..s0 + w]`, row-major by Gaussian.
    slice: Vec<f64>,
}

/// Adds every image's entries of the block `sums` (Gaussians `sums.start..+len`) to its sums:
/// first `Σ a` and the extras (one visit, entry hook in per-Gaussian order), then `Σ a E` slice by
/// slice of `shape.slice_dims` dimensions, each slice summed in `scratch.slice` and copied into its
/// columns of `sums.num`. Every value sees the same additions in the same order as an unsliced
/// loop (one rounded product, one rounded sum per element), so the bits do not depend on the
/// slicing.
fn add_block<T>(
    images: &[StoredImage],
    tags: &[u32],
    shape: BlockShape,
    sums: &mut ChunkSums<T>,
    scratch: &mut BlockScratch,
    on_entry: &(impl Fn(&mut T, &Entry, u32) + Sync),
) {
    let (dim, len, g0) = (sums.dim, sums.den.len(), sums.start as u32);
    let runs: Vec<Run<'_>> = images.iter().map(|c| Run::of(c, g0, len)).collect();
    for (run, &tag) in runs.iter().zip(tags) {
        run.add_totals(&mut sums.den, &mut sums.extra, tag, on_entry);
    }
    if shape.by_gaussian {
        sum_by_gaussian(&runs, dim, &mut sums.num);
        return;
    }
    for s0 in (0..dim).step_by(shape.slice_dims) {
        let w = shape.slice_dims.min(dim - s0);
        scratch.slice.clear();
        scratch.slice.resize(len * w, 0.0);
        for run in &runs {
            run.add_slice(s0, w, &mut scratch.slice);
        }
        for (row, part) in sums
            .num
            .chunks_exact_mut(dim)
            .zip(scratch.slice.chunks_exact(w))
        {
            row[s0..s0 + w].copy_from_slice(part);
        }
    }
}

/// The entries of one image that fall in one block of Gaussians (its entries are sorted by
/// Gaussian, so they are one contiguous range).
struct Run<'a> {
    image: &'a StoredImage,
    lo: usize,
    hi: usize,
    g0: u32,
}

impl<'a> Run<'a> {
    /// The entries of `c` for Gaussians `g0..g0 + len`.
    fn of(c: &'a StoredImage, g0: u32, len: usize) -> Self {
        let g1 = g0 + len as u32;
        let lo = c.gaussians.partition_point(|&g| g < g0);
        let hi = lo + c.gaussians[lo..].partition_point(|&g| g < g1);
        Run {
            image: c,
            lo,
            hi,
            g0,
        }
    }

    /// `db[r] += a` and `on_entry(xb[r], entry, tag)` for each entry, in entry order (`r` its
    /// Gaussian's row in the block).
    #[inline]
    fn add_totals<T>(
        &self,
        db: &mut [f64],
        xb: &mut [T],
        tag: u32,
        on_entry: &(impl Fn(&mut T, &Entry, u32) + Sync),
    ) {
        let gaussians = &self.image.gaussians[self.lo..self.hi];
        let weights = &self.image.weights[self.lo..self.hi];
        let mut visit = |gaussian: u32, mask: u32, weight: f32| {
            let r = (gaussian - self.g0) as usize;
            db[r] += weight as f64;
            let e = Entry {
                gaussian,
                mask,
                weight,
            };
            on_entry(&mut xb[r], &e, tag);
        };
        match &self.image.masks {
            MaskColumn::U8(m) => each_entry(gaussians, &m[self.lo..self.hi], weights, &mut visit),
            MaskColumn::U16(m) => each_entry(gaussians, &m[self.lo..self.hi], weights, &mut visit),
            MaskColumn::U32(m) => each_entry(gaussians, &m[self.lo..self.hi], weights, &mut visit),
        }
    }

    /// `acc[r·w..(r+1)·w] += a · E_j[s0..s0 + w]` for each entry, in entry order: the slice
    /// `s0..s0 + w` of the block's `Σ a E` (`acc` is `[B * w]`). A portable build targets
    /// x86-64's baseline (SSE2: two f64 per instruction); where the CPU has AVX-512 or AVX2
    /// (checked at run time, cached by std) the whole entry loop is compiled for eight or four,
    /// chosen once per call. Every path gives the same bits ([`add_scaled_portable`]).
    #[inline]
    fn add_slice(&self, s0: usize, w: usize, acc: &mut [f64]) {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                // SAFETY: the CPU has AVX-512F (checked just above).
                #[allow(unsafe_code)]
                unsafe {
                    self.add_slice_avx512(s0, w, acc)
                };
                return;
            }
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU has AVX2 (checked just above).
                #[allow(unsafe_code)]
                unsafe {
                    self.add_slice_avx2(s0, w, acc)
                };
                return;
            }
        }
        self.add_slice_portable(s0, w, acc);
    }

    /// [`Run::add_slice`] for the build's baseline target.
    #[inline(always)]
    fn add_slice_portable(&self, s0: usize, w: usize, acc: &mut [f64]) {
        let dim = self.image.dim;
        let e = &self.image.mask_embeddings;
        let gaussians = &self.image.gaussians[self.lo..self.hi];
        let weights = &self.image.weights[self.lo..self.hi];
        let mut visit = |gaussian: u32, mask: u32, weight: f32| {
            let r = (gaussian - self.g0) as usize;
            let row = mask as usize * dim + s0;
            add_scaled_portable(&mut acc[r * w..(r + 1) * w], weight as f64, &e[row..row + w]);
        };
        match &self.image.masks {
            MaskColumn::U8(m) => each_entry(gaussians, &m[self.lo..self.hi], weights, &mut visit),
            MaskColumn::U16(m) => each_entry(gaussians, &m[self.lo..self.hi], weights, &mut visit),
            MaskColumn::U32(m) => each_entry(gaussians, &m[self.lo..self.hi], weights, &mut visit),
        }
    }

    /// [`Run::add_slice`] compiled for AVX-512F.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    fn add_slice_avx512(&self, s0: usize, w: usize, acc: &mut [f64]) {
        self.add_slice_portable(s0, w, acc);
    }

    /// [`Run::add_slice`] compiled for AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn add_slice_avx2(&self, s0: usize, w: usize, acc: &mut [f64]) {
        self.add_slice_portable(s0, w, acc);
    }
}

/// `num[r·D..(r+1)·D] += a · E_j` for every entry of `runs` (one block's runs, `num` its
/// `[B * D]` sums), Gaussian by Gaussian: for each row, every run's entries of that Gaussian in
/// run order, then entry order (each run's cursor only moves forward, its entries being sorted by
/// Gaussian), so the row stays in the L1 cache while all its entries are added. The same order
/// per value as the image-by-image loop, hence the same bits. The instruction set is chosen once
/// per call, as in [`Run::add_slice`].
fn sum_by_gaussian(runs: &[Run<'_>], dim: usize, num: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU has AVX-512F (checked just above).
            #[allow(unsafe_code)]
            unsafe {
                sum_by_gaussian_avx512(runs, dim, num)
            };
            return;
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2 (checked just above).
            #[allow(unsafe_code)]
            unsafe {
                sum_by_gaussian_avx2(runs, dim, num)
            };
            return;
        }
    }
    sum_by_gaussian_portable(runs, dim, num);
}

/// [`sum_by_gaussian`] for the build's baseline target.
#[inline(always)]
fn sum_by_gaussian_portable(runs: &[Run<'_>], dim: usize, num: &mut [f64]) {
    let Some(g0) = runs.first().map(|r| r.g0) else {
        return;
    };
    let mut cursors: Vec<usize> = runs.iter().map(|r| r.lo).collect();
    for (r, acc) in num.chunks_exact_mut(dim).enumerate() {
        let g = g0 + r as u32;
        for (run, c) in runs.iter().zip(cursors.iter_mut()) {
            let image = run.image;
            while *c < run.hi && image.gaussians[*c] == g {
                let m = match &image.masks {
                    MaskColumn::U8(m) => m[*c] as usize,
                    MaskColumn::U16(m) => m[*c] as usize,
                    MaskColumn::U32(m) => m[*c] as usize,
                };
                let a = f64::from(image.weights[*c]);
                add_scaled_portable(acc, a, &image.mask_embeddings[m * dim..(m + 1) * dim]);
                *c += 1;
            }
        }
    }
}

/// [`sum_by_gaussian`] compiled for AVX-512F.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
fn sum_by_gaussian_avx512(runs: &[Run<'_>], dim: usize, num: &mut [f64]) {
    sum_by_gaussian_portable(runs, dim, num);
}

/// [`sum_by_gaussian`] compiled for AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn sum_by_gaussian_avx2(runs: &[Run<'_>], dim: usize, num: &mut [f64]) {
    sum_by_gaussian_portable(runs, dim, num);
}

/// `visit(gaussian, mask, weight)` for each entry of the three columns, in order.
#[inline(always)]
fn each_entry<M: Copy + Into<u32>>(
    gaussians: &[u32],
    masks: &[M],
    weights: &[f32],
    visit: &mut impl FnMut(u32, u32, f32),
) {
    for ((&g, &m), &a) in gaussians.iter().zip(masks).zip(weights) {
        visit(g, m.into(), a);
    }
}

/// `acc[i] += a · e[i]` in f64 for every `i` (`acc` and `e` of one length): the reduction's inner
/// loop, one multiply-add per dimension of each `a_kj` entry. Each element is one rounded
/// product then one rounded sum (Rust never fuses them into an FMA), so the loop gives the same
/// bits whatever instruction set it is compiled for ([`Run::add_slice`]).
#[inline(always)]
fn add_scaled_portable(acc: &mut [f64], a: f64, e: &[f32]) {
    for (x, &v) in acc.iter_mut().zip(e) {
        *x += a * f64::from(v);
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod simd_tests {
    use super::*;

    /// Every path the CPU offers gives the portable loop's bits, for widths around the vector
    /// widths, whole rows and inner slices, and values across f32's range (subnormal, huge,
    /// signed zeros), with entries of two masks on three Gaussians, one of them twice.
    #[test]
    fn every_instruction_set_adds_the_same_bits() {
        let mut rng = slag_common::rng::SplitMix64::new(7);
        let specials = [0.0f32, -0.0, 1e-40, -3.4e38, 3.4e38, 1.0, -1.0, 6.1e-5];
        for dim in [1usize, 3, 4, 7, 8, 9, 15, 16, 17, 63, 64, 65, 512, 513] {
            for scale in [1e-38f32, 1e-3, 0.37, 1.0, 1e30, -2.5] {
                let mask_embeddings: Vec<f32> = (0..2 * dim)
                    .map(|i| {
                        if i % 5 == 0 {
                            specials[i / 5 % specials.len()]
                        } else {
                            (rng.next_f64() as f32 - 0.5) * 8.0
                        }
                    })
                    .collect();
                let image = StoredImage {
                    dim,
                    mask_embeddings,
                    gaussians: vec![4, 5, 5, 6],
                    masks: MaskColumn::U8(vec![0, 1, 0, 1]),
                    weights: vec![scale, 0.5, -scale, 3.0],
                };
                let run = Run::of(&image, 4, 3);
                for (s0, w) in [(0, dim), (dim / 3, dim - dim / 3 - dim / 4)] {
                    let start: Vec<f64> = (0..3 * w).map(|_| rng.next_f64() * 1e3 - 5e2).collect();
                    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    let mut want = start.clone();
                    for (k, r) in [(0usize, 0usize), (1, 1), (2, 1), (3, 2)] {
                        let m = [0, 1, 0, 1][k] * dim + s0;
                        let a = f64::from(image.weights[k]);
                        add_scaled_portable(&mut want[r * w..(r + 1) * w], a, &image.mask_embeddings[m..m + w]);
                    }
                    let mut got = start.clone();
                    run.add_slice(s0, w, &mut got);
                    assert_eq!(bits(&got), bits(&want), "D {dim}, slice {s0}+{w}, a {scale}");
                    let mut got = start.clone();
                    run.add_slice_portable(s0, w, &mut got);
                    assert_eq!(bits(&got), bits(&want), "portable, D {dim}, a {scale}");
                    #[cfg(target_arch = "x86_64")]
                    {
                        #[allow(unsafe_code)]
                        if std::arch::is_x86_feature_detected!("avx2") {
                            let mut v = start.clone();
                            // SAFETY: checked just above.
                            unsafe { run.add_slice_avx2(s0, w, &mut v) };
                            assert_eq!(bits(&v), bits(&want), "avx2, D {dim}, a {scale}");
                        }
                        #[allow(unsafe_code)]
                        if std::arch::is_x86_feature_detected!("avx512f") {
                            let mut v = start.clone();
                            // SAFETY: checked just above.
                            unsafe { run.add_slice_avx512(s0, w, &mut v) };
                            assert_eq!(bits(&v), bits(&want), "avx512, D {dim}, a {scale}");
                        }
                    }
                }
            }
        }
    }
}
