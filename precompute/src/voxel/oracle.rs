//! Optical distances on demand, for a hierarchical S ([`crate::slinks`]): instead of every
//! pair within the radius (what [`optical_distances`] stores, O(n²) for a large, very
//! translucent object), the distances from given sources to given targets only. The cut
//! of a hierarchical S needs a receiver's near patches and, per cluster node, the
//! receivers that link it: a near run stops after a few patch sizes, a node's run after
//! the distance it is linked from, so the voxel work is a few whole-grid runs for the top
//! nodes instead of one per patch, and no pair list is ever held.
//!
//! Every distance equals the one [`optical_distances`] stores for the same pair, bit for
//! bit: the same entry voxels, the same graph-length bound, the same detour correction;
//! Dijkstra stops once its targets are settled, and settled lengths are final. A target
//! that a straight interior path reaches gets its free-space length without a search
//! ([`straight_length`]): the length a search would settle it at. (Except the far targets
//! of [`Oracle::solve_far`], found on a coarser grid.)

use std::sync::OnceLock;

use super::*;

/// One object's distances on demand (local patch indices `0..n`).
pub struct Oracle {
    centroids: Vec<Vec3>,
    radius: f32,
    /// `None`: straight lines (a convex object, or the fallback for one without interior).
    traced: Option<TracedPaths>,
    /// The same interior on a grid of twice the voxel edge ([`Traced::coarsened`]), built
    /// by the first [`Oracle::solve_far`] that has far targets (never with exact links).
    coarse: OnceLock<TracedPaths>,
    stats: DistanceStats,
}

impl std::fmt::Debug for Oracle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Oracle")
            .field("patches", &self.centroids.len())
            .field("radius", &self.radius)
            .field("stats", &self.stats)
            .finish()
    }
}

struct TracedPaths {
    t: Traced,
    /// Per patch: the largest entry offset among the patches sharing its entry voxel (the
    /// run's graph-length bound, as [`optical_distances`] takes it per entry voxel).
    own_offset: Vec<f64>,
    /// Per patch: the connected piece of the interior its entry voxel lies in. A run would
    /// search its whole reach for a target in another piece (a voxel island at a thin
    /// edge, a separate shell), never to find it.
    piece: Vec<u32>,
    free: Mutex<Vec<Scratch>>,
}

impl TracedPaths {
    /// The paths over `t`, with the number of distinct entry voxels (run sources) and of
    /// unattached patches.
    fn new(t: Traced) -> (TracedPaths, usize, usize) {
        let n = t.entry.len();
        let mut by_voxel: Vec<u32> = (0..n as u32).collect();
        by_voxel.par_sort_unstable_by_key(|&i| (t.entry[i as usize], i));
        let mut own_offset = vec![0.0f64; n];
        let (mut sources, mut unattached) = (0usize, 0usize);
        for run in by_voxel.chunk_by(|&a, &b| t.entry[a as usize] == t.entry[b as usize]) {
            if t.entry[run[0] as usize] == NONE {
                unattached += run.len();
                continue;
            }
            sources += 1;
            let m = run
                .iter()
                .map(|&i| t.offset[i as usize])
                .fold(0.0, f64::max);
            for &i in run {
                own_offset[i as usize] = m;
            }
        }
        let piece = pieces_of(&t, &t.entry);
        let tp = TracedPaths {
            t,
            own_offset,
            piece,
            free: Mutex::new(Vec::new()),
        };
        (tp, sources, unattached)
    }
}

/// Labels the connected pieces of the interior (26-neighbour steps, as the paths take) and
/// returns the label of each given voxel (NONE for NONE).
fn pieces_of(t: &Traced, voxels: &[u32]) -> Vec<u32> {
    let mut label = vec![NONE; t.inside.len()];
    let mut next = 0u32;
    let mut stack = Vec::new();
    for &v in voxels {
        if v == NONE || label[v as usize] != NONE {
            continue;
        }
        label[v as usize] = next;
        stack.push(v);
        while let Some(u) = stack.pop() {
            for &(off, _) in &t.offsets {
                let nb = (u as isize + off) as usize;
                if t.inside[nb] && label[nb] == NONE {
                    label[nb] = next;
                    stack.push(nb as u32);
                }
            }
        }
        next += 1;
    }
    voxels
        .iter()
        .map(|&v| if v == NONE { NONE } else { label[v as usize] })
        .collect()
}

/// How far (in coarse voxel edges, straight line) a target must lie from its source for
/// [`Oracle::solve_far`] to find it on the coarse grid: 8 coarse edges, 16 of the fine
/// grid's, so a coarse voxel's worth of corner is at most about 1/8 of the path.
pub const FAR_RUN_VOXELS: f32 = 8.0;

/// Distances from one source patch to the targets, [`f32::INFINITY`] for a target farther
/// than the radius (or the source itself).
pub type Row = Vec<f32>;

impl Oracle {
    /// Prepares the object as [`optical_distances`] would (convexity test, voxel grid, entry
    /// voxels); no path is traced yet. The same errors, [`VoxelError::NoInterior`] among
    /// them (see [`Oracle::straight`] for the fallback).
    pub fn new(
        object_name: &str,
        source_tris: &[[Vec3; 3]],
        centroids: &[Vec3],
        normals: &[Vec3],
        max_radius: f32,
        params: &VoxelParams,
    ) -> Result<Oracle, VoxelError> {
        let start = Instant::now();
        check_inputs(object_name, centroids, normals, max_radius)?;
        if !params.force_voxels && is_convex(source_tris, params.convex_tolerance) {
            return Ok(Oracle::straight(centroids, max_radius));
        }
        let t = Traced::new(object_name, source_tris, centroids, normals, params)?;
        let (fine, sources, unattached) = TracedPaths::new(t);
        let t = &fine.t;
        let stats = DistanceStats {
            method: Method::Voxel,
            voxels: t.grid.len(),
            interior_voxels: t.interior_voxels,
            voxel_size: t.grid.size as f32,
            grid: t.grid.dims,
            sources,
            unattached,
            seconds: start.elapsed().as_secs_f64(),
            pairs: 0,
        };
        Ok(Oracle {
            centroids: centroids.to_vec(),
            radius: max_radius,
            traced: Some(fine),
            coarse: OnceLock::new(),
            stats,
        })
    }

    /// Straight-line distances between centroids: a convex object's optical paths, and the
    /// fallback for an object without interior.
    pub fn straight(centroids: &[Vec3], max_radius: f32) -> Oracle {
        Oracle {
            centroids: centroids.to_vec(),
            radius: max_radius,
            traced: None,
            coarse: OnceLock::new(),
            stats: DistanceStats::straight(0.0, 0),
        }
    }

    /// How the distances are found (`pairs` and `seconds` count what [`Oracle::solve`] did
    /// only when the caller adds them).
    pub fn stats(&self) -> DistanceStats {
        self.stats
    }

    /// The radius beyond which no distance is given.
    pub fn radius(&self) -> f32 {
        self.radius
    }

    fn euclidean(&self, i: u32, j: u32) -> f32 {
        let d = self.centroids[i as usize].distance(self.centroids[j as usize]);
        if i != j && d <= self.radius {
            d
        } else {
            f32::INFINITY
        }
    }

    /// For every job (source, targets), the optical distance from the source to each
    /// target (aligned with the targets). Sources that share an entry voxel share one
    /// Dijkstra run, which stops once all their targets are settled. Parallel.
    pub fn solve(&self, jobs: &[(u32, Vec<u32>)]) -> Vec<Row> {
        match &self.traced {
            Some(tp) => self.solve_on(tp, jobs),
            None => self.solve_straight(jobs),
        }
    }

    /// As [`Oracle::solve`], except that the targets lying at least [`FAR_RUN_VOXELS`]
    /// coarse voxel edges from their source (in a straight line) are found by a run on the
    /// grid of twice the voxel edge (`Traced::coarsened`): an eighth of the voxels, so a
    /// run settles about an eighth as many; the job's nearer targets keep a run on the fine
    /// grid, which stops at the farthest of them. The far distances are no longer those
    /// [`optical_distances`] stores: the coarse interior covers the fine one, so a path may
    /// cut a corner up to about a coarse voxel shorter (`voxel::tests`: within a coarse
    /// voxel and 4% of the path, the median unchanged). For a hierarchical S, whose far
    /// pairs' profile is smooth over such a change (links, evaluated at one representative
    /// point anyway, and direct pairs 16 voxels apart: `precompute/tests/it/slinks.rs`
    /// holds S so made to the pairwise bounds). Returns the rows and how many jobs had a run
    /// on the coarse grid.
    pub fn solve_far(&self, jobs: &[(u32, Vec<u32>)]) -> (Vec<Row>, usize) {
        let Some(tp) = &self.traced else {
            return (self.solve_straight(jobs), 0);
        };
        let far = FAR_RUN_VOXELS * 2.0 * tp.t.grid.size as f32;
        // Per job, the positions of its far and near targets.
        let split: Vec<(Vec<u32>, Vec<u32>)> = jobs
            .par_iter()
            .map(|(i, ts)| {
                let c = self.centroids[*i as usize];
                (0..ts.len() as u32)
                    .partition(|&k| c.distance(self.centroids[ts[k as usize] as usize]) >= far)
            })
            .collect();
        let part = |far_part: bool| -> (Vec<usize>, Vec<(u32, Vec<u32>)>) {
            split
                .iter()
                .enumerate()
                .filter_map(|(k, (f, n))| {
                    let ks = if far_part { f } else { n };
                    (!ks.is_empty()).then(|| {
                        let (i, ts) = &jobs[k];
                        (k, (*i, ks.iter().map(|&x| ts[x as usize]).collect()))
                    })
                })
                .unzip()
        };
        let mut out: Vec<Row> = jobs.iter().map(|(_, ts)| vec![0.0; ts.len()]).collect();
        let mut coarse_jobs = 0;
        for far_part in [true, false] {
            let (which, sub) = part(far_part);
            if sub.is_empty() {
                continue;
            }
            let grid = if far_part {
                coarse_jobs = sub.len();
                self.coarse
                    .get_or_init(|| TracedPaths::new(tp.t.coarsened(&self.centroids)).0)
            } else {
                tp
            };
            for (&k, row) in which.iter().zip(self.solve_on(grid, &sub)) {
                let (f, n) = &split[k];
                for (&x, d) in (if far_part { f } else { n }).iter().zip(row) {
                    out[k][x as usize] = d;
                }
            }
        }
        (out, coarse_jobs)
    }

    fn solve_straight(&self, jobs: &[(u32, Vec<u32>)]) -> Vec<Row> {
        jobs.par_iter()
            .map(|(i, ts)| ts.iter().map(|&j| self.euclidean(*i, j)).collect())
            .collect()
    }

    fn solve_on(&self, tp: &TracedPaths, jobs: &[(u32, Vec<u32>)]) -> Vec<Row> {
        let t = &tp.t;
        let mut order: Vec<u32> = (0..jobs.len() as u32).collect();
        order.par_sort_unstable_by_key(|&k| t.entry[jobs[k as usize].0 as usize]);
        let runs: Vec<&[u32]> = order
            .chunk_by(|&a, &b| {
                t.entry[jobs[a as usize].0 as usize] == t.entry[jobs[b as usize].0 as usize]
            })
            .collect();
        let pool = Pool {
            free: &tp.free,
            inside: &t.inside,
        };
        let r = f64::from(self.radius);
        let done: Vec<Vec<(u32, Row)>> = runs
            .par_iter()
            .map_init(
                || pool.lease(),
                |l, run| {
                    let s = l.s.as_mut().expect("a leased scratch");
                    let src_voxel = t.entry[jobs[run[0] as usize].0 as usize];
                    if src_voxel == NONE {
                        // Unattached sources: straight lines to everyone.
                        return run
                            .iter()
                            .map(|&k| {
                                let (i, ts) = &jobs[k as usize];
                                (k, ts.iter().map(|&j| self.euclidean(*i, j)).collect())
                            })
                            .collect();
                    }
                    // The targets' entry voxels in the source's piece, once each.
                    let own_piece = tp.piece[jobs[run[0] as usize].0 as usize];
                    let mut want: Vec<u32> = run
                        .iter()
                        .flat_map(|&k| jobs[k as usize].1.iter())
                        .filter(|&&j| tp.piece[j as usize] == own_piece)
                        .map(|&j| t.entry[j as usize])
                        .filter(|&v| v != NONE && v != src_voxel)
                        .collect();
                    want.sort_unstable();
                    want.dedup();
                    let own = tp.own_offset[jobs[run[0] as usize].0 as usize];
                    let gmax = graph_bound(r, own, t.max_offset, t.grid.size);
                    // Targets seen along a straight interior path have their free-space
                    // length; a run searches only for the rest, and stops at the farthest
                    // of those.
                    let mut glen = vec![NONE; want.len()];
                    let mut searched = Vec::new();
                    for (w, &v) in want.iter().enumerate() {
                        match straight_length(&t.grid, &t.inside, src_voxel, v) {
                            // Beyond the bound, a run would not settle it either.
                            Some(g) if g <= u64::from(gmax) => glen[w] = g as u32,
                            Some(_) => {}
                            None => searched.push(w as u32),
                        }
                    }
                    if !searched.is_empty() {
                        let targets: Vec<u32> =
                            searched.iter().map(|&w| want[w as usize]).collect();
                        dijkstra_to(src_voxel, &t.offsets, gmax, &targets, s);
                        for &(k, g) in &s.reached {
                            glen[searched[k as usize] as usize] = g;
                        }
                    }
                    run.iter()
                        .map(|&k| {
                            let (i, ts) = &jobs[k as usize];
                            let ci = self.centroids[*i as usize];
                            let row = ts
                                .iter()
                                .map(|&j| {
                                    let vj = t.entry[j as usize];
                                    if vj == NONE {
                                        return self.euclidean(*i, j);
                                    }
                                    let g = if vj == src_voxel {
                                        0
                                    } else {
                                        match want.binary_search(&vj) {
                                            Ok(w) => glen[w],
                                            Err(_) => NONE,
                                        }
                                    };
                                    if g == NONE || j == *i {
                                        return f32::INFINITY;
                                    }
                                    let (detour, _) = detour(&t.grid, src_voxel, vj, g);
                                    if detour > r {
                                        return f32::INFINITY;
                                    }
                                    // As optical_distances: the detour kept as f32, the sum
                                    // in f64.
                                    let d = f64::from(ci.distance(self.centroids[j as usize]))
                                        + f64::from(detour as f32);
                                    if d <= r { d as f32 } else { f32::INFINITY }
                                })
                                .collect();
                            (k, row)
                        })
                        .collect()
                },
            )
            .collect();
        let mut out: Vec<Row> = vec![Vec::new(); jobs.len()];
        for (k, row) in done.into_iter().flatten() {
            out[k as usize] = row;
        }
        out
    }
}
