//! Stage 1 of S (geometry only): for every translucent object, the optical path r_ij
//! between its patches ([`voxel::optical_distances`]), kept out to `radius_margin` × the
//! built profile's truncation radius (`translux_engine::smatrix::stored_radius`), so that a
//! more translucent profile later still finds its pairs. Stored in the bundle. A thin
//! sheet's distances are geodesics along it, each with a kind — same side or other side —
//! stored as `dist_kind` ([`sheet::sheet_distances`]). Heterogeneous objects ([`hetero`])
//! also record, per stored pair, the length of the path in each medium
//! (`dist_material_len`, [`SceneMedia`] saying where the media are), out to the largest of
//! the media's truncation radii.
//!
//! Stage 2 — S from these distances and the materials, at precompute time and for every
//! translucency change — is `translux_engine::smatrix`.
//!
//! In: patch geometry, each object's material, patch range and source triangles. Out: the
//! distances as CSR with their kinds and per-medium lengths, and a report per object;
//! [`estimate_paths`] bounds their number before any of it runs.

use std::time::Instant;

use glam::Vec3;
use thiserror::Error;
use translux_engine::hetero::{MEDIA, MediaLen};
use translux_engine::sheet::{KIND_SAME, SheetError, profile_eval};
use translux_engine::smatrix::{
    AssemblyReport, ObjectMaterial, PatchGeometry, SError, SParams, object_patches, stored_radius,
};
use translux_engine::subsurface::ObjectPatches;
use translux_proto::bundle::SubsurfaceObject;
use translux_proto::csr::Csr;
use translux_proto::scene::{Material, Profile};

use crate::hetero::{self, PatternFrame};
use crate::sheet;
use crate::voxel::{self, VoxelError, VoxelParams};

/// Why stage 1 failed: a profile, sheet or media problem ([`SError`]) or the voxel grid.
#[derive(Debug, Error)]
pub enum DistanceError {
    #[error(transparent)]
    S(#[from] SError),
    #[error(transparent)]
    Voxel(#[from] VoxelError),
}

impl From<SheetError> for DistanceError {
    fn from(e: SheetError) -> Self {
        DistanceError::S(SError::Sheet(e))
    }
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
    /// Taken from a [`DistanceCache`]: the object only moved rigidly since the frame that
    /// computed them.
    pub reused: bool,
}

/// The optical distances of homogeneous translucent objects, kept across the frames of an
/// animation ([`crate::sequence`]). An object that only moved rigidly — every patch with
/// the same area, the same distances and normal angles between sampled patch pairs, and
/// the same stored radius — has the same distances between its patches (its patches come
/// out of the subdivision in the same order), so a later frame takes them from here
/// instead of tracing paths through a new voxel grid. (The grid is laid along the world's
/// axes, so a fresh computation of a turned object differs by the grid's discretisation;
/// the reused one is the same in every frame.)
#[derive(Default)]
pub struct DistanceCache {
    objects: std::sync::Mutex<std::collections::HashMap<String, CachedDistances>>,
}

impl std::fmt::Debug for DistanceCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("DistanceCache")
    }
}

struct CachedDistances {
    shape: RigidShape,
    rows: Vec<Vec<(u32, f32)>>,
    report: DistanceReport,
}

/// What stays the same when an object moves rigidly: its radius, patch areas, and the
/// distance and normal angle between patches `i` and `(7919 i + 13) mod n`.
struct RigidShape {
    radius: f32,
    area: Vec<f32>,
    probe: Vec<(f32, f32)>,
}

impl RigidShape {
    fn of(g: &PatchGeometry, r: std::ops::Range<usize>, radius: f32) -> Self {
        let n = r.len();
        let (c, nor) = (&g.centroid[r.clone()], &g.normal[r.clone()]);
        let probe = (0..n)
            .map(|i| {
                let j = (7919 * i + 13) % n;
                (c[i].distance(c[j]), nor[i].dot(nor[j]))
            })
            .collect();
        RigidShape {
            radius,
            area: g.area[r].to_vec(),
            probe,
        }
    }

    /// The same object moved rigidly (float rounding of the transform aside).
    fn matches(&self, o: &RigidShape) -> bool {
        let scale = self.probe.iter().fold(1e-12f32, |m, p| m.max(p.0));
        let amax = self.area.iter().fold(1e-30f32, |m, &a| m.max(a));
        self.radius == o.radius
            && self.area.len() == o.area.len()
            && self
                .area
                .iter()
                .zip(&o.area)
                .all(|(a, b)| (a - b).abs() <= 1e-4 * amax)
            && self
                .probe
                .iter()
                .zip(&o.probe)
                .all(|(a, b)| (a.0 - b.0).abs() <= 1e-4 * scale && (a.1 - b.1).abs() <= 1e-4)
    }
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

/// What [`scene_distances`] returns.
#[derive(Debug)]
pub struct SceneDistances {
    /// The distances (CSR, global indices).
    pub dist: Csr<f32>,
    /// Their per-medium lengths, aligned with the CSR entries.
    pub material_len: Vec<MediaLen>,
    /// Their kinds, aligned with the CSR entries.
    pub kind: Vec<u32>,
    /// A report per translucent object.
    pub reports: Vec<DistanceReport>,
    /// Per object: the distances on demand of an object asked for that way (its rows in
    /// `dist` are empty; [`crate::slinks::collapse`] traces what its cut uses).
    pub on_demand: Vec<Option<voxel::Oracle>>,
}

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

/// Stage 1: optical distances of every translucent object (global indices; rows of other
/// patches empty). `triangles[o]` are object o's source triangles (for the inside test).
/// Also returns the kind of every stored distance (`dist_kind`: [`sheet::KIND_OPPOSITE`]
/// for a thin sheet's other side, else [`KIND_SAME`]), aligned with the CSR entries.
/// Also returns the per-medium lengths of every stored distance (aligned with the CSR
/// entries; all 0 outside heterogeneous objects).
/// With a `cache`, a homogeneous translucent object that only moved rigidly since a frame
/// that stored its distances there takes them from it ([`DistanceReport::reused`]); every
/// one computed here is stored in it.
/// A homogeneous translucent object with `on_demand[k]` set gets no pairs: its grid is
/// prepared ([`voxel::Oracle`]) for a hierarchical S's cut to trace only the distances it
/// uses.
#[allow(clippy::too_many_arguments)]
pub fn scene_distances(
    g: &PatchGeometry,
    objects: &[ObjectMaterial<'_>],
    triangles: &[&[[Vec3; 3]]],
    media: &SceneMedia,
    unit_mm: f64,
    params: &SParams,
    voxels: &VoxelParams,
    cache: Option<&DistanceCache>,
    on_demand: &[bool],
) -> Result<SceneDistances, DistanceError> {
    let mut oracles: Vec<Option<voxel::Oracle>> = (0..objects.len()).map(|_| None).collect();
    let mut rows: Vec<Vec<(u32, f32)>> = vec![Vec::new(); g.corners.len()];
    let mut kinds: Vec<Vec<u32>> = vec![Vec::new(); g.corners.len()];
    let mut lens: Vec<Vec<MediaLen>> = vec![Vec::new(); g.corners.len()];
    let mut reports = Vec::new();
    for (k, (o, tris)) in objects.iter().zip(triangles).enumerate() {
        if let Material::ThinSheet {
            reflectance,
            transmittance,
            thickness_mm,
            ..
        } = o.material
        {
            // Geodesics along the sheet, each with its side kind.
            let r = o.patches.clone();
            let (local, report) = sheet_object_distances(
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
            }
            .into());
        }
        if field.is_none()
            && matches!(o.material, Material::Translucent { .. })
            && on_demand.get(k).copied().unwrap_or(false)
        {
            let (oracle, warning) = oracle_of(o.name, tris, cen, nor, radius, voxels)?;
            let stats = oracle.stats();
            reports.push(DistanceReport {
                name: o.name.to_string(),
                method: method_name(Some(stats.method), warning.is_some()),
                radius,
                voxels: stats.voxels as u64,
                interior_voxels: stats.interior_voxels as u64,
                voxel_size: stats.voxel_size,
                warning,
                seconds: t.elapsed().as_secs_f64(),
                reused: false,
            });
            oracles[k] = Some(oracle);
            continue;
        }
        // A homogeneous object seen before in another pose: its distances again.
        let rigid = (field.is_none() && matches!(o.material, Material::Translucent { .. }))
            .then_some(cache)
            .flatten()
            .map(|c| (c, RigidShape::of(g, r.clone(), radius)));
        if let Some((c, shape)) = &rigid {
            let objects = c.objects.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(hit) = objects.get(o.name).filter(|h| h.shape.matches(shape)) {
                let base = r.start as u32;
                for (i, row) in hit.rows.iter().enumerate() {
                    rows[r.start + i] = row.iter().map(|&(j, d)| (base + j, d)).collect();
                }
                reports.push(DistanceReport {
                    seconds: t.elapsed().as_secs_f64(),
                    reused: true,
                    ..hit.report.clone()
                });
                continue;
            }
        }
        let mut local_lens: Vec<Vec<MediaLen>> = Vec::new();
        let (local, stats, warning) = match voxel::optical_distances_media(
            o.name,
            tris,
            cen,
            nor,
            radius,
            voxels,
            field.as_ref(),
        ) {
            Ok((d, s)) => {
                if field.is_some() {
                    local_lens = (0..r.len())
                        .map(|i| {
                            let (a, b) = (d.csr.row_ptr[i] as usize, d.csr.row_ptr[i + 1] as usize);
                            d.material_len[a..b].to_vec()
                        })
                        .collect();
                }
                let rows: Vec<Vec<(u32, f32)>> = (0..r.len())
                    .map(|i| {
                        let (cols, dist) = d.row(i);
                        cols.iter().copied().zip(dist.iter().copied()).collect()
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
                (rows, None, Some(no_interior(o.name)))
            }
            Err(e) => return Err(e.into()),
        };
        let base = r.start as u32;
        let report = DistanceReport {
            name: o.name.to_string(),
            method: method_name(stats.map(|s| s.method), stats.is_none()),
            radius,
            voxels: stats.map_or(0, |s| s.voxels as u64),
            interior_voxels: stats.map_or(0, |s| s.interior_voxels as u64),
            voxel_size: stats.map_or(0.0, |s| s.voxel_size),
            warning,
            seconds: t.elapsed().as_secs_f64(),
            reused: false,
        };
        if let Some((c, shape)) = rigid {
            c.objects.lock().unwrap_or_else(|e| e.into_inner()).insert(
                o.name.to_string(),
                CachedDistances {
                    shape,
                    rows: local.clone(),
                    report: report.clone(),
                },
            );
        }
        for (i, row) in local.into_iter().enumerate() {
            rows[r.start + i] = row.into_iter().map(|(j, d)| (base + j, d)).collect();
        }
        for (i, l) in local_lens.into_iter().enumerate() {
            lens[r.start + i] = l;
        }
        reports.push(report);
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
            kind.extend(std::iter::repeat_n(KIND_SAME, row.len()));
        }
    }
    let n = rows.len();
    let d = Csr::from_rows(n, rows).map_err(SError::Matrix)?;
    Ok(SceneDistances {
        dist: d,
        material_len,
        kind,
        reports,
        on_demand: oracles,
    })
}

/// The distances on demand of one object ([`voxel::Oracle`]): traced through its voxel
/// grid, or straight lines (with a warning) when it has no interior.
fn oracle_of(
    name: &str,
    tris: &[[Vec3; 3]],
    cen: &[Vec3],
    nor: &[Vec3],
    radius: f32,
    voxels: &VoxelParams,
) -> Result<(voxel::Oracle, Option<String>), DistanceError> {
    match voxel::Oracle::new(name, tris, cen, nor, radius, voxels) {
        Ok(oracle) => Ok((oracle, None)),
        Err(VoxelError::NoInterior { .. }) => Ok((
            voxel::Oracle::straight(cen, radius),
            Some(no_interior(name)),
        )),
        Err(e) => Err(e.into()),
    }
}

/// Only the distances on demand of [`scene_distances`] (a shard's share of a hierarchical
/// S needs nothing else): per object, the oracle `scene_distances` would give it, and how
/// far each object's distances reach (0 where it stores none).
#[allow(clippy::too_many_arguments)]
pub fn on_demand_oracles(
    g: &PatchGeometry,
    objects: &[ObjectMaterial<'_>],
    triangles: &[&[[Vec3; 3]]],
    media: &SceneMedia,
    unit_mm: f64,
    params: &SParams,
    voxels: &VoxelParams,
    on_demand: &[bool],
) -> Result<(Vec<Option<voxel::Oracle>>, Vec<f32>), DistanceError> {
    let mut oracles = Vec::with_capacity(objects.len());
    let mut reach = Vec::with_capacity(objects.len());
    for (k, (o, tris)) in objects.iter().zip(triangles).enumerate() {
        let radius = match o.material {
            Material::ThinSheet { .. } => None,
            _ => stored_radius(o, unit_mm, params)?,
        };
        reach.push(radius.unwrap_or(0.0));
        let Some(radius) = radius else {
            oracles.push(None);
            continue;
        };
        let r = o.patches.clone();
        let local_media = media.patch_material.get(r.clone()).unwrap_or(&[]);
        let frame = media.frames.get(k).copied().unwrap_or_default();
        let homogeneous = hetero::medium_field(o.material, frame, local_media).is_none();
        if !(homogeneous
            && matches!(o.material, Material::Translucent { .. })
            && on_demand.get(k).copied().unwrap_or(false))
        {
            oracles.push(None);
            continue;
        }
        let (cen, nor) = (&g.centroid[r.clone()], &g.normal[r]);
        oracles.push(Some(oracle_of(o.name, tris, cen, nor, radius, voxels)?.0));
    }
    Ok((oracles, reach))
}

/// The warning for an object without interior, whose distances fall back to straight lines.
fn no_interior(name: &str) -> String {
    format!("'{name}' has no interior (open or broken mesh): straight-line distances used")
}

/// The report's name of a method (`fallback`: straight lines for want of an interior).
fn method_name(method: Option<voxel::Method>, fallback: bool) -> String {
    match method {
        _ if fallback => "euclidean (fallback)".into(),
        Some(voxel::Method::Voxel) => "voxel".into(),
        _ => "euclidean".into(),
    }
}

/// The manifest's per-object record, from both stages' reports.
pub fn subsurface_objects(
    d: &[DistanceReport],
    a: &[AssemblyReport],
    energy: f32,
) -> Vec<SubsurfaceObject> {
    d.iter()
        .filter_map(|d| a.iter().find(|a| a.name == d.name).map(|a| (d, a)))
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
            links: a.links,
            entries: a.entries,
            warning: d.warning.clone(),
            simulation: None,
            seconds: d.seconds + a.seconds,
        })
        .collect()
}

/// Stage 1 for one thin-sheet object: distances kept out to
/// `radius_margin` × the larger truncation radius of R and T. Returns the local rows
/// (j, r_ij, kind) and the report; a warning when the faces, as meshed, are not about
/// `thickness_mm` apart (a units mistake, most often).
pub fn sheet_object_distances(
    name: &str,
    (reflectance, transmittance, thickness_mm): (&Profile, &Profile, f32),
    p: ObjectPatches<'_>,
    unit_mm: f64,
    params: &SParams,
) -> Result<(sheet::SheetRows, DistanceReport), SheetError> {
    let start = Instant::now();
    let (er, et) = (
        profile_eval(name, "reflectance", reflectance, unit_mm)?,
        profile_eval(name, "transmittance", transmittance, unit_mm)?,
    );
    let e = params.truncation_energy;
    let radius =
        er.truncation_radius(e).max(et.truncation_radius(e)) * params.radius_margin.max(1.0);
    let sd = sheet::sheet_distances(name, p, radius)?;
    // Faces 0 apart (a zero-thickness two-sided mesh) are a modelling choice, not a mistake.
    let gap_mm = sd.separation as f64 * unit_mm;
    let t = thickness_mm as f64;
    let warning = (gap_mm > 2.0 * t || (gap_mm < 0.5 * t && gap_mm > 0.01 * t)).then(|| {
        format!(
            "'{name}': its two faces are {gap_mm:.3} mm apart as meshed (median), but the \
             material's thickness_mm is {thickness_mm}; check the units"
        )
    });
    Ok((
        sd.rows,
        DistanceReport {
            name: name.to_string(),
            method: "geodesic (thin sheet)".into(),
            radius,
            voxels: 0,
            interior_voxels: 0,
            voxel_size: 0.0,
            warning,
            seconds: start.elapsed().as_secs_f64(),
            reused: false,
        },
    ))
}
