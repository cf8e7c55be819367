//! The end of an encode: the reduction of every image's `a_kj` to the mixture form
//! (`mixture.safetensors`, the default output) and, when asked, to the dense `E_k` streamed into
//! `embeddings.safetensors` in the same pass; the per-level files; and `report.json`, written
//! last so that its presence means the run completed.
//!
//! [`OutputFiles`] is the writing order both encoders keep: this process's ([`finish`]) and the
//! cluster's ([`crate::distributed`], whose reduction runs in the dataflow).

use std::path::{Path, PathBuf};
use std::time::Instant;

use slag_common::embeddings::{EmbeddingsWriter, StoredPrecision};
use slag_common::io::{remove_stale, write_atomic};
use slag_common::{Error, Result};

use super::pool::Pooled;
use super::reduction::{
    DeviceReduceMemory, ReducedOutputs, TailInputs, dense_writer, reduce_on_device,
};
use super::{EncodeParams, SceneInput};
use crate::aggregate;
use crate::raster::WeightRasterizer;
use crate::report::{
    ClusterOutputs, Counts, FormOutputs, LevelOutput, Outputs, QueueStats, Report, StageTimings,
};
use crate::segments::SceneHandle;
use slag_common::mixture::SparseMixture;

/// The two files an encode writes into its output folder, each path whether written or not: the
/// dense embeddings (a one-process encode writes them only when asked), then the report, last.
pub(crate) struct OutputFiles {
    /// `<out>/embeddings.safetensors`.
    pub(crate) embeddings: PathBuf,
    /// `<out>/report.json`.
    pub(crate) report: PathBuf,
}

impl OutputFiles {
    /// The files of `out_dir`. A report of an earlier run there is removed first: it must not
    /// vouch for embeddings while they are being replaced.
    ///
    /// Errors: I/O removing it.
    pub(crate) fn begin(out_dir: &Path) -> Result<Self> {
        let files = OutputFiles {
            embeddings: out_dir.join("embeddings.safetensors"),
            report: out_dir.join("report.json"),
        };
        remove_stale(&files.report)?;
        Ok(files)
    }

    /// Records the outputs in `report` (the dense embeddings file and its size read back from
    /// disk, `null` and 0 when this run did not write it; `cluster` and `forms` as given) and writes it to `report.json` atomically: the run's last file.
    ///
    /// Errors: the report cannot be serialised ([`Error::Internal`]), I/O.
    pub(crate) fn write_report(
        &self,
        mut report: Report,
        precision: StoredPrecision,
        cluster: Option<ClusterOutputs>,
        forms: Option<FormOutputs>,
    ) -> Result<Report> {
        // A dense file of an earlier run is removed before the reduction: one here is this run's.
        let (embeddings, embeddings_bytes) = match std::fs::metadata(&self.embeddings) {
            Ok(m) => (Some(self.embeddings.clone()), m.len()),
            Err(_) => (None, 0),
        };
        report.outputs = Outputs {
            cluster,
            embeddings,
            embeddings_bytes,
            forms,
            precision,
            report: self.report.clone(),
        };
        write_report_file(&report)?;
        Ok(report)
    }
}

/// Writes `report` to its own path (`report.outputs.report`) atomically.
///
/// Errors: the report cannot be serialised ([`Error::Internal`]), I/O.
pub(crate) fn write_report_file(report: &Report) -> Result<()> {
    let json =
        serde_json::to_vec_pretty(report).map_err(|e| Error::internal(format!("report: {e}")))?;
    write_atomic(&report.outputs.report, &json)
}

/// The report's models: the rasterizers (the first as `rasterizer`), the front workers, the
/// masks' generator and the CLIP model.
fn record_models(
    models: &mut crate::report::Models,
    rasterizers: Vec<String>,
    fronts: usize,
    mask_name: String,
    model_id: &str,
) {
    models.rasterizer = rasterizers.first().cloned().unwrap_or_default();
    models.rasterizers = Some(rasterizers);
    (models.front_workers, models.masks) = (Some(fronts), mask_name);
    models.clip_model_id = model_id.to_string();
}

/// Reduces what the pool left ([`Pooled`]) and writes the outputs of `scene`'s encode into
/// [`EncodeParams::out_dir`]: `mixture.safetensors` with [`EncodeParams::mixture_keep`],
/// `embeddings.safetensors` with [`EncodeParams::dense`], the level files with
/// [`EncodeParams::levels`], each atomically, then `report.json` (`report` completed with the
/// models, the workers' shares, timings counted from `t_total` and counts). With
/// [`EncodeParams::progress`] a spinner on stderr shows each step of the tail (the reduction,
/// on the GPU or the CPU, then the write).
///
/// Errors: the reduction's, [`Error::Unobserved`] for views that observed no Gaussian or far
/// fewer than they should ([`crate::views::check_observed`]), I/O on the outputs; nothing that
/// looks complete is left then.
pub(crate) fn finish(
    scene: &SceneInput,
    pooled: Pooled,
    params: &EncodeParams,
    mut report: Report,
    t_total: Instant,
) -> Result<Report> {
    let Pooled {
        gaussians,
        dim,
        model_id,
        mask_name,
        fronts,
        rasterizers,
        mut store,
        level_stores,
        timings: mut t,
        mut counts,
        workers,
        queue,
        selection,
        mask_record: _,
        device,
        reduce_fallback,
        retired: _,
    } = pooled;
    crate::memory::log_rss("encode: every view");
    report.view_selection = Some(selection);
    report.workers = workers;
    record_models(
        &mut report.models,
        rasterizers,
        fronts,
        mask_name,
        &model_id,
    );

    // Only the centres are written from here on: the encode lets go of the rest of the geometry
    // (freed now, or copied out if the segments still read the scene, as they do until their
    // first stage is done).
    let centres = SceneHandle::into_means(gaussians).into_owned();
    let means = centres.as_slice();
    let n_gaussians = means.len();
    let files = OutputFiles::begin(&params.out_dir)?;
    let out = TailInputs {
        means,
        dim,
        params,
        model_id: &model_id,
        ply: scene.ply.display().to_string(),
    };
    let mut tail = reduce_tail(&out, device, &mut store, &files.embeddings)?;
    // Every device that reduced is among the spent rasterizers (none when the host reduced).
    counts.device_reduce_gpus = tail.spent.len();
    let spent = let_go(std::mem::take(&mut tail.spent));
    crate::memory::log_rss("encode: reduction");
    counts.spilled_images = store.spilled();
    record_reduction(&tail, reduce_fallback, n_gaussians, &mut t, &mut counts);
    crate::views::check_observed(report.view_selection.as_ref(), tail.observed, n_gaussians)
        .inspect_err(|_| drop(remove_stale(&files.embeddings)))?;
    let (mixture, mixture_s) = build_mixture(store, tail.sparse, tail.gather_s)?;
    let (level_files, levels_s) = write_levels(&out, &level_stores)?;
    drop(level_stores);

    let t0 = Instant::now();
    let mix_path = write_forms(&out, tail.writer, mixture.as_ref())?;
    t.write = tail.write_s + t0.elapsed().as_secs_f64();
    crate::memory::log_rss("encode: written");
    if let Ok(seconds) = spent.join() {
        tracing::debug!(target: "slag_encoder::pipeline", seconds, "rasterizers let go");
    }
    record_totals(&mut report, t, counts, queue, t_total);
    let forms = form_outputs(mixture.as_ref(), mix_path, mixture_s, level_files, levels_s);
    files.write_report(report, params.precision, None, Some(forms))
}

/// Drops the rasterizers that reduced (`spent`: their devices, and the records they kept) on a
/// thread of its own, beside the writes; returns the thread, to be joined before the encode
/// returns (no device outlives it), with the seconds it took.
fn let_go(spent: Vec<Box<dyn WeightRasterizer>>) -> std::thread::JoinHandle<f64> {
    std::thread::spawn(move || {
        let t0 = Instant::now();
        drop(spent);
        t0.elapsed().as_secs_f64()
    })
}

/// Records the tail's reduction in the timings `t` (its seconds, less the mixture's gathering)
/// and `counts` (where it ran, the fallback `reduce_fallback` if any, its chunks and the
/// observed Gaussians, also as a fraction of the scene's `n_gaussians`).
fn record_reduction(
    tail: &ReducedOutputs,
    reduce_fallback: Option<crate::report::DeviceReduceFallback>,
    n_gaussians: usize,
    t: &mut StageTimings,
    counts: &mut Counts,
) {
    // The mixture's own share of the pass (gathering its kept atoms between chunks) is counted
    // as the mixture's, not the reduction's: the tail's phases stay disjoint.
    t.reduce = tail.reduce_s - tail.gather_s;
    counts.device_reduce = tail.on_device;
    counts.device_reduce_fallback = reduce_fallback;
    counts.reduce_chunks = tail.chunks;
    counts.device_reduce_waves = tail.memory.waves;
    counts.device_reduce_peak_bytes = tail.memory.peak_bytes;
    counts.host_fold_peak_bytes = tail.host_fold_peak_bytes;
    counts.dense_fold = tail.dense_fold;
    counts.observed = tail.observed;
    counts.observed_fraction = tail.observed as f64 / n_gaussians.max(1) as f64;
}

/// The mixture's stored form from its reduced `sparse` parts (`None` without the mixture),
/// built after `store` is freed so that its buffers never add to the store's entries. Returns it
/// with the mixture's seconds: `gather_s` (its share of the reduction pass) plus the build.
///
/// Errors: the mixture's (inconsistent sparse parts).
fn build_mixture(
    store: aggregate::ContributionStore,
    sparse: Option<SparseMixture>,
    gather_s: f64,
) -> Result<(Option<slag_common::mixture::MixtureEmbeddings>, f64)> {
    let t0 = Instant::now();
    drop(store);
    let mixture = sparse
        .map(slag_common::mixture::MixtureEmbeddings::from_sparse)
        .transpose()?;
    let mixture_s = gather_s + t0.elapsed().as_secs_f64();
    crate::memory::log_rss("encode: mixture built");
    Ok((mixture, mixture_s))
}

/// Completes `report`'s timings `t` (the total, from `t_total`; the models' set-up, timed
/// before the pool started, kept from the report's header) and `counts` (peak resident bytes,
/// the queues' occupancy `queue`), and stores both in the report.
fn record_totals(
    report: &mut Report,
    mut t: StageTimings,
    mut counts: Counts,
    queue: QueueStats,
    t_total: Instant,
) {
    t.total = t_total.elapsed().as_secs_f64();
    counts.peak_rss_bytes = slag_common::util::peak_rss_bytes();
    counts.queue = Some(queue);
    // The header carries what was timed before the pool started: the models' set-up.
    t.models = report.timings.models;
    report.timings = t;
    report.counts = counts;
}

/// Finishes the dense file of `writer` (every row pushed) and writes the mixture to
/// `<out>/mixture.safetensors`, or removes a mixture of an earlier run when there is none; a
/// spinner shows it with [`EncodeParams::progress`]. Returns the mixture's path.
///
/// Errors: I/O.
fn write_forms(
    out: &TailInputs,
    writer: Option<EmbeddingsWriter>,
    mixture: Option<&slag_common::mixture::MixtureEmbeddings>,
) -> Result<PathBuf> {
    let spinner = super::pool::tail_spinner(out.params.progress, "write", "the outputs");
    let t0 = Instant::now();
    if let Some(writer) = writer {
        writer.finish(out.model_id, out.means.len() as u64, &out.ply)?;
    }
    let mix_path = out.params.out_dir.join("mixture.safetensors");
    match mixture {
        Some(m) => m.write(&mix_path)?,
        None => remove_stale(&mix_path)?,
    }
    spinner.finish_with_message(format!("the outputs: {:.1} s", t0.elapsed().as_secs_f64()));
    Ok(mix_path)
}

/// The report's record of the optional forms: the mixture written at `mix_path` (its reduction
/// took `mixture_s`) and the level files (`levels_s`); each `None` when not written.
pub(crate) fn form_outputs(
    mixture: Option<&slag_common::mixture::MixtureEmbeddings>,
    mix_path: PathBuf,
    mixture_s: f64,
    level_files: Vec<LevelOutput>,
    levels_s: f64,
) -> FormOutputs {
    let has_levels = !level_files.is_empty();
    FormOutputs {
        levels: has_levels.then_some(level_files),
        levels_reduce_s: has_levels.then_some(levels_s),
        mixture: mixture.map(|_| mix_path),
        mixture_bytes_per_gaussian: mixture.map(|m| m.bytes_per_gaussian()),
        mixture_codebook_rows: mixture.map(|m| m.codebook_len()),
        mixture_keep: mixture.map(|m| m.keep),
        mixture_reduce_s: mixture.map(|_| mixture_s),
    }
}

/// The tail's reduction: on the device when the pool kept the views there ([`reduce_on_device`];
/// on several devices each reduces one range of Gaussians,
/// [`super::devices::reduce_across_devices`], or, for the dense file, the first reduces all,
/// [`super::devices::one_device`]), else the host's pass over `store` ([`reduce_outputs`]); a
/// spinner shows it with [`EncodeParams::progress`].
///
/// Errors: the reduction's, I/O on the dense file.
fn reduce_tail(
    out: &TailInputs,
    device: Vec<Box<dyn WeightRasterizer>>,
    store: &mut aggregate::ContributionStore,
    embeddings: &Path,
) -> Result<ReducedOutputs> {
    let place = if device.is_empty() { "CPU" } else { "GPU" };
    let spinner = super::pool::tail_spinner(
        out.params.progress,
        "reduce",
        &format!("E_k on the {place}"),
    );
    let tail = if device.len() > 1 && !out.params.dense {
        super::devices::reduce_across_devices(device, out, embeddings)?
    } else {
        let t0 = Instant::now();
        match super::devices::one_device(device)? {
            Some(mut rasterizer) => {
                // The hand-over between devices counts as the reduction's, as an exchange does.
                let handed_over_s = t0.elapsed().as_secs_f64();
                let writer = dense_writer(out.params, out.dim, embeddings)?;
                let mut tail = reduce_on_device(&mut *rasterizer, out, writer, None)?;
                tail.reduce_s += handed_over_s;
                tail.spent.push(rasterizer);
                tail
            }
            None => reduce_outputs(store, out, embeddings)?,
        }
    };
    spinner.finish_with_message(format!("E_k on the {place}: {:.1} s", tail.reduce_s));
    Ok(tail)
}

/// One ordinary embeddings file per SAM granularity level, `embeddings-level{l}.safetensors`,
/// reduced from `level_stores` (granularity kept apart; [`EncodeParams::levels`]); a level
/// file of an earlier run that this run does not write is removed. Returns the files and the
/// seconds they took.
///
/// Errors: the reduction's, I/O.
fn write_levels(
    out: &TailInputs,
    level_stores: &[aggregate::ContributionStore],
) -> Result<(Vec<LevelOutput>, f64)> {
    let t0 = Instant::now();
    let params = out.params;
    let mut level_files = Vec::new();
    for l in 0..aggregate::levels::LEVELS {
        let path = params
            .out_dir
            .join(format!("embeddings-level{l}.safetensors"));
        let Some(ls) = level_stores.get(l) else {
            remove_stale(&path)?;
            continue;
        };
        let w = EmbeddingsWriter::create(&path, out.dim, params.precision)?;
        let streamed = aggregate::reduce_to_writer(ls, out.means, out.dim, params.reduce, w)?;
        let rows = streamed.writer.len();
        streamed
            .writer
            .finish(out.model_id, out.means.len() as u64, &out.ply)?;
        let bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
        level_files.push(LevelOutput {
            bytes,
            level: l,
            observed: rows,
            path,
        });
    }
    Ok((level_files, t0.elapsed().as_secs_f64()))
}

/// The tail's one f64 pass over `store` (or, when the store folded the views as they came, the
/// mixture made from its fold, [`folded_outputs`], or the dense file and the mixture from its
/// dense fold, [`dense_folded_outputs`]): with [`EncodeParams::dense`] the rows stream into
/// `embeddings` (the `[N, D]` matrix is never in memory) and, with the mixture, the same pass
/// keeps each Gaussian's largest `a_kj` and the codebook; without it only the mixture is
/// reduced, no dense row is made, and an `embeddings` file of an earlier run is removed.
///
/// Errors: neither form asked for ([`Error::Invalid`]), the reduction's, I/O.
fn reduce_outputs(
    store: &mut aggregate::ContributionStore,
    out: &TailInputs,
    embeddings: &Path,
) -> Result<ReducedOutputs> {
    if let Some(fold) = store.take_fold() {
        return folded_outputs(fold, out, embeddings);
    }
    if let Some(fold) = store.take_dense_fold() {
        return dense_folded_outputs(fold, out, embeddings);
    }
    let store = &*store;
    let (means, dim, params, model_id) = (out.means, out.dim, out.params, out.model_id);
    let t0 = Instant::now();
    let p = params.reduce;
    let Some(writer) = dense_writer(params, dim, embeddings)? else {
        let keep = params.mixture_keep.unwrap_or(1);
        let (sparse, chunks) =
            aggregate::reduce_mixture_chunks(store, means, dim, p, keep, model_id)?;
        return Ok(ReducedOutputs {
            on_device: false,
            spent: Vec::new(),
            writer: None,
            observed: sparse.gaussian_ids.len(),
            sparse: Some(sparse),
            chunks,
            reduce_s: t0.elapsed().as_secs_f64(),
            gather_s: 0.0,
            write_s: 0.0,
            memory: DeviceReduceMemory::default(),
            host_fold_peak_bytes: 0,
            dense_fold: None,
        });
    };
    let (streamed, sparse, gather_s) = match params.mixture_keep {
        Some(keep) => {
            let m = aggregate::reduce_to_writer_with_mixture(
                store, means, dim, p, writer, keep, model_id,
            )?;
            (m.streamed, Some(m.sparse), m.gather_s)
        }
        None => (
            aggregate::reduce_to_writer(store, means, dim, p, writer)?,
            None,
            0.0,
        ),
    };
    Ok(ReducedOutputs {
        on_device: false,
        spent: Vec::new(),
        observed: streamed.writer.len(),
        writer: Some(streamed.writer),
        sparse,
        chunks: streamed.chunks,
        reduce_s: streamed.reduce_s,
        gather_s,
        write_s: t0.elapsed().as_secs_f64() - streamed.reduce_s,
        memory: DeviceReduceMemory::default(),
        host_fold_peak_bytes: 0,
        dense_fold: None,
    })
}

/// The mixture from the host's `fold` of the views as they came ([`aggregate::MixtureFold`]):
/// its sparse parts over the centres of `out`; an `embeddings` file of an earlier run is removed
/// (the fold makes no dense row).
///
/// Errors: the fold's ([`aggregate::MixtureFold::finish`]); I/O removing the stale file.
fn folded_outputs(
    fold: aggregate::MixtureFold,
    out: &TailInputs,
    embeddings: &Path,
) -> Result<ReducedOutputs> {
    let t0 = Instant::now();
    remove_stale(embeddings)?;
    let peak = fold.state_bytes() + fold.peak_pending_bytes();
    let sparse = fold.finish(out.means, out.model_id)?;
    Ok(ReducedOutputs {
        on_device: false,
        spent: Vec::new(),
        writer: None,
        observed: sparse.gaussian_ids.len(),
        sparse: Some(sparse),
        chunks: 1,
        reduce_s: t0.elapsed().as_secs_f64(),
        gather_s: 0.0,
        write_s: 0.0,
        memory: DeviceReduceMemory::default(),
        host_fold_peak_bytes: peak as u64,
        dense_fold: None,
    })
}

/// The dense file, and with the mixture its sparse parts, from the host's dense `fold` of the
/// views as they came ([`aggregate::DenseFold`]): the last batch swept over the tiles, then
/// each tile's rows streamed into `embeddings` in id order.
///
/// Errors: the fold's ([`aggregate::DenseFold::finish`]: spill-file I/O, the writer's);
/// [`Error::Internal`] for a fold of an encode without the dense file.
fn dense_folded_outputs(
    fold: aggregate::DenseFold,
    out: &TailInputs,
    embeddings: &Path,
) -> Result<ReducedOutputs> {
    let t0 = Instant::now();
    let writer = dense_writer(out.params, out.dim, embeddings)?
        .ok_or_else(|| Error::internal("the dense fold of an encode without the dense file"))?;
    let done = fold.finish(out.means, out.model_id, writer)?;
    Ok(ReducedOutputs {
        on_device: false,
        spent: Vec::new(),
        writer: Some(done.writer),
        observed: done.observed,
        sparse: done.sparse,
        chunks: done.stats.tiles,
        reduce_s: t0.elapsed().as_secs_f64(),
        gather_s: 0.0,
        write_s: 0.0,
        memory: DeviceReduceMemory::default(),
        host_fold_peak_bytes: done.peak_bytes,
        dense_fold: Some(done.stats),
    })
}
