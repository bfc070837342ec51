//! One scene's transport system on the device: F, S and the solve's vectors, with every bind
//! group made once, so a request writes only what the host holds, runs, and reads back.
//!
//! The Jacobi solve of B = b + S F B, b = Bₑ + S E (the CPU's [`radiosity::solve`] with
//! [`radiosity::Method::Jacobi`]: the same minimal-residual step, `minimal_residual_step`
//! in `engine/src/solver.rs`, and the same stopping rule on the relative residual),
//! recorded into one submission:
//!
//! ```text
//!   [before: E on the device]
//!   sfx ← S E;  b ← Bₑ + sfx, h[0] = ‖b‖²             (jacobi_update with x = 0)
//!   x ← b (or the warm start)
//!   fx ← F x; sfx ← S fx; r ← b + sfx − x; h[1] = ‖r‖²   (mr_step 0, reduce_sum)
//!   m times, each dispatched indirectly from `args`:
//!     fx ← F r; sfx ← S fx                            (one pass over F and S: S F r)
//!     v = sfx − r: per workgroup ⟨r, v⟩_c, ⟨v, v⟩_c    (mr_step 1)
//!     α_qc = clamp(−⟨r, v⟩/⟨v, v⟩, 0.1, 1.9), or 1    (mr_alpha, per system and channel)
//!     x ← x + α r; r ← r + α v; h[k] = ‖r‖²          (mr_step 2, reduce_sum)
//!     (reduce_sum: at the first k ≥ 1 with √h[k] / √h[0] ≤ tolerance it zeroes `args`,
//!      so the iterations after it dispatch nothing)
//!   [after: vertex colours from x]
//!   copy the counter, the history and the answer to staging; read back once
//! ```
//!
//! r(α) = r + α v is the residual of x + α r for every α (v = S F r − r), so α is the
//! least-squares step along r, channel by channel, and each step costs one pass over F and
//! S, as plain Jacobi's (α = 1) did; r is carried from step to step, not recomputed. A
//! step's α is made and read on the device: no host round trip. Slot k of the history is
//! the residual of the iterate after pass k (the start's own in slot 1: a start that
//! already meets the tolerance takes no step), so the answer is the iterate whose
//! residual met the tolerance; `iterations` counts the steps and `products` the passes
//! (one more), as the CPU's stats do. x starts at b, as on the CPU: on the Cornell box a
//! start at 0 (r = b, no first pass) took a pass more.
//!
//! m is half as many again as the last solve took (at least 8); a solve that did not
//! converge in them continues in a further submission, up to the cap. A batch of
//! [`BATCH`] systems (concurrent relights) solves the same way on a second set of vectors
//! (`Lanes`) laid out system after system: each product reads F and S once for all of
//! them, each system has its own α and its own residual, and the iterations stop when
//! every system's residual meets the tolerance.
//!
//! S stands for the system's K: the scene's S, or P = diag ρ for the components that take
//! translucent objects as opaque ([`GpuSystem::with_diagonal`], which binds the scene's S
//! beside it for the paper's heuristics: b = Bₑ + S E, or b = P F (Bₑ + P E) and after the
//! solve y = x + Bₑ + S E, `Rhs`). A job without a solve (`GpuSystem::product`) records
//! only b, and its `after` stage reads b.
//!
//! [`radiosity::solve`]: translux_engine::radiosity::solve
//! [`radiosity::Method::Jacobi`]: translux_engine::radiosity::Method::Jacobi

use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Instant;

use translux_engine::radiosity::{Method, Rgb, SolveParams, SolveStats};
use translux_engine::transport::Transport;
use translux_proto::csr::CsrView;

use super::kernels::BATCH;
use super::matrix::{BoundOp, GpuCsr, alloc_size, staging, storage_zeroed, uniform};
use super::{GpuContext, GpuError, grid};

/// Keep in sync with `Params` in `jacobi_update.wgsl` and `mr_step.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct VecParams {
    n: u32,
    groups_x: u32,
    /// Workgroups per system, systems.
    gpk: u32,
    kv: u32,
}

/// Keep in sync with `Params` in `reduce_sum.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ReduceParams {
    count: u32,
    capacity: u32,
    /// Indirect dispatch triples zeroed when the solve stops (0: it never stops).
    n_args: u32,
    /// The relative tolerance, squared.
    tol2: f32,
    /// Systems solved together (a batch).
    kv: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

/// Keep in sync with `Params` in `mr_alpha.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct AlphaParams {
    /// Workgroups of `mr_step` per system.
    count: u32,
    kv: u32,
    _pad0: u32,
    _pad1: u32,
}

/// The per-scene vectors (n × RGB f32 each) the host and the stages touch, the residual
/// history and the indirect dispatch arguments of one iteration. (F x or F r, the pulled
/// vector x̄ = [x; P x] of a hierarchical F, C x̄ of a two-sided one, the residual r carried
/// from step to step, the partial sums and the steps α live only in the bind groups that
/// use them.)
#[derive(Debug)]
struct Vectors {
    e: wgpu::Buffer,
    be: wgpu::Buffer,
    b: wgpu::Buffer,
    x: wgpu::Buffer,
    sfx: wgpu::Buffer,
    /// Fx (scratch between products).
    fx: wgpu::Buffer,
    /// The heuristics' answer ([`HeuristicOps`]).
    y: Option<wgpu::Buffer>,
    history: wgpu::Buffer,
    /// `[next history slot, the iteration the solve stopped at (0: running), 0, 0]`.
    counter: wgpu::Buffer,
    /// `reduce_sum`'s parameters (the tolerance changes per solve).
    reduce_params: wgpu::Buffer,
    /// The grids of an iteration's dispatches, read indirectly; zeroed on the device when
    /// the solve stops.
    args: wgpu::Buffer,
    /// The same grids as made, copied over `args` at the start of each solve.
    args_full: wgpu::Buffer,
    /// Staging for the counter, the history and B.
    read: wgpu::Buffer,
}

/// Where one of a solve's vectors comes from.
#[derive(Clone, Copy)]
pub(crate) enum Input<'a> {
    /// Written by the host (counted in the bytes sent).
    Host(&'a [Rgb]),
    /// Copied on the device from another buffer.
    Copy(&'a wgpu::Buffer),
    /// Already where it belongs: written by the job's `before` stage (E), or kept on the
    /// device from the last solve (the warm start).
    OnDevice,
    /// Not given: no S E (the right-hand side is given whole), or a cold start (x = b).
    Absent,
}

/// The right-hand side a job solves for (K the system's operator, S the scene's).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Rhs {
    /// b = Bₑ + K E.
    Own,
    /// b = Bₑ + S E (`heuristic_a` on a system of K = P).
    SceneS,
    /// b = K F (Bₑ + K E), and after the solve y = x + Bₑ + S E (`heuristic_b` on a
    /// system of K = P: x is (I − P F)⁻¹ P F (Bₑ + P E)).
    Bounced,
}

/// A stage recorded into a compute pass of the solve's one submission.
pub(crate) type Stage<'a> = &'a dyn Fn(&mut wgpu::ComputePass<'_>);

/// A stage recorded into the solve's command encoder (its own passes and copies).
pub(crate) type EncoderStage<'a> = &'a dyn Fn(&mut wgpu::CommandEncoder);

/// One solve as the device runs it: its inputs, the stages recorded before and after it,
/// and what it reads back.
pub(crate) struct Job<'a> {
    /// E: on the host, recorded by `before`, or absent (then `be` is the whole b).
    pub(crate) e: Input<'a>,
    /// Bₑ (or the whole right-hand side): on the host or copied from a device buffer.
    pub(crate) be: Input<'a>,
    /// The start: on the host, x as the last solve left it, or b.
    pub(crate) warm: Input<'a>,
    /// Records work before the solve (the device's direct light into E).
    pub(crate) before: Option<EncoderStage<'a>>,
    /// The right-hand side (and with [`Rhs::Bounced`] the sum after the solve).
    pub(crate) rhs: Rhs,
    /// Records work after the solve (vertex colours from x).
    pub(crate) after: Option<Stage<'a>>,
    /// What is read back after the counters; `None`: x.
    pub(crate) out: Option<Out<'a>>,
}

/// A job's answer as read back: ranges of device buffers, one after another in `staging`
/// after the counter and the history ([`Lanes::counter_bytes`] of room).
pub(crate) struct Out<'a> {
    /// `(buffer, offset, bytes)`.
    pub(crate) ranges: Vec<(&'a wgpu::Buffer, u64, u64)>,
    pub(crate) staging: &'a wgpu::Buffer,
}

/// What a device solve did, and what crossed the bus for it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GpuSolveStats {
    pub stats: SolveStats,
    /// Command submissions (1 when the iterations recorded sufficed).
    pub submissions: u32,
    /// Bytes the host wrote to the device (vectors, parameters).
    pub bytes_up: u64,
    /// Bytes read back (the counters, the residual history, the answer).
    pub bytes_down: u64,
}

/// The dispatches of the solve, bound once.
#[derive(Debug)]
struct Ops {
    /// sfx ← S E
    s_e: BoundOp,
    /// b ← Bₑ + sfx (x = b starts at zero), h ← ‖b‖²
    rhs: BoundOp,
    /// fx ← F x (the start's residual)
    f_x: BoundOp,
    /// fx ← F r (each step's product)
    f_r: BoundOp,
    /// sfx ← S fx
    s_fx: BoundOp,
    /// r ← b + sfx − x, partials of ‖r‖² (the start's residual)
    residual: BoundOp,
    /// v = sfx − r: partials of ⟨r, v⟩ and ⟨v, v⟩ per channel
    dots: BoundOp,
    /// α per system and channel from the dots' partials
    alpha: BoundOp,
    /// x ← x + α r, r ← r + α v, partials of ‖r‖²
    update: BoundOp,
    /// h[counter++] ← Σ partials
    reduce: BoundOp,
    /// With the scene's S beside K = P: the heuristics' products.
    heuristic: Option<HeuristicOps>,
}

/// The products of the paper's heuristics on a system of K = P, beside the scene's S.
#[derive(Debug)]
struct HeuristicOps {
    /// sfx ← S E
    s_e: BoundOp,
    /// fx ← F b
    f_b: BoundOp,
    /// b ← fx + sfx (fx cleared first: b = P F b), partials of ‖b‖²
    rhs_f: BoundOp,
    /// fx ← Bₑ + sfx
    lit: BoundOp,
    /// y ← x + fx
    sum: BoundOp,
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

    /// y = F x (for a batch's every vector with `batch`); `pulled` holds x̄ for a
    /// hierarchical F, `rows` C x̄ for a two-sided one.
    fn bind(
        &self,
        ctx: &GpuContext,
        x: &wgpu::Buffer,
        pulled: &wgpu::Buffer,
        rows: &wgpu::Buffer,
        y: &wgpu::Buffer,
        batch: bool,
    ) -> BoundOp {
        let c = &self.c;
        match (&self.pull, &self.push) {
            (None, _) => c.bind_lanes(ctx, x, y, batch),
            (Some(p), None) => p
                .bind_lanes(ctx, x, pulled, batch)
                .then(c.bind_lanes(ctx, pulled, y, batch)),
            (Some(p), Some(q)) => p
                .bind_lanes(ctx, x, pulled, batch)
                .then(c.bind_lanes(ctx, pulled, rows, batch))
                .then(q.bind_lanes(ctx, rows, y, batch)),
        }
    }
}

/// y = S x: one CSR product, or for a hierarchical S (`linked`) F's pull of x into
/// `pulled` and then S over it (the pulled vector is free again once F's product is done).
#[allow(clippy::too_many_arguments)]
fn s_product(
    f: &GpuF,
    s: &GpuCsr,
    linked: bool,
    ctx: &GpuContext,
    x: &wgpu::Buffer,
    pulled: &wgpu::Buffer,
    y: &wgpu::Buffer,
    batch: bool,
) -> BoundOp {
    match (&f.pull, linked) {
        (Some(p), true) => p
            .bind_lanes(ctx, x, pulled, batch)
            .then(s.bind_lanes(ctx, pulled, y, batch)),
        _ => s.bind_lanes(ctx, x, y, batch),
    }
}

/// The byte sizes of one set of the solve's vectors, for `kv` systems.
struct Sizes {
    n: usize,
    kv: u32,
    /// One n × RGB vector per system.
    vector: u64,
    pulled: u64,
    rows: u64,
    /// Workgroups of `jacobi_update` and `mr_step` per system.
    groups: u32,
    capacity: u32,
    /// The heuristics' answer vector y ([`HeuristicOps`]).
    heuristic: bool,
}

impl Sizes {
    fn of(f: &GpuF, capacity: u32, kv: u32, heuristic: bool) -> Sizes {
        let n = f.n_rows();
        let k = kv as u64;
        Sizes {
            n,
            kv,
            vector: alloc_size(12 * n as u64 * k),
            pulled: if f.pull.is_some() {
                alloc_size(12 * f.pulled_rows() as u64 * k)
            } else {
                16
            },
            rows: if f.push.is_some() {
                alloc_size(12 * f.stored_rows() as u64 * k)
            } else {
                16
            },
            groups: (n as u32).div_ceil(256),
            capacity,
            heuristic,
        }
    }

    /// Every buffer of [`Vectors`] and the stubs beside them (the indirect arguments
    /// counted at a generous 4 KiB).
    fn total(&self) -> u64 {
        (7 + u64::from(self.heuristic)) * self.vector
            + self.pulled
            + self.rows
            + alloc_size(4 * (self.groups * self.kv) as u64)
            + alloc_size(24 * (self.groups * self.kv) as u64)
            + alloc_size(16 * self.kv as u64)
            + 16
            + alloc_size(4 * (self.capacity * self.kv) as u64)
            + 16
            + 32
            + 2 * 4096
            + alloc_size(counter_bytes(self.capacity, self.kv) + self.vector)
    }
}

/// One set of the solve's vectors and its dispatches, bound once, for `kv` systems at once
/// (1, or a batch of [`BATCH`] relights sharing each pass over F and S).
#[derive(Debug)]
pub(crate) struct Lanes {
    kv: u32,
    v: Vectors,
    ops: Ops,
    /// Indirect dispatch triples of one iteration (`Vectors::args`).
    n_args: u32,
    /// GPU bytes of the vectors.
    bytes: u64,
    /// Iterations the last solve took: the next one records half as many again (and at
    /// least [`MIN_RECORDED`]) in its one submission.
    last_iterations: AtomicU32,
    /// Whether x holds the answer of a solve (a warm start on the device).
    x_solved: AtomicBool,
    /// One solve at a time: the vectors are shared.
    busy: Mutex<()>,
}

/// The solve's vectors and its dispatches, bound once.
fn bind_solve(
    ctx: &GpuContext,
    f: &GpuF,
    (s, s_linked): (&GpuCsr, bool),
    scene_s: Option<(&GpuCsr, bool)>,
    z: &Sizes,
) -> Lanes {
    let batch = z.kv > 1;
    let g = grid(z.groups * z.kv);
    let vp = uniform(
        ctx,
        "vec-params",
        &VecParams {
            n: z.n as u32,
            groups_x: g.0,
            gpk: z.groups,
            kv: z.kv,
        },
    );
    let e = storage_zeroed(ctx, "E", z.vector);
    let be = storage_zeroed(ctx, "Be", z.vector);
    let b = storage_zeroed(ctx, "b", z.vector);
    let x = storage_zeroed(ctx, "x", z.vector);
    let r = storage_zeroed(ctx, "r", z.vector);
    let fx = storage_zeroed(ctx, "Fx", z.vector);
    let sfx = storage_zeroed(ctx, "SFx", z.vector);
    let pulled = storage_zeroed(ctx, "pulled", z.pulled);
    let rows = storage_zeroed(ctx, "rows", z.rows);
    let partial = storage_zeroed(ctx, "partial", 4 * (z.groups * z.kv) as u64);
    let dots_partial = storage_zeroed(ctx, "dots-partial", 24 * (z.groups * z.kv) as u64);
    let alpha = storage_zeroed(ctx, "alpha", 16 * z.kv as u64);
    let ap = uniform(
        ctx,
        "alpha-params",
        &AlphaParams {
            count: z.groups,
            kv: z.kv,
            _pad0: 0,
            _pad1: 0,
        },
    );
    let f_x = f.bind(ctx, &x, &pulled, &rows, &fx, batch);
    let f_r = f.bind(ctx, &r, &pulled, &rows, &fx, batch);
    let s_fx = s_product(f, s, s_linked, ctx, &fx, &pulled, &sfx, batch);
    let k = &ctx.kernels;
    let dev = &ctx.device;
    let mr = |pipeline: &wgpu::ComputePipeline, partial: &wgpu::Buffer| {
        BoundOp::new(
            pipeline.clone(),
            vec![(k.mr.bind(dev, &vp, &[&b, &sfx, &alpha, &x, &r, partial]), g)],
        )
    };
    let residual = mr(&k.mr_residual, &partial);
    let dots = mr(&k.mr_dots, &dots_partial);
    let update = mr(&k.mr_update, &partial);
    let alpha_op = BoundOp::new(
        k.mr_alpha.clone(),
        vec![(k.alpha.bind(dev, &ap, &[&dots_partial, &alpha]), (1, 1))],
    );
    // y ← a + c by `jacobi_update` (x = 0 there: its partials are not read).
    let add = |a: &wgpu::Buffer, c: &wgpu::Buffer, y: &wgpu::Buffer| {
        BoundOp::new(
            k.jacobi_update.clone(),
            vec![(k.jacobi.bind(dev, &vp, &[a, c, y, &partial]), g)],
        )
    };
    let y = z.heuristic.then(|| storage_zeroed(ctx, "y", z.vector));
    let heuristic = scene_s
        .zip(y.as_ref())
        .map(|((ss, linked), y)| HeuristicOps {
            s_e: s_product(f, ss, linked, ctx, &e, &pulled, &sfx, batch),
            f_b: f.bind(ctx, &b, &pulled, &rows, &fx, batch),
            rhs_f: add(&fx, &sfx, &b),
            lit: add(&be, &sfx, &fx),
            sum: add(&x, &fx, y),
        });
    // The grids of one iteration's indirect dispatches, in the order `record_iterations`
    // records them.
    let grids: Vec<u32> = [&f_r, &s_fx, &dots, &alpha_op, &update]
        .iter()
        .flat_map(|op| op.grids())
        .flat_map(|(gx, gy)| [gx, gy, 1])
        .collect();
    let n_args = (grids.len() / 3) as u32;
    let args = ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("solve-args"),
        size: alloc_size(4 * grids.len() as u64),
        usage: wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::INDIRECT
            | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let args_full =
        super::matrix::storage_init(ctx, "solve-args-full", bytemuck::cast_slice(&grids));
    let history = storage_zeroed(ctx, "history", 4 * (z.capacity * z.kv) as u64);
    let counter = storage_zeroed(ctx, "counter", 16);
    let reduce_params = uniform(
        ctx,
        "reduce-params",
        &ReduceParams {
            count: z.groups,
            capacity: z.capacity,
            n_args,
            tol2: 0.0,
            kv: z.kv,
            _pad0: 0,
            _pad1: 0,
            _pad2: 0,
        },
    );
    let reduce = BoundOp::new(
        k.reduce_sum.clone(),
        vec![(
            k.reduce
                .bind(dev, &reduce_params, &[&partial, &history, &counter, &args]),
            (1, 1),
        )],
    );
    let ops = Ops {
        s_e: s_product(f, s, s_linked, ctx, &e, &pulled, &sfx, batch),
        rhs: BoundOp::new(
            k.jacobi_update.clone(),
            vec![(k.jacobi.bind(dev, &vp, &[&be, &sfx, &b, &partial]), g)],
        ),
        f_x,
        f_r,
        s_fx,
        residual,
        dots,
        alpha: alpha_op,
        update,
        reduce,
        heuristic,
    };
    let v = Vectors {
        e,
        be,
        b,
        x,
        sfx,
        fx,
        y,
        history,
        counter,
        reduce_params,
        args,
        args_full,
        read: staging(
            ctx,
            "solve-read",
            counter_bytes(z.capacity, z.kv) + z.vector,
        ),
    };
    Lanes {
        kv: z.kv,
        v,
        ops,
        n_args,
        bytes: z.total(),
        last_iterations: AtomicU32::new(0),
        x_solved: AtomicBool::new(false),
        busy: Mutex::new(()),
    }
}

/// A scene's F and S on the device, with everything the solve needs.
#[derive(Debug)]
pub struct GpuSystem {
    n: usize,
    /// Shared by every system of the scene (the bundle's S and overridden ones).
    f: Arc<GpuF>,
    s: Arc<GpuCsr>,
    s_linked: bool,
    /// On a system of K = P ([`GpuSystem::with_diagonal`]): the scene's S, for the
    /// heuristics' right-hand sides ([`Rhs`]).
    scene_s: Option<(Arc<GpuCsr>, bool)>,
    capacity: u32,
    /// The vectors of one solve.
    one: Lanes,
    /// The vectors of a batch of [`BATCH`], made on the first batch; `Err`: they did not
    /// fit (batches then solve one by one).
    batch: OnceLock<Result<Lanes, String>>,
}

/// Fewest iterations a submission records. Iterations past the stop dispatch no
/// workgroups, so recording a few spare costs little; a solve that needs more than were
/// recorded continues in a further submission.
const MIN_RECORDED: u32 = 8;

/// Bytes of the counter and history a solve reads back before its answer, for a history
/// of `slots` entries of `kv` systems.
fn counter_bytes(slots: u32, kv: u32) -> u64 {
    16 + 4 * (slots * kv) as u64
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
        Self::with_f(ctx, what, (f, s), None, max_iterations).inspect_err(|_| ctx.release(f_bytes))
    }

    /// A system over an F already on the device (shared with other systems of the scene)
    /// and an uploaded S (K), with `scene_s` the scene's S beside a K of P; on failure K's
    /// bytes are returned to the budget.
    pub fn with_f(
        ctx: &GpuContext,
        what: &str,
        (f, s): (Arc<GpuF>, GpuCsr),
        scene_s: Option<(Arc<GpuCsr>, bool)>,
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
        let capacity = max_iterations + 2;
        let sizes = Sizes::of(&f, capacity, 1, scene_s.is_some());
        if let Err(e) = ctx.reserve(&format!("{what} vectors"), sizes.total()) {
            ctx.release(s.bytes());
            return Err(e);
        }
        let scene = scene_s.as_ref().map(|(ss, linked)| (&**ss, *linked));
        match ctx.scoped(|| Ok(bind_solve(ctx, &f, (&s, s_linked), scene, &sizes))) {
            Ok(one) => Ok(GpuSystem {
                n,
                f,
                s: Arc::new(s),
                s_linked,
                scene_s,
                capacity,
                one,
                batch: OnceLock::new(),
            }),
            Err(e) => {
                ctx.release(sizes.total() + s.bytes());
                Err(e)
            }
        }
    }

    /// A system over this one's F with K = `s` (a material override's S, laid out as the
    /// scene's: n × n, or n × (n + nodes) over F's cluster tree), sized like this one; on
    /// failure its bytes are returned to the budget.
    pub fn with_s(
        &self,
        ctx: &GpuContext,
        what: &str,
        s: &CsrView<'_, Rgb>,
    ) -> Result<GpuSystem, GpuError> {
        let k = GpuCsr::upload_rgb(ctx, what, s)?;
        Self::with_f(ctx, what, (self.f.clone(), k), None, self.capacity - 2)
    }

    /// K, the system's own operator (S, or P = diag ρ).
    pub fn k(&self) -> &GpuCsr {
        &self.s
    }

    /// A system over this one's F with K = diag(`diagonal`) (P = diag ρ: the transport with
    /// translucent objects opaque) and this one's S beside it for the heuristics' right-hand
    /// sides, sized like this one; on failure its bytes are returned to the budget.
    pub fn with_diagonal(
        &self,
        ctx: &GpuContext,
        what: &str,
        diagonal: &[Rgb],
    ) -> Result<GpuSystem, GpuError> {
        let n = self.n;
        if diagonal.len() != n {
            return Err(GpuError::Invalid(format!(
                "{what}: {} diagonal entries for {n} patches",
                diagonal.len()
            )));
        }
        let row_ptr: Vec<u64> = (0..=n as u64).collect();
        let col: Vec<u32> = (0..n as u32).collect();
        let view = CsrView::new_checked(n, n, &row_ptr, &col, diagonal)
            .map_err(|e| GpuError::Invalid(format!("{what}: {e}")))?;
        let k = GpuCsr::upload_rgb(ctx, what, &view)?;
        let scene_s = Some((self.s.clone(), self.s_linked));
        Self::with_f(ctx, what, (self.f.clone(), k), scene_s, self.capacity - 2)
    }

    /// The vectors of a batch of [`BATCH`] systems, made on first use; `None` when they do
    /// not fit (said once in the log).
    pub(crate) fn batch(&self, ctx: &GpuContext) -> Option<&Lanes> {
        let made = self.batch.get_or_init(|| {
            let sizes = Sizes::of(&self.f, self.capacity, BATCH, self.scene_s.is_some());
            let scene = self.scene_s.as_ref().map(|(ss, linked)| (&**ss, *linked));
            let own = (&*self.s, self.s_linked);
            ctx.reserve("batch vectors", sizes.total())
                .and_then(|()| {
                    ctx.scoped(|| Ok(bind_solve(ctx, &self.f, own, scene, &sizes)))
                        .inspect_err(|_| ctx.release(sizes.total()))
                })
                .map_err(|e| {
                    tracing::warn!("batched relights solve one by one: {e}");
                    e.to_string()
                })
        });
        made.as_ref().ok()
    }

    /// The vectors of one solve.
    pub(crate) fn one(&self) -> &Lanes {
        &self.one
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
        let batch = match self.batch.get() {
            Some(Ok(b)) => b.bytes,
            _ => 0,
        };
        self.s.bytes() + self.one.bytes + batch
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
        warm: Option<&[Rgb]>,
    ) -> Result<(Vec<Rgb>, GpuSolveStats), GpuError> {
        self.solve_from(ctx, (emission, irradiance), params, self.host_start(warm))
    }

    /// [`Self::solve`] started from the answer the last solve left on the device (cold, from
    /// b, before the first).
    pub fn solve_from_last(
        &self,
        ctx: &GpuContext,
        emission: &[Rgb],
        irradiance: &[Rgb],
        params: &SolveParams,
    ) -> Result<(Vec<Rgb>, GpuSolveStats), GpuError> {
        let start = if self.one.holds_answer() {
            Input::OnDevice
        } else {
            Input::Absent
        };
        self.solve_from(ctx, (emission, irradiance), params, start)
    }

    /// B = Bₑ + S(E + F B) from `start`.
    fn solve_from(
        &self,
        ctx: &GpuContext,
        (emission, irradiance): (&[Rgb], &[Rgb]),
        params: &SolveParams,
        start: Input<'_>,
    ) -> Result<(Vec<Rgb>, GpuSolveStats), GpuError> {
        let n = self.n;
        if emission.len() != n || irradiance.len() != n {
            return Err(GpuError::Invalid(format!(
                "emission has {} and irradiance {} entries; the scene has {n} patches",
                emission.len(),
                irradiance.len()
            )));
        }
        let job = Job {
            e: Input::Host(irradiance),
            be: Input::Host(emission),
            warm: start,
            before: None,
            rhs: Rhs::Own,
            after: None,
            out: None,
        };
        self.solve_x(ctx, &job, params)
    }

    /// Solves (I − S F) B = rhs on the device for a right-hand side computed elsewhere
    /// (the relight's batched path builds Bₑ + S E on the CPU). Otherwise as [`Self::solve`].
    pub fn solve_rhs(
        &self,
        ctx: &GpuContext,
        rhs: &[Rgb],
        params: &SolveParams,
        warm: Option<&[Rgb]>,
    ) -> Result<(Vec<Rgb>, GpuSolveStats), GpuError> {
        if rhs.len() != self.n {
            return Err(GpuError::Invalid(format!(
                "the right-hand side has {} entries; the scene has {} patches",
                rhs.len(),
                self.n
            )));
        }
        let job = Job {
            e: Input::Absent,
            be: Input::Host(rhs),
            warm: self.host_start(warm),
            before: None,
            rhs: Rhs::Own,
            after: None,
            out: None,
        };
        self.solve_x(ctx, &job, params)
    }

    /// A warm start given by the host, when it has the system's length.
    fn host_start<'a>(&self, warm: Option<&'a [Rgb]>) -> Input<'a> {
        match warm {
            Some(w) if w.len() == self.n => Input::Host(w),
            _ => Input::Absent,
        }
    }

    /// [`Self::run`] on the vectors of one solve, reading back x: B per patch (0 where
    /// b = 0).
    fn solve_x(
        &self,
        ctx: &GpuContext,
        job: &Job<'_>,
        params: &SolveParams,
    ) -> Result<(Vec<Rgb>, GpuSolveStats), GpuError> {
        let run = self.run(ctx, &self.one, job, params)?;
        let b: Vec<Rgb> = if run.dark[0] {
            vec![[0.0; 3]; self.n]
        } else {
            let x: Vec<f32> = bytemuck::pod_collect_to_vec(&run.out);
            x.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
        };
        Ok((b, run.stats[0]))
    }

    /// A solve of `lanes`' kv systems in as few submissions as the iterations allow,
    /// usually one: the job's inputs written, then one command buffer that records
    /// `before`, b by the job's [`Rhs`] and ‖b‖², the start, [`Lanes::recorded`] iterations
    /// (dispatched indirectly: `reduce_sum` zeroes their grids once every system's residual
    /// meets the tolerance), what follows for the [`Rhs`], `after`, and the copy of the
    /// counter, the history and the answer into staging, read back once. Only when the
    /// iterations recorded did not reach the tolerance (nor the cap) does a further
    /// submission record more.
    pub(crate) fn run(
        &self,
        ctx: &GpuContext,
        lanes: &Lanes,
        job: &Job<'_>,
        params: &SolveParams,
    ) -> Result<Run, GpuError> {
        let t0 = Instant::now();
        let max_it = params.max_iterations.clamp(1, self.capacity - 2);
        let _busy = lanes.busy.lock().unwrap_or_else(|p| p.into_inner());
        ctx.scoped(|| {
            let bytes_up = lanes.write_inputs(ctx, self.n, self.capacity, job, params);
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            lanes.record_start(&mut enc, self.n, job);
            let mut per = lanes.recorded(max_it);
            let (mut done, mut submissions, mut bytes_down) = (0u32, 0u32, 0u64);
            loop {
                let count = per.min(max_it - done);
                let (slots, out_bytes) =
                    lanes.record_iterations(&mut enc, self.n, job, done, count);
                ctx.queue.submit([enc.finish()]);
                submissions += 1;
                let staging = job.out.as_ref().map_or(&lanes.v.read, |o| o.staging);
                let head = counter_bytes(slots, lanes.kv);
                let bytes = ctx.read_back(staging, head + out_bytes)?;
                bytes_down += head + out_bytes;
                done += count;
                let state = History::parse(&bytes, slots, lanes.kv);
                if state.stopped.is_some() || done >= max_it || state.all_dark() {
                    let stats = lanes.finish(&state, job, t0, max_it, params.tolerance);
                    return Ok(Run {
                        out: bytes[head as usize..].to_vec(),
                        dark: (0..lanes.kv as usize).map(|q| state.dark(q)).collect(),
                        stats: stats
                            .into_iter()
                            .map(|stats| GpuSolveStats {
                                stats,
                                submissions,
                                bytes_up,
                                bytes_down,
                            })
                            .collect(),
                    });
                }
                per = per.saturating_mul(2);
                enc = ctx.device.create_command_encoder(&Default::default());
            }
        })
    }

    /// b = Bₑ + K E for `lanes`' kv systems without a solve (the `subsurface_only` and
    /// `direct` components), in one submission: the job's inputs written, then one command
    /// buffer that records `before`, b and ‖b‖², `after` (which reads b,
    /// [`Lanes::b_buffer`]) and the copy of the counter and of what the job's `out` names
    /// into its staging, read back once. x, the next solve's warm start, is left as it was.
    pub(crate) fn product(
        &self,
        ctx: &GpuContext,
        lanes: &Lanes,
        job: &Job<'_>,
        params: &SolveParams,
    ) -> Result<Run, GpuError> {
        let t0 = Instant::now();
        let Some(out) = job.out.as_ref() else {
            return Err(GpuError::Invalid(
                "a product reads back what its job's `out` names".into(),
            ));
        };
        let _busy = lanes.busy.lock().unwrap_or_else(|p| p.into_inner());
        ctx.scoped(|| {
            let bytes_up = lanes.write_inputs(ctx, self.n, self.capacity, job, params);
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            lanes.record_rhs(&mut enc, self.n, job);
            let (slots, out_bytes) = lanes.record_iterations(&mut enc, self.n, job, 0, 0);
            ctx.queue.submit([enc.finish()]);
            let head = counter_bytes(slots, lanes.kv);
            let bytes = ctx.read_back(out.staging, head + out_bytes)?;
            let seconds = t0.elapsed().as_secs_f64();
            let stats = GpuSolveStats {
                stats: SolveStats {
                    method: Method::Jacobi,
                    iterations: 0,
                    products: 0,
                    warm: false,
                    residual: 0.0,
                    converged: true,
                    seconds,
                },
                submissions: 1,
                bytes_up,
                bytes_down: head + out_bytes,
            };
            Ok(Run {
                out: bytes[head as usize..].to_vec(),
                // The answer is b itself, which the `after` stage read: nothing to zero.
                dark: vec![false; lanes.kv as usize],
                stats: vec![stats; lanes.kv as usize],
            })
        })
    }
}

impl Lanes {
    /// Systems solved together.
    pub(crate) fn kv(&self) -> usize {
        self.kv as usize
    }

    /// The buffer E lives in, system after system (a job's `before` stage writes it).
    pub(crate) fn e_buffer(&self) -> &wgpu::Buffer {
        &self.v.e
    }

    /// The buffer b = Bₑ + K E lives in (a product's answer, [`GpuSystem::product`]).
    pub(crate) fn b_buffer(&self) -> &wgpu::Buffer {
        &self.v.b
    }

    /// The buffer y = x + Bₑ + S E lives in (the answer of a job with [`Rhs::Bounced`]), on
    /// a system of K = P.
    pub(crate) fn y_buffer(&self) -> Option<&wgpu::Buffer> {
        self.v.y.as_ref()
    }

    /// The buffer the solve leaves B in (a job's `after` stage reads it).
    pub(crate) fn x_buffer(&self) -> &wgpu::Buffer {
        &self.v.x
    }

    /// Bytes a job's staging buffer holds before its answer: the counter and the longest
    /// history, for a system of `capacity` history slots.
    pub(crate) fn counter_bytes(&self, system: &GpuSystem) -> u64 {
        counter_bytes(system.capacity, self.kv)
    }

    /// Whether x holds the answer of an earlier solve, so a job may start there
    /// ([`Input::OnDevice`]).
    pub(crate) fn holds_answer(&self) -> bool {
        self.x_solved.load(Ordering::Relaxed)
    }

    /// Iterations the next submission records: half as many again as the last solve took,
    /// at least [`MIN_RECORDED`], at most the cap.
    fn recorded(&self, max_it: u32) -> u32 {
        let last = self.last_iterations.load(Ordering::Relaxed);
        (last + last / 2 + 2).max(MIN_RECORDED).min(max_it)
    }

    /// Writes the job's host vectors (one system's) and the tolerance; answers the bytes
    /// written.
    fn write_inputs(
        &self,
        ctx: &GpuContext,
        n: usize,
        capacity: u32,
        job: &Job<'_>,
        params: &SolveParams,
    ) -> u64 {
        let q = &ctx.queue;
        let mut up = 0u64;
        let mut put = |buffer: &wgpu::Buffer, v: &[Rgb]| {
            q.write_buffer(buffer, 0, bytemuck::cast_slice(v));
            up += 12 * v.len() as u64;
        };
        if let Input::Host(e) = job.e {
            put(&self.v.e, e);
        }
        if let Input::Host(be) = job.be {
            put(&self.v.be, be);
        }
        if let Input::Host(w) = job.warm {
            put(&self.v.x, w);
        }
        let rp = ReduceParams {
            count: (n as u32).div_ceil(256),
            capacity,
            n_args: self.n_args,
            tol2: params.tolerance * params.tolerance,
            kv: self.kv,
            _pad0: 0,
            _pad1: 0,
            _pad2: 0,
        };
        q.write_buffer(&self.v.reduce_params, 0, bytemuck::bytes_of(&rp));
        up + std::mem::size_of::<ReduceParams>() as u64
    }

    /// Records the start of a solve: the right-hand side ([`Lanes::record_rhs`]); then
    /// x = b unless the job starts elsewhere, and the start's residual r = b + S F x − x
    /// (one pass over F and S), its ‖r‖² in history slot 1 (where the stopping rule may
    /// already stop the solve).
    fn record_start(&self, enc: &mut wgpu::CommandEncoder, n: usize, job: &Job<'_>) {
        let vb = 12 * n as u64;
        self.record_rhs(enc, n, job);
        if matches!(job.warm, Input::Absent) {
            enc.copy_buffer_to_buffer(&self.v.b, 0, &self.v.x, 0, vb * self.kv as u64);
        }
        let mut pass = enc.begin_compute_pass(&Default::default());
        self.ops.f_x.encode(&mut pass);
        self.ops.s_fx.encode(&mut pass);
        self.ops.residual.encode(&mut pass);
        self.ops.reduce.encode(&mut pass);
    }

    /// Records the right-hand side: `before` (its own passes and copies), Bₑ copied in for
    /// every system where the job gives it on the device, the iteration grids restored,
    /// the counter cleared; then b by the job's [`Rhs`] (Bₑ + K E, Bₑ + S E, or
    /// K F (Bₑ + K E)) and ‖b‖² in history slot 0.
    fn record_rhs(&self, enc: &mut wgpu::CommandEncoder, n: usize, job: &Job<'_>) {
        let vb = 12 * n as u64;
        if let Some(before) = job.before {
            before(enc);
        }
        if let Input::Copy(be) = job.be {
            for q in 0..self.kv as u64 {
                enc.copy_buffer_to_buffer(be, 0, &self.v.be, q * vb, vb);
            }
        }
        let args_bytes = 12 * self.n_args as u64;
        enc.copy_buffer_to_buffer(&self.v.args_full, 0, &self.v.args, 0, args_bytes);
        enc.clear_buffer(&self.v.counter, 0, None);
        enc.clear_buffer(&self.v.b, 0, None);
        if matches!(job.e, Input::Absent) {
            enc.clear_buffer(&self.v.sfx, 0, None);
        }
        let heuristic = self.ops.heuristic.as_ref();
        let s_e = match (job.rhs, heuristic) {
            (Rhs::SceneS, Some(h)) => &h.s_e,
            _ => &self.ops.s_e,
        };
        let mut pass = enc.begin_compute_pass(&Default::default());
        if !matches!(job.e, Input::Absent) {
            s_e.encode(&mut pass);
        }
        self.ops.rhs.encode(&mut pass);
        if let (Rhs::Bounced, Some(h)) = (job.rhs, heuristic) {
            // b = K F (Bₑ + K E): F and K over the b just made, then b replaced by it.
            h.f_b.encode(&mut pass);
            self.ops.s_fx.encode(&mut pass);
            drop(pass);
            enc.clear_buffer(&self.v.fx, 0, None);
            pass = enc.begin_compute_pass(&Default::default());
            h.rhs_f.encode(&mut pass);
        }
        self.ops.reduce.encode(&mut pass);
    }

    /// Records what follows the solve for the job's [`Rhs`]: with [`Rhs::Bounced`],
    /// y = x + Bₑ + S E (the scratch vectors fx and sfx hold the parts).
    fn record_then(&self, pass: &mut wgpu::ComputePass<'_>, job: &Job<'_>) {
        if let (Rhs::Bounced, Some(h)) = (job.rhs, self.ops.heuristic.as_ref()) {
            h.s_e.encode(pass);
            h.lit.encode(pass);
            h.sum.encode(pass);
        }
    }

    /// Whether the lanes can make `rhs` (the scene's S beside K = P for the heuristics).
    pub(crate) fn makes(&self, rhs: Rhs) -> bool {
        rhs == Rhs::Own || self.ops.heuristic.is_some()
    }

    /// Records `count` iterations (after `done`), the job's `after` stage and the copies of
    /// the counter, the history and the answer into staging; answers the history slots
    /// copied and the answer's bytes.
    fn record_iterations(
        &self,
        enc: &mut wgpu::CommandEncoder,
        n: usize,
        job: &Job<'_>,
        done: u32,
        count: u32,
    ) -> (u32, u64) {
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            for _ in 0..count {
                let mut slot = 0;
                for op in [
                    &self.ops.f_r,
                    &self.ops.s_fx,
                    &self.ops.dots,
                    &self.ops.alpha,
                ] {
                    slot = op.encode_indirect(&mut pass, &self.v.args, slot);
                }
                self.ops
                    .update
                    .encode_indirect(&mut pass, &self.v.args, slot);
                self.ops.reduce.encode(&mut pass);
            }
            self.record_then(&mut pass, job);
            if let Some(after) = job.after {
                after(&mut pass);
            }
        }
        // ‖b‖², the start's residual, then one slot a step.
        let slots = done + count + 2;
        let x_bytes = 12 * (n as u64) * self.kv as u64;
        let x_range = [(&self.v.x, 0, x_bytes)];
        let (ranges, staging) = match &job.out {
            Some(o) => (o.ranges.as_slice(), o.staging),
            None => (x_range.as_slice(), &self.v.read),
        };
        let head = counter_bytes(slots, self.kv);
        enc.copy_buffer_to_buffer(&self.v.counter, 0, staging, 0, 16);
        enc.copy_buffer_to_buffer(&self.v.history, 0, staging, 16, head - 16);
        let mut at = head;
        for &(buffer, offset, bytes) in ranges {
            enc.copy_buffer_to_buffer(buffer, offset, staging, at, bytes);
            at += bytes;
        }
        (slots, at - head)
    }

    /// Each system's stats from the history, remembering the iterations for the next solve.
    fn finish(
        &self,
        h: &History,
        job: &Job<'_>,
        t0: Instant,
        max_it: u32,
        tolerance: f32,
    ) -> Vec<SolveStats> {
        let passes = h.iterations().min(max_it + 1);
        // The steps after the start's residual (the blocks a submission records).
        let iterations = passes.saturating_sub(1);
        self.last_iterations.store(iterations, Ordering::Relaxed);
        self.x_solved.store(true, Ordering::Relaxed);
        let seconds = t0.elapsed().as_secs_f64();
        (0..self.kv as usize)
            .map(|q| {
                let dark = h.dark(q);
                let residual = if dark {
                    0.0
                } else {
                    h.relative(q, passes as usize)
                };
                SolveStats {
                    method: Method::Jacobi,
                    iterations: if dark { 0 } else { iterations },
                    products: if dark { 0 } else { passes },
                    warm: matches!(job.warm, Input::Host(_) | Input::OnDevice),
                    residual,
                    converged: dark || h.stopped.is_some() || residual <= tolerance,
                    seconds,
                }
            })
            .collect()
    }
}

/// What a solve read back: its answer and each system's stats.
pub(crate) struct Run {
    /// The bytes of the job's answer (x, or what `out` names), system after system.
    pub(crate) out: Vec<u8>,
    /// Per system, ‖b‖ = 0: its answer is 0 whatever x holds.
    pub(crate) dark: Vec<bool>,
    pub(crate) stats: Vec<GpuSolveStats>,
}

/// The counter and the residual history as read back.
struct History {
    /// The next free slot.
    next: u32,
    /// The iteration whose residuals all met the tolerance.
    stopped: Option<u32>,
    /// Slot after slot, one entry per system: h[0] = ‖b‖², then the squared residual of
    /// each pass's iterate (the start's own first, then each step's).
    h: Vec<f32>,
    kv: usize,
}

impl History {
    fn parse(bytes: &[u8], slots: u32, kv: u32) -> History {
        let words: Vec<u32> = bytemuck::pod_collect_to_vec(&bytes[..16]);
        let head = counter_bytes(slots, kv) as usize;
        History {
            next: words[0],
            stopped: (words[1] != 0).then_some(words[1]),
            h: bytemuck::pod_collect_to_vec(&bytes[16..head]),
            kv: kv as usize,
        }
    }

    /// System q's ‖b‖ = 0.
    fn dark(&self, q: usize) -> bool {
        self.h.get(q).is_none_or(|&h0| h0 == 0.0)
    }

    fn all_dark(&self) -> bool {
        (0..self.kv).all(|q| self.dark(q))
    }

    /// Passes over F and S run (the start's residual, then the steps): up to the stop,
    /// else every slot after ‖b‖².
    fn iterations(&self) -> u32 {
        self.stopped.unwrap_or(self.next.saturating_sub(1))
    }

    /// System q's √h[k] / √h[0] (the residual of the iterate after pass k).
    fn relative(&self, q: usize, k: usize) -> f32 {
        match (self.h.get(q), self.h.get(k * self.kv + q)) {
            (Some(&h0), Some(&hk)) if k > 0 && h0 > 0.0 => {
                ((hk as f64).sqrt() / (h0 as f64).sqrt()) as f32
            }
            _ => f32::INFINITY,
        }
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
                gpk: groups,
                kv: 1,
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

/// What one dispatch of `mr_step` left ([`mr_step_once`]).
#[derive(Debug, Clone)]
pub struct MrStepRun {
    pub x: Vec<Rgb>,
    pub r: Vec<Rgb>,
    /// Per workgroup: Σ |r|², or for the dots Σ r_c v_c then Σ v_c² (six a workgroup).
    pub partial: Vec<f32>,
}

/// One dispatch of `mr_step` at `stage` on uploaded vectors of one system, α = `alpha`
/// (read by [`MrStage::Update`]): returns the new x, the new r and the per-workgroup
/// partials (what the tests hold to [`super::cpu_twin::mr_step`]).
///
/// [`MrStage::Update`]: super::cpu_twin::MrStage::Update
pub fn mr_step_once(
    ctx: &GpuContext,
    stage: super::cpu_twin::MrStage,
    b: &[Rgb],
    kr: &[Rgb],
    alpha: [f32; 4],
    x: &[Rgb],
    r: &[Rgb],
) -> Result<MrStepRun, GpuError> {
    use super::cpu_twin::MrStage;
    let n = x.len();
    if b.len() != n || kr.len() != n || r.len() != n {
        return Err(GpuError::Invalid(
            "b, kr, x and r must have equal lengths".into(),
        ));
    }
    let groups = (n as u32).div_ceil(256);
    let per = if stage == MrStage::Dots { 6 } else { 1 };
    ctx.scoped(|| {
        let g = grid(groups);
        let p = uniform(
            ctx,
            "vec-params",
            &VecParams {
                n: n as u32,
                groups_x: g.0,
                gpk: groups,
                kv: 1,
            },
        );
        let init =
            |what: &str, v: &[Rgb]| super::matrix::storage_init(ctx, what, bytemuck::cast_slice(v));
        let (bb, kb, xb, rb) = (init("b", b), init("kr", kr), init("x", x), init("r", r));
        let ab = super::matrix::storage_init(ctx, "alpha", bytemuck::cast_slice(&alpha));
        let pbytes = 4 * per * groups as u64;
        let pb = storage_zeroed(ctx, "partial", pbytes);
        let k = &ctx.kernels;
        let pipeline = match stage {
            MrStage::Residual => &k.mr_residual,
            MrStage::Dots => &k.mr_dots,
            MrStage::Update => &k.mr_update,
        };
        let op = BoundOp::new(
            pipeline.clone(),
            vec![(
                k.mr.bind(&ctx.device, &p, &[&bb, &kb, &ab, &xb, &rb, &pb]),
                g,
            )],
        );
        let vbytes = 12 * n as u64;
        let read = staging(ctx, "mr-read", 2 * vbytes + pbytes);
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            op.encode(&mut pass);
        }
        enc.copy_buffer_to_buffer(&xb, 0, &read, 0, vbytes);
        enc.copy_buffer_to_buffer(&rb, 0, &read, vbytes, vbytes);
        enc.copy_buffer_to_buffer(&pb, 0, &read, 2 * vbytes, pbytes);
        ctx.queue.submit([enc.finish()]);
        let all: Vec<f32> =
            bytemuck::pod_collect_to_vec(&ctx.read_back(&read, 2 * vbytes + pbytes)?);
        let rgb =
            |v: &[f32]| -> Vec<Rgb> { v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect() };
        Ok(MrStepRun {
            x: rgb(&all[..3 * n]),
            r: rgb(&all[3 * n..6 * n]),
            partial: all[6 * n..].to_vec(),
        })
    })
}

/// One dispatch of `mr_alpha` on `kv` systems' dots partials (six per workgroup, system
/// after system): returns α, four entries a system (what the tests hold to
/// [`super::cpu_twin::mr_alpha`]).
pub fn mr_alpha_once(ctx: &GpuContext, partial: &[f32], kv: u32) -> Result<Vec<f32>, GpuError> {
    let kv = kv.max(1);
    if partial.is_empty() || !partial.len().is_multiple_of(6 * kv as usize) {
        return Err(GpuError::Invalid(
            "partials must be six per workgroup, a multiple of kv workgroups".into(),
        ));
    }
    let count = (partial.len() / 6 / kv as usize) as u32;
    ctx.scoped(|| {
        let p = uniform(
            ctx,
            "alpha-params",
            &AlphaParams {
                count,
                kv,
                _pad0: 0,
                _pad1: 0,
            },
        );
        let pb = super::matrix::storage_init(ctx, "dots-partial", bytemuck::cast_slice(partial));
        let bytes = 16 * kv as u64;
        let ab = storage_zeroed(ctx, "alpha", bytes);
        let k = &ctx.kernels;
        let op = BoundOp::new(
            k.mr_alpha.clone(),
            vec![(k.alpha.bind(&ctx.device, &p, &[&pb, &ab]), (1, 1))],
        );
        let read = staging(ctx, "alpha-read", bytes);
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            op.encode(&mut pass);
        }
        enc.copy_buffer_to_buffer(&ab, 0, &read, 0, bytes);
        ctx.queue.submit([enc.finish()]);
        Ok(bytemuck::pod_collect_to_vec(&ctx.read_back(&read, bytes)?))
    })
}

/// `reduce_sum` dispatched once per entry of `partials` (each `kv` systems' partial sums,
/// system after system, all of one length, copied in before its dispatch) into a fresh
/// history of `partials.len()` slots, with the stopping rule at `tol2` over `n_args`
/// indirect triples (set to 1): answers the history, the counter and the triples (what the
/// tests hold to [`super::cpu_twin::reduce_stop`]).
pub fn reduce_sum_once(
    ctx: &GpuContext,
    partials: &[Vec<f32>],
    kv: u32,
    tol2: f32,
    n_args: u32,
) -> Result<super::cpu_twin::ReduceState, GpuError> {
    let len = partials.first().map_or(0, Vec::len);
    let kv = kv.max(1);
    if partials.iter().any(|p| p.len() != len) || !len.is_multiple_of(kv as usize) {
        return Err(GpuError::Invalid(
            "partials must have equal lengths, a multiple of kv".into(),
        ));
    }
    let count = len / kv as usize;
    let capacity = (partials.len() as u32).max(1);
    ctx.scoped(|| {
        let p = uniform(
            ctx,
            "reduce-params",
            &ReduceParams {
                count: count as u32,
                capacity,
                n_args,
                tol2,
                kv,
                _pad0: 0,
                _pad1: 0,
                _pad2: 0,
            },
        );
        let all: Vec<f32> = partials.iter().flatten().copied().collect();
        let src = super::matrix::storage_init(ctx, "partials", bytemuck::cast_slice(&all));
        let pb = storage_zeroed(ctx, "partial", 4 * len as u64);
        let hb = storage_zeroed(ctx, "history", 4 * (capacity * kv) as u64);
        let cb = storage_zeroed(ctx, "counter", 16);
        let ab = super::matrix::storage_init(
            ctx,
            "args",
            bytemuck::cast_slice(&vec![1u32; 3 * n_args as usize]),
        );
        let k = &ctx.kernels;
        let op = BoundOp::new(
            k.reduce_sum.clone(),
            vec![(
                k.reduce.bind(&ctx.device, &p, &[&pb, &hb, &cb, &ab]),
                (1, 1),
            )],
        );
        let (hbytes, abytes) = (4 * (capacity * kv) as u64, alloc_size(12 * n_args as u64));
        let read = staging(ctx, "reduce-read", 16 + hbytes + abytes);
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        for i in 0..partials.len() {
            let chunk = 4 * len as u64;
            if chunk > 0 {
                enc.copy_buffer_to_buffer(&src, i as u64 * chunk, &pb, 0, chunk);
            }
            let mut pass = enc.begin_compute_pass(&Default::default());
            op.encode(&mut pass);
        }
        enc.copy_buffer_to_buffer(&cb, 0, &read, 0, 16);
        enc.copy_buffer_to_buffer(&hb, 0, &read, 16, hbytes);
        enc.copy_buffer_to_buffer(&ab, 0, &read, 16 + hbytes, abytes);
        ctx.queue.submit([enc.finish()]);
        let bytes = ctx.read_back(&read, 16 + hbytes + abytes)?;
        let words: Vec<u32> = bytemuck::pod_collect_to_vec(&bytes);
        let h = 4 + (capacity * kv) as usize;
        Ok(super::cpu_twin::ReduceState {
            counter: [words[0], words[1]],
            history: bytemuck::cast_slice(&words[4..h]).to_vec(),
            args: words[h..h + 3 * n_args as usize].to_vec(),
        })
    })
}
