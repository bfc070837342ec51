// mr_step: the minimal-residual Jacobi step of B = b + S F B, per patch i, in three stages
// chosen by the STAGE override (the CPU's `solver::minimal_residual_step`):
//
//   0 (residual): r_i = b_i + (S F x)_i − x_i (kr holds S F x), Σ |r_i|² per workgroup;
//   1 (dots):     v_i = kr_i − r_i (kr holds S F r, so v = S F r − r), per workgroup and
//                 channel c: Σ r_ic v_ic and Σ v_ic² into partial[6 g + c], [6 g + 3 + c];
//   2 (update):   with α = alpha[4 q + c] (`mr_alpha`): x_i ← x_i + α r_i and
//                 r_i ← r_i + α (kr_i − r_i) (the residual of the new x: r(α) = r + α v),
//                 Σ |r_i|² of the new r per workgroup.
//
// A batch of kv systems lies vector after vector (system q's patch i at q · n + i); each
// system has gpk workgroups of its own, so a workgroup's partials belong to one system.
// Partial sums are a tree over the workgroup's 256 patches (one patch a thread).
// CPU twin: `cpu_twin::mr_step`. Keep Params in sync with `gpu::system::VecParams`.

override STAGE: u32 = 0u;

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
@group(0) @binding(2) var<storage, read> kr: array<f32>;
@group(0) @binding(3) var<storage, read> alpha: array<f32>;
@group(0) @binding(4) var<storage, read_write> x: array<f32>;
@group(0) @binding(5) var<storage, read_write> r: array<f32>;
@group(0) @binding(6) var<storage, read_write> partial: array<f32>;

var<workgroup> part_a: array<vec3<f32>, WG>;
var<workgroup> part_b: array<vec3<f32>, WG>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let g = wid.x + wid.y * p.groups_x;
    let q = g / p.gpk;
    let i = (g % p.gpk) * WG + li;
    let e = q * p.n + i;
    // STAGE 0 and 2: |r|² in a.x; STAGE 1: r·v per channel in a, v² in v2.
    var a = vec3<f32>(0.0);
    var v2 = vec3<f32>(0.0);
    if (i < p.n && q < p.kv) {
        for (var c = 0u; c < 3u; c++) {
            let o = 3u * e + c;
            if (STAGE == 0u) {
                let rc = b[o] + kr[o] - x[o];
                r[o] = rc;
                a.x += rc * rc;
            } else if (STAGE == 1u) {
                let rc = r[o];
                let vc = kr[o] - rc;
                a[c] = rc * vc;
                v2[c] = vc * vc;
            } else {
                let s = alpha[4u * q + c];
                let rc = r[o];
                x[o] += s * rc;
                let next = rc + s * (kr[o] - rc);
                r[o] = next;
                a.x += next * next;
            }
        }
    }
    part_a[li] = a;
    part_b[li] = v2;
    workgroupBarrier();
    for (var s = WG / 2u; s > 0u; s = s / 2u) {
        if (li < s) {
            part_a[li] += part_a[li + s];
            part_b[li] += part_b[li + s];
        }
        workgroupBarrier();
    }
    // A 2-D grid may have a few groups past the end: they write nothing.
    if (li == 0u && q < p.kv && (g % p.gpk) * WG < p.n) {
        if (STAGE == 1u) {
            let t = part_a[0];
            let u = part_b[0];
            partial[6u * g] = t.x;
            partial[6u * g + 1u] = t.y;
            partial[6u * g + 2u] = t.z;
            partial[6u * g + 3u] = u.x;
            partial[6u * g + 4u] = u.y;
            partial[6u * g + 5u] = u.z;
        } else {
            partial[g] = part_a[0].x;
        }
    }
}
