//! One scene's transport system on the device: F, S and the solve's vectors, with every bind
//! group made once, so a request only writes E and Bₑ, runs, and reads B back.
//!
//! The Jacobi solve of B = b + S F B, b = Bₑ + S E (the CPU's [`radiosity::solve`] with
//! [`radiosity::Method::Jacobi`], same stopping rule on the relative residual):
//!
//! ```text
//!   sfx ← S E;  b ← Bₑ + sfx, h[0] = ‖b‖²             (jacobi_update with x = 0)
//!   x ← b (or the warm start)
//!   repeat, m iterations per submission:
//!     fx ← F x; sfx ← S fx; r = b + sfx − x, x ← b + sfx; h[k] = ‖r‖²
//!   read h back; stop at the first k with √h[k] / √h[0] ≤ tolerance, or at the cap
//! ```
//!
//! Only the residual history (a few floats) crosses the bus between submissions; B is read
//! once at the end. The returned B has had every iteration of the last submission applied,
//! so it is at least as converged as the iterate whose residual met the tolerance.
//!
//! [`radiosity::solve`]: translux_engine::radiosity::solve
//! [`radiosity::Method::Jacobi`]: translux_engine::radiosity::Method::Jacobi

use std::sync::{Arc, Mutex};
use std::time::Instant;

use translux_engine::radiosity::{Method, Rgb, SolveParams, SolveStats};
use translux_engine::transport::Transport;
use translux_proto::csr::CsrView;

use super::matrix::{BoundOp, GpuCsr, alloc_size, staging, storage_zeroed, uniform};
use super::{GpuContext, GpuError, grid};

/// Keep in sync with `Params` in `jacobi_update.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct VecParams {
    n: u32,
    groups_x: u32,
    _pad0: u32,
    _pad1: u32,
}

/// Keep in sync with `Params` in `reduce_sum.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ReduceParams {
    count: u32,
    capacity: u32,
    _pad0: u32,
    _pad1: u32,
}

/// Settings of the device solve beyond [`SolveParams`].
#[derive(Debug, Clone, Copy)]
pub struct SystemParams {
    /// Iterations per submission: the residual history is read back after each. Default 8.
    pub readback_every: u32,
}

impl Default for SystemParams {
    fn default() -> Self {
        Self { readback_every: 8 }
    }
}

/// The per-scene vectors (n × RGB f32 each) and the residual history.
#[derive(Debug)]
struct Vectors {
    e: wgpu::Buffer,
    be: wgpu::Buffer,
    b: wgpu::Buffer,
    x: wgpu::Buffer,
    fx: wgpu::Buffer,
    sfx: wgpu::Buffer,
    /// x̄ = [x; P x] of a hierarchical F (a stub otherwise).
    pulled: wgpu::Buffer,
    /// C x̄ over a two-sided C's N + M rows, before the push (a stub otherwise).
    rows: wgpu::Buffer,
    partial: wgpu::Buffer,
    history: wgpu::Buffer,
    counter: wgpu::Buffer,
    history_read: wgpu::Buffer,
    x_read: wgpu::Buffer,
}

/// The dispatches of the solve, bound once.
#[derive(Debug)]
struct Ops {
    /// sfx ← S E
    s_e: BoundOp,
    /// b ← Bₑ + sfx (x = b starts at zero), h ← ‖b‖²
    rhs: BoundOp,
    /// fx ← F x
    f_x: BoundOp,
    /// sfx ← S fx
    s_fx: BoundOp,
    /// x ← b + sfx, partials of ‖r‖²
    update: BoundOp,
    /// h[counter++] ← Σ partials
    reduce: BoundOp,
}

/// F on the device: a dense F, or a hierarchical F̃ = C·P as C with its pull
/// P' = [I; P] ((N + M) × N, [`Transport::pull_matrix`]): F x is then two CSR products,
/// x̄ ← P' x and y ← C x̄, with the same kernel. A two-sided F̃ = Q·C·P adds its push
/// Q' = [I | Q] (N × (N + M), [`Transport::push_matrix`]) as a third: ỹ ← C x̄, y ← Q' ỹ.
#[derive(Debug)]
pub struct GpuF {
    c: GpuCsr,
    pull: Option<GpuCsr>,
    push: Option<GpuCsr>,
}

impl GpuF {
    /// Uploads F (and the pull of a hierarchical one).
    pub fn upload(ctx: &GpuContext, what: &str, f: &Transport<'_>) -> Result<GpuF, GpuError> {
        let upload = |m: Option<translux_proto::csr::Csr>, part: &str| -> Result<_, GpuError> {
            let Some(m) = m else { return Ok(None) };
            let view = m
                .view()
                .map_err(|e| GpuError::Invalid(format!("{what} {part}: {e}")))?;
            GpuCsr::upload_f32(ctx, &format!("{what} {part}"), &view).map(Some)
        };
        let pull = upload(f.pull_matrix(), "pull")?;
        let release = |m: &Option<GpuCsr>| {
            if let Some(m) = m {
                ctx.release(m.bytes());
            }
        };
        let push = upload(f.push_matrix(), "push").inspect_err(|_| release(&pull))?;
        match GpuCsr::upload_f32(ctx, &format!("{what} F"), f.matrix()) {
            Ok(c) => Ok(GpuF { c, pull, push }),
            Err(e) => {
                release(&pull);
                release(&push);
                Err(e)
            }
        }
    }

    /// Rows of F (patches).
    pub fn n_rows(&self) -> usize {
        self.push.as_ref().map_or(self.c.n_rows(), GpuCsr::n_rows)
    }

    /// Rows of C x̄ before the push (patches, then the receiving nodes of a two-sided F).
    fn stored_rows(&self) -> usize {
        self.c.n_rows()
    }

    /// Rows of the pulled vector x̄ (patches, then cluster nodes).
    fn pulled_rows(&self) -> usize {
        self.c.n_cols()
    }

    /// Whether the pulled vector matches C (dense: C is square; hierarchical: P' feeds it).
    fn consistent(&self) -> bool {
        let n = self.n_rows();
        let pushed = match &self.push {
            None => true,
            Some(q) => q.n_cols() == self.c.n_rows() && self.pull.is_some(),
        };
        pushed
            && match &self.pull {
                None => self.c.n_cols() == self.c.n_rows(),
                Some(p) => p.n_rows() == self.c.n_cols() && p.n_cols() == n,
            }
    }

    /// Row blocks of C (and of the pull).
    pub fn blocks(&self) -> usize {
        [&self.pull, &self.push]
            .into_iter()
            .flatten()
            .fold(self.c.blocks(), |a, m| a + m.blocks())
    }

    /// GPU bytes held.
    pub fn bytes(&self) -> u64 {
        [&self.pull, &self.push]
            .into_iter()
            .flatten()
            .fold(self.c.bytes(), |a, m| a + m.bytes())
    }

    /// Bytes one product reads.
    pub fn stream_bytes(&self) -> u64 {
        [&self.pull, &self.push]
            .into_iter()
            .flatten()
            .fold(self.c.stream_bytes(), |a, m| a + m.stream_bytes())
    }

    /// y = F x; `pulled` holds x̄ for a hierarchical F, `rows` C x̄ for a two-sided one.
    fn bind(
        &self,
        ctx: &GpuContext,
        x: &wgpu::Buffer,
        pulled: &wgpu::Buffer,
        rows: &wgpu::Buffer,
        y: &wgpu::Buffer,
    ) -> BoundOp {
        match (&self.pull, &self.push) {
            (None, _) => self.c.bind(ctx, x, y),
            (Some(p), None) => p.bind(ctx, x, pulled).then(self.c.bind(ctx, pulled, y)),
            (Some(p), Some(q)) => p
                .bind(ctx, x, pulled)
                .then(self.c.bind(ctx, pulled, rows))
                .then(q.bind(ctx, rows, y)),
        }
    }
}

/// y = S x: one CSR product, or for a hierarchical S (`linked`) F's pull of x into
/// `pulled` and then S over it (the pulled vector is free again once F's product is done).
fn s_product(
    f: &GpuF,
    s: &GpuCsr,
    linked: bool,
    ctx: &GpuContext,
    x: &wgpu::Buffer,
    pulled: &wgpu::Buffer,
    y: &wgpu::Buffer,
) -> BoundOp {
    match (&f.pull, linked) {
        (Some(p), true) => p.bind(ctx, x, pulled).then(s.bind(ctx, pulled, y)),
        _ => s.bind(ctx, x, y),
    }
}

/// A scene's F and S on the device, with everything the solve needs.
#[derive(Debug)]
pub struct GpuSystem {
    n: usize,
    /// Shared by every system of the scene (the bundle's S and overridden ones).
    f: Arc<GpuF>,
    s: GpuCsr,
    v: Vectors,
    ops: Ops,
    capacity: u32,
    vector_bytes: u64,
    /// One solve at a time: the vectors are shared.
    busy: Mutex<()>,
}

/// What a device solve did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GpuSolveStats {
    pub stats: SolveStats,
    /// Submissions (each followed by one read-back of the residual history).
    pub readbacks: u32,
}

impl GpuSystem {
    /// Uploads F and S of an n-patch scene and binds the solve (`max_iterations` sizes the
    /// residual history).
    pub fn new(
        ctx: &GpuContext,
        what: &str,
        f: &Transport<'_>,
        s: &CsrView<'_, Rgb>,
        max_iterations: u32,
    ) -> Result<GpuSystem, GpuError> {
        let n = f.n();
        let s_linked = f.is_hierarchical() && s.n_cols() == n + f.nodes() && f.nodes() > 0;
        if s.n_rows() != n || (s.n_cols() != n && !s_linked) {
            return Err(GpuError::Invalid(format!(
                "{what}: F has {n} rows and S is {}×{}; S must be n×n, or n×(n + nodes) over \
                 F's cluster tree",
                s.n_rows(),
                s.n_cols()
            )));
        }
        let f = Arc::new(GpuF::upload(ctx, what, f)?);
        let s = match GpuCsr::upload_rgb(ctx, &format!("{what} S"), s) {
            Ok(s) => s,
            Err(e) => {
                ctx.release(f.bytes());
                return Err(e);
            }
        };
        let f_bytes = f.bytes();
        Self::with_f(ctx, what, f, s, max_iterations).inspect_err(|_| ctx.release(f_bytes))
    }

    /// A system over an F already on the device (shared with other systems of the scene)
    /// and an uploaded S; on failure S's bytes are returned to the budget.
    pub fn with_f(
        ctx: &GpuContext,
        what: &str,
        f: Arc<GpuF>,
        s: GpuCsr,
        max_iterations: u32,
    ) -> Result<GpuSystem, GpuError> {
        let n = f.n_rows();
        // A hierarchical S has node columns: it reads the vector pulled by F's tree.
        let s_linked = f.pull.is_some() && s.n_cols() == f.pulled_rows() && s.n_cols() > n;
        if !f.consistent() || s.n_rows() != n || (s.n_cols() != n && !s_linked) {
            ctx.release(s.bytes());
            return Err(GpuError::Invalid(format!(
                "{what}: F has {n} rows and {} pulled columns, S is {}×{}; S must be n×n, \
                 or n×(n + nodes) over F's cluster tree",
                f.pulled_rows(),
                s.n_rows(),
                s.n_cols()
            )));
        }
        let vb = alloc_size(12 * n as u64);
        let pulled_bytes = if f.pull.is_some() {
            alloc_size(12 * f.pulled_rows() as u64)
        } else {
            16
        };
        let rows_bytes = if f.push.is_some() {
            alloc_size(12 * f.stored_rows() as u64)
        } else {
            16
        };
        let groups = (n as u32).div_ceil(256);
        let capacity = max_iterations + 2;
        let vector_bytes = 6 * vb
            + pulled_bytes
            + rows_bytes
            + alloc_size(4 * groups as u64)
            + 2 * alloc_size(4 * capacity as u64)
            + 16
            + vb
            + 48;
        if let Err(e) = ctx.reserve(&format!("{what} vectors"), vector_bytes) {
            ctx.release(s.bytes());
            return Err(e);
        }
        let made = ctx.scoped(|| {
            let v = Vectors {
                e: storage_zeroed(ctx, "E", vb),
                be: storage_zeroed(ctx, "Be", vb),
                b: storage_zeroed(ctx, "b", vb),
                x: storage_zeroed(ctx, "x", vb),
                fx: storage_zeroed(ctx, "Fx", vb),
                sfx: storage_zeroed(ctx, "SFx", vb),
                pulled: storage_zeroed(ctx, "pulled", pulled_bytes),
                rows: storage_zeroed(ctx, "rows", rows_bytes),
                partial: storage_zeroed(ctx, "partial", 4 * groups as u64),
                history: storage_zeroed(ctx, "history", 4 * capacity as u64),
                counter: storage_zeroed(ctx, "counter", 16),
                history_read: staging(ctx, "history-read", 4 * capacity as u64),
                x_read: staging(ctx, "x-read", vb),
            };
            let g = grid(groups);
            let vp = uniform(
                ctx,
                "vec-params",
                &VecParams {
                    n: n as u32,
                    groups_x: g.0,
                    _pad0: 0,
                    _pad1: 0,
                },
            );
            let rp = uniform(
                ctx,
                "reduce-params",
                &ReduceParams {
                    count: groups,
                    capacity,
                    _pad0: 0,
                    _pad1: 0,
                },
            );
            let k = &ctx.kernels;
            let dev = &ctx.device;
            let ops = Ops {
                s_e: s_product(&f, &s, s_linked, ctx, &v.e, &v.pulled, &v.sfx),
                rhs: BoundOp::new(
                    k.jacobi_update.clone(),
                    vec![(
                        k.jacobi.bind(dev, &vp, &[&v.be, &v.sfx, &v.b, &v.partial]),
                        g,
                    )],
                ),
                f_x: f.bind(ctx, &v.x, &v.pulled, &v.rows, &v.fx),
                s_fx: s_product(&f, &s, s_linked, ctx, &v.fx, &v.pulled, &v.sfx),
                update: BoundOp::new(
                    k.jacobi_update.clone(),
                    vec![(
                        k.jacobi.bind(dev, &vp, &[&v.b, &v.sfx, &v.x, &v.partial]),
                        g,
                    )],
                ),
                reduce: BoundOp::new(
                    k.reduce_sum.clone(),
                    vec![(
                        k.reduce
                            .bind(dev, &rp, &[&v.partial, &v.history, &v.counter]),
                        (1, 1),
                    )],
                ),
            };
            Ok((v, ops))
        });
        match made {
            Ok((v, ops)) => Ok(GpuSystem {
                n,
                f,
                s,
                v,
                ops,
                capacity,
                vector_bytes,
                busy: Mutex::new(()),
            }),
            Err(e) => {
                ctx.release(vector_bytes + s.bytes());
                Err(e)
            }
        }
    }

    /// Patches.
    pub fn n(&self) -> usize {
        self.n
    }

    /// GPU bytes held by F, S and the vectors.
    pub fn bytes(&self) -> u64 {
        self.f.bytes() + self.own_bytes()
    }

    /// GPU bytes held by S and the vectors (not the shared F).
    pub fn own_bytes(&self) -> u64 {
        self.s.bytes() + self.vector_bytes
    }

    /// The shared F.
    pub fn f(&self) -> &Arc<GpuF> {
        &self.f
    }

    /// The uploaded F and S.
    pub fn matrices(&self) -> (&GpuF, &GpuCsr) {
        (&self.f, &self.s)
    }

    /// Bytes one Jacobi iteration reads from F and S (the bandwidth floor of an iteration).
    pub fn iteration_bytes(&self) -> u64 {
        self.f.stream_bytes() + self.s.stream_bytes()
    }

    /// Returns this system's bytes (F's too when this is its last holder) to the context's
    /// budget; call when dropping it.
    pub fn release(self, ctx: &GpuContext) {
        let own = self.own_bytes();
        let f_bytes = self.f.bytes();
        let last = Arc::strong_count(&self.f) == 1;
        drop(self);
        ctx.release(own + if last { f_bytes } else { 0 });
    }

    /// Solves B = Bₑ + S(E + F B) on the device (Jacobi; `params.method` is not consulted:
    /// Gauss-Seidel is sequential and has no device form). `warm` starts from a previous B.
    pub fn solve(
        &self,
        ctx: &GpuContext,
        emission: &[Rgb],
        irradiance: &[Rgb],
        params: &SolveParams,
        sys: &SystemParams,
        warm: Option<&[Rgb]>,
    ) -> Result<(Vec<Rgb>, GpuSolveStats), GpuError> {
        let n = self.n;
        if emission.len() != n || irradiance.len() != n {
            return Err(GpuError::Invalid(format!(
                "emission has {} and irradiance {} entries; the scene has {n} patches",
                emission.len(),
                irradiance.len()
            )));
        }
        self.run(ctx, Some(irradiance), emission, params, sys, warm)
    }

    /// Solves (I − S F) B = rhs on the device for a right-hand side computed elsewhere
    /// (the relight's batched path builds Bₑ + S E on the CPU). Otherwise as [`Self::solve`].
    pub fn solve_rhs(
        &self,
        ctx: &GpuContext,
        rhs: &[Rgb],
        params: &SolveParams,
        sys: &SystemParams,
        warm: Option<&[Rgb]>,
    ) -> Result<(Vec<Rgb>, GpuSolveStats), GpuError> {
        if rhs.len() != self.n {
            return Err(GpuError::Invalid(format!(
                "the right-hand side has {} entries; the scene has {} patches",
                rhs.len(),
                self.n
            )));
        }
        self.run(ctx, None, rhs, params, sys, warm)
    }

    /// The solve: b = `be` + S `e` (S E skipped without `e`), then Jacobi.
    fn run(
        &self,
        ctx: &GpuContext,
        e: Option<&[Rgb]>,
        be: &[Rgb],
        params: &SolveParams,
        sys: &SystemParams,
        warm: Option<&[Rgb]>,
    ) -> Result<(Vec<Rgb>, GpuSolveStats), GpuError> {
        let t0 = Instant::now();
        let n = self.n;
        // At least one iteration: its residual is the one reported.
        let max_it = params.max_iterations.clamp(1, self.capacity - 2);
        let every = sys.readback_every.max(1);
        let is_warm = warm.is_some_and(|w| w.len() == n);
        let _busy = self.busy.lock().unwrap_or_else(|p| p.into_inner());
        ctx.scoped(|| {
            let q = &ctx.queue;
            if let Some(e) = e {
                q.write_buffer(&self.v.e, 0, bytemuck::cast_slice(e));
            }
            q.write_buffer(&self.v.be, 0, bytemuck::cast_slice(be));
            q.write_buffer(&self.v.counter, 0, bytemuck::bytes_of(&[0u32; 4]));
            let vb = 12 * n as u64;
            // b = Bₑ + S E (or the given rhs: sfx = 0) and ‖b‖², then x = b (or the warm
            // start).
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            enc.clear_buffer(&self.v.b, 0, None);
            if e.is_none() {
                enc.clear_buffer(&self.v.sfx, 0, None);
            }
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                if e.is_some() {
                    self.ops.s_e.encode(&mut pass);
                }
                self.ops.rhs.encode(&mut pass);
                self.ops.reduce.encode(&mut pass);
            }
            match warm {
                Some(w) if w.len() == n => q.write_buffer(&self.v.x, 0, bytemuck::cast_slice(w)),
                _ => enc.copy_buffer_to_buffer(&self.v.b, 0, &self.v.x, 0, vb),
            }
            ctx.queue.submit([enc.finish()]);
            let mut done = 0u32;
            let mut readbacks = 0u32;
            let (b_norm, residual, converged) = loop {
                let batch = every.min(max_it - done);
                let mut enc = ctx.device.create_command_encoder(&Default::default());
                if batch > 0 {
                    let mut pass = enc.begin_compute_pass(&Default::default());
                    for _ in 0..batch {
                        self.ops.f_x.encode(&mut pass);
                        self.ops.s_fx.encode(&mut pass);
                        self.ops.update.encode(&mut pass);
                        self.ops.reduce.encode(&mut pass);
                    }
                }
                let slots = (done + batch + 1) as u64;
                enc.copy_buffer_to_buffer(&self.v.history, 0, &self.v.history_read, 0, 4 * slots);
                ctx.queue.submit([enc.finish()]);
                readbacks += 1;
                let bytes = ctx.read_back(&self.v.history_read, 4 * slots)?;
                let h: Vec<f32> = bytemuck::pod_collect_to_vec(&bytes);
                done += batch;
                let b_norm = (h[0] as f64).sqrt();
                if b_norm == 0.0 {
                    break (0.0, 0.0, true);
                }
                // h[k], k ≥ 1: the residual of the iterate before update k.
                let rel = |k: usize| ((h[k] as f64).sqrt() / b_norm) as f32;
                let hit = (1..h.len()).find(|&k| rel(k) <= params.tolerance);
                let last = if h.len() > 1 {
                    rel(h.len() - 1)
                } else {
                    f32::INFINITY
                };
                if let Some(k) = hit {
                    let _ = k;
                    break (b_norm, last, true);
                }
                if done >= max_it {
                    break (b_norm, last, false);
                }
            };
            if b_norm == 0.0 {
                let stats = SolveStats {
                    method: Method::Jacobi,
                    iterations: 0,
                    products: 0,
                    warm: is_warm,
                    residual: 0.0,
                    converged: true,
                    seconds: t0.elapsed().as_secs_f64(),
                };
                return Ok((vec![[0.0; 3]; n], GpuSolveStats { stats, readbacks }));
            }
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            enc.copy_buffer_to_buffer(&self.v.x, 0, &self.v.x_read, 0, vb);
            ctx.queue.submit([enc.finish()]);
            let bytes = ctx.read_back(&self.v.x_read, vb)?;
            let x: Vec<f32> = bytemuck::pod_collect_to_vec(&bytes);
            let b: Vec<Rgb> = x.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
            let stats = SolveStats {
                method: Method::Jacobi,
                iterations: done,
                products: done,
                warm: is_warm,
                residual,
                converged,
                seconds: t0.elapsed().as_secs_f64(),
            };
            Ok((b, GpuSolveStats { stats, readbacks }))
        })
    }
}

/// One dispatch of `jacobi_update` on uploaded vectors: returns the new x and the
/// per-workgroup Σ‖r‖² (what the tests hold to [`super::cpu_twin::jacobi_update`]).
pub fn jacobi_update_once(
    ctx: &GpuContext,
    b: &[Rgb],
    sfx: &[Rgb],
    x: &[Rgb],
) -> Result<(Vec<Rgb>, Vec<f32>), GpuError> {
    let n = x.len();
    if b.len() != n || sfx.len() != n {
        return Err(GpuError::Invalid(
            "b, sfx and x must have equal lengths".into(),
        ));
    }
    let groups = (n as u32).div_ceil(256);
    ctx.scoped(|| {
        let g = grid(groups);
        let p = uniform(
            ctx,
            "vec-params",
            &VecParams {
                n: n as u32,
                groups_x: g.0,
                _pad0: 0,
                _pad1: 0,
            },
        );
        let bb = super::matrix::storage_init(ctx, "b", bytemuck::cast_slice(b));
        let sb = super::matrix::storage_init(ctx, "sfx", bytemuck::cast_slice(sfx));
        let xb = super::matrix::storage_init(ctx, "x", bytemuck::cast_slice(x));
        let pb = storage_zeroed(ctx, "partial", 4 * groups as u64);
        let k = &ctx.kernels;
        let op = BoundOp::new(
            k.jacobi_update.clone(),
            vec![(k.jacobi.bind(&ctx.device, &p, &[&bb, &sb, &xb, &pb]), g)],
        );
        let xr = staging(ctx, "x-read", 12 * n as u64);
        let pr = staging(ctx, "partial-read", 4 * groups as u64);
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            op.encode(&mut pass);
        }
        enc.copy_buffer_to_buffer(&xb, 0, &xr, 0, 12 * n as u64);
        enc.copy_buffer_to_buffer(&pb, 0, &pr, 0, 4 * groups as u64);
        ctx.queue.submit([enc.finish()]);
        let xs: Vec<f32> = bytemuck::pod_collect_to_vec(&ctx.read_back(&xr, 12 * n as u64)?);
        let ps: Vec<f32> = bytemuck::pod_collect_to_vec(&ctx.read_back(&pr, 4 * groups as u64)?);
        Ok((xs.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(), ps))
    })
}

/// One dispatch of `reduce_sum` on uploaded partials, run `times` times into a fresh
/// history: returns the history (what the tests hold to [`super::cpu_twin::reduce_sum`]).
pub fn reduce_sum_once(
    ctx: &GpuContext,
    partial: &[f32],
    times: u32,
) -> Result<Vec<f32>, GpuError> {
    let capacity = times.max(1);
    ctx.scoped(|| {
        let p = uniform(
            ctx,
            "reduce-params",
            &ReduceParams {
                count: partial.len() as u32,
                capacity,
                _pad0: 0,
                _pad1: 0,
            },
        );
        let pb = super::matrix::storage_init(ctx, "partial", bytemuck::cast_slice(partial));
        let hb = storage_zeroed(ctx, "history", 4 * capacity as u64);
        let cb = storage_zeroed(ctx, "counter", 16);
        let k = &ctx.kernels;
        let op = BoundOp::new(
            k.reduce_sum.clone(),
            vec![(k.reduce.bind(&ctx.device, &p, &[&pb, &hb, &cb]), (1, 1))],
        );
        let hr = staging(ctx, "history-read", 4 * capacity as u64);
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            for _ in 0..times {
                op.encode(&mut pass);
            }
        }
        enc.copy_buffer_to_buffer(&hb, 0, &hr, 0, 4 * capacity as u64);
        ctx.queue.submit([enc.finish()]);
        Ok(bytemuck::pod_collect_to_vec(
            &ctx.read_back(&hr, 4 * capacity as u64)?,
        ))
    })
}
