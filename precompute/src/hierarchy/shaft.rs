//! Shafts between two boxes (Haines and Wallace's shaft culling, 1994): the convex hull of
//! two axis-aligned boxes as at most 18 half-spaces, and conservative tests of a box or a
//! triangle against it. A two-sided link whose shaft holds no other surface sees its source
//! whole from every point of its receiver — no sample ray could tell that.
//!
//! Written here rather than taken from a crate: the BVH crates answer rays, not "does
//! anything cross this convex volume", and the test runs over our own cluster tree.

use glam::Vec3;

/// The hull of two boxes: points x with n · x ≤ d for every plane (n, d).
#[derive(Debug, Clone)]
pub struct Shaft {
    planes: Vec<(Vec3, f32)>,
}

impl Shaft {
    /// The shaft between the boxes `[a_lo, a_hi]` and `[b_lo, b_hi]`.
    pub fn between(a: (Vec3, Vec3), b: (Vec3, Vec3)) -> Shaft {
        let (lo, hi) = (a.0.min(b.0), a.1.max(b.1));
        let mut planes = Vec::with_capacity(18);
        for i in 0..3 {
            let e = Vec3::AXES[i];
            planes.push((-e, -lo[i]));
            planes.push((e, hi[i]));
        }
        // Where one box reaches past the other on one side of axis i and the other reaches
        // past it on one side of axis j, the hull has a face through the two boxes' edges
        // at those sides, parallel to the third axis.
        for (i, j) in [(0, 1), (0, 2), (1, 2)] {
            for si in [-1.0f32, 1.0] {
                for sj in [-1.0f32, 1.0] {
                    let side = |bx: (Vec3, Vec3), s: f32, k: usize| {
                        if s < 0.0 { bx.0[k] } else { bx.1[k] }
                    };
                    let (ai, aj, bi, bj) = (
                        side(a, si, i),
                        side(a, sj, j),
                        side(b, si, i),
                        side(b, sj, j),
                    );
                    let a_past_i = (ai - bi) * si > 0.0;
                    let b_past_i = (bi - ai) * si > 0.0;
                    let a_past_j = (aj - bj) * sj > 0.0;
                    let b_past_j = (bj - aj) * sj > 0.0;
                    if !((a_past_i && b_past_j) || (b_past_i && a_past_j)) {
                        continue;
                    }
                    // The line through (ai, aj) and (bi, bj) in the (i, j) plane; its normal
                    // pointing towards the corner (si, sj).
                    let (ti, tj) = (bi - ai, bj - aj);
                    let (mut ni, mut nj) = (tj, -ti);
                    if ni * si + nj * sj < 0.0 {
                        (ni, nj) = (-ni, -nj);
                    }
                    let len = (ni * ni + nj * nj).sqrt();
                    if len <= 0.0 {
                        continue;
                    }
                    let mut n = Vec3::ZERO;
                    n[i] = ni / len;
                    n[j] = nj / len;
                    planes.push((n, n[i] * ai + n[j] * aj));
                }
            }
        }
        Shaft { planes }
    }

    /// Whether the box `[lo, hi]` lies wholly outside the shaft or on its boundary (beyond
    /// one plane, or within `eps` of it).
    pub fn box_outside(&self, lo: Vec3, hi: Vec3, eps: f32) -> bool {
        let (c, h) = ((lo + hi) * 0.5, (hi - lo) * 0.5);
        self.planes
            .iter()
            .any(|&(n, d)| n.dot(c) - n.abs().dot(h) >= d - eps)
    }

    /// Whether the triangle lies wholly outside the shaft or on its boundary.
    pub fn triangle_outside(&self, t: &[Vec3; 3], eps: f32) -> bool {
        self.planes
            .iter()
            .any(|&(n, d)| t.iter().all(|v| n.dot(*v) >= d - eps))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shaft_holds_both_boxes_and_what_lies_between_them_only() {
        // Two unit boxes along a diagonal: (0,0,0)-(1,1,1) and (3,2,0)-(4,3,1).
        let a = (Vec3::ZERO, Vec3::ONE);
        let b = (Vec3::new(3.0, 2.0, 0.0), Vec3::new(4.0, 3.0, 1.0));
        let s = Shaft::between(a, b);
        // Both boxes are inside (touching their own faces only).
        for bx in [a, b] {
            assert!(!s.box_outside(bx.0, bx.1, 1e-6));
        }
        // A small box on the segment between the centres is inside.
        let mid = Vec3::new(2.0, 1.5, 0.5);
        assert!(!s.box_outside(mid - 0.1, mid + 0.1, 1e-6));
        // The union box's empty corners are outside: near (0, 3) and (4, 0) in x, y.
        for p in [Vec3::new(0.3, 2.7, 0.5), Vec3::new(3.7, 0.3, 0.5)] {
            assert!(s.box_outside(p - 0.1, p + 0.1, 1e-6), "{p}");
        }
        // A triangle in the plane z = 0 (the shaft's floor) is on the boundary: outside.
        let floor = [
            Vec3::new(1.0, 0.5, 0.0),
            Vec3::new(3.0, 2.5, 0.0),
            Vec3::new(2.0, 1.0, 0.0),
        ];
        assert!(s.triangle_outside(&floor, 1e-6));
        // Lifted into the shaft it blocks.
        let lifted = floor.map(|v| v + Vec3::Z * 0.5);
        assert!(!s.triangle_outside(&lifted, 1e-6));
    }
}
