//! Pictures and files of a relit scene, shared by `POST /api/v1/scenes/{id}/render` and the
//! offline commands (`translux-server render | export`).
//!
//! In: a [`Scene`] and a request (a [`RenderRequest`], or a relight request plus exposure and
//! tone for exports). [`plan`] checks it (cheap; the picture's fields first, then
//! [`relight::plan`]); [`run`] relights through [`relight::run`] — the same path as the
//! relight route, nothing duplicated — and rasterizes the per-vertex radiance with
//! [`crate::render`]. Out: PNG or OpenEXR bytes ([`run`], by
//! [`RenderPlan::format`]), or `.glb` / `.ply` bytes ([`export`]), with the relight's
//! statistics and timings and the exposure used.
//!
//! Exposure: a number of EV stops is used as given; [`Exposure::Auto`] (the default) is
//! [`auto_exposure`] of the relit radiance, the rule the viewer applies when it opens a
//! scene, so a default render or export looks like the viewer's first frame instead of
//! clipping a scene whose radiance is well above 1 (the Cornell box's lit walls are).
//!
//! OpenEXR ([`PictureFormat::Exr`]) is for compositing: linear radiance B/π in
//! W·m⁻²·sr⁻¹, no tone curve, no sRGB OETF, background pixels the requested `background`
//! as linear values (black by default). A numeric exposure multiplies the values by 2^EV;
//! `auto` does **not** scale them (the file holds physical radiance; exposing is the
//! compositor's job), so the exposure reported for an EXR with `auto` is 0, the EV applied.

use std::time::Instant;

use crate::export::{ExportError, ExportMesh, MeshPart, to_glb, to_ply};
use crate::render::{
    RenderError, RenderParams, Surface, auto_exposure, check_camera, encode_exr, encode_png,
    render_linear_with, render_with,
};
use crate::specular::{Lighting, ObjectShading, PixelLighting};
use translux_proto::api::{Components, DirectAt, Exposure, RelightStats, RenderRequest, ToneMap};
use translux_proto::light::Camera;

use crate::error::EngineError;
use crate::relight::{self, RelightPlan};
use crate::scene::Scene;

/// A checked render request, ready to run.
#[derive(Debug, Clone)]
pub struct RenderPlan {
    pub relight: RelightPlan,
    pub camera: Camera,
    /// The picture's parameters; `params.exposure` is the requested number, or 0 until
    /// [`run`] replaces it with the automatic one.
    pub params: RenderParams,
    /// What the request asked for.
    pub exposure: Exposure,
    /// The file to make; [`plan`] picks PNG, a caller that negotiated EXR sets it.
    pub format: PictureFormat,
    /// Add the specular pass ([`crate::specular`]) where the components include it
    /// ([`with_highlights`]). (Where diffuse objects' direct light is evaluated is
    /// `relight.direct_at`.)
    pub specular: bool,
}

/// Whether a picture of `components` gets the specular pass: yes for the ones that show
/// the direct light as it leaves the surface (`full`, `direct`, and the paper's heuristics),
/// no for `subsurface_only` and `interreflection_only`, which isolate one transport path.
pub fn with_highlights(components: Components) -> bool {
    !matches!(
        components,
        Components::SubsurfaceOnly | Components::InterreflectionOnly
    )
}

/// What `plan` adds per pixel for `scene` (the specular pass, and the direct light of
/// diffuse objects with [`DirectAt::Pixel`]), or `None` when it adds nothing.
fn pixel_lighting<'a>(
    scene: &'a Scene,
    plan: &RenderPlan,
) -> Result<Option<PixelLighting<'a>>, EngineError> {
    let r = &plan.relight;
    let manifest = scene.bundle.manifest();
    let glossy = plan.specular && with_highlights(r.components);
    let shading: Vec<ObjectShading> = r
        .materials(scene)
        .into_iter()
        .enumerate()
        .map(|(k, material)| ObjectShading {
            gloss: if glossy { r.gloss[k] } else { None },
            diffuse: match r.direct_at {
                DirectAt::Pixel => relight::per_pixel_direct(material),
                DirectAt::Vertex => None,
            },
        })
        .collect();
    if shading
        .iter()
        .all(|s| s.gloss.is_none() && s.diffuse.is_none())
    {
        return Ok(None);
    }
    let env = if shading.iter().any(|s| s.gloss.is_some()) {
        crate::environment::lights_with_maps(&scene.env(), &r.lights)?
    } else {
        Vec::new()
    };
    let lighting = Lighting::new(&r.lights, env, &scene.occluder, manifest.unit_mm);
    let objects = manifest.objects.iter().zip(shading).map(|(o, s)| {
        let start = o.first_patch as u32;
        (start..start + o.patch_count as u32, s)
    });
    Ok(PixelLighting::new(lighting, objects))
}

/// The picture file formats of a render.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PictureFormat {
    /// 8-bit sRGB RGB PNG: exposed, tone mapped, sRGB OETF.
    #[default]
    Png,
    /// OpenEXR, RGB half float in scan lines, linear
    /// radiance; see the module documentation for exposure.
    Exr,
}

impl PictureFormat {
    /// The media type of the answer.
    pub fn media_type(self) -> &'static str {
        match self {
            PictureFormat::Png => "image/png",
            PictureFormat::Exr => "image/x-exr",
        }
    }

    /// The short name for logs: `PNG`, `EXR`.
    pub fn name(self) -> &'static str {
        match self {
            PictureFormat::Png => "PNG",
            PictureFormat::Exr => "EXR",
        }
    }
}

/// Checks `req` for `scene`: picture fields (`width`, `height`, `exposure`, `background`,
/// `camera.*`) give 400 `invalid` naming the field, then the relight fields as in
/// [`relight::plan`]. A request without `camera` uses the bundle's.
pub fn plan(scene: &Scene, req: RenderRequest) -> Result<RenderPlan, EngineError> {
    let params = RenderParams {
        width: req.width,
        height: req.height,
        // An explicit number is checked here, before any work; `auto` is computed in `run`
        // and is always in range.
        exposure: req.exposure.ev().unwrap_or(0.0),
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
                EngineError::invalid(format!(
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
        exposure: req.exposure,
        format: PictureFormat::Png,
        specular: req.specular,
    })
}

/// The exposure in EV stops for `exposure` and the relit radiance: the number as given, or
/// for `auto` the viewer's rule ([`auto_exposure`]). (Not used for EXR with `auto`, which is
/// unscaled.)
pub fn resolve_exposure(exposure: Exposure, vertex_radiance: &[[f32; 3]]) -> f32 {
    exposure
        .ev()
        .unwrap_or_else(|| auto_exposure(vertex_radiance))
}

/// A rendered picture and what it took.
#[derive(Debug, Clone)]
pub struct RenderOutput {
    /// The file, in [`RenderPlan::format`].
    pub bytes: Vec<u8>,
    /// The exposure used, in EV stops (the automatic one when the request asked for `auto`;
    /// 0 for an EXR with `auto`, whose values are not scaled).
    pub exposure: f32,
    pub stats: RelightStats,
    /// Vertices relit.
    pub vertex_count: usize,
    /// Milliseconds rasterizing.
    pub raster_ms: f64,
    /// Milliseconds encoding the file.
    pub encode_ms: f64,
    /// Milliseconds in all (relight, raster, encode).
    pub total_ms: f64,
}

/// Relights the scene and renders it. CPU-heavy: call it off the async runtime.
pub fn run(scene: &Scene, plan: &RenderPlan) -> Result<RenderOutput, EngineError> {
    let t0 = Instant::now();
    let relit = relight::run(scene, &plan.relight)?;
    let b = &scene.bundle;
    let t1 = Instant::now();
    let exposure = match plan.format {
        // With the direct light per pixel, the relight says what the whole answer's
        // automatic exposure is (its radiance lacks that term).
        PictureFormat::Png => match (plan.exposure, relit.stats.auto_exposure) {
            (Exposure::Auto, Some(ev)) => ev,
            _ => resolve_exposure(plan.exposure, &relit.radiance),
        },
        // Linear output: `auto` writes the radiance as it is.
        PictureFormat::Exr => plan.exposure.ev().unwrap_or(0.0),
    };
    let params = RenderParams {
        exposure,
        ..plan.params
    };
    let shine = pixel_lighting(scene, plan)?;
    let surface = shine.as_ref().map(|h| Surface {
        normals: b.vertex_normals(),
        shade: h,
    });
    let args = (
        b.vertex_positions(),
        b.triangle_vertices(),
        &relit.radiance[..],
        &plan.camera,
        &params,
        surface.as_ref(),
    );
    let (bytes, t2) = match plan.format {
        PictureFormat::Png => {
            let img = render_with(args.0, args.1, args.2, args.3, args.4, args.5)
                .map_err(render_error)?;
            let t2 = Instant::now();
            (encode_png(&img).map_err(render_error)?, t2)
        }
        PictureFormat::Exr => {
            let img = render_linear_with(args.0, args.1, args.2, args.3, args.4, args.5)
                .map_err(render_error)?;
            let t2 = Instant::now();
            (encode_exr(&img).map_err(render_error)?, t2)
        }
    };
    let t3 = Instant::now();
    Ok(RenderOutput {
        bytes,
        exposure: params.exposure,
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
    /// Binary glTF 2.0: linear float colours, metres, one named node per object.
    Glb,
    /// Binary PLY: 8-bit sRGB colours, scene units, one mesh.
    Ply,
}

/// An exported mesh file and what it took.
#[derive(Debug, Clone)]
pub struct ExportOutput {
    /// The file.
    pub bytes: Vec<u8>,
    /// The exposure baked in, in EV stops (the automatic one for `auto`).
    pub exposure: f32,
    pub stats: RelightStats,
}

/// The scene's objects as named triangle runs of the viewer mesh: triangle k is patch k, so
/// an object's triangles are its patch range (as in the `/mesh` route's `objects`).
pub fn mesh_parts(scene: &Scene) -> Vec<MeshPart> {
    scene
        .bundle
        .manifest()
        .objects
        .iter()
        .map(|o| MeshPart {
            name: o.name.clone(),
            triangles: o.first_patch as usize..(o.first_patch + o.patch_count) as usize,
        })
        .collect()
}

/// Relights the scene and writes its viewer mesh with baked colours (exposure in EV stops,
/// or `auto` as in [`resolve_exposure`], then the tone curve; the `.glb` in metres with one
/// node per object; see [`crate::export`]).
pub fn export(
    scene: &Scene,
    plan: &RelightPlan,
    exposure: Exposure,
    tone: ToneMap,
    format: MeshFormat,
) -> Result<ExportOutput, EngineError> {
    // A file of vertex colours holds the whole answer: the direct light at the vertices.
    let plan = RelightPlan {
        direct_at: DirectAt::Vertex,
        ..plan.clone()
    };
    let relit = relight::run(scene, &plan)?;
    let b = &scene.bundle;
    let ev = resolve_exposure(exposure, &relit.radiance);
    let parts = mesh_parts(scene);
    let mesh = ExportMesh {
        unit_mm: b.manifest().unit_mm,
        parts: &parts,
        ..ExportMesh::new(
            b.vertex_positions(),
            b.vertex_normals(),
            b.triangle_vertices(),
            &relit.radiance,
        )
    };
    let bytes = match format {
        MeshFormat::Glb => to_glb(&mesh, ev, tone),
        MeshFormat::Ply => to_ply(&mesh, ev, tone),
    }
    .map_err(|e| match e {
        ExportError::Exposure(_) => EngineError::invalid(e.to_string()),
        other => EngineError::internal(format!("cannot export the mesh: {other}")),
    })?;
    Ok(ExportOutput {
        bytes,
        exposure: ev,
        stats: relit.stats,
    })
}

/// A render error as an answer: bad parameters are the client's (400 `invalid`), the rest
/// (a bundle's mesh the renderer refuses, an encoder failure) the server's.
fn render_error(e: RenderError) -> EngineError {
    match e {
        RenderError::Invalid(f) => EngineError::invalid(f.to_string()),
        other => EngineError::internal(format!("cannot render the scene: {other}")),
    }
}
