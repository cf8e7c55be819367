//! The `slag-encoder` command line: one module per subcommand. `main.rs` only dispatches.

pub mod cluster;
pub mod encode;
pub mod eval;
pub mod query;
pub mod render;
pub mod synthetic;

/// `--ep`: ONNX Runtime execution provider, the same value type in every binary.
pub use slag_common::onnx::ExecutionProvider as EpArg;

pub use slag_shards::cli::init_logging;

/// What the user can turn on the command line when `e` (or an error it wraps) is a resource
/// limit of the weight rasterizer: the library names the limit ([`slag_common::Error::Limit`]),
/// the command line names the flag.
pub fn hint(e: &anyhow::Error) -> Option<&'static str> {
    use slag_common::{Error, Resource};
    e.chain().find_map(|c| match c.downcast_ref::<Error>() {
        Some(Error::Limit { resource, .. }) => Some(match resource {
            Resource::GpuBinding
            | Resource::GpuDispatch
            | Resource::GpuMemory
            | Resource::RasterEntries => {
                "lower --raster-scale (fewer pixels per view), or add GPU memory"
            }
        }),
        _ => None,
    })
}

#[cfg(test)]
mod tests {
    use super::hint;
    use slag_common::{Error, Resource};

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
}
