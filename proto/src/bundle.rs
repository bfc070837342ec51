//! The bundle: what `translux-precompute` writes and `translux-server` maps.
//!
//! A bundle is a folder. `manifest.json` describes the scene and lists every array file with
//! its element type, shape, byte length and XXH3-64 checksum; each array is a raw
//! little-endian file that is memory-mapped and cast in place (`bytemuck`), so a mapped file
//! is page-aligned and every element is naturally aligned.
//!
//! ```text
//! bundle/
//! ├── manifest.json          format, version, counts, units, objects, lights, camera, arrays{}
//! ├── patch_corners.f32      [N, 3, 3]  triangle corners of each patch (scene units)
//! ├── patch_normal.f32       [N, 3]     unit normal (the side that sends and receives light)
//! ├── patch_area.f32         [N]        area (scene units²)
//! ├── patch_object.u32       [N]        index into manifest.objects
//! ├── patch_albedo.f32       [N, 3]     ρ: S_ii of an opaque patch (0 for emitters)
//! ├── patch_emission.f32     [N, 3]     emitted exitance π·L_e (W·m⁻²)
//! ├── vertex_position.f32    [V, 3]     viewer mesh vertices (welded, split at creases)
//! ├── vertex_normal.f32      [V, 3]
//! ├── triangle_vertex.u32    [N, 3]     viewer triangle k = patch k
//! ├── occluder_tri.f32       [M, 3, 3]  the scene's source triangles, for shadow rays
//! ├── ff_row_ptr.u64         [N + 1]    F in CSR, rows are receivers (see `csr`)
//! ├── ff_col.u32             [nnz]
//! ├── ff_val.f32             [nnz]
//! ├── s_row_ptr.u64          [N + 1]    S in CSR: row j (exitance at j) lists sources i
//! ├── s_col.u32              [nnz_s]    (irradiance at i) and S_ji per RGB channel; opaque
//! ├── s_val.f32              [nnz_s, 3] patches hold their diagonal ρ, emitters nothing
//! ├── dist_row_ptr.u64       [N + 1]    optical path r_ij (scene units) between patches of
//! ├── dist_col.u32           [nnz_d]    the same translucent object, truncated where the
//! ├── dist_val.f32           [nnz_d]    profile is negligible; S is rebuilt from these
//! ├── dist_kind.u32          [nnz_d]    0: a path inside the object (or along a thin
//! │                                     sheet's side: reflectance), 1: across a thin sheet
//! │                                     to its other side (transmittance profile)
//! ├── dist_material_len.f32  [nnz_d, 4] of a heterogeneous object's path: the length r_k it
//! │                                     travels in medium k (Σ_k r_k = dist_val); all 0
//! │                                     for a homogeneous object
//! ├── patch_material.u32     [N]        medium of a heterogeneous object's patch (under its
//! │                                     centroid; S_ii's profile), 0 for every other patch
//! │  only with `--inverse` (manifest `transfer` present):
//! ├── transfer.f16           [N, N, 3]  R = T − S with T = (I − S F)⁻¹ S, row j (receiver)
//! │                                     by column k (source), RGB; IEEE half floats, each
//! │                                     row and channel scaled to its largest |value| (≤ 1)
//! ├── transfer_scale.f32     [N, 3]     that scale: R_jk,c = transfer[j,k,c] · scale[j,c]
//! │  unless precomputed with `--env-bins 0` (manifest `environment` present):
//! └── env_visibility.f16     [N, R, C]  V_ik = ∫_bin k visible_i(ω) max(n_i·ω, 0) dω (sr) for
//!                                       the R × C equal-area direction bins of
//!                                       `translux_engine::envmap::Bins`; IEEE half floats
//! ```
//!
//! `transfer.f16` row j, channel c: element (j·N + k)·3 + c, 2 bytes each (byte offset
//! 2·((j·N + k)·3 + c)). Why T − S and not T: T's diagonal holds ρ (≈ 0.7) while its
//! off-diagonal entries are ~1/N of that, below f16's normal range after row scaling; S is
//! in the bundle already (sparse, f32), so only the smooth inter-reflected part is stored
//! in half precision.
//!
//! Byte offsets inside an array file: element `k` of a `[N, c]` array of 4-byte type is at
//! `4·(k·c + component)`; `ff_row_ptr` entries are 8 bytes. There are no headers: the manifest
//! holds the shapes, and the loader refuses any file whose length or checksum disagrees.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::light::{Camera, Light};
use crate::scene::Material;

/// The `format` field of every manifest.
pub const FORMAT: &str = "translux-bundle";
/// Bumped whenever the layout changes; this build writes it and reads it and every version
/// from [`OLDEST_READABLE_VERSION`] on (version 5 added hierarchical F, see
/// [`Manifest::hierarchy`]; a version 4 bundle is a dense one and reads unchanged).
pub const FORMAT_VERSION: u32 = 5;
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
}

/// How S was built, per translucent object.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct SubsurfaceInfo {
    /// Stored entries of S (diagonals of opaque patches included).
    pub nnz: u64,
    /// Stored optical distances.
    pub distance_nnz: u64,
    pub objects: Vec<SubsurfaceObject>,
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
    /// A note when something fell back (e.g. no interior found: Euclidean distances used).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub warning: Option<String>,
    pub seconds: f64,
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

// ---------------------------------------------------------------------------------------------
// The verifying, memory-mapping loader.
// ---------------------------------------------------------------------------------------------

/// The environment visibility `[N, rows, cols]` as IEEE half-float bits (verified at open:
/// finite and ≥ 0); patch i's `rows · cols` bins are [`EnvVisibilityView::row`].
#[derive(Debug, Clone, Copy)]
pub struct EnvVisibilityView<'a> {
    pub rows: u32,
    pub cols: u32,
    pub bits: &'a [u16],
}

impl<'a> EnvVisibilityView<'a> {
    /// Bins per patch.
    pub fn bins(&self) -> usize {
        self.rows as usize * self.cols as usize
    }

    /// Patch i's visibility per bin (half-float bits).
    pub fn row(&self, i: usize) -> &'a [u16] {
        let k = self.bins();
        &self.bits[k * i..k * (i + 1)]
    }
}

/// The stored transfer matrix R = T − S (see the layout above): `bits` holds IEEE half
/// floats `[N, N, 3]` as raw bits, `scale` the per-row, per-channel factors.
#[derive(Debug, Clone, Copy)]
pub struct TransferView<'a> {
    pub n: usize,
    pub bits: &'a [u16],
    pub scale: &'a [[f32; 3]],
}

impl<'a> TransferView<'a> {
    /// Row j: 3N half-float bits (column k, channel c at 3k + c).
    pub fn row(&self, j: usize) -> &'a [u16] {
        &self.bits[3 * self.n * j..3 * self.n * (j + 1)]
    }
}

// Array files are raw little-endian and cast in place: a big-endian build would read garbage.
#[cfg(target_endian = "big")]
compile_error!(
    "translux bundles hold little-endian arrays that are cast in place; big-endian targets are not supported"
);

/// The cluster tree of a hierarchical F ([`Bundle::tree`]): node k covers the patches
/// `perm[range[k][0]..range[k][1]]`.
#[derive(Debug, Clone, Copy)]
pub struct TreeView<'a> {
    pub perm: &'a [u32],
    pub range: &'a [[u32; 2]],
}

/// The array files every bundle of [`FORMAT_VERSION`] holds, with their element types.
/// A manifest may list further arrays; the loader verifies and maps those too.
pub const REQUIRED_ARRAYS: &[(&str, DType)] = &[
    (arrays::PATCH_CORNERS, DType::F32),
    (arrays::PATCH_NORMAL, DType::F32),
    (arrays::PATCH_AREA, DType::F32),
    (arrays::PATCH_OBJECT, DType::U32),
    (arrays::PATCH_ALBEDO, DType::F32),
    (arrays::PATCH_EMISSION, DType::F32),
    (arrays::VERTEX_POSITION, DType::F32),
    (arrays::VERTEX_NORMAL, DType::F32),
    (arrays::TRIANGLE_VERTEX, DType::U32),
    (arrays::OCCLUDER_TRI, DType::F32),
    (arrays::FF_ROW_PTR, DType::U64),
    (arrays::FF_COL, DType::U32),
    (arrays::FF_VAL, DType::F32),
    (arrays::S_ROW_PTR, DType::U64),
    (arrays::S_COL, DType::U32),
    (arrays::S_VAL, DType::F32),
    (arrays::DIST_ROW_PTR, DType::U64),
    (arrays::DIST_COL, DType::U32),
    (arrays::DIST_VAL, DType::F32),
    (arrays::DIST_KIND, DType::U32),
    (arrays::DIST_MATERIAL_LEN, DType::F32),
    (arrays::PATCH_MATERIAL, DType::U32),
];

/// What the first dimension of a required array counts.
#[derive(Debug, Clone, Copy)]
enum Rows {
    /// `patch_count`
    Patches,
    /// `patch_count + 1`
    PatchesPlusOne,
    /// `vertex_count`
    Vertices,
    /// `occluder_count`
    Occluders,
    /// `form_factors.nnz`
    Nnz,
    /// `subsurface.nnz`
    SNnz,
    /// `subsurface.distance_nnz`
    DistNnz,
}

/// The documented shape of each required array: (name, rows, trailing dimensions).
const SHAPES: &[(&str, Rows, &[u64])] = &[
    (arrays::PATCH_CORNERS, Rows::Patches, &[3, 3]),
    (arrays::PATCH_NORMAL, Rows::Patches, &[3]),
    (arrays::PATCH_AREA, Rows::Patches, &[]),
    (arrays::PATCH_OBJECT, Rows::Patches, &[]),
    (arrays::PATCH_ALBEDO, Rows::Patches, &[3]),
    (arrays::PATCH_EMISSION, Rows::Patches, &[3]),
    (arrays::VERTEX_POSITION, Rows::Vertices, &[3]),
    (arrays::VERTEX_NORMAL, Rows::Vertices, &[3]),
    (arrays::TRIANGLE_VERTEX, Rows::Patches, &[3]),
    (arrays::OCCLUDER_TRI, Rows::Occluders, &[3, 3]),
    (arrays::FF_ROW_PTR, Rows::PatchesPlusOne, &[]),
    (arrays::FF_COL, Rows::Nnz, &[]),
    (arrays::FF_VAL, Rows::Nnz, &[]),
    (arrays::S_ROW_PTR, Rows::PatchesPlusOne, &[]),
    (arrays::S_COL, Rows::SNnz, &[]),
    (arrays::S_VAL, Rows::SNnz, &[3]),
    (arrays::DIST_ROW_PTR, Rows::PatchesPlusOne, &[]),
    (arrays::DIST_COL, Rows::DistNnz, &[]),
    (arrays::DIST_VAL, Rows::DistNnz, &[]),
    (arrays::DIST_KIND, Rows::DistNnz, &[]),
    (arrays::DIST_MATERIAL_LEN, Rows::DistNnz, &[4]),
    (arrays::PATCH_MATERIAL, Rows::Patches, &[]),
];

/// The file name of array `name` with element type `dtype` (`ff_col.u32`).
pub fn array_file_name(name: &str, dtype: DType) -> String {
    format!("{name}.{}", dtype.name())
}

/// Whether `name` may name an array: non-empty, lower-case ASCII letters, digits and `_`
/// only (so that `NAME.DTYPE` is a plain file name inside the bundle folder, never a path).
pub fn is_valid_array_name(name: &str) -> bool {
    !name.is_empty()
        && name
            .bytes()
            .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_')
}

/// Why a bundle could not be opened. Every message starts with or names the file concerned.
#[derive(Debug, thiserror::Error)]
pub enum BundleError {
    /// A file (or the bundle folder itself) does not exist.
    #[error("{file} is missing")]
    Missing { file: String },
    /// A required array is not listed in the manifest.
    #[error("{file} is missing from {MANIFEST_FILE}")]
    NotListed { file: String },
    /// Reading or mapping a file failed.
    #[error("{file}: {error}")]
    Io { file: String, error: std::io::Error },
    /// `manifest.json` is not JSON, or not a [`Manifest`].
    #[error("{MANIFEST_FILE}: line {line} column {column}: {what}",
        line = .0.line, column = .0.column, what = json_cause(.0))]
    Manifest(crate::JsonError),
    /// The manifest's `format` is not [`FORMAT`].
    #[error("{MANIFEST_FILE}: format is {found:?}, expected {FORMAT:?}")]
    Format { found: String },
    /// The manifest's `version` is not one this build reads.
    #[error(
        "{MANIFEST_FILE}: bundle version {found} is not supported (this build reads versions \
         {OLDEST_READABLE_VERSION} to {FORMAT_VERSION}); rebuild the bundle with this build's \
         translux-precompute"
    )]
    Version { found: u32 },
    /// A file is shorter than the manifest says.
    #[error("{file} is truncated: {got} bytes, manifest says {expected}")]
    Truncated {
        file: String,
        got: u64,
        expected: u64,
    },
    /// A file is longer than the manifest says.
    #[error("{file} is too long: {got} bytes, manifest says {expected}")]
    TooLong {
        file: String,
        got: u64,
        expected: u64,
    },
    /// A file's XXH3-64 differs from the manifest's.
    #[error("{file} is corrupt: checksum {got} != manifest {expected}")]
    Corrupt {
        file: String,
        got: String,
        expected: String,
    },
    /// A manifest entry or a file's content breaks a rule of the format.
    #[error("{file}: {reason}")]
    Invalid { file: String, reason: String },
    /// The form-factor arrays are not a valid CSR matrix; `file` is the array at fault.
    #[error("{file}: F is not a valid CSR matrix: {error}")]
    Csr {
        file: String,
        error: crate::csr::CsrError,
    },
}

fn json_cause(e: &crate::JsonError) -> String {
    if e.path.is_empty() || e.path == "." {
        e.message.clone()
    } else {
        format!("{}: {}", e.path, e.message)
    }
}

impl BundleError {
    /// The file the error is about (`manifest.json` for manifest errors).
    pub fn file(&self) -> &str {
        match self {
            BundleError::Missing { file }
            | BundleError::NotListed { file }
            | BundleError::Io { file, .. }
            | BundleError::Truncated { file, .. }
            | BundleError::TooLong { file, .. }
            | BundleError::Corrupt { file, .. }
            | BundleError::Invalid { file, .. }
            | BundleError::Csr { file, .. } => file,
            BundleError::Manifest(_) | BundleError::Format { .. } | BundleError::Version { .. } => {
                MANIFEST_FILE
            }
        }
    }
}

fn invalid(file: impl Into<String>, reason: impl Into<String>) -> BundleError {
    BundleError::Invalid {
        file: file.into(),
        reason: reason.into(),
    }
}

/// How [`Bundle::open_with`] verifies. Lengths, shapes, counts and the CSR invariants are
/// always checked; only the checksum pass (one read of every byte) is optional.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OpenOptions {
    /// Recompute every array's XXH3-64 and compare it with the manifest (default: true).
    pub verify_checksums: bool,
}

impl Default for OpenOptions {
    fn default() -> Self {
        Self {
            verify_checksums: true,
        }
    }
}

/// Array files up to this size are read into memory when a bundle opens instead of being
/// mapped: a private copy cannot change under the server, so truncating or rewriting such a
/// file in place cannot bring the process down with `SIGBUS`. Larger arrays (F, S, T of a
/// real scene: gigabytes) stay memory-mapped; see [`map_file`] for what that asks of
/// operators.
pub const COPY_ON_OPEN_BYTES: u64 = 16 << 20;

/// One array file's bytes: mapped, or (small files) a private copy. An empty file has
/// neither.
#[derive(Debug)]
enum ArrayBytes {
    Empty,
    Mapped(memmap2::Mmap),
    /// `u64` words so the bytes are 8-aligned for every dtype; the length in bytes.
    Copied(Vec<u64>, usize),
}

#[derive(Debug)]
struct MappedArray {
    dtype: DType,
    data: ArrayBytes,
}

impl MappedArray {
    fn bytes(&self) -> &[u8] {
        match &self.data {
            ArrayBytes::Empty => &[],
            ArrayBytes::Mapped(m) => m,
            ArrayBytes::Copied(words, len) => &bytemuck::cast_slice(words)[..*len],
        }
    }

    /// Whether the bytes are a private copy (not mapped).
    fn is_copied(&self) -> bool {
        matches!(self.data, ArrayBytes::Copied(..))
    }
}

/// `path` must be a regular file (after symlinks) before it is opened: opening a FIFO for
/// reading blocks until some writer appears, which would hang the loader (and every bundle
/// queued behind it); a device or socket is no bundle file either.
fn check_regular(path: &Path, name: &str) -> Result<(), BundleError> {
    match std::fs::metadata(path) {
        Ok(m) if m.is_file() => Ok(()),
        Ok(_) => Err(invalid(name, "is not a regular file")),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(BundleError::Missing {
            file: name.to_string(),
        }),
        Err(error) => Err(BundleError::Io {
            file: name.to_string(),
            error,
        }),
    }
}

/// Maps `file` read-only.
///
/// # Safety
///
/// `memmap2::Mmap::map` is unsafe because the slice it yields changes (or the process gets
/// `SIGBUS`) if another process modifies or truncates the file while it is mapped. Bundles
/// are immutable once they are in place: the writer fills a temporary folder and renames it
/// into place, and replaces a bundle by renaming the old folder aside before deleting it, so
/// a mapped file is never written to. Editing a bundle's files by hand while a server maps
/// them would break this assumption: operators must never truncate, rewrite or `cp` over
/// a served bundle's files in place (replace the folder by a rename; deleting a file or
/// the folder is safe, its pages stay until unmapped). Only arrays over
/// [`COPY_ON_OPEN_BYTES`] are mapped; smaller ones are private copies.
#[expect(
    unsafe_code,
    reason = "memory-mapping a file is unsafe; bundles are immutable once renamed into place"
)]
fn map_file(file: &std::fs::File) -> std::io::Result<memmap2::Mmap> {
    // SAFETY: `file` was opened read-only and the mapping is read-only. Bundle files are never
    // modified after the writer renames the bundle folder into place (write-to-temp-then-rename,
    // replacement by rename-aside-then-delete), so the mapped bytes do not change underneath
    // the slices handed out; only a concurrent writer bypassing that protocol could violate it.
    unsafe { memmap2::Mmap::map(file) }
}

/// A bundle folder, verified and memory-mapped.
///
/// Opening it checks the manifest and every array (see [`Bundle::open`]); afterwards the
/// accessors hand out zero-copy slices of the mapped files and never fail. It is `Send` and
/// `Sync`: share it behind an `Arc`.
#[derive(Debug)]
pub struct Bundle {
    dir: PathBuf,
    manifest: Manifest,
    manifest_bytes: u64,
    arrays: BTreeMap<String, MappedArray>,
    /// The rows of F, equal to patch_count.
    n_patches: usize,
    /// Cluster nodes of a hierarchical F (0 for a dense one): F has N + M columns.
    n_nodes: usize,
}

/// The counts of a manifest, as `usize`.
struct Counts {
    patches: u64,
    vertices: u64,
    occluders: u64,
    nnz: u64,
    s_nnz: u64,
    dist_nnz: u64,
}

impl Counts {
    fn rows(&self, rows: Rows) -> Result<(u64, String), BundleError> {
        Ok(match rows {
            Rows::Patches => (self.patches, "N = patch_count".into()),
            Rows::PatchesPlusOne => (
                self.patches
                    .checked_add(1)
                    .ok_or_else(|| invalid(MANIFEST_FILE, "patch_count is too large"))?,
                "N + 1 with N = patch_count".into(),
            ),
            Rows::Vertices => (self.vertices, "V = vertex_count".into()),
            Rows::Occluders => (self.occluders, "M = occluder_count".into()),
            Rows::Nnz => (self.nnz, "nnz = form_factors.nnz".into()),
            Rows::SNnz => (self.s_nnz, "nnz_s = subsurface.nnz".into()),
            Rows::DistNnz => (self.dist_nnz, "nnz_d = subsurface.distance_nnz".into()),
        })
    }
}

fn to_usize(value: u64, file: &str, what: &str) -> Result<usize, BundleError> {
    usize::try_from(value).map_err(|_| {
        invalid(
            file,
            format!("{what} = {value} does not fit this machine's memory"),
        )
    })
}

/// Checks a manifest entry against its own name and against itself (file name, byte count =
/// elements × dtype size); returns the byte count.
fn check_entry(name: &str, entry: &ArrayEntry) -> Result<u64, BundleError> {
    let expected_file = array_file_name(name, entry.dtype);
    if !is_valid_array_name(name) {
        return Err(invalid(
            MANIFEST_FILE,
            format!("array name {name:?} is not lower-case letters, digits and '_'"),
        ));
    }
    if entry.file != expected_file {
        return Err(invalid(
            MANIFEST_FILE,
            format!(
                "array {name} is stored as {:?}, expected {expected_file:?}",
                entry.file
            ),
        ));
    }
    let bytes = entry
        .shape
        .iter()
        .try_fold(entry.dtype.size() as u64, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| {
            invalid(
                &expected_file,
                format!("shape {:?} is too large", entry.shape),
            )
        })?;
    if bytes != entry.bytes {
        return Err(invalid(
            MANIFEST_FILE,
            format!(
                "{expected_file}: manifest lists {} bytes but shape {:?} of {} holds {bytes}",
                entry.bytes,
                entry.shape,
                entry.dtype.name()
            ),
        ));
    }
    Ok(bytes)
}

/// Opens, length-checks, maps and (optionally) checksums one array file.
fn map_array(
    dir: &Path,
    entry: &ArrayEntry,
    bytes: u64,
    verify_checksum: bool,
) -> Result<MappedArray, BundleError> {
    let file_name = entry.file.as_str();
    let io = |error: std::io::Error| BundleError::Io {
        file: file_name.to_string(),
        error,
    };
    let path = dir.join(file_name);
    check_regular(&path, file_name)?;
    let file = match std::fs::File::open(&path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(BundleError::Missing {
                file: file_name.to_string(),
            });
        }
        Err(e) => return Err(io(e)),
    };
    let meta = file.metadata().map_err(io)?;
    if !meta.is_file() {
        return Err(invalid(file_name, "is not a regular file"));
    }
    let got = meta.len();
    if got < bytes {
        return Err(BundleError::Truncated {
            file: file_name.to_string(),
            got,
            expected: bytes,
        });
    }
    if got > bytes {
        return Err(BundleError::TooLong {
            file: file_name.to_string(),
            got,
            expected: bytes,
        });
    }
    let data = if got == 0 {
        ArrayBytes::Empty
    } else if got <= COPY_ON_OPEN_BYTES {
        use std::io::Read;
        let len = got as usize;
        let mut words = vec![0u64; len.div_ceil(8)];
        let buf: &mut [u8] = bytemuck::cast_slice_mut(&mut words);
        let mut reader = &file;
        // `read_exact` fails if the file shrank since the length check.
        reader.read_exact(&mut buf[..len]).map_err(|e| {
            if e.kind() == std::io::ErrorKind::UnexpectedEof {
                BundleError::Truncated {
                    file: file_name.to_string(),
                    got: 0,
                    expected: bytes,
                }
            } else {
                io(e)
            }
        })?;
        ArrayBytes::Copied(words, len)
    } else {
        let map = map_file(&file).map_err(io)?;
        if map.len() as u64 != bytes {
            // The file changed between the length check and the mapping.
            return Err(BundleError::Truncated {
                file: file_name.to_string(),
                got: map.len() as u64,
                expected: bytes,
            });
        }
        ArrayBytes::Mapped(map)
    };
    let mapped = MappedArray {
        dtype: entry.dtype,
        data,
    };
    if verify_checksum {
        let sum = checksum(mapped.bytes());
        if sum != entry.xxh3 {
            return Err(BundleError::Corrupt {
                file: file_name.to_string(),
                got: sum,
                expected: entry.xxh3.clone(),
            });
        }
    }
    Ok(mapped)
}

/// Which file a CSR violation is about, for the matrix stored as `[row_ptr, col, val]`.
fn csr_file(error: &crate::csr::CsrError, names: [&str; 3]) -> String {
    use crate::csr::CsrError as E;
    let [rp, col, val] = names;
    match error {
        E::RowPtrLength { .. } | E::RowPtrStart(_) | E::RowPtrDecreasing { .. } => {
            array_file_name(rp, DType::U64)
        }
        E::NnzMismatch { .. } => format!(
            "{}/{}/{}",
            array_file_name(rp, DType::U64),
            array_file_name(col, DType::U32),
            array_file_name(val, DType::F32)
        ),
        E::ColumnOutOfRange { .. } | E::ColumnsUnsorted { .. } => array_file_name(col, DType::U32),
        E::NonFinite { .. } => array_file_name(val, DType::F32),
    }
}

const FF_NAMES: [&str; 3] = [arrays::FF_ROW_PTR, arrays::FF_COL, arrays::FF_VAL];
const S_NAMES: [&str; 3] = [arrays::S_ROW_PTR, arrays::S_COL, arrays::S_VAL];
const DIST_NAMES: [&str; 3] = [arrays::DIST_ROW_PTR, arrays::DIST_COL, arrays::DIST_VAL];

impl Bundle {
    /// Opens the bundle in `dir` with full verification, checksums included
    /// ([`OpenOptions::default`]).
    ///
    /// In: a bundle folder. Out: the mapped bundle, or the first problem found, naming its
    /// file. Checked: the manifest parses, its format and version are this build's; every
    /// required array (see [`REQUIRED_ARRAYS`]) is listed with its dtype and the shape the
    /// counts imply, and every listed file exists with exactly the listed length and checksum;
    /// F is a valid `N × N` CSR matrix; `triangle_vertex < vertex_count`; the objects' patch
    /// ranges are contiguous, in order and cover `0..N`, and `patch_object` agrees with them;
    /// areas are finite and positive; the other geometry arrays are finite.
    pub fn open(dir: &Path) -> Result<Bundle, BundleError> {
        Self::open_with(dir, OpenOptions::default())
    }

    /// [`Bundle::open`] with options (skipping the checksum pass saves one read of every
    /// byte; every other check still runs).
    pub fn open_with(dir: &Path, opts: OpenOptions) -> Result<Bundle, BundleError> {
        if !dir.is_dir() {
            return Err(BundleError::Missing {
                file: dir.display().to_string(),
            });
        }
        check_regular(&dir.join(MANIFEST_FILE), MANIFEST_FILE)?;
        let text = match std::fs::read_to_string(dir.join(MANIFEST_FILE)) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(BundleError::Missing {
                    file: MANIFEST_FILE.into(),
                });
            }
            Err(error) => {
                return Err(BundleError::Io {
                    file: MANIFEST_FILE.into(),
                    error,
                });
            }
        };
        let manifest: Manifest = crate::parse_json(&text).map_err(BundleError::Manifest)?;
        if manifest.format != FORMAT {
            return Err(BundleError::Format {
                found: manifest.format,
            });
        }
        if !(OLDEST_READABLE_VERSION..=FORMAT_VERSION).contains(&manifest.version) {
            return Err(BundleError::Version {
                found: manifest.version,
            });
        }
        let counts = Counts {
            patches: manifest.patch_count,
            vertices: manifest.vertex_count,
            occluders: manifest.occluder_count,
            nnz: manifest.form_factors.nnz,
            s_nnz: manifest.subsurface.nnz,
            dist_nnz: manifest.subsurface.distance_nnz,
        };
        let n_patches = to_usize(counts.patches, MANIFEST_FILE, "patch_count")?;

        // The transfer matrix: both arrays, with these shapes, when the manifest says so.
        if manifest.transfer.is_some() {
            let n = counts.patches;
            for (name, dtype, shape) in [
                (arrays::TRANSFER, DType::F16, vec![n, n, 3]),
                (arrays::TRANSFER_SCALE, DType::F32, vec![n, 3]),
            ] {
                let file = array_file_name(name, dtype);
                let entry = manifest
                    .arrays
                    .get(name)
                    .ok_or_else(|| BundleError::NotListed { file: file.clone() })?;
                if entry.dtype != dtype || entry.shape != shape {
                    return Err(invalid(
                        &file,
                        format!(
                            "manifest lists {} {:?}, expected {} {shape:?} (N = patch_count)",
                            entry.dtype.name(),
                            entry.shape,
                            dtype.name()
                        ),
                    ));
                }
            }
        }

        // The environment visibility: listed with its shape when the manifest says so.
        if let Some(env) = &manifest.environment {
            let file = array_file_name(arrays::ENV_VISIBILITY, DType::F16);
            let shape = vec![counts.patches, u64::from(env.rows), u64::from(env.cols)];
            let entry = manifest
                .arrays
                .get(arrays::ENV_VISIBILITY)
                .ok_or_else(|| BundleError::NotListed { file: file.clone() })?;
            if env.rows == 0 || env.cols == 0 || entry.dtype != DType::F16 || entry.shape != shape {
                return Err(invalid(
                    &file,
                    format!(
                        "manifest lists {} {:?}, expected f16 {shape:?} (N = patch_count, \
                         environment.rows and .cols >= 1)",
                        entry.dtype.name(),
                        entry.shape,
                    ),
                ));
            }
        }

        // The cluster tree: both arrays, with these shapes, when the manifest says so.
        let n_nodes = match &manifest.hierarchy {
            Some(h) => {
                let n = counts.patches;
                for (name, shape) in [
                    (arrays::TREE_PERM, vec![n]),
                    (arrays::TREE_RANGE, vec![h.nodes, 2]),
                ] {
                    let file = array_file_name(name, DType::U32);
                    let entry = manifest
                        .arrays
                        .get(name)
                        .ok_or_else(|| BundleError::NotListed { file: file.clone() })?;
                    if entry.dtype != DType::U32 || entry.shape != shape {
                        return Err(invalid(
                            &file,
                            format!(
                                "manifest lists {} {:?}, expected u32 {shape:?} (N = \
                                 patch_count, M = hierarchy.nodes)",
                                entry.dtype.name(),
                                entry.shape,
                            ),
                        ));
                    }
                }
                to_usize(h.nodes, MANIFEST_FILE, "hierarchy.nodes")?
            }
            None => 0,
        };
        if n_patches
            .checked_add(n_nodes)
            .is_none_or(|c| c > u32::MAX as usize)
        {
            return Err(invalid(
                MANIFEST_FILE,
                "patch_count + hierarchy.nodes does not fit a u32 column index",
            ));
        }

        // The required arrays: listed, with the right dtype and shape.
        for &(name, dtype) in REQUIRED_ARRAYS {
            let file = array_file_name(name, dtype);
            let entry = manifest
                .arrays
                .get(name)
                .ok_or_else(|| BundleError::NotListed { file: file.clone() })?;
            if entry.dtype != dtype {
                return Err(invalid(
                    &file,
                    format!(
                        "manifest lists dtype {}, expected {}",
                        entry.dtype.name(),
                        dtype.name()
                    ),
                ));
            }
            let Some(&(_, rows, tail)) = SHAPES.iter().find(|(n, _, _)| *n == name) else {
                return Err(invalid(&file, "no documented shape (a bug in this loader)"));
            };
            let (n, label) = counts.rows(rows)?;
            let expected: Vec<u64> = std::iter::once(n).chain(tail.iter().copied()).collect();
            if entry.shape != expected {
                return Err(invalid(
                    &file,
                    format!(
                        "shape {:?} does not match the manifest's counts: expected {expected:?} ({label} = {n})",
                        entry.shape
                    ),
                ));
            }
        }

        // Every listed array (required or not): consistent entry, file on disk, checksum.
        let mut mapped = BTreeMap::new();
        for (name, entry) in &manifest.arrays {
            let bytes = check_entry(name, entry)?;
            let array = map_array(dir, entry, bytes, opts.verify_checksums)?;
            mapped.insert(name.clone(), array);
        }

        let bundle = Bundle {
            dir: dir.to_path_buf(),
            manifest,
            manifest_bytes: text.len() as u64,
            arrays: mapped,
            n_patches,
            n_nodes,
        };
        bundle.check_contents()?;
        Ok(bundle)
    }

    /// The content rules that need the mapped arrays (see [`Bundle::open`]).
    fn check_contents(&self) -> Result<(), BundleError> {
        let n = self.n_patches;

        // Objects: contiguous runs covering 0..N, and patch_object agrees.
        let object_file = array_file_name(arrays::PATCH_OBJECT, DType::U32);
        let patch_object = self.patch_objects();
        let n_objects = self.manifest.objects.len();
        let mut end = 0u64;
        for (o, object) in self.manifest.objects.iter().enumerate() {
            if object.first_patch != end {
                return Err(invalid(
                    MANIFEST_FILE,
                    format!(
                        "objects[{o}] ({:?}) starts at patch {} but the previous object ends at {end}",
                        object.name, object.first_patch
                    ),
                ));
            }
            end = object.first_patch.saturating_add(object.patch_count);
            if end > n as u64 {
                return Err(invalid(
                    MANIFEST_FILE,
                    format!(
                        "objects[{o}] ({:?}) ends at patch {end} but patch_count is {n}",
                        object.name
                    ),
                ));
            }
            let first = object.first_patch as usize;
            let run = patch_object.get(first..end as usize).unwrap_or(&[]);
            for (k, &v) in (first..).zip(run) {
                if v as usize >= n_objects {
                    return Err(invalid(
                        &object_file,
                        format!("patch {k} names object {v} but the manifest lists {n_objects}"),
                    ));
                }
                if v as usize != o {
                    return Err(invalid(
                        &object_file,
                        format!(
                            "patch {k} names object {v} but lies in the patch range of objects[{o}] ({:?})",
                            object.name
                        ),
                    ));
                }
            }
        }
        if end != n as u64 {
            return Err(invalid(
                MANIFEST_FILE,
                format!("the objects cover patches 0..{end} but patch_count is {n}"),
            ));
        }

        // Areas finite and positive; other geometry finite.
        let area_file = array_file_name(arrays::PATCH_AREA, DType::F32);
        if let Some((k, a)) = self
            .patch_areas()
            .iter()
            .enumerate()
            .find(|(_, a)| !(a.is_finite() && **a > 0.0))
        {
            return Err(invalid(
                area_file,
                format!("patch {k} has area {a}, expected finite and > 0"),
            ));
        }
        for name in [
            arrays::PATCH_CORNERS,
            arrays::PATCH_NORMAL,
            arrays::PATCH_ALBEDO,
            arrays::PATCH_EMISSION,
            arrays::VERTEX_POSITION,
            arrays::VERTEX_NORMAL,
            arrays::OCCLUDER_TRI,
        ] {
            if let Some((k, v)) = self
                .f32s(name)
                .iter()
                .enumerate()
                .find(|(_, v)| !v.is_finite())
            {
                return Err(invalid(
                    array_file_name(name, DType::F32),
                    format!("element {k} is {v}, expected a finite number"),
                ));
            }
        }

        // Viewer triangles index existing vertices.
        let v_count = self.manifest.vertex_count;
        if let Some((k, &v)) = self
            .u32s(arrays::TRIANGLE_VERTEX)
            .iter()
            .enumerate()
            .find(|&(_, &v)| u64::from(v) >= v_count)
        {
            return Err(invalid(
                array_file_name(arrays::TRIANGLE_VERTEX, DType::U32),
                format!(
                    "triangle {} corner {} is vertex {v} but vertex_count is {v_count}",
                    k / 3,
                    k % 3
                ),
            ));
        }

        // F is an N × N CSR matrix, or C an N × (N + M) one over the cluster tree, whose
        // permutation and ranges are valid.
        if self.manifest.hierarchy.is_some() {
            self.check_tree()?;
        }
        crate::csr::CsrView::new_checked(
            n,
            n + self.n_nodes,
            self.u64s(arrays::FF_ROW_PTR),
            self.u32s(arrays::FF_COL),
            self.f32s(arrays::FF_VAL),
        )
        .map_err(|error| BundleError::Csr {
            file: csr_file(&error, FF_NAMES),
            error,
        })?;

        // S is an N × N CSR matrix of RGB values, non-negative; distances likewise, scalar.
        let s = crate::csr::CsrView::<[f32; 3]>::new_checked(
            n,
            n,
            self.u64s(arrays::S_ROW_PTR),
            self.u32s(arrays::S_COL),
            bytemuck::try_cast_slice(self.f32s(arrays::S_VAL)).unwrap_or(&[]),
        )
        .map_err(|error| BundleError::Csr {
            file: csr_file(&error, S_NAMES),
            error,
        })?;
        if let Some(k) = s.val().iter().position(|v| v.iter().any(|&x| x < 0.0)) {
            return Err(invalid(
                array_file_name(arrays::S_VAL, DType::F32),
                format!("entry {k} is negative; S re-emits light, it never absorbs below 0"),
            ));
        }
        let d = crate::csr::CsrView::<f32>::new_checked(
            n,
            n,
            self.u64s(arrays::DIST_ROW_PTR),
            self.u32s(arrays::DIST_COL),
            self.f32s(arrays::DIST_VAL),
        )
        .map_err(|error| BundleError::Csr {
            file: csr_file(&error, DIST_NAMES),
            error,
        })?;
        if let Some(k) = d.val().iter().position(|&x| x < 0.0) {
            return Err(invalid(
                array_file_name(arrays::DIST_VAL, DType::F32),
                format!("distance {k} is negative"),
            ));
        }
        // Distance kinds: 0 (same side / interior) or 1 (a thin sheet's other side).
        if let Some((k, &v)) = self
            .u32s(arrays::DIST_KIND)
            .iter()
            .enumerate()
            .find(|&(_, &v)| v > 1)
        {
            return Err(invalid(
                array_file_name(arrays::DIST_KIND, DType::U32),
                format!("distance {k} has kind {v}, expected 0 (same side) or 1 (other side)"),
            ));
        }
        // Per-medium path lengths: finite and ≥ 0; media indices within the limit.
        if let Some((k, v)) = self
            .f32s(arrays::DIST_MATERIAL_LEN)
            .iter()
            .enumerate()
            .find(|(_, v)| !(v.is_finite() && **v >= 0.0))
        {
            return Err(invalid(
                array_file_name(arrays::DIST_MATERIAL_LEN, DType::F32),
                format!(
                    "distance {} medium {} has length {v}, expected finite and >= 0",
                    k / 4,
                    k % 4
                ),
            ));
        }
        let limit = crate::scene::MAX_HETEROGENEOUS_MATERIALS as u32;
        if let Some((k, &m)) = self
            .u32s(arrays::PATCH_MATERIAL)
            .iter()
            .enumerate()
            .find(|&(_, &m)| m >= limit)
        {
            return Err(invalid(
                array_file_name(arrays::PATCH_MATERIAL, DType::U32),
                format!("patch {k} names medium {m}; there are at most {limit}"),
            ));
        }
        // Environment visibility: finite half floats >= 0 (no sign bit unless zero).
        if let Some(v) = self.environment_visibility()
            && let Some(k) = v
                .bits
                .iter()
                .position(|&b| b & 0x7c00 == 0x7c00 || (b & 0x8000 != 0 && b != 0x8000))
        {
            return Err(invalid(
                array_file_name(arrays::ENV_VISIBILITY, DType::F16),
                format!(
                    "element {k} (patch {}, bin {}) is not a finite number >= 0",
                    k / v.bins().max(1),
                    k % v.bins().max(1)
                ),
            ));
        }
        // The transfer matrix: finite half floats (exponent bits not all ones), scales
        // finite and ≥ 0.
        if let Some(t) = self.transfer() {
            if let Some(k) = t.bits.iter().position(|&b| b & 0x7c00 == 0x7c00) {
                return Err(invalid(
                    array_file_name(arrays::TRANSFER, DType::F16),
                    format!(
                        "element {k} (row {}, column {}, channel {}) is not a finite number",
                        k / (3 * n.max(1)),
                        (k / 3) % n.max(1),
                        k % 3
                    ),
                ));
            }
            if let Some(k) = t
                .scale
                .iter()
                .flatten()
                .position(|v| !(v.is_finite() && *v >= 0.0))
            {
                return Err(invalid(
                    array_file_name(arrays::TRANSFER_SCALE, DType::F32),
                    format!("element {k} is not finite and >= 0"),
                ));
            }
        }
        Ok(())
    }

    /// The environment visibility, when the bundle holds it (see [`EnvVisibilityView`]).
    pub fn environment_visibility(&self) -> Option<EnvVisibilityView<'_>> {
        let env = self.manifest.environment.as_ref()?;
        Some(EnvVisibilityView {
            rows: env.rows,
            cols: env.cols,
            bits: bytemuck::try_cast_slice(self.bytes_of(arrays::ENV_VISIBILITY, DType::F16))
                .unwrap_or(&[]),
        })
    }

    /// The transfer matrix, when the bundle holds one (see [`TransferView`]).
    pub fn transfer(&self) -> Option<TransferView<'_>> {
        self.manifest.transfer.as_ref()?;
        Some(TransferView {
            n: self.n_patches,
            bits: bytemuck::try_cast_slice(self.bytes_of(arrays::TRANSFER, DType::F16))
                .unwrap_or(&[]),
            scale: bytemuck::try_cast_slice(self.f32s(arrays::TRANSFER_SCALE)).unwrap_or(&[]),
        })
    }

    /// The cluster tree of a hierarchical F, when the bundle holds one (see [`TreeView`]).
    pub fn tree(&self) -> Option<TreeView<'_>> {
        self.manifest.hierarchy.as_ref()?;
        Some(TreeView {
            perm: self.u32s(arrays::TREE_PERM),
            range: bytemuck::try_cast_slice(self.u32s(arrays::TREE_RANGE)).unwrap_or(&[]),
        })
    }

    /// Checks the cluster tree: `tree_perm` is a permutation of `0..N` and every node's range
    /// lies in `0..N` and holds at least two patches.
    fn check_tree(&self) -> Result<(), BundleError> {
        let n = self.n_patches;
        let perm_file = array_file_name(arrays::TREE_PERM, DType::U32);
        let mut seen = vec![false; n];
        for (k, &p) in self.u32s(arrays::TREE_PERM).iter().enumerate() {
            let Some(s) = seen.get_mut(p as usize) else {
                return Err(invalid(
                    &perm_file,
                    format!("element {k} is patch {p} but patch_count is {n}"),
                ));
            };
            if *s {
                return Err(invalid(
                    &perm_file,
                    format!("patch {p} appears twice (not a permutation)"),
                ));
            }
            *s = true;
        }
        let range_file = array_file_name(arrays::TREE_RANGE, DType::U32);
        for (k, r) in self.u32s(arrays::TREE_RANGE).chunks_exact(2).enumerate() {
            if !(r[0] < r[1] && r[1] as usize <= n && r[1] - r[0] >= 2) {
                return Err(invalid(
                    &range_file,
                    format!(
                        "node {k} covers [{}, {}): expected at least two patches within 0..{n}",
                        r[0], r[1]
                    ),
                ));
            }
        }
        Ok(())
    }

    /// The bundle folder it was opened from.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The parsed manifest (its `arrays` lists every mapped file).
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    fn bytes_of(&self, name: &str, dtype: DType) -> &[u8] {
        match self.arrays.get(name) {
            Some(a) if a.dtype == dtype => a.bytes(),
            _ => &[],
        }
    }

    /// The elements of f32 array `name` (use the [`arrays`] constants). Never panics: a name
    /// that the bundle does not hold as f32 gives an empty slice. Required arrays are always
    /// present with the verified shape.
    pub fn f32s(&self, name: &str) -> &[f32] {
        bytemuck::try_cast_slice(self.bytes_of(name, DType::F32)).unwrap_or(&[])
    }

    /// The elements of u32 array `name`; empty when the bundle holds no such u32 array.
    pub fn u32s(&self, name: &str) -> &[u32] {
        bytemuck::try_cast_slice(self.bytes_of(name, DType::U32)).unwrap_or(&[])
    }

    /// The elements of u64 array `name`; empty when the bundle holds no such u64 array.
    pub fn u64s(&self, name: &str) -> &[u64] {
        bytemuck::try_cast_slice(self.bytes_of(name, DType::U64)).unwrap_or(&[])
    }

    /// `[N]` triangle corners of every patch (scene units).
    pub fn patch_corners(&self) -> &[[[f32; 3]; 3]] {
        bytemuck::try_cast_slice(self.f32s(arrays::PATCH_CORNERS)).unwrap_or(&[])
    }

    /// `[N]` unit normals.
    pub fn patch_normals(&self) -> &[[f32; 3]] {
        bytemuck::try_cast_slice(self.f32s(arrays::PATCH_NORMAL)).unwrap_or(&[])
    }

    /// `[N]` areas (scene units², finite and > 0).
    pub fn patch_areas(&self) -> &[f32] {
        self.f32s(arrays::PATCH_AREA)
    }

    /// `[N]` index into `manifest().objects` of each patch.
    pub fn patch_objects(&self) -> &[u32] {
        self.u32s(arrays::PATCH_OBJECT)
    }

    /// `[N]` albedo ρ (S_ii of an opaque patch).
    pub fn patch_albedo(&self) -> &[[f32; 3]] {
        bytemuck::try_cast_slice(self.f32s(arrays::PATCH_ALBEDO)).unwrap_or(&[])
    }

    /// `[N]` emitted exitance π·L_e (W·m⁻²).
    pub fn patch_emission(&self) -> &[[f32; 3]] {
        bytemuck::try_cast_slice(self.f32s(arrays::PATCH_EMISSION)).unwrap_or(&[])
    }

    /// `[V]` viewer-mesh vertex positions.
    pub fn vertex_positions(&self) -> &[[f32; 3]] {
        bytemuck::try_cast_slice(self.f32s(arrays::VERTEX_POSITION)).unwrap_or(&[])
    }

    /// `[V]` viewer-mesh vertex normals.
    pub fn vertex_normals(&self) -> &[[f32; 3]] {
        bytemuck::try_cast_slice(self.f32s(arrays::VERTEX_NORMAL)).unwrap_or(&[])
    }

    /// `[N]` viewer triangles (vertex indices `< V`); triangle k is patch k.
    pub fn triangle_vertices(&self) -> &[[u32; 3]] {
        bytemuck::try_cast_slice(self.u32s(arrays::TRIANGLE_VERTEX)).unwrap_or(&[])
    }

    /// `[M]` the scene's source triangles, for shadow rays.
    pub fn occluder_triangles(&self) -> &[[[f32; 3]; 3]] {
        bytemuck::try_cast_slice(self.f32s(arrays::OCCLUDER_TRI)).unwrap_or(&[])
    }

    /// F as an `N × N` CSR view, checked when the bundle was opened (no further pass).
    /// S: row j lists the sources i and S_ji per RGB channel (verified at open).
    pub fn subsurface(&self) -> crate::csr::CsrView<'_, [f32; 3]> {
        crate::csr::CsrView::from_checked_parts(
            self.n_patches,
            self.n_patches,
            self.u64s(arrays::S_ROW_PTR),
            self.u32s(arrays::S_COL),
            bytemuck::try_cast_slice(self.f32s(arrays::S_VAL)).unwrap_or(&[]),
        )
    }

    /// Optical path distances between patches of the same translucent object (verified at
    /// open; scene units).
    pub fn distances(&self) -> crate::csr::CsrView<'_, f32> {
        crate::csr::CsrView::from_checked_parts(
            self.n_patches,
            self.n_patches,
            self.u64s(arrays::DIST_ROW_PTR),
            self.u32s(arrays::DIST_COL),
            self.f32s(arrays::DIST_VAL),
        )
    }

    /// `[nnz_d]` the kind of each stored distance, parallel to `distances().val()`: 0 for a
    /// path inside an object or along one side of a thin sheet, 1 for a thin sheet's other
    /// side (verified at open to be 0 or 1).
    pub fn distance_kinds(&self) -> &[u32] {
        self.u32s(arrays::DIST_KIND)
    }

    /// F (`N × N`), or for a hierarchical bundle C (`N × (N + M)`, see
    /// [`Manifest::hierarchy`]); use it with [`Bundle::tree`].
    pub fn form_factors(&self) -> crate::csr::CsrView<'_> {
        crate::csr::CsrView::from_checked_parts(
            self.n_patches,
            self.n_patches + self.n_nodes,
            self.u64s(arrays::FF_ROW_PTR),
            self.u32s(arrays::FF_COL),
            self.f32s(arrays::FF_VAL),
        )
    }

    /// Bytes of the arrays that are memory-mapped (those over [`COPY_ON_OPEN_BYTES`]); the
    /// rest are private copies read when the bundle opened.
    pub fn mapped_bytes(&self) -> u64 {
        self.arrays
            .values()
            .filter(|a| !a.is_copied())
            .map(|a| a.bytes().len() as u64)
            .sum()
    }

    /// Bytes on disk: `manifest.json` plus every array file it lists.
    pub fn total_bytes(&self) -> u64 {
        self.manifest_bytes + self.manifest.arrays.values().map(|e| e.bytes).sum::<u64>()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::csr::CsrError;
    use crate::light::Camera;
    use crate::scene::Material;

    /// One array as raw parts, for hand-made bundles (the real writer lives in precompute).
    struct Raw {
        name: &'static str,
        dtype: DType,
        shape: Vec<u64>,
        bytes: Vec<u8>,
    }

    fn f32s(name: &'static str, shape: &[u64], v: &[f32]) -> Raw {
        Raw {
            name,
            dtype: DType::F32,
            shape: shape.to_vec(),
            bytes: bytemuck::cast_slice(v).to_vec(),
        }
    }
    fn u32s(name: &'static str, shape: &[u64], v: &[u32]) -> Raw {
        Raw {
            name,
            dtype: DType::U32,
            shape: shape.to_vec(),
            bytes: bytemuck::cast_slice(v).to_vec(),
        }
    }
    fn u64s(name: &'static str, shape: &[u64], v: &[u64]) -> Raw {
        Raw {
            name,
            dtype: DType::U64,
            shape: shape.to_vec(),
            bytes: bytemuck::cast_slice(v).to_vec(),
        }
    }

    /// A unit square on y = 0 split into two patches, one diffuse object, F with two entries.
    fn two_patches() -> (Manifest, Vec<Raw>) {
        let manifest = Manifest {
            format: FORMAT.into(),
            version: FORMAT_VERSION,
            name: "square".into(),
            source: "test".into(),
            created_by: "proto tests".into(),
            unit_mm: 1000.0,
            patch_count: 2,
            vertex_count: 4,
            occluder_count: 1,
            objects: vec![ObjectInfo {
                name: "floor".into(),
                material: Material::Diffuse { albedo: [0.5; 3] },
                first_patch: 0,
                patch_count: 2,
                albedo: [0.5; 3],
            }],
            lights: vec![],
            camera: Camera {
                position: [0.0, 1.0, 3.0],
                target: [0.0; 3],
                up: [0.0, 1.0, 0.0],
                fov_deg: 40.0,
            },
            form_factors: FormFactorInfo {
                nnz: 2,
                ..Default::default()
            },
            subsurface: SubsurfaceInfo {
                nnz: 2,
                ..Default::default()
            },
            stages: vec![],
            transfer: None,
            environment: None,
            hierarchy: None,
            arrays: BTreeMap::new(),
        };
        let (a, b, c, d) = (
            [0.0f32, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 0.0, 1.0],
            [0.0, 0.0, 1.0],
        );
        let corners: Vec<f32> = [a, c, b, a, d, c].concat();
        let arrays = vec![
            f32s(arrays::PATCH_CORNERS, &[2, 3, 3], &corners),
            f32s(
                arrays::PATCH_NORMAL,
                &[2, 3],
                &[0.0, 1.0, 0.0, 0.0, 1.0, 0.0],
            ),
            f32s(arrays::PATCH_AREA, &[2], &[0.5, 0.5]),
            u32s(arrays::PATCH_OBJECT, &[2], &[0, 0]),
            f32s(arrays::PATCH_ALBEDO, &[2, 3], &[0.5; 6]),
            f32s(arrays::PATCH_EMISSION, &[2, 3], &[0.0; 6]),
            f32s(arrays::VERTEX_POSITION, &[4, 3], &[a, b, c, d].concat()),
            f32s(
                arrays::VERTEX_NORMAL,
                &[4, 3],
                &[[0.0, 1.0, 0.0]; 4].concat(),
            ),
            u32s(arrays::TRIANGLE_VERTEX, &[2, 3], &[0, 2, 1, 0, 3, 2]),
            f32s(arrays::OCCLUDER_TRI, &[1, 3, 3], &[a, c, b].concat()),
            u64s(arrays::FF_ROW_PTR, &[3], &[0, 1, 2]),
            u32s(arrays::FF_COL, &[2], &[1, 0]),
            f32s(arrays::FF_VAL, &[2], &[0.25, 0.125]),
            u64s(arrays::S_ROW_PTR, &[3], &[0, 1, 2]),
            u32s(arrays::S_COL, &[2], &[0, 1]),
            f32s(arrays::S_VAL, &[2, 3], &[0.5; 6]),
            u64s(arrays::DIST_ROW_PTR, &[3], &[0, 0, 0]),
            u32s(arrays::DIST_COL, &[0], &[]),
            f32s(arrays::DIST_VAL, &[0], &[]),
            u32s(arrays::DIST_KIND, &[0], &[]),
            f32s(arrays::DIST_MATERIAL_LEN, &[0, 4], &[]),
            u32s(arrays::PATCH_MATERIAL, &[2], &[0, 0]),
        ];
        (manifest, arrays)
    }

    /// Writes the files and a manifest listing them (with their true checksums).
    fn write(dir: &Path, mut manifest: Manifest, arrays: &[Raw]) {
        std::fs::create_dir_all(dir).unwrap();
        manifest.arrays.clear();
        for a in arrays {
            let file = array_file_name(a.name, a.dtype);
            std::fs::write(dir.join(&file), &a.bytes).unwrap();
            manifest.arrays.insert(
                a.name.into(),
                ArrayEntry {
                    file,
                    dtype: a.dtype,
                    shape: a.shape.clone(),
                    bytes: a.bytes.len() as u64,
                    xxh3: checksum(&a.bytes),
                },
            );
        }
        std::fs::write(
            dir.join(MANIFEST_FILE),
            serde_json::to_string_pretty(&manifest).unwrap(),
        )
        .unwrap();
    }

    fn open_err(manifest: Manifest, arrays: &[Raw]) -> String {
        let tmp = tempfile::tempdir().unwrap();
        write(tmp.path(), manifest, arrays);
        match Bundle::open(tmp.path()) {
            Ok(_) => panic!("bundle opened but should not have"),
            Err(e) => e.to_string(),
        }
    }

    fn replace(arrays: &mut [Raw], new: Raw) {
        let slot = arrays.iter_mut().find(|a| a.name == new.name).unwrap();
        *slot = new;
    }

    #[test]
    fn hand_made_bundle_round_trips() {
        let tmp = tempfile::tempdir().unwrap();
        let (manifest, arrays) = two_patches();
        write(tmp.path(), manifest.clone(), &arrays);
        let b = Bundle::open(tmp.path()).unwrap();
        assert_eq!(b.dir(), tmp.path());
        assert_eq!(b.manifest().objects, manifest.objects);
        assert_eq!(b.manifest().arrays.len(), REQUIRED_ARRAYS.len());
        assert_eq!(
            b.patch_corners()[0],
            [[0.0, 0.0, 0.0], [1.0, 0.0, 1.0], [1.0, 0.0, 0.0]]
        );
        assert_eq!(b.patch_normals(), &[[0.0, 1.0, 0.0]; 2]);
        assert_eq!(b.patch_areas(), &[0.5, 0.5]);
        assert_eq!(b.patch_objects(), &[0, 0]);
        assert_eq!(b.patch_albedo(), &[[0.5; 3]; 2]);
        assert_eq!(b.patch_emission(), &[[0.0; 3]; 2]);
        assert_eq!(b.vertex_positions()[2], [1.0, 0.0, 1.0]);
        assert_eq!(b.vertex_normals().len(), 4);
        assert_eq!(b.triangle_vertices(), &[[0, 2, 1], [0, 3, 2]]);
        assert_eq!(b.occluder_triangles().len(), 1);
        let f = b.form_factors();
        assert_eq!((f.n_rows(), f.n_cols(), f.nnz()), (2, 2, 2));
        assert_eq!(f.get(0, 1), 0.25);
        assert_eq!(f.get(1, 0), 0.125);
        assert_eq!(f.get(0, 0), 0.0);
        // Unknown names and wrong dtypes give empty slices, never a panic.
        assert!(b.f32s("nope").is_empty());
        assert!(b.f32s(arrays::FF_COL).is_empty());
        assert_eq!(b.u32s(arrays::FF_COL), &[1, 0]);
        let on_disk: u64 = std::fs::read_dir(tmp.path())
            .unwrap()
            .map(|e| e.unwrap().metadata().unwrap().len())
            .sum();
        assert_eq!(b.total_bytes(), on_disk);
    }

    #[test]
    fn bundle_can_be_shared_between_threads() {
        fn shared<T: Send + Sync>() {}
        shared::<Bundle>();
    }

    #[test]
    fn empty_bundle_maps_zero_length_files() {
        let tmp = tempfile::tempdir().unwrap();
        let (mut manifest, arrays) = two_patches();
        manifest.patch_count = 0;
        manifest.vertex_count = 0;
        manifest.occluder_count = 0;
        manifest.form_factors.nnz = 0;
        manifest.subsurface.nnz = 0;
        manifest.objects.clear();
        let arrays: Vec<Raw> = arrays
            .into_iter()
            .map(|a| {
                if [arrays::FF_ROW_PTR, arrays::S_ROW_PTR, arrays::DIST_ROW_PTR].contains(&a.name) {
                    u64s(a.name, &[1], &[0])
                } else {
                    let mut shape = a.shape;
                    shape[0] = 0;
                    Raw {
                        shape,
                        bytes: vec![],
                        ..a
                    }
                }
            })
            .collect();
        write(tmp.path(), manifest, &arrays);
        let b = Bundle::open(tmp.path()).unwrap();
        assert!(b.patch_corners().is_empty());
        assert!(b.triangle_vertices().is_empty());
        assert_eq!(b.form_factors().n_rows(), 0);
        assert_eq!(b.form_factors().row_ptr(), &[0]);
    }

    #[test]
    fn extra_arrays_are_verified_and_mapped() {
        let tmp = tempfile::tempdir().unwrap();
        let (manifest, mut arrays) = two_patches();
        arrays.push(f32s("extra_val", &[3], &[1.0, 2.0, 3.0]));
        write(tmp.path(), manifest, &arrays);
        let b = Bundle::open(tmp.path()).unwrap();
        assert_eq!(b.f32s("extra_val"), &[1.0, 2.0, 3.0]);
        // A corrupted extra array is refused like any other.
        std::fs::write(
            tmp.path().join("extra_val.f32"),
            bytemuck::cast_slice(&[1.0f32, 2.0, 4.0]),
        )
        .unwrap();
        let e = Bundle::open(tmp.path()).unwrap_err().to_string();
        assert!(e.starts_with("extra_val.f32 is corrupt: checksum "), "{e}");
    }

    #[test]
    fn content_rules_name_the_file() {
        let base = two_patches;

        let (m, mut a) = base();
        replace(
            &mut a,
            u32s(arrays::TRIANGLE_VERTEX, &[2, 3], &[0, 2, 1, 0, 4, 2]),
        );
        let e = open_err(m, &a);
        assert!(
            e.starts_with("triangle_vertex.u32: triangle 1 corner 1 is vertex 4"),
            "{e}"
        );

        let (m, mut a) = base();
        replace(&mut a, f32s(arrays::PATCH_AREA, &[2], &[0.5, 0.0]));
        let e = open_err(m, &a);
        assert!(e.starts_with("patch_area.f32: patch 1 has area 0"), "{e}");

        let (m, mut a) = base();
        replace(
            &mut a,
            f32s(
                arrays::VERTEX_NORMAL,
                &[4, 3],
                &[[0.0, f32::NAN, 0.0]; 4].concat(),
            ),
        );
        assert!(open_err(m, &a).starts_with("vertex_normal.f32: element 1 is NaN"));

        let (m, mut a) = base();
        replace(&mut a, u32s(arrays::PATCH_OBJECT, &[2], &[0, 1]));
        let e = open_err(m, &a);
        assert!(
            e.starts_with("patch_object.u32: patch 1 names object 1 but the manifest lists 1"),
            "{e}"
        );

        // Objects must cover 0..N.
        let (mut m, a) = base();
        m.objects[0].patch_count = 1;
        let e = open_err(m, &a);
        assert!(
            e.starts_with("manifest.json: the objects cover patches 0..1 but patch_count is 2"),
            "{e}"
        );
        let (mut m, a) = base();
        m.objects[0].first_patch = 1;
        m.objects[0].patch_count = 1;
        assert!(open_err(m, &a).contains("objects[0] (\"floor\") starts at patch 1"));

        // A count that disagrees with a shape.
        let (mut m, a) = base();
        m.vertex_count = 5;
        let e = open_err(m, &a);
        assert!(
            e.starts_with("vertex_position.f32: shape [4, 3] does not match"),
            "{e}"
        );

        // A wrong dtype.
        let (m, mut a) = base();
        replace(&mut a, f32s(arrays::PATCH_OBJECT, &[2], &[0.0, 0.0]));
        let e = open_err(m, &a);
        assert!(
            e.starts_with("patch_object.u32: manifest lists dtype f32, expected u32"),
            "{e}"
        );

        // A missing manifest entry.
        let (m, mut a) = base();
        a.retain(|r| r.name != arrays::OCCLUDER_TRI);
        assert_eq!(
            open_err(m, &a),
            "occluder_tri.f32 is missing from manifest.json"
        );

        // A file longer than listed.
        let tmp = tempfile::tempdir().unwrap();
        let (m, a) = base();
        write(tmp.path(), m, &a);
        std::fs::write(tmp.path().join("ff_col.u32"), [0u8; 12]).unwrap();
        let e = Bundle::open(tmp.path()).unwrap_err().to_string();
        assert_eq!(e, "ff_col.u32 is too long: 12 bytes, manifest says 8");

        // Unsorted columns name ff_col; a wrong row_ptr names ff_row_ptr.
        let (mut m, mut a) = base();
        m.form_factors.nnz = 2;
        replace(&mut a, u64s(arrays::FF_ROW_PTR, &[3], &[0, 2, 2]));
        replace(&mut a, u32s(arrays::FF_COL, &[2], &[1, 0]));
        let tmp = tempfile::tempdir().unwrap();
        write(tmp.path(), m.clone(), &a);
        match Bundle::open(tmp.path()).unwrap_err() {
            BundleError::Csr { file, error } => {
                assert_eq!(file, "ff_col.u32");
                assert_eq!(error, CsrError::ColumnsUnsorted { row: 0, col: 0 });
            }
            other => panic!("{other}"),
        }
        replace(&mut a, u64s(arrays::FF_ROW_PTR, &[3], &[1, 2, 2]));
        let e = open_err(m, &a);
        assert!(
            e.starts_with("ff_row_ptr.u64: F is not a valid CSR matrix: row_ptr[0] is 1"),
            "{e}"
        );
    }

    #[test]
    fn per_medium_lengths_and_patch_media_are_checked() {
        // Two distances (0 → 1 and 1 → 0) with their per-medium lengths.
        let with = |lens: [f32; 8], media: [u32; 2]| {
            let (mut m, mut a) = two_patches();
            m.subsurface.distance_nnz = 2;
            replace(&mut a, u64s(arrays::DIST_ROW_PTR, &[3], &[0, 1, 2]));
            replace(&mut a, u32s(arrays::DIST_COL, &[2], &[1, 0]));
            replace(&mut a, f32s(arrays::DIST_VAL, &[2], &[0.5, 0.5]));
            replace(&mut a, f32s(arrays::DIST_MATERIAL_LEN, &[2, 4], &lens));
            replace(&mut a, u32s(arrays::DIST_KIND, &[2], &[0, 0]));
            replace(&mut a, u32s(arrays::PATCH_MATERIAL, &[2], &media));
            (m, a)
        };
        let tmp = tempfile::tempdir().unwrap();
        let (m, a) = with([0.2, 0.3, 0.0, 0.0, 0.3, 0.2, 0.0, 0.0], [0, 1]);
        write(tmp.path(), m, &a);
        let b = Bundle::open(tmp.path()).unwrap();
        assert_eq!(b.f32s(arrays::DIST_MATERIAL_LEN)[4], 0.3);
        assert_eq!(b.u32s(arrays::PATCH_MATERIAL), &[0, 1]);

        let (m, a) = with([0.2, 0.3, 0.0, 0.0, 0.3, -0.2, 0.0, 0.0], [0, 1]);
        let e = open_err(m, &a);
        assert!(
            e.starts_with("dist_material_len.f32: distance 1 medium 1 has length -0.2"),
            "{e}"
        );
        let (m, a) = with([0.2, f32::NAN, 0.0, 0.0, 0.3, 0.2, 0.0, 0.0], [0, 1]);
        assert!(open_err(m, &a).starts_with("dist_material_len.f32: distance 0 medium 1"));
        let (m, a) = with([0.0; 8], [0, 4]);
        let e = open_err(m, &a);
        assert!(
            e.starts_with("patch_material.u32: patch 1 names medium 4; there are at most 4"),
            "{e}"
        );
        // The shape follows the distance count, with 4 media per distance.
        let (m, mut a) = with([0.0; 8], [0, 0]);
        replace(&mut a, f32s(arrays::DIST_MATERIAL_LEN, &[2, 3], &[0.0; 6]));
        let e = open_err(m, &a);
        assert!(
            e.starts_with("dist_material_len.f32: shape [2, 3] does not match"),
            "{e}"
        );
    }

    #[test]
    fn distance_kinds_are_0_or_1() {
        // Two distances (0 → 1 and 1 → 0): a thin sheet's front and back patch.
        let with = |kinds: [u32; 2]| {
            let (mut m, mut a) = two_patches();
            m.subsurface.distance_nnz = 2;
            replace(&mut a, u64s(arrays::DIST_ROW_PTR, &[3], &[0, 1, 2]));
            replace(&mut a, u32s(arrays::DIST_COL, &[2], &[1, 0]));
            replace(&mut a, f32s(arrays::DIST_VAL, &[2], &[0.0, 0.0]));
            replace(&mut a, u32s(arrays::DIST_KIND, &[2], &kinds));
            // Other per-distance arrays follow the count (all zeros).
            for r in a.iter_mut() {
                if ![arrays::DIST_COL, arrays::DIST_VAL, arrays::DIST_KIND].contains(&r.name)
                    && r.shape.first() == Some(&0)
                {
                    r.shape[0] = 2;
                    let per: u64 = r.shape[1..].iter().product();
                    r.bytes = vec![0u8; (2 * per) as usize * r.dtype.size()];
                }
            }
            (m, a)
        };
        let tmp = tempfile::tempdir().unwrap();
        let (m, a) = with([1, 1]);
        write(tmp.path(), m, &a);
        let b = Bundle::open(tmp.path()).unwrap();
        assert_eq!(b.distance_kinds(), &[1, 1]);
        assert_eq!(b.distances().nnz(), 2);

        let (m, a) = with([0, 2]);
        let e = open_err(m, &a);
        assert!(
            e.starts_with("dist_kind.u32: distance 1 has kind 2, expected 0 (same side) or 1"),
            "{e}"
        );
        // The shape follows the distance count.
        let (m, mut a) = with([0, 1]);
        replace(&mut a, u32s(arrays::DIST_KIND, &[1], &[0]));
        let e = open_err(m, &a);
        assert!(
            e.starts_with("dist_kind.u32: shape [1] does not match"),
            "{e}"
        );
    }

    /// Small arrays are private copies: truncating one in place (what an operator must not
    /// do, but might) changes nothing the server reads and cannot raise SIGBUS.
    #[test]
    fn small_arrays_survive_being_truncated_in_place() {
        let tmp = tempfile::tempdir().unwrap();
        let (m, a) = two_patches();
        write(tmp.path(), m, &a);
        let b = Bundle::open(tmp.path()).unwrap();
        assert_eq!(b.mapped_bytes(), 0, "a tiny bundle is copied, not mapped");
        for e in std::fs::read_dir(tmp.path()).unwrap() {
            let p = e.unwrap().path();
            if p.extension().is_some_and(|x| x != "json") {
                std::fs::OpenOptions::new()
                    .write(true)
                    .open(&p)
                    .unwrap()
                    .set_len(0)
                    .unwrap();
            }
        }
        let f = b.form_factors();
        assert_eq!((f.get(0, 1), f.get(1, 0)), (0.25, 0.125));
        assert_eq!(b.patch_areas(), &[0.5, 0.5]);
    }

    /// A FIFO where a bundle file should be: opening it for reading would block until a
    /// writer appears, hanging the loader. It must be an error at once.
    #[test]
    fn a_fifo_in_a_bundle_folder_is_an_error_not_a_hang() {
        for file in ["ff_val.f32", MANIFEST_FILE] {
            let tmp = tempfile::tempdir().unwrap();
            let (m, a) = two_patches();
            write(tmp.path(), m, &a);
            let path = tmp.path().join(file);
            std::fs::remove_file(&path).unwrap();
            let made = std::process::Command::new("mkfifo").arg(&path).status();
            assert!(made.is_ok_and(|s| s.success()), "mkfifo {}", path.display());
            let dir = tmp.path().to_path_buf();
            let (tx, rx) = std::sync::mpsc::channel();
            std::thread::spawn(move || {
                let _ = tx.send(Bundle::open(&dir).map(|_| ()).map_err(|e| e.to_string()));
            });
            let got = rx
                .recv_timeout(std::time::Duration::from_secs(10))
                .expect("Bundle::open hung on a FIFO");
            let e = got.unwrap_err();
            assert!(e.contains(file) && e.contains("not a regular file"), "{e}");
        }
    }

    #[test]
    fn manifest_entries_cannot_escape_the_folder() {
        let tmp = tempfile::tempdir().unwrap();
        let (m, a) = two_patches();
        write(tmp.path(), m, &a);
        let path = tmp.path().join(MANIFEST_FILE);
        let text = std::fs::read_to_string(&path).unwrap();
        std::fs::write(&path, text.replace("\"ff_val.f32\"", "\"../ff_val.f32\"")).unwrap();
        let e = Bundle::open(tmp.path()).unwrap_err().to_string();
        assert!(
            e.starts_with("manifest.json: array ff_val is stored as \"../ff_val.f32\""),
            "{e}"
        );

        // Listed byte counts must agree with the shape.
        let (m, a) = two_patches();
        write(tmp.path(), m, &a);
        let mut m: Manifest = crate::parse_json(&std::fs::read_to_string(&path).unwrap()).unwrap();
        m.arrays.get_mut(arrays::FF_VAL).unwrap().bytes = 12;
        std::fs::write(&path, serde_json::to_string(&m).unwrap()).unwrap();
        let e = Bundle::open(tmp.path()).unwrap_err().to_string();
        assert!(
            e.contains("ff_val.f32: manifest lists 12 bytes but shape [2] of f32 holds 8"),
            "{e}"
        );
    }

    #[test]
    fn manifest_errors_name_manifest_json() {
        let tmp = tempfile::tempdir().unwrap();
        let e = Bundle::open(&tmp.path().join("nope")).unwrap_err();
        assert!(matches!(e, BundleError::Missing { .. }), "{e}");
        let e = Bundle::open(tmp.path()).unwrap_err().to_string();
        assert_eq!(e, "manifest.json is missing");
        std::fs::write(tmp.path().join(MANIFEST_FILE), "{\n  \"format\": 3\n}").unwrap();
        let e = Bundle::open(tmp.path()).unwrap_err();
        assert_eq!(e.file(), MANIFEST_FILE);
        assert!(
            e.to_string()
                .starts_with("manifest.json: line 2 column 13: format: invalid type"),
            "{e}"
        );
        let (mut m, a) = two_patches();
        m.format = "zip".into();
        assert_eq!(
            open_err(m, &a),
            "manifest.json: format is \"zip\", expected \"translux-bundle\""
        );
        let (mut m, a) = two_patches();
        m.version = 7;
        assert_eq!(
            open_err(m, &a),
            format!(
                "manifest.json: bundle version 7 is not supported (this build reads versions 4 to \
                 {FORMAT_VERSION}); rebuild the bundle with this build's translux-precompute"
            )
        );
    }

    /// A version 4 bundle (dense F, no hierarchy) still opens.
    #[test]
    fn version_4_bundles_still_open() {
        let tmp = tempfile::tempdir().unwrap();
        let (mut m, a) = two_patches();
        m.version = 4;
        write(tmp.path(), m, &a);
        let b = Bundle::open(tmp.path()).unwrap();
        assert!(b.tree().is_none());
        assert_eq!(b.form_factors().n_cols(), 2);
    }

    /// A hierarchical F: C has a column per node past the patches; the tree's permutation
    /// and ranges are checked.
    #[test]
    fn hierarchical_f_opens_and_a_bad_tree_is_refused() {
        let hierarchical = |perm: &[u32], range: &[u32]| {
            let (mut m, mut a) = two_patches();
            m.hierarchy = Some(HierarchyInfo {
                nodes: 1,
                ..Default::default()
            });
            // Row 0 sees node 0 (patches 0 and 1), row 1 sees patch 0.
            replace(&mut a, u32s(arrays::FF_COL, &[2], &[2, 0]));
            a.push(u32s(arrays::TREE_PERM, &[2], perm));
            a.push(u32s(arrays::TREE_RANGE, &[1, 2], range));
            (m, a)
        };
        let tmp = tempfile::tempdir().unwrap();
        let (m, a) = hierarchical(&[1, 0], &[0, 2]);
        write(tmp.path(), m, &a);
        let b = Bundle::open(tmp.path()).unwrap();
        let t = b.tree().unwrap();
        assert_eq!((t.perm, t.range), (&[1u32, 0][..], &[[0u32, 2]][..]));
        assert_eq!(b.form_factors().n_cols(), 3);
        let (m, a) = hierarchical(&[1, 1], &[0, 2]);
        assert_eq!(
            open_err(m, &a),
            "tree_perm.u32: patch 1 appears twice (not a permutation)"
        );
        let (m, a) = hierarchical(&[0, 1], &[1, 2]);
        assert_eq!(
            open_err(m, &a),
            "tree_range.u32: node 0 covers [1, 2): expected at least two patches within 0..2"
        );
        // Without the hierarchy the column past N is out of range.
        let (mut m, a) = hierarchical(&[0, 1], &[0, 2]);
        m.hierarchy = None;
        assert!(open_err(m, &a).contains("out of range"));
    }
}
