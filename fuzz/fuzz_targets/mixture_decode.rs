//! Mixture shards and codebooks (format version 2, `slag_common::shards::mixture`):
//! `decode_mixture_shard` and `decode_codebook` on arbitrary bytes never panic, and agree with
//! the header and dense decoders: a mixture shard that decodes has a header that decodes, is
//! refused by the dense decoder as `MixtureRows`, and has consistent lengths; a codebook is a
//! dense f16 shard.
#![no_main]

use libfuzzer_sys::fuzz_target;
use slag_common::shards::{
    ShardError, decode_codebook, decode_header, decode_mixture_shard, decode_shard_stored,
};

fuzz_target!(|data: &[u8]| {
    if let Ok(m) = decode_mixture_shard(data) {
        let h = decode_header(data).expect("a mixture shard that decodes has a header");
        assert_eq!(h, m.header);
        let n = m.ids.len();
        assert_eq!(m.means.len(), n);
        assert_eq!(m.atoms.len(), n * m.slots as usize);
        assert_eq!(m.weights.len(), m.atoms.len());
        assert!(m.weights.iter().all(|w| w.is_finite()));
        assert_eq!(
            decode_shard_stored(data).err(),
            Some(ShardError::MixtureRows {
                tile_id: m.header.tile_id
            })
        );
    }
    if let Ok(c) = decode_codebook(data) {
        assert!(decode_shard_stored(data).is_ok());
        assert_eq!(c.rows.len(), c.len() * c.dim);
        assert!(c.rows.iter().all(|v| v.is_finite()));
    }
});
