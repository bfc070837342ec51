//! The `translux-server` binary's offline commands (`render`, `export`, `relight`) and its
//! server flags, run as a user would, on a small Cornell-box bundle built in the test.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use translux_engine::relight;
use translux_engine::render::RenderParams;
use translux_proto::api::{RelightRequest, RelightResponse, ToneMap};
use translux_proto::bundle::Bundle;
use translux_server::state::Scene;

use crate::support::bundle_dir;

const BIN: &str = env!("CARGO_BIN_EXE_translux-server");

fn server(args: &[&str]) -> Output {
    Command::new(BIN)
        .args(args)
        .env("RUST_LOG", "info")
        .env_remove("TRANSLUX_BUNDLES")
        .output()
        .unwrap()
}

/// Runs the binary, asserting success; returns stderr (the log).
fn ok(args: &[&str]) -> String {
    let out = server(args);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "{args:?}: {stderr}");
    stderr
}

/// Runs the binary, asserting failure; returns stderr.
fn fails(args: &[&str]) -> String {
    let out = server(args);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!out.status.success(), "{args:?} should fail: {stderr}");
    stderr
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The library's answer for the same request: open, plan, relight.
fn library_radiance(req: RelightRequest) -> (Scene, Vec<[f32; 3]>) {
    let scene = Scene::open("cornell", bundle_dir()).unwrap();
    let plan = relight::plan(&scene, req).unwrap();
    let out = relight::run(&scene, &plan).unwrap();
    (scene, out.radiance)
}

const REQUEST: &str = r#"{"components": "direct", "direct_at": "vertex",
    "lights": [{"type": "point", "position": [-0.1, 0.45, 0.05], "intensity": [0.4, 0.35, 0.3]}]}"#;

#[test]
fn render_writes_the_png_the_library_renders() {
    let tmp = tempfile::tempdir().unwrap();
    let req = tmp.path().join("req.json");
    std::fs::write(&req, REQUEST).unwrap();
    let png = tmp.path().join("cornell.png");
    let log = ok(&[
        "render",
        "--bundle",
        s(bundle_dir()),
        "--request",
        s(&req),
        "--out",
        s(&png),
        "--width",
        "96",
        "--height",
        "72",
        "--exposure",
        "-0.5",
        "--tone",
        "filmic",
    ]);
    assert!(log.contains("wrote") && log.contains("96×72"), "{log}");
    let bytes = std::fs::read(&png).unwrap();
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
    let img = image::load_from_memory_with_format(&bytes, image::ImageFormat::Png)
        .unwrap()
        .to_rgb8();
    assert_eq!(img.dimensions(), (96, 72));
    let first = img.get_pixel(0, 0).0;
    assert!(img.pixels().any(|p| p.0 != first), "one colour");

    // Flags applied on top of the request: the same picture as the library makes.
    let (scene, radiance) = library_radiance(translux_proto::parse_json(REQUEST).unwrap());
    let b = &scene.bundle;
    let want = translux_engine::render::render(
        b.vertex_positions(),
        b.triangle_vertices(),
        &radiance,
        &b.manifest().camera,
        &RenderParams {
            width: 96,
            height: 72,
            exposure: -0.5,
            tone: ToneMap::Filmic,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(img.as_raw(), want.as_raw());

    // No request: the bundle's lights and camera, 800 × 600, auto-exposed.
    let default_png = tmp.path().join("default.png");
    let log = ok(&[
        "render",
        "--bundle",
        s(bundle_dir()),
        "--out",
        s(&default_png),
    ]);
    let img = image::open(&default_png).unwrap();
    assert_eq!((img.width(), img.height()), (800, 600));
    assert!(log.contains("EV (auto)"), "{log}");
    let log = ok(&[
        "render",
        "--bundle",
        s(bundle_dir()),
        "--out",
        s(&default_png),
        "--width",
        "8",
        "--height",
        "8",
        "--exposure",
        "auto",
    ]);
    assert!(log.contains("EV (auto)"), "{log}");

    // Errors name the problem and write nothing.
    let bad = tmp.path().join("bad.png");
    let e = fails(&[
        "render",
        "--bundle",
        s(bundle_dir()),
        "--out",
        s(&bad),
        "--width",
        "0",
    ]);
    assert!(e.contains("width must be an integer in 1..=8192"), "{e}");
    std::fs::write(
        &req,
        r#"{"camera": {"position": [0, 0, 1], "target": [0, 0, 1]}}"#,
    )
    .unwrap();
    let e = fails(&[
        "render",
        "--bundle",
        s(bundle_dir()),
        "--request",
        s(&req),
        "--out",
        s(&bad),
    ]);
    assert!(e.contains("camera.target must differ"), "{e}");
    std::fs::write(
        &req,
        r#"{"lights": [{"type": "point", "position": [0, 1]}]}"#,
    )
    .unwrap();
    let e = fails(&[
        "render",
        "--bundle",
        s(bundle_dir()),
        "--request",
        s(&req),
        "--out",
        s(&bad),
    ]);
    assert!(e.contains("lights[0].position"), "{e}");
    let e = fails(&["render", "--bundle", s(bundle_dir()), "--out", "x.jpg"]);
    assert!(e.contains("must end in .png"), "{e}");
    let e = fails(&[
        "render",
        "--bundle",
        "/nonexistent/bundle",
        "--out",
        s(&bad),
    ]);
    assert!(e.contains("cannot open the bundle"), "{e}");
    assert!(!bad.exists());
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}

#[test]
fn export_writes_glb_and_ply() {
    let tmp = tempfile::tempdir().unwrap();
    let req = tmp.path().join("req.json");
    std::fs::write(&req, REQUEST).unwrap();
    let bundle = Bundle::open(bundle_dir()).unwrap();
    let nv = bundle.vertex_positions().len();
    let nf = bundle.triangle_vertices().len();

    let glb_path = tmp.path().join("cornell.glb");
    ok(&[
        "export",
        "--bundle",
        s(bundle_dir()),
        "--request",
        s(&req),
        "--out",
        s(&glb_path),
        "--exposure",
        "1",
    ]);
    let glb = std::fs::read(&glb_path).unwrap();
    assert_eq!(&glb[..4], b"glTF");
    assert_eq!(u32_at(&glb, 8) as usize, glb.len());
    let json_len = u32_at(&glb, 12) as usize;
    assert_eq!(json_len % 4, 0);
    let root = gltf_json::Root::from_slice(&glb[20..20 + json_len]).unwrap();
    let bin_len = u32_at(&glb, 20 + json_len) as usize;
    assert_eq!(root.buffers[0].byte_length.0 as usize, bin_len);
    assert_eq!(bin_len, 36 * nv + 12 * nf);
    // One mesh per object (POSITION, NORMAL, COLOR_0, indices each): every vertex and every
    // triangle once. (The names are checked in tests/tests/it/server.rs.)
    let objects = bundle.manifest().objects.len();
    assert_eq!((root.meshes.len(), root.nodes.len()), (objects, objects));
    let counts: Vec<u64> = root.accessors.iter().map(|a| a.count.0).collect();
    assert_eq!(counts.len(), 4 * objects);
    let sum = |k: usize| counts.iter().skip(k).step_by(4).sum::<u64>();
    assert_eq!(
        [sum(0), sum(1), sum(2), sum(3)],
        [nv as u64, nv as u64, nv as u64, 3 * nf as u64]
    );
    // COLOR_0 is linear: tone(L · 2^1), no OETF.
    let (_, radiance) = library_radiance(translux_proto::parse_json(REQUEST).unwrap());
    let bin = &glb[20 + json_len + 8..];
    let colours: Vec<f32> = bin[24 * nv..36 * nv]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    for (k, c) in radiance.iter().enumerate() {
        for ch in 0..3 {
            let want = (c[ch] * 2.0).min(1.0);
            assert!((colours[3 * k + ch] - want).abs() < 1e-6, "vertex {k}");
        }
    }

    // Without --exposure: the viewer's automatic exposure for the relit radiance, logged.
    let ply_path = tmp.path().join("cornell.ply");
    let log = ok(&[
        "export",
        "--bundle",
        s(bundle_dir()),
        "--request",
        s(&req),
        "--out",
        s(&ply_path),
    ]);
    let auto = translux_engine::render::auto_exposure(&radiance);
    assert!(log.contains(&format!("exposure {auto} EV (auto)")), "{log}");
    let ply = std::fs::read(&ply_path).unwrap();
    let header = translux_engine::export::ply_header(nv, nf, auto, ToneMap::Srgb);
    assert!(ply.starts_with(header.as_bytes()));
    assert_eq!(ply.len(), header.len() + 27 * nv + 13 * nf);

    let e = fails(&["export", "--bundle", s(bundle_dir()), "--out", "mesh.obj"]);
    assert!(e.contains(".glb or .ply"), "{e}");
    // A render request is not a relight request: its picture fields are refused, not ignored.
    std::fs::write(&req, r#"{"width": 10}"#).unwrap();
    let e = fails(&[
        "export",
        "--bundle",
        s(bundle_dir()),
        "--request",
        s(&req),
        "--out",
        s(&glb_path),
    ]);
    assert!(e.contains("unknown field `width`"), "{e}");
}

#[test]
fn relight_writes_f32_and_json() {
    let tmp = tempfile::tempdir().unwrap();
    let req = tmp.path().join("req.json");
    std::fs::write(&req, REQUEST).unwrap();
    let (_, radiance) = library_radiance(translux_proto::parse_json(REQUEST).unwrap());
    let f32_path = tmp.path().join("colours.f32");
    let json_path = tmp.path().join("colours.json");
    for out in [&f32_path, &json_path] {
        ok(&[
            "relight",
            "--bundle",
            s(bundle_dir()),
            "--request",
            s(&req),
            "--out",
            s(out),
        ]);
    }
    let raw: Vec<f32> = std::fs::read(&f32_path)
        .unwrap()
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    let want: Vec<f32> = radiance.iter().flatten().copied().collect();
    assert_eq!(raw, want);
    let answer: RelightResponse =
        serde_json::from_slice(&std::fs::read(&json_path).unwrap()).unwrap();
    assert_eq!(answer.vertex_count, radiance.len());
    assert_eq!(answer.radiance, want);
    assert_eq!(answer.stats.solver, "none");
}

#[test]
fn help_lists_the_subcommands_and_the_server_flags_still_work() {
    let help = String::from_utf8(server(&["--help"]).stdout).unwrap();
    for word in [
        "render",
        "export",
        "relight",
        "--bundles",
        "--demo",
        "--addr",
    ] {
        assert!(help.contains(word), "{word}: {help}");
    }
    // Server flags and a subcommand do not mix; no arguments at all is still an error.
    fails(&["--demo", "render", "--bundle", "b", "--out", "x.png"]);
    let e = fails(&[]);
    assert!(e.contains("--bundles"), "{e}");

    // The flag form serves: start on a free port, wait for "listening", stop it.
    let parent = bundle_dir().parent().unwrap();
    let mut child = Command::new(BIN)
        .args(["--bundles", s(parent), "--addr", "127.0.0.1:0"])
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let start = Instant::now();
    let mut log = Vec::new();
    let (mut listening, mut serving) = (false, false);
    // Bundles are opened in the background: "serving" may come before or after "listening".
    while start.elapsed() < Duration::from_secs(60) {
        match rx.recv_timeout(Duration::from_millis(200)) {
            Ok(line) => {
                listening |= line.contains("listening on http://127.0.0.1:");
                serving |= line.contains("serving \"cornell\"");
                log.push(line);
                if listening && serving {
                    break;
                }
            }
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
                if let Ok(Some(_)) = child.try_wait() {
                    break;
                }
            }
            Err(_) => break,
        }
    }
    let _ = child.kill();
    let _ = child.wait();
    assert!(listening, "{log:#?}");
    assert!(serving, "{log:#?}");
}

#[test]
fn render_writes_a_linear_exr_by_extension_and_rejects_other_extensions() {
    let tmp = tempfile::tempdir().unwrap();
    let req = tmp.path().join("req.json");
    std::fs::write(&req, REQUEST).unwrap();
    let (scene, radiance) = library_radiance(translux_proto::parse_json(REQUEST).unwrap());
    let b = &scene.bundle;
    let linear = |exposure: f32| {
        translux_engine::render::render_linear(
            b.vertex_positions(),
            b.triangle_vertices(),
            &radiance,
            &b.manifest().camera,
            &RenderParams {
                width: 96,
                height: 72,
                exposure,
                ..Default::default()
            },
        )
        .unwrap()
    };
    // `.EXR` in any case; an explicit exposure scales, `auto` (the default) does not.
    for (name, exposure, ev) in [("cornell.EXR", Some("-0.5"), -0.5), ("auto.exr", None, 0.0)] {
        let exr = tmp.path().join(name);
        let mut args = vec![
            "render",
            "--bundle",
            s(bundle_dir()),
            "--request",
            s(&req),
            "--out",
            s(&exr),
            "--width",
            "96",
            "--height",
            "72",
        ];
        if let Some(e) = exposure {
            args.extend(["--exposure", e]);
        }
        let log = ok(&args);
        assert!(log.contains("wrote") && log.contains("EXR"), "{log}");
        let bytes = std::fs::read(&exr).unwrap();
        assert_eq!(
            &bytes[..4],
            &[0x76, 0x2f, 0x31, 0x01],
            "OpenEXR magic number"
        );
        let img = image::load_from_memory_with_format(&bytes, image::ImageFormat::OpenExr)
            .unwrap()
            .to_rgb32f();
        assert_eq!(img.dimensions(), (96, 72));
        let want = linear(ev);
        for (k, (g, w)) in img.as_raw().iter().zip(want.as_raw()).enumerate() {
            assert!(
                (g - w).abs() <= 1e-3 * w.abs() + 1e-6,
                "{name} value {k}: {g} vs {w}"
            );
        }
        assert!(img.as_raw().iter().any(|&v| v > 0.0), "{name}: all black");
    }

    for bad in ["x.jpg", "x.png.tmp", "x"] {
        let e = fails(&["render", "--bundle", s(bundle_dir()), "--out", bad]);
        assert!(e.contains(".png or .exr"), "{bad}: {e}");
    }
    assert!(!tmp.path().join("x.jpg").exists());
}

/// `--demo` keeps a demo bundle that still shows its scene and precomputes one again when
/// the built-in scene's lights or materials changed since it was written (an older
/// translux's bundle), instead of serving the old look.
#[test]
fn a_demo_bundle_of_an_older_scene_is_precomputed_again() {
    use translux_server::cli::ensure_demo_bundle;
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("c");
    let manifest = out.join("manifest.json");
    ensure_demo_bundle(dir.path(), "c", "builtin:cornell").unwrap();
    let scene = translux_precompute::builtin::builtin_scene("cornell").unwrap();
    assert_eq!(Bundle::open(&out).unwrap().manifest().lights, scene.lights);
    let written = std::fs::metadata(&manifest).unwrap().modified().unwrap();
    ensure_demo_bundle(dir.path(), "c", "builtin:cornell").unwrap();
    assert_eq!(
        std::fs::metadata(&manifest).unwrap().modified().unwrap(),
        written,
        "an up-to-date demo bundle was written again"
    );

    // As an older version wrote it: the paper's single ceiling lamp, real marble.
    let paper = translux_precompute::builtin::builtin_scene("cornell_paper").unwrap();
    let mut m: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&manifest).unwrap()).unwrap();
    m["lights"] = serde_json::to_value(&paper.lights).unwrap();
    std::fs::write(&manifest, serde_json::to_vec(&m).unwrap()).unwrap();
    assert_eq!(Bundle::open(&out).unwrap().manifest().lights, paper.lights);
    ensure_demo_bundle(dir.path(), "c", "builtin:cornell").unwrap();
    assert_eq!(Bundle::open(&out).unwrap().manifest().lights, scene.lights);

    let mut m: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&manifest).unwrap()).unwrap();
    let block = m["objects"]
        .as_array()
        .unwrap()
        .iter()
        .position(|o| o["name"] == "tall_block")
        .unwrap();
    m["objects"][block]["material"]["profile"]["scale"] = serde_json::json!(1.0);
    std::fs::write(&manifest, serde_json::to_vec(&m).unwrap()).unwrap();
    ensure_demo_bundle(dir.path(), "c", "builtin:cornell").unwrap();
    let b = Bundle::open(&out).unwrap();
    assert_eq!(
        b.manifest().objects[block].material,
        scene.objects[block].material
    );
}
