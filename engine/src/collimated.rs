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
//! In: the bundle's walks, each object's material (built or overridden), the lamps. Out:
//! [`Tilt`] (Δ over the simulated objects' patches) and [`tilted_irradiance`] (E_t).

use std::ops::Range;

use glam::Vec3;
use rayon::prelude::*;
use translux_proto::bundle::Bundle;
use translux_proto::csr::{Csr, CsrView};
use translux_proto::light::Light;
use translux_proto::scene::Material;

use crate::linalg::{Rgb, Scatter, SparseScatter};
use crate::radiosity::{PatchGeometry, PointLights};
use crate::raycast::Occluder;
use crate::simulated::{self, SimMedium};
use crate::smatrix::SimTilts;

/// Δ = S⁽ⁿ⁾ − S of a scene's simulated objects under one set of materials.
#[derive(Debug)]
pub struct Tilt {
    /// N × N, rows and columns only within simulated objects; entries of either sign.
    pub delta: Csr<Rgb>,
    /// The simulated objects' patch ranges (where E_t is needed).
    pub ranges: Vec<Range<usize>>,
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
    /// Δ as a [`Scatter`] (valid by construction).
    pub fn scatter(&self) -> SparseScatter<'_> {
        SparseScatter(self.view())
    }

    fn view(&self) -> CsrView<'_, Rgb> {
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
    let mut rows: Vec<Vec<(u32, Rgb)>> = vec![Vec::new(); n];
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
    match Csr::from_rows(n, &rows) {
        Ok(delta) => TiltOf::Some(Tilt {
            delta,
            ranges: simulated.into_iter().map(|(_, r, _)| r).collect(),
        }),
        Err(e) => TiltOf::Unsupported(format!("collimated entry: {e}")),
    }
}

/// E_t = Σ_lamps E (3 μ₀ − 2) at the patches of `ranges` (zero elsewhere), with the same
/// shadow rays and fall-off as the direct irradiance ([`PointLights::each`]); environment
/// lights are skipped (their light enters diffusely). `None` when no lamp is given.
pub fn tilted_irradiance(
    geo: PatchGeometry<'_>,
    occ: &Occluder,
    lights: &[Light],
    unit_mm: f64,
    ranges: &[Range<usize>],
) -> Option<Vec<Rgb>> {
    let lamps = PointLights::new(lights, occ, unit_mm);
    if lamps.is_empty() {
        return None;
    }
    let mut out = vec![[0.0f32; 3]; geo.centroid.len()];
    for r in ranges {
        out[r.clone()]
            .par_iter_mut()
            .zip(&geo.centroid[r.clone()])
            .zip(&geo.normal[r.clone()])
            .for_each(|((e, &p), &n)| {
                lamps.each(p, n, |l: Vec3, c| {
                    let k = 3.0 * l.dot(n).clamp(0.0, 1.0) - 2.0;
                    for ch in 0..3 {
                        e[ch] += c[ch] * k;
                    }
                });
            });
    }
    Some(out)
}

/// y = Δ E_t for `k` stacked plans (`e_t` is `[patch][plan][rgb]`), added to `out`.
pub fn add_first_scatter(tilt: &Tilt, e_t: &[f32], k: usize, out: &mut [f32]) {
    let mut y = vec![0.0f32; out.len()];
    tilt.scatter().apply_multi(e_t, &mut y, 3 * k);
    for (o, v) in out.iter_mut().zip(y) {
        *o += v;
    }
}

/// y = Δ E_t for `lights` on `bundle` with its own materials, per patch: what a relight
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
    let e_t = tilted_irradiance(geo, occ, lights, bundle.manifest().unit_mm, &tilt.ranges)?;
    let mut y = vec![0.0f32; 3 * e_t.len()];
    add_first_scatter(&tilt, bytemuck::cast_slice(&e_t), 1, &mut y);
    Some(bytemuck::cast_slice(&y).to_vec())
}
