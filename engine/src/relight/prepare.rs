//! Stages 1 and 2 of the relight, per plan: its direct light (E per patch, at the vertices
//! of opaque surfaces, the lamps' collimated entry and walked beams) and S for its
//! materials, with the path its transport takes.

use std::sync::Arc;
use std::time::Instant;

use translux_proto::api::{Components, DirectAt, Solver};
use translux_proto::light::Light;
use translux_proto::scene::Material;

use super::{RelightPlan, per_pixel_direct, transfer_stale};
use crate::collimated::TiltOf;
use crate::error::EngineError;
use crate::radiosity::{PatchGeometry, Rgb};
use crate::scene::Scene;
use crate::smatrix::OverrideMaterials;
use crate::vertexlight::VertexLit;

/// What one plan needs before the transport: its E, materials and the path it takes.
pub(super) struct Prepared {
    pub(super) irradiance: Arc<Vec<Rgb>>,
    pub(super) materials: Option<Arc<OverrideMaterials>>,
    pub(super) materials_key: String,
    pub(super) materials_ms: f64,
    pub(super) direct_ms: f64,
    pub(super) use_t: bool,
    pub(super) note: Option<String>,
    /// Direct light at the opaque diffuse vertices ([`crate::vertexlight`]).
    pub(super) vertex: Option<VertexDirect>,
    /// Lamps' collimated entry into simulated objects ([`crate::collimated`]).
    pub(super) collimated: Option<Collimated>,
    /// With the full transport and simulated objects: their Δ, G_u and G_v, for the
    /// direction the light from other surfaces arrives from
    /// ([`crate::collimated::interreflected_moments`]).
    pub(super) slant: Option<Arc<TiltOf>>,
    /// The lamps' own beams walked into the simulated objects, when the plan asks, with the
    /// plan's materials (their σa re-weights the walks).
    pub(super) lamp_walks: Option<LampWalked>,
}

/// The tilt of a plan's materials and [E_t, E_u, E_v, E_w] of its lamps ([`crate::collimated`]).
pub(super) type Collimated = (Arc<TiltOf>, Arc<crate::scene::Moments>);

/// The lamps' walked beams and the materials they were walked with ([`crate::lampwalk`]).
pub(super) type LampWalked = (Arc<crate::lampwalk::LampWalks>, Vec<Material>);

/// E at the vertices whose direct term is taken at the vertex, and what it replaces.
pub(super) struct VertexDirect {
    pub(super) lit: Arc<VertexLit>,
    /// With [`DirectAt::Pixel`]: which of `which` leave their direct term out of the answer.
    pub(super) per_pixel: Option<Vec<bool>>,
}

/// The direct light of `plan`'s point, spot and directional lights at the vertices of
/// opaque surfaces (under the plan's materials and components); `None` without such
/// vertices. Without such lights E(v) is 0 and the vertices still take their indirect
/// light through [`crate::vertexlight::VertexMeans`], so that an environment's answer
/// is the same alone as beside a lamp. `lights_key` is the plan's lights as JSON: what
/// the scene's [`crate::scene::DirectCache`] keeps the traced part under.
fn vertex_direct(
    scene: &Scene,
    geo: PatchGeometry<'_>,
    plan: &RelightPlan,
    lights_key: &str,
) -> Result<Option<VertexDirect>, EngineError> {
    let b = &scene.bundle;
    let materials = plan.materials(scene);
    let samples = scene.vertex_samples();
    let opaque = crate::vertexlight::opaque_objects(&materials, plan.components);
    // The vertices traced depend on the lights and on which objects are opaque alone.
    let key: String = opaque
        .iter()
        .map(|&o| if o { '1' } else { '0' })
        .chain(std::iter::once('|'))
        .chain(lights_key.chars())
        .collect();
    let lit = scene.direct.vertices(&key, || {
        let which = samples.opaque_vertices(b, &opaque);
        if which.is_empty() {
            return Ok(None);
        }
        let lights: Vec<Light> = plan
            .lights
            .iter()
            .filter(|l| !matches!(l, Light::Environment { .. }))
            .cloned()
            .collect();
        let (point, normal) = samples.geometry(&which);
        let unit_mm = b.manifest().unit_mm;
        let direct = |geo: PatchGeometry<'_>| {
            if lights.is_empty() {
                return Ok(vec![[0.0; 3]; geo.centroid.len()]);
            }
            crate::radiosity::direct_irradiance(geo, &scene.occluder, &lights, unit_mm)
                .map_err(|e| EngineError::unsupported(e.to_string()))
        };
        let at_vertex = direct(PatchGeometry {
            centroid: &point,
            normal: &normal,
        })?;
        let at_patch = if lights.len() == plan.lights.len() {
            None
        } else {
            Some(direct(geo)?)
        };
        Ok(Some(VertexLit {
            which,
            at_vertex,
            at_patch,
        }))
    })?;
    let Some(lit) = lit else {
        return Ok(None);
    };
    // Per pixel: the vertices of diffuse objects answer the rest alone (E(v) taken as 0);
    // the others that count as opaque (translucent ones in `direct`) keep their E(v).
    let per_pixel = match plan.direct_at {
        DirectAt::Vertex => None,
        DirectAt::Pixel => {
            // Diffuse objects count as opaque under every component.
            let diffuse: Vec<bool> = materials
                .iter()
                .map(|m| per_pixel_direct(m).is_some())
                .collect();
            let skip: std::collections::HashSet<usize> =
                samples.opaque_vertices(b, &diffuse).into_iter().collect();
            Some(lit.which.iter().map(|v| skip.contains(v)).collect())
        }
    };
    Ok(Some(VertexDirect { lit, per_pixel }))
}

/// Δ and the moments [E_t, E_u, E_v, E_w] of `plan`'s lamps and environment maps on its
/// simulated objects ([`crate::collimated`]), when its components scatter light by S and it
/// has such lights and simulated objects; else a note when the bundle's walks cannot serve
/// collimated entry. The moments depend on the lights (`lights_key`) and on which patches
/// are simulated, not on their absorption: the scene keeps the last ones
/// ([`crate::scene::DirectCache`]), so a translucency slider computes none.
fn collimated_entry(
    scene: &Scene,
    geo: PatchGeometry<'_>,
    plan: &RelightPlan,
    materials_key: &str,
    lights_key: &str,
) -> Result<(Option<Collimated>, Option<String>), EngineError> {
    if matches!(
        plan.components,
        Components::Direct | Components::InterreflectionOnly
    ) || plan.lights.is_empty()
    {
        return Ok((None, None));
    }
    let tilt = scene.tilt_for(materials_key, &plan.materials(scene));
    let t = match tilt.as_ref() {
        TiltOf::None => return Ok((None, None)),
        TiltOf::Unsupported(why) => return Ok((None, Some(why.clone()))),
        TiltOf::Some(t) => t,
    };
    let key = format!("{lights_key}|{}", t.patches_key());
    let moments = scene.direct.moments(&key, || {
        let mut e = crate::collimated::tilted_irradiance(
            geo,
            &scene.occluder,
            &plan.lights,
            scene.bundle.manifest().unit_mm,
            t,
        );
        // The environment's bins, each a beam from its direction.
        if let (Some(vis), Some(radiance)) = (
            scene.bundle.environment_visibility(),
            crate::environment::bin_radiance_total(&scene.env(), &plan.lights)?,
        ) {
            let e = e.get_or_insert_with(|| vec![[[0.0f32; 3]; 4]; geo.centroid.len()]);
            crate::collimated::add_environment_moments(geo, vis, &radiance, t, e);
        }
        Ok(e)
    })?;
    Ok((moments.map(|e| (tilt, e)), None))
}

/// Milliseconds since `t`.
fn ms_since(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// Stages 1 and 2 for one plan: its direct light (timed as `direct_ms`, with the moments and
/// the lamps' walks), S for its materials (`materials_ms` when rebuilt), the path its
/// transport takes and the notes that say why.
pub(super) fn prepare(
    scene: &Scene,
    geo: PatchGeometry<'_>,
    plan: &RelightPlan,
) -> Result<Prepared, EngineError> {
    let t0 = Instant::now();
    // A request that keeps the last one's lights (a translucency slider) takes their
    // direct light from the scene's cache instead of tracing it again.
    let lights_key = serde_json::to_string(&plan.lights).unwrap_or_default();
    let irradiance = scene.direct.patches(&lights_key, || {
        crate::environment::direct_irradiance(&scene.env(), geo, &plan.lights)
    })?;
    let vertex = vertex_direct(scene, geo, plan, &lights_key)?;
    let direct_ms = ms_since(t0);
    let tm = Instant::now();
    let (materials, rebuilt) = match scene.materials_for(&plan.overrides)? {
        Some((m, rebuilt)) => (Some(m), rebuilt),
        None => (None, false),
    };
    let materials_ms = if rebuilt { ms_since(tm) } else { 0.0 };
    let (use_t, note) = path(scene, plan);
    let materials_key = serde_json::to_string(&plan.overrides).unwrap_or_default();
    let tc = Instant::now();
    let (collimated, tilt_note) = collimated_entry(scene, geo, plan, &materials_key, &lights_key)?;
    let lamp_walks = walked_beams(scene, geo, plan, &collimated, &lights_key)?;
    // The moments are direct light too (and the lamps' walks).
    let direct_ms = direct_ms + ms_since(tc);
    let slant = slant(scene, plan, &collimated, &materials_key);
    let note = notes(plan, [note, tilt_note], &lamp_walks);
    Ok(Prepared {
        irradiance,
        materials_key,
        collimated,
        slant,
        lamp_walks,
        materials,
        materials_ms,
        direct_ms,
        use_t,
        note,
        vertex,
    })
}

/// Whether the plan's transport takes the bundle's T (its components solve, they are
/// `full`, T exists and holds for its materials, and the plan does not ask for the
/// iterative solver), and, where `auto` falls back to the solver, why.
pub(super) fn path(scene: &Scene, plan: &RelightPlan) -> (bool, Option<String>) {
    let has_t = scene.bundle.transfer().is_some();
    let stale = transfer_stale(scene, &plan.overrides);
    let solves = crate::backend::solves(plan.components);
    let use_t = solves
        && plan.components == Components::Full
        && has_t
        && stale.is_none()
        && plan.solver != Solver::Iterative;
    let note = match (solves, plan.solver, has_t, &stale) {
        (false, _, _, _) => None,
        (true, Solver::Auto, true, Some(why)) => Some(format!("iterative: {why}")),
        (true, Solver::Auto, true, None) if plan.components != Components::Full => Some(format!(
            "iterative: T holds the full transport, not {}",
            plan.components.as_str()
        )),
        (true, Solver::Auto, false, _) => {
            Some("iterative: the bundle has no transfer matrix T".to_string())
        }
        _ => None,
    };
    (use_t, note)
}

/// The lamps' own beams walked into the simulated objects with the plan's materials
/// ([`crate::lampwalk`]), when the plan asks and its lamps enter them collimated; kept in
/// the scene's cache for these lights.
fn walked_beams(
    scene: &Scene,
    geo: PatchGeometry<'_>,
    plan: &RelightPlan,
    collimated: &Option<Collimated>,
    lights_key: &str,
) -> Result<Option<LampWalked>, EngineError> {
    let (Some((t, _)), Some(per)) = (collimated, plan.lamp_walks) else {
        return Ok(None);
    };
    let TiltOf::Some(t) = t.as_ref() else {
        return Ok(None);
    };
    let key = format!("{lights_key}|{}|{per}", t.patches_key());
    let materials = plan.materials(scene);
    let walked = scene.direct.lamp_walks(&key, || {
        crate::lampwalk::LampWalks::walk(
            &scene.bundle,
            geo,
            &scene.occluder,
            (&plan.lights, &materials),
            t,
            per,
            (&plan.stop, plan.work_limit),
        )
    })?;
    Ok(walked.map(|w| (w, materials.into_iter().cloned().collect())))
}

/// With the full transport: the tilt of the plan's simulated objects, for the light from
/// other surfaces entering them ([`crate::collimated::interreflected_moments`]); `None`
/// without such objects.
fn slant(
    scene: &Scene,
    plan: &RelightPlan,
    collimated: &Option<Collimated>,
    materials_key: &str,
) -> Option<Arc<TiltOf>> {
    (plan.components == Components::Full)
        .then(|| match collimated {
            Some((t, _)) => t.clone(),
            None => scene.tilt_for(materials_key, &plan.materials(scene)),
        })
        .filter(|t| matches!(t.as_ref(), TiltOf::Some(_)))
}

/// The plan's notes joined (the path's and the tilt's, then what the lamps' walks did),
/// `None` without any.
fn notes(
    plan: &RelightPlan,
    before: [Option<String>; 2],
    lamp_walks: &Option<LampWalked>,
) -> Option<String> {
    let walks_note = plan.lamp_walks.map(|_| match lamp_walks {
        Some((w, _)) => format!(
            "lamp_walks: the first scattering of the lamps walked along their beams, {} \
             walks from {} lit patches ({:.1} s, kept for these lights)",
            w.walks, w.sources, w.seconds
        ),
        None => "lamp_walks: nothing walked (no lamp lights a simulated object with \
                 these components)"
            .to_string(),
    });
    let [note, tilt_note] = before;
    let note = [note, tilt_note, walks_note]
        .into_iter()
        .flatten()
        .collect::<Vec<_>>();
    (!note.is_empty()).then(|| note.join("; "))
}
