//! The geometric segments file (`segments.safetensors`, beside `embeddings.safetensors`): one
//! segment id per Gaussian of the source `.ply`, made by `slag-encoder segment` (or `encode`,
//! with segments on) from the Gaussians' geometry alone (Felzenszwalb & Huttenlocher 2004 over a
//! k-NN graph of the means, as ScanNet's Segmentator does over a mesh; the algorithm is
//! `slag_encoder::segments`). Readable from Python without slag (`safetensors.numpy.load_file`).
//!
//! Tensors:
//! - `segments` U32 `[N]` — segment id of Gaussian `i` of the source `.ply` (vertex order), for
//!   every Gaussian, observed or not. Ids are dense, `0..segment_count`, numbered in the order of
//!   each segment's smallest Gaussian id, so the same segmentation always has the same ids.
//!
//! Metadata (`__metadata__`, strings): `format = "slag-segments"`, `version = "1"`,
//! `scene_gaussians` (N), `segment_count`, `source_ply`, `parameters` (JSON of the settings that
//! made it, for the record).

use std::path::Path;

use safetensors::tensor::Dtype;

use crate::safetensors_io::{self, FileKind, le_u32, tensor};
use crate::{Error, Result};

/// Format identifier stored in the metadata.
pub const FORMAT: &str = "slag-segments";
/// Current format version.
pub const VERSION: &str = "1";
/// File name the encoder writes beside `embeddings.safetensors`.
pub const FILE_NAME: &str = "segments.safetensors";
/// Segment id of a Gaussian that has none (a row of a shard written without segments, in a
/// store that holds other shards' segments).
pub const NO_SEGMENT: u32 = u32::MAX;

const KIND: FileKind = FileKind {
    format: FORMAT,
    version: VERSION,
    noun: "segments",
    file_name: FILE_NAME,
    rewrite_with: "slag-encoder segment",
};

/// A scene's geometric segments: `segments[i]` is the segment of `.ply` Gaussian `i`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Segments {
    /// Segment id per Gaussian of the source `.ply`, `[N]`, dense ids `0..segment_count`.
    pub segments: Vec<u32>,
    /// Number of distinct segments.
    pub segment_count: u32,
    /// Path of the source `.ply`, as given to the segmenter.
    pub source_ply: String,
    /// JSON of the parameters that made the segmentation (informative).
    pub parameters: String,
}

impl Segments {
    /// Number of Gaussians N of the source `.ply`.
    pub fn len(&self) -> usize {
        self.segments.len()
    }
    /// True for a scene without Gaussians.
    pub fn is_empty(&self) -> bool {
        self.segments.is_empty()
    }

    /// The segment of `.ply` Gaussian `id`; `None` beyond the scene.
    pub fn of(&self, id: u32) -> Option<u32> {
        self.segments.get(id as usize).copied()
    }

    /// Checks that ids are dense (`< segment_count`, every id used) and first-seen ordered.
    ///
    /// Errors: [`Error::Invalid`] describing the first violation.
    pub fn validate(&self) -> Result<()> {
        let mut next = 0u32;
        for (i, &s) in self.segments.iter().enumerate() {
            if s > next || s == NO_SEGMENT {
                return Err(Error::Invalid(format!(
                    "segment id {s} of Gaussian {i} is not the next new id ({next}); segment ids \
                     must be numbered in the order of their smallest Gaussian id"
                )));
            }
            if s == next {
                next += 1;
            }
        }
        if next != self.segment_count {
            return Err(Error::Invalid(format!(
                "{next} segments used but segment_count is {}",
                self.segment_count
            )));
        }
        Ok(())
    }

    /// Writes the file atomically (`<path>.partial`, fsync, rename).
    ///
    /// Errors: ids that [`Segments::validate`] refuses ([`Error::Internal`]: the writer's
    /// contract); I/O.
    pub fn write(&self, path: &Path) -> Result<()> {
        self.validate()
            .map_err(|e| Error::internal(format!("segments writer: {e}")))?;
        let tensors = vec![tensor(
            "segments",
            vec![self.segments.len()],
            &self.segments,
        )];
        let meta = [
            ("scene_gaussians", self.segments.len().to_string()),
            ("segment_count", self.segment_count.to_string()),
            ("source_ply", self.source_ply.clone()),
            ("parameters", self.parameters.clone()),
        ];
        safetensors_io::write(path, &KIND, tensors, &meta)
    }

    /// Reads a file written by [`Segments::write`].
    ///
    /// Errors ([`Error::Format`] naming the file): not safetensors, another format or version,
    /// no `segments` U32 `[N]` tensor, ids that are not dense; I/O.
    pub fn read(path: &Path) -> Result<Segments> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let file = safetensors_io::open(path, &bytes, &KIND)?;
        let t = file.tensor_of(path, "segments", Dtype::U32)?;
        if t.shape().len() != 1 {
            return Err(Error::format(
                path,
                format!("segments has shape {:?}, expected [N]", t.shape()),
            ));
        }
        let segments = le_u32(t.data());
        let segment_count = segments
            .iter()
            .fold(0u32, |m, &s| m.max(s.saturating_add(1)));
        let s = Segments {
            segments,
            segment_count,
            source_ply: file.meta.get("source_ply").cloned().unwrap_or_default(),
            parameters: file.meta.get("parameters").cloned().unwrap_or_default(),
        };
        s.validate()
            .map_err(|e| Error::format(path, e.to_string()))?;
        Ok(s)
    }

    /// The segment of every Gaussian in `ids` (source-`.ply` indices), in order.
    ///
    /// Errors: an id beyond the scene ([`Error::Mismatch`] `Scene`: the segments belong to
    /// another `.ply`).
    pub fn gather(&self, ids: &[u32]) -> Result<Vec<u32>> {
        ids.iter()
            .map(|&id| {
                self.of(id).ok_or_else(|| {
                    Error::mismatch(
                        crate::Mismatched::Scene,
                        format!(
                            "Gaussian id {id} but the segments cover {} Gaussians; segment the \
                             .ply the embeddings were made from",
                            self.len()
                        ),
                    )
                })
            })
            .collect()
    }
}

/// Renumbers arbitrary per-Gaussian labels (e.g. union-find roots) to dense ids in the order of
/// each label's first Gaussian, the canonical form [`Segments`] stores; returns the ids and the
/// segment count.
pub fn canonical_ids(labels: &[u32]) -> (Vec<u32>, u32) {
    let mut map: std::collections::HashMap<u32, u32> = std::collections::HashMap::new();
    let mut out = Vec::with_capacity(labels.len());
    for &l in labels {
        let next = map.len() as u32;
        out.push(*map.entry(l).or_insert(next));
    }
    let count = map.len() as u32;
    (out, count)
}

/// Applies the paper's prediction filtering (SLAG PF) to per-Gaussian classes: every Gaussian
/// of a segment takes the majority class of the segment's Gaussians that have a class
/// (`Some`); ties go to the smallest class index. Gaussians without a class in a segment with a
/// majority receive it; segments where no Gaussian has a class keep `None`.
///
/// `classes[i]` and `segments[i]` describe the same Gaussian (any row order), `[N]`.
///
/// Errors: lengths that differ ([`Error::Internal`]).
pub fn majority_per_segment(classes: &[Option<u8>], segments: &[u32]) -> Result<Vec<Option<u8>>> {
    if classes.len() != segments.len() {
        return Err(Error::internal(format!(
            "{} classes for {} segment ids",
            classes.len(),
            segments.len()
        )));
    }
    // Votes per segment, one counter per class that occurs (memory: segments × classes).
    let classes_seen = classes
        .iter()
        .flatten()
        .map(|&c| c as usize + 1)
        .max()
        .unwrap_or(0);
    let mut index: std::collections::HashMap<u32, usize> = std::collections::HashMap::new();
    let mut votes: Vec<u32> = Vec::new();
    for (&c, &s) in classes.iter().zip(segments) {
        let next = index.len();
        let slot = *index.entry(s).or_insert(next);
        if slot == next {
            votes.resize(votes.len() + classes_seen, 0);
        }
        if let Some(c) = c {
            votes[slot * classes_seen + c as usize] += 1;
        }
    }
    let winner: Vec<Option<u8>> = (0..index.len())
        .map(|slot| {
            let v = &votes[slot * classes_seen..(slot + 1) * classes_seen];
            let (best, &n) = v
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(&a.0)))?;
            (n > 0).then_some(best as u8)
        })
        .collect();
    Ok(segments.iter().map(|s| winner[index[s]]).collect())
}

/// Smooths per-row scores within segments (the open-vocabulary analogue of prediction
/// filtering): each row's score becomes the mean of its segment's scores over the rows given.
/// Rows whose segment is [`NO_SEGMENT`] keep their own score. NaN scores (a row without a
/// score) take no part in their segment's mean and stay NaN; a segment whose scores are all NaN
/// keeps them.
///
/// `scores[i]` and `segments[i]` describe the same row, `[N]`. Means are accumulated in f64.
///
/// Errors: lengths that differ ([`Error::Internal`]).
pub fn segment_mean(scores: &[f32], segments: &[u32]) -> Result<Vec<f32>> {
    if scores.len() != segments.len() {
        return Err(Error::internal(format!(
            "{} scores for {} segment ids",
            scores.len(),
            segments.len()
        )));
    }
    let mut sums: std::collections::HashMap<u32, (f64, u32)> = std::collections::HashMap::new();
    for (&x, &s) in scores.iter().zip(segments) {
        if s != NO_SEGMENT && !x.is_nan() {
            let e = sums.entry(s).or_insert((0.0, 0));
            e.0 += x as f64;
            e.1 += 1;
        }
    }
    Ok(scores
        .iter()
        .zip(segments)
        .map(|(&x, s)| match sums.get(s) {
            Some(&(sum, n)) if *s != NO_SEGMENT && !x.is_nan() => (sum / n as f64) as f32,
            _ => x,
        })
        .collect())
}

/// Ranks rows by their segment-smoothed score: the one query path that `slag-encoder query
/// --smooth segment` and slag-edge's `smooth=segment` share.
///
/// `raw[i]` is row `i`'s own score (cosine or relevancy; NaN: none) and `segments[i]` its
/// segment, both `[N]` over every row the caller holds, so a segment's mean does not depend on
/// which rows the caller then keeps. Each row is scored with [`segment_mean`]; the rows with
/// `keep(i)` whose smoothed score is `>= threshold` (every kept row for `None`) are returned as
/// `(row, smoothed score)`, best first (ties: lower row first), at most `top_k` (all for
/// `None`). NaN scores are never returned.
///
/// Errors: lengths that differ ([`Error::Internal`]).
pub fn rank_smoothed(
    raw: &[f32],
    segments: &[u32],
    threshold: Option<f32>,
    top_k: Option<usize>,
    keep: impl Fn(usize) -> bool,
) -> Result<Vec<(usize, f32)>> {
    let mut smoothed = segment_mean(raw, segments)?;
    for (i, s) in smoothed.iter_mut().enumerate() {
        if !keep(i) || threshold.is_some_and(|t| *s < t) {
            *s = f32::NAN;
        }
    }
    let k = top_k.unwrap_or(smoothed.len());
    Ok(crate::similarity::top_k(&smoothed, k))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_refusals() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join(FILE_NAME);
        let (segments, segment_count) = canonical_ids(&[7, 7, 3, 9, 3, 7]);
        assert_eq!(segments, vec![0, 0, 1, 2, 1, 0]);
        let s = Segments {
            segments,
            segment_count,
            source_ply: "scene/point_cloud.ply".into(),
            parameters: "{}".into(),
        };
        s.write(&p).unwrap();
        assert_eq!(Segments::read(&p).unwrap(), s);
        assert_eq!(s.gather(&[5, 3]).unwrap(), vec![0, 2]);
        assert!(matches!(s.gather(&[6]), Err(Error::Mismatch { .. })));
        // Not dense: refused by the writer and the reader.
        let bad = Segments {
            segments: vec![1, 0],
            segment_count: 2,
            ..Default::default()
        };
        assert!(matches!(bad.write(&p), Err(Error::Internal(_))));
        std::fs::write(&p, b"not safetensors").unwrap();
        assert!(matches!(Segments::read(&p), Err(Error::Format { .. })));
    }

    #[test]
    fn majority_and_mean_follow_segments() {
        let classes = [Some(2), Some(2), Some(1), None, Some(0), None];
        let segs = [0, 0, 0, 0, 1, 2];
        let pf = majority_per_segment(&classes, &segs).unwrap();
        assert_eq!(pf, vec![Some(2), Some(2), Some(2), Some(2), Some(0), None]);
        // A tie goes to the smaller class.
        let tie = majority_per_segment(&[Some(3), Some(1)], &[5, 5]).unwrap();
        assert_eq!(tie, vec![Some(1), Some(1)]);
        let m = segment_mean(&[1.0, 0.0, 0.5, 0.2], &[4, 4, NO_SEGMENT, 9]).unwrap();
        assert_eq!(m, vec![0.5, 0.5, 0.5, 0.2]);
        assert!(segment_mean(&[1.0], &[]).is_err());
        // A NaN score takes no part in its segment's mean and stays NaN.
        let m = segment_mean(&[f32::NAN, 0.2, 0.4], &[1, 1, 1]).unwrap();
        assert!(m[0].is_nan() && (m[1] - 0.3).abs() < 1e-7 && (m[2] - 0.3).abs() < 1e-7);
    }

    #[test]
    fn rank_smoothed_thresholds_and_keeps_the_smoothed_scores() {
        // Segment 0: one high row among low ones (mean 0.3); segment 1: uniform 0.5; row 5 alone.
        let raw = [0.9, 0.0, 0.0, 0.5, 0.5, 0.35];
        let segs = [0, 0, 0, 1, 1, NO_SEGMENT];
        let all = rank_smoothed(&raw, &segs, None, None, |_| true).unwrap();
        let rows: Vec<usize> = all.iter().map(|h| h.0).collect();
        assert_eq!(rows, vec![3, 4, 5, 0, 1, 2]);
        assert!((all[3].1 - 0.3).abs() < 1e-7);
        // The raw 0.9 no longer passes 0.32; the unsegmented row keeps its own 0.35.
        let t = rank_smoothed(&raw, &segs, Some(0.32), None, |_| true).unwrap();
        assert_eq!(t.iter().map(|h| h.0).collect::<Vec<_>>(), vec![3, 4, 5]);
        // keep() drops rows after the mean: row 4 dropped, row 3 still scores its segment's 0.5.
        let k = rank_smoothed(&raw, &segs, Some(0.32), Some(1), |i| i != 4).unwrap();
        assert_eq!(k, vec![(3, 0.5)]);
    }
}
