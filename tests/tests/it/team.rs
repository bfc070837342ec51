//! End-to-end tests of the team features: tokens and roles on every route, uploads and
//! precompute jobs, cancellation, the memory budget, and logs free of tokens. Each test
//! starts its own server (the full router of `translux_server::team::app`) on 127.0.0.1:0.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use reqwest::StatusCode;
use reqwest::header::{ACCEPT, AUTHORIZATION, CONTENT_TYPE, LOCATION, WWW_AUTHENTICATE};
use reqwest::multipart::{Form, Part};
use serde_json::{Value, json};
use tokio::sync::oneshot;
use translux_proto::api::{RelightResponse, SceneList};
use translux_server::ServerParams;
use translux_server::auth::{Role, hash_token, required_role};
use translux_server::team::TeamArgs;

const VIEWER: &str = "tlx_viewer_0000000000000000000000000000";
const EDITOR: &str = "tlx_editor_1111111111111111111111111111";
const ADMIN: &str = "tlx_admin_22222222222222222222222222222";
const BAD: &str = "tlx_unknown_333333333333333333333333333";
/// An editor whose token has its own work limit of 1 s (`work_s`).
const BRIEF: &str = "tlx_brief_44444444444444444444444444444";

// ---------------------------------------------------------------------------------------
// Log capture: every test's server logs into one buffer, at debug level for every crate.

#[derive(Clone, Default)]
struct Captured(Arc<Mutex<Vec<u8>>>);

impl Write for Captured {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(b);
        Ok(b.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

fn logs() -> &'static Captured {
    static LOGS: OnceLock<Captured> = OnceLock::new();
    LOGS.get_or_init(|| {
        let c = Captured::default();
        let w = c.clone();
        tracing_subscriber::fmt()
            .with_env_filter(tracing_subscriber::EnvFilter::new("debug"))
            .with_ansi(false)
            .with_writer(move || w.clone())
            .try_init()
            .expect("the test binary's log subscriber");
        c
    })
}

// ---------------------------------------------------------------------------------------
// Fixtures.

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
}

/// A bundles folder holding the Cornell bundle under each of `ids`.
fn bundles_with(ids: &[&str]) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    for id in ids {
        copy_dir(&crate::support::bundle_dir(), &dir.path().join(id));
    }
    dir
}

fn tokens_file(dir: &Path) -> PathBuf {
    let path = dir.join("tokens.toml");
    let mut text = String::new();
    for (name, role, token) in [
        ("vic", "viewer", VIEWER),
        ("eddie", "editor", EDITOR),
        ("ada", "admin", ADMIN),
        ("bree", "editor", BRIEF),
    ] {
        text.push_str(&format!(
            "[[tokens]]\nname = \"{name}\"\nrole = \"{role}\"\nsha256 = \"{}\"\n",
            hash_token(token).unwrap()
        ));
        if token == BRIEF {
            text.push_str("work_s = 1\n");
        }
        text.push('\n');
    }
    std::fs::write(&path, text).unwrap();
    path
}

struct Server {
    base: String,
    client: reqwest::Client,
    bundles: PathBuf,
    _stop: oneshot::Sender<()>,
}

impl Server {
    /// A server on `bundles` with the team settings `args` (tokens added unless `open`).
    async fn start(bundles: &Path, args: TeamArgs, open: bool) -> Server {
        Server::start_with(bundles, args, open, ServerParams::default()).await
    }

    /// [`Server::start`] with the pool's settings `params`.
    async fn start_with(
        bundles: &Path,
        mut args: TeamArgs,
        open: bool,
        params: ServerParams,
    ) -> Server {
        logs();
        if !open && args.tokens.is_none() {
            let secrets = tempfile::tempdir().unwrap().keep();
            args.tokens = Some(tokens_file(&secrets));
        }
        let (base, stop) = crate::support::start_team_server(bundles, &args, params).await;
        Server {
            base,
            client: reqwest::Client::new(),
            bundles: bundles.to_path_buf(),
            _stop: stop,
        }
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    fn req(
        &self,
        method: reqwest::Method,
        path: &str,
        token: Option<&str>,
    ) -> reqwest::RequestBuilder {
        let r = self.client.request(method, self.url(path));
        match token {
            Some(t) => r.header(AUTHORIZATION, format!("Bearer {t}")),
            None => r,
        }
    }

    async fn get_json(&self, path: &str, token: Option<&str>) -> Value {
        let r = self
            .req(reqwest::Method::GET, path, token)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::OK, "GET {path}");
        r.json().await.unwrap()
    }

    async fn relight(&self, id: &str, token: Option<&str>) -> RelightResponse {
        let r = self
            .req(
                reqwest::Method::POST,
                &format!("/api/v1/scenes/{id}/relight"),
                token,
            )
            .header(ACCEPT, "application/json")
            .header(CONTENT_TYPE, "application/json")
            .body("{}")
            .send()
            .await
            .unwrap();
        let status = r.status();
        let text = r.text().await.unwrap();
        assert_eq!(status, StatusCode::OK, "relight {id}: {text}");
        serde_json::from_str(&text).unwrap()
    }

    /// Waits (polling) until job `id` is final; its record.
    async fn wait_job(&self, id: &str, token: &str) -> Value {
        let t = Instant::now();
        loop {
            let r = self
                .get_json(&format!("/api/v1/jobs/{id}"), Some(token))
                .await;
            let s = r["state"].as_str().unwrap().to_string();
            if matches!(s.as_str(), "done" | "failed" | "cancelled") {
                return r;
            }
            assert!(
                t.elapsed() < Duration::from_secs(240),
                "job {id} never ended: {r}"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
}

const CUBE_OBJ: &str = "\
v -1 -1 -1\nv 1 -1 -1\nv 1 1 -1\nv -1 1 -1\nv -1 -1 1\nv 1 -1 1\nv 1 1 1\nv -1 1 1\n\
f 1 4 3 2\nf 5 6 7 8\nf 1 2 6 5\nf 4 8 7 3\nf 1 5 8 4\nf 2 3 7 6\n";

/// [`CUBE_OBJ`]'s corners and triangles (its quads fanned).
fn cube_mesh() -> (Vec<[f32; 3]>, Vec<[u16; 3]>) {
    let mut v = Vec::new();
    let mut t = Vec::new();
    for line in CUBE_OBJ.lines() {
        let mut w = line.split_whitespace();
        match w.next() {
            Some("v") => v.push([0, 1, 2].map(|_| w.next().unwrap().parse::<f32>().unwrap())),
            Some("f") => {
                let q: Vec<u16> = w.map(|x| x.parse::<u16>().unwrap() - 1).collect();
                t.push([q[0], q[1], q[2]]);
                t.push([q[0], q[2], q[3]]);
            }
            _ => {}
        }
    }
    (v, t)
}

/// The cube as an ASCII PLY file, as a scanner's tools write one.
fn cube_ply() -> Vec<u8> {
    let (v, t) = cube_mesh();
    let mut s = format!(
        "ply\nformat ascii 1.0\ncomment made by a test\nelement vertex {}\nproperty float x\n\
         property float y\nproperty float z\nelement face {}\n\
         property list uchar int vertex_indices\nend_header\n",
        v.len(),
        t.len()
    );
    for p in &v {
        s += &format!("{} {} {}\n", p[0], p[1], p[2]);
    }
    for f in &t {
        s += &format!("3 {} {} {}\n", f[0], f[1], f[2]);
    }
    s.into_bytes()
}

/// The cube as a `.gltf` whose one buffer is the file `uri`, and that buffer's bytes.
fn cube_gltf(uri: &str) -> (Vec<u8>, Vec<u8>) {
    let (v, t) = cube_mesh();
    let mut bin: Vec<u8> = v.iter().flatten().flat_map(|x| x.to_le_bytes()).collect();
    let vbytes = bin.len();
    bin.extend(t.iter().flatten().flat_map(|i| i.to_le_bytes()));
    let doc = json!({
        "asset": {"version": "2.0", "generator": "translux test"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "cube"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "buffers": [{"uri": uri, "byteLength": bin.len()}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": vbytes},
            {"buffer": 0, "byteOffset": vbytes, "byteLength": bin.len() - vbytes}
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": v.len(), "type": "VEC3",
             "min": [-1, -1, -1], "max": [1, 1, 1]},
            {"bufferView": 1, "componentType": 5123, "count": 3 * t.len(), "type": "SCALAR"}
        ]
    });
    (doc.to_string().into_bytes(), bin)
}

fn scene_json(mesh: &str) -> String {
    json!({
        "objects": [
            {"name": "floor", "mesh": {"shape": "quad", "size": [2, 2]},
             "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
            {"name": "cube", "mesh": mesh,
             "transform": {"scale": 0.2, "translate": [0, 0.2, 0]},
             "material": {"type": "diffuse", "albedo": [0.8, 0.3, 0.2]}}
        ],
        "lights": [{"type": "point", "position": [0, 1.5, 0], "intensity": [5, 5, 5]}]
    })
    .to_string()
}

fn upload_form(
    scene_name: &str,
    scene: String,
    meshes: &[(&str, Vec<u8>)],
    fields: &[(&str, &str)],
) -> Form {
    let mut form = Form::new().part(
        "scene",
        Part::bytes(scene.into_bytes()).file_name(scene_name.to_string()),
    );
    for (name, bytes) in meshes {
        form = form.part(
            "mesh",
            Part::bytes(bytes.clone()).file_name(name.to_string()),
        );
    }
    for (k, v) in fields {
        form = form.text(k.to_string(), v.to_string());
    }
    form
}

async fn post_upload(
    s: &Server,
    token: Option<&str>,
    form: Form,
) -> (StatusCode, Value, Option<String>) {
    let r = s
        .req(reqwest::Method::POST, "/api/v1/scenes", token)
        .multipart(form)
        .send()
        .await
        .unwrap();
    let status = r.status();
    let location = r
        .headers()
        .get(LOCATION)
        .map(|v| v.to_str().unwrap().to_string());
    let body: Value = r.json().await.unwrap_or(Value::Null);
    (status, body, location)
}

fn leftovers(bundles: &Path) -> Vec<String> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(bundles).unwrap().flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        if name.contains(".tmp-") || name.contains(".old-") {
            out.push(name);
        }
    }
    if let Ok(entries) = std::fs::read_dir(bundles.join(".uploads")) {
        for e in entries.flatten() {
            out.push(format!(".uploads/{}", e.file_name().to_string_lossy()));
        }
    }
    out
}

// ---------------------------------------------------------------------------------------
// Tests.

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_protected_route_answers_401_and_403() {
    let bundles = bundles_with(&["cornell"]);
    let s = Server::start(bundles.path(), TeamArgs::default(), false).await;
    let mut routes = translux_server::routes::routes();
    routes.extend(translux_server::team::routes());
    let fake_job = "j000000000000aaaaaaaa";
    let mut protected = 0;
    for (method, template) in routes {
        let path = template
            .replace("/api/v1/jobs/{id}", &format!("/api/v1/jobs/{fake_job}"))
            .replace("{id}", "cornell")
            .replace("{*path}", "app.js");
        let method = reqwest::Method::from_bytes(method.as_str().as_bytes()).unwrap();
        let Some(needs) = required_role(&method, &path) else {
            // Open routes answer without a token.
            let r = s.req(method.clone(), &path, None).send().await.unwrap();
            assert!(
                !matches!(r.status(), StatusCode::UNAUTHORIZED | StatusCode::FORBIDDEN),
                "{method} {path} is open but answered {}",
                r.status()
            );
            continue;
        };
        protected += 1;
        for token in [None, Some(BAD), Some("")] {
            let r = s.req(method.clone(), &path, token).send().await.unwrap();
            assert_eq!(
                r.status(),
                StatusCode::UNAUTHORIZED,
                "{method} {path} with {token:?}"
            );
            let challenge = r.headers().get(WWW_AUTHENTICATE).unwrap().to_str().unwrap();
            assert!(challenge.starts_with("Bearer"), "{challenge}");
            let body: Value = r.json().await.unwrap();
            assert_eq!(body["error"]["code"], "unauthorized", "{body}");
        }
        for (role, token) in [
            (Role::Viewer, VIEWER),
            (Role::Editor, EDITOR),
            (Role::Admin, ADMIN),
        ] {
            if role >= needs && method == reqwest::Method::DELETE {
                // Allowed deletes are tried below, once.
                continue;
            }
            let r = s
                .req(method.clone(), &path, Some(token))
                .send()
                .await
                .unwrap();
            if role < needs {
                assert_eq!(
                    r.status(),
                    StatusCode::FORBIDDEN,
                    "{method} {path} as {role}"
                );
                let body: Value = r.json().await.unwrap();
                assert!(
                    body["error"]["message"]
                        .as_str()
                        .unwrap()
                        .contains(needs.as_str()),
                    "{body}"
                );
            } else {
                assert!(
                    !matches!(r.status(), StatusCode::UNAUTHORIZED | StatusCode::FORBIDDEN),
                    "{method} {path} as {role}: {}",
                    r.status()
                );
            }
        }
    }
    assert!(
        protected >= 12,
        "only {protected} protected routes were checked"
    );
    // The token in the query (for WebSockets) works on GET only.
    let r = s
        .client
        .get(s.url(&format!("/api/v1/scenes?access_token={VIEWER}")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    let r = s
        .client
        .post(s.url(&format!(
            "/api/v1/scenes/cornell/relight?access_token={VIEWER}"
        )))
        .header(CONTENT_TYPE, "application/json")
        .body("{}")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::UNAUTHORIZED);
    // Admin deletes; the scene is gone from the registry and the disk.
    let r = s
        .req(
            reqwest::Method::DELETE,
            "/api/v1/scenes/cornell",
            Some(ADMIN),
        )
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    assert!(!s.bundles.join("cornell").exists());
    let r = s
        .req(reqwest::Method::GET, "/api/v1/scenes/cornell", Some(VIEWER))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::NOT_FOUND);
    let who = s.get_json("/api/v1/whoami", Some(EDITOR)).await;
    assert_eq!(
        who,
        json!({"name": "eddie", "role": "editor", "auth": true})
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rate_limits_are_per_token() {
    let bundles = bundles_with(&["cornell"]);
    let args = TeamArgs {
        rate_limit: Some(0.5),
        rate_burst: Some(3.0),
        ..Default::default()
    };
    let s = Server::start(bundles.path(), args, false).await;
    for _ in 0..3 {
        let r = s
            .req(reqwest::Method::GET, "/api/v1/scenes", Some(VIEWER))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::OK);
    }
    let r = s
        .req(reqwest::Method::GET, "/api/v1/scenes", Some(VIEWER))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::TOO_MANY_REQUESTS);
    let wait: u64 = r.headers()["retry-after"]
        .to_str()
        .unwrap()
        .parse()
        .unwrap();
    assert!((1..=2).contains(&wait), "{wait}");
    // Another token has its own bucket; open routes are not limited.
    let r = s
        .req(reqwest::Method::GET, "/api/v1/scenes", Some(EDITOR))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    let r = s
        .req(reqwest::Method::GET, "/healthz", Some(VIEWER))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_refuse_traversal_bad_names_and_oversize() {
    let bundles = bundles_with(&[]);
    let args = TeamArgs {
        upload_file_limit: Some(4096),
        upload_limit: Some(10_000),
        ..Default::default()
    };
    let s = Server::start(bundles.path(), args, false).await;
    let cube = CUBE_OBJ.as_bytes().to_vec();
    let cases: Vec<(&str, Form, StatusCode, &str)> = vec![
        (
            "scene mesh path with ..",
            upload_form(
                "a.json",
                scene_json("../cube.obj"),
                &[("cube.obj", cube.clone())],
                &[],
            ),
            StatusCode::BAD_REQUEST,
            "objects[1].mesh",
        ),
        (
            "absolute mesh path",
            upload_form(
                "a.json",
                scene_json("/etc/passwd"),
                &[("cube.obj", cube.clone())],
                &[],
            ),
            StatusCode::BAD_REQUEST,
            "objects[1].mesh",
        ),
        (
            "mesh in a sub-folder",
            upload_form(
                "a.json",
                scene_json("sub/cube.obj"),
                &[("cube.obj", cube.clone())],
                &[],
            ),
            StatusCode::BAD_REQUEST,
            "objects[1].mesh",
        ),
        (
            "file name with ..",
            upload_form(
                "a.json",
                scene_json("cube.obj"),
                &[("../../cube.obj", cube.clone())],
                &[],
            ),
            StatusCode::BAD_REQUEST,
            "is a path",
        ),
        (
            "absolute file name",
            upload_form(
                "/tmp/a.json",
                scene_json("cube.obj"),
                &[("cube.obj", cube.clone())],
                &[],
            ),
            StatusCode::BAD_REQUEST,
            "is a path",
        ),
        (
            "hidden file",
            upload_form(
                "a.json",
                scene_json("cube.obj"),
                &[(".cube.obj", cube.clone())],
                &[],
            ),
            StatusCode::BAD_REQUEST,
            "hidden",
        ),
        (
            "missing mesh",
            upload_form("a.json", scene_json("cube.obj"), &[], &[]),
            StatusCode::BAD_REQUEST,
            "was not uploaded",
        ),
        (
            "wrong extension",
            upload_form(
                "a.json",
                scene_json("cube.obj"),
                &[("cube.exe", cube.clone())],
                &[],
            ),
            StatusCode::BAD_REQUEST,
            ".obj",
        ),
        (
            "glTF buffer outside the upload",
            upload_form(
                "a.json",
                scene_json("cube.gltf"),
                &[("cube.gltf", cube_gltf("../secret.bin").0)],
                &[],
            ),
            StatusCode::BAD_REQUEST,
            "buffer file \"../secret.bin\" must be the plain name",
        ),
        (
            "glTF buffer as an absolute path",
            upload_form(
                "a.json",
                scene_json("cube.gltf"),
                &[("cube.gltf", cube_gltf("/etc/passwd").0)],
                &[],
            ),
            StatusCode::BAD_REQUEST,
            "must be the plain name",
        ),
        (
            "glTF buffer not uploaded",
            upload_form(
                "a.json",
                scene_json("cube.gltf"),
                &[("cube.gltf", cube_gltf("cube.bin").0)],
                &[],
            ),
            StatusCode::BAD_REQUEST,
            "buffer file \"cube.bin\" was not uploaded",
        ),
        (
            "bad id",
            upload_form(
                "a.json",
                scene_json("cube.obj"),
                &[("cube.obj", cube.clone())],
                &[("id", "../x")],
            ),
            StatusCode::BAD_REQUEST,
            "scene id",
        ),
        (
            "too many patches",
            upload_form(
                "a.json",
                scene_json("cube.obj"),
                &[("cube.obj", cube.clone())],
                &[("patches", "400000")],
            ),
            StatusCode::BAD_REQUEST,
            "patches",
        ),
        (
            "file over the per-file limit",
            upload_form(
                "a.json",
                scene_json("cube.obj"),
                &[("cube.obj", vec![b'#'; 5000])],
                &[],
            ),
            StatusCode::PAYLOAD_TOO_LARGE,
            "per file",
        ),
        (
            "upload over the total limit",
            upload_form(
                "a.json",
                scene_json("cube.obj"),
                &[
                    ("cube.obj", cube.clone()),
                    ("b.mtl", vec![b'#'; 4000]),
                    ("c.mtl", vec![b'#'; 4000]),
                    ("d.mtl", vec![b'#'; 4000]),
                ],
                &[],
            ),
            StatusCode::PAYLOAD_TOO_LARGE,
            "in all",
        ),
    ];
    for (what, form, status, needle) in cases {
        let (got, body, _) = post_upload(&s, Some(EDITOR), form).await;
        assert_eq!(got, status, "{what}: {body}");
        let msg = body["error"]["message"].as_str().unwrap_or_default();
        assert!(msg.contains(needle), "{what}: {msg}");
        assert!(
            !msg.contains(&*s.bundles.to_string_lossy()),
            "{what} leaks a server path: {msg}"
        );
    }
    assert!(
        leftovers(&s.bundles).is_empty(),
        "{:?}",
        leftovers(&s.bundles)
    );
    assert!(!s.bundles.parent().unwrap().join("cube.obj").exists());
    // Not multipart at all.
    let r = s
        .req(reqwest::Method::POST, "/api/v1/scenes", Some(EDITOR))
        .header(CONTENT_TYPE, "application/json")
        .body("{}")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::UNSUPPORTED_MEDIA_TYPE);
}

/// Uploads of one scene id at the same time: the id is reserved when the first is
/// accepted, so exactly one is queued and the others get 409 — never two jobs where the
/// later silently replaces the earlier's served scene.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn concurrent_uploads_of_one_id_queue_exactly_one_job() {
    let bundles = bundles_with(&[]);
    let s = Server::start(bundles.path(), TeamArgs::default(), false).await;
    let cube = CUBE_OBJ.as_bytes().to_vec();
    let uploads = (0..4).map(|_| {
        let form = upload_form(
            "race.json",
            scene_json("cube.obj"),
            &[("cube.obj", cube.clone())],
            &[("id", "race"), ("patches", "150")],
        );
        post_upload(&s, Some(EDITOR), form)
    });
    let results = futures_util::future::join_all(uploads).await;
    let accepted = results
        .iter()
        .filter(|(st, _, _)| *st == StatusCode::ACCEPTED)
        .count();
    assert_eq!(accepted, 1, "{results:?}");
    for (st, body, _) in &results {
        assert!(
            *st == StatusCode::ACCEPTED || *st == StatusCode::CONFLICT,
            "{st}: {body}"
        );
    }
    // Once that job is done the id is a served scene, and a new upload is still refused.
    let job = results
        .iter()
        .find(|(st, _, _)| *st == StatusCode::ACCEPTED)
        .map(|(_, b, _)| b["id"].as_str().unwrap().to_string())
        .unwrap();
    let record = s.wait_job(&job, EDITOR).await;
    assert_eq!(record["state"], "done", "{record}");
    let form = upload_form(
        "race.json",
        scene_json("cube.obj"),
        &[("cube.obj", cube.clone())],
        &[("id", "race")],
    );
    assert_eq!(
        post_upload(&s, Some(EDITOR), form).await.0,
        StatusCode::CONFLICT
    );
}

/// The upload limit is on the patches the precompute will make, not the number asked for:
/// every triangle is at least one patch, so a mesh of many triangles with `patches=50` is
/// refused up front, with the real count.
#[tokio::test]
async fn the_upload_patch_limit_counts_every_triangle() {
    let bundles = bundles_with(&[]);
    let args = TeamArgs {
        max_upload_patches: Some(150),
        ..Default::default()
    };
    let s = Server::start(bundles.path(), args, false).await;
    // A 12 × 12 grid of quads: 288 triangles.
    let mut grid = String::new();
    for i in 0..13 {
        for j in 0..13 {
            grid += &format!("v {} 0 {}\n", i as f32 / 12.0, j as f32 / 12.0);
        }
    }
    for i in 0..12 {
        for j in 0..12 {
            let v = |a: usize, b: usize| 1 + a * 13 + b;
            grid += &format!(
                "f {} {} {} {}\n",
                v(i, j),
                v(i, j + 1),
                v(i + 1, j + 1),
                v(i + 1, j)
            );
        }
    }
    let form = upload_form(
        "grid.json",
        scene_json("grid.obj"),
        &[("grid.obj", grid.into_bytes())],
        &[("id", "grid"), ("patches", "50")],
    );
    let (status, body, _) = post_upload(&s, Some(EDITOR), form).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    let text = body.to_string();
    assert!(
        text.contains("would make") && text.contains("(150)"),
        "{text}"
    );
    let jobs = s.get_json("/api/v1/jobs", Some(ADMIN)).await;
    assert!(jobs["jobs"].as_array().unwrap().is_empty(), "{jobs}");
}

/// An upload that asks for huge geometry in a few bytes is refused from the counts alone,
/// before any triangle is built: eight 4,096-segment spheres (16.8 M triangles each) in a
/// 1.5 KB scene file, and a glTF whose one mesh of a million triangles eight nodes place
/// (its buffer file a few bytes). Building either took gigabytes before.
#[tokio::test]
async fn an_upload_of_huge_shapes_or_instances_is_refused_from_its_counts() {
    let bundles = bundles_with(&[]);
    let s = Server::start(bundles.path(), TeamArgs::default(), false).await;
    let spheres: Vec<Value> = (0..8)
        .map(|k| {
            json!({"name": format!("ball{k}"),
                   "mesh": {"shape": "sphere", "radius": 0.1, "segments": 4096},
                   "transform": {"translate": [k as f32 * 0.3, 0.2, 0]},
                   "material": {"type": "diffuse", "albedo": [0.8, 0.8, 0.8]}})
        })
        .collect();
    let scene = json!({ "objects": spheres }).to_string();
    assert!(scene.len() < 1600, "{}", scene.len());
    let t = Instant::now();
    let form = upload_form("balls.json", scene, &[], &[("id", "balls")]);
    let (status, body, _) = post_upload(&s, Some(EDITOR), form).await;
    let took = t.elapsed();
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    let text = body.to_string();
    assert!(
        text.contains("134152192") && text.contains("(50000)"),
        "{text}"
    );
    assert!(took < Duration::from_secs(1), "refused after {took:?}");

    let nodes: Vec<Value> = (0..8).map(|_| json!({"mesh": 0})).collect();
    let gltf = json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2, 3, 4, 5, 6, 7]}],
        "nodes": nodes,
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3_000_000,
                       "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 1]}],
        "bufferViews": [{"buffer": 0, "byteLength": 36_000_000}],
        "buffers": [{"uri": "big.bin", "byteLength": 36_000_000}],
    })
    .to_string();
    let t = Instant::now();
    let form = upload_form(
        "many.json",
        scene_json("many.gltf"),
        &[("many.gltf", gltf.into_bytes()), ("big.bin", vec![0u8; 16])],
        &[("id", "many")],
    );
    let (status, body, _) = post_upload(&s, Some(EDITOR), form).await;
    let took = t.elapsed();
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    let text = body.to_string();
    assert!(text.contains("8000002"), "{text}");
    assert!(took < Duration::from_secs(1), "refused after {took:?}");
    let jobs = s.get_json("/api/v1/jobs", Some(ADMIN)).await;
    assert!(jobs["jobs"].as_array().unwrap().is_empty(), "{jobs}");
    assert!(leftovers(bundles.path()).is_empty());
}

/// Meshes as people have them: a scan's PLY and a glTF with its buffer file beside it
/// (named with a percent-escape, as exporters write spaces), uploaded with the scene file,
/// become a served scene with both objects.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ply_and_gltf_meshes_can_be_uploaded() {
    let bundles = bundles_with(&[]);
    let s = Server::start(bundles.path(), TeamArgs::default(), false).await;
    let (gltf, bin) = cube_gltf("cube%2Ddata.bin");
    let scene = json!({
        "objects": [
            {"name": "floor", "mesh": {"shape": "quad", "size": [2, 2]},
             "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
            {"name": "scan", "mesh": "cube.ply",
             "transform": {"scale": 0.2, "translate": [-0.4, 0.2, 0]},
             "material": {"type": "diffuse", "albedo": [0.8, 0.3, 0.2]}},
            {"name": "exported", "mesh": "cube.gltf",
             "transform": {"scale": 0.2, "translate": [0.4, 0.2, 0]},
             "material": {"type": "diffuse", "albedo": [0.2, 0.3, 0.8]}}
        ],
        "lights": [{"type": "point", "position": [0, 1.5, 0], "intensity": [5, 5, 5]}]
    })
    .to_string();
    let form = upload_form(
        "formats.json",
        scene,
        &[
            ("cube.ply", cube_ply()),
            ("cube.gltf", gltf),
            ("cube-data.bin", bin),
        ],
        &[("id", "formats"), ("patches", "300")],
    );
    let (status, job, _) = post_upload(&s, Some(EDITOR), form).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{job}");
    let record = s.wait_job(job["id"].as_str().unwrap(), EDITOR).await;
    assert_eq!(record["state"], "done", "{record}");
    let detail = s.get_json("/api/v1/scenes/formats", Some(EDITOR)).await;
    let text = detail.to_string();
    for name in ["\"scan\"", "\"exported\""] {
        assert!(text.contains(name), "{name} missing from {text}");
    }
    let lit = s.relight("formats", Some(EDITOR)).await;
    assert!(lit.vertex_count > 0);
    assert!(lit.radiance.iter().all(|x| x.is_finite()));
}

/// A precompute job runs under its memory budget (`--job-memory`): a scene whose job needs
/// more is failed, saying so, and nothing is served or left behind.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_precompute_job_over_its_memory_budget_fails_naming_it() {
    let bundles = bundles_with(&[]);
    let args = TeamArgs {
        job_memory: Some(1 << 20),
        ..TeamArgs::default()
    };
    let s = Server::start(bundles.path(), args, false).await;
    let form = upload_form(
        "cube-scene.json",
        scene_json("cube.obj"),
        &[("cube.obj", CUBE_OBJ.as_bytes().to_vec())],
        &[("id", "cube"), ("patches", "3000")],
    );
    let (status, job, _) = post_upload(&s, Some(EDITOR), form).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{job}");
    let done = s.wait_job(job["id"].as_str().unwrap(), EDITOR).await;
    assert_eq!(done["state"], "failed", "{done}");
    let message = done["error"].as_str().unwrap();
    assert!(
        message.contains("1 MiB") || message.contains("1.0 MiB"),
        "{message}"
    );
    let list = s.get_json("/api/v1/scenes", Some(VIEWER)).await;
    assert_eq!(list["scenes"], json!([]), "{list}");
    assert!(
        leftovers(&s.bundles).is_empty(),
        "{:?}",
        leftovers(&s.bundles)
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_uploaded_scene_becomes_a_served_bundle() {
    let bundles = bundles_with(&[]);
    let s = Server::start(bundles.path(), TeamArgs::default(), false).await;
    let form = upload_form(
        "cube-scene.json",
        scene_json("cube.obj"),
        &[
            ("cube.obj", CUBE_OBJ.as_bytes().to_vec()),
            ("cube.mtl", b"newmtl x\n".to_vec()),
        ],
        &[("id", "cube"), ("patches", "200")],
    );
    let (status, job, location) = post_upload(&s, Some(EDITOR), form).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{job}");
    let id = job["id"].as_str().unwrap().to_string();
    assert_eq!(
        location.as_deref(),
        Some(format!("/api/v1/jobs/{id}").as_str())
    );
    assert_eq!(job["scene"], "cube");
    assert_eq!(job["owner"], "eddie");

    // Follow the SSE stream to the end: percentages never go down, the last event is done.
    let mut r = s
        .req(
            reqwest::Method::GET,
            &format!("/api/v1/jobs/{id}/events"),
            Some(EDITOR),
        )
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    assert!(
        r.headers()[CONTENT_TYPE]
            .to_str()
            .unwrap()
            .starts_with("text/event-stream")
    );
    let mut text = String::new();
    let t = Instant::now();
    while let Some(chunk) = tokio::time::timeout(Duration::from_secs(240), r.chunk())
        .await
        .expect("the event stream stalled")
        .unwrap()
    {
        text.push_str(&String::from_utf8_lossy(&chunk));
        assert!(t.elapsed() < Duration::from_secs(240));
    }
    let mut events = Vec::new();
    for block in text.split("\n\n") {
        let name = block.lines().find_map(|l| l.strip_prefix("event: "));
        let data = block.lines().find_map(|l| l.strip_prefix("data: "));
        if let (Some(n), Some(d)) = (name, data) {
            events.push((n.to_string(), serde_json::from_str::<Value>(d).unwrap()));
        }
    }
    let (last, record) = events.last().expect("no events");
    assert_eq!(last, "done", "{text}");
    assert_eq!(record["state"], "done");
    let mut prev = -1.0;
    for (_, r) in &events {
        let p = r["percent"].as_f64().unwrap();
        assert!(p >= prev, "percent went down: {text}");
        prev = p;
    }
    assert!(
        events.iter().any(|(_, r)| r["stage"] == "form factors"),
        "{text}"
    );
    let patches = record["result"]["patches"].as_u64().unwrap();
    assert!((150..=260).contains(&patches), "{patches} patches");

    // Served without a restart; relight answers one colour per mesh vertex, lit.
    let list: SceneList =
        serde_json::from_value(s.get_json("/api/v1/scenes", Some(VIEWER)).await).unwrap();
    assert!(list.scenes.iter().any(|x| x.id == "cube"), "{list:?}");
    let mesh = s.get_json("/api/v1/scenes/cube/mesh", Some(VIEWER)).await;
    let vertices = mesh["positions"].as_array().unwrap().len() / 3;
    // Viewers see where the scene came from, never the server's folders.
    let detail = s.get_json("/api/v1/scenes/cube", Some(VIEWER)).await;
    let source = detail["source"].as_str().unwrap();
    assert!(
        source.starts_with("upload:j") && source.ends_with(".json"),
        "{source}"
    );
    let root = s.bundles.display().to_string();
    assert!(!detail.to_string().contains(&root), "{detail}");
    let out = s.relight("cube", Some(VIEWER)).await;
    assert_eq!(out.vertex_count, vertices);
    assert!(out.radiance.iter().all(|v| v.is_finite() && *v >= 0.0));
    assert!(
        out.radiance.iter().any(|v| *v > 1e-3),
        "the uploaded scene is black"
    );
    assert!(s.bundles.join("cube/manifest.json").is_file());
    assert!(
        leftovers(&s.bundles).is_empty(),
        "{:?}",
        leftovers(&s.bundles)
    );

    // The id is now taken; a viewer cannot see jobs; the editor sees theirs.
    let form = upload_form(
        "x.json",
        scene_json("cube.obj"),
        &[("cube.obj", CUBE_OBJ.as_bytes().to_vec())],
        &[("id", "cube")],
    );
    let (status, body, _) = post_upload(&s, Some(EDITOR), form).await;
    assert_eq!(status, StatusCode::CONFLICT, "{body}");
    let jobs = s.get_json("/api/v1/jobs", Some(EDITOR)).await;
    assert_eq!(jobs["jobs"].as_array().unwrap().len(), 1);
    let jobs = s.get_json("/api/v1/jobs", Some(ADMIN)).await;
    assert_eq!(jobs["jobs"].as_array().unwrap().len(), 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancelled_jobs_leave_no_bundle() {
    let bundles = bundles_with(&[]);
    let args = TeamArgs {
        jobs: Some(translux_server::slurm::JobsSetting::Local(1)),
        max_upload_patches: Some(60_000),
        ..Default::default()
    };
    let s = Server::start(bundles.path(), args, false).await;
    let upload = |id: &'static str, patches: &'static str| {
        upload_form(
            "s.json",
            scene_json("cube.obj"),
            &[("cube.obj", CUBE_OBJ.as_bytes().to_vec())],
            &[("id", id), ("patches", patches)],
        )
    };
    // A long job, and one queued behind it (one worker).
    let (st, big, _) = post_upload(&s, Some(EDITOR), upload("big", "12000")).await;
    assert_eq!(st, StatusCode::ACCEPTED, "{big}");
    let (st, queued, _) = post_upload(&s, Some(ADMIN), upload("later", "200")).await;
    assert_eq!(st, StatusCode::ACCEPTED, "{queued}");
    let big_id = big["id"].as_str().unwrap();
    let queued_id = queued["id"].as_str().unwrap();

    // Wait for the big one to run, then cancel both.
    let t = Instant::now();
    loop {
        let r = s
            .get_json(&format!("/api/v1/jobs/{big_id}"), Some(EDITOR))
            .await;
        if r["state"] == "running" {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "{r}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // Another editor's job is not visible to this editor (404), but the admin may cancel it.
    let r = s
        .req(
            reqwest::Method::DELETE,
            &format!("/api/v1/jobs/{queued_id}"),
            Some(EDITOR),
        )
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::NOT_FOUND);
    let r = s
        .req(
            reqwest::Method::DELETE,
            &format!("/api/v1/jobs/{queued_id}"),
            Some(ADMIN),
        )
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    let rec: Value = r.json().await.unwrap();
    assert_eq!(rec["state"], "cancelled", "{rec}");
    let r = s
        .req(
            reqwest::Method::DELETE,
            &format!("/api/v1/jobs/{big_id}"),
            Some(EDITOR),
        )
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    let t = Instant::now();
    let done = s.wait_job(big_id, EDITOR).await;
    assert_eq!(done["state"], "cancelled", "{done}");
    assert!(
        t.elapsed() < Duration::from_secs(30),
        "cancelling took {:?}",
        t.elapsed()
    );
    for id in ["big", "later"] {
        assert!(!s.bundles.join(id).exists(), "{id} has a bundle");
        let r = s
            .req(
                reqwest::Method::GET,
                &format!("/api/v1/scenes/{id}"),
                Some(VIEWER),
            )
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::NOT_FOUND);
    }
    assert!(
        leftovers(&s.bundles).is_empty(),
        "{:?}",
        leftovers(&s.bundles)
    );
}

/// A job's bundle rewrite killed (SIGKILL, the server with it) at each of its steps — the
/// test leaves on disk what each step leaves — then the server restarted: the bundle served
/// and the job record agree (the old bundle and `failed` until the new one was renamed into
/// place, then the new one and `done`), and no leftover stays.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rewrite_killed_at_any_step_restarts_with_the_record_and_the_bundle_agreeing() {
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs();
    // A bundle marked `which`, its manifest written `age` seconds ago.
    let bundle = |dir: &Path, which: &str, age: u64| {
        copy_dir(&crate::support::bundle_dir(), dir);
        std::fs::write(dir.join("which"), which).unwrap();
        let at = std::time::SystemTime::now() - Duration::from_secs(age);
        std::fs::File::options()
            .write(true)
            .open(dir.join("manifest.json"))
            .unwrap()
            .set_modified(at)
            .unwrap();
    };
    let id = "j0190000000001234abcd";
    // The steps of a rewrite, and what is served and recorded after a kill there.
    for (step, old, tmp, aside, new, (served, state)) in [
        ("walking", true, false, false, false, ("old", "failed")),
        (
            "new files written",
            true,
            true,
            false,
            false,
            ("old", "failed"),
        ),
        (
            "old bundle moved aside",
            false,
            true,
            true,
            false,
            ("old", "failed"),
        ),
        (
            "new bundle in place",
            false,
            false,
            true,
            true,
            ("new", "done"),
        ),
        (
            "old bundle deleted",
            false,
            false,
            false,
            true,
            ("new", "done"),
        ),
    ] {
        let bundles = bundles_with(&[]);
        let dir = bundles.path();
        let jobs = dir.join(".jobs");
        std::fs::create_dir_all(&jobs).unwrap();
        std::fs::write(
            jobs.join(format!("{id}.json")),
            json!({
                "id": id, "scene": "cup", "owner": "eddie", "state": "running",
                "stage": "walks", "stage_percent": 40.0, "percent": 30.0, "error": null,
                "patches": null, "max_edge": null, "created": now - 60, "started": now - 30,
                "finished": null, "result": null, "resimulate": ["cube"]
            })
            .to_string(),
        )
        .unwrap();
        let pid = 4_000_000_000u32; // no such process: the killed server
        if old {
            bundle(&dir.join("cup"), "old", 3600);
        }
        if aside {
            bundle(&dir.join(format!(".cup.old-{pid}-1-1")), "old", 3600);
        }
        if tmp {
            bundle(&dir.join(format!(".cup.tmp-{pid}-1-0")), "new", 5);
        }
        if new {
            bundle(&dir.join("cup"), "new", 5);
        }

        let s = Server::start(dir, TeamArgs::default(), false).await;
        let r = s.get_json(&format!("/api/v1/jobs/{id}"), Some(ADMIN)).await;
        assert_eq!(r["state"], state, "killed at '{step}': {r}");
        let on_disk = std::fs::read_to_string(dir.join("cup").join("which")).unwrap();
        assert_eq!(on_disk, served, "killed at '{step}'");
        assert_eq!(
            s.get_json("/api/v1/scenes/cup", Some(VIEWER)).await["id"],
            "cup",
            "killed at '{step}'"
        );
        if state == "done" {
            assert_eq!(r["percent"], 100.0, "{r}");
            assert!(r["result"]["patches"].as_u64().unwrap() > 0, "{r}");
        }
        assert!(
            leftovers(dir).is_empty(),
            "killed at '{step}': {:?}",
            leftovers(dir)
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restart_after_a_killed_job_reports_it_failed_and_serves_no_half_bundle() {
    let bundles = bundles_with(&["cornell"]);
    // What a killed server leaves: a record saying running, a half-written temporary bundle,
    // an upload folder.
    let jobs = bundles.path().join(".jobs");
    std::fs::create_dir_all(&jobs).unwrap();
    let id = "j0190000000001234abcd";
    std::fs::write(
        jobs.join(format!("{id}.json")),
        json!({
            "id": id, "scene": "mug", "owner": "eddie", "state": "running",
            "stage": "form factors", "stage_percent": 40.0, "percent": 30.0, "error": null,
            "patches": 200, "max_edge": null, "created": 1, "started": 2, "finished": null,
            "result": null
        })
        .to_string(),
    )
    .unwrap();
    let tmp = bundles.path().join(".mug.tmp-1234-5678-0");
    std::fs::create_dir_all(&tmp).unwrap();
    std::fs::copy(
        crate::support::bundle_dir().join("manifest.json"),
        tmp.join("manifest.json"),
    )
    .unwrap();
    std::fs::create_dir_all(bundles.path().join(".uploads").join(id)).unwrap();

    let s = Server::start(bundles.path(), TeamArgs::default(), false).await;
    let r = s.get_json(&format!("/api/v1/jobs/{id}"), Some(ADMIN)).await;
    assert_eq!(r["state"], "failed", "{r}");
    assert!(r["error"].as_str().unwrap().contains("stopped"), "{r}");
    assert!(!tmp.exists());
    assert!(
        leftovers(&s.bundles).is_empty(),
        "{:?}",
        leftovers(&s.bundles)
    );
    let list = s.get_json("/api/v1/scenes", Some(VIEWER)).await;
    assert_eq!(list["scenes"].as_array().unwrap().len(), 1, "{list}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_tiny_memory_budget_evicts_and_still_answers_correctly() {
    let bundles = bundles_with(&["a", "b", "c"]);
    // Reference answers from a server without a budget.
    let reference = Server::start(bundles.path(), TeamArgs::default(), true).await;
    let want = reference.relight("a", None).await.radiance;
    let want_mesh = reference.get_json("/api/v1/scenes/a/mesh", None).await;
    drop(reference);

    let args = TeamArgs {
        memory_budget: Some(1),
        ..Default::default()
    };
    let s = Server::start(bundles.path(), args, true).await;
    for round in 0..3 {
        for id in ["a", "b", "c"] {
            let got = s.relight(id, None).await;
            assert_eq!(got.radiance, want, "round {round}, scene {id}");
            let mesh = s.get_json(&format!("/api/v1/scenes/{id}/mesh"), None).await;
            assert_eq!(mesh, want_mesh, "round {round}, scene {id}");
            // Only the scene just used is resident; every scene is still listed.
            let health = s.get_json("/healthz", None).await;
            let states: Vec<(String, String)> = health["scene_states"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| {
                    (
                        x["id"].as_str().unwrap().into(),
                        x["state"].as_str().unwrap().into(),
                    )
                })
                .collect();
            for (sid, st) in &states {
                let expect = if sid == id { "ready" } else { "evicted" };
                if round > 0 || sid == id {
                    assert_eq!(st, expect, "round {round} after {id}: {states:?}");
                }
            }
            let list = s.get_json("/api/v1/scenes", None).await;
            assert_eq!(list["scenes"].as_array().unwrap().len(), 3, "{list}");
        }
    }
    // Concurrent requests on all scenes at once, each answered right.
    let mut tasks = Vec::new();
    for k in 0..12 {
        let id = ["a", "b", "c"][k % 3];
        let c = s.client.clone();
        let url = s.url(&format!("/api/v1/scenes/{id}/relight"));
        tasks.push(tokio::spawn(async move {
            let r = c
                .post(url)
                .header(ACCEPT, "application/json")
                .header(CONTENT_TYPE, "application/json")
                .body("{}")
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), StatusCode::OK);
            r.json::<RelightResponse>().await.unwrap().radiance
        }));
    }
    for t in tasks {
        assert_eq!(t.await.unwrap(), want);
    }
}

/// The team routes and the access layer's refusals are in `/metrics` and the request log,
/// not only the core routes: failed-login bursts and deletions must be visible.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn team_routes_and_refusals_are_counted_and_logged() {
    logs();
    let bundles = bundles_with(&["cornell"]);
    let s = Server::start(bundles.path(), TeamArgs::default(), false).await;
    for _ in 0..3 {
        let r = s
            .req(reqwest::Method::GET, "/api/v1/jobs", Some(BAD))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::UNAUTHORIZED);
    }
    let r = s
        .req(
            reqwest::Method::DELETE,
            "/api/v1/scenes/cornell",
            Some(VIEWER),
        )
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::FORBIDDEN);
    let r = s
        .req(
            reqwest::Method::DELETE,
            "/api/v1/scenes/cornell",
            Some(ADMIN),
        )
        .send()
        .await
        .unwrap();
    assert!(r.status().is_success(), "{}", r.status());
    let _ = s.get_json("/api/v1/whoami", Some(VIEWER)).await;
    let text = s
        .req(reqwest::Method::GET, "/metrics", Some(VIEWER))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    let count = |route: &str, method: &str, status: &str| {
        let want = format!(
            "translux_http_request_duration_seconds_count{{method=\"{method}\",route=\"{route}\",status=\"{status}\"}}"
        );
        text.lines()
            .find(|l| l.starts_with(&want))
            .and_then(|l| l.rsplit(' ').next())
            .map_or(0, |n| n.parse::<u64>().unwrap())
    };
    assert_eq!(count("/api/v1/jobs", "GET", "401"), 3, "{text}");
    assert_eq!(count("/api/v1/scenes/{id}", "DELETE", "403"), 1, "{text}");
    assert_eq!(count("/api/v1/scenes/{id}", "DELETE", "200"), 1, "{text}");
    assert_eq!(count("/api/v1/whoami", "GET", "200"), 1, "{text}");
    assert!(
        text.lines()
            .any(|l| l.starts_with("translux_build_info{") && l.ends_with(" 1")),
        "{text}"
    );
    let log = String::from_utf8_lossy(&logs().0.lock().unwrap()).into_owned();
    assert!(
        log.lines()
            .any(|l| l.contains("/api/v1/jobs") && l.contains("401")),
        "no 401 in the log"
    );
    assert!(
        log.lines()
            .any(|l| l.contains("DELETE") && l.contains("/api/v1/scenes/cornell")),
        "no DELETE in the log"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tokens_never_reach_the_log() {
    let bundles = bundles_with(&["cornell"]);
    let s = Server::start(bundles.path(), TeamArgs::default(), false).await;
    for token in [VIEWER, EDITOR, ADMIN, BAD] {
        for path in [
            "/api/v1/scenes",
            "/api/v1/scenes/cornell",
            "/api/v1/jobs",
            "/api/v1/nothing",
        ] {
            let _ = s
                .req(reqwest::Method::GET, path, Some(token))
                .send()
                .await
                .unwrap();
            let _ = s
                .client
                .get(s.url(&format!("{path}?access_token={token}")))
                .send()
                .await
                .unwrap();
        }
        let _ = s
            .req(reqwest::Method::DELETE, "/api/v1/scenes/none", Some(token))
            .send()
            .await
            .unwrap();
    }
    let text = String::from_utf8_lossy(&logs().0.lock().unwrap()).into_owned();
    // The log is there (this test can fail) and holds none of the tokens.
    assert!(text.contains("/api/v1/scenes"), "nothing was logged");
    for token in [VIEWER, EDITOR, ADMIN, BAD] {
        assert!(!text.contains(token), "a token is in the log");
        assert!(
            !text.contains(&hash_token(token).unwrap()),
            "a token hash is in the log"
        );
    }
}

/// A simulated 20 mm cube of `material` precomputed as `cube` into `bundles` (200 patches).
fn simulated_cube(bundles: &Path, material: Value) {
    let scene = bundles.join("cube.json");
    std::fs::write(
        &scene,
        json!({"unit_mm": 1, "objects": [{"name": "cube",
                 "mesh": {"shape": "box", "size": [20, 20, 20]}, "material": material}],
               "lights": [{"type": "directional", "direction": [0, -1, 0],
                           "irradiance": [1, 1, 1]}]})
        .to_string(),
    )
    .unwrap();
    let loaded = translux_precompute::scene::load_scene_file(&scene).unwrap();
    let params = translux_precompute::pipeline::PrecomputeParams {
        patches: Some(200),
        progress: false,
        ..Default::default()
    };
    translux_precompute::pipeline::precompute(&loaded, &bundles.join("cube"), &params).unwrap();
    std::fs::remove_file(&scene).unwrap();
}

/// A simulated medium of σs′ `s` mm⁻¹ (σa 0.004, 0.008, 0.02 mm⁻¹, η = 1).
fn medium(s: f32) -> Value {
    json!({"type": "simulated", "sigma_s_prime": [s, s, s],
           "sigma_a": [0.004, 0.008, 0.02], "eta": 1.0})
}

/// Three point lamps round the cube, each walked 10⁷ times (the attack of issue #79: hours
/// of walks from one request).
fn walk_for_hours() -> Value {
    let lamps: Vec<Value> = [[30.0, 0.0, 0.0], [0.0, 30.0, 0.0], [0.0, 0.0, 30.0]]
        .iter()
        .map(|p| json!({"type": "point", "position": p, "intensity": [1000, 1000, 1000]}))
        .collect();
    json!({"lights": lamps, "lamp_walks": 10_000_000})
}

/// The relights in flight, from `/metrics`.
async fn in_flight(s: &Server) -> f64 {
    let r = s
        .req(reqwest::Method::GET, "/metrics", Some(VIEWER))
        .send()
        .await
        .unwrap();
    let text = r.text().await.unwrap();
    text.lines()
        .find_map(|l| l.strip_prefix("translux_relights_in_flight "))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no in-flight gauge in {text}"))
}

/// A request's lamp walks are bounded by its role's limit and stop when nobody waits for
/// them: a viewer asking for hours of walks is stopped at the viewer's limit and answered
/// 422 `work_limit` with the time they would need; an editor's (a limit of hours) whose
/// client hangs up stops within a second, leaving the workers idle.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lamp_walks_stop_at_the_roles_limit_and_when_the_client_leaves() {
    let bundles = bundles_with(&[]);
    simulated_cube(bundles.path(), medium(2.0));
    let params = ServerParams {
        viewer_work: Duration::from_millis(1500),
        editor_work: Duration::from_secs(3 * 3600),
        ..ServerParams::default()
    };
    let s = Server::start_with(bundles.path(), TeamArgs::default(), false, params).await;
    let post = |token: &'static str| {
        s.req(
            reqwest::Method::POST,
            "/api/v1/scenes/cube/relight",
            Some(token),
        )
        .header(CONTENT_TYPE, "application/json")
        .body(walk_for_hours().to_string())
    };

    let t = Instant::now();
    let r = post(VIEWER).send().await.unwrap();
    let took = t.elapsed();
    assert_eq!(r.status(), StatusCode::UNPROCESSABLE_ENTITY);
    let e: Value = r.json().await.unwrap();
    assert_eq!(e["error"]["code"], "work_limit", "{e}");
    let message = e["error"]["message"].as_str().unwrap();
    assert!(
        message.contains("limit of 1.5 s") && message.contains("would take about"),
        "{message}"
    );
    assert!(
        took < Duration::from_millis(3500),
        "the viewer's walks ran {took:?} against a limit of 1.5 s"
    );
    assert_eq!(in_flight(&s).await, 0.0);

    // The editor's client gives up after half a second: the walks stop with it.
    let gave_up = post(EDITOR)
        .timeout(Duration::from_millis(500))
        .send()
        .await;
    assert!(gave_up.is_err(), "answered within 0.5 s: {gave_up:?}");
    let t = Instant::now();
    while in_flight(&s).await > 0.0 {
        assert!(
            t.elapsed() < Duration::from_secs(2),
            "the walks still run 2 s after the client left"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // The server is free: a plain relight is answered at once.
    let lit = s.relight("cube", Some(VIEWER)).await;
    assert!(lit.radiance.iter().all(|x| x.is_finite()));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_new_scattering_medium_walks_again_as_a_job_and_is_served() {
    // A simulated cube precomputed into the bundles folder.
    let bundles = bundles_with(&[]);
    simulated_cube(bundles.path(), medium(0.5));
    let s = Server::start(bundles.path(), TeamArgs::default(), false).await;
    let before = s.relight("cube", Some(VIEWER)).await;
    let post = |token: &'static str, body: Value| {
        let r = s
            .req(
                reqwest::Method::POST,
                "/api/v1/scenes/cube/resimulate",
                Some(token),
            )
            .header(CONTENT_TYPE, "application/json")
            .body(body.to_string());
        async move {
            let r = r.send().await.unwrap();
            let status = r.status();
            let location = r
                .headers()
                .get(LOCATION)
                .map(|v| v.to_str().unwrap().to_string());
            (status, r.json::<Value>().await.unwrap(), location)
        }
    };

    // Refused before anything is queued, naming the problem.
    let (status, _, _) = post(VIEWER, json!({"materials": {"cube": medium(1.0)}})).await;
    assert_eq!(status, StatusCode::FORBIDDEN);
    for (body, says) in [
        (
            json!({"materials": {"ball": medium(1.0)}}),
            "no object \"ball\"",
        ),
        (
            json!({"materials": {"cube": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}}}),
            "only a simulated object",
        ),
        (
            json!({"materials": {"cube": {"type": "simulated", "sigma_s_prime": [1, 1, 1],
                                          "sigma_a": [-1, 0, 0]}}}),
            "materials.cube.sigma_a",
        ),
        (json!({"materials": {}}), "at least one"),
        (
            json!({"materials": {"cube": medium(1.0)}, "x": 1}),
            "unknown field",
        ),
    ] {
        let (status, e, _) = post(EDITOR, body.clone()).await;
        assert_eq!(status, StatusCode::BAD_REQUEST, "{body}: {e}");
        let message = e["error"]["message"].as_str().unwrap();
        assert!(message.contains(says), "{body}: {message}");
    }
    // The same object twice: refused, not the last one walked.
    let twice = format!(
        r#"{{"materials": {{"cube": {}, "cube": {}}}}}"#,
        medium(1.0),
        medium(2.0)
    );
    let r = s
        .req(
            reqwest::Method::POST,
            "/api/v1/scenes/cube/resimulate",
            Some(EDITOR),
        )
        .header(CONTENT_TYPE, "application/json")
        .body(twice)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::BAD_REQUEST);
    let text = r.text().await.unwrap();
    assert!(
        text.contains("materials.cube") && text.contains("twice"),
        "{text}"
    );
    assert!(
        s.get_json("/api/v1/jobs", Some(EDITOR)).await["jobs"]
            .as_array()
            .unwrap()
            .is_empty()
    );

    // Before: a relight with the new scattering is refused, saying to walk again.
    let r = s
        .req(
            reqwest::Method::POST,
            "/api/v1/scenes/cube/relight",
            Some(VIEWER),
        )
        .header(CONTENT_TYPE, "application/json")
        .body(json!({"materials": {"cube": medium(1.0)}}).to_string())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::BAD_REQUEST);
    assert!(r.text().await.unwrap().contains("--resimulate"));

    // The job: walks, the bundle rewritten, the scene served with the new medium.
    let (status, job, location) = post(EDITOR, json!({"materials": {"cube": medium(1.0)}})).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{job}");
    let id = job["id"].as_str().unwrap().to_string();
    assert_eq!(
        location.as_deref(),
        Some(format!("/api/v1/jobs/{id}").as_str())
    );
    assert_eq!(job["resimulate"], json!(["cube"]));
    let done = s.wait_job(&id, EDITOR).await;
    assert_eq!(done["state"], "done", "{done}");
    assert_eq!(done["stage"], "walks");
    assert!(done["result"]["patches"].as_u64().unwrap() > 100, "{done}");
    let detail = s.get_json("/api/v1/scenes/cube", Some(VIEWER)).await;
    assert_eq!(
        detail["objects"][0]["material"]["sigma_s_prime"],
        json!([1.0, 1.0, 1.0]),
        "{detail}"
    );
    let after = s.relight("cube", Some(VIEWER)).await;
    assert_eq!(after.vertex_count, before.vertex_count);
    let changed = after
        .radiance
        .iter()
        .zip(&before.radiance)
        .filter(|(a, b)| (*a - *b).abs() > 1e-3 * b.abs().max(1e-6))
        .count();
    assert!(
        changed > after.radiance.len() / 2,
        "{changed} values changed"
    );
    assert!(
        leftovers(&s.bundles).is_empty(),
        "{:?}",
        leftovers(&s.bundles)
    );
}

/// A re-simulation that would walk for hours (σs′ 10⁴ mm⁻¹, σa 0, 10⁶ walks per patch, the
/// attack of issue #79): a DELETE stops it within 2 s (the record turns `cancelled` only
/// once every walking thread has returned) and the only job slot is free again (the next
/// job runs); under a token with a work limit of 1 s the same job fails at the limit
/// with the time it would need. Either way the bundle is served as it was.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resimulation_is_cancelled_by_delete_and_stopped_at_its_limit() {
    let bundles = bundles_with(&[]);
    simulated_cube(bundles.path(), medium(0.5));
    let s = Server::start(bundles.path(), TeamArgs::default(), false).await;
    let before = s.relight("cube", Some(VIEWER)).await;
    let forever = json!({"materials": {"cube": {"type": "simulated",
        "sigma_s_prime": [1e4, 1e4, 1e4], "sigma_a": [0, 0, 0], "eta": 1.0,
        "max_walks": 1_000_000}}});
    let submit = |token: &'static str| {
        let r = s
            .req(
                reqwest::Method::POST,
                "/api/v1/scenes/cube/resimulate",
                Some(token),
            )
            .header(CONTENT_TYPE, "application/json")
            .body(forever.to_string());
        async move {
            let r = r.send().await.unwrap();
            assert_eq!(r.status(), StatusCode::ACCEPTED);
            r.json::<Value>().await.unwrap()["id"]
                .as_str()
                .unwrap()
                .to_string()
        }
    };
    let s = &s;
    let job_state = |id: String| async move {
        s.get_json(&format!("/api/v1/jobs/{id}"), Some(EDITOR))
            .await["state"]
            .as_str()
            .unwrap()
            .to_string()
    };

    // Cancelled while walking: stopped within 2 s.
    let id = submit(EDITOR).await;
    let t = Instant::now();
    while job_state(id.clone()).await != "running" {
        assert!(t.elapsed() < Duration::from_secs(30), "never started");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    let r = s
        .req(
            reqwest::Method::DELETE,
            &format!("/api/v1/jobs/{id}"),
            Some(EDITOR),
        )
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    let t = Instant::now();
    while job_state(id.clone()).await != "cancelled" {
        assert!(
            t.elapsed() < Duration::from_secs(2),
            "the walks still run 2 s after the DELETE"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }

    // Under a token limited to 1 s: failed at the limit, saying what it would take.
    let id = submit(BRIEF).await;
    let t = Instant::now();
    let done = s.wait_job(&id, ADMIN).await;
    assert!(t.elapsed() < Duration::from_secs(10), "{:?}", t.elapsed());
    assert_eq!(done["state"], "failed", "{done}");
    let message = done["error"].as_str().unwrap();
    assert!(
        message.contains("limit of 1.0 s") && message.contains("would take more than"),
        "{message}"
    );

    // The bundle is the one served before, with nothing left beside it.
    let after = s.relight("cube", Some(VIEWER)).await;
    assert_eq!(after.radiance, before.radiance);
    assert!(
        leftovers(&s.bundles).is_empty(),
        "{:?}",
        leftovers(&s.bundles)
    );
}

/// An animated scene on a team server: the memory budget evicts and reopens the whole
/// sequence (every frame answers as before), re-simulation is refused with a message, and a
/// delete removes the sequence folder, frames and all.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_animated_scene_is_evicted_reopened_and_deleted_whole() {
    let bundles = bundles_with(&["still"]);
    let scene_file = bundles.path().join("slide.json");
    std::fs::write(
        &scene_file,
        json!({
            "animation": {"frames": 4, "fps": 8},
            "patches": {"target": 300},
            "objects": [
                {"name": "floor", "mesh": {"shape": "quad", "size": [1, 1]},
                 "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
                {"name": "box", "mesh": {"shape": "box", "size": [0.1, 0.1, 0.1]},
                 "material": {"type": "translucent", "profile": {"type": "dipole", "preset": "marble"}},
                 "keyframes": [{"frame": 0, "translate": [-0.3, 0.05, 0]},
                               {"frame": 3, "translate": [0.3, 0.05, 0]}]}
            ],
            "lights": [{"type": "point", "position": [0, 0.5, 0.2], "intensity": [1, 1, 1]}],
        })
        .to_string(),
    )
    .unwrap();
    let src = translux_precompute::scene::read_scene_file(&scene_file).unwrap();
    std::fs::remove_file(&scene_file).unwrap();
    translux_precompute::sequence::precompute_sequence(
        &src,
        &bundles.path().join("slide"),
        &Default::default(),
        &|_, _| {},
    )
    .unwrap();
    let frame = |s: &Server, k: u32| {
        let c = s.client.clone();
        let url = s.url("/api/v1/scenes/slide/relight");
        async move {
            let r = c
                .post(url)
                .header(ACCEPT, "application/json")
                .header(CONTENT_TYPE, "application/json")
                .header(AUTHORIZATION, format!("Bearer {EDITOR}"))
                .body(json!({"frame": k}).to_string())
                .send()
                .await
                .unwrap();
            let status = r.status();
            let text = r.text().await.unwrap();
            assert_eq!(status, StatusCode::OK, "frame {k}: {text}");
            serde_json::from_str::<RelightResponse>(&text)
                .unwrap()
                .radiance
        }
    };
    let args = TeamArgs {
        memory_budget: Some(1),
        ..Default::default()
    };
    let s = Server::start(bundles.path(), args, false).await;
    let want: Vec<Vec<f32>> = futures_frames(&s, &frame).await;
    // The still scene evicts the sequence; the next frame reopens all of it.
    s.relight("still", Some(EDITOR)).await;
    let health = s.get_json("/healthz", Some(EDITOR)).await;
    assert!(
        health["scene_states"]
            .as_array()
            .unwrap()
            .iter()
            .any(|x| x["id"] == "slide" && x["state"] == "evicted"),
        "{health}"
    );
    assert_eq!(futures_frames(&s, &frame).await, want);

    let r = s
        .req(
            reqwest::Method::POST,
            "/api/v1/scenes/slide/resimulate",
            Some(EDITOR),
        )
        .header(CONTENT_TYPE, "application/json")
        .body(r#"{"materials": {}}"#)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::BAD_REQUEST);
    assert!(r.text().await.unwrap().contains("is animated (4 frames"));

    let r = s
        .req(reqwest::Method::DELETE, "/api/v1/scenes/slide", Some(ADMIN))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK, "{}", r.text().await.unwrap());
    let t = Instant::now();
    while bundles.path().join("slide").exists() || !leftovers(bundles.path()).is_empty() {
        assert!(
            t.elapsed() < Duration::from_secs(20),
            "the sequence folder stayed"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Every frame of `slide` relit, in order.
async fn futures_frames<F, Fut>(s: &Server, frame: &F) -> Vec<Vec<f32>>
where
    F: Fn(&Server, u32) -> Fut,
    Fut: std::future::Future<Output = Vec<f32>>,
{
    let mut out = Vec::new();
    for k in 0..4 {
        out.push(frame(s, k).await);
    }
    out
}
