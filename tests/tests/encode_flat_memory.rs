//! The encode's reduction streams, so its memory stays flat as the views grow: on the device
//! (lavapipe in CI) the kept label sums go in waves within `--device-reduce-memory-mb` and write
//! what keeping every view writes, byte for byte; on the device and on the host the reduction's
//! own peak (the report's counts, which are deterministic, not the noisy RSS) is no larger with
//! 64 views than with 8 but for the codebook.

#![allow(clippy::unwrap_used)]

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
/// views' `a_kj` are many times it.
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
