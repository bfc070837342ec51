//! Loading a scene: from a spec to validated objects with triangles in scene units.
//!
//! In: a spec — `builtin:NAME` or the path of a JSON scene file (see
//! `translux_proto::scene`) whose mesh files are given relative to the scene file's folder:
//! OBJ (read by [`crate::obj`]), PLY or glTF 2.0 (`.gltf`, `.glb`; read by
//! [`crate::meshio`]), by extension. Media by OBJ material (`by_obj_material`) need an OBJ mesh.
//! A glTF file is also a whole scene, given directly (`room.glb`) or imported by a JSON
//! scene file of the `{"gltf": "room.glb", ...}` form that overrides its materials and lights
//! by name ([`crate::gltf_scene`]); either is read into an ordinary [`SceneFile`] whose
//! objects are the file's (`"mesh": "room.glb#Wall"`), loaded with their textures.
//! Out: a [`LoadedScene`]: the validated [`SceneFile`] and, per object, its material, crease
//! angle and triangles in scene units with the object's transform applied (scale, then
//! rotate about X, Y, Z, then translate). Geometry is never rescaled: `unit_mm` stays in
//! the file for later stages.
//!
//! Every failure is a [`SceneError`] whose message names the scene, and the field, or the
//! object and the mesh file: `scenes/box.json: objects[1].material.albedo[0] must be finite
//! and in [0, 1]`, `scenes/box.json: objects[2] "bunny": mesh file "bunny.obj"
//! (scenes/bunny.obj) is not a valid OBJ: line 7: face index 99 is out of range (the file
//! has 3 vertices)`.
//! Bad input never panics.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use glam::{Mat3, Vec3};
use translux_proto::scene::{
    GltfSceneFile, Material, MeshRef, ObjectDesc, Pattern, SceneFile, Shape, Transform,
};
use translux_proto::{FieldError, JsonError};

use crate::builtin::{BUILTIN_SCENES, builtin_scene};
use crate::gltf_scene::{AlbedoMap, GltfFile, ImportError};
use crate::meshio::{MeshError, MeshFormat};
use crate::obj::load_obj_triangles;
use crate::shapes::shape_triangles;

/// How many triangles the mesh file `path` gives ([`crate::meshio::triangle_count`]), also
/// for one object of a glTF file (`room.glb#Wall`: its node's triangles, read).
pub fn triangle_count(path: &Path) -> Result<u64, MeshError> {
    if let Some((file, node)) = path.to_str().and_then(crate::meshio::split_node_ref) {
        let g = GltfFile::open(Path::new(file))?;
        return Ok(g.object(node)?.triangles.len() as u64);
    }
    crate::meshio::triangle_count(path)
}

/// Default crease angle between smoothed and creased edges (degrees).
pub const DEFAULT_CREASE_DEG: f32 = 40.0;

/// One object, ready for patching.
#[derive(Debug, Clone, PartialEq)]
pub struct LoadedObject {
    pub name: String,
    pub material: Material,
    /// Edges whose faces differ by less than this (degrees) are smoothed (default 40).
    pub crease_deg: f32,
    /// Triangles in scene units with the transform applied, counter-clockwise seen from
    /// the side the surface faces.
    pub triangles: Vec<[Vec3; 3]>,
    /// Zero-area triangles (area < 1e-12 × bounding-box diagonal²) that were dropped.
    pub dropped_degenerate: usize,
    /// Triangles the mesh had before `simplify_to` (equal to the loaded count plus
    /// `dropped_degenerate` when it was not simplified).
    pub source_triangles: usize,
    /// Some closed parts of the mesh were turned over by its `orientation` (see
    /// [`crate::orient`]); `orientation_notes` says which and why.
    pub reoriented: bool,
    /// What the orientation pass decided, one line per decision (empty when it had nothing
    /// to decide).
    pub orientation_notes: Vec<String>,
    /// For a heterogeneous object with media by OBJ material (`by_obj_material`): the medium
    /// of each triangle (the index of its `usemtl` name in the pattern's `names`), aligned
    /// with `triangles`. `None` for every other object.
    pub face_material: Option<Vec<u32>>,
    /// For a diffuse glTF object with a base colour texture (or primitives of different base
    /// colours) whose material is the file's own: the albedo over its surface, aligned with
    /// `triangles` (see [`crate::gltf_scene`]); the pipeline averages it over each patch.
    pub albedo_map: Option<Arc<AlbedoMap>>,
    /// What loading read past or changed (a glTF extension translux ignores, a texture it
    /// could not use), one line each; printed as notes by the pipeline.
    pub notes: Vec<String>,
}

/// A validated scene with its geometry.
#[derive(Debug, Clone, PartialEq)]
pub struct LoadedScene {
    /// The file's `name`, else the file stem; for `builtin:NAME`, NAME.
    pub name: String,
    /// The spec it was loaded from (`builtin:cornell`, `scenes/box.json`).
    pub source: String,
    /// The validated scene file.
    pub file: SceneFile,
    /// The objects, in the file's order.
    pub objects: Vec<LoadedObject>,
}

impl LoadedScene {
    /// Number of triangles over all objects.
    pub fn triangle_count(&self) -> usize {
        self.objects.iter().map(|o| o.triangles.len()).sum()
    }
}

/// Why a scene could not be loaded. Each message starts with the scene (its file or
/// `builtin:NAME`).
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The scene file could not be read.
    #[error("{scene}: cannot read the scene file: {source}")]
    Read {
        scene: String,
        #[source]
        source: std::io::Error,
    },
    /// The scene file is not valid JSON for a scene (syntax, unknown field, wrong type).
    #[error("{scene}: line {}, column {}: {}", .error.line, .error.column, json_detail(.error))]
    Json { scene: String, error: JsonError },
    /// A value is out of range.
    #[error("{scene}: {error}")]
    Invalid { scene: String, error: FieldError },
    /// `builtin:NAME` with an unknown NAME.
    #[error("builtin:{name}: no such built-in scene; the built-in scenes are {}", BUILTIN_SCENES.join(", "))]
    UnknownBuiltin { name: String },
    /// An object's mesh file does not exist.
    #[error("{scene}: {object}: mesh file \"{mesh}\" ({}) not found", .path.display())]
    MeshMissing {
        scene: String,
        object: String,
        mesh: String,
        path: PathBuf,
    },
    /// An object's mesh file exists but could not be read.
    #[error("{scene}: {object}: cannot read mesh file \"{mesh}\" ({}): {source}", .path.display())]
    MeshRead {
        scene: String,
        object: String,
        mesh: String,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// An object's mesh file is not a valid file of its format (OBJ, PLY, glTF: by the
    /// path's extension), or holds unusable values.
    #[error("{scene}: {object}: mesh file \"{mesh}\" ({}) is not a valid {}: {detail}", .path.display(), format_name(.path))]
    MeshMalformed {
        scene: String,
        object: String,
        mesh: String,
        path: PathBuf,
        detail: String,
    },
    /// An object's mesh file has no extension or one of no format translux reads.
    #[error("{scene}: {object}: mesh file \"{mesh}\" ({}) {detail}", .path.display())]
    MeshFormat {
        scene: String,
        object: String,
        mesh: String,
        path: PathBuf,
        detail: String,
    },
    /// An object ends up with no triangles of non-zero area.
    #[error("{scene}: {object}: mesh {mesh} has no triangles{detail}")]
    MeshEmpty {
        scene: String,
        object: String,
        mesh: String,
        detail: String,
    },
    /// An animated scene where one frame was expected ([`resolve_frame`] reads its frames).
    #[error(
        "{scene}: the scene is animated ({frames} frames): precompute it as a sequence \
         (translux-precompute writes one bundle per frame), or read one frame of it"
    )]
    Animated { scene: String, frames: u32 },
    /// A glTF file taken as a whole scene (or one of its objects) could not be read.
    #[error("{scene}: glTF file \"{file}\" ({}): {detail}", .path.display())]
    Gltf {
        scene: String,
        file: String,
        path: PathBuf,
        detail: String,
    },
    /// The transform produced non-finite coordinates.
    #[error("{scene}: {object}: the transform gives non-finite coordinates (mesh {mesh})")]
    NonFinite {
        scene: String,
        object: String,
        mesh: String,
    },
}

/// `OBJ`, `PLY` or `glTF` for a mesh file's path (see [`MeshFormat::name`]).
fn format_name(path: &Path) -> &'static str {
    MeshFormat::from_path(path).map_or("mesh file", MeshFormat::name)
}

fn json_detail(e: &JsonError) -> String {
    if e.path.is_empty() || e.path == "." {
        e.message.clone()
    } else {
        format!("{}: {}", e.path, e.message)
    }
}

/// Loads `builtin:NAME` or a scene file.
pub fn load_scene(spec: &str) -> Result<LoadedScene, SceneError> {
    let r = read_scene(spec)?;
    resolve_scene(r.file, &r.base_dir, r.name, r.source)
}

/// A scene file read and parsed, its meshes not loaded yet: an animated scene's frames
/// resolve from it one by one ([`resolve_frame`]).
#[derive(Debug, Clone)]
pub struct SceneSource {
    pub file: SceneFile,
    /// Where its relative mesh paths start.
    pub base_dir: PathBuf,
    /// The file's `name`, else its stem (`NAME` for `builtin:NAME`).
    pub name: String,
    /// The spec, for messages.
    pub source: String,
}

/// Reads and parses `builtin:NAME` or a scene file (not validated yet).
pub fn read_scene(spec: &str) -> Result<SceneSource, SceneError> {
    if let Some(name) = spec.strip_prefix("builtin:") {
        let file = builtin_scene(name).ok_or_else(|| SceneError::UnknownBuiltin {
            name: name.to_owned(),
        })?;
        return Ok(SceneSource {
            file,
            base_dir: PathBuf::from("."),
            name: name.to_owned(),
            source: spec.to_owned(),
        });
    }
    read_scene_file(Path::new(spec))
}

/// A glTF file's failure to import, with the scene and the file named.
fn gltf_error(e: MeshError, scene: &str, file: &str, path: &Path) -> SceneError {
    SceneError::Gltf {
        scene: scene.to_owned(),
        file: file.to_owned(),
        path: path.to_path_buf(),
        detail: e.to_string(),
    }
}

/// Reads and parses a scene file: JSON (a [`SceneFile`], or a [`GltfSceneFile`] that imports
/// a glTF file), or a glTF 2.0 file (`.gltf`, `.glb`) taken as a whole scene
/// ([`crate::gltf_scene`]).
pub fn read_scene_file(path: &Path) -> Result<SceneSource, SceneError> {
    let scene = path.display().to_string();
    let base_dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let stem = || {
        path.file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "scene".to_owned())
    };
    let import = |gltf: &str, import: Option<&GltfSceneFile>| {
        let at = base_dir.join(gltf);
        crate::gltf_scene::scene_from_gltf(&at, gltf, import).map_err(|e| match e {
            ImportError::File(e) => gltf_error(e, &scene, gltf, &at),
            ImportError::Field(error) => SceneError::Invalid {
                scene: scene.clone(),
                error,
            },
        })
    };
    if MeshFormat::from_path(path) == Ok(MeshFormat::Gltf) {
        let gltf = path
            .file_name()
            .map_or_else(|| scene.clone(), |n| n.to_string_lossy().into_owned());
        return Ok(SceneSource {
            file: import(&gltf, None)?,
            base_dir: base_dir.to_path_buf(),
            name: stem(),
            source: scene.clone(),
        });
    }
    let text = std::fs::read_to_string(path).map_err(|source| SceneError::Read {
        scene: scene.clone(),
        source,
    })?;
    let file: SceneFile = if GltfSceneFile::is_gltf_import(&text) {
        let imp: GltfSceneFile =
            translux_proto::parse_json(&text).map_err(|error| SceneError::Json {
                scene: scene.clone(),
                error,
            })?;
        let mut file = import(&imp.gltf, Some(&imp))?;
        file.name = imp.name.clone();
        file
    } else {
        translux_proto::parse_json(&text).map_err(|error| SceneError::Json {
            scene: scene.clone(),
            error,
        })?
    };
    let name = match &file.name {
        Some(n) => n.clone(),
        None => stem(),
    };
    Ok(SceneSource {
        file,
        base_dir: base_dir.to_path_buf(),
        name,
        source: scene,
    })
}

/// Reads, parses, validates and resolves a JSON scene file.
pub fn load_scene_file(path: &Path) -> Result<LoadedScene, SceneError> {
    let r = read_scene_file(path)?;
    resolve_scene(r.file, &r.base_dir, r.name, r.source)
}

/// Validates `file` and builds every object's triangles; mesh paths are relative to
/// `base_dir`. `source` names the scene in error messages.
pub fn resolve_scene(
    file: SceneFile,
    base_dir: &Path,
    name: String,
    source: String,
) -> Result<LoadedScene, SceneError> {
    file.validate().map_err(|error| SceneError::Invalid {
        scene: source.clone(),
        error,
    })?;
    if let Some(a) = &file.animation {
        return Err(SceneError::Animated {
            scene: source,
            frames: a.frames,
        });
    }
    resolve_objects(file, base_dir, name, source, &[])
}

/// Frame `frame` of an animated scene `file` as a static scene: each `{frame}` mesh path
/// read for that frame's file number, each keyframed object moved to where its keyframes put
/// it (after its `transform`). The result has no `animation`: it precomputes like any
/// scene. An error names a frame out of range or a missing frame file.
pub fn resolve_frame(
    file: &SceneFile,
    base_dir: &Path,
    name: String,
    source: String,
    frame: u32,
) -> Result<LoadedScene, SceneError> {
    file.validate().map_err(|error| SceneError::Invalid {
        scene: source.clone(),
        error,
    })?;
    let Some(anim) = file.animation else {
        return Err(SceneError::Invalid {
            scene: source,
            error: FieldError::new("animation", "the scene is not animated"),
        });
    };
    if frame >= anim.frames {
        return Err(SceneError::Invalid {
            scene: source,
            error: FieldError::new(
                "animation.frames",
                format!(
                    "frame {frame} is out of range: the scene has {} frames (0 to {})",
                    anim.frames,
                    anim.frames - 1
                ),
            ),
        });
    }
    let mut still = file.clone();
    still.animation = None;
    let mut motion = Vec::with_capacity(still.objects.len());
    for (i, o) in still.objects.iter_mut().enumerate() {
        if let MeshRef::Path(p) = &mut o.mesh
            && translux_proto::animation::is_frame_pattern(p)
        {
            *p = translux_proto::animation::frame_mesh_path(p, anim.first_number + frame).map_err(
                |e| SceneError::Invalid {
                    scene: source.clone(),
                    error: FieldError::new(format!("objects[{i}].mesh"), e),
                },
            )?;
        }
        motion.push(
            o.keyframes
                .take()
                .map(|keys| translux_proto::animation::Keyframe::at(&keys, frame)),
        );
    }
    resolve_objects(still, base_dir, name, source, &motion)
}

/// The objects of the static `file`, each moved by `motion[i]` (if any) after its transform.
fn resolve_objects(
    file: SceneFile,
    base_dir: &Path,
    name: String,
    source: String,
    motion: &[Option<Transform>],
) -> Result<LoadedScene, SceneError> {
    // Meshes load in parallel; errors are reported in object order.
    use rayon::prelude::*;
    // Each glTF file whose objects the scene names (`room.glb#Wall`) is opened once; the
    // first of its objects carries the file's notes.
    let mut gltf: HashMap<String, Arc<GltfFile>> = HashMap::new();
    let mut file_notes: HashMap<usize, Vec<String>> = HashMap::new();
    for (i, desc) in file.objects.iter().enumerate() {
        let MeshRef::Path(rel) = &desc.mesh else {
            continue;
        };
        let Some((g, _)) = crate::meshio::split_node_ref(rel) else {
            continue;
        };
        if gltf.contains_key(g) {
            continue;
        }
        let path = base_dir.join(g);
        let opened = GltfFile::open(&path).map_err(|e| {
            mesh_error(
                e,
                &source,
                &format!("objects[{i}] \"{}\"", desc.name),
                g,
                path.clone(),
            )
        })?;
        file_notes.insert(i, opened.file_notes());
        gltf.insert(g.to_owned(), Arc::new(opened));
    }
    let results: Vec<Result<LoadedObject, SceneError>> = file
        .objects
        .par_iter()
        .enumerate()
        .map(|(i, desc)| {
            let moved = motion.get(i).and_then(Option::as_ref);
            load_object(i, desc, base_dir, &source, moved, &gltf)
        })
        .collect();
    let mut objects = results.into_iter().collect::<Result<Vec<_>, _>>()?;
    for (i, notes) in file_notes {
        let o = &mut objects[i];
        o.notes.splice(0..0, notes);
    }
    orient_objects(&file, &mut objects);
    Ok(LoadedScene {
        name,
        source,
        file,
        objects,
    })
}

fn load_object(
    index: usize,
    desc: &ObjectDesc,
    base_dir: &Path,
    scene: &str,
    motion: Option<&Transform>,
    gltf: &HashMap<String, Arc<GltfFile>>,
) -> Result<LoadedObject, SceneError> {
    let object = format!("objects[{index}] \"{}\"", desc.name);
    let mut albedo_map: Option<AlbedoMap> = None;
    let mut notes = Vec::new();
    // Media by OBJ material: the `usemtl` group of every face, mapped to the pattern's names.
    let media_names = match &desc.material {
        Material::Heterogeneous {
            pattern: Pattern::ByObjMaterial { names },
            ..
        } => Some(names),
        _ => None,
    };
    let mut face_material: Option<Vec<u32>> = None;
    let (raw, mesh) = match &desc.mesh {
        MeshRef::Shape(shape) => {
            let tag = match shape {
                Shape::Quad { .. } => "quad",
                Shape::Box { .. } => "box",
                Shape::Sphere { .. } => "sphere",
                Shape::Bowl { .. } => "bowl",
                Shape::Sheet { .. } => "sheet",
            };
            (shape_triangles(shape), format!("(built-in {tag})"))
        }
        MeshRef::Path(rel) if let Some((g, node)) = crate::meshio::split_node_ref(rel) => {
            let path = base_dir.join(g);
            if media_names.is_some() {
                return Err(SceneError::Invalid {
                    scene: scene.to_owned(),
                    error: FieldError::new(
                        format!("objects[{index}].material.pattern"),
                        format!(
                            "by_obj_material reads the media from an OBJ mesh's `usemtl` \
                             groups; mesh \"{rel}\" is a glTF object, which has none (use \
                             another pattern)"
                        ),
                    ),
                });
            }
            let file = gltf
                .get(g)
                .expect("resolve_objects opens every glTF file named");
            let got = file
                .object(node)
                .map_err(|e| mesh_error(e, scene, &object, g, path.clone()))?;
            notes = got.notes;
            // The file's texture stays while the object keeps the file's own material.
            if desc.material == got.material {
                albedo_map = got.albedo_map;
            }
            (got.triangles, format!("\"{rel}\""))
        }
        MeshRef::Path(rel) => {
            let path = base_dir.join(rel);
            let format = MeshFormat::from_path(&path).map_err(|detail| SceneError::MeshFormat {
                scene: scene.to_owned(),
                object: object.clone(),
                mesh: rel.clone(),
                path: path.clone(),
                detail,
            })?;
            if media_names.is_some() && format != MeshFormat::Obj {
                return Err(SceneError::Invalid {
                    scene: scene.to_owned(),
                    error: FieldError::new(
                        format!("objects[{index}].material.pattern"),
                        format!(
                            "by_obj_material reads the media from an OBJ mesh's `usemtl` \
                             groups; mesh \"{rel}\" is {}, which has none translux reads \
                             (convert it to OBJ with `usemtl` groups, or use another pattern)",
                            format.name()
                        ),
                    ),
                });
            }
            let loaded = match format {
                MeshFormat::Obj => load_obj_triangles(&path, media_names.is_some()),
                MeshFormat::Ply => crate::meshio::read_ply(&path).map(|t| (t, None)),
                MeshFormat::Gltf => crate::meshio::read_gltf(&path).map(|t| (t, None)),
            };
            let (tris, groups) = loaded.map_err(|e| mesh_error(e, scene, &object, rel, path))?;
            if let (Some(names), Some(groups)) = (media_names, groups) {
                face_material =
                    Some(
                        face_media(names, &groups, rel).map_err(|rule| SceneError::Invalid {
                            scene: scene.to_owned(),
                            error: FieldError::new(
                                format!("objects[{index}].material.pattern.names"),
                                rule,
                            ),
                        })?,
                    );
            }
            (tris, format!("\"{rel}\""))
        }
    };
    if raw.is_empty() {
        return Err(SceneError::MeshEmpty {
            scene: scene.to_owned(),
            object,
            mesh,
            detail: " (no faces in the file)".to_owned(),
        });
    }
    let source_triangles = raw.len();
    let raw = match desc.simplify_to {
        Some(n) if raw.len() as u64 > n => {
            if albedo_map.take().is_some() {
                notes.push(
                    "simplify_to merges triangles, so the texture is not followed per \
                     patch: the object's mean albedo is used"
                        .to_owned(),
                );
            }
            crate::simplify::simplify(&raw, n as usize).triangles
        }
        _ => raw,
    };
    let transformed = apply_transform(apply_transform(raw, desc.transform.as_ref()), motion);
    // The albedo map follows its triangles: moved the same way, corners (and their
    // texture coordinates) swapped where a mirroring transform swaps them.
    if let Some(map) = &mut albedo_map {
        let corners: Vec<[Vec3; 3]> = map.triangles.iter().map(|t| t.corners).collect();
        let moved = apply_transform(apply_transform(corners, desc.transform.as_ref()), motion);
        let mirrored =
            |t: Option<&Transform>| t.is_some() && transform_parts(t).0.determinant() < 0.0;
        let flip = mirrored(desc.transform.as_ref()) != mirrored(motion);
        for (t, c) in map.triangles.iter_mut().zip(moved) {
            t.corners = c;
            if flip {
                t.uv.swap(1, 2);
            }
        }
    }
    if transformed.iter().flatten().any(|v| !v.is_finite()) {
        return Err(SceneError::NonFinite {
            scene: scene.to_owned(),
            object,
            mesh,
        });
    }
    if face_material.is_some() || albedo_map.is_some() {
        let keep = non_degenerate(&transformed);
        if let Some(f) = &mut face_material {
            let mut k = 0;
            f.retain(|_| {
                k += 1;
                keep[k - 1]
            });
        }
        if let Some(map) = &mut albedo_map {
            let mut k = 0;
            map.triangles.retain(|_| {
                k += 1;
                keep[k - 1]
            });
        }
    }
    let (triangles, dropped) = drop_degenerate(transformed);
    if triangles.is_empty() {
        return Err(SceneError::MeshEmpty {
            scene: scene.to_owned(),
            object,
            mesh,
            detail: format!(" with non-zero area (all {dropped} are degenerate)"),
        });
    }
    Ok(LoadedObject {
        name: desc.name.clone(),
        material: desc.material.clone(),
        crease_deg: desc.crease_deg.unwrap_or(DEFAULT_CREASE_DEG),
        triangles,
        dropped_degenerate: dropped,
        source_triangles,
        reoriented: false,
        orientation_notes: Vec::new(),
        face_material,
        albedo_map: albedo_map.map(Arc::new),
        notes,
    })
}

/// Applies each object's `orientation` (see [`crate::orient`]). Scanned meshes are often
/// wound inside out (horse.obj is): every normal then points into the object, so lights
/// outside never reach it and a translucent object has no inside. `auto` turns such closed
/// parts outward, but never an open surface (a wall, a floor, a sheet), and never a closed
/// part that encloses a light, the camera or another object (a room modelled from inside).
/// Built-in shapes are made facing the right way and are only touched by an explicit mode.
fn orient_objects(file: &SceneFile, objects: &mut [LoadedObject]) {
    use rayon::prelude::*;
    use translux_proto::light::Light;
    use translux_proto::scene::Orientation;
    let mut scene_points: Vec<Vec3> = file
        .lights
        .iter()
        .filter_map(|l| match l {
            Light::Point { position, .. } | Light::Spot { position, .. } => {
                Some(Vec3::from(*position))
            }
            _ => None,
        })
        .collect();
    scene_points.extend(file.camera.as_ref().map(|c| Vec3::from(c.position)));
    // A point on each object (a face's centroid near the middle of its list).
    let on_object: Vec<Vec3> = objects
        .iter()
        .map(|o| {
            let [a, b, c] = o.triangles[o.triangles.len() / 2];
            (a + b + c) / 3.0
        })
        .collect();
    objects
        .par_iter_mut()
        .zip(&file.objects)
        .enumerate()
        .for_each(|(k, (o, desc))| {
            if desc.orientation == Orientation::Auto && !matches!(desc.mesh, MeshRef::Path(_)) {
                return;
            }
            let witnesses: Vec<Vec3> = scene_points
                .iter()
                .copied()
                .chain(
                    on_object
                        .iter()
                        .enumerate()
                        .filter(|(j, _)| *j != k)
                        .map(|(_, p)| *p),
                )
                .collect();
            let report = crate::orient::orient(&mut o.triangles, desc.orientation, &witnesses);
            o.reoriented = report.flipped_triangles > 0;
            o.orientation_notes = report.notes;
        });
}

/// The medium of each face from its `usemtl` group: `names[k]` is medium k. Every face must
/// be in a listed group; the error (a rule for the field `…pattern.names`) says which group
/// is missing and how many faces it has.
fn face_media(names: &[String], groups: &[Option<String>], mesh: &str) -> Result<Vec<u32>, String> {
    let mut out = Vec::with_capacity(groups.len());
    for g in groups {
        let found = g.as_ref().and_then(|g| names.iter().position(|n| n == g));
        match found {
            Some(k) => out.push(k as u32),
            None => {
                let count = groups.iter().filter(|x| *x == g).count();
                return Err(match g {
                    Some(g) => format!(
                        "do not list \"{g}\", the `usemtl` material of {count} faces of mesh \
                         \"{mesh}\" (listed: {})",
                        names.join(", ")
                    ),
                    None => format!(
                        "cannot place {count} faces of mesh \"{mesh}\" that come before any \
                         `usemtl`; by_obj_material needs every face in a listed material"
                    ),
                });
            }
        }
    }
    Ok(out)
}

/// sin and cos of an angle in degrees, exact at multiples of 90° (so walls rotated by 90°
/// meet exactly).
fn sin_cos_deg(deg: f32) -> (f32, f32) {
    let quarter = deg / 90.0;
    if quarter == quarter.round() {
        match (quarter as i64).rem_euclid(4) {
            0 => (0.0, 1.0),
            1 => (1.0, 0.0),
            2 => (0.0, -1.0),
            _ => (-1.0, 0.0),
        }
    } else {
        deg.to_radians().sin_cos()
    }
}

/// The linear part M = R_z R_y R_x S and the translation of a transform: a point p goes to
/// M p + t (scale first, then rotate about X, then Y, then Z, then translate).
pub fn transform_parts(t: Option<&Transform>) -> (Mat3, Vec3) {
    let Some(t) = t else {
        return (Mat3::IDENTITY, Vec3::ZERO);
    };
    let scale = t.scale.map(|s| Vec3::from(s.as_vec())).unwrap_or(Vec3::ONE);
    let rot = |axis: usize| {
        let (s, c) = sin_cos_deg(t.rotate_deg[axis]);
        match axis {
            0 => Mat3::from_cols(Vec3::X, Vec3::new(0.0, c, s), Vec3::new(0.0, -s, c)),
            1 => Mat3::from_cols(Vec3::new(c, 0.0, -s), Vec3::Y, Vec3::new(s, 0.0, c)),
            _ => Mat3::from_cols(Vec3::new(c, s, 0.0), Vec3::new(-s, c, 0.0), Vec3::Z),
        }
    };
    let m = rot(2) * rot(1) * rot(0) * Mat3::from_diagonal(scale);
    (m, Vec3::from(t.translate))
}

/// Applies the transform; a mirroring transform (det M < 0) would turn every triangle
/// inside out, so it also swaps b and c to keep the normals on the same side.
fn apply_transform(tris: Vec<[Vec3; 3]>, t: Option<&Transform>) -> Vec<[Vec3; 3]> {
    let (m, tr) = transform_parts(t);
    if t.is_none() {
        return tris;
    }
    let flip = m.determinant() < 0.0;
    tris.into_iter()
        .map(|[a, b, c]| {
            let (a, b, c) = (m * a + tr, m * b + tr, m * c + tr);
            if flip { [a, c, b] } else { [a, b, c] }
        })
        .collect()
}

/// Drops triangles with area < 1e-12 × (bounding-box diagonal)²; returns the rest and the
/// number dropped.
fn drop_degenerate(tris: Vec<[Vec3; 3]>) -> (Vec<[Vec3; 3]>, usize) {
    let keep = non_degenerate(&tris);
    let before = tris.len();
    let kept: Vec<_> = tris
        .into_iter()
        .zip(&keep)
        .filter_map(|(t, &k)| k.then_some(t))
        .collect();
    let dropped = before - kept.len();
    (kept, dropped)
}

/// Which triangles [`drop_degenerate`] keeps.
fn non_degenerate(tris: &[[Vec3; 3]]) -> Vec<bool> {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for v in tris.iter().flatten() {
        lo = lo.min(*v);
        hi = hi.max(*v);
    }
    let diag2 = f64::from((hi - lo).length_squared());
    let min_area = 1e-12 * diag2;
    tris.iter()
        .map(|[a, b, c]| {
            let (a, b, c) = (a.as_dvec3(), b.as_dvec3(), c.as_dvec3());
            let area = 0.5 * (b - a).cross(c - a).length();
            area >= min_area && area > 0.0
        })
        .collect()
}

/// A mesh file's failure with the scene, the object and the file named.
fn mesh_error(e: MeshError, scene: &str, object: &str, mesh: &str, path: PathBuf) -> SceneError {
    let (scene, object, mesh) = (scene.to_owned(), object.to_owned(), mesh.to_owned());
    match e {
        MeshError::Missing => SceneError::MeshMissing {
            scene,
            object,
            mesh,
            path,
        },
        MeshError::Io(source) => SceneError::MeshRead {
            scene,
            object,
            mesh,
            path,
            source,
        },
        MeshError::Malformed(detail) => SceneError::MeshMalformed {
            scene,
            object,
            mesh,
            path,
            detail,
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs::File;
    use std::io::Write;

    const BUNNY: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/stanford-bunny.obj"
    );
    const EXAMPLE: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../examples/scenes/bunny-on-floor.json"
    );

    const TRI_OBJ: &str = "# one triangle and a quad\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\n\
                           o first\nf 1 2 3\no second\nf 2 4 3\n";

    fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
        let p = dir.join(name);
        let mut f = File::create(&p).expect("create");
        f.write_all(text.as_bytes()).expect("write");
        p
    }

    fn scene_with(mesh: &str, material: &str, extra: &str) -> String {
        format!(
            r#"{{
  "objects": [
    {{"name": "floor", "mesh": {{"shape": "quad", "size": [1, 1]}},
     "material": {{"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}}}},
    {{"name": "thing", "mesh": {mesh},
     "material": {material}{extra}}}
  ]
}}"#
        )
    }

    const GREY: &str = r#"{"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}"#;

    /// Loads a scene file and returns the error message, which must name the file.
    fn error_of(dir: &Path, scene: &str) -> String {
        let p = write(dir, "box.json", scene);
        match load_scene_file(&p) {
            Ok(s) => panic!("loaded {} objects", s.objects.len()),
            Err(e) => {
                let msg = e.to_string();
                assert!(msg.starts_with(&p.display().to_string()), "{msg}");
                msg
            }
        }
    }

    fn normal(t: &[Vec3; 3]) -> Vec3 {
        (t[1] - t[0]).cross(t[2] - t[0]).normalize()
    }

    /// A tetrahedron whose faces all point inward (each face's corners clockwise seen
    /// from outside).
    const INSIDE_OUT_TET: &str = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n\
                                  f 1 2 3\nf 1 4 2\nf 1 3 4\nf 2 4 3\n";

    #[test]
    fn inside_out_meshes_are_turned_outward_and_sheets_are_left_alone() {
        let dir = tempfile::tempdir().expect("tempdir");
        write(dir.path(), "tet.obj", INSIDE_OUT_TET);
        let p = write(dir.path(), "s.json", &scene_with("\"tet.obj\"", GREY, ""));
        let s = load_scene_file(&p).expect("loads");
        let o = &s.objects[1];
        assert!(o.reoriented);
        assert!(crate::shapes::signed_volume(&o.triangles) > 0.0);
        // Every normal now points away from the centroid.
        let c = Vec3::splat(0.25);
        for t in &o.triangles {
            assert!(normal(t).dot(t[0] - c) > 0.0, "{t:?}");
        }
        // A lone triangle encloses nothing: kept as it is; built-in shapes never flip.
        assert!(!s.objects[0].reoriented);
        write(dir.path(), "tri.obj", TRI_OBJ);
        let p = write(dir.path(), "t.json", &scene_with("\"tri.obj\"", GREY, ""));
        assert!(!load_scene_file(&p).expect("loads").objects[1].reoriented);
        // `as_is` keeps even a closed inside-out mesh.
        let p = write(
            dir.path(),
            "a.json",
            &scene_with("\"tet.obj\"", GREY, r#", "orientation": "as_is""#),
        );
        let s = load_scene_file(&p).expect("loads");
        assert!(!s.objects[1].reoriented);
        assert!(crate::shapes::signed_volume(&s.objects[1].triangles) < 0.0);
    }

    #[test]
    fn orientation_must_be_one_of_the_documented_modes() {
        let dir = tempfile::tempdir().expect("tempdir");
        write(dir.path(), "tet.obj", INSIDE_OUT_TET);
        let msg = error_of(
            dir.path(),
            &scene_with("\"tet.obj\"", GREY, r#", "orientation": "sideways""#),
        );
        assert!(
            msg.contains("objects[1].orientation")
                && ["auto", "as_is", "outward", "inward"]
                    .iter()
                    .all(|m| msg.contains(m)),
            "{msg}"
        );
    }

    fn shared_mesh(name: &str) -> String {
        let p = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/data")
            .join(name);
        assert!(
            p.exists(),
            "{} is missing: the tests read the scanned meshes from ../shared/data",
            p.display()
        );
        format!("{:?}", p.display().to_string())
    }

    #[test]
    fn the_inside_out_horse_turns_outward_and_the_open_bunny_does_not() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = write(
            dir.path(),
            "h.json",
            &scene_with(&shared_mesh("horse.obj"), GREY, ""),
        );
        let s = load_scene_file(&p).expect("loads");
        let horse = &s.objects[1];
        assert!(horse.reoriented, "{:?}", horse.orientation_notes);
        assert!(crate::shapes::signed_volume(&horse.triangles) > 0.0);
        assert!(
            horse
                .orientation_notes
                .iter()
                .any(|n| n.contains("flipped to face outward")),
            "{:?}",
            horse.orientation_notes
        );
        // The bunny has holes in its base and is wound outward: left alone, wherever it is.
        for translate in ["[0, 0, 0]", "[-3, 1, 7]"] {
            let extra = format!(r#", "transform": {{"translate": {translate}}}"#);
            let p = write(
                dir.path(),
                "b.json",
                &scene_with(&shared_mesh("stanford-bunny.obj"), GREY, &extra),
            );
            let s = load_scene_file(&p).expect("loads");
            assert!(
                !s.objects[1].reoriented,
                "{:?}",
                s.objects[1].orientation_notes
            );
        }
    }

    #[test]
    fn simplify_to_reduces_a_scanned_mesh_and_rejects_bad_values() {
        let dir = tempfile::tempdir().expect("tempdir");
        let bunny =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/stanford-bunny.obj");
        let mesh = format!("{:?}", bunny.display().to_string());
        let p = write(
            dir.path(),
            "b.json",
            &scene_with(&mesh, GREY, r#", "simplify_to": 5000"#),
        );
        let s = load_scene_file(&p).expect("loads");
        let o = &s.objects[1];
        assert_eq!(o.source_triangles, 69_451);
        let n = o.triangles.len() + o.dropped_degenerate;
        assert!((4_000..=5_000).contains(&n), "{n}");
        assert!(!o.reoriented, "the bunny faces outward already");
        for (v, rule) in [("0", "must be in [4, 10000000]"), ("2.5", "simplify_to")] {
            let msg = error_of(
                dir.path(),
                &scene_with(&mesh, GREY, &format!(r#", "simplify_to": {v}"#)),
            );
            assert!(
                msg.contains("objects[1].simplify_to") && msg.contains(rule),
                "{msg}"
            );
        }
    }

    #[test]
    fn obj_with_transform_loads_relative_to_the_scene_file() {
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::create_dir(dir.path().join("meshes")).expect("mkdir");
        write(&dir.path().join("meshes"), "tri.obj", TRI_OBJ);
        let transform = r#", "transform": {"scale": 2, "rotate_deg": [0, 90, 0], "translate": [1, 2, 3]}, "crease_deg": 10"#;
        let p = write(
            dir.path(),
            "s.json",
            &scene_with("\"meshes/tri.obj\"", GREY, transform),
        );
        let s = load_scene_file(&p).expect("loads");
        assert_eq!(s.name, "s");
        assert_eq!(s.source, p.display().to_string());
        assert_eq!(s.objects.len(), 2);
        let o = &s.objects[1];
        assert_eq!(
            (o.name.as_str(), o.crease_deg, o.dropped_degenerate),
            ("thing", 10.0, 0)
        );
        assert_eq!(s.objects[0].crease_deg, DEFAULT_CREASE_DEG);
        // Both models of the file are merged.
        assert_eq!(o.triangles.len(), 2);
        // (1, 0, 0) → scale 2 → (2, 0, 0) → 90° about Y → (0, 0, −2) → + (1, 2, 3).
        let expect = Vec3::new(1.0, 2.0, 1.0);
        assert!(
            o.triangles[0][1].distance(expect) < 1e-6,
            "{}",
            o.triangles[0][1]
        );
        // (0, 1, 0) → (0, 2, 0) → unchanged by the Y rotation → (1, 4, 3).
        assert!(o.triangles[0][2].distance(Vec3::new(1.0, 4.0, 3.0)) < 1e-6);
        // The triangle faced +Z; rotated 90° about Y it faces +X.
        assert!((normal(&o.triangles[0]) - Vec3::X).length() < 1e-6);
        assert_eq!(s.triangle_count(), 4);
        // The name in the file wins over the stem.
        let named = format!(
            "{{\"name\": \"nice\", {}",
            &scene_with("\"meshes/tri.obj\"", GREY, "")[1..]
        );
        let p = write(dir.path(), "s2.json", &named);
        assert_eq!(load_scene_file(&p).expect("loads").name, "nice");
        // `load_scene` takes a path too.
        let s = load_scene(&p.display().to_string()).expect("loads");
        assert_eq!(s.name, "nice");
    }

    #[test]
    fn rotation_order_is_x_then_y_then_z() {
        let t = Transform {
            translate: [0.0; 3],
            rotate_deg: [90.0, 90.0, 0.0],
            scale: None,
        };
        let (m, _) = transform_parts(Some(&t));
        // +Y → 90° about X → +Z → 90° about Y → +X (Y first, then X, would give +Z).
        assert!((m * Vec3::Y - Vec3::X).length() < 1e-6, "{}", m * Vec3::Y);
        let t = Transform {
            translate: [0.0; 3],
            rotate_deg: [0.0, 90.0, 90.0],
            scale: None,
        };
        let (m, _) = transform_parts(Some(&t));
        // +Z → 90° about Y → +X → 90° about Z → +Y.
        assert!((m * Vec3::Z - Vec3::Y).length() < 1e-6);
        // Non-multiples of 90° agree with glam's rotations.
        let t = Transform {
            translate: [0.0; 3],
            rotate_deg: [10.0, 20.0, 30.0],
            scale: None,
        };
        let (m, _) = transform_parts(Some(&t));
        let g = Mat3::from_rotation_z(30f32.to_radians())
            * Mat3::from_rotation_y(20f32.to_radians())
            * Mat3::from_rotation_x(10f32.to_radians());
        assert!((m * Vec3::new(0.3, -0.4, 0.5) - g * Vec3::new(0.3, -0.4, 0.5)).length() < 1e-6);
    }

    #[test]
    fn mirroring_scale_keeps_normals_outward() {
        let dir = tempfile::tempdir().expect("tempdir");
        for (scale, det_sign) in [("[-1, 1, 1]", -1.0), ("[-2, -1, 3]", 1.0), ("-0.5", -1.0)] {
            let extra = format!(r#", "transform": {{"scale": {scale}}}"#);
            let text = scene_with(
                r#"{"shape": "sphere", "radius": 1, "segments": 16}"#,
                GREY,
                &extra,
            );
            let p = write(dir.path(), "m.json", &text);
            let s = load_scene_file(&p).expect("loads");
            let tris = &s.objects[1].triangles;
            let v = crate::shapes::signed_volume(tris);
            assert!(v > 0.0, "scale {scale} (det sign {det_sign}): volume {v}");
            for t in tris {
                let c = (t[0] + t[1] + t[2]) / 3.0;
                assert!(normal(t).dot(c) > 0.0, "scale {scale}: inward face");
            }
        }
    }

    #[test]
    fn degenerate_triangles_are_dropped_and_counted() {
        let dir = tempfile::tempdir().expect("tempdir");
        write(
            dir.path(),
            "d.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 2 0 0\nf 1 2 3\nf 1 2 4\nf 1 1 3\n",
        );
        let p = write(dir.path(), "d.json", &scene_with("\"d.obj\"", GREY, ""));
        let s = load_scene_file(&p).expect("loads");
        assert_eq!(s.objects[1].triangles.len(), 1);
        assert_eq!(s.objects[1].dropped_degenerate, 2);
        // Only degenerate faces: an error, not an empty object.
        write(dir.path(), "d.obj", "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n");
        let msg = error_of(dir.path(), &scene_with("\"d.obj\"", GREY, ""));
        assert!(msg.contains("\"thing\"") && msg.contains("d.obj"), "{msg}");
        assert!(msg.contains("no triangles with non-zero area"), "{msg}");
    }

    #[test]
    fn malformed_obj_names_file_object_and_line() {
        let dir = tempfile::tempdir().expect("tempdir");
        let cases = [
            (
                "v 0 0 0\nv 1 2 banana\nv 0 1 0\nf 1 2 3\n",
                "line 2",
                "banana",
            ),
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99\n",
                "line 4",
                "out of range",
            ),
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n",
                "line 4",
                "not an integer",
            ),
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n",
                "line 4",
                "start at 1",
            ),
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -1 -2 -7\n",
                "line 4",
                "before the first vertex",
            ),
            (
                "v 0 0 0\nv 1 nan 0\nv 0 1 0\nf 1 2 3\n",
                "line 2",
                "not finite",
            ),
            (
                "v 0 0 0\nv 1 inf 0\nv 0 1 0\nf 1 2 3\n",
                "line 2",
                "not finite",
            ),
            ("v 0 0 0\nv 1 0 0\nv 0 1 0 0\nf 1 2 3\n", "line 3", "w = 0"),
            (
                "v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n",
                "line 2",
                "three coordinates",
            ),
        ];
        for (obj, line, what) in cases {
            write(dir.path(), "bad.obj", obj);
            let msg = error_of(dir.path(), &scene_with("\"bad.obj\"", GREY, ""));
            assert!(msg.contains("objects[1] \"thing\""), "{msg}");
            assert!(
                msg.contains("\"bad.obj\"") && msg.contains("not a valid OBJ"),
                "{msg}"
            );
            assert!(msg.contains(line) && msg.contains(what), "{obj:?}: {msg}");
        }
        // Binary garbage.
        std::fs::write(
            dir.path().join("bad.obj"),
            [0x76, 0x20, 0xff, 0xfe, 0x00, 0x0a],
        )
        .expect("write");
        let msg = error_of(dir.path(), &scene_with("\"bad.obj\"", GREY, ""));
        assert!(msg.contains("bad.obj") && msg.contains("UTF-8"), "{msg}");
        // Text with no faces at all (tobj ignores what it does not know).
        write(dir.path(), "bad.obj", "hello world\nthis is not an obj\n");
        let msg = error_of(dir.path(), &scene_with("\"bad.obj\"", GREY, ""));
        assert!(
            msg.contains("\"thing\"") && msg.contains("bad.obj") && msg.contains("no triangles"),
            "{msg}"
        );
        // Only points and lines: no surface.
        write(
            dir.path(),
            "bad.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2\np 3\n",
        );
        let msg = error_of(dir.path(), &scene_with("\"bad.obj\"", GREY, ""));
        assert!(msg.contains("no triangles"), "{msg}");
    }

    #[test]
    fn malformed_mtl_is_ignored_not_a_panic() {
        // tobj 4.0 panics on `Ka 1 2` in a material library; materials are not read.
        let dir = tempfile::tempdir().expect("tempdir");
        write(dir.path(), "m.mtl", "newmtl x\nKa 1 2\n");
        write(
            dir.path(),
            "m.obj",
            &format!("mtllib m.mtl\nusemtl x\n{TRI_OBJ}"),
        );
        let p = write(dir.path(), "s.json", &scene_with("\"m.obj\"", GREY, ""));
        let s = load_scene_file(&p).expect("loads");
        assert_eq!(s.objects[1].triangles.len(), 2);
    }

    #[test]
    fn missing_mesh_and_missing_scene_file() {
        let dir = tempfile::tempdir().expect("tempdir");
        let msg = error_of(dir.path(), &scene_with("\"nowhere/gone.obj\"", GREY, ""));
        assert!(msg.contains("objects[1] \"thing\""), "{msg}");
        assert!(
            msg.contains("\"nowhere/gone.obj\"") && msg.contains("not found"),
            "{msg}"
        );
        // A directory is not a mesh.
        std::fs::create_dir(dir.path().join("adir")).expect("mkdir");
        let msg = error_of(dir.path(), &scene_with("\"adir\"", GREY, ""));
        assert!(
            msg.contains("\"adir\"") && msg.contains("\"thing\""),
            "{msg}"
        );

        let p = dir.path().join("absent.json");
        let msg = load_scene_file(&p)
            .map(|_| ())
            .expect_err("no file")
            .to_string();
        assert!(
            msg.starts_with(&p.display().to_string()) && msg.contains("cannot read"),
            "{msg}"
        );
    }

    #[test]
    fn bad_scene_json_names_file_and_field() {
        let dir = tempfile::tempdir().expect("tempdir");
        let quad = r#"{"shape": "quad", "size": [1, 1]}"#;
        // Unknown material type: line and column, field path and the bad variant.
        let msg = error_of(dir.path(), &scene_with(quad, r#"{"type": "glass"}"#, ""));
        assert!(msg.contains("line 6, column"), "{msg}");
        assert!(
            msg.contains("objects[1].material") && msg.contains("glass"),
            "{msg}"
        );
        // Negative albedo: validation with the full field path.
        let msg = error_of(
            dir.path(),
            &scene_with(
                quad,
                r#"{"type": "diffuse", "albedo": [0.5, -0.1, 0.5]}"#,
                "",
            ),
        );
        assert!(
            msg.ends_with("objects[1].material.albedo[1] must be finite and in [0, 1]"),
            "{msg}"
        );
        // NaN is not JSON; a huge number overflows to infinity and fails validation.
        let msg = error_of(
            dir.path(),
            &scene_with(
                quad,
                r#"{"type": "diffuse", "albedo": [NaN, 0.5, 0.5]}"#,
                "",
            ),
        );
        assert!(
            msg.contains("line 6") && msg.contains("objects[1].material.albedo"),
            "{msg}"
        );
        let msg = error_of(
            dir.path(),
            &scene_with(quad, GREY, r#", "transform": {"translate": [1e39, 0, 0]}"#),
        );
        // 1e39 does not fit an f32: refused while parsing, naming the field.
        assert!(
            msg.contains("objects[1].transform.translate[0]") && msg.contains("out of range"),
            "{msg}"
        );
        // Unknown field.
        let msg = error_of(dir.path(), &scene_with(quad, GREY, r#", "colour": 3"#));
        assert!(
            msg.contains("objects[1]") && msg.contains("colour"),
            "{msg}"
        );
        // Bad shape parameter.
        let msg = error_of(
            dir.path(),
            &scene_with(
                r#"{"shape": "bowl", "radius": 1, "thickness": 2}"#,
                GREY,
                "",
            ),
        );
        assert!(
            msg.contains("objects[1].mesh.thickness must be smaller"),
            "{msg}"
        );
        // Syntax error.
        let msg = error_of(dir.path(), "{\"objects\": [");
        assert!(msg.contains("line 1"), "{msg}");
    }

    #[test]
    fn unknown_builtin_lists_the_known_ones() {
        let msg = load_scene("builtin:teapot")
            .map(|_| ())
            .expect_err("unknown")
            .to_string();
        assert!(msg.contains("teapot"), "{msg}");
        for name in BUILTIN_SCENES {
            assert!(msg.contains(name), "{msg}");
        }
    }

    #[test]
    fn bunny_loads_through_a_scene_file() {
        let dir = tempfile::tempdir().expect("tempdir");
        let text = scene_with(
            &format!("{:?}", BUNNY),
            r#"{"type": "translucent", "profile": {"type": "dipole", "preset": "marble"}}"#,
            r#", "transform": {"scale": 2}"#,
        );
        let p = write(dir.path(), "bunny.json", &text);
        let s = load_scene_file(&p).expect("loads");
        let bunny = &s.objects[1];
        assert_eq!(bunny.triangles.len() + bunny.dropped_degenerate, 69_451);
        assert!(
            bunny.dropped_degenerate < 10,
            "{}",
            bunny.dropped_degenerate
        );
        let top = bunny
            .triangles
            .iter()
            .flatten()
            .map(|v| v.y)
            .fold(f32::MIN, f32::max);
        // The scan is ≈ 0.19 m tall at y ≈ 0.187 max; scaled by 2.
        assert!((0.3..0.45).contains(&top), "{top}");
    }

    #[test]
    fn example_scene_loads() {
        let s = load_scene(EXAMPLE).expect("the example scene loads");
        assert_eq!(s.name, "bunny-on-floor");
        let bunny = s.objects.iter().find(|o| o.name == "bunny").expect("bunny");
        assert!(bunny.triangles.len() > 69_000);
        // It stands on the floor.
        let low = bunny
            .triangles
            .iter()
            .flatten()
            .map(|v| v.y)
            .fold(f32::MAX, f32::min);
        assert!(low.abs() < 2e-3, "{low}");
    }

    // --- PLY and glTF meshes -----------------------------------------------------------

    /// An axis-aligned box [0.5, 2.5] × [−1, 0] × [1, 1.5] (volume 1, area 7) as 8 corners
    /// (corner k = x bit 0, y bit 1, z bit 2) and 6 outward quads.
    fn box_mesh() -> (Vec<[f32; 3]>, Vec<[u32; 4]>) {
        let corners = (0..8)
            .map(|k| {
                [
                    [0.5, 2.5][k & 1],
                    [-1.0, 0.0][(k >> 1) & 1],
                    [1.0, 1.5][(k >> 2) & 1],
                ]
            })
            .collect();
        let quads = vec![
            [0, 4, 6, 2],
            [1, 3, 7, 5],
            [0, 1, 5, 4],
            [2, 6, 7, 3],
            [0, 2, 3, 1],
            [4, 5, 7, 6],
        ];
        (corners, quads)
    }

    fn obj_text(v: &[[f32; 3]], faces: &[Vec<u32>]) -> String {
        let mut s = String::new();
        for p in v {
            s += &format!("v {} {} {}\n", p[0], p[1], p[2]);
        }
        for f in faces {
            s += "f";
            for i in f {
                s += &format!(" {}", i + 1);
            }
            s += "\n";
        }
        s
    }

    fn ply_ascii(v: &[[f32; 3]], faces: &[Vec<u32>]) -> String {
        let mut s = format!(
            "ply\nformat ascii 1.0\ncomment a box\nelement vertex {}\nproperty float x\n\
             property float y\nproperty float z\nproperty uchar red\nelement face {}\n\
             property list uchar int vertex_indices\nend_header\n",
            v.len(),
            faces.len()
        );
        for p in v {
            s += &format!("{} {} {} 200\n", p[0], p[1], p[2]);
        }
        for f in faces {
            s += &f.len().to_string();
            for i in f {
                s += &format!(" {i}");
            }
            s += "\n";
        }
        s
    }

    /// Binary PLY: little endian with float coordinates, an extra `uchar` per vertex and
    /// `int` indices; big endian with double coordinates, `uint` indices and a trailing
    /// `edge` element (both only to be read past).
    fn ply_binary(v: &[[f32; 3]], faces: &[Vec<u32>], big_endian: bool) -> Vec<u8> {
        let (format, coord, index) = if big_endian {
            ("binary_big_endian", "double", "uint")
        } else {
            ("binary_little_endian", "float", "int")
        };
        let extra = if big_endian {
            ""
        } else {
            "property uchar quality\n"
        };
        let edges = if big_endian {
            "element edge 1\nproperty int vertex1\nproperty int vertex2\n"
        } else {
            ""
        };
        let mut out = format!(
            "ply\nformat {format} 1.0\nelement vertex {}\nproperty {coord} x\n\
             property {coord} y\nproperty {coord} z\n{extra}element face {}\n\
             property list uchar {index} vertex_indices\n{edges}end_header\n",
            v.len(),
            faces.len()
        )
        .into_bytes();
        for p in v {
            for c in p {
                if big_endian {
                    out.extend(f64::from(*c).to_be_bytes());
                } else {
                    out.extend(c.to_le_bytes());
                }
            }
            if !big_endian {
                out.push(7);
            }
        }
        for f in faces {
            out.push(f.len() as u8);
            for i in f {
                if big_endian {
                    out.extend(i.to_be_bytes());
                } else {
                    out.extend((*i as i32).to_le_bytes());
                }
            }
        }
        if big_endian {
            out.extend(0i32.to_be_bytes());
            out.extend(1i32.to_be_bytes());
        }
        out
    }

    /// A binary glTF: the 12-byte header, the JSON chunk (padded with spaces) and the BIN
    /// chunk (padded with zeros).
    fn glb(json: &str, bin: &[u8]) -> Vec<u8> {
        let mut j = json.as_bytes().to_vec();
        while !j.len().is_multiple_of(4) {
            j.push(b' ');
        }
        let mut b = bin.to_vec();
        while !b.len().is_multiple_of(4) {
            b.push(0);
        }
        let mut out = b"glTF".to_vec();
        out.extend(2u32.to_le_bytes());
        out.extend(((12 + 8 + j.len() + 8 + b.len()) as u32).to_le_bytes());
        out.extend((j.len() as u32).to_le_bytes());
        out.extend(0x4E4F_534Au32.to_le_bytes());
        out.extend(j);
        out.extend((b.len() as u32).to_le_bytes());
        out.extend(0x004E_4942u32.to_le_bytes());
        out.extend(b);
        out
    }

    /// The box's glTF buffer (8 float positions, then 36 u16 indices fanning each quad as
    /// the other formats do) and a document using it through `buffer` (a JSON object
    /// without `byteLength`, which is added).
    fn box_gltf(buffer: &str) -> (String, Vec<u8>) {
        let (v, quads) = box_mesh();
        let mut bin = Vec::new();
        for c in v.iter().flatten() {
            bin.extend(c.to_le_bytes());
        }
        for q in &quads {
            for i in [q[0], q[1], q[2], q[0], q[2], q[3]] {
                bin.extend((i as u16).to_le_bytes());
            }
        }
        let json = format!(
            r#"{{
  "asset": {{"version": "2.0"}},
  "scene": 0,
  "scenes": [{{"nodes": [0]}}],
  "nodes": [{{"mesh": 0, "name": "box"}}],
  "meshes": [{{"name": "Box", "primitives": [{{"attributes": {{"POSITION": 0}}, "indices": 1}}]}}],
  "accessors": [
    {{"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3",
      "min": [0.5, -1, 1], "max": [2.5, 0, 1.5]}},
    {{"bufferView": 1, "componentType": 5123, "count": 36, "type": "SCALAR"}}
  ],
  "bufferViews": [
    {{"buffer": 0, "byteOffset": 0, "byteLength": 96}},
    {{"buffer": 0, "byteOffset": 96, "byteLength": 72}}
  ],
  "buffers": [{}"byteLength": {}}}]
}}"#,
            buffer.trim_end_matches('}'),
            bin.len()
        );
        (json, bin)
    }

    fn area_and_volume(tris: &[[Vec3; 3]]) -> (f64, f64) {
        let area = tris
            .iter()
            .map(|[a, b, c]| 0.5 * f64::from((*b - *a).cross(*c - *a).length()))
            .sum();
        (area, crate::shapes::signed_volume(tris))
    }

    /// Loads `mesh` as object 1 of a scene (kept as wound), or returns the error message
    /// (which names the scene file).
    fn load_mesh(dir: &Path, mesh: &str) -> Result<Vec<[Vec3; 3]>, String> {
        let text = scene_with(&format!("{mesh:?}"), GREY, r#", "orientation": "as_is""#);
        let p = write(dir, "m.json", &text);
        match load_scene_file(&p) {
            Ok(s) => Ok(s.objects[1].triangles.clone()),
            Err(e) => {
                let msg = e.to_string();
                assert!(msg.starts_with(&p.display().to_string()), "{msg}");
                assert!(msg.contains("objects[1] \"thing\""), "{msg}");
                Err(msg)
            }
        }
    }

    #[test]
    fn the_same_box_as_obj_ply_and_gltf_loads_to_the_same_triangles() {
        use base64::Engine as _;
        let dir = tempfile::tempdir().expect("tempdir");
        let d = dir.path();
        let (v, quads) = box_mesh();
        let faces: Vec<Vec<u32>> = quads.iter().map(|q| q.to_vec()).collect();
        write(d, "box.obj", &obj_text(&v, &faces));
        write(d, "box.ply", &ply_ascii(&v, &faces));
        std::fs::write(d.join("box-le.ply"), ply_binary(&v, &faces, false)).expect("write");
        std::fs::write(d.join("box-be.PLY"), ply_binary(&v, &faces, true)).expect("write");
        let (json, bin) = box_gltf("{}");
        std::fs::write(d.join("box.glb"), glb(&json, &bin)).expect("write");
        // .gltf with the buffer in a file beside it (its name percent-encoded) …
        std::fs::write(d.join("box data.bin"), &bin).expect("write");
        write(d, "box.gltf", &box_gltf(r#"{"uri": "box%20data.bin", }"#).0);
        // … and embedded as a base64 data URI.
        let uri = format!(
            "data:application/octet-stream;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(&bin)
        );
        write(
            d,
            "embedded.GLTF",
            &box_gltf(&format!(r#"{{"uri": "{uri}", }}"#)).0,
        );

        let reference = load_mesh(d, "box.obj").expect("the OBJ loads");
        assert_eq!(reference.len(), 12);
        let (area, volume) = area_and_volume(&reference);
        assert!((area - 7.0).abs() < 1e-5, "{area}");
        assert!((volume - 1.0).abs() < 1e-5, "{volume}");
        for mesh in [
            "box.ply",
            "box-le.ply",
            "box-be.PLY",
            "box.glb",
            "box.gltf",
            "embedded.GLTF",
        ] {
            let tris = load_mesh(d, mesh).unwrap_or_else(|e| panic!("{mesh}: {e}"));
            // Counted without loading, every format gives what loading gives.
            let counted = crate::meshio::triangle_count(&d.join(mesh)).expect("counts");
            assert_eq!(counted, tris.len() as u64, "{mesh}");
            let (a, vol) = area_and_volume(&tris);
            assert!(
                (a - area).abs() < 1e-9 && (vol - volume).abs() < 1e-9,
                "{mesh}"
            );
            assert_eq!(tris, reference, "{mesh}");
        }
    }

    #[test]
    fn gltf_node_transforms_and_strips_and_fans_are_applied() {
        use base64::Engine as _;
        // One triangle facing +Z, then a unit quad as a strip and as a fan.
        let mut bin = Vec::new();
        for c in [
            [0f32, 0., 0.],
            [1., 0., 0.],
            [0., 1., 0.],
            [0., 0., 0.],
            [1., 0., 0.],
            [0., 1., 0.],
            [1., 1., 0.],
            [0., 0., 0.],
            [1., 0., 0.],
            [1., 1., 0.],
            [0., 1., 0.],
        ]
        .iter()
        .flatten()
        {
            bin.extend(c.to_le_bytes());
        }
        let uri = base64::engine::general_purpose::STANDARD.encode(&bin);
        let (s, c) = (45f32.to_radians().sin(), 45f32.to_radians().cos());
        let doc = |scene: &str| {
            format!(
                r#"{{
  "asset": {{"version": "2.0"}}, {scene}
  "scenes": [{{"nodes": [0, 2]}}],
  "nodes": [
    {{"translation": [10, 0, 0], "children": [1]}},
    {{"rotation": [0, {s}, 0, {c}], "scale": [2, 2, 2], "mesh": 0}},
    {{"matrix": [-1,0,0,0, 0,1,0,0, 0,0,1,0, 0,5,0,1], "mesh": 0}},
    {{"translation": [100, 0, 0], "mesh": 1}}
  ],
  "meshes": [
    {{"primitives": [{{"attributes": {{"POSITION": 0}}}}]}},
    {{"primitives": [{{"attributes": {{"POSITION": 1}}, "mode": 5}},
                     {{"attributes": {{"POSITION": 2}}, "mode": 6}}]}}
  ],
  "accessors": [
    {{"bufferView": 0, "byteOffset": 0, "componentType": 5126, "count": 3, "type": "VEC3",
      "min": [0, 0, 0], "max": [1, 1, 0]}},
    {{"bufferView": 0, "byteOffset": 36, "componentType": 5126, "count": 4, "type": "VEC3",
      "min": [0, 0, 0], "max": [1, 1, 0]}},
    {{"bufferView": 0, "byteOffset": 84, "componentType": 5126, "count": 4, "type": "VEC3",
      "min": [0, 0, 0], "max": [1, 1, 0]}}
  ],
  "bufferViews": [{{"buffer": 0, "byteLength": {n}}}],
  "buffers": [{{"byteLength": {n}, "uri": "data:application/gltf-buffer;base64,{uri}"}}]
}}"#,
                n = bin.len()
            )
        };
        let dir = tempfile::tempdir().expect("tempdir");
        let p = write(dir.path(), "nodes.gltf", &doc(r#""scene": 0,"#));
        let tris = crate::meshio::read_gltf(&p).expect("loads");
        // Only the default scene's nodes 0 (with child 1) and 2; node 3 is in no scene.
        assert_eq!(tris.len(), 2, "{tris:?}");
        assert_eq!(crate::meshio::triangle_count(&p).expect("counts"), 2);
        let close = |a: Vec3, b: Vec3| a.distance(b) < 1e-5;
        // Node 1 under node 0: scale 2, 90° about Y, then + (10, 0, 0) from its parent:
        // (1, 0, 0) → (2, 0, 0) → (0, 0, −2) → (10, 0, −2).
        let t = tris[0];
        assert!(close(t[0], Vec3::new(10.0, 0.0, 0.0)), "{t:?}");
        assert!(close(t[1], Vec3::new(10.0, 0.0, -2.0)), "{t:?}");
        assert!(close(t[2], Vec3::new(10.0, 2.0, 0.0)), "{t:?}");
        assert!((normal(&t) - Vec3::X).length() < 1e-5, "{t:?}");
        // Node 2 mirrors x and lifts by 5: the corners swap so the face still faces +Z.
        let t = tris[1];
        assert!(close(t[0], Vec3::new(0.0, 5.0, 0.0)), "{t:?}");
        assert!(close(t[1], Vec3::new(0.0, 6.0, 0.0)), "{t:?}");
        assert!(close(t[2], Vec3::new(-1.0, 5.0, 0.0)), "{t:?}");
        assert!((normal(&t) - Vec3::Z).length() < 1e-5, "{t:?}");

        // No default scene: every root node (0, 2 and 3), with the strip and the fan, each
        // a unit quad of two triangles facing +Z.
        let p = write(dir.path(), "roots.gltf", &doc(""));
        let tris = crate::meshio::read_gltf(&p).expect("loads");
        assert_eq!(tris.len(), 6, "{tris:?}");
        assert_eq!(crate::meshio::triangle_count(&p).expect("counts"), 6);
        let quads = &tris[2..];
        for t in quads {
            assert!((normal(t) - Vec3::Z).length() < 1e-6, "{t:?}");
            assert!(t.iter().all(|v| (100.0..=101.0).contains(&v.x)), "{t:?}");
        }
        let (area, _) = area_and_volume(quads);
        assert!((area - 2.0).abs() < 1e-5, "{area}");
        // Through a scene file, the scene's transform comes after the node's.
        let text = scene_with(
            "\"nodes.gltf\"",
            GREY,
            r#", "transform": {"translate": [0, 0, 1]}"#,
        );
        let p = write(dir.path(), "s.json", &text);
        let s = load_scene_file(&p).expect("loads");
        assert!(close(
            s.objects[1].triangles[0][1],
            Vec3::new(10.0, 0.0, -1.0)
        ));
    }

    /// The Stanford bunny's OBJ (35,947 vertices, 69,451 faces) written as binary PLY.
    fn bunny_as_binary_ply() -> Vec<u8> {
        let text = std::fs::read_to_string(BUNNY).expect("the bunny (../shared/data)");
        let mut v: Vec<[f32; 3]> = Vec::new();
        let mut f: Vec<Vec<u32>> = Vec::new();
        for line in text.lines() {
            let mut w = line.split_whitespace();
            match w.next() {
                Some("v") => {
                    let c: Vec<f32> = w.take(3).map(|x| x.parse().expect("number")).collect();
                    v.push([c[0], c[1], c[2]]);
                }
                Some("f") => f.push(w.map(|x| x.parse::<u32>().expect("index") - 1).collect()),
                _ => {}
            }
        }
        assert_eq!((v.len(), f.len()), (35_947, 69_451));
        ply_binary(&v, &f, false)
    }

    #[test]
    fn the_bunny_as_binary_ply_loads_to_the_same_triangles_as_its_obj() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = dir.path().join("bunny.ply");
        std::fs::write(&p, bunny_as_binary_ply()).expect("write");
        let from_ply = crate::meshio::read_ply(&p).expect("the PLY loads");
        let (from_obj, _) = load_obj_triangles(Path::new(BUNNY), false).expect("the OBJ loads");
        assert_eq!(from_ply.len(), 69_451);
        for counted in [&p, Path::new(BUNNY)].map(crate::meshio::triangle_count) {
            assert_eq!(counted.expect("counts"), 69_451);
        }
        assert!(
            from_ply == from_obj,
            "the PLY's triangles differ from the OBJ's"
        );
        // Through a scene file, as the OBJ bunny does.
        let text = scene_with("\"bunny.ply\"", GREY, "");
        let s = load_scene_file(&write(dir.path(), "b.json", &text)).expect("loads");
        let o = &s.objects[1];
        assert_eq!(o.source_triangles, 69_451);
        assert_eq!(o.triangles.len() + o.dropped_degenerate, 69_451);
        assert!(!o.reoriented);
    }

    #[test]
    fn bad_ply_files_name_the_file_and_the_problem() {
        let dir = tempfile::tempdir().expect("tempdir");
        let d = dir.path();
        let (v, quads) = box_mesh();
        let faces: Vec<Vec<u32>> = quads.iter().map(|q| q.to_vec()).collect();
        let mut cases: Vec<(Vec<u8>, &str)> = Vec::new();
        // Truncated binary: the last face cut short, and the file cut inside the vertices
        // (8 × 13 bytes, then 6 × 17 bytes of faces).
        let full = ply_binary(&v, &faces, false);
        cases.push((
            full[..full.len() - 3].to_vec(),
            "ends early (truncated?): Unexpected end of file while reading binary element \
             'face' (expected 6, got 5)",
        ));
        cases.push((full[..full.len() - 150].to_vec(), "element 'vertex'"));
        let be = ply_binary(&v, &faces, true);
        cases.push((be[..be.len() - 20].to_vec(), "ends early"));
        // No faces at all: a point cloud.
        let cloud = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
                     property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n";
        cases.push((cloud.into(), "no `face` element"));
        // A face index past the vertices, and a negative one.
        let mut bad = faces.clone();
        bad[2][1] = 99;
        cases.push((
            ply_ascii(&v, &bad).into(),
            "face 2: vertex index 99 is out of range (the file has 8 vertices",
        ));
        cases.push((
            ply_binary(&v, &bad, false),
            "face 2: vertex index 99 is out of range",
        ));
        bad[2][1] = u32::MAX;
        cases.push((
            ply_binary(&v, &bad, true),
            "face 2: vertex index 4294967295 is out of range",
        ));
        let mut bad = faces.clone();
        bad[4].truncate(2);
        cases.push((ply_ascii(&v, &bad).into(), "face 4 has 2 vertex indices"));
        // Coordinates that are no number, or not finite.
        let text = ply_ascii(&v, &faces).replace("\n2.5 0 1.5 200\n", "\n2.5 zero 1.5 200\n");
        cases.push((text.into(), "zero"));
        let text = ply_ascii(&v, &faces).replace("\n2.5 0 1.5 200\n", "\n2.5 1e39 1.5 200\n");
        cases.push((text.into(), "vertex 7"));
        // Headers without what a surface needs.
        let text = ply_ascii(&v, &faces).replace("property float z\n", "");
        cases.push((text.into(), "no `z` property"));
        let text = ply_ascii(&v, &faces).replace("list uchar int", "list uchar float");
        cases.push((text.into(), "floating-point"));
        cases.push((b"solid box\nfacet normal 0 0 1\n".to_vec(), "PLY"));
        cases.push((Vec::new(), "PLY"));
        for (bytes, what) in cases {
            std::fs::write(d.join("bad.ply"), &bytes).expect("write");
            let msg = load_mesh(d, "bad.ply").expect_err("refused");
            assert!(
                msg.contains("mesh file \"bad.ply\"") && msg.contains("is not a valid PLY"),
                "{msg}"
            );
            assert!(msg.contains(what), "wanted {what:?}: {msg}");
            assert!(!msg.contains('\n'), "one line: {msg}");
        }
        // Faces declared but none there: no triangles.
        let empty = ply_ascii(&v, &[]);
        write(d, "empty.ply", &empty);
        let msg = load_mesh(d, "empty.ply").expect_err("refused");
        assert!(
            msg.contains("empty.ply") && msg.contains("no triangles"),
            "{msg}"
        );
        // Missing, and a directory.
        let msg = load_mesh(d, "gone.ply").expect_err("refused");
        assert!(
            msg.contains("\"gone.ply\"") && msg.contains("not found"),
            "{msg}"
        );
        std::fs::create_dir(d.join("dir.ply")).expect("mkdir");
        let msg = load_mesh(d, "dir.ply").expect_err("refused");
        assert!(
            msg.contains("\"dir.ply\"") && msg.contains("directory"),
            "{msg}"
        );
    }

    #[test]
    fn bad_gltf_files_name_the_file_and_the_problem() {
        let dir = tempfile::tempdir().expect("tempdir");
        let d = dir.path();
        let (json, bin) = box_gltf("{}");
        let glb_with = |from: &str, to: &str| {
            assert!(json.contains(from), "{from}");
            glb(&json.replacen(from, to, 1), &bin)
        };
        let cases: Vec<(&str, Vec<u8>, &str)> = vec![
            // The positions' accessor claims more than its view holds.
            (
                "bad.glb",
                glb_with(r#""count": 8"#, r#""count": 80"#),
                "accessor 0: 80 items from byte 0 run past the end of buffer view 0",
            ),
            (
                "bad.glb",
                glb_with(
                    r#""bufferView": 1, "componentType": 5123"#,
                    r#""bufferView": 1, "byteOffset": 70, "componentType": 5123"#,
                ),
                "indices accessor 1: 36 items from byte 70 run past",
            ),
            // A view past the end of the buffer.
            (
                "bad.glb",
                glb_with(
                    r#""byteOffset": 96, "byteLength": 72"#,
                    r#""byteOffset": 160, "byteLength": 72"#,
                ),
                "runs past the end of buffer 0",
            ),
            // Positions of the wrong type, indices of a float type.
            (
                "bad.glb",
                glb_with(
                    r#""count": 8, "type": "VEC3""#,
                    r#""count": 8, "type": "VEC2""#,
                ),
                "POSITION accessor 0 is Vec2",
            ),
            (
                "bad.glb",
                glb_with(r#""componentType": 5123"#, r#""componentType": 5126"#),
                "indices accessor 1 is Scalar of F32",
            ),
            // A byteStride smaller than a position.
            (
                "bad.glb",
                glb_with(
                    r#""byteOffset": 0, "byteLength": 96"#,
                    r#""byteOffset": 0, "byteLength": 96, "byteStride": 4"#,
                ),
                "byteStride 4",
            ),
            // POSITION names an accessor that does not exist (gltf-json would panic).
            (
                "bad.glb",
                glb_with(r#""POSITION": 0"#, r#""POSITION": 7"#),
                "names accessor 7, but the file has 2 accessors",
            ),
            // An index past the vertices.
            (
                "bad.glb",
                {
                    let mut b = bin.clone();
                    b[96..98].copy_from_slice(&9u16.to_le_bytes());
                    glb(&json, &b)
                },
                "vertex index 9 is out of range (POSITION has 8 vertices)",
            ),
            // Lines are no surface.
            (
                "bad.glb",
                glb_with(r#""indices": 1}"#, r#""indices": 1, "mode": 1}"#),
                "mesh 0 \"Box\" primitive 0: mode LINES draws no surface",
            ),
            // A node that is its own child.
            (
                "bad.glb",
                glb_with(r#""name": "box"}"#, r#""name": "box", "children": [0]}"#),
                "node 0 is reached twice",
            ),
            // The GLB says its buffer is the BIN chunk but has none.
            ("bad.glb", glb(&json, &[]), "binary chunk"),
            // Truncated and garbage containers, and bad JSON.
            ("bad.glb", glb(&json, &bin)[..40].to_vec(), "GLB"),
            ("bad.gltf", b"{\"asset\": ".to_vec(), "bad glTF JSON"),
            ("bad.gltf", b"\x00\x01binary".to_vec(), "bad glTF JSON"),
            // Validation: a required field missing.
            (
                "bad.gltf",
                box_gltf(r#"{"uri": "box.bin", }"#)
                    .0
                    .replace(r#""min": [0.5, -1, 1], "#, "")
                    .into_bytes(),
                "min",
            ),
            // The buffer file beside the .gltf is missing, or short.
            (
                "bad.gltf",
                box_gltf(r#"{"uri": "gone.bin", }"#).0.into_bytes(),
                "buffer 0: file \"gone.bin\"",
            ),
            (
                "bad.gltf",
                box_gltf(r#"{"uri": "short.bin", }"#).0.into_bytes(),
                "buffer 0 (file \"short.bin\") has 100 bytes but declares byteLength 168",
            ),
            (
                "bad.gltf",
                box_gltf(r#"{"uri": "data:application/octet-stream;base64,@@@", }"#)
                    .0
                    .into_bytes(),
                "bad base64",
            ),
            (
                "bad.gltf",
                box_gltf(r#"{"uri": "https://example.com/box.bin", }"#)
                    .0
                    .into_bytes(),
                "not a file path relative to the glTF file",
            ),
        ];
        std::fs::write(d.join("box.bin"), &bin).expect("write");
        std::fs::write(d.join("short.bin"), &bin[..100]).expect("write");
        for (name, bytes, what) in cases {
            std::fs::write(d.join(name), &bytes).expect("write");
            let msg = load_mesh(d, name).expect_err("refused");
            assert!(
                msg.contains(&format!("mesh file \"{name}\""))
                    && msg.contains("is not a valid glTF"),
                "{msg}"
            );
            assert!(msg.contains(what), "wanted {what:?}: {msg}");
        }
        // A missing buffer file is named with its path.
        write(d, "bad.gltf", &box_gltf(r#"{"uri": "gone.bin", }"#).0);
        let msg = load_mesh(d, "bad.gltf").expect_err("refused");
        assert!(
            msg.contains(&d.join("gone.bin").display().to_string()) && msg.contains("not found"),
            "{msg}"
        );
    }

    #[test]
    fn mesh_formats_go_by_extension_and_by_obj_material_needs_an_obj() {
        let dir = tempfile::tempdir().expect("tempdir");
        let d = dir.path();
        let (v, quads) = box_mesh();
        let faces: Vec<Vec<u32>> = quads.iter().map(|q| q.to_vec()).collect();
        write(d, "box.stl", "solid box\n");
        for mesh in ["box.stl", "box", "box.obj.bak"] {
            let msg = load_mesh(d, mesh).expect_err("refused");
            assert!(msg.contains(&format!("\"{mesh}\"")), "{msg}");
            assert!(msg.contains(".obj, .ply, .gltf and .glb"), "{msg}");
        }
        assert!(
            load_mesh(d, "box.stl")
                .unwrap_err()
                .contains("unknown mesh format \".stl\"")
        );
        // Case does not matter.
        write(d, "BOX.Obj", &obj_text(&v, &faces));
        assert_eq!(load_mesh(d, "BOX.Obj").expect("loads").len(), 12);
        // PLY content under a .glb name is read as glTF, and says so.
        write(d, "box.glb", &ply_ascii(&v, &faces));
        let msg = load_mesh(d, "box.glb").expect_err("refused");
        assert!(msg.contains("not a valid glTF"), "{msg}");

        // Media by OBJ material need the OBJ's `usemtl` groups.
        write(d, "box.ply", &ply_ascii(&v, &faces));
        let material = r#"{"type": "heterogeneous",
            "materials": [{"type": "dipole", "preset": "marble"},
                          {"type": "dipole", "preset": "skin1"}],
            "pattern": {"type": "by_obj_material", "names": ["a", "b"]}}"#;
        let msg = error_of(d, &scene_with("\"box.ply\"", material, ""));
        assert!(
            msg.contains("objects[1].material.pattern")
                && msg.contains("by_obj_material")
                && msg.contains("\"box.ply\" is PLY"),
            "{msg}"
        );
    }
}
