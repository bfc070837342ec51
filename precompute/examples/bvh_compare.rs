//! Occlusion throughput: our [`Occluder`] (obvhs 0.4 CWBVH) against the `bvh` crate (0.13).
//!
//! Backs the choice of BVH in `src/raycast.rs` with a measurement anyone can rerun:
//!
//! ```text
//! cargo run --release -p translux-precompute --example bvh_compare --features bench-bvh
//! cargo run --release -p translux-precompute --example bvh_compare --features bench-bvh -- \
//!     --segments 500000 --repeats 1 --bunny ../shared/data/stanford-bunny.obj
//! ```
//!
//! Scenes: `builtin:cornell` split into ~130k patches (the patch corners are the triangle
//! soup), the Stanford bunny (skipped when its OBJ is missing; `--bunny PATH`), and 100k
//! random overlapping triangles in the unit cube (`--soup-half`). Queries: surface-to-surface segments between uniform points on two random
//! triangles (seeded xorshift), each end pushed off its triangle by 1e-5 × the scene diagonal
//! towards the other end, as `formfactor.rs` does before calling [`Occluder::occluded`].
//!
//! Rows per scene:
//! - `obvhs 0.4 CWBVH (Occluder)`: `Occluder::new` / `Occluder::occluded`, the code the
//!   engine runs (build includes its vertex copy, padding triangles and reordering).
//! - `bvh 0.13 Ray`: `Bvh::build_par`, then `traverse_iterator` with the crate's own
//!   (SIMD) ray–box test and `.any(..)` for an early exit. Its rays are infinite, so boxes
//!   past the segment's end are visited too.
//! - `bvh 0.13 segment query`: the same tree, traversed with our own `IntersectsAabb`
//!   (a scalar slab test clipped to the segment), to show what a t-range would buy.
//!
//! Agreement is the share of segments on which a row gives the same hit/miss answer as the
//! obvhs row; up to 2000 disagreements per row are re-checked by an exact f64 brute force
//! over all triangles. Some disagreement is expected: `intersect_closed` in `raycast.rs`
//! widens the barycentric test by 1e-5 (seams), while bvh's test is exact and culls
//! triangles whose determinant is below `f32::EPSILON`. That threshold is absolute (the
//! determinant is 2 × area × cos for a unit direction), so small triangles seen at a
//! grazing angle are missed: at the bunny's real scale (~0.2 units, ~1e-6 per triangle)
//! about 1% of segments, and none once the bunny is scaled up 100×.
//!
//! "All threads" is rayon's global pool; "1 thread" is a plain sequential loop. Each rate is
//! the best of `--repeats` runs over all segments. Build times use all threads.

use std::path::PathBuf;
use std::time::Instant;

use bvh::aabb::{Aabb, Bounded, IntersectsAabb};
use bvh::bounding_hierarchy::{BHShape, BoundingHierarchy};
use bvh::bvh::Bvh;
use bvh::ray::Ray;
use glam::Vec3;
use rayon::prelude::*;
use translux_engine::raycast::Occluder;
use translux_precompute::patch::{Density, plan, subdivide};
use translux_precompute::scene::load_scene;

/// Seeded xorshift64 (no `rand` crate).
struct XorShift(u64);

impl XorShift {
    fn new(seed: u64) -> Self {
        // Never zero, and the low-entropy seeds get mixed a little.
        Self(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }
    fn next_u64(&mut self) -> u64 {
        let mut s = self.0;
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        self.0 = s;
        s
    }
    /// Uniform in [0, 1).
    fn f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }
    fn vec3(&mut self) -> Vec3 {
        Vec3::new(self.f32(), self.f32(), self.f32())
    }
}

#[derive(Clone, Copy)]
struct Segment {
    a: Vec3,
    b: Vec3,
}

struct Options {
    segments: usize,
    repeats: usize,
    seed: u64,
    bunny: PathBuf,
    soup_half: f32,
}

fn parse_args() -> Options {
    let repo_root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut o = Options {
        segments: 2_000_000,
        repeats: 2,
        seed: 0x5EED,
        bunny: repo_root.join("../shared/data/stanford-bunny.obj"),
        soup_half: SOUP_HALF,
    };
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        let mut value = || args.next().unwrap_or_else(|| panic!("{arg} needs a value"));
        match arg.as_str() {
            "--segments" => o.segments = value().parse().expect("--segments: a count"),
            "--repeats" => o.repeats = value().parse::<usize>().expect("--repeats").max(1),
            "--seed" => o.seed = value().parse().expect("--seed: an integer"),
            "--bunny" => o.bunny = PathBuf::from(value()),
            "--soup-half" => o.soup_half = value().parse().expect("--soup-half: a length"),
            "-h" | "--help" => {
                println!(
                    "bvh_compare [--segments N (2000000)] [--repeats R (2)] [--seed S] [--bunny PATH] \
                     [--soup-half H ({SOUP_HALF})]"
                );
                std::process::exit(0);
            }
            other => panic!("unknown argument {other:?} (try --help)"),
        }
    }
    o
}

/// `builtin:cornell` split to about `target` patches; the patch corners are the soup.
fn cornell(target: u64) -> Vec<[Vec3; 3]> {
    let scene = load_scene("builtin:cornell").expect("builtin:cornell loads");
    let objects: Vec<&[[Vec3; 3]]> = scene
        .objects
        .iter()
        .map(|o| o.triangles.as_slice())
        .collect();
    let (h, _) = plan(&objects, Density::Target(target));
    subdivide(&objects, h).corners
}

/// The triangles of an OBJ file, as they are (no transform).
fn obj_triangles(path: &std::path::Path) -> Result<Vec<[Vec3; 3]>, String> {
    let opts = tobj::LoadOptions {
        triangulate: true,
        single_index: true,
        ..Default::default()
    };
    let (models, _) = tobj::load_obj(path, &opts).map_err(|e| e.to_string())?;
    let mut tris = Vec::new();
    for m in &models {
        let p = &m.mesh.positions;
        let v = |i: u32| {
            let i = i as usize * 3;
            Vec3::new(p[i], p[i + 1], p[i + 2])
        };
        for f in m.mesh.indices.chunks_exact(3) {
            tris.push([v(f[0]), v(f[1]), v(f[2])]);
        }
    }
    Ok(tris)
}

/// Default half-size of the random triangles' corner cube (unit-cube scene).
const SOUP_HALF: f32 = 0.01;

/// `n` triangles with centres uniform in the unit cube and corners within ±`half` of them:
/// overlapping boxes, the worst case for a BVH.
fn random_soup(n: usize, half: f32, seed: u64) -> Vec<[Vec3; 3]> {
    let mut rng = XorShift::new(seed);
    (0..n)
        .map(|_| {
            let c = rng.vec3();
            let mut corner = || c + (rng.vec3() - Vec3::splat(0.5)) * (2.0 * half);
            [corner(), corner(), corner()]
        })
        .collect()
}

fn diagonal(tris: &[[Vec3; 3]]) -> f32 {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for v in tris.iter().flatten() {
        lo = lo.min(*v);
        hi = hi.max(*v);
    }
    (hi - lo).length()
}

/// A uniform point on a random non-degenerate triangle, with the triangle's unit normal.
fn surface_point(tris: &[[Vec3; 3]], rng: &mut XorShift) -> (Vec3, Vec3) {
    loop {
        let t = &tris[rng.below(tris.len())];
        let n = (t[1] - t[0]).cross(t[2] - t[0]);
        if n.length_squared() == 0.0 {
            continue;
        }
        let s = rng.f32().sqrt();
        let r = rng.f32();
        let p = t[0] * (1.0 - s) + t[1] * (s * (1.0 - r)) + t[2] * (s * r);
        return (p, n.normalize());
    }
}

/// Segments between random surface points, each end offset along its normal, on the side
/// facing the other end, by 1e-5 × the scene diagonal (surfaces count as two-sided).
///
/// Pairs where either point lies within 1e-6 × the diagonal of the other's plane are drawn
/// again: `formfactor.rs` culls those before casting (`any_in_front`), and for two points on
/// one wall the side "facing the other end" is rounding noise, which would send the segment
/// through the wall at a grazing angle.
fn make_segments(tris: &[[Vec3; 3]], count: usize, seed: u64) -> Vec<Segment> {
    let diag = diagonal(tris);
    let (offset, eps_plane) = (1e-5 * diag, 1e-6 * diag);
    let mut rng = XorShift::new(seed);
    (0..count)
        .map(|_| {
            loop {
                let (p, np) = surface_point(tris, &mut rng);
                let (q, nq) = surface_point(tris, &mut rng);
                let (hp, hq) = (np.dot(q - p), nq.dot(p - q));
                if hp.abs() <= eps_plane || hq.abs() <= eps_plane {
                    continue;
                }
                break Segment {
                    a: p + np * hp.signum() * offset,
                    b: q + nq * hq.signum() * offset,
                };
            }
        })
        .collect()
}

/// A triangle for the `bvh` crate. Stored as plain arrays: `bvh` does not re-export
/// nalgebra, and `[f32; 3]` converts into its `Point3` with `into()`.
struct BvhTri {
    v: [[f32; 3]; 3],
    node: usize,
}

impl Bounded<f32, 3> for BvhTri {
    fn aabb(&self) -> Aabb<f32, 3> {
        let mut bb = Aabb::empty();
        for p in self.v {
            bb.grow_mut(&p.into());
        }
        bb
    }
}

impl BHShape<f32, 3> for BvhTri {
    fn set_bh_node_index(&mut self, index: usize) {
        self.node = index;
    }
    fn bh_node_index(&self) -> usize {
        self.node
    }
}

/// The ray clipped to `t ≤ tmax` (the crate's `Ray` has no t-range): a scalar slab test.
struct SegmentQuery {
    ray: Ray<f32, 3>,
    tmax: f32,
}

impl IntersectsAabb<f32, 3> for SegmentQuery {
    fn intersects_aabb(&self, aabb: &Aabb<f32, 3>) -> bool {
        let (mut lo, mut hi) = (0.0f32, self.tmax);
        for i in 0..3 {
            let t1 = (aabb.min[i] - self.ray.origin[i]) * self.ray.inv_direction[i];
            let t2 = (aabb.max[i] - self.ray.origin[i]) * self.ray.inv_direction[i];
            // f32::min/max drop a NaN (ray in a slab's plane): that axis does not constrain.
            lo = lo.max(t1.min(t2));
            hi = hi.min(t1.max(t2));
        }
        lo <= hi
    }
}

struct BvhScene {
    bvh: Bvh<f32, 3>,
    tris: Vec<BvhTri>,
}

impl BvhScene {
    fn build(tris: &[[Vec3; 3]]) -> (Self, f64) {
        let mut shapes: Vec<BvhTri> = tris
            .iter()
            .map(|t| BvhTri {
                v: t.map(|p| p.to_array()),
                node: 0,
            })
            .collect();
        let start = Instant::now();
        let bvh = Bvh::build_par(&mut shapes);
        let ms = start.elapsed().as_secs_f64() * 1e3;
        (Self { bvh, tris: shapes }, ms)
    }

    /// The ray for segment (a, b) and the open distance range that counts, matching
    /// `Occluder::occluded`'s (1e-4, 1 − 1e-4) in segment units. `Ray::new` normalises the
    /// direction, so t is a distance here.
    fn ray(a: Vec3, b: Vec3) -> Option<(Ray<f32, 3>, f32, f32)> {
        let d = b - a;
        let len = d.length();
        (len > 0.0).then(|| {
            let ray = Ray::new(a.to_array().into(), d.to_array().into());
            (ray, 1e-4 * len, (1.0 - 1e-4) * len)
        })
    }

    /// bvh's `intersects_triangle` is one-sided (back faces culled, `det < ε`), and its
    /// distance is unbounded: test both windings and check t against the range ourselves.
    #[inline]
    fn hits(ray: &Ray<f32, 3>, t: &BvhTri, tmin: f32, tmax: f32) -> bool {
        let [a, b, c] = t.v.map(Into::into);
        let in_range = |d: f32| d > tmin && d < tmax;
        in_range(ray.intersects_triangle(&a, &b, &c).distance)
            || in_range(ray.intersects_triangle(&a, &c, &b).distance)
    }

    /// Any-hit with the crate's own (infinite) ray.
    fn occluded(&self, a: Vec3, b: Vec3) -> bool {
        let Some((ray, tmin, tmax)) = Self::ray(a, b) else {
            return false;
        };
        self.bvh
            .traverse_iterator(&ray, &self.tris)
            .any(|t| Self::hits(&ray, t, tmin, tmax))
    }

    /// Any-hit with the traversal clipped to the segment.
    fn occluded_segment(&self, a: Vec3, b: Vec3) -> bool {
        let Some((ray, tmin, tmax)) = Self::ray(a, b) else {
            return false;
        };
        let query = SegmentQuery { ray, tmax };
        self.bvh
            .traverse_iterator(&query, &self.tris)
            .any(|t| Self::hits(&query.ray, t, tmin, tmax))
    }
}

/// The referee for disagreements: every triangle, exact Möller–Trumbore in f64, two-sided,
/// no barycentric tolerance, hit when t ∈ (1e-4, 1 − 1e-4) in segment units.
fn brute_force(tris: &[[Vec3; 3]], s: &Segment) -> bool {
    let v = |p: Vec3| p.as_dvec3();
    let (o, d) = (v(s.a), v(s.b) - v(s.a));
    tris.iter().any(|t| {
        let (t0, e1, e2) = (v(t[0]), v(t[1]) - v(t[0]), v(t[2]) - v(t[0]));
        let p = d.cross(e2);
        let det = e1.dot(p);
        if det == 0.0 {
            return false;
        }
        let inv = 1.0 / det;
        let so = o - t0;
        let u = so.dot(p) * inv;
        let q = so.cross(e1);
        let w = d.dot(q) * inv;
        let t = e2.dot(q) * inv;
        (0.0..=1.0).contains(&u) && w >= 0.0 && u + w <= 1.0 && t > 1e-4 && t < 1.0 - 1e-4
    })
}

/// At most this many disagreements per row are checked against [`brute_force`].
const REFEREE_CAP: usize = 2000;

struct Measured {
    rate_1: f64,
    rate_all: f64,
    answers: Vec<bool>,
}

/// Best-of-`repeats` throughput (M rays/s) on one thread and on rayon's pool.
fn measure(segs: &[Segment], repeats: usize, f: impl Fn(Vec3, Vec3) -> bool + Sync) -> Measured {
    let mrays = |secs: f64| segs.len() as f64 / secs / 1e6;
    let mut best_1 = f64::INFINITY;
    let mut answers = Vec::new();
    for _ in 0..repeats {
        let start = Instant::now();
        answers = segs.iter().map(|s| f(s.a, s.b)).collect();
        best_1 = best_1.min(start.elapsed().as_secs_f64());
    }
    let mut best_all = f64::INFINITY;
    for _ in 0..repeats {
        let start = Instant::now();
        let par: Vec<bool> = segs.par_iter().map(|s| f(s.a, s.b)).collect();
        best_all = best_all.min(start.elapsed().as_secs_f64());
        assert_eq!(par, answers, "parallel and sequential answers differ");
    }
    Measured {
        rate_1: mrays(best_1),
        rate_all: mrays(best_all),
        answers,
    }
}

struct Row {
    scene: String,
    triangles: usize,
    krate: &'static str,
    build_ms: String,
    m: Measured,
    /// (segments that differ, of which obvhs hit and this row missed).
    differ: (usize, usize),
    /// (disagreements checked by brute force, of which obvhs had the brute-force answer).
    referee: (usize, usize),
}

fn bench_scene(name: &str, tris: &[[Vec3; 3]], o: &Options, rows: &mut Vec<Row>) {
    eprintln!("{name}: {} triangles", tris.len());
    let segs = make_segments(tris, o.segments, o.seed ^ tris.len() as u64);

    let mut build_obvhs = f64::INFINITY;
    let mut occ = None;
    for _ in 0..o.repeats {
        let start = Instant::now();
        let built = Occluder::new(tris);
        build_obvhs = build_obvhs.min(start.elapsed().as_secs_f64() * 1e3);
        occ = Some(built);
    }
    let occ = occ.expect("built at least once");
    eprintln!("  obvhs built in {build_obvhs:.1} ms; tracing");
    let reference = measure(&segs, o.repeats, |a, b| occ.occluded(a, b));
    drop(occ);

    let mut build_bvh = f64::INFINITY;
    let mut scene = None;
    for _ in 0..o.repeats {
        let (built, ms) = BvhScene::build(tris);
        build_bvh = build_bvh.min(ms);
        scene = Some(built);
    }
    let scene = scene.expect("built at least once");
    eprintln!(
        "  bvh built in {build_bvh:.1} ms ({} nodes); tracing",
        scene.bvh.nodes.len()
    );
    let ray = measure(&segs, o.repeats, |a, b| scene.occluded(a, b));
    eprintln!("  bvh segment query; tracing");
    let seg = measure(&segs, o.repeats, |a, b| scene.occluded_segment(a, b));

    let differ = |m: &Measured| {
        let idx: Vec<usize> = (0..segs.len())
            .filter(|&i| reference.answers[i] != m.answers[i])
            .collect();
        let only_ref = idx.iter().filter(|&&i| reference.answers[i]).count();
        let checked = &idx[..idx.len().min(REFEREE_CAP)];
        let ref_right = checked
            .par_iter()
            .filter(|&&i| brute_force(tris, &segs[i]) == reference.answers[i])
            .count();
        ((idx.len(), only_ref), (checked.len(), ref_right))
    };
    eprintln!("  refereeing disagreements");
    let (d_ray, d_seg) = (differ(&ray), differ(&seg));
    let mut row = |krate, build_ms: String, m: Measured, (differ, referee)| {
        rows.push(Row {
            scene: name.to_owned(),
            triangles: tris.len(),
            krate,
            build_ms,
            m,
            differ,
            referee,
        })
    };
    row(
        "obvhs 0.4 CWBVH (Occluder)",
        format!("{build_obvhs:.1}"),
        reference,
        ((0, 0), (0, 0)),
    );
    row("bvh 0.13 Ray", format!("{build_bvh:.1}"), ray, d_ray);
    row("bvh 0.13 segment query", "(same tree)".into(), seg, d_seg);
}

fn main() {
    let o = parse_args();
    let threads = rayon::current_num_threads();
    eprintln!(
        "{} segments per scene, best of {} runs, {threads} rayon threads",
        o.segments, o.repeats
    );
    let mut rows = Vec::new();

    let tris = cornell(130_000);
    bench_scene("cornell (subdivided)", &tris, &o, &mut rows);

    let mut skipped = None;
    match obj_triangles(&o.bunny) {
        Ok(tris) if !tris.is_empty() => bench_scene("stanford bunny", &tris, &o, &mut rows),
        Ok(_) => skipped = Some(format!("{}: no triangles", o.bunny.display())),
        Err(e) => skipped = Some(format!("{}: {e}", o.bunny.display())),
    }
    if let Some(why) = &skipped {
        eprintln!("skipping the bunny: {why}");
    }

    let tris = random_soup(100_000, o.soup_half, o.seed);
    bench_scene("random overlapping", &tris, &o, &mut rows);

    println!(
        "{} segments per scene, best of {} runs; all threads = {threads} rayon threads.\n",
        o.segments, o.repeats
    );
    println!(
        "| scene | triangles | crate | build ms | M rays/s (1 thread) | M rays/s (all threads) | agreement % | occluded % |"
    );
    println!("| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: |");
    for r in &rows {
        let n = r.m.answers.len().max(1) as f64;
        let hits = r.m.answers.iter().filter(|&&h| h).count() as f64;
        let agree = if r.krate.starts_with("obvhs") {
            "(reference)".to_owned()
        } else {
            format!("{:.4}", 100.0 * (1.0 - r.differ.0 as f64 / n))
        };
        println!(
            "| {} | {} | {} | {} | {:.2} | {:.2} | {} | {:.1} |",
            r.scene,
            r.triangles,
            r.krate,
            r.build_ms,
            r.m.rate_1,
            r.m.rate_all,
            agree,
            100.0 * hits / n
        );
    }
    println!(
        "\nDisagreements with obvhs; the first {REFEREE_CAP} of each row checked against an \
         exact f64 brute force over all triangles (two-sided, no tolerance):\n"
    );
    for r in rows.iter().filter(|r| !r.krate.starts_with("obvhs")) {
        println!(
            "- {}, {}: {} of {} segments (obvhs hit, this row missed: {}; the reverse: {}); \
             brute force agrees with obvhs on {} of {} checked",
            r.scene,
            r.krate,
            r.differ.0,
            r.m.answers.len(),
            r.differ.1,
            r.differ.0 - r.differ.1,
            r.referee.1,
            r.referee.0
        );
    }
    if let Some(why) = skipped {
        println!("\nStanford bunny skipped: {why}");
    }
}
