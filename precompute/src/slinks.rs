//! Hierarchical S: each receiver of a translucent object gathers from far parts of the
//! object through whole cluster nodes (links), near pairs and the self term keep the
//! pairwise quadrature (issue 20; after Jensen & Buhler 2002's octree and Mertens et al.
//! 2003's hierarchical boundary elements, here on the cluster tree of the hierarchical F).
//!
//! In: the cluster tree ([`ClusterTree`], whose top splits objects apart, so each object is
//! one subtree), the patch geometry, the objects with the radius their distances were
//! stored to, stage 1's pairwise distances, [`SLinkParams`] and each object's link bounds
//! ([`link_bounds`]). Out: [`Collapsed`]: the
//! distances as the bundle stores them for a hierarchical S (`N × (N + M)`, see
//! `translux_proto::bundle::SubsurfaceInfo::links`) and the tree's nodes as S's assembly reads
//! them.
//!
//! The cut for receiver j (centroid x, longest edge s_j), from the object's subtree root
//! down, is made before any optical distance is known, from geometry and the profile's
//! bound over a slider's range (a translucency change never re-cuts):
//! - a node holding j is opened;
//! - a node whose bounding sphere (centre c, radius ρ) lies beyond the stored radius
//!   (|x − c| − ρ greater than it: an optical path is never shorter than the straight line)
//!   is dropped;
//! - a node is linked whole when ρ ≤ θ |x − c| (θ = [`SLinkParams::accuracy`]), the node is
//!   outside the receiver's near field (|x − c| − ρ ≥ `near_factor` × s_j), the profile's
//!   error bound accepts it at every translucency of a slider's range ([`LinkBound`], built
//!   per object by [`link_bounds`]: R varies across [|x − c| − ρ, |x − c| + ρ] by at most τ
//!   of its mean, or the node is too small to matter), and its representative patch (the one nearest its area-weighted
//!   centroid) has a stored optical distance r from j: the link is S_{j,node} = A_node R(r)
//!   applied to the node's area-weighted mean (a node's patches are then at most 2θ/(1 − θ)
//!   of the distance apart from the receiver's point of view); a far node whose
//!   representative has no stored distance (it lies beyond the reach) is dropped, since only
//!   its edge is within reach, where the profile has spent all but its truncation energy;
//! - otherwise its children are visited; a patch i with a stored distance becomes a direct
//!   entry, evaluated as in a pairwise S.
//!
//! The distances come one of two ways ([`Trace`]): from stage 1's pairwise distances (every
//! pair within the stored radius, then the cut), or on demand ([`Oracle`], homogeneous
//! translucent objects): every receiver's cut is made first from geometry alone (a
//! candidate whose straight line already exceeds the reach is left out, an optical path
//! being never shorter), then only the distances it uses are traced — a run from each
//! receiver to its close candidates, one from each distant candidate (a patch a loose node
//! of the tree leaves to many near fields) to the receivers listing it, and one from each
//! linked node's representative to the receivers linking it. Runs stop once their targets
//! are settled. A large or very translucent object (the bowls' bunny in skim milk: every
//! patch within reach of every other) then never lists its O(n²) pairs. The two ways give
//! the same distances bit for bit, except that by default ([`SLinkParams::coarse_links`])
//! every run finds its targets 16 voxels away or more on a grid of twice the voxel edge,
//! an eighth of the voxels to settle ([`Oracle::solve_far`]); the fine grid's run then
//! stops at the farthest of the nearer ones.
//!
//! Thin sheets are cut the same way along their geodesics, a node being linked only when its
//! normal cone is at most 45° wide (so it holds one side) and the link taking its
//! representative's kind (same side or other side). Heterogeneous objects keep their
//! pairwise distances (each carries its own per-medium lengths).

use std::ops::{Range, RangeInclusive};

use glam::Vec3;
use rayon::prelude::*;
use translux_engine::hetero::{MEDIA, MediaLen};
use translux_engine::linkbound::{LinkBound, LinkTolerance};
use translux_engine::sheet::KIND_SAME;
use translux_engine::smatrix::{ObjectMaterial, PatchGeometry, SError};
use translux_engine::subsurface::Nodes;
use translux_proto::bundle::TreeView;
use translux_proto::csr::Csr;
use translux_proto::scene::Material;

use crate::hierarchy::{Child, ClusterTree};
use crate::voxel::Oracle;

/// Widest normal cone (half-angle, radians: 45°) of a node a thin sheet's receiver may link:
/// the sheet's two sides face apart, so such a node holds one side.
const SHEET_CONE: f32 = std::f32::consts::FRAC_PI_4;

/// Entries (direct pairs and links) per patch a hierarchical S at the default accuracy
/// stays under, for the memory estimate made before any of it runs: measured 450 on the
/// bowls' bunny at 14k patches and 900 on the whole scan at 69k (skim milk, whose profile
/// reaches across the whole object); links grow about as log n.
pub const ENTRIES_BOUND: u64 = 2_000;

/// The accuracies a precompute accepts ([`SLinkParams::check`]).
pub const ACCURACY_RANGE: RangeInclusive<f32> = 0.05..=1.0;

/// Parameters of [`collapse`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SLinkParams {
    /// θ: a node of bounding radius ρ is linked whole to a receiver only from a distance of
    /// at least ρ/θ. Smaller is more accurate and stores more. Default 0.5; accepted 0.05
    /// to 1.
    pub accuracy: f32,
    /// How a homogeneous translucent object's optical distances are traced: [`Trace::Auto`]
    /// in every precompute; the other ways are for the tests that hold the on-demand cut
    /// to the pairwise one (`precompute/tests/it/slinks.rs`), and no flag sets them.
    pub trace: Trace,
    /// Traced on demand only: every run (from a receiver to its direct candidates, from a
    /// distant candidate, from a linked node's representative) finds its targets at least
    /// [`crate::voxel::FAR_RUN_VOXELS`] coarse voxels away (16 voxels) on a grid of twice
    /// the voxel edge ([`Oracle::solve_far`]), settling about an eighth of the voxels;
    /// those distances then differ slightly from [`Trace::All`]'s (on the scanned bunny in
    /// skim milk, the U, the cube and a thin bowl, S stays as close to the pairwise S:
    /// `precompute/tests/it/slinks.rs`). True in every precompute; `false` (the tests'
    /// exact links, no flag) keeps the bundle equal to `Trace::All`'s bit for bit.
    pub coarse_links: bool,
    /// The near field of links, in receiver sizes (`--s-link-near`), in
    /// [`LINK_NEAR_RANGE`]: nodes are linked from this many sizes on and each link is read
    /// at two distances ([`link_spread`]); the default, [`DEFAULT_LINK_NEAR`] (1 size),
    /// stores a fifth to two fifths of the direct pairs of the quadrature's near-pair rule
    /// (3 sizes) on the test objects, so a translucency change writes fewer entries.
    pub near: f32,
    /// The profile's side of each link's error bound (`--s-link-variation`): a node is
    /// linked only where [`LinkBound::accepts`] it at every scale of a slider's range.
    pub tolerance: LinkTolerance,
}

/// The near fields of links `--s-link-near` accepts, in receiver sizes.
pub const LINK_NEAR_RANGE: RangeInclusive<f32> = 1.0..=3.0;

/// The default near field of links, in receiver sizes: with links read at two distances and
/// scaled with their columns by the energy bound, every test object stays within issue
/// #20's bounds against the pairwise S (median 1%, p90 3%; `precompute/tests/it/slinks.rs`),
/// with fewer direct pairs than at 1.5 sizes (which come closer to the pairwise S;
/// bench/results/HISTORY.md, *Links from one receiver size by default*).
pub const DEFAULT_LINK_NEAR: f32 = 1.0;

impl Default for SLinkParams {
    fn default() -> Self {
        Self {
            accuracy: 0.5,
            trace: Trace::Auto,
            coarse_links: true,
            near: DEFAULT_LINK_NEAR,
            tolerance: LinkTolerance::default(),
        }
    }
}

/// How the optical distances of a homogeneous translucent object are traced for a
/// hierarchical S. Both give the same distances, bit for bit, hence the same bundle, unless
/// [`SLinkParams::coarse_links`] sends the far runs of the on-demand way to a coarser grid.
/// Precomputes use [`Trace::Auto`]; [`Trace::OnDemand`] and [`Trace::All`] are for the tests
/// that hold the two ways equal (`precompute/tests/it/slinks.rs`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Trace {
    /// With [`SLinkParams::coarse_links`] (the default), on demand: its far runs on the
    /// coarse grid made it the faster way on every object measured (the 60 mm U in marble
    /// 39 s against 50 s, the bowls 29 s against 31 s with their bunny). With exact links,
    /// or in an animation (where an object that only moved rigidly reuses the distances
    /// traced pair by pair for an earlier frame), on demand where the cut keeps under a
    /// quarter of the pairs within the radius (a large or very translucent object: a
    /// receiver's near patches lie a few patch sizes away, far inside the profile's reach)
    /// or the pairs exceed [`ENTRIES_BOUND`] per patch (what the memory estimate counted),
    /// every pair otherwise (an object about as small as the reach, where the near runs
    /// would go about as far as the full ones and the exact node runs would come on top:
    /// the U 67 s against 52 s).
    #[default]
    Auto,
    /// Only the distances the cut uses ([`crate::voxel::Oracle`]).
    OnDemand,
    /// Every pair within the radius first, then the cut from those (as a pairwise S
    /// stores them).
    All,
}

/// Per object: whether its distances are traced on demand (`Trace` of `params`; for
/// [`Trace::Auto`] with exact links, or in an animation whose frames reuse the distances of
/// rigidly moved objects (`reuse`: only distances traced pair by pair are kept for the next
/// frame), the cut's entries, counted on up to 256 evenly spaced receivers, against
/// `pairs[k]`, the estimate of what tracing every pair stores). `reach[k]` is how far the
/// object's distances are kept (`None`: it has none).
#[expect(
    clippy::too_many_arguments,
    reason = "the pipeline's arrays as it holds them"
)]
pub fn trace_on_demand(
    tree: &ClusterTree,
    g: &PatchGeometry,
    objects: &[ObjectMaterial<'_>],
    reach: &[Option<f32>],
    pairs: &[u64],
    params: &SLinkParams,
    bounds: &[Vec<LinkBound>],
    reuse: bool,
) -> Vec<bool> {
    if params.trace == Trace::All {
        return vec![false; objects.len()];
    }
    let roots = cut_roots(tree, objects);
    let ranges = tree.ranges();
    let pos = positions(tree);
    let rep = representatives(tree, g);
    let cutter = Cutter::new(tree, &ranges, &pos, g, params);
    objects
        .iter()
        .enumerate()
        .map(|(k, o)| {
            let (Some((root, false)), Some(Some(reach))) = (roots[k], reach.get(k)) else {
                return false;
            };
            if params.trace == Trace::OnDemand || (params.coarse_links && !reuse) {
                return true;
            }
            let r = o.patches.clone();
            let rows = r.len().min(256);
            let kept: u64 = (0..rows)
                .into_par_iter()
                .map(|s| {
                    let j = r.start + s * r.len() / rows;
                    let (mut near, mut far) = (Vec::new(), Vec::new());
                    cutter.cut(j, root, *reach, false, &bounds[k], &mut near, &mut far);
                    let x = g.centroid[j];
                    let close = |p: u32| x.distance(g.centroid[p as usize]) <= *reach;
                    (near.into_iter().filter(|&i| close(i)).count()
                        + far.into_iter().filter(|&q| close(rep[q as usize])).count())
                        as u64
                })
                .sum();
            let kept = kept as f64 / rows as f64 * r.len() as f64;
            // Also on demand whenever every pair would outgrow what the memory estimate
            // made before F counted for it (ENTRIES_BOUND per patch).
            let pairs = pairs.get(k).copied().unwrap_or(0);
            4.0 * kept < pairs as f64 || pairs > r.len() as u64 * ENTRIES_BOUND
        })
        .collect()
}

impl SLinkParams {
    /// Refuses values outside the documented range, naming the option.
    pub fn check(&self) -> Result<(), String> {
        if !(self.accuracy.is_finite() && ACCURACY_RANGE.contains(&self.accuracy)) {
            return Err(format!(
                "--s-accuracy must be in [{}, {}] (the largest node radius over distance a \
                 subsurface link may have), got {}",
                ACCURACY_RANGE.start(),
                ACCURACY_RANGE.end(),
                self.accuracy
            ));
        }
        let k = self.near;
        if !(k.is_finite() && LINK_NEAR_RANGE.contains(&k)) {
            return Err(format!(
                "--s-link-near must be in [{}, {}] (how many receiver sizes away a subsurface \
                 link may start), got {k}",
                LINK_NEAR_RANGE.start(),
                LINK_NEAR_RANGE.end(),
            ));
        }
        let v = self.tolerance.variation;
        if !(v.is_finite() && VARIATION_RANGE.contains(&v)) {
            return Err(format!(
                "--s-link-variation must be in [{}, {}] (the largest relative variation of the \
                 profile across a subsurface link's node), got {v}",
                VARIATION_RANGE.start(),
                VARIATION_RANGE.end(),
            ));
        }
        Ok(())
    }
}

/// The profile variations across a link `--s-link-variation` accepts (2 is no bound: the
/// relative variation (a − b)/((a + b)/2) of two positive values is below 2).
pub const VARIATION_RANGE: RangeInclusive<f32> = 0.01..=2.0;

/// Per object: the profile's side of its links' error bound ([`LinkBound`]), for the
/// homogeneous translucent objects a hierarchical S cuts (and thin sheets: both their
/// profiles), out to `reach[k]` from a quarter of the object's smallest patch. `None` for
/// other objects, or where a profile cannot be read (the stage that evaluates S reports it).
pub fn link_bounds(
    g: &PatchGeometry,
    objects: &[ObjectMaterial<'_>],
    reach: &[Option<f32>],
    unit_mm: f64,
    tolerance: LinkTolerance,
) -> Vec<Vec<LinkBound>> {
    objects
        .iter()
        .enumerate()
        .map(|(k, o)| {
            let Some(Some(reach)) = reach.get(k) else {
                return Vec::new();
            };
            let smallest = g.size[o.patches.clone()]
                .iter()
                .copied()
                .fold(f32::INFINITY, f32::min);
            translux_engine::linkbound::bounds_of(o.material, unit_mm, smallest, *reach, tolerance)
        })
        .collect()
}

/// A link's distance and spread, read at two distances ([`SLinkParams::near`]):
/// receiver j (centroid x) gathers from node q (its patches, `members`, of centroids p and
/// areas a), whose representative (centroid c) lies at optical distance `d`. The node's
/// patches lie at straight distances |x − p| of area-weighted mean m and spread σ; the link
/// is read at r ± σ with r = d + m − |x − c| (the representative's optical distance moved
/// by the straight mean's offset from it), i.e. A_q (R(r − σ) + R(r + σ)) / 2: one point
/// misses the profile's curvature across the node (R is convex, so the mean of R over a
/// node lies above R at its middle), which is why links read at one point must stay 3
/// receiver sizes away. Measured against the pairwise S in `docs/hierarchy.md`.
pub fn link_spread(g: &PatchGeometry, x: Vec3, members: &[u32], rep: u32, d: f32) -> (f32, f32) {
    let (mut a, mut s1, mut s2) = (0.0f64, 0.0f64, 0.0f64);
    for &p in members {
        let w = f64::from(g.area[p as usize]);
        let l = f64::from(x.distance(g.centroid[p as usize]));
        a += w;
        s1 += w * l;
        s2 += w * l * l;
    }
    if a <= 0.0 || a.is_nan() {
        return (d, 0.0);
    }
    let m = s1 / a;
    let sigma = (s2 / a - m * m).max(0.0).sqrt();
    let r = f64::from(d) + m - f64::from(x.distance(g.centroid[rep as usize]));
    (r.max(0.0) as f32, sigma as f32)
}

/// What [`collapse`] made: the distances, their per-medium lengths and kinds (aligned with
/// the entries), the nodes, and the links stored.
#[derive(Debug)]
pub struct Collapsed {
    pub dist: Csr<f32>,
    pub material_len: Vec<MediaLen>,
    pub kind: Vec<u32>,
    pub nodes: Nodes,
    pub links: u64,
    /// Each stored distance's spread (aligned with the entries; 0 for direct pairs,
    /// [`link_spread`] for links). Empty when no link was made.
    pub spread: Vec<f32>,
    /// Seconds each object's cut took (0 for objects not cut), tracing included.
    pub seconds: Vec<f64>,
    /// Linked nodes whose distances were traced on demand (one run each from the
    /// representative), and how many of those ran on the coarse grid
    /// ([`SLinkParams::coarse_links`]).
    pub node_runs: (u64, u64),
}

/// Per node: the representative patch (nearest the area-weighted centroid).
fn representatives(tree: &ClusterTree, g: &PatchGeometry) -> Vec<u32> {
    let ranges = tree.ranges();
    ranges
        .par_iter()
        .map(|r| {
            let members = &tree.perm[r[0] as usize..r[1] as usize];
            let (mut c, mut a) = (Vec3::ZERO, 0.0f32);
            for &p in members {
                let p = p as usize;
                c += g.centroid[p] * g.area[p];
                a += g.area[p];
            }
            let c = if a > 0.0 { c / a } else { c };
            members
                .iter()
                .copied()
                .min_by(|&x, &y| {
                    g.centroid[x as usize]
                        .distance_squared(c)
                        .total_cmp(&g.centroid[y as usize].distance_squared(c))
                })
                .unwrap_or(0)
        })
        .collect()
}

/// Each patch's position in the tree's order.
fn positions(tree: &ClusterTree) -> Vec<u32> {
    let mut pos = vec![0u32; tree.perm.len()];
    for (k, &p) in tree.perm.iter().enumerate() {
        pos[p as usize] = k as u32;
    }
    pos
}

/// Per object: the root of its subtree and whether it is a thin sheet, for the objects a
/// hierarchical S cuts (homogeneous translucent objects and thin sheets of two patches or
/// more whose patches form one subtree; objects are split apart at the top of the tree, so
/// one without stays pairwise).
pub fn cut_roots(tree: &ClusterTree, objects: &[ObjectMaterial<'_>]) -> Vec<Option<(Child, bool)>> {
    let pos = positions(tree);
    objects
        .iter()
        .map(|o| {
            let r = o.patches.clone();
            let sheet = match o.material {
                Material::Translucent { .. } => false,
                Material::ThinSheet { .. } => true,
                _ => return None,
            };
            if r.len() < 2 {
                return None;
            }
            let lo = r.clone().map(|p| pos[p]).min().unwrap_or(0);
            let root = tree.subtree([lo, lo + r.len() as u32])?;
            Some((root, sheet))
        })
        .collect()
}

/// The geometric part of a receiver's cut (the module docs), shared by both ways of
/// finding the distances: it names the patches the receiver may take directly and the
/// nodes it may link, before any optical distance is known.
struct Cutter<'a> {
    tree: &'a ClusterTree,
    ranges: &'a [[u32; 2]],
    /// Position of each patch in the tree's order.
    pos: &'a [u32],
    g: &'a PatchGeometry,
    theta: f32,
    near_factor: f32,
    coarse_links: bool,
    /// Each node's area (the bound's floor weighs a link by it).
    node_area: Vec<f32>,
}

impl<'a> Cutter<'a> {
    fn new(
        tree: &'a ClusterTree,
        ranges: &'a [[u32; 2]],
        pos: &'a [u32],
        g: &'a PatchGeometry,
        params: &SLinkParams,
    ) -> Self {
        let node_area = translux_engine::transport::node_areas(
            TreeView {
                perm: &tree.perm,
                range: ranges,
            },
            &g.area,
        );
        Cutter {
            tree,
            ranges,
            pos,
            g,
            theta: params.accuracy,
            near_factor: params.near,
            coarse_links: params.coarse_links,
            node_area,
        }
    }

    /// The distances of runs (source, targets): the targets 16 voxels away or more on the
    /// coarse grid with [`SLinkParams::coarse_links`], every one on the full grid
    /// otherwise; and how many jobs had a coarse run. A receiver's run to its direct
    /// candidates goes about 25 voxels on the bowls' bunny; its fine part then stops at 16
    /// and the rest costs an eighth: `bench/results/HISTORY.md`.
    fn runs(&self, oracle: &Oracle, jobs: &[(u32, Vec<u32>)]) -> (Vec<Vec<f32>>, usize) {
        if self.coarse_links {
            oracle.solve_far(jobs)
        } else {
            (oracle.solve(jobs), 0)
        }
    }

    /// Receiver j's cut below `root`: patches (other than j) into `direct`, far nodes into
    /// `far`; nodes wholly beyond `reach` are dropped. A node is linked only where every
    /// profile of `bounds` accepts it ([`LinkBound::accepts`]).
    #[expect(
        clippy::too_many_arguments,
        reason = "one receiver's cut: the object's root, reach, kind and bounds"
    )]
    fn cut(
        &self,
        j: usize,
        root: Child,
        reach: f32,
        sheet: bool,
        bounds: &[LinkBound],
        direct: &mut Vec<u32>,
        far: &mut Vec<u32>,
    ) {
        let x = self.g.centroid[j];
        let mut stack = vec![root];
        while let Some(c) = stack.pop() {
            match c {
                Child::Patch(i) => {
                    if i as usize != j {
                        direct.push(i);
                    }
                }
                Child::Node(q) => {
                    let q = q as usize;
                    let range = self.ranges[q];
                    if (range[0]..range[1]).contains(&self.pos[j]) {
                        stack.extend_from_slice(&self.tree.children(q));
                        continue;
                    }
                    let (centre, rho) = self.tree.sphere(q);
                    let de = x.distance(centre);
                    if de - rho > reach {
                        continue;
                    }
                    // On a sheet a link stands for one side only (normals within SHEET_CONE
                    // of their mean), of its representative's kind.
                    let is_far = rho <= self.theta * de
                        && de - rho >= self.near_factor * self.g.size[j]
                        && (!sheet || self.tree.cone(q) <= SHEET_CONE)
                        && bounds.iter().all(|b| b.accepts(de, rho, self.node_area[q]));
                    if is_far {
                        far.push(q as u32);
                    } else {
                        stack.extend_from_slice(&self.tree.children(q));
                    }
                }
            }
        }
    }
}

/// Per receiver j (local): its direct sources and its links, each (patch or node, optical
/// distance, kind).
type Cut = (Vec<(u32, f32, u32)>, Vec<(u32, f32, u32)>);

/// A receiver's cut as S stores it: direct sources (patch, distance, kind) and links
/// (node, distance moved to the node's straight mean, kind, spread; [`link_spread`]).
type SpreadCut = (Vec<(u32, f32, u32)>, Vec<(u32, f32, u32, f32)>);

/// The cuts of a run of the receivers that a hierarchical S traces on demand (a shard's
/// share, or all the shards' put together): the receivers of every object cut on demand,
/// in object order ([`on_demand_receivers`]), numbered from 0, and each one's entries —
/// its direct sources first, then its links — as `[patch or node, distance bits, kind,
/// spread bits]` (spread 0 for a direct source).
#[derive(Debug, Clone, PartialEq)]
pub struct ReceiverCuts {
    /// The first receiver's number among all of them.
    pub first: u64,
    /// Per receiver, where its entries begin (one more at the end).
    pub ptr: Vec<u64>,
    /// Per receiver, how many of its entries are direct sources.
    pub direct: Vec<u32>,
    pub entries: Vec<[u32; 4]>,
    /// [`Collapsed::node_runs`] of these receivers' cuts.
    pub node_runs: (u64, u64),
}

impl Default for ReceiverCuts {
    fn default() -> Self {
        ReceiverCuts {
            first: 0,
            ptr: vec![0],
            direct: Vec::new(),
            entries: Vec::new(),
            node_runs: (0, 0),
        }
    }
}

impl ReceiverCuts {
    /// How many receivers these cuts hold.
    pub fn receivers(&self) -> usize {
        self.direct.len()
    }

    /// Whether the offsets and counts agree with the entries.
    pub fn is_consistent(&self) -> bool {
        self.ptr.len() == self.direct.len() + 1
            && self.ptr.first() == Some(&0)
            && self.ptr.last() == Some(&(self.entries.len() as u64))
            && self
                .ptr
                .windows(2)
                .zip(&self.direct)
                .all(|(w, &d)| w[0] <= w[1] && u64::from(d) <= w[1] - w[0])
    }

    fn push(&mut self, (direct, links): SpreadCut) {
        self.direct.push(direct.len() as u32);
        self.entries.extend(
            direct
                .into_iter()
                .map(|(i, d, kd)| [i, d.to_bits(), kd, 0])
                .chain(
                    links
                        .into_iter()
                        .map(|(q, d, kd, s)| [q, d.to_bits(), kd, s.to_bits()]),
                ),
        );
        self.ptr.push(self.entries.len() as u64);
    }

    /// The next share after these, appended (the shards' parts in order).
    pub fn append(&mut self, other: ReceiverCuts) {
        let base = self.entries.len() as u64;
        self.ptr.extend(other.ptr.iter().skip(1).map(|p| p + base));
        self.direct.extend(other.direct);
        self.entries.extend(other.entries);
        self.node_runs.0 += other.node_runs.0;
        self.node_runs.1 += other.node_runs.1;
    }

    /// The cuts of receivers `range` (numbered from this run's first), or `None` when
    /// these cuts do not hold them all or name a patch or node beyond `(patches, nodes)`.
    fn slice(
        &self,
        range: Range<usize>,
        (patches, nodes): (usize, usize),
    ) -> Option<Vec<SpreadCut>> {
        if range.end > self.receivers() || !self.is_consistent() {
            return None;
        }
        let in_range = range.clone().all(|j| {
            let (a, b) = (self.ptr[j] as usize, self.ptr[j + 1] as usize);
            let split = a + self.direct[j] as usize;
            self.entries[a..split]
                .iter()
                .all(|e| (e[0] as usize) < patches)
                && self.entries[split..b]
                    .iter()
                    .all(|e| (e[0] as usize) < nodes)
        });
        if !in_range {
            return None;
        }
        let f = |e: &[u32; 4]| f32::from_bits(e[1]);
        Some(
            range
                .map(|j| {
                    let (a, b) = (self.ptr[j] as usize, self.ptr[j + 1] as usize);
                    let split = a + self.direct[j] as usize;
                    let direct = self.entries[a..split]
                        .iter()
                        .map(|e| (e[0], f(e), e[2]))
                        .collect();
                    let links = self.entries[split..b]
                        .iter()
                        .map(|e| (e[0], f(e), e[2], f32::from_bits(e[3])))
                        .collect();
                    (direct, links)
                })
                .collect(),
        )
    }
}

/// The objects whose receivers' cuts a shard computes: those cut (a subtree of their own)
/// with distances traced on demand (an [`Oracle`]), not thin sheets; each with its patches.
/// Their receivers, one after the other, are what [`shard_cuts`] splits.
pub fn on_demand_receivers(
    tree: &ClusterTree,
    objects: &[ObjectMaterial<'_>],
    on_demand: &[Option<Oracle>],
) -> Vec<(usize, Range<usize>)> {
    cut_roots(tree, objects)
        .into_iter()
        .enumerate()
        .filter(|&(k, c)| {
            matches!(c, Some((_, false))) && on_demand.get(k).is_some_and(Option::is_some)
        })
        .map(|(k, _)| (k, objects[k].patches.clone()))
        .collect()
}

/// The cuts of receivers `share` (numbered as [`on_demand_receivers`] lists them) with
/// their links' distances and spreads: what [`collapse`] makes for them, by the same code,
/// so that the shards' cuts put together are the bytes of a one-box cut.
#[expect(
    clippy::too_many_arguments,
    reason = "collapse's inputs for the objects cut on demand"
)]
pub fn shard_cuts(
    tree: &ClusterTree,
    g: &PatchGeometry,
    objects: &[ObjectMaterial<'_>],
    stored: &[f32],
    on_demand: &[Option<Oracle>],
    params: &SLinkParams,
    bounds: &[Vec<LinkBound>],
    share: Range<usize>,
) -> ReceiverCuts {
    let ranges = tree.ranges();
    let pos = positions(tree);
    let rep = representatives(tree, g);
    let cutter = Cutter::new(tree, &ranges, &pos, g, params);
    let roots = cut_roots(tree, objects);
    let mut out = ReceiverCuts {
        first: share.start as u64,
        ..Default::default()
    };
    let mut at = 0usize;
    for (k, r) in on_demand_receivers(tree, objects, on_demand) {
        let (from, to) = (at, at + r.len());
        at = to;
        let (lo, hi) = (share.start.max(from), share.end.min(to));
        let (Some((root, _)), Some(oracle)) = (roots[k], on_demand[k].as_ref()) else {
            continue;
        };
        if lo >= hi {
            continue;
        }
        let js = r.start + (lo - from)..r.start + (hi - from);
        let reach = stored.get(k).copied().unwrap_or(0.0);
        let cuts = cut_on_demand(
            &cutter,
            &rep,
            (r.clone(), js.clone()),
            root,
            reach,
            &bounds[k],
            oracle,
            &mut out.node_runs,
        );
        for c in with_spreads(g, tree, &ranges, &rep, js.start, cuts) {
            out.push(c);
        }
    }
    out
}

/// Receivers `first..`'s cuts with each link's distance moved and its spread, read at two
/// distances ([`link_spread`]).
fn with_spreads(
    g: &PatchGeometry,
    tree: &ClusterTree,
    ranges: &[[u32; 2]],
    rep: &[u32],
    first: usize,
    cuts: Vec<Cut>,
) -> Vec<SpreadCut> {
    let spreads: Vec<Vec<(f32, f32)>> = cuts
        .par_iter()
        .enumerate()
        .map(|(jl, (_, links))| {
            let x = g.centroid[first + jl];
            links
                .iter()
                .map(|&(q, d, _)| {
                    let [a, b] = ranges[q as usize];
                    let members = &tree.perm[a as usize..b as usize];
                    link_spread(g, x, members, rep[q as usize], d)
                })
                .collect()
        })
        .collect();
    cuts.into_iter()
        .zip(spreads)
        .map(|((direct, links), moved)| {
            let links = links
                .into_iter()
                .zip(moved)
                .map(|((q, _, kd), (d, sigma))| (q, d, kd, sigma))
                .collect();
            (direct, links)
        })
        .collect()
}

/// Replaces the pairwise distances of every homogeneous translucent object and thin sheet
/// (of two patches or more) by direct pairs and links (the module docs); other rows are
/// copied. `stored[k]` is how far object k's distances reach. An object with an [`Oracle`] in `on_demand` has no pairwise rows in
/// `dist`: its cut is made first and only the distances it uses are traced — or, with
/// `precut`, taken from the shards ([`shard_cuts`]; the receivers of every such object, in
/// object order).
#[expect(
    clippy::too_many_arguments,
    reason = "stage 1's arrays as the pipeline holds them"
)]
pub fn collapse(
    tree: &ClusterTree,
    g: &PatchGeometry,
    objects: &[ObjectMaterial<'_>],
    stored: &[f32],
    dist: &Csr<f32>,
    material_len: &[MediaLen],
    kind: &[u32],
    on_demand: &[Option<Oracle>],
    params: &SLinkParams,
    bounds: &[Vec<LinkBound>],
    precut: Option<&ReceiverCuts>,
) -> Result<Collapsed, SError> {
    let n = g.corners.len();
    let ranges = tree.ranges();
    let m = ranges.len();
    let view = TreeView {
        perm: &tree.perm,
        range: &ranges,
    };
    let nodes = Nodes {
        perm: tree.perm.clone(),
        range: ranges.clone(),
        area: translux_engine::transport::node_areas(view, &g.area),
    };
    let pos = positions(tree);
    let rep = representatives(tree, g);
    let cutter = Cutter::new(tree, &ranges, &pos, g, params);

    let cut: Vec<(usize, Child, bool)> = cut_roots(tree, objects)
        .into_iter()
        .enumerate()
        .filter_map(|(k, c)| c.map(|(root, sheet)| (k, root, sheet)))
        .collect();
    let mut is_cut = vec![false; n];
    for &(k, _, _) in &cut {
        for p in objects[k].patches.clone() {
            is_cut[p] = true;
        }
    }
    // Rows as they will be stored: (column, distance, per-medium lengths, kind). The cut
    // objects' rows start empty (their entries are all within the object): copying them
    // first cost 32 bytes per stored pair, 5 GiB on the bowls.
    type Row = Vec<(u32, f32, MediaLen, u32, f32)>;
    let mut rows: Vec<Row> = (0..n)
        .into_par_iter()
        .map(|i| {
            if is_cut[i] {
                return Vec::new();
            }
            let (a, b) = (dist.row_ptr[i] as usize, dist.row_ptr[i + 1] as usize);
            (a..b)
                .map(|e| {
                    (
                        dist.col[e],
                        dist.val[e],
                        material_len.get(e).copied().unwrap_or([0.0; MEDIA]),
                        kind.get(e).copied().unwrap_or(KIND_SAME),
                        0.0,
                    )
                })
                .collect()
        })
        .collect();
    let mut links_total = 0u64;
    let mut node_runs = (0u64, 0u64);
    let mut seconds = vec![0.0f64; objects.len()];
    // Where each object cut on demand begins among the shards' receivers.
    let mut shared_at = 0usize;
    for &(k, root, sheet) in &cut {
        let t = std::time::Instant::now();
        let r = objects[k].patches.clone();
        let reach = stored.get(k).copied().unwrap_or(0.0);
        let cuts = match (on_demand.get(k).and_then(Option::as_ref), precut) {
            (Some(_), Some(pc)) if !sheet => {
                let from = shared_at;
                shared_at += r.len();
                pc.slice(from..shared_at, (n, m))
                    .ok_or_else(|| SError::Media {
                        object: objects[k].name.to_string(),
                        why: "the shards' cuts do not cover its receivers".into(),
                    })?
            }
            (Some(oracle), None) if !sheet => {
                let c = cut_on_demand(
                    &cutter,
                    &rep,
                    (r.clone(), r.clone()),
                    root,
                    reach,
                    &bounds[k],
                    oracle,
                    &mut node_runs,
                );
                with_spreads(g, tree, &ranges, &rep, r.start, c)
            }
            _ => {
                let c = cut_pairwise(
                    &cutter,
                    &rep,
                    r.clone(),
                    root,
                    (reach, sheet),
                    &bounds[k],
                    dist,
                    kind,
                );
                with_spreads(g, tree, &ranges, &rep, r.start, c)
            }
        };
        // Direct pairs are stored by source (row i lists its receivers j); receivers come
        // in increasing order, so every row stays sorted.
        for (jl, (direct, _)) in cuts.iter().enumerate() {
            let j = (r.start + jl) as u32;
            for &(i, d, kd) in direct {
                rows[i as usize].push((j, d, [0.0; MEDIA], kd, 0.0));
            }
        }
        for (jl, (_, links)) in cuts.into_iter().enumerate() {
            links_total += links.len() as u64;
            rows[r.start + jl].extend(
                links
                    .into_iter()
                    .map(|(q, d, kd, sigma)| (n as u32 + q, d, [0.0; MEDIA], kd, sigma)),
            );
        }
        seconds[k] = t.elapsed().as_secs_f64();
    }
    if let Some(pc) = precut {
        node_runs = pc.node_runs;
    }
    let linked = links_total > 0;
    let mut material_len = Vec::new();
    let mut kinds = Vec::new();
    // Spreads are kept only when there are links (a vector as long as the distances: 250 MB
    // on the whole bunny).
    let mut spread = Vec::new();
    let plain: Vec<Vec<(u32, f32)>> = rows
        .into_iter()
        .map(|row| {
            row.into_iter()
                .map(|(c, d, l, kd, sigma)| {
                    material_len.push(l);
                    kinds.push(kd);
                    if linked {
                        spread.push(sigma);
                    }
                    (c, d)
                })
                .collect()
        })
        .collect();
    let dist = Csr::from_rows(if linked { n + m } else { n }, plain).map_err(SError::Matrix)?;
    Ok(Collapsed {
        dist,
        material_len,
        kind: kinds,
        nodes,
        links: links_total,
        spread,
        seconds,
        node_runs,
    })
}

/// The cut of one object from its stored pairwise distances (thin sheets, and the reference
/// a test compares the on-demand cut with): what reaches each receiver j is the stored
/// entries (source i, receiver j) turned around, as stored (a sheet's entry i → j need not
/// equal j → i).
#[expect(
    clippy::too_many_arguments,
    reason = "one object's share of collapse's inputs"
)]
fn cut_pairwise(
    cutter: &Cutter<'_>,
    rep: &[u32],
    r: Range<usize>,
    root: Child,
    (reach, sheet): (f32, bool),
    bounds: &[LinkBound],
    dist: &Csr<f32>,
    kind: &[u32],
) -> Vec<Cut> {
    let mut incoming: Vec<Vec<(u32, f32, u32)>> = vec![Vec::new(); r.len()];
    for i in r.clone() {
        for e in dist.row_ptr[i] as usize..dist.row_ptr[i + 1] as usize {
            let j = dist.col[e] as usize;
            if r.contains(&j) {
                let kd = kind.get(e).copied().unwrap_or(KIND_SAME);
                incoming[j - r.start].push(((i - r.start) as u32, dist.val[e], kd));
            }
        }
    }
    r.clone()
        .into_par_iter()
        .map_init(
            || (vec![f32::INFINITY; r.len()], vec![KIND_SAME; r.len()]),
            |(dj, kj), j| {
                let into = &incoming[j - r.start];
                for &(i, d, kd) in into {
                    dj[i as usize] = d;
                    kj[i as usize] = kd;
                }
                let (mut near, mut far) = (Vec::new(), Vec::new());
                cutter.cut(j, root, reach, sheet, bounds, &mut near, &mut far);
                let mut direct: Vec<(u32, f32, u32)> = near
                    .into_iter()
                    .filter_map(|i| {
                        let l = i as usize - r.start;
                        dj[l].is_finite().then(|| (i, dj[l], kj[l]))
                    })
                    .collect();
                // A far node whose representative lies beyond the stored reach is dropped:
                // only its edge is within reach, where the profile has spent all but its
                // truncation energy.
                let mut links: Vec<(u32, f32, u32)> = far
                    .into_iter()
                    .filter_map(|q| {
                        let l = rep[q as usize] as usize - r.start;
                        dj[l].is_finite().then(|| (q, dj[l], kj[l]))
                    })
                    .collect();
                for &(i, _, _) in into {
                    dj[i as usize] = f32::INFINITY;
                }
                direct.sort_unstable_by_key(|e| e.0);
                links.sort_unstable_by_key(|e| e.0);
                (direct, links)
            },
        )
        .collect()
}

/// The cut of one homogeneous translucent object whose distances are traced on demand:
/// every receiver's cut first (geometry only; candidates whose straight line already
/// exceeds the reach are left out, an optical path being never shorter), then the
/// distances it uses: one run per receiver to its direct patches, one per linked node from
/// its representative to the receivers linking it. Distances are symmetric, so each
/// equals the stored pairwise one ([`Oracle`]) and the cut equals [`cut_pairwise`]'s.
#[expect(
    clippy::too_many_arguments,
    reason = "one object's share of collapse's inputs"
)]
fn cut_on_demand(
    cutter: &Cutter<'_>,
    rep: &[u32],
    (r, js): (Range<usize>, Range<usize>),
    root: Child,
    reach: f32,
    bounds: &[LinkBound],
    oracle: &Oracle,
    runs: &mut (u64, u64),
) -> Vec<Cut> {
    let g = cutter.g;
    let base = r.start as u32;
    // Receivers are indexed from `js.start` (`jl`); the oracle's runs take object-local
    // indices (`jl + off`).
    let off = (js.start - r.start) as u32;
    let within = |a: u32, b: u32| g.centroid[a as usize].distance(g.centroid[b as usize]) <= reach;
    // Per receiver: its direct candidates (local) and far nodes.
    let geo: Vec<(Vec<u32>, Vec<u32>)> = js
        .clone()
        .into_par_iter()
        .map(|j| {
            let (mut near, mut far) = (Vec::new(), Vec::new());
            cutter.cut(j, root, reach, false, bounds, &mut near, &mut far);
            near.retain(|&i| within(i, j as u32));
            far.retain(|&q| within(rep[q as usize], j as u32));
            near.iter_mut().for_each(|i| *i -= base);
            near.sort_unstable();
            far.sort_unstable();
            (near, far)
        })
        .collect();
    // Direct: from each receiver to its close candidates; a distant candidate (a patch a
    // loose node of the tree leaves to many receivers' near fields) gets one run of its
    // own to every receiver listing it, rather than stretching each of their runs.
    let close = 2.0 * cutter.near_factor;
    let mut distant: std::collections::HashMap<u32, Vec<u32>> = std::collections::HashMap::new();
    let jobs: Vec<(u32, Vec<u32>)> = geo
        .iter()
        .enumerate()
        .map(|(jl, (near, _))| {
            let j = jl as u32 + off + base;
            let limit = close * g.size[j as usize];
            let (mut mine, mut far_off) = (Vec::new(), Vec::new());
            for &i in near {
                if g.centroid[(i + base) as usize].distance(g.centroid[j as usize]) <= limit {
                    mine.push(i);
                } else {
                    far_off.push(i);
                }
            }
            for i in far_off {
                distant.entry(i).or_default().push(jl as u32 + off);
            }
            (jl as u32 + off, mine)
        })
        .collect();
    // Each receiver's distances aligned with its (sorted) candidates.
    let mut direct_d: Vec<Vec<f32>> = geo
        .iter()
        .map(|(near, _)| vec![f32::INFINITY; near.len()])
        .collect();
    let mut put = |jo: u32, i: u32, d: f32| {
        let jl = (jo - off) as usize;
        let (near, _) = &geo[jl];
        if let Ok(k) = near.binary_search(&i) {
            direct_d[jl][k] = d;
        }
    };
    for ((jl, mine), ds) in jobs.iter().zip(cutter.runs(oracle, &jobs).0) {
        for (&i, d) in mine.iter().zip(ds) {
            put(*jl, i, d);
        }
    }
    drop(jobs);
    let far_jobs: Vec<(u32, Vec<u32>)> = distant.into_iter().collect();
    for ((i, receivers), ds) in far_jobs.iter().zip(cutter.runs(oracle, &far_jobs).0) {
        for (&jl, d) in receivers.iter().zip(ds) {
            put(jl, *i, d);
        }
    }
    // Links: from each linked node's representative to the receivers linking it.
    let mut linkers: std::collections::BTreeMap<u32, Vec<u32>> = Default::default();
    for (jl, (_, far)) in geo.iter().enumerate() {
        for &q in far {
            linkers.entry(q).or_default().push(jl as u32 + off);
        }
    }
    let (node_list, jobs): (Vec<u32>, Vec<(u32, Vec<u32>)>) = linkers
        .into_iter()
        .map(|(q, receivers)| (q, (rep[q as usize] - base, receivers)))
        .unzip();
    let (link_d, coarse) = cutter.runs(oracle, &jobs);
    runs.0 += jobs.len() as u64;
    runs.1 += coarse as u64;
    // Back to receivers: (node, distance) per receiver.
    let mut by_receiver: Vec<Vec<(u32, f32, u32)>> = vec![Vec::new(); js.len()];
    for ((q, (_, receivers)), ds) in node_list.iter().zip(&jobs).zip(&link_d) {
        for (&jo, &d) in receivers.iter().zip(ds) {
            if d.is_finite() {
                by_receiver[(jo - off) as usize].push((*q, d, KIND_SAME));
            }
        }
    }
    geo.into_iter()
        .zip(direct_d)
        .zip(by_receiver)
        .map(|(((near, _), ds), mut links)| {
            let direct: Vec<(u32, f32, u32)> = near
                .into_iter()
                .zip(ds)
                .filter(|(_, d)| d.is_finite())
                .map(|(i, d)| (i + base, d, KIND_SAME))
                .collect();
            links.sort_unstable_by_key(|e| e.0);
            (direct, links)
        })
        .collect()
}
