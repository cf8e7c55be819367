//! `slag-encoder encode-cluster`: the encode as a timely dataflow job over several processes
//! ([`slag_encoder::distributed`]). Every process gets the same encode arguments and host file,
//! and its own `--process` index.

use std::path::PathBuf;
use std::time::Duration;

use clap::Args;
use slag_encoder::config::EncodeConfig;
use slag_encoder::distributed::{ClusterConfig, ClusterEncoder, ClusterSecret};
use slag_encoder::report::Report;

use crate::encode::EncodeArgs;

/// Arguments of `encode-cluster`: the cluster placement plus every `encode` argument.
#[derive(Debug, Clone, Args)]
pub struct EncodeClusterArgs {
    /// This process's index: line `I` (0-based) of --hosts; process 0 chooses the views and writes the outputs `encode` writes (OUT/mixture.safetensors, with --dense OUT/embeddings.safetensors, the masks' record, OUT/segments.safetensors, OUT/report.json).
    #[arg(long)]
    pub process: usize,
    /// Host file, the same for every process: one host:port per line (the address each process listens on).
    #[arg(long)]
    pub hosts: PathBuf,
    /// Seconds to wait for every process of the host file to connect (and prove the cluster secret).
    #[arg(long, default_value_t = 300)]
    pub connect_timeout: u64,
    /// File holding the cluster's shared secret (first line, at least 16 bytes, e.g. `head -c 32 /dev/urandom | base64`; mode 0600), the same on every process: each connection starts with an HMAC challenge on it and a peer without it is refused. Needed unless every address of --hosts is on loopback. The traffic after the challenge is not encrypted: use a private network or a VPN.
    #[arg(long, value_name = "PATH")]
    pub cluster_secret_file: Option<PathBuf>,
    /// Seconds between two checkpoints of each process's partition (OUT/.cluster-<P>-of-<N>.checkpoint on that process's machine: the running state of its Gaussians after the views it took in), 0: none. A rerun of every process with the same arguments resumes from them (views every partition holds are not encoded again); a checkpoint of other arguments is refused with what to do. They are removed once the job completes. None are written with --dense.
    #[arg(long, value_name = "SECONDS", default_value = "300", value_parser = seconds)]
    pub checkpoint_every: std::time::Duration,
    /// The encode arguments (identical on every process).
    #[command(flatten)]
    pub encode: EncodeArgs,
}

/// A non-negative, finite number of seconds (fractions allowed).
fn seconds(s: &str) -> Result<Duration, String> {
    let x: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("{s:?} is not a number of seconds"))?;
    Duration::try_from_secs_f64(x).map_err(|_| format!("{s}: give 0 or more seconds"))
}

/// The encode settings of a cluster run: exactly `encode`'s (what a cluster cannot honour,
/// `--levels`, is refused by [`ClusterEncoder::new`]; `--gpus` and `--front-workers` are each
/// process's own).
fn cluster_config(a: &EncodeClusterArgs) -> EncodeConfig {
    EncodeConfig::from(&a.encode)
}

/// Runs this process's part of the job; the report on process 0, `None` on the others.
///
/// Errors: what a cluster cannot honour ([`slag_encoder::config::ConfigError`], before the host
/// file is read; [`crate::hints::hint`] names the flags), then cluster, model and encode errors.
pub fn run(a: &EncodeClusterArgs) -> anyhow::Result<Option<Report>> {
    let encoder = ClusterEncoder::new(cluster_config(a))?;
    let mut cluster = ClusterConfig::from_hosts_file(
        &a.hosts,
        a.process,
        Duration::from_secs(a.connect_timeout),
    )?
    .with_checkpoint_every(Some(a.checkpoint_every));
    if let Some(path) = &a.cluster_secret_file {
        cluster = cluster.with_secret(ClusterSecret::read(path)?);
    }
    Ok(encoder.run(&cluster)?)
}

#[cfg(test)]
mod tests {
    use clap::Parser;
    use slag_encoder::config::ConfigError;

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
            "--scene-dir",
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

    fn check(a: &EncodeClusterArgs) -> Result<ClusterEncoder, ConfigError> {
        ClusterEncoder::new(cluster_config(a))
    }

    #[test]
    fn checkpoint_every_takes_seconds_and_zero_turns_it_off() {
        assert_eq!(parse(&[]).checkpoint_every, Duration::from_secs(300));
        let a = parse(&["--checkpoint-every", "0.25"]);
        assert_eq!(a.checkpoint_every, Duration::from_millis(250));
        for bad in ["-1", "soon", "inf"] {
            let argv = ["x", "--process", "0", "--hosts", "h", "--scene-dir", "s"];
            let argv = argv.iter().copied().chain(["--checkpoint-every", bad]);
            assert!(Cli::try_parse_from(argv).is_err(), "{bad}");
        }
        let c = ClusterConfig {
            process: 0,
            addresses: vec!["127.0.0.1:1".into()],
            connect_timeout: Duration::from_secs(1),
            secret: None,
            checkpoint_every: None,
        };
        let off = c.clone().with_checkpoint_every(Some(Duration::ZERO));
        assert_eq!(off.checkpoint_every, None);
        let on = c.with_checkpoint_every(Some(Duration::from_secs(2)));
        assert_eq!(on.checkpoint_every, Some(Duration::from_secs(2)));
    }

    #[test]
    fn each_process_takes_encodes_outputs_views_gpus_and_front_workers() {
        assert!(
            check(&parse(&[])).is_ok(),
            "encode's default outputs and views"
        );
        for ok in [
            &["--mixture-keep", "8"][..],
            &["--dense"][..],
            &["--views", "coverage"][..],
            &["--gpus", "1", "--front-workers", "1"][..],
            // Each process's GPUs and fronts are its own, as in `encode`.
            &["--gpus", "2"][..],
            &["--gpus", "all"][..],
            &["--front-workers", "3"][..],
        ] {
            assert!(check(&parse(ok)).is_ok(), "{ok:?}");
        }
    }
}
