//! The one query engine behind every interface: [`QueryEngine::query`] takes validated queries
//! ([`QueryParams`]) through the admission gate ([`super::admission`]) and answers each against
//! the generation served now ([`Engine::answer`]: scan, objects, answer frame). The HTTP server
//! ([`crate::serve`]) and the ROS 2 node ([`crate::ros2`]) both call it; neither knows the
//! other.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::time::Instant;

use slag_common::{Error, Result};

use super::admission::{Admission, Busy};
use super::{Engine, LoadProgress, ServedEngine};
use crate::query::{CANONICAL_NEGATIVES, QueryAnswer, QueryParams, TextEmbedder};
use crate::scan::hnsw::HnswBackend;
use crate::store::EdgeStore;

/// Default of [`EngineOptions::max_scans`]: scans running at once.
pub const DEFAULT_MAX_SCANS: usize = 1;
/// Default of [`EngineOptions::scan_queue`]: queries that may wait for a scan.
pub const DEFAULT_SCAN_QUEUE: usize = 32;
/// Default of [`EngineOptions::max_matches`]: matches one request may ask for in all, twice the
/// largest `top_k` of one query ([`crate::query::MAX_TOP_K`]); about 2 MB of JSON.
pub const DEFAULT_MAX_MATCHES: usize = 20_000;

/// What a [`QueryEngine`] serves and how it admits queries.
#[derive(Debug, Clone, PartialEq)]
pub struct EngineOptions {
    /// Scene to serve (its name in the store).
    pub scene: String,
    /// Approximate index to build at every load (`None`: exact scans only; `index=hnsw` is then
    /// refused).
    pub index: Option<HnswBackend>,
    /// Cosine threshold of a query that gives none.
    pub threshold: f32,
    /// Scans running at once (≥ 1; [`super::admission`]).
    pub max_scans: usize,
    /// Queries that may wait for a scan; one more is turned away ([`Busy`]).
    pub scan_queue: usize,
    /// Matches one request may ask for in all (Σ `top_k` over a batch; [`check_matches`]).
    pub max_matches: usize,
    /// The publisher's keys: every load verifies a signed generation's signature and hashes its
    /// tiles ([`Engine::load_trusting`]); `None`: CRC-32s only.
    pub trusted_keys: Option<slag_common::shards::signature::TrustedKeys>,
}

/// The query engine: the served generation ([`ServedEngine`]), the text model and the embedded
/// canonical negatives, the admission gate and the count of queries answered. A cheap handle:
/// clones share one engine.
#[derive(Clone)]
pub struct QueryEngine(Arc<Shared>);

/// What the clones of one [`QueryEngine`] share.
struct Shared {
    served: ServedEngine,
    edge: EdgeStore,
    text: Arc<dyn TextEmbedder>,
    /// Embeddings of [`CANONICAL_NEGATIVES`], `[4][D]`.
    negatives: Vec<Vec<f32>>,
    opts: EngineOptions,
    admission: Admission,
    queries: AtomicU64,
    /// Where the background verification of the tiles served at start stands.
    verification: (Mutex<Verification>, Condvar),
}

/// Where a server's background verification of its stored tiles stands ([`QueryEngine::new`];
/// `/stats` `verification`).
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Verification {
    /// None runs: no trusted key, or an unsigned generation (loaded at once on its CRC-32s).
    Off,
    /// The tiles are being read, hashed and decoded; the server answers from the tiles
    /// verified so far meanwhile (none at first: [`Engine::pending`]; then
    /// [`Engine::verified_so_far`]), every answer [`QueryAnswer::partial`].
    Running,
    /// Done: every tile that passed is served, those that did not are in
    /// [`crate::store::SceneLoad::rejected`].
    Done,
    /// The load failed as a whole (the message): no tile of the generation is served; a
    /// `reload` tries again.
    Failed(String),
}

/// Holds a background verification ([`QueryEngine::new_gated`]) tile by tile: the tiles of the
/// generation are handed on (served, once they pass) only as far as the gate has released them
/// ([`Self::release`], [`Self::open`]), so a test queries a server whose tiles are all pending,
/// then one with exactly the first tiles handed, and so on, without timing anything. Clones
/// share one gate.
#[derive(Debug, Clone, Default)]
pub struct VerifyGate(Arc<(Mutex<GateState>, Condvar)>);

/// Where a [`VerifyGate`] stands: how many tiles it lets through, and how many went through
/// (their outcome published to the served engine).
#[derive(Debug, Default)]
struct GateState {
    released: usize,
    passed: usize,
    /// The verification ended (done or failed): no tile passes any more.
    ended: bool,
}

impl VerifyGate {
    /// A closed gate: no tile goes through.
    pub fn new() -> Self {
        Self::default()
    }

    /// Lets every tile through.
    pub fn open(&self) {
        self.update(|g| g.released = usize::MAX);
    }

    /// Lets `tiles` more tiles through (in manifest tile order).
    pub fn release(&self, tiles: usize) {
        self.update(|g| g.released = g.released.saturating_add(tiles));
    }

    /// Blocks until `tiles` tiles in all have gone through, what became of each published to the
    /// served engine (served, rejected or absent), or the verification ended; returns how many
    /// went through.
    pub fn wait_passed(&self, tiles: usize) -> usize {
        let g = self.wait_until(|g| g.passed >= tiles || g.ended);
        g.passed
    }

    /// Blocks until tile `k` (0-based) may go through.
    fn wait_turn(&self, k: usize) {
        drop(self.wait_until(|g| g.released > k));
    }

    /// Records that `tiles` tiles in all have gone through.
    fn passed(&self, tiles: usize) {
        self.update(|g| g.passed = tiles);
    }

    /// Records that the verification ended.
    fn end(&self) {
        self.update(|g| g.ended = true);
    }

    fn update(&self, f: impl FnOnce(&mut GateState)) {
        let (m, cv) = &*self.0;
        f(&mut m.lock().unwrap_or_else(PoisonError::into_inner));
        cv.notify_all();
    }

    fn wait_until(
        &self,
        done: impl Fn(&GateState) -> bool,
    ) -> std::sync::MutexGuard<'_, GateState> {
        let (m, cv) = &*self.0;
        let mut g = m.lock().unwrap_or_else(PoisonError::into_inner);
        while !done(&g) {
            g = cv.wait(g).unwrap_or_else(PoisonError::into_inner);
        }
        g
    }
}

/// How often a background verification publishes the rows verified so far
/// ([`QueryEngine::new`]): each publish copies them, so without a gate it waits until
/// [`COPY_SHARE`] times the last copy's duration has passed since the last publish, which keeps
/// the copying under a fifth of the verification's time however large the store; with a gate
/// (tests), after every tile.
struct Cadence {
    every_tile: bool,
    last: Instant,
    copy: std::time::Duration,
}

/// See [`Cadence`].
const COPY_SHARE: u32 = 4;

impl Cadence {
    fn due(&self) -> bool {
        self.every_tile || self.last.elapsed() >= self.copy * COPY_SHARE
    }

    fn copied(&mut self, started: Instant) {
        self.last = Instant::now();
        self.copy = self.last - started;
    }
}

impl QueryEngine {
    /// Loads `opts.scene` from `edge` (building the approximate index of `opts.index`) and
    /// embeds the canonical negatives once. With [`EngineOptions::trusted_keys`] and a signed
    /// generation, only its signature (and a mixture scene's codebook) is checked here: the
    /// server answers at once from an engine without rows ([`Engine::pending`]; answers are
    /// [`QueryAnswer::partial`]), while a thread reads, hashes and decodes the tiles, serves
    /// those that passed so far as it goes (a copy of their rows, at most every few tiles on a
    /// large store: [`Cadence`]), and then the whole generation ([`Self::verification`]). No row
    /// of a tile whose SHA-256 was not checked, or did not match, is ever in a served engine.
    ///
    /// Errors: as [`Engine::load_with`]; a text model of another CLIP model than the stored
    /// embeddings ([`Error::ModelMismatch`]) or whose width differs from theirs
    /// ([`Error::Mismatch`]); the text model failing on the negatives ([`Error::Model`]).
    pub fn new(
        edge: EdgeStore,
        text: Arc<dyn TextEmbedder>,
        opts: EngineOptions,
    ) -> Result<QueryEngine> {
        Self::new_gated(edge, text, opts, None)
    }

    /// [`Self::new`], whose background verification (if any) waits at `gate` before each tile
    /// ([`VerifyGate`]).
    ///
    /// Errors: as [`Self::new`].
    pub fn new_gated(
        edge: EdgeStore,
        text: Arc<dyn TextEmbedder>,
        opts: EngineOptions,
        gate: Option<VerifyGate>,
    ) -> Result<QueryEngine> {
        let trusted = opts.trusted_keys.as_ref();
        let (engine, background) = match Engine::pending(&edge, &opts.scene, trusted)? {
            Some(pending) => (pending, true),
            None => (
                Engine::load_trusting(&edge, &opts.scene, opts.index, trusted)?,
                false,
            ),
        };
        text.check_pair(&engine.manifest.model)?;
        let negatives = text.embed(&CANONICAL_NEGATIVES)?;
        if let Some(n) = negatives.first()
            && n.len() != engine.store.dim()
        {
            return Err(Error::mismatch(
                slag_common::Mismatched::EmbeddingWidth,
                format!(
                    "the text model {} gives {}-d embeddings but scene {} holds {}-d ones \
                     from {}; serve with the CLIP text tower of that model",
                    text.name(),
                    n.len(),
                    opts.scene,
                    engine.store.dim(),
                    engine.manifest.model
                ),
            ));
        }
        let state = match background {
            true => Verification::Running,
            false => Verification::Off,
        };
        let engine = QueryEngine(Arc::new(Shared {
            served: ServedEngine::new(engine),
            edge,
            text,
            negatives,
            admission: Admission::new(opts.max_scans, opts.scan_queue),
            opts,
            queries: AtomicU64::new(0),
            verification: (Mutex::new(state), Condvar::new()),
        }));
        if background {
            engine.spawn_verification(gate)?;
        }
        Ok(engine)
    }

    /// Starts the background verification of [`Self::new`] on a thread of its own: the
    /// committed generation loaded as [`Engine::load_trusting`] loads it (each tile's bytes
    /// read once, hashed against the signed manifest, decoded, a window of files at a time on
    /// the rayon pool; a tile that differs is rejected, never pushed), the rows of the tiles
    /// that passed so far published to the served engine as it goes ([`Self::publish_progress`]),
    /// and the whole generation (its approximate index built) offered at the end
    /// ([`ServedEngine::offer`]). Each tile waits at `gate` first, if any.
    ///
    /// Errors: [`Error::Internal`] when the thread cannot be started.
    fn spawn_verification(&self, gate: Option<VerifyGate>) -> Result<()> {
        let s = self.0.clone();
        tracing::info!(
            "scene {}: signature verified; hashing its {} stored tiles in the background, \
             answering partial (from the tiles verified so far) until then",
            s.opts.scene,
            s.served.current().load.pending_verification
        );
        let engine = self.clone();
        std::thread::Builder::new()
            .name("slag-verify".into())
            .spawn(move || {
                let t = Instant::now();
                let pending = s.served.current();
                let mut published = pending.clone();
                let mut publish = engine.publish_progress(&pending, &mut published, gate.clone());
                let loaded = Engine::load_observed(
                    &s.edge,
                    &s.opts.scene,
                    s.opts.index,
                    s.opts.trusted_keys.as_ref(),
                    &mut publish,
                )
                .and_then(|e| s.text.check_pair(&e.manifest.model).map(|()| e));
                drop(publish);
                let state = match loaded {
                    Ok(e) => {
                        tracing::info!(
                            "scene {}: {} tiles verified in the background in {:.2} s, {} not \
                             served; the whole generation is answered now",
                            s.opts.scene,
                            e.load.hashed,
                            t.elapsed().as_secs_f64(),
                            e.load.rejected.len()
                        );
                        s.served.offer(e);
                        Verification::Done
                    }
                    Err(e) => {
                        // No tile of a generation whose load failed stays served.
                        s.served.swap_if(&published, pending);
                        tracing::error!(
                            "scene {}: the background verification of its tiles failed, none \
                             of them is served (POST /reload or SIGHUP tries again): {e}",
                            s.opts.scene
                        );
                        Verification::Failed(e.to_string())
                    }
                };
                let (m, cv) = &s.verification;
                *m.lock().unwrap_or_else(PoisonError::into_inner) = state;
                cv.notify_all();
                if let Some(g) = gate {
                    g.end();
                }
            })
            .map(drop)
            .map_err(|e| Error::internal(format!("the verifying thread did not start: {e}")))
    }

    /// The observer of a background verification ([`Engine::load_observed`]): after each tile
    /// (having waited its turn at `gate`), while tiles are left to verify, it serves an engine
    /// holding a copy of the rows verified so far ([`Engine::verified_so_far`] of `pending`, the
    /// engine served at start) when the [`Cadence`] says so, in place of `published` (the last
    /// one it served). It stops publishing once something else was swapped in (a reload).
    fn publish_progress<'a>(
        &'a self,
        pending: &'a Arc<Engine>,
        published: &'a mut Arc<Engine>,
        gate: Option<VerifyGate>,
    ) -> impl FnMut(&LoadProgress<'_>) -> Result<()> + 'a {
        let mut cadence = Cadence {
            every_tile: gate.is_some(),
            last: Instant::now(),
            copy: std::time::Duration::ZERO,
        };
        let (mut handed, mut stale) = (0, false);
        move |p: &LoadProgress<'_>| {
            if let Some(g) = &gate {
                g.wait_turn(handed);
            }
            handed += 1;
            let left = pending.load.pending_verification
                > p.load.loaded_tiles.len() + p.load.rejected.len();
            if left && !stale && cadence.due() {
                let t = Instant::now();
                let next = Arc::new(pending.verified_so_far(p));
                cadence.copied(t);
                match self.0.served.swap_if(published, next.clone()) {
                    true => *published = next,
                    false => stale = true,
                }
            }
            if let Some(g) = &gate {
                g.passed(handed);
            }
            Ok(())
        }
    }

    /// Where the background verification stands.
    pub fn verification(&self) -> Verification {
        let (m, _) = &self.0.verification;
        m.lock().unwrap_or_else(PoisonError::into_inner).clone()
    }

    /// Blocks until the background verification is no longer [`Verification::Running`] and
    /// returns where it ended (at once when none runs).
    pub fn wait_verified(&self) -> Verification {
        let (m, cv) = &self.0.verification;
        let mut g = m.lock().unwrap_or_else(PoisonError::into_inner);
        while *g == Verification::Running {
            g = cv.wait(g).unwrap_or_else(PoisonError::into_inner);
        }
        g.clone()
    }

    /// The generation served now (a query keeps the one it took to its end).
    pub fn current(&self) -> Arc<Engine> {
        self.0.served.current()
    }

    /// The engine's settings.
    pub fn options(&self) -> &EngineOptions {
        &self.0.opts
    }

    /// The text model prompts are embedded with.
    pub fn text(&self) -> &dyn TextEmbedder {
        self.0.text.as_ref()
    }

    /// The admission gate (its [`Admission::stats`] for `/stats`).
    pub fn admission(&self) -> &Admission {
        &self.0.admission
    }

    /// Queries answered so far (each query of a batch counts; failed ones too).
    pub fn queries_served(&self) -> u64 {
        self.0.queries.load(Ordering::Relaxed)
    }

    /// Refuses a request asking for more than [`EngineOptions::max_matches`] matches in all.
    ///
    /// Errors: as [`check_matches`].
    pub fn check_matches(&self, qs: &[QueryParams]) -> Result<()> {
        check_matches(qs, self.0.opts.max_matches)
    }

    /// Answers `qs` in order once the admission gate lets them in, on the blocking pool (the
    /// scan itself fans out over rayon), each against the generation served when the batch
    /// started ([`Engine::answer`]) and compacted ([`compact_answer`]); the scan permit is held
    /// until the last query of the batch is done. Dropping the future (a request timeout, a
    /// client gone) abandons the batch: queries not yet begun are skipped, so the scan slot is
    /// freed after the current query instead of the last.
    ///
    /// Errors: [`Busy`] when the scan queue is full. Per query: as [`Engine::answer`];
    /// [`Error::Internal`] for a skipped query or a failed task.
    pub async fn query(
        &self,
        qs: Vec<QueryParams>,
    ) -> std::result::Result<Vec<Result<QueryAnswer>>, Busy> {
        let permit = self.0.admission.admit().await?;
        let engine = self.clone();
        let n = qs.len();
        let abandoned = Arc::new(AtomicBool::new(false));
        let _guard = AbandonOnDrop(abandoned.clone());
        let answers = tokio::task::spawn_blocking(move || {
            let _permit = permit;
            engine.answer_batch(&qs, &abandoned)
        })
        .await;
        Ok(match answers {
            Ok(v) => {
                self.0.queries.fetch_add(n as u64, Ordering::Relaxed);
                v
            }
            Err(e) => (0..n)
                .map(|_| Err(Error::internal(format!("query task failed: {e}"))))
                .collect(),
        })
    }

    /// [`Self::query`] for one query.
    ///
    /// Errors: as [`Self::query`].
    pub async fn query_one(
        &self,
        q: QueryParams,
    ) -> std::result::Result<Result<QueryAnswer>, Busy> {
        let mut answers = self.query(vec![q]).await?;
        Ok(answers
            .pop()
            .unwrap_or_else(|| Err(Error::internal("no answer"))))
    }

    /// Loads the scene's committed generation again (on the blocking pool, while the one served
    /// now keeps answering) and serves it, unless the one served now is later
    /// ([`ServedEngine::offer`]).
    ///
    /// Errors: as [`Engine::load_with`]; a generation of another CLIP model than the text
    /// model's ([`Error::ModelMismatch`]: not swapped in); a failed task ([`Error::Internal`]).
    pub async fn reload(&self) -> Result<()> {
        let s = self.0.clone();
        let e = tokio::task::spawn_blocking(move || {
            Engine::load_trusting(
                &s.edge,
                &s.opts.scene,
                s.opts.index,
                s.opts.trusted_keys.as_ref(),
            )
        })
        .await
        .map_err(|e| Error::internal(format!("reload task failed: {e}")))??;
        self.0.text.check_pair(&e.manifest.model)?;
        self.0.served.offer(e);
        Ok(())
    }

    /// Runs an admitted batch against the generation served now, skipping what is left once
    /// `abandoned` is set; times the scan for the admission gate.
    fn answer_batch(&self, qs: &[QueryParams], abandoned: &AtomicBool) -> Vec<Result<QueryAnswer>> {
        let s = &self.0;
        s.admission.started();
        let t0 = Instant::now();
        let e = s.served.current();
        let answers = qs
            .iter()
            .map(|q| {
                if abandoned.load(Ordering::Relaxed) {
                    return Err(Error::internal(
                        "query skipped: its request timed out or its client left",
                    ));
                }
                e.answer(s.text.as_ref(), &s.negatives, q)
                    .map(compact_answer)
            })
            .collect();
        s.admission.record(t0.elapsed());
        answers
    }
}

/// Sets its flag when dropped: [`QueryEngine::query`]'s batch was abandoned (see there).
struct AbandonOnDrop(Arc<AtomicBool>);

impl Drop for AbandonOnDrop {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Relaxed);
    }
}

/// Refuses a request asking for more than `max` matches in all (the sum of `top_k` over its
/// queries; a threshold query returns at most its `top_k` best matches too), before any scan,
/// so the largest answer one request can build is bounded.
///
/// Errors: [`Error::Query`] `top_k` naming the sum and the limit.
pub fn check_matches(qs: &[QueryParams], max: usize) -> Result<()> {
    let asked: usize = qs.iter().map(|q| q.top_k).sum();
    if asked > max {
        return Err(Error::query(
            "top_k",
            format!(
                "the request asks for {asked} matches in all (sum of top_k over its queries); \
                 this server answers at most {max} per request (max_matches): lower top_k or \
                 split the batch"
            ),
        ));
    }
    Ok(())
}

/// `a` holding only what it returns (its lists' capacity shrunk to their length). A threshold
/// query collects every match above its threshold (for the summary and the objects) and returns
/// the `top_k` best, so its lists can keep the capacity of all of them: up to the scene's
/// Gaussian count × 20 bytes per answer, held by every answer of a batch until the batch is
/// sent. Compacted, a batch holds at most [`EngineOptions::max_matches`] matches in all.
pub fn compact_answer(mut a: QueryAnswer) -> QueryAnswer {
    a.matches.shrink_to_fit();
    a.match_objects.shrink_to_fit();
    a.objects.shrink_to_fit();
    a
}
