//! The `translux-server` command line: arguments, logging, the demo bundle, the listener,
//! and the offline subcommands.
//!
//! Two forms, told apart by clap:
//! - the server: `translux-server --bundles DIR [--addr HOST:PORT]` or `--demo` (flags only,
//!   as always);
//! - an offline command: `translux-server render | export | relight --bundle DIR
//!   [--request REQ.json] --out FILE ...` ([`crate::offline`]). A subcommand lifts the
//!   server's `--bundles`-or-`--demo` requirement (`subcommand_negates_reqs`), and the
//!   server's flags cannot be mixed with a subcommand (`args_conflicts_with_subcommands`).

use std::future::Future;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, bail};
use clap::{Parser, Subcommand};
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::load_scene;
use translux_proto::api::ToneMap;
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
    subcommand_negates_reqs = true,
    args_conflicts_with_subcommands = true,
    after_help = "Examples:\n  translux-server --demo\n  translux-server --bundles bundles --addr 0.0.0.0:8080\n  \
                  translux-server render --bundle demo-bundles/cornell --out cornell.png\n  \
                  translux-server export --bundle demo-bundles/cornell --request req.json --out cornell.glb\n\n\
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
    /// An offline command instead of the server.
    #[command(subcommand)]
    pub command: Option<Command>,
}

/// The offline commands: one bundle, one request, one file out, no HTTP.
#[derive(Debug, Clone, Subcommand)]
pub enum Command {
    /// Relight a bundle and render it from a camera to a PNG.
    Render(RenderArgs),
    /// Relight a bundle and write its mesh with baked vertex colours (.glb or .ply).
    Export(ExportArgs),
    /// Relight a bundle and write the per-vertex radiance B/pi (.f32 or .json).
    Relight(RelightArgs),
}

/// `translux-server render`.
#[derive(Debug, Clone, clap::Args)]
#[command(
    after_help = "The request is POST /api/v1/scenes/{id}/render's body: the relight \
    fields (lights, materials, components, solver) plus camera, width, height, exposure, tone, \
    background, cull_backfaces. Flags override the file's fields."
)]
pub struct RenderArgs {
    /// The bundle folder (written by translux-precompute).
    #[arg(long, value_name = "DIR")]
    pub bundle: PathBuf,
    /// JSON render request (`-`: standard input); default `{}`: the bundle's lights and camera.
    #[arg(long, value_name = "REQ.json")]
    pub request: Option<PathBuf>,
    /// The PNG to write.
    #[arg(long, value_name = "FILE.png")]
    pub out: PathBuf,
    /// Image width in pixels (1..=8192; default 800).
    #[arg(long)]
    pub width: Option<u32>,
    /// Image height in pixels (1..=8192; default 600).
    #[arg(long)]
    pub height: Option<u32>,
    /// Exposure in EV stops (radiance × 2^EV; default 0).
    #[arg(long, allow_negative_numbers = true)]
    pub exposure: Option<f32>,
    /// Tone curve: srgb (clamp) or filmic (ACES fit); default srgb.
    #[arg(long, value_name = "srgb|filmic")]
    pub tone: Option<ToneMap>,
}

/// `translux-server export`.
#[derive(Debug, Clone, clap::Args)]
#[command(
    after_help = "glTF colours (COLOR_0) are linear floats (exposure and tone curve \
    applied, no sRGB encoding: glTF vertex colours are linear); PLY colours are 8-bit sRGB."
)]
pub struct ExportArgs {
    /// The bundle folder (written by translux-precompute).
    #[arg(long, value_name = "DIR")]
    pub bundle: PathBuf,
    /// JSON relight request (`-`: standard input); default `{}`: the bundle's lights.
    #[arg(long, value_name = "REQ.json")]
    pub request: Option<PathBuf>,
    /// The file to write: FILE.glb (binary glTF 2.0) or FILE.ply (binary PLY).
    #[arg(long, value_name = "FILE.glb|FILE.ply")]
    pub out: PathBuf,
    /// Exposure in EV stops applied to the baked colours.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.0)]
    pub exposure: f32,
    /// Tone curve for the baked colours: srgb (clamp) or filmic (ACES fit); default srgb.
    #[arg(long, value_name = "srgb|filmic")]
    pub tone: Option<ToneMap>,
}

/// `translux-server relight`.
#[derive(Debug, Clone, clap::Args)]
pub struct RelightArgs {
    /// The bundle folder (written by translux-precompute).
    #[arg(long, value_name = "DIR")]
    pub bundle: PathBuf,
    /// JSON relight request (`-`: standard input); default `{}`: the bundle's lights.
    #[arg(long, value_name = "REQ.json")]
    pub request: Option<PathBuf>,
    /// The file to write: FILE.f32 (n × 3 little-endian f32, as the binary API) or FILE.json
    /// (as the JSON API).
    #[arg(long, value_name = "FILE.f32|FILE.json")]
    pub out: PathBuf,
}

/// The binary's `main`: logging from `RUST_LOG` (default `info`), then [`run`].
pub fn main() -> ExitCode {
    let args = Args::parse();
    init_tracing();
    if let Some(command) = &args.command {
        return match crate::offline::run(command) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                tracing::error!("{e:#}");
                ExitCode::FAILURE
            }
        };
    }
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
    if args.command.is_some() {
        bail!("an offline command runs with crate::offline::run, not as a server");
    }
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
        assert!(a.command.is_none());
    }

    #[test]
    fn subcommands() {
        let a = Args::try_parse_from([
            "translux-server",
            "render",
            "--bundle",
            "b/cornell",
            "--out",
            "x.png",
            "--width",
            "64",
            "--exposure",
            "-1.5",
            "--tone",
            "filmic",
        ])
        .unwrap();
        let Some(Command::Render(r)) = a.command else {
            panic!("{a:?}")
        };
        assert_eq!(r.bundle, PathBuf::from("b/cornell"));
        assert_eq!(r.out, PathBuf::from("x.png"));
        assert_eq!((r.width, r.height), (Some(64), None));
        assert_eq!(r.exposure, Some(-1.5));
        assert_eq!(r.tone, Some(ToneMap::Filmic));
        assert!(r.request.is_none());

        let a = Args::try_parse_from([
            "translux-server",
            "export",
            "--bundle",
            "b",
            "--request",
            "r.json",
            "--out",
            "m.glb",
        ])
        .unwrap();
        let Some(Command::Export(e)) = a.command else {
            panic!("{a:?}")
        };
        assert_eq!(e.request, Some(PathBuf::from("r.json")));
        assert_eq!((e.exposure, e.tone), (0.0, None));

        let a = Args::try_parse_from([
            "translux-server",
            "relight",
            "--bundle",
            "b",
            "--out",
            "c.f32",
        ])
        .unwrap();
        assert!(matches!(a.command, Some(Command::Relight(_))));

        // Missing --out, an unknown tone, server flags mixed with a subcommand: refused.
        assert!(Args::try_parse_from(["translux-server", "render", "--bundle", "b"]).is_err());
        let e = Args::try_parse_from([
            "translux-server",
            "render",
            "--bundle",
            "b",
            "--out",
            "x.png",
            "--tone",
            "aces",
        ])
        .unwrap_err()
        .to_string();
        assert!(e.contains("aces"), "{e}");
        assert!(
            Args::try_parse_from([
                "translux-server",
                "--demo",
                "render",
                "--bundle",
                "b",
                "--out",
                "x.png"
            ])
            .is_err()
        );
    }
}
