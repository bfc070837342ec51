//! What the server holds: one [`Scene`] per bundle, opened once at start-up and shared.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::{Arc, Mutex, OnceLock};

use axum::body::Bytes;
use glam::Vec3;
use translux_precompute::pipeline::{material_albedo_emission, patch_albedo};
use translux_precompute::radiosity::Rgb;
use translux_precompute::raycast::Occluder;
use translux_precompute::smatrix::{self, CsrOwned, SParams};
use translux_proto::bundle::{Bundle, BundleError, MANIFEST_FILE, arrays};
use translux_proto::csr::CsrView;
use translux_proto::scene::Material;

/// One served bundle: the mapped arrays plus what relighting needs that the bundle does not
/// store (the shadow-ray BVH, patch centroids as vectors).
#[derive(Debug)]
pub struct Scene {
    /// The bundle's folder name; the `{id}` of its routes.
    pub id: String,
    pub bundle: Bundle,
    pub(crate) occluder: Occluder,
    pub(crate) centroids: Vec<Vec3>,
    pub(crate) normals: Vec<Vec3>,
    /// `GET /mesh`'s JSON, serialised on first use.
    pub(crate) mesh_json: OnceLock<Bytes>,
    /// The materials of the last override set, so a client that keeps its overrides while
    /// moving lights pays for the S rebuild once.
    pub(crate) material_cache: Mutex<Option<(String, Arc<OverrideMaterials>)>>,
}

/// S, ρ and Bₑ for a set of material overrides.
#[derive(Debug)]
pub struct OverrideMaterials {
    pub s: CsrOwned<[f32; 3]>,
    pub albedo: Vec<Rgb>,
    pub emission: Vec<Rgb>,
}

impl OverrideMaterials {
    /// S as a view (built by `smatrix::assemble_scene`, valid by construction).
    pub fn s_view(&self) -> CsrView<'_, [f32; 3]> {
        let n = self.albedo.len();
        CsrView::new_checked(n, n, &self.s.row_ptr, &self.s.col, &self.s.val)
            .expect("assemble_scene builds a valid CSR matrix")
    }
}

impl Scene {
    /// The materials with `overrides` applied (S rebuilt from the stored distances), or
    /// `None` without overrides. The flag says whether S was rebuilt (not cached).
    pub fn materials_for(
        &self,
        overrides: &[(usize, Material)],
    ) -> Result<Option<(Arc<OverrideMaterials>, bool)>, crate::error::AppError> {
        if overrides.is_empty() {
            return Ok(None);
        }
        let key = serde_json::to_string(overrides).unwrap_or_default();
        if let Ok(cache) = self.material_cache.lock()
            && let Some((k, m)) = cache.as_ref()
            && *k == key
        {
            return Ok(Some((m.clone(), false)));
        }
        let (s, _) = smatrix::rebuild_from_bundle(&self.bundle, overrides, &SParams::default())
            .map_err(|e| crate::error::AppError::invalid(format!("materials: {e}")))?;
        let mut albedo = self.bundle.patch_albedo().to_vec();
        let mut emission = self.bundle.patch_emission().to_vec();
        for (k, m) in overrides {
            let o = &self.bundle.manifest().objects[*k];
            let range = o.first_patch as usize..(o.first_patch + o.patch_count) as usize;
            let (rho, be) = material_albedo_emission(m);
            albedo[range.clone()].fill(rho);
            emission[range.clone()].fill(be);
            if matches!(m, Material::Heterogeneous { .. }) {
                // Each patch at its own medium's total diffuse reflectance.
                let media = self.bundle.u32s(arrays::PATCH_MATERIAL);
                for p in range {
                    albedo[p] = patch_albedo(m, media.get(p).copied().unwrap_or(0));
                }
            }
        }
        let m = Arc::new(OverrideMaterials {
            s,
            albedo,
            emission,
        });
        if let Ok(mut cache) = self.material_cache.lock() {
            *cache = Some((key, m.clone()));
        }
        Ok(Some((m, true)))
    }

    /// Opens (verifies and maps) the bundle in `dir` and builds its BVH.
    pub fn open(id: impl Into<String>, dir: &Path) -> Result<Scene, BundleError> {
        let bundle = Bundle::open(dir)?;
        Ok(Scene::from_bundle(id, bundle))
    }

    /// Builds the relight state for an opened bundle.
    pub fn from_bundle(id: impl Into<String>, bundle: Bundle) -> Scene {
        let tris: Vec<[Vec3; 3]> = bundle
            .occluder_triangles()
            .iter()
            .map(|t| t.map(Vec3::from))
            .collect();
        let occluder = Occluder::new(&tris);
        let centroids = bundle
            .patch_corners()
            .iter()
            .map(|c| (Vec3::from(c[0]) + Vec3::from(c[1]) + Vec3::from(c[2])) / 3.0)
            .collect();
        let normals = bundle
            .patch_normals()
            .iter()
            .map(|&n| Vec3::from(n))
            .collect();
        Scene {
            id: id.into(),
            bundle,
            occluder,
            centroids,
            normals,
            mesh_json: OnceLock::new(),
            material_cache: Mutex::new(None),
        }
    }
}

/// The scenes served, by id; cheap to clone (one `Arc`).
#[derive(Debug, Clone, Default)]
pub struct AppState {
    scenes: Arc<BTreeMap<String, Arc<Scene>>>,
}

impl AppState {
    /// A state serving `scenes` (a later scene with the same id replaces an earlier one).
    pub fn new(scenes: impl IntoIterator<Item = Scene>) -> AppState {
        let map = scenes
            .into_iter()
            .map(|s| (s.id.clone(), Arc::new(s)))
            .collect();
        AppState {
            scenes: Arc::new(map),
        }
    }

    /// The scene with this id.
    pub fn scene(&self, id: &str) -> Option<&Arc<Scene>> {
        self.scenes.get(id)
    }

    /// Every scene, in id order.
    pub fn scenes(&self) -> impl Iterator<Item = &Arc<Scene>> {
        self.scenes.values()
    }

    /// The ids served, sorted.
    pub fn ids(&self) -> Vec<String> {
        self.scenes.keys().cloned().collect()
    }

    pub fn len(&self) -> usize {
        self.scenes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.scenes.is_empty()
    }
}

/// Opens every bundle under `dir`: each sub-folder is one bundle whose id is the folder
/// name. Hidden folders (a writer's temporaries start with `.`) and plain files are passed
/// over. If `dir` itself holds a `manifest.json` it is served alone, under its own name.
///
/// Returns the state with every bundle that opened, and `(id, message)` for each that did
/// not (the loader's message, e.g. `ff_val.f32 is truncated: 100 bytes, manifest says 400`);
/// a folder that cannot be read at all comes back as one error with `dir` as its id.
pub fn load_bundles(dir: &Path) -> (AppState, Vec<(String, String)>) {
    let mut scenes = Vec::new();
    let mut errors = Vec::new();
    let mut try_open =
        |id: String, path: &Path, errors: &mut Vec<(String, String)>| match Scene::open(
            id.clone(),
            path,
        ) {
            Ok(scene) => scenes.push(scene),
            Err(e) => errors.push((id, e.to_string())),
        };
    if dir.join(MANIFEST_FILE).is_file() {
        let id = folder_name(dir).unwrap_or_else(|| "bundle".to_string());
        try_open(id, dir, &mut errors);
        return (AppState::new(scenes), errors);
    }
    let entries = match std::fs::read_dir(dir) {
        Ok(entries) => entries,
        Err(e) => {
            errors.push((
                dir.display().to_string(),
                format!("cannot read the folder: {e}"),
            ));
            return (AppState::new(scenes), errors);
        }
    };
    let mut folders: Vec<_> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.is_dir())
        .collect();
    folders.sort();
    for path in folders {
        let Some(name) = path.file_name() else {
            continue;
        };
        let Some(id) = name.to_str() else {
            errors.push((
                name.to_string_lossy().into_owned(),
                "the folder name is not UTF-8 and cannot be an id".to_string(),
            ));
            continue;
        };
        if id.starts_with('.') {
            continue;
        }
        try_open(id.to_string(), &path, &mut errors);
    }
    (AppState::new(scenes), errors)
}

/// The last component of `dir` (after resolving `.` and `..`).
fn folder_name(dir: &Path) -> Option<String> {
    let abs = std::fs::canonicalize(dir).ok()?;
    abs.file_name().and_then(|n| n.to_str()).map(str::to_string)
}
