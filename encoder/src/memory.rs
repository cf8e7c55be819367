//! The process's resident memory in the debug log, stage by stage (target
//! `slag_encoder::memory`): where a long run's memory goes. The readings are
//! [`slag_common::util`]'s.

/// Logs the resident set size now as a debug line (target `slag_encoder::memory`) after `stage`
/// (nothing unless that target's debug log is on): where a long run's memory goes, stage by stage.
pub fn log_rss(stage: &str) {
    if tracing::enabled!(target: "slag_encoder::memory", tracing::Level::DEBUG) {
        let gib =
            slag_common::util::rss_bytes().map_or(f64::NAN, |b| b as f64 / f64::from(1u32 << 30));
        tracing::debug!(target: "slag_encoder::memory", stage, rss_gib = format!("{gib:.2}"), "resident memory");
    }
}
