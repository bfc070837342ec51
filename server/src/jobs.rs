//! Precompute jobs: uploaded scenes turned into bundles in the background, and served
//! scenes' simulated objects walked again in a new medium.
//!
//! In: a [`JobSpec`] (a checked scene file in an upload folder, the scene id, the patch
//! density, who asked; or the new materials of a re-simulation) through [`Jobs::submit`].
//! Out: a bundle at `BUNDLES/ID`, written by [`translux_precompute::pipeline::precompute`]
//! or rewritten by [`translux_precompute::resimulate`] (to a temporary folder, renamed into
//! place: a bundle is there whole or not at all), handed to the `on_done` hook that starts
//! serving it; and a [`JobRecord`] per job that clients poll or stream.
//!
//! - **Engines** ([`Engine`]): the work runs in this process (the default), or on Slurm
//!   ([`crate::slurm`]: an upload as a job array of shards and a merge, a re-simulation as
//!   one task), a worker then only submitting it and following it to the same record.
//! - **Bounded**: `workers` jobs run at once (default 1), on their own rayon thread pool of
//!   `threads` threads, so a precompute does not starve relighting; at most `queue` jobs wait,
//!   and at most `per_owner` of them from one token; more are refused with 429 `queue_full`.
//!   Waiting jobs run owner by owner in turn (the owner with the fewest running jobs first,
//!   then the oldest job), so one person's batch of uploads does not hold up everyone else.
//! - **States**: `queued` → `running` (stage and percent) → `done` | `failed` (message) |
//!   `cancelled`. [`Jobs::cancel`] cancels a queued job at once and a running one at the
//!   next check (before each stage, between form-factor rows, every few random walks).
//!   A re-simulation's walks also stop at the submitter's work limit
//!   ([`JobSpec::work_limit`]): the job fails saying how long they would take.
//! - **Restarts and several servers**: each record is a small JSON file in the jobs folder,
//!   rewritten at every change of state, and a running job holds an exclusive lock on its
//!   `ID.lock` beside it. On start-up ([`Jobs::start`]) a job found `queued` or `running`
//!   whose lock is free (its server is gone) is marked `failed` ("the server stopped before
//!   the job finished"), its upload folder removed, and temporary bundle folders
//!   (`BUNDLES/.ID.tmp-*`) no live process here writes and unchanged for ten minutes are
//!   removed: a restart never leaves half a bundle, and a server starting beside another on
//!   a shared folder leaves that server's running jobs alone. Records another server wrote
//!   are listed and served too.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use anyhow::Context;
use axum::http::StatusCode;
use serde::{Deserialize, Serialize};
use tokio::sync::watch;
use translux_engine::stop::{Stop, StopFlag};
use translux_precompute::bundle::{Writers, settle_leftovers};
use translux_precompute::options::PrecomputeOptions;
use translux_precompute::pipeline::{
    Observer, PrecomputeError, PrecomputeParams, available_memory, precompute, resident_memory,
};
use translux_precompute::scene::load_scene_file;
use translux_proto::scene::Material;

use crate::error::AppError;

/// Where a job is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    Queued,
    Running,
    Done,
    Failed,
    Cancelled,
}

impl JobState {
    /// `done`, `failed` or `cancelled`: nothing will change any more.
    pub fn is_final(self) -> bool {
        matches!(
            self,
            JobState::Done | JobState::Failed | JobState::Cancelled
        )
    }
}

/// What a finished job produced.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct JobResult {
    pub patches: u64,
    pub vertices: u64,
    pub nnz_f: u64,
    pub bundle_bytes: u64,
    pub seconds: f64,
}

/// A job as clients see it (`GET /api/v1/jobs/{id}`) and as it is kept on disk.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct JobRecord {
    /// `j` and 20 hex digits.
    pub id: String,
    /// The scene id the bundle will be served under.
    pub scene: String,
    /// The name of the token that submitted it.
    pub owner: String,
    pub state: JobState,
    /// The stage running now (`load`, `patches`, `bvh`, `form factors`, `subsurface`,
    /// `write bundle`), the last one reached once final.
    pub stage: Option<String>,
    /// Percent of the current stage done.
    pub stage_percent: f64,
    /// Percent of the whole job done (stages weighted by their usual share of the time).
    pub percent: f64,
    /// Why it failed or was cancelled.
    pub error: Option<String>,
    /// Requested patch target or maximum edge (`None`: the scene file's own).
    pub patches: Option<u64>,
    pub max_edge: Option<f32>,
    /// Unix seconds.
    pub created: u64,
    pub started: Option<u64>,
    pub finished: Option<u64>,
    pub result: Option<JobResult>,
    /// A re-simulation: the objects walked again (`None`: an upload's precompute).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub resimulate: Option<Vec<String>>,
}

/// Settings of the job pool.
#[derive(Debug, Clone)]
pub struct JobsConfig {
    /// The bundles folder: finished bundles go to `bundles/SCENE`.
    pub bundles: PathBuf,
    /// Job records (`ID.json`).
    pub jobs_dir: PathBuf,
    /// Upload folders (`ID/`), one per job, removed when the job ends.
    pub uploads_dir: PathBuf,
    /// Jobs running at once.
    pub workers: usize,
    /// Threads of the precompute thread pool.
    pub threads: usize,
    /// Jobs that may wait.
    pub queue: usize,
    /// Jobs one token may have waiting.
    pub per_owner: usize,
    /// Bytes one job may take (`None`: 85% of the memory available when it starts): the
    /// precompute's own estimate is held to it up front, and the job is stopped when the
    /// server's resident memory grows by more while it runs.
    pub memory: Option<u64>,
    /// Where jobs run: in this process (default), or on Slurm ([`crate::slurm`]).
    pub engine: Engine,
}

/// Where a job's work runs.
#[derive(Debug, Clone, Default, PartialEq)]
pub enum Engine {
    /// In this process, on the job pool's threads.
    #[default]
    Local,
    /// On Slurm: an upload as a job array of shards and a merge, a re-simulation as one
    /// task; the workers only submit and follow them.
    Slurm(crate::slurm::SlurmConfig),
}

impl JobsConfig {
    /// The default layout: records and uploads in hidden folders of the bundles folder
    /// (`.jobs/`, `.uploads/`; the bundle loader passes over dot-folders).
    pub fn in_bundles(bundles: &Path) -> JobsConfig {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        JobsConfig {
            bundles: bundles.to_path_buf(),
            jobs_dir: bundles.join(".jobs"),
            uploads_dir: bundles.join(".uploads"),
            workers: 1,
            threads: (cores / 2).max(1),
            queue: 16,
            per_owner: 4,
            memory: None,
            engine: Engine::Local,
        }
    }
}

/// A job to run: made by the upload route after it has checked everything it can.
#[derive(Debug, Clone)]
pub struct JobSpec {
    /// From [`Jobs::new_id`]; the upload folder is `uploads_dir/ID`.
    pub id: String,
    pub scene: String,
    pub owner: String,
    /// The scene file inside the upload folder.
    pub scene_file: PathBuf,
    pub patches: Option<u64>,
    pub max_edge: Option<f32>,
    /// A re-simulation of the scene's bundle with these materials (by object name) instead
    /// of a precompute of `scene_file`.
    pub resimulate: Option<Vec<(String, Material)>>,
    /// The longest a re-simulation's walks may run (the submitter's work limit); `None`
    /// for no limit. A precompute of an upload is bounded by its patch limit instead.
    pub work_limit: Option<std::time::Duration>,
}

/// Called with `(scene id, bundle folder)` when a job's bundle is in place.
pub type OnDone = Arc<dyn Fn(&str, &Path) + Send + Sync>;

/// The job pool; cheap to clone.
#[derive(Clone)]
pub struct Jobs {
    inner: Arc<Inner>,
}

impl std::fmt::Debug for Jobs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Jobs")
            .field("config", &self.inner.config)
            .finish_non_exhaustive()
    }
}

struct Inner {
    config: JobsConfig,
    state: Mutex<Table>,
    wake: Condvar,
    on_done: OnDone,
    rayon: rayon::ThreadPool,
}

#[derive(Default)]
struct Table {
    jobs: BTreeMap<String, Arc<Entry>>,
    /// Ids of queued jobs, oldest first.
    queued: Vec<String>,
    /// Running jobs per owner.
    running: HashMap<String, usize>,
    closed: bool,
}

/// One job: its record (also published to watchers) and its cancel flag.
struct Entry {
    spec: JobSpec,
    record: Mutex<JobRecord>,
    tx: watch::Sender<JobRecord>,
    cancel: StopFlag,
    /// Last published whole percent, to publish only changes.
    last_percent: AtomicU64,
}

impl std::fmt::Debug for Entry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Entry")
            .field("id", &self.spec.id)
            .finish_non_exhaustive()
    }
}

/// Stage weights for the overall percent: (stage, share of the job's time, typical). Every
/// stage the precompute reports is listed (a test checks it against
/// `translux_precompute::pipeline::STAGES`), so no stage jumps the job to 100%.
const STAGES: [(&str, f64); 8] = [
    ("load", 0.02),
    ("patches", 0.03),
    ("bvh", 0.02),
    ("form factors", 0.62),
    ("environment", 0.06),
    ("subsurface", 0.18),
    ("inverse T", 0.02),
    ("write bundle", 0.05),
];

/// The whole job's percent when `stage` is `stage_fraction` done; `None` for a stage not
/// in [`STAGES`] (the percent then stays where it was).
fn overall_percent(stage: &str, stage_fraction: f64) -> Option<f64> {
    let mut before = 0.0;
    for (name, w) in STAGES {
        if name == stage {
            return Some(100.0 * (before + w * stage_fraction.clamp(0.0, 1.0)));
        }
        before += w;
    }
    None
}

fn now_unix() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

impl Entry {
    fn lock(&self) -> MutexGuard<'_, JobRecord> {
        self.record.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Changes the record, publishes it, and (for changes of state) writes it to disk.
    fn update(&self, jobs_dir: &Path, persist: bool, f: impl FnOnce(&mut JobRecord)) {
        let snapshot = {
            let mut r = self.lock();
            f(&mut r);
            // Published under the lock, so watchers see the records in the order they were
            // made: rows of F finish on several threads, and a record sent after a later
            // one would show the percent going back.
            self.tx.send_replace(r.clone());
            r.clone()
        };
        if persist && let Err(e) = write_record(jobs_dir, &snapshot) {
            tracing::warn!("job {}: cannot save its record: {e:#}", snapshot.id);
        }
    }
}

/// The observer handed to the precompute: progress into the record, the cancel flag out.
#[derive(Debug)]
struct JobObserver {
    entry: Arc<Entry>,
    jobs_dir: PathBuf,
    memory: MemoryWatch,
}

/// A job's memory budget, checked as it goes: the server's resident memory may grow by at
/// most `limit` bytes over `base` (what it held when the job started).
#[derive(Debug)]
struct MemoryWatch {
    limit: u64,
    base: u64,
    started: Instant,
    /// Milliseconds after `started` of the last check (checks are 50 ms apart at most).
    checked_ms: AtomicU64,
    /// The growth that broke the budget (0 while within it).
    over: AtomicU64,
}

impl MemoryWatch {
    fn new(limit: u64) -> MemoryWatch {
        MemoryWatch {
            limit,
            base: resident_memory().unwrap_or(0),
            started: Instant::now(),
            checked_ms: AtomicU64::new(0),
            over: AtomicU64::new(0),
        }
    }

    /// Whether the job has grown past its budget (reads the resident size at most every
    /// 50 ms; called from many threads).
    fn exceeded(&self) -> bool {
        let now = self.started.elapsed().as_millis() as u64;
        let last = self.checked_ms.load(Ordering::Relaxed);
        if now >= last + 50
            && self
                .checked_ms
                .compare_exchange(last, now, Ordering::Relaxed, Ordering::Relaxed)
                .is_ok()
            && let Some(rss) = resident_memory()
        {
            let grown = rss.saturating_sub(self.base);
            if grown > self.limit {
                self.over.store(grown, Ordering::Relaxed);
            }
        }
        self.over.load(Ordering::Relaxed) > 0
    }

    /// The job's error when it was stopped for its memory.
    fn message(&self) -> Option<String> {
        let grown = self.over.load(Ordering::Relaxed);
        (grown > 0).then(|| {
            format!(
                "memory: the job grew the server by {} MiB, past its budget of {} MiB \
                 (--job-memory); ask fewer patches",
                grown >> 20,
                self.limit >> 20
            )
        })
    }
}

impl Observer for JobObserver {
    /// The precompute's notes and warnings go to the server's log with the job and scene,
    /// never to the server's stderr unlabelled.
    fn note(&self, message: &str) {
        tracing::info!(job = %self.entry.spec.id, scene = %self.entry.spec.scene, "{message}");
    }

    fn progress(&self, stage: &str, done: u64, total: u64) {
        if self.memory.exceeded() {
            self.entry.cancel.set();
        }
        let fraction = if total == 0 {
            1.0
        } else {
            done as f64 / total as f64
        };
        // 100 is for a finished job only; an unknown stage leaves the percent as it was.
        let percent = overall_percent(stage, fraction).map_or(0.0, |p| p.min(99.0));
        let stage_changed = self.entry.lock().stage.as_deref() != Some(stage);
        // Publish only when the stage or the whole stage percent changes: the form-factor
        // stage reports once per row.
        let key = (fraction * 100.0).floor() as u64;
        if !stage_changed && self.entry.last_percent.swap(key, Ordering::Relaxed) == key {
            return;
        }
        if stage_changed {
            self.entry.last_percent.store(key, Ordering::Relaxed);
            tracing::info!(job = %self.entry.spec.id, scene = %self.entry.spec.scene, "stage {stage}");
        }
        self.entry.update(&self.jobs_dir, false, |r| {
            let stage_percent = (fraction * 100.0).clamp(0.0, 100.0);
            if r.stage.as_deref() == Some(stage) {
                // Rows finish on several threads: a report may arrive after a later one.
                r.stage_percent = r.stage_percent.max(stage_percent);
                r.percent = r.percent.max(percent);
            } else {
                r.stage = Some(stage.to_string());
                r.stage_percent = stage_percent;
                r.percent = r.percent.max(percent);
            }
        });
    }

    fn cancelled(&self) -> bool {
        self.entry.cancel.is_set()
    }

    fn stop(&self) -> Stop {
        Stop::never().with(&self.entry.cancel)
    }
}

impl Jobs {
    /// Creates the folders, settles what an earlier run left (see the module
    /// documentation), and starts the workers. Returns the pool and one line per job that
    /// was found unfinished.
    pub fn start(config: JobsConfig, on_done: OnDone) -> anyhow::Result<(Jobs, Vec<String>)> {
        if config.workers == 0 || config.threads == 0 || config.queue == 0 || config.per_owner == 0
        {
            anyhow::bail!(
                "the job pool needs at least one worker, thread, queue slot and slot per token"
            );
        }
        for d in [&config.jobs_dir, &config.uploads_dir] {
            std::fs::create_dir_all(d).with_context(|| format!("cannot create {}", d.display()))?;
        }
        let (records, mut notes) = recover(&config)?;
        notes.extend(crate::slurm::settle_leftovers(&config.bundles, &|job| {
            !Jobs::valid_id(job) || record_is_live(&config.jobs_dir, job)
        }));
        let rayon = rayon::ThreadPoolBuilder::new()
            .num_threads(config.threads)
            .thread_name(|k| format!("precompute-{k}"))
            .build()
            .context("cannot start the precompute thread pool")?;
        let mut table = Table::default();
        for r in records {
            let spec = JobSpec {
                id: r.id.clone(),
                scene: r.scene.clone(),
                owner: r.owner.clone(),
                scene_file: PathBuf::new(),
                patches: r.patches,
                max_edge: r.max_edge,
                resimulate: None,
                work_limit: None,
            };
            table
                .jobs
                .insert(r.id.clone(), Arc::new(Entry::new(spec, r)));
        }
        let jobs = Jobs {
            inner: Arc::new(Inner {
                config,
                state: Mutex::new(table),
                wake: Condvar::new(),
                on_done,
                rayon,
            }),
        };
        for k in 0..jobs.inner.config.workers {
            let j = jobs.clone();
            std::thread::Builder::new()
                .name(format!("job-worker-{k}"))
                .spawn(move || j.worker())
                .context("cannot start a job worker")?;
        }
        Ok((jobs, notes))
    }

    pub fn config(&self) -> &JobsConfig {
        &self.inner.config
    }

    fn table(&self) -> MutexGuard<'_, Table> {
        self.inner.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// A fresh job id: `j`, 12 hex digits of milliseconds since 1970, 8 random ones (ids
    /// sort by age; they are safe as file names).
    pub fn new_id() -> String {
        let ms = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_millis() as u64);
        let mut r = [0u8; 4];
        if getrandom::fill(&mut r).is_err() {
            static SEQ: AtomicU64 = AtomicU64::new(0);
            r = (SEQ.fetch_add(1, Ordering::Relaxed) as u32).to_le_bytes();
        }
        format!("j{ms:012x}{}", crate::auth::hex(&r))
    }

    /// Whether `id` has the shape [`Jobs::new_id`] makes.
    pub fn valid_id(id: &str) -> bool {
        id.len() == 21
            && id.starts_with('j')
            && id[1..]
                .bytes()
                .all(|b| b.is_ascii_hexdigit() && !b.is_ascii_uppercase())
    }

    /// The upload folder of job `id`.
    pub fn upload_dir(&self, id: &str) -> PathBuf {
        self.inner.config.uploads_dir.join(id)
    }

    /// Whether a queued or running job will write scene `scene`.
    pub fn busy_scene(&self, scene: &str) -> Option<String> {
        self.table()
            .jobs
            .values()
            .find(|e| e.spec.scene == scene && !e.lock().state.is_final())
            .map(|e| e.spec.id.clone())
    }

    /// Queues `spec`; 429 when the queue (or the owner's share of it) is full, 503 after
    /// shutdown began.
    pub fn submit(&self, spec: JobSpec) -> Result<JobRecord, AppError> {
        let mut t = self.table();
        if t.closed {
            return Err(AppError::shutting_down(
                "the server is shutting down and takes no new jobs",
            ));
        }
        let cfg = &self.inner.config;
        if t.queued.len() >= cfg.queue {
            return Err(AppError::queue_full(
                format!(
                    "the precompute queue is full ({} jobs waiting); retry later",
                    cfg.queue
                ),
                30,
            ));
        }
        let mine = t
            .queued
            .iter()
            .filter(|id| t.jobs.get(*id).is_some_and(|e| e.spec.owner == spec.owner))
            .count();
        if mine >= cfg.per_owner {
            return Err(AppError::queue_full(
                format!(
                    "{:?} already has {mine} jobs waiting, the most one token may queue; \
                     retry when one has started",
                    spec.owner
                ),
                30,
            ));
        }
        if let Some(other) = t
            .jobs
            .values()
            .find(|e| e.spec.scene == spec.scene && !e.lock().state.is_final())
        {
            return Err(AppError::new(
                StatusCode::CONFLICT,
                "conflict",
                format!(
                    "job {} is already making scene {:?}",
                    other.spec.id, spec.scene
                ),
            ));
        }
        let record = JobRecord {
            id: spec.id.clone(),
            scene: spec.scene.clone(),
            owner: spec.owner.clone(),
            state: JobState::Queued,
            stage: None,
            stage_percent: 0.0,
            percent: 0.0,
            error: None,
            patches: spec.patches,
            max_edge: spec.max_edge,
            created: now_unix(),
            started: None,
            finished: None,
            result: None,
            resimulate: spec
                .resimulate
                .as_ref()
                .map(|m| m.iter().map(|(name, _)| name.clone()).collect()),
        };
        write_record(&cfg.jobs_dir, &record)
            .map_err(|e| AppError::internal(format!("cannot save the job record: {e:#}")))?;
        let id = spec.id.clone();
        t.jobs
            .insert(id.clone(), Arc::new(Entry::new(spec, record.clone())));
        t.queued.push(id);
        drop(t);
        self.inner.wake.notify_one();
        tracing::info!(job = %record.id, scene = %record.scene, owner = %record.owner, "job queued");
        Ok(record)
    }

    /// The record of job `id`.
    pub fn get(&self, id: &str) -> Option<JobRecord> {
        self.table().jobs.get(id).map(|e| e.lock().clone())
    }

    /// Every job, newest first.
    pub fn list(&self) -> Vec<JobRecord> {
        let mut v: Vec<JobRecord> = self
            .table()
            .jobs
            .values()
            .map(|e| e.lock().clone())
            .collect();
        v.sort_by(|a, b| b.id.cmp(&a.id));
        v
    }

    /// A receiver that sees every published change of job `id`.
    pub fn watch(&self, id: &str) -> Option<watch::Receiver<JobRecord>> {
        self.table().jobs.get(id).map(|e| e.tx.subscribe())
    }

    /// Cancels job `id`: a queued job at once, a running one at its next check. Returns the
    /// record after the request (a final job is left as it is).
    pub fn cancel(&self, id: &str) -> Option<JobRecord> {
        let mut t = self.table();
        let entry = t.jobs.get(id)?.clone();
        entry.cancel.set();
        if let Some(k) = t.queued.iter().position(|q| q == id) {
            t.queued.remove(k);
            drop(t);
            entry.update(&self.inner.config.jobs_dir, true, |r| {
                r.state = JobState::Cancelled;
                r.error = Some("cancelled before it started".into());
                r.finished = Some(now_unix());
            });
            remove_quietly(&self.upload_dir(id));
            tracing::info!(job = %id, "job cancelled while queued");
        }
        Some(entry.lock().clone())
    }

    /// Takes no new jobs; cancels the queued ones and asks running ones to stop.
    pub fn close(&self) {
        let ids: Vec<String> = {
            let mut t = self.table();
            t.closed = true;
            t.jobs.keys().cloned().collect()
        };
        for id in ids {
            self.cancel(&id);
        }
        self.inner.wake.notify_all();
    }

    /// [`Jobs::close`], then waits up to `limit` for running jobs to stop (they check for
    /// cancellation between form-factor rows and before each stage), so a graceful stop
    /// leaves every record final (`cancelled`), never `running`. Returns whether all did.
    pub fn close_and_wait(&self, limit: std::time::Duration) -> bool {
        self.close();
        let t0 = Instant::now();
        loop {
            let busy = self
                .table()
                .jobs
                .values()
                .any(|e| !e.lock().state.is_final());
            if !busy {
                return true;
            }
            if t0.elapsed() >= limit {
                return false;
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
    }

    /// The next job to run: among queued jobs, the owner with the fewest running jobs, then
    /// the oldest.
    fn next(&self) -> Option<Arc<Entry>> {
        let mut t = self.table();
        loop {
            if t.closed {
                return None;
            }
            let pick = t
                .queued
                .iter()
                .enumerate()
                .filter_map(|(k, id)| t.jobs.get(id).map(|e| (k, e)))
                .min_by_key(|(k, e)| (t.running.get(&e.spec.owner).copied().unwrap_or(0), *k))
                .map(|(k, e)| (k, e.clone()));
            if let Some((k, e)) = pick {
                t.queued.remove(k);
                *t.running.entry(e.spec.owner.clone()).or_default() += 1;
                return Some(e);
            }
            t = self.inner.wake.wait(t).unwrap_or_else(|e| e.into_inner());
        }
    }

    fn worker(&self) {
        while let Some(entry) = self.next() {
            let owner = entry.spec.owner.clone();
            self.run(&entry);
            let mut t = self.table();
            if let Some(n) = t.running.get_mut(&owner) {
                *n = n.saturating_sub(1);
            }
        }
    }

    fn run(&self, entry: &Arc<Entry>) {
        let cfg = &self.inner.config;
        let spec = &entry.spec;
        entry.update(&cfg.jobs_dir, true, |r| {
            r.state = JobState::Running;
            r.started = Some(now_unix());
            r.stage = Some("load".into());
        });
        tracing::info!(job = %spec.id, scene = %spec.scene, "job started");
        let t = Instant::now();
        let out = cfg.bundles.join(&spec.scene);
        let memory_limit = cfg
            .memory
            .or_else(|| available_memory().map(|a| (a as f64 * 0.85) as u64));
        let observer = Arc::new(JobObserver {
            entry: entry.clone(),
            jobs_dir: cfg.jobs_dir.clone(),
            memory: MemoryWatch::new(memory_limit.unwrap_or(u64::MAX)),
        });
        let result: Result<JobResult, String> = (|| {
            if entry.cancel.is_set() {
                return Err("cancelled".to_string());
            }
            if let Engine::Slurm(slurm) = &cfg.engine {
                return self.run_on_slurm(entry, slurm);
            }
            if let Some(materials) = &spec.resimulate {
                return self.resimulate(entry, &out, materials, t);
            }
            let mut scene = load_scene_file(&spec.scene_file)
                .map_err(|e| strip_dir(&e.to_string(), &self.upload_dir(&spec.id)))?;
            // The bundle's `source` is shown to every viewer: name the upload, not the
            // server's folder it was unpacked into.
            let file = spec
                .scene_file
                .file_name()
                .map_or_else(|| "scene.json".into(), |f| f.to_string_lossy().into_owned());
            scene.source = format!("upload:{}/{file}", spec.id);
            // `translux-precompute --patches N` or `--max-edge L` at its other defaults
            // (`--subsurface auto` resolved there); no T is made for uploads.
            let options = PrecomputeOptions {
                patches: spec.patches,
                max_edge: spec.max_edge,
                ..Default::default()
            };
            let params = PrecomputeParams {
                progress: false,
                memory_limit,
                observer: Some(observer.clone()),
                ..options.params()?
            };
            let report = self
                .inner
                .rayon
                .install(|| precompute(&scene, &out, &params))
                .map_err(|e| match e {
                    PrecomputeError::Cancelled => observer
                        .memory
                        .message()
                        .unwrap_or_else(|| "cancelled".to_string()),
                    e => e.to_string(),
                })?;
            Ok(JobResult {
                patches: report.patch_count as u64,
                vertices: report.vertex_count as u64,
                nnz_f: report.nnz_f,
                bundle_bytes: report.bundle_bytes,
                seconds: t.elapsed().as_secs_f64(),
            })
        })();
        remove_quietly(&self.upload_dir(&spec.id));
        match result {
            Ok(res) => {
                (self.inner.on_done)(&spec.scene, &out);
                tracing::info!(
                    job = %spec.id,
                    scene = %spec.scene,
                    "job done in {:.1} s: {} patches, {:.1} MB",
                    res.seconds,
                    res.patches,
                    res.bundle_bytes as f64 / 1e6
                );
                entry.update(&cfg.jobs_dir, true, |r| {
                    r.state = JobState::Done;
                    r.percent = 100.0;
                    r.stage_percent = 100.0;
                    r.finished = Some(now_unix());
                    r.result = Some(res);
                });
            }
            Err(msg) => {
                let cancelled = entry.cancel.is_set() && msg == "cancelled";
                tracing::info!(job = %spec.id, scene = %spec.scene, "job ended: {msg}");
                entry.update(&cfg.jobs_dir, true, |r| {
                    r.state = if cancelled {
                        JobState::Cancelled
                    } else {
                        JobState::Failed
                    };
                    r.error = Some(msg);
                    r.finished = Some(now_unix());
                });
            }
        }
    }
}

impl Jobs {
    /// A re-simulation job's work: the walks (stage `walks`, per patch), then the bundle
    /// rewritten in place. Cancelling it, or its work limit, stops the walks within
    /// milliseconds; the bundle is then left as it was.
    fn resimulate(
        &self,
        entry: &Arc<Entry>,
        out: &Path,
        materials: &[(String, Material)],
        t: Instant,
    ) -> Result<JobResult, String> {
        let jobs_dir = &self.inner.config.jobs_dir;
        entry.update(jobs_dir, false, |r| {
            r.stage = Some("walks".into());
            r.stage_percent = 0.0;
        });
        let report = self.inner.rayon.install(|| {
            translux_precompute::resimulate::resimulate(
                out,
                materials,
                &|done, total| {
                    let fraction = done as f64 / total.max(1) as f64;
                    let key = (fraction * 100.0).floor() as u64;
                    if entry.last_percent.swap(key, Ordering::Relaxed) == key {
                        return;
                    }
                    entry.update(jobs_dir, false, |r| {
                        r.stage_percent = r.stage_percent.max(100.0 * fraction);
                        r.percent = r.percent.max(95.0 * fraction);
                    });
                },
                (&Stop::never().with(&entry.cancel), entry.spec.work_limit),
            )
        })?;
        Ok(JobResult {
            patches: report.patches,
            vertices: report.vertices,
            nnz_f: report.nnz_f,
            bundle_bytes: report.bundle_bytes,
            seconds: t.elapsed().as_secs_f64(),
        })
    }
}

impl Jobs {
    /// A job's work on Slurm ([`crate::slurm::run`]): this worker submits it and follows
    /// it until it ends; the job's cancel flag cancels it there.
    fn run_on_slurm(
        &self,
        entry: &Arc<Entry>,
        slurm: &crate::slurm::SlurmConfig,
    ) -> Result<JobResult, String> {
        let spec = &entry.spec;
        let work = match &spec.resimulate {
            Some(materials) => crate::slurm::Work::Resimulate { materials },
            None => crate::slurm::Work::Precompute {
                scene_file: &spec.scene_file,
                patches: spec.patches,
                max_edge: spec.max_edge,
            },
        };
        let follow = SlurmFollow {
            entry,
            jobs_dir: &self.inner.config.jobs_dir,
        };
        let bundles = &self.inner.config.bundles;
        crate::slurm::run(slurm, bundles, &spec.id, &spec.scene, work, &follow)
            .and_then(|elapsed| bundle_result(&bundles.join(&spec.scene), elapsed))
            .map_err(|e| strip_dir(&e, bundles))
    }
}

/// The numbers of the bundle at `out` (a job that ran elsewhere: on Slurm), read from its
/// manifest.
fn bundle_result(out: &Path, elapsed: std::time::Duration) -> Result<JobResult, String> {
    let path = out.join(translux_proto::bundle::MANIFEST_FILE);
    let text = std::fs::read_to_string(&path).map_err(|e| {
        format!(
            "the job's tasks succeeded but {} cannot be read: {e}",
            path.display()
        )
    })?;
    let m: translux_proto::bundle::Manifest =
        translux_proto::parse_json(&text).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(JobResult {
        patches: m.patch_count,
        vertices: m.vertex_count,
        nnz_f: m.form_factors.nnz,
        bundle_bytes: m.arrays.values().map(|a| a.bytes).sum::<u64>() + text.len() as u64,
        seconds: elapsed.as_secs_f64(),
    })
}

/// Whether job `job`'s record in `jobs_dir` says it is still queued or running.
fn record_is_live(jobs_dir: &Path, job: &str) -> bool {
    let Ok(text) = std::fs::read_to_string(jobs_dir.join(format!("{job}.json"))) else {
        return false;
    };
    translux_proto::parse_json::<JobRecord>(&text).is_ok_and(|r| !r.state.is_final())
}

/// A job's record and cancel flag as [`crate::slurm`] sees them.
struct SlurmFollow<'a> {
    entry: &'a Entry,
    jobs_dir: &'a Path,
}

impl crate::slurm::Follow for SlurmFollow<'_> {
    fn cancelled(&self) -> bool {
        self.entry.cancel.is_set()
    }

    fn progress(&self, stage: &str, stage_percent: f64, percent: f64) {
        tracing::info!(job = %self.entry.spec.id, scene = %self.entry.spec.scene, "stage {stage}");
        self.entry.update(self.jobs_dir, false, |r| {
            r.stage = Some(stage.to_string());
            r.stage_percent = stage_percent;
            r.percent = r.percent.max(percent);
        });
    }
}

impl Entry {
    fn new(spec: JobSpec, record: JobRecord) -> Entry {
        Entry {
            spec,
            tx: watch::channel(record.clone()).0,
            record: Mutex::new(record),
            cancel: StopFlag::new(),
            last_percent: AtomicU64::new(u64::MAX),
        }
    }
}

/// Replaces `dir/` in a message by nothing: clients see file names, not server paths.
pub fn strip_dir(message: &str, dir: &Path) -> String {
    message.replace(&format!("{}/", dir.display()), "")
}

fn remove_quietly(dir: &Path) {
    if dir.exists()
        && let Err(e) = std::fs::remove_dir_all(dir)
    {
        tracing::warn!("cannot remove {}: {e}", dir.display());
    }
}

fn record_path(jobs_dir: &Path, id: &str) -> PathBuf {
    jobs_dir.join(format!("{id}.json"))
}

/// The lock file of job `id`: held (an exclusive `flock`) by the process whose job it is
/// while the job is queued or running ([`write_record`]).
fn lock_path(jobs_dir: &Path, id: &str) -> PathBuf {
    jobs_dir.join(format!("{id}.lock"))
}

/// How long a leftover that no live job can be shown to own must stay unchanged before a
/// server starting over the folder removes it: another server's upload being received, a
/// record being renamed into place, a writer on another machine (whose pid means nothing
/// here).
const ABANDONED_AFTER: std::time::Duration = std::time::Duration::from_secs(600);

/// The job locks this process holds, by lock file. A queued or running job holds an
/// exclusive lock on `JOBS/ID.lock` from its first record until its record is final, so
/// that another server over the same folder (or this one restarted) can tell a live job
/// from one whose server is gone: it can take the lock only of the latter (the kernel, or
/// the file server, lets go of the locks of a process that dies). Kept with the records'
/// writer ([`write_record`]), which alone sees a record become final.
static HELD_LOCKS: std::sync::LazyLock<Mutex<HashMap<PathBuf, std::fs::File>>> =
    std::sync::LazyLock::new(Default::default);

/// The outcome of trying job `id`'s lock.
enum JobLock {
    /// Taken: no live process holds it (its writer is gone, or there never was one).
    Taken(std::fs::File),
    /// Another process (or this one) holds it: the job is live.
    Held,
    /// There is no lock file (and none was to be made).
    Absent,
    /// The filesystem does not lock (an NFS mount without its lock service, say).
    Unsupported(std::io::Error),
}

/// Tries job `id`'s lock without waiting; `create` makes the lock file if it is missing.
fn try_job_lock(jobs_dir: &Path, id: &str, create: bool) -> JobLock {
    let path = lock_path(jobs_dir, id);
    let file = match std::fs::OpenOptions::new()
        .create(create)
        .truncate(false)
        .write(true)
        .open(&path)
    {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return JobLock::Absent,
        Err(e) => return JobLock::Unsupported(e),
    };
    match file.try_lock() {
        Ok(()) => JobLock::Taken(file),
        Err(std::fs::TryLockError::WouldBlock) => JobLock::Held,
        Err(std::fs::TryLockError::Error(e)) => JobLock::Unsupported(e),
    }
}

/// Makes this process hold job `id`'s lock (once; later records of the job find it held).
/// A filesystem that cannot lock is logged and the job runs without one: one server over
/// the folder works as before, several cannot tell each other's jobs apart.
fn hold_job_lock(jobs_dir: &Path, id: &str) -> anyhow::Result<()> {
    let path = lock_path(jobs_dir, id);
    let mut held = HELD_LOCKS.lock().unwrap_or_else(|e| e.into_inner());
    if held.contains_key(&path) {
        return Ok(());
    }
    match try_job_lock(jobs_dir, id, true) {
        JobLock::Taken(file) => {
            held.insert(path, file);
            Ok(())
        }
        JobLock::Held => anyhow::bail!("job {id}'s lock {} is held elsewhere", path.display()),
        JobLock::Absent => anyhow::bail!("cannot create {}", path.display()),
        JobLock::Unsupported(e) => {
            tracing::warn!(
                "job {id}: cannot lock {} ({e}); servers sharing this folder cannot see that \
                 the job is live",
                path.display()
            );
            Ok(())
        }
    }
}

/// Lets go of job `id`'s lock, its record final: the lock file goes first, then the lock.
fn release_job_lock(jobs_dir: &Path, id: &str) {
    let path = lock_path(jobs_dir, id);
    let file = HELD_LOCKS
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .remove(&path);
    remove_file_quietly(&path);
    drop(file);
}

/// Writes the record next to its place and renames it there. The job's lock is taken
/// before its first record is written and let go after its final one.
fn write_record(jobs_dir: &Path, r: &JobRecord) -> anyhow::Result<()> {
    if !r.state.is_final() {
        hold_job_lock(jobs_dir, &r.id)?;
    }
    let path = record_path(jobs_dir, &r.id);
    let tmp = jobs_dir.join(format!(".{}.json.tmp", r.id));
    let text = serde_json::to_vec_pretty(r)?;
    std::fs::write(&tmp, text).with_context(|| format!("cannot write {}", tmp.display()))?;
    std::fs::rename(&tmp, &path).with_context(|| format!("cannot rename to {}", path.display()))?;
    if r.state.is_final() {
        release_job_lock(jobs_dir, &r.id);
    }
    Ok(())
}

/// The record of job `id` in `jobs_dir`, as its server last wrote it (another server's
/// job too: servers over one bundles folder share its records).
pub fn read_record(jobs_dir: &Path, id: &str) -> Option<JobRecord> {
    if !Jobs::valid_id(id) {
        return None;
    }
    let text = std::fs::read_to_string(record_path(jobs_dir, id)).ok()?;
    translux_proto::parse_json(&text).ok()
}

/// Every record in `jobs_dir` that reads, in no order.
pub fn read_records(jobs_dir: &Path) -> Vec<JobRecord> {
    let Ok(entries) = std::fs::read_dir(jobs_dir) else {
        return Vec::new();
    };
    entries
        .flatten()
        .filter_map(|e| {
            let name = e.file_name();
            let id = name.to_str()?.strip_suffix(".json")?;
            read_record(jobs_dir, id)
        })
        .collect()
}

/// Reads the records in the jobs folder and settles those an earlier run left
/// unfinished, but only where that run is gone: an unfinished record whose lock this
/// process can take is failed (or done, when its bundle was written) and its temporary
/// bundle folders removed; one whose lock is held belongs to a live server over the same
/// folder and is left to it (it is not in the returned list: [`read_record`] reads it).
/// Upload folders and bundle leftovers go only when no live job or upload can own them.
fn recover(cfg: &JobsConfig) -> anyhow::Result<(Vec<JobRecord>, Vec<String>)> {
    let mut records = Vec::new();
    let mut notes = Vec::new();
    let mut live_scenes = std::collections::BTreeSet::new();
    let entries = std::fs::read_dir(&cfg.jobs_dir)
        .with_context(|| format!("cannot read {}", cfg.jobs_dir.display()))?;
    for e in entries.flatten() {
        let path = e.path();
        let name = e.file_name().to_string_lossy().into_owned();
        if name.starts_with('.') {
            // A record being written: by a server that stopped, once it has aged.
            if unchanged_for(&path, ABANDONED_AFTER) {
                remove_file_quietly(&path);
            }
            continue;
        }
        if let Some(id) = name.strip_suffix(".lock") {
            remove_orphan_lock(&cfg.jobs_dir, id);
            continue;
        }
        let Some(id) = name.strip_suffix(".json") else {
            continue;
        };
        if !Jobs::valid_id(id) {
            continue;
        }
        let r: JobRecord = match std::fs::read_to_string(&path)
            .map_err(|e| e.to_string())
            .and_then(|t| translux_proto::parse_json(&t).map_err(|e| e.to_string()))
        {
            Ok(r) => r,
            Err(e) => {
                notes.push(format!("skipping job record {}: {e}", path.display()));
                continue;
            }
        };
        if r.state.is_final() {
            records.push(r);
            continue;
        }
        match settle_if_gone(cfg, r, &mut notes)? {
            Ok(r) => records.push(r),
            Err(scene) => {
                live_scenes.insert(scene);
            }
        }
    }
    notes.extend(remove_leftovers(&cfg.bundles, &live_scenes));
    remove_abandoned_uploads(cfg);
    Ok((records, notes))
}

/// Settles unfinished record `r` if its server is gone (its lock can be taken); `Err`
/// with its scene when a live server holds it. Re-read under the lock: its server may have
/// finished it meanwhile.
fn settle_if_gone(
    cfg: &JobsConfig,
    r: JobRecord,
    notes: &mut Vec<String>,
) -> anyhow::Result<Result<JobRecord, String>> {
    let lock = match try_job_lock(&cfg.jobs_dir, &r.id, true) {
        JobLock::Taken(file) => Some(file),
        JobLock::Held | JobLock::Absent => return Ok(Err(r.scene)),
        JobLock::Unsupported(e) => {
            notes.push(format!(
                "job {}: cannot lock its record ({e}): settled as if its server were gone; \
                 several servers over one folder need a filesystem with locks",
                r.id
            ));
            None
        }
    };
    let mut r = read_record(&cfg.jobs_dir, &r.id).unwrap_or(r);
    if !r.state.is_final() {
        notes.push(settle_unfinished(cfg, &mut r));
        write_record(&cfg.jobs_dir, &r)?;
    }
    drop(lock);
    Ok(Ok(r))
}

/// Removes job `id`'s lock file when no record goes with it and no one holds it (its
/// server stopped between taking the lock and writing the record).
fn remove_orphan_lock(jobs_dir: &Path, id: &str) {
    if !Jobs::valid_id(id) || record_path(jobs_dir, id).exists() {
        return;
    }
    if let JobLock::Taken(file) = try_job_lock(jobs_dir, id, false) {
        remove_file_quietly(&lock_path(jobs_dir, id));
        drop(file);
    }
}

/// Removes the upload folders that no live job or upload can own: a job's whose lock is
/// free (its server is gone; a final job's folder is left over), a folder not named like a
/// job, and one with no record (an upload being received, on this server or another,
/// before its job is queued) once it has not changed for [`ABANDONED_AFTER`].
fn remove_abandoned_uploads(cfg: &JobsConfig) {
    let Ok(entries) = std::fs::read_dir(&cfg.uploads_dir) else {
        return;
    };
    for e in entries.flatten() {
        let path = e.path();
        let name = e.file_name().to_string_lossy().into_owned();
        let live = if !Jobs::valid_id(&name) {
            false
        } else if record_path(&cfg.jobs_dir, &name).exists() {
            matches!(try_job_lock(&cfg.jobs_dir, &name, false), JobLock::Held)
        } else {
            !unchanged_for(&path, ABANDONED_AFTER)
        };
        if !live {
            remove_quietly(&path);
        }
    }
}

/// Whether `path`, and each entry of it if it is a folder, has not been modified for `age`.
fn unchanged_for(path: &Path, age: std::time::Duration) -> bool {
    let old = |p: &Path| {
        std::fs::symlink_metadata(p)
            .and_then(|m| m.modified())
            .ok()
            .and_then(|t| t.elapsed().ok())
            .is_some_and(|a| a >= age)
    };
    if !old(path) {
        return false;
    }
    match std::fs::read_dir(path) {
        Ok(entries) => entries.flatten().all(|e| old(&e.path())),
        Err(_) => true,
    }
}

/// Whether `path` was last renamed or otherwise changed (its status change time, which a
/// rename sets and its modification time does not) at least `age` ago.
fn renamed_before(path: &Path, age: std::time::Duration) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        let Ok(m) = std::fs::symlink_metadata(path) else {
            return false;
        };
        let now = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_secs() as i64);
        now.saturating_sub(m.ctime()) >= age.as_secs() as i64
    }
    #[cfg(not(unix))]
    {
        unchanged_for(path, age)
    }
}

/// Settles job `r` that an earlier run left queued or running (see the module docs): what
/// its bundle's writer left is settled (an old bundle set aside goes back, temporary ones
/// go), and the record follows what is served: `done` when its bundle was written in place
/// before the stop, `failed` otherwise. Returns the note for the log.
fn settle_unfinished(cfg: &JobsConfig, r: &mut JobRecord) -> String {
    let was = r.state;
    let out = cfg.bundles.join(&r.scene);
    let settled = match settle_leftovers(&out, Writers::All) {
        Ok(s) => format!(
            "{} temporary bundle folder(s) removed{}",
            s.removed.len(),
            if s.restored.is_some() {
                ", the bundle it was replacing put back"
            } else {
                ""
            }
        ),
        Err(e) => format!("its leftovers could not be settled: {e}"),
    };
    r.finished = Some(now_unix());
    if was == JobState::Running
        && let Some(result) = written_since(&out, r.started.unwrap_or(u64::MAX))
    {
        r.state = JobState::Done;
        r.percent = 100.0;
        r.stage_percent = 100.0;
        r.result = Some(result);
        return format!(
            "job {} (scene {:?}) had written its bundle before the last stop: marked done; {settled}",
            r.id, r.scene
        );
    }
    r.state = JobState::Failed;
    r.error = Some(format!(
        "the server stopped before the job finished (it was {}); {} again",
        match was {
            JobState::Queued => "queued",
            _ => "running",
        },
        if r.resimulate.is_some() {
            "ask for the re-simulation"
        } else {
            "upload the scene"
        }
    ));
    format!(
        "job {} (scene {:?}) did not finish before the last stop: marked failed; {settled}",
        r.id, r.scene
    )
}

/// The result of the bundle at `out` if its manifest was written at or after `started`
/// (unix seconds): a bundle is renamed into place whole, so one written since the job
/// started is that job's.
fn written_since(out: &Path, started: u64) -> Option<JobResult> {
    let path = out.join(translux_proto::bundle::MANIFEST_FILE);
    let written = std::fs::metadata(&path)
        .and_then(|m| m.modified())
        .ok()?
        .duration_since(UNIX_EPOCH)
        .ok()?
        .as_secs();
    if written < started {
        return None;
    }
    let text = std::fs::read_to_string(&path).ok()?;
    let m: translux_proto::bundle::Manifest = translux_proto::parse_json(&text).ok()?;
    Some(JobResult {
        patches: m.patch_count,
        vertices: m.vertex_count,
        nnz_f: m.form_factors.nnz,
        bundle_bytes: m.arrays.values().map(|a| a.bytes).sum::<u64>() + text.len() as u64,
        seconds: written.saturating_sub(started) as f64,
    })
}

/// Settles what killed writers left beside the bundles in `bundles` and removes bundles a
/// delete had renamed aside (`.ID.deleted-*`). One note per folder changed. Several
/// servers (and command-line or scheduler precomputes on other machines) may share the
/// folder, and a pid from another machine says nothing here, so a leftover goes only when
/// its writer's process does not run here *and* it has not changed for
/// [`ABANDONED_AFTER`]; the scenes of live jobs (`live`) are not touched at all.
fn remove_leftovers(bundles: &Path, live: &std::collections::BTreeSet<String>) -> Vec<String> {
    let mut notes = Vec::new();
    let Ok(entries) = std::fs::read_dir(bundles) else {
        return notes;
    };
    // Scene → whether every leftover of it has aged.
    let mut scenes: BTreeMap<String, bool> = BTreeMap::new();
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(rest) = name.strip_prefix('.') else {
            continue;
        };
        let path = e.path();
        if rest.contains(".deleted-") && path.is_dir() {
            if renamed_before(&path, ABANDONED_AFTER) {
                remove_quietly(&path);
                notes.push(format!("removed {name}, a deleted bundle"));
            }
        } else if let Some((scene, _)) = rest.rsplit_once(".tmp-") {
            let aged = unchanged_for(&path, ABANDONED_AFTER);
            *scenes.entry(scene.to_string()).or_insert(true) &= aged;
        } else if let Some((scene, _)) = rest.rsplit_once(".old-") {
            let aged = renamed_before(&path, ABANDONED_AFTER);
            *scenes.entry(scene.to_string()).or_insert(true) &= aged;
        }
    }
    for (scene, aged) in scenes {
        if !aged || live.contains(&scene) {
            continue;
        }
        match settle_leftovers(&bundles.join(&scene), Writers::Gone) {
            Ok(s) if s.restored.is_some() || !s.removed.is_empty() => notes.push(format!(
                "scene {scene:?}: {} leftover bundle folder(s) of a killed writer removed{}",
                s.removed.len(),
                if s.restored.is_some() {
                    ", the bundle it was replacing put back"
                } else {
                    ""
                }
            )),
            Ok(_) => {}
            Err(e) => notes.push(format!("scene {scene:?}: {e}")),
        }
    }
    notes
}

fn remove_file_quietly(p: &Path) {
    let _ = std::fs::remove_file(p);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The budget as it goes: growth past the limit is seen at the next check (50 ms
    /// apart) and named in the job's error; within it nothing fires.
    #[test]
    fn a_job_growing_past_its_memory_budget_is_stopped() {
        if resident_memory().is_none() {
            return; // no /proc: the budget is only the precompute's estimate
        }
        let roomy = MemoryWatch::new(u64::MAX / 2);
        let tight = MemoryWatch::new(8 << 20);
        let block = vec![1u8; 64 << 20];
        std::thread::sleep(std::time::Duration::from_millis(60));
        assert!(block.iter().step_by(4096).all(|&b| b == 1));
        assert!(!roomy.exceeded() && roomy.message().is_none());
        assert!(tight.exceeded());
        let m = tight.message().unwrap();
        assert!(m.contains("past its budget of 8 MiB"), "{m}");
        drop(block);
    }

    #[test]
    fn ids_and_percentages() {
        let a = Jobs::new_id();
        let b = Jobs::new_id();
        assert!(Jobs::valid_id(&a), "{a}");
        assert_ne!(a, b);
        for bad in [
            "",
            "j",
            "../etc",
            "jZZZZZZZZZZZZZZZZZZZZ",
            "j0000000000000000000/",
        ] {
            assert!(!Jobs::valid_id(bad), "{bad}");
        }
        assert_eq!(overall_percent("load", 0.0), Some(0.0));
        assert!((overall_percent("write bundle", 1.0).unwrap() - 100.0).abs() < 1e-9);
        let mid = overall_percent("form factors", 0.5).unwrap();
        assert!((mid - 38.0).abs() < 1e-9, "{mid}");
        assert_eq!(overall_percent("no such stage", 0.5), None);
    }

    /// The environment stage used to be missing from the weights, so it counted as 100%
    /// and `max()` kept 100 while the subsurface stage ran. Every stage the precompute
    /// reports has a weight, and the percent rises through them without reaching 100.
    #[test]
    fn job_progress_covers_every_precompute_stage_in_order() {
        let mut last = 0.0;
        for stage in translux_precompute::pipeline::STAGES {
            let start = overall_percent(stage, 0.0)
                .unwrap_or_else(|| panic!("stage {stage:?} has no weight in STAGES"));
            let end = overall_percent(stage, 1.0).unwrap();
            assert!(
                start >= last && end > start,
                "{stage}: {start}..{end} after {last}"
            );
            last = end;
        }
        assert!((last - 100.0).abs() < 1e-9, "{last}");
        let subsurface = overall_percent("subsurface", 1.0).unwrap();
        assert!(subsurface < 95.0, "{subsurface}");
    }

    /// A graceful stop must leave no job `running`: `close_and_wait` cancels the running
    /// precompute and returns once its record is final.
    #[test]
    fn a_graceful_stop_leaves_no_job_running() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = JobsConfig::in_bundles(dir.path());
        let (jobs, _) = Jobs::start(cfg.clone(), Arc::new(|_: &str, _: &Path| {})).unwrap();
        let id = Jobs::new_id();
        let upload = cfg.uploads_dir.join(&id);
        std::fs::create_dir_all(&upload).unwrap();
        let scene = upload.join("s.json");
        std::fs::write(
            &scene,
            r#"{"objects": [{"name": "ball", "mesh": {"shape": "sphere", "radius": 1},
                 "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}}]}"#,
        )
        .unwrap();
        jobs.submit(JobSpec {
            id: id.clone(),
            scene: "ball".into(),
            owner: "alice".into(),
            scene_file: scene,
            patches: Some(40_000),
            max_edge: None,
            resimulate: None,
            work_limit: None,
        })
        .unwrap();
        let t0 = Instant::now();
        while jobs.get(&id).unwrap().state != JobState::Running {
            assert!(t0.elapsed().as_secs() < 60, "the job never started");
            std::thread::sleep(std::time::Duration::from_millis(10));
        }
        assert!(jobs.close_and_wait(std::time::Duration::from_secs(60)));
        let r = jobs.get(&id).unwrap();
        assert!(r.state.is_final() && r.state != JobState::Done, "{r:?}");
        assert!(
            !dir.path().join("ball").exists(),
            "a cancelled job left a bundle"
        );
    }

    #[test]
    fn restart_fails_unfinished_jobs_and_removes_temporaries() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = JobsConfig::in_bundles(dir.path());
        std::fs::create_dir_all(&cfg.jobs_dir).unwrap();
        std::fs::create_dir_all(cfg.uploads_dir.join("jleftover")).unwrap();
        let mut r = JobRecord {
            id: Jobs::new_id(),
            scene: "cup".into(),
            owner: "alice".into(),
            state: JobState::Running,
            stage: Some("form factors".into()),
            stage_percent: 40.0,
            percent: 30.0,
            error: None,
            patches: Some(200),
            max_edge: None,
            created: 1,
            started: Some(2),
            finished: None,
            result: None,
            resimulate: None,
        };
        write_record(&cfg.jobs_dir, &r).unwrap();
        // Its server was killed: the kernel let go of the job's lock.
        release_job_lock(&cfg.jobs_dir, &r.id);
        let done_id = Jobs::new_id();
        r = JobRecord {
            id: done_id.clone(),
            state: JobState::Done,
            scene: "old".into(),
            ..r
        };
        write_record(&cfg.jobs_dir, &r).unwrap();
        let tmp = dir.path().join(".cup.tmp-1-2-3");
        std::fs::create_dir_all(&tmp).unwrap();
        std::fs::write(tmp.join("ff_val.f32"), [0u8; 8]).unwrap();
        let other = dir.path().join(".other.tmp-1-2-3");
        std::fs::create_dir_all(&other).unwrap();

        let (jobs, notes) = Jobs::start(cfg.clone(), Arc::new(|_, _| {})).unwrap();
        assert_eq!(notes.len(), 1, "{notes:?}");
        assert!(notes[0].contains("cup"), "{notes:?}");
        assert!(!tmp.exists(), "the half-written bundle is still there");
        assert!(
            other.exists(),
            "another scene's temporary folder was removed"
        );
        assert!(!cfg.uploads_dir.join("jleftover").exists());
        let list = jobs.list();
        assert_eq!(list.len(), 2);
        let failed = list.iter().find(|j| j.scene == "cup").unwrap();
        assert_eq!(failed.state, JobState::Failed);
        assert!(
            failed.error.as_deref().unwrap().contains("stopped"),
            "{failed:?}"
        );
        assert_eq!(jobs.get(&done_id).unwrap().state, JobState::Done);
        // The change is on disk too.
        let text = std::fs::read_to_string(record_path(&cfg.jobs_dir, &failed.id)).unwrap();
        assert!(text.contains("\"failed\""), "{text}");
        jobs.close();
    }

    /// Another server over the same folder holds its running job's lock: a server starting
    /// leaves the record, its upload folder and the fresh temporaries of its scene alone
    /// (a pid from another machine means nothing here), and reads the record from disk.
    #[test]
    fn a_start_leaves_a_live_servers_jobs_alone() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = JobsConfig::in_bundles(dir.path());
        std::fs::create_dir_all(&cfg.jobs_dir).unwrap();
        let id = Jobs::new_id();
        let r = JobRecord {
            id: id.clone(),
            scene: "cup".into(),
            owner: "alice".into(),
            state: JobState::Running,
            stage: Some("form factors".into()),
            stage_percent: 40.0,
            percent: 30.0,
            error: None,
            patches: Some(200),
            max_edge: None,
            created: 1,
            started: Some(2),
            finished: None,
            result: None,
            resimulate: None,
        };
        // Written as the live server writes it: holding the job's lock.
        write_record(&cfg.jobs_dir, &r).unwrap();
        let upload = cfg.uploads_dir.join(&id);
        let receiving = cfg.uploads_dir.join(Jobs::new_id());
        let tmp = dir.path().join(".cup.tmp-4294000-1-1");
        let other = dir.path().join(".mug.tmp-4294000-1-1");
        for d in [&upload, &receiving, &tmp, &other] {
            std::fs::create_dir_all(d).unwrap();
        }

        let (jobs, notes) = Jobs::start(cfg.clone(), Arc::new(|_, _| {})).unwrap();
        assert!(notes.is_empty(), "{notes:?}");
        assert!(jobs.get(&id).is_none(), "the live job is not this pool's");
        assert_eq!(read_record(&cfg.jobs_dir, &id), Some(r.clone()));
        for d in [&upload, &receiving, &tmp, &other] {
            assert!(d.exists(), "{} was removed", d.display());
        }
        jobs.close();

        // Its server gone, the next start settles it.
        release_job_lock(&cfg.jobs_dir, &id);
        let (jobs, notes) = Jobs::start(cfg.clone(), Arc::new(|_, _| {})).unwrap();
        assert_eq!(notes.len(), 1, "{notes:?}");
        assert_eq!(jobs.get(&id).unwrap().state, JobState::Failed);
        assert!(!upload.exists() && !tmp.exists());
        assert!(
            receiving.exists() && other.exists(),
            "fresh, unattributed: kept"
        );
        assert!(!lock_path(&cfg.jobs_dir, &id).exists());
        jobs.close();
    }
}
