//! Several real `translux-server` processes over one bundles folder (a cluster's shared
//! filesystem): bundles that appear, are replaced or are removed are picked up by every
//! server without a restart, with no request failing across a replacement; a server
//! starting does not fail another's running job; a token added to the shared tokens file
//! is accepted by a running server. Each server is killed when its guard drops
//! ([`crate::shutdown::Server`]).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::load_scene;
use translux_server::auth::{Role, add_token};

use crate::shutdown::Server;

/// How often the servers here look at the folder (the default is 2 s).
const RESCAN: &[&str] = &["--rescan-s", "0.5"];

/// A fresh, empty bundles folder.
fn folder() -> PathBuf {
    crate::support::kept_folder("server-shared-")
}

/// builtin:cornell at about `patches` patches written to `dir` the way users write
/// bundles: the precompute writes a temporary folder and renames it into place (an
/// existing bundle is renamed aside first).
fn build(dir: &Path, patches: u64) {
    let scene = load_scene("builtin:cornell").expect("builtin:cornell loads");
    let params = PrecomputeParams {
        patches: Some(patches),
        progress: false,
        ..Default::default()
    };
    precompute(&scene, dir, &params).expect("precompute");
}

fn client() -> reqwest::Client {
    reqwest::Client::builder()
        .timeout(Duration::from_secs(60))
        .build()
        .unwrap()
}

/// `GET path` on `base` with an optional bearer token: the status and the JSON body.
async fn get(c: &reqwest::Client, base: &str, path: &str, token: Option<&str>) -> (u16, Value) {
    let mut req = c.get(format!("{base}{path}"));
    if let Some(t) = token {
        req = req.bearer_auth(t);
    }
    let r = req.send().await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

/// Waits (20 s at most) until `check` holds for `GET path` on every server.
async fn until_all(
    c: &reqwest::Client,
    servers: &[&Server],
    path: &str,
    what: &str,
    check: impl Fn(u16, &Value) -> bool,
) {
    let deadline = Instant::now() + Duration::from_secs(20);
    for s in servers {
        loop {
            let (status, body) = get(c, &s.base, path, None).await;
            if check(status, &body) {
                break;
            }
            assert!(
                Instant::now() < deadline,
                "{} never showed {what}: {status} {body}",
                s.base
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
}

/// Relights `scene` on `base` over and over until `stop`, counting answers and failures
/// (any status but 200, or a short answer), each failure noted.
fn relight_stream(
    c: reqwest::Client,
    base: String,
    stop: Arc<AtomicBool>,
    ok: Arc<AtomicUsize>,
) -> tokio::task::JoinHandle<Vec<String>> {
    tokio::spawn(async move {
        let body = json!({"lights": [{"type": "point", "position": [0.0, 0.5, 0.0],
                                       "intensity": [1.0, 1.0, 1.0]}]})
        .to_string();
        let mut failures = Vec::new();
        while !stop.load(Ordering::Relaxed) {
            let r = c
                .post(format!("{base}/api/v1/scenes/room/relight"))
                .header("content-type", "application/json")
                .body(body.clone())
                .send()
                .await;
            match r {
                Ok(r) if r.status() == 200 => match r.bytes().await {
                    Ok(b) if !b.is_empty() => {
                        ok.fetch_add(1, Ordering::Relaxed);
                    }
                    other => failures.push(format!("{base}: a short answer: {other:?}")),
                },
                Ok(r) => {
                    let status = r.status();
                    failures.push(format!("{base}: {status} {}", r.text().await.unwrap()));
                }
                Err(e) => failures.push(format!("{base}: {e}")),
            }
        }
        failures
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bundles_that_appear_are_replaced_or_are_removed_are_picked_up_by_every_server() {
    let root = folder();
    let a = Server::start(&root, &[RESCAN, &["--workers", "1"]].concat());
    let b = Server::start(&root, &[RESCAN, &["--workers", "1"]].concat());
    let c = client();
    let servers = [&a, &b];

    // A bundle built into the folder after the servers started is served by both.
    build(&root.join("room"), 150);
    let mut first = 0;
    until_all(
        &c,
        &servers,
        "/api/v1/scenes/room",
        "the new bundle",
        |s, v| s == 200 && v["patches"].as_u64().is_some(),
    )
    .await;
    for s in &servers {
        let (_, v) = get(&c, &s.base, "/api/v1/scenes/room", None).await;
        let patches = v["patches"].as_u64().unwrap();
        assert!(first == 0 || first == patches, "{v}");
        first = patches;
    }

    // Replaced under a stream of relights on both: both swap, no request fails.
    let stop = Arc::new(AtomicBool::new(false));
    let ok = Arc::new(AtomicUsize::new(0));
    let streams: Vec<_> = servers
        .iter()
        .map(|s| relight_stream(c.clone(), s.base.clone(), stop.clone(), ok.clone()))
        .collect();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let room = root.join("room");
    tokio::task::spawn_blocking(move || build(&room, 400))
        .await
        .unwrap();
    until_all(
        &c,
        &servers,
        "/api/v1/scenes/room",
        "the replaced bundle",
        |s, v| s == 200 && v["patches"].as_u64().is_some_and(|p| p != first),
    )
    .await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let before = ok.load(Ordering::Relaxed);
    stop.store(true, Ordering::Relaxed);
    let mut failures = Vec::new();
    for s in streams {
        failures.extend(s.await.unwrap());
    }
    assert!(failures.is_empty(), "{failures:#?}");
    assert!(before >= 4, "only {before} relights answered");

    // Removed: both answer 404 within a few rescans.
    std::fs::remove_dir_all(root.join("room")).unwrap();
    until_all(&c, &servers, "/api/v1/scenes/room", "404", |s, _| s == 404).await;
    let (_, list) = get(&c, &a.base, "/api/v1/scenes", None).await;
    assert_eq!(list["scenes"], json!([]), "{list}");
}

/// A replacement that does not open leaves the old bundle served; a folder copied in
/// without a manifest is not served.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replacement_that_does_not_open_keeps_the_old_bundle_served() {
    let root = folder();
    build(&root.join("room"), 150);
    let mut a = Server::start(&root, RESCAN);
    let c = client();
    until_all(&c, &[&a], "/api/v1/scenes/room", "the bundle", |s, _| {
        s == 200
    })
    .await;
    let (_, v) = get(&c, &a.base, "/api/v1/scenes/room", None).await;
    let patches = v["patches"].as_u64().unwrap();

    // A broken bundle renamed into place: its largest array cut short.
    let broken = root.join(".room.broken");
    build(&broken, 300);
    let biggest = std::fs::read_dir(&broken)
        .unwrap()
        .flatten()
        .max_by_key(|e| e.metadata().unwrap().len())
        .unwrap()
        .path();
    let len = std::fs::metadata(&biggest).unwrap().len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&biggest)
        .unwrap()
        .set_len(len / 2)
        .unwrap();
    std::fs::rename(root.join("room"), root.join(".room.aside")).unwrap();
    std::fs::rename(&broken, root.join("room")).unwrap();
    a.wait_for("still serving the bundle \"room\" had");
    let (status, v) = get(&c, &a.base, "/api/v1/scenes/room", None).await;
    assert_eq!((status, v["patches"].as_u64()), (200, Some(patches)), "{v}");

    std::fs::create_dir(root.join("empty")).unwrap();
    tokio::time::sleep(Duration::from_millis(1200)).await;
    let (status, _) = get(&c, &a.base, "/api/v1/scenes/empty", None).await;
    assert_eq!(status, 404);
}

/// A `multipart/form-data` body with a scene file and text fields; the boundary is
/// returned with it.
fn upload_body(scene: &str, fields: &[(&str, &str)]) -> (String, Vec<u8>) {
    let boundary = "translux-shared-folder-boundary";
    let mut body = String::new();
    body.push_str(&format!(
        "--{boundary}\r\nContent-Disposition: form-data; name=\"scene\"; \
         filename=\"ball.json\"\r\nContent-Type: application/json\r\n\r\n{scene}\r\n"
    ));
    for (k, v) in fields {
        body.push_str(&format!(
            "--{boundary}\r\nContent-Disposition: form-data; name=\"{k}\"\r\n\r\n{v}\r\n"
        ));
    }
    body.push_str(&format!("--{boundary}--\r\n"));
    (boundary.to_string(), body.into_bytes())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_starting_does_not_fail_another_servers_running_job() {
    let root = folder();
    let mut a = Server::start(&root, &[RESCAN, &["--workers", "1"]].concat());
    let c = client();
    // A sphere at 40,000 patches: its form factors take a while on two cores.
    let scene = json!({"objects": [{"name": "ball", "mesh": {"shape": "sphere", "radius": 1},
                        "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}}]})
    .to_string();
    let (boundary, body) = upload_body(&scene, &[("id", "ball"), ("patches", "40000")]);
    let r = c
        .post(format!("{}/api/v1/scenes", a.base))
        .header(
            "content-type",
            format!("multipart/form-data; boundary={boundary}"),
        )
        .body(body)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 202);
    let job: Value = r.json().await.unwrap();
    let id = job["id"].as_str().unwrap().to_string();
    let path = format!("/api/v1/jobs/{id}");
    until_all(&c, &[&a], &path, "the job running", |_, v| {
        v["state"] == "running"
    })
    .await;
    assert!(root.join(".jobs").join(format!("{id}.lock")).is_file());

    // B starts over the same folder while A's job runs: the job stays A's and running.
    let mut b = Server::start(&root, RESCAN);
    b.drain();
    let settled = b.log.iter().find(|l| l.contains(&id)).cloned();
    assert!(settled.is_none(), "B settled A's job: {settled:?}");
    for s in [&a, &b] {
        let (status, r) = get(&c, &s.base, &path, None).await;
        assert_eq!(
            (status, &r["state"]),
            (200, &json!("running")),
            "{}: {r}",
            s.base
        );
        let (_, list) = get(&c, &s.base, "/api/v1/jobs", None).await;
        assert!(
            list["jobs"]
                .as_array()
                .unwrap()
                .iter()
                .any(|j| j["id"] == id),
            "{}: {list}",
            s.base
        );
    }
    // B does not fight A's job for the scene: a cancel there is refused, not faked.
    let r = c.delete(format!("{}{path}", b.base)).send().await.unwrap();
    assert_eq!(r.status(), 409, "{}", r.text().await.unwrap());
    let (_, r) = get(&c, &a.base, &path, None).await;
    assert_eq!(r["state"], "running", "{r}");

    // Cancelled on A, the record is final for both, never "failed".
    let r = c.delete(format!("{}{path}", a.base)).send().await.unwrap();
    assert_eq!(r.status(), 200);
    until_all(&c, &[&a, &b], &path, "the job cancelled", |_, v| {
        v["state"] == "cancelled"
    })
    .await;
    assert!(!root.join(".jobs").join(format!("{id}.lock")).exists());
    a.drain();
    assert!(
        !a.log
            .iter()
            .chain(&b.log)
            .any(|l| l.contains("marked failed")),
        "{:#?}",
        b.log
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_token_added_to_the_shared_tokens_file_is_accepted_within_a_rescan() {
    const ADMIN: &str = "tlx_shared_folder_admin_0123456789abcdef";
    const LATER: &str = "tlx_shared_folder_later_0123456789abcdef";
    let root = folder();
    let tokens = root.join(".tokens.toml");
    add_token(&tokens, "admin", Role::Admin, None, ADMIN).unwrap();
    let tokens_arg = tokens.to_str().unwrap().to_string();
    let mut a = Server::start(&root, &[RESCAN, &["--tokens", &tokens_arg]].concat());
    let c = client();
    let (status, _) = get(&c, &a.base, "/api/v1/whoami", Some(LATER)).await;
    assert_eq!(status, 401);

    // `token add` on another server (here: the library call it makes).
    add_token(&tokens, "later", Role::Viewer, None, LATER).unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let (status, who) = get(&c, &a.base, "/api/v1/whoami", Some(LATER)).await;
        if status == 200 {
            assert_eq!(who["name"], "later", "{who}");
            break;
        }
        assert!(Instant::now() < deadline, "the new token is still refused");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }

    // A file that no longer reads keeps the tokens in force, and says why in the log.
    let mut text = std::fs::read_to_string(&tokens).unwrap();
    text.push_str("\n[[tokens]]\nname = \"half\"\n");
    std::fs::write(&tokens, text).unwrap();
    a.wait_for("does not read; keeping the tokens it had");
    for t in [ADMIN, LATER] {
        let (status, _) = get(&c, &a.base, "/api/v1/whoami", Some(t)).await;
        assert_eq!(status, 200);
    }
}
