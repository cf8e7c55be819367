//! The device reduction (label sums kept on the device, reduced there in tiles) against the
//! host pipeline: one device, views split over several devices, the masks' record, and a view
//! past the kept budget.

use super::*;

/// The device reduction (label sums kept on the device, reduced there in tiles) gives the host
/// pipeline's results: the same observed Gaussians, `Σ a_kj`, unit `E_k` within f64 round-off,
/// the same kept mixture pairs and the same dominant masks, with overlapping masks, area
/// weighting, several views and tiles of a few blocks of Gaussians, and with the last views kept
/// on a second device whose views the first imports (a run on several GPUs). The views are kept
/// out of order, as the fronts finish them: the codebook still comes in view order.
#[test]
fn device_reduction_equals_the_host_reduction() {
    use crate::aggregate::{
        ContributionStore, ImageStageParams, MaskWeighting, ReduceParams, StoredImage, reduce,
        reduce_mixture_chunks,
    };
    use crate::pipeline::view_contribution;
    let n = 20_000;
    let g = random_scene(11, n);
    let Some(mut host_gpu) = gpu(&g) else { return };
    let Some(mut dev) = gpu(&g) else { return };
    let Some(mut second) = gpu(&g) else { return };
    let dim = 70; // two values per thread for some threads of the 64-wide workgroup
    assert!(
        dev.keep_on_device(dim, 1 << 30, true),
        "the device (lavapipe in CI) has f64: it keeps the label sums"
    );
    assert!(second.keep_on_device(dim, 1 << 30, true));
    dev.set_reduce_tile_bytes(Some(100_000));
    let params = ImageStageParams {
        mask_weighting: MaskWeighting::Area,
        ..Default::default()
    };
    let mut store = ContributionStore::new(1 << 30, std::env::temp_dir());
    let mut dominants = Vec::new();
    let mut first_view_rows = Vec::new();
    for seed in [2u64, 0, 4, 1, 3] {
        let v = RandomKeptView::new(seed, seed ^ 0xE3B, dim, params);
        let (k, w2c, emb) = (&v.intrinsics, &v.world_to_camera, &v.embeddings);
        let (c, _) =
            view_contribution(&mut host_gpu, k, w2c, &v.masks, emb.clone(), dim, params).unwrap();
        let keeper = if seed < 3 { &mut dev } else { &mut second };
        let view = v.keep_on(keeper, true).expect("kept");
        assert_eq!(
            view.dominant,
            crate::pipeline::pool::dominant_masks(&c.entries),
            "view {seed}"
        );
        dominants.push(view.dominant);
        if seed == 0 {
            first_view_rows = v.embeddings.clone();
        }
        let stored = StoredImage::from_contribution(c);
        store.push_stored_as(seed as usize, stored).unwrap();
    }
    let rp = ReduceParams::default();
    let host = reduce(&store, n, dim, rp).unwrap();
    let keep = 3;
    let means = g.means.clone();
    let (sparse, _) = reduce_mixture_chunks(&store, &means, dim, rp, keep, "m").unwrap();
    let p = DeviceReduce {
        min_total_weight: rp.min_total_weight,
        keep,
        dense: true,
        gaussians: None,
    };
    // One band per batch: the batches after the first continue its views.
    let mut batches = 0;
    while let Some(batch) = second.export_kept_batch(1).unwrap() {
        assert_eq!(batch.continues, batches > 0, "batch {batches}");
        assert_eq!(batch.views.is_empty(), batches > 0, "batch {batches}");
        dev.import_kept(batch).unwrap();
        batches += 1;
    }
    assert!(
        batches >= 2,
        "{batches} batches: a band per batch, two views"
    );
    assert!(second.export_kept().unwrap().is_none(), "keeping stopped");
    let mut tiles = Vec::new();
    let out = dev.reduce_kept(&p, &mut |t| {
        tiles.push(t);
        Ok(())
    });
    let out = out.unwrap();
    assert!(
        out.tiles >= 2,
        "{} tiles: the small tile budget splits the scene",
        out.tiles
    );
    assert_eq!(
        out.codebook[..first_view_rows.len()],
        first_view_rows[..],
        "view 0's masks first, though kept second"
    );
    assert_eq!(
        out.codebook, sparse.codebook,
        "the codebook rows in view order"
    );
    let ids: Vec<u32> = tiles.iter().flat_map(|t| t.ids.clone()).collect();
    assert!(
        host.ids.len() > 100,
        "{} observed Gaussians: too few to test",
        host.ids.len()
    );
    let missing: Vec<&u32> = host
        .ids
        .iter()
        .filter(|k| !ids.contains(k))
        .take(10)
        .collect();
    assert_eq!(
        ids.len(),
        host.ids.len(),
        "observed Gaussians; first missing {missing:?}"
    );
    assert_eq!(ids, host.ids, "observed Gaussians");
    let totals: Vec<f32> = tiles.iter().flat_map(|t| t.total_weights.clone()).collect();
    for (d, h) in totals.iter().zip(&host.total_weights) {
        assert!((d - h).abs() <= 1e-6 * h.abs(), "Σ a {d} vs host {h}");
    }
    let rows: Vec<f32> = tiles.iter().flat_map(|t| t.rows.clone()).collect();
    for (d, h) in rows.iter().zip(&host.vectors) {
        assert!((d - h).abs() <= 2e-7, "E_k value {d} vs host {h}");
    }
    let kept: Vec<Vec<(f32, u32)>> = tiles
        .iter()
        .flat_map(|t| (0..t.ids.len()).map(|i| t.kept_of(i).to_vec()))
        .collect();
    for (i, row) in kept.iter().enumerate() {
        let (a, b) = (sparse.offsets[i], sparse.offsets[i + 1]);
        let mut dev_row: Vec<(u32, f32)> = row.iter().map(|&(w, j)| (j, w)).collect();
        let mut host_row: Vec<(u32, f32)> = sparse.atoms[a..b]
            .iter()
            .copied()
            .zip(sparse.weights[a..b].iter().copied())
            .collect();
        dev_row.sort_by_key(|x| x.0);
        host_row.sort_by_key(|x| x.0);
        assert_eq!(dev_row, host_row, "kept pairs of Gaussian {}", ids[i]);
    }
    assert!(dominants.iter().all(|d| !d.is_empty()));
}

/// The device reduction split by Gaussians over three devices gives what one device gives with
/// every view, bit for bit: each device keeps some of the views, the ranges follow the kept
/// records, every device sends the others their ranges' records a band per batch (so a device
/// takes in batches of two sources interleaved), and each reduces its own range; the same
/// observed Gaussians, `Σ a_kj`, rows and kept pairs, and the same codebook on every device.
#[test]
fn device_reduction_split_over_devices_equals_one_device() {
    use crate::pipeline::devices::{exchange_kept, split_by_records};
    let n = 20_000;
    let g = random_scene(11, n);
    let Some(mut one) = gpu(&g) else { return };
    let mut devices: Vec<GpuRasterizer> = (0..3).filter_map(|_| gpu(&g)).collect();
    let dim = 6;
    for r in devices.iter_mut().chain([&mut one]) {
        assert!(r.keep_on_device(dim, 1 << 30, true), "lavapipe has f64");
        r.set_reduce_tile_bytes(Some(100_000));
    }
    let params = crate::aggregate::ImageStageParams {
        mask_weighting: crate::aggregate::MaskWeighting::Area,
        ..Default::default()
    };
    for seed in [2u64, 0, 4, 1, 5, 3] {
        let v = RandomKeptView::new(seed, seed ^ 0x5B1, dim, params);
        for r in [&mut one, &mut devices[seed as usize % 3]] {
            v.keep_on(r, false).expect("kept");
        }
    }
    let p = DeviceReduce {
        min_total_weight: crate::aggregate::ReduceParams::default().min_total_weight,
        keep: 3,
        dense: true,
        gaussians: None,
    };
    let reduce = |r: &mut dyn WeightRasterizer, p: &DeviceReduce| {
        let mut tiles = Vec::new();
        let out = r.reduce_kept(p, &mut |t| {
            tiles.push(t);
            Ok(())
        });
        (out.unwrap(), tiles)
    };
    let (whole, whole_tiles) = reduce(&mut one, &p);
    let boxed: Vec<Box<dyn WeightRasterizer>> = devices
        .into_iter()
        .map(|r| Box::new(r) as Box<dyn WeightRasterizer>)
        .collect();
    let ranges = split_by_records(&boxed, n).unwrap();
    assert_eq!(ranges.len(), 3);
    assert!(ranges.windows(2).all(|w| w[0].end == w[1].start));
    assert_eq!((ranges[0].start, ranges[2].end), (0, n as u32));
    assert!(
        ranges.iter().all(|r| !r.is_empty()),
        "{ranges:?}: every device reduces some"
    );
    let boxed: Vec<_> = boxed.into_iter().map(std::sync::Mutex::new).collect();
    exchange_kept(&boxed, &ranges, 1).unwrap();
    let mut split_tiles = Vec::new();
    for (r, range) in boxed.into_iter().zip(&ranges) {
        let p = DeviceReduce {
            gaussians: Some((range.start, range.end)),
            ..p
        };
        let (out, tiles) = reduce(&mut **r.lock().unwrap(), &p);
        assert!(
            out.codebook == whole.codebook,
            "every device holds every view"
        );
        assert!(tiles.iter().flat_map(|t| &t.ids).all(|k| range.contains(k)));
        split_tiles.extend(tiles);
    }
    let flat = |tiles: &[KeptTile]| {
        let ids: Vec<u32> = tiles.iter().flat_map(|t| t.ids.clone()).collect();
        let totals: Vec<f32> = tiles.iter().flat_map(|t| t.total_weights.clone()).collect();
        let rows: Vec<f32> = tiles.iter().flat_map(|t| t.rows.clone()).collect();
        let kept: Vec<Vec<(f32, u32)>> = tiles
            .iter()
            .flat_map(|t| (0..t.ids.len()).map(|i| t.kept_of(i).to_vec()))
            .collect();
        (ids, totals, rows, kept)
    };
    let (whole, split) = (flat(&whole_tiles), flat(&split_tiles));
    assert!(whole.0.len() > 100, "{} observed: too few", whole.0.len());
    assert_eq!(split.0, whole.0, "observed Gaussians");
    assert!(split == whole, "Σ a_kj, rows or kept pairs differ");
}

/// The masks' record kept on the device equals the host's record fed with the same views'
/// dominant masks: the same slots in the same order, with more views than slots, views split
/// into several bands of tile rows, views arriving out of order, and the views split over two
/// devices whose records merge (a run on several GPUs).
#[test]
fn device_mask_record_equals_the_host_record() {
    use slag_common::mask_record::MaskRecord;
    let n = 6_000;
    let g = random_scene(12, n);
    let Some(mut heads) = gpu(&g) else { return };
    let Some(mut first) = gpu(&g) else { return };
    let Some(mut second) = gpu(&g) else { return };
    let (dim, slots, views) = (4, 2, 7);
    for r in [&mut heads, &mut first, &mut second] {
        assert!(r.keep_on_device(dim, 1 << 30, true));
    }
    assert!(first.keep_mask_record(slots, views));
    assert!(second.keep_mask_record(slots, views));
    let mut host = MaskRecord::new(n, slots, views).unwrap();
    // Every view of each Gaussian, to count those seen in more views than slots.
    let mut every = MaskRecord::new(n, views, views).unwrap();
    for view in [3usize, 0, 6, 1, 5, 2, 4] {
        let (k, w2c) = test_camera(view as u64);
        let masks = random_masks(view as u64, k.width * 2, k.height * 2, 7);
        let overlap = crate::aggregate::ImageStageParams::default().overlap;
        let labels = crate::aggregate::overlap_labels(&masks, k.width, k.height, overlap).merged();
        let area = crate::aggregate::MaskWeighting::Area;
        let factors = crate::aggregate::image::mask_factors(&masks, area);
        let emb = vec![0.5f32; masks.len() * dim];
        // Odd views in bands of a few tile rows: the same bands on both sides.
        let band_limit = (view % 2 == 1).then_some(2_000);
        let keeper = if view < 4 { &mut first } else { &mut second };
        let on = |r: &mut GpuRasterizer, dominant: bool| {
            r.set_label_records(16, band_limit);
            let kept = KeptMasks {
                masks_of: &labels.masks_of,
                factors: &factors,
                embeddings: &emb,
                dominant,
                view,
            };
            let out = r.label_sums_kept(&k, &w2c, &labels.labels, None, kept);
            out.unwrap().expect("kept").dominant
        };
        let dominant = on(&mut heads, true);
        assert!(!dominant.is_empty(), "view {view} sees Gaussians");
        every.add_view(view, dominant.iter().copied());
        host.add_view(view, dominant);
        assert!(
            on(keeper, false).is_empty(),
            "the record on the device returns none"
        );
    }
    let mut merged = first
        .take_mask_record()
        .unwrap()
        .expect("kept on the device");
    assert!(first.take_mask_record().unwrap().is_none(), "taken once");
    merged
        .merge(&second.take_mask_record().unwrap().expect("kept"))
        .unwrap();
    assert_eq!(merged, host);
    let evicted = (0..n).filter(|&k| every.of(k).count() > slots).count();
    assert!(
        evicted >= 10,
        "{evicted} Gaussians seen in more views than slots: too few"
    );
}

/// A view whose keeping fails on the kept sums' budget (met in a later band of the view) is not
/// kept at all: the views kept before it come back alone, as the host has them
/// ([`KeptExport::into_host_views`]: the same records, label table, factors and embeddings).
#[test]
fn a_view_past_the_kept_budget_is_not_kept_and_the_others_come_back() {
    use crate::aggregate::image::mask_factors;
    use crate::aggregate::{MaskWeighting, overlap_labels};
    let g = random_scene(41, 6000);
    let Some(mut host) = gpu(&g) else { return };
    let Some(mut dev) = gpu(&g) else { return };
    let (k, w2c) = test_camera(41);
    let masks = random_masks(41, k.width * 2, k.height * 2, 7);
    let labels = overlap_labels(&masks, k.width, k.height, Default::default()).merged();
    let factors = mask_factors(&masks, MaskWeighting::Area);
    let dim = 5;
    let emb: Vec<f32> = (0..masks.len() * dim).map(|i| i as f32 * 0.25).collect();
    host.set_label_reduce_on_device(false);
    let raw = host
        .label_sums(&k, &w2c, &labels.labels)
        .unwrap()
        .expect("gpu sums");
    let written = host.last_label_records();
    let reference = raw.reduced();
    host.set_label_reduce_on_device(true);
    let kept = KeptMasks {
        masks_of: &labels.masks_of,
        factors: &factors,
        embeddings: &emb,
        dominant: false,
        view: 0,
    };
    // Bands of about a third of the view: what one view keeps, measured on `host`.
    for r in [&mut host, &mut dev] {
        r.set_label_records(16, Some(written / 3));
    }
    assert!(host.keep_on_device(dim, 1 << 30, true), "lavapipe has f64");
    host.label_sums_kept(&k, &w2c, &labels.labels, None, kept)
        .unwrap()
        .expect("kept");
    // Each band read back on its own, through the one staging buffer.
    host.set_readback_bytes(Some(1));
    let one = host.export_kept().unwrap().expect("kept");
    assert!(one.parts.len() >= 3, "{} bands", one.parts.len());
    let read = one.clone().into_host_views().unwrap().remove(0);
    assert_eq!(read.sums.reduced(), reference, "bands read back one by one");
    let bytes: u64 = one.parts.iter().map(|p| p.1.len() as u64).sum();
    // Room for the view and half of it again: the second view's first band fits, a later one not.
    assert!(dev.keep_on_device(dim, bytes + bytes / 2, true));
    let mut keep = || dev.label_sums_kept(&k, &w2c, &labels.labels, None, kept);
    keep().unwrap().expect("the first view is kept");
    let err = keep().unwrap_err();
    assert!(
        matches!(
            err,
            Error::Limit {
                resource: slag_common::Resource::GpuMemory,
                ..
            }
        ),
        "{err}"
    );
    let views = dev
        .export_kept()
        .unwrap()
        .expect("kept")
        .into_host_views()
        .unwrap();
    assert_eq!(views.len(), 1, "the failed view is not kept");
    let v = views.into_iter().next().unwrap();
    assert!(!v.sums.sorted, "bands of a view come back as records");
    assert_eq!(v.sums.reduced(), reference);
    assert_eq!(
        (v.masks_of, v.factors, v.embeddings),
        (labels.masks_of, factors, emb)
    );
}
