//! The device reduction on several GPUs, in one of three ways:
//! - streamed ([`StreamSharing`], the default outputs where each GPU's share of the state fits
//!   its budget): each GPU folds one share of the Gaussians during the run, each view's records
//!   of the other shares sent to their GPUs as it is kept; at the end
//!   [`reduce_across_devices`] has each GPU fold its last views and write its share. The
//!   device memory does not grow with the views, and the bytes are those of one GPU.
//! - kept to the end ([`reduce_across_devices`], where the shares' state does not fit): each
//!   GPU kept the views it rasterized; the Gaussians are split into one range per GPU with
//!   about the same kept records each, every GPU sends the others the records of their ranges,
//!   and each reduces its own range at the same time. Each GPU reads back and takes in about
//!   `(G - 1) / G` of its records, and reduces `1 / G` of the work.
//! - [`one_device`] (with the dense file, whose rows one writer takes in order): every other
//!   GPU hands all its views over to the first, which reduces them all.

use std::ops::Range;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use slag_common::mixture::SparseMixture;
use slag_common::{Error, Result};

use super::reduction::{ReducedOutputs, TailInputs, dense_writer, reduce_on_device};
use crate::raster::{KeptExport, KeptRangeCursor, WeightRasterizer};

/// How the rasterizers of a run on several GPUs stream their kept views together
/// ([`WeightRasterizer::stream_kept_share`]): rasterizer `g` of `G` folds share `g` of the
/// Gaussians; each view it keeps goes, as it is kept, to the others (their shares of its
/// records); and a wave folds only the views below the lowest view not yet done on any
/// device, a view counting as done once it was sent. Each device so adds every view's terms
/// of its Gaussians in the encode's view order, as one device streaming alone adds them, and
/// writes the same bytes; its memory holds its share of the state and of the views not folded
/// yet, whatever the number of views.
pub(super) struct StreamSharing {
    /// Every rasterizer waits here until each has said whether it streams.
    barrier: std::sync::Barrier,
    /// Per rasterizer, where its share comes in; `None` where it does not stream.
    inboxes: Mutex<Vec<Option<crate::raster::gpu::ek::KeptInbox>>>,
    /// The views done on every device.
    done: Mutex<ViewsDone>,
}

impl StreamSharing {
    /// The sharing of `rasterizers` rasterizers over an encode of `n_views` views.
    pub(super) fn new(rasterizers: usize, n_views: usize) -> Self {
        StreamSharing {
            barrier: std::sync::Barrier::new(rasterizers),
            inboxes: Mutex::new(vec![None; rasterizers]),
            done: Mutex::new(ViewsDone::new(n_views)),
        }
    }

    /// Rasterizer `g` joins, before it keeps any view: with `keep` (the mixture's pairs, when
    /// it keeps its views on the device and may stream) it starts streaming its share; then it
    /// waits for every rasterizer of the run, and all stream together or none does
    /// ([`WeightRasterizer::share_kept_with`]). Every rasterizer of the run must call this
    /// once. Returns whether they stream together.
    pub(super) fn join(
        &self,
        g: usize,
        rasterizer: &mut dyn WeightRasterizer,
        keep: Option<usize>,
    ) -> bool {
        let shares = self.inboxes.lock().map_or(0, |i| i.len());
        let inbox = keep.and_then(|k| rasterizer.stream_kept_share(k, g, shares));
        if let Ok(mut inboxes) = self.inboxes.lock()
            && let Some(slot) = inboxes.get_mut(g)
        {
            *slot = inbox;
        }
        self.barrier.wait();
        let all: Option<Vec<_>> = match self.inboxes.lock() {
            Ok(inboxes) => inboxes.iter().cloned().collect(),
            Err(_) => None,
        };
        let peers = all.filter(|all| g < all.len()).map(|mut all| {
            all.remove(g);
            all
        });
        let together = peers.is_some();
        rasterizer.share_kept_with(peers);
        together
    }

    /// Marks `view` done (kept and sent) and returns the lowest view not done on any device.
    pub(super) fn view_done(&self, view: usize) -> usize {
        match self.done.lock() {
            Ok(mut done) => done.add(view),
            // A panicked worker: fold nothing more (the run fails).
            Err(_) => 0,
        }
    }
}

/// The views done so far, as the lowest view not done yet: with one rasterizer every view of
/// the encode comes to it, and with several that stream together each marks its views in one
/// of these ([`StreamSharing`]), so no view below that one is still to come.
pub(super) struct ViewsDone {
    done: Vec<bool>,
    below: usize,
}

impl ViewsDone {
    pub(super) fn new(n_views: usize) -> Self {
        ViewsDone {
            done: vec![false; n_views],
            below: 0,
        }
    }

    /// Marks `view` done and returns the lowest view not done.
    pub(super) fn add(&mut self, view: usize) -> usize {
        if let Some(d) = self.done.get_mut(view) {
            *d = true;
        }
        while self.done.get(self.below).copied().unwrap_or(false) {
            self.below += 1;
        }
        self.below
    }
}

/// Bytes of kept records in one batch of an exchange between devices ([`exchange_kept`]). A
/// device's reader holds one, its channel one and the taker on the other side one: about three
/// per device on the host, as many bytes as a hand-over's three batches on two devices.
const EXCHANGE_BATCH_BYTES: u64 = 128 << 20;

/// The device reduction with its work split between the devices in `device`, every device
/// reducing its own range of Gaussians on a thread of its own ([`reduce_on_device`]): the
/// shares of a streamed reduction ([`StreamSharing`]: each folded its range as the views came,
/// and folds the last views now), or, where the devices kept their own views to the end, the
/// Gaussians cut into one range per device with about the same kept records
/// ([`split_by_records`]) and every device sending the others the records of their ranges
/// first ([`exchange_kept`]). The mixture's rows are joined in Gaussian order; every device
/// holds every view, so their codebooks are the same. The dense file is not made this way
/// ([`one_device`]); a dense file of an earlier run is removed.
///
/// Errors: the devices'; [`Error::Internal`] for devices whose codebooks differ.
pub(super) fn reduce_across_devices(
    mut device: Vec<Box<dyn WeightRasterizer>>,
    out: &TailInputs,
    embeddings: &std::path::Path,
) -> Result<ReducedOutputs> {
    if dense_writer(out.params, out.dim, embeddings)?.is_some() {
        return Err(Error::internal(
            "the dense file's rows are reduced on one device",
        ));
    }
    let t0 = Instant::now();
    // The rasterizers come back in the order they ended; their shares go in Gaussian order.
    device.sort_by_key(|r| r.kept_share());
    let streamed: Option<Vec<Range<u32>>> = device
        .iter()
        .map(|r| r.kept_share().map(|(a, b)| a..b))
        .collect();
    let ranges = match &streamed {
        Some(shares) => shares.clone(),
        None => split_by_records(&device, out.means.len())?,
    };
    let device: Vec<Mutex<Box<dyn WeightRasterizer>>> =
        device.into_iter().map(Mutex::new).collect();
    if streamed.is_none() {
        exchange_kept(&device, &ranges, EXCHANGE_BATCH_BYTES)?;
    }
    let exchange_s = t0.elapsed().as_secs_f64();
    let parts: Vec<Result<ReducedOutputs>> = std::thread::scope(|s| {
        let handles: Vec<_> = device
            .into_iter()
            .zip(&ranges)
            .map(|(r, range)| {
                s.spawn(move || {
                    let mut r = r.into_inner().map_err(|_| poisoned())?;
                    let range = Some((range.start, range.end));
                    let mut reduced = reduce_on_device(&mut *r, out, None, range)?;
                    reduced.spent.push(r);
                    Ok(reduced)
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().unwrap_or_else(|_| Err(panicked("reduction"))))
            .collect()
    });
    let parts = parts.into_iter().collect::<Result<Vec<_>>>()?;
    join_reduced(parts, exchange_s)
}

/// The devices' reductions of consecutive ranges as one: the mixture's rows one after the other
/// (the first codebook, which every other must equal), the tiles and rows added up, the
/// seconds those of the slowest device after the exchange's `exchange_s`.
///
/// Errors: [`Error::Internal`] for codebooks that differ.
fn join_reduced(parts: Vec<ReducedOutputs>, exchange_s: f64) -> Result<ReducedOutputs> {
    let slowest = |f: fn(&ReducedOutputs) -> f64| parts.iter().map(f).fold(0.0, f64::max);
    let (reduce_s, write_s) = (slowest(|p| p.reduce_s), slowest(|p| p.write_s));
    let chunks = parts.iter().map(|p| p.chunks).sum();
    let observed = parts.iter().map(|p| p.observed).sum();
    let memory = super::reduction::DeviceReduceMemory {
        waves: parts.iter().map(|p| p.memory.waves).max().unwrap_or(0),
        peak_bytes: parts.iter().map(|p| p.memory.peak_bytes).max().unwrap_or(0),
    };
    let (mut sparse, mut spent) = (None::<SparseMixture>, Vec::new());
    for p in parts {
        spent.extend(p.spent);
        match (sparse.as_mut(), p.sparse) {
            (_, None) => {}
            (None, Some(part)) => sparse = Some(part),
            (Some(all), Some(part)) => append_rows(all, part)?,
        }
    }
    Ok(ReducedOutputs {
        on_device: true,
        spent,
        writer: None,
        sparse,
        chunks,
        observed,
        reduce_s: exchange_s + reduce_s,
        gather_s: 0.0,
        write_s,
        memory,
        host_fold_peak_bytes: 0,
        dense_fold: None,
    })
}

/// Appends `part`'s rows (Gaussians after `all`'s) to `all`.
///
/// Errors: [`Error::Internal`] when their codebooks differ.
fn append_rows(all: &mut SparseMixture, part: SparseMixture) -> Result<()> {
    if part.codebook != all.codebook {
        return Err(Error::internal(format!(
            "devices reduced over different codebooks ({} and {} values)",
            all.codebook.len(),
            part.codebook.len()
        )));
    }
    let base = all.atoms.len();
    all.offsets
        .extend(part.offsets.iter().skip(1).map(|o| o + base));
    all.gaussian_ids.extend(part.gaussian_ids);
    all.means.extend(part.means);
    all.atoms.extend(part.atoms);
    all.weights.extend(part.weights);
    Ok(())
}

/// One range of Gaussian ids per device, in device order, of whole blocks
/// ([`WeightRasterizer::kept_block_records`]) and about the same kept records each (the
/// reduction's work follows its records): [`split_blocks`] over every device's counts.
///
/// Errors: [`Error::Internal`] for a device that kept nothing, or devices of other scenes.
pub(crate) fn split_by_records(
    device: &[Box<dyn WeightRasterizer>],
    n_gaussians: usize,
) -> Result<Vec<Range<u32>>> {
    let n = u32::try_from(n_gaussians)
        .map_err(|_| Error::Invalid(format!("{n_gaussians} Gaussians: past 2^32")))?;
    let mut block = 1u32;
    let mut totals: Vec<u64> = Vec::new();
    for (d, r) in device.iter().enumerate() {
        let Some((size, counts)) = r.kept_block_records() else {
            return Err(Error::internal(format!("device {d} kept no views")));
        };
        if d > 0 && (size != block || counts.len() != totals.len()) {
            return Err(Error::internal(format!(
                "device {d} keeps {} blocks of {size} Gaussians, device 0 {} of {block}",
                counts.len(),
                totals.len()
            )));
        }
        if d == 0 {
            (block, totals) = (size, counts);
        } else {
            totals.iter_mut().zip(counts).for_each(|(t, c)| *t += c);
        }
    }
    let at = |b: usize| u32::try_from(b).map_or(n, |b| b.saturating_mul(block).min(n));
    Ok(split_blocks(&totals, device.len())
        .into_iter()
        .map(|r| at(r.start)..at(r.end))
        .collect())
}

/// `parts` consecutive runs of the blocks whose record counts are `records`, covering them
/// all: run `i` ends at the first block where the running sum reaches `(i + 1) / parts` of the
/// total (the last takes the rest). A run may be empty (fewer blocks than parts, or a block
/// heavier than a share).
pub(crate) fn split_blocks(records: &[u64], parts: usize) -> Vec<Range<usize>> {
    let total: u128 = records.iter().map(|&r| u128::from(r)).sum();
    let (mut out, mut start, mut b, mut sum) = (Vec::with_capacity(parts), 0, 0, 0u128);
    for i in 0..parts {
        let goal = total * (i as u128 + 1) / parts.max(1) as u128;
        let last = i + 1 == parts;
        while b < records.len() && (sum < goal || last) {
            sum += u128::from(records[b]);
            b += 1;
        }
        out.push(start..b);
        start = b;
    }
    out
}

/// Every device in `device` sends each other device the records of that one's range of
/// Gaussians (`ranges[d]` for device `d`), `batch_bytes` at a time
/// ([`WeightRasterizer::export_kept_range`], [`WeightRasterizer::import_uploaded`]). Per device
/// one thread reads its batches back for the others ([`send_ranges`]) and one takes in what the
/// others send ([`take_batches`]), uploading each batch to the device before it locks the
/// device to add it: a device is locked for one batch's reading or adding at a time, and all
/// devices work at once.
///
/// Errors: the devices' (the first stops the exchange); [`Error::Internal`] for a device
/// poisoned by a panicked thread.
pub(crate) fn exchange_kept(
    device: &[Mutex<Box<dyn WeightRasterizer>>],
    ranges: &[Range<u32>],
    batch_bytes: u64,
) -> Result<()> {
    let t0 = Instant::now();
    let n = device.len();
    if ranges.len() != n {
        return Err(Error::internal(format!(
            "{} ranges for {n} devices",
            ranges.len()
        )));
    }
    let (senders, receivers): (Vec<_>, Vec<_>) = (0..n)
        .map(|_| std::sync::mpsc::sync_channel::<KeptExport>(1))
        .unzip();
    let stats = ExchangeStats::default();
    let results: Vec<Result<()>> = std::thread::scope(|s| {
        let takers: Vec<_> = receivers
            .into_iter()
            .enumerate()
            .map(|(d, rx)| {
                let (device, stats) = (&device[d], &stats);
                s.spawn(move || take_batches(device, rx, stats))
            })
            .collect();
        let readers: Vec<_> = (0..n)
            .map(|from| {
                let senders = senders.clone();
                let (stats, send) = (&stats, (ranges, batch_bytes));
                s.spawn(move || send_ranges(device, from, &senders, send, stats))
            })
            .collect();
        drop(senders);
        let join = |h: std::thread::ScopedJoinHandle<'_, Result<()>>| {
            h.join().unwrap_or_else(|_| Err(panicked("exchange")))
        };
        let mut out: Vec<Result<()>> = readers.into_iter().map(join).collect();
        out.extend(takers.into_iter().map(join));
        out
    });
    results.into_iter().collect::<Result<()>>()?;
    let secs = |a: &AtomicU64| a.load(Ordering::Relaxed) as f64 * 1e-9;
    tracing::debug!(
        target: "slag_encoder::pipeline",
        devices = n,
        bytes = stats.bytes.load(Ordering::Relaxed),
        read_s = secs(&stats.read_ns),
        upload_s = secs(&stats.upload_ns),
        add_s = secs(&stats.add_ns),
        seconds = t0.elapsed().as_secs_f64(),
        "kept views exchanged"
    );
    Ok(())
}

/// What an exchange moved and where its time went, summed over the devices' threads.
#[derive(Default)]
struct ExchangeStats {
    bytes: AtomicU64,
    read_ns: AtomicU64,
    upload_ns: AtomicU64,
    add_ns: AtomicU64,
}

impl ExchangeStats {
    fn add_time(counter: &AtomicU64, since: Instant) {
        counter.fetch_add(since.elapsed().as_nanos() as u64, Ordering::Relaxed);
    }
}

/// Reader step of [`exchange_kept`]: device `from` reads back its records of every other
/// device's range (`ranges`, in batches of `batch_bytes`) and sends them to that device's taker
/// (`senders[to]`), one device after the other.
///
/// Errors: the device's.
fn send_ranges(
    device: &[Mutex<Box<dyn WeightRasterizer>>],
    from: usize,
    senders: &[std::sync::mpsc::SyncSender<KeptExport>],
    (ranges, batch_bytes): (&[Range<u32>], u64),
    stats: &ExchangeStats,
) -> Result<()> {
    let n = device.len();
    for to in (1..n).map(|k| (from + k) % n) {
        let mut cursor = KeptRangeCursor::new(ranges[to].clone());
        loop {
            let mut rasterizer = device[from].lock().map_err(|_| poisoned())?;
            let t = Instant::now();
            let batch = rasterizer.export_kept_range(&mut cursor, batch_bytes)?;
            drop(rasterizer);
            ExchangeStats::add_time(&stats.read_ns, t);
            let Some(mut batch) = batch else { break };
            batch.source = from as u32;
            let b: usize = batch.parts.iter().map(|p| p.1.len()).sum();
            stats.bytes.fetch_add(b as u64, Ordering::Relaxed);
            if senders[to].send(batch).is_err() {
                // The taker stopped on an error of its own, which it returns.
                break;
            }
        }
    }
    Ok(())
}

/// Taker step of [`exchange_kept`]: every batch from `rx` uploaded to the device without
/// holding it ([`WeightRasterizer::kept_uploader`]; a rasterizer without one takes the batch
/// as it is), then added under its lock.
///
/// Errors: the device's; on an error `rx` is dropped, so the readers sending here stop at their
/// next batch.
fn take_batches(
    device: &Mutex<Box<dyn WeightRasterizer>>,
    rx: std::sync::mpsc::Receiver<KeptExport>,
    stats: &ExchangeStats,
) -> Result<()> {
    let uploader = device.lock().map_err(|_| poisoned())?.kept_uploader();
    for batch in rx {
        let t = Instant::now();
        let Some(uploader) = &uploader else {
            device.lock().map_err(|_| poisoned())?.import_kept(batch)?;
            ExchangeStats::add_time(&stats.add_ns, t);
            continue;
        };
        let uploaded = uploader.upload(batch);
        ExchangeStats::add_time(&stats.upload_ns, t);
        let mut rasterizer = device.lock().map_err(|_| poisoned())?;
        let t = Instant::now();
        rasterizer.import_uploaded(uploaded)?;
        ExchangeStats::add_time(&stats.add_ns, t);
    }
    Ok(())
}

fn poisoned() -> Error {
    Error::internal("a device poisoned by a panicked thread")
}

fn panicked(what: &str) -> Error {
    Error::internal(format!("a device's {what} thread panicked"))
}

/// Bytes of kept records that one batch of a hand-over between devices holds on the host
/// ([`hand_over`]).
const HAND_OVER_BATCH_BYTES: u64 = 256 << 20;

/// The rasterizers that kept their views on their devices, as one: the first, with every other
/// one's views imported ([`WeightRasterizer::import_kept`]); `None` without any.
///
/// Errors: the devices' (reading the others' sums back).
pub(super) fn one_device(
    device: Vec<Box<dyn WeightRasterizer>>,
) -> Result<Option<Box<dyn WeightRasterizer>>> {
    let mut rasterizers = device.into_iter();
    let Some(mut first) = rasterizers.next() else {
        return Ok(None);
    };
    for other in rasterizers {
        hand_over(other, &mut *first)?;
    }
    Ok(Some(first))
}

/// Moves every view `from` kept to `to`, batch by batch ([`HAND_OVER_BATCH_BYTES`]): a thread
/// reads `from`'s next batch back while `to` takes the one before, so the host holds at most
/// three batches, and `from`'s records are freed as they go.
///
/// Errors: either device's.
fn hand_over(mut from: Box<dyn WeightRasterizer>, to: &mut dyn WeightRasterizer) -> Result<()> {
    let t0 = Instant::now();
    let (tx, rx) = std::sync::mpsc::sync_channel::<crate::raster::KeptExport>(1);
    let (bytes, read_s, read) = std::thread::scope(|s| {
        let reader = s.spawn(move || -> Result<f64> {
            let mut read_s = 0.0;
            loop {
                let t = Instant::now();
                let batch = from.export_kept_batch(HAND_OVER_BATCH_BYTES)?;
                read_s += t.elapsed().as_secs_f64();
                // Done, or the importer stopped on an error of its own.
                let Some(batch) = batch else {
                    return Ok(read_s);
                };
                if tx.send(batch).is_err() {
                    return Ok(read_s);
                }
            }
        });
        let mut bytes = 0usize;
        let imported = rx.iter().try_for_each(|batch| {
            bytes += batch.parts.iter().map(|p| p.1.len()).sum::<usize>();
            to.import_kept(batch)
        });
        // An import error hangs up first, so that the reader stops at its next batch.
        drop(rx);
        let read = reader
            .join()
            .unwrap_or_else(|_| Err(Error::internal("a kept views' reader panicked")));
        (
            bytes,
            read.as_ref().copied().unwrap_or(0.0),
            read.and(imported),
        )
    });
    tracing::debug!(
        target: "slag_encoder::pipeline",
        bytes,
        read_s,
        seconds = t0.elapsed().as_secs_f64(),
        "kept views handed over"
    );
    read
}

#[cfg(test)]
mod tests {
    use super::split_blocks;

    /// The runs cover the blocks in order, each ends where the running sum first reaches its
    /// share, and a block heavier than a share leaves the runs after it empty, not missing.
    #[test]
    fn the_runs_cover_every_block_with_about_a_share_each() {
        let records = [5u64, 1, 1, 1, 1, 1, 5, 5, 0, 0];
        let runs = split_blocks(&records, 2);
        assert_eq!(runs, vec![0..6, 6..10], "10 of 20 records in the first run");
        let sums: Vec<u64> = runs
            .iter()
            .map(|r| records[r.clone()].iter().sum())
            .collect();
        assert_eq!(sums, vec![10, 10]);
        assert_eq!(
            split_blocks(&records, 3),
            vec![0..2, 2..7, 7..10],
            "6, 9 and 5 records"
        );
        assert_eq!(split_blocks(&[9, 1], 3), vec![0..1, 1..1, 1..2]);
        assert_eq!(split_blocks(&[], 2), vec![0..0, 0..0]);
        assert_eq!(
            split_blocks(&[0, 0, 0], 2),
            vec![0..0, 0..3],
            "nothing kept: the last takes all"
        );
        assert_eq!(split_blocks(&[3, 4], 1), vec![0..2]);
    }
}
