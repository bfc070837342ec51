//! Stage 5 of the relight: a plan's colours (B/π per vertex) and stats from its group's
//! radiosity.

use translux_proto::api::{DirectAt, RelightStats};

use super::prepare::{Prepared, VertexDirect};
use super::transport::TransportStats;
use super::{RelightOutput, RelightPlan};
use crate::error::EngineError;
use crate::radiosity::{Rgb, vertex_radiance};
use crate::scene::Scene;

/// What a group's transport gave its plans: radiosity `[patch][k·3]` for the k plans, its
/// stats and time, and k.
pub(super) struct Transported<'a> {
    pub(super) radiosity: &'a [f32],
    pub(super) stats: &'a TransportStats,
    pub(super) solve_ms: f64,
    pub(super) batch: usize,
}

/// The answer of the plan in `slot` of the group: its radiosity per patch, B/π per vertex
/// with the direct term of opaque diffuse surfaces at the vertex ([`vertex_colours`]), and
/// its stats; an error where the radiance overflowed.
pub(super) fn answer(
    scene: &Scene,
    plan: &RelightPlan,
    p: &Prepared,
    done: &Transported<'_>,
    slot: usize,
) -> Result<RelightOutput, EngineError> {
    let b = &scene.bundle;
    let n = b.patch_areas().len();
    let rad: Vec<Rgb> = (0..n)
        .map(|j| std::array::from_fn(|c| done.radiosity[j * 3 * done.batch + 3 * slot + c]))
        .collect();
    let (radiance, auto_exposure) = vertex_colours(scene, plan, p, &rad);
    // Finite inputs can still overflow f32 (an intensity near f32::MAX);
    // never answer NaN or infinity (JSON has no such numbers).
    if let Some(k) = radiance
        .iter()
        .position(|v| !v.iter().all(|x| x.is_finite()))
    {
        return Err(EngineError::invalid(format!(
            "lights: the result overflows (radiance at vertex {k} is not \
             finite); use smaller intensities or irradiances"
        )));
    }
    let ts = done.stats;
    let solve_ms = done.solve_ms;
    // Where S was written (the CPU, or the backend that wrote it and solved), and the time
    // the transport spent on it, taken out of the solve's.
    let on = ts.device.map_or("cpu", |(on, _)| on);
    let s_ms = ts.materials_ms.min(solve_ms);
    let stats = RelightStats {
        solver: ts.solver.to_string(),
        components: plan.components,
        iterations: ts.iterations,
        residual: ts.residual,
        converged: ts.converged,
        ms: p.direct_ms + p.materials_ms + solve_ms,
        direct_ms: p.direct_ms,
        solve_ms: solve_ms - s_ms,
        materials_ms: p.materials_ms + s_ms,
        materials_on: p.materials.as_ref().map(|_| on.to_string()),
        lights: plan.lights.len(),
        products: ts.products,
        warm: ts.warm,
        batch: done.batch,
        note: p.note.clone(),
        auto_exposure,
        device: ts.device.map(|d| d.1),
    };
    Ok(RelightOutput { radiance, stats })
}

/// B/π per vertex from the patches' radiosity `rad`, the direct term of opaque diffuse
/// surfaces taken at the vertex itself ([`at_vertices`]), and the exposure of the whole
/// answer where the plan leaves the direct term to the picture ([`DirectAt::Pixel`]).
fn vertex_colours(
    scene: &Scene,
    plan: &RelightPlan,
    p: &Prepared,
    rad: &[Rgb],
) -> (Vec<Rgb>, Option<f32>) {
    let b = &scene.bundle;
    let mut radiance = vertex_radiance(
        b.triangle_vertices(),
        b.patch_areas(),
        b.vertex_positions().len(),
        rad,
    );
    let mut auto_exposure = None;
    if let Some(v) = &p.vertex {
        auto_exposure = at_vertices(scene, p, v, rad, &mut radiance);
    }
    if plan.direct_at == DirectAt::Pixel && auto_exposure.is_none() {
        auto_exposure = Some(crate::render::auto_exposure(&radiance));
    }
    (radiance, auto_exposure)
}

/// Sets the vertices of `v` in `radiance` to their direct light at the vertex plus their
/// patches' indirect light ([`crate::vertexlight::VertexMeans`]); per pixel, answers the
/// exposure of that whole answer and then leaves out the direct term the picture adds.
fn at_vertices(
    scene: &Scene,
    p: &Prepared,
    v: &VertexDirect,
    rad: &[Rgb],
    radiance: &mut [Rgb],
) -> Option<f32> {
    let b = &scene.bundle;
    let albedo = match &p.materials {
        Some(m) => m.albedo.as_slice(),
        None => b.patch_albedo(),
    };
    let terms = crate::vertexlight::PatchTerms {
        radiosity: rad,
        irradiance: v.lit.at_patch.as_deref().unwrap_or(&p.irradiance),
        albedo,
    };
    let means = crate::vertexlight::VertexMeans::new(b, scene.vertex_samples(), terms);
    means.set(&v.lit.which, &v.lit.at_vertex, radiance);
    let skip = v.per_pixel.as_ref()?;
    // The exposure of the whole answer, then the answer without the
    // direct term the picture adds per pixel.
    let auto_exposure = crate::render::auto_exposure(radiance);
    let e: Vec<Rgb> = v
        .lit
        .at_vertex
        .iter()
        .zip(skip)
        .map(|(e, &s)| if s { [0.0; 3] } else { *e })
        .collect();
    means.set(&v.lit.which, &e, radiance);
    Some(auto_exposure)
}
