//! Tests of the host's streamed dense reduction ([`DenseFold`]).
#![allow(clippy::unwrap_used)]

use std::path::Path;

use slag_common::embeddings::{EmbeddingsWriter, StoredPrecision};
use slag_common::{Error, Resource};

use super::*;
use crate::aggregate::tests::{means_along_x, mixture_view, weights};
use crate::aggregate::{
    ContributionStore, Entry, ImageContribution, ReduceParams, reduce_to_writer_with_mixture,
};

/// 12 views of three overlapping masks each over 300 Gaussians spread across ids
/// `0..140,000` (each Gaussian seen by many views), mask embeddings of width 8.
fn spread_views() -> (usize, usize, Vec<ImageContribution>) {
    let (n, dim) = (140_000usize, 8);
    let images = (1..=12u64)
        .map(|v| {
            let mut pw = weights(30, 20, 300, v);
            pw.ids.iter_mut().for_each(|g| *g *= 467);
            mixture_view(&pw, dim, v)
        })
        .collect();
    (n, dim, images)
}

/// A fold's parameters: `accumulator` and `batch` bytes, spills under `spill_dir`, 3 pairs kept.
fn params(accumulator: usize, batch: usize, spill_dir: &Path) -> DenseFoldParams {
    DenseFoldParams {
        min_total_weight: ReduceParams::default().min_total_weight,
        accumulator_budget_bytes: accumulator,
        batch_budget_bytes: batch,
        spill_dir: spill_dir.to_path_buf(),
        mixture_keep: Some(3),
    }
}

/// The views pushed in a scrambled order (every third first, then the rest backwards) and
/// finished into `<dir>/<name>.safetensors`: the file's bytes, the fold's result.
fn fold_run(
    images: &[ImageContribution],
    (n, dim): (usize, usize),
    p: DenseFoldParams,
    file: &Path,
) -> (Vec<u8>, Option<SparseMixture>, DenseFoldStats) {
    let means = means_along_x(n as u32, 0.5, -1.0);
    let mut fold = DenseFold::new(n, dim, p).unwrap();
    let views = images.len();
    let order = (0..views)
        .filter(|v| v % 3 == 2)
        .chain((0..views).rev().filter(|v| v % 3 != 2));
    for v in order {
        fold.push(v, StoredImage::from_contribution(images[v].clone()))
            .unwrap();
    }
    assert_eq!(fold.len(), views);
    let writer = EmbeddingsWriter::create(file, dim, StoredPrecision::F32).unwrap();
    let done = fold.finish(&means, "m", writer).unwrap();
    assert_eq!(done.observed, done.writer.len());
    done.writer.finish("m", n as u64, "scene.ply").unwrap();
    (std::fs::read(file).unwrap(), done.sparse, done.stats)
}

/// The fold writes, byte for byte, the dense file that keeping every view writes, and the same
/// mixture parts: with every accumulator in memory, and with tiles spilled at two batch sizes
/// (a sweep per view; a sweep per about three views), the views arriving in any order. The spill
/// folder is gone afterwards.
#[test]
fn the_dense_fold_writes_what_keeping_every_view_writes() {
    let (n, dim, images) = spread_views();
    let dir = tempfile::tempdir().unwrap();
    let kept = ContributionStore::in_memory(images.iter().cloned());
    let means = means_along_x(n as u32, 0.5, -1.0);
    let want_file = dir.path().join("kept.safetensors");
    let writer = EmbeddingsWriter::create(&want_file, dim, StoredPrecision::F32).unwrap();
    let rp = ReduceParams::default();
    let want = reduce_to_writer_with_mixture(&kept, &means, dim, rp, writer, 3, "m").unwrap();
    let observed = want.streamed.writer.len();
    want.streamed
        .writer
        .finish("m", n as u64, "scene.ply")
        .unwrap();
    assert!(observed > 250, "{observed} observed");
    let want_bytes = std::fs::read(&want_file).unwrap();
    // 3 tiles of 384 Gaussians in memory (72 B each), the other 362 spilled.
    let small = 4 * 384 * (dim + 1) * 8;
    let view_bytes = images
        .iter()
        .map(|c| StoredImage::from_contribution(c.clone()).bytes())
        .max()
        .unwrap();
    let spill = dir.path().join("spill");
    for (accumulator, batch) in [(usize::MAX, 0), (small, 0), (small, 3 * view_bytes)] {
        let what = format!("accumulator {accumulator} B, batch {batch} B");
        let p = params(accumulator, batch, &spill);
        let file = dir.path().join("fold.safetensors");
        let (bytes, sparse, stats) = fold_run(&images, (n, dim), p, &file);
        assert!(bytes == want_bytes, "{what}: the dense file differs");
        assert_eq!(
            sparse.as_ref(),
            Some(&want.sparse),
            "{what}: the mixture differs"
        );
        assert!(!spill.exists(), "{what}: the spill folder is left");
        if accumulator == usize::MAX {
            assert_eq!((stats.tiles, stats.tiles_spilled), (1, 0), "{what}");
            assert_eq!(stats.batches, images.len(), "{what}: a sweep per view");
            continue;
        }
        assert_eq!((stats.tiles, stats.tiles_spilled), (365, 362), "{what}");
        assert!(stats.spill_bytes_written > 0, "{what}");
        // The accumulators within their budget; beside them the batch (its budget and one view)
        // and the 11 views that arrive before view 0.
        let most = small + batch + view_bytes + 11 * view_bytes;
        assert!(stats.peak_bytes <= most as u64, "{what}: {stats:?}");
        let batches = if batch == 0 { 12..13 } else { 3..7 };
        assert!(batches.contains(&stats.batches), "{what}: {stats:?}");
    }
}

/// A Gaussian whose mask embeddings cancel (`E` and `−E`, equal `a_kj`) has no dense row, and
/// the fold's mixture leaves it out too, as keeping every view does; its neighbour with one mask
/// is written.
#[test]
fn cancelling_masks_leave_a_gaussian_out_of_both_forms() {
    let (n, dim) = (4usize, 2);
    let view = |e: [f32; 2], entries: Vec<(u32, f32)>| ImageContribution {
        dim,
        mask_embeddings: e.to_vec(),
        entries: entries
            .into_iter()
            .map(|(gaussian, weight)| Entry {
                gaussian,
                mask: 0,
                weight,
            })
            .collect(),
    };
    let images = vec![
        view([1.0, 0.0], vec![(1, 3.5), (2, 1.0)]),
        view([-1.0, 0.0], vec![(1, 3.5)]),
    ];
    let dir = tempfile::tempdir().unwrap();
    let p = params(usize::MAX, 0, &dir.path().join("spill"));
    let (_, sparse, _) = fold_run(&images, (n, dim), p, &dir.path().join("e.safetensors"));
    let sparse = sparse.unwrap();
    assert_eq!(sparse.gaussian_ids, vec![2]);
    assert_eq!(sparse.offsets, vec![0, 1]);
    assert_eq!(sparse.means, vec![[2.0, 0.5, -1.0]]);
}

/// A spill folder that cannot be made is a typed I/O error naming it, and the fold leaves no
/// file; a full disk is the disk-space limit saying what to do; a view pushed twice is refused.
#[test]
fn spill_failures_are_typed_errors_and_leave_nothing() {
    let (n, dim, images) = spread_views();
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("a-file");
    std::fs::write(&file, b"not a folder").unwrap();
    let spill = file.join("spill");
    let small = 4 * 384 * (dim + 1) * 8;
    let mut fold = DenseFold::new(n, dim, params(small, 0, &spill)).unwrap();
    let err = fold
        .push(0, StoredImage::from_contribution(images[0].clone()))
        .unwrap_err();
    assert!(
        matches!(&err, Error::Io { path, .. } if path == &spill),
        "{err}"
    );
    drop(fold);
    assert_eq!(std::fs::read(&file).unwrap(), b"not a folder");

    let full = std::io::Error::from(std::io::ErrorKind::StorageFull);
    let err = spill_error(&dir.path().join("tile-000001.f64"), full, 4096);
    assert!(
        matches!(
            &err,
            Error::Limit {
                resource: Resource::DiskSpace,
                ..
            }
        ) && err.to_string().contains("--accumulator-memory-mb"),
        "{err}"
    );
    let sums = TileSums {
        start: 0,
        num: vec![1.0; 8],
        den: vec![2.0],
    };
    let gone = dir.path().join("missing").join("tile-000000.f64");
    assert!(matches!(write_tile(&gone, &sums), Err(Error::Io { .. })));

    let mut fold = DenseFold::new(n, dim, params(usize::MAX, 0, &dir.path().join("s"))).unwrap();
    let view = || StoredImage::from_contribution(images[0].clone());
    fold.push(0, view()).unwrap();
    assert!(matches!(fold.push(0, view()), Err(Error::Internal(_))));
}

/// A view that never comes (view 5 of 12) holds up no later view for good: they wait, and the
/// finish folds them in order, as keeping the 11 views that came writes them.
#[test]
fn a_view_that_never_comes_leaves_the_others_folded_in_order() {
    let (n, dim, mut images) = spread_views();
    let dir = tempfile::tempdir().unwrap();
    let means = means_along_x(n as u32, 0.5, -1.0);
    let mut fold = DenseFold::new(n, dim, params(usize::MAX, 0, &dir.path().join("s"))).unwrap();
    for (v, c) in images.iter().enumerate().filter(|(v, _)| *v != 5) {
        fold.push(v, StoredImage::from_contribution(c.clone()))
            .unwrap();
    }
    let got_file = dir.path().join("got.safetensors");
    let writer = EmbeddingsWriter::create(&got_file, dim, StoredPrecision::F32).unwrap();
    let got = fold.finish(&means, "m", writer).unwrap();
    got.writer.finish("m", n as u64, "scene.ply").unwrap();
    images.remove(5);
    let kept = ContributionStore::in_memory(images);
    let want_file = dir.path().join("want.safetensors");
    let writer = EmbeddingsWriter::create(&want_file, dim, StoredPrecision::F32).unwrap();
    let rp = ReduceParams::default();
    let want = reduce_to_writer_with_mixture(&kept, &means, dim, rp, writer, 3, "m").unwrap();
    want.streamed
        .writer
        .finish("m", n as u64, "scene.ply")
        .unwrap();
    assert!(std::fs::read(&got_file).unwrap() == std::fs::read(&want_file).unwrap());
    assert_eq!(got.sparse, Some(want.sparse));
}
