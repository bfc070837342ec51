//! Optical path distances inside one translucent object (paper §4, "Computing Subsurface
//! Scattering Matrix").
//!
//! In: one object's source triangles (scene units, before subdivision), the centroids and
//! unit normals of its patches (local indices `0..n`), a truncation radius `max_radius`
//! beyond which the scattering profile is negligible, and [`VoxelParams`].
//! Out: [`Distances`], a CSR matrix over the patches holding, for every pair `i ≠ j` whose
//! optical path is at most `max_radius`, that path length `r(i, j)` — the argument at which
//! S evaluates the diffuse reflectance profile — plus [`DistanceStats`].
//!
//! Two methods:
//! - **Convex objects** ([`is_convex`]): the shortest interior path between two surface points
//!   is the straight segment, so `r = |c_i − c_j|` (pairs found with a uniform grid hash).
//! - **Everything else**: a uniform grid of cubic voxels over the bounding box, an inside
//!   test per voxel (ray parity along the three axes, majority vote — robust to holes), and a
//!   26-neighbour Dijkstra over interior voxels from each patch's entry voxel, truncated at
//!   `max_radius`. The graph length is corrected so that straight interior paths give exactly
//!   the Euclidean distance between centroids (see [`optical_distances`]).
//!
//! Accuracy of the voxel method. In free space the 26-neighbour graph distance for a voxel
//! offset with sorted absolute components `a ≥ b ≥ c` is the chamfer length
//! `ch = (a − b) + √2 (b − c) + √3 c`, which overestimates `√(a² + b² + c²)` by at most
//! `|(1, √2 − 1, √3 − √2)| = 1.1281` (12.8 %, reached in direction (1, 0.414, 0.318); the
//! 8.2 % often quoted is the 2-D 8-neighbour figure). Straight interior paths are corrected to
//! exact (below), so the remaining error of a bent path is at most 12.8 % of its length plus
//! about two voxels (entry-voxel placement and staircase boundaries).
//!
//! Heterogeneous objects ([`optical_distances_media`] with a [`MediumField`]) also get, per
//! stored pair, the length r_k the path travels in each medium k (Σ_k r_k = r):
//! - straight paths (convex objects, unattached patches) are split where the segment between
//!   the centroids crosses the pattern ([`MediumField::straight`]);
//! - voxel paths: every interior voxel carries a medium label (the checkerboard at its
//!   centre, or for per-patch media the medium of the nearest entry voxel through the
//!   interior, `label_by_nearest_entry`). Dijkstra carries along each node's per-medium
//!   graph lengths g_k: relaxing u → v with weight w adds w/2 to label(u) and w/2 to label(v)
//!   (the edge's halves lie in the two voxels; the integer weights are even, so
//!   Σ_k g_k = g exactly). A pair's lengths are its shares of the graph path applied to its
//!   corrected optical length, r_k = r · g_k / g (the entry voxel's medium when g = 0).
//!   Accuracy: a shortest 26-neighbour path to an oblique offset is a staircase whose
//!   diagonal and axial steps may come in any order, so where it crosses a medium boundary,
//!   as a share of its length, can differ from the straight line's by up to ≈ 9 % of the path
//!   (offset (2, 1, 0): diagonal steps first or last), plus about a voxel for the staircase
//!   of the boundary. For a checkerboard, pairs whose interior path is straight (zero
//!   detour) are therefore split exactly along the segment between the centroids instead.
//!   With several shortest paths, the one Dijkstra settles first is used, so r_k(i, j) and
//!   r_k(j, i) may differ where paths tie; r(i, j) itself stays exactly symmetric.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::Instant;

use glam::{DVec3, Vec3};
use rayon::prelude::*;

use translux_proto::csr::{Csr, CsrBuilder, CsrError};

use crate::hetero::MEDIA;

mod grid;
mod oracle;
mod paths;

pub use crate::hetero::{MediaLen, MediumField};
use grid::*;
pub use oracle::{FAR_RUN_VOXELS, Oracle};
use paths::*;

/// Parameters of [`optical_distances`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VoxelParams {
    /// Most voxels the grid may have (padding included). Default 2 000 000.
    pub max_voxels: usize,
    /// Convexity test slack, as a fraction of the bounding-box diagonal: a vertex up to this
    /// far in front of a face plane still counts as behind it. Default 1e-4.
    pub convex_tolerance: f32,
    /// Use the voxel method even when the object is convex (tests, comparisons).
    pub force_voxels: bool,
}

impl Default for VoxelParams {
    fn default() -> Self {
        Self {
            max_voxels: 2_000_000,
            convex_tolerance: 1e-4,
            force_voxels: false,
        }
    }
}

/// Optical path lengths, CSR over the object's patches (`n × n`, built by the checking
/// [`CsrBuilder`]): row `i` holds the columns `j` (sorted, `j ≠ i`) with `r(i, j) ≤
/// max_radius`, the values the lengths (scene units). `material_len` (aligned with the
/// entries) holds the per-medium lengths of each path for a heterogeneous object, and is
/// empty otherwise.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Distances {
    pub csr: Csr<f32>,
    pub material_len: Vec<MediaLen>,
}

impl Distances {
    /// Number of rows (patches).
    pub fn len(&self) -> usize {
        self.csr.n_rows
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Number of stored pairs.
    pub fn nnz(&self) -> u64 {
        self.csr.nnz() as u64
    }
    /// Columns and distances of row `i`.
    pub fn row(&self, i: usize) -> (&[u32], &[f32]) {
        let c = &self.csr;
        let (a, b) = (c.row_ptr[i] as usize, c.row_ptr[i + 1] as usize);
        (&c.col[a..b], &c.val[a..b])
    }
    /// `r(i, j)` if stored.
    pub fn get(&self, i: usize, j: usize) -> Option<f32> {
        let (cols, d) = self.row(i);
        cols.binary_search(&(j as u32)).ok().map(|k| d[k])
    }
    /// The per-medium lengths of the path from i to j, if stored (heterogeneous objects).
    pub fn get_len(&self, i: usize, j: usize) -> Option<MediaLen> {
        let (cols, _) = self.row(i);
        let k = cols.binary_search(&(j as u32)).ok()?;
        self.material_len
            .get(self.csr.row_ptr[i] as usize + k)
            .copied()
    }
}

/// How the distances were computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    /// Convex object: straight-line distance between centroids.
    Euclidean,
    /// Shortest paths through interior voxels (paper §4).
    Voxel,
}

/// What [`optical_distances`] did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DistanceStats {
    pub method: Method,
    /// Grid cells, padding included (0 for [`Method::Euclidean`]).
    pub voxels: usize,
    pub interior_voxels: usize,
    /// Voxel edge length (scene units; 0 for [`Method::Euclidean`]).
    pub voxel_size: f32,
    /// Grid dimensions, padding included.
    pub grid: [usize; 3],
    /// Distinct entry voxels, i.e. Dijkstra runs.
    pub sources: usize,
    /// Patches with no interior voxel within [`ENTRY_SEARCH`] voxels of their entry point
    /// (features thinner than a voxel); their pairs fall back to Euclidean distance.
    pub unattached: usize,
    pub seconds: f64,
    /// Stored pairs (nnz).
    pub pairs: u64,
}

impl DistanceStats {
    /// Straight lines between centroids ([`Method::Euclidean`]): no grid.
    pub fn straight(seconds: f64, pairs: u64) -> DistanceStats {
        DistanceStats {
            method: Method::Euclidean,
            voxels: 0,
            interior_voxels: 0,
            voxel_size: 0.0,
            grid: [0; 3],
            sources: 0,
            unattached: 0,
            seconds,
            pairs,
        }
    }
}

/// Why distances could not be computed.
#[derive(Debug, thiserror::Error)]
pub enum VoxelError {
    #[error(
        "object '{object}': no interior voxel among {voxels} (open or broken mesh); \
         optical paths cannot be traced through it"
    )]
    NoInterior { object: String, voxels: usize },
    #[error("object '{object}': {centroids} centroids but {normals} normals")]
    LengthMismatch {
        object: String,
        centroids: usize,
        normals: usize,
    },
    #[error("object '{object}': max_radius must be finite and > 0, got {radius}")]
    BadRadius { object: String, radius: f32 },
    #[error("object '{object}': {patches} patches do not fit 32-bit column indices")]
    TooManyPatches { object: String, patches: usize },
    /// The distances are not a valid matrix (a non-finite length from non-finite geometry).
    #[error("object '{object}': the optical distances are not a valid matrix: {error}")]
    Matrix { object: String, error: CsrError },
}

/// Max of chamfer/Euclidean length for 26-neighbour paths with the integer weights `W`:
/// |(W₁, W₂ − W₁, W₃ − W₂)| / W₁ = 1.128185 (1.128093 = |(1, √2 − 1, √3 − √2)| exactly).
pub const CHAMFER_MAX_RATIO: f64 = 1.128_19;
/// Fixed-point units per voxel for graph lengths. Integer weights make path lengths exact
/// sums, so `g(a, b) = g(b, a)` bit for bit and the result is exactly symmetric.
const UNIT: u32 = 1024;
/// Edge weights ×UNIT for 1, 2, 3 differing coordinates: 1, √2, √3 (relative rounding error
/// < 1e-4, far below the stencil's own error).
const W: [u32; 3] = [1024, 1448, 1774];
/// How far (in voxels, Chebyshev) to look for an interior voxel around an entry point.
pub const ENTRY_SEARCH: i64 = 4;
const NONE: u32 = u32::MAX;

/// True when the triangles bound a convex solid: every vertex lies on or behind every face
/// plane (within `tolerance` × bounding-box diagonal), and every face plane has some vertex
/// strictly behind it (so a flat or single-sided mesh, which encloses nothing, is not a
/// convex solid). Non-degenerate faces only; normals are `(b − a) × (c − a)`, so the mesh
/// must be wound outwards. O(faces × vertices), short-circuiting on the first violation.
pub fn is_convex(tris: &[[Vec3; 3]], tolerance: f32) -> bool {
    if tris.is_empty() {
        return false;
    }
    let (lo, hi) = bounds(tris);
    let diag = f64::from((hi - lo).length());
    if diag.is_nan() || diag <= 0.0 {
        return false;
    }
    let tol = f64::from(tolerance.max(0.0)) * diag;
    let mut seen = std::collections::HashSet::new();
    let verts: Vec<DVec3> = tris
        .iter()
        .flatten()
        .filter(|v| seen.insert(v.to_array().map(f32::to_bits)))
        .map(|v| v.as_dvec3())
        .collect();
    tris.par_iter().all(|t| {
        let (a, b, c) = (t[0].as_dvec3(), t[1].as_dvec3(), t[2].as_dvec3());
        let n = (b - a).cross(c - a);
        let len = n.length();
        if len <= 1e-12 * diag * diag {
            return true; // degenerate: no plane
        }
        let n = n / len;
        let mut deepest = 0.0f64;
        for v in &verts {
            let h = n.dot(*v - a); // signed height above the face plane
            if h > tol {
                return false;
            }
            deepest = deepest.min(h);
        }
        deepest < -tol
    })
}

/// Optical path lengths between the patches of one object (see the module docs).
///
/// For the voxel method, with `v_i` the entry voxel of patch `i` (the interior voxel nearest
/// to `c_i − n_i · voxel/2`), `g` the 26-neighbour graph length between `v_i` and `v_j`, and
/// `ch(Δv)` the free-space chamfer length of their offset `Δv`:
///
/// ```text
/// r(i, j) = |c_i − c_j| + (g · |Δv| / ch(Δv) − |Δv|)
/// ```
///
/// The bracket is the detour of the interior path over the straight line between the voxel
/// centres, with the graph length rescaled by the stencil's anisotropy in the direction of
/// `Δv`. A straight interior path has `g = ch(Δv)`, a zero detour and therefore exactly the
/// Euclidean distance; since `g ≥ ch(Δv)` always, `r ≥ |c_i − c_j|` (a path is never shorter
/// than the straight line). Patches sharing an entry voxel get `|c_i − c_j|`. Dijkstra is
/// truncated just far enough (`1.1281 × (max_radius + entry offsets)`) that no pair with
/// `r ≤ max_radius` is missed.
pub fn optical_distances(
    object_name: &str,
    source_tris: &[[Vec3; 3]],
    centroids: &[Vec3],
    normals: &[Vec3],
    max_radius: f32,
    params: &VoxelParams,
) -> Result<(Distances, DistanceStats), VoxelError> {
    optical_distances_media(
        object_name,
        source_tris,
        centroids,
        normals,
        max_radius,
        params,
        None,
    )
}

/// [`optical_distances`], plus per-medium path lengths (`Distances::material_len`) when
/// `media` says where the media of a heterogeneous object are (see the module docs).
/// Per-patch media always take the voxel route, since the interior's media come from the
/// voxel labelling.
pub fn optical_distances_media(
    object_name: &str,
    source_tris: &[[Vec3; 3]],
    centroids: &[Vec3],
    normals: &[Vec3],
    max_radius: f32,
    params: &VoxelParams,
    media: Option<&MediumField<'_>>,
) -> Result<(Distances, DistanceStats), VoxelError> {
    let start = Instant::now();
    check_inputs(object_name, centroids, normals, max_radius)?;
    let per_patch = matches!(media, Some(MediumField::PerPatch(_)));
    if !params.force_voxels && !per_patch && is_convex(source_tris, params.convex_tolerance) {
        let all: Vec<u32> = (0..centroids.len() as u32).collect();
        let hash = PointHash::new(centroids, &all, max_radius);
        let mut d = assemble_in_order(object_name, centroids.len(), |i| {
            let mut row = Vec::new();
            hash.within(centroids, centroids[i], max_radius, |j, d| {
                if j as usize != i {
                    row.push((j, d));
                }
            });
            row.sort_unstable_by_key(|p| p.0);
            row
        })?;
        if let Some(field) = media {
            // Straight paths: split where the segment between the centroids crosses the
            // pattern.
            let per_row: Vec<Vec<MediaLen>> = (0..d.len())
                .into_par_iter()
                .map(|i| {
                    let (cols, dist) = d.row(i);
                    cols.iter()
                        .zip(dist)
                        .map(|(&j, &r)| {
                            let j = j as usize;
                            field.straight(i, j, centroids[i], centroids[j], r)
                        })
                        .collect()
                })
                .collect();
            d.material_len = per_row.concat();
        }
        let stats = DistanceStats::straight(start.elapsed().as_secs_f64(), d.nnz());
        return Ok((d, stats));
    }
    voxel_distances(
        object_name,
        source_tris,
        centroids,
        normals,
        max_radius,
        params,
        media,
        start,
    )
}

/// Refuses inputs no path can be traced for: centroids and normals of different lengths, a
/// radius that is not finite and positive, more patches than 32-bit columns hold.
fn check_inputs(
    object_name: &str,
    centroids: &[Vec3],
    normals: &[Vec3],
    max_radius: f32,
) -> Result<(), VoxelError> {
    let object = || object_name.to_string();
    if centroids.len() != normals.len() {
        return Err(VoxelError::LengthMismatch {
            object: object(),
            centroids: centroids.len(),
            normals: normals.len(),
        });
    }
    if !(max_radius.is_finite() && max_radius > 0.0) {
        return Err(VoxelError::BadRadius {
            object: object(),
            radius: max_radius,
        });
    }
    if centroids.len() >= NONE as usize {
        return Err(VoxelError::TooManyPatches {
            object: object(),
            patches: centroids.len(),
        });
    }
    Ok(())
}

/// Appends rows in order (each checked by [`CsrBuilder`]) with their per-medium lengths.
struct RowsBuilder {
    object: String,
    csr: CsrBuilder<f32>,
    material_len: Vec<MediaLen>,
}

impl RowsBuilder {
    fn new(object: &str, n: usize) -> Self {
        let mut csr = CsrBuilder::new(n);
        csr.reserve(n, 0);
        RowsBuilder {
            object: object.to_string(),
            csr,
            material_len: Vec::new(),
        }
    }
    fn rows(&self) -> usize {
        self.csr.rows()
    }
    fn push_row(&mut self, row: &[(u32, f32)]) -> Result<(), VoxelError> {
        self.csr.push_row(row).map_err(|error| VoxelError::Matrix {
            object: self.object.clone(),
            error,
        })
    }
    fn finish(self) -> Distances {
        Distances {
            csr: self.csr.finish(),
            material_len: self.material_len,
        }
    }
}

/// Builds rows `0..n` from `row(i)` in parallel, a slice of rows at a time, so that at most
/// one slice of per-row vectors exists besides the CSR arrays.
fn assemble_in_order(
    object: &str,
    n: usize,
    row: impl Fn(usize) -> Vec<(u32, f32)> + Sync,
) -> Result<Distances, VoxelError> {
    let mut out = RowsBuilder::new(object, n);
    let batch = (n / 16).max(4096);
    let mut i0 = 0;
    while i0 < n {
        let i1 = (i0 + batch).min(n);
        let rows: Vec<Vec<(u32, f32)>> = (i0..i1).into_par_iter().map(&row).collect();
        for r in &rows {
            out.push_row(r)?;
        }
        i0 = i1;
    }
    Ok(out.finish())
}

/// A uniform grid hash of points with cell size = query radius: the points within r of q lie
/// in the 27 cells around q's cell. Only occupied cells are stored.
struct PointHash {
    lo: Vec3,
    cell: f32,
    map: HashMap<[i32; 3], Vec<u32>>,
}

impl PointHash {
    fn new(points: &[Vec3], ids: &[u32], r: f32) -> Self {
        let lo = ids.iter().fold(Vec3::splat(f32::INFINITY), |m, &i| {
            m.min(points[i as usize])
        });
        let mut h = PointHash {
            lo,
            cell: r,
            map: HashMap::new(),
        };
        for &i in ids {
            let k = h.key(points[i as usize]);
            h.map.entry(k).or_default().push(i);
        }
        h
    }

    fn key(&self, p: Vec3) -> [i32; 3] {
        ((p - self.lo) / self.cell)
            .floor()
            .to_array()
            .map(|x| x.clamp(-1e9, 1e9) as i32)
    }

    /// Calls `f(j, |p − p_j|)` for every stored point within r of `p`.
    fn within(&self, points: &[Vec3], p: Vec3, r: f32, mut f: impl FnMut(u32, f32)) {
        let k = self.key(p);
        for dz in -1..=1 {
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let c = [k[0] + dx, k[1] + dy, k[2] + dz];
                    if let Some(ids) = self.map.get(&c) {
                        for &j in ids {
                            let d = p.distance(points[j as usize]);
                            if d <= r {
                                f(j, d);
                            }
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests;
