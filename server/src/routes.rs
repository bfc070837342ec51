//! The HTTP API (axum): routes, handlers, and the middleware around them.

use std::sync::Arc;
use std::time::Instant;

use axum::Router;
use axum::body::{Body, Bytes};
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::http::header::{CONTENT_TYPE, VARY};
use axum::http::{HeaderMap, HeaderValue, Method, Uri};
use axum::middleware::{self, Next};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use serde::Serialize;
use translux_proto::api::{
    GpuHealth, Health, Mesh, MeshObject, RelightRequest, RelightResponse, RenderRequest,
    SceneDetail, SceneList, SceneObject, SceneSummary,
};

use crate::error::AppError;
use crate::extract::{BODY_LIMIT, Format, JsonBody, SceneId, accept_png, negotiate};
use crate::state::{AppState, Scene};
use crate::{picture, relight};

/// The viewer page served at `/`.
pub const INDEX_HTML: &str = include_str!("../../web/index.html");

/// Why `/healthz` reports no GPU.
pub const NO_GPU_REASON: &str = "this build has no GPU backend yet";

/// The whole API over `state`.
pub fn router(state: AppState) -> Router {
    Router::new()
        .route("/", get(index))
        .route("/healthz", get(healthz))
        .route("/api/v1/scenes", get(list_scenes))
        .route("/api/v1/scenes/{id}", get(scene_detail))
        .route("/api/v1/scenes/{id}/mesh", get(scene_mesh))
        .route("/api/v1/scenes/{id}/relight", post(relight))
        .route("/api/v1/scenes/{id}/render", post(render))
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(DefaultBodyLimit::max(BODY_LIMIT))
        .layer(middleware::from_fn(log_request))
        .with_state(state)
}

/// A pre-serialised JSON answer.
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
    state.scene(id).cloned().ok_or_else(|| {
        let ids = state.ids();
        let known = if ids.is_empty() {
            "none".to_string()
        } else {
            ids.join(", ")
        };
        AppError::not_found(format!("no scene {id:?}; the scenes served are: {known}"))
    })
}

async fn index() -> Html<&'static str> {
    Html(INDEX_HTML)
}

async fn healthz(State(state): State<AppState>) -> Result<Response, AppError> {
    to_json(&Health {
        status: "ok".into(),
        backend: "cpu".into(),
        gpu: GpuHealth {
            available: false,
            reason: Some(NO_GPU_REASON.into()),
        },
        scenes: state.ids(),
    })
}

fn summary(scene: &Scene) -> SceneSummary {
    let m = scene.bundle.manifest();
    SceneSummary {
        id: scene.id.clone(),
        name: m.name.clone(),
        patches: m.patch_count,
        vertices: m.vertex_count,
        objects: m.objects.len(),
    }
}

async fn list_scenes(State(state): State<AppState>) -> Result<Response, AppError> {
    to_json(&SceneList {
        scenes: state.scenes().map(|s| summary(s)).collect(),
    })
}

async fn scene_detail(
    State(state): State<AppState>,
    SceneId(id): SceneId,
) -> Result<Response, AppError> {
    let scene = find_scene(&state, &id)?;
    let m = scene.bundle.manifest();
    to_json(&SceneDetail {
        id: scene.id.clone(),
        name: m.name.clone(),
        source: m.source.clone(),
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
            })
            .collect(),
        lights: m.lights.clone(),
        camera: m.camera,
        form_factors: m.form_factors.clone(),
        stages: m.stages.clone(),
        bundle_bytes: scene.bundle.total_bytes(),
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

async fn scene_mesh(
    State(state): State<AppState>,
    SceneId(id): SceneId,
) -> Result<Response, AppError> {
    let scene = find_scene(&state, &id)?;
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

async fn relight(
    State(state): State<AppState>,
    SceneId(id): SceneId,
    headers: HeaderMap,
    body: Result<JsonBody<RelightRequest>, AppError>,
) -> Result<Response, AppError> {
    let scene = find_scene(&state, &id)?;
    let format = negotiate(&headers)?;
    let JsonBody(req) = body?;
    let plan = relight::plan(&scene, req)?;
    let task_scene = scene.clone();
    let out = tokio::task::spawn_blocking(move || relight::run(&task_scene, &plan))
        .await
        .map_err(|e| AppError::internal(format!("the relight task failed: {e}")))??;
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
        "relit"
    );
    let timing = format!(
        "direct;dur={:.3}, solve;dur={:.3}, total;dur={:.3}",
        s.direct_ms, s.solve_ms, s.ms
    );
    let vertex_count = out.radiance.len();
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
    Ok(response)
}

/// `POST /api/v1/scenes/{id}/render`: the relight request's fields plus a camera and the
/// picture's size, exposure and tone curve; answers `image/png`. The relight runs through
/// the same [`relight::plan`] / [`relight::run`] as `/relight`.
async fn render(
    State(state): State<AppState>,
    SceneId(id): SceneId,
    headers: HeaderMap,
    body: Result<JsonBody<RenderRequest>, AppError>,
) -> Result<Response, AppError> {
    let scene = find_scene(&state, &id)?;
    accept_png(&headers)?;
    let JsonBody(req) = body?;
    let plan = picture::plan(&scene, req)?;
    let task_scene = scene.clone();
    let out = tokio::task::spawn_blocking(move || picture::run(&task_scene, &plan))
        .await
        .map_err(|e| AppError::internal(format!("the render task failed: {e}")))??;
    let s = &out.stats;
    tracing::info!(
        scene = %scene.id,
        components = s.components.as_str(),
        lights = s.lights,
        iterations = s.iterations,
        relight_ms = format_args!("{:.1}", s.ms),
        raster_ms = format_args!("{:.1}", out.raster_ms),
        encode_ms = format_args!("{:.1}", out.encode_ms),
        bytes = out.png.len(),
        "rendered"
    );
    let timing = format!(
        "direct;dur={:.3}, solve;dur={:.3}, raster;dur={:.3}, encode;dur={:.3}, total;dur={:.3}",
        s.direct_ms, s.solve_ms, out.raster_ms, out.encode_ms, out.total_ms
    );
    let mut response = Body::from(out.png).into_response();
    let h = response.headers_mut();
    h.insert(CONTENT_TYPE, HeaderValue::from_static("image/png"));
    h.insert("x-vertex-count", HeaderValue::from(out.vertex_count));
    if let Ok(v) = HeaderValue::from_str(&timing) {
        h.insert("server-timing", v);
    }
    Ok(response)
}

async fn not_found(method: Method, uri: Uri) -> AppError {
    AppError::not_found(format!("no route for {method} {}", uri.path()))
}

async fn method_not_allowed(method: Method, uri: Uri) -> AppError {
    AppError::method_not_allowed(format!("{method} is not allowed on {}", uri.path()))
}

/// One log line per request: errors at info, the rest at debug.
async fn log_request(req: Request, next: Next) -> Response {
    let method = req.method().clone();
    let path = req.uri().path().to_owned();
    let t = Instant::now();
    let response = next.run(req).await;
    let status = response.status();
    let ms = t.elapsed().as_secs_f64() * 1e3;
    if status.is_client_error() || status.is_server_error() {
        tracing::info!(%method, %path, status = status.as_u16(), ms = format_args!("{ms:.1}"), "request");
    } else {
        tracing::debug!(%method, %path, status = status.as_u16(), ms = format_args!("{ms:.1}"), "request");
    }
    response
}
