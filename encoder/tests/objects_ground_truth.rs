//! Ground truth for the objects of a query's answer: `synth-scene --objects 5` places five boxes
//! of known colour, size and position on flat gray ground (two red ones far apart), the scene is
//! encoded with the graph segmenter and color-clip, and each colour is queried
//! (`slag-encoder query`). Exactly the placed boxes must come back as objects (the two red ones
//! as two), each centroid within 2 % of the terrain's side of the box shell's true centroid, and
//! each object's AABB with IoU ≥ 0.7 against the true box.
//!
//! Scene: 40,000 terrain Gaussians on a 60 m square (spacing 0.3 m), 8 views of 240×180, raster
//! scale 0.5, 2 threads. Objects are grouped with a 1 m gap (the gap has to exceed the scene's
//! Gaussian spacing; the boxes are ≥ 6 m apart).
//!
//! Needs ONNX Runtime (color-clip) and a Vulkan device (lavapipe on CPU): `. scripts/setup.sh`;
//! SLAG_SKIP_ORT=1 skips.

mod support;

use slag_common::objects::ObjectParams;
use slag_encoder::config::{EncodeConfig, MasksConfig};
use slag_encoder::pipeline::Encoder;
use slag_encoder::query::{QueryParams, run};
use slag_encoder::synthetic::{
    PlacedObject, SyntheticSceneParams, object_layout, write_synthetic_scene_with_objects,
};
use support::{ort_tempdir, shared};

const EXTENT: f64 = 60.0;

fn iou(a: [[f64; 3]; 2], b: [[f64; 3]; 2]) -> f64 {
    let vol = |x: [[f64; 3]; 2]| {
        (0..3)
            .map(|k| (x[1][k] - x[0][k]).max(0.0))
            .product::<f64>()
    };
    let inter = [
        [0, 1, 2].map(|k| a[0][k].max(b[0][k])),
        [0, 1, 2].map(|k| a[1][k].min(b[1][k])),
    ];
    let i = vol(inter);
    i / (vol(a) + vol(b) - i)
}

/// Area-weighted centroid of the box's top and four sides (where its Gaussians lie).
fn shell_centroid(o: &PlacedObject) -> [f64; 3] {
    let b = o.aabb();
    let [sx, sy, h] = o.size;
    let (top, sides) = (sx * sy, 2.0 * (sx + sy) * h);
    [
        o.center[0],
        o.center[1],
        b[0][2] + (top * h + sides * h / 2.0) / (top + sides),
    ]
}

#[test]
fn placed_objects_come_back_with_their_positions_and_boxes() {
    let Some(dir) = ort_tempdir() else {
        return;
    };
    let scene = dir.path().join("scene");
    let p = SyntheticSceneParams {
        gaussians: 40_000,
        views: 8,
        width: 240,
        height: 180,
        extent: EXTENT,
        seed: 3,
        ..Default::default()
    };
    let placed = object_layout(5, EXTENT).expect("layout");
    write_synthetic_scene_with_objects(&scene, &p, &placed).expect("scene");
    assert!(scene.join("objects.json").is_file());
    let out = dir.path().join("out");
    let clip = shared().join("fixtures/clip");
    let mut c = EncodeConfig::new(&scene, clip.join("color-clip-visual.onnx"), &out);
    c.masks = MasksConfig::graph();
    // The floors below were set on every view.
    c.scene.views.mode = slag_encoder::views::SelectionMode::All;
    c.raster.scale = 0.5;
    c.output.progress = false;
    // The floors below were set on the dense rows.
    c.output.dense = true;
    c.execution.threads = Some(2);
    Encoder::new(c).expect("config").run().expect("encode");

    let mut colours: Vec<&str> = placed.iter().map(|o| o.name).collect();
    colours.sort_unstable();
    colours.dedup();
    for colour in colours {
        let truth: Vec<&PlacedObject> = placed.iter().filter(|o| o.name == colour).collect();
        let q = QueryParams {
            objects: ObjectParams {
                gap: Some(1.0),
                ..ObjectParams::default()
            },
            ply: Some(scene.join("point_cloud.ply")),
            highlight_out: Some(dir.path().join(format!("{colour}.ply"))),
            ..QueryParams::new(
                out.join("embeddings.safetensors"),
                clip.join("color-clip-textual.onnx"),
                clip.join("clip-tokenizer.json"),
                colour,
            )
        };
        let answer = run(&q).expect("query");
        let found = &answer.objects;
        assert_eq!(
            found.len(),
            truth.len(),
            "{colour}: {} objects for {} placed: {found:#?}",
            found.len(),
            truth.len()
        );
        // Each placed box is matched by exactly one object, the one nearest its centroid.
        let mut used = vec![false; found.len()];
        for t in &truth {
            let want = shell_centroid(t);
            let (k, d) = found
                .iter()
                .enumerate()
                .map(|(k, o)| {
                    let d = (0..3)
                        .map(|a| (f64::from(o.centroid[a]) - want[a]).powi(2))
                        .sum::<f64>()
                        .sqrt();
                    (k, d)
                })
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .expect("an object");
            assert!(!used[k], "{colour}: one object for two boxes: {found:#?}");
            used[k] = true;
            assert!(
                d <= 0.02 * EXTENT,
                "{colour} at {:?}: centroid {:?} is {d:.2} m from {want:?}",
                t.center,
                found[k].centroid
            );
            let got = found[k].aabb.map(|c| c.map(f64::from));
            let i = iou(got, t.aabb());
            assert!(
                i >= 0.7,
                "{colour} at {:?}: box {got:?} vs {:?}: IoU {i:.2}",
                t.center,
                t.aabb()
            );
        }
    }
}
