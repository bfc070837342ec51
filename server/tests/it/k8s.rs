//! The Kubernetes manifests of `docker/k8s/` without a cluster: every file passes
//! `kubernetes-validate --strict` (PyPI, pinned in scripts/test; it carries the API schemas)
//! for the oldest and the newest Kubernetes version we state, a deliberately broken
//! manifest is refused (so the check can fail), and the files agree with each other and
//! with the server: the ConfigMap's `server.toml` is read by the server's own config
//! reader, its paths are where the Deployment mounts the volume and the Secret, and the
//! Indexed Job's shard count is its completions and the merge Job's count.

use std::path::{Path, PathBuf};
use std::process::Command;

use yaml_rust2::{Yaml, YamlLoader};

/// The Kubernetes versions the manifests are checked against: 1.29 (the oldest a managed
/// cloud still runs; `backoffLimitPerIndex` is there) and the newest the validator knows.
const VERSIONS: [&str; 2] = ["1.29.0", "1.37.0"];

fn k8s_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../docker/k8s")
}

fn manifests() -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(k8s_dir())
        .expect("docker/k8s exists")
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "yaml" || e == "yml"))
        .collect();
    files.sort();
    files
}

/// `kubernetes-validate --strict -k VERSION FILE`: whether it passed, and what it said.
fn validate(file: &Path, version: &str) -> (bool, String) {
    let out = Command::new("kubernetes-validate")
        .args(["--strict", "--kubernetes-version", version])
        .arg(file)
        .output()
        .unwrap_or_else(|e| {
            panic!("cannot run kubernetes-validate ({e}); scripts/test installs it from PyPI")
        });
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

/// Every document of a YAML file.
fn docs(file: &Path) -> Vec<Yaml> {
    let text = std::fs::read_to_string(file).unwrap();
    YamlLoader::load_from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", file.display()))
}

/// The one document of `kind` named `name` in docker/k8s.
fn resource(kind: &str, name: &str) -> Yaml {
    let found: Vec<Yaml> = manifests()
        .iter()
        .flat_map(|f| docs(f))
        .filter(|d| {
            d["kind"].as_str() == Some(kind) && d["metadata"]["name"].as_str() == Some(name)
        })
        .collect();
    assert_eq!(found.len(), 1, "{kind}/{name} in docker/k8s");
    found[0].clone()
}

fn strings(y: &Yaml) -> Vec<String> {
    y.as_vec()
        .unwrap_or_else(|| panic!("not a list: {y:?}"))
        .iter()
        .map(|v| match v {
            Yaml::String(s) => s.clone(),
            Yaml::Integer(i) => i.to_string(),
            other => panic!("not a string: {other:?}"),
        })
        .collect()
}

#[test]
fn every_manifest_passes_the_schemas() {
    let files = manifests();
    let kinds: Vec<String> = files
        .iter()
        .flat_map(|f| docs(f))
        .map(|d| d["kind"].as_str().unwrap_or("?").to_string())
        .collect();
    for kind in [
        "Job",
        "Deployment",
        "Service",
        "PersistentVolumeClaim",
        "ConfigMap",
    ] {
        assert!(kinds.iter().any(|k| k == kind), "no {kind}: {kinds:?}");
    }
    let mut failed = Vec::new();
    for version in VERSIONS {
        for f in &files {
            let (ok, text) = validate(f, version);
            if !ok {
                failed.push(format!("{} for {version}:\n{text}", f.display()));
            }
        }
    }
    assert!(failed.is_empty(), "{}", failed.join("\n"));
}

/// The check can fail: the shards Job with a misspelt field, and with a word for a number.
#[test]
fn a_broken_manifest_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let good = std::fs::read_to_string(k8s_dir().join("precompute-shards.yaml")).unwrap();
    let cases = [
        (
            "completionMode: Indexed",
            "completionMod: Indexed",
            "completionMod",
        ),
        ("parallelism: 4", "parallelism: four", "parallelism"),
    ];
    for (from, to, named) in cases {
        assert!(
            good.contains(from),
            "precompute-shards.yaml has no {from:?}"
        );
        let file = dir.path().join("broken.yaml");
        std::fs::write(&file, good.replacen(from, to, 1)).unwrap();
        let (ok, text) = validate(&file, VERSIONS[0]);
        assert!(!ok, "{to:?} passed: {text}");
        assert!(
            text.contains(named),
            "{to:?}: the message does not name it: {text}"
        );
    }
}

#[test]
fn the_manifests_agree_with_each_other_and_the_server() {
    // The shards: an Indexed Job whose --shard I/K has K = completions; the merge's K too.
    let shards = resource("Job", "translux-shards-room");
    let spec = &shards["spec"];
    assert_eq!(spec["completionMode"].as_str(), Some("Indexed"));
    let k = spec["completions"].as_i64().expect("completions");
    let args = strings(&spec["template"]["spec"]["containers"][0]["args"]);
    let shard = args.iter().position(|a| a == "--shard").expect("--shard");
    assert_eq!(args[shard + 1], format!("$(JOB_COMPLETION_INDEX)/{k}"));
    let merge = resource("Job", "translux-merge-room");
    let margs = strings(&merge["spec"]["template"]["spec"]["containers"][0]["args"]);
    let m = margs.iter().position(|a| a == "--merge").expect("--merge");
    assert_eq!(margs[m + 1], k.to_string());
    // The same scene and bundle folder in both.
    assert_eq!(args[..shard], margs[..m]);

    // The servers: a GPU each, probes on /healthz, the config the server reads.
    let deploy = resource("Deployment", "translux-server");
    let pod = &deploy["spec"]["template"]["spec"];
    let c = &pod["containers"][0];
    assert_eq!(
        c["resources"]["limits"]["nvidia.com/gpu"].as_i64(),
        Some(1),
        "{c:?}"
    );
    for probe in ["readinessProbe", "livenessProbe"] {
        assert_eq!(c[probe]["httpGet"]["path"].as_str(), Some("/healthz"));
    }
    let mounts: Vec<(String, String)> = c["volumeMounts"]
        .as_vec()
        .unwrap()
        .iter()
        .map(|m| {
            (
                m["name"].as_str().unwrap().to_string(),
                m["mountPath"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    let config_map = resource("ConfigMap", "translux-server-config");
    let toml = config_map["data"]["server.toml"].as_str().unwrap();
    let cfg = translux_server::config::FileConfig::parse(toml).expect("server.toml");
    let args = strings(&c["args"]);
    let config_mount = mounts.iter().find(|(n, _)| n == "config").unwrap();
    assert_eq!(
        args,
        ["--config", &format!("{}/server.toml", config_mount.1)]
    );
    let bundles = cfg.bundles.expect("bundles");
    assert!(
        mounts.iter().any(|(_, p)| Path::new(p) == bundles),
        "{bundles:?} is not mounted: {mounts:?}"
    );
    let tokens = cfg.tokens.expect("tokens: a network address needs them");
    let secret_mount = mounts.iter().find(|(n, _)| n == "tokens").unwrap();
    assert_eq!(tokens.parent(), Some(Path::new(&secret_mount.1)));
    assert!(cfg.addr.is_some_and(|a| a.ends_with(":8080")));
    // The shared volume is one ReadWriteMany claim, the one every pod mounts.
    let pvc = resource("PersistentVolumeClaim", "translux-shared");
    assert_eq!(strings(&pvc["spec"]["accessModes"]), ["ReadWriteMany"]);
    for spec in [pod, &shards["spec"]["template"]["spec"]] {
        assert_eq!(
            spec["volumes"][0]["persistentVolumeClaim"]["claimName"].as_str(),
            Some("translux-shared")
        );
    }
}
