//! The transfer matrix T = (I − S F)⁻¹ S, for relighting with one matrix product.
//!
//! In: F (CSR), S (CSR, RGB) and a probe right-hand side (the scene's default lights, to
//! measure what storage costs a relight). Out: [`Transfer`]: R = T − S in half precision,
//! scaled per row and channel, and the errors it carries.
//!
//! Per channel c, M = I − S_c F is dense (F couples every pair of patches that see each
//! other), so T_c = M⁻¹ S_c is a dense n × n matrix computed with faer's partial-pivot LU in
//! f64 and solved with S_c as n right-hand sides. faer's matrices are column-major; the
//! rows of M are filled in parallel into the columns of A = Mᵀ, A is factored, and
//! `solve_transpose` solves Aᵀ X = M X = S. Cost per channel: (2/3)n³ flops for the LU and
//! 2n³ for the solves; memory: two n × n f64 matrices plus the f16 result (22 n² bytes,
//! [`memory_estimate`]).
//!
//! Why R = T − S is stored, in f16: T = S + T F S. S is sparse and already in the bundle;
//! T's diagonal is S's (ρ ≈ 0.7) while the inter-reflected part is smooth and ~1/n of that
//! per entry, which after scaling a row to its largest entry falls below f16's normal range
//! (6·10⁻⁵) when the diagonal is kept. Scaled per row without the diagonal, every entry
//! within 10⁻⁴ of its row's largest keeps 11 bits (relative error ≤ 2⁻¹¹ ≈ 4.9·10⁻⁴), and
//! the relit B is off by far less than the paper's 0.5%: [`Transfer`] reports both.
//!
//! Relighting: B = Bₑ + T(E + F Bₑ) = Bₑ + S v + R v with v = E + F Bₑ, since
//! (I − S F)⁻¹ = I + T F. So emitters (area lights) work with T too.

use std::time::Instant;

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::lu::partial_pivoting::{factor, solve};
use faer::{Mat, Par};
use half::f16;
use half::slice::{HalfBitsSliceExt, HalfFloatSliceExt};
use rayon::prelude::*;
use translux_proto::csr::CsrView;

use crate::linalg::Rgb;

/// Bytes [`compute`] needs at its peak for `n` patches: A (the LU, n² f64), the solution X
/// (n² f64) and the stored result (n² × 3 f16).
pub fn memory_estimate(n: u64) -> u64 {
    n.saturating_mul(n).saturating_mul(8 + 8 + 6)
}

/// Bytes of the stored transfer matrix for `n` patches.
pub fn stored_bytes(n: u64) -> u64 {
    n.saturating_mul(n).saturating_mul(6) + n * 12
}

/// The stored transfer matrix and what it cost.
#[derive(Debug, Clone)]
pub struct Transfer {
    pub n: usize,
    /// R = T − S as f16 bits, `[j][k][c]`, each row and channel divided by `scale[j][c]`.
    pub bits: Vec<u16>,
    pub scale: Vec<Rgb>,
    /// Element-wise relative error of the stored entries (those ≥ 10⁻⁴ of their row's
    /// largest) against the f64 values: median (over a sample of ≤ 10⁶) and max.
    pub median_rel_error: f64,
    pub max_rel_error: f64,
    /// The probe relight B = Bₑ + S v + R v with the stored R against the f64 R: the largest
    /// relative error over patch channels above 1% of the peak, and ‖ΔB‖/‖B‖.
    pub relight_max_rel_error: f64,
    pub relight_rel_error: f64,
    /// ‖M T y − S y‖ / ‖S y‖ for the probe y (the LU's accuracy).
    pub lu_residual: f64,
    pub seconds: f64,
}

/// Why T could not be computed.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum InverseError {
    #[error(
        "the transfer matrix for {n} patches needs about {need} bytes of memory ({gib:.1} GiB: \
         two dense {n}×{n} f64 matrices for the LU and the f16 result), more than the \
         {limit} bytes allowed; precompute with fewer patches or without --inverse (relights \
         then use the iterative solve)",
        gib = *need as f64 / (1u64 << 30) as f64
    )]
    OutOfMemory { n: u64, need: u64, limit: u64 },
    #[error("the probe has {got} patches, F has {n}")]
    Probe { got: usize, n: usize },
    #[error(
        "I − S F is singular or nearly so in channel {channel} (the LU's residual is \
         {residual:.2e}); an S column that re-emits everything in a closed scene has no \
         steady state"
    )]
    Singular { channel: usize, residual: f64 },
}

/// Computes R = T − S (see the module docs). `probe` is v = E + F Bₑ for the scene's
/// default lights and `emission` Bₑ (only to report relight errors). `progress(k)` is
/// called with k = 1..=6 as the stages of the three channels finish.
pub fn compute(
    f: &CsrView<'_>,
    s: &CsrView<'_, Rgb>,
    emission: &[Rgb],
    probe: &[Rgb],
    memory_limit: u64,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<Transfer, InverseError> {
    let t0 = Instant::now();
    let n = f.n_rows();
    let need = memory_estimate(n as u64);
    if need > memory_limit {
        return Err(InverseError::OutOfMemory {
            n: n as u64,
            need,
            limit: memory_limit,
        });
    }
    if probe.len() != n || emission.len() != n {
        return Err(InverseError::Probe {
            got: probe.len().min(emission.len()),
            n,
        });
    }
    let par = Par::rayon(0);
    let mut bits = vec![0u16; n * n * 3];
    let mut scale = vec![[0.0f32; 3]; n];
    let mut max_rel = 0.0f64;
    let mut sample: Vec<f32> = Vec::new();
    let stride = (n * n / 300_000).max(1);
    // Probe results per channel: S v + R v with the f64 R and with the stored R.
    let mut b_exact = vec![[0.0f64; 3]; n];
    let mut b_stored = vec![[0.0f64; 3]; n];
    let mut lu_residual = 0.0f64;
    for c in 0..3 {
        // A = Mᵀ: column j of A is row j of M = I − S_c F, i.e. e_j − Σ_i S_ji F_i,:.
        let mut a = Mat::<f64>::zeros(n, n);
        a.par_col_iter_mut().enumerate().for_each(|(j, col)| {
            // A column of an owned matrix is contiguous.
            let Some(col) = col.try_as_col_major_mut().map(|c| c.as_slice_mut()) else {
                unreachable!("faer's owned matrices are column-major")
            };
            col[j] = 1.0;
            let (si, sv) = s.row(j);
            for (&i, sji) in si.iter().zip(sv) {
                let w = sji[c] as f64;
                if w == 0.0 {
                    continue;
                }
                let (fk, fv) = f.row(i as usize);
                for (&k, &v) in fk.iter().zip(fv) {
                    col[k as usize] -= w * v as f64;
                }
            }
        });
        let mut perm = vec![0usize; n];
        let mut perm_inv = vec![0usize; n];
        let scratch = factor::lu_in_place_scratch::<usize, f64>(n, n, par, Default::default());
        let mut mem = MemBuffer::new(scratch);
        let (_, p) = factor::lu_in_place(
            a.as_mut(),
            &mut perm,
            &mut perm_inv,
            par,
            MemStack::new(&mut mem),
            Default::default(),
        );
        progress(1);
        // X = M⁻¹ S_c: S_c dense, column k holds S_jk.
        let mut x = Mat::<f64>::zeros(n, n);
        for j in 0..n {
            let (ks, vs) = s.row(j);
            for (&k, v) in ks.iter().zip(vs) {
                x[(j, k as usize)] = v[c] as f64;
            }
        }
        let scratch = solve::solve_transpose_in_place_scratch::<usize, f64>(n, n, par);
        let mut mem = MemBuffer::new(scratch);
        solve::solve_transpose_in_place(
            a.as_ref(),
            a.as_ref(),
            p,
            x.as_mut(),
            par,
            MemStack::new(&mut mem),
        );
        drop(a);
        // R = X − S.
        for j in 0..n {
            let (ks, vs) = s.row(j);
            for (&k, v) in ks.iter().zip(vs) {
                x[(j, k as usize)] -= v[c] as f64;
            }
        }
        // The LU's accuracy on the probe: y = T v, then ‖y − S F y − S v‖ / ‖S v‖.
        let v: Vec<f64> = probe.iter().map(|p| p[c] as f64).collect();
        let sv = sparse_rgb_apply(s, &v, c);
        let rv = dense_apply(&x, &v);
        let y: Vec<f64> = sv.iter().zip(&rv).map(|(a, b)| a + b).collect();
        let fy = sparse_apply(f, &y);
        let sfy = sparse_rgb_apply(s, &fy, c);
        let (mut num, mut den) = (0.0f64, 0.0f64);
        for j in 0..n {
            num += (y[j] - sfy[j] - sv[j]).powi(2);
            den += sv[j].powi(2);
        }
        let res = if den > 0.0 { (num / den).sqrt() } else { 0.0 };
        if !res.is_finite() || res > 1e-3 {
            return Err(InverseError::Singular {
                channel: c,
                residual: res,
            });
        }
        lu_residual = lu_residual.max(res);

        // Quantise row by row: scale = max_k |R_jk|, f16 of R/scale.
        let rows: Vec<(f32, f64, Vec<f32>, f64)> = bits
            .par_chunks_mut(3 * n)
            .enumerate()
            .map(|(j, out)| {
                let mut m = 0.0f64;
                for k in 0..n {
                    m = m.max(x[(j, k)].abs());
                }
                let sc = if m > 0.0 { m } else { 1.0 };
                let mut worst = 0.0f64;
                let mut picked = Vec::new();
                let mut dot = 0.0f64;
                for k in 0..n {
                    let exact = x[(j, k)];
                    let h = f16::from_f64(exact / sc);
                    out[3 * k + c] = h.to_bits();
                    let back = h.to_f64() * (sc as f32) as f64;
                    dot += back * v[k];
                    if exact != 0.0 && exact.abs() >= 1e-4 * m {
                        let e = ((back - exact) / exact).abs();
                        worst = worst.max(e);
                        if (j * n + k) % stride == 0 {
                            picked.push(e as f32);
                        }
                    }
                }
                (sc as f32, worst, picked, dot)
            })
            .collect();
        for (j, (sc, worst, picked, dot)) in rows.into_iter().enumerate() {
            scale[j][c] = sc;
            max_rel = max_rel.max(worst);
            sample.extend(picked);
            b_exact[j][c] = emission[j][c] as f64 + y[j];
            b_stored[j][c] = emission[j][c] as f64 + sv[j] + dot;
        }
        progress(1);
    }
    sample.sort_by(f32::total_cmp);
    let median = sample.get(sample.len() / 2).copied().unwrap_or(0.0) as f64;
    let peak = b_exact
        .iter()
        .flat_map(|b| b.iter())
        .fold(0.0f64, |a, &v| a.max(v.abs()));
    let (mut worst, mut num, mut den) = (0.0f64, 0.0f64, 0.0f64);
    for (e, q) in b_exact.iter().zip(&b_stored) {
        for c in 0..3 {
            num += (q[c] - e[c]).powi(2);
            den += e[c].powi(2);
            if e[c].abs() > 0.01 * peak {
                worst = worst.max(((q[c] - e[c]) / e[c]).abs());
            }
        }
    }
    Ok(Transfer {
        n,
        bits,
        scale,
        median_rel_error: median,
        max_rel_error: max_rel,
        relight_max_rel_error: worst,
        relight_rel_error: if den > 0.0 { (num / den).sqrt() } else { 0.0 },
        lu_residual,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

fn dense_apply(x: &Mat<f64>, v: &[f64]) -> Vec<f64> {
    let n = v.len();
    // Column-major: accumulate column by column (contiguous reads).
    let mut y = vec![0.0f64; n];
    for (k, &vk) in v.iter().enumerate() {
        if vk == 0.0 {
            continue;
        }
        for (j, yj) in y.iter_mut().enumerate() {
            *yj += x[(j, k)] * vk;
        }
    }
    y
}

fn sparse_apply(f: &CsrView<'_>, v: &[f64]) -> Vec<f64> {
    (0..f.n_rows())
        .into_par_iter()
        .map(|i| {
            let (cols, vals) = f.row(i);
            cols.iter()
                .zip(vals)
                .map(|(&j, &w)| w as f64 * v[j as usize])
                .sum()
        })
        .collect()
}

fn sparse_rgb_apply(s: &CsrView<'_, Rgb>, v: &[f64], c: usize) -> Vec<f64> {
    (0..s.n_rows())
        .into_par_iter()
        .map(|j| {
            let (cols, vals) = s.row(j);
            cols.iter()
                .zip(vals)
                .map(|(&i, w)| w[c] as f64 * v[i as usize])
                .sum()
        })
        .collect()
}

/// y = R v for RGB vectors with the stored (f16, scaled) R, `k` right-hand sides at once
/// (`v` is `[patch][k·3]`, `y` likewise): one pass over R serves all of them (each row is
/// converted to f32 once and dotted with every right-hand side while it is in cache).
pub fn apply_stored(bits: &[u16], scale: &[Rgb], n: usize, v: &[f32], k: usize, y: &mut [f32]) {
    let ch = 3 * k;
    // The right-hand sides one after another, each [patch][rgb], for contiguous dots.
    let planar: Vec<Vec<f32>> = (0..k)
        .map(|s| {
            (0..n)
                .flat_map(|j| v[j * ch + 3 * s..j * ch + 3 * s + 3].iter().copied())
                .collect()
        })
        .collect();
    y.par_chunks_mut(ch).enumerate().for_each_init(
        || vec![0.0f32; 3 * n],
        |row, (j, yj)| {
            let h: &[f16] = bits[3 * n * j..3 * n * (j + 1)].reinterpret_cast();
            h.convert_to_f32_slice(row);
            for (s, vs) in planar.iter().enumerate() {
                let d = dot_rgb(row, vs);
                for c in 0..3 {
                    yj[3 * s + c] = d[c] * scale[j][c];
                }
            }
        },
    );
}

/// Σ_k a[3k + c]·b[3k + c] for c = 0, 1, 2: twelve lanes (four patches) at a time so the
/// compiler vectorises it, folded to three at the end.
fn dot_rgb(a: &[f32], b: &[f32]) -> [f32; 3] {
    let mut acc = [0.0f32; 12];
    let (a12, a_rest) = a.split_at(a.len() / 12 * 12);
    let (b12, b_rest) = b.split_at(a12.len());
    for (x, y) in a12.chunks_exact(12).zip(b12.chunks_exact(12)) {
        for l in 0..12 {
            acc[l] += x[l] * y[l];
        }
    }
    let mut out = [0.0f32; 3];
    for (l, v) in acc.iter().enumerate() {
        out[l % 3] += v;
    }
    for (l, (x, y)) in a_rest.iter().zip(b_rest).enumerate() {
        out[l % 3] += x * y;
    }
    out
}
