//! The admission gate every scan passes, whichever interface asked (HTTP or ROS 2).
//!
//! A FIFO gate: a fair `tokio` semaphore of `max_scans` permits (default 1) taken after a
//! query's parameters are validated. A scan already fans out over every core (rayon), so
//! running two at once only interleaves them: both finish late and the order in which queries
//! are served becomes arbitrary, which is what made the tail latency grow with the number of
//! connections. One at a time in arrival order, a query waits for the scans ahead of it and no
//! longer. At most `max_queue` queries wait; one more is turned away at once ([`Busy`], with
//! the estimated seconds until the queue drains, from a moving average of recent scan times),
//! so the latency of accepted queries stays bounded by the queue length.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// The FIFO gate scans pass (module doc).
pub struct Admission {
    permits: Arc<tokio::sync::Semaphore>,
    max_scans: usize,
    max_queue: usize,
    waiting: AtomicUsize,
    busy: AtomicU64,
    /// Moving average of scan times, microseconds (0 until the first scan).
    scan_us: AtomicU64,
    /// When the oldest running scan started, microseconds after `epoch` (0: none running).
    running_since_us: AtomicU64,
    epoch: Instant,
}

/// A query turned away because the scan queue is full (HTTP answers 503 with `Retry-After`;
/// ROS 2 drops the prompt).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Busy {
    /// Requests waiting when it was turned away.
    pub waiting: usize,
    /// Seconds after which a retry is likely to be accepted (≥ 1).
    pub retry_after_s: u64,
}

/// Decrements the waiting count when a waiter leaves the queue (admitted, or cancelled by the
/// request timeout).
struct Waiting<'a>(&'a AtomicUsize);

impl Drop for Waiting<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}

impl Admission {
    /// A gate of `max_scans` permits (at least 1) and a queue of `max_queue` waiters.
    pub fn new(max_scans: usize, max_queue: usize) -> Admission {
        let max_scans = max_scans.max(1);
        Admission {
            permits: Arc::new(tokio::sync::Semaphore::new(max_scans)),
            max_scans,
            max_queue,
            waiting: AtomicUsize::new(0),
            busy: AtomicU64::new(0),
            scan_us: AtomicU64::new(0),
            running_since_us: AtomicU64::new(0),
            epoch: Instant::now(),
        }
    }

    /// Waits (FIFO) for a scan permit.
    ///
    /// Errors: [`Busy`] at once when `max_queue` requests already wait.
    pub async fn admit(&self) -> std::result::Result<tokio::sync::OwnedSemaphorePermit, Busy> {
        if let Ok(p) = self.permits.clone().try_acquire_owned() {
            return Ok(p);
        }
        let before = self.waiting.fetch_add(1, Ordering::SeqCst);
        let _w = Waiting(&self.waiting);
        if before >= self.max_queue {
            self.busy.fetch_add(1, Ordering::Relaxed);
            return Err(Busy {
                waiting: before,
                retry_after_s: self.retry_after_s(before),
            });
        }
        // The semaphore is never closed; a closed one would mean no scan can run.
        self.permits
            .clone()
            .acquire_owned()
            .await
            .map_err(|_| Busy {
                waiting: before,
                retry_after_s: 1,
            })
    }

    /// Estimated seconds until `waiting` queued scans and the running ones are done (≥ 1): the
    /// rounds of `max_scans` scans ahead times the time one takes, the larger of the moving
    /// average and how long the running scan has already taken (so the first burst, before any
    /// scan has finished, and a scan slower than the recent ones are not underestimated).
    fn retry_after_s(&self, waiting: usize) -> u64 {
        let mean_s = self.scan_us.load(Ordering::Relaxed) as f64 * 1e-6;
        let since = self.running_since_us.load(Ordering::Relaxed);
        let running_s = if since == 0 {
            0.0
        } else {
            (self.epoch.elapsed().as_micros() as f64 * 1e-6 - since as f64 * 1e-6).max(0.0)
        };
        let scan_s = mean_s.max(running_s);
        let rounds = (waiting + self.max_scans) as f64 / self.max_scans as f64;
        (rounds * scan_s).ceil().max(1.0) as u64
    }

    /// Marks a scan as started (for [`Self::retry_after_s`]); the oldest running one is kept.
    pub(crate) fn started(&self) {
        let now = (self.epoch.elapsed().as_micros() as u64).max(1);
        let _ =
            self.running_since_us
                .compare_exchange(0, now, Ordering::Relaxed, Ordering::Relaxed);
    }

    /// Folds one scan's duration into the moving average (weight 1/8) and clears the running
    /// mark.
    pub(crate) fn record(&self, took: Duration) {
        self.running_since_us.store(0, Ordering::Relaxed);
        let us = took.as_micros().min(u64::MAX as u128) as u64;
        let old = self.scan_us.load(Ordering::Relaxed);
        let new = if old == 0 { us } else { old - old / 8 + us / 8 };
        self.scan_us.store(new, Ordering::Relaxed);
    }

    /// `{"max_scans", "running", "waiting", "max_queue", "rejected_busy", "mean_scan_ms"}`.
    pub fn stats(&self) -> serde_json::Value {
        serde_json::json!({
            "max_scans": self.max_scans,
            "running": self.max_scans - self.permits.available_permits().min(self.max_scans),
            "waiting": self.waiting.load(Ordering::SeqCst),
            "max_queue": self.max_queue,
            "rejected_busy": self.busy.load(Ordering::Relaxed),
            "mean_scan_ms": self.scan_us.load(Ordering::Relaxed) as f64 / 1e3,
        })
    }
}
