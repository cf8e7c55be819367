//! `slag-encoder encode` (and `bench`, which times the same run): flags → [`EncodeConfig`] →
//! [`Encoder`].

use slag_encoder::config::EncodeConfig;
use slag_encoder::pipeline::Encoder;
use slag_encoder::report::Report;

pub use slag_encoder::args::EncodeArgs;

/// Runs `encode` and returns the report it wrote.
///
/// Errors: the [`slag_encoder::config::ConfigError`] of a setting that cannot run, then the
/// run's ([`Encoder::run`]).
pub fn run(a: &EncodeArgs) -> anyhow::Result<Report> {
    Ok(Encoder::new(EncodeConfig::from(a))?.run()?)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use clap::Parser;
    use slag_encoder::config::{GpuCount, MaskSource, MasksConfig};

    use super::*;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: EncodeArgs,
    }

    fn parse(extra: &[&str]) -> EncodeConfig {
        let argv = [
            "encode",
            "--scene-dir",
            "s",
            "--clip-visual",
            "c.onnx",
            "--out",
            "o",
        ];
        match Cli::try_parse_from(argv.iter().chain(extra)) {
            Ok(c) => EncodeConfig::from(&c.args),
            Err(e) => panic!("arguments: {e}"),
        }
    }

    #[test]
    fn the_flags_defaults_are_the_librarys() {
        let c = parse(&["--sam-encoder", "e.onnx", "--sam-decoder", "d.onnx"]);
        let want = EncodeConfig {
            masks: MasksConfig::sam("e.onnx", "d.onnx"),
            ..EncodeConfig::new("s", "c.onnx", "o")
        };
        assert_eq!(c, want);
        assert_eq!(
            c.scene.views.mode,
            slag_encoder::views::SelectionMode::Coverage,
            "the views a scene needs by default"
        );
        let all = parse(&["--masks", "graph", "--views", "all"]);
        assert_eq!(
            all.scene.views.mode,
            slag_encoder::views::SelectionMode::All
        );
        assert_eq!(
            c.aggregate.mixture_keep,
            Some(slag_encoder::config::DEFAULT_MIXTURE_KEEP)
        );
        let dense = parse(&["--masks", "graph", "--mixture-keep", "0"]);
        assert_eq!(
            dense.aggregate.mixture_keep, None,
            "0: dense embeddings only"
        );
        assert!(
            dense.output.dense,
            "--mixture-keep 0 keeps writing the dense file"
        );
        assert!(dense.validate().is_ok());
        assert!(!c.output.dense, "the dense file is written only when asked");
        let both = parse(&["--masks", "graph", "--dense"]);
        assert!(both.output.dense);
        assert_eq!(
            both.aggregate.mixture_keep,
            Some(slag_encoder::config::DEFAULT_MIXTURE_KEEP),
            "--dense adds the dense file to the mixture"
        );
    }

    #[test]
    fn every_flag_reaches_its_field() {
        let c = parse(&[
            "--masks",
            "graph",
            "--ply",
            "p.ply",
            "--every",
            "3",
            "--graph-k",
            "700",
            "--graph-min-size",
            "90",
            "--sam-points-per-side",
            "8",
            "--sam-points-per-batch",
            "16",
            "--sam-pred-iou-thresh",
            "0.5",
            "--sam-stability-score-thresh",
            "0.6",
            "--sam-box-nms-thresh",
            "0.4",
            "--clip-batch",
            "7",
            "--raster-scale",
            "0.25",
            "--rasterizer",
            "cpu",
            "--ep",
            "cpu",
            "--gpu-mem-limit-gb",
            "2.5",
            "--threads",
            "3",
            "--gpus",
            "all",
            "--front-workers",
            "5",
            "--top-k-per-pixel",
            "4",
            "--mask-weighting",
            "area",
            "--overlap",
            "all",
            "--min-weight",
            "0.01",
            "--contribution-memory-mb",
            "10",
            "--accumulator-memory-mb",
            "20",
            "--precision",
            "f32",
            "--mixture-keep",
            "6",
            "--quiet",
            "--hold-out-every",
            "4",
            "--views",
            "coverage",
            "--view-count",
            "9",
            "--view-coverage-weight",
            "2.5",
            "--view-coverage-min-views",
            "3",
            "--view-coverage-angle",
            "15",
            "--view-coverage-target",
            "0.9",
            "--view-coverage-min-gain",
            "0.05",
            "--view-coverage-raster-scale",
            "0.125",
        ]);
        let v = &c.scene.views;
        assert_eq!(c.scene.hold_out_every, Some(4));
        assert_eq!(v.mode, slag_encoder::views::SelectionMode::Coverage);
        assert_eq!(v.count, Some(9));
        assert_eq!(
            v.coverage,
            slag_encoder::views::CoverageRule {
                min_weight: Some(2.5),
                min_views: 3,
                min_angle_deg: 15.0,
                target: 0.9,
                min_gain: 0.05,
                raster_scale: 0.125,
            }
        );
        assert_eq!(c.masks.source, MaskSource::Graph);
        assert_eq!(c.scene.ply.as_deref(), Some(std::path::Path::new("p.ply")));
        assert_eq!(c.scene.every, 3);
        assert_eq!(
            (c.masks.graph.k, c.masks.graph.min_size),
            (Some(700.0), Some(90))
        );
        let s = &c.masks.sam;
        assert_eq!((s.points_per_side, s.points_per_batch), (8, Some(16)));
        assert_eq!(
            (
                s.pred_iou_thresh,
                s.stability_score_thresh,
                s.box_nms_thresh
            ),
            (0.5, 0.6, 0.4)
        );
        assert_eq!(c.clip.batch, Some(7));
        assert_eq!(c.raster.scale, 0.25);
        assert_eq!(c.raster.backend, slag_encoder::config::RasterBackend::Cpu);
        let e = &c.execution;
        assert_eq!(e.ep, slag_common::onnx::ExecutionProvider::Cpu);
        assert_eq!(e.gpu_mem_limit_gb, Some(2.5));
        assert_eq!(
            (e.threads, e.gpus, e.front_workers),
            (Some(3), GpuCount::All, Some(5))
        );
        let a = &c.aggregate;
        assert_eq!(a.top_k_per_pixel, Some(4));
        assert_eq!(
            a.mask_weighting,
            slag_encoder::aggregate::MaskWeighting::Area
        );
        assert_eq!(a.overlap, slag_encoder::aggregate::MaskOverlap::All);
        assert_eq!(a.min_weight, 0.01);
        assert_eq!(
            (a.contribution_memory_mb, a.accumulator_memory_mb),
            (10, 20)
        );
        assert_eq!(a.mixture_keep, Some(6));
        assert!(!a.levels);
        assert_eq!(
            c.output.precision,
            slag_common::embeddings::StoredPrecision::F32
        );
        assert!(!c.output.progress);
        assert!(
            parse(&[
                "--masks",
                "sam",
                "--sam-encoder",
                "e",
                "--sam-decoder",
                "d",
                "--levels"
            ])
            .aggregate
            .levels
        );
    }
}
