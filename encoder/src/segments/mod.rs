//! Geometric segments of the Gaussians (the paper's prediction-filtering segments): a
//! Felzenszwalb–Huttenlocher graph segmentation (Felzenszwalb & Huttenlocher, "Efficient
//! Graph-Based Image Segmentation", IJCV 2004) run, as ScanNet's Segmentator runs it over a mesh,
//! over a k-nearest-neighbour graph of the Gaussian means (`rstar`).
//!
//! # Graph and weights (geometry only, never colour)
//!
//! Each Gaussian `i` has a centre `μ_i`, standard deviations `σ_i` (sorted `σ_min ≤ σ_mid ≤
//! σ_max`, scene units) and a rotation `q_i` (w, x, y, z). Its normal `n_i` is its shortest axis,
//! `R(q_i) e_argmin σ`, sign-free; its flatness `f_i = 1 − σ_min/σ_mid ∈ [0, 1]` says how well
//! that normal is defined (a disk: 1, a sphere: 0). Every Gaussian is joined to its
//! [`SegmentParams::neighbours`] nearest means (ties broken by Gaussian id), edges longer than
//! [`SegmentParams::max_edge`] dropped. The weight of edge `(i, j)`, `d = |μ_i − μ_j|`,
//! `r = σ_max`:
//!
//! `w = w_n (1 − |n_i·n_j|) min(f_i, f_j) + w_d max(0, d − 2(r_i + r_j)) / (r_i + r_j)
//!    + w_s |ln(r_i / r_j)|`
//!
//! (normal term: Segmentator's `1 − n_i·n_j` made sign-free, as a splat's axis has no side;
//! distance term: zero while the two splats overlap at 2σ, then the gap in units of their size;
//! shape term: the ratio of their sizes).
//!
//! # Segmentation
//!
//! Edges in ascending `(w, i, j)` order; components `C1 ∋ i`, `C2 ∋ j` merge when
//! `w ≤ min(Int(C1) + τ/|C1|, Int(C2) + τ/|C2|)` (`Int`: the largest weight of the component's
//! spanning tree, `τ` = [`SegmentParams::threshold`]); then, as Segmentator does, the edges once
//! more in the same order, merging wherever either side has fewer than
//! [`SegmentParams::min_size`] Gaussians. Ids are numbered by each segment's smallest Gaussian
//! id ([`slag_common::segments::canonical_ids`]): the result is deterministic, whatever the
//! thread count.
//!
//! # Region mask profiles (optional veto)
//!
//! With a masks' record and [`SegmentParams::region_veto`] below 1, each component also carries
//! a *mask profile*: its Gaussians' recorded `(view, dominant mask, a_kj)` entries summed per
//! `(view, mask)` (at most 64 entries, the heaviest kept; ties to the smaller key). The region
//! disagreement of two profiles is, over the views both hold, `1 − Σ_v W_v · Σ_m min(p_a(m|v),
//! p_b(m|v)) / Σ_v W_v` with `p(m|v)` a profile's share of its view-`v` weight in mask `m` and
//! `W_v = min(W_a(v), W_b(v))` (no shared view: no veto). Neither pass joins two components
//! whose disagreement exceeds the veto. Memory: 8 bytes per profile entry, at most the record's
//! (64 bytes per Gaussian with 8 slots) plus a vector header per Gaussian. Off by default: on
//! snowmiku it made more, smaller segments but no purer ones than a smaller minimum size does at
//! the same count (docs/results/prediction-filtering.md).
//!
//! # Neighbours: a grid
//!
//! The k-NN search bins the means into cubic cells and scans the cells around each mean, shell
//! after shell, until no cell left can hold a nearer mean: exact, the same
//! neighbours as any exact search (same `d²`, ties by id), in time about linear in the
//! Gaussians. The cells are ordered along a Morton curve, and the means in that order are the
//! *space order* the later stages work in: the lists, the edges' geometric parts and, tile by
//! tile, the masks' record are laid out by it, so that an edge's two ends are read from near
//! places in memory (a trained `.ply`'s id order is unrelated to space, and reading the far
//! end's data by id was most of the edges' time). The edges, their order and the ids are
//! those of the id order. Memory: 44 bytes per Gaussian for the result (the lists and the
//! order), 28 more while the search runs.
//!
//! # Bounded memory and parallel passes: tiles
//!
//! The edges are never held whole. The Gaussians are cut into tiles of at most
//! [`SegmentParams::tile_gaussians`] by median splits on the two world axes of largest extent.
//! The edges that cross a tile border (a few per border Gaussian, about 0.1–0.2 % of a large
//! scene's edges) are weighed first, for the whole scene. Per tile, the edges inside it run the
//! merge criterion, and where each border edge with an end in the tile falls in the edge order,
//! the pass notes that end's component (size and `Int`) as it stands then.
//! Afterwards the border edges join, in order, where their weight is within both sides'
//! thresholds: each is judged by the components it would meet at its own place in the order of
//! one untiled pass, as far as its two tiles tell, not by the components grown after every
//! inner edge; and once border edges have joined a side to others, that side is the group they
//! make (sizes summed, the largest `Int`), so that a line of segments along a border is held to
//! its growing size as one pass holds it. Segments along the borders still differ from one
//! tile's (the purity of tiled segments against one tile's: docs/results/scaling.md). The
//! minimum-size pass then goes over each tile's edges again and the border edges last. As a
//! tile's inner edges join only its own Gaussians, the tiles' criterion passes run in parallel,
//! each on a forest of its own (`passes.rs`), while the next tiles' edges are weighed and sorted
//! on the other threads; a tile reads its rows of the record packed one Gaussian per cache line.
//! The minimum-size pass needs only the inner edges still between two components after their
//! tile's pass, with an end in a component below the minimum size then, that the mask veto lets
//! through (components only grow, so it would skip the others), and of those only the first
//! between each pair of the tile's components (it would pass the later ones by without a join).
//! Each tile picks those in parallel right after its own criterion pass, beside the other
//! tiles' passes (the veto, read from the scene's record, last); the pass itself runs over them
//! in order on one thread. The
//! geometric part of each neighbour's edge weight needs no masks: it is computed before the
//! record arrives, so that afterwards an edge's weight only adds the mask term. Memory: 40 bytes
//! per Gaussian for the whole scene (tile, its place in the tile, both by id and by rank;
//! union-find; normals, flatness and size, 20 more, twice while they are put in space order,
//! until the geometric parts are computed)
//! plus the neighbours and the geometric parts (4 bytes each per slot), the edges of the tiles in
//! flight and their gathered rows of the record (at most 2 GiB, sized from the edges per Gaussian
//! of the tiles built so far: about 100 + 64 bytes per Gaussian of a tile) and the border edges and
//! those kept for the minimum-size pass. The Gaussians themselves are read only until the
//! geometric parts are computed ([`segment_with`] lets go of a shared scene there).
//!
//! With one tile this is exactly the algorithm above. With several, it is the criterion pass of
//! each tile over its inner edges, then the border edges judged by their noted thresholds, then
//! the minimum-size pass over the edge order "every tile's inner edges (ascending), then the
//! border edges (ascending)"; a segment that no tile border cuts comes out the same as with one
//! tile. `tests::tiles_equal_the_tile_grouped_order` checks this statement by brute force. Neither
//! the tiles in parallel nor the thread count change a single id
//! (`tests::ids_do_not_depend_on_threads`).

mod forest;
mod graph;
mod grid;
mod neighbours;
mod passes;
#[cfg(test)]
mod reference;
mod regions;
#[cfg(test)]
mod tests;
mod tiles;
mod weights;

use std::borrow::Cow;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use serde::{Deserialize, Serialize};
use slag_common::mask_record::MaskRecord;
use slag_common::scene::Gaussians;
use slag_common::segments::Segments;
#[cfg(test)]
use slag_common::segments::canonical_ids;
use slag_common::{Error, Result};

use crate::check::require;
use crate::memory::log_rss;
use graph::{neighbour_graph, resolve_max_edge, slot_geometry};
use passes::merge;
use tiles::plan_tiles;
use weights::{Weigher, geometry};

/// Settings of the segmentation; [`SegmentParams::default`] are the documented defaults.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SegmentParams {
    /// Nearest neighbours per Gaussian in the graph, k (default 10).
    pub neighbours: usize,
    /// Felzenszwalb–Huttenlocher scale τ: a component of size |C| accepts an edge up to
    /// `Int(C) + τ/|C|`; larger → larger, fewer segments (default 0.5).
    pub threshold: f32,
    /// Segments below this many Gaussians are merged into a neighbour (default 20, as
    /// Segmentator's `segMinVerts`).
    pub min_size: usize,
    /// Longest edge, scene units. `None` (default): 10 × the median
    /// of the Gaussians' largest standard deviation.
    pub max_edge: Option<f32>,
    /// Weight of the normal term `w_n` (default 1).
    pub normal_weight: f32,
    /// Weight of the distance (gap) term `w_d` (default 1).
    pub distance_weight: f32,
    /// Weight of the shape (size-ratio) term `w_s` (default 0.1).
    pub shape_weight: f32,
    /// Most Gaussians per tile (default 2,000,000); bounds the memory of the edges, and sets
    /// how many union-find passes run in parallel (one per tile). A scene with more Gaussians
    /// gets segments that differ from one tile's where they cross tile borders: smaller tiles
    /// are faster and differ more (docs/results/scaling.md).
    pub tile_gaussians: usize,
    /// Weight of the mask term `w_m`: an edge whose ends fall in different masks in every view
    /// that records both gets `w_m` added (default 1; 0: geometry only). Used only with a
    /// masks' record.
    pub mask_weight: f32,
    /// The mask disagreement assumed for an edge whose ends share no recorded view (default
    /// 0.5: no evidence either way).
    pub mask_unknown: f32,
    /// The minimum-size pass does not join across an edge whose mask disagreement exceeds this
    /// (default 0.5: a border seen in more than half the shared evidence); 1: it joins
    /// anything, as without masks.
    pub mask_veto: f32,
    /// Two segments never join, in either pass, when their *regions'* mask disagreement exceeds
    /// this (module doc, "Region mask profiles"); default 1: no region veto (on snowmiku it
    /// gave no purer segments than smaller segments do). Used only with a masks' record.
    pub region_veto: f32,
}

impl Default for SegmentParams {
    fn default() -> Self {
        SegmentParams {
            neighbours: 10,
            threshold: 0.5,
            min_size: 20,
            max_edge: None,
            normal_weight: 1.0,
            distance_weight: 1.0,
            shape_weight: 0.1,
            tile_gaussians: 2_000_000,
            mask_weight: 1.0,
            mask_unknown: 0.5,
            mask_veto: 0.5,
            region_veto: 1.0,
        }
    }
}

impl SegmentParams {
    /// Checks every setting.
    ///
    /// Errors: [`Error::Param`] naming the setting (`neighbours`, `threshold`, `max_edge`,
    /// `tile_gaussians`, a weight) when outside its domain.
    pub fn validate(&self) -> Result<()> {
        let (k, tau) = (self.neighbours, self.threshold);
        require(
            (1..=256).contains(&k),
            "neighbours",
            k,
            "1 to 256 nearest neighbours per Gaussian (e.g. 10)",
        )?;
        require(
            tau.is_finite() && tau >= 0.0,
            "threshold",
            tau,
            "a finite scale τ ≥ 0 (e.g. 0.5)",
        )?;
        if let Some(m) = self.max_edge {
            let ok = m.is_finite() && m > 0.0;
            require(ok, "max_edge", m, "a positive length in scene units")?;
        }
        for (name, w) in [
            ("normal_weight", self.normal_weight),
            ("distance_weight", self.distance_weight),
            ("shape_weight", self.shape_weight),
            ("mask_weight", self.mask_weight),
        ] {
            require(w.is_finite() && w >= 0.0, name, w, "a finite weight ≥ 0")?;
        }
        for (name, v) in [
            ("mask_unknown", self.mask_unknown),
            ("mask_veto", self.mask_veto),
            ("region_veto", self.region_veto),
        ] {
            require((0.0..=1.0).contains(&v), name, v, "a share in [0, 1]")?;
        }
        require(
            self.tile_gaussians > k,
            "tile_gaussians",
            self.tile_gaussians,
            format!("more than neighbours ({k}) Gaussians per tile"),
        )
    }
}

/// What one segmentation did (for logs and reports).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SegmentStats {
    /// Gaussians segmented.
    pub gaussians: usize,
    /// Segments made.
    pub segments: u32,
    /// Tiles the scene was cut into.
    pub tiles: usize,
    /// Edges of the graph (each undirected edge once).
    pub edges: u64,
    /// Of those, edges across tile borders.
    pub border_edges: u64,
    /// The longest edge used (scene units): the given or derived `max_edge`.
    pub max_edge: f32,
    /// Slots per Gaussian of the masks' record the edges were weighed with; `None`: geometry
    /// only.
    pub mask_record: Option<usize>,
    /// Wall time, seconds.
    pub seconds: f64,
    /// Where the wall time went, stage by stage.
    pub stages: SegmentTimings,
}

/// Wall seconds of each stage of one segmentation (module doc), for the reports: where the
/// time of a segmentation that outlasts the encode goes.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct SegmentTimings {
    /// Each Gaussian's normal, flatness and size.
    pub geometry: f64,
    /// The tiles' plan (median splits), made beside the neighbour search (its own seconds,
    /// within `neighbours`).
    pub tiles: f64,
    /// The k-nearest-neighbour search of the means, and the tiles' plan beside it (wall time).
    pub neighbours: f64,
    /// The geometric part of every edge's weight (before the masks' record).
    pub edge_geometry: f64,
    /// Waiting for the masks' record (the encode's last view).
    pub record_wait: f64,
    /// The edges and their weights (their geometric part read from the `edge_geometry` stage's,
    /// the mask term added), summed over the tiles.
    pub weights: f64,
    /// Sorting the edges, summed over the tiles, and the border edges.
    pub sort: f64,
    /// The merge-criterion pass (union-find), summed over the tiles, and the border edges'.
    pub criterion: f64,
    /// The tiles' edges and criterion passes, which run in parallel (wall time).
    pub tile_passes: f64,
    /// The minimum-size pass: picking its edges (in parallel, each tile's right after its
    /// criterion pass; summed over the tiles) and the union-find pass over them.
    pub min_size: f64,
    /// Each Gaussian's root and the canonical ids.
    pub ids: f64,
}

/// Seconds since `t`, and `t` reset to now.
fn lap(t: &mut Instant) -> f64 {
    let s = t.elapsed().as_secs_f64();
    *t = Instant::now();
    s
}

/// Where [`segment_with`] runs its parallel stages, how much memory its tiles in flight may
/// hold, and whether it should give up. Another thread may change all three while it runs: the
/// encode that runs a segmentation beside itself starts it on a small pool, widens it when the
/// encode is done, lets its tiles hold more once the encode's own memory is freed, and stops it
/// when the encode failed.
#[derive(Debug)]
pub struct SegmentControl {
    stop: AtomicBool,
    pool: Mutex<Option<Arc<rayon::ThreadPool>>>,
    in_flight_bytes: std::sync::atomic::AtomicUsize,
}

impl Default for SegmentControl {
    fn default() -> Self {
        Self::new(None)
    }
}

/// Bytes that the tiles in flight at once may hold ([`SegmentControl::set_in_flight_bytes`]):
/// their edges (12 bytes each) and, while they are built, their rows of the masks' record. The
/// default, 2 GiB, is what a segmentation may add beside an encode's tail at 30M Gaussians
/// within a 10 GiB peak (docs/results/scaling.md).
pub const TILES_IN_FLIGHT_BYTES: usize = 2 << 30;

/// What the tiles in flight may hold once the encode beside them has ended and let go of its
/// own memory (its reduction, its mixture, its write buffers, several GiB at 30M Gaussians):
/// twice [`TILES_IN_FLIGHT_BYTES`], so that more tiles run at once in the wait after the encode.
pub const TILES_IN_FLIGHT_BYTES_ALONE: usize = 4 << 30;

impl SegmentControl {
    /// Stages on `pool`; `None`: on the pool of the calling thread (rayon's global pool, or the
    /// one whose `install` runs the caller).
    pub fn new(pool: Option<rayon::ThreadPool>) -> Self {
        SegmentControl {
            stop: AtomicBool::new(false),
            pool: Mutex::new(pool.map(Arc::new)),
            in_flight_bytes: TILES_IN_FLIGHT_BYTES.into(),
        }
    }

    /// The tiles' waves that start from now on may hold `bytes` at once (their edges and their
    /// rows of the masks' record; at least one tile runs whatever it says). The waves change no
    /// result, only how many tiles run at once.
    pub fn set_in_flight_bytes(&self, bytes: usize) {
        self.in_flight_bytes.store(bytes, Ordering::Relaxed);
    }

    fn in_flight_bytes(&self) -> usize {
        self.in_flight_bytes.load(Ordering::Relaxed)
    }

    /// The stages that start from now on run on `pool` (those under way finish where they are,
    /// but for the neighbour search, which moves over between its rounds).
    pub fn set_pool(&self, pool: rayon::ThreadPool) {
        *self.pool.lock().unwrap_or_else(|e| e.into_inner()) = Some(Arc::new(pool));
    }

    /// Asks the segmentation to give up: [`segment_with`] returns `Ok(None)` soon after.
    pub fn stop(&self) {
        self.stop.store(true, Ordering::Relaxed);
    }

    fn stopped(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }

    /// Whether [`SegmentControl::stop`] was called.
    pub fn is_stopped(&self) -> bool {
        self.stopped()
    }

    /// Runs `op` on the current pool choice.
    pub fn run<R: Send>(&self, op: impl FnOnce() -> R + Send) -> R {
        let pool = self.pool.lock().unwrap_or_else(|e| e.into_inner()).clone();
        match pool {
            Some(p) => p.install(op),
            None => op(),
        }
    }
}

/// Segments the Gaussians of `g` (module doc) and records `source_ply` in the result; with
/// `masks` (the encode's masks' record of the same `.ply`), the edges carry the mask term.
///
/// Runs on the current rayon pool (the global one, or the pool whose `install` calls it); the
/// result does not depend on its thread count.
///
/// Errors: [`Error::Param`] for settings [`SegmentParams::validate`] refuses, a scene of more
/// than `u32::MAX - 1` Gaussians ([`Error::Limit`]), arrays that disagree ([`Error::Internal`]),
/// non-finite means ([`Error::Invalid`]), a record of another scene ([`Error::Mismatch`]).
pub fn segment(
    g: &Gaussians,
    p: &SegmentParams,
    source_ply: &str,
    masks: Option<Arc<MaskRecord>>,
) -> Result<(Segments, SegmentStats)> {
    let ctl = SegmentControl::default();
    segment_with(g, p, source_ply, &ctl, || masks)?
        .ok_or_else(|| Error::internal("the segmentation stopped without being asked to"))
}

/// [`segment`] with its parallel stages on `ctl`'s pool of the moment (the border edges' and
/// the minimum-size union-find passes run on the calling thread), given up once
/// [`SegmentControl::stop`] was called: `Ok(None)` then. The stop is looked at between the
/// stages, for every cell of the k-nearest-neighbour search and between waves of tiles. The result
/// is [`segment`]'s, whatever the pools.
///
/// `masks` is called once the neighbour graph is built (the k-NN search, the costly part, runs
/// before): the encode hands over its record there when its last view is done. It may block;
/// `None`: geometry only.
///
/// `g` is let go of after the Gaussians' geometry ([`SceneHandle::into_means`]: a shared scene,
/// the encode's `Arc<Gaussians>`, is then freed once nothing else holds it), and its means,
/// where copied, before `masks` is called: the stages after the neighbour graph and its edge
/// geometry need only the Gaussians' count.
///
/// Errors: those of [`segment`].
pub fn segment_with(
    g: impl SceneHandle,
    p: &SegmentParams,
    source_ply: &str,
    ctl: &SegmentControl,
    masks: impl FnOnce() -> Option<Arc<MaskRecord>>,
) -> Result<Option<(Segments, SegmentStats)>> {
    p.validate()?;
    let t0 = Instant::now();
    check_scene(&g)?;
    let mut st = SegmentTimings::default();
    let n = g.len();
    let Some(pre) = before_record(g, p, ctl, &mut st) else {
        return Ok(None);
    };
    let mut t = Instant::now();
    let record = masks();
    st.record_wait = lap(&mut t);
    log_rss("segments: masks' record");
    if ctl.stopped() {
        return Ok(None);
    }
    check_record(record.as_deref(), n)?;
    let w = Weigher {
        p,
        masks: record.as_deref(),
    };
    let src = graph::EdgeSource {
        nb: &pre.nb,
        geometric: &pre.geometric,
        ranks: &pre.ranks,
        ids: &pre.ids,
    };
    let (forest, edges, border_edges) = merge(n, p, ctl, &w, &src, &mut st);
    log_rss("segments: passes");
    let Some(forest) = forest else {
        return Ok(None);
    };
    t = Instant::now();
    let (segments, segment_count) = ctl.run(|| canonical_root_ids(&forest.roots()));
    st.ids = lap(&mut t);
    log_rss("segments: ids");
    let stats = SegmentStats {
        gaussians: n,
        segments: segment_count,
        tiles: pre.tiles,
        edges,
        border_edges,
        max_edge: pre.max_edge,
        mask_record: record.as_ref().map(|r| r.slots),
        seconds: t0.elapsed().as_secs_f64(),
        stages: st,
    };
    let segments = Segments {
        segments,
        segment_count,
        source_ply: source_ply.to_string(),
        parameters: parameters_json(p, &stats),
    };
    Ok(Some((segments, stats)))
}

/// What [`segment_with`] builds before the masks' record: the edge length cap used (scene
/// units), the tile count, the k-nearest-neighbour graph in space order, the geometric part of
/// each neighbour slot's weight (`[N * k]`, rank order) and the tiles' members both as ranks
/// and as Gaussian ids (each with every Gaussian's tile and place in it).
struct BeforeRecord {
    max_edge: f32,
    tiles: usize,
    nb: neighbours::Ranked,
    geometric: Vec<f32>,
    ranks: graph::TileMembers,
    ids: graph::TileMembers,
}

/// The stages that need no masks' record, each timed into `st`: the Gaussians' geometry, the
/// tile plan, the neighbour graph, the edges' geometric parts (the per-Gaussian geometry,
/// put in space order for them, is freed after them) and the tiles' members. After the geometry
/// only the means are read: `g` gives them up there ([`SceneHandle::into_means`]). `None` once
/// [`SegmentControl::stop`] was called.
fn before_record(
    g: impl SceneHandle,
    p: &SegmentParams,
    ctl: &SegmentControl,
    st: &mut SegmentTimings,
) -> Option<BeforeRecord> {
    let mut t = Instant::now();
    let scene: &Gaussians = &g;
    let geo = ctl.run(|| geometry(scene));
    if ctl.stopped() {
        return None;
    }
    let max_edge = resolve_max_edge(p, &geo);
    st.geometry = lap(&mut t);
    let means = g.into_means();
    // The tiles' plan (median splits, mostly one thread at a time) is made beside the
    // neighbour search on a one-thread pool of its own: on the search's pool, a thread of the
    // search waiting for its own work could pick up a long split and hold the search up.
    let (planned, nb) = std::thread::scope(|s| {
        let side = s.spawn(|| {
            let clock = Instant::now();
            let plan = || plan_tiles(&means, p.tile_gaussians);
            let (_, tile_of, rects) = match rayon::ThreadPoolBuilder::new().num_threads(1).build() {
                Ok(own) => own.install(plan),
                Err(_) => ctl.run(plan),
            };
            (tile_of, rects.len(), clock.elapsed().as_secs_f64())
        });
        let nb = neighbour_graph(&means, p, max_edge, ctl);
        let planned = side.join().unwrap_or_else(|e| std::panic::resume_unwind(e));
        (planned, nb)
    });
    let (tile_of, tiles, tiles_s) = planned;
    st.tiles = tiles_s;
    let nb = nb?;
    st.neighbours = lap(&mut t);
    log_rss("segments: neighbour graph");
    // The scene-order geometry is freed before the slots' pass, so that only one copy of it
    // is held beside the pass's outputs.
    let ranked = ctl.run(|| geo.permuted(&nb.perm));
    drop(geo);
    let (geometric, (ranks, ids)) = ctl.run(|| {
        rayon::join(
            || slot_geometry(&nb.gather(&means), &nb, &ranked, p),
            || {
                rayon::join(
                    || graph::TileMembers::new(&nb.gather(&tile_of), tiles),
                    || graph::TileMembers::new(&tile_of, tiles),
                )
            },
        )
    });
    drop(ranked);
    st.edge_geometry = lap(&mut t);
    log_rss("segments: edge geometry");
    (!ctl.stopped()).then_some(BeforeRecord {
        max_edge,
        tiles,
        nb,
        geometric,
        ranks,
        ids,
    })
}

/// How the segmentation holds the scene it reads: borrowed (`&Gaussians`, nothing to let go)
/// or shared with the encode (`Arc<Gaussians>`). Only the geometry stage reads more than the
/// means, so a shared scene is let go of after it.
pub trait SceneHandle: std::ops::Deref<Target = Gaussians> + Sized {
    /// The Gaussians' means (`[N]`, scene frame) for the stages after the geometry, the rest of
    /// the scene let go of where this handle can: a borrow lends the scene's own means; a
    /// shared scene gives its means up when this is its last holder (the rest freed now), else
    /// copies them (12 bytes a Gaussian) and lets go, so that the scene is freed as soon as the
    /// encode is done with it rather than when the segments' edge geometry is made.
    fn into_means<'a>(self) -> Cow<'a, [[f32; 3]]>
    where
        Self: 'a;
}

impl SceneHandle for &Gaussians {
    fn into_means<'a>(self) -> Cow<'a, [[f32; 3]]>
    where
        Self: 'a,
    {
        Cow::Borrowed(&self.means)
    }
}

impl SceneHandle for Arc<Gaussians> {
    fn into_means<'a>(self) -> Cow<'a, [[f32; 3]]>
    where
        Self: 'a,
    {
        match Arc::try_unwrap(self) {
            Ok(g) => Cow::Owned(g.means),
            Err(g) => Cow::Owned(g.means.clone()),
        }
    }
}

/// Refuses a masks' record of another scene than the `n` Gaussians segmented
/// ([`Error::Mismatch`], telling the user to pass the record of an encode of this `.ply`).
fn check_record(record: Option<&MaskRecord>, n: usize) -> Result<()> {
    match record {
        Some(r) if r.len() != n => Err(Error::mismatch(
            slag_common::Mismatched::Scene,
            format!(
                "the masks' record holds {} Gaussians but the scene has {n}: use the record \
                 of an encode of this .ply",
                r.len()
            ),
        )),
        _ => Ok(()),
    }
}

/// The settings stored with the segments (JSON): `p`, the edge length cap used, the tile count
/// and the masks' record's slots (`null` without a record).
fn parameters_json(p: &SegmentParams, stats: &SegmentStats) -> String {
    serde_json::to_string(&serde_json::json!({
        "params": p, "max_edge_used": stats.max_edge, "tiles": stats.tiles,
        "mask_record_slots": stats.mask_record,
    }))
    .unwrap_or_default()
}

/// [`canonical_ids`] of union-find roots (each below `roots.len()`), in parallel: the same
/// ids, numbered by each segment's smallest Gaussian id. A segment's smallest member is found
/// by an atomic minimum per root; its id is the count of smaller segments' smallest members
/// (numbered within chunks of the Gaussians, then offset by the chunks before).
fn canonical_root_ids(roots: &[u32]) -> (Vec<u32>, u32) {
    use rayon::prelude::*;
    use std::sync::atomic::AtomicU32;
    const CHUNK: usize = 1 << 16;
    let smallest: Vec<AtomicU32> = (0..roots.len()).map(|_| AtomicU32::new(u32::MAX)).collect();
    roots.par_iter().enumerate().for_each(|(x, &r)| {
        // Read first: most Gaussians are not their segment's smallest, and a write to a
        // segment's shared entry from every thread would contend for its cache line.
        let s = &smallest[r as usize];
        if (x as u32) < s.load(Ordering::Relaxed) {
            s.fetch_min(x as u32, Ordering::Relaxed);
        }
    });
    let smallest: Vec<u32> = smallest.into_iter().map(AtomicU32::into_inner).collect();
    // At each segment's smallest member, its number within its chunk; each chunk's count.
    let mut first_id = vec![u32::MAX; roots.len()];
    let counts: Vec<u32> = first_id
        .par_chunks_mut(CHUNK)
        .enumerate()
        .map(|(c, out)| {
            let mut count = 0;
            for (k, slot) in out.iter_mut().enumerate() {
                let x = c * CHUNK + k;
                if smallest[roots[x] as usize] == x as u32 {
                    *slot = count;
                    count += 1;
                }
            }
            count
        })
        .collect();
    let mut starts = Vec::with_capacity(counts.len());
    let mut next = 0u32;
    for c in counts {
        starts.push(next);
        next += c;
    }
    first_id
        .par_chunks_mut(CHUNK)
        .zip(starts)
        .for_each(|(out, start)| {
            for slot in out.iter_mut().filter(|s| **s != u32::MAX) {
                *slot += start;
            }
        });
    let ids = roots
        .par_iter()
        .map(|&r| first_id[smallest[r as usize] as usize])
        .collect();
    (ids, next)
}

/// The checks of [`segment`] on the scene's arrays.
fn check_scene(g: &Gaussians) -> Result<()> {
    let n = g.len();
    if n >= u32::MAX as usize {
        return Err(Error::limit(
            slag_common::Resource::ShardGaussians,
            n,
            u32::MAX - 1,
        ));
    }
    if g.scales.len() != n || g.rotations.len() != n {
        return Err(Error::internal(format!(
            "{n} means, {} scales, {} rotations",
            g.scales.len(),
            g.rotations.len()
        )));
    }
    if let Some(i) = g
        .means
        .iter()
        .position(|m| m.iter().any(|v| !v.is_finite()))
    {
        return Err(Error::Invalid(format!(
            "mean of Gaussian {i} is not finite"
        )));
    }
    Ok(())
}
