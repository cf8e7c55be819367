// The coverage pass's kernels (gpu/coverage.rs): every Gaussian's total blend weight in a view,
// W_k = Σ_p w_kp over every raster pixel, kept on the device; only a bitset of the Gaussians whose
// W_k reaches the floor leaves it.
//
//   blend_totals   one 16x16 workgroup per tile, the same front-to-back loop as `blend_sums` with
//                  every pixel in one label: each splat's weights over the tile are summed in
//                  workgroup memory (w·2^32 truncated, two atomic words with carry, exactly as
//                  `blend_sums` sums them), and the tile's sum is added to the Gaussian's 64-bit
//                  total in totals[] (again with carry): integer sums, so a total does not depend
//                  on thread order, and it equals the label-sum records of the view reduced.
//   coverage_seen  one thread per Gaussian: a total of at least the floor (params.floor_lo/hi,
//                  at least 1) sets the Gaussian's bit in seen_bits[] and raises its running
//                  maximum over the views that see it in maxima[].

// Per Gaussian its total of the current view: low and high word of Σ w·2^32.
@group(0) @binding(21) var<storage, read_write> totals: array<atomic<u32>>;
// Per Gaussian the largest total of a view that saw it (low, high word), across views.
@group(0) @binding(22) var<storage, read_write> maxima: array<u32>;
// Bit k % 32 of word k / 32: the current view sees Gaussian k.
@group(0) @binding(23) var<storage, read_write> seen_bits: array<atomic<u32>>;

@compute @workgroup_size(16, 16)
fn blend_totals(t: TileThread) {
    let tp = tile_pixel(t);
    let lid = t.lid;
    tile_begin(tp, lid);
    workgroupBarrier();
    let range = workgroupUniformLoad(&sh_range);
    var walk = walk_start(tp, !tp.inside);
    let n_batches = batch_count(range);
    for (var b = 0u; b < n_batches; b++) {
        if (all_stopped(lid)) {
            break;
        }
        atomicStore(&acc_lo[lid], 0u);
        atomicStore(&acc_hi[lid], 0u);
        let n_here = load_batch(range, b, lid);
        for (var k = 0u; k < n_here && !walk.done; k++) {
            let weight = walk_step(&walk, k);
            if (weight == 0.0) {
                continue;
            }
            // w·2^32 truncated (w <= ALPHA_MAX < 1), as blend_sums adds it.
            let lo = u32(min(weight * 4294967296.0, 4294967040.0));
            let old = atomicAdd(&acc_lo[k], lo);
            if (old > 0xFFFFFFFFu - lo) {
                atomicAdd(&acc_hi[k], 1u);
            }
        }
        workgroupBarrier();
        if (lid < n_here) {
            let lo = atomicLoad(&acc_lo[lid]);
            let hi = atomicLoad(&acc_hi[lid]);
            if (lo != 0u || hi != 0u) {
                let g = sh_id[lid];
                let old = atomicAdd(&totals[2u * g], lo);
                var carry = 0u;
                if (old > 0xFFFFFFFFu - lo) {
                    carry = 1u;
                }
                if (hi + carry != 0u) {
                    atomicAdd(&totals[2u * g + 1u], hi + carry);
                }
            }
        }
        // The next batch clears the slots and reloads sh_id only after every thread read them.
        workgroupBarrier();
    }
}

@compute @workgroup_size(256)
fn coverage_seen(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let g = (wid.y * params.groups_x + wid.x) * 256u + lid;
    if (g >= params.n_gaussians) {
        return;
    }
    let lo = atomicLoad(&totals[2u * g]);
    let hi = atomicLoad(&totals[2u * g + 1u]);
    if (hi < params.floor_hi || (hi == params.floor_hi && lo < params.floor_lo)) {
        return;
    }
    atomicOr(&seen_bits[g / 32u], 1u << (g % 32u));
    let best_lo = maxima[2u * g];
    let best_hi = maxima[2u * g + 1u];
    if (hi > best_hi || (hi == best_hi && lo > best_lo)) {
        maxima[2u * g] = lo;
        maxima[2u * g + 1u] = hi;
    }
}
