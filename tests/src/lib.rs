//! Shared by the end-to-end tests and the Table 1 benchmark (`examples/table1.rs`).
//!
//! [`mitsuba`]: an independent reference. In: a bundle (its patches as triangles, its
//! materials) plus lights and query points. Out: Mitsuba 3's path-traced radiance at those
//! points, and per-point error statistics of translux's answer against it.
//!
//! [`rooms`]: rooms modelled the way users model them (one OBJ per wall, or one inward
//! box), written as OBJ files and a scene file.
//!
//! [`compare`]: hierarchical F against dense F on one scene (relit vertices, lit and
//! shadowed apart; the operator on test fields).
//!
//! [`scans`]: where the scanned meshes are, and the bunny as the benchmarks place it.
//!
//! [`architecture`]: checks that crate dependencies point one way and that no crate has a
//! module cycle.
//!
//! `doc_paths` (a unit test, `cargo test -p translux-tests --lib`): in: README.md and
//! docs/*.md; out: a failure naming every repository path they link to or name in
//! backticks that does not exist.

pub mod architecture;
pub mod compare;
mod doc_paths;
pub mod mitsuba;
pub mod rooms;
pub mod scans;
