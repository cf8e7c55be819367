//! `partition`, `serve`, `export` and `keygen` subcommands (clap `Args`, each turned into the
//! library's settings, and its run function), shared by the `slag-shards` binary and
//! `slag-encoder` (same names and flags). The partition itself runs from a typed
//! [`PartitionConfig`] ([`crate::stage`]).

use std::path::PathBuf;

use anyhow::Context;
use slag_common::cli::server::{DEFAULT_SHARD_LISTEN, ServerArgs};
use slag_common::shards::{Dtype, GroundFrame};

use crate::partition::{DEFAULT_MAX_SHARD_MIB, ShardCap};
use crate::qdrant::QdrantParams;
use crate::stage::{
    PartitionConfig, PartitionInput, SegmentsChoice, ToMap, check_key_mode, load_signing_key,
};
use crate::store::ShardStore;

/// `slag-encoder partition`: cut an embeddings file into spatial shards in a sled store.
#[derive(Debug, Clone, clap::Args)]
pub struct PartitionArgs {
    /// Embeddings written by `slag-encoder encode`, either form, told apart by the file's
    /// header. The mixture, OUT/mixture.safetensors (the default output; slots per Gaussian set
    /// by `encode --mixture-keep S`): the shards then hold each Gaussian's codebook slots (atom
    /// indices + f16 weights, shard format 2) and the scene's codebook is stored beside them
    /// (manifest version 2); --dtype does not apply (weights and codebook are f16); with
    /// --qdrant-url the mixture is expanded to dense rows (Qdrant stores dense vectors) and
    /// partitioned dense, so the shards and Qdrant hold the same rows. The dense
    /// OUT/embeddings.safetensors (`encode --dense`). A dense path that does not exist, with
    /// OUT/mixture.safetensors beside it, partitions that mixture (said on stderr).
    #[arg(
        long,
        value_name = "FILE",
        alias = "mixture",
        required_unless_present = "synthetic",
        conflicts_with = "synthetic"
    )]
    pub embeddings: Option<PathBuf>,
    /// With a mixture: keep only each Gaussian's S strongest slots (slots are ordered by weight),
    /// as `eval-colors --held-out` scores "S cut from 16" (8 is its best point); default: every
    /// slot the file has.
    #[arg(
        long,
        value_name = "S",
        alias = "mixture-slots",
        requires = "embeddings"
    )]
    pub mixture_keep: Option<usize>,
    /// Instead of an embeddings file: a synthetic scene of N Gaussians (`N` or `N:DIM`, default
    /// dim 512; 64 clusters over 2 km × 2 km, z up, random unit vectors), for scale and load tests.
    /// Vectors are generated per tile, never all in memory.
    #[arg(long, value_name = "N[:DIM]")]
    pub synthetic: Option<String>,
    /// The publisher's shard store folder (sled: every scene's generations; created if
    /// missing).
    #[arg(long = "shard-store", value_name = "DIR")]
    pub store: PathBuf,
    /// Scene id: 1-64 characters of A-Z a-z 0-9 _ - . (used in URLs).
    #[arg(long, value_name = "NAME")]
    pub scene: String,
    /// Most MiB (2^20 bytes) of encoded shard per tile: tiles split adaptively (k-d on the
    /// ground plane) until each shard fits, the Gaussian cap following from the exact bytes per
    /// Gaussian of --dtype, the dim and the display columns. 16 MiB ≈ the old 16384 Gaussians at
    /// f16 (8128 at f32, 31535 at int8).
    #[arg(
        long,
        value_name = "MIB",
        default_value_t = DEFAULT_MAX_SHARD_MIB,
        conflicts_with = "max_per_shard"
    )]
    pub max_shard_mb: f64,
    /// Override --max-shard-mb: most Gaussians per tile, whatever their size in bytes.
    #[arg(long, value_name = "N")]
    pub max_per_shard: Option<usize>,
    /// Also write the stored-vs-dense report (see the printed summary) as JSON to this file.
    #[arg(long, value_name = "FILE")]
    pub report: Option<PathBuf>,
    /// World up axis (x, y, z, -x, -y, -z). Default: the map's z axis with --to-map /
    /// --to-map-points, else from --cameras if given, else PCA.
    #[arg(long, allow_hyphen_values = true)]
    pub up: Option<String>,
    /// Scene folder with COLMAP `sparse/0` (or nerfstudio `transforms.json`): up = mean camera
    /// −y axis in world frame.
    #[arg(long)]
    pub cameras: Option<PathBuf>,
    /// Scene-to-map transform (the robot's map frame, metres): a JSON file
    /// `{"scale": s, "rotation": [[…],[…],[…]] (row-major) | "quaternion_wxyz": [w,x,y,z],
    /// "translation": [tx,ty,tz]}` with x_map = s·R·x_scene + t, or the word `identity` for a
    /// geo-registered (metric, e.g. ENU) model. Stored in the manifest; `slag-edge fetch` radii
    /// and answers are then in map metres. Without --up, tiles lie on the map's ground (z up).
    #[arg(long, value_name = "FILE|identity", conflicts_with = "to_map_points")]
    pub to_map: Option<PathBuf>,
    /// Estimate the scene-to-map transform from ≥ 3 surveyed points (Umeyama's least-squares
    /// similarity; the RMS residual is printed and stored): JSON
    /// `{"pairs": [{"scene": [x,y,z], "map": [x,y,z]}, …]}`.
    #[arg(long, value_name = "FILE")]
    pub to_map_points: Option<PathBuf>,
    /// Source `.ply`: store each Gaussian's log-scales, pre-sigmoid opacity, normalised rotation
    /// and SH DC colour (INRIA `.ply` convention) in the shards, for display (`GET /query.ply`).
    #[arg(long)]
    pub display_ply: Option<PathBuf>,
    /// Embedding storage in the shards: f32, f16 or int8 (per-vector scale).
    #[arg(long, default_value = "f16")]
    pub dtype: Dtype,
    /// Geometric segments (`segments.safetensors` of `slag-encoder segment` / `encode`): every
    /// shard then carries each Gaussian's scene-wide segment id (shard format 3, mixture shards
    /// 4; a slag-edge before it refuses such shards). Default: `segments.safetensors` beside
    /// --embeddings (or --mixture) when it exists; `off`: none (shard format 1, mixture 2).
    #[arg(long, value_name = "FILE|off", conflicts_with = "synthetic")]
    pub segments: Option<PathBuf>,
    /// After partitioning, upsert every Gaussian (vector + payload id, x, y, z, tile) into this
    /// Qdrant server (gRPC URL, e.g. http://localhost:6334). The collection is recreated.
    #[arg(long)]
    pub qdrant_url: Option<String>,
    /// Qdrant collection name (default: the scene id).
    #[arg(long)]
    pub qdrant_collection: Option<String>,
    /// Points per Qdrant upsert request.
    #[arg(long, default_value_t = 256)]
    pub qdrant_batch: usize,
    /// Enable scalar int8 quantisation in the Qdrant collection.
    #[arg(long)]
    pub qdrant_int8: bool,
    /// Also create one Qdrant collection per tile (`<collection>-tile-<id>`) and a snapshot of
    /// each (Qdrant snapshots are per collection).
    #[arg(long)]
    pub qdrant_snapshot_per_tile: bool,
    /// Qdrant API key.
    #[arg(long, env = "QDRANT_API_KEY", hide_env_values = true)]
    pub qdrant_api_key: Option<String>,
    /// Sign the manifest with this Ed25519 private key (PKCS#8 PEM, from `keygen`): the
    /// signature is stored with the generation and served as `manifest.sig`, so robots that
    /// trust the public key (`slag-edge fetch --trusted-key`) refuse anything else.
    #[arg(long, value_name = "FILE")]
    pub signing_key: Option<PathBuf>,
    /// Sign with a --signing-key that users other than its owner may read (refused otherwise:
    /// chmod 600 it).
    #[arg(long)]
    pub allow_readable_key: bool,
    /// The least generation to write (≥ 1): a publisher that re-created its store carries on
    /// above the generation its robots hold, which they would refuse as a replay. Default: one
    /// more than the store's current generation (1 for a new scene).
    #[arg(long, value_name = "N")]
    pub start_generation: Option<u64>,
}

impl PartitionArgs {
    /// The tile cap asked for: `--max-per-shard N` when given (a count), else `--max-shard-mb`
    /// (bytes; default [`DEFAULT_MAX_SHARD_MIB`]).
    ///
    /// Errors: a non-positive or non-finite `--max-shard-mb` ([`slag_common::Error::Param`]).
    pub fn shard_cap(&self) -> slag_common::Result<ShardCap> {
        match self.max_per_shard {
            Some(n) => Ok(ShardCap::Gaussians(n)),
            None => ShardCap::from_mib(self.max_shard_mb),
        }
    }

    /// The typed settings of the run these flags ask for.
    ///
    /// Errors: a bad `--max-shard-mb`, `--up` or `--synthetic` value, neither `--embeddings`
    /// nor `--synthetic`.
    pub fn config(&self) -> anyhow::Result<PartitionConfig> {
        let input = match (&self.synthetic, &self.embeddings) {
            (Some(spec), _) => synthetic_input(spec)?,
            (None, Some(path)) => PartitionInput::Embeddings(path.clone()),
            (None, None) => anyhow::bail!("pass --embeddings FILE (or --synthetic N)"),
        };
        let to_map = match (&self.to_map, &self.to_map_points) {
            (Some(f), _) => Some(ToMap::File(f.clone())),
            (None, Some(f)) => Some(ToMap::Points(f.clone())),
            (None, None) => None,
        };
        let segments = match &self.segments {
            None => SegmentsChoice::Beside,
            Some(p) if p.as_os_str() == "off" => SegmentsChoice::Off,
            Some(p) => SegmentsChoice::File(p.clone()),
        };
        let qdrant = self.qdrant_url.as_ref().map(|url| QdrantParams {
            url: url.clone(),
            collection: self
                .qdrant_collection
                .clone()
                .unwrap_or_else(|| self.scene.clone()),
            batch_size: self.qdrant_batch,
            quantize_int8: self.qdrant_int8,
            snapshot_per_tile: self.qdrant_snapshot_per_tile,
            api_key: self.qdrant_api_key.clone(),
        });
        Ok(PartitionConfig {
            input,
            mixture_keep: self.mixture_keep,
            store: self.store.clone(),
            scene: self.scene.clone(),
            cap: self.shard_cap()?,
            report: self.report.clone(),
            up: self
                .up
                .as_deref()
                .map(GroundFrame::from_axis_name)
                .transpose()?,
            cameras: self.cameras.clone(),
            to_map,
            display_ply: self.display_ply.clone(),
            dtype: self.dtype,
            segments,
            qdrant,
            signing_key: self.signing_key.clone(),
            allow_readable_key: self.allow_readable_key,
            start_generation: self.start_generation,
        })
    }
}

/// `--synthetic N[:DIM]` as an input.
///
/// Errors: a count of 0, a width outside 1..=65536, anything but `N` or `N:DIM`.
fn synthetic_input(spec: &str) -> anyhow::Result<PartitionInput> {
    let mut it = spec.split(':');
    let gaussians: usize = it
        .next()
        .and_then(|s| s.trim().parse().ok())
        .filter(|&n| n > 0)
        .with_context(|| format!("--synthetic {spec:?}: use N or N:DIM, e.g. 1000000:512"))?;
    let dim: usize = match it.next() {
        None => 512,
        Some(d) => d
            .trim()
            .parse()
            .ok()
            .filter(|&d| d > 0 && d <= slag_common::shards::format::MAX_DIM as usize)
            .with_context(|| format!("--synthetic {spec:?}: DIM must be 1..=65536"))?,
    };
    Ok(PartitionInput::Synthetic { gaussians, dim })
}

/// Runs `partition` with the flags' settings ([`PartitionArgs::config`], [`crate::stage::partition`]).
///
/// Errors: as those two.
pub fn run_partition(args: &PartitionArgs) -> anyhow::Result<()> {
    crate::stage::partition(&args.config()?)
}

/// `slag-encoder serve`: HTTP manifest + shards of a store.
#[derive(Debug, Clone, clap::Args)]
pub struct ServeArgs {
    /// The publisher's shard store folder (written by `partition`).
    #[arg(long = "shard-store", value_name = "DIR")]
    pub store: PathBuf,
    /// Where to listen, the bearer token, TLS and the connection limits (the flags slag-edge
    /// serve shares).
    #[command(flatten)]
    pub server: ServerArgs,
    /// Sign every manifest served (`GET /v1/scenes/{scene}/manifest.sig`) with this Ed25519
    /// private key (PKCS#8 PEM, from `keygen`), also those partitioned unsigned; stored
    /// signatures are then not served. Without it, stored signatures are served.
    #[arg(long, value_name = "FILE")]
    pub signing_key: Option<PathBuf>,
    /// Sign with a --signing-key that users other than its owner may read (refused otherwise).
    #[arg(long)]
    pub allow_readable_key: bool,
}

/// The shard server's token: `--token-file` (first line, trimmed) else env `SLAG_SHARD_TOKEN`.
///
/// Errors: unreadable or blank token file ([`slag_common::Error::Io`] / `Format`); a
/// `SLAG_SHARD_TOKEN` that is set but blank ([`slag_common::Error::Param`] `token`): a blank
/// token never starts the server open.
pub fn serve_token(token_file: Option<&std::path::Path>) -> slag_common::Result<Option<String>> {
    if let Some(p) = token_file {
        return slag_common::auth::read_token_file(p).map(Some);
    }
    slag_common::auth::env_token("SLAG_SHARD_TOKEN")
}

/// Runs `serve` until Ctrl-C (own tokio runtime).
///
/// Errors: store cannot be opened, address cannot be bound.
pub fn run_serve(args: &ServeArgs) -> anyhow::Result<()> {
    let server = &args.server;
    let addr = server.listen_addr(DEFAULT_SHARD_LISTEN)?;
    let token = serve_token(server.token_file.as_deref())?;
    let limits = server.limits()?;
    let tls = server.tls()?;
    slag_common::tls::check_token_transport(
        addr,
        token.is_some(),
        tls.is_some(),
        server.allow_plain_http,
    )?;
    let key = load_signing_key(args.signing_key.as_deref())?;
    if let Some(p) = &args.signing_key {
        check_key_mode(p, args.allow_readable_key)?;
    }
    let store = ShardStore::open(&args.store)?;
    let rt = tokio::runtime::Runtime::new().context("tokio runtime")?;
    let guarded = if token.is_some() {
        " (bearer token required)"
    } else {
        ""
    };
    let scheme = if tls.is_some() { "https" } else { "http" };
    let signed = match &key {
        Some(k) => format!(", manifests signed by key {}", k.key_id()),
        None => String::new(),
    };
    rt.block_on(crate::serve::serve_with_tls_signed(
        store,
        addr,
        token,
        limits,
        tls,
        key,
        |a| println!("serving on {scheme}://{a}/v1/scenes{guarded}{signed}"),
    ))?;
    Ok(())
}

/// `slag-encoder export`: manifest.json + shard files of one scene, written atomically.
#[derive(Debug, Clone, clap::Args)]
pub struct ExportArgs {
    /// The publisher's shard store folder (written by `partition`).
    #[arg(long = "shard-store", value_name = "DIR")]
    pub store: PathBuf,
    /// Scene id.
    #[arg(long, value_name = "NAME")]
    pub scene: String,
    /// Output folder (must not exist unless --force).
    #[arg(long, value_name = "DIR", required_unless_present = "dir")]
    pub out: Option<PathBuf>,
    /// The output folder as a bare argument: the older form of --out, still accepted (noted as
    /// deprecated).
    #[arg(hide = true, conflicts_with = "out", value_name = "DIR")]
    pub dir: Option<PathBuf>,
    /// Replace an existing output folder.
    #[arg(long)]
    pub force: bool,
    /// Write `manifest.sig` signed with this Ed25519 private key (PKCS#8 PEM, from `keygen`)
    /// instead of the signature stored with the generation.
    #[arg(long, value_name = "FILE")]
    pub signing_key: Option<PathBuf>,
    /// Sign with a --signing-key that users other than its owner may read (refused otherwise).
    #[arg(long)]
    pub allow_readable_key: bool,
}

/// Runs `export`.
///
/// Errors: unknown scene, existing folder without --force, I/O.
pub fn run_export(args: &ExportArgs) -> anyhow::Result<()> {
    let key = load_signing_key(args.signing_key.as_deref())?;
    if let Some(p) = &args.signing_key {
        check_key_mode(p, args.allow_readable_key)?;
    }
    let dir = export_dir(args)?;
    let store = ShardStore::open(&args.store)?;
    let m = crate::export::export_signed(&store, &args.scene, &dir, args.force, key.as_ref())?;
    println!(
        "exported {} shards of {} (generation {}) to {}",
        m.tiles.len(),
        m.scene_id,
        m.generation,
        dir.display()
    );
    Ok(())
}

/// The output folder of `export`: `--out`, else the bare argument (noted as deprecated).
///
/// Errors: [`slag_common::Error::Param`] `dir` when neither is given.
fn export_dir(args: &ExportArgs) -> slag_common::Result<PathBuf> {
    match (&args.out, &args.dir) {
        (Some(out), _) => Ok(out.clone()),
        (None, Some(dir)) => {
            eprintln!(
                "note: the output folder as a bare argument is deprecated and will be removed: \
                 use --out {}",
                dir.display()
            );
            Ok(dir.clone())
        }
        (None, None) => Err(slag_common::Error::param("dir", "none", "an output folder")),
    }
}

/// `slag-shards keygen`: a new Ed25519 key pair for signing manifests.
#[derive(Debug, Clone, clap::Args)]
pub struct KeygenArgs {
    /// Folder to write `manifest-key.pem` (private, mode 0600: keep it on the publisher) and
    /// `manifest-key.pub.pem` (public: give it to the robots) into; created if missing. Existing
    /// key files are never overwritten.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
}

/// Runs `keygen`: writes the pair and prints both paths and the key id.
///
/// Errors: key files already in the folder ([`slag_common::Error::Param`] `key_out`), I/O.
pub fn run_keygen(args: &KeygenArgs) -> anyhow::Result<()> {
    let files = slag_common::shards::signature::keygen(&args.out)?;
    println!(
        "key {}: private key {} (mode 0600, keep it on the publisher: partition / serve / \
         export --signing-key), public key {} (for the robots: slag-edge --trusted-key)",
        files.key_id,
        files.private.display(),
        files.public.display()
    );
    Ok(())
}

/// What the command line adds to an error of the shard stage (`e` or an error it wraps): the
/// flag that sets the parameter the library names ([`slag_common::Error::Param`]) or lowers the
/// need ([`slag_common::Error::Limit`]). The library's messages name no flag.
pub fn hint(e: &anyhow::Error) -> Option<String> {
    e.chain()
        .find_map(|c| c.downcast_ref::<slag_common::Error>().and_then(hint_for))
}

/// [`hint`] for one library error.
pub fn hint_for(e: &slag_common::Error) -> Option<String> {
    use slag_common::{Error, Resource};
    match e {
        Error::Param { name, .. } => {
            let flag = match *name {
                "up" => "--up x|y|z|-x|-y|-z",
                "dtype" => "--dtype f32",
                "mixture_slots" => "--mixture-keep S (1 to the file's keep)",
                "qdrant_url" => {
                    "--qdrant-url to the partition of the scene you upload (it partitions a \
                     mixture as its dense rows, the rows Qdrant stores)"
                }
                "max_per_shard" => "--max-per-shard N",
                "max_shard_mib" => "--max-shard-mb MIB (or --max-per-shard N)",
                "batch_size" => "--qdrant-batch N",
                "collection" => "--qdrant-collection NAME",
                "scene_id" | "scene" => "--scene NAME",
                "dir" => "--out DIR (the export folder)",
                "token" => "a non-blank --token-file, or unset SLAG_SHARD_TOKEN",
                "header_timeout" => "--header-timeout SECONDS",
                "write_timeout" => "--write-timeout SECONDS",
                "max_connections" => "--max-connections N (or raise ulimit -n)",
                "body_timeout" => "--body-timeout SECONDS",
                "max_connections_per_ip" => "--max-connections-per-ip N",
                "listen" => "--listen HOST:PORT, e.g. 127.0.0.1:8090",
                "tls_key" => "--tls-key FILE with --tls-cert (the certificate's private key)",
                "tls_cert" => "--tls-cert FILE with --tls-key (the key's certificate chain)",
                "plain_http" => {
                    "--tls-cert FILE --tls-key FILE (HTTPS), or bind a loopback address \
                     (--listen 127.0.0.1:PORT), or --allow-plain-http to send the token in clear \
                     text anyway"
                }
                "key_out" => "another --out DIR (keygen never overwrites a key pair)",
                _ => return None,
            };
            Some(format!("pass {flag}"))
        }
        Error::Limit {
            resource: Resource::ShardGaussians,
            ..
        } => Some("lower --max-per-shard (or --max-shard-mb)".into()),
        Error::Io { source, .. } if source.kind() == std::io::ErrorKind::AlreadyExists => {
            Some("pass --force to replace it".into())
        }
        _ => None,
    }
}
