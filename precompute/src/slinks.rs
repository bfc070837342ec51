//! Hierarchical S: each receiver of a translucent object gathers from far parts of the
//! object through whole cluster nodes (links), near pairs and the self term keep the
//! pairwise quadrature (issue 20; after Jensen & Buhler 2002's octree and Mertens et al.
//! 2003's hierarchical boundary elements, here on the cluster tree of the hierarchical F).
//!
//! In: the cluster tree ([`ClusterTree`], whose top splits objects apart, so each object is
//! one subtree), the patch geometry, the objects with the radius their distances were
//! stored to, stage 1's pairwise distances and [`SLinkParams`]. Out: [`Collapsed`]: the
//! distances as the bundle stores them for a hierarchical S (`N × (N + M)`, see
//! `translux_proto::bundle::SubsurfaceInfo::links`) and the tree's nodes as S's assembly reads
//! them.
//!
//! The cut for receiver j (centroid x, longest edge s_j), from the object's subtree root
//! down, is geometric only, so it holds for every profile the distances were stored for (a
//! translucency change never re-cuts):
//! - a node holding j is opened;
//! - a node whose bounding sphere (centre c, radius ρ) lies beyond the stored radius
//!   (|x − c| − ρ greater than it: an optical path is never shorter than the straight line)
//!   is dropped;
//! - a node is linked whole when ρ ≤ θ |x − c| (θ = [`SLinkParams::accuracy`]), the node is
//!   outside the receiver's near field (|x − c| − ρ ≥ `near_factor` × s_j, the quadrature's
//!   near-pair rule), and its representative patch (the one nearest its area-weighted
//!   centroid) has a stored optical distance r from j: the link is S_{j,node} = A_node R(r)
//!   applied to the node's area-weighted mean (a node's patches are then at most 2θ/(1 − θ)
//!   of the distance apart from the receiver's point of view); a far node whose
//!   representative has no stored distance (it lies beyond the reach) is dropped, since only
//!   its edge is within reach, where the profile has spent all but its truncation energy;
//! - otherwise its children are visited; a patch i with a stored distance becomes a direct
//!   entry, evaluated as in a pairwise S.
//!
//! Thin sheets are cut the same way along their geodesics, a node being linked only when its
//! normal cone is at most 45° wide (so it holds one side) and the link taking its
//! representative's kind (same side or other side). Heterogeneous objects keep their
//! pairwise distances (each carries its own per-medium lengths).

use std::ops::RangeInclusive;

use glam::Vec3;
use rayon::prelude::*;
use translux_engine::hetero::{MEDIA, MediaLen};
use translux_engine::sheet::KIND_SAME;
use translux_engine::smatrix::{ObjectMaterial, PatchGeometry, SError, SParams};
use translux_engine::subsurface::Nodes;
use translux_proto::bundle::TreeView;
use translux_proto::csr::Csr;
use translux_proto::scene::Material;

use crate::hierarchy::{Child, ClusterTree};

/// Widest normal cone (half-angle, radians: 45°) of a node a thin sheet's receiver may link:
/// the sheet's two sides face apart, so such a node holds one side.
const SHEET_CONE: f32 = std::f32::consts::FRAC_PI_4;

/// The accuracies a precompute accepts ([`SLinkParams::check`]).
pub const ACCURACY_RANGE: RangeInclusive<f32> = 0.05..=1.0;

/// Parameters of [`collapse`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SLinkParams {
    /// θ: a node of bounding radius ρ is linked whole to a receiver only from a distance of
    /// at least ρ/θ. Smaller is more accurate and stores more. Default 0.5; accepted 0.05
    /// to 1.
    pub accuracy: f32,
}

impl Default for SLinkParams {
    fn default() -> Self {
        Self { accuracy: 0.5 }
    }
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
        Ok(())
    }
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

/// Replaces the pairwise distances of every homogeneous translucent object and thin sheet
/// (of two patches or more) by direct pairs and links (the module docs); other rows are
/// copied. `stored[k]` is how far object k's distances reach; `sp` gives the quadrature's
/// near-pair rule.
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
    sp: &SParams,
    params: &SLinkParams,
) -> Result<Collapsed, SError> {
    let near_factor = sp.quadrature.near_factor;
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
    let mut pos = vec![0u32; n];
    for (k, &p) in tree.perm.iter().enumerate() {
        pos[p as usize] = k as u32;
    }
    let rep = representatives(tree, g);
    let theta = params.accuracy;

    // The objects cut: homogeneous translucent objects and sheets with a subtree of their
    // own (objects are split apart first; one without stays pairwise): (object, root,
    // whether it is a sheet).
    let cut: Vec<(usize, Child, bool)> = objects
        .iter()
        .enumerate()
        .filter_map(|(k, o)| {
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
            Some((k, root, sheet))
        })
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
    type Row = Vec<(u32, f32, MediaLen, u32)>;
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
                    )
                })
                .collect()
        })
        .collect();
    let mut links_total = 0u64;
    for &(k, root, sheet) in &cut {
        let r = objects[k].patches.clone();
        let reach = stored.get(k).copied().unwrap_or(0.0);
        // Per receiver j (local): its direct sources and its links.
        type Cut = (Vec<(u32, f32, u32)>, Vec<(u32, f32, u32)>);
        // What reaches each receiver j: the stored entries (source i, receiver j) turned
        // around, as stored (a sheet's entry i → j need not equal j → i).
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
        let cuts: Vec<Cut> = r
            .clone()
            .into_par_iter()
            .map_init(
                || (vec![f32::INFINITY; r.len()], vec![KIND_SAME; r.len()]),
                |(dj, kj), j| {
                    let into = &incoming[j - r.start];
                    for &(i, d, kd) in into {
                        dj[i as usize] = d;
                        kj[i as usize] = kd;
                    }
                    let x = g.centroid[j];
                    let (mut direct, mut links) = (Vec::new(), Vec::new());
                    let mut stack = vec![root];
                    while let Some(c) = stack.pop() {
                        match c {
                            Child::Patch(i) => {
                                let d = dj[i as usize - r.start];
                                if i as usize != j && d.is_finite() {
                                    direct.push((i, d, kj[i as usize - r.start]));
                                }
                            }
                            Child::Node(q) => {
                                let q = q as usize;
                                let range = ranges[q];
                                if (range[0]..range[1]).contains(&pos[j]) {
                                    stack.extend_from_slice(&tree.children(q));
                                    continue;
                                }
                                let (centre, rho) = tree.sphere(q);
                                let de = x.distance(centre);
                                if de - rho > reach {
                                    continue;
                                }
                                // On a sheet a link stands for one side only (normals within
                                // SHEET_CONE of their mean), of its representative's kind.
                                let far = rho <= theta * de
                                    && de - rho >= near_factor * g.size[j]
                                    && (!sheet || tree.cone(q) <= SHEET_CONE);
                                let lr = rep[q] as usize - r.start;
                                let d = dj[lr];
                                if far && d.is_finite() {
                                    links.push((q as u32, d, kj[lr]));
                                } else if !far {
                                    stack.extend_from_slice(&tree.children(q));
                                }
                                // A far node whose representative lies beyond the stored
                                // reach is dropped: only its edge is within reach, where the
                                // profile has spent all but its truncation energy.
                            }
                        }
                    }
                    for &(i, _, _) in into {
                        dj[i as usize] = f32::INFINITY;
                    }
                    direct.sort_unstable_by_key(|e| e.0);
                    links.sort_unstable_by_key(|e| e.0);
                    (direct, links)
                },
            )
            .collect();
        // Direct pairs are stored by source (row i lists its receivers j); receivers come
        // in increasing order, so every row stays sorted.
        for (jl, (direct, _)) in cuts.iter().enumerate() {
            let j = (r.start + jl) as u32;
            for &(i, d, kd) in direct {
                rows[i as usize].push((j, d, [0.0; MEDIA], kd));
            }
        }
        for (jl, (_, links)) in cuts.into_iter().enumerate() {
            links_total += links.len() as u64;
            rows[r.start + jl].extend(
                links
                    .into_iter()
                    .map(|(q, d, kd)| (n as u32 + q, d, [0.0; MEDIA], kd)),
            );
        }
    }
    let linked = links_total > 0;
    let mut material_len = Vec::new();
    let mut kinds = Vec::new();
    let plain: Vec<Vec<(u32, f32)>> = rows
        .into_iter()
        .map(|row| {
            row.into_iter()
                .map(|(c, d, l, kd)| {
                    material_len.push(l);
                    kinds.push(kd);
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
    })
}
