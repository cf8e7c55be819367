//! Shard decoder: `decode_header`, `decode_shard`, `decode_shard_stored` on arbitrary bytes; when
//! one succeeds the others agree with it.
#![no_main]

use libfuzzer_sys::fuzz_target;
use slag_common::shards::{decode_header, decode_shard, decode_shard_stored};

fuzz_target!(|data: &[u8]| {
    let h = decode_header(data);
    let full = decode_shard(data);
    let stored = decode_shard_stored(data);
    assert_eq!(full.is_ok(), stored.is_ok());
    if let (Ok(f), Ok(s)) = (&full, &stored) {
        assert!(h.is_ok(), "a shard that decodes has a header that decodes");
        let n = f.ids.len();
        assert_eq!(s.ids.len(), n);
        assert_eq!(f.means.len(), n);
        assert_eq!(s.vectors.values(), n * f.header.dim as usize);
    }
});
