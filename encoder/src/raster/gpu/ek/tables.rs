//! A kept view's label table on the device: the masks of each label and each mask's factor,
//! in one run of words that `ek.wgsl` reads, and back again on the host.

use slag_common::{Error, Result};

use crate::raster::KeptMasks;

/// Appends one view's label table to `tables` and returns its base: `[n_labels, factors
/// offset, n_labels + 1 mask offsets, the masks of every label, one f32 factor (bits) per
/// mask]`, offsets relative to the base. Without factors every mask's is 1.
pub(super) fn push_table(
    tables: &mut Vec<u32>,
    masks: &KeptMasks<'_>,
    n_masks: usize,
) -> Result<u32> {
    let too_big = || Error::Invalid("the kept label tables exceed 2^32 words".into());
    let base = u32::try_from(tables.len()).map_err(|_| too_big())?;
    let n_labels = masks.masks_of.len();
    let header = 2 + n_labels + 1;
    let n_entries: usize = masks.masks_of.iter().map(Vec::len).sum();
    let factors_at = header + n_entries;
    let mut table = Vec::with_capacity(factors_at + n_masks);
    table.extend([n_labels as u32, factors_at as u32]);
    let mut at = header;
    for set in masks.masks_of {
        table.push(at as u32);
        at += set.len();
    }
    table.push(at as u32);
    for set in masks.masks_of {
        table.extend_from_slice(set);
    }
    for j in 0..n_masks {
        let f = masks.factors.get(j).copied().unwrap_or(1.0);
        table.push(f.to_bits());
    }
    tables.extend_from_slice(&table);
    u32::try_from(tables.len()).map_err(|_| too_big())?;
    Ok(base)
}

/// The masks of each label and each mask's factor from a view's label table ([`push_table`]'s
/// layout, `table` starting at its base).
///
/// Errors: a table that is not of that layout ([`Error::Internal`]).
pub(super) fn table_masks(table: &[u32]) -> Result<(Vec<Vec<u32>>, Vec<f32>)> {
    let bad = || Error::internal(format!("a kept label table of {} words", table.len()));
    let (&n_labels, &factors_at) = (
        table.first().ok_or_else(bad)?,
        table.get(1).ok_or_else(bad)?,
    );
    let offsets = table.get(2..3 + n_labels as usize).ok_or_else(bad)?;
    let masks_of = offsets
        .windows(2)
        .map(|w| table.get(w[0] as usize..w[1] as usize).map(<[u32]>::to_vec))
        .collect::<Option<Vec<_>>>()
        .ok_or_else(bad)?;
    let factors = table.get(factors_at as usize..).ok_or_else(bad)?;
    Ok((
        masks_of,
        factors.iter().map(|&b| f32::from_bits(b)).collect(),
    ))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn a_label_table_reads_back_as_written() {
        let masks_of = vec![vec![], vec![0, 2], vec![1]];
        let factors = [0.5f32, 2.0, 1.25];
        let embeddings = [0.0f32; 6];
        let mut tables = vec![7, 7, 7];
        for (f, n) in [(&factors[..], 3), (&[][..], 3)] {
            let masks = KeptMasks {
                masks_of: &masks_of,
                factors: f,
                embeddings: &embeddings,
                dominant: false,
                view: 0,
            };
            let base = push_table(&mut tables, &masks, n).unwrap() as usize;
            let (m, got) = table_masks(&tables[base..]).unwrap();
            assert_eq!(m, masks_of);
            // Without factors every mask's is 1.
            let want = if f.is_empty() {
                vec![1.0; 3]
            } else {
                f.to_vec()
            };
            assert_eq!(got, want);
            tables.truncate(base + 2);
            assert!(table_masks(&tables[base..]).is_err(), "a cut table");
        }
    }
}
