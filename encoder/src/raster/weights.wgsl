// slag weight rasterizer kernels (see gpu.rs). f32 mirror of project.rs; gsplat 1.x conventions.
//
// Entry points, in dispatch order:
//   project      one thread per Gaussian: EWA projection -> splats[] (mean2d, opacity, axes) and
//                isect[] (packed tile rect) read back for CPU binning.
//   blend        one 16x16 workgroup per tile, shared-memory batches of 256 splats (gsplat's
//                rasterize_to_pixels scheme). params.mode == 0: count contributors per pixel into
//                offsets[p]; mode == 1: write ids/weights into [offsets[p], offsets[p+1]), shifted
//                by out_base, for the tile rows tile_y0.. of this dispatch (one band of rows);
//                mode == 2: per-label sums instead of per-pixel lists: every contribution w_kp of
//                a pixel p with labels[p] != 0 is added to the slot of (k, labels[p]) in the
//                open-addressing table sums[] (64-bit fixed point, integer atomics: the sums are
//                exact and independent of thread order), so only the sums are read back.
//   scan_local, scan_blocks, scan_add   exclusive prefix sum of offsets[0..n_pixels] in place,
//                total written to offsets[n_pixels].

struct Params {
    rot0: vec4<f32>,     // world-to-camera rotation row 0 (xyz), translation.x (w)
    rot1: vec4<f32>,     // row 1, translation.y
    rot2: vec4<f32>,     // row 2, translation.z
    focal: vec4<f32>,    // fx, fy, cx, cy (pixels)
    lims: vec4<f32>,     // jacobian clamp: lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg
    width: u32,
    height: u32,
    tiles_x: u32,
    tiles_y: u32,
    n_gaussians: u32,
    n_pixels: u32,
    groups_x: u32,       // x extent of 2D dispatches (project, scan_local, scan_add)
    mode: u32,           // blend: 0 count, 1 write, 2 label sums
    n_blocks: u32,       // scan: number of 1024-element blocks
    tile_y0: u32,        // blend: first tile row of this dispatch (banded write pass)
    out_base: u32,       // blend write: entry index of out_ids[0] / out_weights[0]
    table_mask: u32,     // blend mode 2: slots in sums[] minus 1 (slots are a power of two)
}

struct Splat {
    xy_opac: vec4<f32>,  // mean2d.x, mean2d.y, opacity, unused
    // The inverse 2D covariance in eigen form: unit major axis u (xy), 1/sqrt(λ_major) (z),
    // 1/sqrt(λ_minor) (w); ½dᵀΣ⁻¹d = ½((u·d)²/λ_major + (u⊥·d)²/λ_minor). A sum of squares: no
    // f32 cancellation for needles and sheets, where the (a, b, c) conic form loses ~1e-3 of σ
    // at ~100 px from the centre (its terms are ~1e4 times σ).
    axes: vec4<f32>,
}

const NEAR_PLANE: f32 = 0.01;
const FAR_PLANE: f32 = 1e10;
const LOW_PASS: f32 = 0.3;
const ALPHA_MAX: f32 = 0.99;
const ALPHA_MIN: f32 = 1.0 / 255.0;
const T_MIN: f32 = 1e-4;
const TILE: u32 = 16u;
const BATCH: u32 = 256u;
const SCAN_BLOCK: u32 = 1024u;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> means_opac: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> scales: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> quats: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> splats: array<Splat>;
@group(0) @binding(5) var<storage, read_write> isect: array<vec2<u32>>;
@group(0) @binding(6) var<storage, read> tile_ranges: array<vec2<u32>>;
@group(0) @binding(7) var<storage, read> sorted_ids: array<u32>;
@group(0) @binding(8) var<storage, read_write> offsets: array<u32>;
@group(0) @binding(9) var<storage, read_write> out_ids: array<u32>;
@group(0) @binding(10) var<storage, read_write> out_weights: array<f32>;
@group(0) @binding(11) var<storage, read_write> block_sums: array<u32>;
// Mode 2: the label of every pixel (0 = none: the pixel is skipped).
@group(0) @binding(12) var<storage, read> labels: array<u32>;
// Mode 2: sums[0] = overflow flag (a contribution found no slot within MAX_PROBES: the host
// retries with more slots), sums[1], sums[2] = low and high word of the contributions counted,
// sums[3] unused, then 4 words per slot: Gaussian id + 1 (0 = empty),
// label, low and high word of Σ w·2^32.
@group(0) @binding(13) var<storage, read_write> sums: array<atomic<u32>>;

const MAX_PROBES: u32 = 64u;

// Adds w·2^32 (truncated; w <= ALPHA_MAX < 1) to the 64-bit fixed-point sum of the slot at `base`.
fn fixed_add(base: u32, w: f32) {
    let lo = u32(min(w * 4294967296.0, 4294967040.0));
    let old = atomicAdd(&sums[base + 2u], lo);
    if (old > 0xFFFFFFFFu - lo) {
        atomicAdd(&sums[base + 3u], 1u);
    }
}

// Adds w to the slot of (Gaussian g, label) of sums[], claiming an empty slot if none holds that
// key yet. A slot claimed by another thread whose label is not yet stored reads as a different key,
// so one key can end up in two slots: the host adds such duplicates (integers: exact).
fn add_label_sum(g: u32, label: u32, w: f32) {
    let key = g + 1u;
    var h = (g * 0x9E3779B1u) ^ (label * 0x85EBCA77u);
    h = h ^ (h >> 15u);
    var probe = 0u;
    loop {
        if (probe >= MAX_PROBES) {
            atomicStore(&sums[0], 1u);
            return;
        }
        let base = 4u + ((h + probe) & params.table_mask) * 4u;
        var kk = atomicLoad(&sums[base]);
        if (kk == 0u) {
            let r = atomicCompareExchangeWeak(&sums[base], 0u, key);
            if (r.exchanged) {
                atomicStore(&sums[base + 1u], label);
                fixed_add(base, w);
                return;
            }
            kk = r.old_value;
            if (kk == 0u) {
                continue; // spurious failure of the weak exchange: try this slot again
            }
        }
        if (kk == key && atomicLoad(&sums[base + 1u]) == label) {
            fixed_add(base, w);
            return;
        }
        probe += 1u;
    }
}

fn culled(i: u32) {
    splats[i] = Splat(vec4<f32>(0.0), vec4<f32>(0.0));
    isect[i] = vec2<u32>(0u);
}

fn all_finite(v: vec4<f32>) -> bool {
    // |v| <= max finite f32 is false for NaN and inf.
    return all(abs(v) <= vec4<f32>(3.4028235e38));
}

@compute @workgroup_size(256)
fn project(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = (wid.y * params.groups_x + wid.x) * 256u + lid;
    if (i >= params.n_gaussians) {
        return;
    }
    let mo = means_opac[i];
    // The host uploads opacity 0 for every Gaussian to cull for bad input (gpu.rs, step 0).
    if (!(mo.w > 0.0)) {
        culled(i);
        return;
    }
    // Relative to the scene centre; params.rot*.w carry the folded translation R·o + T.
    let mean = mo.xyz;
    let t = vec3<f32>(
        dot(params.rot0.xyz, mean) + params.rot0.w,
        dot(params.rot1.xyz, mean) + params.rot1.w,
        dot(params.rot2.xyz, mean) + params.rot2.w,
    );
    if (!(t.z >= NEAR_PLANE && t.z <= FAR_PLANE)) {
        culled(i);
        return;
    }
    // Rotation of the normalised (w, x, y, z) quaternion.
    let q4 = quats[i];
    let qn = sqrt(dot(q4, q4));
    if (!(qn > 0.0) || !all_finite(q4)) {
        culled(i);
        return;
    }
    let q = q4 / qn;
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    // WGSL mat3x3 constructor takes columns.
    let r = mat3x3<f32>(
        vec3<f32>(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)),
        vec3<f32>(2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x)),
        vec3<f32>(2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)),
    );
    let s = scales[i].xyz;
    // W = rows rot0..2; Wᵀ has them as columns.
    let wt = mat3x3<f32>(params.rot0.xyz, params.rot1.xyz, params.rot2.xyz);

    let fx = params.focal.x;
    let fy = params.focal.y;
    let rz = 1.0 / t.z;
    let rz2 = rz * rz;
    let tx = t.z * clamp(t.x * rz, -params.lims.y, params.lims.x);
    let ty = t.z * clamp(t.y * rz, -params.lims.w, params.lims.z);
    let j0 = vec3<f32>(fx * rz, 0.0, -fx * tx * rz2);
    let j1 = vec3<f32>(0.0, fy * rz, -fy * ty * rz2);
    // P = J W R S (factored Σ2D, see project.rs).
    let rt = transpose(r);
    let p0 = (rt * (wt * j0)) * s;
    let p1 = (rt * (wt * j1)) * s;
    let a0 = dot(p0, p0);
    let b = dot(p0, p1);
    let c0 = dot(p1, p1);
    let minors = cross(p0, p1);
    let det = dot(minors, minors) + LOW_PASS * (a0 + c0) + LOW_PASS * LOW_PASS;
    let a = a0 + LOW_PASS;
    let c = c0 + LOW_PASS;
    if (!(det > 0.0)) {
        culled(i);
        return;
    }
    let inv = 1.0 / det;
    let conic = vec3<f32>(c * inv, -b * inv, a * inv);
    // Eigen form of Σ2D (see Splat.axes), each step free of cancellation: the discriminant as
    // ((a - c)/2)² + b², the minor eigenvalue as det / λ_major (det by Cauchy-Binet), the major
    // axis from the row whose entries are both non-negative sums.
    let half_diff = 0.5 * (a - c);
    let disc = sqrt(half_diff * half_diff + b * b);
    let l_major = 0.5 * (a + c) + disc;
    let l_minor = det / l_major;
    var u = vec2<f32>(b, disc - half_diff);
    if (a >= c) {
        u = vec2<f32>(half_diff + disc, b);
    }
    let un = length(u);
    if (un > 0.0) {
        u = u / un;
    } else {
        u = vec2<f32>(1.0, 0.0); // isotropic: any axis
    }
    let axes = vec4<f32>(u, inverseSqrt(l_major), inverseSqrt(l_minor));
    let mid = 0.5 * (a + c);
    let lambda = mid + sqrt(max(0.01, mid * mid - det));
    let radius = ceil(3.0 * sqrt(lambda));
    let mean2d = vec2<f32>(fx * t.x * rz + params.focal.z, fy * t.y * rz + params.focal.w);
    if (!all_finite(vec4<f32>(mean2d, radius, 0.0)) || !all_finite(vec4<f32>(conic, 0.0))
        || !all_finite(axes)) {
        culled(i);
        return;
    }
    let wf = f32(params.width);
    let hf = f32(params.height);
    if (mean2d.x + radius <= 0.0 || mean2d.x - radius >= wf || mean2d.y + radius <= 0.0
        || mean2d.y - radius >= hf) {
        culled(i);
        return;
    }
    let txf = f32(params.tiles_x);
    let tyf = f32(params.tiles_y);
    let x0 = u32(clamp(floor((mean2d.x - radius) / 16.0), 0.0, txf));
    let y0 = u32(clamp(floor((mean2d.y - radius) / 16.0), 0.0, tyf));
    let x1 = u32(clamp(ceil((mean2d.x + radius) / 16.0), 0.0, txf));
    let y1 = u32(clamp(ceil((mean2d.y + radius) / 16.0), 0.0, tyf));
    splats[i] = Splat(vec4<f32>(mean2d, mo.w, 0.0), axes);
    isect[i] = vec2<u32>(x0 | (y0 << 16u), x1 | (y1 << 16u));
}

var<workgroup> sh_xy_opac: array<vec4<f32>, 256>;
var<workgroup> sh_axes: array<vec4<f32>, 256>;
var<workgroup> sh_id: array<u32, 256>;
var<workgroup> sh_range: vec2<u32>;
var<workgroup> done_count: atomic<u32>;
var<workgroup> done_snapshot: u32;

@compute @workgroup_size(16, 16)
fn blend(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_id) lid3: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let ty = wid.y + params.tile_y0;
    let tile = ty * params.tiles_x + wid.x;
    let px = wid.x * TILE + lid3.x;
    let py = ty * TILE + lid3.y;
    let inside = px < params.width && py < params.height;
    let pix = py * params.width + px;
    let write = params.mode == 1u;
    let summing = params.mode == 2u;
    if (lid == 0u) {
        sh_range = tile_ranges[tile];
        atomicStore(&done_count, 0u);
    }
    let range = workgroupUniformLoad(&sh_range);
    var out = 0u;
    var out_end = 0u;
    if (write && inside) {
        out = offsets[pix] - params.out_base;
        out_end = offsets[pix + 1u] - params.out_base;
    }
    var label = 0u;
    if (summing && inside) {
        label = labels[pix];
    }
    var t_acc = 1.0;
    var count = 0u;
    // Unlabelled pixels contribute nothing to label sums: done from the start.
    var done = !inside || (summing && label == 0u);
    if (done) {
        atomicAdd(&done_count, 1u);
    }
    let pxc = f32(px) + 0.5;
    let pyc = f32(py) + 0.5;
    let n_batches = (range.y - range.x + BATCH - 1u) / BATCH;
    for (var b = 0u; b < n_batches; b++) {
        workgroupBarrier();
        if (lid == 0u) {
            done_snapshot = atomicLoad(&done_count);
        }
        let n_done = workgroupUniformLoad(&done_snapshot);
        if (n_done >= BATCH) {
            break;
        }
        let start = range.x + b * BATCH;
        let idx = start + lid;
        if (idx < range.y) {
            let g = sorted_ids[idx];
            let s = splats[g];
            sh_xy_opac[lid] = s.xy_opac;
            sh_axes[lid] = s.axes;
            sh_id[lid] = g;
        }
        workgroupBarrier();
        let n_here = min(BATCH, range.y - start);
        if (!done) {
            for (var k = 0u; k < n_here; k++) {
                let xo = sh_xy_opac[k];
                let ax = sh_axes[k];
                let dx = xo.x - pxc;
                let dy = xo.y - pyc;
                // ½dᵀΣ⁻¹d in eigen form (Splat.axes): the same σ as project.rs's conic form.
                let pa = (ax.x * dx + ax.y * dy) * ax.z;
                let pb = (ax.x * dy - ax.y * dx) * ax.w;
                let sigma = 0.5 * (pa * pa + pb * pb);
                let alpha = min(ALPHA_MAX, xo.z * exp(-sigma));
                if (sigma < 0.0 || alpha < ALPHA_MIN) {
                    continue;
                }
                let next_t = t_acc * (1.0 - alpha);
                if (next_t < T_MIN) {
                    done = true;
                    break;
                }
                if (summing) {
                    add_label_sum(sh_id[k], label, alpha * t_acc);
                    count += 1u;
                } else if (write) {
                    // Bounded by the count pass's range: never writes outside this pixel's slots.
                    if (out < out_end) {
                        out_ids[out] = sh_id[k];
                        out_weights[out] = alpha * t_acc;
                        out += 1u;
                    }
                } else {
                    count += 1u;
                }
                t_acc = next_t;
            }
            if (done) {
                atomicAdd(&done_count, 1u);
            }
        }
    }
    if (summing && count > 0u) {
        // Contributions counted (64-bit, words 1 and 2 of the table header).
        let old = atomicAdd(&sums[1], count);
        if (old > 0xFFFFFFFFu - count) {
            atomicAdd(&sums[2], 1u);
        }
    }
    if (params.mode == 0u && inside) {
        offsets[pix] = count;
    }
}

var<workgroup> sh_scan: array<u32, 256>;

// Inclusive Hillis-Steele scan of sh_scan[0..256]; every invocation of the workgroup calls it.
fn scan_shared(lid: u32) {
    for (var off = 1u; off < 256u; off = off * 2u) {
        workgroupBarrier();
        var v = 0u;
        if (lid >= off) {
            v = sh_scan[lid - off];
        }
        workgroupBarrier();
        sh_scan[lid] += v;
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
        sum += v[i];
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
// block_sums[n_blocks] = 1 if the total overflowed u32, else 0. A pixel has at most 2345
// contributors (each kept splat has alpha >= 1/255 and T stays >= 1e-4), so a block total is
// < 2.5e6 and a 1024-block chunk total < 2.6e9 < 2^32: only the running carry can overflow.
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
            sum += v[i];
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
        let total = sh_scan[255];
        if (carry + total < carry) {
            overflow = 1u;
        }
        carry += total;
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
