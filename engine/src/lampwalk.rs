//! A relight's lamps walked into its simulated objects along their own beams
//! (`"lamp_walks"` in a relight request): the first scattering of their light as the medium
//! sends it, where [`crate::collimated`] models it from walks that entered diffusely and
//! along the normal (S(μ₀), its first harmonic in the tilt, and U). That model leaves the
//! faces a beam runs along 7–10% dark (a 16 mm cube lit 60° off its top's normal,
//! docs/validation.md): their exitance has a kink in the beam's azimuth that no short
//! angular expansion follows. Walks along each lamp's own direction have no such limit.
//! They cost seconds to minutes, not milliseconds, so a script asks for them once its
//! lamps are placed; they are made once per set of lights and kept, and like S's records
//! they are binned by path length, so that an absorption change re-weights them instead of
//! walking again.
//!
//! In: the bundle's patches and occluder, each simulated object's medium (its built
//! material: σs, g, η, the absorption floor; the relight's: σa), the relight's lights and
//! the walks per lamp. The walks of all lamps are shared out over the lit patches by the
//! power each receives (A_i E′_i), so each walk carries the same power and the time does
//! not grow with the patch count; a patch's share is rounded at random (unbiased). Out:
//! [`LampWalks`], whose [`LampWalks::add_correction`] is what a relight adds to the lamps'
//! first scattering y ([`crate::collimated`]) so that S E + y at the simulated patches is
//! the walked exitance:
//!
//! ```text
//!   c = X − (S E′ + Δ E′_t + G_u E′_u + G_v E′_v + U E′_w)
//! ```
//!
//! with X the walked exitance, E′ the lamps' irradiance at the lit patches' centroids (what
//! was walked) and E′_t … E′_w its moments ([`crate::collimated::tilted_irradiance`]). Where
//! the relight's own E differs from E′ (E is a patch's mean), S carries the difference as
//! before. As in the stored walks, a beam that crosses the object without scattering is
//! the lamp seen through it, not exitance, and is left out.
//!
//! Why by hand: the walks are [`crate::simulated`]'s own walker (no crate walks a medium
//! inside a mesh and keeps path lengths).

use std::ops::Range;
use std::time::{Duration, Instant};

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use translux_proto::bundle::Bundle;
use translux_proto::light::Light;
use translux_proto::scene::Material;

use crate::collimated::{Tilt, add_first_scatter, tilted_irradiance};
use crate::error::EngineError;
use crate::linalg::{Rgb, Scatter};
use crate::radiosity::{PatchGeometry, PointLights};
use crate::raycast::Occluder;
use crate::simulated::{self, SimMedium};
use crate::stop::{Reason, Stop};

/// The most walks a relight may ask per lamp (each group of channels with its own σs walks
/// as many again). What a walk costs depends on the medium and the object's size: 1.6
/// µs·core on a 16 mm cube, 150 in the Cornell box's marble block (bench/results/HISTORY.md).
pub const MAX_LAMP_WALKS: u32 = 10_000_000;

/// The walked exitance of one set of lights in every simulated object.
#[derive(Debug)]
pub struct LampWalks {
    objects: Vec<ObjectWalks>,
    /// E′: the lamps' irradiance at the simulated patches' centroids (zero elsewhere).
    e: Vec<Rgb>,
    /// Its moments [E′_t, E′_u, E′_v, E′_w] ([`tilted_irradiance`]).
    moments: Vec<[Rgb; 4]>,
    /// Walks made, and lit patches they started from.
    pub walks: u64,
    pub sources: u64,
    /// Wall time, s.
    pub seconds: f64,
}

/// What a relight adds to S E for `lights` on `bundle` with its own materials, their first
/// scattering walked along their beams (`per` walks per lamp): y = X − S E′,
/// per patch (as [`crate::collimated::first_scatter`] gives the model's). `None` where
/// that has nothing to add.
pub fn first_scatter(
    bundle: &Bundle,
    geo: PatchGeometry<'_>,
    occ: &Occluder,
    lights: &[Light],
    per: u32,
) -> Option<Vec<Rgb>> {
    let tilt = crate::collimated::own_tilt(bundle)?;
    let materials = crate::smatrix::materials_with(bundle, &[]);
    let walked = LampWalks::walk(
        bundle,
        geo,
        occ,
        (lights, &materials),
        &tilt,
        per,
        (&Stop::never(), None),
    )
    .ok()??;
    let s = crate::transport::subsurface_operator(bundle, bundle.subsurface());
    let mut se = vec![[0.0f32; 3]; walked.e.len()];
    s.apply(&walked.e, &mut se);
    let mut y = walked.exitance(&materials);
    for (y, se) in y.iter_mut().zip(&se) {
        for c in 0..3 {
            y[c] -= se[c];
        }
    }
    Some(y)
}

/// One object's walked exitance per receiver and path-length bin, before absorption.
#[derive(Debug)]
pub(crate) struct ObjectWalks {
    /// Index into the manifest's objects (the relight's σa is read from its material).
    object: usize,
    range: Range<usize>,
    /// Receiver j's (local) records are `row_ptr[j]..row_ptr[j + 1]`, bins ascending.
    row_ptr: Vec<u32>,
    bin: Vec<u32>,
    /// Exitance (power over A_j) per channel.
    w: Vec<Rgb>,
}

impl LampWalks {
    /// Walks `per` beams per lamp of `lights` into the simulated objects, shared out over
    /// the lit patches by power (`materials`: the relight's, one per manifest object).
    /// `Ok(None)` when no lamp lights a simulated object. The streams are seeded by the
    /// material's `seed` and the beam, so the walks do not depend on the thread count.
    ///
    /// `stop` ends the walks early (an error of kind `Cancelled`), and so does `limit`,
    /// the most time they may take (kind `OverLimit`, with the time all of them would
    /// take, estimated from the walks made): a request's cost is bounded and the walks
    /// stop within a few milliseconds of either.
    pub fn walk(
        bundle: &Bundle,
        geo: PatchGeometry<'_>,
        occ: &Occluder,
        (lights, materials): (&[Light], &[&Material]),
        tilt: &Tilt,
        per: u32,
        (stop, limit): (&Stop, Option<Duration>),
    ) -> Result<Option<LampWalks>, EngineError> {
        let start = Instant::now();
        let stop = match limit {
            Some(limit) => stop.clone().until(start + limit),
            None => stop.clone(),
        };
        Self::walk_until(bundle, geo, occ, (lights, materials), tilt, per, &stop).map_err(|made| {
            let elapsed = start.elapsed().as_secs_f64();
            match stop.reason() {
                Some(Reason::Time) => {
                    let lamps = lights.len().max(1) as f64;
                    let all = per as f64 * lamps;
                    EngineError::over_limit(format!(
                        "lamp_walks: stopped at this request's limit of {:.1} s of \
                         walks, with about {made} of its {all:.0} walks made; all of \
                         them would take about {:.0} s. Ask fewer walks per lamp, or \
                         use a token whose role has a higher limit",
                        limit.map_or(elapsed, |l| l.as_secs_f64()),
                        elapsed * all / made.max(1) as f64
                    ))
                }
                _ => EngineError::cancelled(
                    "lamp_walks: stopped (the client went away or the server is stopping)",
                ),
            }
        })
    }

    /// [`LampWalks::walk`] until `stop`: `Err` with the walks made when it fired.
    fn walk_until(
        bundle: &Bundle,
        geo: PatchGeometry<'_>,
        occ: &Occluder,
        (lights, materials): (&[Light], &[&Material]),
        tilt: &Tilt,
        per: u32,
        stop: &Stop,
    ) -> Result<Option<LampWalks>, u64> {
        let start = Instant::now();
        let manifest = bundle.manifest();
        let unit_mm = manifest.unit_mm;
        let lamps = PointLights::new(lights, occ, unit_mm);
        if lamps.is_empty() || per == 0 {
            return Ok(None);
        }
        let Some(moments) = tilted_irradiance(geo, occ, lights, unit_mm, tilt) else {
            return Ok(None);
        };
        let n = geo.centroid.len();
        let corners_all = crate::smatrix::bundle_geometry(bundle).corners;
        let area_all = bundle.patch_areas();
        let mut e = vec![[0.0f32; 3]; n];
        // Per simulated object: its index, patches, built medium and lit patches' beams
        // (local i, travel direction, irradiance, power A_i Σ E).
        type Beam = (usize, Vec3, Rgb, f64);
        let mut media: Vec<(usize, Range<usize>, SimMedium, Vec<Beam>)> = Vec::new();
        for (k, (o, m)) in manifest.objects.iter().zip(materials).enumerate() {
            let (Some(built), Some(_)) = (SimMedium::of(&o.material), SimMedium::of(m)) else {
                continue;
            };
            let range = o.first_patch as usize..(o.first_patch + o.patch_count) as usize;
            let mut beams = Vec::new();
            for i in range.clone() {
                lamps.each(geo.centroid[i], geo.normal[i], |l, c| {
                    if c.iter().any(|v| *v > 0.0) && l.dot(geo.normal[i]) > 0.0 {
                        let power = area_all[i] as f64 * c.iter().map(|v| *v as f64).sum::<f64>();
                        beams.push((i - range.start, -l, c, power));
                        for ch in 0..3 {
                            e[i][ch] += c[ch];
                        }
                    }
                });
            }
            if !beams.is_empty() {
                media.push((k, range, built, beams));
            }
        }
        let total: f64 = media.iter().flat_map(|m| &m.3).map(|b| b.3).sum();
        if total <= 0.0 || !total.is_finite() {
            return Ok(None);
        }
        let budget = per as f64 * lamps.len() as f64;
        let (mut objects, mut walks, mut sources) = (Vec::new(), 0u64, 0u64);
        for (k, range, built, mut beams) in media {
            // Each beam's power becomes the walks it is expected to get.
            for b in &mut beams {
                b.3 *= budget / total;
            }
            sources += beams.len() as u64;
            let (obj, made) = walk_object(
                (k, range.clone()),
                &corners_all[range.clone()],
                &geo.normal[range.clone()],
                &area_all[range],
                &built,
                unit_mm,
                (&beams, stop),
            )
            .map_err(|made| walks + made)?;
            walks += made;
            objects.push(obj);
        }
        if objects.is_empty() {
            return Ok(None);
        }
        Ok(Some(LampWalks {
            objects,
            e,
            moments,
            walks,
            sources,
            seconds: start.elapsed().as_secs_f64(),
        }))
    }

    /// Adds c = X − (S E′ + the tilt's product with E′'s moments) to `y` (`[patch][rgb]`,
    /// all patches) under `materials` (the relight's; σa re-weights the walks), `s` and
    /// `tilt` the relight's S and tilt.
    pub fn add_correction(
        &self,
        materials: &[&Material],
        s: &dyn Scatter,
        tilt: &Tilt,
        y: &mut [f32],
    ) {
        let n = self.e.len();
        let mut model = vec![[0.0f32; 3]; n];
        s.apply(&self.e, &mut model);
        let flat = bytemuck::cast_slice_mut::<Rgb, f32>(&mut model);
        add_first_scatter(tilt, self.moments.as_flattened().as_flattened(), 1, flat);
        for o in &self.objects {
            let Some(medium) = materials.get(o.object).and_then(|m| SimMedium::of(m)) else {
                continue;
            };
            for (x, j) in o.exitance(medium.sigma_a).into_iter().zip(o.range.clone()) {
                for c in 0..3 {
                    y[3 * j + c] += x[c] - model[j][c];
                }
            }
        }
    }

    /// The walked exitance X (before any inter-reflection) under `materials`, all patches
    /// (zero outside the simulated objects).
    pub fn exitance(&self, materials: &[&Material]) -> Vec<Rgb> {
        let mut x = vec![[0.0f32; 3]; self.e.len()];
        for o in &self.objects {
            let Some(medium) = materials.get(o.object).and_then(|m| SimMedium::of(m)) else {
                continue;
            };
            x[o.range.clone()].copy_from_slice(&o.exitance(medium.sigma_a));
        }
        x
    }
}

impl ObjectWalks {
    /// The walked exitance at absorption `sigma_a` (mm⁻¹), per local receiver.
    pub(crate) fn exitance(&self, sigma_a: [f32; 3]) -> Vec<Rgb> {
        let att = simulated::attenuation(sigma_a);
        (0..self.row_ptr.len() - 1)
            .map(|k| {
                let mut x = [0.0f32; 3];
                for r in self.row_ptr[k] as usize..self.row_ptr[k + 1] as usize {
                    let a = att[self.bin[r] as usize];
                    for c in 0..3 {
                        x[c] += self.w[r][c] * a[c];
                    }
                }
                x
            })
            .collect()
    }
}

/// A walk's exit: receiver (local), path-length bin, exitance per channel.
type Record = (u32, u32, Rgb);

/// Walks made between merges of the records ([`walk_object`]).
const CHUNK_WALKS: f64 = 2_000_000.0;

/// `recs` sorted by receiver and bin, each pair's records summed into one (in the order
/// they came: the sort is stable, so the sums do not depend on the thread count).
fn merged(mut recs: Vec<Record>) -> Vec<Record> {
    recs.sort_by_key(|r| (r.0, r.1));
    let mut out: Vec<Record> = Vec::with_capacity(recs.len());
    for (j, b, v) in recs {
        match out.last_mut() {
            Some(last) if last.0 == j && last.1 == b => {
                for (acc, x) in last.2.iter_mut().zip(v) {
                    *acc += x;
                }
            }
            _ => out.push((j, b, v)),
        }
    }
    out
}

/// The walks of manifest object `object`, its patches `range` (`corners`, `normal` and
/// `area` are theirs, local): `beams` as (local source, travel direction, irradiance, walks
/// expected), each group of channels sharing σs walking a beam's expected count rounded at
/// random (so each walk carries A_i E / expected, and the sum is unbiased). Returns the
/// object's records and the walks made. Each beam's stream is seeded by the material's
/// seed, the object's first patch and the beam's index. `Err` with the walks made (a bound:
/// the chunk under way counts whole) where `stop` fired.
pub(crate) fn walk_object(
    (object, range): (usize, Range<usize>),
    corners: &[[Vec3; 3]],
    normal: &[Vec3],
    area: &[f32],
    medium: &SimMedium,
    unit_mm: f64,
    (beams, stop): (&[(usize, Vec3, Rgb, f64)], &Stop),
) -> Result<(ObjectWalks, u64), u64> {
    let first_patch = range.start as u64;
    let n = corners.len();
    let frame = simulated::WalkFrame::new(corners, unit_mm);
    let groups = medium.groups();
    let floor = medium.floor();
    // (receiver, bin, exitance per channel) per beam, and the walks made.
    // Chunks of about CHUNK_WALKS walks, each merged into `all` as it is done, so what is
    // held at once is the distinct (receiver, bin) records, not one per walk.
    let mut chunks: Vec<Range<usize>> = Vec::new();
    let (mut from, mut acc) = (0usize, 0.0f64);
    for (b, beam) in beams.iter().enumerate() {
        acc += beam.3 * groups.len() as f64;
        if acc >= CHUNK_WALKS {
            chunks.push(from..b + 1);
            (from, acc) = (b + 1, 0.0);
        }
    }
    if from < beams.len() {
        chunks.push(from..beams.len());
    }
    let (mut all, mut walks): (Vec<Record>, u64) = (Vec::new(), 0);
    for chunk in chunks {
        let recs: Vec<(Vec<Record>, u64)> = beams[chunk.clone()]
            .par_iter()
            .enumerate()
            .map(|(k, &(i, d, c, expected))| {
                let b = chunk.start + k;
                let (mut out, mut made) = (Vec::new(), 0u64);
                if stop.is_set() {
                    return (out, made);
                }
                for (gi, group) in groups.iter().enumerate() {
                    let fl = group
                        .iter()
                        .map(|&ch| floor[ch])
                        .fold(f32::INFINITY, f32::min);
                    let mut rng = ChaCha8Rng::seed_from_u64(medium.seed ^ 0x6c61_6d70);
                    rng.set_stream(((first_patch + b as u64) << 2) | gi as u64);
                    let count = (expected + rng.random::<f64>()).floor() as u32;
                    made += count as u64;
                    let scale = (area[i] as f64 / expected) as f32;
                    frame.walk_beams(
                        (normal, area),
                        (medium.sigma_s[group[0]], medium.g, medium.eta, fl),
                        (i, d, count),
                        &mut rng,
                        stop,
                        |j, mm, weight| {
                            let aj = area[j as usize].max(f32::MIN_POSITIVE);
                            let mut v = [0.0f32; 3];
                            for &ch in group {
                                v[ch] = weight * scale * c[ch] / aj;
                            }
                            out.push((j, simulated::bin_of(mm), v));
                        },
                    );
                }
                (merged(out), made)
            })
            .collect();
        walks += recs.iter().map(|r| r.1).sum::<u64>();
        if stop.is_set() {
            // Part of this chunk's walks were not made: nothing of it is kept.
            return Err(walks);
        }
        all.extend(recs.into_iter().flat_map(|r| r.0));
        all = merged(all);
    }
    let mut row_ptr = vec![0u32; n + 1];
    let (mut bin, mut w): (Vec<u32>, Vec<Rgb>) = (Vec::new(), Vec::new());
    for (j, b, v) in all {
        row_ptr[j as usize + 1] += 1;
        bin.push(b);
        w.push(v);
    }
    for k in 0..n {
        row_ptr[k + 1] += row_ptr[k];
    }
    Ok((
        ObjectWalks {
            object,
            range,
            row_ptr,
            bin,
            w,
        },
        walks,
    ))
}
