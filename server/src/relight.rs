//! Relighting one scene on the CPU: request in, per-vertex radiance out.
//!
//! [`plan`] checks a request against the scene and this build (cheap, on the async side);
//! [`run`] does the work (direct light with shadow rays, the diffuse solve, vertex colours)
//! and belongs on a blocking thread.

use std::time::Instant;

use translux_precompute::radiosity::{
    PatchGeometry, Rgb, SolveParams, SparseScatter, direct_irradiance, solve, vertex_radiance,
};
use translux_proto::api::{Components, RelightRequest, RelightStats, Solver};
use translux_proto::light::Light;
use translux_proto::scene::Material;

use crate::error::AppError;
use crate::state::Scene;

/// Most lights one request may carry (each costs a shadow ray per patch).
pub const MAX_LIGHTS: usize = 256;

/// A checked request, ready to run.
#[derive(Debug, Clone)]
pub struct RelightPlan {
    pub lights: Vec<Light>,
    pub components: Components,
    pub solver: Solver,
    /// Objects whose material the request replaces (index into the manifest's objects).
    pub overrides: Vec<(usize, Material)>,
}

/// Validates `req` for `scene`: 400 `invalid` for out-of-range values (the message names the
/// field), 400 `unsupported` for valid requests this build cannot do yet. Nothing is ignored.
pub fn plan(scene: &Scene, req: RelightRequest) -> Result<RelightPlan, AppError> {
    let manifest = scene.bundle.manifest();
    let (lights, given) = match req.lights {
        Some(lights) => (lights, true),
        None => (manifest.lights.clone(), false),
    };
    if lights.len() > MAX_LIGHTS {
        return Err(AppError::invalid(format!(
            "lights has {} entries; at most {MAX_LIGHTS} are allowed per request",
            lights.len()
        )));
    }
    if given {
        for (i, l) in lights.iter().enumerate() {
            l.validate(&format!("lights[{i}]"))
                .map_err(|e| AppError::invalid(e.to_string()))?;
        }
    }
    for (i, l) in lights.iter().enumerate() {
        if !matches!(
            l,
            Light::Point { .. } | Light::Spot { .. } | Light::Directional { .. }
        ) {
            let whose = if given {
                ""
            } else {
                " (one of the scene's default lights)"
            };
            return Err(AppError::unsupported(format!(
                "lights[{i}]{whose}: {} lights are not supported yet; this build evaluates \
                 point, spot and directional lights",
                l.kind()
            )));
        }
    }

    // Material overrides: checked here, applied in `run` by rebuilding S from the bundle's
    // stored optical distances (no geometry work).
    let mut overrides = Vec::new();
    for (name, material) in &req.materials {
        let Some(k) = manifest.objects.iter().position(|o| &o.name == name) else {
            let names: Vec<&str> = manifest.objects.iter().map(|o| o.name.as_str()).collect();
            return Err(AppError::invalid(format!(
                "materials.{name}: scene {:?} has no object {name:?} (its objects are {})",
                scene.id,
                names.join(", ")
            )));
        };
        material
            .validate(&format!("materials.{name}"))
            .map_err(|e| AppError::invalid(e.to_string()))?;
        let built = &manifest.objects[k].material;
        if matches!(material, Material::Translucent { .. })
            && !matches!(
                built,
                Material::Translucent { .. } | Material::Heterogeneous { .. }
            )
        {
            return Err(AppError::unsupported(format!(
                "materials.{name}: {name:?} was precomputed as {}, and a translucent material \
                 needs the optical distances inside it, which only a translucent object's bundle \
                 holds; precompute the scene with {name:?} translucent to vary its translucency",
                built.kind()
            )));
        }
        if matches!(material, Material::ThinSheet { .. })
            && !matches!(built, Material::ThinSheet { .. })
        {
            return Err(AppError::unsupported(format!(
                "materials.{name}: {name:?} was precomputed as {}, and a thin-sheet material \
                 needs the distances along the sheet and which side each pair is on, which only \
                 a thin sheet's bundle holds; precompute the scene with {name:?} as a thin sheet \
                 to vary its reflectance and transmittance",
                built.kind()
            )));
        }
        // A heterogeneous object's stored per-medium lengths serve new profiles for its
        // media, not another layout of media.
        if let Material::Heterogeneous { materials, pattern } = material {
            let same = matches!(built, Material::Heterogeneous { materials: bm, pattern: bp }
                if bm.len() == materials.len() && bp == pattern);
            if !same {
                return Err(AppError::unsupported(format!(
                    "materials.{name}: {name:?} was precomputed as {}; a heterogeneous override \
                     can change the profiles of the media it was precomputed with, not their \
                     pattern or number (the lengths each path travels in each medium are \
                     geometry); precompute the scene with the new pattern",
                    built.kind()
                )));
            }
        }
        if material.kind() != "diffuse"
            && material.kind() != "emitter"
            && material.kind() != "translucent"
            && material.kind() != "thin_sheet"
            && material.kind() != "heterogeneous"
        {
            return Err(AppError::unsupported(format!(
                "materials.{name}: {} overrides are not supported yet",
                material.kind()
            )));
        }
        overrides.push((k, material.clone()));
    }

    match req.components {
        Components::Full | Components::Direct => {}
        other => {
            return Err(AppError::unsupported(format!(
                "components {:?} is not supported yet; this build supports \"full\" and \"direct\"",
                other.as_str()
            )));
        }
    }
    match req.solver {
        Solver::Auto | Solver::Iterative => {}
        Solver::Inverse => {
            return Err(AppError::unsupported(
                "solver \"inverse\" is not supported yet (bundles hold no transfer matrix T); \
                 use \"auto\" or \"iterative\"",
            ));
        }
    }
    Ok(RelightPlan {
        lights,
        components: req.components,
        solver: req.solver,
        overrides,
    })
}

/// Per-vertex radiance and what it took.
#[derive(Debug, Clone)]
pub struct RelightOutput {
    /// B/π per vertex of the viewer mesh, in its order.
    pub radiance: Vec<Rgb>,
    pub stats: RelightStats,
}

/// The solver settings a relight uses (the paper's 0.5% residual).
pub fn solve_params() -> SolveParams {
    SolveParams::default()
}

/// Runs a plan: E from the lights (shadowed), then B = Bₑ + S(E + F B) (`full`, S from the
/// bundle: subsurface scattering in translucent objects, ρ on the diagonal of opaque ones)
/// or B = Bₑ + ρE (`direct`: one local diffuse bounce, translucent patches at their profile's
/// total diffuse reflectance), then B/π per vertex. CPU-heavy: call it off the async runtime.
pub fn run(scene: &Scene, plan: &RelightPlan) -> Result<RelightOutput, AppError> {
    let t0 = Instant::now();
    let b = &scene.bundle;
    let geo = PatchGeometry {
        centroid: &scene.centroids,
        normal: &scene.normals,
    };
    let irradiance = direct_irradiance(geo, &scene.occluder, &plan.lights, b.manifest().unit_mm)
        .map_err(|e| AppError::unsupported(e.to_string()))?;
    let direct_ms = t0.elapsed().as_secs_f64() * 1e3;

    // Materials: the bundle's, or rebuilt for the request's overrides.
    let tm = Instant::now();
    let (overridden, rebuilt) = match scene.materials_for(&plan.overrides)? {
        Some((m, rebuilt)) => (Some(m), rebuilt),
        None => (None, false),
    };
    let materials_ms = if rebuilt {
        tm.elapsed().as_secs_f64() * 1e3
    } else {
        0.0
    };
    let (albedo, emission) = match &overridden {
        Some(m) => (m.albedo.as_slice(), m.emission.as_slice()),
        None => (b.patch_albedo(), b.patch_emission()),
    };
    let t1 = Instant::now();
    let (radiosity, solver, iterations, residual, converged) = match plan.components {
        Components::Direct => {
            let radiosity: Vec<Rgb> = (0..albedo.len())
                .map(|i| std::array::from_fn(|c| emission[i][c] + albedo[i][c] * irradiance[i][c]))
                .collect();
            (radiosity, "none", 0, 0.0, true)
        }
        _ => {
            let f = b.form_factors();
            let scatter = match &overridden {
                Some(m) => SparseScatter(m.s_view()),
                None => SparseScatter(b.subsurface()),
            };
            let (radiosity, s) = solve(&f, &scatter, emission, &irradiance, &solve_params(), None)
                .map_err(|e| AppError::unsupported(e.to_string()))?;
            (radiosity, "jacobi", s.iterations, s.residual, s.converged)
        }
    };
    let solve_ms = t1.elapsed().as_secs_f64() * 1e3;
    let radiance = vertex_radiance(
        b.triangle_vertices(),
        b.patch_areas(),
        b.vertex_positions().len(),
        &radiosity,
    );
    // Finite inputs can still overflow f32 (an intensity near f32::MAX); never answer NaN or
    // infinity (JSON has no such numbers).
    if let Some(k) = radiance
        .iter()
        .position(|v| !v.iter().all(|x| x.is_finite()))
    {
        return Err(AppError::invalid(format!(
            "lights: the result overflows (radiance at vertex {k} is not finite); use smaller \
             intensities or irradiances"
        )));
    }
    let stats = RelightStats {
        solver: solver.to_string(),
        components: plan.components,
        iterations,
        residual,
        converged,
        ms: t0.elapsed().as_secs_f64() * 1e3,
        direct_ms,
        solve_ms,
        materials_ms,
        lights: plan.lights.len(),
    };
    Ok(RelightOutput { radiance, stats })
}
