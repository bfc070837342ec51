// s_entries: every entry S_ji of the subsurface matrix from its stored plan, one thread an
// entry: the translucency change's rebuild of S from the stored distances.
//
// An entry is (source i, receiver j, optical distance r, meta), meta = mode | opposite << 2
// | two << 3 | aux << 4. By mode (the plans of `translux_precompute::subsurface::Quadrature`):
//   0 diag:   S_jj = ρ of the patch's (opaque) object;
//   1 far:    S_ji = A_i R(r); with `two` (a link of `--s-link-near`, spread σ = aux[a].x)
//             S_ji = A_i (R(max(r − σ, 0)) + R(r + σ)) / 2, as `smatrix::node_links`;
//   2 polar:  S_ji = factor · mean over x ∈ samples(i) of ∫_tri R(|x − y|) dA_y, by K
//             directions, exact along each through W(ρ) = ∫₀^ρ R 2πr dr; tri, its plane's
//             normal and the factor are aux[a..a+4];
//   3 points: S_ji = A_i · mean over x ∈ samples(i), y ∈ samples(j) of R(|x − y| + excess),
//             excess = aux[a].x.
// The profile is the object's table (its transmittance table for a thin sheet's other side,
// `opposite`); pairs at or past the table's end are 0 (the self term always counts).
// Tables: per slot 2 (N + 1) vec4, (R.rgb, r_k) then (W.rgb, 0), r_k = r_max (k / N)²,
// interpolated linearly as `Tabulated::r` / `Tabulated::w` do.
// CPU twin: `cpu_twin::s_entries`. Keep Params in sync with `gpu::subsurface::EntryParams`.

const WG: u32 = 256u;
const MAX_SAMPLES: u32 = 64u;
const BIG: f32 = 3.0e38;

struct Params {
    count: u32,
    groups_x: u32,
    // m: m² sample points per patch.
    m: u32,
    // K: directions of the polar integration.
    directions: u32,
    // N: intervals of every table.
    table_n: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> entries: array<vec4<u32>>;
// Per patch 4 vec4: (c0, area), (c1, size), (c2, 0), (normal, object index as f32).
@group(0) @binding(2) var<storage, read> patches: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> aux: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> tables: array<vec4<f32>>;
// Per object 2 vec4<u32>: (class, slot_r, slot_t, 0), (albedo rgb as bits, 0).
@group(0) @binding(5) var<storage, read> objects: array<vec4<u32>>;
// (cos θ_k, sin θ_k) of the K directions, computed once on the CPU.
@group(0) @binding(6) var<storage, read> dirs: array<vec2<f32>>;
@group(0) @binding(7) var<storage, read_write> val: array<f32>;
// The entries in the order they are evaluated (by plan: polar, points, far, diagonal), so a
// warp's threads share one plan's cost; each still writes its own value.
@group(0) @binding(8) var<storage, read> order: array<u32>;

var<private> xs: array<vec3<f32>, MAX_SAMPLES>;
var<private> ys: array<vec3<f32>, MAX_SAMPLES>;

fn corner(i: u32, k: u32) -> vec3<f32> {
    return patches[4u * i + k].xyz;
}

// Point `second` (0 or 1) of cell (i, j) of a triangle split into m² sub-triangles:
// the sub-triangles' centroids, as `subsurface::samples` places them.
fn sample(c0: vec3<f32>, e1: vec3<f32>, e2: vec3<f32>, i: u32, j: u32, second: bool) -> vec3<f32> {
    let fi = f32(i);
    let fj = f32(j);
    if (second) {
        return c0 + e1 * (fi + 2.0 / 3.0) + e2 * (fj + 2.0 / 3.0);
    }
    return c0 + e1 * (fi + 1.0 / 3.0) + e2 * (fj + 1.0 / 3.0);
}

// The m² sample points of a triangle into `out` (xs or ys), in `subsurface::samples` order.
fn samples_into(c0: vec3<f32>, c1: vec3<f32>, c2: vec3<f32>, out: ptr<private, array<vec3<f32>, MAX_SAMPLES>>) -> u32 {
    let m = p.m;
    let e1 = (c1 - c0) / f32(m);
    let e2 = (c2 - c0) / f32(m);
    var n = 0u;
    for (var i = 0u; i < m; i++) {
        for (var j = 0u; j < m - i; j++) {
            (*out)[n] = sample(c0, e1, e2, i, j, false);
            n++;
            if (i + j + 2u <= m) {
                (*out)[n] = sample(c0, e1, e2, i, j, true);
                n++;
            }
        }
    }
    return n;
}

// Row k of table `slot`: 0 for (R, r_k), 1 for (W, 0).
fn row(slot: u32, k: u32, which: u32) -> vec4<f32> {
    return tables[slot * 2u * (p.table_n + 1u) + 2u * k + which];
}

fn r_max(slot: u32) -> f32 {
    return row(slot, p.table_n, 0u).w;
}

// R (which = 0) or W (which = 1) at x; past the table R is 0 and W its total.
fn lookup(slot: u32, x: f32, which: u32) -> vec3<f32> {
    let rm = r_max(slot);
    let n = p.table_n;
    if (x >= rm) {
        if (which == 0u) {
            return vec3<f32>(0.0);
        }
        return row(slot, n, 1u).xyz;
    }
    let s = sqrt(max(x, 0.0) / rm) * f32(n);
    let k = min(u32(s), n - 1u);
    let a = row(slot, k, 0u).w;
    let b = row(slot, k + 1u, 0u).w;
    var t = 0.0;
    if (b > a) {
        t = (x - a) / (b - a);
    }
    let v0 = row(slot, k, which).xyz;
    let v1 = row(slot, k + 1u, which).xyz;
    return v0 + t * (v1 - v0);
}

// ∫ over triangle (t0, t1, t2) of R(|x − y|) dA_y for x in its plane (normal nrm).
fn polar(x: vec3<f32>, t0: vec3<f32>, t1: vec3<f32>, t2: vec3<f32>, nrm: vec3<f32>, slot: u32) -> vec3<f32> {
    let d01 = t1 - t0;
    let len = length(d01);
    var u = vec3<f32>(0.0);
    if (len > 0.0) {
        u = d01 * (1.0 / len);
    }
    let v = cross(nrm, u);
    var q: array<vec2<f32>, 3>;
    q[0] = vec2<f32>(dot(t0 - x, u), dot(t0 - x, v));
    q[1] = vec2<f32>(dot(t1 - x, u), dot(t1 - x, v));
    q[2] = vec2<f32>(dot(t2 - x, u), dot(t2 - x, v));
    let area2 = (q[1].x - q[0].x) * (q[2].y - q[0].y) - (q[1].y - q[0].y) * (q[2].x - q[0].x);
    var sgn = -1.0;
    if (area2 >= 0.0) {
        sgn = 1.0;
    }
    var sum = vec3<f32>(0.0);
    for (var k = 0u; k < p.directions; k++) {
        let d = dirs[k];
        var lo = 0.0;
        var hi = BIG;
        var empty = false;
        for (var e = 0u; e < 3u; e++) {
            let a = q[e];
            let b = q[(e + 1u) % 3u];
            let edge = b - a;
            let c0 = sgn * (edge.x * (-a.y) - edge.y * (-a.x));
            let c1 = sgn * (edge.x * d.y - edge.y * d.x);
            if (abs(c1) < 1e-20) {
                if (c0 < 0.0) {
                    empty = true;
                }
            } else {
                let s = -c0 / c1;
                if (c1 > 0.0) {
                    lo = max(lo, s);
                } else {
                    hi = min(hi, s);
                }
            }
        }
        if (empty || hi <= lo) {
            continue;
        }
        sum += lookup(slot, hi, 1u) - lookup(slot, lo, 1u);
    }
    return sum / f32(p.directions);
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let g = wid.x + wid.y * p.groups_x;
    let slot = g * WG + li;
    if (slot >= p.count) {
        return;
    }
    let idx = order[slot];
    let e = entries[idx];
    let src = e.x;
    let dst = e.y;
    let r = bitcast<f32>(e.z);
    let mode = e.w & 3u;
    let opposite = (e.w >> 2u) & 1u;
    let two = (e.w >> 3u) & 1u;
    let a = e.w >> 4u;
    let obj = u32(patches[4u * src + 3u].w);
    let o = objects[2u * obj];
    var out = vec3<f32>(0.0);
    if (mode == 0u) {
        let alb = objects[2u * obj + 1u];
        out = vec3<f32>(bitcast<f32>(alb.x), bitcast<f32>(alb.y), bitcast<f32>(alb.z));
    } else {
        var slot = o.y;
        if (opposite == 1u) {
            slot = o.z;
        }
        if (src == dst || r < r_max(slot)) {
            let area_i = patches[4u * src].w;
            if (mode == 1u && two == 1u) {
                let s = aux[a].x;
                out = (lookup(slot, max(r - s, 0.0), 0u) + lookup(slot, r + s, 0u)) * 0.5 * area_i;
            } else if (mode == 1u) {
                out = lookup(slot, r, 0u) * area_i;
            } else {
                let nx = samples_into(corner(src, 0u), corner(src, 1u), corner(src, 2u), &xs);
                if (mode == 2u) {
                    let t0 = aux[a];
                    let t1 = aux[a + 1u].xyz;
                    let t2 = aux[a + 2u].xyz;
                    let nrm = aux[a + 3u].xyz;
                    var acc = vec3<f32>(0.0);
                    for (var k = 0u; k < nx; k++) {
                        acc += polar(xs[k], t0.xyz, t1, t2, nrm, slot);
                    }
                    out = acc / f32(nx) * t0.w;
                } else {
                    let excess = aux[a].x;
                    let ny = samples_into(corner(dst, 0u), corner(dst, 1u), corner(dst, 2u), &ys);
                    var acc = vec3<f32>(0.0);
                    for (var k = 0u; k < nx; k++) {
                        for (var l = 0u; l < ny; l++) {
                            acc += lookup(slot, distance(xs[k], ys[l]) + excess, 0u);
                        }
                    }
                    out = acc / f32(nx * ny) * area_i;
                }
            }
        }
    }
    val[3u * idx] = out.x;
    val[3u * idx + 1u] = out.y;
    val[3u * idx + 2u] = out.z;
}
