//! The whole relight on the device (`translux_server::gpu::relight`): the colour and
//! environment kernels against their twins and the engine, whole relights on the GPU
//! backend against the CPU backend per vertex for each lamp type and for environment maps
//! (alone, beside a lamp, in a batch, per pixel) and for the components the device relights,
//! one submission per relight with only the colours read back, and the plans the device
//! leaves to the engine's stages.
//!
//! On lavapipe in CI; `TRANSLUX_SKIP_GPU_TESTS=1` skips them where no adapter exists.

use std::path::Path;
use std::sync::OnceLock;

use translux_engine::radiosity::Rgb;
use translux_engine::relight;
use translux_engine::scene::Scene;
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::load_scene;
use translux_proto::api::{Components, RelightRequest, RelightStats};
use translux_server::backend::Backend;
use translux_server::gpu::environment::{GpuVisibility, env_irradiance_once};
use translux_server::gpu::{GpuContext, GpuOptions, cpu_twin, relight::vertex_colours_once};

/// The shared context, or `None` when skipping is allowed and no adapter exists.
fn ctx() -> Option<&'static GpuContext> {
    crate::support::gpu()
}

/// The GPU backend on an adapter of its own (software ones too).
fn gpu_backend() -> Backend {
    Backend::on_gpu(
        GpuContext::new(&GpuOptions {
            allow_software: true,
            ..Default::default()
        })
        .unwrap(),
    )
}

/// A Cornell box with its marble block at 400 patches (a hierarchical F and S),
/// precomputed once per test binary.
fn cornell() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    precomputed(&DIR, false)
}

/// The same with two-sided links (F's node rows pushed to the patches).
fn cornell_two_sided() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    precomputed(&DIR, true)
}

fn precomputed(dir: &'static OnceLock<tempfile::TempDir>, two_sided: bool) -> &'static Path {
    use translux_precompute::hierarchy::HierarchyParams;
    use translux_precompute::pipeline::FormFactorMethod;
    dir.get_or_init(|| {
        let tmp = tempfile::tempdir().unwrap();
        let params = PrecomputeParams {
            patches: Some(400),
            transport: FormFactorMethod::Hierarchical(HierarchyParams {
                two_sided,
                ..Default::default()
            }),
            ..Default::default()
        };
        precompute(
            &load_scene("builtin:cornell").unwrap(),
            &tmp.path().join("cornell"),
            &params,
        )
        .unwrap();
        tmp
    })
    .path()
    .join("cornell")
    .leak()
}

/// An open Cornell box (no ceiling, no front wall: the sky reaches in) with a marble
/// block and a diffuse box, 400 patches, the precompute's default environment visibility
/// (16 × 32 bins), precomputed once per test binary.
fn open_box() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    use translux_precompute::hierarchy::HierarchyParams;
    use translux_precompute::pipeline::FormFactorMethod;
    DIR.get_or_init(|| {
        let tmp = tempfile::tempdir().unwrap();
        let grey = "\"material\": {\"type\": \"diffuse\", \"albedo\": [0.7, 0.7, 0.7]}";
        let scene = format!(
            r#"{{"unit_mm": 1000, "objects": [
            {{"name": "floor", "mesh": {{"shape": "quad", "size": [0.555, 0.555]}}, {grey}}},
            {{"name": "back_wall", "mesh": {{"shape": "quad", "size": [0.555, 0.555]}},
              "transform": {{"translate": [0, 0.2775, -0.2775], "rotate_deg": [90, 0, 0]}}, {grey}}},
            {{"name": "left_wall", "mesh": {{"shape": "quad", "size": [0.555, 0.555]}},
              "transform": {{"translate": [-0.2775, 0.2775, 0], "rotate_deg": [0, 0, -90]}},
              "material": {{"type": "diffuse", "albedo": [0.63, 0.065, 0.05]}}}},
            {{"name": "short_box", "mesh": {{"shape": "box", "size": [0.165, 0.165, 0.165]}},
              "transform": {{"translate": [0.09, 0.0825, 0.07], "rotate_deg": [0, -17, 0]}},
              "material": {{"type": "diffuse", "albedo": [0.75, 0.65, 0.15]}}}},
            {{"name": "tall_block", "mesh": {{"shape": "box", "size": [0.165, 0.33, 0.165]}},
              "transform": {{"translate": [-0.09, 0.165, -0.08], "rotate_deg": [0, 17, 0]}},
              "material": {{"type": "translucent", "profile": {{"type": "dipole", "preset": "marble"}}}}}}
            ], "lights": []}}"#
        );
        let file = tmp.path().join("open.json");
        std::fs::write(&file, scene).unwrap();
        let params = PrecomputeParams {
            patches: Some(400),
            transport: FormFactorMethod::Hierarchical(HierarchyParams::default()),
            ..Default::default()
        };
        precompute(
            &load_scene(file.to_str().unwrap()).unwrap(),
            &tmp.path().join("open"),
            &params,
        )
        .unwrap();
        tmp
    })
    .path()
    .join("open")
    .leak()
}

/// A seeded xorshift generator.
struct Rng(u64);

impl Rng {
    fn f(&mut self, lo: f32, hi: f32) -> f32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        lo + (hi - lo) * ((self.0 >> 40) as f32 / (1u64 << 24) as f32)
    }
    fn rgb(&mut self, lo: f32, hi: f32) -> Rgb {
        [self.f(lo, hi), self.f(lo, hi), self.f(lo, hi)]
    }
}

/// The largest difference per vertex and channel, relative to the largest value of `want`.
fn max_rel(got: &[Rgb], want: &[Rgb]) -> f32 {
    assert_eq!(got.len(), want.len());
    let scale = want
        .iter()
        .flatten()
        .fold(0.0f32, |m, v| m.max(v.abs()))
        .max(1e-30);
    got.iter()
        .flatten()
        .zip(want.iter().flatten())
        .map(|(g, w)| (g - w).abs() / scale)
        .fold(0.0, f32::max)
}

/// Some vertex of an answer is lit.
fn lit(radiance: &[Rgb]) -> bool {
    radiance.iter().flatten().any(|&v| v > 0.0)
}

/// A relight of `body` on `scene` to a tight tolerance.
fn relit(scene: &Scene, body: &str) -> (Vec<Rgb>, RelightStats) {
    let req: RelightRequest = serde_json::from_str(body).unwrap();
    let mut plan = relight::plan(scene, req).unwrap();
    plan.tolerance = 1e-6;
    let out = relight::run(scene, &plan).unwrap();
    assert!(out.stats.converged, "{body}: {:?}", out.stats);
    (out.radiance, out.stats)
}

#[test]
fn vertex_colours_matches_its_twin_and_the_engines_rows() {
    let Some(ctx) = ctx() else { return };
    let scene = Scene::open("cornell", cornell()).unwrap();
    let rows = scene.vertex_rows(Components::Full);
    let (n, nv) = (rows.albedo.len(), rows.len());
    assert!(
        rows.own.iter().any(|o| o[3] > 0.0),
        "some vertices are opaque"
    );
    let mut rng = Rng(77);
    // B ≥ ρE as on a real answer: E at most 1, B at least 1. The device's E holds an
    // environment's part too (`e_env`), which the opaque vertices leave out of ρE as the
    // engine's rows do when handed the lamps' E alone.
    let e: Vec<Rgb> = (0..n).map(|_| rng.rgb(0.0, 1.0)).collect();
    let x: Vec<Rgb> = (0..n).map(|_| rng.rgb(1.0, 3.0)).collect();
    let ev: Vec<Rgb> = (0..nv).map(|_| rng.rgb(0.0, 2.0)).collect();
    let e_env: Vec<Rgb> = (0..n).map(|_| rng.rgb(0.0, 0.5)).collect();
    let e_all: Vec<Rgb> = e
        .iter()
        .zip(&e_env)
        .map(|(a, b)| std::array::from_fn(|c| a[c] + b[c]))
        .collect();
    let zero = vec![[0.0f32; 3]; n];
    for (pixel, env) in [(false, false), (true, false), (false, true), (true, true)] {
        let (e_dev, e_part) = if env { (&e_all, &e_env) } else { (&e, &zero) };
        let (got, got_lum) =
            vertex_colours_once(ctx, rows, (&x, e_dev, e_part, &ev), pixel).unwrap();
        let (twin, twin_lum) = cpu_twin::vertex_colours(rows, &x, (e_dev, e_part), &ev, pixel);
        let engine = rows.colours(&x, &e, &ev, pixel);
        let what = format!("pixel {pixel}, environment {env}");
        assert!(
            max_rel(&got, &twin) <= 1e-5,
            "{what}: kernel vs twin: {}",
            max_rel(&got, &twin)
        );
        assert!(
            max_rel(&twin, &engine) <= 1e-5,
            "{what}: twin vs engine: {}",
            max_rel(&twin, &engine)
        );
        if pixel {
            let as_rgb = |v: &[f32]| -> Vec<Rgb> { v.iter().map(|&l| [l; 3]).collect() };
            let (g, t) = (as_rgb(&got_lum), as_rgb(&twin_lum));
            assert!(
                max_rel(&g, &t) <= 1e-5,
                "luminance: kernel vs twin {}",
                max_rel(&g, &t)
            );
        }
    }
    // Per pixel the diffuse objects' vertices lose their direct term: some answers change.
    assert!(
        rows.own.iter().any(|o| o[3] == 2.0),
        "the box's walls are diffuse"
    );
    assert_ne!(
        rows.colours(&x, &e, &ev, true),
        rows.colours(&x, &e, &ev, false)
    );
}

/// The bundle's environment visibility (the precompute's default 16 × 32 bins).
fn visibility(scene: &Scene) -> translux_proto::bundle::EnvVisibilityView<'_> {
    let vis = scene
        .bundle
        .environment_visibility()
        .expect("the test bundle holds environment visibility");
    assert_eq!((vis.rows, vis.cols), (16, 32));
    vis
}

/// `env_irradiance` against its twin and the engine's E = Σ_k V_ik L̄_k on the bundle's
/// visibility, for a batch of three relights of which the second has no environment.
#[test]
fn env_irradiance_matches_its_twin_and_the_engine() {
    let Some(ctx) = ctx() else { return };
    let scene = Scene::open("open", open_box()).unwrap();
    let vis = visibility(&scene);
    let (n, k) = (scene.bundle.patch_areas().len(), vis.bins());
    let mut rng = Rng(5);
    let radiance: Vec<Option<Vec<Rgb>>> = vec![
        Some((0..k).map(|_| rng.rgb(0.0, 2.0)).collect()),
        None,
        Some((0..k).map(|_| rng.rgb(0.5, 1.0)).collect()),
    ];
    let e: Vec<Rgb> = (0..3 * n).map(|_| rng.rgb(0.0, 1.0)).collect();
    let (got_e, got_env) = env_irradiance_once(ctx, vis, &radiance, &e).unwrap();
    let mut twin_e = e.clone();
    let words = GpuVisibility::pack(vis);
    let twin_env = cpu_twin::env_irradiance(&words, k, &radiance, &mut twin_e);
    let (de, denv) = (max_rel(&got_e, &twin_e), max_rel(&got_env, &twin_env));
    eprintln!("env_irradiance: kernel vs twin: E {de:e}, E_env {denv:e}");
    assert!(de <= 1e-5, "E: kernel vs twin {de}");
    assert!(denv <= 1e-5, "E_env: kernel vs twin {denv}");
    // The engine's sum over the same half floats.
    let v: Vec<f32> = vis
        .bits
        .iter()
        .map(|&b| half::f16::from_bits(b).to_f32())
        .collect();
    for (r, l) in radiance.iter().enumerate() {
        let at = r * n..(r + 1) * n;
        let mut want = vec![[0.0f32; 3]; n];
        if let Some(l) = l {
            translux_engine::envvis::environment_irradiance(&v, l, 1.0, &mut want);
        }
        assert_eq!(
            &twin_env[at.clone()],
            want.as_slice(),
            "relight {r}: twin vs engine"
        );
        if l.is_none() {
            assert_eq!(&got_e[at.clone()], &e[at], "relight {r} keeps its E");
        }
    }
    assert!(
        twin_env.iter().flatten().any(|&x| x > 0.0),
        "the sky reaches some patch"
    );
}

/// Every lamp type, two lamps at once, the bundle's own lights and none: the GPU backend's
/// whole relight against the CPU backend's stages, per vertex; directional lamps on the open
/// box (the closed one keeps them out).
#[test]
fn the_whole_relight_on_the_device_agrees_with_the_cpu_for_every_lamp() {
    let Some(_) = ctx() else { return };
    let bodies = [
        (cornell(), r#"{"solver":"iterative"}"#),
        (
            cornell(),
            r#"{"lights":[{"type":"point","position":[0.1,0.5,0.2],"intensity":[2,1,0.5]}]}"#,
        ),
        (
            cornell(),
            r#"{"lights":[{"type":"spot","position":[0.0,0.5,0.0],"intensity":[3,3,3],"direction":[0.1,-1,0.05],"inner_deg":15,"outer_deg":35}]}"#,
        ),
        (
            open_box(),
            r#"{"lights":[{"type":"directional","direction":[0.3,-1,-0.2],"irradiance":[1,0.9,0.8]}]}"#,
        ),
        (
            open_box(),
            r#"{"lights":[{"type":"point","position":[-0.3,0.7,0.3],"intensity":[1,1,1]},{"type":"directional","direction":[-0.2,-1,0.4],"irradiance":[0.5,0.5,0.6]}]}"#,
        ),
        (cornell(), r#"{"lights":[]}"#),
    ];
    let gpu_backend = gpu_backend();
    for (dir, body) in bodies {
        let cpu = Scene::open_with("s", dir, &Backend::cpu("reference").resources()).unwrap();
        let gpu = Scene::open_with("s", dir, &gpu_backend.resources()).unwrap();
        let (want, cs) = relit(&cpu, body);
        assert!(
            lit(&want) != body.contains("[]"),
            "{body}: lit {}",
            lit(&want)
        );
        let (got, gs) = relit(&gpu, body);
        assert!(cs.device.is_none(), "{body}: {cs:?}");
        let device = gs
            .device
            .unwrap_or_else(|| panic!("{body}: not on the device: {gs:?}"));
        assert!(device.submissions >= 1, "{body}: {gs:?}");
        assert_eq!(gs.solver, "jacobi", "{body}");
        let err = max_rel(&got, &want);
        assert!(
            err <= 1e-4,
            "{body}: device vs CPU {err} of the brightest vertex"
        );
    }
    let h = gpu_backend.gpu_health();
    assert!(h.scenes.iter().all(|s| s.on == "gpu"), "{h:?}");
}

/// Batches of relights of one scene (as the worker pool runs concurrent requests): 3 in one
/// submission, 11 in two (8 and 3), each as the CPU backend answers it, with a one- and a
/// two-sided F.
#[test]
fn batches_of_whole_relights_agree_with_the_cpu() {
    let Some(_) = ctx() else { return };
    for dir in [cornell(), cornell_two_sided()] {
        for k in [3usize, 11] {
            let bodies: Vec<String> = (0..k)
                .map(|i| {
                    format!(
                        r#"{{"lights":[{{"type":"point","position":[{},0.55,0.1],"intensity":[1,2,1]}}]}}"#,
                        0.05 * i as f32 - 0.3
                    )
                })
                .collect();
            let cpu = batch(dir, &bodies, &Backend::cpu("reference"), 1e-6);
            let backend = gpu_backend();
            let gpu = batch(dir, &bodies, &backend, 1e-6);
            // The same batch again at the default tolerance, warm: one submission for each
            // 8, whose relights share its counts; each reads back its own colours and its
            // share of the history.
            let again = batch(dir, &bodies, &backend, relight::solve_params().tolerance);
            let nv = again[0].0.len() as u64;
            for (r, (_, s)) in again.iter().enumerate() {
                let d = s.device.unwrap();
                assert_eq!(d.submissions, 1, "relight {r} of {k}: {s:?}");
                assert!(s.warm, "relight {r} of {k}: {s:?}");
                assert!(d.bytes_down <= 16 * nv + 4096, "{d:?} for {nv} vertices");
            }
            for (r, ((want, _), (got, s))) in cpu.iter().zip(&gpu).enumerate() {
                let d = s
                    .device
                    .unwrap_or_else(|| panic!("relight {r} of {k}: {s:?}"));
                assert_eq!(s.batch, k, "relight {r} of {k}: {s:?}");
                assert!(d.submissions >= 1, "{s:?}");
                let err = max_rel(got, want);
                assert!(err <= 1e-4, "relight {r} of {k}: device vs CPU {err}");
            }
        }
    }
}

/// Every relight of `bodies` as one batch on `backend`, to `tolerance`.
fn batch(
    dir: &Path,
    bodies: &[String],
    backend: &Backend,
    tolerance: f32,
) -> Vec<(Vec<Rgb>, RelightStats)> {
    let scene = Scene::open_with("cornell", dir, &backend.resources()).unwrap();
    let plans: Vec<_> = bodies
        .iter()
        .map(|b| {
            let mut p = relight::plan(&scene, serde_json::from_str(b).unwrap()).unwrap();
            p.tolerance = tolerance;
            p
        })
        .collect();
    relight::run_batch(&scene, &plans)
        .into_iter()
        .map(|r| {
            let r = r.unwrap();
            assert!(r.stats.converged, "{:?}", r.stats);
            (r.radiance, r.stats)
        })
        .collect()
}

/// The viewer's relights (`direct_at: pixel`): the diffuse objects' vertices without their
/// direct term and the exposure of the whole answer, on the device as on the CPU.
#[test]
fn relights_with_the_direct_light_per_pixel_agree_with_the_cpu() {
    let Some(_) = ctx() else { return };
    let cpu =
        Scene::open_with("cornell", cornell(), &Backend::cpu("reference").resources()).unwrap();
    let backend = gpu_backend();
    let gpu = Scene::open_with("cornell", cornell(), &backend.resources()).unwrap();
    for body in [
        r#"{"direct_at":"pixel"}"#,
        r#"{"direct_at":"pixel","lights":[{"type":"spot","position":[0.0,0.5,0.0],"intensity":[3,3,3],"direction":[0.1,-1,0.05],"inner_deg":15,"outer_deg":35}]}"#,
    ] {
        let (want, cs) = relit(&cpu, body);
        assert!(lit(&want), "{body}: the lamp lights nothing");
        let (got, gs) = relit(&gpu, body);
        assert!(gs.device.is_some(), "{body}: {gs:?}");
        let err = max_rel(&got, &want);
        assert!(err <= 1e-4, "{body}: device vs CPU {err}");
        let (ge, ce) = (gs.auto_exposure.unwrap(), cs.auto_exposure.unwrap());
        assert!(
            (ge - ce).abs() <= 0.1 + 1e-6,
            "{body}: exposure {ge} vs {ce}"
        );
    }
}

/// A dragged light: after the first relight every one is a single submission that writes
/// the lights and reads back the colours with the solve's counter and history, warm from
/// the last answer on the device.
#[test]
fn a_relight_makes_one_submission_and_reads_back_only_vertex_colours() {
    let Some(_) = ctx() else { return };
    let backend = gpu_backend();
    let scene = Scene::open_with("cornell", cornell(), &backend.resources()).unwrap();
    let nv = scene.bundle.vertex_positions().len() as u64;
    let body = |x: f32| {
        format!(r#"{{"lights":[{{"type":"point","position":[{x},0.6,0.1],"intensity":[1,1,1]}}]}}"#)
    };
    let (_, first) = relit(&scene, &body(-0.3));
    assert!(!first.warm, "{first:?}");
    for step in 1..=6 {
        let (radiance, s) = relit(&scene, &body(-0.3 + 0.1 * step as f32));
        let d = s.device.unwrap();
        assert_eq!(d.submissions, 1, "step {step}: {s:?}");
        assert!(s.warm, "step {step}: {s:?}");
        assert!(
            d.bytes_down <= 16 * nv + 4096,
            "step {step}: {d:?} for {nv} vertices"
        );
        assert!(d.bytes_down >= 12 * nv, "step {step}: {d:?}");
        assert!(d.bytes_up <= 1024, "step {step}: {d:?}");
        assert_eq!(radiance.len() as u64, nv);
    }
}

/// The components other than `full`, which the device relights whole too — one product
/// (`subsurface_only`: B = Bₑ + S E; `direct`: B = Bₑ + P E) or a solve over P
/// (`interreflection_only`, and the paper's heuristics with S E beside it), every object
/// counting as opaque at the vertices where the components take translucent objects as
/// opaque — against the CPU backend per vertex, alone, per pixel and in a batch; the
/// answers differ between components.
#[test]
fn the_device_relights_every_component_as_the_cpu_does() {
    let Some(_) = ctx() else { return };
    let cpu =
        Scene::open_with("cornell", cornell(), &Backend::cpu("reference").resources()).unwrap();
    let backend = gpu_backend();
    let gpu = Scene::open_with("cornell", cornell(), &backend.resources()).unwrap();
    let lamps = [
        r#""lights":[{"type":"point","position":[0.1,0.5,0.2],"intensity":[2,1,0.5]}]"#,
        r#""lights":[{"type":"spot","position":[0.0,0.5,0.0],"intensity":[3,3,3],"direction":[0.1,-1,0.05],"inner_deg":15,"outer_deg":35}],"direct_at":"pixel""#,
    ];
    let mut answers = Vec::new();
    for components in COMPONENTS {
        for lamp in lamps {
            let body = format!(r#"{{"components":"{components}",{lamp}}}"#);
            let (want, cs) = relit(&cpu, &body);
            assert!(lit(&want), "{body}: the lamp lights nothing");
            let (got, gs) = relit(&gpu, &body);
            let device = gs
                .device
                .unwrap_or_else(|| panic!("{body}: not on the device: {gs:?}"));
            assert_eq!(gs.components.as_str(), components, "{body}");
            assert_eq!(gs.note, cs.note, "{body}");
            if !matches!(components, "subsurface_only" | "direct") {
                assert_eq!(gs.solver, "jacobi", "{body}");
                assert!(gs.iterations > 0, "{body}: {gs:?}");
            } else {
                assert_eq!((gs.solver.as_str(), gs.iterations), ("none", 0), "{body}");
                assert_eq!(cs.solver, "none", "{body}");
                assert_eq!(device.submissions, 1, "{body}: {gs:?}");
            }
            let err = max_rel(&got, &want);
            assert!(
                err <= 1e-4,
                "{body}: device vs CPU {err} of the brightest vertex"
            );
            if let (Some(ge), Some(ce)) = (gs.auto_exposure, cs.auto_exposure) {
                assert!(
                    (ge - ce).abs() <= 0.1 + 1e-6,
                    "{body}: exposure {ge} vs {ce}"
                );
            }
            answers.push(got);
        }
    }
    // Each component's answer under the point lamp differs from the others'.
    for a in (0..answers.len()).step_by(2) {
        for b in (a + 2..answers.len()).step_by(2) {
            assert!(
                max_rel(&answers[a], &answers[b]) > 1e-3,
                "{} and {} agree",
                COMPONENTS[a / 2],
                COMPONENTS[b / 2]
            );
        }
    }
    // A batch of each, as the worker pool runs concurrent requests.
    for components in COMPONENTS {
        let bodies: Vec<String> = (0..3)
            .map(|i| {
                format!(
                    r#"{{"components":"{components}","lights":[{{"type":"point","position":[{},0.55,0.1],"intensity":[1,2,1]}}]}}"#,
                    0.2 * i as f32 - 0.2
                )
            })
            .collect();
        let want = batch(cornell(), &bodies, &Backend::cpu("reference"), 1e-6);
        let got = batch(cornell(), &bodies, &backend, 1e-6);
        for (r, ((w, _), (g, s))) in want.iter().zip(&got).enumerate() {
            assert!(s.device.is_some(), "{components} {r}: {s:?}");
            assert_eq!(s.batch, 3, "{components} {r}: {s:?}");
            let err = max_rel(g, w);
            assert!(err <= 1e-4, "{components} {r}: device vs CPU {err}");
        }
    }
}

/// The components besides `full`.
const COMPONENTS: [&str; 5] = [
    "subsurface_only",
    "direct",
    "interreflection_only",
    "heuristic_a",
    "heuristic_b",
];

/// Every component's dragged light is one submission that writes the lights and reads back
/// the colours, and a look at another component between two dragged `full` relights
/// leaves the full solve's start on the device: the relight after it is still warm and one
/// submission.
#[test]
fn every_component_drags_in_one_submission_and_keeps_the_full_start() {
    let Some(_) = ctx() else { return };
    let backend = gpu_backend();
    let scene = Scene::open_with("cornell", cornell(), &backend.resources()).unwrap();
    let body = |x: f32, components: &str| {
        format!(
            r#"{{"components":"{components}","lights":[{{"type":"point","position":[{x},0.6,0.1],"intensity":[1,1,1]}}]}}"#
        )
    };
    let at_default = |body: &str| {
        let req: RelightRequest = serde_json::from_str(body).unwrap();
        let plan = relight::plan(&scene, req).unwrap();
        relight::run(&scene, &plan).unwrap().stats
    };
    at_default(&body(-0.2, "full"));
    let warm = at_default(&body(-0.1, "full"));
    let nv = scene.bundle.vertex_positions().len() as u64;
    for components in COMPONENTS {
        // Each component's first relight makes its route; the second is a dragged light.
        at_default(&body(0.05, components));
        let s = at_default(&body(0.0, components));
        let d = s.device.unwrap_or_else(|| panic!("{components}: {s:?}"));
        assert_eq!(d.submissions, 1, "{components}: {s:?}");
        assert!(
            d.bytes_down <= 16 * nv + 4096 && d.bytes_up <= 1024,
            "{components}: {d:?} for {nv} vertices"
        );
        let after = at_default(&body(0.0, "full"));
        let d = after.device.unwrap();
        assert!(after.warm, "full after {components}: {after:?}");
        assert_eq!(d.submissions, 1, "full after {components}: {after:?}");
        assert!(
            after.iterations <= warm.iterations + 2,
            "full after {components}: {after:?}, a warm one before it: {warm:?}"
        );
    }
}

/// Plans that need more than lamps, environments and the bundle's own S (a component other
/// than `full` with overridden materials, lamp walks) run the engine's stages on the GPU
/// backend too, and say so by having no `device` stats. (A `full` relight with overridden
/// materials solves on the device: `gpu::a_translucency_slider_on_the_gpu_backend_writes_s_on_the_device`.)
#[test]
fn plans_the_device_leaves_to_the_stages_have_no_device_stats() {
    let Some(_) = ctx() else { return };
    let backend = gpu_backend();
    let scene = Scene::open_with("cornell", cornell(), &backend.resources()).unwrap();
    for body in [
        r#"{"components":"heuristic_a","materials":{"tall_block":{"type":"translucent","profile":{"type":"dipole","preset":"marble","scale":2}}}}"#,
        r#"{"lamp_walks":1000,"lights":[{"type":"point","position":[0.1,0.5,0.2],"intensity":[1,1,1]}]}"#,
    ] {
        let req: RelightRequest = match serde_json::from_str(body) {
            Ok(r) => r,
            Err(e) => panic!("{body}: {e}"),
        };
        let plan = match relight::plan(&scene, req) {
            Ok(p) => p,
            Err(e) => panic!("{body}: {e}"),
        };
        let out = relight::run(&scene, &plan).unwrap();
        assert!(out.stats.device.is_none(), "{body}: {:?}", out.stats);
    }
}

/// Environment maps (the sky, a uniform white, rotated and scaled), alone, beside a point
/// lamp and per pixel: the GPU backend's whole relight against the CPU backend per vertex.
#[test]
fn environment_relights_on_the_device_agree_with_the_cpu() {
    let Some(_) = ctx() else { return };
    let cpu = Scene::open_with("open", open_box(), &Backend::cpu("reference").resources()).unwrap();
    visibility(&cpu);
    let backend = gpu_backend();
    let gpu = Scene::open_with("open", open_box(), &backend.resources()).unwrap();
    let (dark, _) = relit(&cpu, r#"{"lights":[]}"#);
    for body in [
        r#"{"lights":[{"type":"environment","map":"builtin:sky"}]}"#,
        r#"{"lights":[{"type":"environment","map":"builtin:white","scale":0.5}]}"#,
        r#"{"lights":[{"type":"environment","map":"builtin:sky","rotation_deg":90,"scale":2},{"type":"point","position":[0.1,0.5,0.2],"intensity":[2,1,0.5]}]}"#,
        r#"{"direct_at":"pixel","lights":[{"type":"environment","map":"builtin:sky"}]}"#,
        r#"{"direct_at":"pixel","lights":[{"type":"environment","map":"builtin:sky"},{"type":"spot","position":[0.0,0.95,0.0],"intensity":[3,3,3],"direction":[0.1,-1,0.05],"inner_deg":15,"outer_deg":35}]}"#,
    ] {
        let (want, cs) = relit(&cpu, body);
        let (got, gs) = relit(&gpu, body);
        assert!(cs.device.is_none(), "{body}: {cs:?}");
        let d = gs
            .device
            .unwrap_or_else(|| panic!("{body}: not on the device: {gs:?}"));
        assert!(d.submissions >= 1, "{body}: {gs:?}");
        assert_eq!(gs.solver, "jacobi", "{body}");
        // The environment lights the scene: the answer is not the bundle's emission alone.
        assert!(
            max_rel(&want, &dark) > 1e-3,
            "{body}: the environment adds nothing"
        );
        let err = max_rel(&got, &want);
        eprintln!("{body}: device vs CPU {err:e}");
        assert!(
            err <= 1e-4,
            "{body}: device vs CPU {err} of the brightest vertex"
        );
        if body.contains("pixel") {
            let (ge, ce) = (gs.auto_exposure.unwrap(), cs.auto_exposure.unwrap());
            assert!(
                (ge - ce).abs() <= 0.1 + 1e-6,
                "{body}: exposure {ge} vs {ce}"
            );
        }
    }
    let h = backend.gpu_health();
    assert_eq!(h.scenes[0].on, "gpu", "{h:?}");
}

/// A batch that mixes sky relights with lamp-only ones (and a lamp beside the sky): each
/// as the CPU backend answers it, all on the device; then the lamp-only relights again
/// alone, with no environment left in E.
#[test]
fn batches_mixing_environment_and_lamp_relights_agree_with_the_cpu() {
    let Some(_) = ctx() else { return };
    let lamp =
        |x: f32| format!(r#"{{"type":"point","position":[{x},0.55,0.1],"intensity":[1,2,1]}}"#);
    let sky = r#"{"type":"environment","map":"builtin:sky"}"#;
    let bodies: Vec<String> = vec![
        format!(r#"{{"lights":[{sky}]}}"#),
        format!(r#"{{"lights":[{}]}}"#, lamp(-0.2)),
        format!(r#"{{"lights":[{sky},{}]}}"#, lamp(0.0)),
        format!(r#"{{"lights":[{}]}}"#, lamp(0.2)),
    ];
    let dark = batch(
        open_box(),
        &[r#"{"lights":[]}"#.to_string()],
        &Backend::cpu("reference"),
        1e-6,
    );
    let cpu = batch(open_box(), &bodies, &Backend::cpu("reference"), 1e-6);
    let backend = gpu_backend();
    let gpu = batch(open_box(), &bodies, &backend, 1e-6);
    for (r, ((want, _), (got, s))) in cpu.iter().zip(&gpu).enumerate() {
        let d = s
            .device
            .unwrap_or_else(|| panic!("relight {r}: not on the device: {s:?}"));
        assert!(d.submissions >= 1, "{s:?}");
        assert_eq!(s.batch, bodies.len(), "relight {r}: {s:?}");
        assert!(max_rel(want, &dark[0].0) > 1e-3, "relight {r} is lit");
        let err = max_rel(got, want);
        eprintln!("mixed batch, relight {r}: device vs CPU {err:e}");
        assert!(err <= 1e-4, "relight {r}: device vs CPU {err}");
    }
    // The lamps alone after the sky: the lanes' environment part is cleared.
    let lamps = vec![bodies[1].clone(), bodies[3].clone()];
    let gpu = batch(open_box(), &lamps, &backend, 1e-6);
    for (r, (got, s)) in gpu.iter().enumerate() {
        assert!(s.device.is_some(), "{s:?}");
        let err = max_rel(got, &cpu[2 * r + 1].0);
        assert!(
            err <= 1e-4,
            "lamp relight {r} after the sky: device vs CPU {err}"
        );
    }
}

/// An environment relight is one submission that reads back only the colours; the first
/// with a sky writes its bins' radiance (12 bytes a bin), and a lamp dragged under the
/// same sky writes no more than a lamp alone does (the radiance the device holds is kept).
#[test]
fn an_environment_relight_makes_one_submission_and_writes_the_sky_once() {
    let Some(_) = ctx() else { return };
    let backend = gpu_backend();
    let scene = Scene::open_with("open", open_box(), &backend.resources()).unwrap();
    let bins = visibility(&scene).bins() as u64;
    let nv = scene.bundle.vertex_positions().len() as u64;
    let body = |x: f32, map: &str| {
        format!(
            r#"{{"lights":[{{"type":"environment","map":"{map}"}},{{"type":"point","position":[{x},0.6,0.1],"intensity":[1,1,1]}}]}}"#
        )
    };
    let (_, first) = relit(&scene, &body(-0.3, "builtin:sky"));
    let d = first.device.unwrap();
    eprintln!("the first sky relight: {d:?}");
    // The lamps' 1024 bytes and the sky's bins, once.
    assert!(d.bytes_up <= 1024 + 12 * bins, "{d:?}");
    assert!(
        d.bytes_up >= 12 * bins,
        "{d:?}: the sky's radiance was written"
    );
    for step in 1..=4 {
        let (radiance, s) = relit(&scene, &body(-0.3 + 0.1 * step as f32, "builtin:sky"));
        let d = s.device.unwrap();
        eprintln!("step {step} under the same sky: {d:?}");
        assert_eq!(d.submissions, 1, "step {step}: {s:?}");
        assert!(s.warm, "step {step}: {s:?}");
        assert!(
            d.bytes_down <= 16 * nv + 4096,
            "step {step}: {d:?} for {nv} vertices"
        );
        assert!(d.bytes_down >= 12 * nv, "step {step}: {d:?}");
        // The same sky: nothing of it is written again.
        assert!(d.bytes_up <= 1024, "step {step}: {d:?}");
        assert_eq!(radiance.len() as u64, nv);
    }
    // Another map: its bins are written once more.
    let (_, s) = relit(&scene, &body(0.1, "builtin:white"));
    let d = s.device.unwrap();
    assert_eq!(d.submissions, 1, "{s:?}");
    assert!(
        d.bytes_up <= 1024 + 12 * bins && d.bytes_up >= 12 * bins,
        "{d:?}"
    );
    assert!(d.bytes_down <= 16 * nv + 4096, "{d:?}");
}
