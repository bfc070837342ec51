//! Graceful shutdown of the real `translux-server` binary: SIGTERM while relights are queued
//! loses none of the requests the server accepted, and the process exits cleanly.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use translux_engine::relight;
use translux_proto::api::RelightRequest;
use translux_server::state::Scene;

const BIN: &str = env!("CARGO_BIN_EXE_translux-server");
const PREFIX: &str = "server-shutdown-";

/// A folder holding a 400-patch Cornell box as `cornell`, fresh for this test binary.
pub(crate) fn bundles() -> PathBuf {
    let root = crate::support::kept_folder(PREFIX);
    crate::support::cornell_into(&root, 400);
    root
}

/// The server process and its log lines.
pub(crate) struct Server {
    child: Child,
    lines: mpsc::Receiver<String>,
    pub(crate) log: Vec<String>,
    pub(crate) base: String,
}

impl Server {
    pub(crate) fn start(root: &Path, extra: &[&str]) -> Server {
        let mut child = Command::new(BIN)
            .arg("--bundles")
            .arg(root)
            .args(["--addr", "127.0.0.1:0"])
            .args(extra)
            .env("RUST_LOG", "info")
            .env_remove("TRANSLUX_BUNDLES")
            .env_remove("TRANSLUX_CONFIG")
            .stderr(Stdio::piped())
            .stdout(Stdio::null())
            .spawn()
            .unwrap();
        let stderr = child.stderr.take().unwrap();
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let mut s = Server {
            child,
            lines,
            log: Vec::new(),
            base: String::new(),
        };
        let line = s.wait_for("listening on http://");
        let addr = line
            .split("listening on http://")
            .nth(1)
            .and_then(|r| r.split('/').next())
            .unwrap()
            .to_string();
        s.base = format!("http://{addr}");
        s
    }

    /// Moves the log lines written so far into `log`.
    pub(crate) fn drain(&mut self) {
        while let Ok(line) = self.lines.try_recv() {
            self.log.push(line);
        }
    }

    /// Waits for a log line containing `needle` (60 s at most).
    pub(crate) fn wait_for(&mut self, needle: &str) -> String {
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(line) => {
                    self.log.push(line.clone());
                    if line.contains(needle) {
                        return line;
                    }
                }
                Err(_) => panic!("no {needle:?} in the log: {:#?}", self.log),
            }
        }
    }

    fn sigterm(&self) {
        let ok = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()
            .unwrap()
            .success();
        assert!(ok, "kill -TERM failed");
    }

    /// Waits for the process to exit (60 s at most); returns whether it succeeded.
    fn wait_exit(&mut self) -> bool {
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                while let Ok(line) = self.lines.recv_timeout(Duration::from_millis(200)) {
                    self.log.push(line);
                }
                return status.success();
            }
            if Instant::now() > deadline {
                let _ = self.child.kill();
                panic!("the server did not exit after SIGTERM: {:#?}", self.log);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The value of an unlabelled or labelled sample line `name` in the metrics text.
fn sample(text: &str, name: &str) -> f64 {
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or(0.0)
}

/// A request with `n` point lights (each a shadow ray per patch: `n` sets the cost).
fn request(n: usize, shift: f32) -> Value {
    let lights: Vec<Value> = (0..n)
        .map(|k| {
            let t = k as f32 / n as f32;
            json!({"type": "point", "position": [-0.2 + 0.4 * t, 0.5, -0.2 + 0.4 * ((t * 5.0 + shift) % 1.0)],
                   "intensity": [0.02, 0.02, 0.02]})
        })
        .collect();
    json!({ "lights": lights })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_with_relights_queued_loses_no_accepted_request() {
    let root = bundles();
    let mut server = Server::start(&root, &["--workers", "1", "--no-batch", "--queue", "1000"]);
    let client = reqwest::Client::builder()
        .pool_max_idle_per_host(0)
        .build()
        .unwrap();
    // Wait until the scene has loaded.
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let h: Value = client
            .get(format!("{}/healthz", server.base))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        if h["scenes"] == json!(["cornell"]) {
            break;
        }
        assert!(Instant::now() < deadline, "the scene never loaded: {h}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }

    const N: usize = 24;
    let bodies: Vec<Value> = (0..N).map(|k| request(100, k as f32 / N as f32)).collect();
    let tasks: Vec<_> = bodies
        .iter()
        .map(|body| {
            let c = client.clone();
            let url = format!("{}/api/v1/scenes/cornell/relight", server.base);
            let body = body.to_string();
            tokio::spawn(async move {
                let r = c
                    .post(url)
                    .header("content-type", "application/json")
                    .body(body)
                    .send()
                    .await
                    .expect("an accepted request is answered");
                let status = r.status();
                (status, r.bytes().await.expect("the whole answer"))
            })
        })
        .collect();

    // Every request accepted (done, computing or queued), some still queued: SIGTERM now.
    let deadline = Instant::now() + Duration::from_secs(60);
    let queued = loop {
        let m = client
            .get(format!("{}/metrics", server.base))
            .send()
            .await
            .unwrap()
            .text()
            .await
            .unwrap();
        let done = sample(&m, "translux_relights_total{outcome=\"ok\"}");
        let queued = sample(&m, "translux_queue_depth");
        let running = sample(&m, "translux_relights_in_flight");
        if done + queued + running >= N as f64 {
            break queued;
        }
        assert!(
            Instant::now() < deadline,
            "requests never reached the queue:\n{m}"
        );
        tokio::time::sleep(Duration::from_millis(2)).await;
    };
    server.sigterm();
    assert!(
        queued >= 1.0,
        "nothing was queued at SIGTERM; make the requests heavier"
    );

    // Every accepted request gets its full, correct answer.
    let scene = Scene::open("cornell", &root.join("cornell")).unwrap();
    for (k, t) in tasks.into_iter().enumerate() {
        let (status, bytes) = t.await.unwrap();
        assert_eq!(
            status,
            200,
            "request {k}: {}",
            String::from_utf8_lossy(&bytes)
        );
        let got: Vec<f32> = bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        let req: RelightRequest = serde_json::from_value(bodies[k].clone()).unwrap();
        // The exact answer (residual 1e-6); the server solves to 0.5 %, so the solution is
        // within a few times that (2-norm).
        let mut plan = relight::plan(&scene, req).unwrap();
        plan.tolerance = 1e-6;
        let want = relight::run(&scene, &plan).unwrap();
        let want: Vec<f32> = want.radiance.iter().flatten().copied().collect();
        assert_eq!(got.len(), want.len(), "request {k}");
        let d: f32 = got.iter().zip(&want).map(|(g, w)| (g - w) * (g - w)).sum();
        let n: f32 = want.iter().map(|w| w * w).sum();
        assert!(
            (d / n).sqrt() <= 0.02,
            "request {k}: relative difference {}",
            (d / n).sqrt()
        );
    }
    assert!(server.wait_exit(), "exit status: {:#?}", server.log);
    let log = server.log.join("\n");
    assert!(
        log.contains("shutting down") && log.contains("stopped"),
        "{log}"
    );
    // Nothing listens any more.
    assert!(
        client
            .get(format!("{}/healthz", server.base))
            .send()
            .await
            .is_err()
    );
}

#[test]
fn sigterm_right_after_start_exits_cleanly() {
    let root = bundles();
    let mut server = Server::start(&root, &[]);
    server.sigterm();
    assert!(server.wait_exit(), "{:#?}", server.log);
}

/// A client that sends half a request head and stops is disconnected after the header
/// timeout (it used to be kept open forever), and open connections cannot keep SIGTERM
/// from ending the process.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn half_sent_headers_time_out_and_sigterm_still_ends_the_process() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let root = bundles();
    let mut server = Server::start(&root, &[]);
    let addr = server.base.trim_start_matches("http://").to_string();
    let half = |mut s: tokio::net::TcpStream| async move {
        s.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
            .await
            .unwrap();
        s
    };
    let mut slow = half(tokio::net::TcpStream::connect(&addr).await.unwrap()).await;
    let t0 = Instant::now();
    let limit = translux_server::HEADER_TIMEOUT;
    let mut buf = [0u8; 512];
    // Closed (EOF or reset), or answered 408 and then closed: anything but silence.
    let ended = tokio::time::timeout(limit + Duration::from_secs(20), async {
        loop {
            match slow.read(&mut buf).await {
                Ok(0) | Err(_) => break,
                Ok(_) => continue,
            }
        }
    })
    .await;
    assert!(ended.is_ok(), "a half-sent header held its connection open");
    let waited = t0.elapsed();
    assert!(
        waited + Duration::from_secs(1) >= limit,
        "closed after {waited:?}, before the {limit:?} header timeout"
    );

    // Two more half-open connections and an idle keep-alive one: SIGTERM still ends the
    // process, within the shutdown grace.
    let _a = half(tokio::net::TcpStream::connect(&addr).await.unwrap()).await;
    let _b = half(tokio::net::TcpStream::connect(&addr).await.unwrap()).await;
    let _idle = tokio::net::TcpStream::connect(&addr).await.unwrap();
    let t0 = Instant::now();
    server.sigterm();
    assert!(server.wait_exit(), "{:#?}", server.log);
    assert!(
        t0.elapsed() < translux_server::SHUTDOWN_GRACE + Duration::from_secs(10),
        "exit took {:?}",
        t0.elapsed()
    );
}

/// SIGTERM while a request runs hours of lamp walks (three lamps × 10⁷ walks into a
/// simulated cube): the walks stop, the request is answered 503 `cancelled`, and the
/// process exits well within the shutdown grace (it ran on for hours).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_stops_lamp_walks_in_flight() {
    let root = crate::support::kept_folder("server-shutdown-walks-");
    let scene = root.join("cube.json");
    std::fs::write(
        &scene,
        json!({"unit_mm": 1, "objects": [{"name": "cube",
                 "mesh": {"shape": "box", "size": [20, 20, 20]},
                 "material": {"type": "simulated", "sigma_s_prime": [2, 2, 2],
                              "sigma_a": [0.004, 0.008, 0.02], "eta": 1.0}}]})
        .to_string(),
    )
    .unwrap();
    let loaded = translux_precompute::scene::load_scene_file(&scene).unwrap();
    let params = translux_precompute::pipeline::PrecomputeParams {
        patches: Some(200),
        progress: false,
        ..Default::default()
    };
    translux_precompute::pipeline::precompute(&loaded, &root.join("cube"), &params).unwrap();
    std::fs::remove_file(&scene).unwrap();

    let mut server = Server::start(&root, &[]);
    server.wait_for("serving \"cube\"");
    let lamps: Vec<Value> = [[30.0, 0.0, 0.0], [0.0, 30.0, 0.0], [0.0, 0.0, 30.0]]
        .iter()
        .map(|p| json!({"type": "point", "position": p, "intensity": [1000, 1000, 1000]}))
        .collect();
    let body = json!({"lights": lamps, "lamp_walks": 10_000_000}).to_string();
    let url = format!("{}/api/v1/scenes/cube/relight", server.base);
    let walking = tokio::spawn(async move {
        let r = reqwest::Client::new()
            .post(url)
            .header("content-type", "application/json")
            .body(body)
            .send()
            .await
            .expect("answered");
        (r.status(), r.text().await.unwrap_or_default())
    });
    // Let the walks start.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert!(!walking.is_finished(), "the walks ended by themselves");
    let t0 = Instant::now();
    server.sigterm();
    assert!(server.wait_exit(), "{:#?}", server.log);
    let took = t0.elapsed();
    let (status, text) = walking.await.unwrap();
    assert_eq!(status.as_u16(), 503, "{text}");
    assert!(text.contains("cancelled"), "{text}");
    assert!(
        took < Duration::from_secs(5),
        "exit took {took:?} after SIGTERM"
    );
}
