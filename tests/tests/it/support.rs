//! The fixtures of the end-to-end tests: one rule for kept folders, one way to build a test
//! bundle, a small Cornell-box bundle built once per test run, a server on 127.0.0.1:0 with chosen settings, reference
//! relights through the library, and small HTTP helpers.

use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use reqwest::StatusCode;
use reqwest::header::{ACCEPT, CONTENT_TYPE};
use serde_json::{Value, json};
use tokio::sync::oneshot;
use translux_engine::relight;
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::{LoadedScene, load_scene};
use translux_proto::api::{ErrorBody, RelightRequest};
use translux_server::state::Scene;
use translux_server::{AppState, ServerParams, load_bundles_with};

/// Patches of the test bundle: small enough to precompute in about a second.
pub const PATCHES: u64 = 400;
pub const ID: &str = "cornell";
const PREFIX: &str = "translux-fixture-";

#[path = "../../fixtures/kept_folder.rs"]
mod kept;
pub use kept::kept_folder;

/// The one way this binary builds a test bundle: `scene` precomputed at about `patches`
/// patches into `dir` (the default transport, no environment bins unless the scene's
/// defaults ask), panicking with the precompute's error.
pub fn build_bundle(scene: &LoadedScene, dir: &Path, patches: u64) {
    let params = PrecomputeParams {
        patches: Some(patches),
        ..Default::default()
    };
    precompute(scene, dir, &params).expect("precompute");
}

/// The folder holding the bundle `cornell` (builtin:cornell at [`PATCHES`]), built on first
/// use and shared by every test of this binary that needs a small scene.
pub fn bundles_root() -> &'static Path {
    static ROOT: OnceLock<PathBuf> = OnceLock::new();
    ROOT.get_or_init(|| {
        let root = kept_folder(PREFIX);
        let scene = load_scene("builtin:cornell").expect("builtin:cornell loads");
        build_bundle(&scene, &root.join(ID), PATCHES);
        root
    })
}

/// The `cornell` bundle's own folder.
pub fn bundle_dir() -> PathBuf {
    bundles_root().join(ID)
}

/// The scene opened through the library, once: the reference relights run on it.
pub fn library_scene() -> &'static Arc<Scene> {
    static SCENE: OnceLock<Arc<Scene>> = OnceLock::new();
    SCENE.get_or_init(|| Arc::new(Scene::open(ID, &bundle_dir()).expect("bundle opens")))
}

/// The radiance the library computes for `request`, flat r, g, b per vertex, solved to a
/// relative residual of 1e-6: the exact answer a server relight approximates.
pub fn reference(request: &Value) -> Vec<f32> {
    let req: RelightRequest = serde_json::from_value(request.clone()).expect("request");
    let scene = library_scene();
    let mut plan = relight::plan(scene, req).expect("plan");
    plan.tolerance = 1e-6;
    let out = relight::run(scene, &plan).expect("relight");
    out.radiance.iter().flatten().copied().collect()
}

/// How close a server answer is to the exact one: the server solves to a relative residual
/// of 0.5 % (the paper's), and with I − SF's condition number of a few, the solution's
/// relative error (2-norm) stays within a few times that.
pub const SOLVER_TOL: f32 = 0.02;

/// ‖a − b‖₂ / ‖b‖₂.
pub fn rel_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "lengths");
    let d: f64 = a.iter().zip(b).map(|(x, y)| ((x - y) as f64).powi(2)).sum();
    let n: f64 = b.iter().map(|y| (*y as f64).powi(2)).sum();
    assert!(n > 0.0, "the reference is black");
    (d / n).sqrt() as f32
}

/// Asserts ‖got − want‖₂ ≤ `tol` ‖want‖₂.
pub fn assert_close(got: &[f32], want: &[f32], tol: f32, what: &str) {
    let d = rel_diff(got, want);
    assert!(d <= tol, "{what}: relative difference {d:.2e} > {tol:.0e}");
}

/// A relight request with one point light at `x` along the box's width (the room spans
/// x, z ∈ [−0.2775, 0.2775], y ∈ [0, 0.555]).
pub fn light_at(x: f32, intensity: [f32; 3]) -> Value {
    json!({"lights": [{"type": "point", "position": [x, 0.5, 0.1], "intensity": intensity}]})
}

/// A running server; stopped gracefully by [`TestServer::stop`].
pub struct TestServer {
    pub addr: std::net::SocketAddr,
    pub client: reqwest::Client,
    stop: Option<oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<std::io::Result<()>>,
}

impl TestServer {
    /// Serves `state` on 127.0.0.1:0.
    pub async fn start(state: AppState) -> TestServer {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let (tx, rx) = oneshot::channel::<()>();
        let task = tokio::spawn(translux_server::serve(listener, state, async move {
            let _ = rx.await;
        }));
        TestServer {
            addr,
            // One connection per concurrent request: no pooling surprises.
            client: reqwest::Client::builder()
                .pool_max_idle_per_host(0)
                .build()
                .unwrap(),
            stop: Some(tx),
            task,
        }
    }

    /// The test bundle served with `params`.
    pub async fn cornell(params: ServerParams) -> TestServer {
        let (state, errors) = load_bundles_with(bundles_root(), params);
        assert!(errors.is_empty(), "{errors:?}");
        TestServer::start(state).await
    }

    pub fn url(&self, path: &str) -> String {
        format!("http://{}{path}", self.addr)
    }

    pub fn ws_url(&self, path: &str) -> String {
        format!("ws://{}{path}", self.addr)
    }

    pub async fn get(&self, path: &str) -> reqwest::Response {
        self.client.get(self.url(path)).send().await.unwrap()
    }

    /// POSTs `body` to the scene's relight route asking for binary f32.
    pub async fn relight(&self, body: &Value) -> reqwest::Response {
        self.client
            .post(self.url(&format!("/api/v1/scenes/{ID}/relight")))
            .header(CONTENT_TYPE, "application/json")
            .header(ACCEPT, "application/octet-stream")
            .body(body.to_string())
            .send()
            .await
            .unwrap()
    }

    /// A relight that must succeed: its radiance.
    pub async fn relight_ok(&self, body: &Value) -> Vec<f32> {
        let r = self.relight(body).await;
        let status = r.status();
        let bytes = r.bytes().await.unwrap();
        assert_eq!(
            status,
            StatusCode::OK,
            "{}",
            String::from_utf8_lossy(&bytes)
        );
        floats(&bytes)
    }

    /// The metrics text.
    pub async fn metrics(&self) -> String {
        let r = self.get("/metrics").await;
        assert_eq!(r.status(), StatusCode::OK);
        r.text().await.unwrap()
    }

    pub async fn stop(mut self) {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        self.task.await.expect("server task").expect("serve");
    }
}

pub fn floats(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

/// Reads an error answer: status, code, message (the body must be the JSON error format).
pub async fn error_of(r: reqwest::Response) -> (StatusCode, String, String) {
    let status = r.status();
    let text = r.text().await.unwrap();
    let body: ErrorBody = serde_json::from_str(&text)
        .unwrap_or_else(|e| panic!("not the JSON error format ({e}): {text}"));
    (status, body.error.code, body.error.message)
}

/// One sample of a Prometheus text exposition.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    pub name: String,
    pub labels: Vec<(String, String)>,
    pub value: f64,
}

fn is_metric_name(s: &str) -> bool {
    !s.is_empty()
        && s.chars().enumerate().all(|(i, c)| {
            c == '_' || c == ':' || c.is_ascii_alphabetic() || (i > 0 && c.is_ascii_digit())
        })
}

/// Reads `{k="v",...}` at the start of `s`; returns the labels and what follows the `}`.
/// A sample's labels (name, value) and the rest of the line after them.
type Labels<'a> = (Vec<(String, String)>, &'a str);

fn parse_labels(s: &str) -> Result<Labels<'_>, &'static str> {
    let mut rest = s.strip_prefix('{').ok_or("expected '{'")?;
    let mut labels = Vec::new();
    loop {
        if let Some(after) = rest.strip_prefix('}') {
            return Ok((labels, after));
        }
        let eq = rest.find('=').ok_or("a label without '='")?;
        let key = &rest[..eq];
        if !is_metric_name(key) || key.contains(':') {
            return Err("bad label name");
        }
        rest = rest[eq + 1..]
            .strip_prefix('"')
            .ok_or("label value not quoted")?;
        let mut value = String::new();
        let mut chars = rest.char_indices();
        let end = loop {
            match chars.next() {
                Some((i, '"')) => break i,
                Some((_, '\\')) => match chars.next() {
                    Some((_, '\\')) => value.push('\\'),
                    Some((_, '"')) => value.push('"'),
                    Some((_, 'n')) => value.push('\n'),
                    _ => return Err("bad escape in a label value"),
                },
                Some((_, c)) => value.push(c),
                None => return Err("unterminated label value"),
            }
        };
        labels.push((key.to_string(), value));
        rest = &rest[end + 1..];
        if let Some(after) = rest.strip_prefix(',') {
            rest = after;
        } else if !rest.starts_with('}') {
            return Err("expected ',' or '}' after a label value");
        }
    }
}

/// Parses the Prometheus text format (version 0.0.4) strictly, after its specification
/// ("Exposition formats", prometheus.io): `# HELP name text`, `# TYPE name
/// counter|gauge|histogram|summary|untyped`, and samples `name{label="value",...} value
/// [timestamp]` with `\\`, `\"` and `\n` escapes in label values; each sample's family must
/// be typed before it. Written here because the crate that parses this format
/// (prometheus-parse 0.2) skips lines it cannot read and cuts label values at a `}` (our
/// route templates hold `{id}`). Panics naming the line on anything else.
pub fn parse_prometheus(text: &str) -> Vec<Sample> {
    let mut typed: std::collections::HashMap<String, String> = Default::default();
    let mut samples = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let bad = |why: &str| -> ! { panic!("metrics line {}: {why}: {line:?}", n + 1) };
        if line.is_empty() {
            continue;
        }
        if let Some(rest) = line.strip_prefix("# ") {
            let mut parts = rest.splitn(3, ' ');
            match (parts.next(), parts.next(), parts.next()) {
                (Some("HELP"), Some(name), _) if is_metric_name(name) => {}
                (Some("TYPE"), Some(name), Some(kind)) if is_metric_name(name) => {
                    if !["counter", "gauge", "histogram", "summary", "untyped"].contains(&kind) {
                        bad("unknown type");
                    }
                    if typed.insert(name.to_string(), kind.to_string()).is_some() {
                        bad("a family typed twice");
                    }
                }
                _ => bad("a comment that is neither HELP nor TYPE"),
            }
            continue;
        }
        let name_end = line.find(['{', ' ']).unwrap_or_else(|| bad("no value"));
        let name = &line[..name_end];
        if !is_metric_name(name) {
            bad("bad metric name");
        }
        let (labels, rest) = if line[name_end..].starts_with('{') {
            parse_labels(&line[name_end..]).unwrap_or_else(|e| bad(e))
        } else {
            (Vec::new(), &line[name_end..])
        };
        let mut fields = rest
            .strip_prefix(' ')
            .unwrap_or_else(|| bad("no space before the value"))
            .split(' ');
        let value: f64 = match fields.next().unwrap_or_else(|| bad("no value")) {
            "+Inf" => f64::INFINITY,
            "-Inf" => f64::NEG_INFINITY,
            "NaN" => f64::NAN,
            v => v.parse().unwrap_or_else(|_| bad("value is not a number")),
        };
        if let Some(ts) = fields.next()
            && ts.parse::<i64>().is_err()
        {
            bad("timestamp is not an integer");
        }
        if fields.next().is_some() {
            bad("trailing fields");
        }
        let family = ["_bucket", "_sum", "_count"]
            .iter()
            .find_map(|suffix| {
                name.strip_suffix(suffix).filter(|base| {
                    typed
                        .get(*base)
                        .is_some_and(|t| t == "histogram" || t == "summary")
                })
            })
            .unwrap_or(name);
        if !typed.contains_key(family) {
            bad("a sample before its # TYPE line");
        }
        samples.push(Sample {
            name: name.to_string(),
            labels,
            value,
        });
    }
    samples
}

/// The value of the sample `name` whose labels are exactly `labels` (any order).
pub fn metric(text: &str, name: &str, labels: &[(&str, &str)]) -> Option<f64> {
    parse_prometheus(text)
        .into_iter()
        .find(|s| {
            s.name == name
                && s.labels.len() == labels.len()
                && labels
                    .iter()
                    .all(|(k, v)| s.labels.iter().any(|(a, b)| a == k && b == v))
        })
        .map(|s| s.value)
}

/// A team server (the API behind access control, uploads and jobs) on 127.0.0.1:0 over the
/// bundles folder `bundles`, started as the binary starts it: the team first (it settles
/// what killed jobs left), then the folder's bundles loaded. Its base URL, and the sender
/// whose drop (or send) stops it.
pub async fn start_team_server(
    bundles: &Path,
    args: &translux_server::team::TeamArgs,
    params: ServerParams,
) -> (String, oneshot::Sender<()>) {
    let state = AppState::with_params(params);
    let team = translux_server::team::Team::start(args, bundles, state.clone()).unwrap();
    let (found, errors) = translux_server::state::discover(bundles).unwrap();
    assert!(errors.is_empty(), "{errors:?}");
    for (id, dir) in found {
        state.load_one(&id, &dir);
    }
    let app = translux_server::team::app(state.clone(), team);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (tx, rx) = oneshot::channel::<()>();
    tokio::spawn(translux_server::serve_router(
        listener,
        state,
        app,
        async move {
            let _ = rx.await;
        },
    ));
    (format!("http://{addr}"), tx)
}
