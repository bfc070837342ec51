//! The fixtures of the server's integration tests: one rule for kept folders and one way to
//! build a test bundle (a small builtin:cornell).

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::load_scene;

#[path = "../../../tests/fixtures/kept_folder.rs"]
mod kept;
pub use kept::kept_folder;

/// builtin:cornell precomputed at about `patches` patches into `root/cornell`.
pub fn cornell_into(root: &Path, patches: u64) -> PathBuf {
    let dir = root.join("cornell");
    let scene = load_scene("builtin:cornell").expect("builtin:cornell loads");
    let params = PrecomputeParams {
        patches: Some(patches),
        ..Default::default()
    };
    precompute(&scene, &dir, &params).expect("precompute");
    dir
}

/// A ~300-patch Cornell box, built once per test run and shared (read only).
pub fn bundle_dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| cornell_into(&kept_folder("server-fixture-"), 300))
}
