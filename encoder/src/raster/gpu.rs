//! The GPU weight rasterizer: wgpu compute kernels in `weights.wgsl` (Vulkan backend).
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
//!    form for needles and sheets) kept on the GPU, and an 8-byte tile rect read
//!    back.
//! 2. Tile binning and depth sort **on the CPU** (per Gaussian, never per pixel): every
//!    (tile, Gaussian) intersection gets the key `(tile, depth, id)`, sorted with rayon, then
//!    per-tile ranges. The depth is computed on the host in f64 by the same function as the CPU
//!    reference ([`camera_point`]), so the order is bit-identical to the reference's, near-ties
//!    included; the id makes keys unique, so the order is deterministic. Moving this to the GPU (a
//!    radix sort of the keys, as gsplat does) is the next step for very large scenes; there the
//!    depth would become f32 and exact-tie order would still be fixed by the id.
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
//! Output buffers are sized from the counts and checked against the device's
//! `max_storage_buffer_binding_size` / `max_buffer_size`; a view whose single row of tiles (or
//! offsets array) exceeds them is an [`Error::Limit`] naming the limit (the command line adds
//! that `--raster-scale` lowers the need).

use std::sync::mpsc;

use rayon::prelude::*;
use slag_common::camera::{Intrinsics, WorldToCamera};
use slag_common::rng::SplitMix64;
use slag_common::scene::Gaussians;
use slag_common::{Error, Resource, Result};
use wgpu::util::DeviceExt;

use super::project::{camera_point, jacobian_limits, tile_grid};
use super::{LabelSum, LabelSums, PixelWeights, WeightRasterizer, validate_raster};

const SHADER: &str = include_str!("weights.wgsl");
/// x extent of the 2D dispatches over Gaussians / scan blocks (must match `params.groups_x` use).
const GROUPS_X: u32 = 32768;
/// Elements per scan block (256 invocations × 4).
const SCAN_BLOCK: u32 = 1024;

/// Environment variable: substring (case-insensitive) of the adapter name to use.
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
    table_mask: u32,
}

/// Wall-clock milliseconds of the phases of the last [`GpuRasterizer`] run (host-observed,
/// including submission and readback waits).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PhaseTimings {
    /// Projection kernel + tile-rect readback.
    pub project_ms: f64,
    /// Host binning and depth sort.
    pub bin_sort_ms: f64,
    /// Count pass, prefix sum, offsets readback.
    pub count_scan_ms: f64,
    /// Write pass(es) + ids/weights readback.
    pub write_ms: f64,
}

struct Pipelines {
    project: wgpu::ComputePipeline,
    blend: wgpu::ComputePipeline,
    scan_local: wgpu::ComputePipeline,
    scan_blocks: wgpu::ComputePipeline,
    scan_add: wgpu::ComputePipeline,
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
    /// Means kept on the host for the f64 sort depth ([`camera_point`]).
    means: Vec<[f32; 3]>,
    /// World-frame centre the uploaded means are relative to (f64; see the module docs, step 0).
    origin: glam::DVec3,
    means_opac: wgpu::Buffer,
    scales: wgpu::Buffer,
    quats: wgpu::Buffer,
    splats: wgpu::Buffer,
    isect: wgpu::Buffer,
    pipelines: Pipelines,
    noise_seed: Option<u64>,
    band_limit: Option<u64>,
    timings: PhaseTimings,
    /// Write-pass output and its readback staging, kept across views (grown on demand).
    out: Option<OutBuffers>,
    /// Slots of the label-sum table for the next view (a power of two; grown when a view
    /// overflows it or fills more than half of it).
    label_slots: u32,
    /// Testing aid: start the next view's table at exactly `label_slots` (no estimate).
    label_slots_fixed: bool,
    /// Retries (table overflows) of the last label-sum view.
    label_retries: u32,
}

/// The write pass's output buffers (ids, weights) and their `MAP_READ` staging twins, reused
/// across views so that a view neither allocates (and zero-fills) ~8 bytes per entry on the
/// device nor maps fresh host memory: each view's weights are copied once, from the mapped
/// staging range straight into the returned [`PixelWeights`].
struct OutBuffers {
    ids: wgpu::Buffer,
    weights: wgpu::Buffer,
    stage_ids: wgpu::Buffer,
    stage_weights: wgpu::Buffer,
    /// Bytes each of the four holds.
    capacity: u64,
}

/// What one [`GpuRasterizer::run`] produced.
enum RunOutput {
    /// Per-pixel lists (modes 0 + 1).
    Weights(PixelWeights),
    /// Per-(Gaussian, label) sums (mode 2).
    Sums(LabelSums),
    /// Mode 2 declined: more visible Gaussians than raster pixels (few contributions per sum,
    /// where the per-pixel lists are faster), or more sums than one table binding holds.
    UseLists,
}

/// Label-sum table slots of a new rasterizer (4 MiB); grown per view as needed.
const INITIAL_LABEL_SLOTS: u32 = 1 << 18;
/// Most label-sum table slots (4 GiB of table): beyond, the view is refused.
const MAX_LABEL_SLOTS: u32 = 1 << 28;

/// The non-empty slots of a mode-2 table (4 words each: Gaussian + 1, label, low, high), sorted by
/// (Gaussian, label), duplicates of one key (see `add_label_sum` in weights.wgsl) added.
fn decode_label_sums(slots: &[u32]) -> Vec<LabelSum> {
    let mut out: Vec<LabelSum> = slots
        .chunks_exact(4)
        .filter(|w| w[0] != 0)
        .map(|w| LabelSum {
            gaussian: w[0] - 1,
            label: w[1],
            sum: (u64::from(w[3]) << 32) | u64::from(w[2]),
        })
        .collect();
    out.par_sort_unstable_by_key(|e| (e.gaussian, e.label));
    out.dedup_by(|next, kept| {
        if (next.gaussian, next.label) == (kept.gaussian, kept.label) {
            kept.sum += next.sum;
            true
        } else {
            false
        }
    });
    out
}

/// Appends the little-endian `T`s in `bytes` to `dst` (one copy when `bytes` is aligned for `T`,
/// as mapped ranges are; element by element otherwise).
fn extend_pod<T: bytemuck::Pod>(dst: &mut Vec<T>, bytes: &[u8]) {
    match bytemuck::try_cast_slice::<u8, T>(bytes) {
        Ok(s) => dst.extend_from_slice(s),
        Err(_) => dst.extend(
            bytes
                .chunks_exact(std::mem::size_of::<T>())
                .map(bytemuck::pod_read_unaligned::<T>),
        ),
    }
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

/// The Vulkan adapters slag would use, best first: those matching `$SLAG_WGPU_ADAPTER`
/// (case-insensitive substring) if set, else ranked discrete, integrated, virtual, other, CPU
/// (Mesa lavapipe), in enumeration order within a rank.
///
/// Errors: [`Error::Gpu`] when there is no Vulkan adapter (install a driver) or none matches
/// `$SLAG_WGPU_ADAPTER` (the message lists what exists).
fn ranked_adapters(instance: &wgpu::Instance) -> Result<Vec<wgpu::Adapter>> {
    let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::VULKAN));
    let names: Vec<String> = adapters
        .iter()
        .map(|a| format!("{} ({:?})", a.get_info().name, a.get_info().device_type))
        .collect();
    if adapters.is_empty() {
        return Err(Error::Gpu(
            "no Vulkan adapter found; install a Vulkan driver (on Debian/Ubuntu without a GPU: \
             `apt-get install mesa-vulkan-drivers` for the lavapipe CPU driver)"
                .into(),
        ));
    }
    if let Ok(want) = std::env::var(ADAPTER_ENV) {
        let want_l = want.to_lowercase();
        let matching: Vec<wgpu::Adapter> = adapters
            .into_iter()
            .filter(|a| a.get_info().name.to_lowercase().contains(&want_l))
            .collect();
        if matching.is_empty() {
            return Err(Error::Gpu(format!(
                "{ADAPTER_ENV}={want:?} matches no Vulkan adapter; available: {}",
                names.join(", ")
            )));
        }
        return Ok(matching);
    }
    use wgpu::DeviceType as D;
    let rank = |t: D| match t {
        D::DiscreteGpu => 0,
        D::IntegratedGpu => 1,
        D::VirtualGpu => 2,
        D::Other => 3,
        D::Cpu => 4,
    };
    let mut adapters = adapters;
    adapters.sort_by_key(|a| rank(a.get_info().device_type));
    Ok(adapters)
}

/// Names and types of the adapters [`GpuRasterizer::new_many`] chooses from, best first.
///
/// Errors: as [`GpuRasterizer::new`] when no adapter exists.
pub fn adapter_names() -> Result<Vec<String>> {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::VULKAN;
    let instance = wgpu::Instance::new(desc);
    Ok(ranked_adapters(&instance)?
        .iter()
        .map(|a| format!("{} ({:?})", a.get_info().name, a.get_info().device_type))
        .collect())
}

fn storage_init(device: &wgpu::Device, label: &str, data: &[u8]) -> wgpu::Buffer {
    // Bindings must be non-empty and hold one array element: pad empty data to 64 bytes.
    let pad = [0u8; 64];
    let contents = if data.is_empty() { &pad[..] } else { data };
    device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(label),
        contents,
        usage: wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_SRC
            | wgpu::BufferUsages::COPY_DST,
    })
}

fn storage(device: &wgpu::Device, label: &str, size: u64) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: size.max(64).next_multiple_of(4),
        usage: wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_SRC
            | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

/// Deterministic pseudo-random bytes (splitmix64), for the noise fill.
fn noise_bytes(seed: u64, len: usize) -> Vec<u8> {
    let mut rng = SplitMix64::new(seed);
    let mut out = Vec::with_capacity(len + 8);
    while out.len() < len {
        out.extend_from_slice(&rng.next_u64().to_le_bytes());
    }
    out.truncate(len);
    out
}

impl GpuRasterizer {
    /// Creates the device (see [`ADAPTER_ENV`] for adapter choice), compiles the kernels and
    /// uploads the Gaussians' geometry once (`3 × 16 B` per Gaussian, plus `48 B` of per-view
    /// scratch).
    ///
    /// Errors: [`Error::Gpu`] when no Vulkan adapter exists (install `mesa-vulkan-drivers`), the
    /// device cannot be created, or the scene exceeds the device's buffer limits;
    /// [`Error::Invalid`] for more than 2^32 − 1 Gaussians or array lengths that disagree.
    pub fn new(gaussians: &Gaussians) -> Result<Self> {
        Ok(Self::new_many(gaussians, Some(1))?.remove(0))
    }

    /// One rasterizer per GPU for a multi-GPU run: `gpus` adapters of the best available kind
    /// (all discrete GPUs when `None`; see [`adapter_names`] for the order), each with its own
    /// device, kernels and copy of the Gaussians' geometry. Without a discrete GPU, one rasterizer
    /// on the best adapter (e.g. lavapipe) is returned whatever `gpus` says.
    ///
    /// Errors: as [`GpuRasterizer::new`]; [`Error::Invalid`] when more GPUs are asked for than
    /// exist (the message lists them) or `gpus` is `Some(0)`.
    pub fn new_many(gaussians: &Gaussians, gpus: Option<usize>) -> Result<Vec<Self>> {
        if gpus == Some(0) {
            return Err(Error::Invalid("--gpus must be at least 1".into()));
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
                    return Err(Error::Invalid(format!(
                        "--gpus {k} but only {} GPU(s) are visible: {}",
                        same.len(),
                        same.iter()
                            .map(|a| a.get_info().name)
                            .collect::<Vec<_>>()
                            .join(", ")
                    )));
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
        let n = gaussians.len();
        if gaussians.scales.len() != n
            || gaussians.rotations.len() != n
            || gaussians.opacities.len() != n
        {
            return Err(Error::Invalid(
                "Gaussians arrays (means/scales/rotations/opacities) have different lengths".into(),
            ));
        }
        let n32 = u32::try_from(n)
            .map_err(|_| Error::Invalid(format!("{n} Gaussians exceed the 2^32 - 1 supported")))?;
        let info = adapter.get_info();
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("slag-raster"),
            required_features: wgpu::Features::empty(),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| gpu_err(&format!("cannot open device {}", info.name), e))?;
        let name = format!("wgpu-vulkan {} ({:?})", info.name, info.device_type);
        tracing::info!(adapter = %name, gaussians = n, "weight rasterizer device");

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
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let origin = scene_origin(&gaussians.means);
        let mut mo = Vec::with_capacity(n * 4);
        let mut sc = Vec::with_capacity(n * 4);
        let mut qu = Vec::with_capacity(n * 4);
        for i in 0..n {
            let m = gaussians.means[i];
            let s = gaussians.scales[i];
            let q = unit_quaternion(gaussians.rotations[i]);
            let o = gaussians.opacities[i];
            let valid = m.iter().chain(&s).all(|v| v.is_finite())
                && q.is_some()
                && o > 0.0
                && o.is_finite();
            let rel = |k: usize| (m[k] as f64 - origin[k]) as f32;
            mo.extend_from_slice(&[rel(0), rel(1), rel(2), if valid { o } else { 0.0 }]);
            sc.extend_from_slice(&[s[0], s[1], s[2], 0.0]);
            qu.extend_from_slice(&q.unwrap_or([0.0; 4]));
        }
        let means_opac = storage_init(&device, "means_opac", bytemuck::cast_slice(&mo));
        let scales = storage_init(&device, "scales", bytemuck::cast_slice(&sc));
        let quats = storage_init(&device, "quats", bytemuck::cast_slice(&qu));
        let splats = storage(&device, "splats", n as u64 * 32);
        let isect = storage(&device, "isect", n as u64 * 8);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("weights.wgsl"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
        let pipe = |entry: &str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: None,
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let pipelines = Pipelines {
            project: pipe("project"),
            blend: pipe("blend"),
            scan_local: pipe("scan_local"),
            scan_blocks: pipe("scan_blocks"),
            scan_add: pipe("scan_add"),
        };
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(gpu_err("creating the rasterizer kernels/buffers failed", e));
        }
        Ok(GpuRasterizer {
            device,
            queue,
            name,
            limits,
            n: n32,
            means: gaussians.means.clone(),
            origin,
            means_opac,
            scales,
            quats,
            splats,
            isect,
            pipelines,
            noise_seed: None,
            band_limit: None,
            timings: PhaseTimings::default(),
            out: None,
            label_slots: INITIAL_LABEL_SLOTS,
            label_slots_fixed: false,
            label_retries: 0,
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

    /// Testing aid: the slots of the label-sum table for the next view (rounded up to a power of
    /// two, at least 4). Tiny tables overflow and exercise the retry with more slots; the sums do
    /// not depend on the table size.
    pub fn set_label_table_slots(&mut self, slots: u32) {
        self.label_slots = slots.max(4).next_power_of_two();
        self.label_slots_fixed = true;
    }

    /// Table overflows (each a retry with 4× the slots) of the last label-sum view.
    pub fn last_label_retries(&self) -> u32 {
        self.label_retries
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

    fn noise(&self, buf: &wgpu::Buffer, salt: u64) {
        if let Some(seed) = self.noise_seed {
            let bytes = noise_bytes(
                seed ^ salt.wrapping_mul(0x2545_F491_4F6C_DD1D),
                buf.size() as usize,
            );
            self.queue.write_buffer(buf, 0, &bytes);
        }
    }

    fn bind(
        &self,
        pipeline: &wgpu::ComputePipeline,
        entries: &[(u32, &wgpu::Buffer)],
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry<'_>> = entries
            .iter()
            .map(|(b, buf)| wgpu::BindGroupEntry {
                binding: *b,
                resource: buf.as_entire_binding(),
            })
            .collect();
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        })
    }

    /// Submits `encoder` after adding copies of `(buffer, byte offset, byte size)` into staging
    /// buffers, waits, and returns the bytes of each.
    fn submit_and_read(
        &self,
        mut encoder: wgpu::CommandEncoder,
        reads: &[(&wgpu::Buffer, u64, u64)],
    ) -> Result<Vec<Vec<u8>>> {
        let staging: Vec<wgpu::Buffer> = reads
            .iter()
            .map(|&(src, off, size)| {
                let size = size.max(4).next_multiple_of(4);
                let dst = self.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("readback"),
                    size,
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                });
                let copy = size.min(src.size() - off);
                encoder.copy_buffer_to_buffer(src, off, &dst, 0, copy);
                dst
            })
            .collect();
        let mut out = Vec::with_capacity(reads.len());
        let mapped: Vec<(&wgpu::Buffer, u64)> = staging
            .iter()
            .zip(reads)
            .map(|(buf, &(_, _, size))| (buf, size))
            .collect();
        self.submit_and_map(encoder, &mapped, |_, bytes| out.push(bytes.to_vec()))?;
        Ok(out)
    }

    /// `kept` if it holds `bytes`, else new write-pass buffers of `bytes` plus a quarter (at
    /// most `limit`), so views of similar size reuse them.
    fn out_buffers(&self, kept: Option<OutBuffers>, bytes: u64, limit: u64) -> OutBuffers {
        if let Some(o) = kept
            && o.capacity >= bytes
            && o.capacity <= limit.max(bytes)
        {
            return o;
        }
        let capacity = (bytes + bytes / 4)
            .min(limit.max(bytes))
            .next_multiple_of(4);
        let staging = |label| {
            self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: capacity,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        OutBuffers {
            ids: storage(&self.device, "out_ids", capacity),
            weights: storage(&self.device, "out_weights", capacity),
            stage_ids: staging("readback_ids"),
            stage_weights: staging("readback_weights"),
            capacity,
        }
    }

    /// Submits `enc` (which ends with the copies into `out`'s staging buffers), waits, and
    /// appends the first `bytes` of each staging buffer to `ids` / `weights`.
    fn read_entries(
        &self,
        enc: wgpu::CommandEncoder,
        out: &OutBuffers,
        bytes: u64,
        ids: &mut Vec<u32>,
        weights: &mut Vec<f32>,
    ) -> Result<()> {
        let staged = [(&out.stage_ids, bytes), (&out.stage_weights, bytes)];
        self.submit_and_map(enc, &staged, |i, view| {
            if i == 0 {
                extend_pod(ids, view);
            } else {
                extend_pod(weights, view);
            }
        })
    }

    /// Submits `enc` (which ends with copies into the `MAP_READ` buffers of `staged`), waits, and
    /// hands the first `bytes` of each staged buffer to `visit(index, bytes)`, then unmaps it.
    fn submit_and_map(
        &self,
        enc: wgpu::CommandEncoder,
        staged: &[(&wgpu::Buffer, u64)],
        mut visit: impl FnMut(usize, &[u8]),
    ) -> Result<()> {
        self.queue.submit([enc.finish()]);
        let (tx, rx) = mpsc::channel();
        for &(buf, bytes) in staged {
            let tx = tx.clone();
            buf.slice(..bytes.max(4).next_multiple_of(4)).map_async(
                wgpu::MapMode::Read,
                move |r| {
                    let _ = tx.send(r);
                },
            );
        }
        drop(tx);
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| gpu_err("waiting for the rasterizer kernels failed", e))?;
        for r in rx.iter() {
            r.map_err(|e| gpu_err("reading back rasterizer output failed", e))?;
        }
        for (i, &(buf, bytes)) in staged.iter().enumerate() {
            {
                let view = buf
                    .slice(..bytes.max(4).next_multiple_of(4))
                    .get_mapped_range()
                    .map_err(|e| gpu_err("mapping rasterizer output failed", e))?;
                visit(i, &view[..bytes as usize]);
            }
            buf.unmap();
        }
        Ok(())
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

    fn run(
        &mut self,
        k: &Intrinsics,
        w2c: &WorldToCamera,
        labels: Option<&[u32]>,
    ) -> Result<RunOutput> {
        validate_raster(k)?;
        let mut kept = self.out.take();
        let fixed_slots = labels.is_some() && std::mem::take(&mut self.label_slots_fixed);
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
        let mut params = Params {
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
            table_mask: 0,
        };
        let params_buf = self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("params"),
                contents: bytemuck::bytes_of(&params),
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            });
        let seed_salt = 1;
        self.noise(&self.splats, seed_salt);
        self.noise(&self.isect, seed_salt + 1);

        // 1. Projection.
        let mut clock = std::time::Instant::now();
        let lap = |c: &mut std::time::Instant| {
            let ms = c.elapsed().as_secs_f64() * 1e3;
            *c = std::time::Instant::now();
            ms
        };
        let mut timings = PhaseTimings::default();
        let groups = self.n.div_ceil(256);
        let mut enc = self.device.create_command_encoder(&Default::default());
        if groups > 0 {
            let bg = self.bind(
                &self.pipelines.project,
                &[
                    (0, &params_buf),
                    (1, &self.means_opac),
                    (2, &self.scales),
                    (3, &self.quats),
                    (4, &self.splats),
                    (5, &self.isect),
                ],
            );
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipelines.project);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(groups.min(GROUPS_X), groups.div_ceil(GROUPS_X), 1);
        }
        let isect_bytes = self.n as u64 * 8;
        let read = self.submit_and_read(enc, &[(&self.isect, 0, isect_bytes)])?;
        let isect: Vec<[u32; 2]> = bytemuck::pod_collect_to_vec(&read[0]);

        timings.project_ms = lap(&mut clock);
        let visible = isect
            .iter()
            .filter(|r| (r[0] & 0xffff) < (r[1] & 0xffff) && (r[0] >> 16) < (r[1] >> 16))
            .count() as u64;
        // Label sums pay off when many contributions fall on each (Gaussian, label): with more
        // visible Gaussians than pixels (a 30M-Gaussian terrain at 495x371 px: ~2 per sum,
        // H200: 3.9 s/view vs 1.8 for the lists) the caller takes the lists instead.
        if labels.is_some() && !fixed_slots && visible > u64::from(n_pix) {
            self.out = kept;
            return Ok(RunOutput::UseLists);
        }
        // 2. CPU binning + sort (per Gaussian work only).
        let (ranges, sorted_ids) = bin_and_sort(&isect, &self.means, w2c, tiles_x, n_tiles)?;
        self.check_size("tile intersections", sorted_ids.len() as u64 * 4, k)?;
        timings.bin_sort_ms = lap(&mut clock);
        let ranges_buf = storage_init(&self.device, "tile_ranges", bytemuck::cast_slice(&ranges));
        let ids_buf = storage_init(
            &self.device,
            "sorted_ids",
            bytemuck::cast_slice(&sorted_ids),
        );
        let offsets = storage(&self.device, "offsets", (n_pix as u64 + 1) * 4);
        let block_sums = storage(&self.device, "block_sums", (n_blocks as u64 + 1) * 4);
        let dummy = storage(&self.device, "dummy", 16);
        // Read-only bindings cannot share a buffer with read-write ones in one dispatch.
        let dummy_labels = storage(&self.device, "dummy_labels", 16);
        self.noise(&offsets, seed_salt + 2);
        self.noise(&block_sums, seed_salt + 3);

        // 3a. Count pass + exclusive scan.
        let blend_bg_with = |out_ids: &wgpu::Buffer,
                             out_w: &wgpu::Buffer,
                             labels: &wgpu::Buffer,
                             sums: &wgpu::Buffer| {
            self.bind(
                &self.pipelines.blend,
                &[
                    (0, &params_buf),
                    (4, &self.splats),
                    (6, &ranges_buf),
                    (7, &ids_buf),
                    (8, &offsets),
                    (9, out_ids),
                    (10, out_w),
                    (12, labels),
                    (13, sums),
                ],
            )
        };
        let blend_bg = |out_ids: &wgpu::Buffer, out_w: &wgpu::Buffer| {
            blend_bg_with(out_ids, out_w, &dummy_labels, &dummy)
        };

        // 3'. Label sums (mode 2) instead of per-pixel lists: only the table is read back.
        if let Some(labels) = labels {
            if labels.len() != n_pix as usize {
                return Err(Error::Invalid(format!(
                    "{} pixel labels for a {}x{} raster; pass one label per raster pixel",
                    labels.len(),
                    k.width,
                    k.height
                )));
            }
            let labels_buf = storage_init(&self.device, "labels", bytemuck::cast_slice(labels));
            // A table at most half full for one label per visible Gaussian, at least the size
            // the last view needed: a first view of a large scene then rarely retries.
            // Most slots one binding holds (a power of two).
            let cap = ((self.max_binding().saturating_sub(16) / 16)
                .min(u64::from(MAX_LABEL_SLOTS)))
            .max(4);
            let cap = 1u64 << (63 - cap.leading_zeros());
            let mut slots = if fixed_slots {
                u64::from(self.label_slots.max(4)).min(cap)
            } else {
                (visible * 2)
                    .next_power_of_two()
                    .clamp(u64::from(self.label_slots.max(4)), cap)
            } as u32;
            let mut retries = 0;
            loop {
                let table_bytes = 16 + u64::from(slots) * 16;
                self.check_size("label-sum table", table_bytes, k)?;
                let table = storage(&self.device, "label_sums", table_bytes);
                params.mode = 2;
                params.table_mask = slots - 1;
                self.queue
                    .write_buffer(&params_buf, 0, bytemuck::bytes_of(&params));
                let mut enc = self.device.create_command_encoder(&Default::default());
                enc.clear_buffer(&table, 0, None);
                {
                    let bg = blend_bg_with(&dummy, &dummy, &labels_buf, &table);
                    let mut pass = enc.begin_compute_pass(&Default::default());
                    pass.set_pipeline(&self.pipelines.blend);
                    pass.set_bind_group(0, &bg, &[]);
                    pass.dispatch_workgroups(tiles_x, tiles_y, 1);
                }
                let read = self.submit_and_read(enc, &[(&table, 0, table_bytes)])?;
                let words: Vec<u32> = bytemuck::pod_collect_to_vec(&read[0]);
                if words.first().copied().unwrap_or(1) != 0 {
                    // Some contribution found no slot: retry the view with 4x the slots, or,
                    // past what one binding holds, let the caller take the per-pixel lists.
                    retries += 1;
                    if u64::from(slots) >= cap {
                        self.label_retries = retries;
                        self.out = kept;
                        return Ok(RunOutput::UseLists);
                    }
                    slots = (u64::from(slots) * 4).min(cap) as u32;
                    continue;
                }
                let sums = LabelSums {
                    sums: decode_label_sums(&words[4..]),
                    contributions: (u64::from(words[2]) << 32) | u64::from(words[1]),
                };
                // Next view: keep the table at most half full.
                let want = (sums.sums.len() as u64 * 2).next_power_of_two();
                let next = u64::from(slots).max(want).min(cap) as u32;
                timings.write_ms = lap(&mut clock);
                self.timings = timings;
                self.label_slots = next;
                self.label_retries = retries;
                self.out = kept;
                return Ok(RunOutput::Sums(sums));
            }
        }
        let scan_entries = [(0, &params_buf), (8, &offsets), (11, &block_sums)];
        let mut enc = self.device.create_command_encoder(&Default::default());
        {
            let bg = blend_bg(&dummy, &dummy);
            let bg_l = self.bind(&self.pipelines.scan_local, &scan_entries);
            let bg_b = self.bind(&self.pipelines.scan_blocks, &scan_entries);
            let bg_a = self.bind(&self.pipelines.scan_add, &scan_entries);
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipelines.blend);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(tiles_x, tiles_y, 1);
            let (gx, gy) = (n_blocks.min(GROUPS_X), n_blocks.div_ceil(GROUPS_X));
            pass.set_pipeline(&self.pipelines.scan_local);
            pass.set_bind_group(0, &bg_l, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
            pass.set_pipeline(&self.pipelines.scan_blocks);
            pass.set_bind_group(0, &bg_b, &[]);
            pass.dispatch_workgroups(1, 1, 1);
            pass.set_pipeline(&self.pipelines.scan_add);
            pass.set_bind_group(0, &bg_a, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        let read = self.submit_and_read(
            enc,
            &[
                (&offsets, 0, (n_pix as u64 + 1) * 4),
                (&block_sums, n_blocks as u64 * 4, 4),
            ],
        )?;
        let offsets_host: Vec<u32> = bytemuck::pod_collect_to_vec(&read[0]);
        let overflow = u32::from_le_bytes([read[1][0], read[1][1], read[1][2], read[1][3]]);
        if overflow != 0 {
            return Err(Error::limit(
                Resource::RasterEntries,
                format!(
                    "more than 2^32 for the {}x{} weight raster",
                    k.width, k.height
                ),
                "2^32",
            ));
        }
        let total = offsets_host[n_pix as usize] as usize;
        timings.count_scan_ms = lap(&mut clock);

        // 3b. Write pass, in bands of whole tile rows (a contiguous range of CSR entries) so no
        // output binding exceeds the device limit.
        let band_bytes = self
            .band_limit
            .unwrap_or(u64::MAX)
            .min(self.max_binding())
            .max(4);
        let row_start = |tile_row: u32| {
            let py = (tile_row * super::project::TILE_SIZE).min(k.height);
            offsets_host[(py * k.width) as usize] as u64
        };
        let mut ids = Vec::with_capacity(total);
        let mut weights = Vec::with_capacity(total);
        let mut r0 = 0u32;
        while r0 < tiles_y {
            let base = row_start(r0);
            let mut r1 = r0 + 1;
            if (row_start(r1) - base) * 4 > band_bytes {
                return Err(Error::limit(
                    Resource::GpuBinding,
                    format!(
                        "{:.2} MiB of output for one row of tiles of the {}x{} weight raster",
                        ((row_start(r1) - base) * 4) as f64 / 1048576.0,
                        k.width,
                        k.height
                    ),
                    format!("{:.2} MiB per binding", band_bytes as f64 / 1048576.0),
                ));
            }
            while r1 < tiles_y && (row_start(r1 + 1) - base) * 4 <= band_bytes {
                r1 += 1;
            }
            let entries = row_start(r1) - base;
            let bytes = entries * 4;
            if bytes == 0 {
                r0 = r1; // no pixel of these tile rows has a contributor: nothing to write
                continue;
            }
            let out = self.out_buffers(kept.take(), bytes, band_bytes);
            self.noise(&out.ids, seed_salt + 4 + r0 as u64);
            self.noise(&out.weights, seed_salt + 5 + r0 as u64);
            params.mode = 1;
            params.tile_y0 = r0;
            params.out_base = base as u32;
            self.queue
                .write_buffer(&params_buf, 0, bytemuck::bytes_of(&params));
            let mut enc = self.device.create_command_encoder(&Default::default());
            {
                let bg = blend_bg(&out.ids, &out.weights);
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&self.pipelines.blend);
                pass.set_bind_group(0, &bg, &[]);
                pass.dispatch_workgroups(tiles_x, r1 - r0, 1);
            }
            enc.copy_buffer_to_buffer(&out.ids, 0, &out.stage_ids, 0, bytes);
            enc.copy_buffer_to_buffer(&out.weights, 0, &out.stage_weights, 0, bytes);
            self.read_entries(enc, &out, bytes, &mut ids, &mut weights)?;
            kept = Some(out);
            r0 = r1;
        }
        self.out = kept;
        timings.write_ms = lap(&mut clock);
        self.timings = timings;
        tracing::debug!(?timings, entries = total, "gpu weight raster");
        Ok(RunOutput::Weights(PixelWeights {
            width: k.width,
            height: k.height,
            offsets: offsets_host,
            ids,
            weights,
        }))
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

/// Tile binning on the CPU: for every Gaussian with a non-empty tile rect (from the GPU
/// projection), one 128-bit key `tile | depth | id` per touched tile, sorted. The depth is the f64
/// camera-frame z of [`camera_point`] (bit-identical to the CPU reference's; positive f64 bit
/// patterns sort like their values), so both rasterizers order every tile identically, exact
/// ties included (by id). Returns per-tile `[start, end)` ranges into the sorted Gaussian ids.
fn bin_and_sort(
    isect: &[[u32; 2]],
    means: &[[f32; 3]],
    w2c: &WorldToCamera,
    tiles_x: u32,
    n_tiles: u32,
) -> Result<(Vec<[u32; 2]>, Vec<u32>)> {
    let rect = |r: &[u32; 2]| {
        let (x0, y0, x1, y1) = (r[0] & 0xffff, r[0] >> 16, r[1] & 0xffff, r[1] >> 16);
        (x0, y0, x1.max(x0), y1.max(y0))
    };
    let counts: Vec<u64> = isect
        .par_iter()
        .map(|r| {
            let (x0, y0, x1, y1) = rect(r);
            (x1 - x0) as u64 * (y1 - y0) as u64
        })
        .collect();
    let total: u64 = counts.iter().sum();
    if total > u32::MAX as u64 {
        return Err(Error::limit(
            Resource::RasterEntries,
            format!("{total} tile intersections"),
            "2^32",
        ));
    }
    let mut keys = vec![0u128; total as usize];
    // Fill disjoint chunks in parallel: split `keys` at each Gaussian's start.
    let mut rest: &mut [u128] = &mut keys;
    let mut chunks = Vec::with_capacity(isect.len());
    for c in &counts {
        let (a, b) = rest.split_at_mut(*c as usize);
        chunks.push(a);
        rest = b;
    }
    chunks.into_par_iter().enumerate().for_each(|(id, chunk)| {
        if chunk.is_empty() {
            return;
        }
        let (x0, y0, x1, y1) = rect(&isect[id]);
        let depth = camera_point(means[id].map(f64::from), w2c).z.max(0.0);
        let low = ((depth.to_bits() as u128) << 32) | id as u128;
        let mut e = 0;
        for y in y0..y1 {
            for x in x0..x1 {
                chunk[e] = (((y * tiles_x + x) as u128) << 96) | low;
                e += 1;
            }
        }
    });
    keys.par_sort_unstable();
    let mut ranges = vec![[0u32; 2]; n_tiles as usize];
    let mut i = 0usize;
    while i < keys.len() {
        let tile = (keys[i] >> 96) as usize;
        let mut j = i;
        while j < keys.len() && (keys[j] >> 96) as usize == tile {
            j += 1;
        }
        if tile >= ranges.len() {
            return Err(Error::internal(format!(
                "projection produced tile {tile} outside the grid"
            )));
        }
        ranges[tile] = [i as u32, j as u32];
        i = j;
    }
    let ids = keys.into_iter().map(|k| k as u32).collect();
    Ok((ranges, ids))
}

impl GpuRasterizer {
    /// [`Self::run`] inside validation and out-of-memory error scopes.
    fn run_scoped(
        &mut self,
        k: &Intrinsics,
        w2c: &WorldToCamera,
        labels: Option<&[u32]>,
    ) -> Result<RunOutput> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let out = self.run(k, w2c, labels);
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
        match self.run_scoped(k, w2c, None)? {
            RunOutput::Weights(w) => Ok(w),
            RunOutput::Sums(_) | RunOutput::UseLists => Err(Error::Gpu(
                "rasterizer returned sums for a weights run".into(),
            )),
        }
    }

    fn label_sums(
        &mut self,
        k: &Intrinsics,
        w2c: &WorldToCamera,
        labels: &[u32],
    ) -> Result<Option<LabelSums>> {
        match self.run_scoped(k, w2c, Some(labels))? {
            RunOutput::Sums(s) => Ok(Some(s)),
            // More sums than one table binding holds: the caller rasterizes the lists instead.
            RunOutput::UseLists => Ok(None),
            RunOutput::Weights(_) => Err(Error::Gpu(
                "rasterizer returned weights for a sums run".into(),
            )),
        }
    }

    fn name(&self) -> &str {
        &self.name
    }
}
