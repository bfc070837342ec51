// s_node_energy: what each node of a hierarchical S re-emits through its links, one thread
// a node k (column N + k of S):
//
//     e_k,c = Σ_j A_j S_{j,N+k},c / A_k   over the column's entries (receivers ascending),
//
// which `s_link_bound` then adds to every patch column the node holds (a link spreads the
// node's mean over its patches by area). The node's area is its row of `patches` (N + k).
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
@group(0) @binding(3) var<storage, read> entries: array<vec4<u32>>;
@group(0) @binding(4) var<storage, read> patches: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> val: array<f32>;
@group(0) @binding(6) var<storage, read_write> node_energy: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let g = wid.x + wid.y * p.groups_x;
    let k = g * WG + li;
    if (k >= p.nodes) {
        return;
    }
    let c = p.n + k;
    let area_k = patches[4u * c].w;
    var total = vec3<f32>(0.0);
    for (var t = col_ptr[c]; t < col_ptr[c + 1u]; t++) {
        let e = perm[t];
        let j = entries[e].y;
        let area_j = patches[4u * j].w;
        let s = vec3<f32>(val[3u * e], val[3u * e + 1u], val[3u * e + 2u]);
        total += area_j * s / area_k;
    }
    node_energy[3u * k] = total.x;
    node_energy[3u * k + 1u] = total.y;
    node_energy[3u * k + 2u] = total.z;
}
