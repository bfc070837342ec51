//! Relighting one scene on the CPU: request in, per-vertex radiance out.
//!
//! [`plan`] checks a request against the scene and this build (cheap, on the async side);
//! [`run`] and [`run_batch`] do the work and belong on a blocking thread. The work is a
//! pipeline of stages, each a function of its own:
//!
//! 0. *The whole relight on the backend* (`device::relight`): a plan that needs only the
//!    bundle's materials, lamps, environments and the solve goes to the scene's backend
//!    whole (the GPU: direct light, solve and vertex colours in one submission) and skips
//!    the rest.
//! 1. *Direct light* per plan (`prepare::prepare`): E per patch from the lights, shadowed,
//!    the direct light at the vertices of opaque surfaces ([`crate::vertexlight`]), the
//!    lamps' collimated entry into simulated objects ([`crate::collimated`]) and their walked
//!    beams ([`crate::lampwalk`]), each kept in the scene's caches for the next request.
//! 2. *S for the plan's materials* (same stage): the overrides' S rebuilt from the stored
//!    distances ([`crate::smatrix`]), and the path the plan's transport takes (T or the
//!    solver) with the note that says why.
//! 3. *Grouping* (`groups`): plans with the same materials, components, path and tolerance
//!    share one transport.
//! 4. *Transport and solve* per group (`transport::transport`): E and Bₑ stacked for the
//!    group's plans, the collimated terms, then no solve, the product with T, or the
//!    iterative solve from the warm start kept for these materials (and the start kept for
//!    the next one).
//! 5. *Colours* per plan (`colours::answer`): B/π per vertex, the direct term of opaque
//!    diffuse surfaces taken at the vertex, and the stats.

use std::time::{Duration, Instant};

use crate::radiosity::{PatchGeometry, Rgb, SolveParams};
use translux_proto::api::{Components, RelightRequest, RelightStats, Solver};
use translux_proto::light::Light;
use translux_proto::scene::Material;

use crate::error::EngineError;
use crate::scene::Scene;
use crate::specular::Gloss;
use crate::stop::Stop;
use translux_proto::api::DirectAt;

use prepare::Prepared;

mod colours;
mod device;
mod prepare;
mod transport;

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

pub use crate::vertexlight::per_pixel_direct;

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
    let geo = PatchGeometry {
        centroid: &scene.centroids,
        normal: &scene.normals,
    };
    // Stage 0: the plans the backend does whole.
    let mut out = device::relight(scene, plans);
    // Stages 1 and 2, plan by plan: direct light, then S for its materials.
    let mut prepared: Vec<Option<Prepared>> = Vec::with_capacity(plans.len());
    for (idx, plan) in plans.iter().enumerate() {
        if out[idx].is_some() {
            prepared.push(None);
            continue;
        }
        match prepare::prepare(scene, geo, plan) {
            Ok(p) => prepared.push(Some(p)),
            Err(e) => {
                out[idx] = Some(Err(e));
                prepared.push(None);
            }
        }
    }
    // Stage 3, then 4 and 5 group by group: the transport, then each plan's colours.
    for group in groups(plans, &prepared) {
        let answers = relight_group(scene, plans, &prepared, &group);
        for (&i, answer) in group.iter().zip(answers) {
            out[i] = Some(answer);
        }
    }
    out.into_iter()
        .map(|r| r.unwrap_or_else(|| Err(EngineError::internal("a relight was not run"))))
        .collect()
}

/// The plans that share a transport (indices into `plans`, in order): the prepared ones
/// with the same materials, components, path (T or not) and tolerance.
fn groups(plans: &[RelightPlan], prepared: &[Option<Prepared>]) -> Vec<Vec<usize>> {
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
    groups
}

/// One group's transport (timed as its solve) and each of its plans' answer, in the
/// group's order; a failed transport fails every plan of the group.
fn relight_group(
    scene: &Scene,
    plans: &[RelightPlan],
    prepared: &[Option<Prepared>],
    group: &[usize],
) -> Vec<Result<RelightOutput, EngineError>> {
    let t1 = Instant::now();
    let preps: Vec<&Prepared> = group.iter().filter_map(|&i| prepared[i].as_ref()).collect();
    let plan0 = &plans[group[0]];
    let params = SolveParams {
        tolerance: plan0.tolerance,
        ..solve_params()
    };
    let n = scene.bundle.patch_areas().len();
    let result = transport::transport(scene, plan0.components, &params, preps[0], &preps, n);
    let solve_ms = t1.elapsed().as_secs_f64() * 1e3;
    match result {
        Err(e) => group.iter().map(|_| Err(e.clone())).collect(),
        Ok((radiosity, ts)) => {
            let done = colours::Transported {
                radiosity: &radiosity,
                stats: &ts,
                solve_ms,
                batch: group.len(),
            };
            group
                .iter()
                .zip(&preps)
                .enumerate()
                .map(|(slot, (&i, p))| colours::answer(scene, &plans[i], p, &done, slot))
                .collect()
        }
    }
}
