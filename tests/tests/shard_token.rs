//! `slag-encoder serve` with a bearer token and `slag-edge fetch --shard-token-file`: refused
//! (401, a message naming the token) without or with a wrong token, served with the right one.
#![allow(clippy::unwrap_used)]

use std::time::Duration;

use slag_common::Error;
use slag_common::shards::synthetic::SyntheticScene;
use slag_common::shards::{Dtype, GroundFrame};
use slag_edge::fetch::{FetchParams, fetch};
use slag_edge::store::EdgeStore;
use slag_shards::partition::{PartitionParams, UpChoice};
use slag_shards::store::{ShardStore, partition_into_store};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fetch_needs_the_shard_servers_token() {
    let dir = tempfile::tempdir().unwrap();
    let store = ShardStore::open(&dir.path().join("shards")).unwrap();
    let scene = SyntheticScene::new(400, 8, 2, 20.0, 9);
    let m = partition_into_store(
        &store,
        &scene,
        &PartitionParams {
            scene_id: "lab".into(),
            max_per_shard: 100,
            up: UpChoice::Given(GroundFrame::from_axis_name("z").unwrap()),
            dtype: Dtype::F16,
            to_map: None,
        },
    )
    .unwrap();
    let (tx, rx) = tokio::sync::oneshot::channel();
    tokio::spawn(slag_shards::serve::serve_with_token(
        store,
        "127.0.0.1:0".parse().unwrap(),
        Some("tok-42".into()),
        move |a| {
            let _ = tx.send(a);
        },
    ));
    let url = format!("http://{}", rx.await.unwrap());
    let edge = EdgeStore::open(&dir.path().join("edge")).unwrap();
    // The whole scene, without retries (a refused token is final).
    let (jobs, retries, timeout) = (2, 0, Duration::from_secs(10));
    let mut p = FetchParams {
        scene: "lab".into(),
        jobs,
        retries,
        timeout,
        ..slag_tests::robot_fetch_params(&url)
    };
    for token in [None, Some("tok-4"), Some("TOK-42")] {
        p.token = token.map(str::to_string);
        let e = fetch(&edge, &p).await.unwrap_err();
        let msg = e.to_string();
        assert!(
            matches!(
                e,
                Error::Network {
                    status: Some(401),
                    ..
                }
            ),
            "{msg}"
        );
        // The library names the token; `slag-edge` adds `--shard-token-file` (its hint).
        assert!(msg.contains("401") && msg.contains("token"), "{msg}");
    }
    p.token = Some("tok-42".into());
    let s = fetch(&edge, &p).await.unwrap();
    assert_eq!(s.selected, m.tiles.len());
    assert_eq!(s.downloaded, m.tiles.len());
    let (_, shards, load) = edge.load_scene("lab").unwrap();
    assert_eq!((shards.len(), load.rejected.len()), (m.tiles.len(), 0));
}
