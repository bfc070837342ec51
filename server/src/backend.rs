//! The compute backend, chosen once at start-up: `--backend auto|gpu|cpu`.
//!
//! There is no process-wide backend: the server starts one and hands it to its
//! [`crate::AppState`], which opens every scene with it ([`crate::Scene::open_with`]); a
//! scene remembers its backend, so a relight of it runs there. It implements the engine's
//! [`translux_engine::backend::Backend`] trait, which the relight calls. Library users and
//! tests open scenes on the CPU ([`crate::Scene::open`]) or on a backend of their own, side
//! by side in one process.
//!
//! In: the choice, and per request a scene, its S (the bundle's or a material override's),
//! Bₑ and E. Out: the radiosity B from the device ([`crate::gpu`]), or `None`, which tells
//! the relight to compute on the CPU (the reference path, [`translux_engine::radiosity`]).
//!
//! - `cpu`: everything on the CPU.
//! - `auto` (default): a hardware adapter (discrete, integrated, virtual) if wgpu finds one;
//!   a software adapter (lavapipe/llvmpipe: a CPU in disguise, slower than the CPU backend)
//!   is passed over. Without one the server runs on the CPU and says why in its log and in
//!   `/healthz`.
//! - `gpu`: the best adapter there is, software included (`/healthz` then says `software`);
//!   none at all is a start-up error.
//!
//! A scene is uploaded once, when the server loads it or on its first solve (F, S, and the
//! vectors of the solve; bind groups and staging buffers made once and reused; T on the first
//! relight that uses it). A scene that does not fit — a row larger than one binding, the
//! device refusing memory, or more than the budget (`--gpu-memory-mib`) — is served from
//! the CPU, with a warning in the log and its reason in `/healthz`. The direct light (lamps
//! and environments) runs on the device in a whole relight ([`crate::gpu::relight`]); for
//! the other relights it stays on the CPU. A `full` relight with material overrides solves
//! on the device with S of those materials: uploaded from the CPU's S once per layout, then
//! each translucency change (a slider) writes its changed objects' rows there from their
//! radial terms ([`crate::gpu::sterms`]) and solves from the last answer on the device;
//! other components with overrides take the CPU's S and stages.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use serde::{Deserialize, Serialize};
use translux_engine::radiosity::{Rgb, SolveParams, SolveStats};

use crate::gpu::relight::DeviceRelight;
use crate::gpu::{
    AdapterSummary, DenseData, GpuContext, GpuDense, GpuError, GpuOptions, GpuSystem,
};
use translux_engine::backend::{DeviceAnswer, MaterialsAnswer, SceneRef, WithMaterials};
use translux_engine::sterms::STerms;

use crate::gpu::sterms::{ChangeCounts, MaterialsOnDevice, Rewrite};
use translux_engine::smatrix::OverrideMaterials;
use translux_engine::vertexrows::VertexRows;

/// `--backend` (`TRANSLUX_BACKEND`, the config file's `backend`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BackendChoice {
    /// A hardware GPU if there is one, else the CPU.
    #[default]
    Auto,
    /// The GPU (a software adapter too); an error without any adapter.
    Gpu,
    /// The CPU.
    Cpu,
}

/// Where a scene is served.
#[derive(Debug)]
enum Slot {
    Gpu(Arc<GpuScene>),
    Cpu(String),
}

/// One scene on the device: F and the bundle's S.
#[derive(Debug)]
struct GpuScene {
    base: GpuSystem,
    /// The bundle's transfer matrix R = T − S, uploaded on first use; `Err`: it did not fit
    /// (the CPU computes the product).
    transfer: Mutex<Option<Result<Arc<GpuDense>, String>>>,
    /// What the whole relight needs beside `base` (the occluder, the sample points; each
    /// route's colour rows and the system of K = P on the first relight that needs them),
    /// uploaded on the first one; `Err`: it did not fit (the engine's
    /// stages relight on the CPU and solve here).
    whole: Mutex<Option<Result<Arc<DeviceRelight>, String>>>,
    /// S of the last material overrides solved here, kept for the next translucency
    /// change, which writes its changed rows in place ([`MaterialsOnDevice`]).
    materials: Mutex<MaterialsSlot>,
}

/// S of the last material overrides on the device, and the layout of S that did not fit
/// (not tried again: each try would flatten and upload the objects' terms anew).
#[derive(Debug, Default)]
struct MaterialsSlot {
    on: Option<MaterialsOnDevice>,
    refused: Option<u64>,
}

impl GpuScene {
    fn bytes(&self) -> u64 {
        let t = match self.transfer.lock().ok().as_deref() {
            Some(Some(Ok(t))) => t.bytes(),
            _ => 0,
        };
        let w = match self.whole.lock().ok().as_deref() {
            Some(Some(Ok(w))) => w.bytes(),
            _ => 0,
        };
        let m = match self.materials.lock().ok().as_deref() {
            Some(MaterialsSlot { on: Some(m), .. }) => m.bytes(),
            _ => 0,
        };
        t + w + m + self.base.bytes()
    }

    /// The whole relight's buffers, uploaded on first use (a failure is logged once and
    /// kept: `None` from then on).
    fn whole(
        &self,
        ctx: &GpuContext,
        scene: SceneRef<'_>,
        rows: &VertexRows,
    ) -> Option<Arc<DeviceRelight>> {
        let mut slot = self.whole.lock().unwrap_or_else(|p| p.into_inner());
        if slot.is_none() {
            let made = DeviceRelight::new(ctx, &self.base, scene.bundle, rows);
            match &made {
                Ok(d) => tracing::info!(
                    scene = %scene.id,
                    "the whole relight runs on the GPU (direct light, solve, vertex colours):                      {} MiB more",
                    d.bytes() >> 20
                ),
                Err(e) => tracing::warn!(
                    scene = %scene.id,
                    "the direct light and the vertex colours stay on the CPU: {e}"
                ),
            }
            *slot = Some(made.map(Arc::new).map_err(|e| e.to_string()));
        }
        slot.as_ref().and_then(|r| r.as_ref().ok().cloned())
    }
}

/// The backend: a GPU context and its scenes, or the CPU. Cheap to clone.
#[derive(Debug, Clone)]
pub struct Backend {
    inner: Arc<Inner>,
}

#[derive(Debug)]
struct Inner {
    gpu: Option<GpuContext>,
    /// Why the CPU serves (backend `cpu`), or `None`.
    reason: Option<String>,
    /// By [`scene_key`]: the scene id and where it is served.
    scenes: Mutex<HashMap<String, (String, Slot)>>,
}

/// `/healthz`'s view of the backend.
#[derive(Debug, Clone, Serialize)]
pub struct BackendHealth {
    /// `gpu` or `cpu`.
    pub backend: String,
    /// The adapter in use (absent on the CPU backend).
    pub adapter: Option<AdapterSummary>,
    /// Why the CPU serves (absent on the GPU backend).
    pub reason: Option<String>,
    /// GPU bytes held by all scenes.
    pub gpu_bytes: u64,
    /// Scenes uploaded (or refused) so far.
    pub scenes: Vec<SceneBackend>,
}

/// One scene in [`BackendHealth`].
#[derive(Debug, Clone, Serialize)]
pub struct SceneBackend {
    pub id: String,
    /// `gpu` or `cpu`.
    pub on: String,
    pub gpu_bytes: u64,
    /// Why a scene of the GPU backend is served from the CPU.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

impl Backend {
    /// The CPU backend, with the reason it was chosen.
    pub fn cpu(reason: impl Into<String>) -> Backend {
        Backend {
            inner: Arc::new(Inner {
                gpu: None,
                reason: Some(reason.into()),
                scenes: Mutex::new(HashMap::new()),
            }),
        }
    }

    /// What the engine opens scenes with on this backend (with a new environment-map
    /// cache): `Scene::open_with(id, dir, &backend.resources())`.
    pub fn resources(&self) -> translux_engine::scene::Resources {
        translux_engine::scene::Resources::on(Arc::new(self.clone()))
    }

    /// A GPU backend on `ctx` (a translucency change's S is made on the CPU, and the solves
    /// with it run there).
    pub fn on_gpu(ctx: GpuContext) -> Backend {
        Backend {
            inner: Arc::new(Inner {
                gpu: Some(ctx),
                reason: None,
                scenes: Mutex::new(HashMap::new()),
            }),
        }
    }

    /// Starts the chosen backend (see the module docs). `auto` never fails; `gpu` fails when
    /// no adapter can be had. `memory_mib` caps the GPU memory all scenes may use
    /// (`--gpu-memory-mib`; without it, what the device grants).
    pub fn start(choice: BackendChoice, memory_mib: Option<u64>) -> Result<Backend, GpuError> {
        let mut opts = GpuOptions {
            allow_software: false,
            max_binding_bytes: None,
            budget_bytes: memory_mib.map(|m| m.saturating_mul(1 << 20)),
        };
        match choice {
            BackendChoice::Cpu => Ok(Backend::cpu("--backend cpu")),
            BackendChoice::Gpu => {
                opts.allow_software = true;
                Ok(Backend::on_gpu(GpuContext::new(&opts)?))
            }
            BackendChoice::Auto => match GpuContext::new(&opts) {
                Ok(ctx) => Ok(Backend::on_gpu(ctx)),
                Err(e) => Ok(Backend::cpu(format!("--backend auto: {e}"))),
            },
        }
    }

    /// `gpu` or `cpu`.
    pub fn name(&self) -> &'static str {
        if self.inner.gpu.is_some() {
            "gpu"
        } else {
            "cpu"
        }
    }

    /// The GPU context, when the backend is the GPU.
    pub fn gpu(&self) -> Option<&GpuContext> {
        self.inner.gpu.as_ref()
    }

    /// A line for the start-up log.
    pub fn describe(&self) -> String {
        match (&self.inner.gpu, &self.inner.reason) {
            (Some(ctx), _) => {
                let a = ctx.adapter();
                format!(
                    "backend gpu: {} ({}, {}{}), one binding holds {} MiB; translucency \
                     changes write S on the GPU",
                    a.name,
                    a.backend,
                    a.device_type,
                    if a.software {
                        ", a software adapter: it runs on the CPU"
                    } else {
                        ""
                    },
                    a.max_binding_bytes >> 20,
                )
            }
            (None, Some(r)) => format!("backend cpu: {r}"),
            (None, None) => "backend cpu".into(),
        }
    }

    /// The backend's state for `/healthz`.
    pub fn health(&self) -> BackendHealth {
        let scenes = self.inner.scenes.lock().unwrap_or_else(|p| p.into_inner());
        let mut list: Vec<SceneBackend> = scenes
            .iter()
            .map(|(_, (id, slot))| match slot {
                Slot::Gpu(g) => SceneBackend {
                    id: id.clone(),
                    on: "gpu".into(),
                    gpu_bytes: g.bytes(),
                    reason: None,
                },
                Slot::Cpu(r) => SceneBackend {
                    id: id.clone(),
                    on: "cpu".into(),
                    gpu_bytes: 0,
                    reason: Some(r.clone()),
                },
            })
            .collect();
        list.sort_by(|a, b| a.id.cmp(&b.id));
        BackendHealth {
            backend: self.name().into(),
            adapter: self.inner.gpu.as_ref().map(|g| g.adapter().clone()),
            reason: self.inner.reason.clone(),
            gpu_bytes: self.inner.gpu.as_ref().map_or(0, |g| g.used_bytes()),
            scenes: list,
        }
    }

    /// The GPU part of `/healthz`.
    pub fn gpu_health(&self) -> translux_proto::api::GpuHealth {
        use translux_proto::api::{GpuAdapter, GpuHealth, GpuScene};
        let h = self.health();
        GpuHealth {
            available: self.inner.gpu.is_some(),
            reason: h.reason,
            adapter: h.adapter.map(|a| GpuAdapter {
                name: a.name,
                backend: a.backend,
                device_type: a.device_type,
                software: a.software,
                max_binding_bytes: a.max_binding_bytes,
            }),
            bytes: h.gpu_bytes,
            scenes: h
                .scenes
                .into_iter()
                .map(|s| GpuScene {
                    id: s.id,
                    on: s.on,
                    bytes: s.gpu_bytes,
                    reason: s.reason,
                })
                .collect(),
        }
    }

    /// GPU bytes held for the scene `id` (0 when it is not on the device).
    pub fn scene_bytes(&self, id: &str) -> u64 {
        let scenes = self.inner.scenes.lock().unwrap_or_else(|p| p.into_inner());
        scenes
            .values()
            .filter(|(sid, _)| sid == id)
            .map(|(_, slot)| match slot {
                Slot::Gpu(g) => g.bytes(),
                Slot::Cpu(_) => 0,
            })
            .sum()
    }

    /// The scene's device state, uploading it on first use; `None` on the CPU backend or
    /// when the scene does not fit (then logged once and reported in `/healthz`).
    fn scene(&self, scene: SceneRef<'_>) -> Option<Arc<GpuScene>> {
        let ctx = self.inner.gpu.as_ref()?;
        let key = scene_key(scene);
        let mut scenes = self.inner.scenes.lock().unwrap_or_else(|p| p.into_inner());
        if let Some((_, slot)) = scenes.get(&key) {
            return match slot {
                Slot::Gpu(g) => Some(g.clone()),
                Slot::Cpu(_) => None,
            };
        }
        let b = &scene.bundle;
        let t = std::time::Instant::now();
        let made = GpuSystem::new(
            ctx,
            scene.id,
            &translux_engine::transport::Transport::of(b),
            &b.subsurface(),
            SolveParams::default().max_iterations.max(1000),
        );
        match made {
            Ok(sys) => {
                tracing::info!(
                    scene = %scene.id,
                    "uploaded to the GPU: {} MiB (F {} blocks, S {} blocks) in {:.0} ms",
                    sys.bytes() >> 20,
                    sys.matrices().0.blocks(),
                    sys.matrices().1.blocks(),
                    t.elapsed().as_secs_f64() * 1e3
                );
                let g = Arc::new(GpuScene {
                    base: sys,
                    transfer: Mutex::new(None),
                    whole: Mutex::new(None),
                    materials: Mutex::new(MaterialsSlot::default()),
                });
                scenes.insert(key, (scene.id.to_string(), Slot::Gpu(g.clone())));
                Some(g)
            }
            Err(e) => {
                tracing::warn!(scene = %scene.id, "served from the CPU: it does not fit on the GPU: {e}");
                scenes.insert(
                    key,
                    (
                        scene.id.to_string(),
                        Slot::Cpu(format!("does not fit on the GPU: {e}")),
                    ),
                );
                None
            }
        }
    }

    /// Solves B = Bₑ + S(E + F B) on the device for `scene` with the bundle's S. `None`:
    /// solve on the CPU (CPU backend, a material override's S, made and solved on the CPU, a
    /// scene that does not fit, or a device error, which is logged and moves the scene to the
    /// CPU).
    pub fn solve(
        &self,
        scene: SceneRef<'_>,
        over: Option<&Arc<OverrideMaterials>>,
        emission: &[Rgb],
        irradiance: &[Rgb],
        params: &SolveParams,
    ) -> Option<(Vec<Rgb>, SolveStats)> {
        let ctx = self.inner.gpu.as_ref()?;
        if over.is_some() {
            return None;
        }
        let g = self.scene(scene)?;
        let run = g
            .base
            .solve(ctx, emission, irradiance, params, None)
            .map(|(b, s)| (b, s.stats));
        match run {
            Ok(r) => Some(r),
            Err(e) => {
                self.fail(ctx, scene, "solve", &e);
                None
            }
        }
    }

    /// Moves a scene to the CPU after a device error (logged; its buffers go when the last
    /// request holding them ends).
    fn fail(&self, ctx: &GpuContext, scene: SceneRef<'_>, what: &str, e: &GpuError) {
        tracing::warn!(scene = %scene.id, "GPU {what} failed, the CPU takes over: {e}");
        let mut scenes = self.inner.scenes.lock().unwrap_or_else(|p| p.into_inner());
        let old = scenes.insert(
            scene_key(scene),
            (
                scene.id.to_string(),
                Slot::Cpu(format!("a GPU {what} failed: {e}")),
            ),
        );
        if let Some((_, Slot::Gpu(old))) = old {
            ctx.release(old.bytes());
        }
    }
}

/// A scene's identity on the device: its id and the checksums of F and S, so a bundle
/// replaced under the same id is uploaded anew.
fn scene_key(scene: SceneRef<'_>) -> String {
    let arrays = &scene.bundle.manifest().arrays;
    let sum = |name: &str| {
        arrays
            .get(name)
            .map_or("-", |a| a.xxh3.as_str())
            .to_string()
    };
    format!(
        "{}:{}:{}",
        scene.id,
        sum(translux_proto::bundle::arrays::FF_VAL),
        sum(translux_proto::bundle::arrays::S_VAL)
    )
}

/// The engine calls the device through this; each method declines (answers "on the CPU")
/// on the CPU backend and for scenes the device does not hold.
impl translux_engine::backend::Backend for Backend {
    fn name(&self) -> &'static str {
        Backend::name(self)
    }

    /// Uploads `scene` now (the server may call it at load; a solve does it otherwise).
    /// Returns whether the scene is on the device.
    fn prepare(&self, scene: SceneRef<'_>) -> bool {
        self.scene(scene).is_some()
    }

    /// y = R v with the bundle's stored transfer matrix R = T − S (f16, scaled per row and
    /// channel) for k right-hand sides (`[patch][k·3]`), one pass over R per 64 of them.
    /// `false`: compute it on the CPU (CPU backend, no T, T does not fit, device error).
    fn transfer_product(&self, scene: SceneRef<'_>, v: &[f32], k: usize, y: &mut [f32]) -> bool {
        let Some(ctx) = self.inner.gpu.as_ref() else {
            return false;
        };
        let Some(g) = self.scene(scene) else {
            return false;
        };
        let Some(t) = scene.bundle.transfer() else {
            return false;
        };
        let dense = {
            let mut slot = g.transfer.lock().unwrap_or_else(|p| p.into_inner());
            if slot.is_none() {
                let made = GpuDense::upload(
                    ctx,
                    &format!("{} T", scene.id),
                    t.n,
                    t.n,
                    DenseData::F16(t.bits),
                    Some(t.scale),
                );
                if let Err(e) = &made {
                    tracing::warn!(scene = %scene.id, "the transfer matrix stays on the CPU: {e}");
                }
                *slot = Some(made.map(Arc::new).map_err(|e| e.to_string()));
            }
            match slot.as_ref() {
                Some(Ok(d)) => d.clone(),
                _ => return false,
            }
        };
        match dense.multiply_interleaved(ctx, v, k, y) {
            Ok(()) => true,
            Err(e) => {
                self.fail(ctx, scene, "transfer product", &e);
                false
            }
        }
    }

    /// Solves (I − S F) x = rhs on the device for the k RGB systems of `rhs`
    /// (`[patch][k·3]`, the relight's batched layout) with the bundle's S (`over`, a material
    /// override's S, is solved on the CPU); one device solve per system. `warm` (same layout) starts each from a previous solution.
    /// `None`: solve on the CPU (see [`Backend::solve`]).
    fn solve_rhs(
        &self,
        scene: SceneRef<'_>,
        over: Option<&Arc<OverrideMaterials>>,
        rhs: &[f32],
        k: usize,
        params: &SolveParams,
        warm: Option<&[f32]>,
    ) -> Option<(Vec<f32>, SolveStats)> {
        let ctx = self.inner.gpu.as_ref()?;
        if over.is_some() {
            return None;
        }
        let g = self.scene(scene)?;
        let n = g.base.n();
        if k == 0 || rhs.len() != n * 3 * k {
            return None;
        }
        let run = |sys: &GpuSystem| -> Result<(Vec<f32>, SolveStats), GpuError> {
            let mut x = vec![0.0f32; rhs.len()];
            let mut total: Option<SolveStats> = None;
            for s in 0..k {
                let w = warm.filter(|w| w.len() == rhs.len()).map(|w| lane(w, k, s));
                let (b, st) = sys.solve_rhs(ctx, &lane(rhs, k, s), params, w.as_deref())?;
                put_lane(&mut x, k, s, &b);
                let st = st.stats;
                total = Some(match total {
                    None => st,
                    Some(t) => merge_stats(t, st),
                });
            }
            Ok((x, total.expect("k > 0")))
        };
        match run(&g.base) {
            Ok(r) => Some(r),
            Err(e) => {
                self.fail(ctx, scene, "solve", &e);
                None
            }
        }
    }

    /// The whole relights on the device ([`crate::gpu::relight`]): direct light, solve and
    /// vertex colours in one submission per batch of up to [`crate::gpu::kernels::BATCH`],
    /// from the last answer the device holds. `None`: the engine's stages (CPU backend, the
    /// scene or its relight buffers do not fit, a device error, which moves the scene to the
    /// CPU).
    fn relight(
        &self,
        scene: SceneRef<'_>,
        job: &translux_engine::backend::DeviceRelight<'_>,
    ) -> Option<Vec<DeviceAnswer>> {
        let ctx = self.inner.gpu.as_ref()?;
        let g = self.scene(scene)?;
        let whole = g.whole(ctx, scene, job.rows)?;
        if job.environment.iter().any(Option::is_some)
            && let Err(why) = whole.environment(ctx, scene.bundle)
        {
            tracing::debug!(scene = %scene.id, "environment relights on the CPU: {why}");
            return None;
        }
        let lights = (job.lights, job.environment);
        if let Err(why) = whole.route(ctx, &g.base, job.components, job.rows) {
            tracing::debug!(scene = %scene.id, "relights through the engine's stages: {why}");
            return None;
        }
        let how = (job.components, job.pixel);
        match whole.relight(ctx, &g.base, lights, job.params, how) {
            Ok(answers) => Some(
                answers
                    .into_iter()
                    .map(|a| DeviceAnswer {
                        radiance: a.radiance,
                        luminance: a.luminance,
                        stats: a.stats.stats,
                        submissions: a.stats.submissions,
                        bytes_up: a.stats.bytes_up,
                        bytes_down: a.stats.bytes_down,
                    })
                    .collect(),
            ),
            Err(e) => {
                self.fail(ctx, scene, "relight", &e);
                None
            }
        }
    }

    /// Solves with the relight's overridden materials on the device: S of their layout is
    /// uploaded once from the CPU's, and each later translucency change writes its changed
    /// objects' rows there from their radial terms ([`MaterialsOnDevice`]); each system
    /// solves from the answer the last one left. `None`: on the CPU (CPU backend, no radial
    /// terms yet, S does not fit, a device error, which is logged and leaves S to the CPU
    /// until the next layout).
    fn solve_materials(
        &self,
        scene: SceneRef<'_>,
        with: &WithMaterials<'_>,
        (e, be): (&[f32], &[f32]),
        k: usize,
        params: &SolveParams,
    ) -> Option<MaterialsAnswer> {
        let ctx = self.inner.gpu.as_ref()?;
        let g = self.scene(scene)?;
        let terms = scene.terms?;
        let n = g.base.n();
        if k == 0 || e.len() != n * 3 * k || be.len() != n * 3 * k {
            return None;
        }
        let t0 = std::time::Instant::now();
        let mut slot = g.materials.lock().unwrap_or_else(|p| p.into_inner());
        let counts = self.materials_s(ctx, (scene, terms), &g, &mut slot, with)?;
        let s_seconds = t0.elapsed().as_secs_f64();
        let on = slot.on.as_ref()?;
        let mut x = vec![0.0f32; e.len()];
        let (mut stats, mut counts) = (None::<SolveStats>, counts);
        for q in 0..k {
            let run = on
                .system
                .solve_from_last(ctx, &lane(be, k, q), &lane(e, k, q), params);
            let (b, st) = match run {
                Ok(r) => r,
                Err(err) => {
                    tracing::warn!(scene = %scene.id, "the device's solve with the relight's materials failed, the CPU takes over: {err}");
                    if let Some(m) = slot.on.take() {
                        m.release(ctx);
                    }
                    return None;
                }
            };
            put_lane(&mut x, k, q, &b);
            stats = Some(match stats {
                None => st.stats,
                Some(a) => merge_stats(a, st.stats),
            });
            counts.submissions += st.submissions;
            counts.bytes_up += st.bytes_up;
            counts.bytes_down += st.bytes_down;
        }
        let answer = MaterialsAnswer {
            x,
            stats: stats?,
            s_seconds,
            submissions: counts.submissions,
            bytes_up: counts.bytes_up,
            bytes_down: counts.bytes_down,
        };
        Some(answer)
    }
}

/// System `q` of the `k` stacked in `v` (`[patch][k·3]`, the relight's batched layout).
fn lane(v: &[f32], k: usize, q: usize) -> Vec<Rgb> {
    v.chunks_exact(3 * k)
        .map(|p| [p[3 * q], p[3 * q + 1], p[3 * q + 2]])
        .collect()
}

/// Writes `b` as system `q` of the `k` stacked in `x` ([`lane`]'s layout).
fn put_lane(x: &mut [f32], k: usize, q: usize, b: &[Rgb]) {
    for (p, v) in x.chunks_exact_mut(3 * k).zip(b) {
        p[3 * q..3 * q + 3].copy_from_slice(v);
    }
}

/// Two solves' stats as one batch's: the most iterations and the worst residual, the
/// products and seconds added.
fn merge_stats(a: SolveStats, b: SolveStats) -> SolveStats {
    SolveStats {
        iterations: a.iterations.max(b.iterations),
        products: a.products + b.products,
        residual: a.residual.max(b.residual),
        converged: a.converged && b.converged,
        warm: a.warm && b.warm,
        seconds: a.seconds + b.seconds,
        ..a
    }
}

impl Backend {
    /// Brings the device's S of `slot` to `with`'s materials: the changed objects' rows
    /// written in place where it holds their layout, else S uploaded afresh from the CPU's
    /// (the last one's memory given back first). What crossed the bus; `None` when S stays
    /// on the CPU (logged once per layout that does not fit).
    fn materials_s(
        &self,
        ctx: &GpuContext,
        (scene, terms): (SceneRef<'_>, &STerms),
        g: &GpuScene,
        slot: &mut MaterialsSlot,
        with: &WithMaterials<'_>,
    ) -> Option<ChangeCounts> {
        let m = with.materials;
        if let Some(on) = slot.on.as_mut().filter(|on| on.layout == m.layout) {
            match on.write(ctx, (scene, terms), &m.overrides) {
                Ok(c) => return Some(c),
                Err(Rewrite::Upload) => {}
                Err(Rewrite::Failed(e)) => {
                    tracing::warn!(scene = %scene.id, "a translucency change on the device failed, S is uploaded again: {e}");
                }
            }
        }
        if let Some(old) = slot.on.take() {
            old.release(ctx);
        }
        if slot.refused == Some(m.layout) {
            return None;
        }
        let s = (with.cpu)()?;
        match MaterialsOnDevice::upload(ctx, (scene, terms), &g.base, m, &s) {
            Ok(on) => {
                let bytes = on.bytes();
                tracing::info!(scene = %scene.id, "S of the relight's materials on the GPU ({} MiB): translucency changes write it there", bytes >> 20);
                slot.on = Some(on);
                // Everything it holds was written from the host.
                Some(ChangeCounts {
                    submissions: 0,
                    bytes_up: bytes,
                    bytes_down: 0,
                })
            }
            Err(e) => {
                tracing::warn!(scene = %scene.id, "S of the relight's materials stays on the CPU: {e}");
                slot.refused = Some(m.layout);
                None
            }
        }
    }
}
