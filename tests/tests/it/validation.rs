//! Validation against an independent path tracer: Mitsuba 3 (`llvm_ad_rgb`), driven by
//! `tests/validation/mitsuba_reference.py`, which shares no code with translux.
//!
//! Each test builds a scene, precomputes it, relights it through the server's own relight
//! path (the one the REST route runs) and compares the per-vertex radiance B/π with the
//! radiance Mitsuba measures at the same points. They print a table of the errors
//! (`cargo test -p translux-tests --test it validation:: -- --nocapture`).
//!
//! Mitsuba's answers come from the repository's store (`tests/validation/references/`,
//! [`mitsuba::stored`]) when it holds the answer to exactly this input; otherwise Mitsuba
//! renders it and the new file is to be committed. Rendering needs Mitsuba
//! (`pip install mitsuba`, Debian's `libllvm19`; `.ci/run` installs both); without it such a
//! test fails and says what to install, unless `TRANSLUX_SKIP_MITSUBA=1` (CI never sets
//! it). `TRANSLUX_MITSUBA_RENDER=1` renders every answer again.

use std::path::Path;
use std::sync::{Arc, Mutex, Weak};
use translux_engine::transport::Transport;

use serde_json::json;
use translux_engine::radiosity::Rgb;
use translux_engine::relight;
use translux_precompute::builtin::builtin_scene;
use translux_precompute::hierarchy::HierarchyParams;
use translux_precompute::pipeline::{FormFactorMethod, PrecomputeParams, precompute};
use translux_precompute::scene::{LoadedScene, load_scene_file, resolve_scene};
use translux_proto::bundle::Bundle;
use translux_proto::scene::{Material, SceneFile};
use translux_server::state::Scene;
use translux_tests::compare;
use translux_tests::mitsuba::{self, Errors, errors, every, slice, vertex_queries};
use translux_tests::rooms::{self, RoomSpec, Walls};

/// Precomputes `file` into `dir/name` at about `patches` patches and opens it as the
/// server does.
fn build(file: SceneFile, dir: &Path, name: &str, patches: u64) -> Scene {
    let loaded = resolve_scene(file, Path::new("."), name.to_owned(), name.to_owned()).unwrap();
    let out = dir.join(name);
    let params = PrecomputeParams {
        patches: Some(patches),
        ..Default::default()
    };
    precompute(&loaded, &out, &params).unwrap();
    Scene::open(name, &out).unwrap()
}

/// Patch radiance B/π from the library's solve (the same code the relight runs), to a
/// tight tolerance, with the patch centroids and normals to query.
type PatchSolution = (Vec<Rgb>, Vec<[f32; 3]>, Vec<[f32; 3]>);

fn patch_radiance(b: &Bundle, lights: &[translux_proto::light::Light]) -> PatchSolution {
    patch_radiance_with(b, lights, None)
}

/// [`patch_radiance`], the lamps' first scattering in simulated objects walked along their
/// own beams (`lamp_walks` walks per lamp, as a relight's `"lamp_walks"`) where given.
fn patch_radiance_with(
    b: &Bundle,
    lights: &[translux_proto::light::Light],
    lamp_walks: Option<u32>,
) -> PatchSolution {
    use translux_engine::radiosity::{self, BundleLighting, SolveParams, SparseScatter};
    let lit = BundleLighting::new(b);
    let e = lit.irradiance(lights).unwrap();
    let params = SolveParams {
        tolerance: 1e-6,
        ..Default::default()
    };
    let s = SparseScatter(b.subsurface());
    // Lamps entering simulated objects collimated (what relights add to S E).
    let y = match lamp_walks {
        Some(per) => {
            translux_engine::lampwalk::first_scatter(b, lit.geometry(), &lit.occluder, lights, per)
        }
        None => {
            translux_engine::collimated::first_scatter(b, lit.geometry(), &lit.occluder, lights)
        }
    };
    let emission: Vec<_> = match y {
        Some(y) => b
            .patch_emission()
            .iter()
            .zip(&y)
            .map(|(e, y)| std::array::from_fn(|c| e[c] + y[c]))
            .collect(),
        None => b.patch_emission().to_vec(),
    };
    let f = Transport::of(b);
    let (mut x, stats) = radiosity::solve(&f, &s, &emission, &e, &params, None).unwrap();
    assert!(stats.converged, "{stats:?}");
    // Light from other surfaces entering simulated objects from where it comes (what
    // relights add): one correction through the same transport.
    if let Some(y) =
        translux_engine::collimated::interreflected_first_scatter(b, lit.geometry(), &x)
    {
        let none = vec![[0.0f32; 3]; y.len()];
        let (c, stats) = radiosity::solve(&f, &s, &y, &none, &params, None).unwrap();
        assert!(stats.converged, "{stats:?}");
        for (x, c) in x.iter_mut().zip(&c) {
            for k in 0..3 {
                x[k] += c[k];
            }
        }
    }
    let inv_pi = std::f32::consts::FRAC_1_PI;
    (
        x.iter().map(|c| c.map(|v| v * inv_pi)).collect(),
        lit.centroid.iter().map(|c| c.to_array()).collect(),
        lit.normal.iter().map(|n| n.to_array()).collect(),
    )
}

fn table_row(what: &str, points: usize, e: &Errors) -> String {
    format!(
        "| {what} | {points} ({} counted) | {:.2}% | {:.2}% | {:.4} | {:.2}% |",
        e.counted,
        100.0 * e.median,
        100.0 * e.p90,
        e.total_ratio,
        100.0 * e.reference_noise
    )
}

/// The paper's Cornell box with every object diffuse (the tall block white), lit by a
/// point light: a closed diffuse room, so B is all of classical radiosity's
/// inter-reflection, which Mitsuba's path tracer computes without patches. Compared at
/// patch centroids (the radiosity solution) and at viewer vertices (what users see: B/π
/// interpolated from the patches around each vertex, through the server's relight).
#[test]
fn a_closed_diffuse_room_matches_mitsuba_per_vertex() {
    let mut file = builtin_scene("cornell").unwrap();
    for o in &mut file.objects {
        if let Material::Translucent { .. } = o.material {
            o.material = Material::Diffuse {
                albedo: [0.75, 0.75, 0.75],
                specular: None,
            };
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let scene = build(file, dir.path(), "diffuse_cornell", 4000);
    // The light at mid-height: the box's default light sits 5.5 cm under the ceiling, and
    // the hot spot it makes there lights the room through a small bright area that a path
    // tracer's BSDF-sampled bounces rarely find (the reference would need far more samples).
    let lights =
        json!([{"type": "point", "position": [0.0, 0.3, 0.05], "intensity": [0.8, 0.8, 0.8]}]);
    closed_room_against_mitsuba(&scene, &lights, "diffuse Cornell box", 400);
}

/// A room modelled the way users model one: six OBJ files of one quad each, facing into
/// the room, with the scene's origin outside the room, and a box (one closed OBJ) on the
/// floor. Nothing may be turned over, and the light must match Mitsuba's as closely as in
/// the built-in box.
#[test]
fn a_room_of_separate_wall_objs_matches_mitsuba_per_vertex() {
    let dir = tempfile::tempdir().unwrap();
    let mut spec = RoomSpec::metres([2.0, -0.5, 3.0]);
    spec.patches = 3000;
    let path = rooms::write_room(dir.path(), &spec);
    let loaded = load_scene_file(&path).unwrap();
    for o in &loaded.objects {
        assert!(!o.reoriented, "{}: {:?}", o.name, o.orientation_notes);
    }
    let scene = build_loaded(&loaded, dir.path(), "walls");
    let lights = json!([spec.light()]);
    closed_room_against_mitsuba(&scene, &lights, "room of six wall OBJs", 300);
}

/// Relights `scene` (a closed diffuse room) with `lights` through the server's relight path
/// and compares with Mitsuba at about `points` viewer vertices and as many patch centroids:
/// median error under 3% and the total within 3% at both.
fn closed_room_against_mitsuba(
    scene: &Scene,
    lights: &serde_json::Value,
    what: &str,
    points: usize,
) {
    let b = &scene.bundle;
    let request = json!({ "lights": lights }).to_string();
    let plan = relight::plan(scene, translux_proto::parse_json(&request).unwrap()).unwrap();
    let t0 = std::time::Instant::now();
    let ours = relight::run(scene, &plan).unwrap();
    let ours_ms = t0.elapsed().as_secs_f64() * 1e3;
    let parsed: Vec<translux_proto::light::Light> = serde_json::from_value(lights.clone()).unwrap();
    let (patch_l, centroids, patch_normals) = patch_radiance(b, &parsed);

    // About 400 of each: a converged reference (8192 paths per point, 0.6% noise) costs
    // what 1600 points at 2048 paths would, and a median over 400 points is as telling.
    let (vp, vn) = vertex_queries(b);
    let vstep = (vp.len() / points).max(1);
    let pstep = (centroids.len() / points).max(1);
    let (vp, vn, vours) = (
        every(&vp, vstep),
        every(&vn, vstep),
        every(&ours.radiance, vstep),
    );
    let (pp, pn, pours) = (
        every(&centroids, pstep),
        every(&patch_normals, pstep),
        every(&patch_l, pstep),
    );
    let points: Vec<[f32; 3]> = vp.iter().chain(&pp).copied().collect();
    let normals: Vec<[f32; 3]> = vn.iter().chain(&pn).copied().collect();
    let input = json!({
        "objects": mitsuba::objects(b),
        "lights": lights,
        "queries": {"points": points, "normals": normals},
        "spp": 8192, "max_depth": 64, "rr_depth": 16, "seed": 7,
    });
    let Some(reference) = mitsuba::stored(&input) else {
        return;
    };
    let nv = vp.len();
    let ev = errors(&vours, &slice(&reference, 0, nv), 0.05);
    let ep = errors(&pours, &slice(&reference, nv, points.len()), 0.05);
    println!(
        "{what}, {} patches, point light; translux relight {ours_ms:.0} ms, \
         Mitsuba {:.1} s for {} points x 8192 paths\n\
         | compared at | points | median err | p90 err | Σ ours / Σ Mitsuba | Mitsuba noise (median) |\n\
         |---|---|---|---|---|---|\n{}\n{}",
        b.manifest().patch_count,
        reference.seconds,
        points.len(),
        table_row("patch centroids (radiosity B/π)", pp.len(), &ep),
        table_row("viewer vertices (relight answer)", nv, &ev),
    );
    for (what, e, n) in [("patches", &ep, pp.len()), ("vertices", &ev, nv)] {
        // The reference must be much finer than the bar it checks.
        assert!(
            e.reference_noise < 0.01,
            "{what}: Mitsuba too noisy: {:.3}",
            e.reference_noise
        );
        assert!(
            e.counted > n / 2,
            "{what}: too few lit points: {}",
            e.counted
        );
        assert!(
            e.median < 0.03,
            "{what}: median error {:.2}% > 3%",
            100.0 * e.median
        );
        // The tail: shadow edges and hot spots at the vertices take the direct light at
        // the vertex, and the indirect light on a mesh's edges is reconstructed there
        // (engine::vertexlight; the patch mean gave 10.4% in the Cornell box, the direct
        // light alone 5.25%, both 3.85%). The bar is 4%; the half point more is
        // the reference's own noise (0.6% per point).
        assert!(
            e.p90 < 0.045,
            "{what}: p90 error {:.2}% > 4.5%",
            100.0 * e.p90
        );
        // Energy: inter-reflection neither gained nor lost overall.
        assert!(
            (e.total_ratio - 1.0).abs() < 0.03,
            "{what}: Σ ours / Σ Mitsuba = {:.4}",
            e.total_ratio
        );
    }
}

/// F row sums of the patches of objects `names` whose centroids lie at least 10% of the
/// room's side from every edge of its wall and from the block: (min, max, count).
fn wall_row_sums(b: &Bundle, spec: &RoomSpec, names: &[&str]) -> (f64, f64, usize) {
    let objects: Vec<u32> = b
        .manifest()
        .objects
        .iter()
        .enumerate()
        .filter(|(_, o)| names.contains(&o.name.as_str()))
        .map(|(k, _)| k as u32)
        .collect();
    let f = b.form_factors();
    let (mut lo, mut hi, mut n) = (f64::INFINITY, f64::NEG_INFINITY, 0);
    for (i, corners) in b.patch_corners().iter().enumerate() {
        if !objects.contains(&b.patch_objects()[i]) {
            continue;
        }
        let c: Vec<f32> = (0..3)
            .map(|k| {
                let mean = (corners[0][k] + corners[1][k] + corners[2][k]) / 3.0;
                (mean - spec.corner[k]) / spec.size
            })
            .collect();
        // On a wall one coordinate is 0 or 1; the other two must be inside [0.1, 0.9].
        let inner = c.iter().filter(|x| (0.1..=0.9).contains(*x)).count();
        if inner < 2 {
            continue;
        }
        // The block's contact with the floor is an edge too: floor patches under it or
        // straddling its outline see less than everything.
        let (blo, bhi) = spec.block();
        let near_block = (0..3).all(|k| {
            let (a, z) = (
                (blo[k] - spec.corner[k]) / spec.size,
                (bhi[k] - spec.corner[k]) / spec.size,
            );
            c[k] >= a - 0.1 && c[k] <= z + 0.1
        });
        if near_block {
            continue;
        }
        let sum: f64 = f.row(i).1.iter().map(|&v| v as f64).sum();
        lo = lo.min(sum);
        hi = hi.max(sum);
        n += 1;
    }
    (lo, hi, n)
}

/// Precomputes a loaded scene into `dir/name` and opens it as the server does.
fn build_loaded(loaded: &LoadedScene, dir: &Path, name: &str) -> Scene {
    let out = dir.join(name);
    precompute(loaded, &out, &PrecomputeParams::default()).unwrap();
    Scene::open(name, &out).unwrap()
}

/// A closed room gives every wall patch F row sums near 1, wherever the scene's origin is
/// and whatever the unit — which needs every wall kept facing into the room. The old rule
/// (negative signed volume) flipped walls depending on the origin.
#[test]
fn rooms_of_wall_objs_keep_their_walls_facing_in_wherever_the_origin_is() {
    let cases = [
        ("origin at a corner, metres", [0.0, 0.0, 0.0], 1.0, 1000.0),
        (
            "origin at the centre, metres",
            [-0.5, -0.5, -0.5],
            1.0,
            1000.0,
        ),
        ("origin outside, metres", [2.0, -3.0, 1.5], 1.0, 1000.0),
        (
            "origin at the centre, millimetres",
            [-2000.0, -2000.0, -2000.0],
            4000.0,
            1.0,
        ),
    ];
    for (what, corner, size, unit_mm) in cases {
        let dir = tempfile::tempdir().unwrap();
        let spec = RoomSpec {
            size,
            corner,
            unit_mm,
            ..RoomSpec::metres(corner)
        };
        let loaded = load_scene_file(&rooms::write_room(dir.path(), &spec)).unwrap();
        for o in &loaded.objects {
            assert!(
                !o.reoriented,
                "{what}: {} flipped: {:?}",
                o.name, o.orientation_notes
            );
        }
        let scene = build_loaded(&loaded, dir.path(), "room");
        let (lo, hi, n) = wall_row_sums(&scene.bundle, &spec, &spec.surface_names());
        println!("{what}: {n} wall patches away from edges, F row sums in [{lo:.4}, {hi:.4}]");
        assert!(n > 300, "{what}: {n}");
        assert!(lo > 0.98 && hi < 1.02, "{what}: row sums in [{lo}, {hi}]");
    }
}

/// The same room as one closed OBJ box facing inward. `auto` keeps it (it encloses the
/// light and the block), `inward` and `as_is` keep it, `outward` turns it into a box seen
/// from outside (row sums 0 inside: the walls face away from everything).
#[test]
fn a_room_as_one_inward_box_follows_its_orientation() {
    for (mode, kept) in [
        (None, true),
        (Some("inward"), true),
        (Some("as_is"), true),
        (Some("outward"), false),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let spec = RoomSpec {
            walls: Walls::OneClosedBox,
            orientation: mode,
            patches: 1200,
            ..RoomSpec::metres([-0.5, 0.0, -0.5])
        };
        let loaded = load_scene_file(&rooms::write_room(dir.path(), &spec)).unwrap();
        let room = &loaded.objects[0];
        assert_eq!(
            room.reoriented, !kept,
            "{mode:?}: {:?}",
            room.orientation_notes
        );
        assert!(
            !loaded.objects[1].reoriented,
            "the block faces outward already"
        );
        if mode.is_none() {
            assert!(
                room.orientation_notes.iter().any(|n| n.contains("room")),
                "{:?}",
                room.orientation_notes
            );
        }
        let scene = build_loaded(&loaded, dir.path(), "room");
        let (lo, hi, n) = wall_row_sums(&scene.bundle, &spec, &["room"]);
        assert!(n > 200, "{mode:?}: {n}");
        if kept {
            assert!(lo > 0.98 && hi < 1.02, "{mode:?}: row sums in [{lo}, {hi}]");
        } else {
            assert!(
                hi < 0.02,
                "{mode:?}: an outward room sees nothing: max {hi}"
            );
        }
    }
}

/// Jensen et al. 2001's dipole diffuse reflectance R_d(r) (mm⁻², r in mm) for reduced
/// scattering σs′, absorption σa (mm⁻¹) and relative index η, written here from the
/// published formulas (eqs. 4–5 of the paper, with its F_dr fit): the reference is
/// independent of `translux_engine::profile`.
fn jensen_rd(r: f64, sigma_s_prime: f64, sigma_a: f64, eta: f64) -> f64 {
    let sigma_t = sigma_s_prime + sigma_a;
    let alpha = sigma_s_prime / sigma_t;
    let sigma_tr = (3.0 * sigma_a * sigma_t).sqrt();
    let f_dr = -1.440 / (eta * eta) + 0.710 / eta + 0.668 + 0.0636 * eta;
    let a = (1.0 + f_dr) / (1.0 - f_dr);
    let z_r = 1.0 / sigma_t;
    let z_v = z_r * (1.0 + 4.0 * a / 3.0);
    let d_r = (r * r + z_r * z_r).sqrt();
    let d_v = (r * r + z_v * z_v).sqrt();
    let term = |z: f64, d: f64| z * (sigma_tr * d + 1.0) * (-sigma_tr * d).exp() / (d * d * d);
    alpha / (4.0 * std::f64::consts::PI) * (term(z_r, d_r) + term(z_v, d_v))
}

/// B(x) = ∫ R_d(|x − y|) E(y) dA_y over the surface of an axis-aligned cube of edge `edge`
/// mm centred at the origin, lit by a directional light (E = irradiance · cos on faces
/// that face it, 0 elsewhere; a convex object shadows nothing else), by midpoint
/// quadrature: cells of `cell` mm, each cell within 2 mm of x split 16 × 16 more (R_d peaks
/// over the distance z_r ≈ 0.4 mm).
fn dipole_integral(
    x: [f64; 3],
    edge: f64,
    to_light: [f64; 3],
    e0: f64,
    m: (f64, f64, f64),
    cell: f64,
) -> f64 {
    let h = edge / 2.0;
    let n = (edge / cell).ceil() as usize;
    let c = edge / n as f64;
    let mut total = 0.0;
    for axis in 0..3 {
        for sign in [-1.0f64, 1.0] {
            let mut normal = [0.0; 3];
            normal[axis] = sign;
            let cos = normal
                .iter()
                .zip(&to_light)
                .map(|(a, b)| a * b)
                .sum::<f64>();
            if cos <= 0.0 {
                continue;
            }
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            let point = |a: f64, b: f64| {
                let mut p = [0.0; 3];
                p[axis] = sign * h;
                p[u] = a;
                p[v] = b;
                p
            };
            let dist = |p: [f64; 3]| {
                ((p[0] - x[0]).powi(2) + (p[1] - x[1]).powi(2) + (p[2] - x[2]).powi(2)).sqrt()
            };
            let mut sum = 0.0;
            for i in 0..n {
                for j in 0..n {
                    let (a, b) = (-h + (i as f64 + 0.5) * c, -h + (j as f64 + 0.5) * c);
                    if dist(point(a, b)) < 2.0 {
                        let k = 16;
                        let s = c / k as f64;
                        for p in 0..k {
                            for q in 0..k {
                                let y = point(
                                    a - c / 2.0 + (p as f64 + 0.5) * s,
                                    b - c / 2.0 + (q as f64 + 0.5) * s,
                                );
                                sum += jensen_rd(dist(y), m.0, m.1, m.2) * s * s;
                            }
                        }
                    } else {
                        sum += jensen_rd(dist(point(a, b)), m.0, m.1, m.2) * c * c;
                    }
                }
            }
            total += e0 * cos * sum;
        }
    }
    total
}

/// A lone marble cube (convex: optical paths are straight, and F = 0, so B = S E) lit by a
/// directional light from above and aside, against direct numerical integration of the
/// dipole over its surface: the subsurface matrix S, its quadrature and its units.
#[test]
fn a_convex_translucent_cube_matches_the_integrated_dipole() {
    use translux_proto::scene::{MeshRef, ObjectDesc, Profile, Shape};
    let edge_m = 0.02f32;
    let file = SceneFile {
        animation: None,
        name: Some("cube".into()),
        objects: vec![ObjectDesc {
            keyframes: None,
            name: "cube".into(),
            mesh: MeshRef::Shape(Shape::Box {
                size: [edge_m; 3],
                inward: false,
            }),
            transform: None,
            material: Material::Translucent {
                profile: Profile::Dipole {
                    preset: Some("marble".into()),
                    sigma_a: None,
                    sigma_s_prime: None,
                    eta: None,
                    scale: None,
                },
                specular: None,
            },
            crease_deg: None,
            simplify_to: None,
            orientation: Default::default(),
        }],
        lights: vec![],
        unit_mm: 1000.0,
        patches: None,
        camera: None,
    };
    let dir = tempfile::tempdir().unwrap();
    let scene = build(file, dir.path(), "cube", 6000);
    let b = &scene.bundle;
    assert_eq!(
        b.form_factors().nnz(),
        0,
        "a convex object sees none of itself"
    );
    let travel = glam::Vec3::new(-0.3, -1.0, -0.5).normalize();
    let e0 = 2.0f32;
    let lights = vec![translux_proto::light::Light::Directional {
        direction: travel.to_array(),
        irradiance: [e0; 3],
    }];
    let (ours, centroids, _) = patch_radiance(b, &lights);
    // Marble (Jensen et al. 2001, Table 1), η = 1.5.
    let media = [
        (2.19, 0.0021, 1.5),
        (2.62, 0.0041, 1.5),
        (3.00, 0.0071, 1.5),
    ];
    let to_light = (-travel).as_dvec3().to_array();
    let step = (centroids.len() / 90).max(1);
    let mut rows = Vec::new();
    for k in (0..centroids.len()).step_by(step) {
        let x = centroids[k].map(|v| f64::from(v) * 1000.0);
        let want: [f64; 3] = std::array::from_fn(|c| {
            dipole_integral(
                x,
                f64::from(edge_m) * 1000.0,
                to_light,
                f64::from(e0),
                media[c],
                0.25,
            )
        });
        // patch_radiance gives B/π.
        let got: [f64; 3] = std::array::from_fn(|c| f64::from(ours[k][c]) * std::f64::consts::PI);
        rows.push((x, got, want));
    }
    let peak = rows.iter().flat_map(|r| r.2).fold(0.0f64, f64::max);
    let mut errs: Vec<f64> = rows
        .iter()
        .flat_map(|(_, g, w)| (0..3).map(move |c| (g[c], w[c])))
        .filter(|&(_, w)| w > 0.02 * peak)
        .map(|(g, w)| (g - w).abs() / w)
        .collect();
    errs.sort_by(f64::total_cmp);
    let (median, max) = (errs[errs.len() / 2], errs[errs.len() - 1]);
    // Total exitance over the probes against the integral: energy, whatever the shape.
    let sum = |i: usize| {
        rows.iter()
            .map(|r| {
                if i == 0 {
                    r.1.iter().sum::<f64>()
                } else {
                    r.2.iter().sum::<f64>()
                }
            })
            .sum::<f64>()
    };
    println!(
        "marble cube 2 cm, {} patches, directional light: {} probes ({} channels above 2% of the \
         peak): median error {:.2}%, max {:.2}%, Σ ours / Σ integral {:.4}",
        b.manifest().patch_count,
        rows.len(),
        errs.len(),
        100.0 * median,
        100.0 * max,
        sum(0) / sum(1)
    );
    assert!(
        errs.len() > rows.len(),
        "too few lit probes: {}",
        errs.len()
    );
    assert!(max < 0.05, "worst probe off by {:.2}% (> 5%)", 100.0 * max);
    assert!((sum(0) / sum(1) - 1.0).abs() < 0.02);
}

/// A homogeneous, isotropic scattering medium (mm⁻¹) behind an index-matched boundary (η = 1:
/// a path tracer's point lights reach it), as translux's two S models and as Mitsuba's volume.
struct Medium {
    sigma_s_prime: [f32; 3],
    sigma_a: [f32; 3],
}

impl Medium {
    /// The dipole of the same coefficients (a half-space profile).
    fn dipole(&self) -> Material {
        Material::Translucent {
            profile: translux_proto::scene::Profile::Dipole {
                preset: None,
                sigma_a: Some(self.sigma_a),
                sigma_s_prime: Some(self.sigma_s_prime),
                eta: Some(1.0),
                scale: None,
            },
            specular: None,
        }
    }

    /// Random walks in the same medium (`"type": "simulated"`), at `noise` if given.
    fn simulated(&self, noise: Option<f32>) -> Material {
        let mut m = json!({"type": "simulated", "sigma_s_prime": self.sigma_s_prime,
                           "sigma_a": self.sigma_a, "eta": 1.0});
        if let Some(n) = noise {
            m["noise"] = json!(n);
        }
        translux_proto::parse_json(&m.to_string()).unwrap()
    }

    /// Mitsuba's volume (m⁻¹): σs = σs′ with an isotropic phase.
    fn volume(&self) -> serde_json::Value {
        json!({"type": "volume",
               "sigma_a": self.sigma_a.map(|v| v * 1000.0),
               "sigma_s": self.sigma_s_prime.map(|v| v * 1000.0),
               "g": 0.0, "eta": 1.0})
    }
}

/// Per group of probes: the dipole's (`got`) and the simulated S's (`got_sim`) errors
/// against `reference`, with a table row each (labelled `prefix` + the group's name).
fn errors_per_group(
    groups: &[(String, Vec<usize>)],
    got: &[Rgb],
    got_sim: &[Rgb],
    reference: &mitsuba::Reference,
    prefix: &str,
    rows: &mut Vec<String>,
) -> Vec<(String, Errors, Errors)> {
    groups
        .iter()
        .map(|(name, at)| {
            let (g, r) = pick_at(got, reference, at);
            let (gs, _) = pick_at(got_sim, reference, at);
            let (ed, es) = (errors(&g, &r, 0.05), errors(&gs, &r, 0.05));
            rows.push(table_row(&format!("{prefix}{name}, dipole"), at.len(), &ed));
            rows.push(table_row(
                &format!("{prefix}{name}, simulated"),
                at.len(),
                &es,
            ));
            (name.clone(), ed, es)
        })
        .collect()
}

/// Whether each viewer vertex lies inside a flat region of its mesh: its triangles' angles
/// add up to a full turn, so they go all the way round it (a vertex on a face's border,
/// where the exitance jumps between two faces, is left out).
fn interior_vertices(b: &Bundle) -> Vec<bool> {
    let pos = b.vertex_positions();
    let mut angle = vec![0.0f32; pos.len()];
    for t in b.triangle_vertices() {
        for k in 0..3 {
            let p = glam::Vec3::from(pos[t[k] as usize]);
            let a = glam::Vec3::from(pos[t[(k + 1) % 3] as usize]) - p;
            let c = glam::Vec3::from(pos[t[(k + 2) % 3] as usize]) - p;
            angle[t[k] as usize] += a.angle_between(c);
        }
    }
    angle
        .iter()
        .map(|a| (a - std::f32::consts::TAU).abs() < 1e-3)
        .collect()
}

/// The probes among `probes` (patch indices) that lie on `object`, grouped by the face their
/// normal points along (±x, ±y, ±z), each group labelled by `label(axis, sign)`.
fn face_groups(
    b: &Bundle,
    probes: &[usize],
    object: usize,
    label: &dyn Fn(usize, f32) -> String,
) -> Vec<(String, Vec<usize>)> {
    let normals = b.patch_normals();
    let objects = b.patch_objects();
    let mut groups: Vec<(String, Vec<usize>)> = Vec::new();
    for (q, &k) in probes.iter().enumerate() {
        if objects[k] as usize != object {
            continue;
        }
        let n = normals[k];
        let axis = (0..3)
            .max_by(|&a, &b| n[a].abs().total_cmp(&n[b].abs()))
            .unwrap();
        let name = label(axis, n[axis].signum());
        match groups.iter_mut().find(|g| g.0 == name) {
            Some(g) => g.1.push(q),
            None => groups.push((name, vec![q])),
        }
    }
    groups.sort_by(|a, b| a.0.cmp(&b.0));
    groups
}

/// The answers of `reference` and `got` at the probe positions `at` (indices into both).
fn pick_at(
    got: &[Rgb],
    reference: &mitsuba::Reference,
    at: &[usize],
) -> (Vec<Rgb>, mitsuba::Reference) {
    let mut r = slice(reference, 0, 0);
    for &q in at {
        r.radiance.push(reference.radiance[q]);
        r.std_error.push(reference.std_error[q]);
    }
    r.suspect = reference
        .suspect
        .iter()
        .filter_map(|s| at.iter().position(|q| q == s))
        .collect();
    (at.iter().map(|&q| got[q]).collect(), r)
}

/// The tall block of the Cornell box made a homogeneous scattering medium, with its S from
/// the dipole and from random walks (`simulated`), against Mitsuba's volpath random-walking
/// the same medium inside the same block.
#[test]
fn a_translucent_block_in_a_diffuse_box_against_volumetric_path_tracing() {
    // A warm, fairly translucent medium (mm⁻¹): albedo σs′/(σs′ + σa) 0.99–0.95, diffusion
    // length 1/σtr ≈ 13, 10, 5 mm, mean free path ≈ 2–3 mm: 60+ of them across the block.
    let medium = Medium {
        sigma_s_prime: [0.5, 0.45, 0.35],
        sigma_a: [0.004, 0.008, 0.02],
    };
    let with_block = |material: Material| {
        let mut file = builtin_scene("cornell").unwrap();
        for o in &mut file.objects {
            if o.name == "tall_block" {
                o.material = material.clone();
            }
        }
        file
    };
    let dipole = with_block(medium.dipole());
    let walked = with_block(medium.simulated(None));
    let dir = tempfile::tempdir().unwrap();
    // 12,000 patches, not fewer: at 3,000 the room itself was too coarse behind the block.
    // The same box with the block made diffuse (a temporary variant of this test, 2026-11-30)
    // put the −z face's total at 0.951 of Mitsuba's at 3,000 patches and at 0.990 at 12,000:
    // the light that reaches the gap between the block and the back wall, not S, was what
    // kept −z 5.9% off there (docs/validation.md).
    let scene = build(dipole, dir.path(), "volume_cornell", 12_000);
    let sim_scene = build(walked, dir.path(), "simulated_cornell", 12_000);
    let b = &scene.bundle;
    assert_eq!(b.patch_corners(), sim_scene.bundle.patch_corners());
    let lights =
        json!([{"type": "point", "position": [0.05, 0.32, 0.12], "intensity": [0.8, 0.8, 0.8]}]);
    let parsed: Vec<translux_proto::light::Light> = serde_json::from_value(lights.clone()).unwrap();
    let (ours, centroids, normals) = patch_radiance(b, &parsed);
    let (ours_sim, _, _) = patch_radiance(&sim_scene.bundle, &parsed);

    let m = b.manifest();
    let block = m
        .objects
        .iter()
        .position(|o| o.name == "tall_block")
        .unwrap();
    let objects = m.objects.iter().map(|o| o.name.clone()).collect::<Vec<_>>();
    let object_of = b.patch_objects();
    // 300 of the block's ~1,800 patches and ~150 others.
    let in_block: Vec<usize> = (0..centroids.len())
        .filter(|&k| object_of[k] as usize == block)
        .collect();
    let others: Vec<usize> = (0..centroids.len())
        .filter(|&k| object_of[k] as usize != block)
        .collect();
    let pick = |v: &[usize], n: usize| every(v, (v.len() / n).max(1));
    let probes: Vec<usize> = pick(&in_block, 300)
        .into_iter()
        .chain(pick(&others, 150))
        .collect();
    let input = json!({
        "objects": mitsuba::objects_with(b, &[("tall_block".to_owned(), medium.volume())]),
        "lights": lights,
        "queries": {"points": probes.iter().map(|&k| centroids[k]).collect::<Vec<_>>(),
                    "normals": probes.iter().map(|&k| normals[k]).collect::<Vec<_>>()},
        "measure": "exitance",
        "spp": 2048, "max_depth": 4096, "rr_depth": 256, "seed": 3,
    });
    let Some(reference) = mitsuba::stored(&input) else {
        return;
    };
    let got: Vec<Rgb> = probes.iter().map(|&k| ours[k]).collect();
    let got_sim: Vec<Rgb> = probes.iter().map(|&k| ours_sim[k]).collect();
    let nb = pick(&in_block, 300).len();
    let eb = errors(&got[..nb], &slice(&reference, 0, nb), 0.05);
    let ebs = errors(&got_sim[..nb], &slice(&reference, 0, nb), 0.05);
    let ew = errors(&got[nb..], &slice(&reference, nb, probes.len()), 0.05);
    let ews = errors(&got_sim[nb..], &slice(&reference, nb, probes.len()), 0.05);
    // The block's faces: which face a probe is on, and whether the light sees it.
    let light = [0.05f32, 0.32, 0.12];
    let label = |axis: usize, sign: f32| {
        let name = ["x", "y", "z"][axis];
        let face = format!("{}{name}", if sign > 0.0 { "+" } else { "-" });
        // A face is lit when the light is on its outer side of the block's centre.
        let c = in_block
            .iter()
            .map(|&k| centroids[k][axis])
            .fold(0.0f32, |a, v| a + v)
            / in_block.len() as f32;
        let lit = (light[axis] - c) * sign > 0.0;
        format!("{face} ({})", if lit { "lit" } else { "unlit" })
    };
    let groups = face_groups(b, &probes, block, &label);
    let sim = sim_scene
        .bundle
        .manifest()
        .subsurface
        .objects
        .iter()
        .find(|o| o.name == "tall_block")
        .unwrap()
        .clone();
    let info = sim.simulation.clone().unwrap();
    let mut rows = vec![
        table_row("block, dipole", nb, &eb),
        table_row("block, simulated", nb, &ebs),
    ];
    let per_face = errors_per_group(&groups, &got, &got_sim, &reference, "block ", &mut rows);
    // The faces lit only through the block and round it, again at the viewer's vertices:
    // what a relight answers and what issue #18 measures (a vertex averages the patches
    // round it, as the viewer shows them), with 8,192 paths per vertex. Vertices inside
    // the face only ([`interior_vertices`]), on the block (inside its bounding box).
    let (vp, vn) = vertex_queries(b);
    let interior = interior_vertices(b);
    let pos = b.vertex_positions();
    let corners = b.patch_corners();
    let (lo, hi) = in_block.iter().flat_map(|&k| corners[k].iter()).fold(
        ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]),
        |(lo, hi), p| {
            (
                std::array::from_fn(|a| lo[a].min(p[a])),
                std::array::from_fn(|a| hi[a].max(p[a])),
            )
        },
    );
    let on_block = |p: &[f32; 3]| {
        (0..3).all(|a| {
            let eps = 1e-4 * (hi[a] - lo[a]);
            (lo[a] - eps..=hi[a] + eps).contains(&p[a])
        })
    };
    let mut vertex_faces: Vec<(String, Vec<usize>)> = Vec::new();
    for v in (0..pos.len()).filter(|&v| interior[v] && on_block(&pos[v])) {
        let n = vn[v];
        let axis = (0..3)
            .max_by(|&a, &c| n[a].abs().total_cmp(&n[c].abs()))
            .unwrap();
        let name = label(axis, n[axis].signum());
        if name.contains("unlit") && !name.starts_with("-y") {
            match vertex_faces.iter_mut().find(|g| g.0 == name) {
                Some(g) => g.1.push(v),
                None => vertex_faces.push((name, vec![v])),
            }
        }
    }
    vertex_faces.sort_by(|a, c| a.0.cmp(&c.0));
    // About 48 vertices a face, spread over it (8,192 paths each).
    for (_, at) in &mut vertex_faces {
        *at = every(at, (at.len() / 48).max(1));
    }
    let relit = |scene: &Scene, at: &[usize]| -> Vec<Rgb> {
        let body = json!({ "lights": lights }).to_string();
        let plan = relight::plan(scene, translux_proto::parse_json(&body).unwrap()).unwrap();
        let radiance = relight::run(scene, &plan).unwrap().radiance;
        at.iter().map(|&v| radiance[v]).collect()
    };
    let mut at_vertices = Vec::new();
    let mut vertex_seconds = 0.0;
    for (k, (name, at)) in vertex_faces.iter().enumerate() {
        let mut again = input.clone();
        again["queries"] = json!({
            "points": at.iter().map(|&v| vp[v]).collect::<Vec<_>>(),
            "normals": at.iter().map(|&v| vn[v]).collect::<Vec<_>>(),
        });
        again["spp"] = json!(8192);
        again["seed"] = json!(4 + k);
        let Some(deep) = mitsuba::stored(&again) else {
            return;
        };
        vertex_seconds += deep.seconds;
        let (ed, es) = (
            errors(&relit(&scene, at), &deep, 0.05),
            errors(&relit(&sim_scene, at), &deep, 0.05),
        );
        let name = format!("block {name} at vertices (8192 paths)");
        rows.push(table_row(&format!("{name}, dipole"), at.len(), &ed));
        rows.push(table_row(&format!("{name}, simulated"), at.len(), &es));
        at_vertices.push((name, ed, es));
    }
    rows.push(table_row(
        &format!("the other {} objects, dipole block", objects.len() - 1),
        probes.len() - nb,
        &ew,
    ));
    rows.push(table_row(
        &format!("the other {} objects, simulated block", objects.len() - 1),
        probes.len() - nb,
        &ews,
    ));
    println!(
        "Cornell box, tall block a scattering medium (η = 1), {} patches; Mitsuba {:.1} s \
         (+ {:.1} s at vertices); walks: {} ({} events) in {:.1} s, noise {:.2}% median\n\
         | patches | points | median err | p90 err | Σ ours / Σ Mitsuba | Mitsuba noise (median) |\n\
         |---|---|---|---|---|---|\n{}",
        m.patch_count,
        reference.seconds,
        vertex_seconds,
        info.walks,
        info.events,
        sim.seconds,
        100.0 * info.noise_median,
        rows.join("\n"),
    );
    assert!(
        ew.reference_noise < 0.02,
        "walls: Mitsuba too noisy: {:.3}",
        ew.reference_noise
    );
    assert!(
        ew.median < 0.05 && ews.median < 0.05,
        "walls: median error {:.2}% (dipole block), {:.2}% (simulated block)",
        100.0 * ew.median,
        100.0 * ews.median
    );
    assert!(
        (0.5..2.0).contains(&eb.total_ratio),
        "block: Σ ours / Σ Mitsuba = {:.3}",
        eb.total_ratio
    );
    // The simulated S walks the same medium Mitsuba walks: the bar, 5% median on
    // every face group with enough points, and the block's total within 5%.
    assert!(
        ebs.median < 0.05 && (ebs.total_ratio - 1.0).abs() < 0.05,
        "simulated block: median {:.2}%, Σ ratio {:.3}",
        100.0 * ebs.median,
        ebs.total_ratio
    );
    // The bottom face (−y) stands on the floor: light that reaches it goes into the floor
    // in Mitsuba and back into the block, while S re-emits it at patches the floor buries
    // (its probes are mostly left out as unreachable). Reported only. Every other face,
    // the two lit only through the block and round it (−x, −z) included, is held to the
    // issue's 5% median and its total to 5%, at patch centroids and at the viewer's
    // vertices (issue #18's measure).
    for (name, _, e) in &at_vertices {
        assert!(
            e.reference_noise < 0.03,
            "{name}: Mitsuba too noisy: {:.3}",
            e.reference_noise
        );
        assert!(
            e.counted >= 10 && e.median < 0.05 && (e.total_ratio - 1.0).abs() < 0.05,
            "simulated block, {name}: median {:.2}% over {} vertices, Σ ratio {:.3}",
            100.0 * e.median,
            e.counted,
            e.total_ratio
        );
    }
    for (name, _, e) in &per_face {
        if e.counted >= 10 && !name.starts_with("-y") {
            assert!(
                e.median < 0.05 && (e.total_ratio - 1.0).abs() < 0.05,
                "simulated block, face {name}: median {:.2}%, Σ ratio {:.3}",
                100.0 * e.median,
                e.total_ratio
            );
        }
    }
}

/// One translucent object alone (named `object` in `scene(material)`), its S from the
/// dipole and from walks in `medium`, lit by `lights`, against Mitsuba's volpath in the same
/// medium measuring exitance / π (what a radiosity patch carries) at about `probes` patch
/// centroids; per group of probes (`group` of a probe's centroid and normal names it, in
/// `names`' order) the dipole's and the simulated S's errors. Prints the table under `title`.
struct LoneObject<'a> {
    title: &'a str,
    object: &'a str,
    medium: Medium,
    /// The simulated S's noise target (None: the default).
    noise: Option<f32>,
    patches: u64,
    lights: serde_json::Value,
    probes: usize,
    spp: u32,
    /// Groups (index into `names`) compared again at the viewer's vertices, Mitsuba with
    /// this many paths per vertex: a face lit only through the object is far dimmer, and
    /// noisier, on both sides.
    deep: &'a [(usize, u32)],
    /// Groups every patch of which is probed too (beside every `probes`-th patch): a
    /// narrow face whose patches alternate between two shapes would otherwise be sampled
    /// at one of them only.
    whole: &'a [usize],
    seed: u32,
    names: &'a [&'a str],
    /// Also compare the simulated object with its lamps walked along their own beams, this
    /// many walks per lamp (a relight's `"lamp_walks"`): entries named "…, lamp walks",
    /// (dipole, walked).
    lamp_walks: Option<u32>,
    /// Where tests of the same object, medium and patches (lit differently) find its two
    /// bundles while another of them holds them (S is light-independent); the last to let
    /// go removes their folder.
    shared: Option<&'static Mutex<Weak<Built>>>,
}

/// A lone object precomputed with the dipole and with walks, in its folder.
struct Built {
    _dir: tempfile::TempDir,
    dipole: Scene,
    simulated: Scene,
}

impl Built {
    fn of(c: &LoneObject<'_>, scene: &dyn Fn(Material) -> SceneFile) -> Built {
        let dir = tempfile::tempdir().unwrap();
        let name = |kind: &str| format!("{}_{kind}", c.object);
        let dipole = build(
            scene(c.medium.dipole()),
            dir.path(),
            &name("dipole"),
            c.patches,
        );
        let simulated = build(
            scene(c.medium.simulated(c.noise)),
            dir.path(),
            &name("simulated"),
            c.patches,
        );
        Built {
            _dir: dir,
            dipole,
            simulated,
        }
    }
}

fn lone_object_against_volpath(
    c: &LoneObject<'_>,
    scene: &dyn Fn(Material) -> SceneFile,
    group: &dyn Fn([f32; 3], [f32; 3]) -> usize,
) -> Option<Vec<(String, Errors, Errors)>> {
    let built = match c.shared {
        Some(kept) => {
            // Held while building, so a test lit differently waits for these bundles.
            let mut kept = kept.lock().unwrap_or_else(|e| e.into_inner());
            kept.upgrade().unwrap_or_else(|| {
                let built = Arc::new(Built::of(c, scene));
                *kept = Arc::downgrade(&built);
                built
            })
        }
        None => Arc::new(Built::of(c, scene)),
    };
    let (a, s) = (&built.dipole, &built.simulated);
    let b = &a.bundle;
    assert_eq!(b.patch_corners(), s.bundle.patch_corners());
    let parsed: Vec<translux_proto::light::Light> =
        serde_json::from_value(c.lights.clone()).unwrap();
    let to_m = (b.manifest().unit_mm / 1000.0) as f32;
    let (ours, centroids, normals) = patch_radiance(b, &parsed);
    let (ours_sim, _, _) = patch_radiance(&s.bundle, &parsed);
    let all: Vec<usize> = (0..centroids.len()).collect();
    let mut probes = every(&all, (all.len() / c.probes).max(1));
    probes.extend(
        all.iter()
            .filter(|&&k| c.whole.contains(&group(centroids[k], normals[k]))),
    );
    probes.sort_unstable();
    probes.dedup();
    let input = json!({
        "objects": mitsuba::objects_with(b, &[(c.object.to_owned(), c.medium.volume())]),
        "lights": c.lights,
        "queries": {"points": probes.iter().map(|&k| centroids[k]).collect::<Vec<_>>(),
                    "normals": probes.iter().map(|&k| normals[k]).collect::<Vec<_>>()},
        "measure": "exitance",
        "spp": c.spp, "max_depth": 4096, "rr_depth": 256, "seed": c.seed,
    });
    let reference = mitsuba::stored(&input)?;
    let got: Vec<Rgb> = probes.iter().map(|&k| ours[k]).collect();
    let got_sim: Vec<Rgb> = probes.iter().map(|&k| ours_sim[k]).collect();
    let mut groups: Vec<(String, Vec<usize>)> = c
        .names
        .iter()
        .map(|n| (n.to_string(), Vec::new()))
        .collect();
    for (q, &k) in probes.iter().enumerate() {
        groups[group(centroids[k], normals[k])].1.push(q);
    }
    let mut rows = Vec::new();
    let mut out = errors_per_group(&groups, &got, &got_sim, &reference, "", &mut rows);
    if let Some(per) = c.lamp_walks {
        let t = std::time::Instant::now();
        let (walked, _, _) = patch_radiance_with(&s.bundle, &parsed, Some(per));
        println!(
            "lamp walks ({per} per lamp): {:.1} s",
            t.elapsed().as_secs_f64()
        );
        let got_walked: Vec<Rgb> = probes.iter().map(|&k| walked[k]).collect();
        for (name, at) in &groups {
            let (gw, r) = pick_at(&got_walked, &reference, at);
            let (g, _) = pick_at(&got, &reference, at);
            let (ed, ew) = (errors(&g, &r, 0.05), errors(&gw, &r, 0.05));
            rows.push(table_row(
                &format!("{name}, simulated, lamp walks"),
                at.len(),
                &ew,
            ));
            out.push((format!("{name}, lamp walks"), ed, ew));
        }
    }
    // Groups compared again at the viewer's vertices (what a relight answers), with a
    // reference of `spp` paths per vertex: vertices inside the group's face only (their
    // triangles go all the way round them, so a face's border, where the query point and
    // the vertex's own value depend on the side, is left out), every other one.
    let mut seconds = reference.seconds;
    let (vp, vn) = vertex_queries(&s.bundle);
    let interior = interior_vertices(&s.bundle);
    for &(g, spp) in c.deep {
        let at: Vec<usize> = (0..vp.len())
            .filter(|&v| interior[v] && group(vp[v].map(|x| x / to_m), vn[v]) == g)
            .step_by(2)
            .collect();
        let mut again = input.clone();
        again["queries"] = json!({
            "points": at.iter().map(|&v| vp[v]).collect::<Vec<_>>(),
            "normals": at.iter().map(|&v| vn[v]).collect::<Vec<_>>(),
        });
        again["spp"] = json!(spp);
        again["seed"] = json!(c.seed + 1 + g as u32);
        let deep = mitsuba::stored(&again)?;
        seconds += deep.seconds;
        let relit_with = |scene: &Scene, lamp_walks: Option<u32>| -> Vec<Rgb> {
            let mut body = json!({ "lights": c.lights });
            if let Some(per) = lamp_walks {
                body["lamp_walks"] = json!(per);
            }
            let body = body.to_string();
            let plan = relight::plan(scene, translux_proto::parse_json(&body).unwrap()).unwrap();
            let radiance = relight::run(scene, &plan).unwrap().radiance;
            at.iter().map(|&v| radiance[v]).collect()
        };
        let (ed, es) = (
            errors(&relit_with(a, None), &deep, 0.05),
            errors(&relit_with(s, None), &deep, 0.05),
        );
        let name = format!("{} at vertices ({spp} paths)", c.names[g]);
        rows.push(table_row(&format!("{name}, dipole"), at.len(), &ed));
        rows.push(table_row(&format!("{name}, simulated"), at.len(), &es));
        if let Some(per) = c.lamp_walks {
            let ew = errors(&relit_with(s, Some(per)), &deep, 0.05);
            rows.push(table_row(
                &format!("{name}, simulated, lamp walks"),
                at.len(),
                &ew,
            ));
            out.push((format!("{name}, lamp walks"), ed.clone(), ew));
        }
        out.push((name, ed, es));
    }
    let info = s.bundle.manifest().subsurface.objects[0].clone();
    let sim = info.simulation.clone().unwrap();
    println!(
        "{}, {} patches; Mitsuba (exitance) {:.1} s; walks {} in {:.1} s, noise \
         {:.2}% median\n\
         | faces | points | median err | p90 err | Σ ours / Σ Mitsuba | Mitsuba noise (median) |\n\
         |---|---|---|---|---|---|\n{}",
        c.title,
        b.manifest().patch_count,
        seconds,
        sim.walks,
        info.seconds,
        100.0 * sim.noise_median,
        rows.join("\n")
    );
    Some(out)
}

/// A lone scene file of one object `name`, with `mesh` and `material`.
fn alone(name: &str, mesh: serde_json::Value, material: Material) -> SceneFile {
    let mut file: SceneFile = serde_json::from_value(json!({"objects": [{"name": name,
        "mesh": mesh, "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}}]}))
    .unwrap();
    file.objects[0].material = material;
    file
}

/// Per face of a lone 16 mm cube of a scattering medium (σs′ 0.8, 0.6, 0.5 mm⁻¹; σa 0.01,
/// 0.02, 0.04 mm⁻¹; η = 1) lit on its +x face by a directional light along −x.
fn cube_lit_from_one_side() -> Option<Vec<(String, Errors, Errors)>> {
    let faces = [
        "far (-x)",
        "lit (+x)",
        "side (+y)",
        "side (+z)",
        "side (-y)",
        "side (-z)",
    ];
    lit_cube(
        "16 mm cube lit on +x by a directional light",
        [-1.0, 0.0, 0.0],
        &[(0, 131072)],
        &faces,
        None,
    )
}

/// The lit cubes' bundles, shared by the two tests while both run (their S does not depend
/// on the light).
static CUBE: Mutex<Weak<Built>> = Mutex::new(Weak::new());

/// The same cube lit by a directional light travelling along `direction`, its faces named
/// `faces` (−x, +x, +y, +z, −y, −z), the groups `deep` compared again at vertices.
fn lit_cube(
    title: &str,
    direction: [f32; 3],
    deep: &[(usize, u32)],
    faces: &[&str],
    lamp_walks: Option<u32>,
) -> Option<Vec<(String, Errors, Errors)>> {
    lone_object_against_volpath(
        &LoneObject {
            title,
            object: "cube",
            medium: Medium {
                sigma_s_prime: [0.8, 0.6, 0.5],
                sigma_a: [0.01, 0.02, 0.04],
            },
            noise: Some(0.003),
            patches: 1500,
            lights: json!([{"type": "directional", "direction": direction, "irradiance": [1, 1, 1]}]),
            probes: 300,
            spp: 8192,
            deep,
            whole: &[],
            seed: 5,
            names: faces,
            lamp_walks,
            shared: Some(&CUBE),
        },
        &|m| {
            alone(
                "cube",
                json!({"shape": "box", "size": [0.016, 0.016, 0.016]}),
                m,
            )
        },
        &|_, n| box_face(n),
    )
}

/// The face of an axis-aligned box a normal `n` points out of, in the order −x, +x, +y,
/// +z, −y, −z.
fn box_face(n: [f32; 3]) -> usize {
    let axis = (0..3)
        .max_by(|&a, &b| n[a].abs().total_cmp(&n[b].abs()))
        .unwrap();
    match (axis, n[axis] > 0.0) {
        (0, false) => 0,
        (0, true) => 1,
        (a, true) => 1 + a,
        (a, false) => 3 + a,
    }
}

/// A 16 mm cube lit on one face by a directional light, against Mitsuba's volumetric path
/// tracer in the same medium: the far face and the sides, lit only through the cube, are
/// where the half-space dipole fails. The light enters collimated, and the simulated S's
/// collimated walks carry it (`engine/src/collimated.rs`): every face's total within 5% of
/// Mitsuba's, the lit face's and the sides' medians under the 5% (Mitsuba's own
/// noise is 0.7% and 2.1–2.5% per point there). At patch centroids the far face's median
/// is this S's own noise per far patch (few of the walks from each lit patch get there)
/// beside Mitsuba's 7% at 8192 paths, so there it is held only to beat the dipole; at the
/// viewer's vertices (what a relight answers), against 131,072 paths per vertex, it is
/// held to the 5%; see docs/validation.md.
#[test]
fn a_cube_lit_from_one_side_against_volumetric_path_tracing() {
    let Some(faces) = cube_lit_from_one_side() else {
        return;
    };
    for (name, ed, es) in &faces {
        assert!(
            (es.total_ratio - 1.0).abs() < 0.05,
            "{name}: simulated {es:?} (total)"
        );
        if name.starts_with("lit") {
            assert!(es.median < 0.05, "lit face: simulated {es:?}");
            continue;
        }
        assert!(
            es.median < ed.median && (es.total_ratio - 1.0).abs() < (ed.total_ratio - 1.0).abs(),
            "{name}: simulated {es:?} is not closer to Mitsuba than the dipole {ed:?}"
        );
        if name.starts_with("side") || name.contains("at vertices") {
            assert!(es.median < 0.05, "{name}: simulated {es:?}");
        }
    }
}

/// Walks per lamp for the slanted cube's lamp walks (a relight's `"lamp_walks"`): about
/// 16,000 per lit patch.
const LAMP_WALKS: u32 = 8_000_000;

/// The cube lit at a slant, by a directional light travelling along (−0.866, 0, −0.5): it
/// enters +x 30° and +z 60° off their normals. The direction of the slant decides where the
/// light leaves (more through the faces ahead of the beams, −x and −z), and a beam that
/// crosses an edge unscattered is not exitance: the lamps' first harmonic and U
/// (`engine/src/collimated.rs`) carry both. With S(μ₀) alone the totals were 5–17% over
/// Mitsuba's (+x 8.5%, +y 17%) and the lit faces' p90 27–44%. With the model: the lit and
/// far faces' totals within 5%, the lit faces' medians under the 5% and the far
/// faces' at 5.0–5.4% (−x at the viewer's vertices), held to 6.5%; the sides along the
/// slant (±y) come out 7–10% low, held to 12%: the beam runs parallel to them, on a kink in
/// their exits as the beam turns that a short angular expansion per entry cannot follow
/// (docs/validation.md). With the lamp walked along its own beams (`"lamp_walks"`,
/// `engine/src/lampwalk.rs`) every face, at patch centroids and at the far face's
/// vertices, is held to the 5% in median and total.
#[test]
fn a_cube_lit_at_a_slant_against_volumetric_path_tracing() {
    let faces = [
        "far (-x)",
        "lit (+x)",
        "side (+y)",
        "lit (+z)",
        "side (-y)",
        "far (-z)",
    ];
    let Some(faces) = lit_cube(
        "16 mm cube lit at a slant, along (-0.866, 0, -0.5)",
        [-0.866, 0.0, -0.5],
        &[(0, 131072)],
        &faces,
        Some(LAMP_WALKS),
    ) else {
        return;
    };
    let walked: Vec<_> = faces
        .iter()
        .filter(|(name, ..)| name.ends_with("lamp walks"))
        .collect();
    assert_eq!(walked.len(), 7, "six faces and the far face's vertices");
    for (name, ed, ew) in walked {
        assert!(
            ew.median < 0.05 && (ew.total_ratio - 1.0).abs() < 0.05,
            "{name}: lamp walks {ew:?} (dipole {ed:?})"
        );
    }
    for (name, ed, es) in &faces {
        if name.ends_with("lamp walks") {
            continue;
        }
        assert!(
            (es.total_ratio - 1.0).abs() < (ed.total_ratio - 1.0).abs(),
            "{name}: simulated {es:?} is not closer to Mitsuba than the dipole {ed:?}"
        );
        let side = name.starts_with("side");
        let bar = if side { 0.12 } else { 0.05 };
        assert!(
            (es.total_ratio - 1.0).abs() < bar,
            "{name}: simulated {es:?} (total)"
        );
        if name.starts_with("lit") {
            assert!(es.median < 0.05, "{name}: simulated {es:?}");
        }
        if name == "far (-z)" || name.contains("at vertices") {
            assert!(es.median < 0.065, "{name}: simulated {es:?}");
        }
    }
}

/// A thin translucent bowl (outer radius 50 mm, wall 4 mm; σs′ 1.0, 0.8, 0.6 mm⁻¹, σa 0.005,
/// 0.01, 0.02 mm⁻¹, η = 1) lit by a point light inside it, below the rim: the inside (the
/// normal towards the sphere's centre), the flat rim, and the outside (lit only through the
/// wall) in two bands, the bottom half right below the light and the upper half to the rim.
fn bowl_lit_from_inside() -> Option<Vec<(String, Errors, Errors)>> {
    let (radius, thickness) = (0.05f32, 0.004f32);
    let centre = [0.0f32, radius, 0.0];
    lone_object_against_volpath(
        &LoneObject {
            title: "Bowl (R 50 mm, wall 4 mm) lit from inside by a point light",
            object: "bowl",
            medium: Medium {
                sigma_s_prime: [1.0, 0.8, 0.6],
                sigma_a: [0.005, 0.01, 0.02],
            },
            noise: Some(0.002),
            patches: 2500,
            lights: json!([{"type": "point", "position": [0.0, 0.035, 0.0], "intensity": [1, 1, 1]}]),
            probes: 400,
            spp: 4096,
            deep: &[],
            whole: &[3],
            seed: 7,
            names: &[
                "inside",
                "outside, bottom half",
                "outside, upper half",
                "rim",
            ],
            lamp_walks: None,
            shared: None,
        },
        &|m| {
            alone(
                "bowl",
                json!({"shape": "bowl", "radius": radius, "thickness": thickness}),
                m,
            )
        },
        &|c, n| {
            let d: [f32; 3] = std::array::from_fn(|i| c[i] - centre[i]);
            if n[1] > 0.99 && c[1] > radius - 1e-4 {
                3
            } else if (0..3).map(|i| n[i] * d[i]).sum::<f32>() < 0.0 {
                0
            } else if c[1] < 0.5 * radius {
                1
            } else {
                2
            }
        },
    )
}

/// A bowl lit from inside against Mitsuba's volumetric path tracer: the outside glows only by light that
/// crossed the wall. On every group the simulated S (with the lamp's collimated entry) must
/// be closer than the dipole, in median and in total; the inside's median under 4% (it is
/// 3.3%), the outside's under the 5% with its total within 5% (see
/// docs/validation.md).
/// The walks use `"noise": 0.002`: at the default 1% (S's noise in a patch's re-emitted
/// total) the light through the wall, a third of it spread over many patches, is noisier,
/// and the outside's median was 5–6% for that alone.
#[test]
fn a_bowl_lit_from_inside_against_volumetric_path_tracing() {
    let Some(groups) = bowl_lit_from_inside() else {
        return;
    };
    for (name, ed, es) in &groups {
        assert!(
            es.counted >= 10 && ed.reference_noise < 0.04,
            "{name}: too few points or Mitsuba too noisy: {ed:?}"
        );
        assert!(
            es.median < ed.median && (es.total_ratio - 1.0).abs() < (ed.total_ratio - 1.0).abs(),
            "{name}: simulated {es:?} is not closer to Mitsuba than the dipole {ed:?}"
        );
        if name.starts_with("outside") {
            assert!(
                es.median < 0.05 && (es.total_ratio - 1.0).abs() < 0.05,
                "{name}: simulated {es:?}"
            );
        }
        if name.starts_with("inside") {
            assert!(es.median < 0.04, "{name}: simulated {es:?}");
        }
        if name == "rim" {
            assert!(
                es.median < 0.05 && (es.total_ratio - 1.0).abs() < 0.05,
                "{name}: simulated {es:?}"
            );
        }
    }
}

/// Precomputes `loaded` into `dir/name` with `transport` at about `patches` patches.
fn bundle_with(
    loaded: &LoadedScene,
    dir: &Path,
    name: &str,
    patches: u64,
    transport: FormFactorMethod,
) -> Bundle {
    let out = dir.join(name);
    let params = PrecomputeParams {
        patches: Some(patches),
        transport,
        environment: translux_engine::envvis::EnvVisParams {
            bins: None,
            ..Default::default()
        },
        ..Default::default()
    };
    precompute(loaded, &out, &params).unwrap();
    Bundle::open(&out).unwrap()
}

/// Hierarchical F (the default accuracy) against dense F on the Cornell box: random point
/// and spot lights, near walls and grazing, relit to a residual of 1e-7 with both; the
/// operator on a constant, a smooth field and one cluster's indicator.
#[test]
fn hierarchical_f_agrees_with_dense_f_on_the_cornell_box() {
    let dir = tempfile::tempdir().unwrap();
    let loaded = translux_precompute::scene::load_scene("builtin:cornell").unwrap();
    let dense = bundle_with(&loaded, dir.path(), "dense", 3000, FormFactorMethod::Dense);
    let hier = bundle_with(
        &loaded,
        dir.path(),
        "hier",
        3000,
        FormFactorMethod::Hierarchical(HierarchyParams::default()),
    );
    let (nd, nh) = (dense.form_factors().nnz(), hier.form_factors().nnz());
    let h = hier.manifest().hierarchy.clone().unwrap();
    eprintln!("nnz dense {nd}, hierarchical {nh}: {h:?}");
    assert!(
        nh * 3 < nd,
        "the hierarchy stores a third of dense F or less"
    );
    assert!(h.node_entries > h.patch_entries, "{h:?}");
    let acc = compare::relight_accuracy(&dense, &hier, &compare::random_lights(&dense, 8, 17));
    eprintln!("{acc:?}");
    assert!(acc.lit.count > 1000 && acc.shadowed.count > 1000, "{acc:?}");
    assert!(acc.lit.median < 0.015 && acc.lit.p90 < 0.04, "{acc:?}");
    assert!(
        acc.shadowed.median < 0.04 && acc.shadowed.p90 < 0.15,
        "{acc:?}"
    );
    for (what, x) in compare::fields(&hier, 3) {
        let e = compare::operator_error(&dense, &hier, &x);
        eprintln!("operator error, {what}: {e:.2e}");
        assert!(e < 0.015, "{what}: {e}");
    }
}

/// Hierarchical F against dense F on `loaded` at about `patches` patches, relit by random
/// point and spot lights: the per-vertex errors and the operator errors, printed.
fn hierarchical_against_dense(
    loaded: &LoadedScene,
    patches: u64,
    what: &str,
) -> (compare::Accuracy, Vec<f64>) {
    let dir = tempfile::tempdir().unwrap();
    let dense = bundle_with(
        loaded,
        dir.path(),
        "dense",
        patches,
        FormFactorMethod::Dense,
    );
    let hier = bundle_with(
        loaded,
        dir.path(),
        "hier",
        patches,
        FormFactorMethod::Hierarchical(HierarchyParams::default()),
    );
    let acc = compare::relight_accuracy(&dense, &hier, &compare::random_lights(&dense, 8, 17));
    eprintln!("{what}: {acc:?}");
    let ops = compare::fields(&hier, 3)
        .into_iter()
        .map(|(field, x)| {
            let e = compare::operator_error(&dense, &hier, &x);
            eprintln!("{what}: operator error, {field}: {e:.2e}");
            e
        })
        .collect();
    (acc, ops)
}

/// The same comparison on a closed room modelled as six wall OBJs with a box on the floor,
/// and on the bowls (thin walls, inside and outside faces in separate clusters).
#[test]
fn hierarchical_f_agrees_with_dense_f_on_a_closed_room_and_the_bowls() {
    let dir = tempfile::tempdir().unwrap();
    let mut spec = RoomSpec::metres([2.0, -0.5, 3.0]);
    spec.patches = 3000;
    let room = load_scene_file(&rooms::write_room(dir.path(), &spec)).unwrap();
    let bowls = translux_precompute::scene::load_scene("builtin:bowls").unwrap();
    for (loaded, what) in [(&room, "closed room"), (&bowls, "bowls")] {
        let (acc, ops) = hierarchical_against_dense(loaded, 3000, what);
        assert!(acc.lit.count > 500, "{what}: {acc:?}");
        assert!(
            acc.lit.median < 0.015 && acc.lit.p90 < 0.04,
            "{what}: {acc:?}"
        );
        if acc.shadowed.count > 100 {
            assert!(
                acc.shadowed.median < 0.04 && acc.shadowed.p90 < 0.15,
                "{what}: {acc:?}"
            );
        }
        assert!(ops.iter().all(|&e| e < 0.015), "{what}: {ops:?}");
    }
}

/// A room split in two by a 1 cm wall, the light on one side: the other side stays dark
/// with a hierarchical F (clusters of the floor and ceiling span both sides).
#[test]
fn a_thin_wall_keeps_the_other_room_dark_with_hierarchical_f() {
    thin_wall_room(false);
}

/// The same room with two-sided links: floor and ceiling clusters that receive whole must
/// not carry light through the wall either.
#[test]
fn a_thin_wall_keeps_the_other_room_dark_with_two_sided_f() {
    thin_wall_room(true);
}

fn thin_wall_room(two_sided: bool) {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(
        d.join("room.obj"),
        rooms::box_obj([0.0; 3], [2.0, 1.0, 1.0], true),
    )
    .unwrap();
    std::fs::write(
        d.join("wall.obj"),
        rooms::box_obj([0.995, 0.0, 0.0], [1.005, 1.0, 1.0], false),
    )
    .unwrap();
    let grey = json!({"type": "diffuse", "albedo": [0.7, 0.7, 0.7]});
    let scene = json!({
        "objects": [
            {"name": "room", "mesh": "room.obj", "material": grey, "orientation": "as_is"},
            {"name": "wall", "mesh": "wall.obj", "material": grey},
        ],
        "lights": [{"type": "point", "position": [0.5, 0.5, 0.5], "intensity": [1, 1, 1]}],
    });
    std::fs::write(d.join("split.json"), scene.to_string()).unwrap();
    let loaded = load_scene_file(&d.join("split.json")).unwrap();
    let b = bundle_with(
        &loaded,
        d,
        "split",
        4000,
        FormFactorMethod::Hierarchical(HierarchyParams {
            two_sided,
            ..Default::default()
        }),
    );
    let h = b.manifest().hierarchy.clone().unwrap();
    assert_eq!(h.receiver_nodes, two_sided);
    let (x, centroids, _) = patch_radiance(&b, &b.manifest().lights.clone());
    let (mut lit, mut dark) = ((0.0f64, 0usize), (0.0f64, 0usize));
    for (c, v) in centroids.iter().zip(&x) {
        let y = v[0] as f64;
        if c[0] < 0.99 {
            lit = (lit.0 + y, lit.1 + 1);
        } else if c[0] > 1.01 {
            dark = (dark.0 + y, dark.1 + 1);
        }
    }
    let (lit, dark) = (lit.0 / lit.1 as f64, dark.0 / dark.1 as f64);
    eprintln!("mean radiance: lit side {lit:.3e}, dark side {dark:.3e}");
    assert!(lit > 0.0 && dark <= 1e-3 * lit, "{dark} vs {lit}");
}

/// A lamp inside a bowl on a table (below the rim): with an opaque bowl the outside of the
/// bowl and the table stay dark under a hierarchical F (the inner and outer faces of the
/// wall are in different clusters); with a translucent bowl light reaches the outside only
/// through S, as much as with a dense F.
#[test]
fn a_lamp_inside_a_bowl_reaches_the_outside_only_through_s() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (radius, thickness) = (0.1f32, 0.008f32);
    let scene = |material: serde_json::Value| {
        json!({
            "objects": [
                {"name": "table", "mesh": {"shape": "quad", "size": [1, 1]},
                 "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
                {"name": "bowl",
                 "mesh": {"shape": "bowl", "radius": radius, "thickness": thickness},
                 "material": material},
            ],
            "lights": [{"type": "point", "position": [0, 0.05, 0], "intensity": [1, 1, 1]}],
        })
    };
    // Mean radiance (red) of the bowl's inner face, its outer face, and the table beyond it.
    let regions = |b: &Bundle| -> [f64; 3] {
        let (x, centroids, normals) = patch_radiance(b, &b.manifest().lights.clone());
        let mut acc = [(0.0f64, 0usize); 3];
        let centre = [0.0, radius, 0.0];
        for ((c, n), v) in centroids.iter().zip(&normals).zip(&x) {
            let out: [f32; 3] = std::array::from_fn(|k| c[k] - centre[k]);
            let r = out.iter().map(|v| v * v).sum::<f32>().sqrt();
            let k = if c[1] < 1e-4 {
                if c[0].hypot(c[2]) < radius * 1.02 {
                    continue;
                }
                2
            } else if r < radius - 0.5 * thickness && c[1] < radius - 1e-4 {
                0
            } else if c[1] < radius - 1e-4 && (0..3).map(|k| n[k] * out[k]).sum::<f32>() > 0.0 {
                1
            } else {
                continue;
            };
            acc[k] = (acc[k].0 + v[0] as f64, acc[k].1 + 1);
        }
        acc.map(|(s, n)| {
            assert!(n > 0, "a region has no patches");
            s / n as f64
        })
    };
    let hierarchical = || FormFactorMethod::Hierarchical(HierarchyParams::default());

    let grey = json!({"type": "diffuse", "albedo": [0.8, 0.8, 0.8]});
    std::fs::write(d.join("opaque.json"), scene(grey).to_string()).unwrap();
    let loaded = load_scene_file(&d.join("opaque.json")).unwrap();
    let b = bundle_with(&loaded, d, "opaque", 4000, hierarchical());
    let [inside, outside, table] = regions(&b);
    eprintln!("opaque bowl: inside {inside:.3e}, outside {outside:.3e}, table {table:.3e}");
    assert!(inside > 0.0, "the inside is lit");
    assert!(outside <= 1e-3 * inside, "{outside} vs {inside}");
    assert!(table <= 1e-3 * inside, "{table} vs {inside}");

    let milk = json!({"type": "translucent", "profile": {"type": "dipole", "preset": "skimmilk"}});
    std::fs::write(d.join("milk.json"), scene(milk).to_string()).unwrap();
    let loaded = load_scene_file(&d.join("milk.json")).unwrap();
    let h = regions(&bundle_with(&loaded, d, "milk_h", 4000, hierarchical()));
    let dense = regions(&bundle_with(
        &loaded,
        d,
        "milk_d",
        4000,
        FormFactorMethod::Dense,
    ));
    eprintln!("translucent bowl (inside, outside, table): hierarchical {h:?}, dense {dense:?}");
    assert!(
        h[1] > 1e-3 * h[0],
        "S carries light through the wall: {h:?}"
    );
    for k in 0..3 {
        assert!(
            (h[k] - dense[k]).abs() <= 0.05 * dense[k],
            "region {k}: hierarchical {} against dense {}",
            h[k],
            dense[k]
        );
    }
}

/// The lone cube's medium inside a closed room: a 64 mm room of six quads facing in (the
/// wall at −x red, the one at +x green, the rest white), the 16 mm cube floating at its
/// centre, lit from one side by a point light between the cube's +x face and the green
/// wall. Light reaches the cube from the lamp (collimated entry) and from every wall (the
/// inter-reflected entry), and leaves it onto the walls; the simulated S at its defaults
/// (no `"noise"`, no `"lamp_walks"`). Faces `far (-x)`, `lit (+x)`, `top (+y)`,
/// `side (+z)`, `bottom (-y)`, `side (-z)`, then `walls`.
fn cube_in_a_coloured_room() -> Option<Vec<(String, Errors, Errors)>> {
    const ROOM: f32 = 0.064;
    const CUBE: f32 = 0.016;
    let c = 0.5 * ROOM;
    let wall = |name: &str, rotate: [f32; 3], at: [f32; 3], albedo: [f32; 3]| {
        json!({"name": name, "mesh": {"shape": "quad", "size": [ROOM, ROOM]},
               "transform": {"rotate_deg": rotate, "translate": at},
               "material": {"type": "diffuse", "albedo": albedo}})
    };
    let white = [0.7, 0.7, 0.7];
    let walls = vec![
        wall("floor", [0.0, 0.0, 0.0], [c, 0.0, c], white),
        wall("ceiling", [180.0, 0.0, 0.0], [c, ROOM, c], white),
        wall("back", [90.0, 0.0, 0.0], [c, c, 0.0], white),
        wall("front", [-90.0, 0.0, 0.0], [c, c, ROOM], white),
        wall("left", [0.0, 0.0, -90.0], [0.0, c, c], [0.7, 0.2, 0.15]),
        wall("right", [0.0, 0.0, 90.0], [ROOM, c, c], [0.2, 0.6, 0.2]),
    ];
    let half = 0.5 * CUBE + 1e-5;
    lone_object_against_volpath(
        &LoneObject {
            title: "16 mm cube in a closed 64 mm room of coloured walls, lit on +x by a point light",
            object: "cube",
            medium: Medium {
                sigma_s_prime: [0.8, 0.6, 0.5],
                sigma_a: [0.01, 0.02, 0.04],
            },
            noise: None,
            patches: 6000,
            lights: json!([{"type": "point", "position": [c + 0.02, c, c], "intensity": [0.05, 0.05, 0.05]}]),
            probes: 100,
            spp: 2048,
            deep: &[(0, 16384)],
            whole: &[0, 1, 2, 3, 4, 5],
            seed: 11,
            names: &[
                "far (-x)",
                "lit (+x)",
                "top (+y)",
                "side (+z)",
                "bottom (-y)",
                "side (-z)",
                "walls",
            ],
            lamp_walks: None,
            shared: None,
        },
        &|m| {
            let mut objects = walls.clone();
            objects.push(
                json!({"name": "cube", "mesh": {"shape": "box", "size": [CUBE, CUBE, CUBE]},
                "transform": {"translate": [c, c, c]},
                "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}}),
            );
            let mut file: SceneFile =
                serde_json::from_value(json!({ "objects": objects })).unwrap();
            file.objects.last_mut().unwrap().material = m;
            file
        },
        &|p, n| {
            if (0..3).any(|a| (p[a] - c).abs() > half) {
                return 6;
            }
            box_face(n)
        },
    )
}

/// The simulated S in a closed room against Mitsuba's volumetric path tracer, at its
/// defaults and without `"lamp_walks"`: every face group's median within 5% and its total
/// within 5%, the walls' too, and every face of the cube closer to Mitsuba than the dipole.
/// The far face is held to 5% at its patch centroids too, the patches along its four edges
/// included: their light enters the sides from the room's bright half and crosses the
/// corner, unscattered as often as not (U's own tilt, docs/transport.md; without it the
/// far face reads 5.1%, all of it within 1.5 mm of the edges).
#[test]
fn a_cube_in_a_closed_room_of_coloured_walls_against_volumetric_path_tracing() {
    let Some(groups) = cube_in_a_coloured_room() else {
        return;
    };
    assert_eq!(groups.len(), 8, "seven groups and the far face's vertices");
    for (name, ed, es) in &groups {
        assert!(
            es.counted >= 10 && es.reference_noise < 0.02,
            "{name}: too few points or Mitsuba too noisy: {es:?}"
        );
        assert!(
            (es.total_ratio - 1.0).abs() < 0.05,
            "{name}: simulated {es:?} (total)"
        );
        assert!(es.median < 0.05, "{name}: simulated {es:?}");
        if name != "walls" && !name.starts_with("lit") {
            assert!(
                es.median < ed.median,
                "{name}: simulated {es:?} is not closer to Mitsuba than the dipole {ed:?}"
            );
        }
    }
}
