//! "Bring your own models": `scripts/export-models.py` exports a (tiny, random) SAM and CLIP in
//! slag's signatures, then slag runs on them: `encode` on the embedded scene with the exported SAM
//! encoder (external-data weights) + decoder and CLIP image tower, `query` with the exported text
//! tower and tokenizer; the tokenizer reproduces open_clip's token ids, and a text tower of another
//! CLIP model (same file name, other weights: only its `slag.clip_pair_id` differs) is refused.
//!
//! Needs a python with torch, onnx, segment-anything and open-clip-torch (`$SLAG_PYTHON`, default
//! `python3`); without them (CI) the test prints why and passes.

#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use slag_encoder::query::QueryParams;
use slag_tests::{default_scene, encode, fixture, random_weights_config};

fn python() -> String {
    std::env::var("SLAG_PYTHON").unwrap_or_else(|_| "python3".into())
}

/// Why the test cannot run here, if it cannot.
fn skip_reason() -> Option<String> {
    let probe = Command::new(python())
        .args(["-c", "import torch, onnx, segment_anything, open_clip"])
        .output();
    match probe {
        Err(e) => return Some(format!("cannot run {}: {e}", python())),
        Ok(o) if !o.status.success() => {
            let err = String::from_utf8_lossy(&o.stderr);
            return Some(format!(
                "{} lacks torch/onnx/segment_anything/open_clip ({}); set SLAG_PYTHON to a python \
                 with them",
                python(),
                err.lines().last().unwrap_or("").trim()
            ));
        }
        Ok(_) => {}
    }
    if std::env::var_os("ORT_DYLIB_PATH").is_none() {
        return Some("ORT_DYLIB_PATH is not set (run `. scripts/setup.sh`)".into());
    }
    None
}

/// A folder for the test `test`'s exports (removed with it), or `None` when it cannot run here,
/// having printed why (`SKIPPED <test>: ...`).
fn exports_for(test: &str) -> Option<tempfile::TempDir> {
    if let Some(why) = skip_reason() {
        eprintln!("SKIPPED {test}: {why}");
        return None;
    }
    Some(tempfile::tempdir().unwrap())
}

/// `rel` under `dir`, as a command-line argument.
fn under(dir: &tempfile::TempDir, rel: &str) -> String {
    dir.path().join(rel).display().to_string()
}

/// The first view of the embedded scene.
fn first_view_image() -> image::RgbImage {
    let views = slag_common::camera::load_views(&default_scene()).unwrap();
    slag_encoder::preprocess::load_rgb(&views[0].image_path).unwrap()
}

/// Runs `python <script> <args…>`; panics with its stderr unless it exits with status 0.
fn run_python<A: AsRef<std::ffi::OsStr> + std::fmt::Debug>(script: &Path, args: &[A]) {
    let out = Command::new(python())
        .arg(script)
        .args(args)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{} {args:?} failed:\n{err}", script.display());
}

/// Runs `scripts/export-models.py` with `args`; the seconds it took.
fn export(args: &[&str]) -> f64 {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/export-models.py");
    let t = Instant::now();
    run_python(&script, args);
    t.elapsed().as_secs_f64()
}

fn query_args(emb: &Path, textual: &Path, tokenizer: &Path, text: &str) -> QueryParams {
    QueryParams {
        top_k: 5,
        threshold: 0.28,
        ..QueryParams::new(emb, textual, tokenizer, text)
    }
}

#[test]
fn exported_models_encode_and_query() {
    let Some(dir) = exports_for("exported_models_encode_and_query") else {
        return;
    };
    let p = |rel: &str| -> PathBuf { dir.path().join(rel) };
    let s = |rel: &str| under(&dir, rel);
    let t_sam = export(&["sam", "--kind", "tiny", "--external-data", &s("sam")]);
    let t_clip = export(&["clip", "--model", "tiny", "--random", &s("clip")]);
    let t_other = export(&[
        "clip",
        "--model",
        "tiny",
        "--random",
        "--seed",
        "1",
        &s("other"),
    ]);
    assert!(p("sam/sam-tiny-encoder.onnx.data").is_file());
    let info: serde_json::Value =
        serde_json::from_slice(&std::fs::read(p("clip/tiny-random.json")).unwrap()).unwrap();
    let pair_id = info["clip_pair_id"].as_str().unwrap().to_string();
    assert!(pair_id.starts_with("tiny/random/"), "{pair_id}");

    // The exported tokenizer gives open_clip's ids (recorded by the script).
    let tok = slag_common::text::ClipTokenizer::from_file(&p("clip/clip-tokenizer.json")).unwrap();
    let texts = info["check"]["texts"].as_array().unwrap();
    let ids = info["check"]["input_ids"].as_array().unwrap();
    for (t, want) in texts.iter().zip(ids) {
        let want: Vec<i64> = serde_json::from_value(want.clone()).unwrap();
        assert_eq!(tok.tokenize(t.as_str().unwrap(), 77).unwrap(), want, "{t}");
    }
    // ... and equals the shared fixture's token ids (same vocabulary and merges).
    let fx =
        slag_common::text::ClipTokenizer::from_file(&fixture("clip/clip-tokenizer.json")).unwrap();
    for t in texts {
        let t = t.as_str().unwrap();
        assert_eq!(tok.tokenize(t, 77).unwrap(), fx.tokenize(t, 77).unwrap());
    }

    let out = p("out");
    let sam = [
        p("sam/sam-tiny-encoder.onnx"),
        p("sam/sam-tiny-decoder.onnx"),
    ];
    let visual = p("clip/tiny-random-visual.onnx");
    let config = random_weights_config(default_scene(), visual, sam, 6, &out);
    let t = Instant::now();
    let report = encode(config).expect("encode");
    let t_encode = t.elapsed().as_secs_f64();
    assert!(report.counts.masks > 0, "the exported SAM produced no mask");
    let emb_path = out.join("embeddings.safetensors");
    let emb = slag_common::embeddings::Embeddings::read(&emb_path).unwrap();
    assert_eq!(emb.dim, 512);
    assert!(!emb.is_empty() && emb.vectors.iter().all(|v| v.is_finite()));
    assert_eq!(emb.model, pair_id, "the encoder records the CLIP pair id");

    let tokenizer = p("clip/clip-tokenizer.json");
    let q = slag_encoder::query::run(&query_args(
        &emb_path,
        &p("clip/tiny-random-textual.onnx"),
        &tokenizer,
        "a red chair",
    ))
    .expect("query with the paired text tower");
    assert_eq!(q.model, pair_id);
    assert!(!q.matches.is_empty() || !q.nearest_below_threshold.is_empty());

    // Same architecture, same file name, other weights: refused, naming both ids.
    let e = slag_encoder::query::run(&query_args(
        &emb_path,
        &p("other/tiny-random-textual.onnx"),
        &tokenizer,
        "a red chair",
    ))
    .expect_err("a text tower of another CLIP model must be refused");
    let msg = e.to_string();
    assert!(
        matches!(e, slag_common::Error::ModelMismatch { .. }) && msg.contains(&pair_id),
        "{msg}"
    );
    // The shared fixture's text tower (color-clip) is refused as well.
    let e = slag_encoder::query::run(&query_args(
        &emb_path,
        &fixture("clip/color-clip-textual.onnx"),
        &tokenizer,
        "red",
    ))
    .err()
    .unwrap();
    assert!(e.to_string().contains("`color-clip`"), "{e}");
    eprintln!(
        "byo models: export sam {t_sam:.1} s, clip {t_clip:.1} s (+{t_other:.1} s); encode \
         {t_encode:.1} s: {} views, {} masks, {} Gaussians observed; pair id {pair_id}; \
         'a red chair' best {:?}",
        report.counts.views_used,
        report.counts.masks,
        emb.len(),
        q.matches
            .first()
            .or(q.nearest_below_threshold.first())
            .map(|m| m.score)
    );
}

/// `export-models.py sam --fuse`: the encoder whose attention (relative positions folded into
/// widened queries and keys) is one fused node per block gives the image embeddings of the plain
/// export, run by ONNX Runtime on the CPU on a real image, same weights (same seed).
#[test]
fn fused_sam_encoder_matches_the_plain_export() {
    let Some(dir) = exports_for("fused_sam_encoder_matches_the_plain_export") else {
        return;
    };
    let s = |rel: &str| under(&dir, rel);
    export(&["sam", "--kind", "tiny", &s("plain")]);
    export(&["sam", "--kind", "tiny", "--fuse", &s("fused")]);
    let image = first_view_image();
    let (pixels, _) = slag_encoder::preprocess::sam_pixel_values(&image).unwrap();
    let placement =
        slag_common::onnx::Placement::new(slag_common::onnx::ExecutionProvider::Cpu, 0, 0);
    let embed = |path: String| -> Vec<f32> {
        let mut model = slag_common::onnx::OnnxModel::load(Path::new(&path), &placement).unwrap();
        let input =
            ort::value::TensorRef::from_array_view(([1usize, 3, 1024, 1024], pixels.as_slice()))
                .unwrap();
        let out = model
            .session_mut()
            .run(ort::inputs!["pixel_values" => input])
            .unwrap();
        out["image_embeddings"]
            .try_extract_tensor::<f32>()
            .unwrap()
            .1
            .to_vec()
    };
    let plain = embed(s("plain/sam-tiny-encoder.onnx"));
    let fused = embed(s("fused/sam-tiny-encoder.onnx"));
    assert_eq!(plain.len(), 256 * 64 * 64);
    let scale = plain.iter().fold(0f32, |m, v| m.max(v.abs()));
    let diff = plain
        .iter()
        .zip(&fused)
        .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(
        scale > 0.0 && diff <= 1e-4 * scale,
        "max |diff| {diff} at scale {scale}"
    );
}

/// `sam-decoder-low-res.py --f16-multimask` on an `--fp16-decoder` export: slag reads the f16,
/// three-channel `low_res_masks` and generates the same masks (pixels, boxes, predicted IoUs) as
/// from the same decoder cut without the flag (f32, four channels), on a real image with ONNX
/// Runtime on the CPU. Loose score thresholds, so that the random-weight tiny decoder keeps
/// masks to compare.
#[test]
fn f16_multimask_decoder_gives_the_same_masks() {
    use slag_encoder::masks::MaskGenerator;
    use slag_encoder::masks::sam::{LowResLogits, SamAutomaticMaskGenerator, SamParams};
    let Some(dir) = exports_for("f16_multimask_decoder_gives_the_same_masks") else {
        return;
    };
    let s = |rel: &str| under(&dir, rel);
    export(&["sam", "--kind", "tiny", "--fp16-decoder", &s("m")]);
    let cut = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/sam-decoder-low-res.py");
    for (flag, out) in [(None, "f32.onnx"), (Some("--f16-multimask"), "f16.onnx")] {
        let mut args: Vec<String> = flag.map(String::from).into_iter().collect();
        args.extend([s("m/sam-tiny-decoder.onnx"), s(out)]);
        run_python(&cut, &args);
    }
    // An f32 decoder is refused: its logits would be rounded.
    export(&["sam", "--kind", "tiny", "--decoder-only", &s("f32dec")]);
    let o = Command::new(python())
        .arg(&cut)
        .args([
            "--f16-multimask",
            &s("f32dec/sam-tiny-decoder.onnx"),
            &s("x.onnx"),
        ])
        .output()
        .unwrap();
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("--fp16-decoder"));

    let image = first_view_image();
    let params = SamParams {
        points_per_side: 8,
        pred_iou_thresh: 0.0,
        stability_score_thresh: 0.0,
        stability_score_offset: 0.05,
        ..SamParams::default()
    };
    let run = |decoder: &str, layout: LowResLogits| {
        let mut g = SamAutomaticMaskGenerator::new(
            Path::new(&s("m/sam-tiny-encoder.onnx")),
            Path::new(&s(decoder)),
            slag_common::onnx::ExecutionProvider::Cpu,
            0,
            params.clone(),
        )
        .unwrap();
        assert_eq!(g.models().low_res_logits(), layout);
        g.generate(&image).unwrap()
    };
    let four = run("f32.onnx", LowResLogits::F32AllChannels);
    let three = run("f16.onnx", LowResLogits::F16Multimask);
    assert!(!four.is_empty(), "the tiny decoder kept no mask to compare");
    assert_eq!(four.len(), three.len());
    for (a, b) in four.iter().zip(&three) {
        assert_eq!(a.bbox_xywh, b.bbox_xywh);
        assert_eq!(a.area, b.area);
        assert_eq!(a.predicted_iou.to_bits(), b.predicted_iou.to_bits());
        assert!(a.pixels == b.pixels);
    }
}

/// `export-models.py clip --u8-pixels`: the image tower that takes the crops' bytes and
/// normalises them in its graph gives the embeddings of the plain export (same weights, same
/// seed) on the crops of real masks, with ONNX Runtime on the CPU, and records the same CLIP
/// pair id.
#[test]
fn u8_pixels_clip_export_gives_the_same_embeddings() {
    use slag_encoder::clip::{ClipVisual, VisualInput};
    use slag_encoder::masks::MaskGenerator;
    let Some(dir) = exports_for("u8_pixels_clip_export_gives_the_same_embeddings") else {
        return;
    };
    let s = |rel: &str| under(&dir, rel);
    export(&["clip", "--model", "tiny", "--random", &s("plain")]);
    export(&[
        "clip",
        "--model",
        "tiny",
        "--random",
        "--u8-pixels",
        &s("u8"),
    ]);
    let image = first_view_image();
    let mut seg = slag_encoder::masks::graph::GraphSegmenter::new(Default::default());
    let masks = seg.generate(&image).unwrap();
    assert!(
        masks.len() >= 2,
        "the graph segmenter found {} masks",
        masks.len()
    );
    let cpu = slag_common::onnx::ExecutionProvider::Cpu;
    let mut plain =
        ClipVisual::new(Path::new(&s("plain/tiny-random-visual.onnx")), cpu, 8).unwrap();
    let mut bytes = ClipVisual::new(Path::new(&s("u8/tiny-random-visual.onnx")), cpu, 8).unwrap();
    assert_eq!(bytes.input(), VisualInput::U8Pixels);
    assert_eq!(plain.input(), VisualInput::F32PixelValues);
    assert_eq!(bytes.model_id(), plain.model_id());
    let want = plain.embed_masks(&image, &masks).unwrap();
    let got = bytes.embed_masks(&image, &masks).unwrap();
    let diff = want
        .iter()
        .zip(&got)
        .map(|(a, b)| slag_common::similarity::max_abs_difference(a, b))
        .fold(0f32, f32::max);
    assert!(diff <= 1e-5, "max |Δ| {diff} over {} crops", masks.len());
}
