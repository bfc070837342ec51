//! The Python client (`clients/python`, package `translux`) against a real server: a team
//! server with tokens on a copy of the small Cornell bundle runs the client's own test
//! script, `clients/python/tests/test_client.py` (relight arrays against the JSON route,
//! errors and the 401's message, the stream's order, an upload followed to its end, renders
//! and exports). `scripts/test` installs the package with pip; when Python, the package or
//! its dependencies are missing, or the installed package is not this checkout's source,
//! the test fails saying so.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use tokio::sync::oneshot;
use translux_server::ServerParams;
use translux_server::auth::hash_token;
use translux_server::team::TeamArgs;

const VIEWER: &str = "tlx_pyviewer_00000000000000000000000000";
const EDITOR: &str = "tlx_pyeditor_11111111111111111111111111";

/// The tests the script must run, so a script that loses tests fails here.
const TESTS: usize = 10;

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ has a parent")
        .to_path_buf()
}

fn python(args: &[&str], envs: &[(&str, String)]) -> Output {
    let mut cmd = Command::new("python3");
    cmd.args(args)
        .current_dir(repo_root())
        // No __pycache__ folders in the checkout.
        .env("PYTHONDONTWRITEBYTECODE", "1");
    for (k, v) in envs {
        cmd.env(k, v);
    }
    cmd.output().unwrap_or_else(|e| {
        panic!(
            "cannot run python3 ({e}): the Python client's tests need Python 3.9 or later \
             with the package installed (`python3 -m pip install ./clients/python`, as \
             scripts/test does)"
        )
    })
}

/// Fails unless `import translux` gives this checkout's `clients/python/src/translux`.
const PREFLIGHT: &str = r#"
import importlib.metadata, pathlib, sys
try:
    import numpy, requests, websocket, translux
except ImportError as e:
    sys.exit(f"cannot import {e.name}: install the client with "
             "`python3 -m pip install ./clients/python` (scripts/test does)")
src = pathlib.Path(sys.argv[1])
installed = pathlib.Path(translux.__file__).parent
stale = [p.name for p in sorted(src.glob("*.py"))
         if not (installed / p.name).is_file()
         or (installed / p.name).read_bytes() != p.read_bytes()]
if stale:
    sys.exit(f"the installed translux ({installed}) differs from clients/python/src in "
             f"{', '.join(stale)}: reinstall it with `python3 -m pip install ./clients/python`")
print(importlib.metadata.version("translux"), installed)
"#;

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
}

/// A team server (tokens: a viewer and an editor) on `bundles`; stops when the sender drops.
async fn team_server(bundles: &Path, secrets: &Path) -> (String, oneshot::Sender<()>) {
    let tokens = secrets.join("tokens.toml");
    let mut text = String::new();
    for (name, role, token) in [("vic", "viewer", VIEWER), ("eddie", "editor", EDITOR)] {
        text.push_str(&format!(
            "[[tokens]]\nname = \"{name}\"\nrole = \"{role}\"\nsha256 = \"{}\"\n\n",
            hash_token(token).unwrap()
        ));
    }
    std::fs::write(&tokens, text).unwrap();
    let args = TeamArgs {
        tokens: Some(tokens),
        job_threads: Some(2),
        ..TeamArgs::default()
    };
    crate::support::start_team_server(bundles, &args, ServerParams::default()).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_python_client_passes_its_tests_against_a_real_server() {
    let root = repo_root();
    let src = root.join("clients/python/src/translux");
    let pre = python(&["-c", PREFLIGHT, src.to_str().unwrap()], &[]);
    assert!(
        pre.status.success(),
        "the Python client is not usable: {}{}",
        String::from_utf8_lossy(&pre.stdout),
        String::from_utf8_lossy(&pre.stderr)
    );

    // Uploads write into the bundles folder: serve a copy of the shared Cornell bundle.
    let bundles = tempfile::tempdir().unwrap();
    copy_dir(
        &crate::support::bundle_dir(),
        &bundles.path().join("cornell"),
    );
    let secrets = tempfile::tempdir().unwrap();
    let (url, _stop) = team_server(bundles.path(), secrets.path()).await;

    let t = Instant::now();
    let envs = [
        ("TRANSLUX_URL", url.clone()),
        ("TRANSLUX_VIEWER_TOKEN", VIEWER.to_string()),
        ("TRANSLUX_EDITOR_TOKEN", EDITOR.to_string()),
        ("TRANSLUX_SCENE", "cornell".to_string()),
    ];
    let out = tokio::task::spawn_blocking(move || {
        python(
            &[
                "-m",
                "unittest",
                "-v",
                "clients/python/tests/test_client.py",
            ],
            &envs,
        )
    })
    .await
    .unwrap();
    let report = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        out.status.success(),
        "the Python client's tests failed:\n{report}"
    );
    // unittest writes its summary to stderr: every test ran, none was skipped.
    assert!(
        report.contains(&format!("Ran {TESTS} tests")) && !report.contains("skipped"),
        "expected {TESTS} tests run and none skipped:\n{report}"
    );
    assert!(
        t.elapsed() < Duration::from_secs(120),
        "the Python client's tests took {:?}",
        t.elapsed()
    );
}
