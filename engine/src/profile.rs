//! Diffuse reflectance profiles R(r): Jensen et al. 2001's measured media, the total diffuse
//! reflectance Rd = ∫ R(r) 2πr dr of every profile kind, and [`ProfileEval`], the evaluator
//! the subsurface matrix S is built from.
//!
//! In: a [`Profile`] from the scene file (lengths in mm, coefficients in mm⁻¹, R in mm⁻²) and
//! the scene's length unit (`unit_mm`, millimetres per scene unit). Out:
//! - [`total_reflectance`]: per-channel Rd, the albedo a translucent object has when it is
//!   treated as opaque (the "inter-reflection only" component, and the foundation's diffuse
//!   solve before S is in the bundle);
//! - [`ProfileEval`]: R(r) per unit area in scene units (scene-unit⁻², r in scene units), the
//!   fraction re-emitted within a radius (for the self term and near pairs), and an
//!   energy-based truncation radius;
//! - [`multipole`]: Donner and Jensen 2005's reflectance and transmittance profiles of a slab.
//!
//! Units. A profile R_mm given in mm evaluated in a scene whose unit is `unit_mm` millimetres
//! is R(r) = R_mm(r·unit_mm)·unit_mm²: the area element dA = unit_mm² dA_mm, so the
//! dimensionless ∫ R dA (a reflectance) does not depend on the unit. Stretching a profile by
//! s (mean free paths × s) is the same similarity, R_s(r) = R(r/s)/s², so both fold into one
//! factor k = unit_mm / s and R(r) = k² R_mm(k r); integrals over a disc of radius ρ are
//! ∫₀^{kρ} R_mm(u) 2πu du.

use std::f64::consts::PI;

use translux_proto::scene::{DIPOLE_PRESETS, Profile};

/// Reduced scattering σs′ and absorption σa (mm⁻¹, RGB) and relative index η of a medium.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Medium {
    pub sigma_s_prime: [f32; 3],
    pub sigma_a: [f32; 3],
    pub eta: f32,
}

/// The relative index of a medium where neither its material nor its preset states one.
pub const DEFAULT_ETA: f32 = 1.3;

/// A medium's relative index of refraction: `eta`, else the preset `preset_name`'s, else
/// [`DEFAULT_ETA`].
pub fn eta_of(preset_name: Option<&str>, eta: Option<f32>) -> f32 {
    eta.or_else(|| preset_name.and_then(preset).map(|m| m.eta))
        .unwrap_or(DEFAULT_ETA)
}

/// Jensen, Marschner, Levoy and Hanrahan, "A Practical Model for Subsurface Light
/// Transport", SIGGRAPH 2001, Table 1 (σs′ and σa in mm⁻¹ for R, G, B). η is 1.3 for every
/// medium but marble (1.5), as the usual reproductions of the table list it.
pub fn preset(name: &str) -> Option<Medium> {
    let m = |s: [f32; 3], a: [f32; 3], eta: f32| Medium {
        sigma_s_prime: s,
        sigma_a: a,
        eta,
    };
    Some(match name {
        "apple" => m([2.29, 2.39, 1.97], [0.0030, 0.0034, 0.046], 1.3),
        "chicken1" => m([0.15, 0.21, 0.38], [0.015, 0.077, 0.19], 1.3),
        "chicken2" => m([0.19, 0.25, 0.32], [0.018, 0.088, 0.20], 1.3),
        "cream" => m([7.38, 5.47, 3.15], [0.0002, 0.0028, 0.0163], 1.3),
        "ketchup" => m([0.18, 0.07, 0.03], [0.061, 0.97, 1.45], 1.3),
        "marble" => m([2.19, 2.62, 3.00], [0.0021, 0.0041, 0.0071], 1.5),
        "potato" => m([0.68, 0.70, 0.55], [0.0024, 0.0090, 0.12], 1.3),
        "skimmilk" => m([0.70, 1.22, 1.90], [0.0014, 0.0025, 0.0142], 1.3),
        "skin1" => m([0.74, 0.88, 1.01], [0.032, 0.17, 0.48], 1.3),
        "skin2" => m([1.09, 1.59, 1.79], [0.013, 0.070, 0.145], 1.3),
        "wholemilk" => m([2.55, 3.21, 3.77], [0.0011, 0.0024, 0.014], 1.3),
        _ => return None,
    })
}

/// Diffuse Fresnel reflectance, the rational fit Jensen et al. use:
/// F_dr = −1.440/η² + 0.710/η + 0.668 + 0.0636 η.
pub fn fresnel_diffuse(eta: f32) -> f32 {
    -1.440 / (eta * eta) + 0.710 / eta + 0.668 + 0.0636 * eta
}

/// [`fresnel_diffuse`] in f64, for the evaluator.
fn fresnel_diffuse_f64(eta: f64) -> f64 {
    -1.440 / (eta * eta) + 0.710 / eta + 0.668 + 0.0636 * eta
}

/// The dipole's total diffuse reflectance for reduced albedo α′ = σs′/(σs′ + σa):
/// Rd = (α′/2)(1 + e^(−(4/3)A√(3(1−α′)))) e^(−√(3(1−α′))), A = (1 + F_dr)/(1 − F_dr).
pub fn dipole_rd(sigma_s_prime: f32, sigma_a: f32, eta: f32) -> f32 {
    // In f64, with 1 − α′ = σa/σt′: the subtraction cancels badly in f32 for weakly
    // absorbing media (cream's red channel lost 2e-5).
    let (ss, sa) = (sigma_s_prime as f64, sigma_a as f64);
    let alpha = ss / (ss + sa);
    let fdr = fresnel_diffuse_f64(eta as f64);
    let a = (1.0 + fdr) / (1.0 - fdr);
    let s = (3.0 * sa / (ss + sa)).sqrt();
    (0.5 * alpha * (1.0 + (-(4.0 / 3.0) * a * s).exp()) * (-s).exp()) as f32
}

/// The medium a dipole profile describes (preset or explicit), `None` for other kinds.
pub fn dipole_medium(p: &Profile) -> Option<Medium> {
    match p {
        Profile::Dipole {
            preset: Some(name),
            eta,
            ..
        } => preset(name).map(|m| Medium {
            eta: eta.unwrap_or(m.eta),
            ..m
        }),
        Profile::Dipole {
            sigma_a: Some(a),
            sigma_s_prime: Some(s),
            eta,
            ..
        } => Some(Medium {
            sigma_s_prime: *s,
            sigma_a: *a,
            eta: eta.unwrap_or(DEFAULT_ETA),
        }),
        _ => None,
    }
}

/// Total diffuse reflectance ∫ R(r) 2πr dr per channel (dimensionless), for any profile.
/// A dipole's `scale` stretches lengths and leaves Rd unchanged. A table is constant at its
/// first value inside its first radius (as [`ProfileEval`] evaluates it).
pub fn total_reflectance(p: &Profile) -> [f32; 3] {
    match p {
        Profile::Dipole { .. } => match dipole_medium(p) {
            Some(m) => std::array::from_fn(|c| dipole_rd(m.sigma_s_prime[c], m.sigma_a[c], m.eta)),
            None => [0.0; 3],
        },
        // ∫ a e^(−b r) 2πr dr = 2π a / b².
        Profile::Exponentials { terms } => std::array::from_fn(|c| {
            terms
                .iter()
                .map(|t| 2.0 * std::f32::consts::PI * t.a[c] / (t.b[c] * t.b[c]))
                .sum()
        }),
        // Piecewise-linear R between samples: 2π r R(r) integrated exactly per segment.
        Profile::Table { radius_mm, values } => {
            let n = radius_mm.len().min(values.len());
            let table = Table {
                radius: radius_mm[..n].iter().map(|&r| r as f64).collect(),
                values: values[..n].iter().map(|v| v.map(f64::from)).collect(),
            };
            std::array::from_fn(|c| table.integral(c, 0.0, f64::INFINITY) as f32)
        }
    }
}

/// Why a profile cannot be evaluated. Each variant names the offending input.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProfileError {
    #[error("\"{0}\" is not a known dipole medium; use one of {list}", list = DIPOLE_PRESETS.join(", "))]
    UnknownPreset(String),
    #[error("a dipole needs `preset` or both `sigma_a` and `sigma_s_prime`")]
    MissingCoefficients,
    #[error("a dipole takes either `preset` or `sigma_a` and `sigma_s_prime`, not both")]
    PresetAndCoefficients,
    #[error("`{field}` = {value} is invalid: {why}")]
    Invalid {
        /// The field path inside the profile, e.g. `sigma_a[1]` or `terms[0].b[2]`.
        field: String,
        value: f64,
        why: String,
    },
}

fn invalid(
    field: impl Into<String>,
    value: impl Into<f64>,
    why: impl Into<String>,
) -> ProfileError {
    ProfileError::Invalid {
        field: field.into(),
        value: value.into(),
        why: why.into(),
    }
}

/// A profile prepared for evaluation in scene units: R(r) = k² R_mm(k r), k = unit_mm / s
/// for a translucency stretch s (see the module doc). Everything inside is f64 in mm.
#[derive(Debug, Clone, PartialEq)]
pub struct ProfileEval {
    shape: Shape,
    /// Millimetres of the mm-profile per scene unit: `unit_mm` / stretch.
    k: f64,
}

/// The mm-space profile, per channel.
#[derive(Debug, Clone, PartialEq)]
enum Shape {
    /// A sum of dipole-style point sources (the dipole: two; the multipole: 2(2n+1)).
    Poles([PoleSum; 3]),
    Table(Table),
    /// R(u) = Σ a e^(−b u), per channel.
    Exponentials(Vec<([f64; 3], [f64; 3])>),
}

/// R(u) = (α′/4π) Σⱼ sⱼ hⱼ (1 + σtr Dⱼ) e^(−σtr Dⱼ) / Dⱼ³, Dⱼ = √(u² + hⱼ²): every
/// source or image at signed height hⱼ from the surface the profile is read on, with sign
/// sⱼ = ±1 (real sources +, the negative images of the extrapolated boundaries −).
///
/// Since d/du [e^(−σD)/D] = −u (1 + σD) e^(−σD)/D³, each term integrates in closed form:
/// ∫₀^ρ h (1 + σD) e^(−σD)/D³ 2πu du = 2π h [e^(−σ|h|)/|h| − e^(−σD(ρ))/D(ρ)],
/// so every integral of a pole sum is exact (no quadrature), and the tail beyond ρ is
/// 2π h e^(−σD(ρ))/D(ρ). For Jensen's dipole the total is
/// (α′/2)(e^(−σtr z_r) + e^(−σtr z_v)) = [`dipole_rd`].
#[derive(Debug, Clone, PartialEq)]
struct PoleSum {
    /// Reduced albedo α′ = σs′/σt′.
    alpha: f64,
    /// Effective transport coefficient σtr = √(3 σa σt′), mm⁻¹.
    sigma_tr: f64,
    /// (sⱼ, hⱼ): sign and height in mm. No hⱼ is 0.
    poles: Vec<(f64, f64)>,
}

impl PoleSum {
    fn eval(&self, u: f64) -> f64 {
        let sum: f64 = self
            .poles
            .iter()
            .map(|&(s, h)| {
                let d = (u * u + h * h).sqrt();
                s * h * (1.0 + self.sigma_tr * d) * (-self.sigma_tr * d).exp() / (d * d * d)
            })
            .sum();
        self.alpha / (4.0 * PI) * sum
    }

    /// ∫₀^ρ R 2πu du = (α′/2) Σ s h [e^(−σ|h|)/|h| − e^(−σD)/D].
    fn within(&self, rho: f64) -> f64 {
        if rho.is_infinite() {
            return self.total();
        }
        let sum: f64 = self
            .poles
            .iter()
            .map(|&(s, h)| {
                let d = (rho * rho + h * h).sqrt();
                let ah = h.abs();
                s * h * ((-self.sigma_tr * ah).exp() / ah - (-self.sigma_tr * d).exp() / d)
            })
            .sum();
        0.5 * self.alpha * sum
    }

    /// ∫_ρ^∞ R 2πu du = (α′/2) Σ s h e^(−σD)/D.
    fn tail(&self, rho: f64) -> f64 {
        if rho.is_infinite() {
            return 0.0;
        }
        let sum: f64 = self
            .poles
            .iter()
            .map(|&(s, h)| {
                let d = (rho * rho + h * h).sqrt();
                s * h * (-self.sigma_tr * d).exp() / d
            })
            .sum();
        0.5 * self.alpha * sum
    }

    /// ∫₀^∞ R 2πu du = (α′/2) Σ s sgn(h) e^(−σ|h|).
    fn total(&self) -> f64 {
        let sum: f64 = self
            .poles
            .iter()
            .map(|&(s, h)| s * h.signum() * (-self.sigma_tr * h.abs()).exp())
            .sum();
        0.5 * self.alpha * sum
    }
}

/// A piecewise-linear table in mm: constant `values[0]` on [0, radius[0]], linear between
/// samples, zero beyond the last radius.
#[derive(Debug, Clone, PartialEq)]
struct Table {
    radius: Vec<f64>,
    values: Vec<[f64; 3]>,
}

impl Table {
    fn eval(&self, u: f64) -> [f64; 3] {
        let (r, v) = (&self.radius, &self.values);
        let Some(&last) = r.last() else {
            return [0.0; 3];
        };
        if u <= r[0] {
            return v[0];
        }
        if u > last {
            return [0.0; 3];
        }
        // r[k−1] < u ≤ r[k].
        let k = r.partition_point(|&x| x < u);
        let t = (u - r[k - 1]) / (r[k] - r[k - 1]);
        std::array::from_fn(|c| v[k - 1][c] + t * (v[k][c] - v[k - 1][c]))
    }

    /// ∫_a^b R(u) 2πu du for channel c (a ≤ b; b may be ∞), exact for the linear pieces.
    fn integral(&self, c: usize, a: f64, b: f64) -> f64 {
        let (r, v) = (&self.radius, &self.values);
        if r.is_empty() || b <= a {
            return 0.0;
        }
        // The disc inside the first radius: π (hi² − lo²) v₀.
        let mut sum = {
            let (lo, hi) = (a.min(r[0]), b.min(r[0]));
            PI * (hi * hi - lo * lo) * v[0][c]
        };
        for k in 1..r.len() {
            let (r0, r1) = (r[k - 1], r[k]);
            let (lo, hi) = (a.max(r0), b.min(r1));
            if hi <= lo {
                continue;
            }
            // R = v0 + slope (u − r0) on [r0, r1]; ∫ u R du = (v0 − slope r0) u²/2 + slope u³/3.
            let (v0, v1) = (v[k - 1][c], v[k][c]);
            let slope = (v1 - v0) / (r1 - r0);
            let f = |u: f64| (v0 - slope * r0) * u * u / 2.0 + slope * u * u * u / 3.0;
            sum += 2.0 * PI * (f(hi) - f(lo));
        }
        sum
    }
}

/// ∫_a^b a e^(−b u) 2πu du pieces: the antiderivative is −(2πa/b²) e^(−bu)(1 + bu), so
/// ∫₀^ρ = (2πa/b²)[1 − e^(−bρ)(1 + bρ)] and ∫_ρ^∞ = (2πa/b²) e^(−bρ)(1 + bρ).
fn exp_tail(a: f64, b: f64, rho: f64) -> f64 {
    if rho.is_infinite() {
        return 0.0;
    }
    2.0 * PI * a / (b * b) * (-b * rho).exp() * (1.0 + b * rho)
}

fn check_medium(m: &Medium) -> Result<(), ProfileError> {
    for c in 0..3 {
        let (a, s) = (m.sigma_a[c], m.sigma_s_prime[c]);
        if !(a.is_finite() && a >= 0.0) {
            return Err(invalid(
                format!("sigma_a[{c}]"),
                a,
                "must be finite and ≥ 0 (mm⁻¹)",
            ));
        }
        if !(s.is_finite() && s >= 0.0) {
            return Err(invalid(
                format!("sigma_s_prime[{c}]"),
                s,
                "must be finite and ≥ 0 (mm⁻¹)",
            ));
        }
        if a + s <= 0.0 {
            return Err(invalid(
                format!("sigma_s_prime[{c}]"),
                s,
                "sigma_a + sigma_s_prime must be > 0",
            ));
        }
    }
    if !(m.eta.is_finite() && (1.0..=3.0).contains(&m.eta)) {
        return Err(invalid("eta", m.eta, "must be in [1, 3]"));
    }
    Ok(())
}

/// Per channel: α′, σtr, z_r = 1/σt′ (the depth of the real source, one mean free path) and
/// the extrapolated-boundary distance z_b = 2AD, D = 1/(3σt′), A = (1 + F_dr)/(1 − F_dr).
/// Jensen's virtual source sits at z_v = −(z_r + 2z_b) = −z_r(1 + 4A/3).
fn medium_channel(m: &Medium, c: usize) -> (f64, f64, f64, f64) {
    let (sa, ss) = (m.sigma_a[c] as f64, m.sigma_s_prime[c] as f64);
    let st = sa + ss;
    let fdr = fresnel_diffuse_f64(m.eta as f64);
    let a = (1.0 + fdr) / (1.0 - fdr);
    let d = 1.0 / (3.0 * st);
    (ss / st, (3.0 * sa * st).sqrt(), 1.0 / st, 2.0 * a * d)
}

/// Jensen et al. 2001's dipole:
/// R_d(r) = (α′/4π)[z_r(σtr d_r + 1)e^(−σtr d_r)/d_r³ + z_v(σtr d_v + 1)e^(−σtr d_v)/d_v³],
/// d_{r,v} = √(r² + z_{r,v}²), z_v = z_r + 2z_b — two positive poles (the virtual source is
/// negative and below the surface: −(−z_v) = +z_v).
fn dipole_poles(m: &Medium) -> [PoleSum; 3] {
    std::array::from_fn(|c| {
        let (alpha, sigma_tr, zr, zb) = medium_channel(m, c);
        PoleSum {
            alpha,
            sigma_tr,
            poles: vec![(1.0, zr), (1.0, zr + 2.0 * zb)],
        }
    })
}

impl ProfileEval {
    /// Prepares `profile` for a scene whose unit is `unit_mm` millimetres (1 for a mm scene,
    /// 1000 for metres). A dipole's `scale` stretches its mean free paths (σa and σs′ are
    /// divided by it). Errors name an unknown preset or the first invalid coefficient; the
    /// checks repeat the scene validator's so a profile built in code is safe too.
    pub fn new(profile: &Profile, unit_mm: f64) -> Result<Self, ProfileError> {
        if !(unit_mm.is_finite() && unit_mm > 0.0) {
            return Err(invalid("unit_mm", unit_mm, "must be finite and > 0"));
        }
        let (shape, stretch) = match profile {
            Profile::Dipole {
                preset: name,
                sigma_a,
                sigma_s_prime,
                eta,
                scale,
            } => {
                let medium = match (name, sigma_a, sigma_s_prime) {
                    (Some(name), None, None) => {
                        let m = preset(name)
                            .ok_or_else(|| ProfileError::UnknownPreset(name.clone()))?;
                        Medium {
                            eta: eta.unwrap_or(m.eta),
                            ..m
                        }
                    }
                    (None, Some(a), Some(s)) => Medium {
                        sigma_s_prime: *s,
                        sigma_a: *a,
                        eta: eta.unwrap_or(DEFAULT_ETA),
                    },
                    (Some(_), _, _) => return Err(ProfileError::PresetAndCoefficients),
                    _ => return Err(ProfileError::MissingCoefficients),
                };
                check_medium(&medium)?;
                let s = scale.unwrap_or(1.0);
                if !(s.is_finite() && s > 0.0) {
                    return Err(invalid("scale", s, "must be finite and > 0"));
                }
                (Shape::Poles(dipole_poles(&medium)), s as f64)
            }
            Profile::Table { radius_mm, values } => {
                if radius_mm.len() < 2 {
                    return Err(invalid(
                        "radius_mm",
                        radius_mm.len() as f64,
                        "needs at least two radii",
                    ));
                }
                if radius_mm.len() != values.len() {
                    return Err(invalid(
                        "values",
                        values.len() as f64,
                        format!(
                            "has {} entries but radius_mm has {}",
                            values.len(),
                            radius_mm.len()
                        ),
                    ));
                }
                for (k, &r) in radius_mm.iter().enumerate() {
                    if !(r.is_finite() && r >= 0.0) {
                        return Err(invalid(
                            format!("radius_mm[{k}]"),
                            r,
                            "must be finite and ≥ 0",
                        ));
                    }
                    if k > 0 && r <= radius_mm[k - 1] {
                        return Err(invalid(
                            format!("radius_mm[{k}]"),
                            r,
                            "must be larger than the radius before it",
                        ));
                    }
                }
                for (k, v) in values.iter().enumerate() {
                    for (c, &x) in v.iter().enumerate() {
                        if !(x.is_finite() && x >= 0.0) {
                            return Err(invalid(
                                format!("values[{k}][{c}]"),
                                x,
                                "must be finite and ≥ 0 (mm⁻²)",
                            ));
                        }
                    }
                }
                let table = Table {
                    radius: radius_mm.iter().map(|&r| r as f64).collect(),
                    values: values.iter().map(|v| v.map(f64::from)).collect(),
                };
                (Shape::Table(table), 1.0)
            }
            Profile::Exponentials { terms } => {
                let mut out = Vec::with_capacity(terms.len());
                for (k, t) in terms.iter().enumerate() {
                    for c in 0..3 {
                        if !(t.a[c].is_finite() && t.a[c] >= 0.0) {
                            return Err(invalid(
                                format!("terms[{k}].a[{c}]"),
                                t.a[c],
                                "must be finite and ≥ 0 (mm⁻²)",
                            ));
                        }
                        if !(t.b[c].is_finite() && t.b[c] > 0.0) {
                            return Err(invalid(
                                format!("terms[{k}].b[{c}]"),
                                t.b[c],
                                "must be finite and > 0 (mm⁻¹; the profile must fall off)",
                            ));
                        }
                    }
                    out.push((t.a.map(f64::from), t.b.map(f64::from)));
                }
                (Shape::Exponentials(out), 1.0)
            }
        };
        Ok(Self {
            shape,
            k: unit_mm / stretch,
        })
    }

    /// The same profile with its translucency scaled: mean free paths (and, for a table or
    /// exponentials, the radius axis) × `scale`, R_s(r) = R(r/s)/s², which keeps the total
    /// reflectance. It composes with the scene file's dipole `scale` (they multiply) and
    /// with earlier calls. For a [`multipole`] slab the thickness stretches too (a
    /// similarity); to change translucency at a fixed thickness, build it anew.
    ///
    /// # Panics
    /// If `scale` is not finite and > 0.
    pub fn scaled(&self, scale: f32) -> Self {
        assert!(
            scale.is_finite() && scale > 0.0,
            "translucency scale must be finite and > 0, got {scale}"
        );
        Self {
            shape: self.shape.clone(),
            k: self.k / scale as f64,
        }
    }

    /// R(r) per channel, per unit area in scene units (scene-unit⁻²), at distance `r` ≥ 0 in
    /// scene units: R_mm(r k) k².
    pub fn eval(&self, r: f32) -> [f32; 3] {
        let u = r.max(0.0) as f64 * self.k;
        let k2 = self.k * self.k;
        self.eval_mm(u).map(|x| (x * k2) as f32)
    }

    /// ∫₀^∞ R(r) 2πr dr per channel (dimensionless, independent of units and stretch).
    pub fn total_reflectance(&self) -> [f32; 3] {
        std::array::from_fn(|c| self.total_mm(c) as f32)
    }

    /// ∫₀^ρ R(r) 2πr dr per channel: the fraction of the light entering at a point that
    /// leaves within radius `rho` (scene units) of it. Exact (closed form) for every kind;
    /// `rho` = ∞ gives the total.
    pub fn reflectance_within(&self, rho: f32) -> [f32; 3] {
        let u = rho.max(0.0) as f64 * self.k;
        std::array::from_fn(|c| self.within_mm(c, u) as f32)
    }

    /// The smallest radius ρ (scene units) outside which every channel re-emits at most
    /// `fraction` of its total: ∫_ρ^∞ R 2πr dr ≤ fraction · ∫₀^∞ R 2πr dr, the max over
    /// channels.
    ///
    /// Energy-based rather than "R(ρ) < fraction · R(0)": what truncating S throws away is
    /// the energy of the tail, and for the dipole the two differ a lot — R(0) is finite
    /// (≈ α′/(2π z_r²)) and large for a dense medium while the tail e^(−σtr r)/r carries
    /// most of the energy of a translucent one. The tail is exact (closed form), and the
    /// bisection keeps the side that satisfies the bound, so the result never leaves more
    /// than `fraction` outside. `fraction` ≥ 1 gives 0; `fraction` ≤ 0 gives the support
    /// (the last radius of a table, ∞ otherwise). Channels with zero total are ignored.
    pub fn truncation_radius(&self, fraction: f32) -> f32 {
        let f = fraction as f64;
        if f.is_nan() || f <= 0.0 {
            return match &self.shape {
                Shape::Table(t) => (t.radius.last().copied().unwrap_or(0.0) / self.k) as f32,
                _ => f32::INFINITY,
            };
        }
        let mut rho_mm = 0.0f64;
        for c in 0..3 {
            let total = self.total_mm(c);
            if total <= 0.0 {
                continue;
            }
            let target = f * total;
            if self.tail_mm(c, 0.0) <= target {
                continue;
            }
            // Bracket: tail(lo) > target ≥ tail(hi), doubling from a length far below any
            // physical one, then bisect (the tail is monotone for R ≥ 0).
            let (mut lo, mut hi) = (0.0, 1e-9);
            while self.tail_mm(c, hi) > target {
                lo = hi;
                hi *= 2.0;
                if hi > 1e300 {
                    return f32::INFINITY;
                }
            }
            for _ in 0..200 {
                let mid = 0.5 * (lo + hi);
                if mid <= lo || mid >= hi {
                    break;
                }
                if self.tail_mm(c, mid) > target {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            rho_mm = rho_mm.max(hi);
        }
        let rho = rho_mm / self.k;
        // Round up so that the f32 radius still satisfies the bound.
        let r = rho as f32;
        if (r as f64) < rho { r.next_up() } else { r }
    }

    fn eval_mm(&self, u: f64) -> [f64; 3] {
        match &self.shape {
            Shape::Poles(p) => std::array::from_fn(|c| p[c].eval(u)),
            Shape::Table(t) => t.eval(u),
            Shape::Exponentials(terms) => {
                std::array::from_fn(|c| terms.iter().map(|(a, b)| a[c] * (-b[c] * u).exp()).sum())
            }
        }
    }

    fn total_mm(&self, c: usize) -> f64 {
        match &self.shape {
            Shape::Poles(p) => p[c].total(),
            Shape::Table(t) => t.integral(c, 0.0, f64::INFINITY),
            Shape::Exponentials(terms) => terms
                .iter()
                .map(|(a, b)| 2.0 * PI * a[c] / (b[c] * b[c]))
                .sum(),
        }
    }

    fn within_mm(&self, c: usize, u: f64) -> f64 {
        match &self.shape {
            Shape::Poles(p) => p[c].within(u),
            Shape::Table(t) => t.integral(c, 0.0, u),
            Shape::Exponentials(terms) => terms
                .iter()
                .map(|(a, b)| 2.0 * PI * a[c] / (b[c] * b[c]) - exp_tail(a[c], b[c], u))
                .sum(),
        }
    }

    fn tail_mm(&self, c: usize, u: f64) -> f64 {
        match &self.shape {
            Shape::Poles(p) => p[c].tail(u),
            Shape::Table(t) => t.integral(c, u, f64::INFINITY),
            Shape::Exponentials(terms) => terms.iter().map(|(a, b)| exp_tail(a[c], b[c], u)).sum(),
        }
    }
}

/// Donner and Jensen 2005, "Light Diffusion in Multi-Layered Translucent Materials": the
/// reflectance and transmittance profiles of a slab of `thickness_mm` of `medium` (the same
/// η on both faces), for a scene whose unit is `unit_mm` millimetres.
///
/// The dipole is mirrored in both extrapolated boundaries (at −z_b and d + z_b) repeatedly:
/// for i = −n..=n, with l = 1/σt′ and z_b = 2AD,
///   z_{r,i} = 2i(d + 2z_b) + l,  z_{v,i} = 2i(d + 2z_b) − l − 2z_b,
///   R(r) = (α′/4π) Σᵢ [z_{r,i}(1 + σtr d_{r,i})e^(−σtr d_{r,i})/d_{r,i}³
///                     − z_{v,i}(1 + σtr d_{v,i})e^(−σtr d_{v,i})/d_{v,i}³],
///     d_{·,i} = √(r² + z_{·,i}²);
///   T(r) = the same with heights (d − z_{r,i}) and (d − z_{v,i}) from the far face,
///     d_{·,i} = √(r² + (d − z_{·,i})²).
/// i = 0 of R is Jensen's dipole. The slab must be thicker than 1/σt′ in every channel
/// (else the source lies outside it): an error names the thickness and the channel. `poles` is n (2n + 1 dipoles); the image series converges
/// like e^(−2nσtr(d + 2z_b)), so weakly absorbing thin slabs need more (n ≈ 10 is usual).
/// The totals over the plane are exact for the poles kept and converge to the 1-D slab
/// solution α′ cosh(σtr z_b) sinh(σtr(L − z_b − l)) / sinh(σtr L), L = d + 2z_b (and
/// sinh(σtr(z_b + l)) in place of the middle factor for T).
pub fn multipole(
    medium: &Medium,
    thickness_mm: f32,
    poles: u32,
    unit_mm: f64,
) -> Result<(ProfileEval, ProfileEval), ProfileError> {
    check_medium(medium)?;
    if !(thickness_mm.is_finite() && thickness_mm > 0.0) {
        return Err(invalid(
            "thickness_mm",
            thickness_mm,
            "must be finite and > 0",
        ));
    }
    if !(unit_mm.is_finite() && unit_mm > 0.0) {
        return Err(invalid("unit_mm", unit_mm, "must be finite and > 0"));
    }
    let d = thickness_mm as f64;
    // The real source sits one reduced mean free path deep; in a thinner slab it would lie
    // outside the medium and T would come out negative (diffusion is no model there anyway).
    for c in 0..3 {
        let l = 1.0 / (medium.sigma_a[c] as f64 + medium.sigma_s_prime[c] as f64);
        if d <= l {
            return Err(invalid(
                "thickness_mm",
                thickness_mm,
                format!(
                    "must exceed the reduced mean free path 1/σt′ = {l:.4} mm of channel {c}, \
                     the depth of the diffusion source"
                ),
            ));
        }
    }
    let n = poles as i64;
    let per_channel: [(PoleSum, PoleSum); 3] = std::array::from_fn(|c| {
        let (alpha, sigma_tr, l, zb) = medium_channel(medium, c);
        let (mut rp, mut tp) = (Vec::new(), Vec::new());
        for i in -n..=n {
            let shift = 2.0 * i as f64 * (d + 2.0 * zb);
            let (zr, zv) = (shift + l, shift - l - 2.0 * zb);
            rp.extend([(1.0, zr), (-1.0, zv)]);
            tp.extend([(1.0, d - zr), (-1.0, d - zv)]);
        }
        // A pole at height 0 contributes nothing (its weight is its height); keeping it
        // would only divide 0 by 0.
        rp.retain(|p| p.1 != 0.0);
        tp.retain(|p| p.1 != 0.0);
        let sum = |poles| PoleSum {
            alpha,
            sigma_tr,
            poles,
        };
        (sum(rp), sum(tp))
    });
    let [(r0, t0), (r1, t1), (r2, t2)] = per_channel;
    let eval = |p: [PoleSum; 3]| ProfileEval {
        shape: Shape::Poles(p),
        k: unit_mm,
    };
    Ok((eval([r0, r1, r2]), eval([t0, t1, t2])))
}
#[cfg(test)]
mod tests {
    use super::*;
    use translux_proto::scene::{DIPOLE_PRESETS, ExpTerm};

    /// Jensen et al. 2001, Table 1: the diffuse reflectance Rd each medium's coefficients give.
    const PUBLISHED_RD: [(&str, [f32; 3]); 11] = [
        ("apple", [0.85, 0.84, 0.53]),
        ("chicken1", [0.31, 0.15, 0.10]),
        ("chicken2", [0.32, 0.16, 0.10]),
        ("cream", [0.98, 0.90, 0.73]),
        ("ketchup", [0.16, 0.01, 0.00]),
        ("marble", [0.83, 0.79, 0.75]),
        ("potato", [0.77, 0.62, 0.21]),
        ("skimmilk", [0.81, 0.81, 0.69]),
        ("skin1", [0.44, 0.22, 0.13]),
        ("skin2", [0.63, 0.44, 0.34]),
        ("wholemilk", [0.91, 0.88, 0.76]),
    ];

    fn dipole(name: &str) -> Profile {
        Profile::Dipole {
            preset: Some(name.into()),
            sigma_a: None,
            sigma_s_prime: None,
            eta: None,
            scale: None,
        }
    }

    fn explicit(sigma_a: [f32; 3], sigma_s_prime: [f32; 3], eta: f32) -> Profile {
        Profile::Dipole {
            preset: None,
            sigma_a: Some(sigma_a),
            sigma_s_prime: Some(sigma_s_prime),
            eta: Some(eta),
            scale: None,
        }
    }

    fn table() -> Profile {
        Profile::Table {
            radius_mm: vec![0.5, 1.0, 2.0, 4.0],
            values: vec![
                [4.0, 1.0, 0.5],
                [2.0, 1.0, 0.4],
                [1.0, 0.5, 0.2],
                [0.0, 0.25, 0.1],
            ],
        }
    }

    fn exponentials() -> Profile {
        Profile::Exponentials {
            terms: vec![
                ExpTerm {
                    a: [0.3, 0.2, 0.1],
                    b: [2.0, 3.0, 5.0],
                },
                ExpTerm {
                    a: [0.02, 0.01, 0.005],
                    b: [0.5, 0.8, 1.5],
                },
            ],
        }
    }

    fn rel(a: f64, b: f64) -> f64 {
        (a - b).abs() / b.abs().max(1e-300)
    }

    /// Composite trapezoid of f on [a, b] with n intervals.
    fn trapezoid(f: impl Fn(f64) -> f64, a: f64, b: f64, n: usize) -> f64 {
        let h = (b - a) / n as f64;
        let inner: f64 = (1..n).map(|i| f(a + i as f64 * h)).sum();
        h * (0.5 * f(a) + inner + 0.5 * f(b))
    }

    /// ∫ eval(r) 2πr dr per channel over [a, b] (scene units), by trapezoid on the f32 API.
    fn quad_eval(ev: &ProfileEval, a: f64, b: f64, n: usize) -> [f64; 3] {
        std::array::from_fn(|c| trapezoid(|r| ev.eval(r as f32)[c] as f64 * 2.0 * PI * r, a, b, n))
    }

    /// Jensen et al. 2001, eq. 4 as printed, typed independently in f64:
    /// R_d(r) = α′/(4π) [z_r(σtr + 1/d_r) e^(−σtr d_r)/d_r² + z_v(σtr + 1/d_v) e^(−σtr d_v)/d_v²],
    /// z_r = 1/σt′, z_v = z_r + 4AD, D = 1/(3σt′).
    fn jensen_reference(sigma_s_prime: f64, sigma_a: f64, eta: f64, r: f64) -> f64 {
        let st = sigma_s_prime + sigma_a;
        let alpha = sigma_s_prime / st;
        let s_tr = (3.0 * sigma_a * st).sqrt();
        let fdr = -1.440 / eta.powi(2) + 0.710 / eta + 0.668 + 0.0636 * eta;
        let big_a = (1.0 + fdr) / (1.0 - fdr);
        let diffusion = 1.0 / (3.0 * st);
        let zr = 1.0 / st;
        let zv = zr + 4.0 * big_a * diffusion;
        let term = |z: f64| {
            let dist = r.hypot(z);
            z * (s_tr + 1.0 / dist) * (-s_tr * dist).exp() / (dist * dist)
        };
        alpha / (4.0 * PI) * (term(zr) + term(zv))
    }

    #[test]
    fn every_preset_exists_and_matches_published_rd() {
        for name in DIPOLE_PRESETS {
            assert!(preset(name).is_some(), "{name}");
        }
        for (name, rd) in PUBLISHED_RD {
            let got = total_reflectance(&dipole(name));
            for c in 0..3 {
                if (name, c) == ("chicken1", 2) {
                    // The table's 0.10 does not follow from its own coefficients
                    // (σs′ 0.38, σa 0.19, η 1.3 give 0.126 through the same formula that
                    // reproduces the other 32 entries); check the formula's value instead.
                    assert!((got[c] - 0.126).abs() < 0.002, "{}", got[c]);
                    continue;
                }
                // The table prints two decimals.
                assert!(
                    (got[c] - rd[c]).abs() <= 0.015,
                    "{name}[{c}]: {} vs {}",
                    got[c],
                    rd[c]
                );
            }
        }
    }

    #[test]
    fn exponential_and_table_totals() {
        let p = Profile::Exponentials {
            terms: vec![ExpTerm {
                a: [0.1, 0.2, 0.3],
                b: [1.0, 2.0, 3.0],
            }],
        };
        let r = total_reflectance(&p);
        let tau = 2.0 * std::f32::consts::PI;
        assert!((r[0] - tau * 0.1).abs() < 1e-5 && (r[2] - tau * 0.3 / 9.0).abs() < 1e-5);
        // A table sampling e^(−r) finely integrates to 2π·∫ r e^(−r) dr ≈ 2π.
        let radius_mm: Vec<f32> = (0..=4000).map(|k| k as f32 * 0.01).collect();
        let values = radius_mm.iter().map(|r| [(-r).exp(); 3]).collect();
        let t = total_reflectance(&Profile::Table { radius_mm, values });
        assert!((t[1] - tau).abs() / tau < 1e-3, "{t:?}");
    }

    #[test]
    fn dipole_eval_matches_an_independent_formula() {
        let radii = [0.0, 0.05, 0.3, 1.0, 2.5, 7.0, 20.0];
        let mut cases: Vec<(Profile, Medium)> = ["marble", "skin1"]
            .iter()
            .map(|n| (dipole(n), preset(n).unwrap()))
            .collect();
        let (sa, ss) = ([0.05, 0.2, 0.01], [1.0, 0.5, 3.0]);
        cases.push((
            explicit(sa, ss, 1.4),
            Medium {
                sigma_s_prime: ss,
                sigma_a: sa,
                eta: 1.4,
            },
        ));
        for (p, m) in cases {
            let ev = ProfileEval::new(&p, 1.0).unwrap();
            for r in radii {
                for (c, got) in ev.eval(r as f32).into_iter().enumerate() {
                    let want = jensen_reference(
                        m.sigma_s_prime[c] as f64,
                        m.sigma_a[c] as f64,
                        m.eta as f64,
                        r,
                    );
                    assert!(want > 0.0);
                    assert!(
                        rel(got as f64, want) < 2e-6,
                        "{p:?} r {r} [{c}]: {got} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn dipole_marble_spot_values() {
        // Literal values of the formula above for marble's red channel (σs′ 2.19, σa 0.0021,
        // η 1.5), computed once outside this code base, so that a shared typo in both
        // evaluations would still show.
        let ev = ProfileEval::new(&dipole("marble"), 1.0).unwrap();
        for (r, want) in [
            (0.0, 0.390_746_515),
            (1.0, 0.034_846_692),
            (5.0, 0.001_266_692_6),
        ] {
            let got = ev.eval(r)[0] as f64;
            assert!(rel(got, want) < 1e-5, "r {r}: {got} vs {want}");
        }
    }

    #[test]
    fn within_is_the_integral_of_eval() {
        // d/dρ ∫₀^ρ R 2πr dr = 2πρ R(ρ), for every kind (f64 internals, central differences).
        let medium = preset("skin2").unwrap();
        let (_, slab_t) = multipole(&medium, 1.5, 10, 1.0).unwrap();
        let kinds = [
            ProfileEval::new(&dipole("skin2"), 1.0).unwrap(),
            ProfileEval::new(&table(), 1.0).unwrap(),
            ProfileEval::new(&exponentials(), 1.0).unwrap(),
            slab_t,
        ];
        for ev in &kinds {
            for rho in [0.1, 0.7, 1.3, 3.0, 6.0] {
                let h = 1e-5;
                let r = ev.eval_mm(rho);
                for (c, rc) in r.iter().enumerate() {
                    let d = (ev.within_mm(c, rho + h) - ev.within_mm(c, rho - h)) / (2.0 * h);
                    let want = 2.0 * PI * rho * rc;
                    assert!(
                        (d - want).abs() <= 1e-6 * want.abs().max(1e-3),
                        "{:?} ρ {rho} [{c}]: {d} vs {want}",
                        ev.shape
                    );
                    // The tail is the complement.
                    let sum = ev.within_mm(c, rho) + ev.tail_mm(c, rho);
                    assert!(rel(sum, ev.total_mm(c)) < 1e-12);
                }
            }
        }
    }

    #[test]
    fn dipole_totals_match_closed_form_and_quadrature_for_every_preset() {
        let mut worst = 0.0f64;
        for name in DIPOLE_PRESETS {
            let m = preset(name).unwrap();
            let ev = ProfileEval::new(&dipole(name), 1.0).unwrap();
            let total = ev.total_reflectance();
            // Fine grid near the peak, coarser in the exponential tail (mm).
            let near = quad_eval(&ev, 0.0, 10.0, 200_000);
            let far = quad_eval(&ev, 10.0, 3000.0, 300_000);
            for c in 0..3 {
                let closed = dipole_rd(m.sigma_s_prime[c], m.sigma_a[c], m.eta) as f64;
                let albedo = total_reflectance(&dipole(name))[c] as f64;
                assert!(rel(total[c] as f64, albedo) < 1e-6, "{name}[{c}]");
                assert!(
                    rel(total[c] as f64, closed) < 1e-3,
                    "{name}[{c}]: {} vs {closed}",
                    total[c]
                );
                let quad = near[c] + far[c];
                worst = worst.max(rel(quad, closed));
                assert!(
                    rel(quad, closed) < 5e-3,
                    "{name}[{c}]: ∫ = {quad} vs {closed}"
                );
                let within = ev.reflectance_within(f32::INFINITY)[c];
                assert_eq!(within, total[c]);
                let far = ev.reflectance_within(1e5)[c] as f64;
                assert!(rel(far, closed) < 1e-5, "{name}[{c}]: {far} vs {closed}");
                assert!(rel(far, total[c] as f64) < 1e-6, "{name}[{c}]");
            }
        }
        eprintln!("dipole: worst relative gap of ∫ eval vs dipole_rd: {worst:.2e}");
    }

    #[test]
    fn units_mm_and_metres_agree() {
        let mm = ProfileEval::new(&dipole("marble"), 1.0).unwrap();
        let m = ProfileEval::new(&dipole("marble"), 1000.0).unwrap();
        for r_m in [0.0f32, 1e-4, 5e-4, 2e-3, 1e-2, 5e-2] {
            let (a, b) = (m.eval(r_m), mm.eval(r_m * 1000.0));
            let (wa, wb) = (
                m.reflectance_within(r_m),
                mm.reflectance_within(r_m * 1000.0),
            );
            for c in 0..3 {
                assert!(
                    rel(a[c] as f64, b[c] as f64 * 1e6) < 1e-5,
                    "{r_m}: {a:?} {b:?}"
                );
                assert!(rel(wa[c] as f64, wb[c] as f64) < 1e-5 || r_m == 0.0);
            }
        }
        assert_eq!(m.total_reflectance(), mm.total_reflectance());
        let (tm, tmm) = (m.truncation_radius(1e-3), mm.truncation_radius(1e-3));
        assert!(
            rel(tm as f64 * 1000.0, tmm as f64) < 1e-5,
            "{tm} m vs {tmm} mm"
        );
        // A marble block in a metre-scale scene neither goes black nor white: the profile,
        // integrated in metres, still re-emits marble's Rd.
        let near = quad_eval(&m, 0.0, 0.01, 200_000);
        let far = quad_eval(&m, 0.01, 3.0, 300_000);
        let total = m.total_reflectance();
        for c in 0..3 {
            assert!(rel(near[c] + far[c], total[c] as f64) < 5e-3, "{c}");
        }
    }

    #[test]
    fn scaled_stretches_and_keeps_energy() {
        for p in [dipole("marble"), table(), exponentials()] {
            let ev = ProfileEval::new(&p, 1.0).unwrap();
            for s in [0.25f32, 3.0] {
                let es = ev.scaled(s);
                let (t0, t1) = (ev.total_reflectance(), es.total_reflectance());
                for c in 0..3 {
                    assert!(rel(t1[c] as f64, t0[c] as f64) < 1e-6);
                }
                // R_s(s r) = R(r)/s², within_s(s ρ) = within(ρ). Radii avoid the table's knots.
                for r in [0.0f32, 0.3, 0.77, 1.45, 2.9, 6.0] {
                    let (a, b) = (es.eval(s * r), ev.eval(r));
                    let (wa, wb) = (es.reflectance_within(s * r), ev.reflectance_within(r));
                    for c in 0..3 {
                        let want = b[c] as f64 / (s as f64 * s as f64);
                        assert!(
                            (a[c] as f64 - want).abs() <= 1e-5 * want.max(1e-6),
                            "{p:?} s {s} r {r}: {a:?} vs {b:?}"
                        );
                        assert!((wa[c] - wb[c]).abs() <= 1e-6 * wb[c].max(1e-3));
                    }
                }
            }
            let twice = ev.scaled(2.0).scaled(1.5);
            let once = ev.scaled(3.0);
            assert!(rel(twice.k, once.k) < 1e-12);
        }
        // The scene file's `scale` is the same stretch, and dividing σa and σs′ by s is too.
        let m = preset("marble").unwrap();
        let knob = Profile::Dipole {
            preset: Some("marble".into()),
            sigma_a: None,
            sigma_s_prime: None,
            eta: None,
            scale: Some(2.0),
        };
        let by_knob = ProfileEval::new(&knob, 1.0).unwrap();
        let by_method = ProfileEval::new(&dipole("marble"), 1.0)
            .unwrap()
            .scaled(2.0);
        let by_sigma = ProfileEval::new(
            &explicit(
                m.sigma_a.map(|x| x / 2.0),
                m.sigma_s_prime.map(|x| x / 2.0),
                m.eta,
            ),
            1.0,
        )
        .unwrap();
        let knob_and_method = by_knob.scaled(1.5);
        let by_three = ProfileEval::new(&dipole("marble"), 1.0)
            .unwrap()
            .scaled(3.0);
        for r in [0.0f32, 0.5, 2.0, 9.0] {
            let (a, b, c3) = (by_knob.eval(r), by_method.eval(r), by_sigma.eval(r));
            let (d, e) = (knob_and_method.eval(r), by_three.eval(r));
            for c in 0..3 {
                assert_eq!(a[c], b[c]);
                assert!(
                    rel(a[c] as f64, c3[c] as f64) < 1e-5,
                    "{r}: {a:?} vs {c3:?}"
                );
                assert!(rel(d[c] as f64, e[c] as f64) < 1e-6);
            }
        }
    }

    #[test]
    fn reflectance_within_is_monotone_and_reaches_the_total() {
        let medium = preset("apple").unwrap();
        let (slab_r, slab_t) = multipole(&medium, 2.0, 20, 1.0).unwrap();
        let kinds = [
            ProfileEval::new(&dipole("marble"), 1.0).unwrap(),
            ProfileEval::new(&dipole("ketchup"), 1.0).unwrap(),
            ProfileEval::new(&table(), 1.0).unwrap(),
            ProfileEval::new(&exponentials(), 1.0).unwrap(),
            slab_r,
            slab_t,
        ];
        for ev in &kinds {
            let total = ev.total_reflectance();
            assert_eq!(ev.reflectance_within(0.0), [0.0; 3]);
            let mut prev = [0.0f32; 3];
            for k in 0..=160 {
                let rho = 1e-4f32 * 10f32.powf(k as f32 / 20.0);
                let w = ev.reflectance_within(rho);
                for c in 0..3 {
                    assert!(w[c] >= prev[c], "{:?} ρ {rho} [{c}]", ev.shape);
                    assert!(w[c] <= total[c] * (1.0 + 1e-6));
                }
                prev = w;
            }
            for c in 0..3 {
                assert!(
                    rel(prev[c] as f64, total[c] as f64) < 1e-6,
                    "{:?}",
                    ev.shape
                );
            }
        }
        // A table has all its energy inside its last radius.
        let t = ProfileEval::new(&table(), 1.0).unwrap();
        assert_eq!(t.reflectance_within(4.0), t.total_reflectance());
        assert_eq!(t.truncation_radius(0.0), 4.0);
    }

    #[test]
    fn truncation_radius_leaves_at_most_the_fraction_outside() {
        for name in DIPOLE_PRESETS {
            let ev = ProfileEval::new(&dipole(name), 1.0).unwrap();
            let rho = ev.truncation_radius(1e-3);
            let (total, inside) = (ev.total_reflectance(), ev.reflectance_within(rho));
            let below = ev.reflectance_within(rho * 0.98);
            let mut tight = false;
            for c in 0..3 {
                let outside = ev.tail_mm(c, rho as f64) / ev.total_mm(c);
                assert!(
                    outside <= 1e-3f32 as f64,
                    "{name}[{c}]: {outside} outside ρ = {rho}"
                );
                assert!(1.0 - inside[c] / total[c] <= 1.001e-3);
                tight |= 1.0 - below[c] as f64 / total[c] as f64 > 1e-3;
            }
            assert!(tight, "{name}: ρ = {rho} is not the smallest radius");
            if name == "marble" {
                eprintln!("marble: truncation radius at 1e-3 = {rho} mm");
                // Independent check: the energy of eval beyond ρ, by quadrature.
                let far = quad_eval(&ev, rho as f64, 4000.0, 400_000);
                for c in 0..3 {
                    assert!(far[c] / total[c] as f64 <= 1.001e-3, "{c}: {}", far[c]);
                }
            }
        }
        for p in [table(), exponentials()] {
            let ev = ProfileEval::new(&p, 1.0).unwrap();
            let rho = ev.truncation_radius(1e-3);
            for c in 0..3 {
                assert!(ev.tail_mm(c, rho as f64) <= 1e-3f32 as f64 * ev.total_mm(c));
                assert!(ev.tail_mm(c, 0.98 * rho as f64) > 0.0);
            }
            assert_eq!(ev.truncation_radius(1.0), 0.0);
        }
        // In scene units: a metre scene's radius is the mm one / 1000.
        let m = ProfileEval::new(&dipole("marble"), 1000.0).unwrap();
        assert!(m.truncation_radius(1e-3) < 0.2);
    }

    #[test]
    fn bad_input_names_the_culprit() {
        let err = ProfileEval::new(&dipole("velvet"), 1.0).unwrap_err();
        assert_eq!(err, ProfileError::UnknownPreset("velvet".into()));
        assert!(err.to_string().contains("\"velvet\""), "{err}");
        assert!(err.to_string().contains("marble"), "{err}");

        let field = |p: &Profile, unit: f64| match ProfileEval::new(p, unit) {
            Err(ProfileError::Invalid { field, .. }) => field,
            other => panic!("{other:?}"),
        };
        assert_eq!(
            field(&explicit([0.1, -0.2, 0.1], [1.0; 3], 1.3), 1.0),
            "sigma_a[1]"
        );
        assert_eq!(
            field(&explicit([0.1; 3], [1.0, 1.0, f32::NAN], 1.3), 1.0),
            "sigma_s_prime[2]"
        );
        assert_eq!(
            field(&explicit([0.0; 3], [0.0; 3], 1.3), 1.0),
            "sigma_s_prime[0]"
        );
        assert_eq!(field(&explicit([0.1; 3], [1.0; 3], 0.5), 1.0), "eta");
        assert_eq!(field(&dipole("marble"), 0.0), "unit_mm");
        let scaled = Profile::Dipole {
            preset: Some("marble".into()),
            sigma_a: None,
            sigma_s_prime: None,
            eta: None,
            scale: Some(-1.0),
        };
        assert_eq!(field(&scaled, 1.0), "scale");
        let both = Profile::Dipole {
            preset: Some("marble".into()),
            sigma_a: Some([0.1; 3]),
            sigma_s_prime: Some([1.0; 3]),
            eta: None,
            scale: None,
        };
        assert_eq!(
            ProfileEval::new(&both, 1.0).unwrap_err(),
            ProfileError::PresetAndCoefficients
        );
        let none = Profile::Dipole {
            preset: None,
            sigma_a: Some([0.1; 3]),
            sigma_s_prime: None,
            eta: None,
            scale: None,
        };
        assert_eq!(
            ProfileEval::new(&none, 1.0).unwrap_err(),
            ProfileError::MissingCoefficients
        );
        let short = Profile::Table {
            radius_mm: vec![0.0, 1.0],
            values: vec![[1.0; 3]],
        };
        assert_eq!(field(&short, 1.0), "values");
        let unsorted = Profile::Table {
            radius_mm: vec![0.0, 1.0, 1.0],
            values: vec![[1.0; 3]; 3],
        };
        assert_eq!(field(&unsorted, 1.0), "radius_mm[2]");
        let flat = Profile::Exponentials {
            terms: vec![ExpTerm {
                a: [1.0; 3],
                b: [1.0, 0.0, 1.0],
            }],
        };
        let err = ProfileEval::new(&flat, 1.0).unwrap_err();
        assert!(err.to_string().contains("terms[0].b[1]"), "{err}");
        let m = preset("marble").unwrap();
        assert!(matches!(
            multipole(&m, 0.0, 5, 1.0),
            Err(ProfileError::Invalid { field, .. }) if field == "thickness_mm"
        ));
        // skin1's red mean free path is 1/0.772 = 1.3 mm: a 0.5 mm sheet cannot hold its source.
        let err = multipole(&preset("skin1").unwrap(), 0.5, 5, 1.0).unwrap_err();
        assert!(
            err.to_string().contains("thickness_mm") && err.to_string().contains("channel 0"),
            "{err}"
        );
    }

    #[test]
    fn table_and_exponentials_evaluate_in_scene_units() {
        // unit_mm = 10: scene r = 0.075 is 0.75 mm, R in scene-unit⁻² is 100 × mm⁻².
        let t = ProfileEval::new(&table(), 10.0).unwrap();
        for (r_mm, want) in [(0.0, 4.0), (0.3, 4.0), (0.75, 3.0), (1.5, 1.5), (4.0, 0.0)] {
            let got = t.eval(r_mm / 10.0)[0];
            assert!((got - want * 100.0).abs() < 1e-3, "{r_mm}: {got}");
        }
        assert!((t.eval(0.35)[1] - 31.25).abs() < 1e-4);
        assert_eq!(t.eval(0.41), [0.0; 3]);
        assert_eq!(t.total_reflectance(), total_reflectance(&table()));
        // The piecewise-linear integral against quadrature of eval (scene units).
        let quad = quad_eval(&t, 0.0, 0.5, 400_000);
        let exact = t.total_reflectance();
        for c in 0..3 {
            assert!(
                rel(quad[c], exact[c] as f64) < 1e-4,
                "{c}: {} vs {}",
                quad[c],
                exact[c]
            );
        }

        let p = exponentials();
        let e = ProfileEval::new(&p, 1.0).unwrap();
        let Profile::Exponentials { terms } = &p else {
            unreachable!()
        };
        for r in [0.0f32, 0.4, 2.0, 10.0] {
            let got = e.eval(r);
            let want: f32 = terms.iter().map(|t| t.a[0] * (-t.b[0] * r).exp()).sum();
            assert!(rel(got[0] as f64, want as f64) < 1e-5);
            // ∫₀^ρ a e^(−br) 2πr dr = 2πa/b² [1 − e^(−bρ)(1 + bρ)], typed from the brief.
            let within: f64 = terms
                .iter()
                .map(|t| {
                    let (a, b, rho) = (t.a[2] as f64, t.b[2] as f64, r as f64);
                    2.0 * PI * a / (b * b) * (1.0 - (-b * rho).exp() * (1.0 + b * rho))
                })
                .sum();
            assert!((e.reflectance_within(r)[2] as f64 - within).abs() < 1e-6);
        }
        let te = e.total_reflectance();
        let tp = total_reflectance(&p);
        for c in 0..3 {
            assert!(rel(te[c] as f64, tp[c] as f64) < 1e-6);
        }
    }

    /// The 1-D slab solution (fluence integrated over the plane): a unit source at depth l
    /// between zero-fluence planes at −z_b and d + z_b, L = d + 2z_b, κ = σtr. Returns the
    /// fluxes (×α′) out of the top and bottom faces.
    fn slab_totals(m: &Medium, c: usize, d: f64) -> (f64, f64) {
        let st = (m.sigma_a[c] + m.sigma_s_prime[c]) as f64;
        let alpha = m.sigma_s_prime[c] as f64 / st;
        let kappa = (3.0 * m.sigma_a[c] as f64 * st).sqrt();
        let eta = m.eta as f64;
        let fdr = -1.440 / (eta * eta) + 0.710 / eta + 0.668 + 0.0636 * eta;
        let zb = 2.0 * (1.0 + fdr) / (1.0 - fdr) / (3.0 * st);
        let (l, big_l) = (1.0 / st, d + 2.0 * zb);
        let xs = zb + l;
        let k = alpha * (kappa * zb).cosh() / (kappa * big_l).sinh();
        (k * (kappa * (big_l - xs)).sinh(), k * (kappa * xs).sinh())
    }

    #[test]
    fn multipole_totals_match_the_slab_solution() {
        let weak = Medium {
            sigma_s_prime: [1.0, 2.0, 1.5],
            sigma_a: [0.001, 0.01, 0.05],
            eta: 1.3,
        };
        for m in [preset("marble").unwrap(), preset("skin1").unwrap(), weak] {
            for d in [1.5f32, 4.0, 10.0] {
                let (r, t) = multipole(&m, d, 400, 1.0).unwrap();
                let (rt, tt) = (r.total_reflectance(), t.total_reflectance());
                for c in 0..3 {
                    let (want_r, want_t) = slab_totals(&m, c, d as f64);
                    assert!(want_t > 0.0);
                    assert!(
                        rel(rt[c] as f64, want_r) < 1e-4,
                        "{m:?} d {d} [{c}]: R {} vs {want_r}",
                        rt[c]
                    );
                    assert!(
                        rel(tt[c] as f64, want_t) < 1e-4,
                        "{m:?} d {d} [{c}]: T {} vs {want_t}",
                        tt[c]
                    );
                    assert!(rt[c] + tt[c] <= 1.0);
                }
            }
        }
    }

    #[test]
    fn multipole_profiles() {
        let m = preset("marble").unwrap();
        // A thick slab is a half-space: R is the dipole, T vanishes.
        let (r, t) = multipole(&m, 2000.0, 5, 1.0).unwrap();
        let dip = ProfileEval::new(&dipole("marble"), 1.0).unwrap();
        for x in [0.0f32, 0.5, 3.0, 20.0] {
            let (a, b) = (r.eval(x), dip.eval(x));
            for c in 0..3 {
                assert!(rel(a[c] as f64, b[c] as f64) < 1e-6, "{x}: {a:?} vs {b:?}");
            }
        }
        assert!(t.total_reflectance().iter().all(|&x| x < 1e-20));

        // A thin sheet transmits, and reflects less than the half-space.
        let d = 1.0f64;
        let (r, t) = multipole(&m, d as f32, 10, 1.0).unwrap();
        let (rt, tt, dt) = (
            r.total_reflectance(),
            t.total_reflectance(),
            dip.total_reflectance(),
        );
        for c in 0..3 {
            assert!(rt[c] < dt[c] && tt[c] > 0.05, "{rt:?} {tt:?}");
        }
        // T(r) typed from Donner and Jensen 2005, eq. for the transmitted profile.
        for x in [0.0f64, 0.4, 1.5, 5.0] {
            for (c, got) in t.eval(x as f32).into_iter().enumerate() {
                let (ss, sa) = (m.sigma_s_prime[c] as f64, m.sigma_a[c] as f64);
                let st = ss + sa;
                let alpha = ss / st;
                let s_tr = (3.0 * sa * st).sqrt();
                let eta = m.eta as f64;
                let fdr = -1.440 / (eta * eta) + 0.710 / eta + 0.668 + 0.0636 * eta;
                let zb = 2.0 * (1.0 + fdr) / (1.0 - fdr) / (3.0 * st);
                let l = 1.0 / st;
                let mut sum = 0.0;
                for i in -10i32..=10 {
                    let zr = 2.0 * i as f64 * (d + 2.0 * zb) + l;
                    let zv = 2.0 * i as f64 * (d + 2.0 * zb) - l - 2.0 * zb;
                    let dr = (x * x + (d - zr).powi(2)).sqrt();
                    let dv = (x * x + (d - zv).powi(2)).sqrt();
                    sum += (d - zr) * (1.0 + s_tr * dr) * (-s_tr * dr).exp() / dr.powi(3)
                        - (d - zv) * (1.0 + s_tr * dv) * (-s_tr * dv).exp() / dv.powi(3);
                }
                let want = alpha / (4.0 * PI) * sum;
                assert!(rel(got as f64, want) < 1e-5, "T({x})[{c}]: {got} vs {want}");
            }
        }
        // More poles change little once the series has converged.
        let (r20, t20) = multipole(&m, d as f32, 20, 1.0).unwrap();
        let (r40, t40) = multipole(&m, d as f32, 40, 1.0).unwrap();
        for x in [0.0f32, 1.0, 4.0] {
            for c in 0..3 {
                assert!(rel(r20.eval(x)[c] as f64, r40.eval(x)[c] as f64) < 1e-4);
                assert!(rel(t20.eval(x)[c] as f64, t40.eval(x)[c] as f64) < 1e-4);
            }
        }
    }
}
