//! The tail's reduction on one device and what it is made of and leaves: [`TailInputs`],
//! [`reduce_on_device`] (its tiles taken in by a host thread), [`ReducedOutputs`], and the dense
//! file's writer ([`dense_writer`]). The tail ([`super::finish`]) runs it on one device, or on
//! several through [`super::devices`].

use std::path::Path;
use std::time::Instant;

use slag_common::embeddings::EmbeddingsWriter;
use slag_common::io::remove_stale;
use slag_common::mixture::SparseMixture;
use slag_common::{Error, Result};

use super::EncodeParams;
use crate::raster::{DeviceReduce, KeptTile, WeightRasterizer};

/// What every output of the tail is made from: the Gaussians' centres `means` (`[N]`, scene
/// units), the embedding width `dim`, the encode's parameters, the CLIP model id and the
/// scene's `.ply` path (both recorded in each file's header).
pub(super) struct TailInputs<'a> {
    pub(super) means: &'a [[f32; 3]],
    pub(super) dim: usize,
    pub(super) params: &'a EncodeParams,
    pub(super) model_id: &'a str,
    pub(super) ply: String,
}

/// What the tail's reduction leaves ([`reduce_outputs`]).
pub(super) struct ReducedOutputs {
    /// Whether the device reduced (the views were kept there) rather than the host.
    pub(super) on_device: bool,
    /// The rasterizers that reduced, with what they kept: let go beside the writes
    /// ([`let_go`]).
    pub(super) spent: Vec<Box<dyn WeightRasterizer>>,
    /// The dense file's writer, every row pushed, not yet finished; with [`EncodeParams::dense`].
    pub(super) writer: Option<EmbeddingsWriter>,
    /// The mixture's sparse parts; with [`EncodeParams::mixture_keep`].
    pub(super) sparse: Option<SparseMixture>,
    /// Gaussian-id chunks of the pass.
    pub(super) chunks: usize,
    /// Observed Gaussians (the rows of either form).
    pub(super) observed: usize,
    /// Wall seconds of the reduction, `gather_s` included.
    pub(super) reduce_s: f64,
    /// Seconds of it spent only on gathering the mixture's kept atoms (0 when the mixture is
    /// the only form: then the whole pass is its reduction).
    pub(super) gather_s: f64,
    /// Seconds of the dense write outside the reduction (0 without the dense file).
    pub(super) write_s: f64,
    /// The device reduction's waves and memory (zero when the host reduced).
    pub(super) memory: DeviceReduceMemory,
    /// When the host folded the views as they came ([`crate::aggregate::MixtureFold`]): the
    /// most bytes of its reduction at once (the running state and the views waiting for an
    /// earlier one); 0 otherwise.
    pub(super) host_fold_peak_bytes: u64,
    /// When the host folded the views into the dense accumulators as they came
    /// ([`crate::aggregate::DenseFold`], `--dense`): its tiles, spills and sweeps.
    pub(super) dense_fold: Option<crate::aggregate::DenseFoldStats>,
}

/// How the device reduction used the device's memory ([`crate::raster::KeptReduced`]).
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct DeviceReduceMemory {
    /// Times the kept views were reduced: 1 when every view was kept to the end, else the
    /// streamed reduction's waves.
    pub(super) waves: usize,
    /// The most bytes of the reduction on one device at once: its running state (streamed)
    /// plus the most label sums kept at once.
    pub(super) peak_bytes: u64,
}

/// The device reduction of the views `rasterizer` kept ([`WeightRasterizer::reduce_kept`];
/// of the Gaussian ids `gaussians` only, when given), each tile handed to a host thread
/// ([`take_tiles`]) so that the next tile is reduced while one is taken in: with
/// [`EncodeParams::mixture_keep`] its kept pairs gathered into the mixture's sparse rows over
/// the codebook of the kept views' mask embeddings, with [`EncodeParams::dense`] its unit rows
/// pushed to `writer` (the dense file's, [`dense_writer`]; with `means`, the Gaussians'
/// centres; without it the device makes no row). The reduction's seconds run until the last
/// tile was handed on.
///
/// Errors: the device's; the host thread's (I/O, non-finite rows, a Gaussian id without a mean),
/// which take precedence over the reduction's "host side stopped" error they cause.
pub(super) fn reduce_on_device(
    rasterizer: &mut dyn WeightRasterizer,
    out: &TailInputs,
    writer: Option<EmbeddingsWriter>,
    gaussians: Option<(u32, u32)>,
) -> Result<ReducedOutputs> {
    let (means, dim, params, model_id) = (out.means, out.dim, out.params, out.model_id);
    let t0 = Instant::now();
    let p = DeviceReduce {
        min_total_weight: params.reduce.min_total_weight,
        keep: params.mixture_keep.unwrap_or(1),
        dense: params.dense,
        gaussians,
    };
    let sparse = params.mixture_keep.map(|_| SparseMixture {
        dim,
        model_id: model_id.to_string(),
        offsets: vec![0],
        ..Default::default()
    });
    std::thread::scope(|s| {
        // The host's side of each tile on a thread of its own: the device reduces the next tile
        // meanwhile, and hands it over once the host has taken in the one before (no tile
        // waits between them: the host holds two tiles' outputs at most).
        let (tx, rx) = std::sync::mpsc::sync_channel::<KeptTile>(0);
        let handle = s.spawn(move || take_tiles(rx, means, sparse, writer));
        let reduced = rasterizer.reduce_kept(&p, &mut |tile| {
            tx.send(tile)
                .map_err(|_| Error::internal("the reduction's host side stopped early"))
        });
        let reduce_s = t0.elapsed().as_secs_f64();
        drop(tx);
        let (writer, mut sparse) = handle
            .join()
            .map_err(|_| Error::internal("the reduction's host thread panicked"))??;
        let out = reduced?;
        if let Some(s) = sparse.as_mut() {
            s.codebook = out.codebook;
        }
        let observed = match (&writer, &sparse) {
            (Some(w), _) => w.len(),
            (None, Some(s)) => s.gaussian_ids.len(),
            (None, None) => 0,
        };
        Ok(ReducedOutputs {
            on_device: true,
            spent: Vec::new(),
            writer,
            sparse,
            chunks: out.tiles,
            observed,
            reduce_s,
            gather_s: 0.0,
            write_s: t0.elapsed().as_secs_f64() - reduce_s,
            memory: DeviceReduceMemory {
                waves: out.waves,
                peak_bytes: out.state_bytes + out.peak_kept_bytes,
            },
            host_fold_peak_bytes: 0,
            dense_fold: None,
        })
    })
}

/// The host's side of the device reduction's tiles from `rx`, in order: each tile's centres
/// looked up in `means`, its kept pairs appended to `sparse` (the mixture's rows), its unit rows
/// (with `--dense`) pushed to `writer`. Returns both when the tiles end.
///
/// Errors: a Gaussian id without a mean ([`Error::Internal`]); the writer's (I/O, non-finite
/// rows).
fn take_tiles(
    rx: std::sync::mpsc::Receiver<KeptTile>,
    means: &[[f32; 3]],
    mut sparse: Option<SparseMixture>,
    mut writer: Option<EmbeddingsWriter>,
) -> Result<(Option<EmbeddingsWriter>, Option<SparseMixture>)> {
    for tile in rx {
        let run_means = tile
            .ids
            .iter()
            .map(|&k| {
                means.get(k as usize).copied().ok_or_else(|| {
                    Error::internal(format!("Gaussian {k} has no mean ({} given)", means.len()))
                })
            })
            .collect::<Result<Vec<_>>>()?;
        if let Some(s) = sparse.as_mut() {
            push_kept(s, &tile, &run_means);
        }
        if let Some(w) = writer.as_mut() {
            w.push(&tile.ids, &run_means, &tile.rows, &tile.total_weights)?;
        }
    }
    Ok((writer, sparse))
}

/// Appends the tile's observed Gaussians (ascending, with their centres `means`) and each
/// one's kept `(a_kj, codebook row)` pairs to the mixture's sparse rows.
fn push_kept(s: &mut SparseMixture, tile: &KeptTile, means: &[[f32; 3]]) {
    s.gaussian_ids.extend_from_slice(&tile.ids);
    s.means.extend_from_slice(means);
    s.offsets.reserve(tile.ids.len());
    for i in 0..tile.ids.len() {
        for &(a, atom) in tile.kept_of(i) {
            s.atoms.push(atom);
            s.weights.push(a);
        }
        s.offsets.push(s.atoms.len());
    }
}

/// The dense file's writer at `embeddings` with [`EncodeParams::dense`]; without it `None`, and
/// a dense file of an earlier run there is removed.
///
/// Errors: neither form asked for ([`Error::Invalid`]), I/O.
pub(super) fn dense_writer(
    params: &EncodeParams,
    dim: usize,
    embeddings: &Path,
) -> Result<Option<EmbeddingsWriter>> {
    if params.dense {
        return EmbeddingsWriter::create(embeddings, dim, params.precision).map(Some);
    }
    if params.mixture_keep.is_none() {
        return Err(Error::Invalid(
            "no embeddings output: keep the mixture (mixture_keep) or ask for the dense file"
                .into(),
        ));
    }
    remove_stale(embeddings)?;
    Ok(None)
}
