// bvh_traverse: the any-hit traversal shared by `shadow_rays` and `direct_light` (not a
// kernel: `Kernels::new` puts this source in front of each of them; WGSL has no includes).
//
// In: the flattened binary BVH of `gpu::direct::FlatBvh` at bindings 1 (nodes) and 2
// (triangles in leaf order). `occluded(ray)` is true when a triangle is hit strictly within
// (tmin, tmax). Node boxes are widened on the host to hold everything the triangle test
// accepts, so the answer is that of a loop over every triangle. CPU twin: the traversal in
// `cpu_twin::shadow_rays`. Keep Node and Tri in sync with `BvhNode` and `BvhTri`.

// Entries of the traversal stack (`direct::MAX_DEPTH`): deeper trees are refused at upload.
const STACK: u32 = 64u;
// Barycentric tolerance (`direct::TRI_EPS`, the engine's `intersect_closed`).
const EPS: f32 = 1e-5;

struct Node {
    lo: vec3<f32>,
    // Inner node: the left child (the right is a + 1); leaf: the first triangle.
    a: u32,
    hi: vec3<f32>,
    // 0 for an inner node, else the leaf's triangle count.
    count: u32,
}

struct Tri {
    v0: vec4<f32>,
    v1: vec4<f32>,
    v2: vec4<f32>,
}

struct Ray {
    o: vec3<f32>,
    d: vec3<f32>,
    tmin: f32,
    tmax: f32,
}

@group(0) @binding(1) var<storage, read> nodes: array<Node>;
@group(0) @binding(2) var<storage, read> tris: array<Tri>;

// The ray's parameter interval inside the box, clipped to (tmin, tmax): (enter, exit),
// empty when enter > exit. A direction component of (near) zero tests the origin against
// that slab instead of dividing by it.
fn slab(r: Ray, lo: vec3<f32>, hi: vec3<f32>) -> vec2<f32> {
    var t0 = r.tmin;
    var t1 = r.tmax;
    for (var k = 0u; k < 3u; k++) {
        let o = r.o[k];
        let d = r.d[k];
        if (abs(d) < 1e-30) {
            if (o < lo[k] || o > hi[k]) {
                return vec2<f32>(1.0, 0.0);
            }
        } else {
            let a = (lo[k] - o) / d;
            let b = (hi[k] - o) / d;
            t0 = max(t0, min(a, b));
            t1 = min(t1, max(a, b));
        }
    }
    return vec2<f32>(t0, t1);
}

// Möller–Trumbore with a small tolerance on the barycentrics (the engine's
// `intersect_closed`, step by step): a ray through the edge two triangles share hits one.
fn hit_tri(r: Ray, t: Tri) -> bool {
    let e1 = t.v1.xyz - t.v0.xyz;
    let e2 = t.v2.xyz - t.v0.xyz;
    let p = cross(r.d, e2);
    let det = dot(e1, p);
    if (abs(det) < 1e-20) {
        return false;
    }
    let inv = 1.0 / det;
    let s = r.o - t.v0.xyz;
    let u = dot(s, p) * inv;
    if (!(u >= -EPS && u <= 1.0 + EPS)) {
        return false;
    }
    let q = cross(s, e1);
    let v = dot(r.d, q) * inv;
    if (v < -EPS || u + v > 1.0 + EPS) {
        return false;
    }
    let d = dot(e2, q) * inv;
    return d > r.tmin && d < r.tmax;
}

// Whether any triangle is hit within (tmin, tmax): a stack walk, near child first.
fn occluded(r: Ray) -> bool {
    let root = slab(r, nodes[0].lo, nodes[0].hi);
    if (root.x > root.y) {
        return false;
    }
    var stack: array<u32, STACK>;
    var sp = 0u;
    var i = 0u;
    loop {
        let n = nodes[i];
        if (n.count > 0u) {
            for (var k = n.a; k < n.a + n.count; k++) {
                if (hit_tri(r, tris[k])) {
                    return true;
                }
            }
        } else {
            let l = slab(r, nodes[n.a].lo, nodes[n.a].hi);
            let h = slab(r, nodes[n.a + 1u].lo, nodes[n.a + 1u].hi);
            let hit_l = l.x <= l.y;
            let hit_h = h.x <= h.y;
            if (hit_l && hit_h) {
                let near_l = l.x <= h.x;
                if (sp < STACK) {
                    stack[sp] = select(n.a, n.a + 1u, near_l);
                    sp++;
                }
                i = select(n.a + 1u, n.a, near_l);
                continue;
            }
            if (hit_l) {
                i = n.a;
                continue;
            }
            if (hit_h) {
                i = n.a + 1u;
                continue;
            }
        }
        if (sp == 0u) {
            return false;
        }
        sp--;
        i = stack[sp];
    }
    return false;
}
