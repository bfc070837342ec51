//! Environment lights in a relight: map paths, the map cache, and E from the bundle's
//! precomputed visibility (no rays).
//!
//! In: a scene and the request's lights. Out: [`check`] refuses what cannot be lit (an
//! invalid or unsupported error naming the field) before any work; [`direct_irradiance`] is E for all lights, point-like
//! ones with shadow rays ([`crate::radiosity::direct_irradiance`]) plus each
//! environment light's E_i = scale · Σ_k V_ik L̄_k ([`crate::envvis`]).
//!
//! Maps (see `docs/environment.md`): `builtin:sky`, `builtin:white`, or a Radiance `.hdr`
//! file named by a relative path inside the *bundles folder* — the folder that holds the
//! scene's bundle folder (`--bundles DIR` for the server; the parent of `--bundle DIR`
//! offline). Absolute paths, `..` and links that lead outside it are refused. Loaded maps
//! (keyed by path, length and modification time) and their per-bin means (keyed also by
//! rotation and bins) are cached in the scene's [`EnvCache`] (shared by a server's scenes), a
//! few of each.

use std::path::{Component, Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::SystemTime;

use crate::envmap::{self, Bins, EnvMap};
use crate::radiosity::{self, PatchGeometry, Rgb};
use translux_proto::light::Light;

use crate::error::EngineError;
use crate::raycast::Occluder;
use translux_proto::bundle::Bundle;

/// Maps kept in memory (a 2k × 1k map is 24 MB).
const MAP_CACHE: usize = 4;
/// Per-bin means kept (one per map, rotation and partition; a few KB each).
const MEAN_CACHE: usize = 64;

/// Where a map comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
enum MapKey {
    Builtin(String),
    /// Canonical path, byte length, modification time.
    File(PathBuf, u64, Option<SystemTime>),
}

type MeanKey = (MapKey, u32, u32, u32);

#[derive(Debug, Default)]
struct Caches {
    maps: Vec<(MapKey, Arc<EnvMap>)>,
    means: Vec<(MeanKey, Arc<Vec<Rgb>>)>,
}

/// What environment lighting reads of a scene (see `crate::scene::Scene::env`).
#[derive(Debug, Clone, Copy)]
pub struct EnvScene<'a> {
    /// The scene's id, named in messages.
    pub id: &'a str,
    pub bundle: &'a Bundle,
    /// The shadow-ray BVH, for the lights that are not environments.
    pub occluder: &'a Occluder,
    pub cache: &'a EnvCache,
}

/// Loaded maps and their per-bin means, a few of each: shared by the scenes that hold the
/// same [`crate::scene::Resources`] (a server's scenes share one).
#[derive(Debug, Default)]
pub struct EnvCache(Mutex<Caches>);

/// The folder map paths are relative to: the one holding the scene's bundle folder.
fn maps_root(scene: &EnvScene<'_>) -> PathBuf {
    let dir = scene.bundle.dir();
    let abs = std::fs::canonicalize(dir).unwrap_or_else(|_| dir.to_path_buf());
    abs.parent().map(Path::to_path_buf).unwrap_or(abs)
}

/// Resolves `map` (the value of `lights[i].map`, named `at` in messages).
fn resolve(scene: &EnvScene<'_>, map: &str, at: &str) -> Result<MapKey, EngineError> {
    if map.starts_with("builtin:") {
        EnvMap::builtin(map).map_err(|e| EngineError::invalid(format!("{at}: {e}")))?;
        return Ok(MapKey::Builtin(map.to_string()));
    }
    let rel = Path::new(map);
    let plain = rel
        .components()
        .all(|c| matches!(c, Component::Normal(_) | Component::CurDir));
    if !plain || rel.as_os_str().is_empty() {
        return Err(EngineError::invalid(format!(
            "{at}: {map:?} must be builtin:sky, builtin:white or a relative path inside the \
             bundles folder (no absolute path, no '..')"
        )));
    }
    let is_hdr = rel
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("hdr"));
    if !is_hdr {
        return Err(EngineError::invalid(format!(
            "{at}: {map:?} is not a .hdr file (environment maps are equirectangular Radiance \
             .hdr images)"
        )));
    }
    let root = maps_root(scene);
    let path = match std::fs::canonicalize(root.join(rel)) {
        Ok(p) => p,
        Err(_) => {
            return Err(EngineError::invalid(format!(
                "{at}: no map {map:?} in the bundles folder (paths are relative to the folder \
                 that holds the scene's bundle)"
            )));
        }
    };
    if !path.starts_with(&root) {
        return Err(EngineError::invalid(format!(
            "{at}: {map:?} leads outside the bundles folder"
        )));
    }
    let meta = std::fs::metadata(&path)
        .map_err(|e| EngineError::invalid(format!("{at}: cannot read {map:?}: {e}")))?;
    if !meta.is_file() {
        return Err(EngineError::invalid(format!("{at}: {map:?} is not a file")));
    }
    Ok(MapKey::File(path, meta.len(), meta.modified().ok()))
}

/// The map for `key`, from the cache or loaded (and cached).
fn load(cache: &EnvCache, key: &MapKey, map: &str, at: &str) -> Result<Arc<EnvMap>, EngineError> {
    if let Ok(c) = cache.0.lock()
        && let Some((_, m)) = c.maps.iter().find(|(k, _)| k == key)
    {
        return Ok(m.clone());
    }
    let loaded = match key {
        MapKey::Builtin(name) => EnvMap::builtin(name),
        MapKey::File(path, ..) => EnvMap::load_hdr(path),
    };
    // The message names the request's path, never the server's folders.
    let loaded = Arc::new(loaded.map_err(|e| {
        let reason = match e {
            envmap::EnvMapError::Malformed { reason, .. } => {
                format!("not a valid Radiance .hdr image: {reason}")
            }
            envmap::EnvMapError::TooLarge { width, height, .. } => format!(
                "{width}×{height} pixels is larger than the {} allowed",
                envmap::MAX_PIXELS
            ),
            envmap::EnvMapError::Io { error, .. } => format!("cannot read the file: {error}"),
            other => other.to_string(),
        };
        EngineError::invalid(format!("{at}: {map:?}: {reason}"))
    })?);
    if let Ok(mut c) = cache.0.lock() {
        if c.maps.len() >= MAP_CACHE {
            c.maps.remove(0);
        }
        c.maps.push((key.clone(), loaded.clone()));
    }
    Ok(loaded)
}

/// The map's mean radiance per bin after rotation, cached.
fn means(
    cache: &EnvCache,
    key: &MapKey,
    map: &Arc<EnvMap>,
    rotation_deg: f32,
    bins: Bins,
) -> Arc<Vec<Rgb>> {
    let mk = (key.clone(), rotation_deg.to_bits(), bins.rows, bins.cols);
    if let Ok(c) = cache.0.lock()
        && let Some((_, m)) = c.means.iter().find(|(k, _)| *k == mk)
    {
        return m.clone();
    }
    let m = Arc::new(envmap::bin_radiance(map, rotation_deg, bins));
    if let Ok(mut c) = cache.0.lock() {
        if c.means.len() >= MEAN_CACHE {
            c.means.remove(0);
        }
        c.means.push((mk, m.clone()));
    }
    m
}

/// Checks every environment light of `lights` against `scene` (visibility in the bundle,
/// the map found and readable); loads and caches the maps. `given`: whether the lights came
/// with the request (else they are the scene's defaults, which the message says).
pub fn check(scene: &EnvScene<'_>, lights: &[Light], given: bool) -> Result<(), EngineError> {
    for (i, l) in lights.iter().enumerate() {
        let Light::Environment { map, .. } = l else {
            continue;
        };
        let at = if given {
            format!("lights[{i}]")
        } else {
            format!("lights[{i}] (one of the scene's default lights)")
        };
        if scene.bundle.environment_visibility().is_none() {
            return Err(EngineError::unsupported(format!(
                "{at}: scene {:?} was precomputed without environment visibility \
                 (--env-bins 0); precompute it again without that flag to light it with an \
                 environment",
                scene.id
            )));
        }
        map_of(scene, map, &format!("{at}.map"))?;
    }
    Ok(())
}

/// The loaded map `map` (the value of the field `at`), from the cache or read.
fn map_of(scene: &EnvScene<'_>, map: &str, at: &str) -> Result<Arc<EnvMap>, EngineError> {
    let key = resolve(scene, map, at)?;
    load(scene.cache, &key, map, at)
}

/// The environment lights of `lights` with their maps loaded (from the cache after
/// [`check`]), in order: what the specular pass reflects ([`crate::specular::EnvLight`]).
pub fn lights_with_maps(
    scene: &EnvScene<'_>,
    lights: &[Light],
) -> Result<Vec<crate::specular::EnvLight>, EngineError> {
    let mut out = Vec::new();
    for (i, l) in lights.iter().enumerate() {
        let Light::Environment {
            map,
            scale,
            rotation_deg,
        } = l
        else {
            continue;
        };
        out.push(crate::specular::EnvLight {
            map: map_of(scene, map, &format!("lights[{i}].map"))?,
            scale: *scale,
            rotation_deg: *rotation_deg,
        });
    }
    Ok(out)
}

/// E for every patch from all of `lights`: point, spot and directional lights with shadow
/// rays, environment lights from the bundle's visibility (W·m⁻²).
pub fn direct_irradiance(
    scene: &EnvScene<'_>,
    geo: PatchGeometry<'_>,
    lights: &[Light],
) -> Result<Vec<Rgb>, EngineError> {
    let (env, others): (Vec<&Light>, Vec<&Light>) = lights
        .iter()
        .partition(|l| matches!(l, Light::Environment { .. }));
    let others: Vec<Light> = others.into_iter().cloned().collect();
    let mut e = radiosity::direct_irradiance(
        geo,
        scene.occluder,
        &others,
        scene.bundle.manifest().unit_mm,
    )
    .map_err(|e| EngineError::unsupported(e.to_string()))?;
    if env.is_empty() {
        return finite(e);
    }
    let Some(vis) = scene.bundle.environment_visibility() else {
        return Err(EngineError::unsupported(format!(
            "lights: scene {:?} was precomputed without environment visibility (--env-bins 0)",
            scene.id
        )));
    };
    let total = bin_radiance_total(scene, lights)?.unwrap_or_default();
    add_from_bits(vis, &total, &mut e);
    finite(e)
}

/// Σ over `lights`' environments of scale · L̄_k, the mean radiance of each direction bin
/// of the bundle's visibility (W·m⁻²·sr⁻¹; maps loaded and binned through the scene's
/// cache); `None` without an environment light or without visibility in the bundle.
pub fn bin_radiance_total(
    scene: &EnvScene<'_>,
    lights: &[Light],
) -> Result<Option<Vec<Rgb>>, EngineError> {
    let Some(vis) = scene.bundle.environment_visibility() else {
        return Ok(None);
    };
    if !lights
        .iter()
        .any(|l| matches!(l, Light::Environment { .. }))
    {
        return Ok(None);
    }
    let bins = Bins {
        rows: vis.rows,
        cols: vis.cols,
    };
    // Summed over the lights, so the N × K product runs once.
    let mut total = vec![[0.0f32; 3]; bins.count()];
    for (i, l) in lights.iter().enumerate() {
        let Light::Environment {
            map,
            scale,
            rotation_deg,
        } = l
        else {
            continue;
        };
        let at = format!("lights[{i}].map");
        let key = resolve(scene, map, &at)?;
        let m = load(scene.cache, &key, map, &at)?;
        for (t, l) in total
            .iter_mut()
            .zip(means(scene.cache, &key, &m, *rotation_deg, bins).iter())
        {
            for c in 0..3 {
                t[c] += scale * l[c];
            }
        }
    }
    Ok(Some(total))
}

/// E must be finite: lights within the validated bounds can still overflow f32 next to a
/// surface, and an infinite right-hand side has no solution (a solver would stop at once
/// and return whatever it was warm-started from).
fn finite(e: Vec<Rgb>) -> Result<Vec<Rgb>, EngineError> {
    match e.iter().position(|v| !v.iter().all(|x| x.is_finite())) {
        None => Ok(e),
        Some(i) => Err(EngineError::invalid(format!(
            "lights: the irradiance overflows at patch {i}; use smaller intensities (or a \
             light farther from the surfaces)"
        ))),
    }
}

/// e_i += Σ_k V_ik L_k with V as half-float bits (converted a row at a time).
fn add_from_bits(vis: translux_proto::bundle::EnvVisibilityView<'_>, total: &[Rgb], e: &mut [Rgb]) {
    use rayon::prelude::*;
    let k = vis.bins();
    e.par_iter_mut().enumerate().with_min_len(64).for_each_init(
        || vec![0.0f32; k],
        |row, (i, ei)| {
            visibility_row(vis, i, row);
            let mut acc = [0.0f32; 3];
            for (&v, l) in row.iter().zip(total) {
                acc[0] += v * l[0];
                acc[1] += v * l[1];
                acc[2] += v * l[2];
            }
            for c in 0..3 {
                ei[c] += acc[c];
            }
        },
    );
}

/// Patch i's visibility per bin as f32 into `out` (one value per bin), converted from the
/// bundle's half floats (vectorised by the `half` crate).
pub(crate) fn visibility_row(
    vis: translux_proto::bundle::EnvVisibilityView<'_>,
    i: usize,
    out: &mut [f32],
) {
    use half::slice::{HalfBitsSliceExt, HalfFloatSliceExt};
    let bits: &[half::f16] = vis.row(i).reinterpret_cast();
    bits.convert_to_f32_slice(out);
}
