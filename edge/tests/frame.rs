//! The robot's map frame: a manifest with a scene-to-map transform makes `fetch`'s centre and
//! radius map metres (end to end against the in-process shard server) and answers map
//! coordinates; prompts are refused with each interface's own hint.
#![allow(clippy::unwrap_used)]

mod support;

use std::sync::Arc;

use slag_common::shards::{Dtype, MapSource, SceneToMap, decode_shard, frame};
use slag_edge::fetch::{Center, FetchParams, fetch, select_tiles};
use slag_edge::query::FrameChoice;
use slag_edge::serve::{AppState, ServeOptions};
use slag_edge::store::EdgeStore;
use support::{
    BasisEmbedder, TestScene, error_message, grid_fetch_params, grid_scene, match_ids, send,
    send_json, serve_on_loopback, shard_server, stored_ids, temp_store,
};

/// A yaw of 35° about z, scale 2.5, a UTM-like translation: the map's z is the scene's up (z).
fn yaw_transform() -> SceneToMap {
    let h = 35f64.to_radians() / 2.0;
    SceneToMap::new(
        2.5,
        frame::quaternion_to_matrix([h.cos(), 0.0, 0.0, h.sin()]),
        [500_123.5, 4_200_777.25, 31.5],
        MapSource::File,
    )
    .unwrap()
}

/// A rotation about a tilted axis, scale 0.37: the map's z is not the scene's up.
fn tilted_transform() -> SceneToMap {
    let q = [0.8, 0.3, -0.4, 0.33];
    let n = q.iter().map(|x: &f64| x * x).sum::<f64>().sqrt();
    SceneToMap::new(
        0.37,
        frame::quaternion_to_matrix(q.map(|x| x / n)),
        [-12.0, 7.5, 3.25],
        MapSource::Points,
    )
    .unwrap()
}

fn with_map(mut s: TestScene, t: &SceneToMap) -> TestScene {
    s.manifest.frames.scene_to_map = Some(t.clone());
    s
}

fn params(url: &str, center: Center, radius: f64, frame: FrameChoice) -> FetchParams {
    let (prune, jobs) = (true, 3);
    FetchParams {
        center,
        prune,
        jobs,
        frame,
        ..grid_fetch_params(url, radius)
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_radius_in_metres_selects_the_tiles_of_the_same_radius_in_scene_units_times_scale() {
    let plain = shard_server(grid_scene("grid", 6, 6, 10, 8, Dtype::F16, 1), None).await;
    for t in [yaw_transform(), tilted_transform()] {
        let mapped = shard_server(
            with_map(grid_scene("grid", 6, 6, 10, 8, Dtype::F16, 1), &t),
            None,
        )
        .await;
        let (d1, d2) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        let (scene_store, map_store) = (
            EdgeStore::open(d1.path()).unwrap(),
            EdgeStore::open(d2.path()).unwrap(),
        );
        let mut checked = 0;
        // Centres and radii (scene units) away from exact tile-distance ties.
        for (c, r) in [
            ([4.3, 4.1], 7.7),
            ([27.2, 31.9], 12.4),
            ([55.5, 2.2], 3.3),
            ([-20.0, 70.0], 20.0),
            ([30.3, 30.3], 0.4),
            ([22.0, 38.0], 100.0),
        ] {
            // The same place as a map point (3-d: valid for any rotation).
            let m = t.to_map([c[0], c[1], 0.4]);
            let by_scene = fetch(
                &scene_store,
                &params(&plain.url, Center::Ground(c), r, FrameChoice::Auto),
            )
            .await
            .unwrap();
            let by_map = fetch(
                &map_store,
                &params(
                    &mapped.url,
                    Center::World(m),
                    r * t.scale,
                    FrameChoice::Auto,
                ),
            )
            .await
            .unwrap();
            assert_eq!(by_scene.frame, "scene");
            assert_eq!(by_map.frame, "map");
            assert!((by_map.scene_radius - r).abs() < 1e-9 * r.max(1.0));
            assert_eq!(by_scene.selected, by_map.selected, "{c:?} r {r}");
            assert_eq!(
                stored_ids(&scene_store),
                stored_ids(&map_store),
                "{c:?} r {r}"
            );
            checked += by_map.selected;
            // The manifest's own selection agrees, and frame=scene reads scene units as before.
            let manifest = map_store.manifest("grid").unwrap().unwrap();
            let sel = |center, radius, frame| {
                select_tiles(&manifest, center, radius, frame)
                    .unwrap()
                    .iter()
                    .map(|x| x.id)
                    .collect::<Vec<_>>()
            };
            assert_eq!(
                sel(Center::Ground(c), r, FrameChoice::Scene),
                stored_ids(&map_store)
            );
            assert_eq!(
                sel(Center::World(m), r * t.scale, FrameChoice::Map),
                stored_ids(&map_store)
            );
            // The yaw keeps the map's z as the scene's up: a 2-d map centre (X, Y) works.
            if t.source == MapSource::File {
                assert_eq!(
                    sel(Center::Ground([m[0], m[1]]), r * t.scale, FrameChoice::Map),
                    stored_ids(&map_store),
                    "{c:?} r {r}"
                );
            }
        }
        assert!(checked > 10, "the cases selected too few tiles ({checked})");
    }
    // A map frame asked of a manifest without a transform is a typed error, before any download.
    let (_d, store) = temp_store();
    let origin = Center::Ground([0.0, 0.0]);
    let map_frame = params(&plain.url, origin, 5.0, FrameChoice::Map);
    let e = fetch(&store, &map_frame).await.unwrap_err();
    assert!(
        matches!(e, slag_common::Error::Query { field: "frame", .. })
            && e.to_string().contains("no map frame"),
        "{e}"
    );
    assert!(stored_ids(&store).is_empty());
}

struct Served {
    url: String,
    client: reqwest::Client,
    shards: Vec<Vec<u8>>,
    _dir: tempfile::TempDir,
}

async fn serve_with_map(t: &SceneToMap) -> Served {
    let server = shard_server(
        with_map(grid_scene("grid", 3, 3, 30, 16, Dtype::F32, 1), t),
        None,
    )
    .await;
    let (dir, store) = temp_store();
    let whole = params(
        &server.url,
        Center::Ground([0.0, 0.0]),
        1000.0,
        FrameChoice::Scene,
    );
    fetch(&store, &whole).await.unwrap();
    let m = store.manifest("grid").unwrap().unwrap();
    let shards = m
        .tiles
        .iter()
        .filter_map(|x| store.shard_bytes("grid", x).unwrap())
        .collect();
    let state = AppState::new(
        store,
        Arc::new(BasisEmbedder::new(16)),
        ServeOptions::new("grid"),
    )
    .unwrap();
    Served {
        url: serve_on_loopback(state).await,
        client: reqwest::Client::new(),
        shards,
        _dir: dir,
    }
}

async fn get(s: &Served, path: &str) -> (u16, serde_json::Value) {
    send_json(s.client.get(format!("{}{path}", s.url))).await
}

fn pos(m: &serde_json::Value) -> [f32; 3] {
    let p = m["position"].as_array().unwrap();
    [0, 1, 2].map(|i| p[i].as_f64().unwrap() as f32)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn answers_are_in_the_map_frame_by_default_and_bbox_is_read_in_it() {
    let t = tilted_transform();
    let s = serve_with_map(&t).await;
    // Default: map frame; frame=scene: the stored frame; same ids and scores.
    let q = "/query?text=t4&threshold=none&top_k=1000";
    let (st, a) = get(&s, q).await;
    assert_eq!(st, 200, "{a}");
    assert_eq!(a["frame"], "map");
    let (_, b) = get(&s, &format!("{q}&frame=scene")).await;
    assert_eq!(b["frame"], "scene");
    let (am, bm) = (
        a["matches"].as_array().unwrap(),
        b["matches"].as_array().unwrap(),
    );
    assert_eq!(am.len(), 270);
    for (x, y) in am.iter().zip(bm) {
        assert_eq!((&x["id"], &x["score"]), (&y["id"], &y["score"]));
        assert_eq!(pos(x), t.to_map_f32(pos(y)));
    }
    // Summary: AABB and centroid of the map positions.
    let mp: Vec<[f32; 3]> = am.iter().map(pos).collect();
    for ax in 0..3 {
        let lo = mp.iter().map(|p| p[ax]).fold(f32::INFINITY, f32::min);
        let hi = mp.iter().map(|p| p[ax]).fold(f32::NEG_INFINITY, f32::max);
        assert_eq!(a["summary"]["aabb"][0][ax].as_f64().unwrap() as f32, lo);
        assert_eq!(a["summary"]["aabb"][1][ax].as_f64().unwrap() as f32, hi);
    }
    // bbox in the map frame: exactly the rows whose map position is inside, best first
    // (reference over the decoded shards, independent of the scan).
    let mut rows: Vec<(u32, [f32; 3], f64)> = Vec::new();
    for b in &s.shards {
        let sh = decode_shard(b).unwrap();
        for i in 0..sh.ids.len() {
            rows.push((sh.ids[i], t.to_map_f32(sh.means[i]), sh.vector(i)[4] as f64));
        }
    }
    rows.sort_by(|a, b| b.2.total_cmp(&a.2).then(a.0.cmp(&b.0)));
    // A box around the map centroid (a rotated box in the scene frame).
    let c = [0, 1, 2].map(|i| mp.iter().map(|p| p[i] as f64).sum::<f64>() / mp.len() as f64);
    let bmin = c.map(|v| (v - 2.5) as f32);
    let bmax = c.map(|v| (v + 2.0) as f32);
    let inside = |p: [f32; 3]| (0..3).all(|i| p[i] >= bmin[i] && p[i] <= bmax[i]);
    let want: Vec<u32> = rows
        .iter()
        .filter(|r| inside(r.1))
        .take(25)
        .map(|r| r.0)
        .collect();
    assert!(want.len() >= 2, "box too small: {}", want.len());
    let bbox = format!(
        "{},{},{},{},{},{}",
        bmin[0], bmin[1], bmin[2], bmax[0], bmax[1], bmax[2]
    );
    for extra in ["&threshold=none&top_k=25", "&threshold=-1&top_k=25"] {
        let (st, c) = get(&s, &format!("/query?text=t4&bbox={bbox}{extra}")).await;
        assert_eq!(st, 200, "{c}");
        assert_eq!(match_ids(&c), want, "{extra}");
        assert!(
            c["matches"]
                .as_array()
                .unwrap()
                .iter()
                .all(|m| inside(pos(m)))
        );
    }
    // /query.ply says which frame its vertices are in.
    for (q, want) in [("", "map"), ("&frame=scene", "scene")] {
        let r = send(s.client.get(format!("{}/query.ply?text=t4{q}", s.url))).await;
        assert_eq!(r.status().as_u16(), 200);
        assert_eq!(r.headers()["x-slag-frame"], want);
    }
    // Bad frame names are a 400 naming the field.
    let (st, e) = get(&s, "/query?text=t4&frame=utm").await;
    assert_eq!(st, 400);
    assert!(error_message(&e).contains("frame"), "{e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn blank_and_too_long_prompts_get_the_http_hints() {
    let s = serve_with_map(&SceneToMap::identity()).await;
    for q in [
        "/query?text=",
        "/query?text=%20%20",
        "/query",
        "/query.ply?text=+",
    ] {
        let (st, e) = get(&s, q).await;
        let m = error_message(&e);
        assert_eq!(st, 400, "{q}: {e}");
        assert!(
            m.contains("missing query text") && m.contains("/query?text=chair"),
            "{q}: {m}"
        );
    }
    let long = "a".repeat(slag_common::prompt::MAX_PROMPT_BYTES + 1);
    let (st, e) = get(&s, &format!("/query?text={long}")).await;
    assert_eq!(st, 400);
    assert!(error_message(&e).contains("at most 1000"), "{e}");
    let blank_second = serde_json::json!({"queries": [{"text": "t1"}, {"text": " "}]});
    let (st, e) = send_json(
        s.client
            .post(format!("{}/query", s.url))
            .json(&blank_second),
    )
    .await;
    assert_eq!(st, 400);
    let m = error_message(&e);
    assert!(
        m.contains("queries[1]") && m.contains(r#"{"text": "chair"}"#) && !m.contains("/query?"),
        "{m}"
    );
}
