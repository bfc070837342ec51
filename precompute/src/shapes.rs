//! Procedural shapes: triangle meshes in object space.
//!
//! In: a [`Shape`] from the scene file (already validated, so sizes are finite and > 0).
//! Out: triangles `[a, b, c]` in object space, counter-clockwise seen from the side their
//! normal `(b − a) × (c − a)` points to. Closed shapes (box, sphere, bowl, sheet) are
//! watertight triangle soups whose normals point out of the solid, so their signed volume
//! Σ a·(b×c)/6 is positive (negative for an `inward` box, whose faces point into the room).
//! No triangle has zero area: the poles of revolved shapes are triangle fans.
//!
//! Flat faces are coarse (a quad is two triangles); splitting into patches of the requested
//! density is the job of [`crate::patch`].
//!
//! Conventions per shape:
//! - `quad`: the rectangle |x| ≤ size\[0\]/2, |z| ≤ size\[1\]/2 at y = 0, facing +Y.
//! - `box`: |x| ≤ size\[0\]/2, |y| ≤ size\[1\]/2, |z| ≤ size\[2\]/2, centred on the origin.
//! - `sphere`: radius r at the origin, `segments` around Y (default 32), `segments/2` rings.
//! - `bowl`: outer hemisphere of radius R and inner hemisphere of radius R − t, both centred
//!   on (0, R, 0), joined at y = R by a flat annular rim; the lowest outer point is the origin
//!   and the opening faces +Y. `segments` around (default 32), `max(segments/4, 2)` rings per
//!   quarter circle.
//! - `sheet`: the mid-surface starts at the origin along +Z and bends towards +Y with constant
//!   curvature, turning by `curl` radians over its `length`; it spans |x| ≤ width/2. The front
//!   face (normal up at the base) is `thickness/2` above the mid-surface, the back face
//!   `thickness/2` below, and four thin walls close it. `segments` along the length (default 8).

use glam::Vec3;
use std::f32::consts::{FRAC_PI_2, PI, TAU};
use translux_proto::scene::Shape;

/// Default number of segments around a sphere or a bowl.
pub const DEFAULT_ROUND_SEGMENTS: u32 = 32;
/// Default number of segments along a sheet.
pub const DEFAULT_SHEET_SEGMENTS: u32 = 8;

/// How many triangles [`shape_triangles`] makes for `shape`, without making them: a scene's
/// size is checked before its geometry is built (a sphere of 4,096 segments is 16.8 million
/// triangles). Saturates at `u64::MAX`.
pub fn shape_triangle_count(shape: &Shape) -> u64 {
    match *shape {
        Shape::Quad { .. } => 2,
        Shape::Box { .. } => 12,
        Shape::Sphere { segments, .. } => {
            // A fan at each pole and a band of quads between each pair of inner rings.
            let n = u64::from(segments.unwrap_or(DEFAULT_ROUND_SEGMENTS).max(3));
            let rings = (n / 2).max(2);
            (2 * n).saturating_mul(rings - 1)
        }
        Shape::Bowl { segments, .. } => {
            // 2q + 1 bands along the meridian: a fan at each pole, quads between.
            let n = u64::from(segments.unwrap_or(DEFAULT_ROUND_SEGMENTS).max(3));
            let q = (n / 4).max(2);
            (4 * q).saturating_mul(n)
        }
        Shape::Sheet { segments, .. } => {
            // Four faces of one quad per segment, and the two ends.
            let n = u64::from(segments.unwrap_or(DEFAULT_SHEET_SEGMENTS).max(1));
            8 * n + 4
        }
    }
}

/// The triangles of `shape` in object space (see the module docs for each shape's frame).
pub fn shape_triangles(shape: &Shape) -> Vec<[Vec3; 3]> {
    let mut out = Vec::new();
    match *shape {
        Shape::Quad { size } => {
            let (hx, hz) = (0.5 * size[0], 0.5 * size[1]);
            // Seen from +Y, going -x-z → -x+z → +x+z → +x-z is counter-clockwise.
            push_quad(
                &mut out,
                Vec3::new(-hx, 0.0, -hz),
                Vec3::new(-hx, 0.0, hz),
                Vec3::new(hx, 0.0, hz),
                Vec3::new(hx, 0.0, -hz),
            );
        }
        Shape::Box { size, inward } => box_triangles(&mut out, Vec3::from(size) * 0.5, inward),
        Shape::Sphere { radius, segments } => {
            let n = segments.unwrap_or(DEFAULT_ROUND_SEGMENTS).max(3);
            let rings = (n / 2).max(2);
            // Meridian from the north pole (θ = 0) to the south pole (θ = π):
            // ρ = r sin θ, y = r cos θ.
            let profile: Vec<(f32, f32)> = (0..=rings)
                .map(|k| {
                    if k == 0 {
                        (0.0, radius)
                    } else if k == rings {
                        (0.0, -radius)
                    } else {
                        let theta = PI * k as f32 / rings as f32;
                        (radius * theta.sin(), radius * theta.cos())
                    }
                })
                .collect();
            revolve(&mut out, &profile, n);
        }
        Shape::Bowl {
            radius,
            thickness,
            segments,
        } => {
            let n = segments.unwrap_or(DEFAULT_ROUND_SEGMENTS).max(3);
            bowl_triangles(&mut out, radius, thickness, n);
        }
        Shape::Sheet {
            length,
            width,
            thickness,
            curl,
            segments,
        } => {
            let n = segments.unwrap_or(DEFAULT_SHEET_SEGMENTS).max(1);
            sheet_triangles(&mut out, length, width, thickness, curl, n);
        }
    }
    out
}

/// Two triangles for the quad `a b c d`, counter-clockwise seen from its front.
fn push_quad(out: &mut Vec<[Vec3; 3]>, a: Vec3, b: Vec3, c: Vec3, d: Vec3) {
    out.push([a, b, c]);
    out.push([a, c, d]);
}

/// A box of half-extents `h`: six faces of two triangles each.
fn box_triangles(out: &mut Vec<[Vec3; 3]>, h: Vec3, inward: bool) {
    // For a face with outward normal n, pick u, v with u × v = n; the corners
    // c − u − v, c + u − v, c + u + v, c − u + v then run counter-clockwise seen from n,
    // since (2u) × (2u + 2v) = 4 u × v.
    let axes = [Vec3::X, Vec3::Y, Vec3::Z];
    for k in 0..3 {
        for sign in [1.0f32, -1.0] {
            let n = axes[k] * sign;
            let u0 = axes[(k + 1) % 3];
            let v0 = axes[(k + 2) % 3];
            // X × Y = Z cyclically, so u0 × v0 = axes[k]; flip v for the negative face.
            let (u, v) = (u0 * h, v0 * h * sign);
            let c = n * h;
            let (a, b, cc, d) = (c - u - v, c + u - v, c + u + v, c - u + v);
            if inward {
                push_quad(out, a, d, cc, b);
            } else {
                push_quad(out, a, b, cc, d);
            }
        }
    }
}

/// Revolves a meridian `profile` of (ρ, y) points about the Y axis with `n` segments.
///
/// The vertex of profile point k at angle φ is (ρ_k cos φ, y_k, ρ_k sin φ). With ∂φ ∝
/// (−sin φ, 0, cos φ) and the profile tangent ∂s = (dρ, dy), the quad normal ∂φ × ∂s is the
/// tangent rotated by +90° in the (ρ, y) plane: (−dy, dρ). So the surface faces the *left* of
/// the direction of travel along the profile (travelling down the outside of a sphere faces
/// outwards). Points with ρ = 0 lie on the axis and get triangle fans instead of quads.
fn revolve(out: &mut Vec<[Vec3; 3]>, profile: &[(f32, f32)], n: u32) {
    let angles: Vec<(f32, f32)> = (0..n)
        .map(|j| {
            let phi = TAU * j as f32 / n as f32;
            (phi.cos(), phi.sin())
        })
        .collect();
    let vertex = |(rho, y): (f32, f32), j: usize| -> Vec3 {
        let (c, s) = angles[j % angles.len()];
        Vec3::new(rho * c, y, rho * s)
    };
    for w in profile.windows(2) {
        let (p, q) = (w[0], w[1]);
        for j in 0..n as usize {
            // a = (k, j), b = (k, j+1), c = (k+1, j+1), d = (k+1, j).
            let (a, b) = (vertex(p, j), vertex(p, j + 1));
            let (c, d) = (vertex(q, j + 1), vertex(q, j));
            match (p.0 == 0.0, q.0 == 0.0) {
                (true, true) => {}
                (true, false) => out.push([a, c, d]),
                (false, true) => out.push([a, b, c]),
                (false, false) => push_quad(out, a, b, c, d),
            }
        }
    }
}

/// The bowl's closed meridian, traversed with the wall material on the right so that every
/// face points away from the material (see [`revolve`]):
/// inner pole (0, t) → up the inner hemisphere to (R − t, R) → across the rim to (R, R) →
/// down the outer hemisphere to the outer pole (0, 0).
fn bowl_triangles(out: &mut Vec<[Vec3; 3]>, radius: f32, thickness: f32, n: u32) {
    let inner = radius - thickness;
    let q = (n / 4).max(2);
    let mut profile = Vec::with_capacity(2 * q as usize + 2);
    // Inner hemisphere, α from 0 (bottom) to π/2 (rim): ρ = rᵢ sin α, y = R − rᵢ cos α.
    for k in 0..=q {
        let alpha = FRAC_PI_2 * k as f32 / q as f32;
        profile.push(match k {
            0 => (0.0, radius - inner),
            _ if k == q => (inner, radius),
            _ => (inner * alpha.sin(), radius - inner * alpha.cos()),
        });
    }
    // Outer hemisphere, α from π/2 (rim) down to 0 (bottom): ρ = R sin α, y = R − R cos α.
    // Its first point (R, R) follows the last inner point; the segment between is the rim.
    for k in (0..=q).rev() {
        let alpha = FRAC_PI_2 * k as f32 / q as f32;
        profile.push(match k {
            0 => (0.0, 0.0),
            _ if k == q => (radius, radius),
            _ => (radius * alpha.sin(), radius - radius * alpha.cos()),
        });
    }
    revolve(out, &profile, n);
}

/// A curled sheet; see the module docs.
fn sheet_triangles(
    out: &mut Vec<[Vec3; 3]>,
    length: f32,
    width: f32,
    thickness: f32,
    curl: f32,
    n: u32,
) {
    // Mid-curve in the YZ plane with constant curvature κ = curl / L: after arc length s it
    // has turned by θ = κ s, so c(s) = (0, (1 − cos θ)/κ, sin θ / κ), tangent
    // t = (0, sin θ, cos θ) and up-normal m = (0, cos θ, −sin θ) (towards the centre of
    // curvature when curl > 0). A straight sheet (κ → 0) is c(s) = (0, 0, s).
    let frame = |s: f32| -> (Vec3, Vec3) {
        let theta = curl * s / length;
        let (sin, cos) = theta.sin_cos();
        let centre = if curl.abs() < 1e-6 {
            Vec3::new(0.0, 0.0, s)
        } else {
            let r = length / curl;
            Vec3::new(0.0, r * (1.0 - cos), r * sin)
        };
        (centre, Vec3::new(0.0, cos, -sin))
    };
    let hw = 0.5 * width;
    let ht = 0.5 * thickness;
    let x = Vec3::X * hw;
    // For station k: front-left, front-right, back-left, back-right.
    let stations: Vec<[Vec3; 4]> = (0..=n)
        .map(|k| {
            let (c, m) = frame(length * k as f32 / n as f32);
            let (f, b) = (c + m * ht, c - m * ht);
            [f - x, f + x, b - x, b + x]
        })
        .collect();
    for w in stations.windows(2) {
        let (p, q) = (w[0], w[1]);
        // Front: a = left(k), b = left(k+1), c = right(k+1), d = right(k); (b − a) ≈ t ds and
        // (d − a) = width·x̂, so the normal is along t × x̂ = m (up at the base).
        push_quad(out, p[0], q[0], q[1], p[1]);
        // Back: the same corners reversed, normal −m.
        push_quad(out, p[2], p[3], q[3], q[2]);
        // Left wall (normal −x̂) and right wall (normal +x̂).
        push_quad(out, p[0], p[2], q[2], q[0]);
        push_quad(out, p[1], q[1], q[3], p[3]);
    }
    // Base end (normal −t(0)) and tip end (normal +t(L)).
    let (p, q) = (stations[0], stations[n as usize]);
    push_quad(out, p[0], p[1], p[3], p[2]);
    push_quad(out, q[0], q[2], q[3], q[1]);
}

/// Total area of a triangle list.
pub fn total_area(tris: &[[Vec3; 3]]) -> f64 {
    tris.iter().map(|t| f64::from(triangle_area(t))).sum()
}

/// Area of one triangle: |(b − a) × (c − a)| / 2.
pub fn triangle_area(t: &[Vec3; 3]) -> f32 {
    0.5 * (t[1] - t[0]).cross(t[2] - t[0]).length()
}

/// Signed volume enclosed by a closed triangle list, Σ a·(b × c)/6 (divergence theorem):
/// positive when the normals point outwards.
pub fn signed_volume(tris: &[[Vec3; 3]]) -> f64 {
    tris.iter()
        .map(|[a, b, c]| {
            let (a, b, c) = (a.as_dvec3(), b.as_dvec3(), c.as_dvec3());
            a.dot(b.cross(c)) / 6.0
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    #[test]
    fn triangle_counts_match_the_shapes_made() {
        let mut shapes = vec![
            Shape::Quad { size: [1.0, 2.0] },
            Shape::Box {
                size: [1.0, 2.0, 3.0],
                inward: true,
            },
        ];
        for segments in [None, Some(3), Some(4), Some(7), Some(9), Some(64)] {
            shapes.push(Shape::Sphere {
                radius: 1.0,
                segments,
            });
            shapes.push(Shape::Bowl {
                radius: 1.0,
                thickness: 0.1,
                segments,
            });
            shapes.push(Shape::Sheet {
                length: 1.0,
                width: 0.5,
                thickness: 0.01,
                curl: 0.5,
                segments,
            });
        }
        for shape in &shapes {
            assert_eq!(
                shape_triangle_count(shape),
                shape_triangles(shape).len() as u64,
                "{shape:?}"
            );
        }
    }

    fn rel(a: f64, b: f64) -> f64 {
        (a - b).abs() / b.abs()
    }

    fn min_area(tris: &[[Vec3; 3]]) -> f32 {
        tris.iter().map(triangle_area).fold(f32::INFINITY, f32::min)
    }

    /// Every directed edge must be matched by exactly one reversed edge: the mesh is closed
    /// and consistently oriented.
    fn assert_closed(tris: &[[Vec3; 3]]) {
        let key = |v: Vec3| v.to_array().map(|x| (x * 1e5).round() as i64);
        let mut edges: HashMap<([i64; 3], [i64; 3]), i32> = HashMap::new();
        for t in tris {
            for i in 0..3 {
                let (p, q) = (key(t[i]), key(t[(i + 1) % 3]));
                *edges.entry((p, q)).or_default() += 1;
            }
        }
        for (&(p, q), &count) in &edges {
            assert_eq!(count, 1, "edge {p:?}->{q:?} used {count} times");
            assert_eq!(
                edges.get(&(q, p)),
                Some(&1),
                "edge {p:?}->{q:?} has no twin"
            );
        }
    }

    #[test]
    fn quad_area_and_normal() {
        let t = shape_triangles(&Shape::Quad { size: [2.0, 3.0] });
        assert_eq!(t.len(), 2);
        assert!((total_area(&t) - 6.0).abs() < 1e-6);
        for tri in &t {
            let n = (tri[1] - tri[0]).cross(tri[2] - tri[0]).normalize();
            assert!((n - Vec3::Y).length() < 1e-6, "{n}");
            assert!(
                tri.iter()
                    .all(|v| v.y == 0.0 && v.x.abs() <= 1.0 && v.z.abs() <= 1.5)
            );
        }
    }

    #[test]
    fn box_area_volume_and_orientation() {
        let size = [1.0f32, 2.0, 3.0];
        let t = shape_triangles(&Shape::Box {
            size,
            inward: false,
        });
        assert_eq!(t.len(), 12);
        assert!((total_area(&t) - 2.0 * (2.0 + 6.0 + 3.0)).abs() < 1e-5);
        assert!(
            (signed_volume(&t) - 6.0).abs() < 1e-5,
            "{}",
            signed_volume(&t)
        );
        assert_closed(&t);
        // Each face's normal points away from the centre.
        for tri in &t {
            let n = (tri[1] - tri[0]).cross(tri[2] - tri[0]);
            let centroid = (tri[0] + tri[1] + tri[2]) / 3.0;
            assert!(n.dot(centroid) > 0.0);
        }
        let inward = shape_triangles(&Shape::Box { size, inward: true });
        assert!((signed_volume(&inward) + 6.0).abs() < 1e-5);
        assert!((total_area(&inward) - 22.0).abs() < 1e-5);
        assert_closed(&inward);
    }

    #[test]
    fn sphere_area_volume_and_no_degenerate_poles() {
        let r = 0.7f32;
        let t = shape_triangles(&Shape::Sphere {
            radius: r,
            segments: Some(64),
        });
        let area = 4.0 * std::f64::consts::PI * f64::from(r).powi(2);
        let volume = 4.0 / 3.0 * std::f64::consts::PI * f64::from(r).powi(3);
        assert!(
            rel(total_area(&t), area) < 0.01,
            "{} vs {area}",
            total_area(&t)
        );
        assert!(
            rel(signed_volume(&t), volume) < 0.02,
            "{} vs {volume}",
            signed_volume(&t)
        );
        assert!(min_area(&t) > 0.0);
        // 64 around, 32 rings: fans at both poles, quads between.
        assert_eq!(t.len(), 64 * 2 + 64 * 30 * 2);
        assert_closed(&t);
        for tri in &t {
            assert!(tri.iter().all(|v| (v.length() - r).abs() < 1e-5));
        }
        // Default segments and the smallest allowed.
        let d = shape_triangles(&Shape::Sphere {
            radius: 1.0,
            segments: None,
        });
        assert_eq!(d.len(), 32 * 2 + 32 * 14 * 2);
        let small = shape_triangles(&Shape::Sphere {
            radius: 1.0,
            segments: Some(4),
        });
        assert!(signed_volume(&small) > 0.0 && min_area(&small) > 0.0);
        assert_closed(&small);
    }

    #[test]
    fn bowl_area_volume_and_frame() {
        let (r, th) = (0.09f32, 0.008f32);
        let t = shape_triangles(&Shape::Bowl {
            radius: r,
            thickness: th,
            segments: Some(64),
        });
        let (ro, ri) = (f64::from(r), f64::from(r - th));
        let pi = std::f64::consts::PI;
        // Outer hemisphere + inner hemisphere + rim annulus.
        let area = 2.0 * pi * ro * ro + 2.0 * pi * ri * ri + pi * (ro * ro - ri * ri);
        let volume = 2.0 / 3.0 * pi * (ro.powi(3) - ri.powi(3));
        assert!(
            rel(total_area(&t), area) < 0.02,
            "{} vs {area}",
            total_area(&t)
        );
        assert!(
            rel(signed_volume(&t), volume) < 0.02,
            "{} vs {volume}",
            signed_volume(&t)
        );
        assert!(min_area(&t) > 0.0);
        assert_closed(&t);
        let min_y = t
            .iter()
            .flatten()
            .map(|v| v.y)
            .fold(f32::INFINITY, f32::min);
        let max_y = t
            .iter()
            .flatten()
            .map(|v| v.y)
            .fold(f32::NEG_INFINITY, f32::max);
        assert_eq!(min_y, 0.0);
        assert!((max_y - r).abs() < 1e-6);
        // The inner surface faces the cavity: the triangle at the inner bottom faces +Y,
        // the one at the outer bottom faces −Y.
        let lowest_inner = t
            .iter()
            .filter(|tri| tri.iter().any(|v| v.x == 0.0 && v.z == 0.0 && v.y > 0.0))
            .collect::<Vec<_>>();
        assert!(!lowest_inner.is_empty());
        for tri in lowest_inner {
            assert!((tri[1] - tri[0]).cross(tri[2] - tri[0]).y > 0.0);
        }
        for tri in t.iter().filter(|tri| tri.contains(&Vec3::ZERO)) {
            assert!((tri[1] - tri[0]).cross(tri[2] - tri[0]).y < 0.0);
        }
        // The rim faces +Y.
        for tri in t
            .iter()
            .filter(|tri| tri.iter().all(|v| (v.y - r).abs() < 1e-7))
        {
            assert!((tri[1] - tri[0]).cross(tri[2] - tri[0]).y > 0.0);
        }
        let d = shape_triangles(&Shape::Bowl {
            radius: 1.0,
            thickness: 0.1,
            segments: None,
        });
        assert!(signed_volume(&d) > 0.0 && min_area(&d) > 0.0);
        let small = shape_triangles(&Shape::Bowl {
            radius: 1.0,
            thickness: 0.5,
            segments: Some(4),
        });
        assert!(signed_volume(&small) > 0.0 && min_area(&small) > 0.0);
        assert_closed(&small);
    }

    #[test]
    fn sheet_area_volume_and_faces() {
        let (l, w, th) = (0.06f32, 0.03f32, 0.001f32);
        for curl in [0.0f32, 0.8, -0.5, 2.0] {
            let t = shape_triangles(&Shape::Sheet {
                length: l,
                width: w,
                thickness: th,
                curl,
                segments: Some(32),
            });
            let (l, w, th) = (f64::from(l), f64::from(w), f64::from(th));
            // Front and back are offset curves at ∓t/2 from the mid-curve: their lengths
            // L(1 ∓ κ t/2) average to L, so faces + side walls + ends give:
            let area = 2.0 * l * w + 2.0 * l * th + 2.0 * w * th;
            assert!(
                rel(total_area(&t), area) < 0.02,
                "curl {curl}: {}",
                total_area(&t)
            );
            assert!(rel(signed_volume(&t), l * w * th) < 0.02, "curl {curl}");
            assert!(min_area(&t) > 0.0);
            assert_closed(&t);
        }
        // Default 8 segments; the front (first triangle) faces up at the base, the back down;
        // with curl > 0 the tip rises.
        let t = shape_triangles(&Shape::Sheet {
            length: l,
            width: w,
            thickness: th,
            curl: 0.8,
            segments: None,
        });
        assert_eq!(t.len(), 8 * 8 + 4);
        let n_front = (t[0][1] - t[0][0]).cross(t[0][2] - t[0][0]);
        let n_back = (t[2][1] - t[2][0]).cross(t[2][2] - t[2][0]);
        assert!(n_front.y > 0.0 && n_back.y < 0.0);
        let tip = t
            .iter()
            .flatten()
            .map(|v| v.z)
            .fold(f32::NEG_INFINITY, f32::max);
        let top = t
            .iter()
            .flatten()
            .map(|v| v.y)
            .fold(f32::NEG_INFINITY, f32::max);
        // Chord of the arc: (L/κ) sin(curl) ≈ 0.0538 for L = 0.06, curl = 0.8.
        assert!((tip - 0.06 / 0.8 * 0.8f32.sin()).abs() < 1e-3, "{tip}");
        assert!(top > 0.01);
    }
}
