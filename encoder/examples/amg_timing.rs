use slag_common::onnx::ExecutionProvider;
use slag_encoder::masks::MaskGenerator;
use slag_encoder::masks::sam::{SamAutomaticMaskGenerator, SamParams};
fn main() {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .init();
    let dir = std::path::Path::new("/work/shared/fixtures/sam-amg");
    let params = SamParams {
        pred_iou_thresh: 0.8,
        stability_score_thresh: 0.5,
        ..SamParams::default()
    };
    let mut sam = SamAutomaticMaskGenerator::new(
        &dir.join("color-sam-encoder.onnx"),
        &dir.join("color-sam-decoder.onnx"),
        ExecutionProvider::Cpu,
        0,
        params,
    )
    .unwrap();
    let imgs = std::env::args().skip(1).collect::<Vec<_>>();
    for p in imgs {
        let img = slag_encoder::preprocess::load_rgb(std::path::Path::new(&p)).unwrap();
        for _ in 0..2 {
            let t = std::time::Instant::now();
            let m = sam.generate(&img).unwrap();
            let s: u64 = m.iter().map(|m| m.area as u64).sum();
            println!(
                "{p}: {} masks area {s} in {:.3} s",
                m.len(),
                t.elapsed().as_secs_f64()
            );
            extra(&img, &m);
            pre(&img);
        }
    }
}
#[allow(dead_code)]
fn extra(img: &image::RgbImage, m: &[slag_encoder::masks::Mask]) {
    let t = std::time::Instant::now();
    let c = slag_encoder::masks::compact::compact_all(m);
    println!("compact {:.3} s ({})", t.elapsed().as_secs_f64(), c.len());
    let t = std::time::Instant::now();
    let p = slag_encoder::clip::crop_pixels(img, m).unwrap();
    println!("crops {:.3} s ({})", t.elapsed().as_secs_f64(), p.len());
}
#[allow(dead_code)]
fn pre(img: &image::RgbImage) {
    let t = std::time::Instant::now();
    let p = slag_encoder::preprocess::sam_pixel_values(img).unwrap();
    println!(
        "sam_pixel_values {:.3} s ({})",
        t.elapsed().as_secs_f64(),
        p.0.len()
    );
}
