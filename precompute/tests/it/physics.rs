//! Physics of the foundation against answers no one here wrote: closed-form form factors
//! (Howell's catalogue of configuration factors), conservation in a closed room, occlusion,
//! and the furnace B = Bₑ/(1 − ρ).
//!
//! Where new tests go: form-factor accuracy here; scene/bundle/CLI behaviour in the modules'
//! unit tests and in the `translux-tests` crate.

use std::f64::consts::PI;

use glam::Vec3;
use translux_engine::radiosity::{self, SolveParams};
use translux_engine::raycast::Occluder;
use translux_precompute::formfactor::{self, FormFactorParams};
use translux_precompute::patch::{self, Density, Patches};
use translux_proto::csr::Csr;

/// A rectangle from `origin` spanned by `u` and `v`, facing u × v.
fn rect(origin: Vec3, u: Vec3, v: Vec3) -> Vec<[Vec3; 3]> {
    let (a, b, c, d) = (origin, origin + u, origin + u + v, origin + v);
    vec![[a, b, c], [a, c, d]]
}

fn build(objects: &[Vec<[Vec3; 3]>], density: Density) -> (Patches, Csr) {
    let srcs: Vec<&[[Vec3; 3]]> = objects.iter().map(|o| o.as_slice()).collect();
    let (h, _) = patch::plan(&srcs, density);
    let p = patch::subdivide(&srcs, h);
    let all: Vec<[Vec3; 3]> = objects.iter().flatten().copied().collect();
    let occ = Occluder::new(&all);
    let (f, _) = formfactor::compute(&p, &occ, &FormFactorParams::default(), &|_| {});
    (p, f)
}

/// Object-to-object form factor F_AB = Σ_{i∈A} A_i Σ_{j∈B} F_ij / Σ_{i∈A} A_i.
fn object_ff(p: &Patches, f: &Csr, a: usize, b: usize) -> f64 {
    let v = f.view().unwrap();
    let rb = p.object_ranges[b].clone();
    let mut num = 0.0;
    let mut den = 0.0;
    for i in p.object_ranges[a].clone() {
        let (cols, vals) = v.row(i);
        let s: f64 = cols
            .iter()
            .zip(vals)
            .filter(|(c, _)| rb.contains(&(**c as usize)))
            .map(|(_, &x)| x as f64)
            .sum();
        num += p.area[i] as f64 * s;
        den += p.area[i] as f64;
    }
    num / den
}

/// Parallel, directly opposed rectangles a × b at distance c (Howell, C-11).
fn parallel_rectangles(a: f64, b: f64, c: f64) -> f64 {
    let (x, y) = (a / c, b / c);
    let (x2, y2) = (x * x, y * y);
    2.0 / (PI * x * y)
        * (((1.0 + x2) * (1.0 + y2) / (1.0 + x2 + y2)).sqrt().ln()
            + x * (1.0 + y2).sqrt() * (x / (1.0 + y2).sqrt()).atan()
            + y * (1.0 + x2).sqrt() * (y / (1.0 + x2).sqrt()).atan()
            - x * x.atan()
            - y * y.atan())
}

/// Perpendicular rectangles with a common edge of length l; from the one of width w to the
/// one of height h (Howell, C-14).
fn perpendicular_rectangles(l: f64, w: f64, h: f64) -> f64 {
    let (hh, ww) = (h / l, w / l);
    let (h2, w2) = (hh * hh, ww * ww);
    let s = h2 + w2;
    let log = ((1.0 + w2) * (1.0 + h2) / (1.0 + s)).ln()
        + w2 * (w2 * (1.0 + s) / ((1.0 + w2) * s)).ln()
        + h2 * (h2 * (1.0 + s) / ((1.0 + h2) * s)).ln();
    (ww * (1.0 / ww).atan() + hh * (1.0 / hh).atan() - s.sqrt() * (1.0 / s.sqrt()).atan()
        + 0.25 * log)
        / (PI * ww)
}

#[test]
fn parallel_squares_match_closed_form() {
    for (side, dist) in [(1.0f32, 1.0f32), (1.0, 0.5), (2.0, 0.4)] {
        // Bottom faces up, top faces down.
        let bottom = rect(Vec3::ZERO, Vec3::Z * side, Vec3::X * side);
        let top = rect(Vec3::Y * dist, Vec3::X * side, Vec3::Z * side);
        let (p, f) = build(&[bottom, top], Density::Target(1600));
        let got = object_ff(&p, &f, 0, 1);
        let exact = parallel_rectangles(side as f64, side as f64, dist as f64);
        let rel = (got - exact).abs() / exact;
        eprintln!(
            "parallel squares side {side} dist {dist}: {got:.5} vs {exact:.5} ({:.3}%)",
            rel * 100.0
        );
        assert!(
            rel < 0.01,
            "side {side} dist {dist}: {got:.5} vs {exact:.5} ({:.2}%)",
            rel * 100.0
        );
        // Reciprocity holds at the object level too (equal areas: F_AB = F_BA).
        let back = object_ff(&p, &f, 1, 0);
        assert!((back - got).abs() / got < 1e-3);
    }
}

#[test]
fn perpendicular_rectangles_sharing_an_edge_match_closed_form() {
    for (l, w, h) in [(1.0f32, 1.0f32, 1.0f32), (1.0, 0.5, 2.0), (2.0, 1.0, 0.5)] {
        // Floor: x ∈ [0, w], z ∈ [0, l], facing +y. Wall: x = 0, y ∈ [0, h], facing +x.
        let floor = rect(Vec3::ZERO, Vec3::Z * l, Vec3::X * w);
        let wall = rect(Vec3::ZERO, Vec3::Y * h, Vec3::Z * l);
        let (p, f) = build(&[floor, wall], Density::Target(2000));
        let got = object_ff(&p, &f, 0, 1);
        let exact = perpendicular_rectangles(l as f64, w as f64, h as f64);
        let rel = (got - exact).abs() / exact;
        eprintln!(
            "perpendicular l {l} w {w} h {h}: {got:.5} vs {exact:.5} ({:.3}%)",
            rel * 100.0
        );
        assert!(
            rel < 0.01,
            "l {l} w {w} h {h}: {got:.5} vs {exact:.5} ({:.2}%)",
            rel * 100.0
        );
    }
}

/// The six inward faces of a w × h × d room with a corner at the origin.
fn room(w: f32, h: f32, d: f32) -> Vec<Vec<[Vec3; 3]>> {
    let (x, y, z) = (Vec3::X * w, Vec3::Y * h, Vec3::Z * d);
    vec![
        rect(Vec3::ZERO, z, x), // floor, +y
        rect(y, x, z),          // ceiling, −y
        rect(Vec3::ZERO, x, y), // back (z = 0), +z
        rect(z, y, x),          // front (z = d), −z
        rect(Vec3::ZERO, y, z), // left (x = 0), +x
        rect(x, z, y),          // right (x = w), −x
    ]
}

#[test]
fn closed_room_rows_sum_to_one_and_reciprocity_holds() {
    let (p, f) = build(&room(1.0, 0.8, 1.3), Density::Target(3000));
    let v = f.view().unwrap();
    let mut worst = 0.0f64;
    for i in 0..p.len() {
        let s: f64 = v.row(i).1.iter().map(|&x| x as f64).sum();
        worst = worst.max((s - 1.0).abs());
    }
    eprintln!(
        "closed room: {} patches, worst row-sum error {:.3}%",
        p.len(),
        worst * 100.0
    );
    assert!(worst < 0.01, "worst row sum error {:.3}%", worst * 100.0);
    // A_i F_ij = A_j F_ji for every stored pair, and the pattern is symmetric.
    for i in (0..p.len()).step_by(7) {
        let (cols, vals) = v.row(i);
        for (&j, &fij) in cols.iter().zip(vals) {
            let fji = v.get(j as usize, i);
            let (l, r) = (p.area[i] * fij, p.area[j as usize] * fji);
            assert!(
                (l - r).abs() <= 1e-5 * l.max(r),
                "pair ({i},{j}): {l} vs {r}"
            );
        }
    }
}

#[test]
fn a_plate_between_two_plates_blocks_their_exchange() {
    let bottom = rect(Vec3::ZERO, Vec3::Z, Vec3::X);
    let top = rect(Vec3::Y, Vec3::X, Vec3::Z);
    // Open case first, so the test can tell blocking from a broken computation.
    let (p, f) = build(&[bottom.clone(), top.clone()], Density::Target(400));
    assert!(object_ff(&p, &f, 0, 1) > 0.15);
    // A larger plate half-way (facing up) hides them from each other completely.
    let blocker = rect(Vec3::new(-0.5, 0.5, -0.5), Vec3::Z * 2.0, Vec3::X * 2.0);
    let (p, f) = build(&[bottom, top, blocker], Density::Target(600));
    assert_eq!(object_ff(&p, &f, 0, 1), 0.0);
    assert_eq!(object_ff(&p, &f, 1, 0), 0.0);
    // The blocker still sees the top plate.
    assert!(object_ff(&p, &f, 2, 1) > 0.1);
}

#[test]
fn furnace_gives_emission_over_one_minus_albedo() {
    let (p, f) = build(&room(1.0, 1.0, 1.0), Density::Target(2400));
    let v = translux_engine::transport::Transport::dense(f.view().unwrap());
    let n = p.len();
    for rho in [0.3f32, 0.5, 0.8] {
        let albedo = vec![[rho; 3]; n];
        let be = vec![[1.0f32, 2.0, 0.5]; n];
        let e = vec![[0.0f32; 3]; n];
        let params = SolveParams {
            tolerance: 1e-4,
            max_iterations: 2000,
            ..Default::default()
        };
        let (b, stats) = radiosity::solve_diffuse(&v, &albedo, &be, &e, &params, None);
        assert!(stats.converged, "{stats:?}");
        // Row sums are 1 within 1%, so B is within ρ·1%/(1 − ρ) of exact.
        let tol = (rho as f64 * 0.01 / (1.0 - rho as f64)).max(0.002);
        for c in 0..3 {
            let exact = be[0][c] as f64 / (1.0 - rho as f64);
            let mean: f64 = b.iter().map(|x| x[c] as f64).sum::<f64>() / n as f64;
            let worst = b
                .iter()
                .map(|x| (x[c] as f64 - exact).abs() / exact)
                .fold(0.0, f64::max);
            assert!(
                (mean - exact).abs() / exact < tol,
                "ρ {rho}: mean {mean} vs {exact}"
            );
            assert!(
                worst < 2.0 * tol,
                "ρ {rho}: worst patch off by {:.2}%",
                worst * 100.0
            );
        }
        // Uniform irradiance instead of emission: B = ρE/(1 − ρ).
        let e = vec![[1.0f32; 3]; n];
        let zero = vec![[0.0f32; 3]; n];
        let (b, _) = radiosity::solve_diffuse(&v, &albedo, &zero, &e, &params, None);
        let exact = rho as f64 / (1.0 - rho as f64);
        let mean: f64 = b.iter().map(|x| x[1] as f64).sum::<f64>() / n as f64;
        assert!(
            (mean - exact).abs() / exact < tol,
            "ρ {rho}: {mean} vs {exact}"
        );
    }
}

#[test]
fn point_light_over_a_plane_gives_inverse_square_cosine() {
    // E = I cos θ / r², r in metres (unit_mm = 1000), shadows from a small blocker.
    let floor = rect(Vec3::new(-1.0, 0.0, -1.0), Vec3::Z * 2.0, Vec3::X * 2.0);
    let srcs: Vec<&[[Vec3; 3]]> = vec![&floor];
    let (h, _) = patch::plan(&srcs, Density::Target(800));
    let p = patch::subdivide(&srcs, h);
    let occ = Occluder::new(&floor);
    let light = translux_proto::light::Light::Point {
        position: [0.2, 1.5, -0.1],
        intensity: [2.0, 1.0, 0.5],
    };
    let geo = radiosity::PatchGeometry {
        centroid: &p.centroid,
        normal: &p.normal,
    };
    let e = radiosity::direct_irradiance(geo, &occ, std::slice::from_ref(&light), 1000.0).unwrap();
    for (c, e) in p.centroid.iter().zip(&e) {
        let d = Vec3::new(0.2, 1.5, -0.1) - *c;
        let exact = d.y / d.length() / d.length_squared();
        assert!((e[0] - 2.0 * exact).abs() / (2.0 * exact) < 1e-3);
        assert!((e[2] - 0.5 * exact).abs() / (0.5 * exact) < 1e-3);
    }
    // In millimetres the same numbers mean a light 1000× closer: E scales by 10⁶.
    let e_mm = radiosity::direct_irradiance(geo, &occ, std::slice::from_ref(&light), 1.0).unwrap();
    assert!((e_mm[0][0] / e[0][0] - 1e6).abs() / 1e6 < 1e-3);
    // A blocker above the middle casts a shadow there.
    let mut with_blocker = floor.clone();
    with_blocker.extend(rect(
        Vec3::new(0.0, 0.5, -0.3),
        Vec3::X * 0.3,
        Vec3::Z * 0.3,
    ));
    let occ = Occluder::new(&with_blocker);
    let e = radiosity::direct_irradiance(geo, &occ, &[light], 1000.0).unwrap();
    let shadowed = p
        .centroid
        .iter()
        .zip(&e)
        .filter(|(c, e)| c.x > 0.05 && c.x < 0.2 && c.z > -0.15 && c.z < 0.0 && e[0] == 0.0)
        .count();
    assert!(shadowed > 0, "no patch under the blocker is in shadow");
}

#[test]
fn thresholding_reports_exactly_the_power_it_drops() {
    let objects = room(1.0, 0.8, 1.3);
    let srcs: Vec<&[[Vec3; 3]]> = objects.iter().map(|o| o.as_slice()).collect();
    let (h, _) = patch::plan(&srcs, Density::Target(1500));
    let p = patch::subdivide(&srcs, h);
    let all: Vec<[Vec3; 3]> = objects.iter().flatten().copied().collect();
    let occ = Occluder::new(&all);
    let power = |f: &Csr| -> f64 {
        let v = f.view().unwrap();
        (0..p.len())
            .map(|i| p.area[i] as f64 * v.row(i).1.iter().map(|&x| x as f64).sum::<f64>())
            .sum()
    };
    let (full, info0) = formfactor::compute(&p, &occ, &FormFactorParams::default(), &|_| {});
    assert_eq!(info0.dropped_energy, 0.0);
    let params = FormFactorParams {
        threshold: 2e-4,
        ..Default::default()
    };
    let (cut, info) = formfactor::compute(&p, &occ, &params, &|_| {});
    assert!(cut.nnz() < full.nnz(), "the threshold dropped nothing");
    assert!(cut.val.iter().all(|&v| v >= 2e-4));
    let total_area: f64 = p.area.iter().map(|&a| a as f64).sum();
    let lost = (power(&full) - power(&cut)) / total_area;
    assert!(info.dropped_energy > 0.0);
    assert!(
        (lost - info.dropped_energy).abs() < 1e-4 * lost.max(1e-9) + 1e-7,
        "{lost} vs {}",
        info.dropped_energy
    );
}
