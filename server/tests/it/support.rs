//! The fixtures of the server's integration tests: one rule for kept folders and one way to
//! build a test bundle (a small builtin:cornell).

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::load_scene;

/// A folder under the target's temp folder that outlives the test run (statics are never
/// dropped): removed by a later run once older than ten minutes (no run of this binary
/// takes that long).
pub fn kept_folder(prefix: &str) -> PathBuf {
    let parent = Path::new(env!("CARGO_TARGET_TMPDIR"));
    if let Ok(entries) = std::fs::read_dir(parent) {
        for e in entries.flatten() {
            let stale = e.file_name().to_string_lossy().starts_with(prefix)
                && e.metadata()
                    .and_then(|m| m.modified())
                    .ok()
                    .and_then(|t| t.elapsed().ok())
                    .is_some_and(|age| age.as_secs() > 600);
            if stale {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
    }
    tempfile::Builder::new()
        .prefix(prefix)
        .tempdir_in(parent)
        .expect("temp dir")
        .keep()
}

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
