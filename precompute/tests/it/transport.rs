//! Full transport: the solvers agree with each other and with closed forms, Krylov beats
//! Jacobi where it should, warm starts pay, and the light components mean what their
//! definitions say.
//!
//! Where new tests go: solver and component behaviour here; the transfer matrix T in
//! `inverse.rs`; server-side behaviour in the `translux-tests` crate.

use glam::Vec3;
use translux_engine::radiosity::{self, Albedo, Method, Rgb, SolveParams, SparseScatter};
use translux_engine::raycast::Occluder;
use translux_engine::transport::Transport;
use translux_precompute::formfactor::{self, FormFactorParams};
use translux_precompute::patch::{self, Density, Patches};
use translux_precompute::pipeline::{PrecomputeParams, precompute};
use translux_precompute::scene::load_scene;
use translux_proto::bundle::Bundle;
use translux_proto::csr::Csr;

/// A rectangle from `origin` spanned by `u` and `v`, facing u × v.
fn rect(origin: Vec3, u: Vec3, v: Vec3) -> Vec<[Vec3; 3]> {
    let (a, b, c, d) = (origin, origin + u, origin + u + v, origin + v);
    vec![[a, b, c], [a, c, d]]
}

/// A closed box w × h × d, every face facing inwards.
fn room(w: f32, h: f32, d: f32) -> Vec<Vec<[Vec3; 3]>> {
    let (x, y, z) = (Vec3::X * w, Vec3::Y * h, Vec3::Z * d);
    vec![
        rect(Vec3::ZERO, z, x),
        rect(y, x, z),
        rect(Vec3::ZERO, x, y),
        rect(z, y, x),
        rect(Vec3::ZERO, y, z),
        rect(x, z, y),
    ]
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

/// ‖a − b‖₂ / ‖b‖₂ over every patch and channel.
fn rel_diff(a: &[Rgb], b: &[Rgb]) -> f64 {
    let (mut num, mut den) = (0.0f64, 0.0f64);
    for (x, y) in a.iter().zip(b) {
        for c in 0..3 {
            num += ((x[c] - y[c]) as f64).powi(2);
            den += (y[c] as f64).powi(2);
        }
    }
    (num / den).sqrt()
}

/// A small translucent Cornell box (the paper's, real marble) and its ceiling lamp's E.
fn translucent_cornell(patches: u64) -> (tempfile::TempDir, Bundle, Vec<Rgb>) {
    let dir = tempfile::tempdir().unwrap();
    let scene = load_scene("builtin:cornell_paper").unwrap();
    let out = dir.path().join("cornell");
    let params = PrecomputeParams {
        patches: Some(patches),
        ..Default::default()
    };
    precompute(&scene, &out, &params).unwrap();
    let b = Bundle::open(&out).unwrap();
    let e = direct(&b);
    (dir, b, e)
}

fn direct(b: &Bundle) -> Vec<Rgb> {
    radiosity::BundleLighting::new(b)
        .irradiance(&b.manifest().lights)
        .unwrap()
}

fn params(method: Method, tolerance: f32) -> SolveParams {
    SolveParams {
        method,
        tolerance,
        max_iterations: 5000,
    }
}

#[test]
fn bicgstab_equals_jacobi_on_a_translucent_scene() {
    let (_dir, b, e) = translucent_cornell(1200);
    let f = Transport::of(&b);
    let s = SparseScatter(b.subsurface());
    let be = b.patch_emission();
    // A tight Jacobi solution is the reference.
    let (reference, rs) =
        radiosity::solve(&f, &s, be, &e, &params(Method::Jacobi, 1e-6), None).unwrap();
    assert!(rs.converged, "{rs:?}");
    for tol in [1e-5f32, 0.005] {
        let (jac, js) =
            radiosity::solve(&f, &s, be, &e, &params(Method::Jacobi, tol), None).unwrap();
        let (kry, ks) =
            radiosity::solve(&f, &s, be, &e, &params(Method::BiCgStab, tol), None).unwrap();
        assert!(js.converged && ks.converged, "{js:?} {ks:?}");
        // Deterministic: the same inputs give the same bits.
        let (again, _) =
            radiosity::solve(&f, &s, be, &e, &params(Method::BiCgStab, tol), None).unwrap();
        assert!(again == kry, "two identical BiCGSTAB solves differ");
        assert!(ks.residual <= tol && js.residual <= tol);
        let (dj, dk) = (rel_diff(&jac, &reference), rel_diff(&kry, &reference));
        eprintln!(
            "tolerance {tol}: jacobi {} iterations ({} products), error {dj:.2e}; \
             bicgstab {} iterations ({} products), error {dk:.2e}",
            js.iterations, js.products, ks.iterations, ks.products
        );
        // The error of a solution with relative residual τ is at most κ·τ; here κ(I − SF)
        // ≤ (1 + ‖SF‖)/(1 − ‖SF‖) is a few, so both must be within a few τ of the reference.
        assert!(dk <= 5.0 * tol as f64 + 1e-6, "bicgstab {dk}");
        assert!(dj <= 5.0 * tol as f64 + 1e-6, "jacobi {dj}");
        // In the Cornell box (ρ ≤ 0.73) auto stays with Jacobi.
        let (_, auto) = radiosity::solve(&f, &s, be, &e, &params(Method::Auto, tol), None).unwrap();
        assert_eq!(auto.method, Method::Jacobi, "{auto:?}");
        // Every bright patch agrees per channel at the tight tolerance.
        if tol < 1e-4 {
            let peak = reference
                .iter()
                .flat_map(|x| x.iter())
                .fold(0.0f32, |a, &v| a.max(v));
            for (k, (x, y)) in kry.iter().zip(&reference).enumerate() {
                for c in 0..3 {
                    if y[c] > 0.01 * peak {
                        let d = (x[c] - y[c]).abs() / y[c];
                        assert!(d < 1e-3, "patch {k} channel {c}: {} vs {}", x[c], y[c]);
                    }
                }
            }
        }
    }
}

#[test]
fn bicgstab_needs_far_fewer_products_in_a_bright_closed_room() {
    let (p, f) = build(&room(1.0, 0.9, 1.2), Density::Target(1500));
    let v = Transport::dense(f.view().unwrap());
    let n = p.len();
    let rho = 0.98f32;
    let albedo = vec![[rho, 0.97, 0.96]; n];
    // A light on part of the ceiling.
    let be: Vec<Rgb> = (0..n)
        .map(|i| {
            let c = (p.corners[i][0] + p.corners[i][1] + p.corners[i][2]) / 3.0;
            if c.y > 0.89 && (c.x - 0.5).abs() < 0.2 && (c.z - 0.6).abs() < 0.2 {
                [10.0; 3]
            } else {
                [0.0; 3]
            }
        })
        .collect();
    let e = vec![[0.0f32; 3]; n];
    let s = Albedo(&albedo);
    let tol = 0.005;
    let (jac, js) = radiosity::solve(&v, &s, &be, &e, &params(Method::Jacobi, tol), None).unwrap();
    let (kry, ks) =
        radiosity::solve(&v, &s, &be, &e, &params(Method::BiCgStab, tol), None).unwrap();
    let (gs, gss) =
        radiosity::solve(&v, &s, &be, &e, &params(Method::GaussSeidel, tol), None).unwrap();
    eprintln!(
        "closed room, {n} patches, rho {rho}: jacobi {} iterations / {} products; \
         gauss-seidel {} / {}; bicgstab {} / {}",
        js.iterations, js.products, gss.iterations, gss.products, ks.iterations, ks.products
    );
    assert!(js.converged && ks.converged && gss.converged);
    // Auto measures Jacobi's slow contraction and switches to BiCGSTAB.
    let (_, auto) = radiosity::solve(&v, &s, &be, &e, &params(Method::Auto, tol), None).unwrap();
    eprintln!("auto: {auto:?}");
    assert_eq!(auto.method, Method::BiCgStab);
    assert!(
        auto.converged && auto.products * 3 < js.products,
        "{auto:?}"
    );
    // Jacobi contracts like ρ per sweep, and its step along the residual (at most
    // `solver::MAX_STEP` = 1.9 times it) like 1 − 1.9 (1 − ρ): still on the order of
    // ln(τ)/ln(1 − 1.9 (1 − ρ)) products (122 here; 178 without the longer step).
    assert!(js.products > 60, "{js:?}");
    assert!(
        ks.products * 3 < js.products,
        "bicgstab {ks:?} vs jacobi {js:?}"
    );
    // Same answer (to a few tolerances; κ is larger here, ≈ (1 + ρ)/(1 − ρ)).
    assert!(rel_diff(&kry, &jac) < 0.1, "{}", rel_diff(&kry, &jac));
    assert!(rel_diff(&gs, &jac) < 0.1);
    // The closed room's total power balance: Σ A B (1 − ρ) = Σ A Bₑ (all light absorbed
    // eventually) within the row-sum error (~1%) and the tolerance.
    let absorbed: f64 = (0..n)
        .map(|i| p.area[i] as f64 * kry[i][0] as f64 * (1.0 - albedo[i][0] as f64))
        .sum();
    let emitted: f64 = (0..n).map(|i| p.area[i] as f64 * be[i][0] as f64).sum();
    assert!(
        (absorbed / emitted - 1.0).abs() < 0.1,
        "absorbed {absorbed} emitted {emitted}"
    );
}

/// A Jacobi iteration steps along its residual as far as minimises the next residual:
/// where K F has one bright mode (every patch sees the same average of all, at albedo ρ:
/// K F = ρ J/n), plain Jacobi leaves ρ of that mode's error each sweep and the longer step
/// 1 − 1.9 (1 − ρ) of it. The answer is the closed form x = b + ρ/(1 − ρ) mean(b).
#[test]
fn a_jacobi_step_along_its_residual_removes_a_bright_mode_faster() {
    use translux_engine::solver::{MAX_STEP, solve_system};
    let n = 300usize;
    let f = Csr::from_rows(
        n,
        (0..n).map(|_| {
            (0..n as u32)
                .map(|j| (j, 1.0 / n as f32))
                .collect::<Vec<_>>()
        }),
    )
    .unwrap();
    let t = Transport::dense(f.view().unwrap());
    let rho = [0.5f32, 0.8, 0.9];
    let albedo = vec![rho; n];
    let k = Albedo(&albedo);
    let b: Vec<f32> = (0..n)
        .flat_map(|i| {
            let v = 1.0 + (i as f32 * 0.37).sin();
            [v, 0.5 * v, 2.0 - v]
        })
        .collect();
    // Above f32's floor here (a residual of ~2e-5 of ‖b‖ from the dense product's rounding).
    let tol = 1e-4f32;
    let (x, st) = solve_system(&t, &k, &b, 3, &params(Method::Jacobi, tol), None).unwrap();
    assert!(st.converged, "{st:?}");
    // The closed form, per channel.
    for c in 0..3 {
        let mean = (0..n).map(|i| b[3 * i + c] as f64).sum::<f64>() / n as f64;
        let r = rho[c] as f64;
        for i in 0..n {
            let want = b[3 * i + c] as f64 + r / (1.0 - r) * mean;
            let got = x[3 * i + c] as f64;
            // The residual τ relative to ‖b‖ bounds the error by κ τ, κ = (1 + ρ)/(1 − ρ).
            assert!(
                (got - want).abs() <= 20.0 * tol as f64 * want.abs().max(1.0),
                "channel {c} patch {i}: {got} vs {want}"
            );
        }
    }
    // From b, the residual is all in the bright mode: plain Jacobi needs
    // ln(τ)/ln(ρ) sweeps for the brightest channel (87 at ρ = 0.9), the longer step
    // ln(τ)/ln(1 − MAX_STEP (1 − ρ)) (44), each with one product.
    let plain = (tol as f64).ln() / 0.9f64.ln();
    let longer = (tol as f64).ln() / (1.0 - MAX_STEP * 0.1).ln();
    eprintln!(
        "one bright mode: {} iterations ({} products); plain Jacobi would take {plain:.0}, the \
         longer step {longer:.0}",
        st.iterations, st.products
    );
    assert!(
        (st.iterations as f64) <= longer.ceil() + 1.0 && (st.iterations as f64) < 0.6 * plain,
        "{st:?}"
    );
}

#[test]
fn warm_start_from_a_nearby_solution_needs_fewer_iterations() {
    let (_dir, b, e) = translucent_cornell(1200);
    let f = Transport::of(&b);
    let s = SparseScatter(b.subsurface());
    let be = b.patch_emission();
    // The light moved a little: 5% brighter and a tint.
    let e2: Vec<Rgb> = e
        .iter()
        .map(|x| [x[0] * 1.05, x[1] * 1.04, x[2] * 1.06])
        .collect();
    for method in [Method::Jacobi, Method::BiCgStab] {
        let p = params(method, 0.001);
        let (first, _) = radiosity::solve(&f, &s, be, &e, &p, None).unwrap();
        let (cold_x, cold) = radiosity::solve(&f, &s, be, &e2, &p, None).unwrap();
        let (warm_x, warm) = radiosity::solve(&f, &s, be, &e2, &p, Some(&first)).unwrap();
        eprintln!(
            "{}: cold {} iterations ({} products), warm {} iterations ({} products)",
            method.as_str(),
            cold.iterations,
            cold.products,
            warm.iterations,
            warm.products
        );
        assert!(warm.warm && !cold.warm);
        assert!(cold.converged && warm.converged);
        assert!(
            warm.products < cold.products,
            "{method:?}: warm {warm:?} cold {cold:?}"
        );
        assert!(rel_diff(&warm_x, &cold_x) < 0.01);
    }
}

/// The bundle's S with every entry times `t`.
fn scaled_s(b: &Bundle, t: f32) -> Csr<Rgb> {
    let v = b.subsurface();
    Csr {
        n_rows: v.n_rows(),
        n_cols: v.n_cols(),
        row_ptr: v.row_ptr().to_vec(),
        col: v.col().to_vec(),
        val: v.val().iter().map(|x| x.map(|c| t * c)).collect(),
    }
}

#[test]
fn a_primed_warm_start_answers_as_the_plain_one_with_a_product_less() {
    use translux_engine::solver::{Primed, solve_primed, solve_system};
    let (_dir, b, e) = translucent_cornell(800);
    let f = Transport::of(&b);
    let s = SparseScatter(b.subsurface());
    // Another K: the same S a little less translucent (what a slider step does to S).
    let s2_csr = scaled_s(&b, 0.93);
    let s2 = SparseScatter(s2_csr.view().unwrap());
    let mut se = vec![[0.0f32; 3]; e.len()];
    radiosity::Scatter::apply(&s, &e, &mut se);
    let rhs: &[f32] = bytemuck::cast_slice(&se);
    // The light moved a little.
    let rhs2: Vec<f32> = rhs
        .chunks(3)
        .flat_map(|x| [x[0] * 1.05, x[1] * 1.04, x[2] * 0.0])
        .collect();
    for method in [Method::Jacobi, Method::BiCgStab, Method::Auto] {
        let p = params(method, 1e-3);
        let first = solve_primed(&f, &s, rhs, 3, &p, None, None).unwrap();
        // Its products are its answer's: F x and K F x (a Jacobi iteration's step along its
        // residual derives them from two passes, so they agree to f32 rounding, not bits).
        let mut fx = vec![0.0f32; rhs.len()];
        f.apply_multi(&first.x, &mut fx, 3, &mut Default::default());
        let mut kfx = vec![0.0f32; rhs.len()];
        radiosity::Scatter::apply_multi(&s, &fx, &mut kfx, 3);
        let close =
            |a: &[f32], b: &[f32]| rel_diff(bytemuck::cast_slice(a), bytemuck::cast_slice(b));
        assert!(
            close(&first.fx, &fx) < 1e-5,
            "{method:?}: {}",
            close(&first.fx, &fx)
        );
        assert!(
            close(&first.kfx, &kfx) < 1e-5,
            "{method:?}: {}",
            close(&first.kfx, &kfx)
        );
        for (k, same_k) in [(&s, true), (&s2, false)] {
            let plain = solve_system(&f, k, &rhs2, 3, &p, Some(&first.x)).unwrap();
            let primed = Primed {
                fx: &first.fx,
                kfx: same_k.then_some(first.kfx.as_slice()),
                before: None,
                age: 0,
            };
            let quick = solve_primed(&f, k, &rhs2, 3, &p, Some(&first.x), Some(primed)).unwrap();
            eprintln!(
                "{method:?}, same K {same_k}: {} products from a plain warm start, {} primed",
                plain.1.products, quick.stats.products
            );
            // The same answer to the kept products' rounding (bit for bit where they came
            // out of a pass, as BiCGSTAB's do).
            let d = close(&quick.x, &plain.0);
            assert!(d < 1e-5, "{method:?} same K {same_k}: {d}");
            if method == Method::BiCgStab {
                assert_eq!(quick.x, plain.0, "{method:?} same K {same_k}");
            }
            assert_eq!(quick.stats.iterations, plain.1.iterations);
            assert!((quick.stats.residual - plain.1.residual).abs() <= 1e-3 * plain.1.residual);
            assert_eq!(quick.stats.products + 1, plain.1.products);
            // Primed products of another length, or not finite, are ignored.
            let bad = vec![f32::NAN; rhs.len()];
            for fx in [&first.fx[3..], bad.as_slice()] {
                let p2 = Primed {
                    fx,
                    kfx: None,
                    before: None,
                    age: 0,
                };
                let q = solve_primed(&f, k, &rhs2, 3, &p, Some(&first.x), Some(p2)).unwrap();
                assert_eq!(q.stats.products, plain.1.products);
                assert_eq!(q.x, plain.0);
            }
        }
        // Asked again with the same K and b, a primed start is its own answer at no product.
        let again = solve_primed(
            &f,
            &s,
            rhs,
            3,
            &p,
            Some(&first.x),
            Some(Primed {
                fx: &first.fx,
                kfx: Some(&first.kfx),
                before: None,
                age: 0,
            }),
        )
        .unwrap();
        assert_eq!(again.stats.products, 0, "{method:?}");
        assert_eq!(again.x, first.x);
    }
}

#[test]
fn a_steady_change_is_extrapolated_along_its_last_step() {
    use translux_engine::solver::{Before, MAX_PRIMED_AGE, Primed, solve_primed};
    let (_dir, b, e) = translucent_cornell(800);
    let f = Transport::of(&b);
    // S a little less translucent at each step, as a slider moved at a steady pace.
    let steps: Vec<Csr<Rgb>> = [1.0, 0.95, 0.9]
        .into_iter()
        .map(|t| scaled_s(&b, t))
        .collect();
    let ks: Vec<SparseScatter> = steps
        .iter()
        .map(|c| SparseScatter(c.view().unwrap()))
        .collect();
    let rhs_of = |k: &SparseScatter| -> Vec<f32> {
        let mut se = vec![[0.0f32; 3]; e.len()];
        radiosity::Scatter::apply(k, &e, &mut se);
        bytemuck::cast_slice(&se).to_vec()
    };
    let p = params(Method::Jacobi, 0.005);
    let tight = params(Method::Jacobi, 1e-6);
    let x0 = solve_primed(&f, &ks[0], &rhs_of(&ks[0]), 3, &p, None, None).unwrap();
    fn primed(w: &translux_engine::solver::Solved) -> Primed<'_> {
        Primed {
            fx: &w.fx,
            kfx: None,
            before: None,
            age: 0,
        }
    }
    let x1 = solve_primed(
        &f,
        &ks[1],
        &rhs_of(&ks[1]),
        3,
        &p,
        Some(&x0.x),
        Some(primed(&x0)),
    )
    .unwrap();
    let rhs2 = rhs_of(&ks[2]);
    let plain = solve_primed(&f, &ks[2], &rhs2, 3, &p, Some(&x1.x), Some(primed(&x1))).unwrap();
    let along = solve_primed(
        &f,
        &ks[2],
        &rhs2,
        3,
        &p,
        Some(&x1.x),
        Some(Primed {
            before: Some(Before {
                x: &x0.x,
                fx: &x0.fx,
                kfx: None,
            }),
            ..primed(&x1)
        }),
    )
    .unwrap();
    let exact = solve_primed(&f, &ks[2], &rhs2, 3, &tight, None, None).unwrap();
    let err = |x: &[f32]| rel_diff(bytemuck::cast_slice(x), bytemuck::cast_slice(&exact.x));
    eprintln!(
        "third step: {} products from the last answer ({:.2e} from exact), {} extrapolated \
         ({:.2e})",
        plain.stats.products,
        err(&plain.x),
        along.stats.products,
        err(&along.x)
    );
    assert!(plain.stats.converged && along.stats.converged);
    assert!(along.stats.products < plain.stats.products);
    assert!(err(&along.x) < 0.01);

    // A light brightening at a steady pace under one S: the kept K F x of both answers make
    // the extrapolation free of any pass.
    let k = &ks[0];
    let base = rhs_of(k);
    let at = |t: f32| -> Vec<f32> { base.iter().map(|v| v * t).collect() };
    let a = solve_primed(&f, k, &at(1.0), 3, &p, None, None).unwrap();
    fn full(w: &translux_engine::solver::Solved) -> Primed<'_> {
        Primed {
            fx: &w.fx,
            kfx: Some(&w.kfx),
            before: None,
            age: 0,
        }
    }
    let b1 = solve_primed(&f, k, &at(1.1), 3, &p, Some(&a.x), Some(full(&a))).unwrap();
    let plain = solve_primed(&f, k, &at(1.2), 3, &p, Some(&b1.x), Some(full(&b1))).unwrap();
    let along = solve_primed(
        &f,
        k,
        &at(1.2),
        3,
        &p,
        Some(&b1.x),
        Some(Primed {
            before: Some(Before {
                x: &a.x,
                fx: &a.fx,
                kfx: Some(&a.kfx),
            }),
            ..full(&b1)
        }),
    )
    .unwrap();
    eprintln!(
        "brighter light: {} products from the last answer, {} extrapolated",
        plain.stats.products, along.stats.products
    );
    assert!(along.stats.converged);
    assert!(along.stats.products < plain.stats.products);

    // A long steady drag: products derived from derived products age, and after
    // MAX_PRIMED_AGE solves without a pass over F the next one checks afresh.
    let (mut prev, mut last) = (b1, along);
    let (mut zero_run, mut fresh) = (0, 0);
    for step in 3..16 {
        let rhs = at(1.0 + 0.1 * step as f32);
        let next = solve_primed(
            &f,
            k,
            &rhs,
            3,
            &p,
            Some(&last.x),
            Some(Primed {
                before: Some(Before {
                    x: &prev.x,
                    fx: &prev.fx,
                    kfx: Some(&prev.kfx),
                }),
                age: last.age.max(prev.age),
                ..full(&last)
            }),
        )
        .unwrap();
        assert!(next.stats.converged, "step {step}: {:?}", next.stats);
        let exact = solve_primed(&f, k, &rhs, 3, &tight, None, None).unwrap();
        let err = rel_diff(
            bytemuck::cast_slice(&next.x),
            bytemuck::cast_slice(&exact.x),
        );
        assert!(err < 0.01, "step {step}: {err}");
        zero_run = if next.stats.products == 0 {
            zero_run + 1
        } else {
            0
        };
        fresh += (next.age == 0) as u32;
        assert!(zero_run <= MAX_PRIMED_AGE, "step {step}");
        (prev, last) = (last, next);
    }
    assert!(fresh >= 2, "{fresh} fresh checks in 13 steps");
}

#[test]
fn batched_systems_equal_separate_solves() {
    let (_dir, b, e) = translucent_cornell(800);
    let f = Transport::of(&b);
    let s = SparseScatter(b.subsurface());
    let n = e.len();
    // Three right-hand sides: E, 2E + tint, and zero (answer 0).
    let mut rhs = vec![[0.0f32; 3]; n];
    radiosity::Scatter::apply(&s, &e, &mut rhs);
    let rhs2: Vec<Rgb> = rhs.iter().map(|x| [2.0 * x[0], x[1], 0.5 * x[2]]).collect();
    let mut stacked = Vec::with_capacity(n * 9);
    for i in 0..n {
        stacked.extend_from_slice(&rhs[i]);
        stacked.extend_from_slice(&rhs2[i]);
        stacked.extend_from_slice(&[0.0; 3]);
    }
    for method in [Method::Jacobi, Method::BiCgStab] {
        let p = params(method, 1e-4);
        let (x, st) = translux_engine::solver::solve_system(&f, &s, &stacked, 9, &p, None).unwrap();
        assert!(st.converged, "{st:?}");
        for (k, r) in [&rhs, &rhs2].into_iter().enumerate() {
            let (single, _) =
                translux_engine::solver::solve_system(&f, &s, bytemuck::cast_slice(r), 3, &p, None)
                    .unwrap();
            let single: &[Rgb] = bytemuck::cast_slice(&single);
            let mine: Vec<Rgb> = (0..n)
                .map(|i| std::array::from_fn(|c| x[i * 9 + 3 * k + c]))
                .collect();
            assert!(rel_diff(&mine, single) < 5e-4, "{method:?} system {k}");
        }
        assert!((0..n).all(|i| x[i * 9 + 6..i * 9 + 9] == [0.0; 3]));
    }
}

/// A closed room with a box floating in it (outward faces): the box shadows the room, so
/// shafts between wall clusters are blocked in places and clear in others.
fn room_with_a_box() -> Vec<Vec<[Vec3; 3]>> {
    let mut objects = room(2.0, 1.5, 1.8);
    let (lo, size) = (Vec3::new(0.7, 0.4, 0.6), Vec3::new(0.5, 0.4, 0.5));
    let boxed: Vec<[Vec3; 3]> = room(size.x, size.y, size.z)
        .into_iter()
        .flatten()
        .map(|t| [t[0] + lo, t[2] + lo, t[1] + lo])
        .collect();
    objects.push(boxed);
    objects
}

/// The two-sided cut (nodes receive too) against dense F: each patch's row sum (its own row
/// plus the node rows that hold it), the operator on a smooth field, and the solve under a
/// lamp, in and out of the lamp's shadow.
#[test]
fn two_sided_f_agrees_with_dense_f_in_a_room_with_a_box() {
    use translux_precompute::hierarchy::{self, HierarchyParams};
    let objects = room_with_a_box();
    let srcs: Vec<&[[Vec3; 3]]> = objects.iter().map(|o| o.as_slice()).collect();
    let (h, _) = patch::plan(&srcs, Density::Target(2500));
    let p = patch::subdivide(&srcs, h);
    let all: Vec<[Vec3; 3]> = objects.iter().flatten().copied().collect();
    let occ = Occluder::new(&all);
    let ff = FormFactorParams::default();
    let (dense, _) = formfactor::compute(&p, &occ, &ff, &|_| {});
    let params = HierarchyParams {
        two_sided: true,
        ..Default::default()
    };
    let tree = hierarchy::ClusterTree::build(&p);
    let two = hierarchy::compute(&p, &occ, &ff, &params, tree, &|_| {}, &|| false);
    let n = p.len();
    assert_eq!(two.c.n_rows, n + two.tree.node_count(), "a row per node");
    assert!(two.info.receiver_nodes, "{:?}", two.info);
    let node_entries = two.c.row_ptr[two.c.n_rows] - two.c.row_ptr[n];
    assert!(node_entries > 0, "nodes receive");
    let ranges = two.tree.ranges();
    let tree = translux_proto::bundle::TreeView {
        perm: &two.tree.perm,
        range: &ranges,
    };
    let t = Transport::hierarchical(two.c.view().unwrap(), tree, &p.area);
    let d = Transport::dense(dense.view().unwrap());
    // Row sums: within 2% of dense's everywhere, and a patch never sees more than its
    // hemisphere by more than 2%.
    let (st, sd) = (t.row_sums(), d.row_sums());
    let worst = st
        .iter()
        .zip(&sd)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f64, f64::max);
    let largest = st.iter().cloned().fold(0.0f64, f64::max);
    eprintln!(
        "two-sided: {} entries ({} in node rows) against dense {}; row sums largest {largest:.4}, \
         worst difference {worst:.4}",
        two.c.nnz(),
        node_entries,
        dense.nnz()
    );
    assert!(largest <= 1.02, "{largest}");
    assert!(worst <= 0.02, "{worst}");
    // The operator on a smooth field.
    let x: Vec<Rgb> = p
        .centroid
        .iter()
        .map(|c| {
            let v = 1.0 + 0.5 * (3.0 * c.x).sin() * (2.0 * c.y).cos() + 0.3 * c.z;
            [v, 1.0, 2.0 - c.y]
        })
        .collect();
    let (mut yt, mut yd) = (vec![[0.0f32; 3]; n], vec![[0.0f32; 3]; n]);
    t.apply_rgb(&x, &mut yt);
    d.apply_rgb(&x, &mut yd);
    let e = rel_diff(&yt, &yd);
    eprintln!("two-sided operator error on a smooth field: {e:.2e}");
    assert!(e < 0.015, "{e}");
    // The solve under a lamp over the box: the floor in the box's shadow gets only
    // inter-reflected light, part of which the box hides from it. The bounds on
    // the patches the lamp lights and on those it does not.
    let lamp = Vec3::new(0.95, 1.35, 0.85);
    let e: Vec<Rgb> = (0..n)
        .map(|i| {
            let (c, nrm) = (p.centroid[i], p.normal[i]);
            let to = lamp - c;
            let cos = nrm.dot(to.normalize());
            let seen = cos > 0.0 && !occ.occluded(c + nrm * 1e-4, lamp);
            [if seen { cos / to.length_squared() } else { 0.0 }; 3]
        })
        .collect();
    let mut errors = LampErrors::default();
    errors.add(&bounce(&t, &e), &bounce(&d, &e), &e);
    errors.check("a room with a box, two-sided", 100);
}

/// B = ρ (E + F B) with ρ = 0.6 on every patch, solved to 10⁻⁶.
fn bounce(f: &Transport, e: &[Rgb]) -> Vec<Rgb> {
    let albedo = vec![[0.6f32; 3]; e.len()];
    let none = vec![[0.0f32; 3]; e.len()];
    let (b, stats) = radiosity::solve(
        f,
        &Albedo(&albedo),
        &none,
        e,
        &params(Method::Jacobi, 1e-6),
        None,
    )
    .unwrap();
    assert!(stats.converged, "{stats:?}");
    b
}

/// Relative errors |got − want| / want of solves under lamps, apart over the patches each
/// lamp lights (E > 0) and those it does not.
#[derive(Default)]
struct LampErrors {
    lit: Vec<f64>,
    shadowed: Vec<f64>,
}

impl LampErrors {
    /// Over the patches whose reference is above 1% of the lit patches' median (a patch
    /// that nothing reaches, pressed against another, has no relative error).
    fn add(&mut self, got: &[Rgb], want: &[Rgb], e: &[Rgb]) {
        let mut lit: Vec<f32> = want
            .iter()
            .zip(e)
            .filter(|(_, e)| e[0] > 0.0)
            .map(|(w, _)| w[0])
            .collect();
        lit.sort_by(f32::total_cmp);
        let floor = 0.01 * lit[lit.len() / 2];
        for ((g, w), e) in got.iter().zip(want).zip(e) {
            if w[0] <= floor {
                continue;
            }
            let err = ((g[0] - w[0]) / w[0]).abs() as f64;
            if e[0] > 0.0 {
                self.lit.push(err);
            } else {
                self.shadowed.push(err);
            }
        }
    }

    /// Prints the median and 90th percentile of each side and holds them to the issue's
    /// bounds against dense F: lit 1% / 3%, shadowed 1.5% / 5%.
    fn check(&mut self, what: &str, least_shadowed: usize) {
        let quantiles = |v: &mut Vec<f64>| {
            v.sort_by(f64::total_cmp);
            let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
            (at(0.5), at(0.9))
        };
        let (lit, shadowed) = (quantiles(&mut self.lit), quantiles(&mut self.shadowed));
        eprintln!(
            "{what} under lamps against dense: lit median {:.2}% p90 {:.2}% ({} patches), \
             shadowed median {:.2}% p90 {:.2}% ({} patches)",
            100.0 * lit.0,
            100.0 * lit.1,
            self.lit.len(),
            100.0 * shadowed.0,
            100.0 * shadowed.1,
            self.shadowed.len()
        );
        assert!(
            self.shadowed.len() >= least_shadowed,
            "{} shadowed patches",
            self.shadowed.len()
        );
        assert!(lit.0 <= 0.01 && lit.1 <= 0.03, "{what}, lit: {lit:?}");
        assert!(
            shadowed.0 <= 0.015 && shadowed.1 <= 0.05,
            "{what}, shadowed: {shadowed:?}"
        );
    }
}

/// The furnished room of `examples/scenes/furnished-room` (one OBJ per wall and per piece
/// of furniture, as users model rooms) loads as modelled — no object turned over — and its
/// two-sided F matches dense F at 6,000 patches: row sums for 99% of the patches, and solves
/// under lamps among the furniture (the bounds on lit and shadowed patches). At
/// 2,500 patches the cut stores little but patch pairs, and light let into a shadow by a
/// node's shared visible fraction did not show.
#[test]
fn the_furnished_room_loads_as_modelled_and_its_two_sided_f_matches_dense_row_sums() {
    use translux_precompute::hierarchy::HierarchyParams;
    use translux_precompute::pipeline::FormFactorMethod;
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../examples/scenes/furnished-room/furnished-room.json");
    let loaded = translux_precompute::scene::load_scene_file(&path).unwrap();
    assert!(
        loaded.objects.len() >= 100,
        "{} objects",
        loaded.objects.len()
    );
    let turned: Vec<&str> = loaded
        .objects
        .iter()
        .filter(|o| o.reoriented)
        .map(|o| o.name.as_str())
        .collect();
    assert!(turned.is_empty(), "turned over: {turned:?}");
    let dir = tempfile::tempdir().unwrap();
    let mut bundles = Vec::new();
    for (name, transport) in [
        ("dense", FormFactorMethod::Dense),
        (
            "two-sided",
            FormFactorMethod::Hierarchical(HierarchyParams {
                two_sided: true,
                ..Default::default()
            }),
        ),
    ] {
        let out = dir.path().join(name);
        let params = PrecomputeParams {
            patches: Some(6000),
            transport,
            environment: translux_engine::envvis::EnvVisParams {
                bins: None,
                ..Default::default()
            },
            ..Default::default()
        };
        precompute(&loaded, &out, &params).unwrap();
        bundles.push(Bundle::open(&out).unwrap());
    }
    let (dense, two) = (Transport::of(&bundles[0]), Transport::of(&bundles[1]));
    let sums = [dense.row_sums(), two.row_sums()];
    let mut diffs: Vec<f64> = sums[0]
        .iter()
        .zip(&sums[1])
        .map(|(d, t)| (d - t).abs())
        .collect();
    diffs.sort_by(f64::total_cmp);
    let p99 = diffs[diffs.len() * 99 / 100];
    eprintln!(
        "furnished room: row-sum difference, two-sided against dense: p99 {p99:.4}, largest {:.4}",
        diffs[diffs.len() - 1]
    );
    // Under four lamps among the furniture: the light between books, chairs and tables, in
    // and out of their shadows.
    let lighting = radiosity::BundleLighting::new(&bundles[0]);
    let mut errors = LampErrors::default();
    for at in [
        [2.2, 2.6, 2.0],
        [6.0, 2.4, 4.5],
        [1.0, 1.5, 4.0],
        [4.0, 0.9, 3.0],
    ] {
        let lamp: translux_proto::light::Light = serde_json::from_value(
            serde_json::json!({"type": "point", "position": at, "intensity": [5, 5, 5]}),
        )
        .unwrap();
        let e = lighting.irradiance(&[lamp]).unwrap();
        errors.add(&bounce(&two, &e), &bounce(&dense, &e), &e);
    }
    errors.check("the furnished room, two-sided", 1000);
    // Dense F's own near samples between books and chair legs overshoot (its row sums reach
    // 1.17 here), so the cuts differ from it most there. Dense F also samples its far pairs
    // of a large form factor, which brought its rows nearer a cosine-weighted ray count
    // (a floor patch under a table: the ceiling 0.234 → 0.208, counted 0.199), and the
    // cut's links to whole nodes did not follow: at 6,000 patches the two-sided cut differs
    // by 0.044 at the 99th percentile (0.035 against the dense F of one ray per far pair;
    // 0.053 when a node shared a visible fraction across a shadow).
    assert!(p99 <= 0.05, "{p99}");
}
