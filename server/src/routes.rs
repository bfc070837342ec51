//! The HTTP API (axum): routes, handlers, and the middleware around them.
//!
//! Every route is registered through [`RouteTable`], which routes each handler under the
//! one method and path it records, so [`routes`] lists exactly what [`router`] serves (and
//! [`crate::team::routes`] what the team router adds). Each handler carries its OpenAPI
//! description (`#[utoipa::path]`); [`crate::openapi`] gathers them into the document served
//! at `/api/v1/openapi.json`, and its tests check that the document lists exactly the
//! routes of both tables.

use std::sync::Arc;
use std::time::Instant;

use axum::Router;
use axum::body::{Body, Bytes};
use axum::extract::{DefaultBodyLimit, MatchedPath, Request, State};
use axum::handler::Handler;
use axum::http::header::{CONTENT_TYPE, VARY};
use axum::http::{HeaderMap, HeaderValue, Method, Uri};
use axum::middleware::{self, Next};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{MethodFilter, MethodRouter};
use serde::{Deserialize, Serialize};
use translux_proto::api::{
    ErrorBody, GpuHealth, Mesh, MeshObject, Presets, RelightRequest, RelightResponse,
    RenderRequest, SceneDetail, SceneList, SceneObject, SceneSummary,
};

use crate::error::AppError;
use crate::extract::{
    BODY_LIMIT, ClientKey, Format, FrameQuery, JsonBody, SceneId, accept_picture, negotiate,
};
use crate::pool::{Done, Work};
use crate::schema::{ClientIdParam, FrameParam, SceneIdParam};
use crate::state::{AppState, Scene, SceneState};
use crate::ws;
use translux_engine::{picture, relight};

/// The viewer page served at `/`.
pub const INDEX_HTML: &str = include_str!("../../web/index.html");

/// The viewer's scripts and styles under `/web/` (the list lives beside them in `web/`).
#[path = "../../web/assets.rs"]
pub mod web_assets;

/// Builds a router whose every route is recorded: each handler is routed under exactly the
/// method and path written down (`on(method, handler)`, so a handler cannot answer a method
/// the table does not list), and a path given twice gets both methods.
#[derive(Debug)]
pub struct RouteTable<S> {
    router: Router<S>,
    routes: Vec<(Method, &'static str)>,
}

impl<S: Clone + Send + Sync + 'static> RouteTable<S> {
    pub(crate) fn new() -> Self {
        RouteTable {
            router: Router::new(),
            routes: Vec::new(),
        }
    }

    /// `handler` for `method path`, its method router passed through `wrap` (for layers:
    /// `wrap` must not add methods).
    pub(crate) fn add_with<H, T>(
        mut self,
        method: Method,
        path: &'static str,
        handler: H,
        wrap: impl FnOnce(MethodRouter<S>) -> MethodRouter<S>,
    ) -> Self
    where
        H: Handler<T, S>,
        T: 'static,
    {
        let filter = MethodFilter::try_from(method.clone())
            .unwrap_or_else(|e| panic!("{method} {path}: {e}"));
        self.routes.push((method, path));
        self.router = self
            .router
            .route(path, wrap(axum::routing::on(filter, handler)));
        self
    }

    pub(crate) fn get<H: Handler<T, S>, T: 'static>(self, path: &'static str, h: H) -> Self {
        self.add_with(Method::GET, path, h, |m| m)
    }

    pub(crate) fn post<H: Handler<T, S>, T: 'static>(self, path: &'static str, h: H) -> Self {
        self.add_with(Method::POST, path, h, |m| m)
    }

    pub(crate) fn delete<H: Handler<T, S>, T: 'static>(self, path: &'static str, h: H) -> Self {
        self.add_with(Method::DELETE, path, h, |m| m)
    }

    /// The router built so far, and `(method, path)` of each of its routes.
    pub(crate) fn finish(self) -> (Router<S>, Vec<(Method, &'static str)>) {
        (self.router, self.routes)
    }
}

/// Every route of the API.
fn table() -> RouteTable<AppState> {
    RouteTable::new()
        .get("/", index)
        .get("/healthz", healthz)
        .get("/metrics", metrics)
        .get("/api/v1/openapi.json", crate::openapi_document)
        .get("/api/v1/presets", presets)
        .get("/api/v1/scenes", list_scenes)
        .get("/api/v1/scenes/{id}", scene_detail)
        .get("/api/v1/scenes/{id}/mesh", scene_mesh)
        .post("/api/v1/scenes/{id}/relight", relight)
        .post("/api/v1/scenes/{id}/render", render)
        .get("/api/v1/scenes/{id}/stream", ws::stream)
        .get("/web/{*path}", web_file)
}

/// `(method, path template)` of every route [`router`] serves.
pub fn routes() -> Vec<(Method, &'static str)> {
    table().finish().1
}

/// The whole API over `state`, without the request log (see [`with_request_log`], which
/// `serve` puts around everything, the team routes and the access checks included).
pub fn router(state: AppState) -> Router {
    table()
        .finish()
        .0
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(DefaultBodyLimit::max(BODY_LIMIT))
        .with_state(state)
}

/// `app` with the request log and the latency histogram as its outermost layer, so every
/// route is counted — uploads, jobs, deletes — and every answer, the 401/403/429 of the
/// access layer too: operators of a shared box must see failed-login bursts and deletions.
pub fn with_request_log(app: Router, state: AppState) -> Router {
    app.layer(middleware::from_fn_with_state(state, log_request))
}

/// A pre-serialised JSON answer.
/// A manifest's `source` as clients see it: `builtin:…` and `upload:…` as they are, a scene
/// file by its name alone (the command line may have named it by the server's path).
fn public_source(source: &str) -> String {
    if source.starts_with("builtin:") || source.starts_with("upload:") {
        return source.to_string();
    }
    std::path::Path::new(source)
        .file_name()
        .map_or_else(|| source.to_string(), |f| f.to_string_lossy().into_owned())
}

fn json_bytes(bytes: impl Into<Body>) -> Response {
    (
        [(CONTENT_TYPE, HeaderValue::from_static("application/json"))],
        bytes.into(),
    )
        .into_response()
}

fn to_json<T: Serialize>(v: &T) -> Result<Response, AppError> {
    let bytes = serde_json::to_vec(v)
        .map_err(|e| AppError::internal(format!("cannot serialise the answer: {e}")))?;
    Ok(json_bytes(bytes))
}

fn find_scene(state: &AppState, id: &str) -> Result<Arc<Scene>, AppError> {
    state.lookup(id)
}

/// The viewer page.
#[utoipa::path(
    get,
    path = "/",
    tag = "viewer",
    responses((status = 200, description = "The browser viewer (docs/viewer.md).", body = String, content_type = "text/html"))
)]
pub(crate) async fn index() -> Html<&'static str> {
    Html(INDEX_HTML)
}

/// `GET /healthz`: the backend, each scene's state, memory and the queue.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct HealthReport {
    /// `ok` while the server answers.
    pub status: String,
    /// `cpu` or `gpu`.
    pub backend: String,
    pub gpu: GpuHealth,
    /// Ids of the scenes ready to serve.
    pub scenes: Vec<String>,
    /// Every scene found, ready or not.
    pub scene_states: Vec<SceneHealth>,
    pub memory: MemoryHealth,
    pub queue: QueueHealth,
    /// Open WebSocket streams.
    pub streams: i64,
}

/// One scene in [`HealthReport`].
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct SceneHealth {
    pub id: String,
    /// `loading`, `ready` or `failed`.
    pub state: String,
    /// Why it failed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Bytes of its bundle (ready scenes).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bundle_bytes: Option<u64>,
}

/// Memory in [`HealthReport`].
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct MemoryHealth {
    /// Resident set size of the process (absent where the OS does not say).
    pub rss_bytes: Option<u64>,
    /// Bytes of the bundles mapped by ready scenes (counted in RSS only once touched).
    pub mapped_bundle_bytes: u64,
}

/// The worker pool in [`HealthReport`].
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct QueueHealth {
    pub workers: usize,
    /// Relights waiting now.
    pub depth: usize,
    pub capacity: usize,
    pub max_batch: usize,
    pub deadline_ms: u64,
}

fn health(state: &AppState) -> HealthReport {
    let p = state.params();
    HealthReport {
        status: "ok".into(),
        backend: state.backend().to_string(),
        gpu: state.compute_backend().gpu_health(),
        scenes: state.ids(),
        scene_states: state
            .scene_states()
            .into_iter()
            .map(|(id, s)| SceneHealth {
                id,
                state: s.as_str().to_string(),
                error: match &s {
                    SceneState::Failed(e) => Some(e.clone()),
                    _ => None,
                },
                bundle_bytes: match &s {
                    SceneState::Ready(scene) => Some(scene.total_bytes()),
                    _ => None,
                },
            })
            .collect(),
        memory: MemoryHealth {
            rss_bytes: crate::metrics::resident_bytes(),
            mapped_bundle_bytes: state.mapped_bytes(),
        },
        queue: QueueHealth {
            workers: p.workers,
            depth: state.pool().queued(),
            capacity: p.queue,
            max_batch: p.max_batch,
            deadline_ms: p.deadline.as_millis() as u64,
        },
        streams: state.metrics().ws_connections.get(),
    }
}

/// Backend, GPU, scenes, memory and the queue.
///
/// Each scene's state is `loading`, `ready`, `failed` or `evicted`. Once the server has begun
/// to stop (SIGTERM) it answers 503 `shutting_down` instead, so that a load balancer's or an
/// orchestrator's health check takes it out of rotation (docker/haproxy.cfg).
#[utoipa::path(
    get,
    path = "/healthz",
    tag = "operations",
    responses(
        (status = 200, description = "The server's state.", body = HealthReport),
        (status = 503, description = "`shutting_down`: the server is stopping.", body = ErrorBody),
    )
)]
pub(crate) async fn healthz(State(state): State<AppState>) -> Result<Response, AppError> {
    if *state.shutdown_watch().borrow() {
        return Err(AppError::shutting_down(
            "the server is stopping: it finishes the requests it has accepted and takes no \
             new ones",
        ));
    }
    to_json(&health(&state))
}

/// `GET /metrics`: Prometheus text; the scene and memory gauges are read now.
#[utoipa::path(
    get,
    path = "/metrics",
    tag = "operations",
    summary = "Prometheus text exposition.",
    description = "Latency by route, queue depth, batch sizes, solver iterations, relights by \
                   outcome, memory; the scene and memory gauges are read at the request.",
    responses((status = 200, description = "Prometheus text format 0.0.4.", body = String,
               content_type = "text/plain; version=0.0.4; charset=utf-8"))
)]
pub(crate) async fn metrics(State(state): State<AppState>) -> Result<Response, AppError> {
    let m = state.metrics();
    for s in ["loading", "ready", "failed", "evicted"] {
        m.scenes.with_label_values(&[s]).set(0);
    }
    for (_, s) in state.scene_states() {
        m.scenes.with_label_values(&[s.as_str()]).inc();
    }
    m.resident_bytes
        .set(crate::metrics::resident_bytes().unwrap_or(0) as i64);
    m.mapped_bytes.set(state.mapped_bytes() as i64);
    m.gpu_bytes
        .set(state.compute_backend().gpu_health().bytes as i64);
    m.queue_depth.set(state.pool().queued() as i64);
    let text = m.render().map_err(AppError::internal)?;
    Ok((
        [(
            CONTENT_TYPE,
            HeaderValue::from_static("text/plain; version=0.0.4; charset=utf-8"),
        )],
        text,
    )
        .into_response())
}

/// `GET /api/v1/scenes`' entry for `scene`.
pub(crate) fn summary(scene: &Scene) -> SceneSummary {
    let m = scene.bundle.manifest();
    SceneSummary {
        id: scene.id.clone(),
        name: m.name.clone(),
        patches: m.patch_count,
        vertices: m.vertex_count,
        objects: m.objects.len(),
        frames: scene.frame_count(),
        fps: scene.sequence.as_ref().map(|s| s.fps),
    }
}

/// The named media materials may use, with their coefficients (the viewer's lists come
/// from here).
#[utoipa::path(
    get,
    path = "/api/v1/presets",
    tag = "scenes",
    responses((status = 200, description = "The presets.", body = Presets))
)]
pub(crate) async fn presets() -> Result<Response, AppError> {
    use translux_engine::profile;
    let dipole = translux_proto::scene::DIPOLE_PRESETS
        .iter()
        .filter_map(|&name| {
            profile::preset(name).map(|m| translux_proto::api::DipolePreset {
                name: name.to_string(),
                sigma_s_prime: m.sigma_s_prime,
                sigma_a: m.sigma_a,
                eta: m.eta,
            })
        })
        .collect();
    to_json(&Presets {
        dipole,
        default_eta: profile::DEFAULT_ETA,
        default_coat_eta: translux_engine::specular::DEFAULT_ETA,
    })
}

/// The scenes served (ready ones and those evicted by the memory budget).
#[utoipa::path(
    get,
    path = "/api/v1/scenes",
    tag = "scenes",
    responses((status = 200, description = "The scenes.", body = SceneList))
)]
pub(crate) async fn list_scenes(State(state): State<AppState>) -> Result<Response, AppError> {
    to_json(&SceneList {
        // Evicted scenes (memory budget) are listed too: their next request reopens them.
        scenes: state
            .scene_states()
            .into_iter()
            .filter_map(|(_, s)| match s {
                SceneState::Ready(s) => Some(summary(&s)),
                SceneState::Evicted(e) => Some(e.summary.clone()),
                _ => None,
            })
            .collect(),
    })
}

/// Counts, objects and their materials, default lights and camera, F statistics.
#[utoipa::path(
    get,
    path = "/api/v1/scenes/{id}",
    tag = "scenes",
    params(SceneIdParam, FrameParam),
    responses(
        (status = 200, description = "The scene (the frame asked for).", body = SceneDetail),
        (status = 400, description = "`bad_request`: a bad `frame`; `invalid`: a frame out of range.", body = ErrorBody),
        (status = 404, description = "`not_found`: no such scene, or one whose bundle failed to load (the message says why).", body = ErrorBody),
        (status = 503, description = "`loading`: the scene is still loading (`Retry-After: 1`).", body = ErrorBody),
    )
)]
pub(crate) async fn scene_detail(
    State(state): State<AppState>,
    SceneId(id): SceneId,
    FrameQuery(frame): FrameQuery,
) -> Result<Response, AppError> {
    let whole = find_scene(&state, &id)?;
    let scene = whole.frame(frame)?;
    let m = scene.bundle.manifest();
    to_json(&SceneDetail {
        id: scene.id.clone(),
        name: m.name.clone(),
        source: public_source(&m.source),
        created_by: m.created_by.clone(),
        unit_mm: m.unit_mm,
        patches: m.patch_count,
        vertices: m.vertex_count,
        triangles: scene.bundle.triangle_vertices().len() as u64,
        occluders: m.occluder_count,
        objects: m
            .objects
            .iter()
            .map(|o| SceneObject {
                name: o.name.clone(),
                material: o.material.clone(),
                albedo: o.albedo,
                first_patch: o.first_patch,
                patch_count: o.patch_count,
                absorption: absorption_of(o),
            })
            .collect(),
        lights: m.lights.clone(),
        camera: m.camera,
        form_factors: m.form_factors.clone(),
        stages: m.stages.clone(),
        bundle_bytes: whole.total_bytes(),
        frames: whole.frame_count(),
        fps: whole.sequence.as_ref().map(|s| s.fps),
        frame: frame.unwrap_or(0),
        translucency: scene.translucency(),
    })
}

/// A simulated object's absorption range: its medium's σa and the lowest σa its stored walks
/// serve (the floor `simulated::check_override` applies).
fn absorption_of(
    o: &translux_proto::bundle::ObjectInfo,
) -> Option<translux_proto::api::Absorption> {
    let medium = translux_engine::simulated::SimMedium::of(&o.material)?;
    Some(translux_proto::api::Absorption {
        sigma_a: medium.sigma_a,
        sigma_a_min: medium.floor(),
    })
}

/// The viewer mesh as flat JSON arrays; triangle k is patch k, so an object's triangles are
/// its patch range.
fn mesh_of(scene: &Scene) -> Mesh {
    let b = &scene.bundle;
    Mesh {
        positions: b.vertex_positions().iter().flatten().copied().collect(),
        normals: b.vertex_normals().iter().flatten().copied().collect(),
        indices: b.triangle_vertices().iter().flatten().copied().collect(),
        objects: b
            .manifest()
            .objects
            .iter()
            .map(|o| MeshObject {
                name: o.name.clone(),
                first_triangle: o.first_patch,
                triangle_count: o.patch_count,
            })
            .collect(),
    }
}

/// The viewer mesh: flat positions, normals, indices and each object's triangle range.
#[utoipa::path(
    get,
    path = "/api/v1/scenes/{id}/mesh",
    tag = "scenes",
    params(SceneIdParam, FrameParam),
    responses(
        (status = 200, description = "The mesh, JSON only.", body = Mesh),
        (status = 400, description = "`bad_request`: a bad `frame`; `invalid`: a frame out of range.", body = ErrorBody),
        (status = 404, description = "`not_found`: no such scene.", body = ErrorBody),
        (status = 503, description = "`loading`: the scene is still loading (`Retry-After: 1`).", body = ErrorBody),
    )
)]
pub(crate) async fn scene_mesh(
    State(state): State<AppState>,
    SceneId(id): SceneId,
    FrameQuery(frame): FrameQuery,
) -> Result<Response, AppError> {
    let scene = find_scene(&state, &id)?.frame(frame)?;
    if let Some(bytes) = scene.mesh_json.get() {
        return Ok(json_bytes(bytes.clone()));
    }
    let bytes = tokio::task::spawn_blocking(move || -> Result<Bytes, AppError> {
        let bytes = serde_json::to_vec(&mesh_of(&scene))
            .map_err(|e| AppError::internal(format!("cannot serialise the mesh: {e}")))?;
        Ok(scene.mesh_json.get_or_init(|| Bytes::from(bytes)).clone())
    })
    .await
    .map_err(|e| AppError::internal(format!("the mesh task failed: {e}")))??;
    Ok(json_bytes(bytes))
}

/// Relight: per-vertex linear radiance B/π in the mesh's vertex order.
///
/// The answer's form follows `Accept`: `application/json` for the JSON form; otherwise
/// (`application/octet-stream`, `*/*`, none) n × 3 little-endian f32.
#[utoipa::path(
    post,
    path = "/api/v1/scenes/{id}/relight",
    tag = "scenes",
    params(SceneIdParam, ClientIdParam),
    request_body(content = RelightRequest, content_type = "application/json",
                 description = "Every field is optional: `{}` relights with the bundle's lights."),
    responses(
        (status = 200,
         description = "The radiance: JSON, or n × 3 little-endian f32 (`[r, g, b]` per vertex).",
         content(
             (RelightResponse = "application/json"),
             (crate::schema::Binary = "application/octet-stream"),
         ),
         headers(
             ("X-Vertex-Count" = u64, description = "Vertices in the answer."),
             ("Server-Timing" = String, description = "queue, direct, solve and total milliseconds."),
             ("X-Auto-Exposure" = f32, description = "With `\"direct_at\": \"pixel\"`: the automatic exposure (EV) of the whole answer."),
             ("Vary" = String, description = "`accept`."),
         )),
        (status = 400, description = "`bad_request`: the body is not a relight request (the message names the field); `invalid`: a value breaks a rule; `unsupported`: this bundle cannot do it.", body = ErrorBody),
        (status = 404, description = "`not_found`: no such scene.", body = ErrorBody),
        (status = 406, description = "`not_acceptable`: `Accept` allows neither form.", body = ErrorBody),
        (status = 413, description = "`payload_too_large`: the body is over 1 MiB.", body = ErrorBody),
        (status = 415, description = "`unsupported_media_type`: the body is not declared as JSON.", body = ErrorBody),
        (status = 422, description = "`work_limit`: the request's lamp walks ran past its role's limit.", body = ErrorBody),
        (status = 429, description = "`queue_full`: the relight queue is full (`Retry-After`); with tokens also `rate_limited`.", body = ErrorBody),
        (status = 503, description = "`loading`, `deadline_exceeded`, `shutting_down` or `cancelled`.", body = ErrorBody),
    )
)]
pub(crate) async fn relight(
    State(state): State<AppState>,
    SceneId(id): SceneId,
    ClientKey(client): ClientKey,
    identity: Option<axum::Extension<crate::auth::Identity>>,
    headers: HeaderMap,
    body: Result<JsonBody<RelightRequest>, AppError>,
) -> Result<Response, AppError> {
    let scene = find_scene(&state, &id)?;
    let format = negotiate(&headers)?;
    let JsonBody(req) = body?;
    let scene = scene.frame(req.frame)?;
    let plan = relight::RelightPlan {
        work_limit: Some(state.params().work_limit(&identity)),
        ..relight::plan(&scene, req)?
    };
    let answer = state
        .pool()
        .run(scene.engine(), Work::Relight(plan), client)
        .await?;
    let waited_ms = answer.waited.as_secs_f64() * 1e3;
    let out = match answer.result? {
        Done::Relight(out) => out,
        Done::Render(_) => return Err(AppError::internal("the pool answered a render")),
    };
    let s = &out.stats;
    tracing::info!(
        scene = %scene.id,
        components = s.components.as_str(),
        lights = s.lights,
        iterations = s.iterations,
        residual = format_args!("{:.2e}", s.residual),
        direct_ms = format_args!("{:.1}", s.direct_ms),
        solve_ms = format_args!("{:.1}", s.solve_ms),
        ms = format_args!("{:.1}", s.ms),
        queue_ms = format_args!("{waited_ms:.1}"),
        "relit"
    );
    let timing = format!(
        "queue;dur={waited_ms:.3}, direct;dur={:.3}, solve;dur={:.3}, total;dur={:.3}",
        s.direct_ms, s.solve_ms, s.ms
    );
    let vertex_count = out.radiance.len();
    let auto_exposure = out.stats.auto_exposure;
    let mut response = match format {
        Format::Json => to_json(&RelightResponse {
            vertex_count,
            radiance: out.radiance.iter().flatten().copied().collect(),
            stats: out.stats,
        })?,
        Format::Binary => {
            let mut bytes = Vec::with_capacity(vertex_count * 12);
            for v in out.radiance.iter().flatten() {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
            let mut r = Body::from(bytes).into_response();
            r.headers_mut().insert(
                CONTENT_TYPE,
                HeaderValue::from_static("application/octet-stream"),
            );
            r
        }
    };
    let h = response.headers_mut();
    h.insert(VARY, HeaderValue::from_static("accept"));
    h.insert("x-vertex-count", HeaderValue::from(vertex_count));
    if let Ok(v) = HeaderValue::from_str(&timing) {
        h.insert("server-timing", v);
    }
    // `"direct_at": "pixel"`: the whole answer's automatic exposure, for binary answers
    // too (their stats are only these headers).
    if let Some(ev) = auto_exposure
        && let Ok(v) = HeaderValue::from_str(&format!("{ev}"))
    {
        h.insert("x-auto-exposure", v);
    }
    Ok(response)
}

/// `POST /api/v1/scenes/{id}/render`: the relight request's fields plus a camera and the
/// picture's size, exposure (EV, or `auto`, the default: the viewer's rule on the relit
/// radiance) and tone curve; answers `image/png` with the EV used in `X-Exposure`, or, for
/// `Accept: image/x-exr`, a linear OpenEXR (see [`picture`]: `auto` leaves it unscaled and
/// `X-Exposure` is then 0). The relight runs through the same [`relight::plan`] /
/// [`relight::run`] as `/relight`.
#[utoipa::path(
    post,
    path = "/api/v1/scenes/{id}/render",
    tag = "scenes",
    summary = "Relight and render from a camera to a PNG, or a linear OpenEXR.",
    description = "The relight request's fields plus a camera, the picture's size, exposure \
                   (EV, or `auto`: the viewer's rule) and tone curve. The format follows \
                   `Accept`: `image/x-exr` for a linear OpenEXR (`auto` leaves it unscaled); \
                   otherwise (`image/png`, `image/*`, `*/*`, none) a PNG.",
    params(SceneIdParam, ClientIdParam),
    request_body(content = RenderRequest, content_type = "application/json",
                 description = "Every field is optional: `{}` renders the bundle's lights from its camera at 800 × 600."),
    responses(
        (status = 200,
         description = "The picture.",
         content(
             (crate::schema::Binary = "image/png"),
             (crate::schema::Binary = "image/x-exr"),
         ),
         headers(
             ("X-Exposure" = f32, description = "The EV used (0 for an `auto` OpenEXR, which is left unscaled)."),
             ("X-Vertex-Count" = u64, description = "Vertices relit."),
             ("Server-Timing" = String, description = "direct, solve, raster, encode and total milliseconds."),
             ("Vary" = String, description = "`accept`."),
         )),
        (status = 400, description = "`bad_request`: the body is not a render request; `invalid`: a value breaks a rule; `unsupported`: this bundle cannot do it.", body = ErrorBody),
        (status = 404, description = "`not_found`: no such scene.", body = ErrorBody),
        (status = 406, description = "`not_acceptable`: `Accept` allows neither picture format.", body = ErrorBody),
        (status = 413, description = "`payload_too_large`: the body is over 1 MiB.", body = ErrorBody),
        (status = 415, description = "`unsupported_media_type`: the body is not declared as JSON.", body = ErrorBody),
        (status = 422, description = "`work_limit`: the request's lamp walks ran past its role's limit.", body = ErrorBody),
        (status = 429, description = "`queue_full`: the relight queue is full (`Retry-After`); with tokens also `rate_limited`.", body = ErrorBody),
        (status = 503, description = "`loading`, `deadline_exceeded`, `shutting_down` or `cancelled`.", body = ErrorBody),
    )
)]
pub(crate) async fn render(
    State(state): State<AppState>,
    SceneId(id): SceneId,
    ClientKey(client): ClientKey,
    identity: Option<axum::Extension<crate::auth::Identity>>,
    headers: HeaderMap,
    body: Result<JsonBody<RenderRequest>, AppError>,
) -> Result<Response, AppError> {
    let scene = find_scene(&state, &id)?;
    let format = accept_picture(&headers)?;
    let JsonBody(req) = body?;
    let scene = scene.frame(req.frame)?;
    let mut plan = picture::RenderPlan {
        format,
        ..picture::plan(&scene, req)?
    };
    plan.relight.work_limit = Some(state.params().work_limit(&identity));
    let answer = state
        .pool()
        .run(scene.engine(), Work::Render(Box::new(plan)), client)
        .await?;
    let out = match answer.result? {
        Done::Render(out) => out,
        Done::Relight(_) => return Err(AppError::internal("the pool answered a relight")),
    };
    let s = &out.stats;
    tracing::info!(
        scene = %scene.id,
        components = s.components.as_str(),
        lights = s.lights,
        iterations = s.iterations,
        relight_ms = format_args!("{:.1}", s.ms),
        raster_ms = format_args!("{:.1}", out.raster_ms),
        encode_ms = format_args!("{:.1}", out.encode_ms),
        format = format.name(),
        bytes = out.bytes.len(),
        exposure = out.exposure,
        "rendered"
    );
    let timing = format!(
        "direct;dur={:.3}, solve;dur={:.3}, raster;dur={:.3}, encode;dur={:.3}, total;dur={:.3}",
        s.direct_ms, s.solve_ms, out.raster_ms, out.encode_ms, out.total_ms
    );
    let mut response = Body::from(out.bytes).into_response();
    let h = response.headers_mut();
    h.insert(CONTENT_TYPE, HeaderValue::from_static(format.media_type()));
    h.insert(VARY, HeaderValue::from_static("accept"));
    h.insert("x-vertex-count", HeaderValue::from(out.vertex_count));
    // The EV actually used, so a client that asked for `auto` (or nothing) can repeat the
    // picture with a fixed exposure, or show the number as the viewer does.
    if let Ok(v) = HeaderValue::from_str(&out.exposure.to_string()) {
        h.insert("x-exposure", v);
    }
    if let Ok(v) = HeaderValue::from_str(&timing) {
        h.insert("server-timing", v);
    }
    Ok(response)
}

/// The viewer's scripts and styles, embedded in the binary.
// Answered by `web_assets::serve`, whose file lives with the viewer's in web/.
#[utoipa::path(
    get,
    path = "/web/{path}",
    tag = "viewer",
    params(("path" = String, Path, description = "A file of the viewer, e.g. `viewer.js`.")),
    responses(
        (status = 200, description = "The file.", content(
            (String = "text/javascript; charset=utf-8"),
            (String = "text/css; charset=utf-8"),
        )),
        (status = 404, description = "`not_found`: no such file; the message lists them.", body = ErrorBody),
    )
)]
pub(crate) async fn web_file(path: axum::extract::Path<String>) -> Result<Response, AppError> {
    web_assets::serve(path).await
}

async fn not_found(method: Method, uri: Uri) -> AppError {
    AppError::not_found(format!("no route for {method} {}", uri.path()))
}

async fn method_not_allowed(method: Method, uri: Uri) -> AppError {
    AppError::method_not_allowed(format!("{method} is not allowed on {}", uri.path()))
}

/// One log line per request (errors at info, the rest at debug) and its latency in the
/// `translux_http_request_duration_seconds` histogram, by route template.
async fn log_request(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let method = req.method().clone();
    let path = req.uri().path().to_owned();
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map_or_else(|| "unmatched".to_string(), |m| m.as_str().to_string());
    let t = Instant::now();
    let response = next.run(req).await;
    let status = response.status();
    let elapsed = t.elapsed();
    state
        .metrics()
        .http_duration
        .with_label_values(&[route.as_str(), method_label(&method), status.as_str()])
        .observe(elapsed.as_secs_f64());
    let ms = elapsed.as_secs_f64() * 1e3;
    if status.is_client_error() || status.is_server_error() {
        tracing::info!(%method, %path, status = status.as_u16(), ms = format_args!("{ms:.1}"), "request");
    } else {
        tracing::debug!(%method, %path, status = status.as_u16(), ms = format_args!("{ms:.1}"), "request");
    }
    response
}

/// The `method` label of a request: a standard method's name, else `other`. Clients choose
/// the method string freely, and every distinct label value is a new series held forever,
/// so an unauthenticated client could otherwise grow `/metrics` without bound.
pub fn method_label(method: &Method) -> &'static str {
    const KNOWN: [Method; 9] = [
        Method::GET,
        Method::HEAD,
        Method::POST,
        Method::PUT,
        Method::DELETE,
        Method::PATCH,
        Method::OPTIONS,
        Method::CONNECT,
        Method::TRACE,
    ];
    KNOWN
        .iter()
        .find(|m| *m == method)
        .map_or("other", |m| m.as_str())
}

/// The routes that need no socket, through the router itself (`Router::oneshot`): no
/// listener, no HTTP client. Servers over real sockets are tested in `translux-tests`.
#[cfg(test)]
mod tests {
    use axum::http::{Request, StatusCode};
    use serde_json::Value;
    use tower::ServiceExt;

    use super::*;

    #[test]
    fn a_scene_files_path_on_the_server_is_not_shown() {
        assert_eq!(public_source("/srv/team/scenes/room.json"), "room.json");
        assert_eq!(public_source("C:scenes/room.json"), "room.json");
        assert_eq!(public_source("builtin:cornell"), "builtin:cornell");
        assert_eq!(public_source("upload:j01/a b.json"), "upload:j01/a b.json");
    }

    /// The answer's status and JSON body for `method path` with `body` (as JSON).
    async fn call(method: Method, path: &str, body: Body) -> (StatusCode, Value) {
        let req = Request::builder()
            .method(method)
            .uri(path)
            .header(CONTENT_TYPE, "application/json")
            .body(body)
            .unwrap();
        let resp = router(AppState::default()).oneshot(req).await.unwrap();
        let status = resp.status();
        let bytes = axum::body::to_bytes(resp.into_body(), 1 << 20)
            .await
            .unwrap();
        (
            status,
            serde_json::from_slice(&bytes).unwrap_or(Value::Null),
        )
    }

    #[tokio::test]
    async fn health_and_an_empty_scene_list() {
        let (status, h) = call(Method::GET, "/healthz", Body::empty()).await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(
            (h["status"].as_str(), h["backend"].as_str()),
            (Some("ok"), Some("cpu"))
        );
        let (status, list) = call(Method::GET, "/api/v1/scenes", Body::empty()).await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(list["scenes"], serde_json::json!([]));
    }

    /// A load balancer's check sees a stopping server as down: 503 `shutting_down`.
    #[tokio::test]
    async fn health_answers_503_once_shutdown_has_begun() {
        let state = AppState::default();
        let app = router(state.clone());
        let get = || Request::get("/healthz").body(Body::empty()).unwrap();
        let before = app.clone().oneshot(get()).await.unwrap();
        assert_eq!(before.status(), StatusCode::OK);
        state.begin_shutdown();
        let after = app.oneshot(get()).await.unwrap();
        assert_eq!(after.status(), StatusCode::SERVICE_UNAVAILABLE);
        let bytes = axum::body::to_bytes(after.into_body(), 1 << 20)
            .await
            .unwrap();
        let h: Value = serde_json::from_slice(&bytes).unwrap();
        assert_eq!(h["error"]["code"], "shutting_down", "{h}");
    }

    #[tokio::test]
    async fn refusals_are_json_naming_the_problem() {
        let cases: [(Method, &str, Body, StatusCode, &str, &str); 4] = [
            (
                Method::GET,
                "/api/v1/nothing",
                Body::empty(),
                StatusCode::NOT_FOUND,
                "not_found",
                "/api/v1/nothing",
            ),
            (
                Method::PUT,
                "/api/v1/scenes",
                Body::empty(),
                StatusCode::METHOD_NOT_ALLOWED,
                "method_not_allowed",
                "PUT",
            ),
            (
                Method::GET,
                "/api/v1/scenes/kitchen",
                Body::empty(),
                StatusCode::NOT_FOUND,
                "not_found",
                "kitchen",
            ),
            // The scene is looked up before the body is read: an unknown scene is a 404
            // even with a body over the limit, which is then never buffered.
            (
                Method::POST,
                "/api/v1/scenes/kitchen/relight",
                Body::from(vec![b' '; BODY_LIMIT + 1]),
                StatusCode::NOT_FOUND,
                "not_found",
                "no scene \"kitchen\"",
            ),
        ];
        for (method, path, body, want, code, needle) in cases {
            let (status, e) = call(method.clone(), path, body).await;
            assert_eq!(status, want, "{method} {path}: {e}");
            assert_eq!(e["error"]["code"], code, "{method} {path}: {e}");
            let msg = e["error"]["message"].as_str().unwrap_or_default();
            assert!(msg.contains(needle), "{method} {path}: {msg}");
        }
    }
}
