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
