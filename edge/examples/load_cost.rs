//! The cost of hashing a signed generation's tiles on load: loads a scene of an edge store
//! without trusted keys (CRC-32s and decoding only) and with them (every tile's SHA-256 beside
//! its decoding, `Engine::load_trusting`), alternating, and prints each wall time.
//!
//!     cargo run -p slag-edge --example load_cost -- STORE SCENE PUBLIC_KEY.pem [ROUNDS]
#![allow(clippy::unwrap_used)]

use std::time::Instant;

use slag_common::shards::signature::{TrustedKey, TrustedKeys};
use slag_edge::engine::Engine;
use slag_edge::store::EdgeStore;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let [_, store, scene, key, ..] = &args[..] else {
        eprintln!("usage: load_cost STORE SCENE PUBLIC_KEY.pem [ROUNDS]");
        std::process::exit(2);
    };
    let rounds: usize = args.get(4).map_or(3, |r| r.parse().unwrap());
    let edge = EdgeStore::open(std::path::Path::new(store)).unwrap();
    let keys = TrustedKeys::from(TrustedKey::read_pem(std::path::Path::new(key)).unwrap());
    for round in 0..rounds {
        for trusted in [None, Some(&keys)] {
            let t = Instant::now();
            let e = Engine::load_trusting(&edge, scene, None, trusted).unwrap();
            println!(
                "round {round} {}: {:.3} s, {} tiles loaded, {} hashed, {} rows",
                if trusted.is_some() {
                    "hashed"
                } else {
                    "crc-only"
                },
                t.elapsed().as_secs_f64(),
                e.load.loaded_tiles.len(),
                e.load.hashed,
                e.store.len()
            );
        }
    }
}
