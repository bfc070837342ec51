//! Stage 0 of the relight: the plans the scene's backend can do whole go there — the
//! direct light, the transport and the vertex colours where the matrices are, lights in and
//! colours out ([`crate::backend::Backend::relight`]), a batch of them together — and skip
//! the other stages.
//!
//! A plan qualifies when it needs nothing the backend's relight leaves out: the bundle's
//! materials (no translucency change), any components
//! ([`crate::backend::DeviceRelight::components`]), point, spot and directional lamps
//! and environment lights (these where the bundle holds their visibility: the host hands
//! over each bin's radiance, [`crate::environment::bin_radiance_total`], and the backend
//! adds Σ_k V_ik L̄_k to E), no lamp walks, no simulated objects (their collimated entry),
//! and the iterative path (not the bundle's T); the direct light at the vertices or per
//! pixel. Every other plan, every plan whose maps fail to load (the stages answer the
//! error), and every plan the backend declines, runs the stages.

use std::time::Instant;

use translux_proto::api::{Components, DeviceStats, DirectAt, RelightStats, Solver};
use translux_proto::light::Light;
use translux_proto::scene::Material;

use super::{RelightOutput, RelightPlan, solve_params};
use crate::backend::{DeviceAnswer, DeviceRelight, solves};
use crate::error::EngineError;
use crate::radiosity::SolveParams;
use crate::scene::Scene;

/// The plans done whole by the scene's backend, one slot per plan: `None` where a plan does
/// not qualify or the backend declined. Qualifying plans with the same tolerance, the same
/// `direct_at` and the same components go to the backend together, as one batch.
pub(super) fn relight(
    scene: &Scene,
    plans: &[RelightPlan],
) -> Vec<Option<Result<RelightOutput, EngineError>>> {
    let mut out: Vec<Option<Result<RelightOutput, EngineError>>> =
        plans.iter().map(|_| None).collect();
    if scene.backend().name() == "cpu" {
        return out;
    }
    let mut groups: Vec<((u32, DirectAt, Components), Vec<usize>)> = Vec::new();
    for (i, plan) in plans.iter().enumerate() {
        if let Err(why) = qualifies(scene, plan) {
            tracing::debug!(scene = %scene.id, "relight through the engine's stages: {why}");
            continue;
        }
        let key = (plan.tolerance.to_bits(), plan.direct_at, plan.components);
        match groups.iter_mut().find(|(k, _)| *k == key) {
            Some((_, g)) => g.push(i),
            None => groups.push((key, vec![i])),
        }
    }
    for (_, group) in groups {
        let answers = batch(scene, plans, &group);
        for (i, answer) in group.into_iter().zip(answers) {
            out[i] = answer;
        }
    }
    out
}

/// One batch of qualifying plans (indices into `plans`) on the backend.
fn batch(
    scene: &Scene,
    plans: &[RelightPlan],
    group: &[usize],
) -> Vec<Option<Result<RelightOutput, EngineError>>> {
    let t0 = Instant::now();
    let params = SolveParams {
        tolerance: plans[group[0]].tolerance,
        ..solve_params()
    };
    // The environments' radiance per bin (maps through the scene's cache); a plan whose
    // map fails is left to the stages, which answer the error.
    let mut out: Vec<Option<Result<RelightOutput, EngineError>>> =
        group.iter().map(|_| None).collect();
    let mut kept = Vec::with_capacity(group.len());
    let mut environment = Vec::with_capacity(group.len());
    for (slot, &i) in group.iter().enumerate() {
        match crate::environment::bin_radiance_total(&scene.env(), &plans[i].lights) {
            Ok(total) => {
                kept.push(slot);
                environment.push(total);
            }
            Err(e) => tracing::debug!(scene = %scene.id, "relight through the stages: {e}"),
        }
    }
    if kept.is_empty() {
        return out;
    }
    let lights: Vec<&[Light]> = kept
        .iter()
        .map(|&s| plans[group[s]].lights.as_slice())
        .collect();
    let job = DeviceRelight {
        lights: &lights,
        environment: &environment,
        params: &params,
        pixel: plans[group[0]].direct_at == DirectAt::Pixel,
        components: plans[group[0]].components,
        rows: scene.vertex_rows(plans[group[0]].components),
    };
    let Some(answers) = scene.backend().relight(scene.view(), &job) else {
        return out;
    };
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    for (&s, answer) in kept.iter().zip(answers) {
        out[s] = Some(output(scene, &plans[group[s]], answer, ms, kept.len()));
    }
    out
}

/// Whether the plan needs nothing beyond what a backend's whole relight does; else what
/// it needs.
fn qualifies(scene: &Scene, plan: &RelightPlan) -> Result<(), &'static str> {
    let simulated = scene
        .bundle
        .manifest()
        .objects
        .iter()
        .any(|o| matches!(o.material, Material::Simulated { .. }));
    let why = if !plan.overrides.is_empty() {
        "a translucency or material change (S is made on the CPU)"
    } else if plan.lamp_walks.is_some() {
        "lamp walks"
    } else if scene.bundle.environment_visibility().is_none()
        && plan
            .lights
            .iter()
            .any(|l| matches!(l, Light::Environment { .. }))
    {
        "an environment light without the bundle's visibility"
    } else if simulated {
        "simulated objects (their collimated entry)"
    } else if plan.solver == Solver::Inverse || super::prepare::path(scene, plan).0 {
        "the bundle's T"
    } else {
        return Ok(());
    };
    Err(why)
}

/// The answer and its stats (the direct light is part of the one submission: its time is
/// in `solve_ms`, `direct_ms` is 0; a batch's relights share its time; components without
/// a solve say `none`, and the path's note is the stages' own).
fn output(
    scene: &Scene,
    plan: &RelightPlan,
    answer: DeviceAnswer,
    ms: f64,
    batch: usize,
) -> Result<RelightOutput, EngineError> {
    if let Some(k) = answer
        .radiance
        .iter()
        .position(|v| !v.iter().all(|x| x.is_finite()))
    {
        return Err(EngineError::invalid(format!(
            "lights: the result overflows (radiance at vertex {k} is not finite); use \
             smaller intensities or irradiances"
        )));
    }
    let s = answer.stats;
    let stats = RelightStats {
        solver: if solves(plan.components) {
            s.method.as_str()
        } else {
            "none"
        }
        .to_string(),
        components: plan.components,
        iterations: s.iterations,
        residual: s.residual,
        converged: s.converged,
        ms,
        direct_ms: 0.0,
        solve_ms: ms,
        materials_ms: 0.0,
        materials_on: None,
        lights: plan.lights.len(),
        products: s.products,
        warm: s.warm,
        batch,
        note: super::prepare::path(scene, plan).1,
        auto_exposure: answer.luminance.map(|lum| {
            crate::render::exposure_of_luminance(lum.into_iter().map(f64::from).collect())
        }),
        device: Some(DeviceStats {
            submissions: answer.submissions,
            bytes_up: answer.bytes_up,
            bytes_down: answer.bytes_down,
        }),
    };
    Ok(RelightOutput {
        radiance: answer.radiance,
        stats,
    })
}
