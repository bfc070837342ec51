//! Patches: the triangles radiosity is solved on, and the viewer mesh drawn from them.
//!
//! In: each object's triangles (scene units) and a density (a target patch count or a
//! maximum edge length). Out: [`Patches`] (corners, normals, areas, centroids, object of
//! each patch; objects stay contiguous) and a [`ViewerMesh`] whose triangle `k` is patch
//! `k`, with vertices welded within an object and split where faces meet at a crease.
//!
//! Subdivision is regular: a triangle with longest edge `e` is cut into n² similar triangles,
//! n = ⌈e / h⌉, so neighbours that share an edge and the same n share their new vertices.
//! For a target count the edge length h is found by bisection on Σ n².
//!
//! A vertex's radiance is the area-weighted mean of the patches around it that share its
//! smoothing group ([`vertex_values`]).

use std::collections::HashMap;
use std::ops::Range;
pub use translux_engine::radiosity::vertex_values;

use glam::Vec3;

/// How finely to split.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Density {
    /// About this many patches over the whole scene.
    Target(u64),
    /// No patch edge longer than this (scene units).
    MaxEdge(f32),
}

/// The patches of a scene, structure-of-arrays.
#[derive(Debug, Clone, Default)]
pub struct Patches {
    pub corners: Vec<[Vec3; 3]>,
    /// Unit normal, (b − a) × (c − a) normalised.
    pub normal: Vec<Vec3>,
    pub area: Vec<f32>,
    pub centroid: Vec<Vec3>,
    /// Longest edge of each patch.
    pub size: Vec<f32>,
    /// Index of the object each patch belongs to.
    pub object: Vec<u32>,
    /// Patch range of each object.
    pub object_ranges: Vec<Range<usize>>,
}

impl Patches {
    pub fn len(&self) -> usize {
        self.corners.len()
    }
    pub fn is_empty(&self) -> bool {
        self.corners.is_empty()
    }
}

/// The mesh the viewer draws: triangle `k` is patch `k`.
#[derive(Debug, Clone, Default)]
pub struct ViewerMesh {
    pub positions: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

fn longest_edge(t: &[Vec3; 3]) -> f32 {
    (t[1] - t[0])
        .length()
        .max((t[2] - t[1]).length())
        .max((t[0] - t[2]).length())
}

fn splits(edge: f32, h: f32) -> u64 {
    ((edge / h).ceil() as u64).max(1)
}

/// How many patches splitting every triangle to edge length `h` gives.
fn count_for(edges: &[f32], h: f32) -> u64 {
    edges.iter().fold(0u64, |acc, &e| {
        acc.saturating_add(splits(e, h).saturating_mul(splits(e, h)))
    })
}

/// The edge length h to split at, and the patch count it gives.
///
/// For a target, bisects h (Σ n² falls as h grows) and keeps whichever bracket end lands
/// closer to the target. Never fewer patches than triangles.
pub fn plan(objects: &[&[[Vec3; 3]]], density: Density) -> (f32, u64) {
    let edges: Vec<f32> = objects
        .iter()
        .flat_map(|o| o.iter().map(longest_edge))
        .collect();
    let max_e = edges.iter().cloned().fold(0.0f32, f32::max);
    match density {
        Density::MaxEdge(h) => (h, count_for(&edges, h)),
        Density::Target(target) => {
            let base = edges.len() as u64;
            if target <= base || max_e <= 0.0 {
                return (max_e.max(f32::MIN_POSITIVE), base);
            }
            // lo gives too many patches, hi too few (or exactly the unsplit count).
            let mut hi = max_e;
            let mut lo = max_e / (target as f32).sqrt() / 4.0;
            while count_for(&edges, lo) < target {
                lo *= 0.5;
            }
            for _ in 0..60 {
                let mid = 0.5 * (lo + hi);
                if count_for(&edges, mid) >= target {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            let (clo, chi) = (count_for(&edges, lo), count_for(&edges, hi));
            if clo.abs_diff(target) <= chi.abs_diff(target) {
                (lo, clo)
            } else {
                (hi, chi)
            }
        }
    }
}

/// How many patches [`subdivide`] cuts triangle `t` into at edge length `h` (n², in order,
/// right after those of the triangles before it).
pub fn split_count(t: &[Vec3; 3], h: f32) -> usize {
    let n = splits(longest_edge(t), h) as usize;
    n * n
}

/// Splits every triangle at edge length `h` (from [`plan`]).
pub fn subdivide(objects: &[&[[Vec3; 3]]], h: f32) -> Patches {
    let mut p = Patches::default();
    for (oi, tris) in objects.iter().enumerate() {
        let start = p.corners.len();
        for t in tris.iter() {
            let n = splits(longest_edge(t), h) as usize;
            let (a, e1, e2) = (t[0], (t[1] - t[0]) / n as f32, (t[2] - t[0]) / n as f32);
            let at = |i: usize, j: usize| a + e1 * i as f32 + e2 * j as f32;
            // Grid points P(i, j) = a + i·(b−a)/n + j·(c−a)/n, i + j ≤ n. Each cell gives an
            // "up" triangle and, away from the hypotenuse, a "down" one; both keep the
            // source winding.
            for i in 0..n {
                for j in 0..n - i {
                    push(&mut p, [at(i, j), at(i + 1, j), at(i, j + 1)], oi);
                    if i + j + 2 <= n {
                        push(&mut p, [at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)], oi);
                    }
                }
            }
        }
        p.object_ranges.push(start..p.corners.len());
    }
    p
}

fn push(p: &mut Patches, c: [Vec3; 3], object: usize) {
    let cross = (c[1] - c[0]).cross(c[2] - c[0]);
    let len = cross.length();
    p.normal.push(if len > 0.0 { cross / len } else { Vec3::Y });
    p.area.push(0.5 * len);
    p.centroid.push((c[0] + c[1] + c[2]) / 3.0);
    p.size.push(longest_edge(&c));
    p.object.push(object as u32);
    p.corners.push(c);
}

/// Welds corners by position within eps = 1e-6 × their bounding box's diagonal: a grid of
/// cell size eps, where a corner joins a point within eps in its own or a neighbouring cell
/// (so points that straddle a cell border still weld). Returns the points, each triangle's
/// three point ids, and eps. The one weld of the crate: the viewer mesh (per object) and
/// the sheets' touching patches use it.
pub(crate) fn weld(corners: &[[Vec3; 3]]) -> (Vec<Vec3>, Vec<[u32; 3]>, f32) {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for v in corners.iter().flatten() {
        lo = lo.min(*v);
        hi = hi.max(*v);
    }
    let eps = ((hi - lo).length() * 1e-6).max(1e-12);
    let cell = |v: Vec3| {
        let q = ((v - lo) / eps).floor();
        (q.x as i64, q.y as i64, q.z as i64)
    };
    let mut grid: HashMap<(i64, i64, i64), Vec<u32>> = HashMap::new();
    let mut points: Vec<Vec3> = Vec::new();
    let mut ids = vec![[0u32; 3]; corners.len()];
    for (k, c) in corners.iter().enumerate() {
        for (ci, v) in c.iter().enumerate() {
            let (x, y, z) = cell(*v);
            let mut found = None;
            'search: for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        for &id in grid.get(&(x + dx, y + dy, z + dz)).into_iter().flatten() {
                            if points[id as usize].distance(*v) <= eps {
                                found = Some(id);
                                break 'search;
                            }
                        }
                    }
                }
            }
            ids[k][ci] = found.unwrap_or_else(|| {
                let id = points.len() as u32;
                points.push(*v);
                grid.entry((x, y, z)).or_default().push(id);
                id
            });
        }
    }
    (points, ids, eps)
}

/// Welds corners within each object (`weld`), then splits each welded point into one vertex per
/// smoothing group: faces around a point join the first group whose seed normal is within
/// `crease_deg[object]` of theirs. Vertex normals are area-weighted means of their group.
pub fn viewer_mesh(p: &Patches, crease_deg: &[f32]) -> ViewerMesh {
    let mut mesh = ViewerMesh {
        triangles: vec![[0; 3]; p.len()],
        ..Default::default()
    };
    for (oi, range) in p.object_ranges.iter().enumerate() {
        if range.is_empty() {
            continue;
        }
        let cos_crease = crease_deg
            .get(oi)
            .copied()
            .unwrap_or(40.0)
            .to_radians()
            .cos();
        let (points, corner_point, _) = weld(&p.corners[range.clone()]);
        // Faces around each welded point.
        let mut around: Vec<Vec<(u32, u8)>> = vec![Vec::new(); points.len()];
        for (k, cp) in corner_point.iter().enumerate() {
            for (ci, &pt) in cp.iter().enumerate() {
                around[pt as usize].push((k as u32, ci as u8));
            }
        }
        // Smoothing groups per point; one output vertex per group.
        for (pt, faces) in around.iter().enumerate() {
            let mut groups: Vec<(Vec3, Vec3, u32)> = Vec::new(); // (seed normal, Σ A n, vertex)
            for &(k, ci) in faces {
                let pi = range.start + k as usize;
                let n = p.normal[pi];
                let g = match groups.iter().position(|g| g.0.dot(n) >= cos_crease) {
                    Some(g) => g,
                    None => {
                        let v = mesh.positions.len() as u32;
                        mesh.positions.push(points[pt].to_array());
                        mesh.normals.push([0.0; 3]);
                        groups.push((n, Vec3::ZERO, v));
                        groups.len() - 1
                    }
                };
                groups[g].1 += n * p.area[pi];
                mesh.triangles[pi][ci as usize] = groups[g].2;
            }
            for (seed, sum, v) in groups {
                let n = sum.try_normalize().unwrap_or(seed);
                mesh.normals[v as usize] = n.to_array();
            }
        }
    }
    mesh
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_cube() -> Vec<[Vec3; 3]> {
        // Outward faces of [0,1]³.
        let v = |x: f32, y: f32, z: f32| Vec3::new(x, y, z);
        let quads = [
            [v(0., 0., 0.), v(0., 1., 0.), v(1., 1., 0.), v(1., 0., 0.)], // z = 0, normal −z
            [v(0., 0., 1.), v(1., 0., 1.), v(1., 1., 1.), v(0., 1., 1.)], // z = 1
            [v(0., 0., 0.), v(1., 0., 0.), v(1., 0., 1.), v(0., 0., 1.)], // y = 0
            [v(0., 1., 0.), v(0., 1., 1.), v(1., 1., 1.), v(1., 1., 0.)], // y = 1
            [v(0., 0., 0.), v(0., 0., 1.), v(0., 1., 1.), v(0., 1., 0.)], // x = 0
            [v(1., 0., 0.), v(1., 1., 0.), v(1., 1., 1.), v(1., 0., 1.)], // x = 1
        ];
        quads
            .iter()
            .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
            .collect()
    }

    #[test]
    fn subdivision_keeps_area_winding_and_hits_target() {
        let cube = unit_cube();
        for target in [12u64, 100, 1000, 5000] {
            let (h, count) = plan(&[&cube], Density::Target(target));
            let p = subdivide(&[&cube], h);
            assert_eq!(p.len() as u64, count);
            let rel = (count as f64 - target as f64).abs() / target as f64;
            assert!(rel < 0.35, "target {target}: got {count}");
            let area: f32 = p.area.iter().sum();
            assert!((area - 6.0).abs() < 1e-3, "area {area}");
            // Normals point away from the cube's centre.
            for (c, n) in p.centroid.iter().zip(&p.normal) {
                assert!((*c - Vec3::splat(0.5)).dot(*n) > 0.0);
            }
            assert!(p.size.iter().all(|&s| s <= h * 1.0001));
        }
        let (h, count) = plan(&[&cube], Density::MaxEdge(0.25));
        // Longest edge of each half-face is √2, so n = ⌈√2/0.25⌉ = 6 → 12·36 patches.
        assert_eq!((h, count), (0.25, 12 * 36));
    }

    #[test]
    fn welding_and_creases() {
        let cube = unit_cube();
        let (h, _) = plan(&[&cube], Density::MaxEdge(0.5));
        let p = subdivide(&[&cube], h);
        let m = viewer_mesh(&p, &[40.0]);
        // Sharp cube: every corner of the cube is 3 vertices, edge points 2, face points 1,
        // so the vertex count equals the sum over faces of each face's own grid points.
        // Each face is split with n = 3 along both axes (diagonal √2/0.5 → 3): (n+1)² = 16.
        assert_eq!(m.positions.len(), 6 * 16);
        for (tri, pn) in m.triangles.iter().zip(&p.normal) {
            for &v in tri {
                let n = Vec3::from(m.normals[v as usize]);
                assert!(n.dot(*pn) > 0.999, "crease normal leaked across an edge");
            }
        }
        // Smooth everything: one vertex per welded point: 6·16 − 12 edges·2 shared... a
        // cube surface grid with 3 cells per edge has 6·3²+2 = 56 points.
        let smooth = viewer_mesh(&p, &[180.0]);
        assert_eq!(smooth.positions.len(), 56);
    }

    #[test]
    fn vertex_values_are_area_weighted() {
        let tris = [[0u32, 1, 2], [0, 2, 3]];
        let areas = [1.0f32, 3.0];
        let vals = [[1.0f32, 0.0, 4.0], [3.0, 2.0, 0.0]];
        let v = vertex_values(&tris, &areas, 5, &vals);
        assert_eq!(v[1], [1.0, 0.0, 4.0]);
        assert_eq!(v[3], [3.0, 2.0, 0.0]);
        assert_eq!(v[0], [2.5, 1.5, 1.0]);
        assert_eq!(v[4], [0.0; 3]);
    }
}
