//! The worker pool of `encode` (several front workers, several rasterizers, dynamic scheduling)
//! computes what one front + one rasterizer computes, on a synthetic terrain scene; a failing
//! worker stops the run with nothing that looks complete.

#![allow(clippy::unwrap_used)]

use slag_common::embeddings::Embeddings;
use slag_common::mixture::MixtureEmbeddings;
use slag_encoder::config::ReduceOn;
use slag_encoder::masks::{Mask, MaskGenerator};
use slag_encoder::pipeline::{self, FrontStages};
use slag_encoder::raster::WeightRasterizer;
use slag_encoder::synthetic::{SyntheticSceneParams, write_synthetic_scene};
use slag_tests::{color_clip_visual, encode, graph_config};

/// A temporary folder holding the small synthetic scene in `scene/`; returns the folder and that
/// scene's path.
fn folder_with_small_scene() -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    small_scene(&scene);
    (dir, scene)
}

fn small_scene(dir: &std::path::Path) {
    let p = SyntheticSceneParams {
        gaussians: 40_000,
        views: 7,
        width: 240,
        height: 180,
        extent: 60.0,
        seed: 3,
        ..Default::default()
    };
    write_synthetic_scene(dir, &p).unwrap();
}

fn max_abs_diff(a: &Embeddings, b: &Embeddings) -> f32 {
    assert_eq!(a.ids, b.ids, "observed Gaussians differ");
    slag_common::similarity::max_abs_difference(&a.vectors, &b.vectors)
}

/// Graph masks and color-clip at raster scale 0.5, f32 output, 2 threads.
fn config(scene: &std::path::Path, out: &std::path::Path) -> slag_encoder::config::EncodeConfig {
    let mut c = graph_config(scene, out);
    c.raster.scale = 0.5;
    c.output.precision = slag_common::embeddings::StoredPrecision::F32;
    c.execution.threads = Some(2);
    c
}

#[test]
fn pool_of_fronts_and_rasterizers_equals_one_worker() {
    let (dir, scene) = folder_with_small_scene();
    let one = dir.path().join("one");
    let mut one_front = config(&scene, &one);
    one_front.execution.front_workers = Some(1);
    let r1 = encode(one_front).unwrap();
    assert_eq!(r1.counts.views_used, 7);
    assert!(r1.counts.observed > 10_000, "{}", r1.counts.observed);
    // The models' set-up is timed before the encode and kept in the report written to disk.
    assert!(r1.timings.models > 0.0, "{:?}", r1.timings);
    let written: serde_json::Value =
        serde_json::from_slice(&std::fs::read(one.join("report.json")).unwrap()).unwrap();
    assert_eq!(
        written["timings"]["models"].as_f64(),
        Some(r1.timings.models)
    );

    // Three fronts and two rasterizers (two wgpu devices on the same adapter), built by hand.
    let many = dir.path().join("many");
    let fronts = graph_fronts(&[None, None, None]);
    let params = pipeline::EncodeParams {
        reduce: slag_encoder::aggregate::ReduceParams {
            min_total_weight: 1e-6,
            accumulator_budget_bytes: 64 << 20,
            ..Default::default()
        },
        // Small: the dense accumulators' tiles (40,000 × 513 × 8 B) spill to disk, and the views
        // wait in batches for the sweeps over them.
        contribution_budget_bytes: 1 << 20,
        precision: slag_common::embeddings::StoredPrecision::F32,
        ..pool_params(&many)
    };
    let scene_in = pipeline::SceneInput::new(&scene, None, 1);
    let r2 = pipeline::encode_pool(
        &scene_in,
        fronts,
        |g: &slag_common::scene::Gaussians| rasterizers(2, g),
        &params,
        Default::default(),
    )
    .unwrap();
    assert_eq!(r2.counts.views_used, 7);
    let dense = r2.counts.dense_fold.unwrap();
    assert!(
        dense.tiles_spilled > 0 && dense.spill_bytes_written > 0,
        "the spill path was not exercised: {dense:?}"
    );
    // Every image was done exactly once, by one front and by one rasterizer's three back threads
    // (prepare, raster, image): 3 fronts + 2 × 3 back threads.
    let images_of = |kind: &str| -> usize {
        let workers = r2.workers.iter().filter(|w| w.name.starts_with(kind));
        workers.map(|w| w.images).sum()
    };
    let per_kind = ["front", "prepare", "raster", "image"].map(images_of);
    assert_eq!((per_kind, r2.workers.len()), ([7, 7, 7, 7], 9));
    // Fill and drain times lie inside the wall clock, in order, for every worker that worked.
    for w in r2.workers.iter().filter(|w| w.images > 0) {
        assert!(
            0.0 <= w.first_s && w.first_s <= w.last_s && w.last_s <= r2.timings.total,
            "{w:?} total {}",
            r2.timings.total
        );
        assert!(w.busy_s <= w.last_s - w.first_s + 1e-3, "{w:?}");
    }
    // The GPU rasterizers report their phases summed over their images; fronts report none.
    for w in &r2.workers {
        match (&w.raster_phases_ms, w.name.starts_with("raster")) {
            (Some(p), true) => assert!(
                w.images == 0 || (p.project_ms > 0.0 && p.write_ms > 0.0),
                "{w:?}"
            ),
            (None, false) => {}
            _ => panic!("phases on the wrong worker: {w:?}"),
        }
    }
    assert_eq!(r2.counts.masks, r1.counts.masks);
    assert_eq!(r2.counts.entries, r1.counts.entries);
    // The queue between the stages: 3 unbound fronts share one queue of 6 slots; an image held
    // by a front waiting for a slot counts, so at most 6 + 3 images wait at once. Their masks
    // travel run-length encoded: an image costs less than its masks' bytes at one per pixel.
    let q = r2.counts.queue.clone().unwrap();
    assert_eq!(q.capacity_items, 6);
    assert!((1..=9).contains(&q.high_water_items), "{q:?}");
    assert!(q.high_water_bytes >= q.largest_item_bytes, "{q:?}");
    assert!(
        q.high_water_bytes <= q.high_water_items as u64 * q.largest_item_bytes,
        "{q:?}"
    );
    let masks_per_image = r2.counts.masks as u64 / 7;
    assert!(
        q.largest_item_bytes < masks_per_image * 240 * 180 / 4,
        "{q:?}, {masks_per_image} masks per image"
    );
    assert!(r1.counts.queue.is_some());

    let e1 = Embeddings::read(&one.join("embeddings.safetensors")).unwrap();
    let e2 = Embeddings::read(&many.join("embeddings.safetensors")).unwrap();
    // Same sums in another order: f64 accumulation, stored f32.
    let d = max_abs_diff(&e1, &e2);
    assert!(d <= 1e-6, "max |Δ| {d}");
    assert!(many.join("report.json").exists());
}

/// Front workers with graph masks and color-clip on the CPU, bound to the GPUs `gpus` names.
fn graph_fronts(gpus: &[Option<usize>]) -> Vec<FrontStages> {
    gpus.iter()
        .map(|&gpu| FrontStages {
            masks: Box::new(slag_encoder::masks::graph::GraphSegmenter::new(
                Default::default(),
            )),
            crops: Box::new(
                slag_encoder::clip::ClipVisual::with_threads(
                    &color_clip_visual(),
                    slag_common::onnx::ExecutionProvider::Cpu,
                    32,
                    1,
                )
                .unwrap(),
            ),
            gpu,
        })
        .collect()
}

/// The pool's settings for a run into `out`: raster scale 0.5, f16 rows, no side outputs.
fn pool_params(out: &std::path::Path) -> pipeline::EncodeParams {
    pipeline::EncodeParams {
        raster_scale: 0.5,
        image_stage: Default::default(),
        reduce: Default::default(),
        contribution_budget_bytes: 1 << 30,
        precision: slag_common::embeddings::StoredPrecision::F16,
        out_dir: out.to_path_buf(),
        progress: false,
        dense: true,
        mixture_keep: None,
        levels: false,
        mask_record_slots: None,
        reduce_on: slag_encoder::config::ReduceOn::Auto,
        device_reduce_budget_bytes: 1 << 30,
    }
}

/// `n` GPU rasterizers over `g` (wgpu devices on one adapter).
fn rasterizers(
    n: usize,
    g: &slag_common::scene::Gaussians,
) -> slag_common::Result<Vec<Box<dyn WeightRasterizer>>> {
    rasterizers_set_up(n, g, |_| {})
}

/// [`rasterizers`], each set up by `set_up` first.
fn rasterizers_set_up(
    n: usize,
    g: &slag_common::scene::Gaussians,
    set_up: impl Fn(&mut slag_encoder::raster::GpuRasterizer),
) -> slag_common::Result<Vec<Box<dyn WeightRasterizer>>> {
    (0..n)
        .map(|_| {
            let mut r = slag_encoder::raster::GpuRasterizer::new(g)?;
            set_up(&mut r);
            Ok(Box::new(r) as Box<dyn WeightRasterizer>)
        })
        .collect()
}

/// Fronts bound to GPUs hand their images to their own GPU's rasterizer only (one queue per
/// GPU, two slots each), and the result equals an unbound run's.
#[test]
fn fronts_bound_to_gpus_feed_their_own_gpus_rasterizer() {
    let (dir, scene) = folder_with_small_scene();
    let input = pipeline::SceneInput::new(&scene, None, 1);
    let run = |gpus: &[Option<usize>], name: &str| {
        let out = dir.path().join(name);
        let r = pipeline::encode_pool(
            &input,
            graph_fronts(gpus),
            |g: &slag_common::scene::Gaussians| rasterizers(2, g),
            &pool_params(&out),
            Default::default(),
        )
        .unwrap();
        (
            r,
            Embeddings::read(&out.join("embeddings.safetensors")).unwrap(),
        )
    };
    let (bound, e_bound) = run(&[Some(0), Some(1), Some(1)], "bound");
    let (free, e_free) = run(&[None, None, None], "free");
    let images = |name: &str| -> usize {
        let w = bound.workers.iter().find(|w| w.name.starts_with(name));
        w.unwrap_or_else(|| panic!("no worker {name}")).images
    };
    assert_eq!(images("front-0") + images("front-1") + images("front-2"), 7);
    for (g, fronts) in [
        (0, images("front-0")),
        (1, images("front-1") + images("front-2")),
    ] {
        for stage in ["prepare", "raster", "image"] {
            assert_eq!(images(&format!("{stage}-{g}")), fronts, "{stage}-{g}");
        }
    }
    assert_eq!(bound.counts.queue.as_ref().unwrap().capacity_items, 4);
    assert_eq!(free.counts.queue.as_ref().unwrap().capacity_items, 6);
    assert_eq!(bound.counts.entries, free.counts.entries);
    let d = max_abs_diff(&e_bound, &e_free);
    assert!(d <= 1e-3, "max |Δ| {d} (f16 rows)");
}

/// Set once the failing front has failed; the other front waits for it before its first image,
/// so the failure happens while the pool runs whatever the scheduling (on a loaded machine the
/// healthy front could otherwise take every image before the failing one reached its `n`-th).
type FailureGate = std::sync::Arc<(std::sync::Mutex<bool>, std::sync::Condvar)>;

/// Fails on the `n`-th image it sees, then opens `gate`.
struct FailingMasks {
    left: usize,
    gate: FailureGate,
}

impl MaskGenerator for FailingMasks {
    fn name(&self) -> &str {
        "failing"
    }
    fn generate(&mut self, image: &image::RgbImage) -> slag_common::Result<Vec<Mask>> {
        if self.left == 0 {
            let (failed, cv) = &*self.gate;
            *failed.lock().unwrap() = true;
            cv.notify_all();
            return Err(slag_common::Error::Invalid("injected mask failure".into()));
        }
        self.left -= 1;
        slag_encoder::masks::graph::GraphSegmenter::new(Default::default()).generate(image)
    }
}

/// Graph masks that wait (at most 120 s) until the failing front has failed.
struct GatedMasks {
    gate: FailureGate,
}

impl MaskGenerator for GatedMasks {
    fn name(&self) -> &str {
        "gated"
    }
    fn generate(&mut self, image: &image::RgbImage) -> slag_common::Result<Vec<Mask>> {
        let (failed, cv) = &*self.gate;
        let guard = failed.lock().unwrap();
        drop(
            cv.wait_timeout_while(guard, std::time::Duration::from_secs(120), |f| !*f)
                .unwrap(),
        );
        slag_encoder::masks::graph::GraphSegmenter::new(Default::default()).generate(image)
    }
}

/// An encode of `scene` with `params` through `fronts` and one GPU rasterizer: its report.
fn encode_on_one_rasterizer(
    scene: &std::path::Path,
    fronts: Vec<FrontStages>,
    params: &pipeline::EncodeParams,
) -> slag_common::Result<slag_encoder::report::Report> {
    pipeline::encode_pool(
        &pipeline::SceneInput::new(scene, None, 1),
        fronts,
        |g: &slag_common::scene::Gaussians| rasterizers(1, g),
        params,
        Default::default(),
    )
}

#[test]
fn a_failing_worker_stops_the_pool_and_nothing_looks_complete() {
    let (dir, scene) = folder_with_small_scene();
    let out = dir.path().join("out");
    let clip = || {
        Box::new(
            slag_encoder::clip::ClipVisual::with_threads(
                &color_clip_visual(),
                slag_common::onnx::ExecutionProvider::Cpu,
                32,
                1,
            )
            .unwrap(),
        )
    };
    let gate = FailureGate::default();
    let fronts = vec![
        FrontStages {
            masks: Box::new(FailingMasks {
                left: 2,
                gate: gate.clone(),
            }),
            crops: clip(),
            gpu: None,
        },
        FrontStages {
            masks: Box::new(GatedMasks { gate }),
            crops: clip(),
            gpu: None,
        },
    ];
    let params = pool_params(&out);
    let err = encode_on_one_rasterizer(&scene, fronts, &params).unwrap_err();
    assert!(err.to_string().contains("injected mask failure"), "{err}");
    assert!(!out.join("embeddings.safetensors").exists());
    assert!(!out.join("report.json").exists());
}

/// Masks that find nothing in any image.
struct NoMasks;

impl MaskGenerator for NoMasks {
    fn name(&self) -> &str {
        "none"
    }
    fn generate(&mut self, _image: &image::RgbImage) -> slag_common::Result<Vec<Mask>> {
        Ok(Vec::new())
    }
}

/// Views whose masks observe none of the Gaussians make an empty map: the encode fails with
/// the typed error that says so, and writes neither the embeddings, the mixture nor the report.
#[test]
fn an_encode_that_observes_nothing_fails_and_writes_nothing() {
    let (dir, scene) = folder_with_small_scene();
    let out = dir.path().join("out");
    let mut fronts = graph_fronts(&[None]);
    fronts[0].masks = Box::new(NoMasks);
    let params = pipeline::EncodeParams {
        mixture_keep: Some(4),
        ..pool_params(&out)
    };
    let err = encode_on_one_rasterizer(&scene, fronts, &params).unwrap_err();
    assert!(
        matches!(
            err,
            slag_common::Error::Unobserved {
                stage: slag_common::Observation::Encode,
                observed: 0,
                gaussians: 40_000,
                ..
            }
        ),
        "{err}"
    );
    for file in [
        "embeddings.safetensors",
        "mixture.safetensors",
        "report.json",
    ] {
        assert!(!out.join(file).exists(), "{file} written");
    }
}

/// The rasterizers are set up while the fronts already run: a set-up that fails, or that yields
/// fewer rasterizers than the GPUs the fronts are bound to, stops the fronts (no hang) and
/// returns the error; nothing is written.
#[test]
fn a_rasterizer_set_up_failure_stops_the_running_fronts() {
    let (dir, scene) = folder_with_small_scene();
    let (fronts, params) = (graph_fronts, pool_params);
    let input = pipeline::SceneInput::new(&scene, None, 1);

    let out = dir.path().join("out-err");
    let err = pipeline::encode_pool(
        &input,
        fronts(&[None, None]),
        |_: &slag_common::scene::Gaussians| {
            Err(slag_common::Error::Gpu("injected set-up failure".into()))
        },
        &params(&out),
        Default::default(),
    )
    .unwrap_err();
    assert!(err.to_string().contains("injected set-up failure"), "{err}");
    assert!(!out.join("embeddings.safetensors").exists());
    assert!(!out.join("report.json").exists());

    // Fronts bound to GPUs 0 and 1, one rasterizer: an internal fault, not a hang.
    let out = dir.path().join("out-short");
    let err = pipeline::encode_pool(
        &input,
        fronts(&[Some(0), Some(1)]),
        |g: &slag_common::scene::Gaussians| rasterizers(1, g),
        &params(&out),
        Default::default(),
    )
    .unwrap_err();
    assert!(
        matches!(err, slag_common::Error::Internal(_)) && err.to_string().contains("2 GPUs"),
        "{err}"
    );
    assert!(!out.join("embeddings.safetensors").exists());
}

/// The reduction on the GPU (the label sums kept on the device, reduced there in f64; lavapipe
/// in CI) writes what the host's f64 reduction writes (here the dense fold of `--dense`, whose
/// mixture is restricted to the Gaussians of its rows): the same observed Gaussians, and byte
/// for byte the same mixture, masks' record and segments. `--reduce device` with `--dense` is
/// refused: the dense file is always folded on the host as the views come.
#[test]
fn the_device_reduction_writes_what_the_host_reduction_writes() {
    let Some((dir, scene)) = scene_for_the_gpu() else {
        return;
    };
    let config_for = |name: &str, reduce_on: ReduceOn, dense: bool| {
        let out = dir.path().join(name);
        let mut c = config(&scene, &out);
        c.execution.front_workers = Some(1);
        c.aggregate.reduce_on = reduce_on;
        c.output.dense = dense;
        (c, out)
    };
    let run = |name: &str, reduce_on: ReduceOn, dense: bool| {
        let (c, out) = config_for(name, reduce_on, dense);
        (encode(c).unwrap(), out)
    };
    let (host, host_dir) = run("host", ReduceOn::Host, true);
    // Without the dense file (the default outputs) no row is made, the rest is the same.
    let (dev, dev_dir) = run("device-mixture", ReduceOn::Device, false);
    assert!(!dev_dir.join("embeddings.safetensors").exists());
    assert!(!host.counts.device_reduce && dev.counts.device_reduce);
    assert!(
        host.counts.dense_fold.is_some(),
        "the host folded the dense rows"
    );
    assert!(
        host.counts.entries > 0 && dev.counts.entries == 0,
        "no a_kj reached the host"
    );
    assert_eq!(dev.counts.observed, host.counts.observed);
    assert!(
        host.counts.observed > 1000,
        "{} observed",
        host.counts.observed
    );
    for file in [
        "mixture.safetensors",
        "mask-record.safetensors",
        "segments.safetensors",
    ] {
        let read = |d: &std::path::Path| std::fs::read(d.join(file)).unwrap();
        assert!(read(&host_dir) == read(&dev_dir), "{file} differs");
    }
    let (c, out) = config_for("device-dense", ReduceOn::Device, true);
    let err = encode(c).unwrap_err().to_string();
    assert!(err.contains("--dense") && err.contains("reduce"), "{err}");
    assert!(!out.join("embeddings.safetensors").exists());
}

/// The small scene's folder for a test on the GPU rasterizer; `None` where `SLAG_SKIP_GPU=1`
/// asks to skip those.
fn scene_for_the_gpu() -> Option<(tempfile::TempDir, std::path::PathBuf)> {
    let skip = std::env::var("SLAG_SKIP_GPU").is_ok_and(|v| v == "1");
    (!skip).then(folder_with_small_scene)
}

/// The masks' record an encode hands to its tail.
type TailRecord = Option<std::sync::Arc<slag_common::mask_record::MaskRecord>>;

/// An encode of `input` with `params` over graph fronts bound to `gpus` and `n_rasterizers`
/// GPU rasterizers that keep views for `auto` also on a CPU device (lavapipe in CI): its
/// report and the masks' record it handed to its tail.
fn keeping_run(
    input: &pipeline::SceneInput,
    gpus: &[Option<usize>],
    n_rasterizers: usize,
    params: &pipeline::EncodeParams,
) -> (
    slag_common::Result<slag_encoder::report::Report>,
    TailRecord,
) {
    let mut record = None;
    let report = pipeline::encode_pool_with(
        input,
        graph_fronts(gpus),
        |g: &slag_common::scene::Gaussians| {
            rasterizers_set_up(n_rasterizers, g, |r| r.set_cpu_adapter(false))
        },
        params,
        Default::default(),
        |r, _| record = r,
    );
    (report, record)
}

/// Two GPUs that both keep their views (`--reduce device`, fronts bound to each, the default
/// outputs) write what the host's reduction writes (with `--dense`, folded on the host): each
/// reduces a range of Gaussians after they swapped records. The same mixture byte for byte (the
/// views in view order, whichever device kept them), the same masks' record, and no `a_kj` on
/// the host.
#[test]
fn two_devices_reduce_their_kept_views_as_one() {
    let Some((dir, scene)) = scene_for_the_gpu() else {
        return;
    };
    let input = pipeline::SceneInput::new(&scene, None, 1);
    let run = |name: &str, reduce_on: ReduceOn, dense: bool| {
        let out = dir.path().join(name);
        let params = pipeline::EncodeParams {
            mixture_keep: Some(4),
            mask_record_slots: Some(slag_common::mask_record::DEFAULT_SLOTS),
            reduce_on,
            dense,
            ..pool_params(&out)
        };
        let (report, record) = keeping_run(&input, &[Some(0), Some(1)], 2, &params);
        (report.unwrap(), out, record)
    };
    let (host, host_dir, host_record) = run("host", ReduceOn::Host, true);
    let (split, split_dir, split_record) = run("device-split", ReduceOn::Device, false);
    assert!(
        split.counts.device_reduce && split.counts.entries == 0,
        "reduced on the device"
    );
    let images = |name: &str| {
        split
            .workers
            .iter()
            .find(|w| w.name.starts_with(name))
            .unwrap()
            .images
    };
    assert!(
        images("raster-0") > 0 && images("raster-1") > 0,
        "both devices kept views"
    );
    assert_eq!(split.counts.observed, host.counts.observed);
    let ids = |d: &std::path::Path| {
        MixtureEmbeddings::read(&d.join("mixture.safetensors"))
            .unwrap()
            .gaussian_ids
    };
    assert_eq!(ids(&split_dir), ids(&host_dir), "observed Gaussians");
    let read = |d: &std::path::Path| std::fs::read(d.join("mixture.safetensors")).unwrap();
    assert!(split_record.is_some(), "masks' record");
    assert_eq!(split.counts.device_reduce_gpus, 2, "both reduce");
    assert!(
        !split_dir.join("embeddings.safetensors").exists(),
        "no dense file asked"
    );
    assert!(
        read(&split_dir) == read(&host_dir),
        "mixture differs with the reduction split"
    );
    assert!(
        split_record == host_record,
        "masks' record with the reduction split"
    );
}

/// Kept label sums that pass the device's budget after a few views: the reduction streams (the
/// kept views folded a wave at a time into a state per Gaussian; with two rasterizers, each
/// folding its share of the Gaussians, the views sent between them as they come) and writes
/// what `--reduce host` writes, byte for byte; with two whose shares' state does not fit the
/// budget, `--reduce auto` gives way to the host's reduction and writes the same (their views
/// reach the store in any order), with the same masks' record and `a_kj` count; the report
/// says which. `--reduce device` with a
/// budget the state does not fit fails with the budget's typed error.
#[test]
fn a_reduction_past_the_device_budget_streams_or_gives_way_to_the_host() {
    let Some((dir, scene)) = scene_for_the_gpu() else {
        return;
    };
    let input = pipeline::SceneInput::new(&scene, None, 1);
    // About two views' kept label sums of this scene.
    let budget = 1000 << 10;
    let run_with = |name: &str, reduce_on: ReduceOn, n_rasterizers: usize, budget: u64| {
        let out = dir.path().join(name);
        // The default outputs (the mixture, no dense file): what `auto` reduces on the device.
        let params = pipeline::EncodeParams {
            dense: false,
            mixture_keep: Some(4),
            mask_record_slots: Some(slag_common::mask_record::DEFAULT_SLOTS),
            reduce_on,
            device_reduce_budget_bytes: budget,
            ..pool_params(&out)
        };
        let (report, record) = keeping_run(&input, &[None], n_rasterizers, &params);
        (report, out.join("mixture.safetensors"), record)
    };
    let (host, host_mixture, host_record) = run_with("host", ReduceOn::Host, 1, budget);
    let host = host.unwrap();
    // The streamed reduction's state (Σ a_kj and 4 kept pairs per Gaussian) comes out of the
    // budget first: about two views' label sums are left beside it.
    let two_views = budget;
    let budget = two_views + host.counts.gaussians as u64 * (8 + 8 * 4);
    // Below the state of the larger of two rasterizers' shares, neither streams: each keeps
    // every view, and about two views pass their budget.
    let kept_to_the_end = two_views.min(host.counts.gaussians as u64 * (8 + 8 * 4) / 2);
    assert!(host.counts.device_reduce_fallback.is_none());
    // `--reduce host` with only the mixture folds each view into its state as it comes: no view
    // is kept, none spills.
    assert!(host.counts.host_fold_peak_bytes > 0 && host.counts.spilled_images == 0);
    assert!(
        host.counts.observed > 1000,
        "{} observed",
        host.counts.observed
    );
    let runs = [
        ("auto", 1, budget),
        ("device-streamed", 1, budget),
        ("device-streamed-two", 2, budget),
        ("auto-two", 2, kept_to_the_end),
    ];
    for (name, n_rasterizers, budget) in runs {
        let reduce_on = if name.starts_with("device") {
            ReduceOn::Device
        } else {
            ReduceOn::Auto
        };
        let (auto, auto_mixture, auto_record) = run_with(name, reduce_on, n_rasterizers, budget);
        let auto = auto.unwrap();
        let read = |p: &std::path::Path| std::fs::read(p).unwrap();
        assert!(
            auto_record.is_some() && auto_record == host_record,
            "{name}: masks' record"
        );
        assert!(
            read(&auto_mixture) == read(&host_mixture),
            "{name}: mixture differs"
        );
        if budget != kept_to_the_end {
            assert!(auto.counts.device_reduce_fallback.is_none(), "{name}");
            assert!(auto.counts.device_reduce, "{name}: the device reduced");
            assert!(
                auto.counts.device_reduce_waves >= 2,
                "{name}: {} waves",
                auto.counts.device_reduce_waves
            );
            assert!(
                auto.counts.device_reduce_peak_bytes <= budget,
                "{name}: {} B at most on the device, within {budget}",
                auto.counts.device_reduce_peak_bytes
            );
            assert_eq!(auto.counts.observed, host.counts.observed, "{name}");
            continue;
        }
        let fallback = auto
            .counts
            .device_reduce_fallback
            .clone()
            .expect("gave way");
        assert!(
            (1..7).contains(&fallback.views_brought_back),
            "{name}: {fallback:?}"
        );
        assert!(
            fallback.reason.contains("--device-reduce-memory-mb"),
            "{name}: {fallback:?}"
        );
        assert!(!auto.counts.device_reduce, "{name}: the host reduced");
        assert_eq!(
            auto.counts.entries, host.counts.entries,
            "{name}: a_kj on the host"
        );
        assert_eq!(auto.counts.observed, host.counts.observed, "{name}");
        let ids = |p: &std::path::Path| MixtureEmbeddings::read(p).unwrap().gaussian_ids;
        assert_eq!(
            ids(&auto_mixture),
            ids(&host_mixture),
            "{name}: observed Gaussians"
        );
    }
    // A budget the state of the streamed reduction does not fit: every view is kept, and the
    // first one passes it.
    let (device, device_mixture, _) = run_with("device", ReduceOn::Device, 1, 4 << 10);
    let err = device.unwrap_err();
    assert!(
        matches!(
            err,
            slag_common::Error::Limit {
                resource: slag_common::Resource::GpuMemory,
                ..
            }
        ) && err.to_string().contains("--device-reduce-memory-mb"),
        "{err}"
    );
    assert!(!device_mixture.exists());
}
