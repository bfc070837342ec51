//! S's entries reduced to a few radial terms, once per bundle, so a translucency change is
//! a short sum per stored entry instead of a quadrature.
//!
//! In: an object's patches and its block of the stored distances (translucent objects and
//! thin sheets; `smatrix::terms_of_bundle` does a whole bundle), the quadrature settings.
//! Out: [`STerms`], which [`crate::smatrix::assemble_scene`] uses in
//! place of the quadrature of [`crate::subsurface`] whenever a profile changes: every entry
//! S_ji is a sum of at most [`POLAR_BINS`] (or [`POINT_BINS`]) terms of one table lookup
//! each, where the quadrature took up to m² × K (768 by default) lookups of W.
//!
//! Why this is exact where it matters. Every quadrature plan is linear in the profile:
//! - far pairs: A_i R(r_ij), one term;
//! - polar integration (the self term, coplanar and sheet near pairs):
//!   Σ_rays c (W(ρ_out) − W(ρ_in)) = ∫ n(ρ) R(ρ) 2πρ dρ, where n(ρ) counts (with weights c) the
//!   rays that cover radius ρ — a step function fixed by geometry. Over a bin [a, b] the term
//!   n̄ (W(b) − W(a)) with n̄ the bin's area-weighted mean of n is exact when n is constant on
//!   the bin or R is. The first bin runs from 0 to the first ray end, where n is constant:
//!   the profile's peak is integrated exactly at any translucency, and only the tail, where
//!   rays leave the triangle, is binned (geometric bins);
//! - point samples (near pairs across an edge): Σ c R(ρ_q), the samples grouped into
//!   geometric bins of ρ, each group's mass at its mass-weighted mean radius.
//!
//! The binning error is checked against the full quadrature at translucency scales ×0.25 to
//! ×4 (`tests` below, and `precompute/tests/it/subsurface.rs` through a bundle).

use std::ops::Range;

use glam::Vec3;
use rayon::prelude::*;
use translux_proto::csr::CsrView;

use crate::sheet;
use crate::subsurface::{self, ObjectPatches, ObjectS, Quadrature, SubsurfaceParams, Tabulated};

/// Terms of a polar-integration entry: the exact first bin and geometric bins after it.
/// Measured against the quadrature on the Cornell block (marble, skim milk, ketchup at
/// ×0.25 to ×4) and the flower's sheets, a column's re-emitted energy moves by at most
/// 0.15% and 0.27%; with 12 polar and 16 point bins a single plan was off by up to 0.7%.
pub const POLAR_BINS: usize = 32;
/// Terms of a point-sample entry.
pub const POINT_BINS: usize = 24;

/// One radial term: `weight · R(r)` or `weight · W(r)` at r = `root`² (the root is
/// stored: the table's grid is uniform in √r, so a lookup is a multiply).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Term {
    pub root: f32,
    pub weight: f32,
    pub of: Of,
}

impl Term {
    fn new(r: f32, weight: f32, of: Of) -> Term {
        Term {
            root: r.max(0.0).sqrt(),
            weight,
            of,
        }
    }
}

/// Which tabulated function a [`Term`] weighs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Of {
    /// The profile R(r).
    R,
    /// Its integral W(r) = ∫₀^r R 2πr′ dr′.
    W,
}

impl Term {
    /// The term's value under the profile tabulated by `tab`.
    #[inline]
    pub fn eval(&self, tab: &Tabulated) -> [f32; 3] {
        let v = match self.of {
            Of::R => tab.r_root(self.root),
            Of::W => tab.w_root(self.root),
        };
        v.map(|x| x * self.weight)
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
        Quadrature::Far { area_i } => out.push(Term::new(r, area_i, Of::R)),
        Quadrature::Points {
            tri_j,
            excess,
            area_i,
        } => {
            let ys = subsurface::samples(&tri_j, params.samples);
            let c = area_i / (xs.len() * ys.len()) as f32;
            let rho: Vec<f32> = xs
                .iter()
                .flat_map(|x| ys.iter().map(move |y| x.distance(*y) + excess))
                .collect();
            point_bins(&rho, c, out);
        }
        Quadrature::Polar {
            tri,
            normal,
            factor,
        } => {
            let c = factor / (xs.len() as f32 * params.directions as f32);
            let mut events: Vec<(f32, f32)> =
                Vec::with_capacity(2 * xs.len() * params.directions as usize);
            for &x in xs {
                subsurface::polar_intervals(x, &tri, normal, params.directions, |lo, hi| {
                    events.push((lo, c));
                    events.push((hi, -c));
                });
            }
            polar_bins(events, out);
        }
    }
}

/// Geometric bin edges: 0, then `first` to `last` in `bins − 1` equal ratios.
fn edges(first: f32, last: f32, bins: usize) -> Vec<f32> {
    let mut e = vec![0.0f32];
    if last <= first {
        e.push(last.max(first));
        return e;
    }
    let ratio = (last / first) as f64;
    let k = bins - 1;
    for b in 0..=k {
        e.push((first as f64 * ratio.powf(b as f64 / k as f64)) as f32);
    }
    // Exact ends (powf rounding).
    *e.last_mut().expect("two edges at least") = last;
    e
}

/// Polar terms from the rays' (radius, ±weight) ends: the coverage n(ρ) swept in order,
/// its area mass ∫ n 2πρ dρ summed per bin.
fn polar_bins(mut events: Vec<(f32, f32)>, out: &mut Vec<Term>) {
    if events.is_empty() {
        return;
    }
    events.sort_by(|a, b| a.0.total_cmp(&b.0));
    let last = events.last().map_or(0.0, |e| e.0);
    let first = events
        .iter()
        .map(|e| e.0)
        .find(|&r| r > 1e-6 * last)
        .unwrap_or(last);
    let e = edges(first, last, POLAR_BINS);
    let mut mass = vec![0.0f64; e.len() - 1];
    // Area of the ring [a, b] (π dropped on both sides of n̄ = mass / ring).
    let ring = |a: f64, b: f64| b * b - a * a;
    let bins = mass.len();
    let (mut n, mut prev, mut bin) = (0.0f64, 0.0f64, 0usize);
    for &(r, dn) in &events {
        let r = r as f64;
        // n holds on [prev, r]: spread its mass over the bins that interval crosses.
        let mut a = prev;
        while n != 0.0 && a < r {
            while bin + 1 < bins && e[bin + 1] as f64 <= a {
                bin += 1;
            }
            let end = if bin + 1 == bins {
                r
            } else {
                (e[bin + 1] as f64).min(r)
            };
            mass[bin] += n * ring(a, end);
            a = end;
        }
        prev = prev.max(r);
        n += dn as f64;
    }
    // Σ_b n̄_b (W(e_{b+1}) − W(e_b)) regrouped by edge: one W lookup per edge, n̄ being 0
    // past the last edge and W(e_0) = W(0) = 0.
    let mean = |b: usize| {
        let area = ring(e[b] as f64, e[b + 1] as f64);
        if area > 0.0 { mass[b] / area } else { 0.0 }
    };
    for (k, &edge) in e.iter().enumerate().skip(1) {
        let weight = mean(k - 1) - if k < mass.len() { mean(k) } else { 0.0 };
        if weight != 0.0 {
            out.push(Term::new(edge, weight as f32, Of::W));
        }
    }
}

/// Point terms: radii `rho`, each of weight `c`, grouped into geometric bins, each group at
/// its mean radius.
fn point_bins(rho: &[f32], c: f32, out: &mut Vec<Term>) {
    let last = rho.iter().cloned().fold(0.0f32, f32::max);
    let first = rho
        .iter()
        .cloned()
        .filter(|&r| r > 1e-6 * last)
        .fold(f32::INFINITY, f32::min)
        .min(last);
    let e = edges(first, last, POINT_BINS);
    let mut sum = vec![(0.0f64, 0u32); e.len() - 1];
    for &r in rho {
        let b = e[1..].partition_point(|&edge| edge < r).min(sum.len() - 1);
        sum[b].0 += r as f64;
        sum[b].1 += 1;
    }
    for (s, k) in sum {
        if k > 0 {
            let mean = (s / k as f64) as f32;
            out.push(Term::new(mean, c * k as f32, Of::R));
        }
    }
}

/// One translucent object's or thin sheet's entries as terms (local indices), by source
/// column as [`subsurface::assemble`] builds them: the self term first, then the stored
/// pairs within the object's reach.
#[derive(Debug, Default)]
pub struct ObjectTerms {
    /// A thin sheet (entries carry a side; the self term uses the reflectance profile).
    pub sheet: bool,
    /// Column i's entries are `col_ptr[i]..col_ptr[i + 1]`.
    col_ptr: Vec<u32>,
    /// Receiver j (local) of each entry.
    row: Vec<u32>,
    /// The entry's optical distance (0 for the self term).
    dist: Vec<f32>,
    /// Whether the entry crosses to the sheet's other side (transmittance profile).
    opposite: Vec<bool>,
    /// Entry e's terms are `term_ptr[e]..term_ptr[e + 1]`.
    term_ptr: Vec<u32>,
    terms: Vec<Term>,
    /// Source i (the column) of each entry.
    src: Vec<u32>,
    /// The entries by receiver: row j's are `by_row[row_ptr[j]..row_ptr[j + 1]]`, sorted by
    /// source (the order the transpose of the columns gives), so a rebuild writes S's rows
    /// in parallel instead of transposing its columns.
    row_ptr: Vec<u32>,
    by_row: Vec<u32>,
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
        let mut out = ObjectTerms {
            sheet,
            col_ptr: vec![0],
            term_ptr: vec![0],
            ..Default::default()
        };
        for (entries, terms) in columns {
            let base = out.terms.len() as u32;
            for (j, r, opp, range) in entries {
                out.row.push(j);
                out.dist.push(r);
                out.opposite.push(opp);
                out.term_ptr.push(base + range.end as u32);
            }
            out.terms.extend(terms);
            out.col_ptr.push(out.row.len() as u32);
        }
        // The row index: a counting sort of the entries by receiver, sources ascending.
        let entries = out.row.len();
        out.src = Vec::with_capacity(entries);
        for i in 0..n {
            let len = out.col_ptr[i + 1] - out.col_ptr[i];
            out.src.extend(std::iter::repeat_n(i as u32, len as usize));
        }
        out.row_ptr = vec![0u32; n + 1];
        for &j in &out.row {
            out.row_ptr[j as usize + 1] += 1;
        }
        for j in 0..n {
            out.row_ptr[j + 1] += out.row_ptr[j];
        }
        let mut next = out.row_ptr[..n].to_vec();
        out.by_row = vec![0u32; entries];
        for (e, &j) in out.row.iter().enumerate() {
            out.by_row[next[j as usize] as usize] = e as u32;
            next[j as usize] += 1;
        }
        out
    }

    /// S of the object (local indices) under the profiles tabulated by `same` (a
    /// translucent object's profile, or a sheet's reflectance) and `other` (a sheet's
    /// transmittance): the same entries, skips and energy bound as the quadrature's
    /// assembly.
    pub fn assemble(&self, area: &[f32], same: &Tabulated, other: &Tabulated) -> ObjectS {
        let n = self.col_ptr.len() - 1;
        // Every entry's value (None: not kept), in parallel over the entries.
        let vals: Vec<Option<[f32; 3]>> = (0..self.row.len())
            .into_par_iter()
            .map(|e| {
                let tab = if self.opposite[e] { other } else { same };
                // The self term is each column's first entry (`build`).
                let self_term = e == self.col_ptr[self.src[e] as usize] as usize;
                if !self_term && self.dist[e] >= tab.r_max() {
                    return None;
                }
                let mut s = [0.0f32; 3];
                for t in &self.terms[self.term_ptr[e] as usize..self.term_ptr[e + 1] as usize] {
                    let v = t.eval(tab);
                    for c in 0..3 {
                        s[c] += v[c];
                    }
                }
                (self_term || s.iter().any(|&v| v > 0.0)).then_some(s)
            })
            .collect();
        // Each column's energy, in the column's order (as `subsurface::bound_and_transpose`
        // sums it): the divisor of each channel (1 where the column is not scaled).
        let columns: Vec<([f32; 3], f32, f32, bool)> = (0..n)
            .into_par_iter()
            .map(|i| {
                let mut total = [0.0f32; 3];
                let range = self.col_ptr[i] as usize..self.col_ptr[i + 1] as usize;
                for (val, &j) in vals[range.clone()].iter().zip(&self.row[range]) {
                    if let Some(s) = val {
                        let j = j as usize;
                        for c in 0..3 {
                            total[c] += area[j] * s[c] / area[i];
                        }
                    }
                }
                let worst = total.iter().cloned().fold(0.0f32, f32::max);
                let div = if worst > 1.0 {
                    total.map(|t| if t > 1.0 { t } else { 1.0 })
                } else {
                    [1.0; 3]
                };
                (div, worst, total[1], worst > 1.0)
            })
            .collect();
        let mut report = subsurface::EnergyReport::default();
        let mut mean = 0.0f64;
        for &(_, worst, green, scaled) in &columns {
            report.max_column = report.max_column.max(worst);
            mean += green as f64;
            report.scaled_columns += scaled as usize;
        }
        report.mean_column = if n > 0 { (mean / n as f64) as f32 } else { 0.0 };
        // Rows, each from the row index, sources ascending.
        let rows: Vec<Vec<(u32, [f32; 3])>> = (0..n)
            .into_par_iter()
            .map(|j| {
                self.by_row[self.row_ptr[j] as usize..self.row_ptr[j + 1] as usize]
                    .iter()
                    .filter_map(|&e| {
                        let i = self.src[e as usize];
                        let div = columns[i as usize].0;
                        vals[e as usize].map(|s| (i, std::array::from_fn(|c| s[c] / div[c])))
                    })
                    .collect()
            })
            .collect();
        report.nnz = rows.iter().map(|r| r.len() as u64).sum();
        ObjectS {
            rows,
            links: Vec::new(),
            report,
        }
    }

    /// Stored entries (the self terms included).
    pub fn entries(&self) -> usize {
        self.row.len()
    }

    /// Bytes held.
    pub fn bytes(&self) -> u64 {
        (self.col_ptr.len() * 4
            + self.row.len() * 4
            + self.dist.len() * 4
            + self.opposite.len()
            + self.term_ptr.len() * 4
            + self.terms.len() * std::mem::size_of::<Term>()
            + (self.src.len() + self.row_ptr.len() + self.by_row.len()) * 4) as u64
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
        self.objects.iter().flatten().map(|o| o.terms.len()).sum()
    }

    /// Bytes held.
    pub fn bytes(&self) -> u64 {
        self.objects.iter().flatten().map(ObjectTerms::bytes).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::profile::ProfileEval;
    use translux_proto::scene::Profile;

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

    fn rel(a: [f32; 3], b: [f32; 3]) -> f32 {
        (0..3)
            .map(|c| (a[c] - b[c]).abs() / b[c].abs().max(1e-30))
            .fold(0.0, f32::max)
    }

    fn check(plan: Quadrature, r: f32, xs: &[Vec3], tol: f32, what: &str) {
        let params = SubsurfaceParams::default();
        let mut terms = Vec::new();
        reduce(&plan, r, xs, &params, &mut terms);
        assert!(
            terms.len() <= POINT_BINS.max(POLAR_BINS),
            "{what}: {}",
            terms.len()
        );
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
                5e-3,
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
                5e-3,
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
                5e-3,
                &format!("across an edge, side {side}"),
            );
            let far = Quadrature::Far { area_i: area };
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
    fn a_self_term_first_bin_is_exact_for_a_constant_profile_too() {
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
        let w = |r: f32| std::f32::consts::PI * r * r;
        let got: f32 = terms
            .iter()
            .map(|t| {
                assert_eq!(t.of, Of::W);
                t.weight * w(t.root * t.root)
            })
            .sum();
        assert!(
            (got - 0.5).abs() < 0.5 * 0.02,
            "∫ 1 over the triangle = {got}"
        );
    }

    /// The rows a rebuild writes from its row index equal, bit for bit, the transpose of
    /// the columns summed and bounded one by one (`subsurface::bound_and_transpose`), on a
    /// folded sheet (two planes, so polar and point plans both occur) at translucencies where
    /// columns are and are not scaled, with pairs past the table's reach left out.
    #[test]
    fn rows_from_the_row_index_equal_the_transposed_columns() {
        use crate::smatrix::{PatchGeometry, object_patches};
        use translux_proto::csr::CsrBuilder;
        // A 6 × 6 mm sheet folded at x = 3 (a right angle), 1 mm cells, two triangles each.
        let point = |x: f32, y: f32| {
            if x <= 3.0 {
                Vec3::new(x, y, 0.0)
            } else {
                Vec3::new(3.0, y, x - 3.0)
            }
        };
        let mut corners = Vec::new();
        for a in 0..6 {
            for b in 0..6 {
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
                .filter(|&(_, r)| r < 5.0)
                .collect();
            d.push_row(&row).unwrap();
        }
        let d = d.finish();
        let p = object_patches(&g, 0..n);
        let params = SubsurfaceParams::default();
        let t = ObjectTerms::build(p, d.view().unwrap(), false, &|_| false, &params);
        // The bound weighs columns by area: every third patch counted 6 times as large
        // drives its neighbours' columns past 1.
        let area: Vec<f32> = (0..n)
            .map(|i| {
                if i % 3 == 0 {
                    6.0 * g.area[i]
                } else {
                    g.area[i]
                }
            })
            .collect();
        let mut scaled = 0;
        for (scale, reach) in [(0.3, 5.0), (1.0, 3.0), (4.0, 5.0)] {
            let tab = table(scale, reach);
            let got = t.assemble(&area, &tab, &tab);
            // The reference: each column summed, bounded and transposed.
            let columns: Vec<Vec<(u32, [f32; 3])>> = (0..n)
                .map(|i| {
                    let mut col = Vec::new();
                    for e in t.col_ptr[i] as usize..t.col_ptr[i + 1] as usize {
                        let self_term = e == t.col_ptr[i] as usize;
                        if !self_term && t.dist[e] >= tab.r_max() {
                            continue;
                        }
                        let mut v = [0.0f32; 3];
                        for term in &t.terms[t.term_ptr[e] as usize..t.term_ptr[e + 1] as usize] {
                            let x = term.eval(&tab);
                            for c in 0..3 {
                                v[c] += x[c];
                            }
                        }
                        if self_term || v.iter().any(|&x| x > 0.0) {
                            col.push((t.row[e], v));
                        }
                    }
                    col
                })
                .collect();
            let want = subsurface::bound_and_transpose(columns, &area);
            assert_eq!(got.rows, want.rows, "scale {scale}, reach {reach}");
            assert_eq!(got.report.nnz, want.report.nnz);
            assert_eq!(got.report.scaled_columns, want.report.scaled_columns);
            assert_eq!(
                got.report.max_column.to_bits(),
                want.report.max_column.to_bits()
            );
            assert_eq!(
                got.report.mean_column.to_bits(),
                want.report.mean_column.to_bits()
            );
            assert!(
                got.report.nnz > n as u64,
                "pairs were kept at scale {scale}"
            );
            scaled += got.report.scaled_columns;
        }
        assert!(scaled > 0, "no column was scaled: the bound went untested");
    }
}
