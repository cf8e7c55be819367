//! A crash at every durability boundary of `slag-shards partition` ([`slag_common::fault`]): a
//! store holds generation A of a scene (dense, synthetic) and the leftovers of a partition
//! stopped before its commit; re-partitioning it as generation B
//! (a mixture of other Gaussians: shards and a codebook, with `--report`) is stopped at boundary
//! n for every n = 1..=N, N counted by one run under `SLAG_FAULT_LIST`. After each stop
//! `slag-shards serve` on the store serves exactly A's manifest and bytes or exactly B's, never a
//! mix and never nothing, and one re-run of the partition commits B.
#![allow(clippy::unwrap_used)]

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use slag_common::fault::{EXIT_AT_VAR, FAULT_EXIT_STATUS, LIST_VAR, read_list, stopped_at};
use slag_common::mixture::{MixtureEmbeddings, SparseMixture};
use slag_common::rng::SplitMix64;
use slag_common::shards::Manifest;
use slag_common::testing::{copy_dir, served_address};

const SCENE: &str = "crash";

/// `slag-shards ARGS`, without the fault variables of the test's own environment.
fn slag_shards(args: &[&str]) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_slag-shards"));
    c.args(args)
        .env("RUST_LOG", "error")
        .env_remove(EXIT_AT_VAR)
        .env_remove(LIST_VAR);
    c
}

/// A mixture of `n` Gaussians on a ground grid over 6 codebook rows of width 8, each Gaussian
/// mixing one to three rows.
fn mixture(n: usize) -> MixtureEmbeddings {
    let mut r = SplitMix64::new(11);
    let (m, dim) = (6, 8);
    let codebook: Vec<f32> = (0..m * dim).map(|_| r.range(-1.0, 1.0) as f32).collect();
    let mut parts = SparseMixture {
        dim,
        model_id: "synthetic".into(),
        codebook,
        gaussian_ids: (0..n as u32).collect(),
        means: (0..n)
            .map(|i| [(i % 20) as f32 * 3.0, (i / 20) as f32 * 3.0, 0.5])
            .collect(),
        offsets: vec![0],
        ..Default::default()
    };
    for i in 0..n {
        for t in 0..1 + i % 3 {
            parts.atoms.push(((i + 2 * t) % m) as u32);
            parts.weights.push(r.range(0.2, 1.0) as f32);
        }
        parts.offsets.push(parts.atoms.len());
    }
    MixtureEmbeddings::from_sparse(parts).unwrap()
}

/// What a shard server serves for the scene: its manifest (generation aside) and the bytes of
/// every tile and of the codebook, by id; and the manifest's generation.
#[derive(Debug, PartialEq)]
struct Served {
    manifest: serde_json::Value,
    files: BTreeMap<String, Vec<u8>>,
}

/// Starts `slag-shards serve` on `store`, reads everything it serves for the scene, stops it.
fn served(store: &Path) -> (u64, Served) {
    let store_s = store.display().to_string();
    let mut child = slag_shards(&["serve", "--shard-store", &store_s, "--listen", "127.0.0.1:0"])
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap();
    let base = format!("http://{}/v1/scenes", served_address(&mut child));
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let get = |path: String| {
        rt.block_on(async {
            let r = reqwest::get(format!("{base}/{SCENE}/{path}"))
                .await
                .unwrap();
            let status = r.status().as_u16();
            let body = r.bytes().await.unwrap().to_vec();
            assert_eq!(status, 200, "{path}: {}", String::from_utf8_lossy(&body));
            body
        })
    };
    let body = get("manifest".into());
    let m = Manifest::from_json(&body, "served manifest").unwrap();
    let mut files = BTreeMap::new();
    for t in &m.tiles {
        files.insert(format!("shard {}", t.id), get(format!("shards/{}", t.id)));
    }
    if m.mixture.is_some() {
        files.insert("codebook".into(), get("codebook".into()));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let mut manifest: serde_json::Value = serde_json::from_slice(&body).unwrap();
    manifest["generation"] = serde_json::Value::Null;
    (m.generation, Served { manifest, files })
}

fn assert_success(out: &std::process::Output, what: &str) {
    assert!(
        out.status.success(),
        "{what}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn a_partition_stopped_at_every_boundary_serves_a_or_b_and_a_rerun_commits_b() {
    let tmp = tempfile::tempdir().unwrap();
    let template = tmp.path().join("a");
    let t = template.display().to_string();
    let a_args = [
        "partition",
        "--synthetic",
        "240:8",
        "--shard-store",
        &t,
        "--scene",
        SCENE,
    ];
    let out = slag_shards(&[&a_args[..], &["--max-per-shard", "60"]].concat())
        .output()
        .unwrap();
    assert_success(&out, "partition A");
    let mix = tmp.path().join("mixture.safetensors");
    mixture(200).write(&mix).unwrap();
    let report = tmp.path().join("report.json");
    let (mix_s, report_s) = (mix.display().to_string(), report.display().to_string());
    let partition_b = |store: &Path| {
        let store = store.display().to_string();
        let args = [
            "partition",
            "--embeddings",
            &mix_s,
            "--up",
            "z",
            "--max-per-shard",
            "50",
            "--report",
            &report_s,
            "--shard-store",
            &store,
            "--scene",
            SCENE,
        ];
        slag_shards(&args)
    };
    // A partition stopped once its shards are flushed, before its commit, leaves an uncommitted
    // generation behind, which the next writer removes first. Where that is: a counting run.
    let first = tmp.path().join("first.txt");
    let plain = tmp.path().join("plain");
    copy_dir(&template, &plain);
    let mut c = partition_b(&plain);
    c.env(LIST_VAR, &first);
    assert_success(&c.output().unwrap(), "first counting run");
    let flushed = read_list(&first).unwrap();
    let flushed = 1 + flushed
        .iter()
        .position(|n| n == "shards.commit:flush_codebooks")
        .unwrap_or_else(|| panic!("{flushed:?}"));
    let mut left = partition_b(&template);
    left.env(EXIT_AT_VAR, flushed.to_string());
    let out = left.output().unwrap();
    assert_eq!(out.status.code(), Some(FAULT_EXIT_STATUS));
    let (gen_a, ref_a) = served(&template);
    // Count, and B's reference: the counting run's store.
    let list = tmp.path().join("boundaries.txt");
    let counted: PathBuf = tmp.path().join("count");
    copy_dir(&template, &counted);
    let mut c = partition_b(&counted);
    c.env(LIST_VAR, &list);
    assert_success(&c.output().unwrap(), "counting run");
    let (gen_b, ref_b) = served(&counted);
    assert_ne!(ref_a, ref_b);
    assert!(gen_b > gen_a);
    let listed = read_list(&list).unwrap();
    assert!(listed.len() > 10, "{listed:?}");
    let (mut served_a, mut served_b) = (0, 0);
    let mut names = BTreeSet::new();
    for n in 1..=listed.len() {
        let dir = tmp.path().join(format!("run{n}"));
        copy_dir(&template, &dir);
        let mut stopped = partition_b(&dir);
        stopped.env(EXIT_AT_VAR, n.to_string());
        let out = stopped.output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(FAULT_EXIT_STATUS), "n={n}: {err}");
        let name = stopped_at(&err).unwrap_or_else(|| panic!("n={n}: {err}"));
        assert_eq!(name, listed[n - 1], "n={n}");
        let (g, now) = served(&dir);
        if now == ref_a {
            assert_eq!(g, gen_a, "n={n} ({name})");
            served_a += 1;
        } else {
            assert!(now == ref_b, "n={n} ({name}): neither A nor B is served");
            assert_eq!(g, gen_b, "n={n} ({name})");
            served_b += 1;
        }
        names.insert(name.clone());
        assert_success(
            &partition_b(&dir).output().unwrap(),
            &format!("n={n}: re-run"),
        );
        let (g, after) = served(&dir);
        assert!(
            after == ref_b && g >= gen_b,
            "n={n} ({name}): the re-run did not commit B"
        );
    }
    println!(
        "crash points of slag-shards partition: {} stopped ({} distinct names); A served {served_a} \
         times, B {served_b} times, mixed or lost 0",
        listed.len(),
        names.len()
    );
    for n in &names {
        println!("  {n}");
    }
    assert!(served_a > 0 && served_b > 0);
    for must in [
        "shards.writer:remove_leftover",
        "shards.put_shard:insert",
        "shards.put_codebook:insert",
        "shards.commit:transaction",
        "shards.commit:remove_old",
        "io.write_atomic:rename",
    ] {
        assert!(names.contains(must), "{must} never reached: {listed:?}");
    }
}
