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
//! and the transport adds y = Δ E_t where it adds S E. Every object that is not simulated
//! keeps diffuse entry: Δ is zero there. Light from
//! other surfaces (F B) gets the same treatment as a lamp's, per direction (below).
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
//! projecting their exits on u (G_u = 4 E[w u_in], as E\[u²\] = ¼ over cosine-weighted
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
//! [Δ, G_u, G_v, U]_ji (they share S's sources; and U's own Gᵁ_u, Gᵁ_v, which lamps do not
//! read), with [E_t, E_u, E_v, E_w]_i per source,
//! E_u,i = Σ_lamps E_i u₀, E_w,i = Σ_lamps E_i (3μ₀ − 3).
//!
//! **Light from other surfaces has a direction too.** F B arrives from where the other
//! surfaces are, not evenly from the whole hemisphere: at the top of a bowl's inner wall it
//! all comes from below (the bowl's opening sends nothing), so it travels up toward the rim.
//! The same expansion holds for any incident radiance L(ω), each direction a beam of its own:
//! with the moments of F B at patch i
//!
//! ```text
//!   E_t,i = Σ_j F_ij B_j (3μ_ij − 2),  E_u,i = Σ_j F_ij B_j u_ij,  E_v,i = Σ_j F_ij B_j v_ij
//! ```
//!
//! (μ_ij, u_ij, v_ij: the direction from j's centroid, or from a cluster node's area-weighted
//! centroid, to i's, on i's normal and tangent frame) the light other surfaces send in adds
//! Δ E_t + (G_u + Gᵁ_u) E_u + (G_v + Gᵁ_v) E_v. U keeps its diffuse weight (light crossing a
//! corner unscattered is exitance here, not a beam) and turns with its own first harmonic
//! Gᵁ, from the unscattered walks as G is from the others, no longer than U
//! ([`crate::simulated::with_realizable_u_tilt`]): light entering the sides of a cube
//! from the room's bright half and crossing the corner unscattered leaves on the far face
//! near its edges. For light arriving evenly E_t = E_u = E_v = 0, and nothing changes.
//! [`interreflected_first_scatter`] gives that term for a solved B; a relight adds it as one
//! correction, solved through the same transport (docs/transport.md).
//! An environment map's light is such an L(ω) too, known before the solve: its direction
//! bins' moments ([`add_environment_moments`]) join the lamps'.
//!
//! In: the bundle's walks, each object's material (built or overridden), the lamps, and F
//! with the solved B for the light from other surfaces. Out: [`Tilt`] (Δ, G_u, G_v and U
//! over the simulated objects' patches), [`tilted_irradiance`] ([E_t; E_u; E_v; E_w]) and
//! [`interreflected_first_scatter`].

use std::ops::Range;

use glam::Vec3;
use rayon::prelude::*;
use translux_proto::bundle::Bundle;
use translux_proto::csr::{Csr, CsrView, ValidCsr};
use translux_proto::light::Light;
use translux_proto::scene::Material;

use crate::linalg::Rgb;
use crate::radiosity::{PatchGeometry, PointLights};
use crate::raycast::Occluder;
use crate::simulated::{self, SimMedium, TiltEntry};
use crate::smatrix::SimTilts;
use crate::transport::{Pulled, Transport};

/// Δ = S⁽ⁿ⁾ − S of a scene's simulated objects under one set of materials, with G_u, G_v
/// and U beside it when the walks carry them.
#[derive(Debug, Clone)]
pub struct Tilt {
    /// N × N, rows and columns only within simulated objects; each entry [Δ, G_u, G_v, U,
    /// U's G_u, U's G_v]_ji ([`TiltEntry`]; all but Δ 0 for walks without lamp weights), of
    /// either sign. Checked once when made: a relight reads it twice (the lamps' and the
    /// other surfaces' light).
    pub delta: ValidCsr<TiltEntry>,
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

    fn view(&self) -> CsrView<'_, TiltEntry> {
        self.delta.view()
    }

    /// Names which patches are simulated and whether the harmonic is modelled: what the
    /// lights' moments and F's direction weights into them depend on (not the absorption),
    /// the key they are kept under between relights.
    pub fn patches_key(&self) -> String {
        format!("{:?}|{}", self.ranges, self.has_harmonic())
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
    let mut rows: Vec<Vec<(u32, TiltEntry)>> = vec![Vec::new(); n];
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
    match Csr::from_rows(n, &rows).and_then(ValidCsr::new) {
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
/// ([`PointLights::each`]); environment lights are skipped (their moments:
/// [`add_environment_moments`]).
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

/// Adds to `out` (laid out as [`tilted_irradiance`]'s) the moments [E_t, E_u, E_v, E_w] of
/// an environment's light at the simulated objects' patches: each direction bin k is a beam
/// of irradiance V_ik L̄_k (the bundle's visibility `vis` times the bin's mean radiance
/// `radiance`, as [`crate::envvis::environment_irradiance`] sums them) arriving from the
/// bin's centre direction ω_k, so travelling along −ω_k: E_t = Σ_k V_ik L̄_k (3 μ_k − 2),
/// E_u = −Σ_k V_ik L̄_k ω_k·û_i, E_v likewise (μ_k = ω_k·n_i); an even environment gives
/// E_t = E_u = E_v = 0 up to the bins' size.
///
/// E_w (the unscattered crossing left out, as for a lamp's beam) counts only the part of the
/// light above its even part, the least radiance among the bins patch i sees (per channel):
/// E_w = Σ_k V_ik (L̄_k − L_min,i)(3 μ_k − 3). Light arriving evenly is diffuse, as S
/// assumes, and a viewer sees the map behind a corner through it (U kept); a sun on a dark
/// map is a lamp, and its beam through a corner is seen from its direction alone.
pub fn add_environment_moments(
    geo: PatchGeometry<'_>,
    vis: translux_proto::bundle::EnvVisibilityView<'_>,
    radiance: &[Rgb],
    tilt: &Tilt,
    out: &mut [[Rgb; 4]],
) {
    let bins = crate::envmap::Bins {
        rows: vis.rows,
        cols: vis.cols,
    };
    let k = bins.count();
    assert_eq!(
        radiance.len(),
        k,
        "one radiance per bin of the bundle's visibility"
    );
    let centre: Vec<Vec3> = (0..k).map(|b| bins.direction(b, 0.5, 0.5)).collect();
    let harmonic = tilt.has_harmonic();
    for r in &tilt.ranges {
        out[r.clone()]
            .par_iter_mut()
            .enumerate()
            .with_min_len(16)
            .for_each_init(
                || vec![0.0f32; k],
                |row, (at, e)| {
                    let i = r.start + at;
                    crate::environment::visibility_row(vis, i, row);
                    let nrm = geo.normal[i];
                    let (fu, fv) = if harmonic {
                        tilt.frames[i]
                    } else {
                        (Vec3::ZERO, Vec3::ZERO)
                    };
                    // The even part: the least radiance among the bins seen.
                    let mut floor = [f32::INFINITY; 3];
                    for (&v, l) in row.iter().zip(radiance) {
                        if v > 0.0 {
                            for ch in 0..3 {
                                floor[ch] = floor[ch].min(l[ch]);
                            }
                        }
                    }
                    for ((&v, l), w) in row.iter().zip(radiance).zip(&centre) {
                        if v <= 0.0 {
                            continue;
                        }
                        let mu = w.dot(nrm).clamp(0.0, 1.0);
                        let m = [3.0 * mu - 2.0, -w.dot(fu), -w.dot(fv)];
                        for (e, m) in e.iter_mut().zip(m) {
                            for ch in 0..3 {
                                e[ch] += v * l[ch] * m;
                            }
                        }
                        if harmonic {
                            for ch in 0..3 {
                                e[3][ch] += v * (l[ch] - floor[ch]) * (3.0 * mu - 3.0);
                            }
                        }
                    }
                },
            );
    }
}

/// The direction weights of the light other surfaces send into the simulated objects:
/// for each stored entry F_ij of their rows, [F_ij (3μ − 2), F_ij d·û_i, F_ij d·v̂_i] (d the
/// direction the light travels, from the source to patch i; μ = −d·n_i), laid out row after
/// row. Fixed by the geometry, F and which patches are simulated, not by their absorption:
/// made once ([`Slant::new`]) and read by [`interreflected_moments`] on every relight.
#[derive(Debug, Clone)]
pub struct Slant {
    /// Where row i's weights start in `w` (N + 1 offsets; empty rows outside the simulated
    /// objects).
    start: Vec<usize>,
    /// The column of F's stored matrix each weight goes with (a patch's whole row: its
    /// own entries and a two-sided F's node rows that hold it, [`Transport::patch_row`]).
    cols: Vec<u32>,
    w: Vec<[f32; 3]>,
}

impl Slant {
    /// The weights for `tilt`'s simulated patches under `f`. A link to a cluster node
    /// arrives from the node's area-weighted centroid.
    pub fn new(tilt: &Tilt, f: &Transport<'_>, geo: PatchGeometry<'_>) -> Slant {
        let n = geo.centroid.len();
        // Where each column of F's stored matrix (patches, then cluster nodes) sends from.
        let flat: Vec<f32> = geo.centroid.iter().flat_map(|c| c.to_array()).collect();
        let mut at = Pulled::default();
        f.pull(&flat, 3, &mut at);
        let from = &at.values;
        let mut simulated = vec![false; n];
        for r in &tilt.ranges {
            simulated[r.clone()].fill(true);
        }
        let harmonic = tilt.has_harmonic();
        let holders = f.holders(|p| simulated[p]);
        let rows: Vec<(Vec<u32>, Vec<[f32; 3]>)> = (0..n)
            .into_par_iter()
            .map(|i| {
                if !simulated[i] {
                    return Default::default();
                }
                let (p, nrm) = (geo.centroid[i], geo.normal[i]);
                let (fu, fv) = if harmonic {
                    tilt.frames[i]
                } else {
                    (Vec3::ZERO, Vec3::ZERO)
                };
                let (cols, vals) = f.patch_row(i, &holders[i]);
                let w = cols
                    .iter()
                    .zip(&vals)
                    .map(|(&c, &fij)| {
                        let c = c as usize;
                        let src = Vec3::new(from[3 * c], from[3 * c + 1], from[3 * c + 2]);
                        // A source at the patch itself carries no direction: weight 0.
                        (p - src).try_normalize().map_or([0.0; 3], |d| {
                            let mu = (-d.dot(nrm)).clamp(0.0, 1.0);
                            [fij * (3.0 * mu - 2.0), fij * d.dot(fu), fij * d.dot(fv)]
                        })
                    })
                    .collect();
                (cols, w)
            })
            .collect();
        let mut start = vec![0usize; n + 1];
        for (i, r) in rows.iter().enumerate() {
            start[i + 1] = start[i] + r.0.len();
        }
        let (cols, w): (Vec<Vec<u32>>, Vec<Vec<[f32; 3]>>) = rows.into_iter().unzip();
        Slant {
            start,
            cols: cols.concat(),
            w: w.concat(),
        }
    }
}

/// The moments [E_t, E_u, E_v, 0] of the light other surfaces send into the simulated
/// objects' patches, F x with each entry weighted by its direction (`slant`, made for
/// `tilt` and `f`; module docs), for `k` stacked RGB systems `x` (`[patch][plan][rgb]`);
/// laid out as [`add_first_scatter`] reads them (`[patch][plan][E_t, E_u, E_v, E_w][rgb]`),
/// zero outside the simulated objects.
pub fn interreflected_moments(slant: &Slant, f: &Transport<'_>, x: &[f32], k: usize) -> Vec<f32> {
    let n = slant.start.len() - 1;
    let ch = 3 * k;
    assert_eq!(x.len(), n * ch, "x is [patch][plan][rgb]");
    let mut pulled = Pulled::default();
    f.pull(x, ch, &mut pulled);
    let xbar = &pulled.values;
    let mut out = vec![0.0f32; n * 4 * ch];
    out.par_chunks_mut(4 * ch)
        .with_min_len(16)
        .enumerate()
        .filter(|(i, _)| slant.start[i + 1] > slant.start[*i])
        .for_each(|(i, e)| {
            let cols = &slant.cols[slant.start[i]..slant.start[i + 1]];
            let ws = &slant.w[slant.start[i]..slant.start[i + 1]];
            // Plan by plan, each summed in registers and stored once: adding into `e`
            // entry by entry made every add wait on the store before it (2.7 times
            // slower on the 24,392-patch Cornell box). The same sums in the same order.
            for (plan, ep) in e.chunks_exact_mut(12).enumerate() {
                let mut acc = [0.0f32; 9];
                for (&c, w) in cols.iter().zip(ws) {
                    let at = c as usize * ch + 3 * plan;
                    let xp = &xbar[at..at + 3];
                    for (m, w) in w.iter().enumerate() {
                        for rgb in 0..3 {
                            acc[3 * m + rgb] += w * xp[rgb];
                        }
                    }
                }
                ep[..9].copy_from_slice(&acc);
            }
        });
    out
}

/// y = Δ E_t + G_u E_u + G_v E_v of the light other surfaces send into the simulated objects
/// ([`interreflected_moments`]) for `k` stacked systems `x`: what a relight adds to S F B
/// for the direction that light arrives from, `[patch][plan][rgb]`.
pub fn add_interreflected_first_scatter(
    tilt: &Tilt,
    slant: &Slant,
    f: &Transport<'_>,
    x: &[f32],
    k: usize,
    out: &mut [f32],
) {
    let e = interreflected_moments(slant, f, x, k);
    add_first_scatter_of(tilt, &e, k, Beams::FromSurfaces, out);
}

/// The tilt of `bundle`'s simulated objects under their own materials; `None` without one
/// with collimated weights.
pub(crate) fn own_tilt(bundle: &Bundle) -> Option<Tilt> {
    let materials: Vec<&Material> = bundle
        .manifest()
        .objects
        .iter()
        .map(|o| &o.material)
        .collect();
    match tilt_of(bundle, &materials) {
        TiltOf::Some(tilt) => Some(tilt),
        _ => None,
    }
}

/// [`add_interreflected_first_scatter`] for one solved B of `bundle` with its own materials
/// (F the bundle's): `None` without a simulated object with collimated weights.
pub fn interreflected_first_scatter(
    bundle: &Bundle,
    geo: PatchGeometry<'_>,
    x: &[Rgb],
) -> Option<Vec<Rgb>> {
    let tilt = own_tilt(bundle)?;
    let f = Transport::of(bundle);
    let slant = Slant::new(&tilt, &f, geo);
    let mut y = vec![0.0f32; 3 * x.len()];
    add_interreflected_first_scatter(&tilt, &slant, &f, bytemuck::cast_slice(x), 1, &mut y);
    Some(bytemuck::cast_slice(&y).to_vec())
}

/// y_j += Σ_i Δ_ji E_t,i + G_u,ji E_u,i + G_v,ji E_v,i + U_ji E_w,i for `k` stacked plans of
/// lamps' (or an environment's) light: `e` is `[patch][plan][E_t, E_u, E_v, E_w][rgb]` (12 k
/// values per patch), `out` `[patch][plan][rgb]`.
pub fn add_first_scatter(tilt: &Tilt, e: &[f32], k: usize, out: &mut [f32]) {
    add_first_scatter_of(tilt, e, k, Beams::Lamps, out);
}

/// Whose light [`add_first_scatter_of`] adds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Beams {
    /// Lamps and environments: U's tilt is left out with U (E_w removes U).
    Lamps,
    /// Other surfaces: U stays (E_w is 0), and turns with its own tilt.
    FromSurfaces,
}

/// [`add_first_scatter`] for `beams`: light from other surfaces adds U's tilt to G_u and G_v
/// (U crossing a corner unscattered leaves along its entry direction). Written by hand: RGB
/// matrices on one pattern, which no sparse crate's product takes.
fn add_first_scatter_of(tilt: &Tilt, e: &[f32], k: usize, beams: Beams, out: &mut [f32]) {
    let view = tilt.view();
    let with_u = beams == Beams::FromSurfaces;
    out.par_chunks_mut(3 * k)
        .with_min_len(64)
        .enumerate()
        .for_each(|(j, yj)| {
            let (cols, vals) = view.row(j);
            // Plan by plan in registers, as in [`interreflected_moments`].
            for (plan, y) in yj.chunks_exact_mut(3).enumerate() {
                let mut acc = [y[0], y[1], y[2]];
                for (&i, v) in cols.iter().zip(vals) {
                    let at = (i as usize * k + plan) * 12;
                    let ep = &e[at..at + 12];
                    for c in 0..3 {
                        let (gu, gv) = if with_u {
                            (v[1][c] + v[4][c], v[2][c] + v[5][c])
                        } else {
                            (v[1][c], v[2][c])
                        };
                        acc[c] +=
                            v[0][c] * ep[c] + gu * ep[3 + c] + gv * ep[6 + c] + v[3][c] * ep[9 + c];
                    }
                }
                y.copy_from_slice(&acc);
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
    let tilt = own_tilt(bundle)?;
    let e_t = tilted_irradiance(geo, occ, lights, bundle.manifest().unit_mm, &tilt)?;
    let mut y = vec![0.0f32; 3 * tilt.view().n_rows()];
    add_first_scatter(&tilt, e_t.as_flattened().as_flattened(), 1, &mut y);
    Some(bytemuck::cast_slice(&y).to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;
    use translux_proto::bundle::TreeView;

    /// A tilt over patch 0 alone (frame û = x, v̂ = y) whose only entry, (0, 0), holds
    /// `v` = [Δ, G_u, G_v, U] in every channel (U's own tilt 0); `n` patches in all.
    fn tilt(n: usize, v: [f32; 4]) -> Tilt {
        let [d, gu, gv, u] = v.map(|x| [x; 3]);
        tilt_entry(n, [d, gu, gv, u, [0.0; 3], [0.0; 3]])
    }

    /// [`tilt`] with the whole entry given, U's own tilt included.
    fn tilt_entry(n: usize, entry: TiltEntry) -> Tilt {
        let mut rows: Vec<Vec<(u32, TiltEntry)>> = vec![Vec::new(); n];
        rows[0].push((0, entry));
        let mut frames = vec![(Vec3::ZERO, Vec3::ZERO); n];
        frames[0] = (Vec3::X, Vec3::Y);
        Tilt {
            delta: ValidCsr::new(Csr::from_rows(n, &rows).unwrap()).unwrap(),
            ranges: std::iter::once(0..1).collect(),
            frames,
        }
    }

    /// Patch 0 at the origin facing +z; one source patch per cell of a (θ, φ) grid over its
    /// hemisphere, at unit distance, with F_0j its cosine-weighted solid angle over π (so
    /// a radiosity of 1 everywhere gives E = 1). Returns F (dense) and the geometry.
    fn hemisphere(rings: usize, sectors: usize) -> (Csr, Vec<Vec3>, Vec<Vec3>) {
        let mut centroid = vec![Vec3::ZERO];
        let mut normal = vec![Vec3::Z];
        let mut row = Vec::new();
        let (dt, dp) = (
            std::f32::consts::FRAC_PI_2 / rings as f32,
            std::f32::consts::TAU / sectors as f32,
        );
        for a in 0..rings {
            let t = (a as f32 + 0.5) * dt;
            for b in 0..sectors {
                let p = (b as f32 + 0.5) * dp;
                let w = Vec3::new(t.sin() * p.cos(), t.sin() * p.sin(), t.cos());
                row.push((
                    centroid.len() as u32,
                    t.cos() * t.sin() * dt * dp / std::f32::consts::PI,
                ));
                centroid.push(w);
                normal.push(-w);
            }
        }
        let n = centroid.len();
        let mut rows = vec![Vec::new(); n];
        rows[0] = row;
        (Csr::from_rows(n, &rows).unwrap(), centroid, normal)
    }

    fn moments(t: &Tilt, f: &Transport<'_>, c: &[Vec3], nrm: &[Vec3], x: &[Rgb]) -> [f32; 4] {
        let geo = PatchGeometry {
            centroid: c,
            normal: nrm,
        };
        let e = interreflected_moments(&Slant::new(t, f, geo), f, bytemuck::cast_slice(x), 1);
        // Red of E_t, E_u, E_v, E_w at patch 0; every other patch is not simulated.
        assert!(e[12..].iter().all(|&v| v == 0.0));
        [e[0], e[3], e[6], e[9]]
    }

    /// Patch 0 at the origin facing +z: its visibility per bin of a 16 × 32 partition,
    /// V_k = ∫_bin max(ω·z, 0) dω (unoccluded, 8 × 8 directions uniform in solid angle per
    /// bin), as the bundle stores it (half floats).
    fn open_sky() -> (crate::envmap::Bins, Vec<u16>) {
        let bins = crate::envmap::Bins { rows: 16, cols: 32 };
        let bits = (0..bins.count())
            .map(|k| {
                let mut sum = 0.0f32;
                for a in 0..8 {
                    for b in 0..8 {
                        let w = bins.direction(k, (a as f32 + 0.5) / 8.0, (b as f32 + 0.5) / 8.0);
                        sum += w.z.max(0.0);
                    }
                }
                half::f16::from_f32(sum / 64.0 * bins.solid_angle()).to_bits()
            })
            .collect();
        (bins, bits)
    }

    fn env_moments(bins: crate::envmap::Bins, bits: &[u16], radiance: &[Rgb]) -> [f32; 4] {
        let t = tilt(1, [0.0, 1.0, 0.0, 0.0]);
        let vis = translux_proto::bundle::EnvVisibilityView {
            rows: bins.rows,
            cols: bins.cols,
            bits,
        };
        let geo = PatchGeometry {
            centroid: &[Vec3::ZERO],
            normal: &[Vec3::Z],
        };
        let mut out = vec![[[0.0f32; 3]; 4]; 1];
        add_environment_moments(geo, vis, radiance, &t, &mut out);
        out[0].map(|m| m[0])
    }

    #[test]
    fn an_environments_bins_are_beams_from_their_directions() {
        let (bins, bits) = open_sky();
        let v: Vec<f32> = bits
            .iter()
            .map(|&b| half::f16::from_bits(b).to_f32())
            .collect();
        let e: f32 = v.iter().sum();
        assert!((e - std::f32::consts::PI).abs() < 0.01, "Σ V = {e}");
        // An even sky: no slant (up to the bins' size: each bin's light taken from its
        // centre), and diffuse light keeps the unscattered crossing (E_w = 0).
        let m = env_moments(bins, &bits, &vec![[2.0; 3]; bins.count()]);
        assert!(
            m.iter().all(|x| x.abs() < 0.02 * e),
            "{m:?} against E = {}",
            2.0 * e
        );
        assert_eq!(m[3], 0.0);
        // Sky only over the −x half: its light travels toward +x, E_u = ∫ cos θ (−ω_x) dω
        // = 2/3 (and E_t = 0: the half is as even in μ as the whole).
        let half_sky: Vec<Rgb> = (0..bins.count())
            .map(|k| [f32::from(bins.direction(k, 0.5, 0.5).x < 0.0); 3])
            .collect();
        // Nothing of it is even (the other half is dark): E_w = Σ V L (3μ − 3) = −E = −π/2.
        let m = env_moments(bins, &bits, &half_sky);
        assert!((m[1] - 2.0 / 3.0).abs() < 0.01, "E_u = {}", m[1]);
        assert!(m[0].abs() < 0.01 && m[2].abs() < 0.01, "{m:?}");
        assert!(
            (m[3] + std::f32::consts::FRAC_PI_2).abs() < 0.02,
            "E_w = {}",
            m[3]
        );
        // One bright bin on a dark map against a directional lamp shining from its centre
        // with the same irradiance: the same moments (the lamps' signs, frame and beam).
        let k = bins.bin_of(Vec3::new(-0.6, 0.35, 0.72).normalize());
        let w = bins.direction(k, 0.5, 0.5);
        let mut sun = vec![[0.0f32; 3]; bins.count()];
        sun[k] = [1.0 / v[k]; 3];
        let m = env_moments(bins, &bits, &sun);
        let t = tilt(1, [0.0, 1.0, 0.0, 0.0]);
        let below = [[
            Vec3::new(0.0, 0.0, -5.0),
            Vec3::new(0.1, 0.0, -5.0),
            Vec3::new(0.0, 0.1, -5.0),
        ]];
        let lamp = Light::Directional {
            direction: (-w).to_array(),
            irradiance: [1.0 / w.z; 3],
        };
        let geo = PatchGeometry {
            centroid: &[Vec3::ZERO],
            normal: &[Vec3::Z],
        };
        let l = tilted_irradiance(geo, &Occluder::new(&below), &[lamp], 1.0, &t).unwrap();
        let want = l[0].map(|m| m[0]);
        for (m, want) in m.iter().zip(want) {
            assert!((m - want).abs() < 1e-3, "{m} against the lamp's {want}");
        }
        assert!(
            want[1] > 0.5,
            "the lamp's light travels toward +x: E_u = {}",
            want[1]
        );
    }

    #[test]
    fn us_own_tilt_turns_light_from_surfaces_and_not_lamps() {
        // A tilt whose only entry has U = 0.3 and U's own G_u = 0.2 (nothing else): light
        // from the −x half of the hemisphere (E_u = 2/(3π)) adds 0.2 E_u; a lamp beam along
        // +x adds nothing, for U is taken out of a lamp's light whole (E_w) and its tilt with it.
        let (f, c, nrm) = hemisphere(45, 90);
        let n = c.len();
        let zero = [0.0; 3];
        let t = tilt_entry(n, [zero, zero, zero, [0.3; 3], [0.2; 3], zero]);
        let tr = Transport::dense(f.view().unwrap());
        let x: Vec<Rgb> = c
            .iter()
            .enumerate()
            .map(|(j, w)| [f32::from(j > 0 && w.x < 0.0); 3])
            .collect();
        let geo = PatchGeometry {
            centroid: &c,
            normal: &nrm,
        };
        let slant = Slant::new(&t, &tr, geo);
        let mut y = vec![0.0f32; 3 * n];
        add_interreflected_first_scatter(&t, &slant, &tr, bytemuck::cast_slice(&x), 1, &mut y);
        let want = 0.2 * 2.0 / (3.0 * std::f32::consts::PI);
        assert!((y[0] - want).abs() < 5e-3 * want, "{} against {want}", y[0]);
        // A lamp's light with E_u = 1 alone: U's tilt is not read.
        let mut e = vec![0.0f32; 12 * n];
        e[3..6].copy_from_slice(&[1.0; 3]);
        let mut y = vec![0.0f32; 3 * n];
        add_first_scatter(&t, &e, 1, &mut y);
        assert_eq!(y[..3], [0.0; 3]);
    }

    #[test]
    fn light_from_everywhere_has_no_slant_and_from_one_side_slants_away_from_it() {
        let (f, c, nrm) = hemisphere(90, 180);
        let n = c.len();
        let t = tilt(n, [0.0, 1.0, 0.0, 0.0]);
        let tr = Transport::dense(f.view().unwrap());
        let mut x = vec![[1.0f32; 3]; n];
        x[0] = [0.0; 3];
        let mut e = vec![[0.0f32; 3]; n];
        tr.apply_rgb(&x, &mut e);
        assert!((e[0][0] - 1.0).abs() < 1e-3, "E = {}", e[0][0]);
        // Even light: ∫ (3μ − 2) 2μ dμ = 0, and no tangential drift.
        let m = moments(&t, &tr, &c, &nrm, &x);
        assert!(m.iter().all(|v| v.abs() < 2e-3), "{m:?}");
        // Light only from the −x half travels toward +x: E = ½, E_u = 2/(3π), E_t still 0.
        for (x, w) in x.iter_mut().zip(&c).skip(1) {
            *x = if w.x < 0.0 { [1.0; 3] } else { [0.0; 3] };
        }
        let m = moments(&t, &tr, &c, &nrm, &x);
        let want = 2.0 / (3.0 * std::f32::consts::PI);
        assert!(
            (m[1] - want).abs() < 2e-3 * want,
            "E_u {} want {want}",
            m[1]
        );
        assert!(
            m[0].abs() < 2e-3 && m[2].abs() < 2e-3 && m[3] == 0.0,
            "{m:?}"
        );
        // Light from nearly straight above (μ > 0.99) weighs 3μ − 2, between 0.97 and 1, on Δ.
        for (x, w) in x.iter_mut().zip(&c).skip(1) {
            *x = if w.z > 0.99 { [1.0; 3] } else { [0.0; 3] };
        }
        let mut e = vec![[0.0f32; 3]; n];
        tr.apply_rgb(&x, &mut e);
        let m = moments(&t, &tr, &c, &nrm, &x);
        let r = m[0] / e[0][0];
        assert!((0.97..1.0).contains(&r), "{m:?} against E {}", e[0][0]);
        // And through the tilt: y = G_u E_u (here G_u = 1 alone).
        for (x, w) in x.iter_mut().zip(&c).skip(1) {
            *x = if w.x < 0.0 { [1.0; 3] } else { [0.0; 3] };
        }
        let geo = PatchGeometry {
            centroid: &c,
            normal: &nrm,
        };
        let mut y = vec![0.0f32; 3 * n];
        let slant = Slant::new(&t, &tr, geo);
        add_interreflected_first_scatter(&t, &slant, &tr, bytemuck::cast_slice(&x), 1, &mut y);
        assert!((y[0] - want).abs() < 2e-3 * want, "{}", y[0]);
        assert!(y[3..].iter().all(|&v| v == 0.0));
    }

    #[test]
    fn stacked_plans_equal_one_plan_at_a_time() {
        // Two systems stacked ([patch][plan][rgb]) against each alone, bit for bit: the
        // moments and the first scattering are summed plan by plan.
        let (f, c, nrm) = hemisphere(12, 24);
        let n = c.len();
        let t = tilt(n, [0.5, 1.0, -0.7, 0.3]);
        let tr = Transport::dense(f.view().unwrap());
        let geo = PatchGeometry {
            centroid: &c,
            normal: &nrm,
        };
        let slant = Slant::new(&t, &tr, geo);
        let plans: [Vec<Rgb>; 2] = [
            c.iter().map(|w| [w.x.max(0.0), 1.0, w.y.abs()]).collect(),
            c.iter().map(|w| [w.z, 0.5 * w.x + 1.0, 0.0]).collect(),
        ];
        let stacked: Vec<f32> = (0..n)
            .flat_map(|i| plans[0][i].into_iter().chain(plans[1][i]))
            .collect();
        let both = interreflected_moments(&slant, &tr, &stacked, 2);
        let mut y_both = vec![0.25f32; 6 * n];
        add_interreflected_first_scatter(&t, &slant, &tr, &stacked, 2, &mut y_both);
        for (p, x) in plans.iter().enumerate() {
            let one = interreflected_moments(&slant, &tr, bytemuck::cast_slice(x), 1);
            let mut y_one = vec![0.25f32; 3 * n];
            add_interreflected_first_scatter(
                &t,
                &slant,
                &tr,
                bytemuck::cast_slice(x),
                1,
                &mut y_one,
            );
            for i in 0..n {
                assert_eq!(
                    one[12 * i..12 * i + 12],
                    both[24 * i + 12 * p..24 * i + 12 * p + 12]
                );
                assert_eq!(
                    y_one[3 * i..3 * i + 3],
                    y_both[6 * i + 3 * p..6 * i + 3 * p + 3]
                );
            }
            assert!(one[..9].iter().any(|&v| v != 0.0), "{:?}", &one[..12]);
            assert_ne!(y_one[..3], [0.25; 3]);
        }
    }

    #[test]
    fn a_link_to_a_cluster_arrives_from_its_area_weighted_centroid() {
        // Patch 0 at the origin facing +z; patches 1 (area 1) and 2 (area 3) at height 1,
        // x = −1 and x = +1, one node {1, 2} whose centroid is x = +0.5; F_0 links the node.
        let c = vec![
            Vec3::ZERO,
            Vec3::new(-1.0, 0.0, 1.0),
            Vec3::new(1.0, 0.0, 1.0),
        ];
        let nrm = vec![Vec3::Z, -Vec3::Z, -Vec3::Z];
        let area = vec![1.0f32, 1.0, 3.0];
        let (perm, range) = (vec![0u32, 1, 2], vec![[1u32, 3]]);
        let f = Csr {
            n_rows: 3,
            n_cols: 4,
            row_ptr: vec![0, 1, 1, 1],
            col: vec![3],
            val: vec![0.2],
        };
        let tr = Transport::hierarchical(
            f.view().unwrap(),
            TreeView {
                perm: &perm,
                range: &range,
            },
            &area,
        );
        let t = tilt(3, [1.0, 0.0, 0.0, 0.0]);
        let x = vec![[0.0f32; 3], [2.0; 3], [2.0; 3]];
        let m = moments(&t, &tr, &c, &nrm, &x);
        // From (0.5, 0, 1) to the origin: d = (−0.5, 0, −1)/|…|.
        let d = Vec3::new(-0.5, 0.0, -1.0).normalize();
        let e = 0.2 * 2.0;
        assert!((m[1] - e * d.x).abs() < 1e-6, "{m:?}");
        assert!((m[0] - e * (3.0 * -d.z - 2.0)).abs() < 1e-6, "{m:?}");
        assert_eq!(m[2], 0.0);
    }
}
