//! A cluster process runs the encode's worker pool: one `encode-cluster` process (loopback) with
//! two front workers and two rasterizers (two wgpu devices on one adapter, as `--gpus 2` gives
//! on a host of two GPUs) writes the mixture a one-process `encode --reduce host` writes, byte
//! for byte, and maps every view once. Its own test binary: `encode_cluster`'s panic hook ends
//! the process on any panic while the job runs.

#![allow(clippy::unwrap_used)]

use std::sync::Arc;
use std::time::Duration;

use slag_encoder::config::ReduceOn;
use slag_encoder::distributed::{ClusterConfig, ClusterJob, StageFactory, Stages, encode_cluster};
use slag_encoder::pipeline::{self, build};
use slag_encoder::raster::WeightRasterizer;
use slag_encoder::synthetic::{SyntheticSceneParams, write_synthetic_scene};
use slag_tests::{encode, graph_config};

/// Graph masks and color-clip on a small synthetic scene, raster scale 0.5, the mixture only,
/// reduced on the host, two threads (two fronts of one thread each).
fn config(scene: &std::path::Path, out: &std::path::Path) -> slag_encoder::config::EncodeConfig {
    let mut c = graph_config(scene, out);
    c.raster.scale = 0.5;
    c.output.dense = false;
    c.aggregate.reduce_on = ReduceOn::Host;
    c.execution.threads = Some(2);
    c
}

#[test]
fn a_cluster_process_with_two_fronts_and_two_rasterizers_writes_what_encode_writes() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    let p = SyntheticSceneParams {
        gaussians: 20_000,
        views: 6,
        width: 200,
        height: 150,
        extent: 60.0,
        seed: 5,
        ..Default::default()
    };
    write_synthetic_scene(&scene, &p).unwrap();
    let single = dir.path().join("single");
    let r = encode(config(&scene, &single)).unwrap();
    assert_eq!(r.counts.views_used, 6);

    let out = dir.path().join("cluster");
    let c = config(&scene, &out);
    let for_stages = c.clone();
    let stages: StageFactory = Arc::new(move |g| {
        let fronts = build::build_fronts(&for_stages, 1, 2)?;
        assert_eq!(fronts.stages.len(), 2, "two fronts");
        let rasterizers = (0..2)
            .map(|_| {
                let r = slag_encoder::raster::GpuRasterizer::new(g)?;
                Ok(Box::new(r) as Box<dyn WeightRasterizer>)
            })
            .collect::<slag_common::Result<Vec<_>>>()?;
        Ok(Stages {
            fronts: fronts.stages,
            rasterizers,
            services: fronts.services,
        })
    });
    let job = ClusterJob {
        scene: pipeline::SceneInput {
            selection: c.scene.views,
            ..pipeline::SceneInput::new(&scene, None, 1)
        },
        params: build::encode_params(&c),
        stages,
        report: build::report_header(&c, 2),
        segments: None,
    };
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let cluster = ClusterConfig {
        process: 0,
        addresses: vec![format!("127.0.0.1:{port}")],
        connect_timeout: Duration::from_secs(60),
        secret: None,
        checkpoint_every: None,
    };
    encode_cluster(job, &cluster).unwrap().unwrap();

    let mixture = |d: &std::path::Path| std::fs::read(d.join("mixture.safetensors")).unwrap();
    assert!(mixture(&single) == mixture(&out), "the mixtures differ");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let mut views: Vec<u64> = report["outputs"]["cluster"]["workers"][0]["views"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap())
        .collect();
    views.sort_unstable();
    assert_eq!(views, (0..6).collect::<Vec<_>>(), "every view mapped once");
}
