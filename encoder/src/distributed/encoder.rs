//! [`ClusterEncoder`]: an [`EncodeConfig`] checked for a cluster and run as one of its
//! processes.

use std::sync::Arc;

use slag_common::Result;

use super::{ClusterConfig, ClusterJob, StageFactory, Stages, encode_cluster};
use crate::config::{CLIP_BATCH_CPU, ConfigError, EncodeConfig};
use crate::pipeline::build;
use crate::report::Report;

/// One process's part of a cluster encode ([`encode_cluster`]): every process of the cluster
/// runs the same [`EncodeConfig`], each with its own [`ClusterConfig::process`]. Each process
/// runs one front worker (its own ONNX Runtime sessions, with the config's execution provider
/// and all its threads) and one rasterizer.
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
    /// [`crate::pipeline::Encoder::run`] does.
    ///
    /// Errors: as [`encode_cluster`].
    pub fn run(&self, cluster: &ClusterConfig) -> Result<Option<Report>> {
        let c = &self.config;
        let threads = build::setup_threads(c);
        let mut report = build::report_header(c, threads);
        report.parameters.cluster_processes = Some(cluster.addresses.len());
        let config = c.clone();
        let stages: StageFactory = Arc::new(move |g| {
            let masks = build::build_masks(&config, threads)?;
            let mut crops = crate::clip::ClipVisual::with_threads(
                &config.clip.visual,
                config.execution.ep,
                config.clip.batch.unwrap_or(CLIP_BATCH_CPU),
                threads,
            )?;
            crops.set_crop_fill(config.clip.crop_fill);
            Ok(Stages {
                masks,
                crops: Box::new(crops),
                rasterizer: build::make_rasterizer(config.raster.backend, g)?,
            })
        });
        let job = ClusterJob {
            scene: build::scene_input(c),
            params: build::encode_params(c),
            stages,
            report,
        };
        encode_cluster(job, cluster)
    }
}
