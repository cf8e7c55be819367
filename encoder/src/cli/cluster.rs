//! `slag-encoder encode-cluster`: the encode as a timely dataflow job over several processes
//! ([`crate::distributed`]). Every process gets the same encode arguments and host file, and its
//! own `--process` index.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use clap::Args;
use slag_common::Error;

use crate::distributed::{self, ClusterConfig, ClusterJob, StageFactory, Stages};
use crate::pipeline::SceneInput;
use crate::report::Report;

use super::encode::{
    EncodeArgs, build_masks, encode_params, make_rasterizer, report_header, setup_threads,
};

/// Arguments of `encode-cluster`: the cluster placement plus every `encode` argument.
#[derive(Debug, Clone, Args)]
pub struct EncodeClusterArgs {
    /// This process's index: line `I` (0-based) of --hosts; process 0 writes OUT/embeddings.safetensors and OUT/report.json.
    #[arg(long)]
    pub process: usize,
    /// Host file, the same for every process: one host:port per line (the address each process listens on).
    #[arg(long)]
    pub hosts: PathBuf,
    /// Seconds to wait for every process of the host file to connect.
    #[arg(long, default_value_t = 300)]
    pub connect_timeout: u64,
    /// The encode arguments (identical on every process).
    #[command(flatten)]
    pub encode: EncodeArgs,
}

/// Runs this process's part of the job; the report on process 0, `None` on the others.
pub fn run(a: &EncodeClusterArgs) -> anyhow::Result<Option<Report>> {
    let cluster = ClusterConfig::from_hosts_file(
        &a.hosts,
        a.process,
        Duration::from_secs(a.connect_timeout),
    )?;
    let e = &a.encode;
    let threads = setup_threads(e);
    let scene = SceneInput::new(&e.scene, e.ply.as_deref(), e.every);
    let mut report = report_header(e, &scene, threads);
    if let Some(p) = report.parameters.as_object_mut() {
        p.insert("cluster_processes".into(), cluster.addresses.len().into());
    }
    let args = e.clone();
    let stages: StageFactory = Arc::new(move |g| {
        let masks = build_masks(&args, threads).map_err(|e| Error::Invalid(format!("{e:#}")))?;
        let crops = crate::clip::ClipVisual::with_threads(
            &args.clip_visual,
            args.ep.into(),
            args.clip_batch,
            threads,
        )?;
        Ok(Stages {
            masks,
            crops: Box::new(crops),
            rasterizer: make_rasterizer(args.rasterizer, g)?,
        })
    });
    let job = ClusterJob {
        scene,
        params: encode_params(e),
        stages,
        report,
    };
    Ok(distributed::encode_cluster(job, &cluster)?)
}
