//! Hierarchical F against dense F on the same scene: the tests' and the benchmark's one
//! way to measure what the hierarchy costs in accuracy.
//!
//! In: two bundles of one scene (dense and hierarchical F) and lights. Out: per-vertex
//! relative errors of the relit radiance (median and 90th percentile, lit and shadowed
//! vertices apart), and the operator's error ‖(F̃ − F)x‖ / ‖F x‖ on given fields.

use glam::Vec3;
use translux_engine::linalg::{Rgb, SparseScatter};
use translux_engine::radiosity::{self, BundleLighting};
use translux_engine::solver::{Method, SolveParams};
use translux_engine::transport::Transport;
use translux_proto::bundle::Bundle;
use translux_proto::light::Light;

/// Per-vertex relative errors of a relight against the dense exact solve.
#[derive(Debug, Clone, Copy, Default)]
pub struct Accuracy {
    /// Vertices the lights reach directly (direct radiance above 0.1% of the light's peak).
    pub lit: Spread,
    /// The rest (indirect light only), where the dense answer is not black.
    pub shadowed: Spread,
}

/// Median and 90th percentile of a set of relative errors, and how many there were.
#[derive(Debug, Clone, Copy, Default)]
pub struct Spread {
    pub median: f64,
    pub p90: f64,
    pub count: usize,
}

impl Spread {
    fn of(mut v: Vec<f64>) -> Spread {
        if v.is_empty() {
            return Spread::default();
        }
        v.sort_by(f64::total_cmp);
        let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
        Spread {
            median: at(0.5),
            p90: at(0.9),
            count: v.len(),
        }
    }
}

/// A small deterministic generator (splitmix64): the same lights on every machine.
struct Mix(u64);

impl Mix {
    fn next(&mut self) -> f32 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// `count` point and spot lights (alternating) inside the bounds of the bundle's patches:
/// every third one within 3% of the bounds' faces (near walls), spots aimed anywhere (so
/// some graze). Deterministic in `seed`.
pub fn random_lights(b: &Bundle, count: usize, seed: u64) -> Vec<Light> {
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for c in b.patch_corners() {
        for v in c {
            lo = lo.min(Vec3::from(*v));
            hi = hi.max(Vec3::from(*v));
        }
    }
    let ext = hi - lo;
    let mut r = Mix(seed);
    (0..count)
        .map(|k| {
            let mut t = Vec3::new(r.next(), r.next(), r.next()) * 0.8 + Vec3::splat(0.1);
            if k % 3 == 2 {
                let axis = (r.next() * 3.0) as usize % 3;
                t[axis] = if r.next() < 0.5 { 0.03 } else { 0.97 };
            }
            let position = (lo + ext * t).to_array();
            if k % 2 == 0 {
                Light::Point {
                    position,
                    intensity: [1.0, 0.8, 0.6],
                }
            } else {
                let d = Vec3::new(r.next() - 0.5, r.next() - 0.5, r.next() - 0.5);
                let d = if d.length() > 1e-3 {
                    d.normalize()
                } else {
                    Vec3::NEG_Y
                };
                Light::Spot {
                    position,
                    intensity: [1.0, 0.8, 0.6],
                    direction: d.to_array(),
                    inner_deg: 20.0,
                    outer_deg: 35.0,
                }
            }
        })
        .collect()
}

/// The radiosity of `lights` on `b` solved to a relative residual of 1e-7, and the direct
/// irradiance it started from.
pub fn solve(b: &Bundle, lighting: &BundleLighting, light: &Light) -> (Vec<Rgb>, Vec<Rgb>) {
    let e = lighting
        .irradiance(std::slice::from_ref(light))
        .expect("point and spot lights");
    let params = SolveParams {
        method: Method::BiCgStab,
        tolerance: 1e-7,
        max_iterations: 5_000,
    };
    let (x, _) = radiosity::solve(
        &Transport::of(b),
        &SparseScatter(b.subsurface()),
        b.patch_emission(),
        &e,
        &params,
        None,
    )
    .expect("the solve runs");
    (x, e)
}

fn vertex_luminance(b: &Bundle, x: &[Rgb]) -> Vec<f64> {
    radiosity::vertex_radiance(
        b.triangle_vertices(),
        b.patch_areas(),
        b.vertex_positions().len(),
        x,
    )
    .iter()
    .map(|v| (v[0] as f64 + v[1] as f64 + v[2] as f64) / 3.0)
    .collect()
}

/// Relights both bundles with each light and pools the per-vertex relative errors of the
/// hierarchical answer against the dense one. The bundles must be of one scene at one
/// patch count (same viewer mesh).
pub fn relight_accuracy(dense: &Bundle, hier: &Bundle, lights: &[Light]) -> Accuracy {
    assert_eq!(
        dense.vertex_positions().len(),
        hier.vertex_positions().len(),
        "one scene at one patch count"
    );
    let (ld, lh) = (BundleLighting::new(dense), BundleLighting::new(hier));
    let (mut lit, mut shadowed) = (Vec::new(), Vec::new());
    for light in lights {
        let (xd, e) = solve(dense, &ld, light);
        let (xh, _) = solve(hier, &lh, light);
        let direct = vertex_luminance(dense, &e);
        let (vd, vh) = (vertex_luminance(dense, &xd), vertex_luminance(hier, &xh));
        let peak_direct = direct.iter().cloned().fold(0.0, f64::max);
        let peak = vd.iter().cloned().fold(0.0, f64::max);
        if peak <= 0.0 {
            continue;
        }
        for k in 0..vd.len() {
            if vd[k] <= 1e-6 * peak {
                continue;
            }
            let err = (vh[k] - vd[k]).abs() / vd[k];
            if direct[k] > 1e-3 * peak_direct {
                lit.push(err);
            } else {
                shadowed.push(err);
            }
        }
    }
    Accuracy {
        lit: Spread::of(lit),
        shadowed: Spread::of(shadowed),
    }
}

/// ‖(F̃ − F)x‖ / ‖F x‖ over patches, for one scalar field x (per patch).
pub fn operator_error(dense: &Bundle, hier: &Bundle, x: &[f32]) -> f64 {
    let rgb: Vec<Rgb> = x.iter().map(|&v| [v; 3]).collect();
    let n = rgb.len();
    let (mut yd, mut yh) = (vec![[0.0f32; 3]; n], vec![[0.0f32; 3]; n]);
    Transport::of(dense).apply_rgb(&rgb, &mut yd);
    Transport::of(hier).apply_rgb(&rgb, &mut yh);
    relative_l2(yh.iter().zip(&yd).map(|(h, d)| (h[0] as f64, d[0] as f64)))
}

/// ‖got − want‖ / ‖want‖ over (got, want) pairs (0 when `want` is all zero).
pub fn relative_l2(pairs: impl IntoIterator<Item = (f64, f64)>) -> f64 {
    let (mut num, mut den) = (0.0f64, 0.0f64);
    for (got, want) in pairs {
        num += (got - want).powi(2);
        den += want * want;
    }
    if den > 0.0 { (num / den).sqrt() } else { 0.0 }
}

/// Test fields for [`operator_error`]: a constant, a smooth random field (a few random
/// plane waves over the patch centroids) and the indicator of one cluster node of the
/// hierarchical bundle's tree (its largest node holding under 5% of the patches).
pub fn fields(hier: &Bundle, seed: u64) -> Vec<(&'static str, Vec<f32>)> {
    let n = hier.patch_areas().len();
    let centroids: Vec<Vec3> = hier
        .patch_corners()
        .iter()
        .map(|c| (Vec3::from(c[0]) + Vec3::from(c[1]) + Vec3::from(c[2])) / 3.0)
        .collect();
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for c in &centroids {
        lo = lo.min(*c);
        hi = hi.max(*c);
    }
    let size = (hi - lo).max_element().max(1e-6);
    let mut r = Mix(seed);
    let waves: Vec<(Vec3, f32)> = (0..4)
        .map(|_| {
            let k = Vec3::new(r.next() - 0.5, r.next() - 0.5, r.next() - 0.5) * 12.0 / size;
            (k, r.next() * std::f32::consts::TAU)
        })
        .collect();
    let smooth: Vec<f32> = centroids
        .iter()
        .map(|c| {
            1.0 + 0.2
                * waves
                    .iter()
                    .map(|(k, p)| (k.dot(*c) + p).sin())
                    .sum::<f32>()
        })
        .collect();
    let mut out = vec![("constant", vec![1.0f32; n]), ("smooth random", smooth)];
    if let Some(t) = hier.tree() {
        let pick = t
            .range
            .iter()
            .filter(|r| ((r[1] - r[0]) as usize) * 20 < n)
            .max_by_key(|r| r[1] - r[0]);
        if let Some(r) = pick {
            let mut x = vec![0.0f32; n];
            for &p in &t.perm[r[0] as usize..r[1] as usize] {
                x[p as usize] = 1.0;
            }
            out.push(("cluster indicator", x));
        }
    }
    out
}
