//! Translucency preparation in the background: what a scene's first translucency change
//! would otherwise make and wait for (S's radial terms, on the CPU on both backends;
//! seconds on the benchmark's scenes, about two minutes on the paper's rose) is made
//! on one thread of its own, one scene at a time, on a rayon pool of half the cores so
//! relights keep the other half ([`translux_engine::scene::Scene::prepare_translucency`]).
//!
//! In: scenes (the engine's) queued by the server's state when they load or on their first request
//! ([`crate::config::PrepareWhen`]). Out: the scene's prepared state (`GET
//! /api/v1/scenes/{id}`'s `translucency`), a log line, and a call of the hook that charges
//! the memory budget ([`Preparer::set_hook`]).

use std::collections::HashSet;
use std::sync::mpsc::{Sender, channel};
use std::sync::{Arc, Mutex, OnceLock, Weak};

use translux_proto::api::PrepState;

use translux_engine::scene::Scene;

/// What runs after a scene is prepared: its id (the budget charges what it now holds).
pub type PreparedHook = Arc<dyn Fn(&str) + Send + Sync>;

/// The preparation queue. Dropping it ends the thread once the scene in hand is done.
#[derive(Default)]
pub struct Preparer {
    tx: Mutex<Option<Sender<Weak<Scene>>>>,
    /// Scenes queued or being prepared (by address), so repeated requests queue one once.
    queued: Arc<Mutex<HashSet<usize>>>,
    hook: Arc<OnceLock<PreparedHook>>,
}

impl std::fmt::Debug for Preparer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Preparer").finish_non_exhaustive()
    }
}

impl Preparer {
    /// Sets what runs after each scene is prepared (once; later calls are ignored).
    pub fn set_hook(&self, hook: PreparedHook) {
        let _ = self.hook.set(hook);
    }

    /// Queues `scene` unless it has nothing pending or is queued already. The queue holds
    /// it weakly: a scene evicted or replaced before its turn is not prepared.
    pub fn queue(&self, scene: &Arc<Scene>) {
        if scene.translucency().state != PrepState::Pending {
            return;
        }
        let key = Arc::as_ptr(scene) as usize;
        if !lock(&self.queued).insert(key) {
            return;
        }
        let mut tx = lock(&self.tx);
        let sender = tx.get_or_insert_with(|| self.start());
        if sender.send(Arc::downgrade(scene)).is_err() {
            lock(&self.queued).remove(&key);
            tracing::warn!(scene = %scene.id, "the translucency preparation thread is gone");
        }
    }

    /// The worker thread.
    fn start(&self) -> Sender<Weak<Scene>> {
        let (tx, rx) = channel::<Weak<Scene>>();
        let queued = self.queued.clone();
        let hook = self.hook.clone();
        let threads = std::thread::available_parallelism().map_or(1, |n| (n.get() / 2).max(1));
        let spawned = std::thread::Builder::new()
            .name("translucency-prep".into())
            .spawn(move || {
                // Half the cores; the global pool (every core) if this one cannot be made.
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .thread_name(|i| format!("translucency-prep-{i}"))
                    .build()
                    .map_err(|e| tracing::warn!("translucency preparation on every core: {e}"))
                    .ok();
                while let Ok(weak) = rx.recv() {
                    let key = weak.as_ptr() as usize;
                    if let Some(scene) = weak.upgrade() {
                        prepare_one(&scene, pool.as_ref());
                        if let Some(hook) = hook.get() {
                            hook(&scene.id);
                        }
                    }
                    lock(&queued).remove(&key);
                }
            });
        if let Err(e) = spawned {
            // The sender's receiver is dropped with the closure: queue() then logs each.
            tracing::warn!("cannot start the translucency preparation thread: {e}");
        }
        tx
    }
}

/// Prepares one scene, logging the outcome; a panic marks it failed (its first change then
/// makes what it needs itself).
fn prepare_one(scene: &Scene, pool: Option<&rayon::ThreadPool>) {
    let run = || scene.prepare_translucency();
    let done = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| match pool {
        Some(p) => p.install(run),
        None => run(),
    }));
    match done {
        Ok(p) if p.state == PrepState::Ready => tracing::info!(
            scene = %scene.id,
            on = p.on.as_deref().unwrap_or("?"),
            seconds = p.seconds.unwrap_or(0.0),
            mib = p.bytes.unwrap_or(0) as f64 / (1u64 << 20) as f64,
            "translucency changes prepared"
        ),
        Ok(p) => tracing::info!(scene = %scene.id, state = ?p.state, message = ?p.message,
            "translucency preparation ended"),
        Err(_) => {
            scene.prepare_failed("the preparation panicked (see the log)");
            tracing::warn!(scene = %scene.id, "translucency preparation panicked");
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}
