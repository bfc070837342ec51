//! Server settings: how many workers, how long a queue, how much batching, how long a
//! request may wait, the backend, the team's limits. They come from, in order of precedence,
//! the command line, the environment (`TRANSLUX_*`, read by clap), an optional TOML file
//! (`--config FILE`), and the defaults documented on [`ServerParams`] and the flags. Every
//! setting has all three: the flag `--max-batch`, the variable `TRANSLUX_MAX_BATCH`, the key
//! `max_batch` ([`FileConfig`]).
//!
//! ```toml
//! # translux.toml — every key optional
//! bundles = "bundles"        # relative to this file's folder
//! addr = "0.0.0.0:8080"
//! demo = false
//! workers = 2                # relight threads; default: one per core
//! queue = 256                # relights waiting at most; more get 429
//! max_batch = 32             # relights of one scene computed together; 1 = no batching
//! no_batch = false           # true: the same as max_batch = 1
//! deadline_ms = 30000        # a relight that waited longer gets 503
//! viewer_work_s = 10         # lamp walks a viewer's request may run; longer gets 422
//! editor_work_s = 600        # the same for editors and admins (and without tokens)
//! backend = "auto"           # auto, gpu or cpu
//! gpu_memory_mib = 8192      # GPU memory all scenes may use; default: what the device grants
//! prepare_translucency = "load"  # load, request or off
//! # The team (docs/team.md): sizes as "8GiB" or a number of bytes.
//! tokens = "tokens.toml"     # relative to this file's folder
//! rate_limit = 50
//! rate_burst = 100
//! memory_budget = "8GiB"
//! jobs = 1                   # local (= 1), a number of local jobs at once, or "slurm"
//! slurm_shards = 2           # with jobs = "slurm": shards of an upload's precompute
//! slurm_args = "--partition=gpu"  # with jobs = "slurm": more sbatch arguments
//! job_threads = 4
//! job_queue = 16
//! job_memory = "4GiB"
//! upload_limit = "256MiB"
//! upload_file_limit = "64MiB"
//! max_upload_patches = 50000
//! rescan_s = 2               # looks at the bundles folder and tokens file; 0 = never
//! ```

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context;
use serde::Deserialize;

/// Defaults of [`ServerParams`].
pub const DEFAULT_QUEUE: usize = 256;
pub const DEFAULT_MAX_BATCH: usize = 32;
pub const DEFAULT_DEADLINE_MS: u64 = 30_000;
pub const DEFAULT_PING_S: u64 = 15;
pub const DEFAULT_WRITE_TIMEOUT_S: u64 = 30;
/// Default seconds of lamp walks one request may run: viewers (and requests without a
/// token on open routes), then editors and admins (and every request without tokens).
pub const DEFAULT_VIEWER_WORK_S: f64 = 10.0;
pub const DEFAULT_EDITOR_WORK_S: f64 = 600.0;
/// Upper bounds, so a typo cannot ask for a million threads.
pub const MAX_WORKERS: usize = 1024;
pub const MAX_QUEUE: usize = 1 << 20;
pub const MAX_BATCH: usize = 1024;

/// How the server shares its CPU between requests.
#[derive(Debug, Clone, PartialEq)]
pub struct ServerParams {
    /// Relight worker threads (default: the number of cores).
    pub workers: usize,
    /// Relights that may wait in the queue (default [`DEFAULT_QUEUE`]); one more is
    /// answered 429 with `Retry-After`.
    pub queue: usize,
    /// Most relights of one scene computed in one batch (default [`DEFAULT_MAX_BATCH`]);
    /// 1 turns batching off.
    pub max_batch: usize,
    /// How long a request may wait in the queue before it is answered 503
    /// `deadline_exceeded` instead of computed (default [`DEFAULT_DEADLINE_MS`]).
    pub deadline: Duration,
    /// How often a WebSocket stream is pinged (default [`DEFAULT_PING_S`] s).
    pub ping_interval: Duration,
    /// How long a write to a client may make no progress before the connection is closed
    /// (default [`DEFAULT_WRITE_TIMEOUT_S`] s): a client that stops reading its answer
    /// does not hold the answer in memory.
    pub write_timeout: Duration,
    /// The compute backend named in `/healthz` (`cpu`).
    pub backend: String,
    /// When a scene's first translucency change is made ready ahead of it (default
    /// [`PrepareWhen::Off`] for an embedding library; the binary's `--prepare-translucency`
    /// defaults to `load`, or `request` under a memory budget).
    pub prepare: PrepareWhen,
    /// The most time one request's lamp walks may take, for viewers and requests without
    /// a token (default [`DEFAULT_VIEWER_WORK_S`]); past it the request is stopped and
    /// answered 422 `work_limit` with the time it would need.
    pub viewer_work: Duration,
    /// The same for editors and admins, and for every request when no tokens are
    /// configured (default [`DEFAULT_EDITOR_WORK_S`]).
    pub editor_work: Duration,
}

/// When what a scene's first translucency change needs (S's radial terms) is made on a
/// background thread with half the cores
/// ([`translux_engine::scene::Scene::prepare_translucency`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PrepareWhen {
    /// As soon as the scene is loaded.
    Load,
    /// On the scene's first request (any `/api/v1/scenes/{id}…`), so scenes no one opens
    /// hold no more memory.
    Request,
    /// Never: the first translucency change makes it and waits.
    #[default]
    Off,
}

impl Default for ServerParams {
    fn default() -> Self {
        ServerParams {
            workers: default_workers(),
            queue: DEFAULT_QUEUE,
            max_batch: DEFAULT_MAX_BATCH,
            deadline: Duration::from_millis(DEFAULT_DEADLINE_MS),
            ping_interval: Duration::from_secs(DEFAULT_PING_S),
            write_timeout: Duration::from_secs(DEFAULT_WRITE_TIMEOUT_S),
            backend: "cpu".to_string(),
            prepare: PrepareWhen::Off,
            viewer_work: Duration::from_secs_f64(DEFAULT_VIEWER_WORK_S),
            editor_work: Duration::from_secs_f64(DEFAULT_EDITOR_WORK_S),
        }
    }
}

impl ServerParams {
    /// The work limit of a request by `identity`: its token's own (`work_s` in the tokens
    /// file), else its role's (no valid token on an open route: a viewer's).
    pub fn work_limit(
        &self,
        identity: &Option<axum::Extension<crate::auth::Identity>>,
    ) -> Duration {
        if let Some(axum::Extension(crate::auth::Identity {
            work: Some(work), ..
        })) = identity
        {
            return *work;
        }
        match crate::auth::role_of(identity) {
            Some(crate::auth::Role::Editor | crate::auth::Role::Admin) => self.editor_work,
            _ => self.viewer_work,
        }
    }
}

impl ServerParams {
    /// Checks the ranges; the message names the setting.
    pub fn validate(&self) -> anyhow::Result<()> {
        if !(1..=MAX_WORKERS).contains(&self.workers) {
            anyhow::bail!("workers must be in 1..={MAX_WORKERS}, got {}", self.workers);
        }
        if !(1..=MAX_QUEUE).contains(&self.queue) {
            anyhow::bail!("queue must be in 1..={MAX_QUEUE}, got {}", self.queue);
        }
        if !(1..=MAX_BATCH).contains(&self.max_batch) {
            anyhow::bail!(
                "max_batch must be in 1..={MAX_BATCH}, got {}",
                self.max_batch
            );
        }
        if self.deadline.is_zero() {
            anyhow::bail!("deadline_ms must be at least 1");
        }
        for (name, limit) in [
            ("viewer_work_s", self.viewer_work),
            ("editor_work_s", self.editor_work),
        ] {
            if limit.is_zero() {
                anyhow::bail!("{name} must be more than 0");
            }
        }
        if self.write_timeout.is_zero() {
            anyhow::bail!("the write timeout must be more than 0");
        }
        if self.ping_interval.is_zero() {
            anyhow::bail!("the ping interval must be at least 1 ms");
        }
        Ok(())
    }
}

/// One worker per core (at least one).
pub fn default_workers() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// The TOML file's keys, one per flag (`--max-batch` is `max_batch`); all optional,
/// unknown keys refused.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileConfig {
    pub bundles: Option<PathBuf>,
    pub addr: Option<String>,
    pub demo: Option<bool>,
    pub workers: Option<usize>,
    pub queue: Option<usize>,
    pub max_batch: Option<usize>,
    pub no_batch: Option<bool>,
    pub deadline_ms: Option<u64>,
    pub viewer_work_s: Option<f64>,
    pub editor_work_s: Option<f64>,
    pub backend: Option<crate::backend::BackendChoice>,
    pub gpu_memory_mib: Option<u64>,
    pub prepare_translucency: Option<PrepareWhen>,
    pub tokens: Option<PathBuf>,
    pub rate_limit: Option<f64>,
    pub rate_burst: Option<f64>,
    pub memory_budget: Option<Bytes>,
    pub jobs: Option<crate::slurm::JobsSetting>,
    pub slurm_shards: Option<u32>,
    pub slurm_args: Option<String>,
    pub job_threads: Option<usize>,
    pub job_queue: Option<usize>,
    pub job_memory: Option<Bytes>,
    pub upload_limit: Option<Bytes>,
    pub upload_file_limit: Option<Bytes>,
    pub max_upload_patches: Option<u64>,
    pub rescan_s: Option<f64>,
}

/// A size in the config file: a number of bytes, or text as the flags take it (`8GiB`,
/// [`crate::budget::parse_bytes`]).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(untagged)]
pub enum Bytes {
    Count(u64),
    Text(String),
}

impl Bytes {
    /// The bytes; an error names `key`.
    pub fn bytes(&self, key: &str) -> anyhow::Result<u64> {
        match self {
            Bytes::Count(n) => Ok(*n),
            Bytes::Text(t) => {
                crate::budget::parse_bytes(t).map_err(|e| anyhow::anyhow!("{key}: {e}"))
            }
        }
    }
}

impl FileConfig {
    /// Reads and parses `path`; a relative `bundles` is taken relative to the file's folder.
    /// Errors name the file and, for a bad key or value, the key and line.
    pub fn read(path: &Path) -> anyhow::Result<FileConfig> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read the config file {}", path.display()))?;
        let mut cfg =
            FileConfig::parse(&text).with_context(|| format!("config file {}", path.display()))?;
        let base = path.parent().unwrap_or(Path::new(""));
        for p in [&mut cfg.bundles, &mut cfg.tokens].into_iter().flatten() {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        }
        Ok(cfg)
    }

    /// Parses TOML text.
    pub fn parse(text: &str) -> anyhow::Result<FileConfig> {
        toml::from_str(text).map_err(|e| anyhow::anyhow!("{}", e.to_string().trim_end()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_keys_parse_and_unknown_keys_are_refused() {
        let c = FileConfig::parse(
            "bundles = \"b\"\naddr = \"0.0.0.0:1\"\nworkers = 3\nqueue = 9\nmax_batch = 1\n\
             deadline_ms = 500\ndemo = true\n",
        )
        .unwrap();
        assert_eq!(c.bundles, Some(PathBuf::from("b")));
        assert_eq!(c.addr.as_deref(), Some("0.0.0.0:1"));
        assert_eq!(
            (c.workers, c.queue, c.max_batch, c.deadline_ms, c.demo),
            (Some(3), Some(9), Some(1), Some(500), Some(true))
        );
        assert_eq!(FileConfig::parse("").unwrap(), FileConfig::default());
        let e = FileConfig::parse("wokers = 3").unwrap_err().to_string();
        assert!(e.contains("wokers"), "{e}");
        let e = FileConfig::parse("workers = \"many\"")
            .unwrap_err()
            .to_string();
        assert!(e.contains("workers"), "{e}");
    }

    #[test]
    fn relative_bundles_are_relative_to_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.toml");
        std::fs::write(&path, "bundles = \"bb\"").unwrap();
        let c = FileConfig::read(&path).unwrap();
        assert_eq!(c.bundles, Some(dir.path().join("bb")));
        let e = FileConfig::read(&dir.path().join("missing.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing.toml"), "{e}");
    }

    #[test]
    fn ranges_are_checked() {
        assert!(ServerParams::default().validate().is_ok());
        for (p, key) in [
            (
                ServerParams {
                    workers: 0,
                    ..Default::default()
                },
                "workers",
            ),
            (
                ServerParams {
                    queue: 0,
                    ..Default::default()
                },
                "queue",
            ),
            (
                ServerParams {
                    max_batch: 0,
                    ..Default::default()
                },
                "max_batch",
            ),
            (
                ServerParams {
                    deadline: Duration::ZERO,
                    ..Default::default()
                },
                "deadline_ms",
            ),
        ] {
            let e = p.validate().unwrap_err().to_string();
            assert!(e.contains(key), "{e}");
        }
    }
}
