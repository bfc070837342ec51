//! Several servers behind haproxy: two real `translux-server` processes over one bundles
//! folder (three small scenes), and a real haproxy (Debian's, installed by scripts/test)
//! running `docker/haproxy.cfg` with only its listen addresses and server addresses moved to
//! loopback ports of this test. 16 clients relight through haproxy in a loop:
//!
//! - each scene's requests, and its WebSocket stream, all reach one server (each server's
//!   request log, at debug level, is the record of what it computed), and the scenes are
//!   spread over both;
//! - `kill -9` of a server: no request fails but those it was computing before it was gone
//!   (at most one per client; haproxy sends those again, so in practice none), haproxy
//!   marks it down, and the other server serves its scenes;
//! - SIGTERM of a server (a drain): no request fails at all, the server exits cleanly after
//!   finishing what it had accepted, and haproxy marks it down.
//!
//! Every process is stopped by its pid when the test ends, also when it fails.

use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::load_scene;

const SERVER: &str = env!("CARGO_BIN_EXE_translux-server");
/// The scenes: their ids hash to both servers of docker/haproxy.cfg (checked below).
const SCENES: [&str; 3] = ["a", "b", "c"];
const CLIENTS: usize = 16;

/// A folder of three builtin:cornell bundles (300, 400 and 500 patches), for one test.
fn bundles(prefix: &str) -> PathBuf {
    let root = crate::support::kept_folder(prefix);
    let scene = load_scene("builtin:cornell").expect("builtin:cornell");
    for (id, patches) in SCENES.iter().zip([300, 400, 500]) {
        let params = PrecomputeParams {
            patches: Some(patches),
            progress: false,
            ..Default::default()
        };
        precompute(&scene, &root.join(id), &params).expect("precompute");
    }
    root
}

/// A child process killed (SIGKILL) and reaped when dropped, with its output lines.
pub(crate) struct Proc {
    name: String,
    child: Child,
    lines: Arc<Mutex<Vec<String>>>,
}

impl Proc {
    fn spawn(name: &str, mut cmd: Command) -> Proc {
        let mut child = cmd
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {name}: {e}"));
        let lines = Arc::new(Mutex::new(Vec::new()));
        let out: Box<dyn Read + Send> = Box::new(child.stdout.take().unwrap());
        let err: Box<dyn Read + Send> = Box::new(child.stderr.take().unwrap());
        for pipe in [out, err] {
            let lines = lines.clone();
            std::thread::spawn(move || {
                for line in BufReader::new(pipe).lines().map_while(Result::ok) {
                    lines.lock().unwrap().push(line);
                }
            });
        }
        Proc {
            name: name.to_string(),
            child,
            lines,
        }
    }

    pub(crate) fn log(&self) -> Vec<String> {
        self.lines.lock().unwrap().clone()
    }

    fn signal(&self, sig: &str) {
        let ok = Command::new("kill")
            .args([sig, &self.child.id().to_string()])
            .status()
            .unwrap()
            .success();
        assert!(ok, "kill {sig} {} failed", self.name);
    }

    /// Waits for the process to exit (`limit` at most); its exit status.
    fn wait_exit(&mut self, limit: Duration) -> std::process::ExitStatus {
        let deadline = Instant::now() + limit;
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            assert!(
                Instant::now() < deadline,
                "{} did not exit: {:#?}",
                self.name,
                self.log()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

/// haproxy's log lines worth reading after a failure: requests that did not end normally
/// (a termination state other than `----`) and servers going up or down.
pub(crate) fn unusual(log: &[String]) -> Vec<&String> {
    log.iter()
        .filter(|l| !l.contains(" ---- ") && !l.contains("stats/<STATS>") || l.contains(" is "))
        .collect()
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A `translux-server` over `root` on a free loopback port, logging every request; its
/// address once it listens.
fn start_server(name: &str, root: &Path) -> (Proc, String) {
    let mut cmd = Command::new(SERVER);
    for (k, _) in std::env::vars() {
        if k.starts_with("TRANSLUX_") {
            cmd.env_remove(k);
        }
    }
    cmd.arg("--bundles")
        .arg(root)
        .args(["--addr", "127.0.0.1:0"])
        .env("RUST_LOG", "info,translux_server::routes=debug");
    let p = Proc::spawn(name, cmd);
    let addr = wait_until(Duration::from_secs(60), || {
        p.log().iter().find_map(|l| {
            let rest = l.split("listening on http://").nth(1)?;
            Some(rest.split('/').next()?.to_string())
        })
    })
    .unwrap_or_else(|| panic!("{name} never listened: {:#?}", p.log()));
    (p, addr)
}

/// A loopback port nobody listens on now (haproxy binds it next).
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// `f` every 50 ms until it gives a value or `limit` passes.
fn wait_until<T>(limit: Duration, mut f: impl FnMut() -> Option<T>) -> Option<T> {
    let deadline = Instant::now() + limit;
    loop {
        if let Some(v) = f() {
            return Some(v);
        }
        if Instant::now() > deadline {
            return None;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// docker/haproxy.cfg with its two `bind` addresses and the servers' addresses replaced;
/// every other line (routing, hashing, checks, retries, timeouts) is the file's own.
fn haproxy_config(front: u16, stats: u16, servers: [&str; 2]) -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docker/haproxy.cfg");
    let text = std::fs::read_to_string(path).unwrap();
    let swaps = [
        (
            "    bind :8080\n".to_string(),
            format!("    bind 127.0.0.1:{front}\n"),
        ),
        (
            "    bind 127.0.0.1:8404\n".to_string(),
            format!("    bind 127.0.0.1:{stats}\n"),
        ),
        (
            "    server s1 127.0.0.1:8081 ".to_string(),
            format!("    server s1 {} ", servers[0]),
        ),
        (
            "    server s2 127.0.0.1:8082 ".to_string(),
            format!("    server s2 {} ", servers[1]),
        ),
    ];
    let mut out = text;
    for (from, to) in swaps {
        assert_eq!(
            out.matches(&from).count(),
            1,
            "docker/haproxy.cfg: expected one {from:?}"
        );
        out = out.replace(&from, &to);
    }
    out
}

/// Each server's state in haproxy's stats CSV: `s1` → `UP`, `DOWN`, ...
async fn haproxy_states(c: &reqwest::Client, stats: u16) -> Vec<(String, String)> {
    let Ok(r) = c
        .get(format!("http://127.0.0.1:{stats}/stats;csv"))
        .send()
        .await
    else {
        return Vec::new();
    };
    let text = r.text().await.unwrap_or_default();
    text.lines()
        .filter(|l| l.starts_with("translux_servers,s"))
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[1].to_string(), f[17].to_string())
        })
        .collect()
}

pub(crate) async fn wait_states(
    c: &reqwest::Client,
    stats: u16,
    want: &[(&str, &str)],
    limit: Duration,
) {
    let deadline = Instant::now() + limit;
    loop {
        let states = haproxy_states(c, stats).await;
        let ok = want.iter().all(|(s, w)| {
            states
                .iter()
                .any(|(n, st)| n == s && st.split_whitespace().next() == Some(*w))
        });
        if ok {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "haproxy's servers are {states:?}, not {want:?} after {limit:?}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The two servers, haproxy in front, both servers up and every scene ready on both.
struct Rig {
    servers: Vec<(Proc, String)>,
    haproxy: Proc,
    front: u16,
    stats: u16,
    client: reqwest::Client,
}

/// haproxy running docker/haproxy.cfg in front of two servers (`s1` and `s2`), on free
/// loopback ports; killed when dropped.
pub(crate) struct Haproxy {
    pub(crate) proc: Proc,
    /// The public port (the `translux` frontend).
    pub(crate) front: u16,
    /// The stats page's port.
    pub(crate) stats: u16,
}

/// Starts haproxy with docker/haproxy.cfg ([`haproxy_config`]) in front of `servers`
/// (`s1`, `s2`), checked first with `haproxy -c`, and waits until it listens. A port taken
/// meanwhile by another process is tried again.
pub(crate) fn start_haproxy(servers: [&str; 2]) -> Haproxy {
    let dir = tempfile::tempdir().unwrap();
    let mut tries = 0;
    loop {
        let (front, stats) = (free_port(), free_port());
        let cfg = dir.path().join("haproxy.cfg");
        std::fs::write(&cfg, haproxy_config(front, stats, servers)).unwrap();
        let check = Command::new("haproxy")
            .arg("-c")
            .arg("-f")
            .arg(&cfg)
            .output()
            .unwrap_or_else(|e| panic!("cannot run haproxy ({e}); scripts/test installs it"));
        assert!(
            check.status.success(),
            "haproxy -c: {}",
            String::from_utf8_lossy(&check.stdout)
        );
        let mut cmd = Command::new("haproxy");
        cmd.arg("-db").arg("-f").arg(&cfg);
        let mut p = Proc::spawn("haproxy", cmd);
        let up = wait_until(Duration::from_secs(10), || {
            if p.child.try_wait().unwrap().is_some() {
                return Some(false);
            }
            std::net::TcpStream::connect(("127.0.0.1", stats))
                .ok()
                .map(|_| true)
        });
        if up == Some(true) {
            return Haproxy {
                proc: p,
                front,
                stats,
            };
        }
        tries += 1;
        assert!(tries < 5, "haproxy did not start: {:#?}", p.log());
        let _ = p.child.kill();
    }
}

async fn rig(prefix: &str) -> Rig {
    let root = bundles(prefix);
    let servers = vec![start_server("s1", &root), start_server("s2", &root)];
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(30))
        .build()
        .unwrap();
    for (p, addr) in &servers {
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let h: serde_json::Value = client
                .get(format!("http://{addr}/healthz"))
                .send()
                .await
                .unwrap()
                .json()
                .await
                .unwrap();
            if h["scenes"].as_array().map(Vec::len) == Some(SCENES.len()) {
                break;
            }
            assert!(
                Instant::now() < deadline,
                "{}: scenes never loaded: {h}\n{:#?}",
                p.name,
                p.log()
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
    let Haproxy {
        proc: haproxy,
        front,
        stats,
    } = start_haproxy([&servers[0].1, &servers[1].1]);
    wait_states(
        &client,
        stats,
        &[("s1", "UP"), ("s2", "UP")],
        Duration::from_secs(10),
    )
    .await;
    Rig {
        servers,
        haproxy,
        front,
        stats,
        client,
    }
}

/// One relight through haproxy, as a client saw it.
#[derive(Debug, Clone)]
struct Outcome {
    client: usize,
    scene: &'static str,
    started: Instant,
    ended: Instant,
    /// `Ok(())`, or the status or error.
    result: Result<(), String>,
}

/// A relight with 40 point lights (a shadow ray per patch each): some milliseconds of work,
/// so that a server killed under load is computing some of them.
fn body() -> String {
    let lights: Vec<serde_json::Value> = (0..40)
        .map(|k| {
            let t = k as f32 / 40.0;
            serde_json::json!({"type": "point", "position": [-0.2 + 0.4 * t, 0.5, 0.1],
                               "intensity": [0.02, 0.02, 0.02]})
        })
        .collect();
    serde_json::json!({ "lights": lights }).to_string()
}

/// 16 clients relighting the scenes in turn through haproxy until `stop`.
fn clients(front: u16, stop: Arc<AtomicBool>) -> Vec<tokio::task::JoinHandle<Vec<Outcome>>> {
    (0..CLIENTS)
        .map(|k| {
            let stop = stop.clone();
            tokio::spawn(async move {
                let c = reqwest::Client::builder()
                    .timeout(Duration::from_secs(30))
                    .build()
                    .unwrap();
                let body = body();
                let mut out = Vec::new();
                let mut i = k;
                while !stop.load(Ordering::Relaxed) {
                    let scene = SCENES[i % SCENES.len()];
                    i += 1;
                    let started = Instant::now();
                    let r = c
                        .post(format!(
                            "http://127.0.0.1:{front}/api/v1/scenes/{scene}/relight"
                        ))
                        .header("content-type", "application/json")
                        .header("x-client-id", format!("client-{k}"))
                        .body(body.clone())
                        .send()
                        .await;
                    let result = match r {
                        Ok(r) if r.status() == 200 => match r.bytes().await {
                            Ok(_) => Ok(()),
                            Err(e) => Err(format!("body: {e}")),
                        },
                        Ok(r) => {
                            let s = r.status();
                            Err(format!("{s}: {}", r.text().await.unwrap_or_default()))
                        }
                        Err(e) => {
                            let mut text = e.to_string();
                            let mut source = std::error::Error::source(&e);
                            while let Some(s) = source {
                                text += &format!(": {s}");
                                source = s.source();
                            }
                            Err(text)
                        }
                    };
                    out.push(Outcome {
                        client: k,
                        scene,
                        started,
                        ended: Instant::now(),
                        result,
                    });
                }
                out
            })
        })
        .collect()
}

async fn join(tasks: Vec<tokio::task::JoinHandle<Vec<Outcome>>>) -> Vec<Outcome> {
    let mut all = Vec::new();
    for t in tasks {
        all.extend(t.await.unwrap());
    }
    all
}

/// A WebSocket stream of `scene` through haproxy: `ready` naming the scene, one relight,
/// its binary frame and `stats`, then a close.
async fn stream_once(front: u16, scene: &str) {
    use futures_util::{SinkExt, StreamExt};
    use tokio_tungstenite::tungstenite::Message;
    let url = format!("ws://127.0.0.1:{front}/api/v1/scenes/{scene}/stream");
    let (mut ws, _) = tokio_tungstenite::connect_async(url)
        .await
        .unwrap_or_else(|e| panic!("{scene}: no WebSocket through haproxy: {e}"));
    let msg = serde_json::json!({"type": "relight", "seq": 1,
                                 "request": serde_json::from_str::<serde_json::Value>(&body()).unwrap()});
    let (mut ready, mut frame, mut stats) = (false, false, false);
    let deadline = Instant::now() + Duration::from_secs(30);
    while !(ready && frame && stats) {
        let left = deadline.saturating_duration_since(Instant::now());
        let m = tokio::time::timeout(left, ws.next())
            .await
            .unwrap_or_else(|_| {
                panic!("{scene}: stream: ready {ready}, frame {frame}, stats {stats}")
            })
            .expect("the stream is open")
            .expect("a message");
        match m {
            Message::Text(t) => {
                let v: serde_json::Value = serde_json::from_str(t.as_str()).unwrap();
                match v["type"].as_str() {
                    Some("ready") => {
                        assert_eq!(v["scene"], scene, "{v}");
                        ready = true;
                        ws.send(Message::text(msg.to_string())).await.unwrap();
                    }
                    Some("stats") => stats = true,
                    _ => panic!("{scene}: unexpected {v}"),
                }
            }
            Message::Binary(b) => {
                assert!(
                    b.starts_with(b"TLXF"),
                    "{scene}: a frame without its header"
                );
                frame = true;
            }
            _ => {}
        }
    }
    let _ = ws.close(None).await;
}

/// Relights of each scene in a server's request log (lines from `from` on).
fn served(log: &[String], from: usize) -> Vec<(&'static str, usize)> {
    SCENES
        .iter()
        .map(|s| {
            let path = format!("path=/api/v1/scenes/{s}/relight ");
            let n = log[from.min(log.len())..]
                .iter()
                .filter(|l| l.contains(&path) && l.contains("status=200"))
                .count();
            (*s, n)
        })
        .collect()
}

/// Under load, each scene's relights on one server, both servers used, and each scene's
/// stream on its server. Returns the index of the server holding scene `a`.
async fn scenes_stay_on_one_server(rig: &Rig) -> usize {
    let stop = Arc::new(AtomicBool::new(false));
    let tasks = clients(rig.front, stop.clone());
    tokio::time::sleep(Duration::from_secs(3)).await;
    stop.store(true, Ordering::Relaxed);
    let outcomes = join(tasks).await;
    let failed: Vec<&Outcome> = outcomes.iter().filter(|o| o.result.is_err()).collect();
    assert!(
        failed.is_empty(),
        "failures with both servers up: {failed:#?}"
    );
    assert!(outcomes.len() >= 3 * CLIENTS, "{} relights", outcomes.len());
    // Wait for the last request lines, then read who served what.
    tokio::time::sleep(Duration::from_millis(200)).await;
    let per: Vec<Vec<(&str, usize)>> = rig
        .servers
        .iter()
        .map(|(p, _)| served(&p.log(), 0))
        .collect();
    let mut owner = Vec::new();
    for (k, scene) in SCENES.iter().enumerate() {
        let total: usize = per.iter().map(|s| s[k].1).sum();
        let want = outcomes.iter().filter(|o| o.scene == *scene).count();
        assert_eq!(total, want, "{scene}: {per:?}");
        let on: Vec<usize> = (0..per.len()).filter(|&i| per[i][k].1 > 0).collect();
        assert_eq!(
            on.len(),
            1,
            "scene {scene} was served by several servers: {per:?}"
        );
        owner.push(on[0]);
    }
    assert!(
        owner.contains(&0) && owner.contains(&1),
        "every scene hashed to one server ({per:?}): choose other ids"
    );
    // A stream of each scene is tunnelled to that scene's server.
    for (k, scene) in SCENES.iter().enumerate() {
        stream_once(rig.front, scene).await;
        tokio::time::sleep(Duration::from_millis(100)).await;
        let path = format!("path=/api/v1/scenes/{scene}/stream ");
        for (i, (p, _)) in rig.servers.iter().enumerate() {
            let n = p.log().iter().filter(|l| l.contains(&path)).count();
            assert_eq!(
                n,
                usize::from(i == owner[k]),
                "{scene}'s stream on {}",
                p.name
            );
        }
    }
    owner[0]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_of_a_server_fails_only_its_requests_in_flight() {
    let mut rig = rig("server-balancer-kill-").await;
    let victim = scenes_stay_on_one_server(&rig).await;
    let survivor = 1 - victim;
    let survivor_from = rig.servers[survivor].0.log().len();

    let stop = Arc::new(AtomicBool::new(false));
    let tasks = clients(rig.front, stop.clone());
    tokio::time::sleep(Duration::from_secs(2)).await;
    // SIGKILL (`kill -9`), then the moment the process is reaped: its sockets are closed.
    let sent = Instant::now();
    let killed = tokio::task::block_in_place(|| {
        let child = &mut rig.servers[victim].0.child;
        child.kill().unwrap();
        child.wait().unwrap()
    });
    let killed_at = Instant::now();
    assert!(!killed.success());
    let name = ["s1", "s2"][victim];
    wait_states(
        &rig.client,
        rig.stats,
        &[(name, "DOWN")],
        Duration::from_secs(5),
    )
    .await;
    tokio::time::sleep(Duration::from_secs(3)).await;
    stop.store(true, Ordering::Relaxed);
    let outcomes = join(tasks).await;

    let failed: Vec<&Outcome> = outcomes.iter().filter(|o| o.result.is_err()).collect();
    let report: Vec<String> = failed
        .iter()
        .map(|f| {
            let ms = |t: Instant| {
                if t >= killed_at {
                    (t - killed_at).as_secs_f64() * 1e3
                } else {
                    -(killed_at - t).as_secs_f64() * 1e3
                }
            };
            format!(
                "client {} {}: {:.1} ms to {:.1} ms after the kill: {:?}",
                f.client,
                f.scene,
                ms(f.started),
                ms(f.ended),
                f.result
            )
        })
        .collect();
    assert!(
        failed.len() <= CLIENTS,
        "{} failures, more than the {CLIENTS} clients could have in flight (SIGKILL took {:?}): \
         {report:#?}\nhaproxy: {:#?}",
        failed.len(),
        killed_at - sent,
        unusual(&rig.haproxy.log())
    );
    for k in 0..CLIENTS {
        let n = failed.iter().filter(|f| f.client == k).count();
        assert!(n <= 1, "client {k} failed {n} times: {report:#?}");
    }
    for f in &failed {
        assert!(
            f.started < killed_at,
            "a request sent {:?} after the kill failed: {f:?}\nhaproxy: {:#?}",
            f.started - killed_at,
            unusual(&rig.haproxy.log())
        );
    }
    // Within a few seconds of the kill every scene is served, by the survivor.
    let late = killed_at + Duration::from_secs(2);
    for scene in SCENES {
        let after: Vec<&Outcome> = outcomes
            .iter()
            .filter(|o| o.scene == scene && o.started >= late)
            .collect();
        assert!(!after.is_empty(), "no request for {scene} after the kill");
        assert!(after.iter().all(|o| o.result.is_ok()), "{after:#?}");
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    let moved = served(&rig.servers[survivor].0.log(), survivor_from);
    assert!(
        moved.iter().all(|(_, n)| *n > 0),
        "the survivor did not serve every scene after the kill: {moved:?}"
    );
    eprintln!(
        "kill -9: {} relights, {} failed (in flight at the kill), last failure {:?} after it",
        outcomes.len(),
        failed.len(),
        failed.iter().map(|f| f.ended - killed_at).max()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_drains_a_server_without_failures() {
    let mut rig = rig("server-balancer-drain-").await;
    let victim = scenes_stay_on_one_server(&rig).await;
    let survivor = 1 - victim;
    let survivor_from = rig.servers[survivor].0.log().len();

    let stop = Arc::new(AtomicBool::new(false));
    let tasks = clients(rig.front, stop.clone());
    tokio::time::sleep(Duration::from_secs(2)).await;
    let stopped_at = Instant::now();
    rig.servers[victim].0.signal("-TERM");
    let name = ["s1", "s2"][victim];
    wait_states(
        &rig.client,
        rig.stats,
        &[(name, "DOWN")],
        Duration::from_secs(5),
    )
    .await;
    let status = rig.servers[victim]
        .0
        .wait_exit(translux_server::SHUTDOWN_GRACE + Duration::from_secs(10));
    assert!(
        status.success(),
        "{status}: {:#?}",
        rig.servers[victim].0.log()
    );
    tokio::time::sleep(Duration::from_secs(2)).await;
    stop.store(true, Ordering::Relaxed);
    let outcomes = join(tasks).await;

    let failed: Vec<&Outcome> = outcomes.iter().filter(|o| o.result.is_err()).collect();
    assert!(
        failed.is_empty(),
        "a drain failed requests: {failed:#?}\nhaproxy: {:#?}",
        unusual(&rig.haproxy.log())
    );
    let after = outcomes.iter().filter(|o| o.started > stopped_at).count();
    assert!(after >= CLIENTS, "{after} relights after the stop");
    tokio::time::sleep(Duration::from_millis(200)).await;
    let moved = served(&rig.servers[survivor].0.log(), survivor_from);
    assert!(
        moved.iter().all(|(_, n)| *n > 0),
        "the survivor did not serve every scene after the stop: {moved:?}"
    );
    let log = rig.servers[victim].0.log().join("\n");
    assert!(log.contains("shutting down"), "{log}");
}
