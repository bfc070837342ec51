//! The relight transport through the server's own code (no sockets): the transfer matrix T
//! against a tight iterative solve, the light components against their definitions, area
//! lights, batching, and the errors for what cannot be done.

use std::path::{Path, PathBuf};
use translux_engine::transport::Transport;

use translux_engine::radiosity::Rgb;
use translux_engine::relight::{self, RelightOutput, RelightPlan};
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::{load_scene, load_scene_file};
use translux_proto::api::{Components, RelightRequest, Solver};
use translux_proto::bundle::{Bundle, BundleError, arrays};
use translux_server::state::Scene;

fn build(spec: &str, dir: &Path, name: &str, patches: u64, inverse: bool) -> PathBuf {
    let scene = if spec.starts_with("builtin:") {
        load_scene(spec).unwrap()
    } else {
        load_scene_file(Path::new(spec)).unwrap()
    };
    let out = dir.join(name);
    let params = PrecomputeParams {
        patches: Some(patches),
        inverse,
        ..Default::default()
    };
    precompute(&scene, &out, &params).unwrap();
    out
}

fn request(json: &str) -> RelightRequest {
    translux_proto::parse_json(json).unwrap()
}

fn plan(scene: &Scene, json: &str) -> RelightPlan {
    relight::plan(scene, request(json)).unwrap()
}

/// Runs `json` with the iterative solver at a tight tolerance.
fn tight(scene: &Scene, json: &str) -> RelightOutput {
    let mut p = plan(scene, json);
    p.solver = Solver::Iterative;
    p.tolerance = 1e-6;
    let out = relight::run(scene, &p).unwrap();
    assert!(out.stats.converged, "{:?}", out.stats);
    out
}

fn peak(v: &[Rgb]) -> f32 {
    v.iter().flatten().fold(0.0f32, |a, &x| a.max(x))
}

/// Largest |a − b| / max(|b|, floor·peak(b)) over every vertex and channel.
fn worst_rel(a: &[Rgb], b: &[Rgb], floor: f32) -> f32 {
    let p = peak(b);
    a.iter()
        .zip(b)
        .flat_map(|(x, y)| (0..3).map(move |c| (x[c] - y[c]).abs() / y[c].abs().max(floor * p)))
        .fold(0.0f32, f32::max)
}

#[test]
fn relight_with_t_equals_a_tight_iterative_solve() {
    let dir = tempfile::tempdir().unwrap();
    let scene = Scene::open("c", &build("builtin:cornell", dir.path(), "c", 900, true)).unwrap();
    let t = scene.bundle.manifest().transfer.clone().unwrap();
    assert!(t.relight_max_rel_error < 1e-3, "{t:?}");
    for lights in [
        r#"{}"#,
        r#"{"lights":[{"type":"point","position":[0.1,0.3,0.1],"intensity":[1,0.5,0.2]}]}"#,
        r#"{"lights":[{"type":"spot","position":[0,0.5,0.2],"direction":[0,-1,-0.3],"intensity":[2,2,2],"inner_deg":20,"outer_deg":35}]}"#,
    ] {
        let auto = relight::run(&scene, &plan(&scene, lights)).unwrap();
        assert_eq!(auto.stats.solver, "inverse", "{:?}", auto.stats);
        assert!(auto.stats.note.is_none());
        let reference = tight(&scene, lights);
        let w = worst_rel(&auto.radiance, &reference.radiance, 1e-3);
        eprintln!("{lights}: T vs iterative (1e-6): worst {w:.2e}");
        assert!(w < 0.005, "T differs from the iterative solve by {w}");
        // The default 0.5% iterative solve is close too.
        let it = relight::run(
            &scene,
            &plan(
                &scene,
                &lights
                    .replacen('{', r#"{"solver":"iterative","#, 1)
                    .replacen(",}", "}", 1),
            ),
        )
        .unwrap();
        assert_eq!(
            it.stats.solver, "jacobi",
            "auto picks Jacobi in the Cornell box"
        );
        assert!(worst_rel(&it.radiance, &reference.radiance, 1e-2) < 0.05);
    }

    // A translucency change makes T stale: auto takes the iterative path and says why, and
    // an explicit "inverse" is refused.
    let marble2 = r#"{"materials":{"tall_block":{"type":"translucent","profile":{"type":"dipole","preset":"marble","scale":2}}}}"#;
    let out = relight::run(&scene, &plan(&scene, marble2)).unwrap();
    assert_ne!(out.stats.solver, "inverse");
    assert!(
        out.stats.note.as_deref().unwrap().contains("tall_block"),
        "{:?}",
        out.stats.note
    );
    let e = relight::plan(
        &scene,
        request(&marble2.replacen('{', r#"{"solver":"inverse","#, 1)),
    )
    .unwrap_err();
    let e = translux_server::AppError::from(e);
    assert_eq!((e.status.as_u16(), e.code), (400, "unsupported"), "{e:?}");
    assert!(e.message.contains("stale"), "{}", e.message);
    // Components T does not hold are refused with "inverse", served iteratively by auto.
    let e = relight::plan(
        &scene,
        request(r#"{"solver":"inverse","components":"heuristic_a"}"#),
    )
    .unwrap_err();
    assert!(e.message.contains("heuristic_a"), "{}", e.message);
    let out = relight::run(&scene, &plan(&scene, r#"{"components":"heuristic_a"}"#)).unwrap();
    assert_ne!(out.stats.solver, "inverse");
}

#[test]
fn batches_equal_single_relights_on_both_paths() {
    let dir = tempfile::tempdir().unwrap();
    let scene = Scene::open("c", &build("builtin:cornell", dir.path(), "c", 700, true)).unwrap();
    let reqs = [
        r#"{"lights":[{"type":"point","position":[0.1,0.3,0.1],"intensity":[1,0.5,0.2]}]}"#,
        r#"{"lights":[{"type":"point","position":[-0.1,0.4,0.0],"intensity":[0.3,0.5,1]}]}"#,
        r#"{"solver":"iterative","lights":[{"type":"point","position":[0.0,0.45,0.1],"intensity":[1,1,1]}]}"#,
        r#"{"solver":"iterative","lights":[{"type":"point","position":[0.1,0.45,-0.1],"intensity":[1,2,1]}]}"#,
        r#"{"components":"direct"}"#,
    ];
    // A tight tolerance, so that batched and single solves must agree closely.
    let plans: Vec<RelightPlan> = reqs
        .iter()
        .map(|r| RelightPlan {
            tolerance: 1e-6,
            ..plan(&scene, r)
        })
        .collect();
    let batch = relight::run_batch(&scene, &plans);
    assert_eq!(batch.len(), plans.len());
    for (p, b) in plans.iter().zip(&batch) {
        let b = b.as_ref().unwrap();
        let single = relight::run(&scene, p).unwrap();
        assert_eq!(b.stats.solver, single.stats.solver);
        let w = worst_rel(&b.radiance, &single.radiance, 1e-3);
        assert!(w < 1e-3, "{}: {w}", b.stats.solver);
    }
    let inverse: Vec<_> = batch
        .iter()
        .filter_map(|b| b.as_ref().ok())
        .filter(|b| b.stats.solver == "inverse")
        .collect();
    assert!(inverse.len() >= 2 && inverse.iter().all(|b| b.stats.batch >= 2));
}

#[test]
fn inverse_without_t_is_a_clear_400_and_a_truncated_t_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let plain = Scene::open("p", &build("builtin:cornell", dir.path(), "p", 400, false)).unwrap();
    let e = relight::plan(&plain, request(r#"{"solver":"inverse"}"#)).unwrap_err();
    let e = translux_server::AppError::from(e);
    assert_eq!((e.status.as_u16(), e.code), (400, "unsupported"), "{e:?}");
    assert!(e.message.contains("--inverse"), "{}", e.message);
    // auto says why it solved.
    let out = relight::run(&plain, &plan(&plain, "{}")).unwrap();
    assert!(out.stats.note.unwrap().contains("no transfer matrix"));

    let with_t = build("builtin:cornell", dir.path(), "t", 400, true);
    let file = with_t.join("transfer.f16");
    let len = std::fs::metadata(&file).unwrap().len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&file)
        .unwrap()
        .set_len(len - 2)
        .unwrap();
    match Bundle::open(&with_t) {
        Err(BundleError::Truncated { file, .. }) => assert_eq!(file, "transfer.f16"),
        other => panic!("{other:?}"),
    }
    // A manifest that claims T without listing the arrays is refused too.
    let with_t2 = build("builtin:cornell", dir.path(), "t2", 400, true);
    let mpath = with_t2.join("manifest.json");
    let mut m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&mpath).unwrap()).unwrap();
    m["arrays"]
        .as_object_mut()
        .unwrap()
        .remove(arrays::TRANSFER_SCALE);
    std::fs::write(&mpath, m.to_string()).unwrap();
    let e = Bundle::open(&with_t2).unwrap_err();
    assert!(e.to_string().contains("transfer_scale.f32"), "{e}");
}

#[test]
fn components_match_their_definitions() {
    let dir = tempfile::tempdir().unwrap();
    let scene = Scene::open("c", &build("builtin:cornell", dir.path(), "c", 900, false)).unwrap();
    let m = scene.bundle.manifest();
    let block = m.objects.iter().find(|o| o.name == "tall_block").unwrap();
    let rho = block.albedo;
    let run = |json: &str| tight(&scene, json).radiance;

    // All-diffuse (the block made diffuse): every inter-reflecting component is classical
    // radiosity.
    let diffuse = format!(
        r#""materials":{{"tall_block":{{"type":"diffuse","albedo":[{},{},{}]}}}}"#,
        rho[0], rho[1], rho[2]
    );
    let full_d = run(&format!(r#"{{{diffuse}}}"#));
    for c in ["interreflection_only", "heuristic_a", "heuristic_b"] {
        let other = run(&format!(r#"{{"components":"{c}",{diffuse}}}"#));
        let w = worst_rel(&other, &full_d, 1e-3);
        eprintln!("all diffuse: {c} vs full {w:.2e}");
        assert!(w < 1e-3, "{c}: {w}");
    }
    // Inter-reflection only = the full solve with the block opaque at its ρ̄.
    let io = run(r#"{"components":"interreflection_only"}"#);
    assert!(worst_rel(&io, &full_d, 1e-3) < 1e-3);

    // Translucent: full ≥ subsurface_only (S F B ≥ 0), and strictly more somewhere.
    let full = run("{}");
    let sub = run(r#"{"components":"subsurface_only"}"#);
    let p = peak(&full);
    assert!(
        full.iter()
            .zip(&sub)
            .all(|(f, s)| (0..3).all(|c| f[c] >= s[c] - 1e-4 * p))
    );
    assert!(
        full.iter()
            .zip(&sub)
            .any(|(f, s)| f[0] > 1.5 * s[0] + 1e-3 * p)
    );
    // The heuristics are not the full model in a translucent scene, and B ≥ S E holds for
    // heuristic B by construction.
    let ha = run(r#"{"components":"heuristic_a"}"#);
    let hb = run(r#"{"components":"heuristic_b"}"#);
    assert!(worst_rel(&ha, &full, 1e-2) > 1e-3);
    assert!(worst_rel(&hb, &full, 1e-2) > 1e-3);
    assert!(
        hb.iter()
            .zip(&sub)
            .all(|(h, s)| (0..3).all(|c| h[c] >= s[c] - 1e-4 * p))
    );
    // Direct: B = Bₑ + ρ̄E, below subsurface-only nowhere near the block... and equal to it
    // on opaque patches (S = diag ρ there). Vertices on the walls far from the block agree.
    let direct = run(r#"{"components":"direct"}"#);
    let agree = direct
        .iter()
        .zip(&sub)
        .filter(|(d, s)| (0..3).all(|c| (d[c] - s[c]).abs() <= 1e-5 * p))
        .count();
    assert!(agree > direct.len() / 2, "{agree} of {}", direct.len());
}

#[test]
fn subsurface_only_equals_full_when_nothing_sees_anything() {
    // One convex translucent box: no patch sees another (F = 0), so the full transport is
    // B = Bₑ + S E exactly.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("cube.json");
    std::fs::write(
        &file,
        r#"{"objects":[{"name":"cube","mesh":{"shape":"box","size":[0.1,0.1,0.1]},
            "material":{"type":"translucent","profile":{"type":"dipole","preset":"skimmilk"}}}],
           "lights":[{"type":"point","position":[0.1,0.3,0.2],"intensity":[1,1,1]}]}"#,
    )
    .unwrap();
    let scene = Scene::open(
        "cube",
        &build(file.to_str().unwrap(), dir.path(), "cube", 600, true),
    )
    .unwrap();
    assert_eq!(scene.bundle.manifest().form_factors.nnz, 0);
    let full = tight(&scene, "{}").radiance;
    let sub = relight::run(&scene, &plan(&scene, r#"{"components":"subsurface_only"}"#))
        .unwrap()
        .radiance;
    let via_t = relight::run(&scene, &plan(&scene, "{}")).unwrap();
    assert_eq!(via_t.stats.solver, "inverse");
    assert!(worst_rel(&full, &sub, 1e-4) < 1e-5);
    assert!(worst_rel(&via_t.radiance, &sub, 1e-4) < 1e-5);
    // Light went through the cube: faces the light does not reach glow.
    assert!(peak(&sub) > 0.0);
}

#[test]
fn an_area_light_scales_the_radiosity_on_both_paths() {
    // A closed room lit only by an emitter panel, with a translucent block.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("room.json");
    std::fs::write(
        &file,
        r#"{"objects":[
            {"name":"room","mesh":{"shape":"box","size":[1,1,1],"inward":true},
             "material":{"type":"diffuse","albedo":[0.7,0.6,0.5]}},
            {"name":"panel","mesh":{"shape":"quad","size":[0.3,0.3]},
             "transform":{"rotate_deg":[180,0,0],"translate":[0,0.49,0]},
             "material":{"type":"emitter","radiance":[2,2,2]}},
            {"name":"block","mesh":{"shape":"box","size":[0.2,0.3,0.2]},
             "transform":{"translate":[0,-0.35,0]},
             "material":{"type":"translucent","profile":{"type":"dipole","preset":"marble"}}}],
           "lights":[]}"#,
    )
    .unwrap();
    let scene = Scene::open(
        "room",
        &build(file.to_str().unwrap(), dir.path(), "room", 900, true),
    )
    .unwrap();
    let base = tight(&scene, "{}").radiance;
    assert!(peak(&base) > 0.0);
    let doubled = r#"{"materials":{"panel":{"type":"emitter","radiance":[4,4,4]}}}"#;
    let twice = tight(&scene, doubled).radiance;
    let scaled: Vec<Rgb> = base.iter().map(|v| v.map(|x| 2.0 * x)).collect();
    assert!(worst_rel(&twice, &scaled, 1e-3) < 1e-4);
    // With T: an emitter's radiance does not make T stale.
    let via_t = relight::run(&scene, &plan(&scene, doubled)).unwrap();
    assert_eq!(via_t.stats.solver, "inverse", "{:?}", via_t.stats);
    let w = worst_rel(&via_t.radiance, &twice, 1e-3);
    eprintln!("area light: T vs iterative {w:.2e}");
    assert!(w < 0.005);
    // Red panel: the room turns red, the B ratio per channel follows.
    let red = relight::run(
        &scene,
        &plan(
            &scene,
            r#"{"materials":{"panel":{"type":"emitter","radiance":[2,0,0]}}}"#,
        ),
    )
    .unwrap()
    .radiance;
    assert!(red.iter().all(|v| v[1] == 0.0 && v[2] == 0.0));
    assert!(
        worst_rel(
            &red.iter().map(|v| [v[0], 0.0, 0.0]).collect::<Vec<_>>(),
            &base.iter().map(|v| [v[0], 0.0, 0.0]).collect::<Vec<_>>(),
            1e-3
        ) < 0.005
    );
    let _ = Components::Full;
}

#[test]
fn the_server_solve_equals_the_library_solve() {
    use translux_engine::radiosity::{self, SolveParams, SparseScatter};
    let dir = tempfile::tempdir().unwrap();
    let scene = Scene::open("c", &build("builtin:cornell", dir.path(), "c", 400, false)).unwrap();
    let b = &scene.bundle;
    let e = radiosity::BundleLighting::new(b)
        .irradiance(&b.manifest().lights)
        .unwrap();
    let (x, st) = radiosity::solve(
        &Transport::of(b),
        &SparseScatter(b.subsurface()),
        b.patch_emission(),
        &e,
        &SolveParams::default(),
        None,
    )
    .unwrap();
    let mut want = translux_engine::radiosity::vertex_radiance(
        b.triangle_vertices(),
        b.patch_areas(),
        b.vertex_positions().len(),
        &x,
    );
    // The direct light of the diffuse walls at their vertices, as the relight takes it.
    let lighting = radiosity::BundleLighting::new(b);
    let materials: Vec<_> = b.manifest().objects.iter().map(|o| &o.material).collect();
    translux_engine::vertexlight::apply(
        b,
        &lighting.occluder,
        &b.manifest().lights,
        &translux_engine::vertexlight::opaque_objects(&materials, Components::Full),
        translux_engine::vertexlight::PatchTerms {
            radiosity: &x,
            irradiance: &e,
            albedo: b.patch_albedo(),
        },
        &mut want,
    )
    .unwrap();
    let got = relight::run(&scene, &plan(&scene, "{}")).unwrap();
    eprintln!("{st:?} / {:?}", got.stats);
    assert_eq!(got.stats.iterations, st.iterations);
    assert!(worst_rel(&got.radiance, &want, 1e-3) < 1e-5);
}

/// S⁽ⁿ⁾ of a lone simulated cube straight from the stored walks: Σ over row j's records of
/// the collimated weight × e^(−σa L_bin).
fn s_normal_times(b: &Bundle, e: &[Rgb], sigma_a: [f32; 3]) -> Vec<Rgb> {
    let walks = b.walks().unwrap();
    let normal = walks
        .normal
        .expect("a version 7 bundle has collimated weights");
    (0..b.patch_areas().len())
        .map(|j| {
            let (cols, bins, _) = walks.row(j);
            let at = walks.row_ptr[j] as usize;
            let mut y = [0.0f32; 3];
            for (k, (&i, &bin)) in cols.iter().zip(bins).enumerate() {
                let l = translux_engine::simulated::bin_length_mm(bin);
                for c in 0..3 {
                    y[c] += normal[at + k][c]
                        * (-(sigma_a[c] as f64) * l).exp() as f32
                        * e[i as usize][c];
                }
            }
            y
        })
        .collect()
}

/// A lone simulated 16 mm cube (σs′ 0.8, 0.6, 0.5; σa 0.01, 0.02, 0.04 mm⁻¹; η = 1; F = 0)
/// lit by `lights` (JSON), precomputed with T into `dir`, and the irradiance its lights give
/// each patch.
fn lone_simulated_cube(dir: &Path, lights: &str) -> (Scene, Vec<Rgb>) {
    let file = dir.join("cube.json");
    std::fs::write(
        &file,
        format!(
            r#"{{"unit_mm": 1, "objects":[{{"name":"cube","mesh":{{"shape":"box","size":[16,16,16]}},
                "material":{{"type":"simulated","sigma_s_prime":[0.8,0.6,0.5],
                            "sigma_a":[0.01,0.02,0.04],"eta":1.0}}}}],
               "lights":{lights}}}"#
        ),
    )
    .unwrap();
    let scene = Scene::open(
        "cube",
        &build(file.to_str().unwrap(), dir, "cube", 400, true),
    )
    .unwrap();
    assert_eq!(scene.bundle.manifest().form_factors.nnz, 0);
    let b = &scene.bundle;
    let e = translux_engine::radiosity::BundleLighting::new(b)
        .irradiance(&b.manifest().lights)
        .unwrap();
    (scene, e)
}

/// Per-patch values at the viewer's vertices, as a relight answers.
fn at_vertices(b: &Bundle, x: &[Rgb]) -> Vec<Rgb> {
    translux_engine::radiosity::vertex_radiance(
        b.triangle_vertices(),
        b.patch_areas(),
        b.vertex_positions().len(),
        x,
    )
}

/// The subsurface-only relight, the one through T and the iterative solver all answer
/// `expect` (vertex values; `what` names it) to 1e-4.
fn every_path_gives(scene: &Scene, expect: &[Rgb], what: &str) {
    let sub = relight::run(scene, &plan(scene, r#"{"components":"subsurface_only"}"#))
        .unwrap()
        .radiance;
    let via_t = relight::run(scene, &plan(scene, "{}")).unwrap();
    assert_eq!(via_t.stats.solver, "inverse");
    let full = tight(scene, "{}").radiance;
    for (path, got) in [
        ("subsurface_only", &sub),
        ("T", &via_t.radiance),
        ("iterative", &full),
    ] {
        let w = worst_rel(got, expect, 1e-3);
        eprintln!("{path}: worst {w:.2e} against {what}");
        assert!(w < 1e-4, "{path} differs from {what} by {w}");
    }
}

#[test]
fn lamps_enter_a_simulated_object_collimated_on_every_path() {
    // A lone simulated cube (F = 0) lit by a directional light along its −x: the lit face's
    // light enters at normal incidence, so B = S⁽ⁿ⁾ E exactly, S⁽ⁿ⁾ summed here from the
    // bundle's records; the same through T and the iterative solver, and a diffuse-entry
    // answer (the plain S E) differs.
    let dir = tempfile::tempdir().unwrap();
    let (scene, e) = lone_simulated_cube(
        dir.path(),
        r#"[{"type":"directional","direction":[-1,0,0],"irradiance":[1,1,1]}]"#,
    );
    let b = &scene.bundle;
    let lit = e.iter().filter(|v| v[0] > 0.0).count();
    assert!(lit > 20 && lit < e.len() / 4, "{lit} lit patches");
    let expect = at_vertices(b, &s_normal_times(b, &e, [0.01, 0.02, 0.04]));
    every_path_gives(&scene, &expect, "S(n) E from the records");
    // Diffuse entry (the stored S alone) sends more back out of the lit face: B differs.
    use translux_engine::radiosity::Scatter;
    let mut diffuse = vec![[0.0f32; 3]; e.len()];
    translux_engine::radiosity::SparseScatter(b.subsurface()).apply(&e, &mut diffuse);
    let diffuse = at_vertices(b, &diffuse);
    assert!(worst_rel(&diffuse, &expect, 1e-3) > 0.05);
}

#[test]
fn a_slanted_lamp_enters_with_its_direction_on_every_path() {
    // The same lone cube lit by a directional light along (−0.866, 0, −0.5): it enters +x at
    // μ₀ = 0.87 and +z at 0.5. B = S E + y with y summed here from the bundle's records,
    // y_j = Σ records e^(−σa L) [(w⁽ⁿ⁾ − w)(3μ₀ − 2) + G_u u₀ + G_v v₀ + U (3μ₀ − 3)] E_i
    // (u₀, v₀ the beam's direction along source i's tangent frame, G unpacked from the
    // record's ratios, U the weight of records flagged unscattered); the same through T,
    // the iterative solver and the subsurface-only relight. Leaving out the harmonic and U
    // (S(μ₀) alone) differs.
    let dir = tempfile::tempdir().unwrap();
    let (scene, e) = lone_simulated_cube(
        dir.path(),
        r#"[{"type":"directional","direction":[-0.866,0,-0.5],"irradiance":[1,1,1]}]"#,
    );
    let b = &scene.bundle;
    let d0 = glam::Vec3::new(-0.866, 0.0, -0.5).normalize();
    let corners = translux_engine::smatrix::bundle_geometry(b).corners;
    let normals = b.patch_normals();
    let walks = b.walks().unwrap();
    let (normal, lamp) = (walks.normal.unwrap(), walks.lamp.expect("version 8 walks"));
    let sigma_a = [0.01f32, 0.02, 0.04];
    let mut plain = vec![[0.0f32; 3]; e.len()];
    use translux_engine::radiosity::Scatter;
    translux_engine::radiosity::SparseScatter(b.subsurface()).apply(&e, &mut plain);
    let (mut full_y, mut mu_only_y) = (plain.clone(), plain.clone());
    for j in 0..e.len() {
        let (cols, bins, ws) = walks.row(j);
        let at = walks.row_ptr[j] as usize;
        for (k, ((&i, &bin), w)) in cols.iter().zip(bins).zip(ws).enumerate() {
            let i = i as usize;
            if e[i] == [0.0; 3] {
                continue;
            }
            let n = glam::Vec3::from(normals[i]);
            let mu0 = (-d0.dot(n)).clamp(0.0, 1.0);
            let (fu, fv) = translux_engine::simulated::tangent_frame(&corners[i], n);
            let l = translux_engine::simulated::bin_length_mm(bin);
            let wn = normal[at + k];
            let [gu, gv] = translux_engine::simulated::unpack_tilt(&lamp[at + k], w);
            let unscattered = bin & translux_proto::bundle::SIM_UNSCATTERED != 0;
            for c in 0..3 {
                let a = (-(sigma_a[c] as f64) * l).exp() as f32 * e[i][c];
                let tilt = (wn[c] - w[c]) * (3.0 * mu0 - 2.0);
                let more = if unscattered {
                    w[c] * (3.0 * mu0 - 3.0)
                } else {
                    gu[c] * d0.dot(fu) + gv[c] * d0.dot(fv)
                };
                full_y[j][c] += a * (tilt + more);
                mu_only_y[j][c] += a * tilt;
            }
        }
    }
    let expect = at_vertices(b, &full_y);
    every_path_gives(&scene, &expect, "S E + y from the records");
    let mu_only = at_vertices(b, &mu_only_y);
    let w = worst_rel(&mu_only, &expect, 1e-3);
    eprintln!("S(μ₀) alone: worst {w:.3}");
    assert!(w > 0.05, "the harmonic and U change the answer: {w}");
}

#[test]
fn a_lamps_own_beams_replace_the_model_on_every_path() {
    // The lone cube lit at a slant, its lamp walked along its own beam (`"lamp_walks"`):
    // B = S E + y with y = X − S E′ (the walked exitance in place of the model's first
    // scattering; F = 0, E′ = E for a directional light) on every path, the same walks as
    // the engine's `lampwalk::first_scatter` makes (seeded); the model's answer differs.
    // Walk counts out of range are refused, naming the field.
    let dir = tempfile::tempdir().unwrap();
    let (scene, e) = lone_simulated_cube(
        dir.path(),
        r#"[{"type":"directional","direction":[-0.866,0,-0.5],"irradiance":[1,1,1]}]"#,
    );
    let b = &scene.bundle;
    let lit = translux_engine::radiosity::BundleLighting::new(b);
    let lights = b.manifest().lights.clone();
    let per = 200_000;
    let walked =
        translux_engine::lampwalk::first_scatter(b, lit.geometry(), &lit.occluder, &lights, per)
            .expect("the lamp lights the cube");
    let model =
        translux_engine::collimated::first_scatter(b, lit.geometry(), &lit.occluder, &lights)
            .unwrap();
    use translux_engine::radiosity::Scatter;
    let mut se = vec![[0.0f32; 3]; e.len()];
    translux_engine::radiosity::SparseScatter(b.subsurface()).apply(&e, &mut se);
    let plus = |y: &[Rgb]| -> Vec<Rgb> {
        let sum: Vec<Rgb> = se
            .iter()
            .zip(y)
            .map(|(a, y)| std::array::from_fn(|c| a[c] + y[c]))
            .collect();
        at_vertices(b, &sum)
    };
    let (expect, modelled) = (plus(&walked), plus(&model));
    let body = format!(r#"{{"lamp_walks": {per}}}"#);
    let sub = format!(r#"{{"lamp_walks": {per}, "components": "subsurface_only"}}"#);
    let via_t = relight::run(&scene, &plan(&scene, &body)).unwrap();
    assert_eq!(via_t.stats.solver, "inverse");
    let note = via_t.stats.note.clone().unwrap_or_default();
    assert!(note.contains("lamp_walks"), "{note}");
    for (path, got) in [
        (
            "subsurface_only",
            relight::run(&scene, &plan(&scene, &sub)).unwrap().radiance,
        ),
        ("T", via_t.radiance),
        ("iterative", tight(&scene, &body).radiance),
    ] {
        let w = worst_rel(&got, &expect, 1e-3);
        eprintln!("{path}: worst {w:.2e} against S E + X − S E′");
        assert!(w < 1e-4, "{path} differs from the walked answer by {w}");
    }
    let w = worst_rel(&modelled, &expect, 1e-3);
    eprintln!("the model against the walks: worst {w:.3}");
    assert!(w > 0.02, "the walks change the answer: {w}");
    for bad in ["0", "10000001"] {
        let req = request(&format!(r#"{{"lamp_walks": {bad}}}"#));
        let err = relight::plan(&scene, req).unwrap_err();
        assert!(err.message.contains("lamp_walks"), "{}", err.message);
    }
}

/// ‖a − b‖₂ / ‖b‖₂ over every vertex and channel.
fn rel_l2(a: &[Rgb], b: &[Rgb]) -> f64 {
    let (mut num, mut den) = (0.0f64, 0.0f64);
    for (x, y) in a.iter().zip(b) {
        for c in 0..3 {
            num += ((x[c] - y[c]) as f64).powi(2);
            den += (y[c] as f64).powi(2);
        }
    }
    (num / den).sqrt()
}

#[test]
fn a_translucency_slider_dragged_steadily_starts_along_its_last_step() {
    let dir = tempfile::tempdir().unwrap();
    let path = build("builtin:cornell_paper", dir.path(), "c", 1500, false);
    let scene = Scene::open("c", &path).unwrap();
    // The references come from a scene of their own, so they leave no warm start here.
    let reference = Scene::open("r", &path).unwrap();
    let body = |s: f32| {
        format!(
            r#"{{"solver": "iterative", "materials": {{"tall_block": {{"type": "translucent",
                "profile": {{"type": "dipole", "preset": "marble", "scale": {s}}}}}}}}}"#
        )
    };
    let mut products = Vec::new();
    for step in 0..8 {
        let json = body(1.0 + 0.15 * step as f32);
        let got = relight::run(&scene, &plan(&scene, &json)).unwrap();
        let want = tight(&reference, &json);
        let err = rel_l2(&got.radiance, &want.radiance);
        eprintln!("step {step}: {:?}, {err:.2e} from a tight solve", got.stats);
        assert!(got.stats.converged, "step {step}: {:?}", got.stats);
        assert!(err < 0.01, "step {step}: {err}");
        products.push(got.stats.products);
    }
    // From the third step on the start moves along the last one: fewer products than
    // the second step, which started from the first's answer alone (at least one a step
    // where that answer was already close enough: none).
    let later: u32 = products[2..].iter().sum();
    assert!(
        later < products[1].max(1) * (products.len() as u32 - 2),
        "products per step {products:?}"
    );
}

/// The scene keeps the last lights' direct light (at the patches and at the vertices) for
/// the next request with the same lights: every answer of a sequence that repeats, changes
/// and returns to lights and materials equals the one a fresh scene gives, bit for bit.
#[test]
fn direct_light_kept_for_the_same_lights_answers_as_traced_afresh() {
    let dir = tempfile::tempdir().unwrap();
    let path = build("builtin:cornell_paper", dir.path(), "c", 1500, false);
    let scene = Scene::open("c", &path).unwrap();
    let a = r#"[{"type":"point","position":[0.1,0.3,0.1],"intensity":[1,0.5,0.2]}]"#;
    let b = r#"[{"type":"point","position":[-0.1,0.4,0.0],"intensity":[0.3,0.5,1]}]"#;
    // The tall block turned diffuse: its vertices then take their direct light at the
    // vertex (the traced vertices depend on the materials too).
    let diffuse =
        r#", "materials": {"tall_block": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}}"#;
    let body = |lights: &str, materials: &str, components: &str| {
        format!(r#"{{"components": "{components}", "lights": {lights}{materials}}}"#)
    };
    let steps = [
        body(a, "", "direct"),
        body(a, "", "direct"),
        body(a, diffuse, "direct"),
        body(b, diffuse, "direct"),
        body(b, "", "direct"),
        body(a, "", "direct"),
        body(a, "", "subsurface_only"),
        body(a, diffuse, "full"),
    ];
    for (k, json) in steps.iter().enumerate() {
        let got = relight::run(&scene, &plan(&scene, json)).unwrap();
        let fresh = Scene::open("f", &path).unwrap();
        let want = relight::run(&fresh, &plan(&fresh, json)).unwrap();
        assert!(
            got.radiance == want.radiance,
            "step {k} ({json}): {:.2e} from the fresh scene's answer",
            rel_l2(&got.radiance, &want.radiance)
        );
    }
}

/// A scene prepared for translucency changes ahead of them (S's radial terms made in the
/// background) answers its first change as one that makes them on that change, bit for
/// bit; either way the scene then says it is ready, and preparing again does nothing.
#[test]
fn a_scene_prepared_ahead_answers_its_first_translucency_change_as_one_that_was_not() {
    use translux_proto::api::PrepState;
    let dir = tempfile::tempdir().unwrap();
    let path = build("builtin:cornell_paper", dir.path(), "c", 1500, false);
    let prepared = Scene::open("p", &path).unwrap();
    let lazy = Scene::open("l", &path).unwrap();
    assert_eq!(prepared.translucency().state, PrepState::Pending);
    assert_eq!(prepared.material_cache_bytes(), 0);
    let p = prepared.prepare_translucency();
    assert_eq!(p.state, PrepState::Ready, "{p:?}");
    assert_eq!(p.on.as_deref(), Some("cpu"));
    let bytes = p.bytes.expect("the terms' bytes");
    assert!(
        bytes > 0 && bytes == prepared.material_cache_bytes(),
        "{p:?}"
    );
    assert!(p.seconds.is_some_and(|s| s >= 0.0), "{p:?}");
    assert_eq!(
        prepared.prepare_translucency(),
        p,
        "a second preparation changes nothing"
    );

    let json = r#"{"materials": {"tall_block": {"type": "translucent",
        "profile": {"type": "dipole", "preset": "marble", "scale": 2.5}}}}"#;
    assert_eq!(lazy.translucency().state, PrepState::Pending);
    let a = relight::run(&prepared, &plan(&prepared, json)).unwrap();
    let b = relight::run(&lazy, &plan(&lazy, json)).unwrap();
    assert_eq!(a.radiance, b.radiance);
    let l = lazy.translucency();
    assert_eq!(
        (l.state, l.on.as_deref()),
        (PrepState::Ready, Some("cpu")),
        "{l:?}"
    );
    assert_eq!(l.bytes, Some(bytes));
}
