//! Writing a bundle atomically.
//!
//! In: the output folder, a [`Manifest`] (its `arrays` map is filled here) and the arrays.
//! Out: a bundle folder that [`translux_proto::bundle::Bundle::open`] accepts, or an error
//! and no trace on disk. The layout is documented in [`translux_proto::bundle`].
//!
//! Every file goes into a temporary folder next to `out` (`.{name}.tmp-{pid}-{nanos}-{seq}`,
//! same parent, so the final rename stays on one file system), is fsynced, and the folder is
//! renamed into place. An existing bundle at `out` is renamed aside
//! (`.{name}.old-{pid}-{nanos}-{seq}`) first and deleted after the new one is in place, so
//! a server that maps the old bundle keeps reading intact files. Readers scanning a folder of
//! bundles should skip names that start with `.`.

use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use translux_proto::bundle::{
    ArrayEntry, DType, MANIFEST_FILE, Manifest, REQUIRED_ARRAYS, array_file_name, checksum,
    is_valid_array_name,
};

/// The elements of one array, in row-major order.
#[derive(Debug, Clone, PartialEq)]
pub enum ArrayData {
    /// IEEE half floats as raw bits.
    F16(Vec<u16>),
    F32(Vec<f32>),
    U32(Vec<u32>),
    U64(Vec<u64>),
}

impl ArrayData {
    /// The element type.
    pub fn dtype(&self) -> DType {
        match self {
            ArrayData::F16(_) => DType::F16,
            ArrayData::F32(_) => DType::F32,
            ArrayData::U32(_) => DType::U32,
            ArrayData::U64(_) => DType::U64,
        }
    }

    /// The number of elements.
    pub fn len(&self) -> usize {
        match self {
            ArrayData::F16(v) => v.len(),
            ArrayData::F32(v) => v.len(),
            ArrayData::U32(v) => v.len(),
            ArrayData::U64(v) => v.len(),
        }
    }

    /// Whether there are no elements.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The elements as little-endian bytes (the bundle is little-endian only; proto refuses to
    /// build on big-endian targets).
    pub fn bytes(&self) -> &[u8] {
        match self {
            ArrayData::F16(v) => bytemuck::cast_slice(v),
            ArrayData::F32(v) => bytemuck::cast_slice(v),
            ArrayData::U32(v) => bytemuck::cast_slice(v),
            ArrayData::U64(v) => bytemuck::cast_slice(v),
        }
    }
}

/// One array to write: `name` (an [`translux_proto::bundle::arrays`] constant, or another
/// lower-case name), its shape (the product must equal the element count) and the data. The
/// file is `NAME.DTYPE`.
#[derive(Debug, Clone, PartialEq)]
pub struct NamedArray {
    pub name: &'static str,
    pub shape: Vec<u64>,
    pub data: ArrayData,
}

impl NamedArray {
    /// An f32 array.
    pub fn f32(name: &'static str, shape: Vec<u64>, data: Vec<f32>) -> Self {
        Self {
            name,
            shape,
            data: ArrayData::F32(data),
        }
    }
    /// A u32 array.
    pub fn u32(name: &'static str, shape: Vec<u64>, data: Vec<u32>) -> Self {
        Self {
            name,
            shape,
            data: ArrayData::U32(data),
        }
    }
    /// A u64 array.
    pub fn u64(name: &'static str, shape: Vec<u64>, data: Vec<u64>) -> Self {
        Self {
            name,
            shape,
            data: ArrayData::U64(data),
        }
    }
}

/// What [`write_bundle`] wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WriteReport {
    /// Bytes of all files, manifest included.
    pub bytes: u64,
    /// Files written, manifest included.
    pub files: usize,
}

/// Why a bundle could not be written. Nothing is left on disk when it is returned.
#[derive(Debug, thiserror::Error)]
pub enum BundleWriteError {
    /// The data length disagrees with the shape.
    #[error("array {name}: {elements} elements, but shape {shape:?} holds {expected}")]
    Shape {
        name: String,
        elements: usize,
        shape: Vec<u64>,
        expected: String,
    },
    /// The name is not usable as a file name, or appears twice.
    #[error("array {name:?}: {reason}")]
    Name { name: String, reason: String },
    /// A known array with the wrong element type.
    #[error("array {name}: element type {got}, the format requires {expected}")]
    DType {
        name: String,
        got: &'static str,
        expected: &'static str,
    },
    /// `out` has no final component (`/`, `..`).
    #[error("{}: not usable as a bundle folder (it must end in a folder name)", .0.display())]
    BadOut(PathBuf),
    /// `out` exists and is not a bundle: refuse to delete it.
    #[error(
        "{}: exists and is not a bundle (no {MANIFEST_FILE} in it); refusing to replace it",
        .0.display()
    )]
    NotABundle(PathBuf),
    /// The manifest cannot be written as JSON that reads back the same (e.g. a NaN field).
    #[error("{MANIFEST_FILE}: {0}")]
    Manifest(String),
    /// A file-system operation failed.
    #[error("{what} {}: {error}", .path.display())]
    Io {
        what: &'static str,
        path: PathBuf,
        error: std::io::Error,
    },
}

fn io_err(what: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> BundleWriteError {
    let path = path.to_path_buf();
    move |error| BundleWriteError::Io { what, path, error }
}

/// Removes a folder on drop unless disarmed: the temporary bundle on every error path.
struct RemoveOnDrop(Option<PathBuf>);

impl RemoveOnDrop {
    fn disarm(&mut self) {
        self.0 = None;
    }
}

impl Drop for RemoveOnDrop {
    fn drop(&mut self) {
        if let Some(path) = self.0.take() {
            let _ = fs::remove_dir_all(path);
        }
    }
}

/// A name for a sibling of `out` that no other writer (thread or process) picks.
fn sibling_name(out_name: &str, kind: &str) -> String {
    static SEQ: AtomicU64 = AtomicU64::new(0);
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    let seq = SEQ.fetch_add(1, Ordering::Relaxed);
    format!(".{out_name}.{kind}-{}-{nanos}-{seq}", std::process::id())
}

/// Whose leftovers [`settle_leftovers`] settles.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Writers {
    /// Those of processes that no longer run: folders of a process that still runs (or of
    /// this one) may be a write in progress and are left alone.
    Gone,
    /// Every writer's: the caller knows that none still writes `out` (a server settling
    /// the jobs its previous run left unfinished).
    All,
}

/// What [`settle_leftovers`] did.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct Settled {
    /// Folder names removed: temporary bundles, and old bundles already replaced.
    pub removed: Vec<String>,
    /// The old bundle's folder name, renamed back to `out` (a writer was killed between
    /// moving it aside and renaming the new one into place).
    pub restored: Option<String>,
}

/// Settles what writers of `out` that no longer run left beside it when they were killed
/// (`.{name}.tmp-PID-*`, `.{name}.old-PID-*`, see the module docs): an old bundle whose
/// replacement never arrived goes back to `out`; every other leftover is removed.
/// [`write_bundle`] calls it first; a server calls it at start-up.
pub fn settle_leftovers(out: &Path, writers: Writers) -> Result<Settled, BundleWriteError> {
    let (Some(name), Some(parent)) = (out.file_name(), out.parent()) else {
        return Err(BundleWriteError::BadOut(out.to_path_buf()));
    };
    let parent = if parent.as_os_str().is_empty() {
        Path::new(".")
    } else {
        parent
    };
    let name = name.to_string_lossy();
    let mut found: Vec<(String, &str)> = Vec::new();
    let entries = match fs::read_dir(parent) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Settled::default()),
        Err(e) => return Err(io_err("reading", parent)(e)),
    };
    for e in entries.flatten() {
        let file = e.file_name().to_string_lossy().into_owned();
        for kind in ["tmp", "old"] {
            let Some(rest) = file.strip_prefix(&format!(".{name}.{kind}-")) else {
                continue;
            };
            let pid = rest.split('-').next().and_then(|p| p.parse::<u32>().ok());
            let gone = match writers {
                Writers::Gone => pid.is_some_and(|p| !process_runs(p)),
                Writers::All => true,
            };
            if gone && e.path().is_dir() {
                found.push((file.clone(), kind));
            }
        }
    }
    // Names sort by pid then time: the last old bundle is the newest one set aside.
    found.sort();
    let mut settled = Settled::default();
    if !out.exists()
        && let Some((old, _)) = found.iter().rev().find(|(_, kind)| *kind == "old")
    {
        fs::rename(parent.join(old), out).map_err(io_err("restoring", out))?;
        settled.restored = Some(old.clone());
    }
    for (file, _) in found {
        if settled.restored.as_ref() != Some(&file) {
            let path = parent.join(&file);
            fs::remove_dir_all(&path).map_err(io_err("removing", &path))?;
            settled.removed.push(file);
        }
    }
    if settled.restored.is_some() || !settled.removed.is_empty() {
        sync_dir(parent)?;
    }
    Ok(settled)
}

/// Whether process `pid` runs (this one counts as running). Off Linux, where `/proc` is
/// absent, every process is taken to run: nothing is removed.
fn process_runs(pid: u32) -> bool {
    pid == std::process::id()
        || !Path::new("/proc/self").exists()
        || Path::new("/proc").join(pid.to_string()).exists()
}

/// Flushes a folder's entries (renames, new files) to disk. Best effort off Unix, where a
/// folder cannot be opened as a file.
fn sync_dir(path: &Path) -> Result<(), BundleWriteError> {
    #[cfg(unix)]
    {
        File::open(path)
            .and_then(|f| f.sync_all())
            .map_err(io_err("syncing folder", path))?;
    }
    #[cfg(not(unix))]
    let _ = path;
    Ok(())
}

/// Writes `bytes` to a new file `path` and fsyncs it.
fn write_file(path: &Path, bytes: &[u8]) -> Result<(), BundleWriteError> {
    let mut f = File::create_new(path).map_err(io_err("creating", path))?;
    f.write_all(bytes).map_err(io_err("writing", path))?;
    f.sync_all().map_err(io_err("syncing", path))
}

/// Checks names, dtypes of known arrays and element counts against shapes.
fn check_arrays(arrays: &[NamedArray]) -> Result<(), BundleWriteError> {
    let mut seen = std::collections::BTreeSet::new();
    for a in arrays {
        if !is_valid_array_name(a.name) {
            return Err(BundleWriteError::Name {
                name: a.name.into(),
                reason: "must be lower-case letters, digits and '_'".into(),
            });
        }
        if !seen.insert(a.name) {
            return Err(BundleWriteError::Name {
                name: a.name.into(),
                reason: "appears twice".into(),
            });
        }
        if let Some(&(_, dtype)) = REQUIRED_ARRAYS.iter().find(|(n, _)| *n == a.name)
            && dtype != a.data.dtype()
        {
            return Err(BundleWriteError::DType {
                name: a.name.into(),
                got: a.data.dtype().name(),
                expected: dtype.name(),
            });
        }
        let product = a.shape.iter().try_fold(1u64, |acc, &d| acc.checked_mul(d));
        let elements = a.data.len();
        if product != Some(elements as u64) {
            return Err(BundleWriteError::Shape {
                name: a.name.into(),
                elements,
                shape: a.shape.clone(),
                expected: product.map_or("more than 2^64".into(), |p| p.to_string()),
            });
        }
    }
    Ok(())
}

/// Writes a bundle folder at `out`, atomically.
///
/// In: `out` (its parent is created if missing), the `manifest` with every field but `arrays`
/// filled (whatever `arrays` holds is replaced by the entries of the files written, with
/// their XXH3-64 checksums), and the arrays (each becomes `NAME.DTYPE`, raw little-endian).
/// Out: the total bytes and files written.
///
/// Checked before anything touches the disk: names are lower-case identifiers and unique,
/// known arrays have the format's element type, and each element count equals the product of
/// its shape. The manifest must serialize to JSON that reads back identically (a NaN in a
/// float field does not). The writer does not check the bundle's content rules (counts,
/// CSR invariants): `Bundle::open` does.
///
/// Replacing: when `out` exists it must be a bundle (hold a `manifest.json`) or an empty
/// folder, else [`BundleWriteError::NotABundle`]; the old folder is renamed aside, the new
/// one renamed in, then the old one deleted. On any error the temporary folder is removed and
/// `out` is left as it was.
pub fn write_bundle(
    out: &Path,
    manifest: Manifest,
    arrays: Vec<NamedArray>,
) -> Result<WriteReport, BundleWriteError> {
    write_bundle_keeping(out, manifest, arrays, &[])
}

/// An array file of an existing bundle copied unchanged into a new one
/// ([`write_bundle_keeping`]): its manifest name and entry, and the file to copy.
#[derive(Debug, Clone)]
pub struct KeptArray {
    pub name: String,
    pub entry: ArrayEntry,
    pub from: PathBuf,
}

/// [`write_bundle`] with some arrays copied from an existing bundle as they are (their
/// entries, checksums included, carried over): how a bundle is rewritten in place when only
/// some of its arrays change ([`crate::resimulate`]). `kept` must not name an array of
/// `arrays`.
pub fn write_bundle_keeping(
    out: &Path,
    mut manifest: Manifest,
    arrays: Vec<NamedArray>,
    kept: &[KeptArray],
) -> Result<WriteReport, BundleWriteError> {
    check_arrays(&arrays)?;
    if let Some(k) = kept
        .iter()
        .find(|k| arrays.iter().any(|a| a.name == k.name))
    {
        return Err(BundleWriteError::Name {
            name: k.name.clone(),
            reason: "appears twice".into(),
        });
    }
    let out_name = match out.file_name() {
        Some(n) => n.to_string_lossy().into_owned(),
        None => return Err(BundleWriteError::BadOut(out.to_path_buf())),
    };
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    settle_leftovers(out, Writers::Gone)?;
    let replacing = match fs::symlink_metadata(out) {
        Ok(meta) => {
            let is_bundle = meta.is_dir()
                && (out.join(MANIFEST_FILE).is_file()
                    || fs::read_dir(out)
                        .map_err(io_err("reading", out))?
                        .next()
                        .is_none());
            if !is_bundle {
                return Err(BundleWriteError::NotABundle(out.to_path_buf()));
            }
            true
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => false,
        Err(e) => return Err(io_err("inspecting", out)(e)),
    };
    fs::create_dir_all(&parent).map_err(io_err("creating", &parent))?;

    let tmp = parent.join(sibling_name(&out_name, "tmp"));
    fs::create_dir(&tmp).map_err(io_err("creating", &tmp))?;
    let mut guard = RemoveOnDrop(Some(tmp.clone()));

    let mut report = WriteReport { bytes: 0, files: 0 };
    manifest.arrays.clear();
    for array in arrays {
        let dtype = array.data.dtype();
        let file = array_file_name(array.name, dtype);
        let bytes = array.data.bytes();
        write_file(&tmp.join(&file), bytes)?;
        let entry = ArrayEntry {
            file,
            dtype,
            shape: array.shape,
            bytes: bytes.len() as u64,
            xxh3: checksum(bytes),
        };
        report.bytes += entry.bytes;
        report.files += 1;
        manifest.arrays.insert(array.name.to_string(), entry);
        // `array.data` is dropped here: peak memory stays at the caller's arrays.
    }
    for k in kept {
        // File to file (never the whole bundle in memory), then flushed like the others.
        let to = tmp.join(&k.entry.file);
        fs::copy(&k.from, &to).map_err(io_err("copying", &k.from))?;
        File::open(&to)
            .and_then(|f| f.sync_all())
            .map_err(io_err("syncing", &to))?;
        report.bytes += k.entry.bytes;
        report.files += 1;
        manifest.arrays.insert(k.name.clone(), k.entry.clone());
    }

    let mut text = serde_json::to_string_pretty(&manifest)
        .map_err(|e| BundleWriteError::Manifest(e.to_string()))?;
    text.push('\n');
    match translux_proto::parse_json::<Manifest>(&text) {
        Ok(back) if back == manifest => {}
        Ok(_) => {
            return Err(BundleWriteError::Manifest(
                "does not read back as written (a NaN or infinite number in a float field?)".into(),
            ));
        }
        Err(e) => {
            return Err(BundleWriteError::Manifest(format!(
                "does not read back ({e}); a NaN or infinite number in a float field?"
            )));
        }
    }
    write_file(&tmp.join(MANIFEST_FILE), text.as_bytes())?;
    report.bytes += text.len() as u64;
    report.files += 1;
    sync_dir(&tmp)?;

    if replacing {
        let old = parent.join(sibling_name(&out_name, "old"));
        fs::rename(out, &old).map_err(io_err("moving aside", out))?;
        if let Err(e) = fs::rename(&tmp, out) {
            // Put the old bundle back; the guard removes the new one.
            let _ = fs::rename(&old, out);
            return Err(io_err("renaming into place", out)(e));
        }
        guard.disarm();
        // The new bundle is in place: from here on nothing may fail. Failing to delete the
        // old copy (a dot-folder) loses nothing.
        let _ = sync_dir(&parent);
        let _ = fs::remove_dir_all(&old);
    } else {
        fs::rename(&tmp, out).map_err(io_err("renaming into place", out))?;
        guard.disarm();
        // Durability of the rename is best effort: the bundle is in place and complete.
        let _ = sync_dir(&parent);
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use translux_proto::bundle::{
        Bundle, FORMAT, FORMAT_VERSION, FormFactorInfo, ObjectInfo, OpenOptions, SubsurfaceInfo,
        arrays,
    };
    use translux_proto::light::Camera;
    use translux_proto::scene::Material;

    const N: u64 = 4;
    const V: u64 = 5;
    const M: u64 = 2;

    fn manifest(nnz: u64) -> Manifest {
        Manifest {
            format: FORMAT.into(),
            version: FORMAT_VERSION,
            name: "fan".into(),
            source: "test".into(),
            created_by: "bundle tests".into(),
            unit_mm: 1000.0,
            patch_count: N,
            vertex_count: V,
            occluder_count: M,
            objects: vec![ObjectInfo {
                name: "fan".into(),
                material: Material::Diffuse {
                    albedo: [0.7, 0.6, 0.5],
                    specular: None,
                },
                first_patch: 0,
                patch_count: N,
                albedo: [0.7, 0.6, 0.5],
            }],
            lights: vec![],
            transfer: None,
            environment: None,
            hierarchy: None,
            camera: Camera {
                position: [0.0, 2.0, 0.0],
                target: [0.0; 3],
                up: [0.0, 0.0, 1.0],
                fov_deg: 45.0,
            },
            form_factors: FormFactorInfo {
                nnz,
                threshold: 0.0,
                ..Default::default()
            },
            subsurface: SubsurfaceInfo {
                nnz: N,
                ..Default::default()
            },
            stages: vec![],
            arrays: Default::default(),
        }
    }

    /// A fan of 4 triangles around vertex 0 (a square pyramid's base split in four), a
    /// 4 × 4 CSR F with a row per pattern (empty row included).
    fn fan_arrays(row_ptr: Vec<u64>, col: Vec<u32>, val: Vec<f32>) -> Vec<NamedArray> {
        let v: [[f32; 3]; 5] = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0],
            [-1.0, 0.0, 0.0],
            [0.0, 0.0, -1.0],
        ];
        let tris: [[u32; 3]; 4] = [[0, 2, 1], [0, 3, 2], [0, 4, 3], [0, 1, 4]];
        let corners: Vec<f32> = tris
            .iter()
            .flat_map(|t| t.iter().flat_map(|&k| v[k as usize]))
            .collect();
        let nnz = col.len() as u64;
        vec![
            NamedArray::f32(arrays::PATCH_CORNERS, vec![N, 3, 3], corners.clone()),
            NamedArray::f32(arrays::PATCH_NORMAL, vec![N, 3], [0.0, 1.0, 0.0].repeat(4)),
            NamedArray::f32(arrays::PATCH_AREA, vec![N], vec![0.5; 4]),
            NamedArray::u32(arrays::PATCH_OBJECT, vec![N], vec![0; 4]),
            NamedArray::f32(arrays::PATCH_ALBEDO, vec![N, 3], [0.7, 0.6, 0.5].repeat(4)),
            NamedArray::f32(
                arrays::PATCH_EMISSION,
                vec![N, 3],
                vec![0.0, 0.0, 0.0, 1.5, 2.5, 3.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            ),
            NamedArray::f32(arrays::VERTEX_POSITION, vec![V, 3], v.concat()),
            NamedArray::f32(arrays::VERTEX_NORMAL, vec![V, 3], [0.0, 1.0, 0.0].repeat(5)),
            NamedArray::u32(arrays::TRIANGLE_VERTEX, vec![N, 3], tris.concat()),
            NamedArray::f32(arrays::OCCLUDER_TRI, vec![M, 3, 3], corners[..18].to_vec()),
            NamedArray::u64(arrays::FF_ROW_PTR, vec![N + 1], row_ptr),
            NamedArray::u32(arrays::FF_COL, vec![nnz], col),
            NamedArray::f32(arrays::FF_VAL, vec![nnz], val),
            // S = diag(ρ); no translucent object, so no distances.
            NamedArray::u64(arrays::S_ROW_PTR, vec![N + 1], vec![0, 1, 2, 3, 4]),
            NamedArray::u32(arrays::S_COL, vec![N], vec![0, 1, 2, 3]),
            NamedArray::f32(arrays::S_VAL, vec![N, 3], [0.7, 0.6, 0.5].repeat(4)),
            NamedArray::u64(arrays::DIST_ROW_PTR, vec![N + 1], vec![0; 5]),
            NamedArray::u32(arrays::DIST_COL, vec![0], vec![]),
            NamedArray::f32(arrays::DIST_VAL, vec![0], vec![]),
            NamedArray::u32(arrays::DIST_KIND, vec![0], vec![]),
            NamedArray::f32(arrays::DIST_MATERIAL_LEN, vec![0, 4], vec![]),
            NamedArray::u32(arrays::PATCH_MATERIAL, vec![N], vec![0; 4]),
        ]
    }

    fn good_arrays() -> Vec<NamedArray> {
        fan_arrays(
            vec![0, 2, 3, 3, 6],
            vec![1, 3, 0, 0, 1, 2],
            vec![0.25, 0.125, 0.5, 0.0625, 0.03125, 0.75],
        )
    }

    fn write_good(out: &Path) -> WriteReport {
        write_bundle(out, manifest(6), good_arrays()).unwrap()
    }

    fn entries(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    fn open_err(dir: &Path) -> String {
        match Bundle::open(dir) {
            Ok(_) => panic!("{} opened but should not have", dir.display()),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn round_trip_compares_every_array() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("nested").join("fan");
        let report = write_good(&out);
        assert_eq!(
            report.files,
            translux_proto::bundle::REQUIRED_ARRAYS.len() + 1
        );
        // No temporary folder left next to it.
        assert_eq!(entries(out.parent().unwrap()), vec!["fan".to_string()]);

        let b = Bundle::open(&out).unwrap();
        assert_eq!(b.total_bytes(), report.bytes);
        let disk: u64 = fs::read_dir(&out)
            .unwrap()
            .map(|e| e.unwrap().metadata().unwrap().len())
            .sum();
        assert_eq!(disk, report.bytes);
        let mut expected = manifest(6);
        expected.arrays = b.manifest().arrays.clone();
        assert_eq!(b.manifest(), &expected);
        for a in good_arrays() {
            let entry = &b.manifest().arrays[a.name];
            assert_eq!(entry.shape, a.shape, "{}", a.name);
            assert_eq!(entry.dtype, a.data.dtype(), "{}", a.name);
            assert_eq!(entry.xxh3, checksum(a.data.bytes()), "{}", a.name);
            match &a.data {
                ArrayData::F16(_) => {}
                ArrayData::F32(v) => assert_eq!(b.f32s(a.name), &v[..], "{}", a.name),
                ArrayData::U32(v) => assert_eq!(b.u32s(a.name), &v[..], "{}", a.name),
                ArrayData::U64(v) => assert_eq!(b.u64s(a.name), &v[..], "{}", a.name),
            }
        }
        assert_eq!(b.triangle_vertices()[1], [0, 3, 2]);
        assert_eq!(b.patch_emission()[1], [1.5, 2.5, 3.5]);
        assert_eq!(b.patch_corners()[0][1], [0.0, 0.0, 1.0]);
        assert_eq!(b.occluder_triangles().len(), 2);
        let f = b.form_factors();
        assert_eq!((f.n_rows(), f.nnz()), (4, 6));
        assert_eq!(f.row(2), (&[][..], &[][..]));
        assert_eq!(f.get(3, 2), 0.75);
        assert_eq!(f.get(0, 3), 0.125);
    }

    #[test]
    fn truncated_file_is_named() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("b");
        write_good(&out);
        let path = out.join("vertex_normal.f32");
        let f = fs::OpenOptions::new().write(true).open(&path).unwrap();
        f.set_len(56).unwrap();
        drop(f);
        assert_eq!(
            open_err(&out),
            "vertex_normal.f32 is truncated: 56 bytes, manifest says 60"
        );
        // Lengths are checked without checksums too.
        let e = Bundle::open_with(
            &out,
            OpenOptions {
                verify_checksums: false,
            },
        )
        .unwrap_err();
        assert!(e.to_string().contains("truncated"), "{e}");
    }

    #[test]
    fn flipped_bit_is_corrupt_and_checksums_can_be_skipped() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("b");
        write_good(&out);
        let path = out.join("ff_val.f32");
        let mut bytes = fs::read(&path).unwrap();
        // Lowest mantissa bit of value 2 (0.5 -> 0.50000006): still finite, CSR still valid.
        bytes[8] ^= 1;
        fs::write(&path, &bytes).unwrap();
        let e = open_err(&out);
        assert!(e.starts_with("ff_val.f32 is corrupt: checksum "), "{e}");
        assert!(e.contains("!= manifest "), "{e}");
        let b = Bundle::open_with(
            &out,
            OpenOptions {
                verify_checksums: false,
            },
        )
        .unwrap();
        assert_eq!(
            b.form_factors().get(1, 0),
            f32::from_bits(0.5f32.to_bits() ^ 1)
        );
    }

    #[test]
    fn deleted_file_is_missing() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("b");
        write_good(&out);
        fs::remove_file(out.join("ff_col.u32")).unwrap();
        assert_eq!(open_err(&out), "ff_col.u32 is missing");
        fs::remove_file(out.join(MANIFEST_FILE)).unwrap();
        assert_eq!(open_err(&out), "manifest.json is missing");
    }

    #[test]
    fn manifest_version_and_garbage_are_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("b");
        write_good(&out);
        let path = out.join(MANIFEST_FILE);
        let mut json: serde_json::Value =
            serde_json::from_str(&fs::read_to_string(&path).unwrap()).unwrap();
        json["version"] = 99.into();
        fs::write(&path, serde_json::to_string_pretty(&json).unwrap()).unwrap();
        assert_eq!(
            open_err(&out),
            format!(
                "manifest.json: bundle version 99 is not supported (this build reads versions 4 to \
                 {FORMAT_VERSION}); rebuild the bundle with this build's translux-precompute"
            )
        );
        fs::write(&path, "{\"format\": \"translux-bundle\",\n  oops").unwrap();
        let e = open_err(&out);
        assert!(e.starts_with("manifest.json: line 2 column 3: "), "{e}");
    }

    #[test]
    fn out_of_range_column_names_ff_col() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("b");
        let arrays = fan_arrays(vec![0, 1, 1, 1, 1], vec![4], vec![0.5]);
        write_bundle(&out, manifest(1), arrays).unwrap();
        let e = open_err(&out);
        assert_eq!(
            e,
            "ff_col.u32: F is not a valid CSR matrix: row 0: column 4 is out of range (columns: 4)"
        );
    }

    /// The states a writer killed with SIGKILL leaves, step by step (the test makes them):
    /// the next writer, or a server starting up, puts the old bundle back where the new one
    /// never arrived and removes every other leftover; a running writer's are kept.
    #[test]
    fn leftovers_of_a_killed_writer_are_settled_at_each_step() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("b");
        write_good(&out);
        let before = fs::read(out.join(MANIFEST_FILE)).unwrap();
        // A pid above Linux's largest (2²²): no such process.
        let dead = 4_000_000_000u32;
        let partial = |name: &str| {
            let d = tmp.path().join(name);
            fs::create_dir(&d).unwrap();
            fs::write(d.join("ff_val.f32"), b"half").unwrap();
        };

        // Killed while writing the new files: the temporary folder goes.
        partial(&format!(".b.tmp-{dead}-1-0"));
        let s = settle_leftovers(&out, Writers::Gone).unwrap();
        assert_eq!(s.removed, vec![format!(".b.tmp-{dead}-1-0")]);
        assert_eq!(entries(tmp.path()), vec!["b".to_string()]);

        // Killed after moving the old bundle aside: it comes back.
        partial(&format!(".b.tmp-{dead}-2-0"));
        fs::rename(&out, tmp.path().join(format!(".b.old-{dead}-2-1"))).unwrap();
        let s = settle_leftovers(&out, Writers::Gone).unwrap();
        assert_eq!(s.restored, Some(format!(".b.old-{dead}-2-1")));
        assert_eq!(s.removed, vec![format!(".b.tmp-{dead}-2-0")]);
        assert_eq!(fs::read(out.join(MANIFEST_FILE)).unwrap(), before);
        Bundle::open(&out).unwrap();

        // Killed after the new bundle is in place: the old one goes.
        fs::create_dir(tmp.path().join(format!(".b.old-{dead}-3-0"))).unwrap();
        settle_leftovers(&out, Writers::Gone).unwrap();
        assert_eq!(entries(tmp.path()), vec!["b".to_string()]);

        // A running writer's folders (this process's) are left alone; the next write
        // removes a dead one's.
        let mine = format!(".b.tmp-{}-4-0", std::process::id());
        partial(&mine);
        partial(&format!(".b.tmp-{dead}-4-1"));
        write_good(&out);
        assert_eq!(entries(tmp.path()), vec![mine, "b".to_string()]);
        settle_leftovers(&out, Writers::All).unwrap();
        assert_eq!(entries(tmp.path()), vec!["b".to_string()]);
    }

    #[test]
    fn writer_errors_leave_nothing_behind() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("b");

        // Data length disagrees with the shape.
        let mut arrays = good_arrays();
        arrays[2].shape = vec![5];
        let e = write_bundle(&out, manifest(6), arrays).unwrap_err();
        assert_eq!(
            e.to_string(),
            "array patch_area: 4 elements, but shape [5] holds 5"
        );
        assert!(entries(tmp.path()).is_empty(), "{:?}", entries(tmp.path()));

        // A failure after the arrays are on disk (a NaN in the manifest cannot round-trip).
        let mut m = manifest(6);
        m.unit_mm = f64::NAN;
        let e = write_bundle(&out, m, good_arrays()).unwrap_err();
        assert!(
            e.to_string()
                .starts_with("manifest.json: does not read back"),
            "{e}"
        );
        assert!(entries(tmp.path()).is_empty(), "{:?}", entries(tmp.path()));

        // The same failure while replacing: the old bundle stays as it was.
        write_good(&out);
        let before = fs::read(out.join(MANIFEST_FILE)).unwrap();
        let mut m = manifest(6);
        m.form_factors.dropped_energy = f64::INFINITY;
        assert!(write_bundle(&out, m, good_arrays()).is_err());
        assert_eq!(entries(tmp.path()), vec!["b".to_string()]);
        assert_eq!(fs::read(out.join(MANIFEST_FILE)).unwrap(), before);
        Bundle::open(&out).unwrap();

        // Wrong dtype for a known array, and duplicate names.
        let mut arrays = good_arrays();
        arrays[3] = NamedArray::f32(arrays::PATCH_OBJECT, vec![N], vec![0.0; 4]);
        let e = write_bundle(&tmp.path().join("c"), manifest(6), arrays).unwrap_err();
        assert_eq!(
            e.to_string(),
            "array patch_object: element type f32, the format requires u32"
        );
        let mut arrays = good_arrays();
        arrays.push(NamedArray::f32(arrays::FF_VAL, vec![0], vec![]));
        assert!(write_bundle(&tmp.path().join("c"), manifest(6), arrays).is_err());
        assert_eq!(entries(tmp.path()), vec!["b".to_string()]);
    }

    #[test]
    fn rewriting_replaces_an_existing_bundle() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("b");
        write_good(&out);
        let old = Bundle::open(&out).unwrap();
        // A stray file in the old bundle must not survive the replacement.
        fs::write(out.join("stray.txt"), "x").unwrap();

        let mut m = manifest(1);
        m.name = "second".into();
        write_bundle(&out, m, fan_arrays(vec![0, 0, 0, 0, 1], vec![2], vec![0.5])).unwrap();
        assert_eq!(entries(tmp.path()), vec!["b".to_string()]);
        assert!(!out.join("stray.txt").exists());
        let b = Bundle::open(&out).unwrap();
        assert_eq!(b.manifest().name, "second");
        assert_eq!(b.form_factors().nnz(), 1);
        assert_eq!(b.form_factors().get(3, 2), 0.5);
        // A bundle mapped before the replacement still reads its own (old) data.
        assert_eq!(old.manifest().name, "fan");
        assert_eq!(old.form_factors().get(3, 2), 0.75);
        assert_eq!(old.f32s(arrays::FF_VAL).len(), 6);
    }

    #[test]
    fn refuses_to_replace_what_is_not_a_bundle() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("docs");
        fs::create_dir(&out).unwrap();
        fs::write(out.join("thesis.tex"), "precious").unwrap();
        let e = write_bundle(&out, manifest(6), good_arrays()).unwrap_err();
        assert!(e.to_string().contains("is not a bundle"), "{e}");
        assert_eq!(
            fs::read_to_string(out.join("thesis.tex")).unwrap(),
            "precious"
        );
        assert_eq!(entries(tmp.path()), vec!["docs".to_string()]);
        // An empty folder is fine.
        let empty = tmp.path().join("empty");
        fs::create_dir(&empty).unwrap();
        write_bundle(&empty, manifest(6), good_arrays()).unwrap();
        Bundle::open(&empty).unwrap();
    }
}
