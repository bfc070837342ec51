//! A glTF 2.0 file as a whole scene: objects from its nodes, materials from its PBR
//! materials and their extensions, lights from `KHR_lights_punctual`, the first camera.
//!
//! In: a `.gltf`/`.glb` path (`translux-precompute room.glb`), or a scene file of the
//! [`GltfSceneFile`] form (`{"gltf": "room.glb", ...}`) that overrides materials and lights by
//! name and adds objects. Out: an ordinary [`SceneFile`] whose objects name their node as
//! `"room.glb#Wall"` ([`crate::meshio::split_node_ref`]); [`crate::scene`] loads those nodes
//! through [`GltfFile`], with each textured surface's [`AlbedoMap`], which the pipeline turns
//! into per-patch albedos ([`textured_albedos`]).
//!
//! The mapping (docs/scenes.md has it in full, with its limits):
//! - **Objects**: every node of the default scene (else of every root's tree) that has a
//!   mesh, named by the node's name, else its mesh's, else `node{i}`; a repeated name gets
//!   `.1`, `.2`, … (first come first named). Metres (`unit_mm` 1000), the file's winding
//!   (`orientation: as_is`).
//! - **Diffuse**: ρ = `baseColorFactor` × `baseColorTexture` (sRGB-decoded to linear, sampled
//!   bilinearly by `TEXCOORD_0` with the sampler's wrap modes, or nearest where its
//!   `magFilter` is NEAREST), averaged over each patch by [`TEXTURE_SAMPLES`]-style regular
//!   sub-triangles (enough that each covers about a texel, at most 8² per patch). The
//!   object's `albedo` is the area-weighted mean.
//! - **Emitters**: a material whose `emissiveFactor` × `emissiveTexture` ×
//!   `KHR_materials_emissive_strength` is not black: radiance (W·m⁻²·sr⁻¹) = that product,
//!   averaged over the object.
//! - **Translucent**: `KHR_materials_volume` with `thicknessFactor` > 0 and a transmission
//!   (`KHR_materials_transmission` or `KHR_materials_diffuse_transmission`, factor > 0):
//!   a dipole with σt = −ln(attenuationColor) / attenuationDistance (mm⁻¹; at least
//!   [`MIN_SIGMA_T`]), split by the single-scattering albedo α that gives the multiple-
//!   scattering albedo A = `KHR_materials_volume_scatter`'s `multiscatterColor` (else the base
//!   colour): α = 1 − (4.09712 + 4.20863 A − √(9.59217 + 41.6808 A + 17.7126 A²))² (Kulla and
//!   Conty 2017), σa = (1 − α) σt, σs′ = α σt (1 − g), g = `scatterAnisotropy`; η =
//!   `KHR_materials_ior` (1.5).
//! - **Lights**: point and spot intensity in candela → W·sr⁻¹ = cd / 683; directional
//!   illuminance in lux → W·m⁻² = lx / 683 (683 lm/W, the luminous efficacy at 555 nm); the
//!   colour multiplies it per channel. They shine along the node's −Z.
//! - **Camera**: the first node (in the walk) with a perspective camera: its position,
//!   looking along −Z with +Y up, `yfov` as the vertical field of view.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use glam::{Mat4, Vec3};
use rayon::prelude::*;
use serde_json::Value;
use translux_proto::light::{Camera, Light};
use translux_proto::scene::{
    DEFAULT_UNIT_MM, GltfSceneFile, MAX_SIGMA, Material, MeshRef, ObjectDesc, Orientation, Profile,
    SceneFile,
};

use crate::meshio::{self, GLTF_EXTENSIONS, MeshError};
use crate::patch::Patches;

/// Lumens per watt at 555 nm: photometric glTF lights → radiometric translux lights.
pub const LUMENS_PER_WATT: f32 = 683.0;

/// The smallest extinction σt a glTF medium gets (mm⁻¹): a mean free path of a metre, where
/// the file's attenuation colour is 1 or it gives no attenuation distance (a clear medium,
/// which the dipole cannot represent).
pub const MIN_SIGMA_T: f32 = 1e-3;

/// Most sub-triangles per patch side when a texture is averaged over a patch (8² = 64
/// samples).
pub const TEXTURE_SAMPLES: usize = 8;

fn malformed(detail: impl Into<String>) -> MeshError {
    MeshError::Malformed(detail.into())
}

// ---------------------------------------------------------------------------------------
// Textures

/// How a texture coordinate outside [0, 1] wraps (the glTF sampler's `wrapS`/`wrapT`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Wrap {
    Repeat,
    Clamp,
    Mirror,
}

impl Wrap {
    fn from_gl(code: Option<u64>) -> Wrap {
        match code {
            Some(33071) => Wrap::Clamp,
            Some(33648) => Wrap::Mirror,
            _ => Wrap::Repeat,
        }
    }

    /// Texel index for integer texel coordinate `i` of a row or column of `n`.
    fn index(self, i: i64, n: usize) -> usize {
        let n = n as i64;
        let k = match self {
            Wrap::Repeat => i.rem_euclid(n),
            Wrap::Clamp => i.clamp(0, n - 1),
            Wrap::Mirror => {
                let m = i.rem_euclid(2 * n);
                if m < n { m } else { 2 * n - 1 - m }
            }
        };
        k as usize
    }
}

/// A colour texture decoded to linear RGB (the sRGB transfer function undone), with its
/// sampler's wrap modes and filter.
#[derive(Debug, Clone, PartialEq)]
pub struct Texture {
    pub width: usize,
    pub height: usize,
    /// Row-major from the top row (glTF's v = 0), linear RGB.
    pub texels: Vec<[f32; 3]>,
    pub wrap: [Wrap; 2],
    /// Nearest texel instead of bilinear (the sampler's `magFilter` is NEAREST).
    pub nearest: bool,
}

/// The sRGB transfer function undone: an encoded value in [0, 1] to linear.
pub fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

impl Texture {
    /// The linear colour at texture coordinate `uv` (u right, v down, texel centres at
    /// half-integers × size).
    pub fn sample(&self, uv: [f32; 2]) -> [f32; 3] {
        let x = uv[0] * self.width as f32 - 0.5;
        let y = uv[1] * self.height as f32 - 0.5;
        let at = |i: i64, j: i64| {
            let (i, j) = (
                self.wrap[0].index(i, self.width),
                self.wrap[1].index(j, self.height),
            );
            self.texels[j * self.width + i]
        };
        if self.nearest {
            return at(x.round() as i64, y.round() as i64);
        }
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (i, j) = (x0 as i64, y0 as i64);
        let (a, b, c, d) = (at(i, j), at(i + 1, j), at(i, j + 1), at(i + 1, j + 1));
        std::array::from_fn(|k| {
            let top = a[k] + (b[k] - a[k]) * fx;
            let bottom = c[k] + (d[k] - c[k]) * fx;
            top + (bottom - top) * fy
        })
    }

    /// The mean of all texels.
    pub fn mean(&self) -> [f32; 3] {
        let mut sum = [0.0f64; 3];
        for t in &self.texels {
            for k in 0..3 {
                sum[k] += f64::from(t[k]);
            }
        }
        sum.map(|s| (s / self.texels.len().max(1) as f64) as f32)
    }

    /// The mean colour over the texture-space triangle `uv` (regular sub-triangles, each
    /// sampled at its centroid: enough that one spans about a texel, at most
    /// [`TEXTURE_SAMPLES`]² of them).
    pub fn mean_over(&self, uv: [[f32; 2]; 3]) -> [f32; 3] {
        let texels = |a: [f32; 2], b: [f32; 2]| {
            ((a[0] - b[0]) * self.width as f32).hypot((a[1] - b[1]) * self.height as f32)
        };
        let span = texels(uv[0], uv[1])
            .max(texels(uv[1], uv[2]))
            .max(texels(uv[2], uv[0]));
        let n = (span.ceil() as usize).clamp(1, TEXTURE_SAMPLES);
        let nf = n as f32;
        let point = |i: f32, j: f32| -> [f32; 2] {
            // P(i, j) = a + i (b − a)/n + j (c − a)/n.
            std::array::from_fn(|k| {
                uv[0][k] + (uv[1][k] - uv[0][k]) * i / nf + (uv[2][k] - uv[0][k]) * j / nf
            })
        };
        let mut sum = [0.0f64; 3];
        let mut count = 0usize;
        for i in 0..n {
            for j in 0..n - i {
                let (fi, fj) = (i as f32, j as f32);
                let mut cells = vec![point(fi + 1.0 / 3.0, fj + 1.0 / 3.0)];
                if i + j + 2 <= n {
                    cells.push(point(fi + 2.0 / 3.0, fj + 2.0 / 3.0));
                }
                for p in cells {
                    let c = self.sample(p);
                    for k in 0..3 {
                        sum[k] += f64::from(c[k]);
                    }
                    count += 1;
                }
            }
        }
        sum.map(|s| (s / count as f64) as f32)
    }
}

// ---------------------------------------------------------------------------------------
// Per-patch albedo

/// One triangle of a textured object: where it is (scene units, as loaded), its corners'
/// texture coordinates, the base colour factor and the texture (index into
/// [`AlbedoMap::textures`]) of its primitive's material.
#[derive(Debug, Clone, PartialEq)]
pub struct TexturedTriangle {
    pub corners: [Vec3; 3],
    pub uv: [[f32; 2]; 3],
    pub factor: [f32; 3],
    pub texture: Option<usize>,
}

/// The albedo over an object's surface, per triangle (aligned with the object's loaded
/// triangles): what a glTF base colour texture (or primitives of different base colours)
/// gives. [`textured_albedos`] averages it over each patch.
#[derive(Debug, Clone, PartialEq)]
pub struct AlbedoMap {
    pub triangles: Vec<TexturedTriangle>,
    pub textures: Vec<Arc<Texture>>,
}

/// Barycentric weights of `p` in triangle `t` (p projected onto its plane), clamped inside.
fn barycentric(t: &[Vec3; 3], p: Vec3) -> [f32; 3] {
    let (v0, v1, v2) = (t[1] - t[0], t[2] - t[0], p - t[0]);
    let (d00, d01, d11) = (v0.dot(v0), v0.dot(v1), v1.dot(v1));
    let (d20, d21) = (v2.dot(v0), v2.dot(v1));
    let den = d00 * d11 - d01 * d01;
    if den.abs() <= f32::MIN_POSITIVE {
        return [1.0, 0.0, 0.0];
    }
    let v = ((d11 * d20 - d01 * d21) / den).clamp(0.0, 1.0);
    let w = ((d00 * d21 - d01 * d20) / den).clamp(0.0, 1.0 - v);
    [1.0 - v - w, v, w]
}

impl AlbedoMap {
    /// The albedo averaged over the part `patch` (three points in the plane of triangle
    /// `tri`) of triangle `tri`: the factor times the texture's mean over the patch's
    /// texture-space image, clamped to [0, 1].
    pub fn mean_over(&self, tri: usize, patch: &[Vec3; 3]) -> [f32; 3] {
        let t = &self.triangles[tri];
        let tex = t.texture.and_then(|k| self.textures.get(k));
        let Some(tex) = tex else {
            return t.factor.map(|f| f.clamp(0.0, 1.0));
        };
        let uv = patch.map(|p| {
            let w = barycentric(&t.corners, p);
            std::array::from_fn(|k| w[0] * t.uv[0][k] + w[1] * t.uv[1][k] + w[2] * t.uv[2][k])
        });
        let m = tex.mean_over(uv);
        std::array::from_fn(|k| (t.factor[k] * m[k]).clamp(0.0, 1.0))
    }

    /// The area-weighted mean albedo over the whole object.
    pub fn object_mean(&self) -> [f32; 3] {
        let (mut sum, mut area) = ([0.0f64; 3], 0.0f64);
        for (k, t) in self.triangles.iter().enumerate() {
            let a = f64::from(
                0.5 * (t.corners[1] - t.corners[0])
                    .cross(t.corners[2] - t.corners[0])
                    .length(),
            );
            let m = self.mean_over(k, &t.corners);
            for c in 0..3 {
                sum[c] += a * f64::from(m[c]);
            }
            area += a;
        }
        if area <= 0.0 {
            return [0.0; 3];
        }
        sum.map(|s| (s / area) as f32)
    }
}

/// The albedo of every patch of a textured object (`objects`: each loaded object's
/// triangles and [`AlbedoMap`], if any, in scene order), as (patch index, ρ): patches
/// follow their objects' triangles in order,
/// [`crate::patch::split_count`] of them per triangle at edge length `h`
/// ([`crate::patch::subdivide`]). Empty when no object is textured.
pub fn textured_albedos(
    objects: &[(&[[Vec3; 3]], Option<&AlbedoMap>)],
    patches: &Patches,
    h: f32,
) -> Vec<(usize, [f32; 3])> {
    let mut out = Vec::new();
    for (&(triangles, map), range) in objects.iter().zip(&patches.object_ranges) {
        let Some(map) = map else {
            continue;
        };
        if map.triangles.len() != triangles.len() {
            continue;
        }
        // The first patch of each source triangle.
        let mut first = Vec::with_capacity(triangles.len());
        let mut p = range.start;
        for t in triangles {
            first.push(p);
            p += crate::patch::split_count(t, h);
        }
        if p != range.end {
            continue;
        }
        let per: Vec<Vec<(usize, [f32; 3])>> = triangles
            .par_iter()
            .enumerate()
            .map(|(k, t)| {
                let start = first[k];
                (start..start + crate::patch::split_count(t, h))
                    .map(|q| (q, map.mean_over(k, &patches.corners[q])))
                    .collect()
            })
            .collect();
        out.extend(per.into_iter().flatten());
    }
    out
}

/// Writes textured patches' albedos into a diffuse S, whose row j of an opaque patch holds
/// its one diagonal entry S_jj = ρ_j.
pub fn set_diagonal(s: &mut translux_proto::csr::Csr<[f32; 3]>, albedos: &[(usize, [f32; 3])]) {
    for &(p, rho) in albedos {
        let (Some(&a), Some(&b)) = (s.row_ptr.get(p), s.row_ptr.get(p + 1)) else {
            continue;
        };
        for k in a as usize..b as usize {
            if s.col[k] as usize == p {
                s.val[k] = rho;
            }
        }
    }
}

// ---------------------------------------------------------------------------------------
// The file

/// A glTF file opened for import: its validated document, buffers and JSON as written, the
/// objects it gives (node, world transform, name) and its decoded textures, made as asked.
#[derive(Debug)]
pub struct GltfFile {
    path: PathBuf,
    doc: gltf::Document,
    buffers: Vec<Vec<u8>>,
    raw: Value,
    /// (node index, world transform, object name), in walk order.
    objects: Vec<(usize, Mat4, String)>,
    /// (node index, world transform) of every node the walk places.
    placed: Vec<(usize, Mat4)>,
    textures: Mutex<HashMap<usize, Result<Arc<Texture>, String>>>,
}

/// Lights with their names in the file.
pub type NamedLights = Vec<(String, Light)>;

/// What one object of the file is made of: its triangles, their texture coordinates, the
/// material of each, and the translux material they make with its notes.
#[derive(Debug)]
pub struct NodeObject {
    pub triangles: Vec<[Vec3; 3]>,
    pub material: Material,
    /// The per-triangle albedo, for a diffuse object with a texture or several base colours.
    pub albedo_map: Option<AlbedoMap>,
    pub notes: Vec<String>,
}

/// The material a glTF material gives, before averaging textures.
#[derive(Debug, Clone)]
enum Kind {
    Diffuse,
    Emitter([f32; 3]),
    Translucent(Box<Material>),
}

/// A JSON number array of length `N`, else `default`.
fn floats<const N: usize>(v: &Value, default: [f32; N]) -> [f32; N] {
    match v.as_array() {
        Some(a) if a.len() == N && a.iter().all(Value::is_number) => {
            std::array::from_fn(|k| a[k].as_f64().unwrap_or(0.0) as f32)
        }
        _ => default,
    }
}

fn float(v: &Value, default: f32) -> f32 {
    v.as_f64().map_or(default, |x| x as f32)
}

/// A colour value checked finite and ≥ 0.
fn colour(v: [f32; 3], what: &str) -> Result<[f32; 3], String> {
    if v.iter().all(|x| x.is_finite() && *x >= 0.0) {
        Ok(v)
    } else {
        Err(format!("{what} {v:?} must be finite and >= 0"))
    }
}

/// The single-scattering albedo α whose medium scatters back the multiple-scattering
/// albedo `a` (Kulla and Conty 2017's fit, inverted van de Hulst): α(0) = 0, α(1) = 1.
pub fn single_scattering_albedo(a: f32) -> f32 {
    let a = a.clamp(0.0, 1.0);
    let s = 4.09712 + 4.20863 * a - (9.59217 + 41.6808 * a + 17.7126 * a * a).sqrt();
    (1.0 - s * s).clamp(0.0, 1.0)
}

/// The dipole medium of a glTF volume (see the module's doc).
pub fn volume_medium(
    attenuation_colour: [f32; 3],
    attenuation_distance_m: f32,
    scatter_colour: [f32; 3],
    anisotropy: f32,
    ior: f32,
) -> Material {
    let g = anisotropy.clamp(-0.99, 0.99);
    let d_mm = attenuation_distance_m * 1000.0;
    let mut sigma_a = [0.0f32; 3];
    let mut sigma_s_prime = [0.0f32; 3];
    for c in 0..3 {
        let t = if d_mm.is_finite() && d_mm > 0.0 {
            -(attenuation_colour[c].clamp(1e-12, 1.0)).ln() / d_mm
        } else {
            0.0
        };
        let t = t.clamp(MIN_SIGMA_T, MAX_SIGMA);
        let alpha = single_scattering_albedo(scatter_colour[c]);
        sigma_a[c] = (1.0 - alpha) * t;
        sigma_s_prime[c] = alpha * t * (1.0 - g);
    }
    Material::Translucent {
        profile: Profile::Dipole {
            preset: None,
            sigma_a: Some(sigma_a),
            sigma_s_prime: Some(sigma_s_prime),
            eta: Some(ior.clamp(1.0, 3.0)),
            scale: None,
        },
        specular: None,
    }
}

impl GltfFile {
    /// Opens `path`: the document (a required extension translux does not read is refused
    /// by name), its buffers and the objects' names.
    pub fn open(path: &Path) -> Result<GltfFile, MeshError> {
        let (doc, blob) = meshio::gltf_document(path)?;
        let base = match path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p,
            _ => Path::new("."),
        };
        let buffers = meshio::load_buffers(&doc, base, blob)?;
        let raw = meshio::gltf_raw_json(path)?;
        let placed: Vec<(usize, Mat4)> = meshio::gltf_placed(&doc)?
            .into_iter()
            .map(|(n, w)| (n.index(), w))
            .collect();
        let nodes: Vec<gltf::Node> = doc.nodes().collect();
        let mut taken = std::collections::HashSet::new();
        let mut objects = Vec::new();
        let named = |s: Option<&str>| {
            s.map(str::trim)
                .filter(|s| !s.is_empty())
                .map(str::to_owned)
        };
        for &(i, world) in &placed {
            let node = &nodes[i];
            let Some(mesh) = node.mesh() else { continue };
            let base_name = named(node.name())
                .or_else(|| named(mesh.name()))
                .unwrap_or_else(|| format!("node{i}"));
            let mut name = base_name.clone();
            let mut k = 1;
            while taken.contains(&name) {
                name = format!("{base_name}.{k}");
                k += 1;
            }
            taken.insert(name.clone());
            objects.push((i, world, name));
        }
        if objects.is_empty() {
            return Err(malformed(if doc.meshes().len() == 0 {
                "the file has no meshes".to_owned()
            } else {
                format!(
                    "no node of the scene places any of its {} meshes",
                    doc.meshes().len()
                )
            }));
        }
        Ok(GltfFile {
            path: path.to_path_buf(),
            doc,
            buffers,
            raw,
            objects,
            placed,
            textures: Mutex::new(HashMap::new()),
        })
    }

    /// The objects' names, in the file's walk order.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.objects.iter().map(|(_, _, n)| n.as_str())
    }

    /// Notes on what the file uses that translux reads past: optional extensions it does
    /// not read, lights' `range`, a camera it cannot use.
    pub fn file_notes(&self) -> Vec<String> {
        let mut notes = Vec::new();
        if let Ok((_, n)) = self.lights() {
            notes.extend(n);
        }
        self.camera(&mut notes);
        for e in self.raw["extensionsUsed"].as_array().into_iter().flatten() {
            let Some(e) = e.as_str() else { continue };
            if !GLTF_EXTENSIONS.contains(&e) {
                notes.push(format!(
                    "the file uses extension \"{e}\", which translux does not read: ignored"
                ));
            }
        }
        notes
    }

    /// The file's lights (`KHR_lights_punctual`) as (name, light), in walk order; an
    /// unnamed light is `light{i}`. Notes say what was read past (`range`).
    pub fn lights(&self) -> Result<(NamedLights, Vec<String>), String> {
        let defs = self.raw["extensions"]["KHR_lights_punctual"]["lights"]
            .as_array()
            .cloned()
            .unwrap_or_default();
        let mut out = Vec::new();
        let mut notes = Vec::new();
        for &(n, world) in &self.placed {
            let Some(l) =
                self.raw["nodes"][n]["extensions"]["KHR_lights_punctual"]["light"].as_u64()
            else {
                continue;
            };
            let at = format!("node {n}: KHR_lights_punctual light {l}");
            let def = defs.get(l as usize).ok_or_else(|| {
                format!("{at} does not exist (the file has {} lights)", defs.len())
            })?;
            let name = def["name"]
                .as_str()
                .filter(|s| !s.trim().is_empty())
                .map_or_else(|| format!("light{l}"), str::to_owned);
            let colour = colour(floats(&def["color"], [1.0; 3]), &format!("{at} color"))?;
            let intensity = float(&def["intensity"], 1.0);
            if !(intensity.is_finite() && intensity >= 0.0) {
                return Err(format!(
                    "{at} intensity {intensity} must be finite and >= 0"
                ));
            }
            // cd → W·sr⁻¹ and lx → W·m⁻²: both / 683 lm/W.
            let power = colour.map(|c| c * intensity / LUMENS_PER_WATT);
            let position = world.transform_point3(Vec3::ZERO);
            let direction = world.transform_vector3(Vec3::NEG_Z).normalize_or_zero();
            if !position.is_finite() || direction == Vec3::ZERO {
                return Err(format!("{at}: its node's transform is degenerate"));
            }
            if def.get("range").is_some() {
                notes.push(format!(
                    "light \"{name}\": `range` is ignored (the light falls off as 1/r² \
                     everywhere)"
                ));
            }
            let light = match def["type"].as_str() {
                Some("point") => Light::Point {
                    position: position.to_array(),
                    intensity: power,
                },
                Some("spot") => {
                    let inner = float(&def["spot"]["innerConeAngle"], 0.0).to_degrees();
                    let outer = float(&def["spot"]["outerConeAngle"], std::f32::consts::FRAC_PI_4)
                        .to_degrees();
                    Light::Spot {
                        position: position.to_array(),
                        intensity: power,
                        direction: direction.to_array(),
                        inner_deg: inner.clamp(0.0, outer.max(0.0)),
                        outer_deg: outer,
                    }
                }
                Some("directional") => Light::Directional {
                    direction: direction.to_array(),
                    irradiance: power,
                },
                other => {
                    return Err(format!(
                        "{at} has type {}; the types are point, spot and directional",
                        other.map_or("(none)".to_owned(), |t| format!("\"{t}\""))
                    ));
                }
            };
            out.push((name, light));
        }
        Ok((out, notes))
    }

    /// The first perspective camera in walk order (an orthographic one is noted and
    /// skipped).
    pub fn camera(&self, notes: &mut Vec<String>) -> Option<Camera> {
        let nodes: Vec<gltf::Node> = self.doc.nodes().collect();
        for &(n, world) in &self.placed {
            let Some(cam) = nodes[n].camera() else {
                continue;
            };
            match cam.projection() {
                gltf::camera::Projection::Perspective(p) => {
                    let position = world.transform_point3(Vec3::ZERO);
                    let forward = world.transform_vector3(Vec3::NEG_Z).normalize_or_zero();
                    let up = world.transform_vector3(Vec3::Y).normalize_or_zero();
                    let camera = Camera {
                        position: position.to_array(),
                        target: (position + forward).to_array(),
                        up: up.to_array(),
                        fov_deg: p.yfov().to_degrees().clamp(1.0, 170.0),
                    };
                    if camera.validate("camera").is_ok() {
                        return Some(camera);
                    }
                    notes.push(format!(
                        "node {n}'s camera has a degenerate transform: ignored"
                    ));
                }
                gltf::camera::Projection::Orthographic(_) => notes.push(format!(
                    "node {n}'s camera is orthographic; the viewer's camera is perspective: \
                     ignored"
                )),
            }
        }
        None
    }

    /// Texture `index` decoded to linear RGB with its sampler (cached).
    fn texture(&self, index: usize) -> Result<Arc<Texture>, String> {
        if let Some(t) = self
            .textures
            .lock()
            .ok()
            .and_then(|c| c.get(&index).cloned())
        {
            return t;
        }
        let made = self.decode_texture(index).map(Arc::new);
        if let Ok(mut c) = self.textures.lock() {
            c.insert(index, made.clone());
        }
        made
    }

    fn decode_texture(&self, index: usize) -> Result<Texture, String> {
        use base64::Engine as _;
        let tex = &self.raw["textures"][index];
        let at = format!("texture {index}");
        let Some(source) = tex["source"].as_u64() else {
            return Err(format!(
                "{at} has no PNG `source` (a texture only in an extension, such as \
                 KHR_texture_basisu or EXT_texture_webp, is not read)"
            ));
        };
        let image = &self.raw["images"][source as usize];
        let at = format!("{at} (image {source})");
        let bytes: Vec<u8> = if let Some(uri) = image["uri"].as_str() {
            if uri.starts_with("data:") {
                let (_, payload) = uri.split_once(',').unwrap_or((uri, ""));
                base64::engine::general_purpose::STANDARD
                    .decode(payload)
                    .map_err(|e| format!("{at}: bad base64 data URI: {e}"))?
            } else {
                let rel = percent_encoding::percent_decode_str(uri)
                    .decode_utf8()
                    .map_err(|_| format!("{at}: URI \"{uri}\" is not UTF-8"))?;
                let base = self.path.parent().unwrap_or(Path::new("."));
                let file = base.join(rel.as_ref());
                std::fs::read(&file)
                    .map_err(|e| format!("{at}: cannot read \"{rel}\" ({}): {e}", file.display()))?
            }
        } else if let Some(v) = image["bufferView"].as_u64() {
            let view = self
                .doc
                .views()
                .nth(v as usize)
                .ok_or_else(|| format!("{at}: buffer view {v} does not exist"))?;
            let buf = &self.buffers[view.buffer().index()];
            view.offset()
                .checked_add(view.length())
                .and_then(|end| buf.get(view.offset()..end))
                .ok_or_else(|| format!("{at}: buffer view {v} runs past its buffer"))?
                .to_vec()
        } else {
            return Err(format!("{at} has neither `uri` nor `bufferView`"));
        };
        let format = image::guess_format(&bytes).ok();
        if format != Some(image::ImageFormat::Png) {
            return Err(format!(
                "{at} is {}; translux decodes PNG textures only (re-export the textures as \
                 PNG)",
                format.map_or("not an image it recognises".to_owned(), |f| format!(
                    "{f:?}"
                ))
            ));
        }
        let decoded = image::load_from_memory_with_format(&bytes, image::ImageFormat::Png)
            .map_err(|e| format!("{at}: cannot decode the PNG: {e}"))?
            .to_rgb32f();
        let (width, height) = (decoded.width() as usize, decoded.height() as usize);
        if width == 0 || height == 0 {
            return Err(format!("{at} is empty"));
        }
        let texels = decoded.pixels().map(|p| p.0.map(srgb_to_linear)).collect();
        let sampler = tex["sampler"]
            .as_u64()
            .map_or(Value::Null, |s| self.raw["samplers"][s as usize].clone());
        Ok(Texture {
            width,
            height,
            texels,
            wrap: [
                Wrap::from_gl(sampler["wrapS"].as_u64()),
                Wrap::from_gl(sampler["wrapT"].as_u64()),
            ],
            nearest: sampler["magFilter"].as_u64() == Some(9728),
        })
    }

    /// What glTF material `m` (None: the default material) makes, with notes.
    fn kind_of(&self, m: Option<usize>, notes: &mut Vec<String>) -> Result<Kind, String> {
        let Some(m) = m else {
            return Ok(Kind::Diffuse);
        };
        let mat = &self.raw["materials"][m];
        let label = match mat["name"].as_str() {
            Some(n) => format!("material {m} \"{n}\""),
            None => format!("material {m}"),
        };
        let ext = &mat["extensions"];
        let strength = float(
            &ext["KHR_materials_emissive_strength"]["emissiveStrength"],
            1.0,
        );
        let emissive = colour(
            floats(&mat["emissiveFactor"], [0.0; 3]).map(|c| c * strength),
            &format!("{label}: emissiveFactor × emissiveStrength"),
        )?;
        if emissive.iter().any(|&c| c > 0.0) {
            let mut radiance = emissive;
            if let Some(t) = mat["emissiveTexture"]["index"].as_u64() {
                match self.texture(t as usize) {
                    // The texture's mean over its whole image: an emitter is uniform.
                    Ok(tex) => {
                        let mean = tex.mean();
                        radiance = std::array::from_fn(|k| radiance[k] * mean[k]);
                    }
                    Err(e) => notes.push(format!("{label}: emissiveTexture not used: {e}")),
                }
            }
            return Ok(Kind::Emitter(radiance));
        }
        let transmission = float(
            &ext["KHR_materials_transmission"]["transmissionFactor"],
            0.0,
        )
        .max(float(
            &ext["KHR_materials_diffuse_transmission"]["diffuseTransmissionFactor"],
            0.0,
        ));
        let volume = &ext["KHR_materials_volume"];
        if transmission > 0.0 && volume.is_object() {
            if float(&volume["thicknessFactor"], 0.0) <= 0.0 {
                notes.push(format!(
                    "{label}: KHR_materials_volume with thicknessFactor 0 is thin-walled, \
                     which translux does not model: diffuse with the base colour"
                ));
                return Ok(Kind::Diffuse);
            }
            let base = floats(&mat["pbrMetallicRoughness"]["baseColorFactor"], [1.0; 4]);
            let scatter = &ext["KHR_materials_volume_scatter"];
            let multiscatter = if scatter.is_object() {
                floats(&scatter["multiscatterColor"], [0.0; 3])
            } else {
                [base[0], base[1], base[2]]
            };
            let attenuation = colour(
                floats(&volume["attenuationColor"], [1.0; 3]),
                &format!("{label}: attenuationColor"),
            )?;
            let distance = float(&volume["attenuationDistance"], f32::INFINITY);
            if distance <= 0.0 || distance.is_nan() {
                return Err(format!(
                    "{label}: attenuationDistance {distance} must be > 0"
                ));
            }
            let ior = float(&ext["KHR_materials_ior"]["ior"], 1.5);
            if ior < 1.0 {
                notes.push(format!(
                    "{label}: ior {ior} is below 1 (translux's η is in [1, 3]): taken as 1"
                ));
            }
            let medium = volume_medium(
                attenuation,
                distance,
                multiscatter,
                float(&scatter["scatterAnisotropy"], 0.0),
                ior,
            );
            return Ok(Kind::Translucent(Box::new(medium)));
        }
        if transmission > 0.0 {
            notes.push(format!(
                "{label}: transmission without KHR_materials_volume (a thin surface) is not \
                 modelled: diffuse with the base colour"
            ));
        }
        Ok(Kind::Diffuse)
    }

    /// The object named `name`: its triangles in world coordinates (metres) and its material.
    pub fn object(&self, name: &str) -> Result<NodeObject, MeshError> {
        let Some(&(n, world, _)) = self.objects.iter().find(|(_, _, o)| o == name) else {
            let names: Vec<&str> = self.names().collect();
            return Err(malformed(format!(
                "has no object \"{name}\"; its objects (nodes with a mesh) are {}",
                names.join(", ")
            )));
        };
        let node = self.doc.nodes().nth(n).expect("a placed node exists");
        let mesh = node.mesh().expect("an object's node has a mesh");
        let mut triangles = Vec::new();
        let mut uvs = Vec::new();
        let mut prim_of = Vec::new();
        let mut has_uv = Vec::new();
        for prim in mesh.primitives() {
            let before = triangles.len();
            let had = meshio::read_primitive(
                &mesh,
                &prim,
                &self.buffers,
                world,
                &mut triangles,
                Some(&mut uvs),
            )?;
            prim_of.extend(std::iter::repeat_n(prim.index(), triangles.len() - before));
            has_uv.push(had);
        }
        let mut notes = Vec::new();
        // Each primitive's material, then the object's: the first primitive that is
        // translucent or emits decides; otherwise diffuse with per-triangle colours.
        let prims: Vec<gltf::Primitive> = mesh.primitives().collect();
        let mut kinds = Vec::with_capacity(prims.len());
        for p in &prims {
            kinds.push(
                self.kind_of(p.material().index(), &mut notes)
                    .map_err(malformed)?,
            );
        }
        let special = kinds.iter().position(|k| !matches!(k, Kind::Diffuse));
        if let Some(s) = special {
            let first = prims[0].material().index();
            if prims.iter().any(|p| p.material().index() != first) {
                notes.push(format!(
                    "its mesh's primitives have different materials; one translux object \
                     has one: primitive {s}'s is used for all"
                ));
            }
            let material = match &kinds[s] {
                Kind::Emitter(r) => Material::Emitter { radiance: *r },
                Kind::Translucent(m) => (**m).clone(),
                Kind::Diffuse => unreachable!("special is not diffuse"),
            };
            return Ok(NodeObject {
                triangles,
                material,
                albedo_map: None,
                notes,
            });
        }
        // Diffuse: per triangle, the base colour factor and texture of its primitive.
        let mut textures: Vec<Arc<Texture>> = Vec::new();
        let mut tex_slot: HashMap<usize, usize> = HashMap::new();
        let mut prim_info: Vec<([f32; 3], Option<usize>)> = Vec::new();
        for (k, p) in prims.iter().enumerate() {
            let Some(m) = p.material().index() else {
                prim_info.push(([1.0; 3], None));
                continue;
            };
            let mat = &self.raw["materials"][m];
            let pbr = &mat["pbrMetallicRoughness"];
            let f = floats(&pbr["baseColorFactor"], [1.0; 4]);
            let factor = colour(
                [f[0], f[1], f[2]],
                &format!("material {m}: baseColorFactor"),
            )
            .map_err(malformed)?;
            let mut slot = None;
            if let Some(t) = pbr["baseColorTexture"]["index"].as_u64() {
                if pbr["baseColorTexture"]["texCoord"].as_u64().unwrap_or(0) != 0 {
                    notes.push(format!(
                        "material {m}: baseColorTexture uses texCoord {}; translux reads \
                         TEXCOORD_0 only",
                        pbr["baseColorTexture"]["texCoord"]
                    ));
                }
                if !has_uv[k] {
                    notes.push(format!(
                        "primitive {k} has no TEXCOORD_0 it can read: material {m}'s \
                         baseColorTexture is not used"
                    ));
                } else {
                    match self.texture(t as usize) {
                        Ok(tex) => {
                            slot = Some(*tex_slot.entry(t as usize).or_insert_with(|| {
                                textures.push(tex);
                                textures.len() - 1
                            }));
                        }
                        Err(e) => {
                            notes.push(format!("material {m}: baseColorTexture not used: {e}"))
                        }
                    }
                }
            }
            prim_info.push((factor, slot));
        }
        let map = AlbedoMap {
            triangles: triangles
                .iter()
                .zip(&uvs)
                .zip(&prim_of)
                .map(|((t, uv), &p)| TexturedTriangle {
                    corners: *t,
                    uv: *uv,
                    factor: prim_info[p].0,
                    texture: prim_info[p].1,
                })
                .collect(),
            textures,
        };
        let albedo = map.object_mean();
        let uniform = map.textures.is_empty() && prim_info.windows(2).all(|w| w[0].0 == w[1].0);
        Ok(NodeObject {
            triangles,
            material: Material::Diffuse {
                albedo,
                specular: None,
            },
            albedo_map: (!uniform).then_some(map),
            notes,
        })
    }
}

// ---------------------------------------------------------------------------------------
// The scene

/// Why a glTF scene could not be made, before the scene's name is put on it.
#[derive(Debug)]
pub enum ImportError {
    /// The glTF file could not be read or is not valid.
    File(MeshError),
    /// A field of the importing scene file (`materials.Wall`, `light_overrides.Lamp`) names
    /// something the file does not have, or the file holds an unusable value.
    Field(translux_proto::FieldError),
}

/// The scene a glTF file makes, with what `import` (a `{"gltf": ...}` scene file) overrides
/// and adds. `gltf` is the file's path as the mesh references will name it (relative to the
/// scene's folder), `path` where it is. What the import reads past is noted when the
/// scene's objects load ([`GltfFile::file_notes`], [`NodeObject::notes`]).
pub fn scene_from_gltf(
    path: &Path,
    gltf: &str,
    import: Option<&GltfSceneFile>,
) -> Result<SceneFile, ImportError> {
    use translux_proto::FieldError;
    let file = GltfFile::open(path).map_err(ImportError::File)?;
    let (lights, _) = file.lights().map_err(|e| ImportError::File(malformed(e)))?;
    let camera = file.camera(&mut Vec::new());
    // Each object's own material: the file's objects load in parallel.
    let names: Vec<String> = file.names().map(str::to_owned).collect();
    let made: Vec<Result<Material, MeshError>> = names
        .par_iter()
        .map(|n| file.object(n).map(|o| o.material))
        .collect();
    let mut objects = Vec::with_capacity(names.len());
    for (name, m) in names.iter().zip(made) {
        let material = m.map_err(ImportError::File)?;
        objects.push(ObjectDesc {
            name: name.clone(),
            mesh: MeshRef::Path(format!("{gltf}#{name}")),
            transform: None,
            material,
            crease_deg: None,
            simplify_to: None,
            orientation: Orientation::AsIs,
            keyframes: None,
        });
    }
    let mut lights = lights;
    let mut scene = SceneFile {
        name: None,
        objects,
        lights: Vec::new(),
        unit_mm: DEFAULT_UNIT_MM,
        patches: None,
        camera,
        animation: None,
    };
    if let Some(imp) = import {
        imp.validate().map_err(ImportError::Field)?;
        let list = |v: Vec<&str>| {
            if v.is_empty() {
                "none".to_owned()
            } else {
                v.join(", ")
            }
        };
        for (name, m) in &imp.materials {
            let Some(o) = scene.objects.iter_mut().find(|o| &o.name == name) else {
                return Err(ImportError::Field(FieldError::new(
                    format!("materials.{name}"),
                    format!(
                        "names no object of \"{gltf}\"; its objects are {}",
                        list(names.iter().map(String::as_str).collect())
                    ),
                )));
            };
            o.material = m.clone();
        }
        for (name, l) in &imp.light_overrides {
            let Some(k) = lights.iter().position(|(n, _)| n == name) else {
                return Err(ImportError::Field(FieldError::new(
                    format!("light_overrides.{name}"),
                    format!(
                        "names no light of \"{gltf}\"; its lights are {}",
                        list(lights.iter().map(|(n, _)| n.as_str()).collect())
                    ),
                )));
            };
            match l {
                Some(l) => lights[k].1 = l.clone(),
                None => {
                    lights.remove(k);
                }
            }
        }
        if let Some(l) = &imp.lights {
            lights = l.iter().map(|l| (String::new(), l.clone())).collect();
        }
        scene.objects.extend(imp.objects.iter().cloned());
        scene.name = imp.name.clone();
        scene.patches = imp.patches;
        if imp.camera.is_some() {
            scene.camera = imp.camera;
        }
    }
    scene.lights = lights.into_iter().map(|(_, l)| l).collect();
    Ok(scene)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_decoding_and_albedo_inversion_hit_their_ends() {
        assert_eq!(srgb_to_linear(0.0), 0.0);
        assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-6);
        // sRGB 200/255 is linear 0.578.
        assert!((srgb_to_linear(200.0 / 255.0) - 0.5776).abs() < 1e-3);
        assert!(single_scattering_albedo(0.0).abs() < 1e-4);
        assert!((single_scattering_albedo(1.0) - 1.0).abs() < 1e-3);
        // Monotone: a brighter multiple-scattering colour needs a higher α.
        let mut last = -1.0;
        for k in 0..=20 {
            let a = single_scattering_albedo(k as f32 / 20.0);
            assert!(a >= last, "{k}: {a} < {last}");
            last = a;
        }
    }

    #[test]
    fn wraps_fold_texel_indices() {
        assert_eq!(Wrap::Repeat.index(-1, 4), 3);
        assert_eq!(Wrap::Repeat.index(5, 4), 1);
        assert_eq!(Wrap::Clamp.index(-3, 4), 0);
        assert_eq!(Wrap::Clamp.index(9, 4), 3);
        assert_eq!(Wrap::Mirror.index(4, 4), 3);
        assert_eq!(Wrap::Mirror.index(-1, 4), 0);
    }

    #[test]
    fn a_half_black_half_white_texture_averages_per_half() {
        let (w, h) = (8usize, 8usize);
        let texels = (0..w * h)
            .map(|k| if k % w < w / 2 { [0.0; 3] } else { [1.0; 3] })
            .collect();
        let t = Texture {
            width: w,
            height: h,
            texels,
            wrap: [Wrap::Clamp; 2],
            nearest: true,
        };
        let left = t.mean_over([[0.0, 0.0], [0.4, 0.0], [0.0, 1.0]]);
        let right = t.mean_over([[0.6, 0.0], [1.0, 0.0], [1.0, 1.0]]);
        let whole = t.mean();
        assert!(left[0] < 0.05 && right[0] > 0.95, "{left:?} {right:?}");
        assert!((whole[0] - 0.5).abs() < 0.1, "{whole:?}");
    }
}
