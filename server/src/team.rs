//! One server for a team: access control ([`crate::auth`]), uploads and precompute jobs
//! ([`crate::upload`], [`crate::jobs`]), scene deletion, and the memory budget
//! ([`crate::budget`]) — put around the API of [`crate::routes`] by [`app`].
//!
//! In: [`TeamArgs`] (flags and `TRANSLUX_*` variables), the bundles folder, the
//! [`AppState`]. Out: a router with these routes added —
//!
//! | route | role | answer |
//! | --- | --- | --- |
//! | `POST /api/v1/scenes` | editor | 202, the job record, `Location: /api/v1/jobs/{id}` |
//! | `GET /api/v1/jobs` | editor | `{"jobs":[...]}`: yours (an admin sees all), newest first |
//! | `GET /api/v1/jobs/{id}` | editor | the job record |
//! | `GET /api/v1/jobs/{id}/events` | editor | Server-Sent Events: `progress` per change, then `done`, `failed` or `cancelled` |
//! | `DELETE /api/v1/jobs/{id}` | editor | cancels; the record |
//! | `DELETE /api/v1/scenes/{id}` | admin | unloads the scene and deletes its bundle folder |
//! | `GET /api/v1/whoami` | viewer | `{"name","role","auth"}` |
//!
//! — and two middlewares around everything: [`crate::auth::middleware`] (outermost: 401,
//! 403, 429), then the residency middleware, which makes the scene of a
//! `/api/v1/scenes/{id}...` request resident before its handler runs (reopening an evicted
//! scene) and evicts least-recently-used scenes when the budget is exceeded.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::extract::{DefaultBodyLimit, Path as UrlPath, Request, State};
use axum::http::{Method, StatusCode};
use axum::middleware::{self, Next};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json, Router};
use serde::Serialize;
use translux_proto::api::ErrorBody;
use translux_proto::bundle::OpenOptions;

use crate::auth::{Auth, Identity, RateLimit, Role};
use crate::budget::{EvictedScene, MemoryBudget, parse_bytes};
use crate::error::AppError;
use crate::jobs::{JobRecord, Jobs, JobsConfig};
use crate::routes::RouteTable;
use crate::schema::SceneIdParam;
use crate::state::{AppState, Scene, SceneState};
use crate::upload::{UploadLimits, check_scene_id};

/// The team settings of `translux-server` (flags, or the `TRANSLUX_*` variables named).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct TeamArgs {
    /// Tokens file (TOML, hashed tokens with roles; see `translux-server token add`).
    /// Without it the server serves loopback only.
    #[arg(long, value_name = "FILE", env = "TRANSLUX_TOKENS")]
    pub tokens: Option<PathBuf>,
    /// Requests per second per token (a token's own `rate` overrides it) [default: 50].
    #[arg(long, value_name = "N", env = "TRANSLUX_RATE_LIMIT")]
    pub rate_limit: Option<f64>,
    /// Requests a token may make at once above its rate [default: 100].
    #[arg(long, value_name = "N", env = "TRANSLUX_RATE_BURST")]
    pub rate_burst: Option<f64>,
    /// Memory the resident scenes may hold (e.g. 8GiB); least recently used scenes are
    /// evicted beyond it and reopened on their next request [default: no limit].
    #[arg(long, value_name = "SIZE", env = "TRANSLUX_MEMORY_BUDGET", value_parser = parse_bytes)]
    pub memory_budget: Option<u64>,
    /// Where precompute jobs run: `local` (in the server, one at a time), a number N (in
    /// the server, N at once) or `slurm` (submitted to Slurm with sbatch: docs/team.md)
    /// [default: local].
    #[arg(long, value_name = "local|N|slurm", env = "TRANSLUX_JOBS",
          value_parser = crate::slurm::JobsSetting::parse)]
    pub jobs: Option<crate::slurm::JobsSetting>,
    /// With `--jobs slurm`: shards of an upload's precompute, the tasks of its job array
    /// [default: 2].
    #[arg(long, value_name = "K", env = "TRANSLUX_SLURM_SHARDS")]
    pub slurm_shards: Option<u32>,
    /// With `--jobs slurm`: more sbatch arguments for every job, split on spaces (e.g.
    /// "--partition=gpu --account=lab --time=1:00:00") [default: none].
    #[arg(
        long,
        value_name = "ARGS",
        env = "TRANSLUX_SLURM_ARGS",
        allow_hyphen_values = true
    )]
    pub slurm_args: Option<String>,
    /// Threads of the precompute pool [default: half the cores].
    #[arg(long, value_name = "N", env = "TRANSLUX_JOB_THREADS")]
    pub job_threads: Option<usize>,
    /// Precompute jobs that may wait [default: 16; 4 per token].
    #[arg(long, value_name = "N", env = "TRANSLUX_JOB_QUEUE")]
    pub job_queue: Option<usize>,
    /// Memory one precompute job may take (e.g. 4GiB): refused up front when its estimate
    /// is larger, stopped when the server grows by more while it runs [default: 85% of the
    /// memory available when it starts].
    #[arg(long, value_name = "SIZE", env = "TRANSLUX_JOB_MEMORY", value_parser = parse_bytes)]
    pub job_memory: Option<u64>,
    /// Largest upload, all files together [default: 256MiB].
    #[arg(long, value_name = "SIZE", env = "TRANSLUX_UPLOAD_LIMIT", value_parser = parse_bytes)]
    pub upload_limit: Option<u64>,
    /// Largest file of an upload [default: 64MiB].
    #[arg(long, value_name = "SIZE", env = "TRANSLUX_UPLOAD_FILE_LIMIT", value_parser = parse_bytes)]
    pub upload_file_limit: Option<u64>,
    /// Most patches an uploaded scene may ask for [default: 50000].
    #[arg(long, value_name = "N", env = "TRANSLUX_MAX_UPLOAD_PATCHES")]
    pub max_upload_patches: Option<u64>,
    /// Seconds between looks at the bundles folder for bundles that appeared, were
    /// replaced or were removed, and at the tokens file for changes (several servers over
    /// one shared folder); 0 turns it off [default: 2].
    #[arg(long, value_name = "S", env = "TRANSLUX_RESCAN_S")]
    pub rescan_s: Option<f64>,
}

/// `--rescan-s` when not given.
pub const DEFAULT_RESCAN_S: f64 = 2.0;

/// Everything the team routes need; cheap to clone.
#[derive(Clone)]
pub struct Team {
    pub auth: Arc<Auth>,
    pub jobs: Jobs,
    pub budget: Arc<MemoryBudget>,
    pub limits: UploadLimits,
    pub state: AppState,
    pub bundles: PathBuf,
    /// Per-scene locks so that concurrent requests reopen an evicted scene once.
    reloading: Arc<Mutex<std::collections::HashMap<String, Arc<tokio::sync::Mutex<()>>>>>,
    /// Scene ids of uploads accepted but not yet queued as jobs (see [`Team::reserve`]).
    reserved: Arc<Mutex<std::collections::HashSet<String>>>,
    /// Serves a bundle that is in place: a finished job's, or one the rescan found
    /// ([`Team::rescan`]); one mechanism for both.
    on_bundle: crate::jobs::OnDone,
}

/// An upload's hold on a scene id, from the first check until its job is queued (then the
/// job table holds the id until the job ends, and the served scene after that). Dropping it
/// releases the id.
#[derive(Debug)]
pub struct Reservation {
    set: Arc<Mutex<std::collections::HashSet<String>>>,
    id: String,
}

impl Drop for Reservation {
    fn drop(&mut self) {
        self.set
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(&self.id);
    }
}

impl std::fmt::Debug for Team {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Team")
            .field("auth", &self.auth)
            .field("jobs", &self.jobs)
            .field("budget", &self.budget)
            .field("limits", &self.limits)
            .field("bundles", &self.bundles)
            .finish_non_exhaustive()
    }
}

impl Team {
    /// Reads the tokens, settles the jobs an earlier run left, starts the job pool.
    pub fn start(args: &TeamArgs, bundles: &Path, state: AppState) -> anyhow::Result<Team> {
        let defaults = RateLimit::default();
        let rate = RateLimit {
            per_second: args.rate_limit.unwrap_or(defaults.per_second),
            burst: args.rate_burst.unwrap_or(defaults.burst),
        };
        let auth = match &args.tokens {
            Some(path) => Auth::from_file(path, rate)?,
            None => Auth::open(),
        };
        let d = UploadLimits::default();
        let limits = UploadLimits {
            file_bytes: args.upload_file_limit.unwrap_or(d.file_bytes),
            total_bytes: args.upload_limit.unwrap_or(d.total_bytes),
            files: d.files,
            patches: args.max_upload_patches.unwrap_or(d.patches),
        };
        let mut cfg = JobsConfig::in_bundles(bundles);
        match args.jobs.unwrap_or_default() {
            crate::slurm::JobsSetting::Local(n) => cfg.workers = n,
            crate::slurm::JobsSetting::Slurm => {
                let slurm =
                    crate::slurm::SlurmConfig::new(args.slurm_shards, args.slurm_args.as_deref())?;
                tracing::info!("{}", slurm.describe());
                cfg.engine = crate::jobs::Engine::Slurm(slurm);
            }
        }
        cfg.threads = args.job_threads.unwrap_or(cfg.threads);
        cfg.queue = args.job_queue.unwrap_or(cfg.queue);
        cfg.memory = args.job_memory;
        cfg.per_owner = cfg.per_owner.min(cfg.queue);
        if cfg.engine != crate::jobs::Engine::Local {
            // Slurm queues and runs the jobs; a worker only submits and follows one.
            cfg.workers = cfg.queue;
        }
        let budget = Arc::new(MemoryBudget::new(args.memory_budget));
        {
            // A prepared scene holds its radial terms: charged, and others evicted beyond
            // the budget, as after a first translucency change.
            // Held weakly: the state holds the hook.
            let (weak, budget) = (state.downgrade(), budget.clone());
            state.on_prepared(Arc::new(move |id: &str| {
                let Some(state) = weak.upgrade() else {
                    return;
                };
                if let Some(scene) = state.scene(id) {
                    budget.charge(id, "host", host_bytes(&scene));
                    evict(&state, &budget, id);
                }
            }));
        }
        let on_bundle = serve_bundle(state.clone(), budget.clone());
        let (jobs, notes) = Jobs::start(cfg, on_bundle.clone())?;
        for n in notes {
            tracing::warn!("{n}");
        }
        Ok(Team {
            auth: Arc::new(auth),
            jobs,
            budget,
            limits,
            state,
            bundles: bundles.to_path_buf(),
            reloading: Default::default(),
            reserved: Default::default(),
            on_bundle,
        })
    }

    /// One look at the shared bundles folder and tokens file (see `docs/team.md`, "Several
    /// servers over one folder"): bundles that appeared, were replaced or were removed
    /// ([`AppState::rescan`]; each opened as a finished job's bundle is, and charged to the
    /// memory budget), leaving alone the scenes this server's jobs are writing; then the
    /// tokens file, read again if it changed ([`Auth::reload_if_changed`]). Blocking.
    pub fn rescan(&self) {
        let jobs = self.jobs.clone();
        let skip = move |id: &str| jobs.busy_scene(id).is_some();
        match self.state.rescan(&self.bundles, &skip, &*self.on_bundle) {
            Ok(done) => {
                for id in &done.removed {
                    self.budget.forget(id);
                }
            }
            Err(e) => tracing::warn!("cannot rescan {}: {e}", self.bundles.display()),
        }
        match self.auth.reload_if_changed() {
            Some(Ok(summary)) => tracing::info!("the tokens file changed: {summary}"),
            Some(Err(e)) => tracing::error!(
                "the tokens file changed but does not read; keeping the tokens it had: {e:#}"
            ),
            None => {}
        }
    }

    /// Runs [`Team::rescan`] every `period` on a thread of its own until the server
    /// begins to shut down.
    pub fn watch_folder(&self, period: Duration) -> std::io::Result<std::thread::JoinHandle<()>> {
        let team = self.clone();
        let stop = self.state.shutdown_watch();
        std::thread::Builder::new()
            .name("bundle-rescan".into())
            .spawn(move || {
                loop {
                    std::thread::sleep(period);
                    if *stop.borrow() {
                        return;
                    }
                    team.rescan();
                }
            })
    }

    /// The start-up log line about access.
    pub fn describe(&self) -> String {
        let mut s = if self.auth.enabled() {
            format!("access control on: {}", self.auth.summary())
        } else {
            "no tokens configured: every route is open to this machine only (loopback); \
             give --tokens FILE to serve a network"
                .to_string()
        };
        if let Some(b) = self.budget.limit() {
            s.push_str(&format!(
                "; memory budget {:.1} MiB",
                b as f64 / (1 << 20) as f64
            ));
        }
        s
    }

    /// Reserves `id` for an upload: 409 unless it is free and no other upload holds it. The
    /// check and the hold are one step, so two uploads of one id cannot both pass while
    /// their files are checked (which takes a while) and then both be queued.
    pub fn reserve(&self, id: &str) -> Result<Reservation, AppError> {
        let mut held = self.reserved.lock().unwrap_or_else(|e| e.into_inner());
        if held.contains(id) {
            return Err(AppError::new(
                StatusCode::CONFLICT,
                "conflict",
                format!(
                    "another upload of scene {id:?} is being accepted; upload under another id"
                ),
            ));
        }
        self.check_scene_free(id)?;
        held.insert(id.to_string());
        Ok(Reservation {
            set: self.reserved.clone(),
            id: id.to_string(),
        })
    }

    /// 409 unless `id` is free for a new scene.
    pub fn check_scene_free(&self, id: &str) -> Result<(), AppError> {
        let conflict = |m: String| AppError::new(StatusCode::CONFLICT, "conflict", m);
        if let Some(s) = self.state.scene_state(id) {
            return Err(conflict(format!(
                "scene {id:?} already exists ({}); an admin can DELETE /api/v1/scenes/{id} \
                 first, or upload under another id",
                s.as_str()
            )));
        }
        if self.bundles.join(id).exists() {
            return Err(conflict(format!(
                "the bundles folder already holds {id:?}; upload under another id"
            )));
        }
        if let Some(job) = self.jobs.busy_scene(id) {
            return Err(conflict(format!(
                "job {job} is already making scene {id:?}"
            )));
        }
        Ok(())
    }

    /// Makes scene `id` resident (reopening it if evicted) and charges it to the budget.
    async fn make_resident(&self, id: &str) -> Result<(), AppError> {
        // Only an evicted scene needs the reload lock; a lock per id asked for would let
        // requests for made-up ids grow the map without bound.
        match self.state.scene_state(id) {
            Some(SceneState::Evicted(_)) => {}
            Some(SceneState::Ready(scene)) => {
                self.budget.charge(id, "host", host_bytes(&scene));
                return Ok(());
            }
            _ => return Ok(()),
        }
        let lock = {
            let mut map = self.reloading.lock().unwrap_or_else(|e| e.into_inner());
            map.entry(id.to_string()).or_default().clone()
        };
        let _held = lock.lock().await;
        match self.state.scene_state(id) {
            Some(SceneState::Evicted(e)) => {
                let dir = e.dir.clone();
                let sid = id.to_string();
                let resources = self.state.resources().clone();
                let t = std::time::Instant::now();
                let opened = tokio::task::spawn_blocking(move || {
                    // Verified when first opened; the folder is replaced only by a rename.
                    Scene::open_checked(
                        sid,
                        &dir,
                        &resources,
                        OpenOptions {
                            verify_checksums: false,
                        },
                    )
                })
                .await
                .map_err(|e| AppError::internal(format!("the reload task failed: {e}")))?;
                match opened {
                    Ok(scene) => {
                        tracing::info!(
                            scene = %id,
                            "reopened after eviction in {:.1} ms",
                            t.elapsed().as_secs_f64() * 1e3
                        );
                        let bytes = host_bytes(&scene);
                        self.state.insert_ready(scene);
                        self.budget.charge(id, "host", bytes);
                    }
                    Err(err) => {
                        // Clients see the scene's folder, not the server's path to it.
                        let msg = crate::jobs::strip_dir(
                            &format!("cannot reopen the evicted bundle: {err}"),
                            &self.bundles,
                        );
                        self.state.set_failed(id, msg.clone());
                        return Err(AppError::not_found(format!(
                            "scene {id:?} is not served: {msg}"
                        )));
                    }
                }
            }
            Some(SceneState::Ready(scene)) => {
                self.budget.charge(id, "host", host_bytes(&scene));
            }
            _ => {}
        }
        Ok(())
    }
}

/// What serves a bundle that is in place: open it ([`AppState::load_one`], swapping out
/// the scene it replaces), charge it to the budget and evict beyond it.
fn serve_bundle(state: AppState, budget: Arc<MemoryBudget>) -> crate::jobs::OnDone {
    Arc::new(move |id: &str, dir: &Path| {
        state.load_one(id, dir);
        if let Some(scene) = state.scene(id) {
            budget.charge(id, "host", host_bytes(&scene));
            evict(&state, &budget, id);
        }
    })
}

/// Evicts what the budget says, keeping `keep`.
fn evict(state: &AppState, budget: &MemoryBudget, keep: &str) {
    for victim in budget.victims(keep) {
        if let Some(SceneState::Ready(scene)) = state.scene_state(&victim) {
            let summary = crate::routes::summary(&scene);
            // A sequence reopens from its folder, not from frame 0's bundle.
            let dir = scene
                .sequence
                .as_ref()
                .map_or_else(|| scene.bundle.dir().to_path_buf(), |s| s.dir.clone());
            state.set_evicted(victim.clone(), Arc::new(EvictedScene { dir, summary }));
            tracing::info!(scene = %victim, "evicted to stay within the memory budget");
        }
    }
}

/// Bytes scene `scene` holds on the host: the mapped bundle, the shadow-ray BVH (estimated
/// at twice its triangles), centroids and normals, the mesh JSON once made, and the S
/// matrix and materials of the cached override set.
pub fn host_bytes(scene: &Scene) -> u64 {
    if let Some(seq) = &scene.sequence {
        let mut seen = std::collections::HashSet::new();
        return seq
            .frames
            .iter()
            .filter(|f| seen.insert(Arc::as_ptr(f)))
            .map(|f| host_bytes(f))
            .sum();
    }
    let b = &scene.bundle;
    let occluder = b.manifest().occluder_count * 36 * 2;
    let patches = b.manifest().patch_count * 24;
    let mesh = scene.mesh_json.get().map_or(0, |m| m.len() as u64);
    let materials = scene.material_cache_bytes();
    b.total_bytes() + occluder + patches + mesh + materials
}

/// The scene id of a request the residency middleware looks after: `GET`/`POST` under
/// `/api/v1/scenes/{id}`.
fn scene_of(method: &Method, path: &str) -> Option<String> {
    if *method == Method::DELETE {
        return None;
    }
    let rest = path.strip_prefix("/api/v1/scenes/")?;
    let id = rest.split('/').next()?;
    check_scene_id(id).ok()?;
    Some(id.to_string())
}

/// Unpins a scene when the request ends (also when its future is dropped), charging what
/// its caches grew to and evicting beyond the budget.
struct Pin {
    team: Team,
    id: String,
}

impl Drop for Pin {
    fn drop(&mut self) {
        self.team.budget.unpin(&self.id);
        if let Some(scene) = self.team.state.scene(&self.id) {
            self.team
                .budget
                .charge(&self.id, "host", host_bytes(&scene));
        }
        evict(&self.team.state, &self.team.budget, &self.id);
    }
}

async fn residency(State(team): State<Team>, req: Request, next: Next) -> Response {
    let Some(id) = scene_of(req.method(), req.uri().path()) else {
        return next.run(req).await;
    };
    // Unknown ids (404 from the route) are never accounted: the budget's table holds only
    // scenes that exist.
    if team.budget.limit().is_none() || team.state.scene_state(&id).is_none() {
        team.state.prepare_on_request(&id);
        return next.run(req).await;
    }
    if let Err(e) = team.make_resident(&id).await {
        return e.into_response();
    }
    team.state.prepare_on_request(&id);
    team.budget.pin(&id);
    let _pin = Pin {
        team: team.clone(),
        id: id.clone(),
    };
    evict(&team.state, &team.budget, &id);
    next.run(req).await
}

/// The routes this module adds; uploads take bodies up to `body_limit` bytes.
fn table(body_limit: usize) -> RouteTable<Team> {
    RouteTable::new()
        .add_with(Method::POST, "/api/v1/scenes", upload, |m| {
            m.layer(DefaultBodyLimit::max(body_limit))
        })
        .delete("/api/v1/scenes/{id}", delete_scene)
        .post("/api/v1/scenes/{id}/resimulate", resimulate)
        .get("/api/v1/jobs", list_jobs)
        .get("/api/v1/jobs/{id}", get_job)
        .delete("/api/v1/jobs/{id}", cancel_job)
        .get("/api/v1/jobs/{id}/events", job_events)
        .get("/api/v1/whoami", whoami)
}

/// `(method, path)` of the routes this module adds (what [`app`] adds to
/// [`crate::routes::routes`]).
pub fn routes() -> Vec<(Method, &'static str)> {
    table(0).finish().1
}

/// The whole API: [`crate::router`] and this module's routes, behind the residency and
/// access middlewares.
pub fn app(state: AppState, team: Team) -> Router {
    let body_limit = (team.limits.total_bytes as usize).saturating_add(1 << 20);
    let ours = table(body_limit).finish().0.with_state(team.clone());
    crate::router(state)
        .merge(ours)
        .layer(middleware::from_fn_with_state(team.clone(), residency))
        .layer(middleware::from_fn_with_state(
            team.auth.clone(),
            crate::auth::middleware,
        ))
}

/// `POST /api/v1/scenes`: an upload becomes a precompute job ([`crate::upload::accept`]).
#[utoipa::path(
    post,
    path = "/api/v1/scenes",
    tag = "team",
    summary = "Upload a scene; it becomes a precompute job.",
    description = "The scene file and its meshes as `multipart/form-data` (docs/team.md). \
                   The job's progress is at `Location` and its `/events`.",
    request_body(content = crate::schema::UploadForm, content_type = "multipart/form-data"),
    responses(
        (status = 202, description = "The job, queued.", body = crate::jobs::JobRecord,
         headers(("Location" = String, description = "`/api/v1/jobs/{id}` of the job."))),
        (status = 400, description = "`bad_request` or `invalid`: a bad form, scene file, mesh or id (the message names it).", body = ErrorBody),
        (status = 409, description = "`conflict`: the scene id is taken (served, in the bundles folder, or being made).", body = ErrorBody),
        (status = 413, description = "`payload_too_large`: over the upload limits.", body = ErrorBody),
        (status = 415, description = "`unsupported_media_type`: not `multipart/form-data`.", body = ErrorBody),
        (status = 429, description = "`queue_full`: the job queue (or this token's share of it) is full; with tokens also `rate_limited`.", body = ErrorBody),
        (status = 503, description = "`shutting_down`: the server is stopping.", body = ErrorBody),
    )
)]
pub(crate) async fn upload(
    State(team): State<Team>,
    identity: Option<Extension<Identity>>,
    form: Result<axum::extract::Multipart, axum::extract::multipart::MultipartRejection>,
) -> Result<Response, AppError> {
    crate::upload::accept(
        &team.jobs,
        team.limits,
        |id| team.reserve(id),
        identity,
        form,
    )
    .await
}

/// The body of `POST /api/v1/scenes/{id}/resimulate`.
#[derive(Debug, serde::Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(crate) struct ResimulateRequest {
    /// New media by object name: each a `simulated` material.
    materials: std::collections::BTreeMap<String, translux_proto::scene::Material>,
}

/// `POST /api/v1/scenes/{id}/resimulate`: the named simulated objects walk again in their
/// new media ([`translux_precompute::resimulate`]) as a job; the bundle is rewritten in
/// place and served again when it is done. What the job would refuse (no such object, not
/// simulated, an invalid medium) is a 400 here, before anything is queued.
#[utoipa::path(
    post,
    path = "/api/v1/scenes/{id}/resimulate",
    tag = "team",
    summary = "Walk a scene's simulated objects again in new media (a job).",
    description = "The bundle is rewritten in place and served again when the job is done; \
                   an absorption-only change needs no job (relight with `materials`).",
    params(SceneIdParam),
    request_body(content = ResimulateRequest, content_type = "application/json"),
    responses(
        (status = 202, description = "The job, queued.", body = crate::jobs::JobRecord,
         headers(("Location" = String, description = "`/api/v1/jobs/{id}` of the job."))),
        (status = 400, description = "`bad_request`: not a resimulate request; `invalid`: no such object, not simulated, an invalid medium, an animated scene.", body = ErrorBody),
        (status = 404, description = "`not_found`: no such scene.", body = ErrorBody),
        (status = 409, description = "`conflict`: a job is already making this scene.", body = ErrorBody),
        (status = 429, description = "`queue_full`: the job queue is full; with tokens also `rate_limited`.", body = ErrorBody),
        (status = 503, description = "`loading` or `shutting_down`.", body = ErrorBody),
    )
)]
pub(crate) async fn resimulate(
    State(team): State<Team>,
    crate::extract::SceneId(id): crate::extract::SceneId,
    identity: Option<Extension<Identity>>,
    body: Result<crate::extract::JsonBody<ResimulateRequest>, AppError>,
) -> Result<Response, AppError> {
    let scene = team.state.lookup(&id)?;
    if scene.sequence.is_some() {
        return Err(AppError::invalid(format!(
            "scene {id:?} is animated ({} frames, one bundle each): re-simulate it by \
             precomputing its scene file again with the new medium (translux-precompute keeps \
             what did not change)",
            scene.frame_count()
        )));
    }
    let crate::extract::JsonBody(req) = body?;
    let changes: Vec<_> = req.materials.into_iter().collect();
    translux_precompute::resimulate::check_changes(scene.bundle.manifest(), &changes)
        .map_err(AppError::invalid)?;
    if !team.bundles.join(&id).join("manifest.json").is_file() {
        return Err(AppError::invalid(format!(
            "scene {id:?} is not a bundle of this server's bundles folder"
        )));
    }
    let work_limit = team.state.params().work_limit(&identity);
    let owner = identity.map_or_else(|| "local".to_string(), |Extension(i)| i.name.to_string());
    let record = team.jobs.submit(crate::jobs::JobSpec {
        id: Jobs::new_id(),
        scene: id,
        owner,
        scene_file: PathBuf::new(),
        patches: None,
        max_edge: None,
        resimulate: Some(changes),
        work_limit: Some(work_limit),
    })?;
    let mut r = (StatusCode::ACCEPTED, Json(&record)).into_response();
    if let Ok(v) = axum::http::HeaderValue::from_str(&format!("/api/v1/jobs/{}", record.id)) {
        r.headers_mut().insert(axum::http::header::LOCATION, v);
    }
    Ok(r)
}

/// Whether `who` may see job `r`: its owner, or an admin.
fn visible(r: &JobRecord, who: &Option<Extension<Identity>>) -> bool {
    match who {
        Some(Extension(i)) => i.role == Some(Role::Admin) || *i.name == *r.owner,
        None => true,
    }
}

fn job_or_404(
    team: &Team,
    id: &str,
    who: &Option<Extension<Identity>>,
) -> Result<JobRecord, AppError> {
    let missing = || AppError::not_found(format!("no job {id:?}"));
    if !Jobs::valid_id(id) {
        return Err(missing());
    }
    let r = team
        .jobs
        .get(id)
        .or_else(|| crate::jobs::read_record(&team.jobs.config().jobs_dir, id))
        .ok_or_else(missing)?;
    if !visible(&r, who) {
        return Err(missing());
    }
    Ok(r)
}

/// `GET /api/v1/jobs`.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct JobList {
    /// Newest first.
    #[schema(value_type = Vec<crate::jobs::JobRecord>)]
    pub jobs: Vec<JobRecord>,
}

/// Precompute jobs, newest first: your own (an admin sees every job).
#[utoipa::path(
    get,
    path = "/api/v1/jobs",
    tag = "team",
    responses((status = 200, description = "The jobs.", body = JobList))
)]
pub(crate) async fn list_jobs(
    State(team): State<Team>,
    who: Option<Extension<Identity>>,
) -> Json<JobList> {
    let mut jobs = team.jobs.list();
    // Servers over one bundles folder share its records: the others' jobs too.
    let ours: std::collections::HashSet<String> = jobs.iter().map(|r| r.id.clone()).collect();
    let jobs_dir = team.jobs.config().jobs_dir.clone();
    let theirs = tokio::task::spawn_blocking(move || crate::jobs::read_records(&jobs_dir))
        .await
        .unwrap_or_default();
    jobs.extend(theirs.into_iter().filter(|r| !ours.contains(&r.id)));
    jobs.retain(|r| visible(r, &who));
    jobs.sort_by(|a, b| b.id.cmp(&a.id));
    Json(JobList { jobs })
}

/// `{id}` of a job route.
#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Path)]
#[allow(dead_code)]
pub(crate) struct JobIdParam {
    /// The job id: `j` and 20 hex digits.
    id: String,
}

/// One precompute job's record.
#[utoipa::path(
    get,
    path = "/api/v1/jobs/{id}",
    tag = "team",
    params(JobIdParam),
    responses(
        (status = 200, description = "The job.", body = crate::jobs::JobRecord),
        (status = 404, description = "`not_found`: no such job, or another token's.", body = ErrorBody),
    )
)]
pub(crate) async fn get_job(
    State(team): State<Team>,
    UrlPath(id): UrlPath<String>,
    who: Option<Extension<Identity>>,
) -> Result<Json<JobRecord>, AppError> {
    Ok(Json(job_or_404(&team, &id, &who)?))
}

/// Cancel a precompute job, queued or running; answers its record.
#[utoipa::path(
    delete,
    path = "/api/v1/jobs/{id}",
    tag = "team",
    params(JobIdParam),
    responses(
        (status = 200, description = "The job, cancelled (or as it ended).", body = crate::jobs::JobRecord),
        (status = 404, description = "`not_found`: no such job, or another token's.", body = ErrorBody),
        (status = 409, description = "`conflict`: the job runs on another server over the same bundles folder; cancel it there.", body = ErrorBody),
    )
)]
pub(crate) async fn cancel_job(
    State(team): State<Team>,
    UrlPath(id): UrlPath<String>,
    who: Option<Extension<Identity>>,
) -> Result<Json<JobRecord>, AppError> {
    let on_disk = job_or_404(&team, &id, &who)?;
    match team.jobs.cancel(&id) {
        Some(r) => Ok(Json(r)),
        None if on_disk.state.is_final() => Ok(Json(on_disk)),
        None => Err(AppError::new(
            StatusCode::CONFLICT,
            "conflict",
            format!("job {id} runs on another server over this bundles folder; cancel it there"),
        )),
    }
}

/// `GET /api/v1/jobs/{id}/events`: an SSE stream; each event's data is the job record,
/// named `progress` while the job is queued or running and by the final state at the end.
#[utoipa::path(
    get,
    path = "/api/v1/jobs/{id}/events",
    tag = "team",
    summary = "Server-Sent Events of a job: `progress`, then `done`, `failed` or `cancelled`.",
    description = "Each event's `data` is the job record (JSON); the stream ends after the \
                   final event. Comments keep the connection alive every 15 s.",
    params(JobIdParam),
    responses(
        (status = 200, description = "The event stream.", body = String, content_type = "text/event-stream"),
        (status = 404, description = "`not_found`: no such job, or another token's.", body = ErrorBody),
    )
)]
pub(crate) async fn job_events(
    State(team): State<Team>,
    UrlPath(id): UrlPath<String>,
    who: Option<Extension<Identity>>,
) -> Result<Response, AppError> {
    let on_disk = job_or_404(&team, &id, &who)?;
    let rx = match team.jobs.watch(&id) {
        Some(rx) => rx,
        None => follow_record(team.jobs.config().jobs_dir.clone(), on_disk),
    };
    // (receiver, whether the first event was sent, finished)
    let stream =
        futures_util::stream::unfold((rx, false, false), |(mut rx, started, ended)| async move {
            if ended {
                return None;
            }
            if started && rx.changed().await.is_err() {
                return None;
            }
            let r = rx.borrow_and_update().clone();
            let name = if r.state.is_final() {
                serde_json::to_value(r.state)
                    .ok()
                    .and_then(|v| v.as_str().map(str::to_string))
                    .unwrap_or_else(|| "done".into())
            } else {
                "progress".to_string()
            };
            let event = Event::default()
                .event(name)
                .json_data(&r)
                .unwrap_or_else(|_| Event::default().comment("unserialisable record"));
            let end = r.state.is_final();
            Some((Ok::<_, std::convert::Infallible>(event), (rx, true, end)))
        });
    Ok(Sse::new(stream)
        .keep_alive(KeepAlive::new().interval(Duration::from_secs(15)))
        .into_response())
}

/// A receiver of the record of a job that another server over the same folder runs: its
/// file is read again every second until it is final or no one listens. Another server
/// writes its record at every change of state, not at every percent.
fn follow_record(jobs_dir: PathBuf, first: JobRecord) -> tokio::sync::watch::Receiver<JobRecord> {
    let (tx, rx) = tokio::sync::watch::channel(first);
    tokio::spawn(async move {
        while !tx.is_closed() && !tx.borrow().state.is_final() {
            tokio::time::sleep(Duration::from_secs(1)).await;
            let (dir, id) = (jobs_dir.clone(), tx.borrow().id.clone());
            let read = tokio::task::spawn_blocking(move || crate::jobs::read_record(&dir, &id));
            if let Ok(Some(r)) = read.await {
                tx.send_if_modified(|old| {
                    let changed = *old != r;
                    *old = r;
                    changed
                });
            }
        }
    });
    rx
}

/// `DELETE /api/v1/scenes/{id}` (admin): stops serving the scene and deletes its bundle
/// folder (renamed aside first, so the id is free at once). Requests already running on it
/// finish with the data they have mapped.
#[utoipa::path(
    delete,
    path = "/api/v1/scenes/{id}",
    tag = "team",
    summary = "Stop serving a scene and delete its bundle folder.",
    params(SceneIdParam),
    responses(
        (status = 200, description = "The scene is gone.", body = SceneDeleted),
        (status = 404, description = "`not_found`: no such scene.", body = ErrorBody),
        (status = 409, description = "`conflict`: a job is making this scene; cancel it first.", body = ErrorBody),
    )
)]
pub(crate) async fn delete_scene(
    State(team): State<Team>,
    UrlPath(id): UrlPath<String>,
) -> Result<Json<SceneDeleted>, AppError> {
    check_scene_id(&id).map_err(|_| AppError::not_found(format!("no scene {id:?}")))?;
    if let Some(job) = team.jobs.busy_scene(&id) {
        return Err(AppError::new(
            StatusCode::CONFLICT,
            "conflict",
            format!(
                "job {job} is making scene {id:?}; cancel it first (DELETE /api/v1/jobs/{job})"
            ),
        ));
    }
    let old = team
        .state
        .remove(&id)
        .ok_or_else(|| AppError::not_found(format!("no scene {id:?}")))?;
    team.budget.forget(&id);
    let dir = team.bundles.join(&id);
    let from_here = match &old {
        SceneState::Ready(s) => {
            s.sequence
                .as_ref()
                .map_or_else(|| s.bundle.dir(), |q| q.dir.as_path())
                == dir.as_path()
        }
        SceneState::Evicted(e) => e.dir == dir,
        _ => true,
    };
    let mut deleted = false;
    if from_here && dir.is_dir() {
        let aside = team
            .bundles
            .join(format!(".{id}.deleted-{}", crate::jobs::Jobs::new_id()));
        std::fs::rename(&dir, &aside)
            .map_err(|e| AppError::internal(format!("cannot move {id:?} aside: {e}")))?;
        tokio::task::spawn_blocking(move || std::fs::remove_dir_all(aside))
            .await
            .map_err(|e| AppError::internal(format!("the delete task failed: {e}")))?
            .map_err(|e| AppError::internal(format!("cannot delete the bundle: {e}")))?;
        deleted = true;
    }
    tracing::info!(scene = %id, deleted, "scene removed");
    Ok(Json(SceneDeleted {
        deleted,
        id,
        unloaded: true,
    }))
}

/// `DELETE /api/v1/scenes/{id}`.
// Fields in the order `json!` wrote them before (alphabetical).
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct SceneDeleted {
    /// Whether its bundle folder was deleted (a bundle outside the bundles folder is only
    /// unloaded).
    pub deleted: bool,
    pub id: String,
    /// Always `true`: the scene is no longer served.
    pub unloaded: bool,
}

/// `GET /api/v1/whoami`.
// Fields in the order `json!` wrote them before (alphabetical).
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct WhoAmI {
    /// Whether access control is on (`--tokens`).
    pub auth: bool,
    /// The token's name (`local` without tokens).
    pub name: String,
    /// `viewer`, `editor` or `admin` (`admin` without tokens).
    pub role: Option<&'static str>,
}

/// The token's name and role, and whether access control is on.
#[utoipa::path(
    get,
    path = "/api/v1/whoami",
    tag = "team",
    responses((status = 200, description = "Who the request is from.", body = WhoAmI))
)]
pub(crate) async fn whoami(
    State(team): State<Team>,
    who: Option<Extension<Identity>>,
) -> Json<WhoAmI> {
    let (name, role) = match who {
        Some(Extension(i)) => (i.name.to_string(), i.role.map(Role::as_str)),
        None => (crate::auth::LOCAL_NAME.to_string(), Some("admin")),
    };
    Json(WhoAmI {
        auth: team.auth.enabled(),
        name,
        role,
    })
}
