// `blend_sums` (gpu/label_sums.rs): per-(Gaussian, label) sums of the blend weights, accumulated
// per tile in workgroup memory and written as one record per (tile intersection, tile label) with
// a non-zero sum. One 16x16 workgroup per tile, the same front-to-back loop as `blend`.
//
// The tile's distinct labels L_t are found first (the first pixel of each label claims a local
// index 0..|L_t|). Each batch of 256 depth-sorted splats is then processed in sub-batches of
// ACC_SLOTS / |L_t| splats: every pixel adds its weight of each splat to the workgroup slot
// (splat in sub-batch, its label's local index), 64-bit fixed point (w·2^32 truncated, two
// atomic words with carry: exact integer sums, independent of thread order), and the non-zero
// slots are appended to records[]. The output is bounded by construction: at most one record
// per (intersection, tile label) and per labelled contribution, so the count of the first
// dispatch sizes the second exactly when the first did not fit.

// The label of every pixel (0 = none: the pixel is skipped).
@group(0) @binding(12) var<storage, read> labels: array<u32>;
// records[0]: records this dispatch produced (counts past the capacity params.out_cap: the host
// then re-runs the band with room for them), records[1], records[2]: low and high word of the
// labelled contributions counted, records[3] unused; then 4 words per record: Gaussian id,
// label, low and high word of Σ w·2^32 over the tile's pixels of that label.
@group(0) @binding(13) var<storage, read_write> records: array<atomic<u32>>;

// Workgroup accumulator slots (splats of a sub-batch × tile labels); 2 words each.
const ACC_SLOTS: u32 = 512u;
var<workgroup> acc_lo: array<atomic<u32>, 512>;
var<workgroup> acc_hi: array<atomic<u32>, 512>;
// The pixels' labels, then (by local index) the tile's distinct labels.
var<workgroup> sh_pix_label: array<u32, 256>;
var<workgroup> sh_tile_labels: array<u32, 256>;
var<workgroup> sh_n_labels: atomic<u32>;
var<workgroup> sh_n_labels_u: u32;

@compute @workgroup_size(16, 16)
fn blend_sums(t: TileThread) {
    let tp = tile_pixel(t);
    let lid = t.lid;
    var label = 0u;
    if (tp.inside) {
        label = labels[tp.py * params.width + tp.px];
    }
    sh_pix_label[lid] = label;
    tile_begin(tp, lid);
    if (lid == 0u) {
        atomicStore(&sh_n_labels, 0u);
    }
    workgroupBarrier();
    // The tile's distinct labels: the first pixel (in local order) of each claims a local index,
    // kept in sh_id[first pixel] until the first batch overwrites it.
    var first = lid;
    for (var q = 0u; q < lid; q++) {
        if (sh_pix_label[q] == label) {
            first = q;
            break;
        }
    }
    if (first == lid && label != 0u) {
        let li = atomicAdd(&sh_n_labels, 1u);
        sh_tile_labels[li] = label;
        sh_id[lid] = li;
    }
    workgroupBarrier();
    var li = 0u;
    if (label != 0u) {
        li = sh_id[first];
    }
    if (lid == 0u) {
        sh_n_labels_u = atomicLoad(&sh_n_labels);
    }
    let n_labels = workgroupUniformLoad(&sh_n_labels_u);
    if (n_labels == 0u) {
        return; // no labelled pixel in this tile
    }
    let per = ACC_SLOTS / n_labels; // splats per sub-batch, >= 2
    let range = workgroupUniformLoad(&sh_range);
    var count = 0u;
    var walk = walk_start(tp, !tp.inside || label == 0u);
    let n_batches = batch_count(range);
    for (var b = 0u; b < n_batches; b++) {
        if (all_stopped(lid)) {
            break;
        }
        let n_here = load_batch(range, b, lid);
        for (var s0 = 0u; s0 < n_here; s0 += per) {
            let s1 = min(s0 + per, n_here);
            let slots = (s1 - s0) * n_labels;
            for (var i = lid; i < slots; i += BATCH) {
                atomicStore(&acc_lo[i], 0u);
                atomicStore(&acc_hi[i], 0u);
            }
            workgroupBarrier();
            for (var k = s0; k < s1 && !walk.done; k++) {
                let weight = walk_step(&walk, k);
                if (weight == 0.0) {
                    continue;
                }
                // w·2^32 truncated (w <= ALPHA_MAX < 1), added with carry into the high word.
                let slot = (k - s0) * n_labels + li;
                let lo = u32(min(weight * 4294967296.0, 4294967040.0));
                let old = atomicAdd(&acc_lo[slot], lo);
                if (old > 0xFFFFFFFFu - lo) {
                    atomicAdd(&acc_hi[slot], 1u);
                }
                count += 1u;
            }
            workgroupBarrier();
            for (var i = lid; i < slots; i += BATCH) {
                let lo = atomicLoad(&acc_lo[i]);
                let hi = atomicLoad(&acc_hi[i]);
                if (lo != 0u || hi != 0u) {
                    let r = atomicAdd(&records[0], 1u);
                    if (r < params.out_cap) {
                        let base = 4u + r * 4u;
                        atomicStore(&records[base], sh_id[s0 + i / n_labels]);
                        atomicStore(&records[base + 1u], sh_tile_labels[i % n_labels]);
                        atomicStore(&records[base + 2u], lo);
                        atomicStore(&records[base + 3u], hi);
                    }
                }
            }
            // The next sub-batch clears the slots only after every thread has read them.
            workgroupBarrier();
        }
    }
    if (count > 0u) {
        let old = atomicAdd(&records[1], count);
        if (old > 0xFFFFFFFFu - count) {
            atomicAdd(&records[2], 1u);
        }
    }
}
