//! `--shard I/K` and `--merge K` on an animated scene, through the real
//! `translux-precompute`: shards take consecutive blocks of frames, the merge checks every
//! frame and writes `sequence.json`, and the merged folder is what one box makes — the same
//! frames, each bundle's arrays byte for byte.

use std::path::{Path, PathBuf};

use serde_json::Value;
use translux_proto::animation::{SEQUENCE_FILE, SequenceManifest};
use translux_proto::bundle::Bundle;

use crate::cli::{precompute, text};

/// A 10-frame scene (blocks 0–7 and 8–9): a floor, a marble block sliding rigidly (its
/// optical distances reused from frame to frame within a block) and a ball. Frame 9 holds
/// frame 2's pose: the second share's frame shares the first share's folder.
fn slide(dir: &Path, intensity: f32) -> PathBuf {
    let scene = serde_json::json!({
        "name": "slide",
        "animation": {"frames": 10, "fps": 12},
        "patches": {"target": 300},
        "objects": [
            {"name": "floor", "mesh": {"shape": "quad", "size": [1, 1]},
             "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
            {"name": "blk", "mesh": {"shape": "box", "size": [0.1, 0.16, 0.1]},
             "transform": {"translate": [0, 0.08, 0]},
             "material": {"type": "translucent",
                          "profile": {"type": "dipole", "preset": "marble", "scale": 4}},
             "keyframes": [{"frame": 0, "translate": [-0.2, 0, 0]},
                           {"frame": 2, "translate": [0, 0, 0]},
                           {"frame": 5, "translate": [0.2, 0, 0.1]},
                           {"frame": 9, "translate": [0, 0, 0]}]}
        ],
        "lights": [{"type": "point", "position": [0, 0.6, 0.3],
                    "intensity": [intensity, intensity, intensity]}]
    });
    let path = dir.join("slide.json");
    std::fs::write(&path, scene.to_string()).unwrap();
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

fn sequence(out: &Path) -> SequenceManifest {
    let text = std::fs::read_to_string(out.join(SEQUENCE_FILE)).unwrap();
    let m: SequenceManifest = serde_json::from_str(&text).unwrap();
    m.validate().unwrap();
    m
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

/// Names in `dir`, sorted.
fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// Every file of bundle `a` is in `b` with the same bytes (the manifest: up to its times).
fn assert_same_bundle(a: &Path, b: &Path) {
    assert_eq!(names(a), names(b), "{a:?} and {b:?} hold different files");
    for name in names(a) {
        if name == "manifest.json" {
            assert_eq!(
                manifest_without_times(a),
                manifest_without_times(b),
                "{a:?}"
            );
            continue;
        }
        let (x, y) = (
            std::fs::read(a.join(&name)).unwrap(),
            std::fs::read(b.join(&name)).unwrap(),
        );
        assert!(x == y, "{name:?} differs between {a:?} and {b:?}");
    }
}

/// Two sequence folders hold the same frames: the same `sequence.json`, frame folders and
/// records, and every bundle the same.
fn assert_same_sequence(a: &Path, b: &Path) {
    assert_eq!(sequence(a), sequence(b));
    let visible = |d: &Path| -> Vec<String> {
        names(d)
            .into_iter()
            .filter(|n| n.starts_with("frame-") || n.ends_with(".key"))
            .collect()
    };
    assert_eq!(visible(a), visible(b));
    for n in visible(a) {
        if n.ends_with(".key") {
            assert_eq!(
                std::fs::read(a.join(&n)).unwrap(),
                std::fs::read(b.join(&n)).unwrap(),
                "{n}"
            );
        } else {
            assert_same_bundle(&a.join(&n), &b.join(&n));
            Bundle::open(&b.join(&n)).unwrap();
        }
    }
}

/// The modification time of a frame's manifest.
fn stamp(out: &Path, frame: &str) -> std::time::SystemTime {
    std::fs::metadata(out.join(frame).join("manifest.json"))
        .unwrap()
        .modified()
        .unwrap()
}

#[test]
fn sequence_shards_merged_hold_the_one_box_frames_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let scene = slide(dir.path(), 1.0);
    let scene = scene.to_str().unwrap();
    let one = dir.path().join("one");
    let sharded = dir.path().join("sharded");
    let (o, s) = (one.to_str().unwrap(), sharded.to_str().unwrap());
    run_ok(&[scene, "--out", o]);

    // The second share first: frame 9 points at frame 2, which the other share makes.
    let t = run_ok(&[scene, "--out", s, "--shard", "1/2"]);
    assert!(
        t.contains("frames 8 to 9 of 10")
            && t.contains("1 precomputed, 0 kept from the last run, 1 shared")
            && t.contains("frame 10 of 10 (frame-0002): the same scene as frame 2"),
        "{t}"
    );
    assert!(!sharded.join(SEQUENCE_FILE).exists());
    let t = run_ok(&[scene, "--out", s, "--shard", "0/2"]);
    assert!(
        t.contains("frames 0 to 7 of 10") && t.contains("8 precomputed"),
        "{t}"
    );
    // Frames past the first of a block took the sliding block's distances from it.
    assert!(t.contains("'blk' only moved rigidly"), "{t}");
    assert!(!sharded.join(SEQUENCE_FILE).exists());
    // A shard killed while it wrote a frame leaves a hidden temporary: not a frame.
    std::fs::create_dir(sharded.join(".frame-0003.tmp-999999-1")).unwrap();

    let t = run_ok(&[scene, "--out", s, "--merge", "2"]);
    assert!(
        t.contains("sequence merged from 2 shards, 10 frames"),
        "{t}"
    );
    let m = sequence(&sharded);
    assert_eq!(m.frames[9], "frame-0002");
    assert_same_sequence(&one, &sharded);

    // Merged again (the same inputs): the same sequence.
    run_ok(&[scene, "--out", s, "--merge", "2"]);
    assert_same_sequence(&one, &sharded);
}

#[test]
fn a_merge_with_a_share_missing_names_the_shard_command() {
    let dir = tempfile::tempdir().unwrap();
    let scene = slide(dir.path(), 1.0);
    let scene = scene.to_str().unwrap();
    let out = dir.path().join("seq");
    let o = out.to_str().unwrap();

    // Nothing there yet: both shards named, nothing created.
    let e = run_err(&[scene, "--out", o, "--merge", "2", "--quiet"]);
    assert!(
        e.contains("frame 0 (frame-0000) is missing")
            && e.contains(&format!(
                "translux-precompute {scene} --out {o} --quiet --shard 0/2"
            ))
            && e.contains("--shard 1/2"),
        "{e}"
    );
    assert!(!out.exists());

    run_ok(&[scene, "--out", o, "--shard", "1/2", "--quiet"]);
    let e = run_err(&[scene, "--out", o, "--quiet", "--merge", "2"]);
    assert!(
        e.contains("frame 2 (frame-0002) is missing: shard 0/2")
            && e.contains(&format!(
                "translux-precompute {scene} --out {o} --quiet --shard 0/2"
            ))
            && !e.contains("--shard 1/2")
            && !e.contains("frame 8 "),
        "{e}"
    );
    assert!(!out.join(SEQUENCE_FILE).exists());

    // Three shards of two blocks: the first has none and does nothing.
    let t = run_ok(&[scene, "--out", o, "--shard", "0/3", "--quiet"]);
    assert!(
        t.contains("has no frames") && t.contains("nothing to do"),
        "{t}"
    );
}

#[test]
fn a_sequence_shard_run_again_keeps_its_frames() {
    let dir = tempfile::tempdir().unwrap();
    let scene = slide(dir.path(), 1.0);
    let scene = scene.to_str().unwrap();
    let out = dir.path().join("seq");
    let o = out.to_str().unwrap();
    run_ok(&[scene, "--out", o, "--shard", "1/2"]);
    let before = stamp(&out, "frame-0008");
    let t = run_ok(&[scene, "--out", o, "--shard", "1/2"]);
    assert!(
        t.contains("0 precomputed, 1 kept from the last run, 1 shared"),
        "{t}"
    );
    assert_eq!(stamp(&out, "frame-0008"), before);
    assert!(!out.join(SEQUENCE_FILE).exists());
}

#[test]
fn a_frame_made_before_the_scene_changed_is_refused_then_computed_again() {
    let dir = tempfile::tempdir().unwrap();
    let scene = slide(dir.path(), 1.0);
    let scene = scene.to_str().unwrap();
    let out = dir.path().join("seq");
    let o = out.to_str().unwrap();
    run_ok(&[scene, "--out", o, "--shard", "0/2"]);
    run_ok(&[scene, "--out", o, "--shard", "1/2"]);
    run_ok(&[scene, "--out", o, "--merge", "2"]);
    sequence(&out);

    // The light changes: every frame is stale.
    slide(dir.path(), 2.0);
    let e = run_err(&[scene, "--out", o, "--merge", "2"]);
    assert!(
        e.contains("frame 8 (frame-0008) is made from other inputs")
            && e.contains("--shard 0/2")
            && e.contains("--shard 1/2"),
        "{e}"
    );
    // A refused merge changes nothing: the frames and sequence.json there still agree.
    sequence(&out);
    // The second share again: its frame computed anew; the merge still wants the first.
    let t = run_ok(&[scene, "--out", o, "--shard", "1/2"]);
    assert!(t.contains("1 precomputed, 0 kept"), "{t}");
    assert!(!out.join(SEQUENCE_FILE).exists(), "a shard withdraws it");
    let e = run_err(&[scene, "--out", o, "--merge", "2"]);
    assert!(
        e.contains("frame 0 (frame-0000) is made from other inputs")
            && e.contains("--shard 0/2")
            && !e.contains("--shard 1/2")
            && !e.contains("frame 8 "),
        "{e}"
    );
    run_ok(&[scene, "--out", o, "--shard", "0/2"]);
    run_ok(&[scene, "--out", o, "--merge", "2"]);
    assert_eq!(sequence(&out).frames.len(), 10);
}
