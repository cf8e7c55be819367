//! Prediction filtering (SLAG PF): per-Gaussian class predictions made uniform over the scene's
//! geometric segments ([`crate::segments`]), as the paper does with ScanNet's Segmentator
//! segments: every segment takes the majority class of its Gaussians.
//!
//! The score tables here are `[scene Gaussians × C]`, row `k` for `.ply` Gaussian `k` (the
//! layout of `slag_eval::heldout::gaussian_scores`); `observed[k]` says whether Gaussian `k` has an
//! embedding. Unobserved Gaussians do not vote, and receive their segment's answer when the
//! segment has observed members (a segment without any stays at zero, as unobserved Gaussians are
//! without PF). These tables are scored by `eval-colors --held-out --prediction-filtering`:
//!
//! - `argmax`: each observed Gaussian's own class as a one-hot row (the control: PF's one-hot
//!   rendering without segments);
//! - `pf-majority`: the paper's PF, the segment's majority class one-hot;
//! - `pf-mean`: the open-vocabulary analogue, each class score averaged over the segment's
//!   observed Gaussians;
//! - `pf-weighted`: the majority with each Gaussian's vote weighted by its total blend weight
//!   `Σ_j a_kj` (how much the encoded views saw of it), one-hot;
//! - `pf-confident`: a Gaussian whose own class is clear keeps it: one whose score margin (best
//!   class score minus the second) is at least the median margin of the observed Gaussians keeps
//!   its own class, the others (and the unobserved) take `pf-weighted`'s segment class, one-hot;
//! - `pf-strict`: the paper's majority only where it is a strict majority (the winning class
//!   holds more than half of the segment's votes); the Gaussians of a segment split more evenly,
//!   which PF's premise (one segment, one object) evidently does not fit, keep their own class.

use std::collections::HashMap;

use slag_common::segments::majority_per_segment;
use slag_common::{Error, Result};

/// Each Gaussian's class: the argmax of its row (ties to the smaller class) when observed.
///
/// Errors: `scores` not `observed.len() × classes` ([`Error::Internal`]).
pub fn gaussian_classes(
    scores: &[f32],
    observed: &[bool],
    classes: usize,
) -> Result<Vec<Option<u8>>> {
    check(scores, observed.len(), classes)?;
    Ok(scores
        .chunks_exact(classes)
        .zip(observed)
        .map(|(row, &o)| o.then(|| argmax(row) as u8))
        .collect())
}

/// Index of the first largest value of `v` (ties to the smaller index; a NaN never wins), 0 for
/// an empty `v`.
fn argmax<T: PartialOrd>(v: &[T]) -> usize {
    let mut best = 0usize;
    for (i, x) in v.iter().enumerate() {
        if *x > v[best] {
            best = i;
        }
    }
    best
}

fn check(scores: &[f32], n: usize, classes: usize) -> Result<()> {
    if classes == 0 || classes > 256 || scores.len() != n * classes {
        return Err(Error::internal(format!(
            "score table of {} values for {n} Gaussians × {classes} classes",
            scores.len()
        )));
    }
    Ok(())
}

/// One-hot rows of `classes` (`None`: a zero row), `[N × C]`.
pub fn one_hot(classes: &[Option<u8>], c: usize) -> Vec<f32> {
    let mut t = vec![0.0f32; classes.len() * c];
    for (k, cl) in classes.iter().enumerate() {
        if let Some(cl) = cl
            && (*cl as usize) < c
        {
            t[k * c + *cl as usize] = 1.0;
        }
    }
    t
}

/// What every PF table reads: the scene's score table, which Gaussians are observed and each
/// Gaussian's segment (the module doc's layout).
#[derive(Debug, Clone, Copy)]
pub struct PfInputs<'a> {
    /// `[N × classes]` row-major class scores, row `k` for `.ply` Gaussian `k`.
    pub scores: &'a [f32],
    /// `[N]`: whether Gaussian `k` has an embedding (only observed Gaussians vote).
    pub observed: &'a [bool],
    /// `[N]` segment id of each Gaussian.
    pub segments: &'a [u32],
    /// Classes `C` (1 to 256).
    pub classes: usize,
}

/// One-hot rows of the classes `vote` chooses from each Gaussian's own class
/// ([`gaussian_classes`]): the form of every one-hot PF table.
///
/// Errors: `scores` not `observed.len() × classes`, or `vote`'s ([`Error::Internal`]).
fn vote_table(
    t: &PfInputs,
    vote: impl FnOnce(&[Option<u8>]) -> Result<Vec<Option<u8>>>,
) -> Result<Vec<f32>> {
    let own = gaussian_classes(t.scores, t.observed, t.classes)?;
    Ok(one_hot(&vote(&own)?, t.classes))
}

/// The paper's PF: one-hot rows of each segment's majority class over its observed Gaussians.
///
/// Errors: tables whose sizes disagree ([`Error::Internal`]).
pub fn majority_table(t: &PfInputs) -> Result<Vec<f32>> {
    vote_table(t, |own| majority_per_segment(own, t.segments))
}

/// Each segment's votes by `weights[k]` (≥ 0; non-finite counts 0) over its observed Gaussians
/// of known class: the winning class (ties to the smaller class), its weight and the total
/// weight. Segments without a positive vote are absent.
///
/// Errors: lengths that differ ([`Error::Internal`]).
fn segment_votes(
    own: &[Option<u8>],
    weights: &[f32],
    segments: &[u32],
) -> Result<HashMap<u32, (u8, f64, f64)>> {
    if own.len() != segments.len() || weights.len() != segments.len() {
        return Err(Error::internal(format!(
            "{} classes, {} weights, {} segment ids",
            own.len(),
            weights.len(),
            segments.len()
        )));
    }
    let mut votes: HashMap<u32, [f64; 256]> = HashMap::new();
    for ((c, &w), &s) in own.iter().zip(weights).zip(segments) {
        if let Some(c) = c {
            let w = if w.is_finite() { w.max(0.0) } else { 0.0 };
            votes.entry(s).or_insert([0.0; 256])[*c as usize] += w as f64;
        }
    }
    Ok(votes
        .into_iter()
        .filter_map(|(s, v)| {
            let best = argmax(&v);
            (v[best] > 0.0).then(|| (s, (best as u8, v[best], v.iter().sum())))
        })
        .collect())
}

/// Each segment's class by votes weighted by `weights[k]` (≥ 0; non-finite counts 0) over its
/// observed Gaussians of known class (ties to the smaller class); `None` for a segment
/// without votes. One entry per Gaussian.
///
/// Errors: lengths that differ ([`Error::Internal`]).
pub fn weighted_majority(
    own: &[Option<u8>],
    weights: &[f32],
    segments: &[u32],
) -> Result<Vec<Option<u8>>> {
    let winner = segment_votes(own, weights, segments)?;
    Ok(segments
        .iter()
        .map(|s| winner.get(s).map(|w| w.0))
        .collect())
}

/// `pf-strict` (module doc): the paper's majority where it is one, i.e. where the segment's
/// winning class holds more than half of its observed Gaussians' votes; in a segment split
/// more evenly every observed Gaussian keeps its own class (unobserved ones take the winning
/// class, as with `pf-majority`). One-hot rows.
///
/// Errors: tables whose sizes disagree ([`Error::Internal`]).
pub fn strict_majority_table(t: &PfInputs) -> Result<Vec<f32>> {
    vote_table(t, |own| {
        let votes = segment_votes(own, &vec![1.0; own.len()], t.segments)?;
        Ok(own
            .iter()
            .zip(t.segments)
            .map(|(o, s)| match votes.get(s) {
                Some(&(best, w, total)) if 2.0 * w > total || o.is_none() => Some(best),
                _ => *o,
            })
            .collect())
    })
}

/// `pf-weighted` (module doc): one-hot rows of each segment's class by votes weighted by
/// `weights` (`[N]`, e.g. `Σ_j a_kj`).
///
/// Errors: tables whose sizes disagree ([`Error::Internal`]).
pub fn weighted_table(t: &PfInputs, weights: &[f32]) -> Result<Vec<f32>> {
    vote_table(t, |own| weighted_majority(own, weights, t.segments))
}

/// Each row's margin: its best score minus its second best.
fn margins(scores: &[f32], classes: usize) -> Vec<f32> {
    scores
        .chunks_exact(classes)
        .map(|row| {
            let (mut a, mut b) = (f32::NEG_INFINITY, f32::NEG_INFINITY);
            for &v in row {
                if v > a {
                    b = a;
                    a = v;
                } else if v > b {
                    b = v;
                }
            }
            if b.is_finite() { a - b } else { 0.0 }
        })
        .collect()
}

/// `pf-confident` (module doc): observed Gaussians with a margin at least the observed median
/// keep their own class; the rest take the segment's `weights`-weighted class. One-hot rows.
///
/// Errors: tables whose sizes disagree ([`Error::Internal`]).
pub fn confident_table(t: &PfInputs, weights: &[f32]) -> Result<Vec<f32>> {
    vote_table(t, |own| {
        let seg = weighted_majority(own, weights, t.segments)?;
        let m = margins(t.scores, t.classes);
        let mut seen: Vec<f32> = m
            .iter()
            .zip(t.observed)
            .filter(|(_, o)| **o)
            .map(|(v, _)| *v)
            .collect();
        let median = if seen.is_empty() {
            f32::INFINITY
        } else {
            let mid = seen.len() / 2;
            *seen.select_nth_unstable_by(mid, f32::total_cmp).1
        };
        Ok(own
            .iter()
            .zip(&seg)
            .zip(&m)
            .map(|((o, s), &mk)| match o {
                Some(c) if mk >= median => Some(*c),
                _ => s.or(*o),
            })
            .collect())
    })
}

/// Segment-mean scores: each class score averaged over the segment's observed Gaussians.
///
/// Errors: tables whose sizes disagree ([`Error::Internal`]).
pub fn mean_table(t: &PfInputs) -> Result<Vec<f32>> {
    let &PfInputs {
        scores,
        observed,
        segments,
        classes,
    } = t;
    check(scores, observed.len(), classes)?;
    if segments.len() != observed.len() {
        return Err(Error::internal(format!(
            "{} segment ids for {} Gaussians",
            segments.len(),
            observed.len()
        )));
    }
    let mut sums: HashMap<u32, (Vec<f64>, u32)> = HashMap::new();
    for (k, (&s, &o)) in segments.iter().zip(observed).enumerate() {
        if o {
            let e = sums.entry(s).or_insert_with(|| (vec![0.0; classes], 0));
            for (acc, &v) in e.0.iter_mut().zip(&scores[k * classes..(k + 1) * classes]) {
                *acc += v as f64;
            }
            e.1 += 1;
        }
    }
    let mut out = vec![0.0f32; scores.len()];
    for (k, s) in segments.iter().enumerate() {
        if let Some((sum, n)) = sums.get(s) {
            for (o, &v) in out[k * classes..(k + 1) * classes].iter_mut().zip(sum) {
                *o = (v / *n as f64) as f32;
            }
        }
    }
    Ok(out)
}

/// The same per-Gaussian classes with PF applied, for the 3D score (`slag_eval::evaluate`):
/// `predicted[i]` is the class of embeddings row `i`, `row_segments[i]` its segment.
///
/// Errors: lengths that differ ([`Error::Internal`]).
pub fn filter_rows(predicted: &[u8], row_segments: &[u32]) -> Result<Vec<u8>> {
    let own: Vec<Option<u8>> = predicted.iter().map(|&c| Some(c)).collect();
    Ok(majority_per_segment(&own, row_segments)?
        .into_iter()
        .zip(predicted)
        .map(|(m, &p)| m.unwrap_or(p))
        .collect())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn inputs<'a>(
        scores: &'a [f32],
        observed: &'a [bool],
        segments: &'a [u32],
        classes: usize,
    ) -> PfInputs<'a> {
        PfInputs {
            scores,
            observed,
            segments,
            classes,
        }
    }

    /// A synthetic scene: 3 segments of 50 Gaussians whose true classes are 0, 1, 2; a noisy
    /// labelling gets 30 % of each segment wrong (deterministically), and a few Gaussians are
    /// unobserved. PF restores the truth everywhere, and every segment's Gaussians share a class.
    #[test]
    fn pf_restores_the_majority_of_a_noisy_labelling() {
        let (c, per) = (3usize, 50usize);
        let n = c * per;
        let segments: Vec<u32> = (0..n).map(|k| (k / per) as u32).collect();
        let truth: Vec<usize> = (0..n).map(|k| k / per).collect();
        let observed: Vec<bool> = (0..n).map(|k| k % 17 != 3).collect();
        let mut scores = vec![0.0f32; n * c];
        let mut wrong = 0;
        for k in 0..n {
            // Every 10 Gaussians, 3 get the next class: 30 % noise.
            let label = if k % 10 < 3 {
                (truth[k] + 1) % c
            } else {
                truth[k]
            };
            wrong += usize::from(label != truth[k]);
            scores[k * c + label] = 0.3;
            scores[k * c + (label + 2) % c] = 0.1;
        }
        assert!(wrong >= n / 4);
        let raw = gaussian_classes(&scores, &observed, c).unwrap();
        assert!(
            raw.iter()
                .zip(&truth)
                .filter(|(r, t)| **r == Some(**t as u8))
                .count()
                < n * 3 / 4
        );
        let t = inputs(&scores, &observed, &segments, c);
        let pf = majority_table(&t).unwrap();
        let mean = mean_table(&t).unwrap();
        for k in 0..n {
            let row = &pf[k * c..(k + 1) * c];
            assert_eq!(
                row[truth[k]], 1.0,
                "Gaussian {k} (observed {})",
                observed[k]
            );
            assert_eq!(row.iter().sum::<f32>(), 1.0);
            // The segment mean ranks the true class first too, and is the same in a segment.
            let m = &mean[k * c..(k + 1) * c];
            let best = (0..c).max_by(|&a, &b| m[a].total_cmp(&m[b])).unwrap();
            assert_eq!(best, truth[k]);
            assert_eq!(m, &mean[(k / per) * per * c..((k / per) * per + 1) * c]);
        }
        // The 3D form: rows of one segment get one class.
        let predicted: Vec<u8> = raw.iter().map(|r| r.unwrap_or(0)).collect();
        let filtered = filter_rows(&predicted, &segments).unwrap();
        for (f, t) in filtered.iter().zip(&truth) {
            assert_eq!(*f as usize, *t);
        }
        let short = inputs(&scores, &observed, &segments[1..], c);
        assert!(majority_table(&short).is_err());
    }

    #[test]
    fn weighted_and_confident_votes() {
        // One segment of 4 observed Gaussians, 2 classes: three weak votes for class 0, one
        // strong vote for class 1 that also has the largest margin.
        let scores = vec![
            0.30, 0.29, //
            0.31, 0.30, //
            0.32, 0.30, //
            0.10, 0.90, //
        ];
        let observed = [true; 4];
        let segments = [0u32; 4];
        let weights = [1.0, 1.0, 1.0, 10.0];
        let t = inputs(&scores, &observed, &segments, 2);
        let major = majority_table(&t).unwrap();
        assert!(major.chunks(2).all(|r| r == [1.0, 0.0]));
        let w = weighted_table(&t, &weights).unwrap();
        assert!(w.chunks(2).all(|r| r == [0.0, 1.0]));
        // Confident: margins 0.01, 0.01, 0.02, 0.8; median (upper middle) 0.02: Gaussians 2
        // and 3 keep their own classes, 0 and 1 take the weighted vote (class 1).
        let c = confident_table(&t, &[1.0; 4]).unwrap();
        assert_eq!(c, vec![1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 1.0]);
        let c = confident_table(&t, &weights).unwrap();
        assert_eq!(c, vec![0.0, 1.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0]);
        assert!(weighted_table(&t, &weights[1..]).is_err());
    }

    #[test]
    fn the_strict_majority_filters_only_segments_one_class_holds() {
        // Segment 0: classes 0, 0, 0, 1 (a strict majority: all become 0); segment 1: 0, 0,
        // 1, 1 (split evenly: each keeps its own); an unobserved Gaussian in each takes the
        // winner (the smaller class on the tie).
        let scores = vec![
            0.9, 0.1, 0.9, 0.1, 0.9, 0.1, 0.1, 0.9, 0.0, 0.0, //
            0.9, 0.1, 0.9, 0.1, 0.1, 0.9, 0.1, 0.9, 0.0, 0.0,
        ];
        let observed = [true, true, true, true, false, true, true, true, true, false];
        let segments = [0u32, 0, 0, 0, 0, 1, 1, 1, 1, 1];
        let pf = inputs(&scores, &observed, &segments, 2);
        let t = strict_majority_table(&pf).unwrap();
        let classes: Vec<usize> = t.chunks(2).map(|r| argmax(r)).collect();
        assert_eq!(classes, vec![0, 0, 0, 0, 0, 0, 0, 1, 1, 0]);
        assert!(t.chunks(2).all(|r| r.iter().sum::<f32>() == 1.0));
        // The paper's majority filters both segments.
        let m = majority_table(&pf).unwrap();
        assert!(m.chunks(2).all(|r| r == [1.0, 0.0]));
        let short = inputs(&scores, &observed, &segments[1..], 2);
        assert!(strict_majority_table(&short).is_err());
    }

    #[test]
    fn a_segment_without_observed_gaussians_stays_empty() {
        let scores = vec![0.5, 0.1, 0.0, 0.0];
        let t = inputs(&scores, &[true, false], &[0, 1], 2);
        let pf = majority_table(&t).unwrap();
        assert_eq!(pf, vec![1.0, 0.0, 0.0, 0.0]);
        let mean = mean_table(&t).unwrap();
        assert_eq!(mean, vec![0.5, 0.1, 0.0, 0.0]);
    }
}
