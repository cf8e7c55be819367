//! The GPU weight rasterizer: wgpu compute kernels in the WGSL files beside this module (Vulkan backend).
//!
//! Per view ([`GpuRasterizer::rasterize`]):
//! 0. Once, in [`GpuRasterizer::new`]: the means are uploaded relative to the scene's centre `o`
//!    (the midpoint of their bounding box, f64), `μ - o` rounded to f32, and every view's
//!    world-to-camera translation is folded with it in f64 (`T' = R·o + T`), so that the kernel's
//!    f32 camera-frame point `R·(μ - o) + T'` keeps its precision however far the scene lies from
//!    the world origin (drone scenes in UTM coordinates, ~1e6 m: f32 world coordinates there have
//!    a 6 cm spacing, and `R·μ + T` in f32 loses metres to cancellation). The quaternions are
//!    normalised on the host in f64, and a Gaussian with a non-finite mean, scale or quaternion, a
//!    zero quaternion, or an opacity outside `(0, ∞)` is uploaded with opacity 0, which the kernel
//!    culls: the same Gaussians [`super::project::project_gaussian`] culls, decided without relying
//!    on NaN comparisons in the shader.
//! 1. `project` kernel, one thread per Gaussian: the EWA projection of [`super::project`] in f32 →
//!    per-Gaussian splat (mean2d, opacity, and `Σ2D⁻¹` in eigen form: major axis, `1/√λ` of both
//!    axes, so that `½dᵀΣ⁻¹d` is a sum of two squares, without the f32 cancellation of the conic
//!    form for needles and sheets) and its tile rect, kept on the GPU, and its number of tiles.
//!    The splat also carries the sort depth: the f64 camera-frame depth of
//!    [`super::project::camera_point`] rounded to f32, computed on the host (one multiply-add per
//!    Gaussian and axis, in parallel; ahead of the view, on the caller's thread, where it asks
//!    through [`WeightRasterizer::view_precompute`]) and uploaded, 4 bytes per Gaussian: the GPU's own f32 `t.z`
//!    can be a few f32 steps off, and a two-float evaluation in WGSL is not safe from the
//!    drivers' algebraic rewriting.
//! 2. Tile binning and depth sort **on the GPU** ([`sort`], `sort.wgsl`): an exclusive prefix sum
//!    of the tile counts (the `scan_*` kernels) gives each Gaussian its slots; only the total (one
//!    u32) is read back, to size the buffers. The `emit` kernel writes one 64-bit key per
//!    (tile, Gaussian) intersection, `tile << 32 | f32 depth bits`, with the Gaussian id as value,
//!    in id order; a stable LSD radix sort (4 bits a pass, 8 passes over the depth and as many
//!    over the tile id as the grid needs) orders them by (tile, depth), equal f32 depths by id;
//!    `tile_bounds` finds each tile's `[start, end)` range. The blend kernels read the sorted ids
//!    and the ranges where they lie. [`project::bin_and_sort`] (the same order) is the host
//!    reference the tests compare with.
//! 3. `blend` kernel, one 16×16 workgroup per tile, splats streamed through shared memory in
//!    batches of 256 (gsplat `rasterize_to_pixels`), front to back, stopping a pixel at `T < 1e-4`
//!    and the whole tile once every pixel has stopped. Run twice: a count pass (contributors per
//!    pixel) and, after an exclusive prefix sum on the GPU (`scan_*` kernels), a write pass that
//!    fills each pixel's slots. Both passes run the same compiled kernel (a uniform selects the
//!    mode), so their decisions agree exactly; the write pass is also bounded to its pixel's slots.
//!    The write pass runs in bands of whole tile rows (each band a contiguous CSR range) so that
//!    no output binding exceeds the device limit (lavapipe: 128 MiB).
//! 4. Read back the CSR offsets, ids and weights (the only per-pixel data touching the CPU).
//!
//! 3'. Instead of 3–4, when the caller gives per-pixel labels (the image stage's mask sets,
//!    [`WeightRasterizer::label_sums`]): the `blend_sums` kernel, the same front-to-back loop,
//!    one 16×16 workgroup per tile. The tile's distinct labels `L_t` are found on the GPU from the
//!    label image; each batch of splats is blended in sub-batches of `512 / |L_t|` splats whose
//!    weights are summed per (splat, tile label) in workgroup memory (64-bit fixed point, exact
//!    integer atomics), and every non-zero sum leaves as one 16-byte record (Gaussian, label,
//!    sum). A view's records are at most one per (tile intersection, tile label) and one per
//!    labelled contribution, and the kernel counts them: a band of tile rows that did not fit
//!    its buffer is re-run with room for exactly its count, or split when that exceeds one
//!    binding. Nothing overflows, at any scene size. The records of a band are then reduced on
//!    the device ([`reduce`], `reduce.wgsl`): radix-sorted by (Gaussian, label) and the sums of
//!    one key (the same key from several tiles) added, so one record per key is read back,
//!    sorted. A view of several bands leaves the merge of their keys to the image stage
//!    ([`super::LabelSums::reduced`]), on its own thread.
//!
//! 3''. Instead of 3–4, for the coverage pass of the view selection
//!    ([`WeightRasterizer::coverage_view`], [`coverage`], `coverage.wgsl`): the `blend_totals`
//!    kernel sums each splat's weights over a tile as `blend_sums` does with every pixel in one
//!    label, and adds the tile's sum to the Gaussian's 64-bit total on the device; `coverage_seen`
//!    compares each total with the floor, sets the Gaussian's bit and keeps its largest total
//!    over the views. One bit per Gaussian is read back per view.
//!
//! Output buffers are sized from the counts and checked against the device's
//! `max_storage_buffer_binding_size` / `max_buffer_size`; a view whose single row of tiles (or
//! offsets array) exceeds them is an [`Error::Limit`] naming the limit (the command line adds
//! that `--raster-scale` lowers the need).
//!
//! One file per pass, each beside its WGSL: [`project`] (the host reference of step 2,
//! [`project::bin_and_sort`]), `sort` (steps 1 and 2: `project.wgsl`, `scan.wgsl`, `sort.wgsl`),
//! `count_scan` (step 3a, the count mode of `blend.wgsl` + `scan.wgsl`),
//! `write` (step 3b, the banded write mode of `blend.wgsl`), `label_sums` (step 3', the
//! `blend_sums` kernel of `label_sums.wgsl`), `buffers` (storage, readback, noise fill). `common.wgsl`
//! holds `Params` (mirrored by [`Params`] here, its size checked at compile time), the splat
//! layout, constants and bindings, and the two blend kernels' workgroup arrays and shared
//! steps; the shader module is the files joined in that order.

use std::sync::Arc;

use slag_common::camera::{Intrinsics, WorldToCamera};
use slag_common::scene::Gaussians;
use slag_common::{Error, Resource, Result};
use wgpu::util::DeviceExt;

use super::project::{jacobian_limits, tile_grid};
use super::{
    DeviceReduce, KeptExport, KeptMasks, KeptRangeCursor, KeptReduced, KeptTile, KeptView,
    LabelSums, PixelWeights, PrecomputedView, ViewPrecompute, WeightRasterizer, validate_raster,
};

mod adapters;
mod buffers;
mod count_scan;
mod coverage;
pub mod ek;
mod fold;
pub mod icd;
mod label_sums;
pub mod project;
mod record;
mod reduce;
mod sort;
mod write;

pub use adapters::adapter_names;
use adapters::ranked_adapters;
use buffers::{OutBuffers, storage, storage_init};
use label_sums::{INITIAL_LABEL_RECORDS, RecordBuffers};
use sort::SortBuffers;

/// The kernels: the WGSL files beside this module, joined (common declarations first).
const SHADER: &str = concat!(
    include_str!("common.wgsl"),
    include_str!("label_sums.wgsl"),
    include_str!("project.wgsl"),
    include_str!("blend.wgsl"),
    include_str!("scan.wgsl"),
    include_str!("sort.wgsl"),
    include_str!("reduce.wgsl"),
    include_str!("coverage.wgsl"),
);
/// x extent of the 2D dispatches over Gaussians / scan blocks (must match `params.groups_x` use).
const GROUPS_X: u32 = 32768;
/// Elements per scan block (256 invocations × 4).
const SCAN_BLOCK: u32 = 1024;

/// Environment variable: substring (case-insensitive) of the adapter name to use, or `#N`, the
/// N-th (0-based) adapter of the ranked list `--gpus` takes its GPUs from: the only way to tell
/// apart identical GPUs of one host, e.g. one process per GPU of `encode-cluster` (ONNX Runtime's
/// GPU is chosen by `CUDA_VISIBLE_DEVICES`; Vulkan does not read it).
pub const ADAPTER_ENV: &str = "SLAG_WGPU_ADAPTER";

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    rot0: [f32; 4],
    rot1: [f32; 4],
    rot2: [f32; 4],
    focal: [f32; 4],
    lims: [f32; 4],
    width: u32,
    height: u32,
    tiles_x: u32,
    tiles_y: u32,
    n_gaussians: u32,
    n_pixels: u32,
    groups_x: u32,
    mode: u32,
    n_blocks: u32,
    tile_y0: u32,
    out_base: u32,
    out_cap: u32,
    n_keys: u32,
    shift: u32,
    floor_lo: u32,
    floor_hi: u32,
}

// `Params` is a WGSL uniform (common.wgsl): 5 vec4<f32> then 16 u32, 144 bytes, no padding.
// A field added on one side only changes the size or breaks the test below.
const _: () = assert!(std::mem::size_of::<Params>() == 144);

/// Wall-clock milliseconds of the phases of the last [`GpuRasterizer`] run (host-observed,
/// including submission and readback waits), or their sum over runs ([`PhaseTimings::add`]).
/// With GPU label sums, `write_ms` is the label-sum pass and its readback (`records_ms` of it on
/// the host).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct PhaseTimings {
    /// Projection kernel, the scan of the tile counts and the readback of their total.
    pub project_ms: f64,
    /// Tile binning and depth sort, host side: the f32 sort depths (computed on the host, one
    /// multiply-add per Gaussian and axis) and recording and submitting the GPU passes (the
    /// device's time for them shows in the next phase's wall).
    pub bin_sort_ms: f64,
    /// Count pass, prefix sum, offsets readback.
    pub count_scan_ms: f64,
    /// Write pass(es) + ids/weights readback, or the label-sum pass + records readback.
    pub write_ms: f64,
    /// Label sums: the host's copy of the records out of the mapped readback buffer (their
    /// reduction by (Gaussian, label) is the image stage's, on another thread).
    pub records_ms: f64,
    /// Host computation in the rasterizer's critical path (`bin_sort_ms + records_ms`): wall ms
    /// of work on the host's cores (rayon), excluding waits for the device.
    pub host_ms: f64,
}

impl PhaseTimings {
    /// Adds another run's phases.
    pub fn add(&mut self, o: &PhaseTimings) {
        self.project_ms += o.project_ms;
        self.bin_sort_ms += o.bin_sort_ms;
        self.count_scan_ms += o.count_scan_ms;
        self.write_ms += o.write_ms;
        self.records_ms += o.records_ms;
        self.host_ms += o.host_ms;
    }
}

struct Pipelines {
    project: wgpu::ComputePipeline,
    blend: wgpu::ComputePipeline,
    blend_sums: wgpu::ComputePipeline,
    scan_local: wgpu::ComputePipeline,
    scan_blocks: wgpu::ComputePipeline,
    scan_add: wgpu::ComputePipeline,
    emit: wgpu::ComputePipeline,
    radix_count: wgpu::ComputePipeline,
    radix_scatter: wgpu::ComputePipeline,
    tile_bounds: wgpu::ComputePipeline,
    record_keys: wgpu::ComputePipeline,
    record_heads: wgpu::ComputePipeline,
    record_sums: wgpu::ComputePipeline,
    blend_totals: wgpu::ComputePipeline,
    coverage_seen: wgpu::ComputePipeline,
}

/// 3DGS weight rasterizer on a wgpu device (see the module docs for the kernel sequence).
///
/// The Gaussians' means, scales, rotations and opacities are uploaded once in [`Self::new`];
/// each [`WeightRasterizer::rasterize`] call renders one view. Output is deterministic.
pub struct GpuRasterizer {
    device: wgpu::Device,
    queue: wgpu::Queue,
    name: String,
    limits: wgpu::Limits,
    n: u32,
    /// Means kept on the host for the sort depth (`camera_point` in f64, rounded to f32),
    /// shared with [`WeightRasterizer::view_precompute`].
    means: Arc<Vec<[f32; 3]>>,
    /// The next view's sort depths made ahead ([`WeightRasterizer::label_sums_precomputed`]).
    precomputed: Option<PrecomputedView>,
    /// World-frame centre the uploaded means are relative to (f64; see the module docs, step 0).
    origin: glam::DVec3,
    means_opac: wgpu::Buffer,
    scales: wgpu::Buffer,
    quats: wgpu::Buffer,
    splats: wgpu::Buffer,
    isect: wgpu::Buffer,
    /// Per Gaussian its sort depth of the view (f32), written by the host.
    sort_depths: wgpu::Buffer,
    /// Per Gaussian its number of tiles, scanned into its first intersection slot (`n + 1`
    /// words, the total last), and the scan's block sums.
    tile_counts: wgpu::Buffer,
    tile_count_sums: wgpu::Buffer,
    /// The sort's buffers, kept across views (grown on demand).
    sort: Option<SortBuffers>,
    pipelines: Pipelines,
    noise_seed: Option<u64>,
    band_limit: Option<u64>,
    timings: PhaseTimings,
    /// Write-pass output and its readback staging, kept across views (grown on demand).
    out: Option<OutBuffers>,
    /// Record capacity of the label-sum buffer for the next band (grown when a band needs
    /// more, kept across views).
    label_records: u64,
    /// Testing aid: most records per binding (default: the device's binding limit).
    label_record_limit: Option<u64>,
    /// The label-sum records buffer and its staging twin, kept across views.
    label_out: Option<RecordBuffers>,
    /// The coverage pass's totals, maxima and bitset, kept across its views ([`coverage`]).
    coverage: Option<coverage::CoverageBuffers>,
    /// Re-runs of a band (it did not fit its buffer) in the last label-sum view.
    label_retries: u32,
    /// Records the `blend_sums` kernel wrote in the last label-sum view (all bands).
    label_record_count: u64,
    /// The device reduction's buffers, kept across views ([`reduce`]).
    reduce: Option<reduce::ReduceBuffers>,
    /// Whether the label-sum records are reduced on the device before the readback (the
    /// default) or read back as written (testing aid, [`Self::set_label_reduce_on_device`]).
    reduce_on_device: bool,
    /// The adapter is a CPU device (lavapipe).
    cpu_adapter: bool,
    /// The kept views of the device reduction ([`ek`]), once keeping started.
    kept: Option<ek::Kept>,
    /// The streamed reduction's running state, once started ([`fold`]): the kept views are
    /// folded into it a wave at a time instead of being kept to the end.
    stream: Option<fold::Stream>,
    /// The kept views a reduction used (every band a buffer of its own), freed with the
    /// rasterizer or when keeping starts again: an encode drops its rasterizers on a thread
    /// beside its writes, so their freeing is not on its critical path.
    spent_kept: Option<ek::Kept>,
    /// While a kept view runs: its id, and where its dominant masks go.
    keeping: Option<ek::Keeping>,
    /// The masks' record kept on the device ([`record`]), once started.
    mask_record: Option<record::DeviceRecord>,
    /// The dominant masks of the kept view's bands so far.
    kept_heads: Vec<(u32, u32, f32)>,
    /// Testing aid: bytes of one tile of the device reduction ([`Self::set_reduce_tile_bytes`]).
    reduce_tile_bytes: Option<u64>,
    /// Testing aid: bytes read back through one staging buffer at a time
    /// ([`Self::set_readback_bytes`]).
    readback_bytes: Option<u64>,
}

/// What one [`GpuRasterizer::run`] produced.
enum RunOutput {
    /// Per-pixel lists (modes 0 + 1).
    Weights(PixelWeights),
    /// Per-(Gaussian, label) sums (`blend_sums`).
    Sums(LabelSums),
}

/// One view's dispatch state: its raster size and tile grid, the uniform [`Params`] and their
/// buffer (rewritten per pass as `mode`, `tile_y0`, `out_base`, `out_cap` change).
struct View {
    k: Intrinsics,
    tiles_x: u32,
    tiles_y: u32,
    n_pix: u32,
    n_tiles: u32,
    n_blocks: u32,
    params: Params,
    params_buf: wgpu::Buffer,
}

/// The buffers of a binned view (step 2's output on the device): tile ranges, depth-sorted ids
/// and keys (`n_keys` of them), the per-pixel counts / CSR offsets with the scan's block sums,
/// and the placeholders bound where a mode needs no buffer.
struct Binned {
    ranges: wgpu::Buffer,
    sorted_ids: wgpu::Buffer,
    #[cfg_attr(not(test), allow(dead_code))]
    sorted_keys: wgpu::Buffer,
    offsets: wgpu::Buffer,
    block_sums: wgpu::Buffer,
    dummy: wgpu::Buffer,
}

/// Noise-fill salts (testing aid, [`GpuRasterizer::set_noise_fill`]): one per buffer, the write
/// pass's adding the band's first tile row.
const SEED_SALT: u64 = 1;

/// Milliseconds since `c`, which is reset to now.
fn lap(c: &mut std::time::Instant) -> f64 {
    let ms = c.elapsed().as_secs_f64() * 1e3;
    *c = std::time::Instant::now();
    ms
}

impl std::fmt::Debug for GpuRasterizer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuRasterizer")
            .field("adapter", &self.name)
            .field("n", &self.n)
            .finish()
    }
}

fn gpu_err(what: &str, e: impl std::fmt::Display) -> Error {
    Error::Gpu(format!("{what}: {e}"))
}

/// The compute pipeline of `entry` in `module`, its bind group layout derived from the shader.
fn compute_pipeline(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    entry: &str,
) -> wgpu::ComputePipeline {
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(entry),
        layout: None,
        module,
        entry_point: Some(entry),
        compilation_options: Default::default(),
        cache: None,
    })
}

/// The Gaussians' geometry as the kernels read it (step 0 of the module docs), uploaded: means
/// relative to `origin` with the opacity (0 for a Gaussian the kernels must cull: a non-finite
/// mean or scale, a zero quaternion, an opacity outside `(0, ∞)`), scales, unit quaternions;
/// `[N × 4]` f32 each.
fn upload_geometry(
    device: &wgpu::Device,
    gaussians: &Gaussians,
    origin: glam::DVec3,
) -> [wgpu::Buffer; 3] {
    let n = gaussians.len();
    let mut mo = Vec::with_capacity(n * 4);
    let mut sc = Vec::with_capacity(n * 4);
    let mut qu = Vec::with_capacity(n * 4);
    for i in 0..n {
        let m = gaussians.means[i];
        let s = gaussians.scales[i];
        let q = unit_quaternion(gaussians.rotations[i]);
        let o = gaussians.opacities[i];
        let valid =
            m.iter().chain(&s).all(|v| v.is_finite()) && q.is_some() && o > 0.0 && o.is_finite();
        let rel = |k: usize| (m[k] as f64 - origin[k]) as f32;
        mo.extend_from_slice(&[rel(0), rel(1), rel(2), if valid { o } else { 0.0 }]);
        sc.extend_from_slice(&[s[0], s[1], s[2], 0.0]);
        qu.extend_from_slice(&q.unwrap_or([0.0; 4]));
    }
    [
        storage_init(device, "means_opac", bytemuck::cast_slice(&mo)),
        storage_init(device, "scales", bytemuck::cast_slice(&sc)),
        storage_init(device, "quats", bytemuck::cast_slice(&qu)),
    ]
}

/// Validation step: the Gaussians' arrays agree in length and their count fits a u32.
fn gaussian_count(gaussians: &Gaussians) -> Result<u32> {
    let n = gaussians.len();
    if gaussians.scales.len() != n
        || gaussians.rotations.len() != n
        || gaussians.opacities.len() != n
    {
        return Err(Error::internal(
            "Gaussians arrays (means/scales/rotations/opacities) have different lengths",
        ));
    }
    u32::try_from(n)
        .map_err(|_| Error::Invalid(format!("{n} Gaussians exceed the 2^32 - 1 supported")))
}

/// Device step: opens the adapter's device with its own limits, and f64 where it has it.
fn open_device(
    adapter: &wgpu::Adapter,
    info: &wgpu::AdapterInfo,
    limits: &wgpu::Limits,
) -> Result<(wgpu::Device, wgpu::Queue)> {
    pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
        label: Some("slag-raster"),
        // f64 for the device reduction (ek.wgsl), where the adapter has it.
        required_features: adapter.features() & wgpu::Features::SHADER_F64,
        required_limits: limits.clone(),
        ..Default::default()
    }))
    .map_err(|e| gpu_err(&format!("cannot open device {}", info.name), e))
}

/// Limits step: `n` Gaussians' largest per-Gaussian buffer (the splats) fits one binding.
fn check_gaussians_fit(n: usize, limits: &wgpu::Limits) -> Result<()> {
    let max_bind = limits
        .max_storage_buffer_binding_size
        .min(limits.max_buffer_size);
    let per_g = 32u64; // largest per-Gaussian buffer: splats, 32 B
    if n as u64 * per_g > max_bind {
        return Err(Error::Gpu(format!(
            "{n} Gaussians need {} MiB buffers but the device allows {} MiB per binding; \
             use a GPU with larger limits or a smaller scene",
            (n as u64 * per_g) >> 20,
            max_bind >> 20
        )));
    }
    Ok(())
}

/// Scratch step: the per-Gaussian buffers every view rewrites for `n` Gaussians: splats, tile
/// rects (`isect`), sort depths, tile counts (`n + 1` words) and their scan's block sums.
fn per_view_scratch(device: &wgpu::Device, n: u32) -> [wgpu::Buffer; 5] {
    let n64 = u64::from(n);
    [
        storage(device, "splats", n64 * 32),
        storage(device, "isect", n64 * 8),
        storage(device, "sort_depths", n64 * 4),
        storage(device, "tile_counts", (n64 + 1) * 4),
        storage(
            device,
            "tile_count_sums",
            (u64::from(n.div_ceil(SCAN_BLOCK)) + 1) * 4,
        ),
    ]
}

impl Pipelines {
    /// Kernel step: compiles the joined WGSL ([`SHADER`]) and every entry point's pipeline.
    fn compile(device: &wgpu::Device) -> Self {
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("slag-raster kernels"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
        let pipe = |entry: &str| compute_pipeline(device, &module, entry);
        Pipelines {
            project: pipe("project"),
            blend: pipe("blend"),
            blend_sums: pipe("blend_sums"),
            scan_local: pipe("scan_local"),
            scan_blocks: pipe("scan_blocks"),
            scan_add: pipe("scan_add"),
            emit: pipe("emit"),
            radix_count: pipe("radix_count"),
            radix_scatter: pipe("radix_scatter"),
            tile_bounds: pipe("tile_bounds"),
            record_keys: pipe("record_keys"),
            record_heads: pipe("record_heads"),
            record_sums: pipe("record_sums"),
            blend_totals: pipe("blend_totals"),
            coverage_seen: pipe("coverage_seen"),
        }
    }
}

impl GpuRasterizer {
    /// Creates the device (see [`ADAPTER_ENV`] for adapter choice), compiles the kernels and
    /// uploads the Gaussians' geometry once (`3 × 16 B` per Gaussian, plus `48 B` of per-view
    /// scratch: splat, tile rect, tile count, sort depth; the sort's buffers, `24 B` per tile
    /// intersection, are allocated for the first view and grown when a view needs more).
    ///
    /// Errors: [`Error::Gpu`] when no Vulkan adapter exists (install `mesa-vulkan-drivers`), the
    /// device cannot be created, or the scene exceeds the device's buffer limits;
    /// [`Error::Invalid`] for more than 2^32 − 1 Gaussians, [`Error::Internal`] for array lengths that disagree.
    pub fn new(gaussians: &Gaussians) -> Result<Self> {
        Ok(Self::new_many(gaussians, Some(1))?.remove(0))
    }

    /// One rasterizer per GPU for a multi-GPU run: `gpus` adapters of the best available kind
    /// (all discrete GPUs when `None`; see [`adapter_names`] for the order), each with its own
    /// device, kernels and copy of the Gaussians' geometry. Without a discrete GPU, one rasterizer
    /// on the best adapter (e.g. lavapipe) is returned whatever `gpus` says.
    ///
    /// Errors: as [`GpuRasterizer::new`]; [`Error::Param`] `gpus` when more GPUs are asked for
    /// than exist (the message lists them) or `gpus` is `Some(0)`.
    pub fn new_many(gaussians: &Gaussians, gpus: Option<usize>) -> Result<Vec<Self>> {
        if gpus == Some(0) {
            return Err(Error::param("gpus", 0, "at least 1 GPU"));
        }
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = wgpu::Backends::VULKAN;
        let instance = wgpu::Instance::new(desc);
        let ranked = ranked_adapters(&instance)?;
        let best = ranked[0].get_info().device_type;
        let same: Vec<wgpu::Adapter> = ranked
            .into_iter()
            .filter(|a| a.get_info().device_type == best)
            .collect();
        let chosen: Vec<wgpu::Adapter> = if best != wgpu::DeviceType::DiscreteGpu {
            same.into_iter().take(1).collect()
        } else {
            match gpus {
                None => same,
                Some(k) if k <= same.len() => same.into_iter().take(k).collect(),
                Some(k) => {
                    return Err(Error::param(
                        "gpus",
                        k,
                        format!(
                            "at most the {} visible GPU(s): {}",
                            same.len(),
                            same.iter()
                                .map(|a| a.get_info().name)
                                .collect::<Vec<_>>()
                                .join(", ")
                        ),
                    ));
                }
            }
        };
        chosen
            .into_iter()
            .map(|adapter| Self::with_adapter(gaussians, adapter))
            .collect()
    }

    /// The rasterizer on one given adapter (see [`GpuRasterizer::new`]).
    fn with_adapter(gaussians: &Gaussians, adapter: wgpu::Adapter) -> Result<Self> {
        let n32 = gaussian_count(gaussians)?;
        let n = gaussians.len();
        let info = adapter.get_info();
        let limits = adapter.limits();
        let (device, queue) = open_device(&adapter, &info, &limits)?;
        let name = format!("wgpu-vulkan {} ({:?})", info.name, info.device_type);
        tracing::info!(adapter = %name, gaussians = n, "weight rasterizer device");
        check_gaussians_fit(n, &limits)?;
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let origin = scene_origin(&gaussians.means);
        let [means_opac, scales, quats] = upload_geometry(&device, gaussians, origin);
        let [splats, isect, sort_depths, tile_counts, tile_count_sums] =
            per_view_scratch(&device, n32);
        let pipelines = Pipelines::compile(&device);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(gpu_err("creating the rasterizer kernels/buffers failed", e));
        }
        Ok(GpuRasterizer {
            device,
            queue,
            name,
            limits,
            n: n32,
            means: Arc::new(gaussians.means.clone()),
            precomputed: None,
            origin,
            means_opac,
            scales,
            quats,
            splats,
            isect,
            sort_depths,
            tile_counts,
            tile_count_sums,
            sort: None,
            pipelines,
            noise_seed: None,
            band_limit: None,
            timings: PhaseTimings::default(),
            out: None,
            label_records: INITIAL_LABEL_RECORDS,
            label_record_limit: None,
            label_out: None,
            coverage: None,
            label_retries: 0,
            label_record_count: 0,
            reduce: None,
            reduce_on_device: true,
            cpu_adapter: info.device_type == wgpu::DeviceType::Cpu,
            kept: None,
            stream: None,
            spent_kept: None,
            keeping: None,
            mask_record: None,
            kept_heads: Vec::new(),
            reduce_tile_bytes: None,
            readback_bytes: None,
        })
    }

    /// Testing aid: before every kernel run, fill every GPU output/scratch buffer with
    /// pseudo-random bytes from `seed` (or stop doing so with `None`), so that any output slot the
    /// kernels fail to write shows up as garbage instead of a plausible zero.
    pub fn set_noise_fill(&mut self, seed: Option<u64>) {
        self.noise_seed = seed;
    }

    /// Caps the bytes of one output buffer of the write pass (default: the device's binding
    /// limit). Smaller values split the write pass into more bands of tile rows; output is the
    /// same. For tests of the banding, or to bound peak GPU memory.
    pub fn set_band_limit(&mut self, bytes: Option<u64>) {
        self.band_limit = bytes;
    }

    /// Testing aid: the record capacity of the label-sum buffer for the next view (at least
    /// 1; it grows when a band needs more) and the most records one binding may hold (`None`:
    /// the device's binding limit). A small capacity exercises the re-run of a band; a small
    /// limit splits the view into bands of tile rows. The sums do not depend on either.
    pub fn set_label_records(&mut self, capacity: u64, limit: Option<u64>) {
        self.label_records = capacity.max(1);
        self.label_record_limit = limit.map(|l| l.max(1));
        self.label_out = None;
    }

    /// Testing aid: reduce the label-sum records by (Gaussian, label) on the device before the
    /// readback (`true`, the default) or read them back as the `blend_sums` kernel wrote them,
    /// one per tile (`false`). The sums after [`LabelSums::reduced`] do not depend on it.
    pub fn set_label_reduce_on_device(&mut self, on: bool) {
        self.reduce_on_device = on;
    }

    /// Band re-runs (a band did not fit its records buffer) of the last label-sum view.
    pub fn last_label_retries(&self) -> u32 {
        self.label_retries
    }

    /// Records (one per tile intersection and tile label with a non-zero sum) the `blend_sums`
    /// kernel wrote in the last label-sum view, before any reduction.
    pub fn last_label_records(&self) -> u64 {
        self.label_record_count
    }

    /// Phase timings of the last successful [`WeightRasterizer::rasterize`] call.
    pub fn last_timings(&self) -> PhaseTimings {
        self.timings
    }

    /// The device limits in force (the adapter's own limits).
    pub fn limits(&self) -> &wgpu::Limits {
        &self.limits
    }

    fn max_binding(&self) -> u64 {
        self.limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
    }

    fn check_size(&self, what: &str, bytes: u64, k: &Intrinsics) -> Result<()> {
        if bytes > self.max_binding() {
            return Err(Error::limit(
                Resource::GpuBinding,
                format!(
                    "{} MiB for the {what} buffer of the {}x{} weight raster",
                    bytes >> 20,
                    k.width,
                    k.height
                ),
                format!("{} MiB on this device", self.max_binding() >> 20),
            ));
        }
        Ok(())
    }

    /// One view: projection, binning, then either the label sums (`labels`) or the count +
    /// scan and banded write passes.
    fn run(
        &mut self,
        k: &Intrinsics,
        w2c: &WorldToCamera,
        labels: Option<&[u32]>,
    ) -> Result<RunOutput> {
        let mut kept = self.out.take();
        let (mut view, binned, mut timings, mut clock) = self.project_and_bin(k, w2c)?;

        // 3'. Label sums instead of per-pixel lists: only the compact records are read back.
        if let Some(labels) = labels {
            self.out = kept;
            let (sums, records_ms) = self.label_sums_pass(&mut view, &binned, labels)?;
            timings.write_ms = lap(&mut clock);
            timings.records_ms = records_ms;
            timings.host_ms = timings.bin_sort_ms + records_ms;
            self.timings = timings;
            return Ok(RunOutput::Sums(sums));
        }
        // 3a. Count pass + exclusive scan.
        let offsets = self.count_scan(&view, &binned)?;
        let total = offsets[view.n_pix as usize] as usize;
        timings.count_scan_ms = lap(&mut clock);
        // 3b. Write pass, in bands of whole tile rows.
        let (ids, weights) = self.write_banded(&mut view, &binned, &offsets, &mut kept)?;
        self.out = kept;
        timings.write_ms = lap(&mut clock);
        timings.host_ms = timings.bin_sort_ms;
        self.timings = timings;
        tracing::debug!(?timings, entries = total, "gpu weight raster");
        Ok(RunOutput::Weights(PixelWeights {
            width: k.width,
            height: k.height,
            offsets,
            ids,
            weights,
        }))
    }

    /// Steps 1–2 of a view: projection, the Gaussians' tile counts and their total, then the
    /// tile binning and depth sort on the GPU (recorded and submitted; no wait). Returns the
    /// view, its binned intersections, the phases' timings so far and the clock at their end.
    ///
    /// Errors: an invalid raster ([`validate_raster`]), the device's limits
    /// ([`Self::begin_view`]), device failures.
    fn project_and_bin(
        &mut self,
        k: &Intrinsics,
        w2c: &WorldToCamera,
    ) -> Result<(View, Binned, PhaseTimings, std::time::Instant)> {
        validate_raster(k)?;
        let view = self.begin_view(k, w2c)?;
        self.noise(&self.splats, SEED_SALT);
        self.noise(&self.isect, SEED_SALT + 1);
        let mut clock = std::time::Instant::now();
        let mut timings = PhaseTimings::default();
        self.upload_sort_depths(w2c);
        let depth_ms = lap(&mut clock);
        let total = self.project_count(&view)?;
        timings.project_ms = lap(&mut clock);
        let binned = self.sort_tiles(&view, total)?;
        timings.bin_sort_ms = depth_ms + lap(&mut clock);
        Ok((view, binned, timings, clock))
    }

    /// Checks the view against the device's dispatch and binding limits and uploads its
    /// [`Params`] (mode 0: count).
    fn begin_view(&self, k: &Intrinsics, w2c: &WorldToCamera) -> Result<View> {
        let (tiles_x, tiles_y) = tile_grid(k.width, k.height);
        let max_groups = self.limits.max_compute_workgroups_per_dimension;
        if tiles_x > max_groups.min(65535) || tiles_y > max_groups.min(65535) {
            return Err(Error::limit(
                Resource::GpuDispatch,
                format!(
                    "{tiles_x}x{tiles_y} tiles for the {}x{} raster",
                    k.width, k.height
                ),
                max_groups.min(65535),
            ));
        }
        let n_pix = k.width * k.height; // ≤ 2^28 (validate_raster)
        let n_tiles = tiles_x * tiles_y;
        let n_blocks = n_pix.div_ceil(SCAN_BLOCK);
        self.check_size("offsets", (n_pix as u64 + 1) * 4, k)?;
        self.check_size("tile ranges", n_tiles as u64 * 8, k)?;

        let r = w2c.rotation.transpose(); // rows of R are columns of Rᵀ
        // The kernel sees means relative to `origin`: R·μ + T = R·(μ - o) + (R·o + T), in f64.
        let t = w2c.rotation * self.origin + w2c.translation;
        let row = |i: usize, ti: f64| {
            let c = r.col(i);
            [c.x as f32, c.y as f32, c.z as f32, ti as f32]
        };
        let lims = jacobian_limits(k).map(|v| v as f32);
        let params = Params {
            rot0: row(0, t.x),
            rot1: row(1, t.y),
            rot2: row(2, t.z),
            focal: [k.fx as f32, k.fy as f32, k.cx as f32, k.cy as f32],
            lims,
            width: k.width,
            height: k.height,
            tiles_x,
            tiles_y,
            n_gaussians: self.n,
            n_pixels: n_pix,
            groups_x: GROUPS_X,
            mode: 0,
            n_blocks,
            tile_y0: 0,
            out_base: 0,
            out_cap: 0,
            n_keys: 0,
            shift: 0,
            floor_lo: 0,
            floor_hi: 0,
        };
        let params_buf = self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("params"),
                contents: bytemuck::bytes_of(&params),
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            });
        Ok(View {
            k: *k,
            tiles_x,
            tiles_y,
            n_pix,
            n_tiles,
            n_blocks,
            params,
            params_buf,
        })
    }

    /// Rewrites the view's [`Params`] on the device (after a change of mode or band).
    fn write_params(&self, view: &View) {
        self.queue
            .write_buffer(&view.params_buf, 0, bytemuck::bytes_of(&view.params));
    }

    /// The `blend` kernel's bind group for `view`: per-pixel outputs `out_ids` / `out_w`
    /// (placeholders in the count mode).
    fn blend_group(
        &self,
        view: &View,
        b: &Binned,
        out_ids: &wgpu::Buffer,
        out_w: &wgpu::Buffer,
    ) -> wgpu::BindGroup {
        self.bind(
            &self.pipelines.blend,
            &[
                (0, &view.params_buf),
                (4, &self.splats),
                (6, &b.ranges),
                (7, &b.sorted_ids),
                (8, &b.offsets),
                (9, out_ids),
                (10, out_w),
            ],
        )
    }
}

/// The midpoint of the bounding box of the finite means, f64 (the origin the uploaded means are
/// relative to); zero when there is none.
fn scene_origin(means: &[[f32; 3]]) -> glam::DVec3 {
    let mut lo = glam::DVec3::splat(f64::INFINITY);
    let mut hi = glam::DVec3::splat(f64::NEG_INFINITY);
    for m in means.iter().filter(|m| m.iter().all(|v| v.is_finite())) {
        let p = glam::DVec3::new(m[0] as f64, m[1] as f64, m[2] as f64);
        lo = lo.min(p);
        hi = hi.max(p);
    }
    if lo.x <= hi.x {
        (lo + hi) * 0.5
    } else {
        glam::DVec3::ZERO
    }
}

/// A (w, x, y, z) quaternion normalised in f64 (no f32 overflow or underflow of `|q|²` for any
/// finite f32 components); `None` for a zero or non-finite quaternion (culled, as in
/// [`super::project::quat_to_mat`]).
fn unit_quaternion(q: [f32; 4]) -> Option<[f32; 4]> {
    let q = q.map(f64::from);
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    (n > 0.0 && n.is_finite()).then(|| q.map(|v| (v / n) as f32))
}

impl GpuRasterizer {
    /// `run` (GPU work for the view `k`) inside validation and out-of-memory error scopes: an
    /// out-of-memory error is [`Error::Limit`] `GpuMemory` naming the view's size, a validation
    /// error an internal GPU error.
    fn in_error_scopes<T>(
        &mut self,
        k: &Intrinsics,
        run: impl FnOnce(&mut Self) -> Result<T>,
    ) -> Result<T> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let out = run(self);
        if let Some(e) = pollster::block_on(oom.pop()) {
            let _ = pollster::block_on(scope.pop());
            return Err(Error::limit(
                Resource::GpuMemory,
                format!("the {}x{} view's buffers ({e})", k.width, k.height),
                "the memory the device had free",
            ));
        }
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(gpu_err("rasterizer kernel failed", e));
        }
        out
    }
}

impl WeightRasterizer for GpuRasterizer {
    fn rasterize(&mut self, k: &Intrinsics, w2c: &WorldToCamera) -> Result<PixelWeights> {
        match self.in_error_scopes(k, |r| r.run(k, w2c, None))? {
            RunOutput::Weights(w) => Ok(w),
            RunOutput::Sums(_) => Err(Error::internal(
                "rasterizer returned sums for a weights run",
            )),
        }
    }

    fn label_sums(
        &mut self,
        k: &Intrinsics,
        w2c: &WorldToCamera,
        labels: &[u32],
    ) -> Result<Option<LabelSums>> {
        match self.in_error_scopes(k, |r| r.run(k, w2c, Some(labels)))? {
            RunOutput::Sums(s) => Ok(Some(s)),
            RunOutput::Weights(_) => Err(Error::internal(
                "rasterizer returned weights for a sums run",
            )),
        }
    }

    fn view_precompute(&self) -> Option<Arc<dyn ViewPrecompute>> {
        Some(Arc::new(sort::SortDepthsAhead {
            means: Arc::clone(&self.means),
        }))
    }

    fn label_sums_precomputed(
        &mut self,
        k: &Intrinsics,
        w2c: &WorldToCamera,
        labels: &[u32],
        precomputed: Option<PrecomputedView>,
    ) -> Result<Option<LabelSums>> {
        self.precomputed = precomputed;
        let out = self.label_sums(k, w2c, labels);
        self.precomputed = None;
        out
    }

    fn coverage_view(
        &mut self,
        k: &Intrinsics,
        w2c: &WorldToCamera,
        floor: u64,
        precomputed: Option<PrecomputedView>,
    ) -> Result<Option<Vec<u64>>> {
        self.precomputed = precomputed;
        let out = self.in_error_scopes(k, |r| r.run_coverage(k, w2c, floor));
        self.precomputed = None;
        out.map(Some)
    }

    fn take_coverage_maxima(&mut self) -> Result<Option<Vec<u64>>> {
        self.read_coverage_maxima().map(Some)
    }

    fn keep_on_device(&mut self, dim: usize, budget_bytes: u64, on_cpu_adapter: bool) -> bool {
        if self.cpu_adapter && !on_cpu_adapter {
            return false;
        }
        self.kept.is_some() || self.start_keeping(dim, budget_bytes)
    }

    fn label_sums_kept(
        &mut self,
        k: &Intrinsics,
        w2c: &WorldToCamera,
        labels: &[u32],
        precomputed: Option<PrecomputedView>,
        masks: KeptMasks<'_>,
    ) -> Result<Option<KeptView>> {
        if self.kept.is_none() || !self.reduce_on_device {
            return Ok(None);
        }
        let id = self.begin_kept_view(&masks)?;
        let record_view = self
            .mask_record
            .as_ref()
            .and_then(|_| u32::try_from(masks.view).ok())
            .filter(|&v| v < u32::from(slag_common::mask_record::EMPTY_VIEW));
        self.keeping = Some(ek::Keeping {
            id,
            dominant: masks.dominant,
            record_view,
        });
        self.kept_heads.clear();
        self.precomputed = precomputed;
        let out = self.label_sums(k, w2c, labels);
        self.precomputed = None;
        self.keeping = None;
        let out = out.inspect_err(|_| self.forget_kept_view(id));
        let sums = out?.ok_or_else(|| Error::internal("no sums from a kept view"))?;
        self.kept_view_done(id)?;
        let mut dominant = std::mem::take(&mut self.kept_heads);
        // A view of several bands: its bands' Gaussians interleave; keep them ascending.
        dominant.sort_by_key(|d| d.0);
        Ok(Some(KeptView {
            contributions: sums.contributions,
            dominant,
        }))
    }

    fn reduce_kept(
        &mut self,
        params: &DeviceReduce,
        sink: &mut dyn FnMut(KeptTile) -> Result<()>,
    ) -> Result<KeptReduced> {
        if self.stream.is_some() {
            return self.reduce_streamed(params, sink);
        }
        self.reduce_kept_tiles(params, sink)
    }

    fn stream_kept(&mut self, keep: usize) -> bool {
        self.start_streaming(keep)
    }

    fn fold_kept(&mut self, below: usize) -> Result<bool> {
        self.fold_kept_due(below)
    }

    fn stream_kept_share(
        &mut self,
        keep: usize,
        share: usize,
        shares: usize,
    ) -> Option<ek::KeptInbox> {
        self.start_streaming_share(keep, share, shares)
    }

    fn share_kept_with(&mut self, peers: Option<Vec<ek::KeptInbox>>) {
        self.share_stream_with(peers);
    }

    fn kept_share(&self) -> Option<(u32, u32)> {
        self.streamed_share().map(|r| (r.start, r.end))
    }

    fn keep_mask_record(&mut self, slots: usize, view_count: usize) -> bool {
        self.start_device_mask_record(slots, view_count)
    }

    fn take_mask_record(&mut self) -> Result<Option<slag_common::mask_record::MaskRecord>> {
        self.take_device_mask_record()
    }

    fn export_kept(&mut self) -> Result<Option<KeptExport>> {
        self.export_kept_views()
    }

    fn export_kept_batch(&mut self, max_bytes: u64) -> Result<Option<KeptExport>> {
        self.export_kept_views_batch(max_bytes)
    }

    fn kept_block_records(&self) -> Option<(u32, Vec<u64>)> {
        Some((ek::BLOCK_GAUSSIANS, self.kept_block_records()?))
    }

    fn export_kept_range(
        &mut self,
        cursor: &mut KeptRangeCursor,
        max_bytes: u64,
    ) -> Result<Option<KeptExport>> {
        self.export_kept_range(cursor, max_bytes)
    }

    fn import_kept(&mut self, kept: KeptExport) -> Result<()> {
        self.import_kept_views(kept)
    }

    fn kept_uploader(&self) -> Option<ek::KeptUploader> {
        self.kept.is_some().then(|| self.kept_uploader())
    }

    fn import_uploaded(&mut self, kept: ek::UploadedKept) -> Result<()> {
        self.import_uploaded(kept)
    }

    fn name(&self) -> &str {
        &self.name
    }

    fn last_phases(&self) -> Option<PhaseTimings> {
        Some(self.timings)
    }
}

#[cfg(test)]
mod tests {
    /// The Rust mirror of the WGSL `Params` struct has the same size as the WGSL declaration
    /// (counted from common.wgsl: 16 bytes per vec4<f32>, 4 per u32).
    #[test]
    fn params_size_matches_the_wgsl_struct() {
        let wgsl = include_str!("common.wgsl");
        let start = wgsl.find("struct Params {").expect("Params in common.wgsl");
        let body = &wgsl[start..start + wgsl[start..].find('}').expect("closing brace")];
        let (mut vec4s, mut u32s) = (0, 0);
        for line in body.lines().skip(1) {
            let ty = line.split("//").next().unwrap_or("").trim();
            if ty.ends_with("vec4<f32>,") {
                vec4s += 1;
            } else if ty.ends_with("u32,") {
                u32s += 1;
            }
        }
        assert_eq!((vec4s, u32s), (5, 16), "{body}");
        assert_eq!(16 * vec4s + 4 * u32s, std::mem::size_of::<super::Params>());
    }
}
