//! The geometric segments ([`crate::segments`]) computed beside the encode: they depend on the
//! Gaussians' geometry alone, not on the embeddings, so [`Encoder::run`](super::Encoder::run)
//! starts them before the fronts are built and collects them after the encode.
//!
//! The segmentation runs on a rayon pool of its own, [`segment_threads`] threads, so the
//! encode's host work (SAM post-processing on the global pool, the rasterizer threads, the
//! label and `a_kj` threads) keeps the rest of the cores. It reloads the `.ply` itself (the
//! encode's copy lives inside the pool) and holds its memory only while it runs: on the
//! 2M-Gaussian scene it ends long before the encode's tail, where the encode's peak falls
//! (docs/guide/lifting.md, memory model).
//!
//! Nothing is written here: the caller writes `segments.safetensors` after the encode
//! succeeded. A task dropped without [`SegmentTask::finish`] (the encode failed) is stopped
//! ([`crate::segments::segment_unless_stopped`]) and joined, so no thread outlives the run.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::Instant;

use slag_common::segments::Segments;
use slag_common::{Error, Result};

use crate::config::EncodeConfig;
use crate::segments::SegmentStats;

/// Threads of the segmentation's pool for an encode of `threads` threads
/// ([`crate::config::ExecutionConfig::resolved_threads`]): a quarter of them, at least one (4 of
/// 16 host cores). Enough for the segmentation to end well within the encode at the goal's scale
/// (2M Gaussians), while the encode keeps three quarters of the cores.
pub fn segment_threads(threads: usize) -> usize {
    (threads / 4).max(1)
}

/// What a segmentation thread hands back: `None` when it was stopped.
type Outcome = Result<Option<(Segments, SegmentStats)>>;

/// A segmentation running on its own thread and rayon pool. Dropping it unfinished stops it and
/// waits for its thread.
pub struct SegmentTask {
    stop: Arc<AtomicBool>,
    handle: Option<JoinHandle<Outcome>>,
    threads: usize,
}

/// What [`SegmentTask::finish`] returns.
pub struct Segmented {
    /// The segments, for `segments.safetensors`.
    pub segments: Segments,
    /// The segmentation's own figures (its `seconds` run beside the encode).
    pub stats: SegmentStats,
    /// Threads of its pool.
    pub threads: usize,
    /// Seconds the caller waited for it after the encode (0 when it was already done).
    pub waited_s: f64,
}

impl SegmentTask {
    /// Loads `c`'s `.ply` and segments it with `c.segments.params` on a new pool of
    /// [`segment_threads`]`(threads)` threads, on a thread of its own; returns at once.
    ///
    /// Errors: [`Error::Internal`] when the thread or its pool cannot be started (the
    /// segmentation's own errors come from [`SegmentTask::finish`]).
    pub fn start(c: &EncodeConfig, threads: usize) -> Result<Self> {
        let threads = segment_threads(threads);
        let stop = Arc::new(AtomicBool::new(false));
        let ply = c.ply();
        let params = c.segments.params;
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("slag-segments-{i}"))
            .build()
            .map_err(|e| Error::internal(format!("segmentation thread pool: {e}")))?;
        let flag = Arc::clone(&stop);
        let handle = std::thread::Builder::new()
            .name("slag-segments".into())
            .spawn(move || {
                let out = pool.install(|| -> Outcome {
                    let g = slag_common::scene::load_ply(
                        &ply,
                        slag_common::scene::PlyLoadOptions::default(),
                    )?;
                    crate::segments::segment_unless_stopped(
                        &g,
                        &params,
                        &ply.display().to_string(),
                        &flag,
                    )
                });
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
            stop,
            handle: Some(handle),
            threads,
        })
    }

    /// Waits for the segmentation and returns its result.
    ///
    /// Errors: the segmentation's ([`crate::segments::segment`], the `.ply` unreadable),
    /// [`Error::Internal`] when its thread panicked.
    pub fn finish(mut self) -> Result<Segmented> {
        let t0 = Instant::now();
        let handle = self
            .handle
            .take()
            .ok_or_else(|| Error::internal("segmentation already collected"))?;
        let out = handle
            .join()
            .map_err(|_| Error::internal("the segmentation thread panicked"))??;
        let (segments, stats) =
            out.ok_or_else(|| Error::internal("the segmentation stopped unasked"))?;
        Ok(Segmented {
            segments,
            stats,
            threads: self.threads,
            waited_s: t0.elapsed().as_secs_f64(),
        })
    }
}

impl Drop for SegmentTask {
    fn drop(&mut self) {
        if let Some(h) = self.handle.take() {
            self.stop.store(true, Ordering::Relaxed);
            // Its result is unwanted; a panic there has nothing left to spoil.
            let _ = h.join();
        }
    }
}
