// shadow_rays: one occluded flag per ray against the occluder BVH (after bvh_traverse.wgsl).
//
// In: rays (origin, tmin, direction, tmax; `gpu::direct::ShadowRay`). Out: occluded[i] = 1
// when a triangle is hit strictly within (tmin, tmax) of ray i, else 0. CPU twin:
// `cpu_twin::shadow_rays`. Keep Params in sync with `gpu::direct::RayParams`.

const WG: u32 = 64u;

struct Params {
    n: u32,
    groups_x: u32,
    _pad0: u32,
    _pad1: u32,
}

struct RayIn {
    o: vec3<f32>,
    tmin: f32,
    d: vec3<f32>,
    tmax: f32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(3) var<storage, read> rays: array<RayIn>;
@group(0) @binding(4) var<storage, read_write> occluded_out: array<u32>;

@compute @workgroup_size(64)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let i = (wid.x + wid.y * p.groups_x) * WG + li;
    if (i >= p.n) {
        return;
    }
    let q = rays[i];
    occluded_out[i] = select(0u, 1u, occluded(Ray(q.o, q.d, q.tmin, q.tmax)));
}
