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

use crate::animation::{Animation, Keyframe, frame_mesh_path, is_frame_pattern};
use crate::tagged::tagged_enum;
pub use crate::transform::{Scale, Transform};

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
    /// Makes the scene a sequence of frames (see [`crate::animation`]): objects may then
    /// read a mesh file per frame (`{frame}` in the path) and move by `keyframes`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub animation: Option<Animation>,
}

/// A scene file that imports a whole glTF 2.0 file (`{"gltf": "room.glb", ...}`): the file's
/// nodes become objects (named as in the file), its materials, `KHR_lights_punctual` lights
/// and first camera the scene's (see docs/scenes.md for the mapping), and this file may
/// override any of them by name and add objects of its own.
///
/// ```json
/// {
///   "gltf": "room.glb",
///   "materials": {"Wall": {"type": "diffuse", "albedo": [0.8, 0.1, 0.1]}},
///   "light_overrides": {"Lamp": {"type": "point", "position": [0, 2, 0], "intensity": [3, 3, 3]}},
///   "objects": [{"name": "bunny", "mesh": "bunny.obj",
///                "material": {"type": "translucent", "profile": {"type": "dipole", "preset": "marble"}}}]
/// }
/// ```
///
/// The file's objects can also be placed one by one in an ordinary [`SceneFile`]: an
/// object's `mesh` `"room.glb#Wall"` is the node the import names `Wall`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct GltfSceneFile {
    /// The glTF file (`.gltf` or `.glb`), relative to this file (or absolute).
    pub gltf: String,
    /// Optional display name; defaults to this file's stem.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// Materials by object name, replacing what the file gives (textures included).
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub materials: std::collections::BTreeMap<String, Material>,
    /// When present, the scene's lights instead of the file's (`[]`: none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lights: Option<Vec<Light>>,
    /// The file's lights by their `KHR_lights_punctual` name: replaced by the light given,
    /// or removed by `null`.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub light_overrides: std::collections::BTreeMap<String, Option<Light>>,
    /// More objects, after the file's; their names must differ from the file's.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub objects: Vec<ObjectDesc>,
    /// Patch density; `--patches` on the command line overrides it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub patches: Option<PatchDensity>,
    /// The camera instead of the file's first one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<Camera>,
}

impl GltfSceneFile {
    /// Checks what can be checked without the glTF file: the overriding materials and lights
    /// and the extra objects' fields (names against the file's are checked on import).
    pub fn validate(&self) -> Result<(), FieldError> {
        if self.gltf.trim().is_empty() {
            return Err(FieldError::new("gltf", "must name a .gltf or .glb file"));
        }
        for (name, m) in &self.materials {
            m.validate(&format!("materials.{name}"))?;
        }
        for (i, l) in self.lights.iter().flatten().enumerate() {
            l.validate(&format!("lights[{i}]"))?;
        }
        for (name, l) in &self.light_overrides {
            if let Some(l) = l {
                l.validate(&format!("light_overrides.{name}"))?;
            }
        }
        if let Some(c) = &self.camera {
            c.validate("camera")?;
        }
        Ok(())
    }

    /// Whether a scene file's text is this form rather than a [`SceneFile`]: a JSON object
    /// with a `gltf` key (only looked for when the text is valid JSON).
    pub fn is_gltf_import(text: &str) -> bool {
        serde_json::from_str::<serde_json::Map<String, serde_json::Value>>(text)
            .is_ok_and(|m| m.contains_key("gltf"))
    }
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
    /// Simplify the mesh toward this many triangles before it is split into patches
    /// (quadric edge collapse; open borders stay in place). For scanned meshes whose
    /// triangle count alone would exceed the patch budget: every source triangle becomes at
    /// least one patch. Ignored when the mesh already has no more triangles.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub simplify_to: Option<u64>,
    /// Which way the mesh's faces point (default `auto`). See [`Orientation`].
    #[serde(default, skip_serializing_if = "Orientation::is_auto")]
    pub orientation: Orientation,
    /// In an animated scene: where the object is at each frame, applied after `transform`
    /// (see [`crate::animation::Keyframe`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub keyframes: Option<Vec<Keyframe>>,
}

/// Which way an object's faces are made to point. A face's front is the side its corners
/// run counter-clockwise around; light arrives and leaves on that side only.
///
/// Only a *closed* surface (or a nearly closed one, like a scan with a small hole) has an
/// inside and an outside; an open surface (a wall, a floor, a sheet, a petal) has neither
/// and is never turned over by `auto`, `outward` or `inward`.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq, Default)]
#[serde(rename_all = "snake_case")]
pub enum Orientation {
    /// Turn a closed part outward when it is provably wound inside out, unless it encloses
    /// a light, the camera or another object (then it is a room seen from inside and is
    /// kept facing inward). Open parts are kept as they are. The default.
    #[default]
    Auto,
    /// Keep every face as the file winds it.
    AsIs,
    /// Every closed part faces outward (an object seen from outside).
    Outward,
    /// Every closed part faces inward (a room or a container seen from inside).
    Inward,
}

impl Orientation {
    /// Whether this is the default, `auto`.
    pub fn is_auto(&self) -> bool {
        *self == Orientation::Auto
    }
}

/// The largest absorption or reduced scattering coefficient (mm⁻¹): a mean free path of
/// 0.1 µm, far denser than any measured medium (Jensen et al.'s are below 10 mm⁻¹).
pub const MAX_SIGMA: f32 = 1e4;

/// Bounds of a dipole's `scale` (the factor on its mean free path).
pub const MIN_DIPOLE_SCALE: f32 = 1e-3;
pub const MAX_DIPOLE_SCALE: f32 = 1e3;

/// Bounds of [`ObjectDesc::simplify_to`].
pub const MIN_SIMPLIFY_TO: u64 = 4;
pub const MAX_SIMPLIFY_TO: u64 = 10_000_000;

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

tagged_enum! {
    tag = "type", mirror = MaterialRepr;
    /// What a surface does with light.
    #[derive(Debug, Clone, PartialEq)]
    pub enum Material {
    /// Opaque Lambertian: S_ii = albedo.
    Diffuse {
        albedo: [f32; 3],
        #[serde(default, skip_serializing_if = "Option::is_none")]
        specular: Option<Specular>,
    },
    /// Subsurface scattering through the object, described by a 1-D profile.
    Translucent {
        profile: Profile,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        specular: Option<Specular>,
    },
    /// A thin two-sided sheet (a petal, a leaf, paper) of constant thickness, after the
    /// paper's rose: light entering one face leaves the same face by `reflectance` and the
    /// other face by `transmittance`, both over the geodesic distance along the sheet (R, T
    /// per unit area as measured on a slab of `thickness_mm`). The mesh must have a front and
    /// a back face (a `sheet` shape has both).
    ThinSheet {
        reflectance: Profile,
        transmittance: Profile,
        thickness_mm: f32,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        specular: Option<Specular>,
    },
    /// A Lambertian emitter of constant radiance (W·m⁻²·sr⁻¹); it reflects nothing.
    Emitter { radiance: [f32; 3] },
    /// A translucent object made of 2 to [`MAX_HETEROGENEOUS_MATERIALS`] homogeneous media
    /// laid out by `pattern`. A path of length r = Σ_k r_k, r_k travelled in medium k,
    /// scatters by the paper's eq. 9 generalised to K media,
    /// `S = (Σ_k S_k(0) r_k / r) · Π_k S_k(r_k) / S_k(0)`, S_k the profile of medium k.
    Heterogeneous {
        materials: Vec<Profile>,
        pattern: Pattern,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        specular: Option<Specular>,
    },
    /// A translucent object whose S is simulated: random walks through a homogeneous medium
    /// inside the object's actual closed mesh (the paper's "simulation-based" S). A walk
    /// enters patch i diffusely, scatters (isotropic, or Henyey–Greenstein with `g`) until
    /// it leaves through patch j (an index-matched boundary when η = 1, else a smooth
    /// dielectric that reflects by Fresnel), and adds to S_ji. The medium is a Jensen
    /// `preset` (σs′, σa, η; `sigma_a` and `eta` may replace the preset's), or `sigma_a` with
    /// `sigma_s_prime` (isotropic) or `sigma_s` and `g`, in mm⁻¹. Walks record their path
    /// lengths, so a new `sigma_a` re-weights them (e^(−σa L)) without re-simulating;
    /// scattering, `g` and `eta` are geometry of the walks and need a new precompute.
    Simulated {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        preset: Option<String>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sigma_a: Option<[f32; 3]>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sigma_s_prime: Option<[f32; 3]>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sigma_s: Option<[f32; 3]>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        g: Option<f32>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        eta: Option<f32>,
        /// Walks per patch are added until the relative standard error of the patch's
        /// re-emitted total (at the built σa) is below this (default 0.01).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        noise: Option<f32>,
        /// At most this many diffuse walks per patch and colour group (default 4096); as
        /// many again enter collimated.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        max_walks: Option<u32>,
        /// Seed of the walks (default 1): the same seed gives the same S.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        seed: Option<u64>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        specular: Option<Specular>,
    },
}
}

/// Bounds of [`Material::Simulated`]'s `noise`.
pub const MIN_SIM_NOISE: f32 = 1e-3;
pub const MAX_SIM_NOISE: f32 = 0.5;
/// Bounds of [`Material::Simulated`]'s `max_walks` (per patch and colour group).
pub const MIN_SIM_WALKS: u32 = 16;
pub const MAX_SIM_WALKS: u32 = 1_000_000;

/// A glossy reflection on top of a material's diffuse or subsurface answer: the paper's
/// "one bounce of specularities added in a separate pass". A Fresnel-weighted GGX
/// microfacet lobe (Walter et al. 2007) of the lights, evaluated per pixel by the renderer
/// and the viewer; it does not enter the radiosity transport (B is unchanged).
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Specular {
    /// Perceptual roughness in [[`MIN_ROUGHNESS`], 1] (Blender's and glTF's convention):
    /// the GGX width is α = roughness².
    pub roughness: f32,
    /// Relative index of refraction for the Fresnel term, in [1, 3]. Absent: the medium's
    /// η where the material has one (a dipole's `eta`, else its preset's), else 1.5.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eta: Option<f32>,
}

/// The smallest [`Specular::roughness`]: α = 1e-4, a highlight of a point light still a
/// few pixels wide, and GGX's peak 1/(πα²) far inside f32.
pub const MIN_ROUGHNESS: f32 = 0.01;

impl Specular {
    /// Checks ranges; `at` is the field path of this specular (`objects[0].material.specular`).
    pub fn validate(&self, at: &str) -> Result<(), FieldError> {
        check_range(
            &format!("{at}.roughness"),
            self.roughness,
            MIN_ROUGHNESS,
            1.0,
        )?;
        if let Some(e) = self.eta {
            check_range(&format!("{at}.eta"), e, 1.0, 3.0)?;
        }
        Ok(())
    }
}

/// Most media a [`Material::Heterogeneous`] object may combine (the bundle stores four
/// per-medium lengths per optical path).
pub const MAX_HETEROGENEOUS_MATERIALS: usize = 4;

tagged_enum! {
    tag = "type", mirror = PatternRepr;
    /// Which medium of a heterogeneous object is where.
    #[derive(Debug, Clone, PartialEq)]
    pub enum Pattern {
    /// A 3-D checkerboard of cubic cells of edge `cell` (scene units), fixed to the object:
    /// a point p of the scene is taken into the object's frame by undoing its transform's
    /// translation and rotation (not its scale), q = Rᵀ(p − t) − origin, and lies in medium
    /// (⌊q_x/cell⌋ + ⌊q_y/cell⌋ + ⌊q_z/cell⌋) mod K (K = number of materials).
    Checkerboard {
        cell: f32,
        #[serde(default)]
        origin: [f32; 3],
    },
    /// Media by the OBJ's `usemtl` groups: faces of material `names[k]` are medium k; a point
    /// inside the object is in the medium of the nearest face (measured through the inside).
    ByObjMaterial { names: Vec<String> },
}
}

impl Material {
    /// The lower-case tag used in the scene file.
    pub fn kind(&self) -> &'static str {
        match self {
            Material::Diffuse { .. } => "diffuse",
            Material::Translucent { .. } => "translucent",
            Material::ThinSheet { .. } => "thin_sheet",
            Material::Emitter { .. } => "emitter",
            Material::Heterogeneous { .. } => "heterogeneous",
            Material::Simulated { .. } => "simulated",
        }
    }

    /// The material's glossy coat, if it has one.
    pub fn specular(&self) -> Option<&Specular> {
        match self {
            Material::Diffuse { specular, .. }
            | Material::Translucent { specular, .. }
            | Material::ThinSheet { specular, .. }
            | Material::Heterogeneous { specular, .. }
            | Material::Simulated { specular, .. } => specular.as_ref(),
            Material::Emitter { .. } => None,
        }
    }

    /// The same material without its glossy coat: what the radiosity transport sees (S and
    /// the albedo do not depend on `specular`).
    pub fn without_specular(&self) -> Material {
        let mut m = self.clone();
        match &mut m {
            Material::Diffuse { specular, .. }
            | Material::Translucent { specular, .. }
            | Material::ThinSheet { specular, .. }
            | Material::Heterogeneous { specular, .. }
            | Material::Simulated { specular, .. } => *specular = None,
            Material::Emitter { .. } => {}
        }
        m
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
        if let Some(a) = &self.animation {
            a.validate()?;
        }
        let mut seen = std::collections::HashSet::new();
        for (i, o) in self.objects.iter().enumerate() {
            let at = format!("objects[{i}]");
            if let Some(keys) = &o.keyframes {
                let Some(a) = &self.animation else {
                    return Err(FieldError::new(
                        format!("{at}.keyframes"),
                        "keyframes need an animated scene: add `\"animation\": {\"frames\": N}`",
                    ));
                };
                Keyframe::validate_all(keys, &format!("{at}.keyframes"), a.frames)?;
            }
            if let MeshRef::Path(p) = &o.mesh
                && is_frame_pattern(p)
            {
                if self.animation.is_none() {
                    return Err(FieldError::new(
                        format!("{at}.mesh"),
                        format!(
                            "\"{p}\" is a per-frame pattern ({{frame}}), but the scene has no \
                             `animation`: add `\"animation\": {{\"frames\": N}}`"
                        ),
                    ));
                }
                frame_mesh_path(p, 0).map_err(|e| FieldError::new(format!("{at}.mesh"), e))?;
            }
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
            if let (
                Material::Heterogeneous {
                    pattern: Pattern::ByObjMaterial { .. },
                    ..
                },
                MeshRef::Shape(_),
            ) = (&o.material, &o.mesh)
            {
                return Err(FieldError::new(
                    format!("{at}.material.pattern"),
                    "by_obj_material needs an OBJ mesh with `usemtl` groups; a built-in shape \
                     has none (use a checkerboard)",
                ));
            }
            if let Some(c) = o.crease_deg {
                check_range(&format!("{at}.crease_deg"), c, 0.0, 180.0)?;
            }
            if let Some(n) = o.simplify_to {
                if !(MIN_SIMPLIFY_TO..=MAX_SIMPLIFY_TO).contains(&n) {
                    return Err(FieldError::new(
                        format!("{at}.simplify_to"),
                        format!("must be in [{MIN_SIMPLIFY_TO}, {MAX_SIMPLIFY_TO}] triangles"),
                    ));
                }
                if let Material::Heterogeneous {
                    pattern: Pattern::ByObjMaterial { .. },
                    ..
                } = o.material
                {
                    return Err(FieldError::new(
                        format!("{at}.simplify_to"),
                        "cannot simplify a mesh whose media follow its `usemtl` groups \
                         (by_obj_material): collapsed faces would lose their group",
                    ));
                }
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
        if let Some(s) = self.specular() {
            s.validate(&format!("{at}.specular"))?;
        }
        match self {
            Material::Diffuse { albedo, .. } => {
                check_vec_range(&format!("{at}.albedo"), albedo, 0.0, 1.0)
            }
            Material::Emitter { radiance } => check_vec_range(
                &format!("{at}.radiance"),
                radiance,
                0.0,
                crate::light::MAX_POWER,
            ),
            Material::Translucent { profile, .. } => profile.validate(&format!("{at}.profile")),
            Material::ThinSheet {
                reflectance,
                transmittance,
                thickness_mm,
                ..
            } => {
                reflectance.validate(&format!("{at}.reflectance"))?;
                transmittance.validate(&format!("{at}.transmittance"))?;
                let path = format!("{at}.thickness_mm");
                check_finite(&path, *thickness_mm)?;
                if *thickness_mm <= 0.0 {
                    return Err(FieldError::new(path, "must be > 0"));
                }
                Ok(())
            }
            Material::Heterogeneous {
                materials, pattern, ..
            } => {
                let k = materials.len();
                if !(2..=MAX_HETEROGENEOUS_MATERIALS).contains(&k) {
                    return Err(FieldError::new(
                        format!("{at}.materials"),
                        format!(
                            "has {k} profiles; a heterogeneous object needs 2 to \
                             {MAX_HETEROGENEOUS_MATERIALS}"
                        ),
                    ));
                }
                for (i, p) in materials.iter().enumerate() {
                    p.validate(&format!("{at}.materials[{i}]"))?;
                }
                pattern.validate(&format!("{at}.pattern"), k)
            }
            Material::Simulated {
                preset,
                sigma_a,
                sigma_s_prime,
                sigma_s,
                g,
                eta,
                noise,
                max_walks,
                seed: _,
                specular: _,
            } => {
                if let Some(p) = preset
                    && !DIPOLE_PRESETS.contains(&p.as_str())
                {
                    return Err(FieldError::new(
                        format!("{at}.preset"),
                        format!(
                            "\"{p}\" is not a known medium; use one of {}",
                            DIPOLE_PRESETS.join(", ")
                        ),
                    ));
                }
                if let Some(a) = sigma_a {
                    check_vec_range(&format!("{at}.sigma_a"), a, 0.0, MAX_SIGMA)?;
                }
                let scattering = match (sigma_s_prime, sigma_s) {
                    (Some(_), Some(_)) => {
                        return Err(FieldError::new(
                            at,
                            "give `sigma_s_prime` (isotropic) or `sigma_s` with `g`, not both",
                        ));
                    }
                    (Some(s), None) => Some(("sigma_s_prime", s)),
                    (None, Some(s)) => Some(("sigma_s", s)),
                    (None, None) => None,
                };
                if let Some((name, s)) = scattering {
                    if preset.is_some() {
                        return Err(FieldError::new(
                            format!("{at}.{name}"),
                            "a preset gives the scattering; leave out `preset` to set it",
                        ));
                    }
                    check_vec_range(&format!("{at}.{name}"), s, 0.0, MAX_SIGMA)?;
                    for (k, v) in s.iter().enumerate() {
                        if *v <= 0.0 {
                            return Err(FieldError::new(
                                format!("{at}.{name}[{k}]"),
                                "must be > 0 (a medium that does not scatter has no S)",
                            ));
                        }
                    }
                } else if preset.is_none() {
                    return Err(FieldError::new(
                        at,
                        "a simulated medium needs `preset`, or `sigma_a` with `sigma_s_prime` \
                         or `sigma_s`",
                    ));
                }
                if preset.is_none() && sigma_a.is_none() {
                    return Err(FieldError::new(
                        format!("{at}.sigma_a"),
                        "is required without a preset",
                    ));
                }
                if let Some(g) = g {
                    if sigma_s.is_none() {
                        return Err(FieldError::new(
                            format!("{at}.g"),
                            "goes with `sigma_s` (σs′ = σs (1 − g) is already reduced)",
                        ));
                    }
                    check_range(&format!("{at}.g"), *g, -0.99, 0.99)?;
                }
                if let Some(e) = eta {
                    check_range(&format!("{at}.eta"), *e, 1.0, 3.0)?;
                }
                if let Some(n) = noise {
                    check_range(&format!("{at}.noise"), *n, MIN_SIM_NOISE, MAX_SIM_NOISE)?;
                }
                if let Some(w) = max_walks
                    && !(MIN_SIM_WALKS..=MAX_SIM_WALKS).contains(w)
                {
                    return Err(FieldError::new(
                        format!("{at}.max_walks"),
                        format!(
                            "{w} is out of range: walks per patch must be in \
                             [{MIN_SIM_WALKS}, {MAX_SIM_WALKS}]"
                        ),
                    ));
                }
                Ok(())
            }
        }
    }
}

impl Pattern {
    /// Checks ranges; `at` is the field path of this pattern, `count` the number of media.
    pub fn validate(&self, at: &str, count: usize) -> Result<(), FieldError> {
        match self {
            Pattern::Checkerboard { cell, origin } => {
                check_finite(&format!("{at}.cell"), *cell)?;
                if *cell <= 0.0 {
                    return Err(FieldError::new(format!("{at}.cell"), "must be > 0"));
                }
                check_vec_finite(&format!("{at}.origin"), origin)
            }
            Pattern::ByObjMaterial { names } => {
                if names.len() != count {
                    return Err(FieldError::new(
                        format!("{at}.names"),
                        format!(
                            "has {} names but there are {count} materials; names[k] picks \
                             the faces of materials[k]",
                            names.len()
                        ),
                    ));
                }
                for (i, n) in names.iter().enumerate() {
                    if n.trim().is_empty() {
                        return Err(FieldError::new(
                            format!("{at}.names[{i}]"),
                            "must not be empty",
                        ));
                    }
                    if names[..i].contains(n) {
                        return Err(FieldError::new(
                            format!("{at}.names[{i}]"),
                            format!("\"{n}\" is listed twice; names must be unique"),
                        ));
                    }
                }
                Ok(())
            }
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
                        check_vec_range(&format!("{at}.sigma_a"), sa, 0.0, MAX_SIGMA)?;
                        check_vec_range(&format!("{at}.sigma_s_prime"), ss, 0.0, MAX_SIGMA)?;
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
                    // Beyond these the profile underflows to zero or overflows (1e-20 made
                    // the solver panic).
                    check_range(
                        &format!("{at}.scale"),
                        *s,
                        MIN_DIPOLE_SCALE,
                        MAX_DIPOLE_SCALE,
                    )?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::parse_json;

    /// A one-object scene with `material` (JSON) on mesh `mesh` (JSON).
    fn scene(mesh: &str, material: &str) -> String {
        format!(r#"{{"objects":[{{"name":"block","mesh":{mesh},"material":{material}}}]}}"#)
    }

    const MARBLE: &str = r#"{"type":"dipole","preset":"marble"}"#;
    const KETCHUP: &str = r#"{"type":"dipole","preset":"ketchup"}"#;
    const BOX: &str = r#"{"shape":"box","size":[1,2,1]}"#;

    fn validate(mesh: &str, material: &str) -> Result<SceneFile, String> {
        let s: SceneFile = parse_json(&scene(mesh, material)).map_err(|e| e.to_string())?;
        s.validate().map_err(|e| e.to_string())?;
        Ok(s)
    }

    #[test]
    fn heterogeneous_checkerboard_parses_with_default_origin() {
        let s = validate(
            BOX,
            &format!(
                r#"{{"type":"heterogeneous","materials":[{MARBLE},{KETCHUP}],
                    "pattern":{{"type":"checkerboard","cell":0.25}}}}"#
            ),
        )
        .unwrap();
        let Material::Heterogeneous {
            materials, pattern, ..
        } = &s.objects[0].material
        else {
            panic!("{:?}", s.objects[0].material)
        };
        assert_eq!(materials.len(), 2);
        assert_eq!(
            *pattern,
            Pattern::Checkerboard {
                cell: 0.25,
                origin: [0.0; 3]
            }
        );
        assert_eq!(s.objects[0].material.kind(), "heterogeneous");
        // It round-trips through JSON with its tags.
        let text = serde_json::to_string(&s).unwrap();
        assert!(text.contains(r#""type":"heterogeneous""#), "{text}");
        assert!(text.contains(r#""type":"checkerboard""#), "{text}");
        assert_eq!(parse_json::<SceneFile>(&text).unwrap(), s);
        // by_obj_material on an OBJ mesh.
        validate(
            r#""block.obj""#,
            &format!(
                r#"{{"type":"heterogeneous","materials":[{MARBLE},{KETCHUP}],
                    "pattern":{{"type":"by_obj_material","names":["white","orange"]}}}}"#
            ),
        )
        .unwrap();
    }

    #[test]
    fn heterogeneous_errors_name_the_field() {
        let het = |materials: &str, pattern: &str| {
            format!(r#"{{"type":"heterogeneous","materials":[{materials}],"pattern":{pattern}}}"#)
        };
        let checker = r#"{"type":"checkerboard","cell":0.1}"#;
        let cases = [
            (
                BOX.to_string(),
                het(MARBLE, checker),
                "objects[0].material.materials has 1 profiles; a heterogeneous object needs 2 to 4",
            ),
            (
                BOX.to_string(),
                het(&[MARBLE; 5].join(","), checker),
                "objects[0].material.materials has 5 profiles",
            ),
            (
                BOX.to_string(),
                het(
                    &format!(r#"{MARBLE},{{"type":"dipole","preset":"jade"}}"#),
                    checker,
                ),
                "objects[0].material.materials[1].preset \"jade\" is not a known medium",
            ),
            (
                BOX.to_string(),
                het(
                    &format!("{MARBLE},{KETCHUP}"),
                    r#"{"type":"checkerboard","cell":0}"#,
                ),
                "objects[0].material.pattern.cell must be > 0",
            ),
            (
                BOX.to_string(),
                het(
                    &format!("{MARBLE},{KETCHUP}"),
                    r#"{"type":"checkerboard","cell":-1}"#,
                ),
                "objects[0].material.pattern.cell must be > 0",
            ),
            (
                r#""m.obj""#.to_string(),
                het(
                    &format!("{MARBLE},{KETCHUP}"),
                    r#"{"type":"by_obj_material","names":[]}"#,
                ),
                "objects[0].material.pattern.names has 0 names but there are 2 materials",
            ),
            (
                r#""m.obj""#.to_string(),
                het(
                    &format!("{MARBLE},{KETCHUP}"),
                    r#"{"type":"by_obj_material","names":["a","a"]}"#,
                ),
                "objects[0].material.pattern.names[1] \"a\" is listed twice",
            ),
            (
                r#""m.obj""#.to_string(),
                het(
                    &format!("{MARBLE},{KETCHUP}"),
                    r#"{"type":"by_obj_material","names":["a"," "]}"#,
                ),
                "objects[0].material.pattern.names[1] must not be empty",
            ),
            (
                BOX.to_string(),
                het(
                    &format!("{MARBLE},{KETCHUP}"),
                    r#"{"type":"by_obj_material","names":["a","b"]}"#,
                ),
                "objects[0].material.pattern by_obj_material needs an OBJ mesh",
            ),
        ];
        for (mesh, material, want) in cases {
            let got = validate(&mesh, &material).unwrap_err();
            assert!(
                got.starts_with(want),
                "{material}: got {got:?}, want {want:?}"
            );
        }
        // Decoding errors inside the pattern keep their path too.
        let e = parse_json::<SceneFile>(&scene(
            BOX,
            &het(
                &format!("{MARBLE},{KETCHUP}"),
                r#"{"type":"checkerboard","cell":0.1,"origin":[0,"x",0]}"#,
            ),
        ))
        .unwrap_err();
        assert_eq!(e.path, "objects[0].material.pattern.origin[1]", "{e}");
        let e = parse_json::<SceneFile>(&scene(
            BOX,
            &het(
                &format!("{MARBLE},{KETCHUP}"),
                r#"{"type":"stripes","cell":0.1}"#,
            ),
        ))
        .unwrap_err();
        assert!(e.message.contains("stripes"), "{e}");
    }
}

#[cfg(test)]
mod gltf_import_tests {
    use super::*;
    use crate::parse_json;

    #[test]
    fn a_gltf_import_parses_and_names_bad_overrides() {
        let text = r#"{"gltf": "room.glb",
            "materials": {"Wall": {"type": "diffuse", "albedo": [0.8, 0.1, 0.1]}},
            "light_overrides": {"Lamp": {"type": "point", "position": [0, 2, 0], "intensity": [3, 3, 3]},
                                "Fill": null}}"#;
        assert!(GltfSceneFile::is_gltf_import(text));
        assert!(!GltfSceneFile::is_gltf_import(r#"{"objects": []}"#));
        let s: GltfSceneFile = parse_json(text).unwrap();
        s.validate().unwrap();
        assert_eq!(s.light_overrides["Fill"], None);
        assert_eq!(s.materials["Wall"].kind(), "diffuse");
        let bad: GltfSceneFile = parse_json(
            r#"{"gltf": "room.glb", "materials": {"Wall": {"type": "diffuse", "albedo": [2, 0, 0]}}}"#,
        )
        .unwrap();
        assert_eq!(
            bad.validate().unwrap_err().to_string(),
            "materials.Wall.albedo[0] must be finite and in [0, 1]"
        );
        let e = parse_json::<GltfSceneFile>(r#"{"gltf": "room.glb", "lamps": []}"#).unwrap_err();
        assert!(e.message.contains("lamps"), "{e}");
    }
}

#[cfg(test)]
mod thin_sheet_tests {
    use super::*;
    use crate::parse_json;

    /// A petal-like object with a thin-sheet material whose thickness is `thickness` (JSON).
    fn petal(thickness: &str, t_terms: &str) -> String {
        format!(
            r#"{{"objects":[{{"name":"petal","mesh":{{"shape":"sheet","length":0.06,"width":0.03,"thickness":0.001}},
               "material":{{"type":"thin_sheet",
                 "reflectance":{{"type":"exponentials","terms":[{{"a":[0.1,0.05,0.08],"b":[1,1,1]}}]}},
                 "transmittance":{{"type":"exponentials","terms":[{t_terms}]}},"thickness_mm":{thickness}}}}}]}}"#
        )
    }
    const T_OK: &str = r#"{"a":[0.05,0.02,0.04],"b":[0.8,0.8,0.8]}"#;

    #[test]
    fn thin_sheet_parses_round_trips_and_validates() {
        let s: SceneFile = parse_json(&petal("1.0", T_OK)).unwrap();
        s.validate().unwrap();
        let m = &s.objects[0].material;
        assert_eq!(m.kind(), "thin_sheet");
        let Material::ThinSheet {
            reflectance: Profile::Exponentials { .. },
            transmittance: Profile::Exponentials { terms },
            thickness_mm,
            ..
        } = m
        else {
            panic!("{m:?}")
        };
        assert_eq!((*thickness_mm, terms[0].b[0]), (1.0, 0.8));
        let text = serde_json::to_string(&s).unwrap();
        assert!(text.contains(r#""type":"thin_sheet""#), "{text}");
        assert_eq!(parse_json::<SceneFile>(&text).unwrap(), s);
    }

    #[test]
    fn thin_sheet_errors_name_the_field() {
        for (thickness, want) in [
            ("0", "objects[0].material.thickness_mm must be > 0"),
            ("-1", "objects[0].material.thickness_mm must be > 0"),
        ] {
            let s: SceneFile = parse_json(&petal(thickness, T_OK)).unwrap();
            assert_eq!(s.validate().unwrap_err().to_string(), want);
        }
        // A bad transmittance coefficient names the profile it sits in.
        let s: SceneFile =
            parse_json(&petal("1", r#"{"a":[0.05,0.02,0.04],"b":[0.8,0,0.8]}"#)).unwrap();
        assert_eq!(
            s.validate().unwrap_err().to_string(),
            "objects[0].material.transmittance.terms[0].b[1] must be > 0 (the profile must fall off)"
        );
        // Decoding errors keep their path: a thickness that is not a number, a missing field.
        let e = parse_json::<SceneFile>(&petal(r#""thin""#, T_OK)).unwrap_err();
        assert_eq!(e.path, "objects[0].material.thickness_mm", "{e}");
        let e = parse_json::<SceneFile>(&petal("1", T_OK).replace(r#","thickness_mm":1"#, ""))
            .unwrap_err();
        assert!(e.message.contains("thickness_mm"), "{e}");
    }
}
