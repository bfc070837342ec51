//! `translux-precompute` as a user runs it: real process, real files, exit codes and
//! messages. Physics lives in `physics.rs`; module behaviour in the modules' unit tests.

use std::path::Path;
use std::process::{Command, Output};

use translux_proto::bundle::Bundle;

pub(crate) fn precompute(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_translux-precompute"))
        .args(args)
        .output()
        .expect("the binary runs")
}

pub(crate) fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

fn write(path: &Path, body: &str) {
    std::fs::write(path, body).unwrap();
}

#[test]
fn builtin_cornell_becomes_a_verified_bundle_with_a_summary() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cornell");
    let o = precompute(&[
        "builtin:cornell",
        "--out",
        out.to_str().unwrap(),
        "--patches",
        "600",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let t = text(&o);
    for field in [
        "patches",
        "nnz(F)",
        "bundle",
        "form factors",
        "peak memory",
        "rays",
    ] {
        assert!(t.contains(field), "summary lacks {field}: {t}");
    }
    let b = Bundle::open(&out).unwrap();
    let m = b.manifest();
    assert!((540..=660).contains(&m.patch_count), "{}", m.patch_count);
    assert_eq!(m.source, "builtin:cornell");
    let names: Vec<_> = m.objects.iter().map(|o| o.name.as_str()).collect();
    assert!(
        names.contains(&"tall_block") && names.contains(&"left_wall"),
        "{names:?}"
    );
    // A closed room: row sums average near 1 (patches under the boxes see nothing).
    assert!(
        m.form_factors.row_sum_mean > 0.9 && m.form_factors.row_sum_max < 1.05,
        "{:?}",
        m.form_factors
    );
    assert_eq!(b.form_factors().nnz() as u64, m.form_factors.nnz);
    // No temporary folders left beside the bundle.
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(left.len(), 1, "{left:?}");
}

/// `--transport hierarchical`: a bundle with the cluster tree, a summary that says what it
/// stores against dense F, and an accuracy out of range refused by name with nothing
/// written.
#[test]
fn hierarchical_transport_from_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cornell");
    let args = |extra: &[&'static str]| {
        let mut a = vec![
            "builtin:cornell".to_string(),
            "--out".into(),
            out.to_str().unwrap().into(),
            "--patches".into(),
            "800".into(),
            "--transport".into(),
            "hierarchical".into(),
        ];
        a.extend(extra.iter().map(|s| s.to_string()));
        a
    };
    for bad in [
        "--accuracy=0",
        "--accuracy=1.5",
        "--accuracy=-0.2",
        "--accuracy=NaN",
    ] {
        let a = args(&[bad]);
        let o = precompute(&a.iter().map(String::as_str).collect::<Vec<_>>());
        assert_eq!(o.status.code(), Some(1), "{}", text(&o));
        assert!(
            text(&o).contains("--accuracy must be in [0.02, 1]"),
            "{}",
            text(&o)
        );
        assert!(!out.exists());
    }
    let a = args(&["--accuracy", "0.3"]);
    let o = precompute(&a.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(o.status.success(), "{}", text(&o));
    let t = text(&o);
    assert!(
        t.contains("hierarchical F̃ = C·P, accuracy 0.3") && t.contains("cluster tree"),
        "{t}"
    );
    let b = Bundle::open(&out).unwrap();
    let h = b.manifest().hierarchy.clone().unwrap();
    assert_eq!(h.accuracy, 0.3);
    let n = b.manifest().patch_count;
    assert_eq!(h.nodes, n - 1);
    assert_eq!(b.form_factors().n_cols() as u64, n + h.nodes);
    assert!(h.dense_equivalent > b.form_factors().nnz() as u64, "{h:?}");
}

#[test]
fn hierarchical_subsurface_from_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cornell");
    let run = |extra: &[&str]| {
        let mut a = vec![
            "builtin:cornell",
            "--out",
            out.to_str().unwrap(),
            "--patches",
            "800",
        ];
        a.extend_from_slice(extra);
        precompute(&a)
    };
    for (bad, says) in [
        (
            &["--subsurface", "hierarchical", "--s-accuracy", "0"][..],
            "--s-accuracy must be in [0.05, 1]",
        ),
        (
            &["--subsurface", "hierarchical", "--s-accuracy", "NaN"][..],
            "--s-accuracy must be in",
        ),
        (
            &["--subsurface", "hierarchical", "--transport", "dense"][..],
            "cannot be used with --transport dense",
        ),
        (
            &["--subsurface", "hierarchical", "--inverse"][..],
            "--inverse needs a pairwise S",
        ),
        (
            &["--subsurface", "hierarchical", "--s-link-near", "0.5"][..],
            "--s-link-near must be in [1, 3]",
        ),
        (
            &["--s-link-near", "inf"][..],
            "--s-link-near must be in [1, 3]",
        ),
        (&["--subsurface", "octree"][..], "invalid value 'octree'"),
    ] {
        let o = run(bad);
        assert_ne!(o.status.code(), Some(0), "{}", text(&o));
        assert!(text(&o).contains(says), "{bad:?}: {}", text(&o));
        assert!(!out.exists());
    }
    let o = run(&["--subsurface", "hierarchical"]);
    assert!(o.status.success(), "{}", text(&o));
    let b = Bundle::open(&out).unwrap();
    // The Cornell block's profile barely reaches past the near field at 800 patches: the
    // bundle is valid either way, and says how many links it holds.
    let m = b.manifest();
    assert_eq!(
        b.subsurface().n_cols() as u64,
        m.patch_count
            + if m.subsurface.links > 0 {
                m.hierarchy.as_ref().unwrap().nodes
            } else {
                0
            }
    );
}

/// By default (`--subsurface auto`) a translucent object's S is hierarchical, as the
/// default transport allows; `--inverse` (T needs a pairwise S), `--transport dense` and
/// `--subsurface pairwise` keep it pair by pair.
#[test]
fn the_default_subsurface_is_hierarchical_where_it_can_be() {
    let dir = tempfile::tempdir().unwrap();
    write(
        &dir.path().join("scene.json"),
        r#"{
          "unit_mm": 1,
          "patches": {"target": 1200},
          "objects": [
            {"name": "cube", "mesh": {"shape": "box", "size": [40, 40, 40]},
             "material": {"type": "translucent",
                          "profile": {"type": "dipole", "preset": "skimmilk"}}}
          ],
          "lights": [{"type": "point", "position": [0, 100, 0], "intensity": [1, 1, 1]}]
        }"#,
    );
    let scene = dir.path().join("scene.json");
    let built = |extra: &[&str]| {
        let out = dir
            .path()
            .join(format!("b{}", extra.join("_").replace('-', "")));
        let mut a = vec![scene.to_str().unwrap(), "--out", out.to_str().unwrap()];
        a.extend_from_slice(extra);
        let o = precompute(&a);
        assert!(o.status.success(), "{extra:?}: {}", text(&o));
        Bundle::open(&out).unwrap()
    };
    let links = |extra: &[&str]| {
        let b = built(extra);
        (
            b.manifest().subsurface.links,
            b.manifest().transfer.is_some(),
        )
    };
    let (by_default, _) = links(&[]);
    assert!(by_default > 0, "the default S has no links");
    assert_eq!(links(&["--subsurface", "pairwise"]), (0, false));
    assert_eq!(links(&["--inverse", "--subsurface", "auto"]), (0, true));
    assert_eq!(
        links(&["--transport", "dense", "--subsurface", "auto", "-q"]).0,
        0
    );
    // Links from 1 receiver size, each read at two distances: every stored distance has
    // its spread.
    let near = built(&["-q"]);
    assert_eq!(near.manifest().subsurface.link_near, Some(1.0));
    assert_eq!(
        near.distance_spreads().len() as u64,
        near.manifest().subsurface.distance_nnz
    );
    // A number of receiver sizes, nothing else.
    for bad in ["off", "near"] {
        let o = precompute(&[
            scene.to_str().unwrap(),
            "--out",
            dir.path().join("never").to_str().unwrap(),
            "--s-link-near",
            bad,
        ]);
        assert!(!o.status.success());
        assert!(
            text(&o).contains(&format!("invalid value '{bad}' for '--s-link-near")),
            "{}",
            text(&o)
        );
    }
}

#[test]
fn a_users_scene_file_with_an_obj_becomes_a_bundle() {
    let dir = tempfile::tempdir().unwrap();
    // A unit tetrahedron (outward faces) standing on a floor, in millimetres.
    write(
        &dir.path().join("tet.obj"),
        "v 0 0 0\nv 100 0 0\nv 0 0 100\nv 0 100 0\nf 1 2 3\nf 1 4 2\nf 1 3 4\nf 2 4 3\n",
    );
    write(
        &dir.path().join("scene.json"),
        r#"{
          "unit_mm": 1,
          "patches": {"target": 400},
          "objects": [
            {"name": "floor", "mesh": {"shape": "quad", "size": [400, 400]},
             "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
            {"name": "tet", "mesh": "tet.obj", "transform": {"translate": [-30, 0, -30]},
             "material": {"type": "diffuse", "albedo": [0.8, 0.2, 0.2]}}
          ],
          "lights": [{"type": "point", "position": [0, 300, 0], "intensity": [1, 1, 1]}]
        }"#,
    );
    let out = dir.path().join("bundles").join("tet");
    let o = precompute(&[
        dir.path().join("scene.json").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let b = Bundle::open(&out).unwrap();
    assert_eq!(b.manifest().name, "scene");
    assert_eq!(b.manifest().unit_mm, 1.0);
    assert_eq!(b.manifest().objects[1].name, "tet");
    // The tetrahedron sees the floor and the floor sees it.
    assert!(b.manifest().form_factors.nnz > 0);
}

#[test]
fn bad_input_is_refused_with_a_message_and_no_bundle() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let o_str = out.to_str().unwrap();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (
            vec!["builtin:cornell".into(), "--patches".into(), "0".into()],
            "--patches 0",
        ),
        (
            vec![
                "builtin:cornell".into(),
                "--patches".into(),
                "100000000".into(),
            ],
            "too many",
        ),
        (
            vec![
                "builtin:cornell".into(),
                "--patches".into(),
                "2000".into(),
                "--max-memory-gib".into(),
                "0.001".into(),
            ],
            "MiB",
        ),
        (vec!["builtin:nowhere".into()], "nowhere"),
        (
            vec![dir.path().join("missing.json").to_str().unwrap().into()],
            "missing.json",
        ),
        (
            // The dense LU of T at the default 24,640 patches needs ~13 GiB.
            vec![
                "builtin:cornell".into(),
                "--inverse".into(),
                "--max-memory-gib".into(),
                "2".into(),
            ],
            "--inverse: the transfer matrix for",
        ),
        (
            vec!["builtin:cornell".into(), "--threshold".into(), "NaN".into()],
            "--threshold",
        ),
    ];
    for (mut args, needle) in cases {
        args.extend(["--out".to_string(), o_str.to_string()]);
        let refs: Vec<&str> = args.iter().map(|s| s.as_str()).collect();
        let o = precompute(&refs);
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{args:?}: {t}");
        assert!(
            t.contains(needle),
            "{args:?}: message lacks {needle:?}: {t}"
        );
        assert!(!t.contains("panicked"), "{t}");
        assert!(!out.exists(), "{args:?} left a bundle behind");
    }

    // A malformed OBJ names the mesh file and the line.
    write(
        &dir.path().join("bad.obj"),
        "v 0 0 0\nv 1 0 0\nv 0 banana 1\nf 1 2 3\n",
    );
    write(
        &dir.path().join("bad.json"),
        r#"{"objects":[{"name":"thing","mesh":"bad.obj","material":{"type":"diffuse","albedo":[0.5,0.5,0.5]}}]}"#,
    );
    let o = precompute(&[
        dir.path().join("bad.json").to_str().unwrap(),
        "--out",
        o_str,
    ]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("bad.obj") && t.contains("thing"), "{t}");
    assert!(!out.exists());

    // Usage errors are clap's (exit 2).
    let o = precompute(&["builtin:cornell"]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
}

#[test]
fn an_existing_folder_that_is_not_a_bundle_is_not_overwritten() {
    let dir = tempfile::tempdir().unwrap();
    let precious = dir.path().join("precious");
    std::fs::create_dir(&precious).unwrap();
    write(&precious.join("notes.txt"), "keep me");
    let o = precompute(&[
        "builtin:cornell",
        "--patches",
        "200",
        "--out",
        precious.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert_eq!(
        std::fs::read_to_string(precious.join("notes.txt")).unwrap(),
        "keep me"
    );
    // An existing bundle, though, is replaced.
    let out = dir.path().join("b");
    for patches in ["200", "300"] {
        let o = precompute(&[
            "builtin:cornell",
            "--patches",
            patches,
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", text(&o));
    }
    let n = Bundle::open(&out).unwrap().manifest().patch_count;
    assert!(n > 250, "{n}");
}

/// The memory guard covers the subsurface stage, not only F: the unsimplified bunny as one
/// marble object has almost no F (a lone, nearly convex object sees little of itself) but
/// stores every path within marble's radius, which grew to 24 GB and was killed by the
/// kernel. It is now refused up front, naming the stage, the object and the figure.
#[test]
fn a_subsurface_stage_too_big_for_memory_is_refused_up_front() {
    let dir = tempfile::tempdir().unwrap();
    let bunny = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/stanford-bunny.obj");
    assert!(
        bunny.exists(),
        "{} is missing (../shared/data)",
        bunny.display()
    );
    write(
        &dir.path().join("scene.json"),
        &format!(
            r#"{{"objects": [{{"name": "bunny", "mesh": {:?},
                 "material": {{"type": "translucent",
                              "profile": {{"type": "dipole", "preset": "marble"}}}}}}]}}"#,
            bunny.display().to_string()
        ),
    );
    let out = dir.path().join("bunny");
    let t0 = std::time::Instant::now();
    let o = precompute(&[
        dir.path().join("scene.json").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--max-memory-gib",
        "2",
        "--quiet",
    ]);
    let t = text(&o);
    assert!(!o.status.success(), "{t}");
    assert!(
        t.contains("the subsurface stage would need")
            && t.contains("\"bunny\"")
            && t.contains("GiB"),
        "{t}"
    );
    assert!(!out.exists(), "a refused precompute left a bundle");
    // Refused before any stage ran, not after minutes of work.
    assert!(t0.elapsed().as_secs() < 60, "{:?}", t0.elapsed());
}

/// The memory guard follows the F it will build: a hierarchical F is estimated from its cut
/// on sampled receivers, a refusal says how many patches would fit, and that many do: the
/// run it suggests peaks under the same limit.
#[test]
fn a_refusal_for_memory_names_a_patch_count_that_fits() {
    let dir = tempfile::tempdir().unwrap();
    let scene =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/scenes/cornell-diffuse.json");
    let scene = scene.to_str().unwrap();
    let out = dir.path().join("room");
    let limit_gib = 0.15;
    let limit = limit_gib * 1024.0 * 1024.0 * 1024.0;
    let run = |patches: &str| {
        precompute(&[
            scene,
            "--out",
            out.to_str().unwrap(),
            "--patches",
            patches,
            "--max-memory-gib",
            &limit_gib.to_string(),
            "--quiet",
        ])
    };
    let o = run("40000");
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(!out.exists(), "a refused precompute left a bundle");
    assert!(
        t.contains("entries per patch, from the cut of sampled receivers"),
        "{t}"
    );
    let fits: u64 = t
        .split("(--patches ")
        .nth(1)
        .and_then(|rest| rest.split(')').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no patch count that fits: {t}"));
    assert!((4_000..40_000).contains(&fits), "{fits}: {t}");

    let o = run(&fits.to_string());
    let t = text(&o);
    assert!(
        o.status.success(),
        "the suggested {fits} patches were refused: {t}"
    );
    let (estimate, peak) = (
        summary_bytes(&t, "memory estimate"),
        summary_bytes(&t, "peak memory (RSS)"),
    );
    assert!(
        peak <= limit,
        "the suggested run peaked at {peak} bytes, over {limit}: {t}"
    );
    // The estimate follows the run: neither the old fixed bound per patch (several times
    // the peak) nor far under it.
    assert!(
        (0.9 * peak..=1.5 * peak).contains(&estimate),
        "estimate {estimate} against a peak of {peak}: {t}"
    );
}

/// The summary's figure after `label` (`memory estimate`, `peak memory (RSS)`), in bytes.
fn summary_bytes(t: &str, label: &str) -> f64 {
    let line = t
        .lines()
        .find(|l| l.trim_start().starts_with(label))
        .unwrap_or_else(|| panic!("no {label}: {t}"));
    let mut words = line[line.find(label).unwrap() + label.len()..].split_whitespace();
    let v: f64 = words.next().unwrap().parse().unwrap();
    v * match words.next().unwrap() {
        "GiB" => 1024.0 * 1024.0 * 1024.0,
        "MiB" => 1024.0 * 1024.0,
        "KiB" => 1024.0,
        _ => 1.0,
    }
}

/// The voxel grids of objects whose paths bend through their interior count: the bowls
/// (three hollow bowls traced through 2 M voxels each, on demand, and a convex blob) at a
/// few thousand patches, where the grids and their Dijkstra state outweigh the paths. An
/// estimate without them was 0.73 of the peak on 2 threads.
#[test]
fn the_memory_estimate_counts_the_voxel_grids() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("bowls");
    let o = precompute(&[
        "builtin:bowls",
        "--out",
        out.to_str().unwrap(),
        "--patches",
        "3000",
        "--env-bins",
        "0",
        "--threads",
        "2",
        "--quiet",
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    let (estimate, peak) = (
        summary_bytes(&t, "memory estimate"),
        summary_bytes(&t, "peak memory (RSS)"),
    );
    assert!(
        (peak..=1.5 * peak).contains(&estimate),
        "estimate {estimate} against a peak of {peak}: {t}"
    );
}

/// A binary little-endian PLY with float coordinates and `int` index lists.
fn binary_ply(v: &[[f32; 3]], faces: &[&[u32]]) -> Vec<u8> {
    let mut out = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\n\
         property float y\nproperty float z\nelement face {}\n\
         property list uchar int vertex_indices\nend_header\n",
        v.len(),
        faces.len()
    )
    .into_bytes();
    for c in v.iter().flatten() {
        out.extend(c.to_le_bytes());
    }
    for f in faces {
        out.push(f.len() as u8);
        for i in *f {
            out.extend((*i as i32).to_le_bytes());
        }
    }
    out
}

/// A binary glTF of a box from `lo` to `hi` (one node, u16 indices), written by hand: the
/// 12-byte header, the JSON chunk padded with spaces, the BIN chunk.
fn box_glb(lo: [f32; 3], hi: [f32; 3]) -> Vec<u8> {
    let mut bin = Vec::new();
    for k in 0..8 {
        for (a, (l, h)) in lo.iter().zip(hi).enumerate() {
            let c = if (k >> a) & 1 == 1 { h } else { *l };
            bin.extend(c.to_le_bytes());
        }
    }
    let quads = [
        [0u16, 4, 6, 2],
        [1, 3, 7, 5],
        [0, 1, 5, 4],
        [2, 6, 7, 3],
        [0, 2, 3, 1],
        [4, 5, 7, 6],
    ];
    for q in quads {
        for i in [q[0], q[1], q[2], q[0], q[2], q[3]] {
            bin.extend(i.to_le_bytes());
        }
    }
    let json = format!(
        r#"{{"asset": {{"version": "2.0"}}, "scene": 0, "scenes": [{{"nodes": [0]}}],
  "nodes": [{{"mesh": 0}}],
  "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0}}, "indices": 1}}]}}],
  "accessors": [
    {{"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3",
      "min": {lo:?}, "max": {hi:?}}},
    {{"bufferView": 1, "componentType": 5123, "count": 36, "type": "SCALAR"}}],
  "bufferViews": [{{"buffer": 0, "byteLength": 96}},
                  {{"buffer": 0, "byteOffset": 96, "byteLength": 72}}],
  "buffers": [{{"byteLength": 168}}]}}"#
    );
    let mut j = json.into_bytes();
    while !j.len().is_multiple_of(4) {
        j.push(b' ');
    }
    let mut out = b"glTF".to_vec();
    out.extend(2u32.to_le_bytes());
    out.extend(((12 + 8 + j.len() + 8 + bin.len()) as u32).to_le_bytes());
    out.extend((j.len() as u32).to_le_bytes());
    out.extend(b"JSON");
    out.extend(j);
    out.extend((bin.len() as u32).to_le_bytes());
    out.extend(b"BIN\0");
    out.extend(bin);
    out
}

#[test]
fn a_scene_with_ply_and_glb_meshes_becomes_a_bundle() {
    let dir = tempfile::tempdir().unwrap();
    // The OBJ test's tetrahedron as binary PLY, and a box as .glb, on a floor.
    let tet = binary_ply(
        &[
            [0.0, 0.0, 0.0],
            [100.0, 0.0, 0.0],
            [0.0, 0.0, 100.0],
            [0.0, 100.0, 0.0],
        ],
        &[&[0, 1, 2], &[0, 3, 1], &[0, 2, 3], &[1, 3, 2]],
    );
    std::fs::write(dir.path().join("tet.ply"), tet).unwrap();
    std::fs::write(
        dir.path().join("block.glb"),
        box_glb([60.0, 0.0, 20.0], [120.0, 50.0, 80.0]),
    )
    .unwrap();
    write(
        &dir.path().join("scene.json"),
        r#"{
          "unit_mm": 1,
          "patches": {"target": 500},
          "objects": [
            {"name": "floor", "mesh": {"shape": "quad", "size": [400, 400]},
             "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
            {"name": "tet", "mesh": "tet.ply", "transform": {"translate": [-90, 0, -30]},
             "material": {"type": "diffuse", "albedo": [0.8, 0.2, 0.2]}},
            {"name": "block", "mesh": "block.glb",
             "material": {"type": "diffuse", "albedo": [0.2, 0.2, 0.8]}}
          ],
          "lights": [{"type": "point", "position": [0, 300, 0], "intensity": [1, 1, 1]}]
        }"#,
    );
    let out = dir.path().join("bundle");
    let o = precompute(&[
        dir.path().join("scene.json").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let b = Bundle::open(&out).unwrap();
    let m = b.manifest();
    let names: Vec<_> = m.objects.iter().map(|o| o.name.as_str()).collect();
    assert_eq!(names, ["floor", "tet", "block"]);
    assert!(m.form_factors.nnz > 0);
}

#[test]
fn a_truncated_ply_or_a_gltf_without_its_buffer_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let tet = binary_ply(
        &[
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, 1.0, 0.0],
        ],
        &[&[0, 1, 2], &[0, 3, 1], &[0, 2, 3], &[1, 3, 2]],
    );
    std::fs::write(dir.path().join("cut.ply"), &tet[..tet.len() - 6]).unwrap();
    write(
        &dir.path().join("lost.gltf"),
        r#"{"asset": {"version": "2.0"}, "nodes": [{"mesh": 0}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                           "min": [0, 0, 0], "max": [1, 1, 0]}],
            "bufferViews": [{"buffer": 0, "byteLength": 36}],
            "buffers": [{"byteLength": 36, "uri": "lost.bin"}]}"#,
    );
    let out = dir.path().join("out");
    for (mesh, problem) in [
        ("cut.ply", "ends early"),
        ("lost.gltf", "buffer 0: file \"lost.bin\""),
        ("mesh.stl", "unknown mesh format \".stl\""),
    ] {
        write(
            &dir.path().join("s.json"),
            &format!(
                r#"{{"objects":[{{"name":"thing","mesh":"{mesh}",
                   "material":{{"type":"diffuse","albedo":[0.5,0.5,0.5]}}}}]}}"#
            ),
        );
        let o = precompute(&[
            dir.path().join("s.json").to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ]);
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{t}");
        assert!(
            t.contains("s.json") && t.contains("\"thing\"") && t.contains(mesh),
            "{t}"
        );
        assert!(t.contains(problem), "wanted {problem:?}: {t}");
        assert!(!t.contains("panicked"), "{t}");
        assert!(!out.exists());
    }
}
