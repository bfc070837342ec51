//! `--shard I/K` and `--merge K` by hand, as a scheduler's tasks run them: the merged bundle
//! holds the arrays of a one-box run byte for byte, and every part missing, duplicated, from
//! another split, scene or settings, or damaged is refused with a message naming it.

use std::path::{Path, PathBuf};

use serde_json::Value;

use crate::cli::{precompute, text};

/// A room made the way users make one: separate OBJ files for the floor, two walls and a
/// table top in metres, and a translucent block (S runs in the merge).
fn room(dir: &Path) -> PathBuf {
    let quad = |name: &str, v: [[f32; 3]; 4]| {
        let mut s = String::new();
        for p in v {
            s += &format!("v {} {} {}\n", p[0], p[1], p[2]);
        }
        s += "f 1 2 3 4\n";
        std::fs::write(dir.join(format!("{name}.obj")), s).unwrap();
    };
    quad(
        "floor",
        [[0., 0., 0.], [0., 0., 3.], [4., 0., 3.], [4., 0., 0.]],
    );
    quad(
        "back",
        [[0., 0., 0.], [4., 0., 0.], [4., 2.5, 0.], [0., 2.5, 0.]],
    );
    quad(
        "left",
        [[0., 0., 0.], [0., 2.5, 0.], [0., 2.5, 3.], [0., 0., 3.]],
    );
    quad(
        "table",
        [[1., 0.8, 1.], [1., 0.8, 2.], [2.5, 0.8, 2.], [2.5, 0.8, 1.]],
    );
    let scene = serde_json::json!({
        "unit_mm": 1000.0,
        "objects": [
            {"name": "floor", "mesh": "floor.obj", "material": {"type": "diffuse", "albedo": [0.6, 0.6, 0.6]}},
            {"name": "back", "mesh": "back.obj", "material": {"type": "diffuse", "albedo": [0.7, 0.3, 0.3]}},
            {"name": "left", "mesh": "left.obj", "material": {"type": "diffuse", "albedo": [0.3, 0.7, 0.3]}},
            {"name": "table", "mesh": "table.obj", "material": {"type": "diffuse", "albedo": [0.5, 0.4, 0.3]}},
            {"name": "soap", "mesh": {"shape": "box", "size": [0.4, 0.6, 0.4]},
             "transform": {"translate": [3.0, 0.3, 2.0]},
             "material": {"type": "translucent", "profile": {"type": "dipole", "preset": "marble"}}}
        ],
        "lights": [{"type": "point", "position": [2.0, 2.2, 1.5], "intensity": [30, 30, 30]}]
    });
    let path = dir.join("room.json");
    std::fs::write(&path, serde_json::to_string_pretty(&scene).unwrap()).unwrap();
    path
}

fn run_ok(args: &[&str]) -> String {
    let o = precompute(args);
    assert!(o.status.success(), "{args:?}: {}", text(&o));
    text(&o)
}

fn run_err(args: &[&str]) -> String {
    let o = precompute(args);
    assert!(!o.status.success(), "{args:?} should fail: {}", text(&o));
    text(&o)
}

/// The manifest without what differs between any two runs (wall-clock times).
fn manifest_without_times(dir: &Path) -> Value {
    let mut m: Value =
        serde_json::from_slice(&std::fs::read(dir.join("manifest.json")).unwrap()).unwrap();
    m.as_object_mut().unwrap().remove("stages");
    if let Some(e) = m.get_mut("environment").and_then(Value::as_object_mut) {
        e.remove("seconds");
    }
    if let Some(objects) = m
        .pointer_mut("/subsurface/objects")
        .and_then(Value::as_array_mut)
    {
        for o in objects {
            o.as_object_mut().unwrap().remove("seconds");
        }
    }
    m
}

/// Every file of `a` is in `b` with the same bytes (the manifest: up to its times).
fn assert_same_bundle(a: &Path, b: &Path) {
    let mut names: Vec<_> = std::fs::read_dir(a)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    names.sort();
    let mut other: Vec<_> = std::fs::read_dir(b)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    other.sort();
    assert_eq!(names, other, "the bundles hold different files");
    for name in names {
        if name == "manifest.json" {
            assert_eq!(manifest_without_times(a), manifest_without_times(b));
            continue;
        }
        let (x, y) = (
            std::fs::read(a.join(&name)).unwrap(),
            std::fs::read(b.join(&name)).unwrap(),
        );
        assert!(x == y, "{name:?} differs between the bundles");
    }
}

#[test]
fn shards_merged_hold_the_one_box_bundle_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let scene = room(dir.path());
    let scene = scene.to_str().unwrap();
    let one = dir.path().join("one");
    let sharded = dir.path().join("sharded");
    let common = ["--patches", "1500", "--quiet"];
    let with = |out: &Path, extra: &[&str]| -> Vec<String> {
        let mut a = vec![scene.to_string(), "--out".into(), out.display().to_string()];
        a.extend(common.iter().map(|s| s.to_string()));
        a.extend(extra.iter().map(|s| s.to_string()));
        a
    };
    let a = with(&one, &[]);
    run_ok(&args(&a));

    // Shards in any order; a shard run again is a no-op.
    for i in [2, 0, 1] {
        let a = with(&sharded, &["--shard", &format!("{i}/3")]);
        let t = run_ok(&args(&a));
        assert!(
            t.contains(&format!("shard {i}/3")) && t.contains("receiver rows"),
            "{t}"
        );
    }
    let parts = dir.path().join("sharded.parts");
    let stamp = std::fs::metadata(parts.join("part-1-of-3/part.json"))
        .unwrap()
        .modified()
        .unwrap();
    let a = with(&sharded, &["--shard", "1/3"]);
    let t = run_ok(&args(&a));
    assert!(
        t.contains("already in") && t.contains("nothing to do"),
        "{t}"
    );
    assert_eq!(
        std::fs::metadata(parts.join("part-1-of-3/part.json"))
            .unwrap()
            .modified()
            .unwrap(),
        stamp
    );
    // A killed run of a shard leaves only a hidden temporary, which the merge does not take
    // for a part.
    std::fs::create_dir(parts.join(".part-0-of-3.tmp-999999-1")).unwrap();

    let a = with(&sharded, &["--merge", "3"]);
    let t = run_ok(&args(&a));
    assert!(t.contains("merge parts"), "{t}");
    assert!(!parts.exists(), "the parts are removed after the merge");
    assert_same_bundle(&one, &sharded);
}

/// Two translucent objects on a floor (a box and a ball: the translucent receivers split
/// across both, one object between two shards at K = 3).
fn translucent_pair(dir: &Path) -> PathBuf {
    let scene = serde_json::json!({
        "unit_mm": 1000.0,
        "objects": [
            {"name": "floor", "mesh": {"shape": "quad", "size": [2, 2]},
             "material": {"type": "diffuse", "albedo": [0.6, 0.6, 0.6]}},
            {"name": "soap", "mesh": {"shape": "box", "size": [0.4, 0.6, 0.4]},
             "transform": {"translate": [0.0, 0.3, 0.0]},
             "material": {"type": "translucent", "profile": {"type": "dipole", "preset": "marble"}}},
            {"name": "ball", "mesh": {"shape": "sphere", "radius": 0.2},
             "transform": {"translate": [0.6, 0.2, 0.3]},
             "material": {"type": "translucent", "profile": {"type": "dipole", "preset": "skimmilk"}}}
        ],
        "lights": [{"type": "point", "position": [0.0, 1.5, 0.5], "intensity": [3, 3, 3]}]
    });
    let path = dir.join("pair.json");
    std::fs::write(&path, serde_json::to_string_pretty(&scene).unwrap()).unwrap();
    path
}

/// A hierarchical S whose distances are traced on demand (each shard cuts its share of the
/// translucent receivers) and a pairwise S (made in the merge): merged at K = 2 and 3,
/// every array is the one-box bytes.
#[test]
fn sharded_subsurface_cuts_merge_to_the_one_box_bundle_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let scene = translucent_pair(dir.path());
    for s in ["hierarchical", "pairwise"] {
        let base = |out: &Path| -> Vec<String> {
            [
                scene.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
                "--patches",
                "2000",
                "--quiet",
                "--subsurface",
                s,
            ]
            .map(String::from)
            .to_vec()
        };
        let one = dir.path().join(format!("one-{s}"));
        let t = run_ok(&args(&base(&one)));
        if s == "hierarchical" {
            assert!(
                t.contains("nnz(S)") && t.contains("links to cluster nodes"),
                "{t}"
            );
        }
        for k in [2, 3] {
            let out = dir.path().join(format!("{s}-{k}"));
            for i in 0..k {
                let mut a = base(&out);
                a.extend(["--shard".into(), format!("{i}/{k}")]);
                run_ok(&args(&a));
            }
            let mut a = base(&out);
            a.extend(["--merge".into(), k.to_string()]);
            let t = run_ok(&args(&a));
            if s == "hierarchical" {
                assert!(t.contains("subsurface cuts (shards)"), "{t}");
            }
            assert_same_bundle(&one, &out);
        }
    }
}

#[test]
fn missing_duplicated_foreign_and_damaged_parts_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("c");
    let o = out.to_str().unwrap();
    let base = ["builtin:cornell", "--out", o, "--patches", "500", "--quiet"];
    let with = |extra: &[&'static str]| -> Vec<&str> { [&base[..], extra].concat() };
    let parts = dir.path().join("c.parts");

    // Missing: the message names the part and the command that makes it.
    run_ok(&with(&["--shard", "0/2"]));
    let e = run_err(&with(&["--merge", "2"]));
    assert!(
        e.contains("part 1 of 2 is missing")
            && e.contains("translux-precompute builtin:cornell --out")
            && e.contains("--shard 1/2"),
        "{e}"
    );
    assert!(!out.exists(), "no bundle from a failed merge");

    // Another scene's (other settings: another patch count) part.
    let other = [
        "builtin:cornell",
        "--out",
        o,
        "--patches",
        "520",
        "--quiet",
        "--shard",
        "1/2",
    ];
    run_ok(&other);
    let e = run_err(&with(&["--merge", "2"]));
    assert!(
        e.contains("part 1 of 2") && e.contains("another scene or other settings"),
        "{e}"
    );
    // Its shard is not silently taken as finished either.
    let e = run_err(&with(&["--shard", "1/2"]));
    assert!(
        e.contains("another scene or other settings") && e.contains("remove"),
        "{e}"
    );
    std::fs::remove_dir_all(parts.join("part-1-of-2")).unwrap();

    // A part of another split beside these: its rows would count twice.
    run_ok(&with(&["--shard", "1/2"]));
    run_ok(&with(&["--shard", "0/3"]));
    let e = run_err(&with(&["--merge", "2"]));
    assert!(
        e.contains("part-0-of-3") && e.contains("counted twice"),
        "{e}"
    );
    std::fs::remove_dir_all(parts.join("part-0-of-3")).unwrap();

    // Duplicated: a part copied under another index.
    let keep = dir.path().join("keep");
    std::fs::rename(parts.join("part-0-of-2"), &keep).unwrap();
    copy_dir(&parts.join("part-1-of-2"), &parts.join("part-0-of-2"));
    let e = run_err(&with(&["--merge", "2"]));
    assert!(
        e.contains("holds shard 1/2") && e.contains("counted twice"),
        "{e}"
    );
    std::fs::remove_dir_all(parts.join("part-0-of-2")).unwrap();
    std::fs::rename(&keep, parts.join("part-0-of-2")).unwrap();

    // Damaged: a truncated array.
    let val = parts.join("part-0-of-2/c_val.f32");
    let bytes = std::fs::read(&val).unwrap();
    std::fs::write(&val, &bytes[..bytes.len() / 2]).unwrap();
    let e = run_err(&with(&["--merge", "2"]));
    assert!(e.contains("c_val.f32") && e.contains("truncated"), "{e}");
    std::fs::write(&val, &bytes).unwrap();

    // Whole again: the merge succeeds.
    run_ok(&with(&["--merge", "2"]));
    assert!(out.join("manifest.json").is_file() && !parts.exists());

    // Usage errors.
    for (extra, want) in [
        (&["--shard", "2/2"][..], "numbered from 0 to 1"),
        (&["--shard", "1"][..], "is not I/K"),
        (&["--merge", "0"][..], "shard count must be 1"),
        (
            &["--shard", "0/2", "--transport", "dense"][..],
            "--transport dense",
        ),
        (
            &["--shard", "0/2", "--links", "two-sided"][..],
            "--links two-sided links whole clusters on both sides and runs on one box",
        ),
    ] {
        let e = run_err(&with(extra));
        assert!(e.contains(want), "{extra:?}: {e}");
    }
}

fn args(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
}
