//! Prediction filtering where the truth is objects, end to end on a small labelled-object room
//! (`synth-scene --objects 10 --room`, default texture): encode with the graph segmenter and
//! color-clip, every 4th view held out, segment the geometry alone, and score slag and every
//! PF variant against the object truth (`eval-objects --held-out`). On this truth PF must help:
//! the test fails if it stops doing so.
//!
//! Needs ONNX Runtime (color-clip): `. scripts/setup.sh`; SLAG_SKIP_ORT=1 skips.

#[path = "../../encoder/tests/support/mod.rs"]
mod support;

use slag_encoder::config::{EncodeConfig, MasksConfig, RasterBackend};
use slag_encoder::object_scene::{Texture, room_layout, write_room_scene};
use slag_encoder::pipeline::Encoder;
use slag_encoder::segments::{SegmentParams, segment};
use slag_encoder::synthetic::SyntheticSceneParams;
use slag_eval::object_truth::{ObjectTruthConfig, run_object_truth};
use support::{ort_tempdir, shared};

#[test]
fn prediction_filtering_helps_on_object_truth() {
    let Some(dir) = ort_tempdir() else {
        return;
    };
    let scene = dir.path().join("room");
    let p = SyntheticSceneParams {
        gaussians: 8_000,
        views: 8,
        width: 160,
        height: 120,
        extent: 6.0,
        seed: 11,
        ..Default::default()
    };
    let objects = room_layout(10, p.extent).expect("layout");
    write_room_scene(&scene, &p, &objects, &Texture::for_extent(p.extent)).expect("room");
    let clip = shared().join("fixtures/clip");
    let out = dir.path().join("enc");
    let mut c = EncodeConfig::new(&scene, clip.join("color-clip-visual.onnx"), &out);
    c.masks = MasksConfig::graph();
    c.scene.hold_out_every = Some(4);
    c.scene.views.mode = slag_encoder::views::SelectionMode::All;
    c.output.progress = false;
    c.output.dense = true;
    Encoder::new(c).expect("config").run().expect("encode");
    let g = slag_common::scene::load_ply(
        &scene.join("point_cloud.ply"),
        slag_common::scene::PlyLoadOptions::default(),
    )
    .expect("ply");
    // No masks' record: the geometry alone.
    let (geometric, _) = segment(&g, &SegmentParams::default(), "room", None).expect("segments");
    let geo = dir.path().join("geo").join("segments.safetensors");
    std::fs::create_dir_all(dir.path().join("geo")).expect("segments folder");
    geometric.write(&geo).expect("write segments");
    let r = run_object_truth(&ObjectTruthConfig {
        scene: scene.clone(),
        embeddings: out.join("embeddings.safetensors"),
        color_clip: clip,
        segments: vec![geo],
        every: None,
        rasterizer: RasterBackend::Gpu,
        ep: slag_common::onnx::ExecutionProvider::Cpu,
        picture: None,
    })
    .expect("object truth");
    let pixel = |name: &str| {
        r.predictor(name)
            .and_then(|p| p.pixel.miou)
            .unwrap_or_else(|| panic!("no {name}"))
    };
    let three_d = |name: &str| {
        r.predictor(name)
            .and_then(|p| p.gaussian.as_ref()?.miou)
            .unwrap_or_else(|| panic!("no {name}"))
    };
    let no_pf = pixel("slag");
    eprintln!(
        "object truth: slag {no_pf:.4} (3D {:.4}), pf-majority {:.4} (3D {:.4}), pf-mean {:.4}",
        three_d("slag"),
        pixel("pf-majority"),
        three_d("pf-majority"),
        pixel("pf-mean")
    );
    eprintln!(
        "pf-weighted {:.4} (3D {:.4}), pf-strict {:.4} (3D {:.4})",
        pixel("pf-weighted"),
        three_d("pf-weighted"),
        pixel("pf-strict"),
        three_d("pf-strict")
    );
    assert!(
        no_pf > pixel("majority"),
        "slag at or below the majority class"
    );
    // The segments follow the objects better than the texture does.
    let s = &r.segments[0];
    assert!(s.object_purity.purity > 0.9, "{:?}", s.object_purity);
    // The objects' Gaussians alone, each against its whole segment: every one counted, and
    // most in a segment their object dominates.
    let truth = slag_encoder::object_scene::GaussianTruth::read(&scene).expect("truth");
    let on_objects: usize = truth
        .runs
        .iter()
        .filter(|r| r.object.is_some())
        .map(|r| r.gaussians[1] - r.gaussians[0])
        .sum();
    eprintln!(
        "segments over the objects' Gaussians: object purity {:.4}, class purity {:.4}",
        s.objects_object_purity.purity, s.objects_class_purity.purity
    );
    assert_eq!(s.objects_object_purity.counted, on_objects);
    assert!(
        s.objects_object_purity.purity > 0.5,
        "{:?}",
        s.objects_object_purity
    );
    // PF helps, per pixel and per Gaussian.
    assert!(
        pixel("pf-majority") >= no_pf + 0.02,
        "pf-majority {} vs {no_pf}",
        pixel("pf-majority")
    );
    assert!(three_d("pf-majority") >= three_d("slag") + 0.02);
    // So does the vote weighted by how much the views saw each Gaussian (Σ_j a_kj).
    assert!(
        pixel("pf-weighted") >= no_pf + 0.02,
        "pf-weighted {} vs {no_pf}",
        pixel("pf-weighted")
    );
    // And the majority kept to segments where it is one (more than half of the votes).
    assert!(
        pixel("pf-strict") >= no_pf + 0.02,
        "pf-strict {} vs {no_pf}",
        pixel("pf-strict")
    );
    assert!(three_d("pf-strict") >= three_d("slag") + 0.02);
}
