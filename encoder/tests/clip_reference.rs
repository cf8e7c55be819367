//! CLIP crop embeddings and text embeddings against open_clip's own output
//! (`shared/fixtures/clip/reference.json`, tiny-clip ONNX towers), plus a colour sanity check with
//! the color-clip stand-in whose answer is known.
//!
//! These tests need ONNX Runtime: `. scripts/setup.sh` exports `ORT_DYLIB_PATH` (the path
//! printed by `shared/tools/install-onnxruntime.sh`); without it they fail (SLAG_SKIP_ORT=1 skips).

#![allow(clippy::unwrap_used)]

use std::path::PathBuf;
use std::time::Instant;

use serde::Deserialize;
use serde_json::Value;
use slag_common::Error;
use slag_common::onnx::ExecutionProvider;
use slag_common::similarity::max_abs_difference;
use slag_common::text::TextEncoder;
use slag_encoder::clip::{ClipVisual, CropFill, VisualInput, crop};
use slag_encoder::masks::Mask;
use slag_encoder::preprocess::{clip_pixel_values, load_rgb};

mod support;
use support::{ort_fixtures, rle_to_pixels, shared, test_fixture};

fn json(path: PathBuf) -> Value {
    serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap()
}

/// The reference mask of a COCO RLE ([`rle_to_pixels`]).
fn rle_to_mask(rle: &Value) -> Mask {
    let (w, h, px) = rle_to_pixels(rle);
    Mask::from_pixels(w, h, px).expect("reference masks are non-empty")
}

fn cosine(a: &[f32], b: &[f64]) -> f64 {
    let dot: f64 = a.iter().zip(b).map(|(&x, &y)| f64::from(x) * y).sum();
    let na: f64 = a.iter().map(|&x| f64::from(x).powi(2)).sum::<f64>().sqrt();
    let nb: f64 = b.iter().map(|y| y * y).sum::<f64>().sqrt();
    dot / (na * nb)
}

fn f64s(v: &Value) -> Vec<f64> {
    Vec::<f64>::deserialize(v).unwrap()
}

#[test]
fn clip_crops_reproduce_open_clip_reference() {
    let Some(clip_dir) = ort_fixtures("clip") else {
        return;
    };
    let reference = json(clip_dir.join("reference.json"));
    let sam_ref = json(shared().join("fixtures/sam-amg/reference.json"));
    let mut visual = ClipVisual::new(
        &clip_dir.join("tiny-clip-visual.onnx"),
        ExecutionProvider::Cpu,
        4,
    )
    .unwrap();
    // The reference is the paper's crop: white outside the mask, then open_clip's resize.
    visual.set_crop_fill(CropFill::BeforeResize);
    let crops = reference["crops"].as_array().unwrap();
    let want = reference["image_embeds"].as_array().unwrap();
    let mut done = 0;
    for image_ref in sam_ref["images"].as_array().unwrap() {
        let name = image_ref["image"].as_str().unwrap();
        let img = load_rgb(&shared().join("scenes/snowmiku/images").join(name)).unwrap();
        let mut masks = Vec::new();
        let mut rows = Vec::new();
        for (i, c) in crops.iter().enumerate().filter(|(_, c)| c["image"] == name) {
            let k = c["mask_index"].as_u64().unwrap() as usize;
            let m = rle_to_mask(&image_ref["masks"][k]["rle"]);
            let bbox: Vec<u64> = f64s(&c["bbox_xywh"]).iter().map(|&v| v as u64).collect();
            assert_eq!(
                m.bbox_xywh.map(u64::from).to_vec(),
                bbox,
                "{name} mask {k}: bbox"
            );
            masks.push(m);
            rows.push(i);
        }
        if rows.first() == Some(&0) {
            // Preprocessing of the first crop: channel 0, row 112 (reference rounded to 1e-5).
            let mut px = vec![0f32; 3 * 224 * 224];
            clip_pixel_values(&crop(&img, &masks[0]).unwrap(), &mut px).unwrap();
            let row = f64s(&reference["pixel_values_first_crop_channel0_row112"]);
            let diffs: Vec<f64> = row
                .iter()
                .enumerate()
                .map(|(x, &v)| (f64::from(px[112 * 224 + x]) - v).abs())
                .collect();
            let max = diffs.iter().copied().fold(0.0, f64::max);
            let mean = diffs.iter().sum::<f64>() / diffs.len() as f64;
            eprintln!("pixel_values row 112: max |diff| {max:.5}, mean {mean:.6}");
            assert!(max < 2e-5, "row 112 differs: max {max}, mean {mean}");
        }
        let t = Instant::now();
        let embs = visual.embed_masks(&img, &masks).unwrap();
        eprintln!(
            "{name}: tiny-clip, {} crops (batch 4) in {:.3} s",
            masks.len(),
            t.elapsed().as_secs_f64()
        );
        for (e, &i) in embs.iter().zip(&rows) {
            assert_eq!(e.len(), 512);
            let n: f32 = e.iter().map(|v| v * v).sum::<f32>().sqrt();
            assert!((n - 1.0).abs() < 1e-5, "embedding must be L2-normalised");
            let cos = cosine(e, &f64s(&want[i]));
            eprintln!("crop {i}: cosine {cos:.6}");
            assert!(cos >= 0.999, "crop {i}: cosine {cos}");
            done += 1;
        }
    }
    assert_eq!(done, crops.len());
}

/// A tower with byte input (`tests/fixtures/color-clip-visual-u8.onnx`: `scripts/clip-u8-pixels.py`
/// on shared's color-clip image tower, CLIP's scaling and normalisation moved into the graph)
/// gives the embeddings of the f32 tower it came from, on
/// the crops of real masks, alone, with short batches padded and through the service; and it
/// keeps the f32 tower's CLIP pair id.
#[test]
fn u8_pixel_tower_gives_the_f32_towers_embeddings() {
    let Some(clip_dir) = ort_fixtures("clip") else {
        return;
    };
    let sam_ref = json(shared().join("fixtures/sam-amg/reference.json"));
    let image_ref = &sam_ref["images"][0];
    let img = load_rgb(
        &shared()
            .join("scenes/snowmiku/images")
            .join(image_ref["image"].as_str().unwrap()),
    )
    .unwrap();
    let masks: Vec<Mask> = image_ref["masks"]
        .as_array()
        .unwrap()
        .iter()
        .take(11)
        .map(|m| rle_to_mask(&m["rle"]))
        .collect();
    let f32_path = clip_dir.join("color-clip-visual.onnx");
    let u8_path = test_fixture("color-clip-visual-u8.onnx");
    let mut plain = ClipVisual::new(&f32_path, ExecutionProvider::Cpu, 4).unwrap();
    let mut bytes = ClipVisual::new(&u8_path, ExecutionProvider::Cpu, 4).unwrap();
    assert_eq!(plain.input(), VisualInput::F32PixelValues);
    assert_eq!(bytes.input(), VisualInput::U8Pixels);
    assert_eq!(bytes.model_id(), plain.model_id());
    let want = plain.embed_masks(&img, &masks).unwrap();
    bytes.set_fixed_batch(true); // 11 crops: the last batch of 3 is padded to 4
    let got = bytes.embed_masks(&img, &masks).unwrap();
    let service = ClipVisual::new(&u8_path, ExecutionProvider::Cpu, 4)
        .unwrap()
        .into_service()
        .unwrap();
    let served = service.handle().embed_masks(&img, &masks).unwrap();
    assert_eq!(want.len(), masks.len());
    let max_diff = |a: &[Vec<f32>], b: &[Vec<f32>]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| max_abs_difference(x, y))
            .fold(0f32, f32::max)
    };
    // Crops that differ give different embeddings, so equal rows are not a constant answer.
    assert!(max_diff(&want[..1], &want[1..2]) > 1e-3);
    for (what, rows) in [("alone, padded", &got), ("through the service", &served)] {
        assert_eq!(rows.len(), want.len(), "{what}");
        let d = max_diff(&want, rows);
        assert!(d <= 1e-6, "{what}: max |Δ| {d}");
    }
}

#[test]
fn clip_text_reproduces_open_clip_tokens_and_embeddings() {
    let Some(clip_dir) = ort_fixtures("clip") else {
        return;
    };
    let reference = json(clip_dir.join("reference.json"));
    let mut text = TextEncoder::new(
        &clip_dir.join("tiny-clip-textual.onnx"),
        &clip_dir.join("clip-tokenizer.json"),
        ExecutionProvider::Cpu,
    )
    .unwrap();
    let texts = Vec::<&str>::deserialize(&reference["texts"]).unwrap();
    let ids = text.tokenize(&texts).unwrap();
    for (i, row) in ids.iter().enumerate() {
        let want = Vec::<i64>::deserialize(&reference["input_ids"][i]).unwrap();
        assert_eq!(row, &want, "token ids of {:?}", texts[i]);
    }
    let embs = text.encode(&texts).unwrap();
    for (i, e) in embs.iter().enumerate() {
        let cos = cosine(e, &f64s(&reference["text_embeds"][i]));
        assert!(cos >= 0.999, "text {:?}: cosine {cos}", texts[i]);
    }
    // Cached prompts come back identical, mixed with new ones in order.
    assert_eq!(text.cached(), texts.len());
    let again = text.encode(&[texts[2], "a new prompt", texts[0]]).unwrap();
    assert_eq!(again[0], embs[2]);
    assert_eq!(again[2], embs[0]);
    assert_eq!(text.cached(), texts.len() + 1);

    // Truncation keeps <|endoftext|> last.
    let long = "word ".repeat(100);
    let ids = text.tokenize(&[long.as_str()]).unwrap();
    assert_eq!(ids[0].len(), 77);
    assert_eq!(ids[0][0], 49406);
    assert_eq!(ids[0][76], 49407);
    assert!(ids[0][1..76].iter().all(|&t| t != 0 && t != 49407));
}

#[test]
fn color_clip_red_crop_is_closest_to_red() {
    let Some(clip_dir) = ort_fixtures("clip") else {
        return;
    };
    let meta = json(clip_dir.join("color-clip.json"));
    let classes = Vec::<&str>::deserialize(&meta["classes"]).unwrap();
    let mut text = TextEncoder::new(
        &clip_dir.join("color-clip-textual.onnx"),
        &clip_dir.join("clip-tokenizer.json"),
        ExecutionProvider::Cpu,
    )
    .unwrap();
    let words = text.encode(&classes).unwrap();
    let mut visual = ClipVisual::new(
        &clip_dir.join("color-clip-visual.onnx"),
        ExecutionProvider::Cpu,
        8,
    )
    .unwrap();
    // A pure red object in a grey image, plus pure green and blue ones.
    let img = image::RgbImage::from_fn(64, 48, |x, _| match x / 16 {
        0 => image::Rgb([255, 0, 0]),
        1 => image::Rgb([0, 160, 40]),
        2 => image::Rgb([20, 40, 210]),
        _ => image::Rgb([128, 128, 128]),
    });
    let strip = |k: u32| {
        Mask::from_pixels(
            64,
            48,
            (0..64 * 48).map(|i| u8::from((i % 64) / 16 == k)).collect(),
        )
        .unwrap()
    };
    let masks = [strip(0), strip(1), strip(2)];
    let t = Instant::now();
    let embs = visual.embed_masks(&img, &masks).unwrap();
    eprintln!("color-clip: 3 crops in {:.3} s", t.elapsed().as_secs_f64());
    for (e, expected) in embs.iter().zip(["red", "green", "blue"]) {
        let scores: Vec<f32> = words
            .iter()
            .map(|w| w.iter().zip(e).map(|(a, b)| a * b).sum())
            .collect();
        let best = (0..scores.len())
            .max_by(|&a, &b| scores[a].total_cmp(&scores[b]))
            .unwrap();
        assert_eq!(classes[best], expected, "scores {scores:?}");
    }
}

/// `err` is an [`Error::Model`] whose message holds `part`.
fn assert_model_error(err: &Error, part: &str) {
    assert!(
        matches!(err, Error::Model { message, .. } if message.contains(part)),
        "{err}"
    );
}

#[test]
fn clip_rejects_wrong_models_and_bad_batches() {
    let Some(clip_dir) = ort_fixtures("clip") else {
        return;
    };
    let visual = |model: &str, ep, batch| ClipVisual::new(&clip_dir.join(model), ep, batch);
    // The error of a text encoder from (model, tokenizer), which must fail.
    let text_refused = |model: &str, tokenizer: &str| {
        let (m, t) = (clip_dir.join(model), clip_dir.join(tokenizer));
        let text = TextEncoder::new(&m, &t, ExecutionProvider::Cpu);
        text.err()
            .unwrap_or_else(|| panic!("{model} with {tokenizer} must be refused"))
    };
    let err = visual("tiny-clip-textual.onnx", ExecutionProvider::Cpu, 4)
        .err()
        .expect("a text tower is not a visual tower");
    assert_model_error(&err, "found inputs [input_ids: i64[?,77]]");
    // A visual tower is not a text tower.
    let err = text_refused("tiny-clip-visual.onnx", "clip-tokenizer.json");
    assert_model_error(&err, "CLIP text tower");
    // A model card is not a tokenizer.
    let err = text_refused("tiny-clip-textual.onnx", "color-clip.json");
    assert!(matches!(err, Error::Format { .. }), "{err}");
    assert!(matches!(
        visual("tiny-clip-visual.onnx", ExecutionProvider::Cpu, 0),
        Err(Error::Param {
            name: "clip_batch",
            ..
        })
    ));

    // CUDA on a runtime without it: a typed error, not a silent CPU fallback.
    if !slag_common::onnx::cuda_available().unwrap() {
        let err = visual("tiny-clip-visual.onnx", ExecutionProvider::Cuda, 4)
            .err()
            .expect("CUDA is not available in this ONNX Runtime");
        let Error::Inference {
            provider,
            device,
            message,
            remedy,
            ..
        } = &err
        else {
            panic!("expected Error::Inference, got {err}")
        };
        assert_eq!((provider.as_str(), device.as_str()), ("cuda", "cuda:0"));
        assert!(message.contains("built without it"), "{message}");
        assert!(remedy.contains("setup.sh --gpu"), "{remedy}");
        // `--ep auto` on the same runtime falls back to the CPU and says so (once).
        let auto = visual("tiny-clip-visual.onnx", ExecutionProvider::Auto, 4).unwrap();
        assert_eq!(auto.provider(), ExecutionProvider::Cpu);
        assert_eq!(auto.device_label(), "cpu");
    }
}

/// One CLIP service shared by several front workers (threads) returns, for every worker, exactly
/// the rows a private tower gives for its crops, in order (runs may hold crops of several
/// requests; how many share a run depends on timing and is printed). Both tower inputs: an f32
/// tower (the fronts normalise their crops) and a byte tower (the fronts send bytes).
#[test]
fn clip_service_batches_across_workers_and_returns_each_its_own_rows() {
    let Some(clip_dir) = ort_fixtures("clip") else {
        return;
    };
    let u8_model = test_fixture("color-clip-visual-u8.onnx");
    for model in [clip_dir.join("color-clip-visual.onnx"), u8_model] {
        service_returns_each_worker_its_rows(&model);
    }
}

fn service_returns_each_worker_its_rows(model: &std::path::Path) {
    let img = image::RgbImage::from_fn(64, 48, |x, y| {
        image::Rgb([(x * 4) as u8, (y * 5) as u8, ((x + y) * 2) as u8])
    });
    // Masks of different sizes and places: 3 to 9 per request.
    let masks_of = |seed: u32| -> Vec<Mask> {
        (0..3 + seed % 7)
            .map(|k| {
                let (x0, y0) = ((seed * 7 + k * 5) % 50, (seed * 3 + k * 7) % 36);
                let px = (0..64 * 48)
                    .map(|i| {
                        let (x, y) = (i % 64, i / 64);
                        u8::from(x >= x0 && x < x0 + 10 && y >= y0 && y < y0 + 8)
                    })
                    .collect();
                Mask::from_pixels(64, 48, px).unwrap()
            })
            .collect()
    };
    let mut direct = ClipVisual::new(model, ExecutionProvider::Cpu, 64).unwrap();
    // The service pads every run to its batch size, as it does on a GPU (one input shape for
    // the whole encode); the padded rows must not change the real ones.
    let mut padded = ClipVisual::new(model, ExecutionProvider::Cpu, 64).unwrap();
    padded.set_fixed_batch(true);
    let service = padded.into_service().unwrap();
    let requests = 24u32;
    std::thread::scope(|s| {
        let hs: Vec<_> = (0..4u32)
            .map(|w| {
                let h = service.handle();
                let img = &img;
                s.spawn(move || {
                    (0..requests / 4)
                        .map(|r| {
                            let seed = w * 100 + r;
                            (seed, h.embed_masks(img, &masks_of(seed)).unwrap())
                        })
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        for h in hs {
            for (seed, rows) in h.join().unwrap() {
                let want = direct.embed_masks(&img, &masks_of(seed)).unwrap();
                assert_eq!(rows.len(), want.len());
                for (a, b) in rows.iter().zip(&want) {
                    let d = max_abs_difference(a, b);
                    assert!(d < 1e-5, "request {seed}: max |diff| {d}");
                }
            }
        }
    });
    let st = service.stats();
    eprintln!(
        "CLIP service ({:?}): {} runs for {requests} requests, {} crops",
        direct.input(),
        st.runs,
        st.crops
    );
    assert_eq!(
        st.crops,
        (0..4u32)
            .flat_map(|w| (0..requests / 4).map(move |r| u64::from(3 + (w * 100 + r) % 7)))
            .sum::<u64>()
    );
}
