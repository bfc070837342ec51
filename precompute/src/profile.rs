//! Diffuse reflectance profiles: Jensen et al. 2001's measured media and the total diffuse
//! reflectance Rd = ∫ R(r) 2πr dr of every profile kind.
//!
//! In: a [`Profile`] from the scene file. Out: per-channel coefficients and Rd, the albedo a
//! translucent object has when it is treated as opaque (the "inter-reflection only"
//! component, and the foundation's diffuse solve before S is in the bundle).

use translux_proto::scene::Profile;

/// Reduced scattering σs′ and absorption σa (mm⁻¹, RGB) and relative index η of a medium.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Medium {
    pub sigma_s_prime: [f32; 3],
    pub sigma_a: [f32; 3],
    pub eta: f32,
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

/// The dipole's total diffuse reflectance for reduced albedo α′ = σs′/(σs′ + σa):
/// Rd = (α′/2)(1 + e^(−(4/3)A√(3(1−α′)))) e^(−√(3(1−α′))), A = (1 + F_dr)/(1 − F_dr).
pub fn dipole_rd(sigma_s_prime: f32, sigma_a: f32, eta: f32) -> f32 {
    let alpha = sigma_s_prime / (sigma_s_prime + sigma_a);
    let fdr = fresnel_diffuse(eta);
    let a = (1.0 + fdr) / (1.0 - fdr);
    let s = (3.0 * (1.0 - alpha)).sqrt();
    0.5 * alpha * (1.0 + (-(4.0 / 3.0) * a * s).exp()) * (-s).exp()
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
            eta: eta.unwrap_or(1.3),
        }),
        _ => None,
    }
}

/// Total diffuse reflectance ∫ R(r) 2πr dr per channel (dimensionless), for any profile.
/// A dipole's `scale` stretches lengths and leaves Rd unchanged.
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
        // Piecewise-linear R between samples: integrate 2π r R(r) exactly per segment.
        Profile::Table { radius_mm, values } => std::array::from_fn(|c| {
            let mut sum = 0.0f64;
            for k in 1..radius_mm.len().min(values.len()) {
                let (r0, r1) = (radius_mm[k - 1] as f64, radius_mm[k] as f64);
                let (v0, v1) = (values[k - 1][c] as f64, values[k][c] as f64);
                // ∫ r (v0 + (v1−v0)(r−r0)/(r1−r0)) dr over [r0, r1].
                let slope = (v1 - v0) / (r1 - r0);
                let f = |r: f64| (v0 - slope * r0) * r * r / 2.0 + slope * r * r * r / 3.0;
                sum += f(r1) - f(r0);
            }
            (2.0 * std::f64::consts::PI * sum) as f32
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use translux_proto::scene::DIPOLE_PRESETS;

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

    #[test]
    fn every_preset_exists_and_matches_published_rd() {
        for name in DIPOLE_PRESETS {
            assert!(preset(name).is_some(), "{name}");
        }
        for (name, rd) in PUBLISHED_RD {
            let p = Profile::Dipole {
                preset: Some(name.into()),
                sigma_a: None,
                sigma_s_prime: None,
                eta: None,
                scale: None,
            };
            let got = total_reflectance(&p);
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
            terms: vec![translux_proto::scene::ExpTerm {
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
}
