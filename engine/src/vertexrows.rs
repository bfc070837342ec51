//! A relight's colour stage as sparse rows, for a backend that makes the vertex colours
//! where B is (the GPU, `translux-server`'s `gpu::relight`).
//!
//! In: a bundle, its [`VertexSamples`] and which objects count as opaque (the bundle's
//! materials under the `full` components). Out: [`VertexRows`], per viewer vertex one row
//! over the patches and a mode, so that the colour of vertex q is
//!
//! ```text
//!   mean:   L(q) = Σ_k w_qk B_k                            (w = a_k / (π Σ a))
//!   opaque: c = Σ_k w_qk (B_k − ρ_k E_k), clamped to [lo − s, hi + s] over the row's terms
//!           (s = OVERSHOOT · (hi − lo)),  L(q) = max(0, (c + ρ̄_q E(q)) / π)
//! ```
//!
//! With the direct light per pixel (`direct_at: pixel`) the opaque vertices of diffuse
//! objects leave out ρ̄_q E(q) (mode 2), and the exposure is taken from the luminance of
//! the whole answer.
//!
//! with E(q) the direct light at the vertex's sample point: the same numbers as
//! [`crate::radiosity::vertex_radiance`] followed by [`crate::vertexlight::VertexMeans`]
//! (which [`VertexRows::colours`] computes from the rows, and the tests hold to them).

use translux_proto::bundle::Bundle;

use crate::linalg::Rgb;
use crate::vertexlight::{OVERSHOOT, VertexSamples};

/// The colour stage as rows (see the module docs).
#[derive(Debug, Clone, Default)]
pub struct VertexRows {
    /// Row q spans `offsets[q]..offsets[q + 1]` of `patch` and `weight`.
    pub offsets: Vec<u32>,
    pub patch: Vec<u32>,
    pub weight: Vec<f32>,
    /// Per vertex: ρ̄ (the area-weighted albedo of the patches it counts) in `[0..3]`, and
    /// in `[3]` 0 for the plain mean, 1 for an opaque vertex (its own direct term), 2 for
    /// one of a diffuse object (whose direct term a picture adds per pixel).
    pub own: Vec<[f32; 4]>,
    /// Per patch: the albedo ρ the opaque rows subtract ρE with.
    pub albedo: Vec<Rgb>,
    /// Per vertex: where its direct light is evaluated, and the normal there.
    pub point: Vec<[f32; 3]>,
    pub normal: Vec<[f32; 3]>,
    /// How far past its terms' spread an opaque row's value may run (a share of it).
    pub overshoot: f32,
}

impl VertexRows {
    /// The rows for the bundle's materials, the vertices of objects with `opaque[o]` set
    /// taking their own direct term ([`crate::vertexlight::opaque_objects`]), those of
    /// objects with `per_pixel[o]` set (diffuse ones) leaving it to a picture per pixel.
    pub fn new(
        b: &Bundle,
        samples: &VertexSamples,
        opaque: &[bool],
        per_pixel: &[bool],
    ) -> VertexRows {
        let v = b.vertex_positions().len();
        let albedo = b.patch_albedo().to_vec();
        let (rho, area) = counted_albedo(b, samples, &albedo, v);
        let mut mode = vec![0.0f32; v];
        for q in samples.opaque_vertices(b, opaque) {
            if area[q] > 0.0 {
                mode[q] = 1.0;
            }
        }
        for q in samples.opaque_vertices(b, per_pixel) {
            if mode[q] == 1.0 {
                mode[q] = 2.0;
            }
        }
        let means = mean_rows(b, v);
        let mut rows = VertexRows {
            offsets: vec![0],
            overshoot: OVERSHOOT as f32,
            albedo,
            point: samples.point.iter().map(|p| p.to_array()).collect(),
            normal: samples.normal.iter().map(|n| n.to_array()).collect(),
            ..VertexRows::default()
        };
        for q in 0..v {
            if mode[q] > 0.0 {
                let r: [f32; 3] = std::array::from_fn(|c| (rho[q][c] / area[q]) as f32);
                rows.own.push([r[0], r[1], r[2], mode[q]]);
                // The reconstruction's weights; the 1/π comes after the clamp.
                rows.push(samples.rest.row(q));
            } else {
                rows.own.push([0.0; 4]);
                rows.push(means[q].iter().copied());
            }
        }
        rows
    }

    fn push(&mut self, row: impl Iterator<Item = (usize, f32)>) {
        for (k, w) in row {
            self.patch.push(k as u32);
            self.weight.push(w);
        }
        self.offsets.push(self.patch.len() as u32);
    }

    /// Vertices.
    pub fn len(&self) -> usize {
        self.own.len()
    }

    /// Whether there are no vertices.
    pub fn is_empty(&self) -> bool {
        self.own.is_empty()
    }

    /// The colours from B (`rad`) and E per patch and E at each vertex's sample point
    /// (`at_vertex`, one per vertex): the module's formula, in f64 as the CPU path sums;
    /// with `pixel`, without the direct term of mode-2 vertices.
    pub fn colours(&self, rad: &[Rgb], e: &[Rgb], at_vertex: &[Rgb], pixel: bool) -> Vec<Rgb> {
        let inv_pi = 1.0 / std::f64::consts::PI;
        (0..self.len())
            .map(|q| {
                let (a, z) = (self.offsets[q] as usize, self.offsets[q + 1] as usize);
                let row = self.patch[a..z].iter().zip(&self.weight[a..z]);
                let own = self.own[q];
                if own[3] == 0.0 {
                    let mut sum = [0.0f64; 3];
                    for (&k, &w) in row {
                        for c in 0..3 {
                            sum[c] += w as f64 * rad[k as usize][c] as f64;
                        }
                    }
                    return sum.map(|s| s as f32);
                }
                let mut lo = [f64::INFINITY; 3];
                let mut hi = [f64::NEG_INFINITY; 3];
                let mut sum = [0.0f64; 3];
                for (&k, &w) in row {
                    let k = k as usize;
                    for c in 0..3 {
                        let r = rad[k][c] as f64 - self.albedo[k][c] as f64 * e[k][c] as f64;
                        sum[c] += w as f64 * r;
                        lo[c] = lo[c].min(r);
                        hi[c] = hi[c].max(r);
                    }
                }
                let direct = if pixel && own[3] == 2.0 { 0.0 } else { 1.0 };
                std::array::from_fn(|c| {
                    let rest = if lo[c] <= hi[c] {
                        let slack = self.overshoot as f64 * (hi[c] - lo[c]);
                        sum[c].clamp(lo[c] - slack, hi[c] + slack)
                    } else {
                        0.0
                    };
                    let ev = direct * own[c] as f64 * at_vertex[q][c] as f64;
                    ((rest + ev) * inv_pi).max(0.0) as f32
                })
            })
            .collect()
    }
}

/// Per vertex, Σ a ρ and Σ a over the patches that count in its means.
fn counted_albedo(
    b: &Bundle,
    samples: &VertexSamples,
    albedo: &[Rgb],
    v: usize,
) -> (Vec<[f64; 3]>, Vec<f64>) {
    let mut rho = vec![[0.0f64; 3]; v];
    let mut area = vec![0.0f64; v];
    for (k, t) in b.triangle_vertices().iter().enumerate() {
        if !samples.counts[k] {
            continue;
        }
        let a = b.patch_areas()[k] as f64;
        for &q in t {
            let q = q as usize;
            for c in 0..3 {
                rho[q][c] += a * albedo[k][c] as f64;
            }
            area[q] += a;
        }
    }
    (rho, area)
}

/// Per vertex, the patches that use it with weight a_k / (π Σ a) (every patch, as
/// [`crate::radiosity::vertex_radiance`] takes them).
fn mean_rows(b: &Bundle, v: usize) -> Vec<Vec<(usize, f32)>> {
    let mut rows: Vec<Vec<(usize, f64)>> = vec![Vec::new(); v];
    let mut total = vec![0.0f64; v];
    for (k, (t, &a)) in b
        .triangle_vertices()
        .iter()
        .zip(b.patch_areas())
        .enumerate()
    {
        for &q in t {
            rows[q as usize].push((k, a as f64));
            total[q as usize] += a as f64;
        }
    }
    let inv_pi = 1.0 / std::f64::consts::PI;
    rows.into_iter()
        .zip(total)
        .map(|(row, t)| {
            row.into_iter()
                .filter(|_| t > 0.0)
                .map(|(k, a)| (k, (a / t * inv_pi) as f32))
                .collect()
        })
        .collect()
}
