// csr_spmv_rgb: y = A x for one row block of a CSR matrix A and KV RGB vectors x (a
// batch: vector q at x[q · x_stride ..], its product at y[q · y_stride ..]), reading A once.
//
// A's values are scalars (F: one f32 per entry, applied to all three channels) or RGB
// triples (S: three f32 per entry), chosen by the VAL_RGB override. A block holds rows
// [row0, row0 + rows) of A; its row_ptr is relative to the block's first entry (u32: a block
// never exceeds one storage binding). Each row is summed by LANES threads (entries k ≡ lane
// mod LANES), then a tree over the lanes, vector by vector. CPU twin: `cpu_twin::csr_spmv_rgb`
// (same order, one vector at a time).
// Keep Params in sync with `gpu::matrix::CsrParams`.

override VAL_RGB: bool = false;
// Vectors per product (a batch of relights), at most KMAX.
override KV: u32 = 1u;
const KMAX: u32 = 8u;

const WG: u32 = 256u;
const LANES: u32 = 32u;
const ROWS_PER_WG: u32 = 8u; // WG / LANES

struct Params {
    row0: u32,
    rows: u32,
    groups_x: u32,
    _pad: u32,
    // Entries between a batch's vectors: A's columns (x) and rows (y), in RGB triples.
    x_stride: u32,
    y_stride: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> row_ptr: array<u32>;
@group(0) @binding(2) var<storage, read> col: array<u32>;
@group(0) @binding(3) var<storage, read> val: array<f32>;
@group(0) @binding(4) var<storage, read> x: array<f32>;
@group(0) @binding(5) var<storage, read_write> y: array<f32>;

var<workgroup> part: array<vec3<f32>, WG>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let g = wid.x + wid.y * p.groups_x;
    let local_row = g * ROWS_PER_WG + li / LANES;
    let lane = li % LANES;
    // Each lane's share of the row: entries a + lane, a + lane + LANES, ...
    var acc: array<vec3<f32>, KMAX>;
    if (local_row < p.rows) {
        let a = row_ptr[local_row];
        let b = row_ptr[local_row + 1u];
        for (var k = a + lane; k < b; k += LANES) {
            let j = col[k];
            var v: vec3<f32>;
            if (VAL_RGB) {
                v = vec3<f32>(val[3u * k], val[3u * k + 1u], val[3u * k + 2u]);
            } else {
                v = vec3<f32>(val[k]);
            }
            for (var q = 0u; q < KV; q++) {
                let o = 3u * (q * p.x_stride + j);
                acc[q] += v * vec3<f32>(x[o], x[o + 1u], x[o + 2u]);
            }
        }
    }
    // Per vector, a tree over the row's lanes: lane l += lane l + s for s = 16, 8, 4, 2, 1.
    for (var q = 0u; q < KV; q++) {
        part[li] = acc[q];
        workgroupBarrier();
        for (var s = LANES / 2u; s > 0u; s = s / 2u) {
            if (lane < s) {
                part[li] += part[li + s];
            }
            workgroupBarrier();
        }
        if (lane == 0u && local_row < p.rows) {
            let o = 3u * (q * p.y_stride + p.row0 + local_row);
            let v = part[li];
            y[o] = v.x;
            y[o + 1u] = v.y;
            y[o + 2u] = v.z;
        }
        workgroupBarrier();
    }
}
