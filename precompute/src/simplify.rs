//! Mesh simplification for scanned meshes (`simplify_to` in a scene file).
//!
//! In: triangle soup (three corners per triangle, as the OBJ loader gives it) and a target
//! triangle count. Out: a triangle soup of about that many triangles with the same shape.
//!
//! Every source triangle becomes at least one patch and F is O(N²), so a 70k-triangle scan
//! alone would need 70k patches; simplifying first lets such a mesh take part in a scene of
//! any patch budget. The edge collapses are meshoptimizer's (the `meshopt` crate): quadric
//! error metric, open borders locked in place so a scan's open bottom keeps its outline;
//! welding the soup into the indexed mesh it needs is meshoptimizer's too.

use glam::Vec3;

/// What [`simplify`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct Simplified {
    pub triangles: Vec<[Vec3; 3]>,
    /// meshoptimizer's own error estimate, relative to the mesh's extent (0.01 = 1%).
    pub relative_error: f32,
}

/// Largest geometric deviation a collapse may introduce, relative to the mesh's extent.
/// Generous on purpose: the target count decides, this only keeps pathological collapses
/// (folding a thin part flat) out.
const ERROR_LIMIT: f32 = 0.05;

/// Simplifies `tris` toward `target` triangles. Meshes at or below the target come back
/// unchanged. meshoptimizer can stop above the target when borders or topology forbid
/// further collapses; the caller sees the count it reached.
pub fn simplify(tris: &[[Vec3; 3]], target: usize) -> Simplified {
    if tris.len() <= target {
        return Simplified {
            triangles: tris.to_vec(),
            relative_error: 0.0,
        };
    }
    // Weld corners with bit-identical positions (the OBJ loader de-indexed them): with no
    // index buffer, remap[k] is the welded index of corner k, i.e. the new index buffer.
    let corners: Vec<[f32; 3]> = tris.iter().flatten().map(|v| v.to_array()).collect();
    let (count, indices) = meshopt::generate_vertex_remap(&corners, None);
    let positions = meshopt::remap_vertex_buffer(&corners, count, &indices);
    let bytes: &[u8] = bytemuck::cast_slice(&positions);
    let adapter = meshopt::VertexDataAdapter::new(bytes, 12, 0)
        .expect("a [f32; 3] slice is a valid vertex stream of stride 12");
    let mut relative_error = 0.0f32;
    let kept = meshopt::simplify(
        &indices,
        &adapter,
        3 * target,
        ERROR_LIMIT,
        meshopt::SimplifyOptions::LockBorder,
        Some(&mut relative_error),
    );
    let triangles = kept
        .chunks_exact(3)
        .map(|c| [0, 1, 2].map(|k| Vec3::from(positions[c[k] as usize])))
        .collect();
    Simplified {
        triangles,
        relative_error,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shapes::shape_triangles;
    use translux_proto::scene::Shape;

    fn area(t: &[[Vec3; 3]]) -> f32 {
        t.iter()
            .map(|[a, b, c]| 0.5 * (*b - *a).cross(*c - *a).length())
            .sum()
    }

    fn signed_volume(t: &[[Vec3; 3]]) -> f32 {
        t.iter().map(|[a, b, c]| a.dot(b.cross(*c)) / 6.0).sum()
    }

    #[test]
    fn a_fine_sphere_keeps_its_shape_at_a_tenth_of_the_triangles() {
        let sphere = shape_triangles(&Shape::Sphere {
            radius: 1.0,
            segments: Some(96),
        });
        let target = sphere.len() / 10;
        let s = simplify(&sphere, target);
        let n = s.triangles.len();
        assert!(n <= target && n >= target * 8 / 10, "{n} for {target}");
        // Area and volume of the unit sphere (4π, 4π/3) survive within 2%; orientation too.
        let (a, v) = (area(&s.triangles), signed_volume(&s.triangles));
        assert!((a / area(&sphere) - 1.0).abs() < 0.02, "area {a}");
        assert!(
            (v / signed_volume(&sphere) - 1.0).abs() < 0.02,
            "volume {v}"
        );
        assert!(s.relative_error < 0.02, "{}", s.relative_error);
        // Every corner still lies on the sphere.
        let worst = s
            .triangles
            .iter()
            .flatten()
            .map(|p| (p.length() - 1.0).abs())
            .fold(0.0, f32::max);
        assert!(worst < 1e-3, "{worst}");
    }

    #[test]
    fn small_meshes_are_untouched_and_borders_stay() {
        let quad = shape_triangles(&Shape::Quad { size: [2.0, 1.0] });
        assert_eq!(simplify(&quad, 100).triangles, quad);
        // An open bowl simplified hard keeps its rim: the border is locked.
        let bowl = shape_triangles(&Shape::Bowl {
            radius: 1.0,
            thickness: 0.1,
            segments: Some(64),
        });
        let s = simplify(&bowl, bowl.len() / 8);
        assert!(s.triangles.len() < bowl.len() / 4);
        let top = |t: &[[Vec3; 3]]| t.iter().flatten().fold(f32::MIN, |m, p| m.max(p.y));
        assert!((top(&s.triangles) - top(&bowl)).abs() < 1e-6);
    }
}
