//! Agreement between two answers to the same prompts: IoU of the matched Gaussian sets.

use slag_common::Result;
use slag_common::embeddings::Embeddings;

/// IoU `|a ∩ b| / |a ∪ b|` of two ascending, duplicate-free id lists
/// ([`slag_eval::instances::member_iou`]); `None` when both are empty (the union is
/// empty: no evidence either way).
pub fn iou_sorted(a: &[u32], b: &[u32]) -> Option<f64> {
    (!(a.is_empty() && b.is_empty())).then(|| slag_eval::instances::member_iou(a, b))
}

/// Mean IoU over prompts, `answers[p]` against `reference[p]` (both ascending id lists per
/// prompt). Prompts whose two sets are both empty are left out of the mean (they agree, but
/// carry no information); returns `(mean, prompts averaged)`, and `(1.0, 0)` when every prompt
/// is empty on both sides (the answers are identical).
pub fn mean_iou(answers: &[Vec<u32>], reference: &[Vec<u32>]) -> (f64, usize) {
    let ious: Vec<f64> = answers
        .iter()
        .zip(reference)
        .filter_map(|(a, r)| iou_sorted(a, r))
        .collect();
    if ious.is_empty() {
        (1.0, 0)
    } else {
        (ious.iter().sum::<f64>() / ious.len() as f64, ious.len())
    }
}

/// The exact f32 answer of each prompt: ids (ascending) of the Gaussians whose cosine to the
/// prompt is `>= threshold` (the paper's rule, SLAG Sec. IV), scored with
/// [`slag_common::similarity::cosine_scores`] (what `slag-encoder query` runs).
///
/// Errors: a prompt embedding whose width differs from the embeddings', or a zero prompt.
pub fn threshold_sets(
    emb: &Embeddings,
    prompts: &[Vec<f32>],
    threshold: f32,
) -> Result<Vec<Vec<u32>>> {
    prompts
        .iter()
        .map(|q| {
            let scores = slag_common::similarity::cosine_scores(&emb.vectors, emb.dim, q)?;
            Ok(scores
                .iter()
                .zip(&emb.ids)
                .filter(|(s, _)| **s >= threshold)
                .map(|(_, &id)| id)
                .collect())
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn iou_counts_intersection_over_union() {
        assert_eq!(iou_sorted(&[1, 2, 3, 4], &[3, 4, 5]), Some(2.0 / 5.0));
        assert_eq!(iou_sorted(&[1, 2], &[1, 2]), Some(1.0));
        assert_eq!(iou_sorted(&[1], &[2]), Some(0.0));
        assert_eq!(iou_sorted(&[], &[7]), Some(0.0));
        assert_eq!(iou_sorted(&[], &[]), None);
    }

    #[test]
    fn mean_iou_skips_prompts_empty_on_both_sides() {
        let a = vec![vec![1, 2], vec![], vec![5]];
        let r = vec![vec![2], vec![], vec![6]];
        let (m, n) = mean_iou(&a, &r);
        assert_eq!(n, 2);
        assert!((m - 0.25).abs() < 1e-12);
        assert_eq!(mean_iou(&[vec![]], &[vec![]]), (1.0, 0));
    }
}
