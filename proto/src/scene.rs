//! The JSON scene file (`SCENE.json`) of `translux-precompute`.
//!
//! ```json
//! {
//!   "unit_mm": 1000,
//!   "patches": {"target": 6000},
//!   "objects": [
//!     {"name": "floor", "mesh": {"shape": "quad", "size": [2, 2]},
//!      "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
//!     {"name": "bunny", "mesh": "bunny.obj",
//!      "transform": {"translate": [0, 0, 0], "rotate_deg": [0, 90, 0], "scale": 5},
//!      "material": {"type": "translucent", "profile": {"type": "dipole", "preset": "marble"}}}
//!   ],
//!   "lights": [{"type": "point", "position": [0, 1.5, 0], "intensity": [5, 5, 5]}]
//! }
//! ```
//!
//! Every struct refuses unknown fields, so a typo is an error that names the field. Parsing
//! goes through [`crate::parse_json`], which reports the path of the offending field
//! (`objects[1].material.albedo[2]`) and the line and column. After parsing,
//! [`SceneFile::validate`] checks every value range and names the field and the rule.

use serde::{Deserialize, Serialize};

use crate::tagged::tagged_enum;

use crate::light::{Camera, Light};
use crate::validate::{FieldError, check_finite, check_range, check_vec_finite, check_vec_range};

/// Millimetres per scene unit when a scene file does not say (scene units are metres).
pub const DEFAULT_UNIT_MM: f64 = 1000.0;

fn default_unit_mm() -> f64 {
    DEFAULT_UNIT_MM
}

/// A whole scene file.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SceneFile {
    /// Optional display name; defaults to the file stem.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// The objects; each becomes a contiguous run of patches.
    pub objects: Vec<ObjectDesc>,
    /// Default lights (the server uses them when a request names none).
    #[serde(default)]
    pub lights: Vec<Light>,
    /// Millimetres per scene unit (default 1000: the scene is in metres).
    #[serde(default = "default_unit_mm")]
    pub unit_mm: f64,
    /// Patch density; `--patches` on the command line overrides it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub patches: Option<PatchDensity>,
    /// Default camera for the viewer and the renderer.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<Camera>,
}

/// How finely surfaces are split into patches.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PatchDensity {
    /// Aim for about this many patches in the whole scene.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target: Option<u64>,
    /// Split until no patch edge is longer than this (scene units).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_edge: Option<f32>,
}

/// One object of the scene.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ObjectDesc {
    /// Unique name; material overrides in relight requests refer to it.
    pub name: String,
    /// An OBJ path (relative to the scene file) or a built-in shape.
    pub mesh: MeshRef,
    /// Object-to-scene transform: scale, then rotate (X, then Y, then Z), then translate.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub transform: Option<Transform>,
    /// What the surface does with light.
    pub material: Material,
    /// Vertex normals are smoothed across edges whose faces differ by less than this angle
    /// (degrees); sharper edges stay creased. Default 40.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crease_deg: Option<f32>,
}

/// Where an object's triangles come from.
#[derive(Debug, Clone, Serialize, PartialEq)]
#[serde(untagged)]
pub enum MeshRef {
    /// An OBJ file, relative to the scene file (or absolute).
    Path(String),
    /// A procedural shape.
    Shape(Shape),
}

// A hand-written visitor instead of `#[serde(untagged)]`: untagged enums swallow the inner
// error ("did not match any variant"), while this keeps the shape's own message, which names
// the bad field.
impl<'de> Deserialize<'de> for MeshRef {
    fn deserialize<D: serde::Deserializer<'de>>(de: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> serde::de::Visitor<'de> for V {
            type Value = MeshRef;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("an OBJ path string or a shape object like {\"shape\":\"box\",...}")
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<MeshRef, E> {
                Ok(MeshRef::Path(v.to_owned()))
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(self, map: A) -> Result<MeshRef, A::Error> {
                Shape::deserialize(serde::de::value::MapAccessDeserializer::new(map))
                    .map(MeshRef::Shape)
            }
        }
        de.deserialize_any(V)
    }
}

tagged_enum! {
    tag = "shape", mirror = ShapeRepr;
    /// Procedural shapes, in object space, centred on the origin unless stated.
    #[derive(Debug, Clone, PartialEq)]
    pub enum Shape {
    /// A rectangle in the XZ plane facing +Y, `size` = [x, z].
    Quad { size: [f32; 2] },
    /// An axis-aligned box with outward faces, `size` = [x, y, z]. Set `inward` for a room
    /// seen from inside (faces point in).
    Box {
        size: [f32; 3],
        #[serde(default)]
        inward: bool,
    },
    /// A UV sphere with `segments` around (default 32) and `segments / 2` rings.
    Sphere {
        radius: f32,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        segments: Option<u32>,
    },
    /// A hemispherical bowl opening upwards (+Y), a surface of revolution with a wall of
    /// `thickness`: outer radius `radius`, inner radius `radius - thickness`, a flat rim, and
    /// its lowest outer point at y = 0.
    Bowl {
        radius: f32,
        thickness: f32,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        segments: Option<u32>,
    },
    /// A thin curved sheet (a petal or a leaf) with a front face and a back face `thickness`
    /// apart: length along +Z, width along X, bent upwards (+Y) by `curl` radians along its
    /// length. Both faces are patches of the same object.
    Sheet {
        length: f32,
        width: f32,
        thickness: f32,
        #[serde(default)]
        curl: f32,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        segments: Option<u32>,
    },
}
}

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

tagged_enum! {
    tag = "type", mirror = MaterialRepr;
    /// What a surface does with light.
    #[derive(Debug, Clone, PartialEq)]
    pub enum Material {
    /// Opaque Lambertian: S_ii = albedo.
    Diffuse { albedo: [f32; 3] },
    /// Subsurface scattering through the object, described by a 1-D profile.
    Translucent { profile: Profile },
    /// A Lambertian emitter of constant radiance (W·m⁻²·sr⁻¹); it reflects nothing.
    Emitter { radiance: [f32; 3] },
}
}

impl Material {
    /// The lower-case tag used in the scene file.
    pub fn kind(&self) -> &'static str {
        match self {
            Material::Diffuse { .. } => "diffuse",
            Material::Translucent { .. } => "translucent",
            Material::Emitter { .. } => "emitter",
        }
    }
}

tagged_enum! {
    tag = "type", mirror = ProfileRepr;
    /// A 1-D diffuse reflectance profile R(r) (per unit area, per RGB channel).
    #[derive(Debug, Clone, PartialEq)]
    pub enum Profile {
    /// The dipole of Jensen et al. 2001; either a named `preset` or `sigma_a` and
    /// `sigma_s_prime` (mm⁻¹) with `eta`. `scale` multiplies the mean free path (a larger
    /// scale makes the object more translucent).
    Dipole {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        preset: Option<String>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sigma_a: Option<[f32; 3]>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sigma_s_prime: Option<[f32; 3]>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        eta: Option<f32>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        scale: Option<f32>,
    },
    /// A measured table: R at `radius_mm[k]` is `values[k]` (mm⁻², RGB), linearly
    /// interpolated, zero past the last radius.
    Table {
        radius_mm: Vec<f32>,
        values: Vec<[f32; 3]>,
    },
    /// R(r) = Σ a_k e^(−b_k r), r in mm, b in mm⁻¹, a in mm⁻².
    Exponentials { terms: Vec<ExpTerm> },
}
}

/// One term a·e^(−b r) of an exponential-sum profile.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ExpTerm {
    pub a: [f32; 3],
    pub b: [f32; 3],
}

/// Jensen et al. 2001's measured media, by the lower-case names the scene file accepts.
pub const DIPOLE_PRESETS: [&str; 11] = [
    "apple",
    "chicken1",
    "chicken2",
    "cream",
    "ketchup",
    "marble",
    "potato",
    "skimmilk",
    "skin1",
    "skin2",
    "wholemilk",
];

impl SceneFile {
    /// Checks every value range, naming the field and the rule of the first violation.
    pub fn validate(&self) -> Result<(), FieldError> {
        if !(self.unit_mm.is_finite() && self.unit_mm > 0.0) {
            return Err(FieldError::new("unit_mm", "must be finite and > 0"));
        }
        if self.objects.is_empty() {
            return Err(FieldError::new("objects", "must list at least one object"));
        }
        if let Some(p) = &self.patches {
            if p.target.is_none() && p.max_edge.is_none() {
                return Err(FieldError::new("patches", "needs `target` or `max_edge`"));
            }
            if let Some(t) = p.target
                && t == 0
            {
                return Err(FieldError::new("patches.target", "must be >= 1"));
            }
            if let Some(e) = p.max_edge {
                check_finite("patches.max_edge", e)?;
                if e <= 0.0 {
                    return Err(FieldError::new("patches.max_edge", "must be > 0"));
                }
            }
        }
        let mut seen = std::collections::HashSet::new();
        for (i, o) in self.objects.iter().enumerate() {
            let at = format!("objects[{i}]");
            if o.name.trim().is_empty() {
                return Err(FieldError::new(format!("{at}.name"), "must not be empty"));
            }
            if !seen.insert(o.name.as_str()) {
                return Err(FieldError::new(
                    format!("{at}.name"),
                    format!(
                        "\"{}\" is used by an earlier object; names must be unique",
                        o.name
                    ),
                ));
            }
            if let MeshRef::Shape(s) = &o.mesh {
                s.validate(&format!("{at}.mesh"))?;
            }
            if let Some(t) = &o.transform {
                check_vec_finite(&format!("{at}.transform.translate"), &t.translate)?;
                check_vec_finite(&format!("{at}.transform.rotate_deg"), &t.rotate_deg)?;
                if let Some(s) = t.scale {
                    let path = format!("{at}.transform.scale");
                    for (k, v) in s.as_vec().iter().enumerate() {
                        check_finite(&path, *v)?;
                        if *v == 0.0 {
                            return Err(FieldError::new(
                                format!("{path}[{k}]"),
                                "must not be 0 (a flat object has no area)",
                            ));
                        }
                    }
                }
            }
            o.material.validate(&format!("{at}.material"))?;
            if let Some(c) = o.crease_deg {
                check_range(&format!("{at}.crease_deg"), c, 0.0, 180.0)?;
            }
        }
        for (i, l) in self.lights.iter().enumerate() {
            l.validate(&format!("lights[{i}]"))?;
        }
        if let Some(c) = &self.camera {
            c.validate("camera")?;
        }
        Ok(())
    }
}

impl Shape {
    fn validate(&self, at: &str) -> Result<(), FieldError> {
        let positive = |name: &str, v: f32| -> Result<(), FieldError> {
            check_finite(&format!("{at}.{name}"), v)?;
            if v <= 0.0 {
                return Err(FieldError::new(format!("{at}.{name}"), "must be > 0"));
            }
            Ok(())
        };
        let segments = |s: Option<u32>, min: u32| -> Result<(), FieldError> {
            match s {
                Some(n) if !(min..=4096).contains(&n) => Err(FieldError::new(
                    format!("{at}.segments"),
                    format!("must be in [{min}, 4096]"),
                )),
                _ => Ok(()),
            }
        };
        match self {
            Shape::Quad { size } => {
                positive("size[0]", size[0])?;
                positive("size[1]", size[1])
            }
            Shape::Box { size, .. } => {
                for (k, v) in size.iter().enumerate() {
                    positive(&format!("size[{k}]"), *v)?;
                }
                Ok(())
            }
            Shape::Sphere {
                radius,
                segments: s,
            } => {
                positive("radius", *radius)?;
                segments(*s, 4)
            }
            Shape::Bowl {
                radius,
                thickness,
                segments: s,
            } => {
                positive("radius", *radius)?;
                positive("thickness", *thickness)?;
                if thickness >= radius {
                    return Err(FieldError::new(
                        format!("{at}.thickness"),
                        "must be smaller than the radius",
                    ));
                }
                segments(*s, 4)
            }
            Shape::Sheet {
                length,
                width,
                thickness,
                curl,
                segments: s,
            } => {
                positive("length", *length)?;
                positive("width", *width)?;
                positive("thickness", *thickness)?;
                check_finite(&format!("{at}.curl"), *curl)?;
                segments(*s, 1)
            }
        }
    }
}

impl Material {
    /// Checks ranges; `at` is the field path of this material.
    pub fn validate(&self, at: &str) -> Result<(), FieldError> {
        match self {
            Material::Diffuse { albedo } => {
                check_vec_range(&format!("{at}.albedo"), albedo, 0.0, 1.0)
            }
            Material::Emitter { radiance } => {
                check_vec_range(&format!("{at}.radiance"), radiance, 0.0, f32::MAX)
            }
            Material::Translucent { profile } => profile.validate(&format!("{at}.profile")),
        }
    }
}

impl Profile {
    /// Checks ranges; `at` is the field path of this profile.
    pub fn validate(&self, at: &str) -> Result<(), FieldError> {
        match self {
            Profile::Dipole {
                preset,
                sigma_a,
                sigma_s_prime,
                eta,
                scale,
            } => {
                match (preset, sigma_a, sigma_s_prime) {
                    (Some(p), None, None) => {
                        if !DIPOLE_PRESETS.contains(&p.as_str()) {
                            return Err(FieldError::new(
                                format!("{at}.preset"),
                                format!(
                                    "\"{p}\" is not a known medium; use one of {}",
                                    DIPOLE_PRESETS.join(", ")
                                ),
                            ));
                        }
                    }
                    (None, Some(sa), Some(ss)) => {
                        check_vec_range(&format!("{at}.sigma_a"), sa, 0.0, f32::MAX)?;
                        check_vec_range(&format!("{at}.sigma_s_prime"), ss, 0.0, f32::MAX)?;
                        for k in 0..3 {
                            if sa[k] + ss[k] <= 0.0 {
                                return Err(FieldError::new(
                                    format!("{at}.sigma_s_prime[{k}]"),
                                    "sigma_a + sigma_s_prime must be > 0",
                                ));
                            }
                        }
                    }
                    (Some(_), _, _) => {
                        return Err(FieldError::new(
                            at,
                            "give either `preset` or `sigma_a` and `sigma_s_prime`, not both",
                        ));
                    }
                    _ => {
                        return Err(FieldError::new(
                            at,
                            "a dipole needs `preset` or both `sigma_a` and `sigma_s_prime`",
                        ));
                    }
                }
                if let Some(e) = eta {
                    check_range(&format!("{at}.eta"), *e, 1.0, 3.0)?;
                }
                if let Some(s) = scale {
                    check_finite(&format!("{at}.scale"), *s)?;
                    if *s <= 0.0 {
                        return Err(FieldError::new(format!("{at}.scale"), "must be > 0"));
                    }
                }
                Ok(())
            }
            Profile::Table { radius_mm, values } => {
                if radius_mm.len() < 2 {
                    return Err(FieldError::new(
                        format!("{at}.radius_mm"),
                        "needs at least two radii",
                    ));
                }
                if radius_mm.len() != values.len() {
                    return Err(FieldError::new(
                        format!("{at}.values"),
                        format!(
                            "has {} entries but radius_mm has {}; they must match",
                            values.len(),
                            radius_mm.len()
                        ),
                    ));
                }
                for (k, r) in radius_mm.iter().enumerate() {
                    check_range(&format!("{at}.radius_mm[{k}]"), *r, 0.0, f32::MAX)?;
                    if k > 0 && *r <= radius_mm[k - 1] {
                        return Err(FieldError::new(
                            format!("{at}.radius_mm[{k}]"),
                            "must be larger than the radius before it",
                        ));
                    }
                }
                for (k, v) in values.iter().enumerate() {
                    check_vec_range(&format!("{at}.values[{k}]"), v, 0.0, f32::MAX)?;
                }
                Ok(())
            }
            Profile::Exponentials { terms } => {
                if terms.is_empty() {
                    return Err(FieldError::new(
                        format!("{at}.terms"),
                        "needs at least one term",
                    ));
                }
                for (k, t) in terms.iter().enumerate() {
                    check_vec_range(&format!("{at}.terms[{k}].a"), &t.a, 0.0, f32::MAX)?;
                    check_vec_finite(&format!("{at}.terms[{k}].b"), &t.b)?;
                    for c in 0..3 {
                        if t.b[c] <= 0.0 {
                            return Err(FieldError::new(
                                format!("{at}.terms[{k}].b[{c}]"),
                                "must be > 0 (the profile must fall off)",
                            ));
                        }
                    }
                }
                Ok(())
            }
        }
    }
}
