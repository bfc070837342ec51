//! Linear algebra of the transport on RGB vectors: the product with F ([`spmv_rgb`]) and
//! the scattering operator S ([`Scatter`]: diagonal ρ for opaque patches, or sparse
//! subsurface S). The solvers ([`crate::solver`]) and the relight ([`crate::radiosity`])
//! build on these; nothing here knows about lights or scenes.
//!
//! In: CSR views of F (scalar) and S (RGB entries), vectors of RGB per patch. Out: products.

use std::ops::Range;

use rayon::prelude::*;
use translux_proto::csr::{CsrValue, CsrView, NarrowCols};
use wide::f32x4;

/// RGB triple.
pub type Rgb = [f32; 3];

/// y = F x for RGB vectors: one pass over F serves all three channels.
pub fn spmv_rgb(f: &CsrView<'_>, x: &[Rgb], y: &mut [Rgb]) {
    spmv_lanes::<1>(f, bytemuck::cast_slice(x), bytemuck::cast_slice_mut(y));
}

/// The scattering operator S: what exitance each patch sends out per unit irradiance.
pub trait Scatter: Sync {
    /// y = S h.
    fn apply(&self, h: &[Rgb], y: &mut [Rgb]);
    /// y = S h for `ch` channels per patch (`[patch][channel]`, `ch` a multiple of 3):
    /// channel c uses colour component c % 3. One pass over S for every channel.
    fn apply_multi(&self, h: &[f32], y: &mut [f32], ch: usize);
    /// Whether S is diagonal (Gauss-Seidel needs that).
    fn diagonal(&self) -> Option<&[Rgb]>;
}

/// S applied to each of `vs` (`ch` values per patch each) in one pass over S: the vectors
/// are laid side by side per patch and multiplied as one of `vs.len() · ch` channels, so S
/// is read once for all of them.
pub fn scatter_each(k: &dyn Scatter, vs: &[&[f32]], ch: usize) -> Vec<Vec<f32>> {
    let m = vs.len();
    let n = vs.first().map_or(0, |v| v.len() / ch);
    let mut h = Vec::with_capacity(n * m * ch);
    for j in 0..n {
        for v in vs {
            h.extend_from_slice(&v[j * ch..(j + 1) * ch]);
        }
    }
    let mut y = vec![0.0f32; n * m * ch];
    k.apply_multi(&h, &mut y, m * ch);
    let mut out: Vec<Vec<f32>> = (0..m).map(|_| Vec::with_capacity(n * ch)).collect();
    for row in y.chunks_exact(m * ch) {
        for (o, part) in out.iter_mut().zip(row.chunks_exact(ch)) {
            o.extend_from_slice(part);
        }
    }
    out
}

/// S = diag(ρ): opaque Lambertian patches.
#[derive(Debug, Clone, Copy)]
pub struct Albedo<'a>(pub &'a [Rgb]);

impl Scatter for Albedo<'_> {
    fn apply(&self, h: &[Rgb], y: &mut [Rgb]) {
        y.par_iter_mut()
            .zip(h.par_iter())
            .zip(self.0.par_iter())
            .for_each(|((y, h), r)| {
                *y = [r[0] * h[0], r[1] * h[1], r[2] * h[2]];
            });
    }
    fn apply_multi(&self, h: &[f32], y: &mut [f32], ch: usize) {
        y.par_chunks_mut(ch)
            .zip(h.par_chunks(ch))
            .zip(self.0.par_iter())
            .for_each(|((y, h), r)| {
                for c in 0..ch {
                    y[c] = r[c % 3] * h[c];
                }
            });
    }
    fn diagonal(&self) -> Option<&[Rgb]> {
        Some(self.0)
    }
}

/// S as a sparse matrix of RGB entries: row j lists the sources i with S_ji.
#[derive(Debug, Clone, Copy)]
pub struct SparseScatter<'a>(pub CsrView<'a, Rgb>);

impl Scatter for SparseScatter<'_> {
    fn apply(&self, h: &[Rgb], y: &mut [Rgb]) {
        self.apply_multi(bytemuck::cast_slice(h), bytemuck::cast_slice_mut(y), 3);
    }
    fn apply_multi(&self, h: &[f32], y: &mut [f32], ch: usize) {
        let rows = 0..y.len() / ch.max(1);
        scatter_rows(&self.0, h, ch, &mut [(rows, y)]);
    }
    fn diagonal(&self) -> Option<&[Rgb]> {
        None
    }
}

/// y = F x for `ch` channels per patch: one pass over F serves every channel.
pub fn spmv_multi(f: &CsrView<'_>, x: &[f32], y: &mut [f32], ch: usize) {
    // Fixed widths unroll and vectorise; batches of up to 8 RGB systems.
    match ch {
        3 => spmv_lanes::<1>(f, x, y),
        6 => spmv_lanes::<2>(f, x, y),
        9 => spmv_lanes::<3>(f, x, y),
        12 => spmv_lanes::<4>(f, x, y),
        15 => spmv_lanes::<5>(f, x, y),
        18 => spmv_lanes::<6>(f, x, y),
        21 => spmv_lanes::<7>(f, x, y),
        24 => spmv_lanes::<8>(f, x, y),
        _ => y
            .par_chunks_mut(ch)
            .with_min_len(64)
            .enumerate()
            .for_each(|(i, yi)| {
                yi.fill(0.0);
                let (cols, vals) = f.row(i);
                for (&j, &v) in cols.iter().zip(vals) {
                    let xj = &x[j as usize * ch..(j as usize + 1) * ch];
                    for (a, &b) in yi.iter_mut().zip(xj) {
                        *a += v * b;
                    }
                }
            }),
    }
}

/// [`spmv_multi`] with F's columns read from their 16-bit copy `narrow` (made from `f`):
/// the same sums in the same order, bit for bit, from 6 bytes an entry instead of 8. F's
/// product streams F from memory (22.3 M entries, 178 MB with their columns, on the bowls
/// at 30k patches), so the bytes it reads are its time.
pub fn spmv_multi_narrow(
    f: &CsrView<'_>,
    narrow: &NarrowCols,
    x: &[f32],
    y: &mut [f32],
    ch: usize,
) {
    assert_eq!(narrow.nnz(), f.nnz(), "narrow columns made from this F");
    match ch {
        3 => spmv_narrow::<1>(f, narrow, x, y),
        6 => spmv_narrow::<2>(f, narrow, x, y),
        9 => spmv_narrow::<3>(f, narrow, x, y),
        12 => spmv_narrow::<4>(f, narrow, x, y),
        15 => spmv_narrow::<5>(f, narrow, x, y),
        18 => spmv_narrow::<6>(f, narrow, x, y),
        21 => spmv_narrow::<7>(f, narrow, x, y),
        24 => spmv_narrow::<8>(f, narrow, x, y),
        _ => spmv_multi(f, x, y, ch),
    }
}

/// [`spmv_lanes`] over the narrow columns: each row's runs of one block of columns, in
/// order ([`NarrowCols::for_each_run`]).
fn spmv_narrow<const G: usize>(f: &CsrView<'_>, narrow: &NarrowCols, x: &[f32], y: &mut [f32]) {
    let lanes = rgb_lanes::<G>(x);
    let (rp, val, low) = (f.row_ptr(), f.val(), narrow.low());
    y.par_chunks_exact_mut(3 * G)
        .with_min_len(64)
        .enumerate()
        .for_each(|(i, yi)| {
            let mut acc = [f32x4::ZERO; G];
            narrow.for_each_run(i, rp[i] as usize, rp[i + 1] as usize, |base, run| {
                let lanes = &lanes[base..];
                for (&c, &v) in low[run.clone()].iter().zip(&val[run]) {
                    let v = f32x4::splat(v);
                    let xi = &lanes[c as usize];
                    for g in 0..G {
                        acc[g] += v * xi[g];
                    }
                }
            });
            for (out, a) in yi.chunks_exact_mut(3).zip(acc) {
                out.copy_from_slice(&a.to_array()[..3]);
            }
        });
}

/// y = S h for `ch` channels per column (channel c uses S's colour c % 3), for each part
/// (`rows`, y): y's row k is S's row `rows.start + k` (a hierarchical S's patch rows and
/// node rows are two parts of one product). Up to 8 RGB systems (`ch` ≤ 24) go through
/// `product_lanes`, h laid out in lanes once for every part.
pub fn scatter_rows(
    s: &CsrView<'_, Rgb>,
    h: &[f32],
    ch: usize,
    parts: &mut [(Range<usize>, &mut [f32])],
) {
    match ch {
        3 => scatter_lanes::<1>(s, h, parts),
        6 => scatter_lanes::<2>(s, h, parts),
        9 => scatter_lanes::<3>(s, h, parts),
        12 => scatter_lanes::<4>(s, h, parts),
        15 => scatter_lanes::<5>(s, h, parts),
        18 => scatter_lanes::<6>(s, h, parts),
        21 => scatter_lanes::<7>(s, h, parts),
        24 => scatter_lanes::<8>(s, h, parts),
        _ => {
            for (rows, y) in parts.iter_mut() {
                y.par_chunks_mut(ch.max(1))
                    .with_min_len(64)
                    .enumerate()
                    .for_each(|(k, yj)| {
                        yj.fill(0.0);
                        let (cols, vals) = s.row(rows.start + k);
                        for (&i, v) in cols.iter().zip(vals) {
                            let hi = &h[i as usize * ch..(i as usize + 1) * ch];
                            for c in 0..ch {
                                yj[c] += v[c % 3] * hi[c];
                            }
                        }
                    });
            }
        }
    }
}

/// [`scatter_rows`] for `G` RGB systems: S's RGB value in lanes 0–2.
fn scatter_lanes<const G: usize>(
    s: &CsrView<'_, Rgb>,
    h: &[f32],
    parts: &mut [(Range<usize>, &mut [f32])],
) {
    let lanes = rgb_lanes::<G>(h);
    for (rows, y) in parts.iter_mut() {
        product_lanes(s, rows.start, &lanes, y, |v| {
            f32x4::from([v[0], v[1], v[2], 0.0])
        });
    }
}

/// y = F x for `G` RGB systems: each of F's values in every lane.
fn spmv_lanes<const G: usize>(f: &CsrView<'_>, x: &[f32], y: &mut [f32]) {
    product_lanes(f, 0, &rgb_lanes::<G>(x), y, |&v| f32x4::splat(v));
}

/// y = M x for `G` RGB systems over M's rows from `first` (y's row k is M's row `first +
/// k`), x given as G 4-lane vectors per column ([`rgb_lanes`]) and each of M's values as 4
/// lanes by `value`: an entry is G multiplies and adds of 4 lanes (`wide`, stable Rust).
/// Each channel's sum is the scalar loop's, term by term in the row's order (a multiply,
/// then an add): the same bits. The scalar loop over 9 channels (a translucency change's
/// one pass for S E, S F x₀ and S F x₋₁) took 14–24 ms on the bowls at 30k, twice its 3
/// channels' 7.5 ms; in lanes it takes 11–13 ms.
fn product_lanes<const G: usize, T: CsrValue + Sync>(
    m: &CsrView<'_, T>,
    first: usize,
    lanes: &[[f32x4; G]],
    y: &mut [f32],
    value: impl Fn(&T) -> f32x4 + Sync,
) {
    y.par_chunks_exact_mut(3 * G)
        .with_min_len(64)
        .enumerate()
        .for_each(|(k, yk)| {
            let (cols, vals) = m.row(first + k);
            let mut acc = [f32x4::ZERO; G];
            for (&i, v) in cols.iter().zip(vals) {
                let v = value(v);
                let xi = &lanes[i as usize];
                for g in 0..G {
                    acc[g] += v * xi[g];
                }
            }
            for (out, a) in yk.chunks_exact_mut(3).zip(acc) {
                out.copy_from_slice(&a.to_array()[..3]);
            }
        });
}

/// `3 G` channels per column as G 4-lane vectors (RGB in lanes 0–2, lane 3 zero).
fn rgb_lanes<const G: usize>(h: &[f32]) -> Vec<[f32x4; G]> {
    h.par_chunks_exact(3 * G)
        .map(|c| std::array::from_fn(|g| f32x4::from([c[3 * g], c[3 * g + 1], c[3 * g + 2], 0.0])))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use translux_proto::csr::CsrBuilder;

    /// A small xorshift from `seed`: uniform numbers in [0, 1).
    fn uniform(mut state: u64) -> impl FnMut() -> f64 {
        move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// F h by the scalar loop, channel by channel, term by term in each row's order: the
    /// reference the products in lanes must equal bit for bit.
    fn f_by_loop(f: &CsrView<'_>, h: &[f32], ch: usize) -> Vec<f32> {
        let mut y = vec![0.0f32; f.n_rows() * ch];
        for (i, yi) in y.chunks_exact_mut(ch).enumerate() {
            let (cs, vs) = f.row(i);
            for (&j, &v) in cs.iter().zip(vs) {
                for c in 0..ch {
                    yi[c] += v * h[j as usize * ch + c];
                }
            }
        }
        y
    }

    /// S's and F's products in lanes ([`scatter_rows`], [`spmv_multi`]) equal the scalar
    /// loop bit for bit, for 1 to 9 RGB systems (9: the loop without lanes), S's also over
    /// rows that start past 0 (a hierarchical S's node rows).
    #[test]
    fn products_in_lanes_equal_the_scalar_loop_bit_for_bit() {
        let mut next = uniform(0x9e37_79b9_7f4a_7c15u64);
        let (rows, cols) = (57, 83);
        let mut b = CsrBuilder::<Rgb>::new(cols);
        for _ in 0..rows {
            let mut row: Vec<(u32, Rgb)> = Vec::new();
            for c in 0..cols as u32 {
                if next() < 0.3 {
                    let mut v =
                        || (10f64.powf(4.0 * next() - 3.0) * (next() - 0.3).signum()) as f32;
                    row.push((c, [v(), v(), v()]));
                }
            }
            b.push_row(&row).unwrap();
        }
        let s = b.finish();
        let s = s.view().unwrap();
        for groups in 1..=9 {
            let ch = 3 * groups;
            let h: Vec<f32> = (0..cols * ch)
                .map(|_| (10f64.powf(3.0 * next() - 1.5) * (next() - 0.5)) as f32)
                .collect();
            for first in [0, 20] {
                let rows = first..s.n_rows();
                let mut want = vec![0.0f32; rows.len() * ch];
                for (k, yj) in want.chunks_exact_mut(ch).enumerate() {
                    let (cs, vs) = s.row(first + k);
                    for (&i, v) in cs.iter().zip(vs) {
                        for c in 0..ch {
                            yj[c] += v[c % 3] * h[i as usize * ch + c];
                        }
                    }
                }
                let mut got = vec![f32::NAN; rows.len() * ch];
                scatter_rows(&s, &h, ch, &mut [(rows, &mut got)]);
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&got), bits(&want), "{groups} systems from row {first}");
                // The same rows as two parts of one product.
                let (mut a, mut b) = (vec![f32::NAN; 7 * ch], vec![f32::NAN; got.len() - 7 * ch]);
                let split = first + 7;
                scatter_rows(
                    &s,
                    &h,
                    ch,
                    &mut [(first..split, &mut a), (split..s.n_rows(), &mut b)],
                );
                a.extend_from_slice(&b);
                assert_eq!(bits(&a), bits(&want), "{groups} systems in two parts");
            }
            // F's product likewise, on a scalar matrix of the same pattern (square: its
            // columns are the rows of x).
            let mut fb = CsrBuilder::<f32>::new(cols);
            for j in 0..cols {
                let (cs, vs) = s.row(j % rows);
                let row: Vec<(u32, f32)> = cs.iter().zip(vs).map(|(&c, v)| (c, v[j % 3])).collect();
                fb.push_row(&row).unwrap();
            }
            let f = fb.finish();
            let f = f.view().unwrap();
            let want = f_by_loop(&f, &h, ch);
            let mut got = vec![f32::NAN; cols * ch];
            spmv_multi(&f, &h, &mut got, ch);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&got), bits(&want), "F with {groups} systems");
        }
    }

    /// F's product over its 16-bit columns equals the scalar loop bit for bit, over a
    /// matrix of 150,000 columns (three blocks of 65,536, rows reaching into one, two or
    /// all three), for 1 to 9 RGB systems (9: the loop without lanes).
    #[test]
    fn products_over_narrow_columns_equal_the_scalar_loop_bit_for_bit() {
        let mut next = uniform(0x2545_f491_4f6c_dd1du64);
        let (rows, cols) = (40usize, 150_000usize);
        let mut fb = CsrBuilder::<f32>::new(cols);
        for r in 0..rows {
            // Row r reaches blocks up to r % 3; some rows are empty.
            let reach = 65_536 * (r % 3 + 1);
            let mut cs: Vec<u32> = (0..if r % 11 == 4 { 0 } else { 60 })
                .map(|_| (next() * reach.min(cols) as f64) as u32)
                .collect();
            cs.sort();
            cs.dedup();
            let row: Vec<(u32, f32)> = cs
                .iter()
                .map(|&c| {
                    (
                        c,
                        (10f64.powf(4.0 * next() - 3.0) * (next() - 0.3).signum()) as f32,
                    )
                })
                .collect();
            fb.push_row(&row).unwrap();
        }
        let f = fb.finish();
        let f = f.view().unwrap();
        let narrow = NarrowCols::of(&f);
        assert_eq!(narrow.blocks(), 3);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for groups in 1..=9 {
            let ch = 3 * groups;
            let h: Vec<f32> = (0..cols * ch)
                .map(|_| (10f64.powf(3.0 * next() - 1.5) * (next() - 0.5)) as f32)
                .collect();
            let want = f_by_loop(&f, &h, ch);
            let mut got = vec![f32::NAN; rows * ch];
            spmv_multi_narrow(&f, &narrow, &h, &mut got, ch);
            assert_eq!(bits(&got), bits(&want), "F with {groups} systems");
        }
    }
}
