// `scan_local`, `scan_blocks`, `scan_add` (gpu/count_scan.rs, gpu/sort.rs): exclusive prefix sum
// of offsets[0..params.n_pixels] in place (the pixels' contributor counts, the Gaussians' tile
// counts or a radix histogram), the total to offsets[n_pixels]. Sums saturate at 2^32 - 1, which
// scan_blocks reports as an overflow (the outputs are then meaningless and the host refuses the
// view). Buffers: offsets n_pixels + 1 words, block_sums n_blocks + 1 words.
var<workgroup> sh_scan: array<u32, 256>;

// a + b, or 2^32 - 1 when that overflows.
fn sat_add(a: u32, b: u32) -> u32 {
    let s = a + b;
    return select(s, 0xFFFFFFFFu, s < a);
}

// Inclusive Hillis-Steele scan of sh_scan[0..256]; every invocation of the workgroup calls it.
fn scan_shared(lid: u32) {
    for (var off = 1u; off < 256u; off = off * 2u) {
        workgroupBarrier();
        var v = 0u;
        if (lid >= off) {
            v = sh_scan[lid - off];
        }
        workgroupBarrier();
        sh_scan[lid] = sat_add(sh_scan[lid], v);
    }
    workgroupBarrier();
}

// Exclusive scan of each 1024-element block of offsets[0..n_pixels]; block totals to block_sums.
@compute @workgroup_size(256)
fn scan_local(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let block = wid.y * params.groups_x + wid.x;
    let base = block * SCAN_BLOCK + lid * 4u;
    var v = array<u32, 4>(0u, 0u, 0u, 0u);
    var sum = 0u;
    for (var i = 0u; i < 4u; i++) {
        if (block < params.n_blocks && base + i < params.n_pixels) {
            v[i] = offsets[base + i];
        }
        sum = sat_add(sum, v[i]);
    }
    sh_scan[lid] = sum;
    scan_shared(lid);
    var run = sh_scan[lid] - sum;
    for (var i = 0u; i < 4u; i++) {
        if (block < params.n_blocks && base + i < params.n_pixels) {
            offsets[base + i] = run;
        }
        run += v[i];
    }
    if (lid == 255u && block < params.n_blocks) {
        block_sums[block] = sh_scan[255];
    }
}

// One workgroup: exclusive scan of block_sums[0..n_blocks] in place; total to offsets[n_pixels];
// block_sums[n_blocks] = 1 if the total reached 2^32 - 1 (a saturated sum), else 0.
@compute @workgroup_size(256)
fn scan_blocks(@builtin(local_invocation_index) lid: u32) {
    var carry = 0u;
    var overflow = 0u;
    for (var chunk = 0u; chunk < params.n_blocks; chunk += SCAN_BLOCK) {
        let base = chunk + lid * 4u;
        var v = array<u32, 4>(0u, 0u, 0u, 0u);
        var sum = 0u;
        for (var i = 0u; i < 4u; i++) {
            if (base + i < params.n_blocks) {
                v[i] = block_sums[base + i];
            }
            sum = sat_add(sum, v[i]);
        }
        sh_scan[lid] = sum;
        scan_shared(lid);
        var run = carry + sh_scan[lid] - sum;
        for (var i = 0u; i < 4u; i++) {
            if (base + i < params.n_blocks) {
                block_sums[base + i] = run;
            }
            run += v[i];
        }
        carry = sat_add(carry, sh_scan[255]);
        if (carry == 0xFFFFFFFFu) {
            overflow = 1u;
        }
        // Everyone has read sh_scan[255] before the next chunk overwrites sh_scan.
        workgroupBarrier();
    }
    if (lid == 0u) {
        offsets[params.n_pixels] = carry;
        block_sums[params.n_blocks] = overflow;
    }
}

@compute @workgroup_size(256)
fn scan_add(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let block = wid.y * params.groups_x + wid.x;
    if (block >= params.n_blocks) {
        return;
    }
    let add = block_sums[block];
    let base = block * SCAN_BLOCK + lid * 4u;
    for (var i = 0u; i < 4u; i++) {
        if (base + i < params.n_pixels) {
            offsets[base + i] += add;
        }
    }
}
