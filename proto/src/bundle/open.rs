//! The verifying, memory-mapping loader: checks the manifest against the format, maps every
//! array (checking its length and checksum), validates the matrices and the tree once, and
//! hands out views.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::manifest::*;
use super::views::*;

/// The array files every bundle of [`FORMAT_VERSION`] holds, with their element types.
/// A manifest may list further arrays; the loader verifies and maps those too.
pub const REQUIRED_ARRAYS: &[(&str, DType)] = &[
    (arrays::PATCH_CORNERS, DType::F32),
    (arrays::PATCH_NORMAL, DType::F32),
    (arrays::PATCH_AREA, DType::F32),
    (arrays::PATCH_OBJECT, DType::U32),
    (arrays::PATCH_ALBEDO, DType::F32),
    (arrays::PATCH_EMISSION, DType::F32),
    (arrays::VERTEX_POSITION, DType::F32),
    (arrays::VERTEX_NORMAL, DType::F32),
    (arrays::TRIANGLE_VERTEX, DType::U32),
    (arrays::OCCLUDER_TRI, DType::F32),
    (arrays::FF_ROW_PTR, DType::U64),
    (arrays::FF_COL, DType::U32),
    (arrays::FF_VAL, DType::F32),
    (arrays::S_ROW_PTR, DType::U64),
    (arrays::S_COL, DType::U32),
    (arrays::S_VAL, DType::F32),
    (arrays::DIST_ROW_PTR, DType::U64),
    (arrays::DIST_COL, DType::U32),
    (arrays::DIST_VAL, DType::F32),
    (arrays::DIST_KIND, DType::U32),
    (arrays::DIST_MATERIAL_LEN, DType::F32),
    (arrays::PATCH_MATERIAL, DType::U32),
];

/// What the first dimension of a required array counts.
#[derive(Debug, Clone, Copy)]
enum Rows {
    /// `patch_count`
    Patches,
    /// `patch_count + 1`
    PatchesPlusOne,
    /// F's rows + 1: `patch_count + 1`, or with receiver nodes `patch_count +
    /// hierarchy.nodes + 1`
    FfRowsPlusOne,
    /// `vertex_count`
    Vertices,
    /// `occluder_count`
    Occluders,
    /// `form_factors.nnz`
    Nnz,
    /// `subsurface.nnz`
    SNnz,
    /// `subsurface.distance_nnz`
    DistNnz,
}

/// The documented shape of each required array: (name, rows, trailing dimensions).
const SHAPES: &[(&str, Rows, &[u64])] = &[
    (arrays::PATCH_CORNERS, Rows::Patches, &[3, 3]),
    (arrays::PATCH_NORMAL, Rows::Patches, &[3]),
    (arrays::PATCH_AREA, Rows::Patches, &[]),
    (arrays::PATCH_OBJECT, Rows::Patches, &[]),
    (arrays::PATCH_ALBEDO, Rows::Patches, &[3]),
    (arrays::PATCH_EMISSION, Rows::Patches, &[3]),
    (arrays::VERTEX_POSITION, Rows::Vertices, &[3]),
    (arrays::VERTEX_NORMAL, Rows::Vertices, &[3]),
    (arrays::TRIANGLE_VERTEX, Rows::Patches, &[3]),
    (arrays::OCCLUDER_TRI, Rows::Occluders, &[3, 3]),
    (arrays::FF_ROW_PTR, Rows::FfRowsPlusOne, &[]),
    (arrays::FF_COL, Rows::Nnz, &[]),
    (arrays::FF_VAL, Rows::Nnz, &[]),
    (arrays::S_ROW_PTR, Rows::PatchesPlusOne, &[]),
    (arrays::S_COL, Rows::SNnz, &[]),
    (arrays::S_VAL, Rows::SNnz, &[3]),
    (arrays::DIST_ROW_PTR, Rows::PatchesPlusOne, &[]),
    (arrays::DIST_COL, Rows::DistNnz, &[]),
    (arrays::DIST_VAL, Rows::DistNnz, &[]),
    (arrays::DIST_KIND, Rows::DistNnz, &[]),
    (arrays::DIST_MATERIAL_LEN, Rows::DistNnz, &[4]),
    (arrays::PATCH_MATERIAL, Rows::Patches, &[]),
];

/// The file name of array `name` with element type `dtype` (`ff_col.u32`).
pub fn array_file_name(name: &str, dtype: DType) -> String {
    format!("{name}.{}", dtype.name())
}

/// Whether `name` may name an array: non-empty, lower-case ASCII letters, digits and `_`
/// only (so that `NAME.DTYPE` is a plain file name inside the bundle folder, never a path).
pub fn is_valid_array_name(name: &str) -> bool {
    !name.is_empty()
        && name
            .bytes()
            .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_')
}

/// Why a bundle could not be opened. Every message starts with or names the file concerned.
#[derive(Debug, thiserror::Error)]
pub enum BundleError {
    /// A file (or the bundle folder itself) does not exist.
    #[error("{file} is missing")]
    Missing { file: String },
    /// A required array is not listed in the manifest.
    #[error("{file} is missing from {MANIFEST_FILE}")]
    NotListed { file: String },
    /// Reading or mapping a file failed.
    #[error("{file}: {error}")]
    Io { file: String, error: std::io::Error },
    /// `manifest.json` is not JSON, or not a [`Manifest`].
    #[error("{MANIFEST_FILE}: line {line} column {column}: {what}",
        line = .0.line, column = .0.column, what = json_cause(.0))]
    Manifest(crate::JsonError),
    /// The manifest's `format` is not [`FORMAT`].
    #[error("{MANIFEST_FILE}: format is {found:?}, expected {FORMAT:?}")]
    Format { found: String },
    /// The manifest's `version` is not one this build reads.
    #[error(
        "{MANIFEST_FILE}: bundle version {found} is not supported (this build reads versions \
         {OLDEST_READABLE_VERSION} to {FORMAT_VERSION}); rebuild the bundle with this build's \
         translux-precompute"
    )]
    Version { found: u32 },
    /// A file is shorter than the manifest says.
    #[error("{file} is truncated: {got} bytes, manifest says {expected}")]
    Truncated {
        file: String,
        got: u64,
        expected: u64,
    },
    /// A file is longer than the manifest says.
    #[error("{file} is too long: {got} bytes, manifest says {expected}")]
    TooLong {
        file: String,
        got: u64,
        expected: u64,
    },
    /// A file's XXH3-64 differs from the manifest's.
    #[error("{file} is corrupt: checksum {got} != manifest {expected}")]
    Corrupt {
        file: String,
        got: String,
        expected: String,
    },
    /// A manifest entry or a file's content breaks a rule of the format.
    #[error("{file}: {reason}")]
    Invalid { file: String, reason: String },
    /// The form-factor arrays are not a valid CSR matrix; `file` is the array at fault.
    #[error("{file}: F is not a valid CSR matrix: {error}")]
    Csr {
        file: String,
        error: crate::csr::CsrError,
    },
}

fn json_cause(e: &crate::JsonError) -> String {
    if e.path.is_empty() || e.path == "." {
        e.message.clone()
    } else {
        format!("{}: {}", e.path, e.message)
    }
}

impl BundleError {
    /// The file the error is about (`manifest.json` for manifest errors).
    pub fn file(&self) -> &str {
        match self {
            BundleError::Missing { file }
            | BundleError::NotListed { file }
            | BundleError::Io { file, .. }
            | BundleError::Truncated { file, .. }
            | BundleError::TooLong { file, .. }
            | BundleError::Corrupt { file, .. }
            | BundleError::Invalid { file, .. }
            | BundleError::Csr { file, .. } => file,
            BundleError::Manifest(_) | BundleError::Format { .. } | BundleError::Version { .. } => {
                MANIFEST_FILE
            }
        }
    }
}

/// Each optional array `(name, dtype, shape)` is listed in the manifest with that dtype and
/// shape; `legend` names the letters the message's shapes use.
fn check_listed(
    manifest: &Manifest,
    expected: &[(&str, DType, Vec<u64>)],
    legend: &str,
) -> Result<(), BundleError> {
    for (name, dtype, shape) in expected {
        let file = array_file_name(name, *dtype);
        let entry = manifest
            .arrays
            .get(*name)
            .ok_or_else(|| BundleError::NotListed { file: file.clone() })?;
        if entry.dtype != *dtype || &entry.shape != shape {
            return Err(invalid(
                &file,
                format!(
                    "manifest lists {} {:?}, expected {} {shape:?} ({legend})",
                    entry.dtype.name(),
                    entry.shape,
                    dtype.name()
                ),
            ));
        }
    }
    Ok(())
}

fn invalid(file: impl Into<String>, reason: impl Into<String>) -> BundleError {
    BundleError::Invalid {
        file: file.into(),
        reason: reason.into(),
    }
}

/// How [`Bundle::open_with`] verifies. Lengths, shapes, counts and the CSR invariants are
/// always checked; only the checksum pass (one read of every byte) is optional.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OpenOptions {
    /// Recompute every array's XXH3-64 and compare it with the manifest (default: true).
    pub verify_checksums: bool,
}

impl Default for OpenOptions {
    fn default() -> Self {
        Self {
            verify_checksums: true,
        }
    }
}

/// Array files up to this size are read into memory when a bundle opens instead of being
/// mapped: a private copy cannot change under the server, so truncating or rewriting such a
/// file in place cannot bring the process down with `SIGBUS`. Larger arrays (F, S, T of a
/// real scene: gigabytes) stay memory-mapped; see `map_file` for what that asks of
/// operators.
pub const COPY_ON_OPEN_BYTES: u64 = 16 << 20;

/// One array file's bytes: mapped, or (small files) a private copy. An empty file has
/// neither.
#[derive(Debug)]
enum ArrayBytes {
    Empty,
    Mapped(memmap2::Mmap),
    /// `u64` words so the bytes are 8-aligned for every dtype; the length in bytes.
    Copied(Vec<u64>, usize),
}

#[derive(Debug)]
struct MappedArray {
    dtype: DType,
    data: ArrayBytes,
}

impl MappedArray {
    fn bytes(&self) -> &[u8] {
        match &self.data {
            ArrayBytes::Empty => &[],
            ArrayBytes::Mapped(m) => m,
            ArrayBytes::Copied(words, len) => &bytemuck::cast_slice(words)[..*len],
        }
    }

    /// Whether the bytes are a private copy (not mapped).
    fn is_copied(&self) -> bool {
        matches!(self.data, ArrayBytes::Copied(..))
    }
}

/// `path` must be a regular file (after symlinks) before it is opened: opening a FIFO for
/// reading blocks until some writer appears, which would hang the loader (and every bundle
/// queued behind it); a device or socket is no bundle file either.
fn check_regular(path: &Path, name: &str) -> Result<(), BundleError> {
    match std::fs::metadata(path) {
        Ok(m) if m.is_file() => Ok(()),
        Ok(_) => Err(invalid(name, "is not a regular file")),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(BundleError::Missing {
            file: name.to_string(),
        }),
        Err(error) => Err(BundleError::Io {
            file: name.to_string(),
            error,
        }),
    }
}

/// Maps `file` read-only.
///
/// # Safety
///
/// `memmap2::Mmap::map` is unsafe because the slice it yields changes (or the process gets
/// `SIGBUS`) if another process modifies or truncates the file while it is mapped. Bundles
/// are immutable once they are in place: the writer fills a temporary folder and renames it
/// into place, and replaces a bundle by renaming the old folder aside before deleting it, so
/// a mapped file is never written to. Editing a bundle's files by hand while a server maps
/// them would break this assumption: operators must never truncate, rewrite or `cp` over
/// a served bundle's files in place (replace the folder by a rename; deleting a file or
/// the folder is safe, its pages stay until unmapped). Only arrays over
/// [`COPY_ON_OPEN_BYTES`] are mapped; smaller ones are private copies.
#[expect(
    unsafe_code,
    reason = "memory-mapping a file is unsafe; bundles are immutable once renamed into place"
)]
fn map_file(file: &std::fs::File) -> std::io::Result<memmap2::Mmap> {
    // SAFETY: `file` was opened read-only and the mapping is read-only. Bundle files are never
    // modified after the writer renames the bundle folder into place (write-to-temp-then-rename,
    // replacement by rename-aside-then-delete), so the mapped bytes do not change underneath
    // the slices handed out; only a concurrent writer bypassing that protocol could violate it.
    unsafe { memmap2::Mmap::map(file) }
}

/// A bundle folder, verified and memory-mapped.
///
/// Opening it checks the manifest and every array (see [`Bundle::open`]); afterwards the
/// accessors hand out zero-copy slices of the mapped files and never fail. It is `Send` and
/// `Sync`: share it behind an `Arc`.
#[derive(Debug)]
pub struct Bundle {
    dir: PathBuf,
    manifest: Manifest,
    manifest_bytes: u64,
    arrays: BTreeMap<String, MappedArray>,
    /// patch_count: the rows of F before any node rows.
    n_patches: usize,
    /// Cluster nodes of a hierarchical F (0 for a dense one): F has N + M columns.
    n_nodes: usize,
    /// F's columns in 16 bits ([`Bundle::form_factor_cols`]), made on first use.
    ff_narrow: std::sync::OnceLock<crate::csr::NarrowCols>,
}

/// The counts of a manifest, as `usize`.
struct Counts {
    patches: u64,
    /// Rows of F: the patches, then the receiving nodes of a two-sided F.
    ff_rows: u64,
    vertices: u64,
    occluders: u64,
    nnz: u64,
    s_nnz: u64,
    dist_nnz: u64,
}

impl Counts {
    fn rows(&self, rows: Rows) -> Result<(u64, String), BundleError> {
        Ok(match rows {
            Rows::Patches => (self.patches, "N = patch_count".into()),
            Rows::PatchesPlusOne => (
                self.patches
                    .checked_add(1)
                    .ok_or_else(|| invalid(MANIFEST_FILE, "patch_count is too large"))?,
                "N + 1 with N = patch_count".into(),
            ),
            Rows::FfRowsPlusOne => (
                self.ff_rows
                    .checked_add(1)
                    .ok_or_else(|| invalid(MANIFEST_FILE, "patch_count is too large"))?,
                "F's rows + 1: N + 1, or N + M + 1 with hierarchy.receiver_nodes".into(),
            ),
            Rows::Vertices => (self.vertices, "V = vertex_count".into()),
            Rows::Occluders => (self.occluders, "M = occluder_count".into()),
            Rows::Nnz => (self.nnz, "nnz = form_factors.nnz".into()),
            Rows::SNnz => (self.s_nnz, "nnz_s = subsurface.nnz".into()),
            Rows::DistNnz => (self.dist_nnz, "nnz_d = subsurface.distance_nnz".into()),
        })
    }
}

fn to_usize(value: u64, file: &str, what: &str) -> Result<usize, BundleError> {
    usize::try_from(value).map_err(|_| {
        invalid(
            file,
            format!("{what} = {value} does not fit this machine's memory"),
        )
    })
}

/// Checks a manifest entry against its own name and against itself (file name, byte count =
/// elements × dtype size); returns the byte count.
fn check_entry(name: &str, entry: &ArrayEntry) -> Result<u64, BundleError> {
    let expected_file = array_file_name(name, entry.dtype);
    if !is_valid_array_name(name) {
        return Err(invalid(
            MANIFEST_FILE,
            format!("array name {name:?} is not lower-case letters, digits and '_'"),
        ));
    }
    if entry.file != expected_file {
        return Err(invalid(
            MANIFEST_FILE,
            format!(
                "array {name} is stored as {:?}, expected {expected_file:?}",
                entry.file
            ),
        ));
    }
    let bytes = entry
        .shape
        .iter()
        .try_fold(entry.dtype.size() as u64, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| {
            invalid(
                &expected_file,
                format!("shape {:?} is too large", entry.shape),
            )
        })?;
    if bytes != entry.bytes {
        return Err(invalid(
            MANIFEST_FILE,
            format!(
                "{expected_file}: manifest lists {} bytes but shape {:?} of {} holds {bytes}",
                entry.bytes,
                entry.shape,
                entry.dtype.name()
            ),
        ));
    }
    Ok(bytes)
}

/// Opens, length-checks, maps and (optionally) checksums one array file.
fn map_array(
    dir: &Path,
    entry: &ArrayEntry,
    bytes: u64,
    verify_checksum: bool,
) -> Result<MappedArray, BundleError> {
    let file_name = entry.file.as_str();
    let io = |error: std::io::Error| BundleError::Io {
        file: file_name.to_string(),
        error,
    };
    let path = dir.join(file_name);
    check_regular(&path, file_name)?;
    let file = match std::fs::File::open(&path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(BundleError::Missing {
                file: file_name.to_string(),
            });
        }
        Err(e) => return Err(io(e)),
    };
    let meta = file.metadata().map_err(io)?;
    if !meta.is_file() {
        return Err(invalid(file_name, "is not a regular file"));
    }
    let got = meta.len();
    if got < bytes {
        return Err(BundleError::Truncated {
            file: file_name.to_string(),
            got,
            expected: bytes,
        });
    }
    if got > bytes {
        return Err(BundleError::TooLong {
            file: file_name.to_string(),
            got,
            expected: bytes,
        });
    }
    let data = if got == 0 {
        ArrayBytes::Empty
    } else if got <= COPY_ON_OPEN_BYTES {
        use std::io::Read;
        let len = got as usize;
        let mut words = vec![0u64; len.div_ceil(8)];
        let buf: &mut [u8] = bytemuck::cast_slice_mut(&mut words);
        let mut reader = &file;
        // `read_exact` fails if the file shrank since the length check.
        reader.read_exact(&mut buf[..len]).map_err(|e| {
            if e.kind() == std::io::ErrorKind::UnexpectedEof {
                BundleError::Truncated {
                    file: file_name.to_string(),
                    got: 0,
                    expected: bytes,
                }
            } else {
                io(e)
            }
        })?;
        ArrayBytes::Copied(words, len)
    } else {
        let map = map_file(&file).map_err(io)?;
        if map.len() as u64 != bytes {
            // The file changed between the length check and the mapping.
            return Err(BundleError::Truncated {
                file: file_name.to_string(),
                got: map.len() as u64,
                expected: bytes,
            });
        }
        ArrayBytes::Mapped(map)
    };
    let mapped = MappedArray {
        dtype: entry.dtype,
        data,
    };
    if verify_checksum {
        let sum = checksum(mapped.bytes());
        if sum != entry.xxh3 {
            return Err(BundleError::Corrupt {
                file: file_name.to_string(),
                got: sum,
                expected: entry.xxh3.clone(),
            });
        }
    }
    Ok(mapped)
}

/// Which file a CSR violation is about, for the matrix stored as `[row_ptr, col, val]`.
fn csr_file(error: &crate::csr::CsrError, names: [&str; 3]) -> String {
    use crate::csr::CsrError as E;
    let [rp, col, val] = names;
    match error {
        E::RowPtrLength { .. } | E::RowPtrStart(_) | E::RowPtrDecreasing { .. } => {
            array_file_name(rp, DType::U64)
        }
        E::NnzMismatch { .. } => format!(
            "{}/{}/{}",
            array_file_name(rp, DType::U64),
            array_file_name(col, DType::U32),
            array_file_name(val, DType::F32)
        ),
        E::ColumnOutOfRange { .. } | E::ColumnsUnsorted { .. } => array_file_name(col, DType::U32),
        E::NonFinite { .. } => array_file_name(val, DType::F32),
    }
}

const FF_NAMES: [&str; 3] = [arrays::FF_ROW_PTR, arrays::FF_COL, arrays::FF_VAL];
const S_NAMES: [&str; 3] = [arrays::S_ROW_PTR, arrays::S_COL, arrays::S_VAL];
const DIST_NAMES: [&str; 3] = [arrays::DIST_ROW_PTR, arrays::DIST_COL, arrays::DIST_VAL];

impl Bundle {
    /// Opens the bundle in `dir` with full verification, checksums included
    /// ([`OpenOptions::default`]).
    ///
    /// In: a bundle folder. Out: the mapped bundle, or the first problem found, naming its
    /// file. Checked: the manifest parses, its format and version are this build's; every
    /// required array (see [`REQUIRED_ARRAYS`]) is listed with its dtype and the shape the
    /// counts imply, and every listed file exists with exactly the listed length and checksum;
    /// F is a valid `N × N` CSR matrix; `triangle_vertex < vertex_count`; the objects' patch
    /// ranges are contiguous, in order and cover `0..N`, and `patch_object` agrees with them;
    /// areas are finite and positive; the other geometry arrays are finite.
    pub fn open(dir: &Path) -> Result<Bundle, BundleError> {
        Self::open_with(dir, OpenOptions::default())
    }

    /// [`Bundle::open`] with options (skipping the checksum pass saves one read of every
    /// byte; every other check still runs).
    pub fn open_with(dir: &Path, opts: OpenOptions) -> Result<Bundle, BundleError> {
        if !dir.is_dir() {
            return Err(BundleError::Missing {
                file: dir.display().to_string(),
            });
        }
        check_regular(&dir.join(MANIFEST_FILE), MANIFEST_FILE)?;
        let text = match std::fs::read_to_string(dir.join(MANIFEST_FILE)) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(BundleError::Missing {
                    file: MANIFEST_FILE.into(),
                });
            }
            Err(error) => {
                return Err(BundleError::Io {
                    file: MANIFEST_FILE.into(),
                    error,
                });
            }
        };
        let manifest: Manifest = crate::parse_json(&text).map_err(BundleError::Manifest)?;
        if manifest.format != FORMAT {
            return Err(BundleError::Format {
                found: manifest.format,
            });
        }
        if !(OLDEST_READABLE_VERSION..=FORMAT_VERSION).contains(&manifest.version) {
            return Err(BundleError::Version {
                found: manifest.version,
            });
        }
        let ff_rows = match &manifest.hierarchy {
            Some(h) if h.receiver_nodes => manifest.patch_count.saturating_add(h.nodes),
            _ => manifest.patch_count,
        };
        let counts = Counts {
            patches: manifest.patch_count,
            ff_rows,
            vertices: manifest.vertex_count,
            occluders: manifest.occluder_count,
            nnz: manifest.form_factors.nnz,
            s_nnz: manifest.subsurface.nnz,
            dist_nnz: manifest.subsurface.distance_nnz,
        };
        let n_patches = to_usize(counts.patches, MANIFEST_FILE, "patch_count")?;

        // The transfer matrix: both arrays, with these shapes, when the manifest says so.
        if manifest.transfer.is_some() {
            let n = counts.patches;
            check_listed(
                &manifest,
                &[
                    (arrays::TRANSFER, DType::F16, vec![n, n, 3]),
                    (arrays::TRANSFER_SCALE, DType::F32, vec![n, 3]),
                ],
                "N = patch_count",
            )?;
        }

        // The environment visibility: listed with its shape when the manifest says so.
        if let Some(env) = &manifest.environment {
            let file = array_file_name(arrays::ENV_VISIBILITY, DType::F16);
            let shape = vec![counts.patches, u64::from(env.rows), u64::from(env.cols)];
            let entry = manifest
                .arrays
                .get(arrays::ENV_VISIBILITY)
                .ok_or_else(|| BundleError::NotListed { file: file.clone() })?;
            if env.rows == 0 || env.cols == 0 || entry.dtype != DType::F16 || entry.shape != shape {
                return Err(invalid(
                    &file,
                    format!(
                        "manifest lists {} {:?}, expected f16 {shape:?} (N = patch_count, \
                         environment.rows and .cols >= 1)",
                        entry.dtype.name(),
                        entry.shape,
                    ),
                ));
            }
        }

        // The walks of simulated objects: four arrays, with these shapes, when listed.
        if manifest.subsurface.walks > 0 {
            let (n1, w) = (counts.patches + 1, manifest.subsurface.walks);
            check_listed(
                &manifest,
                &[
                    (arrays::SIM_ROW_PTR, DType::U64, vec![n1]),
                    (arrays::SIM_COL, DType::U32, vec![w]),
                    (arrays::SIM_BIN, DType::U32, vec![w]),
                    (arrays::SIM_WEIGHT, DType::F32, vec![w, 3]),
                ],
                "N = patch_count, W = subsurface.walks",
            )?;
            if manifest.version >= SIM_NORMAL_SINCE {
                check_listed(
                    &manifest,
                    &[(arrays::SIM_WEIGHT_NORMAL, DType::F32, vec![w, 3])],
                    "W = subsurface.walks",
                )?;
            }
            if manifest.version >= SIM_LAMP_SINCE {
                check_listed(
                    &manifest,
                    &[(arrays::SIM_WEIGHT_LAMP, DType::U32, vec![w, 3])],
                    "W = subsurface.walks",
                )?;
            }
        }

        // Links read at two distances: their spreads, one per stored distance.
        if manifest.subsurface.link_near.is_some() {
            check_listed(
                &manifest,
                &[(
                    arrays::DIST_SPREAD,
                    DType::F32,
                    vec![manifest.subsurface.distance_nnz],
                )],
                "subsurface.distance_nnz",
            )?;
        }

        // The cluster tree: both arrays, with these shapes, when the manifest says so.
        let n_nodes = match &manifest.hierarchy {
            Some(h) => {
                let n = counts.patches;
                check_listed(
                    &manifest,
                    &[
                        (arrays::TREE_PERM, DType::U32, vec![n]),
                        (arrays::TREE_RANGE, DType::U32, vec![h.nodes, 2]),
                    ],
                    "N = patch_count, M = hierarchy.nodes",
                )?;
                to_usize(h.nodes, MANIFEST_FILE, "hierarchy.nodes")?
            }
            None => 0,
        };
        if n_patches
            .checked_add(n_nodes)
            .is_none_or(|c| c > u32::MAX as usize)
        {
            return Err(invalid(
                MANIFEST_FILE,
                "patch_count + hierarchy.nodes does not fit a u32 column index",
            ));
        }

        // The required arrays: listed, with the right dtype and shape.
        for &(name, dtype) in REQUIRED_ARRAYS {
            let file = array_file_name(name, dtype);
            let entry = manifest
                .arrays
                .get(name)
                .ok_or_else(|| BundleError::NotListed { file: file.clone() })?;
            if entry.dtype != dtype {
                return Err(invalid(
                    &file,
                    format!(
                        "manifest lists dtype {}, expected {}",
                        entry.dtype.name(),
                        dtype.name()
                    ),
                ));
            }
            let Some(&(_, rows, tail)) = SHAPES.iter().find(|(n, _, _)| *n == name) else {
                return Err(invalid(&file, "no documented shape (a bug in this loader)"));
            };
            let (n, label) = counts.rows(rows)?;
            let expected: Vec<u64> = std::iter::once(n).chain(tail.iter().copied()).collect();
            if entry.shape != expected {
                return Err(invalid(
                    &file,
                    format!(
                        "shape {:?} does not match the manifest's counts: expected {expected:?} ({label} = {n})",
                        entry.shape
                    ),
                ));
            }
        }

        // Every listed array (required or not): consistent entry, file on disk, checksum.
        let mut mapped = BTreeMap::new();
        for (name, entry) in &manifest.arrays {
            let bytes = check_entry(name, entry)?;
            let array = map_array(dir, entry, bytes, opts.verify_checksums)?;
            mapped.insert(name.clone(), array);
        }

        let bundle = Bundle {
            dir: dir.to_path_buf(),
            manifest,
            manifest_bytes: text.len() as u64,
            arrays: mapped,
            n_patches,
            n_nodes,
            ff_narrow: Default::default(),
        };
        bundle.check_contents()?;
        Ok(bundle)
    }

    /// The content rules that need the mapped arrays (see [`Bundle::open`]).
    fn check_contents(&self) -> Result<(), BundleError> {
        let n = self.n_patches;

        // Objects: contiguous runs covering 0..N, and patch_object agrees.
        let object_file = array_file_name(arrays::PATCH_OBJECT, DType::U32);
        let patch_object = self.patch_objects();
        let n_objects = self.manifest.objects.len();
        let mut end = 0u64;
        for (o, object) in self.manifest.objects.iter().enumerate() {
            if object.first_patch != end {
                return Err(invalid(
                    MANIFEST_FILE,
                    format!(
                        "objects[{o}] ({:?}) starts at patch {} but the previous object ends at {end}",
                        object.name, object.first_patch
                    ),
                ));
            }
            end = object.first_patch.saturating_add(object.patch_count);
            if end > n as u64 {
                return Err(invalid(
                    MANIFEST_FILE,
                    format!(
                        "objects[{o}] ({:?}) ends at patch {end} but patch_count is {n}",
                        object.name
                    ),
                ));
            }
            let first = object.first_patch as usize;
            let run = patch_object.get(first..end as usize).unwrap_or(&[]);
            for (k, &v) in (first..).zip(run) {
                if v as usize >= n_objects {
                    return Err(invalid(
                        &object_file,
                        format!("patch {k} names object {v} but the manifest lists {n_objects}"),
                    ));
                }
                if v as usize != o {
                    return Err(invalid(
                        &object_file,
                        format!(
                            "patch {k} names object {v} but lies in the patch range of objects[{o}] ({:?})",
                            object.name
                        ),
                    ));
                }
            }
        }
        if end != n as u64 {
            return Err(invalid(
                MANIFEST_FILE,
                format!("the objects cover patches 0..{end} but patch_count is {n}"),
            ));
        }

        // Areas finite and positive; other geometry finite.
        let area_file = array_file_name(arrays::PATCH_AREA, DType::F32);
        if let Some((k, a)) = self
            .patch_areas()
            .iter()
            .enumerate()
            .find(|(_, a)| !(a.is_finite() && **a > 0.0))
        {
            return Err(invalid(
                area_file,
                format!("patch {k} has area {a}, expected finite and > 0"),
            ));
        }
        for name in [
            arrays::PATCH_CORNERS,
            arrays::PATCH_NORMAL,
            arrays::PATCH_ALBEDO,
            arrays::PATCH_EMISSION,
            arrays::VERTEX_POSITION,
            arrays::VERTEX_NORMAL,
            arrays::OCCLUDER_TRI,
        ] {
            if let Some((k, v)) = self
                .f32s(name)
                .iter()
                .enumerate()
                .find(|(_, v)| !v.is_finite())
            {
                return Err(invalid(
                    array_file_name(name, DType::F32),
                    format!("element {k} is {v}, expected a finite number"),
                ));
            }
        }

        // Viewer triangles index existing vertices.
        let v_count = self.manifest.vertex_count;
        if let Some((k, &v)) = self
            .u32s(arrays::TRIANGLE_VERTEX)
            .iter()
            .enumerate()
            .find(|&(_, &v)| u64::from(v) >= v_count)
        {
            return Err(invalid(
                array_file_name(arrays::TRIANGLE_VERTEX, DType::U32),
                format!(
                    "triangle {} corner {} is vertex {v} but vertex_count is {v_count}",
                    k / 3,
                    k % 3
                ),
            ));
        }

        // F is an N × N CSR matrix, or C an N × (N + M) one over the cluster tree, whose
        // permutation and ranges are valid.
        if self.manifest.hierarchy.is_some() {
            self.check_tree()?;
        }
        if self.manifest.subsurface.walks > 0 {
            self.walks_checked()
                .map_err(|why| invalid(array_file_name(arrays::SIM_ROW_PTR, DType::U64), why))?;
        }
        crate::csr::CsrView::new_checked(
            self.ff_rows(),
            n + self.n_nodes,
            self.u64s(arrays::FF_ROW_PTR),
            self.u32s(arrays::FF_COL),
            self.f32s(arrays::FF_VAL),
        )
        .map_err(|error| BundleError::Csr {
            file: csr_file(&error, FF_NAMES),
            error,
        })?;

        // S is an N × N (hierarchical: N × (N + M)) CSR matrix of RGB values, non-negative;
        // distances likewise, scalar.
        if self.manifest.subsurface.links > 0 && self.manifest.hierarchy.is_none() {
            return Err(invalid(
                MANIFEST_FILE,
                "subsurface.links > 0 (a hierarchical S) needs the cluster tree of \
                 `hierarchy`, which is missing",
            ));
        }
        let s_cols = self.s_cols();
        let s = crate::csr::CsrView::<[f32; 3]>::new_checked(
            n,
            s_cols,
            self.u64s(arrays::S_ROW_PTR),
            self.u32s(arrays::S_COL),
            bytemuck::try_cast_slice(self.f32s(arrays::S_VAL)).unwrap_or(&[]),
        )
        .map_err(|error| BundleError::Csr {
            file: csr_file(&error, S_NAMES),
            error,
        })?;
        if let Some(k) = s.val().iter().position(|v| v.iter().any(|&x| x < 0.0)) {
            return Err(invalid(
                array_file_name(arrays::S_VAL, DType::F32),
                format!("entry {k} is negative; S re-emits light, it never absorbs below 0"),
            ));
        }
        let d = crate::csr::CsrView::<f32>::new_checked(
            n,
            s_cols,
            self.u64s(arrays::DIST_ROW_PTR),
            self.u32s(arrays::DIST_COL),
            self.f32s(arrays::DIST_VAL),
        )
        .map_err(|error| BundleError::Csr {
            file: csr_file(&error, DIST_NAMES),
            error,
        })?;
        if let Some(k) = d.val().iter().position(|&x| x < 0.0) {
            return Err(invalid(
                array_file_name(arrays::DIST_VAL, DType::F32),
                format!("distance {k} is negative"),
            ));
        }
        // Distance kinds: 0 (same side / interior) or 1 (a thin sheet's other side).
        if let Some((k, &v)) = self
            .u32s(arrays::DIST_KIND)
            .iter()
            .enumerate()
            .find(|&(_, &v)| v > 1)
        {
            return Err(invalid(
                array_file_name(arrays::DIST_KIND, DType::U32),
                format!("distance {k} has kind {v}, expected 0 (same side) or 1 (other side)"),
            ));
        }
        // Links' spreads: finite and ≥ 0.
        if let Some((k, v)) = self
            .f32s(arrays::DIST_SPREAD)
            .iter()
            .enumerate()
            .find(|(_, v)| !(v.is_finite() && **v >= 0.0))
        {
            return Err(invalid(
                array_file_name(arrays::DIST_SPREAD, DType::F32),
                format!("distance {k} has spread {v}, expected a finite value >= 0"),
            ));
        }
        // Per-medium path lengths: finite and ≥ 0; media indices within the limit.
        if let Some((k, v)) = self
            .f32s(arrays::DIST_MATERIAL_LEN)
            .iter()
            .enumerate()
            .find(|(_, v)| !(v.is_finite() && **v >= 0.0))
        {
            return Err(invalid(
                array_file_name(arrays::DIST_MATERIAL_LEN, DType::F32),
                format!(
                    "distance {} medium {} has length {v}, expected finite and >= 0",
                    k / 4,
                    k % 4
                ),
            ));
        }
        let limit = crate::scene::MAX_HETEROGENEOUS_MATERIALS as u32;
        if let Some((k, &m)) = self
            .u32s(arrays::PATCH_MATERIAL)
            .iter()
            .enumerate()
            .find(|&(_, &m)| m >= limit)
        {
            return Err(invalid(
                array_file_name(arrays::PATCH_MATERIAL, DType::U32),
                format!("patch {k} names medium {m}; there are at most {limit}"),
            ));
        }
        // Environment visibility: finite half floats >= 0 (no sign bit unless zero).
        if let Some(v) = self.environment_visibility()
            && let Some(k) = v
                .bits
                .iter()
                .position(|&b| b & 0x7c00 == 0x7c00 || (b & 0x8000 != 0 && b != 0x8000))
        {
            return Err(invalid(
                array_file_name(arrays::ENV_VISIBILITY, DType::F16),
                format!(
                    "element {k} (patch {}, bin {}) is not a finite number >= 0",
                    k / v.bins().max(1),
                    k % v.bins().max(1)
                ),
            ));
        }
        // The transfer matrix: finite half floats (exponent bits not all ones), scales
        // finite and ≥ 0.
        if let Some(t) = self.transfer() {
            if let Some(k) = t.bits.iter().position(|&b| b & 0x7c00 == 0x7c00) {
                return Err(invalid(
                    array_file_name(arrays::TRANSFER, DType::F16),
                    format!(
                        "element {k} (row {}, column {}, channel {}) is not a finite number",
                        k / (3 * n.max(1)),
                        (k / 3) % n.max(1),
                        k % 3
                    ),
                ));
            }
            if let Some(k) = t
                .scale
                .iter()
                .flatten()
                .position(|v| !(v.is_finite() && *v >= 0.0))
            {
                return Err(invalid(
                    array_file_name(arrays::TRANSFER_SCALE, DType::F32),
                    format!("element {k} is not finite and >= 0"),
                ));
            }
        }
        Ok(())
    }

    /// The environment visibility, when the bundle holds it (see [`EnvVisibilityView`]).
    pub fn environment_visibility(&self) -> Option<EnvVisibilityView<'_>> {
        let env = self.manifest.environment.as_ref()?;
        Some(EnvVisibilityView {
            rows: env.rows,
            cols: env.cols,
            bits: bytemuck::try_cast_slice(self.bytes_of(arrays::ENV_VISIBILITY, DType::F16))
                .unwrap_or(&[]),
        })
    }

    /// The transfer matrix, when the bundle holds one (see [`TransferView`]).
    pub fn transfer(&self) -> Option<TransferView<'_>> {
        self.manifest.transfer.as_ref()?;
        Some(TransferView {
            n: self.n_patches,
            bits: bytemuck::try_cast_slice(self.bytes_of(arrays::TRANSFER, DType::F16))
                .unwrap_or(&[]),
            scale: bytemuck::try_cast_slice(self.f32s(arrays::TRANSFER_SCALE)).unwrap_or(&[]),
        })
    }

    /// The cluster tree of a hierarchical F, when the bundle holds one (see [`TreeView`]).
    pub fn tree(&self) -> Option<TreeView<'_>> {
        self.manifest.hierarchy.as_ref()?;
        Some(TreeView {
            perm: self.u32s(arrays::TREE_PERM),
            range: bytemuck::try_cast_slice(self.u32s(arrays::TREE_RANGE)).unwrap_or(&[]),
        })
    }

    /// The random walks of the bundle's simulated objects, when it has any (see
    /// [`WalksView`]; checked at open).
    pub fn walks(&self) -> Option<WalksView<'_>> {
        if self.manifest.subsurface.walks == 0 {
            return None;
        }
        // Every record was checked when the bundle was opened (`check_contents`), and the
        // arrays are mapped read-only: the view is made without reading them again (an
        // absorption change asks for it each time, and the check reads every record).
        let (row_ptr, col, bin, weight, normal, lamp) = self.walk_arrays().ok()?;
        Some(WalksView {
            row_ptr,
            col,
            bin,
            weight,
            normal,
            lamp,
        })
    }

    /// The walk arrays, cast (weights as RGB triplets), not checked.
    fn walk_arrays(&self) -> Result<WalkArrays<'_>, String> {
        let weight = bytemuck::try_cast_slice(self.f32s(arrays::SIM_WEIGHT))
            .map_err(|_| "sim_weight is not a whole number of RGB triplets".to_string())?;
        let normal = if self.manifest.version >= SIM_NORMAL_SINCE {
            Some(
                bytemuck::try_cast_slice(self.f32s(arrays::SIM_WEIGHT_NORMAL)).map_err(|_| {
                    "sim_weight_normal is not a whole number of RGB triplets".to_string()
                })?,
            )
        } else {
            None
        };
        let lamp = if self.manifest.version >= SIM_LAMP_SINCE {
            Some(
                bytemuck::try_cast_slice(self.u32s(arrays::SIM_WEIGHT_LAMP)).map_err(|_| {
                    "sim_weight_lamp is not a whole number of RGB triplets".to_string()
                })?,
            )
        } else {
            None
        };
        Ok((
            self.u64s(arrays::SIM_ROW_PTR),
            self.u32s(arrays::SIM_COL),
            self.u32s(arrays::SIM_BIN),
            weight,
            normal,
            lamp,
        ))
    }

    fn walks_checked(&self) -> Result<WalksView<'_>, String> {
        let (row_ptr, col, bin, weight, normal, lamp) = self.walk_arrays()?;
        let view = WalksView::new_checked(self.n_patches, row_ptr, col, bin, weight, normal)?;
        match lamp {
            Some(t) => view.with_lamp(t),
            None => Ok(view),
        }
    }

    /// Checks the cluster tree: `tree_perm` is a permutation of `0..N` and every node's range
    /// lies in `0..N` and holds at least two patches.
    fn check_tree(&self) -> Result<(), BundleError> {
        let n = self.n_patches;
        let perm_file = array_file_name(arrays::TREE_PERM, DType::U32);
        let mut seen = vec![false; n];
        for (k, &p) in self.u32s(arrays::TREE_PERM).iter().enumerate() {
            let Some(s) = seen.get_mut(p as usize) else {
                return Err(invalid(
                    &perm_file,
                    format!("element {k} is patch {p} but patch_count is {n}"),
                ));
            };
            if *s {
                return Err(invalid(
                    &perm_file,
                    format!("patch {p} appears twice (not a permutation)"),
                ));
            }
            *s = true;
        }
        let range_file = array_file_name(arrays::TREE_RANGE, DType::U32);
        for (k, r) in self.u32s(arrays::TREE_RANGE).chunks_exact(2).enumerate() {
            if !(r[0] < r[1] && r[1] as usize <= n && r[1] - r[0] >= 2) {
                return Err(invalid(
                    &range_file,
                    format!(
                        "node {k} covers [{}, {}): expected at least two patches within 0..{n}",
                        r[0], r[1]
                    ),
                ));
            }
        }
        Ok(())
    }

    /// The bundle folder it was opened from.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The parsed manifest (its `arrays` lists every mapped file).
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    fn bytes_of(&self, name: &str, dtype: DType) -> &[u8] {
        match self.arrays.get(name) {
            Some(a) if a.dtype == dtype => a.bytes(),
            _ => &[],
        }
    }

    /// The elements of f32 array `name` (use the [`arrays`] constants). Never panics: a name
    /// that the bundle does not hold as f32 gives an empty slice. Required arrays are always
    /// present with the verified shape.
    pub fn f32s(&self, name: &str) -> &[f32] {
        bytemuck::try_cast_slice(self.bytes_of(name, DType::F32)).unwrap_or(&[])
    }

    /// The elements of u32 array `name`; empty when the bundle holds no such u32 array.
    pub fn u32s(&self, name: &str) -> &[u32] {
        bytemuck::try_cast_slice(self.bytes_of(name, DType::U32)).unwrap_or(&[])
    }

    /// The elements of u64 array `name`; empty when the bundle holds no such u64 array.
    pub fn u64s(&self, name: &str) -> &[u64] {
        bytemuck::try_cast_slice(self.bytes_of(name, DType::U64)).unwrap_or(&[])
    }

    /// `[N]` triangle corners of every patch (scene units).
    pub fn patch_corners(&self) -> &[[[f32; 3]; 3]] {
        bytemuck::try_cast_slice(self.f32s(arrays::PATCH_CORNERS)).unwrap_or(&[])
    }

    /// `[N]` unit normals.
    pub fn patch_normals(&self) -> &[[f32; 3]] {
        bytemuck::try_cast_slice(self.f32s(arrays::PATCH_NORMAL)).unwrap_or(&[])
    }

    /// `[N]` areas (scene units², finite and > 0).
    pub fn patch_areas(&self) -> &[f32] {
        self.f32s(arrays::PATCH_AREA)
    }

    /// `[N]` index into `manifest().objects` of each patch.
    pub fn patch_objects(&self) -> &[u32] {
        self.u32s(arrays::PATCH_OBJECT)
    }

    /// `[N]` albedo ρ (S_ii of an opaque patch).
    pub fn patch_albedo(&self) -> &[[f32; 3]] {
        bytemuck::try_cast_slice(self.f32s(arrays::PATCH_ALBEDO)).unwrap_or(&[])
    }

    /// `[N]` emitted exitance π·L_e (W·m⁻²).
    pub fn patch_emission(&self) -> &[[f32; 3]] {
        bytemuck::try_cast_slice(self.f32s(arrays::PATCH_EMISSION)).unwrap_or(&[])
    }

    /// `[V]` viewer-mesh vertex positions.
    pub fn vertex_positions(&self) -> &[[f32; 3]] {
        bytemuck::try_cast_slice(self.f32s(arrays::VERTEX_POSITION)).unwrap_or(&[])
    }

    /// `[V]` viewer-mesh vertex normals.
    pub fn vertex_normals(&self) -> &[[f32; 3]] {
        bytemuck::try_cast_slice(self.f32s(arrays::VERTEX_NORMAL)).unwrap_or(&[])
    }

    /// `[N]` viewer triangles (vertex indices `< V`); triangle k is patch k.
    pub fn triangle_vertices(&self) -> &[[u32; 3]] {
        bytemuck::try_cast_slice(self.u32s(arrays::TRIANGLE_VERTEX)).unwrap_or(&[])
    }

    /// `[M]` the scene's source triangles, for shadow rays.
    pub fn occluder_triangles(&self) -> &[[[f32; 3]; 3]] {
        bytemuck::try_cast_slice(self.f32s(arrays::OCCLUDER_TRI)).unwrap_or(&[])
    }

    /// F as an `N × N` CSR view, checked when the bundle was opened (no further pass).
    /// S: row j lists the sources i and S_ji per RGB channel (verified at open).
    pub fn subsurface(&self) -> crate::csr::CsrView<'_, [f32; 3]> {
        crate::csr::CsrView::from_checked_parts(
            self.n_patches,
            self.s_cols(),
            self.u64s(arrays::S_ROW_PTR),
            self.u32s(arrays::S_COL),
            bytemuck::try_cast_slice(self.f32s(arrays::S_VAL)).unwrap_or(&[]),
        )
    }

    /// Columns of S and of the distances: N, or N + M for a hierarchical S (see
    /// [`crate::bundle::SubsurfaceInfo::links`]).
    pub fn s_cols(&self) -> usize {
        if self.manifest.subsurface.links > 0 {
            self.n_patches + self.n_nodes
        } else {
            self.n_patches
        }
    }

    /// Optical path distances between patches of the same translucent object (verified at
    /// open; scene units); with a hierarchical S, also each receiver's links to cluster nodes
    /// (columns past N, [`crate::bundle::SubsurfaceInfo::links`]).
    pub fn distances(&self) -> crate::csr::CsrView<'_, f32> {
        crate::csr::CsrView::from_checked_parts(
            self.n_patches,
            self.s_cols(),
            self.u64s(arrays::DIST_ROW_PTR),
            self.u32s(arrays::DIST_COL),
            self.f32s(arrays::DIST_VAL),
        )
    }

    /// `[nnz_d]` each stored distance's spread, parallel to `distances().val()` (links read
    /// at two distances, [`crate::bundle::SubsurfaceInfo::link_near`]; verified at open to
    /// be finite and ≥ 0); empty when the bundle reads every link at one distance.
    pub fn distance_spreads(&self) -> &[f32] {
        self.f32s(arrays::DIST_SPREAD)
    }

    /// `[nnz_d]` the kind of each stored distance, parallel to `distances().val()`: 0 for a
    /// path inside an object or along one side of a thin sheet, 1 for a thin sheet's other
    /// side (verified at open to be 0 or 1).
    pub fn distance_kinds(&self) -> &[u32] {
        self.u32s(arrays::DIST_KIND)
    }

    /// Rows of F: N, or N + M when cluster nodes receive
    /// ([`HierarchyInfo::receiver_nodes`]).
    pub fn ff_rows(&self) -> usize {
        match &self.manifest.hierarchy {
            Some(h) if h.receiver_nodes => self.n_patches + self.n_nodes,
            _ => self.n_patches,
        }
    }

    /// F (`N × N`), or for a hierarchical bundle C (`N × (N + M)`, or `(N + M) × (N + M)`
    /// with node rows; see [`Manifest::hierarchy`]); use it with [`Bundle::tree`].
    pub fn form_factors(&self) -> crate::csr::CsrView<'_> {
        crate::csr::CsrView::from_checked_parts(
            self.ff_rows(),
            self.n_patches + self.n_nodes,
            self.u64s(arrays::FF_ROW_PTR),
            self.u32s(arrays::FF_COL),
            self.f32s(arrays::FF_VAL),
        )
    }

    /// F's columns in 16 bits for the CPU's products ([`crate::csr::NarrowCols`]): made by
    /// the first call (one pass over F's columns, 2 bytes an entry held beside the mapped
    /// ones), which a concurrent caller waits for.
    pub fn form_factor_cols(&self) -> &crate::csr::NarrowCols {
        self.ff_narrow
            .get_or_init(|| crate::csr::NarrowCols::of(&self.form_factors()))
    }

    /// Bytes of the arrays that are memory-mapped (those over [`COPY_ON_OPEN_BYTES`]); the
    /// rest are private copies read when the bundle opened.
    pub fn mapped_bytes(&self) -> u64 {
        self.arrays
            .values()
            .filter(|a| !a.is_copied())
            .map(|a| a.bytes().len() as u64)
            .sum()
    }

    /// Bytes on disk: `manifest.json` plus every array file it lists.
    pub fn total_bytes(&self) -> u64 {
        self.manifest_bytes + self.manifest.arrays.values().map(|e| e.bytes).sum::<u64>()
    }
}

/// A [`WalksView`]'s arrays: row pointers, sources, bins, weights, collimated weights,
/// lamp weights.
type WalkArrays<'a> = (
    &'a [u64],
    &'a [u32],
    &'a [u32],
    &'a [[f32; 3]],
    Option<&'a [[f32; 3]]>,
    Option<&'a [[u32; 3]]>,
);

#[cfg(test)]
#[path = "tests.rs"]
mod tests;
