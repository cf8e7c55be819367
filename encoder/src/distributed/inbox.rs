//! The end of every small dataflow of the cluster (the views' choice, the resume notes, the
//! hand-out's asks and grants): the records sent on an input travel to the worker each names,
//! and each worker's records land in its inbox, which notes when every worker has closed its
//! side of the input.

use std::cell::RefCell;
use std::rc::Rc;

use timely::ExchangeData;
use timely::container::CapacityContainerBuilder;
use timely::dataflow::InputHandle;
use timely::dataflow::channels::pact::Exchange;
use timely::dataflow::operators::Operator;

/// Builds a dataflow of its own (identically on every worker, in the same order) that carries
/// each record sent on `input` to worker `to(record)` (`name`: the operator's name), where it is
/// handed to `take` with this worker's `inbox`; `close` is called (at each step after that) once
/// every worker has closed its side of `input`: no record will come any more.
pub(super) fn build_inbox<R, S>(
    worker: &mut timely::worker::Worker,
    input: &mut InputHandle<u64, CapacityContainerBuilder<Vec<R>>>,
    (name, to): (&str, impl Fn(&R) -> u64 + 'static),
    inbox: &Rc<RefCell<S>>,
    (mut take, mut close): (
        impl FnMut(&mut S, R) + 'static,
        impl FnMut(&mut S) + 'static,
    ),
) where
    R: ExchangeData + Clone,
    S: 'static,
{
    let inbox = Rc::clone(inbox);
    worker.dataflow::<u64, _, _>(|scope| {
        input
            .to_stream(scope)
            .sink(Exchange::new(to), name, move |(input, frontier)| {
                let mut inbox = inbox.borrow_mut();
                input.for_each(|_time, data| {
                    for record in data.drain(..) {
                        take(&mut inbox, record);
                    }
                });
                if frontier.is_empty() {
                    close(&mut inbox);
                }
            });
    });
}
