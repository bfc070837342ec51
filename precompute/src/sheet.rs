//! Thin sheets — petals, leaves, paper — as two-sided translucent objects (the paper's rose,
//! §4–5): light entering one face leaves the *same* face by a reflectance profile R(r) and the
//! *other* face by a transmittance profile T(r), r the geodesic distance along the sheet.
//!
//! In: one object's patches in local indices 0..n (corners, centroids, normals, areas, sizes,
//! as [`ObjectPatches`]) and the radius to keep distances to. Out:
//! - [`sheet_distances`]: the [`Side`] of every patch and, per source patch i, the sorted list
//!   of (j, r_ij, kind) with kind [`KIND_SAME`] (j on i's side) or [`KIND_OPPOSITE`] (j on
//!   the other side). `smatrix` stores them as the object's block of the distance CSR and of
//!   the bundle's `dist_kind`.
//! - S from those distances and kinds, R and T tabulated, is `translux_engine::sheet`
//!   (stage 2, also run for every translucency change).
//!
//! ## Sides
//! Two patches touch when they share a corner (welded by position, as `patch` welds the
//! viewer mesh) or a corner of one lies inside an edge of the other (a T-junction, where
//! neighbouring source triangles were split into different numbers of patches). Touching
//! patches whose normals are within [`SIDE_ANGLE_DEG`] of each other are *joined*; the two
//! largest joined components by area are the two sides, [`Side::First`] the larger. All other
//! patches are the rim — the thin walls of a `sheet` shape, at 90° to both faces. A rim patch
//! keeps its own diagonal S_ii (light entering a 1 mm wall re-emitted there) and nothing else.
//! An object whose second side has less than half the first's area has one side (an error),
//! as does one whose rim holds more than half the area (a box is no sheet). One object is one
//! sheet: a whole flower in one object would need its petals split into objects.
//!
//! ## Distances
//! Same side: g(i, j), the geodesic along the side, by Dijkstra over the side's patch
//! centroids, each linked to its joined neighbours and to theirs (the 2-ring) by the straight
//! distance between centroids, with any-angle steps (Theta*): a patch v reached from u may
//! instead be reached in one straight chord from u's own anchor a (the start of u's last
//! straight step), g(a) + |c_a − c_v|, when the sheet is flat between them — normals within
//! 10° — and a is within 5 patch sizes. Every path is a chain of chords, so
//! g(i, j) ≥ |c_i − c_j| always. Plain centroid-graph Dijkstra overestimates by the zig-zag
//! of the chain, badly on elongated patches (measured on a flat sheet: mean +0.8%, worst +2%
//! with right-isosceles patches; +5% / +12% with the flower's 3.7 : 1 patches, +11% / +22% at
//! 8 : 1); the any-angle steps bring that to < 0.2% mean, ~2% worst. On a curved sheet the
//! chords cut the arc by θ²/24 relative, θ ≤ 10° the turn of one chord (< 0.13%). The
//! search from i and the one from j can differ a little; g(i, j) is the shorter (symmetric).
//! Truncated at the radius. The 5-patch reach bounds how far a chord can cut across a notch
//! in the outline (no line-of-sight test is made).
//!
//! Other side: ô(j) is the patch of the other side nearest to j (by centroid distance), the
//! point "opposite" j. Light entering at i crosses the sheet and travels laterally; that
//! distance is the geodesic on i's side to the point opposite j, or on j's side from the point
//! opposite i, whichever is shorter (which makes it symmetric):
//!
//! ```text
//!   r_T(i, j) = min(g(i, ô(j)), g(ô(i), j)),   g(k, k) = 0,  so  r_T(i, ô(i)) = 0.
//! ```
//!
//! ## S
//! ```text
//!   same side:   S_ji = (1/A_j) ∫_Aj ∫_Ai R(r) dA_i dA_j      (S_ii: R over A_i itself)
//!   other side:  S_ji = (1/A_j) ∫_Aj ∫_Ai T(ℓ) dA_i dA_j      (ℓ the lateral distance)
//! ```
//! Far pairs (r ≥ `near_factor` × the larger patch edge): S_ji = A_i R(r) or A_i T(r). Near
//! pairs: j is projected onto i's plane, y′ = y − n_i ((y − c_i)·n_i), and since the
//! projection is affine the mean of the profile over j is its mean over the projected j′:
//! S_ji = A_i · mean_{x ∈ A_i} (1/A_j′) ∫_j′ P(|x − y′|) dA_y′, integrated in polar
//! coordinates around x exactly in r (subsurface.rs's quadrature). For two patches of one
//! plane this *is* subsurface.rs's coplanar quadrature; across the sheet the projection drops
//! the thickness, since T — as measured through a slab — is a function of the lateral
//! distance. j tilted more than 60° from i's plane (projected area < A_j / 2) falls back to
//! the far formula. The self term uses R only. Energy: Σ_j A_j S_ji ≤ A_i per column and
//! channel, R and T together, enforced and reported as in subsurface.rs.

use std::cmp::Ordering;
use std::collections::{BinaryHeap, HashMap};

use glam::Vec3;
use rayon::prelude::*;

pub use translux_engine::sheet::{KIND_OPPOSITE, KIND_SAME, SIDE_ANGLE_DEG, SheetError};
use translux_engine::subsurface::ObjectPatches;

/// The second side must hold at least this fraction of the first side's area.
const MIN_SIDE_RATIO: f64 = 0.5;
/// The rim may hold at most this fraction of the object's area.
const MAX_RIM_FRACTION: f64 = 0.5;

/// Which face of a sheet a patch lies on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    /// The larger of the two sides.
    First,
    Second,
    /// Neither: a side wall (or anything at a sharp angle to both faces).
    Rim,
}

/// The sides of a sheet's patches.
#[derive(Debug, Clone, PartialEq)]
pub struct Sides {
    pub side: Vec<Side>,
    /// Areas of the first side, the second side and the rim (scene units²).
    pub area: [f64; 3],
    /// The joined neighbours of each side patch (touching, same side, normals within
    /// [`SIDE_ANGLE_DEG`]), sorted: the graph geodesics start from. Empty for rim patches.
    pub neighbours: Vec<Vec<u32>>,
}

fn longest_edge(c: &[Vec3; 3]) -> f32 {
    (c[1] - c[0])
        .length()
        .max((c[2] - c[1]).length())
        .max((c[0] - c[2]).length())
}

/// For every patch, the patches touching it (sharing a welded corner, or a corner of one
/// inside an edge of the other), sorted, itself left out.
pub fn touching(corners: &[[Vec3; 3]]) -> Vec<Vec<u32>> {
    let n = corners.len();
    let (points, ids, eps) = crate::patch::weld(corners);
    let mut around: Vec<Vec<u32>> = vec![Vec::new(); points.len()];
    for (k, c) in ids.iter().enumerate() {
        for &p in c {
            around[p as usize].push(k as u32);
        }
    }
    let mut adj: Vec<Vec<u32>> = vec![Vec::new(); n];
    // Shared corners.
    for list in &around {
        for &a in list {
            adj[a as usize].extend(list.iter().copied().filter(|&b| b != a));
        }
    }
    // T-junctions: a point strictly inside edge (a, b), within tol of the segment. Points are
    // found through a grid whose cell is the median patch size.
    let mut sizes: Vec<f32> = corners.iter().map(longest_edge).collect();
    if !sizes.is_empty() {
        let mid = sizes.len() / 2;
        let cell = sizes
            .select_nth_unstable_by(mid, f32::total_cmp)
            .1
            .max(16.0 * eps);
        let key = |v: Vec3| {
            let q = (v / cell).floor();
            [q.x as i64, q.y as i64, q.z as i64]
        };
        let mut grid: HashMap<[i64; 3], Vec<u32>> = HashMap::new();
        for (id, p) in points.iter().enumerate() {
            grid.entry(key(*p)).or_default().push(id as u32);
        }
        for (k, c) in ids.iter().enumerate() {
            for e in 0..3 {
                let (ia, ib) = (c[e], c[(e + 1) % 3]);
                let (a, b) = (points[ia as usize], points[ib as usize]);
                let len2 = (b - a).length_squared();
                if len2 <= 0.0 {
                    continue;
                }
                let tol = 4.0 * eps + 1e-5 * len2.sqrt();
                let (klo, khi) = (key(a.min(b) - tol), key(a.max(b) + tol));
                for x in klo[0]..=khi[0] {
                    for y in klo[1]..=khi[1] {
                        for z in klo[2]..=khi[2] {
                            for &p in grid.get(&[x, y, z]).into_iter().flatten() {
                                if c.contains(&p) {
                                    continue;
                                }
                                let v = points[p as usize];
                                // Foot of the perpendicular: a + t(b − a),
                                // t = (v − a)·(b − a) / |b − a|².
                                let t = (v - a).dot(b - a) / len2;
                                if t <= 0.0 || t >= 1.0 || (a + (b - a) * t).distance(v) > tol {
                                    continue;
                                }
                                for &q in &around[p as usize] {
                                    adj[k].push(q);
                                    adj[q as usize].push(k as u32);
                                }
                            }
                        }
                    }
                }
            }
        }
    }
    for (k, a) in adj.iter_mut().enumerate() {
        a.retain(|&q| q as usize != k);
        a.sort_unstable();
        a.dedup();
    }
    adj
}

/// Splits an object's patches into its two sides and the rim (see the module docs).
pub fn classify(name: &str, p: &ObjectPatches<'_>) -> Result<Sides, SheetError> {
    let n = p.area.len();
    let cos_max = SIDE_ANGLE_DEG.to_radians().cos();
    // Joined: touching, normals within the angle.
    let joined: Vec<Vec<u32>> = touching(p.corners)
        .into_iter()
        .enumerate()
        .map(|(i, t)| {
            t.into_iter()
                .filter(|&k| p.normal[i].dot(p.normal[k as usize]) >= cos_max)
                .collect()
        })
        .collect();
    // Components by union–find (path halving).
    let mut parent: Vec<u32> = (0..n as u32).collect();
    fn root(parent: &mut [u32], mut x: u32) -> u32 {
        while parent[x as usize] != x {
            parent[x as usize] = parent[parent[x as usize] as usize];
            x = parent[x as usize];
        }
        x
    }
    for (i, ks) in joined.iter().enumerate() {
        for &k in ks {
            let (a, b) = (root(&mut parent, i as u32), root(&mut parent, k));
            if a != b {
                parent[a.max(b) as usize] = a.min(b);
            }
        }
    }
    let roots: Vec<u32> = (0..n as u32).map(|i| root(&mut parent, i)).collect();
    let mut area: HashMap<u32, f64> = HashMap::new();
    for (i, &r) in roots.iter().enumerate() {
        *area.entry(r).or_default() += f64::from(p.area[i]);
    }
    // Largest first; ties by the lowest patch index (the root), so the order is stable.
    let mut order: Vec<(u32, f64)> = area.into_iter().collect();
    order.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    let total: f64 = p.area.iter().map(|&a| f64::from(a)).sum();
    let first = order.first().copied().unwrap_or((u32::MAX, 0.0));
    let second = order.get(1).copied().unwrap_or((u32::MAX, 0.0));
    if first.1 <= 0.0 || second.1 < MIN_SIDE_RATIO * first.1 {
        return Err(SheetError::OneSide {
            object: name.to_string(),
            first: first.1,
            second: second.1,
        });
    }
    if first.1 + second.1 < (1.0 - MAX_RIM_FRACTION) * total {
        return Err(SheetError::MostlyRim {
            object: name.to_string(),
            percent: 100.0 * (first.1 + second.1) / total,
        });
    }
    let side: Vec<Side> = roots
        .iter()
        .map(|&r| match r {
            r if r == first.0 => Side::First,
            r if r == second.0 => Side::Second,
            _ => Side::Rim,
        })
        .collect();
    let neighbours = joined
        .into_iter()
        .enumerate()
        .map(|(i, ks)| if side[i] == Side::Rim { Vec::new() } else { ks })
        .collect();
    Ok(Sides {
        side,
        area: [first.1, second.1, total - first.1 - second.1],
        neighbours,
    })
}

/// A heap entry ordered so that `BinaryHeap` pops the smallest distance first.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Item {
    d: f32,
    node: u32,
}
impl Eq for Item {}
impl Ord for Item {
    fn cmp(&self, o: &Self) -> Ordering {
        o.d.total_cmp(&self.d).then_with(|| o.node.cmp(&self.node))
    }
}
impl PartialOrd for Item {
    fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
        Some(self.cmp(o))
    }
}

/// Straight "any-angle" steps are taken only between patches whose normals are within this
/// angle (the sheet is flat enough between them for the chord to be the geodesic).
const ANCHOR_CONE_DEG: f32 = 10.0;
/// ... and no longer than this many times the larger patch's longest edge (a bound on how far
/// a chord may cut across a notch in the sheet's outline).
const ANCHOR_REACH: f32 = 5.0;

/// Geodesic distances g(i, j) within each side (see the module docs): row i lists the
/// patches j ≠ i of i's side with g ≤ `radius`, sorted by j. Rim rows are empty. Symmetric:
/// the any-angle search from i and from j can end a little differently, and g(i, j) is the
/// shorter of the two (both are chains of chords, so both bound the Euclidean distance).
pub fn geodesics(sides: &Sides, p: &ObjectPatches<'_>, radius: f32) -> Vec<Vec<(u32, f32)>> {
    let n = sides.side.len();
    let (centroid, normal, size) = (p.centroid, p.normal, p.size);
    // The 2-ring graph: joined neighbours and theirs, weighted by centroid distance.
    let graph: Vec<Vec<(u32, f32)>> = (0..n)
        .into_par_iter()
        .map(|i| {
            let ring1 = &sides.neighbours[i];
            let mut ring: Vec<u32> = ring1.clone();
            for &k in ring1 {
                ring.extend_from_slice(&sides.neighbours[k as usize]);
            }
            ring.retain(|&k| k as usize != i);
            ring.sort_unstable();
            ring.dedup();
            ring.into_iter()
                .map(|k| (k, centroid[i].distance(centroid[k as usize])))
                .collect()
        })
        .collect();
    let cos_cone = ANCHOR_CONE_DEG.to_radians().cos();
    // Dijkstra from every side patch, stopped at the radius, with any-angle steps (Theta*):
    // each reached patch remembers the anchor its last straight step started from, and a
    // neighbour v of u is reached straight from u's anchor a, g(a) + |c_a − c_v|, where the
    // sheet is flat and a is near enough — never longer than going through u, by the triangle
    // inequality. Scratch arrays are reset through the list of touched patches.
    let rows: Vec<Vec<(u32, f32)>> = (0..n)
        .into_par_iter()
        .map_init(
            || {
                let dist = vec![f32::INFINITY; n];
                (dist, vec![0u32; n], Vec::<u32>::new(), BinaryHeap::new())
            },
            |(dist, anchor, touched, heap), src| {
                if sides.side[src] == Side::Rim {
                    return Vec::new();
                }
                dist[src] = 0.0;
                anchor[src] = src as u32;
                touched.push(src as u32);
                heap.push(Item {
                    d: 0.0,
                    node: src as u32,
                });
                while let Some(Item { d, node }) = heap.pop() {
                    let u = node as usize;
                    if d > dist[u] {
                        continue;
                    }
                    let a = anchor[u] as usize;
                    for &(k, w) in &graph[u] {
                        let v = k as usize;
                        let chord = centroid[a].distance(centroid[v]);
                        let straight = a != u
                            && normal[a].dot(normal[v]) >= cos_cone
                            && chord <= ANCHOR_REACH * size[a].max(size[v]);
                        let (nd, na) = if straight {
                            (dist[a] + chord, a as u32)
                        } else {
                            (d + w, node)
                        };
                        if nd <= radius && nd < dist[v] {
                            if dist[v] == f32::INFINITY {
                                touched.push(k);
                            }
                            dist[v] = nd;
                            anchor[v] = na;
                            heap.push(Item { d: nd, node: k });
                        }
                    }
                }
                let mut row: Vec<(u32, f32)> = touched
                    .iter()
                    .filter(|&&k| k as usize != src)
                    .map(|&k| (k, dist[k as usize]))
                    .collect();
                row.sort_unstable_by_key(|e| e.0);
                for &k in touched.iter() {
                    dist[k as usize] = f32::INFINITY;
                }
                touched.clear();
                row
            },
        )
        .collect();
    // Symmetrise: g(i, j) = min of the two searches. The transpose's rows come out sorted.
    let mut transpose: Vec<Vec<(u32, f32)>> = vec![Vec::new(); n];
    for (i, row) in rows.iter().enumerate() {
        for &(j, d) in row {
            transpose[j as usize].push((i as u32, d));
        }
    }
    rows.into_par_iter()
        .zip(transpose)
        .map(|(a, b)| {
            let mut out = Vec::with_capacity(a.len().max(b.len()));
            let (mut x, mut y) = (a.into_iter().peekable(), b.into_iter().peekable());
            loop {
                let next = match (x.peek(), y.peek()) {
                    (Some(&p), Some(&q)) => match p.0.cmp(&q.0) {
                        Ordering::Less => x.next(),
                        Ordering::Greater => y.next(),
                        Ordering::Equal => {
                            y.next();
                            x.next().map(|e| (e.0, e.1.min(q.1)))
                        }
                    },
                    (Some(_), None) => x.next(),
                    (None, _) => y.next(),
                };
                match next {
                    Some(e) => out.push(e),
                    None => break out,
                }
            }
        })
        .collect()
}

/// Points of one side in a uniform grid, for nearest-point queries.
struct PointGrid {
    cell: f32,
    lo: [i64; 3],
    hi: [i64; 3],
    map: HashMap<[i64; 3], Vec<u32>>,
}

impl PointGrid {
    fn key(cell: f32, v: Vec3) -> [i64; 3] {
        let q = (v / cell).floor();
        [q.x as i64, q.y as i64, q.z as i64]
    }

    fn new(points: &[Vec3], ids: &[u32], cell: f32) -> Self {
        let mut g = PointGrid {
            cell,
            lo: [i64::MAX; 3],
            hi: [i64::MIN; 3],
            map: HashMap::new(),
        };
        for &id in ids {
            let k = Self::key(cell, points[id as usize]);
            g.lo = std::array::from_fn(|a| g.lo[a].min(k[a]));
            g.hi = std::array::from_fn(|a| g.hi[a].max(k[a]));
            g.map.entry(k).or_default().push(id);
        }
        g
    }

    /// The nearest point to `q`: shells of cells at Chebyshev distance r = 0, 1, … around
    /// q's cell; a point in an unvisited shell is at least r·cell away, so the search stops
    /// once the best distance is within that.
    fn nearest(&self, points: &[Vec3], q: Vec3) -> Option<u32> {
        let k = Self::key(self.cell, q);
        let reach = (0..3)
            .map(|a| (k[a] - self.lo[a]).abs().max((self.hi[a] - k[a]).abs()))
            .max()?;
        let mut best: Option<(f32, u32)> = None;
        for r in 0..=reach {
            let range = |a: usize| (-r).max(self.lo[a] - k[a])..=r.min(self.hi[a] - k[a]);
            for dx in range(0) {
                for dy in range(1) {
                    for dz in range(2) {
                        if dx.abs().max(dy.abs()).max(dz.abs()) != r {
                            continue;
                        }
                        let cell = [k[0] + dx, k[1] + dy, k[2] + dz];
                        for &id in self.map.get(&cell).into_iter().flatten() {
                            let d = points[id as usize].distance(q);
                            if best.is_none_or(|(bd, bid)| (d, id) < (bd, bid)) {
                                best = Some((d, id));
                            }
                        }
                    }
                }
            }
            if let Some((d, _)) = best
                && d <= r as f32 * self.cell
            {
                break;
            }
        }
        best.map(|b| b.1)
    }
}

/// ô: for every side patch, the nearest patch of the other side by centroid distance; `None`
/// for rim patches.
pub fn opposite(sides: &Sides, centroid: &[Vec3], size: &[f32]) -> Vec<Option<u32>> {
    let of = |s: Side| -> Vec<u32> {
        (0..sides.side.len() as u32)
            .filter(|&i| sides.side[i as usize] == s)
            .collect()
    };
    let grid = |ids: &[u32]| {
        let mean = ids.iter().map(|&i| size[i as usize]).sum::<f32>() / ids.len().max(1) as f32;
        PointGrid::new(centroid, ids, mean.max(f32::MIN_POSITIVE))
    };
    let (first, second) = (of(Side::First), of(Side::Second));
    let (g_first, g_second) = (grid(&first), grid(&second));
    (0..sides.side.len())
        .into_par_iter()
        .map(|i| match sides.side[i] {
            Side::First => g_second.nearest(centroid, centroid[i]),
            Side::Second => g_first.nearest(centroid, centroid[i]),
            Side::Rim => None,
        })
        .collect()
}

/// Per source patch i (local indices): (j, r_ij, kind) for every j ≠ i within the radius,
/// sorted by j; kind is [`KIND_SAME`] or [`KIND_OPPOSITE`].
pub type SheetRows = Vec<Vec<(u32, f32, u32)>>;

/// A sheet's distances (local indices).
#[derive(Debug, Clone, PartialEq)]
pub struct SheetDistances {
    pub sides: Sides,
    /// ô(i): the nearest patch of the other side, `None` on the rim.
    pub opposite: Vec<Option<u32>>,
    /// Row i: (j, r_ij, kind) for every j ≠ i within the radius, sorted by j. Rim rows are
    /// empty.
    pub rows: SheetRows,
    /// Median over side patches of |c_i − c_ô(i)|: how far apart the faces are as meshed
    /// (scene units).
    pub separation: f32,
}

/// Sides and distances of one thin-sheet object, truncated at `radius` (scene units).
/// `name` names the object in errors.
pub fn sheet_distances(
    name: &str,
    p: ObjectPatches<'_>,
    radius: f32,
) -> Result<SheetDistances, SheetError> {
    let n = p.area.len();
    let sides = classify(name, &p)?;
    let same = geodesics(&sides, &p, radius);
    let opp = opposite(&sides, p.centroid, p.size);
    // ô⁻¹(k): the patches of the other side whose opposite is k.
    let mut seen_from: Vec<Vec<u32>> = vec![Vec::new(); n];
    for (j, o) in opp.iter().enumerate() {
        if let Some(k) = o {
            seen_from[*k as usize].push(j as u32);
        }
    }
    let rows: SheetRows = (0..n)
        .into_par_iter()
        .map_init(
            || (vec![f32::INFINITY; n], Vec::<u32>::new()),
            |(cand, touched), i| {
                let Some(oi) = opp[i] else {
                    return Vec::new();
                };
                let mut row: Vec<(u32, f32, u32)> =
                    same[i].iter().map(|&(j, d)| (j, d, KIND_SAME)).collect();
                // r_T(i, j) = min(g(i, ô(j)), g(ô(i), j)), with g(k, k) = 0.
                let mut relax = |j: u32, d: f32| {
                    if d < cand[j as usize] {
                        if cand[j as usize] == f32::INFINITY {
                            touched.push(j);
                        }
                        cand[j as usize] = d;
                    }
                };
                for &(k, d) in std::iter::once(&(i as u32, 0.0)).chain(&same[i]) {
                    for &j in &seen_from[k as usize] {
                        relax(j, d);
                    }
                }
                for &(j, d) in std::iter::once(&(oi, 0.0)).chain(&same[oi as usize]) {
                    relax(j, d);
                }
                for &j in touched.iter() {
                    if cand[j as usize] <= radius {
                        row.push((j, cand[j as usize], KIND_OPPOSITE));
                    }
                    cand[j as usize] = f32::INFINITY;
                }
                touched.clear();
                row.sort_unstable_by_key(|e| e.0);
                row
            },
        )
        .collect();
    let mut gaps: Vec<f32> = opp
        .iter()
        .enumerate()
        .filter_map(|(i, o)| o.map(|k| p.centroid[i].distance(p.centroid[k as usize])))
        .collect();
    let separation = if gaps.is_empty() {
        0.0
    } else {
        let mid = gaps.len() / 2;
        *gaps.select_nth_unstable_by(mid, f32::total_cmp).1
    };
    Ok(SheetDistances {
        sides,
        opposite: opp,
        rows,
        separation,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::patch;
    use crate::shapes::shape_triangles;
    use translux_engine::profile::ProfileEval;
    use translux_engine::sheet::assemble;
    use translux_engine::subsurface::{ObjectS, SubsurfaceParams, Tabulated};
    use translux_proto::csr::CsrView;
    use translux_proto::scene::Profile;
    use translux_proto::scene::{ExpTerm, Shape};

    /// Patches of one object, owned.
    struct Owned {
        corners: Vec<[Vec3; 3]>,
        centroid: Vec<Vec3>,
        normal: Vec<Vec3>,
        area: Vec<f32>,
        size: Vec<f32>,
    }

    impl Owned {
        fn view(&self) -> ObjectPatches<'_> {
            ObjectPatches {
                corners: &self.corners,
                centroid: &self.centroid,
                normal: &self.normal,
                area: &self.area,
                size: &self.size,
            }
        }
    }

    /// `shape` split into patches of edge ≤ `h` (the pipeline's own subdivision).
    fn patches(shape: &Shape, h: f32) -> Owned {
        let tris = shape_triangles(shape);
        let p = patch::subdivide(&[tris.as_slice()], h);
        Owned {
            corners: p.corners,
            centroid: p.centroid,
            normal: p.normal,
            area: p.area,
            size: p.size,
        }
    }

    /// A petal in a millimetre scene: `length` × `width` × `thickness`, curled by `curl`,
    /// in patches of edge ≤ `h`: segments about as long as the sheet is wide (the split keeps
    /// the triangles' shape), and short enough to turn by ≤ 0.2 rad each.
    fn sheet(length: f32, width: f32, thickness: f32, curl: f32, h: f32) -> Owned {
        let segments = ((length / width).round() as u32)
            .max((curl.abs() / 0.2).ceil() as u32)
            .max(1);
        patches(
            &Shape::Sheet {
                length,
                width,
                thickness,
                curl,
                segments: Some(segments),
            },
            h,
        )
    }

    /// R(r) = Σ a e^(−b r) with total `rd` per channel: a = rd b² / 2π.
    fn exp_profile(rd: [f32; 3], b: f32) -> Profile {
        Profile::Exponentials {
            terms: vec![ExpTerm {
                a: rd.map(|x| x * b * b / std::f32::consts::TAU),
                b: [b; 3],
            }],
        }
    }

    /// Sides, distances and S of a sheet in a mm scene.
    fn build(o: &Owned, r: &Profile, t: &Profile) -> (SheetDistances, ObjectS) {
        let (er, et) = (
            ProfileEval::new(r, 1.0).unwrap(),
            ProfileEval::new(t, 1.0).unwrap(),
        );
        let (rr, rt) = (er.truncation_radius(1e-4), et.truncation_radius(1e-4));
        let sd = sheet_distances("petal", o.view(), rr.max(rt)).unwrap();
        let mut row_ptr = vec![0u64];
        let (mut col, mut dist, mut kind) = (Vec::new(), Vec::new(), Vec::new());
        for row in &sd.rows {
            for &(j, d, k) in row {
                col.push(j);
                dist.push(d);
                kind.push(k);
            }
            row_ptr.push(col.len() as u64);
        }
        let n = o.area.len();
        let dv = CsrView::new_checked(n, n, &row_ptr, &col, &dist).unwrap();
        let (tr, tt) = (Tabulated::new(&er, rr, 4096), Tabulated::new(&et, rt, 4096));
        let s = assemble(o.view(), dv, &kind, &tr, &tt, &SubsurfaceParams::default());
        (sd, s)
    }

    /// B = S E (exitance per unit irradiance, channel `c`).
    fn apply(s: &ObjectS, e: &[f32], c: usize) -> Vec<f32> {
        s.rows
            .iter()
            .map(|row| row.iter().map(|&(i, v)| v[c] * e[i as usize]).sum())
            .collect()
    }

    #[test]
    fn a_sheet_has_two_equal_sides_and_a_small_rim() {
        let (l, w, t) = (60.0, 30.0, 1.0);
        for curl in [0.0f32, 2.0] {
            let o = sheet(l, w, t, curl, 2.5);
            let s = classify("petal", &o.view()).unwrap();
            let [a1, a2, rim] = s.area;
            // Front and back are offsets of the mid-surface at ∓t/2: L(1 ∓ κt/2) W, equal
            // within κt/2 = curl·t/(2L) relative.
            let face = f64::from(l * w);
            let tol = 0.005 + f64::from(curl * t / (2.0 * l));
            assert!(
                (a1 - face).abs() / face < tol,
                "curl {curl}: {a1} vs {face}"
            );
            assert!(
                (a2 - face).abs() / face < tol,
                "curl {curl}: {a2} vs {face}"
            );
            // The rim is the four walls: 2 L t + 2 W t.
            let walls = f64::from(2.0 * l * t + 2.0 * w * t);
            assert!((rim - walls).abs() / walls < 0.01, "curl {curl}: rim {rim}");
            assert!(rim < 0.06 * (a1 + a2));
            // Each side faces one way: at the base the first side's normals all agree, and
            // the second side's are their opposite.
            let base = |sd: Side| {
                (0..o.area.len())
                    .filter(|&i| s.side[i] == sd && o.centroid[i].z < 2.0)
                    .map(|i| o.normal[i])
                    .collect::<Vec<_>>()
            };
            let (n1, n2) = (base(Side::First), base(Side::Second));
            assert!(!n1.is_empty() && !n2.is_empty());
            assert!(n1.iter().all(|n| n.dot(n1[0]) > 0.99));
            assert!(n2.iter().all(|n| n.dot(n1[0]) < -0.99));
            // Rim patches are the walls: at 90° to the faces.
            for i in (0..o.area.len()).filter(|&i| s.side[i] == Side::Rim) {
                assert!(s.neighbours[i].is_empty());
            }
        }
    }

    #[test]
    fn one_sided_and_boxy_objects_are_refused() {
        let quad = patches(&Shape::Quad { size: [40.0, 30.0] }, 5.0);
        let e = classify("lone_quad", &quad.view()).unwrap_err();
        assert!(
            matches!(e, SheetError::OneSide { second: 0.0, .. }),
            "{e:?}"
        );
        let msg = e.to_string();
        assert!(
            msg.starts_with(
                "a thin-sheet material needs a two-sided mesh (front and back faces); object \
                 'lone_quad' has one side"
            ),
            "{msg}"
        );
        // sheet_distances refuses it the same way.
        let e = sheet_distances("lone_quad", quad.view(), 10.0).unwrap_err();
        assert!(e.to_string().contains("object 'lone_quad' has one side"));
        // A cube has six sides at 90°: two of them are no sheet.
        let cube = patches(
            &Shape::Box {
                size: [10.0; 3],
                inward: false,
            },
            2.0,
        );
        let e = classify("cube", &cube.view()).unwrap_err();
        assert!(
            e.to_string()
                .starts_with("object 'cube' is not a thin sheet"),
            "{e}"
        );
    }

    #[test]
    fn geodesics_on_a_flat_sheet_are_euclidean() {
        let o = sheet(60.0, 30.0, 1.0, 0.0, 2.0);
        let s = classify("petal", &o.view()).unwrap();
        let g = geodesics(&s, &o.view(), 25.0);
        let (mut worst, mut sum, mut count) = (0.0f32, 0.0f64, 0usize);
        for (i, row) in g.iter().enumerate() {
            assert_eq!(row.is_empty(), s.side[i] == Side::Rim);
            for &(j, d) in row {
                assert_eq!(s.side[j as usize], s.side[i], "a path left its side");
                let e = o.centroid[i].distance(o.centroid[j as usize]);
                // A chain of chords is never shorter than the straight line.
                assert!(d >= e * (1.0 - 1e-5), "{i}→{j}: {d} < {e}");
                if e > 6.0 {
                    worst = worst.max(d / e);
                    sum += f64::from(d / e);
                    count += 1;
                }
            }
        }
        let mean = sum / count as f64;
        eprintln!("flat sheet: geodesic / euclidean mean {mean:.4}, worst {worst:.4}");
        // What the chains of chords overestimate by.
        assert!(mean < 1.005, "{mean}");
        assert!(worst < 1.03, "{worst}");
        // Truncated at the radius: a side is 60 mm long, so no row holds all of it.
        assert!(g.iter().flatten().all(|&(_, d)| d <= 25.0));
        let side = (0..o.area.len())
            .filter(|&i| s.side[i] == Side::First)
            .count();
        assert!(g.iter().all(|row| row.len() < side));
    }

    #[test]
    fn geodesics_on_a_curled_sheet_follow_the_arc() {
        // Curled by 3 rad (172°): the tip comes round towards the base.
        let (l, curl, t) = (60.0f32, 3.0f32, 1.0f32);
        let o = sheet(l, 8.0, t, curl, 2.0);
        let s = classify("petal", &o.view()).unwrap();
        let g = geodesics(&s, &o.view(), f32::INFINITY);
        // The front (up-facing at the base) lies at radius R − t/2 about the centre of
        // curvature (0, R, 0), R = L / curl; a centroid's angle is atan2(z, R − y).
        let big_r = l / curl;
        let front = s.side[(0..o.area.len())
            .find(|&i| s.side[i] != Side::Rim && o.normal[i].y > 0.99 && o.centroid[i].z < 3.0)
            .unwrap()];
        let angle = |c: Vec3| c.z.atan2(big_r - c.y);
        let on_front: Vec<usize> = (0..o.area.len())
            .filter(|&i| s.side[i] == front && o.centroid[i].x.abs() < 1.0)
            .collect();
        let base = *on_front
            .iter()
            .min_by(|&&a, &&b| angle(o.centroid[a]).total_cmp(&angle(o.centroid[b])))
            .unwrap();
        let tip = *on_front
            .iter()
            .max_by(|&&a, &&b| angle(o.centroid[a]).total_cmp(&angle(o.centroid[b])))
            .unwrap();
        let (cb, ct) = (o.centroid[base], o.centroid[tip]);
        let d = g[base]
            .iter()
            .find(|e| e.0 as usize == tip)
            .map(|e| e.1)
            .unwrap();
        // Geodesic on the cylinder of radius ρ (the centroids sit a hair inside the arc):
        // √((ρ Δθ)² + Δx²).
        let rho = 0.5 * (cb - Vec3::new(0.0, big_r, 0.0)).length()
            + 0.5 * (ct - Vec3::new(0.0, big_r, 0.0)).length();
        let expected = ((rho * (angle(ct) - angle(cb))).powi(2) + (ct.x - cb.x).powi(2)).sqrt();
        let chord = cb.distance(ct);
        eprintln!("curled sheet: geodesic {d:.3}, arc {expected:.3}, chord {chord:.3}");
        assert!(d > 1.4 * chord, "{d} vs chord {chord}");
        assert!((d - expected).abs() / expected < 0.03, "{d} vs {expected}");
    }

    #[test]
    fn opposite_patches_face_each_other_across_the_thickness() {
        let o = sheet(40.0, 20.0, 1.0, 1.0, 2.5);
        let sd = sheet_distances("petal", o.view(), 10.0).unwrap();
        assert!((sd.separation - 1.0).abs() < 0.05, "{}", sd.separation);
        for (i, op) in sd.opposite.iter().enumerate() {
            let Some(k) = *op else {
                assert_eq!(sd.sides.side[i], Side::Rim);
                assert!(sd.rows[i].is_empty());
                continue;
            };
            let k = k as usize;
            assert!(sd.sides.side[k] != sd.sides.side[i] && sd.sides.side[k] != Side::Rim);
            assert!(o.normal[i].dot(o.normal[k]) < -0.99);
            // The pair i ↔ ô(i) is stored at lateral distance 0, as "other side".
            let e = sd.rows[i].iter().find(|e| e.0 as usize == k).unwrap();
            assert_eq!((e.1, e.2), (0.0, KIND_OPPOSITE));
            // Kinds follow the sides; rows are sorted.
            for &(j, _, kind) in &sd.rows[i] {
                let same = sd.sides.side[j as usize] == sd.sides.side[i];
                assert_eq!(kind, if same { KIND_SAME } else { KIND_OPPOSITE });
            }
            assert!(sd.rows[i].windows(2).all(|w| w[0].0 < w[1].0));
        }
        // Symmetric by construction: r_T(i, j) = r_T(j, i).
        for (i, row) in sd.rows.iter().enumerate() {
            for &(j, d, kind) in row.iter().filter(|e| e.2 == KIND_OPPOSITE) {
                let back = sd.rows[j as usize]
                    .iter()
                    .find(|e| e.0 as usize == i)
                    .unwrap();
                assert_eq!((back.1, back.2), (d, kind));
            }
        }
    }

    #[test]
    fn a_sheet_lit_on_one_side_glows_on_the_other() {
        // 30 × 30 mm, 1 mm thick, 2.5 mm patches; R and T fall off over a few mm (both carry
        // all but 1e-4 of their energy within 10 mm).
        let o = sheet(30.0, 30.0, 1.0, 0.0, 2.5);
        let (rd, td) = ([0.45, 0.3, 0.2], [0.35, 0.25, 0.1]);
        let r = exp_profile(rd, 1.5);
        let (sd, s) = build(&o, &r, &exp_profile(td, 1.2));
        // Light the first side only, uniformly: E = 1 there.
        let lit: Vec<f32> = sd
            .sides
            .side
            .iter()
            .map(|&sd| if sd == Side::First { 1.0 } else { 0.0 })
            .collect();
        // Away from the edges, the lit side re-emits Rd and the dark side glows with Td.
        let centre = |i: usize| {
            let c = o.centroid[i];
            c.x.abs() < 4.0 && (c.z - 15.0).abs() < 4.0
        };
        let mut seen = [0; 2];
        for c in 0..3 {
            let b = apply(&s, &lit, c);
            for i in (0..b.len()).filter(|&i| centre(i)) {
                let (want, k) = match sd.sides.side[i] {
                    Side::First => (rd[c], 0),
                    Side::Second => (td[c], 1),
                    Side::Rim => unreachable!(),
                };
                seen[k] += 1;
                assert!(
                    (b[i] - want).abs() < 0.03 * want,
                    "patch {i} channel {c}: {} vs {want}",
                    b[i]
                );
            }
            // The rim receives nothing through the sheet.
            for i in (0..b.len()).filter(|&i| sd.sides.side[i] == Side::Rim) {
                assert_eq!(b[i], 0.0);
            }
        }
        assert!(seen[0] > 10 && seen[1] > 10, "{seen:?}");

        // A spot of light on the first side glows on the second side right behind it.
        let spot: Vec<f32> = (0..o.area.len())
            .map(|i| {
                let c = o.centroid[i];
                let hit = sd.sides.side[i] == Side::First && c.x.hypot(c.z - 15.0) < 3.0;
                if hit { 1.0 } else { 0.0 }
            })
            .collect();
        let b = apply(&s, &spot, 0);
        let back = |i: usize| sd.sides.side[i] == Side::Second;
        let behind = (0..b.len())
            .filter(|&i| back(i) && o.centroid[i].x.hypot(o.centroid[i].z - 15.0) < 2.0)
            .map(|i| b[i])
            .fold(f32::INFINITY, f32::min);
        let far = (0..b.len())
            .filter(|&i| back(i) && o.centroid[i].x.hypot(o.centroid[i].z - 15.0) > 10.0)
            .map(|i| b[i])
            .fold(0.0f32, f32::max);
        assert!(behind > 0.1 && far < 0.01 * behind, "{behind} vs {far}");

        // With (nearly) no transmittance the other side stays dark.
        let (sd, s) = build(&o, &r, &exp_profile([1e-9; 3], 1.2));
        let b = apply(&s, &lit, 0);
        for i in (0..b.len()).filter(|&i| sd.sides.side[i] == Side::Second) {
            assert!(b[i] < 1e-6, "patch {i}: {}", b[i]);
        }
        // ... while the lit side still reflects.
        let first: Vec<usize> = (0..b.len())
            .filter(|&i| centre(i) && lit[i] > 0.0)
            .collect();
        assert!(first.iter().all(|&i| (b[i] - rd[0]).abs() < 0.03 * rd[0]));
    }

    /// Σ_j A_j S_ji / A_i per column and channel, from the rows.
    fn column_totals(o: &Owned, s: &ObjectS) -> Vec<[f32; 3]> {
        let mut t = vec![[0.0f32; 3]; o.area.len()];
        for (j, row) in s.rows.iter().enumerate() {
            for &(i, v) in row {
                for c in 0..3 {
                    t[i as usize][c] += o.area[j] * v[c] / o.area[i as usize];
                }
            }
        }
        t
    }

    #[test]
    fn every_column_keeps_the_energy_bound() {
        // R + T = 0.95 in the first channel: quadrature alone must not exceed 1 anywhere,
        // flat or curled.
        let (r, t) = (
            exp_profile([0.55, 0.4, 0.3], 1.0),
            exp_profile([0.4, 0.3, 0.2], 0.7),
        );
        for curl in [0.0f32, 2.5] {
            let o = sheet(30.0, 10.0, 1.0, curl, 2.0);
            let (_, s) = build(&o, &r, &t);
            let totals = column_totals(&o, &s);
            let worst = totals.iter().flatten().cloned().fold(0.0f32, f32::max);
            eprintln!(
                "curl {curl}: worst column {worst:.4}, report {:?}",
                s.report
            );
            assert!(worst <= 0.96, "curl {curl}: {worst}");
            assert_eq!(s.report.scaled_columns, 0, "{:?}", s.report);
            assert!((s.report.max_column - worst).abs() < 1e-4);
        }
        // An unphysical pair (R + T = 1.5) is scaled down to the bound, and reported.
        let o = sheet(30.0, 10.0, 1.0, 0.0, 2.0);
        let (_, s) = build(&o, &exp_profile([0.8; 3], 1.0), &exp_profile([0.7; 3], 1.0));
        assert!(
            s.report.scaled_columns > 0 && s.report.max_column > 1.3,
            "{:?}",
            s.report
        );
        let totals = column_totals(&o, &s);
        assert!(totals.iter().flatten().all(|&v| v <= 1.0 + 1e-4));
    }

    #[test]
    fn the_flower_bundle_stores_sides_and_rebuilds_s_from_them() {
        use crate::pipeline::{PrecomputeParams, precompute};
        use translux_engine::smatrix::{self, SParams};
        use translux_proto::bundle::Bundle;
        use translux_proto::scene::Material;

        let scene = crate::scene::load_scene("builtin:flower").unwrap();
        let dir = tempfile::tempdir().unwrap();
        let params = PrecomputeParams {
            patches: Some(1500),
            ..Default::default()
        };
        let report = precompute(&scene, dir.path(), &params).unwrap();
        assert_eq!(report.subsurface.objects.len(), 8);
        let b = Bundle::open(dir.path()).unwrap();
        let m = b.manifest();
        // Every stored distance has a kind, both kinds occur, and each petal's pairs stay in
        // the petal.
        let (d, kinds) = (b.distances(), b.distance_kinds());
        assert_eq!(kinds.len(), d.nnz());
        assert!(kinds.contains(&KIND_SAME) && kinds.contains(&KIND_OPPOSITE));
        for o in m.objects.iter().filter(|o| o.name.starts_with("petal")) {
            let r = o.first_patch as u32..(o.first_patch + o.patch_count) as u32;
            for i in r.clone() {
                assert!(d.row(i as usize).0.iter().all(|j| r.contains(j)));
            }
            assert!(matches!(o.material, Material::ThinSheet { .. }));
            // ρ of the opaque view: R + T.
            assert!((o.albedo[0] - 0.8).abs() < 0.01, "{:?}", o.albedo);
        }
        for so in &m.subsurface.objects {
            assert_eq!(so.method, "geodesic (thin sheet)");
            assert!(
                so.max_column_energy > 0.5 && so.max_column_energy < 0.81,
                "{so:?}"
            );
            assert_eq!(so.scaled_columns, 0);
        }
        // Stage 2 from the bundle alone reproduces the precompute's S (up to f32 rounding:
        // the rebuild re-derives normals from the stored corners, and an entry far out in a
        // profile's tail is a difference of two nearly equal W(ρ), hence the absolute 1e-9
        // against entries up to ~1e-2) ...
        let (s, reports) = smatrix::rebuild_from_bundle(&b, &[], &SParams::default()).unwrap();
        assert_eq!(reports.len(), 8);
        let stored = b.subsurface();
        assert_eq!(s.row_ptr, stored.row_ptr());
        assert_eq!(s.col, stored.col());
        for (x, y) in s.val.iter().zip(stored.val()) {
            for c in 0..3 {
                assert!(
                    (x[c] - y[c]).abs() <= 1e-4 * y[c].abs() + 1e-9,
                    "{x:?} vs {y:?}"
                );
            }
        }
        // ... and the transmittance can change without geometry work: with T ≈ 0 the petal's
        // columns lose their other-side share.
        let k = m.objects.iter().position(|o| o.name == "petal_0").unwrap();
        let Material::ThinSheet {
            reflectance,
            thickness_mm,
            ..
        } = m.objects[k].material.clone()
        else {
            panic!()
        };
        let dark = Material::ThinSheet {
            reflectance,
            transmittance: exp_profile([1e-9; 3], 1.0),
            thickness_mm,
            specular: None,
        };
        let (_, reports) =
            smatrix::rebuild_from_bundle(&b, &[(k, dark)], &SParams::default()).unwrap();
        let r = reports.iter().find(|r| r.name == "petal_0").unwrap();
        assert!(r.max_column_energy < 0.5, "{r:?}");
    }

    #[test]
    fn t_junctions_join_patches_split_differently() {
        // Two coplanar right triangles sharing the edge x = 1: one split in 1, one in 3 (a
        // regular split of a triangle with a longer edge). The small ones along the shared
        // edge touch the big one although they share no corner with it.
        let big = [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 1.0),
            Vec3::new(1.0, 0.0, 0.0),
        ];
        let small = [
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 1.0),
            Vec3::new(4.0, 0.0, 0.0),
        ];
        let mut corners = vec![big];
        let n = 3;
        let (a, e1, e2) = (
            small[0],
            (small[1] - small[0]) / n as f32,
            (small[2] - small[0]) / n as f32,
        );
        for i in 0..n {
            for j in 0..n - i {
                let at = |i: usize, j: usize| a + e1 * i as f32 + e2 * j as f32;
                corners.push([at(i, j), at(i + 1, j), at(i, j + 1)]);
                if i + j + 2 <= n {
                    corners.push([at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)]);
                }
            }
        }
        let t = touching(&corners);
        // Every small patch with a corner on x = 1 touches the big one (patch 0).
        for (k, c) in corners.iter().enumerate().skip(1) {
            let on_edge = c.iter().any(|v| (v.x - 1.0).abs() < 1e-6);
            assert_eq!(t[k].contains(&0), on_edge, "patch {k}: {c:?}");
            assert_eq!(t[0].contains(&(k as u32)), on_edge);
        }
    }
}
