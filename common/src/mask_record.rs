//! The masks' record (`mask-record.safetensors`, beside `embeddings.safetensors`): for each
//! Gaussian of the source `.ply`, the mask that held most of its blend weight in each of its
//! [`MaskRecord::slots`] best-seen views. The segmentation (`slag_encoder::segments`) reads it to
//! weigh the edges of its neighbour graph by multi-view mask co-membership; `encode` keeps it so
//! that `slag-encoder segment` can redo the segments of an existing encode without its masks.
//!
//! A *view's dominant mask* for Gaussian `k` is `argmax_j a_kj` over the view's masks (ties to
//! the smaller mask index), `a_kj = Σ_{p∈M_j} w_kp` the blend weight it received inside mask `j`
//! (pixels at the raster resolution). The record keeps, per Gaussian, the `slots` views with
//! the largest such `a_kj`, ties to the smaller view index: a top-`slots` of a fixed set, so the
//! record does not depend on the order in which views arrive (nor on the thread count).
//!
//! Tensors (`N` Gaussians, `S` slots; slot order: `a_kj` descending, then view ascending; unused
//! slots last):
//! - `views` U16 `[N, S]` — view index in the encode's view list, [`EMPTY_VIEW`] when unused;
//! - `masks` U16 `[N, S]` — the dominant mask's index within that view's masks;
//! - `weights` F32 `[N, S]` — its `a_kj` (raster pixels), 0 when unused.
//!
//! 8 bytes per slot: 64 bytes per Gaussian with the default 8 slots (128 MB at 2M Gaussians, in
//! memory while the encode runs and on disk). Views beyond index 65,534 and masks beyond index
//! 65,535 of one view are not recorded (such an encode's record is partial; the segmentation
//! treats the missing views as unseen).
//!
//! Metadata: `format = "slag-mask-record"`, `version = "1"`, `scene_gaussians` (N), `slots` (S),
//! `views` (the encode's view count).

use std::path::Path;

use safetensors::tensor::Dtype;

use crate::safetensors_io::{self, FileKind, le_f32, tensor};
use crate::{Error, Result};

/// Format identifier stored in the metadata.
pub const FORMAT: &str = "slag-mask-record";
/// Current format version.
pub const VERSION: &str = "1";
/// File name the encoder writes beside `embeddings.safetensors`.
pub const FILE_NAME: &str = "mask-record.safetensors";
/// View index of an unused slot.
pub const EMPTY_VIEW: u16 = u16::MAX;
/// Slots per Gaussian that `encode` keeps.
pub const DEFAULT_SLOTS: usize = 8;

const KIND: FileKind = FileKind {
    format: FORMAT,
    version: VERSION,
    noun: "mask record",
    file_name: FILE_NAME,
    rewrite_with: "slag-encoder encode (it writes the record beside the embeddings)",
};

/// One recorded view of a Gaussian: the view, its dominant mask there, and that mask's `a_kj`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MaskSlot {
    /// View index in the encode's view list.
    pub view: u16,
    /// Dominant mask's index within the view's masks.
    pub mask: u16,
    /// Its `a_kj`, raster pixels.
    pub weight: f32,
}

/// Every Gaussian's dominant mask in its best-seen views (module doc).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct MaskRecord {
    /// Slots per Gaussian, S.
    pub slots: usize,
    /// Views of the encode.
    pub view_count: usize,
    /// `[N * S]` view per slot ([`EMPTY_VIEW`] when unused).
    pub views: Vec<u16>,
    /// `[N * S]` dominant mask per slot.
    pub masks: Vec<u16>,
    /// `[N * S]` its `a_kj`; 0 when unused.
    pub weights: Vec<f32>,
}

impl MaskRecord {
    /// An empty record of `gaussians` Gaussians with `slots` slots each, for an encode of
    /// `view_count` views.
    ///
    /// Errors: [`Error::Param`] `slots` outside 1..=64.
    pub fn new(gaussians: usize, slots: usize, view_count: usize) -> Result<Self> {
        if !(1..=64).contains(&slots) {
            return Err(Error::param("slots", slots, "1 to 64 views per Gaussian"));
        }
        Ok(MaskRecord {
            slots,
            view_count,
            views: vec![EMPTY_VIEW; gaussians * slots],
            masks: vec![0; gaussians * slots],
            weights: vec![0.0; gaussians * slots],
        })
    }

    /// Gaussians N.
    pub fn len(&self) -> usize {
        self.views.len().checked_div(self.slots).unwrap_or(0)
    }

    /// True for a record of no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes held per Gaussian (8 per slot).
    pub fn bytes_per_gaussian(&self) -> usize {
        self.slots * 8
    }

    /// The used slots of Gaussian `k` (`a_kj` descending); empty beyond the scene.
    pub fn of(&self, k: usize) -> impl Iterator<Item = MaskSlot> + '_ {
        let s = self.slots;
        let range = if k < self.len() {
            k * s..(k + 1) * s
        } else {
            0..0
        };
        range
            .filter(|&i| self.views[i] != EMPTY_VIEW)
            .map(|i| MaskSlot {
                view: self.views[i],
                mask: self.masks[i],
                weight: self.weights[i],
            })
    }

    /// Adds one view's `a_kj`: `entries` are `(gaussian, mask, a_kj)` sorted by Gaussian (any
    /// mask order). Each Gaussian's dominant mask (largest `a_kj`, ties to the smaller mask)
    /// enters its slots when it beats the weakest (module doc for the order). Views beyond
    /// index 65,534, masks beyond 65,535, Gaussians beyond N and non-positive or non-finite
    /// weights are skipped.
    pub fn add_view(&mut self, view: usize, entries: impl IntoIterator<Item = (u32, u32, f32)>) {
        let Ok(view) = u16::try_from(view) else {
            return;
        };
        if view == EMPTY_VIEW {
            return;
        }
        let mut current: Option<(u32, u32, f32)> = None;
        for (g, m, w) in entries {
            if !(w.is_finite() && w > 0.0) {
                continue;
            }
            match current {
                Some((cg, cm, cw)) if cg == g => {
                    if w > cw || (w == cw && m < cm) {
                        current = Some((g, m, w));
                    }
                }
                Some(done) => {
                    self.insert(view, done);
                    current = Some((g, m, w));
                }
                None => current = Some((g, m, w)),
            }
        }
        if let Some(done) = current {
            self.insert(view, done);
        }
    }

    fn insert(&mut self, view: u16, (g, m, w): (u32, u32, f32)) {
        let (Ok(mask), true) = (u16::try_from(m), (g as usize) < self.len()) else {
            return;
        };
        let s = self.slots;
        let at = g as usize * s..(g as usize + 1) * s;
        insert_slot(
            &mut self.views[at.clone()],
            &mut self.masks[at.clone()],
            &mut self.weights[at],
            MaskSlot {
                view,
                mask,
                weight: w,
            },
        );
    }

    /// Adds the views of `other`, a record of the same Gaussians and slots whose views this one
    /// does not hold (another GPU's views of the same encode): the result is the record of all
    /// views together, whatever the order of the merge (the slots keep the module doc's order).
    ///
    /// Errors: [`Error::Internal`] for records of other Gaussian counts or slots.
    pub fn merge(&mut self, other: &MaskRecord) -> Result<()> {
        use rayon::prelude::*;
        if other.slots != self.slots || other.len() != self.len() {
            return Err(Error::internal(format!(
                "merging a mask record of {} Gaussians × {} slots into one of {} × {}",
                other.len(),
                other.slots,
                self.len(),
                self.slots
            )));
        }
        let s = self.slots;
        self.views
            .par_chunks_mut(s)
            .zip(self.masks.par_chunks_mut(s))
            .zip(self.weights.par_chunks_mut(s))
            .enumerate()
            .for_each(|(k, ((views, masks), weights))| {
                for slot in other.of(k) {
                    insert_slot(views, masks, weights, slot);
                }
            });
        self.view_count = self.view_count.max(other.view_count);
        Ok(())
    }

    /// Multi-view mask co-membership of Gaussians `i` and `j`: over the views both record, the
    /// share of evidence for *different* dominant masks, each shared view counting
    /// `min(a_i, a_j)`. `None` when they record no common view.
    pub fn disagreement(&self, i: usize, j: usize) -> Option<f32> {
        Self::disagreement_between((self, i), (self, j))
    }

    /// [`MaskRecord::disagreement`] of row `a.1` of record `a.0` and row `b.1` of record `b.0`
    /// (two records of the same slot count, e.g. a scene's and a gathered part of it,
    /// [`MaskRecord::gather`]): the same value, bit for bit, as the one of the two Gaussians
    /// in the scene's record. `None` when they record no common view, a row lies beyond its
    /// record or the slot counts differ.
    pub fn disagreement_between(a: (&MaskRecord, usize), b: (&MaskRecord, usize)) -> Option<f32> {
        let ((ra, i), (rb, j)) = (a, b);
        if rb.slots != ra.slots {
            return None;
        }
        let (a, b) = (ra.row(i)?, rb.row(j)?);
        disagreement_of(ra.slots_at(a), rb.slots_at(b))
    }

    /// The slots at `at`, one row's range ([`MaskRecord::row`]).
    fn slots_at(&self, at: std::ops::Range<usize>) -> Slots<'_> {
        Slots {
            views: &self.views[at.clone()],
            masks: &self.masks[at.clone()],
            weights: &self.weights[at],
        }
    }

    /// Asks the CPU to bring Gaussian `k`'s row (its views, masks and weights) into its cache
    /// ahead of a [`MaskRecord::disagreement`] that reads it: a hint that changes no result. A
    /// pass over edges reads rows at random places of a large record, each read a cache miss;
    /// prefetching the rows of an edge some edges ahead overlaps those misses
    /// ([`crate::cache::prefetch`]). No-op beyond the record.
    #[inline(always)]
    pub fn prefetch(&self, k: usize) {
        if let Some(at) = self.row(k) {
            crate::cache::prefetch(&self.views[at.start]);
            crate::cache::prefetch(&self.masks[at.start]);
            crate::cache::prefetch(&self.weights[at.start]);
        }
    }

    /// The slot range of row `k` in the `[N * S]` arrays; `None` beyond the record.
    fn row(&self, k: usize) -> Option<std::ops::Range<usize>> {
        let start = k.checked_mul(self.slots)?;
        let end = start.checked_add(self.slots)?;
        (self.slots > 0 && end <= self.views.len()).then_some(start..end)
    }

    /// The rows `rows` of this record, in that order, as a record of their own (`rows.len()`
    /// Gaussians, the same slots and view count), gathered in parallel: a part of the scene
    /// laid out so that rows read together sit together in memory. Rows beyond the record
    /// come out empty.
    pub fn gather(&self, rows: &[u32]) -> MaskRecord {
        use rayon::prelude::*;
        let s = self.slots.max(1);
        let mut out = MaskRecord {
            slots: self.slots,
            view_count: self.view_count,
            views: vec![EMPTY_VIEW; rows.len() * self.slots],
            masks: vec![0; rows.len() * self.slots],
            weights: vec![0.0; rows.len() * self.slots],
        };
        let n = self.len();
        out.views
            .par_chunks_mut(s)
            .zip(out.masks.par_chunks_mut(s))
            .zip(out.weights.par_chunks_mut(s))
            .zip(rows.par_iter())
            .filter(|(_, k)| (**k as usize) < n)
            .for_each(|(((views, masks), weights), &k)| {
                let at = k as usize * s;
                views.copy_from_slice(&self.views[at..at + s]);
                masks.copy_from_slice(&self.masks[at..at + s]);
                weights.copy_from_slice(&self.weights[at..at + s]);
            });
        out
    }

    /// The rows `rows` of this record, in that order, each packed into one [`PackedRow`] (a
    /// 64-byte line: an edge's far end is one cache line instead of three), gathered in
    /// parallel; `None` unless the record has [`DEFAULT_SLOTS`] slots. Rows beyond the record
    /// come out empty. [`PackedRow::disagreement`] gives the same values as
    /// [`MaskRecord::disagreement`], bit for bit.
    pub fn gather_packed(&self, rows: &[u32]) -> Option<Vec<PackedRow>> {
        use rayon::prelude::*;
        if self.slots != DEFAULT_SLOTS {
            return None;
        }
        let packed = rows
            .par_iter()
            .map(|&k| {
                let Some(at) = self.row(k as usize) else {
                    return PackedRow::EMPTY;
                };
                let mut row = PackedRow::EMPTY;
                row.views.copy_from_slice(&self.views[at.clone()]);
                row.masks.copy_from_slice(&self.masks[at.clone()]);
                row.weights.copy_from_slice(&self.weights[at]);
                row
            })
            .collect();
        Some(packed)
    }

    /// Writes the file atomically (`<path>.partial`, fsync, rename).
    ///
    /// Errors: arrays whose lengths disagree ([`Error::Internal`]); I/O.
    pub fn write(&self, path: &Path) -> Result<()> {
        let n = self.len();
        if self.masks.len() != self.views.len()
            || self.weights.len() != self.views.len()
            || self.views.len() != n * self.slots
        {
            return Err(Error::internal("mask record arrays of different lengths"));
        }
        let shape = vec![n, self.slots];
        let tensors = vec![
            tensor("views", shape.clone(), &self.views),
            tensor("masks", shape.clone(), &self.masks),
            tensor("weights", shape, &self.weights),
        ];
        let meta = [
            ("scene_gaussians", n.to_string()),
            ("slots", self.slots.to_string()),
            ("views", self.view_count.to_string()),
        ];
        safetensors_io::write(path, &KIND, tensors, &meta)
    }

    /// Reads a file written by [`MaskRecord::write`].
    ///
    /// Errors ([`Error::Format`] naming the file): not safetensors, another format or version,
    /// tensors missing or of other shapes; I/O.
    pub fn read(path: &Path) -> Result<MaskRecord> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let file = safetensors_io::open(path, &bytes, &KIND)?;
        let v = file.tensor_of(path, "views", Dtype::U16)?;
        let m = file.tensor_of(path, "masks", Dtype::U16)?;
        let w = file.tensor_of(path, "weights", Dtype::F32)?;
        let shape = v.shape().to_vec();
        if shape.len() != 2 || m.shape() != shape || w.shape() != shape || shape[1] == 0 {
            return Err(Error::format(
                path,
                format!(
                    "views {:?}, masks {:?}, weights {:?}: expected three [N, S] tensors",
                    v.shape(),
                    m.shape(),
                    w.shape()
                ),
            ));
        }
        let u16s = |b: &[u8]| -> Vec<u16> {
            b.chunks_exact(2)
                .map(|c| u16::from_le_bytes([c[0], c[1]]))
                .collect()
        };
        Ok(MaskRecord {
            slots: shape[1],
            view_count: file
                .meta
                .get("views")
                .and_then(|s| s.parse().ok())
                .unwrap_or(0),
            views: u16s(v.data()),
            masks: u16s(m.data()),
            weights: le_f32(w.data()),
        })
    }
}

/// One Gaussian's [`DEFAULT_SLOTS`] slots of the record side by side in one 64-byte line (the
/// module doc's slot order): what [`MaskRecord::gather_packed`] lays out for the segments'
/// edges, which read one such line at each end.
#[derive(Debug, Clone, Copy, PartialEq)]
#[repr(C, align(64))]
pub struct PackedRow {
    /// View per slot ([`EMPTY_VIEW`] when unused).
    pub views: [u16; DEFAULT_SLOTS],
    /// Dominant mask per slot.
    pub masks: [u16; DEFAULT_SLOTS],
    /// Its `a_kj` (raster pixels); 0 when unused.
    pub weights: [f32; DEFAULT_SLOTS],
}

impl PackedRow {
    /// A row with no recorded view.
    pub const EMPTY: PackedRow = PackedRow {
        views: [EMPTY_VIEW; DEFAULT_SLOTS],
        masks: [0; DEFAULT_SLOTS],
        weights: [0.0; DEFAULT_SLOTS],
    };

    /// [`MaskRecord::disagreement`] of this row's Gaussian and `other`'s, bit for bit.
    pub fn disagreement(&self, other: &PackedRow) -> Option<f32> {
        disagreement_of(self.slots(), other.slots())
    }

    fn slots(&self) -> Slots<'_> {
        Slots {
            views: &self.views,
            masks: &self.masks,
            weights: &self.weights,
        }
    }
}

/// One Gaussian's slots, wherever they are stored.
#[derive(Clone, Copy)]
struct Slots<'a> {
    views: &'a [u16],
    masks: &'a [u16],
    weights: &'a [f32],
}

/// [`MaskRecord::disagreement`] of the Gaussians with the slots `a` and `b`: over `a`'s used
/// slots in their order, each against the first slot of `b` with the same view.
#[inline(always)]
fn disagreement_of(a: Slots, b: Slots) -> Option<f32> {
    let (mut agree, mut differ) = (0.0f32, 0.0f32);
    for (x, &view) in a.views.iter().enumerate() {
        if view == EMPTY_VIEW {
            continue;
        }
        if let Some(y) = first_slot_of(b.views, view) {
            let w = a.weights[x].min(b.weights[y]);
            if a.masks[x] == b.masks[y] {
                agree += w;
            } else {
                differ += w;
            }
        }
    }
    let total = agree + differ;
    (total > 0.0 && total.is_finite()).then(|| differ / total)
}

/// The first of `views` (one Gaussian's slots) equal to `view`. The edges' hot loop: with the
/// default 8 slots the comparisons run side by side (no early exit), so that the compiler
/// turns them into one vector compare.
#[inline(always)]
fn first_slot_of(views: &[u16], view: u16) -> Option<usize> {
    if let Ok(row) = <&[u16; DEFAULT_SLOTS]>::try_from(views) {
        let hits = row
            .iter()
            .enumerate()
            .fold(0u32, |acc, (y, &v)| acc | (u32::from(v == view) << y));
        return (hits != 0).then(|| hits.trailing_zeros() as usize);
    }
    views.iter().position(|&v| v == view)
}

/// Enters `slot` into one Gaussian's slots (`views`, `masks`, `weights`, each `[S]`) when it
/// beats the weakest; slots stay in the module doc's order (`a_kj` descending, then view
/// ascending, unused last).
fn insert_slot(views: &mut [u16], masks: &mut [u16], weights: &mut [f32], slot: MaskSlot) {
    let better = |i: usize| -> bool {
        let (v, wi) = (views[i], weights[i]);
        v == EMPTY_VIEW || slot.weight > wi || (slot.weight == wi && slot.view < v)
    };
    let Some(pos) = (0..views.len()).find(|&i| better(i)) else {
        return;
    };
    views[pos..].rotate_right(1);
    masks[pos..].rotate_right(1);
    weights[pos..].rotate_right(1);
    views[pos] = slot.view;
    masks[pos] = slot.mask;
    weights[pos] = slot.weight;
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn keeps_the_dominant_mask_of_the_best_views_in_any_arrival_order() {
        // Gaussian 0 seen in 4 views with 2 slots; view 2 and view 0 weigh most.
        let views = [
            (0usize, vec![(0u32, 3u32, 5.0f32), (0, 4, 7.0), (1, 1, 1.0)]),
            (1, vec![(0, 0, 2.0), (1, 2, 3.0)]),
            (2, vec![(0, 9, 9.0), (0, 1, 9.0)]),
            (3, vec![(0, 5, 7.0)]),
        ];
        let mut a = MaskRecord::new(2, 2, 4).unwrap();
        let mut b = MaskRecord::new(2, 2, 4).unwrap();
        for (v, e) in &views {
            a.add_view(*v, e.iter().copied());
        }
        for (v, e) in views.iter().rev() {
            b.add_view(*v, e.iter().copied());
        }
        assert_eq!(a, b);
        let g0: Vec<MaskSlot> = a.of(0).collect();
        // View 2: masks 1 and 9 tie at 9.0 → mask 1; views 0 and 3 tie at 7.0 → view 0.
        assert_eq!(
            g0,
            vec![
                MaskSlot {
                    view: 2,
                    mask: 1,
                    weight: 9.0
                },
                MaskSlot {
                    view: 0,
                    mask: 4,
                    weight: 7.0
                }
            ]
        );
        assert_eq!(a.of(1).count(), 2);
        assert_eq!(a.of(7).count(), 0);
        // Gaussians 0 and 1 share view 0 (masks 4 vs 1: differ) only.
        assert_eq!(a.disagreement(0, 1), Some(1.0));
        assert_eq!(a.bytes_per_gaussian(), 16);
    }

    #[test]
    fn gathered_rows_give_the_scene_record_disagreements() {
        // 30 Gaussians in 9 views with 6 slots, shared views with equal and different masks.
        let mut r = MaskRecord::new(30, 6, 9).unwrap();
        for v in 0..9u32 {
            let entries = (0..30u32).filter(|g| (g + v) % 4 != 0).map(|g| {
                (
                    g,
                    (g / 3 + v * (g % 2)) % 4,
                    ((g * 7 + v * 5) % 9 + 1) as f32,
                )
            });
            r.add_view(v as usize, entries);
        }
        let rows: Vec<u32> = vec![17, 3, 29, 4, 0, 12, 30];
        let part = r.gather(&rows);
        assert_eq!((part.len(), part.slots, part.view_count), (7, 6, 9));
        assert_eq!(part.of(6).count(), 0, "a row beyond the record is empty");
        let mut shared = 0;
        for (a, &i) in rows.iter().enumerate().take(6) {
            assert!(part.of(a).eq(r.of(i as usize)));
            for j in 0..30 {
                let want = r.disagreement(i as usize, j);
                shared += usize::from(want.is_some_and(|m| m > 0.0 && m < 1.0));
                let got = MaskRecord::disagreement_between((&part, a), (&r, j));
                assert_eq!(
                    got.map(f32::to_bits),
                    want.map(f32::to_bits),
                    "rows {i}, {j}"
                );
                let back = MaskRecord::disagreement_between((&r, j), (&part, a));
                assert_eq!(
                    back.map(f32::to_bits),
                    r.disagreement(j, i as usize).map(f32::to_bits)
                );
            }
        }
        assert!(
            shared > 10,
            "the pairs must mix agreeing and differing views: {shared}"
        );
        assert_eq!(MaskRecord::disagreement_between((&part, 0), (&r, 30)), None);
        let other = MaskRecord::new(30, 2, 9).unwrap();
        assert_eq!(MaskRecord::disagreement_between((&r, 0), (&other, 0)), None);
    }

    /// The definition, slot by slot: each view of `i` (in its slot order) against the first
    /// slot of `j` with that view.
    fn disagreement_by_definition(r: &MaskRecord, i: usize, j: usize) -> Option<f32> {
        let (mut agree, mut differ) = (0.0f32, 0.0f32);
        for a in r.of(i) {
            let Some(b) = r.of(j).find(|b| b.view == a.view) else {
                continue;
            };
            let sum = if a.mask == b.mask {
                &mut agree
            } else {
                &mut differ
            };
            *sum += a.weight.min(b.weight);
        }
        let total = agree + differ;
        (total > 0.0 && total.is_finite()).then(|| differ / total)
    }

    #[test]
    fn disagreements_follow_the_definition_bit_for_bit_at_any_slot_count() {
        // A fixed xorshift stream: the same rows every run.
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 32) as u32
        };
        // The default 8 slots (the vector compare) and others; rows filled directly so that
        // they hold what a file may hold: unused slots anywhere, a view twice.
        for slots in [DEFAULT_SLOTS, 3, 9] {
            let n = 40;
            let mut r = MaskRecord::new(n, slots, 6).unwrap();
            for x in 0..n * slots {
                let v = next();
                r.views[x] = if v % 7 == 0 {
                    EMPTY_VIEW
                } else {
                    (v % 6) as u16
                };
                r.masks[x] = ((v >> 8) % 3) as u16;
                r.weights[x] = 0.25 + ((v >> 16) % 97) as f32 * 0.37;
            }
            // Packed lines (8 slots only), in reverse order and with a row beyond the record.
            let order: Vec<u32> = (0..=n as u32).rev().collect();
            let packed = r.gather_packed(&order);
            assert_eq!(packed.is_some(), slots == DEFAULT_SLOTS);
            let line = |k: usize| packed.as_ref().map(|p| p[n - k]);
            let mut mixed = 0;
            for i in 0..n {
                for j in 0..n {
                    let want = disagreement_by_definition(&r, i, j);
                    mixed += usize::from(want.is_some_and(|m| m > 0.0 && m < 1.0));
                    assert_eq!(
                        r.disagreement(i, j).map(f32::to_bits),
                        want.map(f32::to_bits),
                        "{slots} slots, rows {i}, {j}"
                    );
                    if let (Some(a), Some(b)) = (line(i), line(j)) {
                        assert_eq!(
                            a.disagreement(&b).map(f32::to_bits),
                            want.map(f32::to_bits),
                            "packed rows {i}, {j}"
                        );
                    }
                }
            }
            if let Some(p) = &packed {
                assert_eq!(p[0], PackedRow::EMPTY, "a row beyond the record is empty");
                assert_eq!(std::mem::size_of::<PackedRow>(), 64);
            }
            assert!(mixed > n, "{slots} slots: too few mixed pairs ({mixed})");
            assert_eq!(r.disagreement(0, n), None, "a row beyond the record");
        }
    }

    #[test]
    fn round_trips_through_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let mut r = MaskRecord::new(3, 4, 2).unwrap();
        r.add_view(0, [(0, 1, 2.0), (2, 7, 1.0)]);
        r.add_view(1, [(0, 1, 3.0), (2, 6, 1.0)]);
        let path = dir.path().join(FILE_NAME);
        r.write(&path).unwrap();
        let back = MaskRecord::read(&path).unwrap();
        assert_eq!(back, r);
        assert_eq!(back.disagreement(0, 2), Some(1.0));
        assert_eq!(back.disagreement(0, 1), None);
        std::fs::write(&path, b"not safetensors").unwrap();
        assert!(matches!(MaskRecord::read(&path), Err(Error::Format { .. })));
        assert!(MaskRecord::new(1, 0, 1).is_err());
    }

    #[test]
    fn merging_records_of_disjoint_views_gives_the_record_of_all_views() {
        // 40 Gaussians in 12 views with 3 slots: most Gaussians have more views than slots, and
        // equal weights occur, so the order rules decide.
        let view_entries = |v: usize| -> Vec<(u32, u32, f32)> {
            (0..40u32)
                .filter(|g| (g + v as u32) % 3 != 0)
                .map(|g| {
                    (
                        g,
                        (g * 7 + v as u32) % 5,
                        ((g * 13 + v as u32 * 29) % 6) as f32,
                    )
                })
                .collect()
        };
        let mut all = MaskRecord::new(40, 3, 12).unwrap();
        let (mut first, mut second) = (all.clone(), all.clone());
        for v in 0..12 {
            all.add_view(v, view_entries(v));
            let part = if v % 2 == 0 { &mut first } else { &mut second };
            part.add_view(v, view_entries(v));
        }
        assert_ne!(first, all, "one half of the views alone is another record");
        first.merge(&second).unwrap();
        assert_eq!(first, all);
        let mut b = MaskRecord::new(40, 3, 12).unwrap();
        for v in (1..12).step_by(2) {
            b.add_view(v, view_entries(v));
        }
        let mut a = MaskRecord::new(40, 3, 12).unwrap();
        for v in (0..12).step_by(2) {
            a.add_view(v, view_entries(v));
        }
        b.merge(&a).unwrap();
        assert_eq!(b, all, "merged the other way round");
        assert!(all.merge(&MaskRecord::new(41, 3, 12).unwrap()).is_err());
        assert!(all.merge(&MaskRecord::new(40, 2, 12).unwrap()).is_err());
    }
}
