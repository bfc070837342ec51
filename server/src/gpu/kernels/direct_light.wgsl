// direct_light: the shadowed direct irradiance E (W·m⁻²) at surface points from point, spot
// and directional lights (after bvh_traverse.wgsl), per point i with normal n:
//
//     origin = p + n · offset
//     point/spot: d = pos − origin, r = |d|, cos = n·d / r > 0, segment (origin, pos) clear:
//                 E += I · spot · cos / (r · to_m)²
//                 spot = smoothstep of axis·normalize(p − pos) from cos_outer to cos_inner
//     directional: cos = n·l > 0, ray (origin, l, 0, far) clear: E += irradiance · cos
//
// the engine's `PointLights::each`. In: points and normals (f32 triples), lights
// (`gpu::direct::GpuLight`). Out: E, RGB f32 triples. CPU twin: `cpu_twin::direct_light`.
// Keep Params in sync with `gpu::direct::DirectParams`.

const WG: u32 = 64u;
const KIND_AT: u32 = 0u;

struct Params {
    count: u32,
    n: u32,
    groups_x: u32,
    _pad0: u32,
    offset: f32,
    far: f32,
    to_m: f32,
    _pad1: f32,
}

struct Light {
    pos: vec4<f32>,
    power: vec4<f32>,
    axis: vec4<f32>,
    kind: u32,
    cone: u32,
    cos_inner: f32,
    cos_outer: f32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(3) var<storage, read> points: array<f32>;
@group(0) @binding(4) var<storage, read> normals: array<f32>;
@group(0) @binding(5) var<storage, read> lights: array<Light>;
@group(0) @binding(6) var<storage, read_write> e_out: array<f32>;

fn load3(i: u32, from_normals: bool) -> vec3<f32> {
    if (from_normals) {
        return vec3<f32>(normals[3u * i], normals[3u * i + 1u], normals[3u * i + 2u]);
    }
    return vec3<f32>(points[3u * i], points[3u * i + 1u], points[3u * i + 2u]);
}

// The engine's `spot_falloff` from precomputed cosines.
fn falloff(c: f32, ci: f32, co: f32) -> f32 {
    if (c >= ci) {
        return 1.0;
    }
    if (c <= co) {
        return 0.0;
    }
    let t = (c - co) / (ci - co);
    return t * t * (3.0 - 2.0 * t);
}

// glam's `normalize_or_zero`.
fn normalize_or_zero(v: vec3<f32>) -> vec3<f32> {
    let len = length(v);
    if (len > 0.0) {
        return v * (1.0 / len);
    }
    return vec3<f32>(0.0);
}

// The irradiance of light l at point x (normal n, shadow-ray origin o), 0 when shadowed.
fn light_at(l: Light, x: vec3<f32>, n: vec3<f32>, o: vec3<f32>) -> vec3<f32> {
    if (l.kind == KIND_AT) {
        let pos = l.pos.xyz;
        let d = pos - o;
        let r = length(d);
        if (r <= 0.0) {
            return vec3<f32>(0.0);
        }
        let c = dot(n, d) / r;
        if (c <= 0.0) {
            return vec3<f32>(0.0);
        }
        var spot = 1.0;
        if (l.cone != 0u) {
            spot = falloff(dot(l.axis.xyz, normalize_or_zero(x - pos)), l.cos_inner, l.cos_outer);
        }
        if (spot <= 0.0 || occluded(Ray(o, d, 1e-4, 1.0 - 1e-4))) {
            return vec3<f32>(0.0);
        }
        let rm = r * p.to_m;
        let w = spot * c / (rm * rm);
        return w * l.power.xyz;
    }
    let to_light = l.pos.xyz;
    let c = dot(n, to_light);
    if (c <= 0.0 || occluded(Ray(o, to_light, 0.0, p.far))) {
        return vec3<f32>(0.0);
    }
    return c * l.power.xyz;
}

@compute @workgroup_size(64)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let i = (wid.x + wid.y * p.groups_x) * WG + li;
    if (i >= p.n) {
        return;
    }
    let x = load3(i, false);
    let n = load3(i, true);
    let o = x + n * p.offset;
    var e = vec3<f32>(0.0);
    for (var k = 0u; k < p.count; k++) {
        e += light_at(lights[k], x, n, o);
    }
    e_out[3u * i] = e.x;
    e_out[3u * i + 1u] = e.y;
    e_out[3u * i + 2u] = e.z;
}
