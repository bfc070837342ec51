//! Animated scenes through the real `translux-precompute`: per-frame OBJ files (a numbered
//! pattern), keyframed transforms, one bundle per frame with `sequence.json`, frames shared
//! when nothing moved, resuming, and the errors a user meets.

use std::path::Path;

use translux_proto::animation::{SEQUENCE_FILE, SequenceManifest};
use translux_proto::bundle::Bundle;

use crate::cli::{precompute, text};

/// An OBJ box 10 cm wide and `h` tall standing on y = 0, faces outward.
fn box_obj(h: f32) -> String {
    let mut s = String::new();
    for x in [-0.05f32, 0.05] {
        for y in [0.0f32, h] {
            for z in [-0.05f32, 0.05] {
                s += &format!("v {x} {y} {z}\n");
            }
        }
    }
    for q in [
        [1, 2, 4, 3],
        [5, 7, 8, 6],
        [1, 5, 6, 2],
        [3, 4, 8, 7],
        [1, 3, 7, 5],
        [2, 6, 8, 4],
    ] {
        s += &format!(
            "f {} {} {}\nf {} {} {}\n",
            q[0], q[1], q[2], q[0], q[2], q[3]
        );
    }
    s
}

/// A 4-frame scene in `dir`: a floor, a box read from `blk_01.obj` … `blk_04.obj` (frames 0
/// and 1 the same file content), and a sphere keyframed from x = 0.2 (frames 0–1) to
/// x = −0.2 (frame 3).
fn write_scene(dir: &Path) -> std::path::PathBuf {
    for (k, h) in [(1, 0.1f32), (2, 0.1), (3, 0.11), (4, 0.13)] {
        std::fs::write(dir.join(format!("blk_{k:02}.obj")), box_obj(h)).unwrap();
    }
    let scene = serde_json::json!({
        "animation": {"frames": 4, "fps": 12, "first_number": 1},
        "patches": {"target": 500},
        "objects": [
            {"name": "floor", "mesh": {"shape": "quad", "size": [1, 1]},
             "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
            {"name": "blk", "mesh": "blk_{frame:02}.obj",
             "material": {"type": "translucent", "profile": {"type": "dipole", "preset": "marble"}}},
            {"name": "ball", "mesh": {"shape": "sphere", "radius": 0.05, "segments": 12},
             "transform": {"translate": [0, 0.05, 0]},
             "material": {"type": "diffuse", "albedo": [0.8, 0.2, 0.2]},
             "keyframes": [{"frame": 0, "translate": [0.2, 0, 0]},
                           {"frame": 1, "translate": [0.2, 0, 0]},
                           {"frame": 3, "translate": [-0.2, 0, 0.1]}]}
        ],
        "lights": [{"type": "point", "position": [0, 0.6, 0.3], "intensity": [1, 1, 1]}]
    });
    let path = dir.join("anim.json");
    std::fs::write(&path, serde_json::to_string_pretty(&scene).unwrap()).unwrap();
    path
}

fn sequence(out: &Path) -> SequenceManifest {
    let text = std::fs::read_to_string(out.join(SEQUENCE_FILE)).unwrap();
    let m: SequenceManifest = serde_json::from_str(&text).unwrap();
    m.validate().unwrap();
    m
}

/// Object `name`'s patch corners in a bundle.
fn corners<'a>(b: &'a Bundle, name: &str) -> &'a [[[f32; 3]; 3]] {
    let o = b
        .manifest()
        .objects
        .iter()
        .find(|o| o.name == name)
        .unwrap();
    let r = o.first_patch as usize..(o.first_patch + o.patch_count) as usize;
    &b.patch_corners()[r]
}

/// The highest corner of object `name`: a box's height as its frame's file has it.
fn top(b: &Bundle, name: &str) -> f32 {
    corners(b, name)
        .iter()
        .flatten()
        .fold(f32::MIN, |m, v| m.max(v[1]))
}

/// Mean position of object `name`'s patch corners in a bundle.
fn centre(b: &Bundle, name: &str) -> [f32; 3] {
    let corners = corners(b, name);
    let mut c = [0.0f32; 3];
    for t in corners {
        for v in t {
            for k in 0..3 {
                c[k] += v[k];
            }
        }
    }
    c.map(|x| x / (3 * corners.len()) as f32)
}

#[test]
fn an_animated_scene_becomes_one_bundle_per_frame_and_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let scene = write_scene(dir.path());
    let out = dir.path().join("anim");
    let args = [scene.to_str().unwrap(), "--out", out.to_str().unwrap()];
    let o = precompute(&args);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(
        t.contains("3 precomputed, 0 kept from the last run, 1 shared"),
        "{t}"
    );
    assert!(
        t.contains("frame 2 of 4 (frame-0000): the same scene as frame 0"),
        "{t}"
    );

    let m = sequence(&out);
    assert_eq!(m.fps, 12.0);
    assert_eq!(
        m.frames,
        ["frame-0000", "frame-0000", "frame-0002", "frame-0003"]
    );
    // The keyframed ball where its keyframes put it (after its own transform), the box as
    // tall as each frame's file.
    let want_ball = [
        [0.2, 0.05, 0.0],
        [0.2, 0.05, 0.0],
        [0.0, 0.05, 0.05],
        [-0.2, 0.05, 0.1],
    ];
    let want_blk = [0.1f32, 0.1, 0.11, 0.13];
    for (k, folder) in m.frames.iter().enumerate() {
        let b = Bundle::open(&out.join(folder)).unwrap();
        let ball = centre(&b, "ball");
        for c in 0..3 {
            assert!(
                (ball[c] - want_ball[k][c]).abs() < 2e-3,
                "frame {k}: the ball's centre is {ball:?}, its keyframes say {:?}",
                want_ball[k]
            );
        }
        let blk = top(&b, "blk");
        assert!(
            (blk - want_blk[k]).abs() < 1e-5,
            "frame {k}: the box is {blk} tall, its file's box {}",
            want_blk[k]
        );
    }

    // The same command again: everything is kept.
    let o = precompute(&args);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(
        t.contains("0 precomputed, 3 kept from the last run, 1 shared"),
        "{t}"
    );

    // One frame's file changes: only that frame is precomputed again.
    std::fs::write(dir.path().join("blk_04.obj"), box_obj(0.15)).unwrap();
    let o = precompute(&args);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(
        t.contains("1 precomputed, 2 kept from the last run, 1 shared"),
        "{t}"
    );
    let b = Bundle::open(&out.join("frame-0003")).unwrap();
    assert!((top(&b, "blk") - 0.15).abs() < 1e-5);

    // A frame file gone: the error names the file and the frame, and sequence.json is
    // withdrawn until the sequence is whole again.
    std::fs::remove_file(dir.path().join("blk_03.obj")).unwrap();
    let o = precompute(&args);
    let t = text(&o);
    assert!(!o.status.success(), "{t}");
    assert!(
        t.contains("frame 2 (of frames 0 to 3)")
            && t.contains("blk_03.obj")
            && t.contains("not found"),
        "{t}"
    );
    assert!(!out.join(SEQUENCE_FILE).exists());
}

#[test]
fn animation_mistakes_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let scene = write_scene(dir.path());
    let text_of = |body: serde_json::Value| {
        let p = dir.path().join("bad.json");
        std::fs::write(&p, body.to_string()).unwrap();
        let out = dir.path().join("bad-out");
        let o = precompute(&[p.to_str().unwrap(), "--out", out.to_str().unwrap()]);
        assert!(!o.status.success());
        text(&o)
    };
    let mut s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&scene).unwrap()).unwrap();

    let mut late = s.clone();
    late["objects"][2]["keyframes"][2]["frame"] = 4.into();
    let t = text_of(late);
    assert!(
        t.contains("objects[2].keyframes[2].frame") && t.contains("frame 4 is out of range"),
        "{t}"
    );

    let mut still = s.clone();
    still.as_object_mut().unwrap().remove("animation");
    let t = text_of(still.clone());
    assert!(
        t.contains("objects[1].mesh") && t.contains("per-frame pattern"),
        "{t}"
    );
    still["objects"][1]["mesh"] = "blk_01.obj".into();
    let t = text_of(still);
    assert!(
        t.contains("objects[2].keyframes") && t.contains("animated scene"),
        "{t}"
    );

    s["objects"][1]["mesh"] = "blk_{frame:x}.obj".into();
    let t = text_of(s.clone());
    assert!(t.contains("{frame:0N}"), "{t}");

    // An existing bundle is not overwritten by a sequence.
    let bundle = dir.path().join("a-bundle");
    let o = precompute(&[
        "builtin:cornell",
        "--out",
        bundle.to_str().unwrap(),
        "--patches",
        "300",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let o = precompute(&[scene.to_str().unwrap(), "--out", bundle.to_str().unwrap()]);
    let t = text(&o);
    assert!(
        !o.status.success() && t.contains("not a sequence folder"),
        "{t}"
    );
    assert!(Bundle::open(&bundle).is_ok());
}

/// Records the notes a precompute tells.
#[derive(Debug, Default)]
struct Notes(std::sync::Mutex<Vec<String>>);

impl translux_precompute::pipeline::Observer for Notes {
    fn progress(&self, _: &str, _: u64, _: u64) {}
    fn note(&self, message: &str) {
        self.0.lock().unwrap().push(message.to_owned());
    }
}

/// A 3-frame scene: a floor and a marble block (×4 its mean free path) keyframed from
/// x = −0.2 to x = 0.2 while it turns 90° about Y, `last_scale` times as large in the last
/// frame.
fn rigid_scene(dir: &Path, last_scale: f32) -> translux_precompute::scene::SceneSource {
    let scene = serde_json::json!({
        "name": "slide",
        "animation": {"frames": 3, "fps": 12},
        "patches": {"target": 500},
        "objects": [
            {"name": "floor", "mesh": {"shape": "quad", "size": [1, 1]},
             "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
            {"name": "blk", "mesh": {"shape": "box", "size": [0.1, 0.16, 0.1]},
             "transform": {"translate": [0, 0.08, 0]},
             "material": {"type": "translucent",
                          "profile": {"type": "dipole", "preset": "marble", "scale": 4}},
             "keyframes": [{"frame": 0, "translate": [-0.2, 0, 0]},
                           {"frame": 2, "translate": [0.2, 0, 0.1], "rotate_deg": [0, 90, 0],
                            "scale": last_scale}]}
        ],
        "lights": [{"type": "point", "position": [0, 0.6, 0.3], "intensity": [1, 1, 1]}]
    });
    let path = dir.join("slide.json");
    std::fs::write(&path, scene.to_string()).unwrap();
    translux_precompute::scene::read_scene_file(&path).unwrap()
}

/// Object `name`'s optical distances in a bundle, rows and columns in the object's own
/// patch numbering, with its S rows (green) alike.
#[allow(clippy::type_complexity)]
fn object_rows(b: &Bundle, name: &str) -> (Vec<Vec<(u32, f32)>>, Vec<Vec<(u32, f32)>>) {
    let o = b
        .manifest()
        .objects
        .iter()
        .find(|o| o.name == name)
        .unwrap();
    let r = o.first_patch as usize..(o.first_patch + o.patch_count) as usize;
    let base = r.start as u32;
    let (d, s) = (b.distances(), b.subsurface());
    let pick = |cols: &[u32], val: &mut dyn Iterator<Item = f32>| {
        cols.iter().map(|&j| j - base).zip(val).collect::<Vec<_>>()
    };
    let dist = r
        .clone()
        .map(|i| {
            let (c, v) = d.row(i);
            pick(c, &mut v.iter().copied())
        })
        .collect();
    let sm = r
        .map(|i| {
            let (c, v) = s.row(i);
            pick(c, &mut v.iter().map(|x| x[1]))
        })
        .collect();
    (dist, sm)
}

/// A block that only slides and turns keeps its optical distances from the first frame;
/// they equal a fresh precompute of the frame, and so does its S. A block that also grows
/// gets new ones.
#[test]
fn a_rigidly_moving_object_keeps_its_optical_distances_between_frames() {
    use std::sync::Arc;
    use translux_precompute::pipeline::{PrecomputeParams, precompute};
    use translux_precompute::sequence::precompute_sequence;
    let dir = tempfile::tempdir().unwrap();
    let src = rigid_scene(dir.path(), 1.0);
    let notes = Arc::new(Notes::default());
    let params = PrecomputeParams {
        observer: Some(notes.clone()),
        ..Default::default()
    };
    let out = dir.path().join("slide");
    let report = precompute_sequence(&src, &out, &params, &|_, _| {}).unwrap();
    assert_eq!(report.computed(), 3);
    let notes = notes.0.lock().unwrap().clone();
    assert!(
        notes
            .iter()
            .any(|n| n.contains("'blk' only moved rigidly") && n.contains("reused")),
        "{notes:?}"
    );
    let frame = |k: u32| Bundle::open(&out.join(format!("frame-{k:04}"))).unwrap();
    let (d0, _) = object_rows(&frame(0), "blk");
    assert!(
        d0.iter().map(Vec::len).sum::<usize>() > 1000,
        "too few distances to compare"
    );
    for k in [1, 2] {
        assert_eq!(
            object_rows(&frame(k), "blk").0,
            d0,
            "frame {k} computed its own"
        );
    }
    // The frame precomputed on its own (no cache): the same distances to float rounding of
    // the turned centroids, and the same S.
    let last = translux_precompute::scene::resolve_frame(
        &src.file,
        &src.base_dir,
        src.name.clone(),
        src.source.clone(),
        2,
    )
    .unwrap();
    let alone = dir.path().join("alone");
    precompute(&last, &alone, &PrecomputeParams::default()).unwrap();
    let (da, sa) = object_rows(&Bundle::open(&alone).unwrap(), "blk");
    let (_, s2) = object_rows(&frame(2), "blk");
    let close = |a: &[Vec<(u32, f32)>], b: &[Vec<(u32, f32)>], what: &str| {
        assert_eq!(a.len(), b.len());
        let peak = b.iter().flatten().fold(0f32, |m, e| m.max(e.1.abs()));
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert_eq!(x.len(), y.len(), "{what} row {i}: other pairs");
            for (p, q) in x.iter().zip(y) {
                assert_eq!(p.0, q.0, "{what} row {i}");
                assert!(
                    (p.1 - q.1).abs() <= 1e-4 * peak,
                    "{what} row {i}: {p:?} vs {q:?}"
                );
            }
        }
    };
    close(&d0, &da, "distances");
    close(&s2, &sa, "S");

    // Grown by half in the last frame: not the same object any more.
    let grown = rigid_scene(dir.path(), 1.5);
    let out = dir.path().join("grown");
    precompute_sequence(&grown, &out, &PrecomputeParams::default(), &|_, _| {}).unwrap();
    let longest = |k: u32| {
        let b = Bundle::open(&out.join(format!("frame-{k:04}"))).unwrap();
        object_rows(&b, "blk")
            .0
            .iter()
            .flatten()
            .fold(0f32, |m, e| m.max(e.1))
    };
    assert!(
        longest(2) > 1.3 * longest(0),
        "{} vs {}",
        longest(2),
        longest(0)
    );
}
