//! Relighting one scene on the CPU: request in, per-vertex radiance out.
//!
//! [`plan`] checks a request against the scene and this build (cheap, on the async side);
//! [`run`] does the work (direct light with shadow rays, the diffuse solve, vertex colours
//! with direct light at the vertices of opaque surfaces)
//! and belongs on a blocking thread.

use std::borrow::Cow;
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::inverse;
use crate::radiosity::{Albedo, PatchGeometry, Rgb, Scatter, SolveParams, vertex_radiance};
use crate::scene::Warm;
use crate::solver::{Before, MAX_PRIMED_AGE, Primed, SolveError, SolveStats, solve_primed};
use crate::transport::{Pulled, Transport};
use translux_proto::api::{Components, RelightRequest, RelightStats, Solver};
use translux_proto::light::Light;
use translux_proto::scene::Material;

use crate::collimated::TiltOf;
use crate::error::EngineError;
use crate::scene::Scene;
use crate::smatrix::OverrideMaterials;
use crate::specular::Gloss;
use crate::stop::Stop;
use crate::vertexlight::VertexLit;
use translux_proto::api::DirectAt;

/// Most lights one request may carry (each costs a shadow ray per patch).
pub const MAX_LIGHTS: usize = 256;

/// A checked request, ready to run.
#[derive(Debug, Clone)]
pub struct RelightPlan {
    pub lights: Vec<Light>,
    pub components: Components,
    pub solver: Solver,
    /// Objects whose material the request replaces (index into the manifest's objects),
    /// as the transport sees them: without `specular`, and without the objects whose
    /// override changes only `specular` (S and the albedo do not depend on it).
    pub overrides: Vec<(usize, Material)>,
    /// Each object's glossy coat after the request's overrides (one per manifest object),
    /// for the specular pass of renders ([`crate::specular`]).
    pub gloss: Vec<Option<Gloss>>,
    /// Where the direct light of diffuse objects is evaluated; with
    /// [`DirectAt::Pixel`] their vertices get only the rest of the transport.
    pub direct_at: DirectAt,
    /// Relative residual the iterative solver stops at ([`solve_params`]'s 0.5% from
    /// [`plan`]; tests tighten it). Plans batch together only with equal tolerances.
    pub tolerance: f32,
    /// Walks per lamp along the lamps' own beams into simulated objects
    /// ([`crate::lampwalk`]); `None`: the stored walks' model alone.
    pub lamp_walks: Option<u32>,
    /// Stops the plan's long work early (its caller sets it: a server when the client
    /// went away or it is stopping). [`plan`] gives one that never fires.
    pub stop: Stop,
    /// The most time the plan's lamp walks may take (a server sets it per role); `None`:
    /// no limit. Past it the relight is refused with the time they would need.
    pub work_limit: Option<Duration>,
}

impl RelightPlan {
    /// Each object's material as the transport sees it: the override where the plan has
    /// one, else the bundle's (one per manifest object).
    pub fn materials<'a>(&'a self, scene: &'a Scene) -> Vec<&'a Material> {
        crate::smatrix::materials_with(&scene.bundle, &self.overrides)
    }
}

/// Validates `req` for `scene`: 400 `invalid` for out-of-range values (the message names the
/// field), 400 `unsupported` for valid requests this build cannot do yet. Nothing is ignored.
pub fn plan(scene: &Scene, req: RelightRequest) -> Result<RelightPlan, EngineError> {
    let manifest = scene.bundle.manifest();
    let (lights, given) = match req.lights {
        Some(lights) => (lights, true),
        None => (manifest.lights.clone(), false),
    };
    if lights.len() > MAX_LIGHTS {
        return Err(EngineError::invalid(format!(
            "lights has {} entries; at most {MAX_LIGHTS} are allowed per request",
            lights.len()
        )));
    }
    if given {
        for (i, l) in lights.iter().enumerate() {
            l.validate(&format!("lights[{i}]"))
                .map_err(|e| EngineError::invalid(e.to_string()))?;
        }
    }
    // Environment lights: the bundle's visibility and a readable map (cached for `run`).
    crate::environment::check(&scene.env(), &lights, given)?;

    // Material overrides: checked here, applied in `run` by rebuilding S from the bundle's
    // stored optical distances (no geometry work).
    let mut overrides = Vec::new();
    let mut gloss: Vec<Option<Gloss>> = manifest
        .objects
        .iter()
        .map(|o| Gloss::of(&o.material))
        .collect();
    for (name, material) in &req.materials {
        let Some(k) = manifest.objects.iter().position(|o| &o.name == name) else {
            let names: Vec<&str> = manifest.objects.iter().map(|o| o.name.as_str()).collect();
            return Err(EngineError::invalid(format!(
                "materials.{name}: scene {:?} has no object {name:?} (its objects are {})",
                scene.id,
                names.join(", ")
            )));
        };
        material
            .validate(&format!("materials.{name}"))
            .map_err(|e| EngineError::invalid(e.to_string()))?;
        let built = &manifest.objects[k].material;
        if matches!(material, Material::Translucent { .. })
            && !matches!(
                built,
                Material::Translucent { .. } | Material::Heterogeneous { .. }
            )
        {
            return Err(EngineError::unsupported(format!(
                "materials.{name}: {name:?} was precomputed as {}, and a translucent material \
                 needs the optical distances inside it, which only a translucent object's bundle \
                 holds; precompute the scene with {name:?} translucent to vary its translucency",
                built.kind()
            )));
        }
        if matches!(material, Material::ThinSheet { .. })
            && !matches!(built, Material::ThinSheet { .. })
        {
            return Err(EngineError::unsupported(format!(
                "materials.{name}: {name:?} was precomputed as {}, and a thin-sheet material \
                 needs the distances along the sheet and which side each pair is on, which only \
                 a thin sheet's bundle holds; precompute the scene with {name:?} as a thin sheet \
                 to vary its reflectance and transmittance",
                built.kind()
            )));
        }
        if matches!(material, Material::Simulated { .. })
            && !matches!(built, Material::Simulated { .. })
        {
            return Err(EngineError::unsupported(format!(
                "materials.{name}: {name:?} was precomputed as {}, and a simulated material \
                 re-weights the random walks stored for it, which only a simulated object's \
                 bundle holds; precompute the scene with {name:?} simulated",
                built.kind()
            )));
        }
        // A heterogeneous object's stored per-medium lengths serve new profiles for its
        // media, not another layout of media.
        if let Material::Heterogeneous {
            materials, pattern, ..
        } = material
        {
            let same = matches!(built, Material::Heterogeneous { materials: bm, pattern: bp, .. }
                if bm.len() == materials.len() && bp == pattern);
            if !same {
                return Err(EngineError::unsupported(format!(
                    "materials.{name}: {name:?} was precomputed as {}; a heterogeneous override \
                     can change the profiles of the media it was precomputed with, not their \
                     pattern or number (the lengths each path travels in each medium are \
                     geometry); precompute the scene with the new pattern",
                    built.kind()
                )));
            }
        }
        gloss[k] = Gloss::of(material);
        // A change of `specular` alone leaves the transport as it is: no S rebuild.
        let transport = material.without_specular();
        if material == built || transport != built.without_specular() {
            overrides.push((k, transport));
        }
    }

    // The transfer matrix holds (I − S F)⁻¹ S for the bundle's own S: it serves `full`
    // (the only component it represents) while the overrides leave S alone.
    if req.solver == Solver::Inverse {
        if scene.bundle.transfer().is_none() {
            return Err(EngineError::unsupported(format!(
                "solver \"inverse\": scene {:?} was precomputed without the transfer matrix T; \
                 precompute it with `translux-precompute ... --inverse`, or use \"auto\" or \
                 \"iterative\"",
                scene.id
            )));
        }
        if let Some(why) = transfer_stale(scene, &overrides) {
            return Err(EngineError::unsupported(format!(
                "solver \"inverse\": {why}; use \"auto\" or \"iterative\""
            )));
        }
        if !matches!(
            req.components,
            Components::Full | Components::Direct | Components::SubsurfaceOnly
        ) {
            return Err(EngineError::unsupported(format!(
                "solver \"inverse\": T = (I - S F)^-1 S gives the \"full\" transport; components \
                 {:?} need the iterative solver (use \"auto\" or \"iterative\")",
                req.components.as_str()
            )));
        }
    }
    if let Some(w) = req.lamp_walks
        && !(1..=crate::lampwalk::MAX_LAMP_WALKS).contains(&w)
    {
        return Err(EngineError::invalid(format!(
            "lamp_walks: {w} walks per lamp; give 1 to {}",
            crate::lampwalk::MAX_LAMP_WALKS
        )));
    }
    Ok(RelightPlan {
        lights,
        components: req.components,
        solver: req.solver,
        overrides,
        gloss,
        direct_at: req.direct_at,
        tolerance: solve_params().tolerance,
        lamp_walks: req.lamp_walks,
        stop: Stop::never(),
        work_limit: None,
    })
}

/// Per-vertex radiance and what it took.
#[derive(Debug, Clone)]
pub struct RelightOutput {
    /// B/π per vertex of the viewer mesh, in its order.
    pub radiance: Vec<Rgb>,
    pub stats: RelightStats,
}

/// The solver settings a relight uses (BiCGSTAB to the paper's 0.5% residual).
pub fn solve_params() -> SolveParams {
    SolveParams::default()
}

/// Why the bundle's T does not hold for these overrides, or `None` when it does: T depends
/// on S (translucency and albedo), not on what emitters emit.
pub fn transfer_stale(scene: &Scene, overrides: &[(usize, Material)]) -> Option<String> {
    let objects = &scene.bundle.manifest().objects;
    overrides.iter().find_map(|(k, m)| {
        let built = &objects[*k].material;
        let emitter_only =
            matches!(m, Material::Emitter { .. }) && matches!(built, Material::Emitter { .. });
        (!emitter_only).then(|| {
            format!(
                "materials.{} changes S (T was precomputed for the bundle's materials; only an \
                 emitter's radiance can change without making T stale)",
                objects[*k].name
            )
        })
    })
}

/// Runs a plan: E from the lights (shadowed), then the transport its components name (see
/// [`run_batch`]), then B/π per vertex, with the direct term of opaque diffuse surfaces
/// taken at the vertex itself ([`crate::vertexlight`]). CPU-heavy: call it off the async runtime.
pub fn run(scene: &Scene, plan: &RelightPlan) -> Result<RelightOutput, EngineError> {
    run_batch(scene, std::slice::from_ref(plan))
        .pop()
        .unwrap_or_else(|| Err(EngineError::internal("run_batch answered nothing")))
}

/// What one plan needs before the transport: its E, materials and the path it takes.
struct Prepared {
    irradiance: Arc<Vec<Rgb>>,
    materials: Option<Arc<OverrideMaterials>>,
    materials_key: String,
    materials_ms: f64,
    direct_ms: f64,
    use_t: bool,
    note: Option<String>,
    /// Direct light at the opaque diffuse vertices ([`crate::vertexlight`]).
    vertex: Option<VertexDirect>,
    /// Lamps' collimated entry into simulated objects ([`crate::collimated`]).
    collimated: Option<Collimated>,
    /// With the full transport and simulated objects: their Δ, G_u and G_v, for the
    /// direction the light from other surfaces arrives from
    /// ([`crate::collimated::interreflected_moments`]).
    slant: Option<Arc<TiltOf>>,
    /// The lamps' own beams walked into the simulated objects, when the plan asks, with the
    /// plan's materials (their σa re-weights the walks).
    lamp_walks: Option<(Arc<crate::lampwalk::LampWalks>, Vec<Material>)>,
}

/// The tilt of a plan's materials and [E_t, E_u, E_v, E_w] of its lamps ([`crate::collimated`]).
type Collimated = (Arc<TiltOf>, Arc<crate::scene::Moments>);

/// E at the vertices whose direct term is taken at the vertex, and what it replaces.
struct VertexDirect {
    lit: Arc<VertexLit>,
    /// With [`DirectAt::Pixel`]: which of `which` leave their direct term out of the answer.
    per_pixel: Option<Vec<bool>>,
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

/// The albedo a picture multiplies the per-pixel direct irradiance by for an object of
/// `material` ([`DirectAt::Pixel`]): a diffuse object's ρ; `None` for the others, which keep
/// their direct light at the vertices (a translucent object's is smoothed by S).
pub fn per_pixel_direct(material: &Material) -> Option<Rgb> {
    match material {
        Material::Diffuse { albedo, .. } => Some(*albedo),
        _ => None,
    }
}

/// Runs several plans for one scene (the worker pool batches concurrent relights this way);
/// answers one result per plan, in order. Each plan fails or succeeds on its own.
///
/// Plans with the same materials and components share the transport: with T, one pass over
/// T for all of their right-hand sides; with the iterative solver, one read of F and S per
/// iteration for all of their systems ([`crate::solver`]).
///
/// Components (docs/transport.md), with ρ̄ the opaque albedo of each patch (a translucent
/// patch's profile's total diffuse reflectance) and P = diag ρ̄:
/// - `full`: B = Bₑ + S(E + F B)
/// - `direct`: B = Bₑ + P E
/// - `subsurface_only`: B = Bₑ + S E
/// - `interreflection_only`: B = Bₑ + P(E + F B)
/// - `heuristic_a`: B = Bₑ + S E + P F B, i.e. (I − P F)⁻¹(Bₑ + S E)
/// - `heuristic_b`: B = Bₑ + S E + (I − P F)⁻¹ P F (Bₑ + P E)
///
/// Wherever S E appears, the lamps' light into simulated objects adds
/// Δ E_t + G_u E_u + G_v E_v + U E_w: it enters collimated at its own angle and direction,
/// not diffusely ([`crate::collimated`]). With `full`, the light other surfaces send into
/// them adds Δ E_t + G_u E_u + G_v E_v of F B, by the direction it arrives from
/// ([`crate::collimated::interreflected_moments`]): one correction solved after B.
/// Environment maps enter diffusely.
pub fn run_batch(scene: &Scene, plans: &[RelightPlan]) -> Vec<Result<RelightOutput, EngineError>> {
    let b = &scene.bundle;
    let geo = PatchGeometry {
        centroid: &scene.centroids,
        normal: &scene.normals,
    };
    let n = b.patch_areas().len();
    // Per plan: E and materials.
    let mut out: Vec<Option<Result<RelightOutput, EngineError>>> =
        plans.iter().map(|_| None).collect();
    let mut prepared: Vec<Option<Prepared>> = Vec::with_capacity(plans.len());
    for (idx, plan) in plans.iter().enumerate() {
        let t0 = Instant::now();
        // A request that keeps the last one's lights (a translucency slider) takes their
        // direct light from the scene's cache instead of tracing it again.
        let lights_key = serde_json::to_string(&plan.lights).unwrap_or_default();
        let irradiance = match scene.direct.patches(&lights_key, || {
            crate::environment::direct_irradiance(&scene.env(), geo, &plan.lights)
        }) {
            Ok(e) => e,
            Err(e) => {
                out[idx] = Some(Err(e));
                prepared.push(None);
                continue;
            }
        };
        let vertex = match vertex_direct(scene, geo, plan, &lights_key) {
            Ok(v) => v,
            Err(e) => {
                out[idx] = Some(Err(e));
                prepared.push(None);
                continue;
            }
        };
        let direct_ms = t0.elapsed().as_secs_f64() * 1e3;
        let tm = Instant::now();
        let (materials, rebuilt) = match scene.materials_for(&plan.overrides) {
            Ok(Some((m, rebuilt))) => (Some(m), rebuilt),
            Ok(None) => (None, false),
            Err(e) => {
                out[idx] = Some(Err(e));
                prepared.push(None);
                continue;
            }
        };
        let materials_ms = if rebuilt {
            tm.elapsed().as_secs_f64() * 1e3
        } else {
            0.0
        };
        let has_t = b.transfer().is_some();
        let stale = transfer_stale(scene, &plan.overrides);
        let solves = !matches!(
            plan.components,
            Components::Direct | Components::SubsurfaceOnly
        );
        let use_t = solves
            && plan.components == Components::Full
            && has_t
            && stale.is_none()
            && plan.solver != Solver::Iterative;
        let note = match (solves, plan.solver, has_t, &stale) {
            (false, _, _, _) => None,
            (true, Solver::Auto, true, Some(why)) => Some(format!("iterative: {why}")),
            (true, Solver::Auto, true, None) if plan.components != Components::Full => {
                Some(format!(
                    "iterative: T holds the full transport, not {}",
                    plan.components.as_str()
                ))
            }
            (true, Solver::Auto, false, _) => {
                Some("iterative: the bundle has no transfer matrix T".to_string())
            }
            _ => None,
        };
        let materials_key = serde_json::to_string(&plan.overrides).unwrap_or_default();
        let tc = Instant::now();
        let (collimated, tilt_note) =
            match collimated_entry(scene, geo, plan, &materials_key, &lights_key) {
                Ok(c) => c,
                Err(e) => {
                    out[idx] = Some(Err(e));
                    prepared.push(None);
                    continue;
                }
            };
        let lamp_walks = match (&collimated, plan.lamp_walks) {
            (Some((t, _)), Some(per)) => match t.as_ref() {
                TiltOf::Some(t) => {
                    let key = format!("{lights_key}|{}|{per}", t.patches_key());
                    let materials = plan.materials(scene);
                    let walked = scene.direct.lamp_walks(&key, || {
                        crate::lampwalk::LampWalks::walk(
                            b,
                            geo,
                            &scene.occluder,
                            (&plan.lights, &materials),
                            t,
                            per,
                            (&plan.stop, plan.work_limit),
                        )
                    });
                    match walked {
                        Ok(w) => w.map(|w| (w, materials.into_iter().cloned().collect())),
                        Err(e) => {
                            out[idx] = Some(Err(e));
                            prepared.push(None);
                            continue;
                        }
                    }
                }
                _ => None,
            },
            _ => None,
        };
        // The moments are direct light too (and the lamps' walks).
        let direct_ms = direct_ms + tc.elapsed().as_secs_f64() * 1e3;
        let slant = (plan.components == Components::Full)
            .then(|| match &collimated {
                Some((t, _)) => t.clone(),
                None => scene.tilt_for(&materials_key, &plan.materials(scene)),
            })
            .filter(|t| matches!(t.as_ref(), TiltOf::Some(_)));
        let walks_note = plan.lamp_walks.map(|_| match &lamp_walks {
            Some((w, _)) => format!(
                "lamp_walks: the first scattering of the lamps walked along their beams, {} \
                 walks from {} lit patches ({:.1} s, kept for these lights)",
                w.walks, w.sources, w.seconds
            ),
            None => "lamp_walks: nothing walked (no lamp lights a simulated object with \
                     these components)"
                .to_string(),
        });
        let note = [note, tilt_note, walks_note]
            .into_iter()
            .flatten()
            .collect::<Vec<_>>();
        let note = (!note.is_empty()).then(|| note.join("; "));
        prepared.push(Some(Prepared {
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
        }));
    }

    // Groups: same materials, components and path.
    let mut groups: Vec<Vec<usize>> = Vec::new();
    for (idx, p) in prepared.iter().enumerate() {
        let Some(p) = p else { continue };
        let key = |q: &Prepared, i: usize| {
            (
                q.materials_key.clone(),
                plans[i].components,
                q.use_t,
                plans[i].tolerance.to_bits(),
            )
        };
        match groups.iter_mut().find(|g| {
            let first = g[0];
            prepared[first]
                .as_ref()
                .is_some_and(|q| key(q, first) == key(p, idx))
        }) {
            Some(g) => g.push(idx),
            None => groups.push(vec![idx]),
        }
    }

    for group in groups {
        let t1 = Instant::now();
        let preps: Vec<&Prepared> = group.iter().filter_map(|&i| prepared[i].as_ref()).collect();
        let first = preps[0];
        let plan0 = &plans[group[0]];
        let params = SolveParams {
            tolerance: plan0.tolerance,
            ..solve_params()
        };
        let result = transport(scene, plan0.components, &params, first, &preps, n);
        let solve_ms = t1.elapsed().as_secs_f64() * 1e3;
        match result {
            Err(e) => {
                for &i in &group {
                    out[i] = Some(Err(e.clone()));
                }
            }
            Ok((radiosity, ts)) => {
                for (slot, (&i, p)) in group.iter().zip(&preps).enumerate() {
                    let rad: Vec<Rgb> = (0..n)
                        .map(|j| {
                            std::array::from_fn(|c| radiosity[j * 3 * group.len() + 3 * slot + c])
                        })
                        .collect();
                    let mut radiance = vertex_radiance(
                        b.triangle_vertices(),
                        b.patch_areas(),
                        b.vertex_positions().len(),
                        &rad,
                    );
                    let mut auto_exposure = None;
                    if let Some(v) = &p.vertex {
                        let albedo = match &p.materials {
                            Some(m) => m.albedo.as_slice(),
                            None => b.patch_albedo(),
                        };
                        let terms = crate::vertexlight::PatchTerms {
                            radiosity: &rad,
                            irradiance: v.lit.at_patch.as_deref().unwrap_or(&p.irradiance),
                            albedo,
                        };
                        let means =
                            crate::vertexlight::VertexMeans::new(b, scene.vertex_samples(), terms);
                        means.set(&v.lit.which, &v.lit.at_vertex, &mut radiance);
                        if let Some(skip) = &v.per_pixel {
                            // The exposure of the whole answer, then the answer without the
                            // direct term the picture adds per pixel.
                            auto_exposure = Some(crate::render::auto_exposure(&radiance));
                            let e: Vec<Rgb> = v
                                .lit
                                .at_vertex
                                .iter()
                                .zip(skip)
                                .map(|(e, &s)| if s { [0.0; 3] } else { *e })
                                .collect();
                            means.set(&v.lit.which, &e, &mut radiance);
                        }
                    }
                    if plans[i].direct_at == DirectAt::Pixel && auto_exposure.is_none() {
                        auto_exposure = Some(crate::render::auto_exposure(&radiance));
                    }
                    // Finite inputs can still overflow f32 (an intensity near f32::MAX);
                    // never answer NaN or infinity (JSON has no such numbers).
                    if let Some(k) = radiance
                        .iter()
                        .position(|v| !v.iter().all(|x| x.is_finite()))
                    {
                        out[i] = Some(Err(EngineError::invalid(format!(
                            "lights: the result overflows (radiance at vertex {k} is not \
                             finite); use smaller intensities or irradiances"
                        ))));
                        continue;
                    }
                    let stats = RelightStats {
                        solver: ts.solver.to_string(),
                        components: plans[i].components,
                        iterations: ts.iterations,
                        residual: ts.residual,
                        converged: ts.converged,
                        ms: p.direct_ms + p.materials_ms + solve_ms,
                        direct_ms: p.direct_ms,
                        solve_ms,
                        materials_ms: p.materials_ms,
                        materials_on: p.materials.as_ref().map(|_| "cpu".to_string()),
                        lights: plans[i].lights.len(),
                        products: ts.products,
                        warm: ts.warm,
                        batch: group.len(),
                        note: p.note.clone(),
                        auto_exposure,
                    };
                    out[i] = Some(Ok(RelightOutput { radiance, stats }));
                }
            }
        }
    }
    out.into_iter()
        .map(|r| r.unwrap_or_else(|| Err(EngineError::internal("a relight was not run"))))
        .collect()
}

/// What the transport of one group did.
struct TransportStats {
    solver: &'static str,
    iterations: u32,
    products: u32,
    residual: f32,
    converged: bool,
    warm: bool,
}

/// The transport for a group of plans with the same materials and components: radiosity
/// `[patch][k·3]` for the k plans.
fn transport(
    scene: &Scene,
    components: Components,
    params: &SolveParams,
    first: &Prepared,
    preps: &[&Prepared],
    n: usize,
) -> Result<(Vec<f32>, TransportStats), EngineError> {
    let b = &scene.bundle;
    let k = preps.len();
    let ch = 3 * k;
    let (albedo, emission) = match &first.materials {
        Some(m) => (m.albedo.as_slice(), m.emission.as_slice()),
        None => (b.patch_albedo(), b.patch_emission()),
    };
    let (s_view, columns) = match &first.materials {
        Some(m) => m.s_parts(),
        None => (b.subsurface(), None),
    };
    let s = crate::transport::subsurface_operator_scaled(b, s_view, columns);
    let s = s.as_ref();
    let p = Albedo(albedo);
    let f = Transport::of(b);
    // Stacked E: [patch][plan][rgb].
    let mut e = vec![0.0f32; n * ch];
    for (slot, q) in preps.iter().enumerate() {
        for j in 0..n {
            e[j * ch + 3 * slot..j * ch + 3 * slot + 3].copy_from_slice(&q.irradiance[j]);
        }
    }
    // Bₑ repeated per plan.
    let be: Vec<f32> = (0..n)
        .flat_map(|j| std::iter::repeat_n(emission[j], k).flatten())
        .collect();
    let add = |a: &mut [f32], x: &[f32]| {
        for (a, x) in a.iter_mut().zip(x) {
            *a += x;
        }
    };
    let none = |x: Vec<f32>| {
        (
            x,
            TransportStats {
                solver: "none",
                iterations: 0,
                products: 0,
                residual: 0.0,
                converged: true,
                warm: false,
            },
        )
    };
    // Lamps' collimated entry into simulated objects: y = Δ E_t + G_u E_u + G_v E_v + U E_w,
    // added where S E is.
    let tilt = first
        .collimated
        .as_ref()
        .and_then(|(t, _)| match t.as_ref() {
            TiltOf::Some(t) => Some(t),
            _ => None,
        });
    let y: Option<Vec<f32>> = tilt.map(|t| {
        // [E_t, E_u, E_v, E_w] per patch and plan.
        let mut e_t = vec![0.0f32; n * 4 * ch];
        for (slot, q) in preps.iter().enumerate() {
            if let Some((_, et)) = &q.collimated {
                for (j, v) in et.iter().enumerate() {
                    let at = j * 4 * ch + 12 * slot;
                    e_t[at..at + 12].copy_from_slice(v.as_flattened());
                }
            }
        }
        let mut y = vec![0.0f32; n * ch];
        crate::collimated::add_first_scatter(t, &e_t, k, &mut y);
        // Where a plan walked its lamps' own beams: the walked first scattering in place of
        // the model's ([`crate::lampwalk`]).
        for (slot, q) in preps.iter().enumerate() {
            if let Some((w, materials)) = &q.lamp_walks {
                let mut c = vec![0.0f32; 3 * n];
                let materials: Vec<&Material> = materials.iter().collect();
                w.add_correction(&materials, s, t, &mut c);
                for j in 0..n {
                    for ch3 in 0..3 {
                        y[j * ch + 3 * slot + ch3] += c[3 * j + ch3];
                    }
                }
            }
        }
        y
    });
    let add_y = |a: &mut [f32]| {
        if let Some(y) = &y {
            add(a, y);
        }
    };
    // y = Δ E_t + G_u E_u + G_v E_v of F x entering the simulated objects from where it
    // comes (the full transport only: elsewhere F B reaches them through P or not at all).
    let slant = match first.slant.as_deref() {
        Some(TiltOf::Some(t)) if components == Components::Full => Some(t),
        _ => None,
    };
    let suffix = format!("|{}", components.as_str());
    let key = format!("{}{suffix}", first.materials_key);
    // Where the correction for the light from other surfaces is kept (below).
    let (ckey, csuffix) = (format!("{key}|slant"), format!("{suffix}|slant"));
    // B += c, c = (I − S F)⁻¹ y for y of B: solved to the answer's own tolerance relative to
    // B (c is a few per cent of it), from the last correction kept (under these materials
    // with its products, like the answer's: a request made again costs no product).
    let correct = |x: &mut [f32]| -> Result<Option<SolveStats>, EngineError> {
        let Some(t) = slant else {
            return Ok(None);
        };
        let mut y = vec![0.0f32; n * ch];
        let weights = scene.slant_for(t);
        crate::collimated::add_interreflected_first_scatter(t, &weights, &f, x, k, &mut y);
        let norms = |v: &[f32]| -> Vec<f64> {
            (0..ch)
                .map(|c| {
                    v.iter()
                        .skip(c)
                        .step_by(ch)
                        .map(|a| f64::from(*a).powi(2))
                        .sum::<f64>()
                        .sqrt()
                })
                .collect()
        };
        let scale = norms(x)
            .iter()
            .zip(norms(&y))
            .filter(|(_, y)| *y > 0.0)
            .map(|(x, y)| x / y)
            .fold(f64::INFINITY, f64::min);
        if !scale.is_finite() {
            return Ok(None);
        }
        let cparams = SolveParams {
            tolerance: (f64::from(params.tolerance) * scale).clamp(f64::from(params.tolerance), 0.5)
                as f32,
            ..*params
        };
        let kept = scene.warm.history(&ckey, &csuffix);
        let start = kept
            .as_ref()
            .map(|h| KeptStart::of(h, n, k))
            .unwrap_or_default();
        let primed = start.fx.as_deref().map(|fx| Primed {
            fx,
            kfx: start.kfx.as_deref(),
            before: None,
            age: start.age,
        });
        let on = Solve {
            f: &f,
            kop: s,
            k,
            params: &cparams,
            device: true,
        };
        let (c, more, products) = on.run(scene, first, &y, start.x.as_deref(), primed)?;
        drop(start);
        drop(kept);
        keep(scene, ckey.clone(), &c, products, n, ch);
        for (x, c) in x.iter_mut().zip(&c) {
            *x += c;
        }
        // Its residual on the answer's scale (relative to B, not to y).
        Ok(Some(SolveStats {
            residual: (f64::from(more.residual) / scale) as f32,
            ..more
        }))
    };
    let mut se = vec![0.0f32; n * ch];
    match components {
        Components::Direct => {
            // B = Bₑ + P E.
            p.apply_multi(&e, &mut se, ch);
            add(&mut se, &be);
            return Ok(none(se));
        }
        Components::SubsurfaceOnly => {
            s.apply_multi(&e, &mut se, ch);
            add(&mut se, &be);
            add_y(&mut se);
            return Ok(none(se));
        }
        _ => {}
    }
    if first.use_t {
        // B = Bₑ + S v + R v, v = E + F Bₑ (R = T − S, stored). With lamps' collimated
        // entry (y, above): B = Bₑ + y + T(E + F (Bₑ + y)).
        let t = b
            .transfer()
            .ok_or_else(|| EngineError::internal("the transfer matrix vanished"))?;
        let mut v = vec![0.0f32; n * ch];
        let mut lit = be.clone();
        add_y(&mut lit);
        f.apply_multi(&lit, &mut v, ch, &mut Pulled::default());
        add(&mut v, &e);
        let mut bvec = vec![0.0f32; n * ch];
        s.apply_multi(&v, &mut bvec, ch);
        let mut rv = vec![0.0f32; n * ch];
        // The product over T on the scene's backend ([`crate::backend`]) when it takes it, else on the CPU.
        if !scene
            .backend()
            .transfer_product(scene.view(), &v, k, &mut rv)
        {
            inverse::apply_stored(t.bits, t.scale, t.n, &v, k, &mut rv);
        }
        add(&mut bvec, &rv);
        add(&mut bvec, &lit);
        // The light from other surfaces, entering simulated objects from where it comes.
        let more = correct(&mut bvec)?;
        return Ok((
            bvec,
            TransportStats {
                solver: "inverse",
                iterations: more.map_or(0, |m| m.iterations),
                products: 1 + more.map_or(0, |m| m.products),
                residual: more.map_or(0.0, |m| m.residual),
                converged: more.is_none_or(|m| m.converged),
                warm: false,
            },
        ));
    }
    // The iterative path: (I − K F) x = rhs, from the answer kept under these materials
    // (or the last under others).
    let kept = scene.warm.history(&key, &suffix);
    let KeptStart {
        x: warm,
        fx,
        mut kfx,
        age,
    } = kept
        .as_ref()
        .map(|h| KeptStart::of(h, n, k))
        .unwrap_or_default();
    // The answer before it, to extrapolate along the last step.
    type Spread<'a> = (Cow<'a, [f32]>, Cow<'a, [f32]>, Option<Cow<'a, [f32]>>, u32);
    let mut before: Option<Spread> = kept
        .as_ref()
        .and_then(|h| h.before.as_ref())
        // Products that old end the chain (the start stays at x₀), so they never hold
        // back x₀'s own: right after a fresh check the next solve still takes them.
        .filter(|(w, _)| w.age < MAX_PRIMED_AGE)
        .and_then(|(w, same)| {
            Some((
                spread(&w.x, n, k)?,
                spread(w.fx.as_ref()?, n, k)?,
                w.kfx
                    .as_ref()
                    .filter(|_| *same)
                    .and_then(|v| spread(v, n, k)),
                w.age,
            ))
        });
    // How many solves ago the kept products last came out of a pass over F.
    let age = age.max(before.as_ref().map_or(0, |b| b.3));
    let (kop, mut rhs): (&dyn Scatter, Vec<f32>) = match components {
        Components::Full => {
            // A translucency change on the CPU extrapolated along its last step needs S E
            // (for b), S F x₀ and S F x₋₁ under the new S: one pass over S for all three
            // (S is read once, not twice), up to the fixed widths' 8 RGB systems.
            let fuse = scene.backend().name() == "cpu"
                && kfx.is_none()
                && 3 * ch <= 24
                && age < MAX_PRIMED_AGE;
            match (&fx, &mut before) {
                (Some(fx0), Some((_, fx1, kfx1 @ None, _))) if fuse => {
                    let [se1, k0, k1]: [Vec<f32>; 3] =
                        crate::linalg::scatter_each(s, &[&e, fx0, fx1], ch)
                            .try_into()
                            .expect("one product per vector");
                    se = se1;
                    kfx = Some(Cow::Owned(k0));
                    *kfx1 = Some(Cow::Owned(k1));
                }
                _ => s.apply_multi(&e, &mut se, ch),
            }
            add(&mut se, &be);
            add_y(&mut se);
            (s, se)
        }
        Components::InterreflectionOnly | Components::HeuristicB => {
            p.apply_multi(&e, &mut se, ch);
            add(&mut se, &be);
            (&p, se)
        }
        Components::HeuristicA => {
            s.apply_multi(&e, &mut se, ch);
            add(&mut se, &be);
            add_y(&mut se);
            (&p, se)
        }
        Components::Direct | Components::SubsurfaceOnly => unreachable!("handled above"),
    };
    if components == Components::HeuristicB {
        // Y = (I − P F)⁻¹ P F (Bₑ + P E) solves (I − P F) Y = P F (Bₑ + P E).
        let mut fx = vec![0.0f32; n * ch];
        f.apply_multi(&rhs, &mut fx, ch, &mut Pulled::default());
        p.apply_multi(&fx, &mut rhs, ch);
    }
    let primed = fx.as_deref().map(|fx| Primed {
        fx,
        kfx: kfx.as_deref(),
        before: before.as_ref().map(|(x, fx, kfx, _)| Before {
            x,
            fx,
            kfx: kfx.as_deref(),
        }),
        age,
    });
    let on = Solve {
        f: &f,
        kop,
        k,
        params,
        device: components == Components::Full,
    };
    let (mut x, st, products) = on.run(scene, first, &rhs, warm.as_deref(), primed)?;
    // Keep the last system's answer for the next relight with these materials (never one
    // that overflowed: it would poison the next solve), with its products when the CPU
    // solved it.
    // The kept answers are let go first, so the one replaced below moves instead of copying.
    drop(kept);
    keep(scene, key, &x, products, n, ch);
    // The light from other surfaces entering simulated objects from where it comes (kept
    // above without it: the next solve's start and products are this system's).
    let mut st = st;
    if let Some(more) = correct(&mut x)? {
        st.iterations += more.iterations;
        st.products += more.products;
        st.residual = st.residual.max(more.residual);
        st.converged &= more.converged;
    }
    if components == Components::HeuristicB {
        // B = Bₑ + S E + Y.
        let mut sev = vec![0.0f32; n * ch];
        s.apply_multi(&e, &mut sev, ch);
        add(&mut x, &sev);
        add(&mut x, &be);
        add_y(&mut x);
    }
    Ok((
        x,
        TransportStats {
            solver: st.method.as_str(),
            iterations: st.iterations,
            products: st.products,
            residual: st.residual,
            converged: st.converged,
            warm: st.warm,
        },
    ))
}

/// One solve of (I − K F) x = rhs for k stacked RGB systems.
struct Solve<'a> {
    f: &'a Transport<'a>,
    kop: &'a dyn Scatter,
    k: usize,
    params: &'a SolveParams,
    /// K is the materials' S (the full transport): the scene's backend may take it.
    device: bool,
}

/// F x, K F x and their age from a CPU solve ([`keep`]).
type Products = (Vec<f32>, Vec<f32>, u32);

impl Solve<'_> {
    /// On the scene's backend ([`crate::backend`]) when it takes the system, else on the
    /// CPU from `warm` and the kept products `primed`: x, the solve's stats and, from the
    /// CPU, the products to keep.
    fn run(
        &self,
        scene: &Scene,
        first: &Prepared,
        rhs: &[f32],
        warm: Option<&[f32]>,
        primed: Option<Primed<'_>>,
    ) -> Result<(Vec<f32>, SolveStats, Option<Products>), EngineError> {
        let on_device = self
            .device
            .then(|| {
                scene.backend().solve_rhs(
                    scene.view(),
                    first.materials.as_ref(),
                    rhs,
                    self.k,
                    self.params,
                    warm,
                )
            })
            .flatten();
        if let Some((x, st)) = on_device {
            return Ok((x, st, None));
        }
        let s = solve_primed(self.f, self.kop, rhs, 3 * self.k, self.params, warm, primed)
            .map_err(|e| match e {
                SolveError::Overflow => EngineError::invalid(format!("lights: {e}")),
                e => EngineError::internal(e.to_string()),
            })?;
        Ok((s.x, s.stats, Some((s.fx, s.kfx, s.age))))
    }
}

/// A kept answer spread over a batch of k RGB systems: a single relight borrows it as it
/// is, a batch's systems all start from it.
fn spread(w: &[f32], n: usize, k: usize) -> Option<Cow<'_, [f32]>> {
    (w.len() == 3 * n).then(|| match k {
        1 => Cow::Borrowed(w),
        _ => Cow::Owned(
            (0..n)
                .flat_map(|j| {
                    std::iter::repeat_n(&w[3 * j..3 * j + 3], k)
                        .flatten()
                        .copied()
                })
                .collect(),
        ),
    })
}

/// Where a solve starts from the answer kept for its key: x₀, F x₀ (F is the bundle's: it
/// holds under any materials) and K F x₀ (only under the same ones), each spread over the
/// batch, and how many solves ago those products came out of a pass over F.
#[derive(Default)]
struct KeptStart<'a> {
    x: Option<Cow<'a, [f32]>>,
    fx: Option<Cow<'a, [f32]>>,
    kfx: Option<Cow<'a, [f32]>>,
    age: u32,
}

impl<'a> KeptStart<'a> {
    fn of(kept: &'a crate::scene::Kept, n: usize, k: usize) -> Self {
        KeptStart {
            x: spread(&kept.last.x, n, k),
            fx: kept.last.fx.as_ref().and_then(|w| spread(w, n, k)),
            kfx: (kept.same)
                .then_some(kept.last.kfx.as_ref())
                .flatten()
                .and_then(|w| spread(w, n, k)),
            age: kept.last.age,
        }
    }
}

/// Keeps the batch's last system of `x` under `key` for the next solve, with its products
/// F x and K F x when the CPU solved it (`products`); never an answer that is not finite
/// (it would poison the next solve).
fn keep(scene: &Scene, key: String, x: &[f32], products: Option<Products>, n: usize, ch: usize) {
    if !x.iter().all(|v| v.is_finite()) {
        return;
    }
    let last = |v: &[f32]| -> Vec<f32> {
        (0..n)
            .flat_map(|j| v[j * ch + ch - 3..j * ch + ch].iter().copied())
            .collect()
    };
    let (fx, kfx, age) = match &products {
        Some((fx, kfx, age)) => (Some(last(fx)), Some(last(kfx)), *age),
        None => (None, None, 0),
    };
    scene.warm.put(
        key,
        Warm {
            x: last(x),
            fx,
            kfx,
            age,
            prev: None,
        },
    );
}
