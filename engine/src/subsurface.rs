//! The subsurface-scattering matrix S of one homogeneous translucent object.
//!
//! In: the object's patches (corners, centroids, normals, areas), the optical path distance
//! r_ij between patch pairs (sparse, from `voxel::optical_distances`), and a radial profile
//! R(r) (per unit area, RGB). Out: the entries S_ji — exitance at j per unit irradiance at i —
//! as RGB triplets, and an energy report.
//!
//! ```text
//!   S_ji = (1/A_j) ∫_Aj ∫_Ai R(r(x, y)) dA_i dA_j          (PRODUCT.md, the paper's eq. 4)
//! ```
//!
//! Quadrature, by how close the pair is:
//! - far pairs (r_ij > `near_factor` × the larger patch's longest edge):
//!   S_ji = A_i (R(m − σ) + R(m + σ)) / 2, with m and σ the mean and spread of the distance
//!   between the two patches' points about r_ij (their second moments, [`far_plan`]): R
//!   is convex, so its mean over the pair lies above R(r_ij), by several percent where the
//!   profile falls steeply across a patch, and the two readings keep the mean exactly where
//!   R is quadratic in the distance;
//! - the self term and near pairs in the same plane: polar integration around m² sample
//!   points x of patch i. With W(ρ) = ∫₀^ρ R(r) 2πr dr, the integral of R over a region seen
//!   from x is Σₖ (W(ρ_out,k) − W(ρ_in,k)) / K over K directions, where [ρ_in, ρ_out] is where
//!   the ray from x at angle k crosses the region — exact in r, so patches far larger than a
//!   mean free path are handled;
//! - near pairs in different planes (across an edge of a box, neighbouring facets of a
//!   curved mesh) joined by a straight path: the same polar integration around the feet of
//!   patch i's samples on patch j's plane, each ray's ends lifted to the 3-D distance
//!   √(ρ² + h²) from the sample (exact in r too: point samples miss a profile narrower than
//!   a patch), around (2m)² sample points of patch i where the two touch at a crease
//!   ([`CREASE_DEG`]);
//! - near pairs in different planes whose optical path bends (voxel paths round a
//!   concavity): m² × m² point samples with r(x, y) = |x − y| plus the excess of the optical
//!   path over the centroid distance.
//!
//! Energy: Σ_j A_j S_ji ≤ A_i must hold for every column i (light re-emitted never exceeds
//! light received). Quadrature can overshoot a little; such columns are scaled down to the
//! bound and counted in the report, never silently.

use std::borrow::Cow;
use std::ops::Range;

use glam::Vec3;
use rayon::prelude::*;
use translux_proto::csr::{Csr, CsrBuilder, CsrView};

use crate::profile::ProfileEval;

/// Parameters of [`assemble`], defaults on each field.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SubsurfaceParams {
    /// Pairs closer than this many times the larger patch's longest edge get quadrature.
    /// Default 3.
    pub near_factor: f32,
    /// m: m² sample points per patch for quadrature. Default 4.
    pub samples: u32,
    /// K: directions of the polar integration. Default 48.
    pub directions: u32,
    /// θ_r of the receiver-side cut that a translucency change summed from radial terms
    /// makes of a hierarchical S's links (`sterms::ObjectTerms::with_node_pairs`): a receiver
    /// node m of bounding radius ρ_m ≤ θ_r |c_m − c_k| whose patches all link node k gets
    /// one node-to-node link instead. 0 keeps every receiver's own links.
    pub receiver_theta: f32,
}

impl Default for SubsurfaceParams {
    fn default() -> Self {
        Self {
            near_factor: 3.0,
            samples: 4,
            directions: 48,
            receiver_theta: 0.2,
        }
    }
}

/// One object's patches (slices of the scene's arrays for the object's patch range).
#[derive(Debug, Clone, Copy)]
pub struct ObjectPatches<'a> {
    pub corners: &'a [[Vec3; 3]],
    pub centroid: &'a [Vec3],
    pub normal: &'a [Vec3],
    pub area: &'a [f32],
    pub size: &'a [f32],
}

/// One object's block of the stored distances as a local CSR (indices relative to the
/// object's first patch): the entries of its rows whose column is inside the object and
/// that `keep(local row, distance, global entry index)` keeps. Row i of [`ObjectBlock::view`]
/// lists the patches j ≠ i within the truncation radius and r_ij.
#[derive(Debug, Default)]
pub struct ObjectBlock {
    pub csr: Csr<f32>,
    /// Each kept entry's index among the stored entries (for the arrays aligned with them:
    /// kinds, per-medium lengths).
    pub entries: Vec<usize>,
}

impl ObjectBlock {
    pub fn of(
        distances: CsrView<'_, f32>,
        r: Range<usize>,
        keep: impl Fn(usize, f32, usize) -> bool,
    ) -> ObjectBlock {
        let (base, len) = (r.start as u64, r.len() as u64);
        let mut csr = CsrBuilder::new(r.len());
        let mut entries = Vec::new();
        let mut row = Vec::new();
        for i in r {
            let first = distances.row_ptr()[i] as usize;
            let (cols, ds) = distances.row(i);
            row.clear();
            for (k, (&j, &d)) in cols.iter().zip(ds).enumerate() {
                let inside = (j as u64) >= base && (j as u64) < base + len;
                if inside && keep(i - base as usize, d, first + k) {
                    row.push(((j as u64 - base) as u32, d));
                    entries.push(first + k);
                }
            }
            csr.push_row(&row)
                .expect("a block of a checked matrix, shifted, is a valid matrix");
        }
        ObjectBlock {
            csr: csr.finish(),
            entries,
        }
    }

    /// The block as a view (checked once more: one pass).
    pub fn view(&self) -> CsrView<'_, f32> {
        self.csr
            .view()
            .expect("ObjectBlock::of builds it with the checking builder")
    }
}

/// S of one object in local indices: `rows[j]` holds (i, S_ji) sorted by i, the diagonal
/// included.
#[derive(Debug, Clone, Default)]
pub struct ObjectS {
    pub rows: Vec<Vec<(u32, [f32; 3])>>,
    /// A hierarchical S's links per row: (N + k, S_{j,N+k}), node k's column (global; see
    /// [`add_links`]). Empty for a pairwise S.
    pub links: Vec<Vec<(u32, [f32; 3])>>,
    pub report: EnergyReport,
}

/// How S's columns stand against energy conservation.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct EnergyReport {
    /// max over columns and channels of Σ_j A_j S_ji / A_i, before any scaling.
    pub max_column: f32,
    /// Mean of the same over columns (channel 1).
    pub mean_column: f32,
    /// Columns that exceeded 1 and were scaled down to it.
    pub scaled_columns: usize,
    pub nnz: u64,
}

/// R(r) and W(r) = ∫₀^r R 2πr' dr' tabulated on a grid dense near 0, interpolated linearly:
/// S assembly evaluates them millions of times.
#[derive(Debug, Clone)]
pub struct Tabulated {
    r_max: f32,
    /// Grid radii r_k = r_max (k / N)², so the peak near 0 is resolved.
    radii: Vec<f32>,
    r: Vec<[f32; 3]>,
    w: Vec<[f32; 3]>,
    w_total: [f32; 3],
    /// N / √r_max: √x times this is x's position on the grid.
    root_scale: f32,
}

impl Tabulated {
    /// Tabulates `p` on [0, r_max] with `n` intervals.
    pub fn new(p: &ProfileEval, r_max: f32, n: usize) -> Self {
        let n = n.max(8);
        let radii: Vec<f32> = (0..=n)
            .map(|k| r_max * (k as f32 / n as f32).powi(2))
            .collect();
        let r: Vec<[f32; 3]> = radii.iter().map(|&x| p.eval(x)).collect();
        // W by the trapezoid rule on 2πr R(r) over the same grid (f64 sums).
        let mut w = vec![[0.0f32; 3]; radii.len()];
        let mut acc = [0.0f64; 3];
        for k in 1..radii.len() {
            let (r0, r1) = (radii[k - 1] as f64, radii[k] as f64);
            for c in 0..3 {
                let f0 = 2.0 * std::f64::consts::PI * r0 * r[k - 1][c] as f64;
                let f1 = 2.0 * std::f64::consts::PI * r1 * r[k][c] as f64;
                acc[c] += 0.5 * (f0 + f1) * (r1 - r0);
                w[k][c] = acc[c] as f32;
            }
        }
        let w_total = w[radii.len() - 1];
        Self {
            root_scale: n as f32 / r_max.sqrt(),
            r_max,
            radii,
            r,
            w,
            w_total,
        }
    }

    fn locate(&self, x: f32) -> Option<(usize, f32)> {
        if x >= self.r_max {
            return None;
        }
        let n = (self.radii.len() - 1) as f32;
        let s = (x.max(0.0) / self.r_max).sqrt() * n;
        let k = (s as usize).min(self.radii.len() - 2);
        let (a, b) = (self.radii[k], self.radii[k + 1]);
        Some((k, if b > a { (x - a) / (b - a) } else { 0.0 }))
    }

    /// R(x), zero beyond the table.
    #[inline]
    pub fn r(&self, x: f32) -> [f32; 3] {
        match self.locate(x) {
            None => [0.0; 3],
            Some((k, t)) => lerp(&self.r, k, t),
        }
    }

    /// W(x) = ∫₀^x R 2πr dr, constant beyond the table.
    #[inline]
    pub fn w(&self, x: f32) -> [f32; 3] {
        match self.locate(x) {
            None => self.w_total,
            Some((k, t)) => lerp(&self.w, k, t),
        }
    }

    /// The cell and fraction of √x on the grid, which is uniform in √r: the lookup of
    /// [`Tabulated::r_root`] and [`Tabulated::w_root`], with no square root or division.
    #[inline]
    fn locate_root(&self, root: f32) -> Option<(usize, f32)> {
        let n = self.radii.len() - 1;
        let s = root.max(0.0) * self.root_scale;
        if s >= n as f32 {
            return None;
        }
        let k = (s as usize).min(n - 1);
        Some((k, s - k as f32))
    }

    /// R(x) given √x, interpolated linearly in √r between grid points (within a few ulps of
    /// [`Tabulated::r`] on this grid's 4096 cells; what summed terms use).
    #[inline]
    pub fn r_root(&self, root: f32) -> [f32; 3] {
        match self.locate_root(root) {
            None => [0.0; 3],
            Some((k, t)) => lerp(&self.r, k, t),
        }
    }

    /// W(x) given √x, as [`Tabulated::r_root`] does R.
    #[inline]
    pub fn w_root(&self, root: f32) -> [f32; 3] {
        match self.locate_root(root) {
            None => self.w_total,
            Some((k, t)) => lerp(&self.w, k, t),
        }
    }

    /// The radius the table ends at.
    pub fn r_max(&self) -> f32 {
        self.r_max
    }

    /// Grid cells per unit of √r (the grid is uniform in √r).
    pub fn root_scale(&self) -> f32 {
        self.root_scale
    }

    /// √ of the radius the table ends at.
    #[inline]
    pub fn root_max(&self) -> f32 {
        (self.radii.len() - 1) as f32 / self.root_scale
    }

    /// The grid radii r_k = r_max (k / N)², and R and W at them (N + 1 each): what the GPU
    /// rebuild of S uploads to interpolate exactly as [`Tabulated::r`] and [`Tabulated::w`] do.
    pub fn grid(&self) -> (&[f32], &[[f32; 3]], &[[f32; 3]]) {
        (&self.radii, &self.r, &self.w)
    }
}

/// `v[k]` to `v[k + 1]` at fraction `t`, per channel.
#[inline]
fn lerp(v: &[[f32; 3]], k: usize, t: f32) -> [f32; 3] {
    std::array::from_fn(|c| v[k][c] + t * (v[k + 1][c] - v[k][c]))
}

/// Points at the centroids of a triangle's m² regular sub-triangles (equal areas).
pub fn samples(c: &[Vec3; 3], m: u32) -> Vec<Vec3> {
    let m = m.max(1) as usize;
    let (a, e1, e2) = (c[0], (c[1] - c[0]) / m as f32, (c[2] - c[0]) / m as f32);
    let mut out = Vec::with_capacity(m * m);
    for i in 0..m {
        for j in 0..m - i {
            let (fi, fj) = (i as f32, j as f32);
            out.push(a + e1 * (fi + 1.0 / 3.0) + e2 * (fj + 1.0 / 3.0));
            if i + j + 2 <= m {
                out.push(a + e1 * (fi + 2.0 / 3.0) + e2 * (fj + 2.0 / 3.0));
            }
        }
    }
    out
}

/// ∫ over triangle `t` of R(|x − y|) dA_y for x in t's plane: polar integration with K
/// directions, exact along each direction through W.
pub fn polar_integral(x: Vec3, t: &[Vec3; 3], n: Vec3, tab: &Tabulated, k: u32) -> [f32; 3] {
    let mut sum = [0.0f32; 3];
    polar_intervals(x, t, n, k, |lo, hi| {
        let (w0, w1) = (tab.w(lo), tab.w(hi));
        for c in 0..3 {
            sum[c] += w1[c] - w0[c];
        }
    });
    sum.map(|s| s / k as f32)
}

/// ∫ over triangle `t` of R(|x − y|) dA_y for x off t's plane (normal `n`): the polar rule
/// about x's foot, lifted ([`lifted_intervals`]).
pub fn lifted_integral(x: Vec3, t: &[Vec3; 3], n: Vec3, tab: &Tabulated, k: u32) -> [f32; 3] {
    let mut sum = [0.0f32; 3];
    lifted_intervals(x, t, n, k, |lo, hi, w| {
        let (w0, w1) = (tab.w(lo), tab.w(hi));
        for c in 0..3 {
            sum[c] += w * (w1[c] - w0[c]);
        }
    });
    sum.map(|s| s / k as f32)
}

/// `factor` × the mean over the samples `xs` of `integral(x)`.
fn mean_over(xs: &[Vec3], factor: f32, integral: impl Fn(Vec3) -> [f32; 3]) -> [f32; 3] {
    let mut acc = [0.0f32; 3];
    for &x in xs {
        let v = integral(x);
        for c in 0..3 {
            acc[c] += v[c];
        }
    }
    acc.map(|v| v / xs.len() as f32 * factor)
}

/// The K rays of [`polar_integral`]: for each direction from x in t's plane that crosses
/// `t`, `f(ρ_in, ρ_out)`, where the ray enters and leaves the triangle (ρ_in = 0 when x is
/// inside). The integral is Σ (W(ρ_out) − W(ρ_in)) / K over these calls.
pub fn polar_intervals(x: Vec3, t: &[Vec3; 3], n: Vec3, k: u32, f: impl FnMut(f32, f32)) {
    let p = plane_coords(x, t, n);
    rays(&p, (0.0, std::f32::consts::TAU), k, f);
}

/// t's corners in an orthonormal frame of its plane (normal `n`) centred on x's foot.
fn plane_coords(x: Vec3, t: &[Vec3; 3], n: Vec3) -> [[f32; 2]; 3] {
    let u = (t[1] - t[0]).normalize_or_zero();
    let v = n.cross(u);
    let to2 = |p: Vec3| {
        let d = p - x;
        [d.dot(u), d.dot(v)]
    };
    [to2(t[0]), to2(t[1]), to2(t[2])]
}

/// K rays from the origin at angles spread evenly over `[θ₀, θ₀ + span)` (each at the
/// middle of its share), clipped against the triangle `p`: `f(ρ_in, ρ_out)` for each ray
/// that crosses it.
fn rays(p: &[[f32; 2]; 3], (th0, span): (f32, f32), k: u32, mut f: impl FnMut(f32, f32)) {
    // Orientation so that "inside" is left of every edge.
    let area2 =
        (p[1][0] - p[0][0]) * (p[2][1] - p[0][1]) - (p[1][1] - p[0][1]) * (p[2][0] - p[0][0]);
    let sign = if area2 >= 0.0 { 1.0 } else { -1.0 };
    // The directions by rotating one step at a time (in f64, so k steps drift by ~k ulps
    // of f64): a sine and cosine per ray were a tenth of S's assembly.
    let step = span as f64 / k as f64;
    let (sin_step, cos_step) = step.sin_cos();
    let (mut sin_th, mut cos_th) = (th0 as f64 + 0.5 * step).sin_cos();
    for _ in 0..k {
        let d = [cos_th as f32, sin_th as f32];
        (cos_th, sin_th) = (
            cos_th * cos_step - sin_th * sin_step,
            sin_th * cos_step + cos_th * sin_step,
        );
        // Clip the ray s·d, s ≥ 0, against the three edge half-planes.
        let (mut lo, mut hi) = (0.0f32, f32::INFINITY);
        let mut empty = false;
        for e in 0..3 {
            let (a, b) = (p[e], p[(e + 1) % 3]);
            let edge = [b[0] - a[0], b[1] - a[1]];
            // Inside when sign·cross(edge, q − a) ≥ 0, q = s·d: linear in s.
            let c0 = sign * (edge[0] * (-a[1]) - edge[1] * (-a[0]));
            let c1 = sign * (edge[0] * d[1] - edge[1] * d[0]);
            if c1.abs() < 1e-20 {
                if c0 < 0.0 {
                    empty = true;
                }
            } else {
                let s = -c0 / c1;
                if c1 > 0.0 {
                    lo = lo.max(s)
                } else {
                    hi = hi.min(s)
                }
            }
        }
        if !empty && hi > lo {
            f(lo, hi);
        }
    }
}

/// The angles under which the origin sees the triangle `p`, as (θ₀, span): the whole
/// circle when the origin is inside it by more than [`INSIDE_MARGIN`] of its longest edge,
/// else the arc from one corner's angle to another's that holds the third (at most about π;
/// for an origin just inside, a little more, and the rays miss only a sliver between it and
/// the nearest edge).
///
/// The margin keeps the choice stable: a sample's foot on a box's edge lies on the other
/// face's boundary, where the precompute's and a rebuild's arithmetic differ in the last
/// bits, and the two rules' angular quadratures differ by more than that.
fn seen_arc(p: &[[f32; 2]; 3]) -> (f32, f32) {
    use std::f32::consts::TAU;
    let area2 =
        (p[1][0] - p[0][0]) * (p[2][1] - p[0][1]) - (p[1][1] - p[0][1]) * (p[2][0] - p[0][0]);
    let sign = if area2 >= 0.0 { 1.0 } else { -1.0 };
    let edge = |e: usize| {
        let (a, b) = (p[e], p[(e + 1) % 3]);
        [b[0] - a[0], b[1] - a[1]]
    };
    let longest = (0..3)
        .map(|e| edge(e)[0].hypot(edge(e)[1]))
        .fold(0.0f32, f32::max);
    // Each edge's c0 is |edge| × the origin's signed distance from its line.
    let inside = (0..3).all(|e| {
        let (a, d) = (p[e], edge(e));
        sign * (d[0] * (-a[1]) - d[1] * (-a[0])) > INSIDE_MARGIN * longest * d[0].hypot(d[1])
    });
    if inside || area2 == 0.0 {
        return (0.0, TAU);
    }
    let mut a: Vec<f32> = p.iter().map(|q| q[1].atan2(q[0])).collect();
    a.sort_by(f32::total_cmp);
    // The widest gap between neighbouring corners' angles (round the circle) is what the
    // triangle leaves out; the arc starts where that gap ends.
    let gaps = [(a[1] - a[0], 1), (a[2] - a[1], 2), (a[0] + TAU - a[2], 0)];
    let (gap, after) = gaps
        .into_iter()
        .fold((f32::MIN, 0), |m, g| if g.0 > m.0 { g } else { m });
    (a[after], TAU - gap)
}

/// How far inside a triangle (a fraction of its longest edge) the origin must be for
/// [`seen_arc`] to take the whole circle.
const INSIDE_MARGIN: f32 = 1e-3;

/// [`polar_intervals`] from x's foot on t's plane (normal `n`), each ray's ends lifted to
/// the distances from x itself: `f(√(ρ_in² + h²), √(ρ_out² + h²), w)`, h x's height over
/// the plane. The rays cover only the arc under which the foot sees `t` (the whole circle
/// when the foot is inside, K rays): `arc_rays` of them, the full circle's angular
/// density, so a far or small triangle is crossed by K / 2 rays, not by the few of a full
/// circle that hit it. Each stands for w = (arc / 2π) ·
/// (K / rays) of a full circle's ray, so the integral of R over `t` seen from x is
/// Σ w (W(out) − W(in)) / K over these calls (the area element ρ dρ dθ is s ds dθ with
/// s² = ρ² + h²).
pub fn lifted_intervals(x: Vec3, t: &[Vec3; 3], n: Vec3, k: u32, mut f: impl FnMut(f32, f32, f32)) {
    let h = n.dot(x - t[0]);
    let h2 = h * h;
    let p = plane_coords(x, t, n);
    let arc = seen_arc(&p);
    let count = arc_rays(k, arc.1);
    let w = arc.1 / std::f32::consts::TAU * (k as f32 / count as f32);
    rays(&p, arc, count, |lo, hi| {
        f((lo * lo + h2).sqrt(), (hi * hi + h2).sqrt(), w)
    });
}

/// How many rays [`lifted_intervals`] spreads over an arc of `span` radians, K being the
/// full circle's: K for the whole circle, else K / 2. An arc is at most a little over π
/// ([`seen_arc`]: a foot outside the triangle, or inside by less than [`INSIDE_MARGIN`]),
/// so that is the circle's angular density. One count for every arc: a count rounded up
/// from the span would jump at π, where a sample's foot on a box's edge sees the other
/// face, and a rebuild would differ from the precompute by more than rounding.
fn arc_rays(k: u32, span: f32) -> u32 {
    if span >= std::f32::consts::TAU {
        k
    } else {
        (k / 2).max(1)
    }
}

/// A near pair's optical path counts as straight (its S taken by [`Quadrature::Lifted`])
/// when it exceeds the centroid distance by at most this fraction of the larger patch's
/// size: rounding, not a bend (a convex object's distances are the centroid distances; an
/// object's voxel paths bend by at least a voxel).
pub const STRAIGHT: f32 = 1e-4;

/// Touching near pairs whose normals are further apart than this many degrees meet at a
/// crease and integrate from more points of the source patch ([`Quadrature::Lifted`]'s
/// `source`).
pub const CREASE_DEG: f32 = 30.0;

/// Whether two triangles share a corner (within `eps`).
fn touching(a: &[Vec3; 3], b: &[Vec3; 3], eps: f32) -> bool {
    a.iter()
        .any(|u| b.iter().any(|v| u.distance_squared(*v) <= eps * eps))
}

fn coplanar(a: &[Vec3; 3], na: Vec3, b: &[Vec3; 3], nb: Vec3, eps: f32) -> bool {
    na.dot(nb) > 0.9999 && b.iter().all(|v| na.dot(*v - a[0]).abs() <= eps)
}

/// Assembles S for one object (local indices). `tab` must reach the truncation radius the
/// distances were computed with.
pub fn assemble(
    p: ObjectPatches<'_>,
    d: CsrView<'_, f32>,
    tab: &Tabulated,
    params: &SubsurfaceParams,
) -> ObjectS {
    let n = p.area.len();
    let eps = coplanar_eps(&p);
    // Columns: for each source patch i, the receivers j with S_ji (computed per column so the
    // energy bound can be enforced per column).
    let columns: Vec<Vec<(u32, [f32; 3])>> = (0..n)
        .into_par_iter()
        .map(|i| {
            let mut col = Vec::new();
            let xs = samples(&p.corners[i], params.samples);
            col.push((i as u32, self_term(&p, i, &xs, tab, params)));
            let (cols, ds) = d.row(i);
            for (&j, &r) in cols.iter().zip(ds) {
                if r >= tab.r_max() {
                    continue;
                }
                let s = pair_term(&p, i, j as usize, r, &xs, tab, params, eps);
                if s.iter().any(|&v| v > 0.0) {
                    col.push((j, s));
                }
            }
            col
        })
        .collect();
    bound_and_transpose(columns, p.area)
}

/// Tolerance of the coplanarity test: 1e-4 × the object's largest patch.
pub fn coplanar_eps(p: &ObjectPatches<'_>) -> f32 {
    1e-4 * p.size.iter().cloned().fold(0.0f32, f32::max)
}

/// How one entry S_ji is integrated: decided from geometry alone (which pair, how near, in
/// which plane), then evaluated against a profile table ([`Quadrature::eval`]) or reduced to
/// radial terms for translucency changes (`crate::sterms::reduce`), so both share one
/// decision.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Quadrature {
    /// S_ji ≈ A_i (R(r_ij + shift − σ) + R(r_ij + shift + σ)) / 2: pairs far apart compared
    /// with their size, read at the mean distance between their points ± its spread
    /// ([`far_plan`]; σ = 0 reads R(r_ij + shift) alone).
    Far { area_i: f32, shift: f32, sigma: f32 },
    /// S_ji = `factor` · mean over x ∈ patch i's samples of ∫_tri R(|x − y|) dA_y, with `tri`
    /// in the plane of normal `normal` through the samples: the self term (tri = patch i,
    /// factor 1), a coplanar near pair (tri = patch j, factor A_i / A_j), a thin sheet's near
    /// pair (tri = j projected onto i's plane, factor A_i / A_j′).
    Polar {
        tri: [Vec3; 3],
        normal: Vec3,
        factor: f32,
    },
    /// S_ji = `factor` · mean over x ∈ patch i's samples of ∫_tri R(|x − y|) dA_y, x off
    /// `tri`'s plane (normal `normal`): near pairs in different planes joined by a straight
    /// path. With x′ x's foot on the plane and h its height, |x − y| = √(ρ² + h²) for y at
    /// ρ from x′, so each ray from x′ adds W(√(ρ_out² + h²)) − W(√(ρ_in² + h²))
    /// ([`lifted_intervals`]): exact in r, like [`Quadrature::Polar`], for profiles far
    /// narrower than the patches (point samples miss them).
    ///
    /// Across a crease (touching patches whose normals are more than [`CREASE_DEG`] apart,
    /// a box's edge) `source` holds patch i's corners and x runs over (2m)² points of it
    /// ([`Quadrature::sources`]) instead of the caller's m²: there the integral over j
    /// falls off from the shared edge within a mean free path on i's side alone, and a
    /// profile far narrower than a patch falls between m² points. Between facets of a
    /// smooth mesh the over- and under-reads cancel across the neighbours, as in a plane.
    Lifted {
        tri: [Vec3; 3],
        normal: Vec3,
        factor: f32,
        source: Option<[Vec3; 3]>,
    },
    /// S_ji = A_i · mean over sample pairs (x, y) of R(|x − y| + excess): near pairs in
    /// different planes whose optical path bends (`excess`, its excess over the centroid
    /// distance, above [`STRAIGHT`] of the larger patch).
    Points {
        tri_j: [Vec3; 3],
        excess: f32,
        area_i: f32,
    },
}

impl Quadrature {
    /// The self term S_ii = (1/A_i) ∫_Ai ∫_Ai R.
    pub fn self_term(p: &ObjectPatches<'_>, i: usize) -> Quadrature {
        Quadrature::Polar {
            tri: p.corners[i],
            normal: p.normal[i],
            factor: 1.0,
        }
    }

    /// The plan for S_ji of a pair at optical distance r through one homogeneous medium
    /// (the module docs' rules); `eps` is [`coplanar_eps`] of the object.
    pub fn pair(
        p: &ObjectPatches<'_>,
        i: usize,
        j: usize,
        r: f32,
        params: &SubsurfaceParams,
        eps: f32,
    ) -> Quadrature {
        let near = r < params.near_factor * p.size[i].max(p.size[j]);
        if !near {
            far_plan(p, i, j)
        } else if coplanar(&p.corners[i], p.normal[i], &p.corners[j], p.normal[j], eps) {
            Quadrature::Polar {
                tri: p.corners[j],
                normal: p.normal[j],
                factor: p.area[i] / p.area[j],
            }
        } else {
            let excess = (r - p.centroid[i].distance(p.centroid[j])).max(0.0);
            if excess <= STRAIGHT * p.size[i].max(p.size[j]) {
                let crease = p.normal[i].dot(p.normal[j]) < CREASE_DEG.to_radians().cos()
                    && touching(&p.corners[i], &p.corners[j], eps);
                Quadrature::Lifted {
                    tri: p.corners[j],
                    normal: p.normal[j],
                    factor: p.area[i] / p.area[j],
                    source: crease.then_some(p.corners[i]),
                }
            } else {
                Quadrature::Points {
                    tri_j: p.corners[j],
                    excess,
                    area_i: p.area[i],
                }
            }
        }
    }

    /// Patch i's points the plan integrates from: `xs` (its m² sample points), or (2m)²
    /// points of patch i for a [`Quadrature::Lifted`] pair across a crease.
    pub fn sources<'a>(&self, xs: &'a [Vec3], params: &SubsurfaceParams) -> Cow<'a, [Vec3]> {
        match self {
            Quadrature::Lifted {
                source: Some(c), ..
            } => Cow::Owned(samples(c, 2 * params.samples)),
            _ => Cow::Borrowed(xs),
        }
    }

    /// Evaluates the plan at distance `r` with patch i's sample points `xs`.
    pub fn eval(
        &self,
        r: f32,
        xs: &[Vec3],
        tab: &Tabulated,
        params: &SubsurfaceParams,
    ) -> [f32; 3] {
        match *self {
            Quadrature::Far {
                area_i,
                shift,
                sigma,
            } => match two_point_roots(r + shift, sigma) {
                Some([lo, hi]) => {
                    let (a, b) = (tab.r(lo * lo), tab.r(hi * hi));
                    std::array::from_fn(|c| 0.5 * (a[c] + b[c]) * area_i)
                }
                None => tab.r(r + shift).map(|v| v * area_i),
            },
            Quadrature::Polar {
                tri,
                normal,
                factor,
            } => mean_over(xs, factor, |x| {
                polar_integral(x, &tri, normal, tab, params.directions)
            }),
            Quadrature::Lifted {
                tri,
                normal,
                factor,
                ..
            } => mean_over(&self.sources(xs, params), factor, |x| {
                lifted_integral(x, &tri, normal, tab, params.directions)
            }),
            Quadrature::Points {
                tri_j,
                excess,
                area_i,
            } => {
                let ys = samples(&tri_j, params.samples);
                let mut acc = [0.0f32; 3];
                for &x in xs {
                    for &y in &ys {
                        let v = tab.r(x.distance(y) + excess);
                        for c in 0..3 {
                            acc[c] += v[c];
                        }
                    }
                }
                let k = (xs.len() * ys.len()) as f32;
                acc.map(|v| v / k * area_i)
            }
        }
    }
}

/// A far pair's plan: A_i R read at the mean distance between the two patches' points
/// ± its spread, from the patches' second moments (Σ = (1/12) Σ_k (v_k − c)(v_k − c)ᵀ per
/// triangle; with u the unit vector between centroids D apart, the distance's mean is
/// |D| + (tr Σ − uᵀΣu) / 2|D| and its variance uᵀΣu, Σ = Σ_i + Σ_j).
pub fn far_plan(p: &ObjectPatches<'_>, i: usize, j: usize) -> Quadrature {
    let d = p.centroid[j] - p.centroid[i];
    let len = d.length();
    let area_i = p.area[i];
    if len <= 0.0 {
        return Quadrature::Far {
            area_i,
            shift: 0.0,
            sigma: 0.0,
        };
    }
    let u = d / len;
    let (mut trace, mut along) = (0.0f32, 0.0f32);
    for (k, c) in [(i, p.centroid[i]), (j, p.centroid[j])] {
        for v in p.corners[k] {
            let e = v - c;
            trace += e.length_squared() / 12.0;
            along += e.dot(u).powi(2) / 12.0;
        }
    }
    Quadrature::Far {
        area_i,
        shift: (trace - along).max(0.0) / (2.0 * len),
        sigma: along.max(0.0).sqrt(),
    }
}

/// The self term S_ii = (1/A_i) ∫_Ai ∫_Ai R = mean over x ∈ A_i of ∫_Ai R(|x − y|) dA_y,
/// with `xs` the sample points of patch i.
pub(crate) fn self_term(
    p: &ObjectPatches<'_>,
    i: usize,
    xs: &[Vec3],
    tab: &Tabulated,
    params: &SubsurfaceParams,
) -> [f32; 3] {
    Quadrature::self_term(p, i).eval(0.0, xs, tab, params)
}

/// S_ji of a pair at optical distance r (< the table's reach) through one homogeneous
/// medium, by the quadrature the module docs describe. `xs` are patch i's sample points.
#[expect(
    clippy::too_many_arguments,
    reason = "one pair's quadrature inputs, called per pair in the assembly's inner loop"
)]
pub(crate) fn pair_term(
    p: &ObjectPatches<'_>,
    i: usize,
    j: usize,
    r: f32,
    xs: &[Vec3],
    tab: &Tabulated,
    params: &SubsurfaceParams,
    eps: f32,
) -> [f32; 3] {
    Quadrature::pair(p, i, j, r, params, eps).eval(r, xs, tab, params)
}

/// Enforces Σ_j A_j S_ji / A_i ≤ 1 per column `columns[i]` = [(j, S_ji)] and channel
/// (scaling offending columns down to the bound, counted in the report), then transposes the
/// columns into rows (receivers j), sorted by source.
pub(crate) fn bound_and_transpose(mut columns: Vec<Vec<(u32, [f32; 3])>>, area: &[f32]) -> ObjectS {
    let n = columns.len();
    let mut report = EnergyReport::default();
    let mut mean = 0.0f64;
    for (i, col) in columns.iter_mut().enumerate() {
        let mut total = [0.0f32; 3];
        for &(j, s) in col.iter() {
            for c in 0..3 {
                total[c] += area[j as usize] * s[c] / area[i];
            }
        }
        let worst = total.iter().cloned().fold(0.0f32, f32::max);
        report.max_column = report.max_column.max(worst);
        mean += total[1] as f64;
        if worst > 1.0 {
            report.scaled_columns += 1;
            for (_, s) in col.iter_mut() {
                for c in 0..3 {
                    if total[c] > 1.0 {
                        s[c] /= total[c];
                    }
                }
            }
        }
    }
    report.mean_column = if n > 0 { (mean / n as f64) as f32 } else { 0.0 };

    // Transpose columns into rows (receivers), sorted by source.
    let mut rows: Vec<Vec<(u32, [f32; 3])>> = vec![Vec::new(); n];
    for (i, col) in columns.into_iter().enumerate() {
        for (j, s) in col {
            rows[j as usize].push((i as u32, s));
        }
    }
    report.nnz = rows.iter().map(|r| r.len() as u64).sum();
    ObjectS {
        rows,
        links: Vec::new(),
        report,
    }
}

/// The scene's cluster tree as a hierarchical S's links refer to it: the patches in tree
/// order, each node's range of that order, and each node's area.
#[derive(Debug, Clone, Default)]
pub struct Nodes {
    pub perm: Vec<u32>,
    pub range: Vec<[u32; 2]>,
    pub area: Vec<f32>,
}

impl Nodes {
    /// Node k's patches (global indices).
    pub fn members(&self, k: usize) -> &[u32] {
        let r = self.range[k];
        &self.perm[r[0] as usize..r[1] as usize]
    }
}

/// Adds one object's links to its S (`s` in local indices, the object starting at patch
/// `start`; `links[j]` lists (N + k, S_{j,N+k}) for local receiver j, N = `n`) and enforces
/// the energy bound on every column with them: patch i's column re-emits
/// Σ_j A_j S_ji / A_i directly plus, through every node k that holds it,
/// e_k = Σ_j A_j S_{j,N+k} / A_k (the link spreads node k's mean over its patches by area).
/// A pairwise S scales a column over 1 whole, by f_i = 1 / total. A link is shared by its
/// node's patches, so it is scaled by their area-weighted mean factor m_k, and the column's
/// direct entries by f_i, or further (to (1 − Σ_k e_k m_k) / direct) where the nodes' means
/// left more than f_i of the links: every column ends within the bound, and where a node's
/// patches are alike its column keeps the pairwise column's shape. (Until 2026-12-03 the
/// links stayed whole and the direct entries took all of the scaling: the more energy a
/// column's links carried, the more its shape departed from the pairwise column's.)
pub fn add_links(
    s: &mut ObjectS,
    start: usize,
    area: &[f32],
    links: Vec<Vec<(u32, [f32; 3])>>,
    nodes: &Nodes,
    n: usize,
) {
    if links.iter().all(Vec::is_empty) {
        return;
    }
    let local = area.len();
    // e_k per node, then spread to the member patches.
    let mut e = vec![[0.0f32; 3]; nodes.range.len()];
    for (j, row) in links.iter().enumerate() {
        for &(col, v) in row {
            let k = col as usize - n;
            for c in 0..3 {
                e[k][c] += area[j] * v[c] / nodes.area[k];
            }
        }
    }
    // Σ over the nodes holding each patch of e_k × w_k.
    let spread = |w: &dyn Fn(usize) -> [f32; 3]| {
        let mut out = vec![[0.0f32; 3]; local];
        for (k, ek) in e.iter().enumerate() {
            if ek.iter().all(|&v| v == 0.0) {
                continue;
            }
            let wk = w(k);
            for &p in nodes.members(k) {
                let i = p as usize - start;
                for c in 0..3 {
                    out[i][c] += ek[c] * wk[c];
                }
            }
        }
        out
    };
    let far = spread(&|_| [1.0; 3]);
    // Direct column sums (already bounded by 1 each).
    let mut direct = vec![[0.0f32; 3]; local];
    for (j, row) in s.rows.iter().enumerate() {
        for &(i, v) in row {
            for c in 0..3 {
                direct[i as usize][c] += area[j] * v[c] / area[i as usize];
            }
        }
    }
    // The links shared by a node's patches: each column's factor as a pairwise S would
    // scale it (1 / total past 1), the node's links scaled by its patches' area-weighted
    // mean factor, and what each node then re-emits.
    let factor: Vec<[f32; 3]> = (0..local)
        .map(|i| std::array::from_fn(|c| 1.0 / (direct[i][c] + far[i][c]).max(1.0)))
        .collect();
    let mean_factor: Vec<[f32; 3]> = (0..nodes.range.len())
        .map(|k| {
            let (mut num, mut den) = ([0.0f64; 3], 0.0f64);
            if e[k] != [0.0; 3] {
                for &p in nodes.members(k) {
                    let i = p as usize - start;
                    den += area[i] as f64;
                    for c in 0..3 {
                        num[c] += area[i] as f64 * factor[i][c] as f64;
                    }
                }
            }
            std::array::from_fn(|c| {
                if den > 0.0 {
                    (num[c] / den) as f32
                } else {
                    1.0
                }
            })
        })
        .collect();
    let mut links = links;
    if mean_factor.iter().any(|m| *m != [1.0; 3]) {
        for row in &mut links {
            for (col, v) in row.iter_mut() {
                let m = mean_factor[*col as usize - n];
                for c in 0..3 {
                    v[c] *= m[c];
                }
            }
        }
    }
    let far_kept = spread(&|k| mean_factor[k]);
    let mut scale = vec![[1.0f32; 3]; local];
    let mut scaled = 0usize;
    let mut mean = 0.0f64;
    for i in 0..local {
        mean += (direct[i][1] + far[i][1]) as f64;
        // A column no linked node reaches was bounded with its direct entries alone.
        if far[i] == [0.0; 3] {
            continue;
        }
        let mut any = false;
        for c in 0..3 {
            s.report.max_column = s.report.max_column.max(direct[i][c] + far[i][c]);
            // Scaled as the pairwise column, or further where its nodes' mean left more.
            let mut g = 1.0f32;
            if factor[i][c] < 1.0 && direct[i][c] > 0.0 {
                g = factor[i][c].min((1.0 - far_kept[i][c]).max(0.0) / direct[i][c]);
                any = true;
            }
            scale[i][c] = g;
        }
        scaled += any as usize;
    }
    if scaled > 0 {
        for row in &mut s.rows {
            for (i, v) in row.iter_mut() {
                for c in 0..3 {
                    v[c] *= scale[*i as usize][c];
                }
            }
        }
    }
    s.report.scaled_columns += scaled;
    if local > 0 {
        s.report.mean_column = (mean / local as f64) as f32;
    }
    s.report.nnz += links.iter().map(|r| r.len() as u64).sum::<u64>();
    s.links = links;
}

/// Settings of S: how far profiles are kept and stored, and the quadrature. Defaults on each
/// field.
#[derive(Debug, Clone, Copy)]
pub struct SParams {
    /// S keeps pairs out to the radius beyond which the profile carries less than this
    /// fraction of its energy. Default 1e-3.
    pub truncation_energy: f32,
    /// Distances are stored out to this many times the built profile's truncation radius,
    /// so translucency can grow that much without new geometry work. Default 2.
    pub radius_margin: f32,
    pub quadrature: SubsurfaceParams,
}

impl Default for SParams {
    fn default() -> Self {
        Self {
            truncation_energy: 1e-3,
            radius_margin: 2.0,
            quadrature: SubsurfaceParams::default(),
        }
    }
}

/// How stage 2 went for one translucent object.
#[derive(Debug, Clone, PartialEq)]
pub struct AssemblyReport {
    pub name: String,
    /// The radius S used (the profile's truncation radius, capped by the stored distances).
    pub radius: f32,
    /// Set when the profile wanted more radius than the stored distances reach.
    pub capped_from: Option<f32>,
    pub max_column_energy: f32,
    pub scaled_columns: u64,
    /// Entries of the object's S, and how many of them are links to cluster nodes.
    pub entries: u64,
    pub links: u64,
    pub seconds: f64,
}

/// The roots √(r − σ) and √(r + σ) at which a link of distance `r` and spread `sigma` is
/// read (r − σ clamped at 0), or None for a link read at r alone (σ = 0). Shared by the
/// assembly (`smatrix::node_links`), far pairs ([`Quadrature::eval`]) and the radial terms'
/// rewrite (`sterms::ObjectTerms::write`), so all read the same cells: a link's value is
/// the mean of the profile at the two.
#[inline]
pub fn two_point_roots(r: f32, sigma: f32) -> Option<[f32; 2]> {
    (sigma > 0.0).then(|| [(r - sigma).max(0.0).sqrt(), (r + sigma).max(0.0).sqrt()])
}

#[cfg(test)]
mod tests {
    use super::*;
    use translux_proto::scene::{ExpTerm, Profile};

    /// A flat square of side `side` (mm scene) split into 2·k² right triangles, facing +y.
    fn slab(side: f32, k: usize) -> Vec<[Vec3; 3]> {
        let h = side / k as f32;
        let mut t = Vec::new();
        for a in 0..k {
            for b in 0..k {
                let o = Vec3::new(a as f32 * h - side / 2.0, 0.0, b as f32 * h - side / 2.0);
                let (p0, p1, p2, p3) = (
                    o,
                    o + Vec3::Z * h,
                    o + Vec3::new(h, 0.0, h),
                    o + Vec3::X * h,
                );
                t.push([p0, p1, p2]);
                t.push([p0, p2, p3]);
            }
        }
        t
    }

    struct Owned {
        corners: Vec<[Vec3; 3]>,
        centroid: Vec<Vec3>,
        normal: Vec<Vec3>,
        area: Vec<f32>,
        size: Vec<f32>,
        row_ptr: Vec<u64>,
        col: Vec<u32>,
        dist: Vec<f32>,
    }

    impl Owned {
        fn patches(&self) -> ObjectPatches<'_> {
            ObjectPatches {
                corners: &self.corners,
                centroid: &self.centroid,
                normal: &self.normal,
                area: &self.area,
                size: &self.size,
            }
        }
    }

    /// Patches and Euclidean distances within `r_max` (brute force: test sizes are small).
    fn prepare(corners: Vec<[Vec3; 3]>, r_max: f32) -> Owned {
        let centroid: Vec<Vec3> = corners.iter().map(|c| (c[0] + c[1] + c[2]) / 3.0).collect();
        let normal = corners
            .iter()
            .map(|c| (c[1] - c[0]).cross(c[2] - c[0]).normalize())
            .collect();
        let area = corners
            .iter()
            .map(|c| 0.5 * (c[1] - c[0]).cross(c[2] - c[0]).length())
            .collect();
        let size = corners
            .iter()
            .map(|c| {
                (c[1] - c[0])
                    .length()
                    .max((c[2] - c[1]).length())
                    .max((c[0] - c[2]).length())
            })
            .collect();
        let (mut row_ptr, mut col, mut dist) = (vec![0u64], Vec::new(), Vec::new());
        for i in 0..corners.len() {
            for j in 0..corners.len() {
                let r = centroid[i].distance(centroid[j]);
                if i != j && r < r_max {
                    col.push(j as u32);
                    dist.push(r);
                }
            }
            row_ptr.push(col.len() as u64);
        }
        Owned {
            corners,
            centroid,
            normal,
            area,
            size,
            row_ptr,
            col,
            dist,
        }
    }

    fn run(o: &Owned, tab: &Tabulated) -> ObjectS {
        let n = o.area.len();
        let d = CsrView::new_checked(n, n, &o.row_ptr, &o.col, &o.dist).unwrap();
        assemble(o.patches(), d, tab, &SubsurfaceParams::default())
    }

    #[test]
    fn flat_slab_reemits_the_total_diffuse_reflectance_at_its_centre() {
        // Marble in a millimetre scene, a 120 mm slab of 4 mm patches (larger than the
        // 0.45 mm mean free path: the quadrature has to do the work).
        let marble = Profile::Dipole {
            preset: Some("marble".into()),
            sigma_a: None,
            sigma_s_prime: None,
            eta: None,
            scale: None,
        };
        let eval = ProfileEval::new(&marble, 1.0).unwrap();
        let r_max = eval.truncation_radius(1e-3);
        let tab = Tabulated::new(&eval, r_max, 4096);
        let o = prepare(slab(120.0, 30), r_max);
        let s = run(&o, &tab);
        // Uniform irradiance H = 1: B_j = Σ_i S_ji. Patches near the centre see the whole
        // profile (the slab is wider than 2 r_max), so B ≈ Rd there.
        let rd = eval.total_reflectance();
        let centre: Vec<usize> = (0..o.centroid.len())
            .filter(|&j| o.centroid[j].length() < 10.0)
            .collect();
        assert!(!centre.is_empty());
        for &j in &centre {
            let b: [f32; 3] = std::array::from_fn(|c| s.rows[j].iter().map(|(_, v)| v[c]).sum());
            for c in 0..3 {
                let rel = (b[c] - rd[c]).abs() / rd[c];
                eprintln!(
                    "slab patch {j} channel {c}: B {:.4} vs Rd {:.4} ({:.2}%)",
                    b[c],
                    rd[c],
                    rel * 100.0
                );
                assert!(
                    rel < 0.03,
                    "patch {j} channel {c}: B {} vs Rd {} ({:.2}%)",
                    b[c],
                    rd[c],
                    rel * 100.0
                );
            }
        }
        assert!(s.report.max_column <= 1.0 + 1e-3, "{:?}", s.report);
    }

    #[test]
    fn a_crease_integrates_from_more_points_of_its_source_patch() {
        // A profile 20 times narrower than the 1 mm patches: across a right-angled edge the
        // integral over the wall falls off within 0.05 mm of the edge on the source's side.
        let narrow = Profile::Exponentials {
            terms: vec![ExpTerm {
                a: [1.0; 3],
                b: [20.0; 3],
            }],
        };
        let eval = ProfileEval::new(&narrow, 1.0).unwrap();
        let r_max = eval.truncation_radius(1e-4);
        let tab = Tabulated::new(&eval, r_max, 4096);
        let a = [Vec3::ZERO, Vec3::X, Vec3::Z];
        let wall = [Vec3::ZERO, Vec3::Y, Vec3::Z];
        let turn = glam::Quat::from_axis_angle(Vec3::Z, -10f32.to_radians());
        let folded = [Vec3::ZERO, Vec3::Z, turn * -Vec3::X];
        let params = SubsurfaceParams::default();
        for (other, crease) in [(wall, true), (folded, false)] {
            let o = prepare(vec![a, other], 10.0);
            let p = o.patches();
            let r = o.centroid[0].distance(o.centroid[1]);
            let plan = Quadrature::pair(&p, 0, 1, r, &params, coplanar_eps(&p));
            let Quadrature::Lifted { source, .. } = plan else {
                panic!("a straight near pair in two planes is lifted: {plan:?}");
            };
            assert_eq!(source.is_some(), crease, "{plan:?}");
            if !crease {
                continue;
            }
            // The source integrated from 64² points, against the plan and the m² rule.
            let xs = samples(&a, params.samples);
            let dense = mean_over(&samples(&a, 64), 1.0, |x| {
                lifted_integral(x, &wall, o.normal[1], &tab, params.directions)
            })[0];
            let got = plan.eval(r, &xs, &tab, &params)[0];
            let coarse = mean_over(&xs, 1.0, |x| {
                lifted_integral(x, &wall, o.normal[1], &tab, params.directions)
            })[0];
            let (e, e_coarse) = ((got / dense - 1.0).abs(), (coarse / dense - 1.0).abs());
            eprintln!(
                "crease: (2m)² {:.2}%, m² {:.2}%",
                100.0 * e,
                100.0 * e_coarse
            );
            assert!(e < 0.5 * e_coarse, "(2m)² {e} against m² {e_coarse}");
        }
    }

    #[test]
    fn energy_never_exceeds_what_enters() {
        // A profile with total reflectance 0.95 on a small square: columns must stay ≤ 1
        // after assembly, and most of them well below (light escapes past the edges).
        let p = Profile::Exponentials {
            terms: vec![ExpTerm {
                a: [0.6, 0.5, 0.4],
                b: [2.0, 2.0, 2.0],
            }],
        };
        let eval = ProfileEval::new(&p, 1.0).unwrap();
        let r_max = eval.truncation_radius(1e-4);
        let tab = Tabulated::new(&eval, r_max, 2048);
        let o = prepare(slab(8.0, 8), r_max);
        let s = run(&o, &tab);
        for (i, _) in o.area.iter().enumerate() {
            let mut total = [0.0f32; 3];
            for (j, row) in s.rows.iter().enumerate() {
                for &(src, v) in row {
                    if src as usize == i {
                        for c in 0..3 {
                            total[c] += o.area[j] * v[c] / o.area[i];
                        }
                    }
                }
            }
            assert!(
                total.iter().all(|&t| t <= 1.0 + 1e-4),
                "column {i}: {total:?}"
            );
        }
        // The quadrature itself conserved energy: nothing needed scaling.
        assert_eq!(s.report.scaled_columns, 0, "{:?}", s.report);
        assert!(s.report.max_column < 0.95, "{:?}", s.report);

        // An unphysical profile (total reflectance 1.5) is scaled down to the bound and
        // reported, not passed on.
        let hot = Profile::Exponentials {
            terms: vec![ExpTerm {
                a: [0.9549; 3],
                b: [2.0; 3],
            }],
        };
        let eval = ProfileEval::new(&hot, 1.0).unwrap();
        assert!(eval.total_reflectance()[0] > 1.4);
        let r_max = eval.truncation_radius(1e-4);
        let tab = Tabulated::new(&eval, r_max, 2048);
        let o = prepare(slab(30.0, 12), r_max);
        let s = run(&o, &tab);
        assert!(
            s.report.scaled_columns > 0 && s.report.max_column > 1.2,
            "{:?}",
            s.report
        );
        let mut totals = vec![0.0f32; o.area.len()];
        for (j, row) in s.rows.iter().enumerate() {
            for &(src, v) in row {
                totals[src as usize] += o.area[j] * v[0] / o.area[src as usize];
            }
        }
        assert!(totals.iter().all(|&t| t <= 1.0 + 1e-4), "{totals:?}");
    }

    #[test]
    fn polar_integral_of_a_constant_is_the_area() {
        // R ≡ 1/area-unit up to r_max: ∫ R dA over the triangle = its area, from any point
        // inside it.
        let t = [
            Vec3::ZERO,
            Vec3::new(3.0, 0.0, 0.0),
            Vec3::new(0.0, 0.0, -2.0),
        ];
        let n = (t[1] - t[0]).cross(t[2] - t[0]).normalize();
        let radii = vec![0.0, 10.0];
        let tab_profile = Profile::Table {
            radius_mm: radii.clone(),
            values: vec![[1.0; 3], [1.0; 3]],
        };
        let eval = ProfileEval::new(&tab_profile, 1.0).unwrap();
        let tab = Tabulated::new(&eval, 9.99, 4096);
        for x in [Vec3::new(1.0, 0.0, -0.5), Vec3::new(0.2, 0.0, -1.5)] {
            let v = polar_integral(x, &t, n, &tab, 720);
            assert!((v[0] - 3.0).abs() < 0.01, "{v:?}");
        }
    }
}
