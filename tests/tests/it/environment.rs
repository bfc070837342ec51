//! Environment lights end to end: a plate over a floor precomputed with environment
//! visibility, a real server on 127.0.0.1:0, relights with built-in and `.hdr` maps, and the
//! errors for maps that cannot be used (docs/environment.md).

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use reqwest::StatusCode;
use reqwest::header::{ACCEPT, CONTENT_TYPE};
use serde_json::{Value, json};
use tokio::sync::oneshot;
use translux_engine::envvis::EnvVisParams;
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::load_scene;
use translux_proto::api::{ErrorBody, Mesh, RelightResponse};
use translux_server::load_bundles;

/// Albedo of every object: a vertex under uniform radiance L·scale with nothing in the way
/// has B/π = ρ L scale.
const ALBEDO: f32 = 0.5;
/// Height of the 1 × 1 plate over the floor (above the wall's top, 1.1, so nothing hides
/// any of its sky).
const PLATE_Y: f32 = 1.5;

/// The bundles folder: `plate` (with visibility), `novis` (precomputed with `--env-bins 0`),
/// and maps beside them: `uniform3.hdr` (radiance 3), `halves.hdr` (1 for u < 0.5, else 0),
/// `broken.hdr` (not an image).
fn fixture() -> &'static PathBuf {
    static ROOT: OnceLock<PathBuf> = OnceLock::new();
    ROOT.get_or_init(|| {
        let root = crate::support::kept_folder("translux-fixture-env-");
        let scene_file = root.join("plate.json");
        let scene = json!({
            "unit_mm": 1000,
            "patches": {"target": 600},
            "objects": [
                {"name": "floor", "mesh": {"shape": "quad", "size": [4, 4]},
                 "material": {"type": "diffuse", "albedo": [ALBEDO, ALBEDO, ALBEDO]}},
                {"name": "plate", "mesh": {"shape": "quad", "size": [1, 1]},
                 "transform": {"translate": [0, PLATE_Y, 0]},
                 "material": {"type": "diffuse", "albedo": [ALBEDO, ALBEDO, ALBEDO]}},
                // A vertical wall facing +X (a quad turned from +Y to +X) far to the side.
                {"name": "wall", "mesh": {"shape": "quad", "size": [1, 1]},
                 "transform": {"rotate_deg": [0, 0, -90], "translate": [1.9, 0.6, 0]},
                 "material": {"type": "diffuse", "albedo": [ALBEDO, ALBEDO, ALBEDO]}}
            ],
            "lights": []
        });
        std::fs::write(&scene_file, scene.to_string()).unwrap();
        let loaded = load_scene(scene_file.to_str().unwrap()).expect("scene loads");
        precompute(&loaded, &root.join("plate"), &PrecomputeParams::default()).expect("precompute");
        let novis = PrecomputeParams {
            environment: EnvVisParams {
                bins: None,
                ..Default::default()
            },
            ..Default::default()
        };
        precompute(&loaded, &root.join("novis"), &novis).expect("precompute");
        std::fs::remove_file(&scene_file).unwrap();
        write_hdr(&root.join("uniform3.hdr"), 16, 8, |_| 3.0);
        write_hdr(&root.join("halves.hdr"), 16, 8, |u| {
            if u < 0.5 { 1.0 } else { 0.0 }
        });
        std::fs::write(root.join("broken.hdr"), b"#?RADIANCE\nnot really\n").unwrap();
        root
    })
}

/// An equirectangular `.hdr` of grey radiance `f(u)` (u at pixel centres).
fn write_hdr(path: &Path, w: usize, h: usize, f: impl Fn(f32) -> f32) {
    let px: Vec<image::Rgb<f32>> = (0..w * h)
        .map(|i| image::Rgb([f(((i % w) as f32 + 0.5) / w as f32); 3]))
        .collect();
    let file = std::fs::File::create(path).unwrap();
    image::codecs::hdr::HdrEncoder::new(std::io::BufWriter::new(file))
        .encode(&px, w, h)
        .unwrap();
}

struct Server {
    base: String,
    client: reqwest::Client,
    stop: Option<oneshot::Sender<()>>,
}

impl Server {
    async fn start() -> Server {
        let (state, errors) = load_bundles(fixture());
        assert!(errors.is_empty(), "{errors:?}");
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let (tx, rx) = oneshot::channel::<()>();
        tokio::spawn(translux_server::serve(listener, state, async move {
            let _ = rx.await;
        }));
        Server {
            base: format!("http://{addr}"),
            client: reqwest::Client::new(),
            stop: Some(tx),
        }
    }

    async fn relight(&self, id: &str, body: &Value) -> reqwest::Response {
        self.client
            .post(format!("{}/api/v1/scenes/{id}/relight", self.base))
            .header(CONTENT_TYPE, "application/json")
            .header(ACCEPT, "application/json")
            .body(body.to_string())
            .send()
            .await
            .unwrap()
    }

    async fn radiance(&self, lights: Value) -> Vec<[f32; 3]> {
        let r = self
            .relight("plate", &json!({"lights": lights, "components": "direct"}))
            .await;
        let status = r.status();
        let text = r.text().await.unwrap();
        assert_eq!(status, StatusCode::OK, "{text}");
        let body: RelightResponse = serde_json::from_str(&text).unwrap();
        body.radiance
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect()
    }

    async fn mesh(&self) -> Mesh {
        self.client
            .get(format!("{}/api/v1/scenes/plate/mesh", self.base))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap()
    }

    async fn expect_error(&self, id: &str, lights: Value, code: &str, needles: &[&str]) {
        let r = self.relight(id, &json!({ "lights": lights })).await;
        assert_eq!(r.status(), StatusCode::BAD_REQUEST);
        let body: ErrorBody = r.json().await.unwrap();
        assert_eq!(body.error.code, code, "{}", body.error.message);
        for n in needles {
            assert!(
                body.error.message.contains(n),
                "{:?} lacks {n:?}",
                body.error.message
            );
        }
    }

    fn stop(mut self) {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
    }
}

/// Vertices of object `name` (from the mesh's triangle ranges).
fn object_vertices(mesh: &Mesh, name: &str) -> Vec<usize> {
    let o = mesh.objects.iter().find(|o| o.name == name).unwrap();
    let first = o.first_triangle as usize * 3;
    let mut v: Vec<usize> = mesh.indices[first..first + o.triangle_count as usize * 3]
        .iter()
        .map(|&i| i as usize)
        .collect();
    v.sort_unstable();
    v.dedup();
    v
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uniform_sky_gives_pi_l_on_open_surfaces_and_shadows_under_the_plate() {
    let server = Server::start().await;
    let mesh = server.mesh().await;
    let plate = object_vertices(&mesh, "plate");
    let floor = object_vertices(&mesh, "floor");
    let pos = |v: usize| [mesh.positions[3 * v], mesh.positions[3 * v + 2]];

    // White sky, scale 2: the plate's top sees the whole upper hemisphere, so E = 2π and
    // B/π = ρ · 2 (within the partition's error, 0.05% for a uniform map).
    let white = server
        .radiance(json!([{"type": "environment", "map": "builtin:white", "scale": 2}]))
        .await;
    for &v in &plate {
        let got = white[v][1];
        assert!(
            (got / (2.0 * ALBEDO) - 1.0).abs() < 0.01,
            "plate vertex {v}: {got}"
        );
    }
    // The floor right under the plate's centre: the plate hides the cosine-weighted
    // fraction F = 4 · (1/2π) · 2 · X/√(1+X²) · atan(X/√(1+X²)), X = 0.5/PLATE_Y, of the
    // sky (the closed-form point-to-parallel-rectangle form factor, four quadrants): 0.123;
    // the wall (x = 1.9, y ∈ [0.1, 1.1], z ∈ [−0.5, 0.5]) hides (1/π)∫ (y/r)(1.9/r)/r² dA,
    // 0.020 by a 200 × 200 midpoint rule. Far from both the floor is nearly unoccluded.
    let x = 0.5 / PLATE_Y;
    let q = x / (1.0 + x * x).sqrt();
    let plate_hides = 4.0 / (2.0 * std::f32::consts::PI) * 2.0 * q * q.atan();
    let m = 200;
    let mut wall_hides = 0.0f64;
    for i in 0..m {
        for j in 0..m {
            let (y, z) = (
                0.1 + (i as f64 + 0.5) / m as f64,
                -0.5 + (j as f64 + 0.5) / m as f64,
            );
            let r2 = 1.9f64 * 1.9 + y * y + z * z;
            wall_hides += y * 1.9 / (r2 * r2) / (m * m) as f64 / std::f64::consts::PI;
        }
    }
    let hidden = plate_hides + wall_hides as f32;
    let under = floor
        .iter()
        .copied()
        .min_by(|&a, &b| {
            let (pa, pb) = (pos(a), pos(b));
            (pa[0].hypot(pa[1])).total_cmp(&pb[0].hypot(pb[1]))
        })
        .unwrap();
    let ratio = white[under][1] / (2.0 * ALBEDO);
    println!(
        "floor under the plate at {:?}: {ratio:.4}, closed form {:.4}",
        pos(under),
        1.0 - hidden
    );
    assert!(
        (ratio - (1.0 - hidden)).abs() < 0.01,
        "floor under the plate: {ratio}"
    );
    let corner = floor
        .iter()
        .copied()
        .find(|&v| pos(v)[0] < -1.9 && pos(v)[1] < -1.9)
        .unwrap();
    let open = white[corner][1] / (2.0 * ALBEDO);
    assert!(open > 0.97 && open <= 1.01, "floor corner: {open}");

    // A uniform .hdr of radiance 3 through the file path: the same pattern, 1.5 times.
    let file = server
        .radiance(json!([{"type": "environment", "map": "uniform3.hdr"}]))
        .await;
    for v in 0..white.len() {
        let want = 1.5 * white[v][0];
        assert!(
            (file[v][0] - want).abs() <= 0.02 * want + 1e-6,
            "vertex {v}"
        );
    }

    // Environment plus a point light adds up.
    let point = json!({"type": "point", "position": [0, 2, 0], "intensity": [1, 1, 1]});
    let alone = server.radiance(json!([point])).await;
    let both = server
        .radiance(json!([point, {"type": "environment", "map": "builtin:white", "scale": 2}]))
        .await;
    for v in 0..white.len() {
        let want = alone[v][2] + white[v][2];
        assert!(
            (both[v][2] - want).abs() <= 1e-4 * want + 1e-6,
            "vertex {v}"
        );
    }
    server.stop();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rotating_a_half_bright_map_by_180_degrees_moves_the_light_to_the_other_side() {
    let server = Server::start().await;
    let mesh = server.mesh().await;
    let wall = object_vertices(&mesh, "wall");
    // The wall faces +X: the map's bright half (u < 0.5) is the +X half of the sky.
    let lit = server
        .radiance(json!([{"type": "environment", "map": "halves.hdr"}]))
        .await;
    let dark = server
        .radiance(json!([{"type": "environment", "map": "halves.hdr", "rotation_deg": 180}]))
        .await;
    for &v in &wall {
        // Lit: the whole +X hemisphere has radiance 1 and the wall sees nearly all of it
        // (the floor reaches only 0.1 in front of it, the plate is small and far): B/π ≈ ρ.
        // Turned by 180°, the bright half is the −X sky, behind the wall: exactly 0, since
        // the map's edge at u = 0.5 falls on a bin boundary.
        assert!(
            lit[v][0] > 0.8 * ALBEDO && lit[v][0] < 1.001 * ALBEDO,
            "wall vertex {v}: {}",
            lit[v][0]
        );
        assert!(
            dark[v][0] < 0.01 * lit[v][0] + 1e-6,
            "wall vertex {v}: {}",
            dark[v][0]
        );
    }
    server.stop();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unusable_maps_are_clear_400s() {
    let server = Server::start().await;
    let env = |map: &str| json!([{"type": "environment", "map": map}]);
    server
        .expect_error(
            "plate",
            env("../uniform3.hdr"),
            "invalid",
            &["lights[0].map", "'..'"],
        )
        .await;
    server
        .expect_error(
            "plate",
            env("/etc/passwd"),
            "invalid",
            &["lights[0].map", "absolute"],
        )
        .await;
    server
        .expect_error(
            "plate",
            env("missing.hdr"),
            "invalid",
            &["lights[0].map", "no map"],
        )
        .await;
    server
        .expect_error(
            "plate",
            env("broken.hdr"),
            "invalid",
            &["lights[0].map", "broken.hdr", "not a valid Radiance .hdr"],
        )
        .await;
    server
        .expect_error(
            "plate",
            env("plate/manifest.json"),
            "invalid",
            &["not a .hdr"],
        )
        .await;
    server
        .expect_error(
            "plate",
            env("builtin:moon"),
            "invalid",
            &["builtin:moon", "builtin:sky"],
        )
        .await;
    server
        .expect_error(
            "novis",
            env("builtin:sky"),
            "unsupported",
            &["lights[0]", "--env-bins 0"],
        )
        .await;
    // The built-in sky works, and the message of a bad request never names server folders.
    let sky = server
        .radiance(json!([{"type": "environment", "map": "builtin:sky", "rotation_deg": 90}]))
        .await;
    assert!(
        sky.iter()
            .all(|c| c.iter().all(|x| x.is_finite() && *x >= 0.0))
    );
    assert!(sky.iter().any(|c| c[2] > 0.1));
    server.stop();
}

/// The built-in Cornell box is closed: a sky-only relight must leave every vertex at
/// exactly zero. The bases of the blocks resting on the floor used to see the sky below
/// the floor (their offset ray origins lay under it) and S carried that into the block.
#[test]
fn no_sky_reaches_inside_the_closed_cornell_box() {
    let dir = tempfile::tempdir().unwrap();
    let scene = load_scene("builtin:cornell").unwrap();
    let params = PrecomputeParams {
        patches: Some(1500),
        ..Default::default()
    };
    precompute(&scene, &dir.path().join("cornell"), &params).unwrap();
    let scene =
        translux_server::state::Scene::open("cornell", &dir.path().join("cornell")).unwrap();
    for components in ["direct", "full"] {
        let request = json!({
            "lights": [{"type": "environment", "map": "builtin:sky", "scale": 10}],
            "components": components,
        });
        let plan = translux_engine::relight::plan(
            &scene,
            translux_proto::parse_json(&request.to_string()).unwrap(),
        )
        .unwrap();
        let out = translux_engine::relight::run(&scene, &plan).unwrap();
        let lit: Vec<(usize, f32)> = out
            .radiance
            .iter()
            .enumerate()
            .map(|(k, c)| (k, c.iter().fold(0.0f32, |m, &x| m.max(x))))
            .filter(|(_, m)| *m != 0.0)
            .collect();
        assert!(
            lit.is_empty(),
            "{components}: {} vertices lit, e.g. {:?}",
            lit.len(),
            &lit[..lit.len().min(5)]
        );
    }
}
