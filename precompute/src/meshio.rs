//! Mesh files: which format a scene's `"mesh": "PATH"` is, and readers for PLY and glTF 2.0
//! (OBJ is read by [`crate::obj`], which also keeps its `usemtl` groups).
//!
//! The format is chosen by the file's extension, in any case: `.obj`, `.ply`, `.gltf`,
//! `.glb` ([`MeshFormat::from_path`]). Every reader gives the same thing: the file's
//! triangles, polygons fan-triangulated, in the file's own coordinates and units — before
//! the object's `transform`, and never rescaled (`unit_mm` applies to the numbers as read).
//!
//! - **PLY** (ASCII, binary little and big endian; [`read_ply`], parsed by `ply-rs-bw`):
//!   the `vertex` element's `x`, `y`, `z` (any scalar type) and the `face` element's
//!   `vertex_indices` (or `vertex_index`) list of any integer type. Other elements and
//!   properties (normals, colours, `edge`, `material`) are read past and ignored.
//! - **glTF 2.0** (`.gltf` with external buffer files beside it or base64 `data:` URIs, and
//!   binary `.glb`; [`read_gltf`], parsed and validated by `gltf`): every primitive of every
//!   mesh placed by a node of the file's default scene — or, when the file names no
//!   default scene, by the hierarchy under every root node — with the node's world
//!   transform (a mirroring one keeps the faces' sides). TRIANGLES, TRIANGLE_STRIP and
//!   TRIANGLE_FAN primitives, indexed or not; a POINTS or LINES primitive is an error. Skins,
//!   morph targets and materials are not applied. glTF is in metres: with the default
//!   `unit_mm: 1000` the numbers are metres; a scene in millimetres (`unit_mm: 1`) gives
//!   the object `"transform": {"scale": 1000}`.
//!
//! - **One object of a glTF file**: a mesh path `room.glb#Wall` ([`split_node_ref`]) is the
//!   object a whole-scene import names `Wall` (a node with a mesh; see
//!   [`crate::gltf_scene`]), read with its texture coordinates and materials there.
//!
//! A glTF file that lists in `extensionsRequired` an extension translux does not read
//! ([`GLTF_EXTENSIONS`]) is refused, naming it, whichever way it is read.
//!
//! Failures are [`MeshError`]s; [`crate::scene`] adds the scene, the object and the file.
//! Bad input never panics: the few things the parsing crates would panic on (see
//! [`read_gltf`]) are checked here first.

use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;

use glam::{Mat4, Vec3};
use gltf::Semantic;
use gltf::accessor::{DataType, Dimensions};
use gltf::mesh::Mode;
use ply_rs_bw::parser::{ParseError, Parser, Reader};
use ply_rs_bw::ply::{ElementDef, PropertyAccess, PropertyAccessResult, PropertyType, ScalarType};

/// The mesh file formats, by extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    /// Wavefront OBJ (`.obj`).
    Obj,
    /// Stanford PLY (`.ply`), ASCII or binary.
    Ply,
    /// glTF 2.0: JSON (`.gltf`) or binary (`.glb`).
    Gltf,
}

/// The extensions read, for messages.
pub const SUPPORTED_EXTENSIONS: &str = ".obj, .ply, .gltf and .glb";

impl MeshFormat {
    /// The format of `path` by its extension (case-insensitive); the error says what is
    /// wrong and lists the supported extensions.
    pub fn from_path(path: &Path) -> Result<MeshFormat, String> {
        let Some(ext) = path.extension() else {
            return Err(format!(
                "has no file extension to tell its format (the supported mesh formats are \
                 {SUPPORTED_EXTENSIONS})"
            ));
        };
        match ext.to_string_lossy().to_ascii_lowercase().as_str() {
            "obj" => Ok(MeshFormat::Obj),
            "ply" => Ok(MeshFormat::Ply),
            "gltf" | "glb" => Ok(MeshFormat::Gltf),
            other => Err(format!(
                "unknown mesh format \".{other}\" (the supported mesh formats are \
                 {SUPPORTED_EXTENSIONS})"
            )),
        }
    }

    /// The format's name in messages: `OBJ`, `PLY`, `glTF`.
    pub fn name(self) -> &'static str {
        match self {
            MeshFormat::Obj => "OBJ",
            MeshFormat::Ply => "PLY",
            MeshFormat::Gltf => "glTF",
        }
    }
}

/// A mesh file that could not be read, before it is given the scene and object names.
#[derive(Debug)]
pub enum MeshError {
    /// The file does not exist.
    Missing,
    /// The file exists but could not be read (or is a directory).
    Io(std::io::Error),
    /// The file is not a valid file of its format, or holds unusable values; the text says
    /// where and what.
    Malformed(String),
}

impl std::fmt::Display for MeshError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            MeshError::Missing => f.write_str("the file does not exist"),
            MeshError::Io(e) => write!(f, "cannot read the file: {e}"),
            MeshError::Malformed(m) => f.write_str(m),
        }
    }
}

impl std::error::Error for MeshError {}

/// Opens a mesh file: a missing file and a directory are told apart from other failures.
pub fn open(path: &Path) -> Result<File, MeshError> {
    let file = File::open(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => MeshError::Missing,
        _ => MeshError::Io(e),
    })?;
    if path.is_dir() {
        return Err(MeshError::Io(std::io::Error::other("it is a directory")));
    }
    Ok(file)
}

fn malformed(detail: impl Into<String>) -> MeshError {
    MeshError::Malformed(detail.into())
}

// ---------------------------------------------------------------------------------------
// PLY

/// The names a face's index list goes by (`vertex_indices` is the usual one).
const PLY_FACE_LISTS: [&str; 2] = ["vertex_indices", "vertex_index"];

/// A PLY vertex: x, y, z of any scalar type; everything else ignored.
#[derive(Debug, Default)]
struct PlyVertex([f64; 3]);

impl PlyVertex {
    fn set(&mut self, name: &str, v: f64) -> PropertyAccessResult {
        let k = match name {
            "x" => 0,
            "y" => 1,
            "z" => 2,
            _ => return PropertyAccessResult::Ignored,
        };
        self.0[k] = v;
        PropertyAccessResult::Set
    }
}

impl PropertyAccess for PlyVertex {
    fn new() -> Self {
        Self::default()
    }
    fn set_char(&mut self, name: &str, v: i8) -> PropertyAccessResult {
        self.set(name, v.into())
    }
    fn set_uchar(&mut self, name: &str, v: u8) -> PropertyAccessResult {
        self.set(name, v.into())
    }
    fn set_short(&mut self, name: &str, v: i16) -> PropertyAccessResult {
        self.set(name, v.into())
    }
    fn set_ushort(&mut self, name: &str, v: u16) -> PropertyAccessResult {
        self.set(name, v.into())
    }
    fn set_int(&mut self, name: &str, v: i32) -> PropertyAccessResult {
        self.set(name, v.into())
    }
    fn set_uint(&mut self, name: &str, v: u32) -> PropertyAccessResult {
        self.set(name, v.into())
    }
    fn set_float(&mut self, name: &str, v: f32) -> PropertyAccessResult {
        self.set(name, v.into())
    }
    fn set_double(&mut self, name: &str, v: f64) -> PropertyAccessResult {
        self.set(name, v)
    }
}

/// A PLY face: its vertex index list, of any integer type; everything else ignored.
#[derive(Debug, Default)]
struct PlyFace(Vec<i64>);

impl PlyFace {
    fn set<T: Into<i64>>(&mut self, name: &str, v: Vec<T>) -> PropertyAccessResult {
        if !PLY_FACE_LISTS.contains(&name) {
            return PropertyAccessResult::Ignored;
        }
        self.0 = v.into_iter().map(Into::into).collect();
        PropertyAccessResult::Set
    }
}

impl PropertyAccess for PlyFace {
    fn new() -> Self {
        Self::default()
    }
    fn set_list_char(&mut self, name: &str, v: Vec<i8>) -> PropertyAccessResult {
        self.set(name, v)
    }
    fn set_list_uchar(&mut self, name: &str, v: Vec<u8>) -> PropertyAccessResult {
        self.set(name, v)
    }
    fn set_list_short(&mut self, name: &str, v: Vec<i16>) -> PropertyAccessResult {
        self.set(name, v)
    }
    fn set_list_ushort(&mut self, name: &str, v: Vec<u16>) -> PropertyAccessResult {
        self.set(name, v)
    }
    fn set_list_int(&mut self, name: &str, v: Vec<i32>) -> PropertyAccessResult {
        self.set(name, v)
    }
    fn set_list_uint(&mut self, name: &str, v: Vec<u32>) -> PropertyAccessResult {
        self.set(name, v)
    }
}

/// An element translux does not use: read past, nothing kept.
#[derive(Debug)]
struct PlySkip;

impl PropertyAccess for PlySkip {
    fn new() -> Self {
        PlySkip
    }
}

/// ply-rs-bw's message, made one line: its nested parts (`\n\t`-separated) without
/// repeats or parser-internal dumps; "line N" only where the file has lines (the header
/// and ASCII data: in binary data the crate counts elements); and a file that ends early
/// says so first, with only the element it was reading.
fn ply_error(e: ParseError, binary_payload: bool) -> MeshError {
    let text = e.to_string().replace("\n'", "'").replace("\r'", "'");
    let mut parts: Vec<String> = Vec::new();
    for part in text.split("\n\t").map(str::trim) {
        if part.is_empty() || part.starts_with("Error: ParseError {") {
            continue;
        }
        let part = match (part.strip_prefix("Line "), e.line()) {
            (Some(rest), Some(n)) if binary_payload => rest
                .strip_prefix(&format!("{n}: "))
                .unwrap_or(part)
                .to_owned(),
            (Some(rest), Some(_)) => format!("line {rest}"),
            _ => part.to_owned(),
        };
        // The same string is quoted again by each level of the parser.
        let repeat = |p: &String| p == &part || (part.starts_with("String:") && p.contains(&part));
        if !parts.iter().any(repeat) {
            parts.push(part);
        }
    }
    if e.kind() == std::io::ErrorKind::UnexpectedEof {
        parts.truncate(1);
        malformed(format!(
            "the file ends early (truncated?): {}",
            parts.join("; ")
        ))
    } else {
        malformed(parts.join("; "))
    }
}

/// Checks the header has what a surface needs: a `vertex` element with scalar x, y, z and
/// a `face` element with an integer index list.
fn check_ply_header(vertex: Option<&ElementDef>, face: Option<&ElementDef>) -> Result<(), String> {
    let Some(vertex) = vertex else {
        return Err("the header declares no `vertex` element".to_owned());
    };
    for axis in ["x", "y", "z"] {
        match vertex.properties.get(axis).map(|p| &p.data_type) {
            Some(PropertyType::Scalar(_)) => {}
            Some(PropertyType::List(..)) => {
                return Err(format!("vertex property `{axis}` is a list, not a number"));
            }
            None => return Err(format!("the `vertex` element has no `{axis}` property")),
        }
    }
    let Some(face) = face else {
        return Err(
            "the header declares no `face` element: without faces (a point cloud) there is \
             no surface"
                .to_owned(),
        );
    };
    let list = PLY_FACE_LISTS
        .iter()
        .find_map(|n| face.properties.get(*n))
        .ok_or("the `face` element has no `vertex_indices` list")?;
    match &list.data_type {
        PropertyType::List(_, ScalarType::Float | ScalarType::Double) => Err(format!(
            "face property `{}` is a list of floating-point numbers, not vertex indices",
            list.name
        )),
        PropertyType::List(..) => Ok(()),
        PropertyType::Scalar(_) => Err(format!(
            "face property `{}` is a single number, not a list of vertex indices",
            list.name
        )),
    }
}

/// Reads a PLY file (ASCII, binary little or big endian) as triangles in file coordinates;
/// polygons are fan-triangulated. A face with fewer than 3 corners, an index outside the
/// vertices, a non-finite coordinate or a file that ends early is an error that names
/// the face or vertex (counted from 0).
pub fn read_ply(path: &Path) -> Result<Vec<[Vec3; 3]>, MeshError> {
    let file = open(path)?;
    let mut reader = Reader::new(BufReader::new(file));
    let header = Parser::<PlySkip>::new()
        .read_header(&mut reader)
        .map_err(|e| ply_error(e, false))?;
    let binary = header.encoding != ply_rs_bw::ply::Encoding::Ascii;
    check_ply_header(header.elements.get("vertex"), header.elements.get("face"))
        .map_err(malformed)?;
    // The elements come in the header's order; each is read by the type that keeps what
    // translux needs from it.
    let (mut vertices, mut faces) = (Vec::new(), Vec::new());
    for (name, def) in &header.elements {
        match name.as_str() {
            "vertex" => {
                vertices = Parser::<PlyVertex>::new()
                    .read_payload_for_element(&mut reader, def, &header)
                    .map_err(|e| ply_error(e, binary))?;
            }
            "face" => {
                faces = Parser::<PlyFace>::new()
                    .read_payload_for_element(&mut reader, def, &header)
                    .map_err(|e| ply_error(e, binary))?;
            }
            _ => {
                Parser::<PlySkip>::new()
                    .read_payload_for_element(&mut reader, def, &header)
                    .map_err(|e| ply_error(e, binary))?;
            }
        }
    }
    let mut points = Vec::with_capacity(vertices.len());
    for (k, PlyVertex(p)) in vertices.iter().enumerate() {
        let v = Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32);
        if !v.is_finite() {
            return Err(malformed(format!(
                "vertex {k} ({}, {}, {}) has a coordinate that is not a finite number",
                p[0], p[1], p[2]
            )));
        }
        points.push(v);
    }
    let n = points.len();
    let mut tris = Vec::with_capacity(faces.len());
    for (f, PlyFace(idx)) in faces.iter().enumerate() {
        if idx.len() < 3 {
            return Err(malformed(format!(
                "face {f} has {} vertex indices; a face needs at least 3",
                idx.len()
            )));
        }
        let mut corner = Vec::with_capacity(idx.len());
        for &i in idx {
            match usize::try_from(i).ok().and_then(|i| points.get(i)) {
                Some(p) => corner.push(*p),
                None => {
                    return Err(malformed(format!(
                        "face {f}: vertex index {i} is out of range (the file has {n} vertices, \
                         indices 0 to {})",
                        n as i64 - 1
                    )));
                }
            }
        }
        for k in 1..corner.len() - 1 {
            tris.push([corner[0], corner[k], corner[k + 1]]);
        }
    }
    Ok(tris)
}

// ---------------------------------------------------------------------------------------
// glTF

/// Reads a glTF 2.0 file (`.gltf` or `.glb`, told apart by content) as triangles in the
/// file's coordinates (metres) with every node's world transform applied.
///
/// `gltf` parses the JSON and the GLB container, validates the document (indices in range,
/// required fields, the primitive modes) and reads accessors; what is checked here first:
/// - a primitive's `POSITION` index: gltf-json 1.4 indexes the accessor list with it while
///   validating, which panics when it is out of range;
/// - each accessor used (type, component type, count, stride, and that its bytes lie inside
///   its buffer view and buffer): gltf's reader assumes these and panics (or, for index
///   accessors of a float type, hits `unreachable!`) when they are wrong, and says nothing
///   about which accessor was bad when it merely finds no data;
/// - a node hierarchy that is not a tree (a cycle would recurse forever).
///
/// Buffers are resolved here rather than with gltf's `import` feature, which would also
/// enable JPEG decoding in the workspace's `image` (features unify across the workspace)
/// and bring an old `base64`, for three cases: the GLB's BIN chunk, a base64 `data:` URI,
/// or a file relative to the glTF file (percent-decoded). A missing buffer file is named.
pub fn read_gltf(path: &Path) -> Result<Vec<[Vec3; 3]>, MeshError> {
    let (doc, blob) = gltf_document(path)?;
    let base = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let buffers = load_buffers(&doc, base, blob)?;

    let mut tris = Vec::new();
    for (node, world) in gltf_placed(&doc)? {
        if let Some(mesh) = node.mesh() {
            for prim in mesh.primitives() {
                read_primitive(&mesh, &prim, &buffers, world, &mut tris, None)?;
            }
        }
    }
    if tris.is_empty() {
        return Err(malformed(if doc.meshes().len() == 0 {
            "the file has no meshes".to_owned()
        } else {
            format!(
                "no node of the scene places any of its {} meshes",
                doc.meshes().len()
            )
        }));
    }
    Ok(tris)
}

/// The glTF extensions translux reads (a whole-scene import: [`crate::gltf_scene`]); a file
/// that lists any other in `extensionsRequired` is refused, naming it.
pub const GLTF_EXTENSIONS: [&str; 7] = [
    "KHR_lights_punctual",
    "KHR_materials_emissive_strength",
    "KHR_materials_volume",
    "KHR_materials_transmission",
    "KHR_materials_diffuse_transmission",
    "KHR_materials_volume_scatter",
    "KHR_materials_ior",
];

/// Refuses a file that requires an extension translux does not read (the glTF spec: a
/// loader that does not support a required extension must not load the file).
fn check_required_extensions(required: &[String]) -> Result<(), MeshError> {
    let missing: Vec<&str> = required
        .iter()
        .map(String::as_str)
        .filter(|e| !GLTF_EXTENSIONS.contains(e))
        .collect();
    if missing.is_empty() {
        return Ok(());
    }
    Err(malformed(format!(
        "the file requires the extension{} {} (extensionsRequired), which translux does not \
         support; it reads {}",
        if missing.len() > 1 { "s" } else { "" },
        missing
            .iter()
            .map(|e| format!("\"{e}\""))
            .collect::<Vec<_>>()
            .join(", "),
        GLTF_EXTENSIONS.join(", ")
    )))
}

/// A glTF file's document, validated, and its GLB binary chunk if any (see [`read_gltf`]
/// for what is checked before `gltf` validates). A required extension translux does not
/// read is refused by name.
pub(crate) fn gltf_document(path: &Path) -> Result<(gltf::Document, Option<Vec<u8>>), MeshError> {
    let gltf = open_gltf(path)?;
    let json = gltf.as_json();
    for (m, mesh) in json.meshes.iter().enumerate() {
        for (p, prim) in mesh.primitives.iter().enumerate() {
            for (semantic, index) in &prim.attributes {
                if index.value() >= json.accessors.len() {
                    return Err(malformed(format!(
                        "meshes[{m}].primitives[{p}].attributes[\"{}\"] names accessor {}, \
                         but the file has {} accessors",
                        match semantic {
                            gltf::json::validation::Checked::Valid(s) => s.to_string(),
                            gltf::json::validation::Checked::Invalid => "?".to_owned(),
                        },
                        index.value(),
                        json.accessors.len()
                    )));
                }
            }
        }
    }
    check_required_extensions(&json.extensions_required)?;
    let gltf::Gltf { document, blob } = gltf;
    let mut root = document.into_json();
    // Checked above against what translux reads; gltf's own list knows fewer of them
    // (KHR_materials_volume, _diffuse_transmission, _volume_scatter) and would refuse them.
    root.extensions_required.clear();
    let doc = gltf::Document::from_json(root).map_err(|e| match e {
        gltf::Error::Validation(list) => malformed(format!(
            "invalid glTF: {}",
            list.iter()
                .map(|(path, err)| format!("{path}: {err}"))
                .collect::<Vec<_>>()
                .join("; ")
        )),
        e => malformed(e.to_string()),
    })?;
    Ok((doc, blob))
}

/// The nodes a glTF file draws, each with its world transform, parents before children:
/// the hierarchy under its default scene's nodes, else under every root (a node no node
/// has as child). A node reached twice (a cycle, two parents) is an error.
pub(crate) fn gltf_placed(doc: &gltf::Document) -> Result<Vec<(gltf::Node<'_>, Mat4)>, MeshError> {
    let roots: Vec<gltf::Node> = match doc.default_scene() {
        Some(scene) => scene.nodes().collect(),
        None => {
            let mut child = vec![false; doc.nodes().len()];
            for node in doc.nodes() {
                for c in node.children() {
                    child[c.index()] = true;
                }
            }
            doc.nodes().filter(|n| !child[n.index()]).collect()
        }
    };
    let mut seen = vec![false; doc.nodes().len()];
    let mut stack: Vec<(gltf::Node, Mat4)> = roots
        .into_iter()
        .rev()
        .map(|n| (n, Mat4::IDENTITY))
        .collect();
    let mut placed = Vec::new();
    while let Some((node, parent)) = stack.pop() {
        if std::mem::replace(&mut seen[node.index()], true) {
            return Err(malformed(format!(
                "node {} is reached twice: the node hierarchy must be a tree (no cycles, one \
                 parent per node)",
                node.index()
            )));
        }
        let world = parent * Mat4::from_cols_array_2d(&node.transform().matrix());
        let children: Vec<_> = node.children().collect();
        stack.extend(children.into_iter().rev().map(|c| (c, world)));
        placed.push((node, world));
    }
    Ok(placed)
}

/// A glTF file's JSON as written, extensions and all (`gltf` keeps only those it knows):
/// the whole `.gltf` file, or a `.glb`'s JSON chunk.
pub(crate) fn gltf_raw_json(path: &Path) -> Result<serde_json::Value, MeshError> {
    let mut bytes = Vec::new();
    open(path)?.read_to_end(&mut bytes).map_err(MeshError::Io)?;
    let parsed = if bytes.starts_with(b"glTF") {
        let glb = gltf::binary::Glb::from_slice(&bytes)
            .map_err(|e| malformed(format!("bad GLB container: {e}")))?;
        serde_json::from_slice(&glb.json)
    } else {
        serde_json::from_slice(&bytes)
    };
    parsed.map_err(|e| malformed(format!("bad glTF JSON: {e}")))
}

/// A mesh path that names one object of a glTF file, `room.glb#Wall`: the file and the
/// object's name as a whole-scene import names it ([`crate::gltf_scene`]). `None` for any
/// other path. The file ends at the first `.gltf#` or `.glb#` (any case), so the name may
/// itself hold a `#`.
pub fn split_node_ref(mesh: &str) -> Option<(&str, &str)> {
    // ASCII lower-casing keeps every byte where it was.
    let lower = mesh.to_ascii_lowercase();
    let end = [".glb#", ".gltf#"]
        .iter()
        .filter_map(|m| lower.find(m).map(|k| k + m.len() - 1))
        .min()?;
    Some((&mesh[..end], &mesh[end + 1..]))
}

/// A glTF or GLB file parsed but not yet validated (see [`read_gltf`]).
fn open_gltf(path: &Path) -> Result<gltf::Gltf, MeshError> {
    let mut bytes = Vec::new();
    open(path)?.read_to_end(&mut bytes).map_err(MeshError::Io)?;
    gltf::Gltf::from_slice_without_validation(&bytes).map_err(|e| match e {
        gltf::Error::Binary(e) => malformed(format!("bad GLB container: {e}")),
        gltf::Error::Deserialize(e) => malformed(format!("bad glTF JSON: {e}")),
        e => malformed(e.to_string()),
    })
}

/// The files a glTF file's buffers name: every buffer URI that is not a `data:` URI,
/// percent-decoded where it decodes (as written otherwise), in buffer order. Empty for a
/// `.glb` whose only buffer is its binary chunk, and for any file that is not glTF.
///
/// [`read_gltf`] reads such a file relative to the glTF file, wherever it points; a caller
/// that must keep reads inside one folder (the server's uploads) checks these names first.
pub fn referenced_files(path: &Path) -> Result<Vec<String>, MeshError> {
    if !matches!(MeshFormat::from_path(path), Ok(MeshFormat::Gltf)) {
        return Ok(Vec::new());
    }
    let gltf = open_gltf(path)?;
    Ok(gltf
        .as_json()
        .buffers
        .iter()
        .filter_map(|b| b.uri.as_deref())
        .filter(|uri| !uri.starts_with("data:"))
        .map(|uri| {
            percent_encoding::percent_decode_str(uri)
                .decode_utf8()
                .map_or_else(|_| uri.to_owned(), |d| d.into_owned())
        })
        .collect())
}

/// Every buffer's bytes, in order (see [`read_gltf`]).
pub(crate) fn load_buffers(
    doc: &gltf::Document,
    base: &Path,
    mut blob: Option<Vec<u8>>,
) -> Result<Vec<Vec<u8>>, MeshError> {
    use base64::Engine as _;
    let mut out = Vec::new();
    for buffer in doc.buffers() {
        let i = buffer.index();
        let (data, what) = match buffer.source() {
            gltf::buffer::Source::Bin => (
                blob.take().ok_or_else(|| {
                    malformed(format!(
                        "buffer {i} is the GLB's binary chunk, but the file has none"
                    ))
                })?,
                "the GLB's binary chunk".to_owned(),
            ),
            gltf::buffer::Source::Uri(uri) if uri.starts_with("data:") => {
                let (head, payload) = uri.split_once(',').unwrap_or((uri, ""));
                if !head.ends_with(";base64") {
                    return Err(malformed(format!(
                        "buffer {i}: only base64 `data:` URIs are read (the URI starts \
                         \"{}\")",
                        head.chars().take(60).collect::<String>()
                    )));
                }
                let data = base64::engine::general_purpose::STANDARD
                    .decode(payload)
                    .map_err(|e| malformed(format!("buffer {i}: bad base64 data URI: {e}")))?;
                (data, "its data URI".to_owned())
            }
            gltf::buffer::Source::Uri(uri) => {
                // A scheme (`http:`, `file:`) before any `/` makes it an absolute URI.
                let scheme = uri.split('/').next().is_some_and(|s| s.contains(':'));
                if scheme {
                    return Err(malformed(format!(
                        "buffer {i}: \"{uri}\" is not a file path relative to the glTF file \
                         nor a base64 data URI"
                    )));
                }
                let rel = percent_encoding::percent_decode_str(uri)
                    .decode_utf8()
                    .map_err(|_| malformed(format!("buffer {i}: URI \"{uri}\" is not UTF-8")))?;
                let file = base.join(rel.as_ref());
                let data = std::fs::read(&file).map_err(|e| {
                    malformed(match e.kind() {
                        std::io::ErrorKind::NotFound => {
                            format!("buffer {i}: file \"{rel}\" ({}) not found", file.display())
                        }
                        _ => format!(
                            "buffer {i}: cannot read file \"{rel}\" ({}): {e}",
                            file.display()
                        ),
                    })
                })?;
                (data, format!("file \"{rel}\""))
            }
        };
        if data.len() < buffer.length() {
            return Err(malformed(format!(
                "buffer {i} ({what}) has {} bytes but declares byteLength {}",
                data.len(),
                buffer.length()
            )));
        }
        out.push(data);
    }
    Ok(out)
}

/// `mesh 2 "Bunny" primitive 0`, for messages.
fn primitive_label(mesh: &gltf::Mesh, prim: &gltf::Primitive) -> String {
    match mesh.name() {
        Some(n) => format!("mesh {} \"{n}\" primitive {}", mesh.index(), prim.index()),
        None => format!("mesh {} primitive {}", mesh.index(), prim.index()),
    }
}

/// Checks that gltf's reader can read `acc` without panicking: its type is `dims` of one of
/// `types`, not normalized, and every byte it reads (base values and sparse indices and
/// values) lies inside its buffer view and that view inside its buffer.
fn check_accessor(
    acc: &gltf::Accessor,
    dims: Dimensions,
    types: &[DataType],
    buffers: &[Vec<u8>],
) -> Result<(), String> {
    let at = format!("accessor {}", acc.index());
    if acc.dimensions() != dims || !types.contains(&acc.data_type()) || acc.normalized() {
        return Err(format!(
            "{at} is {:?} of {:?}{}; expected {dims:?} of {}",
            acc.dimensions(),
            acc.data_type(),
            if acc.normalized() {
                " (normalized)"
            } else {
                ""
            },
            types
                .iter()
                .map(|t| format!("{t:?}"))
                .collect::<Vec<_>>()
                .join(" or ")
        ));
    }
    if acc.count() == 0 {
        return Err(format!("{at} has count 0"));
    }
    let size = acc.size();
    // `count` items of `size` bytes, `stride` apart, from `offset` in `view`.
    let span = |what: &str, view: gltf::buffer::View, offset: usize, count: usize, size: usize| {
        let stride = view.stride().unwrap_or(size);
        if stride < size {
            return Err(format!(
                "{at}{what}: buffer view {} has byteStride {stride}, smaller than one \
                 {size}-byte item",
                view.index()
            ));
        }
        let end = (count - 1)
            .checked_mul(stride)
            .and_then(|x| x.checked_add(size))
            .and_then(|x| x.checked_add(offset));
        if end.is_none_or(|end| end > view.length()) {
            return Err(format!(
                "{at}{what}: {count} items from byte {offset} run past the end of buffer view \
                 {} ({} bytes)",
                view.index(),
                view.length()
            ));
        }
        let buffer = view.buffer();
        let have = buffers.get(buffer.index()).map_or(0, Vec::len);
        if view
            .offset()
            .checked_add(view.length())
            .is_none_or(|end| end > have)
        {
            return Err(format!(
                "{at}{what}: buffer view {} (bytes {} to {}) runs past the end of buffer {} \
                 ({have} bytes)",
                view.index(),
                view.offset(),
                view.offset().saturating_add(view.length()),
                buffer.index()
            ));
        }
        Ok(())
    };
    if let Some(view) = acc.view() {
        span("", view, acc.offset(), acc.count(), size)?;
    }
    if let Some(sparse) = acc.sparse() {
        let n = sparse.count();
        if n == 0 || n > acc.count() {
            return Err(format!(
                "{at}: sparse count {n} is not in [1, {}]",
                acc.count()
            ));
        }
        let idx = sparse.indices();
        span(
            " (sparse indices)",
            idx.view(),
            idx.offset(),
            n,
            idx.index_type().size(),
        )?;
        let values = sparse.values();
        span(" (sparse values)", values.view(), values.offset(), n, size)?;
    }
    Ok(())
}

/// Appends one primitive's triangles, in world coordinates, to `out`, and with `uvs` each
/// triangle's corners' `TEXCOORD_0` (zeros where the primitive has none it can read; the
/// result says whether it had).
pub(crate) fn read_primitive(
    mesh: &gltf::Mesh,
    prim: &gltf::Primitive,
    buffers: &[Vec<u8>],
    world: Mat4,
    out: &mut Vec<[Vec3; 3]>,
    uvs: Option<&mut Vec<[[f32; 2]; 3]>>,
) -> Result<bool, MeshError> {
    let label = primitive_label(mesh, prim);
    let fail = |what: String| malformed(format!("{label}: {what}"));
    let mode = prim.mode();
    if !matches!(
        mode,
        Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
    ) {
        let name = match mode {
            Mode::Points => "POINTS",
            Mode::Lines => "LINES",
            Mode::LineLoop => "LINE_LOOP",
            _ => "LINE_STRIP",
        };
        return Err(fail(format!(
            "mode {name} draws no surface; only TRIANGLES, TRIANGLE_STRIP and TRIANGLE_FAN \
             primitives are read"
        )));
    }
    let Some(pos) = prim.get(&Semantic::Positions) else {
        return Err(fail("has no POSITION attribute".to_owned()));
    };
    check_accessor(&pos, Dimensions::Vec3, &[DataType::F32], buffers)
        .map_err(|e| fail(format!("POSITION {e}")))?;
    if let Some(idx) = prim.indices() {
        check_accessor(
            &idx,
            Dimensions::Scalar,
            &[DataType::U8, DataType::U16, DataType::U32],
            buffers,
        )
        .map_err(|e| fail(format!("indices {e}")))?;
    }
    let reader = prim.reader(|b| buffers.get(b.index()).map(Vec::as_slice));
    let positions: Vec<Vec3> = reader
        .read_positions()
        .ok_or_else(|| fail("cannot read the POSITION data".to_owned()))?
        .map(Vec3::from)
        .collect();
    if positions.len() != pos.count() {
        return Err(fail(format!(
            "POSITION accessor {} gave {} of its {} vertices",
            pos.index(),
            positions.len(),
            pos.count()
        )));
    }
    if let Some(k) = positions.iter().position(|p| !p.is_finite()) {
        return Err(fail(format!(
            "vertex {k} has a coordinate that is not a finite number"
        )));
    }
    let n = positions.len();
    let indices: Vec<u32> = match (prim.indices(), reader.read_indices()) {
        (Some(acc), Some(r)) => {
            let v: Vec<u32> = r.into_u32().collect();
            if v.len() != acc.count() {
                return Err(fail(format!(
                    "indices accessor {} gave {} of its {} indices",
                    acc.index(),
                    v.len(),
                    acc.count()
                )));
            }
            if let Some(&i) = v.iter().find(|&&i| i as usize >= n) {
                return Err(fail(format!(
                    "vertex index {i} is out of range (POSITION has {n} vertices)"
                )));
            }
            v
        }
        (Some(acc), None) => {
            return Err(fail(format!(
                "cannot read indices accessor {}",
                acc.index()
            )));
        }
        (None, _) => (0..n as u32).collect(),
    };
    // Corner triples per the glTF 2.0 spec (§3.7.2.1): strips alternate their winding so
    // every triangle keeps the first one's side; fans turn around the first vertex.
    let corners: Vec<[u32; 3]> = match mode {
        Mode::TriangleStrip => (0..indices.len().saturating_sub(2))
            .map(|i| {
                let (a, b, c) = (indices[i], indices[i + 1], indices[i + 2]);
                if i % 2 == 0 { [a, b, c] } else { [a, c, b] }
            })
            .collect(),
        Mode::TriangleFan => (1..indices.len().saturating_sub(1))
            .map(|i| [indices[0], indices[i], indices[i + 1]])
            .collect(),
        _ => {
            if !indices.len().is_multiple_of(3) {
                return Err(fail(format!(
                    "TRIANGLES with {} vertex indices, not a multiple of 3",
                    indices.len()
                )));
            }
            indices
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect()
        }
    };
    // A mirroring world transform turns faces inside out; swapping two corners keeps the
    // side a face faces (as the spec asks of a negative determinant).
    let flip = world.determinant() < 0.0;
    let placed: Vec<Vec3> = positions
        .iter()
        .map(|&p| world.transform_point3(p))
        .collect();
    if !placed.iter().all(|p| p.is_finite()) {
        return Err(fail(
            "its node's world transform gives non-finite coordinates".to_owned(),
        ));
    }
    let at = |i: u32| placed[i as usize];
    let order = |[a, b, c]: [u32; 3]| if flip { [a, c, b] } else { [a, b, c] };
    out.extend(corners.iter().map(|&t| order(t).map(at)));
    let Some(uvs) = uvs else {
        return Ok(false);
    };
    // TEXCOORD_0 as float pairs, one per vertex; anything else is read as no coordinates.
    let coords: Option<Vec<[f32; 2]>> = prim
        .get(&Semantic::TexCoords(0))
        .filter(|acc| check_accessor(acc, Dimensions::Vec2, &[DataType::F32], buffers).is_ok())
        .and_then(|_| reader.read_tex_coords(0))
        .map(|r| r.into_f32().collect::<Vec<_>>())
        .filter(|c| c.len() == n && c.iter().flatten().all(|x| x.is_finite()));
    match &coords {
        Some(c) => uvs.extend(corners.iter().map(|&t| order(t).map(|i| c[i as usize]))),
        None => uvs.extend(corners.iter().map(|_| [[0.0; 2]; 3])),
    }
    Ok(coords.is_some())
}

// ---------------------------------------------------------------------------------------
// Triangle counts without geometry

/// How many triangles reading `path` would give (polygons fan-triangulated, glTF meshes
/// once per node that places them), read from the file without building any geometry: a
/// scene's size is checked before it is loaded. Memory stays flat whatever the count: OBJ
/// is read line by line, PLY keeps one corner count per face, glTF reads only its JSON.
/// A file the readers would refuse may still be counted; loading it names the problem.
///
/// One object of a glTF file (`room.glb#Wall`) is counted by
/// [`crate::scene::triangle_count`].
pub fn triangle_count(path: &Path) -> Result<u64, MeshError> {
    match MeshFormat::from_path(path).map_err(malformed)? {
        MeshFormat::Obj => obj_triangle_count(path),
        MeshFormat::Ply => ply_triangle_count(path),
        MeshFormat::Gltf => gltf_triangle_count(path),
    }
}

/// An OBJ file's `f` lines, each of k corners k − 2 triangles. Counted here because tobj
/// builds the whole mesh to count it.
fn obj_triangle_count(path: &Path) -> Result<u64, MeshError> {
    use std::io::BufRead;
    let mut reader = BufReader::new(open(path)?);
    let (mut count, mut line) = (0u64, Vec::new());
    loop {
        line.clear();
        if reader.read_until(b'\n', &mut line).map_err(MeshError::Io)? == 0 {
            return Ok(count);
        }
        let mut words = line
            .split(|b| b.is_ascii_whitespace())
            .filter(|w| !w.is_empty());
        if words.next() == Some(b"f".as_slice()) {
            count += (words.count() as u64).saturating_sub(2);
        }
    }
}

/// A PLY face's corner count; everything else ignored.
#[derive(Debug, Default)]
struct PlyCorners(u32);

impl PlyCorners {
    fn set(&mut self, name: &str, len: usize) -> PropertyAccessResult {
        if !PLY_FACE_LISTS.contains(&name) {
            return PropertyAccessResult::Ignored;
        }
        self.0 = u32::try_from(len).unwrap_or(u32::MAX);
        PropertyAccessResult::Set
    }
}

impl PropertyAccess for PlyCorners {
    fn new() -> Self {
        Self::default()
    }
    fn set_list_char(&mut self, name: &str, v: Vec<i8>) -> PropertyAccessResult {
        self.set(name, v.len())
    }
    fn set_list_uchar(&mut self, name: &str, v: Vec<u8>) -> PropertyAccessResult {
        self.set(name, v.len())
    }
    fn set_list_short(&mut self, name: &str, v: Vec<i16>) -> PropertyAccessResult {
        self.set(name, v.len())
    }
    fn set_list_ushort(&mut self, name: &str, v: Vec<u16>) -> PropertyAccessResult {
        self.set(name, v.len())
    }
    fn set_list_int(&mut self, name: &str, v: Vec<i32>) -> PropertyAccessResult {
        self.set(name, v.len())
    }
    fn set_list_uint(&mut self, name: &str, v: Vec<u32>) -> PropertyAccessResult {
        self.set(name, v.len())
    }
}

/// A PLY file's faces, each of k corners k − 2 triangles; the vertices are read past.
fn ply_triangle_count(path: &Path) -> Result<u64, MeshError> {
    let mut reader = Reader::new(BufReader::new(open(path)?));
    let header = Parser::<PlySkip>::new()
        .read_header(&mut reader)
        .map_err(|e| ply_error(e, false))?;
    let binary = header.encoding != ply_rs_bw::ply::Encoding::Ascii;
    check_ply_header(header.elements.get("vertex"), header.elements.get("face"))
        .map_err(malformed)?;
    let mut count = 0u64;
    for (name, def) in &header.elements {
        if name == "face" {
            let faces = Parser::<PlyCorners>::new()
                .read_payload_for_element(&mut reader, def, &header)
                .map_err(|e| ply_error(e, binary))?;
            count += faces
                .iter()
                .map(|f| u64::from(f.0.saturating_sub(2)))
                .sum::<u64>();
            // Nothing after the faces changes the count.
            break;
        }
        Parser::<PlySkip>::new()
            .read_payload_for_element(&mut reader, def, &header)
            .map_err(|e| ply_error(e, binary))?;
    }
    Ok(count)
}

/// A glTF file's triangles from its accessors' counts: per node placing a mesh, per
/// TRIANGLES primitive a third of its indices (or vertices), per strip or fan two fewer.
fn gltf_triangle_count(path: &Path) -> Result<u64, MeshError> {
    let (doc, _) = gltf_document(path)?;
    let mut count = 0u64;
    for (node, _) in gltf_placed(&doc)? {
        for prim in node.mesh().iter().flat_map(|m| m.primitives()) {
            let corners = match prim.indices() {
                Some(idx) => idx.count(),
                None => prim.get(&Semantic::Positions).map_or(0, |p| p.count()),
            } as u64;
            count = count.saturating_add(match prim.mode() {
                Mode::Triangles => corners / 3,
                Mode::TriangleStrip | Mode::TriangleFan => corners.saturating_sub(2),
                _ => 0,
            });
        }
    }
    Ok(count)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn node_references_split_at_the_gltf_file() {
        assert_eq!(split_node_ref("room.glb#Wall"), Some(("room.glb", "Wall")));
        assert_eq!(
            split_node_ref("dir/Room.GLTF#Lamp #2"),
            Some(("dir/Room.GLTF", "Lamp #2"))
        );
        assert_eq!(split_node_ref("a#b.glb#C#D"), Some(("a#b.glb", "C#D")));
        assert_eq!(split_node_ref("room.glb"), None);
        assert_eq!(split_node_ref("model#1.obj"), None);
    }

    #[test]
    fn a_required_extension_is_refused_by_name() {
        check_required_extensions(&["KHR_materials_volume".to_owned()]).unwrap();
        let e = check_required_extensions(&[
            "KHR_lights_punctual".to_owned(),
            "EXT_meshopt_compression".to_owned(),
        ])
        .unwrap_err()
        .to_string();
        assert!(e.contains("\"EXT_meshopt_compression\""), "{e}");
        assert!(!e.contains("\"KHR_lights_punctual\""), "{e}");
    }
}
