//! End-to-end tests of `translux-server`: the small Cornell-box bundle of `support` is
//! precomputed once per test run, each test starts a server on 127.0.0.1:0 and talks HTTP to it.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use translux_engine::transport::Transport;

use glam::Vec3;
use reqwest::StatusCode;
use reqwest::header::{ACCEPT, CONTENT_TYPE};
use serde_json::{Value, json};
use tokio::sync::oneshot;
use translux_engine::radiosity::{
    PatchGeometry, Rgb, SolveParams, SparseScatter, direct_irradiance, solve, vertex_radiance,
};
use translux_engine::raycast::Occluder;
use translux_precompute::scene::load_scene;
use translux_proto::api::{
    Components, ErrorBody, Health, Mesh, RelightResponse, SceneDetail, SceneList,
};
use translux_proto::bundle::Bundle;
use translux_proto::light::Light;
use translux_server::{AppState, load_bundles};

use crate::support::{ID, PATCHES, build_bundle, bundle_dir, bundles_root, kept_folder};

/// A running server; stopped (gracefully) by [`TestServer::stop`] or when the test's runtime
/// ends.
struct TestServer {
    base: String,
    client: reqwest::Client,
    stop: Option<oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<std::io::Result<()>>,
}

impl TestServer {
    async fn start(state: AppState) -> TestServer {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let (tx, rx) = oneshot::channel::<()>();
        let task = tokio::spawn(translux_server::serve(listener, state, async move {
            let _ = rx.await;
        }));
        TestServer {
            base: format!("http://{addr}"),
            client: reqwest::Client::new(),
            stop: Some(tx),
            task,
        }
    }

    /// The server on the shared test bundle.
    async fn cornell() -> TestServer {
        let (state, errors) = load_bundles(bundles_root());
        assert!(errors.is_empty(), "{errors:?}");
        TestServer::start(state).await
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    async fn get(&self, path: &str) -> reqwest::Response {
        self.client.get(self.url(path)).send().await.unwrap()
    }

    async fn get_json<T: serde::de::DeserializeOwned>(&self, path: &str) -> T {
        let r = self.get(path).await;
        assert_eq!(r.status(), StatusCode::OK, "GET {path}");
        assert_eq!(content_type(&r), "application/json", "GET {path}");
        r.json().await.unwrap()
    }

    /// POSTs a JSON body to the scene's relight endpoint with the given `Accept`.
    async fn relight(&self, id: &str, body: &Value, accept: Option<&str>) -> reqwest::Response {
        let mut req = self
            .client
            .post(self.url(&format!("/api/v1/scenes/{id}/relight")))
            .header(CONTENT_TYPE, "application/json")
            .body(body.to_string());
        if let Some(a) = accept {
            req = req.header(ACCEPT, a);
        }
        req.send().await.unwrap()
    }

    async fn relight_json(&self, body: &Value) -> RelightResponse {
        let r = self.relight(ID, body, Some("application/json")).await;
        let status = r.status();
        let text = r.text().await.unwrap();
        assert_eq!(status, StatusCode::OK, "{text}");
        serde_json::from_str(&text).unwrap()
    }

    async fn stop(mut self) {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        self.task.await.expect("server task").expect("serve");
    }
}

fn content_type(r: &reqwest::Response) -> String {
    r.headers()
        .get(CONTENT_TYPE)
        .map(|v| v.to_str().unwrap().to_string())
        .unwrap_or_default()
}

/// Asserts an error answer: status, JSON error body with `code`, message containing each
/// of `needles`.
async fn expect_error(r: reqwest::Response, status: StatusCode, code: &str, needles: &[&str]) {
    assert_eq!(r.status(), status);
    assert_eq!(content_type(&r), "application/json");
    let body: ErrorBody = r.json().await.expect("error body is JSON");
    assert_eq!(body.error.code, code, "{}", body.error.message);
    for n in needles {
        assert!(
            body.error.message.contains(n),
            "{:?} lacks {n:?}",
            body.error.message
        );
    }
}

/// Direct irradiance for `lights` on the bundle's patches, through the library.
fn direct(bundle: &Bundle, lights: &[Light]) -> Vec<Rgb> {
    let tris: Vec<[Vec3; 3]> = bundle
        .occluder_triangles()
        .iter()
        .map(|t| t.map(Vec3::from))
        .collect();
    let occ = Occluder::new(&tris);
    let centroid: Vec<Vec3> = bundle
        .patch_corners()
        .iter()
        .map(|c| (Vec3::from(c[0]) + Vec3::from(c[1]) + Vec3::from(c[2])) / 3.0)
        .collect();
    let normal: Vec<Vec3> = bundle
        .patch_normals()
        .iter()
        .map(|&n| Vec3::from(n))
        .collect();
    direct_irradiance(
        PatchGeometry {
            centroid: &centroid,
            normal: &normal,
        },
        &occ,
        lights,
        bundle.manifest().unit_mm,
    )
    .unwrap()
}

/// The answer without a server: the same bundle through the library calls.
fn offline(bundle: &Bundle, lights: &[Light], interreflection: bool) -> Vec<Rgb> {
    let e = direct(bundle, lights);
    let (albedo, emission) = (bundle.patch_albedo(), bundle.patch_emission());
    let b = if interreflection {
        let (b, stats) = solve(
            &Transport::of(bundle),
            &SparseScatter(bundle.subsurface()),
            emission,
            &e,
            &SolveParams::default(),
            None,
        )
        .unwrap();
        assert!(stats.converged);
        b
    } else {
        (0..albedo.len())
            .map(|i| std::array::from_fn(|c| emission[i][c] + albedo[i][c] * e[i][c]))
            .collect()
    };
    let vertex_count = bundle.vertex_positions().len();
    let mut radiance = vertex_radiance(
        bundle.triangle_vertices(),
        bundle.patch_areas(),
        vertex_count,
        &b,
    );
    let components = if interreflection {
        Components::Full
    } else {
        Components::Direct
    };
    at_vertices(bundle, lights, components, &b, &e, &mut radiance);
    radiance
}

/// The direct light of opaque diffuse surfaces taken at their vertices, as the relight
/// does for `components` (engine::vertexlight, tested against closed forms in
/// `vertices`), under the bundle's materials; `e` is the lights' E per patch (no
/// environment lights here).
fn at_vertices(
    bundle: &Bundle,
    lights: &[Light],
    components: Components,
    b: &[Rgb],
    e: &[Rgb],
    radiance: &mut [Rgb],
) {
    let tris: Vec<[Vec3; 3]> = bundle
        .occluder_triangles()
        .iter()
        .map(|t| t.map(Vec3::from))
        .collect();
    let materials: Vec<_> = bundle
        .manifest()
        .objects
        .iter()
        .map(|o| &o.material)
        .collect();
    translux_engine::vertexlight::apply(
        bundle,
        &Occluder::new(&tris),
        lights,
        &translux_engine::vertexlight::opaque_objects(&materials, components),
        translux_engine::vertexlight::PatchTerms {
            radiosity: b,
            irradiance: e,
            albedo: bundle.patch_albedo(),
        },
        radiance,
    )
    .unwrap();
}

fn assert_close(got: &[f32], want: &[Rgb], rel: f32) {
    let want: Vec<f32> = want.iter().flatten().copied().collect();
    assert_eq!(got.len(), want.len());
    let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(scale > 0.0, "the scene is black");
    for (k, (g, w)) in got.iter().zip(&want).enumerate() {
        assert!(
            (g - w).abs() <= rel * w.abs().max(1e-3 * scale),
            "value {k}: {g} vs {w}"
        );
    }
}

fn floats(bytes: &[u8]) -> Vec<f32> {
    assert_eq!(bytes.len() % 4, 0);
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

/// The viewer's lists of media come from `GET /api/v1/presets`: every name the scene file
/// accepts, each with the coefficients a scene naming it gets.
#[tokio::test]
async fn presets_are_the_media_the_scene_file_accepts() {
    let s = TestServer::cornell().await;
    let p: translux_proto::api::Presets = s.get_json("/api/v1/presets").await;
    let names: Vec<&str> = p.dipole.iter().map(|d| d.name.as_str()).collect();
    assert_eq!(names, translux_proto::scene::DIPOLE_PRESETS);
    for d in &p.dipole {
        let m = translux_engine::profile::preset(&d.name).unwrap();
        assert_eq!(
            (d.sigma_s_prime, d.sigma_a, d.eta),
            (m.sigma_s_prime, m.sigma_a, m.eta)
        );
    }
    let marble = p.dipole.iter().find(|d| d.name == "marble").unwrap();
    assert_eq!(marble.eta, 1.5);
    assert_eq!((p.default_eta, p.default_coat_eta), (1.3, 1.5));
    s.stop().await;
}

#[tokio::test]
async fn scene_list_detail_health_and_index() {
    let s = TestServer::cornell().await;
    let bundle = Bundle::open(&bundle_dir()).unwrap();
    let m = bundle.manifest();

    let list: SceneList = s.get_json("/api/v1/scenes").await;
    assert_eq!(list.scenes.len(), 1);
    let summary = &list.scenes[0];
    assert_eq!(
        (summary.id.as_str(), summary.name.as_str()),
        (ID, "cornell")
    );
    assert_eq!(summary.patches, m.patch_count);
    assert_eq!(summary.vertices, m.vertex_count);
    assert_eq!(summary.objects, m.objects.len());
    assert!(summary.patches >= PATCHES / 2, "{}", summary.patches);

    let d: SceneDetail = s.get_json("/api/v1/scenes/cornell").await;
    assert_eq!(d.patches, m.patch_count);
    assert_eq!(d.triangles, m.patch_count);
    assert_eq!(d.objects.len(), m.objects.len());
    for (o, mo) in d.objects.iter().zip(&m.objects) {
        assert_eq!(
            (&o.name, &o.material, o.first_patch),
            (&mo.name, &mo.material, mo.first_patch)
        );
    }
    assert!(
        d.objects.iter().any(|o| o.material.kind() == "translucent"),
        "{:?}",
        d.objects
    );
    assert_eq!(d.lights, m.lights);
    assert!(!d.lights.is_empty());
    assert_eq!(d.camera, m.camera);
    assert_eq!(d.form_factors, m.form_factors);
    assert_eq!(d.bundle_bytes, bundle.total_bytes());
    // The raw JSON uses the proto material format.
    let raw: Value = s.get_json("/api/v1/scenes/cornell").await;
    assert!(raw["objects"][0]["material"]["type"].is_string(), "{raw}");

    let h: Health = s.get_json("/healthz").await;
    assert_eq!((h.status.as_str(), h.backend.as_str()), ("ok", "cpu"));
    assert!(!h.gpu.available);
    // The test builds its state without choosing a backend: the CPU, and /healthz says why.
    assert_eq!(
        h.gpu.reason.as_deref(),
        Some("no backend was chosen (a state made without one): the CPU relights")
    );
    assert_eq!(h.scenes, vec![ID.to_string()]);

    let r = s.get("/").await;
    assert_eq!(r.status(), StatusCode::OK);
    assert!(content_type(&r).starts_with("text/html"));
    let page = r.text().await.unwrap();
    assert!(page.contains("/api/v1/scenes") && page.contains("<title>translux"));
    assert!(
        !page.contains("http://") && !page.contains("https://"),
        "external resources"
    );

    expect_error(
        s.get("/api/v1/scenes/nope").await,
        StatusCode::NOT_FOUND,
        "not_found",
        &["\"nope\"", "cornell"],
    )
    .await;
    expect_error(
        s.get("/api/v1/scenes/nope/mesh").await,
        StatusCode::NOT_FOUND,
        "not_found",
        &["nope"],
    )
    .await;
    let r = s.get("/api/v1/scenes/%FF").await;
    expect_error(r, StatusCode::BAD_REQUEST, "bad_request", &["UTF-8"]).await;
    expect_error(
        s.get("/api/v2/whatever").await,
        StatusCode::NOT_FOUND,
        "not_found",
        &["/api/v2/whatever"],
    )
    .await;
    expect_error(
        s.get("/api/v1/scenes/cornell/relight").await,
        StatusCode::METHOD_NOT_ALLOWED,
        "method_not_allowed",
        &["GET"],
    )
    .await;
    s.stop().await;
}

#[tokio::test]
async fn mesh_is_the_bundles_viewer_mesh() {
    let s = TestServer::cornell().await;
    let bundle = Bundle::open(&bundle_dir()).unwrap();
    // Twice: the second answer comes from the cache and must be the same.
    let mesh: Mesh = s.get_json("/api/v1/scenes/cornell/mesh").await;
    let again: Mesh = s.get_json("/api/v1/scenes/cornell/mesh").await;
    assert_eq!(mesh, again);
    let nv = bundle.vertex_positions().len();
    let nt = bundle.triangle_vertices().len();
    assert_eq!(mesh.positions.len(), 3 * nv);
    assert_eq!(mesh.normals.len(), 3 * nv);
    assert_eq!(mesh.indices.len(), 3 * nt);
    assert_eq!(mesh.positions, bundle.vertex_positions().concat());
    assert_eq!(mesh.normals, bundle.vertex_normals().concat());
    assert_eq!(mesh.indices, bundle.triangle_vertices().concat());
    assert!(mesh.indices.iter().all(|&i| (i as usize) < nv));
    // Objects' triangle ranges tile 0..N in order, with the manifest's names.
    let mut next = 0;
    for (o, mo) in mesh.objects.iter().zip(&bundle.manifest().objects) {
        assert_eq!(o.name, mo.name);
        assert_eq!(o.first_triangle, next);
        assert_eq!(o.triangle_count, mo.patch_count);
        next += o.triangle_count;
    }
    assert_eq!(mesh.objects.len(), bundle.manifest().objects.len());
    assert_eq!(next as usize, nt);
    s.stop().await;
}

#[tokio::test]
async fn relight_json_and_binary_agree_and_match_the_offline_solve() {
    let s = TestServer::cornell().await;
    let bundle = Bundle::open(&bundle_dir()).unwrap();
    let nv = bundle.vertex_positions().len();

    // No lights given: the bundle's default lights, full transport.
    let json_answer = s.relight_json(&json!({})).await;
    assert_eq!(json_answer.vertex_count, nv);
    assert_eq!(json_answer.radiance.len(), 3 * nv);
    let st = &json_answer.stats;
    assert_eq!(st.solver, "jacobi");
    assert!(
        st.iterations > 0 && st.converged && st.residual <= 0.005,
        "{st:?}"
    );
    assert!(st.ms >= st.direct_ms && st.direct_ms >= 0.0, "{st:?}");
    assert_eq!(st.lights, bundle.manifest().lights.len());

    let want = offline(&bundle, &bundle.manifest().lights, true);
    assert_close(&json_answer.radiance, &want, 1e-5);

    // Binary with every Accept that asks for it (and none): the same numbers, bit for bit.
    for accept in [None, Some("application/octet-stream"), Some("*/*")] {
        let r = s.relight(ID, &json!({}), accept).await;
        assert_eq!(r.status(), StatusCode::OK, "{accept:?}");
        assert_eq!(content_type(&r), "application/octet-stream");
        let timing = r
            .headers()
            .get("server-timing")
            .unwrap()
            .to_str()
            .unwrap()
            .to_string();
        assert!(
            timing.contains("direct;dur=") && timing.contains("solve;dur="),
            "{timing}"
        );
        let bytes = r.bytes().await.unwrap();
        assert_eq!(bytes.len(), nv * 12);
        let got = floats(&bytes);
        assert_eq!(got, json_answer.radiance, "{accept:?}");
    }

    // An empty body (no Content-Type) is the same request as {}.
    let r = s
        .client
        .post(s.url("/api/v1/scenes/cornell/relight"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(floats(&r.bytes().await.unwrap()), json_answer.radiance);

    // Explicit lights of every supported type, solver "iterative".
    let lights = json!([
        {"type":"point","position":[0.1,0.45,0.05],"intensity":[0.5,0.4,0.3]},
        {"type":"spot","position":[0.0,0.52,0.0],"intensity":[2,2,2],"direction":[0,-1,0],
         "inner_deg":15,"outer_deg":30},
        {"type":"directional","direction":[0.2,-1,-0.3],"irradiance":[0.3,0.3,0.3]}
    ]);
    let answer = s
        .relight_json(&json!({"lights": lights, "solver": "iterative"}))
        .await;
    let parsed: Vec<Light> = serde_json::from_value(lights).unwrap();
    // This solve starts from the previous answer (same materials and components), so it
    // is a different iterate than the offline cold start: both have a residual ≤ 0.5%, and
    // they agree to the solver's accuracy rather than bit for bit.
    assert!(answer.stats.warm, "{:?}", answer.stats);
    assert_close(&answer.radiance, &offline(&bundle, &parsed, true), 0.15);
    assert_ne!(answer.radiance, json_answer.radiance);

    // No lights at all: a black scene (the Cornell box has no emitters).
    let dark = s.relight_json(&json!({"lights": []})).await;
    assert!(dark.radiance.iter().all(|&v| v == 0.0));
    s.stop().await;
}

#[tokio::test]
async fn material_overrides_rebuild_s_and_match_the_offline_solve() {
    let s = TestServer::cornell().await;
    let bundle = Bundle::open(&bundle_dir()).unwrap();
    let base = s.relight_json(&json!({})).await;
    // A more translucent block: S rebuilt from the stored distances.
    let body = json!({"materials": {"tall_block": {"type": "translucent",
        "profile": {"type": "dipole", "preset": "marble", "scale": 1.8}}}});
    let first = s.relight_json(&body).await;
    assert!(first.stats.materials_ms > 0.0, "{:?}", first.stats);
    // A translucency change starts from the last answer under other materials (the
    // base relight's): the offline reference below does the same.
    assert!(!base.stats.warm && first.stats.warm, "{:?}", first.stats);
    assert_ne!(first.radiance, base.radiance);
    // The same overrides again come from the cache, with the same answer: its warm start
    // is the first's answer, whose residual check the first's own last product already
    // made (F x and S F x, kept beside it), so it takes no product at all.
    let again = s.relight_json(&body).await;
    assert_eq!(again.stats.materials_ms, 0.0, "{:?}", again.stats);
    assert_eq!(again.radiance, first.radiance);
    assert_eq!(again.stats.products, 0, "{:?}", again.stats);
    assert!(first.stats.products > 0, "{:?}", first.stats);
    // The offline answer: rebuild S through the library, solve, average to vertices.
    let k = bundle
        .manifest()
        .objects
        .iter()
        .position(|o| o.name == "tall_block")
        .unwrap();
    let material: translux_proto::scene::Material =
        serde_json::from_value(body["materials"]["tall_block"].clone()).unwrap();
    // The CPU backend sums S from the bundle's radial terms (engine::sterms; checked against
    // the quadrature in precompute's subsurface tests), so the reference does too.
    let sp = translux_engine::smatrix::SParams::default();
    let terms = translux_engine::smatrix::terms_of_bundle(&bundle, &sp.quadrature);
    let (smat, _) =
        translux_engine::smatrix::rebuild_with_terms(&bundle, &[(k, material)], &sp, &terms)
            .unwrap();
    let n = bundle.patch_areas().len();
    let sv = translux_proto::csr::CsrView::new_checked(n, n, &smat.row_ptr, &smat.col, &smat.val)
        .unwrap();
    let e = direct(&bundle, &bundle.manifest().lights);
    let (b0, _) = solve(
        &Transport::of(&bundle),
        &SparseScatter(bundle.subsurface()),
        bundle.patch_emission(),
        &e,
        &SolveParams::default(),
        None,
    )
    .unwrap();
    let (b, stats) = solve(
        &Transport::of(&bundle),
        &SparseScatter(sv),
        bundle.patch_emission(),
        &e,
        &SolveParams::default(),
        Some(&b0),
    )
    .unwrap();
    assert!(stats.converged);
    let mut want = vertex_radiance(
        bundle.triangle_vertices(),
        bundle.patch_areas(),
        bundle.vertex_positions().len(),
        &b,
    );
    // The override keeps the block translucent: the diffuse vertices are the bundle's.
    at_vertices(
        &bundle,
        &bundle.manifest().lights,
        Components::Full,
        &b,
        &e,
        &mut want,
    );
    assert_close(&first.radiance, &want, 1e-5);

    // A wall's albedo: greener left wall, different picture.
    let green = s
        .relight_json(
            &json!({"materials": {"left_wall": {"type": "diffuse", "albedo": [0.1, 0.7, 0.1]}}}),
        )
        .await;
    assert_ne!(green.radiance, base.radiance);
    s.stop().await;
}

/// After one client relights, another client's finite but overflowing intensity must be a
/// 400 naming the field, as on a cold server — never the first client's answer (the solver's
/// warm start) with `iterations: 0`.
#[tokio::test]
async fn overflowing_intensity_is_a_400_and_never_another_clients_answer() {
    let s = TestServer::cornell().await;
    let a = json!({"lights":[{"type":"point","position":[0.0,0.4,0.0],"intensity":[1,1,1]}],
                   "solver":"iterative"});
    let first = s.relight_json(&a).await;
    assert!(first.stats.iterations > 0);
    for huge in [3.4e38f32, 1e37, 1e13] {
        let b = json!({"lights":[{"type":"point","position":[0.0,0.4,0.0],
                                  "intensity":[huge,huge,huge]}], "solver":"iterative"});
        let r = s.relight(ID, &b, Some("application/json")).await;
        expect_error(
            r,
            StatusCode::BAD_REQUEST,
            "invalid",
            &["lights[0].intensity[0]"],
        )
        .await;
    }
    // The largest accepted intensity is answered for real: its radiance scales with it.
    let big = json!({"lights":[{"type":"point","position":[0.0,0.4,0.0],
                                "intensity":[1e12,1e12,1e12]}], "solver":"iterative"});
    let answer = s.relight_json(&big).await;
    let ratio = answer.radiance.iter().sum::<f32>() / first.radiance.iter().sum::<f32>();
    assert!((ratio / 1e12 - 1.0).abs() < 0.02, "{ratio}");
    s.stop().await;
}

/// Out-of-range material parameters are a 400 naming the field, not a 500 from a caught
/// panic; a body with anything after its JSON value is refused.
#[tokio::test]
async fn absurd_dipole_scale_and_trailing_garbage_are_400s() {
    let s = TestServer::cornell().await;
    for scale in [1e-20, 1e20, 0.0] {
        let body = json!({"materials":{"tall_block":{"type":"translucent",
            "profile":{"type":"dipole","preset":"marble","scale":scale}}}});
        let r = s.relight(ID, &body, Some("application/json")).await;
        expect_error(
            r,
            StatusCode::BAD_REQUEST,
            "invalid",
            &["materials.tall_block.profile.scale", "[0.001, 1000]"],
        )
        .await;
    }
    let r = s
        .client
        .post(s.url(&format!("/api/v1/scenes/{ID}/relight")))
        .header(CONTENT_TYPE, "application/json")
        .body("{} xyz")
        .send()
        .await
        .unwrap();
    expect_error(
        r,
        StatusCode::BAD_REQUEST,
        "bad_request",
        &["trailing characters"],
    )
    .await;
    s.stop().await;
}

/// Method names are the client's to choose: only standard ones become label values, the
/// rest count as `other`, so random methods cannot grow `/metrics` without bound.
#[tokio::test]
async fn random_http_methods_do_not_become_metric_labels() {
    let s = TestServer::cornell().await;
    for k in 0..40 {
        let m = reqwest::Method::from_bytes(format!("ATTACK{k}").as_bytes()).unwrap();
        let r = s.client.request(m, s.url("/healthz")).send().await.unwrap();
        assert!(r.status().is_client_error(), "{}", r.status());
    }
    let text = s.get("/metrics").await.text().await.unwrap();
    assert!(!text.contains("ATTACK"), "a method name became a label");
    assert!(text.contains("method=\"other\""), "{text}");
    let series = text
        .lines()
        .filter(|l| l.starts_with("translux_http_request_duration_seconds_count"))
        .count();
    assert!(series < 10, "{series} series after 40 odd methods");
    s.stop().await;
}

/// A precompute that crashed leaves `.ID.tmp-PID-…`; the server removes such folders when
/// their process is gone and they are idle, and never a live writer's.
#[test]
fn abandoned_precompute_temporaries_are_removed_and_live_ones_kept() {
    let dir = tempfile::tempdir().unwrap();
    let aged = |name: &str, age_s: u64| {
        let p = dir.path().join(name);
        std::fs::create_dir(&p).unwrap();
        std::fs::write(p.join("ff_val.f32"), [0u8; 16]).unwrap();
        let then = std::time::SystemTime::now() - std::time::Duration::from_secs(age_s);
        std::fs::File::open(&p).unwrap().set_modified(then).unwrap();
    };
    // PIDs above Linux's largest pid_max (2^22) never run.
    aged(".cup.tmp-4294000-1-1", 3600);
    aged(".fresh.tmp-4294001-1-1", 5);
    aged(&format!(".mine.tmp-{}-1-1", std::process::id()), 3600);
    aged(".notes.d", 3600);
    let (_state, errors) = translux_server::load_bundles(dir.path());
    assert!(errors.is_empty(), "{errors:?}");
    let mut left: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    let mine = format!(".mine.tmp-{}-1-1", std::process::id());
    assert_eq!(left, vec![".fresh.tmp-4294001-1-1", &mine, ".notes.d"]);
}

#[tokio::test]
async fn direct_differs_from_full_and_full_is_never_darker() {
    let s = TestServer::cornell().await;
    let bundle = Bundle::open(&bundle_dir()).unwrap();
    // The paper's ceiling lamp alone. (builtin:cornell's spot behind the block makes a hot
    // spot on its back face that S spreads over the block: there full is darker than
    // direct's ρ̄E, light moved rather than lost.)
    let lamp =
        json!([{"type": "point", "position": [0.0, 0.5, 0.0], "intensity": [0.8, 0.8, 0.8]}]);
    let lights: Vec<Light> = serde_json::from_value(lamp.clone()).unwrap();
    let full = s
        .relight_json(&json!({"components": "full", "lights": lamp}))
        .await;
    let direct = s
        .relight_json(&json!({"components": "direct", "lights": lamp}))
        .await;
    assert_eq!(direct.stats.solver, "none");
    assert_eq!(direct.stats.iterations, 0);
    assert_close(&direct.radiance, &offline(&bundle, &lights, false), 1e-5);
    assert_eq!(full.radiance.len(), direct.radiance.len());
    let mut brighter = 0;
    for (k, (f, d)) in full.radiance.iter().zip(&direct.radiance).enumerate() {
        assert!(f >= d, "value {k}: full {f} < direct {d}");
        brighter += (f > &(d * 1.01)) as usize;
    }
    // Inter-reflection lights up most of the box, including what the lamp cannot see.
    assert!(
        brighter > full.radiance.len() / 2,
        "{brighter} of {}",
        full.radiance.len()
    );
    s.stop().await;
}

#[tokio::test]
async fn bad_input_gets_its_status_and_a_message_naming_the_problem() {
    let s = TestServer::cornell().await;
    let post = |path: &str| s.client.post(s.url(path));
    let relight = "/api/v1/scenes/cornell/relight";

    // Unknown scene.
    let r = s
        .relight("attic", &json!({}), Some("application/json"))
        .await;
    expect_error(r, StatusCode::NOT_FOUND, "not_found", &["attic"]).await;

    // Malformed JSON: the message gives line and column.
    let r = post(relight)
        .header(CONTENT_TYPE, "application/json")
        .body("{\n  \"lights\": [\n    {\"type\": \"point\",\n")
        .send()
        .await
        .unwrap();
    expect_error(r, StatusCode::BAD_REQUEST, "bad_request", &["line 4"]).await;
    // A wrong type: the message names the field.
    let body = json!({"lights":[{"type":"point","position":[0,0.5,0],"intensity":[1,"x",1]}]});
    let r = s.relight(ID, &body, None).await;
    expect_error(
        r,
        StatusCode::BAD_REQUEST,
        "bad_request",
        &["lights[0].intensity[1]", "line 1"],
    )
    .await;
    // NaN is not JSON.
    let r = post(relight)
        .header(CONTENT_TYPE, "application/json")
        .body(r#"{"lights":[{"type":"point","position":[0,0.5,0],"intensity":[NaN,1,1]}]}"#)
        .send()
        .await
        .unwrap();
    expect_error(
        r,
        StatusCode::BAD_REQUEST,
        "bad_request",
        &["lights[0].intensity"],
    )
    .await;

    // Out-of-range values: `invalid`, with the field path and the rule.
    let r = post(relight)
        .header(CONTENT_TYPE, "application/json")
        .body(r#"{"lights":[{"type":"point","position":[0,0.5,0],"intensity":[1e39,1,1]}]}"#)
        .send()
        .await
        .unwrap();
    expect_error(
        r,
        StatusCode::BAD_REQUEST,
        "invalid",
        &["lights[0].intensity[0] must be finite and in [0, 1000000000000]"],
    )
    .await;
    let body = json!({"lights":[
        {"type":"directional","direction":[0,-1,0],"irradiance":[1,1,1]},
        {"type":"point","position":[0,0.5,0],"intensity":[1,-2,1]}]});
    let r = s.relight(ID, &body, Some("application/json")).await;
    expect_error(
        r,
        StatusCode::BAD_REQUEST,
        "invalid",
        &["lights[1].intensity[1] must be finite and in [0, 1000000000000]"],
    )
    .await;
    let body = json!({"lights":[{"type":"directional","direction":[0,0,0],"irradiance":[1,1,1]}]});
    let r = s.relight(ID, &body, None).await;
    expect_error(
        r,
        StatusCode::BAD_REQUEST,
        "invalid",
        &["lights[0].direction"],
    )
    .await;

    // Finite but absurd: an error or an answer, never a hang, a 500 or a NaN.
    let body = json!({"lights":[
        {"type":"point","position":[1e30,-1e30,3e38],"intensity":[3e38,3e38,3e38]},
        {"type":"point","position":[0,0.3,0],"intensity":[3e38,3e38,3e38]}]});
    let r = s.relight(ID, &body, None).await;
    expect_error(
        r,
        StatusCode::BAD_REQUEST,
        "invalid",
        &["lights[0].intensity[0] must be finite and in [0, 1000000000000]"],
    )
    .await;
    // That overflow must not poison the next relight (the solver warm-starts from the last
    // answer with the same materials): an ordinary light still gets the library's answer.
    let lights = json!([{"type":"point","position":[0.05,0.4,0.02],"intensity":[1,1,1]}]);
    let answer = s
        .relight_json(&json!({"lights": lights, "solver": "iterative"}))
        .await;
    assert!(answer.radiance.iter().all(|v| v.is_finite()));
    let parsed: Vec<Light> = serde_json::from_value(lights).unwrap();
    assert_close(
        &answer.radiance,
        &offline(&Bundle::open(&bundle_dir()).unwrap(), &parsed, true),
        0.15,
    );

    // Unknown fields, at the top and inside a light.
    let r = s.relight(ID, &json!({"light": []}), None).await;
    expect_error(
        r,
        StatusCode::BAD_REQUEST,
        "bad_request",
        &["unknown field `light`"],
    )
    .await;
    let body =
        json!({"lights":[{"type":"point","position":[0,0.5,0],"intensity":[1,1,1],"radius":1}]});
    let r = s.relight(ID, &body, None).await;
    expect_error(
        r,
        StatusCode::BAD_REQUEST,
        "bad_request",
        &["lights[0]", "radius"],
    )
    .await;
    let r = s
        .relight(ID, &json!({"components": "everything"}), None)
        .await;
    expect_error(
        r,
        StatusCode::BAD_REQUEST,
        "bad_request",
        &["components", "everything"],
    )
    .await;

    // Valid but not supported yet: `unsupported`, saying what.
    for (body, needle) in [
        (
            json!({"solver": "inverse"}),
            "precomputed without the transfer matrix T",
        ),
        (
            json!({"materials": {"floor": {"type": "translucent",
                "profile": {"type": "dipole", "preset": "marble"}}}}),
            "\"floor\" was precomputed as diffuse",
        ),
    ] {
        let r = s.relight(ID, &body, Some("application/json")).await;
        expect_error(r, StatusCode::BAD_REQUEST, "unsupported", &[needle]).await;
    }
    // An environment map that is not there is invalid, and names the light and the map.
    let body = json!({"lights": [{"type": "environment", "map": "no-such-map.hdr"}]});
    let r = s.relight(ID, &body, None).await;
    expect_error(
        r,
        StatusCode::BAD_REQUEST,
        "invalid",
        &["lights[0]", "no-such-map.hdr"],
    )
    .await;
    // A material override for an object that does not exist is invalid, not unsupported.
    let body = json!({"materials": {"teapot": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}}});
    let r = s.relight(ID, &body, None).await;
    expect_error(
        r,
        StatusCode::BAD_REQUEST,
        "invalid",
        &["materials.teapot", "tall_block"],
    )
    .await;

    // Over 1 MiB.
    let big = format!("{{\"lights\":[],\"pad\":\"{}\"}}", "x".repeat(2 << 20));
    let r = post(relight)
        .header(CONTENT_TYPE, "application/json")
        .body(big)
        .send()
        .await
        .unwrap();
    expect_error(
        r,
        StatusCode::PAYLOAD_TOO_LARGE,
        "payload_too_large",
        &["1 MiB"],
    )
    .await;

    // Not JSON.
    let r = post(relight)
        .header(CONTENT_TYPE, "text/plain")
        .body("{}")
        .send()
        .await
        .unwrap();
    expect_error(
        r,
        StatusCode::UNSUPPORTED_MEDIA_TYPE,
        "unsupported_media_type",
        &["text/plain"],
    )
    .await;
    let r = post(relight).body("{}").send().await.unwrap();
    expect_error(
        r,
        StatusCode::UNSUPPORTED_MEDIA_TYPE,
        "unsupported_media_type",
        &["Content-Type"],
    )
    .await;

    // An answer format the endpoint does not offer.
    let r = s.relight(ID, &json!({}), Some("image/png")).await;
    expect_error(
        r,
        StatusCode::NOT_ACCEPTABLE,
        "not_acceptable",
        &["image/png"],
    )
    .await;

    // The server is still fine.
    let ok = s.relight_json(&json!({})).await;
    assert!(ok.vertex_count > 0);
    s.stop().await;
}

/// Copies a bundle folder (flat: a bundle has no sub-folders).
fn copy_bundle(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
}

#[tokio::test]
async fn a_corrupt_bundle_is_skipped_and_the_good_one_served() {
    let tmp = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap();
    copy_bundle(&bundle_dir(), &tmp.path().join("good"));
    copy_bundle(&bundle_dir(), &tmp.path().join("bad"));
    let ff_val = tmp.path().join("bad").join("ff_val.f32");
    let len = std::fs::metadata(&ff_val).unwrap().len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&ff_val)
        .unwrap()
        .set_len(len - 4)
        .unwrap();
    // A writer's hidden temporary folder and a stray file are passed over silently.
    std::fs::create_dir(tmp.path().join(".good.tmp-1")).unwrap();
    std::fs::write(tmp.path().join("README"), "not a bundle").unwrap();

    let (state, errors) = load_bundles(tmp.path());
    assert_eq!(state.ids(), vec!["good".to_string()]);
    assert_eq!(errors.len(), 1, "{errors:?}");
    assert_eq!(errors[0].0, "bad");
    assert!(
        errors[0].1.starts_with("ff_val.f32 is truncated"),
        "{}",
        errors[0].1
    );

    let s = TestServer::start(state).await;
    let list: SceneList = s.get_json("/api/v1/scenes").await;
    let ids: Vec<&str> = list.scenes.iter().map(|x| x.id.as_str()).collect();
    assert_eq!(ids, ["good"]);
    let h: Health = s.get_json("/healthz").await;
    assert_eq!(h.scenes, ["good"]);
    expect_error(
        s.get("/api/v1/scenes/bad").await,
        StatusCode::NOT_FOUND,
        "not_found",
        &["bad"],
    )
    .await;
    let r = s
        .relight("good", &json!({}), Some("application/json"))
        .await;
    assert_eq!(r.status(), StatusCode::OK);
    s.stop().await;

    // A folder that does not exist is one error, not a panic.
    let (state, errors) = load_bundles(&tmp.path().join("missing"));
    assert!(state.is_empty());
    assert_eq!(errors.len(), 1);
}

/// A simulated object over HTTP: the scene detail gives its absorption range, a `sigma_a`
/// override is served (S re-weighted from the stored walks, also on the render route), and
/// what the walks cannot serve is a 400 naming the object and what to do.
#[tokio::test]
async fn a_simulated_object_changes_absorption_over_http_and_refuses_the_rest() {
    let tmp = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap();
    let scene_file = tmp.path().join("cube.json");
    std::fs::write(
        &scene_file,
        json!({
            "name": "sim",
            "objects": [
                {"name": "floor", "mesh": {"shape": "quad", "size": [0.2, 0.2]},
                 "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
                {"name": "cube", "mesh": {"shape": "box", "size": [0.02, 0.02, 0.02]},
                 "transform": {"translate": [0, 0.01, 0]},
                 "material": {"type": "simulated", "sigma_s_prime": [0.5, 0.5, 0.5],
                              "sigma_a": [0.01, 0.02, 0.04], "noise": 0.05}},
            ],
            "lights": [{"type": "point", "position": [0.03, 0.06, 0.02], "intensity": [0.01, 0.01, 0.01]}],
        })
        .to_string(),
    )
    .unwrap();
    let loaded = translux_precompute::scene::load_scene_file(&scene_file).unwrap();
    let bundles = tmp.path().join("bundles");
    build_bundle(&loaded, &bundles.join("sim"), 800);
    let (state, errors) = load_bundles(&bundles);
    assert!(errors.is_empty(), "{errors:?}");
    let s = TestServer::start(state).await;

    let detail: SceneDetail = s.get_json("/api/v1/scenes/sim").await;
    let cube = detail.objects.iter().find(|o| o.name == "cube").unwrap();
    let range = cube
        .absorption
        .clone()
        .expect("a simulated object's absorption range");
    assert_eq!(range.sigma_a, [0.01, 0.02, 0.04]);
    for c in 0..3 {
        assert!(
            (range.sigma_a_min[c] - range.sigma_a[c] / 16.0).abs() < 1e-7,
            "{range:?}"
        );
    }
    assert!(
        detail
            .objects
            .iter()
            .find(|o| o.name == "floor")
            .unwrap()
            .absorption
            .is_none()
    );

    let ok = |r: reqwest::Response| async move {
        let status = r.status();
        let text = r.text().await.unwrap();
        assert_eq!(status, StatusCode::OK, "{text}");
        serde_json::from_str::<RelightResponse>(&text).unwrap()
    };
    let base = ok(s.relight("sim", &json!({}), Some("application/json")).await).await;
    let material = |extra: Value| {
        let mut m = json!({"type": "simulated", "sigma_s_prime": [0.5, 0.5, 0.5],
                           "sigma_a": [0.01, 0.02, 0.04], "noise": 0.05});
        for (k, v) in extra.as_object().unwrap() {
            m[k] = v.clone();
        }
        json!({"materials": {"cube": m}})
    };
    // Less absorption: a brighter cube, more light on the floor too.
    let clearer = ok(s
        .relight(
            "sim",
            &material(json!({"sigma_a": [0.0025, 0.005, 0.01]})),
            Some("application/json"),
        )
        .await)
    .await;
    assert!(clearer.stats.materials_ms > 0.0, "{:?}", clearer.stats);
    let total = |r: &RelightResponse| r.radiance.iter().map(|&v| f64::from(v)).sum::<f64>();
    assert!(
        total(&clearer) > 1.01 * total(&base),
        "{} vs {}",
        total(&clearer),
        total(&base)
    );
    // The same material as the bundle's gives the bundle's answer, to the solver's 0.5%
    // residual (a relight after another material starts from that one's answer).
    let same = ok(s
        .relight("sim", &material(json!({})), Some("application/json"))
        .await)
    .await;
    let peak = base.radiance.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let worst = same
        .radiance
        .iter()
        .zip(&base.radiance)
        .map(|(a, b)| (a - b).abs() / peak)
        .fold(0.0f32, f32::max);
    eprintln!(
        "same σa: worst difference {worst} of the peak, totals {} / {}",
        total(&same),
        total(&base)
    );
    assert!(
        worst < 0.01,
        "the bundle's own σa re-weighted differs by {worst} of the peak"
    );
    assert!((total(&same) / total(&base) - 1.0).abs() < 0.005);

    for (extra, needles) in [
        (
            json!({"sigma_a": [0.0001, 0.02, 0.04]}),
            vec!["cube", "precompute"],
        ),
        (
            json!({"sigma_s_prime": [0.6, 0.5, 0.5]}),
            vec!["cube", "precompute"],
        ),
    ] {
        let r = s
            .relight("sim", &material(extra.clone()), Some("application/json"))
            .await;
        assert_eq!(r.status(), StatusCode::BAD_REQUEST, "{extra}");
        let body: ErrorBody = r.json().await.unwrap();
        for n in needles {
            assert!(
                body.error.message.contains(n),
                "{extra}: {:?} lacks {n:?}",
                body.error.message
            );
        }
    }
    // A dipole on the simulated cube, walks on the diffuse floor: refused, naming what to do.
    let dipole = json!({"materials": {"cube": {"type": "translucent",
        "profile": {"type": "dipole", "preset": "marble"}}}});
    let r = s.relight("sim", &dipole, Some("application/json")).await;
    assert!(r.status().is_client_error(), "{}", r.status());
    let walked_floor = json!({"materials": {"floor": {"type": "simulated", "preset": "marble"}}});
    let r = s
        .relight("sim", &walked_floor, Some("application/json"))
        .await;
    assert!(r.status().is_client_error(), "{}", r.status());
    let body: ErrorBody = r.json().await.unwrap();
    assert!(
        body.error
            .message
            .contains("precompute the scene with \"floor\" simulated"),
        "{}",
        body.error.message
    );
    s.stop().await;
}

/// POSTs a JSON body to the scene's render endpoint.
async fn post_render(s: &TestServer, body: &Value, accept: Option<&str>) -> reqwest::Response {
    let mut req = s
        .client
        .post(s.url("/api/v1/scenes/cornell/render"))
        .header(CONTENT_TYPE, "application/json")
        .body(body.to_string());
    if let Some(a) = accept {
        req = req.header(ACCEPT, a);
    }
    req.send().await.unwrap()
}

/// Renders and decodes, asserting a 200 PNG answer.
async fn render_png(s: &TestServer, body: &Value) -> image::RgbImage {
    let r = post_render(s, body, Some("image/png")).await;
    let status = r.status();
    let ct = content_type(&r);
    let bytes = r.bytes().await.unwrap();
    assert_eq!(
        status,
        StatusCode::OK,
        "{}",
        String::from_utf8_lossy(&bytes)
    );
    assert_eq!(ct, "image/png");
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n", "PNG signature");
    image::load_from_memory_with_format(&bytes, image::ImageFormat::Png)
        .expect("the answer decodes as PNG")
        .to_rgb8()
}

/// Mean of the red channel over the columns `cols` (all rows).
fn mean_red(img: &image::RgbImage, cols: std::ops::Range<u32>) -> f64 {
    let mut sum = 0.0;
    let mut n = 0.0;
    for y in 0..img.height() {
        for x in cols.clone() {
            sum += img.get_pixel(x, y).0[0] as f64;
            n += 1.0;
        }
    }
    sum / n
}

/// With the direct light per pixel (the render route's default) the short box's shadow on
/// the floor has a sharp edge; at the vertices it spreads over a patch. A light just under
/// the ceiling right above the box casts a ring of shadow around its base; looking straight
/// down (through the culled ceiling), each row across the middle of the picture crosses the
/// ring's outer edge on the floor. Measured as the transition width, contrast / largest
/// step between neighbouring floor pixels (the yellow box top left out).
#[tokio::test]
async fn direct_light_per_pixel_gives_sharp_shadow_edges() {
    let s = TestServer::cornell().await;
    let picture = |direct_at: &str| {
        json!({"width": 200, "height": 200, "exposure": 0.0, "components": "direct",
            "direct_at": direct_at,
            "lights": [{"type": "point", "position": [0.09, 0.54, 0.07],
                "intensity": [0.5, 0.5, 0.5]}],
            "camera": {"position": [0.09, 1.0, 0.07], "target": [0.09, 0.0, 0.07],
                "up": [0.0, 0.0, -1.0], "fov_deg": 40}})
    };
    // Per row: the contrast between lit and shadowed floor, and the largest step between
    // neighbouring floor pixels, from the box's centre to short of the right (green) wall.
    let rows = |img: &image::RgbImage| -> Vec<(f64, f64)> {
        (85..115)
            .map(|y| {
                let floor: Vec<Option<f64>> = (100..145)
                    .map(|x| {
                        let p = img.get_pixel(x, y).0.map(f64::from);
                        let yellow = p[0] > 20.0 && p[2] < 0.6 * p[0];
                        (!yellow).then_some(0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2])
                    })
                    .collect();
                let lum: Vec<f64> = floor.iter().flatten().copied().collect();
                let (lo, hi) = lum
                    .iter()
                    .fold((f64::MAX, 0f64), |(a, b), &v| (a.min(v), b.max(v)));
                let step = floor
                    .windows(2)
                    .filter_map(|w| Some((w[1]? - w[0]?).abs()))
                    .fold(0.0, f64::max);
                (hi - lo, step)
            })
            .collect()
    };
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let pixel = render_png(&s, &picture("pixel")).await;
    let vertex = render_png(&s, &picture("vertex")).await;
    // Kept for a look: target/tmp/shadow-{pixel,vertex}.png.
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR"));
    pixel.save(dir.join("shadow-pixel.png")).unwrap();
    vertex.save(dir.join("shadow-vertex.png")).unwrap();
    // The width: the per-pixel picture's contrast over each picture's largest step.
    let (rp, rv) = (rows(&pixel), rows(&vertex));
    for (y, (c, _)) in rp.iter().enumerate() {
        assert!(
            *c > 60.0,
            "row {}: no shadow to measure (contrast {c:.0})",
            85 + y
        );
    }
    let wp = median(rp.iter().map(|(c, s)| c / s).collect());
    let wv = median(rp.iter().zip(&rv).map(|((c, _), (_, s))| c / s).collect());
    println!("shadow edge: {wp:.1} px per pixel, {wv:.1} px at the vertices");
    assert!(wp <= 3.0, "per pixel the edge is {wp:.1} px wide");
    assert!(
        wv >= 2.0 * wp,
        "at the vertices {wv:.1} px, per pixel {wp:.1} px"
    );
    // Away from edges the two agree: the mean brightness differs little.
    let mean = |img: &image::RgbImage| {
        img.as_raw().iter().map(|&v| v as f64).sum::<f64>() / img.as_raw().len() as f64
    };
    let (mp, mv) = (mean(&pixel), mean(&vertex));
    assert!(
        (mp - mv).abs() < 0.05 * mv,
        "mean {mp:.1} per pixel, {mv:.1} at the vertices"
    );
    s.stop().await;
}

/// A material override that gives the marble block a glossy coat: the render gains a
/// highlight, and nothing else changes (the transport ignores the coat, S is not rebuilt).
#[tokio::test]
async fn a_specular_coat_adds_a_highlight_to_renders_only() {
    let s = TestServer::cornell().await;
    // The scene's own medium (marble ×16), with a coat.
    let glossy = json!({"tall_block": {"type": "translucent",
        "profile": {"type": "dipole", "preset": "marble",
            "scale": translux_precompute::builtin::CORNELL_BLOCK_SCALE},
        "specular": {"roughness": 0.3}}});
    let picture = |materials: &Value, specular: bool, components: &str| {
        // Looking down at the block's top from where it mirrors the ceiling light (the
        // paper's lamp alone).
        json!({"width": 160, "height": 120, "exposure": -4.0, "materials": materials,
            "specular": specular, "components": components,
            "lights": [{"type": "point", "position": [0.0, 0.5, 0.0], "intensity": [0.8, 0.8, 0.8]}],
            "camera": {"position": [-0.18, 0.5, -0.16], "target": [-0.09, 0.33, -0.08],
                "fov_deg": 50}})
    };
    let none = json!({});
    let plain = render_png(&s, &picture(&none, true, "full")).await;
    let on = render_png(&s, &picture(&glossy, true, "full")).await;
    let off = render_png(&s, &picture(&glossy, false, "full")).await;
    // Without the pass, the coat changes nothing.
    assert_eq!(off.as_raw(), plain.as_raw());
    // With it, light is only added, and a highlight of some size appears.
    let mut added = 0u64;
    let mut brighter = 0;
    for (a, b) in on.as_raw().iter().zip(off.as_raw()) {
        assert!(a >= b, "the specular pass darkened a pixel: {a} < {b}");
        added += u64::from(a - b);
        brighter += usize::from(u16::from(*a) > u16::from(*b) + 8);
    }
    assert!(
        brighter >= 20 && added > 2000,
        "{brighter} pixels brighter by more than 8, {added} added in all"
    );
    // Components that isolate a transport path get no highlight.
    let sub_on = render_png(&s, &picture(&glossy, true, "subsurface_only")).await;
    let sub_off = render_png(&s, &picture(&glossy, false, "subsurface_only")).await;
    assert_eq!(sub_on.as_raw(), sub_off.as_raw());

    // The relight answer is the same with and without the coat, and S is not rebuilt.
    let relit = s.relight_json(&json!({"materials": glossy})).await;
    let bare = s.relight_json(&json!({})).await;
    assert_eq!(relit.stats.materials_ms, 0.0, "{:?}", relit.stats);
    let scale = bare.radiance.iter().fold(0f32, |m, v| m.max(v.abs()));
    for (a, b) in relit.radiance.iter().zip(&bare.radiance) {
        // Both solves stop at the iterative solver's residual tolerance.
        assert!((a - b).abs() <= 5e-3 * scale, "{a} vs {b}");
    }

    // A roughness out of range names the field.
    let bad = json!({"materials": {"tall_block": {"type": "translucent",
        "profile": {"type": "dipole", "preset": "marble"}, "specular": {"roughness": 0.0}}}});
    let r = s.relight(ID, &bad, Some("application/json")).await;
    expect_error(
        r,
        StatusCode::BAD_REQUEST,
        "invalid",
        &["materials.tall_block.specular.roughness"],
    )
    .await;
    s.stop().await;
}

#[tokio::test]
async fn render_answers_a_png_of_the_relit_scene() {
    let s = TestServer::cornell().await;
    let bundle = Bundle::open(&bundle_dir()).unwrap();

    // The bundle's lights and camera, at the requested size, direct light at the vertices.
    let body = json!({"width": 160, "height": 120, "exposure": -1.0, "direct_at": "vertex"});
    let img = render_png(&s, &body).await;
    assert_eq!(img.dimensions(), (160, 120));
    let colours: std::collections::HashSet<[u8; 3]> = img.pixels().map(|p| p.0).collect();
    assert!(colours.len() > 50, "{} distinct colours", colours.len());
    // The camera looks into the box through its (culled) front wall: the centre is lit, the
    // corners are outside the box (background black).
    assert_ne!(img.get_pixel(80, 60).0, [0, 0, 0]);
    assert_eq!(img.get_pixel(0, 0).0, [0, 0, 0]);

    // The same pixels as the library's renderer on the relight route's radiance: the render
    // route relights through the same path.
    let relit = s.relight_json(&json!({})).await;
    let radiance: Vec<[f32; 3]> = relit
        .radiance
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    let want = translux_engine::render::render(
        bundle.vertex_positions(),
        bundle.triangle_vertices(),
        &radiance,
        &bundle.manifest().camera,
        &translux_engine::render::RenderParams {
            width: 160,
            height: 120,
            exposure: -1.0,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(img.as_raw(), want.as_raw());

    // Moving the light changes the picture: near the red (left, −x) wall the left third is
    // redder than with the light near the green (right) wall.
    let light = |x: f32| {
        json!({"width": 120, "height": 90, "components": "direct", "lights": [
            {"type": "point", "position": [x, 0.45, 0.0], "intensity": [0.3, 0.3, 0.3]}]})
    };
    let left = render_png(&s, &light(-0.2)).await;
    let right = render_png(&s, &light(0.2)).await;
    assert_ne!(left.as_raw(), right.as_raw());
    assert!(
        mean_red(&left, 0..40) > mean_red(&right, 0..40) + 5.0,
        "{} vs {}",
        mean_red(&left, 0..40),
        mean_red(&right, 0..40)
    );

    // A camera, a tone curve, an empty body (800 × 600 by default), and no Accept header.
    let cam = json!({"width": 64, "height": 64, "tone": "filmic", "background": [0.2, 0.2, 0.2],
        "camera": {"position": [0.0, 0.3, 0.25], "target": [0.0, 0.1, -0.2], "fov_deg": 60}});
    let inside = render_png(&s, &cam).await;
    assert_eq!(inside.dimensions(), (64, 64));
    assert_ne!(inside.as_raw(), img.as_raw());
    let r = s
        .client
        .post(s.url("/api/v1/scenes/cornell/render"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    let big = image::load_from_memory(&r.bytes().await.unwrap()).unwrap();
    assert_eq!((big.width(), big.height()), (800, 600));
    s.stop().await;
}

#[tokio::test]
async fn render_rejects_bad_input_in_the_json_error_format() {
    let s = TestServer::cornell().await;
    for (body, status, code, needles) in [
        (
            json!({"width": 0}),
            400,
            "invalid",
            &["width must be an integer in 1..=8192"][..],
        ),
        (json!({"height": 9000}), 400, "invalid", &["height", "9000"]),
        (json!({"width": -3}), 400, "bad_request", &["width"]),
        (
            json!({"exposure": 1000}),
            400,
            "invalid",
            &["exposure must be finite"],
        ),
        (
            json!({"tone": "aces"}),
            400,
            "bad_request",
            &["tone", "aces"],
        ),
        (
            json!({"hieght": 3}),
            400,
            "bad_request",
            &["unknown field `hieght`"],
        ),
        (
            json!({"camera": {"position": [0, 0, 1], "target": [0, 0, 1]}}),
            400,
            "invalid",
            &["camera.target must differ from position"],
        ),
        (
            json!({"camera": {"position": [0, 0, 1], "target": [0, 0, 0], "fov_deg": 0}}),
            400,
            "invalid",
            &["camera.fov_deg"],
        ),
        (
            json!({"camera": {"position": [0, 0, 1], "target": [0, 0, 0], "up": [0, 0, 1]}}),
            400,
            "invalid",
            &["camera.up must not be parallel"],
        ),
        (
            json!({"camera": {"position": [0, 0, 1], "target": [0, 0, 0], "zoom": 2}}),
            400,
            "bad_request",
            &["camera", "zoom"],
        ),
        // The relight fields are checked as on /relight.
        (
            json!({"lights": [{"type": "point", "position": [0, 0.5, 0], "intensity": [1, -1, 1]}]}),
            400,
            "invalid",
            &["lights[0].intensity[1] must be finite and in [0, 1000000000000]"],
        ),
        (
            json!({"solver": "inverse"}),
            400,
            "unsupported",
            &["--inverse"],
        ),
    ] {
        let r = post_render(&s, &body, None).await;
        expect_error(r, StatusCode::from_u16(status).unwrap(), code, needles).await;
    }
    let r = post_render(&s, &json!({}), Some("application/json")).await;
    expect_error(
        r,
        StatusCode::NOT_ACCEPTABLE,
        "not_acceptable",
        &["image/png"],
    )
    .await;
    let r = s
        .client
        .post(s.url("/api/v1/scenes/attic/render"))
        .send()
        .await
        .unwrap();
    expect_error(r, StatusCode::NOT_FOUND, "not_found", &["attic"]).await;
    expect_error(
        s.get("/api/v1/scenes/cornell/render").await,
        StatusCode::METHOD_NOT_ALLOWED,
        "method_not_allowed",
        &["GET"],
    )
    .await;
    s.stop().await;
}

// ---- Exposure by default, and the exported .glb (metres, named objects, trimesh) -------------
//
// Renders and exports default to the viewer's automatic exposure (the Cornell box's lit walls
// are well above 1, so EV 0 clips most of the picture); the .glb is in metres and has one
// named node per scene object; an independent reader (Python's trimesh) sees its colours.

/// Fraction of the lit pixels (not the black background) with a channel at 255, and how many
/// pixels are lit.
fn clipped_fraction(img: &image::RgbImage) -> (f64, usize) {
    let lit: Vec<&image::Rgb<u8>> = img.pixels().filter(|p| p.0 != [0, 0, 0]).collect();
    let clipped = lit.iter().filter(|p| p.0.contains(&255)).count();
    (clipped as f64 / lit.len().max(1) as f64, lit.len())
}

/// A render's `X-Exposure` header as a number.
fn exposure_header(r: &reqwest::Response) -> f32 {
    r.headers()
        .get("x-exposure")
        .expect("the render answer has X-Exposure")
        .to_str()
        .unwrap()
        .parse()
        .unwrap()
}

#[tokio::test]
async fn render_defaults_to_the_viewers_auto_exposure() {
    let s = TestServer::cornell().await;
    // The viewer's rule on the relight route's radiance (relit first, so that the render's
    // own relight starts from this converged solution and answers the same radiance).
    let relit = s.relight_json(&json!({})).await;
    let radiance: Vec<[f32; 3]> = relit
        .radiance
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    let want = translux_engine::render::auto_exposure(&radiance);
    assert!(
        want < -1.0,
        "the Cornell box needs a negative exposure, got {want}"
    );

    // `{}`: auto, 800 × 600, and the answer says which EV it used.
    let r = post_render(&s, &json!({}), None).await;
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(exposure_header(&r), want);
    let auto = image::load_from_memory(&r.bytes().await.unwrap())
        .unwrap()
        .to_rgb8();
    let (auto_clipped, lit) = clipped_fraction(&auto);
    assert!(
        lit > (800 * 600) / 4,
        "{lit} lit pixels: the box fills the view"
    );
    assert!(
        auto_clipped < 0.10,
        "{:.1}% of the lit pixels clip at EV {want}",
        100.0 * auto_clipped
    );

    // "auto" is the default spelled out; the number it chose gives the same picture.
    for body in [json!({"exposure": "auto"}), json!({"exposure": want})] {
        let r = post_render(&s, &body, None).await;
        assert_eq!(r.status(), StatusCode::OK, "{body}");
        assert_eq!(exposure_header(&r), want, "{body}");
        let img = image::load_from_memory(&r.bytes().await.unwrap())
            .unwrap()
            .to_rgb8();
        assert_eq!(img.as_raw(), auto.as_raw(), "{body}");
    }

    // An explicit number is used as given, as before: EV 0 clips most of the box.
    let r = post_render(&s, &json!({"exposure": 0}), None).await;
    assert_eq!(exposure_header(&r), 0.0);
    let ev0 = image::load_from_memory(&r.bytes().await.unwrap())
        .unwrap()
        .to_rgb8();
    let (ev0_clipped, _) = clipped_fraction(&ev0);
    assert!(ev0_clipped > 0.5, "{ev0_clipped}");
    eprintln!(
        "Cornell box ({PATCHES} patches), 800 × 600: auto exposure {want} EV clips {:.1}% of \
         the lit pixels; EV 0 clips {:.1}%",
        100.0 * auto_clipped,
        100.0 * ev0_clipped
    );

    // Neither a string other than "auto" nor null is an exposure.
    for bad in [json!({"exposure": "bright"}), json!({"exposure": null})] {
        let r = post_render(&s, &bad, None).await;
        expect_error(
            r,
            StatusCode::BAD_REQUEST,
            "bad_request",
            &["exposure", "\"auto\""],
        )
        .await;
    }
    s.stop().await;
}

/// A Cornell box precomputed as a centimetre scene (unit_mm 10, the same coordinates), kept
/// outside the served fixture folder so that the other tests still see one scene.
fn centimetre_bundle() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let mut scene = load_scene("builtin:cornell").expect("builtin:cornell loads");
        scene.file.unit_mm = 10.0;
        let dir = kept_folder("translux-fixture-cm-").join("cornell_cm");
        build_bundle(&scene, &dir, 200);
        dir
    })
}

/// A .glb's JSON and BIN chunks.
fn glb_chunks(glb: &[u8]) -> (Value, &[u8]) {
    let word = |at: usize| u32::from_le_bytes(glb[at..at + 4].try_into().unwrap()) as usize;
    assert_eq!(&glb[..4], b"glTF");
    assert_eq!(word(8), glb.len());
    let json_len = word(12);
    assert_eq!(&glb[16..20], b"JSON");
    let json: Value = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
    let bin_at = 20 + json_len;
    assert_eq!(&glb[bin_at + 4..bin_at + 8], b"BIN\0");
    (json, &glb[bin_at + 8..bin_at + 8 + word(bin_at)])
}

/// Accessor `k`'s data as little-endian 4-byte words (f32 or u32 alike).
fn accessor_words(json: &Value, bin: &[u8], k: &Value) -> Vec<[u8; 4]> {
    let a = &json["accessors"][k.as_u64().unwrap() as usize];
    let v = &json["bufferViews"][a["bufferView"].as_u64().unwrap() as usize];
    let at = v["byteOffset"].as_u64().unwrap_or(0) + a["byteOffset"].as_u64().unwrap_or(0);
    let per = if a["type"] == "VEC3" { 3 } else { 1 };
    let n = a["count"].as_u64().unwrap() as usize * per;
    bin[at as usize..at as usize + 4 * n]
        .chunks_exact(4)
        .map(|c| c.try_into().unwrap())
        .collect()
}

fn accessor_f32s(json: &Value, bin: &[u8], k: &Value) -> Vec<f32> {
    accessor_words(json, bin, k)
        .into_iter()
        .map(f32::from_le_bytes)
        .collect()
}

fn accessor_u32s(json: &Value, bin: &[u8], k: &Value) -> Vec<u32> {
    accessor_words(json, bin, k)
        .into_iter()
        .map(u32::from_le_bytes)
        .collect()
}

/// Opens a bundle as the server does and relights it with its own lights.
fn relit_scene(
    dir: &Path,
) -> (
    translux_server::state::Scene,
    translux_engine::relight::RelightPlan,
    Vec<[f32; 3]>,
) {
    let scene = translux_server::state::Scene::open("cm", dir).unwrap();
    let plan = translux_engine::relight::plan(&scene, Default::default()).unwrap();
    let radiance = translux_engine::relight::run(&scene, &plan)
        .unwrap()
        .radiance;
    (scene, plan, radiance)
}

#[test]
fn export_glb_is_in_metres_with_one_named_node_per_object() {
    use translux_engine::export::linear_colour;
    use translux_engine::picture::{MeshFormat, export};
    use translux_proto::api::{Exposure, ToneMap};

    let (scene, plan, radiance) = relit_scene(centimetre_bundle());
    let b = &scene.bundle;
    let m = b.manifest();
    assert_eq!(m.unit_mm, 10.0);
    let out = export(
        &scene,
        &plan,
        Exposure::Auto,
        ToneMap::Srgb,
        MeshFormat::Glb,
    )
    .unwrap();
    // The viewer's rule on the relit radiance.
    assert_eq!(
        out.exposure,
        translux_engine::render::auto_exposure(&radiance)
    );
    let scale = 2f32.powf(out.exposure);
    let (json, bin) = glb_chunks(&out.bytes);

    // One node per object, named after it, in the manifest's order, each with its own mesh.
    let names: Vec<&str> = json["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n["name"].as_str().unwrap())
        .collect();
    let want: Vec<&str> = m.objects.iter().map(|o| o.name.as_str()).collect();
    assert_eq!(names, want);
    assert!(names.contains(&"tall_block"));
    let mut triangles = 0;
    let mut clipped = 0;
    let mut vertices = 0;
    for (node, o) in json["nodes"].as_array().unwrap().iter().zip(&m.objects) {
        let mesh = &json["meshes"][node["mesh"].as_u64().unwrap() as usize];
        assert_eq!(mesh["name"], o.name.as_str());
        let prim = &mesh["primitives"][0];
        let indices = accessor_u32s(&json, bin, &prim["indices"]);
        // Its triangles are its patch range: the same corners, rebased to its own vertices.
        let range = o.first_patch as usize..(o.first_patch + o.patch_count) as usize;
        assert_eq!(indices.len(), 3 * range.len(), "{}", o.name);
        triangles += range.len();
        let mut used: Vec<u32> = b.triangle_vertices()[range.clone()]
            .iter()
            .flatten()
            .copied()
            .collect();
        used.sort_unstable();
        used.dedup();
        let positions = accessor_f32s(&json, bin, &prim["attributes"]["POSITION"]);
        let colours = accessor_f32s(&json, bin, &prim["attributes"]["COLOR_0"]);
        assert_eq!(positions.len(), 3 * used.len(), "{}", o.name);
        for (t, local) in b.triangle_vertices()[range].iter().zip(indices.chunks(3)) {
            for (&v, &l) in t.iter().zip(local) {
                assert_eq!(used[l as usize], v, "{}", o.name);
            }
        }
        for (j, &v) in used.iter().enumerate() {
            // Metres: a centimetre scene's coordinates × 0.01.
            let p = b.vertex_positions()[v as usize];
            for c in 0..3 {
                let want = (f64::from(p[c]) * 0.01) as f32;
                assert_eq!(positions[3 * j + c], want, "{} vertex {v}", o.name);
            }
            let want = linear_colour(radiance[v as usize], scale, ToneMap::Srgb);
            assert_eq!(colours[3 * j..3 * j + 3], want, "{} vertex {v}", o.name);
            clipped += usize::from(want.contains(&1.0));
        }
        vertices += used.len();
    }
    assert_eq!(triangles, b.triangle_vertices().len());
    assert_eq!(vertices, b.vertex_positions().len());
    // Auto exposure clips few vertices; EV 0 (the old default) clips most of them.
    let auto_clipped = clipped as f64 / vertices as f64;
    assert!(auto_clipped < 0.10, "{:.1}% clipped", 100.0 * auto_clipped);
    let ev0 = export(
        &scene,
        &plan,
        Exposure::Ev(0.0),
        ToneMap::Srgb,
        MeshFormat::Glb,
    )
    .unwrap();
    assert_eq!(ev0.exposure, 0.0);
    let (json0, bin0) = glb_chunks(&ev0.bytes);
    let (mut clipped0, mut n0) = (0, 0);
    for mesh in json0["meshes"].as_array().unwrap() {
        let c = accessor_f32s(
            &json0,
            bin0,
            &mesh["primitives"][0]["attributes"]["COLOR_0"],
        );
        n0 += c.len() / 3;
        clipped0 += c.chunks(3).filter(|c| c.contains(&1.0)).count();
    }
    let ev0_clipped = clipped0 as f64 / n0 as f64;
    assert!(ev0_clipped > 0.5, "{ev0_clipped}");
    eprintln!(
        ".glb of the centimetre Cornell box: auto exposure {} EV, {:.1}% of vertices with a \
         channel at 1.0; EV 0: {:.1}%",
        out.exposure,
        100.0 * auto_clipped,
        100.0 * ev0_clipped
    );

    // PLY keeps scene units and says how long one is.
    let ply = export(
        &scene,
        &plan,
        Exposure::Auto,
        ToneMap::Srgb,
        MeshFormat::Ply,
    )
    .unwrap();
    let header = translux_engine::export::ply_header_in(
        b.vertex_positions().len(),
        b.triangle_vertices().len(),
        ply.exposure,
        ToneMap::Srgb,
        10.0,
    );
    assert!(ply.bytes.starts_with(header.as_bytes()));
    assert!(header.contains("1 unit = 10 mm"), "{header}");
    let first: Vec<f32> = ply.bytes[header.len()..header.len() + 12]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    assert_eq!(first, b.vertex_positions()[0]);
}

/// Loads a .glb with trimesh and prints, per geometry, its vertex count and colours, and per
/// node its geometry. Exit status 3: python3 has no trimesh (or numpy).
const TRIMESH_SCRIPT: &str = r#"
import json, sys
try:
    import numpy as np
    import trimesh
except ImportError as e:
    print(f"cannot import: {e}", file=sys.stderr)
    sys.exit(3)
path = sys.argv[1]
out = {"version": trimesh.__version__, "colors": {}, "attributes": {}, "vertices": {}, "nodes": {}}
# As a plain load sees it: the primitives carry the unlit material, so trimesh keeps COLOR_0
# as the "color" vertex attribute of its TextureVisuals.
scene = trimesh.load(path, force="scene")
for name, g in scene.geometry.items():
    out["attributes"][name] = np.asarray(g.visual.vertex_attributes["color"]).tolist()
# Without materials: ColorVisuals, whose vertex_colors are 8-bit RGBA.
scene = trimesh.load(path, force="scene", skip_materials=True)
for name, g in scene.geometry.items():
    out["colors"][name] = np.asarray(g.visual.vertex_colors)[:, :3].tolist()
    out["vertices"][name] = len(g.vertices)
for node in scene.graph.nodes_geometry:
    out["nodes"][node] = scene.graph[node][1]
json.dump(out, sys.stdout)
"#;

#[test]
fn trimesh_reads_the_exported_vertex_colours() {
    use translux_engine::picture::{MeshFormat, export};
    use translux_proto::api::{Exposure, ToneMap};

    let (scene, plan, _) = relit_scene(centimetre_bundle());
    let out = export(
        &scene,
        &plan,
        Exposure::Auto,
        ToneMap::Srgb,
        MeshFormat::Glb,
    )
    .unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("cornell_cm.glb");
    std::fs::write(&path, &out.bytes).unwrap();

    const INSTALL: &str = "`bash scripts/test` installs it (pip install trimesh)";
    let run = std::process::Command::new("python3")
        .arg("-c")
        .arg(TRIMESH_SCRIPT)
        .arg(&path)
        .output()
        .unwrap_or_else(|e| {
            panic!("cannot run python3 ({e}); this test needs python3 with trimesh: {INSTALL}")
        });
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        run.status.code() != Some(3),
        "python3 has no trimesh ({}); {INSTALL}",
        stderr.trim()
    );
    assert!(
        run.status.success(),
        "trimesh failed to load the .glb: {stderr}"
    );
    let seen: Value = serde_json::from_slice(&run.stdout).unwrap();

    // What the file says: per mesh (named after its object), the float COLOR_0.
    let (json, bin) = glb_chunks(&out.bytes);
    let meshes = json["meshes"].as_array().unwrap();
    assert_eq!(meshes.len(), scene.bundle.manifest().objects.len());
    assert_eq!(
        seen["colors"].as_object().unwrap().len(),
        meshes.len(),
        "{seen}"
    );
    for (node, mesh) in json["nodes"].as_array().unwrap().iter().zip(meshes) {
        let name = mesh["name"].as_str().unwrap();
        // trimesh names the node and its geometry after the object.
        assert_eq!(seen["nodes"][node["name"].as_str().unwrap()], name);
        let colours = accessor_f32s(&json, bin, &mesh["primitives"][0]["attributes"]["COLOR_0"]);
        let n = colours.len() / 3;
        assert_eq!(seen["vertices"][name], n, "{name}");
        let got = seen["colors"][name].as_array().unwrap();
        let attrs = seen["attributes"][name].as_array().unwrap();
        assert_eq!((got.len(), attrs.len()), (n, n), "{name}");
        for (k, want) in colours.chunks(3).enumerate() {
            for c in 0..3 {
                // vertex_colors: 8-bit, within rounding of 255 × the linear value.
                let byte = got[k][c].as_f64().unwrap();
                let exact = 255.0 * f64::from(want[c]);
                assert!(
                    (byte - exact).abs() <= 0.5 + 1e-6,
                    "{name} vertex {k}: trimesh {byte}, file {exact}"
                );
                // The plain load's attribute: the float itself.
                let attr = attrs[k][c].as_f64().unwrap();
                assert!(
                    (attr - f64::from(want[c])).abs() < 1e-6,
                    "{name} vertex {k}"
                );
            }
        }
    }
    eprintln!(
        "trimesh {} read {} geometries with their vertex colours",
        seen["version"],
        meshes.len()
    );
}

/// Renders as OpenEXR, asserting a 200 `image/x-exr` answer; the image and `X-Exposure`.
async fn render_exr(s: &TestServer, body: &Value, accept: &str) -> (image::Rgb32FImage, f32) {
    let r = post_render(s, body, Some(accept)).await;
    let status = r.status();
    let ct = content_type(&r);
    let ev = exposure_header(&r);
    let bytes = r.bytes().await.unwrap();
    assert_eq!(
        status,
        StatusCode::OK,
        "{}",
        String::from_utf8_lossy(&bytes)
    );
    assert_eq!(ct, "image/x-exr");
    assert_eq!(
        &bytes[..4],
        &[0x76, 0x2f, 0x31, 0x01],
        "OpenEXR magic number"
    );
    let img = image::load_from_memory_with_format(&bytes, image::ImageFormat::OpenExr)
        .expect("the answer decodes as OpenEXR")
        .to_rgb32f();
    (img, ev)
}

#[tokio::test]
async fn render_answers_a_linear_exr_for_accept_image_x_exr() {
    let s = TestServer::cornell().await;
    let bundle = Bundle::open(&bundle_dir()).unwrap();
    let relit = s.relight_json(&json!({})).await;
    let radiance: Vec<[f32; 3]> = relit
        .radiance
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    let linear = |params: &translux_engine::render::RenderParams| {
        translux_engine::render::render_linear(
            bundle.vertex_positions(),
            bundle.triangle_vertices(),
            &radiance,
            &bundle.manifest().camera,
            params,
        )
        .unwrap()
    };
    let mean = |img: &image::Rgb32FImage| {
        img.as_raw().iter().map(|&v| f64::from(v)).sum::<f64>() / img.as_raw().len() as f64
    };
    let close = |got: &image::Rgb32FImage, want: &image::Rgb32FImage| {
        assert_eq!(got.dimensions(), want.dimensions());
        for (k, (g, w)) in got.as_raw().iter().zip(want.as_raw()).enumerate() {
            // Half-float precision: the file holds half floats.
            assert!(
                (g - w).abs() <= 1e-3 * w.abs() + 1e-6,
                "value {k}: {g} vs {w}"
            );
        }
        let (g, w) = (mean(got), mean(want));
        assert!((g - w).abs() <= 1e-3 * w.abs(), "mean {g} vs {w}");
    };

    // An explicit exposure scales the radiance by 2^EV; the background is linear as asked;
    // the tone curve does not apply.
    let body = json!({"width": 160, "height": 120, "exposure": -1.0, "tone": "filmic",
        "direct_at": "vertex",
        "background": [0.2, 0.4, 0.6]});
    let (exr, ev) = render_exr(&s, &body, "image/x-exr").await;
    assert_eq!(exr.dimensions(), (160, 120));
    assert_eq!(ev, -1.0);
    let params = translux_engine::render::RenderParams {
        width: 160,
        height: 120,
        exposure: -1.0,
        tone: translux_engine::render::ToneMap::Filmic,
        background: [0.2, 0.4, 0.6],
        ..Default::default()
    };
    let want = linear(&params);
    close(&exr, &want);
    // Stored as half floats: the background within half precision (2⁻¹¹ relative).
    for (g, w) in exr.get_pixel(0, 0).0.iter().zip([0.2f32, 0.4, 0.6]) {
        assert!((g - w).abs() <= w / 2048.0, "background {g} vs {w}");
    }
    let centre = exr.get_pixel(80, 60).0;
    assert!(centre.iter().all(|&v| v > 0.0), "{centre:?}");
    // Linear, not display values: the lit walls of the Cornell box exceed 1 somewhere at
    // EV 0, which no PNG value can.
    let unexposed = linear(&translux_engine::render::RenderParams {
        exposure: 0.0,
        ..params
    });
    assert!(unexposed.as_raw().iter().any(|&v| v > 1.0));

    // The PNG of the same request is these values through the tone curve and the OETF.
    let png = render_png(&s, &body).await;
    let mut covered = 0;
    for (l, d) in exr.pixels().zip(png.pixels()) {
        let background =
            (l.0.iter().zip(params.background)).all(|(a, b)| (a - b).abs() <= b / 2048.0);
        if background {
            continue;
        }
        covered += 1;
        let want = translux_engine::render::display_rgb8(l.0, 1.0, params.tone);
        for c in 0..3 {
            assert!(d.0[c].abs_diff(want[c]) <= 1, "{:?} vs {want:?}", d.0);
        }
    }
    assert!(covered > 1000, "{covered} covered pixels");

    // `auto` (the default) writes the radiance unscaled and says EV 0; EXR wins over PNG when
    // preferred by q; the default background is black.
    let body = json!({"width": 96, "height": 72, "direct_at": "vertex"});
    let (exr, ev) = render_exr(&s, &body, "image/png;q=0.5, image/x-exr").await;
    assert_eq!(ev, 0.0);
    close(
        &exr,
        &linear(&translux_engine::render::RenderParams {
            width: 96,
            height: 72,
            ..Default::default()
        }),
    );
    assert_eq!(exr.get_pixel(0, 0).0, [0.0; 3]);

    // Neither type acceptable: 406 naming both.
    for accept in ["image/jpeg", "image/x-exr;q=0, image/png;q=0", "text/html"] {
        let r = post_render(&s, &json!({}), Some(accept)).await;
        expect_error(
            r,
            StatusCode::NOT_ACCEPTABLE,
            "not_acceptable",
            &["image/png", "image/x-exr"],
        )
        .await;
    }
    s.stop().await;
}

/// An animated scene (`docs/scenes.md#animation`): a sequence folder is one scene with
/// `frames`; `frame` in a relight or render picks the frame, `?frame=` the mesh and detail;
/// each frame's answer is that frame bundle's own relight; a frame out of range is a 400
/// naming it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_animated_scene_is_served_frame_by_frame() {
    let tmp = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap();
    let scene_file = tmp.path().join("roll.json");
    std::fs::write(
        &scene_file,
        json!({
            "name": "roll",
            "animation": {"frames": 6, "fps": 30},
            "patches": {"target": 400},
            "objects": [
                {"name": "floor", "mesh": {"shape": "quad", "size": [1, 1]},
                 "material": {"type": "diffuse", "albedo": [0.6, 0.6, 0.6]}},
                {"name": "ball", "mesh": {"shape": "sphere", "radius": 0.08, "segments": 12},
                 "material": {"type": "translucent", "profile": {"type": "dipole", "preset": "marble"}},
                 "keyframes": [{"frame": 0, "translate": [-0.3, 0.08, 0]},
                               {"frame": 5, "translate": [0.3, 0.08, 0], "rotate_deg": [0, 0, -200]}]}
            ],
            "lights": [{"type": "point", "position": [0.25, 0.5, 0.2], "intensity": [1, 1, 1]}],
        })
        .to_string(),
    )
    .unwrap();
    let src = translux_precompute::scene::read_scene_file(&scene_file).unwrap();
    let bundles = tmp.path().join("bundles");
    let params = translux_precompute::pipeline::PrecomputeParams::default();
    let report = translux_precompute::sequence::precompute_sequence(
        &src,
        &bundles.join("roll"),
        &params,
        &|_, _| {},
    )
    .unwrap();
    assert_eq!(report.computed(), 6);
    let (state, errors) = load_bundles(&bundles);
    assert!(errors.is_empty(), "{errors:?}");
    let s = TestServer::start(state).await;

    let list: SceneList = s.get_json("/api/v1/scenes").await;
    assert_eq!(list.scenes.len(), 1);
    assert_eq!((list.scenes[0].frames, list.scenes[0].fps), (6, Some(30.0)));
    let detail: SceneDetail = s.get_json("/api/v1/scenes/roll?frame=4").await;
    assert_eq!((detail.frames, detail.frame), (6, 4));

    // The ball moves to the right frame by frame, in the mesh as in the bundles.
    let mut xs = Vec::new();
    for k in 0..6 {
        let mesh: Mesh = s
            .get_json(&format!("/api/v1/scenes/roll/mesh?frame={k}"))
            .await;
        let o = mesh.objects.iter().find(|o| o.name == "ball").unwrap();
        let tri = &mesh.indices
            [3 * o.first_triangle as usize..3 * (o.first_triangle + o.triangle_count) as usize];
        let x = tri
            .iter()
            .map(|&v| mesh.positions[3 * v as usize])
            .sum::<f32>()
            / tri.len() as f32;
        assert!(
            (x - (-0.3 + 0.12 * k as f32)).abs() < 0.01,
            "frame {k}: ball at x = {x}"
        );
        xs.push(x);
    }

    // Each frame's relight is that frame bundle's own answer, and the frames differ.
    let mut answers = Vec::new();
    for k in [0u32, 3, 5] {
        let r = s
            .relight("roll", &json!({"frame": k}), Some("application/json"))
            .await;
        assert_eq!(r.status(), StatusCode::OK);
        let got: RelightResponse = r.json().await.unwrap();
        let alone = translux_server::state::Scene::open(
            "alone",
            &bundles.join("roll").join(format!("frame-{k:04}")),
        )
        .unwrap();
        let plan =
            translux_engine::relight::plan(&alone, translux_proto::parse_json("{}").unwrap())
                .unwrap();
        let want = translux_engine::relight::run(&alone, &plan).unwrap();
        let want: Vec<f32> = want.radiance.iter().flatten().copied().collect();
        assert_eq!(got.radiance.len(), want.len());
        let worst = got
            .radiance
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs() / b.abs().max(1e-3))
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "frame {k}: {worst}");
        answers.push(got.radiance);
    }
    assert_ne!(answers[0], answers[1]);

    // Frames out of range and frames of a still scene.
    expect_error(
        s.relight("roll", &json!({"frame": 6}), None).await,
        StatusCode::BAD_REQUEST,
        "bad_request",
        &["frame 6 is out of range", "6 frames (0 to 5)"],
    )
    .await;
    expect_error(
        s.get("/api/v1/scenes/roll/mesh?frame=-1").await,
        StatusCode::BAD_REQUEST,
        "bad_request",
        &["bad frame \"-1\""],
    )
    .await;
    let r = s
        .client
        .post(s.url("/api/v1/scenes/roll/render"))
        .header(CONTENT_TYPE, "application/json")
        .body(json!({"frame": 9, "width": 32, "height": 24}).to_string())
        .send()
        .await
        .unwrap();
    expect_error(r, StatusCode::BAD_REQUEST, "bad_request", &["frame 9"]).await;
    let r = s
        .client
        .post(s.url("/api/v1/scenes/roll/render"))
        .header(CONTENT_TYPE, "application/json")
        .body(json!({"frame": 2, "width": 32, "height": 24}).to_string())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    s.stop().await;
}
