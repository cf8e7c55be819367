//! sled shard store: commit/read round trip, generations, and interrupted writes (injected
//! failure and a child process killed mid-write) leaving the previous generation intact.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};

use slag_common::shards::synthetic::SyntheticScene;
use slag_common::shards::{Dtype, GroundFrame, Manifest, decode_shard, shard_checksum};
use slag_common::{Error, Result};
use slag_shards::partition::{PartitionParams, UpChoice, partition_with};
use slag_shards::store::{ShardStore, partition_into_store};

fn params(scene: &str, max: usize, dtype: Dtype) -> PartitionParams {
    PartitionParams {
        scene_id: scene.into(),
        max_per_shard: max,
        up: UpChoice::Given(GroundFrame::from_axis_name("z").expect("z")),
        dtype,
        to_map: None,
    }
}

/// Every tile of the current manifest has a shard whose bytes match size and checksum and that
/// decodes to the expected scene and count; returns the manifest.
fn assert_complete(store: &ShardStore, scene: &str) -> Manifest {
    let m = store.manifest(scene).expect("read").expect("committed");
    let mut total = 0;
    for t in &m.tiles {
        let b = store
            .shard(scene, t.id)
            .expect("read")
            .expect("shard present");
        assert_eq!(b.len() as u64, t.bytes);
        assert_eq!(format!("{:08x}", shard_checksum(&b)), t.checksum);
        let s = decode_shard(&b).expect("decodes");
        assert_eq!(s.header.scene_id, scene);
        assert_eq!(s.header.count as u64, t.count);
        assert_eq!(store.tile(scene, t.id).expect("tile").as_ref(), Some(t));
        total += t.count;
    }
    assert_eq!(total, m.total_gaussians);
    m
}

#[test]
fn commit_publishes_and_new_generations_replace_old_ones() {
    let dir = tempfile::tempdir().expect("tmp");
    let store = ShardStore::open(dir.path()).expect("open");
    assert_eq!(store.manifest("a").expect("read"), None);
    let s1 = SyntheticScene::new(2000, 8, 3, 50.0, 1);
    let m1 = partition_into_store(&store, &s1, &params("a", 300, Dtype::F16)).expect("v1");
    assert_eq!(m1.generation, 1);
    assert_eq!(assert_complete(&store, "a"), m1);
    let s2 = SyntheticScene::new(900, 8, 3, 50.0, 2);
    let m2 = partition_into_store(&store, &s2, &params("a", 100, Dtype::I8)).expect("v2");
    assert_eq!(m2.generation, 2);
    assert_eq!(assert_complete(&store, "a"), m2);
    assert_eq!(store.scenes().expect("scenes"), vec!["a".to_string()]);
    assert!(
        store
            .shard("a", m1.tiles.len() as u64 + 100)
            .expect("read")
            .is_none()
    );
    assert!(matches!(
        store.manifest("../x"),
        Err(Error::Param {
            name: "scene_id",
            ..
        })
    ));
}

#[test]
fn injected_failure_mid_partition_keeps_previous_generation() {
    let dir = tempfile::tempdir().expect("tmp");
    let store = ShardStore::open(dir.path()).expect("open");
    let s1 = SyntheticScene::new(1500, 8, 3, 50.0, 1);
    let m1 = partition_into_store(&store, &s1, &params("scene", 200, Dtype::F32)).expect("v1");
    // Second partition fails after 3 shards were written to the store.
    let s2 = SyntheticScene::new(1500, 8, 3, 50.0, 99);
    let mut w = store.writer("scene").expect("writer");
    let mut written = 0;
    let r: Result<Manifest> =
        partition_with(&s2, &params("scene", 100, Dtype::F32), |info, bytes| {
            if written == 3 {
                return Err(Error::Invalid("injected failure".into()));
            }
            w.put_shard(info.id, &bytes)?;
            written += 1;
            Ok(())
        });
    assert!(r.is_err());
    drop(w);
    assert_eq!(assert_complete(&store, "scene"), m1);
    // Leftovers of the unfinished generation exist but are invisible: shard 0 is still v1's.
    let b = store.shard("scene", 0).expect("read").expect("present");
    assert_eq!(format!("{:08x}", shard_checksum(&b)), m1.tiles[0].checksum);
    // The next writer discards the leftovers and commits normally.
    let m3 = partition_into_store(&store, &s2, &params("scene", 100, Dtype::F32))
        .expect("v after failure");
    assert_eq!(assert_complete(&store, "scene"), m3);
}

const CHILD_ENV: &str = "SLAG_SHARDS_KILL_CHILD_STORE";

/// Child half of `killed_writer_leaves_previous_generation_readable`: commits generation 1, then
/// writes part of generation 2, reports, and waits to be killed.
#[test]
#[ignore = "helper run as a child process by killed_writer_leaves_previous_generation_readable"]
fn child_writer_for_kill_test() {
    let Ok(path) = std::env::var(CHILD_ENV) else {
        return;
    };
    let store = ShardStore::open(std::path::Path::new(&path)).expect("open");
    let s1 = SyntheticScene::new(3000, 16, 4, 80.0, 5);
    let m1 = partition_into_store(&store, &s1, &params("kill", 250, Dtype::F16)).expect("v1");
    let s2 = SyntheticScene::new(3000, 16, 4, 80.0, 6);
    let mut w = store.writer("kill").expect("writer");
    let mut n = 0;
    let _ = partition_with(&s2, &params("kill", 100, Dtype::F16), |info, bytes| {
        w.put_shard(info.id, &bytes)?;
        n += 1;
        if n == 5 {
            store.flush()?;
            println!("READY {}", m1.tiles.len());
            std::thread::sleep(std::time::Duration::from_secs(120));
        }
        Ok(())
    });
}

#[test]
fn killed_writer_leaves_previous_generation_readable() {
    let dir = tempfile::tempdir().expect("tmp");
    let exe = std::env::current_exe().expect("exe");
    let mut child = Command::new(exe)
        .args([
            "--exact",
            "child_writer_for_kill_test",
            "--ignored",
            "--nocapture",
            "--test-threads=1",
        ])
        .env(CHILD_ENV, dir.path())
        .stdout(Stdio::piped())
        .spawn()
        .expect("spawn child");
    let stdout = child.stdout.take().expect("stdout");
    let mut tiles_v1 = None;
    for line in BufReader::new(stdout).lines() {
        let line = line.expect("line");
        // libtest prints "test <name> ... " on the same line before the test's own output.
        if let Some(at) = line.find("READY ") {
            tiles_v1 = line[at + 6..].trim().parse::<usize>().ok();
            break;
        }
    }
    child.kill().expect("SIGKILL the writer mid-partition");
    let _ = child.wait();
    let tiles_v1 = tiles_v1.expect("child reached the middle of generation 2");
    let store = ShardStore::open(dir.path()).expect("reopen after kill");
    // The killed writer did leave part of generation 2 behind, but generation 1 is current.
    assert_eq!(store.stored_generations("kill").expect("gens"), vec![1, 2]);
    assert_eq!(store.current_generation("kill").expect("current"), Some(1));
    let m = assert_complete(&store, "kill");
    assert_eq!(m.generation, 1);
    assert_eq!(m.tiles.len(), tiles_v1);
    assert_eq!(m.max_per_shard, 250);
    // And the store still accepts a new generation.
    let s3 = SyntheticScene::new(500, 16, 2, 80.0, 7);
    let m3 = partition_into_store(&store, &s3, &params("kill", 100, Dtype::I8)).expect("v2");
    assert_eq!(m3.generation, 2);
    assert_eq!(assert_complete(&store, "kill"), m3);
    assert_eq!(store.stored_generations("kill").expect("gens"), vec![2]);
}

/// A store closed in this process opens again at once, however long sled's flusher takes to
/// let go of its lock; a store that is still open elsewhere is refused with a typed error that
/// says it is in use, after a bounded wait.
#[test]
fn a_closed_store_reopens_and_one_in_use_is_refused() {
    let dir = tempfile::tempdir().expect("tmp");
    for round in 0..20 {
        let store = ShardStore::open(dir.path()).expect("open");
        let s = SyntheticScene::new(300, 8, 3, 50.0, round);
        partition_into_store(&store, &s, &params("a", 100, Dtype::F16)).expect("partition");
        drop(store);
    }
    let held = ShardStore::open(dir.path()).expect("open");
    let t0 = std::time::Instant::now();
    let e = ShardStore::open(dir.path()).err().expect("a second open while held");
    assert!(matches!(e, Error::Invalid(_)), "{e}");
    assert!(e.to_string().contains("in use"), "{e}");
    assert!(t0.elapsed() < std::time::Duration::from_secs(10), "bounded wait");
    drop(held);
}
