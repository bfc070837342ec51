//! What a viewer vertex shows: on opaque diffuse surfaces the direct term is taken at the
//! vertex itself (its shadow ray, its normal), the rest interpolated from the patches;
//! translucent objects keep the S-smoothed patch mean (`engine::vertexlight`).
//!
//! Checked against closed forms (E = I cos θ / r² at the vertex, a shadow cast by a box
//! found with the test's own segment–box test) through the relight the REST route runs.

use std::path::Path;

use glam::Vec3;
use serde_json::json;
use translux_engine::radiosity::{self, BundleLighting, Rgb, SolveParams, SparseScatter};
use translux_engine::relight;
use translux_engine::transport::Transport;
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::resolve_scene;
use translux_proto::bundle::Bundle;
use translux_proto::light::Light;
use translux_proto::scene::SceneFile;
use translux_server::state::Scene;

fn build(file: serde_json::Value, dir: &Path, patches: u64) -> Scene {
    let file: SceneFile = serde_json::from_value(file).unwrap();
    let loaded = resolve_scene(file, Path::new("."), "v".into(), "v".into()).unwrap();
    let out = dir.join("bundle");
    let params = PrecomputeParams {
        patches: Some(patches),
        ..Default::default()
    };
    precompute(&loaded, &out, &params).unwrap();
    Scene::open("v", &out).unwrap()
}

fn relight(scene: &Scene, lights: &serde_json::Value) -> Vec<Rgb> {
    let request = json!({ "lights": lights, "solver": "iterative" }).to_string();
    let mut plan = relight::plan(scene, translux_proto::parse_json(&request).unwrap()).unwrap();
    plan.tolerance = 1e-6;
    relight::run(scene, &plan).unwrap().radiance
}

/// Irradiance I cos θ / r² (r in metres) at `p` with normal `n` from a point light.
fn point_e(p: Vec3, n: Vec3, light: Vec3, intensity: f32) -> f32 {
    let d = light - p;
    let r2 = d.length_squared();
    (n.dot(d) / r2.sqrt()).max(0.0) * intensity / r2
}

fn percentile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// A lone floor (F = 0) under a low point light: every vertex shows ρ I cos θ / (π r²)
/// at its own position, where the patch mean misses the hot spot's peak.
#[test]
fn a_lit_floor_shows_the_closed_form_at_every_vertex() {
    let dir = tempfile::tempdir().unwrap();
    let rho = 0.6f32;
    let scene = build(
        json!({
            "objects": [{"name": "floor", "mesh": {"shape": "quad", "size": [2, 2]},
                         "material": {"type": "diffuse", "albedo": [rho, rho, rho]}}],
            "lights": [],
        }),
        dir.path(),
        2000,
    );
    let light = Vec3::new(0.3, 0.15, -0.2);
    let lights = json!([{"type": "point", "position": light.to_array(), "intensity": [2, 2, 2]}]);
    let got = relight(&scene, &lights);
    let b = &scene.bundle;
    // The patch mean the viewer showed before: B = ρ E per patch, averaged.
    let lit = BundleLighting::new(b);
    let parsed: Vec<Light> = serde_json::from_value(lights.clone()).unwrap();
    let patch_b: Vec<Rgb> = lit
        .irradiance(&parsed)
        .unwrap()
        .iter()
        .map(|e| e.map(|x| rho * x))
        .collect();
    let mean = radiosity::vertex_radiance(
        b.triangle_vertices(),
        b.patch_areas(),
        b.vertex_positions().len(),
        &patch_b,
    );
    let (mut now, mut before) = (Vec::new(), Vec::new());
    for (k, p) in b.vertex_positions().iter().enumerate() {
        let want = rho / std::f32::consts::PI * point_e(Vec3::from(*p), Vec3::Y, light, 2.0);
        now.extend(got[k].iter().map(|&g| ((g - want) / want).abs() as f64));
        before.push(((mean[k][0] - want) / want).abs() as f64);
    }
    let (now_max, now_p50) = (
        now.iter().cloned().fold(0.0, f64::max),
        percentile(&mut now, 0.5),
    );
    let (before_max, before_p90) = (
        before.iter().cloned().fold(0.0, f64::max),
        percentile(&mut before, 0.9),
    );
    println!(
        "lone floor, {} vertices: at the vertex median {:.3}% max {:.3}%; patch mean p90 \
         {:.2}% max {:.2}%",
        b.vertex_positions().len(),
        100.0 * now_p50,
        100.0 * now_max,
        100.0 * before_p90,
        100.0 * before_max
    );
    // The sample point sits 1% of the way into the vertex's triangles: well under 1%.
    assert!(now_max < 0.01, "max error at the vertices {now_max}");
    // The patch mean misses the peak by far more: the check can tell the two apart.
    assert!(before_max > 10.0 * now_max, "{before_max} vs {now_max}");
}

/// Whether the segment a → b crosses the box [lo, hi] (slab test, the test's own).
fn segment_hits_box(a: Vec3, b: Vec3, lo: Vec3, hi: Vec3) -> bool {
    let d = b - a;
    let (mut t0, mut t1) = (0.0f32, 1.0f32);
    for k in 0..3 {
        if d[k].abs() < 1e-12 {
            if a[k] < lo[k] || a[k] > hi[k] {
                return false;
            }
            continue;
        }
        let (mut u, mut v) = ((lo[k] - a[k]) / d[k], (hi[k] - a[k]) / d[k]);
        if u > v {
            std::mem::swap(&mut u, &mut v);
        }
        t0 = t0.max(u);
        t1 = t1.min(v);
        if t0 > t1 {
            return false;
        }
    }
    true
}

/// A marble cube on a floor (scene in millimetres) casts a shadow: a floor vertex shows
/// the interpolated indirect light plus ρ E at the vertex, lit or shadowed by the vertex's
/// own ray, and the cube's vertices keep the patch mean of S's answer.
#[test]
fn a_shadow_edge_is_sharp_at_the_vertices_and_translucent_vertices_keep_the_mean() {
    let dir = tempfile::tempdir().unwrap();
    let rho = 0.5f32;
    let scene = build(
        json!({
            "unit_mm": 1,
            "objects": [
                {"name": "floor", "mesh": {"shape": "quad", "size": [300, 300]},
                 "material": {"type": "diffuse", "albedo": [rho, rho, rho]}},
                {"name": "cube", "mesh": {"shape": "box", "size": [60, 60, 60]},
                 "transform": {"translate": [0, 30, 0]},
                 "material": {"type": "translucent",
                              "profile": {"type": "dipole", "preset": "marble"}}}],
            "lights": [],
        }),
        dir.path(),
        3000,
    );
    let light = Vec3::new(150.0, 200.0, 60.0);
    let lights = json!([{"type": "point", "position": light.to_array(), "intensity": [1, 1, 1]}]);
    let got = relight(&scene, &lights);
    let b: &Bundle = &scene.bundle;

    // The library's solve: B per patch, and the part ρ E of it on the floor.
    let lit = BundleLighting::new(b);
    let parsed: Vec<Light> = serde_json::from_value(lights.clone()).unwrap();
    let e = lit.irradiance(&parsed).unwrap();
    let params = SolveParams {
        tolerance: 1e-7,
        ..Default::default()
    };
    let s = SparseScatter(b.subsurface());
    let (patch_b, _) =
        radiosity::solve(&Transport::of(b), &s, b.patch_emission(), &e, &params, None).unwrap();
    let (tris, areas, nv) = (
        b.triangle_vertices(),
        b.patch_areas(),
        b.vertex_positions().len(),
    );
    let mean = radiosity::vertex_radiance(tris, areas, nv, &patch_b);
    let rho_e: Vec<Rgb> = e.iter().map(|e| e.map(|x| rho * x)).collect();
    let mean_rho_e = radiosity::vertex_radiance(tris, areas, nv, &rho_e);
    let objects = &b.manifest().objects;
    let owner = |k: usize| {
        objects
            .iter()
            .position(|o| {
                tris[o.first_patch as usize..(o.first_patch + o.patch_count) as usize]
                    .iter()
                    .any(|t| t.contains(&(k as u32)))
            })
            .unwrap()
    };
    let peak = mean.iter().map(|v| v[0]).fold(0.0f32, f32::max);
    let (lo, hi) = (Vec3::new(-30.0, 0.0, -30.0), Vec3::new(30.0, 60.0, 30.0));
    let (mut floor, mut shadowed, mut changed, mut cube) = (0, 0, 0, 0);
    for (k, p) in b.vertex_positions().iter().enumerate() {
        let p = Vec3::from(*p);
        if owner(k) == 1 {
            // Translucent: exactly the mean of B/π (up to the solver's tolerance).
            cube += 1;
            for c in 0..3 {
                assert!(
                    (got[k][c] - mean[k][c]).abs() <= 1e-3 * peak,
                    "cube vertex {k}: {:?} vs {:?}",
                    got[k],
                    mean[k]
                );
            }
            continue;
        }
        // A floor vertex, where the box's shadow is decided the same way 2 mm around it
        // (the engine samples 1% of the way into the vertex's triangles), and whose
        // patches are all clear of the cube's footprint (those under it are left out of
        // the means, which this check does not model).
        let around = [Vec3::ZERO, Vec3::X, -Vec3::X, Vec3::Z, -Vec3::Z].map(|d| p + 2.0 * d);
        let hit: Vec<bool> = around
            .iter()
            .map(|&q| segment_hits_box(q + 0.01 * Vec3::Y, light, lo, hi))
            .collect();
        let inside = p.x.abs() <= 45.0 && p.z.abs() <= 45.0;
        if inside || hit.iter().any(|&h| h != hit[0]) {
            continue;
        }
        floor += 1;
        let own = if hit[0] {
            shadowed += 1;
            0.0
        } else {
            // r in metres: the scene is in millimetres.
            rho * point_e(p * 1e-3, Vec3::Y, light * 1e-3, 1.0)
        } / std::f32::consts::PI;
        let want = mean[k][0] - mean_rho_e[k][0] + own;
        assert!(
            (got[k][0] - want).abs() <= 2e-3 * peak + 5e-3 * want,
            "floor vertex {k} at {p}: {} vs {want} (mean {})",
            got[k][0],
            mean[k][0]
        );
        if (got[k][0] - mean[k][0]).abs() > 0.2 * mean[k][0] {
            changed += 1;
        }
    }
    println!(
        "cube on a floor: {cube} cube vertices kept, {floor} floor vertices checked \
         ({shadowed} in the shadow), {changed} differ from the patch mean by > 20%"
    );
    assert!(
        cube > 100 && floor > 500 && shadowed > 20,
        "too few vertices checked"
    );
    assert!(
        changed > 0,
        "no vertex left the patch mean: the shadow edge is still blurred"
    );
}
