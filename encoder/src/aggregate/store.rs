//! Every image's `a_kj` kept until the reduction: in memory up to a budget, as columns with the
//! narrowest mask index that fits ([`StoredImage`]), spilled to raw little-endian files beyond it.

use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use slag_common::{Error, Result};

use super::*;

/// One image's contribution as the store holds it: the [`ImageContribution`]'s entries split into
/// columns, the mask indices in the narrowest unsigned type that holds the image's mask count
/// (one byte up to 256 masks), so that an `a_kj` takes 9 to 12 bytes instead of
/// [`Entry`]'s 12. Same values, same (Gaussian, mask) order.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredImage {
    /// Embedding width D.
    pub dim: usize,
    /// `[M * D]` mask embeddings `E_j`.
    pub mask_embeddings: Vec<f32>,
    /// `[E]` Gaussian index of each `a_kj`, ascending.
    pub gaussians: Vec<u32>,
    /// `[E]` mask index of each `a_kj` within the image.
    pub masks: MaskColumn,
    /// `[E]` the `a_kj`.
    pub weights: Vec<f32>,
}

/// The mask indices of a [`StoredImage`], in the narrowest type that holds the largest.
#[derive(Debug, Clone, PartialEq)]
pub enum MaskColumn {
    /// Every index below 256.
    U8(Vec<u8>),
    /// Every index below 65,536.
    U16(Vec<u16>),
    /// Any index.
    U32(Vec<u32>),
}

impl MaskColumn {
    /// The indices of `entries`, in the narrowest type that holds `most`, their largest.
    fn of(entries: &[Entry], most: u32) -> Self {
        if most <= u8::MAX as u32 {
            MaskColumn::U8(entries.iter().map(|e| e.mask as u8).collect())
        } else if most <= u16::MAX as u32 {
            MaskColumn::U16(entries.iter().map(|e| e.mask as u16).collect())
        } else {
            MaskColumn::U32(entries.iter().map(|e| e.mask).collect())
        }
    }

    /// Bytes of one index.
    fn width(&self) -> usize {
        match self {
            MaskColumn::U8(_) => 1,
            MaskColumn::U16(_) => 2,
            MaskColumn::U32(_) => 4,
        }
    }
}

impl StoredImage {
    /// The columns of `c` (its entries are freed), in two sequential passes over the entries. (A
    /// rayon split of these passes cost the image thread about 70 ms per image with 8 CPU SAM
    /// fronts on the host's cores, on an H100 machine with 16 cores.)
    pub fn from_contribution(c: ImageContribution) -> Self {
        let ImageContribution {
            dim,
            mask_embeddings,
            entries,
        } = c;
        let mut gaussians = Vec::with_capacity(entries.len());
        let mut weights = Vec::with_capacity(entries.len());
        let mut most = 0u32;
        for e in &entries {
            gaussians.push(e.gaussian);
            weights.push(e.weight);
            most = most.max(e.mask);
        }
        let masks = MaskColumn::of(&entries, most);
        StoredImage {
            dim,
            mask_embeddings,
            gaussians,
            masks,
            weights,
        }
    }

    /// Number of `a_kj` held.
    pub fn len(&self) -> usize {
        self.gaussians.len()
    }

    /// True when the image has no `a_kj`.
    pub fn is_empty(&self) -> bool {
        self.gaussians.is_empty()
    }

    /// Entry `i` (`i < len()`), as the image stage made it.
    #[inline]
    pub fn entry(&self, i: usize) -> Entry {
        let mask = match &self.masks {
            MaskColumn::U8(m) => m[i] as u32,
            MaskColumn::U16(m) => m[i] as u32,
            MaskColumn::U32(m) => m[i],
        };
        Entry {
            gaussian: self.gaussians[i],
            mask,
            weight: self.weights[i],
        }
    }

    /// Bytes of the [`ImageContribution`] it was made from ([`ImageContribution::bytes`]: 12 an
    /// `a_kj`), what the store's budget counts.
    pub fn arrival_bytes(&self) -> usize {
        self.mask_embeddings.len() * 4 + self.len() * std::mem::size_of::<Entry>()
    }

    /// Bytes held in memory: the mask embeddings and `4 + 4 + (1, 2 or 4)` bytes an `a_kj`.
    pub fn bytes(&self) -> usize {
        self.mask_embeddings.len() * 4 + self.len() * (8 + self.masks.width())
    }
}

/// Holds image contributions until the reduction, in memory up to a budget and spilled to files
/// in `spill_dir` beyond it (little-endian raw records), so scenes of any size complete.
///
/// The budget counts each image as [`ImageContribution::bytes`] (12 bytes an `a_kj`), the size it
/// arrives in; in memory it is held as a [`StoredImage`] (9 bytes an `a_kj` with at most 256 masks
/// an image), so the memory held stays below the budget. Which images spill depends on that count
/// and on the order they arrive in; the reduction visits them by view index whatever the order
/// ([`Self::push_stored_as`]), so that the same encode gives the same sums in the same order.
pub struct ContributionStore {
    budget_bytes: usize,
    used_bytes: usize,
    /// The images held in memory, by view index (ties in push order).
    pub(super) in_memory: Vec<StoredImage>,
    /// `[in_memory.len()]` the view index of each, ascending.
    memory_views: Vec<usize>,
    /// The spilled images' view indices and files, by view index (ties in push order).
    spilled: Vec<(usize, PathBuf)>,
    spill_dir: PathBuf,
    /// When set, every view is folded into the mixture's running state instead of kept
    /// ([`Self::folding`]).
    fold: Option<Box<MixtureFold>>,
    /// When set, every view is folded into the dense accumulators instead of kept
    /// ([`Self::folding_dense`]).
    dense: Option<Box<DenseFold>>,
}

impl ContributionStore {
    /// A store keeping up to `budget_bytes` in memory, spilling the rest into `spill_dir`
    /// (created on first spill; its files are removed when the store is dropped).
    pub fn new(budget_bytes: usize, spill_dir: PathBuf) -> Self {
        Self {
            budget_bytes,
            used_bytes: 0,
            in_memory: Vec::new(),
            memory_views: Vec::new(),
            spilled: Vec::new(),
            spill_dir,
            fold: None,
            dense: None,
        }
    }

    /// A store that keeps no view: each pushed view is folded into `fold` once every view
    /// before it is in ([`MixtureFold::push`]), so that the host's memory stays flat however
    /// many views come. For an encode that writes only the mixture; [`Self::take_fold`] hands
    /// the state to the reduction, and [`Self::for_each`] refuses.
    pub fn folding(fold: MixtureFold) -> Self {
        let mut store = Self::new(0, PathBuf::new());
        store.fold = Some(Box::new(fold));
        store
    }

    /// The fold of a [`Self::folding`] store (`None` otherwise, or once taken); the store then
    /// holds nothing.
    pub fn take_fold(&mut self) -> Option<MixtureFold> {
        self.fold.take().map(|f| *f)
    }

    /// A store that keeps no view: each pushed view is folded into the dense accumulators of
    /// `fold` once every view before it is in ([`DenseFold::push`]), so that the host's memory
    /// stays flat however many views come. For an encode that writes the dense file;
    /// [`Self::take_dense_fold`] hands the fold to the reduction, and [`Self::for_each`]
    /// refuses.
    pub fn folding_dense(fold: DenseFold) -> Self {
        let mut store = Self::new(0, PathBuf::new());
        store.dense = Some(Box::new(fold));
        store
    }

    /// The fold of a [`Self::folding_dense`] store (`None` otherwise, or once taken); the store
    /// then holds nothing.
    pub fn take_dense_fold(&mut self) -> Option<DenseFold> {
        self.dense.take().map(|f| *f)
    }

    /// Whether views pushed here are folded ([`Self::folding`], [`Self::folding_dense`]).
    pub fn is_folding(&self) -> bool {
        self.fold.is_some() || self.dense.is_some()
    }

    /// Number of contributions held.
    pub fn len(&self) -> usize {
        self.in_memory.len()
            + self.spilled.len()
            + self.fold.as_ref().map_or(0, |f| f.len())
            + self.dense.as_ref().map_or(0, |f| f.len())
    }
    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Contributions written to disk so far.
    pub fn spilled(&self) -> usize {
        self.spilled.len()
    }
    /// Total `a_kj` entries held in memory.
    pub fn entries_in_memory(&self) -> usize {
        self.in_memory.iter().map(StoredImage::len).sum()
    }

    /// Bytes the in-memory contributions hold ([`StoredImage::bytes`]).
    pub fn bytes_in_memory(&self) -> usize {
        self.in_memory.iter().map(StoredImage::bytes).sum()
    }

    /// Adds one image's contribution after every image so far: kept in memory as a
    /// [`StoredImage`] while the budget (counted at [`ImageContribution::bytes`]) allows, else
    /// written to a spill file.
    ///
    /// Errors: I/O writing the spill file.
    pub fn push(&mut self, c: ImageContribution) -> Result<()> {
        self.push_stored_as(self.len(), StoredImage::from_contribution(c))
    }

    /// [`Self::push`] of a contribution already in the store's columns
    /// ([`StoredImage::from_contribution`], made by the caller outside any lock around the store).
    /// The budget counts it at its [`ImageContribution::bytes`] ([`StoredImage::arrival_bytes`]).
    ///
    /// Errors: I/O writing the spill file.
    pub fn push_stored(&mut self, c: StoredImage) -> Result<()> {
        self.push_stored_as(self.len(), c)
    }

    /// [`Self::push_stored`] of the image `view` (its index in the encode's view list): the
    /// reduction visits the images by `view` ([`Self::for_each`]), not in the order they
    /// arrived, so views finished in any order give the same codebook, the same ties and the
    /// same sums. Images of equal `view` keep their push order.
    ///
    /// A [`Self::folding`] store folds it instead ([`MixtureFold::push`]), a
    /// [`Self::folding_dense`] one into its accumulators ([`DenseFold::push`]).
    ///
    /// Errors: I/O writing the spill file; the fold's.
    pub fn push_stored_as(&mut self, view: usize, c: StoredImage) -> Result<()> {
        if let Some(fold) = &mut self.fold {
            return fold.push(view, c);
        }
        if let Some(dense) = &mut self.dense {
            return dense.push(view, c);
        }
        if self.used_bytes + c.arrival_bytes() <= self.budget_bytes {
            self.used_bytes += c.arrival_bytes();
            let at = self.memory_views.partition_point(|&v| v <= view);
            self.memory_views.insert(at, view);
            self.in_memory.insert(at, c);
            return Ok(());
        }
        std::fs::create_dir_all(&self.spill_dir).map_err(|e| Error::io(&self.spill_dir, e))?;
        let path = self
            .spill_dir
            .join(format!("contribution-{:06}.bin", self.spilled.len()));
        let io = |e| Error::io(&path, e);
        let mut f = BufWriter::new(std::fs::File::create(&path).map_err(io)?);
        let mut put = |v: u64| f.write_all(&v.to_le_bytes());
        put(c.dim as u64).map_err(io)?;
        put(c.mask_embeddings.len() as u64).map_err(io)?;
        put(c.len() as u64).map_err(io)?;
        for v in &c.mask_embeddings {
            f.write_all(&v.to_le_bytes()).map_err(io)?;
        }
        for e in (0..c.len()).map(|i| c.entry(i)) {
            f.write_all(&e.gaussian.to_le_bytes()).map_err(io)?;
            f.write_all(&e.mask.to_le_bytes()).map_err(io)?;
            f.write_all(&e.weight.to_le_bytes()).map_err(io)?;
        }
        f.flush().map_err(io)?;
        let at = self.spilled.partition_point(|(v, _)| *v <= view);
        self.spilled.insert(at, (view, path));
        Ok(())
    }

    fn read_spilled(path: &Path) -> Result<StoredImage> {
        let io = |e| Error::io(path, e);
        let mut r = BufReader::new(std::fs::File::open(path).map_err(io)?);
        let mut b8 = [0u8; 8];
        let mut get = |r: &mut BufReader<std::fs::File>| -> Result<u64> {
            r.read_exact(&mut b8).map_err(io)?;
            Ok(u64::from_le_bytes(b8))
        };
        let (dim, ne, nn) = (
            get(&mut r)? as usize,
            get(&mut r)? as usize,
            get(&mut r)? as usize,
        );
        let mut buf = vec![0u8; ne * 4];
        r.read_exact(&mut buf).map_err(io)?;
        let mask_embeddings = buf
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let mut buf = vec![0u8; nn * 12];
        r.read_exact(&mut buf).map_err(io)?;
        let u = |c: &[u8]| u32::from_le_bytes([c[0], c[1], c[2], c[3]]);
        let entries: Vec<Entry> = buf
            .chunks_exact(12)
            .map(|c| Entry {
                gaussian: u(&c[0..4]),
                mask: u(&c[4..8]),
                weight: f32::from_bits(u(&c[8..12])),
            })
            .collect();
        drop(buf);
        Ok(StoredImage::from_contribution(ImageContribution {
            dim,
            mask_embeddings,
            entries,
        }))
    }

    /// Calls `f` on every contribution by view index ([`Self::push_stored_as`]), the in-memory
    /// ones and the spilled ones (read back one at a time) merged; of equal view index, the
    /// in-memory ones first, each side in push order.
    ///
    /// Errors: I/O reading a spill file; [`Error::Internal`] for a [`Self::folding`] store,
    /// which keeps no view.
    pub fn for_each(&self, mut f: impl FnMut(&StoredImage)) -> Result<()> {
        if self.is_folding() {
            return Err(Error::internal(
                "the views were folded into the mixture: no reduction can read them again",
            ));
        }
        let mut memory = self.memory_views.iter().zip(&self.in_memory).peekable();
        for (view, path) in &self.spilled {
            while let Some((_, c)) = memory.next_if(|(v, _)| *v <= view) {
                f(c);
            }
            f(&Self::read_spilled(path)?);
        }
        memory.for_each(|(_, c)| f(c));
        Ok(())
    }
}

#[cfg(test)]
impl ContributionStore {
    /// Test shorthand: a store with no memory limit holding `images` in order (nothing spills).
    #[allow(clippy::unwrap_used)] // an unlimited store never spills, so never fails to push
    pub(crate) fn in_memory(images: impl IntoIterator<Item = ImageContribution>) -> Self {
        let mut store = Self::new(usize::MAX, std::env::temp_dir().join("unused"));
        for c in images {
            store.push(c).unwrap();
        }
        store
    }
}

impl Drop for ContributionStore {
    fn drop(&mut self) {
        for (_, p) in &self.spilled {
            let _ = std::fs::remove_file(p);
        }
        let _ = std::fs::remove_dir(&self.spill_dir);
    }
}
