// reduce_sum: for each of kv systems q, history[counter · kv + q] = Σ partial[q · count ..
// (q + 1) · count], then counter += 1 (one workgroup), and the solve's stopping rule on the
// device (every system's residual met).
//
// Appends each iteration's squared residual to a history, so the solve needs no read-back
// per iteration. Thread t sums entries t, t + WG, ..., then a tree. Slot 0 holds ‖b‖²; a
// later slot k holds the residual of iteration k. Once a slot k ≥ 1 meets the tolerance
// (h[k] ≤ tol2 · h[0], or h[0] = 0) the kernel records k in counter[1] and zeroes the
// `args` of the solve's indirect dispatches (n_args triples), so the iterations recorded
// after it dispatch no workgroups; a stopped history takes no more slots. CPU twin:
// `cpu_twin::reduce_sum` and `cpu_twin::reduce_stop`.

const WG: u32 = 256u;

struct Params {
    count: u32,
    capacity: u32,
    // Dispatch triples in `args` to zero when the solve stops (0: never stop).
    n_args: u32,
    // The relative tolerance squared.
    tol2: f32,
    // Systems (a batch).
    kv: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> partial: array<f32>;
@group(0) @binding(2) var<storage, read_write> history: array<f32>;
@group(0) @binding(3) var<storage, read_write> counter: array<u32>;
@group(0) @binding(4) var<storage, read_write> args: array<u32>;

var<workgroup> part: array<f32, WG>;
var<workgroup> stopped: u32;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) li: u32) {
    // The flag is read once and shared, so the early return is uniform across the group.
    if (li == 0u) {
        stopped = counter[1];
    }
    if (workgroupUniformLoad(&stopped) != 0u) {
        return;
    }
    let slot = counter[0];
    var met = true;
    for (var q = 0u; q < p.kv; q++) {
        var s = 0.0;
        for (var k = li; k < p.count; k += WG) {
            s += partial[q * p.count + k];
        }
        part[li] = s;
        workgroupBarrier();
        for (var h = WG / 2u; h > 0u; h = h / 2u) {
            if (li < h) {
                part[li] += part[li + h];
            }
            workgroupBarrier();
        }
        if (li == 0u && slot < p.capacity) {
            history[slot * p.kv + q] = part[0];
        }
        let h0 = history[q];
        met = met && (h0 == 0.0 || part[0] <= p.tol2 * h0);
        workgroupBarrier();
    }
    if (li == 0u) {
        counter[0] = slot + 1u;
        if (p.n_args > 0u && slot >= 1u && met) {
            counter[1] = slot;
            for (var a = 0u; a < 3u * p.n_args; a++) {
                args[a] = 0u;
            }
        }
    }
}
