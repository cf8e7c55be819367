//! A partition's checkpoint: the running state of its Gaussians (the mixture's fold, the masks'
//! record) after views `0..next`, in one file per partition, `OUT/.cluster-<p>-of-<P>.checkpoint`,
//! written atomically (`.partial`, fsync, rename, folder sync) and read back by a rerun of the
//! same job ([`super::resume`]).
//!
//! # Format (little-endian)
//!
//! ```text
//!   magic "SLAGCKP1"
//!   job digest [32]  partition u32  peers u32  gaussians u64  views u32  dim u64
//!   next u32  entries u64  masks u64
//!   fold? u8 { keep u64  min_total_weight f64  keeps_codebook u8  atoms u64
//!              den [N] f64  kept [N·keep] (f32, u32)  n_kept [N] u8  codebook [atoms·D] f32 }
//!   record? u8 { slots u64  view_count u64  views [N·S] u16  masks [N·S] u16  weights [N·S] f32 }
//!   SHA-256 of every byte above [32]
//! ```
//!
//! Each array is preceded by its length (u64 elements). A file that does not parse, is shorter
//! or longer than its lengths say, or whose SHA-256 differs is refused by [`read`] with
//! [`Error::Format`]; one of another job by [`Saved::check_job`].

use std::borrow::Cow;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use ring::digest::{Context, SHA256};
use slag_common::mask_record::MaskRecord;
use slag_common::{Error, Result};

use crate::aggregate::FoldState;

/// The file's first bytes (format version 1).
const MAGIC: &[u8; 8] = b"SLAGCKP1";

/// Elements converted per write or read of an array.
const CHUNK: usize = 1 << 16;

/// The checkpoint of partition `partition` of `peers` under the output folder `out`.
pub(super) fn path(out: &Path, partition: u32, peers: u32) -> PathBuf {
    out.join(format!(".cluster-{partition}-of-{peers}.checkpoint"))
}

/// Removes the checkpoint of partition `partition` of `peers` under `out` and a `.partial` one
/// beside it, once the job has completed; a failure is logged (a stale checkpoint is refused or
/// resumed by a later run, never mistaken for output).
pub(super) fn remove(out: &Path, partition: u32, peers: u32) {
    let path = path(out, partition, peers);
    let mut partial = path.clone().into_os_string();
    partial.push(".partial");
    for p in [path, PathBuf::from(partial)] {
        if let Err(e) = slag_common::io::remove_stale(&p) {
            tracing::warn!("the finished job's checkpoint stays: {e}");
        }
    }
}

/// What a checkpoint belongs to and how far its partition got.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Progress {
    /// SHA-256 of the job's arguments, scene and views ([`super::resume::job_digest`]).
    pub(super) job: [u8; 32],
    pub(super) partition: u32,
    pub(super) peers: u32,
    /// The scene's Gaussians and the job's views.
    pub(super) scene: (u64, u32),
    /// Embedding width D.
    pub(super) dim: u64,
    /// Views folded into the state: `0..next`.
    pub(super) next: u32,
    /// Non-zero `a_kj` of the partition's Gaussians in those views.
    pub(super) entries: u64,
    /// Masks of those views.
    pub(super) masks: u64,
}

/// A partition's state as written and read back: [`Progress`], the mixture's fold (with the
/// mixture) and the masks' record of the partition's Gaussians (with the record).
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Saved<'a> {
    pub(super) progress: Progress,
    pub(super) fold: Option<FoldState<'a>>,
    pub(super) record: Option<Cow<'a, MaskRecord>>,
}

impl Saved<'_> {
    /// Refuses a checkpoint of another job than `job` (digest), partition or process count.
    ///
    /// Errors: [`Error::Format`] naming `path` and what to do: rerun with the arguments of the
    /// job that wrote it, or remove it to start afresh.
    pub(super) fn check_job(
        &self,
        path: &Path,
        job: &[u8; 32],
        partition: u32,
        peers: u32,
    ) -> Result<()> {
        let p = &self.progress;
        if (&p.job, p.partition, p.peers) == (job, partition, peers) {
            return Ok(());
        }
        Err(Error::format(
            path,
            format!(
                "a checkpoint of another job (other encode arguments, scene, views or process \
                 count) after {} views: rerun every process with that job's arguments to resume \
                 it, or remove OUT/.cluster-*.checkpoint on every machine (or pass another --out) \
                 to start this job afresh",
                p.next
            ),
        ))
    }
}

/// A file being written: the bytes go through a buffer and into a SHA-256.
struct HashWriter {
    w: BufWriter<std::fs::File>,
    hash: Context,
    bytes: u64,
    path: PathBuf,
}

impl HashWriter {
    fn put(&mut self, b: &[u8]) -> Result<()> {
        self.hash.update(b);
        self.bytes += b.len() as u64;
        self.w.write_all(b).map_err(|e| Error::io(&self.path, e))
    }

    /// `items` as its length (u64) then each item's bytes, converted a chunk at a time.
    fn array<T: Copy, const B: usize>(&mut self, items: &[T], enc: fn(T) -> [u8; B]) -> Result<()> {
        self.put(&(items.len() as u64).to_le_bytes())?;
        let mut buf = Vec::with_capacity(CHUNK.min(items.len()) * B);
        for chunk in items.chunks(CHUNK) {
            buf.clear();
            chunk.iter().for_each(|&x| buf.extend_from_slice(&enc(x)));
            self.put(&buf)?;
        }
        Ok(())
    }
}

/// Writes `saved` to `path` atomically: `<path>.partial`, fsync, rename, the folder synced (each
/// step a durability boundary `cluster.checkpoint:write`, `:fsync`, `:rename`, `:dir_sync`,
/// [`slag_common::fault`]); returns the bytes written. A crash leaves the previous checkpoint or
/// this one.
///
/// Errors: [`Error::Io`] naming the file or folder that failed.
pub(super) fn write(path: &Path, saved: &Saved<'_>) -> Result<u64> {
    const SITE: &str = "cluster.checkpoint";
    let (tmp, f) = slag_common::io::create_partial(path)?;
    let mut w = HashWriter {
        w: BufWriter::with_capacity(1 << 20, f),
        hash: Context::new(&SHA256),
        bytes: 0,
        path: tmp.clone(),
    };
    write_body(&mut w, saved)?;
    let digest = w.hash.clone().finish();
    w.put(digest.as_ref())?;
    let f =
        w.w.into_inner()
            .map_err(|e| Error::io(&tmp, e.into_error()))?;
    slag_common::fault::boundary_in(SITE, "write");
    f.sync_all().map_err(|e| Error::io(&tmp, e))?;
    slag_common::fault::boundary_in(SITE, "fsync");
    drop(f);
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))?;
    slag_common::fault::boundary_in(SITE, "rename");
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        slag_common::io::sync_dir(dir)?;
        slag_common::fault::boundary_in(SITE, "dir_sync");
    }
    Ok(w.bytes)
}

/// Everything but the trailing SHA-256 (module doc).
fn write_body(w: &mut HashWriter, saved: &Saved<'_>) -> Result<()> {
    let p = &saved.progress;
    w.put(MAGIC)?;
    w.put(&p.job)?;
    for x in [p.partition, p.peers] {
        w.put(&x.to_le_bytes())?;
    }
    w.put(&p.scene.0.to_le_bytes())?;
    w.put(&p.scene.1.to_le_bytes())?;
    w.put(&p.dim.to_le_bytes())?;
    w.put(&p.next.to_le_bytes())?;
    w.put(&p.entries.to_le_bytes())?;
    w.put(&p.masks.to_le_bytes())?;
    w.put(&[saved.fold.is_some() as u8])?;
    if let Some(f) = &saved.fold {
        w.put(&(f.keep as u64).to_le_bytes())?;
        w.put(&f.min_total_weight.to_le_bytes())?;
        w.put(&[f.keeps_codebook as u8])?;
        w.put(&(f.atoms as u64).to_le_bytes())?;
        w.array(&f.den, f64::to_le_bytes)?;
        w.array(&f.kept, pair_bytes)?;
        w.array(&f.n_kept, |x: u8| [x])?;
        w.array(&f.codebook, f32::to_le_bytes)?;
    }
    w.put(&[saved.record.is_some() as u8])?;
    if let Some(r) = &saved.record {
        w.put(&(r.slots as u64).to_le_bytes())?;
        w.put(&(r.view_count as u64).to_le_bytes())?;
        w.array(&r.views, u16::to_le_bytes)?;
        w.array(&r.masks, u16::to_le_bytes)?;
        w.array(&r.weights, f32::to_le_bytes)?;
    }
    Ok(())
}

fn pair_bytes((a, atom): (f32, u32)) -> [u8; 8] {
    let mut b = [0; 8];
    b[..4].copy_from_slice(&a.to_le_bytes());
    b[4..].copy_from_slice(&atom.to_le_bytes());
    b
}

fn pair_of(b: [u8; 8]) -> (f32, u32) {
    let (a, atom) = b.split_at(4);
    let a: [u8; 4] = a.try_into().unwrap_or_default();
    let atom: [u8; 4] = atom.try_into().unwrap_or_default();
    (f32::from_le_bytes(a), u32::from_le_bytes(atom))
}

/// A file being read: its bytes before the trailing SHA-256, hashed as they are read.
struct HashReader {
    r: BufReader<std::fs::File>,
    hash: Context,
    /// Bytes left before the trailer.
    left: u64,
    path: PathBuf,
}

impl HashReader {
    fn corrupt(&self, what: &str) -> Error {
        Error::format(
            &self.path,
            format!(
                "a damaged cluster checkpoint ({what}); it is ignored and its partition starts \
                 afresh, or remove it"
            ),
        )
    }

    fn take<const B: usize>(&mut self) -> Result<[u8; B]> {
        let mut b = [0u8; B];
        self.fill(&mut b)?;
        Ok(b)
    }

    fn fill(&mut self, b: &mut [u8]) -> Result<()> {
        if (b.len() as u64) > self.left {
            return Err(self.corrupt("truncated"));
        }
        self.r.read_exact(b).map_err(|e| Error::io(&self.path, e))?;
        self.hash.update(b);
        self.left -= b.len() as u64;
        Ok(())
    }

    fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take()?))
    }

    fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(self.take()?))
    }

    fn flag(&mut self) -> Result<bool> {
        match self.take::<1>()?[0] {
            0 => Ok(false),
            1 => Ok(true),
            _ => Err(self.corrupt("a flag that is neither 0 nor 1")),
        }
    }

    /// An array of `expected` elements of `B` bytes each (its length prefix must say so).
    fn array<T, const B: usize>(&mut self, expected: u64, dec: fn([u8; B]) -> T) -> Result<Vec<T>> {
        let n = self.u64()?;
        if n != expected {
            return Err(self.corrupt(&format!("an array of {n} elements where {expected} belong")));
        }
        if n.saturating_mul(B as u64) > self.left {
            return Err(self.corrupt("truncated"));
        }
        let mut out = Vec::with_capacity(n as usize);
        let mut buf = vec![0u8; CHUNK.min(n as usize) * B];
        let mut left = n as usize;
        while left > 0 {
            let k = left.min(CHUNK);
            self.fill(&mut buf[..k * B])?;
            out.extend(buf[..k * B].chunks_exact(B).map(|c| {
                let mut a = [0u8; B];
                a.copy_from_slice(c);
                dec(a)
            }));
            left -= k;
        }
        Ok(out)
    }
}

/// Reads the checkpoint at `path` (module doc's format), checking its lengths against the
/// Gaussians of its partition and its SHA-256.
///
/// Errors: [`Error::Io`] (unreadable); [`Error::Format`] naming `path` for a file that is not a
/// checkpoint, truncated, longer than its contents, inconsistent or damaged (SHA-256).
pub(super) fn read(path: &Path) -> Result<Saved<'static>> {
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let len = f.metadata().map_err(|e| Error::io(path, e))?.len();
    let mut r = HashReader {
        r: BufReader::with_capacity(1 << 20, f),
        hash: Context::new(&SHA256),
        left: len.saturating_sub(32),
        path: path.to_path_buf(),
    };
    if len < 32 || r.take::<8>()? != *MAGIC {
        return Err(r.corrupt("not a cluster checkpoint of this version"));
    }
    let progress = read_progress(&mut r)?;
    let n = super::records::local_gaussians(
        progress.partition as u64,
        progress.scene.0,
        progress.peers as u64,
    ) as u64;
    let fold = match r.flag()? {
        true => Some(FoldState {
            next: progress.next as usize,
            ..read_fold(&mut r, n, progress.dim)?
        }),
        false => None,
    };
    let record = match r.flag()? {
        true => Some(Cow::Owned(read_record(&mut r, n)?)),
        false => None,
    };
    if r.left != 0 {
        return Err(r.corrupt("bytes past its contents"));
    }
    let want = r.hash.clone().finish();
    let mut trailer = [0u8; 32];
    r.r.read_exact(&mut trailer)
        .map_err(|e| Error::io(path, e))?;
    if trailer != want.as_ref() {
        return Err(r.corrupt("its SHA-256 does not match its contents"));
    }
    let saved = Saved {
        progress,
        fold,
        record,
    };
    Ok(saved)
}

fn read_progress(r: &mut HashReader) -> Result<Progress> {
    let job = r.take::<32>()?;
    let (partition, peers) = (r.u32()?, r.u32()?);
    let scene = (r.u64()?, r.u32()?);
    let dim = r.u64()?;
    let (next, entries, masks) = (r.u32()?, r.u64()?, r.u64()?);
    if peers == 0 || partition >= peers || next > scene.1 {
        return Err(r.corrupt("partition, processes or views out of range"));
    }
    Ok(Progress {
        job,
        partition,
        peers,
        scene,
        dim,
        next,
        entries,
        masks,
    })
}

/// The fold's state of `n` Gaussians of width `dim`, its view count left to the caller.
fn read_fold(r: &mut HashReader, n: u64, dim: u64) -> Result<FoldState<'static>> {
    let keep = r.u64()?;
    let min_total_weight = f64::from_le_bytes(r.take()?);
    let keeps_codebook = r.flag()?;
    let atoms = r.u64()?;
    if !(1..=255).contains(&keep) || dim > u32::MAX as u64 || atoms > u32::MAX as u64 {
        return Err(r.corrupt("a fold's parameters out of range"));
    }
    let den = r.array(n, f64::from_le_bytes)?;
    let kept = r.array(n * keep, pair_of)?;
    let n_kept = r.array(n, |b: [u8; 1]| b[0])?;
    let codebook_len = if keeps_codebook { atoms * dim } else { 0 };
    let codebook = r.array(codebook_len, f32::from_le_bytes)?;
    Ok(FoldState {
        dim: dim as usize,
        keep: keep as usize,
        min_total_weight,
        keeps_codebook,
        atoms: atoms as usize,
        next: 0,
        den: Cow::Owned(den),
        kept: Cow::Owned(kept),
        n_kept: Cow::Owned(n_kept),
        codebook: Cow::Owned(codebook),
    })
}

/// The masks' record of `n` Gaussians.
fn read_record(r: &mut HashReader, n: u64) -> Result<MaskRecord> {
    let slots = r.u64()?;
    let view_count = r.u64()?;
    if !(1..=64).contains(&slots) {
        return Err(r.corrupt("a masks' record's slots out of range"));
    }
    let views = r.array(n * slots, u16::from_le_bytes)?;
    let masks = r.array(n * slots, u16::from_le_bytes)?;
    let weights = r.array(n * slots, f32::from_le_bytes)?;
    Ok(MaskRecord {
        slots: slots as usize,
        view_count: view_count as usize,
        views,
        masks,
        weights,
    })
}
