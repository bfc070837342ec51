// vertex_colours: B/π per viewer vertex from B, E and ρ per patch and E at the vertex
// (translux_engine::vertexrows), one thread per vertex:
//
//   mean vertex (own.w = 0):   L = Σ_k w_k B_k                 (w = a_k / (π Σ a))
//   opaque vertex (own.w = 1): c = Σ_k w_k (B_k − ρ_k E'_k), clamped to its terms' spread
//                              widened by `overshoot` on each side;
//                              L = max(0, (c + ρ̄ E(v)) / π),   ρ̄ = own.xyz
//   a diffuse object's (own.w = 2): the same, without ρ̄ E(v) when `pixel` is set; the
//                              luminance of the whole L is written beside the colours
//
// E' = E − E_env: the lamps' part of E. E(v) holds the lamps alone, so the environment's
// direct light stays in the patches' smooth part c (the engine's `at_patch`); E_env is 0
// for relights without an environment (`env_irradiance` writes it).
//
// A batch of kv relights lies vector after vector: relight r's B, E and E_env at r · n, its
// E(v) and colours at r · nv; each has gpv workgroups. CPU twin: `cpu_twin::vertex_colours`.

const WG: u32 = 256u;

struct Params {
    nv: u32,
    groups_x: u32,
    overshoot: f32,
    inv_pi: f32,
    // Patches, relights in the batch, workgroups per relight.
    n: u32,
    kv: u32,
    gpv: u32,
    // 1: the direct light of diffuse objects is added per pixel (own.w = 2 leaves it out),
    // and the luminance of the whole answer follows the colours (at 3 · nv · kv).
    pixel: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> offsets: array<u32>;
// (patch, weight bits) per entry.
@group(0) @binding(2) var<storage, read> entries: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read> own: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> albedo: array<f32>;
@group(0) @binding(5) var<storage, read> x: array<f32>;
@group(0) @binding(6) var<storage, read> e: array<f32>;
@group(0) @binding(7) var<storage, read> e_env: array<f32>;
@group(0) @binding(8) var<storage, read> ev: array<f32>;
@group(0) @binding(9) var<storage, read_write> out: array<f32>;

// B of patch k in the relight whose vectors start at patch `at`.
fn x_at(at: u32, k: u32) -> vec3<f32> {
    let o = 3u * (at + k);
    return vec3<f32>(x[o], x[o + 1u], x[o + 2u]);
}

fn rho_e_at(at: u32, k: u32) -> vec3<f32> {
    let rho = vec3<f32>(albedo[3u * k], albedo[3u * k + 1u], albedo[3u * k + 2u]);
    let o = 3u * (at + k);
    let env = vec3<f32>(e_env[o], e_env[o + 1u], e_env[o + 2u]);
    let lamps = vec3<f32>(e[o], e[o + 1u], e[o + 2u]) - env;
    return rho * lamps;
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let g = wid.x + wid.y * p.groups_x;
    let r = g / p.gpv;
    let q = (g % p.gpv) * WG + li;
    if (q >= p.nv || r >= p.kv) {
        return;
    }
    let at = r * p.n;
    let out_at = 3u * (r * p.nv + q);
    let a = offsets[q];
    let z = offsets[q + 1u];
    let o = own[q];
    var value = vec3<f32>(0.0);
    var whole = vec3<f32>(0.0);
    if (o.w == 0.0) {
        for (var k = a; k < z; k++) {
            let en = entries[k];
            value += bitcast<f32>(en.y) * x_at(at, en.x);
        }
        whole = value;
    } else {
        var sum = vec3<f32>(0.0);
        var lo = vec3<f32>(0.0);
        var hi = vec3<f32>(0.0);
        for (var k = a; k < z; k++) {
            let en = entries[k];
            let t = x_at(at, en.x) - rho_e_at(at, en.x);
            sum += bitcast<f32>(en.y) * t;
            if (k == a) {
                lo = t;
                hi = t;
            } else {
                lo = min(lo, t);
                hi = max(hi, t);
            }
        }
        var rest = vec3<f32>(0.0);
        if (z > a) {
            let slack = p.overshoot * (hi - lo);
            rest = clamp(sum, lo - slack, hi + slack);
        }
        let e_v = vec3<f32>(ev[out_at], ev[out_at + 1u], ev[out_at + 2u]);
        whole = max((rest + o.xyz * e_v) * p.inv_pi, vec3<f32>(0.0));
        value = whole;
        if (p.pixel == 1u && o.w == 2.0) {
            value = max(rest * p.inv_pi, vec3<f32>(0.0));
        }
    }
    if (p.pixel == 1u) {
        out[3u * p.nv * p.kv + r * p.nv + q] = dot(whole, vec3<f32>(0.2126, 0.7152, 0.0722));
    }
    out[out_at] = value.x;
    out[out_at + 1u] = value.y;
    out[out_at + 2u] = value.z;
}
