//! Thin sheets' S (stage 2): a sheet's reflectance R and transmittance T profiles
//! tabulated, and its S assembled from the stored sheet distances and their kinds (same
//! side or other side). The geometry — sides, geodesics, the point opposite each patch, and
//! the model with its quadrature — is documented in `translux_precompute::sheet`, which
//! computes the distances (stage 1).
//!
//! In: one object's patches ([`ObjectPatches`], local indices), its block of the stored
//! distances with kinds, the two profiles. Out: the object's S columns ([`ObjectS`]),
//! energy-bounded, and an [`AssemblyReport`].

use std::ops::Range;
use std::time::Instant;

use rayon::prelude::*;
use thiserror::Error;
use translux_proto::csr::CsrView;
use translux_proto::scene::Profile;

use crate::profile::{ProfileError, ProfileEval};
use crate::subsurface::{
    self, AssemblyReport, ObjectBlock, ObjectPatches, ObjectS, Quadrature, SParams,
    SubsurfaceParams, Tabulated,
};

/// `dist_kind` of a pair on one side of a sheet (or inside an ordinary translucent object).
pub const KIND_SAME: u32 = 0;
/// `dist_kind` of a pair on opposite sides of a thin sheet (the transmittance profile).
pub const KIND_OPPOSITE: u32 = 1;
/// Touching patches whose normals differ by more than this are not joined into one side.
pub const SIDE_ANGLE_DEG: f32 = 60.0;
/// Why an object cannot be a thin sheet.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum SheetError {
    #[error(
        "a thin-sheet material needs a two-sided mesh (front and back faces); object '{object}' \
         has one side (its largest smooth surface has {first:.3e} scene units² of area, the \
         next {second:.3e})"
    )]
    OneSide {
        object: String,
        first: f64,
        second: f64,
    },
    #[error(
        "object '{object}' is not a thin sheet: its two largest smooth sides hold only \
         {percent:.0}% of its area, and the rest (patches at more than {SIDE_ANGLE_DEG}° to \
         their neighbours) would get no subsurface transfer; a thin-sheet material needs a \
         two-sided mesh with thin side walls"
    )]
    MostlyRim { object: String, percent: f64 },
    #[error("object '{object}', {which} profile: {error}")]
    Profile {
        object: String,
        which: &'static str,
        error: ProfileError,
    },
}

/// The plan for S_ji of a pair at sheet distance `r` through either profile (R for the same
/// side, T for the other), by the quadrature of the module docs: far pairs by A_i P read at
/// two distances ([`subsurface::far_plan`]), near pairs by polar integration over j
/// projected onto i's plane (far again when the projection is edge-on).
pub fn pair_plan(
    p: &ObjectPatches<'_>,
    (i, j): (usize, usize),
    r: f32,
    params: &SubsurfaceParams,
) -> Quadrature {
    // Far: S_ji ≈ A_i (P(m − σ) + P(m + σ)) / 2.
    let far = subsurface::far_plan(p, i, j);
    if r >= params.near_factor * p.size[i].max(p.size[j]) {
        return far;
    }
    // Near: j projected onto i's plane, y′ = y − n_i ((y − c_i)·n_i).
    let (ci, ni) = (p.centroid[i], p.normal[i]);
    let proj = p.corners[j].map(|y| y - ni * (y - ci).dot(ni));
    let a_proj = 0.5 * (proj[1] - proj[0]).cross(proj[2] - proj[0]).length();
    if a_proj < 0.5 * p.area[j] {
        return far;
    }
    // S_ji = A_i · mean_x (1/A_j′) ∫_j′ P(|x − y′|) dA_y′.
    Quadrature::Polar {
        tri: proj,
        normal: ni,
        factor: p.area[i] / a_proj,
    }
}

/// S of one thin-sheet object in local indices. `kind[e]` is the kind of distance entry e
/// (parallel to `d.col()`; missing entries count as [`KIND_SAME`]); `r` and `t` tabulate the
/// reflectance and transmittance profiles out to the radii the distances were cut at.
pub fn assemble(
    p: ObjectPatches<'_>,
    d: CsrView<'_, f32>,
    kind: &[u32],
    r: &Tabulated,
    t: &Tabulated,
    params: &SubsurfaceParams,
) -> ObjectS {
    let n = p.area.len();
    let columns: Vec<Vec<(u32, [f32; 3])>> = (0..n)
        .into_par_iter()
        .map(|i| {
            let xs = subsurface::samples(&p.corners[i], params.samples);
            // Self term: reflectance only (the other side's "self" is ô(i), a pair).
            let mut col = vec![(i as u32, subsurface::self_term(&p, i, &xs, r, params))];
            for e in d.row_ptr()[i] as usize..d.row_ptr()[i + 1] as usize {
                let (j, dist) = (d.col()[e] as usize, d.val()[e]);
                let tab = if kind.get(e) == Some(&KIND_OPPOSITE) {
                    t
                } else {
                    r
                };
                if dist >= tab.r_max() {
                    continue;
                }
                let s = pair_plan(&p, (i, j), dist, params).eval(dist, &xs, tab, params);
                if s.iter().any(|&v| v > 0.0) {
                    col.push((j as u32, s));
                }
            }
            col
        })
        .collect();
    subsurface::bound_and_transpose(columns, p.area)
}

/// The sheet's `which` profile (`reflectance` or `transmittance`) ready to evaluate; the
/// error names the object and the profile.
pub fn profile_eval(
    name: &str,
    which: &'static str,
    profile: &Profile,
    unit_mm: f64,
) -> Result<ProfileEval, SheetError> {
    ProfileEval::new(profile, unit_mm).map_err(|error| SheetError::Profile {
        object: name.to_string(),
        which,
        error,
    })
}

/// A thin sheet's reflectance and transmittance profiles tabulated out to their truncation
/// radii, each capped by `reach` (how far the stored distances go), and the radius wanted
/// when the cap bites.
pub fn tables(
    name: &str,
    (reflectance, transmittance): (&Profile, &Profile),
    reach: f32,
    unit_mm: f64,
    params: &SParams,
) -> Result<(Tabulated, Tabulated, Option<f32>), SheetError> {
    let (er, et) = (
        profile_eval(name, "reflectance", reflectance, unit_mm)?,
        profile_eval(name, "transmittance", transmittance, unit_mm)?,
    );
    let e = params.truncation_energy;
    let (want_r, want_t) = (er.truncation_radius(e), et.truncation_radius(e));
    let radius_r = want_r.min(reach.max(f32::MIN_POSITIVE));
    let radius_t = want_t.min(reach.max(f32::MIN_POSITIVE));
    let wanted = want_r.max(want_t);
    let capped_from = (wanted > reach * (1.0 + 1e-6)).then_some(wanted);
    Ok((
        Tabulated::new(&er, radius_r, 4096),
        Tabulated::new(&et, radius_t, 4096),
        capped_from,
    ))
}

/// Stage 2 for one thin-sheet object whose patches are `range` of the scene: S from the
/// stored distances (`distances`, global) and their kinds (`kinds`, parallel to the stored
/// values), which reach `reach` scene units. Returns S in local indices and the report.
#[expect(
    clippy::too_many_arguments,
    reason = "the object's profiles and patches with its block of the scene's stored distances"
)]
pub fn object_s(
    name: &str,
    (reflectance, transmittance): (&Profile, &Profile),
    p: ObjectPatches<'_>,
    range: Range<usize>,
    distances: CsrView<'_, f32>,
    kinds: &[u32],
    reach: f32,
    unit_mm: f64,
    params: &SParams,
) -> Result<(ObjectS, AssemblyReport), SheetError> {
    let start = Instant::now();
    let (tr, tt, capped_from) = tables(name, (reflectance, transmittance), reach, unit_mm, params)?;
    let (radius_r, radius_t) = (tr.r_max(), tt.r_max());
    // The object's block of the stored distances, in local indices, with kinds.
    let kind_of = |e: usize| kinds.get(e).copied().unwrap_or(KIND_SAME);
    let block = ObjectBlock::of(distances, range, |_, d, e| {
        d < if kind_of(e) == KIND_OPPOSITE {
            radius_t
        } else {
            radius_r
        }
    });
    let kind: Vec<u32> = block.entries.iter().map(|&e| kind_of(e)).collect();
    let dv = block.view();
    let s = assemble(p, dv, &kind, &tr, &tt, &params.quadrature);
    let report = AssemblyReport {
        name: name.to_string(),
        radius: radius_r.max(radius_t),
        capped_from,
        max_column_energy: s.report.max_column,
        scaled_columns: s.report.scaled_columns as u64,
        entries: s.report.nnz,
        links: 0,
        seconds: start.elapsed().as_secs_f64(),
    };
    Ok((s, report))
}
