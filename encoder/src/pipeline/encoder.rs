//! [`Encoder`]: an [`EncodeConfig`] checked and run in this process.

use slag_common::Result;

use super::build::{self, Fronts};
use super::scene_load::SceneLoad;
use super::segment_task::SegmentTask;
use crate::config::{ConfigError, EncodeConfig};
use crate::report::{Report, SegmentsOutput};

/// One encode run of this process (the Semantic Embedding stage over a scene): front workers
/// (decode → masks → CLIP crops) and one rasterizer per GPU (raster → `a_kj`), then the reduction
/// to `E_k`, written to [`crate::config::OutputConfig::dir`]
/// ([`super::encode_pool`]).
///
/// ```no_run
/// use slag_encoder::config::{EncodeConfig, MasksConfig};
/// use slag_encoder::pipeline::Encoder;
///
/// let mut config = EncodeConfig::new("scene", "clip-visual.onnx", "out");
/// config.masks = MasksConfig::graph();
/// config.scene.every = 2;
/// let report = Encoder::new(config)?.run()?;
/// println!("{} Gaussians observed", report.counts.observed);
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
#[derive(Debug, Clone)]
pub struct Encoder {
    config: EncodeConfig,
}

impl Encoder {
    /// Checks `config` ([`EncodeConfig::validate`]); nothing is loaded yet.
    ///
    /// Errors: the [`ConfigError`] of the first setting that cannot run.
    pub fn new(config: EncodeConfig) -> std::result::Result<Self, ConfigError> {
        config.validate()?;
        Ok(Encoder { config })
    }

    /// The configuration this encoder runs.
    pub fn config(&self) -> &EncodeConfig {
        &self.config
    }

    /// Runs the encode and returns the report it wrote beside the embeddings
    /// (`mixture.safetensors`, with [`crate::config::OutputConfig::dense`]
    /// `embeddings.safetensors`, the optional forms, and `report.json`, each atomically, the
    /// report last), then, with [`crate::config::SegmentsConfig::enabled`],
    /// `segments.safetensors`. Sets rayon's global pool to
    /// [`crate::config::ExecutionConfig::threads`] unless the process already has one.
    ///
    /// The segments are computed beside the encode, from the start, on a pool of their own
    /// (a quarter of the threads, all of them for what is left once the encode is done:
    /// `pipeline::segment_task`), on the encode's own Gaussians (the `.ply` is loaded once, on
    /// a thread of its own while the models are set up: `pipeline::scene_load`), and written only once the encode has succeeded: a failed or
    /// killed encode leaves no segments file. When the segmentation fails, the encode still
    /// finishes and writes its complete outputs (the embeddings do not depend on the
    /// segments), and the run then returns the segmentation's error with no segments file:
    /// `slag-encoder segment` makes it later without re-encoding.
    ///
    /// Errors: unreadable scene or models, no GPU for the GPU rasterizer, a resource limit of
    /// the rasterizer ([`slag_common::Error::Limit`]), any worker's error (nothing that looks
    /// complete is written), I/O on the outputs; after the encode's outputs, the
    /// segmentation's errors ([`crate::segments::segment`]).
    pub fn run(&self) -> Result<Report> {
        let c = &self.config;
        if c.segments.enabled {
            // Refused before the encode, not after it.
            c.segments.params.validate()?;
        }
        crate::views::check_hold_out(c.scene.hold_out_every)?;
        c.scene.views.validate()?;
        let threads = build::setup_threads(c);
        let scene = build::scene_input(c);
        // Started before anything else; dropped (stopped and joined) on any early return. The
        // scene is loaded once, for both: the segments build their neighbour graph as soon as
        // it is loaded and weigh it when the masks' record comes.
        let (record_tx, record_rx) = std::sync::mpsc::channel();
        let (shared, segments) = start_segments(c, &scene, threads, record_rx)?;
        let mut record = None;
        let gpus = build::gpu_count(c);
        let t_models = std::time::Instant::now();
        let fronts = build::build_fronts(c, gpus, threads)?;
        let params = build::encode_params(c);
        let mut header = build::report_header(c, threads);
        header.timings.models = t_models.elapsed().as_secs_f64();
        header.models.execution_provider = Some(fronts.provider);
        header.models.execution_providers = Some(fronts.providers.clone());
        let Fronts {
            stages, services, ..
        } = fronts;
        // The views' sums and the masks' record stay on the GPU: the host's cores, but for the
        // fronts', are the segments' from the first kept view on.
        let widen_segments = || {
            if let Some(task) = segments.as_ref() {
                task.widen(threads);
            }
        };
        let pool = super::EncodePool {
            scene: &scene,
            shared,
            fronts: stages,
            params: &params,
            on_device_keep: Some(&widen_segments),
        };
        let report = super::encode_pool_sharing(
            pool,
            |g| build::make_rasterizers(c, g),
            header,
            |r, on_device| {
                if let Some(r) = r {
                    // A segmentation that already failed has hung up: it needs no record then.
                    let _ = record_tx.send(std::sync::Arc::clone(&r));
                    record = Some(r);
                }
                // The device reduces from here on: the host's cores are the segments'.
                if let (Some(task), true) = (segments.as_ref(), on_device) {
                    task.widen(threads);
                }
            },
        )?;
        drop(record_tx);
        log_clip_services(&services);
        finish_with_segments(c, report, record.as_deref(), segments, threads)
    }
}

/// The scene's shared load and the segmentation beside the encode (with `c.segments`, else
/// neither): the load starts at once on a thread of its own, the segmentation on
/// [`SegmentTask::start`]'s pool, waiting for the masks' record on `record_rx`.
///
/// Errors: a thread or pool that cannot be started ([`Error::Internal`](slag_common::Error)).
fn start_segments(
    c: &EncodeConfig,
    scene: &super::SceneInput,
    threads: usize,
    record_rx: std::sync::mpsc::Receiver<std::sync::Arc<slag_common::mask_record::MaskRecord>>,
) -> Result<(Option<SceneLoad>, Option<SegmentTask>)> {
    if !c.segments.enabled {
        return Ok((None, None));
    }
    let (load, loaded) = SceneLoad::start(scene.ply.clone())?;
    let task = SegmentTask::start(c, threads, loaded, record_rx)?;
    Ok((Some(load), Some(task)))
}

/// Logs each GPU's shared CLIP service's work (runs, crops, seconds).
fn log_clip_services(services: &[crate::clip::ClipService]) {
    for s in services {
        let st = s.stats();
        tracing::info!(
            device = s.device_label(),
            runs = st.runs,
            crops = st.crops,
            run_s = st.run_s,
            "CLIP service"
        );
    }
}

/// After a successful encode: the masks' record written (when kept), then, with `segments`,
/// the segments waited for and written, and the report written again with them, so that it
/// stays the run's last file. A failed or killed run leaves neither file looking complete; each
/// is optional and atomic (`partition` without the segments simply stores none).
///
/// Errors: I/O; the segmentation's ([`write_segments`]).
pub(crate) fn finish_with_segments(
    c: &EncodeConfig,
    mut report: Report,
    record: Option<&slag_common::mask_record::MaskRecord>,
    segments: Option<SegmentTask>,
    threads: usize,
) -> Result<Report> {
    let mask_record = match record {
        Some(r) => Some(write_mask_record(c, r)?),
        None => None,
    };
    let Some(task) = segments else {
        return Ok(report);
    };
    let mut segmented = write_segments(c, task, threads)?;
    segmented.mask_record = mask_record.filter(|_| segmented.stats.mask_record.is_some());
    report.segments = Some(segmented);
    super::finish::write_report_file(&report)?;
    Ok(report)
}

/// Writes the masks' record to `<out>/mask-record.safetensors` (atomically), for
/// `slag-encoder segment` on this encode later.
///
/// Errors: I/O.
fn write_mask_record(
    c: &EncodeConfig,
    r: &slag_common::mask_record::MaskRecord,
) -> Result<std::path::PathBuf> {
    let dir = &c.output.dir;
    std::fs::create_dir_all(dir).map_err(|e| slag_common::Error::io(dir, e))?;
    let path = dir.join(slag_common::mask_record::FILE_NAME);
    r.write(&path)?;
    tracing::info!(
        gaussians = r.len(),
        slots = r.slots,
        bytes_per_gaussian = r.bytes_per_gaussian(),
        "masks' record written"
    );
    Ok(path)
}

/// Waits for `task` (on `threads` threads from now on, if it is still running; a spinner
/// shows the wait with the output's progress setting) and writes its segments to
/// `<out>/segments.safetensors` (atomically). Returns the report's record of them, its
/// `mask_record` left `None` for the caller.
///
/// Errors: the segmentation's ([`SegmentTask::finish`]), I/O.
fn write_segments(c: &EncodeConfig, task: SegmentTask, threads: usize) -> Result<SegmentsOutput> {
    let spinner = super::pool::tail_spinner(c.output.progress, "segments", "waiting");
    let done = task.finish(threads)?;
    spinner.finish_with_message(format!("waited {:.1} s", done.waited_s));
    let dir = &c.output.dir;
    std::fs::create_dir_all(dir).map_err(|e| slag_common::Error::io(dir, e))?;
    let path = dir.join(slag_common::segments::FILE_NAME);
    done.segments.write(&path)?;
    let stats = done.stats;
    tracing::info!(
        segments = stats.segments,
        gaussians = stats.gaussians,
        tiles = stats.tiles,
        seconds = stats.seconds,
        threads = done.threads,
        widened_to = done.widened_to,
        waited_s = done.waited_s,
        "geometric segments written"
    );
    Ok(SegmentsOutput {
        mask_record: None,
        path,
        stats,
        threads: done.threads,
        waited_s: done.waited_s,
        widened_to: done.widened_to,
    })
}
