//! Segments measured against a ground truth (`eval-colors`: colour classes; `eval-segments`: the
//! instances of a `synth-scene --objects` scene).
//!
//! - *Purity*: the fraction of the labelled Gaussians whose segment's majority label (over the
//!   segment's labelled Gaussians, ties to the smaller label) is their own. 1 when no segment
//!   mixes labels; a single segment over everything scores the largest label's share.
//! - *Boundary recall*: of the pairs (Gaussian, one of its `k` nearest labelled neighbours within
//!   a radius) whose labels differ, the fraction whose segments differ too: how much of the true
//!   boundaries the segments keep. Over-segmentation scores 1 here and purity keeps it honest in
//!   the other direction through the size distribution.
//! - *Size distribution*: segment count, Gaussians per segment (min, median, mean, 90th
//!   percentile, max), the largest segment's share, and a histogram by decades.

use std::collections::HashMap;

use rayon::prelude::*;
use rstar::RTree;
use rstar::primitives::GeomWithData;
use slag_common::{Error, Result};

/// Segment count and sizes.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SizeDistribution {
    /// Distinct segments.
    pub segments: usize,
    /// Gaussians segmented.
    pub gaussians: usize,
    /// Smallest segment, Gaussians.
    pub min: usize,
    /// Median segment size (the lower middle for an even count).
    pub median: usize,
    /// Mean segment size.
    pub mean: f64,
    /// 90th percentile of the segment sizes.
    pub p90: usize,
    /// Largest segment, Gaussians.
    pub max: usize,
    /// Share of the Gaussians in the largest segment.
    pub largest_share: f64,
    /// Segments and Gaussians per size decade: 1, 2–9, 10–99, 100–999, 1,000–9,999, ≥ 10,000.
    pub histogram: Vec<SizeBin>,
}

/// One decade of [`SizeDistribution::histogram`].
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SizeBin {
    /// Smallest size in the bin.
    pub from: usize,
    /// Largest size in the bin (`None`: unbounded).
    pub to: Option<usize>,
    /// Segments of that size.
    pub segments: usize,
    /// Gaussians in them.
    pub gaussians: usize,
}

/// The sizes of the segments in `segments` (one id per Gaussian; any ids).
pub fn size_distribution(segments: &[u32]) -> SizeDistribution {
    let mut count: HashMap<u32, usize> = HashMap::new();
    for &s in segments {
        *count.entry(s).or_default() += 1;
    }
    let mut sizes: Vec<usize> = count.into_values().collect();
    sizes.sort_unstable();
    let n = segments.len();
    let at = |q: f64| -> usize {
        if sizes.is_empty() {
            return 0;
        }
        sizes[(((sizes.len() - 1) as f64) * q).floor() as usize]
    };
    let bounds = [1usize, 2, 10, 100, 1_000, 10_000];
    let histogram = bounds
        .iter()
        .enumerate()
        .map(|(b, &from)| {
            let to = bounds.get(b + 1).map(|t| t - 1);
            let inside: Vec<usize> = sizes
                .iter()
                .copied()
                .filter(|&s| s >= from && to.is_none_or(|t| s <= t))
                .collect();
            SizeBin {
                from,
                to,
                segments: inside.len(),
                gaussians: inside.iter().sum(),
            }
        })
        .collect();
    let max = sizes.last().copied().unwrap_or(0);
    SizeDistribution {
        segments: sizes.len(),
        gaussians: n,
        min: sizes.first().copied().unwrap_or(0),
        median: at(0.5),
        mean: if sizes.is_empty() {
            0.0
        } else {
            n as f64 / sizes.len() as f64
        },
        p90: at(0.9),
        max,
        largest_share: if n == 0 { 0.0 } else { max as f64 / n as f64 },
        histogram,
    }
}

/// Purity of `segments` against `labels` (module doc).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Purity {
    /// Labelled Gaussians whose segment's majority label is theirs, over the labelled ones.
    pub purity: f64,
    /// Labelled Gaussians counted.
    pub counted: usize,
}

fn same_length(a: usize, b: usize, what: &str) -> Result<()> {
    if a != b {
        return Err(Error::internal(format!(
            "{a} labels for {b} segment ids ({what})"
        )));
    }
    Ok(())
}

/// The votes of each segment (one id per Gaussian): its labelled Gaussians counted per label.
pub(crate) fn segment_votes(
    labels: &[Option<u32>],
    segments: &[u32],
) -> HashMap<u32, HashMap<u32, usize>> {
    let mut votes: HashMap<u32, HashMap<u32, usize>> = HashMap::new();
    for (l, &s) in labels.iter().zip(segments) {
        if let Some(l) = l {
            *votes.entry(s).or_default().entry(*l).or_default() += 1;
        }
    }
    votes
}

/// An R-tree of the labelled Gaussians' means (`labels[i]` not `None`), each with its index.
pub(crate) fn labelled_tree(
    means: &[[f32; 3]],
    labels: &[Option<u32>],
) -> RTree<GeomWithData<[f32; 3], u32>> {
    RTree::bulk_load(
        (0..means.len())
            .filter(|&i| labels[i].is_some())
            .map(|i| GeomWithData::new(means[i], i as u32))
            .collect(),
    )
}

/// The label with the most votes and its count (ties to the smaller label); `None` without
/// votes.
pub(crate) fn majority(votes: &HashMap<u32, usize>) -> Option<(u32, usize)> {
    votes
        .iter()
        .max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0)))
        .map(|(&l, &c)| (l, c))
}

/// Purity of `segments` (one id per Gaussian) against `labels` (`None`: not counted, e.g. an
/// unobserved Gaussian or one without a true class).
///
/// Errors: lengths that differ ([`Error::Internal`]).
pub fn purity(labels: &[Option<u32>], segments: &[u32]) -> Result<Purity> {
    same_length(labels.len(), segments.len(), "purity")?;
    let (mut counted, mut kept) = (0usize, 0usize);
    for v in segment_votes(labels, segments).values() {
        let total: usize = v.values().sum();
        let best = majority(v).map_or(0, |(_, c)| c);
        counted += total;
        kept += best;
    }
    Ok(Purity {
        purity: if counted == 0 {
            0.0
        } else {
            kept as f64 / counted as f64
        },
        counted,
    })
}

/// Purity counted over the Gaussians with `counted[i]` only, each against the majority label of
/// its **whole** segment (every labelled Gaussian of the segment votes, counted or not; ties to
/// the smaller label). Over an object scene's object Gaussians this says how many of them sit in
/// a segment that another label (the floor, a wall, a touching object) dominates, which
/// [`purity`] over the objects' labels alone cannot see and which a purity over every Gaussian
/// hides under the floor's and walls' share.
///
/// Errors: lengths that differ ([`Error::Internal`]).
pub fn purity_within(labels: &[Option<u32>], segments: &[u32], counted: &[bool]) -> Result<Purity> {
    same_length(labels.len(), segments.len(), "purity_within")?;
    same_length(counted.len(), segments.len(), "purity_within (counted)")?;
    let winner: HashMap<u32, u32> = segment_votes(labels, segments)
        .iter()
        .filter_map(|(&s, v)| majority(v).map(|(l, _)| (s, l)))
        .collect();
    let (mut n, mut kept) = (0usize, 0usize);
    for ((l, s), _) in labels
        .iter()
        .zip(segments)
        .zip(counted)
        .filter(|(_, c)| **c)
    {
        if let Some(l) = l {
            n += 1;
            kept += usize::from(winner.get(s) == Some(l));
        }
    }
    Ok(Purity {
        purity: if n == 0 { 0.0 } else { kept as f64 / n as f64 },
        counted: n,
    })
}

/// Boundary recall of `segments` against `labels` (module doc).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct BoundaryRecall {
    /// Neighbour pairs with different labels.
    pub boundary_pairs: usize,
    /// Of those, pairs in different segments.
    pub separated: usize,
    /// `separated / boundary_pairs` (1 when there is no boundary).
    pub recall: f64,
    /// Neighbours per Gaussian looked at.
    pub neighbours: usize,
    /// Largest neighbour distance, scene units.
    pub radius: f32,
}

/// Boundary recall over the `k` nearest labelled neighbours within `radius` of each labelled
/// Gaussian (`means` in scene units).
///
/// Errors: lengths that differ ([`Error::Internal`]).
pub fn boundary_recall(
    means: &[[f32; 3]],
    labels: &[Option<u32>],
    segments: &[u32],
    k: usize,
    radius: f32,
) -> Result<BoundaryRecall> {
    same_length(labels.len(), segments.len(), "boundary recall")?;
    same_length(means.len(), segments.len(), "boundary recall means")?;
    let tree = labelled_tree(means, labels);
    let r2 = radius * radius;
    let (pairs, separated) = (0..means.len())
        .into_par_iter()
        .filter(|&i| labels[i].is_some())
        .map(|i| {
            let (mut p, mut s) = (0usize, 0usize);
            for (g, d2) in tree
                .nearest_neighbor_iter_with_distance_2(&means[i])
                .filter(|(g, _)| g.data as usize != i)
                .take(k)
            {
                let j = g.data as usize;
                if d2 > r2 {
                    break;
                }
                if labels[j] != labels[i] {
                    p += 1;
                    s += usize::from(segments[j] != segments[i]);
                }
            }
            (p, s)
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    Ok(BoundaryRecall {
        boundary_pairs: pairs,
        separated,
        recall: if pairs == 0 {
            1.0
        } else {
            separated as f64 / pairs as f64
        },
        neighbours: k,
        radius,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn purity_counts_each_segments_majority() {
        // Segment 0: labels 1,1,2 (2 kept of 3); segment 1: 3,3 (2 of 2); one unlabelled.
        let labels = [Some(1), Some(1), Some(2), Some(3), Some(3), None];
        let segments = [0, 0, 0, 1, 1, 0];
        let p = purity(&labels, &segments).unwrap();
        assert_eq!(p.counted, 5);
        assert!((p.purity - 0.8).abs() < 1e-12);
        // One segment over everything: the largest label's share.
        let one = purity(&labels, &[7; 6]).unwrap();
        assert!((one.purity - 0.4).abs() < 1e-12);
        // Singletons are pure.
        assert_eq!(purity(&labels, &[0, 1, 2, 3, 4, 5]).unwrap().purity, 1.0);
        assert!(purity(&labels, &segments[1..]).is_err());
    }

    #[test]
    fn purity_within_counts_some_against_the_whole_segments_majority() {
        // Segment 0: an object of 2 (label 1) inside a floor of 3 (label 9); segment 1: an
        // object of 2 (label 2) with one floor Gaussian.
        let labels: Vec<Option<u32>> = [1, 1, 9, 9, 9, 2, 2, 9].map(Some).to_vec();
        let segments = [0, 0, 0, 0, 0, 1, 1, 1];
        let objects = [true, true, false, false, false, true, true, false];
        let p = purity_within(&labels, &segments, &objects).unwrap();
        // The first object is swallowed by the floor, the second holds its segment.
        assert_eq!(p.counted, 4);
        assert!((p.purity - 0.5).abs() < 1e-12);
        // Over the objects' labels alone both would look pure.
        let only: Vec<Option<u32>> = labels
            .iter()
            .zip(&objects)
            .map(|(l, o)| if *o { *l } else { None })
            .collect();
        assert_eq!(purity(&only, &segments).unwrap().purity, 1.0);
        assert!(purity_within(&labels, &segments, &objects[1..]).is_err());
    }

    #[test]
    fn boundary_recall_sees_merged_boundaries() {
        // Two rows of points along x, labels 0 (x < 5) and 1 (x ≥ 5).
        let means: Vec<[f32; 3]> = (0..10).map(|x| [x as f32, 0.0, 0.0]).collect();
        let labels: Vec<Option<u32>> = (0..10).map(|x| Some(u32::from(x >= 5))).collect();
        let split: Vec<u32> = (0..10).map(|x| u32::from(x >= 5)).collect();
        let all = boundary_recall(&means, &labels, &[0; 10], 2, 1.5).unwrap();
        assert_eq!(all.boundary_pairs, 2);
        assert_eq!(all.recall, 0.0);
        let good = boundary_recall(&means, &labels, &split, 2, 1.5).unwrap();
        assert_eq!(good.recall, 1.0);
    }

    #[test]
    fn sizes_by_decade() {
        let mut segs = vec![0u32; 150];
        segs.extend([1, 1, 2]);
        let d = size_distribution(&segs);
        assert_eq!((d.segments, d.gaussians, d.min, d.max), (3, 153, 1, 150));
        assert_eq!(d.median, 2);
        assert_eq!(d.histogram[0].segments, 1);
        assert_eq!(d.histogram[1].segments, 1);
        assert_eq!(d.histogram[3].gaussians, 150);
        assert!((d.largest_share - 150.0 / 153.0).abs() < 1e-12);
    }
}
