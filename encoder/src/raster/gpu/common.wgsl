// slag weight rasterizer kernels (see gpu/mod.rs): the declarations every kernel shares; the module is
// this file joined with label_sums.wgsl, project.wgsl, blend.wgsl, scan.wgsl and sort.wgsl, in that
// order.
// f32 mirror of project.rs; gsplat 1.x conventions.
//
// Entry points, in dispatch order:
//   project      one thread per Gaussian: EWA projection -> splats[] (mean2d, opacity, depth, axes),
//                isect[] (packed tile rect) and offsets[i] (its number of tiles).
//   scan_*       (over the Gaussians' tile counts) exclusive offsets, total intersections.
//   emit, radix_count, scan_*, radix_scatter, tile_bounds   tile binning and depth sort
//                (sort.wgsl): the intersections' (tile, depth) keys radix-sorted, tile ranges.
//   blend        one 16x16 workgroup per tile, shared-memory batches of 256 splats (gsplat's
//                rasterize_to_pixels scheme). params.mode == 0: count contributors per pixel into
//                offsets[p]; mode == 1: write ids/weights into [offsets[p], offsets[p+1]), shifted
//                by out_base, for the tile rows tile_y0.. of this dispatch (one band of rows).
//   blend_sums   instead of per-pixel lists: the same loop, per-(Gaussian, label) sums of the
//                weights of labelled pixels accumulated per tile in workgroup memory and written
//                as one record per (tile intersection, tile label) with a non-zero sum
//                (label_sums.wgsl; 64-bit fixed point, integer atomics: exact and independent of
//                thread order), so only those records are read back.
//   scan_local, scan_blocks, scan_add   exclusive prefix sum of offsets[0..n_pixels] in place,
//                total written to offsets[n_pixels] (n_pixels is the length of whatever is scanned:
//                pixels' contributor counts, Gaussians' tile counts or a radix histogram).

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
    mode: u32,           // blend: 0 count, 1 write
    n_blocks: u32,       // scan: number of 1024-element blocks
    tile_y0: u32,        // blend, blend_sums: first tile row of this dispatch (a band of rows)
    out_base: u32,       // blend write: entry index of out_ids[0] / out_weights[0]
    out_cap: u32,        // blend_sums: records that fit in records[] after its 4-word header
    n_keys: u32,         // sort: (Gaussian, tile) intersections of the view
    shift: u32,          // radix passes: bit of the 64-bit key where this pass's 4-bit digit starts
    floor_lo: u32,       // coverage_seen: the floor of a seen Gaussian's total, low word
    floor_hi: u32,       //   and high word (64-bit fixed point, 2^32 = one raster pixel)
}

struct Splat {
    xy_opac: vec4<f32>,  // mean2d.x, mean2d.y, opacity, sort depth (f32, sort.wgsl's key)
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
// Per Gaussian its sort depth: the host's f64 camera-frame depth rounded to f32 (gpu/sort.rs).
@group(0) @binding(19) var<storage, read> sort_depths: array<f32>;

// The blend loops' shared steps (`blend`, `blend_sums`).

// One workgroup's batch of splats (positions and opacities, axes, Gaussian ids), the tile's
// range of sorted intersections, and how many of its pixels have stopped.
var<workgroup> sh_xy_opac: array<vec4<f32>, 256>;
var<workgroup> sh_axes: array<vec4<f32>, 256>;
var<workgroup> sh_id: array<u32, 256>;
var<workgroup> sh_range: vec2<u32>;
var<workgroup> done_count: atomic<u32>;
var<workgroup> done_snapshot: u32;

// A thread of a tile's 16x16 workgroup: the blend entry points' built-in ids.
struct TileThread {
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_id) lid3: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
}

// The pixel of thread `t.lid3` in the tile of workgroup `t.wid` (tile rows from params.tile_y0:
// the dispatch's band).
struct TilePixel {
    tile: u32,
    px: u32,
    py: u32,
    inside: bool, // within the raster (edge tiles reach past it)
}

fn tile_pixel(t: TileThread) -> TilePixel {
    let ty = t.wid.y + params.tile_y0;
    let px = t.wid.x * TILE + t.lid3.x;
    let py = ty * TILE + t.lid3.y;
    return TilePixel(ty * params.tiles_x + t.wid.x, px, py, px < params.width && py < params.height);
}

// Thread 0 of the tile reads the tile's range into sh_range and resets done_count (seen by the
// other threads after the next barrier).
fn tile_begin(tp: TilePixel, lid: u32) {
    if (lid == 0u) {
        sh_range = tile_ranges[tp.tile];
        atomicStore(&done_count, 0u);
    }
}

// Whether every pixel of the tile has stopped, read at the top of a batch (uniform across the
// workgroup; call in uniform control flow).
fn all_stopped(lid: u32) -> bool {
    workgroupBarrier();
    if (lid == 0u) {
        done_snapshot = atomicLoad(&done_count);
    }
    return workgroupUniformLoad(&done_snapshot) >= BATCH;
}

// Thread `lid` loads the splat at `idx` of the tile's depth-sorted list (when `idx < end`) into
// the workgroup batch.
fn load_splat(idx: u32, end: u32, lid: u32) {
    if (idx < end) {
        let g = sorted_ids[idx];
        let s = splats[g];
        sh_xy_opac[lid] = s.xy_opac;
        sh_axes[lid] = s.axes;
        sh_id[lid] = g;
    }
}

// α of batch splat `k` at the pixel centre (pxc, pyc): ½dᵀΣ⁻¹d in eigen form (Splat.axes; the same
// σ as project.rs's conic form), α = min(ALPHA_MAX, opacity·exp(-σ)); 0 when the splat does not
// contribute (σ < 0 or α < ALPHA_MIN).
fn splat_alpha(k: u32, pxc: f32, pyc: f32) -> f32 {
    let xo = sh_xy_opac[k];
    let ax = sh_axes[k];
    let dx = xo.x - pxc;
    let dy = xo.y - pyc;
    let pa = (ax.x * dx + ax.y * dy) * ax.z;
    let pb = (ax.x * dy - ax.y * dx) * ax.w;
    let sigma = 0.5 * (pa * pa + pb * pb);
    let alpha = min(ALPHA_MAX, xo.z * exp(-sigma));
    if (sigma < 0.0 || alpha < ALPHA_MIN) {
        return 0.0;
    }
    return alpha;
}

// One pixel's front-to-back walk over its tile's depth-sorted splats: the transmittance T so far,
// whether the walk has stopped (T would fall below T_MIN, or the pixel takes no part), and the
// pixel centre.
struct Walk {
    t: f32,
    done: bool,
    pxc: f32,
    pyc: f32,
}

// The walk of pixel `tp` at T = 1; `skip`: the pixel takes no part (done, and counted in
// done_count, at once). Call after done_count was reset and a barrier.
fn walk_start(tp: TilePixel, skip: bool) -> Walk {
    if (skip) {
        atomicAdd(&done_count, 1u);
    }
    return Walk(1.0, skip, f32(tp.px) + 0.5, f32(tp.py) + 0.5);
}

// Batches of BATCH splats in the tile's range.
fn batch_count(range: vec2<u32>) -> u32 {
    return (range.y - range.x + BATCH - 1u) / BATCH;
}

// Loads batch `b` of the tile's range into the workgroup arrays; returns how many splats it
// holds (call in uniform control flow).
fn load_batch(range: vec2<u32>, b: u32, lid: u32) -> u32 {
    let start = range.x + b * BATCH;
    load_splat(start + lid, range.y, lid);
    workgroupBarrier();
    return min(BATCH, range.y - start);
}

// The blend weight α·T of batch splat `k` at the walk's pixel, the walk moved past it: 0 when
// the splat does not contribute (α < ALPHA_MIN; T unchanged) or when T would fall below T_MIN
// (the walk is then done, and counted in done_count). A contributing weight is > 0 (α ≥ 1/255,
// T ≥ T_MIN).
fn walk_step(w: ptr<function, Walk>, k: u32) -> f32 {
    let alpha = splat_alpha(k, (*w).pxc, (*w).pyc);
    if (alpha < ALPHA_MIN) {
        return 0.0;
    }
    let next_t = (*w).t * (1.0 - alpha);
    if (next_t < T_MIN) {
        (*w).done = true;
        atomicAdd(&done_count, 1u);
        return 0.0;
    }
    let weight = alpha * (*w).t;
    (*w).t = next_t;
    return weight;
}
