//! A team past one box, whole: munged, slurmctld and slurmd on this node
//! ([`crate::slurm::Cluster`]), two `translux-server --jobs slurm` over one bundles folder
//! ([`crate::slurm::Server`], with `--rescan-s 1`), and haproxy running docker/haproxy.cfg in
//! front of them ([`crate::balancer::start_haproxy`]). An upload through haproxy becomes a
//! Slurm job array of two shards plus a merge, followed through haproxy to `done`; the
//! bundle holds the same bytes as a one-box `translux-precompute` of the same scene and
//! settings; and both servers serve it (the one that did not run the job picks it up at its
//! next look at the folder): a relight asked of each server directly and of haproxy answers
//! 200 with the same bytes. Every daemon and process is stopped by its pid when the test
//! ends, also when it fails (their guards' `Drop`).

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use crate::balancer::{start_haproxy, unusual, wait_states};
use crate::slurm::{
    Cluster, Server, assert_array_and_merge, assert_only_whole_bundles, assert_same_files,
    follow_job, get_json, precompute_bin, serial, state_is, upload, upload_scene,
};

/// The upload's patch count: small enough for two cores, large enough for two real shards.
const PATCHES: u64 = 2000;

/// `POST /api/v1/scenes/room/relight` with the bundle's own lights on `addr`: the status and
/// the answer's bytes.
fn relight(rt: &tokio::runtime::Runtime, c: &reqwest::Client, addr: &str) -> (u16, Vec<u8>) {
    rt.block_on(async {
        let r = c
            .post(format!("http://{addr}/api/v1/scenes/room/relight"))
            .header("content-type", "application/json")
            .body("{}")
            .send()
            .await
            .unwrap_or_else(|e| panic!("relight on {addr}: {e}"));
        let status = r.status().as_u16();
        (status, r.bytes().await.unwrap().to_vec())
    })
}

#[test]
fn an_upload_through_haproxy_runs_on_slurm_and_both_servers_serve_the_same_bytes() {
    let _one = serial();
    let bin = precompute_bin();
    let t0 = Instant::now();
    let cluster = Cluster::start();
    let bundles = tempfile::tempdir().unwrap();
    let rescan = ["--rescan-s", "1"];
    let servers = [
        Server::start_with(&cluster, bundles.path(), &rescan),
        Server::start_with(&cluster, bundles.path(), &rescan),
    ];
    let haproxy = start_haproxy([&servers[0].addr, &servers[1].addr]);
    let logs = || {
        format!(
            "--- s1\n{}\n--- s2\n{}\n--- haproxy\n{:#?}\n{}",
            servers[0].log(),
            servers[1].log(),
            unusual(&haproxy.proc.log()),
            cluster.logs()
        )
    };
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(30))
        .build()
        .unwrap();
    rt.block_on(wait_states(
        &client,
        haproxy.stats,
        &[("s1", "UP"), ("s2", "UP")],
        Duration::from_secs(10),
    ));
    let started_s = t0.elapsed().as_secs_f64();

    // The upload and its job's routes go through haproxy (one server, by the fixed key).
    let front = format!("127.0.0.1:{}", haproxy.front);
    let t1 = Instant::now();
    let job = upload(&front, "room", PATCHES);
    let (record, seen) = follow_job(&cluster, &front, &job, Duration::from_secs(60), logs);
    assert!(state_is(&record, "done"), "{record}\n{}", logs());
    let slurm_s = t1.elapsed().as_secs_f64();
    assert_array_and_merge(&cluster, &job, seen);
    let accepted = format!("upload accepted job={job}");
    let ran: Vec<usize> = (0..2)
        .filter(|&i| servers[i].log().contains(&accepted))
        .collect();
    assert_eq!(
        ran.len(),
        1,
        "not one server ran job {job} (haproxy pins job routes to one): {}",
        logs()
    );
    assert!(
        servers[ran[0]].log().contains("submitted to Slurm"),
        "{}",
        logs()
    );
    assert_only_whole_bundles(bundles.path(), &["room"]);

    // The same scene and settings on one box, run as the Slurm tasks run it (from the
    // uploads folder, the scene as `JOB/room.json`, so the manifests' `source` agree).
    let t2 = Instant::now();
    let work = tempfile::tempdir().unwrap();
    std::fs::create_dir(work.path().join(&job)).unwrap();
    std::fs::write(work.path().join(&job).join("room.json"), upload_scene()).unwrap();
    let one = Command::new(&bin)
        .current_dir(work.path())
        .arg(Path::new(&job).join("room.json"))
        .arg("--out")
        .arg(work.path().join("one-box"))
        .args(["--patches", &PATCHES.to_string(), "--quiet"])
        .output()
        .unwrap();
    assert!(
        one.status.success(),
        "the one-box precompute failed: {}",
        String::from_utf8_lossy(&one.stderr)
    );
    let one_box_s = t2.elapsed().as_secs_f64();
    assert_same_files(&bundles.path().join("room"), &work.path().join("one-box"));

    // Both servers serve it: the one that ran the job at once, the other within a rescan.
    let deadline = Instant::now() + Duration::from_secs(15);
    for s in &servers {
        while get_json(&s.addr, "/api/v1/scenes/room").0 != 200 {
            assert!(
                Instant::now() < deadline,
                "{} never served the bundle: {}",
                s.addr,
                logs()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }
    let other = 1 - ran[0];
    assert!(
        servers[other].log().contains("\"room\" appeared"),
        "the server that did not run the job did not pick the bundle up from the folder: {}",
        servers[other].log()
    );
    let mut answers = Vec::new();
    for (name, addr) in [
        ("s1", servers[0].addr.as_str()),
        ("s2", servers[1].addr.as_str()),
        ("haproxy", front.as_str()),
    ] {
        let (status, bytes) = relight(&rt, &client, addr);
        assert_eq!(
            status,
            200,
            "relight on {name}: {}\n{}",
            String::from_utf8_lossy(&bytes),
            logs()
        );
        assert!(!bytes.is_empty(), "an empty relight from {name}");
        answers.push((name, bytes));
    }
    for (name, bytes) in &answers[1..] {
        assert!(
            *bytes == answers[0].1,
            "{name}'s relight differs from {}'s ({} and {} bytes)",
            answers[0].0,
            bytes.len(),
            answers[0].1.len()
        );
    }
    eprintln!(
        "daemons, servers and haproxy up: {started_s:.1} s; upload to done on Slurm \
         (2 shards and a merge, {PATCHES} patches): {slurm_s:.1} s; one box: {one_box_s:.1} s; \
         whole test: {:.1} s",
        t0.elapsed().as_secs_f64()
    );
}
