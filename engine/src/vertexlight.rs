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
//! The indirect part ρ F B stays interpolated (it varies slowly), and so does everything
//! on translucent objects and sheets, whose S already smooths the direct light over a
//! mean free path (an exact E at a vertex would be the wrong answer there), except in
//! the components that take them as opaque at ρ̄ (`direct`, `interreflection_only`). Environment
//! lights stay per patch too: their visibility is stored per patch only.

use glam::Vec3;
use translux_proto::api::Components;
use translux_proto::bundle::Bundle;
use translux_proto::scene::Material;

use crate::linalg::Rgb;
use crate::raycast::Occluder;
use rayon::prelude::*;

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
        let normal = (0..v)
            .map(|k| {
                let n = normals.get(k).map(|&n| Vec3::from(n)).unwrap_or(Vec3::ZERO);
                if n.length_squared() > 0.0 && n.is_finite() {
                    n.normalize()
                } else {
                    face_n[k].normalize_or_zero()
                }
            })
            .collect();
        VertexSamples {
            point,
            normal,
            area,
            counts,
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

/// Which objects reflect the direct light as an opaque surface, B = … + ρ̄E, under
/// `materials` (one per object, the request's overrides applied) and `components`: diffuse
/// objects always; every object in the `direct` and `interreflection_only` components,
/// which take translucent objects as opaque at ρ̄ (emitters have ρ̄ = 0 and are unchanged).
pub fn opaque_objects(materials: &[&Material], components: Components) -> Vec<bool> {
    let all = matches!(
        components,
        Components::Direct | Components::InterreflectionOnly
    );
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

/// Per vertex, over the patches that count ([`VertexSamples::counts`]): Σ a (B − ρE),
/// Σ a ρ and Σ a, made once per relight; [`VertexMeans::set`] then writes the vertices'
/// values for any E at the vertices.
#[derive(Debug, Clone)]
pub struct VertexMeans {
    rest: Vec<[f64; 3]>,
    rho: Vec<[f64; 3]>,
    area: Vec<f64>,
}

impl VertexMeans {
    pub fn new(b: &Bundle, samples: &VertexSamples, patches: PatchTerms<'_>) -> VertexMeans {
        let v = b.vertex_positions().len();
        let mut m = VertexMeans {
            rest: vec![[0.0; 3]; v],
            rho: vec![[0.0; 3]; v],
            area: vec![0.0; v],
        };
        for (k, t) in b.triangle_vertices().iter().enumerate() {
            if !samples.counts[k] {
                continue;
            }
            let a = b.patch_areas()[k] as f64;
            let (bb, e, r) = (
                patches.radiosity[k],
                patches.irradiance[k],
                patches.albedo[k],
            );
            for &q in t {
                let q = q as usize;
                for c in 0..3 {
                    m.rest[q][c] += a * (bb[c] as f64 - r[c] as f64 * e[c] as f64);
                    m.rho[q][c] += a * r[c] as f64;
                }
                m.area[q] += a;
            }
        }
        m
    }

    /// Sets `radiance` (per vertex, W·m⁻²·sr⁻¹) at the vertices `which` to
    /// mean(B − ρE)/π + ρ̄ E(v)/π; `vertex_e[i]` is E at vertex `which[i]`.
    pub fn set(&self, which: &[usize], vertex_e: &[Rgb], radiance: &mut [Rgb]) {
        let inv_pi = 1.0 / std::f64::consts::PI;
        for (&q, ev) in which.iter().zip(vertex_e) {
            if self.area[q] <= 0.0 {
                continue;
            }
            for c in 0..3 {
                let value =
                    (self.rest[q][c] + self.rho[q][c] * ev[c] as f64) / self.area[q] * inv_pi;
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
