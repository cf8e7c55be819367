//! Aggregation beyond the paper's mean: granularity kept apart and the finest-mask
//! rule.
//!
//! SAM answers every prompt point with three masks (multimask output channels 1..=3: roughly
//! subpart, part, whole), and automatic mask generation keeps all three kinds. The paper's
//! `E_k = Σ a_kj E_j / Σ a_kj` averages them together. Two training-free, single-pass
//! alternatives live here:
//!
//! - **Levels kept apart** (`encode --levels`, LangSplat's three levels): the image stage is
//!   unchanged, but each image's `a_kj` are split by the level of mask `j`
//!   ([`split_by_level`]) and reduced separately, giving one `E_k^l` per level `l` and Gaussian
//!   (`embeddings-level{l}.safetensors`, each an ordinary embeddings file). At query time the
//!   level answers that scores highest ([`LevelRule`]).
//! - **Finest mask per pixel** (`encode --overlap finest`, in the image stage: [`super::MaskOverlap`]):
//!   a pixel covered by several masks contributes its blend weights only to the smallest of them
//!   ([`super::image::restrict_to_finest`]), so
//!   `a_kj = Σ_{p ∈ M_j, j = finest(p)} w_kp` and the masks partition the covered pixels. Each
//!   Gaussian's embedding then mixes only the most specific segments that contain it.

use slag_common::{Error, Result};

use super::image::{Entry, ImageContribution};

/// Number of SAM granularity levels (multimask channels 1..=3).
pub const LEVELS: usize = 3;

/// Splits one image's contribution by mask level: part `l` holds the masks of level `l` (in
/// their original order, renumbered from 0) with their embeddings, and the entries of those
/// masks (still sorted by (Gaussian, mask)). `levels[j]` is mask `j`'s level ([`crate::masks::Mask::level`]).
///
/// Errors: a mask without a level ([`Error::Param`] `levels`: the generator has none, per-level
/// embeddings need SAM masks); `levels` not one per mask of `c`, a level ≥ [`LEVELS`]
/// ([`Error::Internal`]).
pub fn split_by_level(
    c: &ImageContribution,
    levels: &[Option<u8>],
) -> Result<Vec<ImageContribution>> {
    let dim = c.dim;
    let masks = c.mask_embeddings.len().checked_div(dim).unwrap_or(0);
    if levels.len() != masks {
        return Err(Error::internal(format!(
            "{} mask levels for {masks} masks",
            levels.len()
        )));
    }
    let mut parts: Vec<ImageContribution> = (0..LEVELS)
        .map(|_| ImageContribution {
            dim,
            ..Default::default()
        })
        .collect();
    // New index of every mask within its level.
    let mut renumber = Vec::with_capacity(masks);
    for (j, level) in levels.iter().enumerate() {
        let l = match level {
            Some(l) if (*l as usize) < LEVELS => *l as usize,
            Some(l) => {
                return Err(Error::internal(format!(
                    "mask {j} has level {l}; levels are 0..{LEVELS} (SAM's three multimask outputs)"
                )));
            }
            None => {
                return Err(Error::param(
                    "levels",
                    true,
                    "masks with a granularity level (SAM's multimask output); the graph \
                     segmenter's masks have none",
                ));
            }
        };
        let part = &mut parts[l];
        renumber.push((l, (part.mask_embeddings.len() / dim.max(1)) as u32));
        part.mask_embeddings
            .extend_from_slice(&c.mask_embeddings[j * dim..(j + 1) * dim]);
    }
    for e in &c.entries {
        let Some(&(l, mask)) = renumber.get(e.mask as usize) else {
            return Err(Error::internal(format!(
                "entry of mask {} but the image has {masks} masks",
                e.mask
            )));
        };
        parts[l].entries.push(Entry { mask, ..*e });
    }
    Ok(parts)
}

/// How per-level class scores become one score per (Gaussian, class) at query time
/// (`eval-colors --held-out` reports each).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum LevelRule {
    /// One level for every query (0 subpart, 1 part, 2 whole).
    Fixed(usize),
    /// LangSplat's rule: per query, the level whose scores are highest (the mean of its best
    /// 1 % of Gaussians' cosines) answers for every Gaussian.
    Select,
    /// Per Gaussian and query, the highest of its levels' cosines.
    Max,
}

impl LevelRule {
    /// A short name for reports (`level-0`, `levels-select`, `levels-max`).
    pub fn name(self) -> String {
        match self {
            LevelRule::Fixed(l) => format!("level-{l}"),
            LevelRule::Select => "levels-select".into(),
            LevelRule::Max => "levels-max".into(),
        }
    }
}

/// Combines per-level score tables into one: `per_level[l]` is `[N × C]` (as
/// `slag_eval::heldout::gaussian_scores` returns, 0 rows for Gaussians without that level's
/// embedding), `has_level[l][k]` whether Gaussian `k` has level `l`, and `fallback` the `[N × C]`
/// table of the mean `E_k` used where the chosen level is missing. Returns `[N × C]` and, for
/// [`LevelRule::Select`], the level chosen per class (empty otherwise).
///
/// Errors: tables of different sizes, `C == 0` ([`Error::Internal`]), a fixed level out of range
/// ([`Error::Param`] `level`).
pub fn combine_levels(
    per_level: &[Vec<f32>],
    has_level: &[Vec<bool>],
    fallback: &[f32],
    classes: usize,
    rule: LevelRule,
) -> Result<(Vec<f32>, Vec<usize>)> {
    let n = fallback.len() / classes.max(1);
    if classes == 0
        || per_level.is_empty()
        || per_level.len() != has_level.len()
        || per_level.iter().any(|t| t.len() != fallback.len())
        || has_level.iter().any(|h| h.len() != n)
    {
        return Err(Error::internal(format!(
            "level score tables do not match: {} levels, {classes} classes, {n} Gaussians",
            per_level.len()
        )));
    }
    let tables = LevelTables {
        per_level,
        has_level,
        fallback,
        classes,
        n,
    };
    match rule {
        LevelRule::Fixed(l) => {
            if l >= per_level.len() {
                return Err(Error::param(
                    "level",
                    l,
                    format!("a level below {} (the levels stored)", per_level.len()),
                ));
            }
            let mut out = vec![0f32; fallback.len()];
            for k in 0..n {
                for c in 0..classes {
                    out[k * classes + c] = tables.pick(l, k, c);
                }
            }
            Ok((out, Vec::new()))
        }
        LevelRule::Max => Ok((tables.max_over_levels(), Vec::new())),
        LevelRule::Select => Ok(tables.select_per_class()),
    }
}

/// The checked inputs of [`combine_levels`]: `L` per-level `[N × C]` score tables, which
/// Gaussians have each level, and the mean `E_k`'s `[N × C]` table.
struct LevelTables<'a> {
    per_level: &'a [Vec<f32>],
    has_level: &'a [Vec<bool>],
    fallback: &'a [f32],
    /// C.
    classes: usize,
    /// N.
    n: usize,
}

impl LevelTables<'_> {
    /// Gaussian `k`'s score for class `c` at level `l`, the fallback's where it lacks that level.
    fn pick(&self, l: usize, k: usize, c: usize) -> f32 {
        if self.has_level[l][k] {
            self.per_level[l][k * self.classes + c]
        } else {
            self.fallback[k * self.classes + c]
        }
    }

    /// Writes class `c`'s column of `out` (`[N × C]`) from level `l` ([`LevelTables::pick`]).
    fn fill_class(&self, out: &mut [f32], l: usize, c: usize) {
        for k in 0..self.n {
            out[k * self.classes + c] = self.pick(l, k, c);
        }
    }

    /// [`LevelRule::Max`]: per Gaussian and class, the highest score of the levels it has (the
    /// fallback's where it has none). `[N × C]`.
    fn max_over_levels(&self) -> Vec<f32> {
        let classes = self.classes;
        let mut out = vec![0f32; self.fallback.len()];
        for k in 0..self.n {
            let present: Vec<usize> = (0..self.per_level.len())
                .filter(|&l| self.has_level[l][k])
                .collect();
            for c in 0..classes {
                out[k * classes + c] = present
                    .iter()
                    .map(|&l| self.per_level[l][k * classes + c])
                    .reduce(f32::max)
                    .unwrap_or(self.fallback[k * classes + c]);
            }
        }
        out
    }

    /// [`LevelRule::Select`]: per class, the level of highest [`LevelTables::relevancy`] (the
    /// first on a tie) answers for every Gaussian. Returns `[N × C]` and the level per class.
    fn select_per_class(&self) -> (Vec<f32>, Vec<usize>) {
        let mut out = vec![0f32; self.fallback.len()];
        let mut chosen = Vec::with_capacity(self.classes);
        for c in 0..self.classes {
            let mut best = 0;
            let mut best_r = f32::NEG_INFINITY;
            for l in 0..self.per_level.len() {
                let r = self.relevancy(l, c);
                if r > best_r {
                    (best, best_r) = (l, r);
                }
            }
            chosen.push(best);
            self.fill_class(&mut out, best, c);
        }
        (out, chosen)
    }

    /// LangSplat's relevancy of level `l` for class `c`: the mean of the best 1 % (rounded up) of
    /// the class's scores among the Gaussians that have the level; −∞ where none has it.
    fn relevancy(&self, l: usize, c: usize) -> f32 {
        let mut s: Vec<f32> = (0..self.n)
            .filter(|&k| self.has_level[l][k])
            .map(|k| self.per_level[l][k * self.classes + c])
            .collect();
        if s.is_empty() {
            return f32::NEG_INFINITY;
        }
        let top = s.len().div_ceil(100);
        s.select_nth_unstable_by(top - 1, |a, b| b.total_cmp(a));
        s[..top].iter().sum::<f32>() / top as f32
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // tests fail loudly on purpose
mod tests {
    use super::*;
    use crate::aggregate::image::{MaskOverlap, entries, restrict_to_finest};
    use crate::masks::Mask;

    fn mask(area: u32) -> Mask {
        let mut px = vec![0u8; 100];
        px[..area as usize].iter_mut().for_each(|v| *v = 1);
        Mask::from_pixels(10, 10, px).unwrap()
    }

    #[test]
    fn finest_keeps_the_smallest_mask_of_each_label() {
        let masks = [mask(50), mask(10), mask(30), mask(10)];
        let mut sets = vec![vec![], vec![0, 2], vec![0, 1, 2], vec![1, 3], vec![0, 9]];
        restrict_to_finest(&mut sets, &masks);
        assert_eq!(sets, vec![vec![], vec![2], vec![1], vec![1], vec![0]]);
    }

    #[test]
    fn finest_overlap_gives_each_pixel_to_its_smallest_mask_only() {
        use crate::aggregate::{ImageStageParams, image_contribution};
        use crate::raster::PixelWeights;
        // 4×1 image, full resolution raster. Masks: big = all 4 pixels, small = pixels 1..3.
        let big = Mask::from_pixels(4, 1, vec![1, 1, 1, 1]).unwrap();
        let small = Mask::from_pixels(4, 1, vec![0, 1, 1, 0]).unwrap();
        // Gaussian 0 on every pixel (0.5), Gaussian 1 on pixel 2 (0.25).
        let pw = PixelWeights {
            width: 4,
            height: 1,
            offsets: vec![0, 1, 2, 4, 5],
            ids: vec![0, 0, 0, 1, 0],
            weights: vec![0.5, 0.5, 0.5, 0.25, 0.5],
        };
        let masks = [big, small];
        let run = |overlap| {
            let params = ImageStageParams {
                overlap,
                ..ImageStageParams::default()
            };
            let c = image_contribution(&pw, &masks, vec![1.0, 0.0, 0.0, 1.0], 2, params).unwrap();
            c.entries
                .iter()
                .map(|e| (e.gaussian, e.mask, e.weight))
                .collect::<Vec<_>>()
        };
        // The paper: every covering mask gets the pixel.
        assert_eq!(
            run(MaskOverlap::All),
            vec![(0, 0, 2.0), (0, 1, 1.0), (1, 0, 0.25), (1, 1, 0.25)]
        );
        // Finest: pixels 1 and 2 go to the small mask only; Gaussian 1 sees only the small one.
        assert_eq!(
            run(MaskOverlap::Finest),
            vec![(0, 0, 1.0), (0, 1, 1.0), (1, 1, 0.25)]
        );
    }

    #[test]
    fn split_by_level_partitions_masks_and_entries() {
        let dim = 2;
        let c = ImageContribution {
            dim,
            // masks 0..4 with embeddings [j, j]
            mask_embeddings: (0..4).flat_map(|j| [j as f32, j as f32]).collect(),
            entries: entries(&[(0, 0, 1.0), (0, 2, 2.0), (1, 1, 3.0), (1, 3, 4.0)]),
        };
        let levels = [Some(0), Some(2), Some(0), Some(1)];
        let parts = split_by_level(&c, &levels).unwrap();
        assert_eq!(parts[0].mask_embeddings, vec![0.0, 0.0, 2.0, 2.0]);
        assert_eq!(parts[0].entries, entries(&[(0, 0, 1.0), (0, 1, 2.0)]));
        assert_eq!(parts[1].mask_embeddings, vec![3.0, 3.0]);
        assert_eq!(parts[1].entries, entries(&[(1, 0, 4.0)]));
        assert_eq!(parts[2].entries, entries(&[(1, 0, 3.0)]));
        let total: usize = parts.iter().map(|p| p.entries.len()).sum();
        assert_eq!(total, c.entries.len());
        assert!(split_by_level(&c, &[Some(0); 3]).is_err());
        assert!(split_by_level(&c, &[Some(0), None, Some(0), Some(0)]).is_err());
        assert!(split_by_level(&c, &[Some(0), Some(3), Some(0), Some(0)]).is_err());
    }

    #[test]
    fn level_rules_pick_fixed_max_or_the_most_relevant_level() {
        // 2 Gaussians, 2 classes, 2 levels. Gaussian 1 lacks level 1.
        let l0 = vec![0.9, 0.1, 0.2, 0.3];
        let l1 = vec![0.5, 0.8, 0.0, 0.0];
        let has = vec![vec![true, true], vec![true, false]];
        let fb = vec![0.4, 0.4, 0.6, 0.7];
        let t = [l0, l1];
        let (f1, _) = combine_levels(&t, &has, &fb, 2, LevelRule::Fixed(1)).unwrap();
        assert_eq!(f1, vec![0.5, 0.8, 0.6, 0.7]);
        let (m, _) = combine_levels(&t, &has, &fb, 2, LevelRule::Max).unwrap();
        assert_eq!(m, vec![0.9, 0.8, 0.2, 0.3]);
        // Class 0: level 0's best is 0.9 > 0.5; class 1: level 1's best 0.8 > 0.3.
        let (s, chosen) = combine_levels(&t, &has, &fb, 2, LevelRule::Select).unwrap();
        assert_eq!(chosen, vec![0, 1]);
        assert_eq!(s, vec![0.9, 0.8, 0.2, 0.7]);
        assert!(combine_levels(&t, &has, &fb, 2, LevelRule::Fixed(2)).is_err());
        assert!(combine_levels(&t, &has, &fb[..2], 2, LevelRule::Max).is_err());
    }
}
