//! The shard stage run from typed settings: [`PartitionConfig`] says what to partition and how
//! (built from `partition`'s flags by `cli::PartitionArgs::config`, or by a library
//! caller), [`partition`] runs it: read the embeddings (either form) or make a synthetic scene,
//! choose the up axis and the scene-to-map transform, cut the tiles into the store (signed when
//! asked), report the bytes stored, and upload to Qdrant when asked.

use std::path::{Path, PathBuf};

use anyhow::Context;
use slag_common::embeddings::Embeddings;
use slag_common::forms::EmbeddingsForm;
use slag_common::mixture::MixtureEmbeddings;
use slag_common::shards::signature::SigningKey;
use slag_common::shards::synthetic::SyntheticScene;
use slag_common::shards::{
    DisplayColumns, Dtype, GaussianSource, GroundFrame, Manifest, SceneToMap,
};

use crate::partition::{
    PartitionParams, ShardCap, StorageReport, UpChoice, mixture_layout, resolve_max_per_shard,
    resolve_mixture_max_per_shard, shard_layout, storage_report,
};
use crate::qdrant::QdrantParams;
use crate::store::{ShardStore, partition_into_store_signed, partition_mixture_into_store_signed};

/// What a partition reads.
#[derive(Debug, Clone, PartialEq)]
pub enum PartitionInput {
    /// An embeddings file of `slag-encoder encode`, either form (mixture or dense), told apart by
    /// its header; a dense path that does not exist, with `mixture.safetensors` beside it, reads
    /// that mixture.
    Embeddings(PathBuf),
    /// A synthetic scene of `gaussians` unit vectors of width `dim` (64 clusters over 2 km ×
    /// 2 km, z up), generated per tile, for scale and load tests.
    Synthetic {
        /// Gaussians.
        gaussians: usize,
        /// Embedding width.
        dim: usize,
    },
}

/// Where the scene-to-map transform comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum ToMap {
    /// A JSON file of the transform, or the word `identity` ([`SceneToMap::read`]).
    File(PathBuf),
    /// Surveyed point pairs, fitted by Umeyama's similarity ([`SceneToMap::read_points`]).
    Points(PathBuf),
}

/// Which geometric segments the shards carry.
#[derive(Debug, Clone, PartialEq)]
pub enum SegmentsChoice {
    /// `segments.safetensors` beside the embeddings file when it exists, else none.
    Beside,
    /// This segments file.
    File(PathBuf),
    /// None (shard format 1, mixture shards 2).
    Off,
}

/// The settings of one partition: the shard stage's typed configuration, as `EncodeConfig` is
/// the encode's.
#[derive(Debug, Clone)]
pub struct PartitionConfig {
    /// What to partition.
    pub input: PartitionInput,
    /// With a mixture: keep each Gaussian's strongest slots only, this many.
    pub mixture_keep: Option<usize>,
    /// The publisher's shard store folder (created if missing).
    pub store: PathBuf,
    /// The scene's id in the store and the URLs.
    pub scene: String,
    /// How large one tile may grow.
    pub cap: ShardCap,
    /// Also write the stored-vs-dense report as JSON here.
    pub report: Option<PathBuf>,
    /// The world's up axis; `None`: the map's z with a transform, else the cameras', else PCA.
    pub up: Option<GroundFrame>,
    /// A scene folder whose cameras give the up axis (mean camera −y).
    pub cameras: Option<PathBuf>,
    /// The scene-to-map transform stored in the manifest.
    pub to_map: Option<ToMap>,
    /// A source `.ply` whose display columns the shards store.
    pub display_ply: Option<PathBuf>,
    /// Dense rows' storage type (mixture shards are f16).
    pub dtype: Dtype,
    /// The segments the shards carry.
    pub segments: SegmentsChoice,
    /// Upload to Qdrant after partitioning.
    pub qdrant: Option<QdrantParams>,
    /// Sign the manifest with this Ed25519 private key (PKCS#8 PEM).
    pub signing_key: Option<PathBuf>,
    /// Sign with a key that users other than its owner may read (refused otherwise).
    pub allow_readable_key: bool,
    /// The least generation to write (≥ 1); `None`: one more than the store's.
    pub start_generation: Option<u64>,
}

impl PartitionConfig {
    /// The scene-to-map transform of [`Self::to_map`], if any (printed).
    ///
    /// Errors: unreadable file, bad JSON, too few / collinear points, a non-rotation
    /// ([`slag_common::Error`]).
    pub fn scene_to_map(&self) -> slag_common::Result<Option<SceneToMap>> {
        let t = match &self.to_map {
            Some(ToMap::File(f)) => SceneToMap::read(f)?,
            Some(ToMap::Points(f)) => SceneToMap::read_points(f)?,
            None => return Ok(None),
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

    /// The up-axis choice: [`Self::up`], else the map's z when a transform is given, else the
    /// cameras', else PCA of the means.
    fn up_choice(&self, to_map: Option<&SceneToMap>) -> anyhow::Result<Option<UpChoice>> {
        Ok(if let Some(u) = self.up {
            Some(UpChoice::Given(u))
        } else {
            to_map
                .map(|t| crate::partition::map_ground_frame(t).map(UpChoice::Given))
                .transpose()?
        })
    }

    /// [`Self::up_choice`], else the mean camera up of [`Self::cameras`], else PCA.
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
}

/// The segments `--segments` names for the embeddings (or mixture) file at `embeddings`: the
/// file given, the `segments.safetensors` beside it when it exists, or none (`off`).
fn resolve_segments(
    c: &PartitionConfig,
    embeddings: &std::path::Path,
) -> anyhow::Result<Option<slag_common::segments::Segments>> {
    let path = match &c.segments {
        SegmentsChoice::Off => return Ok(None),
        SegmentsChoice::File(p) => p.clone(),
        SegmentsChoice::Beside => {
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
    c: &PartitionConfig,
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
            partition_source(c, &src, mix, up, to_map, scene_gaussians)
        }
        None => partition_source(c, src, mix, up, to_map, scene_gaussians),
    }
}

/// Resolves the cap for `src`, opens `--store` and partitions `src` into it, then prints and
/// (with `--report`) writes the [`StorageReport`]. `mix`: the mixture whose rows `src` gives ids,
/// means and display columns of (its shards are f16 slots, `--dtype` does not apply); `None`:
/// `src`'s own dense vectors. `scene_gaussians`: the source scene's Gaussian count if known. A
/// cap that cannot hold one Gaussian fails before the store is opened.
fn partition_source(
    c: &PartitionConfig,
    src: &impl GaussianSource,
    mix: Option<&MixtureEmbeddings>,
    up: UpChoice,
    to_map: Option<SceneToMap>,
    scene_gaussians: Option<u64>,
) -> anyhow::Result<(Manifest, StorageReport)> {
    let (max_per_shard, dtype) = match mix {
        None => {
            let layout = shard_layout(src, &c.scene, c.dtype);
            (resolve_max_per_shard(&layout, c.cap)?, c.dtype)
        }
        Some(mix) => {
            let layout = mixture_layout(src, &c.scene, mix.keep);
            let cap = resolve_mixture_max_per_shard(&layout, c.cap)?;
            (cap, Dtype::F16)
        }
    };
    let key = load_signing_key(c.signing_key.as_deref())?;
    let mut store = ShardStore::open(&c.store)?;
    if let Some(g) = c.start_generation {
        store = store.starting_at(g)?;
    }
    let store = &store;
    let params = PartitionParams {
        scene_id: c.scene.clone(),
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
    let report = report_partition(c, store, &m, scene_gaussians)?;
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

/// Runs the partition `c` asks for; prints a one-line summary and the stored-vs-dense
/// [`StorageReport`] (also written as JSON to [`PartitionConfig::report`]).
///
/// Errors: unreadable embeddings, invalid parameters (a shard cap smaller than one Gaussian's
/// shard, a cap of 0 Gaussians, a start generation of 0), store failures.
pub fn partition(c: &PartitionConfig) -> anyhow::Result<()> {
    // Reject a bad signing key before reading a large input.
    if let Some(p) = &c.signing_key {
        SigningKey::read_pem(p)?;
        check_key_mode(p, c.allow_readable_key)?;
    }
    if c.start_generation == Some(0) {
        return Err(slag_common::Error::param(
            "start_generation",
            0,
            "a generation ≥ 1 (above the one the robots hold)",
        )
        .into());
    }
    let path = match &c.input {
        PartitionInput::Synthetic { gaussians, dim } => {
            return run_partition_synthetic(c, *gaussians, *dim);
        }
        PartitionInput::Embeddings(path) => path,
    };
    let (path, form) = partition_input(path)?;
    let path = &path;
    let emb = match form {
        EmbeddingsForm::Mixture if c.qdrant.is_none() => {
            return run_partition_mixture(c, path);
        }
        EmbeddingsForm::Mixture => {
            eprintln!(
                "{}: Qdrant stores dense vectors: the mixture is expanded to its rows and \
                 partitioned dense",
                path.display()
            );
            slag_common::forms::expand_mixture(&read_mixture(c, path)?)
        }
        EmbeddingsForm::Dense => Embeddings::read(path)?,
    };
    let to_map = c.scene_to_map()?;
    let segments = resolve_segments(c, path)?;
    let segs = segments.as_ref();
    let up = c.up_or_cameras(to_map.as_ref())?;
    let t = std::time::Instant::now();
    // The embeddings file records the source .ply's Gaussian count (0 in files without it).
    let mut scene_gaussians = Some(emb.scene_gaussians).filter(|&n| n > 0);
    let (m, _) = match &c.display_ply {
        Some(ply) => {
            let (cols, n) = display_columns(ply)?;
            scene_gaussians = scene_gaussians.or(Some(n));
            let src = slag_common::shards::WithDisplay::from_columns(&emb, &cols)?;
            partition_with_segments(c, &src, None, segs, up, to_map, scene_gaussians)?
        }
        None => partition_with_segments(c, &emb, None, segs, up, to_map, scene_gaussians)?,
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
    match &c.qdrant {
        Some(params) => upload_to_qdrant(params, &emb, &m),
        None => Ok(()),
    }
}

/// The embeddings file a partition reads at `path` and its form (either form, by its header; a
/// missing dense file with `mixture.safetensors` beside it gives that mixture, said on stderr).
///
/// Errors: an unreadable file or one of neither form.
fn partition_input(path: &Path) -> anyhow::Result<(PathBuf, EmbeddingsForm)> {
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
    Ok((path.to_path_buf(), slag_common::forms::form_of(path)?))
}

/// The mixture at `path`, cut to [`PartitionConfig::mixture_keep`] slots when given.
///
/// Errors: unreadable file, a slot count out of range.
fn read_mixture(c: &PartitionConfig, path: &std::path::Path) -> anyhow::Result<MixtureEmbeddings> {
    let full = MixtureEmbeddings::read(path)?;
    Ok(match c.mixture_keep {
        Some(s) => full.truncated(s)?,
        None => full,
    })
}

/// Upserts `emb` (the rows `m` was partitioned from) into the Qdrant server of `params`.
///
/// Errors: Qdrant's, a collection or batch the server refuses.
fn upload_to_qdrant(params: &QdrantParams, emb: &Embeddings, m: &Manifest) -> anyhow::Result<()> {
    let url = &params.url;
    let t = std::time::Instant::now();
    // Display attributes are not uploaded; the plain embeddings have the same rows.
    let s = crate::qdrant::upload(emb, m, params).context("Qdrant upload")?;
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
fn run_partition_mixture(c: &PartitionConfig, path: &std::path::Path) -> anyhow::Result<()> {
    let to_map = c.scene_to_map()?;
    let mix = read_mixture(c, path)?;
    // The segments beside the mixture file (the encoder writes both into OUT/), as for dense
    // embeddings: the shards then carry them (format version 4).
    let segments = resolve_segments(c, path)?;
    let segs = segments.as_ref();
    let up = c.up_or_cameras(to_map.as_ref())?;
    let t = std::time::Instant::now();
    let (m, report) = match &c.display_ply {
        Some(ply) => {
            let (cols, n) = display_columns(ply)?;
            let src = slag_common::shards::WithDisplay::from_columns(&mix, &cols)?;
            partition_with_segments(c, &src, Some(&mix), segs, up, to_map, Some(n))?
        }
        None => partition_with_segments(c, &mix, Some(&mix), segs, up, to_map, None)?,
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
    c: &PartitionConfig,
    store: &ShardStore,
    m: &Manifest,
    scene_gaussians: Option<u64>,
) -> anyhow::Result<StorageReport> {
    let bytes = store
        .scene_bytes(&m.scene_id)?
        .context("the partition was committed but its scene is missing from the store")?;
    let report = storage_report(m, scene_gaussians, bytes);
    println!("{report}");
    if let Some(path) = &c.report {
        let json = serde_json::to_vec_pretty(&report).context("report JSON")?;
        slag_common::io::write_atomic(path, &json)?;
    }
    Ok(report)
}

/// A synthetic scene of `n` Gaussians of width `dim` ([`SyntheticScene`], z up) straight into the
/// store.
fn run_partition_synthetic(c: &PartitionConfig, n: usize, dim: usize) -> anyhow::Result<()> {
    anyhow::ensure!(
        c.qdrant.is_none() && c.display_ply.is_none(),
        "--synthetic has no display attributes and is not uploaded to Qdrant"
    );
    let to_map = c.scene_to_map()?;
    let scene = SyntheticScene::new(n, dim, 64, 2000.0, 42);
    let up = match c.up_choice(to_map.as_ref())? {
        Some(u) => u,
        None => UpChoice::Given(GroundFrame::from_axis_name("z")?),
    };
    let t = std::time::Instant::now();
    // A synthetic scene has no source .ply: its baseline counts the stored rows.
    let (m, _) = partition_source(c, &scene, None, up, to_map, None)?;
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

/// The private signing key at `path`, if given.
///
/// Errors: as [`SigningKey::read_pem`].
pub(crate) fn load_signing_key(
    path: Option<&std::path::Path>,
) -> slag_common::Result<Option<SigningKey>> {
    path.map(SigningKey::read_pem).transpose()
}

/// Refuses the private key file at `path` when users other than its owner may read or write it
/// (anyone who reads it can sign maps the robots accept), unless `allow` (`--allow-readable-key`,
/// then logged as a warning).
///
/// Errors: [`slag_common::Error::Param`] `signing_key` naming the file's mode.
pub(crate) fn check_key_mode(path: &std::path::Path, allow: bool) -> slag_common::Result<()> {
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
