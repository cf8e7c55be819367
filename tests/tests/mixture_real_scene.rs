//! `slag-encoder encode --mixture-keep S` on the embedded scene (data/snowmiku-mini, graph masks,
//! color-clip): with S above every Gaussian's number of non-zero `a_kj`, `mixture.safetensors`
//! reproduces the dense f32 `embeddings.safetensors` to f16 rounding, and the colour prompts score
//! the same.

#![allow(clippy::unwrap_used)]

use slag_common::embeddings::Embeddings;
use slag_common::mixture::MixtureEmbeddings;
use slag_common::similarity::{cosine_scores, max_abs_difference};
use slag_tests::{default_scene, encode, fixture, graph_config};

#[test]
fn mixture_keeping_every_atom_reproduces_the_dense_embeddings() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let mut config = graph_config(&default_scene(), &out);
    config.raster.scale = 0.25;
    config.output.precision = slag_common::embeddings::StoredPrecision::F32;
    config.aggregate.mixture_keep = Some(100_000);
    let report = encode(config).expect("encode");
    let dense = Embeddings::read(&out.join("embeddings.safetensors")).unwrap();
    let mix = MixtureEmbeddings::read(&out.join("mixture.safetensors")).unwrap();
    assert_eq!(mix.gaussian_ids, dense.ids);
    assert_eq!(mix.means, dense.means);
    assert_eq!(mix.dim, dense.dim);
    assert_eq!(mix.model_id, dense.model);
    assert!(mix.len() > 10_000, "{} observed", mix.len());
    // S was clamped to the most atoms any Gaussian has, and some Gaussian needs several.
    assert!(mix.keep > 1 && mix.keep < 100_000, "S = {}", mix.keep);
    let forms = report
        .outputs
        .forms
        .as_ref()
        .expect("encode writes the forms' section");
    assert_eq!(forms.mixture_keep, Some(mix.keep));
    assert_eq!(forms.mixture_codebook_rows, Some(mix.codebook_len()));
    assert!(mix.codebook_len() <= report.counts.masks);
    let recon = mix.to_dense();
    let max = max_abs_difference(&recon, &dense.vectors);
    assert!(max < 1e-3, "max |Δ| {max} beyond f16 rounding");
    // The colour prompts' scores agree too (color-clip text embeddings).
    let mut text = slag_common::text::TextEncoder::new(
        &fixture("clip/color-clip-textual.onnx"),
        &fixture("clip/clip-tokenizer.json"),
        Default::default(),
    )
    .unwrap();
    let prompts = text.encode(&["red", "pink", "gray", "black"]).unwrap();
    for q in &prompts {
        let a = mix.scores(q).unwrap();
        let b = cosine_scores(&dense.vectors, dense.dim, q).unwrap();
        let worst = max_abs_difference(&a, &b);
        assert!(worst < 2e-3, "score difference {worst}");
    }

    // A later run without the mixture (`--mixture-keep 0`) into the same folder leaves no stale
    // mixture behind.
    let mut config = graph_config(&default_scene(), &out);
    config.raster.scale = 0.25;
    config.scene.every = 13;
    config.aggregate.mixture_keep = None;
    let report = encode(config).expect("encode");
    assert!(!out.join("mixture.safetensors").exists());
    let forms = report
        .outputs
        .forms
        .as_ref()
        .expect("encode writes the forms' section");
    assert_eq!(forms.mixture, None);
}
