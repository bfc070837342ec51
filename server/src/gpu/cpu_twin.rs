//! CPU twins of the WGSL kernels in `kernels/`: one function per kernel, of the same name,
//! written to follow the shader step by step (the same lanes, the same summation order), so
//! that tests can hold each kernel to its twin on random inputs. They are references, not the
//! CPU backend (that is `translux_engine::radiosity`).

use translux_engine::radiosity::Rgb;

/// Threads per row in `csr_spmv_rgb.wgsl` (`LANES`).
pub const SPMV_LANES: usize = 32;
/// Threads per workgroup of every kernel (`WG`).
pub const WG: usize = 256;
/// Rows per workgroup of `dense_matmul_rgb.wgsl` (`R`).
pub const DENSE_ROWS: usize = 4;

/// A CSR value as the SpMV kernel reads it: a scalar for all channels, or RGB.
pub trait SpmvValue: Copy {
    fn rgb(self) -> Rgb;
}

impl SpmvValue for f32 {
    fn rgb(self) -> Rgb {
        [self; 3]
    }
}

impl SpmvValue for [f32; 3] {
    fn rgb(self) -> Rgb {
        self
    }
}

/// Sums `lanes` partial sums by the kernels' tree: lane l += lane l + s for s = L/2, …, 1.
fn tree(mut lanes: Vec<Rgb>) -> Rgb {
    let mut s = lanes.len() / 2;
    while s > 0 {
        for l in 0..s {
            let upper = lanes[l + s];
            for (a, b) in lanes[l].iter_mut().zip(upper) {
                *a += b;
            }
        }
        s /= 2;
    }
    lanes[0]
}

/// Twin of `csr_spmv_rgb.wgsl`: y_r = Σ_k val_k x_{col_k} over row r's entries, per channel;
/// entry k of the row goes to lane k mod 32, then the lanes' tree.
pub fn csr_spmv_rgb<V: SpmvValue>(
    row_ptr: &[u64],
    col: &[u32],
    val: &[V],
    x: &[Rgb],
    y: &mut [Rgb],
) {
    for (r, yr) in y.iter_mut().enumerate() {
        let (a, b) = (row_ptr[r] as usize, row_ptr[r + 1] as usize);
        let mut lanes = vec![[0.0f32; 3]; SPMV_LANES];
        for (lane, acc) in lanes.iter_mut().enumerate() {
            let mut k = a + lane;
            while k < b {
                let v = val[k].rgb();
                let xj = x[col[k] as usize];
                for c in 0..3 {
                    acc[c] += v[c] * xj[c];
                }
                k += SPMV_LANES;
            }
        }
        *yr = tree(lanes);
    }
}

/// Dense RGB matrix storage, row-major with interleaved channels: element
/// `(row · n_cols + col) · 3 + c`.
#[derive(Debug, Clone, Copy)]
pub enum DenseData<'a> {
    /// IEEE half-precision bits.
    F16(&'a [u16]),
    F32(&'a [f32]),
}

impl DenseData<'_> {
    /// Element `e` as f32.
    #[inline]
    pub fn get(&self, e: usize) -> f32 {
        match self {
            DenseData::F16(h) => half::f16::from_bits(h[e]).to_f32(),
            DenseData::F32(f) => f[e],
        }
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        match self {
            DenseData::F16(h) => h.len(),
            DenseData::F32(f) => f.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes per element.
    pub fn elem_bytes(&self) -> usize {
        match self {
            DenseData::F16(_) => 2,
            DenseData::F32(_) => 4,
        }
    }
}

/// Vector lanes `dense_matmul_rgb.wgsl` uses for a pass of `k` vectors: the next power of
/// two, at most 64 (`KV`).
pub fn dense_vector_lanes(k: usize) -> usize {
    k.clamp(1, 64).next_power_of_two()
}

/// Twin of `dense_matmul_rgb.wgsl`: Y_c\[j\]\[v\] = Σ_i T_c\[j\]\[i\] X_c\[i\]\[v\] for the `k` vectors
/// of `x` (`[n_cols][k]`), into `y` (`[n_rows][k]`); column i goes to column lane
/// i mod (256 / KV), then the lanes' tree. `k` ≤ 64 (one pass).
pub fn dense_matmul_rgb(
    t: DenseData<'_>,
    n_rows: usize,
    n_cols: usize,
    x: &[Rgb],
    k: usize,
    y: &mut [Rgb],
) {
    assert!(k <= 64, "one pass holds at most 64 vectors");
    let cl_count = WG / dense_vector_lanes(k);
    for j in 0..n_rows {
        for v in 0..k {
            let mut lanes = vec![[0.0f32; 3]; cl_count];
            for (cl, acc) in lanes.iter_mut().enumerate() {
                let mut i = cl;
                while i < n_cols {
                    let xv = x[i * k + v];
                    let e = (j * n_cols + i) * 3;
                    for c in 0..3 {
                        acc[c] += t.get(e + c) * xv[c];
                    }
                    i += cl_count;
                }
            }
            y[j * k + v] = tree(lanes);
        }
    }
}

/// Twin of `jacobi_update.wgsl`: x_i ← b_i + sfx_i, returning Σ |b_i + sfx_i − x_i|² per
/// workgroup of 256 patches (tree order).
pub fn jacobi_update(b: &[Rgb], sfx: &[Rgb], x: &mut [Rgb]) -> Vec<f32> {
    let n = x.len();
    let groups = n.div_ceil(WG);
    (0..groups)
        .map(|g| {
            let mut part = vec![0.0f32; WG];
            for (li, p) in part.iter_mut().enumerate() {
                let i = g * WG + li;
                if i < n {
                    for c in 0..3 {
                        let next = b[i][c] + sfx[i][c];
                        let r = next - x[i][c];
                        *p += r * r;
                        x[i][c] = next;
                    }
                }
            }
            let mut s = WG / 2;
            while s > 0 {
                for l in 0..s {
                    part[l] += part[l + s];
                }
                s /= 2;
            }
            part[0]
        })
        .collect()
}

/// The stage of `mr_step.wgsl` (its `STAGE` override).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MrStage {
    /// r ← b + kr − x (kr = S F x); answers Σ |r|² per workgroup.
    Residual = 0,
    /// v = kr − r (kr = S F r); answers per workgroup Σ r_c v_c (c = 0, 1, 2) then Σ v_c².
    Dots = 1,
    /// x ← x + α r, r ← r + α (kr − r) with α = `alpha[4 q + c]`; answers Σ |r|² of the
    /// new r per workgroup.
    Update = 2,
}

/// Twin of `mr_step.wgsl` at `stage` for one system (q = 0): one patch a thread, each
/// workgroup's sums by the tree over its 256 patches (three channels at once). Answers the
/// partials as the kernel writes them (one per workgroup, six for [`MrStage::Dots`]).
pub fn mr_step(
    stage: MrStage,
    b: &[Rgb],
    kr: &[Rgb],
    alpha: [f32; 4],
    x: &mut [Rgb],
    r: &mut [Rgb],
) -> Vec<f32> {
    let n = x.len();
    let groups = n.div_ceil(WG);
    let mut out = Vec::new();
    for g in 0..groups {
        let mut part_a = vec![[0.0f32; 3]; WG];
        let mut part_b = vec![[0.0f32; 3]; WG];
        for li in 0..WG {
            let i = g * WG + li;
            if i >= n {
                continue;
            }
            let (a, v2) = (&mut part_a[li], &mut part_b[li]);
            for c in 0..3 {
                match stage {
                    MrStage::Residual => {
                        let rc = b[i][c] + kr[i][c] - x[i][c];
                        r[i][c] = rc;
                        a[0] += rc * rc;
                    }
                    MrStage::Dots => {
                        let rc = r[i][c];
                        let vc = kr[i][c] - rc;
                        a[c] = rc * vc;
                        v2[c] = vc * vc;
                    }
                    MrStage::Update => {
                        let s = alpha[c];
                        let rc = r[i][c];
                        x[i][c] += s * rc;
                        let next = rc + s * (kr[i][c] - rc);
                        r[i][c] = next;
                        a[0] += next * next;
                    }
                }
            }
        }
        let (t, u) = (tree(part_a), tree(part_b));
        match stage {
            MrStage::Dots => out.extend(t.into_iter().chain(u)),
            _ => out.push(t[0]),
        }
    }
    out
}

/// Twin of `mr_alpha.wgsl`: for each of `kv` systems (their `mr_step` dots partials one
/// after another, six per workgroup) and channel c, α = clamp(−⟨r, v⟩_c / ⟨v, v⟩_c, 0.1,
/// 1.9), or 1 where ⟨v, v⟩_c = 0 or the ratio is not finite; thread t summing workgroups
/// t, t + 256, …, then the tree. Answers four entries a system (the fourth 0).
pub fn mr_alpha(partial: &[f32], kv: usize) -> Vec<f32> {
    let count = partial.len() / 6 / kv.max(1);
    let mut alpha = Vec::with_capacity(4 * kv);
    for q in 0..kv {
        let mut rv = vec![[0.0f32; 3]; WG];
        let mut vv = vec![[0.0f32; 3]; WG];
        for k in 0..count {
            let o = 6 * (q * count + k);
            for c in 0..3 {
                rv[k % WG][c] += partial[o + c];
                vv[k % WG][c] += partial[o + 3 + c];
            }
        }
        let (rv, vv) = (tree(rv), tree(vv));
        for c in 0..3 {
            let s = -rv[c] / vv[c];
            alpha.push(if vv[c] > 0.0 && s.abs() < 3.0e38 {
                s.clamp(0.1, 1.9)
            } else {
                1.0
            });
        }
        alpha.push(0.0);
    }
    alpha
}

/// Twin of `reduce_sum.wgsl`: Σ partial, thread t summing entries t, t + 256, …, then the
/// tree.
pub fn reduce_sum(partial: &[f32]) -> f32 {
    let mut part = vec![0.0f32; WG];
    for (k, v) in partial.iter().enumerate() {
        part[k % WG] += v;
    }
    let mut s = WG / 2;
    while s > 0 {
        for l in 0..s {
            part[l] += part[l + s];
        }
        s /= 2;
    }
    part[0]
}

/// What one `reduce_sum.wgsl` dispatch keeps between dispatches: the history, the counter
/// (`[next slot, the iteration the solve stopped at or 0]`) and the indirect dispatch
/// triples it zeroes when the solve stops.
#[derive(Debug, Clone, PartialEq)]
pub struct ReduceState {
    pub history: Vec<f32>,
    pub counter: [u32; 2],
    pub args: Vec<u32>,
}

/// Twin of one `reduce_sum.wgsl` dispatch with its stopping rule, for `kv` systems whose
/// partial sums lie one after another in `partial`: nothing once stopped; else each
/// system's sum ([`reduce_sum`]) appended to the history (slot after slot, one entry per
/// system), and at a slot k ≥ 1 where every system has `h[k] ≤ tol2 · h[0]` (or
/// `h[0] = 0`) the stop recorded and `args` zeroed (no `args`: never stops).
pub fn reduce_stop(partial: &[f32], kv: usize, tol2: f32, state: &mut ReduceState) {
    if state.counter[1] != 0 {
        return;
    }
    let slot = state.counter[0] as usize;
    let count = partial.len() / kv.max(1);
    let mut met = true;
    for q in 0..kv {
        let sum = reduce_sum(&partial[q * count..(q + 1) * count]);
        if (slot + 1) * kv <= state.history.len() {
            state.history[slot * kv + q] = sum;
        }
        let h0 = state.history.get(q).copied().unwrap_or(0.0);
        met &= h0 == 0.0 || sum <= tol2 * h0;
    }
    state.counter[0] += 1;
    if !state.args.is_empty() && slot >= 1 && met {
        state.counter[1] = slot as u32;
        state.args.iter_mut().for_each(|a| *a = 0);
    }
}

/// Twin of `vertex_colours.wgsl`: one vertex at a time, in f32, from `rows`
/// ([`translux_engine::vertexrows::VertexRows`]), B (`x`), E (`e`) and its environment
/// part (`e_env`, taken out of E at opaque vertices) per patch and E at each vertex's
/// sample point (`ev`); with `pixel` the diffuse objects' vertices without their direct
/// term. Answers the colours and the luminance of the whole answer.
pub fn vertex_colours(
    rows: &translux_engine::vertexrows::VertexRows,
    x: &[Rgb],
    (e, e_env): (&[Rgb], &[Rgb]),
    ev: &[Rgb],
    pixel: bool,
) -> (Vec<Rgb>, Vec<f32>) {
    let inv_pi = std::f32::consts::FRAC_1_PI;
    let lum = |v: Rgb| v[0] * 0.2126 + v[1] * 0.7152 + v[2] * 0.0722;
    (0..rows.len())
        .map(|q| {
            let (a, z) = (rows.offsets[q] as usize, rows.offsets[q + 1] as usize);
            let entries = rows.patch[a..z].iter().zip(&rows.weight[a..z]);
            let own = rows.own[q];
            if own[3] == 0.0 {
                let mut value = [0.0f32; 3];
                for (&k, &w) in entries {
                    for c in 0..3 {
                        value[c] += w * x[k as usize][c];
                    }
                }
                return (value, lum(value));
            }
            let (mut sum, mut lo, mut hi) = ([0.0f32; 3], [0.0f32; 3], [0.0f32; 3]);
            for (i, (&k, &w)) in entries.enumerate() {
                let k = k as usize;
                let r: Rgb =
                    std::array::from_fn(|c| x[k][c] - rows.albedo[k][c] * (e[k][c] - e_env[k][c]));
                for c in 0..3 {
                    sum[c] += w * r[c];
                    (lo[c], hi[c]) = if i == 0 {
                        (r[c], r[c])
                    } else {
                        (lo[c].min(r[c]), hi[c].max(r[c]))
                    };
                }
            }
            let rest: Rgb = std::array::from_fn(|c| {
                if z > a {
                    let slack = rows.overshoot * (hi[c] - lo[c]);
                    sum[c].clamp(lo[c] - slack, hi[c] + slack)
                } else {
                    0.0
                }
            });
            let whole: Rgb =
                std::array::from_fn(|c| ((rest[c] + own[c] * ev[q][c]) * inv_pi).max(0.0));
            let value = if pixel && own[3] == 2.0 {
                rest.map(|r| (r * inv_pi).max(0.0))
            } else {
                whole
            };
            (value, lum(whole))
        })
        .unzip()
}

/// Twin of `env_irradiance.wgsl`: for each relight r with an environment (`radiance[r]`,
/// its L̄ per bin) and each patch i, E_env = Σ_k V_ik L̄_k in bin order in one f32
/// accumulator, from `words` (V packed as [`super::environment::GpuVisibility::pack`]
/// lays it out: two half floats a word, ⌈bins/2⌉ words a patch), added to `e` (relight
/// after relight, n each). Answers E_env (0 for relights without an environment).
pub fn env_irradiance(
    words: &[u32],
    bins: usize,
    radiance: &[Option<Vec<Rgb>>],
    e: &mut [Rgb],
) -> Vec<Rgb> {
    let per = bins.div_ceil(2);
    let n = words.len().checked_div(per).unwrap_or(0);
    let half = |bits: u32| half::f16::from_bits(bits as u16).to_f32();
    let mut env = vec![[0.0f32; 3]; e.len()];
    for (r, l) in radiance.iter().enumerate() {
        let Some(l) = l else { continue };
        for i in 0..n {
            let mut acc = [0.0f32; 3];
            for w in 0..per {
                let word = words[i * per + w];
                let k = 2 * w;
                let (lo, hi) = (half(word & 0xffff), half(word >> 16));
                for c in 0..3 {
                    acc[c] += lo * l[k][c];
                }
                if k + 1 < bins {
                    for c in 0..3 {
                        acc[c] += hi * l[k + 1][c];
                    }
                }
            }
            let o = r * n + i;
            env[o] = acc;
            for c in 0..3 {
                e[o][c] += acc[c];
            }
        }
    }
    env
}

/// Twin of `bvh_traverse.wgsl`'s `slab`: the ray's interval inside the box, clipped to
/// (tmin, tmax); empty when enter > exit.
fn bvh_slab(r: &super::direct::ShadowRay, lo: [f32; 3], hi: [f32; 3]) -> (f32, f32) {
    let (mut t0, mut t1) = (r.tmin, r.tmax);
    for k in 0..3 {
        let (o, d) = (r.origin[k], r.dir[k]);
        if d.abs() < 1e-30 {
            if o < lo[k] || o > hi[k] {
                return (1.0, 0.0);
            }
        } else {
            let a = (lo[k] - o) / d;
            let b = (hi[k] - o) / d;
            t0 = t0.max(a.min(b));
            t1 = t1.min(a.max(b));
        }
    }
    (t0, t1)
}

/// Twin of `bvh_traverse.wgsl`'s `hit_tri` (the engine's `intersect_closed`).
fn bvh_hit_tri(r: &super::direct::ShadowRay, t: &super::direct::BvhTri) -> bool {
    use glam::Vec3;
    const EPS: f32 = super::direct::TRI_EPS;
    let v = t.v.map(|p| Vec3::new(p[0], p[1], p[2]));
    let (o, d) = (Vec3::from(r.origin), Vec3::from(r.dir));
    let e1 = v[1] - v[0];
    let e2 = v[2] - v[0];
    let p = d.cross(e2);
    let det = e1.dot(p);
    if det.abs() < 1e-20 {
        return false;
    }
    let inv = 1.0 / det;
    let s = o - v[0];
    let u = s.dot(p) * inv;
    if !(-EPS..=1.0 + EPS).contains(&u) {
        return false;
    }
    let q = s.cross(e1);
    let w = d.dot(q) * inv;
    if w < -EPS || u + w > 1.0 + EPS {
        return false;
    }
    let t = e2.dot(q) * inv;
    t > r.tmin && t < r.tmax
}

/// Twin of `bvh_traverse.wgsl`'s `occluded`: the same stack walk, near child first.
fn bvh_occluded(bvh: &super::direct::FlatBvh, r: &super::direct::ShadowRay) -> bool {
    let box_of = |i: usize| bvh_slab(r, bvh.nodes[i].lo, bvh.nodes[i].hi);
    let root = box_of(0);
    if root.0 > root.1 {
        return false;
    }
    let mut stack = [0u32; super::direct::MAX_DEPTH as usize];
    let mut sp = 0usize;
    let mut i = 0usize;
    loop {
        let n = bvh.nodes[i];
        if n.count > 0 {
            let tris = &bvh.tris[n.a as usize..(n.a + n.count) as usize];
            if tris.iter().any(|t| bvh_hit_tri(r, t)) {
                return true;
            }
        } else {
            let (a, b) = (n.a as usize, n.a as usize + 1);
            let (l, h) = (box_of(a), box_of(b));
            let (hit_l, hit_h) = (l.0 <= l.1, h.0 <= h.1);
            if hit_l && hit_h {
                let (near, far) = if l.0 <= h.0 { (a, b) } else { (b, a) };
                if sp < stack.len() {
                    stack[sp] = far as u32;
                    sp += 1;
                }
                i = near;
                continue;
            }
            if hit_l {
                i = a;
                continue;
            }
            if hit_h {
                i = b;
                continue;
            }
        }
        if sp == 0 {
            return false;
        }
        sp -= 1;
        i = stack[sp] as usize;
    }
}

/// Twin of `shadow_rays.wgsl`: one occluded flag per ray through `bvh`.
pub fn shadow_rays(bvh: &super::direct::FlatBvh, rays: &[super::direct::ShadowRay]) -> Vec<bool> {
    rays.iter().map(|r| bvh_occluded(bvh, r)).collect()
}

/// Twin of `direct_light.wgsl`: E at each point (normal `normals[i]`) from `lights`, each
/// light's term added in order.
pub fn direct_light(
    bvh: &super::direct::FlatBvh,
    points: &[glam::Vec3],
    normals: &[glam::Vec3],
    lights: &super::direct::GpuLights,
) -> Vec<Rgb> {
    points
        .iter()
        .zip(normals)
        .map(|(&x, &n)| {
            let o = x + n * lights.offset;
            let mut e = glam::Vec3::ZERO;
            for l in &lights.lights {
                e += direct_light_one(bvh, lights, l, x, n, o);
            }
            e.into()
        })
        .collect()
}

/// One light's term of [`direct_light`] (`light_at` in the shader).
fn direct_light_one(
    bvh: &super::direct::FlatBvh,
    lights: &super::direct::GpuLights,
    l: &super::direct::GpuLight,
    x: glam::Vec3,
    n: glam::Vec3,
    o: glam::Vec3,
) -> glam::Vec3 {
    use glam::Vec3;
    let pos = Vec3::new(l.pos[0], l.pos[1], l.pos[2]);
    let power = Vec3::new(l.power[0], l.power[1], l.power[2]);
    if l.kind == super::direct::LIGHT_AT {
        let d = pos - o;
        let r = d.length();
        if r <= 0.0 {
            return Vec3::ZERO;
        }
        let c = n.dot(d) / r;
        if c <= 0.0 {
            return Vec3::ZERO;
        }
        let spot = if l.cone != 0 {
            let axis = Vec3::new(l.axis[0], l.axis[1], l.axis[2]);
            let c_axis = axis.dot((x - pos).normalize_or_zero());
            bvh_falloff(c_axis, l.cos_inner, l.cos_outer)
        } else {
            1.0
        };
        let ray = super::direct::ShadowRay::segment(o, pos);
        if spot <= 0.0 || bvh_occluded(bvh, &ray) {
            return Vec3::ZERO;
        }
        let rm = r * lights.to_m;
        let w = spot * c / (rm * rm);
        return w * power;
    }
    let c = n.dot(pos);
    let ray = super::direct::ShadowRay {
        origin: o.into(),
        tmin: 0.0,
        dir: pos.into(),
        tmax: lights.far,
    };
    if c <= 0.0 || bvh_occluded(bvh, &ray) {
        return Vec3::ZERO;
    }
    c * power
}

/// Twin of `direct_light.wgsl`'s `falloff` (the engine's `spot_falloff` from cosines).
fn bvh_falloff(c: f32, ci: f32, co: f32) -> f32 {
    if c >= ci {
        1.0
    } else if c <= co {
        0.0
    } else {
        let t = (c - co) / (ci - co);
        t * t * (3.0 - 2.0 * t)
    }
}
