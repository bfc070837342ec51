//! Environment lights in the whole relight: the bundle's visibility on the device and the
//! `env_irradiance` pass that adds each relight's E_env,i = Σ_k V_ik L̄_k to E.
//!
//! In: the bundle's visibility V ([`translux_proto::bundle::EnvVisibilityView`], N patches ×
//! K direction bins of half floats), uploaded once per scene on its first environment
//! relight as u32 words holding two halves each ([`GpuVisibility`]); per relight the bins'
//! total radiance L̄ (K RGB triples, made on the host by
//! `translux_engine::environment::bin_radiance_total`, or none). Out: E += E_env at the
//! patches, and E_env itself, which `vertex_colours` takes out of E again at opaque
//! vertices (their E(v) holds the lamps alone, as the engine's colour stage has it).
//!
//! A pass ([`EnvPass`]) belongs to one lane of relights and remembers the L̄ it last wrote
//! for each relight slot, so a relight with the same environments as the last one in its
//! slot (a dragged lamp under the same sky) writes no radiance; and it dispatches nothing
//! while no relight of its lane has an environment and E_env is already 0.

use std::sync::Mutex;

use translux_engine::radiosity::Rgb;
use translux_proto::bundle::EnvVisibilityView;

use super::matrix::{alloc_size, staging, storage_init, storage_zeroed, uniform};
use super::{GpuContext, GpuError, grid};

/// Keep in sync with `Params` in `env_irradiance.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct EnvParams {
    pub n: u32,
    pub bins: u32,
    /// u32 words per patch: ⌈bins / 2⌉.
    pub words: u32,
    pub groups_x: u32,
    /// Relights in the lane, and workgroups per relight.
    pub kv: u32,
    pub gpn: u32,
    /// Bit r: relight r has an environment.
    pub lit: u32,
    pub _pad: u32,
}

/// The bundle's visibility on the device: per patch ⌈K/2⌉ words, bin 2w in word w's low
/// half and bin 2w + 1 in its high half (0 past the last bin).
#[derive(Debug)]
pub struct GpuVisibility {
    words: wgpu::Buffer,
    n: usize,
    bins: usize,
    bytes: u64,
}

impl GpuVisibility {
    /// V packed as the kernel reads it: two half floats a word, ⌈K/2⌉ words a patch.
    pub fn pack(vis: EnvVisibilityView<'_>) -> Vec<u32> {
        let k = vis.bins();
        let n = vis.bits.len().checked_div(k).unwrap_or(0);
        let words = k.div_ceil(2);
        let mut out = Vec::with_capacity(n * words);
        for i in 0..n {
            let row = vis.row(i);
            out.extend(row.chunks(2).map(|pair| {
                let hi = pair.get(1).copied().unwrap_or(0);
                u32::from(pair[0]) | (u32::from(hi) << 16)
            }));
        }
        out
    }

    /// Uploads `vis` (one storage binding; counted against the context's budget).
    pub fn upload(ctx: &GpuContext, vis: EnvVisibilityView<'_>) -> Result<GpuVisibility, GpuError> {
        let bins = vis.bins();
        let n = vis.bits.len().checked_div(bins).unwrap_or(0);
        let raw = 4 * (n * bins.div_ceil(2)) as u64;
        if raw > ctx.adapter().max_binding_bytes {
            return Err(GpuError::MatrixTooLarge {
                what: "the environment's visibility".into(),
                requested: raw,
                max_binding: ctx.adapter().max_binding_bytes,
            });
        }
        let bytes = alloc_size(raw);
        ctx.reserve("environment visibility", bytes)?;
        let words = ctx
            .scoped(|| {
                let packed = Self::pack(vis);
                Ok(storage_init(
                    ctx,
                    "env-visibility",
                    bytemuck::cast_slice(&packed),
                ))
            })
            .inspect_err(|_| ctx.release(bytes))?;
        Ok(GpuVisibility {
            words,
            n,
            bins,
            bytes,
        })
    }

    /// GPU bytes held.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Direction bins K.
    pub fn bins(&self) -> usize {
        self.bins
    }
}

/// What a pass last left on the device.
#[derive(Debug)]
struct Written {
    /// Per relight slot, the L̄ the radiance buffer holds there (`None`: none written).
    radiance: Vec<Option<Vec<Rgb>>>,
    /// The parameters as written.
    params: EnvParams,
    /// Whether E_env may hold anything but 0 (the last dispatch had a lit relight).
    env_nonzero: bool,
}

/// The `env_irradiance` dispatch of one lane of `kv` relights, bound to the lane's E and
/// E_env (each `kv · n` RGB triples, relight after relight) and its own L̄ buffer.
#[derive(Debug)]
pub struct EnvPass {
    params: wgpu::Buffer,
    radiance: wgpu::Buffer,
    bind: wgpu::BindGroup,
    pipeline: wgpu::ComputePipeline,
    groups: (u32, u32),
    written: Mutex<Written>,
    bytes: u64,
}

impl EnvPass {
    /// GPU bytes a pass of `kv` relights over `bins` bins holds.
    fn bytes_for(bins: usize, kv: usize) -> u64 {
        alloc_size(12 * (bins * kv) as u64) + alloc_size(std::mem::size_of::<EnvParams>() as u64)
    }

    /// Binds `vis` to the lane's `e` and `e_env`, for `kv` relights of `n` patches each.
    pub fn new(
        ctx: &GpuContext,
        vis: &GpuVisibility,
        kv: usize,
        e: &wgpu::Buffer,
        e_env: &wgpu::Buffer,
    ) -> Result<EnvPass, GpuError> {
        let n = vis.n;
        let needed = 12 * (n * kv) as u64;
        for (what, b) in [("E", e), ("E_env", e_env)] {
            if b.size() < needed {
                return Err(GpuError::Invalid(format!(
                    "the {what} buffer holds {} bytes; {kv} relights of {n} patches need \
                     {needed}",
                    b.size()
                )));
            }
        }
        if kv > 32 {
            return Err(GpuError::Invalid(format!(
                "{kv} relights in one environment pass; it holds at most 32"
            )));
        }
        let bytes = Self::bytes_for(vis.bins, kv);
        ctx.reserve("environment pass", bytes)?;
        ctx.scoped(|| {
            let gpn = (n as u32).div_ceil(256);
            let groups = grid(gpn * kv as u32);
            let params = EnvParams {
                n: n as u32,
                bins: vis.bins as u32,
                words: vis.bins.div_ceil(2) as u32,
                groups_x: groups.0,
                kv: kv as u32,
                gpn,
                lit: 0,
                _pad: 0,
            };
            let params_buffer = uniform(ctx, "env-params", &params);
            let radiance = storage_zeroed(ctx, "env-radiance", 12 * (vis.bins * kv) as u64);
            let bind = ctx.kernels.env.bind(
                &ctx.device,
                &params_buffer,
                &[&vis.words, &radiance, e, e_env],
            );
            Ok(EnvPass {
                params: params_buffer,
                radiance,
                bind,
                pipeline: ctx.kernels.env_irradiance.clone(),
                groups,
                written: Mutex::new(Written {
                    radiance: vec![None; kv],
                    params,
                    env_nonzero: false,
                }),
                bytes,
            })
        })
        .inspect_err(|_| ctx.release(bytes))
    }

    /// GPU bytes held.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Writes each relight slot's L̄ (`radiance[r]`; slots past it have none) where it
    /// differs from what the slot holds, and which slots are lit; answers the bytes written
    /// and whether the pass must be dispatched (some slot is lit, or E_env is still to be
    /// cleared after lit ones). Record the dispatch when it answers `true`.
    pub fn write(&self, ctx: &GpuContext, radiance: &[Option<&[Rgb]>]) -> (u64, bool) {
        let mut w = self.written.lock().unwrap_or_else(|p| p.into_inner());
        let bins = w.params.bins as usize;
        let mut up = 0u64;
        let mut lit = 0u32;
        for (r, slot) in w.radiance.iter_mut().enumerate() {
            let Some(l) = radiance.get(r).copied().flatten() else {
                continue;
            };
            lit |= 1 << r;
            if l.len() != bins || slot.as_deref() == Some(l) {
                continue;
            }
            ctx.queue.write_buffer(
                &self.radiance,
                12 * (r * bins) as u64,
                bytemuck::cast_slice(l),
            );
            up += 12 * l.len() as u64;
            *slot = Some(l.to_vec());
        }
        if lit != w.params.lit {
            w.params.lit = lit;
            ctx.queue
                .write_buffer(&self.params, 0, bytemuck::bytes_of(&w.params));
            up += std::mem::size_of::<EnvParams>() as u64;
        }
        let run = lit != 0 || w.env_nonzero;
        w.env_nonzero = lit != 0;
        (up, run)
    }

    /// Records the dispatch into `pass`.
    pub fn encode(&self, pass: &mut wgpu::ComputePass<'_>) {
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind, &[]);
        pass.dispatch_workgroups(self.groups.0, self.groups.1, 1);
    }
}

/// One `env_irradiance` dispatch on uploaded inputs: `vis`, each relight's L̄ (`None`: no
/// environment) and E (`e`, relight after relight, n each): E with the environments added,
/// and E_env (what the tests hold to [`super::cpu_twin::env_irradiance`]).
pub fn env_irradiance_once(
    ctx: &GpuContext,
    vis: EnvVisibilityView<'_>,
    radiance: &[Option<Vec<Rgb>>],
    e: &[Rgb],
) -> Result<(Vec<Rgb>, Vec<Rgb>), GpuError> {
    let kv = radiance.len();
    let dev = GpuVisibility::upload(ctx, vis)?;
    let n = dev.n;
    let fail = |msg: String| {
        ctx.release(dev.bytes);
        Err(GpuError::Invalid(msg))
    };
    if kv == 0 || e.len() != n * kv {
        return fail(format!(
            "e has {} entries; {kv} relights of {n} patches need {}",
            e.len(),
            n * kv
        ));
    }
    if radiance.iter().flatten().any(|l| l.len() != dev.bins) {
        return fail(format!("every L̄ must have {} bins", dev.bins));
    }
    let out = ctx.scoped(|| {
        let eb = storage_init(ctx, "e", bytemuck::cast_slice(e));
        let bytes = 12 * (n * kv) as u64;
        let env = storage_zeroed(ctx, "e-env", bytes);
        let pass = EnvPass::new(ctx, &dev, kv, &eb, &env)?;
        let lights: Vec<Option<&[Rgb]>> = radiance.iter().map(|l| l.as_deref()).collect();
        pass.write(ctx, &lights);
        let read = staging(ctx, "env-read", 2 * alloc_size(bytes));
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        {
            let mut cp = enc.begin_compute_pass(&Default::default());
            pass.encode(&mut cp);
        }
        enc.copy_buffer_to_buffer(&eb, 0, &read, 0, alloc_size(bytes));
        enc.copy_buffer_to_buffer(&env, 0, &read, alloc_size(bytes), alloc_size(bytes));
        ctx.queue.submit([enc.finish()]);
        let v = ctx.read_back_as::<f32>(&read, 2 * alloc_size(bytes));
        ctx.release(pass.bytes());
        let v = v?;
        let rgb = |at: usize| -> Vec<Rgb> {
            v[at..at + 3 * n * kv]
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect()
        };
        Ok((rgb(0), rgb(alloc_size(bytes) as usize / 4)))
    });
    ctx.release(dev.bytes);
    out
}
