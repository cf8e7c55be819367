//! The job's views, chosen once: worker 0 runs the view selection (the coverage pass by
//! default, on its own rasterizer, as a one-process `encode` with one rasterizer runs it) and
//! sends the chosen views' names to every worker before the map starts; the others wait for
//! them. One coverage pass for the job, and every worker maps the same views.

use std::cell::RefCell;
use std::rc::Rc;

use serde::{Deserialize, Serialize};
use slag_common::camera::View;
use slag_common::scene::Gaussians;
use slag_common::{Error, Result};
use timely::container::CapacityContainerBuilder;
use timely::dataflow::InputHandle;

use super::inbox::build_inbox;
use crate::pipeline::SceneInput;
use crate::raster::WeightRasterizer;
use crate::views::SelectionReport;

/// What worker 0 tells worker `to`: the chosen views' names (name order), or why it could not
/// choose them.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) struct ViewChoice {
    to: u32,
    chosen: std::result::Result<Vec<String>, String>,
}

pub(super) type ViewsInput = InputHandle<u64, CapacityContainerBuilder<Vec<ViewChoice>>>;

/// What a worker has heard of the choice: worker 0's message, and whether every worker closed
/// its side (no message will come any more).
#[derive(Default)]
pub(super) struct Heard {
    choice: Option<std::result::Result<Vec<String>, String>>,
    closed: bool,
}

/// Builds the dataflow that carries worker 0's choice to every worker (built identically on
/// every worker, before the job's own dataflow); what this worker hears lands in `heard`.
pub(super) fn build_views_dataflow(
    worker: &mut timely::worker::Worker,
    input: &mut ViewsInput,
    heard: &Rc<RefCell<Heard>>,
) {
    build_inbox(
        worker,
        input,
        ("views", |c: &ViewChoice| c.to as u64),
        heard,
        (
            |heard: &mut Heard, c: ViewChoice| {
                heard.choice.get_or_insert(c.chosen);
            },
            |heard: &mut Heard| heard.closed = true,
        ),
    );
}

/// The job's views among the scene's `training` views: on worker 0 chosen here
/// ([`crate::views::choose`] on this process's `rasterizers`) and sent to every
/// worker, with the selection's report; on the others the views worker 0 named, waited for.
/// Closes `input` either way.
///
/// Errors: worker 0's selection error (on every worker); views worker 0 named that this worker's
/// scene does not have; the choice never came (worker 0 ended without one).
pub(super) fn agree_on_views(
    worker: &mut timely::worker::Worker,
    mut input: ViewsInput,
    heard: &RefCell<Heard>,
    scene: &SceneInput,
    (gaussians, training): (&Gaussians, Vec<View>),
    rasterizers: &mut [Box<dyn WeightRasterizer>],
) -> Result<(Vec<View>, Option<SelectionReport>)> {
    if worker.index() == 0 {
        let chosen = crate::views::choose(training, &scene.selection, gaussians, rasterizers);
        let names = match &chosen {
            Ok((_, report)) => Ok(report.chosen.clone()),
            Err(e) => Err(e.to_string()),
        };
        for to in 0..worker.peers() as u32 {
            input.send(ViewChoice {
                to,
                chosen: names.clone(),
            });
        }
        drop(input);
        let (views, report) = chosen?;
        return Ok((views, Some(report)));
    }
    drop(input);
    while heard.borrow().choice.is_none() && !heard.borrow().closed {
        worker.step_or_park(None);
    }
    let choice = heard.borrow_mut().choice.take();
    let names = match choice {
        Some(Ok(names)) => names,
        Some(Err(m)) => {
            return Err(Error::Invalid(format!(
                "process 0 could not choose the views: {m}"
            )));
        }
        None => {
            return Err(Error::internal(
                "process 0 ended without choosing the views",
            ));
        }
    };
    let views = named_views(training, &names)?;
    Ok((views, None))
}

/// The views of `training` named in `names` (both in name order).
///
/// Errors: a name `training` lacks ([`Error::Mismatch`]: the processes read other scenes).
fn named_views(training: Vec<View>, names: &[String]) -> Result<Vec<View>> {
    let wanted: std::collections::HashSet<&str> = names.iter().map(String::as_str).collect();
    let views: Vec<View> = training
        .into_iter()
        .filter(|v| wanted.contains(v.name.as_str()))
        .collect();
    if views.len() != names.len() {
        return Err(Error::mismatch(
            slag_common::Mismatched::Scene,
            format!(
                "process 0 chose {} views this process's scene lacks: give every process the \
                 same scene",
                names.len() - views.len()
            ),
        ));
    }
    Ok(views)
}

/// Closes `input` after a failure before the views could be chosen; worker 0 first tells every
/// worker `message`, so that none waits for a choice that will not come.
pub(super) fn refuse_views(worker: &timely::worker::Worker, mut input: ViewsInput, message: &str) {
    if worker.index() == 0 {
        for to in 0..worker.peers() as u32 {
            input.send(ViewChoice {
                to,
                chosen: Err(message.to_string()),
            });
        }
    }
}
