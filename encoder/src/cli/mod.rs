//! The `slag-encoder` command line: one module per subcommand, each turning its flags into the
//! library's typed configuration and calling it. `main.rs` only dispatches.

pub mod cluster;
pub mod encode;
pub mod encode_args;
pub mod eval;
pub mod query;
pub mod render;
pub mod synthetic;

/// `--ep`: ONNX Runtime execution provider, the same value type in every binary.
pub use slag_common::onnx::ExecutionProvider as EpArg;

pub use slag_shards::cli::init_logging;

/// What the user can change on the command line when `e` (or an error it wraps) is a resource
/// limit of the weight rasterizer or an encode setting that cannot run: the library names the
/// limit ([`slag_common::Error::Limit`]) or the setting ([`ConfigError`]), the command line
/// names the flag.
pub fn hint(e: &anyhow::Error) -> Option<&'static str> {
    use slag_common::{Error, Resource};
    e.chain().find_map(|c| {
        if let Some(c) = c.downcast_ref::<ConfigError>() {
            return Some(config_hint(c));
        }
        match c.downcast_ref::<Error>() {
            Some(Error::Limit { resource, .. }) => Some(match resource {
                Resource::GpuBinding
                | Resource::GpuDispatch
                | Resource::GpuMemory
                | Resource::RasterEntries => {
                    "lower --raster-scale (fewer pixels per view), or add GPU memory"
                }
            }),
            _ => None,
        }
    })
}

use slag_encoder::config::{ClusterUnsupported, ConfigError, Field};

/// The flags behind a [`ConfigError`].
fn config_hint(e: &ConfigError) -> &'static str {
    match e {
        ConfigError::Missing { field } | ConfigError::NotPositive { field } => match field {
            Field::SceneDir => "pass --scene DIR",
            Field::ClipVisual => "pass --clip-visual CLIP_VISUAL.onnx",
            Field::OutputDir => "pass --out DIR",
            Field::SamEncoder | Field::SamDecoder => {
                "pass --sam-encoder and --sam-decoder, or use --masks graph"
            }
            Field::MixtureKeep => "pass --mixture-keep S with S >= 1",
            Field::Gpus => "pass --gpus N with N >= 1, or --gpus all",
            _ => "see slag-encoder encode --help",
        },
        ConfigError::LevelsNeedSam => "use --masks sam, or drop --levels",
        ConfigError::ClusterUnsupported(ClusterUnsupported::Mixture) => {
            "drop --mixture-keep, or run `slag-encoder encode --mixture-keep S` on one machine"
        }
        ConfigError::ClusterUnsupported(ClusterUnsupported::Levels) => {
            "drop --levels, or run `slag-encoder encode --levels` on one machine"
        }
        ConfigError::ClusterUnsupported(_) => {
            "drop --gpus / --front-workers and start one process per GPU (one line each in \
             --hosts)"
        }
        _ => "see slag-encoder encode --help",
    }
}

#[cfg(test)]
mod tests {
    use super::hint;
    use slag_common::{Error, Resource};
    use slag_encoder::config::{ConfigError, Field};

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
    fn config_errors_get_their_flags() {
        let e = anyhow::Error::new(ConfigError::Missing {
            field: Field::SamEncoder,
        });
        assert!(!format!("{e:#}").contains("--"), "{e:#}");
        assert!(hint(&e).is_some_and(|h| h.contains("--sam-encoder")));
        let e = anyhow::Error::new(ConfigError::LevelsNeedSam).context("encode");
        assert!(hint(&e).is_some_and(|h| h.contains("--levels") && h.contains("--masks sam")));
    }
}
