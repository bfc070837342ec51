// env_irradiance: an environment's direct irradiance from the bundle's visibility
// (translux_engine::environment::direct_irradiance), one thread per patch and relight:
//
//   E_env,i = Σ_k V_ik L̄_k      (k in bin order, summed in one f32 accumulator)
//   E_i    += E_env,i           (E holds the lamps' light from `direct_light`)
//
// V: the bundle's visibility as half floats, two to a u32 word (bin 2w in the low half, as
// `unpack2x16float` reads it), `words` words a patch (an odd bin count pads each row).
// L̄: per relight, the bins' total radiance (Σ over its environments of scale · the bin's
// mean), `bins` RGB triples. A batch of kv relights lies vector after vector: relight r's E
// and E_env at r · n, its L̄ at r · bins; each has gpn workgroups. Bit r of `lit` clear:
// relight r has no environment, its E_env is written 0 and E is left as it is.
// CPU twin: `cpu_twin::env_irradiance`.

const WG: u32 = 256u;

struct Params {
    n: u32,
    bins: u32,
    words: u32,
    groups_x: u32,
    kv: u32,
    gpn: u32,
    // Bit r: relight r has an environment.
    lit: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> vis: array<u32>;
@group(0) @binding(2) var<storage, read> radiance: array<f32>;
@group(0) @binding(3) var<storage, read_write> e: array<f32>;
@group(0) @binding(4) var<storage, read_write> e_env: array<f32>;

// L̄ of bin k in the relight whose bins start at `at`.
fn radiance_at(at: u32, k: u32) -> vec3<f32> {
    let o = 3u * (at + k);
    return vec3<f32>(radiance[o], radiance[o + 1u], radiance[o + 2u]);
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let g = wid.x + wid.y * p.groups_x;
    let r = g / p.gpn;
    let i = (g % p.gpn) * WG + li;
    if (i >= p.n || r >= p.kv) {
        return;
    }
    let o = 3u * (r * p.n + i);
    if (((p.lit >> r) & 1u) == 0u) {
        e_env[o] = 0.0;
        e_env[o + 1u] = 0.0;
        e_env[o + 2u] = 0.0;
        return;
    }
    let at = r * p.bins;
    let row = i * p.words;
    var acc = vec3<f32>(0.0);
    for (var w = 0u; w < p.words; w++) {
        let v = unpack2x16float(vis[row + w]);
        let k = 2u * w;
        acc += v.x * radiance_at(at, k);
        if (k + 1u < p.bins) {
            acc += v.y * radiance_at(at, k + 1u);
        }
    }
    e_env[o] = acc.x;
    e_env[o + 1u] = acc.y;
    e_env[o + 2u] = acc.z;
    e[o] += acc.x;
    e[o + 1u] += acc.y;
    e[o + 2u] += acc.z;
}
