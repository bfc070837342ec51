//! Two-sided links: cluster nodes receive as well as send (hierarchical radiosity with
//! clustering on both sides, after Hanrahan et al. 1991 and Smits et al. 1994; see
//! `docs/hierarchy.md`, *Two-sided links*).
//!
//! In: the patches, the occluder, the cluster tree of [`super`] and its parameters. Out: the
//! rows of C for N patches and M nodes ([`compute`]): row N + k holds what node k's patches
//! receive alike, pushed to each of them by `translux_engine::transport`.
//!
//! The cut is a dual-tree traversal from (root, root). For a receiver r (a node or a patch)
//! and a candidate source s:
//! - **culled** when every face of one turns away from every point of the other (by normal
//!   cones and extents along the cone axis, or by a patch's own plane);
//! - **linked** when both are far against their size (max(R_r, R_s) ≤ η d, η the accuracy),
//!   both cones are at most `cone_deg` wide, every face of each faces every point of the
//!   other, and two error bounds hold:
//!   - the kernel Σₖ wₖ F(x → qₖ)/A_qₖ (the one-sided link's, over area-stratified source
//!     patches qₖ) varies across area-stratified receiver points x by at most
//!     [`RECEIVER_VARIATION`] of its mean, or by less than [`RECEIVER_SPREAD`] — every patch
//!     of a node receives the mean, so this bounds how far a patch's share may be off;
//!   - visibility: a node receiver sees its source whole when the shaft between their boxes
//!     ([`super::shaft`]) holds no other patch. Otherwise each receiver point casts a ray to
//!     each source point: when the receiver points see different shares of the source,
//!     the node's patches lie in different shadows and the receiver is split; when they see
//!     the same share, its fraction is kept only when the unoccluded coefficient is at most
//!     [`PARTIAL_VISIBILITY`] (the most light the shadow could misplace). A patch receiver
//!     takes the one-sided rule (rays to every source point, linked when they agree);
//! - otherwise **refined**: the larger of the two is split (the receiver when its kernel
//!   or its shadow varies; a receiver split hands the source down to its children); two patches
//!   take the dense code's pair rule.
//!
//! The admissibility test is symmetric and scale-invariant; where shafts are clear and the
//! kernel is smooth, nodes receive whole (`docs/hierarchy.md` has the links per patch it
//! stores at growing N against the one-sided cut).

use std::f32::consts::{FRAC_PI_2, PI};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicU64, Ordering};

use glam::Vec3;
use translux_engine::raycast::Occluder;

use super::shaft::Shaft;
use super::{Child, ClusterTree, Cut, HierarchyParams, RowBlock, kernel_per_area};
use crate::formfactor::{FormFactorParams, any_in_front, pair};
use crate::patch::Patches;

/// The largest unoccluded coefficient a partly visible link may keep with its visible
/// fraction instead of being refined: 0.05% of a receiver's hemisphere.
pub const PARTIAL_VISIBILITY: f32 = 0.0005;

/// Receiver points a node link averages its kernel over.
const RECEIVER_SAMPLES: usize = 4;

/// The largest spread (max − min over the receiver points, against their mean) of a node
/// link's kernel across its receiver: every patch of the node receives the mean, so this
/// bounds how far a patch's share may be off.
pub const RECEIVER_VARIATION: f32 = 0.05;

/// A spread of the kernel across the receiver below this (a share of the receiver's
/// hemisphere) is accepted whatever its ratio to the mean: it cannot misplace more.
pub const RECEIVER_SPREAD: f32 = 2e-4;

/// One side of a pair: a node or a patch, as the tests see it.
#[derive(Debug, Clone, Copy)]
struct Shape {
    center: Vec3,
    radius: f32,
    box_center: Vec3,
    box_half: Vec3,
    axis: Vec3,
    cone: f32,
    plane_min: f32,
    plane_max: f32,
}

impl Shape {
    /// Least and greatest `a · y` over the shape's points (box and sphere bounds).
    fn extent(&self, a: Vec3) -> (f32, f32) {
        let reach = a.abs().dot(self.box_half).min(self.radius);
        let mid = a.dot(self.box_center);
        (mid - reach, mid + reach)
    }

    /// How far a face normal may lean off the axis, as a length per unit distance: |n − a|
    /// ≤ 2 sin(cone/2) (infinite for a cone of 90° or more).
    fn lean(&self) -> f32 {
        if self.cone < FRAC_PI_2 {
            2.0 * (self.cone * 0.5).sin()
        } else {
            f32::INFINITY
        }
    }
}

/// What the traversal does with a pair.
enum Verdict {
    Cull,
    Link(f32),
    SplitReceiver,
    SplitSource,
}

/// What the samples of an admissible pair say.
enum Coefficient {
    Link(f32),
    /// The kernel varies across the receiver more than [`RECEIVER_VARIATION`].
    ReceiverVaries,
    /// A node receiver's points see different shares of the source: some of its patches
    /// are in a blocker's shadow that others are not.
    ShadowVaries,
    /// Partly visible and carrying too much to keep the visible fraction.
    PartlyVisible,
}

/// One row of C: its links (column, value), sorted by column.
type Row = Vec<(u32, f32)>;

/// The one-sided cut's inputs and tolerances ([`Cut`], reached through `Deref`), with what
/// the traversal adds.
struct Traversal<'a> {
    cut: Cut<'a>,
    radius: Vec<f32>,
    /// Each patch's position in the tree order.
    position: Vec<u32>,
    rays: AtomicU64,
    tests: AtomicU64,
    progress: &'a (dyn Fn(u64) + Sync),
    stop: &'a (dyn Fn() -> bool + Sync),
    /// Each row of C (the N patches, then the M nodes), set by the one visit of its
    /// receiver: the rows are put together once, without the halves of the tree being
    /// joined level by level (which held each link about three times over, 29 bytes a
    /// link while F was built) or a sort of every link.
    rows: Vec<OnceLock<Row>>,
}

/// The two-sided C's rows: the N patch rows then the M node rows, as one block from row 0
/// (its counts as [`super::compute_rows`]'s).
pub fn compute(
    p: &Patches,
    occ: &Occluder,
    ff: &FormFactorParams,
    params: &HierarchyParams,
    tree: &ClusterTree,
    progress: &(dyn Fn(u64) + Sync),
    stop: &(dyn Fn() -> bool + Sync),
) -> RowBlock {
    let radius = (0..p.len())
        .map(|i| {
            let c = p.centroid[i];
            p.corners[i]
                .iter()
                .map(|v| v.distance(c))
                .fold(0.0, f32::max)
        })
        .collect();
    let mut position = vec![0u32; p.len()];
    for (k, &q) in tree.perm.iter().enumerate() {
        position[q as usize] = k as u32;
    }
    let mut t = Traversal {
        cut: Cut::new(p, occ, ff, params, tree),
        position,
        radius,
        rays: AtomicU64::new(0),
        tests: AtomicU64::new(0),
        progress,
        stop,
        rows: (0..p.len() + tree.node_count())
            .map(|_| OnceLock::new())
            .collect(),
    };
    if !p.is_empty() {
        t.visit(tree.root, vec![tree.root]);
    }
    t.block()
}

impl<'a> std::ops::Deref for Traversal<'a> {
    type Target = Cut<'a>;
    fn deref(&self) -> &Cut<'a> {
        &self.cut
    }
}

impl Traversal<'_> {
    /// The links of receiver `r` with the sources `candidates` (what its ancestors handed
    /// down) into its row, and of its descendants with what it hands down in turn.
    fn visit(&self, r: Child, candidates: Vec<Child>) {
        if (self.stop)() {
            return;
        }
        let mut out = Vec::new();
        let mut deferred = Vec::new();
        let mut stack = candidates;
        let mut samples = Vec::new();
        let mut rays = 0u64;
        let mut tests = 0u64;
        while let Some(s) = stack.pop() {
            tests += 1;
            if let (Child::Patch(i), Child::Patch(j)) = (r, s) {
                if let Some(v) = self.patch_pair(i as usize, j as usize, &mut samples, &mut rays) {
                    out.push((j, v));
                }
                continue;
            }
            match self.verdict(r, s, &mut rays) {
                Verdict::Cull => {}
                Verdict::Link(v) => {
                    if v > 0.0 {
                        out.push((self.index(s), v));
                    }
                }
                Verdict::SplitReceiver => deferred.push(s),
                Verdict::SplitSource => match s {
                    Child::Node(k) => {
                        stack.extend_from_slice(&self.tree.nodes[k as usize].children)
                    }
                    Child::Patch(_) => unreachable!("a patch source is never split"),
                },
            }
        }
        self.rays.fetch_add(rays, Ordering::Relaxed);
        self.tests.fetch_add(tests, Ordering::Relaxed);
        out.sort_unstable_by_key(|e| e.0);
        out.shrink_to_fit();
        let first = self.rows[self.index(r) as usize].set(out);
        debug_assert!(first.is_ok(), "every receiver is visited once");
        match r {
            Child::Patch(_) => {
                debug_assert!(deferred.is_empty(), "a patch receiver is never split");
                (self.progress)(1);
            }
            Child::Node(k) => {
                let [a, b] = self.tree.nodes[k as usize].children;
                let copy = deferred.clone();
                rayon::join(|| self.visit(a, copy), || self.visit(b, deferred));
            }
        }
    }

    /// Row or column of a side: a patch's index, or N + its node index.
    fn index(&self, c: Child) -> u32 {
        match c {
            Child::Patch(i) => i,
            Child::Node(k) => self.p.len() as u32 + k,
        }
    }

    /// Two patches: the dense code's culls and pair rule (F_ij of receiver i).
    fn patch_pair(
        &self,
        i: usize,
        j: usize,
        samples: &mut Vec<Vec3>,
        rays: &mut u64,
    ) -> Option<f32> {
        let p = self.p;
        if i == j
            || !any_in_front(&p.corners[j], p.centroid[i], p.normal[i], self.eps_plane)
            || !any_in_front(&p.corners[i], p.centroid[j], p.normal[j], self.eps_plane)
        {
            return None;
        }
        pair(p, self.occ, self.ff, self.offset, i, j, samples, rays).map(|(f, _)| f)
    }

    fn shape(&self, c: Child) -> Shape {
        match c {
            Child::Node(k) => {
                let n = &self.tree.nodes[k as usize];
                Shape {
                    center: n.center,
                    radius: n.radius,
                    box_center: n.box_center,
                    box_half: n.box_half,
                    axis: n.axis,
                    cone: n.cone,
                    plane_min: n.plane_min,
                    plane_max: n.plane_max,
                }
            }
            Child::Patch(i) => {
                let i = i as usize;
                let (p, c) = (self.p, self.p.centroid[i]);
                let (lo, hi) = p.corners[i].iter().fold(
                    (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
                    |(l, h), v| (l.min(*v), h.max(*v)),
                );
                let h = p.normal[i].dot(c);
                Shape {
                    center: c,
                    radius: self.radius[i],
                    box_center: (lo + hi) * 0.5,
                    box_half: (hi - lo) * 0.5,
                    axis: p.normal[i],
                    cone: 0.0,
                    plane_min: h,
                    plane_max: h,
                }
            }
        }
    }

    /// The pair (receiver r, source s), not both patches.
    fn verdict(&self, r: Child, s: Child, rays: &mut u64) -> Verdict {
        if let (Child::Node(a), Child::Node(b)) = (r, s)
            && a == b
        {
            return Verdict::SplitReceiver;
        }
        let (sr, ss) = (self.shape(r), self.shape(s));
        let d = sr.center.distance(ss.center);
        let reach = d + sr.radius + ss.radius;
        let (behind_r, front_r) = self.sides(&sr, &ss, d, reach);
        let (behind_s, front_s) = self.sides(&ss, &sr, d, reach);
        if behind_r || behind_s {
            return Verdict::Cull;
        }
        let near = match r {
            Child::Patch(i) => self.ff.near_factor * self.p.size[i as usize],
            Child::Node(_) => 0.0,
        };
        let admissible = sr.radius.max(ss.radius) <= self.eta * d
            && d >= near
            && sr.cone <= self.half_cone
            && ss.cone <= self.half_cone
            && front_r
            && front_s;
        let mut varies = false;
        if admissible {
            match self.coefficient(r, s, rays) {
                Coefficient::Link(v) => return Verdict::Link(v),
                Coefficient::ReceiverVaries | Coefficient::ShadowVaries => varies = true,
                Coefficient::PartlyVisible => {}
            }
        }
        let split_receiver = match (r, s) {
            (Child::Patch(_), _) => false,
            (_, Child::Patch(_)) => true,
            _ => varies || sr.radius >= ss.radius,
        };
        if split_receiver {
            Verdict::SplitReceiver
        } else {
            Verdict::SplitSource
        }
    }

    /// Whether every point of `b` lies behind (or on) every face of `a`, and whether every
    /// point of `b` lies in front of (or on) every face of `a`: by `a`'s extent along its
    /// cone axis against `b`'s (the face normals lean off the axis by at most
    /// [`Shape::lean`], over distances of at most `reach`), or by the angle from the axis
    /// to `b` (widened by `a`'s cone and by what the two spheres subtend at distance `d`).
    fn sides(&self, a: &Shape, b: &Shape, d: f32, reach: f32) -> (bool, bool) {
        let (lo, hi) = b.extent(a.axis);
        let slack = a.lean() * reach;
        let mut behind = hi - a.plane_min + slack <= self.eps_plane;
        let mut front = lo - a.plane_max - slack >= -self.eps_plane;
        let spread = a.radius + b.radius;
        if a.cone < PI && d > spread {
            let theta = a
                .axis
                .dot((b.center - a.center) / d)
                .clamp(-1.0, 1.0)
                .acos();
            let beta = (spread / d).asin();
            behind |= theta > FRAC_PI_2 + a.cone + beta;
            front |= theta + a.cone + beta < FRAC_PI_2;
        }
        (behind, front)
    }

    /// A side's range of the tree order.
    fn range(&self, c: Child) -> [u32; 2] {
        match c {
            Child::Node(k) => self.tree.nodes[k as usize].range,
            Child::Patch(i) => {
                let q = self.position[i as usize];
                [q, q + 1]
            }
        }
    }

    /// Whether some patch other than r's and s's own crosses the shaft between their boxes
    /// (the cluster tree's boxes prune the search).
    fn shaft_blocked(&self, r: Child, s: Child) -> bool {
        let bounds = |c: Child| {
            let sh = self.shape(c);
            (sh.box_center - sh.box_half, sh.box_center + sh.box_half)
        };
        let shaft = Shaft::between(bounds(r), bounds(s));
        let own = [self.range(r), self.range(s)];
        let inside = |g: [u32; 2]| own.iter().any(|o| o[0] <= g[0] && g[1] <= o[1]);
        let eps = self.eps_plane;
        let mut stack = vec![self.tree.root];
        while let Some(c) = stack.pop() {
            match c {
                Child::Node(k) => {
                    let n = &self.tree.nodes[k as usize];
                    if inside(n.range)
                        || shaft.box_outside(
                            n.box_center - n.box_half,
                            n.box_center + n.box_half,
                            eps,
                        )
                    {
                        continue;
                    }
                    stack.extend_from_slice(&n.children);
                }
                Child::Patch(q) => {
                    if inside(self.range(c)) {
                        continue;
                    }
                    if !shaft.triangle_outside(&self.p.corners[q as usize], eps) {
                        return true;
                    }
                }
            }
        }
        false
    }

    /// Area-stratified patches of a side (up to `m`), with their weights summing to its area.
    fn samples(&self, c: Child, m: usize, out: &mut Vec<(usize, f64)>) {
        match c {
            Child::Patch(i) => {
                out.clear();
                out.push((i as usize, self.p.area[i as usize] as f64));
            }
            Child::Node(k) => {
                let n = &self.tree.nodes[k as usize];
                self.tree.strata(n.range, n.area, m, &self.p.area, out);
            }
        }
    }

    /// The link's coefficient: the receiver points' mean of the source's kernel sum, times
    /// the visible fraction of the sample pairs — unless the kernel or the visible share
    /// varies across the receiver, or a partly visible pair carries too much to keep its
    /// fraction (the caller refines).
    fn coefficient(&self, r: Child, s: Child, rays: &mut u64) -> Coefficient {
        let p = self.p;
        let (mut xs, mut qs) = (Vec::new(), Vec::new());
        self.samples(r, RECEIVER_SAMPLES.min(self.m), &mut xs);
        self.samples(s, self.m, &mut qs);
        let area_r: f64 = xs.iter().map(|x| x.1).sum();
        let (mut kernel, mut lo, mut hi) = (0.0f64, f64::INFINITY, 0.0f64);
        for &(i, wi) in &xs {
            let (x, ni) = (p.centroid[i], p.normal[i]);
            let mut sum = 0.0f64;
            for &(q, wq) in &qs {
                let (y, ny) = (p.centroid[q], p.normal[q]);
                if ny.dot(x - y) <= 0.0 || ni.dot(y - x) <= 0.0 {
                    continue;
                }
                sum += wq * kernel_per_area(p, x, ni, q);
            }
            kernel += wi / area_r * sum;
            lo = lo.min(sum);
            hi = hi.max(sum);
        }
        let kernel = kernel as f32;
        if (hi - lo) as f32 > (RECEIVER_VARIATION * kernel).max(RECEIVER_SPREAD) {
            return Coefficient::ReceiverVaries;
        }
        // Visibility. A node receiver sees its source whole when the shaft between them
        // holds no other surface; otherwise sample rays give the visible fraction, which
        // only a pair carrying little and seen alike from every receiver point may keep (a
        // fraction shared by patches in and out of a shadow would light the shadow). A patch
        // receiver takes the one-sided rule: rays to every source point, kept when they all
        // agree.
        let vs = match r {
            Child::Node(_) if !self.shaft_blocked(r, s) => return Coefficient::Link(kernel),
            Child::Node(_) => &xs,
            Child::Patch(_) => &xs[..1],
        };
        let pairs = vs.len() * qs.len();
        let seen = self.visible_per_point(vs, &qs, rays);
        let all: usize = seen.iter().sum();
        if let Child::Patch(_) = r {
            return match all {
                0 => Coefficient::Link(0.0),
                s if s == pairs => Coefficient::Link(kernel),
                _ => Coefficient::PartlyVisible,
            };
        }
        if seen.iter().any(|&s| s != seen[0]) {
            Coefficient::ShadowVaries
        } else if kernel <= PARTIAL_VISIBILITY {
            Coefficient::Link(kernel * all as f32 / pairs as f32)
        } else {
            Coefficient::PartlyVisible
        }
    }

    /// How many of the source points `qs` each receiver point of `xs` sees (a ray each).
    fn visible_per_point(
        &self,
        xs: &[(usize, f64)],
        qs: &[(usize, f64)],
        rays: &mut u64,
    ) -> Vec<usize> {
        let p = self.p;
        xs.iter()
            .map(|&(i, _)| {
                let from = p.centroid[i] + p.normal[i] * self.offset;
                *rays += qs.len() as u64;
                qs.iter()
                    .filter(|&&(q, _)| {
                        !self
                            .occ
                            .occluded(from, p.centroid[q] + p.normal[q] * self.offset)
                    })
                    .count()
            })
            .collect()
    }

    /// Every row, in order, as one block of N + M rows, with the counts of the cut.
    fn block(&mut self) -> RowBlock {
        let n = self.p.len();
        let rows = std::mem::take(&mut self.rows);
        let links: usize = rows.iter().map(|r| r.get().map_or(0, Vec::len)).sum();
        let mut block = RowBlock {
            first: 0,
            row_ptr: Vec::with_capacity(rows.len() + 1),
            col: Vec::with_capacity(links),
            val: Vec::with_capacity(links),
            rays: self.rays.load(Ordering::Relaxed),
            tests: self.tests.load(Ordering::Relaxed),
            ..Default::default()
        };
        let size = |c: u32| -> u64 {
            let c = c as usize;
            if c < n {
                1
            } else {
                let r = self.tree.nodes[c - n].range;
                u64::from(r[1] - r[0])
            }
        };
        block.row_ptr.push(0);
        for (row, links) in rows.into_iter().enumerate() {
            // Each row is freed as it is copied.
            for (c, v) in links.into_inner().unwrap_or_default() {
                block.col.push(c);
                block.val.push(v);
                if (c as usize) < n {
                    block.patch_entries += 1;
                } else {
                    block.node_entries += 1;
                }
                block.covered += size(row as u32) * size(c);
            }
            block.row_ptr.push(block.col.len() as u64);
        }
        block
    }
}
