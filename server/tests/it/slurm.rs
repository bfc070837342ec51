//! Slurm as the precompute engine, with real daemons: each test starts munged, slurmctld and
//! slurmd on this node in a temporary folder ([`Cluster`]: its own slurm.conf through
//! `SLURM_CONF`, its own munge key and socket, state, spool, logs and pid files) and stops
//! them by pid when it ends, also when it fails. Slurm's packages are installed by
//! `scripts/test`; without them these tests fail.
//!
//! - `sbatch_script_by_hand_matches_one_box`: docker/slurm/submit.sh (a job array of
//!   shards and a merge after it) makes the same bytes as one `translux-precompute`;
//! - `an_upload_runs_as_a_slurm_array_and_merge`: `translux-server --jobs slurm` turns an
//!   upload into an array plus a merge; the job ends `done` and the scene is served;
//! - `cancelling_a_job_cancels_it_in_slurm`: `DELETE /api/v1/jobs/{id}` ends the tasks;
//! - `a_killed_shard_runs_again_or_fails_and_a_resubmission_completes`: kill -9 of a shard's
//!   process (run again in its task) and of a shard's batch script (the job fails, the
//!   upload again completes); no half bundle is ever under a bundle's name;
//! - `a_resimulation_runs_as_one_slurm_task`: a re-simulation is one Slurm job (its walks
//!   are not sharded) and the scene is served with the new medium.
//!
//! The precompute binary must be built: `cargo test --workspace` builds it; with
//! `-p translux-server` alone, first `cargo build --profile test -p translux-precompute --bins`.

use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde_json::Value;

const SERVER: &str = env!("CARGO_BIN_EXE_translux-server");

/// One Slurm test at a time: each starts its own daemons and two cores run two shards.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

pub(crate) fn serial() -> std::sync::MutexGuard<'static, ()> {
    ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner())
}

/// `translux-precompute` beside the server binary, with `--shard`.
pub(crate) fn precompute_bin() -> PathBuf {
    let bin = Path::new(SERVER).with_file_name("translux-precompute");
    assert!(
        bin.is_file(),
        "{} is missing: build it first with `cargo build --profile test -p translux-precompute \
         --bins` (cargo test --workspace builds it)",
        bin.display()
    );
    let help = Command::new(&bin).arg("--help").output().unwrap();
    assert!(
        String::from_utf8_lossy(&help.stdout).contains("--shard"),
        "{} has no --shard: rebuild it (cargo build --profile test -p translux-precompute --bins)",
        bin.display()
    );
    bin
}

/// munged, slurmctld and slurmd in a temporary folder; dropping it cancels every job and
/// stops the daemons by their pids.
pub(crate) struct Cluster {
    dir: tempfile::TempDir,
    pub(crate) conf: PathBuf,
    /// (daemon, pid), in the order they started.
    daemons: Vec<(&'static str, i32)>,
}

impl Cluster {
    /// Starts the three daemons and waits until `sinfo` shows the node idle.
    pub(crate) fn start() -> Cluster {
        for program in [
            "/usr/sbin/munged",
            "/usr/sbin/slurmctld",
            "/usr/sbin/slurmd",
        ] {
            assert!(
                Path::new(program).is_file(),
                "{program} is missing: install Slurm and munge (apt-get install slurm-wlm \
                 munge; scripts/test does)"
            );
        }
        let dir = tempfile::tempdir().unwrap();
        let mut cluster = Cluster {
            conf: dir.path().join("slurm.conf"),
            dir,
            daemons: Vec::new(),
        };
        cluster.start_munge();
        cluster.write_conf();
        cluster.start_daemon("slurmctld", "/usr/sbin/slurmctld");
        cluster.start_daemon("slurmd", "/usr/sbin/slurmd");
        cluster.wait_idle();
        cluster
    }

    fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    /// munged with its own key, socket, pid, log and seed files (`--force`: the temporary
    /// folder's parent is world-writable).
    fn start_munge(&mut self) {
        use std::os::unix::fs::PermissionsExt;
        let munge = self.path("munge");
        std::fs::create_dir_all(&munge).unwrap();
        for d in [self.dir.path(), munge.as_path()] {
            std::fs::set_permissions(d, std::fs::Permissions::from_mode(0o711)).unwrap();
        }
        let mut key = vec![0u8; 128];
        std::fs::File::open("/dev/urandom")
            .unwrap()
            .read_exact(&mut key)
            .unwrap();
        let key_file = munge.join("munge.key");
        std::fs::write(&key_file, key).unwrap();
        std::fs::set_permissions(&key_file, std::fs::Permissions::from_mode(0o600)).unwrap();
        let out = Command::new("/usr/sbin/munged")
            .arg("--force")
            .arg(format!("--socket={}", munge.join("munge.sock").display()))
            .arg(format!("--key-file={}", key_file.display()))
            .arg(format!("--pid-file={}", munge.join("munged.pid").display()))
            .arg(format!("--log-file={}", munge.join("munged.log").display()))
            .arg(format!(
                "--seed-file={}",
                munge.join("munged.seed").display()
            ))
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "munged did not start: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        self.track("munged", &munge.join("munged.pid"));
    }

    /// slurm.conf as docs CLUSTER.md has it, every path in the temporary folder, free ports,
    /// the node as `slurmd -C` describes this machine.
    fn write_conf(&self) {
        let d = self.dir.path().display();
        for sub in ["state", "spool", "log"] {
            std::fs::create_dir_all(self.path(sub)).unwrap();
        }
        let node = node_line();
        let host = node
            .split_whitespace()
            .next()
            .and_then(|w| w.strip_prefix("NodeName="))
            .unwrap()
            .to_string();
        let (ctl, slurmd) = (free_port(), free_port());
        let conf = format!(
            "ClusterName=translux-test\nSlurmctldHost={host}(127.0.0.1)\n\
             SlurmctldPort={ctl}\nSlurmdPort={slurmd}\nSlurmUser=root\nSlurmdUser=root\n\
             AuthType=auth/munge\nCredType=cred/munge\nAuthInfo=socket={d}/munge/munge.sock\n\
             ProctrackType=proctrack/pgid\nTaskPlugin=task/none\n\
             SelectType=select/cons_tres\nSelectTypeParameters=CR_Core\n\
             AccountingStorageType=accounting_storage/none\n\
             JobAcctGatherType=jobacct_gather/none\nJobCompType=jobcomp/none\n\
             StateSaveLocation={d}/state\nSlurmdSpoolDir={d}/spool\n\
             SlurmctldPidFile={d}/slurmctld.pid\nSlurmdPidFile={d}/slurmd.pid\n\
             SlurmctldLogFile={d}/log/slurmctld.log\nSlurmdLogFile={d}/log/slurmd.log\n\
             ReturnToService=2\nMpiDefault=none\n\
             {node} NodeAddr=127.0.0.1 State=UNKNOWN\n\
             PartitionName=main Nodes=ALL Default=YES MaxTime=INFINITE State=UP\n"
        );
        std::fs::write(&self.conf, conf).unwrap();
    }

    /// Starts a Slurm daemon (it forks) and records its pid from its pid file.
    fn start_daemon(&mut self, name: &'static str, program: &str) {
        let out = self.command(program).output().unwrap();
        assert!(
            out.status.success(),
            "{name} did not start: {}\n{}",
            String::from_utf8_lossy(&out.stderr),
            self.logs()
        );
        self.track(name, &self.path(&format!("{name}.pid")));
    }

    /// Waits for `pid_file` (10 s) and keeps the pid to stop it.
    fn track(&mut self, name: &'static str, pid_file: &Path) {
        let t0 = Instant::now();
        loop {
            if let Some(pid) = std::fs::read_to_string(pid_file)
                .ok()
                .and_then(|t| t.trim().parse().ok())
            {
                self.daemons.push((name, pid));
                return;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(10),
                "{name} wrote no pid file: {}",
                self.logs()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    fn wait_idle(&self) {
        let t0 = Instant::now();
        loop {
            let states = self.run("sinfo", &["--noheader", "--format=%T"]);
            if states.trim() == "idle" {
                return;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(30),
                "the node is not idle after 30 s (sinfo: {states:?}): {}",
                self.logs()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// A Slurm command with this cluster's `SLURM_CONF`.
    fn command(&self, program: &str) -> Command {
        let mut c = Command::new(program);
        c.env("SLURM_CONF", &self.conf);
        c
    }

    /// Runs a Slurm command; its stdout (its stderr too when it fails).
    fn run(&self, program: &str, args: &[&str]) -> String {
        let out = self.command(program).args(args).output().unwrap();
        let mut text = String::from_utf8_lossy(&out.stdout).into_owned();
        if !out.status.success() {
            text.push_str(&String::from_utf8_lossy(&out.stderr));
        }
        text
    }

    /// `squeue` lines `ID STATE` of the jobs named `name`, finished ones too.
    pub(crate) fn jobs_named(&self, name: &str) -> Vec<String> {
        self.run(
            "squeue",
            &[
                "--noheader",
                "--states=all",
                "--format=%i %T",
                "--name",
                name,
            ],
        )
        .lines()
        .map(str::to_string)
        .collect()
    }

    /// Waits until Slurm runs or queues none of the jobs `ids` (comma-separated).
    fn wait_ended(&self, ids: &str, limit: Duration) {
        let t0 = Instant::now();
        loop {
            let active = self.run("squeue", &["--noheader", "--format=%i %T", "--jobs", ids]);
            if active.trim().is_empty() || active.contains("Invalid job id") {
                return;
            }
            assert!(
                t0.elapsed() < limit,
                "jobs {ids} still in Slurm after {limit:?}: {active}\n{}",
                self.logs()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// The daemons' logs, for failure messages.
    pub(crate) fn logs(&self) -> String {
        ["munge/munged.log", "log/slurmctld.log", "log/slurmd.log"]
            .iter()
            .map(|f| {
                let text = std::fs::read_to_string(self.path(f)).unwrap_or_default();
                let tail: Vec<&str> = text.lines().rev().take(15).collect();
                format!(
                    "--- {f}\n{}",
                    tail.into_iter().rev().collect::<Vec<_>>().join("\n")
                )
            })
            .collect::<Vec<_>>()
            .join("\n")
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        if self.daemons.iter().any(|(n, _)| *n == "slurmctld") {
            let ids = self.run("squeue", &["--noheader", "--format=%A"]);
            let ids: Vec<&str> = ids.split_whitespace().collect();
            if !ids.is_empty() {
                let _ = self.command("scancel").args(&ids).output();
                std::thread::sleep(Duration::from_millis(500));
            }
        }
        for (_, pid) in self.daemons.iter().rev() {
            stop_pid(*pid);
        }
    }
}

/// SIGTERM, up to 5 s for it to go, then SIGKILL.
fn stop_pid(pid: i32) {
    let _ = Command::new("kill").arg(pid.to_string()).output();
    let t0 = Instant::now();
    while Path::new(&format!("/proc/{pid}")).exists() && t0.elapsed() < Duration::from_secs(5) {
        std::thread::sleep(Duration::from_millis(50));
    }
    if Path::new(&format!("/proc/{pid}")).exists() {
        let _ = Command::new("kill").args(["-9", &pid.to_string()]).output();
    }
}

/// `slurmd -C`'s node line (`NodeName=HOST CPUs=... RealMemory=...`), without its UpTime.
fn node_line() -> String {
    let out = Command::new("/usr/sbin/slurmd").arg("-C").output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text
        .lines()
        .find(|l| l.starts_with("NodeName="))
        .unwrap_or_else(|| panic!("slurmd -C printed no node line: {text}"));
    line.to_string()
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Every file under `dir`, by path relative to it, with its bytes.
fn files(dir: &Path) -> std::collections::BTreeMap<PathBuf, Vec<u8>> {
    let mut out = std::collections::BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.insert(
                    p.strip_prefix(dir).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                );
            }
        }
    }
    out
}

/// A manifest without the record of how it was made: `stages` (their names and seconds:
/// a sharded run lists `form factors (shards)` and `merge parts`) and any other `seconds`,
/// which differ between any two runs.
fn without_provenance(v: Value) -> Value {
    match v {
        Value::Object(m) => Value::Object(
            m.into_iter()
                .filter(|(k, _)| k != "seconds" && k != "stages")
                .map(|(k, v)| (k, without_provenance(v)))
                .collect(),
        ),
        Value::Array(a) => Value::Array(a.into_iter().map(without_provenance).collect()),
        v => v,
    }
}

/// The top-level keys whose values differ between two manifests.
fn differing_keys(a: &Value, b: &Value) -> Vec<String> {
    let keys: std::collections::BTreeSet<&String> = a
        .as_object()
        .into_iter()
        .chain(b.as_object())
        .flat_map(|m| m.keys())
        .collect();
    keys.into_iter()
        .filter(|k| a.get(k.as_str()) != b.get(k.as_str()))
        .cloned()
        .collect()
}

/// Asserts that folders `a` and `b` hold the same files with the same bytes (the
/// manifest's record of its stages aside; every array's checksum is compared with it).
pub(crate) fn assert_same_files(a: &Path, b: &Path) {
    let (fa, fb) = (files(a), files(b));
    let names =
        |f: &std::collections::BTreeMap<PathBuf, Vec<u8>>| f.keys().cloned().collect::<Vec<_>>();
    assert_eq!(
        names(&fa),
        names(&fb),
        "{} and {} hold other files",
        a.display(),
        b.display()
    );
    for (name, bytes) in &fa {
        if name == Path::new("manifest.json") {
            let parse = |b: &[u8]| without_provenance(serde_json::from_slice(b).unwrap());
            let (ma, mb) = (parse(bytes), parse(&fb[name]));
            assert!(
                ma == mb,
                "the manifests of {} and {} differ beyond their stages: {:?}",
                a.display(),
                b.display(),
                differing_keys(&ma, &mb)
            );
            continue;
        }
        assert!(
            *bytes == fb[name],
            "{} differs between {} and {}{}",
            name.display(),
            a.display(),
            b.display(),
            first_difference(bytes, &fb[name])
        );
    }
    assert!(!fa.is_empty(), "{} is empty", a.display());
}

/// For text: the first line that differs, from each side.
fn first_difference(a: &[u8], b: &[u8]) -> String {
    let (ta, tb) = (String::from_utf8_lossy(a), String::from_utf8_lossy(b));
    ta.lines()
        .zip(tb.lines())
        .find(|(x, y)| x != y)
        .map_or_else(String::new, |(x, y)| format!(": {x:?} against {y:?}"))
}

#[test]
fn sbatch_script_by_hand_matches_one_box() {
    let _one = serial();
    let bin = precompute_bin();
    let cluster = Cluster::start();
    let work = tempfile::tempdir().unwrap();
    let out = work.path().join("cornell");
    let flags = ["--patches", "2000", "--quiet"];
    let submit = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docker/slurm/submit.sh");
    let t0 = Instant::now();
    let printed = cluster
        .command("bash")
        .arg(&submit)
        .arg("builtin:cornell")
        .arg(&out)
        .arg("2")
        .args(flags)
        .env("TRANSLUX_PRECOMPUTE", &bin)
        .output()
        .unwrap();
    assert!(
        printed.status.success(),
        "submit.sh failed: {}",
        String::from_utf8_lossy(&printed.stderr)
    );
    let ids: Vec<String> = String::from_utf8_lossy(&printed.stdout)
        .split_whitespace()
        .map(str::to_string)
        .collect();
    assert_eq!(ids.len(), 2, "submit.sh printed {ids:?}");
    cluster.wait_ended(&ids.join(","), Duration::from_secs(60));
    let slurm_s = t0.elapsed().as_secs_f64();
    let logs: Vec<String> = std::fs::read_dir(work.path())
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with("slurm-"))
        .map(|e| std::fs::read_to_string(e.path()).unwrap_or_default())
        .collect();
    assert!(
        out.join("manifest.json").is_file(),
        "no merged bundle after the jobs ended; task logs: {logs:#?}\n{}",
        cluster.logs()
    );
    assert!(
        !work.path().join("cornell.parts").exists(),
        "the merge left the parts folder"
    );
    let one_box = work.path().join("one-box");
    let one = Command::new(&bin)
        .arg("builtin:cornell")
        .arg("--out")
        .arg(&one_box)
        .args(flags)
        .output()
        .unwrap();
    assert!(
        one.status.success(),
        "the one-box precompute failed: {}",
        String::from_utf8_lossy(&one.stderr)
    );
    assert_same_files(&out, &one_box);
    eprintln!("2 shards and a merge on Slurm: {slurm_s:.1} s");
}

/// The real `translux-server --jobs slurm` over `bundles`, open on loopback.
pub(crate) struct Server {
    child: Child,
    pub(crate) addr: String,
    log: Arc<Mutex<Vec<String>>>,
}

impl Server {
    fn start(cluster: &Cluster, bundles: &Path) -> Server {
        Server::start_with(cluster, bundles, &[])
    }

    /// As [`Server::start`], with `extra` flags (`--rescan-s 1`, ...).
    pub(crate) fn start_with(cluster: &Cluster, bundles: &Path, extra: &[&str]) -> Server {
        let mut child = Command::new(SERVER)
            .arg("--bundles")
            .arg(bundles)
            .args([
                "--addr",
                "127.0.0.1:0",
                "--jobs",
                "slurm",
                "--slurm-shards",
                "2",
            ])
            .args(extra)
            .env("SLURM_CONF", &cluster.conf)
            .env("RUST_LOG", "info")
            .env_remove("TRANSLUX_CONFIG")
            .env_remove("TRANSLUX_BUNDLES")
            .env_remove("TRANSLUX_TOKENS")
            .stderr(Stdio::piped())
            .stdout(Stdio::null())
            .spawn()
            .unwrap();
        let (tx, rx) = mpsc::channel();
        let log = Arc::new(Mutex::new(Vec::new()));
        let stderr = child.stderr.take().unwrap();
        let kept = log.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if line.contains("listening on http://") {
                    let _ = tx.send(line.clone());
                }
                kept.lock().unwrap().push(line);
            }
        });
        let line = rx
            .recv_timeout(Duration::from_secs(60))
            .unwrap_or_else(|_| panic!("the server did not start: {:#?}", log.lock().unwrap()));
        let addr = line
            .split("listening on http://")
            .nth(1)
            .and_then(|r| r.split('/').next())
            .unwrap()
            .to_string();
        Server { child, addr, log }
    }

    pub(crate) fn log(&self) -> String {
        self.log.lock().unwrap().join("\n")
    }

    fn request(&self, method: &str, path: &str, content_type: &str, body: &[u8]) -> (u16, String) {
        request(&self.addr, method, path, content_type, body)
    }

    pub(crate) fn get_json(&self, path: &str) -> (u16, Value) {
        get_json(&self.addr, path)
    }

    /// Uploads a scene of a floor and a ball at about `patches` patches as `id`; the job id.
    fn upload(&self, id: &str, patches: u64) -> String {
        upload(&self.addr, id, patches)
    }

    /// Polls job `job` until `done(record)`, at most `limit`.
    fn wait_job(&self, job: &str, limit: Duration, done: impl Fn(&Value) -> bool) -> Value {
        let t0 = Instant::now();
        loop {
            let (status, r) = self.get_json(&format!("/api/v1/jobs/{job}"));
            assert_eq!(status, 200, "GET job {job}: {r}");
            if done(&r) {
                return r;
            }
            assert!(
                t0.elapsed() < limit,
                "job {job} not there after {limit:?}: {r}\n{}",
                self.log()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    }
}

/// One HTTP/1.1 request to `addr` (a server, or haproxy in front) on a fresh loopback
/// connection: (status, body).
pub(crate) fn request(
    addr: &str,
    method: &str,
    path: &str,
    content_type: &str,
    body: &[u8],
) -> (u16, String) {
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {}\r\nConnection: close\r\n\
         Content-Type: {content_type}\r\nContent-Length: {}\r\n\r\n",
        addr,
        body.len()
    );
    s.write_all(head.as_bytes()).unwrap();
    s.write_all(body).unwrap();
    let mut answer = Vec::new();
    s.read_to_end(&mut answer).unwrap();
    let text = String::from_utf8_lossy(&answer);
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    // Chunked answers: the JSON is between the chunk sizes; the tests read JSON only.
    let body = match (body.find('{'), body.rfind('}')) {
        (Some(a), Some(b)) if b >= a => body[a..=b].to_string(),
        _ => body.to_string(),
    };
    (status, body)
}

/// `GET path` on `addr`: the status and the JSON body.
pub(crate) fn get_json(addr: &str, path: &str) -> (u16, Value) {
    let (status, body) = request(addr, "GET", path, "application/json", b"");
    (status, serde_json::from_str(&body).unwrap_or(Value::Null))
}

/// The scene [`upload`] sends: a floor and a ball, as the file `room.json`.
pub(crate) fn upload_scene() -> String {
    serde_json::json!({
        "objects": [
            {"name": "floor", "mesh": {"shape": "quad", "size": [2, 2]},
             "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
            {"name": "ball", "mesh": {"shape": "sphere", "radius": 0.3},
             "transform": {"translate": [0, 0.3, 0]},
             "material": {"type": "diffuse", "albedo": [0.8, 0.3, 0.2]}}
        ],
        "lights": [{"type": "point", "position": [0, 1.5, 0], "intensity": [5, 5, 5]}]
    })
    .to_string()
}

/// Uploads [`upload_scene`] at about `patches` patches as `id` to `addr` (a server, or
/// haproxy in front); the job id.
pub(crate) fn upload(addr: &str, id: &str, patches: u64) -> String {
    let scene = upload_scene();
    let boundary = "translux-slurm-test-boundary";
    let mut body = String::new();
    body.push_str(&format!(
        "--{boundary}\r\nContent-Disposition: form-data; name=\"scene\"; \
         filename=\"room.json\"\r\nContent-Type: application/json\r\n\r\n{scene}\r\n"
    ));
    for (k, v) in [("id", id.to_string()), ("patches", patches.to_string())] {
        body.push_str(&format!(
            "--{boundary}\r\nContent-Disposition: form-data; name=\"{k}\"\r\n\r\n{v}\r\n"
        ));
    }
    body.push_str(&format!("--{boundary}--\r\n"));
    let (status, answer) = request(
        addr,
        "POST",
        "/api/v1/scenes",
        &format!("multipart/form-data; boundary={boundary}"),
        body.as_bytes(),
    );
    assert_eq!(status, 202, "upload answered {status}: {answer}");
    let record: Value = serde_json::from_str(&answer).unwrap();
    record["id"].as_str().unwrap().to_string()
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub(crate) fn state_is(r: &Value, state: &str) -> bool {
    r["state"] == state
}

pub(crate) fn is_final(r: &Value) -> bool {
    ["done", "failed", "cancelled"]
        .iter()
        .any(|s| state_is(r, s))
}

/// Waits until Slurm lists the jobs of `job` (an array's tasks or its merge).
fn wait_listed(cluster: &Cluster, job: &str, limit: Duration) -> Vec<String> {
    let t0 = Instant::now();
    loop {
        let listed = cluster.jobs_named(&format!("translux-{job}"));
        if !listed.is_empty() {
            return listed;
        }
        assert!(
            t0.elapsed() < limit,
            "Slurm never listed job {job}: {}",
            cluster.logs()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// Follows job `job` through `addr` (a server, or haproxy in front) until it is final,
/// `limit` at most, noting the `squeue` lines Slurm lists under its name meanwhile: the
/// final record and those lines. `log` describes the servers for a failure.
pub(crate) fn follow_job(
    cluster: &Cluster,
    addr: &str,
    job: &str,
    limit: Duration,
    log: impl Fn() -> String,
) -> (Value, std::collections::BTreeSet<String>) {
    let mut seen = std::collections::BTreeSet::new();
    let t0 = Instant::now();
    loop {
        seen.extend(cluster.jobs_named(&format!("translux-{job}")));
        let (_, r) = get_json(addr, &format!("/api/v1/jobs/{job}"));
        if is_final(&r) {
            return (r, seen);
        }
        assert!(t0.elapsed() < limit, "job not done: {r}\n{}", log());
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// Slurm ran job `job` as an array of two shards and one merge: `seen` (from
/// [`follow_job`]) and what Slurm still keeps of the finished jobs (MinJobAge).
pub(crate) fn assert_array_and_merge(
    cluster: &Cluster,
    job: &str,
    mut seen: std::collections::BTreeSet<String>,
) {
    seen.extend(cluster.jobs_named(&format!("translux-{job}")));
    let ids: std::collections::BTreeSet<&str> = seen
        .iter()
        .filter_map(|l| l.split_whitespace().next())
        .collect();
    let shards: Vec<&&str> = ids
        .iter()
        .filter(|i| i.contains('_') && !i.contains('['))
        .collect();
    let plain: Vec<&&str> = ids.iter().filter(|i| !i.contains('_')).collect();
    assert_eq!(shards.len(), 2, "not two array tasks in Slurm: {seen:?}");
    assert_eq!(plain.len(), 1, "not one merge job in Slurm: {seen:?}");
}

#[test]
fn an_upload_runs_as_a_slurm_array_and_merge() {
    let _one = serial();
    precompute_bin();
    let cluster = Cluster::start();
    let bundles = tempfile::tempdir().unwrap();
    let server = Server::start(&cluster, bundles.path());
    let job = server.upload("room", 1500);
    let (record, seen) = follow_job(
        &cluster,
        &server.addr,
        &job,
        Duration::from_secs(60),
        || server.log(),
    );
    assert!(state_is(&record, "done"), "{record}\n{}", server.log());
    assert!(
        record["result"]["patches"].as_u64().unwrap() > 500,
        "{record}"
    );
    assert_array_and_merge(&cluster, &job, seen);
    let (status, scene) = server.get_json("/api/v1/scenes/room");
    assert_eq!(
        status,
        200,
        "the scene is not served: {scene}\n{}",
        server.log()
    );
    assert_only_whole_bundles(bundles.path(), &["room"]);
    let names = listing(bundles.path());
    assert!(
        !names.iter().any(|n| n.starts_with(".slurm-")),
        "the job's Slurm folder is left: {names:?}"
    );
}

/// Every entry of `dir`, sorted.
fn listing(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// Every non-hidden entry of `bundles` is one of `allowed` and a whole bundle: its manifest
/// and every array file it names, at its size.
pub(crate) fn assert_only_whole_bundles(bundles: &Path, allowed: &[&str]) {
    for name in listing(bundles).into_iter().filter(|n| !n.starts_with('.')) {
        assert!(
            allowed.contains(&name.as_str()),
            "{name} appeared in the bundles folder"
        );
        if let Err(e) = whole_bundle(&bundles.join(&name)) {
            panic!("{name} is not a whole bundle: {e}");
        }
    }
}

fn whole_bundle(dir: &Path) -> Result<(), String> {
    let text = std::fs::read_to_string(dir.join("manifest.json")).map_err(|e| e.to_string())?;
    let m: Value = serde_json::from_str(&text).map_err(|e| e.to_string())?;
    let arrays = m["arrays"].as_object().ok_or("no arrays in the manifest")?;
    for (name, a) in arrays {
        let file = a["file"].as_str().unwrap_or(name);
        let want = a["bytes"].as_u64().unwrap_or(0);
        let got = std::fs::metadata(dir.join(file))
            .map_err(|e| format!("{file}: {e}"))?
            .len();
        if got != want {
            return Err(format!("{file}: {got} bytes, the manifest says {want}"));
        }
    }
    Ok(())
}

#[test]
fn cancelling_a_job_cancels_it_in_slurm() {
    let _one = serial();
    precompute_bin();
    let cluster = Cluster::start();
    let bundles = tempfile::tempdir().unwrap();
    let server = Server::start(&cluster, bundles.path());
    let job = server.upload("big", 20_000);
    let listed = wait_listed(&cluster, &job, Duration::from_secs(20));
    let (status, _) = server.request("DELETE", &format!("/api/v1/jobs/{job}"), "text/plain", b"");
    assert_eq!(status, 200);
    let record = server.wait_job(&job, Duration::from_secs(40), is_final);
    assert!(state_is(&record, "cancelled"), "{record}\n{}", server.log());
    let active = cluster.run(
        "squeue",
        &[
            "--noheader",
            "--format=%i %T",
            "--name",
            &format!("translux-{job}"),
        ],
    );
    assert!(
        active.trim().is_empty(),
        "Slurm still runs the job: {active} (listed before: {listed:?})"
    );
    assert!(
        !bundles.path().join("big").exists(),
        "a cancelled job left a bundle"
    );
    assert!(
        !listing(bundles.path())
            .iter()
            .any(|n| n.starts_with(".slurm-")),
        "the cancelled job's Slurm folder is left"
    );
}

/// The pids of processes whose command line contains every one of `needles`.
fn pids_with(needles: &[&str]) -> Vec<i32> {
    let mut pids = Vec::new();
    for e in std::fs::read_dir("/proc").unwrap().flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<i32>() else {
            continue;
        };
        let Ok(cmdline) = std::fs::read(e.path().join("cmdline")) else {
            continue;
        };
        let cmdline = String::from_utf8_lossy(&cmdline).replace('\0', " ");
        if needles.iter().all(|n| cmdline.contains(n)) {
            pids.push(pid);
        }
    }
    pids
}

/// Waits for a process matching `needles` (30 s) and kills it with SIGKILL.
fn kill_9(needles: &[&str]) -> i32 {
    let t0 = Instant::now();
    loop {
        if let Some(&pid) = pids_with(needles).first() {
            let ok = Command::new("kill")
                .args(["-9", &pid.to_string()])
                .status()
                .unwrap();
            assert!(ok.success());
            return pid;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "no process {needles:?} ran"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Watches `bundles` every 20 ms until stopped: every non-hidden entry must be a whole
/// bundle named `scene`. Returns what went wrong.
fn watch_bundles(
    bundles: PathBuf,
    scene: &'static str,
) -> (
    Arc<std::sync::atomic::AtomicBool>,
    std::thread::JoinHandle<Vec<String>>,
) {
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let flag = stop.clone();
    let handle = std::thread::spawn(move || {
        let mut problems = Vec::new();
        while !flag.load(std::sync::atomic::Ordering::Relaxed) {
            for name in listing(&bundles)
                .into_iter()
                .filter(|n| !n.starts_with('.'))
            {
                if name != scene {
                    problems.push(format!("{name} appeared in the bundles folder"));
                } else if let Err(e) = whole_bundle(&bundles.join(&name)) {
                    problems.push(format!("{name} was seen half-made: {e}"));
                }
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        problems
    });
    (stop, handle)
}

#[test]
fn a_killed_shard_runs_again_or_fails_and_a_resubmission_completes() {
    let _one = serial();
    precompute_bin();
    let cluster = Cluster::start();
    let bundles = tempfile::tempdir().unwrap();
    let server = Server::start(&cluster, bundles.path());
    let (stop, watcher) = watch_bundles(bundles.path().to_path_buf(), "room");
    let patches = 6000;

    // kill -9 of a shard's translux-precompute: its task runs it again, the job ends done.
    let job = server.upload("room", patches);
    let staging = format!(".slurm-{job}/");
    kill_9(&["translux-precompute", "--shard", &staging]);
    let record = server.wait_job(&job, Duration::from_secs(60), is_final);
    assert!(state_is(&record, "done"), "{record}\n{}", server.log());
    let (status, _) = server.request("DELETE", "/api/v1/scenes/room", "text/plain", b"");
    assert_eq!(status, 200, "{}", server.log());

    // kill -9 of a shard's batch script: the task fails, the job is recorded failed with
    // the shard named, nothing is served; the same upload again completes.
    let job = server.upload("room", patches);
    let staging = format!(".slurm-{job}/");
    kill_9(&["slurm_script", &staging]);
    let record = server.wait_job(&job, Duration::from_secs(60), is_final);
    assert!(state_is(&record, "failed"), "{record}\n{}", server.log());
    let error = record["error"].as_str().unwrap_or_default();
    assert!(error.contains("shard"), "the error names no shard: {error}");
    assert!(
        !error.contains(&*bundles.path().to_string_lossy()) && !error.contains("/spool/"),
        "the error shows a server or node path: {error}"
    );
    assert!(
        !bundles.path().join("room").exists(),
        "a failed job left a bundle"
    );
    let job = server.upload("room", patches);
    let record = server.wait_job(&job, Duration::from_secs(60), is_final);
    assert!(state_is(&record, "done"), "{record}\n{}", server.log());
    let (status, _) = server.get_json("/api/v1/scenes/room");
    assert_eq!(status, 200);

    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let problems = watcher.join().unwrap();
    assert!(problems.is_empty(), "{problems:#?}");
}

#[test]
fn a_resimulation_runs_as_one_slurm_task() {
    let _one = serial();
    let bin = precompute_bin();
    let cluster = Cluster::start();
    let bundles = tempfile::tempdir().unwrap();
    let medium = |s: f32| {
        serde_json::json!({"type": "simulated", "sigma_s_prime": [s, s, s],
                           "sigma_a": [0.004, 0.008, 0.02], "eta": 1.0})
    };
    let work = tempfile::tempdir().unwrap();
    let scene = work.path().join("cube.json");
    let cube = serde_json::json!({"unit_mm": 1, "objects": [{"name": "cube",
        "mesh": {"shape": "box", "size": [20, 20, 20]}, "material": medium(0.5)}],
        "lights": [{"type": "directional", "direction": [0, -1, 0], "irradiance": [1, 1, 1]}]});
    std::fs::write(&scene, cube.to_string()).unwrap();
    let made = Command::new(&bin)
        .arg(&scene)
        .arg("--out")
        .arg(bundles.path().join("cube"))
        .args(["--patches", "200", "--quiet"])
        .output()
        .unwrap();
    assert!(
        made.status.success(),
        "{}",
        String::from_utf8_lossy(&made.stderr)
    );
    let server = Server::start(&cluster, bundles.path());
    let t0 = Instant::now();
    while server.get_json("/api/v1/scenes/cube").0 != 200 {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "cube never loaded: {}",
            server.log()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let body = serde_json::json!({"materials": {"cube": medium(1.0)}}).to_string();
    let (status, answer) = server.request(
        "POST",
        "/api/v1/scenes/cube/resimulate",
        "application/json",
        body.as_bytes(),
    );
    assert_eq!(status, 202, "{answer}\n{}", server.log());
    let job: Value = serde_json::from_str(&answer).unwrap();
    let job = job["id"].as_str().unwrap().to_string();
    let listed = wait_listed(&cluster, &job, Duration::from_secs(20));
    let record = server.wait_job(&job, Duration::from_secs(60), is_final);
    assert!(state_is(&record, "done"), "{record}\n{}", server.log());
    assert_eq!(record["stage"], "walks", "{record}");
    assert!(
        listed.iter().all(|l| !l.contains('_')),
        "a re-simulation ran as an array: {listed:?}"
    );
    let (_, detail) = server.get_json("/api/v1/scenes/cube");
    assert_eq!(
        detail["objects"][0]["material"]["sigma_s_prime"],
        serde_json::json!([1.0, 1.0, 1.0]),
        "the served scene is not the re-simulated one: {detail}"
    );
}
