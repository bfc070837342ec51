// s_column_bound: energy conservation per column of S, one thread a source patch i:
//
//     total_c = Σ_j A_j S_ji,c / A_i   over the column's entries (in the CPU's order),
//
// and where a channel's total passes 1 its entries are divided by it (the CPU's
// `subsurface::bound_and_transpose`). Columns of objects that are not translucent or thin
// sheets are left alone. Per object, the largest total before scaling (as f32 bits:
// non-negative floats order as their bits) and the number of scaled columns go to `report`.
// CPU twin: `cpu_twin::s_column_bound`. Keep Params in sync with `gpu::subsurface::ColumnParams`.

const WG: u32 = 256u;

struct Params {
    n: u32,
    groups_x: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> col_ptr: array<u32>;
// Positions, in the row-major value array, of each column's entries.
@group(0) @binding(2) var<storage, read> perm: array<u32>;
@group(0) @binding(3) var<storage, read> entries: array<vec4<u32>>;
@group(0) @binding(4) var<storage, read> patches: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> objects: array<vec4<u32>>;
@group(0) @binding(6) var<storage, read_write> val: array<f32>;
// Per object: (max total bits, scaled columns).
@group(0) @binding(7) var<storage, read_write> report: array<atomic<u32>>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let g = wid.x + wid.y * p.groups_x;
    let i = g * WG + li;
    if (i >= p.n) {
        return;
    }
    let obj = u32(patches[4u * i + 3u].w);
    let cls = objects[2u * obj].x;
    // 2: translucent, 3: thin sheet.
    if (cls != 2u && cls != 3u) {
        return;
    }
    let area_i = patches[4u * i].w;
    var total = vec3<f32>(0.0);
    for (var k = col_ptr[i]; k < col_ptr[i + 1u]; k++) {
        let e = perm[k];
        let j = entries[e].y;
        let area_j = patches[4u * j].w;
        let s = vec3<f32>(val[3u * e], val[3u * e + 1u], val[3u * e + 2u]);
        total += area_j * s / area_i;
    }
    let worst = max(max(total.x, total.y), max(total.z, 0.0));
    atomicMax(&report[2u * obj], bitcast<u32>(worst));
    if (worst > 1.0) {
        atomicAdd(&report[2u * obj + 1u], 1u);
        for (var k = col_ptr[i]; k < col_ptr[i + 1u]; k++) {
            let e = perm[k];
            for (var c = 0u; c < 3u; c++) {
                if (total[c] > 1.0) {
                    val[3u * e + c] = val[3u * e + c] / total[c];
                }
            }
        }
    }
}
