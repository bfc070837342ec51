//! Translucency preparation in the real `translux-server` binary (`--prepare-translucency`):
//! by default a loaded scene's radial terms are made in the background and its detail says
//! so; under a memory budget only once the scene is first asked for; with `off` only by the
//! first translucency change.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use serde_json::{Value, json};

use crate::shutdown::Server;

/// A folder holding a 400-patch Cornell box (a translucent `tall_block`) as `cornell`.
fn bundles(case: &str) -> PathBuf {
    let root = crate::support::kept_folder(&format!("server-prepare-{case}-"));
    crate::support::cornell_into(&root, 400);
    root
}

fn client() -> reqwest::Client {
    reqwest::Client::builder()
        .pool_max_idle_per_host(0)
        .build()
        .unwrap()
}

async fn get(c: &reqwest::Client, url: String) -> Value {
    let r = c.get(&url).send().await.unwrap();
    assert!(r.status().is_success(), "{url}: {}", r.status());
    r.json().await.unwrap()
}

/// Waits until `/healthz` lists the scene.
async fn loaded(c: &reqwest::Client, base: &str) {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let h = get(c, format!("{base}/healthz")).await;
        if h["scenes"] == json!(["cornell"]) {
            return;
        }
        assert!(Instant::now() < deadline, "the scene never loaded: {h}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// The scene detail's `translucency` once its state is `want` (60 s at most).
async fn state_becomes(c: &reqwest::Client, base: &str, want: &str) -> Value {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let d = get(c, format!("{base}/api/v1/scenes/cornell")).await;
        let t = d["translucency"].clone();
        if t["state"] == want {
            return t;
        }
        assert!(Instant::now() < deadline, "translucency never {want}: {t}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// A translucency change of the tall block.
async fn change(c: &reqwest::Client, base: &str) {
    let body = json!({"materials": {"tall_block": {"type": "translucent",
        "profile": {"type": "dipole", "preset": "marble", "scale": 0.5}}}});
    let r = c
        .post(format!("{base}/api/v1/scenes/cornell/relight"))
        .json(&body)
        .send()
        .await
        .unwrap();
    assert!(r.status().is_success(), "{}", r.status());
}

fn ready_on_cpu(t: &Value) {
    assert_eq!(t["on"], "cpu", "{t}");
    assert!(t["bytes"].as_u64().is_some_and(|b| b > 0), "{t}");
    assert!(t["seconds"].as_f64().is_some_and(|s| s >= 0.0), "{t}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_loaded_scene_is_prepared_in_the_background_by_default() {
    let root = bundles("load");
    let mut server = Server::start(&root, &["--backend", "cpu"]);
    let c = client();
    // Prepared without any request for the scene.
    server.wait_for("translucency changes prepared");
    loaded(&c, &server.base).await;
    let t = state_becomes(&c, &server.base, "ready").await;
    ready_on_cpu(&t);
    change(&c, &server.base).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn under_a_memory_budget_a_scene_is_prepared_on_its_first_request() {
    let root = bundles("budget");
    let mut server = Server::start(&root, &["--backend", "cpu", "--memory-budget", "4GiB"]);
    let c = client();
    loaded(&c, &server.base).await;
    // Neither the list nor the health report asks for the scene: nothing is prepared.
    get(&c, format!("{}/api/v1/scenes", server.base)).await;
    tokio::time::sleep(Duration::from_millis(1500)).await;
    server.drain();
    assert!(
        !server
            .log
            .iter()
            .any(|l| l.contains("translucency changes prepared")),
        "prepared before any request for the scene: {:#?}",
        server.log
    );
    let t = state_becomes(&c, &server.base, "ready").await;
    ready_on_cpu(&t);
    server.wait_for("translucency changes prepared");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_preparation_off_the_first_change_makes_the_terms() {
    let root = bundles("off");
    let server = Server::start(
        &root,
        &["--backend", "cpu", "--prepare-translucency", "off"],
    );
    let c = client();
    loaded(&c, &server.base).await;
    for _ in 0..10 {
        let d = get(&c, format!("{}/api/v1/scenes/cornell", server.base)).await;
        assert_eq!(d["translucency"], json!({"state": "pending"}));
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    change(&c, &server.base).await;
    let t = state_becomes(&c, &server.base, "ready").await;
    ready_on_cpu(&t);
}
