//! translux-precompute's integration tests, one binary with a module per subject:
//! `cli` (the real process, its files, exit codes and messages), `physics` (closed-form
//! form factors and conservation), `transport` (the solvers and light components),
//! `subsurface` (S through the pipeline), `dipole` (the default S against direct
//! integration of the dipole on a sphere, a slab and a cube), `slinks` (hierarchical S against pairwise),
//! `heterogeneous` (eq. 9 objects), `simulated` (S from random walks), `animation`
//! (animated scenes: one bundle per frame), `gltf_scene` (glTF 2.0 files as whole scenes,
//! from fixtures written by the tests), `shard` (`--shard` and `--merge` by hand) and
//! `shard_sequence` (the same for an animated scene's frames).
//!
//! Run one subject with `cargo test -p translux-precompute --test it physics::`. One binary
//! links the crate's dependencies once instead of once per file.

mod animation;
mod cli;
mod dipole;
mod gltf_scene;
mod heterogeneous;
mod physics;
mod shard;
mod shard_sequence;
mod simulated;
mod slinks;
mod subsurface;
mod transport;
