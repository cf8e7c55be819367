//! What `slag-encoder` adds to a library error: the flag to turn. The library names the limit
//! ([`Error::Limit`]), the parameter by its library name ([`Error::Param`]`{ name, .. }`) or the
//! encode setting ([`ConfigError`]) and never a flag; this is the one place that maps them to the command line (`main.rs` prints the
//! result as `hint: …` under the error).

use slag_common::onnx::{InferenceCause, inference_cause};
use slag_common::{Error, Observation, Resource};
use slag_encoder::config::{ClusterUnsupported, ConfigError, Field};

/// The hint for `e` or the first error it wraps that has one.
pub fn hint(e: &anyhow::Error) -> Option<String> {
    e.chain().find_map(|c| {
        if let Some(c) = c.downcast_ref::<ConfigError>() {
            return Some(config_hint(c).to_string());
        }
        c.downcast_ref::<Error>().and_then(hint_for)
    })
}

/// The flags behind a [`ConfigError`].
fn config_hint(e: &ConfigError) -> &'static str {
    match e {
        ConfigError::Missing { field } | ConfigError::NotPositive { field } => match field {
            Field::SceneDir => "pass --scene-dir DIR",
            Field::ClipVisual => "pass --clip-visual CLIP_VISUAL.onnx",
            Field::OutputDir => "pass --out DIR",
            Field::SamEncoder | Field::SamDecoder => {
                "pass --sam-encoder and --sam-decoder, or use --masks graph"
            }
            Field::SamTimingEncoder | Field::SamTimingDecoder => {
                "pass both --sam-timing-encoder and --sam-timing-decoder, or neither"
            }
            Field::MixtureKeep => "pass --mixture-keep S with S >= 1",
            Field::Gpus => "pass --gpus N with N >= 1, or --gpus all",
            // `Field` is non_exhaustive: a setting added later.
            _ => "see slag-encoder encode --help",
        },
        ConfigError::LevelsNeedSam => {
            "--levels needs --masks sam; drop --levels with --masks graph"
        }
        ConfigError::NoEmbeddingsOutput => {
            "keep the mixture (--mixture-keep S with S >= 1, the default 4) or pass --dense"
        }
        ConfigError::ClusterUnsupported(ClusterUnsupported::Levels) => {
            "drop --levels, or run `slag-encoder encode --levels` on one machine"
        }
        // `ConfigError` is non_exhaustive: a case added later.
        _ => "see slag-encoder encode --help",
    }
}

/// The hint for one library error: the encoder's flags, then the shard subcommands'
/// ([`slag_shards::cli::hint_for`]).
pub fn hint_for(e: &Error) -> Option<String> {
    match e {
        Error::Limit { resource, .. } => match resource {
            Resource::GpuBinding
            | Resource::GpuDispatch
            | Resource::GpuMemory
            | Resource::RasterEntries
            | Resource::RasterPixels => {
                Some("lower --raster-scale (fewer pixels per view), or add GPU memory".into())
            }
            Resource::Memory
            | Resource::ShardGaussians
            | Resource::DiskSpace
            | Resource::ManifestBytes => slag_shards::cli::hint_for(e),
        },
        Error::Param { name, .. } => param_flag(name)
            .map(str::to_string)
            .or_else(|| slag_shards::cli::hint_for(e)),
        Error::Inference {
            message, provider, ..
        } => inference_hint(inference_cause(message), provider),
        Error::Internal(_) => {
            Some("rerun with --verbose and report the command and its log".into())
        }
        Error::Unobserved { stage, .. } => Some(unobserved_hint(*stage).into()),
        _ => slag_shards::cli::hint_for(e),
    }
}

/// The flag that sets the library parameter `name`, as a hint.
fn param_flag(name: &str) -> Option<&'static str> {
    Some(match name {
        "raster_scale" => "pass --raster-scale in (0, 4], e.g. 0.5",
        "gap" => "pass --object-gap D with D > 0 (scene units)",
        "min_gaussians" => "pass --object-min-gaussians N with N >= 1",
        "max_objects" => "pass --max-objects N in 1..=1000",
        "near" => "pass --near X,Y,Z",
        "objects" => "pass --objects K with K in 1..=6",
        "raster_size" => "raise --raster-scale (the raster is empty)",
        "every" => {
            "pass --every N to `encode` (and the same N to `eval-colors --held-out` as \
             --hold-out-every N; N >= 2 holds views out)"
        }
        "hold_out_every" => {
            "pass --hold-out-every N with N >= 2 (the same N to `eval-colors --held-out`)"
        }
        "view_count" => "pass --view-count N with N >= 1 (--views uniform needs it)",
        "view_coverage_weight" => "pass --view-coverage-weight W with W >= 0 (pixels)",
        "view_coverage_min_views" => "pass --view-coverage-min-views K in 1..=16",
        "view_coverage_angle" => "pass --view-coverage-angle in [0, 180) degrees",
        "view_coverage_target" => "pass --view-coverage-target in (0, 1]",
        "view_coverage_raster_scale" => "pass --view-coverage-raster-scale in (0, 4], e.g. 0.25",
        "scene" => {
            "pass --scene-dir DIR holding point_cloud.ply, images/ and sparse/0 or transforms.json"
        }
        "gpus" => "pass --gpus N (at most the GPUs listed)",
        "levels" => "--levels needs --masks sam; drop --levels with --masks graph",
        "mixture_keep" => "pass --mixture-keep S with S >= 1",
        "clip_batch" => "pass --clip-batch N with N >= 1",
        "points_per_side" => "pass --sam-points-per-side in 1..=1024",
        "points_per_batch" => "pass --sam-points-per-batch N with N >= 1",
        "pred_iou_thresh" => "pass --sam-pred-iou-thresh in [0, 1]",
        "stability_score_thresh" => "pass --sam-stability-score-thresh in [0, 1]",
        "box_nms_thresh" => "pass --sam-box-nms-thresh in [0, 1]",
        "graph_k" => "pass --graph-k K with K > 0",
        "precision" => "pass --precision f32",
        "color_clip" => "pass --color-clip DIR (or set SLAG_SHARED)",
        "ply" => "pass the .ply used by encode with --ply",
        "cluster_secret" => {
            "pass --cluster-secret-file FILE, the same file (mode 0600, at least 16 random bytes) \
             on every process"
        }
        _ => return None,
    })
}

/// The flags that let an encode's views observe the scene's Gaussians ([`Error::Unobserved`]).
fn unobserved_hint(stage: Observation) -> &'static str {
    match stage {
        Observation::CoveragePass => {
            "encode every view with --views all, lower the floor with --view-coverage-weight \
             (e.g. 0.01 pixels), or raise --view-coverage-raster-scale (e.g. 1); check that the \
             cameras look at the scene's Gaussians"
        }
        Observation::Encode => {
            "encode every view with --views all, or raise --raster-scale (e.g. 1) so that small \
             Gaussians reach a pixel; check that the cameras look at the scene's Gaussians and \
             that --scene-dir's images and point cloud belong together"
        }
    }
}

/// The flags that act on an ONNX Runtime failure of `cause` on `provider`; `None` where the
/// library's remedy is an install step, not a flag.
fn inference_hint(cause: InferenceCause, provider: &str) -> Option<String> {
    Some(match cause {
        InferenceCause::OutOfMemory => "lower --clip-batch or --sam-points-per-batch, or cap each \
                                        model's arena with --gpu-mem-limit-gb"
            .into(),
        InferenceCause::NoSuchDevice => {
            "pass --gpus N with at most the GPUs nvidia-smi lists".into()
        }
        InferenceCause::ProviderMissing if provider == "tensorrt" => "use --ep cuda".into(),
        InferenceCause::ProviderMissing => "use --ep cpu or --ep auto".into(),
        InferenceCause::Other => {
            "rerun with --ep cpu to tell a model fault from a GPU fault".into()
        }
        InferenceCause::MissingLibrary | InferenceCause::DriverMismatch => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::{hint, hint_for};
    use slag_common::{Error, Resource};
    use slag_encoder::config::{ConfigError, Field};

    #[test]
    fn config_errors_get_their_flags() {
        let e = anyhow::Error::new(ConfigError::Missing {
            field: Field::SamEncoder,
        });
        assert!(!format!("{e:#}").contains("--"), "{e:#}");
        assert!(hint(&e).is_some_and(|h| h.contains("--sam-encoder")));
        let e = anyhow::Error::new(ConfigError::LevelsNeedSam).context("encode");
        assert!(hint(&e).is_some_and(|h| h.contains("--levels") && h.contains("--masks sam")));
    }

    #[test]
    fn raster_limits_get_the_flag_other_errors_do_not() {
        let limit = anyhow::Error::new(Error::limit(Resource::GpuBinding, "300 MiB", "128 MiB"))
            .context("view 3");
        assert!(hint(&limit).is_some_and(|h| h.contains("--raster-scale")));
        let msg = format!("{limit:#}");
        assert!(
            !msg.contains("--"),
            "the library's message names no flag: {msg}"
        );
        assert!(msg.contains("300 MiB") && msg.contains("128 MiB"), "{msg}");
        assert_eq!(hint(&anyhow::Error::new(Error::Invalid("x".into()))), None);
        assert_eq!(hint(&anyhow::anyhow!("plain")), None);
    }

    #[test]
    fn every_raster_resource_and_the_raster_scale_parameter_name_the_flag() {
        for r in [
            Resource::GpuBinding,
            Resource::GpuDispatch,
            Resource::GpuMemory,
            Resource::RasterEntries,
            Resource::RasterPixels,
        ] {
            let h = hint_for(&Error::limit(r, "2.1 G entries", "2^32 - 1")).unwrap_or_default();
            assert!(h.contains("--raster-scale"), "{r:?}: {h}");
        }
        let p = Error::param("raster_scale", 5.0, "a value in (0, 4], e.g. 0.5");
        assert!(!p.to_string().contains("--"), "{p}");
        assert!(
            hint_for(&p).is_some_and(|h| h.contains("--raster-scale")),
            "{p}"
        );
        // Wrapped in context, as `main` sees it.
        let wrapped = anyhow::Error::new(p).context("encode");
        assert!(hint(&wrapped).is_some_and(|h| h.contains("--raster-scale")));
    }

    #[test]
    fn parameters_inference_failures_and_shard_errors_get_their_flags() {
        let h = |e: Error| hint_for(&e).unwrap_or_default();
        assert!(h(Error::param("every", 1, "2 or more")).contains("--every"));
        assert!(
            h(Error::param("points_per_batch", 0, "at least 1")).contains("--sam-points-per-batch")
        );
        assert!(h(Error::param("levels", true, "SAM masks")).contains("--masks sam"));
        // The shard subcommands' parameters, through slag_shards::cli::hint_for.
        assert!(h(Error::param("max_per_shard", 0, "at least 1")).contains("--max-per-shard"));
        assert!(
            h(Error::limit(Resource::ShardGaussians, 5e9, u32::MAX)).contains("--max-per-shard")
        );
        let oom = slag_common::onnx::remedy(
            slag_common::onnx::ExecutionProvider::Cuda,
            "CUDA failure 2: out of memory",
        );
        let e = Error::Inference {
            model: "m.onnx".into(),
            provider: "cuda".into(),
            device: "cuda:0".into(),
            message: "CUDA failure 2: out of memory".into(),
            remedy: oom.into(),
        };
        assert!(!e.to_string().contains("--"), "{e}");
        assert!(h(e).contains("--clip-batch"));
        assert!(h(Error::internal("panicked")).contains("--verbose"));
        assert_eq!(hint_for(&Error::param("no_such_parameter", 0, "x")), None);
    }

    #[test]
    fn an_encode_that_observes_nothing_names_the_flags_that_let_it() {
        for (stage, flag) in [
            (
                slag_common::Observation::CoveragePass,
                "--view-coverage-weight",
            ),
            (slag_common::Observation::Encode, "--raster-scale"),
        ] {
            let e = Error::Unobserved {
                stage,
                observed: 0,
                gaussians: 30_000_000,
                expected: "at least 1".into(),
            };
            assert!(!e.to_string().contains("--"), "{e}");
            assert!(e.is_user_input());
            let h = hint(&anyhow::Error::new(e).context("encode")).unwrap_or_default();
            assert!(
                h.contains(flag) && h.contains("--views all"),
                "{stage:?}: {h}"
            );
        }
    }
}
