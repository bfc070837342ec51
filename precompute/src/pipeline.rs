//! The whole precompute: loaded scene in, verified bundle on disk out.
//!
//! Stages, in the order `run` calls them, each a function of this module: the scene's notes
//! and the settings checked (`check_settings`) → plan, patches and viewer mesh
//! (`Stages::patches`) → BVH (`Stages::bvh`) and a hierarchical F's cluster tree → the
//! memory budget (`check_memory`, which samples the F cut it estimates) → form
//! factors and environment visibility: all rows (`transport_rows`), one shard's rows into a
//! part (`shard_rows`) or the parts merged (`merged_rows`; [`crate::shard`]) → subsurface
//! (`Stages::subsurface`: walks, which objects trace on demand, distances, links, S) → T
//! (`Stages::transfer`) → write (`Stages::write`, its arrays from `bundle_arrays`).
//! Each long stage reports progress (a bar on a terminal, a line per stage otherwise), and
//! [`PrecomputeReport`] carries the summary the CLI prints.

use std::path::Path;
use std::time::Instant;

use glam::Vec3;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use rayon::prelude::*;
use thiserror::Error;
use translux_proto::bundle::{
    FORMAT, FORMAT_VERSION, FormFactorInfo, HierarchyInfo, Manifest, ObjectInfo, StageTime,
    SubsurfaceInfo, TransferInfo, arrays,
};
use translux_proto::csr::{Csr, CsrView};
use translux_proto::light::Camera;
use translux_proto::scene::Material;

use crate::bundle::{ArrayData, BundleWriteError, NamedArray, write_bundle};
use crate::distances::{self, DistanceError};
use crate::formfactor::{self, FormFactorParams};
use crate::hetero::{self, PatternFrame};
use crate::hierarchy::{self, HierarchyParams};
use crate::patch::{self, Density, Patches};
use crate::scene::LoadedScene;
use crate::shard::{PartReport, Shard, ShardRows, Split};
use crate::simulate::SceneWalks;
use crate::slinks::ReceiverCuts;
use crate::voxel::VoxelParams;
use translux_engine::hetero::MediaLen;
use translux_engine::inverse::Transfer;
use translux_engine::linkbound::LinkBound;
use translux_engine::raycast::Occluder;
use translux_engine::simulated::SimError;
use translux_engine::smatrix::{
    self, AssemblyReport, ObjectMaterial, SError, SParams, material_albedo_emission, patch_albedo,
};
use translux_engine::stop::Stop;

/// Patch target for scene files that name no density.
pub const DEFAULT_PATCHES: u64 = 10_000;
/// More patches than this are refused outright: the pair loop is O(N²).
pub const MAX_PATCHES: u64 = 400_000;

/// Settings of [`precompute`].
#[derive(Debug, Clone, Default)]
pub struct PrecomputeParams {
    /// Patch target; overrides the scene file's `patches`.
    pub patches: Option<u64>,
    /// Maximum patch edge (scene units); overrides the scene file's `patches`.
    pub max_edge: Option<f32>,
    pub form_factors: FormFactorParams,
    /// Hierarchical F̃ = C·P ([`crate::hierarchy`], the default) or dense F.
    pub transport: FormFactorMethod,
    pub subsurface: SParams,
    /// The voxel grid of the optical distances (stage 1 of S).
    pub voxels: VoxelParams,
    /// Refuse when the estimated peak memory exceeds this many bytes (default: 85% of the
    /// memory available now).
    pub memory_limit: Option<u64>,
    /// Draw progress bars / stage lines on stderr.
    pub progress: bool,
    /// Told each stage's progress and asked whether to stop (a server's precompute jobs).
    pub observer: Option<std::sync::Arc<dyn Observer>>,
    /// Also compute the transfer matrix T = (I − S F)⁻¹ S ([`translux_engine::inverse`]).
    pub inverse: bool,
    /// Per-patch environment visibility ([`translux_engine::envvis`]); `bins: None` skips it.
    pub environment: translux_engine::envvis::EnvVisParams,
    /// Hierarchical S ([`crate::slinks`]): far parts of each translucent object reach a
    /// receiver through whole cluster nodes. Needs the hierarchical F's tree. `None`: S is
    /// stored pair by pair.
    pub subsurface_links: Option<crate::slinks::SLinkParams>,
    /// Optical distances kept from earlier frames of an animation
    /// ([`crate::distances::DistanceCache`]; [`crate::sequence`] sets it).
    pub distance_cache: Option<std::sync::Arc<crate::distances::DistanceCache>>,
}

/// How F is computed and stored.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FormFactorMethod {
    /// One entry per visible patch pair (O(N²)): for validation and small scenes.
    Dense,
    /// A cluster tree and a light-independent cut per receiver ([`crate::hierarchy`]).
    Hierarchical(HierarchyParams),
}

/// Whether `--subsurface auto` (`translux-precompute`'s default, and the server's uploads')
/// stores a hierarchical S: it needs the hierarchical F's tree, and T (`inverse`) needs a
/// pairwise S.
pub fn hierarchical_s_by_default(transport: &FormFactorMethod, inverse: bool) -> bool {
    !inverse && matches!(transport, FormFactorMethod::Hierarchical(_))
}

impl Default for FormFactorMethod {
    /// Hierarchical, at the default accuracy.
    fn default() -> Self {
        Self::Hierarchical(HierarchyParams::default())
    }
}

impl FormFactorMethod {
    /// The CLI's name of it.
    pub fn name(&self) -> &'static str {
        match self {
            Self::Dense => "dense",
            Self::Hierarchical(_) => "hierarchical",
        }
    }
}

/// More patches than this are refused with a hierarchical F (its pass is O(N log N); the
/// limit keeps u32 column indices and the tree's memory far from their bounds).
pub const MAX_PATCHES_HIERARCHICAL: u64 = 4_000_000;

/// Watches a [`precompute`]: progress per stage, and a way to stop it.
pub trait Observer: Send + Sync + std::fmt::Debug {
    /// `stage` has done `done` of `total` units (called from many threads, often).
    fn progress(&self, stage: &str, done: u64, total: u64);
    /// `true` stops the precompute at the next check (before each stage and between
    /// form-factor rows) with [`PrecomputeError::Cancelled`]; nothing is written.
    fn cancelled(&self) -> bool {
        false
    }
    /// What the random walks of simulated objects read to stop (they run long between
    /// stage checks); it should fire when [`Observer::cancelled`] turns `true`.
    fn stop(&self) -> Stop {
        Stop::never()
    }
    /// A note or warning about the scene for whoever runs the precompute (an object turned
    /// outward or simplified, distances that look like a units mistake). Without an
    /// observer they go to stderr.
    fn note(&self, message: &str);
}

/// Tells `message` to the observer, or prints it on stderr when there is none (the CLI).
fn tell(params: &PrecomputeParams, message: &str) {
    match &params.observer {
        Some(o) => o.note(message),
        None => eprintln!("{message}"),
    }
}

/// Every stage a precompute reports to its observer, in order (`inverse T` only with
/// [`PrecomputeParams::inverse`]).
pub const STAGES: [&str; 7] = [
    "patches",
    "bvh",
    "form factors",
    "environment",
    "subsurface",
    "inverse T",
    "write bundle",
];

/// Reports the start of `stage` to the observer, or stops if it asks to.
fn stage_start(params: &PrecomputeParams, stage: &str) -> Result<(), PrecomputeError> {
    debug_assert!(STAGES.contains(&stage), "{stage} is not listed in STAGES");
    if let Some(o) = &params.observer {
        if o.cancelled() {
            return Err(PrecomputeError::Cancelled);
        }
        o.progress(stage, 0, 1);
    }
    Ok(())
}

/// What a precompute produced.
#[derive(Debug, Clone)]
pub struct PrecomputeReport {
    pub patch_count: usize,
    pub vertex_count: usize,
    pub occluder_count: usize,
    pub nnz_f: u64,
    pub bundle_bytes: u64,
    pub form_factors: FormFactorInfo,
    /// The tree and links of a hierarchical F.
    pub hierarchy: Option<HierarchyInfo>,
    pub subsurface: SubsurfaceInfo,
    /// The transfer matrix's storage and errors (with `inverse`).
    pub transfer: Option<TransferInfo>,
    pub stages: Vec<StageTime>,
    /// Occlusion rays per second during the form-factor stage.
    pub rays_per_second: f64,
    /// Estimated peak memory before the form-factor stage (bytes).
    pub memory_estimate: u64,
    /// Peak resident memory of the process so far (bytes), where the OS tells.
    pub peak_rss: Option<u64>,
}

/// Why a precompute stopped.
#[derive(Debug, Error)]
pub enum PrecomputeError {
    #[error("--patches 0: a scene needs at least one patch")]
    ZeroPatches,
    #[error("max_edge must be finite and > 0, got {0}")]
    BadMaxEdge(f32),
    #[error(
        "{requested} patches is too many: the form-factor pass is O(N²) (~{pairs:.1e} pairs); \
         the limit is {MAX_PATCHES} with --transport dense ({MAX_PATCHES_HIERARCHICAL} with \
         --transport hierarchical)"
    )]
    TooManyPatches { requested: u64, pairs: f64 },
    #[error(
        "{requested} patches is too many: the limit is {MAX_PATCHES_HIERARCHICAL} with \
         --transport hierarchical"
    )]
    TooManyPatchesHierarchical { requested: u64 },
    #[error("{0}")]
    BadHierarchy(String),
    #[error(
        "the subsurface stage would need about {} (~{paths:.2e} stored optical paths in \
         {object:?}, every patch pair within {radius:.4} scene units, {bytes_each} bytes each \
         while building, with F), more than the {} allowed; use fewer patches (simplify_to \
         for a scanned mesh), a less translucent profile, or --subsurface hierarchical (which \
         traces only the paths its cut uses)",
        human_bytes(*estimate),
        human_bytes(*limit)
    )]
    SubsurfaceOutOfMemory {
        object: String,
        paths: u64,
        radius: f32,
        bytes_each: u64,
        estimate: u64,
        limit: u64,
    },
    #[error(
        "{patches} patches would need about {} (F: ~{per_patch:.0} entries per patch, from \
         {how}), more than the {} allowed; {}",
        human_bytes(*estimate),
        human_bytes(*limit),
        fits_hint(*fits)
    )]
    OutOfMemory {
        patches: u64,
        per_patch: f64,
        how: &'static str,
        estimate: u64,
        limit: u64,
        /// About how many patches would fit (0: not even a hundred).
        fits: u64,
    },
    #[error("the scene has no triangles")]
    Empty,
    #[error(transparent)]
    Subsurface(#[from] SError),
    #[error(transparent)]
    Distances(#[from] DistanceError),
    #[error("--inverse: {0}")]
    Inverse(#[from] translux_engine::inverse::InverseError),
    #[error(transparent)]
    Write(#[from] BundleWriteError),
    #[error("cancelled")]
    Cancelled,
    /// A simulated object that walks cannot run in (an open mesh, say).
    #[error("{0}")]
    Simulation(String),
    /// A shard that cannot be written or parts that cannot be merged ([`crate::shard`]).
    #[error("{0}")]
    Shard(String),
}

/// Where the media of the scene's heterogeneous objects are: each object's pattern frame
/// (from its transform) and each patch's medium ([`hetero::patch_media`]; by OBJ material,
/// the medium of the source face the patch was cut from). `h` is the subdivision edge.
pub fn scene_media(scene: &LoadedScene, patches: &Patches, h: f32) -> distances::SceneMedia {
    let frames: Vec<PatternFrame> = scene
        .file
        .objects
        .iter()
        .map(|o| PatternFrame::of(o.transform.as_ref()))
        .collect();
    let mut patch_material = vec![0u32; patches.len()];
    for (k, (o, range)) in scene.objects.iter().zip(&patches.object_ranges).enumerate() {
        if !matches!(o.material, Material::Heterogeneous { .. }) {
            continue;
        }
        // Source face media, repeated for the n² patches each face is split into.
        let face_media: Option<Vec<u32>> = o.face_material.as_ref().map(|f| {
            o.triangles
                .iter()
                .zip(f)
                .flat_map(|(t, &m)| std::iter::repeat_n(m, patch::split_count(t, h)))
                .collect()
        });
        let frame = frames.get(k).copied().unwrap_or_default();
        let m = hetero::patch_media(
            &o.material,
            frame,
            &patches.centroid[range.clone()],
            &patches.normal[range.clone()],
            face_media.as_deref(),
        );
        patch_material[range.clone()].copy_from_slice(&m);
    }
    distances::SceneMedia {
        patch_material,
        frames,
    }
}

fn stage_bar(progress: bool, len: u64, name: &str) -> ProgressBar {
    let target = if progress {
        ProgressDrawTarget::stderr()
    } else {
        ProgressDrawTarget::hidden()
    };
    let bar = ProgressBar::with_draw_target(Some(len), target);
    if let Ok(style) = ProgressStyle::with_template(
        "{prefix:>14} [{elapsed_precise}] {wide_bar} {percent:>3}% eta {eta}",
    ) {
        bar.set_style(style);
    }
    bar.set_prefix(name.to_string());
    if progress && bar.is_hidden() {
        // Not a terminal: one line per stage instead of a bar.
        eprintln!("{name}: started");
    }
    bar
}

fn finish(bar: ProgressBar, progress: bool, name: &str, t: Instant, stages: &mut Vec<StageTime>) {
    let seconds = t.elapsed().as_secs_f64();
    if progress && bar.is_hidden() {
        eprintln!("{name}: done in {seconds:.2} s");
    }
    bar.finish_and_clear();
    stages.push(StageTime {
        stage: name.to_string(),
        seconds,
    });
}

/// What an out-of-memory refusal suggests: the patch count that would fit, or a larger
/// limit.
fn fits_hint(fits: u64) -> String {
    if fits > 0 {
        format!("about {fits} patches would fit (--patches {fits}), or raise --max-memory-gib")
    } else {
        "not even a hundred patches would fit; raise --max-memory-gib".into()
    }
}

/// `1.5 GiB`, `12.0 MiB`, `512 B`.
pub fn human_bytes(b: u64) -> String {
    const UNITS: [&str; 4] = ["KiB", "MiB", "GiB", "TiB"];
    if b < 1024 {
        return format!("{b} B");
    }
    let mut v = b as f64 / 1024.0;
    let mut u = 0;
    while v >= 1024.0 && u + 1 < UNITS.len() {
        v /= 1024.0;
        u += 1;
    }
    format!("{v:.1} {}", UNITS[u])
}

/// Bytes of memory available now (Linux `MemAvailable`), if known.
pub fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Resident set size of this process now (Linux `VmRSS`), if known.
pub fn resident_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = text.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Peak resident set size of this process (Linux `VmHWM`), if known.
pub fn peak_rss() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = text.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Estimates nnz(F) from the orientation cull alone on up to 256 evenly spaced rows (an
/// upper bound: occlusion only removes entries).
pub fn estimate_nnz(p: &Patches) -> f64 {
    let n = p.len();
    if n < 2 {
        return 0.0;
    }
    let rows = n.min(256);
    let eps = 1e-9;
    let front = |a: usize, b: usize| {
        p.corners[b]
            .iter()
            .any(|v| p.normal[a].dot(*v - p.centroid[a]) > eps)
    };
    let seen: u64 = (0..rows)
        .into_par_iter()
        .map(|k| {
            let i = k * n / rows;
            (0..n)
                .filter(|&j| j != i && front(i, j) && front(j, i))
                .count() as u64
        })
        .sum();
    seen as f64 / rows as f64 * n as f64
}

fn default_camera(p: &Patches) -> Camera {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for c in &p.corners {
        for v in c {
            lo = lo.min(*v);
            hi = hi.max(*v);
        }
    }
    let centre = (lo + hi) * 0.5;
    let radius = ((hi - lo).length() * 0.5).max(1e-3);
    // Far enough for a 40° vertical field of view to hold the bounding sphere.
    let dist = radius / (20f32.to_radians().sin());
    Camera {
        position: (centre + Vec3::new(0.0, 0.25 * radius, dist)).to_array(),
        target: centre.to_array(),
        up: [0.0, 1.0, 0.0],
        fov_deg: 40.0,
    }
}

/// The patch density a precompute uses: `patches` (the command line's or an upload's), else
/// `max_edge`, else the scene file's `patches`, else [`DEFAULT_PATCHES`]. The patch count
/// it gives is `patch::plan(…, density).1`: never fewer patches than triangles.
pub fn density_for(
    patches: Option<u64>,
    max_edge: Option<f32>,
    file: Option<translux_proto::scene::PatchDensity>,
) -> Density {
    match (patches, max_edge, file) {
        (Some(n), _, _) => Density::Target(n),
        (None, Some(e), _) => Density::MaxEdge(e),
        (None, None, Some(d)) => match (d.target, d.max_edge) {
            (Some(t), _) => Density::Target(t),
            (None, Some(e)) => Density::MaxEdge(e),
            (None, None) => Density::Target(DEFAULT_PATCHES),
        },
        (None, None, None) => Density::Target(DEFAULT_PATCHES),
    }
}

/// Runs every stage and writes the bundle to `out` (atomically).
pub fn precompute(
    scene: &LoadedScene,
    out: &Path,
    params: &PrecomputeParams,
) -> Result<PrecomputeReport, PrecomputeError> {
    match run(scene, out, params, Split::Whole)? {
        Outcome::Bundle(report) => Ok(*report),
        Outcome::Part(_) => unreachable!("a whole precompute writes a bundle"),
    }
}

/// Computes shard `shard` of the receiver rows (form factors and environment visibility)
/// into `out`'s parts folder ([`crate::shard`]); a shard already finished for the same plan
/// is left as it is (`computed: false`).
pub fn precompute_shard(
    scene: &LoadedScene,
    out: &Path,
    params: &PrecomputeParams,
    shard: Shard,
) -> Result<PartReport, PrecomputeError> {
    match run(scene, out, params, Split::Shard(shard))? {
        Outcome::Part(report) => Ok(report),
        Outcome::Bundle(_) => unreachable!("a shard writes a part"),
    }
}

/// Puts the `count` parts in `out`'s parts folder together (each checked against this
/// run's plan), runs the remaining stages and writes the bundle (atomically); the parts
/// folder is removed after. The bundle's arrays are the bytes [`precompute`] writes.
pub fn precompute_merge(
    scene: &LoadedScene,
    out: &Path,
    params: &PrecomputeParams,
    count: u32,
) -> Result<PrecomputeReport, PrecomputeError> {
    let report = match run(scene, out, params, Split::Merge(count))? {
        Outcome::Bundle(report) => *report,
        Outcome::Part(_) => unreachable!("a merge writes a bundle"),
    };
    crate::shard::remove_parts(out);
    Ok(report)
}

/// What one run of the stages made.
enum Outcome {
    Bundle(Box<PrecomputeReport>),
    Part(PartReport),
}

/// The stages, whole, for one shard, or from the parts ([`Split`]): notes and checks,
/// patches, the memory budget, BVH, the receiver rows (where a shard stops), subsurface, T
/// and the bundle.
fn run(
    scene: &LoadedScene,
    out: &Path,
    params: &PrecomputeParams,
    split: Split,
) -> Result<Outcome, PrecomputeError> {
    let mut stages = Stages {
        scene,
        params,
        times: Vec::new(),
    };
    tell_scene_notes(scene, params);
    let density = check_settings(scene, params, split)?;
    let sources = source_triangles(scene)?;
    let patched = stages.patches(sources, density)?;
    let materials = object_materials(scene, &patched.patches);
    let (occluder_tris, occ) = stages.bvh(&patched.sources)?;
    // A hierarchical F's cluster tree, built once: the memory estimate samples its cut.
    let tree = matches!(params.transport, FormFactorMethod::Hierarchical(_))
        .then(|| hierarchy::ClusterTree::build(&patched.patches));
    let budget = check_memory(
        scene,
        params,
        &patched.patches,
        &materials,
        (&occ, tree.as_ref()),
    )?;

    // Form factors and environment visibility: every receiver's row, one shard's, or the
    // parts' put together.
    let patches = &patched.patches;
    let rows = match split {
        Split::Whole => transport_rows(patches, &occ, tree, params, &mut stages.times)?,
        Split::Shard(shard) => {
            let tree = tree.expect("check_settings refuses a split of a dense F");
            let plan = plan_of(scene, patches, &occluder_tris, &tree, params);
            let subsurface = SubsurfaceInputs {
                patched: &patched,
                materials: &materials,
                paths: &budget.paths,
            };
            return shard_rows(scene, &subsurface, &occ, params, out, (shard, plan, &tree))
                .map(Outcome::Part);
        }
        Split::Merge(count) => {
            let tree = tree.expect("check_settings refuses a split of a dense F");
            let plan = plan_of(scene, patches, &occluder_tris, &tree, params);
            merged_rows(
                scene,
                patches,
                params,
                out,
                (count, plan, tree),
                &mut stages.times,
            )?
        }
    };

    let tree = rows.tree.as_ref().map(|(t, _, _)| t);
    let subsurface =
        stages.subsurface(&patched, &materials, &budget, (tree, rows.cuts.as_ref()))?;
    let transfer = stages.transfer(&patched, &occ, &rows, &subsurface.smat, budget.limit)?;
    let made = Made {
        patched,
        occluder_tris,
        rows,
        subsurface,
        transfer,
    };
    let report = stages.write(out, made, budget.memory_estimate)?;
    Ok(Outcome::Bundle(Box::new(report)))
}

/// Tells the notes the scene's loading left on its objects (turned outward, simplified).
fn tell_scene_notes(scene: &LoadedScene, params: &PrecomputeParams) {
    for (k, o) in scene.objects.iter().enumerate() {
        for note in o.orientation_notes.iter().chain(&o.notes) {
            tell(params, &format!("note: objects[{k}] {:?}: {note}", o.name));
        }
        let loaded = o.triangles.len() + o.dropped_degenerate;
        if o.source_triangles > loaded {
            tell(
                params,
                &format!(
                    "note: objects[{k}] {:?}: simplified from {} to {} triangles (simplify_to)",
                    o.name, o.source_triangles, loaded
                ),
            );
        }
    }
}

/// Checks the scene and the settings before any work: simulated objects' meshes, the patch
/// density, the split, the hierarchical F and S settings and the patch target. Out: the
/// patch density.
fn check_settings(
    scene: &LoadedScene,
    params: &PrecomputeParams,
    split: Split,
) -> Result<Density, PrecomputeError> {
    // Simulated objects need closed meshes facing out: refused before any work.
    crate::simulate::check_meshes(
        scene
            .objects
            .iter()
            .map(|o| (o.name.as_str(), &o.material, o.triangles.as_slice())),
    )
    .map_err(PrecomputeError::Simulation)?;

    // Plan: density and the patch count it gives, checked before anything big is made.
    if params.patches == Some(0) {
        return Err(PrecomputeError::ZeroPatches);
    }
    if split != Split::Whole && params.transport == FormFactorMethod::Dense {
        return Err(PrecomputeError::Shard(
            "--shard and --merge split the hierarchical F's receiver rows; --transport dense \
             computes F pair by pair and runs on one box"
                .into(),
        ));
    }
    let density = density_for(params.patches, params.max_edge, scene.file.patches);
    if let Density::MaxEdge(e) = density
        && !(e.is_finite() && e > 0.0)
    {
        return Err(PrecomputeError::BadMaxEdge(e));
    }
    check_hierarchical_settings(params)?;
    if split != Split::Whole
        && matches!(params.transport, FormFactorMethod::Hierarchical(h) if h.two_sided)
    {
        return Err(PrecomputeError::Shard(
            "--shard and --merge split the one-sided F's receiver rows; --links two-sided \
             links whole clusters on both sides and runs on one box"
                .into(),
        ));
    }
    if let Density::Target(t) = density
        && let Some(e) = too_many(params, t)
    {
        return Err(e);
    }
    Ok(density)
}

/// Checks the settings of a hierarchical S (its own, and that it has a hierarchical F and
/// no T) and of a hierarchical F (its own, and no threshold).
fn check_hierarchical_settings(params: &PrecomputeParams) -> Result<(), PrecomputeError> {
    if let Some(sl) = &params.subsurface_links {
        sl.check().map_err(PrecomputeError::BadHierarchy)?;
        if params.transport == FormFactorMethod::Dense {
            return Err(PrecomputeError::BadHierarchy(
                "--subsurface hierarchical links S to the cluster tree of the hierarchical \
                 F; it cannot be used with --transport dense"
                    .into(),
            ));
        }
        if params.inverse {
            return Err(PrecomputeError::BadHierarchy(
                "--inverse needs a pairwise S (T = (I - S F)^-1 S is dense anyway); leave out \
                 --subsurface hierarchical"
                    .into(),
            ));
        }
    }
    if let FormFactorMethod::Hierarchical(h) = &params.transport {
        h.check().map_err(PrecomputeError::BadHierarchy)?;
        if params.form_factors.threshold > 0.0 {
            return Err(PrecomputeError::BadHierarchy(
                "a threshold drops entries of a dense F; a hierarchical F is bounded by its \
                 accuracy instead"
                    .into(),
            ));
        }
    }
    Ok(())
}

/// The refusal of `requested` patches, when that is more than the F method allows.
fn too_many(params: &PrecomputeParams, requested: u64) -> Option<PrecomputeError> {
    match params.transport {
        FormFactorMethod::Dense if requested > MAX_PATCHES => {
            Some(PrecomputeError::TooManyPatches {
                requested,
                pairs: (requested as f64).powi(2) / 2.0,
            })
        }
        FormFactorMethod::Hierarchical(_) if requested > MAX_PATCHES_HIERARCHICAL => {
            Some(PrecomputeError::TooManyPatchesHierarchical { requested })
        }
        _ => None,
    }
}

/// Each object's source triangles, in object order; a scene without any is refused.
fn source_triangles(scene: &LoadedScene) -> Result<Vec<&[[Vec3; 3]]>, PrecomputeError> {
    let sources: Vec<&[[Vec3; 3]]> = scene
        .objects
        .iter()
        .map(|o| o.triangles.as_slice())
        .collect();
    if sources.iter().all(|s| s.is_empty()) {
        return Err(PrecomputeError::Empty);
    }
    Ok(sources)
}

/// Each object's name, material and patch range, as the memory check and the subsurface
/// stage read them.
fn object_materials<'a>(scene: &'a LoadedScene, patches: &Patches) -> Vec<ObjectMaterial<'a>> {
    scene
        .objects
        .iter()
        .zip(&patches.object_ranges)
        .map(|(o, r)| ObjectMaterial {
            name: &o.name,
            material: &o.material,
            patches: r.clone(),
        })
        .collect()
}

/// The scene cut into patches: each object's source triangles, the subdivision edge, the
/// patches and the viewer's mesh of them.
struct Patched<'a> {
    sources: Vec<&'a [[Vec3; 3]]>,
    h: f32,
    patches: Patches,
    mesh: patch::ViewerMesh,
}

/// The memory a run may use and what the checks before F estimated.
struct Budget {
    /// Bytes the run may use: `memory_limit`, else 85% of the memory available now.
    limit: u64,
    /// The estimated peak: F while it is built, or the subsurface stage where larger.
    memory_estimate: u64,
    /// Bytes held through the subsurface stage besides its paths: what F leaves resident
    /// ([`MemoryModel::f_resident`]) and the voxel grids ([`voxel_grid_bytes`]).
    held: u64,
    /// Per translucent object: its name, the paths a pairwise S stores (an estimate, an
    /// upper bound) and their radius ([`distances::estimate_paths`]).
    paths: Vec<(String, u64, f32)>,
}

/// Estimates the peak memory of F, of T (with `inverse`) and of the subsurface stage, and
/// refuses a run that would exceed the limit before anything big is allocated. Out: the
/// budget the later stages keep to.
fn check_memory(
    scene: &LoadedScene,
    params: &PrecomputeParams,
    patches: &Patches,
    materials: &[ObjectMaterial<'_>],
    (occ, tree): (&Occluder, Option<&hierarchy::ClusterTree>),
) -> Result<Budget, PrecomputeError> {
    let f = estimate_f(patches, occ, tree, params);
    let n = patches.len() as u64;
    let held = MemoryModel::of(params);
    let memory_estimate = held.f_peak(n, f.nnz);
    let limit = params
        .memory_limit
        .or_else(|| available_memory().map(|a| (a as f64 * 0.85) as u64))
        .unwrap_or(u64::MAX);
    // F and what every stage holds: refused with the patch count that would fit.
    if memory_estimate > limit {
        return Err(PrecomputeError::OutOfMemory {
            patches: n,
            per_patch: f.per_patch(n),
            how: f.how,
            estimate: memory_estimate,
            limit,
            fits: held.patches_that_fit(n, &f, limit),
        });
    }
    // The dense LU of the inverse comes after F is built and dominates: refuse it up front.
    if params.inverse {
        let need = translux_engine::inverse::memory_estimate(n) + held.f_resident(n, f.nnz);
        if need > limit {
            return Err(
                translux_engine::inverse::InverseError::OutOfMemory { n, need, limit }.into(),
            );
        }
    }
    // The subsurface stage comes after F (which it keeps) and can outgrow it: a large
    // translucent object stores every path within its profile's radius. Refused up front.
    let paths = distances::estimate_paths(
        &patches.centroid,
        materials,
        scene.file.unit_mm,
        &params.subsurface,
    )?;
    let f_kept = held.f_resident(n, f.nnz);
    let held_paths = held_paths(params, materials, &paths);
    let path_bytes: u64 = held_paths
        .iter()
        .map(|p| p.paths.saturating_mul(p.bytes_each))
        .fold(0, u64::saturating_add);
    let grids = voxel_grid_bytes(scene, params, materials, &paths);
    let subsurface_estimate = f_kept.saturating_add(path_bytes).saturating_add(grids);
    if subsurface_estimate > limit {
        let most = held_paths
            .iter()
            .max_by_key(|p| p.paths.saturating_mul(p.bytes_each))
            .cloned()
            .unwrap_or_default();
        return Err(PrecomputeError::SubsurfaceOutOfMemory {
            object: most.name,
            paths: most.paths,
            radius: most.radius,
            bytes_each: most.bytes_each,
            estimate: subsurface_estimate,
            limit,
        });
    }
    Ok(Budget {
        memory_estimate: memory_estimate.max(subsurface_estimate),
        limit,
        held: f_kept.saturating_add(grids),
        paths,
    })
}

/// F's stored entries as estimated before it is built, and how.
#[derive(Debug, Clone, Copy)]
struct FEstimate {
    nnz: f64,
    /// How entries per patch grow with the patch count at this scene's density:
    /// entries per patch ∝ N^growth (1 for dense F).
    growth: f64,
    how: &'static str,
}

impl FEstimate {
    fn per_patch(&self, n: u64) -> f64 {
        self.nnz / n.max(1) as f64
    }
}

/// Receivers whose one-sided cut the memory estimate makes ([`hierarchy::sample_entries`]):
/// a sixteenth of the patches, at least 64 and at most 1,024 (4% of the F stage at 25k
/// patches, a few seconds at a million, where the mean's standard error is about 3%).
fn sampled_receivers(n: usize) -> usize {
    (n / 16).clamp(64, 1024)
}

/// The two-sided cut's entries against the one-sided cut's at the same accuracy, at most,
/// as measured (docs/hierarchy.md: 1.11 on the Cornell box at 25k, 0.73 in the furnished
/// room at 50k), with room.
const TWO_SIDED_ENTRIES_RATIO: f64 = 1.25;

/// How entries per patch of the hierarchical cut grow with the patch count, for the
/// refusal's "would fit": as N^0.1, below every growth measured (the Cornell box: 376 →
/// 484 from 6k to 25k, N^0.18, and N^0.14 from 19k to 40k; the furnished room: 485 →
/// 1,579 from 6k to 50k, N^0.56; `bench/results/links-2026-12-06.md`). Going down, the
/// smaller exponent is the cautious one: fewer patches keep more of their entries.
const HIERARCHICAL_GROWTH: f64 = 0.1;

/// nnz(F) before F is built: dense F from the orientation cull on sampled rows (an upper
/// bound), a hierarchical F from its cut made for [`sampled_receivers`] receivers (their
/// mean plus three standard errors; two-sided, times [`TWO_SIDED_ENTRIES_RATIO`]).
fn estimate_f(
    patches: &Patches,
    occ: &Occluder,
    tree: Option<&hierarchy::ClusterTree>,
    params: &PrecomputeParams,
) -> FEstimate {
    let n = patches.len() as f64;
    match (&params.transport, tree) {
        (FormFactorMethod::Hierarchical(hp), Some(tree)) => {
            let cut = hierarchy::sample_entries(
                patches,
                occ,
                &params.form_factors,
                hp,
                tree,
                sampled_receivers(patches.len()),
            );
            let one_sided = (cut.mean + 3.0 * cut.std_error) * n;
            let (nnz, how) = if hp.two_sided {
                (
                    one_sided * TWO_SIDED_ENTRIES_RATIO,
                    "the one-sided cut of sampled receivers, with room for the two-sided one",
                )
            } else {
                (one_sided, "the cut of sampled receivers")
            };
            FEstimate {
                nnz,
                growth: HIERARCHICAL_GROWTH,
                how,
            }
        }
        _ => FEstimate {
            nnz: estimate_nnz(patches),
            growth: 1.0,
            how: "the pairs facing each other, an upper bound",
        },
    }
}

/// What a run holds besides F and S, and what F costs while built and once kept: the
/// memory estimate's model (`docs/commands.md`, *Memory*).
#[derive(Debug, Clone, Copy)]
struct MemoryModel {
    /// Bytes per stored entry of F while it is built.
    build_per_nnz: u64,
    /// Bytes per patch of the environment visibility (f16), and of the run of rows traced
    /// at once (f32, `translux_engine::envvis::stage`).
    env_kept: u64,
    env_run: u64,
}

/// Bytes per stored non-zero of a dense F while building: the final CSR (col 4 + val 4),
/// the upper triangle as computed (12 bytes per pair = 6 per non-zero) and the transposed
/// lower half (8 bytes per lower entry = 4 per non-zero).
const BUILD_BYTES_PER_NNZ: u64 = 18;

/// Bytes per stored entry of a hierarchical F while built: each receiver's entries (8
/// bytes) and the block they are put together into (8), with room (measured 17.0 on the
/// diffuse Cornell box from 25k to 100k patches, `bench/results/memory-estimate-2026-12-07.md`).
const HIERARCHICAL_BUILD_BYTES_PER_NNZ: u64 = 18;
/// The same two-sided: each receiver's row, set by its visit, then the block (measured 19.5
/// at 25k).
const TWO_SIDED_BUILD_BYTES_PER_NNZ: u64 = 22;

/// Bytes per patch held through every stage besides F, S and the environment visibility:
/// the patches (72), the viewer mesh (up to 84), the cluster
/// tree (about 110) and F's row pointers and per-patch arrays, with room (measured about
/// 106 with the process's own on the Cornell box's simple mesh).
const PATCH_BYTES: u64 = 400;

/// Rows of the environment visibility traced at once (`translux_engine::envvis::stage`).
const ENV_RUN_ROWS: u64 = 8192;

impl MemoryModel {
    fn of(params: &PrecomputeParams) -> MemoryModel {
        let bins = params
            .environment
            .bins
            .map_or(0, |b| u64::from(b.rows) * u64::from(b.cols));
        let build_per_nnz = match params.transport {
            FormFactorMethod::Dense => BUILD_BYTES_PER_NNZ,
            FormFactorMethod::Hierarchical(h) if h.two_sided => TWO_SIDED_BUILD_BYTES_PER_NNZ,
            FormFactorMethod::Hierarchical(_) => HIERARCHICAL_BUILD_BYTES_PER_NNZ,
        };
        MemoryModel {
            build_per_nnz,
            env_kept: bins * 2,
            env_run: bins * 4,
        }
    }

    /// What the stages after F start from: F's build counted whole, the allocator keeping
    /// most of what F's rows held when they are freed (measured: 97 of the F stage's 105
    /// MiB still resident after it, at 16k patches), with what every stage holds and the
    /// environment visibility kept beside it.
    fn f_resident(&self, n: u64, nnz: f64) -> u64 {
        (nnz * self.build_per_nnz as f64) as u64 + n * (PATCH_BYTES + self.env_kept)
    }

    /// The F and environment stages' peak: [`MemoryModel::f_resident`] and the run of
    /// environment rows traced at once.
    fn f_peak(&self, n: u64, nnz: f64) -> u64 {
        self.f_resident(n, nnz) + n.min(ENV_RUN_ROWS) * self.env_run
    }

    /// The most patches, about, whose F peak fits in `limit` at this scene's density of
    /// entries ([`FEstimate::growth`]), rounded down to two significant figures; 0 when
    /// not even a hundred would.
    fn patches_that_fit(&self, n: u64, f: &FEstimate, limit: u64) -> u64 {
        let per_patch = f.per_patch(n);
        let peak = |m: f64| -> f64 {
            let nnz = m * per_patch * (m / n as f64).powf(f.growth);
            self.f_peak(m as u64, nnz) as f64
        };
        let (mut lo, mut hi) = (0.0f64, n as f64);
        for _ in 0..60 {
            let mid = 0.5 * (lo + hi);
            if peak(mid) <= limit as f64 {
                lo = mid
            } else {
                hi = mid
            }
        }
        round_down_2(lo as u64).filter(|&m| m >= 100).unwrap_or(0)
    }
}

/// `x` rounded down to two significant figures (None for 0).
fn round_down_2(x: u64) -> Option<u64> {
    if x == 0 {
        return None;
    }
    let digits = x.ilog10();
    let unit = 10u64.pow(digits.saturating_sub(1));
    Some(x / unit * unit)
}

/// Bytes per voxel of an object's grid while its paths are traced: which voxels are
/// inside (1) and the same on the grid of twice the edge (1/8), with room.
const GRID_BYTES_PER_VOXEL: u64 = 2;

/// Bytes per voxel and worker thread: a Dijkstra run's distances and target slots (4 + 4
/// bytes a voxel, `voxel::paths::Scratch`), on the grid and on the coarse one (an eighth
/// of that), with room. Each object keeps one per thread while it is traced.
const SCRATCH_BYTES_PER_VOXEL: u64 = 10;

/// The voxel grids the subsurface stage holds at its peak, which no patch count scales:
/// an object whose optical paths bend through its interior (not convex, or media set per
/// patch) gets a grid of up to `VoxelParams::max_voxels` cells (2 M), and each worker
/// thread's Dijkstra state over it (about 42 MiB a grid on 2 threads). A heterogeneous
/// object counts one whatever its shape (an upper bound: a convex one laid out by a
/// pattern takes straight paths). Objects whose
/// paths a hierarchical S traces on demand keep theirs until S is cut (summed); the
/// others are traced one after another (the largest counts). `paths` names the objects
/// S is made for ([`distances::estimate_paths`]).
fn voxel_grid_bytes(
    scene: &LoadedScene,
    params: &PrecomputeParams,
    materials: &[ObjectMaterial<'_>],
    paths: &[(String, u64, f32)],
) -> u64 {
    let threads = rayon::current_num_threads() as u64;
    let grid = params.voxels.max_voxels as u64
        * (GRID_BYTES_PER_VOXEL + threads * SCRATCH_BYTES_PER_VOXEL);
    let on_demand = params
        .subsurface_links
        .as_ref()
        .is_some_and(|sl| sl.trace != crate::slinks::Trace::All)
        && matches!(params.transport, FormFactorMethod::Hierarchical(_));
    let (mut held, mut one_at_a_time) = (0u64, 0u64);
    // `materials` is made from `scene.objects`, one per object in order.
    for (o, source) in materials.iter().zip(&scene.objects) {
        if !paths.iter().any(|p| p.0 == o.name) {
            continue;
        }
        let translucent = matches!(o.material, Material::Translucent { .. });
        // The only other material with paths is a heterogeneous one: media by patch always
        // take the voxel route, a pattern's only where the object is not convex (counted
        // as if it never were).
        let bends = !translucent
            || params.voxels.force_voxels
            || !crate::voxel::is_convex(&source.triangles, params.voxels.convex_tolerance);
        if !bends {
            continue;
        }
        if on_demand && translucent {
            held = held.saturating_add(grid);
        } else {
            one_at_a_time = one_at_a_time.max(grid);
        }
    }
    held.saturating_add(one_at_a_time)
}

/// What one object holds at the subsurface stage's peak ([`held_paths`]).
#[derive(Debug, Clone, Default)]
struct HeldPaths {
    name: String,
    /// Its stored paths (pairs, or a cut's direct pairs and links).
    paths: u64,
    /// Their radius (scene units).
    radius: f32,
    /// Bytes each holds while S is built.
    bytes_each: u64,
}

/// Bytes an entry of a hierarchical S traced on demand holds while S is built, with room:
/// its optical distance and spread, the cut's lists, S's value and column, and the
/// allocator's share (measured 92 on the Cornell box's translucent block at 25k patches,
/// `bench/results/memory-estimate-2026-12-07.md`).
const ON_DEMAND_BYTES_PER_ENTRY: u64 = 112;

/// The paths each object of `paths` holds at the subsurface stage's peak: a hierarchical S
/// traced on demand never lists a homogeneous translucent object's pairs, it holds its
/// direct pairs and links only (counted as [`crate::slinks::ENTRIES_BOUND`] per patch, at
/// [`ON_DEMAND_BYTES_PER_ENTRY`]); every other object its pairs within reach
/// ([`distances::PEAK_BYTES_PER_PATH`] each).
fn held_paths(
    params: &PrecomputeParams,
    materials: &[ObjectMaterial<'_>],
    paths: &[(String, u64, f32)],
) -> Vec<HeldPaths> {
    let on_demand_bound = |name: &str| -> Option<u64> {
        params
            .subsurface_links
            .as_ref()
            .filter(|sl| sl.trace != crate::slinks::Trace::All)?;
        if !matches!(params.transport, FormFactorMethod::Hierarchical(_)) {
            return None;
        }
        let o = materials.iter().find(|o| o.name == name)?;
        matches!(o.material, Material::Translucent { .. })
            .then(|| o.patches.len() as u64 * crate::slinks::ENTRIES_BOUND)
    };
    paths
        .iter()
        .map(|(name, p, r)| {
            let (paths, bytes_each) = match on_demand_bound(name) {
                Some(b) => (b.min(*p), ON_DEMAND_BYTES_PER_ENTRY),
                None => (*p, distances::PEAK_BYTES_PER_PATH),
            };
            HeldPaths {
                name: name.clone(),
                paths,
                radius: *r,
                bytes_each,
            }
        })
        .collect()
}

impl Budget {
    /// The estimate was an upper bound; should the `stored` paths of stage 1 still outgrow
    /// the budget, stop here, before S (the larger half) is assembled.
    fn check_stored(&self, stored: u64) -> Result<(), PrecomputeError> {
        let grown = self
            .held
            .saturating_add(stored.saturating_mul(distances::PEAK_BYTES_PER_PATH));
        if grown > self.limit {
            return Err(PrecomputeError::SubsurfaceOutOfMemory {
                object: "all translucent objects".into(),
                paths: stored,
                radius: 0.0,
                bytes_each: distances::PEAK_BYTES_PER_PATH,
                estimate: grown,
                limit: self.limit,
            });
        }
        Ok(())
    }
}

/// One precompute's inputs, which every stage reads, and the times of the stages done.
struct Stages<'a> {
    scene: &'a LoadedScene,
    params: &'a PrecomputeParams,
    /// Each finished stage's time, in order (the manifest's and the report's `stages`).
    times: Vec<StageTime>,
}

impl<'a> Stages<'a> {
    /// Plan and patches: the subdivision edge for `density` (the patch count it gives is
    /// checked first), then the patches and the viewer mesh.
    fn patches(
        &mut self,
        sources: Vec<&'a [[Vec3; 3]]>,
        density: Density,
    ) -> Result<Patched<'a>, PrecomputeError> {
        let params = self.params;
        let t = Instant::now();
        let (h, count) = patch::plan(&sources, density);
        if let Some(e) = too_many(params, count) {
            return Err(e);
        }
        stage_start(params, "patches")?;
        let bar = stage_bar(params.progress, 2, "patches");
        let patches = patch::subdivide(&sources, h);
        bar.inc(1);
        let crease: Vec<f32> = self.scene.objects.iter().map(|o| o.crease_deg).collect();
        let mesh = patch::viewer_mesh(&patches, &crease);
        bar.inc(1);
        finish(bar, params.progress, "patches", t, &mut self.times);
        Ok(Patched {
            sources,
            h,
            patches,
            mesh,
        })
    }

    /// The BVH over the source triangles. Out: the triangles, in object order (the
    /// bundle's occluders), and the occluder that knows each one's object.
    fn bvh(
        &mut self,
        sources: &[&[[Vec3; 3]]],
    ) -> Result<(Vec<[Vec3; 3]>, Occluder), PrecomputeError> {
        let t = Instant::now();
        stage_start(self.params, "bvh")?;
        let bar = stage_bar(self.params.progress, 1, "bvh");
        let occluder_tris: Vec<[Vec3; 3]> =
            sources.iter().flat_map(|s| s.iter().copied()).collect();
        let owners: Vec<u32> = sources
            .iter()
            .enumerate()
            .flat_map(|(k, s)| std::iter::repeat_n(k as u32, s.len()))
            .collect();
        let occ = Occluder::with_owners(&occluder_tris, &owners);
        bar.inc(1);
        finish(bar, self.params.progress, "bvh", t, &mut self.times);
        Ok((occluder_tris, occ))
    }

    /// Subsurface: distances and S per translucent object, ρ on the diagonal elsewhere. In:
    /// the patches, each object's material, the budget and a hierarchical F's cluster tree;
    /// out: S and what the bundle stores beside it.
    fn subsurface(
        &mut self,
        patched: &Patched<'_>,
        materials: &[ObjectMaterial<'_>],
        budget: &Budget,
        (tree, precut): (Option<&hierarchy::ClusterTree>, Option<&ReceiverCuts>),
    ) -> Result<SubsurfaceOut, PrecomputeError> {
        let (scene, params) = (self.scene, self.params);
        let t = Instant::now();
        stage_start(params, "subsurface")?;
        let bar = stage_bar(params.progress, 2, "subsurface");
        let patches = &patched.patches;
        let mut geometry = patch_geometry(patches);
        let media = scene_media(scene, patches, patched.h);
        let steps = SubsurfaceSteps {
            params,
            materials,
            unit_mm: scene.file.unit_mm,
            tree,
            paths: &budget.paths,
        };
        // Random walks of simulated objects, before the distances of the others.
        let walks = steps.walks(&geometry, &bar)?;
        let (on_demand, link_bounds) = steps.on_demand(&geometry)?;
        let found = steps.distances(&geometry, &patched.sources, &media, &on_demand)?;
        bar.inc(1);
        budget.check_stored(found.dist.col.len() as u64)?;
        let stored = stored_radii(materials, &found.reports);
        let linked = steps.links(&mut geometry, &stored, found, (&link_bounds, precut))?;
        let (mut smat, s_reports) =
            steps.assemble(&geometry, &linked, &media.patch_material, &stored, &walks)?;
        let textured = textured_albedos(scene, patched);
        crate::gltf_scene::set_diagonal(&mut smat, &textured);
        bar.inc(1);
        for d in &linked.reports {
            if let Some(w) = &d.warning {
                tell(params, &format!("warning: {w}"));
            }
        }
        let info = steps.info(&smat, &linked, &walks, &s_reports);
        finish(bar, params.progress, "subsurface", t, &mut self.times);
        Ok(SubsurfaceOut {
            smat,
            linked,
            walks,
            patch_material: media.patch_material,
            textured,
            info,
        })
    }

    /// The transfer matrix T = (I − S F)⁻¹ S, stored as f16 R = T − S; `None` without
    /// `inverse`. In: the patches, the occluder, F (its tree's C·P multiplied out), S and
    /// the memory limit.
    fn transfer(
        &mut self,
        patched: &Patched<'_>,
        occ: &Occluder,
        rows: &TransportRows,
        smat: &Csr<[f32; 3]>,
        limit: u64,
    ) -> Result<Option<Transfer>, PrecomputeError> {
        let params = self.params;
        if !params.inverse {
            return Ok(None);
        }
        let patches = &patched.patches;
        let n = patches.len();
        let t = Instant::now();
        stage_start(params, "inverse T")?;
        let bar = stage_bar(params.progress, 6, "inverse T");
        // T needs F itself: a hierarchical C·P is multiplied out (N² at most, like T).
        let expanded = rows.tree.as_ref().map(|(t, range, _)| {
            let tree = translux_proto::bundle::TreeView {
                perm: &t.perm,
                range,
            };
            let c = rows.ff.view().expect("form factors are a valid CSR");
            translux_engine::transport::Transport::hierarchical(c, tree, &patches.area).expand()
        });
        let f_view = expanded
            .as_ref()
            .unwrap_or(&rows.ff)
            .view()
            .expect("form factors are a valid CSR");
        let s_view = CsrView::new_checked(n, n, &smat.row_ptr, &smat.col, &smat.val)
            .expect("assemble_scene builds a valid CSR");
        let emission = patch_emission(self.scene, patches);
        let probe = relight_probe(self.scene, patches, occ, &f_view, &emission);
        let tr =
            translux_engine::inverse::compute(&f_view, &s_view, &emission, &probe, limit, &|k| {
                bar.inc(k)
            })?;
        finish(bar, params.progress, "inverse T", t, &mut self.times);
        Ok(Some(tr))
    }

    /// The bundle: the arrays, the manifest, written to `out` atomically. In: what the
    /// stages made and the memory estimate; out: the report of the whole precompute.
    fn write(
        mut self,
        out: &Path,
        made: Made<'_>,
        memory_estimate: u64,
    ) -> Result<PrecomputeReport, PrecomputeError> {
        let (scene, params) = (self.scene, self.params);
        let transfer_info = made.transfer.as_ref().map(transfer_info);
        let t = Instant::now();
        stage_start(params, "write bundle")?;
        let bar = stage_bar(params.progress, 1, "write bundle");
        let patches = &made.patched.patches;
        let s = &made.subsurface;
        let (objects, albedo, emission) =
            object_surfaces(scene, patches, &s.patch_material, &s.textured);
        let np = patches.len() as u64;
        let nv = made.patched.mesh.positions.len() as u64;
        let occluder_count = made.occluder_tris.len() as u64;
        let nnz = made.rows.ff.nnz() as u64;
        let ff_seconds = made.rows.ff_seconds;
        let ff_info = made.rows.ff_info.clone();
        let subsurface_info = s.info.clone();
        let hierarchy_info = made.rows.tree.as_ref().map(|(_, _, info)| info.clone());
        let environment_info = made.rows.environment.as_ref().map(|(_, i)| i.clone());
        let camera = scene.file.camera.unwrap_or_else(|| default_camera(patches));
        let arrays_out = bundle_arrays(made, albedo, emission);
        let manifest = Manifest {
            format: FORMAT.into(),
            version: FORMAT_VERSION,
            name: scene.name.clone(),
            source: scene.source.clone(),
            created_by: format!("translux-precompute {}", env!("CARGO_PKG_VERSION")),
            unit_mm: scene.file.unit_mm,
            patch_count: np,
            vertex_count: nv,
            occluder_count,
            objects,
            lights: scene.file.lights.clone(),
            camera,
            form_factors: ff_info.clone(),
            subsurface: subsurface_info.clone(),
            stages: self.times.clone(),
            transfer: transfer_info.clone(),
            environment: environment_info,
            hierarchy: hierarchy_info.clone(),
            arrays: Default::default(),
        };
        let written = write_bundle(out, manifest, arrays_out)?;
        bar.inc(1);
        finish(bar, params.progress, "write bundle", t, &mut self.times);

        Ok(PrecomputeReport {
            patch_count: np as usize,
            vertex_count: nv as usize,
            occluder_count: occluder_count as usize,
            nnz_f: nnz,
            bundle_bytes: written.bytes,
            rays_per_second: ff_info.rays as f64 / ff_seconds.max(1e-9),
            form_factors: ff_info,
            hierarchy: hierarchy_info,
            subsurface: subsurface_info,
            transfer: transfer_info,
            stages: self.times,
            memory_estimate,
            peak_rss: peak_rss(),
        })
    }
}

/// What the steps of the subsurface stage read: the settings, each object's material and
/// patches, the scene's unit, a hierarchical F's cluster tree and the estimated paths.
struct SubsurfaceSteps<'s> {
    params: &'s PrecomputeParams,
    materials: &'s [ObjectMaterial<'s>],
    unit_mm: f64,
    /// With `subsurface_links`, S links far pairs to this tree's nodes.
    tree: Option<&'s hierarchy::ClusterTree>,
    /// [`Budget::paths`]: what a pairwise S stores per object, estimated before F.
    paths: &'s [(String, u64, f32)],
}

/// The distances S is assembled from, after a hierarchical S's cut (or as stage 1 left
/// them), with stage 1's reports and what the cut counted.
struct Linked {
    dist: Csr<f32>,
    material_len: Vec<MediaLen>,
    kind: Vec<u32>,
    /// Each entry's spread of distances (empty without a cut).
    spread: Vec<f32>,
    /// The entries of `dist` that are links to cluster nodes.
    links: u64,
    /// The nearer distance links are read at (`--s-link-near`), where spreads are stored.
    link_near: Option<f32>,
    /// The distances a pairwise S would have stored (estimated for objects traced on
    /// demand).
    pairwise_distances: u64,
    /// Stage 1's report per object, an on-demand object's tracing time included.
    reports: Vec<distances::DistanceReport>,
}

impl SubsurfaceSteps<'_> {
    /// The random walks of the simulated objects (their progress on `bar`, a note per
    /// object); the observer's stop cancels them.
    fn walks(
        &self,
        geometry: &smatrix::PatchGeometry,
        bar: &ProgressBar,
    ) -> Result<SceneWalks, PrecomputeError> {
        let sim_patches: u64 = self
            .materials
            .iter()
            .filter(|o| matches!(o.material, Material::Simulated { .. }))
            .map(|o| o.patches.len() as u64)
            .sum();
        if sim_patches > 0 {
            bar.set_length(2 + sim_patches);
        }
        let stop = self
            .params
            .observer
            .as_ref()
            .map_or_else(Stop::never, |o| o.stop());
        let walks = crate::simulate::scene_walks(
            geometry,
            self.materials,
            self.unit_mm,
            (&|d| bar.set_position(d), &stop),
        )
        .map_err(|e| match e {
            SimError::Stopped { .. } => PrecomputeError::Cancelled,
            e => PrecomputeError::Simulation(e.to_string()),
        })?;
        for (name, info, seconds) in &walks.reports {
            tell(
                self.params,
                &format!(
                    "note: simulated '{name}': {} walks, {} events in {seconds:.1} s; noise \
                     {:.2}% median, {:.2}% max; {} records; {} lost, {} cut",
                    info.walks,
                    info.events,
                    100.0 * info.noise_median,
                    100.0 * info.noise_max,
                    info.records,
                    info.lost,
                    info.cut
                ),
            );
        }
        Ok(walks)
    }

    /// Which objects a hierarchical S traces on demand (the cut first, then only the paths
    /// it uses) where that saves work, with a note. Out: a flag per object, and each cut
    /// object's link bound ([`crate::slinks::link_bounds`]; empty without a cut).
    fn on_demand(
        &self,
        geometry: &smatrix::PatchGeometry,
    ) -> Result<(Vec<bool>, Vec<Vec<LinkBound>>), PrecomputeError> {
        let (materials, unit_mm) = (self.materials, self.unit_mm);
        let mut link_bounds = Vec::new();
        let on_demand: Vec<bool> = match (&self.params.subsurface_links, self.tree) {
            (Some(sl), Some(t)) => {
                let reach = materials
                    .iter()
                    .map(|o| smatrix::stored_radius(o, unit_mm, &self.params.subsurface))
                    .collect::<Result<Vec<_>, _>>()?;
                let pairs: Vec<u64> = materials
                    .iter()
                    .map(|o| self.paths.iter().find(|p| p.0 == o.name).map_or(0, |p| p.1))
                    .collect();
                let reuse = self.params.distance_cache.is_some();
                link_bounds =
                    crate::slinks::link_bounds(geometry, materials, &reach, unit_mm, sl.tolerance);
                crate::slinks::trace_on_demand(
                    t,
                    geometry,
                    materials,
                    &reach,
                    &pairs,
                    sl,
                    &link_bounds,
                    reuse,
                )
            }
            _ => vec![false; materials.len()],
        };
        if on_demand.iter().any(|&d| d) {
            let names = |want: bool| -> Vec<&str> {
                materials
                    .iter()
                    .zip(&on_demand)
                    .filter(|(o, d)| {
                        **d == want && matches!(o.material, Material::Translucent { .. })
                    })
                    .map(|(o, _)| o.name)
                    .collect()
            };
            tell(
                self.params,
                &format!(
                    "note: hierarchical S: optical paths traced on demand in {:?}, every pair \
                     within reach in {:?}",
                    names(true),
                    names(false)
                ),
            );
        }
        Ok((on_demand, link_bounds))
    }

    /// Stage 1: the optical distances of the translucent objects (an object flagged in
    /// `on_demand` gets an oracle instead of rows), with a note for each one reused from an
    /// earlier frame.
    fn distances(
        &self,
        geometry: &smatrix::PatchGeometry,
        sources: &[&[[Vec3; 3]]],
        media: &distances::SceneMedia,
        on_demand: &[bool],
    ) -> Result<distances::SceneDistances, PrecomputeError> {
        let params = self.params;
        let found = distances::scene_distances(
            geometry,
            self.materials,
            sources,
            media,
            self.unit_mm,
            &params.subsurface,
            &params.voxels,
            params.distance_cache.as_deref(),
            on_demand,
        )?;
        for d in found.reports.iter().filter(|d| d.reused) {
            tell(
                params,
                &format!(
                    "note: '{}' only moved rigidly since an earlier frame: its optical \
                     distances were reused",
                    d.name
                ),
            );
        }
        Ok(found)
    }

    /// A hierarchical S: far pairs of translucent objects become links to whole nodes
    /// ([`crate::slinks::collapse`], which gives `geometry` its nodes when it links any),
    /// with a note. Without a cut, stage 1's distances pass through.
    fn links(
        &self,
        geometry: &mut smatrix::PatchGeometry,
        stored: &[f32],
        found: distances::SceneDistances,
        (link_bounds, precut): (&[Vec<LinkBound>], Option<&ReceiverCuts>),
    ) -> Result<Linked, PrecomputeError> {
        let distances::SceneDistances {
            dist,
            material_len: dist_len,
            kind: dist_kind,
            reports: mut dist_reports,
            on_demand: oracles,
        } = found;
        let materials = self.materials;
        let t_links = Instant::now();
        // Objects traced on demand never had their pairs listed: their share of what a
        // pairwise S would have stored is the estimate made before F.
        let pairwise_distances = dist.col.len() as u64
            + materials
                .iter()
                .zip(&oracles)
                .filter(|(_, o)| o.is_some())
                .filter_map(|(m, _)| self.paths.iter().find(|p| p.0 == m.name).map(|p| p.1))
                .sum::<u64>();
        let mut cut_object_seconds = vec![0.0f64; materials.len()];
        let mut node_runs = (0u64, 0u64);
        let (dist, dist_len, dist_kind, dist_spread, links) =
            match (&self.params.subsurface_links, self.tree) {
                (Some(sl), Some(t)) => {
                    check_cuts(t, materials, &oracles, precut)?;
                    let c = crate::slinks::collapse(
                        t,
                        geometry,
                        materials,
                        stored,
                        &dist,
                        &dist_len,
                        &dist_kind,
                        &oracles,
                        sl,
                        link_bounds,
                        precut,
                    )?;
                    if c.links > 0 {
                        geometry.nodes = Some(c.nodes);
                    }
                    cut_object_seconds = c.seconds;
                    node_runs = c.node_runs;
                    (c.dist, c.material_len, c.kind, c.spread, c.links)
                }
                _ => (dist, dist_len, dist_kind, Vec::new(), 0),
            };
        // Links read at two distances (`--s-link-near`), recorded with their spreads.
        let link_near = self
            .params
            .subsurface_links
            .map(|sl| sl.near)
            .filter(|_| !dist_spread.is_empty());
        let cut_seconds = t_links.elapsed().as_secs_f64();
        // The paths an on-demand object traced belong to its stage-1 time.
        for ((m, _), secs) in materials
            .iter()
            .zip(&oracles)
            .zip(&cut_object_seconds)
            .filter(|((_, o), _)| o.is_some())
        {
            if let Some(d) = dist_reports.iter_mut().find(|d| d.name == m.name) {
                d.seconds += secs;
            }
        }
        if links > 0 {
            tell(
                self.params,
                &format!(
                    "note: hierarchical S: {links} links to cluster nodes beside {} direct \
                     pairs, against {pairwise_distances} pairwise distances{} (cut in \
                     {cut_seconds:.2} s)",
                    dist.col.len() as u64 - links,
                    if oracles.iter().any(Option::is_some) {
                        format!(
                            ", estimated; only the distances the cut uses were traced: {} \
                             linked nodes' runs, {} of them on the grid of twice the voxel \
                             edge",
                            node_runs.0, node_runs.1
                        )
                    } else {
                        String::new()
                    },
                ),
            );
        }
        Ok(Linked {
            dist,
            material_len: dist_len,
            kind: dist_kind,
            spread: dist_spread,
            links,
            link_near,
            pairwise_distances,
            reports: dist_reports,
        })
    }

    /// S from the distances, each patch's medium, how far each object's distances reach and
    /// the simulated objects' walks. Out: S and a report per object.
    fn assemble(
        &self,
        geometry: &smatrix::PatchGeometry,
        linked: &Linked,
        patch_material: &[u32],
        stored: &[f32],
        walks: &SceneWalks,
    ) -> Result<(Csr<[f32; 3]>, Vec<AssemblyReport>), PrecomputeError> {
        let n = geometry.corners.len();
        let walks_view = (!walks.is_empty()).then(|| {
            translux_proto::bundle::WalksView::new_checked(
                n,
                &walks.row_ptr,
                &walks.col,
                &walks.bin,
                &walks.weight,
                Some(&walks.weight_normal),
            )
            .and_then(|v| v.with_lamp(&walks.weight_lamp))
            .expect("the walks build valid records")
        });
        let dist = &linked.dist;
        let dist_view = CsrView::new_checked(n, dist.n_cols, &dist.row_ptr, &dist.col, &dist.val)
            .expect("stage 1 builds a valid CSR");
        let (smat, s_reports) = smatrix::assemble_scene(
            geometry,
            self.materials,
            dist_view,
            &linked.material_len,
            patch_material,
            &linked.kind,
            &linked.spread,
            stored,
            self.unit_mm,
            &self.params.subsurface,
            None,
            walks_view.as_ref(),
        )?;
        Ok((smat.into_csr(), s_reports))
    }

    /// The subsurface stage's summary (the manifest's and the report's): S, the distances,
    /// the links and each object's method, entries and time.
    fn info(
        &self,
        smat: &Csr<[f32; 3]>,
        linked: &Linked,
        walks: &SceneWalks,
        s_reports: &[AssemblyReport],
    ) -> SubsurfaceInfo {
        let sp = &self.params.subsurface;
        let links = linked.links;
        let mut objects =
            distances::subsurface_objects(&linked.reports, s_reports, sp.truncation_energy);
        for (name, info, seconds) in &walks.reports {
            let a = s_reports.iter().find(|a| &a.name == name);
            objects.push(translux_proto::bundle::SubsurfaceObject {
                name: name.clone(),
                method: "simulated".into(),
                truncation_energy: sp.truncation_energy,
                max_column_energy: a.map_or(0.0, |a| a.max_column_energy),
                entries: a.map_or(0, |a| a.entries),
                simulation: Some(info.clone()),
                seconds: seconds + a.map_or(0.0, |a| a.seconds),
                ..Default::default()
            });
        }
        SubsurfaceInfo {
            nnz: smat.col.len() as u64,
            distance_nnz: linked.dist.col.len() as u64,
            links,
            pairwise_distances: if links > 0 {
                linked.pairwise_distances
            } else {
                0
            },
            link_near: linked.link_near,
            link_variation: self
                .params
                .subsurface_links
                .filter(|_| links > 0)
                .map(|sl| sl.tolerance.variation),
            walks: walks.col.len() as u64,
            objects,
        }
    }
}

/// The per-patch geometry S reads, copied from the patches (no tree nodes yet).
fn patch_geometry(patches: &Patches) -> smatrix::PatchGeometry {
    smatrix::PatchGeometry {
        corners: patches.corners.clone(),
        centroid: patches.centroid.clone(),
        normal: patches.normal.clone(),
        area: patches.area.clone(),
        size: patches.size.clone(),
        nodes: None,
    }
}

/// The shards' cuts (a merge's) cover exactly the receivers this run traces on demand.
fn check_cuts(
    tree: &hierarchy::ClusterTree,
    materials: &[ObjectMaterial<'_>],
    oracles: &[Option<crate::voxel::Oracle>],
    precut: Option<&ReceiverCuts>,
) -> Result<(), PrecomputeError> {
    let Some(pc) = precut else {
        return Ok(());
    };
    let want: usize = crate::slinks::on_demand_receivers(tree, materials, oracles)
        .iter()
        .map(|(_, r)| r.len())
        .sum();
    if pc.receivers() != want {
        return Err(PrecomputeError::Shard(format!(
            "the parts hold the subsurface cuts of {} receivers; this scene traces {want} on \
             demand (parts made by another version of translux-precompute?)",
            pc.receivers()
        )));
    }
    Ok(())
}

/// How far each object's stored distances reach (stage 1's radius; 0 where it has none).
fn stored_radii(
    materials: &[ObjectMaterial<'_>],
    reports: &[distances::DistanceReport],
) -> Vec<f32> {
    materials
        .iter()
        .map(|o| {
            reports
                .iter()
                .find(|d| d.name == o.name)
                .map_or(0.0, |d| d.radius)
        })
        .collect()
}

/// Textured surfaces (glTF): each textured patch's ρ, the texture's mean over it, for S_jj
/// and the bundle's albedos ([`crate::gltf_scene::textured_albedos`]).
fn textured_albedos(scene: &LoadedScene, patched: &Patched<'_>) -> Vec<(usize, [f32; 3])> {
    let textured_objects: Vec<_> = scene
        .objects
        .iter()
        .map(|o| (o.triangles.as_slice(), o.albedo_map.as_deref()))
        .collect();
    crate::gltf_scene::textured_albedos(&textured_objects, &patched.patches, patched.h)
}

/// What the subsurface stage made: S, the distances and walks the bundle stores beside it,
/// each patch's medium, the textured patches' ρ and the summary.
struct SubsurfaceOut {
    smat: Csr<[f32; 3]>,
    linked: Linked,
    walks: SceneWalks,
    patch_material: Vec<u32>,
    textured: Vec<(usize, [f32; 3])>,
    info: SubsurfaceInfo,
}

/// Each patch's emission Bₑ, its object's.
fn patch_emission(scene: &LoadedScene, patches: &Patches) -> Vec<[f32; 3]> {
    let mut emission = vec![[0.0f32; 3]; patches.len()];
    for (o, range) in scene.objects.iter().zip(&patches.object_ranges) {
        emission[range.clone()].fill(material_albedo_emission(&o.material).1);
    }
    emission
}

/// The probe of T's f16 error: v = E + F Bₑ for the scene's lights (uniform E = 1 W/m²
/// where they cannot be evaluated here), to report what f16 storage does to a relight.
fn relight_probe(
    scene: &LoadedScene,
    patches: &Patches,
    occ: &Occluder,
    f_view: &CsrView<'_>,
    emission: &[[f32; 3]],
) -> Vec<[f32; 3]> {
    let geo = translux_engine::radiosity::PatchGeometry {
        centroid: &patches.centroid,
        normal: &patches.normal,
    };
    let mut probe = translux_engine::radiosity::direct_irradiance(
        geo,
        occ,
        &scene.file.lights,
        scene.file.unit_mm,
    )
    .unwrap_or_else(|_| vec![[1.0; 3]; patches.len()]);
    let mut fbe = vec![[0.0f32; 3]; patches.len()];
    translux_engine::radiosity::spmv_rgb(f_view, emission, &mut fbe);
    for (p, x) in probe.iter_mut().zip(&fbe) {
        for c in 0..3 {
            p[c] += x[c];
        }
    }
    probe
}

/// T's storage and errors, for the manifest and the report.
fn transfer_info(t: &Transfer) -> TransferInfo {
    TransferInfo {
        storage: "f16 T - S, per-row scale".into(),
        method: "dense partial-pivot LU per channel (faer), f64".into(),
        median_rel_error: t.median_rel_error,
        max_rel_error: t.max_rel_error,
        relight_max_rel_error: t.relight_max_rel_error,
        relight_rel_error: t.relight_rel_error,
        lu_residual: t.lu_residual,
        seconds: t.seconds,
    }
}

/// What the bundle stores, as the stages left it.
struct Made<'a> {
    patched: Patched<'a>,
    occluder_tris: Vec<[Vec3; 3]>,
    rows: TransportRows,
    subsurface: SubsurfaceOut,
    transfer: Option<Transfer>,
}

/// Each object's manifest entry, and each patch's ρ and emission: its object's, per medium
/// in a heterogeneous object, the texture's mean on a textured patch (as in its S_jj).
fn object_surfaces(
    scene: &LoadedScene,
    patches: &Patches,
    patch_material: &[u32],
    textured: &[(usize, [f32; 3])],
) -> (Vec<ObjectInfo>, Vec<[f32; 3]>, Vec<[f32; 3]>) {
    let mut objects = Vec::new();
    let mut albedo = vec![[0.0f32; 3]; patches.len()];
    let mut emission = vec![[0.0f32; 3]; patches.len()];
    for (o, range) in scene.objects.iter().zip(&patches.object_ranges) {
        let (rho, be) = material_albedo_emission(&o.material);
        albedo[range.clone()].fill(rho);
        emission[range.clone()].fill(be);
        if matches!(o.material, Material::Heterogeneous { .. }) {
            for p in range.clone() {
                albedo[p] = patch_albedo(&o.material, patch_material[p]);
            }
        }
        objects.push(ObjectInfo {
            name: o.name.clone(),
            material: o.material.clone(),
            first_patch: range.start as u64,
            patch_count: range.len() as u64,
            albedo: rho,
        });
    }
    // Textured patches carry their own ρ (the same as their S_jj).
    for &(p, rho) in textured {
        albedo[p] = rho;
    }
    (objects, albedo, emission)
}

/// The bundle's arrays, in order: the patches, the viewer mesh, the occluders, F, S and the
/// distances, then what the scene has of link spreads, walks, the tree, T and environment
/// visibility. In: what the stages made and each patch's ρ and emission.
fn bundle_arrays(
    made: Made<'_>,
    albedo: Vec<[f32; 3]>,
    emission: Vec<[f32; 3]>,
) -> Vec<NamedArray> {
    let Made {
        patched: Patched { patches, mesh, .. },
        occluder_tris,
        rows,
        subsurface:
            SubsurfaceOut {
                smat,
                linked,
                walks,
                patch_material,
                ..
            },
        transfer,
    } = made;
    let flat3 = |v: &[Vec3]| v.iter().flat_map(|x| x.to_array()).collect::<Vec<f32>>();
    let np = patches.len() as u64;
    let nv = mesh.positions.len() as u64;
    let (ff, dist) = (rows.ff, linked.dist);
    let nnz = ff.nnz() as u64;
    let corners = patches.corners.iter().flat_map(|c| flat3(c)).collect();
    let occluders = occluder_tris.iter().flat_map(|c| flat3(c)).collect();
    let mut arrays_out = vec![
        NamedArray::f32(arrays::PATCH_CORNERS, vec![np, 3, 3], corners),
        NamedArray::f32(arrays::PATCH_NORMAL, vec![np, 3], flat3(&patches.normal)),
        NamedArray::f32(arrays::PATCH_AREA, vec![np], patches.area),
        NamedArray::u32(arrays::PATCH_OBJECT, vec![np], patches.object),
        NamedArray::f32(arrays::PATCH_ALBEDO, vec![np, 3], albedo.concat()),
        NamedArray::f32(arrays::PATCH_EMISSION, vec![np, 3], emission.concat()),
        NamedArray::f32(
            arrays::VERTEX_POSITION,
            vec![nv, 3],
            mesh.positions.concat(),
        ),
        NamedArray::f32(arrays::VERTEX_NORMAL, vec![nv, 3], mesh.normals.concat()),
        NamedArray::u32(
            arrays::TRIANGLE_VERTEX,
            vec![np, 3],
            mesh.triangles.concat(),
        ),
        NamedArray::f32(
            arrays::OCCLUDER_TRI,
            vec![occluder_tris.len() as u64, 3, 3],
            occluders,
        ),
        NamedArray::u64(arrays::FF_ROW_PTR, vec![ff.n_rows as u64 + 1], ff.row_ptr),
        NamedArray::u32(arrays::FF_COL, vec![nnz], ff.col),
        NamedArray::f32(arrays::FF_VAL, vec![nnz], ff.val),
        NamedArray::u64(arrays::S_ROW_PTR, vec![np + 1], smat.row_ptr),
        NamedArray::u32(arrays::S_COL, vec![smat.col.len() as u64], smat.col),
        NamedArray::f32(
            arrays::S_VAL,
            vec![smat.val.len() as u64, 3],
            smat.val.concat(),
        ),
        NamedArray::u64(arrays::DIST_ROW_PTR, vec![np + 1], dist.row_ptr),
        NamedArray::u32(arrays::DIST_COL, vec![dist.col.len() as u64], dist.col),
        NamedArray::f32(arrays::DIST_VAL, vec![dist.val.len() as u64], dist.val),
        NamedArray::u32(
            arrays::DIST_KIND,
            vec![linked.kind.len() as u64],
            linked.kind,
        ),
        NamedArray::f32(
            arrays::DIST_MATERIAL_LEN,
            vec![linked.material_len.len() as u64, hetero::MEDIA as u64],
            linked.material_len.concat(),
        ),
        NamedArray::u32(arrays::PATCH_MATERIAL, vec![np], patch_material),
    ];
    if linked.link_near.is_some() {
        let spread = linked.spread;
        arrays_out.push(NamedArray::f32(
            arrays::DIST_SPREAD,
            vec![spread.len() as u64],
            spread,
        ));
    }
    if !walks.is_empty() {
        arrays_out.extend(walk_arrays(np, walks));
    }
    if let Some((t, range, _)) = rows.tree {
        arrays_out.push(NamedArray::u32(arrays::TREE_PERM, vec![np], t.perm));
        arrays_out.push(NamedArray::u32(
            arrays::TREE_RANGE,
            vec![range.len() as u64, 2],
            range.concat(),
        ));
    }
    if let Some(tr) = transfer {
        arrays_out.push(NamedArray {
            name: arrays::TRANSFER,
            shape: vec![np, np, 3],
            data: ArrayData::F16(tr.bits),
        });
        arrays_out.push(NamedArray::f32(
            arrays::TRANSFER_SCALE,
            vec![np, 3],
            tr.scale.concat(),
        ));
    }
    if let Some((bits, info)) = rows.environment {
        arrays_out.push(NamedArray {
            name: arrays::ENV_VISIBILITY,
            shape: vec![np, u64::from(info.rows), u64::from(info.cols)],
            data: ArrayData::F16(bits),
        });
    }
    arrays_out
}

/// The simulated objects' walk records as the bundle's arrays (rows over all `np` patches).
fn walk_arrays(np: u64, walks: SceneWalks) -> Vec<NamedArray> {
    let w = walks.col.len() as u64;
    vec![
        NamedArray::u64(arrays::SIM_ROW_PTR, vec![np + 1], walks.row_ptr),
        NamedArray::u32(arrays::SIM_COL, vec![w], walks.col),
        NamedArray::u32(arrays::SIM_BIN, vec![w], walks.bin),
        NamedArray::f32(arrays::SIM_WEIGHT, vec![w, 3], walks.weight.concat()),
        NamedArray::f32(
            arrays::SIM_WEIGHT_NORMAL,
            vec![w, 3],
            walks.weight_normal.concat(),
        ),
        NamedArray::u32(
            arrays::SIM_WEIGHT_LAMP,
            vec![w, 3],
            walks.weight_lamp.concat(),
        ),
    ]
}

/// F, its summary and tree, and the environment visibility, for every receiver.
struct TransportRows {
    ff: translux_proto::csr::Csr,
    ff_info: FormFactorInfo,
    tree: Option<(hierarchy::ClusterTree, Vec<[u32; 2]>, HierarchyInfo)>,
    environment: Option<(Vec<u16>, translux_proto::bundle::EnvironmentInfo)>,
    ff_seconds: f64,
    /// A merge's: the shards' subsurface cuts, put together.
    cuts: Option<ReceiverCuts>,
}

/// The F and environment stages over every receiver (one box).
fn transport_rows(
    patches: &Patches,
    occ: &Occluder,
    tree: Option<hierarchy::ClusterTree>,
    params: &PrecomputeParams,
    stages: &mut Vec<StageTime>,
) -> Result<TransportRows, PrecomputeError> {
    let progress = params.progress;
    let t = Instant::now();
    let n = patches.len() as u64;
    stage_start(params, "form factors")?;
    let ff_total = n * n.saturating_sub(1) / 2;
    let bar = stage_bar(progress, ff_total, "form factors");
    let ff_done = std::sync::atomic::AtomicU64::new(0);
    let stop = || params.observer.as_ref().is_some_and(|o| o.cancelled());
    let (ff, ff_info, tree) = match &params.transport {
        FormFactorMethod::Dense => {
            let (ff, info) = formfactor::compute_with_stop(
                patches,
                occ,
                &params.form_factors,
                &|k| {
                    bar.inc(k);
                    if let Some(o) = &params.observer {
                        let done = ff_done.fetch_add(k, std::sync::atomic::Ordering::Relaxed) + k;
                        o.progress("form factors", done, ff_total);
                    }
                },
                &stop,
            );
            (ff, info, None)
        }
        FormFactorMethod::Hierarchical(hp) => {
            bar.set_length(n);
            let h = hierarchy::compute(
                patches,
                occ,
                &params.form_factors,
                hp,
                tree.unwrap_or_else(|| hierarchy::ClusterTree::build(patches)),
                &row_progress(&bar, params, &ff_done, n),
                &stop,
            );
            let ranges = h.tree.ranges();
            (h.c, h.ff_info, Some((h.tree, ranges, h.info)))
        }
    };
    if stop() {
        return Err(PrecomputeError::Cancelled);
    }
    let ff_seconds = t.elapsed().as_secs_f64();
    finish(bar, progress, "form factors", t, stages);
    let environment = environment_rows(patches, occ, params, 0..patches.len(), stages)?;
    Ok(TransportRows {
        ff,
        ff_info,
        tree,
        environment,
        ff_seconds,
        cuts: None,
    })
}

/// A hierarchical F's row counter: the bar and the observer, `n` rows in all.
fn row_progress<'a>(
    bar: &'a ProgressBar,
    params: &'a PrecomputeParams,
    done: &'a std::sync::atomic::AtomicU64,
    n: u64,
) -> impl Fn(u64) + Sync + 'a {
    move |k| {
        bar.inc(k);
        if let Some(o) = &params.observer {
            let d = done.fetch_add(k, std::sync::atomic::Ordering::Relaxed) + k;
            o.progress("form factors", d, n);
        }
    }
}

/// Environment visibility per patch of `rows` and direction bin ([`translux_engine::envvis`]).
fn environment_rows(
    patches: &Patches,
    occ: &Occluder,
    params: &PrecomputeParams,
    rows: std::ops::Range<usize>,
    stages: &mut Vec<StageTime>,
) -> Result<Option<(Vec<u16>, translux_proto::bundle::EnvironmentInfo)>, PrecomputeError> {
    let t = Instant::now();
    stage_start(params, "environment")?;
    let bar = stage_bar(params.progress, rows.len() as u64, "environment");
    let environment = translux_engine::envvis::stage(
        &patches.centroid,
        &patches.normal,
        Some(&patches.object),
        rows,
        occ,
        &params.environment,
        &|k| bar.inc(k),
    );
    finish(bar, params.progress, "environment", t, stages);
    Ok(environment)
}

/// The fingerprint of what the receiver rows depend on ([`crate::shard::plan_hash`]): the
/// bundle format, the patches, the source triangles, the tree, the F, environment and
/// subsurface settings and the materials.
fn plan_of(
    scene: &LoadedScene,
    patches: &Patches,
    occluder_tris: &[[Vec3; 3]],
    tree: &hierarchy::ClusterTree,
    params: &PrecomputeParams,
) -> u64 {
    let materials: Vec<_> = scene.objects.iter().map(|o| &o.material).collect();
    let settings = format!(
        "{:?}|{:?}|{:?}|{:?}|{:?}|{:?}|{:?}|{}",
        params.form_factors,
        params.transport,
        params.environment,
        params.subsurface,
        params.subsurface_links,
        params.voxels,
        materials,
        scene.file.unit_mm
    );
    crate::shard::plan_hash(&[
        &FORMAT_VERSION.to_le_bytes(),
        bytemuck::cast_slice(&patches.corners),
        bytemuck::cast_slice(&patches.object),
        bytemuck::cast_slice(occluder_tris),
        bytemuck::cast_slice(&tree.perm),
        settings.as_bytes(),
    ])
}

/// What a shard's share of the subsurface stage reads: the patches, each object's material
/// and the paths estimated before F ([`Budget::paths`]).
#[derive(Clone, Copy)]
struct SubsurfaceInputs<'a, 'b> {
    patched: &'a Patched<'b>,
    materials: &'a [ObjectMaterial<'b>],
    paths: &'a [(String, u64, f32)],
}

/// One shard's rows (F, environment visibility and the subsurface cuts of its share of
/// the receivers traced on demand) into its part folder, or nothing when it is already
/// there, finished, for the same plan.
fn shard_rows(
    scene: &LoadedScene,
    inputs: &SubsurfaceInputs<'_, '_>,
    occ: &Occluder,
    params: &PrecomputeParams,
    out: &Path,
    (shard, plan, tree): (Shard, u64, &hierarchy::ClusterTree),
) -> Result<PartReport, PrecomputeError> {
    let patches = &inputs.patched.patches;
    let rows = shard.rows(patches.len());
    if crate::shard::finished(out, shard, plan).map_err(PrecomputeError::Shard)? {
        return Ok(PartReport {
            shard,
            dir: crate::shard::part_dir(out, shard),
            rows,
            computed: false,
            bytes: 0,
            entries: 0,
            form_factor_seconds: 0.0,
            environment_seconds: 0.0,
            subsurface_seconds: 0.0,
        });
    }
    let FormFactorMethod::Hierarchical(hp) = &params.transport else {
        unreachable!("run() refuses a split of a dense F")
    };
    let t = Instant::now();
    stage_start(params, "form factors")?;
    let bar = stage_bar(params.progress, rows.len() as u64, "form factors");
    let done = std::sync::atomic::AtomicU64::new(0);
    let stop = || params.observer.as_ref().is_some_and(|o| o.cancelled());
    let block = hierarchy::compute_rows(
        patches,
        occ,
        &params.form_factors,
        hp,
        tree,
        rows.clone(),
        &row_progress(&bar, params, &done, rows.len() as u64),
        &stop,
    );
    if stop() {
        return Err(PrecomputeError::Cancelled);
    }
    let form_factor_seconds = t.elapsed().as_secs_f64();
    let mut stages = Vec::new();
    finish(bar, params.progress, "form factors", t, &mut stages);
    let t = Instant::now();
    let environment = environment_rows(patches, occ, params, rows, &mut stages)?;
    let environment_seconds = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let cuts = shard_cuts(scene, inputs, params, (shard, tree))?;
    let part = ShardRows {
        block,
        environment,
        cuts,
        form_factor_seconds,
        environment_seconds,
        subsurface_seconds: t.elapsed().as_secs_f64(),
    };
    crate::shard::write_part(out, shard, plan, &part).map_err(PrecomputeError::Shard)
}

/// A shard's share of a hierarchical S: of the receivers of the objects whose distances are
/// traced on demand ([`crate::slinks::on_demand_receivers`], one after the other), the
/// shard's equal share, cut and traced ([`crate::slinks::shard_cuts`]). The same steps the
/// subsurface stage takes up to its cut: which objects are traced on demand, their link
/// bounds and their oracles. Nothing without a hierarchical S.
fn shard_cuts(
    scene: &LoadedScene,
    inputs: &SubsurfaceInputs<'_, '_>,
    params: &PrecomputeParams,
    (shard, tree): (Shard, &hierarchy::ClusterTree),
) -> Result<ReceiverCuts, PrecomputeError> {
    let Some(sl) = &params.subsurface_links else {
        return Ok(ReceiverCuts::default());
    };
    stage_start(params, "subsurface")?;
    let SubsurfaceInputs {
        patched,
        materials,
        paths,
    } = *inputs;
    let patches = &patched.patches;
    let geometry = patch_geometry(patches);
    let media = scene_media(scene, patches, patched.h);
    let steps = SubsurfaceSteps {
        params,
        materials,
        unit_mm: scene.file.unit_mm,
        tree: Some(tree),
        paths,
    };
    let (on_demand, link_bounds) = steps.on_demand(&geometry)?;
    let (oracles, reach) = distances::on_demand_oracles(
        &geometry,
        materials,
        &patched.sources,
        &media,
        scene.file.unit_mm,
        &params.subsurface,
        &params.voxels,
        &on_demand,
    )?;
    let total: usize = crate::slinks::on_demand_receivers(tree, materials, &oracles)
        .iter()
        .map(|(_, r)| r.len())
        .sum();
    Ok(crate::slinks::shard_cuts(
        tree,
        &geometry,
        materials,
        &reach,
        &oracles,
        sl,
        &link_bounds,
        shard.rows(total),
    ))
}

/// The rows of the `count` parts, checked against this run's plan and put together; their
/// stage times (summed over the shards) and the merge's own.
fn merged_rows(
    scene: &LoadedScene,
    patches: &Patches,
    params: &PrecomputeParams,
    out: &Path,
    (count, plan, tree): (u32, u64, hierarchy::ClusterTree),
    stages: &mut Vec<StageTime>,
) -> Result<TransportRows, PrecomputeError> {
    let FormFactorMethod::Hierarchical(hp) = &params.transport else {
        unreachable!("run() refuses a split of a dense F")
    };
    let t = Instant::now();
    stage_start(params, "form factors")?;
    let rerun = |s: Shard| {
        format!(
            "translux-precompute {} --out {} --shard {s}",
            scene.source,
            out.display()
        )
    };
    let parts = crate::shard::read_parts(out, count, plan, patches.len(), &rerun)
        .map_err(PrecomputeError::Shard)?;
    let ff_seconds: f64 = parts.iter().map(|p| p.form_factor_seconds).sum();
    let env_seconds: f64 = parts.iter().map(|p| p.environment_seconds).sum();
    let s_seconds: f64 = parts.iter().map(|p| p.subsurface_seconds).sum();
    let mut cuts = ReceiverCuts::default();
    let mut environment: Option<(Vec<u16>, translux_proto::bundle::EnvironmentInfo)> = None;
    let mut blocks = Vec::with_capacity(parts.len());
    for p in parts {
        if let Some((bits, info)) = p.environment {
            match &mut environment {
                None => environment = Some((bits, info)),
                Some((all, sum)) => {
                    all.extend_from_slice(&bits);
                    sum.rays += info.rays;
                    sum.seconds += info.seconds;
                }
            }
        }
        cuts.append(p.cuts);
        blocks.push(p.block);
    }
    let h = hierarchy::assemble(tree, hp, blocks);
    let ranges = h.tree.ranges();
    stages.push(StageTime {
        stage: "form factors (shards)".into(),
        seconds: ff_seconds,
    });
    stages.push(StageTime {
        stage: "environment (shards)".into(),
        seconds: env_seconds,
    });
    if params.subsurface_links.is_some() {
        stages.push(StageTime {
            stage: "subsurface cuts (shards)".into(),
            seconds: s_seconds,
        });
    }
    stages.push(StageTime {
        stage: "merge parts".into(),
        seconds: t.elapsed().as_secs_f64(),
    });
    Ok(TransportRows {
        ff: h.c,
        ff_info: h.ff_info,
        tree: Some((h.tree, ranges, h.info)),
        environment,
        ff_seconds,
        cuts: params.subsurface_links.is_some().then_some(cuts),
    })
}

#[cfg(test)]
mod tests {
    use std::sync::{Arc, Mutex};

    use super::*;

    #[derive(Debug, Default)]
    struct Notes(Mutex<Vec<String>>);

    impl Observer for Notes {
        fn progress(&self, _stage: &str, _done: u64, _total: u64) {}
        fn note(&self, message: &str) {
            self.0.lock().unwrap().push(message.to_string());
        }
    }

    /// A server job's observer gets the scene's notes (here: a closed OBJ wound inside out,
    /// turned outward), rather than the library printing them.
    #[test]
    fn notes_go_to_the_observer() {
        let dir = tempfile::tempdir().unwrap();
        // A cube with every face wound inward.
        let obj = "v -1 -1 -1\nv 1 -1 -1\nv 1 1 -1\nv -1 1 -1\nv -1 -1 1\nv 1 -1 1\nv 1 1 1\n\
                   v -1 1 1\nf 2 3 4 1\nf 8 7 6 5\nf 5 6 2 1\nf 3 7 8 4\nf 4 8 5 1\nf 6 7 3 2\n";
        std::fs::write(dir.path().join("cube.obj"), obj).unwrap();
        let scene = r#"{"objects": [{"name": "cube", "mesh": "cube.obj",
            "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}}],
            "lights": [{"type": "point", "position": [0, 5, 0], "intensity": [1, 1, 1]}]}"#;
        std::fs::write(dir.path().join("scene.json"), scene).unwrap();
        let loaded = crate::scene::load_scene_file(&dir.path().join("scene.json")).unwrap();
        let notes = Arc::new(Notes::default());
        let params = PrecomputeParams {
            patches: Some(60),
            observer: Some(notes.clone()),
            environment: translux_engine::envvis::EnvVisParams {
                bins: None,
                ..Default::default()
            },
            ..Default::default()
        };
        precompute(&loaded, &dir.path().join("out"), &params).unwrap();
        let got = notes.0.lock().unwrap().clone();
        assert!(
            got.iter()
                .any(|n| n.starts_with("note: objects[0] \"cube\"") && n.contains("outward")),
            "{got:?}"
        );
    }
}
