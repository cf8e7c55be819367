//! The mixture's reduction folded on the host view by view ([`MixtureFold`]): each view's `a_kj`
//! are added to a running state per Gaussian as soon as every view before it is in, and then
//! freed, so that the host's memory does not grow with the views.
//!
//! The mixture needs, per Gaussian, only `Σ_i Σ_j a_kj` and its `keep` largest `(a_kj, atom)`:
//! each mask belongs to one view, so a pair's weight is final once its view is in. The state is
//! `N × (8 + 8·keep + 1)` bytes whatever the number of views, plus the codebook (`M × D` f32, the
//! views' mask embeddings) and the views that arrived before an earlier one (at most the views in
//! flight).

use std::borrow::Cow;
use std::collections::BTreeMap;

use rayon::prelude::*;
use slag_common::mixture::SparseMixture;
use slag_common::{Error, Result};

use super::top::replace_weakest;
use super::{MaskColumn, StoredImage};

/// Gaussians per parallel block of a fold (each block's state is one task's).
const BLOCK: usize = 1 << 16;

/// Most (mask, weight) pairs a fold keeps per Gaussian ([`MixtureFold::new`]): its pair counts
/// are bytes. A mixture of more pairs (up to every atom) is reduced from the kept views instead.
pub const MAX_FOLDED_KEEP: usize = u8::MAX as usize;

/// The host's streamed mixture reduction: views pushed in any order
/// ([`MixtureFold::push`]) are folded in view order, each Gaussian's terms added in the order
/// [`super::reduce_mixture_chunks`] adds them (views by index, entries in their order), so that
/// `Σ a_kj` has the same f64 bits and the kept pairs are the same pairs in the same slots.
///
/// Where it differs from [`super::reduce_mixture_chunks`]: that pass also sums `Σ a_kj·E_j` and
/// leaves a Gaussian unobserved when that sum's norm is at most `1e-9·Σ a_kj` (mask embeddings
/// that cancel out). The fold holds no such sum (that is its saving), so its rule is on `Σ a_kj`
/// alone: at least `min_total_weight`, positive and finite, as the device's streamed reduction.
/// CLIP embeddings of masks do not cancel in practice; the rule is documented in
/// docs/results/stability.md.
///
/// A fold may also cover a share of a scene's Gaussians ([`MixtureFold::counting`], the cluster
/// encode's partitions): its Gaussian ids are that share's own numbering, and it counts each
/// view's mask embeddings (the codebook's atom ids stay global) without keeping them. Since each
/// Gaussian's terms depend only on its own entries and on the views' mask counts, the shares'
/// rows are, bit for bit, the rows of one fold over the whole scene.
pub struct MixtureFold {
    dim: usize,
    keep: usize,
    min_total_weight: f64,
    /// `[N]` Σ a_kj in f64.
    den: Vec<f64>,
    /// `[N × keep]` kept `(a_kj, atom)` in push order; the first `n_kept[k]` of a row are used.
    kept: Vec<(f32, u32)>,
    /// `[N]` kept pairs used per Gaussian.
    n_kept: Vec<u8>,
    /// `[M × D]` every folded view's mask embeddings, in view order (empty when not kept).
    codebook: Vec<f32>,
    /// Whether the views' mask embeddings are kept ([`MixtureFold::new`]) or only counted
    /// ([`MixtureFold::counting`]).
    keeps_codebook: bool,
    /// Mask embeddings of the views folded so far (the next view's first atom id).
    atoms: usize,
    /// The next view to fold: every view below it is folded or never comes.
    next: usize,
    /// Views that arrived before `next` reached them, by view index, with their mask counts.
    pending: BTreeMap<usize, (StoredImage, usize)>,
    /// The most bytes `pending` held at once.
    peak_pending_bytes: usize,
    /// Views folded.
    folded: usize,
}

impl MixtureFold {
    /// An empty fold for `n_gaussians` Gaussians of `dim`-wide embeddings, keeping `keep`
    /// pairs per Gaussian; a Gaussian is observed when its `Σ a_kj` is at least
    /// `min_total_weight`, positive and finite.
    ///
    /// Errors: [`Error::Param`] `mixture_keep` for `keep` outside 1..=255.
    pub fn new(n_gaussians: usize, dim: usize, keep: usize, min_total_weight: f64) -> Result<Self> {
        Self::with_codebook(n_gaussians, dim, keep, min_total_weight, true)
    }

    /// As [`MixtureFold::new`], for a share of a scene's Gaussians numbered `0..n_gaussians` in
    /// the share, that counts the views' mask embeddings without keeping them: its views come
    /// with their mask counts ([`MixtureFold::push_counted`]), their embeddings may be left out,
    /// and [`MixtureFold::finish_rows`] gives an empty codebook.
    ///
    /// Errors: as [`MixtureFold::new`].
    pub fn counting(
        n_gaussians: usize,
        dim: usize,
        keep: usize,
        min_total_weight: f64,
    ) -> Result<Self> {
        Self::with_codebook(n_gaussians, dim, keep, min_total_weight, false)
    }

    fn with_codebook(
        n_gaussians: usize,
        dim: usize,
        keep: usize,
        min_total_weight: f64,
        keeps_codebook: bool,
    ) -> Result<Self> {
        if !(1..=MAX_FOLDED_KEEP).contains(&keep) {
            return Err(Error::param(
                "mixture_keep",
                keep,
                "1 to 255 mask embeddings kept per Gaussian",
            ));
        }
        Ok(MixtureFold {
            dim,
            keep,
            min_total_weight,
            den: vec![0.0; n_gaussians],
            kept: vec![(0.0, 0); n_gaussians * keep],
            n_kept: vec![0; n_gaussians],
            codebook: Vec::new(),
            keeps_codebook,
            atoms: 0,
            next: 0,
            pending: BTreeMap::new(),
            peak_pending_bytes: 0,
            folded: 0,
        })
    }

    /// Bytes of the running state per Gaussian with `keep` pairs (Σ a, the pairs, their count).
    pub fn state_bytes_per_gaussian(keep: usize) -> usize {
        8 + keep * std::mem::size_of::<(f32, u32)>() + 1
    }

    /// Adds view `view`'s `a_kj` (its index in the encode's view list, each view once): folded
    /// now when every view below it is in (with the views waiting behind it), else kept until
    /// they are.
    ///
    /// Errors: a view pushed twice or one already passed ([`Error::Internal`]); a contribution
    /// of another width than `dim` ([`Error::Mismatch`]); a Gaussian id past the scene or a mask
    /// past the view's embeddings ([`Error::Invalid`]); more than `u32::MAX - 1` mask
    /// embeddings in all ([`Error::Invalid`]).
    pub fn push(&mut self, view: usize, c: StoredImage) -> Result<()> {
        let masks = c.mask_embeddings.len() / self.dim.max(1);
        self.push_counted(view, c, masks)
    }

    /// As [`MixtureFold::push`], for a view of `masks` mask embeddings: `c` holds all of them,
    /// or none when the fold does not keep the codebook ([`MixtureFold::counting`]).
    ///
    /// Errors: as [`MixtureFold::push`]; [`Error::Invalid`] when `c` holds another number of
    /// mask embeddings (none is allowed only in a counting fold).
    pub fn push_counted(&mut self, view: usize, c: StoredImage, masks: usize) -> Result<()> {
        if view < self.next || self.pending.contains_key(&view) {
            return Err(Error::internal(format!(
                "view {view} reached the host's reduction twice"
            )));
        }
        check_width(&c, self.dim)?;
        let held = c.mask_embeddings.len();
        if held != masks * self.dim && (self.keeps_codebook || held != 0) {
            return Err(Error::Invalid(format!(
                "view {view} comes with {held} mask embedding values for {masks} masks of width {}",
                self.dim
            )));
        }
        self.pending.insert(view, (c, masks));
        let waiting: usize = self.pending.values().map(|(c, _)| c.bytes()).sum();
        self.peak_pending_bytes = self.peak_pending_bytes.max(waiting);
        while let Some((c, masks)) = self.pending.remove(&self.next) {
            self.fold(&c, masks)?;
            self.next += 1;
        }
        Ok(())
    }

    /// Folds view `view` now, by reference: for a caller that already holds the views in view
    /// order ([`super::DenseFold`], which keeps the view for its own sums), so that no view is
    /// copied or waits here. `view` must not come before the next view ([`Self::folded_views`];
    /// a later one means the views between never come, as at [`Self::finish_rows`]) and no
    /// view may be waiting.
    ///
    /// Errors: a view already passed, or views waiting ([`Error::Internal`]); as
    /// [`Self::push`] otherwise.
    pub(crate) fn fold_next(&mut self, view: usize, c: &StoredImage) -> Result<()> {
        if view < self.next || !self.pending.is_empty() {
            return Err(Error::internal(format!(
                "view {view} folded out of order: the mixture's fold expects view {}",
                self.next
            )));
        }
        check_width(c, self.dim)?;
        self.fold(c, c.mask_embeddings.len() / self.dim.max(1))?;
        self.next = view + 1;
        Ok(())
    }

    /// Views folded so far (all below this index): a checkpoint of the fold covers them.
    pub fn folded_views(&self) -> usize {
        self.next
    }

    /// The running state of a fold with no view waiting, to write as a checkpoint: it covers
    /// views `0..next` ([`MixtureFold::folded_views`]). The arrays are borrowed.
    ///
    /// Errors: [`Error::Internal`] while a view waits for an earlier one (its state would be
    /// lost: push views in view order before taking the state).
    pub fn state(&self) -> Result<FoldState<'_>> {
        if !self.pending.is_empty() {
            return Err(Error::internal(format!(
                "the fold's state was taken with {} views waiting for view {}",
                self.pending.len(),
                self.next
            )));
        }
        Ok(FoldState {
            dim: self.dim,
            keep: self.keep,
            min_total_weight: self.min_total_weight,
            keeps_codebook: self.keeps_codebook,
            atoms: self.atoms,
            next: self.next,
            den: Cow::Borrowed(&self.den),
            kept: Cow::Borrowed(&self.kept),
            n_kept: Cow::Borrowed(&self.n_kept),
            codebook: Cow::Borrowed(&self.codebook),
        })
    }

    /// The fold [`MixtureFold::state`] took, views `0..state.next` folded: pushing views
    /// `state.next..` then gives the rows of one fold of every view, bit for bit.
    ///
    /// Errors: [`Error::Param`] `mixture_keep` as [`MixtureFold::new`]; [`Error::Invalid`] for
    /// arrays of other lengths than `N`, `N × keep`, `atoms × dim` (none without the codebook),
    /// a row using more than `keep` pairs.
    pub fn from_state(state: FoldState<'_>) -> Result<Self> {
        let n = state.den.len();
        let mut fold = Self::with_codebook(
            n,
            state.dim,
            state.keep,
            state.min_total_weight,
            state.keeps_codebook,
        )?;
        let codebook_len = if state.keeps_codebook {
            state.atoms.checked_mul(state.dim)
        } else {
            Some(0)
        };
        if state.kept.len() != n * state.keep
            || state.n_kept.len() != n
            || Some(state.codebook.len()) != codebook_len
            || state.n_kept.iter().any(|&u| u as usize > state.keep)
        {
            return Err(Error::Invalid(format!(
                "a fold's state of {n} Gaussians, {} pairs, {} counts and {} codebook values \
                 for {} kept pairs and {} mask embeddings of width {}",
                state.kept.len(),
                state.n_kept.len(),
                state.codebook.len(),
                state.keep,
                state.atoms,
                state.dim
            )));
        }
        fold.den = state.den.into_owned();
        fold.kept = state.kept.into_owned();
        fold.n_kept = state.n_kept.into_owned();
        fold.codebook = state.codebook.into_owned();
        (fold.atoms, fold.next, fold.folded) = (state.atoms, state.next, state.next);
        Ok(fold)
    }

    /// Views pushed so far.
    pub fn len(&self) -> usize {
        self.folded + self.pending.len()
    }

    /// True before the first view.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The most bytes of views waiting for an earlier one, so far.
    pub fn peak_pending_bytes(&self) -> usize {
        self.peak_pending_bytes
    }

    /// Bytes of the running state (Σ a, the kept pairs, the codebook so far).
    pub fn state_bytes(&self) -> usize {
        self.den.len() * Self::state_bytes_per_gaussian(self.keep) + self.codebook.len() * 4
    }

    /// One view's entries (of its `masks` masks) into the state, its mask embeddings appended to
    /// the codebook when the fold keeps it.
    fn fold(&mut self, c: &StoredImage, masks: usize) -> Result<()> {
        check_view(c, self.dim, masks, self.den.len())?;
        let base = self.atoms;
        if base + masks >= u32::MAX as usize {
            return Err(Error::Invalid(format!(
                "more than {} mask embeddings in all: too many for u32 codebook ids",
                u32::MAX - 1
            )));
        }
        if self.keeps_codebook {
            self.codebook.extend_from_slice(&c.mask_embeddings);
        }
        self.atoms += masks;
        let (keep, base) = (self.keep, base as u32);
        self.den
            .par_chunks_mut(BLOCK)
            .zip(self.kept.par_chunks_mut(BLOCK * keep))
            .zip(self.n_kept.par_chunks_mut(BLOCK))
            .enumerate()
            .for_each(|(b, ((den, kept), n_kept))| {
                let g0 = (b * BLOCK) as u32;
                let lo = c.gaussians.partition_point(|&g| g < g0);
                let hi = lo + c.gaussians[lo..].partition_point(|&g| g < g0 + den.len() as u32);
                let block = Block {
                    g0,
                    keep,
                    den,
                    kept,
                    n_kept,
                };
                match &c.masks {
                    MaskColumn::U8(m) => block.add(c, &m[lo..hi], lo, base),
                    MaskColumn::U16(m) => block.add(c, &m[lo..hi], lo, base),
                    MaskColumn::U32(m) => block.add(c, &m[lo..hi], lo, base),
                }
            });
        self.folded += 1;
        Ok(())
    }

    /// The mixture's sparse parts: every view still waiting folded (in view order), then the
    /// observed Gaussians in id order with their kept pairs and `means` (`[N]`, world frame),
    /// the codebook in view order. The same parts as [`super::reduce_mixture_chunks`] on the
    /// same views, up to the observed rule ([`MixtureFold`]).
    ///
    /// Errors: as [`Self::push`]; [`Error::Internal`] when `means` is not `[N]`.
    pub fn finish(self, means: &[[f32; 3]], model_id: &str) -> Result<SparseMixture> {
        if means.len() != self.den.len() {
            return Err(Error::internal(format!(
                "the host's fold: {} means for {} Gaussians",
                means.len(),
                self.den.len()
            )));
        }
        let mut parts = self.finish_rows()?;
        parts.model_id = model_id.to_string();
        parts.means = parts
            .gaussian_ids
            .iter()
            .map(|&k| means[k as usize])
            .collect();
        Ok(parts)
    }

    /// The fold's rows: every view still waiting folded (in view order), then the observed
    /// Gaussians in id order (the fold's own numbering) with their kept pairs, and the codebook
    /// (empty for a [`MixtureFold::counting`] fold). `means` and `model_id` are left empty.
    ///
    /// Errors: as [`Self::push`].
    pub fn finish_rows(mut self) -> Result<SparseMixture> {
        for (_, (c, masks)) in std::mem::take(&mut self.pending) {
            self.fold(&c, masks)?;
        }
        let min = self.min_total_weight;
        let mut parts = SparseMixture {
            dim: self.dim,
            offsets: vec![0],
            ..Default::default()
        };
        for (k, &d) in self.den.iter().enumerate() {
            if d.is_nan() || d < min || d <= 0.0 || !d.is_finite() {
                continue;
            }
            parts.gaussian_ids.push(k as u32);
            let row = &self.kept[k * self.keep..k * self.keep + self.n_kept[k] as usize];
            for &(a, atom) in row {
                parts.atoms.push(atom);
                parts.weights.push(a);
            }
            parts.offsets.push(parts.atoms.len());
        }
        parts.codebook = std::mem::take(&mut self.codebook);
        Ok(parts)
    }
}

/// The running state of a [`MixtureFold`] with no view waiting ([`MixtureFold::state`],
/// [`MixtureFold::from_state`]): what a checkpoint of the fold holds. `N` is the fold's
/// Gaussians.
#[derive(Debug, Clone, PartialEq)]
pub struct FoldState<'a> {
    /// Embedding width D.
    pub dim: usize,
    /// Pairs kept per Gaussian.
    pub keep: usize,
    /// The observed rule's floor on `Σ a_kj`.
    pub min_total_weight: f64,
    /// Whether the fold keeps the views' mask embeddings (else it counts them).
    pub keeps_codebook: bool,
    /// Mask embeddings of the folded views (the next view's first atom id).
    pub atoms: usize,
    /// Views folded: `0..next`.
    pub next: usize,
    /// `[N]` Σ a_kj in f64.
    pub den: Cow<'a, [f64]>,
    /// `[N × keep]` kept `(a_kj, atom)`; the first `n_kept[k]` of row `k` are used.
    pub kept: Cow<'a, [(f32, u32)]>,
    /// `[N]` kept pairs used per Gaussian (at most `keep`).
    pub n_kept: Cow<'a, [u8]>,
    /// `[atoms × dim]` the folded views' mask embeddings in view order; empty when the fold only
    /// counts them.
    pub codebook: Cow<'a, [f32]>,
}

/// Refuses a view a fold cannot add (this one's, and [`super::DenseFold`]'s): embeddings of
/// another width than `dim` ([`Error::Mismatch`]), a Gaussian id at or past `n_gaussians`, a
/// mask past the view's `masks` masks ([`Error::Invalid`]).
pub(super) fn check_view(
    c: &StoredImage,
    dim: usize,
    masks: usize,
    n_gaussians: usize,
) -> Result<()> {
    check_width(c, dim)?;
    if let Some(&g) = c.gaussians.last()
        && g as usize >= n_gaussians
    {
        return Err(Error::Invalid(format!(
            "a view names Gaussian {g} of a scene of {n_gaussians}"
        )));
    }
    let most = match &c.masks {
        MaskColumn::U8(m) => m.iter().max().map(|&v| v as usize),
        MaskColumn::U16(m) => m.iter().max().map(|&v| v as usize),
        MaskColumn::U32(m) => m.iter().max().map(|&v| v as usize),
    };
    if most.is_some_and(|j| j >= masks) {
        return Err(Error::Invalid(format!(
            "a view names mask {} of its {masks}",
            most.unwrap_or(0)
        )));
    }
    Ok(())
}

/// Refuses a view whose mask embeddings are not `dim` wide ([`Error::Mismatch`]).
fn check_width(c: &StoredImage, dim: usize) -> Result<()> {
    if c.dim != dim || !c.mask_embeddings.len().is_multiple_of(dim.max(1)) {
        return Err(Error::mismatch(
            slag_common::Mismatched::EmbeddingWidth,
            format!(
                "a view's mask embeddings are {} wide, the reduction's {dim}: one CLIP model \
                 per encode",
                c.dim
            ),
        ));
    }
    Ok(())
}

/// One parallel block of Gaussians `g0..g0 + den.len()`: its slices of the state.
struct Block<'a> {
    g0: u32,
    keep: usize,
    den: &'a mut [f64],
    kept: &'a mut [(f32, u32)],
    n_kept: &'a mut [u8],
}

impl Block<'_> {
    /// Adds the view's entries `lo..lo + masks.len()` (those of this block, `masks` their mask
    /// indices) in entry order: `Σ a += a` in f64, and the pair `(a, base + mask)` offered to the
    /// Gaussian's kept pairs by the rule the mixture keeps them by ([`super::top`]).
    fn add<M: Copy + Into<u32>>(mut self, c: &StoredImage, masks: &[M], lo: usize, base: u32) {
        let n = masks.len();
        let ids = &c.gaussians[lo..lo + n];
        let weights = &c.weights[lo..lo + n];
        for ((&g, &mask), &a) in ids.iter().zip(masks).zip(weights) {
            let r = (g - self.g0) as usize;
            self.den[r] += a as f64;
            let atom = base + mask.into();
            self.push_top(r, a, atom);
        }
    }

    /// The kept pairs of row `r`: filled in arrival order, then the weakest (least `a`; of equal
    /// `a`, the larger atom) replaced by a stronger pair. Atoms arrive in increasing order, so an
    /// equal `a` never displaces a kept one.
    fn push_top(&mut self, r: usize, a: f32, atom: u32) {
        let keep = self.keep;
        let used = self.n_kept[r] as usize;
        let row = &mut self.kept[r * keep..(r + 1) * keep];
        if used < keep {
            row[used] = (a, atom);
            self.n_kept[r] += 1;
            return;
        }
        replace_weakest(row, a, atom);
    }
}
