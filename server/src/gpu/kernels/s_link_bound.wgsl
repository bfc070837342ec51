// s_link_bound: the energy bound of a hierarchical S, after `s_column_bound` held each
// column's direct entries to 1, one thread a source patch i of an object with links, in two
// passes around `s_link_scale` (the CPU's `subsurface::add_links`):
//
//     far_c    = Σ e_k,c over the linked nodes k that hold i (`far`, from s_node_energy)
//     direct_c = Σ_j A_j S_ji,c / A_i over the column's direct entries
//
// FINAL = false: the column's factor as a pairwise S would scale it whole,
// f_c = 1 / max(direct_c + far_c, 1), into `factor` (1 for a column no linked node reaches);
// the largest total goes to `report`. `s_link_scale` then scales each node's links by its
// patches' mean factor, and its e_k with them.
// FINAL = true: with those e_k, where f_c < 1 (and direct_c > 0) the direct entries are
// scaled by min(f_c, max(1 − far_c, 0) / direct_c): as the pairwise column, or further where
// the node's mean left more than f_c of the links. Scaled columns are counted in `report`.
// CPU twin: `cpu_twin::s_link_bound`. Keep Params in sync with `gpu::subsurface::ColumnParams`.

override FINAL: bool = false;

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
@group(0) @binding(5) var<storage, read_write> val: array<f32>;
@group(0) @binding(6) var<storage, read_write> report: array<atomic<u32>>;
@group(0) @binding(7) var<storage, read> node_energy: array<f32>;
// Words far[i]..far[i + 1] of this array: the linked nodes holding patch i.
@group(0) @binding(8) var<storage, read> far: array<u32>;
// Per patch, f (three words): written by the first pass, read by the last.
@group(0) @binding(9) var<storage, read_write> factor: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let g = wid.x + wid.y * p.groups_x;
    let i = g * WG + li;
    if (i >= p.n) {
        return;
    }
    // 1 where the patch's object has links (only translucent objects and thin sheets do).
    if (patches[4u * i + 2u].w == 0.0) {
        return;
    }
    var outside = vec3<f32>(0.0);
    for (var t = far[i]; t < far[i + 1u]; t++) {
        let k = far[t];
        outside += vec3<f32>(node_energy[3u * k], node_energy[3u * k + 1u], node_energy[3u * k + 2u]);
    }
    if (all(outside == vec3<f32>(0.0))) {
        if (!FINAL) {
            for (var c = 0u; c < 3u; c++) {
                factor[3u * i + c] = 1.0;
            }
        }
        return;
    }
    let obj = u32(patches[4u * i + 3u].w);
    let area_i = patches[4u * i].w;
    var direct = vec3<f32>(0.0);
    for (var t = col_ptr[i]; t < col_ptr[i + 1u]; t++) {
        let e = perm[t];
        let j = entries[e].y;
        let area_j = patches[4u * j].w;
        direct += area_j * vec3<f32>(val[3u * e], val[3u * e + 1u], val[3u * e + 2u]) / area_i;
    }
    if (!FINAL) {
        let total = direct + outside;
        let worst = max(max(total.x, total.y), max(total.z, 0.0));
        atomicMax(&report[2u * obj], bitcast<u32>(worst));
        for (var c = 0u; c < 3u; c++) {
            factor[3u * i + c] = 1.0 / max(total[c], 1.0);
        }
        return;
    }
    var scale = vec3<f32>(1.0);
    var any = false;
    for (var c = 0u; c < 3u; c++) {
        let f = factor[3u * i + c];
        if (f < 1.0 && direct[c] > 0.0) {
            scale[c] = min(f, max(1.0 - outside[c], 0.0) / direct[c]);
            any = true;
        }
    }
    if (any) {
        atomicAdd(&report[2u * obj + 1u], 1u);
        for (var t = col_ptr[i]; t < col_ptr[i + 1u]; t++) {
            let e = perm[t];
            for (var c = 0u; c < 3u; c++) {
                val[3u * e + c] = val[3u * e + c] * scale[c];
            }
        }
    }
}
