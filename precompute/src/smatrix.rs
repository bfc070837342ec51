//! The scene's S in two stages, so translucency can change without touching geometry.
//!
//! 1. [`scene_distances`] (precompute, geometry only): for every translucent object, the
//!    optical path r_ij between its patches ([`voxel::optical_distances`]), kept out to
//!    `radius_margin` × the built profile's truncation radius, so that a more translucent
//!    profile later still finds its pairs. Stored in the bundle. A thin sheet's distances
//!    are geodesics along it, each with a kind — same side or other side — stored as
//!    `dist_kind` ([`sheet::sheet_distances`]).
//! 2. [`assemble_scene`] (precompute *and* every translucency change): S from the stored
//!    distances and the materials — [`subsurface::assemble`] per translucent object,
//!    [`sheet::assemble`] per thin sheet (R by same-side, T by other-side distances), ρ on the
//!    diagonal of opaque patches, nothing for emitters.
//!
//! [`rebuild_from_bundle`] runs stage 2 on a mapped bundle with material overrides: the
//! library call behind a translucency slider.
//!
//! Heterogeneous objects ([`crate::hetero`]) take both stages too: stage 1 also records, per
//! stored pair, the length of the path in each medium (`dist_material_len` in the bundle,
//! [`SceneMedia`] saying where the media are), out to the largest of the media's truncation
//! radii; stage 2 combines the media's profiles by eq. 9 from those lengths, so changing a
//! medium's profile needs no geometry work either (its pattern must stay as built).

use std::ops::Range;
use std::time::Instant;

use glam::Vec3;
use thiserror::Error;
use translux_proto::bundle::{Bundle, SubsurfaceObject, arrays};
use translux_proto::csr::CsrView;
use translux_proto::scene::{Material, Profile};

use crate::hetero::{self, MEDIA, MediaLen, PatternFrame};
use crate::profile::{ProfileError, ProfileEval};
use crate::sheet::{self, SheetError};
use crate::subsurface::{self, DistanceView, ObjectPatches, SubsurfaceParams, Tabulated};
use crate::voxel::{self, VoxelError, VoxelParams};

/// Settings of both stages, defaults on each field.
#[derive(Debug, Clone, Copy)]
pub struct SParams {
    /// S keeps pairs out to the radius beyond which the profile carries less than this
    /// fraction of its energy. Default 1e-3.
    pub truncation_energy: f32,
    /// Distances are stored out to this many times the built profile's truncation radius,
    /// so translucency can grow that much without new geometry work. Default 2.
    pub radius_margin: f32,
    pub quadrature: SubsurfaceParams,
    pub voxels: VoxelParams,
}

impl Default for SParams {
    fn default() -> Self {
        Self {
            truncation_energy: 1e-3,
            radius_margin: 2.0,
            quadrature: SubsurfaceParams::default(),
            voxels: VoxelParams::default(),
        }
    }
}

/// Why S could not be built.
#[derive(Debug, Error)]
pub enum SError {
    #[error("object '{object}': {error}")]
    Profile { object: String, error: ProfileError },
    #[error(transparent)]
    Voxel(#[from] VoxelError),
    #[error(transparent)]
    Sheet(#[from] SheetError),
    /// A heterogeneous material that the stored per-medium lengths cannot serve.
    #[error("object '{object}': {why}")]
    Media { object: String, why: String },
}

/// Where the media of the scene's heterogeneous objects are (stage 1), and which medium each
/// patch is in (stage 2's self terms; `patch_material` in the bundle).
#[derive(Debug, Clone, Default)]
pub struct SceneMedia {
    /// Per patch (global): its medium ([`hetero::patch_media`]); 0 outside heterogeneous
    /// objects. May be empty when the scene has no heterogeneous object.
    pub patch_material: Vec<u32>,
    /// Per object: the frame its pattern is laid in (identity when missing).
    pub frames: Vec<PatternFrame>,
}

/// The per-patch geometry S needs (one scene's worth, global indices).
#[derive(Debug, Clone, Default)]
pub struct PatchGeometry {
    pub corners: Vec<[Vec3; 3]>,
    pub centroid: Vec<Vec3>,
    pub normal: Vec<Vec3>,
    pub area: Vec<f32>,
    pub size: Vec<f32>,
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

/// A matrix as owned CSR arrays (global indices).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CsrOwned<T> {
    pub row_ptr: Vec<u64>,
    pub col: Vec<u32>,
    pub val: Vec<T>,
}

impl<T: Copy> CsrOwned<T> {
    fn from_rows(rows: Vec<Vec<(u32, T)>>) -> Self {
        let mut m = CsrOwned {
            row_ptr: vec![0],
            col: Vec::new(),
            val: Vec::new(),
        };
        for row in rows {
            for (c, v) in row {
                m.col.push(c);
                m.val.push(v);
            }
            m.row_ptr.push(m.col.len() as u64);
        }
        m
    }
}

/// An object as S sees it: its material and patch range.
#[derive(Debug, Clone)]
pub struct ObjectMaterial<'a> {
    pub name: &'a str,
    pub material: &'a Material,
    pub patches: Range<usize>,
}

/// How stage 1 went for one translucent object.
#[derive(Debug, Clone, PartialEq)]
pub struct DistanceReport {
    pub name: String,
    pub method: String,
    pub radius: f32,
    pub voxels: u64,
    pub interior_voxels: u64,
    pub voxel_size: f32,
    pub warning: Option<String>,
    pub seconds: f64,
}

/// Straight-line distances between centroids within `r_max`: the fallback when an object
/// has no interior to trace paths through. O(n²), only reached for broken meshes.
fn euclidean_rows(c: &[Vec3], r_max: f32) -> Vec<Vec<(u32, f32)>> {
    (0..c.len())
        .map(|i| {
            c.iter()
                .enumerate()
                .filter(|&(j, cj)| j != i && c[i].distance(*cj) <= r_max)
                .map(|(j, cj)| (j as u32, c[i].distance(*cj)))
                .collect()
        })
        .collect()
}

/// The object's patches as `subsurface` and `sheet` take them.
fn object_patches(g: &PatchGeometry, r: Range<usize>) -> ObjectPatches<'_> {
    ObjectPatches {
        corners: &g.corners[r.clone()],
        centroid: &g.centroid[r.clone()],
        normal: &g.normal[r.clone()],
        area: &g.area[r.clone()],
        size: &g.size[r],
    }
}

/// What [`scene_distances`] returns: the distances (CSR), their per-medium lengths and their
/// kinds (both aligned with the CSR entries), and a report per translucent object.
pub type SceneDistances = (CsrOwned<f32>, Vec<MediaLen>, Vec<u32>, Vec<DistanceReport>);

/// Bytes the subsurface stage holds per stored path at its peak, counted from its buffers:
/// the path as a row entry (column and length, 8) and its kind (4) while the rows are
/// built, the same in the CSR they become (12), S's column and RGB value (16) and the
/// assembly's row buffers (about as much again), rounded up. With
/// [`estimate_paths`]'s upper bound this refused the unsimplified bunny as marble
/// (69k patches: ~1.5e9 paths, ~93 GiB) at once; it used to run for 12 minutes and be
/// killed by the kernel at 24 GB.
pub const PEAK_BYTES_PER_PATH: u64 = 64;

/// An upper bound on the paths stage 1 will store, per translucent (or heterogeneous)
/// object, before any of it runs: each object's patch pairs whose centroids lie within
/// its radius (an optical path is never shorter than the straight line), counted on up to
/// 256 evenly spaced rows. `(object name, paths, radius)` in scene units. Thin sheets are
/// not counted (their paths run along the sheet, two sides, far fewer).
pub fn estimate_paths(
    centroid: &[Vec3],
    objects: &[ObjectMaterial<'_>],
    unit_mm: f64,
    params: &SParams,
) -> Result<Vec<(String, u64, f32)>, SError> {
    use rayon::prelude::*;
    let mut out = Vec::new();
    for o in objects {
        let Some(radius) = stored_radius(o, unit_mm, params)? else {
            continue;
        };
        let cen = &centroid[o.patches.clone()];
        let n = cen.len();
        if n == 0 {
            continue;
        }
        let rows = n.min(256);
        let r2 = radius * radius;
        let near: u64 = (0..rows)
            .into_par_iter()
            .map(|k| {
                let c = cen[k * n / rows];
                cen.iter().filter(|p| p.distance_squared(c) <= r2).count() as u64
            })
            .sum();
        let paths = (near as f64 / rows as f64 * n as f64) as u64;
        out.push((o.name.to_string(), paths, radius));
    }
    Ok(out)
}

/// How far stage 1 stores paths inside a translucent or heterogeneous object (scene
/// units): the profile's truncation radius with the margin; a heterogeneous object keeps
/// pairs out to the largest of its media's radii. `None` for other materials.
fn stored_radius(
    o: &ObjectMaterial<'_>,
    unit_mm: f64,
    params: &SParams,
) -> Result<Option<f32>, SError> {
    let profiles: &[Profile] = match o.material {
        Material::Translucent { profile } => std::slice::from_ref(profile),
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

/// Stage 1: optical distances of every translucent object (global indices; rows of other
/// patches empty). `triangles[o]` are object o's source triangles (for the inside test).
/// Also returns the kind of every stored distance (`dist_kind`: [`sheet::KIND_OPPOSITE`]
/// for a thin sheet's other side, else [`sheet::KIND_SAME`]), aligned with the CSR entries.
/// Also returns the per-medium lengths of every stored distance (aligned with the CSR
/// entries; all 0 outside heterogeneous objects).
pub fn scene_distances(
    g: &PatchGeometry,
    objects: &[ObjectMaterial<'_>],
    triangles: &[&[[Vec3; 3]]],
    media: &SceneMedia,
    unit_mm: f64,
    params: &SParams,
) -> Result<SceneDistances, SError> {
    let mut rows: Vec<Vec<(u32, f32)>> = vec![Vec::new(); g.corners.len()];
    let mut kinds: Vec<Vec<u32>> = vec![Vec::new(); g.corners.len()];
    let mut lens: Vec<Vec<MediaLen>> = vec![Vec::new(); g.corners.len()];
    let mut reports = Vec::new();
    for (k, (o, tris)) in objects.iter().zip(triangles).enumerate() {
        if let Material::ThinSheet {
            reflectance,
            transmittance,
            thickness_mm,
        } = o.material
        {
            // Geodesics along the sheet, each with its side kind.
            let r = o.patches.clone();
            let (local, report) = sheet::object_distances(
                o.name,
                (reflectance, transmittance, *thickness_mm),
                object_patches(g, r.clone()),
                unit_mm,
                params,
            )?;
            for (i, row) in local.into_iter().enumerate() {
                rows[r.start + i] = row.iter().map(|e| (r.start as u32 + e.0, e.1)).collect();
                kinds[r.start + i] = row.iter().map(|e| e.2).collect();
            }
            reports.push(report);
            continue;
        }
        let Some(radius) = stored_radius(o, unit_mm, params)? else {
            continue;
        };
        let t = Instant::now();
        let r = o.patches.clone();
        let (cen, nor) = (&g.centroid[r.clone()], &g.normal[r.clone()]);
        let local_media = media.patch_material.get(r.clone()).unwrap_or(&[]);
        let frame = media.frames.get(k).copied().unwrap_or_default();
        let field = hetero::medium_field(o.material, frame, local_media);
        if matches!(field, Some(hetero::MediumField::PerPatch(m)) if m.len() != r.len()) {
            return Err(SError::Media {
                object: o.name.to_string(),
                why: "by_obj_material needs the medium of every patch".into(),
            });
        }
        let mut local_lens: Vec<Vec<MediaLen>> = Vec::new();
        let (local, stats, warning) = match voxel::optical_distances_media(
            o.name,
            tris,
            cen,
            nor,
            radius,
            &params.voxels,
            field.as_ref(),
        ) {
            Ok((d, s)) => {
                if field.is_some() {
                    local_lens = (0..r.len())
                        .map(|i| {
                            let (a, b) = (d.row_ptr[i] as usize, d.row_ptr[i + 1] as usize);
                            d.material_len[a..b].to_vec()
                        })
                        .collect();
                }
                let rows: Vec<Vec<(u32, f32)>> = (0..r.len())
                    .map(|i| {
                        let (a, b) = (d.row_ptr[i] as usize, d.row_ptr[i + 1] as usize);
                        d.col[a..b]
                            .iter()
                            .copied()
                            .zip(d.dist[a..b].iter().copied())
                            .collect()
                    })
                    .collect();
                (rows, Some(s), None)
            }
            Err(VoxelError::NoInterior { .. }) => {
                let rows = euclidean_rows(cen, radius);
                if let Some(f) = &field {
                    local_lens = rows
                        .iter()
                        .enumerate()
                        .map(|(i, row)| {
                            row.iter()
                                .map(|&(j, d)| {
                                    f.straight(i, j as usize, cen[i], cen[j as usize], d)
                                })
                                .collect()
                        })
                        .collect();
                }
                (
                    rows,
                    None,
                    Some(format!(
                        "'{}' has no interior (open or broken mesh): straight-line distances used",
                        o.name
                    )),
                )
            }
            Err(e) => return Err(e.into()),
        };
        let base = r.start as u32;
        for (i, row) in local.into_iter().enumerate() {
            rows[r.start + i] = row.into_iter().map(|(j, d)| (base + j, d)).collect();
        }
        for (i, l) in local_lens.into_iter().enumerate() {
            lens[r.start + i] = l;
        }
        reports.push(DistanceReport {
            name: o.name.to_string(),
            method: match stats.map(|s| s.method) {
                Some(voxel::Method::Voxel) => "voxel".into(),
                Some(voxel::Method::Euclidean) => "euclidean".into(),
                None => "euclidean (fallback)".into(),
            },
            radius,
            voxels: stats.map_or(0, |s| s.voxels as u64),
            interior_voxels: stats.map_or(0, |s| s.interior_voxels as u64),
            voxel_size: stats.map_or(0.0, |s| s.voxel_size),
            warning,
            seconds: t.elapsed().as_secs_f64(),
        });
    }
    // Per-medium lengths aligned with the CSR entries (zeros for homogeneous rows).
    let mut material_len = Vec::new();
    for (row, l) in rows.iter().zip(&lens) {
        if l.len() == row.len() {
            material_len.extend_from_slice(l);
        } else {
            material_len.extend(std::iter::repeat_n([0.0; MEDIA], row.len()));
        }
    }
    // Kinds aligned with the CSR entries (same side / interior unless a sheet said otherwise).
    let mut kind = Vec::new();
    for (row, kd) in rows.iter().zip(&kinds) {
        if kd.len() == row.len() {
            kind.extend_from_slice(kd);
        } else {
            kind.extend(std::iter::repeat_n(sheet::KIND_SAME, row.len()));
        }
    }
    Ok((CsrOwned::from_rows(rows), material_len, kind, reports))
}

/// How stage 2 went for one translucent object.
#[derive(Debug, Clone, PartialEq)]
pub struct AssemblyReport {
    pub name: String,
    /// The radius S used (the profile's truncation radius, capped by the stored distances).
    pub radius: f32,
    /// Set when the profile wanted more radius than the stored distances reach.
    pub capped_from: Option<f32>,
    pub max_column_energy: f32,
    pub scaled_columns: u64,
    pub seconds: f64,
}

/// Stage 2: S from stored distances. `stored_radius[o]` is how far object o's distances
/// reach (0 for non-translucent objects). `material_len` (aligned with the entries of
/// `distances`) and `patch_material` are stage 1's per-medium lengths and patch media; they
/// are read for heterogeneous objects only. `dist_kind` (aligned likewise; missing entries
/// read as same side) is read for thin sheets only.
#[allow(clippy::too_many_arguments)]
pub fn assemble_scene(
    g: &PatchGeometry,
    objects: &[ObjectMaterial<'_>],
    distances: CsrView<'_, f32>,
    material_len: &[MediaLen],
    patch_material: &[u32],
    dist_kind: &[u32],
    stored_radius: &[f32],
    unit_mm: f64,
    params: &SParams,
) -> Result<(CsrOwned<[f32; 3]>, Vec<AssemblyReport>), SError> {
    let n = g.corners.len();
    let mut rows: Vec<Vec<(u32, [f32; 3])>> = vec![Vec::new(); n];
    let mut reports = Vec::new();
    for (k, o) in objects.iter().enumerate() {
        let r = o.patches.clone();
        match o.material {
            Material::Diffuse { albedo } => {
                for j in r {
                    rows[j] = vec![(j as u32, *albedo)];
                }
            }
            Material::Emitter { .. } => {}
            Material::ThinSheet {
                reflectance,
                transmittance,
                ..
            } => {
                let (s, report) = sheet::object_s(
                    o.name,
                    (reflectance, transmittance),
                    object_patches(g, r.clone()),
                    r.clone(),
                    distances,
                    dist_kind,
                    stored_radius.get(k).copied().unwrap_or(0.0),
                    unit_mm,
                    params,
                )?;
                for (j, row) in s.rows.into_iter().enumerate() {
                    rows[r.start + j] = row
                        .into_iter()
                        .map(|(i, v)| (r.start as u32 + i, v))
                        .collect();
                }
                reports.push(report);
            }
            Material::Heterogeneous { materials, .. } => {
                let t = Instant::now();
                let object = || o.name.to_string();
                if material_len.len() != distances.nnz() || patch_material.len() != n {
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
                    let eval = ProfileEval::new(&materials[d], unit_mm).map_err(|error| {
                        SError::Profile {
                            object: object(),
                            error,
                        }
                    })?;
                    wanted = wanted.max(eval.truncation_radius(params.truncation_energy));
                    evals.push(eval);
                }
                let reach = stored_radius.get(k).copied().unwrap_or(0.0);
                let radius = wanted.min(reach.max(f32::MIN_POSITIVE));
                let capped_from = (wanted > reach * (1.0 + 1e-6)).then_some(wanted);
                // Local CSR of this object's block, with its per-medium lengths.
                let base = r.start as u64;
                let ptr = distances.row_ptr();
                let mut row_ptr = vec![0u64];
                let (mut col, mut dist, mut lens) = (Vec::new(), Vec::new(), Vec::new());
                for i in r.clone() {
                    let (cols, ds) = distances.row(i);
                    for (e, (&j, &d)) in cols.iter().zip(ds).enumerate() {
                        if (j as u64) >= base && (j as u64) < base + r.len() as u64 && d < radius {
                            col.push((j as u64 - base) as u32);
                            dist.push(d);
                            lens.push(material_len[ptr[i] as usize + e]);
                        }
                    }
                    row_ptr.push(col.len() as u64);
                }
                let tabs: Vec<Tabulated> = evals
                    .iter()
                    .map(|e| Tabulated::new(e, radius, 4096))
                    .collect();
                let op = ObjectPatches {
                    corners: &g.corners[r.clone()],
                    centroid: &g.centroid[r.clone()],
                    normal: &g.normal[r.clone()],
                    area: &g.area[r.clone()],
                    size: &g.size[r.clone()],
                };
                let dv = DistanceView {
                    row_ptr: &row_ptr,
                    col: &col,
                    dist: &dist,
                };
                let media = &patch_material[r.clone()];
                let s = hetero::assemble(op, dv, &lens, media, &map, &tabs, &params.quadrature);
                for (j, row) in s.rows.into_iter().enumerate() {
                    rows[r.start + j] = row
                        .into_iter()
                        .map(|(i, v)| (r.start as u32 + i, v))
                        .collect();
                }
                reports.push(AssemblyReport {
                    name: o.name.to_string(),
                    radius,
                    capped_from,
                    max_column_energy: s.report.max_column,
                    scaled_columns: s.report.scaled_columns as u64,
                    seconds: t.elapsed().as_secs_f64(),
                });
            }
            Material::Translucent { profile } => {
                let t = Instant::now();
                let reach = stored_radius.get(k).copied().unwrap_or(0.0);
                let (tab, capped_from) =
                    translucent_table(o.name, profile, reach, unit_mm, params)?;
                let radius = tab.r_max();
                // Local CSR view of this object's block of the distances.
                let base = r.start as u64;
                let mut row_ptr = vec![0u64];
                let (mut col, mut dist) = (Vec::new(), Vec::new());
                for i in r.clone() {
                    let (cols, ds) = distances.row(i);
                    for (&j, &d) in cols.iter().zip(ds) {
                        if (j as u64) >= base && (j as u64) < base + r.len() as u64 && d < radius {
                            col.push((j as u64 - base) as u32);
                            dist.push(d);
                        }
                    }
                    row_ptr.push(col.len() as u64);
                }
                let op = ObjectPatches {
                    corners: &g.corners[r.clone()],
                    centroid: &g.centroid[r.clone()],
                    normal: &g.normal[r.clone()],
                    area: &g.area[r.clone()],
                    size: &g.size[r.clone()],
                };
                let dv = DistanceView {
                    row_ptr: &row_ptr,
                    col: &col,
                    dist: &dist,
                };
                let s = subsurface::assemble(op, dv, &tab, &params.quadrature);
                for (j, row) in s.rows.into_iter().enumerate() {
                    rows[r.start + j] = row
                        .into_iter()
                        .map(|(i, v)| (r.start as u32 + i, v))
                        .collect();
                }
                reports.push(AssemblyReport {
                    name: o.name.to_string(),
                    radius,
                    capped_from,
                    max_column_energy: s.report.max_column,
                    scaled_columns: s.report.scaled_columns as u64,
                    seconds: t.elapsed().as_secs_f64(),
                });
            }
        }
    }
    Ok((CsrOwned::from_rows(rows), reports))
}

/// A homogeneous translucent object's profile tabulated out to its truncation radius,
/// capped by `reach` (how far its stored distances go), and the radius wanted when the cap
/// bites.
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
    let wanted = eval.truncation_radius(params.truncation_energy);
    let radius = wanted.min(reach.max(f32::MIN_POSITIVE));
    let capped_from = (wanted > reach * (1.0 + 1e-6)).then_some(wanted);
    Ok((Tabulated::new(&eval, radius, 4096), capped_from))
}

/// The manifest's per-object record, from both stages' reports.
pub fn subsurface_objects(
    d: &[DistanceReport],
    a: &[AssemblyReport],
    energy: f32,
) -> Vec<SubsurfaceObject> {
    d.iter()
        .zip(a)
        .map(|(d, a)| SubsurfaceObject {
            name: d.name.clone(),
            method: d.method.clone(),
            truncation_radius: a.radius,
            distance_radius: d.radius,
            truncation_energy: energy,
            voxels: d.voxels,
            interior_voxels: d.interior_voxels,
            voxel_size: d.voxel_size,
            max_column_energy: a.max_column_energy,
            scaled_columns: a.scaled_columns,
            warning: d.warning.clone(),
            seconds: d.seconds + a.seconds,
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
    let materials: Vec<Material> = m
        .objects
        .iter()
        .enumerate()
        .map(|(k, o)| {
            overrides
                .iter()
                .find(|(i, _)| *i == k)
                .map(|(_, mat)| mat.clone())
                .unwrap_or_else(|| o.material.clone())
        })
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
        let Material::Heterogeneous { materials, pattern } = mat else {
            continue;
        };
        let Some(built) = m.objects.get(*k) else {
            continue;
        };
        let same = matches!(&built.material, Material::Heterogeneous { materials: bm, pattern: bp }
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

/// The bundle's patch geometry as S assembly takes it.
pub fn bundle_geometry(bundle: &Bundle) -> PatchGeometry {
    PatchGeometry::from_corners(
        bundle
            .patch_corners()
            .iter()
            .map(|c| c.map(Vec3::from))
            .collect(),
    )
}

/// Rebuilds S for a bundle with some objects' materials replaced (by object index), from
/// the stored distances: no voxels, no rays. Objects not overridden keep their material.
pub fn rebuild_from_bundle(
    bundle: &Bundle,
    overrides: &[(usize, Material)],
    params: &SParams,
) -> Result<(CsrOwned<[f32; 3]>, Vec<AssemblyReport>), SError> {
    let m = bundle.manifest();
    let g = bundle_geometry(bundle);
    let (materials, stored) = bundle_materials(bundle, overrides)?;
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
    assemble_scene(
        &g,
        &objects,
        bundle.distances(),
        material_len,
        bundle.u32s(arrays::PATCH_MATERIAL),
        bundle.distance_kinds(),
        &stored,
        m.unit_mm,
        params,
    )
}
