//! The encode's last check before its outputs: views that observed none of the scene's Gaussians,
//! or far fewer than the coverage pass saw them see, make an empty or mostly empty map, which is
//! refused instead of written.

use slag_common::{Error, Observation, Result};

use super::SelectionReport;

/// The share of the Gaussians that the coverage pass saw the chosen views see, below which the
/// encode's own count is refused (a tenth: the encode counts any blend weight in a mask, the
/// pass a floor of weight in the whole view, so the encode's count is normally the larger, and
/// falls far below only when the encode's raster or masks miss what the views show).
pub const MIN_OBSERVED_SHARE: f64 = 0.1;

/// Checks the encode's `observed` Gaussians (of the scene's `gaussians`) against the view
/// `selection` that chose its views: at least one, and with coverage selection at least
/// [`MIN_OBSERVED_SHARE`] of the Gaussians the pass saw the chosen views see.
///
/// Errors: [`Error::Unobserved`] ([`Observation::Encode`]) otherwise.
pub fn check_observed(
    selection: Option<&SelectionReport>,
    observed: usize,
    gaussians: usize,
) -> Result<()> {
    let seen_by_pass = selection
        .and_then(|s| s.coverage.as_ref())
        .map(|c| c.observed_chosen);
    let least = seen_by_pass.map_or(1, |n| {
        ((n as f64 * MIN_OBSERVED_SHARE).ceil() as usize).max(1)
    });
    if observed >= least {
        return Ok(());
    }
    let views = selection.map_or(0, |s| s.chosen.len());
    let expected = match seen_by_pass {
        Some(n) => format!(
            "expected at least {least}: the coverage pass saw the {views} chosen views see {n}; \
             the map would be mostly empty"
        ),
        None => format!(
            "expected at least 1 in the {views} encoded views' masks; the map would be empty"
        ),
    };
    Err(Error::Unobserved {
        stage: Observation::Encode,
        observed: observed as u64,
        gaussians: gaussians as u64,
        expected,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::views::{CoverageOutcome, CoverageRule, CoverageStop, FloorSource, SelectionMode};

    fn selection(observed_chosen: Option<usize>) -> SelectionReport {
        SelectionReport {
            mode: match observed_chosen {
                Some(_) => SelectionMode::Coverage,
                None => SelectionMode::All,
            },
            candidates: 10,
            chosen: vec!["a.png".into(), "b.png".into()],
            pass_s: 0.0,
            coverage: observed_chosen.map(|n| CoverageOutcome {
                rule: CoverageRule::default(),
                raster_s: 0.0,
                greedy_s: 0.0,
                seen_bytes: 0,
                floor_px: 1.0,
                floor_source: FloorSource::Default,
                observed: n,
                observed_chosen: n,
                pairs_wanted: 0,
                pairs_chosen: 0,
                pairs_wanted_px: 0.0,
                pairs_chosen_px: 0.0,
                stop: CoverageStop::MinGain,
                order_complete: true,
                full_views: 0,
                covered: 0,
                order: Vec::new(),
            }),
        }
    }

    #[test]
    fn an_encode_that_observes_nothing_or_far_too_little_is_refused() {
        // No selection report, or every view: any Gaussian will do, none will not.
        for s in [None, Some(selection(None))] {
            assert!(check_observed(s.as_ref(), 1, 100).is_ok());
            let e = check_observed(s.as_ref(), 0, 100).unwrap_err();
            assert!(
                matches!(
                    e,
                    Error::Unobserved {
                        stage: Observation::Encode,
                        observed: 0,
                        gaussians: 100,
                        ..
                    }
                ),
                "{e}"
            );
        }
        // Coverage saw the chosen views see 1,000: a tenth of that is the least.
        let s = selection(Some(1000));
        assert!(check_observed(Some(&s), 100, 5000).is_ok());
        let e = check_observed(Some(&s), 99, 5000).unwrap_err();
        assert!(e.to_string().contains("99 of 5000"), "{e}");
        assert!(e.to_string().contains("1000"), "{e}");
        assert!(e.is_user_input());
    }
}
