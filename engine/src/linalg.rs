//! Linear algebra of the transport on RGB vectors: the product with F ([`spmv_rgb`]) and
//! the scattering operator S ([`Scatter`]: diagonal ρ for opaque patches, or sparse
//! subsurface S). The solvers ([`crate::solver`]) and the relight ([`crate::radiosity`])
//! build on these; nothing here knows about lights or scenes.
//!
//! In: CSR views of F (scalar) and S (RGB entries), vectors of RGB per patch. Out: products.

use rayon::prelude::*;
use translux_proto::csr::CsrView;

/// RGB triple.
pub type Rgb = [f32; 3];

/// y = F x for RGB vectors: one pass over F serves all three channels.
pub fn spmv_rgb(f: &CsrView<'_>, x: &[Rgb], y: &mut [Rgb]) {
    y.par_iter_mut()
        .with_min_len(64)
        .enumerate()
        .for_each(|(i, yi)| {
            let (cols, vals) = f.row(i);
            let mut acc = [0.0f32; 3];
            for (&j, &v) in cols.iter().zip(vals) {
                let xj = &x[j as usize];
                acc[0] += v * xj[0];
                acc[1] += v * xj[1];
                acc[2] += v * xj[2];
            }
            *yi = acc;
        });
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
        y.par_iter_mut()
            .with_min_len(64)
            .enumerate()
            .for_each(|(j, yj)| {
                let (cols, vals) = self.0.row(j);
                let mut acc = [0.0f32; 3];
                for (&i, s) in cols.iter().zip(vals) {
                    let hi = &h[i as usize];
                    acc[0] += s[0] * hi[0];
                    acc[1] += s[1] * hi[1];
                    acc[2] += s[2] * hi[2];
                }
                *yj = acc;
            });
    }
    fn apply_multi(&self, h: &[f32], y: &mut [f32], ch: usize) {
        // Fixed widths unroll and vectorise, as spmv_multi's: batches of up to 8 RGB
        // systems (and a warm start's extrapolation, 2).
        match ch {
            3 => return self.apply(bytemuck::cast_slice(h), bytemuck::cast_slice_mut(y)),
            6 => return scatter_fixed::<6>(&self.0, h, y),
            9 => return scatter_fixed::<9>(&self.0, h, y),
            12 => return scatter_fixed::<12>(&self.0, h, y),
            15 => return scatter_fixed::<15>(&self.0, h, y),
            18 => return scatter_fixed::<18>(&self.0, h, y),
            21 => return scatter_fixed::<21>(&self.0, h, y),
            24 => return scatter_fixed::<24>(&self.0, h, y),
            _ => {}
        }
        y.par_chunks_mut(ch)
            .with_min_len(64)
            .enumerate()
            .for_each(|(j, yj)| {
                yj.fill(0.0);
                let (cols, vals) = self.0.row(j);
                for (&i, s) in cols.iter().zip(vals) {
                    let hi = &h[i as usize * ch..(i as usize + 1) * ch];
                    for c in 0..ch {
                        yj[c] += s[c % 3] * hi[c];
                    }
                }
            });
    }
    fn diagonal(&self) -> Option<&[Rgb]> {
        None
    }
}

/// y = F x for `ch` channels per patch: one pass over F serves every channel.
pub fn spmv_multi(f: &CsrView<'_>, x: &[f32], y: &mut [f32], ch: usize) {
    // Fixed widths unroll and vectorise; batches of up to 8 RGB systems.
    match ch {
        3 => {
            let (x3, y3): (&[[f32; 3]], &mut [[f32; 3]]) =
                (bytemuck::cast_slice(x), bytemuck::cast_slice_mut(y));
            spmv_rgb(f, x3, y3);
        }
        6 => spmv_fixed::<6>(f, x, y),
        9 => spmv_fixed::<9>(f, x, y),
        12 => spmv_fixed::<12>(f, x, y),
        15 => spmv_fixed::<15>(f, x, y),
        18 => spmv_fixed::<18>(f, x, y),
        21 => spmv_fixed::<21>(f, x, y),
        24 => spmv_fixed::<24>(f, x, y),
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

/// y = S h for `CH` channels per patch (channel c uses S's colour c % 3).
fn scatter_fixed<const CH: usize>(s: &CsrView<'_, Rgb>, h: &[f32], y: &mut [f32]) {
    let (hs, ys): (&[[f32; CH]], &mut [[f32; CH]]) =
        (h.as_chunks::<CH>().0, y.as_chunks_mut::<CH>().0);
    ys.par_iter_mut()
        .with_min_len(64)
        .enumerate()
        .for_each(|(j, yj)| {
            let (cols, vals) = s.row(j);
            let mut acc = [0.0f32; CH];
            for (&i, v) in cols.iter().zip(vals) {
                let hi = &hs[i as usize];
                for c in 0..CH {
                    acc[c] += v[c % 3] * hi[c];
                }
            }
            *yj = acc;
        });
}

fn spmv_fixed<const CH: usize>(f: &CsrView<'_>, x: &[f32], y: &mut [f32]) {
    let (xs, ys): (&[[f32; CH]], &mut [[f32; CH]]) =
        (x.as_chunks::<CH>().0, y.as_chunks_mut::<CH>().0);
    ys.par_iter_mut()
        .with_min_len(64)
        .enumerate()
        .for_each(|(i, yi)| {
            let (cols, vals) = f.row(i);
            let mut acc = [0.0f32; CH];
            for (&j, &v) in cols.iter().zip(vals) {
                let xj = &xs[j as usize];
                for c in 0..CH {
                    acc[c] += v * xj[c];
                }
            }
            *yi = acc;
        });
}
