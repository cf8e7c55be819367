//! The cost of hashing a signed generation's tiles on load: loads a scene of an edge store
//! without trusted keys (CRC-32s and decoding only) and with them (every tile's SHA-256 checked
//! before its decoding, `Engine::load_trusting`), alternating, and prints each load's wall time
//! and the CPU time the process spent on it (user + system, all threads: on a machine shared
//! with other work the steadier figure), then the medians of both.
//!
//!     cargo run -p slag-edge --example load_cost -- STORE SCENE PUBLIC_KEY.pem [ROUNDS]
#![allow(clippy::unwrap_used)]

use std::time::Instant;

use slag_common::shards::signature::{TrustedKey, TrustedKeys};
use slag_edge::engine::Engine;
use slag_edge::store::EdgeStore;

/// CPU seconds (user + system, every thread) this process has used so far: fields 14 and 15 of
/// `/proc/self/stat`, in USER_HZ ticks (100 per second on Linux).
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap();
    // The command name (field 2) may hold spaces: count the fields after its closing ')'.
    let after = &stat[stat.rfind(')').unwrap() + 2..];
    let f: Vec<&str> = after.split(' ').collect();
    let ticks: u64 = f[11].parse::<u64>().unwrap() + f[12].parse::<u64>().unwrap();
    ticks as f64 / 100.0
}

/// The median of `v` (sorted in place).
fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let [_, store, scene, key, ..] = &args[..] else {
        eprintln!("usage: load_cost STORE SCENE PUBLIC_KEY.pem [ROUNDS]");
        std::process::exit(2);
    };
    let rounds: usize = args.get(4).map_or(3, |r| r.parse().unwrap());
    let edge = EdgeStore::open(std::path::Path::new(store)).unwrap();
    let keys = TrustedKeys::from(TrustedKey::read_pem(std::path::Path::new(key)).unwrap());
    // [crc-only, hashed] × (wall, cpu)
    let mut figures = [[Vec::new(), Vec::new()], [Vec::new(), Vec::new()]];
    // Wall seconds until a server with the key answers (`Engine::pending`).
    let mut answering = Vec::new();
    for round in 0..rounds {
        for (k, trusted) in [None, Some(&keys)].into_iter().enumerate() {
            if trusted.is_some() {
                let t = Instant::now();
                let p = Engine::pending(&edge, scene, trusted).unwrap().unwrap();
                answering.push(t.elapsed().as_secs_f64());
                println!(
                    "round {round} answering: {:.4} s wall, {} tiles pending",
                    answering[round], p.load.pending_verification
                );
            }
            let (t, cpu) = (Instant::now(), cpu_seconds());
            let e = Engine::load_trusting(&edge, scene, None, trusted).unwrap();
            let (wall, cpu) = (t.elapsed().as_secs_f64(), cpu_seconds() - cpu);
            println!(
                "round {round} {}: {wall:.3} s wall, {cpu:.3} s CPU, {} tiles loaded, {} \
                 hashed, {} rows",
                ["crc-only", "hashed"][k],
                e.load.loaded_tiles.len(),
                e.load.hashed,
                e.store.len()
            );
            figures[k][0].push(wall);
            figures[k][1].push(cpu);
        }
    }
    let [[mut w0, mut c0], [mut w1, mut c1]] = figures;
    let (w0, c0, w1, c1) = (
        median(&mut w0),
        median(&mut c0),
        median(&mut w1),
        median(&mut c1),
    );
    let a = median(&mut answering);
    println!(
        "median of {rounds}: crc-only {w0:.3} s wall, {c0:.3} s CPU; hashed {w1:.3} s wall \
         ({:+.1} %), {c1:.3} s CPU ({:+.1} %); with the key answering after {a:.4} s wall \
         ({:+.1} % of crc-only), every tile verified in the background after the hashed load",
        (w1 / w0 - 1.0) * 100.0,
        (c1 / c0 - 1.0) * 100.0,
        (a / w0 - 1.0) * 100.0
    );
}
