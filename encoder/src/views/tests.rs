//! Coverage selection on a synthetic scene (a ring of cameras over a terrain), with the CPU
//! reference rasterizer.

#![allow(clippy::unwrap_used)]

use std::sync::OnceLock;

use glam::DVec3;
use slag_common::camera::View;
use slag_common::scene::Gaussians;

use super::*;
use crate::pipeline::SceneInput;
use crate::raster::{CpuRasterizer, WeightRasterizer};
use crate::synthetic::{SyntheticSceneParams, write_synthetic_scene};

/// 48 views on a ring (7.5° apart), 4000 Gaussians, 96 × 72 images; written once.
fn scene_dir() -> &'static std::path::Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let p = SyntheticSceneParams {
            gaussians: 4000,
            views: 48,
            width: 96,
            height: 72,
            extent: 10.0,
            seed: 7,
            ..Default::default()
        };
        write_synthetic_scene(dir.path(), &p).unwrap();
        dir
    })
    .path()
}

/// The scene with every 4th view (index ≡ 2 mod 4) held out: its Gaussians and training views.
fn training() -> (Gaussians, Vec<View>, Vec<View>) {
    let mut input = SceneInput::new(scene_dir(), None, 1);
    input.hold_out_every = Some(4);
    let (g, training, total) = input.load().unwrap();
    assert_eq!(total, 48);
    let all = slag_common::camera::load_views(scene_dir()).unwrap();
    (g, training, all)
}

/// Every view that adds a pair (no stopping rule), at full resolution, at a floor of one pixel.
fn rule() -> CoverageRule {
    CoverageRule {
        min_weight: Some(1.0),
        raster_scale: 1.0,
        target: 1.0,
        min_gain: 0.0,
        ..CoverageRule::default()
    }
}

/// The default stopping rule, at full resolution.
fn default_rule() -> ViewSelection {
    ViewSelection {
        coverage: CoverageRule {
            raster_scale: 1.0,
            ..CoverageRule::default()
        },
        ..coverage_selection()
    }
}

fn coverage_selection() -> ViewSelection {
    ViewSelection {
        mode: SelectionMode::Coverage,
        count: None,
        coverage: rule(),
    }
}

fn cpu(g: &Gaussians) -> Vec<Box<dyn WeightRasterizer>> {
    vec![Box::new(CpuRasterizer::new(g))]
}

/// Angle between the directions from two camera centres to a point, degrees.
fn angle(p: DVec3, a: DVec3, b: DVec3) -> f64 {
    (p - a)
        .normalize()
        .dot((p - b).normalize())
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

#[test]
fn the_pass_keeps_the_gaussians_a_view_gives_enough_weight() {
    let (g, views, _) = training();
    let r = rule();
    let floor = r.min_weight.unwrap();
    let cov = coverage::measure(&mut cpu(&g), &views[..2], g.len(), &r).unwrap();
    assert_eq!(cov.floor(), (floor, FloorSource::Given));
    let mut raster = CpuRasterizer::new(&g);
    let mut footprint = vec![0f64; g.len()];
    for (v, view) in views[..2].iter().enumerate() {
        let w = raster
            .rasterize(&view.intrinsics, &view.world_to_camera)
            .unwrap();
        let mut total = vec![0f64; g.len()];
        for (&id, &wt) in w.ids.iter().zip(&w.weights) {
            total[id as usize] += f64::from(wt);
        }
        let want: Vec<usize> = (0..g.len()).filter(|&k| total[k] >= floor).collect();
        assert!(!want.is_empty() && want.len() < g.len());
        assert_eq!(cov.seen_by(v), want, "view {}", view.name);
        for &k in &want {
            footprint[k] = footprint[k].max(total[k]);
        }
    }
    // A footprint is the largest weight of a view that sees the Gaussian (to 1/256 pixel).
    for (k, &f) in footprint.iter().enumerate() {
        assert!(
            (cov.footprint(k) - f).abs() <= 0.5 / 256.0 + 1e-9,
            "{k}: {f}"
        );
    }
    assert!(footprint.iter().any(|&f| f > 4.0 * floor));
}

#[test]
fn coverage_covers_every_observed_gaussian_and_its_target_picks_fewer_views() {
    let (g, training, all) = training();
    let (chosen, report) =
        choose(training.clone(), &coverage_selection(), &g, &mut cpu(&g)).unwrap();
    assert_eq!(report.candidates, 36);
    assert!(!chosen.is_empty() && chosen.len() <= training.len());
    // At the default rule the last views, each adding a few edge Gaussians, are dropped: the
    // views kept are the greedy's first ones, each worth min_gain of the first or more.
    let (fewer, r) = choose(training.clone(), &default_rule(), &g, &mut cpu(&g)).unwrap();
    let o = r.coverage.unwrap();
    assert!(
        fewer.len() < chosen.len(),
        "{} of {} views",
        fewer.len(),
        chosen.len()
    );
    assert_eq!(o.stop, CoverageStop::MinGain);
    let bar = o.rule.min_gain * o.order[0].gain_px;
    assert!(o.order[..fewer.len()].iter().all(|s| s.gain_px >= bar));
    assert!(o.order[fewer.len()].gain_px < bar);
    assert!(o.pairs_chosen_px < o.pairs_wanted_px && o.pairs_chosen < o.pairs_wanted);
    assert_eq!(
        report.chosen,
        chosen.iter().map(|v| v.name.clone()).collect::<Vec<_>>()
    );
    // Never a held-out view.
    let held: Vec<&str> = super::held_out_indices(all.len(), 4)
        .unwrap()
        .into_iter()
        .map(|i| all[i].name.as_str())
        .collect();
    assert_eq!(held.len(), 12);
    assert!(chosen.iter().all(|v| !held.contains(&v.name.as_str())));

    // The rule, checked from the pass's sets: every Gaussian some candidate sees is seen by two
    // chosen views at least 10° apart, or no candidate could add a second viewpoint to the ones
    // chosen (each candidate seeing it is within 10° of a chosen view seeing it).
    let r = rule();
    let cov = coverage::measure(&mut cpu(&g), &training, g.len(), &r).unwrap();
    let seers = |k: usize| -> Vec<usize> {
        (0..training.len())
            .filter(|&v| cov.seen_by(v).binary_search(&k).is_ok())
            .collect()
    };
    let centre = |v: usize| training[v].world_to_camera.camera_centre();
    let is_chosen = |v: usize| chosen.iter().any(|c| c.name == training[v].name);
    let (mut observed, mut two_viewpoints) = (0, 0);
    for k in 0..g.len() {
        let s = seers(k);
        if s.is_empty() {
            continue;
        }
        observed += 1;
        let p = DVec3::from_array(g.means[k].map(f64::from));
        let picked: Vec<usize> = s.iter().copied().filter(|&v| is_chosen(v)).collect();
        assert!(!picked.is_empty(), "Gaussian {k} is seen by no chosen view");
        let distinct_pair = picked.iter().any(|&a| {
            picked
                .iter()
                .any(|&b| angle(p, centre(a), centre(b)) >= r.min_angle_deg)
        });
        if distinct_pair {
            two_viewpoints += 1;
            continue;
        }
        for &v in &s {
            assert!(
                picked
                    .iter()
                    .any(|&c| angle(p, centre(v), centre(c)) < r.min_angle_deg),
                "Gaussian {k}: view {v} would add a viewpoint"
            );
        }
    }
    let outcome = report.coverage.unwrap();
    assert_eq!(outcome.stop, CoverageStop::Exhausted);
    assert_eq!(outcome.observed, observed);
    assert_eq!(outcome.covered, observed);
    assert_eq!(outcome.pairs_chosen, outcome.pairs_wanted);
    assert!(
        two_viewpoints > observed / 2,
        "{two_viewpoints} of {observed}"
    );
    // The greedy counts the viewpoints it assigned (a maximal set per Gaussian, not always the
    // largest one the chosen views hold), so its figure is a lower bound.
    assert!(outcome.full_views <= two_viewpoints && outcome.full_views > observed / 2);
}

#[test]
fn coverage_is_the_same_for_any_thread_count() {
    let (g, training, _) = training();
    // The choice of `selection` on `threads` rayon threads.
    let run = |threads: usize, selection: &ViewSelection| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let (_, report) = choose(training.clone(), selection, &g, &mut cpu(&g)).unwrap();
            let c = report.coverage.unwrap();
            (report.chosen, c.order, c.pairs_wanted, c.full_views)
        })
    };
    let one = run(1, &coverage_selection());
    assert_eq!(run(3, &coverage_selection()), one);
    // The default stopping rule too.
    let default = |threads: usize| run(threads, &default_rule());
    let d1 = default(1);
    assert!(d1.0.len() < one.0.len());
    assert_eq!(default(3), d1);
    // Two rasterizers share the pass: the same sets, so the same choice.
    let (_, report) = choose(
        training.clone(),
        &coverage_selection(),
        &g,
        &mut cpu(&g).into_iter().chain(cpu(&g)).collect::<Vec<_>>(),
    )
    .unwrap();
    assert_eq!(report.chosen, one.0);
}

#[test]
fn a_duplicate_view_is_not_picked_twice() {
    let (g, mut training, _) = training();
    // The first view again under another name (sorted last): the same place, the same weights.
    let mut twin = training[0].clone();
    twin.name = "zz-duplicate".into();
    training.push(twin);
    let (chosen, report) = choose(training, &coverage_selection(), &g, &mut cpu(&g)).unwrap();
    let names: Vec<&str> = chosen.iter().map(|v| v.name.as_str()).collect();
    let original = report.coverage.as_ref().unwrap().order[0].view.clone();
    assert!(
        !(names.contains(&"zz-duplicate") && names.contains(&"view_0000.png")),
        "both copies chosen: {names:?} (first pick {original})"
    );
    // The duplicate never adds a pair once its twin is chosen, so the greedy never takes both.
    let order = &report.coverage.unwrap().order;
    let both = order
        .iter()
        .filter(|s| s.view == "zz-duplicate" || s.view == "view_0000.png")
        .count();
    assert!(both <= 1, "{order:?}");
}

#[test]
fn a_cap_and_a_target_shorten_the_choice() {
    let (g, training, _) = training();
    let full = choose(training.clone(), &coverage_selection(), &g, &mut cpu(&g))
        .unwrap()
        .1;
    let mut capped = coverage_selection();
    capped.count = Some(3);
    let (c, r) = choose(training.clone(), &capped, &g, &mut cpu(&g)).unwrap();
    assert_eq!(c.len(), 3);
    // The cap takes the first views of the same greedy order.
    let mut first: Vec<String> = full.coverage.as_ref().unwrap().order[..3]
        .iter()
        .map(|s| s.view.clone())
        .collect();
    first.sort();
    assert_eq!(r.chosen, first);
    assert_eq!(r.coverage.unwrap().stop, CoverageStop::Count);
    let mut part = coverage_selection();
    part.coverage.target = 0.8;
    let (c, r) = choose(training, &part, &g, &mut cpu(&g)).unwrap();
    let o = r.coverage.unwrap();
    assert!(c.len() < full.chosen.len());
    assert_eq!(o.stop, CoverageStop::Target);
    assert!(o.pairs_chosen_px >= 0.8 * o.pairs_wanted_px);
    let before: f64 = o.order[..c.len() - 1].iter().map(|s| s.gain_px).sum();
    assert!(before < 0.8 * o.pairs_wanted_px, "the shortest such prefix");
}

#[test]
fn the_rule_stops_earlier_on_a_redundant_ring_than_on_a_sparse_set() {
    let (g, _, all) = training();
    // All 48 views of the ring (7.5° apart), and every 6th of them (45° apart): the same scene,
    // seen all round either way.
    let sparse: Vec<View> = all.iter().step_by(6).cloned().collect();
    let keep = |views: &[View]| {
        let (c, r) = choose(views.to_vec(), &default_rule(), &g, &mut cpu(&g)).unwrap();
        (c.len(), r.coverage.unwrap())
    };
    let (dense_kept, dense) = keep(&all);
    let (sparse_kept, _) = keep(&sparse);
    let dense_share = dense_kept as f64 / all.len() as f64;
    let sparse_share = sparse_kept as f64 / sparse.len() as f64;
    assert!(
        dense_share < sparse_share,
        "ring: {dense_kept} of {}, sparse: {sparse_kept} of {}",
        all.len(),
        sparse.len()
    );
    assert_eq!(dense.stop, CoverageStop::MinGain);
    // The ring's views past the stop each add little: less than min_gain of the first.
    let first = dense.order[0].gain_px;
    assert!(
        dense.order[dense_kept..]
            .iter()
            .all(|s| s.gain_px < dense.rule.min_gain * first)
    );
}

#[test]
fn the_default_is_coverage_and_all_takes_every_view() {
    assert_eq!(ViewSelection::default().mode, SelectionMode::Coverage);
    assert!(CoverageRule::default().min_gain > 0.0);
    let (g, training, _) = training();
    let all = ViewSelection {
        mode: SelectionMode::All,
        ..Default::default()
    };
    let (c, r) = choose(training.clone(), &all, &g, &mut []).unwrap();
    assert_eq!(c.len(), training.len());
    assert_eq!(r.chosen.len(), 36);
    assert!(r.coverage.is_none());
    let bad = CoverageRule {
        min_gain: 1.5,
        ..CoverageRule::default()
    };
    assert!(matches!(
        bad.validate(),
        Err(slag_common::Error::Param {
            name: "view_coverage_min_gain",
            ..
        })
    ));
}

#[test]
fn uniform_keeps_the_count_asked_for() {
    let (g, training, _) = training();
    let s = ViewSelection {
        mode: SelectionMode::Uniform,
        count: Some(5),
        ..Default::default()
    };
    let (c, r) = choose(training, &s, &g, &mut []).unwrap();
    assert_eq!(c.len(), 5);
    assert_eq!(r.candidates, 36);
    assert!(r.coverage.is_none());
}

/// A synthetic ring of `views` views of `gaussians` Gaussians on `width × height` images (extent
/// 10), written to a temporary folder: its Gaussians and views.
fn ring(gaussians: usize, views: usize, width: u32, height: u32) -> (Gaussians, Vec<View>) {
    let dir = tempfile::tempdir().unwrap();
    let p = SyntheticSceneParams {
        gaussians,
        views,
        width,
        height,
        extent: 10.0,
        seed: 3,
        ..Default::default()
    };
    write_synthetic_scene(dir.path(), &p).unwrap();
    let (g, views, _) = SceneInput::new(dir.path(), None, 1).load().unwrap();
    (g, views)
}

/// The Gaussians that any of `views` gives any blend weight at the pass's raster `scale`.
fn any_weight(g: &Gaussians, views: &[View], scale: f64) -> usize {
    let r = CoverageRule {
        min_weight: Some(0.0),
        raster_scale: scale,
        ..CoverageRule::default()
    };
    coverage::measure(&mut cpu(g), views, g.len(), &r)
        .unwrap()
        .observed()
}

#[test]
fn a_scene_dense_in_gaussians_per_pixel_gets_views_that_observe_most_of_it() {
    // 40,000 Gaussians seen by a ring of 48 views on 24 × 18 images: about 90 Gaussians to a
    // pixel, so no Gaussian reaches a pixel of weight in any view.
    let (g, views) = ring(40_000, 48, 24, 18);
    let with_floor = |min_weight: Option<f64>| ViewSelection {
        mode: SelectionMode::Coverage,
        count: None,
        coverage: CoverageRule {
            min_weight,
            raster_scale: 1.0,
            ..CoverageRule::default()
        },
    };
    let e = choose(views.clone(), &with_floor(Some(1.0)), &g, &mut cpu(&g)).unwrap_err();
    assert!(
        matches!(
            e,
            slag_common::Error::Unobserved {
                stage: slag_common::Observation::CoveragePass,
                observed: 0,
                gaussians: 40_000,
                ..
            }
        ),
        "{e}"
    );
    // The scene's own floor: below a pixel, and the chosen views observe nearly every Gaussian
    // that any view observes.
    let (chosen, report) = choose(views.clone(), &with_floor(None), &g, &mut cpu(&g)).unwrap();
    let o = report.coverage.unwrap();
    assert_eq!(o.floor_source, FloorSource::Median);
    assert!(o.floor_px > 0.0 && o.floor_px < 1.0, "{}", o.floor_px);
    let every = any_weight(&g, &views, 1.0);
    let by_chosen = any_weight(&g, &chosen, 1.0);
    assert!(
        !chosen.is_empty() && chosen.len() < views.len(),
        "{}",
        chosen.len()
    );
    assert!(
        by_chosen as f64 >= 0.95 * every as f64,
        "{by_chosen} of {every} by {} views",
        chosen.len()
    );
    assert!(o.observed_chosen <= o.observed && o.observed_chosen > 0);
}

#[test]
fn a_scene_sparse_in_gaussians_per_pixel_keeps_the_one_pixel_floor() {
    // 400 Gaussians on 96 × 72 images: each covers pixels.
    let (g, views) = ring(400, 24, 96, 72);
    let scene = ViewSelection::default();
    let given = ViewSelection {
        coverage: CoverageRule {
            min_weight: Some(coverage::DEFAULT_FLOOR_PX),
            ..CoverageRule::default()
        },
        ..ViewSelection::default()
    };
    let (a, ra) = choose(views.clone(), &scene, &g, &mut cpu(&g)).unwrap();
    let (b, rb) = choose(views, &given, &g, &mut cpu(&g)).unwrap();
    let (oa, ob) = (ra.coverage.unwrap(), rb.coverage.unwrap());
    assert_eq!(
        (oa.floor_px, oa.floor_source),
        (coverage::DEFAULT_FLOOR_PX, FloorSource::Default)
    );
    assert_eq!(ob.floor_source, FloorSource::Given);
    assert_eq!(ra.chosen, rb.chosen);
    assert_eq!(oa.order, ob.order);
    assert_eq!(a.len(), b.len());
}

/// Re-evaluating the stale views on top of the greedy's heap together changes no choice: on a
/// ring of near-duplicate views (many stale bounds at every step) the order, the viewpoints and
/// whether the order is complete are those of re-evaluating one view at a time, for every
/// batch size, with and without the early stop.
#[test]
fn the_greedy_order_is_the_same_however_many_stale_views_are_re_evaluated_at_once() {
    let (g, views) = ring(3_000, 40, 48, 36);
    let rule = CoverageRule {
        raster_scale: 1.0,
        ..CoverageRule::default()
    };
    let cov = coverage::measure(&mut cpu(&g), &views, g.len(), &rule).unwrap();
    let centres: Vec<DVec3> = views
        .iter()
        .map(|v| v.world_to_camera.camera_centre())
        .collect();
    for early in [None, Some(None)] {
        let at_once = |views, seen| coverage::AtOnce { views, seen };
        let one = coverage::greedy(
            &mut cov.clone(),
            &g.means,
            &centres,
            &rule,
            early,
            at_once(1, 0),
        );
        assert!(one.0.len() > 3, "{} views in the order", one.0.len());
        for (views, seen) in [
            (2, usize::MAX),
            (7, usize::MAX),
            (64, usize::MAX),
            (64, 2_000),
        ] {
            let many = coverage::greedy(
                &mut cov.clone(),
                &g.means,
                &centres,
                &rule,
                early,
                at_once(views, seen),
            );
            assert_eq!(
                many, one,
                "{views} views, {seen} seen at once, early {early:?}"
            );
        }
    }
}
