//! The label sums per (Gaussian, mask label): the GPU's against the host's image stage, the
//! list path for top-k and mask-free views, precomputed sort depths, and the records reduced on
//! the device against the host's reduction.

use super::*;

#[test]
fn gpu_label_sums_equal_the_host_image_stage() {
    use crate::aggregate::{ImageStageParams, image_contribution};
    use crate::pipeline::view_contribution;
    for seed in 0..4u64 {
        let g = random_scene(seed, 600 + seed as usize * 250);
        let (k, w2c) = test_camera(seed);
        let Some(mut gpu) = gpu(&g) else { return };
        // Masks at 2x the raster size: the labels resample them like the host stage does.
        let masks = random_masks(seed, k.width * 2, k.height * 2, 7);
        assert!(masks.len() >= 5, "seed {seed}: too few masks");
        let dim = 3;
        let emb: Vec<f32> = (0..masks.len() * dim).map(|i| i as f32).collect();
        let params = ImageStageParams::default();
        let weights = gpu.rasterize(&k, &w2c).expect("gpu lists");
        let host = image_contribution(&weights, &masks, emb.clone(), dim, params).expect("host");
        assert!(
            host.entries.len() > 100,
            "seed {seed}: too few a_kj to test"
        );
        // Seed 0 starts from a 4-record buffer: the view does not fit and is re-run with room
        // for its count. Seed 2 caps one binding at half the view's records: the view is
        // split into bands of tile rows.
        gpu.set_label_records(4, None);
        let (dev, stats) =
            view_contribution(&mut gpu, &k, &w2c, &masks, emb.clone(), dim, params).expect("dev");
        assert!(stats.device_sums, "the GPU rasterizer sums per label");
        assert!(
            gpu.last_label_retries() > 0,
            "seed {seed}: 4 records cannot hold the view"
        );
        let records = gpu.last_label_records();
        assert!(records > 0, "seed {seed}: no records");
        if seed == 2 {
            gpu.set_label_records(4, Some(records / 2));
            let (banded, _) =
                view_contribution(&mut gpu, &k, &w2c, &masks, emb.clone(), dim, params)
                    .expect("banded");
            // The whole view exceeds one binding, so it was split (at least one re-run).
            assert!(gpu.last_label_retries() >= 1, "seed {seed}: bands split");
            assert_eq!(banded, dev, "seed {seed}: banded label sums differ");
        }
        assert_eq!(dev.mask_embeddings, host.mask_embeddings);
        assert_eq!(
            dev.entries.len(),
            host.entries.len(),
            "seed {seed}: a_kj key sets differ"
        );
        // Contributions counted on the device = list entries of labelled pixels.
        let labels = crate::aggregate::pixel_labels(&masks, k.width, k.height);
        let labelled: u64 = (0..labels.labels.len())
            .filter(|&p| labels.labels[p] != 0)
            .map(|p| u64::from(weights.offsets[p + 1] - weights.offsets[p]))
            .sum();
        assert_eq!(stats.contributions, labelled, "seed {seed}");
        for (d, h) in dev.entries.iter().zip(&host.entries) {
            assert_eq!((d.gaussian, d.mask), (h.gaussian, h.mask), "seed {seed}");
            // Fixed point truncates each weight by < 2^-32; f32 storage rounds both.
            let tol = 1e-6 * h.weight.abs().max(1.0) as f64;
            assert!(
                (d.weight as f64 - h.weight as f64).abs() <= tol,
                "seed {seed}: a_kj({}, {}) {} vs host {}",
                d.gaussian,
                d.mask,
                d.weight,
                h.weight
            );
        }
        // The finest covering mask only, and per-mask weighting, with whole and eroded masks:
        // the same labels, expanded and weighted on the host like the list path's.
        for mask_erode in [0, 2].into_iter().filter(|_| seed == 1) {
            let fine = ImageStageParams {
                overlap: crate::aggregate::MaskOverlap::Finest,
                mask_weighting: crate::aggregate::MaskWeighting::Area,
                mask_erode,
                ..params
            };
            let host = image_contribution(&weights, &masks, emb.clone(), dim, fine).expect("host");
            let (dev, stats) =
                view_contribution(&mut gpu, &k, &w2c, &masks, emb.clone(), dim, fine).expect("d");
            assert!(stats.device_sums);
            assert_eq!(
                dev.entries.len(),
                host.entries.len(),
                "finest: key sets differ"
            );
            for (d, h) in dev.entries.iter().zip(&host.entries) {
                assert_eq!((d.gaussian, d.mask), (h.gaussian, h.mask));
                // The unweighted tolerance, scaled by the mask's factor g (a_kj · g).
                let g = crate::aggregate::MaskWeighting::Area.factor(&masks[h.mask as usize]);
                let tol = 1e-6 * h.weight.abs().max(g) as f64;
                assert!(
                    (d.weight as f64 - h.weight as f64).abs() <= tol,
                    "{d:?} vs {h:?}"
                );
            }
        }
        // Deterministic: integer sums do not depend on the threads' order.
        let (again, _) =
            view_contribution(&mut gpu, &k, &w2c, &masks, emb, dim, params).expect("dev again");
        assert_eq!(again, dev, "seed {seed}: label sums not deterministic");
    }
}

#[test]
fn top_k_and_mask_free_views_take_the_list_path() {
    use crate::aggregate::{ImageStageParams, image_contribution};
    use crate::pipeline::view_contribution;
    let g = random_scene(11, 500);
    let (k, w2c) = test_camera(11);
    let Some(mut gpu) = gpu(&g) else { return };
    let masks = random_masks(11, k.width, k.height, 4);
    let emb = vec![0.5f32; masks.len() * 2];
    let params = ImageStageParams {
        top_k_per_pixel: Some(2),
        ..ImageStageParams::default()
    };
    let (c, stats) =
        view_contribution(&mut gpu, &k, &w2c, &masks, emb.clone(), 2, params).expect("top-k");
    assert!(!stats.device_sums, "top-K needs the per-pixel lists");
    let weights = gpu.rasterize(&k, &w2c).expect("lists");
    assert_eq!(
        c,
        image_contribution(&weights, &masks, emb.clone(), 2, params).expect("host")
    );
    let (empty, stats) = view_contribution(
        &mut gpu,
        &k,
        &w2c,
        &[],
        Vec::new(),
        2,
        ImageStageParams::default(),
    )
    .expect("no masks");
    assert!(empty.entries.is_empty() && !stats.device_sums);
    // More visible Gaussians than raster pixels: the GPU still sums per label, same a_kj.
    let tiny = Intrinsics {
        width: 12,
        height: 9,
        fx: k.fx * 12.0 / f64::from(k.width),
        fy: k.fy * 9.0 / f64::from(k.height),
        cx: k.cx * 12.0 / f64::from(k.width),
        cy: k.cy * 9.0 / f64::from(k.height),
    };
    let (c, stats) = view_contribution(
        &mut gpu,
        &tiny,
        &w2c,
        &masks,
        emb.clone(),
        2,
        ImageStageParams::default(),
    )
    .expect("tiny raster");
    assert!(
        stats.device_sums,
        "500 Gaussians on 108 pixels take the GPU sums"
    );
    let weights = gpu.rasterize(&tiny, &w2c).expect("tiny lists");
    assert!(!c.entries.is_empty());
    let host =
        image_contribution(&weights, &masks, emb, 2, ImageStageParams::default()).expect("host");
    assert_eq!(c.entries.len(), host.entries.len());
    for (d, h) in c.entries.iter().zip(&host.entries) {
        assert_eq!((d.gaussian, d.mask), (h.gaussian, h.mask));
        assert!((d.weight as f64 - h.weight as f64).abs() <= 1e-6 * h.weight.max(1.0) as f64);
    }
    // Labels of the wrong size are refused with a typed error.
    let err = gpu
        .label_sums(&k, &w2c, &[1, 2, 3])
        .expect_err("wrong label count");
    assert!(err.to_string().contains("labels"), "{err}");
}

/// Sort depths made ahead on another thread ([`WeightRasterizer::view_precompute`]) give the
/// same label sums as depths made by the rasterizer itself; depths made for another view are
/// not used (the sums stay this view's); the CPU rasterizer has none to offer.
#[test]
fn precomputed_sort_depths_give_the_same_label_sums() {
    let g = random_scene(23, 800);
    let (k, w2c) = test_camera(23);
    let (_, other) = test_camera(24);
    assert!(CpuRasterizer::new(&g).view_precompute().is_none());
    let Some(mut gpu) = gpu(&g) else { return };
    let labels: Vec<u32> = (0..k.width * k.height).map(|p| 1 + p % 3).collect();
    let own = gpu
        .label_sums(&k, &w2c, &labels)
        .expect("own depths")
        .expect("gpu sums")
        .reduced();
    assert!(!own.is_empty());
    let pre = gpu
        .view_precompute()
        .expect("the GPU rasterizer precomputes");
    let ahead = pre.precompute(&w2c);
    assert_eq!(ahead.sort_depths.len(), g.len());
    for p in [ahead, pre.precompute(&other)] {
        let sums = gpu
            .label_sums_precomputed(&k, &w2c, &labels, Some(p))
            .expect("precomputed depths")
            .expect("gpu sums")
            .reduced();
        assert_eq!(sums, own);
    }
}

/// The label-sum records reduced on the device equal the host's reduction of the records as
/// the kernel wrote them, bit for bit and in the same (Gaussian, label) order: over a view in
/// one band (returned as sorted) and split into bands (merged on the host), with label counts
/// that take one to three radix passes over the label bits, and a repeated view reusing the
/// kept buffers.
#[test]
fn device_reduced_label_sums_equal_the_host_reduction() {
    let g = random_scene(31, 1500);
    let (k, w2c) = test_camera(31);
    let Some(mut gpu) = gpu(&g) else { return };
    for labels_in_use in [3u32, 40, 700] {
        // Stripes and a checkerboard of labels: many labels per tile, some pixels unlabelled.
        let labels: Vec<u32> = (0..k.width * k.height)
            .map(|p| {
                let (x, y) = (p % k.width, p / k.width);
                if (x + 3 * y) % 11 == 0 {
                    0
                } else {
                    1 + (x / 3 + y * 7) % labels_in_use
                }
            })
            .collect();
        gpu.set_label_reduce_on_device(false);
        let raw = gpu
            .label_sums(&k, &w2c, &labels)
            .expect("raw records")
            .expect("gpu sums");
        assert!(!raw.sorted, "raw records are not reduced");
        let written = gpu.last_label_records();
        let reference = raw.clone().reduced();
        assert!(
            (reference.len() as u64) < written,
            "{labels_in_use} labels: some keys span several tiles"
        );
        gpu.set_label_reduce_on_device(true);
        for _ in 0..2 {
            let dev = gpu
                .label_sums(&k, &w2c, &labels)
                .expect("device reduce")
                .expect("gpu sums");
            assert!(
                dev.sorted,
                "{labels_in_use} labels: one band is returned reduced"
            );
            assert_eq!(dev.contributions, raw.contributions);
            assert_eq!(dev.records, reference, "{labels_in_use} labels");
        }
        // Bands of tile rows: each reduced on the device, their keys merged on the host.
        gpu.set_label_records(16, Some(written / 3));
        let banded = gpu
            .label_sums(&k, &w2c, &labels)
            .expect("banded")
            .expect("gpu sums");
        assert!(!banded.sorted, "{labels_in_use} labels: several bands");
        assert_eq!(
            banded.reduced(),
            reference,
            "{labels_in_use} labels: banded"
        );
        gpu.set_label_records(1 << 16, None);
    }
}
