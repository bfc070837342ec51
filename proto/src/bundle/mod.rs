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
//! ├── dist_spread.f32        [nnz_d]    only with `subsurface.link_near`: a link's spread σ,
//! │                                     the link read at r ± σ (0 for direct pairs)
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

mod manifest;
mod open;
mod views;

pub use manifest::*;
pub use open::*;
pub use views::*;
