// dense_matmul_rgb: Y = T X for one row block of a dense RGB matrix T and k RGB vectors.
//
// Per channel c: Y_c[j][v] = Σ_i T_c[j][i] X_c[i][v]. T is stored row-major with the three
// channels interleaved, element e = (j·n_cols + i)·3 + c of the block, as f16 (two per u32,
// low half first: F16 = true) or f32 bits (F16 = false); accumulation is f32. X and Y are
// [rows][k][3] f32 (vectors fastest), so one pass over T serves every vector of the pass.
//
// Threads: KV vector lanes × CL = WG / KV column lanes; thread (cl, v) sums columns
// i ≡ cl (mod CL) for vector v0 + v and R rows, then a tree over the column lanes. Threads
// with the same cl read the same T element (a broadcast). A block's first element is even,
// so a half's position in its u32 is the parity of e. CPU twin: `cpu_twin::dense_matmul_rgb`.
// Keep Params in sync with `gpu::matrix::DenseParams`.

override F16: bool = true;
override KV: u32 = 1u;

const WG: u32 = 256u;
const R: u32 = 4u;

struct Params {
    row0: u32,
    rows: u32,
    n_cols: u32,
    k: u32,
    v0: u32,
    groups_x: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> t: array<u32>;
@group(0) @binding(2) var<storage, read> x: array<f32>;
@group(0) @binding(3) var<storage, read_write> y: array<f32>;

var<workgroup> part: array<vec3<f32>, WG>;

// The RGB triple starting at element e of the block.
fn load_t(e: u32) -> vec3<f32> {
    if (F16) {
        let a = unpack2x16float(t[e >> 1u]);
        let b = unpack2x16float(t[(e >> 1u) + 1u]);
        if ((e & 1u) == 0u) {
            return vec3<f32>(a.x, a.y, b.x);
        }
        return vec3<f32>(a.y, b.x, b.y);
    }
    return vec3<f32>(bitcast<f32>(t[e]), bitcast<f32>(t[e + 1u]), bitcast<f32>(t[e + 2u]));
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let cl_count = WG / KV;
    let g = wid.x + wid.y * p.groups_x;
    let v = li % KV;
    let cl = li / KV;
    let vec_id = p.v0 + v;
    let first = g * R;
    var acc: array<vec3<f32>, R>;
    for (var r = 0u; r < R; r++) {
        acc[r] = vec3<f32>(0.0);
    }
    if (vec_id < p.k) {
        for (var i = cl; i < p.n_cols; i += cl_count) {
            let xo = (i * p.k + vec_id) * 3u;
            let xv = vec3<f32>(x[xo], x[xo + 1u], x[xo + 2u]);
            for (var r = 0u; r < R; r++) {
                if (first + r < p.rows) {
                    acc[r] += load_t(((first + r) * p.n_cols + i) * 3u) * xv;
                }
            }
        }
    }
    // Per row: tree over the column lanes (stride KV in the workgroup), then write.
    for (var r = 0u; r < R; r++) {
        part[li] = acc[r];
        workgroupBarrier();
        for (var s = cl_count / 2u; s > 0u; s = s / 2u) {
            if (cl < s) {
                part[li] += part[li + s * KV];
            }
            workgroupBarrier();
        }
        if (cl == 0u && vec_id < p.k && first + r < p.rows) {
            let yo = ((p.row0 + first + r) * p.k + vec_id) * 3u;
            let s = part[li];
            y[yo] = s.x;
            y[yo + 1u] = s.y;
            y[yo + 2u] = s.z;
        }
        workgroupBarrier();
    }
}
