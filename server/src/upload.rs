//! `POST /api/v1/scenes`: a scene uploaded as `multipart/form-data` becomes a precompute job.
//!
//! In: the form's parts —
//! - `scene`: the scene file (JSON, as for `translux-precompute`; file name ending `.json`),
//! - `mesh`: its meshes — `.obj`, `.ply`, `.gltf` (with the `.bin` buffer files it names)
//!   or `.glb` — and MTL files (kept but not read: media by OBJ material come from the OBJ's
//!   `usemtl` names), any number,
//! - `id` (text, optional): the scene id to serve it under (default: the scene file's stem),
//! - `patches` or `max_edge` (text, optional): the patch density, overriding the file's.
//!
//! Out: `202 Accepted` with the job's record ([`crate::jobs::JobRecord`]) and
//! `Location: /api/v1/jobs/{id}`; or a 4xx naming the problem, with nothing left on disk.
//!
//! Checks, in order: every file name is a plain name (letters, digits, `.`, `_`, `-`; no
//! path separator, no `..`, no leading dot, at most 128 characters) with an allowed
//! extension, and appears once; every file is within the per-file limit and all of them
//! within the total (413, counted while streaming to disk, so an oversized upload is cut off
//! early); the scene file parses and validates; each of its `mesh` paths is the plain name of
//! an uploaded file (so no path can reach outside the upload folder); the triangles, counted
//! from shape parameters and mesh files without building geometry, are within the patch
//! limit (every triangle is at least one patch) and within [`SOURCE_TRIANGLES_PER_PATCH`]
//! times it before `simplify_to`; the meshes load; the patch count is within the server's
//! limit; the id is free (409 otherwise).

use std::io::Write;
use std::path::{Path, PathBuf};

use axum::extract::Multipart;
use axum::extract::multipart::{Field, MultipartError};
use axum::http::header::LOCATION;
use axum::http::{HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use translux_precompute::meshio::referenced_files;
use translux_precompute::patch::{Density, plan};
use translux_precompute::pipeline::{MAX_PATCHES, density_for};
use translux_precompute::scene::load_scene_file;
use translux_precompute::scene::triangle_count;
use translux_precompute::shapes::shape_triangle_count;
use translux_proto::scene::{MeshRef, SceneFile};

use crate::auth::Identity;
use crate::error::AppError;
use crate::jobs::{JobSpec, Jobs, strip_dir};

/// Upload limits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UploadLimits {
    /// Largest single file, bytes.
    pub file_bytes: u64,
    /// All files together, bytes.
    pub total_bytes: u64,
    /// Most files in one upload.
    pub files: usize,
    /// Most patches an uploaded scene may ask for.
    pub patches: u64,
}

impl Default for UploadLimits {
    fn default() -> Self {
        UploadLimits {
            file_bytes: 64 << 20,
            total_bytes: 256 << 20,
            files: 64,
            patches: 50_000,
        }
    }
}

/// Longest file name kept.
pub const MAX_NAME: usize = 128;

/// Checks an uploaded file name: a plain name, nothing that a path could be made of.
pub fn check_file_name(name: &str) -> Result<(), String> {
    let shown = name.escape_debug();
    if name.is_empty() {
        return Err("a file has an empty name".into());
    }
    if name.len() > MAX_NAME {
        return Err(format!(
            "file name \"{shown}\" is longer than {MAX_NAME} bytes"
        ));
    }
    if name.contains(['/', '\\']) || name == ".." || name.contains("..") {
        return Err(format!(
            "file name \"{shown}\" is a path; send plain file names (no '/', '\\' or '..'): \
             every file of an upload lands in one folder"
        ));
    }
    if name.starts_with('.') {
        return Err(format!(
            "file name \"{shown}\" starts with '.'; hidden files are refused"
        ));
    }
    if !name
        .bytes()
        .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'))
    {
        return Err(format!(
            "file name \"{shown}\" has characters other than letters, digits, '.', '_' and '-'"
        ));
    }
    Ok(())
}

/// Checks a scene id: 1 to 64 letters, digits, `_` or `-`, starting with a letter or digit.
pub fn check_scene_id(id: &str) -> Result<(), String> {
    let ok = !id.is_empty()
        && id.len() <= 64
        && id.as_bytes()[0].is_ascii_alphanumeric()
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'_' | b'-'));
    if ok {
        Ok(())
    } else {
        Err(format!(
            "scene id \"{}\" must be 1 to 64 letters, digits, '_' or '-', starting with a \
             letter or digit",
            id.escape_debug()
        ))
    }
}

/// The extensions a `mesh` part may have: the mesh formats `translux-precompute` reads,
/// MTL files beside OBJs, and the `.bin` buffers a `.gltf` file names.
const MESH_EXTENSIONS: &[&str] = &["obj", "ply", "gltf", "glb", "mtl", "bin"];

fn extension(name: &str) -> String {
    name.rsplit_once('.')
        .map(|(_, e)| e.to_ascii_lowercase())
        .unwrap_or_default()
}

/// What the form held once on disk.
#[derive(Debug, Default)]
struct Received {
    scene: Option<String>,
    meshes: Vec<String>,
    id: Option<String>,
    patches: Option<u64>,
    max_edge: Option<f32>,
    total: u64,
}

fn multipart_error(e: MultipartError, limits: &UploadLimits) -> AppError {
    if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
        AppError::payload_too_large(format!(
            "the upload is larger than the limit of {} bytes in all",
            limits.total_bytes
        ))
    } else {
        AppError::bad_request(format!("cannot read the multipart form: {}", e.body_text()))
    }
}

/// Streams one file part to `dir/name`, counting against the limits.
async fn save_file(
    field: &mut Field<'_>,
    dir: &Path,
    name: &str,
    got: &mut Received,
    limits: &UploadLimits,
) -> Result<(), AppError> {
    let path = dir.join(name);
    let mut file = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&path)
        .map_err(|e| AppError::internal(format!("cannot store {name}: {e}")))?;
    let mut size = 0u64;
    while let Some(chunk) = field
        .chunk()
        .await
        .map_err(|e| multipart_error(e, limits))?
    {
        size += chunk.len() as u64;
        got.total += chunk.len() as u64;
        if size > limits.file_bytes {
            return Err(AppError::payload_too_large(format!(
                "file {name} is larger than the limit of {} bytes per file",
                limits.file_bytes
            )));
        }
        if got.total > limits.total_bytes {
            return Err(AppError::payload_too_large(format!(
                "the upload is larger than the limit of {} bytes in all (at file {name})",
                limits.total_bytes
            )));
        }
        // Chunks are small (tens of KiB): writing them inline costs less than a hop to a
        // blocking thread per chunk.
        file.write_all(&chunk)
            .map_err(|e| AppError::internal(format!("cannot store {name}: {e}")))?;
    }
    Ok(())
}

async fn text_value(field: Field<'_>, limits: &UploadLimits) -> Result<String, AppError> {
    let name = field.name().unwrap_or("").to_string();
    let text = field.text().await.map_err(|e| multipart_error(e, limits))?;
    if text.len() > 256 {
        return Err(AppError::invalid(format!("form field {name} is too long")));
    }
    Ok(text.trim().to_string())
}

async fn receive(
    mut form: Multipart,
    dir: &Path,
    limits: &UploadLimits,
) -> Result<Received, AppError> {
    let mut got = Received::default();
    let mut names: Vec<String> = Vec::new();
    while let Some(mut field) = form
        .next_field()
        .await
        .map_err(|e| multipart_error(e, limits))?
    {
        let part = field.name().unwrap_or("").to_string();
        match part.as_str() {
            "scene" | "mesh" => {
                let Some(name) = field.file_name().map(str::to_string) else {
                    return Err(AppError::invalid(format!(
                        "form field {part} must be a file (with a file name)"
                    )));
                };
                check_file_name(&name).map_err(AppError::invalid)?;
                let ext = extension(&name);
                let allowed: &[&str] = if part == "scene" {
                    &["json"]
                } else {
                    MESH_EXTENSIONS
                };
                if !allowed.contains(&ext.as_str()) {
                    return Err(AppError::invalid(format!(
                        "{part} file {name} must end in {}",
                        allowed
                            .iter()
                            .map(|e| format!(".{e}"))
                            .collect::<Vec<_>>()
                            .join(" or ")
                    )));
                }
                if names.iter().any(|n| n.eq_ignore_ascii_case(&name)) {
                    return Err(AppError::invalid(format!("file {name} is uploaded twice")));
                }
                if names.len() >= limits.files {
                    return Err(AppError::payload_too_large(format!(
                        "more than {} files in one upload",
                        limits.files
                    )));
                }
                if part == "scene" && got.scene.is_some() {
                    return Err(AppError::invalid("more than one scene file"));
                }
                names.push(name.clone());
                save_file(&mut field, dir, &name, &mut got, limits).await?;
                if part == "scene" {
                    got.scene = Some(name);
                } else {
                    got.meshes.push(name);
                }
            }
            "id" => got.id = Some(text_value(field, limits).await?),
            "patches" => {
                let v = text_value(field, limits).await?;
                got.patches = Some(v.parse().map_err(|_| {
                    AppError::invalid(format!("patches must be a whole number, got {v:?}"))
                })?);
            }
            "max_edge" => {
                let v = text_value(field, limits).await?;
                let e: f32 = v.parse().map_err(|_| {
                    AppError::invalid(format!("max_edge must be a number, got {v:?}"))
                })?;
                if !(e.is_finite() && e > 0.0) {
                    return Err(AppError::invalid(format!(
                        "max_edge must be finite and > 0, got {v}"
                    )));
                }
                got.max_edge = Some(e);
            }
            other => {
                return Err(AppError::invalid(format!(
                    "unknown form field {:?}; the fields are scene, mesh, id, patches, max_edge",
                    other
                )));
            }
        }
    }
    Ok(got)
}

/// The checks that need the scene file: mesh paths, meshes, patch count. Blocking.
fn check_scene(
    dir: &Path,
    scene_name: &str,
    meshes: &[String],
    got_patches: Option<u64>,
    max_edge: Option<f32>,
    limits: &UploadLimits,
) -> Result<(), AppError> {
    let path = dir.join(scene_name);
    let text = std::fs::read_to_string(&path)
        .map_err(|e| AppError::invalid(format!("{scene_name}: cannot read it as text: {e}")))?;
    let file: SceneFile = translux_proto::parse_json(&text)
        .map_err(|e| AppError::invalid(format!("{scene_name}: {e}")))?;
    for (k, o) in file.objects.iter().enumerate() {
        if let MeshRef::Path(p) = &o.mesh {
            if check_file_name(p).is_err() {
                return Err(AppError::invalid(format!(
                    "{scene_name}: objects[{k}].mesh \"{}\" must be the plain name of an \
                     uploaded file (no folders, no '..', no absolute path)",
                    p.escape_debug()
                )));
            }
            if !meshes.iter().any(|m| m == p) {
                return Err(AppError::invalid(format!(
                    "{scene_name}: objects[{k}].mesh {p:?} was not uploaded; the meshes \
                     uploaded are: {}",
                    if meshes.is_empty() {
                        "none".to_string()
                    } else {
                        meshes.join(", ")
                    }
                )));
            }
        }
    }
    // A glTF file's buffers are read relative to it, wherever they point: each must be
    // the plain name of an uploaded file, like the scene's meshes.
    for m in meshes {
        let refs = referenced_files(&dir.join(m))
            .map_err(|e| AppError::invalid(strip_dir(&format!("{m}: {e}"), dir)))?;
        for r in refs {
            if check_file_name(&r).is_err() {
                return Err(AppError::invalid(format!(
                    "{m}: buffer file \"{}\" must be the plain name of an uploaded file (no \
                     folders, no '..', no absolute path, no URL)",
                    r.escape_debug()
                )));
            }
            if !meshes.contains(&r) {
                return Err(AppError::invalid(format!(
                    "{m}: its buffer file {r:?} was not uploaded (send it as a mesh part)"
                )));
            }
        }
    }
    let most = limits.patches.min(MAX_PATCHES);
    check_triangle_counts(dir, &file, most)?;
    let loaded =
        load_scene_file(&path).map_err(|e| AppError::invalid(strip_dir(&e.to_string(), dir)))?;
    let density = density_for(got_patches, max_edge, file.patches);
    if let Density::Target(0) = density {
        return Err(AppError::invalid("patches must be at least 1"));
    }
    // The count the precompute will make, not the one asked for: every triangle becomes at
    // least one patch, so a 60k-triangle mesh with `patches=100` is 60k patches.
    let sources: Vec<&[[glam::Vec3; 3]]> = loaded
        .objects
        .iter()
        .map(|o| o.triangles.as_slice())
        .collect();
    let count = plan(&sources, density).1;
    if count > most {
        return Err(AppError::invalid(format!(
            "the scene would make {count} patches, more than this server precomputes for an \
             upload ({most}); ask for fewer with the patches field, or simplify the meshes \
             (every triangle is at least one patch; `simplify_to` in the scene file)"
        )));
    }
    Ok(())
}

/// How many source triangles an upload may load per patch it may make: an object with
/// `simplify_to` is loaded whole before it is simplified.
pub const SOURCE_TRIANGLES_PER_PATCH: u64 = 20;

/// Refuses a scene whose meshes and shapes hold too many triangles, counted from the shape
/// parameters and the files' headers and faces without building any geometry (memory stays
/// flat: a 1.5 KB scene of eight 4,096-segment spheres asks for 134 million triangles).
/// Every triangle is at least one patch, so more triangles than `most` patches (after
/// `simplify_to`) is refused, and so is loading more than [`SOURCE_TRIANGLES_PER_PATCH`]
/// times `most`.
fn check_triangle_counts(dir: &Path, file: &SceneFile, most: u64) -> Result<(), AppError> {
    let (mut loaded, mut kept) = (0u64, 0u64);
    for o in &file.objects {
        let count = match &o.mesh {
            MeshRef::Shape(shape) => shape_triangle_count(shape),
            MeshRef::Path(p) => triangle_count(&dir.join(p))
                .map_err(|e| AppError::invalid(format!("object '{}': mesh {p:?}: {e}", o.name)))?,
        };
        loaded = loaded.saturating_add(count);
        kept = kept.saturating_add(o.simplify_to.map_or(count, |n| n.min(count)));
    }
    if kept > most {
        return Err(AppError::invalid(format!(
            "the scene would make at least {kept} patches (every triangle is at least one \
             patch), more than this server precomputes for an upload ({most}); use fewer \
             segments or simpler meshes (`simplify_to` in the scene file)"
        )));
    }
    let most_loaded = most.saturating_mul(SOURCE_TRIANGLES_PER_PATCH);
    if loaded > most_loaded {
        return Err(AppError::invalid(format!(
            "the scene's meshes hold {loaded} triangles, more than this server loads for an \
             upload ({most_loaded}: {SOURCE_TRIANGLES_PER_PATCH} per patch it may make, even \
             with `simplify_to`); simplify them before uploading"
        )));
    }
    Ok(())
}

/// Removes the upload folder unless disarmed (every refusal leaves nothing behind).
struct Staging(Option<PathBuf>);

impl Drop for Staging {
    fn drop(&mut self) {
        if let Some(d) = self.0.take() {
            let _ = std::fs::remove_dir_all(d);
        }
    }
}

/// `POST /api/v1/scenes` (its handler is [`crate::team`]'s): receives and checks the form
/// within `limits`, reserves the scene id with `reserve` (the guard it returns is held until
/// the job is queued or the upload refused) and queues the precompute job on `jobs`.
pub async fn accept<R>(
    jobs: &Jobs,
    limits: UploadLimits,
    reserve: impl FnOnce(&str) -> Result<R, AppError>,
    identity: Option<Extension<Identity>>,
    form: Result<Multipart, axum::extract::multipart::MultipartRejection>,
) -> Result<Response, AppError> {
    let form = form.map_err(|e| {
        AppError::unsupported_media_type(format!(
            "send the scene as multipart/form-data (fields scene, mesh, id, patches): {}",
            e.body_text()
        ))
    })?;
    let job_id = Jobs::new_id();
    let dir = jobs.upload_dir(&job_id);
    std::fs::create_dir_all(&dir)
        .map_err(|e| AppError::internal(format!("cannot create the upload folder: {e}")))?;
    let mut staging = Staging(Some(dir.clone()));

    let got = receive(form, &dir, &limits).await?;
    let Some(scene_name) = got.scene.clone() else {
        return Err(AppError::invalid(
            "no scene file: send the scene JSON in the form field `scene`",
        ));
    };
    if got.patches.is_some() && got.max_edge.is_some() {
        return Err(AppError::invalid("give patches or max_edge, not both"));
    }
    let id = match &got.id {
        Some(id) => id.clone(),
        None => scene_name.trim_end_matches(".json").to_string(),
    };
    check_scene_id(&id).map_err(AppError::invalid)?;
    // Held until the job is queued (or the upload is refused): see `Team::reserve`.
    let _reservation = reserve(&id)?;

    let (d, meshes, patches, max_edge) =
        (dir.clone(), got.meshes.clone(), got.patches, got.max_edge);
    let name = scene_name.clone();
    tokio::task::spawn_blocking(move || {
        check_scene(&d, &name, &meshes, patches, max_edge, &limits)
    })
    .await
    .map_err(|e| AppError::internal(format!("the scene check failed: {e}")))??;

    let owner = identity.map_or_else(|| "local".to_string(), |Extension(i)| i.name.to_string());
    let record = jobs.submit(JobSpec {
        id: job_id.clone(),
        scene: id,
        owner,
        scene_file: dir.join(&scene_name),
        patches: got.patches,
        max_edge: got.max_edge,
        resimulate: None,
        work_limit: None,
    })?;
    staging.0 = None;
    tracing::info!(
        job = %record.id,
        scene = %record.scene,
        files = got.meshes.len() + 1,
        bytes = got.total,
        "upload accepted"
    );
    let mut r = (StatusCode::ACCEPTED, Json(&record)).into_response();
    if let Ok(v) = HeaderValue::from_str(&format!("/api/v1/jobs/{}", record.id)) {
        r.headers_mut().insert(LOCATION, v);
    }
    Ok(r)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_names() {
        for ok in ["bunny.obj", "scene.json", "a-b_c.1.mtl", "X"] {
            assert!(check_file_name(ok).is_ok(), "{ok}");
        }
        for bad in [
            "",
            "../x.obj",
            "..",
            "a/b.obj",
            "a\\b.obj",
            "/etc/passwd",
            ".hidden.obj",
            "a..b.obj",
            "sp ace.obj",
            "nul\0.obj",
            "é.obj",
        ] {
            assert!(check_file_name(bad).is_err(), "{bad:?}");
        }
        assert!(check_file_name(&"a".repeat(MAX_NAME + 1)).is_err());
        for ok in ["cup", "Cup_2", "9-lives"] {
            assert!(check_scene_id(ok).is_ok(), "{ok}");
        }
        for bad in [
            "",
            ".cup",
            "-cup",
            "cup/x",
            "..",
            "cup cup",
            &"c".repeat(65),
        ] {
            assert!(check_scene_id(bad).is_err(), "{bad:?}");
        }
    }
}
