//! The `translux-server` command line: arguments, logging, the demo bundle, the listener.

use std::future::Future;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Parser;
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::load_scene;
use translux_proto::bundle::Bundle;

use crate::state::load_bundles;

/// Where `--demo` keeps its bundles when `--bundles` is not given.
pub const DEMO_DIR: &str = "demo-bundles";
/// The demo scene and its bundle id.
pub const DEMO_SCENE: &str = "builtin:cornell";
pub const DEMO_ID: &str = "cornell";
/// Patches of the demo bundle: ready in seconds on two cores.
pub const DEMO_PATCHES: u64 = 3000;

/// Serves translux bundles: lights in, per-vertex colours out.
#[derive(Debug, Clone, Parser)]
#[command(
    name = "translux-server",
    version,
    about,
    long_about = None,
    after_help = "Examples:\n  translux-server --demo\n  translux-server --bundles bundles --addr 0.0.0.0:8080\n\n\
                  Logging: RUST_LOG (default info); RUST_LOG=debug logs every request."
)]
pub struct Args {
    /// Folder of bundles: each sub-folder is one bundle, served under its folder name.
    #[arg(
        long,
        value_name = "DIR",
        env = "TRANSLUX_BUNDLES",
        required_unless_present = "demo"
    )]
    pub bundles: Option<PathBuf>,
    /// Address to listen on.
    #[arg(
        long,
        value_name = "HOST:PORT",
        env = "TRANSLUX_ADDR",
        default_value = "127.0.0.1:8080"
    )]
    pub addr: String,
    /// Precompute the built-in Cornell box into DIR/cornell (DIR: --bundles, else
    /// ./demo-bundles) unless a valid bundle is already there, then serve DIR.
    #[arg(long)]
    pub demo: bool,
}

/// The binary's `main`: logging from `RUST_LOG` (default `info`), then [`run`].
pub fn main() -> ExitCode {
    let args = Args::parse();
    init_tracing();
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(rt) => rt,
        Err(e) => {
            tracing::error!("cannot start the async runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    match runtime.block_on(run(args, shutdown_signal())) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!("{e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Logs to stderr, filtered by `RUST_LOG` (default `info`).
pub fn init_tracing() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    // A second call (tests) keeps the first subscriber.
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .try_init();
}

/// Prepares the demo bundle if asked, opens the bundles, listens on `args.addr` and serves
/// until `shutdown` completes.
pub async fn run(
    args: Args,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    let dir = match (&args.bundles, args.demo) {
        (Some(dir), _) => dir.clone(),
        (None, true) => PathBuf::from(DEMO_DIR),
        (None, false) => bail!("--bundles DIR is required (or --demo)"),
    };
    if args.demo {
        let demo_dir = dir.clone();
        tokio::task::spawn_blocking(move || ensure_demo_bundle(&demo_dir))
            .await
            .context("the demo precompute task failed")??;
    }
    if !dir.is_dir() {
        bail!("--bundles {}: no such folder", dir.display());
    }

    let loading = dir.clone();
    let (state, errors) = tokio::task::spawn_blocking(move || load_bundles(&loading))
        .await
        .context("the bundle loading task failed")?;
    for (id, error) in &errors {
        tracing::warn!("skipping bundle {id:?} in {}: {error}", dir.display());
    }
    for scene in state.scenes() {
        let m = scene.bundle.manifest();
        tracing::info!(
            "serving {:?} ({}, from {}): {} patches, {} vertices, {} objects, nnz(F) {}, {:.1} MB",
            scene.id,
            m.name,
            m.source,
            m.patch_count,
            m.vertex_count,
            m.objects.len(),
            m.form_factors.nnz,
            scene.bundle.total_bytes() as f64 / 1e6
        );
    }
    if state.is_empty() {
        tracing::warn!("no valid bundle under {}; serving no scenes", dir.display());
    }

    let listener = tokio::net::TcpListener::bind(&args.addr)
        .await
        .with_context(|| format!("cannot listen on {}", args.addr))?;
    let local = listener
        .local_addr()
        .context("cannot read the listening address")?;
    tracing::info!("listening on http://{local}/ (Ctrl-C to stop)");
    crate::serve(listener, state, shutdown)
        .await
        .context("the server failed")?;
    tracing::info!("stopped");
    Ok(())
}

/// Makes sure `dir/cornell` holds a valid bundle, precomputing `builtin:cornell` at
/// [`DEMO_PATCHES`] patches if not.
pub fn ensure_demo_bundle(dir: &Path) -> anyhow::Result<()> {
    let out = dir.join(DEMO_ID);
    let why = match Bundle::open(&out) {
        Ok(b) => {
            tracing::info!(
                "demo bundle {} is ready ({} patches)",
                out.display(),
                b.manifest().patch_count
            );
            return Ok(());
        }
        Err(e) => e,
    };
    tracing::info!(
        "no valid demo bundle in {} ({why}); precomputing {DEMO_SCENE} at {DEMO_PATCHES} patches",
        out.display()
    );
    let t = Instant::now();
    let scene = load_scene(DEMO_SCENE).with_context(|| format!("cannot load {DEMO_SCENE}"))?;
    let params = PrecomputeParams {
        patches: Some(DEMO_PATCHES),
        progress: true,
        ..Default::default()
    };
    let report = precompute(&scene, &out, &params)
        .with_context(|| format!("cannot precompute {DEMO_SCENE} into {}", out.display()))?;
    tracing::info!(
        "demo bundle written to {} in {:.1} s: {} patches, {} vertices, nnz(F) {}, {:.1} MB",
        out.display(),
        t.elapsed().as_secs_f64(),
        report.patch_count,
        report.vertex_count,
        report.nnz_f,
        report.bundle_bytes as f64 / 1e6
    );
    Ok(())
}

/// Completes on Ctrl-C or (on Unix) SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        if let Err(e) = tokio::signal::ctrl_c().await {
            tracing::warn!("cannot listen for Ctrl-C: {e}");
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(e) => {
                tracing::warn!("cannot listen for SIGTERM: {e}");
                std::future::pending::<()>().await;
            }
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = terminate => {},
    }
    tracing::info!("shutting down: finishing requests in flight");
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arguments() {
        let a = Args::try_parse_from(["translux-server", "--demo"]).unwrap();
        assert!(a.demo && a.bundles.is_none());
        assert_eq!(a.addr, "127.0.0.1:8080");
        let a = Args::try_parse_from([
            "translux-server",
            "--bundles",
            "b",
            "--addr",
            "0.0.0.0:9000",
        ])
        .unwrap();
        assert_eq!(a.bundles, Some(PathBuf::from("b")));
        assert_eq!(a.addr, "0.0.0.0:9000");
        assert!(Args::try_parse_from(["translux-server", "--demo", "--bundles", "x"]).is_ok());
        // Without --bundles or --demo (and no TRANSLUX_BUNDLES in the environment): refused.
        if std::env::var_os("TRANSLUX_BUNDLES").is_none() {
            assert!(Args::try_parse_from(["translux-server"]).is_err());
        }
    }
}
