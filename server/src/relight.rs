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

    if !req.materials.is_empty() {
        for (name, material) in &req.materials {
            if !manifest.objects.iter().any(|o| &o.name == name) {
                let names: Vec<&str> = manifest.objects.iter().map(|o| o.name.as_str()).collect();
                return Err(AppError::invalid(format!(
                    "materials.{name}: scene {:?} has no object {name:?} (its objects are {})",
                    scene.id,
                    names.join(", ")
                )));
            }
            material
                .validate(&format!("materials.{name}"))
                .map_err(|e| AppError::invalid(e.to_string()))?;
        }
        let names: Vec<String> = req.materials.keys().map(|k| format!("{k:?}")).collect();
        return Err(AppError::unsupported(format!(
            "materials: per-request material overrides are not supported yet (got overrides for \
             {}); relight without \"materials\" to use the bundle's materials",
            names.join(", ")
        )));
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

    let albedo = b.patch_albedo();
    let emission = b.patch_emission();
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
            let scatter = SparseScatter(b.subsurface());
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
        lights: plan.lights.len(),
    };
    Ok(RelightOutput { radiance, stats })
}
