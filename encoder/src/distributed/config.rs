//! Where a process sits in the cluster and what every process runs: [`ClusterConfig`] (host
//! file), [`ClusterJob`], the per-worker [`Stages`].

use std::path::Path;
use std::sync::mpsc::Sender;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use slag_common::mask_record::MaskRecord;
use slag_common::scene::Gaussians;
use slag_common::{Error, Result};

use super::net::{ClusterSecret, all_loopback};
use crate::pipeline::{EncodeParams, FrontStages, SceneInput};
use crate::raster::WeightRasterizer;
use crate::report::Report;

/// The per-image stage implementations of one worker process: its front workers and its
/// rasterizers, as `encode` runs them (`--front-workers`, `--gpus`).
pub struct Stages {
    /// The front workers (each a mask source and a CLIP visual tower over mask crops, possibly
    /// bound to a GPU); at least one, all embedding with the same model.
    pub fronts: Vec<FrontStages>,
    /// One weight rasterizer over the scene's Gaussians per GPU (or the one CPU reference); at
    /// least one, and one for each GPU the fronts are bound to.
    pub rasterizers: Vec<Box<dyn WeightRasterizer>>,
    /// What keeps the fronts' shared GPU models alive (the GPUs' CLIP services; empty on the
    /// CPU), dropped after the job.
    pub services: Vec<crate::clip::ClipService>,
}

impl Stages {
    /// The first front's masks (their name) and CLIP model (its id and width `D`); every front
    /// embeds with the same model.
    ///
    /// Errors: [`Error::Param`] `fronts` when there is none.
    pub(super) fn first_front(&self) -> Result<&FrontStages> {
        self.fronts
            .first()
            .ok_or_else(|| Error::param("fronts", 0, "at least one front worker"))
    }

    /// The first rasterizer's name (the report's).
    pub(super) fn rasterizer_name(&self) -> String {
        self.rasterizers
            .first()
            .map_or_else(String::new, |r| r.name().to_string())
    }
}

/// Builds a worker's [`Stages`] from the scene's Gaussians; called once in every process, on its
/// worker thread; the stages then map the views on the encode's worker pool, fed by the job's
/// hand-out (`map::map_side`).
pub type StageFactory = Arc<dyn Fn(&Gaussians) -> Result<Stages> + Send + Sync>;

/// The least time between two checkpoints unless set ([`ClusterConfig::checkpoint_every`]):
/// 5 minutes, a small share of a long job's wall for the state of its Gaussians.
pub const DEFAULT_CHECKPOINT_EVERY: Duration = Duration::from_secs(300);

/// Where this process sits in the cluster.
#[derive(Debug, Clone)]
pub struct ClusterConfig {
    /// This process's index, `0..addresses.len()`; process 0 writes the outputs.
    pub process: usize,
    /// `host:port` of every process, the same list in every process; process `i` listens on
    /// `addresses[i]`, the others connect to it.
    pub addresses: Vec<String>,
    /// How long to wait for every process to connect before giving up.
    pub connect_timeout: Duration,
    /// The secret every connection proves at its start ([`super::net`]'s handshake); `None` is
    /// allowed only when every address is on loopback (see [`ClusterConfig::check_secret`]).
    pub secret: Option<ClusterSecret>,
    /// The least time between two checkpoints of a process's partition
    /// (`OUT/.cluster-<p>-of-<P>.checkpoint`, [`super::encode_cluster`]); `None`: none written
    /// (a checkpoint of the same job is still resumed).
    pub checkpoint_every: Option<Duration>,
}

impl ClusterConfig {
    /// Reads a host file: one `host:port` per line, line `i` for process `i`; blank lines and
    /// lines starting with `#` are ignored.
    ///
    /// Errors: unreadable file, no address, a line that is not `host:port`, `process` out of range.
    pub fn from_hosts_file(path: &Path, process: usize, connect_timeout: Duration) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let addresses: Vec<String> = text
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty() && !l.starts_with('#'))
            .map(str::to_string)
            .collect();
        if let Some(bad) = addresses.iter().find(|a| {
            a.rsplit_once(':')
                .is_none_or(|(_, p)| p.parse::<u16>().is_err())
        }) {
            return Err(Error::format(
                path,
                format!(
                    "{bad:?} is not host:port; write one host:port per line, one line per process"
                ),
            ));
        }
        let config = Self {
            process,
            addresses,
            connect_timeout,
            secret: None,
            checkpoint_every: Some(DEFAULT_CHECKPOINT_EVERY),
        };
        config.check().map_err(|m| Error::format(path, m))?;
        Ok(config)
    }

    /// This configuration with checkpoints at most every `every` (`None` or zero: none).
    pub fn with_checkpoint_every(self, every: Option<Duration>) -> Self {
        Self {
            checkpoint_every: every.filter(|d| !d.is_zero()),
            ..self
        }
    }

    /// This configuration with the cluster secret `secret`.
    pub fn with_secret(self, secret: ClusterSecret) -> Self {
        Self {
            secret: Some(secret),
            ..self
        }
    }

    /// Refuses a cluster without a secret unless every address is on loopback (then only users
    /// of this machine can reach its ports; a warning says so): on a shared network anyone who
    /// reaches an unauthenticated port could join the job or feed it records.
    ///
    /// Errors: [`Error::Param`] `cluster_secret` naming the first address off loopback.
    pub fn check_secret(&self) -> Result<()> {
        if self.secret.is_some() {
            return Ok(());
        }
        if all_loopback(&self.addresses) {
            tracing::warn!(
                "encode-cluster without a cluster secret: any user of this machine can connect \
                 to its ports; give every process the same secret file"
            );
            return Ok(());
        }
        let off = self
            .addresses
            .iter()
            .find(|a| !all_loopback(std::slice::from_ref(a)))
            .cloned()
            .unwrap_or_default();
        Err(Error::param(
            "cluster_secret",
            format!("none, with {off} off loopback"),
            "a shared secret file, the same on every process, when any process is on another \
             machine: without one anyone who reaches the ports could join the job or send it data",
        ))
    }

    pub(super) fn check(&self) -> std::result::Result<(), String> {
        if self.addresses.is_empty() {
            return Err("no process address; write one host:port per line".into());
        }
        if self.process >= self.addresses.len() {
            return Err(format!(
                "process index {} but the host list names {} processes (0..{})",
                self.process,
                self.addresses.len(),
                self.addresses.len()
            ));
        }
        Ok(())
    }
}

/// What every process runs: the same scene, parameters and stage factory.
pub struct ClusterJob {
    /// Scene folder, `.ply` and view selection (identical on every process).
    pub scene: SceneInput,
    /// Encode parameters; `out_dir` is where process 0 writes and where every process spills.
    pub params: EncodeParams,
    /// Builds the per-image stages on each worker.
    pub stages: StageFactory,
    /// The report header (inputs, models, parameters) process 0 completes and writes.
    pub report: Report,
    /// Process 0 with the segments: where its scene and its masks' record go (`None` on the
    /// other processes, or without the segments).
    pub segments: Option<Arc<SegmentFeed>>,
}

/// What process 0's encode hands to the segments computed beside it (as `encode` computes
/// them, `pipeline::segment_task`): the Gaussians as soon as they are loaded,
/// the masks' record once every partition's rows are assembled. Each is sent once; a receiver
/// that hung up (a failed segmentation) is ignored.
pub struct SegmentFeed {
    scene: Mutex<Option<Sender<Arc<Gaussians>>>>,
    record: Mutex<Option<Sender<Arc<MaskRecord>>>>,
    kept: Mutex<Option<Arc<MaskRecord>>>,
}

impl SegmentFeed {
    /// A feed into the segments' `scene` and `record` channels.
    pub fn new(scene: Sender<Arc<Gaussians>>, record: Sender<Arc<MaskRecord>>) -> Self {
        SegmentFeed {
            scene: Mutex::new(Some(scene)),
            record: Mutex::new(Some(record)),
            kept: Mutex::new(None),
        }
    }

    /// Sends the loaded Gaussians (the first call only).
    pub(super) fn send_scene(&self, gaussians: &Arc<Gaussians>) {
        if let Some(tx) = self.scene.lock().ok().and_then(|mut s| s.take()) {
            let _ = tx.send(Arc::clone(gaussians));
        }
    }

    /// Sends the assembled masks' record (the first call only) and keeps it for
    /// [`SegmentFeed::take_record`].
    pub(super) fn send_record(&self, record: MaskRecord) {
        let record = Arc::new(record);
        if let Some(tx) = self.record.lock().ok().and_then(|mut s| s.take()) {
            let _ = tx.send(Arc::clone(&record));
        }
        if let Ok(mut kept) = self.kept.lock() {
            *kept = Some(record);
        }
    }

    /// The masks' record sent, once the job has completed (to write it beside the outputs).
    pub fn take_record(&self) -> Option<Arc<MaskRecord>> {
        self.kept.lock().ok().and_then(|mut k| k.take())
    }
}
