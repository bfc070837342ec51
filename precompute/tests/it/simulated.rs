//! Simulated S through the pipeline: walks stored in the bundle, re-weighted for a new
//! absorption on a rebuild, and the meshes and settings walks cannot serve refused with a
//! message that names the problem.

use std::path::Path;
use std::time::Duration;

use translux_engine::collimated::{self, TiltOf};
use translux_engine::smatrix::{self, SParams};
use translux_engine::stop::{Stop, StopFlag};
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::load_scene_file;
use translux_proto::bundle::Bundle;
use translux_proto::scene::{Material, SceneFile};

/// A 20 mm box of a scattering medium on nothing, in millimetres.
fn cube_scene(material: &str) -> String {
    format!(
        r#"{{"unit_mm": 1, "objects": [
            {{"name": "cube", "mesh": {{"shape": "box", "size": [20, 20, 20]}},
              "material": {material}}}],
           "lights": [{{"type": "directional", "direction": [0, -1, 0], "irradiance": [1, 1, 1]}}]}}"#
    )
}

const MEDIUM: &str = r#"{"type": "simulated", "sigma_s_prime": [0.5, 0.45, 0.35],
    "sigma_a": [0.004, 0.008, 0.02], "eta": 1.0}"#;

fn write(dir: &Path, name: &str, text: &str) -> std::path::PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

fn build(dir: &Path, scene: &str, patches: u64) -> Result<Bundle, String> {
    let path = write(dir, "scene.json", scene);
    let loaded = load_scene_file(&path).map_err(|e| e.to_string())?;
    let out = dir.join("bundle");
    let params = PrecomputeParams {
        patches: Some(patches),
        ..Default::default()
    };
    precompute(&loaded, &out, &params).map_err(|e| e.to_string())?;
    Ok(Bundle::open(&out).unwrap())
}

fn with_sigma_a(b: &Bundle, sigma_a: [f32; 3]) -> Material {
    let mut m = b.manifest().objects[0].material.clone();
    if let Material::Simulated { sigma_a: s, .. } = &mut m {
        *s = Some(sigma_a);
    }
    m
}

/// Σ over all entries of A_j S_ji, per channel.
fn total(b: &Bundle, s: translux_proto::csr::CsrView<'_, [f32; 3]>) -> [f64; 3] {
    let area = b.patch_areas();
    let mut t = [0.0f64; 3];
    for (j, &aj) in area.iter().enumerate() {
        for v in s.row(j).1 {
            for c in 0..3 {
                t[c] += f64::from(aj) * f64::from(v[c]);
            }
        }
    }
    t
}

#[test]
fn a_simulated_cube_stores_its_walks_and_changes_absorption_without_new_walks() {
    let dir = tempfile::tempdir().unwrap();
    let b = build(dir.path(), &cube_scene(MEDIUM), 600).unwrap();
    let m = b.manifest();
    assert!(m.subsurface.walks > 0);
    let o = &m.subsurface.objects[0];
    assert_eq!(o.method, "simulated");
    let sim = o.simulation.as_ref().unwrap();
    assert!(sim.walks >= 256 * 600, "{sim:?}");
    assert!(sim.noise_median <= 0.01 + 1e-6, "{sim:?}");
    assert!(o.max_column_energy <= 1.0);
    assert_eq!(sim.lost * 1000 / sim.walks, 0, "{sim:?}");
    let walks = b.walks().expect("walks are stored");
    assert_eq!(walks.row_ptr.len(), b.patch_areas().len() + 1);

    // The same absorption rebuilds the stored S exactly.
    let params = SParams::default();
    let same = with_sigma_a(&b, [0.004, 0.008, 0.02]);
    let (s, _) = smatrix::rebuild_from_bundle(&b, &[(0, same)], &params).unwrap();
    let stored = b.subsurface();
    assert_eq!(s.col.len(), stored.nnz());
    let (t0, t1) = (total(&b, stored), total(&b, s.view().unwrap()));
    for c in 0..3 {
        assert!((t0[c] - t1[c]).abs() <= 1e-6 * t0[c], "{t0:?} {t1:?}");
    }
    // More absorption re-emits less, channel by channel.
    let more = with_sigma_a(&b, [0.04, 0.008, 0.02]);
    let (s, _) = smatrix::rebuild_from_bundle(&b, &[(0, more.clone())], &params).unwrap();
    let t2 = total(&b, s.view().unwrap());
    assert!(t2[0] < 0.9 * t0[0], "{t2:?} {t0:?}");
    assert!((t2[1] - t0[1]).abs() <= 1e-6 * t0[1]);

    // A relight's absorption change makes S and the lamps' tilt (Δ = S⁽ⁿ⁾ − S, G_u, G_v, U)
    // in one pass over the walks (smatrix::rebuild_with_terms_and_tilt): the same S as the
    // rebuild above, and the same tilt as re-weighting it on its own.
    let terms = smatrix::terms_of_bundle(&b, &params.quadrature);
    let (s_both, _, tilts) =
        smatrix::rebuild_with_terms_and_tilt(&b, &[(0, more.clone())], &params, &terms).unwrap();
    assert_eq!(s_both.csr().val, s.val);
    assert_eq!(tilts.len(), 1);
    let fused = collimated::tilt_of_with(&b, &[&more], tilts);
    let alone = collimated::tilt_of(&b, &[&more]);
    let (TiltOf::Some(fused), TiltOf::Some(alone)) = (fused, alone) else {
        panic!("the walks carry collimated weights");
    };
    assert_eq!(fused.ranges, alone.ranges);
    assert_eq!(fused.delta.csr().col, alone.delta.csr().col);
    assert_eq!(fused.delta.csr().val, alone.delta.csr().val);
    // Δ, and the lamps' G_u, G_v and U beside it (format version 8).
    for part in 0..4 {
        assert!(
            fused.delta.csr().val.iter().any(|v| v[part][0] != 0.0),
            "part {part} of the tilt is all 0"
        );
    }
    assert!(fused.has_harmonic());
    let at_built = collimated::tilt_of(&b, &[&b.manifest().objects[0].material]);
    let TiltOf::Some(at_built) = at_built else {
        panic!("the walks carry collimated weights");
    };
    assert_ne!(
        at_built.delta.csr().val,
        fused.delta.csr().val,
        "Δ follows σa"
    );

    // The next absorption change is written into that S and tilt in place, in one pass over
    // the walks, and equals a rebuild at the new absorption value for value.
    let third = with_sigma_a(&b, [0.01, 0.03, 0.02]);
    let changed = smatrix::changed_profiles(&[(0, more.clone())], &[(0, third.clone())], &terms)
        .expect("an absorption change is written in place");
    assert_eq!(changed, [0]);
    let mut delta = Some(fused.delta.clone());
    let (s_in_place, reports) = smatrix::rewrite_with_terms(
        &b,
        s_both,
        &mut delta,
        &[(0, third.clone())],
        &changed,
        &params,
        &terms,
        &mut Default::default(),
    )
    .unwrap();
    let (s_fresh, fresh_reports, tilts) =
        smatrix::rebuild_with_terms_and_tilt(&b, &[(0, third.clone())], &params, &terms).unwrap();
    assert_eq!(s_in_place.csr(), s_fresh.csr());
    assert_eq!(
        reports[0].max_column_energy,
        fresh_reports[0].max_column_energy
    );
    let TiltOf::Some(fresh) = collimated::tilt_of_with(&b, &[&third], tilts) else {
        panic!("the walks carry collimated weights");
    };
    assert_eq!(delta.as_ref().unwrap().csr(), fresh.delta.csr());
    assert_ne!(fresh.delta.csr().val, fused.delta.csr().val);
    // An S whose rows are not the walks' sources is not written into: it must be built
    // again (here one entry of the cube's first row is missing).
    let view = s_fresh.view();
    let mut rows: Vec<Vec<(u32, [f32; 3])>> = (0..view.n_rows())
        .map(|j| {
            let (c, v) = view.row(j);
            c.iter().copied().zip(v.iter().copied()).collect()
        })
        .collect();
    rows[0].pop();
    let short = translux_proto::csr::ValidCsr::new(
        translux_proto::csr::Csr::from_rows(view.n_cols(), &rows).unwrap(),
    )
    .unwrap();
    let err = smatrix::rewrite_with_terms(
        &b,
        short,
        &mut None,
        &[(0, more.clone())],
        &changed,
        &params,
        &terms,
        &mut Default::default(),
    )
    .unwrap_err();
    assert!(
        matches!(err, smatrix::SError::Pattern { row: 0, .. }),
        "{err}"
    );

    // Through a scene: the first change builds S, the next is written in place, and the
    // tilt a relight reads then is the one made afresh.
    let scene = translux_engine::scene::Scene::open("cube", &dir.path().join("bundle")).unwrap();
    let (m, rebuilt) = scene.materials_for(&[(0, more.clone())]).unwrap().unwrap();
    assert!(rebuilt && !m.in_place);
    drop(m);
    let over = [(0, third.clone())];
    let (m, rebuilt) = scene.materials_for(&over).unwrap().unwrap();
    assert!(
        rebuilt && m.in_place,
        "the absorption change is written in place"
    );
    assert_eq!(
        translux_engine::smatrix::scaled_s(scene.cpu_s(&m).unwrap())
            .unwrap()
            .csr(),
        s_fresh.csr()
    );
    let key = serde_json::to_string(&over[..]).unwrap();
    match scene.tilt_for(&key, &[&third]).as_ref() {
        TiltOf::Some(kept) => assert_eq!(kept.delta.csr(), fresh.delta.csr()),
        _ => panic!("the scene keeps the rewritten tilt"),
    }

    // What the walks cannot serve is refused, naming the object and what changed.
    let err =
        smatrix::rebuild_from_bundle(&b, &[(0, with_sigma_a(&b, [1e-5, 0.008, 0.02]))], &params)
            .unwrap_err()
            .to_string();
    assert!(err.contains("'cube'") && err.contains("below"), "{err}");
    let mut other = b.manifest().objects[0].material.clone();
    if let Material::Simulated { sigma_s_prime, .. } = &mut other {
        *sigma_s_prime = Some([1.0, 1.0, 1.0]);
    }
    let err = smatrix::rebuild_from_bundle(&b, &[(0, other)], &params)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("scattering") && err.contains("translux-precompute"),
        "{err}"
    );
    let dipole: Material = translux_proto::parse_json(
        r#"{"type": "translucent", "profile": {"type": "dipole", "preset": "marble"}}"#,
    )
    .unwrap();
    let err = smatrix::rebuild_from_bundle(&b, &[(0, dipole)], &params)
        .unwrap_err()
        .to_string();
    assert!(err.contains("precomputed as simulated"), "{err}");
}

#[test]
fn the_same_seed_gives_the_same_s_and_another_seed_a_different_one() {
    let a = tempfile::tempdir().unwrap();
    let b = tempfile::tempdir().unwrap();
    let c = tempfile::tempdir().unwrap();
    let ba = build(a.path(), &cube_scene(MEDIUM), 200).unwrap();
    let bb = build(b.path(), &cube_scene(MEDIUM), 200).unwrap();
    let seeded = MEDIUM.replace("\"eta\": 1.0", "\"eta\": 1.0, \"seed\": 5");
    let bc = build(c.path(), &cube_scene(&seeded), 200).unwrap();
    assert_eq!(ba.subsurface().val(), bb.subsurface().val());
    assert_ne!(ba.subsurface().val(), bc.subsurface().val());
}

#[test]
fn meshes_walks_cannot_run_in_are_refused() {
    // An open mesh: a single quad.
    let dir = tempfile::tempdir().unwrap();
    let quad = cube_scene(MEDIUM).replace(
        r#"{"shape": "box", "size": [20, 20, 20]}"#,
        r#"{"shape": "quad", "size": [20, 20]}"#,
    );
    let err = build(dir.path(), &quad, 100).unwrap_err();
    assert!(
        err.contains("'cube'") && err.contains("not closed"),
        "{err}"
    );

    // The scanned bunny is open at the bottom.
    let bunny = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/stanford-bunny.obj");
    let scene = cube_scene(MEDIUM).replace(
        r#"{"shape": "box", "size": [20, 20, 20]}"#,
        &format!("{:?}", bunny.display().to_string()),
    );
    let scene = scene.replace(r#""unit_mm": 1,"#, r#""unit_mm": 1000,"#);
    let err = build(dir.path(), &scene, 300).unwrap_err();
    assert!(
        err.contains("not closed") && err.contains("bunny is open"),
        "{err}"
    );

    // A closed box OBJ wound inward, kept as the file winds it.
    let obj = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1\n\
               f 1 2 3\nf 1 3 4\nf 5 8 7\nf 5 7 6\nf 1 5 6\nf 1 6 2\nf 2 6 7\nf 2 7 3\n\
               f 3 7 8\nf 3 8 4\nf 4 8 5\nf 4 5 1\n";
    write(dir.path(), "inward.obj", obj);
    let scene = cube_scene(MEDIUM)
        .replace(
            r#"{"shape": "box", "size": [20, 20, 20]}"#,
            r#""inward.obj""#,
        )
        .replace(
            r#""material""#,
            r#""orientation": "as_is", "transform": {"scale": 20}, "material""#,
        );
    let err = build(dir.path(), &scene, 100).unwrap_err();
    assert!(err.contains("wound inward"), "{err}");
}

#[test]
fn absurd_walk_settings_are_refused_naming_the_field() {
    for (field, value, needle) in [
        ("max_walks", "0", "max_walks"),
        ("max_walks", "1000000000", "max_walks"),
        ("noise", "0", "noise"),
        ("g", "0.5", "g"),
    ] {
        let material = MEDIUM.replace(
            "\"eta\": 1.0",
            &format!("\"eta\": 1.0, \"{field}\": {value}"),
        );
        let text = cube_scene(&material);
        let file: SceneFile = translux_proto::parse_json(&text).unwrap();
        let err = file.validate().unwrap_err().to_string();
        assert!(err.contains(needle), "{field} = {value}: {err}");
    }
    let text = cube_scene(r#"{"type": "simulated", "preset": "marble", "sigma_s": [1, 1, 1]}"#);
    let file: SceneFile = translux_proto::parse_json(&text).unwrap();
    assert!(file.validate().unwrap_err().to_string().contains("preset"));
    let text = cube_scene(r#"{"type": "simulated", "sigma_s_prime": [1, 1, 1]}"#);
    let file: SceneFile = translux_proto::parse_json(&text).unwrap();
    assert!(file.validate().unwrap_err().to_string().contains("sigma_a"));
}

#[test]
fn a_new_scattering_medium_walks_again_in_the_bundle_and_equals_a_fresh_precompute() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a");
    let b = dir.path().join("b");
    std::fs::create_dir_all(&a).unwrap();
    std::fs::create_dir_all(&b).unwrap();
    let old = build(&a, &cube_scene(MEDIUM), 300).unwrap();
    let new_medium = MEDIUM.replace("[0.5, 0.45, 0.35]", "[1.0, 0.9, 0.7]");
    let fresh = build(&b, &cube_scene(&new_medium), 300).unwrap();
    let new: Material = translux_proto::parse_json(&new_medium).unwrap();
    drop(old);

    // Walked again from the bundle alone: the same S, walks and material as a precompute of
    // the scene with the new medium (the walks are seeded per patch).
    let done = std::sync::atomic::AtomicU64::new(0);
    let report = translux_precompute::resimulate::resimulate(
        &a.join("bundle"),
        &[("cube".to_string(), new.clone())],
        &|d, total| {
            assert!(d <= total);
            done.store(d, std::sync::atomic::Ordering::Relaxed);
        },
        (&Stop::never(), None),
    )
    .unwrap();
    assert_eq!(done.into_inner(), report.patches);
    let re = Bundle::open(&a.join("bundle")).unwrap();
    assert_eq!(re.manifest().objects[0].material, new);
    assert_eq!(
        re.manifest().subsurface.objects[0].simulation,
        fresh.manifest().subsurface.objects[0].simulation
    );
    let (s1, s2) = (re.subsurface(), fresh.subsurface());
    assert_eq!(s1.col(), s2.col());
    assert_eq!(s1.val(), s2.val());
    let (w1, w2) = (re.walks().unwrap(), fresh.walks().unwrap());
    assert_eq!((w1.col, w1.bin, w1.weight), (w2.col, w2.bin, w2.weight));
    assert_eq!(w1.normal, w2.normal);
    // More scattering: the cube re-emits more than before.
    assert!(total(&re, s1)[0] > 0.0);

    // What cannot walk again is refused, naming it; the bundle is left as it was.
    let refuse = |name: &str, m: &str| {
        let m: Material = translux_proto::parse_json(m).unwrap();
        translux_precompute::resimulate::resimulate(
            &a.join("bundle"),
            &[(name.to_string(), m)],
            &|_, _| {},
            (&Stop::never(), None),
        )
        .unwrap_err()
    };
    let e = refuse("nope", &new_medium);
    assert!(
        e.contains("no object \"nope\"") && e.contains("cube"),
        "{e}"
    );
    let e = refuse("cube", r#"{"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}"#);
    assert!(
        e.contains("materials.cube") && e.contains("simulated"),
        "{e}"
    );
    let e = refuse(
        "cube",
        r#"{"type": "simulated", "sigma_s_prime": [1, 1, 1], "sigma_a": [-1, 0, 0]}"#,
    );
    assert!(e.contains("materials.cube.sigma_a"), "{e}");

    // Walks stopped by their flag or their time limit: the reasons told apart, nothing
    // written.
    let stopped = |stop: &Stop, limit: Option<Duration>| {
        translux_precompute::resimulate::resimulate(
            &a.join("bundle"),
            &[("cube".to_string(), new.clone())],
            &|_, _| {},
            (stop, limit),
        )
        .unwrap_err()
    };
    let flag = StopFlag::new();
    flag.set();
    let e = stopped(&Stop::never().with(&flag), None);
    assert_eq!(e, translux_precompute::resimulate::CANCELLED);
    let e = stopped(&Stop::never(), Some(Duration::ZERO));
    assert!(
        e.contains("limit of 0.0 s")
            && e.contains(&format!("of {} patches walked", report.patches)),
        "{e}"
    );
    let again = Bundle::open(&a.join("bundle")).unwrap();
    assert_eq!(again.subsurface().val(), fresh.subsurface().val());
}

/// A simulated cube floating over a glowing floor (an emitter, no lamp) beside a white
/// wall (light bounces between them): the floor's light reaches it from below, not evenly over each face's
/// hemisphere. Relights add the direction that
/// light arrives from (Δ E_t + G_u E_u + G_v E_v of F B, engine
/// `collimated::interreflected_moments`) as one correction solved through the transport:
/// on the transfer matrix's path and on the iterative one alike (a path without it would
/// differ by the correction, asserted to be several per cent of the cube's faces here).
#[test]
fn a_floors_light_enters_a_simulated_cube_from_below_on_every_solver_path() {
    use translux_engine::radiosity::{self, BundleLighting, SolveParams, SparseScatter};
    use translux_engine::relight;
    use translux_engine::scene::Scene;
    use translux_engine::transport::Transport;
    let dir = tempfile::tempdir().unwrap();
    let scene = format!(
        r#"{{"unit_mm": 1, "objects": [
            {{"name": "floor", "mesh": {{"shape": "quad", "size": [200, 200]}},
              "material": {{"type": "emitter", "radiance": [1, 1, 1]}}}},
            {{"name": "wall", "mesh": {{"shape": "quad", "size": [80, 80]}},
              "transform": {{"translate": [-40, 40, 0], "rotate_deg": [0, 0, -90]}},
              "material": {{"type": "diffuse", "albedo": [0.8, 0.8, 0.8]}}}},
            {{"name": "cube", "mesh": {{"shape": "box", "size": [20, 20, 20]}},
              "transform": {{"translate": [0, 15, 0]}}, "material": {MEDIUM}}}],
           "lights": []}}"#
    );
    let path = write(dir.path(), "scene.json", &scene);
    let loaded = load_scene_file(&path).unwrap();
    let out = dir.path().join("bundle");
    let params = PrecomputeParams {
        patches: Some(1200),
        inverse: true,
        ..Default::default()
    };
    precompute(&loaded, &out, &params).unwrap();
    let b = Bundle::open(&out).unwrap();
    assert!(b.transfer().is_some());
    let cube = &b.manifest().objects[2];
    let cube = cube.first_patch as usize..(cube.first_patch + cube.patch_count) as usize;

    // The patch solution without the direction of F B, and the correction it brings.
    let lit = BundleLighting::new(&b);
    let lights = b.manifest().lights.clone();
    let e = lit.irradiance(&lights).unwrap();
    assert!(collimated::first_scatter(&b, lit.geometry(), &lit.occluder, &lights).is_none());
    let y = b.patch_emission().to_vec();
    let solve = SolveParams {
        tolerance: 1e-6,
        ..Default::default()
    };
    let (f, s) = (Transport::of(&b), SparseScatter(b.subsurface()));
    let (x, _) = radiosity::solve(&f, &s, &y, &e, &solve, None).unwrap();
    let yf = collimated::interreflected_first_scatter(&b, lit.geometry(), &x).unwrap();
    let none = vec![[0.0f32; 3]; yf.len()];
    let (c, _) = radiosity::solve(&f, &s, &yf, &none, &solve, None).unwrap();
    let normals = b.patch_normals();
    let mut worst = 0.0f64;
    for (name, axis, sign) in [("bottom", 1, -1.0), ("top", 1, 1.0), ("side", 0, 1.0)] {
        let (mut sx, mut sc) = (0.0f64, 0.0f64);
        for i in cube.clone().filter(|&i| normals[i][axis] * sign > 0.9) {
            let a = f64::from(b.patch_areas()[i]);
            sx += a * f64::from(x[i][0]);
            sc += a * f64::from(c[i][0]);
        }
        eprintln!(
            "{name}: the correction is {:+.2}% of the face's total",
            100.0 * sc / sx
        );
        worst = worst.max((sc / sx).abs());
    }
    assert!(worst > 0.03, "the floor's light hardly slants: {worst}");

    // Both relight paths carry it: T (c = y + T F y) and the iterative solve.
    let scene = Scene::open("cube", &out).unwrap();
    let relit = |solver: &str| {
        let body = serde_json::json!({ "solver": solver }).to_string();
        let plan = relight::plan(&scene, translux_proto::parse_json(&body).unwrap()).unwrap();
        relight::run(&scene, &plan).unwrap()
    };
    let (t, it) = (relit("inverse"), relit("iterative"));
    assert_eq!(t.stats.solver, "inverse");
    // The same request again starts both solves from their kept answers and products.
    let again = relit("iterative");
    assert_eq!(again.stats.products, 0, "{:?}", again.stats);
    assert_eq!(again.radiance, it.radiance);
    // Each face of the cube (the floor is at y = 0, the wall at x = −40): the mean of its
    // vertices on both paths. The iterative solves stop at a 0.5% residual (the answer's
    // and the correction's), single vertices 3% apart at most here; a face's mean much
    // closer than the correction.
    let pos = b.vertex_positions();
    let on_cube = |p: &[f32; 3]| p[1] > 1.0 && p[0].abs() < 15.0 && p[2].abs() < 15.0;
    let (lo, hi) = pos
        .iter()
        .filter(|p| on_cube(p))
        .fold((f32::MAX, f32::MIN), |(lo, hi), p| {
            (lo.min(p[1]), hi.max(p[1]))
        });
    for (name, face) in [("top", hi), ("bottom", lo)] {
        let (mut a, mut b, mut count) = (0.0f64, 0.0f64, 0);
        for ((u, v), p) in t.radiance.iter().zip(&it.radiance).zip(pos) {
            if on_cube(p) && (p[1] - face).abs() < 1e-3 {
                a += f64::from(u[0]);
                b += f64::from(v[0]);
                count += 1;
            }
        }
        assert!(count >= 9, "{name}: {count} vertices");
        let rel = (a / b - 1.0).abs();
        eprintln!(
            "{name}: inverse against iterative {:.2}% over {count} vertices",
            100.0 * rel
        );
        assert!(
            rel < worst / 2.0,
            "{name}: {rel} against a correction of {worst}"
        );
    }
}

/// A sun in an environment map is a lamp: it enters a simulated object collimated and
/// slanted, and its beam crossing a corner unscattered is left out, like a directional
/// light shining from it. A lone cube under a map that is dark but for one direction bin
/// and under a directional lamp along that bin's centre: every face's share of the light
/// leaving the cube the same within 1%.
#[test]
fn a_sun_in_an_environment_map_enters_a_simulated_cube_like_a_directional_lamp() {
    use translux_engine::envmap::Bins;
    use translux_engine::relight;
    use translux_engine::scene::Scene;
    let dir = tempfile::tempdir().unwrap();
    let scene = format!(
        r#"{{"unit_mm": 1, "objects": [
            {{"name": "cube", "mesh": {{"shape": "box", "size": [20, 20, 20]}},
              "material": {MEDIUM}}}],
           "lights": []}}"#
    );
    let path = write(dir.path(), "scene.json", &scene);
    let loaded = load_scene_file(&path).unwrap();
    let out = dir.path().join("bundle");
    let params = PrecomputeParams {
        patches: Some(600),
        ..Default::default()
    };
    precompute(&loaded, &out, &params).unwrap();
    let b = Bundle::open(&out).unwrap();
    let vis = b.environment_visibility().expect("visibility");
    let bins = Bins {
        rows: vis.rows,
        cols: vis.cols,
    };
    // The sun: the bin holding a direction 60° from +y, toward −x and a little −z.
    let toward = glam::Vec3::new(-0.85, 0.5, -0.17).normalize();
    let k = bins.bin_of(toward);
    let sun = bins.direction(k, 0.5, 0.5);
    // An equirectangular map, radiance 1 on the texels whose centre lies in bin k.
    let (w, h) = (512usize, 256usize);
    let px: Vec<image::Rgb<f32>> = (0..w * h)
        .map(|i| {
            let (u, v) = (
                ((i % w) as f32 + 0.5) / w as f32,
                ((i / w) as f32 + 0.5) / h as f32,
            );
            let d = translux_engine::envmap::uv_to_direction(u, v);
            image::Rgb([if bins.bin_of(d) == k { 1.0 } else { 0.0 }; 3])
        })
        .collect();
    let file = std::fs::File::create(dir.path().join("sun.hdr")).unwrap();
    image::codecs::hdr::HdrEncoder::new(std::io::BufWriter::new(file))
        .encode(&px, w, h)
        .unwrap();

    let scene = Scene::open("cube", &out).unwrap();
    let relit = |lights: serde_json::Value| {
        let body = serde_json::json!({ "lights": lights, "solver": "iterative" }).to_string();
        let plan = relight::plan(&scene, translux_proto::parse_json(&body).unwrap()).unwrap();
        relight::run(&scene, &plan).unwrap().radiance
    };
    let map = relit(serde_json::json!([{"type": "environment", "map": "sun.hdr"}]));
    let lamp = relit(serde_json::json!([{"type": "directional",
        "direction": (-sun).to_array(), "irradiance": [1.0, 1.0, 1.0]}]));
    // Each face's share of the cube's vertices' total (red), map against lamp.
    let pos = b.vertex_positions();
    let share = |r: &[[f32; 3]], axis: usize, sign: f32| {
        let total: f64 = r.iter().map(|v| f64::from(v[0])).sum();
        let face: f64 = r
            .iter()
            .zip(pos)
            .filter(|(_, p)| (p[axis] * sign - 10.0).abs() < 1e-3)
            .map(|(v, _)| f64::from(v[0]))
            .sum();
        face / total
    };
    let mut worst = 0.0f64;
    for (name, axis, sign) in [
        ("+x", 0, 1.0),
        ("-x", 0, -1.0),
        ("+y", 1, 1.0),
        ("-y", 1, -1.0),
        ("+z", 2, 1.0),
        ("-z", 2, -1.0),
    ] {
        let (m, l) = (share(&map, axis, sign), share(&lamp, axis, sign));
        eprintln!(
            "{name}: map {m:.4}, lamp {l:.4}, {:+.1}%",
            100.0 * (m / l - 1.0)
        );
        worst = worst.max((m / l - 1.0).abs());
    }
    assert!(worst < 0.01, "a face's share differs by {worst}");
}

/// `scene`'s materials for `over`, asserted equal to a build afresh (S, and the simulated
/// objects' tilt kept for them) and written in place from the second `step` on.
fn changed_like_fresh(
    scene: &translux_engine::scene::Scene,
    b: &Bundle,
    over: &[(usize, Material)],
    terms: &translux_engine::sterms::STerms,
    step: usize,
) -> std::sync::Arc<smatrix::OverrideMaterials> {
    let params = SParams::default();
    let (m, rebuilt) = scene.materials_for(over).unwrap().unwrap();
    assert!(rebuilt);
    assert_eq!(m.in_place, step > 0, "step {step}");
    let (fresh, _, tilts) = smatrix::rebuild_with_terms_and_tilt(b, over, &params, terms).unwrap();
    assert_eq!(
        translux_engine::smatrix::scaled_s(scene.cpu_s(&m).unwrap())
            .unwrap()
            .csr(),
        fresh.csr(),
        "step {step}"
    );
    let materials = smatrix::materials_with(b, over);
    let TiltOf::Some(want) = collimated::tilt_of_with(b, &materials, tilts) else {
        panic!("the walks carry collimated weights");
    };
    let key = serde_json::to_string(over).unwrap();
    match scene.tilt_for(&key, &materials).as_ref() {
        TiltOf::Some(kept) => assert_eq!(kept.delta.csr(), want.delta.csr(), "step {step}"),
        _ => panic!("step {step}: the scene keeps the tilt"),
    }
    m
}

/// Two simulated cubes on a diffuse floor, in metres: an absorption change to one, then to
/// both, is written into the scene's last S and tilt in place, and each equals a build
/// afresh for those materials (the cube left alone keeps its values).
#[test]
fn absorption_changes_to_one_simulated_object_of_two_are_written_in_place() {
    let dir = tempfile::tempdir().unwrap();
    let scene = format!(
        r#"{{"unit_mm": 1000, "objects": [
            {{"name": "floor", "mesh": {{"shape": "quad", "size": [0.2, 0.2]}},
              "material": {{"type": "diffuse", "albedo": [0.6, 0.6, 0.6]}}}},
            {{"name": "a", "mesh": {{"shape": "box", "size": [0.02, 0.02, 0.02]}},
              "transform": {{"translate": [-0.03, 0.0101, 0]}}, "material": {MEDIUM}}},
            {{"name": "b", "mesh": {{"shape": "box", "size": [0.02, 0.02, 0.02]}},
              "transform": {{"translate": [0.03, 0.0101, 0]}}, "material": {MEDIUM}}}],
           "lights": [{{"type": "point", "position": [0, 0.2, 0.05], "intensity": [1, 1, 1]}}]}}"#
    );
    let b = build(dir.path(), &scene, 900).unwrap();
    let sim = |k: usize, sigma_a: [f32; 3]| {
        let mut m = b.manifest().objects[k].material.clone();
        let Material::Simulated { sigma_a: s, .. } = &mut m else {
            panic!("object {k} is simulated");
        };
        *s = Some(sigma_a);
        m
    };
    let params = SParams::default();
    let terms = smatrix::terms_of_bundle(&b, &params.quadrature);
    let scene = translux_engine::scene::Scene::open("two", &dir.path().join("bundle")).unwrap();
    let steps = [
        vec![
            (1, sim(1, [0.01, 0.01, 0.03])),
            (2, sim(2, [0.01, 0.01, 0.03])),
        ],
        // One cube changes.
        vec![
            (1, sim(1, [0.05, 0.01, 0.03])),
            (2, sim(2, [0.01, 0.01, 0.03])),
        ],
        // Both change.
        vec![
            (1, sim(1, [0.02, 0.2, 0.03])),
            (2, sim(2, [0.005, 0.01, 0.1])),
        ],
    ];
    let mut last: Option<Vec<[f32; 3]>> = None;
    for (step, over) in steps.iter().enumerate() {
        let m = changed_like_fresh(&scene, &b, over, &terms, step);
        let s = translux_engine::smatrix::scaled_s(scene.cpu_s(&m).unwrap()).unwrap();
        // The cube left alone at step 1 (b) keeps its rows; the changed one (a) does not.
        let o = &b.manifest().objects;
        let rows = |k: usize| {
            let r = o[k].first_patch as usize..(o[k].first_patch + o[k].patch_count) as usize;
            let p = &s.csr().row_ptr;
            s.csr().val[p[r.start] as usize..p[r.end] as usize].to_vec()
        };
        if let (1, Some(before)) = (step, &last) {
            let (ra, rb) = (rows(1), rows(2));
            let p = &s.csr().row_ptr;
            let start_a = p[o[1].first_patch as usize] as usize;
            let start_b = p[o[2].first_patch as usize] as usize;
            assert_ne!(ra[..], before[start_a..start_a + ra.len()]);
            assert_eq!(rb[..], before[start_b..start_b + rb.len()]);
        }
        last = Some(s.csr().val.clone());
    }
}

/// A room modelled the way a user exports one, in millimetres: the floor and two walls as
/// separate OBJ files (comments, object names, texture coordinates and normals, one wall
/// with negative indices), and a 20 mm cube exported as quads with its own normals. The
/// cube is simulated; an absorption change is written into the scene's last S and tilt in
/// place and equals a build afresh, and a relight through the scene is finite and lights
/// the cube.
#[test]
fn a_room_of_obj_walls_in_millimetres_takes_an_absorption_change_in_place() {
    let dir = tempfile::tempdir().unwrap();
    let wall = |name: &str, corners: [[f32; 3]; 4], negative: bool| {
        let mut s = format!("# exported wall\no {name}\n");
        for c in corners {
            s += &format!("v {:.6} {:.6} {:.6}\n", c[0], c[1], c[2]);
        }
        s += "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n";
        // The face's normal from its first corner's edges.
        let [a, b, c] = [0, 1, 2].map(|k| glam::Vec3::from(corners[k]));
        let n = (b - a).cross(c - a).normalize();
        s += &format!("vn {} {} {}\ns off\n", n.x, n.y, n.z);
        s += if negative {
            "f -4/-4/-1 -3/-3/-1 -2/-2/-1 -1/-1/-1\n"
        } else {
            "f 1/1/1 2/2/1 3/3/1 4/4/1\n"
        };
        write(dir.path(), &format!("{name}.obj"), &s);
    };
    wall(
        "floor",
        [
            [-100.0, 0.0, -100.0],
            [-100.0, 0.0, 100.0],
            [100.0, 0.0, 100.0],
            [100.0, 0.0, -100.0],
        ],
        false,
    );
    wall(
        "back",
        [
            [-100.0, 0.0, -100.0],
            [100.0, 0.0, -100.0],
            [100.0, 200.0, -100.0],
            [-100.0, 200.0, -100.0],
        ],
        true,
    );
    wall(
        "left",
        [
            [-100.0, 0.0, -100.0],
            [-100.0, 200.0, -100.0],
            [-100.0, 200.0, 100.0],
            [-100.0, 0.0, 100.0],
        ],
        false,
    );
    // A cube as a modelling tool writes one: eight corners, six outward quads, a normal
    // per face.
    let mut cube = String::from("# cube, 20 mm\no Cube\n");
    for z in [-10, 10] {
        for (x, y) in [(-10, -10), (10, -10), (10, 10), (-10, 10)] {
            cube += &format!("v {x}.000000 {y}.000000 {z}.000000\n");
        }
    }
    cube += "vn 0 0 -1\nvn 0 0 1\nvn 0 -1 0\nvn 0 1 0\nvn -1 0 0\nvn 1 0 0\ns off\n";
    for (n, f) in [
        [1, 4, 3, 2],
        [5, 6, 7, 8],
        [1, 2, 6, 5],
        [4, 8, 7, 3],
        [1, 5, 8, 4],
        [2, 3, 7, 6],
    ]
    .iter()
    .enumerate()
    {
        cube += &format!(
            "f {}//{k} {}//{k} {}//{k} {}//{k}\n",
            f[0],
            f[1],
            f[2],
            f[3],
            k = n + 1
        );
    }
    write(dir.path(), "cube.obj", &cube);
    let grey = r#"{"type": "diffuse", "albedo": [0.6, 0.6, 0.6]}"#;
    let scene = format!(
        r#"{{"unit_mm": 1, "objects": [
            {{"name": "floor", "mesh": "floor.obj", "material": {grey}}},
            {{"name": "back", "mesh": "back.obj", "material": {grey}}},
            {{"name": "left", "mesh": "left.obj", "material": {grey}}},
            {{"name": "cube", "mesh": "cube.obj", "transform": {{"translate": [0, 10.1, 0]}},
              "material": {MEDIUM}}}],
           "lights": [{{"type": "point", "position": [30, 150, 60], "intensity": [1, 1, 1]}}]}}"#
    );
    let b = build(dir.path(), &scene, 900).unwrap();
    let o = &b.manifest().objects;
    assert_eq!(o[3].name, "cube");
    assert!(matches!(o[3].material, Material::Simulated { .. }));
    let sim = |sigma_a: [f32; 3]| {
        let mut m = o[3].material.clone();
        let Material::Simulated { sigma_a: s, .. } = &mut m else {
            unreachable!()
        };
        *s = Some(sigma_a);
        vec![(3, m)]
    };
    let params = SParams::default();
    let terms = smatrix::terms_of_bundle(&b, &params.quadrature);
    let scene = translux_engine::scene::Scene::open("room", &dir.path().join("bundle")).unwrap();
    let cube = o[3].first_patch as usize..(o[3].first_patch + o[3].patch_count) as usize;
    let mut lit = Vec::new();
    for (step, sigma_a) in [
        [0.004, 0.008, 0.02],
        [0.04, 0.008, 0.002],
        [0.001, 0.1, 0.02],
    ]
    .into_iter()
    .enumerate()
    {
        let over = sim(sigma_a);
        changed_like_fresh(&scene, &b, &over, &terms, step);
        // A relight under these materials: finite, and the cube glows.
        let req: translux_proto::api::RelightRequest = serde_json::from_value(serde_json::json!({
            "solver": "iterative",
            "materials": {"cube": serde_json::to_value(&over[0].1).unwrap()}
        }))
        .unwrap();
        let plan = translux_engine::relight::plan(&scene, req).unwrap();
        let out = translux_engine::relight::run(&scene, &plan).unwrap();
        assert!(
            out.radiance.iter().flatten().all(|v| v.is_finite()),
            "step {step}"
        );
        // The cube's vertices (viewer triangle k is patch k).
        let mut vertices: Vec<u32> = b.triangle_vertices()[cube.clone()]
            .iter()
            .flatten()
            .copied()
            .collect();
        vertices.sort_unstable();
        vertices.dedup();
        let b_cube: Vec<[f32; 3]> = vertices.iter().map(|&v| out.radiance[v as usize]).collect();
        let mean: [f64; 3] = std::array::from_fn(|c| {
            b_cube.iter().map(|v| f64::from(v[c])).sum::<f64>() / b_cube.len() as f64
        });
        assert!(mean.iter().all(|v| *v > 0.0), "step {step}: {mean:?}");
        lit.push(mean);
    }
    // More absorption in a channel leaves the cube darker in it: red at step 1 (σa ×10),
    // green at step 2 (×12.5).
    assert!(lit[1][0] < lit[0][0], "{lit:?}");
    assert!(lit[2][1] < lit[0][1], "{lit:?}");
}
