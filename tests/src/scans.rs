//! The scanned meshes of `../shared/data/` as the benchmarks place them.

use std::path::{Path, PathBuf};

use translux_proto::scene::{Material, MeshRef, ObjectDesc, Scale, Transform};

/// The folder of the scanned meshes: `../shared/data` beside the repository (found from
/// this crate's folder, so from any working directory).
pub fn data_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data")
}

/// The whole Stanford bunny scan (`stanford-bunny.obj`, 69,451 triangles) scaled 1.2 (0.19
/// tall), turned `yaw_deg` about +Y, its feet on y = 0 and its centre at (x, z). The scan's
/// lowest point is at y = 0.033 and its centre at x = −0.0168. Mesh paths are relative
/// to [`data_dir`].
pub fn bunny(x: f32, z: f32, yaw_deg: f32, material: Material) -> ObjectDesc {
    ObjectDesc {
        keyframes: None,
        name: "bunny".into(),
        mesh: MeshRef::Path("stanford-bunny.obj".into()),
        transform: Some(Transform {
            translate: [x + 0.0168 * 1.2, -0.032987 * 1.2, z],
            rotate_deg: [0.0, yaw_deg, 0.0],
            scale: Some(Scale::Uniform(1.2)),
        }),
        material,
        crease_deg: Some(60.0),
        simplify_to: None,
        orientation: Default::default(),
    }
}
