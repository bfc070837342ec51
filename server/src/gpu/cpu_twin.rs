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

/// Twin of `s_entries.wgsl`: every entry of the template's S for the materials `m`, each
/// plan evaluated by the precompute's own [`Quadrature::eval`](translux_engine::subsurface::Quadrature::eval)
/// — the CPU assembly's arithmetic — with patch i's sample points.
pub fn s_entries(
    t: &super::subsurface::STemplate,
    m: &super::subsurface::SMaterials,
    params: &translux_engine::subsurface::SubsurfaceParams,
) -> Vec<Rgb> {
    use rayon::prelude::*;
    use translux_engine::subsurface::samples;
    (0..t.nnz())
        .into_par_iter()
        .map(|e| {
            let [i, j, r, meta] = t.entries[e];
            let r = f32::from_bits(r);
            let o = &m.objects[t.object(i as usize)];
            let Some(plan) = t.plan(e) else {
                return o.albedo;
            };
            let slot = if (meta >> 2) & 1 == 1 {
                o.slot_t
            } else {
                o.slot_r
            };
            let tab = &m.tables[slot as usize];
            if i != j && r >= tab.r_max() {
                return [0.0; 3];
            }
            if let Some(s) = t.spread(e) {
                // A link read at two distances, summed as the kernel sums it.
                let (lo, hi) = (tab.r((r - s).max(0.0)), tab.r(r + s));
                let area_i = t.patches[4 * i as usize][3];
                return std::array::from_fn(|c| (lo[c] + hi[c]) * 0.5 * area_i);
            }
            let corners: [glam::Vec3; 3] = std::array::from_fn(|k| {
                glam::Vec3::from_slice(&t.patches[4 * i as usize + k][..3])
            });
            plan.eval(r, &samples(&corners, params.samples), tab, params)
        })
        .collect()
}

/// Twin of `s_column_bound.wgsl`: per column of a translucent object or thin sheet,
/// total_c = Σ_j A_j S_ji,c / A_i in the template's column order; channels past 1 are
/// divided by their total. Returns, per object, the largest total and the scaled columns.
pub fn s_column_bound(
    t: &super::subsurface::STemplate,
    m: &super::subsurface::SMaterials,
    val: &mut [Rgb],
) -> Vec<super::subsurface::ColumnReport> {
    use super::subsurface::{Class, ColumnReport};
    let mut reports = vec![ColumnReport::default(); m.objects.len()];
    let area = |p: usize| t.patches[4 * p][3];
    for i in 0..t.n {
        let obj = t.object(i);
        if !matches!(m.objects[obj].class, Class::Translucent | Class::Sheet) {
            continue;
        }
        let range = t.col_ptr[i] as usize..t.col_ptr[i + 1] as usize;
        let mut total = [0.0f32; 3];
        for &e in &t.perm[range.clone()] {
            let j = t.entries[e as usize][1] as usize;
            for c in 0..3 {
                total[c] += area(j) * val[e as usize][c] / area(i);
            }
        }
        let worst = total.iter().cloned().fold(0.0f32, f32::max);
        let rep = &mut reports[obj];
        rep.max_column = rep.max_column.max(worst);
        if worst > 1.0 {
            rep.scaled_columns += 1;
            for &e in &t.perm[range] {
                for c in 0..3 {
                    if total[c] > 1.0 {
                        val[e as usize][c] /= total[c];
                    }
                }
            }
        }
    }
    reports
}

/// Twin of `s_node_energy.wgsl`, `s_link_bound.wgsl` (both passes) and
/// `s_link_scale.wgsl` (a hierarchical S, after [`s_column_bound`]): e_k per linked node
/// over its column N + k; per patch column of an object with links, far = Σ e_k over the
/// nodes holding it and the factor f = 1 / max(direct + far, 1); per node, its links and
/// e_k scaled by its patches' area-weighted mean factor; then where f < 1 (and direct > 0)
/// the direct entries scaled by min(f, max(1 − far, 0) / direct), far the scaled e_k's
/// sum. Columns no linked node reaches are left alone. Adds to `reports` as the kernels
/// do.
pub fn s_link_bound(
    t: &super::subsurface::STemplate,
    val: &mut [Rgb],
    reports: &mut [super::subsurface::ColumnReport],
) {
    if !t.has_links() {
        return;
    }
    let area = |p: usize| t.patches[4 * p][3];
    let mut energy: Vec<Rgb> = (0..t.nodes)
        .map(|k| {
            let c = t.n + k;
            let mut e = [0.0f32; 3];
            for &p in &t.perm[t.col_ptr[c] as usize..t.col_ptr[c + 1] as usize] {
                let j = t.entries[p as usize][1] as usize;
                for ch in 0..3 {
                    e[ch] += area(j) * val[p as usize][ch] / area(c);
                }
            }
            e
        })
        .collect();
    let far_of = |i: usize, energy: &[Rgb]| {
        let mut far = [0.0f32; 3];
        for &k in &t.far[t.far[i] as usize..t.far[i + 1] as usize] {
            for ch in 0..3 {
                far[ch] += energy[k as usize][ch];
            }
        }
        far
    };
    let direct_of = |i: usize, val: &[Rgb]| {
        let mut direct = [0.0f32; 3];
        for &p in &t.perm[t.col_ptr[i] as usize..t.col_ptr[i + 1] as usize] {
            let j = t.entries[p as usize][1] as usize;
            for ch in 0..3 {
                direct[ch] += area(j) * val[p as usize][ch] / area(i);
            }
        }
        direct
    };
    let linked = |i: usize| t.patches[4 * i + 2][3] != 0.0;
    // First pass: each column's factor.
    let mut factor = vec![[1.0f32; 3]; t.n];
    for i in 0..t.n {
        if !linked(i) {
            continue;
        }
        let far = far_of(i, &energy);
        if far == [0.0; 3] {
            continue;
        }
        let direct = direct_of(i, val);
        let total: Rgb = std::array::from_fn(|ch| direct[ch] + far[ch]);
        let rep = &mut reports[t.object(i)];
        rep.max_column = rep
            .max_column
            .max(total.iter().cloned().fold(0.0f32, f32::max));
        factor[i] = total.map(|v| 1.0 / v.max(1.0));
    }
    // Each node's links and e_k by its patches' mean factor.
    let base = t.far[t.n] as usize;
    for (k, e) in energy.iter_mut().enumerate() {
        let members = &t.far[t.far[base + k] as usize..t.far[base + k + 1] as usize];
        let (mut num, mut den) = ([0.0f32; 3], 0.0f32);
        for &i in members {
            let a = area(i as usize);
            for ch in 0..3 {
                num[ch] += a * factor[i as usize][ch];
            }
            den += a;
        }
        if den <= 0.0 {
            continue;
        }
        let m = num.map(|v| v / den);
        if m == [1.0; 3] {
            continue;
        }
        let c = t.n + k;
        for &p in &t.perm[t.col_ptr[c] as usize..t.col_ptr[c + 1] as usize] {
            for ch in 0..3 {
                val[p as usize][ch] *= m[ch];
            }
        }
        for ch in 0..3 {
            e[ch] *= m[ch];
        }
    }
    // The last pass: the direct entries.
    for i in 0..t.n {
        if !linked(i) {
            continue;
        }
        let far = far_of(i, &energy);
        if far == [0.0; 3] {
            continue;
        }
        let direct = direct_of(i, val);
        let mut scale = [1.0f32; 3];
        let mut any = false;
        for ch in 0..3 {
            let f = factor[i][ch];
            if f < 1.0 && direct[ch] > 0.0 {
                scale[ch] = f.min((1.0 - far[ch]).max(0.0) / direct[ch]);
                any = true;
            }
        }
        if any {
            reports[t.object(i)].scaled_columns += 1;
            for &p in &t.perm[t.col_ptr[i] as usize..t.col_ptr[i + 1] as usize] {
                for ch in 0..3 {
                    val[p as usize][ch] *= scale[ch];
                }
            }
        }
    }
}
