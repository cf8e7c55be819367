//! [`ClusterEncoder`]: an [`EncodeConfig`] checked for a cluster and run as one of its
//! processes.

use std::sync::Arc;

use slag_common::Result;

use super::{ClusterConfig, ClusterJob, SegmentFeed, StageFactory, Stages, encode_cluster};
use crate::config::{ConfigError, EncodeConfig};
use crate::pipeline::build;
use crate::pipeline::segment_task::SegmentTask;
use crate::report::Report;

/// One process's part of a cluster encode ([`encode_cluster`]): every process of the cluster
/// runs the same [`EncodeConfig`], each with its own [`ClusterConfig::process`]. Each process
/// runs `encode`'s front workers and rasterizers ([`build::build_fronts`] over
/// [`build::gpu_count`] GPUs, [`build::make_rasterizers`]: `execution.gpus` and
/// `execution.front_workers` mean what they mean to `encode`, for this process alone), fed by
/// the job's hand-out.
#[derive(Debug, Clone)]
pub struct ClusterEncoder {
    config: EncodeConfig,
}

impl ClusterEncoder {
    /// Checks `config` ([`EncodeConfig::validate`], then [`EncodeConfig::check_cluster`]: what
    /// a cluster cannot honour is refused, not ignored); nothing is loaded yet.
    ///
    /// Errors: the [`ConfigError`] of the first setting that cannot run.
    pub fn new(config: EncodeConfig) -> std::result::Result<Self, ConfigError> {
        config.validate()?;
        config.check_cluster()?;
        Ok(ClusterEncoder { config })
    }

    /// The configuration every process runs.
    pub fn config(&self) -> &EncodeConfig {
        &self.config
    }

    /// Runs this process's part of the job over `cluster`; the report on process 0 (which
    /// writes the outputs), `None` on the others. Sets rayon's global pool as
    /// [`crate::pipeline::Encoder::run`] does. With [`crate::config::SegmentsConfig::enabled`]
    /// process 0 computes the segments beside the job, as `encode` does (from its own load of
    /// the scene, then the masks' record the partitions assembled), and writes the masks' record
    /// and `segments.safetensors` after the job's outputs, then the report again.
    ///
    /// Errors: as [`encode_cluster`]; the segmentation's, after the job's outputs.
    pub fn run(&self, cluster: &ClusterConfig) -> Result<Option<Report>> {
        let c = &self.config;
        if c.segments.enabled {
            // Refused before the job, not after it.
            c.segments.params.validate()?;
        }
        crate::views::check_hold_out(c.scene.hold_out_every)?;
        c.scene.views.validate()?;
        let threads = build::setup_threads(c);
        let (segments, feed) = if c.segments.enabled && cluster.process == 0 {
            let (scene_tx, scene_rx) = std::sync::mpsc::channel();
            let (record_tx, record_rx) = std::sync::mpsc::channel();
            let task = SegmentTask::start(c, threads, scene_rx, record_rx)?;
            let feed = Arc::new(SegmentFeed::new(scene_tx, record_tx));
            (Some(task), Some(feed))
        } else {
            (None, None)
        };
        let mut report = build::report_header(c, threads);
        report.parameters.cluster_processes = Some(cluster.addresses.len());
        let config = c.clone();
        let stages: StageFactory = Arc::new(move |g| {
            let fronts = build::build_fronts(&config, build::gpu_count(&config), threads)?;
            Ok(Stages {
                fronts: fronts.stages,
                rasterizers: build::make_rasterizers(&config, g)?,
                services: fronts.services,
            })
        });
        let job = ClusterJob {
            scene: build::scene_input(c),
            params: build::encode_params(c),
            stages,
            report,
            segments: feed.clone(),
        };
        let Some(report) = encode_cluster(job, cluster)? else {
            return Ok(None);
        };
        let record = feed.as_deref().and_then(SegmentFeed::take_record);
        crate::pipeline::finish_with_segments(c, report, record.as_deref(), segments, threads)
            .map(Some)
    }
}
