// jacobi_update: one Jacobi step of B = b + S F B and its residual, per patch i:
//
//     r_i = b_i + (S F x)_i − x_i,   x_i ← b_i + (S F x)_i,
//
// and Σ_i |r_i|² per workgroup into partial[g] (summed by `reduce_sum`). With x = 0 and
// (b, sfx) = (Bₑ, S E) the same step builds the right-hand side b = Bₑ + S E and ‖b‖².
// CPU twin: `cpu_twin::jacobi_update`. Keep Params in sync with `gpu::solve::VecParams`.

const WG: u32 = 256u;

struct Params {
    n: u32,
    groups_x: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> b: array<f32>;
@group(0) @binding(2) var<storage, read> sfx: array<f32>;
@group(0) @binding(3) var<storage, read_write> x: array<f32>;
@group(0) @binding(4) var<storage, read_write> partial: array<f32>;

var<workgroup> part: array<f32, WG>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let g = wid.x + wid.y * p.groups_x;
    let i = g * WG + li;
    var r2 = 0.0;
    if (i < p.n) {
        for (var c = 0u; c < 3u; c++) {
            let next = b[3u * i + c] + sfx[3u * i + c];
            let r = next - x[3u * i + c];
            r2 += r * r;
            x[3u * i + c] = next;
        }
    }
    part[li] = r2;
    workgroupBarrier();
    for (var s = WG / 2u; s > 0u; s = s / 2u) {
        if (li < s) {
            part[li] += part[li + s];
        }
        workgroupBarrier();
    }
    // A 2-D grid may have a few groups past the end: they write nothing.
    if (li == 0u && g * WG < p.n) {
        partial[g] = part[0];
    }
}
