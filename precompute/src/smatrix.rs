//! The scene's S in two stages, so translucency can change without touching geometry.
//!
//! 1. [`scene_distances`] (precompute, geometry only): for every translucent object, the
//!    optical path r_ij between its patches ([`voxel::optical_distances`]), kept out to
//!    `radius_margin` × the built profile's truncation radius, so that a more translucent
//!    profile later still finds its pairs. Stored in the bundle.
//! 2. [`assemble_scene`] (precompute *and* every translucency change): S from the stored
//!    distances and the materials — [`subsurface::assemble`] per translucent object, ρ on the
//!    diagonal of opaque patches, nothing for emitters.
//!
//! [`rebuild_from_bundle`] runs stage 2 on a mapped bundle with material overrides: the
//! library call behind a translucency slider.

use std::ops::Range;
use std::time::Instant;

use glam::Vec3;
use thiserror::Error;
use translux_proto::bundle::{Bundle, SubsurfaceObject};
use translux_proto::csr::CsrView;
use translux_proto::scene::Material;

use crate::profile::{ProfileError, ProfileEval};
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

/// Stage 1: optical distances of every translucent object (global indices; rows of other
/// patches empty). `triangles[o]` are object o's source triangles (for the inside test).
pub fn scene_distances(
    g: &PatchGeometry,
    objects: &[ObjectMaterial<'_>],
    triangles: &[&[[Vec3; 3]]],
    unit_mm: f64,
    params: &SParams,
) -> Result<(CsrOwned<f32>, Vec<DistanceReport>), SError> {
    let mut rows: Vec<Vec<(u32, f32)>> = vec![Vec::new(); g.corners.len()];
    let mut reports = Vec::new();
    for (o, tris) in objects.iter().zip(triangles) {
        let Material::Translucent { profile } = o.material else {
            continue;
        };
        let t = Instant::now();
        let eval = ProfileEval::new(profile, unit_mm).map_err(|error| SError::Profile {
            object: o.name.to_string(),
            error,
        })?;
        let radius =
            eval.truncation_radius(params.truncation_energy) * params.radius_margin.max(1.0);
        let r = o.patches.clone();
        let (cen, nor) = (&g.centroid[r.clone()], &g.normal[r.clone()]);
        let (local, stats, warning) =
            match voxel::optical_distances(o.name, tris, cen, nor, radius, &params.voxels) {
                Ok((d, s)) => {
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
                Err(VoxelError::NoInterior { .. }) => (
                    euclidean_rows(cen, radius),
                    None,
                    Some(format!(
                        "'{}' has no interior (open or broken mesh): straight-line distances used",
                        o.name
                    )),
                ),
                Err(e) => return Err(e.into()),
            };
        let base = r.start as u32;
        for (i, row) in local.into_iter().enumerate() {
            rows[r.start + i] = row.into_iter().map(|(j, d)| (base + j, d)).collect();
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
    Ok((CsrOwned::from_rows(rows), reports))
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
/// reach (0 for non-translucent objects).
pub fn assemble_scene(
    g: &PatchGeometry,
    objects: &[ObjectMaterial<'_>],
    distances: CsrView<'_, f32>,
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
            Material::Translucent { profile } => {
                let t = Instant::now();
                let eval = ProfileEval::new(profile, unit_mm).map_err(|error| SError::Profile {
                    object: o.name.to_string(),
                    error,
                })?;
                let wanted = eval.truncation_radius(params.truncation_energy);
                let reach = stored_radius.get(k).copied().unwrap_or(0.0);
                let radius = wanted.min(reach.max(f32::MIN_POSITIVE));
                let capped_from = (wanted > reach * (1.0 + 1e-6)).then_some(wanted);
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
                let tab = Tabulated::new(&eval, radius, 4096);
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

/// Rebuilds S for a bundle with some objects' materials replaced (by object index), from
/// the stored distances: no voxels, no rays. Objects not overridden keep their material.
pub fn rebuild_from_bundle(
    bundle: &Bundle,
    overrides: &[(usize, Material)],
    params: &SParams,
) -> Result<(CsrOwned<[f32; 3]>, Vec<AssemblyReport>), SError> {
    let m = bundle.manifest();
    let corners: Vec<[Vec3; 3]> = bundle
        .patch_corners()
        .iter()
        .map(|c| c.map(Vec3::from))
        .collect();
    let g = PatchGeometry::from_corners(corners);
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
    assemble_scene(&g, &objects, bundle.distances(), &stored, m.unit_mm, params)
}
