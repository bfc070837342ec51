//! Where the heavy products of a relight run: the [`Backend`] trait, and the CPU's
//! ([`Cpu`]), which leaves everything to the engine's own CPU code.
//!
//! In: a scene ([`SceneRef`]), and per call the vectors of one relight batch, or a whole
//! relight ([`DeviceRelight`]: lights in, vertex colours out). Out: the product, the solve
//! or the colours when the backend did it, or "not here" (`false`, `None`), which
//! tells the engine to compute it on the CPU — so a backend may decline any call (a scene
//! that does not fit, a device error) and the answer is still computed. S for a
//! translucency change is built on the CPU; a change written in place (a slider) is left
//! to the backend's [`Backend::solve_materials`] first, and written on the CPU only when
//! it declines or a CPU stage needs S ([`crate::scene::Scene::cpu_s`]).
//!
//! A backend is made once by whoever owns the process (the server's `--backend`) and handed
//! to every scene it opens ([`crate::scene::Resources`]); there is no global backend,
//! so one process can hold a CPU and a GPU backend side by side.

use std::sync::Arc;

use translux_proto::api::Components;
use translux_proto::bundle::Bundle;
use translux_proto::csr::ValidCsr;
use translux_proto::light::Light;

use crate::linalg::Rgb;
use crate::smatrix::OverrideMaterials;
use crate::solver::{SolveParams, SolveStats};
use crate::sterms::STerms;
use crate::vertexrows::VertexRows;

/// What a backend sees of a scene ([`crate::scene::Scene::view`]): its id (named in logs,
/// a key of the device's copy with the bundle's checksums), its bundle, and S's radial
/// terms once the first translucency change (or its preparation) made them.
#[derive(Debug, Clone, Copy)]
pub struct SceneRef<'a> {
    pub id: &'a str,
    pub bundle: &'a Bundle,
    pub terms: Option<&'a STerms>,
}

/// Relights a backend may do whole, where the matrices are: for each set of `lights`
/// (point, spot and directional lamps, shadowed, and environment lights through the
/// bundle's visibility) the direct light at the patches and at the vertices, the transport
/// of `components` with the bundle's S, albedo and emission, and the vertex colours by
/// `rows` ([`crate::relight`] hands over only plans that need nothing else). Several sets
/// are a batch (concurrent requests), which a backend may solve together.
#[derive(Debug, Clone, Copy)]
pub struct DeviceRelight<'a> {
    pub lights: &'a [&'a [Light]],
    /// Per set of lights, its environments' radiance per direction bin of the bundle's
    /// visibility, Σ scale · L̄_k ([`crate::environment::bin_radiance_total`]); `None`
    /// without an environment light. The environment's E at patch i is Σ_k V_ik L̄_k, and
    /// the colour stage leaves it out of ρE at opaque vertices (it is part of the patches'
    /// smooth light there, as [`crate::vertexlight`]'s `at_patch` has it).
    pub environment: &'a [Option<Vec<Rgb>>],
    pub params: &'a SolveParams,
    /// The direct light of diffuse objects is left to a picture per pixel
    /// (`direct_at: pixel`): their opaque vertices leave it out, and each answer carries
    /// the luminance of the whole answer for the exposure.
    pub pixel: bool,
    /// The transport, with P = diag ρ (the bundle's `patch_albedo`):
    /// - `full`: B = Bₑ + S(E + F B), solved;
    /// - `subsurface_only`: B = Bₑ + S E, no solve;
    /// - `direct`: B = Bₑ + P E, no solve;
    /// - `interreflection_only`: B = Bₑ + P(E + F B), solved;
    /// - `heuristic_a`: B = Bₑ + S E + P F B, solved;
    /// - `heuristic_b`: B = Bₑ + S E + Y, Y = P F (Bₑ + P E) + P F Y solved.
    pub components: Components,
    /// The colour stage for the bundle's materials under `components`
    /// ([`crate::scene::Scene::vertex_rows`]).
    pub rows: &'a std::sync::Arc<VertexRows>,
}

/// Whether `components` solve a system (else B is Bₑ plus one product).
pub fn solves(components: Components) -> bool {
    !matches!(components, Components::Direct | Components::SubsurfaceOnly)
}

/// What a backend's whole relight gave: B/π per vertex (as [`crate::relight`]'s colour
/// stage makes it), the solve's stats and what it took on the device (for a relight solved
/// in a batch: the batch's submissions, and its share of the bytes).
#[derive(Debug, Clone)]
pub struct DeviceAnswer {
    pub radiance: Vec<Rgb>,
    /// With [`DeviceRelight::pixel`]: per vertex, the luminance of the whole answer (the
    /// direct term included), from which the exposure is taken.
    pub luminance: Option<Vec<f32>>,
    pub stats: SolveStats,
    /// Command submissions.
    pub submissions: u32,
    /// Bytes written to the device and read back.
    pub bytes_up: u64,
    pub bytes_down: u64,
}

/// The materials of a relight whose S a backend may write itself
/// ([`Backend::solve_materials`]): the overrides (their S on the CPU may not be written
/// yet), and S made on the CPU for a backend that holds no S of their layout yet (each
/// value times its column's factor; `None` when it cannot be made).
pub struct WithMaterials<'a> {
    pub materials: &'a Arc<OverrideMaterials>,
    pub cpu: &'a dyn Fn() -> Option<std::borrow::Cow<'a, ValidCsr<Rgb>>>,
}

impl std::fmt::Debug for WithMaterials<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WithMaterials")
            .field("materials", &self.materials.key)
            .finish_non_exhaustive()
    }
}

/// What a backend's solve with overridden materials gave ([`Backend::solve_materials`]).
#[derive(Debug, Clone)]
pub struct MaterialsAnswer {
    /// B per patch, `[patch][k·3]`.
    pub x: Vec<f32>,
    pub stats: SolveStats,
    /// Seconds spent writing S for the materials (0 when the backend held it).
    pub s_seconds: f64,
    pub submissions: u32,
    pub bytes_up: u64,
    pub bytes_down: u64,
}

/// A compute backend for the relight's products. Every method may decline.
pub trait Backend: Send + Sync + std::fmt::Debug {
    /// `cpu` or `gpu`, for stats and logs.
    fn name(&self) -> &'static str;

    /// Makes `scene` ready (uploads it) now rather than on its first relight; whether it is
    /// served by this backend.
    fn prepare(&self, scene: SceneRef<'_>) -> bool;

    /// y = (T − S) v for `k` right-hand sides (`[patch][k·3]`) with the bundle's stored T;
    /// `false` to leave it to the CPU.
    fn transfer_product(&self, scene: SceneRef<'_>, v: &[f32], k: usize, y: &mut [f32]) -> bool;

    /// Solves (I − S F) x = rhs for `k` right-hand sides with the bundle's S or `over`'s,
    /// warm-started from `warm`; `None` to leave it to the CPU.
    fn solve_rhs(
        &self,
        scene: SceneRef<'_>,
        over: Option<&Arc<OverrideMaterials>>,
        rhs: &[f32],
        k: usize,
        params: &SolveParams,
        warm: Option<&[f32]>,
    ) -> Option<(Vec<f32>, SolveStats)>;

    /// The whole relights of `job` for `scene` where the matrices are, one answer per set of
    /// lights in order; `None` to leave them to the engine's stages.
    fn relight(&self, scene: SceneRef<'_>, job: &DeviceRelight<'_>) -> Option<Vec<DeviceAnswer>>;

    /// Solves B = Bₑ + S(E + F B) for `k` right-hand sides (`sources`: E and Bₑ, each
    /// `[patch][k·3]`) with S of `with`'s materials, written where the backend keeps S (a
    /// translucency change's rows summed there from S's radial terms); `None` to leave S
    /// and the solve to the CPU.
    fn solve_materials(
        &self,
        scene: SceneRef<'_>,
        with: &WithMaterials<'_>,
        sources: (&[f32], &[f32]),
        k: usize,
        params: &SolveParams,
    ) -> Option<MaterialsAnswer>;
}

/// The CPU backend: declines every call, so the engine computes everything itself.
#[derive(Debug, Clone, Default)]
pub struct Cpu;

impl Backend for Cpu {
    fn name(&self) -> &'static str {
        "cpu"
    }

    fn prepare(&self, _scene: SceneRef<'_>) -> bool {
        false
    }

    fn transfer_product(
        &self,
        _scene: SceneRef<'_>,
        _v: &[f32],
        _k: usize,
        _y: &mut [f32],
    ) -> bool {
        false
    }

    fn solve_rhs(
        &self,
        _scene: SceneRef<'_>,
        _over: Option<&Arc<OverrideMaterials>>,
        _rhs: &[f32],
        _k: usize,
        _params: &SolveParams,
        _warm: Option<&[f32]>,
    ) -> Option<(Vec<f32>, SolveStats)> {
        None
    }

    fn relight(&self, _scene: SceneRef<'_>, _job: &DeviceRelight<'_>) -> Option<Vec<DeviceAnswer>> {
        None
    }

    fn solve_materials(
        &self,
        _scene: SceneRef<'_>,
        _with: &WithMaterials<'_>,
        _sources: (&[f32], &[f32]),
        _k: usize,
        _params: &SolveParams,
    ) -> Option<MaterialsAnswer> {
        None
    }
}
