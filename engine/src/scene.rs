//! A bundle opened for relighting: the mapped arrays plus what relighting needs that the
//! bundle does not store — the shadow-ray BVH, patch centroids and normals as vectors — and
//! the caches that make the next relight cheaper (the last override set's S, the last
//! solutions for warm starts). It relights on the [`Backend`] of its [`Resources`].
//!
//! In: a bundle folder (or an opened [`Bundle`]) and the [`Resources`] to relight with.
//! Out: a [`Scene`] that [`crate::relight`] and [`crate::picture`] take; with material
//! overrides, [`Scene::materials_for`] gives S, ρ and Bₑ: S built on the CPU from its radial
//! terms, and for a change that only moves profiles (a slider) written in place, on the CPU
//! when a CPU stage first needs it ([`Scene::cpu_s`]), so a backend that writes those rows
//! itself (the GPU's) is not kept waiting. What the first translucency change would make
//! (S's radial terms) can be made ahead of it: [`Scene::prepare_translucency`].

use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};

use glam::Vec3;
use translux_proto::api::{Components, PrepState, TranslucencyPrep};
use translux_proto::bundle::{Bundle, BundleError, arrays};
use translux_proto::csr::ValidCsr;
use translux_proto::scene::Material;

use crate::backend::{Backend, Cpu, SceneRef};
use crate::collimated::{Slant, Tilt, TiltOf};
use crate::environment::{EnvCache, EnvScene};
use crate::error::EngineError;
use crate::radiosity::Rgb;
use crate::raycast::Occluder;
use crate::smatrix::{
    self, ColumnScale, OverrideMaterials, SParams, material_albedo_emission, patch_albedo,
};
use crate::sterms::{STerms, Scratch};
use crate::vertexlight::{VertexLit, VertexSamples};

/// What the scenes of one process share: the backend they relight on and the cache of
/// environment maps. Cheap to clone. The default is the CPU with a cache of its own.
#[derive(Debug, Clone)]
pub struct Resources {
    pub backend: Arc<dyn Backend>,
    pub env: Arc<EnvCache>,
}

impl Default for Resources {
    fn default() -> Self {
        Resources::on(Arc::new(Cpu))
    }
}

impl Resources {
    /// `backend` with a new environment-map cache.
    pub fn on(backend: Arc<dyn Backend>) -> Resources {
        Resources {
            backend,
            env: Arc::new(EnvCache::default()),
        }
    }
}

/// S for a translucency change written in place ([`Scene::rewrite_last`]), of the last
/// S's layout: made on the CPU, or deferred (an earlier S and the objects whose rows in it
/// are stale).
enum Rewritten {
    Made(smatrix::ScaledS, u64),
    Deferred((smatrix::ScaledS, Vec<usize>), u64),
}

/// One bundle opened for relighting (see the module docs).
#[derive(Debug)]
pub struct Scene {
    /// The scene's id (the server's bundle folder name); named in messages.
    pub id: String,
    pub bundle: Bundle,
    pub(crate) occluder: Occluder,
    pub(crate) centroids: Vec<Vec3>,
    pub(crate) normals: Vec<Vec3>,
    /// The materials of the last override set, so a client that keeps its overrides while
    /// moving lights pays for the S rebuild once.
    pub(crate) material_cache: Mutex<Option<(String, Arc<OverrideMaterials>)>>,
    /// The next layout number of an S built afresh ([`OverrideMaterials::layout`]).
    layouts: AtomicU64,
    /// S's entries reduced to radial terms, made by the first CPU rebuild of S and reused
    /// by every later one ([`crate::sterms`]).
    pub(crate) s_terms: OnceLock<STerms>,
    /// Whether what the first translucency change needs is made ([`Scene::prepare_translucency`]).
    prep: Mutex<TranslucencyPrep>,
    /// The buffers a translucency change writes S through, kept for the next one.
    pub(crate) s_scratch: Mutex<Scratch>,
    /// Δ = S⁽ⁿ⁾ − S of the simulated objects for the last materials key
    /// ([`crate::collimated`]).
    pub(crate) tilt_cache: Mutex<Option<(String, Arc<TiltOf>)>>,
    /// The direction weights of the light entering the simulated objects, for the last
    /// set of simulated patches ([`Scene::slant_for`]).
    slant_cache: Mutex<Option<(String, Arc<Slant>)>>,
    /// Where direct light is evaluated at the viewer's vertices (made on first use).
    pub(crate) vertex_samples: OnceLock<VertexSamples>,
    /// The colour stage as rows for the bundle's materials, made on a backend's first
    /// whole relight ([`Scene::vertex_rows`]): where diffuse objects alone count as opaque,
    /// and where every object does (`direct`, `interreflection_only`).
    pub(crate) vertex_rows: [OnceLock<Arc<crate::vertexrows::VertexRows>>; 2],
    /// The last solutions, for warm starts (see [`WarmCache`]).
    pub(crate) warm: WarmCache,
    /// The last lights' direct light (see [`DirectCache`]).
    pub(crate) direct: DirectCache,
    pub(crate) resources: Resources,
}

impl Scene {
    /// The materials with `overrides` applied (S rebuilt from the stored distances), or
    /// `None` without overrides. The flag says whether S was rebuilt (not cached).
    pub fn materials_for(
        &self,
        overrides: &[(usize, Material)],
    ) -> Result<Option<(Arc<OverrideMaterials>, bool)>, EngineError> {
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
        let invalid = |e: smatrix::SError| EngineError::invalid(format!("materials: {e}"));
        let named = (key.clone(), overrides.to_vec());
        let rho_be = self.albedo_emission(overrides);
        let m = match self.rewrite_last(&key, overrides) {
            Some(Ok(Rewritten::Made(s, layout))) => {
                OverrideMaterials::made(named, s, rho_be, (true, layout))
            }
            Some(Ok(Rewritten::Deferred(base, layout))) => {
                OverrideMaterials::deferred(named, base, rho_be, layout)
            }
            Some(Err(e)) => return Err(invalid(e)),
            None => {
                let s = (self.build_s(&key, overrides)?, ColumnScale::default());
                let layout = self.layouts.fetch_add(1, Ordering::Relaxed);
                OverrideMaterials::made(named, s, rho_be, (false, layout))
            }
        };
        let m = Arc::new(m);
        if let Ok(mut cache) = self.material_cache.lock() {
            *cache = Some((key, m.clone()));
        }
        Ok(Some((m, true)))
    }

    /// ρ and Bₑ per patch with `overrides` applied.
    fn albedo_emission(&self, overrides: &[(usize, Material)]) -> (Vec<Rgb>, Vec<Rgb>) {
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
        (albedo, emission)
    }

    /// S of `m` on the CPU: made now when it was deferred (the changed objects' rows
    /// written in place from their radial terms, [`smatrix::rewrite_with_terms_deferred`]).
    pub fn cpu_s<'m>(&self, m: &'m OverrideMaterials) -> Result<&'m smatrix::ScaledS, EngineError> {
        let rewrite = |(s, mut columns): smatrix::ScaledS, stale: &[usize]| {
            let terms = self.s_terms.get().ok_or_else(|| smatrix::SError::Media {
                object: "S".into(),
                why: "its radial terms are not made".into(),
            })?;
            let mut scratch = self.s_scratch.lock().unwrap_or_else(|p| p.into_inner());
            let (s, _) = smatrix::rewrite_with_terms_deferred(
                &self.bundle,
                s,
                &mut columns,
                &mut None,
                &m.overrides,
                stale,
                &SParams::default(),
                terms,
                &mut scratch,
            )?;
            Ok((s, columns))
        };
        m.cpu_s(&rewrite)
            .map_err(|e| EngineError::invalid(format!("materials: {e}")))
    }

    /// S for `overrides` built afresh on the CPU from the radial terms (on every backend).
    fn build_s(
        &self,
        key: &str,
        overrides: &[(usize, Material)],
    ) -> Result<ValidCsr<[f32; 3]>, EngineError> {
        let invalid = |e: smatrix::SError| EngineError::invalid(format!("materials: {e}"));
        let params = SParams::default();
        let terms = self.terms();
        let (s, _, tilts) =
            smatrix::rebuild_with_terms_and_tilt(&self.bundle, overrides, &params, terms)
                .map_err(invalid)?;
        if !tilts.is_empty() {
            // The simulated objects' Δ came from the same pass over their walks: kept for
            // this set of materials, where tilt_for finds it.
            let materials = smatrix::materials_with(&self.bundle, overrides);
            let t = crate::collimated::tilt_of_with(&self.bundle, &materials, tilts);
            if let Ok(mut cache) = self.tilt_cache.lock() {
                *cache = Some((key.to_string(), Arc::new(t)));
            }
        }
        Ok(s)
    }

    /// S's entries reduced to radial terms: made by the first call (the first translucency
    /// change on the CPU, or [`Scene::prepare_translucency`]), which a concurrent caller
    /// waits for, and kept.
    fn terms(&self) -> &STerms {
        let params = SParams::default();
        let terms = self.s_terms.get_or_init(|| {
            let t = smatrix::terms_of_bundle(&self.bundle, &params.quadrature);
            tracing::info!(
                scene = %self.id,
                entries = t.entries(),
                terms = t.terms(),
                mib = t.bytes() as f64 / (1u64 << 20) as f64,
                seconds = t.seconds,
                "S reduced to radial terms for translucency changes"
            );
            t
        });
        self.settle_ready(TranslucencyPrep {
            on: Some("cpu".into()),
            seconds: Some(terms.seconds),
            bytes: Some(terms.bytes()),
            ..Default::default()
        });
        terms
    }

    fn settle_prep(&self, f: impl FnOnce(&mut TranslucencyPrep)) {
        f(&mut self.prep.lock().unwrap_or_else(|p| p.into_inner()));
    }

    /// Marks the preparation ready as `ready` says (its state set here; a message already
    /// recorded kept where `ready` has none), unless it already is.
    fn settle_ready(&self, ready: TranslucencyPrep) {
        self.settle_prep(|p| {
            if p.state != PrepState::Ready {
                let message = ready.message.or(p.message.take());
                *p = TranslucencyPrep {
                    state: PrepState::Ready,
                    message,
                    ..ready
                };
            }
        });
    }

    /// Where the scene stands in preparing for translucency changes.
    pub fn translucency(&self) -> TranslucencyPrep {
        self.prep.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// Makes now what the first translucency change would otherwise make and wait for: S's
    /// radial terms ([`crate::sterms`]). Blocking, and as long as that first change's
    /// wait (seconds to minutes on the paper's sizes); runs on the calling rayon pool, so
    /// a caller can leave relights cores of their own. Does nothing unless the state is
    /// [`PrepState::Pending`] (a scene without translucent objects, or one already made or
    /// being made); returns the state it left.
    pub fn prepare_translucency(&self) -> TranslucencyPrep {
        {
            let mut p = self.prep.lock().unwrap_or_else(|p| p.into_inner());
            if p.state != PrepState::Pending {
                return p.clone();
            }
            p.state = PrepState::Preparing;
        }
        self.terms();
        self.translucency()
    }

    /// Records that preparing failed (`why` is shown to clients); the first translucency
    /// change then makes what it needs itself, as without preparing.
    pub fn prepare_failed(&self, why: &str) {
        self.settle_prep(|p| {
            if p.state != PrepState::Ready {
                *p = TranslucencyPrep {
                    state: PrepState::Failed,
                    message: Some(why.to_string()),
                    ..Default::default()
                };
            }
        });
    }

    /// A translucency change since the last S (only translucent objects' or thin sheets'
    /// profiles, or simulated objects' absorption, differ, [`smatrix::changed_profiles`]):
    /// the last S, taken from the cache (copied only while a relight still holds it), with
    /// those objects' values to be rewritten in place. Where only profiles summed from
    /// radial terms changed, the rewrite is deferred to the first CPU consumer
    /// ([`Scene::cpu_s`]), so a backend that writes those rows itself never waits for it;
    /// where a simulated object's absorption changed it is made now, with the simulated
    /// objects' lamp tilt (kept under `key` for [`Scene::tilt_for`]). S comes as its values
    /// and the energy bound's column factors ([`smatrix::rewrite_with_terms_deferred`]).
    /// `None` when S must be built afresh.
    fn rewrite_last(
        &self,
        key: &str,
        overrides: &[(usize, Material)],
    ) -> Option<Result<Rewritten, smatrix::SError>> {
        let terms = self.s_terms.get()?;
        let (last, changed, tilt, simulated) = {
            let mut cache = self.material_cache.lock().ok()?;
            let (_, m) = cache.as_ref()?;
            let changed = smatrix::changed_profiles(&m.overrides, overrides, terms)?;
            let (last_key, m) = cache.take()?;
            let simulated = overrides
                .iter()
                .any(|(k, m)| changed.contains(k) && matches!(m, Material::Simulated { .. }));
            let mut slot = self.tilt_cache.lock().unwrap_or_else(|p| p.into_inner());
            let tilt = match slot.as_mut() {
                // The simulated objects are as they were: so is their Δ.
                Some((k, _)) if *k == last_key && !simulated => {
                    *k = key.to_string();
                    None
                }
                // Their absorption changed: their Δ is rewritten beside S.
                Some((k, _)) if *k == last_key => slot.take().and_then(|(_, t)| {
                    match Arc::try_unwrap(t).unwrap_or_else(|shared| match shared.as_ref() {
                        TiltOf::Some(t) => TiltOf::Some(t.clone()),
                        _ => TiltOf::None,
                    }) {
                        TiltOf::Some(t) => Some(t),
                        _ => None,
                    }
                }),
                _ => None,
            };
            (m, changed, tilt, simulated)
        };
        let layout = last.layout;
        let ((s, mut columns), mut stale) = OverrideMaterials::into_base(last)?;
        for k in changed {
            if !stale.contains(&k) {
                stale.push(k);
            }
        }
        if !simulated {
            return Some(Ok(Rewritten::Deferred(((s, columns), stale), layout)));
        }
        let params = SParams::default();
        let mut scratch = self.s_scratch.lock().unwrap_or_else(|p| p.into_inner());
        let (mut delta, rest) = match tilt {
            Some(Tilt {
                delta,
                ranges,
                frames,
            }) => (Some(delta), Some((ranges, frames))),
            None => (None, None),
        };
        let written = smatrix::rewrite_with_terms_deferred(
            &self.bundle,
            s,
            &mut columns,
            &mut delta,
            overrides,
            &stale,
            &params,
            terms,
            &mut scratch,
        );
        if let (Ok(_), Some((ranges, frames)), Some(delta)) = (&written, rest, delta) {
            let t = Tilt {
                delta,
                ranges,
                frames,
            };
            if let Ok(mut cache) = self.tilt_cache.lock() {
                *cache = Some((key.to_string(), Arc::new(TiltOf::Some(t))));
            }
        }
        match written {
            Ok((s, _)) => Some(Ok(Rewritten::Made((s, columns), layout))),
            Err(e @ smatrix::SError::Pattern { .. }) => {
                tracing::warn!(scene = %self.id, "S built again: {e}");
                None
            }
            Err(e) => Some(Err(e)),
        }
    }

    /// Δ = S⁽ⁿ⁾ − S of the simulated objects under `materials` (one per manifest object),
    /// `key` naming that set of materials; the last one is kept.
    pub fn tilt_for(&self, key: &str, materials: &[&Material]) -> Arc<TiltOf> {
        if let Ok(cache) = self.tilt_cache.lock()
            && let Some((k, t)) = cache.as_ref()
            && k == key
        {
            return t.clone();
        }
        let t = Arc::new(crate::collimated::tilt_of(&self.bundle, materials));
        if let Ok(mut cache) = self.tilt_cache.lock() {
            *cache = Some((key.to_string(), t.clone()));
        }
        t
    }

    /// The direction weights of the light other surfaces send into `tilt`'s simulated
    /// patches ([`Slant`]): made on the first relight that needs them and kept while the
    /// same patches are simulated (an absorption change keeps them).
    pub fn slant_for(&self, tilt: &Tilt) -> Arc<Slant> {
        let key = tilt.patches_key();
        let made: Result<_, std::convert::Infallible> = kept_or(&self.slant_cache, &key, || {
            let geo = crate::radiosity::PatchGeometry {
                centroid: &self.centroids,
                normal: &self.normals,
            };
            Ok(Arc::new(Slant::new(
                tilt,
                &crate::transport::Transport::of(&self.bundle),
                geo,
            )))
        });
        let Ok(s) = made;
        s
    }

    /// Opens (verifies and maps) the bundle in `dir` and builds its BVH, relit on the CPU
    /// with caches of its own.
    pub fn open(id: impl Into<String>, dir: &Path) -> Result<Scene, BundleError> {
        Scene::open_with(id, dir, &Resources::default())
    }

    /// [`Scene::open`], relit with `resources` (the backend, which holds the scene's device
    /// copy if any, and the environment-map cache shared by the scenes of a server).
    pub fn open_with(
        id: impl Into<String>,
        dir: &Path,
        resources: &Resources,
    ) -> Result<Scene, BundleError> {
        let bundle = Bundle::open(dir)?;
        Ok(Scene::from_bundle_with(id, bundle, resources))
    }

    /// Builds the relight state for an opened bundle, relit on the CPU.
    pub fn from_bundle(id: impl Into<String>, bundle: Bundle) -> Scene {
        Scene::from_bundle_with(id, bundle, &Resources::default())
    }

    /// [`Scene::from_bundle`], relit with `resources`.
    pub fn from_bundle_with(id: impl Into<String>, bundle: Bundle, resources: &Resources) -> Scene {
        // What a translucency change rebuilds from radial terms or a device template: S of
        // translucent objects and thin sheets (as smatrix::terms_of_bundle picks them).
        let translucent = bundle.manifest().objects.iter().any(|o| {
            matches!(
                o.material,
                Material::Translucent { .. } | Material::ThinSheet { .. }
            )
        });
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
            material_cache: Mutex::new(None),
            layouts: AtomicU64::new(0),
            tilt_cache: Mutex::new(None),
            slant_cache: Mutex::new(None),
            s_terms: OnceLock::new(),
            prep: Mutex::new(TranslucencyPrep {
                state: if translucent {
                    PrepState::Pending
                } else {
                    PrepState::None
                },
                ..Default::default()
            }),
            s_scratch: Mutex::new(Scratch::default()),
            vertex_samples: OnceLock::new(),
            vertex_rows: [OnceLock::new(), OnceLock::new()],
            warm: Default::default(),
            direct: Default::default(),
            resources: resources.clone(),
        }
    }

    /// Where direct light is evaluated at the viewer's vertices ([`crate::vertexlight`]).
    pub fn vertex_samples(&self) -> &VertexSamples {
        self.vertex_samples
            .get_or_init(|| VertexSamples::new(&self.bundle, &self.occluder))
    }

    /// The colour stage of a relight with the bundle's materials and `components` as rows
    /// ([`crate::vertexrows`]), for a backend's whole relight: one set where diffuse objects
    /// alone count as opaque, one where every object does
    /// ([`crate::vertexlight::opaque_objects`]), each made on first use.
    pub fn vertex_rows(&self, components: Components) -> &Arc<crate::vertexrows::VertexRows> {
        let all = crate::vertexlight::all_opaque(components);
        self.vertex_rows[usize::from(all)].get_or_init(|| {
            let materials = crate::smatrix::materials_with(&self.bundle, &[]);
            let opaque = crate::vertexlight::opaque_objects(&materials, components);
            let per_pixel: Vec<bool> = materials
                .iter()
                .map(|m| crate::vertexlight::per_pixel_direct(m).is_some())
                .collect();
            Arc::new(crate::vertexrows::VertexRows::new(
                &self.bundle,
                self.vertex_samples(),
                &opaque,
                &per_pixel,
            ))
        })
    }

    /// What environment lighting reads of it ([`crate::environment`]).
    pub fn env(&self) -> EnvScene<'_> {
        EnvScene {
            id: &self.id,
            bundle: &self.bundle,
            occluder: &self.occluder,
            cache: &self.resources.env,
        }
    }

    /// What a backend sees of it: its id and bundle.
    pub fn view(&self) -> SceneRef<'_> {
        SceneRef {
            id: &self.id,
            bundle: &self.bundle,
            terms: self.s_terms.get(),
        }
    }

    /// The backend its relights run on.
    pub fn backend(&self) -> &dyn Backend {
        self.resources.backend.as_ref()
    }

    /// Host bytes held by the cached override materials (S, ρ, Bₑ), S's radial terms and
    /// the buffers a change writes S through, 0 when none.
    pub fn material_cache_bytes(&self) -> u64 {
        self.s_terms.get().map_or(0, STerms::bytes)
            + self.override_bytes()
            + self.s_scratch.lock().map_or(0, |s| s.bytes())
    }

    fn override_bytes(&self) -> u64 {
        self.material_cache
            .lock()
            .ok()
            .and_then(|c| {
                c.as_ref()
                    .map(|(_, m)| m.s_bytes() + m.albedo.len() as u64 * 24)
            })
            .unwrap_or(0)
    }
}

/// The direct light of the last lights asked, at the patches (E) and at the viewer's
/// vertices ([`crate::relight`]), keyed by the lights as JSON (and, at the vertices, by
/// which objects count as opaque). A translucency slider sends the same lights with every
/// step; the scene's geometry never changes, so their direct light is traced once. One
/// entry each: a light that moves replaces it.
#[derive(Debug, Default)]
pub struct DirectCache {
    patches: Mutex<Option<(String, Arc<Vec<Rgb>>)>>,
    vertices: Mutex<Option<(String, Option<Arc<VertexLit>>)>>,
    moments: Mutex<Option<(String, Option<Arc<Moments>>)>>,
    lamp_walks: Mutex<Option<(String, Option<Arc<crate::lampwalk::LampWalks>>)>>,
}

/// [E_t, E_u, E_v, E_w] per patch: the lights' moments at the simulated objects' patches
/// ([`crate::collimated`]).
pub type Moments = Vec<[Rgb; 4]>;

impl DirectCache {
    /// E at the patches under the lights `key`, traced by `trace` unless kept.
    pub(crate) fn patches<E>(
        &self,
        key: &str,
        trace: impl FnOnce() -> Result<Vec<Rgb>, E>,
    ) -> Result<Arc<Vec<Rgb>>, E> {
        kept_or(&self.patches, key, || trace().map(Arc::new))
    }

    /// The direct light at the vertices under `key`, traced by `trace` unless kept (`None`:
    /// no vertex takes it).
    pub(crate) fn vertices<E>(
        &self,
        key: &str,
        trace: impl FnOnce() -> Result<Option<VertexLit>, E>,
    ) -> Result<Option<Arc<VertexLit>>, E> {
        kept_or(&self.vertices, key, || trace().map(|v| v.map(Arc::new)))
    }

    /// The lights' moments at the simulated objects under `key` (the lights and which
    /// patches are simulated: not their absorption), made by `make` unless kept (`None`: no
    /// light enters them by its direction).
    pub(crate) fn moments<E>(
        &self,
        key: &str,
        make: impl FnOnce() -> Result<Option<Moments>, E>,
    ) -> Result<Option<Arc<Moments>>, E> {
        kept_or(&self.moments, key, || make().map(|v| v.map(Arc::new)))
    }

    /// The lamps' own beams walked into the simulated objects under `key` (the lights,
    /// which patches are simulated and the walks per lamp: not their absorption), made by
    /// `make` unless kept (`None`: no lamp lights a simulated object).
    pub(crate) fn lamp_walks(
        &self,
        key: &str,
        make: impl FnOnce() -> Result<Option<crate::lampwalk::LampWalks>, EngineError>,
    ) -> Result<Option<Arc<crate::lampwalk::LampWalks>>, EngineError> {
        // A walk stopped early is an error, never kept.
        kept_or(&self.lamp_walks, key, || Ok(make()?.map(Arc::new)))
    }
}

/// The value kept in `slot` under `key`, else `make`'s, kept there when it succeeds. The
/// lock is not held while `make` runs (concurrent relights of other lights go on).
fn kept_or<T: Clone, E>(
    slot: &Mutex<Option<(String, T)>>,
    key: &str,
    make: impl FnOnce() -> Result<T, E>,
) -> Result<T, E> {
    let lock = || slot.lock().unwrap_or_else(|p| p.into_inner());
    if let Some((k, v)) = lock().as_ref()
        && k == key
    {
        return Ok(v.clone());
    }
    let v = make()?;
    *lock() = Some((key.to_string(), v.clone()));
    Ok(v)
}

/// The last solutions per scene, so a relight that differs a little from the previous one
/// (a light moved, a translucency slider moved) starts from it. Keyed by materials and
/// components; the few most recent.
#[derive(Debug, Default)]
pub struct WarmCache(Mutex<Vec<(String, Arc<Warm>)>>);

/// One kept solution (one RGB system: 3 values per patch) with the products its solve
/// ended on, F x and K F x, when the CPU solved it ([`crate::solver::Solved`]): a solve
/// started from x takes them for its first residual check instead of computing it.
#[derive(Debug, Clone)]
pub struct Warm {
    pub x: Vec<f32>,
    pub fx: Option<Vec<f32>>,
    pub kfx: Option<Vec<f32>>,
    /// [`crate::solver::Solved::age`] of `fx` and `kfx`.
    pub age: u32,
    /// The answer this one replaced under the same key (same materials and components),
    /// without its own: with x it gives the last step of a light that keeps moving.
    pub prev: Option<Arc<Warm>>,
}

/// What a relight starts from (`WarmCache::history`): the kept answer, whether its K is
/// the relight's (the same key), and an answer kept before it with the same flag.
#[derive(Debug, Clone)]
pub struct Kept {
    pub last: Arc<Warm>,
    pub same: bool,
    pub before: Option<(Arc<Warm>, bool)>,
}

const WARM_ENTRIES: usize = 8;

impl WarmCache {
    /// What a relight under `key` starts from: the solution stored under `key` (same: its
    /// K is this one's) with the one it replaced; else the most recent one whose key ends
    /// with `suffix` (the same components under other materials: a translucency change
    /// starts from the previous scale's answer, which the solver iterates to its tolerance
    /// like any other start) with the one kept before it.
    pub(crate) fn history(&self, key: &str, suffix: &str) -> Option<Kept> {
        let cache = self.0.lock().ok()?;
        if let Some((_, last)) = cache.iter().find(|(k, _)| k == key) {
            return Some(Kept {
                last: last.clone(),
                same: true,
                before: last.prev.clone().map(|p| (p, true)),
            });
        }
        let mut latest = cache.iter().rev().filter(|(k, _)| k.ends_with(suffix));
        let last = latest.next()?.1.clone();
        let before = latest.next().map(|(_, v)| (v.clone(), false));
        Some(Kept {
            last,
            same: false,
            before,
        })
    }

    /// Keeps `value` under `key`; the answer it replaces becomes its `prev`.
    pub(crate) fn put(&self, key: String, mut value: Warm) {
        if let Ok(mut cache) = self.0.lock() {
            if let Some(at) = cache.iter().position(|(k, _)| *k == key) {
                // Moved, not copied, unless a relight still holds it; one level deep.
                let (_, old) = cache.remove(at);
                let mut old = Arc::try_unwrap(old).unwrap_or_else(|a| (*a).clone());
                old.prev = None;
                value.prev = Some(Arc::new(old));
            }
            if cache.len() >= WARM_ENTRIES {
                cache.remove(0);
            }
            cache.push((key, Arc::new(value)));
        }
    }
}
