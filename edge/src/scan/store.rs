//! [`VectorStore`]: every stored row in one matrix, in the shard's stored type.

use half::f16;
use half::slice::HalfFloatSliceExt;
use rayon::prelude::*;
use slag_common::Error;
use slag_common::rng::splitmix64 as splitmix;
use slag_common::shards::format::quantize_i8;
use slag_common::shards::{Dtype, MixtureShard, StoredShard, StoredVectors};

use super::mixture::MixtureRows;
use super::synthetic::{fast_normal, random_centres, uniform};

/// All embedding rows held by the robot, concatenated shard after shard, kept in the stored type
/// (no f32 copy): `f32` = 4 B per value, `f16` = 2 B per value, `int8` = 1 B per value + one
/// `f32` scale per row (value = `q · scale`, [`quantize_i8`]).
///
/// Row `i` describes the Gaussian `ids()[i]` (index in the source `.ply`) centred at `means()[i]`
/// (world frame, scene units). Rows are expected to be (approximately) unit L2 norm, as written
/// by the encoder, so a dot product with a unit query is the cosine similarity.
///
/// A *mixture* store ([`VectorStore::new_mixture`], from mixture shards) holds codebook mixtures
/// instead ([`MixtureRows`]): [`VectorStore::vectors`] is then empty, [`VectorStore::dtype`]
/// says f16 (the stored weights and codebook), and the scan scores each row as the exact cosine
/// of its reconstruction.
///
/// Rows from shards that carry geometric segments (format version 3, or 4 for mixture shards)
/// keep each Gaussian's scene-wide segment id ([`VectorStore::segments`]).
#[derive(Debug, Clone)]
pub struct VectorStore {
    dim: usize,
    ids: Vec<u32>,
    means: Vec<[f32; 3]>,
    vectors: StoredVectors,
    mixture: Option<MixtureRows>,
    /// `[N]` segment ids once any pushed shard had them ([`NO_SEGMENT`] for rows without).
    segments: Option<Vec<u32>>,
}

/// Segment id of a row whose shard carried none, in a store that holds other rows' segments.
pub use slag_common::segments::NO_SEGMENT;

fn empty_vectors(dtype: Dtype) -> StoredVectors {
    match dtype {
        Dtype::F32 => StoredVectors::F32(Vec::new()),
        Dtype::F16 => StoredVectors::F16(Vec::new()),
        Dtype::I8 => StoredVectors::I8 {
            q: Vec::new(),
            scales: Vec::new(),
        },
    }
}

fn dtype_name(d: Dtype) -> &'static str {
    match d {
        Dtype::F32 => "f32",
        Dtype::F16 => "f16",
        Dtype::I8 => "int8",
    }
}

/// Asks the kernel to back the not yet written part of `v`'s buffer (`[len, capacity)`, the
/// 2 MiB-aligned pages inside it) with transparent huge pages (`madvise(MADV_HUGEPAGE)`), so that
/// a scan over hundreds of MB walks 2 MiB pages instead of 4 KiB ones (fewer TLB misses; measured
/// 3–4 % on a 1M × 512 f32 scan and plain read, 2-core x86 VM, THP in `madvise` mode). Pages are
/// faulted in as huge pages when first written, so call it after reserving and before filling.
/// A hint only: ignored where THP is off, not Linux, or the range is under 2 MiB; contents and
/// memory accounting (RSS) are unchanged.
fn advise_huge_pages<T>(v: &Vec<T>) {
    #[cfg(target_os = "linux")]
    {
        const HUGE: usize = 2 << 20;
        let size = std::mem::size_of::<T>();
        let start = v.as_ptr() as usize + v.len() * size;
        let end = v.as_ptr() as usize + v.capacity() * size;
        let (a, b) = (start.next_multiple_of(HUGE), end / HUGE * HUGE);
        if b > a {
            // SAFETY: [a, b) lies inside `v`'s own allocation (its unused capacity), which stays
            // allocated for the duration of the call; MADV_HUGEPAGE only sets a paging hint on
            // the mapping and never changes or frees memory, so no Rust reference is affected.
            #[allow(unsafe_code)]
            let rc = unsafe { libc::madvise(a as *mut libc::c_void, b - a, libc::MADV_HUGEPAGE) };
            if rc != 0 {
                tracing::debug!(
                    error = %std::io::Error::last_os_error(),
                    "madvise(MADV_HUGEPAGE) refused; the scan store stays on 4 KiB pages"
                );
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = v;
}

/// Reserves room for exactly `additional` more values in `v` and advises the new room to use
/// huge pages ([`advise_huge_pages`]).
fn reserve_on_huge_pages<T>(
    v: &mut Vec<T>,
    additional: usize,
) -> Result<(), std::collections::TryReserveError> {
    v.try_reserve_exact(additional)?;
    advise_huge_pages(v);
    Ok(())
}

impl VectorStore {
    /// Reserves room for `rows` more rows (exactly: no doubling, so that the served store stays
    /// near its floor of memory), with the vector buffer advised to use transparent huge pages
    /// ([`advise_huge_pages`]). Call it before [`VectorStore::push_shard`] with the row count of
    /// the shards about to be loaded: rows then land in place, without reallocation.
    ///
    /// Errors: [`Error::Limit`] [`slag_common::Resource::Memory`] when the allocator refuses the
    /// room (the rows do not fit this machine's memory: fetch a smaller radius, or shards of a
    /// smaller dtype); the store is then unchanged apart from spare capacity.
    pub fn reserve(&mut self, rows: usize) -> Result<(), Error> {
        let values = rows.saturating_mul(self.dim);
        let refused = |what: &str, e: std::collections::TryReserveError| {
            Error::limit(
                slag_common::Resource::Memory,
                format!("{rows} more rows of {what}"),
                format!(
                    "what the allocator gives ({e}); fetch a smaller radius or shards of a \
                     smaller dtype (int8, f16)"
                ),
            )
        };
        self.ids
            .try_reserve_exact(rows)
            .map_err(|e| refused("ids", e))?;
        self.means
            .try_reserve_exact(rows)
            .map_err(|e| refused("means", e))?;
        if let Some(s) = &mut self.segments {
            s.try_reserve_exact(rows)
                .map_err(|e| refused("segments", e))?;
        }
        let vectors = |e| refused("vectors", e);
        if let Some(m) = &mut self.mixture {
            return m.try_reserve(rows).map_err(vectors);
        }
        match &mut self.vectors {
            StoredVectors::F32(v) => reserve_on_huge_pages(v, values).map_err(vectors)?,
            StoredVectors::F16(v) => reserve_on_huge_pages(v, values).map_err(vectors)?,
            StoredVectors::I8 { q, scales } => {
                reserve_on_huge_pages(q, values).map_err(vectors)?;
                scales
                    .try_reserve_exact(rows)
                    .map_err(|e| refused("scales", e))?;
            }
        }
        Ok(())
    }

    /// An empty store of `dim`-wide rows stored as `dtype`.
    ///
    /// Errors: [`Error::Param`] `dim` when `dim == 0`.
    pub fn new(dim: usize, dtype: Dtype) -> Result<VectorStore, Error> {
        if dim == 0 {
            return Err(Error::param(
                "dim",
                0,
                "the embedding width of the shards (e.g. 512)",
            ));
        }
        Ok(VectorStore {
            dim,
            ids: Vec::new(),
            means: Vec::new(),
            vectors: empty_vectors(dtype),
            mixture: None,
            segments: None,
        })
    }

    /// An empty mixture store over a scene's codebook (`[A * dim]` row-major, the values of the
    /// codebook file whose CRC-32 is `codebook_crc`) with `slots` slots per row; fill it with
    /// [`VectorStore::push_mixture_shard`].
    ///
    /// Errors: [`Error::Param`] for `dim == 0`, `slots == 0`, or an empty codebook or one that
    /// is not rows of `dim` values.
    pub fn new_mixture(
        dim: usize,
        slots: usize,
        codebook: Vec<f32>,
        codebook_crc: u32,
    ) -> Result<VectorStore, Error> {
        let mut store = VectorStore::new(dim, Dtype::F16)?;
        store.mixture = Some(MixtureRows::new(dim, slots, codebook, codebook_crc)?);
        Ok(store)
    }

    /// The mixture rows of a mixture store; `None` for a dense one.
    pub fn mixture(&self) -> Option<&MixtureRows> {
        self.mixture.as_ref()
    }

    /// True for a mixture store ([`VectorStore::new_mixture`]).
    pub fn is_mixture(&self) -> bool {
        self.mixture.is_some()
    }

    /// Appends every row of a decoded mixture shard: weights scaled by each row's reconstruction
    /// norm, empty slots made harmless (module doc of [`super::mixture`]).
    ///
    /// Errors: [`Error::Mismatch`] for a dense store, or a shard of another width, slot count
    /// or codebook; [`Error::Format`] for an atom beyond the codebook; [`Error::Invalid`] for
    /// arrays that disagree with its count. The store is unchanged on error.
    pub fn push_mixture_shard(&mut self, shard: MixtureShard) -> Result<(), Error> {
        let Some(m) = &mut self.mixture else {
            return Err(Error::mismatch(
                slag_common::Mismatched::Dtype,
                format!(
                    "mixture shard (tile {}) but the store holds dense {} rows; fetch shards of \
                     one partition into one store",
                    shard.header.tile_id,
                    dtype_name(self.vectors.dtype())
                ),
            ));
        };
        m.check(&shard)?;
        if shard.means.len() != shard.ids.len()
            || shard
                .segments
                .as_ref()
                .is_some_and(|s| s.len() != shard.ids.len())
        {
            return Err(Error::Invalid(format!(
                "mixture shard (tile {}) has {} ids but {} means or another number of segment \
                 ids; re-download it",
                shard.header.tile_id,
                shard.ids.len(),
                shard.means.len()
            )));
        }
        m.push_checked(&shard);
        self.push_segments(shard.segments.as_deref(), shard.ids.len());
        self.ids.extend_from_slice(&shard.ids);
        self.means.extend_from_slice(&shard.means);
        Ok(())
    }

    /// Appends every row of a decoded shard (vectors moved, not converted).
    ///
    /// Errors: [`Error::Mismatch`] when the shard's dim or dtype differ from the store's (both are
    /// named; fetch shards of one encoding into one store), [`Error::Invalid`] when its arrays
    /// disagree with its Gaussian count. The store is unchanged on error.
    pub fn push_shard(&mut self, shard: StoredShard) -> Result<(), Error> {
        let h = &shard.header;
        let n = shard.ids.len();
        if self.mixture.is_some() {
            return Err(Error::mismatch(
                slag_common::Mismatched::Dtype,
                format!(
                    "dense shard (tile {}) but the store holds codebook mixtures; fetch shards \
                     of one partition into one store",
                    h.tile_id
                ),
            ));
        }
        if h.dim as usize != self.dim {
            return Err(Error::mismatch(
                slag_common::Mismatched::EmbeddingWidth,
                format!(
                    "shard (tile {}) has embedding dim {} but the store holds dim {}; use one \
                     embedding model for all shards of a store",
                    h.tile_id, h.dim, self.dim
                ),
            ));
        }
        let sd = shard.vectors.dtype();
        if sd != self.dtype() {
            return Err(Error::mismatch(
                slag_common::Mismatched::Dtype,
                format!(
                    "shard (tile {}) stores {} vectors but the store holds {}; fetch shards of \
                     one dtype or open a store of dtype {}",
                    h.tile_id,
                    dtype_name(sd),
                    dtype_name(self.dtype()),
                    dtype_name(sd)
                ),
            ));
        }
        let values_ok = shard.vectors.values() == n * self.dim;
        let scales_ok = match &shard.vectors {
            StoredVectors::I8 { scales, .. } => scales.len() == n,
            _ => true,
        };
        let segments_ok = shard.segments.as_ref().is_none_or(|s| s.len() == n);
        if shard.means.len() != n || !values_ok || !scales_ok || !segments_ok {
            return Err(Error::Invalid(format!(
                "shard (tile {}) is inconsistent: {} ids, {} means, {} vector values for dim {}; \
                 re-download it",
                h.tile_id,
                n,
                shard.means.len(),
                shard.vectors.values(),
                self.dim
            )));
        }
        // Checked: the dtype match below cannot fail, so the segments stay in step.
        self.push_segments(shard.segments.as_deref(), n);
        self.ids.extend_from_slice(&shard.ids);
        self.means.extend_from_slice(&shard.means);
        match (&mut self.vectors, shard.vectors) {
            (StoredVectors::F32(a), StoredVectors::F32(b)) => a.extend_from_slice(&b),
            (StoredVectors::F16(a), StoredVectors::F16(b)) => a.extend_from_slice(&b),
            (StoredVectors::I8 { q, scales }, StoredVectors::I8 { q: bq, scales: bs }) => {
                q.extend_from_slice(&bq);
                scales.extend_from_slice(&bs);
            }
            // Unreachable: dtypes were compared above; kept as an error, not a panic.
            _ => {
                return Err(Error::internal(
                    "push_shard: dtype mismatch after the check",
                ));
            }
        }
        Ok(())
    }

    /// Appends rows given as `f32` (`vectors` is `[n * dim]` row-major), converting them to the
    /// store's dtype exactly as the shard encoder does (f16 round-to-nearest, [`quantize_i8`]).
    ///
    /// Errors: [`Error::Internal`] when `ids`, `means` and `vectors` disagree in length,
    /// [`Error::Invalid`] when a value is not finite, [`Error::Param`] `dtype` when (f16 store) a
    /// value rounds beyond the f16 range.
    pub fn push_f32_rows(
        &mut self,
        ids: &[u32],
        means: &[[f32; 3]],
        vectors: &[f32],
    ) -> Result<(), Error> {
        let n = ids.len();
        if means.len() != n || vectors.len() != n * self.dim {
            return Err(Error::internal(format!(
                "{} ids, {} means and {} vector values do not describe rows of dim {}",
                n,
                means.len(),
                vectors.len(),
                self.dim
            )));
        }
        if self.mixture.is_some() {
            return Err(Error::mismatch(
                slag_common::Mismatched::Dtype,
                "dense rows for a store of codebook mixtures; use a dense store",
            ));
        }
        if vectors.iter().any(|x| !x.is_finite()) {
            return Err(Error::Invalid(
                "embedding rows contain NaN or infinite values; re-encode the scene".into(),
            ));
        }
        if matches!(self.vectors, StoredVectors::F16(_))
            && let Some(x) = vectors.iter().find(|&&x| !f16::from_f32(x).is_finite())
        {
            return Err(Error::param(
                "dtype",
                "f16",
                format!(
                    "an f32 store for the embedding value {x}, beyond the f16 range (±65504), or \
                     L2-normalised rows"
                ),
            ));
        }
        match &mut self.vectors {
            StoredVectors::F32(a) => a.extend_from_slice(vectors),
            StoredVectors::F16(a) => a.extend(vectors.iter().map(|&x| f16::from_f32(x))),
            StoredVectors::I8 { q, scales } => {
                let mut bytes = Vec::with_capacity(self.dim);
                for row in vectors.chunks_exact(self.dim) {
                    bytes.clear();
                    scales.push(quantize_i8(row, &mut bytes));
                    q.extend(bytes.iter().map(|&b| b as i8));
                }
            }
        }
        self.push_segments(None, n);
        self.ids.extend_from_slice(ids);
        self.means.extend_from_slice(means);
        Ok(())
    }

    /// Appends the segment ids of `n` new rows (`segments`, or [`NO_SEGMENT`] each): starts the
    /// column (earlier rows [`NO_SEGMENT`]) at the first rows that have segments. Call before
    /// `ids` grows.
    fn push_segments(&mut self, segments: Option<&[u32]>, n: usize) {
        match (&mut self.segments, segments) {
            (None, None) => {}
            (Some(col), None) => col.extend(std::iter::repeat_n(NO_SEGMENT, n)),
            (Some(col), Some(s)) => col.extend_from_slice(s),
            (None, Some(s)) => {
                let mut col = Vec::with_capacity(self.ids.capacity().max(self.ids.len() + n));
                col.resize(self.ids.len(), NO_SEGMENT);
                col.extend_from_slice(s);
                self.segments = Some(col);
            }
        }
    }

    /// Scene-wide geometric segment id of every row, `[N]` (in [`VectorStore::ids`] order), when
    /// any loaded shard carried segments (format version 3); rows from shards without them are
    /// [`NO_SEGMENT`]. `None` when no row has a segment. Rows of one segment are one surface
    /// patch of the scene (Felzenszwalb–Huttenlocher over the Gaussians' geometry, made by the
    /// encoder); ids are comparable across shards of one partition.
    pub fn segments(&self) -> Option<&[u32]> {
        self.segments.as_deref()
    }

    /// Embedding width D.
    pub fn dim(&self) -> usize {
        self.dim
    }
    /// Number of rows N.
    pub fn len(&self) -> usize {
        self.ids.len()
    }
    /// `true` when no row is stored.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }
    /// Storage type of the rows (f16 for a mixture store: its weights and codebook).
    pub fn dtype(&self) -> Dtype {
        self.vectors.dtype()
    }
    /// Source-`.ply` index of every row, `[N]`.
    pub fn ids(&self) -> &[u32] {
        &self.ids
    }
    /// Centre of every row's Gaussian, `[N]`, world frame, scene units.
    pub fn means(&self) -> &[[f32; 3]] {
        &self.means
    }
    /// The rows as stored (`[N * D]` row-major; int8 with `[N]` scales).
    pub fn vectors(&self) -> &StoredVectors {
        &self.vectors
    }

    /// Bytes of the embedding rows (values plus int8 scales; a mixture store's codebook plus
    /// its slots), not counting ids and means.
    pub fn vector_bytes(&self) -> usize {
        match &self.mixture {
            Some(m) => m.memory_bytes(),
            None => self.len() * self.dtype().bytes_per_vector(self.dim),
        }
    }

    /// Bytes held by the store's live data: rows + ids (4 B) + means (12 B) per Gaussian, plus
    /// segment ids (4 B) when the store has them.
    /// Vector capacity slack beyond the length is not counted (it is at most what the last
    /// shard appended).
    pub fn memory_bytes(&self) -> usize {
        let segments = if self.segments.is_some() { 4 } else { 0 };
        self.vector_bytes() + self.len() * (4 + 12 + segments)
    }

    /// Bytes per Gaussian: `dtype.bytes_per_vector(dim) + 16` (id + mean); for a mixture store
    /// `8 · S + 16` (u32 atom + f32 weight per slot; the shared codebook is not counted).
    pub fn bytes_per_gaussian(&self) -> usize {
        match &self.mixture {
            Some(m) => 8 * m.slots() + 16,
            None => self.dtype().bytes_per_vector(self.dim) + 16,
        }
    }

    /// Row `i` dequantised to `f32` (`[D]`), or `None` when `i >= len()`. For tests and index
    /// building, not for the scan loop.
    pub fn row_f32(&self, i: usize) -> Option<Vec<f32>> {
        if i >= self.len() {
            return None;
        }
        if let Some(m) = &self.mixture {
            return m.row_f32(i);
        }
        let d = self.dim;
        let r = i * d..(i + 1) * d;
        Some(match &self.vectors {
            StoredVectors::F32(v) => v[r].to_vec(),
            StoredVectors::F16(v) => v[r].iter().map(|h| h.to_f32()).collect(),
            StoredVectors::I8 { q, scales } => {
                let s = scales[i];
                q[r].iter().map(|&b| b as f32 * s).collect()
            }
        })
    }

    /// A deterministic synthetic store for benchmarks and tests: `n` unit rows of width `dim` in
    /// `clusters` directional clusters (row = normalise(centre + 0.75 · g / √D), g standard
    /// normal, so cos(row, centre) ≈ 0.8), means uniform in a 100 m cube, ids `0..n`.
    ///
    /// Rows are generated in parallel (rayon) straight into the stored type: no f32 copy of the
    /// whole matrix exists for f16/int8. The same `(n, dim, clusters, seed)` gives the same rows
    /// for every dtype (before conversion) and every thread count.
    ///
    /// Errors: [`Error::Param`] for `dim == 0` or `clusters == 0`, [`Error::Limit`] for `n · dim` overflowing.
    pub fn synthetic(
        n: usize,
        dim: usize,
        dtype: Dtype,
        clusters: usize,
        seed: u64,
    ) -> Result<VectorStore, Error> {
        let mut store = VectorStore::new(dim, dtype)?;
        if clusters == 0 {
            return Err(Error::param("clusters", 0, "at least one cluster"));
        }
        let total = n.checked_mul(dim).ok_or_else(|| {
            Error::limit(
                slag_common::Resource::Memory,
                format!("{n} rows of dim {dim}"),
                "the address space",
            )
        })?;
        let rows = SyntheticRows {
            centres: random_centres(dim, clusters, seed),
            clusters,
            dim,
            seed,
        };
        let gen_row = |i: usize, out: &mut [f32]| rows.row(i, out);
        const ROWS: usize = 256;
        // The same layout as a served store: reserved exactly, on huge pages, then written.
        store.reserve(n)?;
        match &mut store.vectors {
            StoredVectors::F32(v) => {
                v.resize(total, 0.0);
                v.par_chunks_mut(ROWS * dim)
                    .enumerate()
                    .for_each(|(b, chunk)| {
                        for (r, row) in chunk.chunks_exact_mut(dim).enumerate() {
                            gen_row(b * ROWS + r, row);
                        }
                    });
            }
            StoredVectors::F16(v) => {
                v.resize(total, f16::ZERO);
                v.par_chunks_mut(ROWS * dim).enumerate().for_each_init(
                    || vec![0.0f32; dim],
                    |tmp, (b, chunk)| {
                        for (r, row) in chunk.chunks_exact_mut(dim).enumerate() {
                            gen_row(b * ROWS + r, tmp);
                            row.convert_from_f32_slice(tmp);
                        }
                    },
                );
            }
            StoredVectors::I8 { q, scales } => {
                q.resize(total, 0);
                scales.resize(n, 0.0);
                q.par_chunks_mut(ROWS * dim)
                    .zip(scales.par_chunks_mut(ROWS))
                    .enumerate()
                    .for_each_init(
                        || (vec![0.0f32; dim], Vec::with_capacity(dim)),
                        |(tmp, bytes), (b, (chunk, sc))| {
                            for (r, (row, s)) in
                                chunk.chunks_exact_mut(dim).zip(sc.iter_mut()).enumerate()
                            {
                                gen_row(b * ROWS + r, tmp);
                                bytes.clear();
                                *s = quantize_i8(tmp, bytes);
                                for (o, &byte) in row.iter_mut().zip(bytes.iter()) {
                                    *o = byte as i8;
                                }
                            }
                        },
                    );
            }
        }
        store.ids = (0..n).map(|i| i as u32).collect();
        store.means = synthetic_means(n, seed);
        Ok(store)
    }
}

/// The rows of [`VectorStore::synthetic`]: `clusters` unit centres (`[clusters][dim]`, from
/// `seed`), each row a centre plus Gaussian noise, normalised.
struct SyntheticRows {
    centres: Vec<f32>,
    clusters: usize,
    dim: usize,
    seed: u64,
}

impl SyntheticRows {
    /// Writes row `i` (`[dim]`, unit norm; zero for a zero draw) into `out`: normalise(centre +
    /// 0.75 · g / √D), the centre and g drawn from `seed` and `i` only.
    fn row(&self, i: usize, out: &mut [f32]) {
        let dim = self.dim;
        let mut s = self.seed ^ (i as u64).wrapping_mul(0xD6E8_FEB8_6659_FD93) ^ 0xA5A5;
        let c = (splitmix(&mut s) % self.clusters as u64) as usize;
        let centre = &self.centres[c * dim..(c + 1) * dim];
        let sigma = 0.75 / (dim as f32).sqrt();
        let mut norm = 0.0f32;
        for (x, &m) in out.iter_mut().zip(centre) {
            *x = m + sigma * fast_normal(&mut s);
            norm += *x * *x;
        }
        let inv = if norm > 0.0 { norm.sqrt().recip() } else { 0.0 };
        out.iter_mut().for_each(|x| *x *= inv);
    }
}

/// The means of [`VectorStore::synthetic`]'s `n` rows: uniform in a 100 m cube about the
/// origin, drawn from `seed` and the row only.
fn synthetic_means(n: usize, seed: u64) -> Vec<[f32; 3]> {
    (0..n)
        .into_par_iter()
        .map(|i| {
            let mut s = seed ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0x3EA5;
            [
                100.0 * uniform(&mut s) - 50.0,
                100.0 * uniform(&mut s) - 50.0,
                100.0 * uniform(&mut s) - 50.0,
            ]
        })
        .collect()
}
