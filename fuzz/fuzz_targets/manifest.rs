//! Partition manifest: `Manifest::from_json`, then `tile_index` + `select_tiles` at a centre and
//! radius taken from the input's last 17 bytes. Selected ids must be tiles of the manifest.
#![no_main]

use libfuzzer_sys::fuzz_target;
use slag_common::shards::Manifest;

fuzz_target!(|data: &[u8]| {
    let (json, tail) = data.split_at(data.len().saturating_sub(17));
    let Ok(m) = Manifest::from_json(json, "fuzz") else {
        return;
    };
    let idx = m.tile_index();
    let f = |i: usize| {
        let mut b = [0u8; 8];
        for (k, x) in b.iter_mut().enumerate() {
            *x = tail.get(i * 8 + k).copied().unwrap_or(0);
        }
        f64::from_le_bytes(b)
    };
    let (c, r) = ([f(0), f(1)], tail.get(16).map_or(1.0, |&b| b as f64));
    for id in idx.select_tiles(c, r) {
        assert!(
            m.tiles.iter().any(|t| t.id == id),
            "selected unknown tile {id}"
        );
    }
    let _ = m.to_json();
});
