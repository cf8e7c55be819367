//! `slag-encoder encode-cluster`: three worker processes of the built binary on loopback
//! (timely dataflow's TCP cluster) on the embedded mini scene, graph masks + color-clip, the
//! default outputs and the default view selection (coverage).
//!
//! 1. The cluster writes the files a single-process `slag-encoder encode --reduce host` of the
//!    same arguments writes (the mixture, the masks' record, the segments, the report), each
//!    byte-identical but the report, whose counts and chosen views agree.
//! 2. With a checkpoint after every view taken in (`--checkpoint-every 0.001`), one worker
//!    process dies right after writing its third checkpoint (`SLAG_FAULT_EXIT_AT`, exit 137
//!    without destructors or connection shutdown, as `kill -9`): every process exits non-zero
//!    within the timeout, the survivors with status 3 and a message naming the process that died,
//!    and OUT holds nothing that looks complete (no output file, only `.partial` names and the
//!    partitions' checkpoints). A rerun in the same OUT resumes from the checkpoints (the report
//!    says how many views each partition restored), matches the single-process run byte for byte
//!    and removes the checkpoints.
//! 3. With one process slowed down (`SLAG_TEST_MAP_DELAY_MS` before each view it maps) the
//!    views are handed out by work done: the slow process maps fewer views than each of the
//!    others, every view is mapped once, and the files are still byte-identical to `encode`'s.
//! 4. With `--front-workers 2 --threads 2` (each process runs the encode's worker pool: two
//!    front workers of one thread each, several views in flight) the files are still
//!    byte-identical to `encode`'s, every view is mapped once and every process maps views.
//! 5. With `--dense` the cluster's dense embeddings equal the single-process ones: the same
//!    observed Gaussian ids, vectors within 1e-6 (both stored as f32; the reductions run the same
//!    f64 code, only the order in which images are summed may differ), total weights within 1e-6
//!    relative; its mixture stays byte-identical.
#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::{Child, ExitStatus};
use std::time::{Duration, Instant};

use slag_common::embeddings::Embeddings;
use slag_common::similarity::max_abs_difference;

mod support;
use support::{assert_success, slag_encoder};

/// Exit status of a process that lost a peer (`slag_encoder::distributed::EXIT_PEER_LOST`).
const PEER_LOST: i32 = slag_encoder::distributed::EXIT_PEER_LOST;
const TIMEOUT: Duration = Duration::from_secs(180);

/// The encode arguments shared by every run: 7 of the 13 views (the coverage pass chooses among
/// them), raster scale 0.25, f32 output, the host's reduction, one thread unless `extra` (the
/// run's other arguments) sets `--threads`.
fn encode_args(out: &Path, extra: &[String]) -> Vec<String> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let fixtures = slag_common::paths::source_tree_shared_dir().join("fixtures");
    let mut a: Vec<String> = vec![
        "--scene-dir".into(),
        root.join("data/snowmiku-mini").display().to_string(),
    ];
    a.extend(["--masks", "graph", "--clip-visual"].map(String::from));
    a.push(
        fixtures
            .join("clip/color-clip-visual.onnx")
            .display()
            .to_string(),
    );
    a.extend(
        [
            "--every",
            "2",
            "--reduce",
            "host",
            "--raster-scale",
            "0.25",
            "--rasterizer",
            "cpu",
            "--precision",
            "f32",
            "--quiet",
        ]
        .map(String::from),
    );
    if !extra.iter().any(|a| a == "--threads") {
        a.extend(["--threads", "1"].map(String::from));
    }
    a.push("--out".into());
    a.push(out.display().to_string());
    a
}

/// Three free loopback ports in a host file.
fn hosts_file(dir: &Path, name: &str) -> PathBuf {
    let listeners: Vec<_> = (0..3)
        .map(|_| std::net::TcpListener::bind("127.0.0.1:0").unwrap())
        .collect();
    let text: String = listeners
        .iter()
        .map(|l| format!("127.0.0.1:{}\n", l.local_addr().unwrap().port()))
        .collect();
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

struct Proc {
    child: Child,
    log: PathBuf,
}

/// Starts process `i` of the cluster described by `hosts`, logging to `dir/<tag>-<i>.log`,
/// with `extra` arguments (a secret file).
fn spawn(
    i: usize,
    hosts: &Path,
    out: &Path,
    dir: &Path,
    tag: &str,
    fault: Option<u32>,
    extra: &[String],
) -> Proc {
    let fault = fault.map(|n| (FAULT_AFTER_IMAGES, n));
    spawn_with(i, hosts, (out, dir, tag), fault, extra)
}

/// The fault hook that stops a process after its n-th image.
const FAULT_AFTER_IMAGES: &str = "SLAG_FAULT_EXIT_AFTER_IMAGES";

/// [`spawn`] with any fault hook: `fault` is the variable and its value.
fn spawn_with(
    i: usize,
    hosts: &Path,
    (out, dir, tag): (&Path, &Path, &str),
    fault: Option<(&str, u32)>,
    extra: &[String],
) -> Proc {
    let log = dir.join(format!("{tag}-{i}.log"));
    let f = std::fs::File::create(&log).unwrap();
    let mut c = slag_encoder();
    c.args(["encode-cluster", "--process", &i.to_string(), "--hosts"])
        .arg(hosts)
        .args(["--connect-timeout", "120"])
        .args(extra)
        .args(encode_args(out, extra))
        // Spill every contribution and chunk the accumulator, as on a scene larger than memory.
        .args([
            "--contribution-memory-mb",
            "0",
            "--accumulator-memory-mb",
            "16",
        ])
        .env_remove(FAULT_AFTER_IMAGES)
        .env_remove(slag_common::fault::EXIT_AT_VAR)
        .env_remove(slag_encoder::distributed::MAP_DELAY_VAR)
        .env("RUST_LOG", "info")
        .stdout(f.try_clone().unwrap())
        .stderr(f);
    if let Some((var, n)) = fault {
        c.env(var, n.to_string());
    }
    Proc {
        child: c.spawn().unwrap(),
        log,
    }
}

/// Waits for every process (killing all on timeout); their statuses and logs.
fn wait_all(mut procs: Vec<Proc>) -> Vec<(ExitStatus, String)> {
    let t0 = Instant::now();
    let mut statuses: Vec<Option<ExitStatus>> = vec![None; procs.len()];
    while statuses.iter().any(Option::is_none) {
        for (p, s) in procs.iter_mut().zip(statuses.iter_mut()) {
            if s.is_none() {
                *s = p.child.try_wait().unwrap();
            }
        }
        if t0.elapsed() > TIMEOUT {
            for p in procs.iter_mut() {
                let _ = p.child.kill();
                let _ = p.child.wait();
            }
            let logs: Vec<String> = procs
                .iter()
                .map(|p| std::fs::read_to_string(&p.log).unwrap_or_default())
                .collect();
            panic!("cluster did not finish within {TIMEOUT:?}: {statuses:?}\n{logs:#?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    procs
        .iter()
        .zip(statuses)
        .map(|(p, s)| (s.unwrap(), std::fs::read_to_string(&p.log).unwrap()))
        .collect()
}

fn run_cluster(
    hosts: &Path,
    out: &Path,
    dir: &Path,
    tag: &str,
    fault: Option<(usize, &str, u32)>,
    extra: &[String],
) -> Vec<(ExitStatus, String)> {
    let procs = (0..3)
        .map(|i| {
            let fault = fault.filter(|f| f.0 == i).map(|f| (f.1, f.2));
            spawn_with(i, hosts, (out, dir, tag), fault, extra)
        })
        .collect();
    wait_all(procs)
}

/// A single-process `encode` of [`encode_args`] and `extra` into `out`.
fn run_single(out: &Path, extra: &[&str]) {
    let extra: Vec<String> = extra.iter().map(|a| a.to_string()).collect();
    let o = slag_encoder()
        .arg("encode")
        .args(&extra)
        .args(encode_args(out, &extra))
        .output()
        .unwrap();
    assert_success(&o);
}

/// Asserts every file of `single` but the report has the same bytes in `cluster`, and that the
/// two folders hold the same names.
fn assert_same_bytes(single: &Path, cluster: &Path) {
    assert_eq!(names(single), names(cluster));
    for name in names(single) {
        if name == "report.json" {
            continue;
        }
        let (a, b) = (
            std::fs::read(single.join(&name)).unwrap(),
            std::fs::read(cluster.join(&name)).unwrap(),
        );
        assert!(a == b, "{name}: {} and {} bytes differ", a.len(), b.len());
    }
}

fn report(out: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap()
}

/// Asserts the cluster's output equals the single-process output (module doc, point 1).
fn assert_same(single: &Embeddings, cluster: &Embeddings) {
    assert!(!single.is_empty());
    assert_eq!(single.ids, cluster.ids, "observed Gaussian ids differ");
    assert_eq!(single.dim, cluster.dim);
    assert_eq!(single.means, cluster.means);
    assert_eq!(single.model, cluster.model);
    assert_eq!(single.scene_gaussians, cluster.scene_gaussians);
    let max_dv = max_abs_difference(&single.vectors, &cluster.vectors);
    let max_dw = single
        .total_weights
        .iter()
        .zip(&cluster.total_weights)
        .map(|(a, b)| (a - b).abs() / a.abs().max(1e-12))
        .fold(0f32, f32::max);
    eprintln!(
        "{} observed Gaussians; max |Δ| vector component {max_dv:e}, max relative Δ total weight {max_dw:e}",
        single.len()
    );
    assert!(max_dv <= 1e-6, "max |Δ| {max_dv}");
    assert!(max_dw <= 1e-6, "max relative Δ weight {max_dw}");
}

/// The `host:port` lines of a host file.
fn host_lines(hosts: &Path) -> Vec<String> {
    std::fs::read_to_string(hosts)
        .unwrap()
        .lines()
        .map(str::to_string)
        .collect()
}

/// `--cluster-secret-file` with `secret` written to `dir/name` (mode 0600).
fn secret_args(dir: &Path, name: &str, secret: &str) -> Vec<String> {
    use std::os::unix::fs::PermissionsExt;
    let path = dir.join(name);
    std::fs::write(&path, format!("{secret}\n")).unwrap();
    std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600)).unwrap();
    vec!["--cluster-secret-file".into(), path.display().to_string()]
}

fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn cluster_of_three_matches_single_process_and_survives_a_killed_worker() {
    let dir = tempfile::tempdir().unwrap();
    let single_out = dir.path().join("single");
    let out = dir.path().join("cluster");

    // Reference: one process, the default outputs.
    run_single(&single_out, &[]);
    assert_eq!(
        names(&single_out),
        [
            "mask-record.safetensors",
            "mixture.safetensors",
            "report.json",
            "segments.safetensors"
        ]
    );

    faulted_run(dir.path(), &out);
    let views = resumed_run(dir.path(), &out, &single_out);
    slow_run(dir.path(), &single_out, views);
    pooled_run(dir.path(), &single_out, views);
    dense_run(dir.path(), views);
}

/// The views each process mapped, from a cluster's report; asserts that together they are the
/// `views` views, each mapped once.
fn mapped_views(report: &serde_json::Value, views: u64) -> Vec<Vec<u64>> {
    let workers = report["outputs"]["cluster"]["workers"].as_array().unwrap();
    let mapped: Vec<Vec<u64>> = workers
        .iter()
        .map(|w| {
            let v: Vec<u64> = w["views"]
                .as_array()
                .unwrap()
                .iter()
                .map(|i| i.as_u64().unwrap())
                .collect();
            assert_eq!(w["images"].as_u64(), Some(v.len() as u64), "{w}");
            v
        })
        .collect();
    let mut all: Vec<u64> = mapped.concat();
    all.sort_unstable();
    assert_eq!(
        all,
        (0..views).collect::<Vec<_>>(),
        "every view mapped once"
    );
    mapped
}

/// Point 3 of the module doc: process 1 waits `SLOW_MS` before each view it maps; compared
/// with `single_out`, the single-process run over the same `views` views.
fn slow_run(dir: &Path, single_out: &Path, views: u64) {
    // Several views' time of the others (about a second each on a loaded 2-core machine), so
    // that they map the other views while it waits on its first.
    const SLOW_MS: u32 = 6000;
    let out = dir.join("slow");
    let hosts = hosts_file(dir, "hosts-slow");
    let slow = (1, slag_encoder::distributed::MAP_DELAY_VAR, SLOW_MS);
    let t0 = Instant::now();
    let r = run_cluster(&hosts, &out, dir, "slow", Some(slow), &[]);
    for (i, (status, log)) in r.iter().enumerate() {
        assert!(status.success(), "process {i}: {log}");
    }
    assert_same_bytes(single_out, &out);
    let mapped = mapped_views(&report(&out), views);
    eprintln!(
        "slow process 1: views mapped per process {mapped:?} in {:.1} s",
        t0.elapsed().as_secs_f64()
    );
    assert!(
        mapped[1].len() < mapped[0].len() && mapped[1].len() < mapped[2].len(),
        "the slow process maps fewer views than each of the others: {mapped:?}"
    );
}

/// Point 4 of the module doc: every process runs two front workers (one thread each, as the
/// single-process run's one front); compared with `single_out` over the same `views` views.
fn pooled_run(dir: &Path, single_out: &Path, views: u64) {
    let out = dir.join("pooled");
    let hosts = hosts_file(dir, "hosts-pooled");
    let extra: Vec<String> = ["--front-workers", "2", "--threads", "2"]
        .map(String::from)
        .into();
    let t0 = Instant::now();
    let r = run_cluster(&hosts, &out, dir, "pooled", None, &extra);
    for (i, (status, log)) in r.iter().enumerate() {
        assert!(status.success(), "process {i}: {log}");
        assert!(
            log.lines()
                .any(|l| l.contains("map pool started") && l.contains("fronts=2")),
            "process {i} runs two fronts: {log}"
        );
    }
    assert_same_bytes(single_out, &out);
    let report = report(&out);
    let mapped = mapped_views(&report, views);
    eprintln!(
        "two fronts per process: views mapped per process {mapped:?} in {:.1} s",
        t0.elapsed().as_secs_f64()
    );
    for (i, m) in mapped.iter().enumerate() {
        assert!(!m.is_empty(), "process {i} mapped no view: {mapped:?}");
    }
}

/// Point 2 of the module doc: process 1 of a cluster writing OUT `out` dies after its third
/// checkpoint; the survivors name it, and OUT holds only `.partial` names and checkpoints.
fn faulted_run(dir: &Path, out: &Path) {
    // (2) Process 1 dies right after its third checkpoint (four durability boundaries each:
    // write, fsync, rename, folder sync), in a cluster whose connections prove a secret.
    let hosts = hosts_file(dir, "hosts-1");
    let mut args = secret_args(dir, "secret", "the cluster's secret, 32 bytes..");
    args.extend(["--checkpoint-every".into(), "0.001".into()]);
    let t0 = Instant::now();
    let exit_at = (1, slag_common::fault::EXIT_AT_VAR, 12);
    let r = run_cluster(&hosts, out, dir, "faulted", Some(exit_at), &args);
    eprintln!("faulted run ended in {:.1} s", t0.elapsed().as_secs_f64());
    assert_eq!(r[1].0.code(), Some(137), "{}", r[1].1);
    assert_eq!(
        slag_common::fault::stopped_at(&r[1].1).as_deref(),
        Some("cluster.checkpoint:dir_sync"),
        "{}",
        r[1].1
    );
    let dead = format!(
        "process 1 ({}) died or its connection failed",
        host_lines(&hosts)[1]
    );
    for i in [0, 2] {
        let (status, log) = &r[i];
        assert_eq!(status.code(), Some(PEER_LOST), "process {i}: {log}");
        assert!(
            log.contains(&dead),
            "process {i} names the dead process: {log}"
        );
    }
    for name in names(out) {
        assert!(
            name.ends_with(".partial") || name.ends_with(".checkpoint"),
            "{name} left after a failed job"
        );
    }
    assert!(out.join(".cluster-1-of-3.checkpoint").exists());
}

/// Point 1 of the module doc: the rerun in `out` resumes and matches `single_out`, the
/// single-process run, byte for byte; returns the views encoded.
fn resumed_run(dir: &Path, out: &Path, single_out: &Path) -> u64 {
    // (1) Rerun in the same OUT, checkpoints at the default interval: resumes, the same files as
    // the single-process run, no checkpoint left.
    let hosts = hosts_file(dir, "hosts-2");
    // Without a secret: allowed, every address being on loopback.
    let r = run_cluster(&hosts, out, dir, "rerun", None, &[]);
    for (i, (status, log)) in r.iter().enumerate() {
        assert!(status.success(), "process {i}: {log}");
    }
    assert!(
        r[1].1.contains("resumed from the partition's checkpoint"),
        "{}",
        r[1].1
    );
    assert_same_bytes(single_out, &out);
    let (report, single_report) = (report(out), report(single_out));
    for key in ["views_used", "views_total", "observed", "masks", "entries"] {
        assert_eq!(report["counts"][key], single_report["counts"][key], "{key}");
    }
    assert_eq!(
        report["view_selection"]["chosen"],
        single_report["view_selection"]["chosen"]
    );
    assert_eq!(report["view_selection"]["mode"], "coverage");
    assert_eq!(
        report["outputs"]["forms"]["mixture_codebook_rows"],
        single_report["outputs"]["forms"]["mixture_codebook_rows"]
    );
    assert_eq!(
        report["segments"]["stats"]["segments"],
        single_report["segments"]["stats"]["segments"]
    );
    let views = report["counts"]["views_used"].as_u64().unwrap();
    let cluster = &report["outputs"]["cluster"];
    let parts = cluster["partitions"].as_array().unwrap();
    assert_eq!(parts.len(), 3);
    let observed: u64 = parts.iter().map(|p| p["observed"].as_u64().unwrap()).sum();
    assert_eq!(observed, report["counts"]["observed"].as_u64().unwrap());
    let restored: Vec<u64> = parts
        .iter()
        .map(|p| p["views_restored"].as_u64().unwrap())
        .collect();
    let resumed = cluster["views_resumed"].as_u64().unwrap();
    eprintln!("views restored per partition {restored:?}, views not encoded again {resumed}");
    assert!(
        restored[1] >= 3,
        "partition 1 wrote 3 checkpoints: {restored:?}"
    );
    assert_eq!(resumed, *restored.iter().min().unwrap());
    let images: u64 = cluster["workers"]
        .as_array()
        .unwrap()
        .iter()
        .map(|w| w["images"].as_u64().unwrap())
        .sum();
    assert_eq!(
        images + resumed,
        views,
        "every view encoded once or resumed"
    );
    for name in names(out) {
        assert!(
            !name.contains("checkpoint"),
            "{name} left after the job completed"
        );
    }
    views
}

/// Point 5 of the module doc: with `--dense`, over the same `views` views.
fn dense_run(dir: &Path, views: u64) {
    // (3) The dense file too: within f32 round-off of the single process's, the rest the same.
    let (single_dense, dense) = (dir.join("single-dense"), dir.join("dense"));
    run_single(&single_dense, &["--dense"]);
    let hosts = hosts_file(dir, "hosts-3");
    let r = run_cluster(&hosts, &dense, dir, "dense", None, &["--dense".into()]);
    for (i, (status, log)) in r.iter().enumerate() {
        assert!(status.success(), "process {i}: {log}");
    }
    let e = |d: &Path| Embeddings::read(&d.join("embeddings.safetensors")).unwrap();
    assert_same(&e(&single_dense), &e(&dense));
    assert_eq!(
        std::fs::read(single_dense.join("mixture.safetensors")).unwrap(),
        std::fs::read(dense.join("mixture.safetensors")).unwrap(),
        "the mixture with --dense"
    );
    let report = self::report(&dense);
    assert_eq!(
        report["counts"]["spilled_images"],
        views * 3,
        "every image part was spilled"
    );
    mapped_views(&report, views);
    assert!(report["counts"]["reduce_chunks"].as_u64().unwrap() >= 3 * 3);
}

/// A process holding another secret takes process 1's place first: processes 0 and 2 refuse it
/// (logged with its address), it refuses them, and the job does not start with it; once it is
/// gone the right process 1 joins and the job completes. A run off loopback without a secret
/// is refused before anything is bound.
#[test]
fn a_peer_with_a_wrong_secret_is_refused_and_the_job_waits_for_the_right_one() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let hosts = hosts_file(dir.path(), "hosts");
    let right = secret_args(dir.path(), "right", "the cluster's secret, 32 bytes..");
    let wrong = secret_args(dir.path(), "wrong", "another secret of the same length");
    let p0 = spawn(0, &hosts, &out, dir.path(), "auth", None, &right);
    let p2 = spawn(2, &hosts, &out, dir.path(), "auth", None, &right);
    let mut intruder = spawn(1, &hosts, &out, dir.path(), "intruder", None, &wrong);
    let refused = |p: &Proc, what: &str| {
        std::fs::read_to_string(&p.log)
            .unwrap_or_default()
            .contains(what)
    };
    let t0 = Instant::now();
    while !(refused(&p0, "refused a connection from 127.0.0.1:")
        && refused(&p2, "refused the connection to process 1")
        && refused(&intruder, "refused the connection to process 0"))
    {
        assert!(t0.elapsed() < TIMEOUT, "no refusal logged");
        assert!(
            intruder.child.try_wait().unwrap().is_none(),
            "intruder exited"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let intruder_log = std::fs::read_to_string(&intruder.log).unwrap();
    assert!(
        intruder_log.contains("process 0 failed the challenge"),
        "{intruder_log}"
    );
    intruder.child.kill().unwrap();
    intruder.child.wait().unwrap();
    assert!(
        !out.join("report.json").exists(),
        "no job ran with the intruder"
    );

    let p1 = spawn(1, &hosts, &out, dir.path(), "auth", None, &right);
    let r = wait_all(vec![p0, p1, p2]);
    for (i, (status, log)) in r.iter().enumerate() {
        assert!(status.success(), "process {i}: {log}");
    }
    assert!(
        r[2].1.contains("process 1 failed the challenge"),
        "process 2 logs why: {}",
        r[2].1
    );
    assert!(
        r[0].1.contains("it holds another cluster secret"),
        "process 0 logs why: {}",
        r[0].1
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["counts"]["views_used"], 7);

    // Off loopback without a secret: refused at once, with the flag in the hint.
    let remote = dir.path().join("hosts-remote");
    std::fs::write(&remote, "127.0.0.1:1\n10.255.255.1:4000\n").unwrap();
    let o = slag_encoder()
        .args(["encode-cluster", "--process", "0", "--hosts"])
        .arg(&remote)
        .args(encode_args(&dir.path().join("refused"), &[]))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{stderr}");
    assert!(
        stderr.contains("10.255.255.1:4000 off loopback")
            && stderr.contains("--cluster-secret-file"),
        "{stderr}"
    );
}
