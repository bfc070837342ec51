//! The whole relight on the device: lights in, vertex colours out, one submission.
//!
//! In: a scene's [`GpuSystem`] (F, S and the solve), its bundle (the occluder triangles,
//! patch centroids and normals, emission) and the colour stage as rows
//! ([`translux_engine::vertexrows::VertexRows`]), uploaded once by [`DeviceRelight::new`];
//! per request the point, spot and directional lamps and the solve's tolerance. Out: B/π
//! per viewer vertex, as the engine's colour stage makes it, with what crossed the bus.
//!
//! One command buffer records, in order (the system's one-submission solve, [`super::system`]):
//!
//! ```text
//!   direct_light at the patch centroids → E          (the occluder's BVH, [`super::direct`])
//!   direct_light at the vertices' sample points → E(v)
//!   Bₑ copied from the scene's emission; b = Bₑ + S E; the Jacobi iterations, stopped on
//!   the device; x starts from the last answer the device holds
//!   vertex_colours from B, E, ρ and E(v) → colours
//!   copy the counter, the residual history and the colours to staging
//! ```
//!
//! The host writes only the lights and a few parameters, and reads back the colours (12
//! bytes a vertex) with the counter and the history of the iterations recorded.

use translux_engine::radiosity::{Rgb, SolveParams};
use translux_engine::vertexrows::VertexRows;
use translux_proto::bundle::Bundle;
use translux_proto::light::Light;

use super::direct::{DirectPass, GpuLights, GpuOccluder, SurfacePoints};
use super::matrix::{BoundOp, alloc_size, staging, storage_init, storage_zeroed, uniform};
use super::system::{GpuSolveStats, GpuSystem, Input, Job};
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
}

/// What a scene keeps on the device for its whole relights, beside its [`GpuSystem`].
#[derive(Debug)]
pub struct DeviceRelight {
    occluder: GpuOccluder,
    patches: SurfacePoints,
    vertices: SurfacePoints,
    at_patches: DirectPass,
    at_vertices: DirectPass,
    emission: wgpu::Buffer,
    colours: BoundOp,
    out: wgpu::Buffer,
    read: wgpu::Buffer,
    nv: usize,
    unit_mm: f64,
    /// Bytes of the buffers this holds besides the occluder and the points.
    own_bytes: u64,
    /// One relight at a time from writing its lights to reading its colours: the light
    /// buffers are shared.
    busy: std::sync::Mutex<()>,
}

impl DeviceRelight {
    /// Uploads what the whole relight needs beside `system`: the occluder, the patches'
    /// and the vertices' sample points, the emission and the colour rows; on failure
    /// every byte reserved is returned to the budget.
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
        let nv = rows.len();
        let own_bytes = 2 * alloc_size(12 * nv as u64)
            + alloc_size(12 * n as u64)
            + alloc_size(system.counter_bytes() + 12 * nv as u64)
            + alloc_size(4 * (nv as u64 + 1))
            + alloc_size(8 * rows.patch.len() as u64)
            + alloc_size(16 * nv as u64)
            + alloc_size(12 * n as u64);
        ctx.reserve("relight buffers", own_bytes)
            .inspect_err(|_| ctx.release(held))?;
        let made = ctx.scoped(|| {
            let ev = storage_zeroed(ctx, "E(v)", 12 * nv as u64);
            let at_patches = DirectPass::new(
                ctx,
                &occluder,
                &patches.points,
                &patches.normals,
                n,
                system.e_buffer(),
                MAX_LIGHTS,
            )?;
            let at_vertices = DirectPass::new(
                ctx,
                &occluder,
                &vertices.points,
                &vertices.normals,
                nv,
                &ev,
                MAX_LIGHTS,
            )?;
            let emission = storage_init(
                ctx,
                "emission",
                bytemuck::cast_slice(bundle.patch_emission()),
            );
            let out = storage_zeroed(ctx, "colours", 12 * nv as u64);
            let colours = bind_colours(ctx, rows, system.x_buffer(), system.e_buffer(), &ev, &out);
            let read = staging(ctx, "relight-read", system.counter_bytes() + 12 * nv as u64);
            Ok((at_patches, at_vertices, emission, colours, out, read))
        });
        match made {
            Ok((at_patches, at_vertices, emission, colours, out, read)) => Ok(DeviceRelight {
                occluder,
                patches,
                vertices,
                at_patches,
                at_vertices,
                emission,
                colours,
                out,
                read,
                nv,
                unit_mm: bundle.manifest().unit_mm,
                own_bytes,
                busy: std::sync::Mutex::new(()),
            }),
            Err(e) => {
                ctx.release(held + own_bytes);
                Err(e)
            }
        }
    }

    /// GPU bytes held.
    pub fn bytes(&self) -> u64 {
        self.occluder.bytes() + self.patches.bytes() + self.vertices.bytes() + self.own_bytes
    }

    /// Returns the bytes to the context's budget; call when dropping it.
    pub fn release(self, ctx: &GpuContext) {
        let bytes = self.bytes();
        drop(self);
        ctx.release(bytes);
    }

    /// The relight of `lights` (point, spot and directional; environment lights are
    /// refused) on `system`, the system this was made with: B/π per vertex and the solve's
    /// stats with what crossed the bus. Starts from the last answer the device holds.
    pub fn relight(
        &self,
        ctx: &GpuContext,
        system: &GpuSystem,
        lights: &[Light],
        params: &SolveParams,
    ) -> Result<(Vec<Rgb>, GpuSolveStats), GpuError> {
        if lights
            .iter()
            .any(|l| matches!(l, Light::Environment { .. }))
        {
            return Err(GpuError::Invalid(
                "environment lights are lit on the CPU, not in a device relight".into(),
            ));
        }
        let lamps = GpuLights::new(lights, self.occluder.diagonal(), self.unit_mm);
        let _busy = self.busy.lock().unwrap_or_else(|p| p.into_inner());
        self.at_patches.write_lights(ctx, &lamps)?;
        self.at_vertices.write_lights(ctx, &lamps)?;
        let lights_up = 2
            * (std::mem::size_of_val(lamps.lights.as_slice())
                + std::mem::size_of::<super::direct::DirectParams>()) as u64;
        let before = |pass: &mut wgpu::ComputePass<'_>| {
            self.at_patches.encode(pass);
            self.at_vertices.encode(pass);
        };
        let after = |pass: &mut wgpu::ComputePass<'_>| self.colours.encode(pass);
        let job = Job {
            e: Input::OnDevice,
            be: Input::Copy(&self.emission),
            warm: if system.holds_answer() {
                Input::OnDevice
            } else {
                Input::Absent
            },
            before: Some(&before),
            after: Some(&after),
            out: Some((&self.out, 12 * self.nv as u64, &self.read)),
        };
        let run = system.run(ctx, &job, params)?;
        let radiance: Vec<Rgb> = if run.dark {
            vec![[0.0; 3]; self.nv]
        } else {
            let v: Vec<f32> = bytemuck::pod_collect_to_vec(&run.out);
            v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
        };
        let mut stats = run.stats;
        stats.bytes_up += lights_up;
        Ok((radiance, stats))
    }
}

/// The `vertex_colours` dispatch over `rows`, reading B from `x`, E from `e` and E(v)
/// from `ev`, writing `out`.
fn bind_colours(
    ctx: &GpuContext,
    rows: &VertexRows,
    x: &wgpu::Buffer,
    e: &wgpu::Buffer,
    ev: &wgpu::Buffer,
    out: &wgpu::Buffer,
) -> BoundOp {
    let nv = rows.len();
    let g = grid((nv as u32).div_ceil(256));
    let params = uniform(
        ctx,
        "colour-params",
        &ColourParams {
            nv: nv as u32,
            groups_x: g.0,
            overshoot: rows.overshoot,
            inv_pi: std::f32::consts::FRAC_1_PI,
        },
    );
    let entries: Vec<[u32; 2]> = rows
        .patch
        .iter()
        .zip(&rows.weight)
        .map(|(&k, &w)| [k, w.to_bits()])
        .collect();
    let offsets = storage_init(ctx, "colour-offsets", bytemuck::cast_slice(&rows.offsets));
    let entries = storage_init(ctx, "colour-entries", bytemuck::cast_slice(&entries));
    let own = storage_init(ctx, "colour-own", bytemuck::cast_slice(&rows.own));
    let albedo = storage_init(ctx, "albedo", bytemuck::cast_slice(&rows.albedo));
    let k = &ctx.kernels;
    let bind = k.colours.bind(
        &ctx.device,
        &params,
        &[&offsets, &entries, &own, &albedo, x, e, ev, out],
    );
    BoundOp::new(k.vertex_colours.clone(), vec![(bind, g)])
}

/// One `vertex_colours` dispatch on uploaded inputs: B (`x`) and E (`e`) per patch, E at
/// each vertex (`ev`); what the tests hold to [`super::cpu_twin::vertex_colours`].
pub fn vertex_colours_once(
    ctx: &GpuContext,
    rows: &VertexRows,
    x: &[Rgb],
    e: &[Rgb],
    ev: &[Rgb],
) -> Result<Vec<Rgb>, GpuError> {
    let (n, nv) = (rows.albedo.len(), rows.len());
    if x.len() != n || e.len() != n || ev.len() != nv {
        return Err(GpuError::Invalid(format!(
            "x has {}, e {} and ev {} entries; the rows span {n} patches and {nv} vertices",
            x.len(),
            e.len(),
            ev.len()
        )));
    }
    ctx.scoped(|| {
        let xb = storage_init(ctx, "x", bytemuck::cast_slice(x));
        let eb = storage_init(ctx, "e", bytemuck::cast_slice(e));
        let evb = storage_init(ctx, "ev", bytemuck::cast_slice(ev));
        let out = storage_zeroed(ctx, "colours", 12 * nv as u64);
        let op = bind_colours(ctx, rows, &xb, &eb, &evb, &out);
        let read = staging(ctx, "colours-read", 12 * nv as u64);
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            op.encode(&mut pass);
        }
        enc.copy_buffer_to_buffer(&out, 0, &read, 0, alloc_size(12 * nv as u64));
        ctx.queue.submit([enc.finish()]);
        let v: Vec<f32> = ctx.read_back_as(&read, alloc_size(12 * nv as u64))?;
        Ok(v[..3 * nv]
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect())
    })
}
