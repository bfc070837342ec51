//! Hierarchical form factors: a cluster tree over the patches and, per receiver patch, a
//! light-independent cut through it (the paper's future work, after Hanrahan et al. 1991
//! and Willmott et al.'s face clusters 1999; see `docs/hierarchy.md`).
//!
//! In: [`Patches`], an [`Occluder`] over the scene, [`HierarchyParams`] and the leaf rule of
//! [`crate::formfactor`]. Out: [`Hierarchical`]: C (rows: patches; columns: patches `0..N`,
//! then cluster nodes `N..N+M`), the tree (patches in tree order and each node's range of
//! that order), and the summaries. `translux_engine::transport` applies F̃ = C·P, P being the
//! area-weighted mean of each node's patches.
//!
//! The tree: objects are split apart first (a median split of the object centres, so the top
//! of the tree is a BVH over objects); within an object a node whose normal cone is wide is
//! split by normal (the two sides of a thin wall part there), else at the median of the
//! patch centroids along the longest axis. Leaves are the patches.
//!
//! The cut for receiver i at x (its centroid, normal nᵢ), from the root down:
//! - a node entirely behind nᵢ's plane, or whose every face turns away from every point of
//!   patch i (normal cone and bounding sphere, against x widened by the patch's reach), is
//!   culled;
//! - a node s is linked when R_s ≤ η d (η = [`HierarchyParams::accuracy`], d the distance
//!   from x to its centre), d ≥ `near_factor` × patch i's size, s lies wholly in front of
//!   x's plane, its normal cone is at most [`HierarchyParams::cone_deg`] wide and every face
//!   faces x, and the shadow rays to its sample points all agree. The coefficient is
//!   Σₖ wₖ F(x → qₖ) / A_qₖ · Vₖ over area-stratified patches qₖ of s (weights A_s/m, or
//!   each patch's area when s has at most m patches), the kernel's mean over each sampled
//!   patch taken exactly (point-to-polygon): a radiosity constant over s is moved exactly as
//!   far as the samples resolve the kernel;
//! - otherwise its children are visited; two patches use the dense code's pair rule (exact
//!   point-to-polygon, sub-sampled when near). Nothing depends on a light.
//!
//! With [`HierarchyParams::two_sided`] nodes receive too ([`twosided`], its visibility by
//! [`shaft`]s between boxes): C then has a row per node after the patch rows.

use std::f32::consts::{FRAC_PI_2, PI};
use std::sync::atomic::{AtomicU64, Ordering};

use glam::Vec3;
use rayon::prelude::*;
use translux_engine::raycast::Occluder;
use translux_proto::bundle::{FormFactorInfo, HierarchyInfo};
use translux_proto::csr::Csr;

use crate::formfactor::{
    FormFactorParams, any_in_front, pair, point_to_polygon, summarize, summarize_sums,
};
use crate::patch::Patches;

pub mod shaft;
pub mod twosided;

/// The accuracy parameters a precompute accepts ([`HierarchyParams::check`]).
pub const ACCURACY_RANGE: std::ops::RangeInclusive<f32> = 0.02..=1.0;

/// Parameters of [`compute`], with the defaults documented on each field.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HierarchyParams {
    /// η: a node of bounding radius R is linked whole to a receiver only from a distance of
    /// at least R/η; it bounds the angle a linked cluster subtends (about 2η radians) and so
    /// the kernel's variation over it. Smaller is more accurate and stores more. Default
    /// 0.2; accepted 0.02 to 1.
    pub accuracy: f32,
    /// Points of a linked node (one shadow ray each; their agreement is the visibility test).
    /// Default 8.
    pub node_samples: u32,
    /// Widest normal cone (full angle, degrees) a linked node may have. Default 60.
    pub cone_deg: f32,
    /// Whether cluster nodes receive too ([`twosided`]: links between nodes on both
    /// sides), or only patches (the one-sided cut below). Default false.
    pub two_sided: bool,
}

impl Default for HierarchyParams {
    fn default() -> Self {
        Self {
            accuracy: 0.2,
            node_samples: 8,
            cone_deg: 60.0,
            two_sided: false,
        }
    }
}

impl HierarchyParams {
    /// Refuses values outside the documented ranges, naming the parameter.
    pub fn check(&self) -> Result<(), String> {
        if !(self.accuracy.is_finite() && ACCURACY_RANGE.contains(&self.accuracy)) {
            return Err(format!(
                "--accuracy must be in [{}, {}] (the largest cluster radius over distance a \
                 link may have), got {}",
                ACCURACY_RANGE.start(),
                ACCURACY_RANGE.end(),
                self.accuracy
            ));
        }
        if !(1..=64).contains(&self.node_samples) {
            return Err(format!(
                "node samples must be in [1, 64], got {}",
                self.node_samples
            ));
        }
        if !(self.cone_deg.is_finite() && (0.0..=180.0).contains(&self.cone_deg)) {
            return Err(format!(
                "the node cone must be in [0, 180] degrees, got {}",
                self.cone_deg
            ));
        }
        Ok(())
    }
}

/// A child of a tree node: another node (by index) or a patch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Child {
    Node(u32),
    Patch(u32),
}

/// One cluster node.
#[derive(Debug, Clone, Copy)]
struct Node {
    /// Range of the tree order it covers.
    range: [u32; 2],
    area: f64,
    /// Bounding sphere of its patches' corners.
    center: Vec3,
    radius: f32,
    /// Bounding box of its patches' corners: centre and half extent.
    box_center: Vec3,
    box_half: Vec3,
    /// Least and greatest axis · corner over its corners (its extent along the cone axis).
    plane_min: f32,
    plane_max: f32,
    /// Normal cone: area-weighted mean normal and the largest angle to it (π when the
    /// normals cancel).
    axis: Vec3,
    cone: f32,
    children: [Child; 2],
}

/// The cluster tree over the patches.
#[derive(Debug)]
pub struct ClusterTree {
    /// Patches in tree order.
    pub perm: Vec<u32>,
    nodes: Vec<Node>,
    root: Child,
    /// Σ area of the patches before each position of the tree order (N + 1 values).
    area_prefix: Vec<f64>,
    pub depth: u32,
}

impl ClusterTree {
    /// Builds the tree (see the module docs).
    pub fn build(p: &Patches) -> Self {
        let n = p.len();
        let mut perm: Vec<u32> = (0..n as u32).collect();
        let centers = object_centers(p);
        let mut b = Builder {
            p,
            centers: &centers,
            nodes: Vec::with_capacity(n.saturating_sub(1)),
            depth: 0,
        };
        let root = if n == 0 {
            Child::Patch(0)
        } else {
            b.build(&mut perm, 0, 0)
        };
        let (nodes, depth) = (b.nodes, b.depth);
        let mut area_prefix = Vec::with_capacity(n + 1);
        area_prefix.push(0.0);
        let mut acc = 0.0f64;
        for &q in &perm {
            acc += p.area[q as usize] as f64;
            area_prefix.push(acc);
        }
        Self {
            perm,
            nodes,
            root,
            area_prefix,
            depth,
        }
    }

    /// Cluster nodes (internal nodes; the leaves are the patches).
    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// Each node's range of [`ClusterTree::perm`].
    pub fn ranges(&self) -> Vec<[u32; 2]> {
        self.nodes.iter().map(|n| n.range).collect()
    }

    /// Node k's two children.
    pub fn children(&self, k: usize) -> [Child; 2] {
        self.nodes[k].children
    }

    /// Node k's normal cone: the largest angle (radians) of a patch normal to the node's
    /// mean normal (π when the normals cancel).
    pub fn cone(&self, k: usize) -> f32 {
        self.nodes[k].cone
    }

    /// Node k's bounding sphere (centre, radius) of its patches' corners.
    pub fn sphere(&self, k: usize) -> (Vec3, f32) {
        (self.nodes[k].center, self.nodes[k].radius)
    }

    /// The subtree that holds exactly the patches at positions `range` of the tree order
    /// (an object's, since objects are split apart first): a node, a single patch, or `None`
    /// when no subtree covers exactly that range.
    pub fn subtree(&self, range: [u32; 2]) -> Option<Child> {
        if range[1] == range[0] + 1 {
            return Some(Child::Patch(self.perm[range[0] as usize]));
        }
        self.nodes
            .iter()
            .position(|n| n.range == range)
            .map(|k| Child::Node(k as u32))
    }
}

/// Area-weighted centre of each object's patches.
fn object_centers(p: &Patches) -> Vec<Vec3> {
    p.object_ranges
        .iter()
        .map(|r| {
            let (mut c, mut a) = (Vec3::ZERO, 0.0f32);
            for k in r.clone() {
                c += p.centroid[k] * p.area[k];
                a += p.area[k];
            }
            if a > 0.0 { c / a } else { c }
        })
        .collect()
}

struct Builder<'a> {
    p: &'a Patches,
    centers: &'a [Vec3],
    nodes: Vec<Node>,
    depth: u32,
}

/// Normal cones wider than this (full angle) are split by normal before position.
const SPLIT_BY_NORMAL_DEG: f32 = 90.0;

impl Builder<'_> {
    /// The subtree over `perm` (which starts at `offset` of the tree order).
    fn build(&mut self, perm: &mut [u32], offset: u32, depth: u32) -> Child {
        if perm.len() == 1 {
            return Child::Patch(perm[0]);
        }
        self.depth = self.depth.max(depth);
        let p = self.p;
        let at = self.nodes.len();
        // Bounds, area and normal cone.
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        let (mut area, mut sum_n) = (0.0f64, Vec3::ZERO);
        for &q in perm.iter() {
            let q = q as usize;
            for c in &p.corners[q] {
                lo = lo.min(*c);
                hi = hi.max(*c);
            }
            area += p.area[q] as f64;
            sum_n += p.normal[q] * p.area[q];
        }
        let center = (lo + hi) * 0.5;
        let mut radius = 0.0f32;
        let (axis, mut cone) = if sum_n.length() > 1e-6 * area as f32 {
            (sum_n.normalize(), 0.0f32)
        } else {
            (Vec3::Y, PI)
        };
        let (mut plane_min, mut plane_max) = (f32::INFINITY, f32::NEG_INFINITY);
        for &q in perm.iter() {
            let q = q as usize;
            for c in &p.corners[q] {
                radius = radius.max(c.distance(center));
                plane_min = plane_min.min(axis.dot(*c));
                plane_max = plane_max.max(axis.dot(*c));
            }
            if cone < PI {
                cone = cone.max(axis.dot(p.normal[q]).clamp(-1.0, 1.0).acos());
            }
        }
        self.nodes.push(Node {
            range: [offset, offset + perm.len() as u32],
            area,
            center,
            radius,
            box_center: center,
            box_half: (hi - lo) * 0.5,
            plane_min,
            plane_max,
            axis,
            cone,
            children: [Child::Patch(0); 2],
        });
        let mid = self.split(perm, cone);
        let (left, right) = perm.split_at_mut(mid);
        let a = self.build(left, offset, depth + 1);
        let b = self.build(right, offset + mid as u32, depth + 1);
        self.nodes[at].children = [a, b];
        Child::Node(at as u32)
    }

    /// Reorders `perm` and returns where the two children part (0 < mid < len).
    fn split(&self, perm: &mut [u32], cone: f32) -> usize {
        let p = self.p;
        let len = perm.len();
        // 1. Several objects: by object, at the object boundary nearest the middle.
        let first = p.object[perm[0] as usize];
        if perm.iter().any(|&q| p.object[q as usize] != first) {
            let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
            for &q in perm.iter() {
                let c = self.centers[p.object[q as usize] as usize];
                lo = lo.min(c);
                hi = hi.max(c);
            }
            let axis = longest_axis(hi - lo);
            let key = |q: &u32| {
                let o = p.object[*q as usize];
                (self.centers[o as usize][axis], o)
            };
            perm.sort_by(|a, b| {
                let (ka, kb) = (key(a), key(b));
                ka.0.total_cmp(&kb.0).then(ka.1.cmp(&kb.1))
            });
            let mut best = 0usize;
            for k in 1..len {
                if p.object[perm[k] as usize] != p.object[perm[k - 1] as usize]
                    && (best == 0 || k.abs_diff(len / 2) < best.abs_diff(len / 2))
                {
                    best = k;
                }
            }
            return best;
        }
        // 2. A wide normal cone: by normal, at the middle of the normals' extent along the
        //    axis where they spread most (opposite sides of a wall part exactly).
        if cone.to_degrees() * 2.0 > SPLIT_BY_NORMAL_DEG {
            let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
            for &q in perm.iter() {
                lo = lo.min(p.normal[q as usize]);
                hi = hi.max(p.normal[q as usize]);
            }
            let axis = longest_axis(hi - lo);
            let t = 0.5 * (lo[axis] + hi[axis]);
            perm.sort_by(|a, b| {
                p.normal[*a as usize][axis].total_cmp(&p.normal[*b as usize][axis])
            });
            let mid = perm.partition_point(|&q| p.normal[q as usize][axis] < t);
            if mid > 0 && mid < len {
                return mid;
            }
        }
        // 3. By position: the median centroid along the longest axis.
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for &q in perm.iter() {
            lo = lo.min(p.centroid[q as usize]);
            hi = hi.max(p.centroid[q as usize]);
        }
        let axis = longest_axis(hi - lo);
        let mid = len / 2;
        perm.select_nth_unstable_by(mid, |a, b| {
            p.centroid[*a as usize][axis].total_cmp(&p.centroid[*b as usize][axis])
        });
        mid
    }
}

fn longest_axis(e: Vec3) -> usize {
    if e.x >= e.y && e.x >= e.z {
        0
    } else if e.y >= e.z {
        1
    } else {
        2
    }
}

/// A link's sample patch q is integrated with the point-to-point kernel when it lies
/// farther than this many times its longest edge from the receiver (squared here).
const POINT_KERNEL_RATIO2: f32 = 10.0 * 10.0;

/// What [`compute`] made.
#[derive(Debug)]
pub struct Hierarchical {
    /// C: `N × (N + M)`, or `(N + M) × (N + M)` two-sided.
    pub c: Csr,
    pub tree: ClusterTree,
    pub info: HierarchyInfo,
    pub ff_info: FormFactorInfo,
}

/// Every receiver's cut through `tree` ([`ClusterTree::build`] of `p`). `progress` is
/// called with the number of rows finished since its last call; once `stop()` returns
/// `true` the rows not yet started are skipped (the result must then be thrown away).
pub fn compute(
    p: &Patches,
    occ: &Occluder,
    ff: &FormFactorParams,
    params: &HierarchyParams,
    tree: ClusterTree,
    progress: &(dyn Fn(u64) + Sync),
    stop: &(dyn Fn() -> bool + Sync),
) -> Hierarchical {
    let rows = if params.two_sided {
        twosided::compute(p, occ, ff, params, &tree, progress, stop)
    } else {
        compute_rows(p, occ, ff, params, &tree, 0..p.len(), progress, stop)
    };
    assemble(tree, params, vec![rows])
}

/// The cuts of the receivers `rows` (a share of [`compute`]'s work: a precompute shard,
/// [`crate::shard`]). Each receiver's cut depends on nothing but the patches, the tree and
/// the parameters, so the rows of several blocks put together are [`compute`]'s rows.
#[allow(clippy::too_many_arguments)]
pub fn compute_rows(
    p: &Patches,
    occ: &Occluder,
    ff: &FormFactorParams,
    params: &HierarchyParams,
    tree: &ClusterTree,
    rows: std::ops::Range<usize>,
    progress: &(dyn Fn(u64) + Sync),
    stop: &(dyn Fn() -> bool + Sync),
) -> RowBlock {
    let ctx = Cut::new(p, occ, ff, params, tree);
    let rays = AtomicU64::new(0);
    let tests = AtomicU64::new(0);
    let cuts: Vec<(Vec<(u32, f32)>, RowStats)> = rows
        .clone()
        .into_par_iter()
        .with_min_len(4)
        .map_init(Vec::new, |samples, i| {
            if stop() {
                return Default::default();
            }
            let mut r = ctx.row(i, samples);
            // Held until the block is put together: without the room its pushes grew
            // (about 1.4 times the entries' bytes otherwise), as the memory estimate counts
            // (`pipeline::HIERARCHICAL_BUILD_BYTES_PER_NNZ`).
            r.0.shrink_to_fit();
            rays.fetch_add(r.1.rays, Ordering::Relaxed);
            tests.fetch_add(r.1.tests, Ordering::Relaxed);
            progress(1);
            r
        })
        .collect();
    let nnz: usize = cuts.iter().map(|c| c.0.len()).sum();
    let mut block = RowBlock {
        first: rows.start as u64,
        row_ptr: Vec::with_capacity(cuts.len() + 1),
        col: Vec::with_capacity(nnz),
        val: Vec::with_capacity(nnz),
        rays: rays.into_inner(),
        tests: tests.into_inner(),
        ..Default::default()
    };
    block.row_ptr.push(0);
    for (row, stats) in cuts {
        block.node_entries += stats.node_entries;
        block.patch_entries += stats.patch_entries;
        block.covered += stats.covered;
        for (j, v) in row {
            block.col.push(j);
            block.val.push(v);
        }
        block.row_ptr.push(block.col.len() as u64);
    }
    block
}

/// Entries per receiver of the one-sided cut, measured on a sample of receivers before F is
/// built (the memory estimate, `pipeline::check_memory`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SampledCut {
    /// Receivers whose cut was made.
    pub rows: usize,
    /// Their mean entries per row.
    pub mean: f64,
    /// The standard error of that mean.
    pub std_error: f64,
}

/// Makes the one-sided cut of `rows` receivers spread evenly over the patches (in the
/// tree's order, so every part of the scene is sampled: objects are contiguous there) and
/// counts their entries. Each cut depends on nothing but the patches, the tree and the
/// parameters ([`compute_rows`]), so their mean estimates F's entries per patch; the cost
/// is that of `rows` rows of the F stage.
pub fn sample_entries(
    p: &Patches,
    occ: &Occluder,
    ff: &FormFactorParams,
    params: &HierarchyParams,
    tree: &ClusterTree,
    rows: usize,
) -> SampledCut {
    let n = p.len();
    let rows = rows.min(n);
    if rows == 0 {
        return SampledCut {
            rows: 0,
            mean: 0.0,
            std_error: 0.0,
        };
    }
    let ctx = Cut::new(p, occ, ff, params, tree);
    let counts: Vec<f64> = (0..rows)
        .into_par_iter()
        .map_init(Vec::new, |samples, k| {
            // The middle of each of `rows` equal runs of the tree's order.
            let i = tree.perm[(2 * k + 1) * n / (2 * rows)] as usize;
            ctx.row(i, samples).0.len() as f64
        })
        .collect();
    let mean = counts.iter().sum::<f64>() / rows as f64;
    let var = counts.iter().map(|c| (c - mean).powi(2)).sum::<f64>() / (rows.max(2) - 1) as f64;
    SampledCut {
        rows,
        mean,
        std_error: (var / rows as f64).sqrt(),
    }
}

/// Consecutive rows of C ([`compute_rows`]) with their counts.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RowBlock {
    /// The first receiver (row) of the block.
    pub first: u64,
    /// Offsets of each row's entries in `col`/`val`, from 0 (rows + 1 of them).
    pub row_ptr: Vec<u64>,
    pub col: Vec<u32>,
    pub val: Vec<f32>,
    /// Occlusion rays cast and nodes or patch pairs examined.
    pub rays: u64,
    pub tests: u64,
    /// Entries linking a receiver to a cluster node, and to a single patch.
    pub node_entries: u64,
    pub patch_entries: u64,
    /// Patches behind the entries (what dense F would store, visibility aside).
    pub covered: u64,
}

impl RowBlock {
    /// Rows in the block.
    pub fn rows(&self) -> usize {
        self.row_ptr.len().saturating_sub(1)
    }
}

/// C and its summaries from row blocks that together cover every receiver in order (checked:
/// a caller putting shards together has verified them already, so a gap is a bug).
pub fn assemble(
    tree: ClusterTree,
    params: &HierarchyParams,
    blocks: Vec<RowBlock>,
) -> Hierarchical {
    let n = tree.perm.len();
    let rows = if params.two_sided {
        n + tree.node_count()
    } else {
        n
    };
    let nnz: usize = blocks.iter().map(|b| b.col.len()).sum();
    let mut c = Csr {
        n_rows: rows,
        n_cols: n + tree.node_count(),
        row_ptr: Vec::with_capacity(n + 1),
        col: Vec::new(),
        val: Vec::new(),
    };
    c.row_ptr.push(0);
    let (mut rays, mut tests) = (0u64, 0u64);
    let (mut node_entries, mut patch_entries, mut dense_equivalent) = (0u64, 0u64, 0u64);
    let whole = blocks.len() == 1;
    if !whole {
        c.col.reserve_exact(nnz);
        c.val.reserve_exact(nnz);
    }
    for mut b in blocks {
        assert_eq!(
            b.first as usize,
            c.row_ptr.len() - 1,
            "row blocks out of order"
        );
        let base = c.col.len() as u64;
        c.row_ptr.extend(b.row_ptr[1..].iter().map(|&o| base + o));
        if whole {
            // One block (one box): its entries are C's, moved rather than copied (F's
            // peak is then its entries once).
            (c.col, c.val) = (std::mem::take(&mut b.col), std::mem::take(&mut b.val));
        } else {
            c.col.extend_from_slice(&b.col);
            c.val.extend_from_slice(&b.val);
        }
        rays += b.rays;
        tests += b.tests;
        node_entries += b.node_entries;
        patch_entries += b.patch_entries;
        dense_equivalent += b.covered;
    }
    assert_eq!(
        c.row_ptr.len(),
        rows + 1,
        "row blocks do not cover every receiver"
    );
    let ff_info = if params.two_sided {
        let sums = pushed_row_sums(&c, &tree);
        summarize_sums(&sums, c.nnz() as u64, 0.0, 0.0, rays, tests)
    } else {
        summarize(&c, 0.0, 0.0, rays, tests)
    };
    let info = HierarchyInfo {
        nodes: tree.node_count() as u64,
        depth: tree.depth,
        accuracy: params.accuracy,
        node_samples: params.node_samples,
        node_entries,
        patch_entries,
        dense_equivalent,
        receiver_nodes: params.two_sided,
    };
    Hierarchical {
        c,
        tree,
        info,
        ff_info,
    }
}

/// Each patch's row sum of a two-sided C: its own row plus the rows of every node holding
/// it (a difference array over the tree order, as the engine's push).
fn pushed_row_sums(c: &Csr, tree: &ClusterTree) -> Vec<f64> {
    let n = tree.perm.len();
    let row_sum = |i: usize| -> f64 {
        let (a, b) = (c.row_ptr[i] as usize, c.row_ptr[i + 1] as usize);
        c.val[a..b].iter().map(|&v| v as f64).sum()
    };
    let mut diff = vec![0.0f64; n + 1];
    for (k, node) in tree.nodes.iter().enumerate() {
        let v = row_sum(n + k);
        diff[node.range[0] as usize] += v;
        diff[node.range[1] as usize] -= v;
    }
    let mut sums: Vec<f64> = (0..n).map(row_sum).collect();
    let mut run = 0.0;
    for (q, &p) in tree.perm.iter().enumerate() {
        run += diff[q];
        sums[p as usize] += run;
    }
    sums
}

/// Counts of one receiver's cut.
#[derive(Debug, Default, Clone, Copy)]
struct RowStats {
    rays: u64,
    /// Nodes and patch pairs examined.
    tests: u64,
    node_entries: u64,
    patch_entries: u64,
    /// Patches behind the row's entries (what dense F would store, visibility aside).
    covered: u64,
}

struct Cut<'a> {
    p: &'a Patches,
    occ: &'a Occluder,
    ff: &'a FormFactorParams,
    tree: &'a ClusterTree,
    eta: f32,
    m: usize,
    half_cone: f32,
    eps_plane: f32,
    offset: f32,
}

impl<'a> Cut<'a> {
    /// The cut's inputs and the tolerances they give (planes within 10⁻⁶ of the scene's
    /// diagonal count as touching; rays leave 10⁻⁵ of it off their surfaces).
    fn new(
        p: &'a Patches,
        occ: &'a Occluder,
        ff: &'a FormFactorParams,
        params: &HierarchyParams,
        tree: &'a ClusterTree,
    ) -> Self {
        let diag = occ.diagonal();
        Cut {
            p,
            occ,
            ff,
            tree,
            eta: params.accuracy,
            m: params.node_samples as usize,
            half_cone: (params.cone_deg * 0.5).to_radians(),
            eps_plane: 1e-6 * diag,
            offset: 1e-5 * diag,
        }
    }

    /// Receiver i's entries, sorted by column, and its counts.
    fn row(&self, i: usize, samples: &mut Vec<Vec3>) -> (Vec<(u32, f32)>, RowStats) {
        let p = self.p;
        let n = p.len();
        let (x, ni, corners_i) = (p.centroid[i], p.normal[i], &p.corners[i]);
        let near = self.ff.near_factor * p.size[i];
        // The receiver's reach from its centroid: a node is culled only when every face of
        // it turns away from every point of the receiver (the dense pair cull asks each of
        // the receiver's corners), not from its centroid alone.
        let r_i = corners_i.iter().map(|c| c.distance(x)).fold(0.0, f32::max);
        let mut st = RowStats::default();
        let mut out = Vec::new();
        let mut stack = vec![self.tree.root];
        while let Some(child) = stack.pop() {
            st.tests += 1;
            let k = match child {
                Child::Patch(j) => {
                    let j = j as usize;
                    if j == i
                        || !any_in_front(&p.corners[j], x, ni, self.eps_plane)
                        || !any_in_front(corners_i, p.centroid[j], p.normal[j], self.eps_plane)
                    {
                        continue;
                    }
                    if let Some((f, _)) = pair(
                        p,
                        self.occ,
                        self.ff,
                        self.offset,
                        i,
                        j,
                        samples,
                        &mut st.rays,
                    ) {
                        out.push((j as u32, f));
                        st.patch_entries += 1;
                        st.covered += 1;
                    }
                    continue;
                }
                Child::Node(k) => k as usize,
            };
            let s = &self.tree.nodes[k];
            let to = s.center - x;
            let d = to.length();
            // The node's extent in front of the receiver's plane (box and sphere bounds).
            let reach = ni.abs().dot(s.box_half).min(s.radius);
            let front = ni.dot(s.box_center - x);
            // Wholly behind (or in) the receiver's plane: nothing of it is seen.
            if front + reach <= self.eps_plane {
                continue;
            }
            // x against the node's faces: every face turned away from x, or every face
            // towards it. By the normal cone and the sphere (the axis more than 90° + cone +
            // the sphere's half-angle from the direction to x), or, for a narrow cone, by
            // the node's extent along its axis.
            let (facing, beta) = if d > s.radius {
                let theta = s.axis.dot(-to / d).clamp(-1.0, 1.0).acos();
                (theta, (s.radius / d).asin())
            } else {
                (0.0, FRAC_PI_2)
            };
            let slack = if s.cone < FRAC_PI_2 {
                s.cone.sin() * (d + s.radius) + self.eps_plane
            } else {
                f32::INFINITY
            };
            let height = s.axis.dot(x);
            // The cull's angle, widened by what the receiver subtends at the node.
            let beta_cull = if d > s.radius + r_i {
                ((s.radius + r_i) / d).asin()
            } else {
                PI
            };
            if (s.cone < PI && facing > FRAC_PI_2 + s.cone + beta_cull)
                || s.plane_min - (height + r_i) > slack
                || (s.cone == 0.0 && height + r_i - s.plane_min <= self.eps_plane)
            {
                continue;
            }
            let faces_x = facing + s.cone + beta < FRAC_PI_2 || height - s.plane_max > slack;
            let linkable = s.radius <= self.eta * d
                && d >= near
                && front - reach >= -self.eps_plane
                && s.cone <= self.half_cone
                && faces_x;
            if linkable && let Some(v) = self.link(x, ni, s, &mut st.rays) {
                if v > 0.0 {
                    out.push(((n + k) as u32, v));
                    st.node_entries += 1;
                    st.covered += u64::from(s.range[1] - s.range[0]);
                }
                continue;
            }
            stack.extend_from_slice(&s.children);
        }
        out.sort_unstable_by_key(|e| e.0);
        (out, st)
    }

    /// The coefficient of node s for a receiver at x, or `None` when its sample points
    /// disagree about visibility (then the caller descends).
    fn link(&self, x: Vec3, ni: Vec3, s: &Node, rays: &mut u64) -> Option<f32> {
        let p = self.p;
        let from = x + ni * self.offset;
        let (mut seen, mut hidden) = (0u32, 0u32);
        let mut sum = 0.0f64;
        // Each sample is a patch q of s: the kernel's mean over q, weighted by w, estimates
        // s's share. The first disagreement about visibility ends the test (the caller
        // descends).
        let mut strata = Vec::with_capacity(self.m);
        self.tree
            .strata(s.range, s.area, self.m, &p.area, &mut strata);
        for (q, w) in strata {
            let (y, ny) = (p.centroid[q], p.normal[q]);
            if ny.dot(x - y) <= 0.0 || ni.dot(y - x) <= 0.0 {
                continue;
            }
            *rays += 1;
            if self.occ.occluded(from, y + ny * self.offset) {
                hidden += 1;
            } else {
                seen += 1;
                sum += w * kernel_per_area(p, x, ni, q);
            }
            if seen > 0 && hidden > 0 {
                return None;
            }
        }
        Some(sum as f32)
    }
}

/// The form-factor kernel's mean over patch q per unit of its area, seen from x with normal
/// nᵢ (both facing each other): far from q against its size (the point kernel is then within
/// ~(size/r)² ≈ 1% of the exact polygon integral) the differential kernel
/// cos θ cos θ' / (π r²), else the exact point-to-polygon form factor over A_q.
fn kernel_per_area(p: &Patches, x: Vec3, ni: Vec3, q: usize) -> f64 {
    let r = p.centroid[q] - x;
    let r2 = r.length_squared();
    if p.size[q] * p.size[q] * POINT_KERNEL_RATIO2 <= r2 {
        (ni.dot(r) * p.normal[q].dot(-r) / (r2 * r2 * PI)) as f64
    } else {
        point_to_polygon(x, ni, &p.corners[q]) as f64 / p.area[q] as f64
    }
}

impl ClusterTree {
    /// Area-stratified patches of the tree-order `range` (of total area `area`) with their
    /// weights: each patch with its own area when there are at most `m`, else the patch at
    /// the middle of each of `m` equal shares of the area, weighted area/m.
    fn strata(
        &self,
        range: [u32; 2],
        area: f64,
        m: usize,
        patch_area: &[f32],
        out: &mut Vec<(usize, f64)>,
    ) {
        out.clear();
        let (a, b) = (range[0] as usize, range[1] as usize);
        if b - a <= m {
            out.extend(
                self.perm[a..b]
                    .iter()
                    .map(|&q| (q as usize, patch_area[q as usize] as f64)),
            );
            return;
        }
        let w = area / m as f64;
        let base = self.area_prefix[a];
        for k in 0..m {
            let target = base + (k as f64 + 0.5) * w;
            let at = a + self.area_prefix[a + 1..=b].partition_point(|&c| c <= target);
            out.push((self.perm[at.min(b - 1)] as usize, w));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::patch;

    /// Two triangles wound a, d, c, b (the walls below are listed outward-wound).
    fn quad(a: Vec3, b: Vec3, c: Vec3, d: Vec3) -> Vec<[Vec3; 3]> {
        vec![[a, d, c], [a, c, b]]
    }

    /// A closed unit box seen from inside (inward normals), split into `h`-sized patches.
    fn closed_box(h: f32) -> Patches {
        let v = |x: f32, y: f32, z: f32| Vec3::new(x, y, z);
        let walls: Vec<Vec<[Vec3; 3]>> = vec![
            quad(v(0., 0., 0.), v(1., 0., 0.), v(1., 0., 1.), v(0., 0., 1.)),
            quad(v(0., 1., 0.), v(0., 1., 1.), v(1., 1., 1.), v(1., 1., 0.)),
            quad(v(0., 0., 0.), v(0., 0., 1.), v(0., 1., 1.), v(0., 1., 0.)),
            quad(v(1., 0., 0.), v(1., 1., 0.), v(1., 1., 1.), v(1., 0., 1.)),
            quad(v(0., 0., 0.), v(0., 1., 0.), v(1., 1., 0.), v(1., 0., 0.)),
            quad(v(0., 0., 1.), v(1., 0., 1.), v(1., 1., 1.), v(0., 1., 1.)),
        ];
        let sources: Vec<&[[Vec3; 3]]> = walls.iter().map(|w| w.as_slice()).collect();
        patch::subdivide(&sources, h)
    }

    #[test]
    fn the_tree_covers_every_patch_in_contiguous_ranges() {
        let p = closed_box(0.2);
        let t = ClusterTree::build(&p);
        let n = p.len();
        assert_eq!(t.node_count(), n - 1, "a binary tree with N leaves");
        let mut sorted = t.perm.clone();
        sorted.sort();
        assert_eq!(sorted, (0..n as u32).collect::<Vec<_>>());
        let root = &t.nodes[0];
        assert_eq!(root.range, [0, n as u32]);
        // Each node's range is the union of its children's.
        for node in &t.nodes {
            let span = |c: Child, at: u32| match c {
                Child::Node(k) => t.nodes[k as usize].range,
                Child::Patch(_) => [at, at + 1],
            };
            let l = span(node.children[0], node.range[0]);
            let r = span(node.children[1], l[1]);
            assert_eq!([l[0], r[1]], node.range);
            if let Child::Patch(q) = node.children[0] {
                assert_eq!(t.perm[node.range[0] as usize], q);
            }
        }
        // Objects are apart: no node below the object level mixes walls.
        for node in &t.nodes {
            if node.cone < 1e-3 {
                let o = p.object[t.perm[node.range[0] as usize] as usize];
                assert!(
                    t.perm[node.range[0] as usize..node.range[1] as usize]
                        .iter()
                        .all(|&q| p.object[q as usize] == o)
                );
            }
        }
    }

    /// In a closed box every row of F sums to 1; the hierarchical rows too, within what
    /// the node links' point sampling resolves.
    /// `formfactor::dense_row` (the exact-row reference of the benchmark) is dense F's row.
    #[test]
    fn a_dense_row_alone_is_dense_fs_row() {
        let p = closed_box(0.25);
        let occ = Occluder::new(&p.corners);
        let params = FormFactorParams::default();
        let (f, _) = crate::formfactor::compute(&p, &occ, &params, &|_| {});
        let f = f.view().unwrap();
        for i in [0, 7, p.len() / 2, p.len() - 1] {
            let (cols, vals) = f.row(i);
            let want: Vec<(u32, f32)> = cols.iter().copied().zip(vals.iter().copied()).collect();
            assert_eq!(
                crate::formfactor::dense_row(&p, &occ, &params, i),
                want,
                "row {i}"
            );
        }
    }

    #[test]
    fn closed_box_rows_sum_to_one() {
        let p = closed_box(0.1);
        let tris: Vec<[Vec3; 3]> = p.corners.clone();
        let occ = Occluder::new(&tris);
        let h = compute(
            &p,
            &occ,
            &FormFactorParams::default(),
            &HierarchyParams::default(),
            ClusterTree::build(&p),
            &|_| {},
            &|| false,
        );
        assert!(h.info.node_entries > 0, "{:?}", h.info);
        let n = p.len();
        assert!(
            (h.c.nnz() as f64) < 0.5 * (n * n) as f64,
            "{} entries for {n} patches",
            h.c.nnz()
        );
        let (lo, hi) = (h.ff_info.row_sum_min, h.ff_info.row_sum_max);
        assert!(
            (h.ff_info.row_sum_mean - 1.0).abs() < 0.01 && lo > 0.95 && hi < 1.05,
            "{:?}",
            h.ff_info
        );
    }

    /// The memory estimate's sample of receivers: their cuts are the rows F will have, so
    /// their mean is F's entries per patch within its standard errors.
    #[test]
    fn sampled_receivers_estimate_the_entries_per_patch() {
        let p = closed_box(0.05);
        let occ = Occluder::new(&p.corners);
        let (ff, params) = (FormFactorParams::default(), HierarchyParams::default());
        let tree = ClusterTree::build(&p);
        let sample = sample_entries(&p, &occ, &ff, &params, &tree, 64);
        let h = compute(&p, &occ, &ff, &params, tree, &|_| {}, &|| false);
        let n = p.len();
        let actual = h.c.nnz() as f64 / n as f64;
        assert_eq!(sample.rows, 64);
        assert!(
            sample.std_error > 0.0 && (sample.mean - actual).abs() <= 4.0 * sample.std_error,
            "{sample:?} against {actual} entries per patch over {n} patches"
        );
        assert!(
            (sample.mean / actual - 1.0).abs() < 0.15,
            "{sample:?} against {actual}"
        );
    }

    #[test]
    fn out_of_range_parameters_are_refused() {
        for accuracy in [0.0, -1.0, 1.5, f32::NAN] {
            let e = HierarchyParams {
                accuracy,
                ..Default::default()
            }
            .check()
            .unwrap_err();
            assert!(e.starts_with("--accuracy must be in [0.02, 1]"), "{e}");
        }
        assert!(HierarchyParams::default().check().is_ok());
    }
}
