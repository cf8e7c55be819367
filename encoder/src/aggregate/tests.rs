//! Tests of the image stage, the store and the reductions.
#![allow(clippy::unwrap_used)]

use super::*;
use crate::aggregate::image::entries;
use crate::masks::Mask;
use crate::raster::PixelWeights;
use rustc_hash::FxHashMap;
use slag_common::Error;
use std::path::Path;

pub(super) fn mask(w: u32, h: u32, f: impl Fn(u32, u32) -> bool) -> Mask {
    Mask::from_fn(w, h, f).unwrap()
}

/// Random-ish PixelWeights with 0..4 contributors per pixel.
pub(super) fn weights(w: u32, h: u32, n: u32, seed: u64) -> PixelWeights {
    let mut s = seed;
    let mut next = || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s
    };
    let mut pw = PixelWeights {
        width: w,
        height: h,
        offsets: vec![0],
        ..Default::default()
    };
    for _ in 0..w * h {
        let c = next() % 5;
        for _ in 0..c {
            pw.ids.push((next() % n as u64) as u32);
            pw.weights.push((next() % 1000) as f32 / 4000.0 + 1e-3);
        }
        pw.offsets.push(pw.ids.len() as u32);
    }
    pw
}

/// Brute force straight from the paper's formula.
fn brute(pw: &PixelWeights, masks: &[Mask]) -> FxHashMap<(u32, u32), f64> {
    let mut m = FxHashMap::default();
    for (j, mk) in masks.iter().enumerate() {
        for y in 0..pw.height {
            for x in 0..pw.width {
                if mk.contains(x, y) {
                    let (ids, ws) = pw.pixel(x, y);
                    for (&k, &w) in ids.iter().zip(ws) {
                        *m.entry((k, j as u32)).or_insert(0.0) += w as f64;
                    }
                }
            }
        }
    }
    m
}

#[test]
fn mask_weighting_scales_each_masks_a_kj() {
    let (w, h, n) = (37, 23, 50);
    let pw = weights(w, h, n, 0x51ed);
    let mut masks = vec![
        mask(w, h, |x, _| x < 20),
        mask(w, h, |x, y| x > 10 && y > 5),
        mask(w, h, |_, _| true),
    ];
    masks[0].predicted_iou = 0.5;
    masks[0].stability_score = 0.8;
    masks[1].predicted_iou = f32::NAN;
    let expect = brute(&pw, &masks);
    for weighting in [MaskWeighting::Area, MaskWeighting::SamScore] {
        let params = ImageStageParams {
            mask_weighting: weighting,
            ..ImageStageParams::default()
        };
        let c = image_contribution(&pw, &masks, vec![0.0; 3 * 2], 2, params).unwrap();
        assert_eq!(c.entries.len(), expect.len());
        for e in &c.entries {
            let m = &masks[e.mask as usize];
            let g = match weighting {
                MaskWeighting::Area => (w * h) as f64 / m.area as f64,
                _ if e.mask == 0 => 0.4,
                _ if e.mask == 1 => f32::MIN_POSITIVE as f64,
                _ => 1.0,
            };
            let v = g * expect[&(e.gaussian, e.mask)];
            assert!(
                (v - e.weight as f64).abs() < 1e-5 * v.max(1e-30),
                "{weighting:?} {e:?} vs {v}"
            );
        }
    }
    assert_eq!(MaskWeighting::None.factor(&masks[1]), 1.0);
    assert_eq!(MaskWeighting::Area.factor(&masks[2]), 1.0);
}

#[test]
fn image_stage_matches_brute_force_with_overlapping_masks() {
    let (w, h, n) = (37, 23, 50);
    let pw = weights(w, h, n, 0x9e3779b97f4a7c15);
    let masks = vec![
        mask(w, h, |x, _| x < 20),
        mask(w, h, |x, y| x > 10 && y > 5),
        mask(w, h, |x, y| (x + y) % 3 == 0),
        mask(w, h, |_, _| true),
    ];
    let c = image_contribution(
        &pw,
        &masks,
        vec![0.0; 4 * 2],
        2,
        ImageStageParams::default(),
    )
    .unwrap();
    let expect = brute(&pw, &masks);
    assert_eq!(c.entries.len(), expect.len());
    for e in &c.entries {
        let v = expect[&(e.gaussian, e.mask)];
        assert!(
            (v - e.weight as f64).abs() < 1e-5 * v.max(1.0),
            "{e:?} vs {v}"
        );
    }
    assert!(
        c.entries
            .windows(2)
            .all(|p| (p[0].gaussian, p[0].mask) < (p[1].gaussian, p[1].mask))
    );
}

#[test]
fn masks_are_resampled_to_a_smaller_raster() {
    // Full-res masks 40x20, raster 20x10: raster pixel (x, y) samples mask pixel (2x+1, 2y+1).
    let masks = vec![mask(40, 20, |x, _| x >= 20)];
    let mut pw = PixelWeights {
        width: 20,
        height: 10,
        offsets: vec![0],
        ..Default::default()
    };
    for p in 0..200u32 {
        pw.ids.push(p);
        pw.weights.push(0.5);
        pw.offsets.push(pw.ids.len() as u32);
    }
    let c = image_contribution(&pw, &masks, vec![1.0], 1, ImageStageParams::default()).unwrap();
    assert_eq!(c.entries.len(), 100);
    assert!(
        c.entries
            .iter()
            .all(|e| e.gaussian % 20 >= 10 && e.weight == 0.5)
    );
}

#[test]
fn top_k_keeps_largest_contributors() {
    let masks = vec![mask(1, 1, |_, _| true)];
    let pw = PixelWeights {
        width: 1,
        height: 1,
        offsets: vec![0, 4],
        ids: vec![0, 1, 2, 3],
        weights: vec![0.1, 0.4, 0.05, 0.3],
    };
    let c = image_contribution(
        &pw,
        &masks,
        vec![1.0],
        1,
        ImageStageParams {
            top_k_per_pixel: Some(2),
            ..ImageStageParams::default()
        },
    )
    .unwrap();
    let kept: Vec<u32> = c.entries.iter().map(|e| e.gaussian).collect();
    assert_eq!(kept, vec![1, 3]);
}

#[test]
fn reduction_is_the_weighted_mean_and_flags_unobserved() {
    let dim = 3;
    let store = ContributionStore::in_memory([
        // Image 1: masks e_x and e_y. Gaussian 0: a=1 in both; Gaussian 2: a=3 in e_y only.
        ImageContribution {
            dim,
            mask_embeddings: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
            entries: entries(&[(0, 0, 1.0), (0, 1, 1.0), (2, 1, 3.0), (3, 0, 1e-9)]),
        },
        // Image 2: mask e_z. Gaussian 0: a=2.
        ImageContribution {
            dim,
            mask_embeddings: vec![0.0, 0.0, 1.0],
            entries: entries(&[(0, 0, 2.0)]),
        },
    ]);
    let r = reduce(&store, 5, dim, ReduceParams::default()).unwrap();
    assert_eq!(r.ids, vec![0, 2]); // 1 and 4 unseen, 3 below the threshold
    let n = (1.0f64 + 1.0 + 4.0).sqrt();
    let e0: Vec<f32> = [1.0 / n, 1.0 / n, 2.0 / n]
        .iter()
        .map(|&v| v as f32)
        .collect();
    for (a, b) in r.vectors[..3].iter().zip(&e0) {
        assert!((a - b).abs() < 1e-6);
    }
    assert_eq!(&r.vectors[3..6], &[0.0, 1.0, 0.0]);
    assert_eq!(r.total_weights, vec![4.0, 3.0]);
}

#[test]
fn chunked_and_spilled_reduction_equals_single_pass() {
    let dim = 4;
    let n = 5000;
    let make = |seed: u64| {
        let pw = weights(30, 20, n, seed);
        let masks = vec![mask(30, 20, |x, _| x < 15), mask(30, 20, |_, y| y < 12)];
        let emb: Vec<f32> = (0..8)
            .map(|i| ((i * 7 + seed as usize) % 5) as f32 - 2.0)
            .collect();
        image_contribution(&pw, &masks, emb, dim, ImageStageParams::default()).unwrap()
    };
    let dir = tempfile::tempdir().unwrap();
    let mut all_mem = ContributionStore::new(usize::MAX, dir.path().join("a"));
    let mut spilling = ContributionStore::new(0, dir.path().join("b"));
    for seed in 1..6 {
        all_mem.push(make(seed)).unwrap();
        spilling.push(make(seed)).unwrap();
    }
    assert_eq!(spilling.spilled(), 5);
    let one = reduce(&all_mem, n as usize, dim, ReduceParams::default()).unwrap();
    let tight = ReduceParams {
        accumulator_budget_bytes: 1024 * (dim + 1) * 8,
        ..Default::default()
    };
    let many = reduce(&spilling, n as usize, dim, tight).unwrap();
    assert_eq!(one.chunks, 1);
    assert!(many.chunks >= 4);
    assert_eq!(one.ids, many.ids);
    assert!(!one.ids.is_empty());
    for (a, b) in one.vectors.iter().zip(&many.vectors) {
        assert!((a - b).abs() < 1e-6);
    }
    drop(spilling);
    assert!(!dir.path().join("b").exists());
}

/// Views pushed out of order, some kept in memory and some spilled, are visited by view index;
/// and the same views pushed in any order give the same mixture, bit for bit.
#[test]
fn the_store_visits_views_by_index_whatever_their_arrival() {
    let (dim, n) = (2, 50u32);
    // View v: one mask embedding [v, 1] and an a_kj on Gaussians v and v + 10.
    let view = |v: u32| ImageContribution {
        dim,
        mask_embeddings: vec![v as f32, 1.0],
        entries: entries(&[(v, 0, 1.0 + v as f32), (v + 10, 0, 0.5)]),
    };
    let one_view_bytes = view(0).bytes();
    let dir = tempfile::tempdir().unwrap();
    let visited = |arrival: &[u32], name: &str| {
        // Room for three views in memory: the rest spill.
        let mut store = ContributionStore::new(3 * one_view_bytes, dir.path().join(name));
        for &v in arrival {
            let stored = StoredImage::from_contribution(view(v));
            store.push_stored_as(v as usize, stored).unwrap();
        }
        let mut seen = Vec::new();
        store
            .for_each(|c| seen.push(c.mask_embeddings[0] as u32))
            .unwrap();
        (store, seen)
    };
    let (sorted, in_order) = visited(&[0, 1, 2, 3, 4, 5], "sorted");
    let (shuffled, out_of_order) = visited(&[4, 1, 5, 0, 3, 2], "shuffled");
    assert_eq!(shuffled.spilled(), 3);
    assert_eq!(in_order, [0, 1, 2, 3, 4, 5]);
    assert_eq!(out_of_order, in_order);
    let means = vec![[0.0f32; 3]; n as usize];
    let rp = ReduceParams::default();
    let a = reduce_mixture_chunks(&sorted, &means, dim, rp, 2, "m")
        .unwrap()
        .0;
    let b = reduce_mixture_chunks(&shuffled, &means, dim, rp, 2, "m")
        .unwrap()
        .0;
    assert_eq!(a.codebook, b.codebook);
    assert_eq!((a.atoms, a.weights), (b.atoms, b.weights));
}
/// Unit rows from a xorshift stream.
pub(super) fn unit_rows(m: usize, dim: usize, seed: u64) -> Vec<f32> {
    let mut s = seed | 1;
    let mut out = Vec::new();
    for _ in 0..m {
        let v: Vec<f32> = (0..dim)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                (s >> 40) as f32 / (1u64 << 23) as f32 - 1.0
            })
            .collect();
        let n = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
        out.extend(v.iter().map(|x| x / n));
    }
    out
}

/// Centres of `n` Gaussians on a line along x: Gaussian `k` at `(k, y, z)`.
pub(super) fn means_along_x(n: u32, y: f32, z: f32) -> Vec<[f32; 3]> {
    (0..n).map(|k| [k as f32, y, z]).collect()
}

/// View `seed`'s contribution: three overlapping masks over the Gaussians of `pw` (30 × 20
/// pixels), unit mask embeddings of width `dim`.
pub(super) fn mixture_view(pw: &PixelWeights, dim: usize, seed: u64) -> ImageContribution {
    let masks = vec![
        mask(30, 20, |x, _| x < 15),
        mask(30, 20, |_, y| y < 12),
        mask(30, 20, |x, y| (x + 2 * y) % 5 < 2),
    ];
    let emb = unit_rows(masks.len(), dim, seed * 31);
    image_contribution(pw, &masks, emb, dim, ImageStageParams::default()).unwrap()
}

/// Images with overlapping masks over `n` Gaussians, unit mask embeddings of width `dim`.
fn mixture_store(n: u32, dim: usize, budget: usize, dir: &Path) -> ContributionStore {
    let mut store = ContributionStore::new(budget, dir.to_path_buf());
    for seed in 1..5u64 {
        store
            .push(mixture_view(&weights(30, 20, n, seed), dim, seed))
            .unwrap();
    }
    store
}

/// The host's fold of views pushed in any order gives the kept store's mixture bit for bit
/// (Σ a_kj in f64 in view order, the same pairs in the same slots, the codebook in view order),
/// at one kept pair (displaced by later views) and at three, over Gaussians spread across
/// several of the fold's parallel blocks; a view pushed twice is refused.
#[test]
fn the_folded_mixture_equals_the_kept_stores_whatever_the_arrival() {
    let (dim, views) = (8, 12u64);
    // 300 Gaussians, each seen by many views, spread over ids 0..140,000 (three blocks).
    let spread = |seed| {
        let mut pw = weights(30, 20, 300, seed);
        pw.ids.iter_mut().for_each(|g| *g *= 467);
        pw
    };
    let n = 140_000usize;
    let images: Vec<ImageContribution> = (1..=views)
        .map(|v| mixture_view(&spread(v), dim, v))
        .collect();
    let means = means_along_x(n as u32, 0.0, 0.0);
    let rp = ReduceParams::default();
    let kept = ContributionStore::in_memory(images.iter().cloned());
    for keep in [1, 3] {
        let (want, _) = reduce_mixture_chunks(&kept, &means, dim, rp, keep, "m").unwrap();
        let mut fold = MixtureFold::new(n, dim, keep, rp.min_total_weight).unwrap();
        // Arrival: every third view first, then the rest backwards.
        let order: Vec<usize> = (0..views as usize)
            .filter(|v| v % 3 == 2)
            .chain((0..views as usize).rev().filter(|v| v % 3 != 2))
            .collect();
        for &v in &order {
            fold.push(v, StoredImage::from_contribution(images[v].clone()))
                .unwrap();
        }
        assert_eq!(fold.len(), views as usize);
        assert!(
            fold.peak_pending_bytes() > 0,
            "views waited for earlier ones"
        );
        let again = StoredImage::from_contribution(images[0].clone());
        assert!(matches!(fold.push(0, again), Err(Error::Internal(_))));
        let got = fold.finish(&means, "m").unwrap();
        assert!(
            want.gaussian_ids.len() > 250,
            "{} observed",
            want.gaussian_ids.len()
        );
        assert!(want.gaussian_ids.last().is_some_and(|&g| g > 2 * 65_536));
        assert_eq!(got.gaussian_ids, want.gaussian_ids, "keep {keep}");
        assert_eq!(got.means, want.means);
        assert_eq!(got.offsets, want.offsets);
        assert_eq!(got.atoms, want.atoms, "keep {keep}");
        assert_eq!(
            got.weights.iter().map(|w| w.to_bits()).collect::<Vec<_>>(),
            want.weights.iter().map(|w| w.to_bits()).collect::<Vec<_>>()
        );
        assert_eq!(got.codebook, want.codebook);
    }
}

/// A fold refuses what it cannot add, with the error that names it: no kept pair, a view of
/// another width, a Gaussian past the scene, a mask past the view's embeddings.
#[test]
fn a_fold_refuses_views_it_cannot_add() {
    assert!(matches!(
        MixtureFold::new(10, 2, 0, 1e-6),
        Err(Error::Param { .. })
    ));
    let view = |dim: usize, g: u32, mask: u32| {
        StoredImage::from_contribution(ImageContribution {
            dim,
            mask_embeddings: vec![1.0; dim],
            entries: entries(&[(g, mask, 1.0)]),
        })
    };
    let mut fold = MixtureFold::new(10, 2, 2, 1e-6).unwrap();
    assert!(matches!(
        fold.push(0, view(3, 1, 0)),
        Err(Error::Mismatch { .. })
    ));
    let mut fold = MixtureFold::new(10, 2, 2, 1e-6).unwrap();
    assert!(matches!(
        fold.push(0, view(2, 10, 0)),
        Err(Error::Invalid(_))
    ));
    let mut fold = MixtureFold::new(10, 2, 2, 1e-6).unwrap();
    assert!(matches!(
        fold.push(0, view(2, 1, 1)),
        Err(Error::Invalid(_))
    ));
    // Nothing past a refused view is half-added: the next good view folds from a clean state.
    let mut fold = MixtureFold::new(10, 2, 2, 1e-6).unwrap();
    fold.push(0, view(2, 3, 0)).unwrap();
    let got = fold.finish(&means_along_x(10, 0.0, 0.0), "m").unwrap();
    assert_eq!(got.gaussian_ids, [3]);
    assert_eq!((got.atoms, got.weights), (vec![0], vec![1.0]));
}

#[test]
fn mixture_with_every_atom_kept_reproduces_reduce() {
    let (n, dim) = (3000u32, 16);
    let dir = tempfile::tempdir().unwrap();
    let means = means_along_x(n, 1.0, -2.0);
    let store = mixture_store(n, dim, usize::MAX, &dir.path().join("a"));
    let exact = reduce(&store, n as usize, dim, ReduceParams::default()).unwrap();
    let mix = reduce_mixture(
        &store,
        n as usize,
        dim,
        ReduceParams::default(),
        usize::MAX,
        "m",
        &means,
    )
    .unwrap();
    assert_eq!(mix.gaussian_ids, exact.ids);
    assert!(mix.len() > 1000);
    assert_eq!(mix.model_id, "m");
    // 4 images x 3 overlapping masks: up to 12 atoms, all of them used by someone.
    assert_eq!(mix.codebook_len(), 12);
    assert!(mix.keep > 3 && mix.keep <= 12);
    for (i, &k) in mix.gaussian_ids.iter().enumerate() {
        assert_eq!(mix.means[i], means[k as usize]);
    }
    let dense = mix.to_dense();
    let max = slag_common::similarity::max_abs_difference(&dense, &exact.vectors);
    // f16 rounding of codebook values and weights of magnitude <= 1: <= 2^-11 each.
    assert!(max < 1e-3, "max |Δ| {max}");
    assert!(max > 0.0, "f16 storage should not be bit-exact against f32");

    // Chunked and spilled: the same mixture.
    let spilling = mixture_store(n, dim, 0, &dir.path().join("b"));
    assert_eq!(spilling.spilled(), 4);
    let tight = ReduceParams {
        accumulator_budget_bytes: 1024 * (dim + 1) * 8,
        ..Default::default()
    };
    let again = reduce_mixture(&spilling, n as usize, dim, tight, usize::MAX, "m", &means).unwrap();
    assert_eq!(again, mix);
}

#[test]
fn both_loop_orders_give_the_same_sums_bit_for_bit() {
    // 3000 Gaussians = 23.4 blocks of REDUCE_BLOCK: a partial last block, and with the tight
    // budget 3 chunks whose edges fall inside blocks of the image-major loop.
    let (n, dim) = (3000u32, 16);
    let dir = tempfile::tempdir().unwrap();
    let means = means_along_x(n, 0.0, 0.0);
    let store = mixture_store(n, dim, usize::MAX, &dir.path().join("a"));
    assert_eq!(store.spilled(), 0);
    for budget in [usize::MAX / 2, 1024 * (dim + 1) * 8] {
        let block_major = ReduceParams {
            accumulator_budget_bytes: budget,
            ..Default::default()
        };
        let image_major = ReduceParams {
            image_major: true,
            ..block_major
        };
        let a = reduce(&store, n as usize, dim, block_major).unwrap();
        let b = reduce(&store, n as usize, dim, image_major).unwrap();
        assert!(a.ids.len() > 1000);
        // Exact equality of the f32 outputs of the f64 sums, not a tolerance.
        assert_eq!(a, b, "budget {budget}");
        let ma = reduce_mixture(&store, n as usize, dim, block_major, 4, "m", &means).unwrap();
        let mb = reduce_mixture(&store, n as usize, dim, image_major, 4, "m", &means).unwrap();
        assert_eq!(ma, mb, "budget {budget}");
    }
    // A contribution of another width fails in both orders, before any sum is handed on.
    let mut bad = mixture_store(n, dim, usize::MAX, &dir.path().join("b"));
    bad.push(ImageContribution {
        dim: dim + 1,
        mask_embeddings: vec![0.0; dim + 1],
        entries: vec![],
    })
    .unwrap();
    for image_major in [false, true] {
        let p = ReduceParams {
            image_major,
            ..Default::default()
        };
        let mut handed = 0;
        let e = reduce_each(&bad, n as usize, dim, p, |_| {
            handed += 1;
            Ok(())
        })
        .unwrap_err();
        assert!(e.to_string().contains("dim 17"), "{e}");
        assert_eq!(handed, 0);
    }
}

/// One case of the fused-tail comparison: a store and the reduction's parameters.
struct TailCase<'a> {
    store: &'a ContributionStore,
    means: &'a [[f32; 3]],
    dim: usize,
    p: ReduceParams,
    keep: usize,
}

impl TailCase<'_> {
    /// An f32 embeddings writer at `path` (f32 rows, so that every bit of the reduction shows).
    fn writer(&self, path: &Path) -> slag_common::embeddings::EmbeddingsWriter {
        use slag_common::embeddings::{EmbeddingsWriter, StoredPrecision};
        EmbeddingsWriter::create(path, self.dim, StoredPrecision::F32).unwrap()
    }

    /// The embeddings file and the mixture's sparse parts of the two separate passes,
    /// `reduce_to_writer` then `reduce_mixture_chunks`.
    fn separate(&self, path: &Path) -> (Vec<u8>, slag_common::mixture::SparseMixture) {
        let (store, means, dim, p) = (self.store, self.means, self.dim, self.p);
        let s = reduce_to_writer(store, means, dim, p, self.writer(path)).unwrap();
        s.writer
            .finish("m", means.len() as u64, "scene.ply")
            .unwrap();
        let (sparse, _) = reduce_mixture_chunks(store, means, dim, p, self.keep, "m").unwrap();
        (std::fs::read(path).unwrap(), sparse)
    }

    /// The same outputs from the one fused pass, `reduce_to_writer_with_mixture`.
    fn fused(&self, path: &Path) -> (Vec<u8>, slag_common::mixture::SparseMixture) {
        let w = self.writer(path);
        let (store, means, dim, p) = (self.store, self.means, self.dim, self.p);
        let m = reduce_to_writer_with_mixture(store, means, dim, p, w, self.keep, "m").unwrap();
        assert!(m.gather_s >= 0.0 && m.gather_s <= m.streamed.reduce_s);
        let s = m.streamed;
        s.writer
            .finish("m", means.len() as u64, "scene.ply")
            .unwrap();
        (std::fs::read(path).unwrap(), m.sparse)
    }
}

#[test]
fn fused_tail_writes_exactly_what_the_two_passes_write() {
    let (n, dim) = (5000u32, 16);
    let dir = tempfile::tempdir().unwrap();
    let means = means_along_x(n, 0.5, -1.0);
    let in_memory = mixture_store(n, dim, usize::MAX, &dir.path().join("mem"));
    let half = in_memory.bytes_in_memory() / 2;
    let mixed = mixture_store(n, dim, half, &dir.path().join("mixed"));
    let spilled = mixture_store(n, dim, 0, &dir.path().join("spilled"));
    assert_eq!(in_memory.spilled(), 0);
    assert!(mixed.spilled() > 0 && mixed.spilled() < mixed.len());
    assert_eq!(spilled.spilled(), spilled.len());
    let exact = reduce(&in_memory, n as usize, dim, ReduceParams::default()).unwrap();
    assert!(exact.ids.len() > 1000 && exact.ids.len() < n as usize);
    // One chunk; chunks of 1024 Gaussians; chunks whose edges differ between the embeddings'
    // pass and the mixture's (whose accumulator is wider per Gaussian).
    let budgets = [usize::MAX / 2, 1024 * (dim + 1) * 8, 2500 * (dim + 1) * 8];
    // 4 images x 3 overlapping masks: at most 12 atoms per Gaussian.
    let keeps = [1, 3, 12, usize::MAX];
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    for (name, store) in [
        ("in memory", &in_memory),
        ("mixed", &mixed),
        ("spilled", &spilled),
    ] {
        for budget in budgets {
            for image_major in [false, true] {
                let p = ReduceParams {
                    accumulator_budget_bytes: budget,
                    image_major,
                    ..Default::default()
                };
                for keep in keeps {
                    let case =
                        format!("{name}, budget {budget}, image-major {image_major}, keep {keep}");
                    let tail = TailCase {
                        store,
                        means: &means,
                        dim,
                        p,
                        keep,
                    };
                    let (file_a, sparse_a) = tail.separate(&a);
                    let (file_b, sparse_b) = tail.fused(&b);
                    assert!(file_a == file_b, "embeddings differ: {case}");
                    assert_eq!(sparse_a, sparse_b, "{case}");
                    assert_eq!(sparse_b.gaussian_ids, exact.ids, "{case}");
                    // keep below the atom counts cuts rows; above them it keeps them whole.
                    let longest = sparse_b.offsets.windows(2).map(|w| w[1] - w[0]).max();
                    let longest = longest.unwrap();
                    assert!(longest <= keep, "{case}");
                    assert!(
                        if keep <= 3 {
                            longest == keep
                        } else {
                            longest > 3
                        },
                        "{case}"
                    );
                    // The stored forms, as `encode` writes them, byte for byte.
                    let ma =
                        slag_common::mixture::MixtureEmbeddings::from_sparse(sparse_a).unwrap();
                    let mb =
                        slag_common::mixture::MixtureEmbeddings::from_sparse(sparse_b).unwrap();
                    ma.write(&a).unwrap();
                    mb.write(&b).unwrap();
                    assert!(
                        std::fs::read(&a).unwrap() == std::fs::read(&b).unwrap(),
                        "{case}"
                    );
                }
            }
        }
    }
}

#[test]
fn fused_tail_rejects_what_the_mixture_rejects() {
    use slag_common::embeddings::{EmbeddingsWriter, StoredPrecision};
    let (n, dim) = (300u32, 8);
    let dir = tempfile::tempdir().unwrap();
    let means = means_along_x(n, 0.0, 0.0);
    let mut store = mixture_store(n, dim, usize::MAX, &dir.path().join("s"));
    let path = dir.path().join("e.safetensors");
    let p = ReduceParams::default();
    let writer = || EmbeddingsWriter::create(&path, dim, StoredPrecision::F16).unwrap();
    assert!(matches!(
        reduce_to_writer_with_mixture(&store, &means, dim, p, writer(), 0, "m"),
        Err(Error::Param {
            name: "mixture_keep",
            ..
        })
    ));
    store
        .push(ImageContribution {
            dim: dim + 1,
            mask_embeddings: vec![0.0; dim + 1],
            entries: vec![],
        })
        .unwrap();
    assert!(matches!(
        reduce_to_writer_with_mixture(&store, &means, dim, p, writer(), 4, "m"),
        Err(Error::Mismatch { .. })
    ));
}

#[test]
fn mixture_observes_what_reduce_observes_and_rejects_bad_input() {
    let dim = 3;
    // Gaussian 0: a=1 on e_x and on -e_x (cancels: unobserved); 1: tiny weight; 2: e_y.
    let store = ContributionStore::in_memory([ImageContribution {
        dim,
        mask_embeddings: vec![1.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
        entries: entries(&[
            (0, 0, 1.0),
            (0, 1, 1.0),
            (1, 2, 1e-9),
            (2, 2, 2.0),
            (2, 0, 0.5),
        ]),
    }]);
    let means = vec![[0.0; 3]; 4];
    let p = ReduceParams::default();
    let exact = reduce(&store, 4, dim, p).unwrap();
    let mix = reduce_mixture(&store, 4, dim, p, 1, "m", &means).unwrap();
    assert_eq!(exact.ids, vec![2]);
    assert_eq!(mix.gaussian_ids, vec![2]);
    // keep 1: only the e_y atom (a=2) survives, and the unused codebook rows are dropped.
    assert_eq!(mix.codebook, vec![0.0, 1.0, 0.0]);
    assert_eq!(
        (mix.keep, mix.atoms.clone(), mix.weights.clone()),
        (1, vec![0], vec![1.0])
    );
    assert!(matches!(
        reduce_mixture(&store, 4, dim, p, 0, "m", &means),
        Err(Error::Param {
            name: "mixture_keep",
            ..
        })
    ));
    assert!(matches!(
        reduce_mixture(&store, 4, dim, p, 2, "m", &means[..3]),
        Err(Error::Internal(_))
    ));
    assert!(matches!(
        reduce_mixture(&store, 4, 4, p, 2, "m", &means),
        Err(Error::Mismatch { .. })
    ));
}

mod mixture_props {
    use super::*;
    use proptest::prelude::*;

    /// Random sparse contributions: per image, random masks and random (gaussian, mask, a).
    fn random_store(n: u32, images: usize, dim: usize, seed: u64) -> Vec<ImageContribution> {
        let mut s = seed | 1;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        (0..images)
            .map(|i| {
                let m = 1 + (next() % 5) as u32;
                let mut entries = Vec::new();
                for g in 0..n {
                    for j in 0..m {
                        if next() % 3 == 0 {
                            // Coarse weights so that ties happen and test the tie rule.
                            let weight = (1 + next() % 40) as f32 / 8.0;
                            entries.push(Entry {
                                gaussian: g,
                                mask: j,
                                weight,
                            });
                        }
                    }
                }
                ImageContribution {
                    dim,
                    mask_embeddings: unit_rows(m as usize, dim, seed ^ ((i as u64 + 1) * 77)),
                    entries,
                }
            })
            .collect()
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(40))]
        #[test]
        fn mixture_scores_and_top_atom(
            n in 1u32..40, images in 1usize..5, dim in 2usize..12, keep in 1usize..6,
            seed in any::<u64>(),
        ) {
            let contribs = random_store(n, images, dim, seed);
            let store = ContributionStore::in_memory(contribs.iter().cloned());
            let means = vec![[0.5f32; 3]; n as usize];
            let p = ReduceParams::default();
            let exact = reduce(&store, n as usize, dim, p).unwrap();
            // Random embeddings may cancel at some keep: then the mixture refuses, typed.
            let mix = match reduce_mixture(&store, n as usize, dim, p, keep, "m", &means) {
                Ok(m) => m,
                Err(e) => {
                    prop_assert!(matches!(e, Error::Invalid(_)));
                    return Ok(());
                }
            };
            prop_assert_eq!(&mix.gaussian_ids, &exact.ids);
            prop_assert!(mix.keep <= keep);
            // Scores equal dense cosine scores of the reconstruction (its rows are unit only up
            // to the f16 rounding of the weights; `scores` divides by their norm).
            let q = unit_rows(1, dim, seed ^ 0xabc);
            let s = mix.scores(&q).unwrap();
            let mut rows = mix.to_dense();
            for r in rows.chunks_exact_mut(dim) {
                let _ = slag_common::similarity::normalize_in_place(r);
            }
            let dense = slag_common::similarity::cosine_scores(&rows, dim, &q).unwrap();
            for (a, b) in s.iter().zip(&dense) {
                prop_assert!((a - b).abs() < 1e-5, "{} vs {}", a, b);
            }
            // The first slot holds the largest a_kj (ties: first image, then lower mask).
            for (i, &k) in mix.gaussian_ids.iter().enumerate() {
                let mut best: Option<(f32, &[f32])> = None;
                for c in &contribs {
                    for e in c.entries.iter().filter(|e| e.gaussian == k) {
                        if best.is_none_or(|(a, _)| e.weight > a) {
                            let j = e.mask as usize;
                            best = Some((e.weight, &c.mask_embeddings[j * dim..(j + 1) * dim]));
                        }
                    }
                }
                let (_, want) = best.unwrap();
                let atom = mix.atoms[i * mix.keep];
                let row = &mix.codebook[atom as usize * dim..(atom as usize + 1) * dim];
                for (a, b) in row.iter().zip(want) {
                    prop_assert_eq!(*a, half::f16::from_f32(*b).to_f32());
                }
                if keep == 1 {
                    // One atom: the reconstruction is that mask embedding (weight 1/‖E‖ ≈ 1).
                    prop_assert!((mix.weights[i] - 1.0).abs() < 2e-3);
                }
            }
        }
    }
}

#[test]
fn store_keeps_entries_as_narrow_columns_and_reduces_them_alike() {
    let dim = 2;
    // One image per mask-index width: the last mask is e_x, every other one e_y.
    for (masks, width) in [(3u32, 1usize), (300, 2), (70_000, 4)] {
        let mut mask_embeddings = vec![0.0f32; masks as usize * dim];
        for j in 0..masks as usize {
            mask_embeddings[j * dim + usize::from(j + 1 < masks as usize)] = 1.0;
        }
        let last = masks - 1;
        let c = ImageContribution {
            dim,
            mask_embeddings,
            // Gaussian 0: a=1 in the last mask (e_x), a=3 in mask 0 (e_y); Gaussian 5: a=2 in
            // the last mask only.
            entries: entries(&[(0, 0, 3.0), (0, last, 1.0), (5, last, 2.0)]),
        };
        let stored = StoredImage::from_contribution(c.clone());
        assert_eq!(stored.len(), 3);
        let back: Vec<Entry> = (0..stored.len()).map(|i| stored.entry(i)).collect();
        assert_eq!(back, c.entries, "{masks} masks");
        assert_eq!(
            stored.bytes(),
            masks as usize * dim * 4 + 3 * (8 + width),
            "{masks} masks"
        );

        let dir = tempfile::tempdir().unwrap();
        let mut spilling = ContributionStore::new(0, dir.path().join("s"));
        spilling.push(c.clone()).unwrap();
        assert_eq!(spilling.spilled(), 1);
        let in_memory = ContributionStore::in_memory([c]);
        let p = ReduceParams::default();
        let r = reduce(&in_memory, 6, dim, p).unwrap();
        assert_eq!(r.ids, vec![0, 5]);
        let n = 10f64.sqrt();
        assert_eq!(
            r.vectors,
            vec![(1.0 / n) as f32, (3.0 / n) as f32, 1.0, 0.0]
        );
        assert_eq!(r.total_weights, vec![4.0, 2.0]);
        assert_eq!(reduce(&spilling, 6, dim, p).unwrap(), r, "{masks} masks");
    }
}

#[test]
fn reduction_chunks_by_output_size_with_the_same_values() {
    let dim = 512;
    let rows = output_chunk_rows(dim);
    assert_eq!(rows % 128, 0);
    assert!(rows * (4 * dim + 8) <= OUTPUT_CHUNK_BYTES);
    let n = 2 * rows + 100;
    // Gaussians on both sides of each chunk edge, in two images.
    let edge = |k: usize| [k - 1, k, k + 1].map(|g| g as u32);
    let ids: Vec<u32> = [edge(rows), edge(2 * rows), [0, 1, n as u32 - 1]]
        .concat()
        .into_iter()
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .collect();
    let image = |seed: u64| ImageContribution {
        dim,
        mask_embeddings: unit_rows(2, dim, seed),
        entries: entries(
            &ids.iter()
                .enumerate()
                .map(|(i, &g)| (g, (i % 2) as u32, 0.5 + i as f32 + seed as f32))
                .collect::<Vec<_>>(),
        ),
    };
    let store = ContributionStore::in_memory([image(1), image(2)]);
    let p = ReduceParams::default();
    let mut chunks = Vec::new();
    let n_chunks = reduce_each(&store, n, dim, p, |parts| {
        chunks.push(Reduced::concat(parts));
        Ok(())
    })
    .unwrap();
    assert_eq!(n_chunks, 3);
    assert_eq!(chunks.len(), 3);
    // The chunks hold ids of their own range, ascending, and together every observed one.
    for (c, part) in chunks.iter().enumerate() {
        assert!(part.ids.iter().all(|&k| (k as usize) / rows == c));
    }
    let streamed = Reduced::concat(chunks);
    assert_eq!(streamed.ids, ids);
    // One chunk of the image-major loop (its accumulator budget holds the whole scene): the same
    // values bit for bit.
    let one = reduce(
        &store,
        n,
        dim,
        ReduceParams {
            image_major: true,
            ..p
        },
    )
    .unwrap();
    assert_eq!(one.chunks, 1);
    assert_eq!(
        (streamed.ids, streamed.vectors, streamed.total_weights),
        (one.ids, one.vectors, one.total_weights)
    );
}
