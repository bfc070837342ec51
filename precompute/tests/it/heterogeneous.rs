//! Heterogeneous objects through the whole pipeline: the checkerboard block of the paper's
//! Fig. 7 (`builtin:cornell_checker`), media by OBJ material (`usemtl`), per-medium lengths
//! in the bundle, eq. 9 assembly and rebuilds.

use translux_engine::smatrix::{self, SError, SParams};
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::{load_scene, load_scene_file};
use translux_proto::bundle::{Bundle, arrays};
use translux_proto::scene::{Material, Pattern, Profile};

fn build(spec: &str, dir: &std::path::Path, name: &str, patches: u64) -> Bundle {
    let scene = load_scene(spec).unwrap();
    let out = dir.join(name);
    let params = PrecomputeParams {
        patches: Some(patches),
        ..Default::default()
    };
    precompute(&scene, &out, &params).unwrap();
    Bundle::open(&out).unwrap()
}

fn object(b: &Bundle, name: &str) -> (usize, std::ops::Range<usize>) {
    let m = b.manifest();
    let k = m.objects.iter().position(|o| o.name == name).unwrap();
    let o = &m.objects[k];
    (
        k,
        o.first_patch as usize..(o.first_patch + o.patch_count) as usize,
    )
}

fn marble() -> Profile {
    Profile::Dipole {
        preset: Some("marble".into()),
        sigma_a: None,
        sigma_s_prime: None,
        eta: None,
        scale: None,
    }
}

/// Σ_j A_j S_ji / A_i per column i and channel.
fn column_energy(row_ptr: &[u64], col: &[u32], val: &[[f32; 3]], area: &[f32]) -> Vec<[f64; 3]> {
    let mut out = vec![[0.0f64; 3]; area.len()];
    for j in 0..area.len() {
        for e in row_ptr[j] as usize..row_ptr[j + 1] as usize {
            let i = col[e] as usize;
            for c in 0..3 {
                out[i][c] += f64::from(area[j]) * f64::from(val[e][c]) / f64::from(area[i]);
            }
        }
    }
    out
}

#[test]
fn cornell_checker_block_is_a_checkerboard_of_two_media() {
    let dir = tempfile::tempdir().unwrap();
    let het = build("builtin:cornell_checker", dir.path(), "checker", 1500);
    let hom = build("builtin:cornell_paper", dir.path(), "cornell", 1500);
    let n = het.manifest().patch_count as usize;
    assert_eq!(
        n,
        hom.manifest().patch_count as usize,
        "same geometry, same patches"
    );
    let (k, block) = object(&het, "tall_block");
    assert!(matches!(
        het.manifest().objects[k].material,
        Material::Heterogeneous { .. }
    ));
    let info = &het.manifest().subsurface.objects;
    assert_eq!(info.len(), 1);
    assert_eq!(info[0].method, "euclidean");

    // Patch media: both, only on the block.
    let media = het.u32s(arrays::PATCH_MATERIAL);
    assert_eq!(media.len(), n);
    let orange = block.clone().filter(|&p| media[p] == 1).count();
    assert!(
        orange > block.len() / 4 && orange < 3 * block.len() / 4,
        "{orange} of {}",
        block.len()
    );
    assert!((0..n).filter(|p| !block.contains(p)).all(|p| media[p] == 0));
    // The per-patch albedo of the inter-reflection-only view follows the pattern.
    let albedo = het.patch_albedo();
    let (m0, m1) = (
        block.clone().find(|&p| media[p] == 0).unwrap(),
        block.clone().find(|&p| media[p] == 1).unwrap(),
    );
    assert!(
        albedo[m1][2] < 0.5 * albedo[m0][2],
        "{:?} {:?}",
        albedo[m0],
        albedo[m1]
    );

    // Per-medium lengths: one row of 4 per distance, summing to it; both media in use, and
    // some paths crossing from one to the other.
    let d = het.distances();
    let lens: &[[f32; 4]] = bytemuck::cast_slice(het.f32s(arrays::DIST_MATERIAL_LEN));
    assert_eq!(lens.len(), d.nnz());
    let (mut mixed, mut pure) = (0, 0);
    for (l, &r) in lens.iter().zip(d.val()) {
        let sum: f32 = l.iter().sum();
        assert!((sum - r).abs() <= 1e-5 * r.max(1e-6), "{l:?} vs {r}");
        assert_eq!((l[2], l[3]), (0.0, 0.0));
        if l[0] > 0.0 && l[1] > 0.0 {
            mixed += 1;
        } else {
            pure += 1;
        }
    }
    eprintln!(
        "cornell_checker: {} block patches ({orange} orange), {} distances ({mixed} crossing \
         a cell plane), S nnz {}, max column energy {:.4}",
        block.len(),
        d.nnz(),
        het.subsurface().nnz(),
        info[0].max_column_energy
    );
    assert!(mixed > 100 && pure > 100, "{mixed} mixed, {pure} pure");

    // The block's S differs from the homogeneous marble block's: the orange patches
    // re-emit far less blue; the marble patches stay as they were on the diagonal.
    let (sh, sm) = (het.subsurface(), hom.subsurface());
    let diag = |s: &translux_proto::csr::CsrView<'_, [f32; 3]>, p: usize| {
        let (cols, vals) = s.row(p);
        vals[cols.binary_search(&(p as u32)).unwrap()]
    };
    let (mut lower, mut same) = (0, 0);
    for p in block.clone() {
        let (a, b) = (diag(&sh, p), diag(&sm, p));
        if media[p] == 1 {
            assert!(a[2] < 0.5 * b[2], "patch {p}: {a:?} vs marble {b:?}");
            lower += 1;
        } else if (a[2] - b[2]).abs() <= 1e-6 * b[2] {
            same += 1;
        }
    }
    assert_eq!(lower, orange);
    assert_eq!(same, block.len() - orange);
    // Outside the block nothing changed.
    for p in (0..n).filter(|p| !block.contains(p)) {
        assert_eq!(sh.row(p), sm.row(p), "patch {p}");
    }

    // Energy: no column re-emits more than it receives.
    let e = column_energy(sh.row_ptr(), sh.col(), sh.val(), het.patch_areas());
    for p in block.clone() {
        assert!(
            e[p].iter().all(|&x| x <= 1.0 + 1e-5),
            "column {p}: {:?}",
            e[p]
        );
    }
    assert!(info[0].max_column_energy <= 1.0);

    // Rebuilding S from the bundle with the built media gives the precomputed S.
    let built = het.manifest().objects[k].material.clone();
    let (s, _) = smatrix::rebuild_from_bundle(&het, &[(k, built)], &SParams::default()).unwrap();
    assert_eq!(s.row_ptr, sh.row_ptr());
    assert_eq!(s.col, sh.col());
    for (x, y) in s.val.iter().zip(sh.val()) {
        for c in 0..3 {
            assert!(
                (x[c] - y[c]).abs() <= 1e-5 * y[c].abs().max(1e-12),
                "{x:?} vs {y:?}"
            );
        }
    }

    // Both media marble: exactly the homogeneous marble block (eq. 9 after merging equal
    // media), from the same stored lengths.
    let Material::Heterogeneous { pattern, .. } = &het.manifest().objects[k].material else {
        unreachable!()
    };
    let twins = Material::Heterogeneous {
        materials: vec![marble(), marble()],
        pattern: pattern.clone(),
        specular: None,
    };
    let (s, _) = smatrix::rebuild_from_bundle(&het, &[(k, twins)], &SParams::default()).unwrap();
    assert_eq!(s.row_ptr, sm.row_ptr(), "different sparsity");
    assert_eq!(s.col, sm.col());
    for (x, y) in s.val.iter().zip(sm.val()) {
        for c in 0..3 {
            assert!(
                (x[c] - y[c]).abs() <= 1e-5 * y[c].abs().max(1e-12),
                "{x:?} vs {y:?}"
            );
        }
    }

    // A medium's profile can change (here: the orange one twice as translucent) ...
    let Material::Heterogeneous { materials, .. } = &het.manifest().objects[k].material else {
        unreachable!()
    };
    let mut softer = materials.clone();
    if let Profile::Dipole { scale, .. } = &mut softer[1] {
        *scale = Some(2.0);
    }
    let (s2, reports) = smatrix::rebuild_from_bundle(
        &het,
        &[(
            k,
            Material::Heterogeneous {
                materials: softer,
                pattern: pattern.clone(),
                specular: None,
            },
        )],
        &SParams::default(),
    )
    .unwrap();
    assert_eq!(reports.len(), 1);
    assert!(s2.val != sh.val().to_vec());
    // ... but not the pattern: its lengths are geometry.
    let moved = Material::Heterogeneous {
        materials: materials.clone(),
        pattern: Pattern::Checkerboard {
            cell: 0.05,
            origin: [0.0; 3],
        },
        specular: None,
    };
    let e = smatrix::rebuild_from_bundle(&het, &[(k, moved)], &SParams::default()).unwrap_err();
    assert!(matches!(e, SError::Media { .. }), "{e}");
    assert!(e.to_string().contains("same pattern"), "{e}");
    // Nor can a homogeneous bundle's block become heterogeneous.
    let (kh, _) = object(&hom, "tall_block");
    let e = smatrix::rebuild_from_bundle(
        &hom,
        &[(kh, het.manifest().objects[k].material.clone())],
        &SParams::default(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("precomputed as translucent"), "{e}");
    // A heterogeneous bundle's block can become homogeneous (distances are all it needs).
    let (s, _) = smatrix::rebuild_from_bundle(
        &het,
        &[(
            k,
            Material::Translucent {
                profile: marble(),
                specular: None,
            },
        )],
        &SParams::default(),
    )
    .unwrap();
    assert_eq!(s.col, sm.col());
}

/// A 0.2 × 0.1 × 0.1 bar of two cubes side by side (x < 0 and x > 0), each cube's faces in
/// its own `usemtl` group; the long faces are split at x = 0 so every face is in one cube.
fn two_cube_obj(left: &str, right: &str, header: &str) -> String {
    let mut s = String::from(header);
    for x in [-0.1, 0.0, 0.1] {
        for y in [0.0, 0.1] {
            for z in [-0.05, 0.05] {
                s += &format!("v {x} {y} {z}\n");
            }
        }
    }
    // Vertex (ix, iy, iz) is 1 + 4 ix + 2 iy + iz.
    let v = |ix: usize, iy: usize, iz: usize| 1 + 4 * ix + 2 * iy + iz;
    for (cube, name) in [(0usize, left), (1, right)] {
        s += &format!("usemtl {name}\n");
        let (a, b) = (cube, cube + 1);
        let mut quad = |p: [usize; 4]| s += &format!("f {} {} {} {}\n", p[0], p[1], p[2], p[3]);
        // Counter-clockwise seen from outside.
        quad([v(a, 0, 0), v(b, 0, 0), v(b, 0, 1), v(a, 0, 1)]); // bottom (−y)
        quad([v(a, 1, 0), v(a, 1, 1), v(b, 1, 1), v(b, 1, 0)]); // top (+y)
        quad([v(a, 0, 0), v(a, 1, 0), v(b, 1, 0), v(b, 0, 0)]); // back (−z)
        quad([v(a, 0, 1), v(b, 0, 1), v(b, 1, 1), v(a, 1, 1)]); // front (+z)
        if cube == 0 {
            quad([v(0, 0, 0), v(0, 0, 1), v(0, 1, 1), v(0, 1, 0)]); // left end (−x)
        } else {
            quad([v(2, 0, 0), v(2, 1, 0), v(2, 1, 1), v(2, 0, 1)]); // right end (+x)
        }
    }
    s
}

fn bar_scene(dir: &std::path::Path, names: &str) -> std::path::PathBuf {
    let scene = format!(
        r#"{{"objects":[
            {{"name":"floor","mesh":{{"shape":"quad","size":[1,1]}},
              "material":{{"type":"diffuse","albedo":[0.5,0.5,0.5]}}}},
            {{"name":"bar","mesh":"bar.obj","transform":{{"translate":[0,0.01,0]}},
              "material":{{"type":"heterogeneous",
                "materials":[{{"type":"dipole","preset":"skimmilk","scale":20}},
                             {{"type":"dipole","preset":"ketchup","scale":20}}],
                "pattern":{{"type":"by_obj_material","names":{names}}}}}}}],
           "lights":[{{"type":"point","position":[0,1,0],"intensity":[1,1,1]}}],
           "patches":{{"target":900}}}}"#
    );
    let path = dir.join("scene.json");
    std::fs::write(&path, scene).unwrap();
    path
}

#[test]
fn media_by_obj_material_follow_the_usemtl_groups() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("bar.obj"),
        two_cube_obj("white", "orange", "mtllib nowhere.mtl\n"),
    )
    .unwrap();
    let path = bar_scene(dir.path(), r#"["white","orange"]"#);
    let scene = load_scene_file(&path).unwrap();
    let bar = scene.objects.iter().find(|o| o.name == "bar").unwrap();
    let faces = bar.face_material.as_ref().expect("face media");
    assert_eq!(faces.len(), bar.triangles.len());
    for (t, &m) in bar.triangles.iter().zip(faces) {
        let cx = (t[0].x + t[1].x + t[2].x) / 3.0;
        assert_eq!(m, u32::from(cx > 0.0), "face at x = {cx}");
    }
    assert!(
        scene
            .objects
            .iter()
            .find(|o| o.name == "floor")
            .unwrap()
            .face_material
            .is_none()
    );

    let out = dir.path().join("b");
    precompute(&scene, &out, &PrecomputeParams::default()).unwrap();
    let b = Bundle::open(&out).unwrap();
    let (_, range) = object(&b, "bar");
    let media = b.u32s(arrays::PATCH_MATERIAL);
    let corners = b.patch_corners();
    for p in range.clone() {
        let cx = (corners[p][0][0] + corners[p][1][0] + corners[p][2][0]) / 3.0;
        assert_eq!(media[p], u32::from(cx > 0.0), "patch {p} at x = {cx}");
    }
    let info = &b.manifest().subsurface.objects[0];
    assert_eq!(info.method, "voxel", "per-patch media take the voxel route");
    assert!(info.max_column_energy <= 1.0);
    let lens: &[[f32; 4]] = bytemuck::cast_slice(b.f32s(arrays::DIST_MATERIAL_LEN));
    let d = b.distances();
    let crossing = lens.iter().filter(|l| l[0] > 0.0 && l[1] > 0.0).count();
    assert!(crossing > 0);
    for (l, &r) in lens.iter().zip(d.val()) {
        assert!((l.iter().sum::<f32>() - r).abs() <= 1e-5 * r.max(1e-6));
    }
    // A patch pair on the far ends of the bar, both on the left half, is all in medium 0.
    for i in range.clone() {
        let (cols, _) = d.row(i);
        let xi = (corners[i][0][0] + corners[i][1][0] + corners[i][2][0]) / 3.0;
        for (e, &j) in cols.iter().enumerate() {
            let j = j as usize;
            let xj = (corners[j][0][0] + corners[j][1][0] + corners[j][2][0]) / 3.0;
            if xi < -0.03 && xj < -0.03 {
                let l = lens[d.row_ptr()[i] as usize + e];
                assert_eq!(l[1], 0.0, "{i} → {j}: {l:?}");
            }
        }
    }
}

#[test]
fn usemtl_groups_must_all_be_named() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("bar.obj"),
        two_cube_obj("white", "orange", ""),
    )
    .unwrap();
    let path = bar_scene(dir.path(), r#"["white","red"]"#);
    let e = load_scene_file(&path).unwrap_err().to_string();
    assert!(
        e.contains("objects[1].material.pattern.names do not list \"orange\", the `usemtl` material of 10 faces of mesh \"bar.obj\""),
        "{e}"
    );
    // Faces before any usemtl cannot be placed.
    let obj = two_cube_obj("white", "orange", "").replacen("usemtl white\n", "", 1);
    std::fs::write(dir.path().join("bar.obj"), obj).unwrap();
    let path = bar_scene(dir.path(), r#"["white","orange"]"#);
    let e = load_scene_file(&path).unwrap_err().to_string();
    assert!(
        e.contains("objects[1].material.pattern.names cannot place 10 faces of mesh \"bar.obj\" that come before any `usemtl`"),
        "{e}"
    );
}
