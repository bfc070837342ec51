//! A simulated S: random walks through a homogeneous medium inside an object's actual
//! closed mesh, stored with their path lengths so absorption can change without new walks.
//!
//! In: one object's patches (triangles, outward normals, areas; the mesh must be closed),
//! its [`SimMedium`] (from a `"type": "simulated"` material) and the scene unit. Out:
//! [`Walks`], per receiver patch j the sources i with a histogram of path lengths,
//! `(i, bin, w)`, where w is the walks' share of S_ji at zero absorption; and
//! [`reweight`], which turns them into S_ji for any absorption:
//!
//! ```text
//!   S_ji = Σ_bins w_jib · e^(−σa L_b)          (L_b the bin's length, σa per channel)
//! ```
//!
//! A walk from patch i starts at a uniform point of i with a diffuse (cosine-weighted)
//! incident direction, as the paper's model assumes. With a dielectric boundary (η > 1) it
//! enters with the Fresnel transmittance of that direction as its weight and is refracted;
//! with η = 1 (index-matched) it goes straight in. Inside, it flies exponential distances
//! at the scattering coefficient σs (absorption is left to the re-weighting: sampling
//! flights at σs and weighting by e^(−σa L) is the same estimator as flights at σs + σa with
//! survival σs/σt, for any σa), scatters isotropically or by Henyey–Greenstein, and meets
//! the mesh again from inside: with η = 1 it leaves there; with η > 1 it is reflected back
//! with the Fresnel reflectance of its angle (total internal reflection included) and
//! otherwise leaves. The patch it leaves through is j, and
//!
//! ```text
//!   S_ji = (A_i / A_j) · (1/n_i) Σ_{walks from i leaving through j} w
//! ```
//!
//! (exitance at j per unit irradiance at i), so Σ_j A_j S_ji = A_i · (fraction re-emitted)
//! ≤ A_i for every column by construction.
//!
//! **Collimated entry.** Light from a point, spot or directional lamp does not enter
//! diffusely: at normal incidence it first scatters a mean free path deep on average, not
//! two thirds of one, so less comes back near where it entered and more goes through. Each
//! source patch therefore also launches as many walks entering collimated along its inward
//! normal (weight T(1), the Fresnel transmittance at normal incidence), which estimate
//! S⁽ⁿ⁾, S for that light, in the same records. (Re-weighting the diffuse walks by the depth
//! of their first scattering instead matches a half-space exactly but not a finite object:
//! the heavily weighted deep walks are also the ones that stepped sideways, toward the
//! edges; on a 16 mm cube it returned 10% too little from the lit face's border.) A lamp at
//! incidence cosine μ₀ then uses S(μ₀) = S + (3μ₀ − 2)(S⁽ⁿ⁾ − S): linear in μ₀, S⁽ⁿ⁾ at normal
//! incidence, and S itself on average over diffuse light (∫ 2μ₀ S(μ₀) dμ₀ = S).
//! [`reweight_tilt`] gives S⁽ⁿ⁾ − S at any absorption. A collimated walk that leaves
//! without scattering once is the lamp seen through the object, a beam in one direction,
//! not diffuse exitance: it is left out of S⁽ⁿ⁾ (a path tracer cannot find it either; through
//! a 4 mm wall of 2.4 mean free paths it is 9% of the light).
//!
//! Channels with the same σs share walks; a medium with three different σs walks three
//! times. Walk counts adapt per patch: walks are added in batches until the relative
//! standard error of the patch's re-emitted total at the built σa is below the material's
//! `noise`, up to `max_walks`. Each patch has its own seeded stream, so S does not depend
//! on the thread count. A walk is cut (dropped) once its length makes it negligible at a
//! sixteenth of the built σa ([`ABSORPTION_FLOOR`]): lower absorption than that needs a new
//! precompute, and [`check_override`] says so.
//!
//! Why by hand: no crate walks a medium inside a triangle mesh and keeps per-pair path
//! lengths; the rays go through the scene's BVH crate (`obvhs`, [`Occluder`]), and only
//! where a flight may reach the mesh ([`Clearance`]).

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Instant;

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use thiserror::Error;
use translux_proto::bundle::SimulationInfo;
use translux_proto::scene::Material;

use crate::clearance::Clearance;
use crate::profile;
use crate::raycast::Occluder;
use crate::specular::fresnel_dielectric;
use crate::stop::Stop;

pub use translux_proto::bundle::{
    SIM_BIN_L0_MM as BIN_L0_MM, SIM_BINS as BINS, SIM_BINS_PER_OCTAVE as BINS_PER_OCTAVE,
    SIM_TILT_ONE as TILT_ONE, SIM_UNSCATTERED as UNSCATTERED, WalksView,
};

/// Walks are kept while they matter at this fraction of the built σa (per channel).
pub const ABSORPTION_FLOOR: f32 = 1.0 / 16.0;
/// A walk is cut when e^(−σa_floor L) falls below e^(−CUT_OPTICAL_DEPTH).
pub const CUT_OPTICAL_DEPTH: f32 = 20.0;
/// A walk is cut after this many scattering events (reported).
pub const MAX_EVENTS: u32 = 1_000_000;
/// The size (bounding-box diagonal) an object is scaled to for its walks.
pub const WALK_FRAME: f32 = 1000.0;
/// Defaults of the material's fields.
pub const DEFAULT_NOISE: f32 = 0.01;
pub const DEFAULT_MAX_WALKS: u32 = 4096;
pub const DEFAULT_SEED: u64 = 1;
/// Walks are added in batches of this size; no patch gets fewer than [`MIN_WALKS`].
pub const BATCH: u32 = 64;
pub const MIN_WALKS: u32 = 256;
/// A source's walks read their [`Stop`] every this many walks.
const STOP_EVERY: u32 = 4;

/// The bin of a path of `len_mm` millimetres.
#[inline]
pub fn bin_of(len_mm: f64) -> u32 {
    if len_mm <= BIN_L0_MM {
        return 0;
    }
    let b = ((len_mm / BIN_L0_MM).log2() * BINS_PER_OCTAVE as f64) as u32;
    b.min(BINS - 1)
}

/// The length (mm) a bin stands for: its geometric centre (a record's [`UNSCATTERED`] flag
/// is ignored).
#[inline]
pub fn bin_length_mm(b: u32) -> f64 {
    let b = b & !UNSCATTERED;
    BIN_L0_MM * ((b as f64 + 0.5) / BINS_PER_OCTAVE as f64).exp2()
}

/// A record's G_u and G_v per channel from its packed tilt ratios (`lamp`, see
/// [`WalksView`]) and its diffuse weight `w`: G = 4 w r.
#[inline]
pub fn unpack_tilt(lamp: &[u32; 3], w: &[f32; 3]) -> [[f32; 3]; 2] {
    let k = 4.0 / TILT_ONE;
    [
        std::array::from_fn(|c| (lamp[c] as u16 as i16) as f32 * k * w[c]),
        std::array::from_fn(|c| ((lamp[c] >> 16) as u16 as i16) as f32 * k * w[c]),
    ]
}

/// The packed tilt ratios of G_u and G_v (per channel) against a record's diffuse weight w:
/// |G| ≤ 4 w by construction (|u_in| ≤ 1), rounded to i16 fixed point.
fn pack_tilt(g: &[[f32; 3]; 2], w: &[f32; 3]) -> [u32; 3] {
    std::array::from_fn(|c| {
        let r = |x: f32| {
            let q = if w[c] > 0.0 {
                (x / (4.0 * w[c])).clamp(-1.0, 1.0)
            } else {
                0.0
            };
            ((q * TILT_ONE).round() as i16) as u16 as u32
        };
        r(g[0][c]) | (r(g[1][c]) << 16)
    })
}

/// The medium of a simulated material, resolved (preset filled in), in mm⁻¹.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimMedium {
    /// Scattering coefficient per channel (σs′ with `g` = 0 for a preset or `sigma_s_prime`).
    pub sigma_s: [f32; 3],
    /// Henyey–Greenstein asymmetry.
    pub g: f32,
    pub sigma_a: [f32; 3],
    /// Relative index of the boundary; 1 is index-matched.
    pub eta: f32,
    pub noise: f32,
    pub max_walks: u32,
    pub seed: u64,
}

impl SimMedium {
    /// The medium of `m`, `None` unless it is a (validated) simulated material.
    pub fn of(m: &Material) -> Option<SimMedium> {
        let Material::Simulated {
            preset,
            sigma_a,
            sigma_s_prime,
            sigma_s,
            g,
            eta,
            noise,
            max_walks,
            seed,
            ..
        } = m
        else {
            return None;
        };
        let base = preset.as_deref().and_then(profile::preset);
        let (ss, gg) = match (sigma_s_prime, sigma_s, base) {
            (Some(s), _, _) => (*s, 0.0),
            (None, Some(s), _) => (*s, g.unwrap_or(0.0)),
            (None, None, Some(b)) => (b.sigma_s_prime, 0.0),
            (None, None, None) => return None,
        };
        let sa = sigma_a.or(base.map(|b| b.sigma_a))?;
        Some(SimMedium {
            sigma_s: ss,
            g: gg,
            sigma_a: sa,
            eta: profile::eta_of(preset.as_deref(), *eta),
            noise: noise.unwrap_or(DEFAULT_NOISE),
            max_walks: max_walks.unwrap_or(DEFAULT_MAX_WALKS),
            seed: seed.unwrap_or(DEFAULT_SEED),
        })
    }

    /// The dipole's total diffuse reflectance of the same medium (σs′ = σs (1 − g)): the
    /// albedo the object has where it is treated as opaque (the inter-reflection-only view).
    pub fn opaque_albedo(&self) -> [f32; 3] {
        std::array::from_fn(|c| {
            profile::dipole_rd(self.sigma_s[c] * (1.0 - self.g), self.sigma_a[c], self.eta)
                .clamp(0.0, 0.999)
        })
    }

    /// Channels grouped by equal σs: each group shares walks.
    pub fn groups(&self) -> Vec<Vec<usize>> {
        let mut groups: Vec<Vec<usize>> = Vec::new();
        for c in 0..3 {
            match groups
                .iter_mut()
                .find(|g| same(self.sigma_s[g[0]], self.sigma_s[c]))
            {
                Some(g) => g.push(c),
                None => groups.push(vec![c]),
            }
        }
        groups
    }

    /// The lowest σa per channel the stored walks serve.
    pub fn floor(&self) -> [f32; 3] {
        self.sigma_a.map(|a| a * ABSORPTION_FLOOR)
    }
}

fn same(a: f32, b: f32) -> bool {
    (a - b).abs() <= 1e-6 * a.abs().max(b.abs())
}

/// Whether an override of a simulated object can be served by its stored walks: only σa
/// (and the coat, and the walk settings, which only mattered for the precompute) may
/// differ, and σa may not go below [`SimMedium::floor`] of the built medium. The error says
/// what differs.
pub fn check_override(built: &SimMedium, new: &SimMedium) -> Result<(), String> {
    let what = if !(0..3).all(|c| same(built.sigma_s[c], new.sigma_s[c])) {
        Some(format!(
            "its scattering (σs {:?} mm⁻¹, precomputed with {:?})",
            new.sigma_s, built.sigma_s
        ))
    } else if !same(built.g, new.g) {
        Some(format!("g ({}, precomputed with {})", new.g, built.g))
    } else if !same(built.eta, new.eta) {
        Some(format!("eta ({}, precomputed with {})", new.eta, built.eta))
    } else {
        None
    };
    if let Some(what) = what {
        return Err(format!(
            "a simulated object's walks are fixed by {what}; only sigma_a can change \
             without new walks: walk them again in the new medium (`translux-precompute \
             BUNDLE --resimulate --materials '{{...}}'`, or a server's POST \
             /api/v1/scenes/ID/resimulate job)"
        ));
    }
    let floor = built.floor();
    for (c, &f) in floor.iter().enumerate() {
        if new.sigma_a[c] < f * (1.0 - 1e-6) {
            return Err(format!(
                "sigma_a[{c}] = {} mm⁻¹ is below {} (1/16 of the precomputed {}): the stored \
                 walks were cut where they stop mattering at that absorption; run \
                 translux-precompute again with the lower sigma_a",
                new.sigma_a[c], f, built.sigma_a[c]
            ));
        }
    }
    Ok(())
}

/// Why a simulation could not run.
#[derive(Debug, Error)]
pub enum SimError {
    #[error(
        "object '{object}': {lost} of {walks} walks left the mesh where it has no surface \
         (through a hole, or the faces point inward): a simulated S needs a closed mesh \
         whose faces point outward"
    )]
    Leaky {
        object: String,
        lost: u64,
        walks: u64,
    },
    /// Its [`Stop`] fired: no walks are kept.
    #[error("object '{object}': walks stopped with {walked} of its {patches} patches walked")]
    Stopped {
        object: String,
        walked: u64,
        patches: u64,
    },
}

/// One object's patches as the walks see them (local indices).
#[derive(Debug, Clone, Copy)]
pub struct SimPatches<'a> {
    pub corners: &'a [[Vec3; 3]],
    /// Outward unit normals.
    pub normal: &'a [Vec3],
    pub area: &'a [f32],
}

/// The walks of one object: row j (local) lists `(i, bin, w, w⁽ⁿ⁾)` sorted by i then bin.
#[derive(Debug, Clone, Default)]
pub struct Walks {
    pub row_ptr: Vec<u64>,
    pub col: Vec<u32>,
    pub bin: Vec<u32>,
    pub weight: Vec<[f32; 3]>,
    /// The same records for collimated entry along the normal (see the module docs).
    pub weight_normal: Vec<[f32; 3]>,
    /// The records' G_u and G_v, S's first harmonic in the tilt of collimated entry, packed
    /// ([`unpack_tilt`]); records of walks that left without scattering (U) have
    /// [`UNSCATTERED`] in their bin and U's own first harmonic here (see the module docs).
    pub weight_lamp: Vec<[u32; 3]>,
    /// What the walks did (the bundle's per-object record).
    pub report: SimulationInfo,
    /// Wall time of the walks, s.
    pub seconds: f64,
}

/// Rows of S: per receiver, `(source, S_ji)`.
pub type Rows = Vec<Vec<(u32, [f32; 3])>>;

/// One entry of the tilt, per channel: [Δ, G_u, G_v, U, G_u of U, G_v of U]. Lamps read
/// the first four ([`crate::collimated`]); light from other surfaces reads Δ and G_u, G_v
/// with U's own beside them (U's exits leave along their entry direction, so its tilt is
/// the strongest of all, and is limited to U's length: [`with_realizable_u_tilt`]; lamps
/// leave U out altogether).
pub type TiltEntry = [[f32; 3]; 6];

/// Rows of the tilt: per receiver, `(source, TiltEntry)` (all but Δ 0 for walks without
/// lamp weights).
pub type TiltRows = Vec<Vec<(u32, TiltEntry)>>;

/// e^(−σa L_b) for every bin and channel, σa in mm⁻¹.
pub(crate) fn attenuation(sigma_a: [f32; 3]) -> Vec<[f32; 3]> {
    (0..BINS)
        .map(|b| {
            let l = bin_length_mm(b);
            sigma_a.map(|a| (-(a as f64) * l).exp() as f32)
        })
        .collect()
}

/// Row j of `walks` summed per source at attenuation `att` ([`attenuation`]): `emit(i, S_ji,
/// t_ji)` once per source i, in the records' order (a source's records are consecutive), with
/// t_ji = [Δ_ji, G_u,ji, G_v,ji, U_ji, U's G_u,ji, U's G_v,ji] when `tilt` and the walks
/// carry collimated weights (all 0 otherwise): Δ = S⁽ⁿ⁾ − S from w⁽ⁿ⁾ − w, and where the walks
/// carry lamp weights G_u, G_v and U beside it, and U's own G ([`with_realizable_u_tilt`]),
/// which [`crate::collimated`] applies to E_t, E_u, E_v and E_w.
fn merge_row(
    walks: &WalksView<'_>,
    j: usize,
    att: &[[f32; 3]],
    tilt: bool,
    mut emit: impl FnMut(u32, [f32; 3], TiltEntry),
) {
    let (cols, bins, ws) = walks.row(j);
    let wn = if tilt { walks.row_normal(j) } else { None };
    let wt = if tilt { walks.row_lamp(j) } else { None };
    let mut cur: Option<(u32, [f32; 3], TiltEntry)> = None;
    for (k, ((&i, &b), w)) in cols.iter().zip(bins).zip(ws).enumerate() {
        let a = att[(b & !UNSCATTERED) as usize];
        let v = [w[0] * a[0], w[1] * a[1], w[2] * a[2]];
        let mut t = [[0.0f32; 3]; 6];
        if let Some(wn) = wn {
            let n = wn[k];
            t[0] = std::array::from_fn(|c| (n[c] - w[c]) * a[c]);
            // U's tilt goes beside U (slots 4 and 5), the scattered walks' in slots 1 and 2.
            let g = if b & UNSCATTERED != 0 {
                t[3] = v;
                4
            } else {
                1
            };
            if let Some(wt) = wt {
                let [gu, gv] = unpack_tilt(&wt[k], w);
                t[g] = std::array::from_fn(|c| gu[c] * a[c]);
                t[g + 1] = std::array::from_fn(|c| gv[c] * a[c]);
            }
        }
        match &mut cur {
            Some((c, acc, tacc)) if *c == i => {
                for ch in 0..3 {
                    acc[ch] += v[ch];
                }
                for (acc, t) in tacc.iter_mut().zip(t) {
                    for ch in 0..3 {
                        acc[ch] += t[ch];
                    }
                }
            }
            _ => {
                if let Some((c, acc, tacc)) = cur.replace((i, v, t)) {
                    emit(c, acc, with_realizable_u_tilt(tacc));
                }
            }
        }
    }
    if let Some((c, acc, tacc)) = cur {
        emit(c, acc, with_realizable_u_tilt(tacc));
    }
}

/// `t` with U's tilt (slots 4 and 5) no longer than U, per channel. U's response to light
/// from direction ω is a density: U + G·ω_t ≥ 0 for every tangential part |ω_t| ≤ 1 holds
/// only while |G| ≤ U. Unscattered walks leave along their entry direction, so a source
/// reached through a corner is a narrow lobe whose least-squares slope is longer than that,
/// and taken as it is it overshoots wherever the incident light is itself peaked (the
/// bowl's rim, lit by light that climbs the inner wall: 7% too bright). Scaling G down to
/// U keeps the lobe's direction and makes it the nearest realizable first harmonic, the
/// same limit that flux-limited diffusion puts on a flux (|F| ≤ c E).
pub fn with_realizable_u_tilt(mut t: TiltEntry) -> TiltEntry {
    let [_, _, _, u, gu, gv] = &mut t;
    for ((&u, gu), gv) in u.iter().zip(gu.iter_mut()).zip(gv.iter_mut()) {
        let g = gu.hypot(*gv);
        if g > u {
            let scale = if u > 0.0 { u / g } else { 0.0 };
            *gu *= scale;
            *gv *= scale;
        }
    }
    t
}

/// Rows `rows` (global) of `walks` summed per source at absorption `sigma_a` in one pass
/// over the records ([`merge_row`]): S_ji, and with `tilt` also the tilt rows (the walks must
/// carry collimated weights then). The tilt rows have S's sources.
fn sum_rows(
    walks: &WalksView<'_>,
    rows: std::ops::Range<usize>,
    sigma_a: [f32; 3],
    tilt: bool,
) -> (Rows, Option<TiltRows>) {
    let att = attenuation(sigma_a);
    let tilt = tilt && walks.normal.is_some();
    let both: Vec<_> = rows
        .into_par_iter()
        .map(|j| {
            let mut row: Vec<(u32, [f32; 3])> = Vec::new();
            let mut delta: Vec<(u32, TiltEntry)> = Vec::new();
            merge_row(walks, j, &att, tilt, |i, v, t| {
                row.push((i, v));
                if tilt {
                    delta.push((i, t));
                }
            });
            (row, delta)
        })
        .collect();
    let (s, delta): (Rows, TiltRows) = both.into_iter().unzip();
    (s, tilt.then_some(delta))
}

/// One row of a matrix to rewrite in place: its columns and its values.
pub type RowMut<'a, T> = (&'a [u32], &'a mut [T]);

/// An absorption change written in place: rows `rows` (global) of `walks` at `sigma_a` into
/// `s_rows`, and into `tilt_rows` when given (the walks must carry collimated weights then),
/// each row as [`ValidCsr::rewrite_vouched`](translux_proto::csr::ValidCsr::rewrite_vouched)
/// hands it over. The rows must have the patterns a build from the same walks made (S's and
/// the tilt's rows list each row's sources, `sum_rows`): where one does not, nothing is
/// promised of the values and the answer is `Err` with that row, so that the caller builds
/// again. `Ok` says whether every value written is finite.
///
/// No row is built and nothing is allocated per row: on the 24,392-patch Cornell box a
/// rebuild spent about as long making and checking new matrices as summing the records.
pub fn write_rows(
    walks: &WalksView<'_>,
    rows: std::ops::Range<usize>,
    sigma_a: [f32; 3],
    s_rows: Vec<RowMut<'_, [f32; 3]>>,
    tilt_rows: Option<Vec<RowMut<'_, TiltEntry>>>,
) -> Result<bool, usize> {
    assert_eq!(s_rows.len(), rows.len(), "one S row per walks row");
    let att = attenuation(sigma_a);
    let tilt = tilt_rows.is_some();
    if tilt && walks.normal.is_none() {
        return Err(rows.start);
    }
    let mut tilt_rows: Vec<Option<RowMut<'_, TiltEntry>>> = match tilt_rows {
        Some(t) => {
            assert_eq!(t.len(), rows.len(), "one tilt row per walks row");
            t.into_iter().map(Some).collect()
        }
        None => std::iter::repeat_with(|| None).take(rows.len()).collect(),
    };
    s_rows
        .into_par_iter()
        .zip(tilt_rows.par_iter_mut())
        .enumerate()
        .map(|(k, ((cols, vals), t))| {
            let j = rows.start + k;
            if t.as_ref().is_some_and(|(tc, _)| *tc != cols) {
                return Err(j);
            }
            let (mut at, mut same, mut finite) = (0usize, true, true);
            merge_row(walks, j, &att, tilt, |i, v, d| {
                if !same || cols.get(at) != Some(&i) {
                    same = false;
                    return;
                }
                finite &= v.iter().all(|x| x.is_finite());
                vals[at] = v;
                if let Some((_, tv)) = t {
                    finite &= d.iter().flatten().all(|x| x.is_finite());
                    tv[at] = d;
                }
                at += 1;
            });
            if same && at == cols.len() {
                Ok(finite)
            } else {
                Err(j)
            }
        })
        .try_reduce(|| true, |a, b| Ok(a && b))
}

/// The largest column energy Σ_j A_j S_ji / A_i of `rows`, each a global row j with its
/// entries (global i, S_ji); areas global.
pub fn max_column_energy<'a, R>(rows: impl IntoIterator<Item = (usize, R)>, area: &[f32]) -> f32
where
    R: IntoIterator<Item = (u32, &'a [f32; 3])>,
{
    let mut energy = vec![[0.0f64; 3]; area.len()];
    for (j, row) in rows {
        let aj = area[j] as f64;
        for (i, v) in row {
            for c in 0..3 {
                energy[i as usize][c] += aj * v[c] as f64;
            }
        }
    }
    energy
        .iter()
        .zip(area)
        .filter(|(_, a)| **a > 0.0)
        .map(|(e, a)| e.iter().fold(0.0f64, |m, v| m.max(*v)) / *a as f64)
        .fold(0.0f64, f64::max) as f32
}

/// [`max_column_energy`] of local rows of global sources, starting at global row `first`.
fn max_column_energy_of(rows: &Rows, first: usize, area: &[f32]) -> f32 {
    max_column_energy(
        rows.iter()
            .enumerate()
            .map(|(k, row)| (first + k, row.iter().map(|(i, v)| (*i, v)))),
        area,
    )
}

/// The re-weighted S of one simulated object: rows `rows` (global) of `walks`, as local
/// rows of `(global i, S_ji)`, and the largest column energy Σ_j A_j S_ji / A_i (areas
/// global).
pub fn reweight(
    walks: &WalksView<'_>,
    rows: std::ops::Range<usize>,
    area: &[f32],
    sigma_a: [f32; 3],
) -> (Rows, f32) {
    let (out, _) = sum_rows(walks, rows.clone(), sigma_a, false);
    let max = max_column_energy_of(&out, rows.start, area);
    (out, max)
}

/// [`reweight`] and [`reweight_tilt`] in one pass over the records (an absorption change
/// needs both, and reading the records is most of the work): S, Δ = S⁽ⁿ⁾ − S (`None`
/// when the walks carry no collimated weights) and S's largest column energy.
pub fn reweight_with_tilt(
    walks: &WalksView<'_>,
    rows: std::ops::Range<usize>,
    area: &[f32],
    sigma_a: [f32; 3],
) -> (Rows, Option<TiltRows>, f32) {
    let (out, delta) = sum_rows(walks, rows.clone(), sigma_a, walks.normal.is_some());
    let max = max_column_energy_of(&out, rows.start, area);
    (out, delta, max)
}

/// S⁽ⁿ⁾ − S of one simulated object at absorption `sigma_a` (see the module docs), with
/// G_u, G_v and U beside it when the walks carry lamp weights (the tilt rows of `sum_rows`):
/// rows `rows` (global) as local rows of `(global i, `[`TiltEntry`]`)`, values of either
/// sign; `None` when the walks carry no collimated weights (a bundle older than version 7).
pub fn reweight_tilt(
    walks: &WalksView<'_>,
    rows: std::ops::Range<usize>,
    sigma_a: [f32; 3],
) -> Option<TiltRows> {
    walks.normal?;
    sum_rows(walks, rows, sigma_a, true).1
}

/// Patch i's tangent frame for the tilt of collimated light (u along its first edge, v =
/// n × u), from its corners and outward unit normal: the walks and the lamps use the same
/// one.
pub fn tangent_frame(corners: &[Vec3; 3], n: Vec3) -> (Vec3, Vec3) {
    let e = corners[1] - corners[0];
    let u = (e - n * e.dot(n)).normalize_or_zero();
    (u, n.cross(u))
}

/// How a walk enters its patch.
#[derive(Debug, Clone, Copy)]
enum Entry {
    /// Cosine-weighted about the inward normal (the paper's diffuse entry).
    Diffuse,
    /// Collimated along the inward normal.
    Normal,
    /// Collimated, travelling along the given unit direction outside (a lamp's own beam,
    /// [`crate::lampwalk`]).
    Along(Vec3),
}

/// An orthonormal frame around unit `n` (Duff et al. 2017).
fn frame(n: Vec3) -> (Vec3, Vec3) {
    let s = 1.0f32.copysign(n.z);
    let a = -1.0 / (s + n.z);
    let b = n.x * n.y * a;
    (
        Vec3::new(1.0 + s * n.x * n.x * a, s * b, -s * n.x),
        Vec3::new(b, s + n.y * n.y * a, -n.y),
    )
}

/// A direction around `axis` with cos θ = `ct` and azimuth 2π `u`.
fn around(axis: Vec3, ct: f32, u: f32) -> Vec3 {
    let (t, b) = frame(axis);
    let st = (1.0 - ct * ct).max(0.0).sqrt();
    let phi = std::f32::consts::TAU * u;
    (t * (st * phi.cos()) + b * (st * phi.sin()) + axis * ct).normalize()
}

/// Henyey–Greenstein: cos θ between the old and the new direction.
fn hg_cos(g: f32, u: f32) -> f32 {
    if g.abs() < 1e-3 {
        return 1.0 - 2.0 * u;
    }
    let s = (1.0 - g * g) / (1.0 - g + 2.0 * g * u);
    ((1.0 + g * g - s * s) / (2.0 * g)).clamp(-1.0, 1.0)
}

/// How one walk ended.
enum End {
    /// Left through local patch j after `len` (scene units); `scattered`: whether it
    /// scattered at least once on the way.
    Out {
        j: u32,
        len: f32,
        scattered: bool,
    },
    Lost,
    Cut,
}

/// The walker of one object.
struct Walker<'a> {
    p: SimPatches<'a>,
    occ: &'a Occluder,
    /// Where a free flight certainly misses the mesh (the ray query is skipped there).
    clear: &'a Clearance,
    /// σs of the group being walked, per scene unit.
    sigma_s: f32,
    g: f32,
    eta: f32,
    /// Inward offset of start points (scene units).
    eps: f32,
    /// Cut length (scene units).
    max_len: f32,
    events: u64,
}

impl Walker<'_> {
    /// One walk from local patch i, entering as `entry` says; returns how it ended, its
    /// entry weight and the tangential part of its incident direction outside (zero along
    /// the normal).
    fn walk(&mut self, i: usize, entry: Entry, rng: &mut ChaCha8Rng) -> (End, f32, Vec3) {
        let [a, b, c] = self.p.corners[i];
        let (u1, u2): (f32, f32) = (rng.random(), rng.random());
        let su = u1.sqrt();
        let x = a * (1.0 - su) + b * (su * (1.0 - u2)) + c * (su * u2);
        let n = self.p.normal[i];
        // The incident direction outside, travelling in: diffuse incidence has cos θ = √u
        // (cosine-weighted) and a uniform azimuth.
        let d_out = match entry {
            Entry::Diffuse => around(-n, rng.random::<f32>().sqrt(), rng.random()),
            Entry::Normal => {
                // The azimuth a diffuse entry would draw (keeps the streams as they were).
                let _: f32 = rng.random();
                -n
            }
            Entry::Along(d) => d,
        };
        let cos_o = (-d_out.dot(n)).clamp(0.0, 1.0);
        let tangent = d_out + n * cos_o;
        let (mut d, w) = if self.eta == 1.0 {
            (d_out, 1.0)
        } else {
            // Refracted: the tangential part shrinks by η, the normal part makes it unit.
            let t = 1.0 - fresnel_dielectric(cos_o, self.eta);
            let dt = tangent / self.eta;
            let cos_t = (1.0 - dt.length_squared()).max(0.0).sqrt();
            ((dt - n * cos_t).normalize(), t)
        };
        let mut pos = x - n * self.eps;
        let mut len = 0.0f32;
        let mut events = 0u32;
        let mut scatters = 0u32;
        let end = loop {
            let s = -(1.0 - rng.random::<f32>()).ln() / self.sigma_s;
            let hit = if self.clear.clear(pos, s) {
                None
            } else {
                self.occ.closest_hit(pos, d, 0.0, s)
            };
            match hit {
                None => {
                    pos += d * s;
                    len += s;
                    events += 1;
                    scatters += 1;
                    if len > self.max_len || events >= MAX_EVENTS {
                        break End::Cut;
                    }
                    let ct = hg_cos(self.g, rng.random());
                    d = around(d, ct, rng.random());
                }
                Some((j, t)) => {
                    len += t;
                    let nj = self.p.normal[j];
                    let cos = d.dot(nj);
                    if cos <= 0.0 {
                        // Met a face from its front: the walk is outside the object.
                        break End::Lost;
                    }
                    let hit = pos + d * t;
                    if self.eta != 1.0
                        && rng.random::<f32>() < fresnel_dielectric(cos, 1.0 / self.eta)
                    {
                        d = (d - nj * (2.0 * cos)).normalize();
                        pos = hit - nj * self.eps;
                        events += 1;
                        if events >= MAX_EVENTS {
                            break End::Cut;
                        }
                        continue;
                    }
                    break End::Out {
                        j: j as u32,
                        len,
                        scattered: scatters > 0,
                    };
                }
            }
        };
        self.events += events as u64;
        (end, w, tangent)
    }
}

/// One object's patches in the frame its walks run in, centred and [`WALK_FRAME`] across,
/// with their occluder: obvhs's traversal loses rays near faces of small objects in
/// absolute coordinates (measured: 5% of the walks of a 16 mm cube modelled in metres, 0.1%
/// scaled to 1 across, left through its faces; none at 1000 across).
pub(crate) struct WalkFrame {
    corners: Vec<[Vec3; 3]>,
    occ: Occluder,
    clear: Clearance,
    /// Millimetres per unit of the frame.
    unit_mm: f64,
}

impl WalkFrame {
    /// The frame of an object's patch `corners` in scene units of `unit_mm` millimetres.
    pub(crate) fn new(corners: &[[Vec3; 3]], unit_mm: f64) -> WalkFrame {
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for t in corners {
            for v in t {
                lo = lo.min(*v);
                hi = hi.max(*v);
            }
        }
        let centre = 0.5 * (lo + hi);
        let size = (hi - lo).length().max(f32::MIN_POSITIVE);
        let corners: Vec<[Vec3; 3]> = corners
            .iter()
            .map(|t| t.map(|v| (v - centre) * (WALK_FRAME / size)))
            .collect();
        let occ = Occluder::new(&corners);
        let clear = Clearance::new(&corners);
        WalkFrame {
            corners,
            occ,
            clear,
            unit_mm: unit_mm * (size / WALK_FRAME) as f64,
        }
    }

    /// `count` walks into local patch i collimated along the unit travel direction `d`
    /// (outside; a uniform scale keeps directions), in a medium of `sigma_s` (mm⁻¹), HG
    /// `g`, boundary `eta`, cut where e^(−`floor` L) is negligible (`floor` in mm⁻¹, 0: never).
    /// `exit(j, length in mm, entry weight)` for each walk that scattered and left through
    /// local patch j (a beam crossing unscattered is the lamp seen through, not exitance).
    /// Returns false, with fewer walks made, where `stop` fired.
    pub(crate) fn walk_beams(
        &self,
        (normal, area): (&[Vec3], &[f32]),
        (sigma_s, g, eta, floor): (f32, f32, f32, f32),
        (i, d, count): (usize, Vec3, u32),
        rng: &mut ChaCha8Rng,
        stop: &crate::stop::Stop,
        mut exit: impl FnMut(u32, f64, f32),
    ) -> bool {
        let mut w = Walker {
            p: SimPatches {
                corners: &self.corners,
                normal,
                area,
            },
            occ: &self.occ,
            clear: &self.clear,
            sigma_s: sigma_s * self.unit_mm as f32,
            g,
            eta,
            eps: 1e-5 * self.occ.diagonal(),
            max_len: if floor > 0.0 {
                CUT_OPTICAL_DEPTH / (floor * self.unit_mm as f32)
            } else {
                f32::INFINITY
            },
            events: 0,
        };
        for k in 0..count {
            // A walk is microseconds to milliseconds: looking every 32 keeps a stop prompt.
            if k % 32 == 0 && stop.is_set() {
                return false;
            }
            if let (
                End::Out {
                    j,
                    len,
                    scattered: true,
                },
                weight,
                _,
            ) = w.walk(i, Entry::Along(d), rng)
            {
                exit(j, len as f64 * self.unit_mm, weight);
            }
        }
        true
    }
}

/// Runs the walks of one object. `unit_mm` converts scene units to mm; `first_patch` (the
/// object's first global patch) seeds each patch's stream; `progress` is called with the
/// number of patches finished so far.
pub fn simulate(
    name: &str,
    p: SimPatches<'_>,
    medium: &SimMedium,
    unit_mm: f64,
    first_patch: u64,
    (progress, stop): (&(dyn Fn(u64) + Sync), &Stop),
) -> Result<Walks, SimError> {
    let start = Instant::now();
    let n = p.corners.len();
    let frame = WalkFrame::new(p.corners, unit_mm);
    let p = SimPatches {
        corners: &frame.corners,
        ..p
    };
    let (unit_mm, occ, clear) = (frame.unit_mm, &frame.occ, &frame.clear);
    let eps = 1e-5 * occ.diagonal();
    let groups = medium.groups();
    let floor = medium.floor();
    let done = AtomicU64::new(0);
    let stopped = AtomicBool::new(false);
    // Per source patch: its records (j, bin, w, w⁽ⁿ⁾ and the lamp weights per channel)
    // merged, its walk counts and noise.
    type Record = (u32, u32, [f32; 3], [f32; 3], [[f32; 3]; 2]);
    type Source = (Vec<Record>, u64, u64, u64, u64, f32);
    let sources: Vec<Source> = (0..n)
        .into_par_iter()
        .map_init(
            || Walker {
                p,
                occ,
                clear,
                sigma_s: 1.0,
                g: medium.g,
                eta: medium.eta,
                eps,
                max_len: f32::INFINITY,
                events: 0,
            },
            |w, i| {
                // What a source stopped early gives: nothing (the whole result is refused).
                let cut_short = || {
                    stopped.store(true, Ordering::Relaxed);
                    (Vec::new(), 0, 0, 0, 0, 0.0)
                };
                if stop.is_set() {
                    return cut_short();
                }
                let mut recs: Vec<Record> = Vec::new();
                let (mut walks, mut lost, mut cut) = (0u64, 0u64, 0u64);
                let (tu, tv) = tangent_frame(&p.corners[i], p.normal[i]);
                let mut noise = 0.0f32;
                let events_before = w.events;
                for (gi, group) in groups.iter().enumerate() {
                    let c0 = group[0];
                    w.sigma_s = medium.sigma_s[c0] * unit_mm as f32;
                    let fl = group
                        .iter()
                        .map(|&c| floor[c])
                        .fold(f32::INFINITY, f32::min);
                    w.max_len = if fl > 0.0 {
                        CUT_OPTICAL_DEPTH / (fl * unit_mm as f32)
                    } else {
                        f32::INFINITY
                    };
                    let mut rng = ChaCha8Rng::seed_from_u64(medium.seed);
                    rng.set_stream(((first_patch + i as u64) << 2) | gi as u64);
                    // (j, bin, w, w⁽ⁿ⁾, [4 w u_in, 4 w v_in, w unscattered])
                    let mut group_recs: Vec<(u32, u32, f32, f32, [f32; 2])> = Vec::new();
                    let (mut sum, mut sum2, mut count) = (0.0f64, 0.0f64, 0u32);
                    while count < medium.max_walks {
                        for _ in 0..BATCH.min(medium.max_walks - count) {
                            // A walk may take up to MAX_EVENTS steps (milliseconds).
                            if count.is_multiple_of(STOP_EVERY) && stop.is_set() {
                                return cut_short();
                            }
                            count += 1;
                            let (end, weight, tangent) = w.walk(i, Entry::Diffuse, &mut rng);
                            let ret = match end {
                                End::Out { j, len, scattered } => {
                                    let mm = len as f64 * unit_mm;
                                    // The first harmonic in the tilt: 4 E[w u_in] (E[u²] = ¼
                                    // under cosine-weighted incidence). Walks that left
                                    // without scattering are U, which lamps leave out (a
                                    // lamp's unscattered beam is not exitance): records of
                                    // their own, flagged in the bin, with their own tilt
                                    // for light from other surfaces.
                                    let lamp = [
                                        4.0 * weight * tangent.dot(tu),
                                        4.0 * weight * tangent.dot(tv),
                                    ];
                                    let bin = if scattered {
                                        bin_of(mm)
                                    } else {
                                        bin_of(mm) | UNSCATTERED
                                    };
                                    group_recs.push((j, bin, weight, 0.0, lamp));
                                    let att: f64 = group
                                        .iter()
                                        .map(|&c| (-(medium.sigma_a[c] as f64) * mm).exp())
                                        .sum::<f64>()
                                        / group.len() as f64;
                                    weight as f64 * att
                                }
                                End::Lost => {
                                    lost += 1;
                                    0.0
                                }
                                End::Cut => {
                                    cut += 1;
                                    0.0
                                }
                            };
                            sum += ret;
                            sum2 += ret * ret;
                        }
                        let k = count as f64;
                        let mean = sum / k;
                        let var = (sum2 / k - mean * mean).max(0.0) / (k - 1.0).max(1.0);
                        let rel = if mean > 0.0 {
                            (var.sqrt() / mean) as f32
                        } else {
                            f32::INFINITY
                        };
                        if count >= MIN_WALKS && rel < medium.noise {
                            noise = noise.max(rel);
                            break;
                        }
                        if count >= medium.max_walks || (count >= 1024 && mean == 0.0) {
                            noise = noise.max(if mean > 0.0 { rel } else { 0.0 });
                            break;
                        }
                    }
                    // As many walks entering collimated along the normal (S⁽ⁿ⁾).
                    for k in 0..count {
                        if k.is_multiple_of(STOP_EVERY) && stop.is_set() {
                            return cut_short();
                        }
                        match w.walk(i, Entry::Normal, &mut rng) {
                            // A lamp seen through the object (no scattering) is not
                            // diffuse exitance: left out (see the module docs).
                            (
                                End::Out {
                                    j,
                                    len,
                                    scattered: true,
                                },
                                weight,
                                _,
                            ) => {
                                group_recs.push((
                                    j,
                                    bin_of(len as f64 * unit_mm),
                                    0.0,
                                    weight,
                                    [0.0; 2],
                                ));
                            }
                            (End::Out { .. }, ..) => {}
                            (End::Lost, ..) => lost += 1,
                            (End::Cut, ..) => cut += 1,
                        }
                    }
                    walks += 2 * count as u64;
                    // S_ji = A_i / (A_j n) Σ w: the A_j is applied when rows are made.
                    let scale = p.area[i] / count as f32;
                    group_recs.sort_unstable_by_key(|r| (r.0, r.1));
                    for (j, b, wt, wn, lamp) in group_recs {
                        let (mut v, mut vn, mut g) = ([0.0f32; 3], [0.0f32; 3], [[0.0f32; 3]; 2]);
                        for &c in group {
                            v[c] = wt * scale;
                            vn[c] = wn * scale;
                            for (g, l) in g.iter_mut().zip(lamp) {
                                g[c] = l * scale;
                            }
                        }
                        recs.push((j, b, v, vn, g));
                    }
                }
                recs.sort_unstable_by_key(|r| (r.0, r.1));
                let mut merged: Vec<Record> = Vec::with_capacity(recs.len());
                for r in recs {
                    match merged.last_mut() {
                        Some(m) if m.0 == r.0 && m.1 == r.1 => {
                            for c in 0..3 {
                                m.2[c] += r.2[c];
                                m.3[c] += r.3[c];
                                for k in 0..2 {
                                    m.4[k][c] += r.4[k][c];
                                }
                            }
                        }
                        _ => merged.push(r),
                    }
                }
                let d = done.fetch_add(1, Ordering::Relaxed) + 1;
                if d.is_multiple_of(64) || d == n as u64 {
                    progress(d);
                }
                (merged, walks, lost, cut, w.events - events_before, noise)
            },
        )
        .collect();
    if stopped.load(Ordering::Relaxed) {
        return Err(SimError::Stopped {
            object: name.to_string(),
            walked: done.load(Ordering::Relaxed),
            patches: n as u64,
        });
    }
    // Transpose: rows j, records (i, bin, w / A_j).
    let mut counts = vec![0u64; n + 1];
    for (recs, ..) in &sources {
        for r in recs {
            counts[r.0 as usize + 1] += 1;
        }
    }
    for k in 0..n {
        counts[k + 1] += counts[k];
    }
    let total = counts[n] as usize;
    let mut col = vec![0u32; total];
    let mut bin = vec![0u32; total];
    let mut weight = vec![[0.0f32; 3]; total];
    let mut weight_normal = vec![[0.0f32; 3]; total];
    let mut weight_lamp = vec![[0u32; 3]; total];
    let mut next = counts.clone();
    for (i, (recs, ..)) in sources.iter().enumerate() {
        for &(j, b, w, wn, g) in recs {
            let at = next[j as usize] as usize;
            next[j as usize] += 1;
            col[at] = i as u32;
            bin[at] = b;
            let aj = p.area[j as usize].max(f32::MIN_POSITIVE);
            weight[at] = w.map(|v| v / aj);
            weight_normal[at] = wn.map(|v| v / aj);
            weight_lamp[at] = pack_tilt(&g, &w);
        }
    }
    let mut report = SimulationInfo {
        records: total as u64,
        sigma_a_floor: medium.floor(),
        ..Default::default()
    };
    let mut noises: Vec<f32> = Vec::with_capacity(n);
    for (_, walks, lost, cut, events, noise) in &sources {
        report.walks += walks;
        report.lost += lost;
        report.cut += cut;
        report.events += events;
        noises.push(*noise);
    }
    noises.sort_by(f32::total_cmp);
    report.noise_median = noises.get(n / 2).copied().unwrap_or(0.0);
    report.noise_max = noises.last().copied().unwrap_or(0.0);
    if report.walks > 0 && report.lost * 20 > report.walks {
        return Err(SimError::Leaky {
            object: name.to_string(),
            lost: report.lost,
            walks: report.walks,
        });
    }
    Ok(Walks {
        row_ptr: counts,
        col,
        bin,
        weight,
        weight_normal,
        weight_lamp,
        report,
        seconds: start.elapsed().as_secs_f64(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An axis-aligned box `[0, s]` as triangles facing out, its face z = s (the top) split
    /// into `k` × `k` squares and every other face into two triangles. Returns the
    /// triangles and, per triangle, which face it is on (0..6: −x, +x, −y, +y, −z, +z).
    fn box_mesh(s: [f32; 3], k: usize) -> (Vec<[Vec3; 3]>, Vec<usize>) {
        let mut tris = Vec::new();
        let mut face = Vec::new();
        let mut quad = |a: Vec3, b: Vec3, c: Vec3, d: Vec3, f: usize, tris: &mut Vec<[Vec3; 3]>| {
            tris.push([a, b, c]);
            tris.push([a, c, d]);
            face.push(f);
            face.push(f);
        };
        let p = |x: f32, y: f32, z: f32| Vec3::new(x, y, z);
        let [sx, sy, sz] = s;
        quad(
            p(0., 0., 0.),
            p(0., 0., sz),
            p(0., sy, sz),
            p(0., sy, 0.),
            0,
            &mut tris,
        );
        quad(
            p(sx, 0., 0.),
            p(sx, sy, 0.),
            p(sx, sy, sz),
            p(sx, 0., sz),
            1,
            &mut tris,
        );
        quad(
            p(0., 0., 0.),
            p(sx, 0., 0.),
            p(sx, 0., sz),
            p(0., 0., sz),
            2,
            &mut tris,
        );
        quad(
            p(0., sy, 0.),
            p(0., sy, sz),
            p(sx, sy, sz),
            p(sx, sy, 0.),
            3,
            &mut tris,
        );
        quad(
            p(0., 0., 0.),
            p(0., sy, 0.),
            p(sx, sy, 0.),
            p(sx, 0., 0.),
            4,
            &mut tris,
        );
        for a in 0..k {
            for b in 0..k {
                let (x0, x1) = (sx * a as f32 / k as f32, sx * (a + 1) as f32 / k as f32);
                let (y0, y1) = (sy * b as f32 / k as f32, sy * (b + 1) as f32 / k as f32);
                quad(
                    p(x0, y0, sz),
                    p(x1, y0, sz),
                    p(x1, y1, sz),
                    p(x0, y1, sz),
                    5,
                    &mut tris,
                );
            }
        }
        (tris, face)
    }

    struct Mesh {
        tris: Vec<[Vec3; 3]>,
        normal: Vec<Vec3>,
        area: Vec<f32>,
        face: Vec<usize>,
    }

    fn mesh(s: [f32; 3], k: usize) -> Mesh {
        let (tris, face) = box_mesh(s, k);
        let normal = tris
            .iter()
            .map(|t| (t[1] - t[0]).cross(t[2] - t[0]).normalize())
            .collect();
        let area = tris
            .iter()
            .map(|t| 0.5 * (t[1] - t[0]).cross(t[2] - t[0]).length())
            .collect();
        Mesh {
            tris,
            normal,
            area,
            face,
        }
    }

    fn walks(m: &Mesh, medium: &SimMedium) -> Walks {
        let p = SimPatches {
            corners: &m.tris,
            normal: &m.normal,
            area: &m.area,
        };
        simulate("box", p, medium, 1.0, 0, (&|_| {}, &Stop::never())).expect("a closed box")
    }

    fn view(w: &Walks) -> WalksView<'_> {
        WalksView::new_checked(
            w.row_ptr.len() - 1,
            &w.row_ptr,
            &w.col,
            &w.bin,
            &w.weight,
            Some(&w.weight_normal),
        )
        .expect("valid walks")
    }

    /// Σ_j A_j S_ji / A_i per source patch i, per channel.
    fn column_energy(m: &Mesh, w: &Walks, sigma_a: [f32; 3]) -> Vec<[f64; 3]> {
        let (rows, _) = reweight(&view(w), 0..m.tris.len(), &m.area, sigma_a);
        energy_of_rows(m, &rows)
    }

    /// The same for collimated entry along the normal: S + (S⁽ⁿ⁾ − S).
    fn column_energy_normal(m: &Mesh, w: &Walks, sigma_a: [f32; 3]) -> Vec<[f64; 3]> {
        let n = m.tris.len();
        let tilt: Rows = reweight_tilt(&view(w), 0..n, sigma_a)
            .expect("collimated weights")
            .into_iter()
            .map(|row| row.into_iter().map(|(i, t)| (i, t[0])).collect())
            .collect();
        let mut e = column_energy(m, w, sigma_a);
        for (i, t) in energy_of_rows(m, &tilt).iter().enumerate() {
            for c in 0..3 {
                e[i][c] += t[c];
            }
        }
        e
    }

    fn energy_of_rows(m: &Mesh, rows: &Rows) -> Vec<[f64; 3]> {
        let n = m.tris.len();
        let mut e = vec![[0.0f64; 3]; n];
        for (j, row) in rows.iter().enumerate() {
            for (i, v) in row {
                for c in 0..3 {
                    e[*i as usize][c] += (m.area[j] * v[c]) as f64 / m.area[*i as usize] as f64;
                }
            }
        }
        e
    }

    fn medium(sigma_s: f32, sigma_a: f32, eta: f32) -> SimMedium {
        SimMedium {
            sigma_s: [sigma_s; 3],
            g: 0.0,
            sigma_a: [sigma_a; 3],
            eta,
            noise: 0.01,
            max_walks: 20_000,
            seed: 7,
        }
    }

    /// Chandrasekhar's H function of isotropic scattering with single-scattering albedo
    /// `w`, by iterating H(μ) = 1 / (1 − (w/2) μ ∫₀¹ H(μ′)/(μ + μ′) dμ′) on a Gauss–Legendre
    /// grid; returns α₁ = ∫₀¹ H(μ) μ dμ and H(1). An independent method: an integral
    /// equation, no random walks.
    fn h_function(w: f64) -> (f64, f64) {
        // 48-point Gauss–Legendre on [0, 1] from Newton's iteration on P_48.
        let n = 48;
        let mut x = vec![0.0f64; n];
        let mut wt = vec![0.0f64; n];
        for i in 0..n {
            let mut z = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
            for _ in 0..100 {
                let (mut p0, mut p1) = (1.0f64, z);
                for k in 2..=n {
                    let p2 = ((2 * k - 1) as f64 * z * p1 - (k - 1) as f64 * p0) / k as f64;
                    p0 = p1;
                    p1 = p2;
                }
                let dp = n as f64 * (z * p1 - p0) / (z * z - 1.0);
                let dz = p1 / dp;
                z -= dz;
                if dz.abs() < 1e-15 {
                    let (mut q0, mut q1) = (1.0f64, z);
                    for k in 2..=n {
                        let q2 = ((2 * k - 1) as f64 * z * q1 - (k - 1) as f64 * q0) / k as f64;
                        q0 = q1;
                        q1 = q2;
                    }
                    let dq = n as f64 * (z * q1 - q0) / (z * z - 1.0);
                    x[i] = 0.5 * (1.0 - z);
                    wt[i] = 1.0 / ((1.0 - z * z) * dq * dq);
                    break;
                }
            }
        }
        let mut h = vec![1.0f64; n];
        for _ in 0..2000 {
            let next: Vec<f64> = (0..n)
                .map(|i| {
                    let s: f64 = (0..n).map(|k| wt[k] * h[k] / (x[i] + x[k])).sum();
                    1.0 / (1.0 - 0.5 * w * x[i] * s)
                })
                .collect();
            h = next;
        }
        let s1: f64 = (0..n).map(|k| wt[k] * h[k] / (1.0 + x[k])).sum();
        (
            (0..n).map(|k| wt[k] * h[k] * x[k]).sum(),
            1.0 / (1.0 - 0.5 * w * s1),
        )
    }

    fn h_first_moment(w: f64) -> f64 {
        h_function(w).0
    }

    #[test]
    fn gauss_legendre_h_function_has_its_conservative_limit() {
        // For w = 1, α₁ = 2/√3 (Chandrasekhar, Radiative Transfer, §39).
        let a1 = h_first_moment(1.0 - 1e-9);
        assert!((a1 - 2.0 / 3f64.sqrt()).abs() < 2e-3, "α₁ = {a1}");
    }

    #[test]
    fn bins_cover_path_lengths() {
        for l in [1e-3, 0.5, 1.0, 37.0, 1e4] {
            let b = bin_of(l);
            let c = bin_length_mm(b);
            assert!((c / l).ln().abs() < 0.5 * std::f64::consts::LN_2 / 16.0 + 1e-9);
        }
        assert_eq!(bin_of(0.0), 0);
        assert_eq!(bin_of(1e30), BINS - 1);
    }

    #[test]
    fn a_semi_infinite_medium_reemits_chandrasekhars_albedo() {
        // A 200 mm block, mean free path 1 mm: from the middle of its top face it is a
        // half-space. Index-matched boundary, isotropic scattering, diffuse incidence: the
        // re-emitted fraction is the spherical albedo 1 − 2 √(1 − w) α₁(w).
        let m = mesh([200.0, 200.0, 200.0], 20);
        let built = medium(1.0, 0.0101, 1.0);
        let w = walks(&m, &built);
        let centre: Vec<usize> = (0..m.tris.len())
            .filter(|&i| {
                let c = (m.tris[i][0] + m.tris[i][1] + m.tris[i][2]) / 3.0;
                m.face[i] == 5 && (c.x - 100.0).abs() < 40.0 && (c.y - 100.0).abs() < 40.0
            })
            .collect();
        assert!(centre.len() >= 32);
        for single_albedo in [0.99f64, 0.95, 0.8] {
            let sigma_a = (1.0 / single_albedo - 1.0) as f32;
            let e = column_energy(&m, &w, [sigma_a; 3]);
            let ours: f64 = centre.iter().map(|&i| e[i][1]).sum::<f64>() / centre.len() as f64;
            let reference =
                1.0 - 2.0 * (1.0 - single_albedo).sqrt() * h_first_moment(single_albedo);
            let err = (ours / reference - 1.0).abs();
            eprintln!(
                "w = {single_albedo}: walks {ours:.4}, H function {reference:.4} ({:.2}%)",
                100.0 * err
            );
            assert!(
                err < 0.015,
                "w = {single_albedo}: {ours} against {reference}"
            );
        }
        // Collimated entry along the normal, the same walks re-weighted by their first
        // scattering's depth: the plane albedo 1 − H(1) √(1 − w).
        for single_albedo in [0.99f64, 0.95, 0.8] {
            let sigma_a = (1.0 / single_albedo - 1.0) as f32;
            let e = column_energy_normal(&m, &w, [sigma_a; 3]);
            let ours: f64 = centre.iter().map(|&i| e[i][1]).sum::<f64>() / centre.len() as f64;
            let reference = 1.0 - h_function(single_albedo).1 * (1.0 - single_albedo).sqrt();
            let diffuse = column_energy(&m, &w, [sigma_a; 3]);
            let diffuse: f64 =
                centre.iter().map(|&i| diffuse[i][1]).sum::<f64>() / centre.len() as f64;
            let err = (ours / reference - 1.0).abs();
            eprintln!(
                "w = {single_albedo}, normal incidence: walks {ours:.4}, H function \
                 {reference:.4} ({:.2}%; diffuse entry {diffuse:.4})",
                100.0 * err
            );
            assert!(
                err < 0.015,
                "w = {single_albedo}, normal incidence: {ours} against {reference}"
            );
            // Collimated light goes deeper, so less of it comes back.
            assert!(ours < diffuse);
        }
        // Every column within the bound.
        let e = column_energy(&m, &w, [0.0101; 3]);
        assert!(e.iter().flatten().all(|v| *v <= 1.0 + 1e-6));
    }

    #[test]
    fn reweighting_equals_a_fresh_simulation() {
        // A 20 mm cube; S per pair of faces (lit face to far face included) from walks at
        // σa = 0.01 re-weighted to 0.03, against new walks at 0.03 with another seed.
        let m = mesh([20.0, 20.0, 20.0], 6);
        let n = m.tris.len();
        let face_sums = |w: &Walks, sigma_a: f32| {
            let (rows, _) = reweight(&view(w), 0..n, &m.area, [sigma_a; 3]);
            let mut s = [[0.0f64; 6]; 6];
            for (j, row) in rows.iter().enumerate() {
                for (i, v) in row {
                    s[m.face[j]][m.face[*i as usize]] += (m.area[j] * v[0]) as f64;
                }
            }
            s
        };
        // Tight noise: the transfer to one side face is a small share of a column.
        let mut built = medium(1.0, 0.01, 1.0);
        built.noise = 0.002;
        let a = walks(&m, &built);
        let mut fresh = medium(1.0, 0.03, 1.0);
        fresh.noise = 0.002;
        fresh.seed = 99;
        let b = walks(&m, &fresh);
        let (sa, sb) = (face_sums(&a, 0.03), face_sums(&b, 0.03));

        for to in 0..6 {
            let (x, y) = (sa[to][5], sb[to][5]);
            let err = (x / y - 1.0).abs();
            eprintln!(
                "top → face {to}: re-weighted {x:.3}, fresh {y:.3} ({:.2}%)",
                100.0 * err
            );
            // The far face (4) gets a few per cent of the walks the sides get.
            let bar = if to == 4 { 0.06 } else { 0.03 };
            assert!(err < bar, "top → face {to}: {x} against {y}");
        }
        // And a different σa does change it (the test can fail).
        let sc = face_sums(&a, 0.01);
        assert!(
            sc[4][5] > 1.5 * sa[4][5],
            "{} against {}",
            sc[4][5],
            sa[4][5]
        );
    }

    /// Per face of `m`, Σ over `per` walks from each patch i of `sources` entering as
    /// `entry` says (index-matched, isotropic; at absorption `sigma_a`; the exits that
    /// scattered at least once, or with `scattered` false those that did not) of the
    /// walk's weight times `weigh(i, tangent)` (its incident direction's tangential part),
    /// each patch's sum times A_i / `per`.
    fn face_totals(
        m: &Mesh,
        (sigma_s, sigma_a): (f32, f32),
        sources: &[usize],
        (entry, per, seed, scattered): (Entry, u32, u64, bool),
        weigh: impl Fn(usize, Vec3) -> f64 + Sync,
    ) -> [f64; 6] {
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for v in m.tris.iter().flatten() {
            lo = lo.min(*v);
            hi = hi.max(*v);
        }
        let (centre, size) = (0.5 * (lo + hi), (hi - lo).length());
        let corners: Vec<[Vec3; 3]> = m
            .tris
            .iter()
            .map(|t| t.map(|v| (v - centre) * (WALK_FRAME / size)))
            .collect();
        let unit_mm = size / WALK_FRAME;
        let occ = Occluder::new(&corners);
        let clear = Clearance::new(&corners);
        let p = SimPatches {
            corners: &corners,
            normal: &m.normal,
            area: &m.area,
        };
        let per_source: Vec<[f64; 6]> = sources
            .par_iter()
            .map(|&i| {
                let mut w = Walker {
                    p,
                    occ: &occ,
                    clear: &clear,
                    sigma_s: sigma_s * unit_mm,
                    g: 0.0,
                    eta: 1.0,
                    eps: 1e-5 * occ.diagonal(),
                    max_len: f32::INFINITY,
                    events: 0,
                };
                let mut rng = ChaCha8Rng::seed_from_u64(seed);
                rng.set_stream(i as u64);
                let mut out = [0.0f64; 6];
                for _ in 0..per {
                    if let (
                        End::Out {
                            j,
                            len,
                            scattered: s,
                        },
                        weight,
                        tangent,
                    ) = w.walk(i, entry, &mut rng)
                        && s == scattered
                    {
                        let att = (-(sigma_a as f64) * (len * unit_mm) as f64).exp();
                        out[m.face[j as usize]] += weigh(i, tangent) * weight as f64 * att;
                    }
                }
                out.map(|v| v * m.area[i] as f64 / per as f64)
            })
            .collect();
        let mut out = [0.0f64; 6];
        for s in per_source {
            for f in 0..6 {
                out[f] += s[f];
            }
        }
        out
    }

    /// The clearance grid only skips ray queries that would have missed: walks with it and
    /// with a grid that never skips (one built over no triangles) end at the same patch
    /// after the same length, walk for walk, and most flights deep in a large box skip.
    #[test]
    fn skipping_flights_by_clearance_changes_no_walk() {
        let m = mesh([40.0, 20.0, 30.0], 6);
        let scale = WALK_FRAME / Vec3::new(40.0, 20.0, 30.0).length();
        let corners: Vec<[Vec3; 3]> = m.tris.iter().map(|t| t.map(|v| v * scale)).collect();
        let occ = Occluder::new(&corners);
        let (clear, never) = (Clearance::new(&corners), Clearance::new(&[]));
        let p = SimPatches {
            corners: &corners,
            normal: &m.normal,
            area: &m.area,
        };
        let walker = |clear| Walker {
            p,
            occ: &occ,
            clear,
            sigma_s: 0.5 / scale,
            g: 0.3,
            eta: 1.4,
            eps: 1e-5 * occ.diagonal(),
            max_len: f32::INFINITY,
            events: 0,
        };
        let (mut a, mut b) = (walker(&clear), walker(&never));
        for i in (0..corners.len()).step_by(7) {
            let mut ra = ChaCha8Rng::seed_from_u64(5);
            ra.set_stream(i as u64);
            let mut rb = ra.clone();
            for _ in 0..200 {
                let (ea, wa, ta) = a.walk(i, Entry::Diffuse, &mut ra);
                let (eb, wb, tb) = b.walk(i, Entry::Diffuse, &mut rb);
                let key = |e: End| match e {
                    End::Out { j, len, scattered } => (0, j, len.to_bits(), scattered),
                    End::Lost => (1, 0, 0, false),
                    End::Cut => (2, 0, 0, false),
                };
                assert_eq!((key(ea), wa, ta), (key(eb), wb, tb), "patch {i}");
            }
        }
        assert_eq!(a.events, b.events);
        // How often the grid spoke: the flights it let through without a query.
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut skipped = 0u64;
        for _ in 0..10_000 {
            let q = Vec3::new(rng.random(), rng.random(), rng.random()) * 2.0 - 1.0;
            let half = Vec3::new(20.0, 10.0, 15.0);
            let pos = (half + q * half * 0.6) * scale;
            skipped += clear.clear(pos, 2.0 * scale) as u64;
        }
        assert!(skipped > 5_000, "{skipped} of 10,000 deep flights skipped");
    }

    /// Per face of `m`, the power leaving it (scattered light only, at absorption
    /// `sigma_a`) for unit irradiance on each patch of `sources` by a beam travelling along
    /// `d0`, from 40,000 walks per patch entering along `d0` themselves: what the tilt model
    /// approximates, walked directly.
    fn beam_exits(m: &Mesh, sigma_s: f32, sigma_a: f32, sources: &[usize], d0: Vec3) -> [f64; 6] {
        let along = (Entry::Along(d0), 40_000, 99, true);
        face_totals(m, (sigma_s, sigma_a), sources, along, |_, _| 1.0)
    }

    /// Per face of `m`, what a beam along `d0` into the patches of face `lit` leaves there
    /// through the model (`s`, `tilt` from [`reweight`] and [`reweight_tilt`]; channel 1):
    /// S(μ₀) = S + (3μ₀ − 2) Δ alone, and with the harmonic and U, S + (3μ₀ − 2) Δ + u₀ G_u +
    /// v₀ G_v + (3μ₀ − 3) U; each summed as A_j S_ji.
    fn model_faces(
        m: &Mesh,
        s: &Rows,
        tilt: &TiltRows,
        lit: usize,
        d0: Vec3,
    ) -> ([f64; 6], [f64; 6]) {
        let (mut slant, mut harmonic) = ([0.0f64; 6], [0.0f64; 6]);
        for j in 0..m.tris.len() {
            let f = m.face[j];
            let aj = m.area[j] as f64;
            for &(c, val) in &s[j] {
                if m.face[c as usize] == lit {
                    slant[f] += aj * val[1] as f64;
                    harmonic[f] += aj * val[1] as f64;
                }
            }
            for &(c, val) in &tilt[j] {
                let i = c as usize;
                if m.face[i] != lit {
                    continue;
                }
                let mu0 = -d0.dot(m.normal[i]);
                let (fu, fv) = tangent_frame(&m.tris[i], m.normal[i]);
                let k = [3.0 * mu0 - 2.0, d0.dot(fu), d0.dot(fv), 3.0 * mu0 - 3.0];
                slant[f] += aj * k[0] as f64 * val[0][1] as f64;
                for (k, v) in k.iter().zip(val) {
                    harmonic[f] += aj * *k as f64 * v[1] as f64;
                }
            }
        }
        (slant, harmonic)
    }

    /// σs and σa (mm⁻¹) of [`slanted_cube`].
    const SLANTED_CUBE_MEDIUM: (f32, f32) = (0.8, 0.01);

    /// A 16 mm cube (mean free path 1.25 mm, index-matched; 4 × 4 cells a face) walked at
    /// [`SLANTED_CUBE_MEDIUM`]: its S and tilt at the walked σa, and its top face's patches.
    fn slanted_cube() -> (Mesh, Rows, TiltRows, Vec<usize>) {
        let m = mesh([16.0, 16.0, 16.0], 4);
        let n = m.tris.len();
        let (sigma_s, sigma_a) = SLANTED_CUBE_MEDIUM;
        // G is noisier than S (each walk adds ±4 u w): many walks per patch.
        let w = walks(
            &m,
            &SimMedium {
                noise: 0.0,
                max_walks: 16_384,
                ..medium(sigma_s, sigma_a, 1.0)
            },
        );
        let v = view(&w).with_lamp(&w.weight_lamp).expect("lamp weights");
        let (s, _) = reweight(&v, 0..n, &m.area, [sigma_a; 3]);
        let tilt = reweight_tilt(&v, 0..n, [sigma_a; 3]).expect("collimated weights");
        let top: Vec<usize> = (0..n).filter(|&i| m.face[i] == 5).collect();
        (m, s, tilt, top)
    }

    #[test]
    fn a_lamps_own_beams_leave_where_the_beam_walked_directly_does() {
        // The slanted cube's top lit 60° off its normal, toward −x: the lamp's own beams
        // ([`crate::lampwalk`], walked without absorption and re-weighted to σa) against
        // the beam walked directly at σa by the test's own loop ([`beam_exits`]), face by
        // face. The faces differ: ahead of the beam (−x) gets 1.6× what is behind it (+x),
        // and the top's patches are a sixteenth of the other faces' (the areas A_i / A_j
        // must be right).
        let m = mesh([16.0, 16.0, 16.0], 4);
        let (sigma_s, sigma_a) = SLANTED_CUBE_MEDIUM;
        let top: Vec<usize> = (0..m.tris.len()).filter(|&i| m.face[i] == 5).collect();
        let d0 = Vec3::new(-0.866, 0.0, -0.5).normalize();
        // 19,999.5 walks expected per patch: each walks 19,999 or 20,000, at random.
        let beams: Vec<(usize, Vec3, [f32; 3], f64)> = top
            .iter()
            .map(|&i| (i, d0, [1.0, 1.0, 1.0], 19_999.5))
            .collect();
        let built = medium(sigma_s, sigma_a / 4.0, 1.0);
        let (walked, made) = crate::lampwalk::walk_object(
            (0, 0..m.tris.len()),
            &m.tris,
            &m.normal,
            &m.area,
            &built,
            1.0,
            (&beams, &crate::stop::Stop::never()),
        )
        .expect("never stopped");
        let k = top.len() as u64;
        assert!((19_999 * k..=20_000 * k).contains(&made), "{made} walks");
        assert!(
            made != 19_999 * k && made != 20_000 * k,
            "not rounded at random"
        );
        let x = walked.exitance([sigma_a; 3]);
        let mut faces = [0.0f64; 6];
        for (j, v) in x.iter().enumerate() {
            faces[m.face[j]] += m.area[j] as f64 * v[1] as f64;
        }
        let direct = beam_exits(&m, sigma_s, sigma_a, &top, d0);
        for f in 0..6 {
            let r = faces[f] / direct[f];
            assert!(
                (r - 1.0).abs() < 0.03,
                "face {f}: lamp walks {:.4} against the beam walked directly {:.4}",
                faces[f],
                direct[f]
            );
        }
        assert!(faces[0] > 1.4 * faces[1], "{faces:?}");
    }

    #[test]
    fn the_unscattered_walks_tilt_is_a_density_at_most_as_long_as_u() {
        // A thin medium (mean free path 20 mm in a 16 mm cube): most walks cross
        // unscattered, each to the patch its entry direction points at, so a pair's U is a
        // narrow lobe whose least-squares slope is longer than U. The tilt rows keep U's
        // G beside U and no longer than it; pairs seen through a corner reach the limit.
        let m = mesh([16.0, 16.0, 16.0], 4);
        let n = m.tris.len();
        let w = walks(
            &m,
            &SimMedium {
                noise: 0.0,
                max_walks: 4_096,
                ..medium(0.05, 0.01, 1.0)
            },
        );
        let v = view(&w).with_lamp(&w.weight_lamp).expect("lamp weights");
        let tilt = reweight_tilt(&v, 0..n, [0.01; 3]).expect("collimated weights");
        let (mut with_u, mut turned, mut at_limit) = (0, 0, 0);
        for t in tilt.iter().flatten().map(|(_, t)| t) {
            for c in 0..3 {
                let (u, g) = (t[3][c], t[4][c].hypot(t[5][c]));
                assert!(g <= u * (1.0 + 1e-5), "U {u}, its tilt {g}: {t:?}");
                with_u += (u > 0.0) as usize;
                turned += (g > 0.0) as usize;
                at_limit += (g > 0.0 && g >= u * (1.0 - 1e-5)) as usize;
            }
        }
        assert!(turned > with_u / 2, "{turned} of {with_u} U entries turn");
        assert!(
            at_limit > 0 && at_limit < turned,
            "{at_limit} of {turned} at |G| = U"
        );
    }

    #[test]
    fn a_tilt_longer_than_u_is_scaled_to_u_along_its_direction() {
        let mut t = [[0.0f32; 3]; 6];
        t[3] = [0.5, 0.5, 0.0];
        t[4] = [0.3, 0.6, 0.2];
        t[5] = [0.4, -0.8, 0.0];
        let r = with_realizable_u_tilt(t);
        // Channel 0: |G| = 0.5 = U, kept; channel 1: |G| = 1, halved; channel 2: no U,
        // so no tilt.
        assert_eq!((r[4][0], r[5][0]), (0.3, 0.4));
        assert_eq!((r[4][1], r[5][1]), (0.3, -0.4));
        assert_eq!((r[4][2], r[5][2]), (0.0, 0.0));
        assert_eq!(r[..4], t[..4]);
    }

    #[test]
    fn the_first_harmonic_follows_a_slanted_beam() {
        // A 16 mm cube (mean free path 1.25 mm, index-matched), its top lit by a beam 60°
        // off the normal travelling toward −x: light leaves mostly through the face ahead
        // of it (−x). S(μ₀) alone gives −x and +x the same share and counts the diffuse
        // walks' unscattered exits 1.5 times; with the first harmonic (G_u, G_v from the
        // diffuse walks) and U taken out, the model must follow the beam walked directly.
        let (m, s, tilt, top) = slanted_cube();
        let (sigma_s, sigma_a) = SLANTED_CUBE_MEDIUM;
        let names = ["-x", "+x", "-y", "+y", "-z", "+z"];
        for d0 in [Vec3::new(-0.866, 0.0, -0.5), Vec3::new(-0.5, 0.3, -0.8124)] {
            let d0 = d0.normalize();
            let truth = beam_exits(&m, sigma_s, sigma_a, &top, d0);
            let (slant, harmonic) = model_faces(&m, &s, &tilt, 5, d0);
            for f in 0..5 {
                eprintln!(
                    "beam {d0:?} → {}: walked {:.4}, S(μ₀) {:.3}×, with the harmonic and U {:.3}×",
                    names[f],
                    truth[f],
                    slant[f] / truth[f],
                    harmonic[f] / truth[f]
                );
            }
            // The faces ahead of and behind the beam: the worst of the two, much better.
            let worst = |m: &[f64; 6]| {
                [0, 1]
                    .iter()
                    .map(|&f| (m[f] / truth[f] - 1.0).abs())
                    .fold(0.0f64, f64::max)
            };
            let (e_slant, e_model) = (worst(&slant), worst(&harmonic));
            assert!(
                e_model < 0.5 * e_slant,
                "±x: the model's error {e_model} against S(μ₀)'s {e_slant}"
            );
            if d0.z < -0.6 {
                continue;
            }
            // At 60°: S(μ₀) is off by over 30% there, the model within a few per cent, and
            // the bottom too. (The sides along the slant, ±y, come out 15–18% low: the beam
            // runs parallel to them, where their exits have a kink in the beam's azimuth
            // that no short angular expansion follows; docs/validation.md and
            // `measure_a_sixty_degree_beam_by_harmonics`.)
            assert!(e_slant > 0.3, "{e_slant}");
            for f in [0, 1, 4] {
                let err = (harmonic[f] / truth[f] - 1.0).abs();
                assert!(
                    err < 0.06,
                    "{}: {} against {}",
                    names[f],
                    harmonic[f],
                    truth[f]
                );
            }
        }
    }

    /// Face totals of diffuse walks from `sources` (scattered exits only, as [`beam_exits`]),
    /// each weighted by 6 cos 2(φ − φ₀) sin²θ sin²θ₀: the least-squares second azimuthal
    /// harmonic of S for a beam along `d0`, were it sin²θ in the polar angle (6 = 1 / E[(sin²θ
    /// cos 2φ)²] over cosine-weighted directions).
    fn diffuse_second_harmonic(
        m: &Mesh,
        sigma_s: f32,
        sigma_a: f32,
        sources: &[usize],
        d0: Vec3,
    ) -> [f64; 6] {
        let diffuse = (Entry::Diffuse, 100_000, 7, true);
        face_totals(m, (sigma_s, sigma_a), sources, diffuse, |i, t| {
            let n = m.normal[i];
            let t0 = d0 + n * (-d0.dot(n));
            // |t|²|t₀|² cos 2(φ − φ₀), frame-free.
            let c2 = 2.0 * (t.dot(t0) as f64).powi(2)
                - (t.length_squared() * t0.length_squared()) as f64;
            6.0 * c2
        })
    }

    /// A measurement for docs/validation.md (*Still off: the sides along the slant*), not a
    /// check: `cargo test --release -p translux-engine --lib -- --ignored
    /// measure_a_sixty_degree_beam --nocapture`. The 16 mm cube of
    /// [`the_first_harmonic_follows_a_slanted_beam`], its top lit by a beam 60° off the normal
    /// travelling toward −x, walked directly (the truth), against: today's model; beams at
    /// the same 60° walked at 12 azimuths, as a walk set at μ₀ = ½ would store them, summed
    /// as their azimuthal Fourier series to orders 0, 1, 2 and 5 at the beam's azimuth; and
    /// today's model plus a second harmonic estimated from the diffuse walks. Then the side
    /// +y's exits as the beam turns about the normal by a few degrees either way, and the
    /// beam crossing it unscattered.
    #[test]
    #[ignore = "a measurement; run it by name"]
    fn measure_a_sixty_degree_beam_by_harmonics() {
        let (m, s, tilt, top) = slanted_cube();
        let (sigma_s, sigma_a) = SLANTED_CUBE_MEDIUM;
        let (sin_t, cos_t) = (0.75f32.sqrt(), 0.5f32);
        let along = |phi: f32| Vec3::new(-sin_t * phi.cos(), -sin_t * phi.sin(), -cos_t);
        let d0 = along(0.0);
        let truth = beam_exits(&m, sigma_s, sigma_a, &top, d0);
        // Today's model, as `the_first_harmonic_follows_a_slanted_beam` sums it.
        let (_, model) = model_faces(&m, &s, &tilt, 5, d0);
        // The azimuthal series at μ₀ = ½ from 12 walked azimuths (φ = 0 is the beam's).
        const AZ: usize = 12;
        let mut series = [[0.0f64; 6]; 6];
        for k in 0..AZ {
            let phi = (k as f32 + 0.5) / AZ as f32 * std::f32::consts::TAU;
            let e = beam_exits(&m, sigma_s, sigma_a, &top, along(phi));
            for f in 0..6 {
                for (order, acc) in series.iter_mut().enumerate() {
                    // Each order's part at φ = 0: a₀, then a_k cos(k·0) = 2/AZ Σ e cos kφ.
                    let c = if order == 0 {
                        1.0
                    } else {
                        2.0 * (order as f64 * phi as f64).cos()
                    };
                    acc[f] += c * e[f] / AZ as f64;
                }
            }
        }
        let second = diffuse_second_harmonic(&m, sigma_s, sigma_a, &top, d0);
        let names = ["-x", "+x", "-y", "+y", "-z", "+z"];
        eprintln!(
            "face | walked | model | μ₀=½ order 0 | ≤ 1 | ≤ 2 | ≤ 5 | model + diffuse 2nd harmonic"
        );
        for f in 0..6 {
            let r = |x: f64| x / truth[f];
            let upto = |k: usize| series[..=k].iter().map(|o| o[f]).sum::<f64>();
            eprintln!(
                "{} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3}",
                names[f],
                truth[f],
                r(model[f]),
                r(upto(0)),
                r(upto(1)),
                r(upto(2)),
                r(upto(5)),
                r(model[f] + second[f]),
            );
        }
        for deg in [-10.0f32, -5.0, -2.0, 0.0, 2.0, 5.0, 10.0] {
            let d = along(deg.to_radians());
            let e = beam_exits(&m, sigma_s, sigma_a, &top, d);
            let beam = (Entry::Along(d), 40_000, 99, false);
            let crossing = face_totals(&m, (sigma_s, sigma_a), &top, beam, |_, _| 1.0);
            eprintln!(
                "beam turned {deg:+}° (toward −y when positive): +y {:.3}, crossing +y unscattered {:.3}",
                e[3], crossing[3]
            );
        }
    }

    #[test]
    fn one_pass_gives_s_and_the_collimated_difference() {
        // Δ from the fused pass against S⁽ⁿ⁾ re-weighted on its own (the collimated
        // weights read as if they were the diffuse ones) minus S, at two absorptions.
        let m = mesh([12.0, 12.0, 12.0], 4);
        let n = m.tris.len();
        let w = walks(&m, &medium(1.0, 0.02, 1.0));
        let normal_only =
            WalksView::new_checked(n, &w.row_ptr, &w.col, &w.bin, &w.weight_normal, None)
                .expect("valid walks");
        for sigma_a in [[0.02f32; 3], [0.05, 0.1, 0.2]] {
            let (s, delta, max) = reweight_with_tilt(&view(&w), 0..n, &m.area, sigma_a);
            let delta = delta.expect("collimated weights");
            let (s_alone, max_alone) = reweight(&view(&w), 0..n, &m.area, sigma_a);
            assert_eq!(s, s_alone, "S is the same with or without Δ");
            assert_eq!(max, max_alone);
            let (s_n, _) = reweight(&normal_only, 0..n, &m.area, sigma_a);
            let (mut d2, mut n2, mut entries) = (0.0f64, 0.0f64, 0usize);
            for j in 0..n {
                assert_eq!(delta[j].len(), s[j].len(), "Δ's row {j} has S's sources");
                // S⁽ⁿ⁾'s sources are a subset of the union; compare by source.
                let get = |row: &[(u32, [f32; 3])], i: u32| {
                    row.iter()
                        .find(|(c, _)| *c == i)
                        .map_or([0.0; 3], |(_, v)| *v)
                };
                for &(i, [d, ..]) in &delta[j] {
                    let want = get(&s_n[j], i);
                    let have = get(&s[j], i);
                    for c in 0..3 {
                        let x = (want[c] - have[c]) as f64;
                        d2 += (d[c] as f64 - x).powi(2);
                        n2 += x * x;
                    }
                    entries += 1;
                }
                // Every source S⁽ⁿ⁾ has in this row is one of Δ's.
                for (i, _) in &s_n[j] {
                    assert!(delta[j].iter().any(|(c, _)| c == i), "row {j} source {i}");
                }
            }
            assert!(entries > n, "{entries} entries");
            let rel = (d2 / n2).sqrt();
            assert!(
                rel < 1e-5,
                "σa {sigma_a:?}: ‖Δ − (S⁽ⁿ⁾ − S)‖ / ‖S⁽ⁿ⁾ − S‖ = {rel}"
            );
        }
    }

    #[test]
    fn a_dielectric_boundary_loses_only_the_fresnel_reflection() {
        // No absorption: every walk that enters leaves, so a column re-emits the mean
        // Fresnel transmittance of diffuse light, 1 − 2 ∫ F(μ) μ dμ.
        let m = mesh([20.0, 20.0, 20.0], 4);
        let w = walks(&m, &medium(1.0, 0.0, 1.4));
        let e = column_energy(&m, &w, [0.0; 3]);
        let k = 20_000;
        let fdr: f64 = (0..k)
            .map(|q| {
                let mu = (q as f64 + 0.5) / k as f64;
                2.0 * fresnel_dielectric(mu as f32, 1.4) as f64 * mu / k as f64
            })
            .sum();
        let mean: f64 = e.iter().map(|v| v[0]).sum::<f64>() / e.len() as f64;
        eprintln!("re-emitted {mean:.4}, 1 − F_dr = {:.4}", 1.0 - fdr);
        assert!((mean - (1.0 - fdr)).abs() < 0.01);
    }

    #[test]
    fn overrides_may_change_absorption_only() {
        let built = medium(1.0, 0.01, 1.3);
        let mut new = built;
        new.sigma_a = [0.02; 3];
        assert!(check_override(&built, &new).is_ok());
        new.sigma_a = [0.0001; 3];
        assert!(check_override(&built, &new).unwrap_err().contains("below"));
        let mut new = built;
        new.sigma_s = [2.0; 3];
        assert!(
            check_override(&built, &new)
                .unwrap_err()
                .contains("scattering")
        );
        let mut new = built;
        new.eta = 1.0;
        assert!(check_override(&built, &new).unwrap_err().contains("eta"));
    }
}
