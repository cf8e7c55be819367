//! The views handed out by work done: worker 0 keeps the job's next view nobody has taken
//! ([`Handout`]); a worker that has no view asks it for one ([`Ask`]) and gets the next view
//! index or word that none is left ([`Grant`]). A slow process asks less often, so it maps fewer
//! views and never holds the others back.
//!
//! Asks and grants travel over the job's timely channels (the authenticated connections), one
//! small dataflow each, built identically on every worker. Every worker maps its views on a
//! thread of its own (`map::map_side`) while its timely worker keeps stepping, so worker 0
//! answers an ask within a step even while it maps a view itself.
//!
//! Nothing waits on a message that may never come: a worker waits for its grant until worker 0
//! closes its grants (it has handed out every view or stopped), and worker 0 serves until every
//! worker has closed its asks. A lost process fails its connections, which ends every process at
//! once ([`super::encode_cluster`]'s panic hook).

use std::cell::RefCell;
use std::collections::VecDeque;
use std::rc::Rc;

use serde::{Deserialize, Serialize};
use timely::container::CapacityContainerBuilder;
use timely::dataflow::InputHandle;

use super::inbox::build_inbox;

/// Worker 0's hand-out of one job's views: the views some partition lacks, in view order, each
/// to the first worker that asks after the one before it was taken.
#[derive(Debug, Clone)]
pub(super) struct Handout {
    /// The views still to hand out, ascending.
    left: VecDeque<u32>,
    /// Views no worker maps: every partition's checkpoint holds them.
    skipped: u64,
    /// `[P]` whether worker `w` has been told that no view is left.
    ended: Vec<bool>,
}

impl Handout {
    /// The hand-out of `views` views to `peers` workers when partition `p` holds views
    /// `0..held[p]` from its checkpoint: view `i` is handed out when some partition lacks it
    /// (`held[p] <= i`); with no partition (`held` empty) every view is.
    pub(super) fn new(views: usize, held: &[u32], peers: usize) -> Self {
        let needed = |i: u32| held.is_empty() || held.iter().any(|&h| h <= i);
        let left: VecDeque<u32> = (0..views as u32).filter(|&i| needed(i)).collect();
        Handout {
            skipped: (views - left.len()) as u64,
            left,
            ended: vec![false; peers],
        }
    }

    /// Views no worker maps because every partition holds them.
    pub(super) fn skipped(&self) -> u64 {
        self.skipped
    }

    /// The next view for worker `to`, or `None` when none is left (then `to` has ended).
    pub(super) fn grant(&mut self, to: u32) -> Option<u32> {
        let view = self.left.pop_front();
        if view.is_none()
            && let Some(e) = self.ended.get_mut(to as usize)
        {
            *e = true;
        }
        view
    }

    /// Hands out nothing more (the job failed): every later ask gets `None`.
    pub(super) fn stop(&mut self) {
        self.left.clear();
    }

    /// Whether every worker has been told that no view is left.
    pub(super) fn all_ended(&self) -> bool {
        self.ended.iter().all(|&e| e)
    }
}

/// Worker `from` asks worker 0 for a view.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) struct Ask {
    from: u32,
}

/// Worker 0's answer to worker `to`: the view it maps next, or `None`: none is left.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) struct Grant {
    to: u32,
    view: Option<u32>,
}

pub(super) type AskInput = InputHandle<u64, CapacityContainerBuilder<Vec<Ask>>>;
pub(super) type GrantInput = InputHandle<u64, CapacityContainerBuilder<Vec<Grant>>>;

/// What a worker has received of the hand-out: on worker 0 the asks not yet answered, on every
/// worker its grants not yet taken; each with whether its senders have all closed.
#[derive(Default)]
pub(super) struct Inbox {
    asks: VecDeque<u32>,
    asks_closed: bool,
    grants: VecDeque<Option<u32>>,
    grants_closed: bool,
}

/// One worker's ends of the hand-out: its inputs (each dropped once this worker sends no more on
/// it) and its inbox.
pub(super) struct HandoutEnds {
    asks: Option<AskInput>,
    grants: Option<GrantInput>,
    inbox: Rc<RefCell<Inbox>>,
    /// Asks (grants on worker 0) sent, the inputs' next time.
    sent: u64,
}

/// Builds the asks' and the grants' dataflows (identically on every worker, in this order); what
/// this worker receives lands in its [`HandoutEnds`]'s inbox.
pub(super) fn build_handout_dataflows(worker: &mut timely::worker::Worker) -> HandoutEnds {
    let inbox = Rc::new(RefCell::new(Inbox::default()));
    let mut asks = AskInput::new();
    let mut grants = GrantInput::new();
    build_inbox(
        worker,
        &mut asks,
        ("asks", |_: &Ask| 0),
        &inbox,
        (
            |inbox: &mut Inbox, a: Ask| inbox.asks.push_back(a.from),
            |inbox: &mut Inbox| inbox.asks_closed = true,
        ),
    );
    build_inbox(
        worker,
        &mut grants,
        ("grants", |g: &Grant| g.to as u64),
        &inbox,
        (
            |inbox: &mut Inbox, g: Grant| inbox.grants.push_back(g.view),
            |inbox: &mut Inbox| inbox.grants_closed = true,
        ),
    );
    HandoutEnds {
        asks: Some(asks),
        // Only worker 0 grants.
        grants: (worker.index() == 0).then_some(grants),
        inbox,
        sent: 0,
    }
}

/// What a worker's wait for a view came to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Granted {
    /// Map this view.
    View(u32),
    /// Nothing yet: keep stepping.
    Waiting,
    /// No view is left for this worker (worker 0 said so, or closed its grants).
    Ended,
}

impl HandoutEnds {
    /// Asks worker 0 for a view (nothing after [`HandoutEnds::end_asks`]).
    pub(super) fn ask(&mut self, from: u32) {
        if let Some(asks) = self.asks.as_mut() {
            asks.send(Ask { from });
            self.sent += 1;
            asks.advance_to(self.sent);
        }
    }

    /// The grant this worker received, if any.
    pub(super) fn granted(&mut self) -> Granted {
        let mut inbox = self.inbox.borrow_mut();
        match inbox.grants.pop_front() {
            Some(Some(view)) => Granted::View(view),
            Some(None) => Granted::Ended,
            None if inbox.grants_closed => Granted::Ended,
            None => Granted::Waiting,
        }
    }

    /// This worker asks no more: closes its asks.
    pub(super) fn end_asks(&mut self) {
        self.asks = None;
    }

    /// Worker 0: answers every ask received from `handout`; returns whether it answered any.
    pub(super) fn serve(&mut self, handout: &mut Handout) -> bool {
        let asks: Vec<u32> = self.inbox.borrow_mut().asks.drain(..).collect();
        let Some(grants) = self.grants.as_mut() else {
            return false;
        };
        for &to in &asks {
            let view = handout.grant(to);
            grants.send(Grant { to, view });
        }
        if !asks.is_empty() {
            self.sent += 1;
            grants.advance_to(self.sent);
        }
        !asks.is_empty()
    }

    /// Worker 0: whether it may stop serving: every worker has closed its asks, or has been told
    /// that no view is left (and, being done, closes its asks in turn).
    pub(super) fn served(&self, handout: &Handout) -> bool {
        let inbox = self.inbox.borrow();
        inbox.asks.is_empty() && (inbox.asks_closed || handout.all_ended())
    }

    /// Closes this worker's grants (worker 0, once it has served every ask).
    pub(super) fn end_grants(&mut self) {
        self.grants = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fresh job hands out every view once, in view order, whoever asks; a worker told that
    /// none is left stays told, and the hand-out ends once every worker was told.
    #[test]
    fn every_view_is_handed_out_once_in_view_order_to_whoever_asks() {
        let mut h = Handout::new(5, &[0, 0, 0], 3);
        assert_eq!(h.skipped(), 0);
        // Worker 1 is slow: it asks once while the others ask again and again.
        let got: Vec<(u32, Option<u32>)> = [0, 2, 1, 0, 2, 0, 2, 0]
            .into_iter()
            .map(|w| (w, h.grant(w)))
            .collect();
        assert_eq!(
            got,
            [
                (0, Some(0)),
                (2, Some(1)),
                (1, Some(2)),
                (0, Some(3)),
                (2, Some(4)),
                (0, None),
                (2, None),
                (0, None)
            ]
        );
        assert!(!h.all_ended(), "worker 1 has not been told yet");
        assert_eq!(h.grant(1), None);
        assert!(h.all_ended());
    }

    /// Resumed: views every partition holds are skipped, a view some partition lacks is handed
    /// out even when the others hold it.
    #[test]
    fn views_every_partition_holds_are_not_handed_out() {
        let mut h = Handout::new(6, &[4, 2, 5], 3);
        assert_eq!(h.skipped(), 2);
        let views: Vec<u32> = std::iter::from_fn(|| h.grant(1)).collect();
        assert_eq!(views, [2, 3, 4, 5]);
        let mut all = Handout::new(3, &[3, 3], 2);
        assert_eq!((all.skipped(), all.grant(0)), (3, None));
    }

    /// A stopped hand-out (the job failed) gives nothing more.
    #[test]
    fn a_stopped_handout_gives_nothing_more() {
        let mut h = Handout::new(4, &[0, 0], 2);
        assert_eq!(h.grant(1), Some(0));
        h.stop();
        assert_eq!((h.grant(0), h.grant(1)), (None, None));
        assert!(h.all_ended());
    }

    /// Two workers on one timely worker's dataflows: the asks reach worker 0, its grants come
    /// back in the order asked, and once it closes its grants a waiting worker ends.
    #[test]
    fn asks_and_grants_travel_over_the_dataflows() {
        timely::execute_directly(|worker| {
            let mut ends = build_handout_dataflows(worker);
            let mut h = Handout::new(2, &[0], 1);
            for _ in 0..3 {
                ends.ask(0);
            }
            for _ in 0..100 {
                worker.step();
                if !ends.inbox.borrow().asks.is_empty() {
                    break;
                }
            }
            assert_eq!(ends.inbox.borrow().asks.len(), 3);
            assert!(ends.serve(&mut h));
            let mut got = Vec::new();
            for _ in 0..100 {
                worker.step();
                match ends.granted() {
                    Granted::Waiting => {}
                    g => got.push(g),
                }
                if got.len() == 3 {
                    break;
                }
            }
            assert_eq!(got, [Granted::View(0), Granted::View(1), Granted::Ended]);
            ends.end_asks();
            for _ in 0..100 {
                worker.step();
            }
            assert!(ends.served(&h));
            ends.end_grants();
            for _ in 0..100 {
                worker.step();
            }
            assert_eq!(ends.granted(), Granted::Ended, "grants closed");
        });
    }
}
