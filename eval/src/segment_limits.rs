//! What limits segment purity ([`crate::segment_quality`]) on a scene with a per-Gaussian
//! ground truth (`eval-colors --prediction-filtering`: the colour classes).
//!
//! - [`neighbour_agreement`]: how much the truth itself agrees locally. For each labelled
//!   Gaussian, the share of its `k` nearest labelled neighbours with its label, and whether its
//!   label is the majority of the ball of itself and those `k` (ties to the smaller label). The
//!   latter is the purity of compact segments of `k + 1` Gaussians centred on each Gaussian: a
//!   ceiling for any segmentation that does not look at the labels and whose segments are that
//!   small.
//! - [`purity_by_size`]: purity per segment-size decade (tiny segments are pure by construction;
//!   the large ones say what the method does).
//! - [`weighted_purity`]: purity with each Gaussian counted by a weight (its total blend weight
//!   `Σ a_kj` over the encoded views, how much the views see it), and restricted to the Gaussians
//!   seen most. The segments' majority is the unweighted one of the purity definition.
//! - [`mask_purity`]: how pure the masks of a masks' record are against the labels: over the
//!   (view, mask) groups of the recorded dominant masks, the share of entries whose mask's
//!   majority label is their own.
//! - [`mask_evidence`]: how well the record's multi-view mask disagreement separates the
//!   `k`-nearest-neighbour pairs of different labels from those of the same label.

use std::collections::HashMap;

use rayon::prelude::*;
use slag_common::mask_record::MaskRecord;
use slag_common::{Error, Result};

use crate::segment_quality::{labelled_tree, majority, segment_votes};

fn same_length(a: usize, b: usize, what: &str) -> Result<()> {
    if a != b {
        return Err(Error::internal(format!(
            "{a} labels for {b} values ({what})"
        )));
    }
    Ok(())
}

/// The majority label of each segment over its labelled Gaussians (ties to the smaller label).
fn majorities(labels: &[Option<u32>], segments: &[u32]) -> HashMap<u32, u32> {
    segment_votes(labels, segments)
        .into_iter()
        .map(|(s, v)| (s, majority(&v).map_or(0, |(l, _)| l)))
        .collect()
}

/// [`neighbour_agreement`] for one `k`.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct NeighbourAgreement {
    /// Neighbours per Gaussian.
    pub k: usize,
    /// Mean over the labelled Gaussians of the share of their `k` nearest labelled neighbours
    /// that have their label.
    pub same_share: f64,
    /// Share of the labelled Gaussians whose label is the majority of the ball of themselves and
    /// their `k` nearest labelled neighbours.
    pub local_majority: f64,
    /// Labelled Gaussians counted (those with at least one labelled neighbour).
    pub counted: usize,
    /// The five most frequent unordered label pairs `(a, b, share)`, `a < b`, among the
    /// neighbour pairs of different labels, most frequent first.
    pub different_pairs: Vec<(u32, u32, f64)>,
}

/// The local agreement of `labels` for each `k` of `ks` (module doc); `means` in scene units,
/// one per label.
///
/// Errors: lengths that differ ([`Error::Internal`]).
pub fn neighbour_agreement(
    means: &[[f32; 3]],
    labels: &[Option<u32>],
    ks: &[usize],
) -> Result<Vec<NeighbourAgreement>> {
    same_length(labels.len(), means.len(), "neighbour agreement")?;
    let tree = labelled_tree(means, labels);
    let kmax = ks.iter().copied().max().unwrap_or(0);
    // Per Gaussian: its label and its kmax nearest labelled neighbours' labels, nearest first.
    let near: Vec<(u32, Vec<u32>)> = (0..means.len())
        .into_par_iter()
        .filter_map(|i| {
            let l = labels[i]?;
            let mut c: Vec<(f32, u32)> = tree
                .nearest_neighbor_iter_with_distance_2(&means[i])
                .filter(|(g, _)| g.data as usize != i)
                .take(kmax)
                .map(|(g, d2)| (d2, g.data))
                .collect();
            c.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            Some((
                l,
                c.iter().filter_map(|&(_, j)| labels[j as usize]).collect(),
            ))
        })
        .collect();
    Ok(ks
        .iter()
        .map(|&k| {
            let (mut share, mut major, mut counted) = (0.0f64, 0usize, 0usize);
            let mut pairs: HashMap<(u32, u32), usize> = HashMap::new();
            for (l, ns) in &near {
                let ns = &ns[..k.min(ns.len())];
                if ns.is_empty() {
                    continue;
                }
                counted += 1;
                let same = ns.iter().filter(|&&m| m == *l).count();
                for &m in ns.iter().filter(|&&m| m != *l) {
                    *pairs.entry((m.min(*l), m.max(*l))).or_default() += 1;
                }
                share += same as f64 / ns.len() as f64;
                let mut votes: HashMap<u32, usize> = HashMap::new();
                *votes.entry(*l).or_default() += 1;
                for &m in ns {
                    *votes.entry(m).or_default() += 1;
                }
                let best = majority(&votes).map(|(m, _)| m);
                major += usize::from(best == Some(*l));
            }
            let c = counted.max(1) as f64;
            let total = pairs.values().sum::<usize>().max(1) as f64;
            let mut different_pairs: Vec<((u32, u32), usize)> = pairs.into_iter().collect();
            different_pairs.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
            NeighbourAgreement {
                k,
                same_share: share / c,
                local_majority: major as f64 / c,
                counted,
                different_pairs: different_pairs
                    .into_iter()
                    .take(5)
                    .map(|((a, b), n)| (a, b, n as f64 / total))
                    .collect(),
            }
        })
        .collect())
}

/// Purity of the segments of one size range ([`purity_by_size`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SizePurity {
    /// Smallest segment size (all Gaussians of the segment, labelled or not).
    pub from: usize,
    /// Largest (`None`: unbounded).
    pub to: Option<usize>,
    /// Segments of that size holding a labelled Gaussian.
    pub segments: usize,
    /// Labelled Gaussians in them.
    pub counted: usize,
    /// Of those, the share whose segment's majority label is their own.
    pub purity: f64,
}

/// Purity per segment-size decade (1, 2–9, 10–99, 100–999, 1,000–9,999, ≥ 10,000).
///
/// Errors: lengths that differ ([`Error::Internal`]).
pub fn purity_by_size(labels: &[Option<u32>], segments: &[u32]) -> Result<Vec<SizePurity>> {
    same_length(labels.len(), segments.len(), "purity by size")?;
    let major = majorities(labels, segments);
    let mut size: HashMap<u32, usize> = HashMap::new();
    for &s in segments {
        *size.entry(s).or_default() += 1;
    }
    let bounds = [1usize, 2, 10, 100, 1_000, 10_000];
    let bin = |n: usize| bounds.iter().rposition(|&b| n >= b).unwrap_or(0);
    let mut counted = [0usize; 6];
    let mut kept = [0usize; 6];
    for (l, s) in labels.iter().zip(segments) {
        if let Some(l) = l {
            let b = bin(size[s]);
            counted[b] += 1;
            kept[b] += usize::from(major.get(s) == Some(l));
        }
    }
    let mut segs = [0usize; 6];
    for s in major.keys() {
        segs[bin(size[s])] += 1;
    }
    Ok((0..6)
        .map(|b| SizePurity {
            from: bounds[b],
            to: bounds.get(b + 1).map(|t| t - 1),
            segments: segs[b],
            counted: counted[b],
            purity: if counted[b] == 0 {
                0.0
            } else {
                kept[b] as f64 / counted[b] as f64
            },
        })
        .collect())
}

/// Purity counted by weight ([`weighted_purity`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct WeightedPurity {
    /// Σ weight of the labelled Gaussians whose segment's majority is theirs / Σ weight.
    pub weighted: f64,
    /// Purity (unweighted count) over the labelled Gaussians whose weight is at least the median
    /// of the labelled weights.
    pub top_half: f64,
    /// The same over the top quarter.
    pub top_quarter: f64,
    /// The same over the bottom half (weight below the median).
    pub bottom_half: f64,
    /// The median weight.
    pub median_weight: f64,
    /// Labelled Gaussians with a weight.
    pub counted: usize,
}

/// Purity of `segments` against `labels` with each Gaussian counted by `weights` (`None` or a
/// non-finite or negative weight: not counted); the segments' majority labels are the unweighted
/// ones over all labelled Gaussians (as in
/// [`crate::segment_quality::purity`]).
///
/// Errors: lengths that differ ([`Error::Internal`]).
pub fn weighted_purity(
    labels: &[Option<u32>],
    segments: &[u32],
    weights: &[Option<f32>],
) -> Result<WeightedPurity> {
    same_length(labels.len(), segments.len(), "weighted purity")?;
    same_length(labels.len(), weights.len(), "weighted purity weights")?;
    let major = majorities(labels, segments);
    // (weight, kept) per counted Gaussian.
    let mut rows: Vec<(f32, bool)> = (0..labels.len())
        .filter_map(|i| {
            let l = labels[i]?;
            let w = weights[i].filter(|w| w.is_finite() && *w >= 0.0)?;
            Some((w, major.get(&segments[i]) == Some(&l)))
        })
        .collect();
    rows.sort_by(|a, b| a.0.total_cmp(&b.0));
    let n = rows.len();
    let share = |r: &[(f32, bool)]| {
        if r.is_empty() {
            0.0
        } else {
            r.iter().filter(|x| x.1).count() as f64 / r.len() as f64
        }
    };
    let total: f64 = rows.iter().map(|r| r.0 as f64).sum();
    let kept: f64 = rows.iter().filter(|r| r.1).map(|r| r.0 as f64).sum();
    Ok(WeightedPurity {
        weighted: if total > 0.0 { kept / total } else { 0.0 },
        top_half: share(&rows[n / 2..]),
        top_quarter: share(&rows[n - n / 4..]),
        bottom_half: share(&rows[..n / 2]),
        median_weight: rows.get(n / 2).map_or(0.0, |r| r.0 as f64),
        counted: n,
    })
}

/// How pure a masks' record's masks are ([`mask_purity`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct MaskPurity {
    /// Over the entries of the first slot (each labelled Gaussian's best-seen view): the share
    /// whose (view, mask) group's majority label is their own.
    pub best_view: f64,
    /// The same over every recorded slot.
    pub all_slots: f64,
    /// Distinct (view, mask) groups.
    pub masks: usize,
    /// Slot entries of labelled Gaussians.
    pub entries: usize,
    /// Labelled Gaussians without any recorded slot.
    pub unrecorded: usize,
}

/// Purity of the record's dominant masks against `labels` (module doc).
///
/// Errors: a record of another length ([`Error::Internal`]).
pub fn mask_purity(labels: &[Option<u32>], record: &MaskRecord) -> Result<MaskPurity> {
    same_length(labels.len(), record.len(), "mask purity")?;
    let mut votes: HashMap<(u16, u16), HashMap<u32, usize>> = HashMap::new();
    for (i, l) in labels.iter().enumerate() {
        if let Some(l) = l {
            for s in record.of(i) {
                *votes
                    .entry((s.view, s.mask))
                    .or_default()
                    .entry(*l)
                    .or_default() += 1;
            }
        }
    }
    let major: HashMap<(u16, u16), u32> = votes
        .iter()
        .map(|(k, v)| (*k, majority(v).map_or(0, |(l, _)| l)))
        .collect();
    let (mut best_n, mut best_k, mut all_n, mut all_k, mut unrecorded) = (0, 0, 0, 0, 0);
    for (i, l) in labels.iter().enumerate() {
        let Some(l) = l else { continue };
        let mut any = false;
        for (slot, s) in record.of(i).enumerate() {
            any = true;
            let ok = usize::from(major.get(&(s.view, s.mask)) == Some(l));
            all_n += 1;
            all_k += ok;
            if slot == 0 {
                best_n += 1;
                best_k += ok;
            }
        }
        unrecorded += usize::from(!any);
    }
    let r = |k: usize, n: usize| if n == 0 { 0.0 } else { k as f64 / n as f64 };
    Ok(MaskPurity {
        best_view: r(best_k, best_n),
        all_slots: r(all_k, all_n),
        masks: votes.len(),
        entries: all_n,
        unrecorded,
    })
}

/// The record's disagreement over one kind of neighbour pair ([`mask_evidence`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PairEvidence {
    /// Pairs.
    pub pairs: usize,
    /// Share of them whose ends share no recorded view.
    pub unknown: f64,
    /// Mean disagreement over the pairs with a shared view.
    pub mean_disagreement: f64,
    /// Share of the pairs with a shared view whose disagreement exceeds 0.5.
    pub over_half: f64,
    /// Share of the pairs with a shared view whose disagreement is 0 (every shared view agrees).
    pub zero: f64,
}

/// [`mask_evidence`]: the record's disagreement on same-label and different-label pairs.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct MaskEvidence {
    /// Neighbours per Gaussian.
    pub k: usize,
    /// Pairs (Gaussian, one of its `k` nearest labelled neighbours) of one label.
    pub same_label: PairEvidence,
    /// Pairs of different labels.
    pub different_label: PairEvidence,
}

/// The record's multi-view mask disagreement ([`MaskRecord::disagreement`]) over the pairs
/// (labelled Gaussian, one of its `k` nearest labelled neighbours), split by whether the labels
/// agree; `means` in scene units.
///
/// Errors: lengths that differ ([`Error::Internal`]).
pub fn mask_evidence(
    means: &[[f32; 3]],
    labels: &[Option<u32>],
    record: &MaskRecord,
    k: usize,
) -> Result<MaskEvidence> {
    same_length(labels.len(), means.len(), "mask evidence")?;
    same_length(labels.len(), record.len(), "mask evidence record")?;
    let tree = labelled_tree(means, labels);
    // [same, different] × (pairs, unknown, Σ m, over half, zero)
    type Tally = [(usize, usize, f64, usize, usize); 2];
    let add = |mut a: Tally, b: Tally| {
        for s in 0..2 {
            a[s].0 += b[s].0;
            a[s].1 += b[s].1;
            a[s].2 += b[s].2;
            a[s].3 += b[s].3;
            a[s].4 += b[s].4;
        }
        a
    };
    let t: Tally = (0..means.len())
        .into_par_iter()
        .filter(|&i| labels[i].is_some())
        .map(|i| {
            let mut t: Tally = [(0, 0, 0.0, 0, 0); 2];
            for g in tree
                .nearest_neighbor_iter(&means[i])
                .filter(|g| g.data as usize != i)
                .take(k)
            {
                let j = g.data as usize;
                let s = usize::from(labels[j] != labels[i]);
                t[s].0 += 1;
                match record.disagreement(i, j) {
                    None => t[s].1 += 1,
                    Some(m) => {
                        t[s].2 += m as f64;
                        t[s].3 += usize::from(m > 0.5);
                        t[s].4 += usize::from(m == 0.0);
                    }
                }
            }
            t
        })
        .reduce(|| [(0, 0, 0.0, 0, 0); 2], add);
    let ev = |x: (usize, usize, f64, usize, usize)| {
        let known = (x.0 - x.1).max(1) as f64;
        PairEvidence {
            pairs: x.0,
            unknown: x.1 as f64 / x.0.max(1) as f64,
            mean_disagreement: x.2 / known,
            over_half: x.3 as f64 / known,
            zero: x.4 as f64 / known,
        }
    };
    Ok(MaskEvidence {
        k,
        same_label: ev(t[0]),
        different_label: ev(t[1]),
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A row of 20 points along x: labels 0 for x < 10, 1 after, except x = 3 (label 1).
    fn row() -> (Vec<[f32; 3]>, Vec<Option<u32>>) {
        let means = (0..20).map(|x| [x as f32, 0.0, 0.0]).collect();
        let labels = (0..20)
            .map(|x| Some(u32::from(x >= 10 || x == 3)))
            .collect();
        (means, labels)
    }

    #[test]
    fn neighbour_agreement_sees_isolated_labels() {
        let (means, labels) = row();
        let a = neighbour_agreement(&means, &labels, &[2]).unwrap();
        assert_eq!(a[0].counted, 20);
        // x = 3 loses its local majority (2 and 4 are 0); so do no others: 19 of 20.
        assert!((a[0].local_majority - 0.95).abs() < 1e-12, "{a:?}");
        assert!(a[0].same_share < 1.0);
        assert_eq!(a[0].different_pairs.len(), 1);
        assert_eq!(
            (a[0].different_pairs[0].0, a[0].different_pairs[0].1),
            (0, 1)
        );
        // Clean labels agree everywhere but at the border.
        let clean: Vec<Option<u32>> = (0..20).map(|x| Some(u32::from(x >= 10))).collect();
        let c = neighbour_agreement(&means, &clean, &[2]).unwrap();
        assert_eq!(c[0].local_majority, 1.0);
        assert!(c[0].same_share > a[0].same_share);
    }

    #[test]
    fn weighted_purity_counts_by_weight() {
        // Segment 0 holds labels 0,0,1 (the 1 is impure); segment 1 holds 1.
        let labels = [Some(0), Some(0), Some(1), Some(1)];
        let segments = [0, 0, 0, 1];
        let light = [Some(1.0), Some(1.0), Some(0.1), Some(1.0)];
        let w = weighted_purity(&labels, &segments, &light).unwrap();
        assert!((w.weighted - 3.0 / 3.1).abs() < 1e-9, "{w:?}");
        assert_eq!(w.top_half, 1.0);
        let heavy = [Some(1.0), Some(1.0), Some(10.0), Some(1.0)];
        let h = weighted_purity(&labels, &segments, &heavy).unwrap();
        assert!((h.weighted - 3.0 / 13.0).abs() < 1e-9, "{h:?}");
        assert!(h.top_quarter == 0.0);
        assert!(weighted_purity(&labels, &segments, &heavy[1..]).is_err());
    }

    #[test]
    fn purity_by_size_separates_tiny_segments() {
        let mut labels = vec![Some(0u32); 12];
        labels[11] = Some(1);
        let mut segments = vec![0u32; 12];
        segments[0] = 5; // a singleton
        let p = purity_by_size(&labels, &segments).unwrap();
        assert_eq!((p[0].segments, p[0].counted, p[0].purity), (1, 1, 1.0));
        assert_eq!(p[2].counted, 11);
        assert!((p[2].purity - 10.0 / 11.0).abs() < 1e-12);
    }

    #[test]
    fn mask_purity_and_evidence_from_a_record() {
        let (means, labels) = row();
        let mut r = MaskRecord::new(20, 2, 2).unwrap();
        // View 0: masks follow the labels; view 1: one mask over everything.
        r.add_view(
            0,
            (0..20u32).map(|i| (i, u32::from(i >= 10 || i == 3), 2.0)),
        );
        r.add_view(1, (0..20u32).map(|i| (i, 0, 1.0)));
        let p = mask_purity(&labels, &r).unwrap();
        assert_eq!(p.best_view, 1.0);
        // View 1's single mask: majority 1 (11 of its 20 entries).
        assert!((p.all_slots - (20.0 + 11.0) / 40.0).abs() < 1e-12, "{p:?}");
        assert_eq!((p.masks, p.unrecorded), (3, 0));
        let e = mask_evidence(&means, &labels, &r, 2).unwrap();
        assert!(e.different_label.mean_disagreement > e.same_label.mean_disagreement);
        assert_eq!(e.same_label.mean_disagreement, 0.0);
        assert_eq!(e.different_label.unknown, 0.0);
    }
}
