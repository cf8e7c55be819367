//! Which of a scene's views an encode uses: the training views (every N-th view, minus the views
//! the 2D held-out protocol keeps back) and, among them, all, a uniformly thinned subset, or the
//! views a coverage pass finds necessary ([`coverage`]).
//!
//! The split is over name-sorted view indices `i`:
//!
//! | setting | training views |
//! |---|---|
//! | `every = E` | `i ≡ 0 (mod E)` (E = 1: all) |
//! | `hold_out_every = N` | additionally `i ≢ ⌊N/2⌋ (mod N)`: the held-out views ([`held_out_indices`]) are never encoded |
//!
//! The selection then picks among the training views only, so a held-out view is never encoded
//! whatever the selection does. The held-out views are scored by `slag-eval`'s 2D held-out
//! protocol (`slag-encoder eval-colors --held-out`).

use std::time::Instant;

use serde::{Deserialize, Serialize};
use slag_common::camera::View;
use slag_common::scene::Gaussians;
use slag_common::{Error, Result};

use crate::raster::WeightRasterizer;

pub mod coverage;
mod observed;

pub use coverage::{
    CoverageOutcome, CoverageRule, CoverageStop, FloorSource, GreedyStep, ViewCoverage,
};
pub use observed::{MIN_OBSERVED_SHARE, check_observed};

/// How the encoded views are chosen among the training views.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SelectionMode {
    /// Every training view.
    All,
    /// [`ViewSelection::count`] training views, evenly spaced in name order ([`uniform`]).
    Uniform,
    /// The views a cheap weight-raster pass finds necessary to see every observed Gaussian with
    /// enough blend weight from enough distinct viewpoints, as many as the scene's own coverage
    /// curve asks for ([`coverage`]; the default).
    #[default]
    Coverage,
}

/// Which training views an encode uses ([`crate::config::SceneConfig::views`]).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ViewSelection {
    /// How they are chosen (default: coverage, with its own stopping rule).
    pub mode: SelectionMode,
    /// [`SelectionMode::Uniform`]: exactly this many views (required). [`SelectionMode::Coverage`]:
    /// at most this many (the first ones of the greedy order). `None`: no cap.
    pub count: Option<usize>,
    /// The stopping rule of [`SelectionMode::Coverage`].
    pub coverage: CoverageRule,
}

impl ViewSelection {
    /// Checks the selection's settings.
    ///
    /// Errors: [`Error::Param`] `view_count` (uniform without a count, or a count of 0), and as
    /// [`CoverageRule::validate`] with [`SelectionMode::Coverage`].
    pub fn validate(&self) -> Result<()> {
        if self.count == Some(0) {
            return Err(Error::param("view_count", 0, "a view count >= 1"));
        }
        match self.mode {
            SelectionMode::All => Ok(()),
            SelectionMode::Uniform if self.count.is_none() => Err(Error::param(
                "view_count",
                "none",
                "a view count >= 1: uniform selection keeps that many evenly spaced views",
            )),
            SelectionMode::Uniform => Ok(()),
            SelectionMode::Coverage => self.coverage.validate(),
        }
    }
}

/// Name-sorted indices of the training views among `n_views` views: `i ≡ 0 (mod every)` (0 counts
/// as 1) and, with `hold_out_every = Some(N)`, `i ≢ ⌊N/2⌋ (mod N)` (the views
/// [`held_out_indices`] holds out).
///
/// Errors: [`Error::Param`] `hold_out_every` for N < 2 (nothing would be held out).
pub fn training_indices(
    n_views: usize,
    every: usize,
    hold_out_every: Option<usize>,
) -> Result<Vec<usize>> {
    let every = every.max(1);
    check_hold_out(hold_out_every)?;
    Ok((0..n_views)
        .filter(|i| i % every == 0)
        .filter(|i| hold_out_every.is_none_or(|n| i % n != n / 2))
        .collect())
}

/// Name-sorted indices of the held-out views for the encoder's step `every` among `n_views`
/// views: the indices `i ≡ ⌊every/2⌋ (mod every)`. The encoder keeps `i ≡ 0 (mod every)`
/// ([`slag_common::camera::subsample`]), so these were never encoded.
///
/// Errors ([`Error::Param`] `every`): `every < 2` (every view was encoded, none is held out).
pub fn held_out_indices(n_views: usize, every: usize) -> Result<Vec<usize>> {
    if every < 2 {
        return Err(Error::param(
            "every",
            every,
            "2 or more (e.g. 4): every view was encoded, so none is held out; encode with that \
             step and evaluate with the same one",
        ));
    }
    Ok((0..n_views).filter(|i| i % every == every / 2).collect())
}

/// Name-sorted indices of the views that none of several encodes saw, for comparing encodes made
/// with different steps on the same held-out pixels: the indices `i < n_views` with
/// `i mod every ≠ 0` for every step in `everys` (each encode keeps `i ≡ 0 (mod every)`,
/// [`slag_common::camera::subsample`]). With one step `N` this is a superset of
/// [`held_out_indices`]`(n_views, N)`.
///
/// Errors ([`Error::Param`] `every`): a step below 2 (that encode saw every view), no step, or
/// no view left unencoded (a scene of too few views for these steps).
pub fn held_out_for_all(n_views: usize, everys: &[usize]) -> Result<Vec<usize>> {
    if let Some(&e) = everys.iter().find(|&&e| e < 2) {
        return Err(Error::param(
            "every",
            e,
            "2 or more for every encode compared: an encode of every view leaves none held out",
        ));
    }
    if everys.is_empty() {
        return Err(Error::param(
            "every",
            "none",
            "at least one encode step (2 or more) to hold views out from",
        ));
    }
    let held: Vec<usize> = (0..n_views)
        .filter(|i| everys.iter().all(|e| i % e != 0))
        .collect();
    if held.is_empty() {
        return Err(Error::param(
            "every",
            format!("{everys:?}"),
            format!("steps that leave a view of the {n_views} unencoded by all of them"),
        ));
    }
    Ok(held)
}

/// Checks a held-out step (`hold_out_every`): `None` or at least 2.
///
/// Errors: [`Error::Param`] `hold_out_every` for N < 2 (nothing would be held out).
pub fn check_hold_out(hold_out_every: Option<usize>) -> Result<()> {
    match hold_out_every {
        Some(n) if n < 2 => Err(Error::param(
            "hold_out_every",
            n,
            "2 or more (e.g. 4): views with index ≡ N/2 (mod N) are held out",
        )),
        _ => Ok(()),
    }
}

/// The training views of `views` (name-sorted), see [`training_indices`].
///
/// Errors: as [`training_indices`].
pub fn training_views(
    views: Vec<View>,
    every: usize,
    hold_out_every: Option<usize>,
) -> Result<Vec<View>> {
    let keep = training_indices(views.len(), every, hold_out_every)?;
    Ok(pick(views, &keep))
}

/// `count` positions evenly spaced over `0..n` (the middle of each of `count` equal strata:
/// `⌊(2i + 1)·n / 2·count⌋`), ascending and distinct; all of `0..n` when `count ≥ n`.
pub fn uniform(n: usize, count: usize) -> Vec<usize> {
    if count >= n {
        return (0..n).collect();
    }
    (0..count).map(|i| (2 * i + 1) * n / (2 * count)).collect()
}

/// The elements of `items` at the ascending positions `keep`.
pub fn pick<T>(items: Vec<T>, keep: &[usize]) -> Vec<T> {
    let mut keep = keep.iter().peekable();
    items
        .into_iter()
        .enumerate()
        .filter_map(|(i, v)| {
            if keep.peek() == Some(&&i) {
                keep.next();
                Some(v)
            } else {
                None
            }
        })
        .collect()
}

/// What the report records of a run's view selection (`report.json`'s `view_selection`).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct SelectionReport {
    /// The mode that ran.
    pub mode: SelectionMode,
    /// Training views the selection chose among.
    pub candidates: usize,
    /// The encoded views' names, in name order.
    pub chosen: Vec<String>,
    /// Seconds choosing them (the coverage pass: raster and greedy; 0 otherwise).
    pub pass_s: f64,
    /// The coverage pass's figures ([`SelectionMode::Coverage`] only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub coverage: Option<CoverageOutcome>,
}

/// Chooses the encoded views among `training` (name-sorted) as `selection` asks: all, the
/// uniform subset, or coverage selection ([`coverage::select`]) run on `rasterizers` over
/// `gaussians`. Returns the chosen views in name order and what the report records of them.
///
/// Errors: as [`ViewSelection::validate`] and [`coverage::select`]; [`Error::Param`]
/// `rasterizers` when coverage selection gets none.
pub fn choose(
    training: Vec<View>,
    selection: &ViewSelection,
    gaussians: &Gaussians,
    rasterizers: &mut [Box<dyn WeightRasterizer>],
) -> Result<(Vec<View>, SelectionReport)> {
    choose_shown(
        training,
        selection,
        gaussians,
        rasterizers,
        &indicatif::ProgressBar::hidden(),
    )
}

/// [`choose`], the coverage pass's views counted on `progress` ([`coverage::select_shown`]).
///
/// Errors: as [`choose`].
pub fn choose_shown(
    training: Vec<View>,
    selection: &ViewSelection,
    gaussians: &Gaussians,
    rasterizers: &mut [Box<dyn WeightRasterizer>],
    progress: &indicatif::ProgressBar,
) -> Result<(Vec<View>, SelectionReport)> {
    selection.validate()?;
    let t0 = Instant::now();
    let candidates = training.len();
    let (keep, coverage) = match selection.mode {
        SelectionMode::All => ((0..candidates).collect(), None),
        SelectionMode::Uniform => (
            uniform(candidates, selection.count.unwrap_or(candidates)),
            None,
        ),
        SelectionMode::Coverage => {
            let (keep, outcome) = coverage::select_shown(
                rasterizers,
                gaussians,
                &training,
                &selection.coverage,
                selection.count,
                progress,
            )?;
            (keep, Some(outcome))
        }
    };
    let chosen = pick(training, &keep);
    let report = SelectionReport {
        mode: selection.mode,
        candidates,
        chosen: chosen.iter().map(|v| v.name.clone()).collect(),
        pass_s: t0.elapsed().as_secs_f64(),
        coverage,
    };
    Ok((chosen, report))
}

#[cfg(test)]
mod tests;

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod split_tests {
    use super::*;

    #[test]
    fn held_out_views_are_never_encoded() {
        assert_eq!(held_out_indices(13, 4).unwrap(), vec![2, 6, 10]);
        assert_eq!(held_out_indices(10, 3).unwrap(), vec![1, 4, 7]);
        assert_eq!(held_out_indices(5, 2).unwrap(), vec![1, 3]);
        for every in 2..9 {
            for i in held_out_indices(97, every).unwrap() {
                assert_ne!(i % every, 0, "view {i} is encoded with every = {every}");
            }
        }
        for every in [0, 1] {
            assert!(matches!(
                held_out_indices(10, every),
                Err(Error::Param { name: "every", .. })
            ));
        }
    }

    #[test]
    fn views_held_out_for_all_steps_are_encoded_by_none() {
        let held = held_out_for_all(21, &[2, 6, 5]).unwrap();
        assert_eq!(held, vec![1, 3, 7, 9, 11, 13, 17, 19]);
        for every in [2, 6, 5] {
            let encoded: Vec<usize> = (0..21).step_by(every).collect();
            assert!(held.iter().all(|i| !encoded.contains(i)), "step {every}");
        }
        // One step: the eval-colors split is a subset.
        let one = held_out_for_all(13, &[4]).unwrap();
        assert!(
            held_out_indices(13, 4)
                .unwrap()
                .iter()
                .all(|i| one.contains(i))
        );
        for (n, bad) in [(6, &[1usize, 4][..]), (6, &[]), (1, &[2])] {
            let e = held_out_for_all(n, bad).unwrap_err();
            assert!(
                matches!(e, Error::Param { name: "every", .. }),
                "{bad:?}: {e}"
            );
        }
    }

    #[test]
    fn the_split_never_trains_on_a_held_out_view() {
        // 13 views, hold out every 4th from index 2: 2, 6, 10.
        let t = training_indices(13, 1, Some(4)).unwrap();
        assert_eq!(t, vec![0, 1, 3, 4, 5, 7, 8, 9, 11, 12]);
        for n in 2..9 {
            let held = held_out_indices(97, n).unwrap();
            let train = training_indices(97, 1, Some(n)).unwrap();
            assert_eq!(held.len() + train.len(), 97);
            assert!(held.iter().all(|h| !train.contains(h)), "N = {n}");
            // `every N` alone is a subset of the held-out split's training views.
            let every = training_indices(97, n, None).unwrap();
            assert!(every.iter().all(|i| train.contains(i)), "N = {n}");
            assert_eq!(training_indices(97, n, Some(n)).unwrap(), every);
        }
        assert_eq!(training_indices(5, 0, None).unwrap(), vec![0, 1, 2, 3, 4]);
        assert!(matches!(
            training_indices(5, 1, Some(1)),
            Err(Error::Param {
                name: "hold_out_every",
                ..
            })
        ));
    }

    #[test]
    fn uniform_thinning_is_evenly_spaced_and_exact() {
        assert_eq!(uniform(10, 5), vec![1, 3, 5, 7, 9]);
        assert_eq!(uniform(73, 36).len(), 36);
        assert_eq!(uniform(4, 9), vec![0, 1, 2, 3]);
        for n in 1..40 {
            for c in 1..=n {
                let u = uniform(n, c);
                assert_eq!(u.len(), c);
                assert!(u.windows(2).all(|w| w[0] < w[1]), "{n} {c}: {u:?}");
                assert!(*u.last().unwrap() < n);
            }
        }
        assert_eq!(pick(vec!['a', 'b', 'c', 'd'], &[1, 3]), vec!['b', 'd']);
    }

    #[test]
    fn uniform_needs_a_count() {
        let s = ViewSelection {
            mode: SelectionMode::Uniform,
            ..Default::default()
        };
        assert!(matches!(
            s.validate(),
            Err(Error::Param {
                name: "view_count",
                ..
            })
        ));
        assert!(ViewSelection::default().validate().is_ok());
    }
}
