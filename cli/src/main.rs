//! `slag-encoder`: give every Gaussian of a trained 3DGS scene a CLIP embedding (SLAG).
//!
//! Subcommands: `encode` (the Semantic Embedding stage), `encode-cluster` (the same over several
//! processes), `query` (check a prompt), `eval-colors`
//! (colour mIoU with color-clip), `render` (validate the rasterizer against a photo), `bench`
//! (per-stage timings), `partition` / `serve` / `export` (spatial shards), `synth-scene`
//! (synthetic scenes of any size).
//!
//! One module per subcommand, each turning its flags into the library's typed configuration
//! (`slag_encoder`, `slag_eval`, `slag_shards`) and calling it; `main` only dispatches.

use clap::{Parser, Subcommand};

mod cluster;
mod encode;
mod eval;
mod eval_objects;
mod hints;
mod query;
mod render;
mod segment;
mod synthetic;

/// `--ep`: ONNX Runtime execution provider, the same value type in every binary.
use slag_common::cli::EpArg;

/// slag-encoder: per-Gaussian CLIP embeddings for 3D Gaussian Splatting scenes (SLAG).
///
/// Typical run (models are any SAM / CLIP ONNX exports; see docs/guide/encoding.md):
///   slag-encoder encode --scene-dir SCENE --sam-encoder SAM_ENC.onnx --sam-decoder SAM_DEC.onnx
///       --clip-visual CLIP_VISUAL.onnx --out OUT
///   slag-encoder query --embeddings OUT/mixture.safetensors --clip-textual CLIP_TEXT.onnx
///       --tokenizer clip-tokenizer.json --text "a chair"
///
/// ONNX Runtime is loaded from $ORT_DYLIB_PATH (../shared/tools/install-onnxruntime.sh).
#[derive(Parser)]
#[command(version, about, long_about, verbatim_doc_comment)]
struct Cli {
    #[command(flatten)]
    global: slag_common::cli::process::GlobalArgs,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Embed a scene: masks -> CLIP crops -> weight raster -> aggregation -> mixture.safetensors
    /// (+ embeddings.safetensors with --dense), segments.safetensors, report.json.
    Encode(encode::EncodeArgs),
    /// `encode` as one process of a timely dataflow cluster (same arguments on every process).
    EncodeCluster(cluster::EncodeClusterArgs),
    /// Rank the Gaussians of an embeddings file against a text prompt.
    Query(query::QueryArgs),
    /// Colour mIoU of an embeddings file made with color-clip: per Gaussian (SH-DC colour truth),
    /// or with --held-out per pixel of the views the encoder never saw (photo colour truth).
    EvalColors(eval::EvalArgs),
    /// Instance AP50 and box IoU of query answers' objects on a `synth-scene --objects` scene,
    /// against the placed boxes.
    EvalObjects(eval_objects::EvalObjectsArgs),
    /// Render a training view through the weight rasterizer and compare it with the photo.
    Render(render::RenderArgs),
    /// Run `encode` and print a per-stage timing table.
    Bench(encode::EncodeArgs),
    /// Cut an embeddings file into spatial shards (ground-plane k-d tiles) in a sled store.
    Partition(slag_shards::cli::PartitionArgs),
    /// Serve a store's manifests and shards over HTTP (ETag, Range).
    Serve(slag_shards::cli::ServeArgs),
    /// Write a scene's manifest.json + shard files for any static host or object store.
    Export(slag_shards::cli::ExportArgs),
    /// Write a new Ed25519 key pair for signing manifests (--signing-key).
    Keygen(slag_shards::cli::KeygenArgs),
    /// Geometric segments of a scene's Gaussians (Felzenszwalb–Huttenlocher over a k-NN graph
    /// of the means; its edges also weigh the encode's masks when a masks' record is given or
    /// beside --out) -> segments.safetensors, without re-encoding.
    Segment(segment::SegmentCmdArgs),
    /// Write a synthetic terrain scene of any size (ply + images + COLMAP poses) for scale tests.
    SynthScene(synthetic::SynthArgs),
}

/// The embeddings file an encode wrote: the dense file when asked for, else the mixture.
fn written(r: &slag_encoder::report::Report) -> std::path::PathBuf {
    let mixture = r.outputs.forms.as_ref().and_then(|f| f.mixture.clone());
    r.outputs
        .embeddings
        .clone()
        .or(mixture)
        .unwrap_or_else(|| r.outputs.report.clone())
}

/// Where the encode's tail went, for its closing line: the reduction (on the GPU or the CPU),
/// the write, and the wait for the segments after it.
fn tail_summary(r: &slag_encoder::report::Report) -> String {
    let place = if r.counts.device_reduce { "GPU" } else { "CPU" };
    let mut s = format!(
        "reduce {:.1} s on the {place}, write {:.1} s",
        r.timings.reduce, r.timings.write
    );
    if let Some(f) = &r.counts.device_reduce_fallback {
        s.push_str(&format!(
            " (the GPU reduction gave way after {} views: {})",
            f.views_brought_back, f.reason
        ));
    }
    if let Some(seg) = &r.segments {
        s.push_str(&format!(", segments waited {:.1} s", seg.waited_s));
    }
    s
}

fn print_json<T: serde::Serialize>(v: &T) -> anyhow::Result<()> {
    println!("{}", serde_json::to_string_pretty(v)?);
    Ok(())
}

fn main() -> std::process::ExitCode {
    slag_common::cli::deprecated::note_deprecated();
    let args = Cli::parse();
    let verbose = args.global.verbose;
    slag_common::cli::process::init_logging(verbose);
    let result = match &args.command {
        Command::Encode(a) => encode::run(a).map(|r| {
            eprintln!(
                "encoded {} of {} Gaussians ({:.1}%) from {} views in {:.1} s ({}) -> {}",
                r.counts.observed,
                r.counts.gaussians,
                100.0 * r.counts.observed_fraction,
                r.counts.views_used,
                r.timings.total,
                tail_summary(&r),
                written(&r).display()
            );
        }),
        Command::EncodeCluster(a) => cluster::run(a).map(|r| match r {
            Some(r) => eprintln!(
                "encoded {} of {} Gaussians ({:.1}%) from {} views on {} processes in {:.1} s -> {}",
                r.counts.observed,
                r.counts.gaussians,
                100.0 * r.counts.observed_fraction,
                r.counts.views_used,
                r.parameters.cluster_processes.unwrap_or(0),
                r.timings.total,
                a.encode.out.join("embeddings.safetensors").display()
            ),
            None => eprintln!("process {}: job completed (process 0 wrote the outputs)", a.process),
        }),
        Command::Query(a) => query::run(a).and_then(|o| print_json(&o)),
        Command::EvalColors(a) if a.held_out => {
            slag_eval::colors::run_held_out(&a.into()).and_then(|o| print_json(&o))
        }
        Command::EvalColors(a) if a.prediction_filtering => {
            slag_eval::colors::run_pf(&a.into()).and_then(|o| print_json(&o))
        }
        Command::EvalColors(a) => {
            slag_eval::colors::run(&a.into()).and_then(|o| print_json(&o))
        }
        Command::EvalObjects(a) => eval_objects::run(a).and_then(|o| print_json(&o)),
        Command::Render(a) => render::run(a).and_then(|o| print_json(&o)),
        Command::Bench(a) => {
            encode::run(a).map(|r| println!("{}", slag_encoder::report::timing_table(&r)))
        }
        Command::Partition(a) => slag_shards::cli::run_partition(a),
        Command::Serve(a) => slag_shards::cli::run_serve(a),
        Command::Export(a) => slag_shards::cli::run_export(a),
        Command::Keygen(a) => slag_shards::cli::run_keygen(a),
        Command::SynthScene(a) => synthetic::run(a).and_then(|o| print_json(&o)),
        Command::Segment(a) => segment::run(a).and_then(|o| print_json(&o)),
    };
    slag_common::cli::process::exit_code(result, hints::hint, verbose)
}

#[cfg(test)]
mod flag_names {
    /// Every flag name of this binary, hidden aliases included, keeps one meaning across the slag
    /// binaries, and every meaning one name ([`slag_common::flag_names`]).
    #[test]
    fn each_flag_name_has_one_meaning_across_the_binaries() {
        use clap::CommandFactory;
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        slag_common::flag_names::assert_one_meaning("slag-encoder", &super::Cli::command(), &root);
    }
}
