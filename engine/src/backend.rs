//! Where the heavy products of a relight run: the [`Backend`] trait, and the CPU's
//! ([`Cpu`]), which leaves everything to the engine's own CPU code.
//!
//! In: a scene ([`SceneRef`]), and per call the vectors of one relight batch. Out: the product or the
//! solve when the backend did it, or "not here" (`false`, `None`, [`SBuild::Cpu`]), which
//! tells the engine to compute it on the CPU — so a backend may decline any call (a scene
//! that does not fit, a device error) and the answer is still computed.
//!
//! A backend is made once by whoever owns the process (the server's `--backend`) and handed
//! to every scene it opens ([`crate::scene::Resources`]); there is no global backend,
//! so one process can hold a CPU and a GPU backend side by side.

use std::sync::Arc;

use translux_proto::bundle::Bundle;
use translux_proto::scene::Material;

use crate::linalg::Rgb;
use translux_proto::csr::Csr;

use crate::smatrix::{OverrideMaterials, SError};
use crate::solver::{SolveParams, SolveStats};

/// What a backend sees of a scene ([`crate::scene::Scene::view`]): its id (named in logs,
/// a key of the device's copy with the bundle's checksums) and its bundle.
#[derive(Debug, Clone, Copy)]
pub struct SceneRef<'a> {
    pub id: &'a str,
    pub bundle: &'a Bundle,
}

/// Where S for a set of material overrides was built ([`Backend::rebuild_s`]).
#[derive(Debug)]
pub enum SBuild {
    /// On the device; its values, read back once, for the CPU's products.
    Device(Csr<Rgb>),
    /// Build it on the CPU; why, when the backend is not the CPU.
    Cpu(Option<String>),
}

/// What [`Backend::prepare_s`] made ready for a scene's translucency changes.
#[derive(Debug, Clone, PartialEq)]
pub enum SPrep {
    /// Changes rebuild S on the device: its S template is there, holding `bytes` of
    /// device memory.
    Device { bytes: u64 },
    /// Changes rebuild S on the CPU; why, when the backend is not the CPU.
    Cpu(Option<String>),
}

/// A compute backend for the relight's products. Every method may decline.
pub trait Backend: Send + Sync + std::fmt::Debug {
    /// `cpu` or `gpu`, for stats and logs.
    fn name(&self) -> &'static str;

    /// Makes `scene` ready (uploads it) now rather than on its first relight; whether it is
    /// served by this backend.
    fn prepare(&self, scene: SceneRef<'_>) -> bool;

    /// Makes now what the first [`Backend::rebuild_s`] of `scene` would otherwise make (a
    /// device's S template for the bundle's own materials), and says where translucency
    /// changes will rebuild S. The default (the CPU backend's): [`SPrep::Cpu`], nothing made.
    fn prepare_s(&self, _scene: SceneRef<'_>) -> Result<SPrep, SError> {
        Ok(SPrep::Cpu(None))
    }

    /// Rebuilds S for `overrides` (keyed by `key`, the overrides as JSON).
    fn rebuild_s(
        &self,
        scene: SceneRef<'_>,
        key: &str,
        overrides: &[(usize, Material)],
    ) -> Result<SBuild, SError>;

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

    fn rebuild_s(
        &self,
        _scene: SceneRef<'_>,
        _key: &str,
        _overrides: &[(usize, Material)],
    ) -> Result<SBuild, SError> {
        Ok(SBuild::Cpu(None))
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
}
