//! The scene's S from stored distances (stage 2 of two), so translucency can change without
//! touching geometry.
//!
//! Stage 1 (`translux_precompute::distances`, geometry only) stores, for every translucent
//! object, the optical path r_ij between its patches out to `radius_margin` × the built
//! profile's truncation radius ([`stored_radius`]); a thin sheet's distances come with a
//! kind (same side or other side); a heterogeneous object's with the length in each medium.
//!
//! [`assemble_scene`] (the precompute *and* every translucency change): S from the stored
//! distances and the materials — [`subsurface::assemble`] per translucent object,
//! [`sheet::object_s`] per thin sheet (R by same-side, T by other-side distances),
//! [`hetero::assemble`] per heterogeneous object (eq. 9 from the per-medium lengths), ρ on
//! the diagonal of opaque patches, nothing for emitters.
//!
//! [`rebuild_from_bundle`] runs it on a mapped bundle with material overrides: the library
//! call behind a translucency slider.
//!
//! In: patch geometry, each object's material and patch range, the stored distances (CSR)
//! with their kinds and per-medium lengths. Out: S as owned CSR of RGB entries (row j lists
//! the sources i of S_ji), with a report per translucent object.

use std::ops::Range;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Instant;

use glam::Vec3;
use thiserror::Error;
use translux_proto::bundle::{Bundle, arrays};
use translux_proto::csr::{Csr, CsrBuilder, CsrError, CsrView, ValidCsr};
use translux_proto::scene::{Material, Profile};

use crate::hetero::{self, MediaLen};
use crate::linalg::Rgb;
use crate::profile::{ProfileError, ProfileEval};
use crate::sheet::{self, SheetError};
use crate::simulated::{self, SimMedium, WalksView};
use crate::sterms::{
    ColumnFactors, FlatTable, NodeRow, NodeShapes, ObjectTerms, Placement, STerms, Scratch,
    TermTable, Written,
};
use crate::subsurface::{self, Nodes, ObjectBlock, ObjectPatches, SubsurfaceParams, Tabulated};
pub use crate::subsurface::{AssemblyReport, SParams};
use rayon::prelude::*;

/// Why S could not be built.
#[derive(Debug, Error)]
pub enum SError {
    #[error("object '{object}': {error}")]
    Profile { object: String, error: ProfileError },
    #[error(transparent)]
    Sheet(#[from] SheetError),
    /// A heterogeneous material that the stored per-medium lengths cannot serve.
    #[error("object '{object}': {why}")]
    Media { object: String, why: String },
    /// Assembly made an invalid matrix (a non-finite value from a profile, say).
    #[error("S is not a valid matrix: {0}")]
    Matrix(#[from] CsrError),
    /// A rewrite in place met rows whose pattern is not the one its values are summed into
    /// (an S not built from this bundle's walks, or without the node rows of these radial
    /// terms): S must be built again.
    #[error("object '{object}': row {row} of the last S is not laid out as its rewrite needs")]
    Pattern { object: String, row: usize },
}

/// The per-patch geometry S needs (one scene's worth, global indices).
#[derive(Debug, Clone, Default)]
pub struct PatchGeometry {
    pub corners: Vec<[Vec3; 3]>,
    pub centroid: Vec<Vec3>,
    pub normal: Vec<Vec3>,
    pub area: Vec<f32>,
    pub size: Vec<f32>,
    /// The cluster tree a hierarchical S's links refer to (`None`: no links are read).
    pub nodes: Option<Nodes>,
}

impl PatchGeometry {
    /// Derives centroids, normals, areas and sizes from triangle corners.
    pub fn from_corners(corners: Vec<[Vec3; 3]>) -> Self {
        let mut g = PatchGeometry {
            corners,
            ..Default::default()
        };
        for c in &g.corners {
            let cross = (c[1] - c[0]).cross(c[2] - c[0]);
            g.centroid.push((c[0] + c[1] + c[2]) / 3.0);
            g.normal.push(cross.normalize_or_zero());
            g.area.push(0.5 * cross.length());
            g.size.push(
                (c[1] - c[0])
                    .length()
                    .max((c[2] - c[1]).length())
                    .max((c[0] - c[2]).length()),
            );
        }
        g
    }
}

/// An object as S sees it: its material and patch range.
#[derive(Debug, Clone)]
pub struct ObjectMaterial<'a> {
    pub name: &'a str,
    pub material: &'a Material,
    pub patches: Range<usize>,
}

/// The object's patches as `subsurface` and `sheet` take them.
pub fn object_patches(g: &PatchGeometry, r: Range<usize>) -> ObjectPatches<'_> {
    ObjectPatches {
        corners: &g.corners[r.clone()],
        centroid: &g.centroid[r.clone()],
        normal: &g.normal[r.clone()],
        area: &g.area[r.clone()],
        size: &g.size[r],
    }
}

/// How far stage 1 stores paths inside a translucent or heterogeneous object (scene
/// units): the profile's truncation radius with the margin; a heterogeneous object keeps
/// pairs out to the largest of its media's radii. `None` for other materials.
pub fn stored_radius(
    o: &ObjectMaterial<'_>,
    unit_mm: f64,
    params: &SParams,
) -> Result<Option<f32>, SError> {
    let profiles: &[Profile] = match o.material {
        Material::Translucent { profile, .. } => std::slice::from_ref(profile),
        Material::Heterogeneous { materials, .. } => materials,
        _ => return Ok(None),
    };
    let mut wanted = 0.0f32;
    for profile in profiles {
        let eval = ProfileEval::new(profile, unit_mm).map_err(|error| SError::Profile {
            object: o.name.to_string(),
            error,
        })?;
        wanted = wanted.max(eval.truncation_radius(params.truncation_energy));
    }
    Ok(Some(wanted * params.radius_margin.max(1.0)))
}

/// Stage 2: S from stored distances. `stored_radius[o]` is how far object o's distances
/// reach (0 for non-translucent objects). `material_len` (aligned with the entries of
/// `distances`) and `patch_material` are stage 1's per-medium lengths and patch media; they
/// are read for heterogeneous objects only. `dist_kind` (aligned likewise; missing entries
/// read as same side) is read for thin sheets only. With `fast` (a translucency change's
/// path, [`FastPath`]), objects it marks kept copy their rows of the stored S and the
/// other translucent objects and thin sheets are summed from their terms instead of
/// integrated.
#[expect(
    clippy::too_many_arguments,
    reason = "stage 1's arrays as the bundle stores them, each read by one kind of object"
)]
pub fn assemble_scene(
    g: &PatchGeometry,
    objects: &[ObjectMaterial<'_>],
    distances: CsrView<'_, f32>,
    material_len: &[MediaLen],
    patch_material: &[u32],
    dist_kind: &[u32],
    dist_spread: &[f32],
    stored_radius: &[f32],
    unit_mm: f64,
    params: &SParams,
    fast: Option<&FastPath<'_>>,
    walks: Option<&WalksView<'_>>,
) -> Result<(ValidCsr<[f32; 3]>, Vec<AssemblyReport>), SError> {
    let scene = StoredScene {
        g,
        distances,
        material_len,
        patch_material,
        dist_kind,
        dist_spread,
        stored_radius,
        unit_mm,
        params,
        fast,
        walks,
    };
    let mut laid = SceneRows::new(g.corners.len());
    for (k, o) in objects.iter().enumerate() {
        scene.object_rows(k, o, &mut laid)?;
    }
    let SceneRows {
        rows,
        mut reports,
        pending,
        node_rows,
    } = laid;
    let s = scene_matrix(g, rows, node_rows)?;
    let s = scene.write_pending(s, objects, pending, &mut reports)?;
    reports.sort_by_key(|r| r.0);
    Ok((s, reports.into_iter().map(|r| r.1).collect()))
}

/// What [`assemble_scene`] reads besides the objects: the patch geometry, stage 1's stored
/// arrays, the settings, and a translucency change's fast path and the stored walks.
#[derive(Clone, Copy)]
struct StoredScene<'a> {
    g: &'a PatchGeometry,
    distances: CsrView<'a, f32>,
    material_len: &'a [MediaLen],
    patch_material: &'a [u32],
    dist_kind: &'a [u32],
    dist_spread: &'a [f32],
    stored_radius: &'a [f32],
    unit_mm: f64,
    params: &'a SParams,
    fast: Option<&'a FastPath<'a>>,
    walks: Option<&'a WalksView<'a>>,
}

/// The scene's S as [`assemble_scene`] lays it out object by object: the patch rows, the
/// reports by object index, the objects summed from their terms once the matrix stands
/// (index, terms, reach), and the node rows of their node-to-node links (by node; empty
/// if none).
struct SceneRows<'a> {
    rows: Vec<Vec<(u32, [f32; 3])>>,
    reports: Vec<(usize, AssemblyReport)>,
    pending: Vec<(usize, &'a ObjectTerms, f32)>,
    node_rows: Vec<NodeRow>,
}

impl SceneRows<'_> {
    /// Empty rows for `n` patches.
    fn new(n: usize) -> Self {
        SceneRows {
            rows: vec![Vec::new(); n],
            reports: Vec::new(),
            pending: Vec::new(),
            node_rows: Vec::new(),
        }
    }
}

impl<'a> StoredScene<'a> {
    /// How far object k's stored distances reach (0 if none are stored).
    fn reach(&self, k: usize) -> f32 {
        self.stored_radius.get(k).copied().unwrap_or(0.0)
    }

    /// In: object k. Lays out its rows in `out` (its values, or zeros to be summed from
    /// its terms later) and adds its report; out: the first error of its material.
    fn object_rows(
        &self,
        k: usize,
        o: &ObjectMaterial<'_>,
        out: &mut SceneRows<'a>,
    ) -> Result<(), SError> {
        let r = o.patches.clone();
        if let Some(f) = self.fast.filter(|f| f.kept.get(k) == Some(&true)) {
            for j in r {
                let (cols, vals) = f.stored.row(j);
                out.rows[j] = cols.iter().copied().zip(vals.iter().copied()).collect();
            }
            return Ok(());
        }
        if let Some(t) = self.terms_of(k, o) {
            self.lay_out_terms(k, r, t, out);
            return Ok(());
        }
        let rows = &mut out.rows;
        let report = match o.material {
            Material::Diffuse { albedo, .. } => {
                for j in r {
                    rows[j] = vec![(j as u32, *albedo)];
                }
                return Ok(());
            }
            Material::Emitter { .. } => return Ok(()),
            Material::ThinSheet {
                reflectance,
                transmittance,
                ..
            } => self.sheet_rows(k, o, (reflectance, transmittance), rows)?,
            Material::Heterogeneous { materials, .. } => {
                self.heterogeneous_rows(k, o, materials, rows)?
            }
            Material::Simulated { .. } => self.simulated_rows(k, o, rows)?,
            Material::Translucent { profile, .. } => self.translucent_rows(k, o, profile, rows)?,
        };
        out.reports.push((k, report));
        Ok(())
    }

    /// Object k's radial terms when a translucency change sums it from them (a
    /// translucent object or thin sheet the bundle built as such); None otherwise.
    fn terms_of(&self, k: usize, o: &ObjectMaterial<'_>) -> Option<&'a ObjectTerms> {
        let sheet = matches!(o.material, Material::ThinSheet { .. });
        if !matches!(
            o.material,
            Material::Translucent { .. } | Material::ThinSheet { .. }
        ) {
            return None;
        }
        self.fast?.terms.get(k, sheet)
    }

    /// In: object k (patches `r`) summed from its terms `t`. Lays out its rows and node
    /// rows as zeros in `out` (the values are written once the matrix stands) and queues
    /// it.
    fn lay_out_terms(
        &self,
        k: usize,
        r: Range<usize>,
        t: &'a ObjectTerms,
        out: &mut SceneRows<'a>,
    ) {
        let g = self.g;
        for (j, row) in t
            .pattern(r.start, g.nodes.is_some())
            .into_iter()
            .enumerate()
        {
            out.rows[r.start + j] = row;
        }
        if let Some(nodes) = g.nodes.as_ref().filter(|_| !t.receiver_nodes().is_empty()) {
            out.node_rows.resize_with(nodes.range.len(), Vec::new);
            for (m, row) in t.node_rows() {
                out.node_rows[m] = row;
            }
        }
        out.pending.push((k, t, self.reach(k)));
    }

    /// In: thin sheet k with its reflectance and transmittance profiles. Writes its rows
    /// of S (R by same-side, T by other-side distances, then its links) into `rows`; out:
    /// its report.
    fn sheet_rows(
        &self,
        k: usize,
        o: &ObjectMaterial<'_>,
        (reflectance, transmittance): (&Profile, &Profile),
        rows: &mut [Vec<(u32, [f32; 3])>],
    ) -> Result<AssemblyReport, SError> {
        let (g, n, r) = (self.g, self.g.corners.len(), o.patches.clone());
        let (unit_mm, params) = (self.unit_mm, self.params);
        let reach = self.reach(k);
        let (s, report) = sheet::object_s(
            o.name,
            (reflectance, transmittance),
            object_patches(g, r.clone()),
            r.clone(),
            self.distances,
            self.dist_kind,
            reach,
            unit_mm,
            params,
        )?;
        let (mut s, mut report) = (s, report);
        if let Some(nodes) = &g.nodes {
            // Links read the table of their kind (the representative's side).
            let (tr, tt, _) =
                sheet::tables(o.name, (reflectance, transmittance), reach, unit_mm, params)?;
            let tab = |kind: u32| {
                if kind == sheet::KIND_OPPOSITE {
                    &tt
                } else {
                    &tr
                }
            };
            let links = node_links(
                self.distances,
                self.dist_kind,
                self.dist_spread,
                r.clone(),
                nodes,
                &tab,
            );
            subsurface::add_links(&mut s, r.start, &g.area[r.clone()], links, nodes, n);
            report.max_column_energy = s.report.max_column;
            report.scaled_columns = s.report.scaled_columns as u64;
            report.entries = s.report.nnz;
            report.links = s.links.iter().map(|l| l.len() as u64).sum();
        }
        place(rows, r.start, s.rows, s.links);
        Ok(report)
    }

    /// In: heterogeneous object k with its media's profiles. Writes its rows of S (eq. 9
    /// from the stored per-medium lengths) into `rows`; out: its report, or an error where
    /// no lengths were stored or a profile is invalid.
    fn heterogeneous_rows(
        &self,
        k: usize,
        o: &ObjectMaterial<'_>,
        materials: &[Profile],
        rows: &mut [Vec<(u32, [f32; 3])>],
    ) -> Result<AssemblyReport, SError> {
        let (g, n, r) = (self.g, self.g.corners.len(), o.patches.clone());
        let (distances, params) = (self.distances, self.params);
        let t = Instant::now();
        let object = || o.name.to_string();
        if self.material_len.len() != distances.nnz() || self.patch_material.len() != n {
            return Err(SError::Media {
                object: object(),
                why: "no per-medium path lengths were stored for it".into(),
            });
        }
        // Equal media merge (eq. 9 is not idempotent); each distinct medium gets a
        // table out to the largest wanted radius, capped by the stored distances.
        let (map, distinct) = hetero::merge_media(materials);
        let mut evals = Vec::with_capacity(distinct.len());
        let mut wanted = 0.0f32;
        for &d in &distinct {
            let eval =
                ProfileEval::new(&materials[d], self.unit_mm).map_err(|error| SError::Profile {
                    object: object(),
                    error,
                })?;
            wanted = wanted.max(eval.truncation_radius(params.truncation_energy));
            evals.push(eval);
        }
        let reach = self.reach(k);
        let radius = wanted.min(reach.max(f32::MIN_POSITIVE));
        let capped_from = (wanted > reach * (1.0 + 1e-6)).then_some(wanted);
        // Local CSR of this object's block, with its per-medium lengths.
        let block = ObjectBlock::of(distances, r.clone(), |_, d, _| d < radius);
        let lens: Vec<MediaLen> = block
            .entries
            .iter()
            .map(|&e| self.material_len[e])
            .collect();
        let tabs: Vec<Tabulated> = evals
            .iter()
            .map(|e| Tabulated::new(e, radius, 4096))
            .collect();
        let media = &self.patch_material[r.clone()];
        let s = hetero::assemble(
            object_patches(g, r.clone()),
            block.view(),
            &lens,
            media,
            &map,
            &tabs,
            &params.quadrature,
        );
        let report = AssemblyReport {
            name: o.name.to_string(),
            radius,
            capped_from,
            max_column_energy: s.report.max_column,
            scaled_columns: s.report.scaled_columns as u64,
            entries: s.report.nnz,
            links: 0,
            seconds: t.elapsed().as_secs_f64(),
        };
        place(rows, r.start, s.rows, Vec::new());
        Ok(report)
    }

    /// In: simulated object k. Writes its rows of S (its stored walks reweighted by its
    /// absorption; with the fast path's tilt, its Δ goes there) into `rows`; out: its
    /// report, or an error where no walks were stored or the medium is incomplete.
    fn simulated_rows(
        &self,
        k: usize,
        o: &ObjectMaterial<'_>,
        rows: &mut [Vec<(u32, [f32; 3])>],
    ) -> Result<AssemblyReport, SError> {
        let (g, r) = (self.g, o.patches.clone());
        let t = Instant::now();
        let Some(walks) = self.walks else {
            return Err(SError::Media {
                object: o.name.to_string(),
                why: "no walks were stored for it (precompute it with this material)".into(),
            });
        };
        let medium = SimMedium::of(o.material).ok_or_else(|| SError::Media {
            object: o.name.to_string(),
            why: "its simulated medium is incomplete".into(),
        })?;
        let sink = self.fast.and_then(|f| f.tilt);
        let (local, max_column) = match sink {
            Some(sink) => {
                let (local, delta, max) =
                    simulated::reweight_with_tilt(walks, r.clone(), &g.area, medium.sigma_a);
                if let Some(delta) = delta
                    && let Ok(mut sink) = sink.lock()
                {
                    sink.push((k, delta));
                }
                (local, max)
            }
            None => simulated::reweight(walks, r.clone(), &g.area, medium.sigma_a),
        };
        let entries = local.iter().map(|row| row.len() as u64).sum();
        for (k, row) in local.into_iter().enumerate() {
            rows[r.start + k] = row;
        }
        Ok(AssemblyReport {
            name: o.name.to_string(),
            radius: 0.0,
            capped_from: None,
            max_column_energy: max_column,
            scaled_columns: 0,
            entries,
            links: 0,
            seconds: t.elapsed().as_secs_f64(),
        })
    }

    /// In: translucent object k with its profile. Writes its rows of S (the quadrature over
    /// its block of the distances, then its links) into `rows`; out: its report.
    fn translucent_rows(
        &self,
        k: usize,
        o: &ObjectMaterial<'_>,
        profile: &Profile,
        rows: &mut [Vec<(u32, [f32; 3])>],
    ) -> Result<AssemblyReport, SError> {
        let (g, n, r) = (self.g, self.g.corners.len(), o.patches.clone());
        let t = Instant::now();
        let reach = self.reach(k);
        let (tab, capped_from) =
            translucent_table(o.name, profile, reach, self.unit_mm, self.params)?;
        let radius = tab.r_max();
        // This object's block of the distances, within the radius.
        let block = ObjectBlock::of(self.distances, r.clone(), |_, d, _| d < radius);
        let s = subsurface::assemble(
            object_patches(g, r.clone()),
            block.view(),
            &tab,
            &self.params.quadrature,
        );
        let mut s = s;
        if let Some(nodes) = &g.nodes {
            let links = node_links(
                self.distances,
                self.dist_kind,
                self.dist_spread,
                r.clone(),
                nodes,
                &|_| &tab,
            );
            subsurface::add_links(&mut s, r.start, &g.area[r.clone()], links, nodes, n);
        }
        let links = s.links.iter().map(|l| l.len() as u64).sum();
        let report = AssemblyReport {
            name: o.name.to_string(),
            radius,
            capped_from,
            max_column_energy: s.report.max_column,
            scaled_columns: s.report.scaled_columns as u64,
            entries: s.report.nnz,
            links,
            seconds: t.elapsed().as_secs_f64(),
        };
        place(rows, r.start, s.rows, s.links);
        Ok(report)
    }

    /// In: S laid out, the objects, and those queued to be summed from their terms. Writes
    /// each queued object's values into its rows of `s`, adding its report; out: S.
    fn write_pending(
        &self,
        s: ValidCsr<[f32; 3]>,
        objects: &[ObjectMaterial<'_>],
        pending: Vec<(usize, &ObjectTerms, f32)>,
        reports: &mut Vec<(usize, AssemblyReport)>,
    ) -> Result<ValidCsr<[f32; 3]>, SError> {
        let mut s = s;
        let mut scratch = Scratch::default();
        for (k, t, reach) in pending {
            let report;
            (s, report) = write_terms(
                s,
                self.g,
                &objects[k],
                t,
                reach,
                self.unit_mm,
                self.params,
                &mut scratch,
                None,
            )?;
            reports.push((k, report));
        }
        Ok(s)
    }
}

/// In: the patch rows and the node rows (node-to-node links; empty if none). Out: S as a
/// valid CSR, (N + M) × (N + M) where any row links to a node, N × N otherwise.
fn scene_matrix(
    g: &PatchGeometry,
    rows: Vec<Vec<(u32, [f32; 3])>>,
    node_rows: Vec<NodeRow>,
) -> Result<ValidCsr<[f32; 3]>, SError> {
    let n = g.corners.len();
    let mut rows = rows;
    // Node rows after the patch rows ((N + M) × (N + M), transport::LinkedScatter).
    rows.extend(node_rows);
    // Node columns when any row links to a node (a hierarchical S).
    let linked = rows
        .iter()
        .any(|row| row.last().is_some_and(|e| e.0 as usize >= n));
    let cols = match &g.nodes {
        Some(nodes) if linked => n + nodes.range.len(),
        _ => n,
    };
    // Room for every entry first: growing the arrays row by row cost a rebuild more than
    // the rows' own sum on a 24k-patch scene.
    let mut b = CsrBuilder::new(cols);
    b.reserve(rows.len(), rows.iter().map(Vec::len).sum());
    for row in &rows {
        b.push_row(row)?;
    }
    drop(rows);
    Ok(b.finish_valid())
}

/// The tables object `o`'s S is summed under: a translucent object's profile (`same`), or a
/// sheet's reflectance and transmittance (`same`, `other`), each out to its kept radius
/// capped by `reach` (how far its stored distances go), and the radius wanted where the cap
/// bites. An error for any other material.
pub fn object_tables(
    o: &ObjectMaterial<'_>,
    reach: f32,
    unit_mm: f64,
    params: &SParams,
) -> Result<(Tabulated, Option<Tabulated>, Option<f32>), SError> {
    Ok(match o.material {
        Material::Translucent { profile, .. } => {
            let (tab, capped) = translucent_table(o.name, profile, reach, unit_mm, params)?;
            (tab, None, capped)
        }
        Material::ThinSheet {
            reflectance,
            transmittance,
            ..
        } => {
            let (tr, tt, capped) =
                sheet::tables(o.name, (reflectance, transmittance), reach, unit_mm, params)?;
            (tr, Some(tt), capped)
        }
        _ => {
            return Err(SError::Media {
                object: o.name.to_string(),
                why: "only translucent objects and thin sheets are summed from terms".into(),
            });
        }
    })
}

/// Writes object `o`'s S, summed from its terms `t` under its material's profiles, into its
/// rows of `s` (laid out by [`ObjectTerms::pattern`]), `reach` being how far its stored
/// distances go. With `columns` (S's column factors, [`ColumnScale`]), the energy bound's
/// factors of the object's columns go there instead of into the values.
#[expect(
    clippy::too_many_arguments,
    reason = "the matrix, the object and its terms, and the settings its tables are made with"
)]
fn write_terms(
    s: ValidCsr<[f32; 3]>,
    g: &PatchGeometry,
    o: &ObjectMaterial<'_>,
    t: &ObjectTerms,
    reach: f32,
    unit_mm: f64,
    params: &SParams,
    scratch: &mut Scratch,
    columns: Option<&mut ColumnScale>,
) -> Result<(ValidCsr<[f32; 3]>, AssemblyReport), SError> {
    let start = Instant::now();
    let (same, other, capped_from) = object_tables(o, reach, unit_mm, params)?;
    let r = o.patches.clone();
    let at = Placement {
        start: r.start,
        n: g.corners.len(),
        nodes: g.nodes.as_ref(),
        defer_bound: columns.is_some(),
    };
    // The object's patch rows, then its node rows (runs of consecutive nodes).
    let mut ranges = vec![r.clone()];
    if at.nodes.is_some() {
        for &m in t.receiver_nodes() {
            let row = at.n + m as usize;
            match ranges.last_mut() {
                Some(last) if last.end == row && last.start >= at.n => last.end += 1,
                _ => ranges.push(row..row + 1),
            }
        }
    }
    // An S without this object's node rows was not built from these terms: built again
    // (the rows' own layout is checked as `ObjectTerms::write` reads them).
    if let Some(last) = ranges.last().filter(|l| l.end > s.view().n_rows()) {
        return Err(SError::Pattern {
            object: o.name.to_string(),
            row: last.end - 1,
        });
    }
    let mut out = None;
    let s = s.rewrite_ranges_vouched(&ranges, |rows| {
        let w = t.write(
            &g.area[r.clone()],
            &same,
            other.as_ref().unwrap_or(&same),
            at,
            rows,
            scratch,
        );
        let finite = w.finite;
        out = Some(w);
        finite
    })?;
    let Written {
        report: e,
        links,
        columns: factors,
        ..
    } = out.unwrap_or_default();
    if let (Some(scale), Some(f)) = (columns, factors) {
        scale.set(s.view().n_cols(), r.start, &f);
    }
    let report = AssemblyReport {
        name: o.name.to_string(),
        radius: same
            .r_max()
            .max(other.as_ref().map_or(0.0, Tabulated::r_max)),
        capped_from,
        max_column_energy: e.max_column,
        scaled_columns: e.scaled_columns as u64,
        entries: e.nnz,
        links,
        seconds: start.elapsed().as_secs_f64(),
    };
    Ok((s, report))
}

/// Receiver j's links to whole nodes for the rows `r` of a hierarchical S: S_{j,N+k} =
/// A_k P(r), P the table `tab(kind)` of the stored entry's kind, kept while √r is within
/// the table's end; a link with a spread σ > 0 (`dist_spread`, aligned with the entries;
/// empty: none) is read at two distances, A_k (P(r − σ) + P(r + σ)) / 2
/// ([`crate::subsurface::two_point_roots`]). Empty rows when the distances hold no links.
fn node_links<'t>(
    distances: CsrView<'_, f32>,
    dist_kind: &[u32],
    dist_spread: &[f32],
    r: Range<usize>,
    nodes: &Nodes,
    tab: &(dyn Fn(u32) -> &'t Tabulated + Sync),
) -> Vec<Vec<(u32, [f32; 3])>> {
    let n = distances.n_rows();
    r.into_par_iter()
        .map(|j| {
            let first = distances.row_ptr()[j] as usize;
            let (cols, ds) = distances.row(j);
            cols.iter()
                .zip(ds)
                .enumerate()
                .filter(|&(_, (&c, _))| c as usize >= n)
                .filter_map(|(e, (&c, &d))| {
                    let t = tab(dist_kind
                        .get(first + e)
                        .copied()
                        .unwrap_or(sheet::KIND_SAME));
                    // Looked up by √r against the table's end, as the radial terms'
                    // rebuild (`sterms`) does: a distance within an ulp of the end is then
                    // in or out of both alike.
                    let root = d.max(0.0).sqrt();
                    let spread = dist_spread.get(first + e).copied().unwrap_or(0.0);
                    (root < t.root_max()).then(|| {
                        let a = nodes.area[c as usize - n];
                        let two = crate::subsurface::two_point_roots(d, spread);
                        let r = crate::sterms::link_reading(two, root, |x| t.r_root(x));
                        (c, r.map(|v| v * a))
                    })
                })
                .collect()
        })
        .collect()
}

/// Writes an object's S rows (local indices, the object starting at patch `start`) into
/// the scene's rows, each followed by its links to nodes (global columns, if any).
fn place(
    rows: &mut [Vec<(u32, [f32; 3])>],
    start: usize,
    local: Vec<Vec<(u32, [f32; 3])>>,
    links: Vec<Vec<(u32, [f32; 3])>>,
) {
    let mut links = links.into_iter();
    for (j, row) in local.into_iter().enumerate() {
        let mut out: Vec<(u32, [f32; 3])> = row
            .into_iter()
            .map(|(i, v)| (start as u32 + i, v))
            .collect();
        if let Some(l) = links.next() {
            out.extend(l);
        }
        rows[start + j] = out;
    }
}

/// A homogeneous translucent object's profile tabulated out to its kept radius
/// ([`kept_radius`]), capped by `reach` (how far its stored distances go), and the radius
/// wanted when the cap bites.
pub fn translucent_table(
    name: &str,
    profile: &Profile,
    reach: f32,
    unit_mm: f64,
    params: &SParams,
) -> Result<(Tabulated, Option<f32>), SError> {
    let eval = ProfileEval::new(profile, unit_mm).map_err(|error| SError::Profile {
        object: name.to_string(),
        error,
    })?;
    let wanted = kept_radius(&eval, reach, params);
    let radius = wanted.min(reach.max(f32::MIN_POSITIVE));
    let capped_from = (wanted > reach * (1.0 + 1e-6)).then_some(wanted);
    Ok((Tabulated::new(&eval, radius, 4096), capped_from))
}

/// How far S keeps a translucent profile whose distances are stored out to `reach`: its
/// truncation radius (the tail past it carries `truncation_energy` of its energy), or,
/// for a profile narrower than the one the distances were stored for (a translucency
/// change towards less translucent: the stored radius, `reach / radius_margin`, is
/// wider), further, as far as the tail carries [`TAIL_ENERGY`] of the energy and at most
/// to the stored radius.
///
/// Why. On an object a few profile widths across, what reaches its far side is the tail
/// alone, so a tail cut at 10⁻³ of the energy takes 1–5% of that light (the slab and the
/// cube at ×0.25, `precompute/tests/it/dipole.rs`). The stored radius is what the bundle's
/// own S was built to, so keeping the narrower profile out to it costs at most the entries
/// that S had; a built profile and a wider one keep their truncation radius (their stored
/// radius is theirs, or narrower).
pub fn kept_radius(eval: &ProfileEval, reach: f32, params: &SParams) -> f32 {
    let kept = eval.truncation_radius(params.truncation_energy);
    let stored = reach / params.radius_margin.max(1.0);
    // A relative margin: the built profile's own radius, stored times the margin and
    // divided again, may come back an ulp away.
    if kept < stored * (1.0 - 1e-4) {
        eval.truncation_radius(TAIL_ENERGY).clamp(kept, stored)
    } else {
        kept
    }
}

/// The tail a narrower profile keeps within the stored radius ([`kept_radius`]): 10⁻⁶ of
/// its energy.
pub const TAIL_ENERGY: f32 = 1e-6;

/// Each object's material with `overrides` (by object index) applied: the override where
/// there is one, else the bundle's (one per manifest object).
pub fn materials_with<'a>(
    bundle: &'a Bundle,
    overrides: &'a [(usize, Material)],
) -> Vec<&'a Material> {
    bundle
        .manifest()
        .objects
        .iter()
        .enumerate()
        .map(|(k, o)| {
            overrides
                .iter()
                .find(|(i, _)| *i == k)
                .map_or(&o.material, |(_, m)| m)
        })
        .collect()
}

/// The bundle's materials with `overrides` applied (by object index), and how far each
/// object's stored distances reach (0 for objects without any). Refuses a heterogeneous
/// override the stored per-medium lengths cannot serve.
pub fn bundle_materials(
    bundle: &Bundle,
    overrides: &[(usize, Material)],
) -> Result<(Vec<Material>, Vec<f32>), SError> {
    let m = bundle.manifest();
    let materials: Vec<Material> = materials_with(bundle, overrides)
        .into_iter()
        .cloned()
        .collect();
    let stored: Vec<f32> = m
        .objects
        .iter()
        .map(|o| {
            m.subsurface
                .objects
                .iter()
                .find(|s| s.name == o.name)
                .map_or(0.0, |s| s.distance_radius)
        })
        .collect();
    // A heterogeneous override needs lengths stored for the same media layout: the object
    // must have been built heterogeneous with the same pattern and number of media (only the
    // media's profiles may change).
    for (k, mat) in overrides {
        if let (Some(new), Some(built)) = (SimMedium::of(mat), m.objects.get(*k)) {
            let why = match SimMedium::of(&built.material) {
                Some(b) => simulated::check_override(&b, &new).err(),
                None => Some(format!(
                    "it was precomputed as {}; a simulated S needs walks, which only \
                     translux-precompute runs",
                    built.material.kind()
                )),
            };
            if let Some(why) = why {
                return Err(SError::Media {
                    object: built.name.clone(),
                    why,
                });
            }
        }
        if let (
            Material::Translucent { .. }
            | Material::Heterogeneous { .. }
            | Material::ThinSheet { .. },
            Some(built),
        ) = (mat, m.objects.get(*k))
            && matches!(built.material, Material::Simulated { .. })
        {
            return Err(SError::Media {
                object: built.name.clone(),
                why: format!(
                    "it was precomputed as simulated, without the optical distances a {} \
                     material needs; run translux-precompute again to change its kind",
                    mat.kind()
                ),
            });
        }
        let Material::Heterogeneous {
            materials, pattern, ..
        } = mat
        else {
            continue;
        };
        let Some(built) = m.objects.get(*k) else {
            continue;
        };
        let same = matches!(&built.material, Material::Heterogeneous { materials: bm, pattern: bp, .. }
            if bm.len() == materials.len() && bp == pattern);
        if !same {
            return Err(SError::Media {
                object: built.name.clone(),
                why: format!(
                    "it was precomputed as {}; a heterogeneous material can only change the \
                     profiles of the media it was precomputed with (same pattern, same number \
                     of media), since the lengths per medium are geometry",
                    built.material.kind()
                ),
            });
        }
    }
    Ok((materials, stored))
}

/// The link bounds a translucency change groups an object's receivers under: the
/// bundle's own (`SubsurfaceInfo::link_variation`), one per profile of the object (a thin
/// sheet has two), none for a bundle cut by geometry alone.
fn receiver_bounds(
    bundle: &Bundle,
    material: &Material,
    g: &PatchGeometry,
    range: Range<usize>,
    reach: f32,
) -> Vec<crate::linkbound::LinkBound> {
    let manifest = bundle.manifest();
    let Some(variation) = manifest.subsurface.link_variation else {
        return Vec::new();
    };
    let smallest = g.size[range].iter().copied().fold(f32::INFINITY, f32::min);
    let tolerance = crate::linkbound::LinkTolerance {
        variation,
        ..Default::default()
    };
    crate::linkbound::bounds_of(material, manifest.unit_mm, smallest, reach, tolerance)
}

/// Reduces the S entries of every translucent object and thin sheet of `bundle`, out to the
/// radius its distances were stored to, to radial terms ([`crate::sterms`]): what
/// [`rebuild_with_terms`] sums.
pub fn terms_of_bundle(bundle: &Bundle, params: &SubsurfaceParams) -> STerms {
    let t = Instant::now();
    let g = bundle_geometry(bundle);
    let (materials, reach) = bundle_materials(bundle, &[]).expect("the bundle's own materials");
    let kinds = bundle.distance_kinds();
    let shapes = g
        .nodes
        .as_ref()
        .filter(|_| params.receiver_theta > 0.0)
        .map(|nodes| NodeShapes::new(nodes, &g.corners, &g.area));
    let objects = bundle
        .manifest()
        .objects
        .iter()
        .zip(&materials)
        .zip(&reach)
        .map(|((o, material), &reach)| {
            let sheet = match material {
                Material::Translucent { .. } => false,
                Material::ThinSheet { .. } => true,
                _ => return None,
            };
            let range = o.first_patch as usize..(o.first_patch + o.patch_count) as usize;
            let block = ObjectBlock::of(bundle.distances(), range.clone(), |_, d, _| d < reach);
            let opposite = |e: usize| kinds.get(block.entries[e]) == Some(&sheet::KIND_OPPOSITE);
            let t = ObjectTerms::build(
                object_patches(&g, range.clone()),
                block.view(),
                sheet,
                &opposite,
                params,
            );
            // A hierarchical S also links rows to whole nodes (see `assemble_scene`).
            Some(match &g.nodes {
                Some(nodes) => {
                    let start = range.start;
                    let t = t.with_links(
                        bundle.distances(),
                        kinds,
                        bundle.distance_spreads(),
                        range.clone(),
                        reach,
                    );
                    match &shapes {
                        Some(shapes) => {
                            let bounds = receiver_bounds(bundle, material, &g, range, reach);
                            t.with_node_pairs(params.receiver_theta, nodes, shapes, start, &bounds)
                        }
                        None => t,
                    }
                }
                None => t,
            })
        })
        .collect();
    STerms::new(objects, t.elapsed().as_secs_f64())
}

/// The bundle's patch geometry as S assembly takes it.
pub fn bundle_geometry(bundle: &Bundle) -> PatchGeometry {
    let mut g = PatchGeometry::from_corners(
        bundle
            .patch_corners()
            .iter()
            .map(|c| c.map(Vec3::from))
            .collect(),
    );
    if bundle.manifest().subsurface.links > 0
        && let Some(t) = bundle.tree()
    {
        g.nodes = Some(Nodes {
            perm: t.perm.to_vec(),
            range: t.range.to_vec(),
            area: crate::transport::node_areas(t, bundle.patch_areas()),
        });
    }
    g
}

/// ρ a patch of this material carries in the diffuse solve, and its emitted exitance.
pub fn material_albedo_emission(m: &Material) -> ([f32; 3], [f32; 3]) {
    match m {
        Material::Diffuse { albedo, .. } => (*albedo, [0.0; 3]),
        // Until S is in the bundle a translucent object is opaque with its profile's total
        // diffuse reflectance (the "inter-reflection only" view of it), capped below 1.
        Material::Translucent { profile, .. } => (
            crate::profile::total_reflectance(profile).map(|r| r.clamp(0.0, 0.999)),
            [0.0; 3],
        ),
        Material::Emitter { radiance } => ([0.0; 3], radiance.map(|l| l * std::f32::consts::PI)),
        // A thin sheet returns light to the side it came from (R) and to the other (T); seen
        // as an opaque two-sided patch, a face re-emits the sum, capped below 1.
        Material::ThinSheet {
            reflectance,
            transmittance,
            ..
        } => {
            let (r, t) = (
                crate::profile::total_reflectance(reflectance),
                crate::profile::total_reflectance(transmittance),
            );
            (
                std::array::from_fn(|c| (r[c] + t[c]).clamp(0.0, 0.999)),
                [0.0; 3],
            )
        }
        // A simulated object: the dipole's total diffuse reflectance of the same medium.
        Material::Simulated { .. } => (
            SimMedium::of(m).map_or([0.5; 3], |s| s.opaque_albedo()),
            [0.0; 3],
        ),
        // A heterogeneous object as a whole: the mean of its media's total diffuse
        // reflectances, each medium counted once (the precompute writes each patch's own
        // medium's instead, see `patch_albedo`).
        Material::Heterogeneous { materials, .. } => {
            let mut sum = [0.0f32; 3];
            for p in materials {
                let rd = crate::profile::total_reflectance(p);
                for c in 0..3 {
                    sum[c] += rd[c] / materials.len().max(1) as f32;
                }
            }
            (sum.map(|r| r.clamp(0.0, 0.999)), [0.0; 3])
        }
    }
}

/// ρ of one patch: [`material_albedo_emission`]'s, except that a patch of a heterogeneous
/// object carries the total diffuse reflectance of its own medium `medium` (so the
/// inter-reflection-only view shows the pattern).
pub fn patch_albedo(m: &Material, medium: u32) -> [f32; 3] {
    match m {
        Material::Heterogeneous { materials, .. } => match materials.get(medium as usize) {
            Some(p) => crate::profile::total_reflectance(p).map(|r| r.clamp(0.0, 0.999)),
            None => material_albedo_emission(m).0,
        },
        _ => material_albedo_emission(m).0,
    }
}

/// The energy bound's factors of S's columns that its stored values do not carry (a
/// translucency change written in place, [`rewrite_with_terms_deferred`]): S is the
/// values times diag(factors), one factor per column (patches, then cluster nodes), each
/// in [0, 1]. A product scales its vector by them instead of S being passed over again to
/// scale its entries ([`crate::transport::subsurface_operator`]). Empty, or all 1: S is
/// its values.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ColumnScale {
    factors: Vec<Rgb>,
    /// Some factor is not 1.
    any: bool,
}

impl ColumnScale {
    /// The factors, one per column of S, or None when every one is 1.
    pub fn factors(&self) -> Option<&[Rgb]> {
        self.any.then_some(self.factors.as_slice())
    }

    /// Bytes held (the factors, once a deferred write has set any, kept at S's width).
    pub fn bytes(&self) -> u64 {
        (self.factors.len() * std::mem::size_of::<Rgb>()) as u64
    }

    /// Object columns' factors from one deferred write: its patches' from S's column
    /// `start` on, its nodes' where `f` says (S has `n_cols` columns).
    fn set(&mut self, n_cols: usize, start: usize, f: &ColumnFactors) {
        if self.factors.len() != n_cols {
            self.factors = vec![[1.0; 3]; n_cols];
        }
        self.factors[start..start + f.patches.len()].copy_from_slice(&f.patches);
        self.factors[f.node_column..f.node_column + f.nodes.len()].copy_from_slice(&f.nodes);
        self.any = self.factors.iter().any(|f| *f != [1.0; 3]);
    }

    /// S's values scaled by the factors (the matrix itself, as every consumer that reads
    /// S's entries rather than multiplying by it needs it): each value times its column's
    /// factor, the same products a write that scales in place makes.
    pub fn apply(&self, s: ValidCsr<[f32; 3]>) -> Result<ValidCsr<[f32; 3]>, CsrError> {
        let Some(f) = self.factors() else {
            return Ok(s);
        };
        assert_eq!(f.len(), s.view().n_cols(), "a factor per column of S");
        let rows = 0..s.view().n_rows();
        // A factor in [0, 1] keeps a finite value finite.
        s.rewrite_vouched(rows, |rows| {
            rows.into_par_iter().for_each(|(cols, vals)| {
                for (v, &c) in vals.iter_mut().zip(cols) {
                    let k = f[c as usize];
                    if k != [1.0; 3] {
                        *v = std::array::from_fn(|ch| v[ch] * k[ch]);
                    }
                }
            });
            true
        })
    }
}

/// S's values and the column factors S is those times ([`rewrite_with_terms_deferred`]).
pub type ScaledS = (ValidCsr<[f32; 3]>, ColumnScale);

/// S, ρ and Bₑ for a set of material overrides.
///
/// S's values are made on the CPU when it is built, or, for a change written in place
/// ([`rewrite_with_terms`]), when a CPU consumer first asks ([`OverrideMaterials::cpu_s`]):
/// a backend that writes S's changed rows itself (the GPU's) leaves the CPU's copy
/// unwritten while it serves every relight with these materials.
#[derive(Debug)]
pub struct OverrideMaterials {
    /// The overrides, as JSON: which override set this is (the backend's key too).
    pub key: String,
    /// The overrides themselves (what a translucency change compares with).
    pub overrides: Vec<(usize, Material)>,
    pub albedo: Vec<Rgb>,
    pub emission: Vec<Rgb>,
    /// S is the last override set's, with the profiles that changed written into it in
    /// place ([`rewrite_with_terms`]), not built afresh.
    pub in_place: bool,
    /// S's layout: a number of its own for every S built afresh, kept by every change
    /// written in place since (a device holding S of this layout writes only the changed
    /// objects' rows).
    pub layout: u64,
    /// S's values and the energy bound's column factors they do not carry yet, once made
    /// on the CPU.
    cpu: OnceLock<ScaledS>,
    /// Until then: the values of an earlier S of this layout and the objects whose rows
    /// in them are not yet these overrides' (`None` once made, or after a failure).
    pending: Mutex<Option<(ScaledS, Vec<usize>)>>,
}

/// S written in place for later overrides ([`OverrideMaterials::cpu_s`]): from an earlier
/// S of the same layout and the objects to rewrite, S for these overrides.
pub type RewriteS<'a> = &'a dyn Fn(ScaledS, &[usize]) -> Result<ScaledS, SError>;

impl OverrideMaterials {
    /// Materials whose S is made: its values and column factors.
    pub fn made(
        (key, overrides): (String, Vec<(usize, Material)>),
        s: ScaledS,
        (albedo, emission): (Vec<Rgb>, Vec<Rgb>),
        (in_place, layout): (bool, u64),
    ) -> Self {
        let cpu = OnceLock::new();
        let _ = cpu.set(s);
        OverrideMaterials {
            key,
            overrides,
            albedo,
            emission,
            in_place,
            layout,
            cpu,
            pending: Mutex::new(None),
        }
    }

    /// Materials whose S is `base` (an earlier S of this layout) with the rows of the
    /// objects `stale` not yet written for these overrides.
    pub fn deferred(
        (key, overrides): (String, Vec<(usize, Material)>),
        (base, stale): (ScaledS, Vec<usize>),
        (albedo, emission): (Vec<Rgb>, Vec<Rgb>),
        layout: u64,
    ) -> Self {
        OverrideMaterials {
            key,
            overrides,
            albedo,
            emission,
            in_place: true,
            layout,
            cpu: OnceLock::new(),
            pending: Mutex::new(Some((base, stale))),
        }
    }

    /// S on the CPU, made by `rewrite` on first use when it was deferred; an error when
    /// that rewrite failed (now or before).
    pub fn cpu_s(&self, rewrite: RewriteS<'_>) -> Result<&ScaledS, SError> {
        if let Some(s) = self.cpu.get() {
            return Ok(s);
        }
        let mut pending = self.pending.lock().unwrap_or_else(|p| p.into_inner());
        // Made by a concurrent caller while this one waited.
        if let Some(s) = self.cpu.get() {
            return Ok(s);
        }
        let (base, stale) = pending.take().ok_or_else(|| SError::Media {
            object: "S".into(),
            why: "an earlier rewrite of these materials failed".into(),
        })?;
        let s = rewrite(base, &stale)?;
        Ok(self.cpu.get_or_init(|| s))
    }

    /// S's values and column factors if made on the CPU.
    pub fn made_s(&self) -> Option<&ScaledS> {
        self.cpu.get()
    }

    /// What a change written in place after this one starts from: S's values and factors
    /// (the CPU's, or the earlier S still pending) and the objects whose rows in them are
    /// stale; taken from `this` when it is the only holder, copied otherwise (a relight
    /// still reads it). `None` after a failed rewrite.
    pub fn into_base(this: Arc<Self>) -> Option<(ScaledS, Vec<usize>)> {
        match Arc::try_unwrap(this) {
            Ok(m) => match m.cpu.into_inner() {
                Some(s) => Some((s, Vec::new())),
                None => m.pending.into_inner().unwrap_or_else(|p| p.into_inner()),
            },
            Err(shared) => match shared.cpu.get() {
                Some(s) => Some((s.clone(), Vec::new())),
                None => shared
                    .pending
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .clone(),
            },
        }
    }

    /// Bytes held by S's values and factors (made or pending).
    pub fn s_bytes(&self) -> u64 {
        let of = |(v, c): &ScaledS| {
            let s = v.csr();
            (s.row_ptr.len() * 8 + s.col.len() * 4 + s.val.len() * 12) as u64 + c.bytes()
        };
        match self.cpu.get() {
            Some(s) => of(s),
            None => self
                .pending
                .lock()
                .map(|p| p.as_ref().map_or(0, |(s, _)| of(s)))
                .unwrap_or(0),
        }
    }
}

/// S itself from its values and column factors: the values, or a copy scaled by the
/// factors when there are any (for those that read S's entries: a device upload, a check).
pub fn scaled_s(
    (values, columns): &ScaledS,
) -> Result<std::borrow::Cow<'_, ValidCsr<[f32; 3]>>, CsrError> {
    match columns.factors() {
        None => Ok(std::borrow::Cow::Borrowed(values)),
        Some(_) => Ok(std::borrow::Cow::Owned(columns.apply(values.clone())?)),
    }
}

/// What a translucency change reuses ([`assemble_scene`]): the radial terms of the
/// bundle's translucent objects and thin sheets, its stored S, and which objects (by index)
/// keep their stored rows. With `tilt`, simulated objects assembled here also leave their
/// Δ = S⁽ⁿ⁾ − S there (made in the same pass over their walks, [`crate::collimated`]).
#[derive(Debug, Clone, Copy)]
pub struct FastPath<'a> {
    pub terms: &'a STerms,
    pub stored: CsrView<'a, [f32; 3]>,
    pub kept: &'a [bool],
    pub tilt: Option<&'a Mutex<SimTilts>>,
}

/// The lamps' tilt of simulated objects (Δ = S⁽ⁿ⁾ − S, G_u, G_v, U), per object index:
/// local rows of `(global i, [Δ_ji, G_u,ji, G_v,ji, U_ji])`.
pub type SimTilts = Vec<(usize, simulated::TiltRows)>;

/// S, its assembly reports, and the Δ made beside it ([`rebuild_with_terms_and_tilt`]).
pub type WithTilt = (ValidCsr<[f32; 3]>, Vec<AssemblyReport>, SimTilts);

/// Rebuilds S for a bundle with some objects' materials replaced (by object index), from
/// the stored distances: no voxels, no rays. Objects not overridden keep their material.
pub fn rebuild_from_bundle(
    bundle: &Bundle,
    overrides: &[(usize, Material)],
    params: &SParams,
) -> Result<(Csr<[f32; 3]>, Vec<AssemblyReport>), SError> {
    assemble_overrides(bundle, overrides, params, None, None).map(|(s, r)| (s.into_csr(), r))
}

/// [`rebuild_from_bundle`] for a translucency change: objects that are not overridden keep
/// their rows of the bundle's stored S (so overriding one object, or only an emitter, leaves
/// the others exactly as precomputed), and overridden translucent objects and thin sheets
/// are summed from `terms` (reduced once from this bundle, [`terms_of_bundle`]) instead of
/// integrated. Reports cover the objects assembled here.
pub fn rebuild_with_terms(
    bundle: &Bundle,
    overrides: &[(usize, Material)],
    params: &SParams,
    terms: &STerms,
) -> Result<(Csr<[f32; 3]>, Vec<AssemblyReport>), SError> {
    let kept: Vec<bool> = (0..bundle.manifest().objects.len())
        .map(|k| !overrides.iter().any(|(i, _)| *i == k))
        .collect();
    let fast = FastPath {
        terms,
        stored: bundle.subsurface(),
        kept: &kept,
        tilt: None,
    };
    assemble_overrides(bundle, overrides, params, Some(&fast), None).map(|(s, r)| (s.into_csr(), r))
}

/// [`rebuild_with_terms`] for a relight, which with lamps also needs Δ = S⁽ⁿ⁾ − S of the
/// overridden simulated objects ([`crate::collimated`]): made in the same pass over their
/// walks as S (an absorption change reads the records once, not twice).
pub fn rebuild_with_terms_and_tilt(
    bundle: &Bundle,
    overrides: &[(usize, Material)],
    params: &SParams,
    terms: &STerms,
) -> Result<WithTilt, SError> {
    let kept: Vec<bool> = (0..bundle.manifest().objects.len())
        .map(|k| !overrides.iter().any(|(i, _)| *i == k))
        .collect();
    let sink = Mutex::new(Vec::new());
    let fast = FastPath {
        terms,
        stored: bundle.subsurface(),
        kept: &kept,
        tilt: Some(&sink),
    };
    let (s, reports) = assemble_overrides(bundle, overrides, params, Some(&fast), None)?;
    let tilts = sink.into_inner().unwrap_or_else(|e| e.into_inner());
    Ok((s, reports, tilts))
}

/// S for a bundle whose simulated objects in `overrides` walked again (`walks`, the whole
/// scene's records after the new walks): those objects' rows re-weighted from `walks`, every
/// other object's rows kept from the bundle's stored S. What a re-simulation writes
/// (`translux_precompute::resimulate`). Reports cover the overridden objects.
pub fn rebuild_with_walks(
    bundle: &Bundle,
    overrides: &[(usize, Material)],
    params: &SParams,
    walks: &WalksView<'_>,
) -> Result<(Csr<[f32; 3]>, Vec<AssemblyReport>), SError> {
    let objects = bundle.manifest().objects.len();
    let kept: Vec<bool> = (0..objects)
        .map(|k| !overrides.iter().any(|(i, _)| *i == k))
        .collect();
    // Simulated objects take nothing from the radial terms: none are made.
    let terms = STerms::new((0..objects).map(|_| None).collect(), 0.0);
    let fast = FastPath {
        terms: &terms,
        stored: bundle.subsurface(),
        kept: &kept,
        tilt: None,
    };
    assemble_overrides(bundle, overrides, params, Some(&fast), Some(walks))
        .map(|(s, r)| (s.into_csr(), r))
}

/// The objects whose S a change from overrides `before` to `after` rewrites in place
/// ([`rewrite_with_terms`]): `Some` when the two list the same objects in the same order
/// and every material that differs is a translucent profile for a translucent object, or
/// a sheet's profiles for a thin sheet, that `terms` sums (a translucency slider); `None`
/// when anything else differs, so S must be built again.
pub fn changed_profiles(
    before: &[(usize, Material)],
    after: &[(usize, Material)],
    terms: &STerms,
) -> Option<Vec<usize>> {
    if before.len() != after.len() {
        return None;
    }
    let mut changed = Vec::new();
    for ((k, a), (k2, b)) in before.iter().zip(after) {
        if k != k2 {
            return None;
        }
        if a == b {
            continue;
        }
        let sums = match (a, b) {
            (Material::Translucent { .. }, Material::Translucent { .. }) => {
                terms.get(*k, false).is_some()
            }
            (Material::ThinSheet { .. }, Material::ThinSheet { .. }) => {
                terms.get(*k, true).is_some()
            }
            // Re-weighted from the stored walks (an absorption change): the walks fix the
            // pattern.
            (Material::Simulated { .. }, Material::Simulated { .. }) => true,
            _ => false,
        };
        if !sums {
            return None;
        }
        changed.push(*k);
    }
    Some(changed)
}

/// A translucency change written into the last S: `s` was built by
/// [`rebuild_with_terms_and_tilt`] (or this) for overrides that differ from `overrides` only
/// in the objects `changed` ([`changed_profiles`]); their values are summed from `terms`
/// (a simulated object's from its walks, and its rows of the lamps' tilt `tilt` with them
/// when given, [`crate::collimated::Tilt::delta`]) into `s` in place (its pattern holds
/// every stored entry, so no row is built and nothing is copied), every other value stays;
/// `scratch` holds the buffers between changes. Reports cover the objects written. On an
/// error `tilt` is left `None`; [`SError::Pattern`] says to build S again.
#[expect(
    clippy::too_many_arguments,
    reason = "the two matrices, the change, and what their values are summed from"
)]
pub fn rewrite_with_terms(
    bundle: &Bundle,
    s: ValidCsr<[f32; 3]>,
    tilt: &mut Option<ValidCsr<crate::simulated::TiltEntry>>,
    overrides: &[(usize, Material)],
    changed: &[usize],
    params: &SParams,
    terms: &STerms,
    scratch: &mut Scratch,
) -> Result<(ValidCsr<[f32; 3]>, Vec<AssemblyReport>), SError> {
    let mut columns = ColumnScale::default();
    let (s, reports) = rewrite_with_terms_deferred(
        bundle,
        s,
        &mut columns,
        tilt,
        overrides,
        changed,
        params,
        terms,
        scratch,
    )?;
    Ok((columns.apply(s)?, reports))
}

/// [`rewrite_with_terms`] with the energy bound's column factors left out of the values:
/// `s` is S's values and `columns` its column factors ([`ColumnScale`]) as the last change
/// left them, and both come back for the new overrides (the objects not changed keep
/// theirs). What a translucency slider's step runs ([`crate::scene`]).
#[expect(
    clippy::too_many_arguments,
    reason = "the two matrices, the change, and what their values are summed from"
)]
pub fn rewrite_with_terms_deferred(
    bundle: &Bundle,
    mut s: ValidCsr<[f32; 3]>,
    columns: &mut ColumnScale,
    tilt: &mut Option<ValidCsr<crate::simulated::TiltEntry>>,
    overrides: &[(usize, Material)],
    changed: &[usize],
    params: &SParams,
    terms: &STerms,
    scratch: &mut Scratch,
) -> Result<(ValidCsr<[f32; 3]>, Vec<AssemblyReport>), SError> {
    let m = bundle.manifest();
    let g = bundle_geometry(bundle);
    let (materials, stored) = bundle_materials(bundle, overrides)?;
    let mut reports = Vec::with_capacity(changed.len());
    for &k in changed {
        let o = &m.objects[k];
        let object = ObjectMaterial {
            name: &o.name,
            material: &materials[k],
            patches: o.first_patch as usize..(o.first_patch + o.patch_count) as usize,
        };
        if matches!(materials[k], Material::Simulated { .. }) {
            let report;
            (s, report) = write_walks(bundle, s, tilt, &g, &object)?;
            reports.push(report);
            continue;
        }
        let sheet = matches!(materials[k], Material::ThinSheet { .. });
        let t = terms.get(k, sheet).ok_or_else(|| SError::Media {
            object: o.name.clone(),
            why: "it has no radial terms to rewrite S from".into(),
        })?;
        let reach = stored.get(k).copied().unwrap_or(0.0);
        let report;
        (s, report) = write_terms(
            s,
            &g,
            &object,
            t,
            reach,
            m.unit_mm,
            params,
            scratch,
            Some(&mut *columns),
        )?;
        reports.push(report);
    }
    Ok((s, reports))
}

/// Where object `k`'s rows sit in the scene's S and its patches' areas, for a device that
/// writes them from the object's terms ([`ObjectTerms::flatten`],
/// [`ObjectTerms::factors_from_sums`]); `g` is the bundle's geometry ([`bundle_geometry`]).
pub fn object_placement<'g>(
    bundle: &Bundle,
    g: &'g PatchGeometry,
    k: usize,
) -> Option<(&'g [f32], Placement<'g>)> {
    let o = bundle.manifest().objects.get(k)?;
    let start = o.first_patch as usize;
    let area = g.area.get(start..start + o.patch_count as usize)?;
    let at = Placement {
        start,
        n: g.corners.len(),
        nodes: g.nodes.as_ref(),
        defer_bound: false,
    };
    Some((area, at))
}

/// The tables object `k`'s S is summed under with `overrides` applied, as a device reads
/// them: (`same`, `other`), `other` only for a thin sheet (its transmittance). An error
/// when the object's material is summed from no terms (neither translucent nor a thin
/// sheet).
pub fn object_flat_tables(
    bundle: &Bundle,
    overrides: &[(usize, Material)],
    k: usize,
    params: &SParams,
) -> Result<(FlatTable, Option<FlatTable>), SError> {
    let m = bundle.manifest();
    let (materials, stored) = bundle_materials(bundle, overrides)?;
    let o = m.objects.get(k).ok_or_else(|| SError::Media {
        object: format!("#{k}"),
        why: "the bundle has no such object".into(),
    })?;
    let object = ObjectMaterial {
        name: &o.name,
        material: &materials[k],
        patches: o.first_patch as usize..(o.first_patch + o.patch_count) as usize,
    };
    let reach = stored.get(k).copied().unwrap_or(0.0);
    let (same, other, _) = object_tables(&object, reach, m.unit_mm, params)?;
    let flat = |t: &Tabulated| FlatTable::of(&TermTable::new(t));
    Ok((flat(&same), other.as_ref().map(flat)))
}

/// Writes simulated object `o`'s S at its material's absorption, re-weighted from the
/// bundle's walks, into its rows of `s` in place, and its rows of the lamps' tilt `tilt`
/// (taken and given back) in the same pass over the records ([`simulated::write_rows`]).
fn write_walks(
    bundle: &Bundle,
    s: ValidCsr<[f32; 3]>,
    tilt: &mut Option<ValidCsr<crate::simulated::TiltEntry>>,
    g: &PatchGeometry,
    o: &ObjectMaterial<'_>,
) -> Result<(ValidCsr<[f32; 3]>, AssemblyReport), SError> {
    let start = Instant::now();
    let media = |why: &str| SError::Media {
        object: o.name.to_string(),
        why: why.into(),
    };
    let walks = bundle
        .walks()
        .ok_or_else(|| media("no walks were stored for it (precompute it with this material)"))?;
    let medium =
        SimMedium::of(o.material).ok_or_else(|| media("its simulated medium is incomplete"))?;
    let rows = o.patches.clone();
    let mut t = tilt.take();
    let mut written: Result<bool, usize> = Ok(true);
    let mut t_out = None;
    let s = s.rewrite_vouched(rows.clone(), |s_rows| {
        match t.take() {
            Some(tm) => {
                t_out = Some(tm.rewrite_vouched(rows.clone(), |t_rows| {
                    written = simulated::write_rows(
                        &walks,
                        rows.clone(),
                        medium.sigma_a,
                        s_rows,
                        Some(t_rows),
                    );
                    written == Ok(true)
                }));
            }
            None => {
                written = simulated::write_rows(&walks, rows.clone(), medium.sigma_a, s_rows, None)
            }
        }
        written == Ok(true)
    })?;
    if let Err(row) = written {
        return Err(SError::Pattern {
            object: o.name.to_string(),
            row,
        });
    }
    *tilt = t_out.transpose()?;
    let view = s.view();
    let max_column_energy = simulated::max_column_energy(
        rows.clone().map(|j| {
            let (c, v) = view.row(j);
            (j, c.iter().copied().zip(v))
        }),
        &g.area,
    );
    let report = AssemblyReport {
        name: o.name.to_string(),
        radius: 0.0,
        capped_from: None,
        max_column_energy,
        scaled_columns: 0,
        entries: (view.row_ptr()[rows.end] - view.row_ptr()[rows.start]),
        links: 0,
        seconds: start.elapsed().as_secs_f64(),
    };
    Ok((s, report))
}

/// Stage 2 on a bundle with `overrides` applied to its materials.
fn assemble_overrides(
    bundle: &Bundle,
    overrides: &[(usize, Material)],
    params: &SParams,
    fast: Option<&FastPath<'_>>,
    walks: Option<&WalksView<'_>>,
) -> Result<(ValidCsr<[f32; 3]>, Vec<AssemblyReport>), SError> {
    let m = bundle.manifest();
    let g = bundle_geometry(bundle);
    let (materials, stored) = match walks {
        None => bundle_materials(bundle, overrides)?,
        // The overridden objects walked again in their new media: nothing to check them
        // against.
        Some(_) => {
            let (mut materials, stored) = bundle_materials(bundle, &[])?;
            for (k, mat) in overrides {
                materials[*k] = mat.clone();
            }
            (materials, stored)
        }
    };
    let objects: Vec<ObjectMaterial<'_>> = m
        .objects
        .iter()
        .zip(&materials)
        .map(|(o, mat)| ObjectMaterial {
            name: &o.name,
            material: mat,
            patches: o.first_patch as usize..(o.first_patch + o.patch_count) as usize,
        })
        .collect();
    let material_len: &[MediaLen] =
        bytemuck::try_cast_slice(bundle.f32s(arrays::DIST_MATERIAL_LEN)).unwrap_or(&[]);
    let stored_walks = bundle.walks();
    let walks = walks.or(stored_walks.as_ref());
    assemble_scene(
        &g,
        &objects,
        bundle.distances(),
        material_len,
        bundle.u32s(arrays::PATCH_MATERIAL),
        bundle.distance_kinds(),
        bundle.distance_spreads(),
        &stored,
        m.unit_mm,
        params,
        fast,
        walks,
    )
}
