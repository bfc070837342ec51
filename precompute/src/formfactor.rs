//! The form-factor matrix F, with visibility.
//!
//! In: [`Patches`], an [`Occluder`] over the scene's source triangles, [`FormFactorParams`].
//! Out: F as a [`Csr`] whose rows are receivers — F_ij is the fraction of the power leaving
//! patch i that reaches patch j directly — and a [`FormFactorInfo`] summary.
//!
//! Method, per unordered pair {i, j}:
//! 1. Orientation cull: each patch must have a corner strictly in front of the other's plane
//!    (back-facing and coplanar pairs exchange nothing).
//! 2. The smaller patch p is the "point" side, the larger q the polygon: the differential
//!    form factor from a point x with normal n to polygon q (Lambert's contour formula,
//!    q first clipped to the half-space in front of x),
//!    `F(x → q) = (1/2π) |Σₖ θₖ n·ĝₖ|`, `ĝₖ = unit(rₖ × rₖ₊₁)`, `θₖ = ∠(rₖ, rₖ₊₁)`,
//!    `rₖ = qₖ − x`, is exact for the polygon; only p is point-sampled. Far pairs use p's
//!    centroid and one occlusion ray centroid to centroid. Near pairs (centroid distance
//!    below `near_factor` × the larger patch's longest edge), and far pairs whose centroid
//!    form factor exceeds `far_sampled_above` (one ray would decide a large share of a row:
//!    a floor patch seeing the ceiling past a table's edge), average F(x → q) over
//!    `near_samples`² equal-area points x of p, each with its own ray to one of as many
//!    points of q, taken in front of x's plane (the part of q behind it is clipped from
//!    F(x → q)); the rays spread over q, so a q partly hidden counts in part.
//! 3. Reciprocity gives the other direction: A_p F_pq = A_q F_qp. Nothing is computed twice.
//!
//! Entries below `threshold` are dropped only when asked, and the power they carried is
//! reported as `dropped_energy`.

use std::sync::atomic::{AtomicU64, Ordering};

use glam::Vec3;
use rayon::prelude::*;
use translux_proto::bundle::FormFactorInfo;
use translux_proto::csr::Csr;

use crate::patch::Patches;
use translux_engine::raycast::Occluder;

/// Parameters of [`compute`], with the defaults documented on each field.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FormFactorParams {
    /// Pairs whose centroids are closer than this many times the larger patch's longest
    /// edge are sub-sampled. Default 2.5.
    pub near_factor: f32,
    /// Sub-sampling level for near pairs: m² points on the smaller patch. Default 4.
    pub near_samples: u32,
    /// Sub-sampling level for touching pairs (centroids closer than 1.5 × the larger
    /// patch's longest edge: neighbours across a crease, where F(x → q) varies fastest).
    /// Default 10.
    pub touching_samples: u32,
    /// Far pairs whose form factor from the point side's centroid exceeds this are sampled
    /// as near pairs (`near_samples`² points, as many rays), not decided by one ray.
    /// Default 10⁻³.
    pub far_sampled_above: f32,
    /// Drop entries below this value (0 = keep every non-zero entry). Default 0.
    pub threshold: f32,
}

impl Default for FormFactorParams {
    fn default() -> Self {
        Self {
            near_factor: 2.5,
            near_samples: 4,
            touching_samples: 10,
            far_sampled_above: 1e-3,
            threshold: 0.0,
        }
    }
}

/// Differential form factor from a point `x` with unit normal `n` to the polygon `poly`,
/// without occlusion. The polygon is clipped to the half-space n·(y − x) ≥ 0 first; the
/// polygon's own facing is the caller's business.
pub fn point_to_polygon(x: Vec3, n: Vec3, poly: &[Vec3]) -> f32 {
    // Clip (Sutherland–Hodgman against one plane); a triangle becomes at most a quad.
    let mut clipped = [Vec3::ZERO; 8];
    let mut m = 0;
    let h = |p: Vec3| n.dot(p - x);
    let k = poly.len();
    let mut all_front = true;
    for p in poly {
        if h(*p) < 0.0 {
            all_front = false;
        }
    }
    let verts: &[Vec3] = if all_front {
        poly
    } else {
        for a in 0..k {
            let (p, q) = (poly[a], poly[(a + 1) % k]);
            let (hp, hq) = (h(p), h(q));
            if hp >= 0.0 {
                clipped[m] = p;
                m += 1;
            }
            if (hp >= 0.0) != (hq >= 0.0) {
                let t = hp / (hp - hq);
                clipped[m] = p + (q - p) * t;
                m += 1;
            }
        }
        if m < 3 {
            return 0.0;
        }
        &clipped[..m]
    };
    // Lambert: each edge contributes its angle times the cosine of its plane with n.
    let mut sum = 0.0f32;
    let len = verts.len();
    for a in 0..len {
        let r0 = verts[a] - x;
        let r1 = verts[(a + 1) % len] - x;
        let c = r0.cross(r1);
        let cl = c.length();
        if cl <= 1e-30 {
            continue;
        }
        let theta = cl.atan2(r0.dot(r1));
        sum += theta * n.dot(c) / cl;
    }
    (sum.abs() / (2.0 * std::f32::consts::PI)).min(1.0)
}

/// Points of a triangle at the centroids of its m² regular sub-triangles (equal areas).
fn sample_points(c: &[Vec3; 3], m: u32, out: &mut Vec<Vec3>) {
    out.clear();
    let m = m.max(1) as usize;
    let (a, e1, e2) = (c[0], (c[1] - c[0]) / m as f32, (c[2] - c[0]) / m as f32);
    let at = |i: f32, j: f32| a + e1 * i + e2 * j;
    for i in 0..m {
        for j in 0..m - i {
            let (fi, fj) = (i as f32, j as f32);
            out.push(at(fi + 1.0 / 3.0, fj + 1.0 / 3.0));
            if i + j + 2 <= m {
                out.push(at(fi + 2.0 / 3.0, fj + 2.0 / 3.0));
            }
        }
    }
}

/// Near pairs: sample k of the point side asks visibility at the polygon's sample
/// (STRIDE k + 3) mod m² (or the next in front of its plane), so the rays spread over both
/// patches and each of q's points is asked about once (7 is prime to 16 and 100).
const VISIBILITY_STRIDE: usize = 7;

/// True when some corner of `corners` lies strictly in front of the plane (x, n).
#[inline]
pub(crate) fn any_in_front(corners: &[Vec3; 3], x: Vec3, n: Vec3, eps: f32) -> bool {
    corners.iter().any(|v| n.dot(*v - x) > eps)
}

/// F_ij and F_ji of one pair that passed the orientation cull (`None`: they exchange
/// nothing). The smaller patch is point-sampled (its centroid far away unless the pair's
/// form factor is above `far_sampled_above`, `near_samples`² or `touching_samples`²
/// points near), the larger integrated exactly; reciprocity gives the
/// other direction. Adds the rays it cast to `rays`. Shared by the dense F and the leaf
/// links of the hierarchical one ([`crate::hierarchy`]).
#[expect(
    clippy::too_many_arguments,
    reason = "the pair's two ids beside the scene-wide inputs and the caller's scratch"
)]
pub(crate) fn pair(
    p: &Patches,
    occ: &Occluder,
    params: &FormFactorParams,
    offset: f32,
    i: usize,
    j: usize,
    samples: &mut Vec<Vec3>,
    rays: &mut u64,
) -> Option<(f32, f32)> {
    let (ai, aj) = (p.area[i], p.area[j]);
    let (pp, qq) = if ai <= aj { (i, j) } else { (j, i) };
    let (cp, np, cq, nq) = (p.centroid[pp], p.normal[pp], p.centroid[qq], p.normal[qq]);
    let poly = &p.corners[qq];
    let dist = cp.distance(cq);
    let big = p.size[i].max(p.size[j]);
    let near = dist < params.near_factor * big;
    let far_f = if near || nq.dot(cp - cq) <= 0.0 {
        0.0
    } else {
        point_to_polygon(cp, np, poly)
    };
    let f_pq = if !near && far_f <= params.far_sampled_above {
        if far_f <= 0.0 {
            return None;
        }
        *rays += 1;
        if occ.occluded(cp + np * offset, cq + nq * offset) {
            return None;
        }
        far_f
    } else {
        let m = if near && dist < 1.5 * big {
            params.touching_samples
        } else {
            params.near_samples
        };
        sample_points(&p.corners[pp], m, samples);
        let mut targets = Vec::with_capacity(samples.len());
        sample_points(poly, m, &mut targets);
        let mut sum = 0.0;
        for (k, &x) in samples.iter().enumerate() {
            if nq.dot(x - cq) <= 0.0 {
                continue;
            }
            // Visibility of q from x, asked at one of q's points in front of x's plane (the
            // part behind it is clipped from F(x → q)): the first from (STRIDE k + 3) on.
            let Some(y) = (0..targets.len())
                .map(|t| targets[(VISIBILITY_STRIDE * k + 3 + t) % targets.len()])
                .find(|y| np.dot(*y - x) > 0.0)
            else {
                continue;
            };
            *rays += 1;
            if occ.occluded(x + np * offset, y + nq * offset) {
                continue;
            }
            sum += point_to_polygon(x, np, poly);
        }
        sum / samples.len() as f32
    };
    if f_pq <= 0.0 {
        return None;
    }
    // Reciprocity: A_p F_pq = A_q F_qp.
    let f_qp = f_pq * p.area[pp] / p.area[qq];
    Some(if pp == i { (f_pq, f_qp) } else { (f_qp, f_pq) })
}

/// Row i of dense F, exactly as [`compute`] makes it (the same culls and the same pair rule,
/// each pair evaluated in the order `compute` evaluates it): the reference for checking
/// single rows of a hierarchical F where dense F would not fit. Sorted by column.
pub fn dense_row(
    p: &Patches,
    occ: &Occluder,
    params: &FormFactorParams,
    i: usize,
) -> Vec<(u32, f32)> {
    let diag = occ.diagonal();
    let (eps_plane, offset) = (1e-6 * diag, 1e-5 * diag);
    let (mut samples, mut rays) = (Vec::new(), 0u64);
    let mut row = Vec::new();
    for j in 0..p.len() {
        if j == i
            || !any_in_front(&p.corners[j], p.centroid[i], p.normal[i], eps_plane)
            || !any_in_front(&p.corners[i], p.centroid[j], p.normal[j], eps_plane)
        {
            continue;
        }
        let (a, b) = (i.min(j), i.max(j));
        if let Some((f_ab, f_ba)) = pair(p, occ, params, offset, a, b, &mut samples, &mut rays) {
            let f = if a == i { f_ab } else { f_ba };
            if f >= params.threshold {
                row.push((j as u32, f));
            }
        }
    }
    row
}

/// The summary of a computed F (dense, or the C of a hierarchical one: P keeps constants,
/// so C's row sums are F̃'s): entries and row sums Σ_j F_ij (mean, min, max).
pub(crate) fn summarize(
    csr: &Csr,
    threshold: f32,
    dropped_energy: f64,
    rays: u64,
    pairs: u64,
) -> FormFactorInfo {
    let sums: Vec<f64> = (0..csr.n_rows)
        .into_par_iter()
        .map(|i| {
            let (a, b) = (csr.row_ptr[i] as usize, csr.row_ptr[i + 1] as usize);
            csr.val[a..b].iter().map(|&v| v as f64).sum()
        })
        .collect();
    summarize_sums(
        &sums,
        csr.nnz() as u64,
        threshold,
        dropped_energy,
        rays,
        pairs,
    )
}

/// [`summarize`] from each patch's row sum (a two-sided C's node rows already added).
pub(crate) fn summarize_sums(
    sums: &[f64],
    nnz: u64,
    threshold: f32,
    dropped_energy: f64,
    rays: u64,
    pairs: u64,
) -> FormFactorInfo {
    let n = sums.len();
    FormFactorInfo {
        nnz,
        threshold,
        dropped_energy,
        row_sum_mean: if n > 0 {
            sums.iter().sum::<f64>() / n as f64
        } else {
            0.0
        },
        row_sum_min: sums
            .iter()
            .cloned()
            .fold(f64::INFINITY, f64::min)
            .min(f64::MAX),
        row_sum_max: sums.iter().cloned().fold(0.0, f64::max),
        rays,
        pairs,
    }
}

/// One computed pair: column j (> row i), F_ij and F_ji.
type UpperEntry = (u32, f32, f32);

/// Computes F. `progress` is called with the number of pairs finished since its last call.
pub fn compute(
    p: &Patches,
    occ: &Occluder,
    params: &FormFactorParams,
    progress: &(dyn Fn(u64) + Sync),
) -> (Csr, FormFactorInfo) {
    compute_with_stop(p, occ, params, progress, &|| false)
}

/// [`compute`] that skips the rows not yet started once `stop()` returns `true` (a
/// cancelled precompute job); the result is then incomplete and must be thrown away.
pub fn compute_with_stop(
    p: &Patches,
    occ: &Occluder,
    params: &FormFactorParams,
    progress: &(dyn Fn(u64) + Sync),
    stop: &(dyn Fn() -> bool + Sync),
) -> (Csr, FormFactorInfo) {
    let n = p.len();
    let diag = occ.diagonal();
    let eps_plane = 1e-6 * diag;
    let offset = 1e-5 * diag;
    let rays = AtomicU64::new(0);
    let pairs = AtomicU64::new(0);

    // 1. The upper triangle, row by row in parallel.
    let upper: Vec<Vec<UpperEntry>> = (0..n)
        .into_par_iter()
        .with_min_len(8)
        .map_init(Vec::new, |samples, i| {
            let mut row = Vec::new();
            if stop() {
                return row;
            }
            let (ci, ni) = (p.centroid[i], p.normal[i]);
            let corners_i = &p.corners[i];
            let (mut row_rays, mut row_pairs) = (0u64, 0u64);
            for j in i + 1..n {
                let (cj, nj) = (p.centroid[j], p.normal[j]);
                if !any_in_front(&p.corners[j], ci, ni, eps_plane)
                    || !any_in_front(corners_i, cj, nj, eps_plane)
                {
                    continue;
                }
                row_pairs += 1;
                let Some((f_ij, f_ji)) = pair(p, occ, params, offset, i, j, samples, &mut row_rays)
                else {
                    continue;
                };
                row.push((j as u32, f_ij, f_ji));
            }
            rays.fetch_add(row_rays, Ordering::Relaxed);
            pairs.fetch_add(row_pairs, Ordering::Relaxed);
            progress((n - 1 - i) as u64);
            row
        })
        .collect();

    // 2. Threshold (explicit only), counting the power dropped: Σ A_i F_ij over dropped.
    let thr = params.threshold;
    let mut dropped = 0.0f64;
    let mut upper_count = vec![0u64; n];
    let mut lower_count = vec![0u64; n];
    for (i, row) in upper.iter().enumerate() {
        for &(j, fij, fji) in row {
            if fij >= thr {
                upper_count[i] += 1;
            } else {
                dropped += p.area[i] as f64 * fij as f64;
            }
            if fji >= thr {
                lower_count[j as usize] += 1;
            } else {
                dropped += p.area[j as usize] as f64 * fji as f64;
            }
        }
    }

    // 3. The lower triangle as a transposed scatter: row j gets (i, F_ji) for i < j, in
    //    increasing i because rows are visited in order.
    let mut lower_ptr = vec![0u64; n + 1];
    for j in 0..n {
        lower_ptr[j + 1] = lower_ptr[j] + lower_count[j];
    }
    let nnz_lower = lower_ptr[n] as usize;
    let mut lower_col = vec![0u32; nnz_lower];
    let mut lower_val = vec![0f32; nnz_lower];
    let mut fill = lower_ptr.clone();
    for (i, row) in upper.iter().enumerate() {
        for &(j, _, fji) in row {
            if fji >= thr {
                let at = &mut fill[j as usize];
                lower_col[*at as usize] = i as u32;
                lower_val[*at as usize] = fji;
                *at += 1;
            }
        }
    }

    // 4. Final rows: lower part then upper part, filled in parallel into disjoint slices.
    let mut row_ptr = vec![0u64; n + 1];
    for i in 0..n {
        row_ptr[i + 1] = row_ptr[i] + lower_count[i] + upper_count[i];
    }
    let nnz = row_ptr[n] as usize;
    let mut col = vec![0u32; nnz];
    let mut val = vec![0f32; nnz];
    {
        let mut col_rows: Vec<&mut [u32]> = Vec::with_capacity(n);
        let mut val_rows: Vec<&mut [f32]> = Vec::with_capacity(n);
        let (mut crest, mut vrest) = (&mut col[..], &mut val[..]);
        for i in 0..n {
            let len = (row_ptr[i + 1] - row_ptr[i]) as usize;
            let (c, ct) = crest.split_at_mut(len);
            let (v, vt) = vrest.split_at_mut(len);
            col_rows.push(c);
            val_rows.push(v);
            crest = ct;
            vrest = vt;
        }
        col_rows
            .into_par_iter()
            .zip(val_rows)
            .zip(upper.into_par_iter())
            .enumerate()
            .for_each(|(i, ((c, v), up))| {
                let (a, b) = (lower_ptr[i] as usize, lower_ptr[i + 1] as usize);
                let k = b - a;
                c[..k].copy_from_slice(&lower_col[a..b]);
                v[..k].copy_from_slice(&lower_val[a..b]);
                let mut at = k;
                for (j, fij, _) in up {
                    if fij >= thr {
                        c[at] = j;
                        v[at] = fij;
                        at += 1;
                    }
                }
            });
    }
    let csr = Csr {
        n_rows: n,
        n_cols: n,
        row_ptr,
        col,
        val,
    };

    // 5. Summary: row sums (1 in a closed room), power dropped as a fraction of all power.
    let total_area: f64 = p.area.iter().map(|&a| a as f64).sum();
    let dropped_energy = if total_area > 0.0 {
        dropped / total_area
    } else {
        0.0
    };
    let info = summarize(
        &csr,
        thr,
        dropped_energy,
        rays.into_inner(),
        pairs.into_inner(),
    );
    (csr, info)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f32::consts::PI;

    #[test]
    fn point_to_disc_like_polygon_matches_closed_form() {
        // A point on axis under a parallel square of half-side s at height h:
        // F = (2/π)[ (s/√(s²+h²)) atan(s/√(s²+h²)) ] · 2 … use the classic closed form for a
        // point to a coaxial rectangle corner, summed over four quadrants:
        // F_corner(a, b, h) = (1/2π)[ A/√(1+A²) atan(B/√(1+A²)) + B/√(1+B²) atan(A/√(1+B²)) ],
        // A = a/h, B = b/h.
        let corner = |a: f32, b: f32, h: f32| {
            let (a, b) = (a / h, b / h);
            let (sa, sb) = ((1.0 + a * a).sqrt(), (1.0 + b * b).sqrt());
            (a / sa * (b / sa).atan() + b / sb * (a / sb).atan()) / (2.0 * PI)
        };
        let (s, h) = (0.7f32, 1.3f32);
        let sq = [
            Vec3::new(-s, h, -s),
            Vec3::new(s, h, -s),
            Vec3::new(s, h, s),
            Vec3::new(-s, h, s),
        ];
        let f = point_to_polygon(Vec3::ZERO, Vec3::Y, &sq);
        let exact = 4.0 * corner(s, s, h);
        assert!((f - exact).abs() / exact < 1e-4, "{f} vs {exact}");
        // Winding does not matter.
        let rev = [sq[3], sq[2], sq[1], sq[0]];
        assert!((point_to_polygon(Vec3::ZERO, Vec3::Y, &rev) - f).abs() < 1e-6);
        // Half below the horizon: only the upper half counts (clipped).
        let tilted = [
            Vec3::new(1.0, -1.0, -1.0),
            Vec3::new(1.0, 1.0, -1.0),
            Vec3::new(1.0, 1.0, 1.0),
            Vec3::new(1.0, -1.0, 1.0),
        ];
        let half = point_to_polygon(Vec3::ZERO, Vec3::Y, &tilted);
        let upper_only = [
            Vec3::new(1.0, 0.0, -1.0),
            Vec3::new(1.0, 1.0, -1.0),
            Vec3::new(1.0, 1.0, 1.0),
            Vec3::new(1.0, 0.0, 1.0),
        ];
        assert!((half - point_to_polygon(Vec3::ZERO, Vec3::Y, &upper_only)).abs() < 1e-6);
        // A huge plane overhead covers the whole hemisphere.
        let big = 1e4;
        let sky = [
            Vec3::new(-big, 1.0, -big),
            Vec3::new(big, 1.0, -big),
            Vec3::new(big, 1.0, big),
            Vec3::new(-big, 1.0, big),
        ];
        assert!((point_to_polygon(Vec3::ZERO, Vec3::Y, &sky) - 1.0).abs() < 1e-3);
    }

    #[test]
    fn sample_points_are_inside_and_average_to_centroid() {
        let c = [Vec3::ZERO, Vec3::X, Vec3::Y];
        let mut pts = Vec::new();
        for m in 1..6 {
            sample_points(&c, m, &mut pts);
            assert_eq!(pts.len(), (m * m) as usize);
            let mean = pts.iter().fold(Vec3::ZERO, |a, b| a + *b) / pts.len() as f32;
            assert!(mean.distance(Vec3::new(1.0 / 3.0, 1.0 / 3.0, 0.0)) < 1e-5);
            assert!(
                pts.iter()
                    .all(|p| p.x > 0.0 && p.y > 0.0 && p.x + p.y < 1.0)
            );
        }
    }

    /// The box `[lo, hi]` as the scene file's `box` shape makes it (facing out, or in).
    fn box_triangles(lo: Vec3, hi: Vec3, inward: bool) -> Vec<[Vec3; 3]> {
        let shape = translux_proto::scene::Shape::Box {
            size: (hi - lo).to_array(),
            inward,
        };
        let centre = (lo + hi) * 0.5;
        crate::shapes::shape_triangles(&shape)
            .into_iter()
            .map(|t| t.map(|v| v + centre))
            .collect()
    }

    /// A box standing on the floor of a closed 1 m room, off the patch grid: every patch
    /// sees a closed surround, so each face of the box off the floor sees all of its
    /// hemisphere (row sum 1, within the pair rule's error), the bottom row too, whose
    /// nearest floor patches lie partly under the box. A near pair's visibility asked at
    /// the source's centroid alone found such a floor patch hidden or seen whole, and
    /// asked at points all over it, counted the part behind the receiver's plane (which
    /// F(x → q) leaves out) as hidden: the bottom row read 0.82–0.87.
    #[test]
    fn a_box_on_the_floor_sees_its_whole_hemisphere() {
        let room = box_triangles(Vec3::ZERO, Vec3::ONE, true);
        let block = box_triangles(
            Vec3::new(0.37, 0.0, 0.33),
            Vec3::new(0.63, 0.3, 0.61),
            false,
        );
        let objects: Vec<&[[Vec3; 3]]> = vec![&room, &block];
        let p = crate::patch::subdivide(&objects, 0.06);
        let occ = Occluder::new(&p.corners);
        let (f, info) = compute(&p, &occ, &FormFactorParams::default(), &|_| {});
        let view = f.view().unwrap();
        let sum = |i: usize| view.row(i).1.iter().map(|&v| v as f64).sum::<f64>();
        let worst = (0..p.len()).map(sum).fold(0.0, f64::max);
        assert!(worst <= 1.02, "largest row sum {worst} ({info:?})");
        let (s, i) = (0..p.len())
            .filter(|&i| p.object[i] == 1 && p.normal[i].y > -0.5)
            .map(|i| (sum(i), i))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .unwrap();
        assert!(
            s > 0.97,
            "the box's face patch at {} (normal {}) sees {s} of its hemisphere",
            p.centroid[i],
            p.normal[i]
        );
    }

    /// A far pair whose one ray would decide a large share of a row: a small floor patch
    /// under a 1 m ceiling 5 m up, and at mid-height a half-plane hiding the ceiling's
    /// quarter on one side. The rays from the patches' centroids all pass the edge, so one
    /// ray each counted the ceiling whole (4/3 of the reference).
    #[test]
    fn a_far_pair_partly_hidden_counts_its_visible_part() {
        let quad = |c: [Vec3; 4]| vec![[c[0], c[1], c[2]], [c[0], c[2], c[3]]];
        let v = Vec3::new;
        let floor = quad([
            v(-0.1, 0.0, -0.1),
            v(-0.1, 0.0, 0.1),
            v(0.1, 0.0, 0.1),
            v(0.1, 0.0, -0.1),
        ]);
        let ceiling = quad([
            v(-0.5, 5.0, -0.5),
            v(0.5, 5.0, -0.5),
            v(0.5, 5.0, 0.5),
            v(-0.5, 5.0, 0.5),
        ]);
        let edge = -0.125;
        let blocker = quad([
            v(-3.0, 2.5, -3.0),
            v(edge, 2.5, -3.0),
            v(edge, 2.5, 3.0),
            v(-3.0, 2.5, 3.0),
        ]);
        let objects: Vec<&[[Vec3; 3]]> = vec![&floor, &ceiling, &blocker];
        let p = crate::patch::subdivide(&objects, 1.5);
        let occ = Occluder::new(&p.corners);
        let (f, _) = compute(&p, &occ, &FormFactorParams::default(), &|_| {});
        let view = f.view().unwrap();
        let floor_patches: Vec<usize> = (0..p.len()).filter(|&i| p.object[i] == 0).collect();
        let flux: f64 = floor_patches
            .iter()
            .map(|&i| {
                let (cols, vals) = view.row(i);
                let to_ceiling: f64 = cols
                    .iter()
                    .zip(vals)
                    .filter(|(j, _)| p.object[**j as usize] == 1)
                    .map(|(_, &x)| x as f64)
                    .sum();
                p.area[i] as f64 * to_ceiling
            })
            .sum();
        let got = flux / floor_patches.iter().map(|&i| p.area[i] as f64).sum::<f64>();
        // The reference: from a point x0 of the floor the half-plane's edge hides the
        // ceiling up to 2 · edge − x0, so F(x0 → the visible part), averaged over the floor.
        let k = 40;
        let mut want = 0.0f64;
        for a in 0..k {
            for b in 0..k {
                let x0 = v(
                    -0.1 + 0.2 * (a as f32 + 0.5) / k as f32,
                    0.0,
                    -0.1 + 0.2 * (b as f32 + 0.5) / k as f32,
                );
                let cut = 2.0 * edge - x0.x;
                let seen = [
                    v(cut, 5.0, -0.5),
                    v(0.5, 5.0, -0.5),
                    v(0.5, 5.0, 0.5),
                    v(cut, 5.0, 0.5),
                ];
                want += point_to_polygon(x0, Vec3::Y, &seen) as f64;
            }
        }
        want /= (k * k) as f64;
        assert!(
            (got / want - 1.0).abs() < 0.05,
            "floor to ceiling {got}, the visible part's {want}"
        );
    }
}
