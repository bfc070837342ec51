// s_link_scale: between the two passes of `s_link_bound`, one thread a linked node k
// (column N + k of S): its patches' area-weighted mean factor
//
//     m_k,c = Σ_p A_p f_p,c / Σ_p A_p   over the patches the node holds,
//
// scales every link to it (the column's entries) and what it re-emits, e_k (links are
// shared by a node's patches, so each takes its patches' mean). The node's patches are
// listed in `far` after the patches' own lists: from word far[n], nodes + 1 offsets, then
// the lists (empty for a node without links).
// CPU twin: `cpu_twin::s_link_bound`. Keep Params in sync with `gpu::subsurface::ColumnParams`.

const WG: u32 = 256u;

struct Params {
    n: u32,
    groups_x: u32,
    nodes: u32,
    _pad0: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> col_ptr: array<u32>;
@group(0) @binding(2) var<storage, read> perm: array<u32>;
@group(0) @binding(3) var<storage, read> patches: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> val: array<f32>;
@group(0) @binding(5) var<storage, read_write> node_energy: array<f32>;
@group(0) @binding(6) var<storage, read> far: array<u32>;
@group(0) @binding(7) var<storage, read> factor: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let g = wid.x + wid.y * p.groups_x;
    let k = g * WG + li;
    if (k >= p.nodes) {
        return;
    }
    let base = far[p.n] + k;
    var num = vec3<f32>(0.0);
    var den = 0.0;
    for (var t = far[base]; t < far[base + 1u]; t++) {
        let i = far[t];
        let a = patches[4u * i].w;
        num += a * vec3<f32>(factor[3u * i], factor[3u * i + 1u], factor[3u * i + 2u]);
        den += a;
    }
    if (den <= 0.0) {
        return;
    }
    let m = num / den;
    if (all(m == vec3<f32>(1.0))) {
        return;
    }
    let c = p.n + k;
    for (var t = col_ptr[c]; t < col_ptr[c + 1u]; t++) {
        let e = perm[t];
        for (var ch = 0u; ch < 3u; ch++) {
            val[3u * e + ch] = val[3u * e + ch] * m[ch];
        }
    }
    for (var ch = 0u; ch < 3u; ch++) {
        node_energy[3u * k + ch] = node_energy[3u * k + ch] * m[ch];
    }
}
