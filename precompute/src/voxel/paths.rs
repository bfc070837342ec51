//! Shortest interior paths on the voxel grid: the chamfer metric, the truncated
//! 26-neighbour Dijkstra with per-medium lengths and its per-thread scratch, medium labels
//! by nearest entry voxel, and the voxel method's whole pass over an object.

use super::*;

/// The 26 neighbours of a voxel as (linear index offset, edge weight [`W`] by how many
/// axes the step moves along).
pub(super) fn neighbour_offsets(grid: &Grid) -> [(isize, u32); 26] {
    let [nx, ny, _] = grid.dims;
    let mut offsets = [(0isize, 0u32); 26];
    let mut m = 0;
    for dz in -1isize..=1 {
        for dy in -1isize..=1 {
            for dx in -1isize..=1 {
                let kind = (dx != 0) as usize + (dy != 0) as usize + (dz != 0) as usize;
                if kind > 0 {
                    offsets[m] = (dx + nx as isize * (dy + ny as isize * dz), W[kind - 1]);
                    m += 1;
                }
            }
        }
    }
    offsets
}

/// Free-space 26-neighbour length (×UNIT) of a voxel offset: with sorted |components|
/// a ≥ b ≥ c, (a − b)·W₁ + (b − c)·W₂ + c·W₃.
pub(super) fn chamfer(d: [i64; 3]) -> u64 {
    let mut s = d.map(|x| x.unsigned_abs());
    s.sort_unstable();
    let [c, b, a] = s;
    (a - b) * u64::from(W[0]) + (b - c) * u64::from(W[1]) + c * u64::from(W[2])
}

/// The graph length (×UNIT) from voxel `a` to voxel `b` when the interior holds a shortest
/// free-space path between them, `None` when the one tried leaves it. The one tried keeps
/// nearest the straight segment, built by nesting two Bresenham steppers: along the axes
/// sorted by |Δ| (p ≥ q ≥ r), each of its p steps moves along the first axis, q of them
/// also along the second and r of those also along the third: r corner, q − r edge and
/// p − q face steps, [`chamfer`]'s length exactly. No interior path is shorter than the
/// shortest path through all space, so a search would settle `b` at that length, bit for
/// bit. O(p) lookups, where a run of [`dijkstra_to`] settles the whole ball around `a`.
pub(super) fn straight_length(grid: &Grid, inside: &[bool], a: u32, b: u32) -> Option<u64> {
    let (ca, cb) = (grid.coords(a as usize), grid.coords(b as usize));
    let d = [cb[0] - ca[0], cb[1] - ca[1], cb[2] - ca[2]];
    let stride = [
        1i64,
        grid.dims[0] as i64,
        (grid.dims[0] * grid.dims[1]) as i64,
    ];
    let mut axes = [0usize, 1, 2].map(|k| (d[k].abs(), d[k].signum() * stride[k]));
    axes.sort_unstable_by_key(|x| std::cmp::Reverse(x.0));
    let [(np, sp), (nq, sq), (nr, sr)] = axes;
    // Started half way, so the path runs symmetrically about the segment.
    let (mut eq, mut er) = (np / 2, nq / 2);
    let mut v = i64::from(a);
    for _ in 0..np {
        v += sp;
        eq += nq;
        if eq >= np {
            eq -= np;
            v += sq;
            er += nr;
            if er >= nq {
                er -= nq;
                v += sr;
            }
        }
        if !inside[v as usize] {
            return None;
        }
    }
    debug_assert_eq!(v, i64::from(b));
    Some(chamfer(d))
}

/// Per-thread Dijkstra state. Between runs `dist` is NONE on interior voxels and 0 on the
/// rest, so "exterior" and "already as short" are one test (`ng >= dist`); a run resets what
/// it touched.
pub(super) struct Scratch {
    pub(super) dist: Vec<u32>,
    pub(super) touched: Vec<u32>,
    /// Dial's buckets of width W₁ (the smallest weight), used as a ring: an edge adds at most
    /// W₃ < 2 W₁, so from bucket k a relaxation lands in bucket k + 1 or k + 2, never in k —
    /// nodes within one bucket cannot improve each other, and 4 slots suffice.
    pub(super) buckets: [Vec<(u32, u32)>; 4],
    pub(super) reached: Vec<(u32, u32)>,
    pub(super) candidates: Vec<(u32, f32)>,
    // Per-medium tracking (heterogeneous objects only; empty otherwise).
    /// `slot[v]`: where voxel v sits in `touched` (and `mlen`) during a run; grid-sized,
    /// allocated on the first tracked run.
    pub(super) slot: Vec<u32>,
    /// Per-medium graph lengths g_k of `touched[k]`.
    pub(super) mlen: Vec<[u32; MEDIA]>,
    /// g_k of each `reached` entry.
    pub(super) reached_len: Vec<[u32; MEDIA]>,
    /// Media shares g_k / g of each candidate (`None`: split the straight segment instead).
    pub(super) cand_share: Vec<Option<MediaLen>>,
    /// `want[v]`: where voxel v sits in a [`dijkstra_to`] run's target list (NONE when it is
    /// not a target); grid-sized, allocated on the first such run.
    pub(super) want: Vec<u32>,
}

impl Scratch {
    pub(super) fn new(inside: &[bool]) -> Self {
        Scratch {
            dist: inside.iter().map(|&b| if b { NONE } else { 0 }).collect(),
            touched: Vec::new(),
            buckets: Default::default(),
            reached: Vec::new(),
            candidates: Vec::new(),
            slot: Vec::new(),
            mlen: Vec::new(),
            reached_len: Vec::new(),
            cand_share: Vec::new(),
            want: Vec::new(),
        }
    }
}

/// Hands out scratch buffers to rayon jobs and takes them back, so each thread allocates
/// its grid-sized arrays once rather than once per job.
pub(super) struct Pool<'a> {
    pub(super) free: &'a Mutex<Vec<Scratch>>,
    pub(super) inside: &'a [bool],
}

pub(super) struct Lease<'a> {
    pub(super) free: &'a Mutex<Vec<Scratch>>,
    pub(super) s: Option<Scratch>,
}

impl Pool<'_> {
    pub(super) fn lease(&self) -> Lease<'_> {
        let s = self.free.lock().ok().and_then(|mut f| f.pop());
        Lease {
            free: self.free,
            s: Some(s.unwrap_or_else(|| Scratch::new(self.inside))),
        }
    }
}

impl Drop for Lease<'_> {
    fn drop(&mut self) {
        if let (Some(s), Ok(mut f)) = (self.s.take(), self.free.lock()) {
            f.push(s);
        }
    }
}

/// Single-source shortest paths over interior voxels with the 26-neighbour stencil, up to
/// `gmax` (×UNIT). Leaves in `s.reached` every (group, length) whose entry voxel it settles.
/// With `labels` (a medium per voxel), also the per-medium lengths of each path in
/// `s.reached_len`: relaxing u → v with weight w gives v the lengths of u plus w/2 in
/// label(u) and w/2 in label(v) (weights are even, so the parts sum to the length exactly).
pub(super) fn dijkstra(
    src: u32,
    offsets: &[(isize, u32); 26],
    group_of: &[u32],
    gmax: u32,
    labels: Option<&[u8]>,
    s: &mut Scratch,
) {
    s.reached.clear();
    s.reached_len.clear();
    if labels.is_some() {
        if s.slot.len() != group_of.len() {
            s.slot = vec![0; group_of.len()];
        }
        s.mlen.clear();
        s.slot[src as usize] = 0;
        s.mlen.push([0; MEDIA]);
    }
    s.dist[src as usize] = 0;
    s.touched.push(src);
    s.buckets[0].push((src, 0));
    let mut pending = 1usize;
    let mut k = 0usize;
    while pending > 0 {
        let slot = k % 4;
        let mut cur = std::mem::take(&mut s.buckets[slot]);
        pending -= cur.len();
        for &(v, g) in &cur {
            if g != s.dist[v as usize] {
                continue; // superseded by a shorter path
            }
            let grp = group_of[v as usize];
            if grp != NONE {
                s.reached.push((grp, g));
                if labels.is_some() {
                    s.reached_len.push(s.mlen[s.slot[v as usize] as usize]);
                }
            }
            for &(off, w) in offsets {
                let nb = (v as isize + off) as usize;
                let ng = g + w;
                if ng > gmax || ng >= s.dist[nb] {
                    continue;
                }
                if s.dist[nb] == NONE {
                    if labels.is_some() {
                        s.slot[nb] = s.touched.len() as u32;
                        s.mlen.push([0; MEDIA]);
                    }
                    s.touched.push(nb as u32);
                }
                s.dist[nb] = ng;
                if let Some(l) = labels {
                    let mut m = s.mlen[s.slot[v as usize] as usize];
                    m[l[v as usize] as usize] += w / 2;
                    m[l[nb] as usize] += w / 2;
                    s.mlen[s.slot[nb] as usize] = m;
                }
                s.buckets[(ng / UNIT) as usize % 4].push((nb as u32, ng));
                pending += 1;
            }
        }
        cur.clear();
        s.buckets[slot] = cur;
        k += 1;
    }
    for &v in &s.touched {
        s.dist[v as usize] = NONE;
    }
    s.touched.clear();
}

/// [`dijkstra`] towards some voxels only (homogeneous media): stops as soon as every voxel
/// of `want` (interior voxels) is settled, or nothing within `gmax` is left, and leaves in
/// `s.reached` (index in `want`, length) for those it settled. Dial's buckets settle a voxel
/// at its final length, so each length equals a full run's, bit for bit.
pub(super) fn dijkstra_to(
    src: u32,
    offsets: &[(isize, u32); 26],
    gmax: u32,
    want: &[u32],
    s: &mut Scratch,
) {
    s.reached.clear();
    if s.want.len() != s.dist.len() {
        s.want = vec![NONE; s.dist.len()];
    }
    let mut left = 0usize;
    for (k, &v) in want.iter().enumerate() {
        if s.want[v as usize] == NONE {
            s.want[v as usize] = k as u32;
            left += 1;
        }
    }
    s.dist[src as usize] = 0;
    s.touched.push(src);
    s.buckets[0].push((src, 0));
    let mut pending = 1usize;
    let mut k = 0usize;
    'run: while pending > 0 && left > 0 {
        let slot = k % 4;
        let mut cur = std::mem::take(&mut s.buckets[slot]);
        pending -= cur.len();
        for &(v, g) in &cur {
            if g != s.dist[v as usize] {
                continue; // superseded by a shorter path
            }
            let w = s.want[v as usize];
            if w != NONE {
                s.reached.push((w, g));
                s.want[v as usize] = NONE;
                left -= 1;
                if left == 0 {
                    cur.clear();
                    s.buckets[slot] = cur;
                    break 'run;
                }
            }
            for &(off, w) in offsets {
                let nb = (v as isize + off) as usize;
                let ng = g + w;
                if ng > gmax || ng >= s.dist[nb] {
                    continue;
                }
                if s.dist[nb] == NONE {
                    s.touched.push(nb as u32);
                }
                s.dist[nb] = ng;
                s.buckets[(ng / UNIT) as usize % 4].push((nb as u32, ng));
                pending += 1;
            }
        }
        cur.clear();
        s.buckets[slot] = cur;
        k += 1;
    }
    for b in &mut s.buckets {
        b.clear();
    }
    for &v in want {
        s.want[v as usize] = NONE;
    }
    for &v in &s.touched {
        s.dist[v as usize] = NONE;
    }
    s.touched.clear();
}

/// The graph-length bound of a run from an entry voxel whose patches lie up to `own_offset`
/// from it: r(i, j) ≤ R needs g·|Δv|/ch ≤ R + |Δv| − |Δc| ≤ R + off_i + off_j, and
/// |Δv|/ch ≥ 1/1.1281, so g ≤ 1.1281 (R + off_i + off_j) covers every such pair.
pub(super) fn graph_bound(r: f64, own_offset: f64, max_offset: f64, vs: f64) -> u32 {
    let reach = CHAMFER_MAX_RATIO * 1.001 * (r + own_offset + max_offset) / vs;
    (reach * f64::from(UNIT))
        .ceil()
        .min(f64::from(NONE - 4 * W[2])) as u32
}

/// The detour (scene units, 0 for a straight graph path) of a graph path of length `glen`
/// between entry voxels `a` and `b` over the straight chord between their centres, and
/// whether the path is straight (g = ch exactly, in integers).
pub(super) fn detour(grid: &Grid, a: u32, b: u32, glen: u32) -> (f64, bool) {
    let (src, c) = (grid.coords(a as usize), grid.coords(b as usize));
    let dv = [c[0] - src[0], c[1] - src[1], c[2] - src[2]];
    let ch = chamfer(dv);
    let straight = u64::from(glen) == ch;
    if ch == 0 {
        return (0.0, straight);
    }
    let chord = DVec3::new(dv[0] as f64, dv[1] as f64, dv[2] as f64).length();
    (
        (f64::from(glen) * chord / ch as f64 - chord).max(0.0) * grid.size,
        straight,
    )
}

/// An object's voxel grid as the paths need it: which voxels are interior, each patch's
/// entry voxel (the interior voxel nearest to the point half a voxel below its centroid;
/// NONE when none is near: the patch is unattached) and its offset |centre(v_i) − c_i|, which
/// bounds how much the voxel chord |Δv| can exceed the centroid chord |Δc|.
pub(super) struct Traced {
    pub(super) grid: Grid,
    pub(super) inside: Vec<bool>,
    pub(super) interior_voxels: usize,
    pub(super) entry: Vec<u32>,
    pub(super) offset: Vec<f64>,
    pub(super) max_offset: f64,
    pub(super) offsets: [(isize, u32); 26],
}

impl Traced {
    pub(super) fn new(
        object_name: &str,
        tris: &[[Vec3; 3]],
        centroids: &[Vec3],
        normals: &[Vec3],
        params: &VoxelParams,
    ) -> Result<Traced, VoxelError> {
        let n = centroids.len();
        if tris.is_empty() {
            return Err(VoxelError::NoInterior {
                object: object_name.to_string(),
                voxels: 0,
            });
        }
        let (lo, hi) = bounds(tris);
        let grid = Grid::choose(lo, hi, params.max_voxels);
        let inside = classify_interior(tris, &grid);
        let interior_voxels = inside.par_iter().filter(|&&b| b).count();
        if interior_voxels == 0 {
            return Err(VoxelError::NoInterior {
                object: object_name.to_string(),
                voxels: grid.len(),
            });
        }
        let vs = grid.size;
        let entry: Vec<u32> = (0..n)
            .into_par_iter()
            .map(|i| {
                let p = centroids[i] - normals[i] * (0.5 * vs as f32);
                entry_voxel(&grid, &inside, grid.grid_pos(p)).unwrap_or(NONE)
            })
            .collect();
        Ok(Traced::with_entries(
            grid,
            inside,
            interior_voxels,
            entry,
            centroids,
        ))
    }

    /// The rest from the grid, its interior and the patches' entry voxels: each patch's
    /// offset from its entry voxel's centre, the largest, and the stencil.
    fn with_entries(
        grid: Grid,
        inside: Vec<bool>,
        interior_voxels: usize,
        entry: Vec<u32>,
        centroids: &[Vec3],
    ) -> Traced {
        let offset: Vec<f64> = entry
            .par_iter()
            .zip(centroids)
            .map(|(&v, c)| match v {
                NONE => 0.0,
                v => grid.centre(v as usize).distance(c.as_dvec3()),
            })
            .collect();
        let max_offset = offset.iter().cloned().fold(0.0, f64::max);
        let offsets = neighbour_offsets(&grid);
        Traced {
            grid,
            inside,
            interior_voxels,
            entry,
            offset,
            max_offset,
            offsets,
        }
    }

    /// The same object on a grid of twice the voxel edge (an eighth of the voxels), for
    /// the targets far from their source ([`super::Oracle::solve_far`]).
    /// Coarse voxel X spans fine voxels 2X − 1 and 2X along each axis, and is interior when
    /// any of its 2 × 2 × 2 fine voxels is: the coarse interior covers the fine one, so every
    /// fine path has a coarse counterpart (a target reachable on the fine grid is reachable
    /// here, and no piece of the interior splits), and a patch enters through the coarse
    /// voxel holding its fine entry voxel (unattached patches stay unattached).
    pub(super) fn coarsened(&self, centroids: &[Vec3]) -> Traced {
        let fine = &self.grid;
        let grid = Grid {
            origin: fine.origin - DVec3::splat(fine.size),
            size: 2.0 * fine.size,
            dims: fine.dims.map(|d| (d - 1) / 2 + 2),
        };
        let up = |v: usize| -> usize {
            let [x, y, z] = fine.coords(v).map(|c| (c as usize).div_ceil(2));
            grid.index(x, y, z)
        };
        let mut inside = vec![false; grid.len()];
        for (v, _) in self.inside.iter().enumerate().filter(|(_, b)| **b) {
            inside[up(v)] = true;
        }
        let interior_voxels = inside.iter().filter(|&&b| b).count();
        let entry: Vec<u32> = self
            .entry
            .iter()
            .map(|&v| {
                if v == NONE {
                    NONE
                } else {
                    up(v as usize) as u32
                }
            })
            .collect();
        Traced::with_entries(grid, inside, interior_voxels, entry, centroids)
    }
}

/// One row of the result, (column, distance), sorted by column.
pub(super) type Row = Vec<(u32, f32)>;

/// A finished row: patch, row, and the per-medium lengths of its entries (empty unless media
/// are tracked; kept apart so that homogeneous objects carry no extra bytes per pair).
pub(super) type RowOut = (u32, Row, Vec<MediaLen>);

/// Sorts a row by column, its per-medium lengths (if any) alongside.
pub(super) fn sort_row(row: &mut Row, lens: &mut Vec<MediaLen>) {
    if lens.is_empty() {
        row.sort_unstable_by_key(|p| p.0);
        return;
    }
    let mut order: Vec<u32> = (0..row.len() as u32).collect();
    order.sort_unstable_by_key(|&k| row[k as usize].0);
    *row = order.iter().map(|&k| row[k as usize]).collect();
    *lens = order.iter().map(|&k| lens[k as usize]).collect();
}

/// Labels every interior voxel with the medium of the nearest seed voxel through the
/// interior (a multi-source Dijkstra with the 26-neighbour weights; ties go to the seed
/// popped first, i.e. the lower voxel index). Interior voxels no seed reaches, and exterior
/// voxels, get medium 0.
pub(super) fn label_by_nearest_entry(
    inside: &[bool],
    seeds: &[(u32, u8)],
    offsets: &[(isize, u32); 26],
) -> Vec<u8> {
    use std::cmp::Reverse;
    use std::collections::BinaryHeap;
    let mut label = vec![0u8; inside.len()];
    let mut dist = vec![u32::MAX; inside.len()];
    let mut heap = BinaryHeap::new();
    for &(v, m) in seeds {
        if inside[v as usize] && dist[v as usize] != 0 {
            dist[v as usize] = 0;
            label[v as usize] = m;
            heap.push(Reverse((0u32, v)));
        }
    }
    while let Some(Reverse((g, v))) = heap.pop() {
        if g != dist[v as usize] {
            continue;
        }
        for &(off, w) in offsets {
            let nb = (v as isize + off) as usize;
            let ng = g + w;
            if inside[nb] && ng < dist[nb] {
                dist[nb] = ng;
                label[nb] = label[v as usize];
                heap.push(Reverse((ng, nb as u32)));
            }
        }
    }
    label
}

/// Patches that share an entry voxel (or one unattached patch, `voxel == NONE`).
pub(super) struct Group {
    pub(super) voxel: u32,
    pub(super) members: std::ops::Range<usize>,
}

#[expect(
    clippy::too_many_arguments,
    reason = "the private worker behind optical_distances_media, which names each input"
)]
pub(super) fn voxel_distances(
    object_name: &str,
    tris: &[[Vec3; 3]],
    centroids: &[Vec3],
    normals: &[Vec3],
    max_radius: f32,
    params: &VoxelParams,
    media: Option<&MediumField<'_>>,
    start: Instant,
) -> Result<(Distances, DistanceStats), VoxelError> {
    let n = centroids.len();
    let Traced {
        grid,
        inside,
        interior_voxels,
        entry,
        offset,
        max_offset,
        offsets,
    } = Traced::new(object_name, tris, centroids, normals, params)?;
    let vs = grid.size;

    // Groups sorted by their smallest member, so that after a batch of groups every row
    // below the next group's smallest member is complete and can be written out.
    let mut by_voxel: Vec<u32> = (0..n as u32).collect();
    by_voxel.par_sort_unstable_by_key(|&i| (entry[i as usize], i));
    let mut groups: Vec<Group> = Vec::new();
    let mut k = 0;
    while k < n {
        let v = entry[by_voxel[k] as usize];
        let mut e = k + 1;
        if v != NONE {
            while e < n && entry[by_voxel[e] as usize] == v {
                e += 1;
            }
        }
        groups.push(Group {
            voxel: v,
            members: k..e,
        });
        k = e;
    }
    groups.sort_unstable_by_key(|g| by_voxel[g.members.start]);
    let mut group_of = vec![NONE; grid.len()];
    for (gi, g) in groups.iter().enumerate() {
        if g.voxel != NONE {
            group_of[g.voxel as usize] = gi as u32;
        }
    }
    let sources = groups.iter().filter(|g| g.voxel != NONE).count();
    let unattached = groups.len() - sources;

    // Unattached patches fall back to Euclidean pairs, with everyone (their own rows) and
    // from everyone (a hash of just them), which keeps the matrix symmetric.
    let all: Vec<u32> = (0..n as u32).collect();
    let loose: Vec<u32> = (0..n as u32)
        .filter(|&i| entry[i as usize] == NONE)
        .collect();
    let hash_all = (unattached > 0).then(|| PointHash::new(centroids, &all, max_radius));
    let hash_loose = (unattached > 0).then(|| PointHash::new(centroids, &loose, max_radius));

    // Media labels of the interior voxels (heterogeneous objects).
    let labels: Option<Vec<u8>> = media.map(|field| match field {
        MediumField::Checker(c) => (0..grid.len())
            .into_par_iter()
            .map(|v| {
                if inside[v] {
                    c.medium_at(grid.centre(v).as_vec3()) as u8
                } else {
                    0
                }
            })
            .collect(),
        MediumField::PerPatch(pm) => {
            // Each entry voxel seeds the medium of its smallest patch.
            let seeds: Vec<(u32, u8)> = groups
                .iter()
                .filter(|g| g.voxel != NONE)
                .map(|g| {
                    let first = by_voxel[g.members.start] as usize;
                    (g.voxel, pm.get(first).copied().unwrap_or(0) as u8)
                })
                .collect();
            label_by_nearest_entry(&inside, &seeds, &offsets)
        }
    });
    let straight = |i: u32, j: u32, d: f32| -> MediaLen {
        match media {
            Some(f) => f.straight(
                i as usize,
                j as usize,
                centroids[i as usize],
                centroids[j as usize],
                d,
            ),
            None => [0.0; MEDIA],
        }
    };

    let r = f64::from(max_radius);
    let track = media.is_some();
    let row_for_group = |g: &Group, s: &mut Scratch| -> Vec<RowOut> {
        let members = &by_voxel[g.members.clone()];
        if g.voxel == NONE {
            let i = members[0];
            let (mut row, mut lens) = (Vec::new(), Vec::new());
            if let Some(h) = &hash_all {
                h.within(centroids, centroids[i as usize], max_radius, |j, d| {
                    if j != i {
                        row.push((j, d));
                        if track {
                            lens.push(straight(i, j, d));
                        }
                    }
                });
            }
            sort_row(&mut row, &mut lens);
            return vec![(i, row, lens)];
        }
        let own_offset = members
            .iter()
            .map(|&i| offset[i as usize])
            .fold(0.0, f64::max);
        let gmax = graph_bound(r, own_offset, max_offset, vs);
        dijkstra(g.voxel, &offsets, &group_of, gmax, labels.as_deref(), s);
        // Candidates (j, detour), once per source: the detour over the straight voxel chord,
        // in scene units (0 when g = ch). The same for every member of the group. With media,
        // also each candidate's shares g_k / g of the graph path (all in the source voxel's
        // medium when g = 0).
        s.candidates.clear();
        s.cand_share.clear();
        for (k, &(gj, glen)) in s.reached.iter().enumerate() {
            let other = &groups[gj as usize];
            let (detour, straight_path) = detour(&grid, g.voxel, other.voxel, glen);
            if detour <= r {
                let members = &by_voxel[other.members.clone()];
                s.candidates
                    .extend(members.iter().map(|&j| (j, detour as f32)));
                if let Some(l) = &labels {
                    let share = if straight_path && matches!(media, Some(MediumField::Checker(_))) {
                        // A straight interior path: the exact split of the segment.
                        None
                    } else if glen == 0 {
                        let mut one = [0.0; MEDIA];
                        one[l[g.voxel as usize] as usize] = 1.0;
                        Some(one)
                    } else {
                        Some(s.reached_len[k].map(|x| x as f32 / glen as f32))
                    };
                    s.cand_share
                        .extend(std::iter::repeat_n(share, members.len()));
                }
            }
        }
        let mut out = Vec::with_capacity(members.len());
        for &i in members {
            let ci = centroids[i as usize];
            let (mut row, mut lens) = (Vec::new(), Vec::new());
            for (k, &(j, detour)) in s.candidates.iter().enumerate() {
                let d = f64::from(ci.distance(centroids[j as usize])) + f64::from(detour);
                if d <= r && j != i {
                    let d = d as f32;
                    row.push((j, d));
                    if track {
                        lens.push(match s.cand_share[k] {
                            Some(share) => share.map(|f| f * d),
                            None => straight(i, j, d),
                        });
                    }
                }
            }
            if let Some(h) = &hash_loose {
                h.within(centroids, ci, max_radius, |j, d| {
                    row.push((j, d));
                    if track {
                        lens.push(straight(i, j, d));
                    }
                });
            }
            sort_row(&mut row, &mut lens);
            out.push((i, row, lens));
        }
        out
    };

    let free = Mutex::new(Vec::new());
    let pool = Pool {
        free: &free,
        inside: &inside,
    };
    let mut rows: Vec<(Row, Vec<MediaLen>)> = vec![(Vec::new(), Vec::new()); n];
    let mut out = RowsBuilder::new(object_name, n);
    let batch = (groups.len() / 32).max(256);
    let mut g0 = 0;
    while g0 < groups.len() {
        let g1 = (g0 + batch).min(groups.len());
        let done: Vec<Vec<RowOut>> = groups[g0..g1]
            .par_iter()
            .map_init(
                || pool.lease(),
                |l, g| row_for_group(g, l.s.as_mut().unwrap()),
            )
            .collect();
        for (i, row, lens) in done.into_iter().flatten() {
            rows[i as usize] = (row, lens);
        }
        // Every row below the next batch's smallest member belongs to a finished group.
        let complete = groups
            .get(g1)
            .map_or(n, |g| by_voxel[g.members.start] as usize);
        while out.rows() < complete {
            let i = out.rows();
            let (row, lens) = std::mem::take(&mut rows[i]);
            out.push_row(&row)?;
            out.material_len.extend_from_slice(&lens);
        }
        g0 = g1;
    }
    let d = out.finish();
    let stats = DistanceStats {
        method: Method::Voxel,
        voxels: grid.len(),
        interior_voxels,
        voxel_size: vs as f32,
        grid: grid.dims,
        sources,
        unattached,
        seconds: start.elapsed().as_secs_f64(),
        pairs: d.nnz(),
    };
    Ok((d, stats))
}
