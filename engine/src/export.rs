//! Mesh export with baked vertex colours: binary glTF 2.0 (`.glb`) and binary PLY.
//!
//! In: an [`ExportMesh`] (vertex positions and normals, triangles counter-clockwise seen from
//! the front, linear radiance B/π per vertex as a relight answers it, the scene's unit and its
//! objects as named runs of triangles), an exposure in EV stops and a [`ToneMap`]. Out: the
//! bytes of a file.
//!
//! Colours: c = tone(L · 2^EV) per channel, with the tone curve of [`crate::render`] (clamp
//! to [0, 1], or the ACES filmic fit). Then:
//!
//! - **glTF** stores `COLOR_0` as float RGB **in linear space**: the glTF 2.0 specification
//!   defines vertex colours as a linear multiplier of the base colour, and viewers apply the
//!   display encoding (the sRGB OETF) to their output themselves. So the export applies the
//!   exposure and the tone curve but **not** the sRGB OETF; applying it here would brighten
//!   every mid-tone twice. The material is white, non-metallic, fully rough and carries
//!   `KHR_materials_unlit`, so viewers that know the extension show the baked colours as
//!   they are (no lighting on top); others fall back to a lit white PBR material tinted by
//!   the colours. `doubleSided` is false, like the renderer's default back-face culling: a
//!   closed room is seen from outside through its near wall.
//! - **PLY** stores red, green, blue as `uchar` **sRGB-encoded** (the MeshLab / CloudCompare
//!   convention: 8-bit colours are display values): round(255 · OETF(c)), exactly the pixel
//!   values [`crate::render::render`] would show for the same vertex.
//!
//! Units. glTF lengths are metres (specification §3.4), and a bundle's positions are in
//! scene units of `unit_mm` millimetres, so the `.glb` multiplies positions by
//! unit_mm / 1000 (a centimetre scene, unit_mm = 10, by 0.01; a metre scene is written
//! unchanged). Normals need no change: the scale is uniform. PLY has no unit convention: it
//! keeps scene units and its header says what one is.
//!
//! Objects. The `.glb` has one mesh (one primitive) and one node per [`MeshPart`], both named
//! after it, so a modelling tool lists `tall_block` rather than one anonymous mesh. Each
//! primitive has its own vertices: those its triangles use, in ascending order of their input
//! index, with the indices rebased (a vertex that two parts share is written in both). A part
//! without triangles becomes a node without a mesh (glTF accessors need count ≥ 1), so every
//! object's name is still there. PLY has no standard grouping and writes the whole mesh.
//!
//! Readers. `COLOR_0` as float `VEC3` is one of the three encodings the specification allows
//! and is read as written by Blender's importer and by trimesh. (Normalized `u16`, also
//! allowed, is not: trimesh 5.2 casts the raw 0..65535 values to 8 bits.) trimesh hands a
//! primitive's `COLOR_0` to `visual.vertex_colors` only when the primitive has no material;
//! with one it keeps them as `visual.vertex_attributes["color"]`, or gives `vertex_colors` when
//! loaded with `skip_materials=True`. The material stays nonetheless: without one, glTF's
//! default material is fully metallic, which most viewers show nearly black.
//!
//! The `.glb` layout (glTF 2.0 §4.4): a 12-byte header (`glTF`, version 2, total length),
//! a JSON chunk padded with spaces to a multiple of 4 bytes, and a BIN chunk padded with
//! zeros, holding in order the positions of every part (part after part), then their
//! normals, then their colours (`f32` × 3 per vertex each), then their indices (`u32` × 3 per
//! triangle); each part's run of each has its own buffer view and accessor. `POSITION` has the
//! `min`/`max` the specification requires. Normals are written unit length (glTF requires
//! it); a zero normal is written as +Z.
//!
//! The PLY layout: an ASCII header ([`ply_header_in`]), then per vertex x y z nx ny nz
//! (`float`) and red green blue (`uchar`), 27 bytes, then per face a `uchar` count 3 and three
//! `int` indices, 13 bytes, little-endian.

use std::ops::Range;

use serde_json::{Value, json};
use translux_proto::api::ToneMap;

use crate::render::{exposure_scale, srgb_oetf, to_u8, tone_map};

/// Why an export failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ExportError {
    /// The arrays disagree, an index is out of range, a value is not finite, a part's
    /// triangles are out of range, or the unit is not a positive number.
    #[error("bad mesh: {0}")]
    Mesh(String),
    /// `exposure` is not finite or out of range.
    #[error("exposure must be finite and in [-64, 64] (got {0})")]
    Exposure(String),
    /// The file would be larger than its format can say (a `.glb` over 4 GiB, more than
    /// 2³¹ − 1 vertices in a PLY).
    #[error("too large: {0}")]
    TooLarge(String),
    /// The glTF JSON could not be written.
    #[error("cannot write the glTF JSON: {0}")]
    Json(String),
}

/// glTF's magic, "glTF" read as a little-endian u32.
pub const GLB_MAGIC: u32 = 0x4654_6C67;
/// Chunk type "JSON".
pub const GLB_CHUNK_JSON: u32 = 0x4E4F_534A;
/// Chunk type "BIN\0".
pub const GLB_CHUNK_BIN: u32 = 0x004E_4942;

/// Millimetres in a metre: the `unit_mm` of a scene in metres, glTF's unit.
pub const METRE_MM: f64 = 1000.0;

/// The name of the one part of a mesh exported without parts.
pub const DEFAULT_PART: &str = "mesh";

/// One named part of an exported mesh: a scene object and its run of triangles.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MeshPart {
    /// The node's and the mesh's name in the `.glb` (the object's name).
    pub name: String,
    /// Its triangles, as indices into [`ExportMesh::triangles`].
    pub triangles: Range<usize>,
}

/// A mesh to export. Build it with [`ExportMesh::new`] and set `unit_mm` and `parts`.
#[derive(Debug, Clone, Copy)]
pub struct ExportMesh<'a> {
    /// Scene units.
    pub positions: &'a [[f32; 3]],
    /// One per vertex, any length (the `.glb` normalizes them, PLY writes them as given).
    pub normals: &'a [[f32; 3]],
    /// Indices into the vertices, counter-clockwise seen from the front.
    pub triangles: &'a [[u32; 3]],
    /// Linear radiance B/π per vertex.
    pub vertex_radiance: &'a [[f32; 3]],
    /// Millimetres per scene unit (a bundle manifest's `unit_mm`; [`METRE_MM`] for metres).
    pub unit_mm: f64,
    /// The objects, each one mesh and node of the `.glb`; they should cover every triangle
    /// (a bundle's objects do: their patch ranges partition the viewer triangles). Empty:
    /// one part named [`DEFAULT_PART`] with every triangle. PLY ignores them.
    pub parts: &'a [MeshPart],
}

impl<'a> ExportMesh<'a> {
    /// A mesh in metres, without parts.
    pub fn new(
        positions: &'a [[f32; 3]],
        normals: &'a [[f32; 3]],
        triangles: &'a [[u32; 3]],
        vertex_radiance: &'a [[f32; 3]],
    ) -> Self {
        ExportMesh {
            positions,
            normals,
            triangles,
            vertex_radiance,
            unit_mm: METRE_MM,
            parts: &[],
        }
    }
}

/// Checks the arrays, the unit and the exposure; returns 2^exposure.
fn check(mesh: &ExportMesh, exposure: f32) -> Result<f32, ExportError> {
    let limit = crate::render::MAX_EXPOSURE;
    if !(exposure.is_finite() && (-limit..=limit).contains(&exposure)) {
        return Err(ExportError::Exposure(exposure.to_string()));
    }
    if !(mesh.unit_mm.is_finite() && mesh.unit_mm > 0.0) {
        return Err(ExportError::Mesh(format!(
            "unit_mm must be finite and > 0 (got {})",
            mesh.unit_mm
        )));
    }
    let n = mesh.positions.len();
    for (name, len) in [
        ("normals", mesh.normals.len()),
        ("vertex_radiance", mesh.vertex_radiance.len()),
    ] {
        if len != n {
            return Err(ExportError::Mesh(format!(
                "{name} has {len} entries for {n} vertices"
            )));
        }
    }
    for (name, arr) in [
        ("positions", mesh.positions),
        ("normals", mesh.normals),
        ("vertex_radiance", mesh.vertex_radiance),
    ] {
        if let Some(k) = arr.iter().position(|v| !v.iter().all(|x| x.is_finite())) {
            return Err(ExportError::Mesh(format!(
                "{name}[{k}] = {:?} is not finite",
                arr[k]
            )));
        }
    }
    if let Some((k, t)) = mesh
        .triangles
        .iter()
        .enumerate()
        .find(|(_, t)| t.iter().any(|&i| i as usize >= n))
    {
        return Err(ExportError::Mesh(format!(
            "triangles[{k}] = {t:?} has an index out of range ({n} vertices)"
        )));
    }
    Ok(exposure_scale(exposure))
}

/// The linear display colour glTF stores: tone(L · scale) per channel, no OETF.
pub fn linear_colour(radiance: [f32; 3], scale: f32, tone: ToneMap) -> [f32; 3] {
    radiance.map(|c| tone_map(c * scale, tone))
}

/// The 8-bit sRGB colour PLY stores: round(255 · OETF(tone(L · scale))).
pub fn srgb8_colour(radiance: [f32; 3], scale: f32, tone: ToneMap) -> [u8; 3] {
    linear_colour(radiance, scale, tone).map(|c| to_u8(srgb_oetf(c)))
}

/// n / |n|, or +Z for a zero normal.
fn unit(n: [f32; 3]) -> [f32; 3] {
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if len > 1e-20 && len.is_finite() {
        n.map(|x| x / len)
    } else {
        [0.0, 0.0, 1.0]
    }
}

/// The factor from scene units to metres: unit_mm / 1000.
pub fn metres_per_unit(unit_mm: f64) -> f64 {
    unit_mm / METRE_MM
}

/// glTF 2.0 enum values: accessor component types, buffer-view targets.
const FLOAT: u32 = 5126;
const UNSIGNED_INT: u32 = 5125;
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;
/// Primitive mode TRIANGLES.
const TRIANGLES: u32 = 4;

/// A part's vertices: the input indices its triangles use, ascending.
fn part_vertices(triangles: &[[u32; 3]], stamp: &mut [u32], id: u32) -> Vec<u32> {
    let mut used = Vec::new();
    for &i in triangles.iter().flatten() {
        // `stamp[i] == id` marks a vertex already taken for this part, so one array serves
        // every part without being cleared between them.
        if stamp[i as usize] != id {
            stamp[i as usize] = id;
            used.push(i);
        }
    }
    used.sort_unstable();
    used
}

/// A binary glTF 2.0 file of the mesh with baked linear vertex colours, positions in metres
/// and one named node per part; see the module documentation for what goes where.
pub fn to_glb(mesh: &ExportMesh, exposure: f32, tone: ToneMap) -> Result<Vec<u8>, ExportError> {
    let scale = check(mesh, exposure)?;
    let (nv, nf) = (mesh.positions.len(), mesh.triangles.len());
    if nv == 0 || nf == 0 {
        // glTF accessors need count ≥ 1.
        return Err(ExportError::Mesh(
            "the mesh is empty (glTF needs at least one vertex and one triangle)".into(),
        ));
    }
    let whole = [MeshPart {
        name: DEFAULT_PART.into(),
        triangles: 0..nf,
    }];
    let parts = if mesh.parts.is_empty() {
        &whole[..]
    } else {
        mesh.parts
    };
    if let Some(p) = parts
        .iter()
        .find(|p| p.triangles.start > p.triangles.end || p.triangles.end > nf)
    {
        return Err(ExportError::Mesh(format!(
            "part {:?} has triangles {:?}, outside 0..{nf}",
            p.name, p.triangles
        )));
    }
    let metres = metres_per_unit(mesh.unit_mm);

    // Each part's vertices, and the buffer's size before anything is written.
    let mut stamp = vec![u32::MAX; nv];
    let vertices: Vec<Vec<u32>> = parts
        .iter()
        .enumerate()
        .map(|(k, p)| part_vertices(&mesh.triangles[p.triangles.clone()], &mut stamp, k as u32))
        .collect();
    let vertex_total: u64 = vertices.iter().map(|v| v.len() as u64).sum();
    let triangle_total: u64 = parts.iter().map(|p| p.triangles.len() as u64).sum();
    let attr_bytes = vertex_total * 12;
    let bin_len = 3 * attr_bytes + triangle_total * 12; // a multiple of 4 already
    if bin_len > u32::MAX as u64 / 2 {
        return Err(ExportError::TooLarge(format!(
            "{vertex_total} vertices and {triangle_total} triangles need {bin_len} bytes of \
             buffer; a .glb holds under 4 GiB"
        )));
    }

    // BIN: positions | normals | colours | indices, each part after part. `runs[k]` holds
    // part k's (offset, length) in each of the four sections.
    let mut bin: Vec<u8> = Vec::with_capacity(bin_len as usize);
    let mut runs = vec![[(0usize, 0usize); 4]; parts.len()];
    let mut bounds = vec![([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]); parts.len()];
    let put = |bin: &mut Vec<u8>, v: [f32; 3]| {
        for x in v {
            bin.extend_from_slice(&x.to_le_bytes());
        }
    };
    for (k, vs) in vertices.iter().enumerate() {
        let at = bin.len();
        let (lo, hi) = &mut bounds[k];
        for &i in vs {
            // In f64, so that the product is rounded once.
            let p = mesh.positions[i as usize].map(|x| (f64::from(x) * metres) as f32);
            for c in 0..3 {
                lo[c] = lo[c].min(p[c]);
                hi[c] = hi[c].max(p[c]);
            }
            put(&mut bin, p);
        }
        if !vs.is_empty() && !lo.iter().chain(hi.iter()).all(|x| x.is_finite()) {
            return Err(ExportError::Mesh(format!(
                "part {:?}: positions overflow when scaled to metres (unit_mm {})",
                parts[k].name, mesh.unit_mm
            )));
        }
        runs[k][0] = (at, bin.len() - at);
    }
    for (k, vs) in vertices.iter().enumerate() {
        let at = bin.len();
        for &i in vs {
            put(&mut bin, unit(mesh.normals[i as usize]));
        }
        runs[k][1] = (at, bin.len() - at);
    }
    for (k, vs) in vertices.iter().enumerate() {
        let at = bin.len();
        for &i in vs {
            put(
                &mut bin,
                linear_colour(mesh.vertex_radiance[i as usize], scale, tone),
            );
        }
        runs[k][2] = (at, bin.len() - at);
    }
    // `local[i]`: vertex i's index within the part being written (`stamp` is free again).
    let local = &mut stamp;
    for (k, (p, vs)) in parts.iter().zip(&vertices).enumerate() {
        for (j, &i) in vs.iter().enumerate() {
            local[i as usize] = j as u32;
        }
        let at = bin.len();
        for &i in mesh.triangles[p.triangles.clone()].iter().flatten() {
            bin.extend_from_slice(&local[i as usize].to_le_bytes());
        }
        runs[k][3] = (at, bin.len() - at);
    }
    debug_assert_eq!(bin.len() as u64, bin_len);

    // JSON: per part one buffer view and accessor for each section, a mesh and a node.
    let mut views = Vec::new();
    let mut accessors = Vec::new();
    let mut accessor = |(offset, len): (usize, usize), target: u32, mut a: Value| {
        views.push(json!({
            "buffer": 0, "byteOffset": offset, "byteLength": len, "target": target,
        }));
        a["bufferView"] = json!(views.len() - 1);
        accessors.push(a);
        accessors.len() - 1
    };
    let mut meshes = Vec::new();
    let mut nodes = Vec::new();
    for (k, (p, vs)) in parts.iter().zip(&vertices).enumerate() {
        if vs.is_empty() {
            nodes.push(json!({ "name": p.name }));
            continue;
        }
        let count = vs.len();
        let (lo, hi) = bounds[k];
        let vec3 = |extra: Value| {
            let mut a = json!({ "componentType": FLOAT, "count": count, "type": "VEC3" });
            if let (Value::Object(a), Value::Object(extra)) = (&mut a, extra) {
                a.extend(extra);
            }
            a
        };
        let position = accessor(
            runs[k][0],
            ARRAY_BUFFER,
            vec3(json!({ "min": lo, "max": hi })),
        );
        let normal = accessor(runs[k][1], ARRAY_BUFFER, vec3(json!({})));
        let colour = accessor(runs[k][2], ARRAY_BUFFER, vec3(json!({})));
        let indices = accessor(
            runs[k][3],
            ELEMENT_ARRAY_BUFFER,
            json!({
                "componentType": UNSIGNED_INT,
                "count": 3 * p.triangles.len(),
                "type": "SCALAR",
            }),
        );
        meshes.push(json!({
            "name": p.name,
            "primitives": [{
                "attributes": { "POSITION": position, "NORMAL": normal, "COLOR_0": colour },
                "indices": indices,
                "material": 0,
                "mode": TRIANGLES,
            }],
        }));
        nodes.push(json!({ "name": p.name, "mesh": meshes.len() - 1 }));
    }
    let root = json!({
        "asset": {
            "version": "2.0",
            "generator": format!(
                "translux {} (COLOR_0: linear B/pi, exposure {exposure} EV, tone {}; \
                 positions in metres, 1 scene unit = {} mm)",
                env!("CARGO_PKG_VERSION"),
                tone.as_str(),
                mesh.unit_mm
            ),
        },
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0,
        "scenes": [{ "nodes": (0..nodes.len()).collect::<Vec<_>>() }],
        "nodes": nodes,
        "meshes": meshes,
        "materials": [{
            "name": "translux baked colours",
            "pbrMetallicRoughness": {
                "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                "metallicFactor": 0.0,
                "roughnessFactor": 1.0,
            },
            "doubleSided": false,
            "extensions": { "KHR_materials_unlit": {} },
        }],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{ "byteLength": bin_len }],
    });

    let mut text = serde_json::to_vec(&root).map_err(|e| ExportError::Json(e.to_string()))?;
    // Chunks start and end on 4-byte boundaries: JSON padded with spaces, BIN with zeros.
    text.resize(text.len().next_multiple_of(4), b' ');
    let total = 12 + 8 + text.len() as u64 + 8 + bin.len() as u64;
    if total > u32::MAX as u64 {
        return Err(ExportError::TooLarge(format!(
            "the .glb would be {total} bytes; the format holds under 4 GiB"
        )));
    }
    let mut out = Vec::with_capacity(total as usize);
    for word in [
        GLB_MAGIC,
        2,
        total as u32,
        text.len() as u32,
        GLB_CHUNK_JSON,
    ] {
        out.extend_from_slice(&word.to_le_bytes());
    }
    out.extend_from_slice(&text);
    for word in [bin.len() as u32, GLB_CHUNK_BIN] {
        out.extend_from_slice(&word.to_le_bytes());
    }
    out.extend_from_slice(&bin);
    Ok(out)
}

/// The PLY header for `vertices` vertices and `faces` faces of a scene in metres
/// ([`ply_header_in`] with unit_mm = 1000, the built-in scenes' unit).
pub fn ply_header(vertices: usize, faces: usize, exposure: f32, tone: ToneMap) -> String {
    ply_header_in(vertices, faces, exposure, tone, METRE_MM)
}

/// The PLY header for `vertices` vertices and `faces` faces (ASCII, `\n` line ends); a
/// comment says what the colours are and how long a scene unit is, as positions stay in
/// scene units.
pub fn ply_header_in(
    vertices: usize,
    faces: usize,
    exposure: f32,
    tone: ToneMap,
    unit_mm: f64,
) -> String {
    format!(
        "ply\n\
         format binary_little_endian 1.0\n\
         comment translux: colours are sRGB-encoded B/pi, exposure {exposure} EV, tone {}\n\
         comment translux: positions in scene units, 1 unit = {unit_mm} mm\n\
         element vertex {vertices}\n\
         property float x\n\
         property float y\n\
         property float z\n\
         property float nx\n\
         property float ny\n\
         property float nz\n\
         property uchar red\n\
         property uchar green\n\
         property uchar blue\n\
         element face {faces}\n\
         property list uchar int vertex_indices\n\
         end_header\n",
        tone.as_str()
    )
}

/// A binary little-endian PLY of the mesh with 8-bit sRGB vertex colours, positions in scene
/// units; see the module documentation. Normals are written as given; parts are ignored.
pub fn to_ply(mesh: &ExportMesh, exposure: f32, tone: ToneMap) -> Result<Vec<u8>, ExportError> {
    let scale = check(mesh, exposure)?;
    let (positions, triangles) = (mesh.positions, mesh.triangles);
    // Face indices are PLY `int` (i32).
    if positions.len() > i32::MAX as usize {
        return Err(ExportError::TooLarge(format!(
            "{} vertices; PLY int indices reach {}",
            positions.len(),
            i32::MAX
        )));
    }
    let header = ply_header_in(
        positions.len(),
        triangles.len(),
        exposure,
        tone,
        mesh.unit_mm,
    );
    let mut out = Vec::with_capacity(header.len() + 27 * positions.len() + 13 * triangles.len());
    out.extend_from_slice(header.as_bytes());
    for ((p, n), c) in positions.iter().zip(mesh.normals).zip(mesh.vertex_radiance) {
        for x in p.iter().chain(n) {
            out.extend_from_slice(&x.to_le_bytes());
        }
        out.extend_from_slice(&srgb8_colour(*c, scale, tone));
    }
    for t in triangles {
        out.push(3);
        for &i in t {
            // i < positions.len() ≤ i32::MAX (checked above).
            out.extend_from_slice(&(i as i32).to_le_bytes());
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use gltf_json as json;

    /// Positions, normals, triangles, radiance.
    type TestMesh = (Vec<[f32; 3]>, Vec<[f32; 3]>, Vec<[u32; 3]>, Vec<[f32; 3]>);

    /// A quad facing +Z (one corner bent back), radiance 0.5 / (0.25, 0.5, 1) / 0 / 2.
    fn quad() -> TestMesh {
        (
            vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 2.0, 0.0],
                [0.0, 2.0, -0.5],
            ],
            vec![[0.0, 0.0, 2.0]; 4],
            vec![[0, 1, 2], [0, 2, 3]],
            vec![[0.5; 3], [0.25, 0.5, 1.0], [0.0; 3], [2.0; 3]],
        )
    }

    fn mesh(m: &TestMesh) -> ExportMesh<'_> {
        ExportMesh::new(&m.0, &m.1, &m.2, &m.3)
    }

    fn u32_at(b: &[u8], at: usize) -> u32 {
        u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
    }

    fn f32s(b: &[u8]) -> Vec<f32> {
        b.chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect()
    }

    /// A parsed `.glb`: the JSON as gltf-json reads it (validated), the raw JSON (gltf-json
    /// without its `names` feature drops names), and the BIN chunk.
    struct Glb {
        root: json::Root,
        raw: Value,
        bin: Vec<u8>,
    }

    impl Glb {
        /// Checks the header, the chunks and their padding, and the JSON against the
        /// specification's rules (gltf-json's validation).
        fn parse(glb: &[u8]) -> Glb {
            assert_eq!(&glb[..4], b"glTF");
            assert_eq!(u32_at(glb, 4), 2);
            assert_eq!(u32_at(glb, 8) as usize, glb.len());
            let json_len = u32_at(glb, 12) as usize;
            assert_eq!(&glb[16..20], b"JSON");
            assert_eq!(json_len % 4, 0);
            let text = &glb[20..20 + json_len];
            assert!(
                text.iter()
                    .rev()
                    .take_while(|&&b| b != b'}')
                    .all(|&b| b == b' '),
                "JSON padding must be spaces"
            );
            let root = json::Root::from_slice(text).unwrap();
            let mut errors = Vec::new();
            json::validation::Validate::validate(
                &root,
                &root,
                json::Path::new,
                &mut |path: &dyn Fn() -> json::Path, e| errors.push(format!("{}: {e}", path())),
            );
            assert!(errors.is_empty(), "{errors:?}");
            let bin_at = 20 + json_len;
            assert_eq!(bin_at % 4, 0);
            let bin_len = u32_at(glb, bin_at) as usize;
            assert_eq!(&glb[bin_at + 4..bin_at + 8], b"BIN\0");
            assert_eq!(bin_len % 4, 0);
            assert_eq!(bin_at + 8 + bin_len, glb.len());
            assert_eq!(root.buffers.len(), 1);
            assert_eq!(root.buffers[0].byte_length.0 as usize, bin_len);
            Glb {
                root,
                raw: serde_json::from_slice(text).unwrap(),
                bin: glb[bin_at + 8..].to_vec(),
            }
        }

        /// The bytes of accessor `k`.
        fn data(&self, k: usize) -> &[u8] {
            let a = &self.root.accessors[k];
            let v = &self.root.buffer_views[a.buffer_view.unwrap().value()];
            let at = v.byte_offset.unwrap().0 as usize + a.byte_offset.map_or(0, |o| o.0 as usize);
            &self.bin[at..at + v.byte_length.0 as usize]
        }

        /// Mesh `m`'s (POSITION, NORMAL, COLOR_0, indices) accessors.
        fn accessors(&self, m: usize) -> [usize; 4] {
            let prim = &self.root.meshes[m].primitives[0];
            let get = |s: json::mesh::Semantic| {
                prim.attributes[&json::validation::Checked::Valid(s)].value()
            };
            [
                get(json::mesh::Semantic::Positions),
                get(json::mesh::Semantic::Normals),
                get(json::mesh::Semantic::Colors(0)),
                prim.indices.unwrap().value(),
            ]
        }

        fn indices(&self, k: usize) -> Vec<u32> {
            self.data(k)
                .chunks_exact(4)
                .map(|c| u32::from_le_bytes(c.try_into().unwrap()))
                .collect()
        }
    }

    #[test]
    fn glb_is_valid_gltf_with_linear_colours() {
        let q = quad();
        let (p, _, _, _) = &q;
        let glb = Glb::parse(&to_glb(&mesh(&q), 0.0, ToneMap::Srgb).unwrap());
        let root = &glb.root;
        assert_eq!(glb.bin.len(), 4 * 36 + 2 * 12);

        // Without parts: one mesh and one node, both named "mesh".
        assert_eq!(root.accessors.len(), 4);
        assert_eq!(root.meshes.len(), 1);
        assert_eq!(root.nodes.len(), 1);
        assert_eq!(glb.raw["nodes"][0]["name"], "mesh");
        assert_eq!(glb.raw["meshes"][0]["name"], "mesh");
        assert_eq!(
            root.extensions_used,
            vec!["KHR_materials_unlit".to_string()]
        );
        let [pos, nrm, col, idx] = glb.accessors(0);
        let pos_a = &root.accessors[pos];
        assert_eq!(pos_a.count.0, 4);
        assert_eq!(pos_a.min, Some(serde_json::json!([0.0, 0.0, -0.5])));
        assert_eq!(pos_a.max, Some(serde_json::json!([1.0, 2.0, 0.0])));
        assert_eq!(root.accessors[nrm].count.0, 4);
        assert_eq!(root.accessors[col].count.0, 4);
        assert_eq!(root.accessors[idx].count.0, 6);
        let prim = &root.meshes[0].primitives[0];
        let m = &root.materials[prim.material.unwrap().value()];
        assert!(m.extensions.as_ref().unwrap().unlit.is_some());
        assert_eq!(m.pbr_metallic_roughness.metallic_factor.0, 0.0);

        // Data: positions as given (a metre scene), normals unit length, colours linear (no
        // OETF), indices as given.
        assert_eq!(f32s(glb.data(pos)), p.concat());
        assert_eq!(f32s(glb.data(nrm))[..3], [0.0, 0.0, 1.0]);
        let colours = f32s(glb.data(col));
        assert_eq!(colours[..3], [0.5, 0.5, 0.5]);
        assert_eq!(colours[3..6], [0.25, 0.5, 1.0]);
        assert_eq!(colours[9..12], [1.0, 1.0, 1.0]); // 2.0 clamped
        assert_eq!(glb.indices(idx), [0, 1, 2, 0, 2, 3]);

        // Exposure +1 and the filmic curve: 0.5 · 2 = 1 → 0.8038 (still linear).
        let glb = Glb::parse(&to_glb(&mesh(&q), 1.0, ToneMap::Filmic).unwrap());
        let col0 = f32s(glb.data(glb.accessors(0)[2]));
        assert!((col0[0] - 2.54 / 3.16).abs() < 1e-6, "{col0:?}");
    }

    #[test]
    fn glb_positions_are_metres_and_ply_stays_in_scene_units() {
        // A centimetre scene: 1 unit = 10 mm, so glTF positions are 0.01 × the scene's.
        let q = quad();
        let m = ExportMesh {
            unit_mm: 10.0,
            ..mesh(&q)
        };
        let glb = Glb::parse(&to_glb(&m, 0.0, ToneMap::Srgb).unwrap());
        let [pos, nrm, _, _] = glb.accessors(0);
        let want: Vec<f32> = q.0.concat().iter().map(|&x| x * 0.01).collect();
        let got = f32s(glb.data(pos));
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() <= 1e-7, "{got:?} vs {want:?}");
        }
        // min/max are the written values (the specification requires them exact).
        let a = &glb.root.accessors[pos];
        assert_eq!(a.max, Some(serde_json::json!([got[3], got[7], got[2]])));
        assert_eq!(a.min, Some(serde_json::json!([got[0], got[1], got[11]])));
        // Normals are directions: unchanged.
        assert_eq!(f32s(glb.data(nrm))[..3], [0.0, 0.0, 1.0]);
        let generator = glb.raw["asset"]["generator"].as_str().unwrap();
        assert!(generator.contains("1 scene unit = 10 mm"), "{generator}");

        // A millimetre scene: × 0.001; a metre scene: bit for bit.
        let m = ExportMesh {
            unit_mm: 1.0,
            ..mesh(&q)
        };
        let glb = Glb::parse(&to_glb(&m, 0.0, ToneMap::Srgb).unwrap());
        assert!((f32s(glb.data(glb.accessors(0)[0]))[7] - 0.002).abs() < 1e-9);

        // PLY keeps scene units and says so.
        let m = ExportMesh {
            unit_mm: 10.0,
            ..mesh(&q)
        };
        let ply = to_ply(&m, 0.0, ToneMap::Srgb).unwrap();
        let header = ply_header_in(4, 2, 0.0, ToneMap::Srgb, 10.0);
        assert!(ply.starts_with(header.as_bytes()));
        assert!(header.contains("comment translux: positions in scene units, 1 unit = 10 mm\n"));
        assert_eq!(f32s(&ply[header.len() + 27..header.len() + 39]), q.0[1]);

        let e = to_glb(
            &ExportMesh {
                unit_mm: 0.0,
                ..mesh(&q)
            },
            0.0,
            ToneMap::Srgb,
        )
        .unwrap_err();
        assert!(
            e.to_string().contains("unit_mm must be finite and > 0"),
            "{e}"
        );
    }

    #[test]
    fn glb_has_one_named_mesh_and_node_per_part() {
        // Two quads side by side (vertices 0–3 and 4–7) and a part without triangles.
        let (mut p, mut n, mut t, mut c) = quad();
        let q2 = quad();
        p.extend(q2.0.iter().map(|v| [v[0] + 2.0, v[1], v[2]]));
        n.extend(&q2.1);
        t.extend(q2.2.iter().map(|t| t.map(|i| i + 4)));
        c.extend(q2.3.iter().rev());
        let parts = [
            MeshPart {
                name: "short_box".into(),
                triangles: 0..2,
            },
            MeshPart {
                name: "lamp".into(),
                triangles: 2..2,
            },
            MeshPart {
                name: "tall_block".into(),
                triangles: 2..4,
            },
        ];
        let m = ExportMesh {
            parts: &parts,
            ..ExportMesh::new(&p, &n, &t, &c)
        };
        let glb = Glb::parse(&to_glb(&m, 0.0, ToneMap::Srgb).unwrap());
        // Every part is a node named after it, in order; the empty one has no mesh.
        let names: Vec<&str> = glb.raw["nodes"]
            .as_array()
            .unwrap()
            .iter()
            .map(|n| n["name"].as_str().unwrap())
            .collect();
        assert_eq!(names, ["short_box", "lamp", "tall_block"]);
        assert!(glb.raw["nodes"][1].get("mesh").is_none());
        assert_eq!(glb.raw["scenes"][0]["nodes"], serde_json::json!([0, 1, 2]));
        assert_eq!(glb.root.meshes.len(), 2);
        assert_eq!(glb.raw["meshes"][1]["name"], "tall_block");
        assert_eq!(glb.raw["nodes"][2]["mesh"], 1);
        // The buffer holds each vertex once, each triangle once.
        assert_eq!(glb.bin.len(), 8 * 36 + 4 * 12);
        // Each mesh has its own four vertices, indices rebased to them, its own colours.
        for (mesh_k, first) in [(0, 0), (1, 4)] {
            let [pos, _, col, idx] = glb.accessors(mesh_k);
            assert_eq!(glb.root.accessors[pos].count.0, 4);
            assert_eq!(f32s(glb.data(pos)), p[first..first + 4].concat());
            let want: Vec<f32> = c[first..first + 4]
                .iter()
                .flat_map(|&r| linear_colour(r, 1.0, ToneMap::Srgb))
                .collect();
            assert_eq!(f32s(glb.data(col)), want);
            assert_eq!(glb.indices(idx), [0, 1, 2, 0, 2, 3]);
        }
        // A vertex two parts share is written in each; unused vertices are left out.
        let parts = [
            MeshPart {
                name: "a".into(),
                triangles: 0..1,
            },
            MeshPart {
                name: "b".into(),
                triangles: 1..2,
            },
        ];
        let q = quad();
        let m = ExportMesh {
            parts: &parts,
            ..mesh(&q)
        };
        let glb = Glb::parse(&to_glb(&m, 0.0, ToneMap::Srgb).unwrap());
        let [pos_b, _, _, idx_b] = glb.accessors(1);
        assert_eq!(
            f32s(glb.data(pos_b)),
            [q.0[0], q.0[2], q.0[3]].concat(),
            "part b uses vertices 0, 2, 3"
        );
        assert_eq!(glb.indices(idx_b), [0, 1, 2]);
        // A part past the triangles is an error naming it.
        let parts = [MeshPart {
            name: "ghost".into(),
            triangles: 1..3,
        }];
        let e = to_glb(
            &ExportMesh {
                parts: &parts,
                ..mesh(&q)
            },
            0.0,
            ToneMap::Srgb,
        )
        .unwrap_err();
        assert!(e.to_string().contains("\"ghost\""), "{e}");
    }

    #[test]
    fn ply_header_is_exact_and_sizes_add_up() {
        let q = quad();
        let ply = to_ply(&mesh(&q), 0.0, ToneMap::Srgb).unwrap();
        let header = "ply\n\
                      format binary_little_endian 1.0\n\
                      comment translux: colours are sRGB-encoded B/pi, exposure 0 EV, tone srgb\n\
                      comment translux: positions in scene units, 1 unit = 1000 mm\n\
                      element vertex 4\n\
                      property float x\n\
                      property float y\n\
                      property float z\n\
                      property float nx\n\
                      property float ny\n\
                      property float nz\n\
                      property uchar red\n\
                      property uchar green\n\
                      property uchar blue\n\
                      element face 2\n\
                      property list uchar int vertex_indices\n\
                      end_header\n";
        assert!(ply.starts_with(header.as_bytes()));
        assert_eq!(header, ply_header(4, 2, 0.0, ToneMap::Srgb));
        assert_eq!(ply.len(), header.len() + 4 * 27 + 2 * 13);
        let body = &ply[header.len()..];
        // Vertex 0: position, normal as given, then sRGB 188 for radiance 0.5.
        assert_eq!(f32s(&body[..24]), [0.0, 0.0, 0.0, 0.0, 0.0, 2.0]);
        assert_eq!(&body[24..27], &[188, 188, 188]);
        // Vertex 1: 0.25 → 137, 0.5 → 188, 1.0 → 255.
        assert_eq!(&body[27 + 24..27 + 27], &[137, 188, 255]);
        // Vertex 3: 2.0 clamps to 255.
        assert_eq!(&body[3 * 27 + 24..4 * 27], &[255, 255, 255]);
        // Faces.
        let faces = &body[4 * 27..];
        let ids: Vec<i32> = faces
            .chunks_exact(13)
            .flat_map(|f| {
                assert_eq!(f[0], 3);
                f[1..]
                    .chunks_exact(4)
                    .map(|c| i32::from_le_bytes(c.try_into().unwrap()))
            })
            .collect();
        assert_eq!(ids, [0, 1, 2, 0, 2, 3]);
        // A different exposure changes the header line and the colours.
        let ply = to_ply(&mesh(&q), -1.0, ToneMap::Filmic).unwrap();
        let text = String::from_utf8_lossy(&ply[..200]);
        assert!(text.contains("exposure -1 EV, tone filmic"), "{text}");
    }

    #[test]
    fn colours_round_trip() {
        // glTF's linear value, encoded, is PLY's byte; PLY's byte, decoded, is within half a
        // step of glTF's linear value; and both match the renderer's pixel.
        for l in [0.0f32, 0.001, 0.02, 0.18, 0.5, 0.9, 1.0] {
            for tone in [ToneMap::Srgb, ToneMap::Filmic] {
                let lin = linear_colour([l; 3], 1.0, tone)[0];
                let byte = srgb8_colour([l; 3], 1.0, tone)[0];
                assert_eq!(byte, to_u8(srgb_oetf(lin)));
                assert_eq!(
                    [byte; 3],
                    crate::render::display_rgb8([l; 3], 1.0, tone),
                    "{l} {tone:?}"
                );
                let back = crate::render::srgb_oetf(lin) * 255.0;
                assert!(
                    (back - byte as f32).abs() <= 0.5 + 1e-3,
                    "{l}: {back} vs {byte}"
                );
            }
        }
        assert_eq!(srgb8_colour([0.5; 3], 1.0, ToneMap::Srgb), [188; 3]);
        assert_eq!(linear_colour([0.5; 3], 1.0, ToneMap::Srgb), [0.5; 3]);
    }

    #[test]
    fn bad_input_is_an_error() {
        let (p, n, t, c) = quad();
        let e = to_glb(&ExportMesh::new(&p, &n[..3], &t, &c), 0.0, ToneMap::Srgb).unwrap_err();
        assert!(e.to_string().contains("normals has 3 entries"), "{e}");
        let e = to_ply(
            &ExportMesh::new(&p, &n, &[[0, 1, 4]], &c),
            0.0,
            ToneMap::Srgb,
        )
        .unwrap_err();
        assert!(e.to_string().contains("triangles[0]"), "{e}");
        let e = to_ply(&ExportMesh::new(&p, &n, &t, &c), f32::NAN, ToneMap::Srgb).unwrap_err();
        assert!(e.to_string().starts_with("exposure"), "{e}");
        let mut bad = c.clone();
        bad[2][1] = f32::INFINITY;
        let e = to_glb(&ExportMesh::new(&p, &n, &t, &bad), 0.0, ToneMap::Srgb).unwrap_err();
        assert!(e.to_string().contains("vertex_radiance[2]"), "{e}");
        let empty = ExportMesh::new(&[], &[], &[], &[]);
        assert!(to_glb(&empty, 0.0, ToneMap::Srgb).is_err());
        // An empty PLY is fine.
        let ply = to_ply(&empty, 0.0, ToneMap::Srgb).unwrap();
        assert_eq!(ply.len(), ply_header(0, 0, 0.0, ToneMap::Srgb).len());
    }
}
