//! S's entries reduced to a few radial terms, once per bundle, so a translucency change is
//! a short sum per stored entry instead of a quadrature.
//!
//! In: an object's patches and its block of the stored distances (translucent objects and
//! thin sheets; `smatrix::terms_of_bundle` does a whole bundle), the quadrature settings.
//! Out: [`STerms`], which [`crate::smatrix::assemble_scene`] uses in
//! place of the quadrature of [`crate::subsurface`] whenever a profile changes: every entry
//! S_ji is a sum of at most [`MAX_TERMS`] terms of one table lookup each (4–6 on average:
//! 3.9 M for 722 k entries of the 24k Cornell box's block), where the quadrature took up to
//! m² × K (768 by default) lookups of W. [`ObjectTerms::write`] writes an object's S from
//! them into its rows of the scene's S, laid out once by [`ObjectTerms::pattern`] (every
//! stored entry and link, 0 where the profile does not reach), so a later change writes
//! the same rows in place.
//!
//! Why this is accurate at every translucency. Every quadrature plan is linear in the
//! profile: S_ji = ∫ R(ρ) dμ(ρ) for a positive measure μ on the radii the pair spans, fixed by
//! geometry:
//! - far pairs: A_i (R(m − σ) + R(m + σ)) / 2 (`subsurface::far_plan`), two terms (one
//!   where the spread is 0);
//! - polar integration (the self term, coplanar and sheet near pairs):
//!   Σ_rays c (W(ρ_out) − W(ρ_in)) = ∫ n(ρ) R(ρ) 2πρ dρ, where n(ρ) counts (with weights c) the
//!   rays that cover radius ρ — a step function. From 0 to the first ray end n is constant,
//!   and that head is one exact term n W(ρ₁): the profile's peak is integrated exactly at any
//!   translucency;
//! - point samples (near pairs across an edge): Σ c R(ρ_q).
//!
//! Past the head, the radii are cut into coarse geometric bins (each spanning a ratio of at
//! most [`GAUSS_RATIO`]), and each bin's part of μ is replaced by its three-node Gauss rule,
//! computed from μ's moments (exact ones for the polar step function): positive weights at
//! radii inside the bin that integrate every polynomial of degree ≤ 5 in ρ exactly. Over a
//! bin whose radii differ by at most that ratio the profile — a sum of exponentials over
//! powers of ρ — is that smooth at every translucency, and where it is steep across a bin
//! (less translucent), the bin is in the tail, far below the entry's head.
//!
//! The error is checked against the full quadrature at translucency scales ×0.25 to
//! ×4 (`tests` below, and `precompute/tests/it/subsurface.rs` through a bundle).
//!
//! For a device that writes S itself (the server's GPU backend), [`ObjectTerms::flatten`]
//! lays an object's entries, terms and links out as flat records ([`FlatTerms`], module
//! `flat`), [`ObjectTerms::push_into`] maps them onto S with node rows pushed down to the
//! patches, and [`ObjectTerms::factors_from_sums`] turns the sums the device adds up into
//! the energy bound's factors, as `write` would.

use std::ops::Range;

use glam::Vec3;
use rayon::prelude::*;
use translux_proto::csr::CsrView;
use wide::{f32x4, f64x4};

mod flat;

pub use flat::{FlatEntry, FlatLink, FlatRow, FlatTable, FlatTerms, OPPOSITE, TWO, ValueRun};

use crate::linkbound::LinkBound;
use crate::sheet;
use crate::subsurface::{
    self, EnergyReport, Nodes, ObjectPatches, ObjectS, Quadrature, SubsurfaceParams, Tabulated,
    two_point_roots,
};

/// Each coarse bin of an entry's radii spans at most this ratio (ρ_max / ρ_min).
pub const GAUSS_RATIO: f64 = 1.5;
/// At most this many coarse bins per entry: an entry has at most 3 terms per bin, and one
/// more (the exact head) for polar integration.
pub const GAUSS_BINS: usize = 10;
/// The most terms one entry can have.
pub const MAX_TERMS: usize = 3 * GAUSS_BINS + 1;

/// One radial term: `weight · R(r)` or `weight · W(r)` at r = `root`² (the root is
/// stored: the table's grid is uniform in √r, so a lookup is a multiply). 16 bytes: which
/// function it weighs is packed into the cell ([`Term::of`]; a negative `lo` marks W), so a
/// change reads a fifth less than with an enum beside it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Term {
    pub root: f32,
    pub weight: f32,
    /// The cell [`Of::R`] stands for, or −1 for [`Of::W`].
    lo: f32,
    hi: f32,
}

impl Term {
    fn new(r: f32, weight: f32, of: Of) -> Term {
        let (lo, hi) = match of {
            Of::R { lo, hi } => (lo.max(0.0), hi.max(0.0)),
            Of::W => (-1.0, -1.0),
        };
        Term {
            root: r.max(0.0).sqrt(),
            weight,
            lo,
            hi,
        }
    }

    /// Which tabulated function it weighs.
    pub fn of(&self) -> Of {
        if self.lo < 0.0 {
            Of::W
        } else {
            Of::R {
                lo: self.lo,
                hi: self.hi,
            }
        }
    }
}

/// Which tabulated function a [`Term`] weighs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Of {
    /// The profile R(r). The node stands for the radii √r ∈ [`lo`, `hi`] (a Gauss node's
    /// share of its bin; a point for far pairs): where a table ends inside that cell, the
    /// term counts the part of the cell below the table's end, so S changes continuously
    /// as the truncation radius sweeps over an entry's radii.
    R { lo: f32, hi: f32 },
    /// Its integral W(r) = ∫₀^r R 2πr′ dr′.
    W,
}

/// An RGB value in lanes 0–2 of a 4-lane vector, lane 3 zero.
#[inline]
fn lanes(v: [f32; 3]) -> f32x4 {
    f32x4::from([v[0], v[1], v[2], 0.0])
}

/// `items` cut into at most `runs` contiguous runs, none empty, each of about an equal
/// share of the total `cost` (a run ends once the items so far reach its share; an item
/// costlier than a share makes a run of its own). No items give no runs.
fn even_runs<T>(items: &mut [T], runs: usize, cost: impl Fn(&T) -> u64) -> Vec<&mut [T]> {
    let costs: Vec<u64> = items.iter().map(&cost).collect();
    let total: u64 = costs.iter().sum();
    let runs = runs.max(1) as u64;
    let mut out = Vec::with_capacity(runs as usize);
    let (mut rest, mut done, mut taken, mut so_far) = (items, 0usize, 0u64, 0u64);
    for (x, c) in costs.iter().enumerate() {
        so_far += c;
        // Past this run's share of the total (the last run takes what is left).
        if (so_far * runs >= total * (taken + 1) && taken + 1 < runs) || x + 1 == costs.len() {
            let (run, tail) = std::mem::take(&mut rest).split_at_mut(x + 1 - done);
            out.push(run);
            (rest, done) = (tail, x + 1);
            taken = (so_far * runs / total.max(1)).min(runs - 1).max(taken + 1);
        }
    }
    out
}

/// Lanes 0–2 of a 4-lane vector as an RGB value.
#[inline]
fn rgb(v: f32x4) -> [f32; 3] {
    let a = v.to_array();
    [a[0], a[1], a[2]]
}

/// A table that terms are summed under: its end (√ of its radius) computed once, and R's
/// and W's cells laid out for the terms' sum, each cell's start and rise side by side in
/// one 32-byte row of two 4-lane vectors, so a term is one multiply, one row read and two
/// 4-lane operations (`wide`: the same sums as per channel, lane by lane, on stable Rust).
///
/// R's N cells come first, then one cell of 0 (R past the table), then W's N cells and
/// one of W's total (W past the table). A term's position on the grid is clamped at N, so
/// a term past the table reads the cell after its function's last, and a W term reads
/// W's half: the sum has no branch per term, which a term of R past the table or a W term
/// took (the slider's rewrite is a few tens of millions of terms; bench/results/HISTORY.md).
#[derive(Debug, Clone)]
pub struct TermTable<'a> {
    tab: &'a Tabulated,
    end: f32,
    /// Cells per unit of √r, and their count N (R's; W's are as many).
    scale: f32,
    cells_f: f32,
    /// Where W's cells start: N + 1.
    w_base: usize,
    /// R at each cell's start, then its rise over the cell (lanes 0–2 the channels, lane
    /// 3 zero); then 0, W's cells and W's total, as the type's doc says.
    cells: Vec<[f32x4; 2]>,
}

impl<'a> TermTable<'a> {
    pub fn new(tab: &'a Tabulated) -> TermTable<'a> {
        let (_, r, w) = tab.grid();
        let n = r.len() - 1;
        let end = tab.root_max();
        let row = |v: &[[f32; 3]], k: usize| {
            let rise = std::array::from_fn(|ch| v[k + 1][ch] - v[k][ch]);
            [lanes(v[k]), lanes(rise)]
        };
        let mut cells = Vec::with_capacity(2 * n + 2);
        cells.extend((0..n).map(|k| row(r, k)));
        cells.push([f32x4::ZERO; 2]);
        cells.extend((0..n).map(|k| row(w, k)));
        cells.push([lanes(w[n]), f32x4::ZERO]);
        TermTable {
            tab,
            end,
            scale: tab.root_scale(),
            cells_f: n as f32,
            w_base: n + 1,
            cells,
        }
    }

    /// The table's radius.
    pub fn r_max(&self) -> f32 {
        self.tab.r_max()
    }

    /// R at √r = `root`, 0 past the table (as [`Tabulated::r_root`]).
    #[inline]
    pub fn r_root(&self, root: f32) -> [f32; 3] {
        rgb(self.r_lanes(root))
    }

    /// [`TermTable::r_root`] in lanes 0–2.
    #[inline]
    fn r_lanes(&self, root: f32) -> f32x4 {
        self.cell(root.max(0.0) * self.scale, 0)
    }

    /// The function whose cells start at `base` (0 for R, `w_base` for W) at `x` = √r ×
    /// `scale`, x ≥ 0, in lanes 0–2: past the table, the cell after its last (R: 0, W:
    /// its total). The same operations, lane by lane, as [`Tabulated::r_root`] and
    /// [`Tabulated::w_root`] per channel.
    #[inline]
    fn cell(&self, x: f32, base: usize) -> f32x4 {
        // Clamped at N (a NaN too) by one `minss`; `f32::min`'s NaN rule takes five.
        let x = if x < self.cells_f { x } else { self.cells_f };
        // 0 ≤ x ≤ N (4,096 cells), inside i32's range: truncated by one instruction
        // (`fast_trunc_int`), where `as` adds five a term for a saturation never needed
        // (and through usize a dozen more on x86-64 without AVX-512).
        let k = f32x4::splat(x).fast_trunc_int().to_array()[0];
        let f = x - k as f32;
        let [start, rise] = self.cells[base + k as usize];
        start + f32x4::splat(f) * rise
    }

    /// Σ of packed terms ((√r, weight), √r negated for W): [`TermTable::eval`]'s value
    /// for each whose R cell lies inside the table or past its end.
    #[inline]
    fn sum_packed(&self, terms: &[[f32; 2]]) -> f32x4 {
        let mut s = f32x4::ZERO;
        for &[root, weight] in terms {
            // W's cells for a negated root, without a branch.
            let base = (root.to_bits() >> 31) as usize * self.w_base;
            s += self.cell(root.abs() * self.scale, base) * f32x4::splat(weight);
        }
        s
    }

    /// One term's value.
    #[inline]
    pub fn eval(&self, t: &Term) -> [f32; 3] {
        let (tab, end) = (self.tab, self.end);
        let v = if t.lo < 0.0 {
            tab.w_root(t.root)
        } else if t.hi <= end {
            tab.r_root(t.root)
        } else if t.lo >= end {
            [0.0; 3]
        } else {
            // The covered part of the cell (by area, ρ = root²), at R just inside the table
            // when the node itself is past its end.
            let f = (end * end - t.lo * t.lo) / (t.hi * t.hi - t.lo * t.lo);
            tab.r_root(t.root.min(end * (1.0 - 1e-6))).map(|v| v * f)
        };
        v.map(|x| x * t.weight)
    }
}

impl Term {
    /// The term's value under the profile tabulated by `tab`.
    pub fn eval(&self, tab: &Tabulated) -> [f32; 3] {
        TermTable::new(tab).eval(self)
    }
}

/// A link's profile value, R read through `r_at` (R at a root √r): at its two roots'
/// mean when it has them ([`two_point_roots`]), at `root` alone otherwise. The one place
/// the assembly (`smatrix::node_links`, a [`Tabulated`]) and the rewrite
/// ([`ObjectTerms::write`], a [`TermTable`], through `link_lanes`) form it, so the two
/// agree bit for bit.
#[inline]
pub fn link_reading(two: Option<[f32; 2]>, root: f32, r_at: impl Fn(f32) -> [f32; 3]) -> [f32; 3] {
    rgb(link_lanes(two, root, |x| lanes(r_at(x))))
}

/// [`link_reading`] with R in lanes 0–2 (the rewrite reads its table that way).
#[inline]
fn link_lanes(two: Option<[f32; 2]>, root: f32, r_at: impl Fn(f32) -> f32x4) -> f32x4 {
    match two {
        Some([lo, hi]) => (r_at(lo) + r_at(hi)) * f32x4::splat(0.5),
        None => r_at(root),
    }
}

/// Appends to `out` the terms of `plan` for a pair at optical distance `r`, patch i's
/// sample points being `xs` (as [`Quadrature::eval`] would evaluate it).
pub fn reduce(
    plan: &Quadrature,
    r: f32,
    xs: &[Vec3],
    params: &SubsurfaceParams,
    out: &mut Vec<Term>,
) {
    match *plan {
        Quadrature::Far {
            area_i,
            shift,
            sigma,
        } => match two_point_roots(r + shift, sigma) {
            Some([lo, hi]) => {
                out.push(Term::new(lo * lo, 0.5 * area_i, Of::R { lo, hi: lo }));
                out.push(Term::new(hi * hi, 0.5 * area_i, Of::R { lo: hi, hi }));
            }
            None => {
                let root = (r + shift).max(0.0).sqrt();
                out.push(Term::new(r + shift, area_i, Of::R { lo: root, hi: root }))
            }
        },
        Quadrature::Points {
            tri_j,
            excess,
            area_i,
        } => {
            let ys = subsurface::samples(&tri_j, params.samples);
            let c = area_i / (xs.len() * ys.len()) as f32;
            let mut rho = Vec::with_capacity(xs.len() * ys.len());
            for x in xs {
                rho.extend(ys.iter().map(|y| x.distance(*y) + excess));
            }
            point_terms(&rho, c, out);
        }
        Quadrature::Polar {
            tri,
            normal,
            factor,
        } => {
            let rays = ray_intervals(xs, factor, params.directions, |x, f| {
                subsurface::polar_intervals(x, &tri, normal, params.directions, |lo, hi| {
                    f(lo, hi, 1.0)
                })
            });
            polar_terms(&rays, out);
        }
        Quadrature::Lifted {
            tri,
            normal,
            factor,
            ..
        } => {
            let xs = plan.sources(xs, params);
            let rays = ray_intervals(&xs, factor, params.directions, |x, f| {
                subsurface::lifted_intervals(x, &tri, normal, params.directions, f)
            });
            polar_terms(&rays, out);
        }
    }
}

/// The intervals (ρ_in, ρ_out, weight) of every ray of a polar rule, for [`polar_terms`]:
/// `rays(x, f)` calls `f(ρ_in, ρ_out, w)` for each of the `k` rays from sample x that cross
/// the patch, and a ray weighs `factor` · w / (samples · k).
fn ray_intervals(
    xs: &[Vec3],
    factor: f32,
    k: u32,
    rays: impl Fn(Vec3, &mut dyn FnMut(f32, f32, f32)),
) -> Vec<[f32; 3]> {
    let c = factor / (xs.len() as f32 * k as f32);
    let mut out = Vec::with_capacity(xs.len() * k as usize);
    for &x in xs {
        rays(x, &mut |lo, hi, w| out.push([lo, hi, c * w]));
    }
    out
}

/// Geometric edges from `first` to `last`, each bin spanning a ratio of at most
/// [`GAUSS_RATIO`] (wider when more than [`GAUSS_BINS`] bins would be needed).
fn coarse_edges(first: f64, last: f64) -> Vec<f64> {
    if !(last > first && first > 0.0) {
        return vec![first.min(last), last.max(first)];
    }
    let ratio = last / first;
    let bins = (ratio.ln() / GAUSS_RATIO.ln())
        .ceil()
        .clamp(1.0, GAUSS_BINS as f64) as usize;
    let mut e: Vec<f64> = (0..=bins)
        .map(|b| first * ratio.powf(b as f64 / bins as f64))
        .collect();
    e[bins] = last;
    e
}

/// The moments ∫ tᵏ dμ, k = 0..5, of a positive measure μ on one coarse bin, in a
/// coordinate t = (ρ − a) / h of its own (so that they stay well conditioned): the bin's
/// for polar rings, the span of its samples for point samples.
#[derive(Debug, Clone, Copy)]
struct Moments {
    m: [f64; 6],
    /// The smallest and largest t with mass.
    support: (f64, f64),
}

impl Default for Moments {
    fn default() -> Self {
        Moments {
            m: [0.0; 6],
            support: (f64::INFINITY, f64::NEG_INFINITY),
        }
    }
}

impl Moments {
    fn cover(&mut self, t0: f64, t1: f64) {
        self.support = (self.support.0.min(t0), self.support.1.max(t1));
    }

    /// A point mass `w` at t.
    #[cfg(test)]
    fn point(&mut self, t: f64, w: f64) {
        self.cover(t, t);
        let mut p = w;
        for m in &mut self.m {
            *m += p;
            p *= t;
        }
    }

    /// dμ = c ρ dρ for t in [t0, t1], ρ = a + h t: ∫ tᵏ c (a + h t) h dt.
    fn ring(&mut self, (t0, t1): (f64, f64), a: f64, h: f64, c: f64) {
        self.cover(t0, t1);
        let (mut p0, mut p1) = (t0, t1);
        for k in 0..6 {
            // p0 = t0^(k+1), p1 = t1^(k+1) here.
            let first = a * (p1 - p0) / (k + 1) as f64;
            let second = h * (p1 * t1 - p0 * t0) / (k + 2) as f64;
            self.m[k] += c * h * (first + second);
            p0 *= t0;
            p1 *= t1;
        }
    }
}

/// Appends the Gauss rule of a bin's measure as R terms: three nodes, whose sum integrates
/// every polynomial of degree ≤ 5 in ρ over the measure exactly (two nodes, or one, when
/// the measure's support has fewer points). Nodes lie inside the support and weights are
/// positive, so the sum is a positive combination of R at radii the entry really spans.
///
/// Written here: a Gauss rule for an arbitrary discrete or piecewise measure, from its
/// moments, is a few lines of closed form for three nodes; the quadrature crates only
/// tabulate the classical weight functions.
fn gauss_terms(m: &Moments, a: f64, h: f64, out: &mut Vec<Term>) {
    let m0 = m.m[0];
    if !(m0 > 0.0 && m0.is_finite()) {
        return;
    }
    let raw: [f64; 6] = m.m.map(|v| v / m0);
    let mu = raw[1];
    // Central moments c_k = E[(t − μ)^k] by the binomial expansion.
    let central = |k: usize| {
        let mut sum = 0.0;
        let mut binom = 1.0;
        for (j, &r) in raw.iter().enumerate().take(k + 1) {
            sum += binom * r * (-mu).powi((k - j) as i32);
            binom = binom * (k - j) as f64 / (j + 1) as f64;
        }
        sum
    };
    let var = central(2);
    // Each node stands for the support between the midpoints to its neighbours.
    let (low, high) = m.support;
    let mut push = |x: &[(f64, f64)]| {
        let root = |t: f64| (a + h * t).max(0.0).sqrt() as f32;
        for (k, &(t, w)) in x.iter().enumerate() {
            let lo = if k == 0 { low } else { 0.5 * (x[k - 1].0 + t) };
            let hi = if k + 1 == x.len() {
                high
            } else {
                0.5 * (t + x[k + 1].0)
            };
            out.push(Term::new(
                (a + h * t) as f32,
                (m0 * w) as f32,
                Of::R {
                    lo: root(lo.min(t)),
                    hi: root(hi.max(t)),
                },
            ));
        }
    };
    if var.is_nan() || var <= 1e-12 {
        push(&[(mu, 1.0)]);
        return;
    }
    let sd = var.sqrt();
    // Standardized: E[x] = 0, E[x²] = 1, x = (t − μ) / sd.
    let g = central(3) / (sd * sd * sd);
    let k = central(4) / (var * var);
    let q = central(5) / (var * var * sd);
    let inside = |x: f64| (-1e-9..=1.0 + 1e-9).contains(&(mu + sd * x));
    let two = || {
        // Roots of x² − g x − 1, the second orthogonal polynomial.
        let root = (g * g + 4.0).sqrt();
        let (x1, x2) = ((g - root) / 2.0, (g + root) / 2.0);
        [(x1, x2 / (x2 - x1)), (x2, -x1 / (x2 - x1))]
    };
    // k − g² − 1 ≥ 0, zero exactly when the support has two points.
    let det = k - g * g - 1.0;
    let three = (det > 1e-9).then(|| {
        // x³ + b2 x² + b1 x + b0 orthogonal to 1, x, x².
        let b2 = (g + g * k - q) / det;
        let b1 = -k - g * b2;
        let b0 = -g - b2;
        // Three real roots, by the trigonometric form of the depressed cubic.
        let p = b1 - b2 * b2 / 3.0;
        let r = 2.0 * b2 * b2 * b2 / 27.0 - b2 * b1 / 3.0 + b0;
        if p.is_nan() || p >= 0.0 {
            return None;
        }
        let amp = 2.0 * (-p / 3.0).sqrt();
        let phi = ((3.0 * r / (2.0 * p)) * (-3.0 / p).sqrt())
            .clamp(-1.0, 1.0)
            .acos()
            / 3.0;
        let x: [f64; 3] = std::array::from_fn(|i| {
            amp * (phi - 2.0 * std::f64::consts::PI * i as f64 / 3.0).cos() - b2 / 3.0
        });
        // Weights from E[1] = 1, E[x] = 0, E[x²] = 1 (Lagrange basis).
        let w: [f64; 3] = std::array::from_fn(|i| {
            let (j, l) = ((i + 1) % 3, (i + 2) % 3);
            (1.0 + x[j] * x[l]) / ((x[i] - x[j]) * (x[i] - x[l]))
        });
        (w.iter().all(|&w| w > 0.0 && w.is_finite()) && x.iter().all(|&x| inside(x)))
            .then(|| std::array::from_fn::<_, 3, _>(|i| (x[i], w[i])))
    });
    let rule: Vec<(f64, f64)> = match three.flatten() {
        Some(r) => r.to_vec(),
        None => two().to_vec(),
    };
    let mut rule: Vec<(f64, f64)> = rule.iter().map(|&(x, w)| (mu + sd * x, w)).collect();
    rule.sort_by(|p, q| p.0.total_cmp(&q.0));
    push(&rule);
}

/// Polar terms from the rays' intervals (ρ_in, ρ_out, weight). The coverage n(ρ), the
/// weights of the rays covering ρ, gives from 0 to the first ray end (where n is constant)
/// one exact term n̄ W(first); past it the measure n(ρ) 2πρ dρ, in coarse geometric bins,
/// each replaced by its Gauss rule. Both are linear in n, so each interval adds its own
/// share (no sweep over sorted ends: sorting them was half the reduction's time).
fn polar_terms(rays: &[[f32; 3]], out: &mut Vec<Term>) {
    let Some(last) = rays.iter().map(|r| r[1]).reduce(f32::max) else {
        return;
    };
    let last = last as f64;
    let floor = 1e-6 * last;
    let first = rays
        .iter()
        .flat_map(|r| [r[0] as f64, r[1] as f64])
        .filter(|&r| r > floor)
        .fold(last, f64::min);
    let e = coarse_edges(first, last);
    let mut bins = vec![Moments::default(); e.len() - 1];
    let mut head = 0.0f64;
    for &[lo, hi, w] in rays {
        let (mut lo, hi, w) = (lo as f64, hi as f64, w as f64);
        if hi.is_nan() || lo.is_nan() || hi <= lo {
            continue;
        }
        // The head [0, first]: its area mass (π dropped, W carries it).
        let end = hi.min(first);
        if lo < end {
            head += w * (end * end - lo * lo);
            lo = end;
        }
        let mut bin = 0;
        while lo < hi {
            while bin + 1 < bins.len() && e[bin + 1] <= lo {
                bin += 1;
            }
            let end = if bin + 1 == bins.len() {
                hi
            } else {
                e[bin + 1].min(hi)
            };
            let (a, h) = (e[bin], (e[bin + 1] - e[bin]).max(f64::MIN_POSITIVE));
            bins[bin].ring(
                ((lo - a) / h, (end - a) / h),
                a,
                h,
                2.0 * std::f64::consts::PI * w,
            );
            lo = end;
        }
    }
    if head > 0.0 && first > 0.0 {
        out.push(Term::new(
            first as f32,
            (head / (first * first)) as f32,
            Of::W,
        ));
    }
    for (b, m) in bins.iter().enumerate() {
        gauss_terms(m, e[b], e[b + 1] - e[b], out);
    }
}

/// The coarse bins' edges of point samples at radii `rho`: geometric from the smallest
/// radius above 0 to the largest, the first bin reaching down to 0 (where samples may touch).
fn point_edges(rho: &[f32]) -> Vec<f64> {
    // Extremes by comparison: a NaN fails every one and is skipped, as `f32::max` and
    // `f64::min` skip it, without the NaN test they make per sample. One pass finds the
    // largest radius and the smallest above 0; a second is needed only when that one lies
    // below the floor (10⁻⁶ of the largest), which the largest fixes.
    let (mut last, mut least) = (0.0f32, f32::INFINITY);
    for &r in rho {
        if r > last {
            last = r;
        }
        if r > 0.0 && r < least {
            least = r;
        }
    }
    let last = last as f64;
    let floor = 1e-6 * last;
    let first = if least as f64 > floor {
        least as f64
    } else {
        let mut first = f64::INFINITY;
        for &r in rho {
            let r = r as f64;
            if r > floor && r < first {
                first = r;
            }
        }
        first
    };
    let mut e = coarse_edges(first.min(last), last);
    e[0] = 0.0;
    e
}

/// Point terms: radii `rho`, each of weight `c`, in coarse geometric bins, each replaced by
/// its Gauss rule (the first bin reaches down to 0, where samples may touch).
fn point_terms(rho: &[f32], c: f32, out: &mut Vec<Term>) {
    let e = point_edges(rho);
    let bins = e.len() - 1;
    // The samples bin by bin, each bin's in their given order (a stable counting sort), so
    // that each bin's moments are summed in registers: added straight into the bins'
    // arrays as the samples come, every add waited on the last one's store (the reduction
    // of a large object's near entries spent a third of its time there). Each sample's
    // bin is found once (the inner edges below it, counted without a branch).
    let inner = &e[1..bins];
    let bin: Vec<u8> = rho
        .iter()
        .map(|&r| {
            let r = r as f64;
            inner.iter().map(|&edge| (edge < r) as u8).sum()
        })
        .collect();
    let mut start = [0usize; GAUSS_BINS + 2];
    for &b in &bin {
        start[b as usize + 1] += 1;
    }
    for b in 0..bins {
        start[b + 1] += start[b];
    }
    let mut next = start;
    let mut sorted = vec![0.0f32; rho.len()];
    for (&r, &b) in rho.iter().zip(&bin) {
        sorted[next[b as usize]] = r;
        next[b as usize] += 1;
    }
    for b in 0..bins {
        let samples = &sorted[start[b]..start[b + 1]];
        // The bin's extreme radii (by comparison: a NaN fails both and is skipped; it
        // makes the moments NaN, and the bin then gives no term, as any NaN did before).
        let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
        for &r in samples {
            if r < lo {
                lo = r;
            }
            if r > hi {
                hi = r;
            }
        }
        if lo > hi {
            continue; // no sample in the bin
        }
        // The moments in the coordinate of the samples' own span, t = (ρ − lo) / (hi − lo)
        // ∈ [0, 1]: near pairs' radii often fill a sliver of their bin (the first bin
        // reaches down to 0), and in the bin's coordinate their fifth central moment was
        // lost to cancellation, so rounding decided between a two- and three-node rule.
        let a = lo as f64;
        let h = (hi as f64 - a).max(f64::MIN_POSITIVE);
        let mut m = Moments {
            support: (0.0, (hi as f64 - a) / h),
            ..Default::default()
        };
        // Four samples at a time (`wide`'s f64x4; the last group padded with samples of
        // weight 0), the lanes summed at the end.
        let (a4, h4) = (f64x4::splat(a), f64x4::splat(h));
        let mut acc = [f64x4::ZERO; 6];
        let mut add = |r: [f64; 4], w: [f64; 4]| {
            let t = (f64x4::from(r) - a4) / h4;
            let mut p = f64x4::from(w);
            for v in &mut acc {
                *v += p;
                p *= t;
            }
        };
        let c = c as f64;
        let mut groups = samples.chunks_exact(4);
        for g in &mut groups {
            add(std::array::from_fn(|k| g[k] as f64), [c; 4]);
        }
        let rest = groups.remainder();
        if !rest.is_empty() {
            let (mut r, mut w) = ([a; 4], [0.0; 4]);
            for (k, &x) in rest.iter().enumerate() {
                (r[k], w[k]) = (x as f64, c);
            }
            add(r, w);
        }
        for (v, s) in m.m.iter_mut().zip(acc) {
            *v = s.reduce_add();
        }
        gauss_terms(&m, a, h, out);
    }
}

/// One translucent object's or thin sheet's entries as terms (local indices), laid out by
/// receiver as S's rows hold them: row j's entries are its sources in ascending order (the
/// self term among them), so a rebuild writes each row from one contiguous run of terms.
/// Every entry is kept, also where a profile does not reach (it is written 0 there), so the
/// rows' pattern never changes with the translucency.
#[derive(Debug, Default)]
pub struct ObjectTerms {
    /// A thin sheet (entries carry a side; the self term uses the reflectance profile).
    pub sheet: bool,
    /// Row j's entries are `row_ptr[j]..row_ptr[j + 1]`.
    row_ptr: Vec<u32>,
    /// Source i (local) of each entry.
    src: Vec<u32>,
    /// The entry's optical distance (0 for the self term).
    dist: Vec<f32>,
    /// Whether the entry crosses to the sheet's other side (transmittance profile).
    opposite: Vec<bool>,
    /// The largest √r any of the entry's R terms stands for ([`Of::R`]'s `hi`): while a
    /// table reaches that far, the entry is summed from `packed` alone.
    hi_max: Vec<f32>,
    /// Entry e's terms are `term_ptr[e]..term_ptr[e + 1]`.
    term_ptr: Vec<u32>,
    /// The entries of source i (local) are `by_src[by_src_ptr[i]..by_src_ptr[i + 1]]`,
    /// each as its row j and its index into `src` (the row stored: finding it by a binary
    /// search of `row_ptr` took 3× as long). The energy bound scales the few columns over
    /// it through them, where a pass over every row's columns took 6–14 ms of the bowls'
    /// bunny's ~120 ms rewrite at 30k patches for ~40–600 scaled columns of 14,000.
    by_src_ptr: Vec<u32>,
    by_src: Vec<[u32; 2]>,
    /// Each term as (√r, weight), √r negated for a W term: the 8 bytes a rebuild reads per
    /// term (the rebuild is bound by reading them; 16-byte terms took half as long again).
    packed: Vec<[f32; 2]>,
    /// Each term's cell (`lo`, `hi`; −1 for W), read only by entries a table ends inside.
    bounds: Vec<[f32; 2]>,
    /// A hierarchical S's links from each receiver to whole cluster nodes
    /// ([`ObjectTerms::with_links`]; empty without a tree).
    links: Links,
    /// Node-to-node links ([`ObjectTerms::with_node_pairs`]): S's node row N + m for each
    /// receiver node m of `recv` (its links are `pairs`' row at m's index in `recv`).
    pairs: Links,
    /// The receiver nodes with a node row, ascending.
    recv: Vec<u32>,
}

/// Each cluster node's area-weighted centre and bounding radius, the patches' areas in the
/// tree's order, and the nodes starting at each position of that order: what the
/// receiver-side cut ([`ObjectTerms::with_node_pairs`]) reads.
#[derive(Debug, Default)]
pub struct NodeShapes {
    centre: Vec<Vec3>,
    radius: Vec<f32>,
    /// A_p of the patch at each position of the tree's order.
    area_at: Vec<f32>,
    /// Nodes of two or more patches starting at position q: `start_node[start_ptr[q]..
    /// start_ptr[q + 1]]`, widest first.
    start_ptr: Vec<u32>,
    start_node: Vec<u32>,
}

impl NodeShapes {
    /// The shapes of `nodes` over the patches' `corners` and `area` (scene indices).
    pub fn new(nodes: &Nodes, corners: &[[Vec3; 3]], area: &[f32]) -> NodeShapes {
        let m = nodes.range.len();
        let shapes: Vec<(Vec3, f32)> = (0..m)
            .into_par_iter()
            .map(|k| {
                let [a, b] = nodes.range[k];
                let members = &nodes.perm[a as usize..b as usize];
                let mid = |p: u32| {
                    let t = &corners[p as usize];
                    (t[0] + t[1] + t[2]) / 3.0
                };
                let (mut c, mut w) = (Vec3::ZERO, 0.0f32);
                for &p in members {
                    c += mid(p) * area[p as usize];
                    w += area[p as usize];
                }
                let c = if w > 0.0 {
                    c / w
                } else {
                    members.first().map_or(Vec3::ZERO, |&p| mid(p))
                };
                let r = members
                    .iter()
                    .flat_map(|&p| corners[p as usize])
                    .map(|v| v.distance(c))
                    .fold(0.0f32, f32::max);
                (c, r)
            })
            .collect();
        let mut starting: Vec<(u32, u32, u32)> = (0..m)
            .filter(|&k| nodes.range[k][1] > nodes.range[k][0] + 1)
            .map(|k| (nodes.range[k][0], u32::MAX - nodes.range[k][1], k as u32))
            .collect();
        starting.sort_unstable();
        let mut start_ptr = vec![0u32; nodes.perm.len() + 1];
        for &(a, ..) in &starting {
            start_ptr[a as usize + 1] += 1;
        }
        for q in 0..nodes.perm.len() {
            start_ptr[q + 1] += start_ptr[q];
        }
        NodeShapes {
            centre: shapes.iter().map(|s| s.0).collect(),
            radius: shapes.iter().map(|s| s.1).collect(),
            area_at: nodes.perm.iter().map(|&p| area[p as usize]).collect(),
            start_ptr,
            start_node: starting.into_iter().map(|s| s.2).collect(),
        }
    }

    /// The nodes of two or more patches starting at position `q`, widest first.
    fn starting(&self, q: usize) -> &[u32] {
        match self.start_ptr.get(q..q + 2) {
            Some(&[a, b]) => &self.start_node[a as usize..b as usize],
            _ => &[],
        }
    }
}

/// A node row's columns, each with a zero value ([`ObjectTerms::node_rows`]).
pub type NodeRow = Vec<(u32, [f32; 3])>;

/// A node-to-node link as the cut forms it: (receiver node m, one of the links it covers,
/// the covered distances' mean and spread).
type NodePair = (u32, u32, f32, f32);

/// One object's links to cluster nodes, by local receiver: row j's are
/// `ptr[j]..ptr[j + 1]`, in column order.
#[derive(Debug, Default)]
struct Links {
    ptr: Vec<u32>,
    /// The node's column in S (N + k).
    col: Vec<u32>,
    /// √ of the optical distance to the node's representative (a table lookup's argument).
    root: Vec<f32>,
    /// A sheet's link read through the transmittance (the stored entry's kind).
    opposite: Vec<bool>,
    /// With links read at two distances (the bundle's spreads): each link's roots
    /// √(r − σ) and √(r + σ) ([`two_point_roots`]; [√r, √r] for σ = 0);
    /// empty when every link is read at `root` alone.
    two: Vec<[f32; 2]>,
    /// The nodes (k, column N + k) that `col` reaches: a rebuild sums their energies in
    /// arrays this long.
    nodes: Range<usize>,
}

impl Links {
    fn bytes(&self) -> usize {
        (self.ptr.len() + self.col.len() + self.root.len()) * 4
            + self.two.len() * 8
            + self.opposite.len()
    }

    /// Every link of an object's `n` receivers (scene patches `start..start + n`) as
    /// (source node, its receiver's position in the tree's order, link), sorted
    /// ([`ObjectTerms::with_node_pairs`]).
    fn by_source(&self, nodes: &Nodes, start: usize, n: usize) -> Vec<(u32, u32, u32)> {
        let big_n = nodes.perm.len() as u32;
        let mut pos = vec![0u32; n];
        for (q, &p) in nodes.perm.iter().enumerate() {
            let j = (p as usize).wrapping_sub(start);
            if j < n {
                pos[j] = q as u32;
            }
        }
        let mut by: Vec<(u32, u32, u32)> = Vec::with_capacity(self.col.len());
        for (j, &q) in pos.iter().enumerate() {
            for e in self.ptr[j]..self.ptr[j + 1] {
                by.push((self.col[e as usize] - big_n, q, e));
            }
        }
        by.par_sort_unstable();
        by
    }

    /// The node links of the receiver cut's sources ([`ReceiverCut::cover`]), by receiver
    /// node and then column, and which of these links they cover.
    fn gather(&self, cut: Vec<(Vec<NodePair>, Vec<u32>)>) -> (Vec<NodePair>, Vec<bool>) {
        let mut removed = vec![false; self.col.len()];
        let mut pairs: Vec<NodePair> = Vec::new();
        for (taken, covered) in cut {
            pairs.extend(taken);
            for e in covered {
                removed[e as usize] = true;
            }
        }
        // The node rows, by receiver node, columns ascending.
        pairs.par_sort_unstable_by_key(|&(m, e, ..)| (m, self.col[e as usize]));
        (pairs, removed)
    }

    /// The node rows of `pairs` (sorted by [`Links::gather`]), one per receiver node, and
    /// those nodes ascending: each link at the column and side of a link it covers, read at
    /// the covered distances' mean and spread ([`two_point_roots`]).
    fn node_rows_of(&self, pairs: &[NodePair]) -> (Links, Vec<u32>) {
        let mut p = Links {
            ptr: vec![0],
            nodes: self.nodes.clone(),
            ..Default::default()
        };
        let mut recv: Vec<u32> = Vec::new();
        for &(m, e, mean, spread) in pairs {
            if recv.last().is_some_and(|&last| last != m) {
                p.ptr.push(p.col.len() as u32);
            }
            if recv.last() != Some(&m) {
                recv.push(m);
            }
            // The column and side of any covered link; the distances of them all.
            let root = mean.max(0.0).sqrt();
            p.col.push(self.col[e as usize]);
            p.opposite.push(self.opposite[e as usize]);
            p.root.push(root);
            p.two
                .push(two_point_roots(mean, spread).unwrap_or([root, root]));
        }
        if !recv.is_empty() {
            p.ptr.push(p.col.len() as u32);
        }
        (p, recv)
    }

    /// The links left where `removed` is false, by the same receivers.
    fn without(&self, removed: &[bool]) -> Links {
        let take = |out: &mut Links, e: usize| {
            out.col.push(self.col[e]);
            out.root.push(self.root[e]);
            out.opposite.push(self.opposite[e]);
            if !self.two.is_empty() {
                out.two.push(self.two[e]);
            }
        };
        let mut kept = Links {
            ptr: vec![0],
            nodes: self.nodes.clone(),
            ..Default::default()
        };
        for w in self.ptr.windows(2) {
            let (a, b) = (w[0] as usize, w[1] as usize);
            for (e, _) in removed[a..b].iter().enumerate().filter(|(_, gone)| !**gone) {
                take(&mut kept, a + e);
            }
            kept.ptr.push(kept.col.len() as u32);
        }
        kept
    }
}

/// The receiver side's rule of [`ObjectTerms::with_node_pairs`] over an object's links:
/// which receiver nodes m one source node's links may be grouped into.
struct ReceiverCut<'a> {
    links: &'a Links,
    /// A node m is small from the source k where ρ_m ≤ θ |c_m − c_k|.
    theta: f32,
    nodes: &'a Nodes,
    shapes: &'a NodeShapes,
    /// One per profile of the object: each must accept a grouped link's range.
    bounds: &'a [LinkBound],
}

/// A receiver node taken for a source: (m, its patches, the first link it covers, the
/// covered distances' mean and spread).
type Taken = (u32, usize, u32, f32, f32);

impl ReceiverCut<'_> {
    /// One source node's links `g` (sorted by receiver position, [`Links::by_source`]):
    /// its receivers' runs covered, in the tree's order, by the widest nodes that may group
    /// them ([`ReceiverCut::widest`]); the node links taken and the links they cover.
    fn cover(&self, g: &[(u32, u32, u32)]) -> (Vec<NodePair>, Vec<u32>) {
        let (mut taken, mut covered) = (Vec::new(), Vec::new());
        let mut i = 0;
        while i < g.len() {
            let mut run = i + 1;
            while run < g.len() && g[run].1 == g[run - 1].1 + 1 {
                run += 1;
            }
            let end = g[run - 1].1 as usize + 1;
            match self.widest(g, i, end) {
                Some((m, size, first, mean, spread)) => {
                    taken.push((m, first, mean, spread));
                    covered.extend(g[i..i + size].iter().map(|t| t.2));
                    i += size;
                }
                None => i += 1,
            }
        }
        (taken, covered)
    }

    /// The widest node m starting at the receiver position of `g[i]` that ends by `end`
    /// (within the run of consecutive receivers), is small from the source, has all its
    /// links on one side of a sheet and a range of distances every bound accepts; `None`
    /// where there is none.
    fn widest(&self, g: &[(u32, u32, u32)], i: usize, end: usize) -> Option<Taken> {
        let (l, nodes, shapes) = (self.links, self.nodes, self.shapes);
        let ck = shapes.centre[g[0].0 as usize];
        let q = g[i].1 as usize;
        shapes.starting(q).iter().find_map(|&m| {
            let m = m as usize;
            let [a, b] = nodes.range[m];
            if b as usize > end || shapes.radius[m] > self.theta * shapes.centre[m].distance(ck) {
                return None;
            }
            let size = (b - a) as usize;
            let first = g[i].2;
            let side = l.opposite[first as usize];
            let covered = &g[i..i + size];
            if covered.iter().any(|t| l.opposite[t.2 as usize] != side) {
                return None;
            }
            let (mean, spread) = self.distances(covered, &shapes.area_at[q..q + size], g[0].0)?;
            Some((m as u32, size, first, mean, spread))
        })
    }

    /// The `covered` links' distances ρ = root² (a two-point link's as its pair ρ ± s),
    /// weighted by their receivers' `areas`: their mean and spread, in f64; `None` where
    /// a bound does not accept their range for the source node `k`.
    fn distances(&self, covered: &[(u32, u32, u32)], areas: &[f32], k: u32) -> Option<(f32, f32)> {
        let l = self.links;
        let (mut w, mut s1, mut s2) = (0.0f64, 0.0f64, 0.0f64);
        let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
        for (t, &area) in covered.iter().zip(areas) {
            let e = t.2 as usize;
            let rho = (l.root[e] as f64).powi(2);
            let own = l
                .two
                .get(e)
                .map_or(0.0, |[lo, hi]| (*hi as f64).powi(2) - (*lo as f64).powi(2))
                / 2.0;
            let a = area as f64;
            w += a;
            s1 += a * rho;
            s2 += a * (rho * rho + own * own);
            lo = lo.min(rho - own);
            hi = hi.max(rho + own);
        }
        let source_area = self.nodes.area[k as usize];
        if !self
            .bounds
            .iter()
            .all(|b| b.accepts_range(lo as f32, hi as f32, source_area))
        {
            return None;
        }
        let mean = if w > 0.0 { s1 / w } else { 0.0 };
        let spread = if w > 0.0 {
            (s2 / w - mean * mean).max(0.0).sqrt()
        } else {
            0.0
        };
        Some((mean as f32, spread as f32))
    }
}

/// Per-block sums of a rebuild, kept between translucency changes: fresh ones cost page
/// faults.
#[derive(Debug, Default)]
pub struct Scratch {
    blocks: Vec<BlockSums>,
}

impl Scratch {
    /// Bytes held.
    pub fn bytes(&self) -> u64 {
        self.blocks
            .iter()
            .map(|b| ((b.column.capacity() + b.node.capacity()) * 16) as u64)
            .sum()
    }
}

/// What one block of rows adds up while it is written: Σ_j A_j S_ji per column i, e_k's
/// Σ_j A_j R(r_jk) per node k (RGB in lanes 0–2: one 4-lane add each, the same sums as
/// per channel), the entries kept and the links within reach.
#[derive(Debug, Default, Clone)]
struct BlockSums {
    column: Vec<f32x4>,
    node: Vec<f32x4>,
    kept: u64,
    linked: u64,
    /// Every value the block wrote is finite.
    finite: bool,
}

/// What [`ObjectTerms::write`] did.
#[derive(Debug, Clone, Default)]
pub struct Written {
    /// The columns' energy as the bound left it, the entries kept (links within reach
    /// included).
    pub report: EnergyReport,
    /// The links within reach.
    pub links: u64,
    /// Every value written is finite (checked as it was written, so the matrix's own
    /// check need not read them again: [`translux_proto::csr::ValidCsr::rewrite_vouched`]).
    pub finite: bool,
    /// With [`Placement::defer_bound`], the factors the values were not scaled by.
    pub columns: Option<ColumnFactors>,
}

/// The energy bound's factors of one object's columns, left out of the values written
/// ([`Placement::defer_bound`]): S's entry (j, c) is the value written times column c's
/// factor. Each factor is in [0, 1].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ColumnFactors {
    /// Per patch of the object (local index): its direct entries' factor.
    pub patches: Vec<[f32; 3]>,
    /// Per cluster node the object's links reach, from S's column `node_column` on: the
    /// factor of every link to it (node rows' links too).
    pub nodes: Vec<[f32; 3]>,
    pub node_column: usize,
}

/// Rows written into a local pattern: each row's columns, its values, and what the write
/// did ([`ObjectTerms::write_local`]).
type LocalWrite = (Vec<Vec<u32>>, Vec<Vec<[f32; 3]>>, Written);

/// One stored entry's fields ([`ObjectTerms::value`]).
struct EntryRef {
    src: usize,
    dist: f32,
    hi_max: f32,
    opposite: bool,
    terms: Range<usize>,
}

/// One row of S as [`ObjectTerms::write`] fills it: its columns and its values.
type Row<'a> = (&'a [u32], &'a mut [[f32; 3]]);

/// Where one object's rows of the scene's S are written ([`ObjectTerms::write`]).
#[derive(Debug, Clone, Copy)]
pub struct Placement<'a> {
    /// The object's first patch (its local row 0).
    pub start: usize,
    /// Patches in the scene (N: node columns start there).
    pub n: usize,
    /// The cluster tree the links refer to.
    pub nodes: Option<&'a Nodes>,
    /// The energy bound's column factors are returned ([`Written::columns`]) instead of
    /// written into the values: S is then the values times them, column by column, and a
    /// product scales its vector instead ([`crate::transport::subsurface_operator_scaled`]).
    /// Writing them took two more passes over the rows (the links of nodes over the bound,
    /// the entries of scaled columns): 7–15 ms of the bowls' bunny's 55–70 ms at 30,003
    /// patches.
    pub defer_bound: bool,
}

/// What every row of one [`ObjectTerms::write`] reads besides its own cells: the object's
/// patch areas, the tables of its two profiles, and where its rows are placed.
#[derive(Clone, Copy)]
struct WriteInput<'a> {
    area: &'a [f32],
    same: &'a TermTable<'a>,
    other: &'a TermTable<'a>,
    at: Placement<'a>,
}

/// One row's place in an object's arrays: its index j (n + x for node row x), its
/// entries, the link set and range its links are read from, and the receiver's area.
struct RowSpan<'a> {
    j: usize,
    entries: Range<usize>,
    set: &'a Links,
    links: Range<usize>,
    aj: f32,
}

/// A write's block sums added up in block order: per column Σ_j A_j S_ji, per linked node
/// e_k, the entries kept, the links within reach, and whether every value was finite.
struct BlockTotals {
    column: Vec<[f32; 3]>,
    node: Vec<[f32; 3]>,
    kept: u64,
    linked: u64,
    finite: bool,
}

impl BlockTotals {
    /// In: the blocks a write filled, its count of columns and of linked nodes. Out: their sums, added
    /// block by block in order.
    fn add(blocks: &[BlockSums], n: usize, node_count: usize) -> BlockTotals {
        let mut column = vec![f32x4::ZERO; n];
        let mut node = vec![f32x4::ZERO; node_count];
        let (mut kept, mut linked, mut finite) = (0u64, 0u64, true);
        for s in blocks {
            for (t, p) in column.iter_mut().zip(&s.column) {
                *t += *p;
            }
            for (t, p) in node.iter_mut().zip(&s.node) {
                *t += *p;
            }
            kept += s.kept;
            finite &= s.finite;
            linked += s.linked;
        }
        BlockTotals {
            column: column.into_iter().map(rgb).collect(),
            node: node.into_iter().map(rgb).collect(),
            kept,
            linked,
            finite,
        }
    }
}

/// The energy bound on an object's columns: the report so far, each column's direct
/// energy Σ_j A_j S_ji / A_i (`total`), and the factor its direct entries are scaled by.
struct ColumnBound {
    report: EnergyReport,
    total: Vec<[f32; 3]>,
    factor: Vec<[f32; 3]>,
}

impl ColumnBound {
    /// In: each column's Σ_j A_j S_ji, the patches' areas, the entries kept. Out: the bound
    /// on the direct entries alone (a column only scaled in some channel keeps its divisor
    /// 1 in the others).
    fn direct(column: &[[f32; 3]], area: &[f32], kept: u64) -> ColumnBound {
        let n = column.len();
        let mut report = EnergyReport {
            nnz: kept,
            ..Default::default()
        };
        let total: Vec<[f32; 3]> = column
            .iter()
            .zip(area)
            .map(|(t, &a)| t.map(|v| v / a))
            .collect();
        let mut factor = vec![[1.0f32; 3]; n];
        let mut mean = 0.0f64;
        for (i, t) in total.iter().enumerate() {
            let worst = t.iter().cloned().fold(0.0f32, f32::max);
            report.max_column = report.max_column.max(worst);
            mean += t[1] as f64;
            if worst > 1.0 {
                report.scaled_columns += 1;
                factor[i] = t.map(|v| 1.0 / v.max(1.0));
            }
        }
        report.mean_column = if n > 0 { (mean / n as f64) as f32 } else { 0.0 };
        ColumnBound {
            report,
            total,
            factor,
        }
    }

    /// In: each column's direct energy after its own bound, its links' energy before and
    /// after the nodes' factors, and its pairwise factor. Counts the links into the report
    /// and scales the factors further, as `subsurface::add_links` counts.
    fn count_links(
        &mut self,
        direct: &[[f32; 3]],
        far: &[[f32; 3]],
        far_kept: &[[f32; 3]],
        pair_factor: &[[f32; 3]],
    ) {
        let n = direct.len();
        let report = &mut self.report;
        let mut mean = 0.0f64;
        for i in 0..n {
            mean += (direct[i][1] + far[i][1]) as f64;
            if far[i] == [0.0; 3] {
                continue;
            }
            // As subsurface::add_links counts: a column scaled again for its links
            // counts again.
            let mut any = false;
            for c in 0..3 {
                let sum = direct[i][c] + far[i][c];
                report.max_column = report.max_column.max(sum);
                if pair_factor[i][c] < 1.0 && direct[i][c] > 0.0 {
                    self.factor[i][c] *=
                        pair_factor[i][c].min((1.0 - far_kept[i][c]).max(0.0) / direct[i][c]);
                    any = true;
                }
            }
            report.scaled_columns += any as usize;
        }
        report.mean_column = if n > 0 { (mean / n as f64) as f32 } else { 0.0 };
    }
}

/// The linked nodes of one object's write over the cluster tree: node k of the sums is
/// the tree's node `first` + k; the object's patches are `start..start + n`.
struct NodeSpan<'a> {
    nodes: &'a Nodes,
    first: usize,
    start: usize,
    n: usize,
}

impl NodeSpan<'_> {
    /// In: each node's e_k = Σ_j A_j R(r_jk) and a weight w_k. Out: per patch, Σ over the
    /// nodes holding it of e_k × w_k (node k's column re-emits e_k over its patches).
    fn spread(&self, node: &[[f32; 3]], w: &dyn Fn(usize) -> [f32; 3]) -> Vec<[f32; 3]> {
        let nodes = self.nodes;
        // A node covers a contiguous range of the tree's order, so one difference array
        // over that order adds every e_k.
        let mut diff = vec![[0.0f64; 3]; nodes.perm.len() + 1];
        for (k, e) in node.iter().enumerate() {
            if e.iter().all(|&v| v == 0.0) {
                continue;
            }
            let [a, b] = nodes.range[self.first + k];
            let wk = w(k);
            for c in 0..3 {
                diff[a as usize][c] += (e[c] * wk[c]) as f64;
                diff[b as usize][c] -= (e[c] * wk[c]) as f64;
            }
        }
        let mut out = vec![[0.0f32; 3]; self.n];
        let mut run = [0.0f64; 3];
        for (q, &p) in nodes.perm.iter().enumerate() {
            for c in 0..3 {
                run[c] += diff[q][c];
            }
            let i = (p as usize).wrapping_sub(self.start);
            if i < self.n {
                out[i] = run.map(|v| v as f32);
            }
        }
        out
    }

    /// In: the patches' areas and pairwise factors, each node's e_k. Out: each linked
    /// node's factor, its patches' area-weighted mean factor (1 where e_k is 0, or where
    /// no patch is scaled).
    fn mean_factors(
        &self,
        area: &[f32],
        pair_factor: &[[f32; 3]],
        node: &[[f32; 3]],
    ) -> Vec<[f32; 3]> {
        let (nodes, n) = (self.nodes, self.n);
        let mut mean_factor = vec![[1.0f32; 3]; node.len()];
        if !pair_factor.iter().any(|f| *f != [1.0; 3]) {
            return mean_factor;
        }
        // Σ A_p f_p and Σ A_p over the tree's order, this object's patches only.
        let mut prefix = Vec::with_capacity(nodes.perm.len() + 1);
        let mut run = [0.0f64; 4];
        prefix.push(run);
        for &p in &nodes.perm {
            let i = (p as usize).wrapping_sub(self.start);
            if i < n {
                for c in 0..3 {
                    run[c] += area[i] as f64 * pair_factor[i][c] as f64;
                }
                run[3] += area[i] as f64;
            }
            prefix.push(run);
        }
        for (k, (m, e)) in mean_factor.iter_mut().zip(node).enumerate() {
            if e.iter().all(|&v| v == 0.0) {
                continue;
            }
            let [a, b] = nodes.range[self.first + k];
            let (hi, lo) = (prefix[b as usize], prefix[a as usize]);
            let den = hi[3] - lo[3];
            if den > 0.0 {
                *m = std::array::from_fn(|c| ((hi[c] - lo[c]) / den) as f32);
            }
        }
        mean_factor
    }
}

/// Scales every row's links (a node row holds links alone) by their node's factor `mf`,
/// node k's column being `first` + k.
fn scale_links(rows: &mut [(usize, Row<'_>)], first: usize, mf: &[[f32; 3]]) {
    rows.par_iter_mut().for_each(|(_, (cols, out))| {
        for (o, &c) in out.iter_mut().zip(cols.iter()).rev() {
            let Some(m) = (c as usize).checked_sub(first).and_then(|k| mf.get(k)) else {
                break; // the direct entries, before the row's links
            };
            *o = std::array::from_fn(|ch| o[ch] * m[ch]);
        }
    });
}

/// Scales the entries of the `scaled` columns (of the object's n, starting at patch
/// `start`) by their `factor` in one parallel pass over every row's columns (many columns).
fn scale_every_row(
    rows: &mut [(usize, Row<'_>)],
    factor: &[[f32; 3]],
    scaled: &[bool],
    start: usize,
    n: usize,
) {
    // A byte per column tells the scaled ones: the pass over every row's columns
    // reads a table that stays in cache.
    rows.par_iter_mut().for_each(|(_, (cols, out))| {
        for (o, &c) in out.iter_mut().zip(cols.iter()) {
            let i = (c as usize).wrapping_sub(start);
            if i >= n {
                break; // the links, after the row's direct entries
            }
            if scaled[i] {
                let f = factor[i];
                *o = std::array::from_fn(|ch| o[ch] * f[ch]);
            }
        }
    });
}

impl ObjectTerms {
    /// Reduces every entry of one object: `d` is its block of the stored distances (local
    /// indices), `opposite(e)` tells a sheet's other-side entries (by index in `d`).
    pub fn build(
        p: ObjectPatches<'_>,
        d: CsrView<'_, f32>,
        sheet: bool,
        opposite: &(dyn Fn(usize) -> bool + Sync),
        params: &SubsurfaceParams,
    ) -> ObjectTerms {
        let n = p.area.len();
        let eps = subsurface::coplanar_eps(&p);
        type Entry = (u32, f32, bool, Range<usize>);
        // By source column, as the quadrature's assembly builds them: the self term first,
        // then the stored pairs within the object's reach.
        let columns: Vec<(Vec<Entry>, Vec<Term>)> = (0..n)
            .into_par_iter()
            .map(|i| {
                let xs = subsurface::samples(&p.corners[i], params.samples);
                let mut terms = Vec::new();
                let mut entries = Vec::new();
                reduce(&Quadrature::self_term(&p, i), 0.0, &xs, params, &mut terms);
                entries.push((i as u32, 0.0, false, 0..terms.len()));
                for e in d.row_ptr()[i] as usize..d.row_ptr()[i + 1] as usize {
                    let (j, r) = (d.col()[e] as usize, d.val()[e]);
                    let plan = if sheet {
                        sheet::pair_plan(&p, (i, j), r, params)
                    } else {
                        Quadrature::pair(&p, i, j, r, params, eps)
                    };
                    let start = terms.len();
                    reduce(&plan, r, &xs, params, &mut terms);
                    entries.push((j as u32, r, sheet && opposite(e), start..terms.len()));
                }
                (entries, terms)
            })
            .collect();
        // Laid out by receiver: a counting sort of the entries, sources ascending within
        // a row (the columns are visited in order), then their terms in that order.
        let mut row_ptr = vec![0u32; n + 1];
        for (entries, _) in &columns {
            for &(j, ..) in entries {
                row_ptr[j as usize + 1] += 1;
            }
        }
        for j in 0..n {
            row_ptr[j + 1] += row_ptr[j];
        }
        let count = row_ptr[n] as usize;
        let (mut src, mut dist) = (vec![0u32; count], vec![0.0f32; count]);
        let (mut opp, mut hi_max) = (vec![false; count], vec![0.0f32; count]);
        let mut len = vec![0u32; count];
        let mut next = row_ptr[..n].to_vec();
        let (mut by_src_ptr, mut by_src) = (Vec::with_capacity(n + 1), Vec::with_capacity(count));
        by_src_ptr.push(0u32);
        for (i, (entries, terms)) in columns.iter().enumerate() {
            for (j, r, o, range) in entries {
                let s = next[*j as usize] as usize;
                next[*j as usize] += 1;
                by_src.push([*j, s as u32]);
                (src[s], dist[s], opp[s]) = (i as u32, *r, *o);
                len[s] = range.len() as u32;
                // A W term's `hi` is −1: it never lowers the maximum from 0.
                hi_max[s] = terms[range.clone()]
                    .iter()
                    .map(|t| t.hi)
                    .fold(0.0, f32::max);
            }
            by_src_ptr.push(by_src.len() as u32);
        }
        let mut term_ptr = Vec::with_capacity(count + 1);
        term_ptr.push(0u32);
        for l in &len {
            term_ptr.push(term_ptr.last().copied().unwrap_or(0) + l);
        }
        let total = term_ptr[count] as usize;
        let (mut packed, mut bounds) = (vec![[0.0f32; 2]; total], vec![[0.0f32; 2]; total]);
        next.copy_from_slice(&row_ptr[..n]);
        for (entries, terms) in columns {
            for (j, _, _, range) in entries {
                let s = next[j as usize] as usize;
                next[j as usize] += 1;
                let at = term_ptr[s] as usize;
                for (k, t) in terms[range].iter().enumerate() {
                    let w = matches!(t.of(), Of::W);
                    let root = t.root.abs();
                    packed[at + k] = [if w { -root } else { root }, t.weight];
                    bounds[at + k] = [t.lo, t.hi];
                }
            }
        }
        ObjectTerms {
            sheet,
            row_ptr,
            src,
            dist,
            opposite: opp,
            hi_max,
            term_ptr,
            by_src_ptr,
            by_src,
            packed,
            bounds,
            links: Links::default(),
            pairs: Links::default(),
            recv: Vec::new(),
        }
    }

    /// Stored term `t` (an index into `packed`) as a [`Term`], for the slow path.
    fn term(&self, t: usize) -> Term {
        let [root, weight] = self.packed[t];
        let [lo, hi] = self.bounds[t];
        Term {
            root: root.abs(),
            weight,
            lo,
            hi,
        }
    }

    /// An entry's sum under `tab` in lanes 0–2 (lane 3 is 0), before the energy bound (0
    /// where not kept), and whether it is kept (the self term, or some channel above 0).
    /// The entry is given by its fields (`e`'s `src`, `dist`, `hi_max`, `opposite` and its
    /// terms' range), which a row's pass reads side by side.
    #[inline]
    fn value(
        &self,
        e: EntryRef,
        j: usize,
        same: &TermTable<'_>,
        other: &TermTable<'_>,
    ) -> (f32x4, bool) {
        let tab = if e.opposite { other } else { same };
        let self_term = e.src == j;
        if !self_term && e.dist >= tab.r_max() {
            return (f32x4::ZERO, false);
        }
        let range = e.terms;
        let s = if e.hi_max <= tab.end {
            tab.sum_packed(&self.packed[range])
        } else {
            // A table ends inside some of its cells: those terms count the part below the
            // end ([`TermTable::eval`]), the others are summed as usual.
            let mut s = f32x4::ZERO;
            for t in range {
                s += if self.bounds[t][1] <= tab.end {
                    tab.sum_packed(std::slice::from_ref(&self.packed[t]))
                } else {
                    lanes(tab.eval(&self.term(t)))
                };
            }
            s
        };
        let kept = self_term | (s.simd_gt(f32x4::ZERO).to_bitmask() != 0);
        (if kept { s } else { f32x4::ZERO }, kept)
    }

    /// S of the object (local indices) under the profiles tabulated by `same` (a
    /// translucent object's profile, or a sheet's reflectance) and `other` (a sheet's
    /// transmittance), without links: the same entries, skips and energy bound as the
    /// quadrature's assembly. [`ObjectTerms::write`] into a local pattern, entries written 0
    /// left out.
    pub fn assemble(&self, area: &[f32], same: &Tabulated, other: &Tabulated) -> ObjectS {
        let (cols, vals, written) = self.write_local(area, same, other, false);
        let report = written.report;
        let rows = cols
            .into_iter()
            .zip(vals)
            .enumerate()
            .map(|(j, (c, v))| {
                c.into_iter()
                    .zip(v)
                    .filter(|&(i, s)| i as usize == j || s.iter().any(|&x| x > 0.0))
                    .collect()
            })
            .collect();
        ObjectS {
            rows,
            links: Vec::new(),
            report,
        }
    }

    /// [`ObjectTerms::write`] into a fresh local pattern without links: each row's columns
    /// and values, and what the write did (with `defer_bound`, the bound's factors left out
    /// of the values, [`Placement::defer_bound`]).
    fn write_local(
        &self,
        area: &[f32],
        same: &Tabulated,
        other: &Tabulated,
        defer_bound: bool,
    ) -> LocalWrite {
        let pattern = self.pattern(0, false);
        let cols: Vec<Vec<u32>> = pattern
            .iter()
            .map(|r| r.iter().map(|e| e.0).collect())
            .collect();
        let mut vals: Vec<Vec<[f32; 3]>> =
            pattern.iter().map(|r| vec![[0.0; 3]; r.len()]).collect();
        let out = cols
            .iter()
            .zip(vals.iter_mut())
            .map(|(c, v)| (c.as_slice(), v.as_mut_slice()))
            .collect();
        let at = Placement {
            start: 0,
            n: area.len(),
            nodes: None,
            defer_bound,
        };
        let written = self.write(area, same, other, at, out, &mut Scratch::default());
        (cols, vals, written)
    }

    /// Adds the links of rows `r` (this object's patches) to whole cluster nodes, from the
    /// scene's stored distances `d` (columns ≥ N are nodes) out to `reach`; `kinds` tells a
    /// sheet's other-side entries, `spreads` (aligned likewise; empty: none) the spread of
    /// links read at two distances.
    pub fn with_links(
        mut self,
        d: CsrView<'_, f32>,
        kinds: &[u32],
        spreads: &[f32],
        r: Range<usize>,
        reach: f32,
    ) -> Self {
        let two_point = !spreads.is_empty();
        let n = d.n_rows();
        let mut l = Links {
            ptr: vec![0],
            ..Default::default()
        };
        for j in r {
            let first = d.row_ptr()[j] as usize;
            let (cols, ds) = d.row(j);
            for (e, (&c, &dist)) in cols.iter().zip(ds).enumerate() {
                if c as usize >= n && dist < reach {
                    l.col.push(c);
                    let root = dist.max(0.0).sqrt();
                    l.root.push(root);
                    if two_point {
                        let sigma = spreads.get(first + e).copied().unwrap_or(0.0);
                        l.two
                            .push(two_point_roots(dist, sigma).unwrap_or([root, root]));
                    }
                    l.opposite
                        .push(self.sheet && kinds.get(first + e) == Some(&sheet::KIND_OPPOSITE));
                }
            }
            l.ptr.push(l.col.len() as u32);
        }
        let (lo, hi) = l.col.iter().fold((usize::MAX, 0), |(lo, hi), &c| {
            (lo.min(c as usize - n), hi.max(c as usize - n + 1))
        });
        l.nodes = lo.min(hi)..hi;
        self.links = l;
        self
    }

    /// Thins the links ([`ObjectTerms::with_links`]) by clustering their receivers too, as
    /// classical hierarchical radiosity links node to node: for each source node k, the
    /// receivers that link it are covered, in the tree's order, by the widest nodes m whose
    /// patches all link k (on the same side of a sheet) and that are small from k (bounding
    /// radius ρ_m ≤ `theta` |c_m − c_k|, the source side's rule with its own θ). Each such m
    /// gets one node-to-node link (S's node row N + m, pushed to every patch of m by the
    /// product). Every patch of m links k, so the distances its links stored are all known:
    /// the node link is read at two distances ([`two_point_roots`]) that keep their
    /// area-weighted mean and spread (each link's own two-point spread counted in), so
    /// it reads the mean of R over m exactly where R is quadratic in the distance. One
    /// distance per node (a representative patch's) was tried first: on the 60 mm marble
    /// cube at 4× its coefficients it put vertices 5% (median) off the pairwise S.
    /// Receivers left uncovered keep their own links. `theta` ≤ 0 leaves the links as they
    /// are. Accuracy: bench/results/HISTORY.md, *Receiver-side clustering*.
    ///
    /// With `bounds` (one per profile of the object: a bundle cut by the profile's error
    /// bound), a receiver node is grouped only where the covered links' distances, each
    /// with its own spread, span a range every bound accepts for the source node
    /// ([`LinkBound::accepts_range`]): the grouped link then varies across its receivers by
    /// no more than a link may across its source.
    pub fn with_node_pairs(
        mut self,
        theta: f32,
        nodes: &Nodes,
        shapes: &NodeShapes,
        start: usize,
        bounds: &[LinkBound],
    ) -> Self {
        if theta.is_nan() || theta <= 0.0 || self.links.col.is_empty() {
            return self;
        }
        let n = self.row_ptr.len() - 1;
        let l = &self.links;
        // Every link as (source node, its receiver's position in the tree's order, link).
        let by = l.by_source(nodes, start, n);
        // Per source node, its receivers' runs covered (independent of the other sources).
        let groups: Vec<&[(u32, u32, u32)]> = by.chunk_by(|a, b| a.0 == b.0).collect();
        let rule = ReceiverCut {
            links: l,
            theta,
            nodes,
            shapes,
            bounds,
        };
        let cut: Vec<(Vec<NodePair>, Vec<u32>)> =
            groups.par_iter().map(|g| rule.cover(g)).collect();
        drop(groups);
        drop(by);
        // The node links, and the patch links they replace.
        let (pairs, removed) = l.gather(cut);
        let (p, recv) = l.node_rows_of(&pairs);
        let kept = l.without(&removed);
        (self.links, self.pairs, self.recv) = (kept, p, recv);
        self
    }

    /// The receiver nodes with a node row ([`ObjectTerms::with_node_pairs`]), ascending.
    pub fn receiver_nodes(&self) -> &[u32] {
        &self.recv
    }

    /// Node-to-node links.
    pub fn node_pairs(&self) -> usize {
        self.pairs.col.len()
    }

    /// Links from a patch to a node.
    pub fn patch_links(&self) -> usize {
        self.links.col.len()
    }

    /// The object's node rows with every link at zero: (receiver node m, S's row N + m),
    /// in the order of [`ObjectTerms::receiver_nodes`].
    pub fn node_rows(&self) -> Vec<(usize, NodeRow)> {
        self.recv
            .iter()
            .enumerate()
            .map(|(x, &m)| {
                let (a, b) = (self.pairs.ptr[x] as usize, self.pairs.ptr[x + 1] as usize);
                let row = self.pairs.col[a..b]
                    .iter()
                    .map(|&c| (c, [0.0; 3]))
                    .collect();
                (m as usize, row)
            })
            .collect()
    }

    /// The object's rows of S with every stored entry and link at zero (global columns):
    /// the pattern that [`ObjectTerms::write`] fills. Row j lists its sources (the object's
    /// patches, ascending), then (with `links`) its links.
    pub fn pattern(&self, start: usize, links: bool) -> Vec<Vec<(u32, [f32; 3])>> {
        let n = self.row_ptr.len() - 1;
        (0..n)
            .into_par_iter()
            .map(|j| {
                let entries = &self.src[self.row_ptr[j] as usize..self.row_ptr[j + 1] as usize];
                let mut row: Vec<(u32, [f32; 3])> = entries
                    .iter()
                    .map(|&i| (start as u32 + i, [0.0; 3]))
                    .collect();
                if let Some(l) = self.links.ptr.get(j..j + 2).filter(|_| links) {
                    row.extend(
                        self.links.col[l[0] as usize..l[1] as usize]
                            .iter()
                            .map(|&c| (c, [0.0; 3])),
                    );
                }
                row
            })
            .collect()
    }

    /// Writes the object's S under the profiles tabulated by `same` and `other` (as
    /// [`ObjectTerms::assemble`]) into `rows`, its rows of the scene's S laid out as
    /// [`ObjectTerms::pattern`] made them: entries past the table's reach are written 0,
    /// links are node k's A_k P(r) while r is within reach, and the energy bound is enforced
    /// on every column with the links counted ([`subsurface::add_links`]). `area` is the
    /// object's patch areas; without `at.nodes` the rows hold no links. With `at.nodes` and
    /// node-to-node links ([`ObjectTerms::with_node_pairs`]), `rows` continues with the
    /// object's node rows in the order of [`ObjectTerms::receiver_nodes`]: node m's links are
    /// A_k P(r) like a patch's, and count A_m P(r) into e_k. Every value is
    /// written, so the rows may hold any earlier values: a translucency change writes the
    /// last S's values in place.
    ///
    /// One pass writes every row and adds up, per block of rows, the columns' and the
    /// nodes' energies; a second pass, only where some column is over the bound, scales
    /// the direct entries of those columns.
    pub fn write(
        &self,
        area: &[f32],
        same: &Tabulated,
        other: &Tabulated,
        at: Placement<'_>,
        rows: Vec<Row<'_>>,
        scratch: &mut Scratch,
    ) -> Written {
        let n = self.row_ptr.len() - 1;
        let mut rows = self.tree_order(at, rows);
        let (same, other) = (TermTable::new(same), TermTable::new(other));
        let input = WriteInput {
            area,
            same: &same,
            other: &other,
            at,
        };
        let blocks = self.write_blocks(input, &mut rows, scratch);
        let sums = BlockTotals::add(&scratch.blocks[..blocks], n, self.node_count(at));
        let mut bound = ColumnBound::direct(&sums.column, area, sums.kept);
        let node_factor = match (at.nodes, sums.linked > 0) {
            (Some(nodes), true) => {
                let links = (input.area, at, &sums.node[..]);
                let scale = (!at.defer_bound).then_some(&mut rows[..]);
                bound.report.nnz += sums.linked;
                self.bound_links(nodes, links, &mut bound, scale)
            }
            _ => vec![[1.0f32; 3]; sums.node.len()],
        };
        // A factor is in [0, 1] (a finite value stays finite).
        debug_assert!(
            bound
                .factor
                .iter()
                .flatten()
                .all(|f| (0.0..=1.0).contains(f))
        );
        if at.defer_bound {
            return Written {
                report: bound.report,
                links: sums.linked,
                finite: sums.finite,
                columns: Some(ColumnFactors {
                    patches: bound.factor,
                    nodes: node_factor,
                    node_column: at.n + self.links.nodes.start,
                }),
            };
        }
        self.scale_columns(&mut rows, &bound.factor, at.start);
        Written {
            report: bound.report,
            links: sums.linked,
            finite: sums.finite,
            columns: None,
        }
    }

    /// The nodes this object's links reach (a contiguous span of them) where `at` places
    /// links; 0 without a tree.
    fn node_count(&self, at: Placement<'_>) -> usize {
        at.nodes.map_or(0, |_| self.links.nodes.len())
    }

    /// In: [`ObjectTerms::write`]'s rows (the patch rows, then the node rows). Out: each
    /// with its row index (local; node row x is n + x), in the cluster tree's order.
    /// Panics unless there is one row per patch, then one per node row.
    fn tree_order<'r>(&self, at: Placement<'_>, rows: Vec<Row<'r>>) -> Vec<(usize, Row<'r>)> {
        let n = self.row_ptr.len() - 1;
        let node_rows = if at.nodes.is_some() {
            self.recv.len()
        } else {
            0
        };
        assert_eq!(
            rows.len(),
            n + node_rows,
            "one row per patch of the object, then its node rows"
        );
        let mut rows = rows;
        let tail_rows = rows.split_off(n);
        // The rows in the cluster tree's order: neighbouring receivers read and add to the
        // same few columns and nodes, so a block's sums stay in cache (in patch order the
        // scattered adds cost as much as the sums themselves on the bowls' bunny).
        match at.nodes {
            Some(nodes) => {
                let mut slots: Vec<_> = rows.into_iter().map(Some).collect();
                let mut ordered: Vec<_> = nodes
                    .perm
                    .iter()
                    .filter_map(|&p| {
                        let j = (p as usize).wrapping_sub(at.start);
                        slots.get_mut(j)?.take().map(|row| (j, row))
                    })
                    .collect();
                // Patches the tree does not order (none in a valid bundle), after them.
                ordered.extend(
                    slots
                        .into_iter()
                        .enumerate()
                        .filter_map(|(j, row)| row.map(|row| (j, row))),
                );
                // The node rows after them (each in the tree's order too).
                ordered.extend(
                    tail_rows
                        .into_iter()
                        .enumerate()
                        .map(|(x, row)| (n + x, row)),
                );
                ordered
            }
            None => rows.into_iter().enumerate().collect(),
        }
    }

    /// In: the ordered rows and what every row reads. Writes every row's values (before the
    /// energy bound) in parallel blocks of rows; out: how many blocks, whose sums are the
    /// first ones of `scratch`.
    fn write_blocks(
        &self,
        input: WriteInput<'_>,
        rows: &mut [(usize, Row<'_>)],
        scratch: &mut Scratch,
    ) -> usize {
        let n = self.row_ptr.len() - 1;
        let node_count = self.node_count(input.at);
        // Blocks over every row, node rows included, of about equal work: a row's terms,
        // entries and links (each link reads the table twice). Blocks of equal row counts
        // differed 3.5× in entries on the bowls' bunny (its rows' reach varies with the
        // shape, and node rows hold links alone), and one thread sat idle for a quarter of
        // the loop while the other finished the heaviest block.
        let cost = |(j, (cols, _)): &(usize, Row<'_>)| self.row_cost(*j, cols.len());
        let chunks = even_runs(rows, rayon::current_num_threads() * 4, cost);
        let blocks = chunks.len();
        scratch.blocks.resize_with(blocks, BlockSums::default);
        chunks
            .into_par_iter()
            .zip(scratch.blocks.par_iter_mut())
            .for_each(|(chunk, sums)| {
                sums.column.clear();
                sums.column.resize(n, f32x4::ZERO);
                sums.node.clear();
                sums.node.resize(node_count, f32x4::ZERO);
                (sums.kept, sums.linked) = (0, 0);
                // Σ 0·x over every value written: 0 while all are finite, NaN after any
                // that is not (cheaper than testing each).
                let mut probe = f32x4::ZERO;
                for (j, (cols, out)) in chunk.iter_mut() {
                    self.write_row(*j, (*cols, &mut **out), input, sums, &mut probe);
                }
                sums.finite = probe.to_array().iter().all(|&x| x == 0.0);
            });
        blocks
    }

    /// Row j's work in a block (its terms, entries and links, a link counted twice), from
    /// its index and its count of columns.
    fn row_cost(&self, j: usize, cols: usize) -> u64 {
        let (entries, terms) = match self.row_ptr.get(j..j + 2) {
            Some(&[a, b]) => (
                (b - a) as u64,
                (self.term_ptr[b as usize] - self.term_ptr[a as usize]) as u64,
            ),
            _ => (0, 0),
        };
        terms + entries + 2 * (cols as u64 - entries)
    }

    /// Writes row j (a patch's, or node row j − n) into `out`: its direct entries, then its
    /// links; adds into `sums` its columns' and nodes' energies, its entries kept and links
    /// within reach, and into `probe` 0 × every value written.
    #[inline]
    fn write_row(
        &self,
        j: usize,
        (cols, out): Row<'_>,
        input: WriteInput<'_>,
        sums: &mut BlockSums,
        probe: &mut f32x4,
    ) {
        let n = self.row_ptr.len() - 1;
        let at = input.at;
        // A node row (j ≥ n): node m's links alone, weighed by m's area.
        let (set, entries, aj) = match at.nodes {
            Some(nodes) if j >= n => (&self.pairs, 0..0, { nodes.area[self.recv[j - n] as usize] }),
            _ => (
                &self.links,
                self.row_ptr[j] as usize..self.row_ptr[j + 1] as usize,
                input.area[j],
            ),
        };
        let l = if j >= n { j - n } else { j };
        let links = match set.ptr.get(l..l + 2).filter(|_| at.nodes.is_some()) {
            Some(l) => l[0] as usize..l[1] as usize,
            None => 0..0,
        };
        assert_eq!(
            out.len(),
            entries.len() + links.len(),
            "row {j} is not laid out as ObjectTerms::pattern made it"
        );
        let (direct, tail) = out.split_at_mut(entries.len());
        let span = RowSpan {
            j,
            entries,
            set,
            links,
            aj,
        };
        self.write_entries(&span, (cols, direct), input, sums, probe);
        let Some(nodes) = at.nodes else {
            tail.fill([0.0; 3]);
            return;
        };
        let node_cols = &cols[direct.len()..];
        self.write_links(&span, (node_cols, tail), nodes, input, sums, probe);
    }

    /// Writes a row's direct entries into `direct` (`cols` the row's columns): each entry's
    /// sum of terms, 0 where not kept; adds A_j S_ji into column i's sum.
    #[inline]
    fn write_entries(
        &self,
        span: &RowSpan<'_>,
        (cols, direct): Row<'_>,
        input: WriteInput<'_>,
        sums: &mut BlockSums,
        probe: &mut f32x4,
    ) {
        let (j, entries, aj) = (span.j, span.entries.clone(), span.aj);
        // The row's entries' fields side by side: one bounds check a row, not
        // five an entry.
        let fields = self.src[entries.clone()]
            .iter()
            .zip(&self.dist[entries.clone()])
            .zip(&self.hi_max[entries.clone()])
            .zip(&self.opposite[entries.clone()])
            .zip(self.term_ptr[entries.start..=entries.end].windows(2));
        for (k, (o, ((((&i, &dist), &hi_max), &opposite), t))) in
            direct.iter_mut().zip(fields).enumerate()
        {
            let i = i as usize;
            let e = EntryRef {
                src: i,
                dist,
                hi_max,
                opposite,
                terms: t[0] as usize..t[1] as usize,
            };
            let (v, kept) = self.value(e, j, input.same, input.other);
            debug_assert_eq!(cols[k] as usize, input.at.start + i);
            sums.kept += kept as u64;
            *probe += v * f32x4::ZERO;
            sums.column[i] += f32x4::splat(aj) * v;
            *o = rgb(v);
        }
    }

    /// Writes a row's links into `tail` (`node_cols` their columns, N + k): node k's
    /// A_k R(r), read through the table of the entry's kind; adds A_j R(r) into e_k.
    #[inline]
    fn write_links(
        &self,
        span: &RowSpan<'_>,
        (node_cols, tail): Row<'_>,
        nodes: &Nodes,
        input: WriteInput<'_>,
        sums: &mut BlockSums,
        probe: &mut f32x4,
    ) {
        let (set, links, aj) = (span.set, span.links.clone(), span.aj);
        let two = set.two.get(links.clone()).unwrap_or(&[]);
        let fields = set.root[links.clone()].iter().zip(&set.opposite[links]);
        for (l, ((o, &c), (&root, &opposite))) in
            tail.iter_mut().zip(node_cols).zip(fields).enumerate()
        {
            let tab = if opposite { input.other } else { input.same };
            let within = root < tab.end;
            sums.linked += within as u64;
            // A link read at two distances: the mean of the profile at both (as
            // `smatrix::node_links` reads it), 0 past the table's end.
            let two = two.get(l).copied().filter(|_| within);
            let r = link_lanes(two, root, |x| tab.r_lanes(x));
            let k = c as usize - input.at.n;
            let a = nodes.area[k];
            sums.node[k - self.links.nodes.start] += f32x4::splat(aj) * r;
            let v = r * f32x4::splat(a);
            *probe += v * f32x4::ZERO;
            *o = rgb(v);
        }
    }

    /// In: the tree, the object's patch areas, its placement and its linked nodes' e_k,
    /// and the direct bound. Bounds every column with its links counted (as
    /// `subsurface::add_links`), updating `bound`, and scales the links in `rows` when
    /// given; out: each linked node's factor.
    fn bound_links(
        &self,
        nodes: &Nodes,
        (area, at, node): (&[f32], Placement<'_>, &[[f32; 3]]),
        bound: &mut ColumnBound,
        rows: Option<&mut [(usize, Row<'_>)]>,
    ) -> Vec<[f32; 3]> {
        let n = self.row_ptr.len() - 1;
        let span = NodeSpan {
            nodes,
            first: self.links.nodes.start,
            start: at.start,
            n,
        };
        let far = span.spread(node, &|_| [1.0; 3]);
        // As subsurface::add_links: each column's factor as a pairwise S would scale
        // it, every link to node k scaled by k's patches' area-weighted mean factor
        // (a node covers a contiguous range of the tree's order: prefix sums), then the
        // direct entries by that factor, or further where the node's mean left more.
        let direct: Vec<[f32; 3]> = (0..n)
            .map(|i| std::array::from_fn(|c| bound.total[i][c] * bound.factor[i][c]))
            .collect();
        let pair_factor: Vec<[f32; 3]> = (0..n)
            .map(|i| std::array::from_fn(|c| 1.0 / (direct[i][c] + far[i][c]).max(1.0)))
            .collect();
        let mean_factor = span.mean_factors(area, &pair_factor, node);
        let nodes_scaled = mean_factor.iter().any(|m| *m != [1.0; 3]);
        let far_kept = if nodes_scaled {
            span.spread(node, &|k| mean_factor[k])
        } else {
            far.clone()
        };
        if let Some(rows) = rows.filter(|_| nodes_scaled) {
            scale_links(rows, at.n + self.links.nodes.start, &mean_factor);
        }
        bound.count_links(&direct, &far, &far_kept, &pair_factor);
        mean_factor
    }

    /// The energy bound's factors of the object's columns from the sums a write adds up
    /// (a device's write, [`FlatTerms`]): `column` holds each column's Σ_j A_j S_ji before the
    /// bound, `node` each linked node's e_k = Σ_j A_j R(r_jk) (as many as
    /// [`FlatTerms::nodes`]); `area` the object's patch areas. The factors
    /// [`ObjectTerms::write`] with [`Placement::defer_bound`] returns for the same values,
    /// to the rounding of the sums' order.
    pub fn factors_from_sums(
        &self,
        area: &[f32],
        at: Placement<'_>,
        column: &[[f32; 3]],
        node: &[[f32; 3]],
    ) -> ColumnFactors {
        let mut bound = ColumnBound::direct(column, area, 0);
        let linked = node.iter().any(|e| *e != [0.0; 3]);
        let nodes = match (at.nodes, linked) {
            (Some(nodes), true) => self.bound_links(nodes, (area, at, node), &mut bound, None),
            _ => vec![[1.0f32; 3]; node.len()],
        };
        ColumnFactors {
            patches: bound.factor,
            nodes,
            node_column: at.n + self.links.nodes.start,
        }
    }

    /// Scales the direct entries of the columns over the bound (`factor` per local column,
    /// the object starting at patch `start`) in `rows`.
    fn scale_columns(&self, rows: &mut [(usize, Row<'_>)], factor: &[[f32; 3]], start: usize) {
        let n = self.row_ptr.len() - 1;
        let scaled: Vec<bool> = factor.iter().map(|f| *f != [1.0; 3]).collect();
        // The entries of the scaled columns: few (a few hundred columns of the bunny's
        // 69,451) are found through the entries by source, many (most columns of a bowl
        // dragged to a wide profile) by one parallel pass over every row's columns.
        let touched: usize = (0..n)
            .filter(|&i| scaled[i])
            .map(|i| (self.by_src_ptr[i + 1] - self.by_src_ptr[i]) as usize)
            .sum();
        if touched > 0 && touched * 16 < self.src.len() {
            self.scale_by_source(rows, factor, &scaled, start);
        } else if touched > 0 {
            scale_every_row(rows, factor, &scaled, start, n);
        }
    }

    /// Scales the entries of the `scaled` columns by their `factor`, found through the
    /// entries by source (few columns).
    fn scale_by_source(
        &self,
        rows: &mut [(usize, Row<'_>)],
        factor: &[[f32; 3]],
        scaled: &[bool],
        start: usize,
    ) {
        let n = self.row_ptr.len() - 1;
        // Where row j sits among `rows`.
        let mut slot = vec![u32::MAX; n];
        for (x, (j, _)) in rows.iter().enumerate() {
            if let Some(s) = slot.get_mut(*j) {
                *s = x as u32;
            }
        }
        for (i, f) in factor.iter().enumerate().filter(|&(i, _)| scaled[i]) {
            let entries = self.by_src_ptr[i] as usize..self.by_src_ptr[i + 1] as usize;
            for &[j, e] in &self.by_src[entries] {
                let (j, e) = (j as usize, e as usize);
                let (_, (cols, out)) = &mut rows[slot[j] as usize];
                let k = e - self.row_ptr[j] as usize;
                debug_assert_eq!(cols[k] as usize, start + i);
                out[k] = std::array::from_fn(|ch| out[k][ch] * f[ch]);
            }
        }
    }

    /// Stored entries (the self terms included).
    pub fn entries(&self) -> usize {
        self.src.len()
    }

    /// Radial terms stored.
    pub fn terms(&self) -> usize {
        self.packed.len()
    }

    /// Entries and their terms by how many terms an entry has: bucket b counts entries of
    /// 2^b to 2^(b+1) − 1 terms (1, 2–3, 4–7, 8–15, 16–31, 32 and more).
    pub fn term_histogram(&self) -> [(usize, usize); 6] {
        let mut h = [(0, 0); 6];
        for t in self.term_ptr.windows(2) {
            let c = (t[1] - t[0]) as usize;
            let b = (usize::BITS - c.max(1).leading_zeros() - 1).min(5) as usize;
            h[b].0 += 1;
            h[b].1 += c;
        }
        h
    }

    /// Bytes held.
    pub fn bytes(&self) -> u64 {
        (self.row_ptr.len() * 4
            + self.src.len() * 4
            + self.dist.len() * 4
            + self.opposite.len()
            + self.hi_max.len() * 4
            + self.term_ptr.len() * 4
            + self.by_src_ptr.len() * 4
            + self.by_src.len() * 8
            + self.packed.len() * 8
            + self.bounds.len() * 8
            + self.links.bytes()
            + self.pairs.bytes()
            + self.recv.len() * 4) as u64
    }
}

/// Every translucent object's and thin sheet's [`ObjectTerms`] of one bundle, by object
/// index (as the bundle was built: an override that turns an object into another kind of
/// material is assembled by quadrature).
#[derive(Debug, Default)]
pub struct STerms {
    objects: Vec<Option<ObjectTerms>>,
    /// Seconds the reduction took.
    pub seconds: f64,
}

impl STerms {
    /// Terms by object index (`None` for objects that have none), reduced in `seconds`.
    pub fn new(objects: Vec<Option<ObjectTerms>>, seconds: f64) -> STerms {
        STerms { objects, seconds }
    }

    /// Object `k`'s terms, if it was built translucent (`sheet == false`) or as a thin sheet
    /// (`sheet == true`).
    pub fn get(&self, k: usize, sheet: bool) -> Option<&ObjectTerms> {
        self.objects
            .get(k)
            .and_then(|o| o.as_ref())
            .filter(|o| o.sheet == sheet)
    }

    /// Entries over all objects.
    pub fn entries(&self) -> usize {
        self.objects
            .iter()
            .flatten()
            .map(ObjectTerms::entries)
            .sum()
    }

    /// Terms over all objects.
    pub fn terms(&self) -> usize {
        self.objects.iter().flatten().map(ObjectTerms::terms).sum()
    }

    /// Bytes held.
    pub fn bytes(&self) -> u64 {
        self.objects.iter().flatten().map(ObjectTerms::bytes).sum()
    }

    /// [`ObjectTerms::term_histogram`] over all objects.
    pub fn term_histogram(&self) -> [(usize, usize); 6] {
        self.objects.iter().flatten().fold([(0, 0); 6], |mut h, o| {
            for (t, p) in h.iter_mut().zip(o.term_histogram()) {
                (t.0, t.1) = (t.0 + p.0, t.1 + p.1);
            }
            h
        })
    }

    /// Links from a patch to a node, and node-to-node links, over all objects.
    pub fn links(&self) -> (usize, usize) {
        self.objects.iter().flatten().fold((0, 0), |(l, p), o| {
            (l + o.patch_links(), p + o.node_pairs())
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::profile::ProfileEval;
    use translux_proto::scene::Profile;

    /// Σ weight · ρᵏ over terms (ρ = root²): what a rule integrates ρᵏ to.
    fn power_sum(terms: &[Term], k: i32) -> f64 {
        terms
            .iter()
            .map(|t| t.weight as f64 * (t.root as f64).powi(2 * k))
            .sum()
    }

    /// The marble preset's dipole (Jensen et al. 2001), its mean free path scaled by
    /// `scale` (the translucency slider), in a millimetre scene.
    fn table(scale: f32, r_max: f32) -> Tabulated {
        let p = Profile::Dipole {
            preset: Some("marble".into()),
            sigma_a: None,
            sigma_s_prime: None,
            eta: None,
            scale: Some(scale),
        };
        Tabulated::new(&ProfileEval::new(&p, 1.0).unwrap(), r_max, 4096)
    }

    /// The rewrite's table (R's cells, a 0 cell, W's cells, W's total; no branch per term)
    /// reads what the profile's own table reads, bit for bit: R and W inside the table, on
    /// a cell's edge, at its last cell, and past its end (R 0, W its total), with weights
    /// of either sign.
    #[test]
    fn the_rewrites_table_reads_r_and_w_as_the_profiles_table_does() {
        let tab = table(1.0, 3.0);
        let tt = TermTable::new(&tab);
        let end = tab.root_max();
        let step = end / 4096.0;
        let roots = [
            0.0,
            0.3 * step,
            step,
            17.5 * step,
            0.5 * end,
            end - 0.5 * step,
            end * (1.0 - 1e-6),
            end,
            1.5 * end,
            1e30,
        ];
        for root in roots {
            for weight in [0.75f32, -2.5] {
                let w_of = |v: [f32; 3]| v.map(|x| x * weight);
                let r = rgb(tt.sum_packed(&[[root, weight]]));
                assert_eq!(r, w_of(tab.r_root(root)), "R at root {root}");
                assert_eq!(tt.r_root(root), tab.r_root(root), "r_root at {root}");
                let w = rgb(tt.sum_packed(&[[-root, weight]]));
                // (−0 is a W term too: W(0).)
                assert_eq!(w, w_of(tab.w_root(root)), "W at root {root}");
            }
        }
        // W's total is not 0, so reading it past the end is tested above.
        assert!(tab.w_root(1e30).iter().all(|&v| v > 0.0));
        assert_eq!(tt.r_root(1.5 * end), [0.0; 3]);
    }

    fn rel(a: [f32; 3], b: [f32; 3]) -> f32 {
        (0..3)
            .map(|c| (a[c] - b[c]).abs() / b[c].abs().max(1e-30))
            .fold(0.0, f32::max)
    }

    fn check(plan: Quadrature, r: f32, xs: &[Vec3], tol: f32, what: &str) -> usize {
        let params = SubsurfaceParams::default();
        let mut terms = Vec::new();
        reduce(&plan, r, xs, &params, &mut terms);
        assert!(terms.len() <= MAX_TERMS, "{what}: {}", terms.len());
        for scale in [0.25, 1.0, 4.0] {
            let tab = table(scale, 200.0);
            let exact = plan.eval(r, xs, &tab, &params);
            let mut got = [0.0f32; 3];
            for t in &terms {
                let v = t.eval(&tab);
                for c in 0..3 {
                    got[c] += v[c];
                }
            }
            let e = rel(got, exact);
            assert!(
                e <= tol,
                "{what} at ×{scale}: terms {got:?} vs quadrature {exact:?} ({e:.2e})"
            );
        }
        terms.len()
    }

    #[test]
    fn terms_match_the_quadrature_at_every_translucency() {
        let params = SubsurfaceParams::default();
        // Patch sizes from well below to well above a mean free path (~0.4 mm here).
        for side in [0.1f32, 1.0, 5.0] {
            let a = [
                Vec3::ZERO,
                Vec3::new(side, 0.0, 0.0),
                Vec3::new(0.0, 0.0, side),
            ];
            let b = [
                Vec3::new(side, 0.0, 0.0),
                Vec3::new(side, 0.0, side),
                Vec3::new(0.0, 0.0, side),
            ];
            // Across an edge: a wall rising from a's edge x = 0.
            let w = [
                Vec3::ZERO,
                Vec3::new(0.0, side, 0.0),
                Vec3::new(0.0, 0.0, side),
            ];
            let n = Vec3::Y;
            let xs = subsurface::samples(&a, params.samples);
            let area = 0.5 * side * side;
            let self_plan = Quadrature::Polar {
                tri: a,
                normal: n,
                factor: 1.0,
            };
            check(
                self_plan,
                0.0,
                &xs,
                1e-3,
                &format!("self term, side {side}"),
            );
            let near = Quadrature::Polar {
                tri: b,
                normal: n,
                factor: 1.0,
            };
            check(
                near,
                side * 0.5,
                &xs,
                1e-3,
                &format!("coplanar pair, side {side}"),
            );
            let across = Quadrature::Points {
                tri_j: w,
                excess: 0.0,
                area_i: area,
            };
            check(
                across,
                side * 0.5,
                &xs,
                1e-3,
                &format!("across an edge, side {side}"),
            );
            // The same wall by the lifted polar rule (a straight path), and a facet folded
            // 10° down from b's edge (neighbouring facets of a curved mesh).
            let wall = Quadrature::Lifted {
                tri: w,
                normal: Vec3::X,
                factor: 1.0,
                source: None,
            };
            check(
                wall,
                side * 0.5,
                &xs,
                1e-3,
                &format!("across an edge, lifted, side {side}"),
            );
            // The same, integrated from (2m)² points of a (a crease's plan).
            check(
                Quadrature::Lifted {
                    tri: w,
                    normal: Vec3::X,
                    factor: 1.0,
                    source: Some(a),
                },
                side * 0.5,
                &xs,
                1e-3,
                &format!("across a crease, lifted, side {side}"),
            );
            // b turned 10° down about the diagonal it shares with a.
            let pivot = Vec3::new(side, 0.0, 0.0);
            let turn = glam::Quat::from_axis_angle(
                Vec3::new(-1.0, 0.0, 1.0).normalize(),
                10f32.to_radians(),
            );
            let folded = b.map(|v| pivot + turn * (v - pivot));
            let folded_n = (folded[1] - folded[0])
                .cross(folded[2] - folded[0])
                .normalize();
            check(
                Quadrature::Lifted {
                    tri: folded,
                    normal: folded_n,
                    factor: 1.0,
                    source: None,
                },
                side * 0.5,
                &xs,
                1e-3,
                &format!("folded facet, lifted, side {side}"),
            );
            // A coplanar pair two cells away (near, not touching): its radii span a ratio of
            // about 2, two Gauss bins.
            let shifted = b.map(|v| v + Vec3::new(2.0 * side, 0.0, 0.0));
            let apart = Quadrature::Polar {
                tri: shifted,
                normal: n,
                factor: 1.0,
            };
            // (At side 5 and ×0.25 the blue profile falls ~300× across the pair: 1.4e-3.)
            let terms = check(
                apart,
                side * 2.5,
                &xs,
                2e-3,
                &format!("coplanar pair two cells apart, side {side}"),
            );
            assert!(terms <= 6, "{terms} terms for a pair two cells apart");
            let far = Quadrature::Far {
                area_i: area,
                shift: 0.0,
                sigma: 0.0,
            };
            // Only the table lookup differs: linear in √r instead of r within a grid cell.
            check(
                far,
                3.0 * side,
                &xs,
                1e-4,
                &format!("far pair, side {side}"),
            );
        }
    }

    #[test]
    fn a_self_term_is_exact_for_a_constant_profile_too() {
        // R ≡ 1: W(ρ) = πρ², the polar integral is the triangle's area whatever the bins.
        let t = [Vec3::ZERO, Vec3::X, Vec3::Z];
        let xs = subsurface::samples(&t, 4);
        let plan = Quadrature::Polar {
            tri: t,
            normal: Vec3::Y,
            factor: 1.0,
        };
        let mut terms = Vec::new();
        reduce(&plan, 0.0, &xs, &SubsurfaceParams::default(), &mut terms);
        assert_eq!(terms[0].of(), Of::W, "the head is one exact W term");
        let got: f32 = terms
            .iter()
            .map(|t| match t.of() {
                Of::W => t.weight * std::f32::consts::PI * t.root.powi(4),
                Of::R { .. } => t.weight,
            })
            .sum();
        // The rays' own sum (what the quadrature computes), which the terms must equal.
        let params = SubsurfaceParams::default();
        let mut rays = 0.0f64;
        for &x in &xs {
            subsurface::polar_intervals(x, &t, Vec3::Y, params.directions, |lo, hi| {
                rays += std::f64::consts::PI * (hi as f64 * hi as f64 - lo as f64 * lo as f64);
            });
        }
        let rays = (rays / (xs.len() as f64 * params.directions as f64)) as f32;
        assert!(
            (got - rays).abs() < rays * 1e-4 && (got - 0.5).abs() < 0.5 * 0.02,
            "∫ 1 over the triangle = {got} (rays: {rays}, area 0.5)"
        );
    }

    /// Point terms integrate the samples: every power of ρ up to the fifth summed over the
    /// terms is its sum over the samples (each bin's rule is exact to that degree, and the
    /// bins split the samples), every node lies within its bin's samples and weighs more
    /// than 0, and a bin gives at most three. A sample lost or counted twice, a bin's
    /// moments in the wrong coordinate, or a node placed outside fails it.
    #[test]
    fn point_terms_integrate_the_samples_to_degree_five() {
        // Samples as a near pair makes them (distances between two triangles' points), one
        // on a bin edge, a wide spread (many bins), a narrow one (a sliver of the first
        // bin, which reaches down to 0), ties and 0, a count no multiple of 4.
        let mut seed = 7u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 40) as f32 / (1u64 << 24) as f32
        };
        let cases: Vec<Vec<f32>> = vec![
            (0..256).map(|_| 0.2 + 3.0 * next()).collect(),
            (0..256).map(|_| 1e-3 + 40.0 * next() * next()).collect(),
            (0..256).map(|_| 5.0 + 0.01 * next()).collect(),
            (0..100)
                .map(|k| [0.0, 1.0, 1.5, 2.25, 3.375][k % 5])
                .collect(),
            vec![2.0; 16],
            (0..19).map(|_| 0.5 + next()).collect(),
        ];
        let c = 0.37f32;
        for (k, rho) in cases.iter().enumerate() {
            let mut got = Vec::new();
            point_terms(rho, c, &mut got);
            let e = point_edges(rho);
            assert!(
                !got.is_empty() && got.len() <= 3 * (e.len() - 1),
                "case {k}: {} terms for {} bins",
                got.len(),
                e.len() - 1
            );
            // Each bin's samples' span.
            let inner = &e[1..e.len() - 1];
            let mut spans = vec![(f64::INFINITY, f64::NEG_INFINITY); e.len() - 1];
            for &x in rho {
                let x = x as f64;
                let s = &mut spans[inner.partition_point(|&edge| edge < x)];
                *s = (s.0.min(x), s.1.max(x));
            }
            for t in &got {
                // A node's radius is rounded to f32: on a bin's edge it may read as the next.
                let r = t.root as f64 * t.root as f64;
                let slack = 1e-6 * r.max(1e-30);
                assert!(
                    spans
                        .iter()
                        .any(|&(lo, hi)| r >= lo - slack && r <= hi + slack)
                        && t.weight > 0.0,
                    "case {k}: node at ρ = {r} (weight {}) outside every bin's samples {spans:?}",
                    t.weight
                );
                assert!(matches!(t.of(), Of::R { .. }), "case {k}: a W term");
            }
            for p in 0..=5 {
                let want: f64 = rho.iter().map(|&r| c as f64 * (r as f64).powi(p)).sum();
                let sum = power_sum(&got, p);
                assert!(
                    (sum - want).abs() <= 1e-5 * want,
                    "case {k}: Σ ρ^{p} = {sum} over the terms, {want} over the samples"
                );
            }
        }
    }

    /// A bin's three-node rule integrates ρᵏ, k ≤ 5, exactly over the measure it replaces
    /// (a discrete one and the polar ring measure c ρ dρ), with nodes inside the bin and
    /// positive weights; a two-point support gets its two points back.
    #[test]
    fn a_bins_gauss_rule_is_exact_to_degree_five() {
        let (a, h) = (2.0f64, 2.0f64);
        // Uneven samples in [2, 4] with uneven weights.
        let pts: Vec<(f64, f64)> = (0..40)
            .map(|k| {
                let u = (k as f64 * 0.618_034).fract();
                (a + h * u * u, 0.5 + u)
            })
            .collect();
        let mut m = Moments::default();
        for &(r, w) in &pts {
            m.point((r - a) / h, w);
        }
        let mut out = Vec::new();
        gauss_terms(&m, a, h, &mut out);
        assert_eq!(out.len(), 3);
        for k in 0..=5 {
            let want: f64 = pts.iter().map(|&(r, w)| w * r.powi(k)).sum();
            let got = power_sum(&out, k);
            assert!((got - want).abs() <= 1e-5 * want, "ρ^{k}: {got} vs {want}");
        }
        for t in &out {
            let r = t.root * t.root;
            assert!(t.weight > 0.0 && (2.0..=4.0).contains(&r), "{t:?}");
        }
        // The ring measure 3 ρ dρ on [2.5, 3.5] (t in [0.25, 0.75]): ∫ ρᵏ 3ρ dρ.
        let mut m = Moments::default();
        m.ring((0.25, 0.75), a, h, 3.0);
        let mut out = Vec::new();
        gauss_terms(&m, a, h, &mut out);
        for k in 0..=5 {
            let want = 3.0 * (3.5f64.powi(k + 2) - 2.5f64.powi(k + 2)) / (k + 2) as f64;
            let got = power_sum(&out, k);
            assert!(
                (got - want).abs() <= 1e-5 * want,
                "ring ρ^{k}: {got} vs {want}"
            );
        }
        // Two points: the rule is those points.
        let mut m = Moments::default();
        m.point(0.1, 2.0);
        m.point(0.9, 1.0);
        let mut out = Vec::new();
        gauss_terms(&m, a, h, &mut out);
        let mut got: Vec<(f32, f32)> = out
            .iter()
            .filter(|t| t.weight > 1e-6)
            .map(|t| (t.root * t.root, t.weight))
            .collect();
        got.sort_by(|x, y| x.0.total_cmp(&y.0));
        assert_eq!(got.len(), 2, "{out:?}");
        assert!(
            (got[0].0 - 2.2).abs() < 1e-4 && (got[0].1 - 2.0).abs() < 1e-4,
            "{got:?}"
        );
        assert!(
            (got[1].0 - 3.8).abs() < 1e-4 && (got[1].1 - 1.0).abs() < 1e-4,
            "{got:?}"
        );
    }

    /// A sheet of `cells` × `cells` unit cells (two triangles each) placed by `point`, its
    /// pairs within `reach` stored, reduced to terms.
    fn sheet_terms(
        cells: usize,
        point: impl Fn(f32, f32) -> Vec3,
        reach: f32,
    ) -> (crate::smatrix::PatchGeometry, ObjectTerms) {
        use crate::smatrix::{PatchGeometry, object_patches};
        use translux_proto::csr::CsrBuilder;
        let mut corners = Vec::new();
        for a in 0..cells {
            for b in 0..cells {
                let (x, y) = (a as f32, b as f32);
                corners.push([point(x, y), point(x + 1.0, y), point(x + 1.0, y + 1.0)]);
                corners.push([point(x, y), point(x + 1.0, y + 1.0), point(x, y + 1.0)]);
            }
        }
        let g = PatchGeometry::from_corners(corners);
        let n = g.area.len();
        let mut d = CsrBuilder::new(n);
        for i in 0..n {
            let row: Vec<(u32, f32)> = (0..n)
                .filter(|&j| j != i)
                .map(|j| (j as u32, g.centroid[i].distance(g.centroid[j])))
                .filter(|&(_, r)| r < reach)
                .collect();
            d.push_row(&row).unwrap();
        }
        let d = d.finish();
        let p = object_patches(&g, 0..n);
        let params = SubsurfaceParams::default();
        let t = ObjectTerms::build(p, d.view().unwrap(), false, &|_| false, &params);
        (g, t)
    }

    /// The flat records a device writes through ([`ObjectTerms::flatten`]) put each entry
    /// at S's value for its column, and the energy bound's factors taken from the sums a
    /// device adds up through their column gather ([`ObjectTerms::factors_from_sums`])
    /// are those a deferred write returns, with many columns scaled and with none.
    #[test]
    fn factors_from_a_devices_sums_are_the_writes_own() {
        let point = |x: f32, y: f32| Vec3::new(x, y, 0.0);
        let (g, t) = sheet_terms(6, point, 5.0);
        let n = g.area.len();
        // Every third patch counted 6 times as large drives its neighbours' columns past 1.
        let area: Vec<f32> = (0..n)
            .map(|i| g.area[i] * if i % 3 == 0 { 6.0 } else { 1.0 })
            .collect();
        let pattern = t.pattern(0, false);
        let mut row_ptr = vec![0u64];
        for r in &pattern {
            row_ptr.push(row_ptr.last().unwrap() + r.len() as u64);
        }
        let at = Placement {
            start: 0,
            n,
            nodes: None,
            defer_bound: true,
        };
        let flat = t.flatten(&area, at, &row_ptr).unwrap();
        assert_eq!(flat.values as u64, row_ptr[n]);
        assert_eq!(
            flat.runs.len(),
            1,
            "one object's rows are one run of S's values"
        );
        for (j, row) in flat.rows.iter().enumerate() {
            for e in row.entries[0]..row.entries[1] {
                let v = (row.value + e - row.entries[0]) as usize;
                let (col, _) = pattern[j][v - row_ptr[j] as usize];
                assert_eq!(col, flat.entries[e as usize].src, "row {j}, entry {e}");
            }
        }
        let mut scaled = 0;
        for scale in [0.5f32, 8.0] {
            let tab = table(scale, 5.0);
            let (_, vals, w) = t.write_local(&area, &tab, &tab, true);
            let want = w.columns.unwrap();
            let values: Vec<[f32; 3]> = vals.into_iter().flatten().collect();
            let column: Vec<[f32; 3]> = (0..n)
                .map(|i| {
                    let items = &flat.column_items
                        [flat.column_ptr[i] as usize..flat.column_ptr[i + 1] as usize];
                    let mut s = [0.0f32; 3];
                    for &[v, a] in items {
                        for c in 0..3 {
                            s[c] += f32::from_bits(a) * values[v as usize][c];
                        }
                    }
                    s
                })
                .collect();
            let got = t.factors_from_sums(&area, at, &column, &[]);
            for (i, (g, w)) in got.patches.iter().zip(&want.patches).enumerate() {
                assert!(
                    (0..3).all(|c| (g[c] - w[c]).abs() <= 1e-5 * w[c]),
                    "column {i} at scale {scale}: {g:?} vs {w:?}"
                );
            }
            scaled += want.patches.iter().filter(|f| **f != [1.0; 3]).count();
        }
        assert!(
            scaled > 0,
            "no column was scaled: the factors went untested"
        );
    }

    /// A write's `finite` says whether every value it wrote is finite: true under marble,
    /// false under a profile whose values overflow once weighed by the cells' areas.
    #[test]
    fn a_write_reports_whether_every_value_it_wrote_is_finite() {
        // A flat 40 × 40 mm sheet of 10 mm cells, every pair within 30 mm stored.
        let (g, t) = sheet_terms(4, |x, y| Vec3::new(10.0 * x, 10.0 * y, 0.0), 30.0);
        let write = |tab: &Tabulated| {
            let (_, vals, w) = t.write_local(&g.area, tab, tab, false);
            let all_finite = vals.iter().flatten().flatten().all(|x| x.is_finite());
            (w.finite, all_finite)
        };
        assert_eq!(write(&table(1.0, 30.0)), (true, true), "marble");
        // A profile near f32's largest value: weighed by 10 mm cells' areas, it overflows.
        let huge = Profile::Table {
            radius_mm: vec![0.0, 30.0],
            values: vec![[3.0e38; 3], [3.0e38; 3]],
        };
        let tab = Tabulated::new(&ProfileEval::new(&huge, 1.0).unwrap(), 30.0, 4096);
        assert_eq!(write(&tab), (false, false), "a profile that overflows");
    }

    /// A rewrite's blocks ([`even_runs`]): exact runs for small cases, and on random costs
    /// every item in one run, in order, none empty, none past a share plus one item.
    #[test]
    fn even_runs_cut_by_cost_cover_every_item_once() {
        // Costs 1 ×12 then 12: four runs of a total 24 end at shares of 6.
        let mut items: Vec<u64> = vec![1; 12];
        items.push(12);
        let runs = even_runs(&mut items, 4, |&c| c);
        let lens: Vec<usize> = runs.iter().map(|r| r.len()).collect();
        assert_eq!(
            lens,
            vec![6, 6, 1],
            "the heavy item alone, its shares taken"
        );
        // Equal costs: equal runs; fewer items than runs: one each; none: none.
        let mut even = vec![3u64; 16];
        let lens: Vec<usize> = even_runs(&mut even, 8, |&c| c)
            .iter()
            .map(|r| r.len())
            .collect();
        assert_eq!(lens, vec![2; 8]);
        let mut few = vec![5u64; 3];
        assert_eq!(even_runs(&mut few, 8, |&c| c).len(), 3);
        let mut zero = vec![0u64; 5];
        let lens: Vec<usize> = even_runs(&mut zero, 2, |&c| c)
            .iter()
            .map(|r| r.len())
            .collect();
        assert_eq!(
            lens.iter().sum::<usize>(),
            5,
            "zero costs: every item still in a run"
        );
        assert!(even_runs(&mut Vec::<u64>::new(), 4, |&c| c).is_empty());
        // Random costs: every item in exactly one run, in order, no run empty, and no run
        // past a share plus its last item.
        let mut state = 7u64;
        let mut rnd: Vec<u64> = (0..1000)
            .map(|_| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (state >> 33) % 100
            })
            .collect();
        let total: u64 = rnd.iter().sum();
        let copy = rnd.clone();
        let runs = even_runs(&mut rnd, 8, |&c| c);
        assert!(runs.len() <= 8 && runs.iter().all(|r| !r.is_empty()));
        let flat: Vec<u64> = runs.iter().flat_map(|r| r.iter().copied()).collect();
        assert_eq!(flat, copy);
        for r in &runs[..runs.len() - 1] {
            let sum: u64 = r.iter().sum();
            assert!(
                sum <= total / 8 + 100,
                "a run of {sum} against a share of {}",
                total / 8
            );
        }
    }

    /// The rows a rebuild writes in row order equal, to f32 rounding, the transpose of
    /// the columns summed and bounded one by one (`subsurface::bound_and_transpose`), on a
    /// folded sheet (two planes, so polar and point plans both occur) at translucencies where
    /// columns are and are not scaled, with pairs past the table's reach left out; with
    /// many columns scaled (one pass over every row) and with a few (found through the
    /// entries by source).
    #[test]
    fn rows_written_in_row_order_equal_the_transposed_columns() {
        // A 6 × 6 mm sheet folded at x = 3 (a right angle), 1 mm cells, two triangles each.
        let point = |x: f32, y: f32| {
            if x <= 3.0 {
                Vec3::new(x, y, 0.0)
            } else {
                Vec3::new(3.0, y, x - 3.0)
            }
        };
        let (g, t) = sheet_terms(6, point, 5.0);
        let n = g.area.len();
        // The bound weighs columns by area: every third patch counted 6 times as large
        // drives its neighbours' columns past 1; one patch 3 times as large, a few.
        let many: Vec<f32> = (0..n)
            .map(|i| {
                if i % 3 == 0 {
                    6.0 * g.area[i]
                } else {
                    g.area[i]
                }
            })
            .collect();
        let mut few = g.area.clone();
        few[40] *= 3.0;
        let widest = t.by_src_ptr.windows(2).map(|w| w[1] - w[0]).max().unwrap() as usize;
        let (mut scaled, mut sparse) = (0, 0);
        for (area, (scale, reach)) in [&many, &few]
            .into_iter()
            .flat_map(|a| [(0.3, 5.0), (1.0, 3.0), (4.0, 5.0)].map(|s| (a, s)))
        {
            let tab = table(scale, reach);
            let got = t.assemble(area, &tab, &tab);
            // The reference: each column summed term by term, bounded and transposed.
            let mut columns: Vec<Vec<(u32, [f32; 3])>> = vec![Vec::new(); n];
            for j in 0..n {
                for e in t.row_ptr[j] as usize..t.row_ptr[j + 1] as usize {
                    let i = t.src[e] as usize;
                    let self_term = i == j;
                    if !self_term && t.dist[e] >= tab.r_max() {
                        continue;
                    }
                    let mut v = [0.0f32; 3];
                    for k in t.term_ptr[e] as usize..t.term_ptr[e + 1] as usize {
                        let x = t.term(k).eval(&tab);
                        for c in 0..3 {
                            v[c] += x[c];
                        }
                    }
                    if self_term || v.iter().any(|&x| x > 0.0) {
                        columns[i].push((j as u32, v));
                    }
                }
            }
            let want = subsurface::bound_and_transpose(columns, area);
            // The same entries; values within f32 rounding (the columns' energies are
            // summed in another order, by blocks of rows).
            let close = |a: f32, b: f32| (a - b).abs() <= 1e-5 * b.abs().max(1e-30);
            for (j, (g, w)) in got.rows.iter().zip(&want.rows).enumerate() {
                assert_eq!(g.len(), w.len(), "row {j} at scale {scale}, reach {reach}");
                for ((gi, gv), (wi, wv)) in g.iter().zip(w) {
                    assert_eq!(gi, wi, "row {j} at scale {scale}");
                    assert!(
                        (0..3).all(|c| close(gv[c], wv[c])),
                        "S[{j}][{gi}] at scale {scale}, reach {reach}: {gv:?} vs {wv:?}"
                    );
                }
            }
            assert_eq!(got.report.nnz, want.report.nnz);
            assert_eq!(got.report.scaled_columns, want.report.scaled_columns);
            assert!(close(got.report.max_column, want.report.max_column));
            assert!(close(got.report.mean_column, want.report.mean_column));
            assert!(
                got.report.nnz > n as u64,
                "pairs were kept at scale {scale}"
            );
            scaled += got.report.scaled_columns;
            // Few enough for the path through the entries by source (at most `widest`
            // entries a column).
            let cols = got.report.scaled_columns;
            sparse += (cols > 0 && cols * widest * 16 < t.entries()) as usize;
        }
        assert!(scaled > 0, "no column was scaled: the bound went untested");
        assert!(
            sparse > 0,
            "no write scaled a few columns: that path went untested"
        );
    }
}
