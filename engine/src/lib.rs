//! # translux-engine
//!
//! The run-time transport: what turns a bundle's arrays and a request (lights, materials,
//! a camera) into radiance, pictures and meshes. In: CSR views of F and S, the stored
//! transfer matrix T, patch geometry and the occluders for shadow rays, lights and
//! environment maps. Out: radiosity B per patch (W·m⁻²), vertex radiance B/π, rendered
//! images (PNG, OpenEXR) and relit meshes (glTF, PLY). No HTTP and no global state: the
//! server (`translux-server`), the offline commands and the benchmarks call it, and the
//! precompute (`translux-precompute`) uses its solvers, ray casting and S.
//!
//! Modules, from the bottom up:
//! - [`linalg`] — RGB vectors, y = F x ([`linalg::spmv_rgb`]) and the scattering operator S
//!   ([`linalg::Scatter`]: diagonal ρ or sparse subsurface S).
//! - [`transport`] — in: a bundle's F arrays, dense or hierarchical (C over patches and
//!   cluster nodes); out: the products y = F x the solvers apply, row sums, F written densely
//!   for T.
//! - [`solver`] — Jacobi, Gauss-Seidel and BiCGSTAB for (I − S F) B = S E + Bₑ, warm
//!   started, several right-hand sides per pass over F.
//! - [`raycast`] — a BVH over the scene's triangles for shadow and visibility rays;
//!   [`clearance`] — a lower bound on the distance to an object's triangles, from a grid,
//!   so a random walk's flight that cannot reach the mesh asks no ray.
//! - [`radiosity`] — direct irradiance from the lights (with shadows), the solve
//!   B = Bₑ + S (E + F B), and patch values to vertex values; [`vertexlight`] — the direct
//!   term of opaque diffuse surfaces evaluated at the viewer's vertices themselves;
//!   [`vertexrows`] — that colour stage as sparse rows per vertex, for a backend that makes
//!   the colours where B is.
//! - [`inverse`] — the transfer matrix T = (I − S F)⁻¹ S: computing it (dense LU) and
//!   applying the stored f16 T.
//! - [`envmap`], [`envvis`] — environment maps (`.hdr`, built-in skies) binned by
//!   direction, and per-patch visibility of those bins.
//! - [`profile`] — diffuse reflectance profiles (dipole, multipole, tables, exponentials);
//!   [`subsurface`] — the quadrature of S between patches; [`sheet`] and [`hetero`] — S of
//!   thin sheets and of heterogeneous objects; [`smatrix`] — the scene's S from the stored
//!   distances and the materials (stage 2: the precompute's, and every translucency change);
//!   [`sterms`] — in: an object's patches and stored distances; out: S's entries reduced to
//!   a few radial terms each, so a translucency change is a short sum per entry;
//!   [`simulated`] — a simulated S: random walks inside the mesh, re-weighted for absorption;
//!   [`collimated`] — lamps into simulated objects by S at the lamp's angle (collimated
//!   entry, its tilt and unscattered part); [`lampwalk`] — in: a relight's lamps and its
//!   simulated objects; out: their first scattering walked along each lamp's own beam
//!   (`"lamp_walks"`);
//!   [`linkbound`] — the profile's error bound on a hierarchical S's links, over a slider's
//!   range of translucency.
//! - [`render`] — a CPU rasterizer from vertex radiance to an image; [`specular`] — in: a
//!   surface point, the eye and the lights; out: the glossy coat's one bounce of reflected
//!   radiance, added per pixel; [`export`] — the relit mesh as binary glTF or PLY.
//! - [`scene`] — a bundle opened for relighting, with its caches and the [`backend`] it
//!   relights on (a trait: the CPU's here, the server's wgpu backend beside it);
//!   [`environment`] — environment lights (map paths and cache, E from visibility);
//!   [`relight`] — a request checked against a scene ([`relight::plan`]) and computed
//!   ([`relight::run`], [`relight::run_batch`]: the six components, T or the solver, warm
//!   starts), a pipeline whose stages are its submodules: `prepare` (direct light and S for
//!   a plan's materials), `transport` (per group of plans: the transport and its solve) and
//!   `colours` (vertex colours and stats); [`picture`] — renders and exports of a relight.
//!   Failures are [`error::EngineError`]s; [`stop`] — long work (lamp walks) stopped by its
//!   caller or its time limit.
//!
//! Crate graph: `proto ← engine ← {precompute, server (with its wgpu backend)}`; see
//! `docs/architecture.md`.

pub mod backend;
pub mod clearance;
pub mod collimated;
pub mod environment;
pub mod envmap;
pub mod envvis;
pub mod error;
pub mod export;
pub mod hetero;
pub mod inverse;
pub mod lampwalk;
pub mod linalg;
pub mod linkbound;
pub mod picture;
pub mod profile;
pub mod radiosity;
pub mod raycast;
pub mod relight;
pub mod render;
pub mod scene;
pub mod sheet;
pub mod simulated;
pub mod smatrix;
pub mod solver;
pub mod specular;
pub mod sterms;
pub mod stop;
pub mod subsurface;
pub mod transport;
pub mod vertexlight;
pub mod vertexrows;
