//! The loader against hand-made bundles: good ones open, every kind of damage is refused
//! with a message naming the file and the problem.

use super::*;
use crate::csr::CsrError;
use crate::light::Camera;
use crate::scene::Material;

/// One array as raw parts, for hand-made bundles (the real writer lives in precompute).
struct Raw {
    name: &'static str,
    dtype: DType,
    shape: Vec<u64>,
    bytes: Vec<u8>,
}

fn f32s(name: &'static str, shape: &[u64], v: &[f32]) -> Raw {
    Raw {
        name,
        dtype: DType::F32,
        shape: shape.to_vec(),
        bytes: bytemuck::cast_slice(v).to_vec(),
    }
}
fn u32s(name: &'static str, shape: &[u64], v: &[u32]) -> Raw {
    Raw {
        name,
        dtype: DType::U32,
        shape: shape.to_vec(),
        bytes: bytemuck::cast_slice(v).to_vec(),
    }
}
fn u64s(name: &'static str, shape: &[u64], v: &[u64]) -> Raw {
    Raw {
        name,
        dtype: DType::U64,
        shape: shape.to_vec(),
        bytes: bytemuck::cast_slice(v).to_vec(),
    }
}

/// A unit square on y = 0 split into two patches, one diffuse object, F with two entries.
fn two_patches() -> (Manifest, Vec<Raw>) {
    let manifest = Manifest {
        format: FORMAT.into(),
        version: FORMAT_VERSION,
        name: "square".into(),
        source: "test".into(),
        created_by: "proto tests".into(),
        unit_mm: 1000.0,
        patch_count: 2,
        vertex_count: 4,
        occluder_count: 1,
        objects: vec![ObjectInfo {
            name: "floor".into(),
            material: Material::Diffuse {
                albedo: [0.5; 3],
                specular: None,
            },
            first_patch: 0,
            patch_count: 2,
            albedo: [0.5; 3],
        }],
        lights: vec![],
        camera: Camera {
            position: [0.0, 1.0, 3.0],
            target: [0.0; 3],
            up: [0.0, 1.0, 0.0],
            fov_deg: 40.0,
        },
        form_factors: FormFactorInfo {
            nnz: 2,
            ..Default::default()
        },
        subsurface: SubsurfaceInfo {
            nnz: 2,
            ..Default::default()
        },
        stages: vec![],
        transfer: None,
        environment: None,
        hierarchy: None,
        arrays: BTreeMap::new(),
    };
    let (a, b, c, d) = (
        [0.0f32, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 0.0, 1.0],
        [0.0, 0.0, 1.0],
    );
    let corners: Vec<f32> = [a, c, b, a, d, c].concat();
    let arrays = vec![
        f32s(arrays::PATCH_CORNERS, &[2, 3, 3], &corners),
        f32s(
            arrays::PATCH_NORMAL,
            &[2, 3],
            &[0.0, 1.0, 0.0, 0.0, 1.0, 0.0],
        ),
        f32s(arrays::PATCH_AREA, &[2], &[0.5, 0.5]),
        u32s(arrays::PATCH_OBJECT, &[2], &[0, 0]),
        f32s(arrays::PATCH_ALBEDO, &[2, 3], &[0.5; 6]),
        f32s(arrays::PATCH_EMISSION, &[2, 3], &[0.0; 6]),
        f32s(arrays::VERTEX_POSITION, &[4, 3], &[a, b, c, d].concat()),
        f32s(
            arrays::VERTEX_NORMAL,
            &[4, 3],
            &[[0.0, 1.0, 0.0]; 4].concat(),
        ),
        u32s(arrays::TRIANGLE_VERTEX, &[2, 3], &[0, 2, 1, 0, 3, 2]),
        f32s(arrays::OCCLUDER_TRI, &[1, 3, 3], &[a, c, b].concat()),
        u64s(arrays::FF_ROW_PTR, &[3], &[0, 1, 2]),
        u32s(arrays::FF_COL, &[2], &[1, 0]),
        f32s(arrays::FF_VAL, &[2], &[0.25, 0.125]),
        u64s(arrays::S_ROW_PTR, &[3], &[0, 1, 2]),
        u32s(arrays::S_COL, &[2], &[0, 1]),
        f32s(arrays::S_VAL, &[2, 3], &[0.5; 6]),
        u64s(arrays::DIST_ROW_PTR, &[3], &[0, 0, 0]),
        u32s(arrays::DIST_COL, &[0], &[]),
        f32s(arrays::DIST_VAL, &[0], &[]),
        u32s(arrays::DIST_KIND, &[0], &[]),
        f32s(arrays::DIST_MATERIAL_LEN, &[0, 4], &[]),
        u32s(arrays::PATCH_MATERIAL, &[2], &[0, 0]),
    ];
    (manifest, arrays)
}

/// Writes the files and a manifest listing them (with their true checksums).
fn write(dir: &Path, mut manifest: Manifest, arrays: &[Raw]) {
    std::fs::create_dir_all(dir).unwrap();
    manifest.arrays.clear();
    for a in arrays {
        let file = array_file_name(a.name, a.dtype);
        std::fs::write(dir.join(&file), &a.bytes).unwrap();
        manifest.arrays.insert(
            a.name.into(),
            ArrayEntry {
                file,
                dtype: a.dtype,
                shape: a.shape.clone(),
                bytes: a.bytes.len() as u64,
                xxh3: checksum(&a.bytes),
            },
        );
    }
    std::fs::write(
        dir.join(MANIFEST_FILE),
        serde_json::to_string_pretty(&manifest).unwrap(),
    )
    .unwrap();
}

fn open_err(manifest: Manifest, arrays: &[Raw]) -> String {
    let tmp = tempfile::tempdir().unwrap();
    write(tmp.path(), manifest, arrays);
    match Bundle::open(tmp.path()) {
        Ok(_) => panic!("bundle opened but should not have"),
        Err(e) => e.to_string(),
    }
}

fn replace(arrays: &mut [Raw], new: Raw) {
    let slot = arrays.iter_mut().find(|a| a.name == new.name).unwrap();
    *slot = new;
}

#[test]
fn hand_made_bundle_round_trips() {
    let tmp = tempfile::tempdir().unwrap();
    let (manifest, arrays) = two_patches();
    write(tmp.path(), manifest.clone(), &arrays);
    let b = Bundle::open(tmp.path()).unwrap();
    assert_eq!(b.dir(), tmp.path());
    assert_eq!(b.manifest().objects, manifest.objects);
    assert_eq!(b.manifest().arrays.len(), REQUIRED_ARRAYS.len());
    assert_eq!(
        b.patch_corners()[0],
        [[0.0, 0.0, 0.0], [1.0, 0.0, 1.0], [1.0, 0.0, 0.0]]
    );
    assert_eq!(b.patch_normals(), &[[0.0, 1.0, 0.0]; 2]);
    assert_eq!(b.patch_areas(), &[0.5, 0.5]);
    assert_eq!(b.patch_objects(), &[0, 0]);
    assert_eq!(b.patch_albedo(), &[[0.5; 3]; 2]);
    assert_eq!(b.patch_emission(), &[[0.0; 3]; 2]);
    assert_eq!(b.vertex_positions()[2], [1.0, 0.0, 1.0]);
    assert_eq!(b.vertex_normals().len(), 4);
    assert_eq!(b.triangle_vertices(), &[[0, 2, 1], [0, 3, 2]]);
    assert_eq!(b.occluder_triangles().len(), 1);
    let f = b.form_factors();
    assert_eq!((f.n_rows(), f.n_cols(), f.nnz()), (2, 2, 2));
    assert_eq!(f.get(0, 1), 0.25);
    assert_eq!(f.get(1, 0), 0.125);
    assert_eq!(f.get(0, 0), 0.0);
    // Unknown names and wrong dtypes give empty slices, never a panic.
    assert!(b.f32s("nope").is_empty());
    assert!(b.f32s(arrays::FF_COL).is_empty());
    assert_eq!(b.u32s(arrays::FF_COL), &[1, 0]);
    let on_disk: u64 = std::fs::read_dir(tmp.path())
        .unwrap()
        .map(|e| e.unwrap().metadata().unwrap().len())
        .sum();
    assert_eq!(b.total_bytes(), on_disk);
}

#[test]
fn bundle_can_be_shared_between_threads() {
    fn shared<T: Send + Sync>() {}
    shared::<Bundle>();
}

#[test]
fn empty_bundle_maps_zero_length_files() {
    let tmp = tempfile::tempdir().unwrap();
    let (mut manifest, arrays) = two_patches();
    manifest.patch_count = 0;
    manifest.vertex_count = 0;
    manifest.occluder_count = 0;
    manifest.form_factors.nnz = 0;
    manifest.subsurface.nnz = 0;
    manifest.objects.clear();
    let arrays: Vec<Raw> = arrays
        .into_iter()
        .map(|a| {
            if [arrays::FF_ROW_PTR, arrays::S_ROW_PTR, arrays::DIST_ROW_PTR].contains(&a.name) {
                u64s(a.name, &[1], &[0])
            } else {
                let mut shape = a.shape;
                shape[0] = 0;
                Raw {
                    shape,
                    bytes: vec![],
                    ..a
                }
            }
        })
        .collect();
    write(tmp.path(), manifest, &arrays);
    let b = Bundle::open(tmp.path()).unwrap();
    assert!(b.patch_corners().is_empty());
    assert!(b.triangle_vertices().is_empty());
    assert_eq!(b.form_factors().n_rows(), 0);
    assert_eq!(b.form_factors().row_ptr(), &[0]);
}

#[test]
fn extra_arrays_are_verified_and_mapped() {
    let tmp = tempfile::tempdir().unwrap();
    let (manifest, mut arrays) = two_patches();
    arrays.push(f32s("extra_val", &[3], &[1.0, 2.0, 3.0]));
    write(tmp.path(), manifest, &arrays);
    let b = Bundle::open(tmp.path()).unwrap();
    assert_eq!(b.f32s("extra_val"), &[1.0, 2.0, 3.0]);
    // A corrupted extra array is refused like any other.
    std::fs::write(
        tmp.path().join("extra_val.f32"),
        bytemuck::cast_slice(&[1.0f32, 2.0, 4.0]),
    )
    .unwrap();
    let e = Bundle::open(tmp.path()).unwrap_err().to_string();
    assert!(e.starts_with("extra_val.f32 is corrupt: checksum "), "{e}");
}

#[test]
fn content_rules_name_the_file() {
    let base = two_patches;

    let (m, mut a) = base();
    replace(
        &mut a,
        u32s(arrays::TRIANGLE_VERTEX, &[2, 3], &[0, 2, 1, 0, 4, 2]),
    );
    let e = open_err(m, &a);
    assert!(
        e.starts_with("triangle_vertex.u32: triangle 1 corner 1 is vertex 4"),
        "{e}"
    );

    let (m, mut a) = base();
    replace(&mut a, f32s(arrays::PATCH_AREA, &[2], &[0.5, 0.0]));
    let e = open_err(m, &a);
    assert!(e.starts_with("patch_area.f32: patch 1 has area 0"), "{e}");

    let (m, mut a) = base();
    replace(
        &mut a,
        f32s(
            arrays::VERTEX_NORMAL,
            &[4, 3],
            &[[0.0, f32::NAN, 0.0]; 4].concat(),
        ),
    );
    assert!(open_err(m, &a).starts_with("vertex_normal.f32: element 1 is NaN"));

    let (m, mut a) = base();
    replace(&mut a, u32s(arrays::PATCH_OBJECT, &[2], &[0, 1]));
    let e = open_err(m, &a);
    assert!(
        e.starts_with("patch_object.u32: patch 1 names object 1 but the manifest lists 1"),
        "{e}"
    );

    // Objects must cover 0..N.
    let (mut m, a) = base();
    m.objects[0].patch_count = 1;
    let e = open_err(m, &a);
    assert!(
        e.starts_with("manifest.json: the objects cover patches 0..1 but patch_count is 2"),
        "{e}"
    );
    let (mut m, a) = base();
    m.objects[0].first_patch = 1;
    m.objects[0].patch_count = 1;
    assert!(open_err(m, &a).contains("objects[0] (\"floor\") starts at patch 1"));

    // A count that disagrees with a shape.
    let (mut m, a) = base();
    m.vertex_count = 5;
    let e = open_err(m, &a);
    assert!(
        e.starts_with("vertex_position.f32: shape [4, 3] does not match"),
        "{e}"
    );

    // A wrong dtype.
    let (m, mut a) = base();
    replace(&mut a, f32s(arrays::PATCH_OBJECT, &[2], &[0.0, 0.0]));
    let e = open_err(m, &a);
    assert!(
        e.starts_with("patch_object.u32: manifest lists dtype f32, expected u32"),
        "{e}"
    );

    // A missing manifest entry.
    let (m, mut a) = base();
    a.retain(|r| r.name != arrays::OCCLUDER_TRI);
    assert_eq!(
        open_err(m, &a),
        "occluder_tri.f32 is missing from manifest.json"
    );

    // A file longer than listed.
    let tmp = tempfile::tempdir().unwrap();
    let (m, a) = base();
    write(tmp.path(), m, &a);
    std::fs::write(tmp.path().join("ff_col.u32"), [0u8; 12]).unwrap();
    let e = Bundle::open(tmp.path()).unwrap_err().to_string();
    assert_eq!(e, "ff_col.u32 is too long: 12 bytes, manifest says 8");

    // Unsorted columns name ff_col; a wrong row_ptr names ff_row_ptr.
    let (mut m, mut a) = base();
    m.form_factors.nnz = 2;
    replace(&mut a, u64s(arrays::FF_ROW_PTR, &[3], &[0, 2, 2]));
    replace(&mut a, u32s(arrays::FF_COL, &[2], &[1, 0]));
    let tmp = tempfile::tempdir().unwrap();
    write(tmp.path(), m.clone(), &a);
    match Bundle::open(tmp.path()).unwrap_err() {
        BundleError::Csr { file, error } => {
            assert_eq!(file, "ff_col.u32");
            assert_eq!(error, CsrError::ColumnsUnsorted { row: 0, col: 0 });
        }
        other => panic!("{other}"),
    }
    replace(&mut a, u64s(arrays::FF_ROW_PTR, &[3], &[1, 2, 2]));
    let e = open_err(m, &a);
    assert!(
        e.starts_with("ff_row_ptr.u64: F is not a valid CSR matrix: row_ptr[0] is 1"),
        "{e}"
    );
}

#[test]
fn per_medium_lengths_and_patch_media_are_checked() {
    // Two distances (0 → 1 and 1 → 0) with their per-medium lengths.
    let with = |lens: [f32; 8], media: [u32; 2]| {
        let (mut m, mut a) = two_patches();
        m.subsurface.distance_nnz = 2;
        replace(&mut a, u64s(arrays::DIST_ROW_PTR, &[3], &[0, 1, 2]));
        replace(&mut a, u32s(arrays::DIST_COL, &[2], &[1, 0]));
        replace(&mut a, f32s(arrays::DIST_VAL, &[2], &[0.5, 0.5]));
        replace(&mut a, f32s(arrays::DIST_MATERIAL_LEN, &[2, 4], &lens));
        replace(&mut a, u32s(arrays::DIST_KIND, &[2], &[0, 0]));
        replace(&mut a, u32s(arrays::PATCH_MATERIAL, &[2], &media));
        (m, a)
    };
    let tmp = tempfile::tempdir().unwrap();
    let (m, a) = with([0.2, 0.3, 0.0, 0.0, 0.3, 0.2, 0.0, 0.0], [0, 1]);
    write(tmp.path(), m, &a);
    let b = Bundle::open(tmp.path()).unwrap();
    assert_eq!(b.f32s(arrays::DIST_MATERIAL_LEN)[4], 0.3);
    assert_eq!(b.u32s(arrays::PATCH_MATERIAL), &[0, 1]);

    let (m, a) = with([0.2, 0.3, 0.0, 0.0, 0.3, -0.2, 0.0, 0.0], [0, 1]);
    let e = open_err(m, &a);
    assert!(
        e.starts_with("dist_material_len.f32: distance 1 medium 1 has length -0.2"),
        "{e}"
    );
    let (m, a) = with([0.2, f32::NAN, 0.0, 0.0, 0.3, 0.2, 0.0, 0.0], [0, 1]);
    assert!(open_err(m, &a).starts_with("dist_material_len.f32: distance 0 medium 1"));
    let (m, a) = with([0.0; 8], [0, 4]);
    let e = open_err(m, &a);
    assert!(
        e.starts_with("patch_material.u32: patch 1 names medium 4; there are at most 4"),
        "{e}"
    );
    // The shape follows the distance count, with 4 media per distance.
    let (m, mut a) = with([0.0; 8], [0, 0]);
    replace(&mut a, f32s(arrays::DIST_MATERIAL_LEN, &[2, 3], &[0.0; 6]));
    let e = open_err(m, &a);
    assert!(
        e.starts_with("dist_material_len.f32: shape [2, 3] does not match"),
        "{e}"
    );
}

#[test]
fn distance_kinds_are_0_or_1() {
    // Two distances (0 → 1 and 1 → 0): a thin sheet's front and back patch.
    let with = |kinds: [u32; 2]| {
        let (mut m, mut a) = two_patches();
        m.subsurface.distance_nnz = 2;
        replace(&mut a, u64s(arrays::DIST_ROW_PTR, &[3], &[0, 1, 2]));
        replace(&mut a, u32s(arrays::DIST_COL, &[2], &[1, 0]));
        replace(&mut a, f32s(arrays::DIST_VAL, &[2], &[0.0, 0.0]));
        replace(&mut a, u32s(arrays::DIST_KIND, &[2], &kinds));
        // Other per-distance arrays follow the count (all zeros).
        for r in a.iter_mut() {
            if ![arrays::DIST_COL, arrays::DIST_VAL, arrays::DIST_KIND].contains(&r.name)
                && r.shape.first() == Some(&0)
            {
                r.shape[0] = 2;
                let per: u64 = r.shape[1..].iter().product();
                r.bytes = vec![0u8; (2 * per) as usize * r.dtype.size()];
            }
        }
        (m, a)
    };
    let tmp = tempfile::tempdir().unwrap();
    let (m, a) = with([1, 1]);
    write(tmp.path(), m, &a);
    let b = Bundle::open(tmp.path()).unwrap();
    assert_eq!(b.distance_kinds(), &[1, 1]);
    assert_eq!(b.distances().nnz(), 2);

    let (m, a) = with([0, 2]);
    let e = open_err(m, &a);
    assert!(
        e.starts_with("dist_kind.u32: distance 1 has kind 2, expected 0 (same side) or 1"),
        "{e}"
    );
    // The shape follows the distance count.
    let (m, mut a) = with([0, 1]);
    replace(&mut a, u32s(arrays::DIST_KIND, &[1], &[0]));
    let e = open_err(m, &a);
    assert!(
        e.starts_with("dist_kind.u32: shape [1] does not match"),
        "{e}"
    );
}

#[test]
fn link_spreads_are_listed_with_their_near_field_and_checked() {
    // Two distances, the second read at two distances with spread 0.5.
    let with = |spread: Option<&[f32]>| {
        let (mut m, mut a) = two_patches();
        m.subsurface.distance_nnz = 2;
        m.subsurface.link_near = Some(1.5);
        replace(&mut a, u64s(arrays::DIST_ROW_PTR, &[3], &[0, 1, 2]));
        replace(&mut a, u32s(arrays::DIST_COL, &[2], &[1, 0]));
        replace(&mut a, f32s(arrays::DIST_VAL, &[2], &[1.0, 1.0]));
        replace(&mut a, u32s(arrays::DIST_KIND, &[2], &[0, 0]));
        replace(&mut a, f32s(arrays::DIST_MATERIAL_LEN, &[2, 4], &[0.0; 8]));
        if let Some(s) = spread {
            a.push(f32s(arrays::DIST_SPREAD, &[s.len() as u64], s));
        }
        (m, a)
    };
    let tmp = tempfile::tempdir().unwrap();
    let (m, a) = with(Some(&[0.0, 0.5]));
    write(tmp.path(), m, &a);
    let b = Bundle::open(tmp.path()).unwrap();
    assert_eq!(b.distance_spreads(), &[0.0, 0.5]);
    assert_eq!(b.manifest().subsurface.link_near, Some(1.5));

    let (m, a) = with(None);
    let e = open_err(m, &a);
    assert!(
        e.starts_with("dist_spread.f32 is missing from manifest.json"),
        "{e}"
    );
    let (m, a) = with(Some(&[0.0, -1.0]));
    let e = open_err(m, &a);
    assert!(
        e.starts_with("dist_spread.f32: distance 1 has spread -1"),
        "{e}"
    );
    let (m, a) = with(Some(&[0.0, f32::NAN]));
    assert!(open_err(m, &a).starts_with("dist_spread.f32: distance 1 has spread NaN"));
    let (m, a) = with(Some(&[0.0]));
    let e = open_err(m, &a);
    assert!(
        e.starts_with("dist_spread.f32: manifest lists f32 [1], expected f32 [2]"),
        "{e}"
    );
}

/// Small arrays are private copies: truncating one in place (what an operator must not
/// do, but might) changes nothing the server reads and cannot raise SIGBUS.
#[test]
fn small_arrays_survive_being_truncated_in_place() {
    let tmp = tempfile::tempdir().unwrap();
    let (m, a) = two_patches();
    write(tmp.path(), m, &a);
    let b = Bundle::open(tmp.path()).unwrap();
    assert_eq!(b.mapped_bytes(), 0, "a tiny bundle is copied, not mapped");
    for e in std::fs::read_dir(tmp.path()).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x != "json") {
            std::fs::OpenOptions::new()
                .write(true)
                .open(&p)
                .unwrap()
                .set_len(0)
                .unwrap();
        }
    }
    let f = b.form_factors();
    assert_eq!((f.get(0, 1), f.get(1, 0)), (0.25, 0.125));
    assert_eq!(b.patch_areas(), &[0.5, 0.5]);
}

/// A FIFO where a bundle file should be: opening it for reading would block until a
/// writer appears, hanging the loader. It must be an error at once.
#[test]
fn a_fifo_in_a_bundle_folder_is_an_error_not_a_hang() {
    for file in ["ff_val.f32", MANIFEST_FILE] {
        let tmp = tempfile::tempdir().unwrap();
        let (m, a) = two_patches();
        write(tmp.path(), m, &a);
        let path = tmp.path().join(file);
        std::fs::remove_file(&path).unwrap();
        let made = std::process::Command::new("mkfifo").arg(&path).status();
        assert!(made.is_ok_and(|s| s.success()), "mkfifo {}", path.display());
        let dir = tmp.path().to_path_buf();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send(Bundle::open(&dir).map(|_| ()).map_err(|e| e.to_string()));
        });
        let got = rx
            .recv_timeout(std::time::Duration::from_secs(10))
            .expect("Bundle::open hung on a FIFO");
        let e = got.unwrap_err();
        assert!(e.contains(file) && e.contains("not a regular file"), "{e}");
    }
}

#[test]
fn manifest_entries_cannot_escape_the_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let (m, a) = two_patches();
    write(tmp.path(), m, &a);
    let path = tmp.path().join(MANIFEST_FILE);
    let text = std::fs::read_to_string(&path).unwrap();
    std::fs::write(&path, text.replace("\"ff_val.f32\"", "\"../ff_val.f32\"")).unwrap();
    let e = Bundle::open(tmp.path()).unwrap_err().to_string();
    assert!(
        e.starts_with("manifest.json: array ff_val is stored as \"../ff_val.f32\""),
        "{e}"
    );

    // Listed byte counts must agree with the shape.
    let (m, a) = two_patches();
    write(tmp.path(), m, &a);
    let mut m: Manifest = crate::parse_json(&std::fs::read_to_string(&path).unwrap()).unwrap();
    m.arrays.get_mut(arrays::FF_VAL).unwrap().bytes = 12;
    std::fs::write(&path, serde_json::to_string(&m).unwrap()).unwrap();
    let e = Bundle::open(tmp.path()).unwrap_err().to_string();
    assert!(
        e.contains("ff_val.f32: manifest lists 12 bytes but shape [2] of f32 holds 8"),
        "{e}"
    );
}

#[test]
fn manifest_errors_name_manifest_json() {
    let tmp = tempfile::tempdir().unwrap();
    let e = Bundle::open(&tmp.path().join("nope")).unwrap_err();
    assert!(matches!(e, BundleError::Missing { .. }), "{e}");
    let e = Bundle::open(tmp.path()).unwrap_err().to_string();
    assert_eq!(e, "manifest.json is missing");
    std::fs::write(tmp.path().join(MANIFEST_FILE), "{\n  \"format\": 3\n}").unwrap();
    let e = Bundle::open(tmp.path()).unwrap_err();
    assert_eq!(e.file(), MANIFEST_FILE);
    assert!(
        e.to_string()
            .starts_with("manifest.json: line 2 column 13: format: invalid type"),
        "{e}"
    );
    let (mut m, a) = two_patches();
    m.format = "zip".into();
    assert_eq!(
        open_err(m, &a),
        "manifest.json: format is \"zip\", expected \"translux-bundle\""
    );
    let (mut m, a) = two_patches();
    m.version = FORMAT_VERSION + 1;
    assert_eq!(
        open_err(m, &a),
        format!(
            "manifest.json: bundle version {} is not supported (this build reads versions 4 to \
             {FORMAT_VERSION}); rebuild the bundle with this build's translux-precompute",
            FORMAT_VERSION + 1
        )
    );
}

/// A version 4 bundle (dense F, no hierarchy) still opens.
#[test]
fn version_4_bundles_still_open() {
    let tmp = tempfile::tempdir().unwrap();
    let (mut m, a) = two_patches();
    m.version = 4;
    write(tmp.path(), m, &a);
    let b = Bundle::open(tmp.path()).unwrap();
    assert!(b.tree().is_none());
    assert_eq!(b.form_factors().n_cols(), 2);
}

/// A hierarchical F: C has a column per node past the patches; the tree's permutation
/// and ranges are checked.
#[test]
fn hierarchical_f_opens_and_a_bad_tree_is_refused() {
    let hierarchical = |perm: &[u32], range: &[u32]| {
        let (mut m, mut a) = two_patches();
        m.hierarchy = Some(HierarchyInfo {
            nodes: 1,
            ..Default::default()
        });
        // Row 0 sees node 0 (patches 0 and 1), row 1 sees patch 0.
        replace(&mut a, u32s(arrays::FF_COL, &[2], &[2, 0]));
        a.push(u32s(arrays::TREE_PERM, &[2], perm));
        a.push(u32s(arrays::TREE_RANGE, &[1, 2], range));
        (m, a)
    };
    let tmp = tempfile::tempdir().unwrap();
    let (m, a) = hierarchical(&[1, 0], &[0, 2]);
    write(tmp.path(), m, &a);
    let b = Bundle::open(tmp.path()).unwrap();
    let t = b.tree().unwrap();
    assert_eq!((t.perm, t.range), (&[1u32, 0][..], &[[0u32, 2]][..]));
    assert_eq!(b.form_factors().n_cols(), 3);
    let (m, a) = hierarchical(&[1, 1], &[0, 2]);
    assert_eq!(
        open_err(m, &a),
        "tree_perm.u32: patch 1 appears twice (not a permutation)"
    );
    let (m, a) = hierarchical(&[0, 1], &[1, 2]);
    assert_eq!(
        open_err(m, &a),
        "tree_range.u32: node 0 covers [1, 2): expected at least two patches within 0..2"
    );
    // Without the hierarchy the column past N is out of range.
    let (mut m, a) = hierarchical(&[0, 1], &[0, 2]);
    m.hierarchy = None;
    assert!(open_err(m, &a).contains("out of range"));
}

/// A two-sided F: with `hierarchy.receiver_nodes` C has a row per node after the patch
/// rows (`ff_row_ptr` N + M + 1 long); without the flag those offsets are refused.
#[test]
fn node_rows_of_f_open_with_receiver_nodes_only() {
    let two_sided = |receiver_nodes: bool| {
        let (mut m, mut a) = two_patches();
        m.hierarchy = Some(HierarchyInfo {
            nodes: 1,
            receiver_nodes,
            ..Default::default()
        });
        m.form_factors.nnz = 3;
        // Row 0 sees patch 1, row 1 nothing, node 0 (both patches) receives 0.25·node 0.
        replace(&mut a, u64s(arrays::FF_ROW_PTR, &[4], &[0, 1, 1, 3]));
        replace(&mut a, u32s(arrays::FF_COL, &[3], &[1, 0, 2]));
        replace(&mut a, f32s(arrays::FF_VAL, &[3], &[0.5, 0.125, 0.25]));
        a.push(u32s(arrays::TREE_PERM, &[2], &[0, 1]));
        a.push(u32s(arrays::TREE_RANGE, &[1, 2], &[0, 2]));
        (m, a)
    };
    let tmp = tempfile::tempdir().unwrap();
    let (m, a) = two_sided(true);
    write(tmp.path(), m, &a);
    let b = Bundle::open(tmp.path()).unwrap();
    assert_eq!(b.ff_rows(), 3);
    let f = b.form_factors();
    assert_eq!((f.n_rows(), f.n_cols()), (3, 3));
    assert_eq!(f.row(2).0, &[0, 2]);
    let (m, a) = two_sided(false);
    let err = open_err(m, &a);
    assert!(
        err.contains("ff_row_ptr") && err.contains("receiver_nodes"),
        "{err}"
    );
}

/// A hierarchical S: with `subsurface.links` S and the distances have node columns over
/// F's tree; without the tree it is refused, and without `links` a node column is out of
/// range.
#[test]
fn hierarchical_s_opens_with_the_tree_and_is_refused_without_it() {
    let linked = |links: u64, tree: bool| {
        let (mut m, mut a) = two_patches();
        if tree {
            m.hierarchy = Some(HierarchyInfo {
                nodes: 1,
                ..Default::default()
            });
            a.push(u32s(arrays::TREE_PERM, &[2], &[0, 1]));
            a.push(u32s(arrays::TREE_RANGE, &[1, 2], &[0, 2]));
        }
        m.subsurface.links = links;
        m.subsurface.distance_nnz = 1;
        // Row 1 gathers node 0 (column N + 0 = 2) whole; its distance is stored likewise.
        m.subsurface.nnz = 3;
        replace(&mut a, u64s(arrays::S_ROW_PTR, &[3], &[0, 1, 3]));
        replace(&mut a, u32s(arrays::S_COL, &[3], &[0, 1, 2]));
        replace(&mut a, f32s(arrays::S_VAL, &[3, 3], &[0.25; 9]));
        replace(&mut a, u64s(arrays::DIST_ROW_PTR, &[3], &[0, 0, 1]));
        replace(&mut a, u32s(arrays::DIST_COL, &[1], &[2]));
        replace(&mut a, f32s(arrays::DIST_VAL, &[1], &[0.75]));
        replace(&mut a, u32s(arrays::DIST_KIND, &[1], &[0]));
        replace(&mut a, f32s(arrays::DIST_MATERIAL_LEN, &[1, 4], &[0.0; 4]));
        (m, a)
    };
    let tmp = tempfile::tempdir().unwrap();
    let (m, a) = linked(1, true);
    write(tmp.path(), m, &a);
    let b = Bundle::open(tmp.path()).unwrap();
    assert_eq!((b.subsurface().n_cols(), b.distances().n_cols()), (3, 3));
    assert_eq!(b.subsurface().row(1).0, &[1, 2]);
    let (m, a) = linked(1, false);
    assert!(
        open_err(m, &a).contains("needs the cluster tree"),
        "a hierarchical S without the tree"
    );
    let (m, a) = linked(0, true);
    assert!(open_err(m, &a).contains("out of range"));
}
