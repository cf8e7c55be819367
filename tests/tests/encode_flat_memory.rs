//! The encode's reduction streams, so its memory stays flat as the views grow: on the device
//! (lavapipe in CI) the kept label sums go in waves within `--device-reduce-memory-mb` and write
//! what keeping every view writes, byte for byte; `--dense` folds each view on the host into f64
//! accumulators tiled by Gaussian ids and spilled past `--accumulator-memory-mb`, and writes the
//! same rows whatever the tiles and batches; on the device and on the host the reduction's own
//! peak (the report's counts, which are deterministic, not the noisy RSS) is no larger with 64
//! views than with 8 but for the codebook.

#![allow(clippy::unwrap_used)]

use slag_common::embeddings::Embeddings;
use slag_encoder::config::{EncodeConfig, ReduceOn};
use slag_encoder::report::Report;
use slag_encoder::synthetic::{SyntheticSceneParams, write_synthetic_scene};
use slag_tests::{encode, graph_config};

/// A terrain of `gaussians` Gaussians seen by `views` views of `width` × `height` (seed 3),
/// written into `dir`.
fn scene(dir: &std::path::Path, gaussians: usize, views: usize, width: u32, height: u32) {
    let p = SyntheticSceneParams {
        gaussians,
        views,
        width,
        height,
        extent: 60.0,
        seed: 3,
        ..Default::default()
    };
    write_synthetic_scene(dir, &p).unwrap();
}

/// Graph masks and color-clip on every view at raster scale 1, the default outputs (the
/// mixture, the masks' record, the segments; no dense file), one front (the views in order),
/// 2 threads, the reduction on `reduce_on` within `budget_mb` MiB on the device.
fn config(
    scene: &std::path::Path,
    out: &std::path::Path,
    reduce_on: ReduceOn,
    budget_mb: usize,
) -> EncodeConfig {
    let mut c = graph_config(scene, out);
    c.raster.scale = 1.0;
    c.output.dense = false;
    c.execution.threads = Some(2);
    c.execution.front_workers = Some(1);
    c.aggregate.reduce_on = reduce_on;
    c.aggregate.device_reduce_memory_mb = Some(budget_mb);
    c
}

/// `SLAG_SKIP_GPU=1` asks to skip the tests on the GPU rasterizer.
fn skip_gpu() -> bool {
    std::env::var("SLAG_SKIP_GPU").is_ok_and(|v| v == "1")
}

/// Bytes of the device's streamed state of `r`'s Gaussians (Σ a_kj and the kept pairs, f32
/// weight + u32 mask id each).
fn device_state_bytes(r: &Report) -> u64 {
    let keep = r.parameters.mixture_keep.unwrap() as u64;
    r.counts.gaussians as u64 * (8 + 8 * keep)
}

/// The device reduced in several waves (`what` names the run).
fn assert_streamed(c: &slag_encoder::report::Counts, what: &str) {
    assert!(
        c.device_reduce && c.device_reduce_fallback.is_none(),
        "{what}"
    );
    assert!(
        c.device_reduce_waves > 1,
        "{what}: {} waves",
        c.device_reduce_waves
    );
}

/// Streamed against all kept on the device: at two budgets small enough that the views go in
/// several waves (fewer with the larger), the mixture, the masks' record and the segments are
/// byte for byte those of the reduction that kept every view to the end, and the device held
/// no more than each budget.
#[test]
fn the_streamed_device_reduction_writes_what_keeping_every_view_writes_at_two_budgets() {
    if skip_gpu() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let scene_dir = dir.path().join("scene");
    scene(&scene_dir, 40_000, 7, 480, 360);
    let run = |name: &str, budget_mb: usize| {
        let out = dir.path().join(name);
        (
            encode(config(&scene_dir, &out, ReduceOn::Device, budget_mb)).unwrap(),
            out,
        )
    };
    let (all, all_dir) = run("all-kept", 1024);
    assert!(all.counts.device_reduce && all.counts.device_reduce_fallback.is_none());
    assert_eq!(
        all.counts.device_reduce_waves, 1,
        "every view kept to the end"
    );
    let kept = all.counts.device_reduce_peak_bytes;
    let state = device_state_bytes(&all);
    assert!(
        all.counts.observed > 1000,
        "{} observed",
        all.counts.observed
    );
    // Budgets that leave about a third and about two thirds of the views' label sums beside
    // the state, rounded up to whole MiB.
    let mib = |bytes: u64| bytes.div_ceil(1 << 20) as usize;
    let small = mib(state + kept / 3);
    let larger = mib(state + 2 * kept / 3);
    assert!(
        ((larger as u64) << 20) < state + kept,
        "{larger} MiB hold every view's {kept} B: the test would stream nothing"
    );
    let mut waves = Vec::new();
    for budget_mb in [small, larger] {
        let (streamed, streamed_dir) = run(&format!("streamed-{budget_mb}"), budget_mb);
        let c = &streamed.counts;
        assert_streamed(c, &format!("{budget_mb} MiB"));
        assert!(
            c.device_reduce_peak_bytes <= (budget_mb as u64) << 20,
            "{budget_mb} MiB: {} B on the device",
            c.device_reduce_peak_bytes
        );
        assert_eq!(c.observed, all.counts.observed, "{budget_mb} MiB");
        for file in [
            "mixture.safetensors",
            "mask-record.safetensors",
            "segments.safetensors",
        ] {
            let read = |d: &std::path::Path| std::fs::read(d.join(file)).unwrap();
            assert!(
                read(&streamed_dir) == read(&all_dir),
                "{budget_mb} MiB: {file} differs"
            );
        }
        waves.push(c.device_reduce_waves);
    }
    assert!(
        waves[1] < waves[0],
        "waves at {small} and {larger} MiB: {waves:?}"
    );
}

/// The reduction's own peak with 64 views against 8 of the same terrain (the same Gaussians,
/// raster and masks per view): on the device, within the same budget at both though 64 views'
/// label sums are many times it; on the host (`--reduce host`, the mixture folded as views
/// come), its peak less the codebook (masks × D × 4 B) grows by at most a quarter, though 64
/// views' `a_kj` are many times it; with `--dense` (the accumulators tiled within 1 MiB, most
/// spilled), likewise, though the accumulators are many times it.
#[test]
fn the_reductions_peak_stays_flat_from_8_to_64_views_but_for_the_codebook() {
    let dir = tempfile::tempdir().unwrap();
    let budget_mb = 2;
    let run = |views: usize, reduce_on: ReduceOn, budget_mb: usize| {
        let scene_dir = dir.path().join(format!("scene-{views}"));
        if !scene_dir.exists() {
            scene(&scene_dir, 10_000, views, 96, 72);
        }
        let out = dir
            .path()
            .join(format!("{views}-{reduce_on:?}-{budget_mb}"));
        let mut c = config(&scene_dir, &out, reduce_on, budget_mb);
        c.segments.enabled = false;
        let r = encode(c).unwrap();
        assert_eq!(r.counts.views_used, views);
        r
    };
    let (host_8, host_64) = (
        run(8, ReduceOn::Host, budget_mb),
        run(64, ReduceOn::Host, budget_mb),
    );
    // Every run writes the same codebook's width (the CLIP's embedding).
    let mixture = dir
        .path()
        .join(format!("8-Host-{budget_mb}"))
        .join("mixture.safetensors");
    let dim = slag_common::mixture::MixtureEmbeddings::read(&mixture)
        .unwrap()
        .dim as u64;
    let beside_codebook = |r: &Report| {
        let c = &r.counts;
        assert!(!c.device_reduce && c.host_fold_peak_bytes > 0);
        c.host_fold_peak_bytes - c.masks as u64 * dim * 4
    };
    let (flat_8, flat_64) = (beside_codebook(&host_8), beside_codebook(&host_64));
    assert!(
        flat_64 * 4 <= flat_8 * 5,
        "host: {flat_64} B beside the codebook with 64 views, {flat_8} B with 8"
    );
    let a_kj_64 = host_64.counts.entries as u64 * 8;
    assert!(
        a_kj_64 > 4 * flat_64,
        "64 views' a_kj ({a_kj_64} B) are several times the fold's peak: the test means something"
    );
    // `--dense`: the accumulators (N × (D + 1) × 8 B) within 1 MiB, the rest spilled, the views
    // swept one at a time (a batch of 1 MiB would hold all 8 small views but not 64); its peak
    // less the codebook grows by at most a quarter too.
    let dense_run = |views: usize| {
        let out = dir.path().join(format!("{views}-dense"));
        let scene_dir = dir.path().join(format!("scene-{views}"));
        let mut c = dense(config(&scene_dir, &out, ReduceOn::Auto, budget_mb), 1, 0);
        c.segments.enabled = false;
        encode(c).unwrap()
    };
    let (dense_8, dense_64) = (dense_run(8), dense_run(64));
    let (dense_flat_8, dense_flat_64) = (beside_codebook(&dense_8), beside_codebook(&dense_64));
    assert!(
        dense_flat_64 * 4 <= dense_flat_8 * 5,
        "dense: {dense_flat_64} B beside the codebook with 64 views, {dense_flat_8} B with 8"
    );
    let accumulators = dense_64.counts.gaussians as u64 * (dim + 1) * 8;
    let spilled = dense_64.counts.dense_fold.unwrap().tiles_spilled;
    assert!(
        accumulators > 4 * dense_flat_64 && spilled > 0,
        "the accumulators ({accumulators} B) are several times the dense fold's peak and spill"
    );
    if skip_gpu() {
        return;
    }
    let budget = (budget_mb as u64) << 20;
    for views in [8, 64] {
        let r = run(views, ReduceOn::Device, budget_mb);
        let c = &r.counts;
        assert_streamed(c, &format!("{views} views"));
        assert!(
            c.device_reduce_peak_bytes <= budget,
            "{views} views: {} B on the device, budget {budget} B",
            c.device_reduce_peak_bytes
        );
    }
    // Kept to the end, 64 views' label sums are several times the budget.
    let all_64 = run(64, ReduceOn::Device, 1024);
    assert_eq!(all_64.counts.device_reduce_waves, 1);
    assert!(
        all_64.counts.device_reduce_peak_bytes > 4 * budget,
        "64 views kept: {} B, the budget {budget} B: the test would stream nothing",
        all_64.counts.device_reduce_peak_bytes
    );
}

/// `c` with the dense file, folded on the host within `accumulator_mb` MiB of f64 accumulators
/// (the tiles past it spilled) and `batch_mb` MiB of views per sweep over the spilled tiles.
fn dense(mut c: EncodeConfig, accumulator_mb: usize, batch_mb: usize) -> EncodeConfig {
    c.output.dense = true;
    c.aggregate.reduce_on = ReduceOn::Auto;
    c.aggregate.accumulator_memory_mb = accumulator_mb;
    c.aggregate.contribution_memory_mb = batch_mb;
    c
}

/// The smallest cosine between the rows of Gaussian `ids[i]` in `a` and `b` (the same ids).
fn least_cosine(a: &Embeddings, b: &Embeddings) -> f64 {
    assert_eq!(a.ids, b.ids, "the same observed Gaussians");
    (0..a.ids.len())
        .map(|i| {
            let (x, y) = (a.vector(i), b.vector(i));
            let dot: f64 = x.iter().zip(y).map(|(p, q)| *p as f64 * *q as f64).sum();
            let norm = |v: &[f32]| v.iter().map(|p| (*p as f64).powi(2)).sum::<f64>().sqrt();
            dot / (norm(x) * norm(y))
        })
        .fold(f64::INFINITY, f64::min)
}

/// `--dense` streamed at two tile and batch sizes (1 MiB of accumulators: tiles of 128
/// Gaussians, a sweep per view; 16 MiB: tiles of 896, the views batched within 1 MiB, which
/// holds all 8 here), each with a
/// budget far below the scene's `N × (D + 1) × 8` B so that most tiles spill: the dense rows
/// within the documented tolerance of the fold that holds every accumulator in memory (cosine
/// ≥ 0.9999 per Gaussian; in fact the same bytes, the f64 sums running in the same order), and
/// the mixture, the masks' record and the segments byte for byte; the spill folder is gone.
#[test]
fn the_dense_fold_writes_the_same_rows_at_two_tile_and_batch_sizes() {
    let dir = tempfile::tempdir().unwrap();
    let scene_dir = dir.path().join("scene");
    scene(&scene_dir, 10_000, 8, 96, 72);
    let run = |name: &str, accumulator_mb: usize, batch_mb: usize| {
        let out = dir.path().join(name);
        let c = dense(
            config(&scene_dir, &out, ReduceOn::Auto, 1024),
            accumulator_mb,
            batch_mb,
        );
        let r = encode(c).unwrap();
        assert!(
            !out.join(".dense-accumulators.partial").exists(),
            "{name}: spill left"
        );
        (r.counts.dense_fold.expect("the dense fold"), out)
    };
    let (held, held_dir) = run("in-memory", 2048, 4096);
    assert_eq!((held.tiles, held.tiles_spilled), (1, 0));
    let load = |d: &std::path::Path| Embeddings::read(&d.join("embeddings.safetensors")).unwrap();
    let want = load(&held_dir);
    assert!(want.ids.len() > 1000, "{} observed", want.ids.len());
    let mut tiles = Vec::new();
    for (accumulator_mb, batch_mb) in [(1, 0), (16, 1)] {
        let what = format!("{accumulator_mb} MiB of accumulators, {batch_mb} MiB of views");
        let (stats, out) = run(
            &format!("{accumulator_mb}-{batch_mb}"),
            accumulator_mb,
            batch_mb,
        );
        // A sweep per view without a batch; with 1 MiB the 8 small views wait for one sweep.
        let sweeps = if batch_mb == 0 { 8..9 } else { 1..8 };
        assert!(
            stats.tiles_spilled * 2 > stats.tiles && sweeps.contains(&stats.batches),
            "{what}: {stats:?}"
        );
        let cosine = least_cosine(&load(&out), &want);
        assert!(cosine >= 0.9999, "{what}: a row at cosine {cosine}");
        for file in [
            "embeddings.safetensors",
            "mixture.safetensors",
            "mask-record.safetensors",
            "segments.safetensors",
        ] {
            let read = |d: &std::path::Path| std::fs::read(d.join(file)).unwrap();
            assert!(read(&out) == read(&held_dir), "{what}: {file} differs");
        }
        tiles.push(stats.tiles);
    }
    assert!(tiles[0] > tiles[1], "tiles at 1 and 16 MiB: {tiles:?}");
}
