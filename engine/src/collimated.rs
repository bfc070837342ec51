//! Collimated entry into simulated objects: lamps light them by S at the lamp's angle, not by
//! the diffuse-entry S.
//!
//! S (the paper's model) assumes light enters diffusely. A point, spot or directional lamp's
//! light enters collimated at incidence cosine μ₀; at normal incidence it first scatters a
//! mean free path deep instead of two thirds of one, so less comes back near the entry and
//! more goes through. A simulated object's walks also store S⁽ⁿ⁾, S for collimated entry
//! along the normal ([`crate::simulated`]), and a lamp's light uses
//!
//! ```text
//!   S(μ₀) = S + (3μ₀ − 2) Δ,   Δ = S⁽ⁿ⁾ − S
//! ```
//!
//! (linear in μ₀: S⁽ⁿ⁾ at μ₀ = 1, and S on average over diffuse light, ∫ 2μ₀ S(μ₀) dμ₀ = S).
//! Summed over the lamps, the first scattering of their light is S E + Δ E_t with
//!
//! ```text
//!   E_t,i = Σ_lamps E_i (3 μ₀ − 2)
//! ```
//!
//! and the transport adds y = Δ E_t where it adds S E. Light arriving from other surfaces
//! (F B) and from environment maps stays diffuse, and so does every object that is not
//! simulated: Δ is zero there.
//!
//! **The direction of the slant.** S(μ₀) cannot tell which way a lamp slants: light entering
//! at a slant toward +x leaves mostly toward +x (on a 16 mm cube lit 60° off the normal, the
//! face ahead of the beam gets 1.6× the face behind it, where S(μ₀) gives both the same).
//! Bundles from version 8 on also carry S's first harmonic in the tilt, G_u and G_v: for a
//! beam travelling along d₀ into patch i, with u₀ = d₀·û_i and v₀ = d₀·v̂_i its components
//! along the patch's tangent frame ([`crate::simulated::tangent_frame`]),
//!
//! ```text
//!   S(d₀) = S + (3μ₀ − 2) Δ + u₀ G_u + v₀ G_v
//! ```
//!
//! G_u is estimated from the same diffuse walks: each entered along its own direction, so
//! projecting their exits on u (G_u = 4 E[w u_in], as E[u²] = ¼ over cosine-weighted
//! directions) is the least-squares slope of S in u, and it averages to zero over diffuse
//! light (the diffuse S is unchanged).
//!
//! **The beam seen through the object.** A diffuse walk that leaves without scattering
//! (across an edge of a cube, through a thin wall) is part of S: diffuse light crossing a
//! corner leaves in many directions. A lamp's beam crossing unscattered leaves in one, as a
//! beam, not as exitance, so S⁽ⁿ⁾ leaves it out; but S(μ₀) above would still count the
//! diffuse U with weight 1 − (3μ₀ − 2) = 3 − 3μ₀ (1.5× at 60°; on a 16 mm cube lit by
//! 4 × 4 patches a face, 20% of what its sides got). Version 8 stores U apart, and a lamp
//! uses S − U where S stands:
//!
//! ```text
//!   S(d₀) = (S − U) + (3μ₀ − 2)(S⁽ⁿ⁾ − S + U) + u₀ G_u + v₀ G_v
//!         = S + (3μ₀ − 2) Δ + u₀ G_u + v₀ G_v + (3μ₀ − 3) U
//! ```
//!
//! The lamps' part is then one product over the pattern of Δ, whose every entry holds
//! [Δ, G_u, G_v, U]_ji (they share S's sources), with [E_t, E_u, E_v, E_w]_i per source,
//! E_u,i = Σ_lamps E_i u₀, E_w,i = Σ_lamps E_i (3μ₀ − 3).
//!
//! In: the bundle's walks, each object's material (built or overridden), the lamps. Out:
//! [`Tilt`] (Δ, G_u, G_v and U over the simulated objects' patches) and
//! [`tilted_irradiance`] ([E_t; E_u; E_v; E_w]).

use std::ops::Range;

use glam::Vec3;
use rayon::prelude::*;
use translux_proto::bundle::Bundle;
use translux_proto::csr::{Csr, CsrView};
use translux_proto::light::Light;
use translux_proto::scene::Material;

use crate::linalg::Rgb;
use crate::radiosity::{PatchGeometry, PointLights};
use crate::raycast::Occluder;
use crate::simulated::{self, SimMedium};
use crate::smatrix::SimTilts;

/// Δ = S⁽ⁿ⁾ − S of a scene's simulated objects under one set of materials, with G_u, G_v
/// and U beside it when the walks carry them.
#[derive(Debug)]
pub struct Tilt {
    /// N × N, rows and columns only within simulated objects; each entry [Δ, G_u, G_v, U]_ji
    /// (the last three 0 for walks without lamp weights), of either sign.
    pub delta: Csr<[Rgb; 4]>,
    /// The simulated objects' patch ranges (where E_t is needed).
    pub ranges: Vec<Range<usize>>,
    /// Each patch's tangent frame (û, v̂) where `delta` has G_u, G_v and U (zero outside the
    /// simulated objects); empty otherwise.
    pub frames: Vec<(Vec3, Vec3)>,
}

/// What a scene's simulated objects can do with collimated light.
#[derive(Debug)]
pub enum TiltOf {
    /// No simulated object (under these materials).
    None,
    /// The walks predate collimated weights (a bundle older than version 7): lamps enter
    /// diffusely, and relights say so.
    Unsupported(String),
    Some(Tilt),
}

impl Tilt {
    /// Whether the lamps' slant direction and unscattered beam are modelled (G_u, G_v and U
    /// are stored: bundles from version 8 on).
    pub fn has_harmonic(&self) -> bool {
        !self.frames.is_empty()
    }

    fn view(&self) -> CsrView<'_, [Rgb; 4]> {
        self.delta
            .view()
            .expect("Tilt::of builds a valid CSR matrix")
    }
}

/// Δ for `bundle` with each object's material as in `materials` (one per manifest object).
pub fn tilt_of(bundle: &Bundle, materials: &[&Material]) -> TiltOf {
    tilt_of_with(bundle, materials, Vec::new())
}

/// [`tilt_of`] with the Δ of some objects already made (`given`, by object index, for
/// their material in `materials`: [`crate::smatrix::rebuild_with_terms_and_tilt`] makes
/// them beside S); the other simulated objects' Δ are re-weighted here.
pub fn tilt_of_with(bundle: &Bundle, materials: &[&Material], mut given: SimTilts) -> TiltOf {
    let objects = &bundle.manifest().objects;
    let simulated: Vec<(usize, Range<usize>, SimMedium)> = objects
        .iter()
        .zip(materials)
        .enumerate()
        .filter_map(|(k, (o, m))| {
            let medium = SimMedium::of(m)?;
            let r = o.first_patch as usize..(o.first_patch + o.patch_count) as usize;
            Some((k, r, medium))
        })
        .collect();
    if simulated.is_empty() {
        return TiltOf::None;
    }
    let Some(walks) = bundle.walks() else {
        return TiltOf::None;
    };
    if walks.normal.is_none() {
        return TiltOf::Unsupported(
            "this bundle's walks predate collimated entry (format version 6): lamps light its \
             simulated objects as diffuse light; precompute it again"
                .into(),
        );
    }
    let n = bundle.patch_areas().len();
    let harmonic = walks.lamp.is_some();
    let mut rows: Vec<Vec<(u32, [Rgb; 4])>> = vec![Vec::new(); n];
    for (k, r, medium) in &simulated {
        let made = given
            .iter()
            .position(|(g, _)| g == k)
            .map(|p| given.swap_remove(p).1);
        let Some(local) =
            made.or_else(|| simulated::reweight_tilt(&walks, r.clone(), medium.sigma_a))
        else {
            return TiltOf::None;
        };
        for (k, row) in local.into_iter().enumerate() {
            rows[r.start + k] = row;
        }
    }
    let frames = if harmonic {
        let corners = crate::smatrix::bundle_geometry(bundle).corners;
        let normals = bundle.patch_normals();
        let mut f = vec![(Vec3::ZERO, Vec3::ZERO); n];
        for (_, r, _) in &simulated {
            for i in r.clone() {
                f[i] = simulated::tangent_frame(&corners[i], Vec3::from(normals[i]));
            }
        }
        f
    } else {
        Vec::new()
    };
    match Csr::from_rows(n, &rows) {
        Ok(delta) => TiltOf::Some(Tilt {
            delta,
            ranges: simulated.into_iter().map(|(_, r, _)| r).collect(),
            frames,
        }),
        Err(e) => TiltOf::Unsupported(format!("collimated entry: {e}")),
    }
}

/// [E_t, E_u, E_v, E_w] per patch (E_u, E_v and E_w 0 when `tilt` has no harmonic) at the
/// patches of the simulated objects (zero elsewhere): E_t = Σ_lamps E (3 μ₀ − 2), E_u = Σ_lamps E u₀,
/// E_v = Σ_lamps E v₀ (u₀, v₀: the beam's travel direction along the patch's tangent
/// frame) and E_w = Σ_lamps E (3 μ₀ − 3), with the same shadow rays and fall-off as the direct irradiance
/// ([`PointLights::each`]); environment lights are skipped (their light enters diffusely).
/// `None` when no lamp is given.
pub fn tilted_irradiance(
    geo: PatchGeometry<'_>,
    occ: &Occluder,
    lights: &[Light],
    unit_mm: f64,
    tilt: &Tilt,
) -> Option<Vec<[Rgb; 4]>> {
    let lamps = PointLights::new(lights, occ, unit_mm);
    if lamps.is_empty() {
        return None;
    }
    let n = geo.centroid.len();
    let mut out = vec![[[0.0f32; 3]; 4]; n];
    let harmonic = tilt.has_harmonic();
    for r in &tilt.ranges {
        out[r.clone()]
            .par_iter_mut()
            .enumerate()
            .for_each(|(k, e)| {
                let i = r.start + k;
                let (p, nrm) = (geo.centroid[i], geo.normal[i]);
                let (fu, fv) = if harmonic {
                    tilt.frames[i]
                } else {
                    (Vec3::ZERO, Vec3::ZERO)
                };
                lamps.each(p, nrm, |l: Vec3, c| {
                    // l points toward the lamp: the beam travels along −l.
                    let mu0 = l.dot(nrm).clamp(0.0, 1.0);
                    // Without lamp weights (version 7) the tilt's G and U parts are 0.
                    let w = [3.0 * mu0 - 2.0, -l.dot(fu), -l.dot(fv), 3.0 * mu0 - 3.0];
                    for (e, w) in e.iter_mut().zip(w) {
                        for ch in 0..3 {
                            e[ch] += c[ch] * w;
                        }
                    }
                });
            });
    }
    Some(out)
}

/// y_j += Σ_i Δ_ji E_t,i + G_u,ji E_u,i + G_v,ji E_v,i + U_ji E_w,i for `k` stacked plans:
/// `e` is `[patch][plan][E_t, E_u, E_v, E_w][rgb]` (12 k values per patch), `out`
/// `[patch][plan][rgb]`. Written by hand: four RGB matrices on one pattern, which no sparse
/// crate's product takes.
pub fn add_first_scatter(tilt: &Tilt, e: &[f32], k: usize, out: &mut [f32]) {
    let view = tilt.view();
    out.par_chunks_mut(3 * k)
        .with_min_len(64)
        .enumerate()
        .for_each(|(j, yj)| {
            let (cols, vals) = view.row(j);
            for (&i, v) in cols.iter().zip(vals) {
                let ei = &e[i as usize * 12 * k..(i as usize + 1) * 12 * k];
                for (plan, y) in yj.chunks_exact_mut(3).enumerate() {
                    let ep = &ei[12 * plan..12 * plan + 12];
                    for c in 0..3 {
                        y[c] += v[0][c] * ep[c]
                            + v[1][c] * ep[3 + c]
                            + v[2][c] * ep[6 + c]
                            + v[3][c] * ep[9 + c];
                    }
                }
            }
        });
}

/// y = Δ E_t + G_u E_u + G_v E_v + U E_w ([`add_first_scatter`]) for `lights` on `bundle`
/// with its own materials, per patch: what a relight
/// adds to S E (it enters the transport like emission, B = Bₑ + y + S(E + F B)). `None`
/// when there is nothing to add (no lamp, no simulated object, or walks without
/// collimated weights).
pub fn first_scatter(
    bundle: &Bundle,
    geo: PatchGeometry<'_>,
    occ: &Occluder,
    lights: &[Light],
) -> Option<Vec<Rgb>> {
    let materials: Vec<&Material> = bundle
        .manifest()
        .objects
        .iter()
        .map(|o| &o.material)
        .collect();
    let TiltOf::Some(tilt) = tilt_of(bundle, &materials) else {
        return None;
    };
    let e_t = tilted_irradiance(geo, occ, lights, bundle.manifest().unit_mm, &tilt)?;
    let mut y = vec![0.0f32; 3 * tilt.view().n_rows()];
    add_first_scatter(&tilt, e_t.as_flattened().as_flattened(), 1, &mut y);
    Some(bytemuck::cast_slice(&y).to_vec())
}
