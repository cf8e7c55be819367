// `project` (gpu/project.rs): one thread per Gaussian, EWA projection to a splat + tile rect, and
// its number of tiles into offsets[i] (scanned into the intersections' offsets, sort.wgsl).

fn culled(i: u32) {
    splats[i] = Splat(vec4<f32>(0.0), vec4<f32>(0.0));
    isect[i] = vec2<u32>(0u);
    offsets[i] = 0u;
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
    // The host uploads opacity 0 for every Gaussian to cull for bad input (gpu/mod.rs, step 0).
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
    splats[i] = Splat(vec4<f32>(mean2d, mo.w, sort_depths[i]), axes);
    isect[i] = vec2<u32>(x0 | (y0 << 16u), x1 | (y1 << 16u));
    var tiles = 0u;
    if (x1 > x0 && y1 > y0) {
        tiles = (x1 - x0) * (y1 - y0); // at most the grid's tiles
    }
    offsets[i] = tiles;
}

