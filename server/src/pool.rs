//! The relight worker pool: compute runs here, never on the async runtime.
//!
//! In: checked work ([`Work`]: a relight or render plan for one scene) from any number of
//! clients, through [`Pool::submit`]. Out: one answer per job on a oneshot channel.
//!
//! - **Bounded**: at most [`ServerParams::queue`] jobs wait; one more is refused at once with
//!   429 `queue_full` and a `Retry-After` estimated from the queue length and the recent
//!   compute time per job.
//! - **Fair**: each client (an `X-Client-Id` header, else the connection; a WebSocket stream
//!   is its own client) has its own FIFO, and workers take the clients in turn
//!   (round-robin), so one client's burst of 100 requests does not make everyone else wait
//!   behind it.
//! - **Batched**: a worker that takes a relight also takes the other queued relights of the
//!   same scene (from every client, up to [`ServerParams::max_batch`], and no more than a fair
//!   share of them when other workers are idle) and runs them with
//!   [`relight::run_batch`] — one multi-right-hand-side product instead of several.
//! - **Deadlines**: a job still queued [`ServerParams::deadline`] after it was accepted is
//!   answered 503 `deadline_exceeded` at its deadline (a reaper thread looks every 50 ms,
//!   so the answer does not wait for a worker to free up) instead of computed; a queued job
//!   whose client went away is dropped.
//! - **Shutdown**: [`Pool::close`] refuses new jobs; the workers finish every job already
//!   accepted, then exit ([`Pool::join`]).
//!
//! The workers are plain OS threads blocked on a condition variable; a panic inside a relight
//! is caught and answered 500 for its batch, and the worker lives on.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use tokio::sync::oneshot;

use crate::config::ServerParams;
use crate::error::AppError;
use crate::metrics::Metrics;
use translux_engine::picture::{self, RenderOutput, RenderPlan};
use translux_engine::relight::{self, RelightOutput, RelightPlan};
use translux_engine::scene::Scene;
use translux_engine::stop::{Stop, StopFlag};

/// What a job computes.
#[derive(Debug, Clone)]
pub enum Work {
    Relight(RelightPlan),
    Render(Box<RenderPlan>),
}

/// A job's answer.
#[derive(Debug)]
pub enum Done {
    Relight(RelightOutput),
    Render(Box<RenderOutput>),
}

/// Who asked: jobs of one client are served in order, clients in turn.
pub type ClientKey = String;

/// A finished job: the answer and how long it waited before computing started.
#[derive(Debug)]
pub struct Answer {
    pub result: Result<Done, AppError>,
    pub waited: Duration,
}

/// The receiving end of a submitted job: await it for the answer. Dropped before the
/// answer came (the client went away: its request's future or its stream was dropped), it
/// stops the job's long work ([`translux_engine::stop`]), so a lamp walk nobody waits for
/// ends within milliseconds instead of running for hours.
#[derive(Debug)]
pub struct Ticket {
    answer: oneshot::Receiver<Answer>,
    cancel: StopFlag,
    answered: bool,
}

impl std::future::Future for Ticket {
    type Output = Result<Answer, oneshot::error::RecvError>;
    fn poll(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Self::Output> {
        let polled = std::pin::Pin::new(&mut self.answer).poll(cx);
        if polled.is_ready() {
            self.answered = true;
        }
        polled
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        if !self.answered {
            self.cancel.set();
        }
    }
}

struct Job {
    scene: Arc<Scene>,
    work: Work,
    accepted: Instant,
    deadline: Instant,
    reply: oneshot::Sender<Answer>,
}

impl Job {
    /// Relights of one scene batch together (the scene's address is the key); renders
    /// run alone.
    fn batch_key(&self) -> Option<usize> {
        match self.work {
            Work::Relight(_) => Some(Arc::as_ptr(&self.scene) as usize),
            Work::Render(_) => None,
        }
    }
}

/// The waiting jobs: one FIFO per client, clients served in turn.
#[derive(Debug)]
struct Queue<J> {
    /// Each client's jobs, oldest first.
    per_client: HashMap<ClientKey, VecDeque<J>>,
    /// Clients with queued jobs, in the order they are served next.
    turn: VecDeque<ClientKey>,
    len: usize,
    /// Workers computing right now.
    busy: usize,
    closed: bool,
}

impl<J> Default for Queue<J> {
    fn default() -> Self {
        Queue {
            per_client: HashMap::new(),
            turn: VecDeque::new(),
            len: 0,
            busy: 0,
            closed: false,
        }
    }
}

impl<J> Queue<J> {
    fn push(&mut self, client: ClientKey, job: J) {
        let jobs = self.per_client.entry(client.clone()).or_default();
        if jobs.is_empty() {
            self.turn.push_back(client);
        }
        jobs.push_back(job);
        self.len += 1;
    }

    /// Removes and returns every queued job for which `expired` holds (each client's others
    /// keep their order).
    fn remove_where(&mut self, expired: impl Fn(&J) -> bool) -> Vec<J> {
        let mut out = Vec::new();
        for jobs in self.per_client.values_mut() {
            if !jobs.iter().any(&expired) {
                continue;
            }
            let (gone, kept): (VecDeque<J>, VecDeque<J>) =
                std::mem::take(jobs).into_iter().partition(|j| expired(j));
            out.extend(gone);
            *jobs = kept;
        }
        if !out.is_empty() {
            self.per_client.retain(|_, jobs| !jobs.is_empty());
            let per_client = &self.per_client;
            self.turn.retain(|c| per_client.contains_key(c));
            self.len -= out.len();
        }
        out
    }

    /// Takes the next client's oldest job; if it has a batch key, also queued jobs with the
    /// same key, clients in turn order and each client's oldest first, up to `max_batch` in
    /// all and at most ⌈matching / (idle workers + 1)⌉ so that idle workers get their share.
    /// `workers` counts every worker; `self.busy` the others computing now.
    fn take_batch(
        &mut self,
        max_batch: usize,
        workers: usize,
        key: impl Fn(&J) -> Option<usize>,
    ) -> Vec<J> {
        let Some(client) = self.turn.pop_front() else {
            return Vec::new();
        };
        let Some(jobs) = self.per_client.get_mut(&client) else {
            return Vec::new();
        };
        let Some(first) = jobs.pop_front() else {
            self.per_client.remove(&client);
            return Vec::new();
        };
        if jobs.is_empty() {
            self.per_client.remove(&client);
        } else {
            self.turn.push_back(client);
        }
        self.len -= 1;
        let wanted = key(&first);
        let mut batch = vec![first];
        let Some(wanted) = wanted else {
            return batch;
        };
        if max_batch <= 1 {
            return batch;
        }
        let matching = self
            .per_client
            .values()
            .flatten()
            .filter(|j| key(j) == Some(wanted))
            .count();
        let participants = workers.saturating_sub(self.busy + 1) + 1;
        let limit = (matching + 1).div_ceil(participants).min(max_batch);
        let order: Vec<ClientKey> = self.turn.iter().cloned().collect();
        for client in order {
            if batch.len() >= limit {
                break;
            }
            let Some(jobs) = self.per_client.get_mut(&client) else {
                continue;
            };
            let mut kept = VecDeque::with_capacity(jobs.len());
            while let Some(j) = jobs.pop_front() {
                if batch.len() < limit && key(&j) == Some(wanted) {
                    batch.push(j);
                } else {
                    kept.push_back(j);
                }
            }
            *jobs = kept;
            if jobs.is_empty() {
                self.per_client.remove(&client);
                self.turn.retain(|c| *c != client);
            }
        }
        self.len -= batch.len() - 1;
        batch
    }
}

struct Shared {
    queue: Mutex<Queue<Job>>,
    ready: Condvar,
    params: ServerParams,
    metrics: Metrics,
    /// Recent compute time per job in µs (an exponential moving average), for `Retry-After`.
    job_us: AtomicU64,
    /// Set by [`Pool::close`]: running jobs' long work stops (a server that is stopping
    /// does not wait for hours of lamp walks).
    closing: StopFlag,
}

/// The worker pool; cheap to clone (one `Arc`).
#[derive(Clone)]
pub struct Pool {
    shared: Arc<Shared>,
    threads: Arc<Mutex<Vec<JoinHandle<()>>>>,
}

impl std::fmt::Debug for Pool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pool")
            .field("params", &self.shared.params)
            .field("queued", &self.queued())
            .finish()
    }
}

impl Pool {
    /// Starts `params.workers` worker threads.
    pub fn new(params: ServerParams, metrics: Metrics) -> Pool {
        metrics.workers.set(params.workers as i64);
        metrics.queue_capacity.set(params.queue as i64);
        let shared = Arc::new(Shared {
            queue: Mutex::new(Queue::default()),
            ready: Condvar::new(),
            params,
            metrics,
            job_us: AtomicU64::new(0),
            closing: StopFlag::new(),
        });
        let mut threads: Vec<JoinHandle<()>> = (0..shared.params.workers)
            .map(|k| {
                let shared = shared.clone();
                std::thread::Builder::new()
                    .name(format!("relight-{k}"))
                    .spawn(move || worker(&shared))
                    .expect("cannot start a relight worker thread")
            })
            .collect();
        let reaping = shared.clone();
        threads.push(
            std::thread::Builder::new()
                .name("relight-deadlines".into())
                .spawn(move || reaper(&reaping))
                .expect("cannot start the relight deadline thread"),
        );
        Pool {
            shared,
            threads: Arc::new(Mutex::new(threads)),
        }
    }

    /// The settings the pool runs with.
    pub fn params(&self) -> &ServerParams {
        &self.shared.params
    }

    /// Jobs waiting.
    pub fn queued(&self) -> usize {
        lock(&self.shared.queue).len
    }

    /// Queues `work` for `client`. Refused at once with 429 `queue_full` (and a
    /// `Retry-After`) when the queue is full, 503 `shutting_down` after [`Pool::close`].
    pub fn submit(
        &self,
        scene: Arc<Scene>,
        mut work: Work,
        client: ClientKey,
    ) -> Result<Ticket, AppError> {
        let s = &self.shared;
        let (reply, answer) = oneshot::channel();
        let cancel = StopFlag::new();
        let stop = Stop::never().with(&cancel).with(&s.closing);
        match &mut work {
            Work::Relight(plan) => plan.stop = stop,
            Work::Render(plan) => plan.relight.stop = stop,
        }
        let ticket = Ticket {
            answer,
            cancel,
            answered: false,
        };
        let mut q = lock(&s.queue);
        if q.closed {
            return Err(AppError::shutting_down(
                "the server is shutting down and accepts no new relights",
            ));
        }
        if q.len >= s.params.queue {
            let (waiting, retry) = (q.len, retry_after(s, q.len));
            drop(q);
            s.metrics.outcome("rejected", 1);
            return Err(AppError::queue_full(
                format!(
                    "the relight queue is full ({} requests waiting, the limit is {}); retry \
                     after {retry} s",
                    waiting, s.params.queue
                ),
                retry,
            ));
        }
        let now = Instant::now();
        let job = Job {
            scene,
            work,
            accepted: now,
            deadline: now + s.params.deadline,
            reply,
        };
        q.push(client, job);
        s.metrics.queue_depth.set(q.len as i64);
        drop(q);
        s.ready.notify_one();
        Ok(ticket)
    }

    /// [`Pool::submit`], then waits for the answer.
    pub async fn run(
        &self,
        scene: Arc<Scene>,
        work: Work,
        client: ClientKey,
    ) -> Result<Answer, AppError> {
        let ticket = self.submit(scene, work, client)?;
        ticket
            .await
            .map_err(|_| AppError::internal("a relight worker stopped without answering"))
    }

    /// Seconds a client should wait with `queued` jobs ahead of it (see the private `retry_after`).
    pub fn retry_after(&self, queued: usize) -> u64 {
        retry_after(&self.shared, queued)
    }

    /// Stops the long work (lamp walks) of every job, running or to come, which is answered
    /// 503 `cancelled`; other work goes on. The server calls it when its stop begins, so
    /// that no request in flight holds the stop for hours.
    pub fn stop_long_work(&self) {
        self.shared.closing.set();
    }

    /// Refuses new jobs from now on; queued and running jobs still finish, but their long
    /// work stops ([`Pool::stop_long_work`]).
    pub fn close(&self) {
        self.stop_long_work();
        lock(&self.shared.queue).closed = true;
        self.shared.ready.notify_all();
    }

    /// Closes the pool and waits until the workers have finished every accepted job and
    /// exited. Blocking: call it from a blocking thread.
    pub fn join(&self) {
        self.close();
        let threads = std::mem::take(&mut *lock(&self.threads));
        for t in threads {
            let _ = t.join();
        }
    }
}

/// Locks, recovering from poisoning (a panic while holding the queue lock cannot leave it
/// inconsistent: every mutation is a few lines without panicking calls).
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A worker: takes the next client's next job (plus same-scene relights to batch with it),
/// answers it, repeats; exits once the pool is closed and the queue empty.
fn worker(s: &Shared) {
    loop {
        let batch = {
            let mut q = lock(&s.queue);
            while q.len == 0 {
                if q.closed {
                    return;
                }
                q = s.ready.wait(q).unwrap_or_else(|e| e.into_inner());
            }
            let batch = q.take_batch(s.params.max_batch, s.params.workers, Job::batch_key);
            q.busy += 1;
            s.metrics.queue_depth.set(q.len as i64);
            batch
        };
        process(s, batch);
        lock(&s.queue).busy -= 1;
    }
}

/// Answers a job that waited past its deadline with 503 `deadline_exceeded`, `queued`
/// jobs still waiting.
fn answer_expired(s: &Shared, job: Job, waited: Duration, queued: usize) {
    s.metrics.outcome("deadline", 1);
    let retry = retry_after(s, queued);
    let _ = job.reply.send(Answer {
        result: Err(AppError::deadline_exceeded(
            format!(
                "the request waited {} ms in the queue, past the server's deadline of {} ms, \
                 and was not computed; the server is overloaded, retry later",
                waited.as_millis(),
                s.params.deadline.as_millis()
            ),
            retry,
        )),
        waited,
    });
}

/// How often the reaper looks for queued jobs past their deadline.
const REAP_EVERY: Duration = Duration::from_millis(50);

/// The reaper: answers queued jobs at their deadline while every worker is busy (a worker
/// would only see them when it frees up, minutes later behind a long job), and drops those
/// whose client went away. Exits once the pool is closed and its queue empty.
fn reaper(s: &Shared) {
    loop {
        let (expired, queued) = {
            let mut q = lock(&s.queue);
            if q.closed && q.len == 0 {
                return;
            }
            let now = Instant::now();
            let expired = q.remove_where(|j| now > j.deadline || j.reply.is_closed());
            if !expired.is_empty() {
                s.metrics.queue_depth.set(q.len as i64);
            }
            (expired, q.len)
        };
        let now = Instant::now();
        for job in expired {
            if job.reply.is_closed() {
                s.metrics.outcome("cancelled", 1);
            } else {
                let waited = now - job.accepted;
                answer_expired(s, job, waited, queued);
            }
        }
        std::thread::sleep(REAP_EVERY);
    }
}

/// Answers a batch: drops jobs whose client is gone, refuses expired ones, computes the
/// rest (relights of one scene together), and records the metrics.
fn process(s: &Shared, batch: Vec<Job>) {
    let m = &s.metrics;
    let now = Instant::now();
    let mut live = Vec::with_capacity(batch.len());
    for job in batch {
        let waited = now - job.accepted;
        if job.reply.is_closed() {
            m.outcome("cancelled", 1);
        } else if now > job.deadline {
            let queued = lock(&s.queue).len;
            answer_expired(s, job, waited, queued);
        } else {
            m.queue_wait.observe(waited.as_secs_f64());
            live.push((job, waited));
        }
    }
    if live.is_empty() {
        return;
    }
    let n = live.len();
    m.in_flight.add(n as i64);
    m.batch_size.observe(n as f64);
    let t = Instant::now();
    let scene = live[0].0.scene.clone();
    let results: Vec<Result<Done, AppError>> = match &live[0].0.work {
        Work::Relight(_) => {
            let plans: Vec<RelightPlan> = live
                .iter()
                .map(|(j, _)| match &j.work {
                    Work::Relight(p) => p.clone(),
                    Work::Render(_) => unreachable!("a batch holds relights of one scene"),
                })
                .collect();
            guarded(n, || {
                relight::run_batch(&scene, &plans)
                    .into_iter()
                    .map(|r| r.map_err(AppError::from))
                    .collect()
            })
            .into_iter()
            .map(|r| r.map(Done::Relight))
            .collect()
        }
        Work::Render(plan) => guarded(1, || {
            vec![picture::run(&scene, plan).map_err(AppError::from)]
        })
        .into_iter()
        .map(|r| r.map(|o| Done::Render(Box::new(o))))
        .collect(),
    };
    let elapsed = t.elapsed();
    m.compute.observe(elapsed.as_secs_f64());
    m.in_flight.sub(n as i64);
    // Moving average of the time per job, weight 1/4 for the newest batch.
    let per_job = (elapsed.as_micros() as u64 / n as u64).max(1);
    let old = s.job_us.load(Ordering::Relaxed);
    let avg = if old == 0 {
        per_job
    } else {
        (3 * old + per_job) / 4
    };
    s.job_us.store(avg, Ordering::Relaxed);
    for ((job, waited), result) in live.into_iter().zip(results) {
        match &result {
            Ok(Done::Relight(o)) => {
                m.outcome("ok", 1);
                m.relit(&o.stats);
            }
            Ok(Done::Render(o)) => {
                m.outcome("ok", 1);
                m.relit(&o.stats);
            }
            Err(_) => m.outcome("failed", 1),
        }
        let _ = job.reply.send(Answer { result, waited });
    }
}

/// The queue's estimated compute time over the workers, in whole seconds, at least 1: the
/// moving average time per job × `queued` / workers.
fn retry_after(s: &Shared, queued: usize) -> u64 {
    let per_job = s.job_us.load(Ordering::Relaxed) as f64 * 1e-6;
    let secs = queued.max(1) as f64 * per_job / s.params.workers as f64;
    (secs.ceil() as u64).clamp(1, 3600)
}

/// Runs `f`, turning a panic into a 500 for each of the `n` jobs (and a logged error), and a
/// wrong number of answers into 500s too.
fn guarded<T>(n: usize, f: impl FnOnce() -> Vec<Result<T, AppError>>) -> Vec<Result<T, AppError>> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(results) if results.len() == n => results,
        Ok(results) => {
            let msg = format!(
                "the relight batch answered {} results for {n} requests",
                results.len()
            );
            tracing::error!("{msg}");
            (0..n)
                .map(|_| Err(AppError::internal(msg.clone())))
                .collect()
        }
        Err(panic) => {
            let what = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "a panic".to_string());
            tracing::error!("a relight panicked: {what}");
            (0..n)
                .map(|_| {
                    Err(AppError::internal(format!(
                        "the relight failed inside the server ({what})"
                    )))
                })
                .collect()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A job named `(client, n)` with a batch key.
    type Fake = (&'static str, u32, Option<usize>);

    fn queue(jobs: &[Fake]) -> Queue<Fake> {
        let mut q = Queue::default();
        for &j in jobs {
            q.push(j.0.to_string(), j);
        }
        q
    }

    fn names(batch: &[Fake]) -> Vec<String> {
        batch.iter().map(|j| format!("{}{}", j.0, j.1)).collect()
    }

    #[test]
    fn clients_take_turns_and_each_clients_jobs_stay_in_order() {
        let mut q = queue(&[
            ("a", 1, None),
            ("a", 2, None),
            ("a", 3, None),
            ("a", 4, None),
            ("b", 1, None),
            ("b", 2, None),
            ("c", 1, None),
        ]);
        let mut order = Vec::new();
        while q.len > 0 {
            let batch = q.take_batch(32, 1, |j| j.2);
            assert_eq!(batch.len(), 1);
            order.extend(names(&batch));
        }
        assert_eq!(order, ["a1", "b1", "c1", "a2", "b2", "a3", "a4"]);
        assert!(q.per_client.is_empty() && q.turn.is_empty());
        // A client that comes back after its queue emptied goes to the end of the turn.
        q.push("b".into(), ("b", 3, None));
        q.push("a".into(), ("a", 5, None));
        assert_eq!(names(&q.take_batch(1, 1, |j| j.2)), ["b3"]);
    }

    #[test]
    fn relights_of_one_scene_are_batched_across_clients() {
        let mut q = queue(&[
            ("a", 1, Some(7)),
            ("a", 2, Some(8)),
            ("a", 3, Some(7)),
            ("b", 1, Some(7)),
            ("c", 1, None),
        ]);
        let batch = q.take_batch(32, 1, |j| j.2);
        assert_eq!(names(&batch), ["a1", "b1", "a3"]);
        assert_eq!(q.len, 2);
        assert_eq!(names(&q.take_batch(32, 1, |j| j.2)), ["c1"]);
        assert_eq!(names(&q.take_batch(32, 1, |j| j.2)), ["a2"]);
        assert_eq!(q.len, 0);
        // Renders (no key) never batch; max_batch 1 turns batching off.
        let mut q = queue(&[("a", 1, Some(7)), ("b", 1, Some(7)), ("b", 2, Some(7))]);
        assert_eq!(names(&q.take_batch(1, 1, |j| j.2)), ["a1"]);
        assert_eq!(names(&q.take_batch(2, 1, |j| j.2)), ["b1", "b2"]);
    }

    #[test]
    fn expired_jobs_leave_the_queue_and_the_rest_keep_their_turns() {
        let mut q = queue(&[
            ("a", 1, None),
            ("a", 2, None),
            ("b", 1, None),
            ("c", 1, None),
            ("c", 2, None),
        ]);
        let gone = q.remove_where(|j| j.1 == 1 && j.0 != "c");
        let mut gone = names(&gone);
        gone.sort();
        assert_eq!(gone, ["a1", "b1"]);
        assert_eq!(q.len, 3);
        assert!(!q.per_client.contains_key("b") && !q.turn.contains(&"b".to_string()));
        let mut order = Vec::new();
        while q.len > 0 {
            order.extend(names(&q.take_batch(1, 1, |j| j.2)));
        }
        assert_eq!(order, ["a2", "c1", "c2"]);
        assert!(q.remove_where(|_| true).is_empty());
    }

    #[test]
    fn idle_workers_get_their_share_of_a_batch() {
        let jobs: Vec<Fake> = (0..8)
            .map(|k| (["a", "b", "c", "d"][k % 4], k as u32, Some(1)))
            .collect();
        // Two workers, none busy: the first takes half.
        let mut q = queue(&jobs);
        assert_eq!(q.take_batch(32, 2, |j| j.2).len(), 4);
        q.busy = 1;
        assert_eq!(q.take_batch(32, 2, |j| j.2).len(), 4);
        // The cap applies too.
        let mut q = queue(&jobs);
        assert_eq!(q.take_batch(3, 1, |j| j.2).len(), 3);
        assert_eq!(q.len, 5);
    }
}
