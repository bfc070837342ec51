//! Direct light on the device: a binary BVH over the scene's occluder triangles, shadow
//! rays through it, and the shadowed direct irradiance E of point, spot and directional
//! lights at surface points.
//!
//! In: the occluder triangles (a bundle's `occluder_triangles()`, what the engine's
//! [`Occluder`] is built from), surface points with their normals (patch centroids, once per
//! scene), and per request the lights ([`GpuLights`], a few hundred bytes). Out: one
//! occluded flag per ray (`shadow_rays.wgsl`), or E as tightly packed RGB f32 triples per
//! point (`direct_light.wgsl`), the same numbers as
//! [`translux_engine::radiosity::direct_irradiance`] (same origin offset, same segment
//! margins, same spot fall-off).
//!
//! ```text
//!  host:   triangles + 2 padding ──obvhs BVH2 (PLOC)──▶ FlatBvh { nodes, tris in leaf order }
//!  device: nodes  [BvhNode; N]   lo, a | hi, count     (count 0: children a, a + 1;
//!                                                        count > 0: tris a .. a + count)
//!          tris   [BvhTri; M]    v0, v1, v2 as vec4
//! ```
//!
//! The tree is obvhs's BVH2 (the engine's CWBVH is built from it but its compressed,
//! quantised nodes have no plain form to upload). Node boxes are recomputed on the host from
//! the triangles, widened by the triangle test's barycentric tolerance, so that the
//! traversal finds every triangle the test accepts: a ray's answer is that of a loop over
//! all triangles. The two padding triangles the engine adds (for obvhs's Morton-code
//! wrap-around) are built into the tree too, and written degenerate (never hit).

use glam::Vec3;
use obvhs::{BvhBuildParams, bvh2::builder::build_bvh2_from_tris, triangle::Triangle};
use translux_engine::radiosity::Rgb;
use translux_proto::light::Light;

use super::matrix::{alloc_size, staging, storage_init, storage_zeroed, uniform};
use super::{GpuContext, GpuError, grid};

#[cfg(doc)]
use translux_engine::raycast::Occluder;

/// Entries of the traversal stack in `bvh_traverse.wgsl` (`STACK`): a tree deeper than this
/// is refused at upload.
pub const MAX_DEPTH: u32 = 64;
/// Threads per workgroup of `shadow_rays.wgsl` and `direct_light.wgsl` (`WG`).
pub const DIRECT_WG: u32 = 64;
/// The barycentric tolerance of the triangle test (`EPS` in `bvh_traverse.wgsl`, the
/// engine's `intersect_closed`).
pub const TRI_EPS: f32 = 1e-5;

/// A node of the flattened tree. Keep in sync with `Node` in `bvh_traverse.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct BvhNode {
    pub lo: [f32; 3],
    /// Inner node: the left child (the right is `a + 1`); leaf: the first triangle.
    pub a: u32,
    pub hi: [f32; 3],
    /// 0 for an inner node, else the leaf's triangle count.
    pub count: u32,
}

/// A triangle as the device reads it (vertices padded to vec4). Keep in sync with `Tri` in
/// `bvh_traverse.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct BvhTri {
    pub v: [[f32; 4]; 3],
}

/// A shadow ray: hit test within `(tmin, tmax)` along `dir` (not necessarily unit). Keep in
/// sync with `RayIn` in `shadow_rays.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct ShadowRay {
    pub origin: [f32; 3],
    pub tmin: f32,
    pub dir: [f32; 3],
    pub tmax: f32,
}

impl ShadowRay {
    /// The open segment (a, b) as [`Occluder::occluded`] tests it: direction b − a, margins
    /// 1e-4 at both ends.
    pub fn segment(a: Vec3, b: Vec3) -> ShadowRay {
        ShadowRay {
            origin: a.into(),
            tmin: 1e-4,
            dir: (b - a).into(),
            tmax: 1.0 - 1e-4,
        }
    }

    /// The ray of [`Occluder::occluded_dir`] (−0.0 components of `dir` made +0.0, as there).
    pub fn along(origin: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> ShadowRay {
        ShadowRay {
            origin: origin.into(),
            tmin,
            dir: (dir + Vec3::ZERO).into(),
            tmax,
        }
    }
}

/// The tree on the host, flattened as the device reads it.
#[derive(Debug, Clone)]
pub struct FlatBvh {
    pub nodes: Vec<BvhNode>,
    /// Triangles in leaf order (padding ones degenerate).
    pub tris: Vec<BvhTri>,
    /// The bounding-box diagonal of the real triangles, as [`Occluder::diagonal`].
    pub diagonal: f32,
    /// Nodes on the longest root-to-leaf path.
    pub depth: u32,
}

/// `lo`/`hi` bounds of a set of points.
#[derive(Debug, Clone, Copy)]
struct Bounds {
    lo: Vec3,
    hi: Vec3,
}

impl Bounds {
    const EMPTY: Bounds = Bounds {
        lo: Vec3::splat(f32::INFINITY),
        hi: Vec3::splat(f32::NEG_INFINITY),
    };

    fn grow(self, p: Vec3) -> Bounds {
        Bounds {
            lo: self.lo.min(p),
            hi: self.hi.max(p),
        }
    }

    fn union(self, o: Bounds) -> Bounds {
        Bounds {
            lo: self.lo.min(o.lo),
            hi: self.hi.max(o.hi),
        }
    }

    fn widen(self, by: f32) -> Bounds {
        Bounds {
            lo: self.lo - Vec3::splat(by),
            hi: self.hi + Vec3::splat(by),
        }
    }
}

impl FlatBvh {
    /// Builds the tree over `triangles` (plus the engine's two padding triangles).
    pub fn build(triangles: &[[Vec3; 3]]) -> FlatBvh {
        let (tris, diagonal) = translux_engine::raycast::padded_triangles(triangles);
        let bvh = build_bvh2_from_tris(
            &tris,
            BvhBuildParams::medium_build(),
            &mut std::time::Duration::default(),
        );
        let n_real = triangles.len();
        let ordered: Vec<(Triangle, bool)> = bvh
            .primitive_indices
            .iter()
            .map(|&k| (tris[k as usize], k as usize >= n_real))
            .collect();
        let mut nodes: Vec<BvhNode> = bvh
            .nodes
            .iter()
            .map(|n| BvhNode {
                lo: [0.0; 3],
                a: n.first_index,
                hi: [0.0; 3],
                count: n.prim_count,
            })
            .collect();
        let depth = fit_boxes(&mut nodes, &ordered, diagonal);
        FlatBvh {
            nodes,
            tris: ordered.iter().map(|&(t, pad)| device_tri(t, pad)).collect(),
            diagonal,
            depth,
        }
    }

    /// Bytes on the device.
    pub fn bytes(&self) -> u64 {
        alloc_size(std::mem::size_of_val(&self.nodes[..]) as u64)
            + alloc_size(std::mem::size_of_val(&self.tris[..]) as u64)
    }
}

/// The device form of a triangle; a padding triangle collapses to one point (never hit:
/// its determinant is 0).
fn device_tri(t: Triangle, padding: bool) -> BvhTri {
    let v = if padding {
        [t.v0, t.v0, t.v0]
    } else {
        [t.v0, t.v1, t.v2]
    };
    BvhTri {
        v: v.map(|p| [p.x, p.y, p.z, 0.0]),
    }
}

/// A triangle's box widened by what the test's tolerance accepts beyond its edges (4 ×
/// `TRI_EPS` of its extent) and 1e-6 of the scene's diagonal for rounding in the slab test.
fn tri_bounds(t: &Triangle, diagonal: f32) -> Bounds {
    let b = [t.v0, t.v1, t.v2]
        .iter()
        .fold(Bounds::EMPTY, |b, &v| b.grow(v.into()));
    let extent = (b.hi - b.lo).max_element();
    b.widen(4.0 * TRI_EPS * extent + 1e-6 * diagonal)
}

/// Sets every node's box from the triangles under it (children before parents: the reverse
/// of a pre-order walk) and returns the tree's depth.
fn fit_boxes(nodes: &mut [BvhNode], ordered: &[(Triangle, bool)], diagonal: f32) -> u32 {
    let mut order = Vec::with_capacity(nodes.len());
    let mut depth = 0u32;
    let mut stack = vec![(0usize, 1u32)];
    while let Some((i, d)) = stack.pop() {
        order.push(i);
        depth = depth.max(d);
        if nodes[i].count == 0 {
            let a = nodes[i].a as usize;
            stack.push((a, d + 1));
            stack.push((a + 1, d + 1));
        }
    }
    for &i in order.iter().rev() {
        let n = nodes[i];
        let b = if n.count > 0 {
            let (a, c) = (n.a as usize, n.count as usize);
            ordered[a..a + c]
                .iter()
                .fold(Bounds::EMPTY, |b, (t, _)| b.union(tri_bounds(t, diagonal)))
        } else {
            let (l, r) = (nodes[n.a as usize], nodes[n.a as usize + 1]);
            let bl = Bounds {
                lo: l.lo.into(),
                hi: l.hi.into(),
            };
            bl.union(Bounds {
                lo: r.lo.into(),
                hi: r.hi.into(),
            })
        };
        nodes[i].lo = b.lo.into();
        nodes[i].hi = b.hi.into();
    }
    depth
}

/// Light kinds of [`GpuLight::kind`] (`KIND_AT`, `KIND_FAR` in `direct_light.wgsl`).
pub const LIGHT_AT: u32 = 0;
pub const LIGHT_FAR: u32 = 1;

/// One light as `direct_light.wgsl` reads it. Keep in sync with `Light` there.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct GpuLight {
    /// Point/spot: position; directional: unit direction toward the light (w unused).
    pub pos: [f32; 4],
    /// Intensity (W·sr⁻¹) or irradiance (W·m⁻²), RGB (w unused).
    pub power: [f32; 4],
    /// The spot's unit axis (w unused).
    pub axis: [f32; 4],
    /// [`LIGHT_AT`] or [`LIGHT_FAR`].
    pub kind: u32,
    /// 1 for a spot (a cone), 0 otherwise.
    pub cone: u32,
    /// cos of the inner and outer half-angles, in f32 as `spot_falloff` computes them.
    pub cos_inner: f32,
    pub cos_outer: f32,
}

/// The point, spot and directional lights of a request, ready for `direct_light.wgsl`,
/// with the scene constants of the engine's `PointLights` (environment lights are skipped).
#[derive(Debug, Clone)]
pub struct GpuLights {
    pub lights: Vec<GpuLight>,
    /// Shadow rays start this far off the surface (1e-5 × diagonal).
    pub offset: f32,
    /// Rays toward directional lights end here (4 × diagonal).
    pub far: f32,
    /// Metres per scene unit.
    pub to_m: f32,
}

impl GpuLights {
    /// `diagonal` is the occluder's ([`GpuOccluder::diagonal`]), `unit_mm` the scene's
    /// millimetres per unit.
    pub fn new(lights: &[Light], diagonal: f32, unit_mm: f64) -> GpuLights {
        GpuLights {
            lights: lights.iter().filter_map(gpu_light).collect(),
            offset: 1e-5 * diagonal,
            far: 4.0 * diagonal,
            to_m: (unit_mm / 1000.0) as f32,
        }
    }

    pub fn len(&self) -> usize {
        self.lights.len()
    }

    pub fn is_empty(&self) -> bool {
        self.lights.is_empty()
    }
}

fn vec4(v: Vec3) -> [f32; 4] {
    [v.x, v.y, v.z, 0.0]
}

/// One light in device form, as the engine's `PointLights::new` reads it.
fn gpu_light(l: &Light) -> Option<GpuLight> {
    let at = |position: &[f32; 3], intensity: &[f32; 3]| GpuLight {
        pos: vec4(Vec3::from(*position)),
        power: vec4(Vec3::from(*intensity)),
        axis: [0.0; 4],
        kind: LIGHT_AT,
        cone: 0,
        cos_inner: 1.0,
        cos_outer: 1.0,
    };
    match l {
        Light::Point {
            position,
            intensity,
        } => Some(at(position, intensity)),
        Light::Spot {
            position,
            intensity,
            direction,
            inner_deg,
            outer_deg,
        } => Some(GpuLight {
            axis: vec4(Vec3::from(*direction).normalize_or_zero()),
            cone: 1,
            cos_inner: inner_deg.to_radians().cos(),
            cos_outer: outer_deg.to_radians().cos(),
            ..at(position, intensity)
        }),
        Light::Directional {
            direction,
            irradiance,
        } => Some(GpuLight {
            // −0.0 made +0.0, as `Occluder::occluded_dir` does with its ray.
            pos: vec4(-Vec3::from(*direction).normalize_or_zero() + Vec3::ZERO),
            power: vec4(Vec3::from(*irradiance)),
            axis: [0.0; 4],
            kind: LIGHT_FAR,
            cone: 0,
            cos_inner: 1.0,
            cos_outer: 1.0,
        }),
        Light::Environment { .. } => None,
    }
}

/// Keep in sync with `Params` in `shadow_rays.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct RayParams {
    n: u32,
    groups_x: u32,
    _pad0: u32,
    _pad1: u32,
}

/// Keep in sync with `Params` in `direct_light.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct DirectParams {
    pub count: u32,
    pub n: u32,
    pub groups_x: u32,
    pub _pad0: u32,
    pub offset: f32,
    pub far: f32,
    pub to_m: f32,
    pub _pad1: f32,
}

impl DirectParams {
    /// The parameters of `lights` over `n` points.
    pub fn new(lights: &GpuLights, n: usize) -> DirectParams {
        DirectParams {
            count: lights.len() as u32,
            n: n as u32,
            groups_x: grid(groups(n)).0,
            _pad0: 0,
            offset: lights.offset,
            far: lights.far,
            to_m: lights.to_m,
            _pad1: 0.0,
        }
    }
}

/// Workgroups for `n` items.
fn groups(n: usize) -> u32 {
    (n as u32).div_ceil(DIRECT_WG)
}

/// The occluder tree on the device.
#[derive(Debug)]
pub struct GpuOccluder {
    nodes: wgpu::Buffer,
    tris: wgpu::Buffer,
    diagonal: f32,
    bytes: u64,
}

impl GpuOccluder {
    /// Builds the tree over `triangles` and uploads it ([`FlatBvh::build`]).
    pub fn upload(ctx: &GpuContext, triangles: &[[Vec3; 3]]) -> Result<GpuOccluder, GpuError> {
        Self::from_flat(ctx, &FlatBvh::build(triangles))
    }

    /// Uploads a tree built on the host, counting its bytes against the context's budget.
    pub fn from_flat(ctx: &GpuContext, flat: &FlatBvh) -> Result<GpuOccluder, GpuError> {
        check_depth(flat)?;
        let bytes = flat.bytes();
        ctx.reserve("occluder BVH", bytes)?;
        let made = ctx.scoped(|| {
            Ok((
                storage_init(ctx, "bvh-nodes", bytemuck::cast_slice(&flat.nodes)),
                storage_init(ctx, "bvh-tris", bytemuck::cast_slice(&flat.tris)),
            ))
        });
        match made {
            Ok((nodes, tris)) => Ok(GpuOccluder {
                nodes,
                tris,
                diagonal: flat.diagonal,
                bytes,
            }),
            Err(e) => {
                ctx.release(bytes);
                Err(e)
            }
        }
    }

    /// The real triangles' bounding-box diagonal, as `Occluder::diagonal`.
    pub fn diagonal(&self) -> f32 {
        self.diagonal
    }

    /// GPU bytes held.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Returns this tree's bytes to the context's budget; call when dropping it.
    pub fn release(self, ctx: &GpuContext) {
        let bytes = self.bytes;
        drop(self);
        ctx.release(bytes);
    }

    /// One occluded flag per ray (`shadow_rays.wgsl`), uploading the rays and reading the
    /// flags back (tests and one-off queries).
    pub fn shadow_rays_once(
        &self,
        ctx: &GpuContext,
        rays: &[ShadowRay],
    ) -> Result<Vec<bool>, GpuError> {
        let n = rays.len();
        if n == 0 {
            return Ok(Vec::new());
        }
        ctx.scoped(|| {
            let g = grid(groups(n));
            let params = RayParams {
                n: n as u32,
                groups_x: g.0,
                _pad0: 0,
                _pad1: 0,
            };
            let p = uniform(ctx, "shadow-params", &params);
            let rb = storage_init(ctx, "rays", bytemuck::cast_slice(rays));
            let out = storage_zeroed(ctx, "occluded", 4 * n as u64);
            let k = &ctx.kernels;
            let bg = k
                .shadow
                .bind(&ctx.device, &p, &[&self.nodes, &self.tris, &rb, &out]);
            let words: Vec<u32> = run_and_read(ctx, &k.shadow_rays, &bg, g, &out, 4 * n as u64)?;
            Ok(words[..n].iter().map(|&w| w != 0).collect())
        })
    }

    /// E at each point (`direct_light.wgsl`), uploading points, normals and lights and
    /// reading E back (tests and one-off queries; the relight uses [`DirectPass`]).
    pub fn direct_light_once(
        &self,
        ctx: &GpuContext,
        points: &[Vec3],
        normals: &[Vec3],
        lights: &GpuLights,
    ) -> Result<Vec<Rgb>, GpuError> {
        let n = points.len();
        if normals.len() != n {
            return Err(GpuError::Invalid(format!(
                "{n} points but {} normals",
                normals.len()
            )));
        }
        if n == 0 {
            return Ok(Vec::new());
        }
        ctx.scoped(|| {
            let pb = storage_init(ctx, "points", bytemuck::cast_slice(points));
            let nb = storage_init(ctx, "normals", bytemuck::cast_slice(normals));
            let out = storage_zeroed(ctx, "direct-e", 12 * n as u64);
            let pass = DirectPass::bind(ctx, self, &pb, &nb, n, &out, lights.len().max(1));
            pass.write_lights(ctx, lights)?;
            let g = grid(groups(n));
            let floats: Vec<f32> =
                run_and_read(ctx, &pass.pipeline, &pass.bind, g, &out, 12 * n as u64)?;
            Ok(floats[..3 * n]
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect())
        })
    }
}

/// Refuses a tree deeper than the kernels' traversal stack.
fn check_depth(flat: &FlatBvh) -> Result<(), GpuError> {
    if flat.depth > MAX_DEPTH {
        return Err(GpuError::Invalid(format!(
            "the occluder BVH is {} levels deep; the device traversal holds {MAX_DEPTH}",
            flat.depth
        )));
    }
    Ok(())
}

/// Runs one dispatch of `pipeline` and reads `bytes` of `out` back.
fn run_and_read<T: bytemuck::Pod>(
    ctx: &GpuContext,
    pipeline: &wgpu::ComputePipeline,
    bind: &wgpu::BindGroup,
    g: (u32, u32),
    out: &wgpu::Buffer,
    bytes: u64,
) -> Result<Vec<T>, GpuError> {
    let st = staging(ctx, "direct-read", bytes);
    let mut enc = ctx.device.create_command_encoder(&Default::default());
    {
        let mut pass = enc.begin_compute_pass(&Default::default());
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, bind, &[]);
        pass.dispatch_workgroups(g.0, g.1, 1);
    }
    enc.copy_buffer_to_buffer(out, 0, &st, 0, alloc_size(bytes));
    ctx.queue.submit([enc.finish()]);
    ctx.read_back_as(&st, alloc_size(bytes))
}

/// A scene's surface points and normals on the device (tightly packed f32 triples), uploaded
/// once per scene.
#[derive(Debug)]
pub struct SurfacePoints {
    pub points: wgpu::Buffer,
    pub normals: wgpu::Buffer,
    n: usize,
    bytes: u64,
}

impl SurfacePoints {
    /// Uploads `points` and `normals` (equal lengths), counting them against the budget.
    pub fn upload(
        ctx: &GpuContext,
        points: &[Vec3],
        normals: &[Vec3],
    ) -> Result<SurfacePoints, GpuError> {
        let n = points.len();
        if normals.len() != n {
            return Err(GpuError::Invalid(format!(
                "{n} points but {} normals",
                normals.len()
            )));
        }
        let bytes = 2 * alloc_size(12 * n as u64);
        ctx.reserve("surface points", bytes)?;
        ctx.scoped(|| {
            Ok(SurfacePoints {
                points: storage_init(ctx, "points", bytemuck::cast_slice(points)),
                normals: storage_init(ctx, "normals", bytemuck::cast_slice(normals)),
                n,
                bytes,
            })
        })
        .inspect_err(|_| ctx.release(bytes))
    }

    /// A bundle's patch centroids and normals, as the engine's `BundleLighting` makes them.
    pub fn of_bundle(b: &translux_proto::bundle::Bundle) -> (Vec<Vec3>, Vec<Vec3>) {
        let centroid = b
            .patch_corners()
            .iter()
            .map(|c| (Vec3::from(c[0]) + Vec3::from(c[1]) + Vec3::from(c[2])) / 3.0)
            .collect();
        let normal = b.patch_normals().iter().map(|&n| Vec3::from(n)).collect();
        (centroid, normal)
    }

    pub fn len(&self) -> usize {
        self.n
    }

    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Returns the bytes to the context's budget; call when dropping it.
    pub fn release(self, ctx: &GpuContext) {
        let bytes = self.bytes;
        drop(self);
        ctx.release(bytes);
    }
}

/// The direct-light dispatch bound to a scene's buffers, recorded into the relight's own
/// compute pass, so that E, the solve and the colours go in one submission. Per request
/// only the lights are written ([`DirectPass::write_lights`]).
#[derive(Debug)]
pub struct DirectPass {
    pipeline: wgpu::ComputePipeline,
    params: wgpu::Buffer,
    lights: wgpu::Buffer,
    bind: wgpu::BindGroup,
    n: usize,
    max_lights: usize,
    groups: (u32, u32),
}

impl DirectPass {
    /// Binds `occ` to `points` and `normals` (`n` f32 triples each) and `out` (E, `n` RGB
    /// f32 triples), with room for `max_lights` lights.
    pub fn new(
        ctx: &GpuContext,
        occ: &GpuOccluder,
        points: &wgpu::Buffer,
        normals: &wgpu::Buffer,
        n: usize,
        out: &wgpu::Buffer,
        max_lights: usize,
    ) -> Result<DirectPass, GpuError> {
        let needed = 12 * n as u64;
        for (what, b) in [("points", points), ("normals", normals), ("E", out)] {
            if b.size() < needed {
                return Err(GpuError::Invalid(format!(
                    "the {what} buffer holds {} bytes; {n} points need {needed}",
                    b.size()
                )));
            }
        }
        ctx.scoped(|| {
            Ok(Self::bind(
                ctx,
                occ,
                points,
                normals,
                n,
                out,
                max_lights.max(1),
            ))
        })
    }

    fn bind(
        ctx: &GpuContext,
        occ: &GpuOccluder,
        points: &wgpu::Buffer,
        normals: &wgpu::Buffer,
        n: usize,
        out: &wgpu::Buffer,
        max_lights: usize,
    ) -> DirectPass {
        let empty = GpuLights {
            lights: Vec::new(),
            offset: 0.0,
            far: 0.0,
            to_m: 1.0,
        };
        let params = uniform(ctx, "direct-params", &DirectParams::new(&empty, n));
        let lights = storage_zeroed(
            ctx,
            "lights",
            (max_lights * std::mem::size_of::<GpuLight>()) as u64,
        );
        let bind = ctx.kernels.direct.bind(
            &ctx.device,
            &params,
            &[&occ.nodes, &occ.tris, points, normals, &lights, out],
        );
        DirectPass {
            pipeline: ctx.kernels.direct_light.clone(),
            params,
            lights,
            bind,
            n,
            max_lights,
            groups: grid(groups(n)),
        }
    }

    /// Writes a request's lights (at most `max_lights`) and the scene constants.
    pub fn write_lights(&self, ctx: &GpuContext, lights: &GpuLights) -> Result<(), GpuError> {
        if lights.len() > self.max_lights {
            return Err(GpuError::Invalid(format!(
                "{} lights; this scene's direct pass holds {}",
                lights.len(),
                self.max_lights
            )));
        }
        if !lights.is_empty() {
            ctx.queue
                .write_buffer(&self.lights, 0, bytemuck::cast_slice(&lights.lights));
        }
        let params = DirectParams::new(lights, self.n);
        ctx.queue
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        Ok(())
    }

    /// Records the dispatch into `pass`; the pipeline and bind group are left set.
    pub fn encode(&self, pass: &mut wgpu::ComputePass<'_>) {
        if self.n == 0 {
            return;
        }
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind, &[]);
        pass.dispatch_workgroups(self.groups.0, self.groups.1, 1);
    }

    /// A zeroed buffer for E of `n` points (what [`DirectPass::new`] writes into).
    pub fn output_buffer(ctx: &GpuContext, n: usize) -> wgpu::Buffer {
        storage_zeroed(ctx, "direct-e", 12 * n as u64)
    }

    /// Records this pass ([`DirectPass::encode`]) in a submission of its own and reads E
    /// back from `out`, the buffer it was made with (tests).
    pub fn run_once(&self, ctx: &GpuContext, out: &wgpu::Buffer) -> Result<Vec<Rgb>, GpuError> {
        let bytes = 12 * self.n as u64;
        ctx.scoped(|| {
            let st = staging(ctx, "direct-read", bytes);
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                self.encode(&mut pass);
            }
            enc.copy_buffer_to_buffer(out, 0, &st, 0, alloc_size(bytes));
            ctx.queue.submit([enc.finish()]);
            let floats: Vec<f32> = ctx.read_back_as(&st, alloc_size(bytes))?;
            Ok(floats[..3 * self.n]
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect())
        })
    }
}
