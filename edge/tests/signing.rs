//! Signed manifests end to end on loopback: a fetch with a trusted key refuses a tile rewritten
//! with its CRC-32 made consistent, a rewritten manifest, a manifest signed by another key, an
//! unsigned one, an older signed generation and a tile swapped in from another scene, each with
//! its typed error; the store keeps its last good generation and `serve` keeps answering from it
//! (`/stats` counts the refusals); `check`'s offline verification finds a stored file changed
//! on disk; a mixture scene's codebook is held to its SHA-256 like a tile.
#![allow(missing_docs, clippy::unwrap_used)]

mod support;

use std::sync::Arc;

use slag_common::shards::signature::{SigningKey, TrustedKey, sha256_hex};
use slag_common::shards::{Dtype, decode_shard};
use slag_common::{Error, Untrusted};
use slag_edge::engine::Verification;
use slag_edge::fetch::{FetchParams, fetch};
use slag_edge::serve::{AppState, ServeOptions};
use slag_edge::store::EdgeStore;
use support::{
    BasisEmbedder, ServerState, TestScene, grid_fetch_params, grid_scene, send_json,
    serve_on_loopback, shard_server, temp_store,
};

/// Gaussians per tile and embedding width of the grid scenes here.
const PER_TILE: usize = 10;
const DIM: usize = 8;

/// Scene `id` (3×3 tiles), generation `generation`.
fn scene(id: &str, generation: u64) -> TestScene {
    grid_scene(id, 3, 3, PER_TILE, DIM, Dtype::F16, generation)
}

/// Puts `scene` on the server with `key`'s signature of the manifest bytes it serves (none
/// with `None`).
fn publish(state: &ServerState, scene: TestScene, key: Option<&SigningKey>) {
    let sig = key.map(|k| k.sign(&scene.manifest.to_json()).to_json());
    *state.scene.write().unwrap() = scene;
    *state.signature.write().unwrap() = sig;
}

/// Recomputes a dense shard's payload and header CRC-32s (format module doc: payload CRC at
/// offset 64, header CRC in the header's last 4 bytes).
fn fix_inner_crcs(b: &mut [u8]) {
    let hl = u32::from_le_bytes(b[20..24].try_into().unwrap()) as usize;
    let payload = crc32fast::hash(&b[hl..]);
    b[64..68].copy_from_slice(&payload.to_le_bytes());
    let header = crc32fast::hash(&b[..hl - 4]);
    b[hl - 4..hl].copy_from_slice(&header.to_le_bytes());
}

/// Flips bits among those of the bytes at `free` so that the whole file's CRC-32 (after
/// [`fix_inner_crcs`]) is `target`: CRC-32 is affine over GF(2), so is the whole map, and 64
/// free bits solve its 32 equations.
fn force_crc(b: &mut [u8], free: &[usize], target: u32) {
    let crc_of = |b: &mut [u8]| {
        fix_inner_crcs(b);
        crc32fast::hash(b)
    };
    let base = crc_of(b);
    let bits: Vec<(usize, u8)> = free
        .iter()
        .flat_map(|&i| (0..8).map(move |k| (i, 1u8 << k)))
        .collect();
    // Rows: (effect on the CRC, which bits were combined).
    let mut rows: Vec<(u32, Vec<bool>)> = bits
        .iter()
        .enumerate()
        .map(|(n, &(i, m))| {
            b[i] ^= m;
            let d = crc_of(b) ^ base;
            b[i] ^= m;
            let mut used = vec![false; bits.len()];
            used[n] = true;
            (d, used)
        })
        .collect();
    // Gaussian elimination: one row per pivot bit of the CRC.
    let mut pivots: Vec<(u32, Vec<bool>)> = Vec::new();
    for bit in (0..32).rev() {
        let Some(p) = rows.iter().position(|r| r.0 >> bit & 1 == 1) else {
            continue;
        };
        let pivot = rows.swap_remove(p);
        for r in rows.iter_mut().chain(pivots.iter_mut()) {
            if r.0 >> bit & 1 == 1 {
                r.0 ^= pivot.0;
                r.1.iter_mut().zip(&pivot.1).for_each(|(a, b)| *a ^= b);
            }
        }
        pivots.push(pivot);
    }
    let mut want = base ^ target;
    let mut flip = vec![false; bits.len()];
    for (d, used) in &pivots {
        if want & (1 << (31 - d.leading_zeros())) != 0 {
            want ^= d;
            flip.iter_mut().zip(used).for_each(|(a, b)| *a ^= b);
        }
    }
    assert_eq!(want, 0, "the free bits do not reach every CRC value");
    for (n, &(i, m)) in bits.iter().enumerate() {
        if flip[n] {
            b[i] ^= m;
        }
    }
    assert_eq!(crc_of(b), target);
}

/// Tile 0 of `scene` rewritten: its first Gaussian's embedding replaced (basis direction 5),
/// the low mantissa bytes of its last Gaussian's embedding adjusted so that the shard still
/// decodes with valid inner CRCs and has the whole-file CRC-32 the manifest lists.
fn rewrite_tile(scene: &TestScene) -> Vec<u8> {
    let mut b = scene.shards[&0].clone();
    let hl = u32::from_le_bytes(b[20..24].try_into().unwrap()) as usize;
    // Payload: ids u32[N], means f32[N][3], then the f16 embeddings.
    let emb = hl + 16 * PER_TILE;
    for k in 0..DIM {
        let v = half::f16::from_f32(if k == 5 { 1.0 } else { 0.0 });
        b[emb + 2 * k..emb + 2 * k + 2].copy_from_slice(&v.to_le_bytes());
    }
    let last = emb + 2 * DIM * (PER_TILE - 1);
    let free: Vec<usize> = (0..DIM).map(|k| last + 2 * k).collect();
    let target = u32::from_str_radix(&scene.manifest.tiles[0].checksum, 16).unwrap();
    force_crc(&mut b, &free, target);
    b
}

/// `state` once the background verification of its stored tiles is done (it starts with
/// `AppState::new` under a trusted key; none runs without one).
fn verified(state: AppState) -> AppState {
    let v = state.query_engine().wait_verified();
    assert!(matches!(v, Verification::Done | Verification::Off), "{v:?}");
    state
}

/// A store holding scene "grid" fetched under a trusted key, then tile 0 rewritten on disk with
/// its CRC-32s kept ([`rewrite_tile`]): the store's folder (kept alive), the store and the key.
async fn signed_store_with_a_rewritten_tile() -> (tempfile::TempDir, EdgeStore, TrustedKey) {
    let publisher = SigningKey::generate();
    let trusted = publisher.public();
    let server = shard_server(scene("grid", 1), None).await;
    publish(&server.state, scene("grid", 1), Some(&publisher));
    let (dir, store) = temp_store();
    fetch(&store, &signed_params(&server.url, &trusted))
        .await
        .unwrap();
    std::fs::write(
        support::shard_path(&store, 0),
        rewrite_tile(&scene("grid", 1)),
    )
    .unwrap();
    (dir, store, trusted)
}

/// A fetch of the whole grid from `url` that trusts `key`.
fn signed_params(url: &str, key: &TrustedKey) -> FetchParams {
    FetchParams {
        trusted_keys: Some(key.clone().into()),
        ..grid_fetch_params(url, 100.0)
    }
}

/// The edge under test: its store, and `serve` over it with `key` trusted for `POST /fetch`.
struct Edge {
    store: EdgeStore,
    url: String,
    client: reqwest::Client,
    _dir: tempfile::TempDir,
}

impl Edge {
    async fn start(shards: &str, key: &TrustedKey) -> Edge {
        let (dir, store) = temp_store();
        fetch(&store, &signed_params(shards, key)).await.unwrap();
        let opts = ServeOptions {
            trusted_keys: Some(key.clone().into()),
            ..ServeOptions::new("grid")
        };
        let state = AppState::new(store.clone(), Arc::new(BasisEmbedder::new(DIM)), opts).unwrap();
        let state = verified(state);
        Edge {
            store,
            url: serve_on_loopback(state).await,
            client: reqwest::Client::new(),
            _dir: dir,
        }
    }

    /// `POST /fetch` of the whole grid from `shards`: status and body.
    async fn post_fetch(&self, shards: &str) -> (u16, serde_json::Value) {
        let body = serde_json::json!({"center": [0.0, 0.0], "radius": 100.0, "server": shards});
        send_json(self.client.post(format!("{}/fetch", self.url)).json(&body)).await
    }

    async fn stats(&self) -> serde_json::Value {
        send_json(self.client.get(format!("{}/stats", self.url)))
            .await
            .1
    }

    /// The store's committed generation, and that serve still answers from `generation`.
    async fn assert_serving(&self, generation: u64) {
        let committed = {
            let _g = self.store.lock_generation();
            self.store.committed("grid").unwrap()
        };
        assert_eq!(committed.manifest.generation, generation);
        assert_eq!(committed.tiles().len(), 9);
        let stats = self.stats().await;
        assert_eq!(stats["generation"], generation, "{stats}");
        assert_eq!(stats["shards_loaded"], 9, "{stats}");
        let (status, answer) = send_json(
            self.client
                .get(format!("{}/query?text=t4&top_k=5", self.url)),
        )
        .await;
        assert_eq!(status, 200, "{answer}");
        assert_eq!(
            answer["matches"].as_array().map(Vec::len),
            Some(5),
            "{answer}"
        );
    }

    /// Fetches from `shards` with the library (typed error) and through `POST /fetch`; both
    /// are refused with `what`, and the store keeps serving `generation`. Returns the message.
    async fn refused(
        &self,
        shards: &str,
        key: &TrustedKey,
        what: Untrusted,
        generation: u64,
    ) -> String {
        let e = fetch(&self.store, &signed_params(shards, key))
            .await
            .unwrap_err();
        match &e {
            Error::Untrusted { what: w, .. } => assert_eq!(*w, what, "{e}"),
            other => panic!("expected a {what:?} refusal, got {other}"),
        }
        self.assert_serving(generation).await;
        let before = self.stats().await["fetch_refusals"].as_u64().unwrap();
        let (status, body) = self.post_fetch(shards).await;
        assert_eq!(status, 502, "{body}");
        assert!(
            body["error"].as_str().unwrap().contains(&what.to_string()),
            "{body}"
        );
        let stats = self.stats().await;
        assert_eq!(stats["fetch_refusals"], before + 1, "{stats}");
        assert!(
            stats["last_refusal"].as_str().unwrap().contains("refused"),
            "{stats}"
        );
        self.assert_serving(generation).await;
        e.to_string()
    }
}

/// `e` is [`Error::Untrusted`] for `what`.
fn assert_untrusted(e: &Error, what: Untrusted) {
    assert!(
        matches!(e, Error::Untrusted { what: w, .. } if *w == what),
        "{e}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_trusted_key_refuses_every_tampering_and_the_last_good_generation_keeps_serving() {
    let publisher = SigningKey::generate();
    let trusted = publisher.public();
    let server = shard_server(scene("grid", 1), None).await;
    publish(&server.state, scene("grid", 1), Some(&publisher));
    let edge = Edge::start(&server.url, &trusted).await;
    edge.assert_serving(1).await;
    let mut seen = Vec::new();

    // 1. A tile rewritten, its CRC-32 (and inner CRCs) made consistent: the manifest and its
    // signature are the publisher's; only the SHA-256 tells.
    let good = scene("grid", 2);
    let forged = rewrite_tile(&good);
    assert_ne!(forged, good.shards[&0]);
    decode_shard(&forged).unwrap();
    let t0 = &good.manifest.tiles[0];
    // Without the SHA-256 the rewritten tile passes every check an unsigned fetch makes.
    slag_edge::store::verify_shard(&good.manifest, t0, &forged).unwrap();
    let mut tampered = scene("grid", 2);
    tampered.shards.insert(0, forged.clone());
    publish(&server.state, tampered, Some(&publisher));
    seen.push((
        "rewritten tile (CRC-32 made consistent)",
        edge.refused(&server.url, &trusted, Untrusted::ContentHash, 1)
            .await,
    ));

    // 2. The manifest rewritten to match the rewritten tile, served with the publisher's
    // signature of the original.
    let mut tampered = scene("grid", 2);
    let sig = publisher.sign(&tampered.manifest.to_json()).to_json();
    tampered.manifest.tiles[0].sha256 = Some(sha256_hex(&forged));
    tampered.shards.insert(0, forged.clone());
    publish(&server.state, tampered, None);
    *server.state.signature.write().unwrap() = Some(sig);
    seen.push((
        "rewritten manifest",
        edge.refused(&server.url, &trusted, Untrusted::BadSignature, 1)
            .await,
    ));

    // 3. Signed by another key.
    let other = SigningKey::generate();
    publish(&server.state, scene("grid", 2), Some(&other));
    seen.push((
        "manifest signed by another key",
        edge.refused(&server.url, &trusted, Untrusted::OtherKey, 1)
            .await,
    ));

    // 4. No signature at all.
    publish(&server.state, scene("grid", 2), None);
    seen.push((
        "manifest without signature",
        edge.refused(&server.url, &trusted, Untrusted::Unsigned, 1)
            .await,
    ));

    // 5. A tile of another scene (same publisher, same length) in place of tile 0.
    let elsewhere = scene("grix", 2);
    assert_eq!(elsewhere.shards[&0].len(), good.shards[&0].len());
    let mut swapped = scene("grid", 2);
    swapped.shards.insert(0, elsewhere.shards[&0].clone());
    publish(&server.state, swapped, Some(&publisher));
    seen.push((
        "tile swapped in from another scene",
        edge.refused(&server.url, &trusted, Untrusted::ContentHash, 1)
            .await,
    ));

    // The publisher's generation 2 is accepted...
    publish(&server.state, scene("grid", 2), Some(&publisher));
    let (status, body) = edge.post_fetch(&server.url).await;
    assert_eq!(status, 200, "{body}");
    edge.assert_serving(2).await;
    // ... and kept with its signature: verified again offline, every stored file hashed.
    let check = edge
        .store
        .verify_signed("grid", Some(&trusted.clone().into()))
        .unwrap();
    assert!(
        check.signed && check.verified && check.files_hashed == 9,
        "{check:?}"
    );

    // 6. Generation 1 again, validly signed: a replay.
    publish(&server.state, scene("grid", 1), Some(&publisher));
    seen.push((
        "older signed generation (replay)",
        edge.refused(&server.url, &trusted, Untrusted::Replay, 2)
            .await,
    ));
    assert_eq!(edge.stats().await["fetch_refusals"], 6);
    for (case, message) in &seen {
        println!("{case}: {message}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn check_verifies_the_stored_signature_and_finds_a_file_changed_on_disk() {
    let publisher = SigningKey::generate();
    let trusted = publisher.public();
    let server = shard_server(scene("grid", 1), None).await;
    // Unsigned: fetched without a key, the store says so.
    let (_dir, store) = temp_store();
    fetch(&store, &grid_fetch_params(&server.url, 100.0))
        .await
        .unwrap();
    let check = store
        .verify_signed("grid", Some(&trusted.clone().into()))
        .unwrap();
    assert!(!check.signed && !check.verified, "{check:?}");
    // Signed: verified without a key only as far as naming the key.
    publish(&server.state, scene("grid", 1), Some(&publisher));
    fetch(&store, &signed_params(&server.url, &trusted))
        .await
        .unwrap();
    let check = store.verify_signed("grid", None).unwrap();
    assert_eq!(check.key_id, Some(trusted.key_id()));
    assert!(check.signed && !check.verified, "{check:?}");
    assert_eq!(
        store
            .verify_signed("grid", Some(&trusted.clone().into()))
            .unwrap()
            .files_hashed,
        9
    );
    // Another trusted key: refused.
    let e = store
        .verify_signed("grid", Some(&SigningKey::generate().public().into()))
        .unwrap_err();
    assert_untrusted(&e, Untrusted::OtherKey);
    // A stored shard rewritten in place with its CRC-32 kept: the CRC check passes, the
    // SHA-256 does not.
    let s = scene("grid", 1);
    let path = support::shard_path(&store, 0);
    std::fs::write(&path, rewrite_tile(&s)).unwrap();
    let e = store
        .verify_signed("grid", Some(&trusted.clone().into()))
        .unwrap_err();
    assert_untrusted(&e, Untrusted::ContentHash);
    let m = e.to_string();
    assert!(m.contains("tile 0"), "{m}");
    // Named as the store's file changed after its commit, with what repairs it: a fetch with
    // the key whose disc covers the tile.
    assert!(
        m.contains("changed after its commit") && m.contains("fetch --trusted-key"),
        "{m}"
    );
    // A signed fetch sets the rewritten file aside and downloads the tile again.
    let summary = fetch(&store, &signed_params(&server.url, &trusted))
        .await
        .unwrap();
    assert_eq!((summary.set_aside, summary.downloaded), (1, 1), "{summary}");
    store
        .verify_signed("grid", Some(&trusted.clone().into()))
        .unwrap();
}

/// A mixture scene of 2 tiles × 4 Gaussians, 2 slots each, over a codebook of 4 basis rows
/// (rotated by `generation`, so each generation's codebook has other bytes), signed by `key`:
/// the scene and its codebook file.
fn mixture_scene(generation: u64, key: &SigningKey) -> (TestScene, Vec<u8>, Vec<u8>) {
    use slag_common::shards::{
        MIXTURE_MANIFEST_VERSION, MIXTURE_SHARD_FORMAT_VERSION, MixtureInfo, MixtureShardInput,
        TileInfo, encode_codebook, encode_mixture_shard, shard_checksum,
    };
    let rows: Vec<f32> = (0..4)
        .flat_map(|k| (0..DIM).map(move |d| (d == (k + generation as usize) % DIM) as u8 as f32))
        .collect();
    let codebook = encode_codebook("grid", "color-clip", DIM, &rows).unwrap();
    let crc = shard_checksum(&codebook);
    let mut s = scene("grid", generation);
    s.manifest.tiles.truncate(2);
    s.shards.clear();
    for t in &mut s.manifest.tiles {
        let ids: Vec<u32> = (0..4).map(|i| (t.id * 4 + i) as u32).collect();
        let means: Vec<[f32; 3]> = ids
            .iter()
            .map(|&i| [t.id as f32 * 10.0 + i as f32, 1.0, 0.0])
            .collect();
        let atoms: Vec<u32> = ids.iter().flat_map(|&i| [i % 4, (i + 1) % 4]).collect();
        let weights: Vec<f32> = ids.iter().flat_map(|_| [0.7, 0.3]).collect();
        let bytes = encode_mixture_shard(&MixtureShardInput {
            scene_id: "grid",
            model: "color-clip",
            tile_id: t.id,
            dim: DIM,
            slots: 2,
            codebook_crc: crc,
            ids: &ids,
            means: &means,
            atoms: &atoms,
            weights: &weights,
            ..Default::default()
        })
        .unwrap();
        *t = TileInfo {
            count: 4,
            bytes: bytes.len() as u64,
            checksum: format!("{:08x}", shard_checksum(&bytes)),
            sha256: Some(sha256_hex(&bytes)),
            aabb: slag_common::shards::Aabb::of_points(means.iter().copied()).unwrap(),
            ..t.clone()
        };
        s.shards.insert(t.id, bytes);
    }
    s.manifest.manifest_version = MIXTURE_MANIFEST_VERSION;
    s.manifest.shard_format_version = MIXTURE_SHARD_FORMAT_VERSION;
    s.manifest.total_gaussians = 8;
    s.manifest.mixture = Some(MixtureInfo {
        slots: 2,
        atoms: 4,
        codebook_bytes: codebook.len() as u64,
        codebook_checksum: format!("{crc:08x}"),
        codebook_sha256: Some(sha256_hex(&codebook)),
    });
    let sig = key.sign(&s.manifest.to_json()).to_json();
    (s, codebook, sig)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_mixture_scenes_codebook_is_held_to_its_signed_sha256() {
    let publisher = SigningKey::generate();
    let trusted = publisher.public();
    let server = shard_server(scene("grid", 1), None).await;
    let serve = |(s, codebook, sig): (TestScene, Vec<u8>, Vec<u8>)| {
        *server.state.scene.write().unwrap() = s;
        *server.state.codebook.write().unwrap() = Some(codebook);
        *server.state.signature.write().unwrap() = Some(sig);
    };
    serve(mixture_scene(1, &publisher));
    let (_dir, store) = temp_store();
    fetch(&store, &signed_params(&server.url, &trusted))
        .await
        .unwrap();
    let check = store
        .verify_signed("grid", Some(&trusted.clone().into()))
        .unwrap();
    assert_eq!(
        check.files_hashed, 3,
        "two shards and the codebook: {check:?}"
    );
    // Generation 2 with a byte of its codebook changed on the way.
    let (s, mut codebook, sig) = mixture_scene(2, &publisher);
    let n = codebook.len();
    codebook[n - 3] ^= 0x40;
    serve((s, codebook, sig));
    let e = fetch(&store, &signed_params(&server.url, &trusted))
        .await
        .unwrap_err();
    assert_untrusted(&e, Untrusted::ContentHash);
    assert!(e.to_string().contains("the codebook"), "{e}");
    println!("codebook changed on the way: {e}");
    let committed = {
        let _g = store.lock_generation();
        store.committed("grid").unwrap()
    };
    assert_eq!(committed.manifest.generation, 1);
    store.codebook(&committed.manifest).unwrap();
    // The genuine generation 2 is accepted.
    serve(mixture_scene(2, &publisher));
    fetch(&store, &signed_params(&server.url, &trusted))
        .await
        .unwrap();
    assert_eq!(
        store
            .verify_signed("grid", Some(&trusted.clone().into()))
            .unwrap()
            .files_hashed,
        3
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_command_lines_fetch_with_a_trusted_key_and_check_says_whether_the_store_is_signed() {
    use support::{
        color_clip_text_model, fetch_args, output_blocking, slag_edge_with_log, success_json,
        text_model_args,
    };
    let run = async |args: Vec<&str>| output_blocking(slag_edge_with_log(&args, "warn")).await;
    let dir = tempfile::tempdir().unwrap();
    let keys = slag_common::shards::signature::keygen(&dir.path().join("keys")).unwrap();
    let publisher = SigningKey::read_pem(&keys.private).unwrap();
    let public = keys.public.display().to_string();
    // 512-d so that color-clip's text tower fits the stored embeddings.
    let grid = grid_scene("grid", 2, 2, 5, 512, Dtype::F16, 1);
    let server = shard_server(grid_scene("grid", 2, 2, 5, 512, Dtype::F16, 1), None).await;
    let (signed, unsigned) = (dir.path().join("signed"), dir.path().join("unsigned"));
    let (signed, unsigned) = (signed.display().to_string(), unsigned.display().to_string());

    // Unsigned server: a fetch that trusts the key is refused (error, then hint), one without
    // it is today's fetch.
    let with_key = [
        &fetch_args(&server.url, &signed, "100")[..],
        &["--trusted-key", &public],
    ]
    .concat();
    let out = run(with_key.clone()).await;
    let stderr = String::from_utf8_lossy(&out.stderr);
    let lines: Vec<&str> = stderr.trim().lines().collect();
    assert!(!out.status.success(), "{stderr}");
    assert_eq!(lines.len(), 2, "{stderr}");
    assert!(
        lines[0].starts_with("error: ") && lines[0].contains("refused, no signature"),
        "{stderr}"
    );
    assert!(
        lines[1].starts_with("hint: ") && lines[1].contains("--signing-key"),
        "{stderr}"
    );
    success_json(
        &run([&fetch_args(&server.url, &unsigned, "100")[..], &["--json"]].concat()).await,
    );

    // Signed by the publisher: fetched; another key's signature: refused, naming the flag.
    publish(&server.state, grid, Some(&publisher));
    success_json(&run([&with_key[..], &["--json"]].concat()).await);
    *server.state.signature.write().unwrap() = Some(
        SigningKey::generate()
            .sign(&server.state.scene.read().unwrap().manifest.to_json())
            .to_json(),
    );
    let out = run(with_key.clone()).await;
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("refused, signed by another key"),
        "{stderr}"
    );
    assert!(
        stderr.contains("hint: pass the publisher's public key with --trusted-key"),
        "{stderr}"
    );

    let [tm, tok] = color_clip_text_model();
    if support::skip_without_ort() {
        return;
    }
    let check = |store: &str, key: bool| {
        let mut args = text_model_args("check", store, "grid", [&tm, &tok]);
        if key {
            args.extend(["--trusted-key", public.as_str()]);
        }
        args.into_iter()
            .map(str::to_string)
            .collect::<Vec<String>>()
    };
    let report = |args: Vec<String>| async move {
        let out = run(args.iter().map(String::as_str).collect()).await;
        (
            out.status.success(),
            serde_json::from_slice::<serde_json::Value>(&out.stdout).unwrap(),
        )
    };
    let (ok, r) = report(check(&signed, true)).await;
    assert!(ok, "{r}");
    assert_eq!(r["signature"]["status"], "verified", "{r}");
    assert_eq!(r["signature"]["files_hashed"], 4, "{r}");
    let (ok, r) = report(check(&signed, false)).await;
    assert!(ok, "{r}");
    assert_eq!(r["signature"]["status"], "signed, not verified", "{r}");
    let (ok, r) = report(check(&unsigned, false)).await;
    assert!(ok, "{r}");
    assert_eq!(r["signature"]["status"], "unsigned", "{r}");
    assert!(
        r["signature"]["detail"]
            .as_str()
            .unwrap()
            .starts_with("unsigned"),
        "{r}"
    );
    // A trusted key and an unsigned store: a problem.
    let (ok, r) = report(check(&unsigned, true)).await;
    assert!(!ok, "{r}");
    assert!(r["problems"].to_string().contains("unsigned"), "{r}");
}

/// The centre of tile 8 (the grid's far corner, tile (2, 2)): a disc of radius 1 there selects
/// that tile alone.
const FAR_CORNER: [f64; 2] = [24.5, 24.5];

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_tile_forged_under_an_unsigned_fetch_outside_a_signed_fetchs_disc_is_dropped_never_served()
 {
    use slag_edge::fetch::Center;
    use slag_edge::store::KeptTiles;
    let publisher = SigningKey::generate();
    let trusted = publisher.public();
    // An unsigned fetch of the whole grid while tile 0 is forged on the way (its CRC-32s
    // kept): accepted, as every unsigned fetch would.
    let forged = rewrite_tile(&scene("grid", 1));
    let mut tampered = scene("grid", 1);
    tampered.shards.insert(0, forged.clone());
    let server = shard_server(tampered, None).await;
    let (_dir, store) = temp_store();
    fetch(&store, &grid_fetch_params(&server.url, 100.0))
        .await
        .unwrap();
    assert_eq!(
        std::fs::read(support::shard_path(&store, 0)).unwrap(),
        forged
    );
    let before = slag_edge::engine::Engine::load(&store, "grid", false).unwrap();
    assert!(before.load.loaded_tiles.contains(&0), "{:?}", before.load);

    // The publisher's signed generation, fetched for a disc that does not cover tile 0: every
    // stored tile the generation keeps is hashed, and the forged one is dropped.
    publish(&server.state, scene("grid", 1), Some(&publisher));
    let small = FetchParams {
        center: Center::Ground(FAR_CORNER),
        radius: 1.0,
        ..signed_params(&server.url, &trusted)
    };
    let s = fetch(&store, &small).await.unwrap();
    assert_eq!((s.selected, s.downloaded, s.skipped), (1, 0, 1), "{s:?}");
    let dropped = KeptTiles {
        verified: 8,
        refetched: 0,
        dropped: 1,
    };
    assert_eq!(s.kept, dropped, "{s:?}");
    assert!(s.to_string().contains("1 dropped"), "{s}");
    assert!(!support::shard_path(&store, 0).exists());
    let committed = {
        let _g = store.lock_generation();
        store.committed("grid").unwrap()
    };
    let ids: Vec<u64> = committed.tiles().iter().map(|t| t.id).collect();
    assert_eq!(ids, (1..9).collect::<Vec<u64>>());
    assert_eq!(committed.record.as_ref().unwrap().kept, Some(dropped));

    // `serve` with the key: the forged rows are not answered, and /stats says what the fetch
    // did with the kept tiles and that every served tile was hashed on load.
    let opts = ServeOptions {
        trusted_keys: Some(trusted.clone().into()),
        ..ServeOptions::new("grid")
    };
    let state = AppState::new(store.clone(), Arc::new(BasisEmbedder::new(DIM)), opts).unwrap();
    let url = serve_on_loopback(verified(state)).await;
    let client = reqwest::Client::new();
    let (_, stats) = send_json(client.get(format!("{url}/stats"))).await;
    assert_eq!(stats["shards_loaded"], 8, "{stats}");
    assert_eq!(stats["shards_hashed"], 8, "{stats}");
    assert_eq!(stats["last_fetch"]["kept"]["dropped"], 1, "{stats}");
    assert_eq!(stats["last_fetch"]["kept"]["verified"], 8, "{stats}");
    // The forged Gaussian (id 0) points along basis 5.
    let (status, answer) =
        send_json(client.get(format!("{url}/query?text=t5&top_k=90&threshold=-1"))).await;
    assert_eq!(status, 200, "{answer}");
    assert!(
        !support::match_ids(&answer).contains(&0),
        "the forged row is served: {answer}"
    );

    // Fetching the same disc again finds nothing more to drop.
    let s = fetch(&store, &small).await.unwrap();
    assert_eq!(
        s.kept,
        KeptTiles {
            verified: 8,
            refetched: 0,
            dropped: 0
        }
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_tile_rewritten_on_disk_with_its_crcs_kept_is_not_served_by_a_server_that_trusts_the_key()
{
    let (_dir, store, trusted) = signed_store_with_a_rewritten_tile().await;
    let load = |keys: Option<TrustedKey>| {
        let opts = ServeOptions {
            trusted_keys: keys.map(Into::into),
            ..ServeOptions::new("grid")
        };
        verified(AppState::new(store.clone(), Arc::new(BasisEmbedder::new(DIM)), opts).unwrap())
    };
    // Without the key, the CRC-32s pass: the rewritten tile is served.
    let url = serve_on_loopback(load(None)).await;
    let client = reqwest::Client::new();
    let (_, stats) = send_json(client.get(format!("{url}/stats"))).await;
    assert_eq!(
        (
            stats["shards_loaded"].as_u64(),
            stats["shards_hashed"].as_u64()
        ),
        (Some(9), Some(0)),
        "{stats}"
    );
    // With it, every tile is hashed on load; the rewritten one is rejected, the rest served.
    let url = serve_on_loopback(load(Some(trusted.clone()))).await;
    let (_, stats) = send_json(client.get(format!("{url}/stats"))).await;
    assert_eq!(stats["shards_loaded"], 8, "{stats}");
    assert_eq!(stats["shards_hashed"], 8, "{stats}");
    let rejected = stats["shards_rejected"].to_string();
    assert!(
        rejected.contains("tile 0") && rejected.contains("SHA-256"),
        "{stats}"
    );
    // POST /reload loads the same way.
    let (status, body) = send_json(client.post(format!("{url}/reload"))).await;
    assert_eq!((status, body["shards"].as_u64()), (200, Some(8)), "{body}");
    // A stored manifest whose signature no longer holds is refused as a whole.
    let other = SigningKey::generate().public();
    let e = match AppState::new(
        store.clone(),
        Arc::new(BasisEmbedder::new(DIM)),
        ServeOptions {
            trusted_keys: Some(other.into()),
            ..ServeOptions::new("grid")
        },
    ) {
        Err(e) => e,
        Ok(_) => panic!("loaded a generation the trusted key did not sign"),
    };
    assert_untrusted(&e, Untrusted::OtherKey);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_manifest_failing_a_size_check_under_a_trusted_key_is_a_counted_refusal() {
    let publisher = SigningKey::generate();
    let trusted = publisher.public();
    let server = shard_server(scene("grid", 1), None).await;
    publish(&server.state, scene("grid", 1), Some(&publisher));
    let edge = Edge::start(&server.url, &trusted).await;
    // Edited in transit: tile 0 declares 10^12 bytes; the publisher's signature of the original.
    let mut edited = scene("grid", 2);
    let sig = publisher.sign(&edited.manifest.to_json()).to_json();
    edited.manifest.tiles[0].bytes = 1_000_000_000_000;
    publish(&server.state, edited, None);
    *server.state.signature.write().unwrap() = Some(sig);
    let m = edge
        .refused(&server.url, &trusted, Untrusted::BadSignature, 1)
        .await;
    assert!(m.contains("changed after it was signed"), "{m}");
    // Signed that way by the publisher itself: still a refusal, naming the check and the value.
    let mut signed_bad = scene("grid", 2);
    signed_bad.manifest.tiles[0].bytes = 1_000_000_000_000;
    publish(&server.state, signed_bad, Some(&publisher));
    let m = edge
        .refused(&server.url, &trusted, Untrusted::Malformed, 1)
        .await;
    assert!(m.contains("declares 1000000000000 bytes"), "{m}");
    // The sizes the message gives are how a length is made, never a range holding the value.
    assert!(!m.contains("..="), "{m}");
    assert_eq!(edge.stats().await["fetch_refusals"], 2);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_trusted_keys_accept_either_during_a_rotation_and_refuse_a_third_naming_both() {
    let (old, new) = (SigningKey::generate(), SigningKey::generate());
    let keys =
        slag_common::shards::signature::TrustedKeys::new(vec![old.public(), new.public()]).unwrap();
    let server = shard_server(scene("grid", 1), None).await;
    let (_dir, store) = temp_store();
    let params = FetchParams {
        trusted_keys: Some(keys),
        ..grid_fetch_params(&server.url, 100.0)
    };
    publish(&server.state, scene("grid", 1), Some(&old));
    assert_eq!(fetch(&store, &params).await.unwrap().generation, 1);
    publish(&server.state, scene("grid", 2), Some(&new));
    assert_eq!(fetch(&store, &params).await.unwrap().generation, 2);
    let stranger = SigningKey::generate();
    publish(&server.state, scene("grid", 3), Some(&stranger));
    let e = fetch(&store, &params).await.unwrap_err();
    assert_untrusted(&e, Untrusted::OtherKey);
    let m = e.to_string();
    assert!(
        m.contains(&old.key_id()) && m.contains(&new.key_id()),
        "{m}"
    );
}

/// A server that trusts the key answers at once, and serves its tiles one by one as they pass
/// the verification in the background (released one at a time by a gate, so nothing is timed):
/// every answer while it runs is marked partial with the count of pending tiles, holds exactly
/// the rows of the tiles verified so far and none of a pending one, and `/stats` counts move as
/// tiles pass; once verified, every tile that passed is answered. The first tile, rewritten on
/// disk with its CRC-32s kept, is never served, before, during or after.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tiles_are_served_one_by_one_as_they_pass_verification_and_a_forged_one_never() {
    let (_dir, store, trusted) = signed_store_with_a_rewritten_tile().await;
    let opts = ServeOptions {
        trusted_keys: Some(trusted.clone().into()),
        ..ServeOptions::new("grid")
    };
    let gate = slag_edge::engine::VerifyGate::new();
    let embedder = Arc::new(BasisEmbedder::new(DIM));
    let state = AppState::new_gated(store.clone(), embedder, opts, Some(gate.clone())).unwrap();
    let state = Arc::new(state);
    let engine = slag_edge::engine::QueryEngine::from(state.clone());
    let url = support::serve_shared_on_loopback(state).await;
    let client = reqwest::Client::new();
    let all = format!("{url}/query?text=t5&top_k=90&threshold=-1");

    // Held at the gate: answered at once, partial, no row of the nine pending tiles.
    let (_, stats) = send_json(client.get(format!("{url}/stats"))).await;
    assert_eq!(stats["verification"], "running", "{stats}");
    assert_eq!(stats["tiles_pending_verification"], 9, "{stats}");
    assert_eq!(
        (
            stats["tiles_verified"].as_u64(),
            stats["gaussians"].as_u64()
        ),
        (Some(0), Some(0)),
        "{stats}"
    );
    let (status, answer) = send_json(client.get(&all)).await;
    assert_eq!(status, 200, "{answer}");
    assert_eq!(answer["partial"], true, "{answer}");
    assert_eq!(answer["tiles_pending_verification"], 9, "{answer}");
    assert_eq!(support::match_ids(&answer), Vec::<u32>::new(), "{answer}");
    let ply = client
        .get(format!("{url}/query.ply?text=t5&threshold=-1"))
        .send()
        .await
        .unwrap();
    assert_eq!(ply.status(), 200);
    assert_eq!(ply.headers()["x-slag-tiles-pending-verification"], "9");
    assert_eq!(ply.headers()["x-slag-gaussians"], "0");

    // Tile by tile: tile 0 (forged) is dropped, then tiles 1 and 2 pass. After each, the
    // answer holds exactly the rows of the tiles verified so far (tile k holds ids
    // 10k..10k+9) and none of the pending ones.
    for (handed, verified, dropped) in [(1, 0, 1), (2, 1, 1), (3, 2, 1)] {
        gate.release(1);
        let passed = tokio::task::spawn_blocking({
            let gate = gate.clone();
            move || gate.wait_passed(handed)
        })
        .await
        .unwrap();
        assert_eq!(passed, handed, "the verification ended early");
        let (_, stats) = send_json(client.get(format!("{url}/stats"))).await;
        assert_eq!(stats["verification"], "running", "{stats}");
        assert_eq!(
            (
                stats["tiles_verified"].as_u64(),
                stats["tiles_dropped"].as_u64(),
                stats["tiles_pending_verification"].as_u64(),
                stats["gaussians"].as_u64()
            ),
            (
                Some(verified),
                Some(dropped),
                Some(9 - handed as u64),
                Some(verified * PER_TILE as u64)
            ),
            "{stats}"
        );
        let (status, answer) = send_json(client.get(&all)).await;
        assert_eq!(status, 200, "{answer}");
        assert_eq!(answer["partial"], true, "{answer}");
        assert_eq!(answer["tiles_pending_verification"], 9 - handed, "{answer}");
        let mut ids = support::match_ids(&answer);
        ids.sort_unstable();
        let expected: Vec<u32> =
            (PER_TILE as u32..(1 + verified as u32) * PER_TILE as u32).collect();
        assert_eq!(ids, expected, "tiles 1..={verified} exactly: {answer}");
    }
    gate.open();

    // Verified: the eight good tiles are answered, the forged one is dropped and counted.
    assert_eq!(engine.wait_verified(), Verification::Done);
    let (_, stats) = send_json(client.get(format!("{url}/stats"))).await;
    assert_eq!(stats["verification"], "done", "{stats}");
    assert_eq!(
        (
            stats["tiles_verified"].as_u64(),
            stats["tiles_pending_verification"].as_u64(),
            stats["tiles_dropped"].as_u64(),
            stats["gaussians"].as_u64()
        ),
        (Some(8), Some(0), Some(1), Some(8 * PER_TILE as u64)),
        "{stats}"
    );
    assert!(
        stats["shards_rejected"].to_string().contains("SHA-256"),
        "{stats}"
    );
    let (_, answer) = send_json(client.get(&all)).await;
    assert!(answer.get("partial").is_none(), "{answer}");
    assert!(
        answer.get("tiles_pending_verification").is_none(),
        "{answer}"
    );
    let ids = support::match_ids(&answer);
    assert_eq!(ids.len(), 8 * PER_TILE, "{answer}");
    assert!(!ids.contains(&0), "the forged row is served: {answer}");
    assert!(ids.contains(&(PER_TILE as u32)), "{answer}");
}
