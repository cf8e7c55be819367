// Mode 2 of `blend` (gpu/label_sums.rs): the pixel labels and the per-(Gaussian, label) sum table.
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
