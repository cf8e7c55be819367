//! Objects in the answers of `slag-edge serve` over loopback: a 4 × 3 grid scene whose tiles 0
//! and 11 share one embedding direction, so "t0" matches two separate groups of Gaussians (30
//! units apart). `GET /query`, `POST /query` and `GET /query.ply?color_by=object` must agree
//! with an independent reference computed from the decoded shards: one object per matching
//! tile, its count, AABB, centroid weighted by score × sigmoid(opacity) (tile 0 carries
//! opacities) or by score alone (tile 11 carries none), scores; `near` and `max_objects`; typed
//! 400s for bad object parameters.
#![allow(clippy::unwrap_used)]

mod support;

use std::sync::Arc;

use slag_common::scene::{PlyLoadOptions, SH_C0, load_ply};
use slag_common::shards::{Dtype, decode_shard};
use slag_edge::view::object_colour;
use support::{
    BasisEmbedder, Grid, error_message, fetch_grid, grid_scene, grid_scene_segmented,
    grid_serve_options, send, send_json, serve_store, shard_server,
};

const PER_TILE: usize = 60;

/// Reference matches of `q` (score ≥ 0.28) per tile: (id, mean, score, opacity weight).
type Ref = Vec<(u32, [f32; 3], f64, f64)>;

/// Every number of `v`, depth first, as f32.
fn as_f32(v: &serde_json::Value) -> Vec<f32> {
    match v {
        serde_json::Value::Number(n) => vec![n.as_f64().unwrap() as f32],
        serde_json::Value::Array(a) => a.iter().flat_map(as_f32).collect(),
        serde_json::Value::Object(o) => o.values().flat_map(as_f32).collect(),
        _ => Vec::new(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn objects_follow_an_independent_reference_through_every_route() {
    let scene = grid_scene("grid", 4, 3, PER_TILE, 12, Dtype::F32, 1);
    let server = shard_server(scene, None).await;
    let (_dir, store) = fetch_grid(&server.url, 1000.0).await;
    let m = store.manifest("grid").unwrap().unwrap();
    let shards: Vec<_> = m
        .tiles
        .iter()
        .filter_map(|t| store.shard_bytes("grid", t).unwrap())
        .map(|b| decode_shard(&b).unwrap())
        .collect();
    assert_eq!(shards.len(), 12);
    let embedder = Arc::new(BasisEmbedder::new(12));
    let q = embedder.vector("t0");
    let url = serve_store(store, embedder, grid_serve_options(None, false)).await;
    let client = reqwest::Client::new();

    // The reference, per tile.
    let mut per_tile: Vec<(u64, Ref)> = Vec::new();
    for (tile, s) in shards.iter().enumerate() {
        let mut r = Vec::new();
        for i in 0..s.ids.len() {
            let v = s.vector(i);
            let score: f64 = v.iter().zip(&q).map(|(a, b)| *a as f64 * *b as f64).sum();
            if score >= 0.28 {
                let w = s
                    .opacities
                    .as_ref()
                    .map_or(1.0, |o| 1.0 / (1.0 + (-(o[i] as f64)).exp()));
                r.push((s.ids[i], s.means[i], score, w));
            }
        }
        if !r.is_empty() {
            per_tile.push((tile as u64, r));
        }
    }
    let tiles: Vec<u64> = per_tile.iter().map(|t| t.0).collect();
    assert_eq!(tiles, vec![0, 11], "the fixture's two matching tiles");
    assert!(shards[0].opacities.is_some() && shards[11].opacities.is_none());

    let get = |path: String| send_json(client.get(format!("{url}{path}")));
    // The HTTP API reference's example answer: `SLAG_EXAMPLE_OUT=FILE` writes it.
    if let Some(out) = std::env::var_os("SLAG_EXAMPLE_OUT") {
        let (_, ex) = get("/query?text=t0&object_gap=3&top_k=2".into()).await;
        std::fs::write(out, serde_json::to_string_pretty(&ex).unwrap()).unwrap();
    }
    // Tiles are 9 units wide with ~1 unit between Gaussians: a gap of 3 joins a tile, not two.
    let (status, a) = get("/query?text=t0&object_gap=3&top_k=5".into()).await;
    assert_eq!(status, 200, "{a}");
    let objects = a["objects"].as_array().unwrap();
    assert_eq!(objects.len(), 2, "{a:#}");
    // Built over every match, not the 5 returned.
    assert_eq!(a["matches"].as_array().unwrap().len(), 5);
    let total = gaussians_in_objects(&a);
    assert_eq!(total, a["summary"]["count"].as_u64().unwrap());
    let f = |v: &serde_json::Value| v.as_f64().unwrap();
    // The tile whose first match lies in the object's AABB.
    let owner = |o: &serde_json::Value| -> &(u64, Ref) {
        per_tile
            .iter()
            .find(|(_, r)| {
                let p = r[0].1;
                (0..3).all(|k| {
                    f(&o["aabb"][0][k]) <= p[k] as f64 + 1e-6
                        && f(&o["aabb"][1][k]) >= p[k] as f64 - 1e-6
                })
            })
            .unwrap_or_else(|| panic!("no tile for {o}"))
    };
    for (tile, r) in &per_tile {
        let o = objects
            .iter()
            .find(|o| owner(o).0 == *tile)
            .unwrap_or_else(|| panic!("no object for tile {tile}: {a:#}"));
        assert_eq!(o["gaussians"].as_u64().unwrap() as usize, r.len());
        let wsum: f64 = r.iter().map(|m| m.2 * m.3).sum();
        for k in 0..3 {
            let c = r.iter().map(|m| m.2 * m.3 * m.1[k] as f64).sum::<f64>() / wsum;
            assert!(
                (f(&o["centroid"][k]) - c).abs() < 1e-3,
                "tile {tile} centroid"
            );
            let lo = r.iter().map(|m| m.1[k]).fold(f32::INFINITY, f32::min);
            let hi = r.iter().map(|m| m.1[k]).fold(f32::NEG_INFINITY, f32::max);
            assert_eq!(f(&o["aabb"][0][k]) as f32, lo);
            assert_eq!(f(&o["aabb"][1][k]) as f32, hi);
        }
        let max = r.iter().map(|m| m.2).fold(f64::MIN, f64::max);
        let mean = r.iter().map(|m| m.2).sum::<f64>() / r.len() as f64;
        assert!((f(&o["max_score"]) - max).abs() < 1e-5);
        assert!((f(&o["mean_score"]) - mean).abs() < 1e-5);
        let mass: f64 = r.iter().map(|m| m.2.max(0.0) * m.3).sum();
        assert!(
            (f(&o["score_mass"]) - mass).abs() < 1e-3 * mass,
            "tile {tile} mass"
        );
        // The oriented box holds every member.
        let obb = &o["obb"];
        for m in r {
            for ax in 0..3 {
                let t: f64 = (0..3)
                    .map(|k| (m.1[k] as f64 - f(&obb["center"][k])) * f(&obb["axes"][ax][k]))
                    .sum();
                assert!(t.abs() <= f(&obb["extents"][ax]) / 2.0 + 1e-3);
            }
        }
    }
    // Sorted by score mass (score × opacity summed over the members).
    assert!(f(&objects[0]["score_mass"]) >= f(&objects[1]["score_mass"]));
    // near: the object nearest to the point first, whatever its score.
    for (p, tile) in [("35,25,0", 11u64), ("1,1,0", 0)] {
        let (_, n) = get(format!("/query?text=t0&object_gap=3&near={p}")).await;
        assert_eq!(owner(&n["objects"][0]).0, tile, "{p}");
    }
    let (_, one) = get("/query?text=t0&object_gap=3&max_objects=1".into()).await;
    assert_eq!(one["objects"].as_array().unwrap().len(), 1);
    assert_eq!(one["objects"][0], objects[0]);
    // Without object_gap the gap is derived from the matches' spacing: the same two tiles.
    let (_, d) = get("/query?text=t0".into()).await;
    assert_eq!(d["objects"].as_array().unwrap().len(), 2, "{d:#}");
    assert_eq!(gaussians_in_objects(&d), total);
    // A gap below the spacing leaves every match alone, all suppressed: a given gap wins.
    let (_, t) = get("/query?text=t0&object_gap=0.01".into()).await;
    assert_eq!(t["objects"].as_array().unwrap().len(), 0);
    // POST: the same objects; numbers and arrays accepted.
    let batch =
        serde_json::json!({"queries": [{"text": "t0", "object_gap": 3, "near": [35, 25, 0]}]});
    let (status, b) = send_json(client.post(format!("{url}/query")).json(&batch)).await;
    assert_eq!(status, 200, "{b}");
    let post = b["answers"][0]["objects"]
        .as_array()
        .unwrap_or_else(|| panic!("{b:#}"));
    assert_eq!(post.len(), 2);
    assert_eq!(owner(&post[0]).0, 11);
    let same = objects.iter().find(|o| o["id"] == post[0]["id"]).unwrap();
    // The batch answer widens f32 to f64 in its JSON: compare as f32.
    assert_eq!(as_f32(same), as_f32(&post[0]));
    // Bad object parameters: typed 400s naming the field.
    for (q, field) in [
        ("max_objects=0", "max_objects"),
        ("max_objects=1001", "max_objects"),
        ("near=1,2", "near"),
        ("near=1,2,nan", "near"),
        ("object_gap=-1", "object_gap"),
        ("object_gap=0", "object_gap"),
        ("object_min_gaussians=0", "object_min_gaussians"),
    ] {
        let (status, e) = get(format!("/query?text=t0&{q}")).await;
        assert_eq!(status, 400, "{q}: {e}");
        assert!(error_message(&e).contains(field), "{q}: {e}");
    }

    // /query.ply?color_by=object: each object's matches in its colour, rows in store order.
    let ply = "/query.ply?text=t0&object_gap=3&color_by=object";
    let r = send(client.get(format!("{url}{ply}"))).await;
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["x-slag-objects"], "2");
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("o.ply");
    std::fs::write(&p, r.bytes().await.unwrap()).unwrap();
    let g = load_ply(&p, PlyLoadOptions { colours: true }).unwrap();
    let sh = g.sh.as_ref().unwrap();
    let row_of = |id: u32| id as usize; // tiles in order, PER_TILE rows each, ids sequential
    assert_eq!(shards[3].ids[0] as usize, 3 * PER_TILE);
    for (k, o) in objects.iter().enumerate() {
        let want = object_colour(k);
        let r = &owner(o).1;
        for m in r.iter() {
            let c = sh.dc(row_of(m.0)).map(|c| 0.5 + SH_C0 * c as f64);
            for ch in 0..3 {
                assert!((c[ch] - want[ch] as f64).abs() < 1e-5, "object {k}: {c:?}");
            }
        }
    }
    let r = send(client.get(format!("{url}/query.ply?text=t0&color_by=tile"))).await;
    assert_eq!(r.status(), 400);
}

/// Segment of Gaussian `id` in the smoothing fixture: the first 20 Gaussians of tile 0 share one
/// segment with all of tile 1 (which does not match "t0"); every other tile is one segment.
fn smoothing_segment(id: u32) -> u32 {
    let tile = id / PER_TILE as u32;
    if tile == 1 || id < 20 { 0 } else { 100 + tile }
}

/// `smooth=segment` over HTTP: every score is its segment's mean over the loaded Gaussians,
/// checked against a reference from the decoded shards; the smoothing changes which Gaussians
/// match (tile 0's first 20 match alone, not in their segment); typed 400s for a bad value, for
/// `index=hnsw`, and for a scene without segments.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn smooth_segment_scores_each_gaussian_with_its_segment_mean() {
    let grid = Grid("grid", 4, 3, PER_TILE, 12, Dtype::F32, 1);
    let scene = grid_scene_segmented(grid, &smoothing_segment);
    let server = shard_server(scene, None).await;
    let (_dir, store) = fetch_grid(&server.url, 1000.0).await;
    let m = store.manifest("grid").unwrap().unwrap();
    // Shards with segments (format version 3) verify as stored: a later fetch keeps them.
    for t in &m.tiles {
        let st = store.check_stored(&m, t).unwrap();
        assert!(
            matches!(st, slag_edge::store::Stored::Verified),
            "tile {}: {st:?}",
            t.id
        );
    }
    let embedder = Arc::new(BasisEmbedder::new(12));
    let q = embedder.vector("t0");
    // Reference: raw score of every Gaussian, then its segment's mean (f64).
    let mut raw: Vec<(u32, f64)> = Vec::new();
    for t in &m.tiles {
        let s = decode_shard(&store.shard_bytes("grid", t).unwrap().unwrap()).unwrap();
        assert_eq!(s.segments.as_ref().map(Vec::len), Some(s.ids.len()));
        for i in 0..s.ids.len() {
            let score: f64 = s
                .vector(i)
                .iter()
                .zip(&q)
                .map(|(a, b)| *a as f64 * *b as f64)
                .sum();
            raw.push((s.ids[i], score));
        }
    }
    let mut sums: std::collections::HashMap<u32, (f64, f64)> = Default::default();
    for &(id, sc) in &raw {
        let e = sums.entry(smoothing_segment(id)).or_default();
        e.0 += sc;
        e.1 += 1.0;
    }
    let smoothed = |id: u32| {
        let (s, n) = sums[&smoothing_segment(id)];
        s / n
    };
    let mut want: Vec<(u32, f64)> = raw
        .iter()
        .map(|&(id, _)| (id, smoothed(id)))
        .filter(|&(_, s)| s >= 0.28)
        .collect();
    want.sort_by_key(|w| w.0);
    let raw_hits: Vec<u32> = raw.iter().filter(|r| r.1 >= 0.28).map(|r| r.0).collect();
    // The fixture does what it is for: tile 0's first 20 match on their own scores only.
    assert!((0..20).all(|id| raw_hits.contains(&id)), "{raw_hits:?}");
    assert!(want.iter().all(|w| w.0 >= 20) && want.len() == raw_hits.len() - 20);

    let url = serve_store(store, embedder, grid_serve_options(None, false)).await;
    let client = reqwest::Client::new();
    let get = |path: String| send_json(client.get(format!("{url}{path}")));
    let ids_scores = |a: &serde_json::Value| -> Vec<(u32, f64)> {
        let mut v: Vec<(u32, f64)> = a["matches"]
            .as_array()
            .unwrap()
            .iter()
            .map(|m| {
                (
                    m["id"].as_u64().unwrap() as u32,
                    m["score"].as_f64().unwrap(),
                )
            })
            .collect();
        v.sort_by_key(|w| w.0);
        v
    };
    let (status, a) = get("/query?text=t0&smooth=segment&top_k=10000&object_gap=3".into()).await;
    assert_eq!(status, 200, "{a}");
    assert_eq!(a["smooth"], "segment");
    let got = ids_scores(&a);
    assert_eq!(
        got.iter().map(|g| g.0).collect::<Vec<_>>(),
        want.iter().map(|w| w.0).collect::<Vec<_>>()
    );
    for (g, w) in got.iter().zip(&want) {
        assert!((g.1 - w.1).abs() < 1e-5, "id {}: {} vs {}", g.0, g.1, w.1);
    }
    assert_eq!(a["summary"]["count"].as_u64().unwrap() as usize, want.len());
    let in_objects = gaussians_in_objects(&a);
    assert_eq!(in_objects as usize, want.len(), "{a:#}");
    // Without smoothing: each Gaussian's own score, tile 0's first 20 included.
    let (_, plain) = get("/query?text=t0&top_k=10000".into()).await;
    assert_eq!(plain["smooth"], "none");
    let plain_ids: Vec<u32> = ids_scores(&plain).iter().map(|p| p.0).collect();
    assert_eq!(
        plain_ids,
        raw_hits
            .iter()
            .copied()
            .collect::<std::collections::BTreeSet<_>>()
            .into_iter()
            .collect::<Vec<_>>()
    );
    // A box over tile 0 only: its segment's scores still come from every loaded Gaussian.
    let (_, boxed) =
        get("/query?text=t0&smooth=segment&top_k=10000&bbox=-1,-1,-1,9.5,9.5,2".into()).await;
    let b = ids_scores(&boxed);
    assert!(
        !b.is_empty() && b.iter().all(|g| g.0 < PER_TILE as u32 && g.0 >= 20),
        "{boxed:#}"
    );
    for g in &b {
        assert!((g.1 - smoothed(g.0)).abs() < 1e-5);
    }
    // POST: the same field.
    let batch =
        serde_json::json!({"queries": [{"text": "t0", "smooth": "segment", "top_k": 10000}]});
    let (status, body) = send_json(client.post(format!("{url}/query")).json(&batch)).await;
    assert_eq!(status, 200, "{body}");
    let post: Vec<u32> = ids_scores(&body["answers"][0])
        .iter()
        .map(|p| p.0)
        .collect();
    assert_eq!(post, want.iter().map(|w| w.0).collect::<Vec<_>>());
    // Typed refusals.
    for (q, needle) in [
        ("smooth=mean", "use none or segment"),
        ("smooth=segment&index=hnsw", "index=exact"),
    ] {
        let (status, e) = get(format!("/query?text=t0&{q}")).await;
        assert_eq!(status, 400, "{q}: {e}");
        let msg = error_message(&e);
        assert!(msg.contains("smooth") && msg.contains(needle), "{q}: {e}");
    }

    // A scene whose shards carry no segments: 400 saying what to do.
    let plain_server = shard_server(grid_scene("grid", 2, 2, 20, 12, Dtype::F32, 1), None).await;
    let (_dir2, plain_store) = fetch_grid(&plain_server.url, 1000.0).await;
    let options = grid_serve_options(None, false);
    let url2 = serve_store(plain_store, Arc::new(BasisEmbedder::new(12)), options).await;
    let (status, e) = send_json(client.get(format!("{url2}/query?text=t0&smooth=segment"))).await;
    assert_eq!(status, 400);
    let msg = error_message(&e);
    assert!(
        msg.contains("no geometric segments") && msg.contains("leave smooth out"),
        "{msg}"
    );
}

/// The Gaussians of all of an answer's `objects`.
fn gaussians_in_objects(answer: &serde_json::Value) -> u64 {
    let objects = answer["objects"].as_array().unwrap();
    objects
        .iter()
        .map(|o| o["gaussians"].as_u64().unwrap())
        .sum()
}
