//! The greedy alone at scale: a drone sweep's coverage sets made without rasterizing (each
//! view sees the terrain Gaussians in its frustum whose projected disc reaches a floor, so a
//! view sees a patch of the terrain and its neighbours along and across the lane overlap it).
//!
//! `SLAG_GREEDY_BENCH_GAUSSIANS=8000000 SLAG_GREEDY_BENCH_VIEWS=1657 cargo test -p
//! slag-encoder --lib greedy_at_scale -- --ignored --nocapture` prints the sets' size, the
//! greedy's seconds and a digest of its order (the same digest: the same choice).

#![allow(clippy::unwrap_used)]

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use glam::DVec3;
use rayon::prelude::*;

use super::{AtOnce, CoverageRule, FloorSource, SeenSet, ViewCoverage, greedy};
use crate::synthetic::{SyntheticSceneParams, ViewLayout, camera, focal, terrain_gaussians};

/// Side of the grid cells the Gaussians are binned in, scene units.
const CELL: f64 = 2.0;

/// Range at which a Gaussian of the terrain's spacing, seen at the sweep's height, falls to
/// the floor: scene units.
const REACH: f64 = 18.0;

/// The sweep's Gaussian means and camera centres, and its coverage: `gaussians` terrain
/// Gaussians (the synthetic scene's, extent 100), `views` sweep views at 990 × 742.
pub(super) fn sweep_coverage(
    gaussians: usize,
    views: usize,
) -> (Vec<[f32; 3]>, Vec<DVec3>, ViewCoverage) {
    let p = SyntheticSceneParams {
        gaussians,
        views,
        layout: ViewLayout::Sweep,
        ..SyntheticSceneParams::default()
    };
    let g = terrain_gaussians(&p);
    let n = g.len();
    let spacing = p.extent / (n as f64).sqrt();
    let f = focal(&p);
    let height = 0.12 * p.extent;
    // A disc of the spacing at REACH, seen at the angle the sweep's height gives there.
    let floor = std::f64::consts::PI * (spacing * f / REACH).powi(2) * (height / REACH);
    let cells = Cells::new(&g.means, p.extent);
    let footprint: Vec<AtomicU64> = (0..n).map(|_| AtomicU64::new(0)).collect();
    let seen: Vec<SeenSet> = (0..views)
        .into_par_iter()
        .map(|i| {
            let (rot, centre) = camera(i, &p);
            let fwd = rot.row(2);
            let mut ids = Vec::new();
            for k in cells.ahead(centre, fwd) {
                let s = g.scales[k][0] as f64;
                let m = g.means[k].map(f64::from);
                let m = DVec3::new(m[0], m[1], m[2]);
                let c = rot * (m - centre);
                if c.z < 0.1 {
                    continue;
                }
                let (u, v) = (f * c.x / c.z, f * c.y / c.z);
                if u.abs() >= 0.5 * p.width as f64 || v.abs() >= 0.5 * p.height as f64 {
                    continue;
                }
                let incidence = (centre - m).normalize().z.abs();
                let w = std::f64::consts::PI * (s * f / c.z).powi(2) * incidence;
                if w >= floor {
                    let steps = ((w / floor * 256.0).round() as u64).max(1);
                    footprint[k].fetch_max(steps, Ordering::Relaxed);
                    ids.push(k as u32);
                }
            }
            ids.sort_unstable();
            SeenSet::new(ids, n)
        })
        .collect();
    let centres = (0..views).map(|i| camera(i, &p).1).collect();
    let coverage = ViewCoverage {
        gaussians: n,
        seen,
        footprint: footprint.into_iter().map(AtomicU64::into_inner).collect(),
        floor_px: floor,
        floor_source: FloorSource::Given,
        steps_per_px: 256.0 / floor,
    };
    (g.means, centres, coverage)
}

/// The Gaussians binned in square cells of side [`CELL`] over the terrain.
struct Cells {
    side: usize,
    extent: f64,
    /// Per cell the range of its Gaussians in `ids`.
    starts: Vec<usize>,
    ids: Vec<usize>,
}

impl Cells {
    fn new(means: &[[f32; 3]], extent: f64) -> Self {
        let side = (extent / CELL).ceil() as usize;
        let cell = |m: &[f32; 3]| {
            let at = |x: f32| (((x as f64 / extent + 0.5) * side as f64) as usize).min(side - 1);
            at(m[1]) * side + at(m[0])
        };
        let mut starts = vec![0usize; side * side + 1];
        for m in means {
            starts[cell(m) + 1] += 1;
        }
        for c in 0..side * side {
            starts[c + 1] += starts[c];
        }
        let mut next = starts.clone();
        let mut ids = vec![0usize; means.len()];
        for (k, m) in means.iter().enumerate() {
            let c = cell(m);
            ids[next[c]] = k;
            next[c] += 1;
        }
        Cells {
            side,
            extent,
            starts,
            ids,
        }
    }

    /// The Gaussians of the cells within [`REACH`] of `centre` and within 40° of `fwd` on the
    /// ground (a superset of those a sweep view can see).
    fn ahead(&self, centre: DVec3, fwd: DVec3) -> impl Iterator<Item = usize> + '_ {
        let ahead = DVec3::new(fwd.x, fwd.y, 0.0).normalize();
        let side = self.side;
        let extent = self.extent;
        (0..side * side)
            .filter(move |&c| {
                let at = |i: usize| (i as f64 + 0.5) / side as f64 * extent - 0.5 * extent;
                let d = DVec3::new(at(c % side) - centre.x, at(c / side) - centre.y, 0.0);
                let dist = d.length();
                dist <= REACH + CELL && (dist < 2.0 * CELL || d.dot(ahead) >= dist * 0.75)
            })
            .flat_map(move |c| self.ids[self.starts[c]..self.starts[c + 1]].iter().copied())
    }
}

/// The process's CPU seconds so far (user and system, all threads), from `/proc/self/stat`
/// (0 where it cannot be read).
fn cpu_s() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    // utime and stime (clock ticks, 100 a second) are fields 14 and 15 of the line, the 12th
    // and 13th past the name.
    let ticks = |i: usize| f.get(i).and_then(|x| x.parse::<f64>().ok()).unwrap_or(0.0);
    (ticks(11) + ticks(12)) / 100.0
}

fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

/// FNV-1a over the order's (view, gain footprint, gain pairs).
fn digest(order: &[(usize, (u64, u64))]) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    for &(v, (w, c)) in order {
        for x in [v as u64, w, c] {
            h = (h ^ x).wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    h
}

#[test]
#[ignore = "a benchmark: minutes at its default size"]
fn greedy_at_scale_on_a_drone_sweep() {
    let n = env_usize("SLAG_GREEDY_BENCH_GAUSSIANS", 8_000_000);
    let views = env_usize("SLAG_GREEDY_BENCH_VIEWS", 1_657);
    let (t, cpu) = (Instant::now(), cpu_s());
    let (means, centres, mut cov) = sweep_coverage(n, views);
    let sizes: Vec<usize> = cov.seen.iter().map(SeenSet::len).collect();
    let bits = cov
        .seen
        .iter()
        .filter(|s| matches!(s, SeenSet::Bits(_)))
        .count();
    eprintln!(
        "sets: {n} Gaussians x {views} views in {:.1} s ({:.1} CPU s); observed {}; seen per view mean {} max \
         {}; {bits} bitsets; {} bytes",
        t.elapsed().as_secs_f64(),
        cpu_s() - cpu,
        cov.observed(),
        sizes.iter().sum::<usize>() / views.max(1),
        sizes.iter().max().unwrap_or(&0),
        cov.bytes()
    );
    let rule = CoverageRule::default();
    eprintln!(
        "sparse bitsets: {} bytes for the sets' {} bytes",
        super::greedy::words_bytes(&cov, &means),
        cov.bytes() - cov.footprint.len() * 8
    );
    let (t, cpu) = (Instant::now(), cpu_s());
    let (order, _, complete) = greedy(
        &mut cov,
        &means,
        &centres,
        &rule,
        Some(None),
        AtOnce::for_threads(),
    );
    eprintln!(
        "greedy: {:.2} s ({:.1} CPU s) on {} threads; {} views in the order (complete {complete}); digest \
         {:016x}; first {:?}",
        t.elapsed().as_secs_f64(),
        cpu_s() - cpu,
        rayon::current_num_threads(),
        order.len(),
        digest(&order),
        &order[..order.len().min(4)]
    );
    assert!(order.len() > 1, "{} views in the order", order.len());
}

/// The greedy from its definition: every round every view's gain from scratch over the
/// Gaussians it sees, the largest of the views not yet taken (ties to the lower index), until
/// no view adds a pair or the stopping rule refuses the view just taken. Returns the order and per Gaussian its
/// viewpoints in the order they were given.
#[allow(clippy::type_complexity)]
fn reference(
    cov: &ViewCoverage,
    means: &[[f32; 3]],
    centres: &[DVec3],
    rule: &CoverageRule,
) -> (Vec<(usize, (u64, u64))>, Vec<Vec<usize>>) {
    let cos_max = rule.min_angle_deg.to_radians().cos();
    let seen: Vec<Vec<usize>> = (0..cov.views()).map(|v| cov.seen_by(v)).collect();
    let dir = |k: usize, v: usize| {
        (DVec3::from(means[k].map(f64::from)) - centres[v]).normalize_or_zero()
    };
    let adds = |given: &[usize], k: usize, v: usize| {
        given.len() < rule.min_views && given.iter().all(|&u| dir(k, v).dot(dir(k, u)) <= cos_max)
    };
    let mut given: Vec<Vec<usize>> = vec![Vec::new(); means.len()];
    let mut order = Vec::new();
    while let Some((gain, std::cmp::Reverse(v))) = (0..seen.len())
        .filter(|v| order.iter().all(|&(u, _)| u != *v))
        .map(|v| {
            let new = seen[v].iter().filter(|&&k| adds(&given[k], k, v));
            let gain = new.fold((0, 0), |g, &k| (g.0 + cov.footprint[k], g.1 + 1));
            (gain, std::cmp::Reverse(v))
        })
        .max()
    {
        if gain.1 == 0 {
            break;
        }
        for &k in &seen[v] {
            if adds(&given[k], k, v) {
                given[k].push(v);
            }
        }
        order.push((v, gain));
        if (gain.0 as f64) < rule.min_gain * order[0].1.0 as f64 {
            break;
        }
    }
    (order, given)
}

/// A random scene for the greedy: `n` Gaussians in a box, views in clusters of near-duplicate
/// centres around it (so the angle rule refuses some pairs), each view seeing a random ball of
/// the Gaussians, some views thin (ids kept) and some dense (a bitset), random footprints.
fn random_coverage(seed: u64, n: usize, views: usize) -> (Vec<[f32; 3]>, Vec<DVec3>, ViewCoverage) {
    let mut rng = slag_common::rng::SplitMix64::new(seed);
    let means: Vec<[f32; 3]> = (0..n)
        .map(|_| [0; 3].map(|_| rng.range(-10.0, 10.0) as f32))
        .collect();
    let mut centres = Vec::new();
    while centres.len() < views {
        let c = DVec3::new(
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
        );
        let c = c.normalize_or_zero() * 40.0;
        for _ in 0..(1 + rng.next_u64() % 4).min((views - centres.len()) as u64) {
            centres.push(c + DVec3::new(rng.range(-2.0, 2.0), rng.range(-2.0, 2.0), 0.0));
        }
    }
    let footprint: Vec<u64> = (0..n).map(|_| 1 + rng.next_u64() % 1000).collect();
    let mut observed = vec![false; n];
    let seen = centres
        .iter()
        .map(|_| {
            let at = DVec3::new(
                rng.range(-10.0, 10.0),
                rng.range(-10.0, 10.0),
                rng.range(-10.0, 10.0),
            );
            let radius = rng.range(2.0, 14.0);
            let ids: Vec<u32> = (0..n as u32)
                .filter(|&k| DVec3::from(means[k as usize].map(f64::from)).distance(at) <= radius)
                .collect();
            for &k in &ids {
                observed[k as usize] = true;
            }
            SeenSet::new(ids, n)
        })
        .collect();
    let footprint = footprint
        .iter()
        .zip(&observed)
        .map(|(&f, &o)| if o { f } else { 0 })
        .collect();
    let cov = ViewCoverage {
        gaussians: n,
        seen,
        footprint,
        floor_px: 1.0,
        floor_source: FloorSource::Given,
        steps_per_px: 256.0,
    };
    (means, centres, cov)
}

/// The greedy (renumbered Gaussians, sparse bitsets, lazy evaluation, batched re-evaluation) chooses
/// exactly the views, gains and viewpoints of the greedy from its definition, on random
/// scenes and rules.
#[test]
fn the_greedy_chooses_what_its_definition_chooses() {
    let mut bitsets = 0;
    for seed in 0..6u64 {
        let (means, centres, cov) = random_coverage(seed, 4_000 + 700 * seed as usize, 36);
        bitsets += cov
            .seen
            .iter()
            .filter(|s| matches!(s, SeenSet::Bits(_)))
            .count();
        let rule = CoverageRule {
            min_views: 1 + seed as usize % 3,
            min_angle_deg: [10.0, 0.0, 25.0][seed as usize / 2],
            min_gain: [0.02, 0.0][seed as usize / 3],
            ..CoverageRule::default()
        };
        let (want, given) = reference(&cov, &means, &centres, &rule);
        assert!(want.len() > 2, "seed {seed}: {} views", want.len());
        for at_once in [AtOnce::for_threads(), AtOnce { views: 1, seen: 0 }] {
            let mut taken = cov.clone();
            let (order, slots, _) =
                greedy(&mut taken, &means, &centres, &rule, Some(None), at_once);
            assert_eq!(order, want, "seed {seed}, {at_once:?}");
            let per = rule.min_views;
            for (k, g) in given.iter().enumerate() {
                let s: Vec<usize> = slots[k * per..(k + 1) * per]
                    .iter()
                    .take_while(|&&u| u != u32::MAX)
                    .map(|&u| u as usize)
                    .collect();
                assert_eq!(&s, g, "seed {seed}, Gaussian {k}");
            }
        }
    }
    assert!(bitsets > 0, "no view's set was a bitset");
}
