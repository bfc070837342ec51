//! # translux-precompute
//!
//! The offline half. In: a scene (a JSON scene file with OBJ, PLY or glTF meshes, or
//! `builtin:NAME`). Out: a verified bundle on disk (see `translux_proto::bundle`) holding
//! the patches, the viewer mesh, the form-factor matrix F, the subsurface matrix S with what
//! rebuilds it, environment visibility and optionally the transfer matrix T. The run-time
//! transport (solvers, T, lights, rendering, export, ray casting) is `translux_engine`,
//! which this crate uses for F's visibility rays and for T.
//!
//! Stages, each in its own module:
//! 1. [`scene`] — load and validate the scene; [`shapes`] and [`builtin`] make procedural
//!    geometry and the built-in scenes.
//!    [`simplify`] reduces scanned meshes toward a triangle budget (`simplify_to`);
//!    [`orient`] turns closed parts wound inside out outward (`orientation`).
//!    [`meshio`] picks a mesh file's format by extension and reads PLY and glTF 2.0;
//!    [`obj`] reads OBJ (with `usemtl` groups). [`gltf_scene`] takes a glTF 2.0 file as a
//!    whole scene (objects from its nodes, materials with textures, lights, camera).
//! 2. [`patch`] — split triangles into patches, weld vertices (the crate's one weld, also
//!    used by [`sheet`]), crease-aware normals.
//! 3. [`formfactor`] — F with visibility (`translux_engine::raycast`), point-to-polygon,
//!    near-pair sub-sampling; [`hierarchy`] — the cluster tree and the hierarchical F̃ = C·P.
//! 4. [`distances`] (with [`voxel`], [`sheet`], [`hetero`]) — optical path distances inside
//!    translucent objects (voxel Dijkstra), along thin two-sided sheets (geodesics, same or
//!    other side) and per medium in heterogeneous objects; S from them and the materials is
//!    `translux_engine::smatrix` (profiles, quadrature, eq. 9), run here once and by the
//!    server for every translucency change. [`simulate`] walks simulated media (random
//!    walks, stage 1 of their S); [`slinks`] links far parts of an object to receivers
//!    through whole cluster nodes (the hierarchical S).
//! 5. [`bundle`] — write arrays and manifest atomically; environment visibility and T come
//!    from `translux_engine::{envvis, inverse}`.
//!
//! [`pipeline::precompute`] runs 1–5 with progress and a summary. Its settings are
//! [`options::PrecomputeOptions`]: the command line's flags as one clap `Args` (flattened
//! into `translux-precompute`'s, used too by the server's upload jobs and the Table 1
//! benchmark), which checks them and resolves `--subsurface auto` into
//! [`pipeline::PrecomputeParams`]. [`shard`] splits the receiver rows of stage 3 (and the
//! environment visibility) over the tasks of a scheduler (`pipeline::precompute_shard`) and
//! puts them together (`pipeline::precompute_merge`). [`sequence`] precomputes an animated
//! scene, one bundle per frame; [`resimulate`] walks the simulated objects of a bundle again
//! in new media.
//!
//! ```no_run
//! use translux_precompute::{options::PrecomputeOptions, pipeline, scene};
//! let loaded = scene::load_scene("builtin:cornell").unwrap();
//! // As `translux-precompute builtin:cornell --patches 2000`.
//! let params = PrecomputeOptions { patches: Some(2000), ..Default::default() }.params().unwrap();
//! let report = pipeline::precompute(&loaded, std::path::Path::new("out/cornell"), &params).unwrap();
//! println!("{} patches, nnz(F) = {}", report.patch_count, report.nnz_f);
//! ```

pub mod builtin;
pub mod bundle;
pub mod distances;
pub mod formfactor;
pub mod gltf_scene;
pub mod hetero;
pub mod hierarchy;
pub mod meshio;
pub mod obj;
pub mod options;
pub mod orient;
pub mod patch;
pub mod pipeline;
pub mod resimulate;
pub mod scene;
pub mod sequence;
pub mod shapes;
pub mod shard;
pub mod sheet;
pub mod simplify;
pub mod simulate;
pub mod slinks;
pub mod voxel;
