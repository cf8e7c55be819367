//! The objects table of `slag-edge bench`: the time to group a query's matching Gaussians into
//! objects ([`slag_common::objects::group_objects`], what every answer now does after the scan).

use std::time::Instant;

use slag_common::objects::{Matches, ObjectParams, group_objects};
use slag_common::rng::SplitMix64;
use slag_common::table::Table;

use super::{BenchArgs, fmt_size, median};

/// Boxes of the synthetic workload.
const BOXES: usize = 20;
/// Fraction of the matches scattered over the room (stray matches, suppressed as small groups).
const STRAY: f64 = 0.01;

/// `n` matching Gaussians like a query's matches in a room: [`BOXES`] box shells (sides 0.3 to
/// 1.0 m, ≥ 1.5 m apart on a 5 × 4 grid, points uniform on their surfaces), plus [`STRAY`] of
/// them uniform in the 10 × 8 × 3 m room; scores in 0.28..0.4, opacities in 0.5..1.
pub(super) fn workload(n: usize, seed: u64) -> (Vec<u32>, Vec<[f32; 3]>, Vec<f32>, Vec<f32>) {
    let mut rng = SplitMix64::new(seed ^ 0x0B1E);
    let mut r = || rng.next_f64();
    let stray = (n as f64 * STRAY) as usize;
    let per_box = (n - stray) / BOXES;
    let mut pos = Vec::with_capacity(n);
    for b in 0..BOXES {
        let c = [(b % 5) as f64 * 2.0 + 1.0, (b / 5) as f64 * 2.0 + 1.0, 0.5];
        let s: [f64; 3] = [0.3 + 0.7 * r(), 0.3 + 0.7 * r(), 0.3 + 0.7 * r()];
        let count = if b + 1 == BOXES {
            n - stray - per_box * (BOXES - 1)
        } else {
            per_box
        };
        for _ in 0..count {
            // A face (axis, side), then a point on it.
            let axis = (r() * 3.0) as usize % 3;
            let side = if r() < 0.5 { -0.5 } else { 0.5 };
            let p: [f64; 3] = [0, 1, 2].map(|a| {
                if a == axis {
                    c[a] + side * s[a]
                } else {
                    c[a] + (r() - 0.5) * s[a]
                }
            });
            pos.push(p.map(|v| v as f32));
        }
    }
    for _ in 0..stray {
        pos.push([(10.0 * r()) as f32, (8.0 * r()) as f32, (3.0 * r()) as f32]);
    }
    let ids: Vec<u32> = (0..pos.len() as u32)
        .map(|i| i.wrapping_mul(2_654_435_761))
        .collect();
    let scores: Vec<f32> = (0..pos.len()).map(|_| (0.28 + 0.12 * r()) as f32).collect();
    let opacities: Vec<f32> = (0..pos.len()).map(|_| (0.5 + 0.5 * r()) as f32).collect();
    (ids, pos, scores, opacities)
}

/// The table: median time of [`group_objects`] (gap 0.1 m given, the default minimum of 10
/// Gaussians: 20 objects) over `args.queries` runs on the [`workload`] of
/// `args.objects_matches` matches. The grouping runs on one thread. The gap is given so that the
/// workload stays the one measured before the default gap was derived from the matches' spacing
/// (which splits these sparse shells: 29 groups at 40K matches).
pub(super) fn table(args: &BenchArgs) -> anyhow::Result<String> {
    let n = args.objects_matches;
    let (ids, pos, scores, opacities) = workload(n, args.seed);
    let m = Matches {
        ids: &ids,
        positions: &pos,
        scores: &scores,
        opacities: Some(&opacities),
    };
    let p = ObjectParams {
        gap: Some(0.1),
        ..ObjectParams::default()
    };
    let mut ts = Vec::new();
    let mut last = None;
    for _ in 0..args.queries {
        let t = Instant::now();
        let o = group_objects(&m, &p)?;
        ts.push(t.elapsed().as_secs_f64() * 1e3);
        last = Some(o);
    }
    let o = last.ok_or_else(|| anyhow::anyhow!("--queries must be at least 1"))?;
    let mut t = Table::with_header("matches | objects | groups suppressed | group_objects ms");
    t.row([
        fmt_size(n),
        o.groups.to_string(),
        o.suppressed.to_string(),
        format!("{:.1}", median(ts)),
    ]);
    Ok(format!(
        "Objects: grouping {} matching Gaussians ({BOXES} box shells of 0.3–1 m, {:.0} % strays \
         in a 10 × 8 × 3 m room; gap {} m, minimum {} Gaussians; one thread, median of {} runs)\n\n{t}",
        fmt_size(n),
        STRAY * 100.0,
        o.gap,
        p.min_gaussians,
        args.queries
    ))
}
