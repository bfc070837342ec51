//! The profile's side of a subsurface link's error bound: whether a cluster node of bounding
//! radius ρ whose centre lies at distance d from a receiver may be read through one link,
//! at every translucency a slider can set.
//!
//! In: a profile ([`ProfileEval`], scene units), the range of distances its links may have,
//! a tolerance τ and a floor ε ([`LinkTolerance`]). Out: [`LinkBound::accepts`], asked by the
//! precompute's cut for every node it would link (`translux_precompute::slinks`) and by
//! [`crate::sterms::ObjectTerms::with_node_pairs`] for every receiver node it would group.
//!
//! Why this bound: a link gives receiver j the node's area-weighted mean irradiance H̄
//! times A R̄, R̄ the profile's mean over the node's distances (read at two of them). The
//! exact sum is Σ_p A_p R(r_p) H_p, so the link's error is A·Cov(R, H) over the node (plus
//! the two-point read's, of higher order). The bound may not depend on the light, and for
//! any H ≥ 0, |Cov(R, H)| ≤ (R_max − R_min) H̄, with R_max = R(d − ρ), R_min = R(d + ρ)
//! for a profile that falls with distance. Light that reaches a receiver only from one
//! side of a node (a sphere's dark side sees the lit side's edge first) makes that
//! covariance one-signed on every link, so the errors add rather than cancel: a link is
//! accepted only when, at every scale of [`SLIDER_SCALES`] and in every channel,
//!
//! ```text
//!   R(d − ρ) − R(d + ρ) ≤ τ · (R(d − ρ) + R(d + ρ)) / 2      (the profile varies by at most τ
//!                                                              across the node), or
//!   A · (R(d − ρ) − R(d + ρ)) ≤ ε · T                         (the link can never carry more
//!                                                              than ε of the total reflectance T)
//! ```
//!
//! The first is what makes links accurate where they matter; the second lets far, negligible
//! nodes through whole (at ×1/8 the milk's profile is spent a few millimetres away, and
//! a relative test alone would take such nodes down to their patches). The profile is read
//! from a table of ln R on a logarithmic grid of distances, 32 points per doubling, for the
//! seven scales ×1/8 … ×8: a node test costs 14 lookups, not 14 profile evaluations.

use translux_proto::scene::Material;

use crate::profile::ProfileEval;

/// An object's link bounds, one per profile of `material` (a thin sheet has two; none for
/// other materials or a profile that cannot be read), from a quarter of its smallest patch
/// (`smallest_patch`, scene units) out to `reach`.
pub fn bounds_of(
    material: &Material,
    unit_mm: f64,
    smallest_patch: f32,
    reach: f32,
    tolerance: LinkTolerance,
) -> Vec<LinkBound> {
    let profiles = match material {
        Material::Translucent { profile, .. } => vec![profile],
        Material::ThinSheet {
            reflectance,
            transmittance,
            ..
        } => vec![reflectance, transmittance],
        _ => return Vec::new(),
    };
    profiles
        .into_iter()
        .filter_map(|p| ProfileEval::new(p, unit_mm).ok())
        .map(|p| LinkBound::new(&p, 0.25 * smallest_patch, reach, tolerance))
        .collect()
}

/// The translucency scales a link must hold at: a slider's range, ×1/8 … ×8 of the
/// precomputed profile, by doublings (the bound varies smoothly between them).
pub const SLIDER_SCALES: [f32; 7] = [0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0];

/// Grid points per doubling of the distance.
const PER_DOUBLING: f32 = 32.0;

/// How much a link may vary and how small a link may be ignored (the module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinkTolerance {
    /// τ: the largest relative variation of the profile across a linked node,
    /// (R(d − ρ) − R(d + ρ)) / mean. Default [`LinkTolerance::DEFAULT_VARIATION`].
    pub variation: f32,
    /// ε: a link whose variation could carry at most ε of the total reflectance is
    /// accepted whatever its relative variation. Default [`LinkTolerance::DEFAULT_FLOOR`].
    pub floor: f32,
}

impl LinkTolerance {
    /// The default τ: measured against direct integration of the dipole
    /// (`precompute/tests/it/dipole.rs`) and against the pairwise S; docs/hierarchy.md.
    pub const DEFAULT_VARIATION: f32 = 1.0;
    /// The default ε: 10⁻⁶ of the total reflectance, a hundredth of a percent of a vertex at
    /// 1% of the lit peak for each such link (10⁻⁵ stored 5–20% fewer entries on the test
    /// objects and put the cube's dark side at ×4 past 3% p90: 3.25%).
    pub const DEFAULT_FLOOR: f32 = 1e-6;
}

impl Default for LinkTolerance {
    fn default() -> Self {
        Self {
            variation: Self::DEFAULT_VARIATION,
            floor: Self::DEFAULT_FLOOR,
        }
    }
}

/// One profile's tables for [`LinkBound::accepts`].
#[derive(Debug, Clone)]
pub struct LinkBound {
    /// ln of the grid's first distance, and grid points per unit of ln r.
    ln_r0: f32,
    per_ln: f32,
    points: usize,
    /// ln R per scale (outer) and grid point, per channel; −∞ where R is 0.
    ln_r: Vec<[f32; 3]>,
    /// The total reflectance per channel (the same at every scale).
    total: [f32; 3],
    tolerance: LinkTolerance,
}

impl LinkBound {
    /// Tables of `profile` from `r_min` to `r_max` (scene units; distances outside read as
    /// the nearer end).
    pub fn new(profile: &ProfileEval, r_min: f32, r_max: f32, tolerance: LinkTolerance) -> Self {
        let r_min = r_min.max(f32::MIN_POSITIVE);
        // At most 60 doublings (a profile without absorption may reach very far, or without
        // end): past them the table reads its last point.
        let r_max = r_max.max(r_min).min(r_min * 2f32.powi(60));
        let per_ln = PER_DOUBLING / std::f32::consts::LN_2;
        let points = ((r_max / r_min).ln() * per_ln).ceil() as usize + 2;
        let ln_r0 = r_min.ln();
        let mut ln_r = Vec::with_capacity(points * SLIDER_SCALES.len());
        for &s in &SLIDER_SCALES {
            let p = profile.scaled(s);
            for k in 0..points {
                let r = (ln_r0 + k as f32 / per_ln).exp();
                ln_r.push(
                    p.eval(r)
                        .map(|v| if v > 0.0 { v.ln() } else { f32::NEG_INFINITY }),
                );
            }
        }
        LinkBound {
            ln_r0,
            per_ln,
            points,
            ln_r,
            total: profile.total_reflectance(),
            tolerance,
        }
    }

    /// The grid position of distance `r`.
    fn position(&self, r: f32) -> f32 {
        ((r.max(f32::MIN_POSITIVE).ln() - self.ln_r0) * self.per_ln)
            .clamp(0.0, (self.points - 1) as f32)
    }

    /// R at scale index `s`, distance `r`, per channel.
    #[cfg(test)]
    fn at(&self, s: usize, r: f32) -> [f32; 3] {
        self.at_position(s, self.position(r))
    }

    /// R at scale index `s` and grid position `x`, per channel.
    fn at_position(&self, s: usize, x: f32) -> [f32; 3] {
        let k = (x as usize).min(self.points - 2);
        let t = x - k as f32;
        let row = &self.ln_r[s * self.points..(s + 1) * self.points];
        let (a, b) = (row[k], row[k + 1]);
        std::array::from_fn(|c| {
            if a[c] == f32::NEG_INFINITY || b[c] == f32::NEG_INFINITY {
                // Past a table's end on one side: the nearer point's value, or 0.
                if t < 0.5 { a[c].exp() } else { b[c].exp() }
            } else {
                (a[c] + t * (b[c] - a[c])).exp()
            }
        })
    }

    /// Whether a node of bounding radius `rho` and area `area` whose centre lies `d` from
    /// the receiver may be linked whole (the module docs).
    pub fn accepts(&self, d: f32, rho: f32, area: f32) -> bool {
        self.accepts_range(d - rho, d + rho, area)
    }

    /// [`LinkBound::accepts`] for a node whose distances span `[lo, hi]`.
    pub fn accepts_range(&self, lo: f32, hi: f32, area: f32) -> bool {
        let LinkTolerance { variation, floor } = self.tolerance;
        let (x_lo, x_hi) = (self.position(lo), self.position(hi));
        (0..SLIDER_SCALES.len()).all(|s| {
            let (near, far) = (self.at_position(s, x_lo), self.at_position(s, x_hi));
            (0..3).all(|c| {
                let diff = (near[c] - far[c]).abs();
                diff <= variation * 0.5 * (near[c] + far[c]) || area * diff <= floor * self.total[c]
            })
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use translux_proto::scene::Profile;

    fn milk() -> ProfileEval {
        let p = Profile::Dipole {
            preset: Some("skimmilk".into()),
            sigma_a: None,
            sigma_s_prime: None,
            eta: None,
            scale: None,
        };
        ProfileEval::new(&p, 1.0).unwrap()
    }

    #[test]
    fn the_tables_read_the_profile_at_every_scale() {
        let p = milk();
        let b = LinkBound::new(&p, 0.01, 100.0, LinkTolerance::default());
        for (s, &scale) in SLIDER_SCALES.iter().enumerate() {
            let q = p.scaled(scale);
            for r in [0.013f32, 0.5, 3.7, 20.0, 77.0] {
                let (got, want) = (b.at(s, r), q.eval(r));
                for c in 0..3 {
                    if want[c] > 1e-30 {
                        let e = (got[c] / want[c] - 1.0).abs();
                        assert!(
                            e < 2e-3,
                            "×{scale} r {r} channel {c}: {} against {}",
                            got[c],
                            want[c]
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn small_far_nodes_pass_and_wide_near_ones_do_not() {
        let p = milk();
        let b = LinkBound::new(&p, 0.01, 200.0, LinkTolerance::default());
        // A node as wide as half its distance varies by far more than τ (1/r³ alone: 27×).
        assert!(!b.accepts(8.0, 4.0, 1.0));
        // A node a twentieth of its distance, at ×8 too (the 1/r³ part: ±15%, then e^(−σr)).
        assert!(b.accepts(8.0, 0.4, 1.0));
        // Far beyond where the sharpest scale's profile is spent, but at ×8 (where it is not)
        // too wide for a node of its size (a 60 mm node holds thousands of mm²): refused.
        assert!(!b.accepts(150.0, 60.0, 5000.0));
        // A tiny node whose variation cannot matter passes whatever its width.
        assert!(b.accepts(150.0, 60.0, 1e-9));
        // A tighter tolerance refuses what the default accepts.
        let tight = LinkBound::new(
            &p,
            0.01,
            200.0,
            LinkTolerance {
                variation: 0.05,
                ..Default::default()
            },
        );
        assert!(!tight.accepts(8.0, 0.4, 1.0));
    }
}
