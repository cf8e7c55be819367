//! Mixture storage of the per-Gaussian embeddings: one shared codebook of mask embeddings plus a
//! few sparse weights per Gaussian.
//!
//! SLAG's per-Gaussian embedding (Semantic Embedding stage)
//!
//! ```text
//!   E_k = Σ_i Σ_j a_kj · E_j / Σ_i Σ_j a_kj
//! ```
//!
//! is a weighted mean of the CLIP embeddings `E_j` of the masks that cover Gaussian `k` in the
//! training images. Instead of storing `E_k` densely (D values per Gaussian), this form stores
//! every mask embedding of the run once (the *codebook*, `M × D`) and, per Gaussian, the `S`
//! largest `a_kj` (over all images) as `(codebook row, weight)` pairs. With `S` at least the number
//! of non-zero `a_kj` of a Gaussian, its reconstruction equals the normalised `E_k` up to f16
//! rounding; with fewer it is the normalised mean of its `S` strongest masks.
//!
//! Because the reconstruction is linear in the codebook, a query needs one dot product per
//! codebook row (`q·E_j`, `M × D` work) and then only `S` multiply-adds per Gaussian
//! ([`MixtureEmbeddings::scores`]).
//!
//! File layout (safetensors, little-endian, readable with `safetensors.numpy.load_file`):
//! - `codebook`     F16 `[M, D]` — mask embeddings `E_j` (L2-normalised CLIP crop embeddings);
//! - `atoms`        U32 `[N, S]` — codebook row of each kept mask, [`UNUSED`] for an empty slot;
//! - `weights`      F16 `[N, S]` — `a_kj / ‖Σ_s a_ks E_s‖` (0 in empty slots), so each row of
//!   `Σ_s weights · codebook[atoms]` has unit L2 norm (up to f16 rounding);
//! - `gaussian_ids` U32 `[N]` — source `.ply` vertex index, strictly ascending;
//! - `means`        F32 `[N, 3]` — Gaussian centres, world frame of the scene, scene units.
//!
//! Metadata (`__metadata__`, strings): `format = "slag-mixture"`, `version = "1"`, `dim`,
//! `model_id` (CLIP visual model id), `keep` (S).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use half::f16;
use half::slice::HalfFloatSliceExt;
use rayon::prelude::*;
use safetensors::tensor::Dtype;

use crate::safetensors_io::{self, FileKind, le_f16, le_f32, le_u32, tensor, triples};
use crate::similarity::dot;
use crate::{Error, Result};

/// Format identifier stored in the metadata.
pub const FORMAT: &str = "slag-mixture";
/// Current format version.
pub const VERSION: &str = "1";

/// The metadata and message words of this file for [`safetensors_io`].
const KIND: FileKind = FileKind {
    format: FORMAT,
    version: VERSION,
    noun: "mixture",
    file_name: "mixture.safetensors",
    rewrite_with: "slag-encoder encode --mixture-keep",
};
/// Atom value of an empty slot (a Gaussian with fewer than `S` non-zero `a_kj`).
pub const UNUSED: u32 = u32::MAX;
/// Largest weight magnitude the f16 file can hold (`f16::MAX`, 65504).
pub const MAX_WEIGHT: f32 = 65504.0;

/// `mixture.safetensors` beside `path` (the encoder writes both into one folder).
pub fn mixture_beside(path: &Path) -> PathBuf {
    path.with_file_name("mixture.safetensors")
}

/// The error for a command that reads the dense file at `path` ([`crate::embeddings`]) when that
/// file is not there or is the mixture: what the encoder wrote instead and how to get the dense
/// file. `None` when neither applies (the caller's own error stands).
pub fn dense_file_needed(path: &Path) -> Option<Error> {
    let is_mixture = path.exists()
        && safetensors_io::metadata_format(path)
            .ok()
            .flatten()
            .as_deref()
            == Some(FORMAT);
    let beside = mixture_beside(path);
    let mixture_here = !path.exists() && beside.is_file();
    (is_mixture || mixture_here).then(|| {
        let what = if is_mixture {
            "this is the mixture form of the embeddings".to_string()
        } else {
            format!(
                "no dense embeddings file here; the encode wrote the mixture form, {}",
                beside.display()
            )
        };
        Error::format(
            path,
            format!(
                "{what}, and this step reads the dense embeddings.safetensors: re-run \
                 `slag-encoder encode` with --dense (it writes the dense file beside the \
                 mixture), or use a command that takes the mixture (partition, query, \
                 eval-objects)"
            ),
        )
    })
}

/// Rounds to the nearest f16 value (what the file stores), returned as f32.
fn round_f16(v: f32) -> f32 {
    f16::from_f32(v).to_f32()
}

/// L2 norm of one Gaussian's reconstruction `‖Σ_s weights[s] · codebook[atoms[s]]‖` (f64
/// accumulation, returned as f32): `codebook` is `[A * dim]` row-major, slots whose atom is
/// beyond it ([`UNUSED`]) count as 0. The one definition shared by [`MixtureEmbeddings::scores`]
/// and the edge's mixture scan, so both divide by the same value.
pub fn row_norm(
    codebook: &[f32],
    dim: usize,
    atoms: &[u32],
    weights: impl IntoIterator<Item = f32>,
) -> f32 {
    let mut acc = vec![0f64; dim];
    for (&a, w) in atoms.iter().zip(weights) {
        let Some(row) = codebook.get(a as usize * dim..(a as usize + 1) * dim) else {
            continue;
        };
        if w == 0.0 {
            continue;
        }
        let w = w as f64;
        acc.iter_mut()
            .zip(row)
            .for_each(|(s, &v)| *s += w * v as f64);
    }
    acc.iter().map(|v| v * v).sum::<f64>().sqrt() as f32
}

/// Per-Gaussian embeddings as a sparse mixture over a shared codebook of mask embeddings.
///
/// All values held here are exactly the values the file stores (the codebook and the weights are
/// rounded to f16 when built), so [`MixtureEmbeddings::write`] then [`MixtureEmbeddings::read`]
/// returns an equal value and every figure measured in memory holds for the file.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct MixtureEmbeddings {
    /// Embedding width D (512 for CLIP ViT-B).
    pub dim: usize,
    /// CLIP visual model id the mask embeddings come from.
    pub model_id: String,
    /// `[M * D]` row-major codebook: the mask embeddings `E_j` some kept atom uses (unit L2 norm
    /// up to f16 rounding), f16-representable values.
    pub codebook: Vec<f32>,
    /// `[N]` source-`.ply` indices of the observed Gaussians, strictly ascending.
    pub gaussian_ids: Vec<u32>,
    /// `[N]` Gaussian centres, world frame of the scene, scene units.
    pub means: Vec<[f32; 3]>,
    /// `S`: atom slots per Gaussian.
    pub keep: usize,
    /// `[N * S]` codebook row per slot, [`UNUSED`] for an empty slot. Within a Gaussian the
    /// slots are ordered by decreasing weight, empty slots last.
    pub atoms: Vec<u32>,
    /// `[N * S]` weights, f16-representable values, 0 in empty slots, scaled so that each
    /// Gaussian's `Σ_s weights · codebook[atoms]` has unit L2 norm (up to f16 rounding).
    pub weights: Vec<f32>,
}

/// The unnormalised input of [`MixtureEmbeddings::from_sparse`]: a codebook and, per Gaussian, a
/// ragged row of `(codebook row, a)` pairs in CSR layout.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SparseMixture {
    /// Embedding width D.
    pub dim: usize,
    /// CLIP visual model id.
    pub model_id: String,
    /// `[M * D]` mask embeddings `E_j` (any precision; rounded to f16 by the build).
    pub codebook: Vec<f32>,
    /// `[N]` source-`.ply` indices, strictly ascending.
    pub gaussian_ids: Vec<u32>,
    /// `[N]` centres, world frame.
    pub means: Vec<[f32; 3]>,
    /// `[N + 1]` offsets into `atoms` / `weights` (row `i` is `offsets[i]..offsets[i + 1]`).
    pub offsets: Vec<usize>,
    /// Codebook rows (`< M`); no repeats within a row.
    pub atoms: Vec<u32>,
    /// Mixture weights `a_kj` (any positive scale; zeros are dropped). f32, as the reductions
    /// keep them (the build's norms run in f64).
    pub weights: Vec<f32>,
}

impl SparseMixture {
    /// The codebook's row count M, once the parts agree with each other. The passes over the
    /// per-entry arrays run in parallel and answer as a serial pass would (the atom named is the
    /// first one out of range).
    ///
    /// Errors ([`Error::Invalid`]): as [`MixtureEmbeddings::from_sparse`], apart from the checks
    /// of each row.
    fn codebook_rows(&self) -> Result<usize> {
        let (dim, n) = (self.dim, self.gaussian_ids.len());
        let bad = |m: String| Err(Error::Invalid(format!("mixture: {m}")));
        if dim == 0 || !self.codebook.len().is_multiple_of(dim) {
            return bad(format!(
                "codebook of {} values for dim {dim}",
                self.codebook.len()
            ));
        }
        let m = self.codebook.len() / dim;
        if m >= UNUSED as usize {
            return bad(format!(
                "{m} codebook rows; at most {} fit u32 ids",
                UNUSED - 1
            ));
        }
        let (offsets, atoms, weights) = (&self.offsets, &self.atoms, &self.weights);
        if self.means.len() != n
            || offsets.len() != n + 1
            || atoms.len() != weights.len()
            || offsets.first() != Some(&0)
            || offsets.last() != Some(&atoms.len())
            || offsets.par_windows(2).any(|w| w[0] > w[1])
        {
            return bad(format!(
                "{n} ids, {} means, {} offsets, {} atoms, {} weights disagree",
                self.means.len(),
                offsets.len(),
                atoms.len(),
                weights.len()
            ));
        }
        if self.gaussian_ids.par_windows(2).any(|w| w[0] >= w[1]) {
            return bad("Gaussian ids are not strictly ascending".into());
        }
        if self.codebook.par_iter().any(|v| !v.is_finite())
            || weights.par_iter().any(|v| !v.is_finite())
        {
            return bad("non-finite codebook value or weight".into());
        }
        if let Some(a) = atoms.par_iter().find_first(|&&a| a as usize >= m) {
            return bad(format!("atom {a} beyond the {m} codebook rows"));
        }
        Ok(m)
    }

    /// `S` of the stored form: the most non-zero weights in any row, at least 1. Call after
    /// [`SparseMixture::codebook_rows`] (the offsets index the weights).
    fn longest_row(&self) -> usize {
        self.offsets
            .par_windows(2)
            .map(|w| {
                self.weights[w[0]..w[1]]
                    .iter()
                    .filter(|&&a| a != 0.0)
                    .count()
            })
            .max()
            .unwrap_or(0)
            .max(1)
    }
}

/// The codebook rows some non-zero weight uses, renumbered in their original order: each of the
/// `m` rows' new number ([`UNUSED`] for a dropped row) and the kept rows as f16, `[kept, dim]`
/// row-major (the values the file stores; half the bytes of f32 for the rows' many random
/// reads). The marking and the rounding run in parallel; the numbering is one serial pass over
/// the `m` rows.
fn used_codebook(
    codebook: &[f32],
    dim: usize,
    m: usize,
    atoms: &[u32],
    weights: &[f32],
) -> (Vec<u32>, Vec<f16>) {
    let used: Vec<AtomicBool> = (0..m).map(|_| AtomicBool::new(false)).collect();
    atoms.par_iter().zip(weights).for_each(|(&a, &w)| {
        // Only the first sighting writes, so that workers seldom contend for a line.
        let u = &used[a as usize];
        if w != 0.0 && !u.load(Ordering::Relaxed) {
            u.store(true, Ordering::Relaxed);
        }
    });
    let mut new_row = vec![UNUSED; m];
    let mut kept = Vec::new();
    for (r, u) in used.iter().enumerate() {
        if u.load(Ordering::Relaxed) {
            new_row[r] = kept.len() as u32;
            kept.push(r);
        }
    }
    drop(used);
    let mut book = vec![f16::ZERO; kept.len() * dim];
    book.par_chunks_mut(dim)
        .zip(kept.par_iter())
        .for_each(|(out, &r)| out.convert_from_f32_slice(&codebook[r * dim..(r + 1) * dim]));
    (new_row, book)
}

/// The f16 rows as f32 (exact), in parallel: the stored codebook.
fn widened(book: &[f16], dim: usize) -> Vec<f32> {
    let mut out = vec![0f32; book.len()];
    out.par_chunks_mut(dim)
        .zip(book.par_chunks(dim))
        .for_each(|(o, h)| h.convert_to_f32_slice(o));
    out
}

/// The largest used codebook (rows M) whose Gram matrix the build computes (`M² × 8` bytes:
/// 32 MiB at the limit). Beyond it each row's norm comes from its weighted sum instead.
pub(crate) const GRAM_MAX_ROWS: usize = 2048;

/// Where [`MixtureEmbeddings::from_sparse_with`] takes each row's norm from.
#[derive(Clone, Copy, Debug)]
pub(crate) enum GramUse {
    /// The Gram matrix when it is the cheaper: at most [`GRAM_MAX_ROWS`] used codebook rows M,
    /// and `M²` at most the sparse entries (`M² · D` work to make it, against `entries · D` for
    /// the sums).
    WhenCheaper,
    /// Always the Gram matrix (the tests' check of that path).
    #[cfg(test)]
    Always,
    /// Always the sums (the tests' check of that path).
    #[cfg(test)]
    Never,
}

impl GramUse {
    /// Whether a build over `used` codebook rows and `entries` sparse entries uses the matrix.
    pub(crate) fn applies(self, used: usize, entries: usize) -> bool {
        match self {
            GramUse::WhenCheaper => used <= GRAM_MAX_ROWS && used * used <= entries,
            #[cfg(test)]
            GramUse::Always => true,
            #[cfg(test)]
            GramUse::Never => false,
        }
    }
}

/// The Gram matrix of the codebook `book` (`[M, D]` row-major, f32 values of f16 rows):
/// `[M * M]` f64 with entry `(s, t)` = `Σ_d book[s, d] · book[t, d]`, each summed in dimension
/// order (so `(s, t)` and `(t, s)` are the same bits). Rows in parallel.
fn gram_matrix(book: &[f32], dim: usize) -> Vec<f64> {
    let m = book.len() / dim;
    let mut g = vec![0f64; m * m];
    g.par_chunks_mut(m.max(1))
        .zip(book.par_chunks(dim))
        .for_each(|(out, es)| {
            for (o, et) in out.iter_mut().zip(book.chunks_exact(dim)) {
                *o = es
                    .iter()
                    .zip(et)
                    .fold(0f64, |acc, (&x, &y)| acc + x as f64 * y as f64);
            }
        });
    g
}

/// How [`fill_rows`] finds each row's norm `‖Σ_s a_s · E_s‖`: from the codebook's Gram matrix
/// (`[M * M]`, [`gram_matrix`]) when the codebook is small, else from the weighted sum itself.
#[derive(Clone, Copy)]
enum Norms<'a> {
    /// `sqrt(Σ_s Σ_t a_s · a_t · G[s, t])`, `s` then `t` in slot order: `S²` multiply-adds
    /// per Gaussian instead of `S · D`.
    Gram {
        /// `[M * M]`, [`gram_matrix`].
        g: &'a [f64],
        /// M.
        m: usize,
    },
    /// The `[D]` sum in f64, each dimension summed in slot order, the squares in dimension
    /// order.
    Sums,
}

/// Gaussians whose rows one worker normalises together: the sums of squares of their norms run
/// side by side (each still in dimension order, so each as alone), not one long chain of
/// dependent additions after another.
const BATCH: usize = 8;

/// What one worker of [`MixtureEmbeddings::from_sparse`] reuses from batch to batch, so that a
/// row costs no allocation: each batched Gaussian's row of `(kept codebook row, a)`, the
/// `[BATCH, D]` f64 accumulators of their weighted sums (empty when the norms come from the
/// Gram matrix), and room to sort the ids of a long row.
struct RowScratch {
    rows: [Vec<(u32, f64)>; BATCH],
    acc: Vec<f64>,
    ids: Vec<u32>,
}

impl RowScratch {
    fn new(dim: usize, keep: usize, norms: Norms) -> Self {
        let sums = matches!(norms, Norms::Sums);
        RowScratch {
            rows: std::array::from_fn(|_| Vec::with_capacity(keep)),
            acc: vec![0.0; if sums { BATCH * dim } else { 0 }],
            ids: Vec::new(),
        }
    }
}

/// True when `row` names some codebook row twice: compared pairwise in a short row, through a
/// sorted copy of the ids (in `ids`, reused) in a long one.
fn repeats_an_atom(row: &[(u32, f64)], ids: &mut Vec<u32>) -> bool {
    if row.len() <= 32 {
        return (1..row.len()).any(|i| row[..i].iter().any(|x| x.0 == row[i].0));
    }
    ids.clear();
    ids.extend(row.iter().map(|r| r.0));
    ids.sort_unstable();
    ids.windows(2).any(|w| w[0] == w[1])
}

/// Writes the `S` packed slots of a batch of Gaussians (`ids`, at most [`BATCH`]) from their
/// rows of `(kept codebook row, a)` (the non-zero `a`, in `s.rows`): each ordered by decreasing
/// `a` (ties: lower row first), scaled by `1 / ‖Σ_s a_s · E_s‖` over the f16-rounded codebook
/// `book` (`[M, D]` as f32; f64, found as `norms` says), rounded to f16; the slots past a row get
/// [`UNUSED`] and 0.
///
/// Errors (the message, naming the first failing Gaussian of the batch): a repeated atom, a
/// weighted sum of zero, a weight beyond the f16 range (checked per Gaussian in that order); the
/// slots are then left part-written.
fn fill_rows(
    s: &mut RowScratch,
    book: &[f32],
    norms: Norms,
    ids: &[u32],
    atoms: &mut [u32],
    weights: &mut [f32],
) -> std::result::Result<(), String> {
    let ready = sort_rows(s, ids.len());
    let rows = &s.rows[..ready];
    let mut squares = [0f64; BATCH];
    match norms {
        Norms::Gram { g, m } => {
            for (sum, row) in squares.iter_mut().zip(rows) {
                *sum = gram_square(g, m, row);
            }
        }
        Norms::Sums => summed_squares(&mut s.acc, book, rows, &mut squares),
    }
    let keep = atoms.len() / ids.len();
    let slots = atoms
        .chunks_exact_mut(keep)
        .zip(weights.chunks_exact_mut(keep));
    for (g, (slot_atoms, slot_weights)) in slots.enumerate().take(ready) {
        write_slots(
            &s.rows[g],
            squares[g].sqrt(),
            ids[g],
            slot_atoms,
            slot_weights,
        )?;
    }
    match ids.get(ready) {
        Some(id) => Err(format!("Gaussian {id} repeats an atom")),
        None => Ok(()),
    }
}

/// Orders the first `n` rows of `s` by decreasing `a` (ties: lower codebook row first). Returns
/// how many of them come before the first row that repeats an atom (`n` when none does): a
/// repeat ends the batch, and the rows before it may still fail first.
fn sort_rows(s: &mut RowScratch, n: usize) -> usize {
    for (g, row) in s.rows.iter_mut().enumerate().take(n) {
        row.sort_unstable_by(|x, y| y.1.total_cmp(&x.1).then(x.0.cmp(&y.0)));
        if repeats_an_atom(row, &mut s.ids) {
            return g;
        }
    }
    n
}

/// `Σ_s Σ_t a_s · a_t · G[s, t]` over one ordered row, `s` then `t` in slot order (f64): the
/// squared norm of its weighted sum, from the codebook's Gram matrix `g` (`[m * m]`).
fn gram_square(g: &[f64], m: usize, row: &[(u32, f64)]) -> f64 {
    let mut sum = 0f64;
    for &(s, a) in row {
        let g_s = &g[s as usize * m..(s as usize + 1) * m];
        for &(t, b) in row {
            sum += a * b * g_s[t as usize];
        }
    }
    sum
}

/// The squared norms of the batch's weighted sums `Σ_s a_s · E_s` into `squares` (one per row of
/// `rows`): each sum in the f64 lanes `acc` (`[BATCH, D]`), each dimension summed in slot order,
/// then the squares in dimension order, the batch's sums side by side (each still as alone).
fn summed_squares(
    acc: &mut [f64],
    book: &[f32],
    rows: &[Vec<(u32, f64)>],
    squares: &mut [f64; BATCH],
) {
    let dim = acc.len() / BATCH;
    // One read per cache line of every codebook row the batch uses, all independent, so the
    // processor fetches the lines side by side before the sums walk them row after row.
    let mut probe = 0u32;
    for row in rows {
        for &(a, _) in row {
            let e = &book[a as usize * dim..(a as usize + 1) * dim];
            e.iter().step_by(16).for_each(|v| probe |= v.to_bits());
        }
    }
    std::hint::black_box(probe);
    for (row, acc) in rows.iter().zip(acc.chunks_exact_mut(dim)) {
        acc.fill(0.0);
        for &(a, w) in row {
            let e = &book[a as usize * dim..(a as usize + 1) * dim];
            acc.iter_mut().zip(e).for_each(|(s, &v)| *s += w * v as f64);
        }
    }
    // Lanes past the batch's rows hold stale sums nobody reads.
    let lanes: [&[f64]; BATCH] = std::array::from_fn(|g| &acc[g * dim..(g + 1) * dim]);
    for d in 0..dim {
        for (sum, lane) in squares.iter_mut().zip(&lanes) {
            *sum += lane[d] * lane[d];
        }
    }
}

/// Writes one Gaussian's slots from its ordered row and the norm of its weighted sum: each
/// `a / norm` rounded to f16, then [`UNUSED`] and 0 past the row.
///
/// Errors (the message, naming Gaussian `id`): a norm of zero or not finite, a weight beyond the
/// f16 range.
fn write_slots(
    row: &[(u32, f64)],
    norm: f64,
    id: u32,
    atoms: &mut [u32],
    weights: &mut [f32],
) -> std::result::Result<(), String> {
    if !(norm.is_finite() && norm > 0.0) {
        return Err(format!(
            "Gaussian {id}: its weighted mask embeddings sum to zero (no direction)"
        ));
    }
    let mut out = atoms.iter_mut().zip(weights.iter_mut());
    for (&(a, w), (slot_atom, slot_weight)) in row.iter().zip(&mut out) {
        let scaled = w / norm;
        if scaled.abs() > MAX_WEIGHT as f64 {
            return Err(format!(
                "Gaussian {id}: weight {scaled:e} beyond the f16 range (its mask embeddings \
                 nearly cancel out); such a Gaussian cannot be stored as a mixture, \
                 use the dense embeddings file"
            ));
        }
        *slot_atom = a;
        *slot_weight = round_f16(scaled as f32);
    }
    for (slot_atom, slot_weight) in out {
        *slot_atom = UNUSED;
        *slot_weight = 0.0;
    }
    Ok(())
}

/// Moves the sparse rows (`offsets`, `[N + 1]`, into `atoms` and `weights`) into `keep` slots
/// per Gaussian in place: row `i`'s entries of non-zero weight, in their order, at
/// `[i · keep, i · keep + count)`, then slots of atom 0 and weight 0 (which the build reads as
/// empty) up to `(i + 1) · keep`; both arrays end `N · keep` long. `keep` is at least each row's
/// count of non-zero weights ([`SparseMixture::longest_row`]). Two serial passes: the non-zero
/// entries packed forward (each lands at or before where it was), then the rows spread
/// backward (each lands at or after where it was), so that no entry is overwritten before it
/// is moved; none when every row already fills its slots.
fn pad_rows_in_place(
    mut offsets: Vec<usize>,
    atoms: &mut Vec<u32>,
    weights: &mut Vec<f32>,
    keep: usize,
) {
    let n = offsets.len() - 1;
    let padded = atoms.len() == n * keep
        && offsets.par_iter().enumerate().all(|(i, &o)| o == i * keep)
        && weights.par_iter().all(|&w| w != 0.0);
    if padded {
        return;
    }
    // Forward: the non-zero entries, `offsets[i]` becoming where row `i`'s now start.
    let (mut write, mut read) = (0, 0);
    for i in 0..n {
        let end = offsets[i + 1];
        offsets[i] = write;
        for e in read..end {
            if weights[e] != 0.0 {
                atoms[write] = atoms[e];
                weights[write] = weights[e];
                write += 1;
            }
        }
        read = end;
    }
    offsets[n] = write;
    // Backward: each row to its slots.
    let len = atoms.len().max(n * keep);
    // Exactly: a doubled capacity would stay reserved with the stored form.
    atoms.reserve_exact(len - atoms.len());
    weights.reserve_exact(len - weights.len());
    atoms.resize(len, 0);
    weights.resize(len, 0.0);
    for i in (0..n).rev() {
        let (start, end, slot) = (offsets[i], offsets[i + 1], i * keep);
        atoms.copy_within(start..end, slot);
        weights.copy_within(start..end, slot);
        atoms[slot + end - start..slot + keep].fill(0);
        weights[slot + end - start..slot + keep].fill(0.0);
    }
    atoms.truncate(n * keep);
    weights.truncate(n * keep);
}

impl MixtureEmbeddings {
    /// Builds the stored form from sparse rows: drops codebook rows no atom uses (renumbering the
    /// rest in their original order), rounds the codebook to f16, orders each row by decreasing
    /// `a` (ties: lower codebook row first), sets `S` to the longest row, and scales each row's
    /// weights by `1 / ‖Σ_s a_s · E_s‖` (computed in f64 with the f16-rounded codebook) before
    /// rounding them to f16. Where it is the cheaper ([`GramUse::WhenCheaper`]: a small codebook
    /// beside many Gaussians) the norm comes from the codebook's Gram matrix (`S²` multiply-adds
    /// per Gaussian, where the sum costs `S · D`); the two agree to f64 rounding, far below the
    /// f16 rounding of the stored weights.
    ///
    /// The rows are written straight into the `[N, S]` arrays in parallel (rayon), and the sparse
    /// inputs are freed as soon as they are spent, so the build holds at most the parts plus the
    /// stored form.
    ///
    /// Errors ([`Error::Invalid`]): inconsistent lengths, ids not strictly ascending, an atom out of
    /// range or repeated in a row, non-finite values, a row whose weighted codebook rows sum to
    /// zero (no direction), or a weight beyond the f16 range (the kept mask embeddings nearly
    /// cancel: `‖Σ a E‖ < Σ|a| / 65504`). A row's error names the first such Gaussian in id order.
    pub fn from_sparse(parts: SparseMixture) -> Result<MixtureEmbeddings> {
        Self::from_sparse_with(parts, GramUse::WhenCheaper)
    }

    /// [`MixtureEmbeddings::from_sparse`] with the norms from the Gram matrix where `gram` says.
    pub(crate) fn from_sparse_with(
        parts: SparseMixture,
        gram: GramUse,
    ) -> Result<MixtureEmbeddings> {
        let m = parts.codebook_rows()?;
        let keep = parts.longest_row();
        let SparseMixture {
            dim,
            model_id,
            codebook,
            gaussian_ids,
            means,
            offsets,
            atoms,
            weights,
        } = parts;
        let (new_row, book) = used_codebook(&codebook, dim, m, &atoms, &weights);
        drop(codebook);
        let codebook = widened(&book, dim);
        drop(book);
        let used = codebook.len() / dim;
        let g = gram
            .applies(used, atoms.len())
            .then(|| gram_matrix(&codebook, dim));
        let norms = match &g {
            Some(g) => Norms::Gram { g, m: used },
            None => Norms::Sums,
        };
        // The rows' non-zero entries moved into `keep` slots per Gaussian in place, so that the
        // packed arrays are the sparse ones (no second copy of the pairs beside them: 32 bytes
        // a Gaussian at S = 4); each batch then reads its own slots before `fill_rows`
        // overwrites them.
        let (mut packed_atoms, mut packed_weights) = (atoms, weights);
        pad_rows_in_place(offsets, &mut packed_atoms, &mut packed_weights, keep);
        let failed = packed_atoms
            .par_chunks_mut(keep * BATCH)
            .zip(packed_weights.par_chunks_mut(keep * BATCH))
            .enumerate()
            .map_init(
                || RowScratch::new(dim, keep, norms),
                |s, (b, (slot_atoms, slot_weights))| {
                    let first = b * BATCH;
                    let batch = first..first + slot_atoms.len() / keep;
                    let slots = slot_atoms
                        .chunks_exact(keep)
                        .zip(slot_weights.chunks_exact(keep));
                    for (row, (a, w)) in s.rows.iter_mut().zip(slots) {
                        row.clear();
                        row.extend(
                            a.iter()
                                .zip(w)
                                .filter(|&(_, &w)| w != 0.0)
                                .map(|(&a, &w)| (new_row[a as usize], f64::from(w))),
                        );
                    }
                    let ids = &gaussian_ids[batch];
                    fill_rows(s, &codebook, norms, ids, slot_atoms, slot_weights)
                },
            )
            .find_map_first(std::result::Result::err);
        drop((new_row, g));
        if let Some(m) = failed {
            return Err(Error::Invalid(format!("mixture: {m}")));
        }
        Ok(MixtureEmbeddings {
            dim,
            model_id,
            codebook,
            gaussian_ids,
            means,
            keep,
            atoms: packed_atoms,
            weights: packed_weights,
        })
    }

    /// Number of stored (observed) Gaussians N.
    pub fn len(&self) -> usize {
        self.gaussian_ids.len()
    }
    /// True when no Gaussian is stored.
    pub fn is_empty(&self) -> bool {
        self.gaussian_ids.is_empty()
    }
    /// Number of codebook rows M.
    pub fn codebook_len(&self) -> usize {
        self.codebook.len().checked_div(self.dim).unwrap_or(0)
    }

    /// Codebook row `j` (`[D]`), `None` beyond the codebook (including [`UNUSED`]).
    fn row(&self, j: u32) -> Option<&[f32]> {
        let j = j as usize;
        self.codebook.get(j * self.dim..(j + 1) * self.dim)
    }

    /// The reconstructed unit embedding of stored Gaussian `i` (`[D]`):
    /// `Σ_s weights[i,s] · codebook[atoms[i,s]]`, unit L2 norm up to f16 rounding of the weights.
    ///
    /// # Panics
    /// If `i >= len()` (like slice indexing).
    pub fn vector(&self, i: usize) -> Vec<f32> {
        let mut v = vec![0f32; self.dim];
        self.add_vector_into(i, &mut v);
        v
    }

    /// Adds row `i`'s reconstruction `Σ_s weights · codebook[atoms]` into `out` (`[D]`).
    pub(crate) fn add_vector_into(&self, i: usize, out: &mut [f32]) {
        let slots = i * self.keep..(i + 1) * self.keep;
        for (&a, &w) in self.atoms[slots.clone()].iter().zip(&self.weights[slots]) {
            if let Some(e) = self.row(a) {
                out.iter_mut().zip(e).for_each(|(o, &v)| *o += w * v);
            }
        }
    }

    /// All reconstructed embeddings, `[N * D]` row-major (row `i` = [`MixtureEmbeddings::vector`]).
    pub fn to_dense(&self) -> Vec<f32> {
        let mut out = vec![0f32; self.len() * self.dim];
        if self.dim > 0 {
            out.par_chunks_mut(self.dim)
                .enumerate()
                .for_each(|(i, row)| self.add_vector_into(i, row));
        }
        out
    }

    /// The L2 norm of every Gaussian's reconstruction `‖Σ_s weights · codebook[atoms]‖` (`[N]`,
    /// [`row_norm`]): 1 up to f16 rounding for a mixture as built, less for one cut to fewer
    /// slots ([`MixtureEmbeddings::truncated`]). What [`MixtureEmbeddings::scores`] divides by.
    ///
    /// Errors: [`Error::Internal`] for arrays of inconsistent lengths.
    pub fn norms(&self) -> Result<Vec<f32>> {
        self.check_shapes()?;
        Ok(self
            .atoms
            .par_chunks_exact(self.keep)
            .zip(self.weights.par_chunks_exact(self.keep))
            .map(|(a, w)| row_norm(&self.codebook, self.dim, a, w.iter().copied()))
            .collect())
    }

    /// The same Gaussians with only their first `slots` slots (their `slots` largest weights:
    /// slots are ordered by decreasing weight), weights unchanged (not renormalised: the cosine
    /// divides by the norm), and the codebook rows no kept slot uses dropped (the rest renumbered
    /// in their original order). `slots ≥ keep` returns an equal copy. This is eval-colors'
    /// "mean over the top `s` masks" (`heldout_variants`, S = 8 cut from 16): every score equals
    /// the dense cosine of that variant's reconstruction.
    ///
    /// Errors: `slots == 0` ([`Error::Param`] `mixture_slots`), inconsistent arrays
    /// ([`Error::Internal`]).
    pub fn truncated(&self, slots: usize) -> Result<MixtureEmbeddings> {
        if slots == 0 {
            return Err(Error::param(
                "mixture_slots",
                0,
                "at least 1 slot per Gaussian (at most the file's keep)",
            ));
        }
        self.validate()?;
        let s = slots.min(self.keep);
        let m = self.codebook_len();
        let mut used = vec![false; m];
        for row in self.atoms.chunks_exact(self.keep) {
            for &a in &row[..s] {
                if let Some(u) = used.get_mut(a as usize) {
                    *u = true;
                }
            }
        }
        let mut new_row = vec![UNUSED; m];
        let mut codebook = Vec::new();
        let mut next = 0u32;
        for (j, &u) in used.iter().enumerate() {
            if u {
                new_row[j] = next;
                next += 1;
                codebook.extend_from_slice(&self.codebook[j * self.dim..(j + 1) * self.dim]);
            }
        }
        let mut atoms = Vec::with_capacity(self.len() * s);
        let mut weights = Vec::with_capacity(self.len() * s);
        for (a, w) in self
            .atoms
            .chunks_exact(self.keep)
            .zip(self.weights.chunks_exact(self.keep))
        {
            atoms.extend(
                a[..s]
                    .iter()
                    .map(|&x| new_row.get(x as usize).copied().unwrap_or(UNUSED)),
            );
            weights.extend_from_slice(&w[..s]);
        }
        Ok(MixtureEmbeddings {
            dim: self.dim,
            model_id: self.model_id.clone(),
            codebook,
            gaussian_ids: self.gaussian_ids.clone(),
            means: self.means.clone(),
            keep: s,
            atoms,
            weights,
        })
    }

    /// Bytes of the tensors as written to disk: the codebook at f16 (`M·D·2`, shared by all
    /// Gaussians) plus per Gaussian `S × (4 B atom + 2 B f16 weight)`, 4 B id and 12 B mean. The
    /// safetensors JSON header (a few hundred bytes) is not counted.
    pub fn stored_bytes(&self) -> usize {
        self.codebook.len() * 2 + self.len() * (self.keep * 6 + 4 + 12)
    }

    /// [`MixtureEmbeddings::stored_bytes`] per stored Gaussian (the codebook amortised over N);
    /// 0 when empty. Compare with 1040 B (dense f16, D = 512) or 2064 B (dense f32).
    pub fn bytes_per_gaussian(&self) -> f64 {
        if self.is_empty() {
            0.0
        } else {
            self.stored_bytes() as f64 / self.len() as f64
        }
    }

    /// Checks the arrays agree (lengths, `S ≥ 1`, atoms in range or [`UNUSED`] with weight 0,
    /// finite values, weights within the f16 range, ids strictly ascending).
    ///
    /// Errors: [`Error::Internal`] naming the first inconsistency (the reduction that builds
    /// a mixture keeps them consistent).
    pub fn validate(&self) -> Result<()> {
        self.check()
            .map_err(|m| Error::internal(format!("mixture: {m}")))
    }

    fn check(&self) -> std::result::Result<(), String> {
        let n = self.len();
        if self.dim == 0 || !self.codebook.len().is_multiple_of(self.dim) {
            return Err(format!(
                "codebook of {} values for dim {}",
                self.codebook.len(),
                self.dim
            ));
        }
        if self.keep == 0 {
            return Err("keep (atom slots per Gaussian) is 0".into());
        }
        if self.means.len() != n
            || self.atoms.len() != n * self.keep
            || self.weights.len() != n * self.keep
        {
            return Err(format!(
                "{n} ids, {} means, {} atoms, {} weights for keep {}",
                self.means.len(),
                self.atoms.len(),
                self.weights.len(),
                self.keep
            ));
        }
        if self.gaussian_ids.windows(2).any(|w| w[0] >= w[1]) {
            return Err("Gaussian ids are not strictly ascending".into());
        }
        if self.codebook.iter().any(|v| !v.is_finite())
            || self.means.iter().flatten().any(|v| !v.is_finite())
        {
            return Err("non-finite codebook value or mean".into());
        }
        let m = self.codebook_len();
        for (&a, &w) in self.atoms.iter().zip(&self.weights) {
            if !(w.is_finite() && w.abs() <= MAX_WEIGHT) {
                return Err(format!("weight {w} is not a finite f16 value"));
            }
            if a == UNUSED {
                if w != 0.0 {
                    return Err(format!("an empty slot carries weight {w}"));
                }
            } else if a as usize >= m {
                return Err(format!("atom {a} beyond the {m} codebook rows"));
            }
        }
        Ok(())
    }

    /// Normalised copy of a query, or a typed error.
    fn unit_query(&self, query: &[f32]) -> Result<Vec<f32>> {
        if query.len() != self.dim {
            return Err(Error::mismatch(
                crate::Mismatched::EmbeddingWidth,
                format!(
                    "query has {} components, the mixture embeddings have {}; use the text tower \
                     of the same CLIP model",
                    query.len(),
                    self.dim
                ),
            ));
        }
        crate::similarity::unit_query(query)
    }

    fn check_shapes(&self) -> Result<()> {
        let n = self.len();
        if self.dim == 0
            || self.keep == 0
            || !self.codebook.len().is_multiple_of(self.dim)
            || self.atoms.len() != n * self.keep
            || self.weights.len() != n * self.keep
        {
            return self.validate();
        }
        Ok(())
    }

    /// Cosine similarity of every stored Gaussian with `query` (`[D]`, any norm; normalised here):
    /// `[N]` scores. Computes `q·E_j` once per codebook row, then per Gaussian the sparse sum
    /// `Σ_s weights · (q·E_atom)` divided by the reconstruction's norm ([`MixtureEmbeddings::norms`];
    /// 1 up to f16 rounding of the weights, less after [`MixtureEmbeddings::truncated`]): the
    /// paper's query rule over the reconstructed `E_k`, exactly (rayon over N). A Gaussian whose
    /// reconstruction is zero scores 0.
    ///
    /// Errors: `query.len() != dim` ([`Error::Mismatch`]), a zero or non-finite query
    /// ([`Error::Query`]), arrays of inconsistent lengths ([`Error::Internal`]).
    pub fn scores(&self, query: &[f32]) -> Result<Vec<f32>> {
        self.check_shapes()?;
        let q = self.unit_query(query)?;
        let norms = self.norms()?;
        let proj: Vec<f32> = self
            .codebook
            .par_chunks_exact(self.dim)
            .map(|row| dot(row, &q))
            .collect();
        Ok(self
            .atoms
            .par_chunks_exact(self.keep)
            .zip(self.weights.par_chunks_exact(self.keep))
            .zip(norms.par_iter())
            .map(|((atoms, weights), &norm)| {
                let s: f32 = atoms
                    .iter()
                    .zip(weights)
                    .map(|(&a, &w)| proj.get(a as usize).map_or(0.0, |&p| w * p))
                    .sum();
                if norm > 0.0 { s / norm } else { 0.0 }
            })
            .collect())
    }

    /// The mixture's *max* form: per Gaussian, the highest cosine of `query` (`[D]`, any
    /// norm) with any of its `top` strongest mask embeddings (its first `min(top, S)` non-empty
    /// slots, which hold its largest `a_kj`), instead of the cosine with their weighted mean
    /// ([`MixtureEmbeddings::scores`]). `[N]` scores; a Gaussian without atoms scores 0. One dot
    /// per codebook row, then `top` comparisons per Gaussian.
    ///
    /// Errors: `top == 0` ([`Error::Param`]), and as [`MixtureEmbeddings::scores`].
    pub fn max_atom_scores(&self, query: &[f32], top: usize) -> Result<Vec<f32>> {
        if top == 0 {
            return Err(Error::param(
                "top",
                top,
                "at least 1 mask embedding to take the max over",
            ));
        }
        self.check_shapes()?;
        let q = self.unit_query(query)?;
        let proj: Vec<f32> = self
            .codebook
            .par_chunks_exact(self.dim)
            .map(|row| {
                let norm = dot(row, row).sqrt();
                if norm > 0.0 { dot(row, &q) / norm } else { 0.0 }
            })
            .collect();
        Ok(self
            .atoms
            .par_chunks_exact(self.keep)
            .map(|atoms| {
                atoms
                    .iter()
                    .take(top)
                    .filter_map(|&a| proj.get(a as usize).copied())
                    .reduce(f32::max)
                    .unwrap_or(0.0)
            })
            .collect())
    }

    /// [`MixtureEmbeddings::scores`] for several queries in one pass over the Gaussians:
    /// `[queries.len()][N]`.
    ///
    /// Errors: as [`MixtureEmbeddings::scores`], for the first bad query.
    pub fn scores_many(&self, queries: &[&[f32]]) -> Result<Vec<Vec<f32>>> {
        self.check_shapes()?;
        let qs = queries
            .iter()
            .map(|q| self.unit_query(q))
            .collect::<Result<Vec<_>>>()?;
        let nq = qs.len();
        if nq == 0 {
            return Ok(Vec::new());
        }
        // proj[j * nq + t] = q_t · E_j
        let proj: Vec<f32> = self
            .codebook
            .par_chunks_exact(self.dim)
            .flat_map_iter(|row| qs.iter().map(move |q| dot(row, q)))
            .collect();
        let norms = self.norms()?;
        let mut flat = vec![0f32; self.len() * nq];
        flat.par_chunks_mut(nq)
            .zip(self.atoms.par_chunks_exact(self.keep))
            .zip(self.weights.par_chunks_exact(self.keep))
            .zip(norms.par_iter())
            .for_each(|(((out, atoms), weights), &norm)| {
                for (&a, &w) in atoms.iter().zip(weights) {
                    if let Some(p) = proj.get(a as usize * nq..(a as usize + 1) * nq) {
                        out.iter_mut().zip(p).for_each(|(o, &p)| *o += w * p);
                    }
                }
                let inv = if norm > 0.0 { norm.recip() } else { 0.0 };
                out.iter_mut().for_each(|o| *o *= inv);
            });
        Ok((0..nq)
            .map(|t| flat.iter().skip(t).step_by(nq).copied().collect())
            .collect())
    }

    /// Writes the file atomically (`<path>.partial`, fsync, rename; see the module docs for the
    /// layout).
    ///
    /// Errors: [`Error::Internal`] when [`MixtureEmbeddings::validate`] fails, I/O.
    pub fn write(&self, path: &Path) -> Result<()> {
        self.validate()?;
        let (n, s, m, d) = (self.len(), self.keep, self.codebook_len(), self.dim);
        let book: Vec<f16> = self.codebook.iter().map(|&v| f16::from_f32(v)).collect();
        let weights: Vec<f16> = self.weights.iter().map(|&v| f16::from_f32(v)).collect();
        let tensors = vec![
            tensor("codebook", vec![m, d], &book),
            tensor("atoms", vec![n, s], &self.atoms),
            tensor("weights", vec![n, s], &weights),
            tensor("gaussian_ids", vec![n], &self.gaussian_ids),
            tensor("means", vec![n, 3], &self.means),
        ];
        let meta = [
            ("dim", d.to_string()),
            ("model_id", self.model_id.clone()),
            ("keep", s.to_string()),
        ];
        safetensors_io::write(path, &KIND, tensors, &meta)
    }

    /// Reads a file written by [`MixtureEmbeddings::write`].
    ///
    /// Errors: [`Error::Io`]; [`Error::Format`] (naming the file) for a file that is not
    /// safetensors, another format or version, missing tensors, wrong dtypes or shapes, metadata
    /// that disagrees with the shapes, atoms out of range, non-finite values, or ids not
    /// ascending.
    pub fn read(path: &Path) -> Result<MixtureEmbeddings> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let bad = |m: String| Error::format(path, m);
        let file = safetensors_io::open(path, &bytes, &KIND)?;
        let meta = &file.meta;
        let num = |key: &str| -> Result<usize> {
            meta.get(key)
                .and_then(|v| v.parse().ok())
                .ok_or_else(|| bad(format!("metadata {key} missing or not a number")))
        };
        let (dim, keep) = (num("dim")?, num("keep")?);
        let get = |name: &str, dtype: Dtype| file.tensor_of(path, name, dtype);
        let book_t = get("codebook", Dtype::F16)?;
        let atoms_t = get("atoms", Dtype::U32)?;
        let weights_t = get("weights", Dtype::F16)?;
        let ids_t = get("gaussian_ids", Dtype::U32)?;
        let means_t = get("means", Dtype::F32)?;
        let n = ids_t.shape().first().copied().unwrap_or(0);
        let m = book_t.shape().first().copied().unwrap_or(0);
        if book_t.shape() != [m, dim]
            || atoms_t.shape() != [n, keep]
            || weights_t.shape() != [n, keep]
            || ids_t.shape() != [n]
            || means_t.shape() != [n, 3]
        {
            return Err(bad(format!(
                "tensor shapes disagree with the mixture layout (dim {dim}, keep {keep}): \
                 codebook {:?}, atoms {:?}, weights {:?}, gaussian_ids {:?}, means {:?}",
                book_t.shape(),
                atoms_t.shape(),
                weights_t.shape(),
                ids_t.shape(),
                means_t.shape()
            )));
        }
        let out = MixtureEmbeddings {
            dim,
            model_id: meta.get("model_id").cloned().unwrap_or_default(),
            codebook: le_f16(book_t.data()),
            gaussian_ids: le_u32(ids_t.data()),
            means: triples(&le_f32(means_t.data())),
            keep,
            atoms: le_u32(atoms_t.data()),
            weights: le_f16(weights_t.data()),
        };
        out.check().map_err(bad)?;
        Ok(out)
    }
}

#[cfg(test)]
mod build_tests;

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests;
