//! The OBJ reader: a file's triangles (every model as one list, polygons fan-triangulated, in
//! the file's own coordinates) and, when asked, each triangle's `usemtl` group, for media by
//! OBJ material. Parsing is tobj's; this module names the line of a malformed file and
//! refuses what tobj lets through (non-finite coordinates, unknown statements).
//!
//! Failures are [`MeshError`]s; [`crate::scene`] adds the scene, the object and the file.

use std::io::{BufReader, Read};
use std::path::Path;

use glam::Vec3;

use crate::meshio::MeshError;

/// An OBJ file's triangles and, when asked for, the `usemtl` group of each.
pub type ObjTriangles = (Vec<[Vec3; 3]>, Option<Vec<Option<String>>>);

/// Reads every model of an OBJ file as one triangle list (object space), and with `groups`
/// the `usemtl` material name of every triangle (`None` before the first `usemtl`).
///
/// tobj parses; its error says what kind of problem it met but not where, so on failure the
/// file is scanned again by `diagnose_obj` to name the line. tobj also accepts `nan` and
/// `inf` as coordinates and silently ignores unknown statements, so the result is checked
/// here too. Material libraries are not read: they carry nothing translux uses, and tobj
/// 4.0 panics on some malformed `.mtl` lines. tobj only resolves `usemtl` names it found in
/// a library, so for `groups` the file is fed to it behind one synthetic line,
/// `mtllib <GROUPS_LIBRARY>`, whose "library" (answered here, never read from disk) defines
/// one empty material per `usemtl` name the file uses.
pub fn load_obj_triangles(path: &Path, groups: bool) -> Result<ObjTriangles, MeshError> {
    /// The file name of the synthetic material library (a control character keeps it from
    /// ever naming a real file).
    const GROUPS_LIBRARY: &str = "\u{1}translux-usemtl-groups";
    let file = crate::meshio::open(path)?;
    let options = tobj::LoadOptions {
        triangulate: true,
        ignore_points: true,
        ignore_lines: true,
        ..Default::default()
    };
    // The `usemtl` names in order of first use, parsed as tobj does (the rest of the line
    // after the first space, trimmed).
    let mut names: Vec<String> = Vec::new();
    if groups && let Ok(text) = std::fs::read_to_string(path) {
        for line in text.lines() {
            if line.split_whitespace().next() == Some("usemtl") {
                let name = line.split_once(' ').unwrap_or_default().1.trim();
                if !name.is_empty() && !names.iter().any(|n| n == name) {
                    names.push(name.to_owned());
                }
            }
        }
    }
    let header = if groups {
        format!("mtllib {GROUPS_LIBRARY}\n")
    } else {
        String::new()
    };
    let mut reader = BufReader::new(std::io::Cursor::new(header).chain(file));
    let (models, _materials) = tobj::load_obj_buf(&mut reader, &options, |p| {
        if groups && p == Path::new(GROUPS_LIBRARY) {
            let materials = names
                .iter()
                .map(|n| tobj::Material {
                    name: n.clone(),
                    ..Default::default()
                })
                .collect();
            let map = names
                .iter()
                .enumerate()
                .map(|(k, n)| (n.clone(), k))
                .collect();
            Ok((materials, map))
        } else {
            Err(tobj::LoadError::GenericFailure)
        }
    })
    .map_err(|e| MeshError::Malformed(explain_tobj_error(path, &e)))?;
    let mut tris = Vec::new();
    let mut face_groups = Vec::new();
    for model in &models {
        let pos = &model.mesh.positions;
        let vertex = |i: u32| -> Option<Vec3> {
            let k = 3 * i as usize;
            Some(Vec3::new(*pos.get(k)?, *pos.get(k + 1)?, *pos.get(k + 2)?))
        };
        let group = model.mesh.material_id.and_then(|k| names.get(k).cloned());
        for idx in model.mesh.indices.chunks(3) {
            let [a, b, c] = idx else {
                return Err(MeshError::Malformed(
                    "a face has fewer than 3 vertices".to_owned(),
                ));
            };
            let (Some(a), Some(b), Some(c)) = (vertex(*a), vertex(*b), vertex(*c)) else {
                return Err(MeshError::Malformed(with_location(
                    path,
                    "a face index is out of range".to_owned(),
                )));
            };
            if !(a.is_finite() && b.is_finite() && c.is_finite()) {
                return Err(MeshError::Malformed(with_location(
                    path,
                    "a vertex coordinate is not a finite number".to_owned(),
                )));
            }
            tris.push([a, b, c]);
            if groups {
                face_groups.push(group.clone());
            }
        }
    }
    Ok((tris, groups.then_some(face_groups)))
}

fn explain_tobj_error(path: &Path, e: &tobj::LoadError) -> String {
    with_location(path, e.to_string())
}

/// `what`, followed by the first problem [`diagnose_obj`] finds in the file, if any.
fn with_location(path: &Path, what: String) -> String {
    match std::fs::read(path)
        .ok()
        .and_then(|bytes| diagnose_obj(&bytes))
    {
        Some(found) => found,
        None => what,
    }
}

/// Scans OBJ text for the first line that cannot be right: a vertex whose first three
/// coordinates are not finite numbers, or a face with an index that is not a number, is 0,
/// or points past the vertices of the file (negative indices count back from the vertices
/// read so far). Returns `line N: problem: \`text\``.
fn diagnose_obj(bytes: &[u8]) -> Option<String> {
    let text = match std::str::from_utf8(bytes) {
        Ok(t) => t,
        Err(e) => {
            let line = 1 + bytes[..e.valid_up_to()]
                .iter()
                .filter(|&&b| b == b'\n')
                .count();
            return Some(format!(
                "line {line}: not UTF-8 text (is it a binary file?)"
            ));
        }
    };
    let total = text
        .lines()
        .filter(|l| l.split_whitespace().next() == Some("v"))
        .count();
    let mut seen = 0usize;
    for (n, line) in text.lines().enumerate() {
        let mut words = line.split_whitespace();
        let shown: String = line.trim().chars().take(80).collect();
        let at = |problem: String| Some(format!("line {}: {problem}: `{shown}`", n + 1));
        match words.next() {
            Some("v") => {
                seen += 1;
                let coords: Vec<&str> = words.by_ref().take(3).collect();
                if coords.len() < 3 {
                    return at("a vertex needs three coordinates".to_owned());
                }
                for c in coords {
                    match c.parse::<f32>() {
                        Ok(x) if x.is_finite() => {}
                        Ok(_) => return at(format!("coordinate \"{c}\" is not finite")),
                        Err(_) => return at(format!("coordinate \"{c}\" is not a number")),
                    }
                }
                if let Some(w) = words.next() {
                    match (w.parse::<f32>(), words.next()) {
                        (Ok(w), None) if w == 0.0 || !w.is_finite() => {
                            return at(format!("weight w = {w} is unusable"));
                        }
                        (Err(_), None) => return at(format!("weight \"{w}\" is not a number")),
                        _ => {}
                    }
                }
            }
            Some("f") => {
                for word in words {
                    let v = word.split('/').next().unwrap_or("");
                    let Ok(i) = v.parse::<i64>() else {
                        return at(format!("vertex index \"{v}\" is not an integer"));
                    };
                    if i == 0 {
                        return at("vertex index 0 (OBJ indices start at 1)".to_owned());
                    }
                    if i > total as i64 {
                        return at(format!(
                            "face index {i} is out of range (the file has {total} vertices)"
                        ));
                    }
                    if i < 0 && -i > seen as i64 {
                        return at(format!(
                            "relative face index {i} points before the first vertex \
                             ({seen} vertices so far)"
                        ));
                    }
                }
            }
            _ => {}
        }
    }
    None
}
