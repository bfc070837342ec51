//! Heterogeneous objects' S (the paper's eq. 9): media with equal profiles merged, and S of
//! one object assembled from the per-medium lengths of every stored path.
//!
//! In: an object's patches, its stored distances with their per-medium lengths (stage 1 in
//! `translux_precompute::hetero` records where each medium is and measures the lengths),
//! each patch's medium, and the media's tabulated profiles. Out: the object's S columns,
//! energy-bounded like a homogeneous object's. See `translux_precompute::hetero` for the
//! patterns and for the quadrature of mixed pairs.

use rayon::prelude::*;
use translux_proto::csr::CsrView;
use translux_proto::scene::{MAX_HETEROGENEOUS_MATERIALS, Profile};

use crate::subsurface::{
    ObjectPatches, ObjectS, SubsurfaceParams, Tabulated, bound_and_transpose, coplanar_eps,
    pair_term, samples, self_term,
};

/// Media per path the bundle stores (`dist_material_len` has this many columns).
pub const MEDIA: usize = MAX_HETEROGENEOUS_MATERIALS;

/// Per-medium lengths of one optical path (scene units); unused media are 0.
pub type MediaLen = [f32; MEDIA];

/// Merges media with equal profiles: `map[k]` is the distinct medium of pattern medium k
/// (indices into `distinct`, which lists the first pattern medium of each). `map` has
/// [`MEDIA`] entries; those past `materials.len()` map to 0 (their lengths are always 0).
pub fn merge_media(materials: &[Profile]) -> ([usize; MEDIA], Vec<usize>) {
    let mut map = [0usize; MEDIA];
    let mut distinct: Vec<usize> = Vec::new();
    for (k, p) in materials.iter().enumerate().take(MEDIA) {
        map[k] = match distinct.iter().position(|&d| materials[d] == *p) {
            Some(m) => m,
            None => {
                distinct.push(k);
                distinct.len() - 1
            }
        };
    }
    (map, distinct)
}

/// Eq. 9 for K media: `len[k]` = r_k, `s0[k]` = S_k(0), `s(k, r)` = S_k(r), per channel
/// (see the module docs). With r = Σ r_k = 0 it is the prefactor's limit along no medium: 0.
pub fn eq9(len: &[f32], s0: &[[f32; 3]], s: impl Fn(usize, f32) -> [f32; 3]) -> [f32; 3] {
    let r: f32 = len.iter().sum();
    if r <= 0.0 {
        return [0.0; 3];
    }
    let mut pre = [0.0f32; 3];
    let mut prod = [1.0f32; 3];
    for (k, &rk) in len.iter().enumerate() {
        if rk <= 0.0 {
            continue; // S_k(0) / S_k(0) = 1, and no share of the prefactor
        }
        let sk = s(k, rk);
        for c in 0..3 {
            pre[c] += s0[k][c] * rk / r;
            prod[c] *= if s0[k][c] > 0.0 {
                sk[c] / s0[k][c]
            } else {
                0.0
            };
        }
    }
    std::array::from_fn(|c| pre[c] * prod[c])
}

/// Assembles S of one heterogeneous object (local indices).
///
/// `len[e]` are the per-medium lengths of distance entry e (aligned with `d.col()`), `media`
/// the pattern medium of each patch, `map` the merge of [`merge_media`], and `tabs[m]` the
/// tabulated profile of distinct medium m, all reaching the same truncation radius.
pub fn assemble(
    p: ObjectPatches<'_>,
    d: CsrView<'_, f32>,
    len: &[MediaLen],
    media: &[u32],
    map: &[usize; MEDIA],
    tabs: &[Tabulated],
    params: &SubsurfaceParams,
) -> ObjectS {
    let n = p.area.len();
    let eps = coplanar_eps(&p);
    let s0: Vec<[f32; 3]> = tabs.iter().map(|t| t.r(0.0)).collect();
    let r_max = tabs.iter().map(|t| t.r_max()).fold(f32::INFINITY, f32::min);
    let combined = |l: &[f32]| eq9(l, &s0, |k, r| tabs[k].r(r));
    let columns: Vec<Vec<(u32, [f32; 3])>> = (0..n)
        .into_par_iter()
        .map(|i| {
            let mut col = Vec::new();
            let xs = samples(&p.corners[i], params.samples);
            let own = map[(media[i] as usize).min(MEDIA - 1)];
            col.push((i as u32, self_term(&p, i, &xs, &tabs[own], params)));
            let (a, b) = (d.row_ptr()[i] as usize, d.row_ptr()[i + 1] as usize);
            let (cols, ds) = d.row(i);
            for ((&j, &r), le) in cols.iter().zip(ds).zip(&len[a..b]) {
                let j = j as usize;
                if r >= r_max {
                    continue;
                }
                // Lengths per distinct medium, rescaled to sum to r exactly.
                let mut m = [0.0f32; MEDIA];
                for (k, &l) in le.iter().enumerate() {
                    m[map[k]] += l;
                }
                let total: f32 = m.iter().sum();
                let used = m.iter().filter(|&&x| x > 0.0).count();
                let s = if total <= 0.0 || used <= 1 {
                    // One medium: the homogeneous quadrature with its profile.
                    let k = if total > 0.0 {
                        m.iter().position(|&x| x > 0.0).unwrap_or(own)
                    } else {
                        own
                    };
                    pair_term(&p, i, j, r, &xs, &tabs[k], params, eps)
                } else {
                    let share = m.map(|x| x / total);
                    let near = r < params.near_factor * p.size[i].max(p.size[j]);
                    if !near {
                        combined(&share.map(|f| f * r)).map(|v| v * p.area[i])
                    } else {
                        let excess = (r - p.centroid[i].distance(p.centroid[j])).max(0.0);
                        let ys = samples(&p.corners[j], params.samples);
                        let mut acc = [0.0f32; 3];
                        for &x in &xs {
                            for &y in &ys {
                                let dd = x.distance(y) + excess;
                                let v = combined(&share.map(|f| f * dd));
                                for c in 0..3 {
                                    acc[c] += v[c];
                                }
                            }
                        }
                        let k = (xs.len() * ys.len()) as f32;
                        acc.map(|v| v / k * p.area[i])
                    }
                };
                if s.iter().any(|&v| v > 0.0) {
                    col.push((j as u32, s));
                }
            }
            col
        })
        .collect();
    bound_and_transpose(columns, p.area)
}
