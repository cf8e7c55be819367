// `blend` (gpu/count_scan.rs, write.rs): one 16x16 workgroup per tile; its workgroup splat
// arrays, shared with `blend_sums` (label_sums.wgsl), are declared in common.wgsl.

@compute @workgroup_size(16, 16)
fn blend(t: TileThread) {
    let tp = tile_pixel(t);
    let lid = t.lid;
    let pix = tp.py * params.width + tp.px;
    let write = params.mode == 1u;
    tile_begin(tp, lid);
    let range = workgroupUniformLoad(&sh_range);
    var out = 0u;
    var out_end = 0u;
    if (write && tp.inside) {
        out = offsets[pix] - params.out_base;
        out_end = offsets[pix + 1u] - params.out_base;
    }
    var count = 0u;
    var walk = walk_start(tp, !tp.inside);
    let n_batches = batch_count(range);
    for (var b = 0u; b < n_batches; b++) {
        if (all_stopped(lid)) {
            break;
        }
        let n_here = load_batch(range, b, lid);
        for (var k = 0u; k < n_here && !walk.done; k++) {
            let weight = walk_step(&walk, k);
            if (weight == 0.0) {
                continue;
            }
            if (write) {
                // Bounded by the count pass's range: never writes outside this pixel's slots.
                if (out < out_end) {
                    out_ids[out] = sh_id[k];
                    out_weights[out] = weight;
                    out += 1u;
                }
            } else {
                count += 1u;
            }
        }
    }
    if (params.mode == 0u && tp.inside) {
        offsets[pix] = count;
    }
}

