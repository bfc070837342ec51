//! `translux-precompute` as a user runs it: real process, real files, exit codes and
//! messages. Physics lives in `physics.rs`; module behaviour in the modules' unit tests.

use std::path::Path;
use std::process::{Command, Output};

use translux_proto::bundle::Bundle;

fn precompute(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_translux-precompute"))
        .args(args)
        .output()
        .expect("the binary runs")
}

fn text(o: &Output) -> String {
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
