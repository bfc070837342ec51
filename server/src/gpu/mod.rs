//! The wgpu compute backend: the relight's matrix work on a GPU, and whole relights.
//!
//! In: a bundle's sparse F and S (CSR, [`translux_proto::csr`]), a dense transfer matrix T
//! when one is given, the occluder triangles, the colour rows and the environment
//! visibility, and per request the direct irradiance E and emission Bₑ, or the lamps and
//! environments' bin radiance of one relight or a batch. Out: the
//! radiosity B = Bₑ + S(E + F B) from a minimal-residual Jacobi solve that runs on the
//! device, the vertex
//! colours of whole relights ([`relight`]), or the products T X for a batch of up to 64
//! right-hand sides in one pass over T.
//!
//! | kernel (`kernels/*.wgsl`) | work | CPU twin ([`cpu_twin`]) |
//! | --- | --- | --- |
//! | `csr_spmv_rgb` | y = A x, A CSR with f32 (F) or RGB (S) values, 32 threads a row, for 1 or [`kernels::BATCH`] vectors per read of A | same name |
//! | `dense_matmul_rgb` | Y = T X, T dense f16/f32 RGB, k ≤ 64 vectors per pass | same name |
//! | `jacobi_update` | x ← b + S F x, Σ‖r‖² per workgroup, for each system of a batch (the solve's right-hand side b = Bₑ + S E, ‖b‖²) | same name |
//! | `mr_step` | the minimal-residual step by `STAGE`: r = b + S F x − x; ⟨r, v⟩ and ⟨v, v⟩ per channel and workgroup (v = S F r − r); x ← x + α r, r ← r + α v with Σ‖r‖² | same name |
//! | `mr_alpha` | α = clamp(−⟨r, v⟩/⟨v, v⟩, 0.1, 1.9) per system and channel from `mr_step`'s partials (one workgroup) | same name |
//! | `reduce_sum` | appends each system's Σ of the partials to a residual history; stops the iterations once all meet the tolerance | `reduce_sum`, `reduce_stop` |
//! | `shadow_rays` | one occluded flag per ray, any-hit walk of the occluder BVH | same name |
//! | `direct_light` | shadowed direct irradiance E per surface point (point, spot, directional) | same name |
//! | `env_irradiance` | an environment's E_i = Σ_k V_ik L̄_k from the bundle's f16 visibility, added to E | same name |
//! | `vertex_colours` | B/π per vertex from B, E (less its environment part), ρ and E at the vertex (`translux_engine::vertexrows`) | same name |
//! | `s_terms` | a translucency change: one object's rows of S from its radial terms by `STAGE` (values, column sums, node sums, scaling by the energy bound's factors) | `translux_engine::sterms::ObjectTerms::write` |
//!
//! `shadow_rays` and `direct_light` share one traversal source, `bvh_traverse.wgsl`, put in
//! front of each at compile time.
//!
//! Layout: [`GpuContext`] acquires the adapter and device once and compiles the kernels
//! ([`kernels`]); [`matrix`] uploads matrices, split into row blocks that each fit one storage
//! binding (the adapter's real limit, or a smaller forced one for tests); [`system`] holds one
//! scene's buffers and bind groups, built once and reused by every request (one set of
//! vectors per solve, one more for batches); [`direct`] holds the occluder BVH on the device
//! and the direct-light dispatch; [`environment`] the visibility and the environments'
//! pass; [`sterms`] an object's radial terms and the write of its rows of S on a
//! translucency change; [`relight`] puts direct light, solve and colours in one submission. A solve is one submission and one read-back (the counter, the residual
//! history and the answer); the stopping rule runs on the device ([`system`]).

pub mod cpu_twin;
pub mod direct;
pub mod environment;
pub mod kernels;
pub mod matrix;
pub mod relight;
pub mod sterms;
pub mod system;

use std::sync::{Arc, Mutex};

use thiserror::Error;

pub use cpu_twin::DenseData;
pub use matrix::{GpuCsr, GpuDense};
pub use system::{GpuSolveStats, GpuSystem};

/// Why the GPU cannot do something.
#[derive(Debug, Error)]
pub enum GpuError {
    #[error("no GPU adapter found (wgpu backends tried: {backends}); {hint}")]
    NoAdapter { backends: String, hint: String },
    #[error(
        "only software adapters found ({found}); they run on the CPU and are slower than the \
         CPU backend — pass --backend gpu to use one anyway"
    )]
    OnlySoftware { found: String },
    #[error("requesting a device from {adapter} failed: {error}")]
    Device { adapter: String, error: String },
    #[error(
        "{what}: one row needs {requested} bytes but one storage binding holds at most \
         {max_binding} bytes"
    )]
    MatrixTooLarge {
        what: String,
        requested: u64,
        max_binding: u64,
    },
    #[error("{what} needs {requested} bytes of GPU memory; the budget left is {available} bytes")]
    OutOfBudget {
        what: String,
        requested: u64,
        available: u64,
    },
    #[error("the GPU reported an error: {0}")]
    Reported(String),
    #[error("reading a result back from the GPU failed: {0}")]
    Readback(String),
    #[error("{0}")]
    Invalid(String),
}

/// How to pick and use the adapter.
#[derive(Debug, Clone, Copy, Default)]
pub struct GpuOptions {
    /// Accept a software (CPU-type) adapter such as lavapipe/llvmpipe.
    pub allow_software: bool,
    /// Cap one matrix buffer below the adapter's binding limit (tests force tiling with it).
    pub max_binding_bytes: Option<u64>,
    /// GPU memory the scenes may use in all, in bytes; `None`: no budget beyond what the
    /// device refuses (wgpu does not report a device's memory size).
    pub budget_bytes: Option<u64>,
}

/// What the server reports about the adapter.
#[derive(Debug, Clone, serde::Serialize)]
pub struct AdapterSummary {
    pub name: String,
    pub backend: String,
    /// `discrete`, `integrated`, `virtual`, `cpu` or `other`.
    pub device_type: String,
    pub driver: String,
    /// A CPU-type adapter (lavapipe, llvmpipe): correct but no faster than the CPU backend.
    pub software: bool,
    pub max_binding_bytes: u64,
    pub max_buffer_bytes: u64,
}

/// The device, its queue and the compiled kernels; one per process, shared by every scene.
#[derive(Debug)]
pub struct GpuContext {
    pub(crate) device: wgpu::Device,
    pub(crate) queue: wgpu::Queue,
    pub(crate) kernels: kernels::Kernels,
    summary: AdapterSummary,
    /// The largest single matrix buffer: min(binding limit, buffer limit, forced cap).
    tile_bytes: u64,
    budget: Option<u64>,
    used: Mutex<u64>,
    /// Errors the device reported outside an error scope (logged, and failed on next check).
    uncaptured: Arc<Mutex<Vec<String>>>,
}

fn device_type_name(t: wgpu::DeviceType) -> &'static str {
    match t {
        wgpu::DeviceType::DiscreteGpu => "discrete",
        wgpu::DeviceType::IntegratedGpu => "integrated",
        wgpu::DeviceType::VirtualGpu => "virtual",
        wgpu::DeviceType::Cpu => "cpu",
        wgpu::DeviceType::Other => "other",
    }
}

/// Preference among adapters: hardware first (discrete, integrated, virtual, other), CPU last.
fn rank(t: wgpu::DeviceType) -> u8 {
    match t {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    }
}

impl GpuContext {
    /// Picks the best adapter of the backends `WGPU_BACKEND` allows (all by default) and
    /// requests a device with the adapter's own limits (not WebGPU's defaults: the matrices
    /// need the largest bindings the hardware has).
    pub fn new(opts: &GpuOptions) -> Result<GpuContext, GpuError> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
        // Refuse allocations near the driver's memory budget (an error, not a lost device).
        desc.memory_budget_thresholds.for_resource_creation = Some(90);
        let backends = desc.backends;
        let instance = wgpu::Instance::new(desc);
        let adapters = pollster::block_on(instance.enumerate_adapters(backends));
        let mut best: Option<wgpu::Adapter> = None;
        for a in adapters {
            let t = a.get_info().device_type;
            if best
                .as_ref()
                .is_none_or(|b| rank(t) < rank(b.get_info().device_type))
            {
                best = Some(a);
            }
        }
        let Some(adapter) = best else {
            return Err(GpuError::NoAdapter {
                backends: format!(
                    "{:?}",
                    backends & wgpu::Instance::enabled_backend_features()
                ),
                hint: "install a Vulkan driver (on Debian without a GPU: apt-get install \
                       mesa-vulkan-drivers libvulkan1 for the lavapipe software adapter)"
                    .into(),
            });
        };
        let info = adapter.get_info();
        let software = info.device_type == wgpu::DeviceType::Cpu;
        if software && !opts.allow_software {
            return Err(GpuError::OnlySoftware {
                found: format!("{} ({:?})", info.name, info.backend),
            });
        }
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("translux"),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device {
            adapter: info.name.clone(),
            error: e.to_string(),
        })?;
        let uncaptured = Arc::new(Mutex::new(Vec::new()));
        let sink = uncaptured.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            tracing::error!("GPU error: {e}");
            if let Ok(mut v) = sink.lock() {
                v.push(e.to_string());
            }
        }));
        let mut tile_bytes = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        if let Some(cap) = opts.max_binding_bytes {
            tile_bytes = tile_bytes.min(cap.max(64));
        }
        // Bindings are sized in multiples of 4 bytes.
        tile_bytes &= !3;
        let kernels = kernels::Kernels::new(&device);
        let summary = AdapterSummary {
            name: info.name.clone(),
            backend: format!("{:?}", info.backend).to_lowercase(),
            device_type: device_type_name(info.device_type).into(),
            driver: format!("{} {}", info.driver, info.driver_info)
                .trim()
                .to_string(),
            software,
            max_binding_bytes: limits.max_storage_buffer_binding_size,
            max_buffer_bytes: limits.max_buffer_size,
        };
        Ok(GpuContext {
            device,
            queue,
            kernels,
            summary,
            tile_bytes,
            budget: opts.budget_bytes,
            used: Mutex::new(0),
            uncaptured,
        })
    }

    /// The adapter in use.
    pub fn adapter(&self) -> &AdapterSummary {
        &self.summary
    }

    /// The largest matrix buffer this context makes (bytes).
    pub fn tile_bytes(&self) -> u64 {
        self.tile_bytes
    }

    /// GPU bytes held by everything uploaded through this context.
    pub fn used_bytes(&self) -> u64 {
        self.used.lock().map(|u| *u).unwrap_or(0)
    }

    /// Reserves `bytes` of the budget for `what`, or says why not.
    pub(crate) fn reserve(&self, what: &str, bytes: u64) -> Result<(), GpuError> {
        let mut used = self
            .used
            .lock()
            .map_err(|_| GpuError::Invalid("GPU memory accounting lock poisoned".into()))?;
        if let Some(budget) = self.budget
            && *used + bytes > budget
        {
            return Err(GpuError::OutOfBudget {
                what: what.into(),
                requested: bytes,
                available: budget.saturating_sub(*used),
            });
        }
        *used += bytes;
        Ok(())
    }

    /// Returns `bytes` to the budget (a scene's buffers were dropped).
    pub(crate) fn release(&self, bytes: u64) {
        if let Ok(mut used) = self.used.lock() {
            *used = used.saturating_sub(bytes);
        }
    }

    /// Fails with the first error the device reported outside an error scope since the last
    /// check.
    pub(crate) fn check_uncaptured(&self) -> Result<(), GpuError> {
        if let Ok(mut v) = self.uncaptured.lock()
            && let Some(e) = v.first().cloned()
        {
            v.clear();
            return Err(GpuError::Reported(e));
        }
        Ok(())
    }

    /// Runs `f` inside out-of-memory and validation error scopes; an error the device reports
    /// for the work `f` created becomes `Err`.
    pub(crate) fn scoped<T>(&self, f: impl FnOnce() -> Result<T, GpuError>) -> Result<T, GpuError> {
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let val = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let out = f();
        let val = pollster::block_on(val.pop());
        let oom = pollster::block_on(oom.pop());
        if let Some(e) = oom {
            return Err(GpuError::Reported(format!("out of GPU memory: {e}")));
        }
        if let Some(e) = val {
            return Err(GpuError::Reported(e.to_string()));
        }
        out
    }

    /// Copies `bytes` bytes of `src` (a GPU buffer with COPY_SRC) back to the CPU.
    pub(crate) fn read_back(
        &self,
        staging: &wgpu::Buffer,
        bytes: u64,
    ) -> Result<Vec<u8>, GpuError> {
        self.read_back_as(staging, bytes)
    }

    /// [`GpuContext::read_back`] straight into a vector of `T` (one copy out of the mapped
    /// range; `bytes` a multiple of `T`'s size).
    pub(crate) fn read_back_as<T: bytemuck::Pod>(
        &self,
        staging: &wgpu::Buffer,
        bytes: u64,
    ) -> Result<Vec<T>, GpuError> {
        let (tx, rx) = std::sync::mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, 0..bytes, move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        rx.recv()
            .map_err(|e| GpuError::Readback(e.to_string()))?
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        let out = {
            let view = staging
                .get_mapped_range(0..bytes)
                .map_err(|e| GpuError::Readback(e.to_string()))?;
            bytemuck::pod_collect_to_vec(&view[..])
        };
        staging.unmap();
        self.check_uncaptured()?;
        Ok(out)
    }

    /// Measures device-to-device copy bandwidth with a `bytes`-byte buffer (GB/s: bytes read
    /// plus bytes written per second, best of `reps`). The floor a memory-bound kernel is
    /// held to.
    pub fn copy_bandwidth(&self, bytes: u64, reps: u32) -> Result<f64, GpuError> {
        let bytes = bytes.min(self.summary.max_buffer_bytes) & !3;
        let usage = wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST;
        let mk = |label| {
            self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes,
                usage,
                mapped_at_creation: false,
            })
        };
        let (a, b) = (mk("bw-src"), mk("bw-dst"));
        let mut best = f64::INFINITY;
        for _ in 0..reps.max(1) + 1 {
            let mut enc = self.device.create_command_encoder(&Default::default());
            enc.copy_buffer_to_buffer(&a, 0, &b, 0, bytes);
            let t = std::time::Instant::now();
            self.queue.submit([enc.finish()]);
            self.device
                .poll(wgpu::PollType::wait_indefinitely())
                .map_err(|e| GpuError::Readback(e.to_string()))?;
            best = best.min(t.elapsed().as_secs_f64());
        }
        Ok(2.0 * bytes as f64 / best / 1e9)
    }

    /// Waits until the queue is idle.
    pub fn wait(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        Ok(())
    }
}

/// Splits `groups` workgroups over x and y (each at most 65,535): (x, y).
pub(crate) fn grid(groups: u32) -> (u32, u32) {
    const MAX: u32 = 65_535;
    if groups <= MAX {
        (groups.max(1), 1)
    } else {
        (MAX, groups.div_ceil(MAX))
    }
}
