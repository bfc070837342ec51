//! Slurm as the job engine (`translux-server --jobs slurm`): an upload's precompute runs as
//! a job array of K shards and a merge that waits for all of them
//! (`--dependency=afterok`), a re-simulation as one task; the server submits them with
//! `sbatch`, follows them, cancels them with `scancel`, and records how they ended.
//!
//! In: a job of [`crate::jobs`] — its id, its scene id and its [`Work`] (the uploaded scene
//! file and patch density, or a re-simulation's materials) — the bundles folder, and a
//! [`SlurmConfig`] (K, extra `sbatch` arguments, the `translux-precompute` binary). Out: the
//! bundle at `BUNDLES/SCENE` and the job's wall time, or an error naming the task that
//! failed with the tail of its log; progress (shards done of K) and cancellation go through
//! [`Follow`]. This module knows nothing of job records: `crate::jobs` calls it.
//!
//! Each job works in `BUNDLES/.slurm-JOB/` (hidden: the bundle loader passes over it):
//! `precompute.sbatch` (`docker/slurm/precompute.sbatch`, built into the server), `SCENE/`
//! and `SCENE.parts/` (the merge's bundle and the shards' parts), `logs/` (one file per
//! task), `outcome/` (each task's exit code: `shard-I.exit`, `merge.exit`,
//! `resimulate.exit`) and `slurm.json` (the Slurm job ids). The merge task renames `SCENE/`
//! to `BUNDLES/SCENE` (same filesystem: atomic), so nothing half-made is ever under a
//! bundle's name, even if the server is down when it ends. The folder is removed when the
//! job ends; [`settle_leftovers`] removes those of jobs a killed server left.
//!
//! Following: `sacct` needs accounting storage, which a small cluster may not have, so the
//! server reads the outcome files the tasks write and asks `squeue -t all` for the tasks'
//! states (a task killed before it could write its outcome shows `FAILED`, `NODE_FAIL`,
//! `TIMEOUT` ... there). A shard killed by a signal is run again inside its task (the
//! script's `TRANSLUX_SHARD_TRIES`); a task whose node fails is requeued by Slurm
//! (`--requeue`). A shard that fails for good fails the job: the merge is cancelled.
//!
//! Needs: `sbatch`, `squeue`, `scancel` on the server's `PATH` (and `SLURM_CONF` where the
//! cluster's configuration is not the default); the bundles folder and
//! `translux-precompute` (looked for beside the server's executable, then on `PATH`) at the
//! same paths on every node: a shared filesystem.

use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use serde::Deserialize;
use translux_proto::scene::Material;

/// The script every task runs (shards and merge), the same file `docs/team.md` shows.
pub const SBATCH_SCRIPT: &str = include_str!("../../docker/slurm/precompute.sbatch");

/// A re-simulation's one task: `BIN BUNDLE MATERIALS OUTCOME_DIR`. The bundle is rewritten
/// in place by `translux-precompute --resimulate` (atomically).
const RESIMULATE_SCRIPT: &str = r#"#!/bin/bash
# translux re-simulation on Slurm (written by translux-server --jobs slurm).
#SBATCH --job-name=translux-resimulate
"$1" "$2" --resimulate --materials "@$3" --quiet
rc=$?
printf '%s\n' "$rc" >"$4/.resimulate.exit.$$" && mv -f "$4/.resimulate.exit.$$" "$4/resimulate.exit"
exit "$rc"
"#;

/// Shards of an upload's precompute when `--slurm-shards` is not given.
pub const DEFAULT_SHARDS: u32 = 2;
/// The most shards `--slurm-shards` takes.
pub const MAX_SHARDS: u32 = 4096;
/// How often a job's tasks are looked at.
const POLL: Duration = Duration::from_millis(500);
/// How long a cancel waits for Slurm to end the tasks.
const CANCEL_WAIT: Duration = Duration::from_secs(30);
/// Polls in a row that Slurm may show a failed task before its outcome is read (then the
/// job fails with Slurm's state), and that it may run none of the tasks without the last
/// one's outcome.
const FAILED_POLLS: u32 = 3;
const IDLE_POLLS: u32 = 60;
/// Lines of a failed task's log in the job's error.
const TAIL_LINES: usize = 12;

/// The `--jobs` setting: where precompute jobs run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(try_from = "JobsValue")]
pub enum JobsSetting {
    /// In the server, this many at once (`local` is 1; a number N is local with N at once).
    Local(usize),
    /// On Slurm, as job arrays (this module).
    Slurm,
}

impl Default for JobsSetting {
    fn default() -> Self {
        JobsSetting::Local(1)
    }
}

/// The config file's `jobs`: a number, or `"local"` / `"slurm"`.
#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum JobsValue {
    Count(usize),
    Text(String),
}

impl TryFrom<JobsValue> for JobsSetting {
    type Error = String;

    fn try_from(v: JobsValue) -> Result<Self, String> {
        match v {
            JobsValue::Count(n) => JobsSetting::parse(&n.to_string()),
            JobsValue::Text(t) => JobsSetting::parse(&t),
        }
    }
}

impl JobsSetting {
    /// `local`, `slurm`, or a number of local jobs at once (at least 1).
    pub fn parse(text: &str) -> Result<JobsSetting, String> {
        match text.trim() {
            "local" => Ok(JobsSetting::Local(1)),
            "slurm" => Ok(JobsSetting::Slurm),
            t => match t.parse::<usize>() {
                Ok(n) if n >= 1 => Ok(JobsSetting::Local(n)),
                _ => Err(format!(
                    "expected local, slurm or a number of local jobs at once (1 or more), \
                     got {text:?}"
                )),
            },
        }
    }
}

/// How the server submits to Slurm.
#[derive(Debug, Clone, PartialEq)]
pub struct SlurmConfig {
    /// Shards of an upload's precompute (K of `--shard I/K`).
    pub shards: u32,
    /// More `sbatch` arguments for every job (`--slurm-args`: partition, account, time).
    pub sbatch_args: Vec<String>,
    /// The `translux-precompute` the tasks run.
    pub precompute: PathBuf,
}

impl SlurmConfig {
    /// Checks the settings (`--slurm-shards`, default [`DEFAULT_SHARDS`]; `--slurm-args`,
    /// split on whitespace) and finds what the jobs need: `sbatch` that runs, and
    /// `translux-precompute` beside this executable or on `PATH`. Errors name the setting
    /// or the program.
    pub fn new(shards: Option<u32>, sbatch_args: Option<&str>) -> anyhow::Result<SlurmConfig> {
        let shards = shards.unwrap_or(DEFAULT_SHARDS);
        if !(1..=MAX_SHARDS).contains(&shards) {
            bail!("slurm_shards must be in 1..={MAX_SHARDS}, got {shards}");
        }
        let sbatch_args: Vec<String> = sbatch_args
            .unwrap_or_default()
            .split_whitespace()
            .map(str::to_string)
            .collect();
        if let Some(a) = sbatch_args.iter().find(|a| !a.starts_with('-')) {
            bail!(
                "slurm_args: {a:?} is not an sbatch option (each starts with -, e.g. --partition=gpu)"
            );
        }
        check_sbatch()?;
        Ok(SlurmConfig {
            shards,
            sbatch_args,
            precompute: find_precompute()?,
        })
    }
}

impl SlurmConfig {
    /// The start-up log line.
    pub fn describe(&self) -> String {
        format!(
            "precompute jobs run on Slurm: uploads as {} shards and a merge, tasks running {}{}",
            self.shards,
            self.precompute.display(),
            if self.sbatch_args.is_empty() {
                String::new()
            } else {
                format!(", sbatch {}", self.sbatch_args.join(" "))
            }
        )
    }
}

/// `sbatch --version` runs, or an error saying what to install.
fn check_sbatch() -> anyhow::Result<()> {
    match Command::new("sbatch").arg("--version").output() {
        Ok(o) if o.status.success() => Ok(()),
        Ok(o) => bail!(
            "--jobs slurm: `sbatch --version` failed: {}",
            String::from_utf8_lossy(&o.stderr).trim()
        ),
        Err(e) => bail!(
            "--jobs slurm: cannot run sbatch ({e}): install Slurm's client commands (Debian: \
             slurm-client) and set SLURM_CONF if the cluster's slurm.conf is elsewhere"
        ),
    }
}

/// `translux-precompute` beside the server's executable, else on `PATH`.
fn find_precompute() -> anyhow::Result<PathBuf> {
    const NAME: &str = "translux-precompute";
    let beside = std::env::current_exe()
        .ok()
        .map(|exe| exe.with_file_name(NAME))
        .filter(|p| p.is_file());
    let on_path = || {
        std::env::var_os("PATH").and_then(|paths| {
            std::env::split_paths(&paths)
                .map(|d| d.join(NAME))
                .find(|p| p.is_file())
        })
    };
    beside.or_else(on_path).with_context(|| {
        format!(
            "--jobs slurm: {NAME} is neither beside this translux-server nor on PATH; install \
             it there (at the same path on every node)"
        )
    })
}

/// The job table's side of a job: cancellation in, progress out.
pub trait Follow {
    /// Whether the job was asked to stop (`DELETE /api/v1/jobs/{id}`, the server's stop).
    fn cancelled(&self) -> bool;
    /// The job reached `stage` (`slurm queue`, `shards`, `merge`, `walks`), `stage_percent`
    /// of it done, `percent` of the whole job.
    fn progress(&self, stage: &str, stage_percent: f64, percent: f64);
}

/// What a job asks Slurm to do.
#[derive(Debug, Clone, Copy)]
pub enum Work<'a> {
    /// Precompute an uploaded scene file in K shards and merge them.
    Precompute {
        scene_file: &'a Path,
        patches: Option<u64>,
        max_edge: Option<f32>,
    },
    /// Walk a served bundle's simulated objects again in these media (one task: the walks
    /// are not sharded).
    Resimulate { materials: &'a [(String, Material)] },
}

/// Runs job `job` (scene id `scene`) on Slurm until it ends: submits it, follows it, and
/// returns the bundle's numbers once it is at `bundles/scene`. The error is `cancelled`
/// when `follow` asked to stop, else a message naming what failed (server paths removed).
pub fn run(
    cfg: &SlurmConfig,
    bundles: &Path,
    job: &str,
    scene: &str,
    work: Work<'_>,
    follow: &dyn Follow,
) -> Result<Duration, String> {
    let started = Instant::now();
    let staging = Staging::create(bundles, job).map_err(|e| format!("{e:#}"))?;
    follow.progress("slurm queue", 0.0, 0.0);
    let submitted = submit(cfg, &staging, job, scene, work).map_err(|e| format!("{e:#}"))?;
    tracing::info!(job, scene, "submitted to Slurm: {}", submitted.describe());
    follow_jobs(&staging, &submitted, follow)?;
    Ok(started.elapsed())
}

/// A job's working folder, `BUNDLES/.slurm-JOB/`; removed when dropped.
#[derive(Debug)]
struct Staging {
    bundles: PathBuf,
    dir: PathBuf,
}

impl Staging {
    fn create(bundles: &Path, job: &str) -> anyhow::Result<Staging> {
        let dir = bundles.join(format!(".slurm-{job}"));
        for sub in ["logs", "outcome"] {
            std::fs::create_dir_all(dir.join(sub))
                .with_context(|| format!("cannot create {}", dir.join(sub).display()))?;
        }
        Ok(Staging {
            bundles: bundles.to_path_buf(),
            dir,
        })
    }

    /// Writes an executable script into the folder.
    fn script(&self, name: &str, text: &str) -> anyhow::Result<PathBuf> {
        use std::os::unix::fs::PermissionsExt;
        let path = self.dir.join(name);
        std::fs::write(&path, text).with_context(|| format!("cannot write {}", path.display()))?;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755))
            .with_context(|| format!("cannot make {} executable", path.display()))?;
        Ok(path)
    }

    fn outcome_dir(&self) -> PathBuf {
        self.dir.join("outcome")
    }

    fn log(&self, task: &str) -> PathBuf {
        self.dir.join("logs").join(format!("{task}.out"))
    }

    /// The exit code task `task` left, if it has ended.
    fn outcome(&self, task: &str) -> Option<i32> {
        let text = std::fs::read_to_string(self.outcome_dir().join(format!("{task}.exit"))).ok()?;
        text.trim().parse().ok()
    }

    /// The last lines of task `task`'s log, on one line each joined by ` | `.
    fn log_tail(&self, task: &str) -> String {
        let Ok(text) = std::fs::read_to_string(self.log(task)) else {
            return "(no log)".into();
        };
        let lines: Vec<String> = text
            .lines()
            .filter(|l| !l.trim().is_empty())
            .map(without_spool_path)
            .collect();
        let tail = lines[lines.len().saturating_sub(TAIL_LINES)..].join(" | ");
        if tail.is_empty() {
            "(empty log)".into()
        } else {
            tail
        }
    }
}

/// A log line with the node's copy of the batch script (`/var/spool/slurmd/job00012/
/// slurm_script: line 44: ...`, as bash names it) cut to `slurm_script`: clients see no
/// node paths.
fn without_spool_path(line: &str) -> String {
    const SCRIPT: &str = "/slurm_script";
    match line.find(SCRIPT) {
        Some(end) => {
            let start = line[..end].rfind(char::is_whitespace).map_or(0, |k| k + 1);
            format!("{}{}", &line[..start], &line[end + 1..])
        }
        None => line.to_string(),
    }
}

impl Drop for Staging {
    fn drop(&mut self) {
        if let Err(e) = std::fs::remove_dir_all(&self.dir) {
            tracing::warn!("cannot remove {}: {e}", self.dir.display());
        }
    }
}

/// What was submitted for one job.
#[derive(Debug, Clone, PartialEq)]
struct Submitted {
    /// The shards' job array (none for a re-simulation).
    array: Option<String>,
    /// The job whose success ends the work: the merge or the re-simulation.
    last: String,
    /// Its task name (outcome and log): `merge` or `resimulate`.
    last_task: &'static str,
    /// Shards in the array.
    shards: u32,
}

impl Submitted {
    fn ids(&self) -> Vec<String> {
        self.array.iter().chain([&self.last]).cloned().collect()
    }

    fn describe(&self) -> String {
        match &self.array {
            Some(a) => format!(
                "job array {a} ({} shards), merge {} after it",
                self.shards, self.last
            ),
            None => format!("job {} ({})", self.last, self.last_task),
        }
    }
}

/// Submits `work`, records the Slurm job ids in `slurm.json`.
fn submit(
    cfg: &SlurmConfig,
    staging: &Staging,
    job: &str,
    scene: &str,
    work: Work<'_>,
) -> anyhow::Result<Submitted> {
    let submitted = match work {
        Work::Precompute {
            scene_file,
            patches,
            max_edge,
        } => submit_precompute(cfg, staging, job, scene, scene_file, (patches, max_edge))?,
        Work::Resimulate { materials } => submit_resimulate(cfg, staging, job, scene, materials)?,
    };
    let ids = serde_json::json!({ "array": submitted.array, "last": submitted.last });
    let path = staging.dir.join("slurm.json");
    std::fs::write(&path, ids.to_string())
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(submitted)
}

/// The shards' array, then the merge after it. The tasks run in the upload folder's parent
/// with the scene as `JOB/FILE`, so the bundle's `source` names the upload, not a server
/// path.
fn submit_precompute(
    cfg: &SlurmConfig,
    staging: &Staging,
    job: &str,
    scene: &str,
    scene_file: &Path,
    (patches, max_edge): (Option<u64>, Option<f32>),
) -> anyhow::Result<Submitted> {
    let script = staging.script("precompute.sbatch", SBATCH_SCRIPT)?;
    let (chdir, scene_arg) = upload_relative(scene_file);
    let k = cfg.shards;
    let mut tail: Vec<OsString> = vec![
        script.into(),
        scene_arg,
        staging.dir.join(scene).into(),
        k.to_string().into(),
        "--quiet".into(),
    ];
    if let Some(p) = patches {
        tail.extend(["--patches".into(), p.to_string().into()]);
    }
    if let Some(e) = max_edge {
        tail.extend(["--max-edge".into(), e.to_string().into()]);
    }
    let common: Vec<OsString> = vec![
        format!("--job-name=translux-{job}").into(),
        os_arg("--chdir=", &chdir),
    ];
    let env = task_env(cfg, staging, scene);
    let array = sbatch(
        cfg,
        &env,
        [
            common.clone(),
            vec![
                format!("--array=0-{}", k - 1).into(),
                os_arg("--output=", &staging.dir.join("logs").join("shard-%a.out")),
            ],
            tail.clone(),
        ]
        .concat(),
    )?;
    let merge = sbatch(
        cfg,
        &env,
        [
            common,
            vec![
                format!("--dependency=afterok:{array}").into(),
                "--kill-on-invalid-dep=yes".into(),
                os_arg("--output=", &staging.log("merge")),
            ],
            tail,
        ]
        .concat(),
    );
    let merge = match merge {
        Ok(m) => m,
        Err(e) => {
            scancel(&[array]);
            return Err(e);
        }
    };
    Ok(Submitted {
        array: Some(array),
        last: merge,
        last_task: "merge",
        shards: k,
    })
}

/// One task that walks the bundle's objects again in the new media.
fn submit_resimulate(
    cfg: &SlurmConfig,
    staging: &Staging,
    job: &str,
    scene: &str,
    materials: &[(String, Material)],
) -> anyhow::Result<Submitted> {
    let script = staging.script("resimulate.sh", RESIMULATE_SCRIPT)?;
    let map: serde_json::Map<String, serde_json::Value> = materials
        .iter()
        .map(|(name, m)| Ok((name.clone(), serde_json::to_value(m)?)))
        .collect::<Result<_, serde_json::Error>>()
        .context("cannot write the new materials")?;
    let file = staging.dir.join("materials.json");
    std::fs::write(&file, serde_json::Value::Object(map).to_string())
        .with_context(|| format!("cannot write {}", file.display()))?;
    let last = sbatch(
        cfg,
        &task_env(cfg, staging, scene),
        vec![
            format!("--job-name=translux-{job}").into(),
            os_arg("--output=", &staging.log("resimulate")),
            script.into(),
            cfg.precompute.clone().into(),
            staging.bundles.join(scene).into(),
            file.into(),
            staging.outcome_dir().into(),
        ],
    )?;
    Ok(Submitted {
        array: None,
        last,
        last_task: "resimulate",
        shards: 0,
    })
}

/// `(folder to run in, scene argument)`: the upload folder's parent and `JOB/FILE`, or no
/// folder and the path as it is.
fn upload_relative(scene_file: &Path) -> (PathBuf, OsString) {
    let upload = scene_file.parent();
    match (
        upload.and_then(Path::parent),
        upload.and_then(Path::file_name),
        scene_file.file_name(),
    ) {
        (Some(base), Some(dir), Some(file)) if base.is_absolute() => {
            (base.to_path_buf(), Path::new(dir).join(file).into())
        }
        _ => (
            std::env::current_dir().unwrap_or_else(|_| PathBuf::from("/")),
            scene_file.into(),
        ),
    }
}

fn os_arg(flag: &str, path: &Path) -> OsString {
    let mut s = OsString::from(flag);
    s.push(path);
    s
}

/// What `precompute.sbatch` reads from its environment (sbatch passes the submitter's on).
fn task_env(cfg: &SlurmConfig, staging: &Staging, scene: &str) -> Vec<(&'static str, OsString)> {
    vec![
        ("TRANSLUX_PRECOMPUTE", cfg.precompute.clone().into()),
        ("TRANSLUX_OUTCOME_DIR", staging.outcome_dir().into()),
        ("TRANSLUX_PUBLISH", staging.bundles.join(scene).into()),
    ]
}

/// `sbatch --parsable ARGS...`: the new job's id.
fn sbatch(
    cfg: &SlurmConfig,
    env: &[(&'static str, OsString)],
    args: Vec<OsString>,
) -> anyhow::Result<String> {
    let out = Command::new("sbatch")
        .arg("--parsable")
        .args(&cfg.sbatch_args)
        .args(&args)
        .envs(env.iter().map(|(k, v)| (k, v)))
        .output()
        .context("cannot run sbatch")?;
    let stdout = String::from_utf8_lossy(&out.stdout);
    if !out.status.success() {
        bail!(
            "sbatch refused the job: {}",
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    // `--parsable` prints `ID` or `ID;CLUSTER`.
    let id = stdout
        .trim()
        .split(';')
        .next()
        .unwrap_or_default()
        .to_string();
    if id.is_empty() || !id.bytes().all(|b| b.is_ascii_digit()) {
        bail!("sbatch printed no job id: {:?}", stdout.trim());
    }
    Ok(id)
}

/// `scancel IDS`; failures are logged (the jobs may have ended already).
fn scancel(ids: &[String]) {
    match Command::new("scancel").args(ids).output() {
        Ok(o) if o.status.success() => {}
        Ok(o) => tracing::warn!(
            "scancel {}: {}",
            ids.join(" "),
            String::from_utf8_lossy(&o.stderr).trim()
        ),
        Err(e) => tracing::warn!("cannot run scancel: {e}"),
    }
}

/// One line of `squeue`: a task (`12_0`, `12_[1-3]` while pending, `13`) and its state.
#[derive(Debug, Clone, PartialEq)]
struct TaskState {
    id: String,
    state: String,
}

/// Slurm states in which a task ended without succeeding.
const FAILED_STATES: [&str; 9] = [
    "FAILED",
    "CANCELLED",
    "TIMEOUT",
    "NODE_FAIL",
    "PREEMPTED",
    "OUT_OF_MEMORY",
    "BOOT_FAIL",
    "DEADLINE",
    "SPECIAL_EXIT",
];

impl TaskState {
    fn failed(&self) -> bool {
        FAILED_STATES.contains(&self.state.as_str())
    }

    fn active(&self) -> bool {
        self.state != "COMPLETED" && !self.failed()
    }

    /// `shard I` for a task of the array, `merge`/`resimulate` for the last job.
    fn name(&self, last_task: &str) -> String {
        match self.id.split_once('_') {
            Some((_, i)) => format!("shard {i}"),
            None => last_task.to_string(),
        }
    }

    /// The log of this task (`shard-I`, or the last job's).
    fn log_name(&self, last_task: &str) -> String {
        match self.id.split_once('_') {
            Some((_, i)) => format!("shard-{i}"),
            None => last_task.to_string(),
        }
    }
}

/// The states of every task of `ids`, finished ones included while Slurm keeps them
/// (`MinJobAge`). Jobs Slurm no longer knows are simply absent.
fn squeue(ids: &[String]) -> anyhow::Result<Vec<TaskState>> {
    let out = Command::new("squeue")
        .args(["--noheader", "--states=all", "--format=%i %T", "--jobs"])
        .arg(ids.join(","))
        .output()
        .context("cannot run squeue")?;
    let stderr = String::from_utf8_lossy(&out.stderr);
    if !out.status.success() {
        if stderr.contains("Invalid job id") {
            return Ok(Vec::new());
        }
        bail!("squeue failed: {}", stderr.trim());
    }
    Ok(String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| {
            let (id, state) = l.trim().split_once(' ')?;
            Some(TaskState {
                id: id.to_string(),
                state: state.trim().to_string(),
            })
        })
        .collect())
}

/// Polls until the last task's outcome says the work is done (`Ok`), a task failed, or the
/// job was cancelled.
fn follow_jobs(
    staging: &Staging,
    submitted: &Submitted,
    follow: &dyn Follow,
) -> Result<(), String> {
    let mut reported = None;
    // Polls in a row in which Slurm showed a failed task, or no task running or waiting,
    // without the outcome that would explain it (a task writes its outcome just before it
    // ends; on a shared filesystem the server may see the file a little later).
    let mut unexplained = 0;
    let mut warned: Option<Instant> = None;
    loop {
        if follow.cancelled() {
            return cancel(staging, submitted);
        }
        if let Some(code) = staging.outcome(submitted.last_task) {
            return match code {
                0 => Ok(()),
                _ => Err(format!(
                    "the {} task failed (exit {code}): {}",
                    submitted.last_task,
                    staging.log_tail(submitted.last_task)
                )),
            };
        }
        let done = shards_done(staging, submitted)?;
        report_progress(submitted, done, &mut reported, follow);
        match squeue(&submitted.ids()) {
            Ok(tasks) => {
                let failed = tasks.iter().find(|t| t.failed());
                let idle = !tasks.iter().any(TaskState::active);
                unexplained = if failed.is_some() || idle {
                    unexplained + 1
                } else {
                    0
                };
                let patience = if failed.is_some() {
                    FAILED_POLLS
                } else {
                    IDLE_POLLS
                };
                if unexplained >= patience {
                    scancel(&submitted.ids());
                    return Err(ended_without_outcome(staging, submitted, failed));
                }
            }
            // The controller may be restarting: keep following, say so every minute.
            Err(e) if warned.is_none_or(|w| w.elapsed() >= Duration::from_secs(60)) => {
                warned = Some(Instant::now());
                tracing::warn!("following Slurm jobs {}: {e:#}", submitted.ids().join(","));
            }
            Err(_) => {}
        }
        std::thread::sleep(POLL);
    }
}

/// Shards that finished; the first one that failed ends the job (the merge is cancelled).
fn shards_done(staging: &Staging, submitted: &Submitted) -> Result<u32, String> {
    let mut done = 0;
    for i in 0..submitted.shards {
        match staging.outcome(&format!("shard-{i}")) {
            Some(0) => done += 1,
            Some(code) => {
                scancel(&submitted.ids());
                return Err(format!(
                    "shard {i} of {} failed (exit {code}): {}",
                    submitted.shards,
                    staging.log_tail(&format!("shard-{i}"))
                ));
            }
            None => {}
        }
    }
    Ok(done)
}

/// Tells `follow` the stage when it changed: the shards (90% of the job) then the merge,
/// or a re-simulation's walks.
fn report_progress(
    submitted: &Submitted,
    done: u32,
    reported: &mut Option<u32>,
    follow: &dyn Follow,
) {
    if *reported == Some(done) {
        return;
    }
    *reported = Some(done);
    let k = submitted.shards;
    if k == 0 {
        follow.progress("walks", 0.0, 0.0);
    } else if done < k {
        let f = f64::from(done) / f64::from(k);
        follow.progress("shards", 100.0 * f, 90.0 * f);
    } else {
        follow.progress("merge", 0.0, 90.0);
    }
}

/// The error of a job whose tasks Slurm ended (or forgot) without the last one's outcome.
fn ended_without_outcome(
    staging: &Staging,
    submitted: &Submitted,
    failed: Option<&TaskState>,
) -> String {
    match failed {
        Some(t) => format!(
            "{} ended {} in Slurm before it finished (killed, out of time or its node \
             failed): {}",
            t.name(submitted.last_task),
            t.state,
            staging.log_tail(&t.log_name(submitted.last_task))
        ),
        None => format!(
            "Slurm lists none of the job's tasks ({}) any more, and the {} left no outcome",
            submitted.ids().join(", "),
            submitted.last_task
        ),
    }
}

/// `scancel` of every job, then a wait until Slurm runs none of their tasks. `Ok` when the
/// work had finished before the cancel arrived (its bundle is in place), else `cancelled`.
fn cancel(staging: &Staging, submitted: &Submitted) -> Result<(), String> {
    let ids = submitted.ids();
    scancel(&ids);
    let t0 = Instant::now();
    while t0.elapsed() < CANCEL_WAIT {
        match squeue(&ids) {
            Ok(tasks) if !tasks.iter().any(TaskState::active) => break,
            Ok(_) => {}
            Err(e) => {
                tracing::warn!("after scancel {}: {e:#}", ids.join(" "));
                break;
            }
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    match staging.outcome(submitted.last_task) {
        Some(0) => Ok(()),
        _ => Err("cancelled".to_string()),
    }
}

/// Removes the working folders (`BUNDLES/.slurm-JOB/`) of jobs that `live` says have ended
/// (their record final or gone: left by a server that was killed), after `scancel` of the
/// Slurm jobs they name, so a forgotten merge cannot put a bundle in place later. One note
/// per folder.
pub fn settle_leftovers(bundles: &Path, live: &dyn Fn(&str) -> bool) -> Vec<String> {
    let mut notes = Vec::new();
    let Ok(entries) = std::fs::read_dir(bundles) else {
        return notes;
    };
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(job) = name.strip_prefix(".slurm-") else {
            continue;
        };
        if live(job) {
            continue;
        }
        let ids = leftover_ids(&e.path());
        if !ids.is_empty() {
            scancel(&ids);
        }
        match std::fs::remove_dir_all(e.path()) {
            Ok(()) => notes.push(format!(
                "removed {name}, the Slurm folder of an ended job{}",
                if ids.is_empty() {
                    String::new()
                } else {
                    format!(" (scancel {})", ids.join(" "))
                }
            )),
            Err(err) => notes.push(format!("cannot remove {name}: {err}")),
        }
    }
    notes
}

/// The Slurm job ids a working folder's `slurm.json` names.
fn leftover_ids(dir: &Path) -> Vec<String> {
    let Ok(text) = std::fs::read_to_string(dir.join("slurm.json")) else {
        return Vec::new();
    };
    let Ok(v) = serde_json::from_str::<serde_json::Value>(&text) else {
        return Vec::new();
    };
    ["array", "last"]
        .iter()
        .filter_map(|k| v.get(k)?.as_str())
        .filter(|id| !id.is_empty() && id.bytes().all(|b| b.is_ascii_digit()))
        .map(str::to_string)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_jobs_setting_takes_local_slurm_or_a_count() {
        assert_eq!(JobsSetting::parse("local"), Ok(JobsSetting::Local(1)));
        assert_eq!(JobsSetting::parse("slurm"), Ok(JobsSetting::Slurm));
        assert_eq!(JobsSetting::parse("3"), Ok(JobsSetting::Local(3)));
        for bad in ["0", "-1", "slum", ""] {
            let e = JobsSetting::parse(bad).unwrap_err();
            assert!(e.contains("local, slurm"), "{e}");
        }
        #[derive(Deserialize)]
        struct F {
            jobs: JobsSetting,
        }
        let f: F = toml::from_str("jobs = 2").unwrap();
        assert_eq!(f.jobs, JobsSetting::Local(2));
        let f: F = toml::from_str("jobs = \"slurm\"").unwrap();
        assert_eq!(f.jobs, JobsSetting::Slurm);
        let e = toml::from_str::<F>("jobs = \"k8s\"")
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("k8s"), "{e}");
    }

    #[test]
    fn task_states_and_names() {
        let t = |id: &str, state: &str| TaskState {
            id: id.into(),
            state: state.into(),
        };
        assert!(t("12_1", "FAILED").failed());
        assert!(!t("12_1", "FAILED").active());
        assert!(t("12_[0-1]", "PENDING").active());
        assert!(!t("13", "COMPLETED").active() && !t("13", "COMPLETED").failed());
        assert_eq!(t("12_1", "FAILED").name("merge"), "shard 1");
        assert_eq!(t("12_1", "FAILED").log_name("merge"), "shard-1");
        assert_eq!(t("13", "CANCELLED").name("merge"), "merge");
    }

    #[test]
    fn log_lines_name_no_node_path() {
        assert_eq!(
            without_spool_path("/var/spool/slurmd/job00003/slurm_script: line 44: 28909 Killed"),
            "slurm_script: line 44: 28909 Killed"
        );
        assert_eq!(
            without_spool_path("x: /s/j/slurm_script: y"),
            "x: slurm_script: y"
        );
        assert_eq!(without_spool_path("error: bad scene"), "error: bad scene");
    }

    #[test]
    fn an_upload_runs_from_its_folder_parent() {
        let (dir, arg) = upload_relative(Path::new("/b/.uploads/j1/room.json"));
        assert_eq!(dir, Path::new("/b/.uploads"));
        assert_eq!(arg, OsString::from("j1/room.json"));
    }

    #[test]
    fn bad_settings_are_named() {
        let e = SlurmConfig::new(Some(0), None).unwrap_err().to_string();
        assert!(e.contains("slurm_shards"), "{e}");
        let e = SlurmConfig::new(Some(2), Some("gpu"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("slurm_args") && e.contains("gpu"), "{e}");
    }

    #[test]
    fn the_script_is_the_one_in_docker_slurm() {
        assert!(SBATCH_SCRIPT.starts_with("#!/bin/bash"));
        assert!(SBATCH_SCRIPT.contains("--shard \"$1/$K\""));
        assert!(SBATCH_SCRIPT.contains("--merge \"$K\""));
    }
}
