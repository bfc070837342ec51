//! Heterogeneous translucent objects: media laid out by a pattern, combined per optical path
//! by the paper's eq. 9 (§5, Fig. 7).
//!
//! In: a [`Material::Heterogeneous`] — K ≤ 4 profiles S_k and a [`Pattern`] saying which
//! medium is where — the object's patches, and for every stored pair (i, j) the lengths r_k
//! its optical path travels in each medium (stage 1, [`crate::voxel`], with the
//! [`MediumField`] built here). Out: S of the object.
//!
//! ```text
//!   S(r₁, …, r_K) = ( Σ_k S_k(0) r_k / r ) · Π_k S_k(r_k) / S_k(0),     r = Σ_k r_k
//! ```
//!
//! the paper's eq. 9 (written there for K = 2) generalised to K media: an albedo-like
//! prefactor mixing the media's S_k(0) by the share of the path in each, times each medium's
//! attenuation over its own stretch. A medium the path does not enter contributes the factor
//! S_k(0)/S_k(0) = 1, so a path entirely in medium m gives exactly S_m(r). Channel by channel;
//! a medium with S_k(0) = 0 in a channel passes nothing there (its factor is 0 once r_k > 0).
//!
//! Eq. 9 is a heuristic ("not physically accurate", the paper says) and it is not idempotent:
//! S(r₁)S(r₂)/S(0) = S(r₁ + r₂) only for an exponential S. For a dipole, a path split half and
//! half between two copies of the *same* medium would scatter less than the homogeneous path
//! of the same length. So media with equal profiles are merged first ([`merge_media`](translux_engine::hetero::merge_media)): an
//! object whose materials are all the same profile is exactly the homogeneous object.
//!
//! Where the media are.
//! - Checkerboard: analytic, in the object's frame (see [`Checker`]). Straight paths (convex
//!   objects) are split exactly at the cell planes they cross ([`Checker::segment_lengths`]);
//!   voxel paths take the medium of each voxel's centre (so cells should be a few voxels
//!   wide; the summary reports the voxel size).
//! - By OBJ material (`usemtl`): every patch carries the medium of its source face; a point
//!   inside the object is in the medium of the nearest patch *measured through the inside*
//!   (a discrete Voronoi diagram of the patches' entry voxels, grown by a multi-source
//!   Dijkstra over the interior voxels). Through-the-inside rather than Euclidean nearest so a
//!   thin wall between two lobes does not lend one lobe's medium to the other. These objects
//!   always take the voxel route, convex or not.
//!
//! Quadrature (per column i, as in [`translux_engine::subsurface`]):
//! - the self term S_ii uses the profile of the patch's own medium (the medium just under its
//!   centroid, [`patch_media`]) with the polar integration of the homogeneous case;
//! - a pair whose path stays in one (merged) medium m gets exactly the homogeneous quadrature
//!   with S_m (near coplanar: polar; near across an edge: point samples; far: A_i S_m(r));
//! - a mixed pair: far, S_ji = A_i · S(r₁, …, r_K); near, m² × m² point samples x ∈ A_i, y ∈ A_j
//!   at distance d = |x − y| + (r − |c_i − c_j|), each with the pair's media shares held fixed,
//!   r_k(d) = d · r_k / r, S_ji = A_i · mean S(r₁(d), …, r_K(d)). (The polar integration needs
//!   W(ρ) = ∫ S 2πr dr of one radial profile; a mixed pair's profile changes with the pair.)
//!
//! Energy: Σ_j A_j S_ji ≤ A_i per column and channel, enforced and reported exactly as for a
//! homogeneous object. Eq. 9's prefactor is a convex mix of the S_k(0) and, for falling
//! profiles, each factor S_k(r_k)/S_k(0) ≤ 1, so a mixed pair never scatters more than the
//! stronger medium would at the shorter of its stretches.

use glam::{DVec3, Mat3, Vec3};
use translux_proto::scene::{Material, Pattern, Transform};

pub use translux_engine::hetero::{MEDIA, MediaLen};

/// Scene → object frame of a pattern: q = Rᵀ (p − t), undoing the object transform's
/// rotation R and translation t but not its scale (pattern lengths stay in scene units).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PatternFrame {
    /// Rᵀ (= R⁻¹, R being a rotation).
    pub rot_t: Mat3,
    pub translate: Vec3,
}

impl Default for PatternFrame {
    fn default() -> Self {
        Self {
            rot_t: Mat3::IDENTITY,
            translate: Vec3::ZERO,
        }
    }
}

impl PatternFrame {
    /// The frame of an object placed by `transform` (identity without one).
    pub fn of(transform: Option<&Transform>) -> Self {
        let Some(t) = transform else {
            return Self::default();
        };
        let unscaled = Transform {
            scale: None,
            ..t.clone()
        };
        let (rot, translate) = crate::scene::transform_parts(Some(&unscaled));
        Self {
            rot_t: rot.transpose(),
            translate,
        }
    }

    /// q = Rᵀ (p − t), in f64.
    pub fn to_local(&self, p: Vec3) -> DVec3 {
        (self.rot_t * (p - self.translate)).as_dvec3()
    }
}

/// A 3-D checkerboard of K media: scene point p is in medium
/// (⌊q_x⌋ + ⌊q_y⌋ + ⌊q_z⌋) mod K with q = (Rᵀ(p − t) − origin) / cell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Checker {
    pub frame: PatternFrame,
    pub cell: f64,
    pub origin: DVec3,
    pub count: u32,
}

impl Checker {
    /// Position in cell units: integer coordinates are the cell planes.
    fn cells(&self, p: Vec3) -> DVec3 {
        (self.frame.to_local(p) - self.origin) / self.cell
    }

    fn medium_of_cells(&self, q: DVec3) -> u32 {
        let s = q.x.floor() + q.y.floor() + q.z.floor();
        (s as i64).rem_euclid(i64::from(self.count.max(1))) as u32
    }

    /// The medium at scene point `p`.
    pub fn medium_at(&self, p: Vec3) -> u32 {
        self.medium_of_cells(self.cells(p))
    }

    /// Lengths the straight segment a → b travels in each medium, split exactly where it
    /// crosses a cell plane: with q(t) = q_a + t (q_b − q_a), the crossings are the t ∈ (0, 1)
    /// where a coordinate of q(t) is an integer; each piece between consecutive crossings lies
    /// in one cell, whose medium is that of its midpoint, and has length Δt · |b − a|.
    /// Σ_k r_k = |b − a| (up to rounding). A segment crossing more than
    /// [`MAX_CROSSINGS`] planes (cells far smaller than the path) is split evenly instead:
    /// over many cells each medium's share tends to 1/K.
    pub fn segment_lengths(&self, a: Vec3, b: Vec3) -> MediaLen {
        let (qa, qb) = (self.cells(a), self.cells(b));
        let d = qb - qa;
        let length = f64::from(a.distance(b));
        if d.abs().element_sum() > MAX_CROSSINGS as f64 {
            let k = self.count.clamp(1, MEDIA as u32) as usize;
            let mut out = [0.0f32; MEDIA];
            out[..k].fill((length / k as f64) as f32);
            return out;
        }
        let mut ts = vec![0.0f64, 1.0];
        for k in 0..3 {
            if d[k] == 0.0 {
                continue;
            }
            let (lo, hi) = (qa[k].min(qb[k]), qa[k].max(qb[k]));
            let mut m = lo.floor() + 1.0;
            while m < hi {
                ts.push((m - qa[k]) / d[k]);
                m += 1.0;
            }
        }
        ts.sort_unstable_by(f64::total_cmp);
        let mut out = [0.0f64; MEDIA];
        for w in ts.windows(2) {
            let dt = w[1] - w[0];
            if dt <= 0.0 {
                continue;
            }
            let mid = qa + d * (0.5 * (w[0] + w[1]));
            out[self.medium_of_cells(mid) as usize] += dt * length;
        }
        out.map(|x| x as f32)
    }
}

/// Most cell planes [`Checker::segment_lengths`] splits a segment at.
pub const MAX_CROSSINGS: usize = 4096;

/// Where the media of a heterogeneous object are, as stage 1 needs it.
#[derive(Debug, Clone, Copy)]
pub enum MediumField<'a> {
    /// An analytic checkerboard.
    Checker(Checker),
    /// The medium of each patch (the object's local indices); the inside takes the medium of
    /// the nearest patch through the interior.
    PerPatch(&'a [u32]),
}

impl MediumField<'_> {
    /// Per-medium lengths of a straight path between patches i and j (centroids `ci`, `cj`,
    /// optical length `r`): exact cell crossings for a checkerboard (rescaled so they sum to
    /// `r`), half in each patch's medium for per-patch media.
    pub fn straight(&self, i: usize, j: usize, ci: Vec3, cj: Vec3, r: f32) -> MediaLen {
        match self {
            MediumField::Checker(c) => {
                let l = c.segment_lengths(ci, cj);
                let sum: f32 = l.iter().sum();
                if sum > 0.0 {
                    l.map(|x| x * r / sum)
                } else {
                    let mut out = [0.0; MEDIA];
                    out[c.medium_at(ci) as usize] = r;
                    out
                }
            }
            MediumField::PerPatch(m) => {
                let mut out = [0.0; MEDIA];
                out[m[i] as usize] += 0.5 * r;
                out[m[j] as usize] += 0.5 * r;
                out
            }
        }
    }
}

/// The field of a heterogeneous material for stage 1, or `None` for any other material.
/// `media` are the object's patch media ([`patch_media`], local indices).
pub fn medium_field<'a>(
    material: &Material,
    frame: PatternFrame,
    media: &'a [u32],
) -> Option<MediumField<'a>> {
    match material {
        Material::Heterogeneous {
            materials,
            pattern: Pattern::Checkerboard { cell, origin },
            ..
        } => Some(MediumField::Checker(Checker {
            frame,
            cell: f64::from(*cell),
            origin: Vec3::from(*origin).as_dvec3(),
            count: materials.len() as u32,
        })),
        Material::Heterogeneous {
            pattern: Pattern::ByObjMaterial { .. },
            ..
        } => Some(MediumField::PerPatch(media)),
        _ => None,
    }
}

/// The medium of each patch of one object: for a checkerboard, the medium just under the
/// centroid (c − 10⁻⁴·cell·n, so a face lying on a cell plane takes the cell behind it); by
/// OBJ material, `face_media[k]` (the medium of patch k's source face). 0 for any other
/// material, or when `face_media` is missing.
pub fn patch_media(
    material: &Material,
    frame: PatternFrame,
    centroids: &[Vec3],
    normals: &[Vec3],
    face_media: Option<&[u32]>,
) -> Vec<u32> {
    match material {
        Material::Heterogeneous {
            materials,
            pattern: Pattern::Checkerboard { cell, origin },
            ..
        } => {
            let c = Checker {
                frame,
                cell: f64::from(*cell),
                origin: Vec3::from(*origin).as_dvec3(),
                count: materials.len() as u32,
            };
            centroids
                .iter()
                .zip(normals)
                .map(|(&p, &n)| c.medium_at(p - n * (1e-4 * *cell)))
                .collect()
        }
        Material::Heterogeneous {
            pattern: Pattern::ByObjMaterial { .. },
            ..
        } => match face_media {
            Some(f) if f.len() == centroids.len() => f.to_vec(),
            _ => vec![0; centroids.len()],
        },
        _ => vec![0; centroids.len()],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use translux_engine::hetero::{assemble, eq9, merge_media};
    use translux_engine::profile::ProfileEval;
    use translux_engine::subsurface::{ObjectPatches, ObjectS, SubsurfaceParams, Tabulated};
    use translux_proto::csr::CsrView;
    use translux_proto::scene::ExpTerm;
    use translux_proto::scene::Profile;

    fn checker(cell: f32, origin: [f32; 3], count: u32) -> Checker {
        Checker {
            frame: PatternFrame::default(),
            cell: f64::from(cell),
            origin: Vec3::from(origin).as_dvec3(),
            count,
        }
    }

    #[test]
    fn checker_media_alternate_and_follow_the_object_frame() {
        let c = checker(1.0, [0.0; 3], 2);
        assert_eq!(c.medium_at(Vec3::new(0.5, 0.5, 0.5)), 0);
        assert_eq!(c.medium_at(Vec3::new(1.5, 0.5, 0.5)), 1);
        assert_eq!(c.medium_at(Vec3::new(1.5, 1.5, 0.5)), 0);
        assert_eq!(c.medium_at(Vec3::new(-0.5, 0.5, 0.5)), 1);
        let c3 = checker(1.0, [0.0; 3], 3);
        assert_eq!(c3.medium_at(Vec3::new(2.5, 0.5, 0.5)), 2);
        assert_eq!(c3.medium_at(Vec3::new(-0.5, -0.5, 0.5)), 1); // −2 mod 3
        // An object turned 90° about Y and moved: its frame turns and moves the pattern.
        let t = Transform {
            translate: [10.0, 0.0, 0.0],
            rotate_deg: [0.0, 90.0, 0.0],
            scale: Some(translux_proto::scene::Scale::Uniform(3.0)),
        };
        let frame = PatternFrame::of(Some(&t));
        // The object-space point (1.5, 0.5, 0.5) (unscaled) sits at t + R q.
        let (rot, _) = crate::scene::transform_parts(Some(&Transform {
            scale: None,
            ..t.clone()
        }));
        let p = Vec3::new(10.0, 0.0, 0.0) + rot * Vec3::new(1.5, 0.5, 0.5);
        let q = frame.to_local(p);
        assert!((q - DVec3::new(1.5, 0.5, 0.5)).length() < 1e-5, "{q}");
        let turned = Checker { frame, ..c };
        assert_eq!(turned.medium_at(p), 1);
    }

    #[test]
    fn straight_lengths_split_at_the_cell_plane_and_sum_to_the_length() {
        // Cells of 0.1 with the origin shifted to x = 0.03: the plane x = 0.13 separates
        // medium 0 (x ∈ [0.03, 0.13)) from medium 1 (x ∈ [0.13, 0.23)), for y, z in [0, 0.1).
        let c = checker(0.1, [0.03, 0.0, 0.0], 2);
        let (a, b) = (Vec3::new(0.05, 0.02, 0.05), Vec3::new(0.20, 0.08, 0.05));
        let l = c.segment_lengths(a, b);
        // By hand: the segment reaches x = 0.13 at t = (0.13 − 0.05)/0.15 = 8/15, where
        // y = 0.02 + 0.06·8/15 = 0.052 (still in the y cell [0, 0.1)). Length |b − a| =
        // √(0.15² + 0.06²) = 0.161555; medium 0 gets 8/15 of it, medium 1 the other 7/15.
        let total = (0.15f32 * 0.15 + 0.06 * 0.06).sqrt();
        assert!((l[0] - total * 8.0 / 15.0).abs() < 1e-6, "{l:?}");
        assert!((l[1] - total * 7.0 / 15.0).abs() < 1e-6, "{l:?}");
        assert_eq!((l[2], l[3]), (0.0, 0.0));
        assert!((l.iter().sum::<f32>() - total).abs() < 1e-6);
        // Reversed: the same split.
        let r = c.segment_lengths(b, a);
        assert!((r[0] - l[0]).abs() < 1e-6 && (r[1] - l[1]).abs() < 1e-6);
        // Crossing three planes diagonally (x, y and z each once, at different t).
        let d = checker(1.0, [0.0; 3], 2);
        let (a, b) = (Vec3::new(0.2, 0.4, 0.6), Vec3::new(1.7, 1.3, 1.1));
        let l = d.segment_lengths(a, b);
        let len = a.distance(b);
        // Planes x = 1 at t = 0.8/1.5, y = 1 at t = 0.6/0.9, z = 1 at t = 0.4/0.5: the
        // media along the way are 0 (cell 000), 1 (100), 0 (110), 1 (111).
        let t = [0.0, 0.8 / 1.5, 0.6 / 0.9, 0.4 / 0.5, 1.0];
        let want0 = (t[1] - t[0]) + (t[3] - t[2]);
        let want1 = (t[2] - t[1]) + (t[4] - t[3]);
        assert!((l[0] - want0 * len).abs() < 1e-5, "{l:?}");
        assert!((l[1] - want1 * len).abs() < 1e-5, "{l:?}");
        // Entirely inside one cell: all of it in that medium.
        let l = d.segment_lengths(Vec3::new(1.1, 0.1, 0.1), Vec3::new(1.9, 0.9, 0.2));
        assert_eq!(l[0], 0.0);
        assert!((l[1] - Vec3::new(0.8, 0.8, 0.1).length()).abs() < 1e-6);
    }

    fn exp_profile(a: f32, b: f32) -> Profile {
        Profile::Exponentials {
            terms: vec![ExpTerm {
                a: [a; 3],
                b: [b, 1.5 * b, 2.0 * b],
            }],
        }
    }

    #[test]
    fn eq9_reduces_to_one_profile_and_is_exact_for_exponentials() {
        let p1 = ProfileEval::new(&exp_profile(0.2, 1.0), 1.0).unwrap();
        let p2 = ProfileEval::new(
            &Profile::Dipole {
                preset: Some("ketchup".into()),
                sigma_a: None,
                sigma_s_prime: None,
                eta: None,
                scale: None,
            },
            1.0,
        )
        .unwrap();
        let s0 = [p1.eval(0.0), p2.eval(0.0)];
        let s = |k: usize, r: f32| if k == 0 { p1.eval(r) } else { p2.eval(r) };
        // A path entirely in medium 2 is profile 2, at every length.
        for r in [0.1f32, 0.7, 2.0] {
            let v = eq9(&[0.0, r], &s0, s);
            let want = p2.eval(r);
            for c in 0..3 {
                assert!(
                    (v[c] - want[c]).abs() <= 1e-6 * want[c],
                    "{r}: {v:?} vs {want:?}"
                );
            }
        }
        // Two media with the same exponential profile: S(r₁)S(r₂)/S(0) = S(r₁ + r₂).
        let s_same = |_: usize, r: f32| p1.eval(r);
        let s0_same = [p1.eval(0.0); 2];
        for (r1, r2) in [(0.3f32, 0.9f32), (1.2, 0.05), (0.5, 0.5)] {
            let v = eq9(&[r1, r2], &s0_same, s_same);
            let want = p1.eval(r1 + r2);
            for c in 0..3 {
                assert!(
                    (v[c] - want[c]).abs() <= 1e-5 * want[c],
                    "{v:?} vs {want:?}"
                );
            }
        }
        // For a dipole it is not: half and half scatters differently from the whole path
        // (here 18 % more in red). This is why equal media are merged before eq. 9.
        let s_dip = |_: usize, r: f32| p2.eval(r);
        let v = eq9(&[1.0, 1.0], &[p2.eval(0.0); 2], s_dip);
        let whole = p2.eval(2.0);
        assert!(
            (v[0] - whole[0]).abs() > 0.1 * whole[0],
            "{v:?} vs {whole:?}"
        );
        // A mixed path: prefactor and attenuation by hand.
        let v = eq9(&[0.4, 0.6], &s0, s);
        let (a, b) = (p1.eval(0.4), p2.eval(0.6));
        for c in 0..3 {
            let pre = s0[0][c] * 0.4 + s0[1][c] * 0.6;
            let want = pre * a[c] / s0[0][c] * b[c] / s0[1][c];
            assert!((v[c] - want).abs() <= 1e-6 * want, "{v:?}");
        }
        assert_eq!(eq9(&[0.0, 0.0], &s0, s), [0.0; 3]);
    }

    /// A flat square slab of side `side` (mm scene) split into 2·k² right triangles, facing
    /// +y, with brute-force Euclidean distances within `r_max` and their per-medium lengths
    /// under `checker`.
    struct Slab {
        corners: Vec<[Vec3; 3]>,
        centroid: Vec<Vec3>,
        normal: Vec<Vec3>,
        area: Vec<f32>,
        size: Vec<f32>,
        row_ptr: Vec<u64>,
        col: Vec<u32>,
        dist: Vec<f32>,
        len: Vec<MediaLen>,
        media: Vec<u32>,
    }

    impl Slab {
        fn new(side: f32, k: usize, r_max: f32, checker: &Checker) -> Slab {
            let h = side / k as f32;
            let mut corners = Vec::new();
            for a in 0..k {
                for b in 0..k {
                    let o = Vec3::new(a as f32 * h - side / 2.0, 0.0, b as f32 * h - side / 2.0);
                    let (p0, p1, p2, p3) = (
                        o,
                        o + Vec3::Z * h,
                        o + Vec3::new(h, 0.0, h),
                        o + Vec3::X * h,
                    );
                    corners.push([p0, p1, p2]);
                    corners.push([p0, p2, p3]);
                }
            }
            let g = translux_engine::smatrix::PatchGeometry::from_corners(corners);
            let (mut row_ptr, mut col, mut dist, mut len) =
                (vec![0u64], Vec::new(), Vec::new(), Vec::new());
            let n = g.centroid.len();
            for i in 0..n {
                for j in 0..n {
                    let r = g.centroid[i].distance(g.centroid[j]);
                    if i != j && r < r_max {
                        col.push(j as u32);
                        dist.push(r);
                        len.push(MediumField::Checker(*checker).straight(
                            i,
                            j,
                            g.centroid[i],
                            g.centroid[j],
                            r,
                        ));
                    }
                }
                row_ptr.push(col.len() as u64);
            }
            let mat = Material::Heterogeneous {
                materials: vec![exp_profile(0.1, 1.0); checker.count as usize],
                pattern: Pattern::Checkerboard {
                    cell: checker.cell as f32,
                    origin: checker.origin.as_vec3().to_array(),
                },
                specular: None,
            };
            let media = patch_media(&mat, checker.frame, &g.centroid, &g.normal, None);
            Slab {
                corners: g.corners,
                centroid: g.centroid,
                normal: g.normal,
                area: g.area,
                size: g.size,
                row_ptr,
                col,
                dist,
                len,
                media,
            }
        }
        fn patches(&self) -> ObjectPatches<'_> {
            ObjectPatches {
                corners: &self.corners,
                centroid: &self.centroid,
                normal: &self.normal,
                area: &self.area,
                size: &self.size,
            }
        }
        fn distances(&self) -> CsrView<'_, f32> {
            let n = self.area.len();
            CsrView::new_checked(n, n, &self.row_ptr, &self.col, &self.dist).unwrap()
        }
        fn hetero(&self, profiles: &[Profile], r_max: f32) -> ObjectS {
            let (map, distinct) = merge_media(profiles);
            let tabs: Vec<Tabulated> = distinct
                .iter()
                .map(|&d| {
                    Tabulated::new(&ProfileEval::new(&profiles[d], 1.0).unwrap(), r_max, 2048)
                })
                .collect();
            assemble(
                self.patches(),
                self.distances(),
                &self.len,
                &self.media,
                &map,
                &tabs,
                &SubsurfaceParams::default(),
            )
        }
        fn homogeneous(&self, profile: &Profile, r_max: f32) -> ObjectS {
            let tab = Tabulated::new(&ProfileEval::new(profile, 1.0).unwrap(), r_max, 2048);
            translux_engine::subsurface::assemble(
                self.patches(),
                self.distances(),
                &tab,
                &SubsurfaceParams::default(),
            )
        }
    }

    fn marble() -> Profile {
        Profile::Dipole {
            preset: Some("marble".into()),
            sigma_a: None,
            sigma_s_prime: None,
            eta: None,
            scale: Some(4.0),
        }
    }

    fn assert_same(a: &ObjectS, b: &ObjectS, rel: f32) {
        assert_eq!(a.rows.len(), b.rows.len());
        for (ra, rb) in a.rows.iter().zip(&b.rows) {
            assert_eq!(ra.len(), rb.len());
            for ((ia, va), (ib, vb)) in ra.iter().zip(rb) {
                assert_eq!(ia, ib);
                for c in 0..3 {
                    assert!(
                        (va[c] - vb[c]).abs() <= rel * vb[c].abs(),
                        "{va:?} vs {vb:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn one_medium_everywhere_is_the_homogeneous_object() {
        // A 24 mm slab of 1.5 mm patches under a checkerboard of 4 mm cells: plenty of pairs
        // cross cell planes.
        let r_max = 8.0;
        let fine = checker(4.0, [0.3, 0.0, 0.7], 2);
        let slab = Slab::new(24.0, 16, r_max, &fine);
        let mixed = slab.len.iter().filter(|l| l[0] > 0.0 && l[1] > 0.0).count();
        assert!(mixed > 1000, "{mixed}");
        // Both media the same profile: exactly the homogeneous S (the media merge; eq. 9 on
        // its own would not give this for a dipole).
        let one = slab.homogeneous(&marble(), r_max);
        let same = slab.hetero(&[marble(), marble()], r_max);
        assert_same(&same, &one, 1e-5);
        // And not by accident: two different media give a different S.
        let orange = crate::builtin::checker_orange();
        let two = slab.hetero(&[marble(), orange.clone()], r_max);
        let differs = two
            .rows
            .iter()
            .zip(&one.rows)
            .flat_map(|(a, b)| a.iter().zip(b))
            .filter(|(a, b)| (a.1[2] - b.1[2]).abs() > 1e-3 * b.1[2].abs())
            .count();
        assert!(differs > 100, "{differs}");

        // The whole slab inside one cell of medium 1: profile 2 everywhere, exactly.
        let coarse = checker(1000.0, [500.0, -500.0, -500.0], 2);
        let inside = Slab::new(24.0, 16, r_max, &coarse);
        assert!(inside.media.iter().all(|&m| m == 1));
        assert!(inside.len.iter().all(|l| l[0] == 0.0 && l[1] > 0.0));
        let s = inside.hetero(&[marble(), orange.clone()], r_max);
        let want = inside.homogeneous(&orange, r_max);
        assert_same(&s, &want, 1e-6);
    }

    #[test]
    fn columns_never_scatter_more_than_they_receive() {
        let r_max = 8.0;
        let fine = checker(3.0, [0.3, 0.0, 0.7], 2);
        let slab = Slab::new(20.0, 14, r_max, &fine);
        let column_sums = |s: &ObjectS| {
            let mut total = vec![[0.0f64; 3]; slab.area.len()];
            for (j, row) in s.rows.iter().enumerate() {
                for &(i, v) in row {
                    for c in 0..3 {
                        total[i as usize][c] +=
                            f64::from(slab.area[j] * v[c] / slab.area[i as usize]);
                    }
                }
            }
            total
        };
        // Two physical media: within the bound by the quadrature itself.
        let s = slab.hetero(&[marble(), crate::builtin::checker_orange()], r_max);
        assert_eq!(s.report.scaled_columns, 0, "{:?}", s.report);
        assert!(s.report.max_column < 1.0, "{:?}", s.report);
        for t in column_sums(&s) {
            assert!(t.iter().all(|&x| x <= 1.0 + 1e-5), "{t:?}");
        }
        // A medium that re-emits 1.5× what it receives (and a slowly falling one next to it):
        // the offending columns are scaled to the bound and reported.
        let hot = Profile::Exponentials {
            terms: vec![ExpTerm {
                a: [0.2387; 3], // 2π a / b² = 1.5
                b: [1.0; 3],
            }],
        };
        let s = slab.hetero(&[hot, exp_profile(0.05, 0.5)], r_max);
        assert!(
            s.report.scaled_columns > 0 && s.report.max_column > 1.1,
            "{:?}",
            s.report
        );
        for t in column_sums(&s) {
            assert!(t.iter().all(|&x| x <= 1.0 + 1e-5), "{t:?}");
        }
    }

    #[test]
    fn equal_profiles_merge() {
        let a = exp_profile(0.2, 1.0);
        let b = exp_profile(0.1, 2.0);
        let (map, distinct) = merge_media(&[a.clone(), b.clone(), a.clone()]);
        assert_eq!(map, [0, 1, 0, 0]);
        assert_eq!(distinct, vec![0, 1]);
        let (map, distinct) = merge_media(&[b.clone(), b]);
        assert_eq!(map, [0; 4]);
        assert_eq!(distinct, vec![0]);
    }
}
