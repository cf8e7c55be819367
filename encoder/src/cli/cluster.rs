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

/// Refuses `encode` arguments that `encode-cluster` cannot honour, instead of ignoring them:
/// `--mixture-keep` (the mixture form is written by `encode` only) and `--gpus`/`--front-workers`
/// other than the defaults (each process runs one rasterizer and one front; start one process
/// per GPU instead).
///
/// Errors: [`Error::Invalid`] naming the flag and what to do instead.
pub fn check_supported(e: &EncodeArgs) -> Result<(), Error> {
    if e.mixture_keep.is_some() {
        return Err(Error::Invalid(
            "encode-cluster does not write the mixture form yet: drop --mixture-keep, or run \
             `slag-encoder encode --mixture-keep S` on one machine"
                .into(),
        ));
    }
    if e.levels {
        return Err(Error::Invalid(
            "encode-cluster does not write per-level embeddings yet: drop --levels, or run \
             `slag-encoder encode --levels` on one machine"
                .into(),
        ));
    }
    if e.gpus != super::encode::GpuCount::Count(1) || e.front_workers.is_some_and(|f| f != 1) {
        return Err(Error::Invalid(
            "encode-cluster runs one rasterizer and one front worker per process: drop --gpus / \
             --front-workers and start one process per GPU (one line each in --hosts)"
                .into(),
        ));
    }
    Ok(())
}

/// Runs this process's part of the job; the report on process 0, `None` on the others.
///
/// Errors: [`check_supported`]'s, then cluster, model and encode errors.
pub fn run(a: &EncodeClusterArgs) -> anyhow::Result<Option<Report>> {
    check_supported(&a.encode)?;
    let cluster = ClusterConfig::from_hosts_file(
        &a.hosts,
        a.process,
        Duration::from_secs(a.connect_timeout),
    )?;
    let e = &a.encode;
    let threads = setup_threads(e);
    let scene = SceneInput::new(&e.scene, e.ply.as_deref(), e.every);
    let mut report = report_header(e, &scene, threads);
    report.parameters.cluster_processes = Some(cluster.addresses.len());
    let args = e.clone();
    let stages: StageFactory = Arc::new(move |g| {
        let masks = build_masks(&args, threads).map_err(|e| Error::Invalid(format!("{e:#}")))?;
        let crops = crate::clip::ClipVisual::with_threads(
            &args.clip_visual,
            args.ep,
            args.clip_batch
                .unwrap_or(crate::cli::encode::CLIP_BATCH_CPU),
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

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: EncodeClusterArgs,
    }

    fn parse(extra: &[&str]) -> EncodeClusterArgs {
        let mut argv = vec![
            "encode-cluster",
            "--process",
            "0",
            "--hosts",
            "hosts.txt",
            "--scene",
            "s",
            "--clip-visual",
            "c.onnx",
            "--masks",
            "graph",
            "--out",
            "o",
        ];
        argv.extend_from_slice(extra);
        match Cli::try_parse_from(argv) {
            Ok(c) => c.args,
            Err(e) => panic!("arguments: {e}"),
        }
    }

    #[test]
    fn flags_the_cluster_cannot_honour_are_refused_not_ignored() {
        assert!(check_supported(&parse(&[]).encode).is_ok());
        assert!(check_supported(&parse(&["--gpus", "1", "--front-workers", "1"]).encode).is_ok());
        for bad in [
            &["--mixture-keep", "8"][..],
            &["--gpus", "2"][..],
            &["--gpus", "all"][..],
            &["--front-workers", "3"][..],
        ] {
            match check_supported(&parse(bad).encode) {
                Err(Error::Invalid(msg)) => {
                    assert!(
                        msg.contains(bad[0]),
                        "{bad:?}: message {msg:?} names the flag"
                    )
                }
                other => panic!("{bad:?}: expected Invalid, got {other:?}"),
            }
        }
    }
}
