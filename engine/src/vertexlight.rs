//! Direct light at the viewer's vertices.
//!
//! In: a bundle's viewer mesh (vertex positions and normals, triangle k = patch k), the
//! patches' albedo ρ and the direct irradiance E at their centroids, the lights and the
//! shadow-ray BVH. Out: a correction per vertex that replaces the patch-averaged direct
//! term of an opaque diffuse surface with the direct term at the vertex itself.
//!
//! A vertex's radiance is the area-weighted mean of B/π over the patches around it
//! ([`crate::radiosity::vertex_radiance`]). On an opaque diffuse patch
//! B = Bₑ + ρ E + ρ F B, so that mean smears the direct term ρE over a patch: shadow edges
//! become stair steps and a light's hot spot is flattened. For a vertex whose patches are
//! all opaque and diffuse, this module swaps the mean of ρE for ρ̄ E(v), with E(v) the
//! shadowed irradiance at the vertex with its own (smooth) normal:
//!
//! ```text
//!     L(v) = mean(B/π) + (ρ̄ E(v) − mean(ρ E)) / π
//! ```
//!
//! Patches pressed against another object (the floor under a block) are left out of both
//! means and of where the vertex is sampled, where the vertex has other patches: a vertex
//! on the block's outline shows the floor outside it, not half the dark floor beneath.
//!
//! The indirect part ρ F B stays interpolated (it varies slowly), but to the vertex rather
//! than as a plain mean: on a mesh's edges the patches lie on one side of the vertex, and
//! a linear fit over its two rings ([`Reconstruction`]) takes the gradient into account.
//!
//! Translucent objects and sheets keep the plain patch mean of everything: their S already
//! smooths the direct light over a mean free path (an exact E at a vertex would be the
//! wrong answer there), except in the components that take them as opaque at ρ̄
//! (`direct`, `interreflection_only`). Environment lights' direct term stays per patch
//! (their visibility is stored per patch only) and is interpolated with the indirect
//! part; a relight without point, spot or directional lights goes the same way, E(v) = 0.

use glam::Vec3;
use translux_proto::api::Components;
use translux_proto::bundle::Bundle;
use translux_proto::scene::Material;

use crate::linalg::Rgb;
use crate::raycast::Occluder;
use rayon::prelude::*;

/// The direct light of a relight's lamps at the vertices that take it at the vertex (the
/// part of `relight`'s vertex terms that depends on the lights and on which objects count
/// as opaque alone), kept by [`crate::scene::DirectCache`].
#[derive(Debug)]
pub(crate) struct VertexLit {
    pub(crate) which: Vec<usize>,
    /// E (lights other than environments) at the vertices `which`.
    pub(crate) at_vertex: Vec<Rgb>,
    /// E of those lights at the patches, where it differs from the plan's E (environment
    /// lights are in that one and stay per patch).
    pub(crate) at_patch: Option<Vec<Rgb>>,
}

/// Where direct light is evaluated for each viewer vertex.
#[derive(Debug)]
pub struct VertexSamples {
    /// The vertex moved 1% of the way toward the area-weighted centroid of its triangles:
    /// on the surface it belongs to, off the edges it shares with walls and other objects
    /// (a room's corner vertex lies on the next wall too).
    pub point: Vec<Vec3>,
    /// The viewer's vertex normal (unit), or its triangles' area-weighted normal where the
    /// mesh has none.
    pub normal: Vec<Vec3>,
    /// Total area of the vertex's patches (0 for a vertex no patch uses).
    pub area: Vec<f32>,
    /// Per patch: whether it counts in its vertices' means ([`Occluder::buried`] at its
    /// centroid is false, or all of some vertex's patches are buried).
    pub counts: Vec<bool>,
    /// Per vertex, the weights that take the indirect term B − ρE from the patches around
    /// it to the vertex itself ([`Reconstruction`]).
    pub rest: Reconstruction,
}

/// Linear reconstruction of a smooth per-patch field at the vertices, as sparse rows:
/// vertex `q`'s value is Σ `weight[i]` × value[`patch[i]`] over `offsets[q]..offsets[q+1]`.
///
/// The area-weighted mean of the patches around a vertex is the field at the vertex only
/// where the patches surround it. On a mesh's edge (a wall meeting the floor, a block's
/// vertical edge) they all lie on one side, and the mean lags a third of a patch behind
/// the gradient: next to the short block of the Cornell box, whose face the tall one lights
/// unevenly, the indirect light at its edges was 13–40% off. Here the field is fitted as
/// c + g·u (u in the vertex's tangent plane) by least squares over the patches of the
/// vertex's two rings that face the same way, weighted by area, and c is the value: exact
/// for linear fields, so also one-sided. Where the patches surround the vertex, where some
/// of them do not count (pressed against another object), or where the fit is ill-posed (a
/// ring that is a line, too few patches), the row is the plain area-weighted mean. How far the answer may
/// run past its patches is limited in [`VertexMeans::new`].
#[derive(Debug, Clone, Default)]
pub struct Reconstruction {
    pub offsets: Vec<u32>,
    pub patch: Vec<u32>,
    pub weight: Vec<f32>,
}

/// Patches of the second ring count this much less per area than those touching the
/// vertex: they steady the gradient without pulling the value toward their own.
const SECOND_RING: f64 = 0.25;
/// Least cosine between a patch's normal and the vertex's for the patch to join the fit
/// (about 37°): across a sharper fold the field is another surface's.
const SAME_SIDE: f32 = 0.8;

impl Reconstruction {
    /// The rows for a mesh of `positions`, `triangles` (triangle k = patch k, of `normals`
    /// and `areas`) with vertex normals `vertex_normal`; patches with `counts[k]` false
    /// take no part.
    pub fn new(
        positions: &[[f32; 3]],
        triangles: &[[u32; 3]],
        normals: &[[f32; 3]],
        areas: &[f32],
        vertex_normal: &[Vec3],
        counts: &[bool],
    ) -> Reconstruction {
        let v = positions.len();
        // Vertex → the patches that use it, as one flat list.
        let mut start = vec![0u32; v + 1];
        for t in triangles {
            for &q in t {
                start[q as usize + 1] += 1;
            }
        }
        for q in 0..v {
            start[q + 1] += start[q];
        }
        let mut fill = start.clone();
        let mut around = vec![0u32; start[v] as usize];
        for (k, t) in triangles.iter().enumerate() {
            for &q in t {
                around[fill[q as usize] as usize] = k as u32;
                fill[q as usize] += 1;
            }
        }
        let ring = |q: usize| &around[start[q] as usize..start[q + 1] as usize];
        let centroid = |k: usize| {
            let t = triangles[k];
            t.iter()
                .map(|&q| Vec3::from(positions[q as usize]))
                .sum::<Vec3>()
                / 3.0
        };
        let rows: Vec<Vec<(u32, f32)>> = (0..v)
            .into_par_iter()
            .map(|q| {
                let all = ring(q);
                let first: Vec<u32> = all
                    .iter()
                    .copied()
                    .filter(|&k| counts[k as usize])
                    .collect();
                let mean = || {
                    let total: f64 = first.iter().map(|&k| areas[k as usize] as f64).sum();
                    first
                        .iter()
                        .map(|&k| (k, (areas[k as usize] as f64 / total) as f32))
                        .collect::<Vec<_>>()
                };
                let n = vertex_normal[q];
                if first.is_empty() || n.length_squared() == 0.0 {
                    return Vec::new();
                }
                // A vertex its patches surround (each edge from it shared by two of them)
                // keeps the mean: there it is already the field at the vertex to first
                // order, and a wider fit would only blur it. So does one beside patches
                // that are pressed against another object (the floor round a block): the
                // patches across that outline are partly covered, and a gradient taken
                // from them runs the wrong way.
                if first.len() < all.len() {
                    return mean();
                }
                let surrounded = all.iter().all(|&k| {
                    triangles[k as usize]
                        .iter()
                        .filter(|&&r| r as usize != q)
                        .all(|&r| {
                            all.iter()
                                .filter(|&&j| triangles[j as usize].contains(&r))
                                .count()
                                == 2
                        })
                });
                if surrounded {
                    return mean();
                }
                // The two rings, each patch once, with its weight in the fit.
                let mut fit: Vec<(u32, f64)> = Vec::with_capacity(4 * first.len());
                for &k in &first {
                    fit.push((k, areas[k as usize] as f64));
                }
                for &k in &first {
                    for &r in &triangles[k as usize] {
                        for &j in ring(r as usize) {
                            if counts[j as usize] && !fit.iter().any(|&(m, _)| m == j) {
                                fit.push((j, SECOND_RING * areas[j as usize] as f64));
                            }
                        }
                    }
                }
                fit.retain(|&(k, _)| Vec3::from(normals[k as usize]).dot(n) >= SAME_SIDE);
                if fit.len() < 4 {
                    return mean();
                }
                let (t1, t2) = n.any_orthonormal_pair();
                let p = Vec3::from(positions[q]);
                let phi: Vec<[f64; 3]> = fit
                    .iter()
                    .map(|&(k, _)| {
                        let u = centroid(k as usize) - p;
                        [1.0, u.dot(t1) as f64, u.dot(t2) as f64]
                    })
                    .collect();
                let mut m = [[0.0f64; 3]; 3];
                for (f, &(_, w)) in phi.iter().zip(&fit) {
                    for a in 0..3 {
                        for b in 0..3 {
                            m[a][b] += w * f[a] * f[b];
                        }
                    }
                }
                // Ill-posed when the centroids lie (nearly) on a line: compare the
                // determinant with what a spread of the same size would give.
                let scale = m[1][1] + m[2][2];
                let det = det3(&m);
                if det.is_nan() || det <= 1e-6 * m[0][0] * scale * scale / 4.0 {
                    return mean();
                }
                // Row 0 of M⁻¹ (M is symmetric): the cofactors of column 0 over det.
                let r0 = [
                    (m[1][1] * m[2][2] - m[1][2] * m[2][1]) / det,
                    (m[1][2] * m[2][0] - m[1][0] * m[2][2]) / det,
                    (m[1][0] * m[2][1] - m[1][1] * m[2][0]) / det,
                ];
                fit.iter()
                    .zip(&phi)
                    .map(|(&(k, w), f)| {
                        (k, (w * (r0[0] * f[0] + r0[1] * f[1] + r0[2] * f[2])) as f32)
                    })
                    .collect()
            })
            .collect();
        let mut out = Reconstruction {
            offsets: Vec::with_capacity(v + 1),
            ..Default::default()
        };
        out.offsets.push(0);
        for row in rows {
            for (k, w) in row {
                out.patch.push(k);
                out.weight.push(w);
            }
            out.offsets.push(out.patch.len() as u32);
        }
        out
    }

    /// The entries of vertex `q`'s row.
    pub fn row(&self, q: usize) -> impl Iterator<Item = (usize, f32)> + '_ {
        let (a, b) = (self.offsets[q] as usize, self.offsets[q + 1] as usize);
        self.patch[a..b]
            .iter()
            .zip(&self.weight[a..b])
            .map(|(&k, &w)| (k as usize, w))
    }
}

fn det3(m: &[[f64; 3]; 3]) -> f64 {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

impl VertexSamples {
    /// The samples of `b`'s vertices; `occ` (the scene's shadow-ray BVH) finds the patches
    /// pressed against other objects.
    pub fn new(b: &Bundle, occ: &Occluder) -> VertexSamples {
        let pos = b.vertex_positions();
        let normals = b.vertex_normals();
        let tris = b.triangle_vertices();
        let v = pos.len();
        let step = occ.contact_step();
        let buried: Vec<bool> = b
            .patch_corners()
            .par_iter()
            .zip(b.patch_normals().par_iter())
            .map(|(c, &n)| {
                let centroid = (Vec3::from(c[0]) + Vec3::from(c[1]) + Vec3::from(c[2])) / 3.0;
                occ.buried(centroid, Vec3::from(n), step, u32::MAX)
            })
            .collect();
        // A vertex all of whose patches are buried keeps them all.
        let mut free = vec![false; v];
        for (t, &d) in tris.iter().zip(&buried) {
            if !d {
                for &k in t {
                    free[k as usize] = true;
                }
            }
        }
        let counts: Vec<bool> = tris
            .iter()
            .zip(&buried)
            .map(|(t, &d)| !d || t.iter().all(|&k| !free[k as usize]))
            .collect();
        let mut centre = vec![Vec3::ZERO; v];
        let mut face_n = vec![Vec3::ZERO; v];
        let mut area = vec![0.0f32; v];
        for (t, _) in tris.iter().zip(&counts).filter(|(_, c)| **c) {
            let [a, bb, c] = t.map(|k| Vec3::from(pos[k as usize]));
            let cross = (bb - a).cross(c - a);
            let w = 0.5 * cross.length();
            let centroid = (a + bb + c) / 3.0;
            for &k in t {
                let k = k as usize;
                centre[k] += w * centroid;
                face_n[k] += cross;
                area[k] += w;
            }
        }
        let point = (0..v)
            .map(|k| {
                let p = Vec3::from(pos[k]);
                if area[k] > 0.0 {
                    p + 0.01 * (centre[k] / area[k] - p)
                } else {
                    p
                }
            })
            .collect();
        let normal: Vec<Vec3> = (0..v)
            .map(|k| {
                let n = normals.get(k).map(|&n| Vec3::from(n)).unwrap_or(Vec3::ZERO);
                if n.length_squared() > 0.0 && n.is_finite() {
                    n.normalize()
                } else {
                    face_n[k].normalize_or_zero()
                }
            })
            .collect();
        let rest = Reconstruction::new(
            pos,
            tris,
            b.patch_normals(),
            b.patch_areas(),
            &normal,
            &counts,
        );
        VertexSamples {
            point,
            normal,
            area,
            counts,
            rest,
        }
    }

    /// The vertices whose patches all belong to objects with `opaque[k]` set (one flag
    /// per object of the manifest; see [`opaque_objects`]).
    pub fn opaque_vertices(&self, b: &Bundle, opaque: &[bool]) -> Vec<usize> {
        let m = b.manifest();
        let n = b.triangle_vertices().len();
        let mut flat = vec![false; n];
        for (o, &op) in m.objects.iter().zip(opaque) {
            if op {
                let (first, count) = (o.first_patch as usize, o.patch_count as usize);
                for d in &mut flat[first.min(n)..(first + count).min(n)] {
                    *d = true;
                }
            }
        }
        let mut ok = vec![true; self.point.len()];
        for (t, &d) in b.triangle_vertices().iter().zip(&flat) {
            if !d {
                for &k in t {
                    ok[k as usize] = false;
                }
            }
        }
        (0..self.point.len())
            .filter(|&k| ok[k] && self.area[k] > 0.0)
            .collect()
    }

    /// The sample points and normals of the vertices `which`, for
    /// [`crate::radiosity::direct_irradiance`].
    pub fn geometry(&self, which: &[usize]) -> (Vec<Vec3>, Vec<Vec3>) {
        (
            which.iter().map(|&k| self.point[k]).collect(),
            which.iter().map(|&k| self.normal[k]).collect(),
        )
    }
}

/// The albedo a picture multiplies the per-pixel direct irradiance by for an object of
/// `material` (`direct_at: pixel`): a diffuse object's ρ; `None` for the others, which keep
/// their direct light at the vertices (a translucent object's is smoothed by S).
pub fn per_pixel_direct(material: &Material) -> Option<Rgb> {
    match material {
        Material::Diffuse { albedo, .. } => Some(*albedo),
        _ => None,
    }
}

/// Whether `components` take every object as opaque (`direct`, `interreflection_only`).
pub fn all_opaque(components: Components) -> bool {
    matches!(
        components,
        Components::Direct | Components::InterreflectionOnly
    )
}

/// Which objects reflect the direct light as an opaque surface, B = … + ρ̄E, under
/// `materials` (one per object, the request's overrides applied) and `components`: diffuse
/// objects always; every object in the `direct` and `interreflection_only` components,
/// which take translucent objects as opaque at ρ̄ (emitters have ρ̄ = 0 and are unchanged).
pub fn opaque_objects(materials: &[&Material], components: Components) -> Vec<bool> {
    let all = all_opaque(components);
    materials
        .iter()
        .map(|m| all || matches!(m, Material::Diffuse { .. }))
        .collect()
}

/// A relight's answer per patch: the radiosity B, the direct irradiance E of the lights
/// taken at the vertices, and the albedo ρ it was solved with.
#[derive(Debug, Clone, Copy)]
pub struct PatchTerms<'a> {
    pub radiosity: &'a [Rgb],
    pub irradiance: &'a [Rgb],
    pub albedo: &'a [Rgb],
}

/// Per vertex, over the patches that count ([`VertexSamples::counts`]): the indirect term
/// B − ρE reconstructed at the vertex ([`Reconstruction`]), Σ a ρ and Σ a, made once per
/// relight; [`VertexMeans::set`] then writes the vertices' values for any E at the vertices.
#[derive(Debug, Clone)]
pub struct VertexMeans {
    rest: Vec<[f64; 3]>,
    rho: Vec<[f64; 3]>,
    area: Vec<f64>,
}

/// How far past the values of its patches a vertex's reconstructed indirect term may run,
/// as a share of their spread: enough for a vertex a third of a patch beyond the outermost
/// centroid of a linear field (a mesh's edge), not for a fit that a kink in the field
/// (a shadow's edge in the indirect light) throws far off.
pub(crate) const OVERSHOOT: f64 = 0.5;

impl VertexMeans {
    pub fn new(b: &Bundle, samples: &VertexSamples, patches: PatchTerms<'_>) -> VertexMeans {
        let v = b.vertex_positions().len();
        let mut m = VertexMeans {
            rest: vec![[0.0; 3]; v],
            rho: vec![[0.0; 3]; v],
            area: vec![0.0; v],
        };
        let rest_of = |k: usize| -> [f64; 3] {
            let (bb, e, r) = (
                patches.radiosity[k],
                patches.irradiance[k],
                patches.albedo[k],
            );
            std::array::from_fn(|c| bb[c] as f64 - r[c] as f64 * e[c] as f64)
        };
        for (k, t) in b.triangle_vertices().iter().enumerate() {
            if !samples.counts[k] {
                continue;
            }
            let a = b.patch_areas()[k] as f64;
            let r = patches.albedo[k];
            for &q in t {
                let q = q as usize;
                for (sum, &rc) in m.rho[q].iter_mut().zip(&r) {
                    *sum += a * rc as f64;
                }
                m.area[q] += a;
            }
        }
        m.rest.par_iter_mut().enumerate().for_each(|(q, out)| {
            let mut lo = [f64::INFINITY; 3];
            let mut hi = [f64::NEG_INFINITY; 3];
            let mut sum = [0.0f64; 3];
            for (k, w) in samples.rest.row(q) {
                let r = rest_of(k);
                for c in 0..3 {
                    sum[c] += w as f64 * r[c];
                    lo[c] = lo[c].min(r[c]);
                    hi[c] = hi[c].max(r[c]);
                }
            }
            for c in 0..3 {
                if lo[c] <= hi[c] {
                    let slack = OVERSHOOT * (hi[c] - lo[c]);
                    out[c] = sum[c].clamp(lo[c] - slack, hi[c] + slack);
                }
            }
        });
        m
    }

    /// Sets `radiance` (per vertex, W·m⁻²·sr⁻¹) at the vertices `which` to
    /// (B − ρE)(v)/π + ρ̄ E(v)/π; `vertex_e[i]` is E at vertex `which[i]`.
    pub fn set(&self, which: &[usize], vertex_e: &[Rgb], radiance: &mut [Rgb]) {
        let inv_pi = 1.0 / std::f64::consts::PI;
        for (&q, ev) in which.iter().zip(vertex_e) {
            if self.area[q] <= 0.0 {
                continue;
            }
            for c in 0..3 {
                let value =
                    (self.rest[q][c] + self.rho[q][c] * ev[c] as f64 / self.area[q]) * inv_pi;
                // B ≥ ρE on every patch, so only rounding can make it negative.
                radiance[q][c] = value.max(0.0) as f32;
            }
        }
    }
}

/// The whole step on its own: for the point, spot and directional `lights`, sets the
/// vertices of opaque surfaces (`opaque`, one flag per object: [`opaque_objects`]) in
/// `radiance` (the patch means of B/π) to their own direct term plus the interpolated rest.
/// `patches.irradiance` must be E of those lights alone. What [`crate::relight`] does,
/// for callers that solve through the library.
pub fn apply(
    b: &Bundle,
    occ: &Occluder,
    lights: &[translux_proto::light::Light],
    opaque: &[bool],
    patches: PatchTerms<'_>,
    radiance: &mut [Rgb],
) -> Result<(), crate::radiosity::LightError> {
    let samples = VertexSamples::new(b, occ);
    let which = samples.opaque_vertices(b, opaque);
    let (point, normal) = samples.geometry(&which);
    let at_vertex = crate::radiosity::direct_irradiance(
        crate::radiosity::PatchGeometry {
            centroid: &point,
            normal: &normal,
        },
        occ,
        lights,
        b.manifest().unit_mm,
    )?;
    VertexMeans::new(b, &samples, patches).set(&which, &at_vertex, radiance);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The unit square in z = 0 as an n × n grid of quads, each split in two (diagonals
    /// alternating): positions, triangles, normals, areas.
    type Mesh = (Vec<[f32; 3]>, Vec<[u32; 3]>, Vec<[f32; 3]>, Vec<f32>);
    fn square(n: usize) -> Mesh {
        let h = 1.0 / n as f32;
        let pos: Vec<[f32; 3]> = (0..=n)
            .flat_map(|j| (0..=n).map(move |i| [i as f32 * h, j as f32 * h, 0.0]))
            .collect();
        let at = |i: usize, j: usize| (j * (n + 1) + i) as u32;
        let mut tris = Vec::new();
        for j in 0..n {
            for i in 0..n {
                let (a, b, c, d) = (at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1));
                if (i + j) % 2 == 0 {
                    tris.extend([[a, b, c], [a, c, d]]);
                } else {
                    tris.extend([[a, b, d], [b, c, d]]);
                }
            }
        }
        let normals = vec![[0.0, 0.0, 1.0]; tris.len()];
        let areas = vec![0.5 * h * h; tris.len()];
        (pos, tris, normals, areas)
    }

    fn centroid(pos: &[[f32; 3]], t: [u32; 3]) -> Vec3 {
        t.iter().map(|&q| Vec3::from(pos[q as usize])).sum::<Vec3>() / 3.0
    }

    #[test]
    fn a_linear_field_is_exact_at_every_vertex_edges_and_corners_included() {
        let (pos, tris, normals, areas) = square(8);
        let up = vec![Vec3::Z; pos.len()];
        let counts = vec![true; tris.len()];
        let r = Reconstruction::new(&pos, &tris, &normals, &areas, &up, &counts);
        let field = |p: Vec3| 2.0 + 3.0 * p.x - 1.5 * p.y;
        let values: Vec<f32> = tris.iter().map(|&t| field(centroid(&pos, t))).collect();
        let mean = crate::radiosity::vertex_values(
            &tris,
            &areas,
            pos.len(),
            &values.iter().map(|&v| [v; 3]).collect::<Vec<_>>(),
        );
        let (mut worst, mut worst_mean) = (0.0f32, 0.0f32);
        for (q, p) in pos.iter().enumerate() {
            let want = field(Vec3::from(*p));
            let got: f32 = r.row(q).map(|(k, w)| w * values[k]).sum();
            worst = worst.max((got - want).abs());
            worst_mean = worst_mean.max((mean[q][0] - want).abs());
        }
        // The area-weighted mean lags a third of a cell (h = 1/8) behind the gradient on
        // the edges; the fit has only rounding left.
        assert!(worst < 1e-4, "worst error {worst}");
        assert!(worst_mean > 0.1, "the mean was already exact? {worst_mean}");
    }

    #[test]
    fn surrounded_vertices_keep_the_mean_and_a_lone_triangle_its_value() {
        let (pos, tris, normals, areas) = square(4);
        let up = vec![Vec3::Z; pos.len()];
        let counts = vec![true; tris.len()];
        let r = Reconstruction::new(&pos, &tris, &normals, &areas, &up, &counts);
        // Vertex (2, 2) of the 4 × 4 grid is inside: its row is its ring, equal weights.
        let q = 2 * 5 + 2;
        let row: Vec<(usize, f32)> = r.row(q).collect();
        let ring = tris.iter().filter(|t| t.contains(&(q as u32))).count();
        assert_eq!(row.len(), ring);
        for (_, w) in &row {
            assert!((w - 1.0 / ring as f32).abs() < 1e-6, "{row:?}");
        }
        // One triangle: nothing to fit, the vertices take its value.
        let one = Reconstruction::new(
            &[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            &[[0, 1, 2]],
            &normals[..1],
            &[0.5],
            &up[..3],
            &[true],
        );
        for q in 0..3 {
            assert_eq!(one.row(q).collect::<Vec<_>>(), vec![(0, 1.0)]);
        }
        // Beside a patch that does not count (pressed against another object), a vertex
        // keeps the mean of those that do, edge or not.
        let mut some = counts.clone();
        some[0] = false;
        let r = Reconstruction::new(&pos, &tris, &normals, &areas, &up, &some);
        for &q in &tris[0] {
            let row: Vec<(usize, f32)> = r.row(q as usize).collect();
            let ring = tris
                .iter()
                .enumerate()
                .filter(|(k, t)| *k != 0 && t.contains(&q))
                .count();
            assert_eq!(row.len(), ring, "{row:?}");
            assert!(
                row.iter()
                    .all(|&(k, w)| k != 0 && (w - 1.0 / ring as f32).abs() < 1e-6)
            );
        }
        // Patches that do not count take no part; a vertex with none has an empty row.
        let none =
            Reconstruction::new(&pos, &tris, &normals, &areas, &up, &vec![false; tris.len()]);
        assert!((0..pos.len()).all(|q| none.row(q).next().is_none()));
    }
}
