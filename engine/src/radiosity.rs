//! Direct lighting and the radiosity solve.
//!
//! In: patch geometry, the scattering operator S (diag ρ for opaque scenes, or the sparse
//! subsurface matrix), emitted exitance Bₑ, the form factors F and lights.
//! Out: radiosity B (W·m⁻², per patch, RGB) from
//!
//! ```text
//!     B = Bₑ + S (E + F B)
//! ```
//!
//! where E is the direct irradiance from the lights (W·m⁻², with shadows): the paper's eq. 7
//! with emitters. With S = diag(ρ) it is classical radiosity. A vertex's colour is the
//! outgoing radiance B/π ([`vertex_radiance`]).

use crate::transport::Transport;
use glam::Vec3;
use rayon::prelude::*;
use thiserror::Error;
use translux_proto::light::Light;

pub use crate::linalg::{Albedo, Rgb, Scatter, SparseScatter, spmv_rgb};
use crate::raycast::Occluder;
pub use crate::solver::{Method, SolveError, SolveParams, SolveStats};

/// Lights this build cannot evaluate yet.
#[derive(Debug, Error, PartialEq)]
pub enum LightError {
    #[error("lights[{index}]: {kind} lights are not supported by the diffuse solver yet")]
    Unsupported { index: usize, kind: &'static str },
}

/// Per-patch geometry needed for lighting.
#[derive(Debug, Clone, Copy)]
pub struct PatchGeometry<'a> {
    pub centroid: &'a [Vec3],
    pub normal: &'a [Vec3],
}

/// What direct lighting needs of a bundle, built from its arrays: the shadow-ray BVH over
/// the scene's source triangles, and each patch's centroid and normal.
#[derive(Debug)]
pub struct BundleLighting {
    pub occluder: Occluder,
    pub centroid: Vec<Vec3>,
    pub normal: Vec<Vec3>,
    unit_mm: f64,
}

impl BundleLighting {
    pub fn new(b: &translux_proto::bundle::Bundle) -> BundleLighting {
        let tris: Vec<[Vec3; 3]> = b
            .occluder_triangles()
            .iter()
            .map(|t| t.map(Vec3::from))
            .collect();
        BundleLighting {
            occluder: Occluder::new(&tris),
            centroid: b
                .patch_corners()
                .iter()
                .map(|c| (Vec3::from(c[0]) + Vec3::from(c[1]) + Vec3::from(c[2])) / 3.0)
                .collect(),
            normal: b.patch_normals().iter().map(|&n| Vec3::from(n)).collect(),
            unit_mm: b.manifest().unit_mm,
        }
    }

    pub fn geometry(&self) -> PatchGeometry<'_> {
        PatchGeometry {
            centroid: &self.centroid,
            normal: &self.normal,
        }
    }

    /// [`direct_irradiance`] of `lights` on the bundle's patches.
    pub fn irradiance(&self, lights: &[Light]) -> Result<Vec<Rgb>, LightError> {
        direct_irradiance(self.geometry(), &self.occluder, lights, self.unit_mm)
    }
}

/// Direct irradiance E at each patch centroid (W·m⁻²), with shadow rays through `occ`
/// ([`PointLights::irradiance`] at each centroid).
///
/// Point: E = I cos θ / r² (r in metres: scene length × `unit_mm` / 1000). Spot: the same
/// times a smoothstep from 1 inside `inner_deg` to 0 at `outer_deg`. Directional:
/// E = irradiance × cos θ.
pub fn direct_irradiance(
    geo: PatchGeometry<'_>,
    occ: &Occluder,
    lights: &[Light],
    unit_mm: f64,
) -> Result<Vec<Rgb>, LightError> {
    for (index, l) in lights.iter().enumerate() {
        if let Light::Environment { .. } = l {
            return Err(LightError::Unsupported {
                index,
                kind: l.kind(),
            });
        }
    }
    let lights = PointLights::new(lights, occ, unit_mm);
    Ok(geo
        .centroid
        .par_iter()
        .zip(geo.normal.par_iter())
        .map(|(&c, &n)| lights.irradiance(c, n))
        .collect())
}

/// A point-like light as [`PointLights`] reads it.
#[derive(Debug, Clone, Copy)]
enum Source {
    /// Point or spot: position, intensity (W·sr⁻¹), and the spot's cone when it has one
    /// (axis, inner and outer half-angles in degrees).
    At {
        position: Vec3,
        intensity: [f32; 3],
        cone: Option<(Vec3, f32, f32)>,
    },
    /// Directional: toward the light, irradiance (W·m⁻²) facing it.
    Far {
        to_light: Vec3,
        irradiance: [f32; 3],
    },
}

/// The point, spot and directional lights of a request, ready to light surface points with
/// shadow rays: patch centroids ([`direct_irradiance`]), viewer vertices
/// ([`crate::vertexlight`]) and pixels ([`crate::specular`]) all go through
/// [`PointLights::each`], so they follow one rule.
#[derive(Debug)]
pub struct PointLights<'a> {
    sources: Vec<Source>,
    occ: &'a Occluder,
    /// Metres per scene unit.
    to_m: f32,
    /// Shadow rays start this far off the surface (scene units).
    offset: f32,
    /// Rays toward directional lights end here.
    far: f32,
}

impl<'a> PointLights<'a> {
    /// The point, spot and directional lights of `lights` (environment lights are skipped);
    /// `unit_mm` is the scene's millimetres per unit.
    pub fn new(lights: &[Light], occ: &'a Occluder, unit_mm: f64) -> Self {
        let sources = lights
            .iter()
            .filter_map(|l| match l {
                Light::Point {
                    position,
                    intensity,
                } => Some(Source::At {
                    position: Vec3::from(*position),
                    intensity: *intensity,
                    cone: None,
                }),
                Light::Spot {
                    position,
                    intensity,
                    direction,
                    inner_deg,
                    outer_deg,
                } => Some(Source::At {
                    position: Vec3::from(*position),
                    intensity: *intensity,
                    cone: Some((
                        Vec3::from(*direction).normalize_or_zero(),
                        *inner_deg,
                        *outer_deg,
                    )),
                }),
                Light::Directional {
                    direction,
                    irradiance,
                } => Some(Source::Far {
                    to_light: -Vec3::from(*direction).normalize_or_zero(),
                    irradiance: *irradiance,
                }),
                Light::Environment { .. } => None,
            })
            .collect();
        PointLights {
            sources,
            occ,
            to_m: (unit_mm / 1000.0) as f32,
            offset: 1e-5 * occ.diagonal(),
            far: 4.0 * occ.diagonal(),
        }
    }

    /// Whether there is no light.
    pub fn is_empty(&self) -> bool {
        self.sources.is_empty()
    }

    /// How many lights.
    pub fn len(&self) -> usize {
        self.sources.len()
    }

    /// The shadow-ray origin for a surface point: `p` moved off the surface along `n`.
    pub fn origin(&self, p: Vec3, n: Vec3) -> Vec3 {
        p + n * self.offset
    }

    /// Where rays toward the far field end (scene units).
    pub fn far(&self) -> f32 {
        self.far
    }

    /// Calls `f(l, e)` for each light that reaches `p` (normal `n`) unshadowed, with `l` the
    /// unit direction toward it and `e` its irradiance there (W·m⁻², cos θ included): point
    /// I cos θ / r² (r from the ray origin, in metres), spot the same times its fall-off,
    /// directional E cos θ.
    pub fn each(&self, p: Vec3, n: Vec3, mut f: impl FnMut(Vec3, [f32; 3])) {
        let origin = self.origin(p, n);
        for s in &self.sources {
            match *s {
                Source::At {
                    position,
                    intensity,
                    cone,
                } => {
                    let d = position - origin;
                    let r = d.length();
                    if r <= 0.0 {
                        continue;
                    }
                    let cos = n.dot(d) / r;
                    if cos <= 0.0 {
                        continue;
                    }
                    let spot = match cone {
                        Some((axis, inner, outer)) => {
                            spot_falloff(axis.dot((p - position).normalize_or_zero()), inner, outer)
                        }
                        None => 1.0,
                    };
                    if spot <= 0.0 || self.occ.occluded(origin, position) {
                        continue;
                    }
                    let rm = r * self.to_m;
                    let w = spot * cos / (rm * rm);
                    f(d / r, intensity.map(|c| w * c));
                }
                Source::Far {
                    to_light,
                    irradiance,
                } => {
                    let cos = n.dot(to_light);
                    if cos <= 0.0 || self.occ.occluded_dir(origin, to_light, 0.0, self.far) {
                        continue;
                    }
                    f(to_light, irradiance.map(|c| cos * c));
                }
            }
        }
    }

    /// The direct irradiance E (W·m⁻²) at `p` with normal `n`: the sum of [`Self::each`].
    pub fn irradiance(&self, p: Vec3, n: Vec3) -> Rgb {
        let mut e = [0.0f32; 3];
        self.each(p, n, |_, c| {
            for k in 0..3 {
                e[k] += c[k];
            }
        });
        e
    }
}

/// 1 inside the inner cone, 0 outside the outer cone, smoothstep between, from cos of the
/// angle between the spot's axis and the direction to the point.
pub fn spot_falloff(cos_angle: f32, inner_deg: f32, outer_deg: f32) -> f32 {
    let (ci, co) = (inner_deg.to_radians().cos(), outer_deg.to_radians().cos());
    if cos_angle >= ci {
        1.0
    } else if cos_angle <= co {
        0.0
    } else {
        let t = (cos_angle - co) / (ci - co);
        t * t * (3.0 - 2.0 * t)
    }
}

/// Solves B = Bₑ + ρ(E + F B) for an opaque scene (S = diag ρ).
pub fn solve_diffuse(
    f: &Transport<'_>,
    albedo: &[Rgb],
    emission: &[Rgb],
    irradiance: &[Rgb],
    params: &SolveParams,
    warm: Option<&[Rgb]>,
) -> (Vec<Rgb>, SolveStats) {
    match solve(f, &Albedo(albedo), emission, irradiance, params, warm) {
        Ok(r) => r,
        // A diagonal S accepts every method, and the lengths are the caller's.
        Err(e) => panic!("solve_diffuse: {e}"),
    }
}

/// Solves B = Bₑ + S(E + F B), i.e. (I − S F) B = Bₑ + S E, with `params.method`
/// ([`crate::solver`]). `warm` starts from a previous solution.
pub fn solve(
    f: &Transport<'_>,
    s: &dyn Scatter,
    emission: &[Rgb],
    irradiance: &[Rgb],
    params: &SolveParams,
    warm: Option<&[Rgb]>,
) -> Result<(Vec<Rgb>, SolveStats), SolveError> {
    let n = emission.len();
    // b = Bₑ + S E, the right-hand side.
    let mut b = vec![[0.0f32; 3]; n];
    s.apply(irradiance, &mut b);
    for (bi, e) in b.iter_mut().zip(emission) {
        for c in 0..3 {
            bi[c] += e[c];
        }
    }
    let (x, stats) = crate::solver::solve_system(
        f,
        s,
        bytemuck::cast_slice(&b),
        3,
        params,
        warm.map(bytemuck::cast_slice),
    )?;
    Ok((bytemuck::cast_slice(&x).to_vec(), stats))
}

/// Outgoing radiance per viewer vertex: B/π, area-weighted over the vertex's patches.
pub fn vertex_radiance(
    triangles: &[[u32; 3]],
    areas: &[f32],
    vertex_count: usize,
    radiosity: &[Rgb],
) -> Vec<Rgb> {
    let inv_pi = 1.0 / std::f32::consts::PI;
    let radiance: Vec<Rgb> = radiosity.iter().map(|b| b.map(|v| v * inv_pi)).collect();
    vertex_values(triangles, areas, vertex_count, &radiance)
}

/// Vertex values from patch values: the area-weighted mean of the patches that use the
/// vertex (its smoothing group). Vertices no patch uses get 0.
pub fn vertex_values(
    triangles: &[[u32; 3]],
    areas: &[f32],
    vertex_count: usize,
    patch_values: &[[f32; 3]],
) -> Vec<[f32; 3]> {
    let mut sum = vec![[0.0f64; 3]; vertex_count];
    let mut weight = vec![0.0f64; vertex_count];
    for ((tri, &a), v) in triangles.iter().zip(areas).zip(patch_values) {
        for &vi in tri {
            let s = &mut sum[vi as usize];
            for c in 0..3 {
                s[c] += a as f64 * v[c] as f64;
            }
            weight[vi as usize] += a as f64;
        }
    }
    sum.iter()
        .zip(&weight)
        .map(|(s, &w)| {
            if w > 0.0 {
                [(s[0] / w) as f32, (s[1] / w) as f32, (s[2] / w) as f32]
            } else {
                [0.0; 3]
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use translux_proto::csr::CsrView;

    #[test]
    fn spot_falloff_edges() {
        assert_eq!(spot_falloff(1.0, 10.0, 20.0), 1.0);
        // Half-way between the cones' cosines is half-way up the smoothstep.
        let mid = 0.5 * (10f32.to_radians().cos() + 20f32.to_radians().cos());
        assert!((spot_falloff(mid, 10.0, 20.0) - 0.5).abs() < 1e-5);
        let (a, b) = (
            spot_falloff(14f32.to_radians().cos(), 10.0, 20.0),
            spot_falloff(16f32.to_radians().cos(), 10.0, 20.0),
        );
        assert!(a > b && a < 1.0 && b > 0.0);
        assert_eq!(spot_falloff(25f32.to_radians().cos(), 10.0, 20.0), 0.0);
        assert_eq!(
            spot_falloff(10f32.to_radians().cos() + 1e-6, 10.0, 20.0),
            1.0
        );
    }

    #[test]
    fn two_patch_system_matches_hand_solution() {
        // F = [[0, .5], [.25, 0]], ρ = .8, E = 0, Bₑ = [1, 0]:
        // B0 = 1 + .8·.5·B1, B1 = .8·.25·B0 → B0 = 1/(1 − .08), B1 = .2 B0.
        let rp = [0u64, 1, 2];
        let col = [1u32, 0];
        let val = [0.5f32, 0.25];
        let f = CsrView::new_checked(2, 2, &rp, &col, &val).unwrap();
        let rho = [[0.8f32; 3]; 2];
        let be = [[1.0f32; 3], [0.0; 3]];
        let e = [[0.0f32; 3]; 2];
        for method in [Method::Jacobi, Method::GaussSeidel] {
            let params = SolveParams {
                method,
                tolerance: 1e-6,
                max_iterations: 100,
            };
            let (b, s) = solve_diffuse(&Transport::dense(f), &rho, &be, &e, &params, None);
            assert!(s.converged);
            let b0 = 1.0 / (1.0 - 0.08);
            assert!(
                (b[0][1] - b0).abs() < 1e-5 && (b[1][2] - 0.2 * b0).abs() < 1e-5,
                "{b:?}"
            );
        }
    }
}
