//! What the server holds: one [`Scene`] per bundle, opened once (in the background at
//! start-up, [`AppState::load_in_background`]) and shared, each in a [`SceneState`]; the
//! worker pool, the metrics, the settings and the shutdown signal ([`AppState`]).

use std::collections::{BTreeMap, HashMap, HashSet};
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock, RwLock};

use axum::body::Bytes;
use tokio::sync::watch;
use translux_proto::animation::{JOURNAL_FILE, SEQUENCE_FILE, SequenceManifest};
use translux_proto::bundle::{Bundle, BundleError, MANIFEST_FILE, OpenOptions};

use crate::backend::Backend;
use crate::config::PrepareWhen;
use crate::config::ServerParams;
use crate::error::AppError;
use crate::metrics::Metrics;
use crate::pool::Pool;
use crate::prepare::{PreparedHook, Preparer};
use translux_engine::scene::Resources;

/// One served bundle: the engine's relight state ([`translux_engine::scene::Scene`], which
/// it dereferences to) plus what only the HTTP API needs (`GET /mesh`'s JSON).
#[derive(Debug)]
pub struct Scene {
    inner: Arc<translux_engine::scene::Scene>,
    /// `GET /mesh`'s JSON, serialised on first use.
    pub(crate) mesh_json: OnceLock<Bytes>,
    /// An animated scene's frames (a sequence folder, `docs/scenes.md#animation`); the
    /// scene itself is then frame 0.
    pub sequence: Option<Arc<Sequence>>,
}

/// The frames of an animated scene, each a bundle opened on its own; frames that share a
/// bundle folder share one opened scene.
#[derive(Debug)]
pub struct Sequence {
    /// The sequence folder (`sequence.json` and the frame bundles).
    pub dir: PathBuf,
    pub fps: f32,
    pub frames: Vec<Arc<Scene>>,
    /// Distinct bundles among the frames.
    pub bundles: usize,
}

impl Scene {
    /// Frame `frame` of this scene (`None`: frame 0), or a 400 naming the frame and the
    /// range. A sequence's frames are scenes of their own (each with its own mesh JSON),
    /// so frame 0 asked with or without `frame` is one and the same.
    pub fn frame(self: &Arc<Self>, frame: Option<u32>) -> Result<Arc<Scene>, AppError> {
        let k = frame.unwrap_or(0);
        let count = self.frame_count();
        match &self.sequence {
            Some(seq) if (k as usize) < seq.frames.len() => Ok(seq.frames[k as usize].clone()),
            None if k == 0 => Ok(self.clone()),
            _ => Err(AppError::bad_request(format!(
                "frame {k} is out of range: scene {:?} has {count} frame{} (0 to {})",
                self.id,
                if count == 1 { "" } else { "s" },
                count - 1
            ))),
        }
    }

    /// Frames: 1 for a still scene.
    pub fn frame_count(&self) -> u32 {
        self.sequence.as_ref().map_or(1, |s| s.frames.len() as u32)
    }

    /// Bytes of its bundles (every distinct frame's for a sequence).
    pub fn total_bytes(&self) -> u64 {
        match &self.sequence {
            None => self.bundle.total_bytes(),
            Some(seq) => {
                let mut seen = std::collections::HashSet::new();
                seq.frames
                    .iter()
                    .filter(|f| seen.insert(Arc::as_ptr(&f.inner)))
                    .map(|f| f.bundle.total_bytes())
                    .sum()
            }
        }
    }
}

impl std::ops::Deref for Scene {
    type Target = translux_engine::scene::Scene;
    fn deref(&self) -> &Self::Target {
        &self.inner
    }
}

impl Scene {
    /// Opens the bundle in `dir` relit on the CPU ([`translux_engine::scene::Scene::open`]).
    pub fn open(id: impl Into<String>, dir: &Path) -> Result<Scene, BundleError> {
        Scene::open_with(id, dir, &Resources::default())
    }

    /// Opens the bundle in `dir` relit with `resources` (the server's backend and caches);
    /// a sequence folder (`sequence.json` beside one bundle per frame) opens every frame.
    pub fn open_with(
        id: impl Into<String>,
        dir: &Path,
        resources: &Resources,
    ) -> Result<Scene, BundleError> {
        Scene::open_checked(id, dir, resources, OpenOptions::default())
    }

    /// [`Scene::open_with`] verifying as `options` say (a scene reopened after eviction
    /// skips the checksums: it was verified when first opened).
    pub fn open_checked(
        id: impl Into<String>,
        dir: &Path,
        resources: &Resources,
        options: OpenOptions,
    ) -> Result<Scene, BundleError> {
        let id = id.into();
        if dir.join(SEQUENCE_FILE).is_file() {
            return Scene::open_sequence(id, dir, resources, options);
        }
        if dir.join(JOURNAL_FILE).is_file() && !dir.join(MANIFEST_FILE).is_file() {
            return Err(BundleError::Invalid {
                file: SEQUENCE_FILE.into(),
                reason: "missing: this animated scene's precompute has not finished (run the \
                         same translux-precompute command again to resume it)"
                    .into(),
            });
        }
        let bundle = Bundle::open_with(dir, options)?;
        Ok(Scene::from_bundle_with(id, bundle, resources))
    }

    /// Opens the sequence in `dir`: every distinct frame bundle once, verified like any.
    fn open_sequence(
        id: String,
        dir: &Path,
        resources: &Resources,
        options: OpenOptions,
    ) -> Result<Scene, BundleError> {
        let text =
            std::fs::read_to_string(dir.join(SEQUENCE_FILE)).map_err(|error| BundleError::Io {
                file: SEQUENCE_FILE.into(),
                error,
            })?;
        let manifest: SequenceManifest =
            translux_proto::parse_json(&text).map_err(|e| BundleError::Invalid {
                file: SEQUENCE_FILE.into(),
                reason: e.to_string(),
            })?;
        manifest.validate().map_err(|reason| BundleError::Invalid {
            file: SEQUENCE_FILE.into(),
            reason,
        })?;
        let mut opened: BTreeMap<&str, Arc<Scene>> = BTreeMap::new();
        let mut frames = Vec::with_capacity(manifest.frames.len());
        for folder in &manifest.frames {
            if let Some(s) = opened.get(folder.as_str()) {
                frames.push(s.clone());
                continue;
            }
            let bundle = Bundle::open_with(&dir.join(folder), options).map_err(|e| {
                BundleError::Invalid {
                    file: format!("{folder}/{}", e.file()),
                    reason: e.to_string(),
                }
            })?;
            let scene = Arc::new(Scene::from_bundle_with(id.clone(), bundle, resources));
            opened.insert(folder, scene.clone());
            frames.push(scene);
        }
        let first = frames[0].inner.clone();
        Ok(Scene {
            inner: first,
            mesh_json: OnceLock::new(),
            sequence: Some(Arc::new(Sequence {
                dir: dir.to_path_buf(),
                fps: manifest.fps,
                bundles: opened.len(),
                frames,
            })),
        })
    }

    /// An opened bundle relit with `resources`.
    pub fn from_bundle_with(id: impl Into<String>, bundle: Bundle, resources: &Resources) -> Scene {
        Scene::wrap(translux_engine::scene::Scene::from_bundle_with(
            id, bundle, resources,
        ))
    }

    /// The engine's scene, shared: what the worker pool relights.
    pub fn engine(&self) -> Arc<translux_engine::scene::Scene> {
        self.inner.clone()
    }

    fn wrap(inner: translux_engine::scene::Scene) -> Scene {
        Scene {
            inner: Arc::new(inner),
            mesh_json: OnceLock::new(),
            sequence: None,
        }
    }
}

/// Where a scene is in its life: bundles load in the background after the server starts
/// listening, so a request can find its scene still loading (503) or failed (404).
#[derive(Debug, Clone)]
pub enum SceneState {
    /// Being opened (verified, mapped, BVH built) or precomputed (`--demo`).
    Loading,
    Ready(Arc<Scene>),
    /// Could not be opened; the loader's message.
    Failed(String),
    /// Dropped to stay within the memory budget ([`crate::budget`]); reopened by its next
    /// request ([`crate::team`]'s residency middleware).
    Evicted(Arc<crate::budget::EvictedScene>),
}

impl SceneState {
    /// `loading`, `ready` or `failed`.
    pub fn as_str(&self) -> &'static str {
        match self {
            SceneState::Loading => "loading",
            SceneState::Ready(_) => "ready",
            SceneState::Failed(_) => "failed",
            SceneState::Evicted(_) => "evicted",
        }
    }
}

/// What the server holds: the scenes by id and their state, the worker pool, the metrics,
/// the settings and the shutdown signal. Cheap to clone (one `Arc`).
#[derive(Debug, Clone)]
pub struct AppState {
    inner: Arc<Inner>,
}

/// An [`AppState`] held without keeping it alive (for hooks the state itself holds).
#[derive(Debug, Clone)]
pub struct WeakAppState(std::sync::Weak<Inner>);

impl WeakAppState {
    /// The state, while any [`AppState`] handle is left.
    pub fn upgrade(&self) -> Option<AppState> {
        self.0.upgrade().map(|inner| AppState { inner })
    }
}

#[derive(Debug)]
struct Inner {
    scenes: RwLock<BTreeMap<String, SceneState>>,
    pool: Pool,
    metrics: Metrics,
    /// `true` once shutdown has begun: streams finish their work and close.
    shutdown: watch::Sender<bool>,
    /// Ids for WebSocket streams (each its own client of the pool).
    next_stream: AtomicU64,
    /// The backend every scene is opened on (its health and device memory).
    backend: Backend,
    /// The same backend as the engine sees it, and the scenes' shared caches.
    resources: Resources,
    /// Scenes' translucency preparation ([`crate::prepare`]).
    preparer: Preparer,
    /// What each scene's folder held when it was last opened, for [`AppState::rescan`].
    stamps: Mutex<HashMap<String, FolderStamp>>,
    /// Scenes whose folder the last rescan did not find (dropped when the next one does
    /// not either: a writer replacing a bundle leaves the name empty for a moment).
    missing: Mutex<HashSet<String>>,
}

impl Drop for Inner {
    /// The last handle gone: the workers finish what is queued and exit.
    fn drop(&mut self) {
        self.pool.close();
    }
}

impl Default for AppState {
    fn default() -> Self {
        AppState::with_params(ServerParams::default())
    }
}

impl AppState {
    /// A state serving `scenes`, all ready, with the default [`ServerParams`] (a later
    /// scene with the same id replaces an earlier one).
    pub fn new(scenes: impl IntoIterator<Item = Scene>) -> AppState {
        let state = AppState::default();
        for s in scenes {
            state.insert_ready(s);
        }
        state
    }

    /// A state with no scenes yet and its worker pool started with `params`, relighting on
    /// the CPU.
    pub fn with_params(params: ServerParams) -> AppState {
        AppState::with_backend(params, cpu_backend())
    }

    /// [`AppState::with_params`] with scenes opened on `backend` (the server's, started
    /// once; `params.backend` should be its name).
    pub fn with_backend(params: ServerParams, backend: Backend) -> AppState {
        let metrics = Metrics::new();
        let pool = Pool::new(params, metrics.clone());
        AppState {
            inner: Arc::new(Inner {
                scenes: RwLock::new(BTreeMap::new()),
                pool,
                metrics,
                shutdown: watch::channel(false).0,
                next_stream: AtomicU64::new(1),
                resources: Resources::on(Arc::new(backend.clone())),
                backend,
                preparer: Preparer::default(),
                stamps: Mutex::default(),
                missing: Mutex::default(),
            }),
        }
    }

    fn scenes_read(&self) -> std::sync::RwLockReadGuard<'_, BTreeMap<String, SceneState>> {
        self.inner.scenes.read().unwrap_or_else(|e| e.into_inner())
    }

    fn set(&self, id: String, state: SceneState) {
        self.inner
            .scenes
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .insert(id, state);
    }

    /// Serves `scene` under its id.
    pub fn insert_ready(&self, scene: Scene) {
        self.set(scene.id.clone(), SceneState::Ready(Arc::new(scene)));
    }

    /// Marks `id` as loading (503 until it is ready or failed).
    pub fn set_loading(&self, id: impl Into<String>) {
        self.set(id.into(), SceneState::Loading);
    }

    /// Marks `id` as evicted (see [`SceneState::Evicted`]).
    pub fn set_evicted(&self, id: impl Into<String>, evicted: Arc<crate::budget::EvictedScene>) {
        self.set(id.into(), SceneState::Evicted(evicted));
    }

    /// Stops serving `id` altogether (a deleted scene); its old state.
    pub fn remove(&self, id: &str) -> Option<SceneState> {
        lock(&self.inner.stamps).remove(id);
        lock(&self.inner.missing).remove(id);
        self.inner
            .scenes
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .remove(id)
    }

    /// Marks `id` as failed with the loader's message.
    pub fn set_failed(&self, id: impl Into<String>, message: impl Into<String>) {
        self.set(id.into(), SceneState::Failed(message.into()));
    }

    /// The state of scene `id`, if it is known at all.
    pub fn scene_state(&self, id: &str) -> Option<SceneState> {
        self.scenes_read().get(id).cloned()
    }

    /// Every known scene with its state, in id order.
    pub fn scene_states(&self) -> Vec<(String, SceneState)> {
        self.scenes_read()
            .iter()
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect()
    }

    /// The ready scene with this id.
    pub fn scene(&self, id: &str) -> Option<Arc<Scene>> {
        match self.scenes_read().get(id) {
            Some(SceneState::Ready(s)) => Some(s.clone()),
            _ => None,
        }
    }

    /// The ready scene with this id, or the error to answer: 503 `loading` (with
    /// `Retry-After`) while it loads, 404 for an unknown id or a bundle that failed to load
    /// (with the loader's message).
    pub fn lookup(&self, id: &str) -> Result<Arc<Scene>, AppError> {
        match self.scene_state(id) {
            Some(SceneState::Ready(s)) => Ok(s),
            Some(SceneState::Loading) => Err(AppError::loading(format!(
                "scene {id:?} is still loading; retry in a moment (GET /healthz shows each \
                 scene's state)"
            ))),
            Some(SceneState::Failed(why)) => Err(AppError::not_found(format!(
                "scene {id:?} is not served: its bundle failed to load ({why})"
            ))),
            Some(SceneState::Evicted(_)) => Err(AppError::loading(format!(
                "scene {id:?} was evicted to stay within the memory budget and is being \
                 reopened; retry in a moment"
            ))),
            None => {
                let ids = self.ids();
                let known = if ids.is_empty() {
                    "none".to_string()
                } else {
                    ids.join(", ")
                };
                Err(AppError::not_found(format!(
                    "no scene {id:?}; the scenes served are: {known}"
                )))
            }
        }
    }

    /// Every ready scene, in id order.
    pub fn scenes(&self) -> Vec<Arc<Scene>> {
        self.scenes_read()
            .values()
            .filter_map(|s| match s {
                SceneState::Ready(s) => Some(s.clone()),
                _ => None,
            })
            .collect()
    }

    /// The ids of the ready scenes, sorted.
    pub fn ids(&self) -> Vec<String> {
        self.scenes().iter().map(|s| s.id.clone()).collect()
    }

    /// Ready scenes.
    pub fn len(&self) -> usize {
        self.scenes().len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes of the bundles that ready scenes map.
    pub fn mapped_bytes(&self) -> u64 {
        self.scenes().iter().map(|s| s.total_bytes()).sum()
    }

    pub fn pool(&self) -> &Pool {
        &self.inner.pool
    }

    pub fn params(&self) -> &ServerParams {
        self.inner.pool.params()
    }

    /// The compute backend named in `/healthz`.
    pub fn backend(&self) -> &str {
        &self.params().backend
    }

    /// The backend its scenes are opened on (the server's; the CPU for a default state).
    pub fn compute_backend(&self) -> &Backend {
        &self.inner.backend
    }

    /// What its scenes are opened with: the backend and the shared environment-map cache.
    pub fn resources(&self) -> &Resources {
        &self.inner.resources
    }

    pub fn metrics(&self) -> &Metrics {
        &self.inner.metrics
    }

    /// A new id for a WebSocket stream.
    pub fn next_stream_id(&self) -> u64 {
        self.inner.next_stream.fetch_add(1, Ordering::Relaxed)
    }

    /// Starts shutting down: streams finish their work and close. Idempotent.
    pub fn begin_shutdown(&self) {
        self.inner.shutdown.send_replace(true);
    }

    /// Whether shutdown has begun; `changed()` on it wakes when it does.
    pub fn shutdown_watch(&self) -> watch::Receiver<bool> {
        self.inner.shutdown.subscribe()
    }

    /// Opens the bundle in `dir` as scene `id` and records the outcome; logs it. Blocking.
    /// A new scene is marked loading first (503 until it is ready or failed). A scene
    /// already served (ready or evicted) is a replacement: it is served as it was while the
    /// new bundle opens, then swapped in, and requests already holding the old one finish
    /// on it; a replacement that does not open leaves the old one served (and logs why).
    pub fn load_one(&self, id: &str, dir: &Path) {
        let stamp = FolderStamp::of(dir);
        let serving = matches!(
            self.scene_state(id),
            Some(SceneState::Ready(_) | SceneState::Evicted(_))
        );
        if !serving {
            self.set_loading(id);
        }
        let t = std::time::Instant::now();
        match Scene::open_with(id, dir, &self.inner.resources) {
            Ok(scene) => {
                log_serving(id, &scene, t.elapsed());
                // On the GPU backend, F and S go to the device now, not on the first relight.
                scene.backend().prepare(scene.view());
                self.insert_ready(scene);
                if self.params().prepare == PrepareWhen::Load {
                    self.prepare_translucency(id);
                }
            }
            Err(e) if serving => {
                tracing::warn!(
                    "still serving the bundle {id:?} had: its replacement in {} does not \
                     open: {e}",
                    dir.display()
                );
            }
            Err(e) => {
                tracing::warn!("skipping bundle {id:?} in {}: {e}", dir.display());
                // Clients (an open /healthz) see the bundle's folder, not the server's path.
                let message = match dir.parent() {
                    Some(root) => crate::jobs::strip_dir(&e.to_string(), root),
                    None => e.to_string(),
                };
                self.set_failed(id, message);
            }
        }
        if let Some(stamp) = stamp {
            lock(&self.inner.stamps).insert(id.to_string(), stamp);
        }
    }

    /// Brings what is served in line with the bundles folder `dir` (see `docs/team.md`,
    /// "Several servers over one folder"): a folder with a new complete bundle, or whose
    /// bundle changed since it was opened ([`FolderStamp`]), is handed to `load` (which
    /// should end in [`AppState::load_one`]); a scene whose folder is gone on two rescans in
    /// a row is dropped. Ids that `skip` names (scenes this server's own jobs are writing)
    /// and scenes still loading are left alone, and so is everything when the folder
    /// cannot be read. Blocking.
    pub fn rescan(
        &self,
        dir: &Path,
        skip: &dyn Fn(&str) -> bool,
        load: &dyn Fn(&str, &Path),
    ) -> Result<Rescanned, String> {
        let (found, _) = discover(dir)?;
        let mut done = Rescanned::default();
        let mut present = HashSet::new();
        for (id, path) in found {
            if skip(&id) || matches!(self.scene_state(&id), Some(SceneState::Loading)) {
                present.insert(id);
                continue;
            }
            let Some(stamp) = FolderStamp::of(&path) else {
                continue; // no manifest: not a bundle (yet)
            };
            present.insert(id.clone());
            let known = lock(&self.inner.stamps).get(&id).cloned();
            if known.as_ref() == Some(&stamp) {
                continue;
            }
            let what = if known.is_some() {
                "was replaced"
            } else {
                "appeared"
            };
            tracing::info!("bundles folder: {id:?} {what}; opening it");
            load(&id, &path);
            done.loaded.push(id);
        }
        let stamped: Vec<String> = lock(&self.inner.stamps).keys().cloned().collect();
        let mut missing = lock(&self.inner.missing);
        missing.retain(|id| !present.contains(id));
        for id in stamped {
            if present.contains(&id) || skip(&id) {
                continue;
            }
            if missing.insert(id.clone()) {
                continue; // gone once: maybe a bundle being renamed into place
            }
            missing.remove(&id);
            lock(&self.inner.stamps).remove(&id);
            self.inner
                .scenes
                .write()
                .unwrap_or_else(|e| e.into_inner())
                .remove(&id);
            tracing::info!("bundles folder: {id:?} was removed; no longer serving it");
            done.removed.push(id);
        }
        Ok(done)
    }

    /// Queues scene `id`'s translucency preparation ([`crate::prepare`]; frame 0 of an
    /// animated scene) unless it is not ready, has nothing pending or is queued already.
    pub fn prepare_translucency(&self, id: &str) {
        if let Some(scene) = self.scene(id) {
            self.inner.preparer.queue(&scene.engine());
        }
    }

    /// [`AppState::prepare_translucency`] when scenes are prepared on their first request.
    pub fn prepare_on_request(&self, id: &str) {
        if self.params().prepare == PrepareWhen::Request {
            self.prepare_translucency(id);
        }
    }

    /// A handle that does not keep the state alive.
    pub fn downgrade(&self) -> WeakAppState {
        WeakAppState(Arc::downgrade(&self.inner))
    }

    /// Sets what runs after a scene is prepared (the memory budget's charge; once).
    pub fn on_prepared(&self, hook: PreparedHook) {
        self.inner.preparer.set_hook(hook);
    }

    /// Marks every `(id, folder)` as loading, then opens them one after another on a
    /// background thread (after `before`, e.g. the demo's precompute, has run).
    pub fn load_in_background(
        &self,
        bundles: Vec<(String, PathBuf)>,
        before: impl FnOnce(&AppState) + Send + 'static,
    ) -> std::thread::JoinHandle<()> {
        for (id, _) in &bundles {
            self.set_loading(id.clone());
        }
        let state = self.clone();
        std::thread::Builder::new()
            .name("bundle-loader".into())
            .spawn(move || {
                before(&state);
                for (id, dir) in bundles {
                    // `before` may have settled a scene already (a failed demo precompute).
                    if matches!(state.scene_state(&id), Some(SceneState::Loading)) {
                        state.load_one(&id, &dir);
                    }
                }
            })
            .expect("cannot start the bundle loader thread")
    }
}

/// What one [`AppState::rescan`] changed.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct Rescanned {
    /// Scenes opened: new folders and replaced bundles (ready now, or failed, or still
    /// served as they were when the replacement did not open).
    pub loaded: Vec<String>,
    /// Scenes dropped: their folders are gone.
    pub removed: Vec<String>,
}

/// What a bundle folder holds, as cheaply as it can be told: the name, identity (inode),
/// size and modification time of each entry. A bundle renamed into place whole has a new
/// manifest inode (and new files); a bundle copied in file by file changes as its files
/// do, so a copy that failed to open half-way is opened again once it has changed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FolderStamp(Vec<(OsString, u64, u64, Option<std::time::SystemTime>)>);

impl FolderStamp {
    /// The stamp of the bundle in `dir`; `None` when it has no `manifest.json` (nor
    /// `sequence.json`): no bundle there, or not yet.
    pub fn of(dir: &Path) -> Option<FolderStamp> {
        if !dir.join(MANIFEST_FILE).is_file() && !dir.join(SEQUENCE_FILE).is_file() {
            return None;
        }
        let mut entries: Vec<_> = std::fs::read_dir(dir)
            .ok()?
            .flatten()
            .filter_map(|e| {
                let m = e.metadata().ok()?;
                Some((e.file_name(), inode(&m), m.len(), m.modified().ok()))
            })
            .collect();
        entries.sort();
        Some(FolderStamp(entries))
    }
}

/// A file's inode number (0 where there is none to read).
fn inode(m: &std::fs::Metadata) -> u64 {
    #[cfg(unix)]
    {
        std::os::unix::fs::MetadataExt::ino(m)
    }
    #[cfg(not(unix))]
    {
        let _ = m;
        0
    }
}

/// Locks `m`, a poisoned lock included (what it guards stays consistent at every step).
fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// The log line of a scene that is served now.
fn log_serving(id: &str, scene: &Scene, took: std::time::Duration) {
    let m = scene.bundle.manifest();
    let frames = match &scene.sequence {
        Some(s) => format!(
            " (frame 0 of {} frames in {} bundles, {:.1} MB in all)",
            s.frames.len(),
            s.bundles,
            scene.total_bytes() as f64 / 1e6
        ),
        None => String::new(),
    };
    tracing::info!(
        "serving {id:?} ({}, from {}): {} patches, {} vertices, {} objects, nnz(F) {}, \
         {:.1} MB{frames}, loaded in {:.2} s",
        m.name,
        m.source,
        m.patch_count,
        m.vertex_count,
        m.objects.len(),
        m.form_factors.nnz,
        scene.bundle.total_bytes() as f64 / 1e6,
        took.as_secs_f64()
    );
}

/// `(id, folder)` of each bundle found, and `(name, why)` of each folder that cannot be one.
pub type Discovered = (Vec<(String, PathBuf)>, Vec<(String, String)>);

/// The bundle folders under `dir` as `(id, folder)`, sorted: each sub-folder whose name is
/// UTF-8 and does not start with `.` (a writer's temporaries); `dir` itself, under its own
/// name, if it holds a `manifest.json`. Folders that cannot be ids come back as errors.
pub fn discover(dir: &Path) -> Result<Discovered, String> {
    if dir.join(MANIFEST_FILE).is_file() || dir.join(SEQUENCE_FILE).is_file() {
        let id = folder_name(dir).unwrap_or_else(|| "bundle".to_string());
        return Ok((vec![(id, dir.to_path_buf())], Vec::new()));
    }
    let entries = std::fs::read_dir(dir).map_err(|e| format!("cannot read the folder: {e}"))?;
    let mut folders: Vec<_> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.is_dir())
        .collect();
    folders.sort();
    let mut found = Vec::new();
    let mut errors = Vec::new();
    for path in folders {
        let Some(name) = path.file_name() else {
            continue;
        };
        let Some(id) = name.to_str() else {
            errors.push((
                name.to_string_lossy().into_owned(),
                "the folder name is not UTF-8 and cannot be an id".to_string(),
            ));
            continue;
        };
        if id.starts_with('.') {
            continue;
        }
        found.push((id.to_string(), path));
    }
    Ok((found, errors))
}

/// Opens every bundle under `dir`: each sub-folder is one bundle whose id is the folder
/// name. Hidden folders (a writer's temporaries start with `.`) and plain files are passed
/// over. If `dir` itself holds a `manifest.json` it is served alone, under its own name.
///
/// Returns the state with every bundle that opened, and `(id, message)` for each that did
/// not (the loader's message, e.g. `ff_val.f32 is truncated: 100 bytes, manifest says 400`);
/// a folder that cannot be read at all comes back as one error with `dir` as its id.
pub fn load_bundles(dir: &Path) -> (AppState, Vec<(String, String)>) {
    load_bundles_with(dir, ServerParams::default())
}

/// [`load_bundles`] with the given settings.
pub fn load_bundles_with(dir: &Path, params: ServerParams) -> (AppState, Vec<(String, String)>) {
    let state = AppState::with_params(params);
    for removed in remove_abandoned_temporaries(dir) {
        tracing::info!("removed {removed}: a precompute's temporary folder whose process is gone");
    }
    let (found, mut errors) = match discover(dir) {
        Ok(x) => x,
        Err(e) => return (state, vec![(dir.display().to_string(), e)]),
    };
    for (id, path) in found {
        match Scene::open_with(id.clone(), &path, state.resources()) {
            Ok(scene) => state.insert_ready(scene),
            Err(e) => errors.push((id, e.to_string())),
        }
    }
    (state, errors)
}

/// Removes the temporary folders (`.ID.tmp-PID-NANOS-SEQ`) that a precompute which
/// crashed or was killed left in `dir`: those whose process no longer runs and that have not
/// changed for ten minutes (a reused PID cannot keep a live writer's folder from aging; nor
/// can a writer on another machine sharing the folder, whose PID means nothing here, but
/// it adds files to its folder as it goes). Returns the names removed. Folders of running
/// precomputes are never touched.
pub fn remove_abandoned_temporaries(dir: &Path) -> Vec<String> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut removed = Vec::new();
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(pid) = name
            .strip_prefix('.')
            .and_then(|n| n.split_once(".tmp-"))
            .and_then(|(_, rest)| rest.split('-').next())
            .and_then(|p| p.parse::<u32>().ok())
        else {
            continue;
        };
        let alive = pid == std::process::id() || Path::new(&format!("/proc/{pid}")).exists();
        let idle = e
            .metadata()
            .and_then(|m| m.modified())
            .ok()
            .and_then(|t| t.elapsed().ok())
            .is_some_and(|age| age.as_secs() >= 600);
        if !alive && idle && e.path().is_dir() && std::fs::remove_dir_all(e.path()).is_ok() {
            removed.push(name);
        }
    }
    removed
}

/// The last component of `dir` (after resolving `.` and `..`).
fn folder_name(dir: &Path) -> Option<String> {
    let abs = std::fs::canonicalize(dir).ok()?;
    abs.file_name().and_then(|n| n.to_str()).map(str::to_string)
}

/// The backend of a state made without one ([`AppState::with_params`]: library use, tests).
fn cpu_backend() -> Backend {
    Backend::cpu("no backend was chosen (a state made without one): the CPU relights")
}
