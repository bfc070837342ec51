// mr_alpha: the step of the minimal-residual Jacobi iteration per system and channel, on
// the device (one workgroup): for each of kv systems q and channels c, from `mr_step`'s
// dots partials (6 per workgroup: Σ r_c v_c then Σ v_c², system q's count workgroups at
// q · count ..),
//
//     α[4 q + c] = clamp(−⟨r, v⟩_c / ⟨v, v⟩_c, MIN_STEP, MAX_STEP),
//
// the α minimising |r + α v|_c (v = S F r − r), or 1 (the plain Jacobi step) where
// ⟨v, v⟩_c = 0 (a dark channel: r = 0) or the ratio is not finite. Thread t sums
// workgroups t, t + WG, ..., then a tree (as `reduce_sum`). Dispatched indirectly with the
// iteration, so a stopped solve runs it no more. CPU twin: `cpu_twin::mr_alpha`; the
// clamp is the CPU's (`translux_engine::solver::MAX_STEP`).
// Keep Params in sync with `gpu::system::AlphaParams`.

const WG: u32 = 256u;
const MIN_STEP: f32 = 0.1;
const MAX_STEP: f32 = 1.9;

struct Params {
    // Workgroups per system.
    count: u32,
    // Systems (a batch).
    kv: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> partial: array<f32>;
@group(0) @binding(2) var<storage, read_write> alpha: array<f32>;

var<workgroup> part_rv: array<vec3<f32>, WG>;
var<workgroup> part_vv: array<vec3<f32>, WG>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) li: u32) {
    for (var q = 0u; q < p.kv; q++) {
        var rv = vec3<f32>(0.0);
        var vv = vec3<f32>(0.0);
        for (var k = li; k < p.count; k += WG) {
            let o = 6u * (q * p.count + k);
            rv += vec3<f32>(partial[o], partial[o + 1u], partial[o + 2u]);
            vv += vec3<f32>(partial[o + 3u], partial[o + 4u], partial[o + 5u]);
        }
        part_rv[li] = rv;
        part_vv[li] = vv;
        workgroupBarrier();
        for (var h = WG / 2u; h > 0u; h = h / 2u) {
            if (li < h) {
                part_rv[li] += part_rv[li + h];
                part_vv[li] += part_vv[li + h];
            }
            workgroupBarrier();
        }
        if (li == 0u) {
            for (var c = 0u; c < 3u; c++) {
                let d = part_vv[0][c];
                let s = -part_rv[0][c] / d;
                // |s| < 3e38 is false for NaN and ±∞.
                var step = 1.0;
                if (d > 0.0 && abs(s) < 3.0e38) {
                    step = clamp(s, MIN_STEP, MAX_STEP);
                }
                alpha[4u * q + c] = step;
            }
            alpha[4u * q + 3u] = 0.0;
        }
        workgroupBarrier();
    }
}
