//! Lights and cameras, as they appear in scene files and relight requests.
//!
//! Units: positions in scene units; a point or spot light's `intensity` in W·sr⁻¹ (the
//! distance in E = I cos θ / r² is converted to metres with the scene's `unit_mm`); a
//! directional light's `irradiance` in W·m⁻² on a surface facing it; `direction` is where
//! the light travels.

use serde::{Deserialize, Serialize};

use crate::tagged::tagged_enum;

use crate::validate::{
    FieldError, check_direction, check_range, check_vec_finite, check_vec_range,
};

tagged_enum! {
    tag = "type", mirror = LightRepr;
    /// A light source.
    #[derive(Debug, Clone, PartialEq)]
    pub enum Light {
    /// Isotropic point light.
    Point { position: [f32; 3], intensity: [f32; 3] },
    /// A point light limited to a cone: full intensity inside `inner_deg` (half-angle), a
    /// smooth fall-off to zero at `outer_deg`.
    Spot {
        position: [f32; 3],
        intensity: [f32; 3],
        direction: [f32; 3],
        inner_deg: f32,
        outer_deg: f32,
    },
    /// A distant light.
    Directional { direction: [f32; 3], irradiance: [f32; 3] },
    /// An environment map (equirectangular `.hdr` path or `builtin:sky`).
    Environment {
        map: String,
        #[serde(default = "one")]
        scale: f32,
        #[serde(default)]
        rotation_deg: f32,
    },
}
}

/// The largest intensity (W·sr⁻¹), irradiance (W·m⁻²) or environment scale a light may
/// have. Far beyond any real light, and small enough that E = I cos θ / r² and the
/// inter-reflected sums stay finite in f32 (3.4e38) for patches down to a micrometre away:
/// a larger value would overflow to infinity and give no answer at all.
pub const MAX_POWER: f32 = 1e12;

fn one() -> f32 {
    1.0
}

impl Light {
    /// The lower-case tag used in JSON.
    pub fn kind(&self) -> &'static str {
        match self {
            Light::Point { .. } => "point",
            Light::Spot { .. } => "spot",
            Light::Directional { .. } => "directional",
            Light::Environment { .. } => "environment",
        }
    }

    /// Checks ranges; `at` is the field path of this light (`lights[0]`).
    pub fn validate(&self, at: &str) -> Result<(), FieldError> {
        let power =
            |name: &str, v: &[f32; 3]| check_vec_range(&format!("{at}.{name}"), v, 0.0, MAX_POWER);
        match self {
            Light::Point {
                position,
                intensity,
            } => {
                check_vec_finite(&format!("{at}.position"), position)?;
                power("intensity", intensity)
            }
            Light::Spot {
                position,
                intensity,
                direction,
                inner_deg,
                outer_deg,
            } => {
                check_vec_finite(&format!("{at}.position"), position)?;
                power("intensity", intensity)?;
                check_direction(&format!("{at}.direction"), direction)?;
                check_range(&format!("{at}.outer_deg"), *outer_deg, 0.0, 180.0)?;
                check_range(&format!("{at}.inner_deg"), *inner_deg, 0.0, *outer_deg).map_err(|_| {
                    FieldError::new(
                        format!("{at}.inner_deg"),
                        "must be finite and in [0, outer_deg]",
                    )
                })
            }
            Light::Directional {
                direction,
                irradiance,
            } => {
                check_direction(&format!("{at}.direction"), direction)?;
                power("irradiance", irradiance)
            }
            Light::Environment {
                map,
                scale,
                rotation_deg,
            } => {
                if map.trim().is_empty() {
                    return Err(FieldError::new(format!("{at}.map"), "must name a map"));
                }
                check_range(&format!("{at}.scale"), *scale, 0.0, MAX_POWER)?;
                check_range(
                    &format!("{at}.rotation_deg"),
                    *rotation_deg,
                    -360_000.0,
                    360_000.0,
                )
            }
        }
    }
}

/// A pinhole camera.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    pub position: [f32; 3],
    pub target: [f32; 3],
    #[serde(default = "up")]
    pub up: [f32; 3],
    /// Vertical field of view in degrees.
    #[serde(default = "fov")]
    pub fov_deg: f32,
}

fn up() -> [f32; 3] {
    [0.0, 1.0, 0.0]
}
fn fov() -> f32 {
    40.0
}

impl Camera {
    /// Checks ranges; `at` is the field path of this camera.
    pub fn validate(&self, at: &str) -> Result<(), FieldError> {
        check_vec_finite(&format!("{at}.position"), &self.position)?;
        check_vec_finite(&format!("{at}.target"), &self.target)?;
        check_direction(&format!("{at}.up"), &self.up)?;
        check_range(&format!("{at}.fov_deg"), self.fov_deg, 1.0, 170.0)?;
        let d: f32 = (0..3)
            .map(|k| (self.position[k] - self.target[k]).powi(2))
            .sum();
        if d <= 1e-20 {
            return Err(FieldError::new(
                format!("{at}.target"),
                "must differ from position",
            ));
        }
        Ok(())
    }
}
