//! `partition`, `serve`, `export` and `keygen` subcommands (clap `Args` + run functions), shared
//! by the `slag-shards` binary and `slag-encoder` (same names and flags).

use std::path::PathBuf;

use anyhow::Context;
use slag_common::cli::server::{DEFAULT_SHARD_LISTEN, ServerArgs};
use slag_common::embeddings::Embeddings;
use slag_common::forms::EmbeddingsForm;
use slag_common::shards::synthetic::SyntheticScene;
use slag_common::shards::{
    DisplayColumns, Dtype, GaussianSource, GroundFrame, Manifest, SceneToMap,
};

use crate::partition::{
    DEFAULT_MAX_SHARD_MIB, PartitionParams, ShardCap, StorageReport, UpChoice, mixture_layout,
    resolve_max_per_shard, resolve_mixture_max_per_shard, shard_layout, storage_report,
};
use crate::store::{ShardStore, partition_into_store_signed, partition_mixture_into_store_signed};
use slag_common::mixture::MixtureEmbeddings;
use slag_common::shards::signature::SigningKey;

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
    /// The scene-to-map transform of `--to-map` / `--to-map-points`, if any (printed).
    ///
    /// Errors: unreadable file, bad JSON, too few / collinear points, a non-rotation
    /// ([`slag_common::Error`]).
    pub fn scene_to_map(&self) -> slag_common::Result<Option<SceneToMap>> {
        let t = match (&self.to_map, &self.to_map_points) {
            (Some(f), _) => SceneToMap::read(f)?,
            (None, Some(f)) => SceneToMap::read_points(f)?,
            (None, None) => return Ok(None),
        };
        let q = t.quaternion_wxyz();
        println!(
            "scene-to-map ({:?}): scale {:.9} m per scene unit, rotation (wxyz) [{:.9}, {:.9}, \
             {:.9}, {:.9}], translation {:?} m{}",
            t.source,
            t.scale,
            q[0],
            q[1],
            q[2],
            q[3],
            t.translation,
            match (t.points, t.rms_residual) {
                (Some(n), Some(r)) => format!("; {n} surveyed points, RMS residual {r:.4} m"),
                _ => String::new(),
            }
        );
        Ok(Some(t))
    }

    /// The up-axis choice: `--up`, else the map's z when a transform is given, else `--cameras`,
    /// else PCA of the means.
    fn up_choice(&self, to_map: Option<&SceneToMap>) -> anyhow::Result<Option<UpChoice>> {
        Ok(if let Some(u) = &self.up {
            Some(UpChoice::Given(GroundFrame::from_axis_name(u)?))
        } else {
            to_map
                .map(|t| crate::partition::map_ground_frame(t).map(UpChoice::Given))
                .transpose()?
        })
    }

    /// [`Self::up_choice`], else the mean camera up of `--cameras`, else PCA.
    fn up_or_cameras(&self, to_map: Option<&SceneToMap>) -> anyhow::Result<UpChoice> {
        Ok(if let Some(u) = self.up_choice(to_map)? {
            u
        } else if let Some(dir) = &self.cameras {
            let views = slag_common::camera::load_views(dir)?;
            UpChoice::CameraUps(
                views
                    .iter()
                    .map(|v| (-v.world_to_camera.rotation.row(1)).to_array())
                    .collect(),
            )
        } else {
            UpChoice::Pca
        })
    }

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
}

/// The segments `--segments` names for the embeddings (or mixture) file at `embeddings`: the
/// file given, the `segments.safetensors` beside it when it exists, or none (`off`).
fn resolve_segments(
    args: &PartitionArgs,
    embeddings: &std::path::Path,
) -> anyhow::Result<Option<slag_common::segments::Segments>> {
    let path = match &args.segments {
        Some(p) if p.as_os_str() == "off" => return Ok(None),
        Some(p) => p.clone(),
        None => {
            let beside = embeddings
                .parent()
                .unwrap_or(std::path::Path::new("."))
                .join(slag_common::segments::FILE_NAME);
            if !beside.exists() {
                return Ok(None);
            }
            beside
        }
    };
    let s = slag_common::segments::Segments::read(&path)?;
    eprintln!(
        "segments: {} ({} segments over {} Gaussians)",
        path.display(),
        s.segment_count,
        s.len()
    );
    Ok(Some(s))
}

/// [`partition_source`] with the segments wrapped around `src` when there are any.
fn partition_with_segments(
    args: &PartitionArgs,
    src: &impl GaussianSource,
    mix: Option<&MixtureEmbeddings>,
    segments: Option<&slag_common::segments::Segments>,
    up: UpChoice,
    to_map: Option<SceneToMap>,
    scene_gaussians: Option<u64>,
) -> anyhow::Result<(Manifest, StorageReport)> {
    match segments {
        Some(s) => {
            let src = slag_common::shards::WithSegments::new(src, s)?;
            partition_source(args, &src, mix, up, to_map, scene_gaussians)
        }
        None => partition_source(args, src, mix, up, to_map, scene_gaussians),
    }
}

/// Resolves the cap for `src`, opens `--store` and partitions `src` into it, then prints and
/// (with `--report`) writes the [`StorageReport`]. `mix`: the mixture whose rows `src` gives ids,
/// means and display columns of (its shards are f16 slots, `--dtype` does not apply); `None`:
/// `src`'s own dense vectors. `scene_gaussians`: the source scene's Gaussian count if known. A
/// cap that cannot hold one Gaussian fails before the store is opened.
fn partition_source(
    args: &PartitionArgs,
    src: &impl GaussianSource,
    mix: Option<&MixtureEmbeddings>,
    up: UpChoice,
    to_map: Option<SceneToMap>,
    scene_gaussians: Option<u64>,
) -> anyhow::Result<(Manifest, StorageReport)> {
    let (max_per_shard, dtype) = match mix {
        None => {
            let layout = shard_layout(src, &args.scene, args.dtype);
            (
                resolve_max_per_shard(&layout, args.shard_cap()?)?,
                args.dtype,
            )
        }
        Some(mix) => {
            let layout = mixture_layout(src, &args.scene, mix.keep);
            let cap = resolve_mixture_max_per_shard(&layout, args.shard_cap()?)?;
            (cap, Dtype::F16)
        }
    };
    let key = load_signing_key(args.signing_key.as_deref())?;
    let mut store = ShardStore::open(&args.store)?;
    if let Some(g) = args.start_generation {
        store = store.starting_at(g)?;
    }
    let store = &store;
    let params = PartitionParams {
        scene_id: args.scene.clone(),
        max_per_shard,
        up,
        dtype,
        to_map,
    };
    let m = match mix {
        None => partition_into_store_signed(store, src, &params, key.as_ref()),
        Some(mix) => partition_mixture_into_store_signed(store, src, mix, &params, key.as_ref()),
    }
    .context("partition")?;
    let report = report_partition(args, store, &m, scene_gaussians)?;
    Ok((m, report))
}

/// The display columns of `--display-ply` and the `.ply`'s Gaussian count. Shards store the
/// `.ply` convention (log-scales, logit opacities, normalised rotations, SH DC): the columns
/// invert load_ply's activations.
fn display_columns(ply: &std::path::Path) -> anyhow::Result<(DisplayColumns, u64)> {
    let g =
        slag_common::scene::load_ply(ply, slag_common::scene::PlyLoadOptions { colours: true })?;
    Ok((DisplayColumns::from_gaussians(&g), g.len() as u64))
}

/// Runs `partition`; prints a one-line summary and the stored-vs-dense [`StorageReport`]
/// (also written as JSON with `--report FILE`).
///
/// Errors: unreadable embeddings, invalid parameters (a `--max-shard-mb` smaller than one
/// Gaussian's shard, `--max-per-shard 0`), store failures.
pub fn run_partition(args: &PartitionArgs) -> anyhow::Result<()> {
    // Reject a bad --max-shard-mb or signing key before reading a large input.
    args.shard_cap()?;
    if let Some(p) = &args.signing_key {
        SigningKey::read_pem(p)?;
        check_key_mode(p, args.allow_readable_key)?;
    }
    if args.start_generation == Some(0) {
        return Err(slag_common::Error::param(
            "start_generation",
            0,
            "a generation ≥ 1 (above the one the robots hold)",
        )
        .into());
    }
    if let Some(spec) = &args.synthetic {
        return run_partition_synthetic(args, spec);
    }
    let (path, form) = partition_input(args)?;
    let path = &path;
    let emb = match form {
        EmbeddingsForm::Mixture if args.qdrant_url.is_none() => {
            return run_partition_mixture(args, path);
        }
        EmbeddingsForm::Mixture => {
            eprintln!(
                "{}: Qdrant stores dense vectors: the mixture is expanded to its rows and \
                 partitioned dense",
                path.display()
            );
            slag_common::forms::expand_mixture(&read_mixture(args, path)?)
        }
        EmbeddingsForm::Dense => Embeddings::read(path)?,
    };
    let to_map = args.scene_to_map()?;
    let segments = resolve_segments(args, path)?;
    let segs = segments.as_ref();
    let up = args.up_or_cameras(to_map.as_ref())?;
    let t = std::time::Instant::now();
    // The embeddings file records the source .ply's Gaussian count (0 in files without it).
    let mut scene_gaussians = Some(emb.scene_gaussians).filter(|&n| n > 0);
    let (m, _) = match &args.display_ply {
        Some(ply) => {
            let (cols, n) = display_columns(ply)?;
            scene_gaussians = scene_gaussians.or(Some(n));
            let src = slag_common::shards::WithDisplay::from_columns(&emb, &cols)?;
            partition_with_segments(args, &src, None, segs, up, to_map, scene_gaussians)?
        }
        None => partition_with_segments(args, &emb, None, segs, up, to_map, scene_gaussians)?,
    };
    let bytes: u64 = m.tiles.iter().map(|t| t.bytes).sum();
    println!(
        "scene {} generation {}: {} Gaussians in {} shards, {} bytes ({:.1} B/Gaussian, {:?}), up {:?} ({:?}), {:.1}s",
        m.scene_id,
        m.generation,
        m.total_gaussians,
        m.tiles.len(),
        bytes,
        bytes as f64 / m.total_gaussians.max(1) as f64,
        m.dtype,
        m.ground.up,
        m.ground.up_source,
        t.elapsed().as_secs_f64()
    );
    match &args.qdrant_url {
        Some(url) => upload_to_qdrant(args, url, &emb, &m),
        None => Ok(()),
    }
}

/// The embeddings `partition` reads and their form: `--embeddings` (either form, by its header; a missing dense file with `mixture.safetensors` beside it gives that
/// mixture, said on stderr).
///
/// Errors: neither flag, an unreadable file or one of neither form.
fn partition_input(args: &PartitionArgs) -> anyhow::Result<(PathBuf, EmbeddingsForm)> {
    let Some(path) = &args.embeddings else {
        anyhow::bail!("pass --embeddings FILE (or --synthetic N)");
    };
    let beside = slag_common::forms::mixture_beside(path);
    if !path.exists() && beside.is_file() {
        eprintln!(
            "{} does not exist (`slag-encoder encode` writes it only with --dense): partitioning \
             the mixture beside it, {}",
            path.display(),
            beside.display()
        );
        return Ok((beside, EmbeddingsForm::Mixture));
    }
    Ok((path.clone(), slag_common::forms::form_of(path)?))
}

/// The mixture at `path`, cut to `--mixture-keep` when given.
///
/// Errors: unreadable file, a slot count out of range.
fn read_mixture(args: &PartitionArgs, path: &std::path::Path) -> anyhow::Result<MixtureEmbeddings> {
    let full = MixtureEmbeddings::read(path)?;
    Ok(match args.mixture_keep {
        Some(s) => full.truncated(s)?,
        None => full,
    })
}

/// Upserts `emb` (the rows `m` was partitioned from) into the Qdrant server at `url`.
///
/// Errors: Qdrant's, a collection or batch the server refuses.
fn upload_to_qdrant(
    args: &PartitionArgs,
    url: &str,
    emb: &Embeddings,
    m: &Manifest,
) -> anyhow::Result<()> {
    let params = crate::qdrant::QdrantParams {
        url: url.to_string(),
        collection: args
            .qdrant_collection
            .clone()
            .unwrap_or_else(|| args.scene.clone()),
        batch_size: args.qdrant_batch,
        quantize_int8: args.qdrant_int8,
        snapshot_per_tile: args.qdrant_snapshot_per_tile,
        api_key: args.qdrant_api_key.clone(),
    };
    let t = std::time::Instant::now();
    // Display attributes are not uploaded; the plain embeddings have the same rows.
    let s = crate::qdrant::upload(emb, m, &params).context("Qdrant upload")?;
    println!(
        "Qdrant {url}: {} points into {} in {} batches, {} tile collections, {} snapshots, {:.1}s",
        s.points,
        s.collection,
        s.batches,
        s.tile_collections.len(),
        s.snapshots.len(),
        t.elapsed().as_secs_f64()
    );
    Ok(())
}

/// `partition --embeddings MIXTURE [--mixture-keep S]`: mixture shards + codebook (module doc of
/// [`slag_common::shards::mixture`]).
fn run_partition_mixture(args: &PartitionArgs, path: &std::path::Path) -> anyhow::Result<()> {
    let to_map = args.scene_to_map()?;
    let mix = read_mixture(args, path)?;
    // The segments beside the mixture file (the encoder writes both into OUT/), as for dense
    // embeddings: the shards then carry them (format version 4).
    let segments = resolve_segments(args, path)?;
    let segs = segments.as_ref();
    let up = args.up_or_cameras(to_map.as_ref())?;
    let t = std::time::Instant::now();
    let (m, report) = match &args.display_ply {
        Some(ply) => {
            let (cols, n) = display_columns(ply)?;
            let src = slag_common::shards::WithDisplay::from_columns(&mix, &cols)?;
            partition_with_segments(args, &src, Some(&mix), segs, up, to_map, Some(n))?
        }
        None => partition_with_segments(args, &mix, Some(&mix), segs, up, to_map, None)?,
    };
    println!(
        "scene {} generation {}: {} Gaussians as mixtures of {} slots over {} codebook rows in {} \
         shards + codebook, {} bytes ({:.1} B/Gaussian), up {:?} ({:?}), {:.1}s",
        m.scene_id,
        m.generation,
        m.total_gaussians,
        mix.keep,
        mix.codebook_len(),
        m.tiles.len(),
        report.bytes_stored,
        report.bytes_stored as f64 / m.total_gaussians.max(1) as f64,
        m.ground.up,
        m.ground.up_source,
        t.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Measures the committed partition's bytes from the store, prints the [`StorageReport`] and
/// writes it with `--report`.
fn report_partition(
    args: &PartitionArgs,
    store: &ShardStore,
    m: &Manifest,
    scene_gaussians: Option<u64>,
) -> anyhow::Result<StorageReport> {
    let bytes = store
        .scene_bytes(&m.scene_id)?
        .context("the partition was committed but its scene is missing from the store")?;
    let report = storage_report(m, scene_gaussians, bytes);
    println!("{report}");
    if let Some(path) = &args.report {
        let json = serde_json::to_vec_pretty(&report).context("report JSON")?;
        slag_common::io::write_atomic(path, &json)?;
    }
    Ok(report)
}

/// `partition --synthetic N[:DIM]`: a [`SyntheticScene`] (z up) straight into the store.
fn run_partition_synthetic(args: &PartitionArgs, spec: &str) -> anyhow::Result<()> {
    let mut it = spec.split(':');
    let n: usize = it
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
    anyhow::ensure!(
        args.qdrant_url.is_none() && args.display_ply.is_none(),
        "--synthetic has no display attributes and is not uploaded to Qdrant"
    );
    let to_map = args.scene_to_map()?;
    let scene = SyntheticScene::new(n, dim, 64, 2000.0, 42);
    let up = match args.up_choice(to_map.as_ref())? {
        Some(u) => u,
        None => UpChoice::Given(GroundFrame::from_axis_name("z")?),
    };
    let t = std::time::Instant::now();
    // A synthetic scene has no source .ply: its baseline counts the stored rows.
    let (m, _) = partition_source(args, &scene, None, up, to_map, None)?;
    let bytes: u64 = m.tiles.iter().map(|t| t.bytes).sum();
    println!(
        "scene {} generation {}: {} synthetic Gaussians (dim {dim}) in {} shards, {} bytes ({:?}), {:.1}s",
        m.scene_id,
        m.generation,
        m.total_gaussians,
        m.tiles.len(),
        bytes,
        m.dtype,
        t.elapsed().as_secs_f64()
    );
    Ok(())
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

/// The private key of a `--signing-key` flag, if given.
///
/// Errors: as [`SigningKey::read_pem`].
fn load_signing_key(path: Option<&std::path::Path>) -> slag_common::Result<Option<SigningKey>> {
    path.map(SigningKey::read_pem).transpose()
}

/// Refuses the private key file at `path` when users other than its owner may read or write it
/// (anyone who reads it can sign maps the robots accept), unless `allow` (`--allow-readable-key`,
/// then logged as a warning).
///
/// Errors: [`slag_common::Error::Param`] `signing_key` naming the file's mode.
fn check_key_mode(path: &std::path::Path, allow: bool) -> slag_common::Result<()> {
    let Some(mode) = slag_common::shards::signature::readable_by_others(path) else {
        return Ok(());
    };
    if allow {
        tracing::warn!(
            "{}: the private signing key may be read by other users (mode {mode:o}); chmod 600 it",
            path.display()
        );
        return Ok(());
    }
    Err(slag_common::Error::param(
        "signing_key",
        format!("{} (mode {mode:o})", path.display()),
        "a private key only its owner may read: chmod 600 it (or pass --allow-readable-key)",
    ))
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
