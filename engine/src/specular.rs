//! The specular pass: one bounce of glossy reflection of the lights, added per pixel on top
//! of the radiosity answer (the paper's "one bounce of specularities are added in a separate
//! pass", Fig. 1 and Fig. 8 b–c).
//!
//! In: a surface point, its shading normal and the direction to the eye, the object's
//! [`Gloss`] (from its material's `specular`), and the request's lights ([`Lighting`]).
//! Out: the reflected radiance in W·m⁻²·sr⁻¹, the unit of the relight's B/π, to be added to
//! it. Nothing here changes B: the highlight is view dependent and leaves the surface, it does
//! not feed the inter-reflection (the paper's model, and what its figures show).
//!
//! The model is a rough dielectric's reflection (Walter et al. 2007, "Microfacet models for
//! refraction through rough surfaces"):
//!
//!   f_s(l, v) = F(v·h, η) · D(h) · G₂(l, v) / (4 |n·l| |n·v|),   h = normalize(l + v)
//!
//! - D is the GGX (Trowbridge–Reitz) distribution, D(h) = α² / (π ((n·h)² (α² − 1) + 1)²),
//!   with α = roughness² ([`translux_proto::scene::Specular`]).
//! - G₂ is Smith's height-correlated masking–shadowing, G₂ = 1 / (1 + Λ(l) + Λ(v)) with
//!   Λ(ω) = (−1 + √(1 + α² tan²θ_ω)) / 2 (Heitz 2014, "Understanding the masking-shadowing
//!   function in microfacet-based BRDFs").
//! - F is the exact Fresnel reflectance of an unpolarised wave at a smooth dielectric of
//!   relative index η ([`fresnel_dielectric`]).
//!
//! Point and spot lights give L = f_s · I cos θ_l / r² (r in metres, as in the direct
//! irradiance), directional lights L = f_s · E cos θ_l; each is shadowed by a ray through the
//! scene's [`Occluder`]. An environment light is integrated by importance sampling D
//! ([`ENV_SAMPLES`] directions per pixel, a fixed stratified set turned by a hash of the
//! pixel, so a picture is reproducible), each direction shadowed by a ray to the far field.

use std::sync::Arc;

use glam::Vec3;
use translux_proto::light::Light;
use translux_proto::scene::{Material, Profile, Specular};

use crate::envmap::EnvMap;
use crate::profile;
use crate::radiosity::PointLights;
use crate::raycast::Occluder;
use crate::render::PixelShade;

/// η where neither the specular nor the medium gives one: glass, plastics, varnish.
pub const DEFAULT_ETA: f32 = 1.5;

/// Directions per pixel for an environment light's highlight.
pub const ENV_SAMPLES: u32 = 32;

/// An object's resolved glossy coat: GGX width α and relative index η.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gloss {
    pub alpha: f32,
    pub eta: f32,
}

impl Gloss {
    /// The material's coat, `None` without one: α = roughness², η from the specular, else
    /// from the medium ([`medium_eta`]), else [`DEFAULT_ETA`].
    pub fn of(material: &Material) -> Option<Gloss> {
        let s: &Specular = material.specular()?;
        Some(Gloss {
            alpha: s.roughness * s.roughness,
            eta: s
                .eta
                .or_else(|| medium_eta(material))
                .unwrap_or(DEFAULT_ETA),
        })
    }
}

/// The relative index of refraction of a material's medium, where it states one: a dipole's
/// `eta`, else its preset's ([`profile::preset`]: 1.5 for marble, 1.3 for the others), else
/// the dipole's default 1.3; a measured table or an exponential sum states none. For a thin sheet,
/// its reflectance profile's; for a heterogeneous object, its first medium's.
pub fn medium_eta(material: &Material) -> Option<f32> {
    let of = |p: &Profile| profile::dipole_medium(p).map(|m| m.eta);
    match material {
        Material::Translucent { profile, .. } => of(profile),
        Material::ThinSheet { reflectance, .. } => of(reflectance),
        Material::Heterogeneous { materials, .. } => materials.first().and_then(of),
        Material::Simulated { preset, eta, .. } => Some(profile::eta_of(preset.as_deref(), *eta)),
        Material::Diffuse { .. } | Material::Emitter { .. } => None,
    }
}

/// GGX's normal distribution D(h) (sr⁻¹ per projected area), from cos θ_h = n·h.
pub fn ggx_d(alpha: f32, cos_h: f32) -> f32 {
    if cos_h <= 0.0 {
        return 0.0;
    }
    let a2 = alpha * alpha;
    let k = cos_h * cos_h * (a2 - 1.0) + 1.0;
    a2 / (std::f32::consts::PI * k * k)
}

/// Smith's Λ for GGX at a direction with cos θ = `cos` to the normal.
pub fn smith_lambda(alpha: f32, cos: f32) -> f32 {
    let c2 = (cos * cos).clamp(1e-12, 1.0);
    let tan2 = (1.0 - c2) / c2;
    0.5 * (-1.0 + (1.0 + alpha * alpha * tan2).sqrt())
}

/// The Fresnel reflectance of unpolarised light meeting a smooth dielectric of relative
/// index `eta` (> 1, light arriving from outside) at cos θ_i = `cos_i`: the mean of the
/// s and p reflectances, with Snell's law for the refracted angle.
pub fn fresnel_dielectric(cos_i: f32, eta: f32) -> f32 {
    let ci = cos_i.clamp(0.0, 1.0);
    let s2 = (1.0 - ci * ci) / (eta * eta);
    if s2 >= 1.0 {
        return 1.0;
    }
    let ct = (1.0 - s2).sqrt();
    let rs = (ci - eta * ct) / (ci + eta * ct);
    let rp = (eta * ci - ct) / (eta * ci + ct);
    0.5 * (rs * rs + rp * rp)
}

/// The BRDF f_s(l, v) (sr⁻¹) for unit vectors: normal `n`, toward the light `l`, toward
/// the eye `v`. Zero when either is below the surface.
pub fn brdf(g: Gloss, n: Vec3, l: Vec3, v: Vec3) -> f32 {
    let (nl, nv) = (n.dot(l), n.dot(v));
    if nl <= 0.0 || nv <= 0.0 {
        return 0.0;
    }
    let h = (l + v).normalize_or_zero();
    if h == Vec3::ZERO {
        return 0.0;
    }
    let g2 = 1.0 / (1.0 + smith_lambda(g.alpha, nl) + smith_lambda(g.alpha, nv));
    fresnel_dielectric(v.dot(h), g.eta) * ggx_d(g.alpha, n.dot(h)) * g2 / (4.0 * nl * nv)
}

/// Samples a direction toward the light by D: h with density D(h)(n·h), l the mirror of `v`
/// about h. Returns l and f_s cos θ_l / pdf(l) = F G₂ (v·h) / ((n·v)(n·h)), or `None` when
/// l falls below the surface. `u` in [0, 1)².
pub fn sample(g: Gloss, n: Vec3, v: Vec3, u: [f32; 2]) -> Option<(Vec3, f32)> {
    let nv = n.dot(v);
    if nv <= 0.0 {
        return None;
    }
    // tan²θ_h = α² u / (1 − u) inverts the GGX slope distribution's CDF.
    let tan2 = g.alpha * g.alpha * u[0] / (1.0 - u[0]).max(1e-7);
    let cos_h = 1.0 / (1.0 + tan2).sqrt();
    let sin_h = (1.0 - cos_h * cos_h).max(0.0).sqrt();
    let phi = std::f32::consts::TAU * u[1];
    let (t, b) = n.any_orthonormal_pair();
    let h = (t * (sin_h * phi.cos()) + b * (sin_h * phi.sin()) + n * cos_h).normalize();
    let vh = v.dot(h);
    if vh <= 0.0 {
        return None;
    }
    let l = h * (2.0 * vh) - v;
    let nl = n.dot(l);
    if nl <= 0.0 {
        return None;
    }
    let g2 = 1.0 / (1.0 + smith_lambda(g.alpha, nl) + smith_lambda(g.alpha, nv));
    Some((l, fresnel_dielectric(vh, g.eta) * g2 * vh / (nv * cos_h)))
}

/// An environment light: its map, scale and rotation about +Y (degrees).
#[derive(Debug, Clone)]
pub struct EnvLight {
    pub map: Arc<EnvMap>,
    pub scale: f32,
    pub rotation_deg: f32,
}

/// The request's lights, ready for per-pixel work: the point, spot and directional ones
/// ([`PointLights`], with their shadow rays) and the environment lights with their maps.
#[derive(Debug)]
pub struct Lighting<'a> {
    point: PointLights<'a>,
    env: Vec<EnvLight>,
    occ: &'a Occluder,
}

impl<'a> Lighting<'a> {
    /// The point, spot and directional lights of `lights` plus the environment lights given
    /// loaded in `env` (environment entries of `lights` are skipped: the caller loads their
    /// maps). `unit_mm` is the scene's millimetres per unit.
    pub fn new(lights: &[Light], env: Vec<EnvLight>, occ: &'a Occluder, unit_mm: f64) -> Self {
        Lighting {
            point: PointLights::new(lights, occ, unit_mm),
            env,
            occ,
        }
    }

    /// Whether no light can add anything.
    pub fn is_empty(&self) -> bool {
        self.point.is_empty() && self.env.is_empty()
    }

    /// The radiance (W·m⁻²·sr⁻¹) a pixel gains at `p` with shading normal `n`, seen from
    /// the unit direction `v` (toward the eye): the highlight of the coat `gloss` (all
    /// lights) plus ρ E / π for `diffuse` = ρ (point, spot and directional lights), each
    /// light's shadow ray cast once. `pixel` seeds the environment's sample set.
    pub fn shade(
        &self,
        gloss: Option<Gloss>,
        diffuse: Option<[f32; 3]>,
        p: Vec3,
        n: Vec3,
        v: Vec3,
        pixel: u32,
    ) -> [f32; 3] {
        let mut out = [0.0f32; 3];
        let seen = n.dot(v) > 0.0;
        let rho = diffuse
            .unwrap_or([0.0; 3])
            .map(|r| r * std::f32::consts::FRAC_1_PI);
        self.point.each(p, n, |l, e| {
            let f = match gloss {
                Some(g) if seen => brdf(g, n, l, v),
                _ => 0.0,
            };
            for k in 0..3 {
                out[k] += (f + rho[k]) * e[k];
            }
        });
        if let (Some(g), true, false) = (gloss, seen, self.env.is_empty()) {
            let origin = self.point.origin(p, n);
            let turn = pixel_offsets(pixel);
            let inv = 1.0 / ENV_SAMPLES as f32;
            for k in 0..ENV_SAMPLES {
                // A stratified (Hammersley) set, turned per pixel (Cranley–Patterson).
                let u = [
                    ((k as f32 + 0.5) * inv + turn[0]).fract(),
                    (radical_inverse(k) + turn[1]).fract(),
                ];
                let Some((l, w)) = sample(g, n, v, u) else {
                    continue;
                };
                if self.occ.occluded_dir(origin, l, 0.0, self.point.far()) {
                    continue;
                }
                for e in &self.env {
                    let c = e.map.radiance_rotated(l, e.rotation_deg);
                    for ch in 0..3 {
                        out[ch] += w * inv * e.scale * c[ch];
                    }
                }
            }
        }
        out
    }
}

/// What a render adds per pixel on one object: the specular pass where it has a coat, and
/// the direct light of the point, spot and directional lights times its albedo where its
/// direct term is taken per pixel ([`translux_proto::api::DirectAt::Pixel`]).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ObjectShading {
    pub gloss: Option<Gloss>,
    /// ρ: the pixel gains ρ E(p) / π, E(p) with shadow rays.
    pub diffuse: Option<[f32; 3]>,
}

/// The per-pixel pass of a render: the objects' triangle ranges with what they get, and the
/// lights, as a [`PixelShade`] for [`crate::render::render_with`].
#[derive(Debug)]
pub struct PixelLighting<'a> {
    lighting: Lighting<'a>,
    /// Mesh triangle ranges [start, end), ascending, of objects that get something.
    ranges: Vec<(u32, u32, ObjectShading)>,
}

impl<'a> PixelLighting<'a> {
    /// `objects`: each object's mesh triangle range and shading. `None` when no object gets
    /// anything or no light can add anything: nothing to do.
    pub fn new(
        lighting: Lighting<'a>,
        objects: impl IntoIterator<Item = (std::ops::Range<u32>, ObjectShading)>,
    ) -> Option<PixelLighting<'a>> {
        let mut ranges: Vec<(u32, u32, ObjectShading)> = objects
            .into_iter()
            .filter(|(r, s)| r.start < r.end && (s.gloss.is_some() || s.diffuse.is_some()))
            .map(|(r, s)| (r.start, r.end, s))
            .collect();
        ranges.sort_by_key(|r| r.0);
        (!ranges.is_empty() && !lighting.is_empty()).then_some(PixelLighting { lighting, ranges })
    }

    fn object(&self, triangle: u32) -> Option<&ObjectShading> {
        let k = self.ranges.partition_point(|r| r.0 <= triangle);
        let (_, end, s) = self.ranges.get(k.checked_sub(1)?)?;
        (triangle < *end).then_some(s)
    }
}

impl PixelShade for PixelLighting<'_> {
    fn shades(&self, triangle: u32) -> bool {
        self.object(triangle).is_some()
    }

    fn shade(&self, triangle: u32, p: Vec3, n: Vec3, to_eye: Vec3, pixel: u32) -> [f32; 3] {
        match self.object(triangle) {
            Some(s) => self.lighting.shade(s.gloss, s.diffuse, p, n, to_eye, pixel),
            None => [0.0; 3],
        }
    }
}

/// The base-2 radical inverse of `k` (van der Corput).
fn radical_inverse(k: u32) -> f32 {
    k.reverse_bits() as f32 * (1.0 / 4_294_967_296.0)
}

/// Two offsets in [0, 1) from a pixel index (a 32-bit integer hash, Wellons' `lowbias32`).
fn pixel_offsets(pixel: u32) -> [f32; 2] {
    let hash = |mut x: u32| {
        x ^= x >> 16;
        x = x.wrapping_mul(0x7feb_352d);
        x ^= x >> 15;
        x = x.wrapping_mul(0x846c_a68b);
        x ^= x >> 16;
        x
    };
    let a = hash(pixel);
    let b = hash(a ^ 0x9e37_79b9);
    [
        (a >> 8) as f32 / 16_777_216.0,
        (b >> 8) as f32 / 16_777_216.0,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// ∫ D(h) (n·h) dω_h = 1: D is a distribution of projected microfacet area.
    #[test]
    fn ggx_projected_area_is_one() {
        for alpha in [0.05f32, 0.2, 0.6, 1.0] {
            // θ_h on a fine grid in cos, φ integrated analytically (2π).
            let n = 200_000;
            let mut sum = 0.0f64;
            for i in 0..n {
                let c = (i as f64 + 0.5) / n as f64;
                sum += ggx_d(alpha, c as f32) as f64 * c * std::f64::consts::TAU / n as f64;
            }
            assert!((sum - 1.0).abs() < 2e-3, "α {alpha}: {sum}");
        }
    }

    /// Fresnel at normal incidence is ((η − 1)/(η + 1))², and total past the critical angle
    /// does not happen from outside (η > 1): F(grazing) → 1.
    #[test]
    fn fresnel_closed_forms() {
        for eta in [1.3f32, 1.5, 2.0] {
            let f0 = ((eta - 1.0) / (eta + 1.0)).powi(2);
            assert!((fresnel_dielectric(1.0, eta) - f0).abs() < 1e-6);
            assert!(fresnel_dielectric(1e-4, eta) > 0.99);
        }
        // Brewster's angle: rp = 0, so F = rs²/2.
        let eta = 1.5f32;
        let tb = eta.atan();
        let (ci, ct) = (tb.cos(), (1.0 - (tb.sin() / eta).powi(2)).sqrt());
        let rs = (ci - eta * ct) / (ci + eta * ct);
        assert!((fresnel_dielectric(ci, eta) - 0.5 * rs * rs).abs() < 1e-6);
    }

    /// ∫ f(ω) dω over the upper hemisphere (+z) by the midpoint rule in θ and φ.
    fn hemisphere(nt: usize, np: usize, f: impl Fn(Vec3) -> f64) -> f64 {
        let (dt, dp) = (
            std::f64::consts::FRAC_PI_2 / nt as f64,
            std::f64::consts::TAU / np as f64,
        );
        let mut sum = 0.0;
        for i in 0..nt {
            let th = (i as f64 + 0.5) * dt;
            for j in 0..np {
                let ph = (j as f64 + 0.5) * dp;
                let w = Vec3::new(
                    (th.sin() * ph.cos()) as f32,
                    (th.sin() * ph.sin()) as f32,
                    th.cos() as f32,
                );
                sum += f(w) * th.sin() * dt * dp;
            }
        }
        sum
    }

    /// The weak white furnace (Heitz 2014, eq. 16): with G₁ alone and F = 1, the visible
    /// normals integrate to one, ∫ G₁(v) max(0, v·h) D(h) dω_h = n·v, for every view.
    #[test]
    fn weak_white_furnace() {
        for alpha in [0.1f32, 0.5, 1.0] {
            for theta_deg in [0.0f32, 40.0, 75.0] {
                let t = theta_deg.to_radians();
                let v = Vec3::new(t.sin(), 0.0, t.cos());
                let g1 = 1.0 / (1.0 + smith_lambda(alpha, v.z)) as f64;
                let sum = hemisphere(1500, 600, |h| {
                    v.dot(h).max(0.0) as f64 * ggx_d(alpha, h.z) as f64
                });
                let got = g1 * sum;
                assert!(
                    (got - v.z as f64).abs() < 0.01 * v.z as f64 + 1e-3,
                    "α {alpha}, θ {theta_deg}: {got} vs {}",
                    v.z
                );
            }
        }
    }

    /// The sampler's weight is f_s cos θ_l / pdf: its mean over many directions is the
    /// directional albedo ∫ f_s cos θ_l dω_l, integrated here by quadrature over l.
    #[test]
    fn sampled_albedo_matches_quadrature() {
        let n = Vec3::Z;
        for (alpha, theta_deg) in [(0.3f32, 30.0f32), (0.8, 60.0)] {
            let g = Gloss { alpha, eta: 1.5 };
            let t = theta_deg.to_radians();
            let v = Vec3::new(t.sin(), 0.0, t.cos());
            let quad = hemisphere(800, 400, |l| brdf(g, n, l, v) as f64 * l.z as f64);
            let m = 512u32;
            let mut mc = 0.0f64;
            for a in 0..m {
                for b in 0..m {
                    let u = [(a as f32 + 0.5) / m as f32, (b as f32 + 0.5) / m as f32];
                    if let Some((_, w)) = sample(g, n, v, u) {
                        mc += w as f64;
                    }
                }
            }
            mc /= (m * m) as f64;
            assert!(
                (mc - quad).abs() < 0.01 * quad,
                "α {alpha}, θ {theta_deg}: sampled {mc} vs quadrature {quad}"
            );
        }
    }

    use crate::render::{RenderParams, Surface, render_linear_with};
    use translux_proto::light::Camera;

    /// A floor of two triangles, z = 0, facing +z, 4 units wide, with its vertex normals,
    /// plus `extra` triangles that only cast shadows.
    fn floor_picture(
        light: Light,
        camera: Camera,
        alpha: f32,
        extra: &[[Vec3; 3]],
        size: u32,
    ) -> Vec<[f32; 3]> {
        let positions = [
            [-2.0, -2.0, 0.0],
            [2.0, -2.0, 0.0],
            [2.0, 2.0, 0.0],
            [-2.0, 2.0, 0.0],
        ];
        let triangles = [[0u32, 1, 2], [0, 2, 3]];
        let normals = [[0.0, 0.0, 1.0]; 4];
        let mut occ_tris: Vec<[Vec3; 3]> = triangles
            .iter()
            .map(|t| t.map(|i| Vec3::from(positions[i as usize])))
            .collect();
        occ_tris.extend_from_slice(extra);
        let occ = Occluder::new(&occ_tris);
        // unit_mm 1000: scene units are metres.
        let lighting = Lighting::new(&[light], Vec::new(), &occ, 1000.0);
        let g = Gloss { alpha, eta: 1.5 };
        let shading = ObjectShading {
            gloss: Some(g),
            diffuse: None,
        };
        let h = PixelLighting::new(lighting, [(0..2, shading)]).unwrap();
        let surface = Surface {
            normals: &normals,
            shade: &h,
        };
        let params = RenderParams {
            width: size,
            height: size,
            ..Default::default()
        };
        let img = render_linear_with(
            &positions,
            &triangles,
            &[[0.0; 3]; 4],
            &camera,
            &params,
            Some(&surface),
        )
        .unwrap();
        img.pixels().map(|p| p.0).collect()
    }

    /// Light and eye straight above the floor at height h: the pixel at the image centre
    /// sees the point below, where h = n, D = 1/(πα²), G₂ = 1, F = ((η−1)/(η+1))², so
    /// L = F₀ I / (4 π α² h²) in closed form. A square between light and floor removes it.
    #[test]
    fn highlight_at_normal_incidence_is_the_closed_form() {
        let (i0, h, alpha) = (100.0f32, 1.0f32, 0.1f32);
        let light = Light::Point {
            position: [0.0, 0.0, h],
            intensity: [i0, 2.0 * i0, 0.5 * i0],
        };
        let camera = Camera {
            position: [0.0, 0.0, h],
            target: [0.0, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_deg: 30.0,
        };
        let size = 101;
        let px = floor_picture(light.clone(), camera, alpha, &[], size);
        let centre = px[(size * size / 2) as usize];
        let f0 = (0.5f32 / 2.5).powi(2);
        let want = f0 * i0 / (4.0 * std::f32::consts::PI * alpha * alpha * h * h);
        for (k, m) in [1.0f32, 2.0, 0.5].iter().enumerate() {
            let rel = (centre[k] / (want * m) - 1.0).abs();
            assert!(rel < 2e-3, "channel {k}: {} vs {}", centre[k], want * m);
        }
        // A 0.2 m square halfway up hides the light from the middle of the floor.
        let (a, b, c, d) = (
            Vec3::new(-0.1, -0.1, 0.5),
            Vec3::new(0.1, -0.1, 0.5),
            Vec3::new(0.1, 0.1, 0.5),
            Vec3::new(-0.1, 0.1, 0.5),
        );
        let px = floor_picture(light, camera, alpha, &[[a, b, c], [a, c, d]], size);
        assert_eq!(px[(size * size / 2) as usize], [0.0; 3]);
    }

    /// Light and eye on opposite sides at equal height: the brightest pixel is the mirror
    /// point (the image centre), to within a pixel.
    #[test]
    fn highlight_peaks_at_the_mirror_point() {
        let light = Light::Point {
            position: [-1.0, 0.0, 1.0],
            intensity: [50.0; 3],
        };
        let camera = Camera {
            position: [1.0, 0.0, 1.0],
            target: [0.0, 0.0, 0.0],
            up: [0.0, 0.0, 1.0],
            fov_deg: 20.0,
        };
        let size = 101u32;
        let px = floor_picture(light, camera, 0.05, &[], size);
        let (k, _) = px
            .iter()
            .enumerate()
            .max_by(|a, b| a.1[0].total_cmp(&b.1[0]))
            .unwrap();
        let (x, y) = ((k as u32 % size) as f32, (k as u32 / size) as f32);
        let c = (size / 2) as f32;
        assert!(
            (x - c).hypot(y - c) <= 1.0,
            "peak at pixel ({x}, {y}), the mirror point is at ({c}, {c})"
        );
    }

    #[test]
    fn gloss_takes_eta_from_the_medium() {
        let spec = Some(Specular {
            roughness: 0.5,
            eta: None,
        });
        let marble = Material::Translucent {
            profile: Profile::Dipole {
                preset: Some("marble".into()),
                sigma_a: None,
                sigma_s_prime: None,
                eta: None,
                scale: None,
            },
            specular: spec,
        };
        let g = Gloss::of(&marble).unwrap();
        assert_eq!(g.alpha, 0.25);
        assert_eq!(g.eta, profile::preset("marble").unwrap().eta);
        let paint = Material::Diffuse {
            albedo: [0.5; 3],
            specular: spec,
        };
        assert_eq!(Gloss::of(&paint).unwrap().eta, DEFAULT_ETA);
        let plain = Material::Diffuse {
            albedo: [0.5; 3],
            specular: None,
        };
        assert!(Gloss::of(&plain).is_none());
    }
}
