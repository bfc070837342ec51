//! # translux-precompute
//!
//! The engine. In: a scene (a JSON scene file with OBJ meshes, or `builtin:NAME`). Out: a
//! verified bundle on disk (see `translux_proto::bundle`) holding the patches, the viewer
//! mesh and the form-factor matrix F, and the CPU radiosity solve that reads it.
//!
//! Stages, each in its own module:
//! 1. [`scene`] — load and validate the scene; [`shapes`] and [`builtin`] make procedural
//!    geometry and the built-in scenes.
//!    [`simplify`] reduces scanned meshes toward a triangle budget (`simplify_to`);
//!    [`orient`] turns closed parts wound inside out outward (`orientation`).
//!    [`meshio`] picks a mesh file's format by extension and reads PLY and glTF 2.0.
//! 2. [`patch`] — split triangles into patches, weld vertices, crease-aware normals.
//! 3. [`raycast`] — a BVH over the source triangles for occlusion queries.
//! 4. [`formfactor`] — F with visibility, point-to-polygon, near-pair sub-sampling.
//! 5. [`voxel`], [`profile`], [`subsurface`], [`smatrix`] — optical path distances inside
//!    translucent objects, diffuse reflectance profiles, and S from both; [`hetero`] —
//!    heterogeneous objects (media by pattern, combined per path by the paper's eq. 9);
//!    [`sheet`] — thin two-sided sheets (geodesic distances, reflectance and transmittance).
//! 6. [`bundle`] — write arrays and manifest atomically; [`envvis`] — per-patch visibility
//!    of direction bins for environment lighting ([`envmap`]: `.hdr` maps, built-in skies).
//! 7. [`radiosity`] — direct lighting and the solve B = Bₑ + S(E + F B).
//! 8. [`render`] — a CPU rasterizer from per-vertex radiance to an sRGB image (PNG);
//!    [`export`] — the relit mesh as binary glTF (`.glb`) or PLY with baked colours.
//!
//! [`pipeline::precompute`] runs 1–5 with progress and a summary.
//!
//! ```no_run
//! use translux_precompute::{pipeline, scene};
//! let loaded = scene::load_scene("builtin:cornell").unwrap();
//! let params = pipeline::PrecomputeParams { patches: Some(2000), ..Default::default() };
//! let report = pipeline::precompute(&loaded, std::path::Path::new("out/cornell"), &params).unwrap();
//! println!("{} patches, nnz(F) = {}", report.patch_count, report.nnz_f);
//! ```

pub mod builtin;
pub mod bundle;
pub mod envmap;
pub mod envvis;
pub mod export;
pub mod formfactor;
pub mod hetero;
pub mod inverse;
pub mod meshio;
pub mod orient;
pub mod patch;
pub mod pipeline;
pub mod profile;
pub mod radiosity;
pub mod raycast;
pub mod render;
pub mod scene;
pub mod shapes;
pub mod sheet;
pub mod simplify;
pub mod smatrix;
pub mod solver;
pub mod subsurface;
pub mod voxel;
