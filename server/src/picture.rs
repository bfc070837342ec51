//! Pictures and files of a relit scene, shared by `POST /api/v1/scenes/{id}/render` and the
//! offline commands (`translux-server render | export`).
//!
//! In: a [`Scene`] and a request (a [`RenderRequest`], or a relight request plus exposure and
//! tone for exports). [`plan`] checks it (cheap; the picture's fields first, then
//! [`relight::plan`]); [`run`] relights through [`relight::run`] — the same path as the
//! relight route, nothing duplicated — and rasterizes the per-vertex radiance with
//! [`translux_precompute::render`]. Out: PNG bytes ([`run`]), or `.glb` / `.ply` bytes
//! ([`export`]), with the relight's statistics and timings.

use std::time::Instant;

use translux_precompute::export::{ExportError, to_glb, to_ply};
use translux_precompute::render::{RenderError, RenderParams, check_camera, encode_png, render};
use translux_proto::api::{RelightStats, RenderRequest, ToneMap};
use translux_proto::light::Camera;

use crate::error::AppError;
use crate::relight::{self, RelightPlan};
use crate::state::Scene;

/// A checked render request, ready to run.
#[derive(Debug, Clone)]
pub struct RenderPlan {
    pub relight: RelightPlan,
    pub camera: Camera,
    pub params: RenderParams,
}

/// Checks `req` for `scene`: picture fields (`width`, `height`, `exposure`, `background`,
/// `camera.*`) give 400 `invalid` naming the field, then the relight fields as in
/// [`relight::plan`]. A request without `camera` uses the bundle's.
pub fn plan(scene: &Scene, req: RenderRequest) -> Result<RenderPlan, AppError> {
    let params = RenderParams {
        width: req.width,
        height: req.height,
        exposure: req.exposure,
        tone: req.tone,
        background: req.background,
        cull_backfaces: req.cull_backfaces,
    };
    params.validate().map_err(render_error)?;
    let camera = match req.camera {
        Some(c) => {
            check_camera(&c).map_err(render_error)?;
            c
        }
        None => {
            let c = scene.bundle.manifest().camera;
            check_camera(&c).map_err(|e| {
                AppError::invalid(format!(
                    "camera: the scene's default camera cannot be used ({e}); give a camera \
                     in the request"
                ))
            })?;
            c
        }
    };
    let relight = relight::plan(scene, req.relight())?;
    Ok(RenderPlan {
        relight,
        camera,
        params,
    })
}

/// A rendered picture and what it took.
#[derive(Debug, Clone)]
pub struct RenderOutput {
    /// The PNG file.
    pub png: Vec<u8>,
    pub stats: RelightStats,
    /// Vertices relit.
    pub vertex_count: usize,
    /// Milliseconds rasterizing.
    pub raster_ms: f64,
    /// Milliseconds encoding the PNG.
    pub encode_ms: f64,
    /// Milliseconds in all (relight, raster, encode).
    pub total_ms: f64,
}

/// Relights the scene and renders it. CPU-heavy: call it off the async runtime.
pub fn run(scene: &Scene, plan: &RenderPlan) -> Result<RenderOutput, AppError> {
    let t0 = Instant::now();
    let relit = relight::run(scene, &plan.relight)?;
    let b = &scene.bundle;
    let t1 = Instant::now();
    let img = render(
        b.vertex_positions(),
        b.triangle_vertices(),
        &relit.radiance,
        &plan.camera,
        &plan.params,
    )
    .map_err(render_error)?;
    let t2 = Instant::now();
    let png = encode_png(&img).map_err(render_error)?;
    let t3 = Instant::now();
    Ok(RenderOutput {
        png,
        stats: relit.stats,
        vertex_count: relit.radiance.len(),
        raster_ms: (t2 - t1).as_secs_f64() * 1e3,
        encode_ms: (t3 - t2).as_secs_f64() * 1e3,
        total_ms: (t3 - t0).as_secs_f64() * 1e3,
    })
}

/// Mesh file formats with baked colours.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    /// Binary glTF 2.0, linear float colours.
    Glb,
    /// Binary PLY, 8-bit sRGB colours.
    Ply,
}

/// Relights the scene and writes its viewer mesh with baked colours (exposure in EV stops,
/// then the tone curve; see [`translux_precompute::export`]). Returns the file's bytes and
/// the relight's statistics.
pub fn export(
    scene: &Scene,
    plan: &RelightPlan,
    exposure: f32,
    tone: ToneMap,
    format: MeshFormat,
) -> Result<(Vec<u8>, RelightStats), AppError> {
    let relit = relight::run(scene, plan)?;
    let b = &scene.bundle;
    let args = (
        b.vertex_positions(),
        b.vertex_normals(),
        b.triangle_vertices(),
        relit.radiance.as_slice(),
    );
    let bytes = match format {
        MeshFormat::Glb => to_glb(args.0, args.1, args.2, args.3, exposure, tone),
        MeshFormat::Ply => to_ply(args.0, args.1, args.2, args.3, exposure, tone),
    }
    .map_err(|e| match e {
        ExportError::Exposure(_) => AppError::invalid(e.to_string()),
        other => AppError::internal(format!("cannot export the mesh: {other}")),
    })?;
    Ok((bytes, relit.stats))
}

/// A render error as an answer: bad parameters are the client's (400 `invalid`), the rest
/// (a bundle's mesh the renderer refuses, an encoder failure) the server's.
fn render_error(e: RenderError) -> AppError {
    match e {
        RenderError::Invalid(f) => AppError::invalid(f.to_string()),
        other => AppError::internal(format!("cannot render the scene: {other}")),
    }
}
