//! Every image's `a_kj` kept until the reduction: in memory up to a budget, spilled to raw
//! little-endian files beyond it.

use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use slag_common::{Error, Result};

use super::*;

/// Holds image contributions until the reduction, in memory up to a budget and spilled to files
/// in `spill_dir` beyond it (little-endian raw records), so scenes of any size complete.
pub struct ContributionStore {
    budget_bytes: usize,
    used_bytes: usize,
    pub(super) in_memory: Vec<ImageContribution>,
    spilled: Vec<PathBuf>,
    spill_dir: PathBuf,
}

impl ContributionStore {
    /// A store keeping up to `budget_bytes` in memory, spilling the rest into `spill_dir`
    /// (created on first spill; its files are removed when the store is dropped).
    pub fn new(budget_bytes: usize, spill_dir: PathBuf) -> Self {
        Self {
            budget_bytes,
            used_bytes: 0,
            in_memory: Vec::new(),
            spilled: Vec::new(),
            spill_dir,
        }
    }

    /// Number of contributions held.
    pub fn len(&self) -> usize {
        self.in_memory.len() + self.spilled.len()
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
        self.in_memory.iter().map(|c| c.entries.len()).sum()
    }

    /// Adds one image's contribution.
    pub fn push(&mut self, c: ImageContribution) -> Result<()> {
        if self.used_bytes + c.bytes() <= self.budget_bytes {
            self.used_bytes += c.bytes();
            self.in_memory.push(c);
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
        put(c.entries.len() as u64).map_err(io)?;
        for v in &c.mask_embeddings {
            f.write_all(&v.to_le_bytes()).map_err(io)?;
        }
        for e in &c.entries {
            f.write_all(&e.gaussian.to_le_bytes()).map_err(io)?;
            f.write_all(&e.mask.to_le_bytes()).map_err(io)?;
            f.write_all(&e.weight.to_le_bytes()).map_err(io)?;
        }
        f.flush().map_err(io)?;
        self.spilled.push(path);
        Ok(())
    }

    fn read_spilled(path: &Path) -> Result<ImageContribution> {
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
        let entries = buf
            .chunks_exact(12)
            .map(|c| Entry {
                gaussian: u(&c[0..4]),
                mask: u(&c[4..8]),
                weight: f32::from_bits(u(&c[8..12])),
            })
            .collect();
        Ok(ImageContribution {
            dim,
            mask_embeddings,
            entries,
        })
    }

    /// Calls `f` on every contribution (spilled ones are read back one at a time).
    pub fn for_each(&self, mut f: impl FnMut(&ImageContribution)) -> Result<()> {
        self.in_memory.iter().for_each(&mut f);
        for p in &self.spilled {
            f(&Self::read_spilled(p)?);
        }
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
        for p in &self.spilled {
            let _ = std::fs::remove_file(p);
        }
        let _ = std::fs::remove_dir(&self.spill_dir);
    }
}
