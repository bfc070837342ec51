//! The whole relight on the device: lights in, vertex colours out, one submission.
//!
//! In: a scene's [`GpuSystem`] (F, S and the solve), its bundle (the occluder triangles,
//! patch centroids and normals, emission), uploaded once by [`DeviceRelight::new`], and per
//! route the colour stage as rows ([`translux_engine::vertexrows::VertexRows`]), uploaded
//! on the route's first relight ([`DeviceRelight::route`]); per request the point, spot and
//! directional lamps of one relight or of a batch, each one's environments as the radiance
//! per direction bin (the visibility uploaded on the first, [`super::environment`]), the
//! components and the solve's tolerance. Out: B/π per viewer vertex for each relight, as
//! the engine's colour stage makes it, with what crossed the bus.
//!
//! Two routes: over the scene's system, K = S (`full`, `subsurface_only`; diffuse objects
//! count as opaque at the vertices), and over a system of K = P = diag ρ sharing the
//! scene's F (`direct`, `interreflection_only`; every object counts as opaque). One command
//! buffer records, in order (the system's one-submission solve, [`super::system`]):
//!
//! ```text
//!   direct_light at the patch centroids → E          (the occluder's BVH, [`super::direct`])
//!   direct_light at the vertices' sample points → E(v)
//!   env_irradiance: E += E_env = V L̄ per relight      (with an environment)
//!   Bₑ copied from the scene's emission; b = Bₑ + K E
//!   full, interreflection_only: the Jacobi iterations (minimal-residual steps, α on the
//!   device), stopped on the device; x starts from the last answer the system holds
//!   vertex_colours from B (x, or b without a solve), E − E_env, ρ and E(v) → colours
//!   copy the counter, the residual history and the colours to staging
//! ```
//!
//! A batch of relights (the worker pool's concurrent requests for one scene) runs
//! [`BATCH`] at a time in one such submission: each has its own direct light, and the
//! iterations read F and K once for all of them (`csr_spmv_rgb` with KV vectors); the solve
//! stops when every one has met the tolerance. The host writes only the lights, a few
//! parameters and an environment's bin radiance where it changed, and reads back the
//! colours (12 bytes a vertex and relight) with the counter and the history of the
//! iterations recorded.

use std::sync::OnceLock;

use translux_engine::radiosity::{Rgb, SolveParams};
use translux_engine::vertexrows::VertexRows;
use translux_proto::api::Components;
use translux_proto::bundle::Bundle;
use translux_proto::light::Light;

use super::direct::{DirectParams, DirectPass, GpuLight, GpuLights, GpuOccluder, SurfacePoints};
use super::environment::{EnvPass, GpuVisibility};
use super::kernels::BATCH;
use super::matrix::{BoundOp, alloc_size, staging, storage_init, storage_zeroed, uniform};
use super::system::{GpuSolveStats, GpuSystem, Input, Job, Lanes, Out, Rhs};
use super::{GpuContext, GpuError, grid};

/// Most lights one relight may carry (the engine's `relight::MAX_LIGHTS`).
const MAX_LIGHTS: usize = 256;

/// Keep in sync with `Params` in `vertex_colours.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ColourParams {
    nv: u32,
    groups_x: u32,
    overshoot: f32,
    inv_pi: f32,
    n: u32,
    kv: u32,
    gpv: u32,
    /// 1: the diffuse objects' direct light is left to a picture, and luminance written.
    pixel: u32,
}

/// The colour rows on the device (uploaded once, read by every lane).
#[derive(Debug)]
struct ColourRows {
    offsets: wgpu::Buffer,
    entries: wgpu::Buffer,
    own: wgpu::Buffer,
    albedo: wgpu::Buffer,
    overshoot: f32,
    n: usize,
    nv: usize,
}

impl ColourRows {
    fn upload(ctx: &GpuContext, rows: &VertexRows) -> ColourRows {
        let entries: Vec<[u32; 2]> = rows
            .patch
            .iter()
            .zip(&rows.weight)
            .map(|(&k, &w)| [k, w.to_bits()])
            .collect();
        ColourRows {
            offsets: storage_init(ctx, "colour-offsets", bytemuck::cast_slice(&rows.offsets)),
            entries: storage_init(ctx, "colour-entries", bytemuck::cast_slice(&entries)),
            own: storage_init(ctx, "colour-own", bytemuck::cast_slice(&rows.own)),
            albedo: storage_init(ctx, "albedo", bytemuck::cast_slice(&rows.albedo)),
            overshoot: rows.overshoot,
            n: rows.albedo.len(),
            nv: rows.len(),
        }
    }

    fn bytes(rows: &VertexRows) -> u64 {
        alloc_size(4 * (rows.len() as u64 + 1))
            + alloc_size(8 * rows.patch.len() as u64)
            + alloc_size(16 * rows.len() as u64)
            + alloc_size(12 * rows.albedo.len() as u64)
    }

    /// The `vertex_colours` dispatch for `kv` relights: B from `x`, E from `e` less its
    /// environment part `e_env`, E(v) from `ev`, colours into `out` (each relight's vector
    /// after the last's; with `pixel` the luminances after all the colours).
    fn bind(
        &self,
        ctx: &GpuContext,
        (kv, pixel): (u32, bool),
        (x, e, e_env, ev): (&wgpu::Buffer, &wgpu::Buffer, &wgpu::Buffer, &wgpu::Buffer),
        out: &wgpu::Buffer,
    ) -> BoundOp {
        let gpv = (self.nv as u32).div_ceil(256);
        let g = grid(gpv * kv);
        let params = uniform(
            ctx,
            "colour-params",
            &ColourParams {
                nv: self.nv as u32,
                groups_x: g.0,
                overshoot: self.overshoot,
                inv_pi: std::f32::consts::FRAC_1_PI,
                n: self.n as u32,
                kv,
                gpv,
                pixel: pixel as u32,
            },
        );
        let k = &ctx.kernels;
        let bind = k.colours.bind(
            &ctx.device,
            &params,
            &[
                &self.offsets,
                &self.entries,
                &self.own,
                &self.albedo,
                x,
                e,
                e_env,
                ev,
                out,
            ],
        );
        BoundOp::new(k.vertex_colours.clone(), vec![(bind, g)])
    }
}

/// The per-lane part of the whole relight: for each of the lane's relights a direct pass
/// at the patches and one at the vertices, E(v), the environments' part of E, the colours
/// and their staging.
#[derive(Debug)]
struct Lane {
    kv: usize,
    at_patches: Vec<DirectPass>,
    at_vertices: Vec<DirectPass>,
    /// A batch's per-relight E and E(v), copied into the lane's vectors after the direct
    /// passes (empty for one relight: its passes write the vectors themselves).
    e_parts: Vec<wgpu::Buffer>,
    ev_parts: Vec<wgpu::Buffer>,
    ev: wgpu::Buffer,
    /// E_env: the environments' part of E, relight after relight (0 until the lane's first
    /// environment).
    e_env: wgpu::Buffer,
    /// The `env_irradiance` pass, made on the lane's first relight with an environment
    /// (`Err`: it did not fit).
    env: OnceLock<Result<EnvPass, String>>,
    /// The colours from each [`ColoursFrom`] buffer the lanes have, each with the direct light
    /// at the vertices and with it per pixel: `colours[answer][pixel]`.
    colours: Vec<[BoundOp; 2]>,
    /// Each relight's colours, then (per pixel) each one's luminances.
    out: wgpu::Buffer,
    read: wgpu::Buffer,
    bytes: u64,
}

impl Lane {
    /// Bytes a lane of `kv` relights holds for `n` patches and `nv` vertices.
    fn bytes(kv: u64, n: u64, nv: u64, head: u64) -> u64 {
        let parts = if kv > 1 {
            kv * (alloc_size(12 * n) + alloc_size(12 * nv))
        } else {
            0
        };
        let lights = 2 * kv * alloc_size((MAX_LIGHTS * std::mem::size_of::<GpuLight>()) as u64);
        parts
            + lights
            + alloc_size(12 * nv * kv)
            + alloc_size(12 * n * kv)
            + 2 * alloc_size(head + 16 * nv * kv)
    }

    /// Binds a lane over `lanes` (the system's vectors for as many relights), its colours
    /// by `rows`.
    fn new(
        ctx: &GpuContext,
        (system, lanes): (&GpuSystem, &Lanes),
        scene: &SceneBuffers,
        rows: &ColourRows,
    ) -> Result<Lane, GpuError> {
        let (n, nv, kv) = (system.n(), rows.nv, lanes.kv());
        let bytes = Lane::bytes(kv as u64, n as u64, nv as u64, lanes.counter_bytes(system));
        ctx.reserve("relight lane", bytes)?;
        ctx.scoped(|| {
            let ev = storage_zeroed(ctx, "E(v)", 12 * (nv * kv) as u64);
            let e_env = storage_zeroed(ctx, "E_env", 12 * (n * kv) as u64);
            let (e_parts, ev_parts) = if kv > 1 {
                (
                    (0..kv).map(|_| DirectPass::output_buffer(ctx, n)).collect(),
                    (0..kv)
                        .map(|_| DirectPass::output_buffer(ctx, nv))
                        .collect(),
                )
            } else {
                (Vec::new(), Vec::new())
            };
            let mut at_patches = Vec::with_capacity(kv);
            let mut at_vertices = Vec::with_capacity(kv);
            for r in 0..kv {
                let (e_out, ev_out) = if kv > 1 {
                    (&e_parts[r], &ev_parts[r])
                } else {
                    (lanes.e_buffer(), &ev)
                };
                let p = &scene.patches;
                let v = &scene.vertices;
                let occ = &scene.occluder;
                at_patches.push(DirectPass::new(
                    ctx, occ, &p.points, &p.normals, n, e_out, MAX_LIGHTS,
                )?);
                at_vertices.push(DirectPass::new(
                    ctx, occ, &v.points, &v.normals, nv, ev_out, MAX_LIGHTS,
                )?);
            }
            let out = storage_zeroed(ctx, "colours", 16 * (nv * kv) as u64);
            let answers = [
                Some(lanes.x_buffer()),
                Some(lanes.b_buffer()),
                lanes.y_buffer(),
            ];
            let colours = answers
                .into_iter()
                .flatten()
                .map(|answer| {
                    let inputs = (answer, lanes.e_buffer(), &e_env, &ev);
                    [false, true].map(|pixel| rows.bind(ctx, (kv as u32, pixel), inputs, &out))
                })
                .collect();
            let read = staging(
                ctx,
                "relight-read",
                lanes.counter_bytes(system) + 16 * (nv * kv) as u64,
            );
            Ok(Lane {
                kv,
                at_patches,
                at_vertices,
                e_parts,
                ev_parts,
                ev,
                e_env,
                env: OnceLock::new(),
                colours,
                out,
                read,
                bytes,
            })
        })
        .inspect_err(|_| ctx.release(bytes))
    }

    /// GPU bytes held, its environment pass included.
    fn held(&self) -> u64 {
        self.bytes
            + match self.env.get() {
                Some(Ok(p)) => p.bytes(),
                _ => 0,
            }
    }

    /// The lane's environment pass over `vis`, made on first use.
    fn env_pass(
        &self,
        ctx: &GpuContext,
        lanes: &Lanes,
        vis: &GpuVisibility,
    ) -> Result<&EnvPass, GpuError> {
        self.env
            .get_or_init(|| {
                EnvPass::new(ctx, vis, self.kv, lanes.e_buffer(), &self.e_env)
                    .map_err(|e| e.to_string())
            })
            .as_ref()
            .map_err(|e| GpuError::Invalid(format!("the environment pass: {e}")))
    }

    /// Records the direct light of every relight of the lane, and for a batch the copies of
    /// each one's E and E(v) into the lane's vectors; then, with `env`, the environments'
    /// E added to E.
    fn record_direct(
        &self,
        enc: &mut wgpu::CommandEncoder,
        lanes: &Lanes,
        (n, nv): (usize, usize),
        env: Option<&EnvPass>,
    ) {
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            for (p, v) in self.at_patches.iter().zip(&self.at_vertices) {
                p.encode(&mut pass);
                v.encode(&mut pass);
            }
        }
        let (eb, evb) = (12 * n as u64, 12 * nv as u64);
        for (r, (e, ev)) in self.e_parts.iter().zip(&self.ev_parts).enumerate() {
            let r = r as u64;
            if eb > 0 {
                enc.copy_buffer_to_buffer(e, 0, lanes.e_buffer(), r * eb, eb);
            }
            if evb > 0 {
                enc.copy_buffer_to_buffer(ev, 0, &self.ev, r * evb, evb);
            }
        }
        if let Some(env) = env
            && n > 0
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            env.encode(&mut pass);
        }
    }
}

/// What every lane reads: the occluder and the sample points.
#[derive(Debug)]
struct SceneBuffers {
    occluder: GpuOccluder,
    patches: SurfacePoints,
    vertices: SurfacePoints,
}

/// The whole relights over one system: its colour rows (which objects count as opaque),
/// the lane of one relight and the lane of a batch (made on the first batch; `Err`: it did
/// not fit, and batches run one relight at a time).
#[derive(Debug)]
struct Route {
    /// Over the system of K = P = diag ρ ([`DeviceRelight::p`]); else over the scene's own
    /// system, K = S.
    over_p: bool,
    rows: ColourRows,
    one: Lane,
    batch: OnceLock<Result<Lane, String>>,
    /// Bytes of the rows.
    own_bytes: u64,
}

impl Route {
    /// GPU bytes held.
    fn bytes(&self) -> u64 {
        let batch = match self.batch.get() {
            Some(Ok(l)) => l.held(),
            _ => 0,
        };
        self.own_bytes + self.one.held() + batch
    }
}

/// Where a relight's colours are read from: x (a solve's answer), b (a product's, no
/// solve) or y (`heuristic_b`'s sum after its solve); the index into [`Lane::colours`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ColoursFrom {
    X = 0,
    B = 1,
    Y = 2,
}

/// How `components` run on the device: the route (0: over S, diffuse objects opaque at the
/// vertices; 1: over P, every object opaque; 2: over P, diffuse objects opaque), the
/// right-hand side, and where the answer is (b: one product, no solve).
fn plan_of(components: Components) -> (usize, Rhs, ColoursFrom) {
    match components {
        Components::Full => (0, Rhs::Own, ColoursFrom::X),
        Components::SubsurfaceOnly => (0, Rhs::Own, ColoursFrom::B),
        Components::Direct => (1, Rhs::Own, ColoursFrom::B),
        Components::InterreflectionOnly => (1, Rhs::Own, ColoursFrom::X),
        Components::HeuristicA => (2, Rhs::SceneS, ColoursFrom::X),
        Components::HeuristicB => (2, Rhs::Bounced, ColoursFrom::Y),
    }
}

/// What a scene keeps on the device for its whole relights, beside its [`GpuSystem`].
#[derive(Debug)]
pub struct DeviceRelight {
    scene: SceneBuffers,
    emission: wgpu::Buffer,
    /// The system of K = P = diag ρ over the scene's F, with the scene's S beside it, made
    /// with the first route over it (`Err`: it did not fit).
    p: OnceLock<Result<GpuSystem, String>>,
    /// The routes of [`plan_of`], each made on its first relight ([`DeviceRelight::route`];
    /// `Err`: it did not fit).
    routes: [OnceLock<Result<Route, String>>; 3],
    /// The bundle's environment visibility, uploaded on the first relight with an
    /// environment ([`DeviceRelight::environment`]; `Err`: the bundle has none, or it did
    /// not fit).
    visibility: OnceLock<Result<GpuVisibility, String>>,
    nv: usize,
    unit_mm: f64,
    /// Bytes of the emission.
    own_bytes: u64,
    /// One relight at a time from writing its lights to reading its colours: the light
    /// buffers are shared.
    busy: std::sync::Mutex<()>,
}

impl DeviceRelight {
    /// Uploads what every whole relight needs beside `system`: the occluder, the patches'
    /// and the vertices' sample points (`rows`' points: every set of colour rows has the
    /// same) and the emission; on failure every byte reserved is returned to the budget.
    /// Each route is made on its first relight ([`DeviceRelight::route`]).
    pub fn new(
        ctx: &GpuContext,
        system: &GpuSystem,
        bundle: &Bundle,
        rows: &VertexRows,
    ) -> Result<DeviceRelight, GpuError> {
        let n = system.n();
        if bundle.patch_areas().len() != n || rows.albedo.len() != n {
            return Err(GpuError::Invalid(format!(
                "the scene's system has {n} patches, its bundle {} and the colour rows {}",
                bundle.patch_areas().len(),
                rows.albedo.len()
            )));
        }
        let tris: Vec<[glam::Vec3; 3]> = bundle
            .occluder_triangles()
            .iter()
            .map(|t| t.map(glam::Vec3::from))
            .collect();
        let occluder = GpuOccluder::upload(ctx, &tris)?;
        let (centroids, normals) = SurfacePoints::of_bundle(bundle);
        let patches = SurfacePoints::upload(ctx, &centroids, &normals)
            .inspect_err(|_| ctx.release(occluder.bytes()))?;
        let points: Vec<glam::Vec3> = rows.point.iter().map(|&p| p.into()).collect();
        let vnormals: Vec<glam::Vec3> = rows.normal.iter().map(|&p| p.into()).collect();
        let vertices = SurfacePoints::upload(ctx, &points, &vnormals)
            .inspect_err(|_| ctx.release(occluder.bytes() + patches.bytes()))?;
        let held = occluder.bytes() + patches.bytes() + vertices.bytes();
        let own_bytes = alloc_size(12 * n as u64);
        ctx.reserve("relight buffers", own_bytes)
            .inspect_err(|_| ctx.release(held))?;
        let emission = match ctx.scoped(|| {
            Ok(storage_init(
                ctx,
                "emission",
                bytemuck::cast_slice(bundle.patch_emission()),
            ))
        }) {
            Ok(made) => made,
            Err(e) => {
                ctx.release(held + own_bytes);
                return Err(e);
            }
        };
        Ok(DeviceRelight {
            scene: SceneBuffers {
                occluder,
                patches,
                vertices,
            },
            emission,
            p: OnceLock::new(),
            routes: [OnceLock::new(), OnceLock::new(), OnceLock::new()],
            visibility: OnceLock::new(),
            nv: rows.len(),
            unit_mm: bundle.manifest().unit_mm,
            own_bytes,
            busy: std::sync::Mutex::new(()),
        })
    }

    /// The route of `components` (over S or over P, by which objects count as opaque),
    /// made on its first call with its colour `rows` (and the first over P with P's system: K = diag of `rows`' albedo, the
    /// bundle's ρ, over `system`'s F); `Err` says why such relights cannot run here (rows
    /// of another scene, or the route does not fit), and a route that did not fit is said
    /// once in the log and kept.
    pub fn route(
        &self,
        ctx: &GpuContext,
        system: &GpuSystem,
        components: Components,
        rows: &VertexRows,
    ) -> Result<(), String> {
        let (k, ..) = plan_of(components);
        let n = system.n();
        if rows.albedo.len() != n || rows.len() != self.nv {
            return Err(format!(
                "the colour rows span {} patches and {} vertices, the scene {n} and {}",
                rows.albedo.len(),
                rows.len(),
                self.nv
            ));
        }
        self.routes[k]
            .get_or_init(|| {
                let made = self.make_route(ctx, system, k, rows);
                if let Err(e) = &made {
                    tracing::warn!(
                        "{} relights take the engine's stages: {e}",
                        components.as_str()
                    );
                }
                made
            })
            .as_ref()
            .map(|_| ())
            .map_err(Clone::clone)
    }

    /// The system of K = P over `base`'s F, made on first use from `albedo`.
    fn p_system(
        &self,
        ctx: &GpuContext,
        base: &GpuSystem,
        albedo: &[Rgb],
    ) -> Result<&GpuSystem, String> {
        self.p
            .get_or_init(|| {
                base.with_diagonal(ctx, "P", albedo)
                    .map_err(|e| e.to_string())
            })
            .as_ref()
            .map_err(Clone::clone)
    }

    /// Uploads route `k`'s colour rows (and the first over P, P's system) and binds its
    /// lane of one relight; on failure the rows' bytes are returned to the budget.
    fn make_route(
        &self,
        ctx: &GpuContext,
        base: &GpuSystem,
        k: usize,
        rows: &VertexRows,
    ) -> Result<Route, String> {
        let over_p = k > 0;
        let on = if over_p {
            self.p_system(ctx, base, &rows.albedo)?
        } else {
            base
        };
        let own_bytes = ColourRows::bytes(rows);
        ctx.reserve("colour rows", own_bytes)
            .map_err(|e| e.to_string())?;
        let made = ctx
            .scoped(|| Ok(ColourRows::upload(ctx, rows)))
            .and_then(|rows| {
                let one = Lane::new(ctx, (on, on.one()), &self.scene, &rows)?;
                Ok((rows, one))
            });
        match made {
            Ok((rows, one)) => Ok(Route {
                over_p,
                rows,
                one,
                batch: OnceLock::new(),
                own_bytes,
            }),
            Err(e) => {
                ctx.release(own_bytes);
                Err(e.to_string())
            }
        }
    }

    /// GPU bytes held.
    pub fn bytes(&self) -> u64 {
        let routes: u64 = self
            .routes
            .iter()
            .filter_map(|r| r.get()?.as_ref().ok())
            .map(Route::bytes)
            .sum();
        let vis = match self.visibility.get() {
            Some(Ok(v)) => v.bytes(),
            _ => 0,
        };
        let p = match self.p.get() {
            Some(Ok(p)) => p.own_bytes(),
            _ => 0,
        };
        self.scene.occluder.bytes()
            + self.scene.patches.bytes()
            + self.scene.vertices.bytes()
            + self.own_bytes
            + routes
            + p
            + vis
    }

    /// Makes environment relights possible: uploads `bundle`'s environment visibility on
    /// the first call (the bundle this was made with); `Err` says why they cannot run here
    /// (no visibility in the bundle, or it does not fit), and is kept.
    pub fn environment(&self, ctx: &GpuContext, bundle: &Bundle) -> Result<(), String> {
        self.visibility
            .get_or_init(|| {
                let Some(vis) = bundle.environment_visibility() else {
                    return Err("the bundle holds no environment visibility".into());
                };
                let n = self.scene.patches.len();
                if vis.bins() == 0 || vis.bits.len() != vis.bins() * n {
                    return Err(format!(
                        "the environment visibility holds {} values, not {} patches × {} bins",
                        vis.bits.len(),
                        n,
                        vis.bins()
                    ));
                }
                let up = GpuVisibility::upload(ctx, vis).map_err(|e| e.to_string());
                match &up {
                    Ok(v) => tracing::info!(
                        "environment visibility on the GPU: {} bins, {} KiB",
                        v.bins(),
                        v.bytes() >> 10
                    ),
                    Err(e) => tracing::warn!("environment lights stay on the CPU: {e}"),
                }
                up
            })
            .as_ref()
            .map(|_| ())
            .map_err(Clone::clone)
    }

    /// Returns the bytes to the context's budget; call when dropping it.
    pub fn release(self, ctx: &GpuContext) {
        let bytes = self.bytes();
        drop(self);
        ctx.release(bytes);
    }

    /// The relights of `lights` (one set of point, spot and directional lamps per relight,
    /// their environment lights given instead as `environment`: per relight the bins' total
    /// radiance L̄, or `None`) under `components` on `system`, the system this was made
    /// with: B/π per vertex and the solve's stats with what crossed the bus, per relight.
    /// One relight runs alone; several run [`BATCH`] at a time where the batch's vectors
    /// fit (else one by one). Each solve starts from the last answer its route's system
    /// holds; `subsurface_only` and `direct` make one product and no solve. The route of
    /// `components` needs [`DeviceRelight::route`], and a relight with an environment
    /// [`DeviceRelight::environment`], to have succeeded first.
    pub fn relight(
        &self,
        ctx: &GpuContext,
        system: &GpuSystem,
        (lights, environment): (&[&[Light]], &[Option<Vec<Rgb>>]),
        params: &SolveParams,
        (components, pixel): (Components, bool),
    ) -> Result<Vec<Answer>, GpuError> {
        let (k, rhs, from) = plan_of(components);
        let (route, p) = (self.routes[k].get(), self.p.get());
        let (route, system) = match (route, p) {
            (Some(Ok(r)), _) if !r.over_p => (r, system),
            (Some(Ok(r)), Some(Ok(p))) => (r, p),
            _ => {
                return Err(GpuError::Invalid(format!(
                    "the route of {} is not on the device",
                    components.as_str()
                )));
            }
        };
        let how = How {
            params,
            pixel,
            rhs,
            from,
        };
        if environment.len() != lights.len() {
            return Err(GpuError::Invalid(format!(
                "{} sets of lights but {} environments",
                lights.len(),
                environment.len()
            )));
        }
        let env: Vec<Option<&[Rgb]>> = environment.iter().map(|l| l.as_deref()).collect();
        if env.iter().any(Option::is_some) {
            match self.visibility.get() {
                Some(Ok(v)) if env.iter().flatten().all(|l| l.len() == v.bins()) => {}
                Some(Ok(v)) => {
                    return Err(GpuError::Invalid(format!(
                        "an environment's radiance must have one value per bin ({})",
                        v.bins()
                    )));
                }
                _ => {
                    return Err(GpuError::Invalid(
                        "environment lights without the visibility on the device".into(),
                    ));
                }
            }
        }
        let batch = if lights.len() > 1 {
            self.batch_lane(ctx, system, route)
        } else {
            None
        };
        let mut answers = Vec::with_capacity(lights.len());
        let per = match batch {
            Some(_) => BATCH as usize,
            None => 1,
        };
        let lane = batch.unwrap_or((&route.one, system.one()));
        for (chunk, env) in lights.chunks(per).zip(env.chunks(per)) {
            answers.extend(self.run_lane(ctx, system, lane, (chunk, env), &how)?);
        }
        Ok(answers)
    }

    /// The batch's lane of `route` and its vectors, made on the first batch; `None` when
    /// they do not fit.
    fn batch_lane<'a>(
        &'a self,
        ctx: &GpuContext,
        system: &'a GpuSystem,
        route: &'a Route,
    ) -> Option<(&'a Lane, &'a Lanes)> {
        let lanes = system.batch(ctx)?;
        let lane = route.batch.get_or_init(|| {
            Lane::new(ctx, (system, lanes), &self.scene, &route.rows).map_err(|e| {
                tracing::warn!("batched relights run one by one: {e}");
                e.to_string()
            })
        });
        lane.as_ref().ok().map(|l| (l, lanes))
    }

    /// One submission's relights (at most the lane's): their lights and environments'
    /// radiance written (lanes past them get none), the solve (or the product) run, each
    /// one's colours and its share of the bytes.
    fn run_lane(
        &self,
        ctx: &GpuContext,
        system: &GpuSystem,
        (lane, lanes): (&Lane, &Lanes),
        (lights, env): (&[&[Light]], &[Option<&[Rgb]>]),
        how: &How<'_>,
    ) -> Result<Vec<Answer>, GpuError> {
        let pixel = how.pixel;
        if !lanes.makes(how.rhs) {
            return Err(GpuError::Invalid(format!(
                "the system cannot make the right-hand side {:?}",
                how.rhs
            )));
        }
        let _busy = self.busy.lock().unwrap_or_else(|p| p.into_inner());
        let mut lights_up = 0u64;
        for r in 0..lane.kv {
            let set = lights.get(r).copied().unwrap_or(&[]);
            let lamps = GpuLights::new(set, self.scene.occluder.diagonal(), self.unit_mm);
            lane.at_patches[r].write_lights(ctx, &lamps)?;
            lane.at_vertices[r].write_lights(ctx, &lamps)?;
            lights_up += 2
                * (std::mem::size_of_val(lamps.lights.as_slice())
                    + std::mem::size_of::<DirectParams>()) as u64;
        }
        // The environments: the lane's pass is made on its first one; once made it runs
        // while any relight has one, and once more after to clear E_env.
        let env_pass = match self.visibility.get() {
            Some(Ok(vis)) if env.iter().any(Option::is_some) => {
                Some(lane.env_pass(ctx, lanes, vis)?)
            }
            _ => lane.env.get().and_then(|p| p.as_ref().ok()),
        };
        let env_pass = env_pass.and_then(|p| {
            let (up, run) = p.write(ctx, env);
            lights_up += up;
            run.then_some(p)
        });
        let (n, nv) = (system.n(), self.nv);
        let before =
            |enc: &mut wgpu::CommandEncoder| lane.record_direct(enc, lanes, (n, nv), env_pass);
        let colours = lane.colours.get(how.from as usize).ok_or_else(|| {
            GpuError::Invalid(format!("these lanes hold no {:?} to colour", how.from))
        })?;
        let colours = &colours[usize::from(pixel)];
        let after = |pass: &mut wgpu::ComputePass<'_>| colours.encode(pass);
        // Only the lanes that carry a relight are read back: their colours, and per pixel
        // their luminances.
        let m = lights.len();
        let mut ranges = vec![(&lane.out, 0, 12 * (nv * m) as u64)];
        if pixel {
            ranges.push((&lane.out, 12 * (nv * lane.kv) as u64, 4 * (nv * m) as u64));
        }
        let job = Job {
            e: Input::OnDevice,
            be: Input::Copy(&self.emission),
            warm: if lanes.holds_answer() {
                Input::OnDevice
            } else {
                Input::Absent
            },
            before: Some(&before),
            rhs: how.rhs,
            after: Some(&after),
            out: Some(Out {
                ranges,
                staging: &lane.read,
            }),
        };
        let run = match how.from {
            ColoursFrom::B => system.product(ctx, lanes, &job, how.params)?,
            ColoursFrom::X | ColoursFrom::Y => system.run(ctx, lanes, &job, how.params)?,
        };
        let share = m.max(1) as u64;
        let lum_at = 12 * nv * m;
        Ok((0..m)
            .map(|r| {
                let floats = |at: usize, count: usize| -> Vec<f32> {
                    bytemuck::pod_collect_to_vec(&run.out[at..at + 4 * count])
                };
                let radiance: Vec<Rgb> = if run.dark[r] {
                    vec![[0.0; 3]; nv]
                } else {
                    let v = floats(12 * nv * r, 3 * nv);
                    v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
                };
                let luminance = pixel.then(|| {
                    if run.dark[r] {
                        vec![0.0; nv]
                    } else {
                        floats(lum_at + 4 * nv * r, nv)
                    }
                });
                let mut stats = run.stats[r];
                stats.bytes_up = (stats.bytes_up + lights_up).div_ceil(share);
                stats.bytes_down = stats.bytes_down.div_ceil(share);
                Answer {
                    radiance,
                    luminance,
                    stats,
                }
            })
            .collect())
    }
}

/// How a lane's relights run: the solve's parameters, the direct light per pixel or not,
/// the right-hand side and where the colours read B (from b: one product, no solve).
struct How<'a> {
    params: &'a SolveParams,
    pixel: bool,
    rhs: Rhs,
    from: ColoursFrom,
}

/// One whole relight's answer: B/π per vertex, with the direct light per pixel the
/// luminance of the whole answer per vertex, and the solve's stats.
#[derive(Debug, Clone)]
pub struct Answer {
    pub radiance: Vec<Rgb>,
    pub luminance: Option<Vec<f32>>,
    pub stats: GpuSolveStats,
}

/// One `vertex_colours` dispatch on uploaded inputs: B (`x`), E (`e`) and its
/// environment part (`e_env`) per patch, E at each vertex (`ev`), the direct light per
/// pixel or not: the colours, and with `pixel` the luminances (what the tests hold to
/// [`super::cpu_twin::vertex_colours`]).
pub fn vertex_colours_once(
    ctx: &GpuContext,
    rows: &VertexRows,
    (x, e, e_env, ev): (&[Rgb], &[Rgb], &[Rgb], &[Rgb]),
    pixel: bool,
) -> Result<(Vec<Rgb>, Vec<f32>), GpuError> {
    let (n, nv) = (rows.albedo.len(), rows.len());
    if x.len() != n || e.len() != n || e_env.len() != n || ev.len() != nv {
        return Err(GpuError::Invalid(format!(
            "x has {}, e {}, e_env {} and ev {} entries; the rows span {n} patches and {nv} \
             vertices",
            x.len(),
            e.len(),
            e_env.len(),
            ev.len()
        )));
    }
    ctx.scoped(|| {
        let dev_rows = ColourRows::upload(ctx, rows);
        let xb = storage_init(ctx, "x", bytemuck::cast_slice(x));
        let eb = storage_init(ctx, "e", bytemuck::cast_slice(e));
        let envb = storage_init(ctx, "e-env", bytemuck::cast_slice(e_env));
        let evb = storage_init(ctx, "ev", bytemuck::cast_slice(ev));
        let bytes = alloc_size(16 * nv as u64);
        let out = storage_zeroed(ctx, "colours", bytes);
        let op = dev_rows.bind(ctx, (1, pixel), (&xb, &eb, &envb, &evb), &out);
        let read = staging(ctx, "colours-read", bytes);
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            op.encode(&mut pass);
        }
        enc.copy_buffer_to_buffer(&out, 0, &read, 0, bytes);
        ctx.queue.submit([enc.finish()]);
        let v: Vec<f32> = ctx.read_back_as(&read, bytes)?;
        let colours = v[..3 * nv]
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect();
        let lum = if pixel {
            v[3 * nv..4 * nv].to_vec()
        } else {
            Vec::new()
        };
        Ok((colours, lum))
    })
}
