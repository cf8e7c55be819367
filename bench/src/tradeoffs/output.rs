//! The study's outputs: `tradeoffs.csv` (one row per point) and `tradeoffs.md` (header, one table
//! row per point, the footprint table).

use std::fmt::Write as _;

use slag_common::table::Table;

use super::Row;
use super::storage::FootprintRow;
use crate::machine::MachineInfo;

/// CSV columns, in order.
pub const CSV_COLUMNS: [&str; 27] = [
    "section",
    "point",
    "knob",
    "masks",
    "every",
    "raster_scale",
    "top_k",
    "storage",
    "index",
    "views",
    "observed",
    "encode_s",
    "decode_s",
    "masks_s",
    "clip_s",
    "raster_s",
    "aggregate_s",
    "reduce_s",
    "build_s",
    "bytes_per_gaussian",
    "query_ms",
    "colour_miou",
    "held_out_miou",
    "iou",
    "set_iou",
    "iou_kind",
    "iou_prompts",
];

/// What the markdown header states about the run.
#[derive(Debug, Clone)]
pub struct Header {
    /// The command line as run.
    pub command: String,
    /// Machine facts.
    pub machine: MachineInfo,
    /// Free text (e.g. other load on the machine).
    pub note: Option<String>,
    /// Scene folder.
    pub scene: String,
    /// Gaussians in the scene's `.ply`.
    pub scene_gaussians: usize,
    /// Match threshold.
    pub threshold: f32,
    /// Timed repetitions per prompt.
    pub repeats: usize,
    /// k of the index comparison.
    pub index_top_k: usize,
    /// Encode points of the plan left out (`--cached-only`), with their knob.
    pub skipped: Vec<String>,
    /// Seconds the whole study took.
    pub study_s: f64,
    /// Names of the views every point is scored on (held out by all of them).
    pub held_out_views: Vec<String>,
    /// The majority-class baseline's mIoU on those views.
    pub majority_miou: Option<f64>,
}

fn miou_str(m: Option<f64>) -> String {
    m.map_or_else(|| "na".into(), |v| format!("{v:.4}"))
}

/// Appends a section of tables to `s`: a blank line, `## heading`, the `intro` paragraph if
/// any, then the markdown table.
fn push_section(s: &mut String, heading: &str, intro: Option<&str>, table: &Table) {
    let _ = writeln!(s, "\n## {heading}\n");
    if let Some(intro) = intro {
        let _ = writeln!(s, "{intro}\n");
    }
    s.push_str(&table.markdown());
}

/// Appends the section `heading` with its `intro` and a table of `header`'s columns (right-aligned
/// from the third): one row of `cells` per row of the study's `section` (`storage`, `index`).
fn push_points_section(
    s: &mut String,
    rows: &[Row],
    section: &str,
    heading: &str,
    intro: &str,
    header: &str,
    cells: impl Fn(&Row) -> Vec<String>,
) {
    let points = rows.iter().filter(|r| r.section == section).map(cells);
    let table = Table::with_header(header).right_from(2).with_rows(points);
    push_section(s, heading, Some(intro), &table);
}

/// The CSV text: a header line of [`CSV_COLUMNS`], then one line per row.
pub fn csv(rows: &[Row]) -> String {
    let mut t = Table::new(CSV_COLUMNS);
    for r in rows {
        let mut cells = vec![
            r.section.clone(),
            r.point.clone(),
            r.knob.clone(),
            r.masks.clone(),
            r.every.to_string(),
            r.raster_scale.to_string(),
            r.top_k.clone(),
            r.storage.clone(),
            r.index.clone(),
            r.views.to_string(),
            r.observed.to_string(),
        ];
        // Every duration in seconds, to the millisecond: the encode, its stages, the build.
        let st = &r.stages;
        let seconds = [
            r.encode_s,
            st.decode,
            st.masks,
            st.clip,
            st.raster,
            st.image_aggregate,
            st.reduce,
            r.build_s,
        ];
        cells.extend(seconds.map(|v| format!("{v:.3}")));
        cells.extend([
            format!("{:.2}", r.bytes_per_gaussian),
            format!("{:.3}", r.query_ms),
            miou_str(r.colour_miou),
            miou_str(r.held_out_miou),
            format!("{:.4}", r.iou),
            format!("{:.4}", r.set_iou),
            r.iou_kind.clone(),
            r.iou_prompts.to_string(),
        ]);
        t.row(cells);
    }
    t.csv()
}

/// Indices of the encode rows on the Pareto front of (lower encode time, higher held-out mIoU):
/// no other row is at least as fast and at least as accurate while strictly better in one. Rows
/// without a held-out score (every view encoded) are not on it.
pub fn pareto_front(rows: &[Row]) -> Vec<usize> {
    let pts: Vec<(usize, f64, f64)> = rows
        .iter()
        .enumerate()
        .filter(|(_, r)| r.section == "encode")
        .filter_map(|(i, r)| r.held_out_miou.map(|m| (i, r.encode_s, m)))
        .collect();
    pts.iter()
        .filter(|&&(i, t, m)| {
            !pts.iter()
                .any(|&(j, t2, m2)| j != i && t2 <= t && m2 >= m && (t2 < t || m2 > m))
        })
        .map(|p| p.0)
        .collect()
}

/// The markdown document (see the module doc).
pub fn markdown(h: &Header, rows: &[Row], footprint: &[FootprintRow]) -> String {
    let mut s = header_markdown(h);
    encode_section(&mut s, rows);
    storage_section(&mut s, rows);
    index_section(&mut s, h, rows);
    footprint_section(&mut s, footprint);
    s += "\n## Recommendations\n\n";
    s += HAND_WRITTEN_MARKER;
    s.push('\n');
    s
}

/// The document's title and its list of what the run was and how it scores.
fn header_markdown(h: &Header) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# slag speed/accuracy trade study\n");
    let _ = writeln!(
        s,
        "Generated by `slag-bench tradeoffs` (bench/src/tradeoffs); do not edit by hand except \
         the recommendations section at the end.\n"
    );
    let _ = writeln!(s, "- Command: `{}`", h.command);
    let _ = writeln!(s, "- Machine: {}", h.machine.markdown());
    if let Some(n) = &h.note {
        let _ = writeln!(s, "- Note: {n}");
    }
    let _ = writeln!(
        s,
        "- Scene: `{}` ({} Gaussians); masks/CLIP: color-sam / color-clip fixtures (colour ground \
         truth known); rasterizer: wgpu (GPU, or Mesa lavapipe on a CPU-only machine); ONNX \
         Runtime CPU.",
        h.scene, h.scene_gaussians
    );
    if !h.skipped.is_empty() {
        let _ = writeln!(
            s,
            "- **Not run** (left out of this study, `--cached-only`): {}",
            h.skipped.join(", ")
        );
    }
    let _ = writeln!(
        s,
        "- Study wall time: {:.0} s (encode runs reused from the work folder count only their \
         recorded time).",
        h.study_s
    );
    let _ = writeln!(
        s,
        "- Prompts: color-clip's 12 colour words. A prompt's answer is the set of Gaussians with \
         cosine ≥ {t}. **IoU** = mean over prompts of |A∩B| / |A∪B| against the exact answer \
         named in each table; prompts empty in both answers are left out of the mean (the count \
         averaged is given in parentheses; 1 with 0 prompts means both answers are empty \
         everywhere). **Colour mIoU**: `slag-encoder eval-colors` (classes ≥ 1% of the opaque \
         Gaussians; unobserved Gaussians count as misses).",
        t = h.threshold
    );
    let _ = writeln!(
        s,
        "- **Held-out mIoU** (the accuracy axis): the protocol of `slag-encoder eval-colors \
         --held-out` (renders at full resolution of class scores cos(E_k, text), argmax per \
         pixel against the photo's nearest colour class, pixels of rendered alpha ≥ 0.5, mIoU \
         over the classes with ≥ 1% of the counted pixels) on the {n} views that no point of \
         the plan encodes (index ≢ 0 modulo every step of 2 or more), the same pixels for every \
         point: {names}. Majority-class baseline on them: {maj}. A point encoded from every view \
         has none held out (`na`).",
        n = h.held_out_views.len(),
        names = h.held_out_views.join(", "),
        maj = miou_str(h.majority_miou)
    );
    let _ = writeln!(
        s,
        "- Query latency: one prompt's exact scan (`slag_edge::scan`, cos ≥ {t}, all cores), \
         median over 12 prompts × {r} repeats after one untimed run per prompt.",
        t = h.threshold,
        r = h.repeats
    );
    s
}

/// The encode sweep: one row per encode point, ★ on the Pareto front.
fn encode_section(s: &mut String, rows: &[Row]) {
    let front = pareto_front(rows);
    let encode_intro = "Baseline: graph masks, every 4th image, raster scale 0.5, all contributors per pixel. \
         **Reference** (for *IoU vs ref*): graph masks, every image, raster scale 0.5, all \
         contributors: the costliest graph configuration of the sweep besides raster 1.0 at 4× \
         the raster cost. Mask sources are compared at every 8th image. Stage columns are \
         seconds summed over images (decode/masks/CLIP on one thread overlap raster/a_kj on \
         another, so they exceed the wall time). ★ = on the Pareto front of (encode time, \
         held-out mIoU). *3D mIoU*: the colour mIoU of each Gaussian's class, beside it. \
         Embeddings are evaluated as f32.";
    let encode_rows = rows
        .iter()
        .enumerate()
        .filter(|(_, r)| r.section == "encode")
        .map(|(i, r)| {
            let star = if front.contains(&i) { " ★" } else { "" };
            vec![
                format!("`{}`", r.point),
                r.knob.clone(),
                r.masks.clone(),
                r.every.to_string(),
                r.views.to_string(),
                r.raster_scale.to_string(),
                r.top_k.clone(),
                format!("{:.1}{star}", r.encode_s),
                format!("{:.1}", r.stages.masks),
                format!("{:.1}", r.stages.clip),
                format!("{:.1}", r.stages.raster),
                format!("{:.1}", r.stages.image_aggregate),
                format!("{:.2}", r.stages.reduce),
                r.observed.to_string(),
                miou_str(r.held_out_miou),
                miou_str(r.colour_miou),
                format!("{:.3} ({})", r.iou, r.iou_prompts),
                format!("{:.2}", r.query_ms),
            ]
        });
    let encode_table = Table::with_header("point | knob | masks | every | views | raster | top-K | encode s | masks s | CLIP s | raster s | a_kj s | reduce s | observed | held-out mIoU | 3D mIoU | IoU vs ref (prompts) | f32 scan ms")
    .right_from(3)
    .with_rows(encode_rows);
    push_section(
        s,
        "Encode sweep (one factor at a time)",
        Some(encode_intro),
        &encode_table,
    );
}

/// The stored-precision table: one row per storage point.
fn storage_section(s: &mut String, rows: &[Row]) {
    let storage_intro = "Rows quantised exactly as the shards store them (f16 round-to-nearest; int8 symmetric per \
         row with an f32 scale). Bytes per Gaussian = vector + 4 B id + 12 B mean. *Build* = \
         seconds to convert the f32 rows. Colour mIoU from the dequantised rows; IoU against the \
         exact f32 answer (`slag_common::similarity::cosine_scores` on the f32 rows). \
         **Mixture** `S`: the mixture of a run with the baseline's settings (`encode \
         --mixture-keep`, every atom kept = `Sall`; its IoU is against that run's own f32 rows) cut to each Gaussian's S largest weights and renormalised (= `reduce_mixture` \
         with keep S up to f16 rounding of the weights); bytes as written (f16 codebook amortised \
         over the Gaussians + S × 6 B + 16 B); its query is `MixtureEmbeddings::scores` (one dot \
         per codebook row, then S multiply-adds per Gaussian) plus the threshold, and its build \
         time the cut.";
    push_points_section(
        s,
        rows,
        "storage",
        "Stored precision (baseline run's embeddings)",
        storage_intro,
        "point | storage | bytes / Gaussian | build s | scan ms | colour mIoU | IoU vs f32 (prompts)",
        |r| {
            vec![
                format!("`{}`", r.point),
                r.storage.clone(),
                format!("{:.1}", r.bytes_per_gaussian),
                format!("{:.3}", r.build_s),
                format!("{:.2}", r.query_ms),
                miou_str(r.colour_miou),
                format!("{:.4} ({})", r.iou, r.iou_prompts),
            ]
        },
    );
}

/// The exact scan against the approximate index: one row per index point.
fn index_section(s: &mut String, h: &Header, rows: &[Row]) {
    let index_intro = format!(
        "Top-{k} per prompt on the baseline's f32 rows (HNSW: instant-distance, M 32, ef_search \
         = k; rows: the indexed ones). HNSW bytes add the index (its f32 copy of the rows and the \
         graph) to the store's. *Recall*: the fraction of HNSW's k rows scoring at least the \
         exact k-th best score (ties counted: color-clip rows are mixtures of 12 prototypes, so \
         many rows tie there); *set IoU*: the top-{k} id sets compared as returned.",
        k = h.index_top_k
    );
    push_points_section(
        s,
        rows,
        "index",
        "Exact scan vs approximate index (HNSW)",
        &index_intro,
        "point | index | rows | build s | bytes / Gaussian | top-k ms | recall vs exact | set IoU (prompts)",
        |r| {
            vec![
                format!("`{}`", r.point),
                r.index.clone(),
                r.observed.to_string(),
                format!("{:.2}", r.build_s),
                format!("{:.1}", r.bytes_per_gaussian),
                format!("{:.3}", r.query_ms),
                format!("{:.4}", r.iou),
                format!("{:.4} ({})", r.set_iou, r.iou_prompts),
            ]
        },
    );
}

/// The footprint of each stored form against the dense one.
fn footprint_section(s: &mut String, footprint: &[FootprintRow]) {
    let dense = footprint.first().map_or(1, |f| f.bytes.max(1));
    let footprint_rows = footprint.iter().map(|f| {
        vec![
            f.form.clone(),
            f.gaussians.to_string(),
            f.bytes.to_string(),
            format!("{:.2}", f.bytes as f64 / (1u64 << 20) as f64),
            format!("{:.3}", f.bytes as f64 / dense as f64),
            f.detail.clone(),
        ]
    });
    let footprint_table =
        Table::with_header("stored form | Gaussians | bytes | MiB | vs dense | detail")
            .right(1..5)
            .with_rows(footprint_rows);
    push_section(
        s,
        "Model only what the scene requires",
        None,
        &footprint_table,
    );
}

/// The line after which `tradeoffs.md` is written by hand; a new run keeps what follows it.
pub const HAND_WRITTEN_MARKER: &str =
    "<!-- recommendations: hand-written from the tables above -->";

/// `generated` (a [`markdown`] document, ending in [`HAND_WRITTEN_MARKER`]) with the hand-written
/// text that followed the marker in the `previous` document, if it had one: a new run replaces
/// the tables and keeps the recommendations and notes written below them.
pub fn keep_hand_written(generated: &str, previous: Option<&str>) -> String {
    let tail = previous.and_then(|p| p.split_once(HAND_WRITTEN_MARKER).map(|(_, t)| t));
    match (generated.split_once(HAND_WRITTEN_MARKER), tail) {
        (Some((head, _)), Some(tail)) => format!("{head}{HAND_WRITTEN_MARKER}{tail}"),
        _ => generated.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(section: &str, point: &str, colour_miou: Option<f64>) -> Row {
        Row {
            section: section.into(),
            point: point.into(),
            knob: "baseline".into(),
            masks: "graph".into(),
            every: 4,
            raster_scale: 0.5,
            top_k: "all".into(),
            storage: "f16".into(),
            index: "hnsw".into(),
            views: 12,
            observed: 1234,
            encode_s: 10.25,
            stages: slag_encoder::report::StageTimings {
                masks: 1.5,
                clip: 2.25,
                raster: 3.125,
                image_aggregate: 0.5,
                reduce: 0.0625,
                ..Default::default()
            },
            build_s: 0.123456,
            bytes_per_gaussian: 1040.04,
            query_ms: 2.345,
            colour_miou,
            held_out_miou: colour_miou.map(|m| m + 0.125),
            iou: 0.987654,
            set_iou: 0.876543,
            iou_kind: "f32 cos>=0.28".into(),
            iou_prompts: 11,
        }
    }

    /// The table lines of [`markdown`] (every line starting with `|`).
    fn table_lines() -> Vec<String> {
        let h = Header {
            command: "slag-bench tradeoffs".into(),
            machine: MachineInfo::detect(),
            note: None,
            scene: "mini".into(),
            scene_gaussians: 5000,
            threshold: 0.28,
            repeats: 1,
            index_top_k: 100,
            skipped: Vec::new(),
            study_s: 60.0,
            held_out_views: vec!["a.jpg".into(), "b.jpg".into()],
            majority_miou: Some(0.1),
        };
        let rows = [
            row("encode", "graph-e4", Some(0.5)),
            row("storage", "store-f16", Some(0.25)),
            row("index", "hnsw", None),
        ];
        let footprint = [FootprintRow {
            form: "dense f32".into(),
            gaussians: 5000,
            bytes: 3 << 20,
            detail: "one tensor".into(),
        }];
        markdown(&h, &rows, &footprint)
            .lines()
            .filter(|l| l.starts_with('|'))
            .map(str::to_string)
            .collect()
    }

    #[test]
    fn a_new_run_keeps_the_hand_written_tail() {
        let new = format!("# study\n| new table |\n## Recommendations\n\n{HAND_WRITTEN_MARKER}\n");
        let old = format!(
            "# study\n| old table |\n## Recommendations\n\n{HAND_WRITTEN_MARKER}\nkeep f16.\n"
        );
        let merged = keep_hand_written(&new, Some(&old));
        assert_eq!(
            merged,
            format!(
                "# study\n| new table |\n## Recommendations\n\n{HAND_WRITTEN_MARKER}\nkeep f16.\n"
            )
        );
        assert_eq!(keep_hand_written(&new, None), new);
        assert_eq!(keep_hand_written(&new, Some("no marker")), new);
    }

    #[test]
    fn the_front_is_taken_on_held_out_miou() {
        // (encode s, held-out, 3D): `a` has the best 3D score but a slower, worse held-out
        // score than `c`; `d` has no held-out score (every view encoded).
        let points = [
            ("a", 10.0, Some(0.30), 0.9),
            ("b", 2.0, Some(0.20), 0.1),
            ("c", 5.0, Some(0.40), 0.2),
            ("d", 1.0, None, 0.8),
        ];
        let rows: Vec<Row> = points
            .iter()
            .map(|&(p, t, held, m3)| Row {
                encode_s: t,
                held_out_miou: held,
                ..row("encode", p, Some(m3))
            })
            .collect();
        assert_eq!(pareto_front(&rows), vec![1, 2]);
    }

    #[test]
    fn csv_has_one_field_per_column() {
        let text = csv(&[row("storage", "store-f16", None)]);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], CSV_COLUMNS.join(","));
        assert_eq!(
            lines[1],
            "storage,store-f16,baseline,graph,4,0.5,all,f16,hnsw,12,1234,10.250,0.000,1.500,2.250,\
             3.125,0.500,0.062,0.123,1040.04,2.345,na,na,0.9877,0.8765,f32 cos>=0.28,11"
        );
        assert_eq!(lines[1].split(',').count(), CSV_COLUMNS.len());
    }

    #[test]
    fn markdown_tables_have_one_cell_per_column() {
        let lines = table_lines();
        let expected = [
            "| point | knob | masks | every | views | raster | top-K | encode s | masks s | CLIP s | raster s | a_kj s | reduce s | observed | held-out mIoU | 3D mIoU | IoU vs ref (prompts) | f32 scan ms |",
            "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
            "| `graph-e4` | baseline | graph | 4 | 12 | 0.5 | all | 10.2 ★ | 1.5 | 2.2 | 3.1 | 0.5 | 0.06 | 1234 | 0.6250 | 0.5000 | 0.988 (11) | 2.35 |",
            "| point | storage | bytes / Gaussian | build s | scan ms | colour mIoU | IoU vs f32 (prompts) |",
            "|---|---|---:|---:|---:|---:|---:|",
            "| `store-f16` | f16 | 1040.0 | 0.123 | 2.35 | 0.2500 | 0.9877 (11) |",
            "| point | index | rows | build s | bytes / Gaussian | top-k ms | recall vs exact | set IoU (prompts) |",
            "|---|---|---:|---:|---:|---:|---:|---:|",
            "| `hnsw` | hnsw | 1234 | 0.12 | 1040.0 | 2.345 | 0.9877 | 0.8765 (11) |",
            "| stored form | Gaussians | bytes | MiB | vs dense | detail |",
            "|---|---:|---:|---:|---:|---|",
            "| dense f32 | 5000 | 3145728 | 3.00 | 1.000 | one tensor |",
        ];
        assert_eq!(lines, expected);
        for table in lines.chunks(3) {
            let cells = |l: &str| l.matches('|').count();
            assert_eq!(cells(&table[0]), cells(&table[1]), "{table:?}");
            assert_eq!(cells(&table[0]), cells(&table[2]), "{table:?}");
        }
    }
}
