//! The container set-up without a container engine: reads `docker/compose.yaml` and the
//! `ENV` lines of `docker/Dockerfile`, starts the real `translux-server` binary with the
//! same arguments and environment (container paths mapped to a temporary folder, the port
//! to 127.0.0.1:0), and checks what a team would see: health open, the API behind the
//! tokens secret. Also: the same image without a tokens file refuses to serve a network.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use yaml_rust2::{Yaml, YamlLoader};

const TOKEN: &str = "tlx_deploy_test_token_0123456789abcdef";

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The translux service of the compose file.
fn service() -> Yaml {
    let text = std::fs::read_to_string(repo().join("docker/compose.yaml")).unwrap();
    let docs = YamlLoader::load_from_str(&text).expect("compose.yaml is YAML");
    docs[0]["services"]["translux"].clone()
}

fn scalar(y: &Yaml) -> String {
    match y {
        Yaml::String(s) => s.clone(),
        Yaml::Integer(i) => i.to_string(),
        Yaml::Real(r) => r.clone(),
        Yaml::Boolean(b) => b.to_string(),
        other => panic!("not a scalar: {other:?}"),
    }
}

/// `ENV K=V K2=V2 \` lines of the Dockerfile's last stage.
fn dockerfile_env() -> Vec<(String, String)> {
    let text = std::fs::read_to_string(repo().join("docker/Dockerfile")).unwrap();
    let runtime = text.rsplit("\nFROM ").next().unwrap();
    let joined = runtime.replace("\\\n", " ");
    let mut out = Vec::new();
    for line in joined.lines() {
        if let Some(rest) = line.trim().strip_prefix("ENV ") {
            for kv in rest.split_whitespace() {
                let (k, v) = kv.split_once('=').expect("ENV K=V");
                out.push((k.to_string(), v.to_string()));
            }
        }
    }
    out
}

struct Mapped {
    args: Vec<String>,
    env: Vec<(String, String)>,
}

/// The container's command and environment with its paths moved under `root`.
fn mapped(root: &Path) -> Mapped {
    let map = |s: &str| {
        s.replace("/data/bundles", &root.join("bundles").to_string_lossy())
            .replace(
                "/run/secrets/translux_tokens",
                &root.join("tokens.toml").to_string_lossy(),
            )
            .replace("0.0.0.0:8080", "127.0.0.1:0")
    };
    let svc = service();
    let args = svc["command"]
        .as_vec()
        .expect("command is a list")
        .iter()
        .map(|a| map(&scalar(a)))
        .collect();
    let mut env: Vec<(String, String)> = dockerfile_env()
        .into_iter()
        .map(|(k, v)| (k, map(&v)))
        .collect();
    for (k, v) in svc["environment"].as_hash().expect("environment is a map") {
        env.push((scalar(k), map(&scalar(v))));
    }
    Mapped { args, env }
}

fn spawn(m: &Mapped) -> Child {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_translux-server"));
    for (k, _) in std::env::vars() {
        if k.starts_with("TRANSLUX_") {
            cmd.env_remove(k);
        }
    }
    cmd.args(&m.args)
        .envs(m.env.iter().map(|(k, v)| (k, v)))
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// Stderr lines as they come.
fn lines(child: &mut Child) -> mpsc::Receiver<String> {
    let (tx, rx) = mpsc::channel();
    let stderr = child.stderr.take().unwrap();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

#[test]
fn compose_file_declares_the_gpu_the_volume_the_secret_and_the_healthcheck() {
    let svc = service();
    let device = &svc["deploy"]["resources"]["reservations"]["devices"][0];
    assert_eq!(device["driver"].as_str(), Some("nvidia"));
    assert!(
        device["capabilities"]
            .as_vec()
            .unwrap()
            .iter()
            .any(|c| c.as_str() == Some("gpu"))
    );
    let volumes: Vec<String> = svc["volumes"]
        .as_vec()
        .unwrap()
        .iter()
        .map(scalar)
        .collect();
    assert!(
        volumes.iter().any(|v| v.ends_with(":/data/bundles")),
        "{volumes:?}"
    );
    let secrets: Vec<String> = svc["secrets"]
        .as_vec()
        .unwrap()
        .iter()
        .map(scalar)
        .collect();
    assert_eq!(secrets, ["translux_tokens"]);
    let ports: Vec<String> = svc["ports"].as_vec().unwrap().iter().map(scalar).collect();
    assert_eq!(ports, ["8080:8080"]);
    let health: Vec<String> = svc["healthcheck"]["test"]
        .as_vec()
        .unwrap()
        .iter()
        .map(scalar)
        .collect();
    assert!(health.iter().any(|h| h.ends_with("/healthz")), "{health:?}");
    let env = dockerfile_env();
    assert!(
        env.contains(&(
            "NVIDIA_DRIVER_CAPABILITIES".into(),
            "compute,utility,graphics".into()
        )),
        "{env:?}"
    );
}

#[test]
fn the_binary_serves_as_the_container_would() {
    let root = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(root.path().join("bundles")).unwrap();
    let hash = translux_server::auth::hash_token(TOKEN).unwrap();
    std::fs::write(
        root.path().join("tokens.toml"),
        format!("[[tokens]]\nname = \"ops\"\nrole = \"admin\"\nsha256 = \"{hash}\"\n"),
    )
    .unwrap();
    let m = mapped(root.path());
    assert!(
        m.args.iter().any(|a| a == "--memory-budget"),
        "{:?}",
        m.args
    );
    let mut child = spawn(&m);
    let rx = lines(&mut child);
    let mut seen = Vec::new();
    let addr = loop {
        let line = rx
            .recv_timeout(Duration::from_secs(60))
            .unwrap_or_else(|_| panic!("no `listening on` line; stderr: {seen:#?}"));
        if let Some(rest) = line.split("listening on http://").nth(1) {
            break rest.split('/').next().unwrap().to_string();
        }
        seen.push(line);
    };
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let result = rt.block_on(async {
        let c = reqwest::Client::new();
        let health = c
            .get(format!("http://{addr}/healthz"))
            .send()
            .await
            .unwrap();
        let open = c
            .get(format!("http://{addr}/api/v1/scenes"))
            .send()
            .await
            .unwrap();
        let who: serde_json::Value = c
            .get(format!("http://{addr}/api/v1/whoami"))
            .bearer_auth(TOKEN)
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        (health.status().as_u16(), open.status().as_u16(), who)
    });
    let _ = child.kill();
    let _ = child.wait();
    let mut log: Vec<String> = seen;
    log.extend(rx.try_iter());
    assert_eq!(result.0, 200, "{log:#?}");
    assert_eq!(result.1, 401, "{log:#?}");
    assert_eq!(result.2["name"], "ops");
    assert_eq!(result.2["role"], "admin");
    assert!(
        log.iter().any(|l| l.contains("access control on")),
        "{log:#?}"
    );
    assert!(!log.iter().any(|l| l.contains(TOKEN)));
}

#[test]
fn without_tokens_a_network_address_is_refused() {
    let root = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(root.path().join("bundles")).unwrap();
    let mut m = mapped(root.path());
    // The image without its secret: no --tokens, no TRANSLUX_TOKENS, the image's address.
    if let Some(k) = m.args.iter().position(|a| a == "--tokens") {
        m.args.drain(k..k + 2);
    }
    m.env.retain(|(k, _)| k != "TRANSLUX_TOKENS");
    for a in m.args.iter_mut() {
        if a == "127.0.0.1:0" {
            *a = "0.0.0.0:0".into();
        }
    }
    let out = Command::new(env!("CARGO_BIN_EXE_translux-server"))
        .args(&m.args)
        .envs(m.env.iter().map(|(k, v)| (k, v)))
        .env_remove("TRANSLUX_TOKENS")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(stderr.contains("refusing to listen"), "{stderr}");
    assert!(stderr.contains("--tokens"), "{stderr}");
}
