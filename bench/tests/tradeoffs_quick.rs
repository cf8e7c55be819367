//! `slag-bench tradeoffs --quick` end to end on the embedded scene (data/snowmiku-mini): runs the
//! binary, then checks the CSV and the markdown against what the study must hold.

#![allow(clippy::unwrap_used)]

use std::collections::HashMap;
use std::path::PathBuf;

use slag_bench::tradeoffs::output::CSV_COLUMNS;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// One CSV row as column name → value (the study writes no quoted commas except in `iou_kind`).
fn parse_csv(text: &str) -> Vec<HashMap<String, String>> {
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!(header, CSV_COLUMNS, "CSV header");
    lines
        .map(|l| {
            // Split on commas outside double quotes.
            let (mut cells, mut cur, mut quoted) = (Vec::new(), String::new(), false);
            for ch in l.chars() {
                match ch {
                    '"' => quoted = !quoted,
                    ',' if !quoted => cells.push(std::mem::take(&mut cur)),
                    c => cur.push(c),
                }
            }
            cells.push(cur);
            assert_eq!(cells.len(), header.len(), "incomplete CSV row: {l}");
            header
                .iter()
                .map(|h| h.to_string())
                .zip(cells)
                .collect::<HashMap<_, _>>()
        })
        .collect()
}

fn num(row: &HashMap<String, String>, col: &str) -> f64 {
    let v: f64 = row[col]
        .parse()
        .unwrap_or_else(|_| panic!("{col} = {:?} is not a number", row[col]));
    assert!(v.is_finite(), "{col} not finite");
    v
}

#[test]
fn quick_study_writes_complete_consistent_tables() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("docs");
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_slag-bench"))
        .args(["tradeoffs", "--quick", "--scene-dir"])
        .arg(repo().join("data/snowmiku-mini"))
        .arg("--out")
        .arg(&out)
        .arg("--work")
        .arg(tmp.path().join("work"))
        .env("RUST_LOG", "warn")
        .status()
        .unwrap();
    assert!(status.success(), "slag-bench tradeoffs --quick failed");
    let csv = std::fs::read_to_string(out.join("tradeoffs.csv")).unwrap();
    let md = std::fs::read_to_string(out.join("tradeoffs.md")).unwrap();
    let rows = parse_csv(&csv);
    let by_point: HashMap<&str, &HashMap<String, String>> =
        rows.iter().map(|r| (r["point"].as_str(), r)).collect();
    assert_eq!(by_point.len(), rows.len(), "point ids must be unique");

    // Every row complete: no empty cell, numbers finite, colour mIoU in [0, 1] (or `na` for an
    // index point, which answers top-k lists and assigns no class).
    let numeric = [
        "every",
        "raster_scale",
        "views",
        "observed",
        "encode_s",
        "build_s",
        "bytes_per_gaussian",
        "query_ms",
        "iou",
        "set_iou",
        "iou_prompts",
    ];
    for r in &rows {
        for c in CSV_COLUMNS {
            assert!(!r[c].is_empty(), "{}: empty {c}", r["point"]);
        }
        for c in numeric {
            num(r, c);
        }
        assert!((0.0..=1.0).contains(&num(r, "iou")), "{}", r["point"]);
        if r["colour_miou"] == "na" {
            assert_eq!(
                r["section"], "index",
                "{}: only index points lack mIoU",
                r["point"]
            );
        } else {
            let m = num(r, "colour_miou");
            assert!((0.0..=1.0).contains(&m), "{}: mIoU {m}", r["point"]);
        }
        assert!(num(r, "query_ms") > 0.0);
    }
    // The markdown has exactly one table row per point.
    for p in by_point.keys() {
        assert_eq!(
            md.matches(&format!("| `{p}` |")).count(),
            1,
            "markdown rows of {p}"
        );
    }
    assert!(
        md.contains("slag-bench tradeoffs --quick"),
        "header names the command"
    );

    // Encode sweep: 3 points; the reference agrees with itself; fewer views (a subset of the
    // reference's) or fewer contributors per pixel never observe more Gaussians.
    let enc: Vec<_> = rows.iter().filter(|r| r["section"] == "encode").collect();
    assert_eq!(enc.len(), 3);
    let reference = enc.iter().find(|r| r["knob"] == "reference").unwrap();
    let baseline = enc.iter().find(|r| r["knob"] == "baseline").unwrap();
    let topk = enc.iter().find(|r| r["knob"] == "top-k").unwrap();
    assert_eq!(num(reference, "iou"), 1.0);
    assert!(num(baseline, "observed") <= num(reference, "observed"));
    assert!(num(topk, "observed") < num(baseline, "observed"));
    assert!(
        num(baseline, "iou") < 1.0,
        "a 3-view run cannot equal the 7-view reference"
    );

    // Held-out 2D mIoU: every encode point (all hold views out in the quick plan) is scored on
    // the same held-out views, within [0, 1] and above the majority-class baseline the header
    // states; storage and index points are not scored. The Pareto front is marked on at least
    // one encode row.
    for r in &rows {
        if r["section"] == "encode" {
            let m = num(r, "held_out_miou");
            assert!((0.0..=1.0).contains(&m), "{}: held-out {m}", r["point"]);
        } else {
            assert_eq!(r["held_out_miou"], "na", "{}", r["point"]);
        }
    }
    let majority: f64 = md
        .split("Majority-class baseline on them: ")
        .nth(1)
        .and_then(|t| {
            t.split('.')
                .take(2)
                .collect::<Vec<_>>()
                .join(".")
                .parse()
                .ok()
        })
        .expect("the header states the majority baseline");
    assert!(
        enc.iter().all(|r| num(r, "held_out_miou") > majority),
        "every point beats the majority class ({majority})"
    );
    assert!(
        md.contains("views that no point of the plan encodes"),
        "the header says which views are held out"
    );
    assert!(
        md.lines()
            .any(|l| l.starts_with("| `graph-") && l.contains(" ★ |"))
    );

    // Storage: bytes per Gaussian as the shard format defines them (D = 512: f32 4D + 16,
    // f16 2D + 16, int8 D + 4 + 16); f32 rows answer exactly as the f32 reference (1 up to a
    // score within f32 rounding of the threshold); f16/int8 close to it.
    let bpg = |p: &str| num(by_point[p], "bytes_per_gaussian");
    assert_eq!(bpg("store-f32"), 2064.0);
    assert_eq!(bpg("store-f16"), 1040.0);
    assert_eq!(bpg("store-int8"), 532.0);
    assert!(bpg("store-int8") < bpg("store-f16") && bpg("store-f16") < bpg("store-f32"));
    assert!(num(by_point["store-f32"], "iou") >= 0.9999);
    assert!(num(by_point["store-f16"], "iou") >= 0.99);
    assert!(num(by_point["store-int8"], "iou") >= 0.95);
    // Quantisation barely moves the colour assignment.
    let m32 = num(by_point["store-f32"], "colour_miou");
    assert!((num(by_point["store-int8"], "colour_miou") - m32).abs() < 0.01);
    assert_eq!(m32, num(baseline, "colour_miou"));

    // Mixture (codebook + S sparse weights): with every atom kept it reconstructs the f32 rows up
    // to f16 rounding, so it answers like them; fewer slots cost fewer bytes.
    let all = by_point["mixture-Sall"];
    assert!(num(all, "iou") >= 0.99, "mixture-Sall IoU {}", all["iou"]);
    assert!((num(all, "colour_miou") - m32).abs() < 0.01);
    let mix_bpg: Vec<f64> = [
        "mixture-S1",
        "mixture-S2",
        "mixture-S4",
        "mixture-S8",
        "mixture-S16",
    ]
    .iter()
    .map(|p| bpg(p))
    .collect();
    assert!(mix_bpg.windows(2).all(|w| w[0] <= w[1]), "{mix_bpg:?}");
    assert!(
        mix_bpg[0] < bpg("store-int8"),
        "S = 1 is smaller than int8 rows"
    );

    // Index: the exact scan is its own reference; HNSW holds more bytes than the store.
    let scan = rows
        .iter()
        .find(|r| r["point"].starts_with("index-scan"))
        .unwrap();
    let hnsw = rows
        .iter()
        .find(|r| r["point"].starts_with("index-hnsw"))
        .unwrap();
    assert_eq!(num(scan, "iou"), 1.0);
    assert!(num(hnsw, "bytes_per_gaussian") > num(scan, "bytes_per_gaussian"));
    assert!(num(hnsw, "iou") > 0.5, "HNSW recall {}", hnsw["iou"]);

    // Footprint: the dense tensor over all 60,000 Gaussians of the mini scene.
    assert!(
        md.contains(&format!("| {} |", 60_000 * 512 * 4)),
        "dense bytes in the footprint"
    );
}
