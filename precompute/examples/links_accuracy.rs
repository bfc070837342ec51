//! The hierarchical F's cuts against dense F under random point lights: precomputes one
//! scene three times at the same patches (dense, `--links one-sided`, `--links two-sided`),
//! relights each through the engine under `LIGHTS` random point lamps, and prints per cut
//! the entries of C per patch, the F stage's seconds, the largest row sum and the vertex
//! radiance's error against dense's, apart on the lit vertices (the lamp reaches them
//! directly) and the shadowed ones (it does not): median and 90th percentile over every
//! vertex and channel whose reference is above 1% of the lit vertices' median. Not a test:
//! nothing here asserts.
//!
//! `cargo run --profile test -p translux-precompute --example links_accuracy -- SCENE
//! [PATCHES] [LIGHTS]` (defaults 6000, 16).

use std::time::Instant;

use anyhow::Context;
use glam::Vec3;
use translux_engine::relight;
use translux_engine::scene::Scene;
use translux_precompute::hierarchy::HierarchyParams;
use translux_precompute::pipeline::{FormFactorMethod, PrecomputeParams, precompute};
use translux_proto::api::RelightRequest;
use translux_proto::bundle::Bundle;

/// One cut's figures.
struct Row {
    name: &'static str,
    entries_per_patch: f64,
    f_seconds: f64,
    row_sum_max: f64,
    lit: (f64, f64),
    shadowed: (f64, f64),
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let scene = args
        .first()
        .context("usage: links_accuracy SCENE [PATCHES] [LIGHTS] (a scene file or builtin:NAME)")?;
    let patches: u64 = args.get(1).map_or(Ok(6000), |a| a.parse())?;
    let light_count: usize = args.get(2).map_or(Ok(16), |a| a.parse())?;
    let loaded = translux_precompute::scene::load_scene(scene)?;
    let dir = tempfile::tempdir()?;
    let cuts = [
        ("dense", FormFactorMethod::Dense),
        (
            "one-sided",
            FormFactorMethod::Hierarchical(HierarchyParams::default()),
        ),
        (
            "two-sided",
            FormFactorMethod::Hierarchical(HierarchyParams {
                two_sided: true,
                ..Default::default()
            }),
        ),
    ];
    let mut bundles = Vec::new();
    for (name, transport) in cuts {
        let out = dir.path().join(name);
        let params = PrecomputeParams {
            patches: Some(patches),
            transport,
            environment: translux_engine::envvis::EnvVisParams {
                bins: None,
                ..Default::default()
            },
            ..Default::default()
        };
        let t = Instant::now();
        precompute(&loaded, &out, &params).with_context(|| format!("precomputing {name}"))?;
        eprintln!("{name}: {:.1} s", t.elapsed().as_secs_f64());
        bundles.push((name, out));
    }
    let lights = random_lights(&Bundle::open(&bundles[0].1)?, light_count);
    let reference = Scene::open("reference", &bundles[0].1)?;
    let lit: Vec<Vec<bool>> = lights
        .iter()
        .map(|l| {
            let direct = relight_with(&reference, l, "direct")?;
            Ok(direct.iter().map(|c| c.iter().any(|&v| v > 0.0)).collect())
        })
        .collect::<anyhow::Result<_>>()?;
    let truth: Vec<Vec<[f32; 3]>> = lights
        .iter()
        .map(|l| relight_with(&reference, l, "full"))
        .collect::<anyhow::Result<_>>()?;
    let mut rows = Vec::new();
    for (name, out) in &bundles[1..] {
        let scene = Scene::open(*name, out)?;
        let (mut on, mut off) = (Vec::new(), Vec::new());
        for ((l, want), lit) in lights.iter().zip(&truth).zip(&lit) {
            let got = relight_with(&scene, l, "full")?;
            errors(&got, want, lit, &mut on, &mut off);
        }
        let b = Bundle::open(out)?;
        let m = b.manifest();
        rows.push(Row {
            name,
            entries_per_patch: m.form_factors.nnz as f64 / m.patch_count as f64,
            f_seconds: m
                .stages
                .iter()
                .filter(|s| s.stage.contains("form"))
                .map(|s| s.seconds)
                .sum(),
            row_sum_max: m.form_factors.row_sum_max,
            lit: quantiles(&mut on),
            shadowed: quantiles(&mut off),
        });
    }
    print_table(scene, patches, light_count, &rows);
    Ok(())
}

/// `count` point lamps at random spots in the middle of the scene's box, each giving the
/// box's centre about unit irradiance.
fn random_lights(b: &Bundle, count: usize) -> Vec<serde_json::Value> {
    let (lo, hi) = b.patch_corners().iter().flatten().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(l, h), p| (l.min(Vec3::from(*p)), h.max(Vec3::from(*p))),
    );
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 40) as f32 / (1u64 << 24) as f32
    };
    let size = (hi - lo).length();
    (0..count)
        .map(|_| {
            let t = Vec3::new(next(), next(), next());
            let p = lo + (hi - lo) * (Vec3::splat(0.2) + 0.6 * t);
            let i = 0.05 * size * size;
            serde_json::json!({"type": "point", "position": [p.x, p.y, p.z],
                               "intensity": [i, i, i]})
        })
        .collect()
}

/// Vertex radiance under one lamp with the given components.
fn relight_with(
    scene: &Scene,
    light: &serde_json::Value,
    components: &str,
) -> anyhow::Result<Vec<[f32; 3]>> {
    let req: RelightRequest = serde_json::from_value(serde_json::json!({
        "lights": [light], "components": components,
    }))?;
    let plan = relight::plan(scene, req)?;
    Ok(relight::run(scene, &plan)?.radiance)
}

/// Relative errors per vertex and channel, split by whether the lamp lights the vertex,
/// over the values above 1% of the lit vertices' median reference.
fn errors(
    got: &[[f32; 3]],
    want: &[[f32; 3]],
    lit: &[bool],
    on: &mut Vec<f64>,
    off: &mut Vec<f64>,
) {
    let mut lit_values: Vec<f64> = want
        .iter()
        .zip(lit)
        .filter(|(_, l)| **l)
        .flat_map(|(w, _)| w.iter().map(|&v| v as f64))
        .collect();
    let floor = 0.01 * quantiles(&mut lit_values).0;
    for ((g, w), &l) in got.iter().zip(want).zip(lit) {
        for c in 0..3 {
            let (g, w) = (g[c] as f64, w[c] as f64);
            if w > floor {
                let e = (g - w).abs() / w;
                if l { on.push(e) } else { off.push(e) }
            }
        }
    }
}

/// Median and 90th percentile.
fn quantiles(v: &mut [f64]) -> (f64, f64) {
    if v.is_empty() {
        return (0.0, 0.0);
    }
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    (at(0.5), at(0.9))
}

fn print_table(scene: &str, patches: u64, lights: usize, rows: &[Row]) {
    println!("{scene}, {patches} patches requested, {lights} random point lamps, against dense F");
    println!(
        "| links | entries per patch | F stage (s) | largest row sum | lit median / p90 | shadowed median / p90 |"
    );
    println!("| --- | --- | --- | --- | --- | --- |");
    for r in rows {
        println!(
            "| {} | {:.0} | {:.2} | {:.4} | {:.2}% / {:.2}% | {:.2}% / {:.2}% |",
            r.name,
            r.entries_per_patch,
            r.f_seconds,
            r.row_sum_max,
            100.0 * r.lit.0,
            100.0 * r.lit.1,
            100.0 * r.shadowed.0,
            100.0 * r.shadowed.1
        );
    }
}
