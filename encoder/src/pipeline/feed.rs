//! Where a pool's front workers take their views ([`ViewFeed`]: the encode's counter, or views
//! handed from outside, [`HandedViews`]) and what a pool fed from outside forwards of each view
//! ([`Forwarded`]); the pool that runs on them is `handed::run_handed`.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, mpsc};
use std::time::Duration;

use crate::aggregate::ImageContribution;
use crate::report::ImageWork;

/// How long a waiting front worker sleeps between two looks at whether the run failed.
const FAILURE_POLL: Duration = Duration::from_millis(50);

/// One view's result, forwarded by the pool's image thread: the view's index in the job's view
/// list, its work figures (the same [`ImageWork`] the encode's back workers sum) and its `a_kj`.
pub(crate) struct Forwarded {
    pub(crate) view: usize,
    pub(crate) work: ImageWork,
    pub(crate) contribution: ImageContribution,
}

/// The views handed to a pool's front workers from outside: a front that is free takes the next
/// one; the feeder ([`ViewsFeeder`]) sees how many are still waiting for a front or in one.
pub(crate) struct HandedViews {
    views: Mutex<mpsc::Receiver<usize>>,
    /// Views whose front work is done (handed to the back queue, or failed).
    fronted: AtomicUsize,
    /// The feeder's thread, woken whenever a front becomes free.
    feeder: std::thread::Thread,
    /// A test-only wait before each view's front ([`crate::distributed::MAP_DELAY_VAR`]).
    delay: Option<Duration>,
}

/// The feeding end of [`HandedViews`], held by the thread that hands the views out.
pub(crate) struct ViewsFeeder {
    /// `None` once closed: the fronts end when the views sent so far are taken.
    to_fronts: Option<mpsc::Sender<usize>>,
    handed: usize,
    views: Arc<HandedViews>,
}

/// A channel of views to a pool's fronts, fed from the calling thread (woken whenever a front
/// becomes free); each front waits `delay` before each view it takes.
pub(crate) fn handed_views(delay: Option<Duration>) -> (ViewsFeeder, Arc<HandedViews>) {
    let (tx, rx) = mpsc::channel();
    let views = Arc::new(HandedViews {
        views: Mutex::new(rx),
        fronted: AtomicUsize::new(0),
        feeder: std::thread::current(),
        delay,
    });
    let feeder = ViewsFeeder {
        to_fronts: Some(tx),
        handed: 0,
        views: Arc::clone(&views),
    };
    (feeder, views)
}

impl ViewsFeeder {
    /// Hands view `view` (an index into the run's views) to the next free front; false when the
    /// feeder is closed or the pool has ended.
    pub(crate) fn hand(&mut self, view: usize) -> bool {
        let sent = self
            .to_fronts
            .as_ref()
            .is_some_and(|tx| tx.send(view).is_ok());
        self.handed += usize::from(sent);
        sent
    }

    /// Views handed whose front work is not done: waiting for a front, or in one.
    pub(crate) fn in_fronts(&self) -> usize {
        let fronted = self.views.fronted.load(Ordering::SeqCst);
        self.handed.saturating_sub(fronted)
    }

    /// No more views: the fronts end once they have taken the views handed so far.
    pub(crate) fn close(&mut self) {
        self.to_fronts = None;
    }
}

/// Where a pool's front workers take their views: the next of a counter over the run's views
/// (the encode), or those handed from outside (the cluster).
pub(super) enum ViewFeed {
    Counter(AtomicUsize),
    Handed(Arc<HandedViews>),
}

impl ViewFeed {
    /// The next view for a free front worker of a run of `n_views` views, `None` when no view
    /// is left or `failed()` says the run failed. A handed view waits for the feeder (polling
    /// `failed` meanwhile); the front that takes it reports it done with [`ViewFeed::fronted`].
    pub(super) fn next(&self, n_views: usize, failed: impl Fn() -> bool) -> Option<usize> {
        match self {
            ViewFeed::Counter(next) => {
                let i = next.fetch_add(1, Ordering::SeqCst);
                (i < n_views && !failed()).then_some(i)
            }
            ViewFeed::Handed(h) => loop {
                if failed() {
                    return None;
                }
                let taken = h.views.lock().ok()?.recv_timeout(FAILURE_POLL);
                match taken {
                    Ok(i) => {
                        if let Some(d) = h.delay {
                            std::thread::sleep(d);
                        }
                        return Some(i);
                    }
                    Err(mpsc::RecvTimeoutError::Timeout) => {}
                    Err(mpsc::RecvTimeoutError::Disconnected) => return None,
                }
            },
        }
    }

    /// A front worker is done with the view it took (handed on or failed): it is free again.
    pub(super) fn fronted(&self) {
        if let ViewFeed::Handed(h) = self {
            h.fronted.fetch_add(1, Ordering::SeqCst);
            h.feeder.unpark();
        }
    }
}
