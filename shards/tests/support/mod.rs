//! Fixtures the shard tests share: partition parameters for a z-up scene and a store holding a
//! small synthetic scene.
#![allow(dead_code, clippy::unwrap_used)]

use std::sync::Arc;

use slag_common::http::ServerLimits;
use slag_common::shards::synthetic::SyntheticScene;
use slag_common::shards::{Dtype, GroundFrame};
use slag_common::tls::ServerTls;
use slag_shards::partition::{PartitionParams, UpChoice};
use slag_shards::store::{ShardStore, partition_into_store};

/// Partition parameters for scene `scene_id` whose up is the +z axis: at most `max_per_shard`
/// Gaussians a shard, vectors stored as `dtype`, no map frame.
pub fn z_up_params(scene_id: &str, max_per_shard: usize, dtype: Dtype) -> PartitionParams {
    PartitionParams {
        scene_id: scene_id.into(),
        max_per_shard,
        up: UpChoice::Given(GroundFrame::from_axis_name("z").unwrap()),
        dtype,
        to_map: None,
    }
}

/// A store in a new temporary folder holding scene `lab`: 300 synthetic Gaussians (8-d, 2
/// clusters over 20 units, seed 5) in f16 shards of at most 100.
pub fn lab_store() -> (tempfile::TempDir, ShardStore) {
    let dir = tempfile::tempdir().unwrap();
    let store = ShardStore::open(dir.path()).unwrap();
    let scene = SyntheticScene::new(300, 8, 2, 20.0, 5);
    partition_into_store(&store, &scene, &z_up_params("lab", 100, Dtype::F16)).unwrap();
    (dir, store)
}

/// The default server limits with this header timeout (seconds) and connection limits.
pub fn limits(
    header_s: u64,
    max_connections: usize,
    max_connections_per_ip: usize,
) -> ServerLimits {
    ServerLimits {
        header_timeout: std::time::Duration::from_secs(header_s),
        max_connections,
        max_connections_per_ip,
        ..ServerLimits::default()
    }
}

/// The [`lab_store`] served on 127.0.0.1 (a free port) with `token`, under `limits`, over HTTPS
/// with `tls` (plain HTTP with `None`); returns `127.0.0.1:port` and the store's folder to keep.
pub async fn serve_lab(
    token: Option<&str>,
    limits: ServerLimits,
    tls: Option<Arc<ServerTls>>,
) -> (String, tempfile::TempDir) {
    let (dir, store) = lab_store();
    let (tx, rx) = tokio::sync::oneshot::channel();
    let token = token.map(str::to_string);
    tokio::spawn(async move {
        let addr = "127.0.0.1:0".parse().unwrap();
        let bound = |a| {
            let _ = tx.send(a);
        };
        slag_shards::serve::serve_with_tls(store, addr, token, limits, tls, bound)
            .await
            .unwrap();
    });
    (rx.await.unwrap().to_string(), dir)
}
