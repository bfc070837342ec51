//! The browser viewer (`web/`) in a real browser: Debian's chromium, headless, driven by
//! playwright-core (`web/tests/viewer.test.mjs`), against a real `translux-server` on
//! 127.0.0.1 that this test starts, stops and starts again.
//!
//! The script checks that the canvas is not blank, that dragging the light's gizmo moves the
//! light and changes the picture, that the translucency slider re-solves and changes the
//! block (with a visible "solving…" state), that `direct` differs from `full` and the other
//! components are either drawn or refused in the banner, that the URL restores the view,
//! that stopping the server shows the banner and restarting it reconnects. Then the first-use
//! checks: on a second server with `--tokens` the page asks for a token, says when one is
//! refused, signs in (form, `?access_token=`, `#token=`) without the token reaching the
//! address bar or the console, and tells apart two scenes of one name; a link to a missing
//! scene says so; a picked medium shows in its caption; at 800×600 nothing overlaps and on a
//! 390×844 phone the panel leaves the view most of the screen. It measures the
//! time to the first lit frame, lit frames per second and input-to-photon latency while
//! dragging. This test then checks its downloads: the `.glb` against the bundle's mesh and
//! the export's colour definition, and the radiance the page showed against the server's
//! answer to the same request.
//!
//! Screenshots, downloads and `result.json` go to `target/viewer-screenshots/`.
//!
//! Needs `node`, `/usr/bin/chromium` (or `$CHROMIUM`) and `web/tests/node_modules`
//! (`npm ci --prefix web/tests`); `bash .ci/run` installs them. Without them the test fails
//! and says what is missing, unless `TRANSLUX_SKIP_BROWSER=1`.

use std::io::{BufRead, BufReader, Write};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::Value;
use translux_engine::export::linear_colour;
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::load_scene;
use translux_proto::api::ToneMap;
use translux_proto::bundle::Bundle;
use translux_server::auth::hash_token;
use translux_server::load_bundles;
use translux_server::team::{Team, TeamArgs};

/// Patches of the test bundle: enough for a picture worth looking at, quick to precompute.
const PATCHES: u64 = 1200;
/// The whole browser session may take this long before it is killed (a hang detector: in
/// CI it shares the 2 cores with Mitsuba and the validation walks, where a software-rendered
/// page's first lit frame has taken over 30 s).
const SESSION_LIMIT: Duration = Duration::from_secs(900);
/// The viewer token of the team server (a test value: 24 characters or more, as
/// `translux-server token hash` wants).
const VIEWER_TOKEN: &str = "tlx_browser_test_viewer_0123456789abcdef0123456789abcdef";

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ has a parent")
        .to_path_buf()
}

/// `target/viewer-screenshots` (beside the target dir's `tmp`).
fn screenshot_dir() -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR"))
        .parent()
        .expect("the target tmp dir has a parent")
        .join("viewer-screenshots")
}

/// What the browser session needs, or why it cannot run.
fn prerequisites() -> Result<(PathBuf, PathBuf), String> {
    let chromium = std::env::var_os("CHROMIUM")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("/usr/bin/chromium"));
    if !chromium.exists() {
        return Err(format!(
            "{} is missing: install Debian's chromium (`apt-get install -y chromium`, as .ci/run does)",
            chromium.display()
        ));
    }
    let node = Command::new("node").arg("--version").output();
    match node {
        Ok(o) if o.status.success() => {}
        _ => return Err("`node` is not on PATH: install Node.js 20 or newer".into()),
    }
    let modules = workspace_root().join("web/tests/node_modules/playwright-core");
    if !modules.exists() {
        return Err(format!(
            "{} is missing: run `npm ci --prefix web/tests` (as .ci/run does)",
            modules.display()
        ));
    }
    Ok((chromium, modules))
}

/// A server on its own thread and runtime, so stopping it ends its connections.
struct ServerThread {
    addr: SocketAddr,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl ServerThread {
    /// Serves `root` on `addr` (port 0 for any free port); with `tokens`, as a team server
    /// (`--tokens FILE`: every API route wants a token).
    fn start(root: &Path, addr: SocketAddr, tokens: Option<&Path>) -> ServerThread {
        let root = root.to_path_buf();
        let tokens = tokens.map(Path::to_path_buf);
        let (tx_addr, rx_addr) = mpsc::channel();
        let (stop, rx_stop) = tokio::sync::oneshot::channel::<()>();
        let thread = std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .build()
                .expect("runtime");
            rt.block_on(async move {
                // The port of a server stopped a moment ago can take a moment to free.
                let t = Instant::now();
                let listener = loop {
                    match tokio::net::TcpListener::bind(addr).await {
                        Ok(l) => break l,
                        Err(e) if t.elapsed() < Duration::from_secs(10) => {
                            let _ = e;
                            tokio::time::sleep(Duration::from_millis(100)).await;
                        }
                        Err(e) => panic!("cannot bind {addr}: {e}"),
                    }
                };
                let (state, errors) = load_bundles(&root);
                assert!(errors.is_empty(), "{errors:?}");
                let app = match tokens {
                    None => translux_server::router(state.clone()),
                    Some(file) => {
                        let args = TeamArgs {
                            tokens: Some(file),
                            ..Default::default()
                        };
                        let team = Team::start(&args, &root, state.clone()).expect("team");
                        translux_server::team::app(state.clone(), team)
                    }
                };
                tx_addr.send(listener.local_addr().unwrap()).unwrap();
                translux_server::serve_router(listener, state, app, async move {
                    let _ = rx_stop.await;
                })
                .await
                .expect("serve");
            });
            // Dropping the runtime ends whatever the graceful shutdown left running.
            rt.shutdown_timeout(Duration::from_secs(1));
        });
        // A generous limit: this test shares the machine (and the process's rayon pool,
        // which opening a bundle's occluder uses) with the suite's other tests, and in CI a
        // restart beside a validation test's walks once took over 30 s.
        let addr = rx_addr
            .recv_timeout(Duration::from_secs(180))
            .expect("the server did not start");
        ServerThread {
            addr,
            stop: Some(stop),
            thread: Some(thread),
        }
    }

    fn stop(&mut self) {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        if let Some(t) = self.thread.take() {
            let deadline = Instant::now() + Duration::from_secs(20);
            while !t.is_finished() {
                assert!(
                    Instant::now() < deadline,
                    "the server did not stop within 20 s"
                );
                std::thread::sleep(Duration::from_millis(20));
            }
            t.join().expect("server thread");
        }
    }
}

impl Drop for ServerThread {
    fn drop(&mut self) {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
    }
}

#[test]
fn viewer_in_a_real_browser() {
    if std::env::var("TRANSLUX_SKIP_BROWSER").as_deref() == Ok("1") {
        eprintln!("TRANSLUX_SKIP_BROWSER=1: the browser test is skipped");
        return;
    }
    if let Err(why) = prerequisites() {
        panic!(
            "the browser test cannot run: {why}. (Set TRANSLUX_SKIP_BROWSER=1 to skip it on a \
             machine without a browser; CI must not.)"
        );
    }

    let bundles = tempfile::Builder::new()
        .prefix("browser-bundles-")
        .tempdir_in(env!("CARGO_TARGET_TMPDIR"))
        .unwrap();
    let scene = load_scene("builtin:cornell").expect("builtin:cornell loads");
    let params = PrecomputeParams {
        patches: Some(PATCHES),
        ..Default::default()
    };
    precompute(&scene, &bundles.path().join("cornell"), &params).expect("precompute");
    // A simulated object for the absorption slider: a 3 cm cube on a floor, lit from above.
    let cube: translux_proto::scene::SceneFile = serde_json::from_value(serde_json::json!({
        "name": "simulated_cube",
        "objects": [
            {"name": "floor", "mesh": {"shape": "quad", "size": [0.2, 0.2]},
             "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
            {"name": "cube", "mesh": {"shape": "box", "size": [0.03, 0.03, 0.03]},
             "transform": {"translate": [0, 0.015, 0]},
             "material": {"type": "simulated", "sigma_s_prime": [0.5, 0.5, 0.5],
                          "sigma_a": [0.01, 0.02, 0.05], "noise": 0.03}},
        ],
        "lights": [{"type": "point", "position": [0.02, 0.08, 0.03], "intensity": [0.01, 0.01, 0.01]}],
        "camera": {"position": [0.0, 0.07, 0.12], "target": [0, 0.015, 0], "fov_deg": 40},
    }))
    .unwrap();
    let cube = translux_precompute::scene::resolve_scene(
        cube,
        Path::new("."),
        "simulated_cube".into(),
        "simulated_cube".into(),
    )
    .unwrap();
    let small = PrecomputeParams {
        patches: Some(1200),
        ..Default::default()
    };
    precompute(&cube, &bundles.path().join("simulated_cube"), &small).expect("precompute");
    // An animated scene for the timeline: 48 frames of a marble block crossing a floor and
    // turning, lit from above (one bundle per frame).
    let gallop = serde_json::json!({
        "name": "gallop",
        "animation": {"frames": 48, "fps": 24},
        "patches": {"target": 300},
        "objects": [
            {"name": "floor", "mesh": {"shape": "quad", "size": [1.2, 0.6]},
             "material": {"type": "diffuse", "albedo": [0.3, 0.55, 0.25]}},
            {"name": "block", "mesh": {"shape": "box", "size": [0.12, 0.2, 0.12]},
             "material": {"type": "translucent", "profile": {"type": "dipole", "preset": "marble"}},
             "keyframes": [{"frame": 0, "translate": [-0.45, 0.1, 0]},
                           {"frame": 47, "translate": [0.45, 0.1, 0], "rotate_deg": [0, 180, 0]}]},
        ],
        "lights": [{"type": "point", "position": [0.0, 0.6, 0.3], "intensity": [0.6, 0.6, 0.6]}],
        "camera": {"position": [0.0, 0.45, 1.1], "target": [0, 0.08, 0], "fov_deg": 45},
    });
    let gallop_file = bundles.path().join("gallop.json");
    std::fs::write(&gallop_file, gallop.to_string()).unwrap();
    let src = translux_precompute::scene::read_scene_file(&gallop_file).unwrap();
    std::fs::remove_file(&gallop_file).unwrap();
    translux_precompute::sequence::precompute_sequence(
        &src,
        &bundles.path().join("gallop"),
        &PrecomputeParams::default(),
        &|_, _| {},
    )
    .expect("the 48-frame sequence precomputes");

    let out = screenshot_dir();
    let _ = std::fs::remove_dir_all(&out);
    std::fs::create_dir_all(&out).unwrap();

    let mut server = ServerThread::start(bundles.path(), "127.0.0.1:0".parse().unwrap(), None);
    let addr = server.addr;
    let url = format!("http://{addr}/");
    let (team_dir, tokens) = team_bundles(&bundles.path().join("cornell"));
    let mut team = ServerThread::start(
        &team_dir.path().join("bundles"),
        "127.0.0.1:0".parse().unwrap(),
        Some(&tokens),
    );
    let team_url = format!("http://{}/", team.addr);

    let mut child = Command::new("node")
        .arg("web/tests/viewer.test.mjs")
        .arg(&url)
        .arg(&out)
        .arg(&team_url)
        .env("TRANSLUX_TEST_TOKEN", VIEWER_TOKEN)
        .current_dir(workspace_root())
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("cannot start node");
    let mut stdin = child.stdin.take().unwrap();
    let stdout = BufReader::new(child.stdout.take().unwrap());
    let stderr = child.stderr.take().unwrap();
    let log = std::thread::spawn(move || {
        let mut all = String::new();
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            all.push_str(&line);
            all.push('\n');
        }
        all
    });
    // The watchdog: a hung browser must not hang the test suite.
    let pid = child.id();
    let (done_tx, done_rx) = mpsc::channel::<()>();
    let watchdog = std::thread::spawn(move || {
        if done_rx.recv_timeout(SESSION_LIMIT).is_err() {
            let _ = Command::new("kill").arg("-9").arg(pid.to_string()).status();
            return true;
        }
        false
    });

    let mut result: Option<Value> = None;
    for line in stdout.lines().map_while(Result::ok) {
        let Ok(msg) = serde_json::from_str::<Value>(&line) else {
            println!("node: {line}");
            continue;
        };
        match msg["event"].as_str() {
            Some("stop-server") => {
                server.stop();
                writeln!(stdin, "stopped").unwrap();
            }
            Some("start-server") => {
                server = ServerThread::start(bundles.path(), addr, None);
                writeln!(stdin, "started").unwrap();
            }
            Some("result") => result = Some(msg),
            _ => println!("node: {line}"),
        }
    }
    let status = child.wait().unwrap();
    let _ = done_tx.send(());
    team.stop();
    let killed = watchdog.join().unwrap();
    let log = log.join().unwrap();
    println!("{log}");
    assert!(
        !killed,
        "the browser session ran past {SESSION_LIMIT:?} and was killed:\n{log}"
    );
    assert!(
        status.success(),
        "the browser test failed ({status}):\n{log}"
    );
    let result = result.expect("the script printed no result");
    std::fs::write(
        out.join("result.json"),
        serde_json::to_string_pretty(&result).unwrap(),
    )
    .unwrap();
    println!(
        "viewer measurements:\n{}",
        serde_json::to_string_pretty(&result).unwrap()
    );
    assert!(
        result["renderer"]
            .as_str()
            .unwrap_or("")
            .contains("SwiftShader")
            || std::env::var_os("CHROMIUM").is_some(),
        "expected SwiftShader WebGL2 in headless chromium: {}",
        result["renderer"]
    );

    // The downloads: the .glb against the bundle and the export's colours; the radiance the
    // page showed against the server's answer to the same request.
    let bundle = Bundle::open(&bundles.path().join("cornell")).unwrap();
    let source: Value =
        serde_json::from_slice(&std::fs::read(out.join("viewer-glb-source.json")).unwrap())
            .unwrap();
    check_glb(
        &std::fs::read(out.join("viewer.glb")).unwrap(),
        &bundle,
        &source,
    );
    // The page drew the answer to its request; the .glb baked the answer to the same request
    // with the direct light at the vertices.
    assert_eq!(
        source["request"]["direct_at"], "pixel",
        "{}",
        source["request"]
    );
    check_radiance_matches_server(&server, &source, &source["request"], "radiance");
    let mut whole = source["request"].clone();
    whole.as_object_mut().unwrap().remove("direct_at");
    check_radiance_matches_server(&server, &source, &whole, "glb_radiance");
    check_snapshot(&out.join("snapshot.png"));
    server.stop();
}

/// The team server's folder: `bundles/` with the Cornell bundle under two ids (`cornell` and
/// `cornell-copy`, one scene name), and `tokens.toml` with [`VIEWER_TOKEN`]'s hash.
fn team_bundles(cornell: &Path) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::Builder::new()
        .prefix("browser-team-")
        .tempdir_in(env!("CARGO_TARGET_TMPDIR"))
        .unwrap();
    for id in ["cornell", "cornell-copy"] {
        let to = dir.path().join("bundles").join(id);
        std::fs::create_dir_all(&to).unwrap();
        for e in std::fs::read_dir(cornell).unwrap() {
            let e = e.unwrap();
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
    let tokens = dir.path().join("tokens.toml");
    std::fs::write(
        &tokens,
        format!(
            "[[tokens]]\nname = \"viewer\"\nrole = \"viewer\"\nsha256 = \"{}\"\n",
            hash_token(VIEWER_TOKEN).unwrap()
        ),
    )
    .unwrap();
    (dir, tokens)
}

fn floats(v: &Value) -> Vec<f32> {
    v.as_array()
        .expect("an array")
        .iter()
        .map(|x| x.as_f64().expect("a number") as f32)
        .collect()
}

fn read_f32s(bin: &[u8], offset: usize, count: usize) -> Vec<f32> {
    bin[offset..offset + 4 * count]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

/// The viewer's .glb: glTF 2.0 binary layout, the bundle's mesh, colours as the export makes
/// them (`linear_colour`: exposure and tone curve, no OETF) from the radiance shown.
fn check_glb(glb: &[u8], bundle: &Bundle, source: &Value) {
    let u32_at = |o: usize| u32::from_le_bytes(glb[o..o + 4].try_into().unwrap()) as usize;
    assert_eq!(&glb[0..4], b"glTF");
    assert_eq!(u32_at(4), 2, "glTF version");
    assert_eq!(u32_at(8), glb.len(), "header length");
    let json_len = u32_at(12);
    assert_eq!(&glb[16..20], b"JSON");
    assert_eq!(json_len % 4, 0);
    let gltf: Value = serde_json::from_slice(&glb[20..20 + json_len]).expect("glTF JSON");
    let b = 20 + json_len;
    let bin_len = u32_at(b);
    assert_eq!(&glb[b + 4..b + 8], b"BIN\0");
    let bin = &glb[b + 8..b + 8 + bin_len];
    assert_eq!(b + 8 + bin_len, glb.len());

    let positions = bundle.vertex_positions();
    let triangles = bundle.triangle_vertices();
    let n = positions.len();
    let prim = &gltf["meshes"][0]["primitives"][0];
    let accessor = |name: &str| {
        let i = prim["attributes"][name].as_u64().unwrap() as usize;
        &gltf["accessors"][i]
    };
    let view_offset = |a: &Value| {
        let v = &gltf["bufferViews"][a["bufferView"].as_u64().unwrap() as usize];
        v["byteOffset"].as_u64().unwrap_or(0) as usize
    };
    for name in ["POSITION", "NORMAL", "COLOR_0"] {
        let a = accessor(name);
        assert_eq!(a["count"].as_u64(), Some(n as u64), "{name} count");
        assert_eq!(a["componentType"].as_u64(), Some(5126), "{name} is float");
        assert_eq!(a["type"].as_str(), Some("VEC3"), "{name}");
    }
    assert_eq!(
        gltf["materials"][0]["extensions"]["KHR_materials_unlit"],
        serde_json::json!({})
    );
    let pos = read_f32s(bin, view_offset(accessor("POSITION")), 3 * n);
    for (i, p) in positions.iter().enumerate() {
        assert_eq!(&pos[3 * i..3 * i + 3], p, "position {i}");
    }
    let nor = read_f32s(bin, view_offset(accessor("NORMAL")), 3 * n);
    for i in 0..n {
        let l = (nor[3 * i].powi(2) + nor[3 * i + 1].powi(2) + nor[3 * i + 2].powi(2)).sqrt();
        assert!((l - 1.0).abs() < 1e-5, "normal {i} has length {l}");
    }
    let ia = &gltf["accessors"][prim["indices"].as_u64().unwrap() as usize];
    assert_eq!(ia["componentType"].as_u64(), Some(5125), "u32 indices");
    assert_eq!(ia["count"].as_u64(), Some(3 * triangles.len() as u64));
    let io = view_offset(ia);
    for (t, tri) in triangles.iter().enumerate() {
        for (k, &want) in tri.iter().enumerate() {
            let o = io + 4 * (3 * t + k);
            let v = u32::from_le_bytes(bin[o..o + 4].try_into().unwrap());
            assert_eq!(v, want, "triangle {t}");
        }
    }
    // What the .glb baked: the whole answer at the vertices (the viewer asks for it again
    // when it draws the direct light per pixel).
    let radiance = floats(&source["glb_radiance"]);
    assert_eq!(radiance.len(), 3 * n);
    let exposure = source["exposure"].as_f64().unwrap() as f32;
    let tone: ToneMap = source["tone"].as_str().unwrap().parse().unwrap();
    let col = read_f32s(bin, view_offset(accessor("COLOR_0")), 3 * n);
    let mut lit = 0;
    for i in 0..n {
        let want = linear_colour(
            [radiance[3 * i], radiance[3 * i + 1], radiance[3 * i + 2]],
            exposure.exp2(),
            tone,
        );
        for k in 0..3 {
            let got = col[3 * i + k];
            assert!(
                (got - want[k]).abs() <= 1e-5,
                "COLOR_0[{i}][{k}] = {got}, the export's colour is {}",
                want[k]
            );
        }
        lit += usize::from(want.iter().any(|&c| c > 0.05));
    }
    // Not blank. The export is of the direct light alone (step 7 leaves `direct` on) from
    // the ceiling lamp dragged low, at the exposure the first frame set (the spot's hot
    // spot behind the block): most of the box is in shadow, exactly 0.
    assert!(
        lit > n / 20,
        "only {lit} of {n} vertices are lit in the .glb"
    );
}

/// `source[field]` is the server's answer to `request`.
fn check_radiance_matches_server(
    server: &ServerThread,
    source: &Value,
    request: &Value,
    field: &str,
) {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let url = format!(
        "http://{}/api/v1/scenes/{}/relight",
        server.addr,
        source["scene"].as_str().unwrap()
    );
    let body = request.to_string();
    let want: Vec<f32> = rt.block_on(async {
        let r = reqwest::Client::new()
            .post(&url)
            .header("content-type", "application/json")
            .header("accept", "application/octet-stream")
            .body(body)
            .send()
            .await
            .unwrap();
        assert!(r.status().is_success(), "{}", r.status());
        let bytes = r.bytes().await.unwrap();
        bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect()
    });
    let got = floats(&source[field]);
    assert_eq!(got.len(), want.len());
    let scale = want.iter().fold(0f32, |m, &x| m.max(x.abs())).max(1e-12);
    for (i, (g, w)) in got.iter().zip(&want).enumerate() {
        // The iterative solve stops at a residual tolerance; the answer is deterministic up
        // to float summation order.
        assert!(
            (g - w).abs() <= 1e-4 * scale + 1e-4 * w.abs(),
            "{field}[{i}]: the page has {g}, the server answers {w}"
        );
    }
}

/// The PNG snapshot decodes and is not one flat colour.
fn check_snapshot(path: &Path) {
    let img = image::open(path).expect("the snapshot is a PNG").to_rgb8();
    assert!(
        img.width() >= 400 && img.height() >= 300,
        "{:?}",
        img.dimensions()
    );
    let first = img.get_pixel(img.width() / 2, img.height() / 2);
    let differing = img.pixels().filter(|p| *p != first).count();
    assert!(
        differing > (img.width() * img.height() / 4) as usize,
        "the snapshot is nearly uniform"
    );
}
