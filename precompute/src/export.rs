//! Mesh export with baked vertex colours: binary glTF 2.0 (`.glb`) and binary PLY.
//!
//! In: vertex positions and normals, triangles (indices, counter-clockwise seen from the
//! front), linear radiance B/π per vertex (a relight's answer), an exposure in EV stops and a
//! [`ToneMap`]. Out: the bytes of a file.
//!
//! Colours: c = tone(L · 2^EV) per channel, with the tone curve of [`crate::render`] (clamp
//! to [0, 1], or the ACES filmic fit). Then:
//!
//! - **glTF** stores `COLOR_0` as float RGB **in linear space**: the glTF 2.0 specification
//!   defines vertex colours as linear and multiplies them into the base colour, and viewers
//!   apply the display encoding (the sRGB OETF) to their output themselves. So the export
//!   applies the exposure and the tone curve but **not** the sRGB OETF; applying it here
//!   would brighten every mid-tone twice. The material is white, non-metallic, fully rough
//!   and carries `KHR_materials_unlit`, so viewers that know the extension show the baked
//!   colours as they are (no lighting on top); others fall back to a lit white PBR
//!   material tinted by the colours. `doubleSided` is false, like the renderer's default
//!   back-face culling: a closed room is seen from outside through its near wall.
//! - **PLY** stores red, green, blue as `uchar` **sRGB-encoded** (the MeshLab / CloudCompare
//!   convention: 8-bit colours are display values): round(255 · OETF(c)), exactly the pixel
//!   values [`crate::render::render`] would show for the same vertex.
//!
//! The `.glb` layout (glTF 2.0 §4.4): a 12-byte header (`glTF`, version 2, total length),
//! a JSON chunk padded with spaces to a multiple of 4 bytes, and a BIN chunk padded with
//! zeros, holding in order positions, normals and colours (V × 12 bytes each, `f32` × 3) and
//! the indices (F × 12 bytes, `u32` × 3). `POSITION` has the `min`/`max` the specification
//! requires. Normals are written unit length (glTF requires it); a zero normal is written as +Z.
//!
//! The PLY layout: an ASCII header ([`ply_header`]), then per vertex x y z nx ny nz (`float`)
//! and red green blue (`uchar`), 27 bytes, then per face a `uchar` count 3 and three `int`
//! indices, 13 bytes, little-endian.

use translux_proto::api::ToneMap;

use crate::render::{exposure_scale, srgb_oetf, to_u8, tone_map};

/// Why an export failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ExportError {
    /// The arrays disagree, an index is out of range, or a value is not finite.
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

/// Checks the arrays and exposure; returns 2^exposure.
fn check(
    positions: &[[f32; 3]],
    normals: &[[f32; 3]],
    triangles: &[[u32; 3]],
    vertex_radiance: &[[f32; 3]],
    exposure: f32,
) -> Result<f32, ExportError> {
    let limit = crate::render::MAX_EXPOSURE;
    if !(exposure.is_finite() && (-limit..=limit).contains(&exposure)) {
        return Err(ExportError::Exposure(exposure.to_string()));
    }
    let n = positions.len();
    for (name, len) in [
        ("normals", normals.len()),
        ("vertex_radiance", vertex_radiance.len()),
    ] {
        if len != n {
            return Err(ExportError::Mesh(format!(
                "{name} has {len} entries for {n} vertices"
            )));
        }
    }
    for (name, arr) in [
        ("positions", positions),
        ("normals", normals),
        ("vertex_radiance", vertex_radiance),
    ] {
        if let Some(k) = arr.iter().position(|v| !v.iter().all(|x| x.is_finite())) {
            return Err(ExportError::Mesh(format!(
                "{name}[{k}] = {:?} is not finite",
                arr[k]
            )));
        }
    }
    if let Some((k, t)) = triangles
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

/// A binary glTF 2.0 file of the mesh with baked linear vertex colours; see the module
/// documentation for what goes where.
pub fn to_glb(
    positions: &[[f32; 3]],
    normals: &[[f32; 3]],
    triangles: &[[u32; 3]],
    vertex_radiance: &[[f32; 3]],
    exposure: f32,
    tone: ToneMap,
) -> Result<Vec<u8>, ExportError> {
    use gltf_json as json;
    use json::validation::{Checked::Valid, USize64};

    let scale = check(positions, normals, triangles, vertex_radiance, exposure)?;
    if positions.is_empty() || triangles.is_empty() {
        // glTF accessors need count ≥ 1.
        return Err(ExportError::Mesh(
            "the mesh is empty (glTF needs at least one vertex and one triangle)".into(),
        ));
    }
    let nv = positions.len();
    let nf = triangles.len();
    let attr_bytes = nv as u64 * 12;
    let index_bytes = nf as u64 * 12;
    let bin_len = 3 * attr_bytes + index_bytes; // a multiple of 4 already
    if bin_len > u32::MAX as u64 / 2 {
        return Err(ExportError::TooLarge(format!(
            "{nv} vertices and {nf} triangles need {bin_len} bytes of buffer; a .glb holds \
             under 4 GiB"
        )));
    }

    // BIN: positions | normals | colours | indices.
    let mut bin = Vec::with_capacity(bin_len as usize);
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for p in positions {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
            bin.extend_from_slice(&p[k].to_le_bytes());
        }
    }
    for n in normals {
        for x in unit(*n) {
            bin.extend_from_slice(&x.to_le_bytes());
        }
    }
    for c in vertex_radiance {
        for x in linear_colour(*c, scale, tone) {
            bin.extend_from_slice(&x.to_le_bytes());
        }
    }
    for t in triangles {
        for i in t {
            bin.extend_from_slice(&i.to_le_bytes());
        }
    }
    debug_assert_eq!(bin.len() as u64, bin_len);

    let mut root = json::Root {
        asset: json::Asset {
            copyright: None,
            extensions: None,
            extras: Default::default(),
            generator: Some(format!(
                "translux {} (COLOR_0: linear B/pi, exposure {exposure} EV, tone {})",
                env!("CARGO_PKG_VERSION"),
                tone.as_str()
            )),
            min_version: None,
            version: "2.0".into(),
        },
        extensions_used: vec!["KHR_materials_unlit".into()],
        ..Default::default()
    };
    let buffer = root.push(json::Buffer {
        byte_length: USize64(bin_len),
        extensions: None,
        extras: Default::default(),
        uri: None,
    });
    let view = |root: &mut json::Root, offset: u64, len: u64, target| {
        root.push(json::buffer::View {
            buffer,
            byte_length: USize64(len),
            byte_offset: Some(USize64(offset)),
            byte_stride: None,
            extensions: None,
            extras: Default::default(),
            target: Some(Valid(target)),
        })
    };
    let accessor = |root: &mut json::Root,
                    view: json::Index<json::buffer::View>,
                    count: usize,
                    component: json::accessor::ComponentType,
                    type_: json::accessor::Type,
                    min_max: Option<([f32; 3], [f32; 3])>| {
        root.push(json::Accessor {
            buffer_view: Some(view),
            byte_offset: None,
            count: USize64(count as u64),
            component_type: Valid(json::accessor::GenericComponentType(component)),
            extensions: None,
            extras: Default::default(),
            type_: Valid(type_),
            min: min_max.map(|(lo, _)| serde_json::json!(lo)),
            max: min_max.map(|(_, hi)| serde_json::json!(hi)),
            normalized: false,
            sparse: None,
        })
    };
    use json::accessor::{ComponentType::F32, ComponentType::U32, Type};
    use json::buffer::Target::{ArrayBuffer, ElementArrayBuffer};
    let v_pos = view(&mut root, 0, attr_bytes, ArrayBuffer);
    let v_nrm = view(&mut root, attr_bytes, attr_bytes, ArrayBuffer);
    let v_col = view(&mut root, 2 * attr_bytes, attr_bytes, ArrayBuffer);
    let v_idx = view(&mut root, 3 * attr_bytes, index_bytes, ElementArrayBuffer);
    let a_pos = accessor(&mut root, v_pos, nv, F32, Type::Vec3, Some((lo, hi)));
    let a_nrm = accessor(&mut root, v_nrm, nv, F32, Type::Vec3, None);
    let a_col = accessor(&mut root, v_col, nv, F32, Type::Vec3, None);
    let a_idx = accessor(&mut root, v_idx, 3 * nf, U32, Type::Scalar, None);

    let material = root.push(json::Material {
        pbr_metallic_roughness: json::material::PbrMetallicRoughness {
            base_color_factor: json::material::PbrBaseColorFactor([1.0; 4]),
            metallic_factor: json::material::StrengthFactor(0.0),
            roughness_factor: json::material::StrengthFactor(1.0),
            ..Default::default()
        },
        double_sided: false,
        extensions: Some(unlit()),
        ..Default::default()
    });
    let mut attributes = std::collections::BTreeMap::new();
    attributes.insert(Valid(json::mesh::Semantic::Positions), a_pos);
    attributes.insert(Valid(json::mesh::Semantic::Normals), a_nrm);
    attributes.insert(Valid(json::mesh::Semantic::Colors(0)), a_col);
    let mesh = root.push(json::Mesh {
        extensions: None,
        extras: Default::default(),
        primitives: vec![json::mesh::Primitive {
            attributes,
            extensions: None,
            extras: Default::default(),
            indices: Some(a_idx),
            material: Some(material),
            mode: Valid(json::mesh::Mode::Triangles),
            targets: None,
        }],
        weights: None,
    });
    let node = root.push(json::Node {
        mesh: Some(mesh),
        ..Default::default()
    });
    let scene = root.push(json::Scene {
        extensions: None,
        extras: Default::default(),
        nodes: vec![node],
    });
    root.scene = Some(scene);

    let mut text = root
        .to_vec()
        .map_err(|e| ExportError::Json(e.to_string()))?;
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

/// The material extensions with `KHR_materials_unlit` set (through `Default`, so that other
/// extensions' fields, present when a crate enables their features, stay absent; a struct
/// literal would stop compiling when feature unification adds a field).
#[allow(clippy::field_reassign_with_default)]
fn unlit() -> gltf_json::extensions::material::Material {
    let mut ext = gltf_json::extensions::material::Material::default();
    ext.unlit = Some(gltf_json::extensions::material::Unlit {});
    ext
}

/// The PLY header for `vertices` vertices and `faces` faces (ASCII, `\n` line ends).
pub fn ply_header(vertices: usize, faces: usize, exposure: f32, tone: ToneMap) -> String {
    format!(
        "ply\n\
         format binary_little_endian 1.0\n\
         comment translux: colours are sRGB-encoded B/pi, exposure {exposure} EV, tone {}\n\
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

/// A binary little-endian PLY of the mesh with 8-bit sRGB vertex colours; see the module
/// documentation. Normals are written as given.
pub fn to_ply(
    positions: &[[f32; 3]],
    normals: &[[f32; 3]],
    triangles: &[[u32; 3]],
    vertex_radiance: &[[f32; 3]],
    exposure: f32,
    tone: ToneMap,
) -> Result<Vec<u8>, ExportError> {
    let scale = check(positions, normals, triangles, vertex_radiance, exposure)?;
    // Face indices are PLY `int` (i32).
    if positions.len() > i32::MAX as usize {
        return Err(ExportError::TooLarge(format!(
            "{} vertices; PLY int indices reach {}",
            positions.len(),
            i32::MAX
        )));
    }
    let header = ply_header(positions.len(), triangles.len(), exposure, tone);
    let mut out = Vec::with_capacity(header.len() + 27 * positions.len() + 13 * triangles.len());
    out.extend_from_slice(header.as_bytes());
    for ((p, n), c) in positions.iter().zip(normals).zip(vertex_radiance) {
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

    fn u32_at(b: &[u8], at: usize) -> u32 {
        u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
    }

    fn f32s(b: &[u8]) -> Vec<f32> {
        b.chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect()
    }

    #[test]
    fn glb_is_valid_gltf_with_linear_colours() {
        let (p, n, t, c) = quad();
        let glb = to_glb(&p, &n, &t, &c, 0.0, ToneMap::Srgb).unwrap();
        // Header.
        assert_eq!(&glb[..4], b"glTF");
        assert_eq!(u32_at(&glb, 4), 2);
        assert_eq!(u32_at(&glb, 8) as usize, glb.len());
        // JSON chunk: aligned, space-padded, parses with gltf-json and validates.
        let json_len = u32_at(&glb, 12) as usize;
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
        // BIN chunk: right after, aligned, the buffer's length.
        let bin_at = 20 + json_len;
        assert_eq!(bin_at % 4, 0);
        let bin_len = u32_at(&glb, bin_at) as usize;
        assert_eq!(&glb[bin_at + 4..bin_at + 8], b"BIN\0");
        assert_eq!(bin_len % 4, 0);
        assert_eq!(bin_at + 8 + bin_len, glb.len());
        assert_eq!(root.buffers.len(), 1);
        assert_eq!(root.buffers[0].byte_length.0 as usize, bin_len);
        assert_eq!(bin_len, 4 * 36 + 2 * 12);
        let bin = &glb[bin_at + 8..];

        // Accessors: counts, types, POSITION min/max.
        assert_eq!(root.accessors.len(), 4);
        assert_eq!(root.meshes.len(), 1);
        assert_eq!(root.nodes.len(), 1);
        assert_eq!(
            root.extensions_used,
            vec!["KHR_materials_unlit".to_string()]
        );
        let prim = &root.meshes[0].primitives[0];
        let get = |s: json::mesh::Semantic| {
            let k = prim.attributes[&json::validation::Checked::Valid(s)].value();
            &root.accessors[k]
        };
        let pos = get(json::mesh::Semantic::Positions);
        assert_eq!(pos.count.0, 4);
        assert_eq!(pos.min, Some(serde_json::json!([0.0, 0.0, -0.5])));
        assert_eq!(pos.max, Some(serde_json::json!([1.0, 2.0, 0.0])));
        assert_eq!(get(json::mesh::Semantic::Normals).count.0, 4);
        let col = get(json::mesh::Semantic::Colors(0));
        assert_eq!(col.count.0, 4);
        let idx = &root.accessors[prim.indices.unwrap().value()];
        assert_eq!(idx.count.0, 6);
        let m = &root.materials[prim.material.unwrap().value()];
        assert!(m.extensions.as_ref().unwrap().unlit.is_some());

        // Data: normals unit length, colours linear (no OETF), indices as given.
        let view = |a: &json::Accessor| {
            let v = &root.buffer_views[a.buffer_view.unwrap().value()];
            let at = v.byte_offset.unwrap().0 as usize;
            &bin[at..at + v.byte_length.0 as usize]
        };
        assert_eq!(f32s(view(pos)), p.concat());
        assert_eq!(
            f32s(view(get(json::mesh::Semantic::Normals)))[..3],
            [0.0, 0.0, 1.0]
        );
        let colours = f32s(view(col));
        assert_eq!(colours[..3], [0.5, 0.5, 0.5]);
        assert_eq!(colours[3..6], [0.25, 0.5, 1.0]);
        assert_eq!(colours[9..12], [1.0, 1.0, 1.0]); // 2.0 clamped
        let idx_bytes = view(idx);
        let ids: Vec<u32> = idx_bytes
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        assert_eq!(ids, [0, 1, 2, 0, 2, 3]);

        // Exposure +1 and the filmic curve: 0.5 · 2 = 1 → 0.8038 (still linear).
        let glb = to_glb(&p, &n, &t, &c, 1.0, ToneMap::Filmic).unwrap();
        let bin = &glb[glb.len() - bin_len..];
        let col0 = f32s(&bin[96..108]);
        assert!((col0[0] - 2.54 / 3.16).abs() < 1e-6, "{col0:?}");
    }

    #[test]
    fn ply_header_is_exact_and_sizes_add_up() {
        let (p, n, t, c) = quad();
        let ply = to_ply(&p, &n, &t, &c, 0.0, ToneMap::Srgb).unwrap();
        let header = "ply\n\
                      format binary_little_endian 1.0\n\
                      comment translux: colours are sRGB-encoded B/pi, exposure 0 EV, tone srgb\n\
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
        let ply = to_ply(&p, &n, &t, &c, -1.0, ToneMap::Filmic).unwrap();
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
        let e = to_glb(&p, &n[..3], &t, &c, 0.0, ToneMap::Srgb).unwrap_err();
        assert!(e.to_string().contains("normals has 3 entries"), "{e}");
        let e = to_ply(&p, &n, &[[0, 1, 4]], &c, 0.0, ToneMap::Srgb).unwrap_err();
        assert!(e.to_string().contains("triangles[0]"), "{e}");
        let e = to_ply(&p, &n, &t, &c, f32::NAN, ToneMap::Srgb).unwrap_err();
        assert!(e.to_string().starts_with("exposure"), "{e}");
        let mut bad = c.clone();
        bad[2][1] = f32::INFINITY;
        let e = to_glb(&p, &n, &t, &bad, 0.0, ToneMap::Srgb).unwrap_err();
        assert!(e.to_string().contains("vertex_radiance[2]"), "{e}");
        assert!(to_glb(&[], &[], &[], &[], 0.0, ToneMap::Srgb).is_err());
        // An empty PLY is fine.
        let ply = to_ply(&[], &[], &[], &[], 0.0, ToneMap::Srgb).unwrap();
        assert_eq!(ply.len(), ply_header(0, 0, 0.0, ToneMap::Srgb).len());
    }
}
