//! Per-patch environment visibility: what lets an environment relight cast no rays.
//!
//! In: patch centroids and normals, the scene's [`Occluder`], and a direction partition
//! [`Bins`]. Out: for every patch i and bin k (row-major `[N, rows, cols]`, W·m⁻² per
//! W·m⁻²·sr⁻¹)
//!
//! ```text
//!     V_ik = ∫_bin k  visible_i(ω) max(n_i·ω, 0) dω
//! ```
//!
//! so that an environment of mean radiance L̄_k over bin k gives the irradiance
//! E_i = Σ_k V_ik L̄_k ([`environment_irradiance`]). An unoccluded patch has Σ_k V_ik = π.
//!
//! Estimation, per bin: the cosine is integrated on a `cos_grid × cos_grid` grid of
//! equal-area cells (no rays); visibility comes from `rays × rays` stratified rays, one per
//! block of cells, each cast through a jittered point of a cell of its block that faces the
//! patch (so rays never start into the patch's own surface). A block's cells take its ray's
//! answer. Bins entirely behind the patch cost nothing.

use glam::Vec3;
use rayon::prelude::*;

use crate::envmap::Bins;
use crate::raycast::Occluder;

/// Settings of [`visibility`] (defaults: 16 × 32 bins, 4 × 4 cosine cells and 2 × 2 rays
/// per bin; measured in `docs/environment.md`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EnvVisParams {
    /// The partition; `None` disables the stage (the bundle then holds no visibility and
    /// environment lights are refused for it).
    pub bins: Option<Bins>,
    /// Cosine cells per bin side.
    pub cos_grid: u32,
    /// Rays per bin side (must divide `cos_grid`).
    pub rays: u32,
    /// Seed of the jitter.
    pub seed: u64,
}

impl Default for EnvVisParams {
    fn default() -> Self {
        EnvVisParams {
            bins: Some(DEFAULT_BINS),
            cos_grid: 4,
            rays: 2,
            seed: 0x5eed_e4f1,
        }
    }
}

/// The default partition: 16 bands × 32 columns = 512 bins of 0.0245 sr each.
pub const DEFAULT_BINS: Bins = Bins { rows: 16, cols: 32 };

/// What [`visibility`] did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct EnvVisStats {
    pub rays: u64,
}

/// Parses `--env-bins`: `ROWSxCOLS` (e.g. `16x32`, each 1–256) or `0`/`off` (no stage).
pub fn parse_bins(text: &str) -> Result<Option<Bins>, String> {
    let t = text.trim();
    if t == "0" || t.eq_ignore_ascii_case("off") {
        return Ok(None);
    }
    let bad =
        || format!("--env-bins must be ROWSxCOLS (e.g. 16x32, each 1 to 256) or 0, got {t:?}");
    let (r, c) = t.split_once(['x', 'X']).ok_or_else(bad)?;
    let rows: u32 = r.trim().parse().map_err(|_| bad())?;
    let cols: u32 = c.trim().parse().map_err(|_| bad())?;
    if !(1..=256).contains(&rows) || !(1..=256).contains(&cols) {
        return Err(bad());
    }
    Ok(Some(Bins { rows, cols }))
}

/// SplitMix64: a small, well-mixed hash for reproducible jitter.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

fn unit(h: u64) -> f32 {
    (h >> 40) as f32 / (1u64 << 24) as f32
}

/// ∫ ω dω over the part of the sphere with y ∈ [y_lo, y_hi] and φ ∈ [φ0, φ1] (ω as in
/// [`crate::envmap`]: (sin θ sin φ, y, −sin θ cos φ), dω = dy dφ).
fn moment(y_lo: f64, y_hi: f64, phi0: f64, phi1: f64) -> Vec3 {
    // ∫ √(1 − y²) dy = ½ (y √(1 − y²) + asin y)
    let f = |y: f64| 0.5 * (y * (1.0 - y * y).max(0.0).sqrt() + y.clamp(-1.0, 1.0).asin());
    let sy = f(y_hi) - f(y_lo);
    Vec3::new(
        (sy * (phi0.cos() - phi1.cos())) as f32,
        (0.5 * (y_hi * y_hi - y_lo * y_lo) * (phi1 - phi0)) as f32,
        (-sy * (phi1.sin() - phi0.sin())) as f32,
    )
}

/// Sub-samples per side of a cell that the horizon crosses.
const HORIZON_SUB: u32 = 4;

/// V of the patches `rows` as `[rows · K]` f32 (patch-major), with `progress(k)` called as
/// patches finish. A patch's rays are seeded by its index among all the patches, so V of a
/// share of the rows is that share of V of all of them (a precompute's shards).
///
/// Cosine part: a cell that faces the patch entirely (all four corners in front) is
/// integrated exactly, n·∫_cell ω dω; a cell the horizon crosses by a 4 × 4 midpoint rule.
#[allow(clippy::too_many_arguments)]
pub fn visibility(
    centroid: &[Vec3],
    normal: &[Vec3],
    owner: Option<&[u32]>,
    rows: std::ops::Range<usize>,
    occ: &Occluder,
    bins: Bins,
    params: &EnvVisParams,
    progress: &(dyn Fn(u64) + Sync),
) -> (Vec<f32>, EnvVisStats) {
    let k_count = bins.count();
    let g = params.cos_grid.clamp(1, 16) as usize;
    let r = (params.rays.max(1) as usize).min(g);
    let block = g.div_ceil(r);
    let cell_omega = bins.solid_angle() / (g * g) as f32;
    let offset = 1e-5 * occ.diagonal();
    let far = 4.0 * occ.diagonal();
    let lat = (g + 1) * (g + 1);
    // Per bin: the (g+1)² lattice of cell corners and the g² cell moments ∫ ω dω.
    let lattice: Vec<Vec3> = (0..k_count)
        .flat_map(|k| {
            (0..lat).map(move |p| {
                bins.direction(
                    k,
                    (p % (g + 1)) as f32 / g as f32,
                    (p / (g + 1)) as f32 / g as f32,
                )
            })
        })
        .collect();
    let moments: Vec<Vec3> = (0..k_count)
        .flat_map(|k| {
            let (row, col) = (k / bins.cols as usize, k % bins.cols as usize);
            (0..g * g).map(move |c| {
                let (cx, cy) = (c % g, c / g);
                let (rows, cols) = (f64::from(bins.rows), f64::from(bins.cols));
                let y_hi = 1.0 - 2.0 * (row as f64 + cy as f64 / g as f64) / rows;
                let y_lo = 1.0 - 2.0 * (row as f64 + (cy + 1) as f64 / g as f64) / rows;
                let tau = 2.0 * std::f64::consts::PI;
                let phi0 = tau * (col as f64 + cx as f64 / g as f64) / cols;
                let phi1 = tau * (col as f64 + (cx + 1) as f64 / g as f64) / cols;
                moment(y_lo, y_hi, phi0, phi1)
            })
        })
        .collect();
    let mut out = vec![0.0f32; rows.len() * k_count];
    let rays: u64 = out
        .par_chunks_mut(k_count)
        .enumerate()
        .map(|(i, row)| {
            let i = rows.start + i;
            let n = normal[i];
            let origin = centroid[i] + n * offset;
            // A face pressed against another (a block's base on the floor) sees nothing of
            // the sky; its offset origin would be below the floor, outside the room.
            let own = owner.and_then(|o| o.get(i)).copied().unwrap_or(u32::MAX);
            if occ.buried(centroid[i], n, occ.contact_step(), own) {
                progress(1);
                return 0;
            }
            let mut rays = 0u64;
            let mut cos = vec![0.0f32; lat];
            let mut cell = vec![0.0f32; g * g];
            for (k, v) in row.iter_mut().enumerate() {
                let corners = &lattice[k * lat..(k + 1) * lat];
                let mut any = false;
                for (c, d) in cos.iter_mut().zip(corners) {
                    *c = n.dot(*d);
                    any |= *c > 0.0;
                }
                if !any {
                    continue;
                }
                // ∫_cell max(n·ω, 0) dω for every cell.
                for (c, val) in cell.iter_mut().enumerate() {
                    let (cx, cy) = (c % g, c / g);
                    let q = [
                        cos[cy * (g + 1) + cx],
                        cos[cy * (g + 1) + cx + 1],
                        cos[(cy + 1) * (g + 1) + cx],
                        cos[(cy + 1) * (g + 1) + cx + 1],
                    ];
                    *val = if q.iter().all(|&x| x > 0.0) {
                        n.dot(moments[k * g * g + c]).max(0.0)
                    } else if q.iter().all(|&x| x <= 0.0) {
                        0.0
                    } else {
                        let m = HORIZON_SUB;
                        let mut acc = 0.0;
                        for sy in 0..m {
                            for sx in 0..m {
                                let s = (cx as f32 + (sx as f32 + 0.5) / m as f32) / g as f32;
                                let t = (cy as f32 + (sy as f32 + 0.5) / m as f32) / g as f32;
                                acc += n.dot(bins.direction(k, s, t)).max(0.0);
                            }
                        }
                        acc * cell_omega / (m * m) as f32
                    };
                }
                let mut acc = 0.0f32;
                for by in 0..r {
                    for bx in 0..r {
                        // The block's cells that receive light, and their total.
                        let mut lit = [0usize; 256];
                        let mut m = 0usize;
                        let mut w = 0.0f32;
                        for cy in by * block..((by + 1) * block).min(g) {
                            for cx in bx * block..((bx + 1) * block).min(g) {
                                let c = cy * g + cx;
                                if cell[c] > 0.0 {
                                    lit[m] = c;
                                    m += 1;
                                    w += cell[c];
                                }
                            }
                        }
                        if m == 0 {
                            continue;
                        }
                        // One ray through a jittered point of a random lit cell.
                        let h = mix(params.seed
                            ^ (i as u64).wrapping_mul(0x1000_0000_01b3)
                            ^ ((k as u64) << 24)
                            ^ (by * r + bx) as u64);
                        let c = lit[(unit(h) * m as f32) as usize % m];
                        let (cx, cy) = (c % g, c / g);
                        let h2 = mix(h);
                        let s = (cx as f32 + unit(h2)) / g as f32;
                        let t = (cy as f32 + unit(mix(h2))) / g as f32;
                        let mut d = bins.direction(k, s, t);
                        if n.dot(d) <= 0.0 {
                            // The jitter fell behind the horizon: the cell's best corner.
                            let best = [
                                cy * (g + 1) + cx,
                                cy * (g + 1) + cx + 1,
                                (cy + 1) * (g + 1) + cx,
                                (cy + 1) * (g + 1) + cx + 1,
                            ]
                            .into_iter()
                            .max_by(|a, b| cos[*a].total_cmp(&cos[*b]))
                            .unwrap_or(0);
                            d = corners[best];
                        }
                        rays += 1;
                        if !occ.occluded_dir(origin, d, 0.0, far) {
                            acc += w;
                        }
                    }
                }
                *v = acc;
            }
            progress(1);
            rays
        })
        .sum();
    (out, EnvVisStats { rays })
}

/// Rows [`stage`] traces at once (their f32 values, 2 KiB a row at 512 bins, live only
/// until converted).
const STAGE_RUN: usize = 8192;

/// The precompute stage: V for the patches `rows` (all of them on one box) as IEEE
/// half-float bits (the bundle's `env_visibility.f16`, `[N, rows, cols]`) and its manifest
/// entry, or `None` when `params.bins` is `None`. f16 keeps 11 significant bits: a relative error ≤ 2⁻¹¹ per
/// entry, far below the estimate's own (see `docs/environment.md`).
pub fn stage(
    centroid: &[Vec3],
    normal: &[Vec3],
    owner: Option<&[u32]>,
    rows: std::ops::Range<usize>,
    occ: &Occluder,
    params: &EnvVisParams,
    progress: &(dyn Fn(u64) + Sync),
) -> Option<(Vec<u16>, translux_proto::bundle::EnvironmentInfo)> {
    let bins = params.bins?;
    let t = std::time::Instant::now();
    let patches = Patches {
        centroid,
        normal,
        owner,
    };
    let (bits, rays) = half_rows(patches, rows, occ, (bins, params), STAGE_RUN, progress);
    Some((
        bits,
        translux_proto::bundle::EnvironmentInfo {
            rows: bins.rows,
            cols: bins.cols,
            cos_grid: params.cos_grid,
            rays_per_side: params.rays,
            rays,
            seconds: t.elapsed().as_secs_f64(),
        },
    ))
}

/// The patches [`visibility`] reads: centroids, normals and (optionally) each one's object.
#[derive(Clone, Copy)]
struct Patches<'a> {
    centroid: &'a [Vec3],
    normal: &'a [Vec3],
    owner: Option<&'a [u32]>,
}

/// V for `rows` as half-float bits, traced `run` rows at a time, and the rays cast. Each
/// run is kept as half floats at once, so the stage holds 2 bytes a bin for every patch
/// and 4 only for one run's (at a million patches of the default 512 bins, 1 GiB instead
/// of 3), which the precompute's memory estimate counts. Rows are independent (a row's
/// jitter is seeded by its index), so the values are those of one pass.
fn half_rows(
    p: Patches<'_>,
    rows: std::ops::Range<usize>,
    occ: &Occluder,
    (bins, params): (Bins, &EnvVisParams),
    run: usize,
    progress: &(dyn Fn(u64) + Sync),
) -> (Vec<u16>, u64) {
    let mut bits = Vec::with_capacity(rows.len() * bins.count());
    let mut rays = 0;
    let mut start = rows.start;
    while start < rows.end {
        let these = start..start.saturating_add(run.max(1)).min(rows.end);
        let (v, stats) = visibility(
            p.centroid,
            p.normal,
            p.owner,
            these.clone(),
            occ,
            bins,
            params,
            progress,
        );
        bits.par_extend(v.par_iter().map(|&x| half::f16::from_f32(x).to_bits()));
        rays += stats.rays;
        start = these.end;
    }
    (bits, rays)
}

/// E_i = scale · Σ_k V_ik L̄_k for every patch (`v` is `[N · K]`, `mean` the map's per-bin
/// mean radiance from [`crate::envmap::bin_radiance`]); adds into `e`.
pub fn environment_irradiance(v: &[f32], mean: &[[f32; 3]], scale: f32, e: &mut [[f32; 3]]) {
    let k = mean.len();
    if k == 0 {
        return;
    }
    e.par_iter_mut()
        .zip(v.par_chunks_exact(k))
        .with_min_len(64)
        .for_each(|(ei, row)| {
            let mut acc = [0.0f32; 3];
            for (&vik, l) in row.iter().zip(mean) {
                acc[0] += vik * l[0];
                acc[1] += vik * l[1];
                acc[2] += vik * l[2];
            }
            for c in 0..3 {
                ei[c] += scale * acc[c];
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::envmap::{EnvMap, bin_radiance};
    use std::f32::consts::PI;

    fn quad(y: f32, half: f32) -> [[Vec3; 3]; 2] {
        let a = Vec3::new(-half, y, -half);
        let b = Vec3::new(half, y, -half);
        let c = Vec3::new(half, y, half);
        let d = Vec3::new(-half, y, half);
        [[a, c, b], [a, d, c]]
    }

    /// V for patches at `c` facing `n`, all of one object, among `tris` (all of it too).
    fn vis(tris: &[[Vec3; 3]], c: &[Vec3], n: &[Vec3], bins: Bins) -> Vec<f32> {
        vis_owned(tris, &vec![0; tris.len()], c, n, &vec![0; c.len()], bins)
    }

    /// V with the object of every triangle and patch given.
    fn vis_owned(
        tris: &[[Vec3; 3]],
        tri_owner: &[u32],
        c: &[Vec3],
        n: &[Vec3],
        owner: &[u32],
        bins: Bins,
    ) -> Vec<f32> {
        let occ = Occluder::with_owners(tris, tri_owner);
        let p = EnvVisParams {
            bins: Some(bins),
            ..Default::default()
        };
        visibility(c, n, Some(owner), 0..c.len(), &occ, bins, &p, &|_| {}).0
    }

    #[test]
    fn env_bins_flag_parses() {
        assert_eq!(parse_bins("16x32"), Ok(Some(Bins { rows: 16, cols: 32 })));
        assert_eq!(parse_bins("0"), Ok(None));
        assert_eq!(parse_bins("off"), Ok(None));
        for bad in ["16", "0x4", "4x300", "axb", ""] {
            assert!(parse_bins(bad).unwrap_err().contains("--env-bins"), "{bad}");
        }
    }

    #[test]
    fn unoccluded_patches_see_pi_under_a_uniform_sky() {
        // A floor alone: nothing above it, E = π L for any orientation of an isolated patch.
        let tris: Vec<_> = quad(0.0, 1.0).into_iter().collect();
        let normals = [
            Vec3::Y,
            Vec3::X,
            Vec3::new(0.3, 0.8, -0.52).normalize(),
            -Vec3::Z,
        ];
        let centroids = [
            Vec3::ZERO,
            Vec3::new(0.0, 1000.0, 0.0),
            Vec3::new(0.0, 1000.0, 0.0),
            Vec3::new(0.0, 1000.0, 0.0),
        ];
        for bins in [DEFAULT_BINS, Bins { rows: 8, cols: 16 }] {
            let v = vis(&tris, &centroids, &normals, bins);
            let mean = bin_radiance(&EnvMap::uniform([2.0; 3]), 0.0, bins);
            let mut e = vec![[0.0f32; 3]; centroids.len()];
            environment_irradiance(&v, &mean, 1.0, &mut e);
            for (i, ei) in e.iter().enumerate() {
                let rel = ei[0] / (2.0 * PI) - 1.0;
                assert!(
                    rel.abs() < 0.0005,
                    "bins {bins:?} patch {i}: E = {ei:?}, {rel:+.4}"
                );
            }
        }
    }

    /// A face pressed against another (a block's base on the floor, and the floor under
    /// it) sees no sky: its offset ray origin lies beyond the other surface. It used to
    /// see the whole lower hemisphere, which lit the blocks of the closed Cornell box.
    #[test]
    fn faces_pressed_together_see_no_sky() {
        let floor: Vec<_> = quad(0.0, 1.0).into_iter().collect();
        let base: Vec<_> = quad(0.0, 0.2).iter().map(|t| [t[0], t[2], t[1]]).collect();
        let tris: Vec<_> = floor.iter().chain(&base).copied().collect();
        let centroids = [
            Vec3::new(0.05, 0.0, 0.05), // the base, facing down onto the floor
            Vec3::new(-0.05, 0.0, 0.1), // the floor under the base, facing up
            Vec3::new(0.6, 0.0, 0.6),   // the floor in the open
        ];
        let normals = [-Vec3::Y, Vec3::Y, Vec3::Y];
        // The floor is object 0, the block's base object 1.
        let tri_owner = [0, 0, 1, 1];
        let v = vis_owned(
            &tris,
            &tri_owner,
            &centroids,
            &normals,
            &[1, 0, 0],
            DEFAULT_BINS,
        );
        let k = DEFAULT_BINS.count();
        let sum = |i: usize| v[i * k..(i + 1) * k].iter().sum::<f32>();
        assert_eq!(sum(0), 0.0);
        assert_eq!(sum(1), 0.0);
        assert!((sum(2) / PI - 1.0).abs() < 0.01, "{}", sum(2));
        // The same base lifted off the floor sees the sky below it (past the floor's edge).
        let lifted: Vec<_> = base
            .iter()
            .map(|t| t.map(|p| p + Vec3::Y * 0.05))
            .chain(floor.iter().copied())
            .collect();
        let v = vis_owned(
            &lifted,
            &tri_owner,
            &[Vec3::new(0.05, 0.05, 0.05)],
            &[-Vec3::Y],
            &[1],
            DEFAULT_BINS,
        );
        assert!(v.iter().sum::<f32>() > 0.0);
        // A zero-thickness two-sided sheet (both faces one object) is not pressed against
        // itself: its faces see the sky on both sides.
        let v = vis(
            &tris[2..],
            &[Vec3::new(0.05, 0.0, 0.05); 2],
            &[Vec3::Y, -Vec3::Y],
            DEFAULT_BINS,
        );
        let k = DEFAULT_BINS.count();
        assert!(v[..k].iter().sum::<f32>() > 3.0 && v[k..].iter().sum::<f32>() > 3.0);
    }

    /// The stage traced in runs of rows gives the values of one pass, bit for bit.
    #[test]
    fn runs_of_rows_give_the_values_of_one_pass() {
        let mut tris: Vec<_> = quad(0.0, 1.0).into_iter().collect();
        tris.extend(quad(0.5, 0.3));
        let occ = Occluder::new(&tris);
        let centroid: Vec<Vec3> = (0..7)
            .map(|k| Vec3::new(-0.6 + 0.2 * k as f32, 0.0, 0.1 * k as f32 - 0.3))
            .collect();
        let normal = vec![Vec3::Y; centroid.len()];
        let p = Patches {
            centroid: &centroid,
            normal: &normal,
            owner: None,
        };
        let params = EnvVisParams::default();
        let bins = Bins { rows: 4, cols: 8 };
        let whole = half_rows(p, 1..7, &occ, (bins, &params), usize::MAX, &|_| {});
        let runs = half_rows(p, 1..7, &occ, (bins, &params), 4, &|_| {});
        assert_eq!(whole, runs);
        assert_eq!(whole.0.len(), 6 * 32);
        assert!(whole.0.iter().any(|&b| b != 0) && whole.1 > 0, "{whole:?}");
    }

    #[test]
    fn a_roof_shadows_and_a_closed_box_is_dark() {
        // A floor patch under a large roof sees only a thin band near the horizon.
        let mut tris: Vec<_> = quad(0.0, 1.0).into_iter().collect();
        tris.extend(quad(0.1, 20.0));
        let v = vis(&tris, &[Vec3::ZERO], &[Vec3::Y], DEFAULT_BINS);
        let sum: f32 = v.iter().sum();
        // Open band: elevation below atan(0.1/20); its cosine-weighted measure is
        // π sin²(0.29°) ≈ 8e-5: essentially nothing.
        assert!(sum < 0.01 * PI, "{sum}");

        // Inside a closed box nothing is visible at all.
        let mut cube = Vec::new();
        let corner = |i: u32| {
            Vec3::new(
                if i & 1 == 0 { -1.0 } else { 1.0 },
                if i & 2 == 0 { -1.0 } else { 1.0 },
                if i & 4 == 0 { -1.0 } else { 1.0 },
            )
        };
        for [a, b, c, d] in [
            [0, 1, 3, 2],
            [4, 5, 7, 6],
            [0, 1, 5, 4],
            [2, 3, 7, 6],
            [0, 2, 6, 4],
            [1, 3, 7, 5],
        ] {
            cube.push([corner(a), corner(b), corner(c)]);
            cube.push([corner(a), corner(c), corner(d)]);
        }
        let v = vis(
            &cube,
            &[Vec3::new(0.0, -1.0, 0.0)],
            &[Vec3::Y],
            DEFAULT_BINS,
        );
        assert_eq!(v.iter().sum::<f32>(), 0.0);
    }

    #[test]
    fn a_wall_sees_the_bright_half_and_rotation_swaps_it() {
        // A map bright for u < 0.5 (directions with x > 0), dark for the rest.
        let texels = vec![[1.0f32; 3], [0.0; 3]];
        let map = EnvMap::from_texels(2, 1, texels).unwrap();
        let bins = DEFAULT_BINS;
        // Two faces of a thin vertical wall, one facing +X and one facing −X, at the origin.
        let wall = [
            [
                Vec3::new(0.0, -1.0, -1.0),
                Vec3::new(0.0, 1.0, -1.0),
                Vec3::new(0.0, 1.0, 1.0),
            ],
            [
                Vec3::new(0.0, -1.0, -1.0),
                Vec3::new(0.0, 1.0, 1.0),
                Vec3::new(0.0, -1.0, 1.0),
            ],
        ];
        let v = vis(&wall, &[Vec3::ZERO, Vec3::ZERO], &[Vec3::X, -Vec3::X], bins);
        for (rot, lit) in [(0.0, 0usize), (180.0, 1)] {
            let mean = bin_radiance(&map, rot, bins);
            let mut e = vec![[0.0f32; 3]; 2];
            environment_irradiance(&v, &mean, 1.0, &mut e);
            assert!((e[lit][0] / PI - 1.0).abs() < 0.005, "rot {rot}: {e:?}");
            assert!(e[1 - lit][0] < 1e-3, "rot {rot}: {e:?}");
        }
    }

    /// Binned E against a brute-force reference (stratified cosine-weighted rays that look
    /// the rotated map up per ray) on patches of a floor, a block and under a plate: the
    /// error the partition and the 2 × 2 rays per bin leave. Prints a table; see
    /// `docs/environment.md`.
    #[test]
    fn binned_irradiance_matches_brute_force_under_the_sky() {
        let mut tris: Vec<_> = quad(0.0, 2.0).into_iter().collect();
        // A closed unit block on the floor, and a plate at y = 1.5 beside it.
        let corner = |i: u32| {
            Vec3::new(
                if i & 1 == 0 { -0.5 } else { 0.5 },
                if i & 2 == 0 { 0.0 } else { 1.0 },
                if i & 4 == 0 { -0.5 } else { 0.5 },
            )
        };
        for [a, b, c, d] in [
            [0, 1, 3, 2],
            [4, 5, 7, 6],
            [0, 1, 5, 4],
            [2, 3, 7, 6],
            [0, 2, 6, 4],
            [1, 3, 7, 5],
        ] {
            tris.push([corner(a), corner(b), corner(c)]);
            tris.push([corner(a), corner(c), corner(d)]);
        }
        for t in quad(1.5, 0.6) {
            tris.push(t.map(|v| v + Vec3::new(1.0, 0.0, 0.3)));
        }
        let occ = Occluder::new(&tris);
        // Receivers: a floor grid (skipping the block's footprint), and the block's faces.
        let mut c = Vec::new();
        let mut n = Vec::new();
        for ix in -7..=7 {
            for iz in -7..=7 {
                let p = Vec3::new(ix as f32 * 0.25 + 0.01, 0.0, iz as f32 * 0.25 + 0.02);
                if p.x.abs() > 0.5 || p.z.abs() > 0.5 {
                    c.push(p);
                    n.push(Vec3::Y);
                }
            }
        }
        for (face, normal) in [
            (Vec3::new(0.5, 0.5, 0.0), Vec3::X),
            (Vec3::new(-0.5, 0.5, 0.0), -Vec3::X),
            (Vec3::new(0.0, 0.5, 0.5), Vec3::Z),
            (Vec3::new(0.0, 0.5, -0.5), -Vec3::Z),
            (Vec3::new(0.1, 1.0, 0.1), Vec3::Y),
            (Vec3::new(0.5, 0.1, 0.3), Vec3::X),
        ] {
            c.push(face);
            n.push(normal);
        }
        let sky = EnvMap::builtin(crate::envmap::BUILTIN_SKY).unwrap();
        let rotation = 37.0;
        // Reference: 128 × 128 stratified cosine-weighted rays per receiver.
        let m = 128;
        let far = 4.0 * occ.diagonal();
        let reference: Vec<f32> = c
            .par_iter()
            .zip(&n)
            .map(|(&p, &nrm)| {
                let (t1, t2) = nrm.any_orthonormal_pair();
                let origin = p + nrm * 1e-5 * occ.diagonal();
                let mut acc = 0.0f64;
                for a in 0..m {
                    for b in 0..m {
                        let h = mix((a * m + b) as u64 ^ 0xabc);
                        let u1 = (a as f32 + unit(h)) / m as f32;
                        let u2 = (b as f32 + unit(mix(h))) / m as f32;
                        let (r, phi) = (u1.sqrt(), 2.0 * PI * u2);
                        let d = (t1 * r * phi.cos()
                            + t2 * r * phi.sin()
                            + nrm * (1.0 - u1).max(0.0).sqrt())
                        .normalize();
                        if !occ.occluded_dir(origin, d, 0.0, far) {
                            acc += f64::from(sky.radiance_rotated(d, rotation)[1]);
                        }
                    }
                }
                (acc * f64::from(PI) / (m * m) as f64) as f32
            })
            .collect();
        let mut lines = Vec::new();
        for (bins, rays) in [
            (Bins { rows: 8, cols: 16 }, 2),
            (DEFAULT_BINS, 1),
            (DEFAULT_BINS, 2),
            (Bins { rows: 32, cols: 64 }, 2),
        ] {
            let p = EnvVisParams {
                bins: Some(bins),
                rays,
                ..Default::default()
            };
            let (v, stats) = visibility(&c, &n, None, 0..c.len(), &occ, bins, &p, &|_| {});
            let mean = bin_radiance(&sky, rotation, bins);
            let mut e = vec![[0.0f32; 3]; c.len()];
            environment_irradiance(&v, &mean, 1.0, &mut e);
            let mut err: Vec<f32> = e
                .iter()
                .zip(&reference)
                .map(|(got, want)| (got[1] - want).abs() / want.max(1e-6))
                .collect();
            err.sort_by(f32::total_cmp);
            let q = |f: f32| err[((err.len() - 1) as f32 * f) as usize];
            lines.push(format!(
                "| {}x{} | {}x{} | {} | {:.2}% | {:.2}% | {:.2}% |",
                bins.rows,
                bins.cols,
                rays,
                rays,
                stats.rays / c.len() as u64,
                100.0 * q(0.5),
                100.0 * q(0.9),
                100.0 * q(1.0)
            ));
            if bins == DEFAULT_BINS && rays == 2 {
                assert!(
                    q(0.5) < 0.01 && q(0.9) < 0.03,
                    "median {} p90 {}",
                    q(0.5),
                    q(0.9)
                );
            }
        }
        println!("| bins | rays/bin | rays/patch | median | p90 | max |");
        println!("| --- | --- | --- | --- | --- | --- |");
        for l in lines {
            println!("{l}");
        }
    }
}
