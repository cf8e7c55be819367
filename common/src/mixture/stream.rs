//! The stored form built run by run, as a reduction hands over its Gaussians: each run of rows is
//! checked and packed into the `[N, S]` slot arrays when it arrives, so no sparse copy of every
//! row (`f64` weights, `usize` offsets) is ever held, and the packing of one run overlaps the
//! reduction of the next (the device reduction's tiles, in `slag-encoder`'s finish).

use std::sync::atomic::{AtomicBool, Ordering};

use half::f16;
use half::slice::HalfFloatSliceExt;
use rayon::prelude::*;

use super::{MixtureEmbeddings, UNUSED, pack_rows, widened};
use crate::{Error, Result};

/// One run of rows for [`MixtureBuilder::push`]: Gaussians of ascending ids with their kept
/// `(a_kj, codebook row)` pairs, as the device reduction's tiles carry them.
#[derive(Debug, Clone, Copy)]
pub struct RowRun<'a> {
    /// `[B]` source-`.ply` indices, strictly ascending and above every id pushed before.
    pub ids: &'a [u32],
    /// `[B]` centres, world frame, scene units.
    pub means: &'a [[f32; 3]],
    /// `[B + 1]` where each Gaussian's pairs start in `pairs` (0 first, `pairs.len()` last).
    pub starts: &'a [u32],
    /// `(a_kj, codebook row)` pairs, Gaussian after Gaussian, any order within one; zero `a`
    /// are dropped.
    pub pairs: &'a [(f32, u32)],
}

/// Builds a [`MixtureEmbeddings`] from runs of rows that arrive in ascending Gaussian order.
///
/// Each run is packed as it comes with the arithmetic of [`MixtureEmbeddings::from_sparse`]
/// (each row ordered by decreasing `a`, ties lower codebook row first, scaled by
/// `1 / ‖Σ_s a_s · E_s‖` over the f16 codebook in f64, rounded to f16), at `width` slots per
/// Gaussian; [`MixtureBuilder::finish`] then drops the codebook rows no atom uses (renumbering
/// the rest in their original order) and narrows the slots to the longest row. The result
/// equals `from_sparse` of all runs joined, bit for bit (the renumbering keeps the rows' order,
/// so ties break the same way).
///
/// Memory: the codebook as f16 (`[M, D]`) and the stored form at `width` slots; nothing per
/// entry besides.
#[derive(Debug)]
pub struct MixtureBuilder {
    dim: usize,
    model_id: String,
    /// `[M, D]` every codebook row, f16 (the values the file stores).
    book: Vec<f16>,
    /// Slots per Gaussian while building: the most pairs a row may hold.
    width: usize,
    gaussian_ids: Vec<u32>,
    means: Vec<[f32; 3]>,
    atoms: Vec<u32>,
    weights: Vec<f32>,
    /// The most non-zero pairs of any row pushed.
    longest: usize,
}

impl MixtureBuilder {
    /// A builder over `codebook` (`[M × D]` f32 row-major, the masks' embeddings `E_j`, rounded
    /// to f16 here) for rows of at most `width` pairs; room for `capacity` Gaussians is reserved
    /// (address space only, touched as runs arrive).
    ///
    /// Errors ([`Error::Invalid`]): `dim` 0 or not dividing the codebook's length, more rows
    /// than u32 ids hold, a non-finite codebook value, `width` 0.
    pub fn new(
        dim: usize,
        model_id: String,
        codebook: &[f32],
        width: usize,
        capacity: usize,
    ) -> Result<Self> {
        let bad = |m: String| Err(Error::Invalid(format!("mixture: {m}")));
        if dim == 0 || !codebook.len().is_multiple_of(dim) {
            return bad(format!("codebook of {} values for dim {dim}", codebook.len()));
        }
        let m = codebook.len() / dim;
        if m >= UNUSED as usize {
            return bad(format!("{m} codebook rows; at most {} fit u32 ids", UNUSED - 1));
        }
        if codebook.par_iter().any(|v| !v.is_finite()) {
            return bad("non-finite codebook value or weight".into());
        }
        if width == 0 {
            return bad("a row of 0 slots".into());
        }
        let mut book = vec![f16::ZERO; codebook.len()];
        book.par_chunks_mut(dim)
            .zip(codebook.par_chunks(dim))
            .for_each(|(h, f)| h.convert_from_f32_slice(f));
        Ok(MixtureBuilder {
            dim,
            model_id,
            book,
            width,
            gaussian_ids: Vec::with_capacity(capacity),
            means: Vec::with_capacity(capacity),
            atoms: Vec::with_capacity(capacity * width),
            weights: Vec::with_capacity(capacity * width),
            longest: 0,
        })
    }

    /// Gaussians pushed so far.
    pub fn len(&self) -> usize {
        self.gaussian_ids.len()
    }

    /// True before any Gaussian is pushed.
    pub fn is_empty(&self) -> bool {
        self.gaussian_ids.is_empty()
    }

    /// Checks `run` and packs its rows (in parallel, rayon). After an error the builder holds
    /// part of the run: drop it.
    ///
    /// Errors ([`Error::Invalid`]): lengths that disagree, ids not strictly ascending (within the
    /// run or after the runs before), a non-finite `a`, a codebook row out of range, a row of
    /// more non-zero pairs than `width`; then, as [`MixtureEmbeddings::from_sparse`], a repeated
    /// row, a weighted sum of zero or a weight beyond the f16 range, naming the first such
    /// Gaussian.
    pub fn push(&mut self, run: RowRun<'_>) -> Result<()> {
        let longest = self.check(run)?;
        let (n0, b, w) = (self.gaussian_ids.len(), run.ids.len(), self.width);
        self.gaussian_ids.extend_from_slice(run.ids);
        self.means.extend_from_slice(run.means);
        self.atoms.resize((n0 + b) * w, 0);
        self.weights.resize((n0 + b) * w, 0.0);
        let failed = pack_rows(
            &self.book,
            self.dim,
            run.ids,
            (&mut self.atoms[n0 * w..], &mut self.weights[n0 * w..]),
            |i, row| {
                let pairs = &run.pairs[run.starts[i] as usize..run.starts[i + 1] as usize];
                row.extend(
                    pairs
                        .iter()
                        .filter(|p| p.0 != 0.0)
                        .map(|&(a, atom)| (atom, f64::from(a))),
                );
            },
        );
        if let Some(m) = failed {
            return Err(Error::Invalid(format!("mixture: {m}")));
        }
        self.longest = self.longest.max(longest);
        Ok(())
    }

    /// The checks of [`MixtureBuilder::push`] before any row is packed; returns the run's
    /// longest row (non-zero pairs).
    fn check(&self, run: RowRun<'_>) -> Result<usize> {
        let bad = |m: String| Err(Error::Invalid(format!("mixture: {m}")));
        let (b, starts, pairs) = (run.ids.len(), run.starts, run.pairs);
        if run.means.len() != b
            || starts.len() != b + 1
            || starts.first() != Some(&0)
            || starts.last().map(|&s| s as usize) != Some(pairs.len())
            || starts.par_windows(2).any(|w| w[0] > w[1])
        {
            return bad(format!(
                "{b} ids, {} means, {} starts, {} pairs disagree",
                run.means.len(),
                starts.len(),
                pairs.len()
            ));
        }
        let after = self.gaussian_ids.last().copied();
        if run.ids.par_windows(2).any(|w| w[0] >= w[1])
            || matches!((after, run.ids.first()), (Some(a), Some(&f)) if f <= a)
        {
            return bad("Gaussian ids are not strictly ascending".into());
        }
        if pairs.par_iter().any(|p| !p.0.is_finite()) {
            return bad("non-finite codebook value or weight".into());
        }
        let m = self.book.len() / self.dim;
        if let Some(p) = pairs.par_iter().find_first(|p| p.1 as usize >= m) {
            return bad(format!("atom {} beyond the {m} codebook rows", p.1));
        }
        let longest = starts
            .par_windows(2)
            .map(|w| pairs[w[0] as usize..w[1] as usize].iter().filter(|p| p.0 != 0.0).count())
            .max()
            .unwrap_or(0);
        if longest > self.width {
            return bad(format!(
                "a row of {longest} pairs for {} slots per Gaussian",
                self.width
            ));
        }
        Ok(longest)
    }

    /// The stored form: the slots narrowed to the longest row (at least 1), the codebook rows
    /// no atom uses dropped and the rest renumbered in their original order, the codebook
    /// widened back to f32 (exact).
    pub fn finish(self) -> MixtureEmbeddings {
        let MixtureBuilder {
            dim,
            model_id,
            book,
            width,
            gaussian_ids,
            means,
            mut atoms,
            mut weights,
            longest,
        } = self;
        let keep = longest.max(1);
        if keep < width {
            // Every row fits its first `keep` slots (the rest are empty): moved down in place.
            for i in 0..gaussian_ids.len() {
                atoms.copy_within(i * width..i * width + keep, i * keep);
                weights.copy_within(i * width..i * width + keep, i * keep);
            }
            atoms.truncate(gaussian_ids.len() * keep);
            weights.truncate(gaussian_ids.len() * keep);
            atoms.shrink_to_fit();
            weights.shrink_to_fit();
        }
        let m = book.len() / dim;
        let used: Vec<AtomicBool> = (0..m).map(|_| AtomicBool::new(false)).collect();
        atoms.par_iter().filter(|&&a| a != UNUSED).for_each(|&a| {
            // Only the first sighting writes, so that workers seldom contend for a line.
            let u = &used[a as usize];
            if !u.load(Ordering::Relaxed) {
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
        atoms.par_iter_mut().for_each(|a| {
            if *a != UNUSED {
                *a = new_row[*a as usize];
            }
        });
        let mut used = vec![f16::ZERO; kept.len() * dim];
        used.par_chunks_mut(dim)
            .zip(kept.par_iter())
            .for_each(|(out, &r)| out.copy_from_slice(&book[r * dim..(r + 1) * dim]));
        drop(book);
        MixtureEmbeddings {
            dim,
            model_id,
            codebook: widened(&used, dim),
            gaussian_ids,
            means,
            keep,
            atoms,
            weights,
        }
    }
}
