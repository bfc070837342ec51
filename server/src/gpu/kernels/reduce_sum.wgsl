// reduce_sum: history[counter] = Σ partial[0..count], then counter += 1 (one workgroup).
//
// Appends each iteration's squared residual to a history the host reads back every few
// iterations, so the solve needs no read-back per iteration. Thread t sums entries
// t, t + WG, ..., then a tree. CPU twin: `cpu_twin::reduce_sum`.

const WG: u32 = 256u;

struct Params {
    count: u32,
    capacity: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> partial: array<f32>;
@group(0) @binding(2) var<storage, read_write> history: array<f32>;
@group(0) @binding(3) var<storage, read_write> counter: array<u32>;

var<workgroup> part: array<f32, WG>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) li: u32) {
    var s = 0.0;
    for (var k = li; k < p.count; k += WG) {
        s += partial[k];
    }
    part[li] = s;
    workgroupBarrier();
    for (var h = WG / 2u; h > 0u; h = h / 2u) {
        if (li < h) {
            part[li] += part[li + h];
        }
        workgroupBarrier();
    }
    if (li == 0u) {
        let slot = counter[0];
        if (slot < p.capacity) {
            history[slot] = part[0];
        }
        counter[0] = slot + 1u;
    }
}
