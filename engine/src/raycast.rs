//! Occlusion queries against the scene's source triangles.
//!
//! In: the scene's triangles (before subdivision: patches lie on them, so the occluding
//! surface is the same and the tree is smaller). Out: [`Occluder::occluded`], an any-hit test
//! for a segment, safe to call from many threads.
//!
//! The tree is `obvhs`'s compressed wide BVH (CWBVH): measured here at 5.7–6.1 M incoherent
//! occlusion rays/s on 2 threads against 1.2 for `bvh` 0.13 and 1.9 for `parry3d`
//! (`../shared/docs/CRATES.md`; re-measure with `cargo run --release --example bvh_compare
//! --features bench-bvh`).

use glam::{Vec3, Vec3A};
use obvhs::{
    BvhBuildParams, cwbvh::CwBvh, cwbvh::builder::build_cwbvh_from_tris, ray::Ray, ray::RayHit,
    triangle::Triangle,
};

/// The triangles as `obvhs` reads them, then two tiny padding triangles just outside their
/// bounds, and the length of the real triangles' bounding-box diagonal: what
/// [`Occluder::new`] builds its tree over (and the GPU backend its own, so both see the same
/// triangles; the padding's hits are ignored).
pub fn padded_triangles(triangles: &[[Vec3; 3]]) -> (Vec<Triangle>, f32) {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for t in triangles {
        for v in t {
            lo = lo.min(*v);
            hi = hi.max(*v);
        }
    }
    if triangles.is_empty() {
        lo = Vec3::ZERO;
        hi = Vec3::ONE;
    }
    let diagonal = (hi - lo).length().max(1e-6);
    let mut tris: Vec<Triangle> = triangles
        .iter()
        .map(|t| Triangle {
            v0: t[0].into(),
            v1: t[1].into(),
            v2: t[2].into(),
        })
        .collect();
    // obvhs 0.4 maps a primitive centroid lying exactly on the scene's upper bound to
    // Morton code 0 (a wrap-around), which makes box-like scenes ~13x slower to trace.
    // Two tiny triangles just outside the bounds move the bounds.
    let pad = 1e-3 * diagonal;
    let tiny = 1e-4 * diagonal;
    for corner in [lo - Vec3::splat(pad), hi + Vec3::splat(pad)] {
        let c: Vec3A = corner.into();
        tris.push(Triangle {
            v0: c,
            v1: c + Vec3A::X * tiny,
            v2: c + Vec3A::Y * tiny,
        });
    }
    (tris, diagonal)
}

/// A BVH over triangles answering "is anything between these two points?".
#[derive(Debug)]
pub struct Occluder {
    bvh: CwBvh,
    /// Triangles in BVH primitive order, so a primitive id indexes them directly.
    tris: Vec<Triangle>,
    /// Whether primitive `k` is one of the two padding triangles (never an occluder).
    padding: Vec<bool>,
    /// Length of the scene's bounding-box diagonal (scene units).
    diagonal: f32,
    /// The object each primitive belongs to (BVH order), when known ([`Occluder::with_owners`]).
    owner: Vec<u32>,
}

impl Occluder {
    /// [`Occluder::new`], also remembering which object each triangle belongs to
    /// (`owners[k]` for `triangles[k]`), for [`Occluder::buried`].
    pub fn with_owners(triangles: &[[Vec3; 3]], owners: &[u32]) -> Self {
        let mut occ = Self::new(triangles);
        if owners.len() == triangles.len() {
            occ.owner = occ
                .bvh
                .primitive_indices
                .iter()
                .map(|&k| owners.get(k as usize).copied().unwrap_or(u32::MAX))
                .collect();
        }
        occ
    }

    /// Builds the tree (in parallel when called inside a rayon pool).
    pub fn new(triangles: &[[Vec3; 3]]) -> Self {
        let (tris, diagonal) = padded_triangles(triangles);
        let n_real = triangles.len();
        let bvh = build_cwbvh_from_tris(
            &tris,
            BvhBuildParams::medium_build(),
            &mut std::time::Duration::default(),
        );
        let ordered: Vec<Triangle> = bvh
            .primitive_indices
            .iter()
            .map(|&k| tris[k as usize])
            .collect();
        let padding = bvh
            .primitive_indices
            .iter()
            .map(|&k| k as usize >= n_real)
            .collect();
        Self {
            bvh,
            tris: ordered,
            padding,
            diagonal,
            owner: Vec::new(),
        }
    }

    /// Length of the scene's bounding-box diagonal.
    pub fn diagonal(&self) -> f32 {
        self.diagonal
    }

    /// True when a triangle crosses the open segment (a, b). The ends are excluded by a
    /// relative margin so that surfaces the ends lie on do not count.
    #[inline]
    pub fn occluded(&self, a: Vec3, b: Vec3) -> bool {
        let d = b - a;
        if d.length_squared() == 0.0 {
            return false;
        }
        let ray = Ray::new(a.into(), d.into(), 1e-4, 1.0 - 1e-4);
        self.occluded_ray(ray)
    }

    /// True when a triangle is hit by the ray from `origin` along unit `dir` within
    /// `(tmin, tmax)` (scene units).
    #[inline]
    pub fn occluded_dir(&self, origin: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> bool {
        self.occluded_ray(Ray::new(
            origin.into(),
            positive_zeros(dir).into(),
            tmin,
            tmax,
        ))
    }

    /// Whether the face at `point` with normal `normal`, on object `owner`, is pressed
    /// against another object's surface (a block's base on the floor, or the floor under
    /// it): looking back at the face from `step` in front of it, a triangle of another
    /// object within twice the step is seen from its back, so the space in front of the
    /// face is behind another surface, outside the room. A free face sees only its own
    /// front looking back; the object's own triangles never count (a zero-thickness
    /// two-sided sheet has its back face there). `step` must be well above the float
    /// precision of the scene's coordinates (obvhs misses flat nodes from closer than about
    /// 1e-5 × the scene's size); [`Occluder::contact_step`] is a safe choice. Without
    /// owners ([`Occluder::new`]) every triangle counts.
    pub fn buried(&self, point: Vec3, normal: Vec3, step: f32, owner: u32) -> bool {
        let origin = point + normal * step;
        let dir = positive_zeros(-normal);
        let ray = Ray::new(origin.into(), dir.into(), 0.0, 2.0 * step);
        let d: Vec3A = dir.into();
        !self.bvh.ray_traverse_miss(ray, |r, id| {
            let t = &self.tris[id];
            let facing = (t.v1 - t.v0).cross(t.v2 - t.v0).dot(d);
            let own = self.owner.get(id).is_some_and(|&o| o == owner);
            if self.padding[id] || own || facing <= 0.0 {
                f32::INFINITY
            } else {
                intersect_closed(t, r)
            }
        })
    }

    /// The step for [`Occluder::buried`]: 2e-4 of the scene's diagonal (0.2 mm in a 1 m
    /// room): surfaces closer than that to a face's front count as touching it.
    pub fn contact_step(&self) -> f32 {
        2e-4 * self.diagonal
    }

    /// The nearest triangle hit by the ray from `origin` along unit `dir` within
    /// `(tmin, tmax)`: its index in the triangles the occluder was built from, and the
    /// distance. Used by the random walks of a simulated S, against one object's mesh.
    pub fn closest_hit(
        &self,
        origin: Vec3,
        dir: Vec3,
        tmin: f32,
        tmax: f32,
    ) -> Option<(usize, f32)> {
        let ray = Ray::new(origin.into(), positive_zeros(dir).into(), tmin, tmax);
        let mut hit = RayHit::none();
        let found = self.bvh.ray_traverse(ray, &mut hit, |r, id| {
            if self.padding[id] {
                f32::INFINITY
            } else {
                intersect_closed(&self.tris[id], r)
            }
        });
        if !found || hit.primitive_id == obvhs::ray::INVALID_ID {
            return None;
        }
        let k = self.bvh.primitive_indices[hit.primitive_id as usize] as usize;
        Some((k, hit.t))
    }

    #[inline]
    fn occluded_ray(&self, ray: Ray) -> bool {
        !self.bvh.ray_traverse_miss(ray, |r, id| {
            if self.padding[id] {
                f32::INFINITY
            } else {
                intersect_closed(&self.tris[id], r)
            }
        })
    }
}

/// `v` with every −0.0 made +0.0. obvhs's traversal misses triangles for directions
/// with negative-zero components (−Y written as `-Vec3::Y` is (−0, −1, −0)): measured here,
/// a ray straight down onto a floor from 0.01 above it reported no hit. Adding +0.0 turns
/// −0.0 into +0.0 and leaves every other value as it is.
#[inline]
fn positive_zeros(v: Vec3) -> Vec3 {
    v + Vec3::ZERO
}

/// Möller–Trumbore with a small tolerance on the barycentrics, so a ray through the edge
/// two triangles share hits at least one of them. `obvhs`'s own test is exact, and rays
/// that cross a seam exactly (common between regular patch grids) slip through it.
#[inline]
fn intersect_closed(t: &Triangle, ray: &Ray) -> f32 {
    const EPS: f32 = 1e-5;
    let e1 = t.v1 - t.v0;
    let e2 = t.v2 - t.v0;
    let p = ray.direction.cross(e2);
    let det = e1.dot(p);
    if det.abs() < 1e-20 {
        return f32::INFINITY;
    }
    let inv = 1.0 / det;
    let s = ray.origin - t.v0;
    let u = s.dot(p) * inv;
    if !(-EPS..=1.0 + EPS).contains(&u) {
        return f32::INFINITY;
    }
    let q = s.cross(e1);
    let v = ray.direction.dot(q) * inv;
    if v < -EPS || u + v > 1.0 + EPS {
        return f32::INFINITY;
    }
    let d = e2.dot(q) * inv;
    if d > ray.tmin && d < ray.tmax {
        d
    } else {
        f32::INFINITY
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quad(y: f32, half: f32) -> [[Vec3; 3]; 2] {
        let a = Vec3::new(-half, y, -half);
        let b = Vec3::new(half, y, -half);
        let c = Vec3::new(half, y, half);
        let d = Vec3::new(-half, y, half);
        [[a, b, c], [a, c, d]]
    }

    #[test]
    fn plate_blocks_segments_through_it_only() {
        let tris: Vec<_> = quad(0.5, 0.25).into_iter().collect();
        let occ = Occluder::new(&tris);
        assert!(occ.occluded(Vec3::new(0.0, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0)));
        assert!(occ.occluded(Vec3::new(0.1, 0.0, -0.1), Vec3::new(-0.1, 1.0, 0.1)));
        // Beside the plate.
        assert!(!occ.occluded(Vec3::new(0.5, 0.0, 0.0), Vec3::new(0.5, 1.0, 0.0)));
        // Stops short of the plate.
        assert!(!occ.occluded(Vec3::new(0.0, 0.0, 0.0), Vec3::new(0.0, 0.4, 0.0)));
        // Ends on the plate itself: the end margin keeps the plate from counting.
        assert!(!occ.occluded(Vec3::new(0.0, 0.0, 0.0), Vec3::new(0.0, 0.5, 0.0)));
        // Direction form.
        assert!(occ.occluded_dir(Vec3::ZERO, Vec3::Y, 1e-4, 10.0));
        assert!(!occ.occluded_dir(Vec3::ZERO, -Vec3::Y, 1e-4, 10.0));
    }

    #[test]
    fn many_random_segments_agree_with_brute_force() {
        // A small random soup, every segment checked against a plain loop over triangles.
        let mut s = 12345u64;
        let mut rnd = || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f32 / (1u64 << 53) as f32
        };
        let mut tris = Vec::new();
        for _ in 0..200 {
            let c = Vec3::new(rnd(), rnd(), rnd());
            let e = 0.1;
            tris.push([
                c,
                c + Vec3::new(rnd() * e, rnd() * e, rnd() * e),
                c + Vec3::new(rnd() * e, rnd() * e, rnd() * e),
            ]);
        }
        let occ = Occluder::new(&tris);
        let plain: Vec<Triangle> = tris
            .iter()
            .map(|t| Triangle {
                v0: t[0].into(),
                v1: t[1].into(),
                v2: t[2].into(),
            })
            .collect();
        let mut hits = 0;
        for _ in 0..2000 {
            let a = Vec3::new(rnd(), rnd(), rnd());
            let b = Vec3::new(rnd(), rnd(), rnd());
            let ray = Ray::new(a.into(), (b - a).into(), 1e-4, 1.0 - 1e-4);
            let brute = plain
                .iter()
                .any(|t| intersect_closed(t, &ray) < f32::INFINITY);
            assert_eq!(occ.occluded(a, b), brute);
            hits += brute as u32;
        }
        assert!(
            hits > 100 && hits < 1900,
            "test scene too trivial: {hits} hits"
        );
    }
}
