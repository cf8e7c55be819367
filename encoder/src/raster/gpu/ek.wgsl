// The device reduction E_k = Σ_i Σ_j a_kj·E_j / Σ_i Σ_j a_kj (gpu/ek/), a shader module of its own
// because it needs f64 (wgpu's SHADER_F64): the raster module compiles on devices without it.
//
// Each labelled view leaves its device-reduced label sums on the device (records sorted by
// (Gaussian, label), one per key: Gaussian, label, low and high word of the 2^-32 fixed-point sum),
// with its label table (the masks of each pixel label, the masks' weighting factors) and the base
// of its masks in the codebook. Nothing per entry is read back.
//
//   block_starts   one thread per record of one view: starts[b] = index of the first record whose
//                  Gaussian is at or after b·BLOCK_GAUSSIANS (starts[n_blocks] = n), so that the
//                  host cuts any tile of whole blocks out of every view without reading records.
//   ek_reduce      at the end, per tile of Gaussians: the tile's records of every view copied
//                  into one buffer (after a 4-word header, view by view), stably radix-sorted by
//                  Gaussian (sort.wgsl, by the raster module: record_keys + radix passes), each
//                  Gaussian's run start marked (run_starts), then one 64-wide workgroup per
//                  Gaussian of the tile that has records: the run's
//                  records, view by view, expanded to the view's masks exactly as the host's image
//                  stage does (aggregate::image::expand_labels: per mask, ascending, the f64 sum of
//                  the sums of the labels holding it, rounded to f32, times the mask's factor),
//                  then added as the host's reduction does (aggregate::reduce: Σ a and Σ a·E_j in
//                  f64, a f32 widened, each thread D/64 dimensions in registers), the `keep`
//                  largest (a, codebook row) kept as aggregate::mixture's push_top keeps them, the
//                  norm summed over the workgroup, the unobserved rule applied, and the Gaussian's
//                  results written: meta (observed, Σ a as f32), kept pairs, and with `dense` the
//                  unit row E_k in f32.

const BLOCK_GAUSSIANS: u32 = 4096u;
const WG: u32 = 64u;
// Most dimensions per thread (D ≤ WG · MAX_PER_THREAD = 1024) and most kept pairs.
const MAX_PER_THREAD: u32 = 16u;
const MAX_KEEP: u32 = 32u;
const UNUSED: u32 = 0xffffffffu;
// gmeta's first word for a Gaussian whose reduction the driver cut short (loops_ran_in_full).
const CUT_SHORT: u32 = 2u;

struct EkParams {
    min_total_weight: f64,
    n_records: u32,      // records of the tile (block_starts: of the view)
    g0: u32,             // first Gaussian of the tile
    n_tile: u32,         // Gaussians of the tile
    dim: u32,
    keep: u32,
    n_segments: u32,     // segments (view parts) of the tile
    groups_x: u32,       // x extent of the 2D dispatch
    dense: u32,          // 1: write the unit rows
    n_blocks: u32,       // block_starts: blocks of BLOCK_GAUSSIANS over the scene
    pad0: u32,
}

@group(0) @binding(0) var<uniform> ep: EkParams;
// The tile's records after a 4-word header (block_starts: one view's records, no header).
@group(0) @binding(1) var<storage, read> recs: array<vec4<u32>>;
// ek_reduce: record indices sorted by Gaussian (stable). block_starts: the starts written.
@group(0) @binding(2) var<storage, read_write> order: array<u32>;
// Per segment: first record (tile index), view id, label-table base, codebook base.
@group(0) @binding(3) var<storage, read> segs: array<vec4<u32>>;
// Label tables: at a view's base, n_labels + 1 offsets (relative to the base), the masks of
// every label, then at base + tables[base + n_labels] ... see ek.rs (ViewTable) for the layout.
@group(0) @binding(4) var<storage, read> tables: array<u32>;
@group(0) @binding(5) var<storage, read> codebook: array<f32>;
// Per tile Gaussian: observed (0/1, or CUT_SHORT when cut short), Σ a as f32 bits.
@group(0) @binding(6) var<storage, read_write> gmeta: array<vec2<u32>>;
// Per tile Gaussian, `keep` slots: codebook row (UNUSED when empty), a as f32 bits.
@group(0) @binding(7) var<storage, read_write> kept: array<vec2<u32>>;
// With `dense`: per tile Gaussian, the unit row E_k (dim f32).
@group(0) @binding(8) var<storage, read_write> rows: array<f32>;

var<workgroup> norm_part: array<f64, 64>;
// ek_reduce: the workgroup's Gaussian's run_start (read by every thread).
var<workgroup> wg_start: u32;
// ek_reduce: 1 when a thread's loops were cut short (zeroed at the workgroup's start).
var<workgroup> wg_cut: atomic<u32>;
// Per tile Gaussian: 1 + the sorted position of its first record, 0 when it has none
// (run_starts writes it, ek_reduce reads it).
@group(0) @binding(11) var<storage, read_write> run_start: array<u32>;

fn flat_group(wid: vec3<u32>) -> u32 {
    return wid.y * ep.groups_x + wid.x;
}

@compute @workgroup_size(256)
fn block_starts(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let r = flat_group(wid) * 256u + lid;
    if (r >= ep.n_records) {
        return;
    }
    let b = recs[r].x / BLOCK_GAUSSIANS;
    var first = 0u;
    if (r > 0u) {
        first = recs[r - 1u].x / BLOCK_GAUSSIANS + 1u;
    }
    for (var bb = first; bb <= b; bb++) {
        order[bb] = r;
    }
    if (r + 1u == ep.n_records) {
        for (var bb = b + 1u; bb <= ep.n_blocks; bb++) {
            order[bb] = ep.n_records;
        }
    }
}

// The tile record at sorted position i.
fn rec_at(i: u32) -> vec4<u32> {
    return recs[order[i] + 1u];
}

// The segment of tile record r: the last segment starting at or before r (an empty segment
// starts where the next one does, so the last wins).
fn segment_of(r: u32) -> u32 {
    var lo = 0u;
    var hi = ep.n_segments;
    while (hi - lo > 1u) {
        let mid = (lo + hi) / 2u;
        if (segs[mid].x <= r) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    return lo;
}

// The label sum of record `rec` in pixels (2^-32 fixed point to f64: one rounding, as u64 → f64).
fn record_weight(rec: vec4<u32>) -> f64 {
    return (f64(rec.w) * 4294967296.0lf + f64(rec.z)) / 4294967296.0lf;
}

// Masks of `label` in the table at `base`: [first, end) indices into tables[].
fn label_masks(base: u32, label: u32) -> vec2<u32> {
    let n_labels = tables[base];
    if (label >= n_labels) {
        return vec2<u32>(0u, 0u);
    }
    let off = base + 2u;
    return vec2<u32>(base + tables[off + label], base + tables[off + label + 1u]);
}

// Record i: at sorted position i of the tile (`sorted`, ek_reduce), else recs[i] (one view's
// records, `dominant`).
fn record_at(i: u32, sorted: bool) -> vec4<u32> {
    if (sorted) {
        return rec_at(i);
    }
    return recs[i];
}

// The smallest mask above `after` (all masks when `first`) among the labels of records [p, q)
// (as record_at reads them) of one view, or UNUSED.
fn next_mask(p: u32, q: u32, base: u32, after: u32, first: bool, sorted: bool) -> u32 {
    var best = UNUSED;
    for (var i = p; i < q; i++) {
        let m = label_masks(base, record_at(i, sorted).y);
        for (var t = m.x; t < m.y; t++) {
            let j = tables[t];
            if ((first || j > after) && j < best) {
                best = j;
            }
        }
    }
    return best;
}

// Σ, in record order, of the sums of the records of [p, q) (as record_at reads them) whose label
// holds mask j (f64).
fn mask_sum(p: u32, q: u32, base: u32, j: u32, sorted: bool) -> f64 {
    var a = 0.0lf;
    for (var i = p; i < q; i++) {
        let rec = record_at(i, sorted);
        let m = label_masks(base, rec.y);
        for (var t = m.x; t < m.y; t++) {
            if (tables[t] == j) {
                a += record_weight(rec);
            }
        }
    }
    return a;
}

// The factor of mask j of the view whose table is at `base`.
fn mask_factor(base: u32, j: u32) -> f32 {
    let factors = base + tables[base + 1u];
    return bitcast<f32>(tables[factors + j]);
}

// push_top (aggregate::mixture's): the pair (a, atom) into the `ep.keep` slots of kept_a /
// kept_atom, n_kept of them used: fill, then replace the weakest (least a; of equal a, the
// larger row) by a stronger pair.
fn push_top(
    kept_a: ptr<function, array<f32, 32>>,
    kept_atom: ptr<function, array<u32, 32>>,
    n_kept: ptr<function, u32>,
    a: f32,
    atom: u32,
) {
    if (*n_kept < ep.keep) {
        (*kept_a)[*n_kept] = a;
        (*kept_atom)[*n_kept] = atom;
        *n_kept = *n_kept + 1u;
        return;
    }
    var w = 0u;
    for (var s = 1u; s < *n_kept; s++) {
        let weaker = (*kept_a)[s] < (*kept_a)[w]
            || ((*kept_a)[s] == (*kept_a)[w] && (*kept_atom)[s] > (*kept_atom)[w]);
        if (weaker) {
            w = s;
        }
    }
    if (a > (*kept_a)[w] || (a == (*kept_a)[w] && atom < (*kept_atom)[w])) {
        (*kept_a)[w] = a;
        (*kept_atom)[w] = atom;
    }
}

// One thread per sorted record of the tile: the first record of each Gaussian's run writes
// where the run starts, so that ek_reduce runs one workgroup per Gaussian, not per record.
@compute @workgroup_size(256)
fn run_starts(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = flat_group(wid) * 256u + lid;
    if (i >= ep.n_records) {
        return;
    }
    let k = rec_at(i).x;
    if (i == 0u || rec_at(i - 1u).x != k) {
        run_start[k - ep.g0] = i + 1u;
    }
}

// Whether this invocation's loops ran their full course. Some drivers end every loop of an
// invocation once its loops ran a fixed number of iterations in all (lavapipe: 65,535): a
// Gaussian with that many terms would be reduced in part, without a word. A last loop of
// `keep + 1` iterations (a bound the compiler cannot see) tells: cut short, it ends after one.
fn loops_ran_in_full() -> bool {
    var canary = 0u;
    loop {
        canary++;
        if (canary > ep.keep) {
            break;
        }
    }
    return canary > ep.keep;
}

@compute @workgroup_size(64)
fn ek_reduce(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    // One workgroup per tile Gaussian; one without records leaves at once. The norm's
    // workgroup sum needs every thread at its barriers, so the test is made uniform through
    // workgroup memory (thread 0's read is the workgroup's).
    let g = flat_group(wid);
    if (lid == 0u) {
        var s = 0u;
        if (g < ep.n_tile) {
            s = run_start[g];
        }
        wg_start = s;
    }
    let start = workgroupUniformLoad(&wg_start);
    if (start == 0u) {
        return;
    }
    let i0 = start - 1u;
    let k = rec_at(i0).x;
    var acc: array<f64, 16>;
    for (var t = 0u; t < MAX_PER_THREAD; t++) {
        acc[t] = 0.0lf;
    }
    var den = 0.0lf;
    var kept_a: array<f32, 32>;
    var kept_atom: array<u32, 32>;
    var n_kept = 0u;
    var end = i0 + 1u;
    while (end < ep.n_records && rec_at(end).x == k) {
        end++;
    }
    var p = i0;
    while (p < end) {
        // One view's records of this Gaussian (a view's parts share its id): [p, q).
        let seg = segs[segment_of(order[p])];
        var q = p + 1u;
        while (q < end && segs[segment_of(order[q])].y == seg.y) {
            q++;
        }
        let base = seg.z;
        var j = next_mask(p, q, base, 0u, true, true);
        while (j != UNUSED) {
            let a64 = mask_sum(p, q, base, j, true);
            if (a64 > 0.0lf) {
                let a = f32(a64) * mask_factor(base, j);
                let atom = seg.w + j;
                let wa = f64(a);
                den += wa;
                let row = atom * ep.dim;
                for (var t = 0u; t < MAX_PER_THREAD; t++) {
                    let d = lid + t * WG;
                    if (d < ep.dim) {
                        acc[t] += wa * f64(codebook[row + d]);
                    }
                }
                push_top(&kept_a, &kept_atom, &n_kept, a, atom);
            }
            j = next_mask(p, q, base, j, false, true);
        }
        p = q;
    }
    var sq = 0.0lf;
    for (var t = 0u; t < MAX_PER_THREAD; t++) {
        sq += acc[t] * acc[t];
    }
    norm_part[lid] = sq;
    workgroupBarrier();
    for (var stride = 32u; stride > 0u; stride = stride / 2u) {
        if (lid < stride) {
            norm_part[lid] += norm_part[lid + stride];
        }
        workgroupBarrier();
    }
    let norm = sqrt(norm_part[0]);
    // Unobserved (nothing written; meta, kept and rows were cleared): Σ a NaN or below the
    // threshold, or the norm not finite or at most 1e-9·Σ a.
    let finite = norm == norm && norm <= 1.7976931348623157e308lf;
    let observed = den >= ep.min_total_weight && finite && norm > 1e-9lf * den;
    let kl = k - ep.g0;
    if (observed && lid == 0u) {
        gmeta[kl] = vec2<u32>(1u, bitcast<u32>(f32(den)));
        for (var s = 0u; s < ep.keep; s++) {
            if (s < n_kept) {
                kept[kl * ep.keep + s] = vec2<u32>(kept_atom[s], bitcast<u32>(kept_a[s]));
            } else {
                kept[kl * ep.keep + s] = vec2<u32>(UNUSED, 0u);
            }
        }
    }
    if (observed && ep.dense == 1u) {
        for (var t = 0u; t < MAX_PER_THREAD; t++) {
            let d = lid + t * WG;
            if (d < ep.dim) {
                rows[kl * ep.dim + d] = f32(acc[t] / norm);
            }
        }
    }
    // Cut short (loops_ran_in_full; last, so that no loop comes after it), the Gaussian is
    // marked CUT_SHORT: the host refuses the tile.
    if (!loops_ran_in_full()) {
        atomicStore(&wg_cut, 1u);
    }
    workgroupBarrier();
    if (lid == 0u && atomicLoad(&wg_cut) != 0u) {
        gmeta[kl] = vec2<u32>(CUT_SHORT, 0u);
    }
}

// The streamed reduction (gpu/fold.rs): instead of keeping every view until the end, the kept
// views are folded, a wave at a time, into a running state per Gaussian: Σ a in f64 and the
// `keep` slots of push_top, exactly the values ek_reduce holds in registers after the same views.
// A wave's views all come before the next wave's in the encode's view order, so each Gaussian's
// terms are added in the order ek_reduce adds them: the state after the last wave is the state
// ek_reduce reaches, bit for bit.
//
//   ek_fold     per tile Gaussian that has records in the wave (one thread each): its state read,
//               its records view by view expanded and added as ek_reduce does, its state written.
//   ek_finish   per tile Gaussian: the unobserved rule on Σ a (below the threshold, not positive,
//               or not finite: nothing written) and the meta and kept pairs as ek_reduce writes
//               them (or CUT_SHORT where a fold was cut short).
//
// State, per Gaussian of the bound chunk (index k - ep.pad0): Σ a (f64), and `keep` slots of
// (codebook row + 1, a bits), 0 where unused (a cleared buffer is the empty state). Σ a is
// CUT_SHORT_DEN (below 0, which no sum of a ≥ 0 is) once a fold of the Gaussian was cut short
// (loops_ran_in_full): later folds leave it so, and ek_finish marks the Gaussian CUT_SHORT.
@group(0) @binding(12) var<storage, read_write> state_den: array<f64>;
@group(0) @binding(13) var<storage, read_write> state_kept: array<vec2<u32>>;
const CUT_SHORT_DEN: f64 = -1.0lf;

@compute @workgroup_size(64)
fn ek_fold(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let g = flat_group(wid) * 64u + lid;
    if (g >= ep.n_tile) {
        return;
    }
    let start = run_start[g];
    if (start == 0u) {
        return;
    }
    let i0 = start - 1u;
    let k = rec_at(i0).x;
    let sl = k - ep.pad0;
    var den = state_den[sl];
    if (den < 0.0lf) {
        return;
    }
    var kept_a: array<f32, 32>;
    var kept_atom: array<u32, 32>;
    var n_kept = 0u;
    for (var s = 0u; s < ep.keep; s++) {
        let v = state_kept[sl * ep.keep + s];
        if (v.x == 0u) {
            break;
        }
        kept_atom[n_kept] = v.x - 1u;
        kept_a[n_kept] = bitcast<f32>(v.y);
        n_kept++;
    }
    var end = i0 + 1u;
    while (end < ep.n_records && rec_at(end).x == k) {
        end++;
    }
    var p = i0;
    while (p < end) {
        let seg = segs[segment_of(order[p])];
        var q = p + 1u;
        while (q < end && segs[segment_of(order[q])].y == seg.y) {
            q++;
        }
        let base = seg.z;
        var j = next_mask(p, q, base, 0u, true, true);
        while (j != UNUSED) {
            let a64 = mask_sum(p, q, base, j, true);
            if (a64 > 0.0lf) {
                let a = f32(a64) * mask_factor(base, j);
                let atom = seg.w + j;
                den += f64(a);
                push_top(&kept_a, &kept_atom, &n_kept, a, atom);
            }
            j = next_mask(p, q, base, j, false, true);
        }
        p = q;
    }
    state_den[sl] = den;
    for (var s = 0u; s < n_kept; s++) {
        state_kept[sl * ep.keep + s] = vec2<u32>(kept_atom[s] + 1u, bitcast<u32>(kept_a[s]));
    }
    // Last, so that no loop comes after it.
    if (!loops_ran_in_full()) {
        state_den[sl] = CUT_SHORT_DEN;
    }
}

@compute @workgroup_size(64)
fn ek_finish(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let g = flat_group(wid) * 64u + lid;
    if (g >= ep.n_tile) {
        return;
    }
    let sl = ep.g0 + g - ep.pad0;
    let den = state_den[sl];
    if (den < 0.0lf) {
        gmeta[g] = vec2<u32>(CUT_SHORT, 0u);
        return;
    }
    let finite = den == den && den <= 1.7976931348623157e308lf;
    if (!(den >= ep.min_total_weight && den > 0.0lf && finite)) {
        return;
    }
    gmeta[g] = vec2<u32>(1u, bitcast<u32>(f32(den)));
    for (var s = 0u; s < ep.keep; s++) {
        let v = state_kept[sl * ep.keep + s];
        if (v.x == 0u) {
            kept[g * ep.keep + s] = vec2<u32>(UNUSED, 0u);
        } else {
            kept[g * ep.keep + s] = vec2<u32>(v.x - 1u, v.y);
        }
    }
}

// The dominant mask of one Gaussian in one view, from its records [r, end) (no order; table at
// `base`): argmax_j a_kj with a_kj as ek_reduce makes it (ties: the smaller mask), as (mask,
// a bits), or (UNUSED, 0) when no mask holds a positive a_kj.
fn view_dominant(r: u32, end: u32, base: u32) -> vec2<u32> {
    var best_j = UNUSED;
    var best_a = 0.0;
    var j = next_mask(r, end, base, 0u, true, false);
    while (j != UNUSED) {
        let a64 = mask_sum(r, end, base, j, false);
        if (a64 > 0.0lf) {
            let a = f32(a64) * mask_factor(base, j);
            if (best_j == UNUSED || a > best_a) {
                best_j = j;
                best_a = a;
            }
        }
        j = next_mask(r, end, base, j, false, false);
    }
    return vec2<u32>(best_j, bitcast<u32>(best_a));
}

// The end of the run of records of the Gaussian whose first record is r, or 0 when r does not
// start a run (one view's records, no order).
fn run_end(r: u32) -> u32 {
    let k = recs[r].x;
    if (r > 0u && recs[r - 1u].x == k) {
        return 0u;
    }
    var end = r + 1u;
    while (end < ep.n_records && recs[end].x == k) {
        end++;
    }
    return end;
}

// The masks' record's view data (slag_common::mask_record), from one kept view's records (no
// header, no order; ep.n_records of them, table at ep.pad0): one thread per record; the first
// record of each Gaussian writes the Gaussian's dominant mask of the view (view_dominant), as
// (Gaussian, mask, a bits) at its own index; every other record writes (UNUSED, 0, 0). Output
// in `kept` (as vec2 pairs: 2 per record, (Gaussian, mask) then (a bits, 0)).
@compute @workgroup_size(256)
fn dominant(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let r = flat_group(wid) * 256u + lid;
    if (r >= ep.n_records) {
        return;
    }
    kept[2u * r] = vec2<u32>(UNUSED, 0u);
    kept[2u * r + 1u] = vec2<u32>(0u, 0u);
    let end = run_end(r);
    if (end == 0u) {
        return;
    }
    let best = view_dominant(r, end, ep.pad0);
    if (best.x != UNUSED) {
        kept[2u * r] = vec2<u32>(recs[r].x, best.x);
        kept[2u * r + 1u] = vec2<u32>(best.y, 0u);
    }
}

// The masks' record kept on the device (record.rs): per Gaussian `slots` slots of ((view + 1)
// << 16 | mask, a bits), 0 when unused (so a zeroed buffer is an empty record), in
// slag_common::mask_record's order: a_kj descending, then view ascending, unused last.
struct RecordParams {
    view: u32,           // the encode's view index (below 65,535)
    slots: u32,
    n_gaussians: u32,
    pad0: u32,
}

@group(0) @binding(9) var<uniform> rp: RecordParams;
@group(0) @binding(10) var<storage, read_write> mask_record: array<vec2<u32>>;

// Whether (a, view) ranks before the used slot s (a_kj descending, then view ascending).
fn ranks_before(a: f32, view: u32, s: vec2<u32>) -> bool {
    let w = bitcast<f32>(s.y);
    return a > w || (a == w && view < (s.x >> 16u) - 1u);
}

// Gaussian k's dominant mask `mask` (a_kj `a`) of view rp.view into its slots, as
// MaskRecord::add_view enters it. An earlier band of the same view may have entered another
// mask for k: the better of the two stays (largest a_kj, ties to the smaller mask), as the
// host keeps the best of a view's bands.
fn record_insert(k: u32, mask: u32, a: f32) {
    let base = k * rp.slots;
    let tag = (rp.view + 1u) << 16u;
    for (var i = 0u; i < rp.slots; i++) {
        let s = mask_record[base + i];
        if ((s.x & 0xffff0000u) == tag) {
            let w = bitcast<f32>(s.y);
            if (!(a > w || (a == w && mask < (s.x & 0xffffu)))) {
                return;
            }
            for (var t = i; t + 1u < rp.slots; t++) {
                mask_record[base + t] = mask_record[base + t + 1u];
            }
            mask_record[base + rp.slots - 1u] = vec2<u32>(0u, 0u);
            break;
        }
    }
    var pos = rp.slots;
    for (var i = 0u; i < rp.slots; i++) {
        let s = mask_record[base + i];
        if (s.x == 0u || ranks_before(a, rp.view, s)) {
            pos = i;
            break;
        }
    }
    if (pos == rp.slots) {
        return;
    }
    for (var t = rp.slots - 1u; t > pos; t--) {
        mask_record[base + t] = mask_record[base + t - 1u];
    }
    mask_record[base + pos] = vec2<u32>(tag | mask, bitcast<u32>(a));
}

// The masks' record of one kept band, on the device: as `dominant`, but each Gaussian's
// dominant mask goes straight into its slots (record_insert) instead of to the host. One
// thread per Gaussian of the band, so no two threads touch the same slots; a view's bands run
// one after the other. Masks past 65,535, Gaussians past the record and a_kj that is not
// positive and finite are not recorded (as on the host).
@compute @workgroup_size(256)
fn record_dominant(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let r = flat_group(wid) * 256u + lid;
    if (r >= ep.n_records) {
        return;
    }
    let end = run_end(r);
    let k = recs[r].x;
    if (end == 0u || k >= rp.n_gaussians) {
        return;
    }
    let best = view_dominant(r, end, ep.pad0);
    let a = bitcast<f32>(best.y);
    if (best.x > 0xffffu || !(a > 0.0) || a > bitcast<f32>(0x7f7fffffu)) {
        return;
    }
    record_insert(k, best.x, a);
}
