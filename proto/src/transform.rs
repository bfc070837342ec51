//! An object's placement: scale, then rotate, then translate (a scene file's `transform`
//! and an animation's keyframes). Re-exported by the `scene` module.

use serde::{Deserialize, Serialize};

/// Scale, rotate, translate.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct Transform {
    #[serde(default)]
    pub translate: [f32; 3],
    /// Rotation in degrees about X, then Y, then Z.
    #[serde(default)]
    pub rotate_deg: [f32; 3],
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scale: Option<Scale>,
}

/// A uniform or per-axis scale.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(untagged)]
pub enum Scale {
    Uniform(f32),
    PerAxis([f32; 3]),
}

impl Scale {
    pub fn as_vec(self) -> [f32; 3] {
        match self {
            Scale::Uniform(s) => [s, s, s],
            Scale::PerAxis(v) => v,
        }
    }
}
