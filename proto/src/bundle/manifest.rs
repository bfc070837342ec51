//! The manifest (`manifest.json`): the format's constants, the array names and element
//! types, and what the precompute records about a bundle (counts, objects, F, S, T, the
//! environment, stage times). Pure data: serde in, serde out.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::light::{Camera, Light};
use crate::scene::Material;

/// The `format` field of every manifest.
pub const FORMAT: &str = "translux-bundle";
/// Bumped whenever the layout changes; this build writes it and reads it and every version
/// from [`OLDEST_READABLE_VERSION`] on (version 5 added hierarchical F, see
/// [`Manifest::hierarchy`]; a version 4 bundle is a dense one and reads unchanged; version 6
/// added hierarchical S, [`SubsurfaceInfo::links`], and reads every version 5 bundle; version
/// 7 added [`arrays::SIM_WEIGHT_NORMAL`], and a version 6 bundle's walks serve diffuse entry
/// only; version 8 added [`arrays::SIM_WEIGHT_LAMP`], and a version 7 bundle's lamps
/// enter by their angle to the normal alone; version 9 added F's node rows,
/// [`HierarchyInfo::receiver_nodes`], and reads every version 8 bundle as one-sided; version
/// 10 writes [`arrays::SIM_WEIGHT_LAMP`] on the unscattered records too, which a version 8
/// or 9 bundle leaves 0, so its unscattered light from other surfaces does not turn).
pub const FORMAT_VERSION: u32 = 10;
/// The first version whose walks carry [`arrays::SIM_WEIGHT_NORMAL`].
pub const SIM_NORMAL_SINCE: u32 = 7;
/// The first version whose walks carry [`arrays::SIM_WEIGHT_LAMP`].
pub const SIM_LAMP_SINCE: u32 = 8;
/// The oldest bundle version this build still reads.
pub const OLDEST_READABLE_VERSION: u32 = 4;
/// The manifest's file name inside a bundle folder.
pub const MANIFEST_FILE: &str = "manifest.json";

/// Names of the arrays (the file is `NAME.DTYPE`).
pub mod arrays {
    pub const PATCH_CORNERS: &str = "patch_corners";
    pub const PATCH_NORMAL: &str = "patch_normal";
    pub const PATCH_AREA: &str = "patch_area";
    pub const PATCH_OBJECT: &str = "patch_object";
    pub const PATCH_ALBEDO: &str = "patch_albedo";
    pub const PATCH_EMISSION: &str = "patch_emission";
    pub const VERTEX_POSITION: &str = "vertex_position";
    pub const VERTEX_NORMAL: &str = "vertex_normal";
    pub const TRIANGLE_VERTEX: &str = "triangle_vertex";
    pub const OCCLUDER_TRI: &str = "occluder_tri";
    pub const FF_ROW_PTR: &str = "ff_row_ptr";
    pub const FF_COL: &str = "ff_col";
    pub const FF_VAL: &str = "ff_val";
    pub const S_ROW_PTR: &str = "s_row_ptr";
    pub const S_COL: &str = "s_col";
    pub const S_VAL: &str = "s_val";
    pub const DIST_ROW_PTR: &str = "dist_row_ptr";
    pub const DIST_COL: &str = "dist_col";
    pub const DIST_VAL: &str = "dist_val";
    pub const DIST_KIND: &str = "dist_kind";
    pub const DIST_MATERIAL_LEN: &str = "dist_material_len";
    /// Per stored distance, f32 `[nnz_d]` (only with [`super::SubsurfaceInfo::link_near`]):
    /// a link's spread σ ≥ 0 about its distance r, the link then read at r − σ and r + σ;
    /// 0 for direct pairs.
    pub const DIST_SPREAD: &str = "dist_spread";
    pub const PATCH_MATERIAL: &str = "patch_material";
    /// R = T − S, f16 `[N, N, 3]` (only with `Manifest::transfer`).
    pub const TRANSFER: &str = "transfer";
    /// Per row and channel scale of [`TRANSFER`], f32 `[N, 3]`.
    pub const TRANSFER_SCALE: &str = "transfer_scale";
    /// Environment visibility, f16 `[N, rows, cols]` (only with `Manifest::environment`).
    pub const ENV_VISIBILITY: &str = "env_visibility";
    /// The patches in cluster-tree order, u32 `[N]`, a permutation of `0..N` (only with
    /// `Manifest::hierarchy`).
    pub const TREE_PERM: &str = "tree_perm";
    /// Each cluster node's range `[start, end)` of [`TREE_PERM`], u32 `[M, 2]` (only with
    /// `Manifest::hierarchy`; M = `hierarchy.nodes`).
    pub const TREE_RANGE: &str = "tree_range";
    /// The random walks of simulated objects (only with `subsurface.walks` > 0): row j's
    /// records `[sim_row_ptr[j], sim_row_ptr[j + 1])`, u64 `[N + 1]`; each record is a source
    /// patch (`sim_col`, u32 `[W]`), a path-length bin (`sim_bin`, u32 `[W]`) and the walks'
    /// share of S_ji at zero absorption (`sim_weight`, f32 `[W, 3]`); see
    /// `crate::bundle::WalksView`.
    pub const SIM_ROW_PTR: &str = "sim_row_ptr";
    pub const SIM_COL: &str = "sim_col";
    pub const SIM_BIN: &str = "sim_bin";
    pub const SIM_WEIGHT: &str = "sim_weight";
    /// The records' share of S⁽ⁿ⁾_ji, S for light entering collimated along the inward
    /// normal instead of diffusely, from walks launched that way (f32 `[W, 3]`, version 7
    /// on); a record has 0 in whichever weight its walks did not add to.
    pub const SIM_WEIGHT_NORMAL: &str = "sim_weight_normal";
    /// The records' share of what directional light uses (u32 `[W, 3]`, version 8 on): G_u
    /// and G_v, how S_ji changes as the beam entering patch i tilts along the patch's
    /// tangent u (its first edge) and v (normal × u), 4 Σ w·u_in and 4 Σ w·v_in over the
    /// record's diffuse walks (u_in, v_in: the tangent components of each walk's incident
    /// direction outside). |G| ≤ 4 w, so each is stored per channel as the ratio G / (4 w)
    /// in i16 fixed point (`SIM_TILT_ONE` = 1): the low 16 bits G_u's, the high G_v's. U,
    /// the diffuse walks' share that left without scattering (which a lamp's beam does not
    /// have), is in records of their own, flagged in `sim_bin` by `SIM_UNSCATTERED`; their
    /// G (version 10 on, 0 before) is U's own, which only light from other surfaces reads.
    pub const SIM_WEIGHT_LAMP: &str = "sim_weight_lamp";
}

/// Element type of an array file.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum DType {
    F16,
    F32,
    U32,
    U64,
}

impl DType {
    pub fn size(self) -> usize {
        match self {
            DType::F16 => 2,
            DType::F32 | DType::U32 => 4,
            DType::U64 => 8,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            DType::F16 => "f16",
            DType::F32 => "f32",
            DType::U32 => "u32",
            DType::U64 => "u64",
        }
    }
}

/// One array file as the manifest lists it.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ArrayEntry {
    /// File name inside the bundle folder.
    pub file: String,
    pub dtype: DType,
    /// Shape; the product is the element count.
    pub shape: Vec<u64>,
    /// File length in bytes (= elements × dtype size).
    pub bytes: u64,
    /// XXH3-64 of the file's bytes, 16 lower-case hex digits.
    pub xxh3: String,
}

/// One scene object: a contiguous run of patches.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ObjectInfo {
    pub name: String,
    pub material: Material,
    pub first_patch: u64,
    pub patch_count: u64,
    /// The ρ its patches carry in `patch_albedo` (for a translucent object: the profile's
    /// total diffuse reflectance, used until S is in the bundle).
    pub albedo: [f32; 3],
}

/// How F was computed, and what was dropped.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct FormFactorInfo {
    pub nnz: u64,
    /// Entries below this were dropped (0: none).
    pub threshold: f32,
    /// Fraction of all power leaving patches that the dropped entries carried,
    /// Σ A_i F_ij (dropped) / Σ A_i.
    pub dropped_energy: f64,
    /// Row sums Σ_j F_ij: mean, min, max.
    pub row_sum_mean: f64,
    pub row_sum_min: f64,
    pub row_sum_max: f64,
    /// Occlusion rays cast.
    pub rays: u64,
    /// Patch pairs considered after orientation culling.
    pub pairs: u64,
}

/// How the hierarchical F̃ = C·P was built (see [`Manifest::hierarchy`]).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct HierarchyInfo {
    /// Cluster nodes M (the columns `N..N+M` of F's arrays); leaves are the patches.
    pub nodes: u64,
    /// Deepest level of the tree (the root is level 0).
    pub depth: u32,
    /// The accuracy parameter η: a node s is linked to a receiver at distance d only when
    /// its bounding radius R_s ≤ η d.
    pub accuracy: f32,
    /// Points (and shadow rays) per node link.
    pub node_samples: u32,
    /// Entries of C that link a receiver to a cluster node, and to a single patch.
    pub node_entries: u64,
    pub patch_entries: u64,
    /// Entries dense F would have held, estimated from the links' patch counts (visibility
    /// aside).
    pub dense_equivalent: u64,
    /// Whether cluster nodes receive too (version 9, two-sided links): C then has N + M rows,
    /// row N + k gathering what node k's patches receive alike (pushed to each of them), and
    /// `ff_row_ptr` N + M + 1 offsets. Absent (false) in a one-sided bundle.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub receiver_nodes: bool,
}

/// How S was built, per translucent object.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct SubsurfaceInfo {
    /// Stored entries of S (diagonals of opaque patches included).
    pub nnz: u64,
    /// Stored optical distances.
    pub distance_nnz: u64,
    /// Stored distances whose column is a cluster node, the links of a hierarchical S
    /// (version 6; S holds at most as many): S and the distances then have N + M columns,
    /// M = `hierarchy.nodes`. In the distances, row i
    /// lists the receivers j < N that take patch i directly (as in a pairwise S) and the
    /// nodes N + k that receiver i gathers from whole, with the optical distance to the
    /// node's representative patch; S_{i,N+k} = A_k R(r) multiplies the area-weighted mean
    /// of node k's patches. 0: a pairwise S.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub links: u64,
    /// With links: the distances stage 1 found pair by pair, before the cut replaced the far
    /// ones (what a pairwise S would have stored). For an object whose paths were traced on
    /// demand, never listed pair by pair, its share is the estimate made before the
    /// precompute (pairs of patches within the reach, counted on sample rows).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub pairwise_distances: u64,
    /// With links made closer in than the quadrature's near field (`translux-precompute
    /// --s-link-near K`): K, the near field of links in receiver sizes. Each link is then read
    /// at two distances, A_k (R(r − σ) + R(r + σ)) / 2, r being the representative's optical
    /// distance moved by the node's mean straight-line offset from it and σ (the
    /// [`arrays::DIST_SPREAD`] array, listed whenever this is) the spread of the node's
    /// straight-line distances from the receiver. A build that does not know this field
    /// refuses the bundle (the manifest denies unknown fields). None: links are read at
    /// their representative's distance alone.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub link_near: Option<f32>,
    /// With links cut by the profile's error bound (`translux-precompute
    /// --s-link-variation τ`): τ, the largest relative variation of the profile across a
    /// linked node at every translucency from ×1/8 to ×8; a translucency change groups
    /// receivers under the same bound. None: links cut by geometry alone (bundles made
    /// before the bound), whose receivers are grouped by geometry alone too.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub link_variation: Option<f32>,
    /// Records of the random walks of simulated objects (the `sim_*` arrays); 0: none.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub walks: u64,
    pub objects: Vec<SubsurfaceObject>,
}

fn is_zero(v: &u64) -> bool {
    *v == 0
}

/// One translucent object's S.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct SubsurfaceObject {
    pub name: String,
    /// `euclidean` (convex object) or `voxel` (shortest interior paths).
    pub method: String,
    /// S keeps pairs up to this radius (scene units): beyond it the profile carries less
    /// than `truncation_energy` of its energy.
    pub truncation_radius: f32,
    /// The stored optical distances reach this far (a margin over `truncation_radius`, so a
    /// more translucent profile can be applied without new geometry work).
    pub distance_radius: f32,
    pub truncation_energy: f32,
    pub voxels: u64,
    pub interior_voxels: u64,
    pub voxel_size: f32,
    /// max over columns of Σ_j A_j S_ji / A_i before enforcing ≤ 1, and how many columns
    /// had to be scaled down to it.
    pub max_column_energy: f32,
    pub scaled_columns: u64,
    /// Entries of S in the object's rows that gather from a cluster node whole (hierarchical
    /// S; 0 for a pairwise one), and all its entries (links included).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub links: u64,
    #[serde(default, skip_serializing_if = "is_zero")]
    pub entries: u64,
    /// A note when something fell back (e.g. no interior found: Euclidean distances used).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub warning: Option<String>,
    /// The random walks of a simulated object (`method` = `simulated`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub simulation: Option<SimulationInfo>,
    pub seconds: f64,
}

/// What the random walks of one simulated object did.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct SimulationInfo {
    /// Walks run (every patch, every group of channels with equal σs).
    pub walks: u64,
    /// Scattering events (one ray each).
    pub events: u64,
    /// Walks that left where the mesh has no surface, and walks cut as negligible.
    pub lost: u64,
    pub cut: u64,
    /// Relative standard error of a patch's re-emitted total at the built σa: median and
    /// largest over patches (the target is the material's `noise`).
    pub noise_median: f32,
    pub noise_max: f32,
    /// Stored records (source, length bin) of the object's rows.
    pub records: u64,
    /// The lowest σa (mm⁻¹) the stored walks serve: an override below it needs new walks.
    pub sigma_a_floor: [f32; 3],
}

/// How the transfer matrix T = (I − S F)⁻¹ S was computed and stored, and what storing it
/// cost in accuracy.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct TransferInfo {
    /// What is stored: `"f16 T - S, per-row scale"`.
    pub storage: String,
    /// How it was computed (`dense partial-pivot LU per channel (faer), f64`).
    pub method: String,
    /// Element-wise relative error |R_f16 − R| / |R| of the stored entries against the
    /// computed f64 values, over entries ≥ 10⁻⁴ of their row's largest: median and max.
    pub median_rel_error: f64,
    pub max_rel_error: f64,
    /// Relative error of the relit radiosity B with the stored T against the f64 T, for the
    /// scene's default lights: largest over patches with B above 1% of the peak, and
    /// ‖ΔB‖/‖B‖ over all patches.
    pub relight_max_rel_error: f64,
    pub relight_rel_error: f64,
    /// ‖(I − S F) T − S‖_max / ‖S‖_max of the f64 solution (LU accuracy).
    pub lu_residual: f64,
    pub seconds: f64,
}

/// How the per-patch environment visibility (`env_visibility.f16`) was estimated.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct EnvironmentInfo {
    /// Direction bins: `rows` bands uniform in cos θ (from +Y) × `cols` ranges of the map's u.
    pub rows: u32,
    pub cols: u32,
    /// Cosine cells per bin side (integrated without rays).
    pub cos_grid: u32,
    /// Visibility rays per bin side.
    pub rays_per_side: u32,
    /// Rays cast in all.
    pub rays: u64,
    pub seconds: f64,
}

/// Wall-clock time of one precompute stage.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct StageTime {
    pub stage: String,
    pub seconds: f64,
}

/// The manifest of a bundle.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// Always [`FORMAT`].
    pub format: String,
    /// Always [`FORMAT_VERSION`] for bundles this build can read.
    pub version: u32,
    /// Scene name (also the default bundle id).
    pub name: String,
    /// What it was built from: a scene file path or `builtin:NAME`.
    pub source: String,
    /// The precompute's version string.
    pub created_by: String,
    /// Millimetres per scene unit.
    pub unit_mm: f64,
    pub patch_count: u64,
    pub vertex_count: u64,
    pub occluder_count: u64,
    pub objects: Vec<ObjectInfo>,
    pub lights: Vec<Light>,
    pub camera: Camera,
    pub form_factors: FormFactorInfo,
    pub subsurface: SubsurfaceInfo,
    pub stages: Vec<StageTime>,
    /// The transfer matrix, when the bundle was precomputed with `--inverse`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub transfer: Option<TransferInfo>,
    /// The environment visibility, unless precomputed with `--env-bins 0`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub environment: Option<EnvironmentInfo>,
    /// Present when F is hierarchical: F̃ = C·P, where the `ff_*` arrays hold C, an
    /// `N × (N + M)` CSR matrix whose columns are the patches then the M cluster nodes of
    /// [`arrays::TREE_RANGE`], and P pulls the area-weighted mean radiosity of each node's
    /// patches. Absent: the `ff_*` arrays are the dense `N × N` F.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hierarchy: Option<HierarchyInfo>,
    /// Every array file, by array name (see [`arrays`]).
    pub arrays: BTreeMap<String, ArrayEntry>,
}

/// XXH3-64 of `bytes` as 16 lower-case hex digits (the manifest's checksum format).
pub fn checksum(bytes: &[u8]) -> String {
    format!("{:016x}", xxhash_rust::xxh3::xxh3_64(bytes))
}
