//! The publisher's side of signed manifests through `slag-shards`: a private key that others
//! may read is refused unless `--allow-readable-key`, and `--start-generation` lets a re-created
//! store carry on above the generation the robots hold.
#![allow(clippy::unwrap_used)]

use std::path::Path;
use std::process::{Command, Output};

/// `slag-shards partition --synthetic 500:8 --scene syn --shard-store STORE` with `extra` flags.
fn partition(store: &Path, extra: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_slag-shards"))
        .args([
            "partition",
            "--synthetic",
            "500:8",
            "--scene",
            "syn",
            "--shard-store",
        ])
        .arg(store)
        .args(extra)
        .output()
        .unwrap()
}

/// The generation a successful partition printed.
fn generation(out: &Output) -> u64 {
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let rest = stdout.split(" generation ").nth(1).unwrap();
    rest.split(':').next().unwrap().trim().parse().unwrap()
}

#[cfg(unix)]
#[test]
fn a_signing_key_others_may_read_is_refused_unless_allowed() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let keys = slag_common::shards::signature::keygen(&dir.path().join("keys")).unwrap();
    std::fs::set_permissions(&keys.private, std::fs::Permissions::from_mode(0o644)).unwrap();
    let key = keys.private.display().to_string();
    let store = dir.path().join("store");
    let out = partition(&store, &["--signing-key", &key]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(
        stderr.contains("644") && stderr.contains("chmod 600"),
        "{stderr}"
    );
    assert!(stderr.contains("--allow-readable-key"), "{stderr}");
    assert!(generation_is_none(&store));
    let out = partition(&store, &["--signing-key", &key, "--allow-readable-key"]);
    assert_eq!(generation(&out), 1);
    std::fs::set_permissions(&keys.private, std::fs::Permissions::from_mode(0o600)).unwrap();
    assert_eq!(generation(&partition(&store, &["--signing-key", &key])), 2);
}

/// No generation of `syn` is committed in `store`.
fn generation_is_none(store: &Path) -> bool {
    let s = slag_shards::store::ShardStore::open(store).unwrap();
    s.current_generation("syn").unwrap().is_none()
}

#[test]
fn a_recreated_store_carries_on_from_the_start_generation() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    assert_eq!(
        generation(&partition(&store, &["--start-generation", "7"])),
        7
    );
    assert_eq!(generation(&partition(&store, &[])), 8);
    // Below the current generation it changes nothing: generations only go up.
    assert_eq!(
        generation(&partition(&store, &["--start-generation", "3"])),
        9
    );
    let out = partition(&store, &["--start-generation", "0"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && stderr.contains("start_generation"),
        "{stderr}"
    );
    assert_eq!(generation(&partition(&store, &[])), 10);
}
