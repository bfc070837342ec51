//! The fixtures of the server's integration tests: one rule for kept folders, one way to
//! build a test bundle (a small builtin:cornell), and the GPU tests' context.

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

/// The GPU tests' shared context (software adapters too; lavapipe in CI), or `None` when
/// there is no adapter and `TRANSLUX_SKIP_GPU_TESTS=1`.
pub fn gpu() -> Option<&'static translux_server::gpu::GpuContext> {
    static CTX: OnceLock<Option<translux_server::gpu::GpuContext>> = OnceLock::new();
    CTX.get_or_init(|| gpu_context(None)).as_ref()
}

/// A GPU context of its own whose matrix buffers hold at most `cap` bytes when given;
/// `None` as for [`gpu`]. Without an adapter and without the skip it panics, saying what to
/// install.
pub fn gpu_context(cap: Option<u64>) -> Option<translux_server::gpu::GpuContext> {
    let opts = translux_server::gpu::GpuOptions {
        allow_software: true,
        max_binding_bytes: cap,
        budget_bytes: None,
    };
    match translux_server::gpu::GpuContext::new(&opts) {
        Ok(c) => {
            eprintln!("GPU tests on {:?}", c.adapter());
            Some(c)
        }
        Err(e) if std::env::var("TRANSLUX_SKIP_GPU_TESTS").as_deref() == Ok("1") => {
            eprintln!("GPU tests skipped (TRANSLUX_SKIP_GPU_TESTS=1): {e}");
            None
        }
        Err(e) => panic!(
            "the GPU tests need a GPU adapter and found none: {e}\n\
             Install Mesa's software Vulkan (apt-get install -y mesa-vulkan-drivers libvulkan1) \
             or set TRANSLUX_SKIP_GPU_TESTS=1 to skip them"
        ),
    }
}
