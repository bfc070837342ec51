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
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::Parser;
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::load_scene;
use translux_proto::bundle::Bundle;

use crate::config::{FileConfig, PrepareWhen, ServerParams};
pub use crate::offline::{Command, ExportArgs, RelightArgs, RenderArgs};
use crate::state::{AppState, discover};

/// Where `--demo` keeps its bundles when `--bundles` is not given.
pub const DEMO_DIR: &str = "demo-bundles";
/// The demo's bundle ids and scenes, in the order they are precomputed. The viewer opens the
/// first id in sort order: the bowls, each lit by a lamp inside, glowing through their walls
/// (skim milk and milky glass-ceramic media at their measured coefficients, in a scene in
/// metres); then the Cornell box with its marble block and the flower lit from inside its cup.
/// Last, the animated `rolling` (48 frames, one bundle each): a skim-milk ball rolling past a
/// lamp.
pub const DEMO_SCENES: [(&str, &str); 4] = [
    ("bowls", "builtin:bowls"),
    ("cornell", "builtin:cornell"),
    ("flower", "builtin:flower"),
    ("rolling", "builtin:rolling"),
];
/// Patches of each demo bundle: ready in seconds on two cores.
pub const DEMO_PATCHES: u64 = 3000;
/// Patches of each frame of an animated demo scene.
pub const DEMO_FRAME_PATCHES: u64 = 1500;

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
                  translux-server --config translux.toml --workers 4\n  \
                  translux-server render --bundle demo-bundles/cornell --out cornell.png\n  \
                  translux-server export --bundle demo-bundles/cornell --request req.json --out cornell.glb\n\n\
                  Settings: flags, then TRANSLUX_* environment variables, then the --config TOML \
                  file, then the defaults. Every flag has all three: --max-batch, TRANSLUX_MAX_BATCH \
                  and the key max_batch (sizes as \"8GiB\" or a number of bytes).\n\
                  Logging: RUST_LOG (default info); RUST_LOG=debug logs every request."
)]
pub struct Args {
    /// Folder of bundles: each sub-folder is one bundle, served under its folder name.
    #[arg(
        long,
        value_name = "DIR",
        env = "TRANSLUX_BUNDLES",
        required_unless_present_any = ["demo", "config"]
    )]
    pub bundles: Option<PathBuf>,
    /// Address to listen on [default: 127.0.0.1:8080].
    #[arg(long, value_name = "HOST:PORT", env = "TRANSLUX_ADDR")]
    pub addr: Option<String>,
    /// Precompute the built-in bowls, Cornell box and flower into DIR/bowls, DIR/cornell and
    /// DIR/flower (DIR: --bundles, else ./demo-bundles) unless valid bundles are already
    /// there, then serve DIR.
    #[arg(long, env = "TRANSLUX_DEMO")]
    pub demo: bool,
    /// A TOML file with any of the other settings, each under its flag's name with `_` for
    /// `-` (bundles, addr, max_batch, memory_budget, …; `crate::config`).
    #[arg(long, value_name = "FILE", env = "TRANSLUX_CONFIG")]
    pub config: Option<PathBuf>,
    /// Relight worker threads [default: one per core].
    #[arg(long, value_name = "N", env = "TRANSLUX_WORKERS")]
    pub workers: Option<usize>,
    /// Relights that may wait; one more is answered 429 [default: 256].
    #[arg(long, value_name = "N", env = "TRANSLUX_QUEUE")]
    pub queue: Option<usize>,
    /// Most relights of one scene computed together [default: 32].
    #[arg(long, value_name = "N", env = "TRANSLUX_MAX_BATCH")]
    pub max_batch: Option<usize>,
    /// Compute every relight on its own (the same as --max-batch 1).
    #[arg(long, env = "TRANSLUX_NO_BATCH", conflicts_with = "max_batch")]
    pub no_batch: bool,
    /// How long a relight may wait in the queue before it is answered 503 [default: 30000].
    #[arg(long, value_name = "MS", env = "TRANSLUX_DEADLINE_MS")]
    pub deadline_ms: Option<u64>,
    /// Seconds of lamp walks one viewer's request (or one without a token) may run before
    /// it is stopped and answered 422 [default: 10].
    #[arg(long, value_name = "S", env = "TRANSLUX_VIEWER_WORK_S")]
    pub viewer_work_s: Option<f64>,
    /// The same for editors and admins, and for every request without tokens [default: 600].
    #[arg(long, value_name = "S", env = "TRANSLUX_EDITOR_WORK_S")]
    pub editor_work_s: Option<f64>,
    /// Compute backend: auto (a hardware GPU if wgpu finds one, else the CPU), gpu (any
    /// adapter, a software one too; none is a start-up error) or cpu [default: auto].
    #[arg(long, value_enum, env = "TRANSLUX_BACKEND")]
    pub backend: Option<crate::backend::BackendChoice>,
    /// GPU memory all scenes may use, in MiB; a scene that would go past it is served from
    /// the CPU [default: what the device grants].
    #[arg(long, value_name = "MIB", env = "TRANSLUX_GPU_MEMORY_MIB")]
    pub gpu_memory_mib: Option<u64>,
    /// Make what a scene's first translucency change needs (S's radial terms: seconds to
    /// minutes on large translucent objects) on a background thread with half the cores:
    /// when the scene is loaded, on its first request, or never [default: load; request
    /// with --memory-budget].
    #[arg(
        long,
        value_enum,
        value_name = "WHEN",
        env = "TRANSLUX_PREPARE_TRANSLUCENCY"
    )]
    pub prepare_translucency: Option<crate::config::PrepareWhen>,
    /// Access control, uploads and jobs, the memory budget ([`crate::team`]).
    #[command(flatten)]
    pub team: crate::team::TeamArgs,
    /// An offline command instead of the server.
    #[command(subcommand)]
    pub command: Option<Command>,
}

/// The server's settings after flags, environment, config file and defaults.
#[derive(Debug, Clone)]
pub struct Settings {
    pub bundles: PathBuf,
    pub addr: String,
    pub demo: bool,
    pub params: ServerParams,
    pub backend: crate::backend::BackendChoice,
    /// `--gpu-memory-mib`.
    pub gpu_memory_mib: Option<u64>,
    /// The team's settings, the config file's keys filled in where no flag gave them.
    pub team: crate::team::TeamArgs,
}

/// A setting in seconds, `default` when not given; a negative, zero or non-finite number,
/// or one over a year, is an error naming it.
fn seconds(name: &str, given: Option<f64>, default: Duration) -> anyhow::Result<Duration> {
    match given {
        None => Ok(default),
        Some(s) if s.is_finite() && s > 0.0 && s <= 365.0 * 86_400.0 => {
            Ok(Duration::from_secs_f64(s))
        }
        Some(s) => bail!("{name} must be a number of seconds above 0 (at most a year), got {s}"),
    }
}

/// `rescan_s` checked: a number of seconds from 0 (off) to a day.
fn rescan_seconds(given: Option<f64>) -> anyhow::Result<Option<f64>> {
    match given {
        Some(s) if !(s.is_finite() && (0.0..=86_400.0).contains(&s)) => {
            bail!("rescan_s must be a number of seconds from 0 (off) to 86400, got {s}")
        }
        _ => Ok(given),
    }
}

/// The address when nothing sets one.
pub const DEFAULT_ADDR: &str = "127.0.0.1:8080";

impl Args {
    /// Merges the flags (and environment) over the config file over the defaults.
    pub fn settings(&self) -> anyhow::Result<Settings> {
        let file = match &self.config {
            Some(path) => FileConfig::read(path)?,
            None => FileConfig::default(),
        };
        let demo = self.demo || file.demo.unwrap_or(false);
        let bundles = match (self.bundles.clone().or(file.bundles), demo) {
            (Some(dir), _) => dir,
            (None, true) => PathBuf::from(DEMO_DIR),
            (None, false) => bail!(
                "no bundles folder: give --bundles DIR, TRANSLUX_BUNDLES, `bundles` in the \
                 config file, or --demo"
            ),
        };
        let defaults = ServerParams::default();
        let file_no_batch = file.no_batch.unwrap_or(false);
        if file_no_batch && file.max_batch.is_some() {
            bail!("no_batch and max_batch exclude each other");
        }
        let max_batch = if self.no_batch || (self.max_batch.is_none() && file_no_batch) {
            1
        } else {
            self.max_batch
                .or(file.max_batch)
                .unwrap_or(defaults.max_batch)
        };
        let t = &self.team;
        let size = |flag: Option<u64>, key: &str, given: &Option<crate::config::Bytes>| match (
            flag, given,
        ) {
            (Some(b), _) => Ok(Some(b)),
            (None, Some(b)) => b.bytes(key).map(Some),
            (None, None) => Ok(None),
        };
        // Every field named: a new team flag does not compile here without its config key.
        let team = crate::team::TeamArgs {
            tokens: t.tokens.clone().or(file.tokens),
            rate_limit: t.rate_limit.or(file.rate_limit),
            rate_burst: t.rate_burst.or(file.rate_burst),
            memory_budget: size(t.memory_budget, "memory_budget", &file.memory_budget)?,
            jobs: t.jobs.or(file.jobs),
            slurm_shards: t.slurm_shards.or(file.slurm_shards),
            slurm_args: t.slurm_args.clone().or(file.slurm_args),
            job_threads: t.job_threads.or(file.job_threads),
            job_queue: t.job_queue.or(file.job_queue),
            job_memory: size(t.job_memory, "job_memory", &file.job_memory)?,
            upload_limit: size(t.upload_limit, "upload_limit", &file.upload_limit)?,
            upload_file_limit: size(
                t.upload_file_limit,
                "upload_file_limit",
                &file.upload_file_limit,
            )?,
            max_upload_patches: t.max_upload_patches.or(file.max_upload_patches),
            rescan_s: rescan_seconds(t.rescan_s.or(file.rescan_s))?,
        };
        let params = ServerParams {
            workers: self.workers.or(file.workers).unwrap_or(defaults.workers),
            queue: self.queue.or(file.queue).unwrap_or(defaults.queue),
            max_batch,
            deadline: self
                .deadline_ms
                .or(file.deadline_ms)
                .map_or(defaults.deadline, Duration::from_millis),
            viewer_work: seconds(
                "viewer_work_s",
                self.viewer_work_s.or(file.viewer_work_s),
                defaults.viewer_work,
            )?,
            editor_work: seconds(
                "editor_work_s",
                self.editor_work_s.or(file.editor_work_s),
                defaults.editor_work,
            )?,
            prepare: self
                .prepare_translucency
                .or(file.prepare_translucency)
                .unwrap_or(if team.memory_budget.is_some() {
                    PrepareWhen::Request
                } else {
                    PrepareWhen::Load
                }),
            ..defaults
        };
        params.validate()?;
        Ok(Settings {
            bundles,
            addr: self
                .addr
                .clone()
                .or(file.addr)
                .unwrap_or_else(|| DEFAULT_ADDR.to_string()),
            demo,
            params,
            backend: self.backend.or(file.backend).unwrap_or_default(),
            gpu_memory_mib: self.gpu_memory_mib.or(file.gpu_memory_mib),
            team,
        })
    }
}

/// The binary's `main`: logging from `RUST_LOG` (default `info`), then [`run`].
pub fn main() -> ExitCode {
    let args = Args::parse();
    init_tracing();
    if let Some(Command::Token(t)) = &args.command {
        return match crate::auth::token_command(t, &mut std::io::stdout()) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                tracing::error!("{e:#}");
                ExitCode::FAILURE
            }
        };
    }
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
    let shutdown = {
        let _inside = runtime.enter();
        shutdown_signal()
    };
    match runtime.block_on(run(args, shutdown)) {
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

/// Listens on the configured address at once and serves until `shutdown` completes; the
/// bundles load in the background meanwhile (each scene answers 503 until it is ready), the
/// demo bundle first precomputed if asked and missing.
pub async fn run(
    args: Args,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    if args.command.is_some() {
        bail!("an offline command runs with crate::offline::run, not as a server");
    }
    let settings = args.settings()?;
    let dir = settings.bundles.clone();
    if settings.demo {
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create the demo folder {}", dir.display()))?;
    }
    if !dir.is_dir() {
        bail!("--bundles {}: no such folder", dir.display());
    }
    // The backend, once for the process; `gpu` without an adapter stops here.
    let backend = crate::backend::Backend::start(settings.backend, settings.gpu_memory_mib)
        .map_err(|e| anyhow::anyhow!("--backend gpu: {e}"))?;
    tracing::info!("{}", backend.describe());
    let mut params = settings.params.clone();
    params.backend = backend.name().to_string();
    let state = AppState::with_backend(params, backend);
    // The team first: it settles what a killed job left (a bundle set aside goes back)
    // before the folder is read.
    let team = crate::team::Team::start(&settings.team, &dir, state.clone())?;
    let (mut bundles, errors) =
        discover(&dir).map_err(|e| anyhow::anyhow!("--bundles {}: {e}", dir.display()))?;
    for (id, error) in errors {
        tracing::warn!("skipping {id:?} in {}: {error}", dir.display());
        state.set_failed(id, crate::jobs::strip_dir(&error, &dir));
    }
    if settings.demo {
        for (id, _) in DEMO_SCENES {
            if !bundles.iter().any(|(b, _)| b == id) {
                bundles.push((id.to_string(), dir.join(id)));
            }
        }
    }
    if bundles.is_empty() {
        tracing::warn!("no bundle under {}; serving no scenes", dir.display());
    }
    let demo_dir = settings.demo.then(|| dir.clone());
    state.load_in_background(bundles, move |state| {
        let Some(dir) = demo_dir else {
            return;
        };
        // Each demo scene is served as soon as it is ready, the first while the others are
        // still being precomputed.
        for (id, scene) in DEMO_SCENES {
            match ensure_demo_bundle(&dir, id, scene) {
                Ok(()) => state.load_one(id, &dir.join(id)),
                Err(e) => {
                    tracing::error!("{e:#}");
                    state.set_failed(id, crate::jobs::strip_dir(&format!("{e:#}"), &dir));
                }
            }
        }
    });

    let listener = tokio::net::TcpListener::bind(&settings.addr)
        .await
        .with_context(|| format!("cannot listen on {}", settings.addr))?;
    let local = listener
        .local_addr()
        .context("cannot read the listening address")?;
    crate::auth::check_bind(&local, &team.auth)?;
    tracing::info!("{}", team.describe());
    let p = &settings.params;
    tracing::info!(
        "listening on http://{local}/ (Ctrl-C to stop); {} workers, queue {}, max batch {}, \
         deadline {} ms, lamp walks at most {} s a viewer's request, {} s an editor's",
        p.workers,
        p.queue,
        p.max_batch,
        p.deadline.as_millis(),
        p.viewer_work.as_secs_f64(),
        p.editor_work.as_secs_f64()
    );
    watch_folder(&team, settings.team.rescan_s)?;
    let jobs = team.jobs.clone();
    let app = crate::team::app(state.clone(), team);
    crate::serve_router(listener, state, app, shutdown)
        .await
        .context("the server failed")?;
    let settled = tokio::task::spawn_blocking(move || {
        jobs.close_and_wait(std::time::Duration::from_secs(30))
    })
    .await
    .unwrap_or(false);
    if !settled {
        tracing::warn!(
            "a precompute job did not stop within 30 s; it is marked failed on the next start"
        );
    }
    tracing::info!("stopped");
    Ok(())
}

/// Starts the rescan of the bundles folder and tokens file (`--rescan-s`, unless 0).
fn watch_folder(team: &crate::team::Team, rescan_s: Option<f64>) -> anyhow::Result<()> {
    let every = rescan_s.unwrap_or(crate::team::DEFAULT_RESCAN_S);
    if every > 0.0 {
        team.watch_folder(Duration::from_secs_f64(every))
            .context("cannot start the bundles folder rescan")?;
        tracing::info!(
            "looking for new, replaced and removed bundles (and tokens file changes) every \
             {every} s"
        );
    }
    Ok(())
}

/// Makes sure `dir/id` holds a valid bundle, precomputing `scene` (one of
/// [`DEMO_SCENES`]) at [`DEMO_PATCHES`] patches if not.
pub fn ensure_demo_bundle(dir: &Path, id: &str, scene: &str) -> anyhow::Result<()> {
    let out = dir.join(id);
    let source = translux_precompute::scene::read_scene(scene)
        .with_context(|| format!("cannot load {scene}"))?;
    if source.file.animation.is_some() {
        return ensure_demo_sequence(&out, &source);
    }
    let why = match Bundle::open(&out) {
        Ok(b) => match demo_bundle_outdated(&b, &source.file) {
            None => {
                tracing::info!(
                    "demo bundle {} is ready ({} patches)",
                    out.display(),
                    b.manifest().patch_count
                );
                return Ok(());
            }
            Some(why) => why,
        },
        Err(e) => e.to_string(),
    };
    tracing::info!(
        "no valid demo bundle in {} ({why}); precomputing {scene} at {DEMO_PATCHES} patches",
        out.display()
    );
    let t = Instant::now();
    let loaded = load_scene(scene).with_context(|| format!("cannot load {scene}"))?;
    let params = PrecomputeParams {
        patches: Some(DEMO_PATCHES),
        progress: true,
        ..Default::default()
    };
    let report = precompute(&loaded, &out, &params)
        .with_context(|| format!("cannot precompute {scene} into {}", out.display()))?;
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

/// Why a demo bundle no longer shows `file` (a built-in scene whose lights or materials
/// changed since the bundle was written, by an older translux), or `None` if it does.
fn demo_bundle_outdated(b: &Bundle, file: &translux_proto::scene::SceneFile) -> Option<String> {
    let m = b.manifest();
    if m.lights != file.lights {
        return Some("it was built with other lights than the scene has now".into());
    }
    let same = m.objects.len() == file.objects.len()
        && m.objects
            .iter()
            .zip(&file.objects)
            .all(|(a, b)| a.name == b.name && a.material == b.material);
    (!same).then(|| "it was built with other objects or materials than the scene has now".into())
}

/// An animated demo scene: its frames precomputed into `out` unless they are there already
/// (the sequence precompute keeps every frame whose inputs did not change, so a complete
/// sequence costs one pass over the meshes and an interrupted one resumes).
fn ensure_demo_sequence(
    out: &Path,
    source: &translux_precompute::scene::SceneSource,
) -> anyhow::Result<()> {
    let t = Instant::now();
    let params = PrecomputeParams {
        patches: Some(DEMO_FRAME_PATCHES),
        ..Default::default()
    };
    let report =
        translux_precompute::sequence::precompute_sequence(source, out, &params, &|f, n| {
            if !matches!(
                f.outcome,
                translux_precompute::sequence::FrameOutcome::Resumed
            ) {
                tracing::info!(
                    "demo {}: frame {} of {n} ready in {:.2} s",
                    source.source,
                    f.frame + 1,
                    f.seconds
                );
            }
        })
        .with_context(|| format!("cannot precompute {} into {}", source.source, out.display()))?;
    tracing::info!(
        "demo sequence {} ready in {:.1} s: {} frames ({} precomputed now, {} kept), {:.1} MB",
        out.display(),
        t.elapsed().as_secs_f64(),
        report.frames.len(),
        report.computed(),
        report.resumed(),
        report.bytes as f64 / 1e6
    );
    Ok(())
}

/// Installs the Ctrl-C and (on Unix) SIGTERM handlers now and returns a future that
/// completes on either. Installing them before the server starts matters: a handler
/// installed on the future's first poll left a window after start-up in which SIGTERM
/// still had its default action and killed the process uncleanly. Call it inside the
/// runtime (it registers with the runtime's signal driver).
pub fn shutdown_signal() -> impl Future<Output = ()> + Send + 'static {
    #[cfg(unix)]
    let (interrupt, terminate) = {
        use tokio::signal::unix::{SignalKind, signal};
        let listen = |kind: SignalKind, name: &str| match signal(kind) {
            Ok(s) => Some(s),
            Err(e) => {
                tracing::warn!("cannot listen for {name}: {e}");
                None
            }
        };
        (
            listen(SignalKind::interrupt(), "Ctrl-C"),
            listen(SignalKind::terminate(), "SIGTERM"),
        )
    };
    async move {
        #[cfg(unix)]
        {
            let wait = |s: Option<tokio::signal::unix::Signal>| async move {
                match s {
                    Some(mut s) => {
                        s.recv().await;
                    }
                    None => std::future::pending::<()>().await,
                }
            };
            tokio::select! {
                _ = wait(interrupt) => {},
                _ = wait(terminate) => {},
            }
        }
        #[cfg(not(unix))]
        if let Err(e) = tokio::signal::ctrl_c().await {
            tracing::warn!("cannot listen for Ctrl-C: {e}");
            std::future::pending::<()>().await;
        }
        tracing::info!("shutting down: finishing the requests accepted, then stopping");
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use translux_proto::api::{Exposure, ToneMap};

    #[test]
    fn arguments() {
        let a = Args::try_parse_from(["translux-server", "--demo"]).unwrap();
        assert!(a.demo && a.bundles.is_none());
        if std::env::vars().all(|(k, _)| !k.starts_with("TRANSLUX_")) {
            let s = a.settings().unwrap();
            assert_eq!(s.addr, "127.0.0.1:8080");
            assert_eq!(s.bundles, PathBuf::from(DEMO_DIR));
            // The binary prepares translucency changes when a scene loads; under a memory
            // budget on its first request; as told.
            let load = ServerParams {
                prepare: PrepareWhen::Load,
                ..ServerParams::default()
            };
            assert_eq!(s.params, load);
            let budget = ["translux-server", "--demo", "--memory-budget", "1GiB"];
            let b = Args::try_parse_from(budget).unwrap().settings().unwrap();
            assert_eq!(b.params.prepare, PrepareWhen::Request);
            let off = [&budget[..], &["--prepare-translucency", "off"]].concat();
            let o = Args::try_parse_from(off).unwrap().settings().unwrap();
            assert_eq!(o.params.prepare, PrepareWhen::Off);
        }
        let a = Args::try_parse_from([
            "translux-server",
            "--bundles",
            "b",
            "--addr",
            "0.0.0.0:9000",
        ])
        .unwrap();
        assert_eq!(a.bundles, Some(PathBuf::from("b")));
        assert_eq!(a.addr.as_deref(), Some("0.0.0.0:9000"));
        assert!(Args::try_parse_from(["translux-server", "--demo", "--bundles", "x"]).is_ok());
        // Without --bundles or --demo (and no TRANSLUX_BUNDLES in the environment): refused.
        if std::env::var_os("TRANSLUX_BUNDLES").is_none() {
            assert!(Args::try_parse_from(["translux-server"]).is_err());
        }
        assert!(a.command.is_none());
    }

    #[test]
    fn flags_override_the_config_file_which_overrides_the_defaults() {
        if std::env::vars().any(|(k, _)| k.starts_with("TRANSLUX_")) {
            return; // the environment would take part
        }
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("t.toml");
        std::fs::write(
            &file,
            "bundles = \"bb\"\naddr = \"0.0.0.0:1\"\nworkers = 3\nqueue = 5\nmax_batch = 4\n\
             deadline_ms = 700\nviewer_work_s = 2.5\n",
        )
        .unwrap();
        let cfg = file.to_str().unwrap();
        let s = Args::try_parse_from(["translux-server", "--config", cfg])
            .unwrap()
            .settings()
            .unwrap();
        assert_eq!(s.params.viewer_work, Duration::from_millis(2500));
        assert_eq!(s.params.editor_work, Duration::from_secs(600));
        let s2 = Args::try_parse_from(["translux-server", "--config", cfg, "--viewer-work-s", "1"])
            .unwrap()
            .settings()
            .unwrap();
        assert_eq!(s2.params.viewer_work, Duration::from_secs(1));
        let bad =
            Args::try_parse_from(["translux-server", "--config", cfg, "--editor-work-s", "0"])
                .unwrap()
                .settings()
                .unwrap_err();
        assert!(bad.to_string().contains("editor_work_s"), "{bad}");
        assert_eq!(s.bundles, dir.path().join("bb"));
        assert_eq!(s.addr, "0.0.0.0:1");
        assert_eq!(
            (s.params.workers, s.params.queue, s.params.max_batch),
            (3, 5, 4)
        );
        assert_eq!(s.params.deadline, Duration::from_millis(700));
        let s = Args::try_parse_from([
            "translux-server",
            "--config",
            cfg,
            "--workers",
            "1",
            "--no-batch",
            "--addr",
            "127.0.0.1:0",
            "--bundles",
            "other",
        ])
        .unwrap()
        .settings()
        .unwrap();
        assert_eq!(
            (s.params.workers, s.params.queue, s.params.max_batch),
            (1, 5, 1)
        );
        assert_eq!(
            (s.addr.as_str(), s.bundles),
            ("127.0.0.1:0", PathBuf::from("other"))
        );
        // Bad values name the setting; --no-batch and --max-batch conflict.
        let e = Args::try_parse_from(["translux-server", "--bundles", "b", "--workers", "0"])
            .unwrap()
            .settings()
            .unwrap_err()
            .to_string();
        assert!(e.contains("workers"), "{e}");
        assert!(
            Args::try_parse_from([
                "translux-server",
                "--demo",
                "--no-batch",
                "--max-batch",
                "2"
            ])
            .is_err()
        );
        std::fs::write(&file, "queue = -1").unwrap();
        let e = Args::try_parse_from(["translux-server", "--config", cfg])
            .unwrap()
            .settings()
            .unwrap_err();
        let e = format!("{e:#}");
        assert!(e.contains("t.toml") && e.contains("queue"), "{e}");
    }

    /// The backend's, the GPU budget's, the preparation's and the team's settings have
    /// config keys too, under their flags' names; a flag still wins over its key.
    #[test]
    fn every_setting_has_a_config_key() {
        if std::env::vars().any(|(k, _)| k.starts_with("TRANSLUX_")) {
            return; // the environment would take part
        }
        use crate::backend::BackendChoice;
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("t.toml");
        std::fs::write(
            &file,
            "demo = true\nno_batch = true\nbackend = \"cpu\"\ngpu_memory_mib = 512\n\
             prepare_translucency = \"off\"\ntokens = \"tok.toml\"\nrate_limit = 5\n\
             rate_burst = 7\nmemory_budget = \"1GiB\"\njobs = 2\njob_threads = 3\n\
             job_queue = 4\njob_memory = 1000\nupload_limit = \"2MiB\"\n\
             upload_file_limit = \"1MiB\"\nmax_upload_patches = 900\nslurm_shards = 3\n\
             slurm_args = \"--partition=p\"\n",
        )
        .unwrap();
        let cfg = file.to_str().unwrap();
        let s = Args::try_parse_from(["translux-server", "--config", cfg])
            .unwrap()
            .settings()
            .unwrap();
        assert!(s.demo);
        assert_eq!(s.params.max_batch, 1);
        assert_eq!(
            (s.backend, s.gpu_memory_mib),
            (BackendChoice::Cpu, Some(512))
        );
        assert_eq!(s.params.prepare, PrepareWhen::Off);
        let t = &s.team;
        assert_eq!(t.tokens, Some(dir.path().join("tok.toml")));
        assert_eq!((t.rate_limit, t.rate_burst), (Some(5.0), Some(7.0)));
        assert_eq!(t.memory_budget, Some(1 << 30));
        assert_eq!(
            (t.jobs, t.job_threads, t.job_queue),
            (Some(crate::slurm::JobsSetting::Local(2)), Some(3), Some(4))
        );
        assert_eq!(t.job_memory, Some(1000));
        assert_eq!(
            (t.upload_limit, t.upload_file_limit),
            (Some(2 << 20), Some(1 << 20))
        );
        assert_eq!(t.max_upload_patches, Some(900));
        assert_eq!(
            (t.slurm_shards, t.slurm_args.as_deref()),
            (Some(3), Some("--partition=p"))
        );
        let s = Args::try_parse_from([
            "translux-server",
            "--config",
            cfg,
            "--backend",
            "auto",
            "--gpu-memory-mib",
            "64",
            "--max-batch",
            "3",
            "--memory-budget",
            "2GiB",
        ])
        .unwrap()
        .settings()
        .unwrap();
        assert_eq!(
            (s.backend, s.gpu_memory_mib),
            (BackendChoice::Auto, Some(64))
        );
        assert_eq!(s.params.max_batch, 3);
        assert_eq!(s.team.memory_budget, Some(2 << 30));
        std::fs::write(&file, "memory_budget = \"lots\"").unwrap();
        let e = Args::try_parse_from(["translux-server", "--config", cfg, "--demo"])
            .unwrap()
            .settings()
            .unwrap_err()
            .to_string();
        assert!(e.contains("memory_budget"), "{e}");
    }

    /// `--rescan-s` has its variable and key like every setting; 0 is off, a negative or
    /// non-finite number is refused naming it.
    #[test]
    fn rescan_s_has_a_flag_and_a_config_key() {
        if std::env::vars().any(|(k, _)| k.starts_with("TRANSLUX_")) {
            return; // the environment would take part
        }
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("t.toml");
        std::fs::write(&file, "bundles = \".\"\nrescan_s = 0\n").unwrap();
        let cfg = file.to_str().unwrap();
        let parse = |extra: &[&str]| {
            Args::try_parse_from([&["translux-server", "--config", cfg], extra].concat())
                .unwrap()
                .settings()
        };
        assert_eq!(parse(&[]).unwrap().team.rescan_s, Some(0.0));
        assert_eq!(
            parse(&["--rescan-s", "0.5"]).unwrap().team.rescan_s,
            Some(0.5)
        );
        for bad in ["--rescan-s=-1", "--rescan-s=inf", "--rescan-s=NaN"] {
            let e = parse(&[bad]).unwrap_err().to_string();
            assert!(e.contains("rescan_s"), "{bad}: {e}");
        }
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
        assert_eq!(r.exposure, Some(Exposure::Ev(-1.5)));
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
        assert_eq!((e.exposure, e.tone), (None, None));
        let a = Args::try_parse_from([
            "translux-server",
            "export",
            "--bundle",
            "b",
            "--out",
            "m.glb",
            "--exposure",
            "auto",
        ])
        .unwrap();
        let Some(Command::Export(e)) = a.command else {
            panic!("{a:?}")
        };
        assert_eq!(e.exposure, Some(Exposure::Auto));
        let e = Args::try_parse_from([
            "translux-server",
            "render",
            "--bundle",
            "b",
            "--out",
            "x.png",
            "--exposure",
            "bright",
        ])
        .unwrap_err()
        .to_string();
        assert!(e.contains("bright") && e.contains("auto"), "{e}");

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
