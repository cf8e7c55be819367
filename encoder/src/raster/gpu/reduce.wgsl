// The label-sum records of one band reduced on the device (gpu/reduce.rs), after `blend_sums`
// wrote them (records[], label_sums.wgsl: a header of 4 words, then 4 words per record) and the
// host read their count n = params.n_keys:
//
//   record_keys    one thread per record r: keys_out[r] = (label, Gaussian) (low word, high
//                  word), vals_out[r] = r.
//   radix passes   (sort.wgsl) the keys ordered by (Gaussian, label), 4 bits a pass over the
//                  label bits the view needs, then the Gaussian-id bits; stable, so the records
//                  of one key keep their index order.
//   record_heads   one thread per sorted key: offsets[i] = 1 where a run of equal keys starts.
//   scan_*         (scan.wgsl) exclusive prefix sum of the heads: each run's output slot, the
//                  number of distinct keys in offsets[n].
//   record_sums    one thread per run head: the run's 64-bit fixed-point sums added in u32 words
//                  with carry (integers: exact, independent of order) and written as one record
//                  (Gaussian, label, low word, high word) to reduced[its slot].
//
// The result is the host's reduction (LabelSums::reduced): sorted by (Gaussian, label), one
// record per key. Bounds: keys and values n each (the sort buffers), offsets n + 1 words,
// reduced n records; every index is checked against n.

// One reduced record per distinct (Gaussian, label): Gaussian, label, low and high word of the sum.
@group(0) @binding(20) var<storage, read_write> reduced: array<vec4<u32>>;

// Index of this invocation in a 2D dispatch of 256-wide workgroups (x extent params.groups_x).
fn flat_index(wid: vec3<u32>, lid: u32) -> u32 {
    return (wid.y * params.groups_x + wid.x) * 256u + lid;
}

// Whether sorted key i starts a run of equal keys.
fn run_head(i: u32) -> bool {
    return i == 0u || any(keys_in[i - 1u] != keys_in[i]);
}

@compute @workgroup_size(256)
fn record_keys(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let r = flat_index(wid, lid);
    if (r >= params.n_keys) {
        return;
    }
    let base = 4u + r * 4u;
    keys_out[r] = vec2<u32>(atomicLoad(&records[base + 1u]), atomicLoad(&records[base]));
    vals_out[r] = r;
}

@compute @workgroup_size(256)
fn record_heads(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = flat_index(wid, lid);
    if (i >= params.n_keys) {
        return;
    }
    offsets[i] = select(0u, 1u, run_head(i));
}

@compute @workgroup_size(256)
fn record_sums(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = flat_index(wid, lid);
    if (i >= params.n_keys) {
        return;
    }
    if (!run_head(i)) {
        return; // not the first record of its key
    }
    let k = keys_in[i];
    var lo = 0u;
    var hi = 0u;
    var j = i;
    loop {
        if (j >= params.n_keys || any(keys_in[j] != k)) {
            break;
        }
        let base = 4u + vals_in[j] * 4u;
        let add_lo = atomicLoad(&records[base + 2u]);
        let sum_lo = lo + add_lo;
        hi += atomicLoad(&records[base + 3u]) + select(0u, 1u, sum_lo < lo);
        lo = sum_lo;
        j += 1u;
    }
    reduced[offsets[i]] = vec4<u32>(k.y, k.x, lo, hi);
}
