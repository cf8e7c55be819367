// Tile binning and the depth sort (gpu/sort.rs), after `project` has written every Gaussian's tile
// count into offsets[i] and the scan kernels have turned the counts into exclusive offsets (the
// total M of (Gaussian, tile) intersections in offsets[n_gaussians]):
//
//   emit           one thread per Gaussian: one 64-bit key per intersection at offsets[i]..,
//                  keys_out[e] = (f32 depth bits, tile id) (low word, high word), vals_out[e] = i.
//                  The unsorted list is therefore in Gaussian-id order.
//   radix_count    one workgroup per block of RADIX_BLOCK keys: the block's histogram of the
//                  4-bit digit at bit params.shift of the key, written digit-major to
//                  offsets[digit * sort blocks + block].
//   scan_*         (scan.wgsl) exclusive prefix sum of that histogram: the first output slot of
//                  every (digit, block).
//   radix_scatter  the same blocks: every key and its value to its digit's next slot, the keys of
//                  one digit in input order (stable). One pass per digit, least significant first
//                  (depth bits 0..31, then only as many tile-id bits as the view's grid needs):
//                  the keys end up ordered by (tile, depth), equal depths by Gaussian id.
//   tile_bounds    one thread per sorted key: the [start, end) range of each tile that has keys
//                  (the host clears ranges_out to [0, 0) first, so empty tiles read [0, 0)).
//
// Bounds (params.n_keys = M, at most the sort buffers' capacity): keys_in/keys_out 8 bytes and
// vals_in/vals_out 4 bytes per intersection; the histogram 16 words per block of RADIX_BLOCK keys;
// ranges_out 2 words per tile. Depths are positive (project culls t.z < NEAR_PLANE), so their f32
// bit patterns order like their values.

// Keys and values of one radix pass (input, output: ping-pong buffers).
@group(0) @binding(14) var<storage, read> keys_in: array<vec2<u32>>;
@group(0) @binding(15) var<storage, read> vals_in: array<u32>;
@group(0) @binding(16) var<storage, read_write> keys_out: array<vec2<u32>>;
@group(0) @binding(17) var<storage, read_write> vals_out: array<u32>;
// Per tile: start, end (2 words), read by `blend` / `blend_sums` as tile_ranges.
@group(0) @binding(18) var<storage, read_write> ranges_out: array<u32>;

// Keys per workgroup of the radix passes: 256 invocations × 4 consecutive keys.
const RADIX_BLOCK: u32 = 1024u;
const RADIX_DIGITS: u32 = 16u;

// Blocks of RADIX_BLOCK keys in this view.
fn radix_blocks() -> u32 {
    return (params.n_keys + RADIX_BLOCK - 1u) / RADIX_BLOCK;
}

// The 4-bit digit at bit params.shift (0..63) of the 64-bit key tile << 32 | depth bits.
fn radix_digit(k: vec2<u32>) -> u32 {
    if (params.shift >= 32u) {
        return (k.y >> (params.shift - 32u)) & 15u;
    }
    return (k.x >> params.shift) & 15u;
}

@compute @workgroup_size(256)
fn emit(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = (wid.y * params.groups_x + wid.x) * 256u + lid;
    if (i >= params.n_gaussians) {
        return;
    }
    let r = isect[i]; // empty for culled Gaussians
    let x0 = r.x & 0xffffu;
    let y0 = r.x >> 16u;
    let x1 = r.y & 0xffffu;
    let y1 = r.y >> 16u;
    let d = splats[i].xy_opac.w;
    var depth_bits = 0u;
    if (d > 0.0) {
        depth_bits = bitcast<u32>(d);
    }
    var e = offsets[i];
    for (var y = y0; y < y1; y++) {
        for (var x = x0; x < x1; x++) {
            // Bounded by the buffers' capacity (the host sized them from the total).
            if (e < params.n_keys) {
                keys_out[e] = vec2<u32>(depth_bits, y * params.tiles_x + x);
                vals_out[e] = i;
            }
            e += 1u;
        }
    }
}

var<workgroup> sh_hist: array<atomic<u32>, 16>;

@compute @workgroup_size(256)
fn radix_count(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let block = wid.y * params.groups_x + wid.x;
    let n_blocks = radix_blocks();
    if (block >= n_blocks) {
        return; // uniform: the same for the whole workgroup
    }
    if (lid < RADIX_DIGITS) {
        atomicStore(&sh_hist[lid], 0u);
    }
    workgroupBarrier();
    let base = block * RADIX_BLOCK + lid * 4u;
    for (var j = 0u; j < 4u; j++) {
        if (base + j < params.n_keys) {
            atomicAdd(&sh_hist[radix_digit(keys_in[base + j])], 1u);
        }
    }
    workgroupBarrier();
    if (lid < RADIX_DIGITS) {
        offsets[lid * n_blocks + block] = atomicLoad(&sh_hist[lid]);
    }
}

// Per invocation, its keys' digit counts packed 16 bits per digit (a block has at most 1024 keys
// of one digit): digits 0..7 in sh_counts[lid], 8..15 in sh_counts[256 + lid], two per word.
var<workgroup> sh_counts: array<vec4<u32>, 512>;
// The block's first output slot of every digit (the scanned histogram).
var<workgroup> sh_digit_base: array<u32, 16>;

// `packed` (digits 0..7 in lo, 8..15 in hi) plus one of digit d.
fn count_digit(lo: ptr<function, vec4<u32>>, hi: ptr<function, vec4<u32>>, d: u32) {
    let w = (d >> 1u) & 3u;
    let inc = 1u << ((d & 1u) * 16u);
    if (d < 8u) {
        (*lo)[w] += inc;
    } else {
        (*hi)[w] += inc;
    }
}

// The count of digit d in a packed pair.
fn digit_count(lo: vec4<u32>, hi: vec4<u32>, d: u32) -> u32 {
    let w = (d >> 1u) & 3u;
    var v = lo[w];
    if (d >= 8u) {
        v = hi[w];
    }
    return (v >> ((d & 1u) * 16u)) & 0xffffu;
}

@compute @workgroup_size(256)
fn radix_scatter(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let block = wid.y * params.groups_x + wid.x;
    let n_blocks = radix_blocks();
    if (block >= n_blocks) {
        return; // uniform
    }
    if (lid < RADIX_DIGITS) {
        sh_digit_base[lid] = offsets[lid * n_blocks + block];
    }
    // This invocation's 4 consecutive keys (digit 16: past the end, not written).
    let base = block * RADIX_BLOCK + lid * 4u;
    var keys: array<vec2<u32>, 4>;
    var vals: array<u32, 4>;
    var digits = array<u32, 4>(16u, 16u, 16u, 16u);
    var lo = vec4<u32>(0u);
    var hi = vec4<u32>(0u);
    for (var j = 0u; j < 4u; j++) {
        if (base + j < params.n_keys) {
            keys[j] = keys_in[base + j];
            vals[j] = vals_in[base + j];
            digits[j] = radix_digit(keys[j]);
            count_digit(&lo, &hi, digits[j]);
        }
    }
    // Inclusive scan of the packed counts over the invocations (Hillis-Steele; lanes never carry:
    // every partial count is at most 1024).
    sh_counts[lid] = lo;
    sh_counts[256u + lid] = hi;
    for (var off = 1u; off < 256u; off = off * 2u) {
        workgroupBarrier();
        var a = vec4<u32>(0u);
        var b = vec4<u32>(0u);
        if (lid >= off) {
            a = sh_counts[lid - off];
            b = sh_counts[256u + lid - off];
        }
        workgroupBarrier();
        sh_counts[lid] += a;
        sh_counts[256u + lid] += b;
    }
    workgroupBarrier();
    // Keys of each digit before this invocation's (exclusive scan), then one by one.
    var seen_lo = sh_counts[lid] - lo;
    var seen_hi = sh_counts[256u + lid] - hi;
    for (var j = 0u; j < 4u; j++) {
        let d = digits[j];
        if (d < RADIX_DIGITS) {
            let dst = sh_digit_base[d] + digit_count(seen_lo, seen_hi, d);
            keys_out[dst] = keys[j];
            vals_out[dst] = vals[j];
            count_digit(&seen_lo, &seen_hi, d);
        }
    }
}

@compute @workgroup_size(256)
fn tile_bounds(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = (wid.y * params.groups_x + wid.x) * 256u + lid;
    if (i >= params.n_keys) {
        return;
    }
    let t = keys_in[i].y;
    if (i == 0u || keys_in[i - 1u].y != t) {
        ranges_out[2u * t] = i;
    }
    if (i + 1u == params.n_keys || keys_in[i + 1u].y != t) {
        ranges_out[2u * t + 1u] = i + 1u;
    }
}
