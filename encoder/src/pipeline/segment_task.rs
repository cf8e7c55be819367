//! The segments ([`crate::segments`]) computed beside the encode: they depend on the Gaussians'
//! geometry and the masks' record, not on the embeddings, so [`Encoder::run`](super::Encoder::run)
//! starts them before the fronts are built and collects them after the encode.
//!
//! The segmentation's parallel stages run on a rayon pool of its own, [`segment_threads`]
//! threads, so the encode's host work (SAM post-processing on the global pool, the rasterizer
//! threads, the label and `a_kj` threads) keeps the rest of the cores. When a rasterizer keeps
//! its views' sums (and the masks' record) on its GPU, the encode's per-view host work is light:
//! the segmentation then gets all the threads at once ([`SegmentTask::widen`]; its neighbour
//! search takes them between its rounds); if it outlasts the encode (a large scene, few views),
//! its remaining stages get all the threads too. It reads the encode's own copy of the
//! Gaussians ([`super::scene_load`]: one load, shared, never cloned) and lets go of it once the
//! Gaussians' geometry is made, keeping a copy of the means until its edge geometry is made
//! (the passes after the masks' record need only the count). The encode's tail keeps the
//! centres only, so the rest of the scene is freed when the later of the two lets go, before
//! the tail's peak. Its own memory it holds while it runs; when that overlaps the encode's peak
//! (its tail), the two add up (docs/guide/lifting.md, memory model).
//!
//! The mask term of the weights needs every view's masks: the k-NN search runs as soon as the
//! scene is loaded (while the encode sets up its models), the weights and the merge passes once
//! the encode hands over its masks' record (after its last view, while it reduces the
//! embeddings).
//!
//! Nothing is written here: the caller writes `segments.safetensors` after the encode
//! succeeded. A task dropped without [`SegmentTask::finish`] (the encode failed) is stopped
//! ([`SegmentControl::stop`]) and joined, so no thread outlives the run.

use std::sync::{Arc, mpsc};
use std::thread::JoinHandle;
use std::time::Instant;

use slag_common::mask_record::MaskRecord;
use slag_common::scene::Gaussians;
use slag_common::segments::Segments;
use slag_common::{Error, Result};

use crate::config::EncodeConfig;
use crate::segments::{SegmentControl, SegmentStats};

/// Threads of the segmentation's pool while the encode runs, for an encode of `threads` threads
/// ([`crate::config::ExecutionConfig::resolved_threads`]): a quarter of them, at least one (4 of
/// 16 host cores), so the encode keeps three quarters of the cores. A segmentation still
/// running when the encode is done gets all `threads` for the stages left
/// ([`SegmentTask::finish`]).
pub fn segment_threads(threads: usize) -> usize {
    (threads / 4).max(1)
}

/// What a segmentation thread hands back: `None` when it was stopped.
type Outcome = Result<Option<(Segments, SegmentStats)>>;

/// A segmentation running on a thread of its own, its parallel stages on a pool of its own.
/// Dropping it unfinished stops it and waits for its thread.
pub struct SegmentTask {
    ctl: Arc<SegmentControl>,
    handle: Option<JoinHandle<Outcome>>,
    threads: usize,
    /// Threads of the pool it was given since ([`SegmentTask::widen`]).
    widened_to: std::sync::OnceLock<usize>,
}

/// What [`SegmentTask::finish`] returns.
pub struct Segmented {
    /// The segments, for `segments.safetensors`.
    pub segments: Segments,
    /// The segmentation's own figures (its `seconds` run beside the encode).
    pub stats: SegmentStats,
    /// Threads of its pool while the encode ran.
    pub threads: usize,
    /// Threads it was given when it outlasted the encode's views (the device reduction) or the
    /// whole encode; `None`: it was done by then.
    pub widened_to: Option<usize>,
    /// Seconds the caller waited for it after the encode (0 when it was already done).
    pub waited_s: f64,
}

impl SegmentTask {
    /// Segments the Gaussians that come on `scene` (the encode's load of `c`'s `.ply`,
    /// [`super::scene_load::SceneLoad`]) with `c.segments.params`, on a thread of its own with
    /// its parallel stages on a new pool of [`segment_threads`]`(threads)` threads; returns at
    /// once. The neighbour graph is built as soon as the scene comes (a closed channel: the load
    /// failed, and the encode reports it); the weights wait for the masks' record that the
    /// encode sends on `masks` when its last view is done (a closed channel: geometry only).
    ///
    /// Errors: [`Error::Internal`] when the thread or its pool cannot be started (the
    /// segmentation's own errors come from [`SegmentTask::finish`]).
    pub fn start(
        c: &EncodeConfig,
        threads: usize,
        scene: mpsc::Receiver<Arc<Gaussians>>,
        masks: mpsc::Receiver<Arc<MaskRecord>>,
    ) -> Result<Self> {
        let threads = segment_threads(threads);
        let ply = c.ply();
        let params = c.segments.params;
        let ctl = Arc::new(SegmentControl::new(Some(pool(threads)?)));
        let shared = Arc::clone(&ctl);
        let handle = std::thread::Builder::new()
            .name("slag-segments".into())
            .spawn(move || -> Outcome {
                let out = match wait_for(&scene, &shared) {
                    // Stopped, or no scene (the encode fails with the load's error).
                    None => Ok(None),
                    Some(g) => crate::segments::segment_with(
                        g,
                        &params,
                        &ply.display().to_string(),
                        &shared,
                        || wait_for(&masks, &shared),
                    ),
                };
                // The graph's many small allocations were freed in this pool's malloc arenas,
                // which glibc keeps for reuse: given back, so that the encode's peak does not
                // carry them (1.9 GiB at 2M Gaussians on an H100 host).
                release_freed_heap();
                if let Err(e) = &out {
                    // Said at once; the run fails with it after the encode.
                    tracing::error!(
                        "geometric segments failed ({e}); the encode goes on, then the run fails"
                    );
                }
                out
            })
            .map_err(|e| Error::internal(format!("segmentation thread: {e}")))?;
        Ok(SegmentTask {
            ctl,
            handle: Some(handle),
            threads,
            widened_to: std::sync::OnceLock::new(),
        })
    }

    /// Gives the segmentation's stages from now on (and its neighbour search's rounds left) a
    /// pool of `threads` threads, while the encode still runs but leaves the host's cores idle
    /// (its views' sums and the masks' record stay on the GPU). Once only; a pool that cannot be
    /// started is logged and the segmentation keeps its own.
    pub fn widen(&self, threads: usize) {
        let done = self.handle.as_ref().is_none_or(|h| h.is_finished());
        if done || threads <= self.threads || self.widened_to.get().is_some() {
            return;
        }
        match pool(threads) {
            Ok(p) => {
                self.ctl.set_pool(p);
                let _ = self.widened_to.set(threads);
            }
            Err(e) => tracing::warn!(error = %e, "segments keep their pool"),
        }
    }

    /// Waits for the segmentation and returns its result. When it is still running, its stages
    /// from now on run on a new pool of `threads` threads (the encode's, idle now), and its
    /// tiles may hold [`crate::segments::TILES_IN_FLIGHT_BYTES_ALONE`] at once (the encode's
    /// memory is let go by now), so that more of them run at once.
    ///
    /// Errors: the segmentation's ([`crate::segments::segment`]),
    /// [`Error::Internal`] when its thread panicked or a pool cannot be started.
    pub fn finish(mut self, threads: usize) -> Result<Segmented> {
        let t0 = Instant::now();
        let handle = self
            .handle
            .take()
            .ok_or_else(|| Error::internal("segmentation already collected"))?;
        self.ctl
            .set_in_flight_bytes(crate::segments::TILES_IN_FLIGHT_BYTES_ALONE);
        let widened = self.widened_to.get().copied();
        let pool_threads = widened.unwrap_or(self.threads);
        let widened_to = if handle.is_finished() || threads <= pool_threads {
            widened
        } else {
            self.ctl.set_pool(pool(threads)?);
            Some(threads)
        };
        let out = handle
            .join()
            .map_err(|_| Error::internal("the segmentation thread panicked"))??;
        let (segments, stats) =
            out.ok_or_else(|| Error::internal("the segmentation stopped unasked"))?;
        Ok(Segmented {
            segments,
            stats,
            threads: self.threads,
            widened_to,
            waited_s: t0.elapsed().as_secs_f64(),
        })
    }
}

/// What comes on `rx` (the scene, the masks' record), waited for until it comes, the channel
/// closes (`None`) or the segmentation is stopped (`None`; the caller then sees the stop).
fn wait_for<T>(rx: &mpsc::Receiver<T>, ctl: &SegmentControl) -> Option<T> {
    loop {
        match rx.recv_timeout(std::time::Duration::from_millis(50)) {
            Ok(r) => return Some(r),
            Err(mpsc::RecvTimeoutError::Disconnected) => return None,
            Err(mpsc::RecvTimeoutError::Timeout) if ctl.is_stopped() => return None,
            Err(mpsc::RecvTimeoutError::Timeout) => {}
        }
    }
}

/// Returns the free pages of every malloc arena to the system (glibc's `malloc_trim(0)`); a
/// no-op on other C libraries.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[allow(unsafe_code)]
fn release_freed_heap() {
    // SAFETY: malloc_trim has no preconditions; it takes each arena's lock itself, so other
    // threads may allocate meanwhile.
    unsafe {
        libc::malloc_trim(0);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn release_freed_heap() {}

/// A rayon pool of `threads` threads named `slag-segments-<i>`.
fn pool(threads: usize) -> Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("slag-segments-{i}"))
        .build()
        .map_err(|e| Error::internal(format!("segmentation thread pool: {e}")))
}

impl Drop for SegmentTask {
    fn drop(&mut self) {
        if let Some(h) = self.handle.take() {
            self.ctl.stop();
            // Its result is unwanted; a panic there has nothing left to spoil.
            let _ = h.join();
        }
    }
}
