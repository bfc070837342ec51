// jacobi_update: one Jacobi step of B = b + S F B and its residual, per patch i:
//
//     r_i = b_i + (S F x)_i − x_i,   x_i ← b_i + (S F x)_i,
//
// and Σ_i |r_i|² per workgroup into partial[g] (summed by `reduce_sum`). A batch of kv
// systems lies vector after vector (system q's patch i at q · n + i); each system has gpk
// workgroups of its own, so a workgroup's partial belongs to one system. With x = 0 and
// (b, sfx) = (Bₑ, S E) the same step builds the right-hand side b = Bₑ + S E and ‖b‖².
// CPU twin: `cpu_twin::jacobi_update`. Keep Params in sync with `gpu::solve::VecParams`.

const WG: u32 = 256u;

struct Params {
    n: u32,
    groups_x: u32,
    // Workgroups per system and systems.
    gpk: u32,
    kv: u32,
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
    let q = g / p.gpk;
    let i = (g % p.gpk) * WG + li;
    let e = q * p.n + i;
    var r2 = 0.0;
    if (i < p.n && q < p.kv) {
        for (var c = 0u; c < 3u; c++) {
            let next = b[3u * e + c] + sfx[3u * e + c];
            let r = next - x[3u * e + c];
            r2 += r * r;
            x[3u * e + c] = next;
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
    if (li == 0u && q < p.kv && (g % p.gpk) * WG < p.n) {
        partial[g] = part[0];
    }
}
